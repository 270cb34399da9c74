//! Channel parameters: the user-facing settings of SPEC §1 (milliseconds, optional overrides,
//! profiles), their validation against 000's limits table, and the validated, nanosecond
//! [`ChannelConfig`] the state machine runs on.
//!
//! Nothing here reads a clock or touches I/O: validation is a pure function so the ROS side can
//! answer a parameter request synchronously with exactly the verdict the core would give.

use super::Nanos;
use std::fmt;

pub mod heater;
mod policy;
mod sizing;

use heater::{HeaterConfig, HeaterConfigError, HeaterParams};

pub(crate) use policy::named_enum;
pub use policy::{ApplyAt, OnDisable, OutputKind, Profile, ShortPulse, ShortStr, UnknownName};
pub use sizing::Sizing;

/// Nanoseconds in one millisecond.
pub const NS_PER_MS: Nanos = 1_000_000;

/// A value outside its range, or not a number: the refusal of a heater or valve setting.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("{name} {value} is outside {min}..{max}")]
pub struct OutOfRange {
    /// The parameter.
    pub name: &'static str,
    /// The refused value.
    pub value: f64,
    /// Lowest accepted.
    pub min: f64,
    /// Highest accepted.
    pub max: f64,
}

impl OutOfRange {
    /// `Ok` when `value` lies within `min..=max` (NaN never does); the refusal otherwise.
    pub fn check(name: &'static str, value: f64, min: f64, max: f64) -> Result<(), OutOfRange> {
        if (min..=max).contains(&value) {
            Ok(())
        } else {
            Err(OutOfRange {
                name,
                value,
                min,
                max,
            })
        }
    }
}

/// Longest period accepted, in ms (one hour).
pub const MAX_PERIOD_MS: u64 = 3_600_000;

/// Longest watchdog timeout accepted, in ms (one day).
pub const MAX_TIMEOUT_MS: u64 = 86_400_000;

/// Longest maximum on time accepted, in ms (one day).
pub const MAX_ON_MS: u64 = 86_400_000;

/// Longest window of the rolling-average duty cap, s (a day).
pub const MAX_AVG_WINDOW_S: u64 = 86_400;

/// Fastest duty slew limit accepted, percent per second (100 % in 1 ms).
pub const MAX_SLEW_PCT_PER_S: f64 = 100_000.0;

/// Largest cycle extension accepted, a factor of the period (`extend_max`).
pub const MAX_EXTEND_FACTOR: f64 = 100.0;

/// Shortest time base accepted when it is not 0, ms: the transistor floor (000: 0.1 ms).
pub const MIN_TIME_BASE_MS: f64 = 0.1;

/// The settings of one channel as a user states them (SPEC §1 table): milliseconds, a profile,
/// and optional policy overrides. `None` means "as the profile says".
///
/// Convert with [`ChannelParams::validate`] into the [`ChannelConfig`] the core runs on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelParams {
    /// Period `T` in ms; 0 means no pulses, output held at 0 (000). 0, or 5 (transistor) /
    /// 100 (relay) ..= 3 600 000.
    pub period_ms: u64,
    /// Minimum on time in ms (ME / T_MINI / nMinSwiTi / P_B_TM); 0 means the hardware floor.
    pub min_on_ms: u64,
    /// Minimum off time in ms; `None` means as the profile says (000: equal to `min_on_ms`).
    pub min_off_ms: Option<u64>,
    /// Transistor or relay limits (000's table).
    pub output_kind: OutputKind,
    /// Profile setting the policies below when they are `None`.
    pub profile: Profile,
    /// Short-pulse policy override.
    pub short_pulse: Option<ShortPulse>,
    /// Frequency_Output edge `i_rEdge` (004), 0..=1, used by [`ShortPulse::Band`].
    pub edge_band: f64,
    /// The longest period [`ShortPulse::Extend`] may grow to, a factor of `period_ms`,
    /// 1..=100; 1 allows no extension (the policy then acts as `suppress`).
    pub extend_max: f64,
    /// Apply-at policy override.
    pub apply_at: Option<ApplyAt>,
    /// Disable policy override.
    pub on_disable: Option<OnDisable>,
    /// Watchdog in ms: no command for this long puts the channel in its safe state (off);
    /// 0 disables. 0..=86 400 000.
    pub command_timeout_ms: u64,
    /// Fault value: the duty, percent 0..=100, the channel runs at when the watchdog trips,
    /// through the same minimum-time rules (fault mode of PLC output modules; frost
    /// protection for a heater, a safe position for a valve). 0: off at once, as before.
    pub fault_duty_pct: f64,
    /// How long the fault value runs before the output goes off, ms; 0 = until the next
    /// command. 0..=86 400 000.
    pub fault_hold_ms: u64,
    /// Maximum continuous on time of the line, ms; 0 = off. The line never stays high longer:
    /// it is switched off for at least its minimum off time, then follows the schedule again,
    /// with E1 and the limit flag (a guard against a controller stuck at 100 %). 0, or the
    /// effective minimum on time ..= 86 400 000.
    pub max_on_ms: u64,
    /// Highest duty applied, percent 0..=100: a command above it is limited to it, after
    /// clamping and before the minimum-time rules (a heater's maximum power). 100 = off.
    pub max_duty_pct: f64,
    /// Lowest duty applied, percent 0..=`max_duty_pct`: a command below it is raised to it,
    /// 0 included unless `zero_means_zero`. 0 = off.
    pub min_duty_pct: f64,
    /// A command of 0 % stays 0 % whatever `min_duty_pct`.
    pub zero_means_zero: bool,
    /// Slew limit, percent per second: the duty applied moves toward the command in force at
    /// most this fast, both ways, from 0 at each enable (soft start). 0 = off.
    /// 0..=100 000.
    pub duty_slew_pct_per_s: f64,
    /// Dead band, percent 0..=100: a command whose duty (after the power limits) differs from
    /// the one in force by less is ignored (relay wear); 0 %, `min_duty_pct` and
    /// `max_duty_pct` always pass. 0 = off.
    pub duty_deadband_pct: f64,
    /// Rolling-average cap, percent 0..=100: over every window of `avg_window_s` the line is
    /// on for at most this share of the window (an energy budget). 100 = off.
    pub avg_duty_limit_pct: f64,
    /// The window of the rolling-average cap, s; 1..=86 400.
    pub avg_window_s: u64,
    /// Time base (tick), ms; 0 = off. Every pulse and break is then a whole number of ticks
    /// and every edge the schedule asks for lies on the channel's tick grid (003's CYCLE_P,
    /// 001's task period, the half cycle a zero-cross SSR switches on). Fractional values are
    /// accepted (8.3333 for 60 Hz half cycles); the tick is rounded to the nearest ns. 0, or
    /// 0.1 ..= `period_ms`.
    pub time_base_ms: f64,
    /// The heater loop and its checks; off by default.
    pub heater: HeaterParams,
}

