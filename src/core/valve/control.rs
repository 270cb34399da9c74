//! The valve's own loop (`NAME.control` `pid`), as Siemens `PID_3Step` and Beckhoff's
//! `FB_BA_Anlg3Pnt` behind a `STEP_PID` run it next to the motor outputs: a PID from a process
//! value (a temperature, a pressure, a flow) to a setpoint, sampled every `pid_sample_ms`,
//! whose output the valve follows.
//!
//! - **Position mode** (the valve knows where it is: a position feedback): the output is the
//!   valve's target, 0..100 %.
//! - **Step mode** (no position knowledge, `PID_3Step` "without position feedback"): the output
//!   lives in the frame of the valve's own drives (the stem displacement its drives gave,
//!   counted from the loop's start); what the valve has not delivered yet is driven as step
//!   pulses. No absolute position is needed, none is assumed.
//!
//! The PID is the heater loop's ([`Pid`]): P and I on the error, D on the measurement with its
//! filter, the integral kept within the output limits and not integrated further while the
//! output sits at a limit in the direction the error pushes (anti-windup). The limits are the
//! ends in position mode; in step mode they are as far as the valve's bounds say it may still
//! travel each way (the uncertainty's limits): once the valve may be at an end, the loop asks
//! no further that way than what reaches the end from the farthest the valve can be.
//!
//! Before the valve follows it, the output is smoothed over a third of the mean interval the
//! motor budget allows between starts (1200 / `max_starts_per_h` s): the sensor's noise, which
//! the proportional term passes on sample by sample, is not worth a start; what it averages
//! out to is. Without a budget there is no smoothing.
//!
//! Only fresh readings count (the heater loop's rule): a reading is stale when its stamp lies
//! more than `process_max_skew_ms` ahead of this node's clock or is older than
//! `process_timeout_ms` on arrival; stale readings are counted and used by nothing. With no fresh
//! reading for `process_timeout_ms` the loop stops and the valve holds where it is (WARN); with a
//! `safe_position_pct`, after `safe_after_ms` more the valve goes there. Fresh readings restart
//! the loop from where the valve stands.
//!
//! Every start of the loop is bumpless: at the first sample after the switch to `pid`, after
//! manual mode, a hold, a pause (the reference, a recalibration, the exercise stroke, the
//! e-stop, the lifecycle's inactive states, a fault) or a command timeout, the integral takes
//! up the difference so that the output is where the valve stands (position mode: the target in
//! force, else the estimate; step mode: the frame, so no step at all).
//!
//! Nothing here reads a clock; the valve passes `now`.

use super::super::heater::pid::{Gains, Pid, Terms};
use crate::core::config::{named_enum, OutOfRange};
use crate::core::{Nanos, NS_PER_MS};
use std::fmt;

/// Who sets the valve's target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Control {
    /// The position commands (`~/valve/NAME/position`).
    #[default]
    Position,
    /// The valve's own loop, from the process value and `~/valve/NAME/setpoint`.
    Pid,
}

impl Control {
    /// The parameter spelling: `position` or `pid`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Control::Position => "position",
            Control::Pid => "pid",
        }
    }
}

named_enum!(Control, "position|pid", [Control::Position, Control::Pid]);

/// What the loop's output drives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum LoopOutput {
    /// Position mode with a position feedback, step mode without.
    #[default]
    Auto,
    /// The output is the valve's target (the estimate must be good: a feedback, or the
    /// recalibrations the valve makes when its uncertainty grows).
    Position,
    /// Step pulses from what the valve has not delivered yet (`PID_3Step` without position
    /// feedback).
    Step,
}

impl LoopOutput {
    /// The parameter spelling: `auto`, `position` or `step`.
    pub const fn as_str(self) -> &'static str {
        match self {
            LoopOutput::Auto => "auto",
            LoopOutput::Position => "position",
            LoopOutput::Step => "step",
        }
    }
}

named_enum!(
    LoopOutput,
    "auto|position|step",
    [LoopOutput::Auto, LoopOutput::Position, LoopOutput::Step]
);

