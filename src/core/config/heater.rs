//! The heater settings of a channel (issue 22): the loop's mode and gains, the temperature
//! limits and the checks' parameters, their ranges and validation. Off by default.

use super::{Nanos, OutOfRange, MAX_PERIOD_MS, MAX_TIMEOUT_MS, NS_PER_MS};

/// The gains of the loop.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Gains {
    /// Proportional gain, % per °C.
    pub kp: f64,
    /// Integral gain, % per °C·s.
    pub ki: f64,
    /// Derivative gain, % per °C/s.
    pub kd: f64,
    /// Time constant of the derivative's first-order filter, s; 0 = unfiltered.
    pub d_filter_s: f64,
}

/// The parameters of `not_heating`, as Klipper's `verify_heater` names them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Runaway {
    /// `hysteresis`, °C: within this of the target the check rests.
    pub hysteresis_c: f64,
    /// `max_error`, °C·s summed over the 1 s ticks below the band.
    pub max_error: f64,
    /// `check_gain_time`, ns: an approach must gain `heating_gain_c` within it.
    pub gain_time: Nanos,
    /// `heating_gain`, °C.
    pub heating_gain_c: f64,
}

/// Who sets the duty of a channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Control {
    /// The duty commands (`~/<ch>/duty`, `~/<ch>/sv`, split range): today's behaviour.
    #[default]
    Open,
    /// The PID, from the feedback and `~/<ch>/setpoint`.
    Pid,
}

impl Control {
    /// The parameter spelling: `open` or `pid`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Control::Open => "open",
            Control::Pid => "pid",
        }
    }
}

super::named_enum!(Control, "open|pid", [Control::Open, Control::Pid]);

/// Lowest temperature a limit may be set to, °C (absolute zero).
pub const MIN_TEMP_C: f64 = -273.15;
/// Highest temperature a limit may be set to, °C.
pub const MAX_TEMP_C: f64 = 3000.0;
/// Largest gain accepted for `pid_kp`, `pid_ki` and `pid_kd`.
pub const MAX_GAIN: f64 = 100_000.0;
/// Longest time accepted for the seconds parameters (derivative filter, `runaway_gain_time_s`,
/// `stuck_on_time_s`), s: a day.
pub const MAX_TIME_S: f64 = 86_400.0;
/// Largest temperature difference accepted (hysteresis, heating gain, stuck-on rise), °C.
pub const MAX_DELTA_C: f64 = 1000.0;
/// Largest `runaway_max_error` accepted, °C·s.
pub const MAX_RUNAWAY_ERROR: f64 = 1.0e7;
/// Shortest PID sample accepted, ms (0 means the channel's period).
pub const MIN_SAMPLE_MS: u64 = 10;

/// The heater settings of one channel as a user states them (issue 22). The defaults are
/// Klipper's for `runaway_*` and "off" for the rest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterParams {
    /// A feedback topic is configured (`feedback_topic` not empty): readings arrive.
    pub feedback: bool,
    /// Who sets the duty.
    pub control: Control,
    /// PID sample, ms; 0 = the channel's period. 0, or 10..=3 600 000.
    pub pid_sample_ms: u64,
    /// % per °C.
    pub pid_kp: f64,
    /// % per °C·s.
    pub pid_ki: f64,
    /// % per °C/s.
    pub pid_kd: f64,
    /// The derivative's filter time constant, s; 0 = unfiltered.
    pub pid_d_filter_s: f64,
    /// Readings below this are `temperature_out_of_range`, °C.
    pub temp_min_c: f64,
    /// Readings above this are `temperature_out_of_range`, °C.
    pub temp_max_c: f64,
    /// `sensor_timeout`: no reading for this long while enabled, ms; 0 = off.
    pub feedback_timeout_ms: u64,
    /// `not_heating`'s hysteresis, °C (Klipper 5).
    pub runaway_hysteresis_c: f64,
    /// `not_heating`'s max_error, °C·s (Klipper 120).
    pub runaway_max_error: f64,
    /// `not_heating`'s check_gain_time, s (Klipper 20).
    pub runaway_gain_time_s: f64,
    /// `not_heating`'s heating_gain, °C (Klipper 2).
    pub runaway_heating_gain_c: f64,
    /// `stuck_on`: a rise of more than this while the line was off, °C; 0 = off.
    pub stuck_on_rise_c: f64,
    /// `stuck_on`'s window, s.
    pub stuck_on_time_s: f64,
    /// An autotune aborts on a reading above its target plus this, °C (20).
    pub autotune_max_overshoot_c: f64,
    /// An autotune aborts when no relay cycle completes within this, s (1200).
    pub autotune_timeout_s: f64,
}