impl Default for ChannelParams {
    fn default() -> Self {
        ChannelParams {
            period_ms: 1000,
            min_on_ms: 0,
            min_off_ms: None,
            output_kind: OutputKind::Transistor,
            profile: Profile::PicoGfx,
            short_pulse: None,
            edge_band: 0.0,
            extend_max: 10.0,
            apply_at: None,
            on_disable: None,
            command_timeout_ms: 0,
            fault_duty_pct: 0.0,
            fault_hold_ms: 0,
            max_on_ms: 0,
            max_duty_pct: 100.0,
            min_duty_pct: 0.0,
            zero_means_zero: false,
            duty_slew_pct_per_s: 0.0,
            duty_deadband_pct: 0.0,
            avg_duty_limit_pct: 100.0,
            avg_window_s: 60,
            time_base_ms: 0.0,
            heater: HeaterParams::default(),
        }
    }
}

/// Which minimum time an error speaks of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MinTime {
    /// `min_on_ms`.
    On,
    /// `min_off_ms`.
    Off,
}

impl fmt::Display for MinTime {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MinTime::On => "min_on_ms",
            MinTime::Off => "min_off_ms",
        })
    }
}

/// Which percentage parameter an error speaks of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PercentParam {
    /// `max_duty_pct`.
    MaxDuty,
    /// `min_duty_pct`.
    MinDuty,
    /// `duty_deadband_pct`.
    Deadband,
    /// `avg_duty_limit_pct`.
    AvgDutyLimit,
}

impl fmt::Display for PercentParam {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            PercentParam::MaxDuty => "max_duty_pct",
            PercentParam::MinDuty => "min_duty_pct",
            PercentParam::Deadband => "duty_deadband_pct",
            PercentParam::AvgDutyLimit => "avg_duty_limit_pct",
        })
    }
}

