//! The settings of one three-point valve: what a user states (milliseconds, percent, hours),
//! their ranges, and the validated form in nanoseconds the valve runs on.

use crate::core::config::{named_enum, OutOfRange};
use crate::core::{Nanos, NS_PER_MS};

/// Shortest travel time accepted, ms.
pub const MIN_TRAVEL_MS: u64 = 1_000;
/// Longest travel time accepted, ms (one hour).
pub const MAX_TRAVEL_MS: u64 = 3_600_000;
/// Largest dead band accepted, percent of the stroke.
pub const MAX_DEADBAND_PCT: f64 = 20.0;
/// Longest reversal pause accepted, ms.
pub const MAX_REVERSAL_PAUSE_MS: u64 = 60_000;
/// Largest overrun at an end accepted, percent of the travel time.
pub const MAX_END_OVERRUN_PCT: f64 = 50.0;
/// Longest accumulated run time before a recalibration accepted, s (ten days).
pub const MAX_RECALIBRATE_AFTER_S: u64 = 864_000;
/// Longest interval of the exercise stroke accepted, h (a year).
pub const MAX_EXERCISE_EVERY_H: u64 = 8_760;
/// Longest command timeout accepted, ms (one day).
pub const MAX_COMMAND_TIMEOUT_MS: u64 = 86_400_000;

/// What the valve does when no position command came for `command_timeout_ms`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum OnTimeout {
    /// Stop where it is (the target becomes the estimate).
    #[default]
    Stop,
    /// Close fully (target 0 %).
    Close,
    /// Open fully (target 100 %).
    Open,
}

impl OnTimeout {
    /// The parameter spelling: `stop`, `close` or `open`.
    pub const fn as_str(self) -> &'static str {
        match self {
            OnTimeout::Stop => "stop",
            OnTimeout::Close => "close",
            OnTimeout::Open => "open",
        }
    }
}

named_enum!(
    OnTimeout,
    "stop|close|open",
    [OnTimeout::Stop, OnTimeout::Close, OnTimeout::Open]
);

/// The settings of one valve as a user states them. Defaults follow OSCAT `ACTUATOR_3P`
/// (`T_RUN` 60 s) and Siemens `PID_3Step` where they name one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValveParams {
    /// Time the actuator needs from fully closed to fully open, ms. 1 000..=3 600 000.
    pub travel_open_ms: u64,
    /// Time from fully open to fully closed, ms. 1 000..=3 600 000.
    pub travel_close_ms: u64,
    /// No move for a smaller difference between target and estimate, percent. 0..=20.
    pub deadband_pct: f64,
    /// Shortest drive, ms: a shorter move is accumulated until it reaches this; a started move
    /// lasts at least this. 0..=the shorter travel time.
    pub min_pulse_ms: u64,
    /// Both lines are low at least this long before the drive reverses, ms. 0..=60 000.
    pub reversal_pause_ms: u64,
    /// A move to 0 % or 100 % drives on past the estimated end by this share of the travel
    /// time, percent. 0..=50.
    pub end_overrun_pct: f64,
    /// Drive closed for 150 % of the travel time when the node starts, and take 0 % from it.
    pub reference_at_start: bool,
    /// After this much accumulated run time since the last reference, the next command at or
    /// near an end becomes an overrun long enough to cover the uncertainty, s; 0 = never.
    pub recalibrate_after_s: u64,
    /// A valve that has not moved for this long makes one full stroke and returns, h;
    /// 0 = never. 0..=8 760.
    pub exercise_every_h: u64,
    /// Above this uncertainty of the estimate the valve's diagnostics warn, percent. 0..=100.
    pub max_uncertainty_pct: f64,
    /// No position command for this long triggers `on_timeout`, ms; 0 = off. 0..=86 400 000.
    pub command_timeout_ms: u64,
    /// What a command timeout does.
    pub on_timeout: OnTimeout,
}

impl Default for ValveParams {
    fn default() -> Self {
        ValveParams {
            travel_open_ms: 60_000,
            travel_close_ms: 60_000,
            deadband_pct: 1.0,
            min_pulse_ms: 200,
            reversal_pause_ms: 500,
            end_overrun_pct: 10.0,
            reference_at_start: true,
            recalibrate_after_s: 600,
            exercise_every_h: 0,
            max_uncertainty_pct: 10.0,
            command_timeout_ms: 0,
            on_timeout: OnTimeout::Stop,
        }
    }
}