/// Largest gain accepted for `pid_kp`, `pid_ki` and `pid_kd`.
pub const MAX_LOOP_GAIN: f64 = 100_000.0;
/// Shortest loop sample accepted, ms.
pub const MIN_LOOP_SAMPLE_MS: u64 = 10;
/// Longest loop sample accepted, ms (an hour).
pub const MAX_LOOP_SAMPLE_MS: u64 = 3_600_000;
/// Longest derivative filter accepted, s (a day).
pub const MAX_D_FILTER_S: f64 = 86_400.0;
/// `process_timeout_ms`'s default, ms: the heater loop's `feedback_timeout_ms`; a sensor
/// publishing at 1 Hz may lose two readings in a row.
pub const DEFAULT_PROCESS_TIMEOUT_MS: u64 = 3_000;
/// Longest `process_timeout_ms` and `safe_after_ms` accepted, ms (a day).
pub const MAX_PROCESS_TIMEOUT_MS: u64 = 86_400_000;
/// Largest `process_max_skew_ms`, ms.
pub const MAX_PROCESS_SKEW_MS: u64 = 60_000;
/// Largest magnitude of a process value or a setpoint accepted, in the process's unit: beyond
/// it a value is a broken sensor or a typing error, in any unit.
pub const MAX_PROCESS_VALUE: f64 = 1.0e9;

/// The loop's settings as a user states them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlParams {
    /// Who sets the target.
    pub control: Control,
    /// A process topic is configured (`NAME.process_topic` not empty): readings arrive.
    pub process: bool,
    /// What the output drives.
    pub output: LoopOutput,
    /// Proportional gain, % of the stroke per unit of the process value.
    pub pid_kp: f64,
    /// Integral gain, % per unit·s.
    pub pid_ki: f64,
    /// Derivative gain, % per unit/s (on the measurement).
    pub pid_kd: f64,
    /// The derivative's first-order filter, s; 0 = unfiltered.
    pub pid_d_filter_s: f64,
    /// Reverse acting: opening the valve lowers the process value (a cooling valve).
    pub pid_reverse: bool,
    /// The loop's sample, ms. 10..=3 600 000.
    pub pid_sample_ms: u64,
    /// No fresh reading for this long stops the loop and holds the valve, ms; also the age on
    /// arrival beyond which a reading is stale. 1..=86 400 000.
    pub process_timeout_ms: u64,
    /// How far in the future a reading's stamp may lie against this node's clock, ms.
    pub process_max_skew_ms: u64,
    /// Where the valve goes once the loop has held for `safe_after_ms`, percent; negative =
    /// nowhere (it holds).
    pub safe_position_pct: f64,
    /// How long the loop holds before the valve goes to `safe_position_pct`, ms.
    pub safe_after_ms: u64,
}

impl Default for ControlParams {
    fn default() -> Self {
        ControlParams {
            control: Control::Position,
            process: false,
            output: LoopOutput::Auto,
            pid_kp: 0.0,
            pid_ki: 0.0,
            pid_kd: 0.0,
            pid_d_filter_s: 0.0,
            pid_reverse: false,
            pid_sample_ms: 1_000,
            process_timeout_ms: DEFAULT_PROCESS_TIMEOUT_MS,
            process_max_skew_ms: 1_000,
            safe_position_pct: -1.0,
            safe_after_ms: 60_000,
        }
    }
}

/// Why the loop's settings are refused.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum ControlError {
    /// A value outside its range, or not a number.
    #[error(transparent)]
    OutOfRange(#[from] OutOfRange),
    /// `control` `pid` without a process value.
    #[error("control pid needs a process_topic (set at start-up): the loop has nothing to read")]
    PidWithoutProcess,
    /// `control` `pid` with no gain.
    #[error("control pid needs pid_kp or pid_ki above 0: with neither the loop never acts")]
    PidWithoutGains,
}