/// Why a set of channel parameters is refused. The old settings stay in force.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ConfigError {
    /// A time base that is not 0 or 0.1 ms ..= one hour, or not a number.
    #[error("time_base_ms {value} is outside 0 or {min}..{max} ms")]
    TimeBaseOutOfRange {
        /// The refused value, ms.
        value: f64,
        /// The shortest non-zero time base, ms.
        min: f64,
        /// The longest, ms.
        max: f64,
    },
    /// A time base longer than the period: a period holds at least one tick.
    #[error("time_base_ms {value} is above period_ms {period_ms}")]
    TimeBaseAbovePeriod {
        /// The refused value, ms.
        value: f64,
        /// The period, ms.
        period_ms: u64,
    },
    /// A non-zero period below the output kind's minimum (000: transistor 5 ms, relay 100 ms).
    #[error(
        "period_ms {period_ms} is below the {kind} minimum of {min_ms} ms (0 stops the pulses)"
    )]
    PeriodTooShort {
        /// The refused period, ms.
        period_ms: u64,
        /// The minimum for this kind, ms.
        min_ms: u64,
        /// The output kind.
        kind: OutputKind,
    },
    /// A period above one hour.
    #[error("period_ms {period_ms} is above the maximum of {max_ms} ms")]
    PeriodTooLong {
        /// The refused period, ms.
        period_ms: u64,
        /// The maximum, ms.
        max_ms: u64,
    },
    /// An explicit relay minimum time below 50 ms (000: relay minimum on duration 50 ms).
    #[error("{which} {value_ms} is below the relay minimum of {min_ms} ms (0 means the floor)")]
    RelayMinTimeTooShort {
        /// Which minimum.
        which: MinTime,
        /// Its value, ms.
        value_ms: u64,
        /// The relay minimum, ms.
        min_ms: u64,
    },
    /// A minimum time above the longest period accepted (one hour), whatever the period.
    #[error("{which} {value_ms} is above the maximum of {max_ms} ms")]
    MinTimeTooLong {
        /// Which minimum.
        which: MinTime,
        /// Its value, ms.
        value_ms: u64,
        /// The maximum, ms.
        max_ms: u64,
    },
    /// `edge_band` outside 0..=1 or not a number (004: i_rEdge range 0.0..1.0).
    #[error("edge_band {value} is outside 0..1")]
    EdgeBandOutOfRange {
        /// The refused value.
        value: f64,
    },
    /// A watchdog timeout above one day.
    #[error("command_timeout_ms {value_ms} is above the maximum of {max_ms} ms")]
    TimeoutTooLong {
        /// The refused value, ms.
        value_ms: u64,
        /// The maximum, ms.
        max_ms: u64,
    },
    /// A fault value outside 0..=100 % or not a number.
    #[error("fault_duty_pct {value} is outside 0..100")]
    FaultDutyOutOfRange {
        /// The refused value.
        value: f64,
    },
    /// A fault hold time above one day.
    #[error("fault_hold_ms {value_ms} is above the maximum of {max_ms} ms")]
    FaultHoldTooLong {
        /// The refused value, ms.
        value_ms: u64,
        /// The maximum, ms.
        max_ms: u64,
    },
    /// A maximum on time above one day.
    #[error("max_on_ms {value_ms} is above the maximum of {max_ms} ms")]
    MaxOnTooLong {
        /// The refused value, ms.
        value_ms: u64,
        /// The maximum, ms.
        max_ms: u64,
    },
    /// A maximum on time below the minimum on time in force: cutting the line there would
    /// emit a pulse below its minimum.
    #[error(
        "max_on_ms {max_on_ms} is below the minimum on time of {min_on_ms} ms (0 turns the \
         maximum off)"
    )]
    MaxOnBelowMinOn {
        /// The refused value, ms.
        max_on_ms: u64,
        /// The effective minimum on time, ms (the hardware floor included).
        min_on_ms: f64,
    },
    /// A duty limit or the dead band outside 0..=100 % or not a number.
    #[error("{which} {value} is outside 0..100")]
    PercentOutOfRange {
        /// Which parameter.
        which: PercentParam,
        /// The refused value, percent.
        value: f64,
    },
    /// `min_duty_pct` above `max_duty_pct`.
    #[error("min_duty_pct {min_pct} is above max_duty_pct {max_pct}")]
    MinDutyAboveMaxDuty {
        /// `min_duty_pct`.
        min_pct: f64,
        /// `max_duty_pct`.
        max_pct: f64,
    },
    /// `extend_max` outside 1..=100 or not a number.
    #[error("extend_max {value} is outside 1..{max}")]
    ExtendMaxOutOfRange {
        /// The refused value, a factor of the period.
        value: f64,
        /// The maximum.
        max: f64,
    },
    /// A slew limit outside 0..=100 000 %/s or not a number.
    #[error("duty_slew_pct_per_s {value} is outside 0..{max}")]
    SlewOutOfRange {
        /// The refused value, percent per second.
        value: f64,
        /// The maximum, percent per second.
        max: f64,
    },
    /// The window of the rolling-average cap outside 1..=86 400 s.
    #[error("avg_window_s {value_s} is outside 1..{max_s} s")]
    AvgWindowOutOfRange {
        /// The refused value, s.
        value_s: u64,
        /// The maximum, s.
        max_s: u64,
    },
    /// A heater setting was refused.
    #[error(transparent)]
    Heater(#[from] HeaterConfigError),
    /// A fault value with no end under `pid` or `mpc`.
    #[error(
        "fault_duty_pct {fault_duty_pct} under control pid or mpc needs fault_hold_ms above 0: \
         nothing but the loop commands the duty, so the fault value would heat open loop \
         for ever"
    )]
    FaultValueUnderPid {
        /// The fault value, %.
        fault_duty_pct: f64,
    },
}

/// Validated channel settings in nanoseconds, with every profile default resolved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChannelConfig {
    /// Period `T`, ns; 0 = no pulses, output held at 0.
    pub period: Nanos,
    /// Effective minimum on time, ns (never below the hardware floor).
    pub min_on: Nanos,
    /// Effective minimum off time, ns (never below the hardware floor).
    pub min_off: Nanos,
    /// Short-pulse policy in force.
    pub short_pulse: ShortPulse,
    /// Edge band (004), 0..=1.
    pub edge_band: f64,
    /// Apply-at policy in force.
    pub apply_at: ApplyAt,
    /// Disable policy in force.
    pub on_disable: OnDisable,
    /// Watchdog timeout, ns; 0 = disabled.
    pub command_timeout: Nanos,
    /// The fault value run after a watchdog trip, duty fraction 0..=1; 0 = off at once.
    pub fault_duty: f64,
    /// How long the fault value runs, ns; 0 = until the next command.
    pub fault_hold: Nanos,
    /// Maximum continuous on time of the line, ns; 0 = off. Never below `min_on`.
    pub max_on: Nanos,
    /// Highest duty applied, fraction 0..=1 (1 = off).
    pub max_duty: f64,
    /// Lowest duty applied, fraction 0..=`max_duty` (0 = off).
    pub min_duty: f64,
    /// A command of 0 stays 0 whatever `min_duty`.
    pub zero_means_zero: bool,
    /// Slew limit of the duty applied, fraction per second; 0 = off.
    pub slew_per_s: f64,
    /// Dead band of commands, fraction 0..=1; 0 = off.
    pub deadband: f64,
    /// Rolling-average cap of the line's on time, fraction 0..=1 of `avg_window` (1 = off).
    pub avg_limit: f64,
    /// The window of the rolling-average cap, ns.
    pub avg_window: Nanos,
    /// The time base, ns (`time_base_ms` rounded to the nearest ns); 0 = off. With a tick,
    /// `period`, `min_on`, `min_off` and `max_on` are whole numbers of ticks (see
    /// [`ChannelParams::validate`]) and the tick grid is the instants `k * tick` of the
    /// monotonic clock, `k` an integer.
    pub tick: Nanos,
    /// The heater loop and its checks.
    pub heater: HeaterConfig,
    /// The parameters this was made from (for status and round trips).
    pub params: ChannelParams,
}

