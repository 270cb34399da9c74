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
/// Shortest reversal pause accepted, ms. A relay needs up to 10 ms to release its contacts
/// (the arc included), and a triac conducts until the next zero of its current: up to 10 ms at
/// 50 Hz (8.3 ms at 60 Hz). Either way a reversal break shorter than 10 ms lets both windings
/// conduct; twice that covers a relay driving a triac-switched actuator.
pub const MIN_REVERSAL_PAUSE_MS: u64 = 20;
/// Largest start lag accepted, percent of the shorter travel time: with it, a drive of 150 %
/// of the travel time still moves a valve whose travel is 10 % slow across the whole stroke.
pub const MAX_START_LAG_PCT_OF_TRAVEL: f64 = 10.0;
/// Largest backlash accepted, percent of the stroke.
pub const MAX_BACKLASH_PCT: f64 = 5.0;
/// Largest feedback tolerance accepted, percent of the stroke.
pub const MAX_FEEDBACK_TOLERANCE_PCT: f64 = 10.0;

/// How the valve finds its position when the node starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum ReferenceAtStart {
    /// Close for 150 % of the closing travel time and take 0 % (Siemens `PID_3Step`'s
    /// virtual actuator limit), whether or not a position was restored.
    #[default]
    Close,
    /// Open for 150 % of the opening travel time and take 100 % (a plant that must not close
    /// at start: frost protection, district heating).
    Open,
    /// No stroke when a position was restored from the state file; close as `close` when none
    /// was.
    SkipIfRestored,
    /// Never: the restored position, or unreferenced until an end switch, an end move or the
    /// feedback references it.
    None,
}

impl ReferenceAtStart {
    /// The parameter spelling: `close`, `open`, `skip_if_restored` or `none`.
    pub const fn as_str(self) -> &'static str {
        match self {
            ReferenceAtStart::Close => "close",
            ReferenceAtStart::Open => "open",
            ReferenceAtStart::SkipIfRestored => "skip_if_restored",
            ReferenceAtStart::None => "none",
        }
    }
}

named_enum!(
    ReferenceAtStart,
    "close|open|skip_if_restored|none",
    [
        ReferenceAtStart::Close,
        ReferenceAtStart::Open,
        ReferenceAtStart::SkipIfRestored,
        ReferenceAtStart::None
    ]
);

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
    /// Both lines are low at least this long before the drive reverses, ms. 20..=60 000
    /// ([`MIN_REVERSAL_PAUSE_MS`]).
    pub reversal_pause_ms: u64,
    /// Time from a line's rise until the motor moves the valve, ms: every drive lasts this
    /// much longer than the displacement it is for, and the estimate counts only the drive
    /// after it. 0..=10 % of the shorter travel time.
    pub start_lag_ms: u64,
    /// Play between the motor and the valve's stem, percent of the stroke: after a reversal the
    /// motor turns this far before the stem follows. 0..=5.
    pub backlash_pct: f64,
    /// A move to 0 % or 100 % drives on past the end by this share of the travel time beyond
    /// what reaches the end from anywhere within the uncertainty, percent. 0..=50.
    pub end_overrun_pct: f64,
    /// How the valve finds its position at start.
    pub reference_at_start: ReferenceAtStart,
    /// A recalibration becomes due after this much accumulated run time since the last
    /// reference (or once the uncertainty passes half of `max_uncertainty_pct`), s; 0 = by the
    /// uncertainty only.
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
    /// How far the position feedback may be from the true position, percent of the stroke
    /// (a potentiometer's or a 0–10 V input's accuracy). 0..=10.
    pub feedback_tolerance_pct: f64,
}

impl Default for ValveParams {
    fn default() -> Self {
        ValveParams {
            travel_open_ms: 60_000,
            travel_close_ms: 60_000,
            deadband_pct: 1.0,
            min_pulse_ms: 200,
            reversal_pause_ms: 500,
            start_lag_ms: 0,
            backlash_pct: 1.0,
            end_overrun_pct: 10.0,
            reference_at_start: ReferenceAtStart::Close,
            recalibrate_after_s: 600,
            exercise_every_h: 0,
            max_uncertainty_pct: 10.0,
            command_timeout_ms: 0,
            on_timeout: OnTimeout::Stop,
            feedback_tolerance_pct: 1.0,
        }
    }
}

/// Why valve settings are refused; the old settings stay in force.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ValveConfigError {
    /// A value outside its range, or not a number.
    #[error(transparent)]
    OutOfRange(#[from] OutOfRange),
    /// A reversal pause below [`MIN_REVERSAL_PAUSE_MS`].
    #[error(
        "reversal_pause_ms {0} is below {MIN_REVERSAL_PAUSE_MS} ms: a relay needs up to 10 ms to \
         release and a triac conducts to the next current zero (up to 10 ms at 50 Hz), so a \
         shorter break lets both windings conduct"
    )]
    ReversalPauseTooShort(u64),
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
    /// Start lag, ns.
    pub start_lag: Nanos,
    /// Backlash, percent of the stroke.
    pub backlash_pct: f64,
    /// Overrun at an end, percent of the travel time.
    pub end_overrun_pct: f64,
    /// Reference at start.
    pub reference_at_start: ReferenceAtStart,
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
    /// Feedback tolerance, percent.
    pub feedback_tolerance_pct: f64,
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
        if self.reversal_pause_ms < MIN_REVERSAL_PAUSE_MS {
            return Err(ValveConfigError::ReversalPauseTooShort(
                self.reversal_pause_ms,
            ));
        }
        OutOfRange::check(
            "reversal_pause_ms",
            self.reversal_pause_ms as f64,
            MIN_REVERSAL_PAUSE_MS as f64,
            MAX_REVERSAL_PAUSE_MS as f64,
        )?;
        OutOfRange::check(
            "start_lag_ms",
            self.start_lag_ms as f64,
            0.0,
            (shorter as f64 * MAX_START_LAG_PCT_OF_TRAVEL / 100.0).floor(),
        )?;
        OutOfRange::check("backlash_pct", self.backlash_pct, 0.0, MAX_BACKLASH_PCT)?;
        OutOfRange::check(
            "feedback_tolerance_pct",
            self.feedback_tolerance_pct,
            0.0,
            MAX_FEEDBACK_TOLERANCE_PCT,
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
            start_lag: self.start_lag_ms * NS_PER_MS,
            backlash_pct: self.backlash_pct,
            end_overrun_pct: self.end_overrun_pct,
            reference_at_start: self.reference_at_start,
            recalibrate_after: self.recalibrate_after_s * 1_000 * NS_PER_MS,
            exercise_every: self.exercise_every_h * 3_600 * 1_000 * NS_PER_MS,
            max_uncertainty_pct: self.max_uncertainty_pct,
            command_timeout: self.command_timeout_ms * NS_PER_MS,
            on_timeout: self.on_timeout,
            feedback_tolerance_pct: self.feedback_tolerance_pct,
            params: self,
        })
    }
}