/// The validated settings the loop runs on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlConfig {
    /// The parameters this was made from.
    pub params: ControlParams,
    /// The gains.
    pub gains: Gains,
    /// The sample, ns.
    pub sample: Nanos,
    /// `process_timeout_ms`, ns.
    pub timeout: Nanos,
    /// `process_max_skew_ms`, ns.
    pub max_skew: Nanos,
    /// The safe position, if one is set, percent.
    pub safe: Option<f64>,
    /// `safe_after_ms`, ns.
    pub safe_after: Nanos,
    /// The output's smoothing time constant, s (from the motor budget); 0 = none.
    pub smooth_s: f64,
}

impl ControlParams {
    /// Checks every value (NaN never passes) and makes the form the loop runs on;
    /// `max_starts_per_h` (0: no budget) sets the output's smoothing.
    pub fn validate(self, max_starts_per_h: u64) -> Result<ControlConfig, ControlError> {
        OutOfRange::check("pid_kp", self.pid_kp, 0.0, MAX_LOOP_GAIN)?;
        OutOfRange::check("pid_ki", self.pid_ki, 0.0, MAX_LOOP_GAIN)?;
        OutOfRange::check("pid_kd", self.pid_kd, 0.0, MAX_LOOP_GAIN)?;
        OutOfRange::check("pid_d_filter_s", self.pid_d_filter_s, 0.0, MAX_D_FILTER_S)?;
        OutOfRange::check(
            "pid_sample_ms",
            self.pid_sample_ms as f64,
            MIN_LOOP_SAMPLE_MS as f64,
            MAX_LOOP_SAMPLE_MS as f64,
        )?;
        OutOfRange::check(
            "process_timeout_ms",
            self.process_timeout_ms as f64,
            1.0,
            MAX_PROCESS_TIMEOUT_MS as f64,
        )?;
        OutOfRange::check(
            "process_max_skew_ms",
            self.process_max_skew_ms as f64,
            0.0,
            MAX_PROCESS_SKEW_MS as f64,
        )?;
        let safe = if self.safe_position_pct < 0.0 {
            None
        } else {
            OutOfRange::check("safe_position_pct", self.safe_position_pct, 0.0, 100.0)?;
            Some(self.safe_position_pct)
        };
        OutOfRange::check(
            "safe_after_ms",
            self.safe_after_ms as f64,
            0.0,
            MAX_PROCESS_TIMEOUT_MS as f64,
        )?;
        if self.control == Control::Pid {
            if !self.process {
                return Err(ControlError::PidWithoutProcess);
            }
            if self.pid_kp == 0.0 && self.pid_ki == 0.0 {
                return Err(ControlError::PidWithoutGains);
            }
        }
        Ok(ControlConfig {
            params: self,
            gains: Gains {
                kp: self.pid_kp,
                ki: self.pid_ki,
                kd: self.pid_kd,
                d_filter_s: self.pid_d_filter_s,
            },
            sample: self.pid_sample_ms * NS_PER_MS,
            timeout: self.process_timeout_ms * NS_PER_MS,
            max_skew: self.process_max_skew_ms * NS_PER_MS,
            safe,
            safe_after: self.safe_after_ms * NS_PER_MS,
            smooth_s: if max_starts_per_h == 0 {
                0.0
            } else {
                1200.0 / max_starts_per_h as f64
            },
        })
    }
}

/// A manual command (`~/valve/NAME/manual`): the valve leaves automatic (the position commands
/// or the loop) and does what the operator says until `auto` (Siemens `PID_3Step`'s
/// `Manual_UP`, `Manual_DN` and `ManualValue`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Manual {
    /// Back to automatic, bumpless: the valve stays where it is until automatic moves it.
    Auto,
    /// Drive open, to the end (an end move).
    Open,
    /// Drive closed, to the end.
    Close,
    /// Stop where it is.
    Stop,
    /// Go to this position, percent (clamped to 0..100).
    Position(f64),
}

impl Manual {
    /// The word for the status: `auto`, `open`, `close`, `stop` or `position`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Manual::Auto => "auto",
            Manual::Open => "open",
            Manual::Close => "close",
            Manual::Stop => "stop",
            Manual::Position(_) => "position",
        }
    }
}