/// Why valve settings are refused; the old settings stay in force.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ValveConfigError {
    /// A value outside its range, or not a number.
    #[error(transparent)]
    OutOfRange(#[from] OutOfRange),
}

/// The validated settings a valve runs on, in nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValveConfig {
    /// Travel time of each direction, ns, indexed by [`Dir::index`](super::Dir::index).
    pub travel: [Nanos; 2],
    /// Dead band, percent.
    pub deadband_pct: f64,
    /// Shortest drive, ns.
    pub min_pulse: Nanos,
    /// Both lines low at least this long before a rise, ns.
    pub reversal_pause: Nanos,
    /// Overrun at an end, percent of the travel time.
    pub end_overrun_pct: f64,
    /// Reference at start.
    pub reference_at_start: bool,
    /// Run time since the last reference that makes a recalibration due, ns; 0 = never.
    pub recalibrate_after: Nanos,
    /// Idle time that makes an exercise stroke due, ns; 0 = never.
    pub exercise_every: Nanos,
    /// Diagnostics warn above this uncertainty, percent.
    pub max_uncertainty_pct: f64,
    /// Command timeout, ns; 0 = off.
    pub command_timeout: Nanos,
    /// What the timeout does.
    pub on_timeout: OnTimeout,
    /// The parameters this was made from.
    pub params: ValveParams,
}

impl ValveParams {
    /// Checks every value against its range (NaN never passes) and makes the nanosecond form.
    pub fn validate(self) -> Result<ValveConfig, ValveConfigError> {
        let travel = (MIN_TRAVEL_MS as f64, MAX_TRAVEL_MS as f64);
        OutOfRange::check(
            "travel_open_ms",
            self.travel_open_ms as f64,
            travel.0,
            travel.1,
        )?;
        OutOfRange::check(
            "travel_close_ms",
            self.travel_close_ms as f64,
            travel.0,
            travel.1,
        )?;
        OutOfRange::check("deadband_pct", self.deadband_pct, 0.0, MAX_DEADBAND_PCT)?;
        let shorter = self.travel_open_ms.min(self.travel_close_ms);
        OutOfRange::check(
            "min_pulse_ms",
            self.min_pulse_ms as f64,
            0.0,
            shorter as f64,
        )?;
        OutOfRange::check(
            "reversal_pause_ms",
            self.reversal_pause_ms as f64,
            0.0,
            MAX_REVERSAL_PAUSE_MS as f64,
        )?;
        OutOfRange::check(
            "end_overrun_pct",
            self.end_overrun_pct,
            0.0,
            MAX_END_OVERRUN_PCT,
        )?;
        OutOfRange::check(
            "recalibrate_after_s",
            self.recalibrate_after_s as f64,
            0.0,
            MAX_RECALIBRATE_AFTER_S as f64,
        )?;
        OutOfRange::check(
            "exercise_every_h",
            self.exercise_every_h as f64,
            0.0,
            MAX_EXERCISE_EVERY_H as f64,
        )?;
        OutOfRange::check("max_uncertainty_pct", self.max_uncertainty_pct, 0.0, 100.0)?;
        OutOfRange::check(
            "command_timeout_ms",
            self.command_timeout_ms as f64,
            0.0,
            MAX_COMMAND_TIMEOUT_MS as f64,
        )?;
        Ok(ValveConfig {
            travel: [
                self.travel_open_ms * NS_PER_MS,
                self.travel_close_ms * NS_PER_MS,
            ],
            deadband_pct: self.deadband_pct,
            min_pulse: self.min_pulse_ms * NS_PER_MS,
            reversal_pause: self.reversal_pause_ms * NS_PER_MS,
            end_overrun_pct: self.end_overrun_pct,
            reference_at_start: self.reference_at_start,
            recalibrate_after: self.recalibrate_after_s * 1_000 * NS_PER_MS,
            exercise_every: self.exercise_every_h * 3_600 * 1_000 * NS_PER_MS,
            max_uncertainty_pct: self.max_uncertainty_pct,
            command_timeout: self.command_timeout_ms * NS_PER_MS,
            on_timeout: self.on_timeout,
            params: self,
        })
    }
}
