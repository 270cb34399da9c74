//! A three-point (floating) valve actuator as a sans-IO state machine: one line drives the motor
//! open, the other closed, and the position is known by counting the time each line was really
//! high against the actuator's travel time (Beckhoff `FB_BA_Anlg3Pnt`, Siemens `PID_3Step`,
//! Schneider `SERVO`, OSCAT `ACTUATOR_3P`), or read from an optional position feedback.
//!
//! Like the channel, it never reads a clock or writes an output: it is given `now` and inputs,
//! answers with edges ([`ValveEvent::Edge`]) and says when to call again ([`Valve::poll_at`]).
//! The edges pass its line guard (`lines`), which holds the rules about the lines themselves;
//! the estimate integrates the real edges, corrected by [`Valve::edge_written`].
//!
//! What the valve knows is an interval: the true position lies between a low and a high bound,
//! propagated through every drive with the worst the actuator may do (travel 10 % off, the
//! start lag off by its tolerance, the play between motor and stem). The estimate lies inside
//! it and the uncertainty is its distance to the farther bound, so "the true position is
//! within the uncertainty of the estimate" holds by construction, and an end is taken as a
//! reference only once the interval has closed on it.
//!
//! What it does, in the order it decides at each call:
//! - a latched fault (`motor_stalled`, `switch_implausible`, `travel_mismatch`) holds both
//!   lines low until [`Valve::reset`];
//! - a safety off (e-stop, lines not live) drops both lines at once; the valve stays where it is;
//! - a command timeout (`command_timeout_ms`) sets the target to where it is, 0 % or 100 %;
//! - a running move ends when its drive time is done, or is retargeted (extended, shortened to
//!   its minimum pulse before a reversal, turned into an end move);
//! - queued legs (the reference at start, a recalibration, the exercise stroke) run in order;
//! - otherwise the valve tracks the target: a move to 0 % or 100 % is an end move that drives
//!   past the end from anywhere the uncertainty allows, plus `end_overrun_pct`; a smaller
//!   difference than the dead band, or a drive shorter than the minimum pulse, waits
//!   (Schneider `SERVO`: short moves accumulate).

mod budget;
mod config;
pub mod control;
mod lines;
pub mod mixing;
pub mod truth;

pub use budget::{Budget, MAX_DEADBAND_FACTOR};
pub use config::{
    OnTimeout, ReferenceAtStart, ValveConfig, ValveConfigError, ValveParams,
    DEFAULT_MAX_STARTS_PER_H, MAX_BACKLASH_PCT, MAX_COMMAND_TIMEOUT_MS, MAX_DEADBAND_PCT,
    MAX_END_OVERRUN_PCT, MAX_EXERCISE_EVERY_H, MAX_FEEDBACK_TOLERANCE_PCT, MAX_RECALIBRATE_AFTER_S,
    MAX_REVERSAL_PAUSE_MS, MAX_STARTS_PER_H, MAX_START_LAG_PCT_OF_TRAVEL, MAX_TRAVEL_MS,
    MIN_REVERSAL_PAUSE_MS, MIN_TRAVEL_MS,
};
pub use control::{
    BadManual, Control, ControlConfig, ControlError, ControlParams, ControlStatus, LoopOutput,
    LoopState, Manual, Refused, ValveRefusal,
};
pub use lines::MIN_BREAK;

use super::board::{LineBoard, Seat};
use super::{Level, Nanos, NS_PER_MS};
use control::{Demand, Loop, View};
use lines::Lines;
use std::sync::Arc;

/// The share by which a real travel time may differ from the configured one, either way, as
/// OSCAT `ACTUATOR_3P` reports an error when open and close run times differ by more than 10 %.
/// A travel time 10 % short moves the valve 1/0.9 − 1 = 11.1 % further than estimated, one 10 %
/// long 1 − 1/1.1 = 9.1 % less.
pub const TRAVEL_TOLERANCE: f64 = 0.10;

/// The estimate's error per unit of run time over the travel time, at worst:
/// `TRAVEL_TOLERANCE / (1 - TRAVEL_TOLERANCE)`.
pub const UNCERTAINTY_RATE: f64 = TRAVEL_TOLERANCE / (1.0 - TRAVEL_TOLERANCE);

/// How far the real start lag (less the coast after a fall) may be from `start_lag_ms`, as a
/// share of it: a motor's start depends on its load, its supply and its temperature.
pub const START_LAG_TOLERANCE: f64 = 0.5;

/// How far the real start lag may be from `start_lag_ms` in any case, ns: a relay's operate and
/// release times and a triac's wait for the next zero crossing (10 ms at 50 Hz) are never
/// counted, so each drive may deliver up to this much more or less than counted.
pub const LAG_FLOOR: Nanos = 20 * NS_PER_MS;

/// A drive never lasts longer than this share of its travel time (Siemens `PID_3Step`'s virtual
/// actuator limit, 150 %); an unreferenced valve's end move drives exactly that.
pub const REFERENCE_FACTOR: f64 = 1.5;

/// With a recalibration due, a target within this many percent of an end counts as "near" it:
/// the valve goes to the end first, then back to the target.
pub const RECALIBRATE_NEAR_PCT: f64 = 5.0;

/// An end switch may close this far before the end, percent of the stroke: a switch active
/// while the valve cannot be that close to its end is `switch_implausible`.
pub const SWITCH_ZONE_PCT: f64 = 3.0;

/// After an end move towards a wired end switch has run its whole drive, its switch has this
/// long to report before the move counts as `motor_stalled` (debounce, reader thread, queue),
/// ns.
pub const SWITCH_GRACE: Nanos = 200 * NS_PER_MS;

/// While a line is high the valve asks to be polled at least this often, so its snapshot (and
/// the state file made from it) follows the move, ns.
pub const REPORT_EVERY: Nanos = 250 * NS_PER_MS;

/// A feedback sample is taken to show the position at most this long before it arrives (the
/// sensor's sampling, its node and the transport), ns: the stall check counts drive time only
/// up to this long before a sample, and the estimate is corrected from a sample only once the
/// lines have been low this long.
pub const FEEDBACK_DELAY: Nanos = 500 * NS_PER_MS;

/// Without a feedback sample for this long the feedback is silent: the valve goes on by its
/// drive times alone and the diagnostics warn, ns.
pub const FEEDBACK_TIMEOUT: Nanos = 2_000 * NS_PER_MS;

/// The feedback must move at least this far (or twice its tolerance, if more) in the drive's
/// direction once the drive was long enough to move a healthy valve twice as far, percent:
/// otherwise the motor is stalled.
pub const STALL_MOVE_MIN_PCT: f64 = 2.0;

/// Feedback values beyond the stroke by more than this are refused as a broken sensor (a
/// potentiometer reads slightly beyond its ends), percent.
pub const FEEDBACK_SLACK_PCT: f64 = 10.0;

/// A move measures the travel time (with feedback) only when it displaced the valve at least
/// this far, rest to rest, away from both ends, percent.
pub const TRAVEL_SAMPLE_MIN_PCT: f64 = 20.0;

/// A direction of drive, and its line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Dir {
    /// The opening line; towards 100 %.
    Open,
    /// The closing line; towards 0 %.
    Close,
}

impl Dir {
    /// Both directions, opening first.
    pub const BOTH: [Dir; 2] = [Dir::Open, Dir::Close];

    /// 0 for open, 1 for close.
    pub const fn index(self) -> usize {
        match self {
            Dir::Open => 0,
            Dir::Close => 1,
        }
    }

    /// The other direction.
    pub const fn other(self) -> Dir {
        match self {
            Dir::Open => Dir::Close,
            Dir::Close => Dir::Open,
        }
    }

    /// +1 opening, −1 closing.
    pub const fn sign(self) -> f64 {
        match self {
            Dir::Open => 1.0,
            Dir::Close => -1.0,
        }
    }

    /// The end this direction drives to, percent.
    pub const fn end_pct(self) -> f64 {
        match self {
            Dir::Open => 100.0,
            Dir::Close => 0.0,
        }
    }
}

/// What the valve tells its driver.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ValveEvent {
    /// Line `dir` goes to `level` at `at` (scheduled, monotonic ns).
    Edge {
        /// Which line.
        dir: Dir,
        /// The level.
        level: Level,
        /// When, ns.
        at: Nanos,
    },
}

/// Which way the motor runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Motion {
    /// Both lines low.
    #[default]
    Stopped,
    /// The opening line is high.
    Opening,
    /// The closing line is high.
    Closing,
}

/// What the valve is doing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Activity {
    /// Following the target.
    #[default]
    Tracking,
    /// The reference at start: closing for 150 % of the travel time.
    Referencing,
    /// A recalibration: an end move long enough to cover the uncertainty.
    Recalibrating,
    /// The exercise stroke (anti-seize).
    Exercising,
}

/// Why a move to an end is made (every end move drives past the end from anywhere the
/// uncertainty allows, plus the overrun; a reference drives 150 %).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EndKind {
    /// A command at the end.
    Plain,
    /// A recalibration on the way to a target.
    Recalibrate,
    /// The exercise stroke.
    Exercise,
    /// The reference at start: 150 % of the travel time, whatever the estimate.
    Reference,
}

/// One piece of work.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Leg {
    /// Drive towards the target.
    Track,
    /// Drive to the end `dir` drives to.
    End(Dir, EndKind),
    /// Drive back to the target after the exercise stroke (still part of it).
    Return,
    /// A step pulse of the loop in step mode: towards its output in the frame of the drives.
    Step,
}

impl Leg {
    /// Follows the target.
    fn tracks(self) -> bool {
        matches!(self, Leg::Track | Leg::Return)
    }
}

/// A move: its direction, how long it drives from the line's real rise, and what it is for.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Move {
    dir: Dir,
    /// Drive time wanted from the real rise, ns.
    want: Nanos,
    leg: Leg,
    /// The target it was planned for (tracking moves), percent.
    aim: f64,
    /// The line rose.
    started: bool,
}

/// Legs waiting to run, first first; at most three (reference, then two exercise strokes).
#[derive(Debug, Clone, Copy, Default)]
struct Legs {
    legs: [Option<Leg>; 3],
}