impl ChannelConfig {
    /// The first instant of the tick grid at or after `t`, ns; `t` itself without a time base.
    pub fn tick_at_or_after(&self, t: Nanos) -> Nanos {
        match self.tick {
            0 => t,
            tick => t.div_ceil(tick).saturating_mul(tick),
        }
    }

    /// The duty fraction the power limits make of a command's fraction `duty` (0..=1): limited
    /// to `min_duty..=max_duty`, except that 0 stays 0 with `zero_means_zero`.
    pub fn limit_duty(&self, duty: f64) -> f64 {
        if self.zero_means_zero && duty <= 0.0 {
            duty
        } else {
            duty.clamp(self.min_duty, self.max_duty)
        }
    }
}

impl ChannelParams {
    /// The profile's policy unless overridden.
    pub fn effective_short_pulse(&self) -> ShortPulse {
        self.short_pulse.unwrap_or(self.profile.short_pulse())
    }

    /// The profile's policy unless overridden.
    pub fn effective_apply_at(&self) -> ApplyAt {
        self.apply_at.unwrap_or(self.profile.apply_at())
    }

    /// The profile's policy unless overridden.
    pub fn effective_on_disable(&self) -> OnDisable {
        self.on_disable.unwrap_or(self.profile.on_disable())
    }

    /// Whether a minimum time of any size is limited rather than refused (002: nMinSwiTi
    /// "internally limited to values between 0 and nPrd").
    fn limits_minima(&self) -> bool {
        self.profile == Profile::TwincatBa
    }

    /// The watchdog's limits: its timeout, and the fault value it runs and for how long.
    fn check_watchdog(&self) -> Result<(), ConfigError> {
        at_most_a_day(self.command_timeout_ms, |value_ms, max_ms| {
            ConfigError::TimeoutTooLong { value_ms, max_ms }
        })?;
        within(self.fault_duty_pct, 0.0..=100.0, |value| {
            ConfigError::FaultDutyOutOfRange { value }
        })?;
        at_most_a_day(self.fault_hold_ms, |value_ms, max_ms| {
            ConfigError::FaultHoldTooLong { value_ms, max_ms }
        })
    }