impl Default for HeaterParams {
    fn default() -> Self {
        HeaterParams {
            feedback: false,
            control: Control::Open,
            pid_sample_ms: 0,
            pid_kp: 0.0,
            pid_ki: 0.0,
            pid_kd: 0.0,
            pid_d_filter_s: 0.0,
            temp_min_c: MIN_TEMP_C,
            temp_max_c: MAX_TEMP_C,
            feedback_timeout_ms: 0,
            runaway_hysteresis_c: 5.0,
            runaway_max_error: 120.0,
            runaway_gain_time_s: 20.0,
            runaway_heating_gain_c: 2.0,
            stuck_on_rise_c: 0.0,
            stuck_on_time_s: 30.0,
            autotune_max_overshoot_c: 20.0,
            autotune_timeout_s: 1200.0,
        }
    }
}

/// Why heater settings are refused. The old settings stay in force.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum HeaterConfigError {
    /// A value outside its range, or not a number.
    #[error(transparent)]
    OutOfRange(#[from] OutOfRange),
    /// `temp_min_c` not below `temp_max_c`.
    #[error("temp_min_c {min_c} is not below temp_max_c {max_c}")]
    TempLimits {
        /// `temp_min_c`.
        min_c: f64,
        /// `temp_max_c`.
        max_c: f64,
    },
    /// A PID sample below the minimum (0 means the period).
    #[error("pid_sample_ms {value_ms} is outside 10..3600000 (0 = the channel's period)")]
    Sample {
        /// The refused value, ms.
        value_ms: u64,
    },
    /// `control` `pid` without feedback.
    #[error("control pid needs a feedback_topic (set at start-up)")]
    PidWithoutFeedback,
}

/// The channel's limits on an autotune run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutotuneLimits {
    /// A reading above `target + max_overshoot_c` aborts, °C.
    pub max_overshoot_c: f64,
    /// No complete cycle within this aborts, ns.
    pub timeout: Nanos,
}

/// The validated heater settings the channel runs on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeaterConfig {
    /// The PID sample, ns; 0 = the channel's period.
    pub sample: Nanos,
    /// The gains.
    pub gains: Gains,
    /// `sensor_timeout`, ns; 0 = off.
    pub feedback_timeout: Nanos,
    /// `not_heating`.
    pub runaway: Runaway,
    /// `stuck_on`'s window, ns.
    pub stuck_window: Nanos,
    /// The autotune's limits.
    pub autotune: AutotuneLimits,
    /// The parameters this was made from.
    pub params: HeaterParams,
}

fn seconds(s: f64) -> Nanos {
    (s * 1e9).round() as Nanos
}

