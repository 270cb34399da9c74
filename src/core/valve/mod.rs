//! A three-point (floating) valve actuator as a sans-IO state machine: one line drives the motor
//! open, the other closed, and the position is known only by counting the time each line was
//! really high against the actuator's travel time (Beckhoff `FB_BA_Anlg3Pnt`, Siemens
//! `PID_3Step`, Schneider `SERVO`, OSCAT `ACTUATOR_3P`).
//!
//! Like the channel, it never reads a clock or writes an output: it is given `now` and inputs,
//! answers with edges ([`ValveEvent::Edge`]) and says when to call again ([`Valve::poll_at`]).
//! The edges pass its line guard (`lines`), which holds the rules about the lines themselves;
//! the estimate integrates the real edges, corrected by [`Valve::edge_written`].
//!
//! What it does, in the order it decides at each call:
//! - a safety off (e-stop, lines not live) drops both lines at once; the valve stays where it is;
//! - a command timeout (`command_timeout_ms`) sets the target to where it is, 0 % or 100 %;
//! - a running move ends when its drive time is done, or is retargeted (extended, shortened to
//!   its minimum pulse before a reversal, turned into an end move);
//! - queued legs (the reference at start, a recalibration, the exercise stroke) run in order;
//! - otherwise the valve tracks the target: a move to 0 % or 100 % is an end move that drives
//!   on past the end by `end_overrun_pct`; a smaller difference than the dead band, or a drive
//!   shorter than the minimum pulse, waits (Schneider `SERVO`: short moves accumulate).

mod config;
mod lines;

pub use config::{
    OnTimeout, ValveConfig, ValveConfigError, ValveParams, MAX_COMMAND_TIMEOUT_MS,
    MAX_DEADBAND_PCT, MAX_END_OVERRUN_PCT, MAX_EXERCISE_EVERY_H, MAX_RECALIBRATE_AFTER_S,
    MAX_REVERSAL_PAUSE_MS, MAX_TRAVEL_MS, MIN_TRAVEL_MS,
};
pub use lines::MIN_BREAK;

use super::board::{LineBoard, Seat};
use super::{Level, Nanos};
use lines::Lines;
use std::sync::Arc;

/// The share by which a real travel time may differ from the configured one, as OSCAT
/// `ACTUATOR_3P` reports an error when open and close run times differ by more than 10 %. A
/// travel time 10 % short moves the valve 1/0.9 − 1 = 11.1 % further than estimated, so the
/// uncertainty grows by [`UNCERTAINTY_RATE`] of the run time since the last reference.
pub const TRAVEL_TOLERANCE: f64 = 0.10;

/// The estimate's error per unit of run time over the travel time, at worst:
/// `TRAVEL_TOLERANCE / (1 - TRAVEL_TOLERANCE)`.
pub const UNCERTAINTY_RATE: f64 = TRAVEL_TOLERANCE / (1.0 - TRAVEL_TOLERANCE);

/// A reference move drives this share of the travel time (Siemens `PID_3Step`'s virtual
/// actuator limit, 150 %); no move is ever longer.
pub const REFERENCE_FACTOR: f64 = 1.5;

/// With a recalibration due, a target within this many percent of an end counts as "near" it:
/// the valve goes to the end first, then back to the target.
pub const RECALIBRATE_NEAR_PCT: f64 = 5.0;

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

/// Why a move to an end is made, which decides how long it drives past the estimated end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EndKind {
    /// A command at the end: `end_overrun_pct`.
    Plain,
    /// A recalibration: the overrun plus the uncertainty.
    Recalibrate,
    /// The exercise stroke: as a recalibration.
    Exercise,
    /// The reference: 150 % of the travel time, whatever the estimate.
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
    /// The uncertainty it covers when it reaches its end, percent (end moves).
    covers: f64,
    /// The uncertainty when it started, percent: an end move that covers it is a reference.
    needs: f64,
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

/// A snapshot of a valve for the state topic and diagnostics.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValveStatus {
    /// The estimated position now, percent (0 = closed).
    pub position_pct: f64,
    /// The target, percent; NaN before the first command.
    pub target_pct: f64,
    /// Which line drives.
    pub motion: Motion,
    /// What the valve is doing.
    pub activity: Activity,
    /// The estimate was set at a reference (the reference at start, an end move that covered
    /// the uncertainty, an end switch) and has not been lost since.
    pub referenced: bool,
    /// Accumulated drive time since the last reference, ns.
    pub run_since_reference: Nanos,
    /// How far the true position may be from the estimate, percent (100 when unreferenced).
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
    /// Moves completed.
    pub moves: u64,
}