    /// Checks every limit of SPEC §1 and 000's table and resolves the profile.
    ///
    /// The checks run in a fixed order so the reason given is deterministic: period, time base,
    /// minimum times, edge band, cycle extension, watchdog, fault value, maximum on time, power
    /// limits, slew limit, rolling-average cap.
    ///
    /// With a time base (`time_base_ms` > 0, tick `τ` ns) the times become whole ticks: the
    /// period is rounded to the nearest whole number of ticks (at least one), so every period
    /// has the same number of ticks and the period grid stays on the tick grid; the minimum
    /// times are rounded up (a minimum is never shortened), then limited to the rounded period
    /// as before; the maximum on time is rounded down (a limit is never lengthened), and
    /// refused if that puts it below the minimum on time.
    pub fn validate(&self) -> Result<ChannelConfig, ConfigError> {
        let kind = self.output_kind;
        if self.period_ms != 0 && self.period_ms < kind.min_period_ms() {
            return Err(ConfigError::PeriodTooShort {
                period_ms: self.period_ms,
                min_ms: kind.min_period_ms(),
                kind,
            });
        }
        if self.period_ms > MAX_PERIOD_MS {
            return Err(ConfigError::PeriodTooLong {
                period_ms: self.period_ms,
                max_ms: MAX_PERIOD_MS,
            });
        }
        if !(self.time_base_ms == 0.0
            || (MIN_TIME_BASE_MS..=MAX_PERIOD_MS as f64).contains(&self.time_base_ms))
        {
            return Err(ConfigError::TimeBaseOutOfRange {
                value: self.time_base_ms,
                min: MIN_TIME_BASE_MS,
                max: MAX_PERIOD_MS as f64,
            });
        }
        if self.period_ms != 0 && self.time_base_ms > self.period_ms as f64 {
            return Err(ConfigError::TimeBaseAbovePeriod {
                value: self.time_base_ms,
                period_ms: self.period_ms,
            });
        }
        // The tick in whole ns: the grid is then exact integer arithmetic on the monotonic
        // clock. The rounding is at most 0.5 ns a tick (60 ns/s at 120 ticks/s), far below
        // the mains frequency's own tolerance, and the clock is not locked to the mains anyway.
        let tick = (self.time_base_ms * NS_PER_MS as f64).round() as Nanos;
        let whole_up = |ns: Nanos| match tick {
            0 => ns,
            _ => ns.div_ceil(tick) * tick,
        };
        let period = match tick {
            _ if self.period_ms == 0 || tick == 0 => self.period_ms * NS_PER_MS,
            _ => (((self.period_ms * NS_PER_MS) + tick / 2) / tick).max(1) * tick,
        };
        let min_off_ms = match self.min_off_ms {
            Some(v) => v,
            None if self.profile.min_off_follows_min_on() => self.min_on_ms,
            None => 0,
        };
        for (which, value_ms) in [(MinTime::On, self.min_on_ms), (MinTime::Off, min_off_ms)] {
            if value_ms != 0 && value_ms < kind.min_explicit_time_ms() {
                return Err(ConfigError::RelayMinTimeTooShort {
                    which,
                    value_ms,
                    min_ms: kind.min_explicit_time_ms(),
                });
            }
            // No vendor allows more than an hour (000: ME <= 65 535 ms); the bound also keeps
            // the nanosecond arithmetic below far from overflow. 002: nMinSwiTi is
            // "internally limited to values between 0 and nPrd": under twincat_ba any value is
            // limited (below), never refused.
            if value_ms > MAX_PERIOD_MS && !self.limits_minima() {
                return Err(ConfigError::MinTimeTooLong {
                    which,
                    value_ms,
                    max_ms: MAX_PERIOD_MS,
                });
            }
        }
        // A minimum longer than the period is valid (000: ME up to 65 535 ms whatever PD; 002:
        // nMinSwiTi "limited to values between 0 and nPrd"): it acts as the period, so every
        // duty other than 0 and 100 % gives a constant output for the period, with E1. With no
        // pulses (period 0) the minima are kept as given for when a period is set again; under
        // `extend` too, as the extended period can hold them.
        // With `extend` the period grows to hold a minimum, so it is kept as given too.
        let extends = self.effective_short_pulse() == ShortPulse::Extend;
        // With a time base, rounded up to whole ticks, then limited to the (rounded) period.
        let effective = |ms: u64| {
            let limited = !(self.period_ms == 0 || extends);
            // Under twincat_ba a minimum is limited, not refused: to the period, or to an
            // hour while there is none to limit it to (or `extend` keeps it as given).
            let ms = ms.min(MAX_PERIOD_MS);
            let ms = if limited { ms.min(self.period_ms) } else { ms };
            let ns = whole_up((ms * NS_PER_MS).max(kind.floor_ns()));
            if limited {
                ns.min(period)
            } else {
                ns
            }
        };
        let min_on = effective(self.min_on_ms);
        let min_off = effective(min_off_ms);
        within(self.edge_band, 0.0..=1.0, |value| {
            ConfigError::EdgeBandOutOfRange { value }
        })?;
        within(self.extend_max, 1.0..=MAX_EXTEND_FACTOR, |value| {
            ConfigError::ExtendMaxOutOfRange {
                value,
                max: MAX_EXTEND_FACTOR,
            }
        })?;
        self.check_watchdog()?;
        if self.max_on_ms > MAX_ON_MS {
            return Err(ConfigError::MaxOnTooLong {
                value_ms: self.max_on_ms,
                max_ms: MAX_ON_MS,
            });
        }
        // With a time base, rounded down to whole ticks: the line is never on longer.
        let max_on = match tick {
            0 => self.max_on_ms * NS_PER_MS,
            _ => self.max_on_ms * NS_PER_MS / tick * tick,
        };
        if self.max_on_ms != 0 && max_on < min_on {
            return Err(ConfigError::MaxOnBelowMinOn {
                max_on_ms: self.max_on_ms,
                min_on_ms: min_on as f64 / NS_PER_MS as f64,
            });
        }
        for (which, value) in [
            (PercentParam::MaxDuty, self.max_duty_pct),
            (PercentParam::MinDuty, self.min_duty_pct),
            (PercentParam::Deadband, self.duty_deadband_pct),
            (PercentParam::AvgDutyLimit, self.avg_duty_limit_pct),
        ] {
            if !(0.0..=100.0).contains(&value) {
                return Err(ConfigError::PercentOutOfRange { which, value });
            }
        }
        if self.min_duty_pct > self.max_duty_pct {
            return Err(ConfigError::MinDutyAboveMaxDuty {
                min_pct: self.min_duty_pct,
                max_pct: self.max_duty_pct,
            });
        }
        if !(0.0..=MAX_SLEW_PCT_PER_S).contains(&self.duty_slew_pct_per_s) {
            return Err(ConfigError::SlewOutOfRange {
                value: self.duty_slew_pct_per_s,
                max: MAX_SLEW_PCT_PER_S,
            });
        }
        if !(1..=MAX_AVG_WINDOW_S).contains(&self.avg_window_s) {
            return Err(ConfigError::AvgWindowOutOfRange {
                value_s: self.avg_window_s,
                max_s: MAX_AVG_WINDOW_S,
            });
        }
        let mut heater = self.heater.validate()?;
        heater.stuck.full = self.max_duty_pct / 100.0;
        if heater.params.control.closed() && self.fault_duty_pct > 0.0 && self.fault_hold_ms == 0 {
            // Under pid nothing commands the duty but the loop: a fault value held "until a
            // command" would heat open loop for ever.
            return Err(ConfigError::FaultValueUnderPid {
                fault_duty_pct: self.fault_duty_pct,
            });
        }
        Ok(ChannelConfig {
            period,
            min_on,
            min_off,
            short_pulse: self.effective_short_pulse(),
            edge_band: self.edge_band,
            apply_at: self.effective_apply_at(),
            on_disable: self.effective_on_disable(),
            command_timeout: self.command_timeout_ms * NS_PER_MS,
            fault_duty: self.fault_duty_pct / 100.0,
            fault_hold: self.fault_hold_ms * NS_PER_MS,
            max_on,
            max_duty: self.max_duty_pct / 100.0,
            min_duty: self.min_duty_pct / 100.0,
            zero_means_zero: self.zero_means_zero,
            slew_per_s: self.duty_slew_pct_per_s / 100.0,
            deadband: self.duty_deadband_pct / 100.0,
            avg_limit: self.avg_duty_limit_pct / 100.0,
            avg_window: self.avg_window_s * 1_000 * NS_PER_MS,
            tick,
            heater,
            params: *self,
        })
    }
}