impl HeaterParams {
    /// Checks every value against its range (NaN never passes) and makes the nanosecond
    /// configuration.
    pub fn validate(&self) -> Result<HeaterConfig, HeaterConfigError> {
        if self.pid_sample_ms != 0 && !(MIN_SAMPLE_MS..=MAX_PERIOD_MS).contains(&self.pid_sample_ms)
        {
            return Err(HeaterConfigError::Sample {
                value_ms: self.pid_sample_ms,
            });
        }
        OutOfRange::check("pid_kp", self.pid_kp, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_ki", self.pid_ki, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_kd", self.pid_kd, 0.0, MAX_GAIN)?;
        OutOfRange::check("pid_d_filter_s", self.pid_d_filter_s, 0.0, MAX_TIME_S)?;
        OutOfRange::check("temp_min_c", self.temp_min_c, MIN_TEMP_C, MAX_TEMP_C)?;
        OutOfRange::check("temp_max_c", self.temp_max_c, MIN_TEMP_C, MAX_TEMP_C)?;
        if self.temp_min_c >= self.temp_max_c {
            return Err(HeaterConfigError::TempLimits {
                min_c: self.temp_min_c,
                max_c: self.temp_max_c,
            });
        }
        OutOfRange::check(
            "feedback_timeout_ms",
            self.feedback_timeout_ms as f64,
            0.0,
            MAX_TIMEOUT_MS as f64,
        )?;
        OutOfRange::check(
            "runaway_hysteresis_c",
            self.runaway_hysteresis_c,
            0.0,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "runaway_max_error",
            self.runaway_max_error,
            0.0,
            MAX_RUNAWAY_ERROR,
        )?;
        OutOfRange::check(
            "runaway_gain_time_s",
            self.runaway_gain_time_s,
            1.0,
            MAX_TIME_S,
        )?;
        // Klipper: heating_gain "above=0".
        OutOfRange::check(
            "runaway_heating_gain_c",
            self.runaway_heating_gain_c,
            0.001,
            MAX_DELTA_C,
        )?;
        OutOfRange::check("stuck_on_rise_c", self.stuck_on_rise_c, 0.0, MAX_DELTA_C)?;
        OutOfRange::check("stuck_on_time_s", self.stuck_on_time_s, 1.0, MAX_TIME_S)?;
        OutOfRange::check(
            "autotune_max_overshoot_c",
            self.autotune_max_overshoot_c,
            0.1,
            MAX_DELTA_C,
        )?;
        OutOfRange::check(
            "autotune_timeout_s",
            self.autotune_timeout_s,
            1.0,
            MAX_TIME_S,
        )?;
        if self.control == Control::Pid && !self.feedback {
            return Err(HeaterConfigError::PidWithoutFeedback);
        }
        Ok(HeaterConfig {
            sample: self.pid_sample_ms * NS_PER_MS,
            gains: Gains {
                kp: self.pid_kp,
                ki: self.pid_ki,
                kd: self.pid_kd,
                d_filter_s: self.pid_d_filter_s,
            },
            feedback_timeout: self.feedback_timeout_ms * NS_PER_MS,
            runaway: Runaway {
                hysteresis_c: self.runaway_hysteresis_c,
                max_error: self.runaway_max_error,
                gain_time: seconds(self.runaway_gain_time_s),
                heating_gain_c: self.runaway_heating_gain_c,
            },
            stuck_window: seconds(self.stuck_on_time_s),
            autotune: AutotuneLimits {
                max_overshoot_c: self.autotune_max_overshoot_c,
                timeout: seconds(self.autotune_timeout_s),
            },
            params: *self,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_klippers_and_off() {
        let c = HeaterParams::default().validate().unwrap();
        assert_eq!(c.params.control, Control::Open);
        assert_eq!(c.runaway.hysteresis_c, 5.0);
        assert_eq!(c.runaway.max_error, 120.0);
        assert_eq!(c.runaway.gain_time, 20 * 1_000_000_000);
        assert_eq!(c.runaway.heating_gain_c, 2.0);
        assert_eq!((c.feedback_timeout, c.params.stuck_on_rise_c), (0, 0.0));
    }

    #[test]
    fn bad_values_are_refused_with_a_reason() {
        let bad = |set: fn(&mut HeaterParams)| {
            let mut p = HeaterParams {
                feedback: true,
                ..HeaterParams::default()
            };
            set(&mut p);
            p.validate().unwrap_err().to_string()
        };
        assert_eq!(
            bad(|p| p.pid_kp = f64::NAN),
            "pid_kp NaN is outside 0..100000"
        );
        assert_eq!(bad(|p| p.pid_ki = -1.0), "pid_ki -1 is outside 0..100000");
        assert_eq!(
            bad(|p| {
                p.temp_min_c = 300.0;
                p.temp_max_c = 200.0;
            }),
            "temp_min_c 300 is not below temp_max_c 200"
        );
        assert_eq!(
            bad(|p| p.pid_sample_ms = 5),
            "pid_sample_ms 5 is outside 10..3600000 (0 = the channel's period)"
        );
        assert!(bad(|p| p.runaway_heating_gain_c = 0.0).starts_with("runaway_heating_gain_c 0"));
        assert!(bad(|p| p.stuck_on_time_s = f64::INFINITY).starts_with("stuck_on_time_s inf"));
        let no_feedback = HeaterParams {
            control: Control::Pid,
            ..HeaterParams::default()
        };
        assert_eq!(
            no_feedback.validate(),
            Err(HeaterConfigError::PidWithoutFeedback)
        );
    }
}