/// A manual command that is none of `auto`, `open`, `close`, `stop` or a finite number.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("manual `{0}` is none of auto, open, close, stop or a position in percent")]
pub struct BadManual(pub crate::core::config::ShortStr);

impl std::str::FromStr for Manual {
    type Err = BadManual;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let t = s.trim();
        Ok(match t {
            "auto" => Manual::Auto,
            "open" => Manual::Open,
            "close" => Manual::Close,
            "stop" => Manual::Stop,
            _ => {
                let number = t.strip_suffix('%').unwrap_or(t).trim();
                match number.parse::<f64>() {
                    Ok(v) if v.is_finite() => Manual::Position(v.clamp(0.0, 100.0)),
                    _ => return Err(BadManual(crate::core::config::ShortStr::new(t))),
                }
            }
        })
    }
}

/// What the loop is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LoopState {
    /// `control` `position`: no loop.
    #[default]
    Off,
    /// No setpoint yet: the valve holds.
    Waiting,
    /// The loop sets the valve.
    Running,
    /// No fresh process value for `process_timeout_ms`: the loop stopped, the valve holds.
    Holding,
    /// The loop held for `safe_after_ms`: the valve is at (or on its way to) the safe position.
    Safe,
    /// Manual mode.
    Manual,
    /// The valve cannot follow (the reference, a recalibration, the exercise stroke, the
    /// e-stop, the inactive lifecycle states, a fault): the loop waits, its integral held.
    Paused,
    /// No setpoint within `command_timeout_ms`: the valve's `on_timeout` acted.
    TimedOut,
}

impl LoopState {
    /// The word for the status: `off`, `waiting`, `running`, `holding`, `safe`, `manual`,
    /// `paused` or `timed_out`.
    pub const fn as_str(self) -> &'static str {
        match self {
            LoopState::Off => "off",
            LoopState::Waiting => "waiting",
            LoopState::Running => "running",
            LoopState::Holding => "holding",
            LoopState::Safe => "safe",
            LoopState::Manual => "manual",
            LoopState::Paused => "paused",
            LoopState::TimedOut => "timed_out",
        }
    }
}

/// Why an input of the valve was refused; the state in force stays.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ValveRefusal {
    /// A position command that is not a number.
    Command(crate::core::CommandError),
    /// A position command while the loop sets the target.
    PositionUnderPid,
    /// A position command in manual mode.
    PositionInManual,
    /// A setpoint while `control` is `position`.
    SetpointUnderPosition,
    /// A setpoint that is not finite or beyond [`MAX_PROCESS_VALUE`].
    BadSetpoint(f64),
    /// A process value that is not finite or beyond [`MAX_PROCESS_VALUE`].
    BadProcessValue(f64),
    /// A manual command while the e-stop is latched, the lines are held or a fault is latched.
    ManualHeld,
    /// A manual command that is none of the words nor a position.
    BadManual(BadManual),
}

/// Refused inputs of a valve since it was made, by kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Refused {
    /// Position commands: NaN, infinite, under `control` `pid`, in manual mode.
    pub position: u64,
    /// Setpoints: not finite, beyond [`MAX_PROCESS_VALUE`], under `control` `position`.
    pub setpoint: u64,
    /// Process values: not finite or beyond [`MAX_PROCESS_VALUE`].
    pub process_value: u64,
    /// Manual commands: no such word, or held by the e-stop, the lifecycle or a fault.
    pub manual: u64,
}

impl Refused {
    /// Counts `r` under its kind.
    pub fn count(&mut self, r: &ValveRefusal) {
        let n = match r {
            ValveRefusal::Command(_)
            | ValveRefusal::PositionUnderPid
            | ValveRefusal::PositionInManual => &mut self.position,
            ValveRefusal::SetpointUnderPosition | ValveRefusal::BadSetpoint(_) => {
                &mut self.setpoint
            }
            ValveRefusal::BadProcessValue(_) => &mut self.process_value,
            ValveRefusal::ManualHeld | ValveRefusal::BadManual(_) => &mut self.manual,
        };
        *n = n.saturating_add(1);
    }