impl Legs {
    fn push(&mut self, leg: Leg) {
        if let Some(slot) = self.legs.iter_mut().find(|l| l.is_none()) {
            *slot = Some(leg);
        }
    }

    fn push_front(&mut self, leg: Leg) {
        self.legs.rotate_right(1);
        self.legs[0] = Some(leg);
    }

    fn pop(&mut self) -> Option<Leg> {
        let first = self.legs[0].take();
        self.legs.rotate_left(1);
        first
    }

    fn is_empty(&self) -> bool {
        self.legs[0].is_none()
    }

    fn any(&self, f: impl Fn(Leg) -> bool) -> bool {
        self.legs.iter().flatten().any(|&l| f(l))
    }

    fn retain(&mut self, f: impl Fn(Leg) -> bool) {
        let mut kept = Legs::default();
        for l in self.legs.iter().flatten().copied().filter(|&l| f(l)) {
            kept.push(l);
        }
        *self = kept;
    }
}

/// Why a valve's motor is taken to be stalled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StallCause {
    /// An end move towards `dir` ran its whole drive and the end switch wired at that end did
    /// not report (OSCAT `ACTUATOR_3P`'s error).
    NoEndSwitch(Dir),
    /// A drive towards `dir` long enough to move a healthy valve `expected_pct` moved the
    /// feedback less than half of that.
    NoFeedbackMotion(Dir),
}

/// A latched valve fault: both lines are held low until [`Valve::reset`] clears it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ValveFault {
    /// The motor does not move the valve (a dead motor, a blown fuse, a seized valve, a broken
    /// wire to the motor).
    MotorStalled {
        /// What showed it.
        cause: StallCause,
        /// The drive time that should have moved it, after the start lag, ms.
        drive_ms: f64,
        /// How far the valve moved meanwhile (by the feedback; NaN without), percent.
        moved_pct: f64,
        /// How far a healthy valve moves at least in that drive, percent.
        expected_pct: f64,
    },
    /// An end switch active where the valve cannot be (beyond the uncertainty), or both
    /// switches active at once.
    SwitchImplausible {
        /// The switches (open, close) active when it latched.
        switches: [bool; 2],
        /// Where the valve could be then: the low and high bounds, percent.
        low_pct: f64,
        /// The high bound, percent.
        high_pct: f64,
    },
    /// A measured travel time differs from the configured one by more than
    /// [`TRAVEL_TOLERANCE`] (OSCAT `ACTUATOR_3P`).
    TravelMismatch {
        /// The direction measured.
        dir: Dir,
        /// The lowest and highest travel time the measurement allows, ms.
        measured_ms: [f64; 2],
        /// The configured one, ms.
        configured_ms: f64,
    },
}

impl ValveFault {
    /// The fault's name on `/diagnostics`: `motor_stalled`, `switch_implausible`,
    /// `travel_mismatch`.
    pub const fn name(&self) -> &'static str {
        match self {
            ValveFault::MotorStalled { .. } => "motor_stalled",
            ValveFault::SwitchImplausible { .. } => "switch_implausible",
            ValveFault::TravelMismatch { .. } => "travel_mismatch",
        }
    }
}

/// The answer to the reset with a ticket: cleared, or refused because the fault's cause lasts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResetAnswer {
    /// The ticket the reset came with.
    pub ticket: u32,
    /// The fault is cleared (or there was none).
    pub cleared: bool,
}

/// What the valve knows of its position from before it started: the state file of a previous
/// run, its bounds already grown by the time the node was down. In motor coordinates (see
/// [`ValveStatus::motor`]): the motor runs over `0..=100 + backlash_pct`, the stem lies within
/// `[motor - backlash_pct, motor]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Restored {
    /// The motor's estimate, percent.
    pub position_pct: f64,
    /// The lowest motor position possible, percent.
    pub low_pct: f64,
    /// The highest, percent.
    pub high_pct: f64,
}

/// What the valve is started with besides its settings.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ValveStart {
    /// The position restored from the state file, if any.
    pub restored: Option<Restored>,
    /// Which ends (open, close) have an end switch wired.
    pub switches_wired: [bool; 2],
    /// A position feedback is configured.
    pub feedback: bool,
}

/// A snapshot of a valve for the state topic and diagnostics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValveStatus {
    /// The estimated position now, percent (0 = closed).
    pub position_pct: f64,
    /// The lowest position the valve can be at now, percent.
    pub low_pct: f64,
    /// The highest position the valve can be at now, percent.
    pub high_pct: f64,
    /// The same knowledge in motor coordinates (estimate, low, high), percent of the stroke
    /// over `0..=100 + backlash_pct`: what the state file keeps, so a restart does not widen
    /// the bounds by the play.
    pub motor: [f64; 3],
    /// The target, percent; NaN before the first command.
    pub target_pct: f64,
    /// Which line drives.
    pub motion: Motion,
    /// What the valve is doing.
    pub activity: Activity,
    /// The estimate was set at a reference (the reference at start, an end move whose
    /// interval closed on the end, an end switch, the feedback, a restored position) and has
    /// not been lost since.
    pub referenced: bool,
    /// The position was restored from the state file at start and no reference came since.
    pub restored: bool,
    /// Accumulated drive time since the last reference, ns.
    pub run_since_reference: Nanos,
    /// How far the true position may be from the estimate, percent.
    pub uncertainty_pct: f64,
    /// The uncertainty the diagnostics accept (`max_uncertainty_pct` in force), percent.
    pub max_uncertainty_pct: f64,
    /// A recalibration is due.
    pub recalibration_due: bool,
    /// The command timeout acted and no command came since.
    pub timed_out: bool,
    /// The e-stop is latched.
    pub estop: bool,
    /// The lines may follow the valve (a managed node's ACTIVE state).
    pub live: bool,
    /// The end switches (open, close) are active.
    pub switches: [bool; 2],
    /// The latched fault, if any.
    pub fault: Option<ValveFault>,
    /// The answer to the last reset, if one came.
    pub reset: Option<ResetAnswer>,
    /// The last feedback sample, percent; NaN without feedback or while it is silent.
    pub feedback_pct: f64,
    /// A feedback is configured and has been silent for [`FEEDBACK_TIMEOUT`].
    pub feedback_silent: bool,
    /// Travel times measured with the feedback (open, close), ms; NaN until measured.
    pub measured_travel_ms: [f64; 2],
    /// Start lags measured with the feedback (open, close), ms; NaN until measured.
    pub measured_lag_ms: [f64; 2],
    /// Moves completed.
    pub moves: u64,
    /// Starts of the motor (rises of either line) since the valve was made.
    pub starts: u64,
    /// Starts within the last hour (the minute under way and the 60 before it).
    pub starts_last_hour: u64,
    /// The budget in force, starts an hour; 0 = none.
    pub max_starts_per_h: u64,
    /// The dead band in force, percent: `deadband_pct`, widened while the budget runs low.
    pub deadband_in_force_pct: f64,
    /// The loop (`control`), and the manual mode.
    pub control: ControlStatus,
    /// Inputs refused since the valve was made, by kind (position commands, setpoints, process
    /// values, manual commands).
    pub refused: Refused,
    /// The last refusal.
    pub last_refusal: Option<ValveRefusal>,
}

/// The stem's displacement the valve's drives gave, nominally (the configured travel times
/// and start lag), counted from the valve's creation and never clamped: the frame of the
/// loop's step mode, which needs no absolute position. The play is counted as the true valve
/// has it: after a reversal the motor turns `slack` before the stem follows.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Odo {
    /// The stem's displacement, percent.
    stem: f64,
    /// How far the motor may turn opening before the stem follows, percent: 0 with the play
    /// taken up on the opening side, `backlash_pct` on the closing side.
    slack_open: f64,
}

impl Odo {
    /// The motor's slack towards `d`, percent.
    fn slack(&self, d: Dir, backlash: f64) -> f64 {
        match d {
            Dir::Open => self.slack_open,
            Dir::Close => (backlash - self.slack_open).max(0.0),
        }
    }

    /// After a motor displacement of `motor` percent towards `d`.
    fn drove(self, d: Dir, motor: f64, backlash: f64) -> Odo {
        let slack = self.slack(d, backlash);
        let moved = (motor - slack).max(0.0);
        match d {
            Dir::Open => Odo {
                stem: self.stem + moved,
                slack_open: (self.slack_open - motor).max(0.0),
            },
            Dir::Close => Odo {
                stem: self.stem - moved,
                slack_open: (self.slack_open + motor).min(backlash),
            },
        }
    }
}

/// What the valve knows of its position, in motor coordinates: the motor's position `m`
/// runs over `0..=100 + backlash`, and the stem (the valve's position) lies within
/// `[m - backlash, m]` and within `0..=100`. Closing into the stop leaves `m = 0` and the stem
/// at 0; opening into it leaves `m = 100 + backlash` and the stem at 100.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Know {
    /// The nominal motor position, percent.
    est: f64,
    /// The lowest motor position possible, percent.
    lo: f64,
    /// The highest, percent.
    hi: f64,
}

/// One drive as written, for the stall check: direction, real rise, real fall (`None` while
/// the line is high).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Drive {
    dir: Dir,
    rose: Nanos,
    fell: Option<Nanos>,
}

/// The drives kept for the stall check.
const DRIVES: usize = 8;

/// Travel samples kept per direction.
const SAMPLES: usize = 8;

/// A stall check under way: drives towards `dir` from `since` on, the feedback `from` then.
#[derive(Debug, Clone, Copy, PartialEq)]
struct StallWindow {
    dir: Dir,
    since: Nanos,
    from: f64,
}

/// A feedback sample at rest and what drove the valve since: the start of a travel sample.
#[derive(Debug, Clone, Copy, PartialEq)]
struct RestMark {
    pct: f64,
    /// Drive time since, per direction, ns, and the number of drives.
    driven: [Nanos; 2],
    drives: u32,
}

