//! Actuator commands in the three forms the seeds use, and their conversion to a duty fraction.
//!
//! Finite out-of-range values are clamped and flagged (001, 002: "internally limited to
//! 0..100 %"); NaN and infinities are refused so the last valid command stays in force (001:
//! "the loop output is frozen").

/// Full scale of the raw manipulated variable SV: 4095 is 100 % (000).
pub const SV_FULL_SCALE: u16 = 4095;

/// A duty command as it arrives.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Command {
    /// Percent, 0..=100 (001, 002).
    Percent(f64),
    /// Raw SV, 0..=4095 where 4095 is 100 % (000).
    Sv(u16),
    /// Fraction, 0..=1 (004's i_rIput).
    Fraction(f64),
}

/// Why a command was refused; the last valid command stays in force.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum CommandError {
    /// The value was NaN.
    #[error("duty command is NaN; last valid command kept")]
    NotANumber,
    /// The value was +inf or -inf.
    #[error("duty command is infinite; last valid command kept")]
    Infinite,
}

/// A command converted to a duty fraction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Duty {
    /// The fraction in force, 0..=1.
    pub fraction: f64,
    /// The command as requested, with its unit (percent, SV or fraction).
    pub requested: Command,
    /// True when `requested` was outside its range and was clamped.
    pub clamped: bool,
}

impl Command {
    /// The value in the command's own unit.
    pub fn raw(&self) -> f64 {
        match *self {
            Command::Percent(v) | Command::Fraction(v) => v,
            Command::Sv(v) => f64::from(v),
        }
    }

    /// The name of the command's unit: `%`, `SV` or `fraction`.
    pub fn unit(&self) -> &'static str {
        match self {
            Command::Percent(_) => "%",
            Command::Sv(_) => "SV",
            Command::Fraction(_) => "fraction",
        }
    }

    /// The top of the command's range in its own unit (100 %, SV 4095, fraction 1).
    pub fn full_scale(&self) -> f64 {
        match self {
            Command::Percent(_) => 100.0,
            Command::Sv(_) => f64::from(SV_FULL_SCALE),
            Command::Fraction(_) => 1.0,
        }
    }

    /// Converts to a duty fraction, clamping finite values and refusing NaN and infinities.
    pub fn to_duty(&self) -> Result<Duty, CommandError> {
        let requested = self.raw();
        if requested.is_nan() {
            return Err(CommandError::NotANumber);
        }
        if requested.is_infinite() {
            return Err(CommandError::Infinite);
        }
        let full_scale = self.full_scale();
        let clamped_value = requested.clamp(0.0, full_scale);
        Ok(Duty {
            fraction: clamped_value / full_scale,
            requested: *self,
            clamped: clamped_value != requested,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn three_forms_agree_on_full_scale() {
        // 000: SV 0..4095 is 0..100 % of the period.
        assert_eq!(Command::Sv(4095).to_duty().unwrap().fraction, 1.0);
        assert_eq!(Command::Sv(0).to_duty().unwrap().fraction, 0.0);
        assert_eq!(Command::Percent(100.0).to_duty().unwrap().fraction, 1.0);
        assert_eq!(Command::Fraction(0.25).to_duty().unwrap().fraction, 0.25);
        assert_eq!(Command::Percent(37.0).to_duty().unwrap().fraction, 0.37);
    }

    #[test]
    fn out_of_range_is_clamped_and_flagged_002() {
        let d = Command::Percent(-5.0).to_duty().unwrap();
        assert_eq!(
            (d.fraction, d.clamped, d.requested),
            (0.0, true, Command::Percent(-5.0))
        );
        let d = Command::Percent(150.0).to_duty().unwrap();
        assert_eq!((d.fraction, d.clamped), (1.0, true));
        let d = Command::Sv(5000).to_duty().unwrap();
        assert_eq!((d.fraction, d.clamped), (1.0, true));
        let d = Command::Fraction(1.0).to_duty().unwrap();
        assert!(!d.clamped);
    }

    #[test]
    fn nan_and_infinities_are_refused_001() {
        assert_eq!(
            Command::Percent(f64::NAN).to_duty(),
            Err(CommandError::NotANumber)
        );
        assert_eq!(
            Command::Percent(f64::INFINITY).to_duty(),
            Err(CommandError::Infinite)
        );
        assert_eq!(
            Command::Fraction(f64::NEG_INFINITY).to_duty(),
            Err(CommandError::Infinite)
        );
    }
}