    /// All of them.
    pub fn total(&self) -> u64 {
        self.position
            .saturating_add(self.setpoint)
            .saturating_add(self.process_value)
            .saturating_add(self.manual)
    }
}

impl fmt::Display for ValveRefusal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            ValveRefusal::Command(e) => write!(f, "position command refused: {e}"),
            ValveRefusal::PositionUnderPid => f.write_str(
                "position command refused: control is pid (the loop sets the target; use \
                 ~/valve/NAME/manual, or set control to position)",
            ),
            ValveRefusal::PositionInManual => f.write_str(
                "position command refused: the valve is in manual mode (send auto to \
                 ~/valve/NAME/manual first)",
            ),
            ValveRefusal::SetpointUnderPosition => {
                f.write_str("setpoint refused: control is position (set control to pid)")
            }
            ValveRefusal::BadSetpoint(v) => write!(
                f,
                "setpoint {v} refused: not finite or beyond ±{MAX_PROCESS_VALUE:e}; the \
                 setpoint in force stays"
            ),
            ValveRefusal::BadProcessValue(v) => write!(
                f,
                "process value {v} refused: not finite or beyond ±{MAX_PROCESS_VALUE:e}; it \
                 counts as no reading"
            ),
            ValveRefusal::ManualHeld => f.write_str(
                "manual command refused: the e-stop, the lifecycle or a fault holds the lines",
            ),
            ValveRefusal::BadManual(b) => write!(f, "manual command refused: {b}"),
        }
    }
}

/// What the loop tells the valve at a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Demand {
    /// Nothing changes.
    None,
    /// Position mode: the target, percent.
    Target(f64),
    /// Step mode: where the output stands in the frame of the valve's drives, percent.
    Step(f64),
    /// Stop where the valve is and hold.
    Hold,
    /// Go to the safe position, percent.
    Safe(f64),
}

/// What the loop needs to know of the valve at a sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct View {
    /// Step mode (else position mode).
    pub step: bool,
    /// Where the output stands for a bumpless start: position mode, the target in force or the
    /// estimate; step mode, the frame.
    pub start: f64,
    /// Step mode: the frame now (the stem displacement of the valve's drives).
    pub frame: f64,
    /// The stem's bounds, percent.
    pub low: f64,
    /// The high bound.
    pub high: f64,
    /// The valve follows the loop (live, no e-stop, no fault, no leg of its own).
    pub follows: bool,
    /// The valve is in manual mode.
    pub manual: bool,
    /// The command timeout acted and no setpoint came since.
    pub timed_out: bool,
}

/// The loop's report.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ControlStatus {
    /// Who sets the target.
    pub control: Control,
    /// What the output drives now (`Position` or `Step`); `Auto` under `control` `position`.
    pub output: LoopOutput,
    /// What the loop is doing.
    pub state: LoopState,
    /// The manual command in force, if the valve is in manual mode.
    pub manual: Option<Manual>,
    /// The setpoint, in the process's unit; NaN before the first.
    pub setpoint: f64,
    /// The last fresh process value; NaN before the first.
    pub process_value: f64,
    /// How old it is, ns; `None` before the first.
    pub process_age: Option<Nanos>,
    /// The PID's terms at the last sample, percent (step mode: in the frame of the drives).
    pub terms: Terms,
    /// Stale readings counted, and the age of the last one, ns (negative: from the future).
    pub stale: (u64, i64),
    /// The latest reading was stale.
    pub stale_now: bool,
    /// `process_timeout_ms` in force, ns.
    pub timeout: Nanos,
    /// `safe_position_pct` in force, percent; `None`: the valve holds.
    pub safe: Option<f64>,
    /// `safe_after_ms` in force, ns.
    pub safe_after: Nanos,
}