/// One three-point valve.
#[derive(Debug, Clone)]
pub struct Valve {
    cfg: ValveConfig,
    lines: Lines,
    /// What is known at the last real fall or reference.
    know: Know,
    /// What was known when the line under way (or the last one) rose: an end move and a
    /// retarget are planned from there, and a fall reported late is integrated afresh.
    at_rise: Know,
    /// The last fall may still be corrected by its real write time (nothing changed the
    /// knowledge since).
    correctable: Option<(Dir, Nanos)>,
    target: Option<f64>,
    mv: Option<Move>,
    legs: Legs,
    referenced: bool,
    restored: bool,
    run_since_ref: Nanos,
    /// The valve sits at this end after an end move or switch (no end move to it again).
    at_end: Option<Dir>,
    last_command: Nanos,
    timed_out: bool,
    estop: bool,
    live: bool,
    /// False after an e-stop or a fault reset until the next command: nothing moves by itself.
    armed: bool,
    idle_since: Nanos,
    switches: [bool; 2],
    wired: [bool; 2],
    /// An end move towards this end ran its drive; its switch is due by then.
    awaiting_switch: Option<(Dir, Nanos, f64)>,
    fault: Option<ValveFault>,
    reset: Option<ResetAnswer>,
    feedback_on: bool,
    /// The last feedback sample: when it came, percent.
    fb: Option<(Nanos, f64)>,
    window: Option<StallWindow>,
    rest: Option<RestMark>,
    drives: [Option<Drive>; DRIVES],
    /// Travel samples per direction: (drive time, drives, displacement percent).
    samples: [[Option<(Nanos, u32, f64)>; SAMPLES]; 2],
    measured_travel: [f64; 2],
    measured_lag: [f64; 2],
    /// Consecutive travel samples outside the tolerance, per direction, and on which side.
    mismatches: [(u8, i8); 2],
    /// The last periodic report while driving.
    tick: Nanos,
    moves: u64,
    /// The motor's budget of starts.
    budget: Budget,
    /// A tracking move the budget (or the dead band it widened) holds back: when to look
    /// again.
    budget_wait: Option<Nanos>,
    /// The target cannot wait for the budget (the command timeout's end move, the safe
    /// position, manual moves).
    target_forced: bool,
    /// The valve's own loop.
    ctl: Loop,
    /// Step mode: where the loop's output stands in the frame of the drives ([`Odo`]).
    step_aim: Option<f64>,
    /// The manual command in force: the valve is in manual mode.
    manual: Option<Manual>,
    /// The stem's displacement by the drives, and at the last rise.
    odo: Odo,
    odo_at_rise: Odo,
    /// The last fall's drive, for the frame's correction by its real write time.
    odo_fix: Option<(Dir, Nanos)>,
    refused: Refused,
    last_refusal: Option<ValveRefusal>,
}

impl Valve {
    /// A stopped valve created at `now`, position unknown (0 % assumed, unreferenced); the
    /// reference at start as `reference_at_start` says. Its lines are live.
    pub fn new(cfg: ValveConfig, now: Nanos) -> Valve {
        Valve::start(cfg, now, ValveStart::default())
    }

    /// A stopped valve created at `now` with what `start` says: a restored position (taken as
    /// the valve's knowledge, referenced), the end switches wired, a feedback. The reference
    /// at start is queued as `reference_at_start` says (none with `skip_if_restored` and a
    /// restored position, none with `none`). Nothing rises before the reversal pause from
    /// `now` has passed: the lines may have been high until the node started.
    pub fn start(cfg: ValveConfig, now: Nanos, start: ValveStart) -> Valve {
        let b = cfg.backlash_pct;
        let mut legs = Legs::default();
        let restored = start.restored.and_then(|r| {
            let ok = [r.position_pct, r.low_pct, r.high_pct]
                .iter()
                .all(|v| v.is_finite() && (0.0..=100.0 + b).contains(v))
                && r.low_pct <= r.position_pct
                && r.position_pct <= r.high_pct;
            ok.then_some(r)
        });
        match cfg.reference_at_start {
            ReferenceAtStart::Close => legs.push(Leg::End(Dir::Close, EndKind::Reference)),
            ReferenceAtStart::Open => legs.push(Leg::End(Dir::Open, EndKind::Reference)),
            ReferenceAtStart::SkipIfRestored if restored.is_none() => {
                legs.push(Leg::End(Dir::Close, EndKind::Reference))
            }
            ReferenceAtStart::SkipIfRestored | ReferenceAtStart::None => {}
        }
        let know = match restored {
            Some(r) => Know {
                est: r.position_pct,
                lo: r.low_pct,
                hi: r.high_pct,
            },
            None => Know {
                est: 0.0,
                lo: 0.0,
                hi: 100.0 + b,
            },
        };
        Valve {
            lines: Lines::new(cfg.reversal_pause, cfg.min_pulse, now),
            cfg,
            know,
            at_rise: know,
            correctable: None,
            target: None,
            mv: None,
            legs,
            referenced: restored.is_some(),
            restored: restored.is_some(),
            run_since_ref: 0,
            at_end: None,
            last_command: now,
            timed_out: false,
            estop: false,
            live: true,
            armed: true,
            idle_since: now,
            switches: [false; 2],
            wired: start.switches_wired,
            awaiting_switch: None,
            fault: None,
            reset: None,
            feedback_on: start.feedback,
            fb: None,
            window: None,
            rest: None,
            drives: [None; DRIVES],
            samples: [[None; SAMPLES]; 2],
            measured_travel: [f64::NAN; 2],
            measured_lag: [f64::NAN; 2],
            mismatches: [(0, 0); 2],
            tick: now,
            moves: 0,
            budget: Budget::new(cfg.max_starts_per_h, now),
            budget_wait: None,
            target_forced: false,
            ctl: Loop::new(cfg.control, now),
            step_aim: None,
            manual: None,
            odo: Odo {
                stem: 0.0,
                slack_open: b / 2.0,
            },
            odo_at_rise: Odo {
                stem: 0.0,
                slack_open: b / 2.0,
            },
            odo_fix: None,
            refused: Refused::default(),
            last_refusal: None,
        }
    }

    /// Puts the valve's lines on the node's board as lines `open` and `close`, paired: the
    /// board refuses a rise while the partner is high, whatever asks for it. The two lines do
    /// not count against the board's `max_simultaneous_on`: a valve's drive cannot wait for a
    /// free slot without its end moves and its reference waiting without bound.
    pub fn seat_on(&mut self, board: &Arc<LineBoard>, open: usize, close: usize) {
        board.pair(open, close);
        board.exempt(open);
        board.exempt(close);
        self.lines.set_seats(
            Seat {
                board: Arc::clone(board),
                line: open,
            },
            Seat {
                board: Arc::clone(board),
                line: close,
            },
        );
    }

    /// The settings in force.
    pub fn config(&self) -> &ValveConfig {
        &self.cfg
    }

    /// New settings at `now`; a running move continues under them. A longer reversal pause or
    /// minimum pulse acts at once, a shorter one from the next fall or rise (the break or drive
    /// under way keeps the one in force at its edge); a new command timeout or exercise
    /// interval counts from `now`. The travel times, the backlash and `reference_at_start`
    /// are start-up settings: the ones in force stay.
    pub fn set_config(&mut self, now: Nanos, cfg: ValveConfig, emit: &mut dyn FnMut(ValveEvent)) {
        // A new command timeout or exercise interval counts from the change: switching one on
        // never makes the valve stroke at once for the time that passed before it.
        if cfg.command_timeout != self.cfg.command_timeout {
            self.last_command = now;
        }
        if cfg.exercise_every != self.cfg.exercise_every {
            self.idle_since = self.idle_since.max(now);
        }
        let keep = self.cfg;
        self.cfg = ValveConfig {
            travel: keep.travel,
            backlash_pct: keep.backlash_pct,
            reference_at_start: keep.reference_at_start,
            ..cfg
        };
        self.lines.set_timing(cfg.reversal_pause, cfg.min_pulse);
        self.budget.set_rate(cfg.max_starts_per_h, now);
        let was_pid = self.ctl.on();
        self.ctl.set_config(now, cfg.control);
        if was_pid != self.ctl.on() {
            // Either way the command timeout counts afresh: from position commands or
            // setpoints, from now.
            self.last_command = now;
            self.timed_out = false;
            if was_pid {
                // Back to position commands: the loop's last target stays until a command;
                // step mode had none, so the valve stays where it is.
                self.step_aim = None;
                self.target_forced = false;
            }
        }
        self.step(now, emit);
    }

    /// Counts a refused input and gives it back as the error.
    fn refuse(&mut self, r: ValveRefusal) -> Result<(), ValveRefusal> {
        self.refused.count(&r);
        self.last_refusal = Some(r);
        Err(r)
    }