/// One three-point valve.
#[derive(Debug, Clone)]
pub struct Valve {
    cfg: ValveConfig,
    lines: Lines,
    /// The estimate at the last real fall or reference, percent.
    pos: f64,
    target: Option<f64>,
    mv: Option<Move>,
    legs: Legs,
    referenced: bool,
    run_since_ref: Nanos,
    /// The valve sits at this end after an end move or switch (no end move to it again).
    at_end: Option<Dir>,
    last_command: Nanos,
    timed_out: bool,
    estop: bool,
    live: bool,
    /// False after an e-stop until the next command: nothing moves by itself after the reset.
    armed: bool,
    idle_since: Nanos,
    switches: [bool; 2],
    moves: u64,
}

impl Valve {
    /// A stopped valve created at `now`, position unknown (0 % assumed, unreferenced); with
    /// `reference_at_start` the reference is its first leg. Its lines are live.
    pub fn new(cfg: ValveConfig, now: Nanos) -> Valve {
        let mut legs = Legs::default();
        if cfg.reference_at_start {
            legs.push(Leg::End(Dir::Close, EndKind::Reference));
        }
        Valve {
            lines: Lines::new(cfg.reversal_pause, cfg.min_pulse),
            cfg,
            pos: 0.0,
            target: None,
            mv: None,
            legs,
            referenced: false,
            run_since_ref: 0,
            at_end: None,
            last_command: now,
            timed_out: false,
            estop: false,
            live: true,
            armed: true,
            idle_since: now,
            switches: [false; 2],
            moves: 0,
        }
    }