impl Default for ControlStatus {
    fn default() -> Self {
        ControlStatus {
            control: Control::Position,
            output: LoopOutput::Auto,
            state: LoopState::Off,
            manual: None,
            setpoint: f64::NAN,
            process_value: f64::NAN,
            process_age: None,
            terms: Terms::default(),
            stale: (0, 0),
            stale_now: false,
            timeout: DEFAULT_PROCESS_TIMEOUT_MS * NS_PER_MS,
            safe: None,
            safe_after: 0,
        }
    }
}

/// The loop (see the module documentation).
#[derive(Debug, Clone)]
pub(super) struct Loop {
    cfg: ControlConfig,
    pid: Pid,
    /// The smoothed output, percent.
    smooth: f64,
    setpoint: Option<f64>,
    /// The last fresh reading and when it came.
    reading: Option<(f64, Nanos)>,
    /// Before the first fresh reading the silence counts from here.
    expected_since: Nanos,
    stale: (u64, i64),
    stale_now: bool,
    next_sample: Option<Nanos>,
    last_sample: Option<Nanos>,
    /// When the reading the last sample used came.
    sampled_reading_at: Option<Nanos>,
    state: LoopState,
    /// Since when the loop holds for want of a fresh reading.
    hold_since: Option<Nanos>,
    /// The next sample starts afresh from where the valve stands.
    restart: bool,
}

impl Loop {
    /// A loop with `cfg` at `now`; under `pid` its first sample is due at once.
    pub(super) fn new(cfg: ControlConfig, now: Nanos) -> Loop {
        Loop {
            pid: Pid::new(cfg.gains),
            smooth: 0.0,
            setpoint: None,
            reading: None,
            expected_since: now,
            stale: (0, 0),
            stale_now: false,
            next_sample: (cfg.params.control == Control::Pid).then_some(now),
            last_sample: None,
            sampled_reading_at: None,
            state: LoopState::Off,
            hold_since: None,
            restart: true,
            cfg,
        }
    }

    /// Whether the loop sets the target (`control` `pid`).
    pub(super) fn on(&self) -> bool {
        self.cfg.params.control == Control::Pid
    }

    /// What the output drives, given whether the valve has a position feedback.
    pub(super) fn output(&self, feedback: bool) -> LoopOutput {
        match self.cfg.params.output {
            LoopOutput::Auto if feedback => LoopOutput::Position,
            LoopOutput::Auto => LoopOutput::Step,
            o => o,
        }
    }

    /// New settings at `now`: a switch to `pid` starts the loop bumplessly at the next call, a
    /// switch to `position` stops it (the target in force stays); a gain change is bumpless; a
    /// new sample counts from the last.
    pub(super) fn set_config(&mut self, now: Nanos, cfg: ControlConfig) {
        let old = self.cfg;
        self.cfg = cfg;
        match (old.params.control, cfg.params.control) {
            (Control::Position, Control::Pid) => {
                self.pid = Pid::new(cfg.gains);
                self.restart = true;
                self.next_sample = Some(now);
                self.last_sample = None;
                self.hold_since = None;
                if self.reading.is_none() {
                    self.expected_since = now;
                }
            }
            (Control::Pid, Control::Position) => {
                self.next_sample = None;
                self.state = LoopState::Off;
                self.hold_since = None;
            }
            (Control::Pid, Control::Pid) => {
                // The frame's limits are applied at the next sample; here only the output's
                // continuity matters.
                self.pid.set_gains(cfg.gains, -1e12, 1e12);
                if old.sample != cfg.sample {
                    let from = self.last_sample.unwrap_or(now);
                    self.next_sample = Some(from.saturating_add(cfg.sample).max(now));
                }
                if old.params.output != cfg.params.output {
                    self.restart = true;
                }
            }
            (Control::Position, Control::Position) => {}
        }
    }

    /// Makes a sample due at `now` (under `pid`): what the loop does follows a change of the
    /// valve's mode (manual mode, its end, a command timeout) at once, not a sample later.
    pub(super) fn sample_now(&mut self, now: Nanos) {
        if self.on() {
            self.next_sample = Some(now);
        }
    }

    /// When the next sample is due.
    pub(super) fn poll_at(&self) -> Option<Nanos> {
        self.next_sample.filter(|_| self.on())
    }