    /// A position command at `now`, percent (0 = closed), clamped to 0..=100. NaN and
    /// infinities are refused and the target in force stays; so is every command while the loop
    /// sets the target (`control` `pid`) or the valve is in manual mode.
    pub fn command(
        &mut self,
        now: Nanos,
        pct: f64,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Result<(), ValveRefusal> {
        if pct.is_nan() {
            return self.refuse(ValveRefusal::Command(crate::core::CommandError::NotANumber));
        }
        if pct.is_infinite() {
            return self.refuse(ValveRefusal::Command(crate::core::CommandError::Infinite));
        }
        if self.manual.is_some() {
            return self.refuse(ValveRefusal::PositionInManual);
        }
        if self.ctl.on() {
            return self.refuse(ValveRefusal::PositionUnderPid);
        }
        self.target = Some(pct.clamp(0.0, 100.0));
        self.target_forced = false;
        self.take_command(now, emit);
        Ok(())
    }

    /// A command (a position, a setpoint) taken at `now`: it feeds the command timeout, arms
    /// the valve unless an e-stop or a fault holds it, and the valve steps at once.
    fn take_command(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        self.last_command = now;
        self.timed_out = false;
        if !self.estop && self.fault.is_none() {
            self.armed = true;
        }
        self.step(now, emit);
    }

    /// A setpoint for the loop at `now`, in the process's unit; refused under `control`
    /// `position`, when not finite or beyond ±1e9. Under `pid` it feeds the command timeout
    /// (as position commands do under `position`), and after an e-stop or a fault's reset it is
    /// the fresh command that lets the valve move again.
    pub fn setpoint(
        &mut self,
        now: Nanos,
        value: f64,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Result<(), ValveRefusal> {
        if let Err(r) = self.ctl.set_setpoint(value) {
            return self.refuse(r);
        }
        self.take_command(now, emit);
        Ok(())
    }

    /// A process value arriving at `now`, `age` ns after its stamp (`None`: unstamped;
    /// negative: stamped in the future): see the loop's freshness rule
    /// ([`control`]). The loop acts on it at its next sample.
    pub fn process_value(
        &mut self,
        now: Nanos,
        value: f64,
        age: Option<i64>,
    ) -> Result<(), ValveRefusal> {
        match self.ctl.reading(now, value, age) {
            Ok(()) => Ok(()),
            Err(r) => self.refuse(r),
        }
    }

    /// A manual command at `now` (`~/valve/NAME/manual`): `open`, `close`, `stop` or a
    /// position put the valve in manual mode — position commands and the loop are set aside,
    /// the motor budget does not hold the operator back (the starts are counted) — and `auto`
    /// returns bumplessly: the valve stays where manual mode left it until automatic moves it
    /// (the loop starts from there). Refused while the e-stop is latched, the lines are held
    /// or a fault is latched.
    pub fn manual(
        &mut self,
        now: Nanos,
        m: Manual,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Result<(), ValveRefusal> {
        if m == Manual::Auto {
            if self.manual.take().is_some() {
                self.last_command = now;
                self.timed_out = false;
                // The manual target stays (forced no longer): automatic takes over from it.
                self.target_forced = false;
                self.ctl.sample_now(now);
            }
            self.step(now, emit);
            return Ok(());
        }
        if self.estop || !self.live || self.fault.is_some() {
            return self.refuse(ValveRefusal::ManualHeld);
        }
        if self.manual.is_none() {
            self.ctl.sample_now(now);
        }
        self.manual = Some(m);
        self.armed = true;
        self.target_forced = true;
        self.step_aim = None;
        match m {
            Manual::Open => self.target = Some(100.0),
            Manual::Close => self.target = Some(0.0),
            Manual::Position(p) => self.target = Some(p.clamp(0.0, 100.0)),
            Manual::Stop | Manual::Auto => self.target = None,
        }
        self.step(now, emit);
        Ok(())
    }

    /// A manual command that is none of the words nor a position (`~/valve/NAME/manual`):
    /// counted with the refusals; nothing changes.
    pub fn manual_refused(&mut self, bad: BadManual) -> Result<(), ValveRefusal> {
        self.refuse(ValveRefusal::BadManual(bad))
    }

    /// Calls due deadlines at `now`.
    pub fn poll(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        self.step(now, emit);
    }

    /// When to poll next, if anything is scheduled (a move's end, a rise held by the pause, the
    /// command timeout, an end switch due, the periodic report while driving). A rise the board
    /// refuses has none: call [`Valve::poll`] after other lines fell (see
    /// [`Valve::rise_waiting`]).
    pub fn poll_at(&self) -> Option<Nanos> {
        if self.fault.is_some() {
            return None;
        }
        let switch_due = self.awaiting_switch.map(|(_, at, _)| at);
        if self.estop || !self.live {
            return switch_due;
        }
        let timeout = (self.cfg.command_timeout > 0 && !self.timed_out)
            .then(|| self.last_command.saturating_add(self.cfg.command_timeout));
        let sample = self.ctl.poll_at();
        let budget = self.budget_wait.filter(|_| self.mv.is_none());
        let mv = self.mv.and_then(|m| {
            if m.started {
                self.lines.rose(m.dir).map(|r| {
                    self.lines
                        .earliest_fall(m.dir, r.saturating_add(m.want))
                        .min(self.tick.saturating_add(REPORT_EVERY))
                })
            } else {
                self.lines.earliest_rise(m.dir, 0)
            }
        });
        // Idle with a leg queued (the reference at start): due at once.
        let leg =
            (self.mv.is_none() && !self.legs.is_empty() && self.armed).then_some(self.idle_since);
        [timeout, mv, leg, switch_due, sample, budget]
            .into_iter()
            .flatten()
            .min()
    }

    /// A move waits for its rise that the board, an end switch or a fall not yet reported holds
    /// (call [`Valve::poll`] after the next write).
    pub fn rise_waiting(&self) -> bool {
        self.mv.is_some_and(|m| {
            !m.started
                && self.live
                && !self.estop
                && self.fault.is_none()
                && self.lines.earliest_rise(m.dir, 0).is_none()
        })
    }

    /// The edge of line `dir` to `level` scheduled last reached the line at `actual` (the output
    /// thread's report): the estimate, the pause, the minimum pulse and the move's end count
    /// from there.
    pub fn edge_written(&mut self, dir: Dir, level: Level, actual: Nanos) {
        let Some(late) = self.lines.written(dir, level, actual) else {
            return;
        };
        if level.is_high() {
            if let Some(d) = self.drives.iter_mut().flatten().last() {
                if d.dir == dir && d.fell.is_none() {
                    d.rose = actual;
                }
            }
            return;
        }
        if let Some(d) = self.drives.iter_mut().flatten().last() {
            if d.dir == dir {
                d.fell = Some(actual);
            }
        }
        self.idle_since = actual;
        // The drive lasted `late` longer (or shorter): the drives' frame counts it whatever
        // else happened since.
        if let Some((d, drive)) = self.odo_fix.take() {
            if d == dir && late != 0 {
                let real = (i128::from(drive) + late).clamp(0, i128::from(Nanos::MAX)) as Nanos;
                self.odo =
                    self.odo_at_rise
                        .drove(dir, self.nominal(dir, real), self.cfg.backlash_pct);
            }
        }
        // The drive lasted `late` longer (or shorter) than integrated at the fall: integrated
        // afresh from what was known at its rise, unless something changed the knowledge since.
        if let Some((d, drive)) = self.correctable.take() {
            if d == dir && late != 0 {
                let real = (i128::from(drive) + late).clamp(0, i128::from(Nanos::MAX)) as Nanos;
                self.know = self.drove(self.at_rise, dir, real);
                self.run_since_ref =
                    (self.run_since_ref as i128 + late).clamp(0, i128::from(Nanos::MAX)) as Nanos;
                self.check_reached(dir);
                if let Some(r) = self.rest.as_mut() {
                    let k = dir.index();
                    r.driven[k] = (r.driven[k] as i128 + late).max(0) as Nanos;
                }
            }
        }
    }

    /// Latches (`true`) or releases the e-stop at `now`: latched, both lines go low at once and
    /// nothing rises; released, the valve waits for a fresh position command.
    pub fn set_estop(&mut self, now: Nanos, latched: bool, emit: &mut dyn FnMut(ValveEvent)) {
        if latched {
            self.safety_off(now, emit);
            self.armed = false;
            self.ctl.pause();
        }
        self.estop = latched;
    }

    /// Lets the lines follow the valve (`true`) or holds both low (a managed node's inactive
    /// states) at `now`; on release the valve resumes its work.
    pub fn set_live(&mut self, now: Nanos, live: bool, emit: &mut dyn FnMut(ValveEvent)) {
        if !live {
            self.safety_off(now, emit);
            self.ctl.pause();
        }
        self.live = live;
        self.step(now, emit);
    }

    /// The end switch of `dir` became `active` at `now`. Active where the valve can be (within
    /// [`SWITCH_ZONE_PCT`] of that end by its bounds), the drive in that direction stops at
    /// once and the valve is referenced at that end; no drive in that direction starts while it
    /// is active. Active where the valve cannot be, or together with the other switch:
    /// `switch_implausible`, latched.
    pub fn set_switch(
        &mut self,
        now: Nanos,
        dir: Dir,
        active: bool,
        emit: &mut dyn FnMut(ValveEvent),
    ) {
        self.switches[dir.index()] = active;
        self.lines.blocked[dir.index()] = active;
        if !active {
            self.step(now, emit);
            return;
        }
        if self.awaiting_switch.is_some_and(|(d, _, _)| d == dir) {
            self.awaiting_switch = None;
        }
        // The bounds now, the drive under way counted.
        let k = self.know_now(now);
        let (lo, hi) = self.stem_bounds(&k);
        let plausible = match dir {
            Dir::Open => hi >= 100.0 - SWITCH_ZONE_PCT,
            Dir::Close => lo <= SWITCH_ZONE_PCT,
        };
        let both = self.switches[dir.other().index()];
        if both || !plausible {
            self.latch(
                now,
                ValveFault::SwitchImplausible {
                    switches: self.switches,
                    low_pct: lo,
                    high_pct: hi,
                },
                emit,
            );
            return;
        }
        if self.lines.driving() == Some(dir.other()) {
            // Driving away from the end it marks: nothing to stop (it releases soon).
            self.step(now, emit);
            return;
        }
        if let Some(drive) = self.lines.fall(dir, now, true, emit) {
            self.after_fall(dir, drive);
            self.finish_move();
        }
        if self.mv.is_some_and(|m| m.dir == dir) {
            self.mv = None;
        }
        // The end is reached: a queued end move to it is done too.
        self.legs
            .retain(|l| !matches!(l, Leg::End(d, _) if d == dir));
        self.reach_end(dir);
        self.step(now, emit);
    }

    /// A position feedback sample at `now`, percent (0 = closed): values within
    /// [`FEEDBACK_SLACK_PCT`] beyond the stroke are clamped, others, NaN and infinities
    /// refused. It checks the drive for a stalled motor, corrects the estimate once the lines
    /// have been low for [`FEEDBACK_DELAY`] (the bounds are then the sample ± the feedback
    /// tolerance), and measures the travel times.
    pub fn feedback(
        &mut self,
        now: Nanos,
        pct: f64,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Result<(), crate::core::CommandError> {
        if pct.is_nan() {
            return Err(crate::core::CommandError::NotANumber);
        }
        if pct.is_infinite() || !(-FEEDBACK_SLACK_PCT..=100.0 + FEEDBACK_SLACK_PCT).contains(&pct) {
            return Err(crate::core::CommandError::Infinite);
        }
        let pct = pct.clamp(0.0, 100.0);
        self.feedback_on = true;
        self.fb = Some((now, pct));
        if self.fault.is_some() {
            return Ok(());
        }
        self.check_stall(now, pct, emit);
        if self.fault.is_some() {
            return Ok(());
        }
        let settled = self.lines.driving().is_none()
            && self
                .lines
                .fell
                .is_none_or(|f| now >= f.saturating_add(FEEDBACK_DELAY))
            && self.mv.is_none_or(|m| !m.started);
        if settled {
            self.measure_travel(now, pct, emit);
            if self.fault.is_some() {
                return Ok(());
            }
            let tol = self.cfg.feedback_tolerance_pct;
            let b = self.cfg.backlash_pct;
            let (lo, hi) = ((pct - tol).max(0.0), (pct + tol).min(100.0));
            self.set_know(Know {
                est: (pct + b / 2.0).clamp(lo, hi + b),
                lo,
                hi: hi + b,
            });
            self.referenced = true;
            self.restored = false;
            self.run_since_ref = 0;
            if self.at_end.is_some_and(|e| (e.end_pct() - pct).abs() > tol) {
                self.at_end = None;
            }
            if self.mv.is_some_and(|m| !m.started) {
                // Planned from what was known before: planned afresh.
                self.mv = None;
            }
        }
        self.step(now, emit);
        Ok(())
    }

    /// Clears the latched fault at `now` if its cause is gone (after `switch_implausible` both
    /// end switches must have released); the answer, with `ticket`, is in the next status. A cleared fault
    /// leaves the valve unreferenced, and nothing moves until a fresh position command.
    pub fn reset(&mut self, now: Nanos, ticket: u32, emit: &mut dyn FnMut(ValveEvent)) -> bool {
        // An implausible switch is not believed again before both have released: a cleared
        // fault leaves the valve unreferenced, where any switch would be plausible.
        let lasting = matches!(self.fault, Some(ValveFault::SwitchImplausible { .. }))
            && self.switches.iter().any(|&s| s);
        let cleared = !lasting;
        if cleared && self.fault.take().is_some() {
            self.lose_reference();
            self.armed = false;
            self.awaiting_switch = None;
            self.window = None;
            self.rest = None;
            self.samples = [[None; SAMPLES]; 2];
            self.mismatches = [(0, 0); 2];
            self.idle_since = now;
        }
        self.reset = Some(ResetAnswer { ticket, cleared });
        self.step(now, emit);
        cleared
    }

    /// The latched fault, if any.
    pub fn fault(&self) -> Option<ValveFault> {
        self.fault
    }

    /// The e-stop is latched.
    pub fn estopped(&self) -> bool {
        self.estop
    }

    /// An exercise stroke is running or queued.
    pub fn exercising(&self) -> bool {
        let ex = |l: Leg| matches!(l, Leg::End(_, EndKind::Exercise) | Leg::Return);
        self.mv.is_some_and(|m| ex(m.leg)) || self.legs.any(ex)
    }

    /// When an exercise stroke becomes due, if the valve is idle, armed and exercising is on.
    pub fn exercise_due_at(&self) -> Option<Nanos> {
        let idle = self.mv.is_none() && self.legs.is_empty();
        let ok = self.live && !self.estop && self.armed && self.fault.is_none();
        (self.cfg.exercise_every > 0 && idle && ok)
            .then(|| self.idle_since.saturating_add(self.cfg.exercise_every))
    }

    /// Starts the exercise stroke at `now`: closed to the end, open to the end, then back to
    /// the target (or to where it was, without one).
    pub fn start_exercise(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        if self.target.is_none() {
            self.target = Some(self.estimate(now));
        }
        self.legs.push(Leg::End(Dir::Close, EndKind::Exercise));
        self.legs.push(Leg::End(Dir::Open, EndKind::Exercise));
        self.legs.push(Leg::Return);
        self.step(now, emit);
    }

    /// The estimated position at `now`, percent.
    pub fn estimate(&self, now: Nanos) -> f64 {
        self.stem(&self.know_now(now))
    }

    /// The uncertainty of the estimate at `now`, percent: its distance to the farther bound.
    pub fn uncertainty_pct(&self, now: Nanos) -> f64 {
        let k = self.know_now(now);
        let (lo, hi) = self.stem_bounds(&k);
        let est = self.stem(&k);
        (est - lo).max(hi - est).clamp(0.0, 100.0)
    }

    /// A snapshot at `now`.
    pub fn status(&self, now: Nanos) -> ValveStatus {
        let motion = match self.lines.driving() {
            Some(Dir::Open) => Motion::Opening,
            Some(Dir::Close) => Motion::Closing,
            None => Motion::Stopped,
        };
        let leg = self.mv.map(|m| m.leg).or(self.legs.legs[0]);
        let activity = if self.exercising() {
            Activity::Exercising
        } else {
            match leg {
                Some(Leg::End(_, EndKind::Reference)) => Activity::Referencing,
                Some(Leg::End(_, EndKind::Recalibrate)) => Activity::Recalibrating,
                _ => Activity::Tracking,
            }
        };
        let k = self.know_now(now);
        let (lo, hi) = self.stem_bounds(&k);
        let fresh = self
            .fb
            .filter(|(t, _)| now < t.saturating_add(FEEDBACK_TIMEOUT));
        ValveStatus {
            position_pct: self.stem(&k),
            low_pct: lo,
            high_pct: hi,
            motor: [k.est, k.lo, k.hi],
            target_pct: self.target.unwrap_or(f64::NAN),
            motion,
            activity,
            referenced: self.referenced,
            restored: self.restored,
            run_since_reference: self.run_since_ref,
            uncertainty_pct: self.uncertainty_pct(now),
            max_uncertainty_pct: self.cfg.max_uncertainty_pct,
            recalibration_due: self.recalibration_due(now),
            timed_out: self.timed_out,
            estop: self.estop,
            live: self.live,
            switches: self.switches,
            fault: self.fault,
            reset: self.reset,
            feedback_pct: fresh.map_or(f64::NAN, |(_, p)| p),
            feedback_silent: self.feedback_on && fresh.is_none(),
            measured_travel_ms: self.measured_travel,
            measured_lag_ms: self.measured_lag,
            moves: self.moves,
            starts: self.budget.total(),
            starts_last_hour: self.budget.last_hour(now),
            max_starts_per_h: self.budget.per_h(),
            deadband_in_force_pct: self.deadband(now),
            control: self.ctl.status(now, self.manual, self.loop_output()),
            refused: self.refused,
            last_refusal: self.last_refusal,
        }
    }

    // ---- the loop and the budget -----------------------------------------------------------

    /// What the loop's output drives now.
    fn loop_output(&self) -> LoopOutput {
        self.ctl.output(self.feedback_on)
    }

    /// The dead band in force for a target that may wait, percent: widened while the budget
    /// runs low.
    fn deadband(&self, now: Nanos) -> f64 {
        self.cfg.deadband_pct * self.budget.deadband_factor(now)
    }

    /// Whether a tracking start that closes `diff` percent may be made at `now`: beyond the
    /// dead band in force and with the budget's leave (a forced target needs neither's). When
    /// only the budget holds it back, the next look is set for when it narrows.
    fn budget_allows(&mut self, now: Nanos, diff: f64) -> bool {
        if self.target_forced {
            return diff.abs() >= self.cfg.deadband_pct;
        }
        if diff.abs() >= self.deadband(now) && self.budget.allows(now) {
            return true;
        }
        if diff.abs() >= self.cfg.deadband_pct {
            self.budget_wait = self.budget.next_token_at(now);
        }
        false
    }

    /// The motor's nominal displacement of a drive of `drive` ns towards `d`, percent.
    fn nominal(&self, d: Dir, drive: Nanos) -> f64 {
        drive.saturating_sub(self.cfg.start_lag) as f64 / self.cfg.travel[d.index()] as f64 * 100.0
    }

    /// The drives' frame at `now`, the drive under way counted.
    fn odo_now(&self, now: Nanos) -> Odo {
        match self.lines.driving() {
            Some(d) => {
                let rose = self.lines.rose(d).unwrap_or(now);
                self.odo_at_rise.drove(
                    d,
                    self.nominal(d, now.saturating_sub(rose)),
                    self.cfg.backlash_pct,
                )
            }
            None => self.odo,
        }
    }

    /// What the loop sees of the valve at `now`.
    fn view(&self, now: Nanos) -> View {
        let k = self.know_now(now);
        let (low, high) = self.stem_bounds(&k);
        let step = self.loop_output() == LoopOutput::Step;
        let frame = self.odo_now(now).stem;
        // Legs of its own (the reference, a recalibration, the exercise stroke): the valve does
        // not follow the loop meanwhile.
        let own = |l: Leg| {
            matches!(
                l,
                Leg::Return
                    | Leg::End(
                        _,
                        EndKind::Reference | EndKind::Recalibrate | EndKind::Exercise
                    )
            )
        };
        let busy = self.mv.is_some_and(|m| own(m.leg)) || !self.legs.is_empty();
        View {
            step,
            start: if step {
                frame
            } else {
                self.target.unwrap_or_else(|| self.stem(&k))
            },
            frame,
            low,
            high,
            follows: self.live && !self.estop && self.fault.is_none() && self.armed && !busy,
            manual: self.manual.is_some(),
            timed_out: self.timed_out,
        }
    }

    /// Does what the loop asks at `now`.
    fn apply(&mut self, d: Demand) {
        match d {
            Demand::None => {}
            Demand::Target(t) => {
                self.target = Some(t.clamp(0.0, 100.0));
                self.target_forced = false;
                self.step_aim = None;
            }
            Demand::Step(aim) => {
                self.step_aim = Some(aim);
                self.target = None;
                self.target_forced = false;
            }
            Demand::Hold => {
                // No target: a move under way ends after its minimum pulse, none starts.
                self.target = None;
                self.step_aim = None;
                self.target_forced = false;
            }
            Demand::Safe(p) => {
                self.target = Some(p);
                self.target_forced = true;
                self.step_aim = None;
            }
        }
    }

    /// Step mode: the pulse towards `aim` (the frame), if one is worth a start at `now`:
    /// beyond the dead band in force, at least the minimum pulse, with the budget's leave, not
    /// towards an end the valve is at. After a reversal the pulse first takes up the play.
    fn plan_step(&mut self, now: Nanos, aim: f64) -> Option<Move> {
        let pending = aim - self.odo.stem;
        if pending == 0.0 {
            return None;
        }
        let d = if pending > 0.0 { Dir::Open } else { Dir::Close };
        if self.switches[d.index()] || self.at_end == Some(d) {
            return None;
        }
        let motor = pending.abs() + self.odo.slack(d, self.cfg.backlash_pct);
        let want = self.drive_for(d, motor);
        if want < self.cfg.min_pulse.max(1) || !self.budget_allows(now, pending) {
            return None;
        }
        Some(Move {
            dir: d,
            want: want.min(self.cap(d)),
            leg: Leg::Step,
            aim,
            started: false,
        })
    }

    /// Whether a recalibration is due: the valve is unreferenced, or the run time since the
    /// last reference reached `recalibrate_after_s`, or the uncertainty passed half of
    /// `max_uncertainty_pct`. The next target near an end then goes to that end first.
    pub fn recalibration_due(&self, now: Nanos) -> bool {
        !self.referenced
            || (self.cfg.recalibrate_after > 0 && self.run_since_ref >= self.cfg.recalibrate_after)
            || self.uncertainty_pct(now) > self.cfg.max_uncertainty_pct / 2.0
    }

    // ---- knowledge -------------------------------------------------------------------------

    /// The stem's estimate from motor knowledge `k`, percent.
    fn stem(&self, k: &Know) -> f64 {
        let b = self.cfg.backlash_pct;
        let (lo, hi) = self.stem_bounds(k);
        (k.est - b / 2.0).clamp(lo, hi)
    }

    /// The stem's bounds from motor knowledge `k`, percent.
    fn stem_bounds(&self, k: &Know) -> (f64, f64) {
        let b = self.cfg.backlash_pct;
        ((k.lo - b).clamp(0.0, 100.0), k.hi.clamp(0.0, 100.0))
    }

    /// The top of the motor's range, percent.
    fn top(&self) -> f64 {
        100.0 + self.cfg.backlash_pct
    }

    /// The real lag's tolerance, ns.
    fn lag_tolerance(&self) -> f64 {
        START_LAG_TOLERANCE * self.cfg.start_lag as f64 + LAG_FLOOR as f64
    }

    /// Knowledge `k` after a drive of `drive` ns (line high time) in `d`: the nominal estimate
    /// after the configured lag at the configured travel time; the bounds with the lag off by
    /// its tolerance and the travel time 10 % off, both the worse way; clamped to the range.
    fn drove(&self, k: Know, d: Dir, drive: Nanos) -> Know {
        let travel = self.cfg.travel[d.index()] as f64;
        let lag = self.cfg.start_lag as f64;
        let tol = self.lag_tolerance();
        let drive = drive as f64;
        let nominal = (drive - lag).max(0.0) / travel * 100.0;
        let least = (drive - lag - tol).max(0.0) / (travel * (1.0 + TRAVEL_TOLERANCE)) * 100.0;
        let most = (drive - lag + tol).max(0.0) / (travel * (1.0 - TRAVEL_TOLERANCE)) * 100.0;
        let top = self.top();
        let s = d.sign();
        let (near, far) = match d {
            Dir::Open => (least, most),
            Dir::Close => (most, least),
        };
        Know {
            est: (k.est + s * nominal).clamp(0.0, top),
            lo: (k.lo + s * near).clamp(0.0, top),
            hi: (k.hi + s * far).clamp(0.0, top),
        }
    }

    /// The knowledge at `now`, the drive under way counted.
    fn know_now(&self, now: Nanos) -> Know {
        match self.lines.driving() {
            Some(d) => {
                let rose = self.lines.rose(d).unwrap_or(now);
                self.drove(self.at_rise, d, now.saturating_sub(rose))
            }
            None => self.know,
        }
    }

    /// Replaces the knowledge (a reference, a switch, the feedback): a late fall reported
    /// afterwards no longer corrects it.
    fn set_know(&mut self, k: Know) {
        self.know = k;
        self.at_rise = k;
        self.correctable = None;
    }

    /// The valve no longer knows where it is.
    fn lose_reference(&mut self) {
        let est = self.know.est;
        self.set_know(Know {
            est,
            lo: 0.0,
            hi: self.top(),
        });
        self.referenced = false;
        self.restored = false;
        self.at_end = None;
    }

    /// The interval closed on the end `d` drives to: the valve is there, referenced.
    fn check_reached(&mut self, d: Dir) {
        let reached = match d {
            Dir::Open => self.know.lo >= self.top() - 1e-9,
            Dir::Close => self.know.hi <= 1e-9,
        };
        if reached {
            self.reach_end(d);
        }
    }

    /// The valve is at end `d` (the interval closed on it, or its switch): referenced there.
    fn reach_end(&mut self, d: Dir) {
        let at = match d {
            Dir::Open => self.top(),
            Dir::Close => 0.0,
        };
        self.set_know(Know {
            est: at,
            lo: at,
            hi: at,
        });
        self.at_end = Some(d);
        self.referenced = true;
        self.restored = false;
        self.run_since_ref = 0;
    }

    /// A drive of `drive` ns in `d` fell: integrated into the knowledge, the run time, the
    /// travel sample under way.
    fn after_fall(&mut self, d: Dir, drive: Nanos) {
        if let Some(x) = self.drives.iter_mut().flatten().last() {
            if x.dir == d && x.fell.is_none() {
                x.fell = Some(x.rose.saturating_add(drive));
            }
        }
        self.know = self.drove(self.at_rise, d, drive);
        self.correctable = Some((d, drive));
        self.odo = self
            .odo_at_rise
            .drove(d, self.nominal(d, drive), self.cfg.backlash_pct);
        self.odo_fix = Some((d, drive));
        self.run_since_ref = self.run_since_ref.saturating_add(drive);
        if let Some(r) = self.rest.as_mut() {
            r.driven[d.index()] = r.driven[d.index()].saturating_add(drive);
            r.drives += 1;
        }
        self.check_reached(d);
    }

    /// A line rose: what was known then is where the move counts from.
    fn after_rise(&mut self, d: Dir, now: Nanos) {
        self.at_rise = self.know;
        self.correctable = None;
        self.odo_at_rise = self.odo;
        self.odo_fix = None;
        self.budget.start(now);
        self.at_end = None;
        self.tick = now;
        self.drives.rotate_left(1);
        self.drives[DRIVES - 1] = Some(Drive {
            dir: d,
            rose: now,
            fell: None,
        });
        if let Some((_, pct)) = self.fresh_feedback(now) {
            if self.window.is_none_or(|w| w.dir != d) {
                self.window = Some(StallWindow {
                    dir: d,
                    since: now,
                    from: pct,
                });
            }
        }
    }

    fn fresh_feedback(&self, now: Nanos) -> Option<(Nanos, f64)> {
        self.fb
            .filter(|(t, _)| now < t.saturating_add(FEEDBACK_TIMEOUT))
    }

    // ---- faults ----------------------------------------------------------------------------

    /// Latches `fault` at `now`: both lines low at once, the moves dropped, nothing moves until
    /// the reset. Every fault says the drive times did not move the valve as counted (or a
    /// switch contradicts them): the position is no longer known.
    fn latch(&mut self, now: Nanos, fault: ValveFault, emit: &mut dyn FnMut(ValveEvent)) {
        self.safety_off(now, emit);
        self.ctl.pause();
        self.lose_reference();
        self.legs = Legs::default();
        self.mv = None;
        self.awaiting_switch = None;
        if self.fault.is_none() {
            self.fault = Some(fault);
        }
        self.armed = false;
    }

    /// Drive time towards `d` after the start lag within `from..to`, ns, from the drives kept.
    fn effective_drive(&self, d: Dir, from: Nanos, to: Nanos) -> Nanos {
        let lag = self.cfg.start_lag;
        self.drives
            .iter()
            .flatten()
            .filter(|x| x.dir == d)
            .map(|x| {
                let a = x.rose.saturating_add(lag).max(from);
                let b = x.fell.unwrap_or(to).min(to);
                b.saturating_sub(a)
            })
            .sum()
    }

    /// How far the feedback must move in a stall window, percent.
    fn stall_move(&self) -> f64 {
        STALL_MOVE_MIN_PCT.max(2.0 * self.cfg.feedback_tolerance_pct)
    }

    /// The drive after the lag that moves a healthy valve `pct` percent towards `d` at least,
    /// from anywhere (the play taken up first, the travel 10 % long, the lag at its worst), ns.
    fn drive_that_moves(&self, d: Dir, pct: f64) -> Nanos {
        let travel = self.cfg.travel[d.index()] as f64;
        let b = self.cfg.backlash_pct;
        ((pct + b) / 100.0 * travel * (1.0 + TRAVEL_TOLERANCE) + self.lag_tolerance()) as Nanos
    }

    /// The stall check at a feedback sample `pct` at `now`.
    fn check_stall(&mut self, now: Nanos, pct: f64, emit: &mut dyn FnMut(ValveEvent)) {
        let dir = self
            .lines
            .driving()
            .or_else(|| self.drives.iter().flatten().last().map(|x| x.dir));
        let Some(d) = dir else { return };
        let Some(w) = self.window.filter(|w| w.dir == d) else {
            self.window = Some(StallWindow {
                dir: d,
                since: now,
                from: pct,
            });
            return;
        };
        let moved = (pct - w.from) * d.sign();
        let need = self.stall_move();
        if moved >= need {
            self.window = Some(StallWindow {
                dir: d,
                since: now,
                from: pct,
            });
            return;
        }
        let expected = 2.0 * need;
        let room = (d.end_pct() - w.from).abs();
        if room < 2.0 * expected {
            // Close to the end it drives to: the stop may hold it.
            return;
        }
        let judged = now.saturating_sub(FEEDBACK_DELAY);
        // Each drive of the window may have lost its lag's tolerance.
        let drives = self
            .drives
            .iter()
            .flatten()
            .filter(|x| x.dir == d && x.fell.is_none_or(|f| f > w.since) && x.rose < judged)
            .count()
            .max(1);
        let bound = self.drive_that_moves(d, expected)
            + (self.lag_tolerance() * (drives - 1) as f64) as Nanos;
        let drive = self.effective_drive(d, w.since, judged);
        if drive >= bound {
            self.latch(
                now,
                ValveFault::MotorStalled {
                    cause: StallCause::NoFeedbackMotion(d),
                    drive_ms: drive as f64 / 1e6,
                    moved_pct: moved,
                    expected_pct: expected,
                },
                emit,
            );
        }
    }

    /// A settled feedback sample `pct` at `now`: a travel sample from the last rest mark, if
    /// the valve moved one way far enough away from both ends; then a new rest mark.
    fn measure_travel(&mut self, now: Nanos, pct: f64, emit: &mut dyn FnMut(ValveEvent)) {
        let mark = self.rest.replace(RestMark {
            pct,
            driven: [0; 2],
            drives: 0,
        });
        let Some(m) = mark else { return };
        let tol = self.cfg.feedback_tolerance_pct;
        let margin = tol + SWITCH_ZONE_PCT;
        let inside = |p: f64| p > margin && p < 100.0 - margin;
        let delta = pct - m.pct;
        let d = if delta > 0.0 { Dir::Open } else { Dir::Close };
        let one_way = m.driven[d.other().index()] == 0 && m.driven[d.index()] > 0;
        if !(one_way && inside(m.pct) && inside(pct) && delta.abs() >= TRAVEL_SAMPLE_MIN_PCT) {
            return;
        }
        let k = d.index();
        let drive = m.driven[k];
        self.samples[k].rotate_left(1);
        self.samples[k][SAMPLES - 1] = Some((drive, m.drives, delta.abs()));
        self.fit(d);
        // The travel times this sample allows: the displacement off by the feedback's
        // tolerance at both ends and the play, the lag off by its tolerance in each drive.
        let n = f64::from(m.drives.max(1));
        let lag = self.cfg.start_lag as f64 * n;
        let lag_tol = self.lag_tolerance() * n;
        let b = self.cfg.backlash_pct;
        let eff = drive as f64 - lag;
        let lowest = (eff - lag_tol).max(0.0) / (delta.abs() + 2.0 * tol + b) * 100.0;
        let highest = (eff + lag_tol) / (delta.abs() - 2.0 * tol).max(1e-6) * 100.0;
        let travel = self.cfg.travel[k] as f64;
        let side = if lowest > travel * (1.0 + TRAVEL_TOLERANCE) {
            1
        } else if highest < travel * (1.0 - TRAVEL_TOLERANCE) {
            -1
        } else {
            0
        };
        let (count, was) = self.mismatches[k];
        self.mismatches[k] = match side {
            0 => (0, 0),
            s if s == was => (count.saturating_add(1), s),
            s => (1, s),
        };
        // Two samples in a row on the same side: not a noisy reading.
        if self.mismatches[k].0 >= 2 {
            self.latch(
                now,
                ValveFault::TravelMismatch {
                    dir: d,
                    measured_ms: [lowest / 1e6, highest / 1e6],
                    configured_ms: travel / 1e6,
                },
                emit,
            );
        }
    }

    /// Fits the travel time and the start lag of direction `d` to its single-drive samples
    /// (displacement = (drive − lag) / travel, least squares), once three with drives at
    /// least a fifth of the travel time apart are there.
    fn fit(&mut self, d: Dir) {
        let k = d.index();
        let pts: Vec<(f64, f64)> = self.samples[k]
            .iter()
            .flatten()
            .filter(|s| s.1 == 1)
            .map(|&(drive, _, pct)| (drive as f64, pct / 100.0))
            .collect();
        let n = pts.len() as f64;
        if pts.len() < 3 {
            return;
        }
        let (mx, my) = (
            pts.iter().map(|p| p.0).sum::<f64>() / n,
            pts.iter().map(|p| p.1).sum::<f64>() / n,
        );
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
        let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        let spread = pts.iter().map(|p| p.0).fold(f64::MIN, f64::max)
            - pts.iter().map(|p| p.0).fold(f64::MAX, f64::min);
        if sxx <= 0.0 || spread < self.cfg.travel[k] as f64 / 5.0 {
            return;
        }
        let slope = sxy / sxx;
        if slope <= 0.0 {
            return;
        }
        let intercept = my - slope * mx;
        self.measured_travel[k] = 1.0 / slope / 1e6;
        self.measured_lag[k] = (-intercept / slope / 1e6).max(0.0);
    }

    // ---- motion ----------------------------------------------------------------------------

    fn finish_move(&mut self) {
        self.moves += 1;
    }

    /// Both lines low at once; a reference interrupted runs again later, other legs are
    /// dropped.
    fn safety_off(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        if let Some(d) = self.lines.driving() {
            if let Some(drive) = self.lines.fall(d, now, true, emit) {
                self.after_fall(d, drive);
                self.idle_since = now;
            }
        }
        let reference = self.mv.and_then(|m| match m.leg {
            Leg::End(d, EndKind::Reference) => Some(d),
            _ => None,
        });
        self.mv = None;
        self.legs
            .retain(|l| matches!(l, Leg::End(_, EndKind::Reference)));
        if let Some(d) = reference {
            if self.legs.is_empty() && !self.referenced {
                self.legs.push_front(Leg::End(d, EndKind::Reference));
            }
        }
    }

    /// Decides at `now`.
    fn step(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        if self.fault.is_some() {
            return;
        }
        if let Some((d, at, expected)) = self.awaiting_switch {
            if now >= at && !self.switches[d.index()] {
                let drive = self.drives.iter().flatten().last().map_or(0, |x| {
                    x.fell
                        .unwrap_or(now)
                        .saturating_sub(x.rose.saturating_add(self.cfg.start_lag))
                });
                self.latch(
                    now,
                    ValveFault::MotorStalled {
                        cause: StallCause::NoEndSwitch(d),
                        drive_ms: drive as f64 / 1e6,
                        moved_pct: f64::NAN,
                        expected_pct: expected,
                    },
                    emit,
                );
                return;
            }
        }
        if self.estop || !self.live {
            return;
        }
        if self.lines.driving().is_some() && now >= self.tick.saturating_add(REPORT_EVERY) {
            self.tick = now;
        }
        self.check_timeout(now);
        if self.ctl.poll_at().is_some_and(|t| now >= t) {
            let v = self.view(now);
            let d = self.ctl.sample(now, &v);
            self.apply(d);
        }
        self.budget_wait = None;
        // A few rounds: a move ends and the next one is queued in the same call.
        for _ in 0..8 {
            match self.mv {
                Some(m) if m.started => {
                    if !self.run_move(now, m, emit) {
                        return;
                    }
                }
                Some(m) if m.leg.tracks() && self.target != Some(m.aim) => {
                    // Retargeted before the line rose: planned afresh.
                    self.mv = None;
                }
                Some(m) if m.leg == Leg::Step && self.step_aim != Some(m.aim) => {
                    self.mv = None;
                }
                Some(m) => {
                    if !self.lines.rise(m.dir, now, emit) {
                        return;
                    }
                    if let Some(mv) = self.mv.as_mut() {
                        mv.started = true;
                    }
                    self.after_rise(m.dir, now);
                }
                None => {
                    if !self.next_move(now) {
                        return;
                    }
                }
            }
        }
    }

    fn check_timeout(&mut self, now: Nanos) {
        let due = self.cfg.command_timeout > 0
            && !self.timed_out
            && now >= self.last_command.saturating_add(self.cfg.command_timeout);
        if !due {
            return;
        }
        self.timed_out = true;
        self.ctl.sample_now(now);
        self.target_forced = true;
        self.step_aim = None;
        self.target = match self.cfg.on_timeout {
            // Under the loop the valve may not know where it is (step mode): it stops
            // without a target rather than aim at a guess.
            OnTimeout::Stop if self.ctl.on() => None,
            OnTimeout::Stop => Some(self.estimate(now)),
            OnTimeout::Close => Some(0.0),
            OnTimeout::Open => Some(100.0),
        };
    }

    /// The longest drive in `d`, ns: 150 % of its travel time.
    fn cap(&self, d: Dir) -> Nanos {
        (self.cfg.travel[d.index()] as f64 * REFERENCE_FACTOR) as Nanos
    }

    /// The started move `m` at `now`: retargets a tracking move, ends it when its drive is
    /// done. Returns whether it ended (the caller looks for the next).
    fn run_move(&mut self, now: Nanos, mut m: Move, emit: &mut dyn FnMut(ValveEvent)) -> bool {
        let Some(rose) = self.lines.rose(m.dir) else {
            self.mv = None;
            return true;
        };
        let elapsed = now.saturating_sub(rose);
        let halted = match m.leg {
            // An end move for a target (a command or a manual open or close at the end, or a
            // recalibration on the way to a target) stops with it: a manual stop, a hold.
            Leg::Track | Leg::End(_, EndKind::Plain | EndKind::Recalibrate) => {
                self.target.is_none()
            }
            Leg::Step => self.step_aim.is_none(),
            _ => false,
        };
        if halted {
            // Nothing to aim at any more (a hold, a manual stop, a switch of mode): the move
            // ends once it has driven its minimum pulse.
            let want = m.want.min(elapsed.max(self.cfg.min_pulse));
            if want != m.want {
                m.want = want;
                self.mv = Some(m);
            }
        } else if m.leg == Leg::Step {
            if let Some(aim) = self.step_aim.filter(|&a| a != m.aim) {
                let d = m.dir;
                let left = (aim - self.odo_at_rise.stem) * d.sign();
                let want = if left > 0.0 {
                    self.drive_for(d, left + self.odo_at_rise.slack(d, self.cfg.backlash_pct))
                } else {
                    0
                };
                m.want = want.max(elapsed).max(self.cfg.min_pulse).min(self.cap(d));
                m.aim = aim;
                self.mv = Some(m);
            }
        }
        let retarget = self.target.filter(|&t| m.leg.tracks() && t != m.aim);
        if let Some(target) = retarget {
            if target == m.dir.end_pct() {
                // The target went to the end this move drives to: an end move from its rise.
                let kind = if self.recalibration_due(now) {
                    EndKind::Recalibrate
                } else {
                    EndKind::Plain
                };
                m = Move {
                    want: self.end_drive(m.dir, &self.at_rise).max(elapsed),
                    leg: Leg::End(m.dir, kind),
                    aim: target,
                    ..m
                };
            } else {
                let left = (target + self.cfg.backlash_pct / 2.0 - self.at_rise.est) * m.dir.sign();
                let want = if left > 0.0 {
                    self.drive_for(m.dir, left)
                } else {
                    0
                };
                m.want = want
                    .max(elapsed)
                    .max(self.cfg.min_pulse)
                    .min(self.cap(m.dir));
                m.aim = target;
            }
            self.mv = Some(m);
        }
        let end = self.lines.earliest_fall(m.dir, rose.saturating_add(m.want));
        if now < end {
            return false;
        }
        let Some(drive) = self.lines.fall(m.dir, end, false, emit) else {
            return false;
        };
        self.after_fall(m.dir, drive);
        self.idle_since = end;
        self.finish_move();
        self.mv = None;
        if let Leg::End(d, _) = m.leg {
            if self.wired[d.index()] && !self.switches[d.index()] {
                // The end switch there must have closed by now: the drive reached the end from
                // the farthest the valve could have been.
                let (lo, hi) = self.stem_bounds(&self.at_rise);
                let far = match d {
                    Dir::Open => 100.0 - lo,
                    Dir::Close => hi,
                };
                self.awaiting_switch = Some((d, end.saturating_add(SWITCH_GRACE), far));
            }
        }
        true
    }

    /// Drive time for `pct` percent of the motor's travel in `d`, the start lag included, ns.
    fn drive_for(&self, d: Dir, pct: f64) -> Nanos {
        let travel = self.cfg.travel[d.index()] as f64;
        (pct.max(0.0) / 100.0 * travel).round() as Nanos + self.cfg.start_lag
    }

    /// The drive of an end move in `d` from knowledge `k`, ns: from the bound farthest from
    /// that end to past it at the slowest travel time and the longest lag, plus the overrun;
    /// 150 % of the travel time when unreferenced; never more.
    fn end_drive(&self, d: Dir, k: &Know) -> Nanos {
        let cap = self.cap(d);
        if !self.referenced {
            return cap;
        }
        let travel = self.cfg.travel[d.index()] as f64;
        let dist = match d {
            Dir::Open => self.top() - k.lo,
            Dir::Close => k.hi,
        };
        let need = dist.max(0.0) / 100.0 * travel * (1.0 + TRAVEL_TOLERANCE)
            + self.lag_tolerance()
            + self.cfg.start_lag as f64
            + self.cfg.end_overrun_pct / 100.0 * travel;
        (need.ceil() as Nanos).min(cap)
    }

    /// Picks the next move when none runs; returns whether one was set.
    fn next_move(&mut self, now: Nanos) -> bool {
        if !self.armed {
            return false;
        }
        let leg = match self.legs.pop() {
            Some(Leg::Return) => {
                let Some(target) = self.target else {
                    return true;
                };
                match self.plan_track(now, target, false) {
                    Some(Leg::Track) => Leg::Return,
                    Some(leg) => leg,
                    None => return true,
                }
            }
            Some(leg) => leg,
            None => {
                if let Some(aim) = self.step_aim {
                    return match self.plan_step(now, aim) {
                        Some(m) => {
                            self.mv = Some(m);
                            true
                        }
                        None => false,
                    };
                }
                let Some(target) = self.target else {
                    return false;
                };
                match self.plan_track(now, target, true) {
                    Some(leg) => leg,
                    None => return false,
                }
            }
        };
        let m = match leg {
            Leg::Step => return false,
            Leg::End(d, kind) => {
                if self.switches[d.index()] {
                    // Already at that end, by its switch.
                    self.reach_end(d);
                    return true;
                }
                if kind == EndKind::Reference {
                    // The reference at start always drives its 150 %.
                    self.lose_reference_keep_estimate();
                }
                Move {
                    dir: d,
                    want: self.end_drive(d, &self.know),
                    leg,
                    aim: d.end_pct(),
                    started: false,
                }
            }
            Leg::Track | Leg::Return => {
                let Some(target) = self.target else {
                    return false;
                };
                let goal = target + self.cfg.backlash_pct / 2.0;
                let d = if goal > self.know.est {
                    Dir::Open
                } else {
                    Dir::Close
                };
                Move {
                    dir: d,
                    want: self
                        .drive_for(d, (goal - self.know.est).abs())
                        .max(self.cfg.min_pulse)
                        .min(self.cap(d)),
                    leg,
                    aim: target,
                    started: false,
                }
            }
        };
        if self.switches[m.dir.index()] {
            return false;
        }
        self.mv = Some(m);
        true
    }

    /// Before the reference at start: whatever was restored, the stroke counts from nothing.
    fn lose_reference_keep_estimate(&mut self) {
        if self.referenced && self.restored {
            self.lose_reference();
        }
    }

    /// What tracking `target` at `now` asks for: an end move, a recalibration first, a move, or
    /// nothing (within the dead band, shorter than the minimum pulse, at the end already, or —
    /// `gated` — held back by the motor budget).
    fn plan_track(&mut self, now: Nanos, target: f64, gated: bool) -> Option<Leg> {
        let due = self.recalibration_due(now);
        let start_allowed = |v: &mut Valve| {
            if !gated || v.target_forced || v.budget.allows(now) {
                return true;
            }
            v.budget_wait = v.budget.next_token_at(now);
            false
        };
        for d in Dir::BOTH {
            if target == d.end_pct() {
                if self.at_end == Some(d) || !start_allowed(self) {
                    return None;
                }
                let kind = if due {
                    EndKind::Recalibrate
                } else {
                    EndKind::Plain
                };
                return Some(Leg::End(d, kind));
            }
            if due && (target - d.end_pct()).abs() <= RECALIBRATE_NEAR_PCT && self.at_end != Some(d)
            {
                if !start_allowed(self) {
                    return None;
                }
                // To the end first; back to the target once there.
                return Some(Leg::End(d, EndKind::Recalibrate));
            }
        }
        let goal = target + self.cfg.backlash_pct / 2.0;
        let err = goal - self.know.est;
        if err.abs() < self.cfg.deadband_pct || err == 0.0 {
            return None;
        }
        let d = if err > 0.0 { Dir::Open } else { Dir::Close };
        let drive = self.drive_for(d, err.abs());
        if drive < self.cfg.min_pulse.max(1) {
            // Shorter than the minimum: the difference stays and grows with later commands.
            return None;
        }
        if gated && !self.budget_allows(now, err) {
            // The budget (or the dead band it widened) holds it back: it waits and adds up.
            return None;
        }
        // A move that would take the uncertainty past the limit recalibrates first, through the
        // end that makes the shorter way among those that keep it within the limit.
        if self.referenced {
            let limit = self.cfg.max_uncertainty_pct;
            let after = self.predict_unc(self.know, d, drive);
            if after > limit {
                let via =
                    |e: Dir| (self.know.est - e.end_pct()).abs() + (target - e.end_pct()).abs();
                let mut ends = Dir::BOTH;
                ends.sort_by(|a, b| via(*a).total_cmp(&via(*b)));
                for e in ends {
                    if self.at_end == Some(e) {
                        continue;
                    }
                    let at = if e == Dir::Open { self.top() } else { 0.0 };
                    let from_end = Know {
                        est: at,
                        lo: at,
                        hi: at,
                    };
                    let back = e.other();
                    let back_drive = self.drive_for(back, (goal - at).abs());
                    if self.predict_unc(from_end, back, back_drive) <= limit {
                        return Some(Leg::End(e, EndKind::Recalibrate));
                    }
                }
            }
        }
        Some(Leg::Track)
    }

    /// The uncertainty after a drive of `drive` ns in `d` from `k`, percent.
    fn predict_unc(&self, k: Know, d: Dir, drive: Nanos) -> f64 {
        let after = self.drove(k, d, drive);
        let (lo, hi) = self.stem_bounds(&after);
        let est = self.stem(&after);
        (est - lo).max(hi - est)
    }
}

/// The exercise strokes of a node's valves, one at a time (OSCAT `ACTUATOR_3P`'s `ARE`/`ARX`):
/// when none is exercising, the one due the longest starts at `now`. Events go to `emit` with the
/// valve's index.
pub fn exercise_turn(
    valves: &mut [Valve],
    now: Nanos,
    emit: &mut dyn FnMut(usize, ValveEvent),
) -> bool {
    if valves.iter().any(Valve::exercising) {
        return false;
    }
    let due = valves
        .iter()
        .enumerate()
        .filter_map(|(i, v)| v.exercise_due_at().map(|t| (t, i)))
        .filter(|&(t, _)| t <= now)
        .min();
    match due {
        Some((_, i)) => {
            valves[i].start_exercise(now, &mut |e| emit(i, e));
            true
        }
        None => false,
    }
}

/// When [`exercise_turn`] should next be called: the earliest exercise due, while none runs.
pub fn exercise_next(valves: &[Valve]) -> Option<Nanos> {
    if valves.iter().any(Valve::exercising) {
        return None;
    }
    valves.iter().filter_map(Valve::exercise_due_at).min()
}

#[cfg(test)]
mod loop_tests;
#[cfg(test)]
mod tests;