    /// Puts the valve's lines on the node's board as lines `open` and `close`, paired: the
    /// board refuses a rise while the partner is high, whatever asks for it.
    pub fn seat_on(&mut self, board: &Arc<LineBoard>, open: usize, close: usize) {
        board.pair(open, close);
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
    /// interval counts from `now`.
    pub fn set_config(&mut self, now: Nanos, cfg: ValveConfig, emit: &mut dyn FnMut(ValveEvent)) {
        // A new command timeout or exercise interval counts from the change: switching one on
        // never makes the valve stroke at once for the time that passed before it.
        if cfg.command_timeout != self.cfg.command_timeout {
            self.last_command = now;
        }
        if cfg.exercise_every != self.cfg.exercise_every {
            self.idle_since = self.idle_since.max(now);
        }
        self.cfg = cfg;
        self.lines.set_timing(cfg.reversal_pause, cfg.min_pulse);
        self.step(now, emit);
    }

    /// A position command at `now`, percent (0 = closed), clamped to 0..=100. NaN and
    /// infinities are refused and the target in force stays.
    pub fn command(
        &mut self,
        now: Nanos,
        pct: f64,
        emit: &mut dyn FnMut(ValveEvent),
    ) -> Result<(), crate::core::CommandError> {
        if pct.is_nan() {
            return Err(crate::core::CommandError::NotANumber);
        }
        if pct.is_infinite() {
            return Err(crate::core::CommandError::Infinite);
        }
        self.target = Some(pct.clamp(0.0, 100.0));
        self.last_command = now;
        self.timed_out = false;
        if !self.estop {
            self.armed = true;
        }
        self.step(now, emit);
        Ok(())
    }

    /// Calls due deadlines at `now`.
    pub fn poll(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        self.step(now, emit);
    }

    /// When to poll next, if anything is scheduled (a move's end, a rise held by the pause, the
    /// command timeout). A rise the board refuses has none: call [`Valve::poll`] after other
    /// lines fell (see [`Valve::rise_waiting`]).
    pub fn poll_at(&self) -> Option<Nanos> {
        if self.estop || !self.live {
            return None;
        }
        let timeout = (self.cfg.command_timeout > 0 && !self.timed_out)
            .then(|| self.last_command.saturating_add(self.cfg.command_timeout));
        let mv = self.mv.and_then(|m| {
            if m.started {
                self.lines
                    .rose(m.dir)
                    .map(|r| self.lines.earliest_fall(m.dir, r.saturating_add(m.want)))
            } else {
                self.lines.earliest_rise(m.dir, 0)
            }
        });
        // Idle with a leg queued (the reference at start): due at once.
        let leg =
            (self.mv.is_none() && !self.legs.is_empty() && self.armed).then_some(self.idle_since);
        let mv = match (leg, mv) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
        match (timeout, mv) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// A move waits for its rise that the board, an end switch or a fall not yet reported holds
    /// (call [`Valve::poll`] after the next write).
    pub fn rise_waiting(&self) -> bool {
        self.mv.is_some_and(|m| {
            !m.started && self.live && !self.estop && self.lines.earliest_rise(m.dir, 0).is_none()
        })
    }

    /// The edge of line `dir` to `level` scheduled last reached the line at `actual` (the output
    /// thread's report): the estimate, the pause, the minimum pulse and the move's end count
    /// from there.
    pub fn edge_written(&mut self, dir: Dir, level: Level, actual: Nanos) {
        let Some(late) = self.lines.written(dir, level, actual) else {
            return;
        };
        if !level.is_high() {
            // The drive lasted `late` longer (or shorter) than integrated at the fall.
            let late_ns = late.clamp(-(i64::MAX as i128), i64::MAX as i128) as f64;
            self.integrate(dir, late_ns);
            self.idle_since = actual;
        }
    }

    /// Latches (`true`) or releases the e-stop at `now`: latched, both lines go low at once and
    /// nothing rises; released, the valve waits for a fresh position command.
    pub fn set_estop(&mut self, now: Nanos, latched: bool, emit: &mut dyn FnMut(ValveEvent)) {
        if latched {
            self.safety_off(now, emit);
            self.armed = false;
        }
        self.estop = latched;
    }

    /// Lets the lines follow the valve (`true`) or holds both low (a managed node's inactive
    /// states) at `now`; on release the valve resumes its work.
    pub fn set_live(&mut self, now: Nanos, live: bool, emit: &mut dyn FnMut(ValveEvent)) {
        if !live {
            self.safety_off(now, emit);
        }
        self.live = live;
        self.step(now, emit);
    }

    /// The end switch of `dir` became `active` at `now`: active, the drive in that direction
    /// stops at once and the position is that end; no drive in that direction starts while it
    /// is active.
    pub fn set_switch(
        &mut self,
        now: Nanos,
        dir: Dir,
        active: bool,
        emit: &mut dyn FnMut(ValveEvent),
    ) {
        self.switches[dir.index()] = active;
        self.lines.blocked[dir.index()] = active;
        // Both ends at once cannot be: a wiring or switch fault. Nothing drives either way (each
        // switch blocks its direction) and the position is not known any more.
        let both = active && self.switches[dir.other().index()];
        if active && (both || self.lines.driving() != Some(dir.other())) {
            if let Some(drive) = self.lines.fall(dir, now, true, emit) {
                self.run_since_ref = self.run_since_ref.saturating_add(drive);
                self.finish_move();
            }
            if self.mv.is_some_and(|m| m.dir == dir) {
                self.mv = None;
            }
            // The end is reached: a queued end move to it is done too.
            self.legs
                .retain(|l| !matches!(l, Leg::End(d, _) if d == dir));
            if both {
                self.referenced = false;
                self.at_end = None;
            } else {
                self.reach_end(dir, true);
            }
        }
        self.step(now, emit);
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
        (self.cfg.exercise_every > 0 && idle && self.live && !self.estop && self.armed)
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
        match self.lines.driving() {
            Some(d) => {
                let rose = self.lines.rose(d).unwrap_or(now);
                let ran = now.saturating_sub(rose) as f64;
                self.moved(self.pos, d, ran)
            }
            None => self.pos,
        }
    }

    /// The uncertainty of the estimate, percent: 100 while unreferenced, else
    /// [`UNCERTAINTY_RATE`] of the run time since the last reference over the shorter travel
    /// time (the worst case).
    pub fn uncertainty_pct(&self) -> f64 {
        if !self.referenced {
            return 100.0;
        }
        let shorter = self.cfg.travel[0].min(self.cfg.travel[1]) as f64;
        (UNCERTAINTY_RATE * self.run_since_ref as f64 / shorter * 100.0).min(100.0)
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
        ValveStatus {
            position_pct: self.estimate(now),
            target_pct: self.target.unwrap_or(f64::NAN),
            motion,
            activity,
            referenced: self.referenced,
            run_since_reference: self.run_since_ref,
            uncertainty_pct: self.uncertainty_pct(),
            max_uncertainty_pct: self.cfg.max_uncertainty_pct,
            recalibration_due: self.recalibration_due(),
            timed_out: self.timed_out,
            estop: self.estop,
            live: self.live,
            switches: self.switches,
            moves: self.moves,
        }
    }

    /// Whether the accumulated run time since the last reference asks for a recalibration.
    pub fn recalibration_due(&self) -> bool {
        self.cfg.recalibrate_after > 0 && self.run_since_ref >= self.cfg.recalibrate_after
    }

    /// `pos` moved by `ran` ns of drive in `d`, clamped to the stroke.
    fn moved(&self, pos: f64, d: Dir, ran: f64) -> f64 {
        let travel = self.cfg.travel[d.index()] as f64;
        (pos + d.sign() * ran / travel * 100.0).clamp(0.0, 100.0)
    }

    /// Adds `ran` ns of drive in `d` to the estimate and the run time.
    fn integrate(&mut self, d: Dir, ran: f64) {
        self.pos = self.moved(self.pos, d, ran);
        let run = self.run_since_ref as f64 + ran;
        self.run_since_ref = run.max(0.0) as Nanos;
    }

    /// Both lines low at once; a reference interrupted runs again later, other legs are
    /// dropped.
    fn safety_off(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        if let Some(d) = self.lines.driving() {
            if let Some(drive) = self.lines.fall(d, now, true, emit) {
                self.integrate(d, drive as f64);
                self.idle_since = now;
            }
        }
        let reference = self
            .mv
            .is_some_and(|m| m.leg == Leg::End(Dir::Close, EndKind::Reference));
        self.mv = None;
        self.legs
            .retain(|l| l == Leg::End(Dir::Close, EndKind::Reference));
        if reference && self.legs.is_empty() {
            self.legs
                .push_front(Leg::End(Dir::Close, EndKind::Reference));
        }
    }

    /// The valve is at end `d`: the estimate is that end; `exact` (a switch, or an end move
    /// that covered the uncertainty) makes it a reference.
    fn reach_end(&mut self, d: Dir, exact: bool) {
        self.pos = d.end_pct();
        self.at_end = Some(d);
        if exact {
            self.referenced = true;
            self.run_since_ref = 0;
        }
    }

    fn finish_move(&mut self) {
        self.moves += 1;
    }

    /// Decides at `now`.
    fn step(&mut self, now: Nanos, emit: &mut dyn FnMut(ValveEvent)) {
        if self.estop || !self.live {
            return;
        }
        self.check_timeout(now);
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
                Some(m) => {
                    if !self.lines.rise(m.dir, now, emit) {
                        return;
                    }
                    if let Some(mv) = self.mv.as_mut() {
                        mv.started = true;
                    }
                    self.at_end = None;
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
        self.target = Some(match self.cfg.on_timeout {
            OnTimeout::Stop => self.estimate(now),
            OnTimeout::Close => 0.0,
            OnTimeout::Open => 100.0,
        });
    }

    /// The started move `m` at `now`: retargets a tracking move, ends it when its drive is
    /// done. Returns whether it ended (the caller looks for the next).
    fn run_move(&mut self, now: Nanos, mut m: Move, emit: &mut dyn FnMut(ValveEvent)) -> bool {
        let Some(rose) = self.lines.rose(m.dir) else {
            self.mv = None;
            return true;
        };
        let elapsed = now.saturating_sub(rose);
        let retarget = self.target.filter(|&t| m.leg.tracks() && t != m.aim);
        if let Some(target) = retarget {
            let est = self.estimate(now);
            if target == m.dir.end_pct() {
                // The target went to the end this move drives to: an end move from here.
                let kind = if self.recalibration_due() {
                    EndKind::Recalibrate
                } else {
                    EndKind::Plain
                };
                let (want, covers) = self.end_drive(m.dir, est, kind);
                m = Move {
                    want: elapsed + want,
                    leg: Leg::End(m.dir, kind),
                    covers,
                    needs: self.uncertainty_pct(),
                    aim: target,
                    ..m
                };
            } else {
                let left = (target - est) * m.dir.sign();
                let more = if left > 0.0 {
                    self.drive_for(m.dir, left)
                } else {
                    0
                };
                m.want = (elapsed + more).max(self.cfg.min_pulse);
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
        self.integrate(m.dir, drive as f64);
        self.idle_since = end;
        self.finish_move();
        self.mv = None;
        if let Leg::End(d, kind) = m.leg {
            let exact = kind == EndKind::Reference || m.covers >= m.needs;
            self.reach_end(d, exact);
        }
        true
    }

    /// Drive time for `pct` percent of the stroke in `d`, ns.
    fn drive_for(&self, d: Dir, pct: f64) -> Nanos {
        let travel = self.cfg.travel[d.index()] as f64;
        (pct.max(0.0) / 100.0 * travel).round() as Nanos
    }

    /// An end move in `d` from `est`: its drive time and the uncertainty it covers, percent.
    fn end_drive(&self, d: Dir, est: f64, kind: EndKind) -> (Nanos, f64) {
        let travel = self.cfg.travel[d.index()];
        let cap = (travel as f64 * REFERENCE_FACTOR) as Nanos;
        let dist = (d.end_pct() - est).abs();
        let overrun = match kind {
            EndKind::Plain => self.cfg.end_overrun_pct,
            EndKind::Recalibrate | EndKind::Exercise => {
                self.cfg.end_overrun_pct + self.uncertainty_pct()
            }
            EndKind::Reference => return (cap, 100.0),
        };
        let want = self.drive_for(d, dist + overrun).min(cap);
        let covers = (want as f64 / travel as f64 * 100.0 - dist).max(0.0);
        (want, covers)
    }

    /// Picks the next move when none runs; returns whether one was set.
    fn next_move(&mut self, now: Nanos) -> bool {
        if !self.armed {
            return false;
        }
        let est = self.estimate(now);
        let leg = match self.legs.pop() {
            Some(Leg::Return) => {
                let Some(target) = self.target else {
                    return true;
                };
                match self.plan_track(est, target) {
                    Some(Leg::Track) => Leg::Return,
                    Some(leg) => leg,
                    None => return true,
                }
            }
            Some(leg) => leg,
            None => {
                let Some(target) = self.target else {
                    return false;
                };
                match self.plan_track(est, target) {
                    Some(leg) => leg,
                    None => return false,
                }
            }
        };
        let m = match leg {
            Leg::End(d, kind) => {
                if self.switches[d.index()] {
                    if self.switches[d.other().index()] {
                        // Both switches: neither says where the valve is; nothing drives.
                        return false;
                    }
                    // Already at that end, by its switch.
                    self.reach_end(d, true);
                    return true;
                }
                let (want, covers) = self.end_drive(d, est, kind);
                Move {
                    dir: d,
                    want,
                    leg,
                    covers,
                    needs: self.uncertainty_pct(),
                    aim: d.end_pct(),
                    started: false,
                }
            }
            Leg::Track | Leg::Return => {
                let Some(target) = self.target else {
                    return false;
                };
                let d = if target > est { Dir::Open } else { Dir::Close };
                Move {
                    dir: d,
                    want: self
                        .drive_for(d, (target - est).abs())
                        .max(self.cfg.min_pulse),
                    leg,
                    covers: 0.0,
                    needs: 100.0,
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

    /// What tracking `target` from `est` asks for: an end move, a recalibration first, a move,
    /// or nothing (within the dead band, shorter than the minimum pulse, at the end already).
    fn plan_track(&mut self, est: f64, target: f64) -> Option<Leg> {
        let due = self.recalibration_due();
        for d in Dir::BOTH {
            if target == d.end_pct() {
                if self.at_end == Some(d) && !due {
                    return None;
                }
                let kind = if due {
                    EndKind::Recalibrate
                } else {
                    EndKind::Plain
                };
                return Some(Leg::End(d, kind));
            }
            if due && (target - d.end_pct()).abs() <= RECALIBRATE_NEAR_PCT {
                return Some(Leg::End(d, EndKind::Recalibrate));
            }
        }
        let err = target - est;
        if err.abs() < self.cfg.deadband_pct || err == 0.0 {
            return None;
        }
        let d = if err > 0.0 { Dir::Open } else { Dir::Close };
        if self.drive_for(d, err.abs()) < self.cfg.min_pulse.max(1) {
            // Shorter than the minimum: the difference stays and grows with later commands.
            return None;
        }
        Some(Leg::Track)
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
mod tests;