    /// A setpoint at `now`, in the process's unit.
    pub(super) fn set_setpoint(&mut self, value: f64) -> Result<(), ValveRefusal> {
        if !self.on() {
            return Err(ValveRefusal::SetpointUnderPosition);
        }
        if !value.is_finite() || value.abs() > MAX_PROCESS_VALUE {
            return Err(ValveRefusal::BadSetpoint(value));
        }
        self.setpoint = Some(value);
        Ok(())
    }

    /// A process value arriving at `now`, `age` ns after its stamp (`None`: unstamped;
    /// negative: stamped in the future). Stale readings are counted and used by nothing;
    /// values that are not finite or beyond [`MAX_PROCESS_VALUE`] are refused.
    pub(super) fn reading(
        &mut self,
        now: Nanos,
        value: f64,
        age: Option<i64>,
    ) -> Result<(), ValveRefusal> {
        if !self.cfg.params.process {
            return Ok(());
        }
        if let Some(age) = age {
            let too_old = age > 0 && age as u64 >= self.cfg.timeout;
            let ahead = age < 0 && age.unsigned_abs() > self.cfg.max_skew;
            if too_old || ahead {
                self.stale = (self.stale.0.saturating_add(1), age);
                self.stale_now = true;
                return Ok(());
            }
        }
        if !value.is_finite() || value.abs() > MAX_PROCESS_VALUE {
            return Err(ValveRefusal::BadProcessValue(value));
        }
        self.stale_now = false;
        self.reading = Some((value, now));
        Ok(())
    }

    /// The last fresh reading at `now`, if it is younger than `process_timeout_ms`.
    fn fresh(&self, now: Nanos) -> Option<(f64, Nanos)> {
        self.reading
            .filter(|(_, at)| now.saturating_sub(*at) < self.cfg.timeout)
    }

    /// One sample at `now` with the valve as `v` says: what the valve should do.
    pub(super) fn sample(&mut self, now: Nanos, v: &View) -> Demand {
        if !self.on() {
            self.next_sample = None;
            self.state = LoopState::Off;
            return Demand::None;
        }
        self.next_sample = Some(now.saturating_add(self.cfg.sample));
        let paused = if v.manual {
            Some(LoopState::Manual)
        } else if !v.follows {
            Some(LoopState::Paused)
        } else if v.timed_out {
            Some(LoopState::TimedOut)
        } else {
            None
        };
        if let Some(state) = paused {
            self.state = state;
            self.restart = true;
            self.hold_since = None;
            return Demand::None;
        }
        let Some(setpoint) = self.setpoint else {
            return self.hold(LoopState::Waiting);
        };
        let Some((value, read_at)) = self.fresh(now) else {
            let since = *self.hold_since.get_or_insert(now);
            if let Some(safe) = self.cfg.safe {
                if now >= since.saturating_add(self.cfg.safe_after) {
                    self.restart = true;
                    if self.state != LoopState::Safe {
                        self.state = LoopState::Safe;
                        return Demand::Safe(safe);
                    }
                    return Demand::None;
                }
            }
            return self.hold(LoopState::Holding);
        };
        self.hold_since = None;
        let (lo, hi) = if v.step {
            (v.frame - v.high, v.frame + (100.0 - v.low))
        } else {
            (0.0, 100.0)
        };
        if self.restart {
            let from = v.start.clamp(lo, hi);
            self.pid.start_from(from);
            self.smooth = from;
            self.last_sample = None;
            self.sampled_reading_at = None;
            self.restart = false;
        }
        let sample = self.cfg.sample;
        // After a pause the nominal sample, so the integral does not take the pause in one step.
        let dt = match self.last_sample {
            Some(last) if now.saturating_sub(last) <= 2 * sample => now.saturating_sub(last),
            _ => sample,
        };
        self.last_sample = Some(now);
        let reading_dt = match self.sampled_reading_at {
            Some(prev) if prev == read_at => None,
            Some(prev) => Some(read_at.saturating_sub(prev) as f64 / 1e9),
            None => Some(dt as f64 / 1e9),
        };
        self.sampled_reading_at = Some(read_at);
        // Reverse acting: the error's sign turns, the anti-windup and the derivative with it.
        let (sp, pv) = if self.cfg.params.pid_reverse {
            (-setpoint, -value)
        } else {
            (setpoint, value)
        };
        let dt_s = dt as f64 / 1e9;
        let out = self.pid.sample(sp, pv, reading_dt, dt_s, lo, hi).output;
        let a = if self.cfg.smooth_s > 0.0 {
            dt_s / (self.cfg.smooth_s + dt_s)
        } else {
            1.0
        };
        self.smooth = (self.smooth + a * (out - self.smooth)).clamp(lo, hi);
        self.state = LoopState::Running;
        if v.step {
            Demand::Step(self.smooth)
        } else {
            Demand::Target(self.smooth)
        }
    }