/// Ok if `value` lies in `range` (NaN never does), else the error `outside` makes of it.
fn within(
    value: f64,
    range: std::ops::RangeInclusive<f64>,
    outside: impl FnOnce(f64) -> ConfigError,
) -> Result<(), ConfigError> {
    if range.contains(&value) {
        Ok(())
    } else {
        Err(outside(value))
    }
}

/// Ok for a time of at most [`MAX_TIMEOUT_MS`], else the error `too_long` makes of it and that
/// maximum.
fn at_most_a_day(
    value_ms: u64,
    too_long: impl FnOnce(u64, u64) -> ConfigError,
) -> Result<(), ConfigError> {
    if value_ms <= MAX_TIMEOUT_MS {
        Ok(())
    } else {
        Err(too_long(value_ms, MAX_TIMEOUT_MS))
    }
}

impl Default for ChannelConfig {
    fn default() -> Self {
        // The defaults of SPEC §1 are valid by construction.
        match ChannelParams::default().validate() {
            Ok(c) => c,
            Err(e) => unreachable!("default parameters are valid: {e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> ChannelParams {
        ChannelParams::default()
    }

    /// The default parameters with the changes `set` makes, validated.
    fn validated(set: impl FnOnce(&mut ChannelParams)) -> Result<ChannelConfig, ConfigError> {
        let mut p = params();
        set(&mut p);
        p.validate()
    }

    #[test]
    fn defaults_match_spec_table() {
        let c = ChannelConfig::default();
        assert_eq!(c.period, 1000 * NS_PER_MS);
        // 000: ME = 0 gives the 0.1 ms hardware floor; min off = min on.
        assert_eq!(c.min_on, 100_000);
        assert_eq!(c.min_off, 100_000);
        assert_eq!(c.short_pulse, ShortPulse::Suppress);
        assert_eq!(c.apply_at, ApplyAt::NextPeriod);
        assert_eq!(c.on_disable, OnDisable::Off);
        assert_eq!(c.command_timeout, 0);
    }

    #[test]
    fn transistor_period_limits_000() {
        for (p, ok) in [
            (0, true),
            (4, false),
            (5, true),
            (65_535, true),
            (3_600_000, true),
        ] {
            let r = validated(|c| c.period_ms = p);
            assert_eq!(r.is_ok(), ok, "period {p}: {r:?}");
        }
        assert_eq!(
            validated(|p| p.period_ms = 3_600_001),
            Err(ConfigError::PeriodTooLong {
                period_ms: 3_600_001,
                max_ms: MAX_PERIOD_MS
            })
        );
    }

    #[test]
    fn relay_limits_000() {
        let relay = |set: fn(&mut ChannelParams)| {
            validated(|p| {
                p.output_kind = OutputKind::Relay;
                set(p);
            })
        };
        assert_eq!(
            relay(|p| p.period_ms = 99),
            Err(ConfigError::PeriodTooShort {
                period_ms: 99,
                min_ms: 100,
                kind: OutputKind::Relay
            })
        );
        assert_eq!(
            relay(|p| p.min_on_ms = 49),
            Err(ConfigError::RelayMinTimeTooShort {
                which: MinTime::On,
                value_ms: 49,
                min_ms: 50
            })
        );
        // 0 means the relay floor of 50 ms, for on and off alike.
        let c = relay(|p| p.period_ms = 100).unwrap();
        assert_eq!((c.min_on, c.min_off), (50 * NS_PER_MS, 50 * NS_PER_MS));
    }

    #[test]
    fn min_off_follows_min_on_unless_profile_says_otherwise() {
        let c = validated(|p| p.min_on_ms = 30).unwrap();
        assert_eq!(c.min_off, 30 * NS_PER_MS, "000: min off = min on");
        let c = validated(|p| {
            p.min_on_ms = 30;
            p.profile = Profile::TwincatBa;
        })
        .unwrap();
        assert_eq!(c.min_off, 100_000, "002: nMinSwiTi limits the on time only");
        let c = validated(|p| {
            p.min_on_ms = 30;
            p.min_off_ms = Some(10);
        })
        .unwrap();
        assert_eq!(c.min_off, 10 * NS_PER_MS);
    }

    #[test]
    fn minima_above_half_the_period_are_valid_000_002() {
        // 000: ME is 0..65 535 ms whatever PD, and "minimum off duration = minimum on
        // duration", so ME above PD/2 is a valid Pico GFX setting.
        let c = validated(|p| {
            p.period_ms = 100;
            p.min_on_ms = 60;
        })
        .unwrap();
        assert_eq!((c.min_on, c.min_off), (60 * NS_PER_MS, 60 * NS_PER_MS));
        // 002: nMinSwiTi "limited to values between 0 and nPrd": equal is valid, above is
        // limited to the period rather than refused.
        for min_on_ms in [1000, 1500, 65_535] {
            let c = validated(|p| {
                p.period_ms = 1000;
                p.min_on_ms = min_on_ms;
                p.profile = Profile::TwincatBa;
            })
            .unwrap();
            assert_eq!(c.min_on, 1000 * NS_PER_MS, "{min_on_ms}");
        }
        // 000's relay table: PD 150 with ME 100.
        let c = validated(|p| {
            p.period_ms = 150;
            p.min_on_ms = 100;
            p.output_kind = OutputKind::Relay;
        })
        .unwrap();
        assert_eq!((c.min_on, c.min_off), (100 * NS_PER_MS, 100 * NS_PER_MS));
        // Period 0 keeps the minima as given, for later.
        let c = validated(|p| {
            p.period_ms = 0;
            p.min_on_ms = 500;
        })
        .unwrap();
        assert_eq!(c.min_on, 500 * NS_PER_MS);
    }

    #[test]
    fn huge_minima_are_refused_without_overflow() {
        // u64 ms * 1e6 overflows above 1.8e13 ms: the check comes first, with a typed error,
        // whatever the period (0 included).
        for period_ms in [0, 1000] {
            for (which, p) in [
                (
                    MinTime::On,
                    ChannelParams {
                        period_ms,
                        min_on_ms: 20_000_000_000_000,
                        ..params()
                    },
                ),
                (
                    MinTime::Off,
                    ChannelParams {
                        period_ms,
                        min_off_ms: Some(u64::MAX),
                        ..params()
                    },
                ),
            ] {
                let e = p.validate().unwrap_err();
                assert!(
                    matches!(e, ConfigError::MinTimeTooLong { which: w, max_ms: MAX_PERIOD_MS, .. } if w == which),
                    "{e:?}"
                );
            }
        }
        let e = validated(|p| p.command_timeout_ms = u64::MAX).unwrap_err();
        assert!(matches!(e, ConfigError::TimeoutTooLong { .. }));
        assert!(validated(|p| p.period_ms = u64::MAX).is_err());
    }

    #[test]
    fn edge_band_range_004() {
        for v in [-0.1, 1.1, f64::NAN, f64::INFINITY] {
            let r = validated(|p| p.edge_band = v);
            assert!(
                matches!(r, Err(ConfigError::EdgeBandOutOfRange { .. })),
                "{v}"
            );
        }
        for v in [0.0, 0.5, 1.0] {
            assert!(validated(|p| p.edge_band = v).is_ok());
        }
    }

    #[test]
    fn extend_max_range() {
        for v in [0.99, 0.0, -1.0, 100.5, f64::NAN, f64::INFINITY] {
            let r = validated(|p| p.extend_max = v);
            assert!(
                matches!(r, Err(ConfigError::ExtendMaxOutOfRange { .. })),
                "{v}"
            );
        }
        assert_eq!(
            validated(|p| p.extend_max = 0.5).unwrap_err().to_string(),
            "extend_max 0.5 is outside 1..100"
        );
        for v in [1.0, 10.0, 100.0] {
            assert_eq!(
                validated(|p| p.extend_max = v).unwrap().params.extend_max,
                v
            );
        }
        assert_eq!("extend".parse::<ShortPulse>(), Ok(ShortPulse::Extend));
        assert_eq!(
            "x".parse::<ShortPulse>().unwrap_err().to_string(),
            "`x` is not one of: suppress|stretch|band|extend"
        );
    }

    #[test]
    fn extend_keeps_minima_longer_than_the_period() {
        // The extended period can hold them; the other policies take the period instead.
        let c = validated(|p| {
            p.period_ms = 1000;
            p.min_on_ms = 3000;
            p.min_off_ms = Some(2000);
            p.short_pulse = Some(ShortPulse::Extend);
        })
        .unwrap();
        assert_eq!((c.min_on, c.min_off), (3000 * NS_PER_MS, 2000 * NS_PER_MS));
        // So does the check of the maximum on time against the minimum on time.
        assert!(matches!(
            validated(|p| {
                p.period_ms = 1000;
                p.min_on_ms = 3000;
                p.max_on_ms = 2000;
                p.short_pulse = Some(ShortPulse::Extend);
            }),
            Err(ConfigError::MaxOnBelowMinOn { .. })
        ));
    }

    #[test]
    fn profiles_set_policies_and_explicit_values_override() {
        let expect = [
            (
                Profile::PicoGfx,
                ShortPulse::Suppress,
                ApplyAt::NextPeriod,
                OnDisable::Off,
            ),
            (
                Profile::TwincatBa,
                ShortPulse::Stretch,
                ApplyAt::NextStep,
                OnDisable::Off,
            ),
            (
                Profile::TcontCp,
                ShortPulse::Suppress,
                ApplyAt::Immediate,
                OnDisable::Off,
            ),
            (
                Profile::SchneiderPwm,
                ShortPulse::Suppress,
                ApplyAt::NextPeriod,
                OnDisable::Off,
            ),
            (
                Profile::FrequencyOutput,
                ShortPulse::Band,
                ApplyAt::NextPeriod,
                OnDisable::Hold,
            ),
        ];
        for (profile, sp, aa, od) in expect {
            let c = validated(|p| p.profile = profile).unwrap();
            assert_eq!(
                (c.short_pulse, c.apply_at, c.on_disable),
                (sp, aa, od),
                "{profile}"
            );
            let c = validated(|p| {
                p.profile = profile;
                p.short_pulse = Some(ShortPulse::Stretch);
                p.apply_at = Some(ApplyAt::Immediate);
                p.on_disable = Some(OnDisable::Hold);
            })
            .unwrap();
            assert_eq!(
                (c.short_pulse, c.apply_at, c.on_disable),
                (ShortPulse::Stretch, ApplyAt::Immediate, OnDisable::Hold)
            );
        }
    }

    #[test]
    fn the_protections_are_off_by_default() {
        let c = ChannelConfig::default();
        assert_eq!(c.max_on, 0);
        assert_eq!(
            (c.max_duty, c.min_duty, c.zero_means_zero),
            (1.0, 0.0, false)
        );
        assert_eq!((c.slew_per_s, c.deadband), (0.0, 0.0));
        for d in [0.0, 0.37, 1.0] {
            assert_eq!(c.limit_duty(d), d);
        }
    }

    #[test]
    fn max_on_is_never_below_the_minimum_on_time_in_force() {
        let max_on = |min_on_ms, max_on_ms, output_kind| {
            ChannelParams {
                min_on_ms,
                max_on_ms,
                output_kind,
                ..params()
            }
            .validate()
        };
        assert!(max_on(100, 100, OutputKind::Transistor).is_ok());
        assert_eq!(
            max_on(100, 99, OutputKind::Transistor)
                .unwrap_err()
                .to_string(),
            "max_on_ms 99 is below the minimum on time of 100 ms (0 turns the maximum off)"
        );
        assert_eq!(
            max_on(100, 99, OutputKind::Transistor),
            Err(ConfigError::MaxOnBelowMinOn {
                max_on_ms: 99,
                min_on_ms: 100.0
            })
        );
        // The relay floor of 50 ms is the minimum when min_on_ms is 0.
        assert!(matches!(
            max_on(0, 49, OutputKind::Relay),
            Err(ConfigError::MaxOnBelowMinOn { min_on_ms, .. }) if min_on_ms == 50.0
        ));
        // A minimum above the period acts as the period, so does the check.
        assert!(ChannelParams {
            period_ms: 200,
            min_on_ms: 5000,
            max_on_ms: 200,
            ..params()
        }
        .validate()
        .is_ok());
        assert!(max_on(0, 1, OutputKind::Transistor).is_ok(), "0.1 ms floor");
        assert!(max_on(0, MAX_ON_MS, OutputKind::Transistor).is_ok());
        assert_eq!(
            max_on(0, MAX_ON_MS + 1, OutputKind::Transistor),
            Err(ConfigError::MaxOnTooLong {
                value_ms: MAX_ON_MS + 1,
                max_ms: MAX_ON_MS
            })
        );
    }

    #[test]
    fn duty_limits_dead_band_and_slew_are_checked() {
        let with = |f: fn(&mut ChannelParams)| {
            let mut p = params();
            f(&mut p);
            p.validate()
        };
        assert!(matches!(
            with(|p| p.max_duty_pct = 100.5),
            Err(ConfigError::PercentOutOfRange {
                which: PercentParam::MaxDuty,
                ..
            })
        ));
        assert!(matches!(
            with(|p| p.min_duty_pct = -1.0),
            Err(ConfigError::PercentOutOfRange {
                which: PercentParam::MinDuty,
                ..
            })
        ));
        assert!(matches!(
            with(|p| p.duty_deadband_pct = f64::NAN),
            Err(ConfigError::PercentOutOfRange {
                which: PercentParam::Deadband,
                ..
            })
        ));
        assert_eq!(
            with(|p| {
                p.min_duty_pct = 30.0;
                p.max_duty_pct = 20.0;
            }),
            Err(ConfigError::MinDutyAboveMaxDuty {
                min_pct: 30.0,
                max_pct: 20.0
            })
        );
        assert!(with(|p| {
            p.min_duty_pct = 20.0;
            p.max_duty_pct = 20.0;
        })
        .is_ok());
        for v in [-0.1, MAX_SLEW_PCT_PER_S + 1.0, f64::INFINITY, f64::NAN] {
            let r = ChannelParams {
                duty_slew_pct_per_s: v,
                ..params()
            }
            .validate();
            assert!(matches!(r, Err(ConfigError::SlewOutOfRange { .. })), "{v}");
        }
        let c = with(|p| {
            p.min_duty_pct = 10.0;
            p.max_duty_pct = 60.0;
        })
        .unwrap();
        assert_eq!((c.limit_duty(0.0), c.limit_duty(0.05)), (0.1, 0.1));
        assert_eq!((c.limit_duty(0.3), c.limit_duty(1.0)), (0.3, 0.6));
        let c = with(|p| {
            p.min_duty_pct = 10.0;
            p.zero_means_zero = true;
        })
        .unwrap();
        assert_eq!((c.limit_duty(0.0), c.limit_duty(0.05)), (0.0, 0.1));
    }

    #[test]
    fn the_rolling_average_cap_is_checked() {
        let c = params().validate().unwrap();
        assert_eq!((c.avg_limit, c.avg_window), (1.0, 60 * 1000 * NS_PER_MS));
        for (pct, s) in [(101.0, 60), (-1.0, 60), (f64::NAN, 60)] {
            let e = ChannelParams {
                avg_duty_limit_pct: pct,
                avg_window_s: s,
                ..params()
            }
            .validate()
            .unwrap_err();
            assert!(e.to_string().starts_with("avg_duty_limit_pct "), "{e}");
        }
        for s in [0, MAX_AVG_WINDOW_S + 1] {
            let e = ChannelParams {
                avg_window_s: s,
                ..params()
            }
            .validate()
            .unwrap_err();
            assert_eq!(
                e.to_string(),
                format!("avg_window_s {s} is outside 1..86400 s")
            );
        }
        let c = ChannelParams {
            avg_duty_limit_pct: 25.0,
            avg_window_s: MAX_AVG_WINDOW_S,
            ..params()
        }
        .validate()
        .unwrap();
        assert_eq!((c.avg_limit, c.avg_window), (0.25, 86_400_000 * NS_PER_MS));
    }

    #[test]
    fn names_round_trip_and_unknown_names_say_what_is_accepted() {
        for p in Profile::ALL {
            assert_eq!(p.as_str().parse::<Profile>(), Ok(p));
        }
        let e = "pico".parse::<Profile>().unwrap_err();
        assert_eq!(
            e.to_string(),
            "`pico` is not one of: pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output"
        );
        assert_eq!("relay".parse::<OutputKind>(), Ok(OutputKind::Relay));
        assert!("x".repeat(100).parse::<ApplyAt>().is_err());
    }
}