    /// The valve stopped following (the e-stop, the lifecycle, a fault): the loop waits and
    /// starts afresh afterwards.
    pub(super) fn pause(&mut self) {
        if self.on() {
            self.state = LoopState::Paused;
            self.restart = true;
            self.hold_since = None;
        }
    }

    /// Holds the valve (once, on entering `state`).
    fn hold(&mut self, state: LoopState) -> Demand {
        self.restart = true;
        if self.state == state {
            return Demand::None;
        }
        self.state = state;
        Demand::Hold
    }

    /// The report at `now`; `manual` and `output` as the valve knows them.
    pub(super) fn status(
        &self,
        now: Nanos,
        manual: Option<Manual>,
        output: LoopOutput,
    ) -> ControlStatus {
        ControlStatus {
            control: self.cfg.params.control,
            output: if self.on() { output } else { LoopOutput::Auto },
            state: if self.on() {
                self.state
            } else {
                LoopState::Off
            },
            manual,
            setpoint: self.setpoint.unwrap_or(f64::NAN),
            process_value: self.reading.map_or(f64::NAN, |(v, _)| v),
            process_age: self.reading.map(|(_, at)| now.saturating_sub(at)),
            terms: self.pid.terms(),
            stale: self.stale,
            stale_now: self.stale_now,
            timeout: self.cfg.timeout,
            safe: self.cfg.safe,
            safe_after: self.cfg.safe_after,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_commands_are_words_or_a_position() {
        assert_eq!("open".parse::<Manual>(), Ok(Manual::Open));
        assert_eq!(" stop ".parse::<Manual>(), Ok(Manual::Stop));
        assert_eq!("auto".parse::<Manual>(), Ok(Manual::Auto));
        assert_eq!("35.5".parse::<Manual>(), Ok(Manual::Position(35.5)));
        assert_eq!("35 %".parse::<Manual>(), Ok(Manual::Position(35.0)));
        assert_eq!("140".parse::<Manual>(), Ok(Manual::Position(100.0)));
        for bad in ["", "nan", "inf", "opne", "1e400"] {
            assert!(bad.parse::<Manual>().is_err(), "{bad}");
        }
    }

    #[test]
    fn pid_is_refused_without_a_process_value_or_gains() {
        let p = ControlParams {
            control: Control::Pid,
            pid_kp: 1.0,
            ..ControlParams::default()
        };
        assert_eq!(p.validate(0), Err(ControlError::PidWithoutProcess));
        let p = ControlParams {
            process: true,
            pid_kp: 0.0,
            ..p
        };
        assert_eq!(p.validate(0), Err(ControlError::PidWithoutGains));
        let p = ControlParams { pid_ki: 0.1, ..p };
        let c = p.validate(120).expect("valid");
        assert_eq!(c.smooth_s, 10.0);
        assert_eq!(p.validate(0).expect("valid").smooth_s, 0.0);
        let bad = ControlParams {
            safe_position_pct: 120.0,
            ..p
        };
        assert!(matches!(
            bad.validate(0),
            Err(ControlError::OutOfRange(OutOfRange {
                name: "safe_position_pct",
                ..
            }))
        ));
    }
}
