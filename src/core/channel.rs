//! One PWM channel as a sans-IO state machine: given `now` and inputs, it answers with edges,
//! flags and status, and says when it next needs to be polled. It never reads a clock, sleeps,
//! or touches an output; the output thread and the tests drive it.
//!
//! Time runs in steps. An on step is followed by an off step; the decision point before an on
//! step starts a new period (000: "period duration unchanged"). Which command a step uses depends
//! on [`ApplyAt`]: the one latched at the period start (000), the one current when the step
//! starts (002), or the one current right now, extending or ending the running step (003).
//!
//! The steps are the schedule; the line is what was really written. A minimum on or off time
//! is a promise about the line: every change of level the schedule asks for passes a guard that
//! holds it back until the line has kept its level for its minimum, counted from the time the
//! last edge really happened (a late poll, or [`Channel::edge_written`], moves that time). Only
//! the safety offs act at once: a falling enable and a watchdog trip. The maximum on time is a
//! promise about the line too: a high phase is cut once it has lasted `max_on_ms` from its real
//! rise, and the schedule's next rise waits out the minimum break after the cut.
//!
//! With a time base every time the schedule plans with is a whole number of ticks
//! (the period, the on and off times, the minima, the maximum on time) and the line guard holds
//! every change of level until an instant of the tick grid (`k * tick` on the monotonic clock):
//! so every edge lies on the grid, and every pulse and break is whole ticks, whatever started
//! the schedule between two ticks (an enable, a release, a re-evaluation). Each period carries
//! the rounding remainder of its on time into the next (see [`Plan::carried`]). Only the safety
//! offs, a maximum on time overdue, and edges written late lie off the grid, by their lateness;
//! the next edge is back on it, its phase at least its minimum from the real edge — except the
//! end of a phase of exactly its minimum, which comes that minimum after the real edge, off the
//! grid by the same lateness, rather than a whole tick later (see `Channel::earliest`).
//!
//! Between a command and the plan lie the load's protections, each off by default:
//! the power limits (`max_duty_pct`, `min_duty_pct`, `zero_means_zero`) after clamping, the
//! dead band that ignores small changes, and the slew limit that moves the duty applied toward
//! the command at most at its rate, advanced at every decision point (a period or step start,
//! a re-evaluation) by the virtual time since the last one. After them, the rolling-average
//! cap keeps the line's on time over a window within its energy budget (see `budget`).
//!
//! The channel's state is kept in parts, each changed only through its own steps and each
//! checking its rule where it is kept (debug assertions, run by every test): the line and what
//! really happened on it (`Line`), the command watchdog (`Watchdog`: a fault value runs only
//! while tripped), the dead band (`DeadBand`: the ends always pass), the slew limit (`Slew`:
//! exact in virtual time), the time base's carried remainder (`Carry`: within half a tick),
//! the rolling-average budget (`budget::Budget`), the flags of this period and the one before
//! (`Marks`), where the running period and its on phase lie (`Placement`: no lead off the
//! stagger grid, a fixed end at or after the period's start), and the heater loop (`Heat`).
//! What is left on `Channel` itself is the configuration, the command, the gates (enable, the
//! emergency stop, the lifecycle) and the schedule: the step and the plan.

use super::board::{LineBoard, Seat};
use super::command::{Command, Duty};
use super::config::{ApplyAt, ChannelConfig, OnDisable};
use super::heater::Heat;
use super::plan::Plan;
use super::{Level, Nanos};

mod budget;
mod duty;
mod gates;
mod heat;
mod line;
mod placement;
mod report;
mod tune;
mod watchdog;

use duty::{DeadBand, Slew};
use placement::Placement;
use watchdog::Watchdog;

/// The earliest of `deadlines` (ns), if any. A plain loop: it is asked once per event, and the
/// virtual-time tests ask it for hours of events in unoptimised builds.
fn earliest(deadlines: &[Option<Nanos>]) -> Option<Nanos> {
    let mut first: Option<Nanos> = None;
    for &d in deadlines {
        if let Some(d) = d {
            if first.is_none_or(|f| d < f) {
                first = Some(d);
            }
        }
    }
    first
}

pub use report::{Event, Protections, Status};

/// The shortest stretch a heater's delivered duty is averaged over, ns.
const CHECK_WINDOW: Nanos = 1_000_000_000;

/// The running on or off step of the schedule.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Step {
    level: Level,
    start: Nanos,
    end: Nanos,
    kind: StepKind,
}

impl Step {
    /// An off step of `kind` from `start` to `end`.
    const fn off(kind: StepKind, start: Nanos, end: Nanos) -> Step {
        Step {
            level: Level::Low,
            start,
            end,
            kind,
        }
    }
}

/// What waiting for a slot (`max_simultaneous_on`, or a stagger group's line on) did to a
/// period's on phase, worst last.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Default)]
enum SlotUse {
    /// It started on time.
    #[default]
    None,
    /// It waited for a slot.
    Delayed,
    /// It was skipped: the duty was not delivered (E1).
    Skipped,
}

/// What happened to the line in the running period and in the one before, as the flags report
/// it: a mark made now stays visible through the next period, then goes.
#[derive(Debug, Clone, Copy, Default)]
struct Marks<T> {
    now: T,
    before: T,
}

impl<T: Ord + Copy + Default> Marks<T> {
    /// Marks the running period with `v`, keeping a higher mark made earlier in it.
    fn raise(&mut self, v: T) {
        self.now = self.now.max(v);
    }

    /// A period ends: its mark becomes the one before.
    fn roll(&mut self) {
        self.before = std::mem::take(&mut self.now);
    }

    /// No pulses run: no marks.
    fn clear(&mut self) {
        *self = Marks::default();
    }

    /// The higher mark of the two periods.
    fn recent(&self) -> T {
        self.now.max(self.before)
    }
}

/// With a time base: the rounding remainder of the on time carried from period to period,
/// ticks (see [`Plan::carried`]).
///
/// Rule, checked at every change: each remainder lies within half a tick, so the on time
/// delivered over any run stays within a tick of the one commanded.
#[derive(Debug, Clone, Copy, Default)]
struct Carry {
    /// The remainder the running period took in.
    taken: f64,
    /// The remainder the last plan made leaves for the next period.
    left: f64,
}

impl Carry {
    fn check(&self) {
        debug_assert!(
            self.taken.abs() <= 0.5 && self.left.abs() <= 0.5,
            "a remainder within half a tick: {self:?}"
        );
    }

    /// A period starts: it takes in what the last one left.
    fn period_starts(&mut self) {
        self.taken = self.left;
    }

    /// A plan for the running period leaves `left` (ticks).
    fn leave(&mut self, left: f64) {
        self.left = left;
        self.check();
    }

    /// A new run of periods (an enable): nothing is carried over from the last one.
    fn restart(&mut self) {
        self.left = 0.0;
    }

    /// The remainder the running period plans with.
    fn taken(&self) -> f64 {
        self.taken
    }
}

/// What a step is for, which decides what follows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
enum StepKind {
    /// An on step, or the off step that ends a period.
    #[default]
    Run,
    /// Off until the next instant of the stagger grid, where the first period starts.
    Align,
    /// Off at the start of a staggered period, until the on phase's place in it.
    Lead,
    /// Off while the on phase waits for a slot under `max_simultaneous_on`; at its end (the
    /// latest start that still fits the pulse in its period) the pulse is skipped.
    Wait,
}

/// The output line as written, and a change of level the guard is holding back.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Line {
    level: Level,
    /// When the line got `level`; `None` while it has never changed (low since creation).
    since: Option<Nanos>,
    /// When the change to `level` was due: `since` less the lateness of its wake-up and
    /// write. With a time base, the instant of the grid the phase counts from (see
    /// [`Channel::earliest`]).
    due: Nanos,
    /// A level the schedule asked for, held back until the given instant.
    held: Option<(Level, Nanos)>,
    /// When the change held back is due, ns: its instant less the lateness of the phase it
    /// waits on (the two differ only with a time base, see [`Channel::earliest`]).
    held_due: Nanos,
    /// An interlock forbids the line to go high (its partner of a split-range pair is high); a
    /// rise asked for meanwhile is held back until it is released.
    locked: bool,
    /// When `max_on_ms` cuts the line's high phase, if it is high and a maximum is set.
    cut: Option<Nanos>,
    /// The change held back is the schedule's rise resuming after a cut: if the schedule drops
    /// it, nothing was lost.
    resumes: bool,
}

/// One PWM channel (SPEC §1).
#[derive(Debug, Clone)]
pub struct Channel {
    cfg: ChannelConfig,
    pending: Option<ChannelConfig>,
    duty: Duty,
    enabled: bool,
    /// The level the schedule asks for; the line follows it through the guard.
    level: Level,
    line: Line,
    step: Option<Step>,
    plan: Plan,
    /// The command watchdog: its last feed, its trip and the fault value's end.
    watchdog: Watchdog,
    flags: (bool, bool),
    /// The emergency stop is latched: the line never goes high.
    estop: bool,
    /// The line may follow the schedule (a managed node's ACTIVE state); when not, it is held
    /// inactive and a rise the schedule asks for waits for the release.
    live: bool,
    /// The dead band: the command in force and the commands it ignored.
    band: DeadBand,
    /// The slew limit: the duty it has reached and its last decision instant (no instant
    /// while no pulses run: the ramp starts at the next decision).
    slew: Slew,
    /// `max_on_ms` cut the line in the running period, and in the period before.
    cuts: Marks<bool>,
    /// Where the running period and its on phase lie: the stagger grid and lead, the slot
    /// the on phase needs, what waiting for one did.
    place: Placement,
    /// The line's on time over the rolling-average window (`avg_duty_limit_pct`).
    avg: budget::Budget,
    /// The board of the node's real line levels this channel's line guard consults before a
    /// rise (see [`Channel::seat_on`]); `None` for a channel on its own.
    seat: Option<Seat>,
    /// With a time base: the rounding remainder carried from period to period.
    carry: Carry,
    /// The heater loop and its checks; inert without feedback.
    heat: Heat,
}

impl Channel {
    /// A disabled channel with output low and a commanded duty of 0, created at `now` (ns); the
    /// watchdog counts from `now` until the first command.
    pub fn new(cfg: ChannelConfig, now: Nanos) -> Channel {
        let duty = Duty {
            fraction: 0.0,
            requested: Command::Percent(0.0),
            clamped: false,
        };
        Channel {
            cfg,
            pending: None,
            duty,
            enabled: false,
            level: Level::Low,
            line: Line {
                level: Level::Low,
                since: None,
                due: 0,
                held: None,
                held_due: 0,
                locked: false,
                cut: None,
                resumes: false,
            },
            step: None,
            plan: Plan::new(0.0, &cfg),
            watchdog: Watchdog::new(now),
            flags: (false, false),
            estop: false,
            live: true,
            band: DeadBand::default(),
            slew: Slew::default(),
            cuts: Marks::default(),
            place: Placement::new(now),
            avg: budget::Budget::new(cfg.avg_window),
            seat: None,
            carry: Carry::default(),
            heat: Heat::new(&cfg.heater, cfg.period.max(CHECK_WINDOW), now),
        }
    }

    /// Seats the channel on `board` as line `line`: from then on every rise of its line is
    /// checked against the board's rules at the moment it would be written (a split-range
    /// partner high, `max_simultaneous_on` lines high), and held back while they forbid it;
    /// every level written is recorded there. Call before the first action.
    pub fn seat_on(&mut self, board: &std::sync::Arc<LineBoard>, line: usize) {
        let seat = Seat {
            board: std::sync::Arc::clone(board),
            line,
        };
        seat.set(self.line.level);
        self.seat = Some(seat);
    }

    /// The logical level of the output line, as last emitted in an [`Event::Edge`].
    pub fn level(&self) -> Level {
        self.line.level
    }

    #[cfg(test)]
    pub(crate) fn line_since(&self) -> Option<Nanos> {
        self.line.since
    }

    /// Tells the channel when its last edge really reached the line (monotonic ns), if that was
    /// later than the instant it was emitted at: the minimum of the phase it began counts from
    /// here. The output thread calls this after each write; virtual-time callers need not.
    pub fn edge_written(&mut self, at: Nanos) {
        if let Some(since) = self.line.since.filter(|s| at > *s) {
            self.avg_write_seen();
            if self.line.level == Level::Low {
                // The line was on until the fall really happened.
                self.avg_late_fall(since, at);
            }
            self.line.since = Some(at);
            self.retime_held();
            self.retime_cut(at);
        }
    }

    /// The configuration in force.
    pub fn config(&self) -> &ChannelConfig {
        &self.cfg
    }

    /// A configuration waiting for the next period boundary.
    pub fn pending_config(&self) -> Option<&ChannelConfig> {
        self.pending.as_ref()
    }

    /// The plan in force.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The period in force, ns: the plan's (longer than the configured one when `extend`
    /// grew it), or the configured one while the plan has none.
    pub fn period(&self) -> Nanos {
        match self.plan.period() {
            0 => self.cfg.period,
            p => p,
        }
    }

    /// Whether the channel is enabled.
    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// The channel runs periods: enabled, with a period, a schedule running.
    pub fn running(&self) -> bool {
        self.enabled && self.cfg.period > 0 && self.step.is_some()
    }

    /// The next instant (ns) at which [`Channel::poll`] has work, if any.
    pub fn poll_at(&self) -> Option<Nanos> {
        earliest(&[
            self.step.map(|s| s.end),
            self.watchdog_deadline(),
            self.heat_deadline(),
            self.watchdog.fault_value_ends(),
            self.line.cut,
            self.line
                .held
                .filter(|(level, _)| !(self.no_rise() && *level == Level::High))
                .map(|(_, at)| at),
        ])
    }

    /// Processes every deadline at or before `now`. When several edges fall due together (the
    /// caller was late by more than a step), only the net level change is emitted, at the time
    /// of the last one, and the rest are reported as [`Event::Missed`].
    pub fn poll(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let before = self.line;
        let mut edges = 0u32;
        let mut last_at = now;
        let outer = self.avg_batch(now);
        {
            let mut inner = |e: Event| match e {
                Event::Edge { at, .. } => {
                    edges += 1;
                    last_at = at;
                }
                other => emit(other),
            };
            while let Some(t) = self.poll_at() {
                if t > now {
                    break;
                }
                self.advance(t, &mut inner);
            }
        }
        self.avg_batch(outer);
        let changed = self.line.level != before.level;
        if changed {
            // The edge reaches the line now, however long ago it was due: the minimum of the
            // phase it begins counts from now, so a late edge moves the next one.
            if self.line.level == Level::Low {
                // And a late fall left the line on until now.
                self.avg_late_fall(self.line.since.unwrap_or(now), now);
            }
            self.line.since = Some(now);
            emit(Event::Edge {
                at: last_at,
                level: self.line.level,
            });
            self.retime_held();
            self.retime_cut(now);
        } else if edges > 0 {
            // Edges that cancelled out never reached the line.
            self.line.since = before.since;
            self.line.due = before.due;
            // A high line has been high since its real rise: the maximum on time counts from
            // there, and may have run out by now.
            self.retime_cut(now);
        }
        let missed = edges - u32::from(changed);
        if missed > 0 {
            emit(Event::Missed { edges: missed });
        }
        if self.line.cut.is_some_and(|t| t <= now) {
            self.cut(now, emit);
        }
    }

    /// Takes a duty command at `now` (SPEC §1.1). NaN and infinities are refused and the last
    /// valid command stays; out-of-range values are clamped and flagged. Under `control` `pid`
    /// the loop sets the duty: a command is refused ([`Event::Refused`]).
    pub fn command(&mut self, now: Nanos, command: Command, emit: &mut dyn FnMut(Event)) {
        if self.loop_on() {
            emit(Event::Refused(if self.pid_on() {
                crate::core::heater::Refusal::DutyUnderPid
            } else {
                crate::core::heater::Refusal::DutyUnderMpc
            }));
            return;
        }
        if self.heat.autotune.is_some() {
            emit(Event::Refused(crate::core::heater::Refusal::Autotuning));
            return;
        }
        self.take_command(now, command, true, emit);
    }

    /// A duty from a command or from the loop, through everything a command goes through.
    /// `fed`: it feeds the watchdog (a command does; the loop's duty does not, as under `pid`
    /// the watchdog watches the setpoint and the feedback).
    fn take_command(
        &mut self,
        now: Nanos,
        command: Command,
        fed: bool,
        emit: &mut dyn FnMut(Event),
    ) {
        let duty = match command.to_duty() {
            Ok(d) => d,
            Err(e) => {
                emit(Event::Rejected(e));
                return;
            }
        };
        if duty.clamped {
            emit(Event::Clamped {
                requested: duty.requested,
                applied: duty.fraction,
            });
        }
        self.duty = duty;
        if fed {
            self.watchdog.feed(now);
        }
        // The dead band; the command counts for the watchdog even when it ignores it.
        self.band.offer(duty.fraction, &self.cfg);
        if fed && self.watchdog.rearm() {
            emit(Event::Watchdog { tripped: false });
        }
        if !self.enabled {
            // 002: a disabled block still computes the on and off times.
            self.latch(Plan::new(self.effective_duty(), &self.cfg), emit);
        } else if self.cfg.apply_at == ApplyAt::Immediate {
            self.reevaluate(now, emit);
        }
    }

    /// Sets enable at `now` (SPEC §1.1, §1.4).
    pub fn set_enable(&mut self, now: Nanos, enable: bool, emit: &mut dyn FnMut(Event)) {
        if enable == self.enabled {
            return;
        }
        if !enable {
            self.finish_autotune(now, crate::core::heater::autotune::Stop::Disabled, emit);
        }
        if enable && !self.heat_before_enable(now, emit) {
            return;
        }
        self.enabled = enable;
        if enable {
            // Soft start: the slew limit ramps the duty applied from 0 at each enable.
            self.slew.stop();
            // A new run of periods: no rounding remainder is carried over from the last one.
            self.carry.restart();
            // A stale command does not get a fresh lease: the watchdog counts from the last
            // command, not from the enable.
            self.trip_if_stale(now, emit);
            // 000/004: a new period starting with its on phase; 002: 0 % straight to off and
            // 100 % straight to on, with no minimum-time rule on the duty. The line's minimum
            // break still holds: toggling EN never puts a break shorter than it on the line, so
            // the period starts once the break since the last real fall has lasted min off (as
            // a restart from 0 % or from period 0 does).
            match self.break_ends_at() {
                Some(end) if end > now && self.cfg.period > 0 => {
                    self.step = Some(Step::off(StepKind::Run, now, end));
                }
                _ => self.start_period(now, emit),
            }
        } else {
            self.heat.next_sample = None;
            self.step = None;
            self.avg.acts = false;
            self.cuts.clear();
            self.place.forget_marks();
            if let Some(p) = self.pending.take() {
                self.put_config(p, now);
            }
            match self.cfg.on_disable {
                // 000, 002: a falling EN sets the output to 0 at once, a safety off.
                OnDisable::Off => self.force_low(now, emit),
                // 004: the line keeps the level it has; nothing held back is written later.
                OnDisable::Hold => {
                    self.line.held = None;
                    self.level = self.line.level;
                }
            }
            self.latch(Plan::new(self.effective_duty(), &self.cfg), emit);
        }
    }

    /// Takes a validated configuration at `now` (SPEC §1.5). Timing and policies take effect at
    /// the next period boundary (with `immediate` in force: at once); the watchdog timeout
    /// takes effect at once, since it guards safety, not timing.
    pub fn set_config(&mut self, now: Nanos, cfg: ChannelConfig, emit: &mut dyn FnMut(Event)) {
        // The heater loop and its checks take their settings at once: they guard the load.
        self.heat_config(now, cfg.heater, emit);
        self.cfg.command_timeout = cfg.command_timeout;
        self.cfg.params.command_timeout_ms = cfg.params.command_timeout_ms;
        // The fault value guards safety too: in force at once.
        self.cfg.fault_duty = cfg.fault_duty;
        self.cfg.fault_hold = cfg.fault_hold;
        self.cfg.params.fault_duty_pct = cfg.params.fault_duty_pct;
        self.cfg.params.fault_hold_ms = cfg.params.fault_hold_ms;
        self.trip_if_stale(now, emit);
        if !self.enabled {
            self.pending = None;
            self.put_config(cfg, now);
            self.latch(Plan::new(self.effective_duty(), &self.cfg), emit);
            // A line held on (004's hold) stays on only while the configuration still holds
            // it: `off` or period 0 switch it off now (after its minimum on time).
            if self.level == Level::High
                && (self.cfg.on_disable == OnDisable::Off || self.cfg.period == 0)
            {
                self.set_level(Level::Low, now, emit);
            }
        } else if self.step.is_none() || self.cfg.apply_at == ApplyAt::Immediate {
            self.pending = None;
            self.put_config(cfg, now);
            self.reevaluate(now, emit);
        } else {
            self.pending = Some(cfg);
        }
    }

    /// Makes `cfg` the configuration in force at `now`. A change held back for the line is
    /// re-timed for the new minima, and a cut of the high line for the new maximum on time
    /// (at `now` if the line has already been high that long).
    fn put_config(&mut self, cfg: ChannelConfig, now: Nanos) {
        self.cfg = cfg;
        self.avg_relayout(now);
        self.retime_held();
        self.retime_cut(now);
    }

    /// Makes `plan` the plan in force and reports what changed.
    fn latch(&mut self, plan: Plan, emit: &mut dyn FnMut(Event)) {
        if plan != self.plan {
            self.plan = plan;
            emit(Event::Plan(plan));
        }
        self.report_flags(emit);
    }

    /// Reports E1 and the limit flag when they changed: the plan's, or a cut by the maximum
    /// on time.
    fn report_flags(&mut self, emit: &mut dyn FnMut(Event)) {
        let cut = self.cuts.recent();
        let skipped = self.place.slots.recent() == SlotUse::Skipped;
        let flags = (self.plan.e1 || cut || skipped, self.plan.limited || cut);
        if flags != self.flags {
            self.flags = flags;
            emit(Event::Flags {
                e1: flags.0,
                limited: flags.1,
            });
        }
    }

    /// Handles the earliest deadline, which falls at `t`. The watchdog goes first when both
    /// fall together, so a tripped channel never starts another pulse.
    fn advance(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        if self.watchdog_deadline() == Some(t) {
            self.trip(t, emit);
            return;
        }
        if self.watchdog.fault_value_ends() == Some(t) {
            // The fault value has run its hold time: off, as a trip without one.
            self.watchdog.end_fault_value();
            self.trip_off(t, false, emit);
            return;
        }
        // A heater check before any step: a fault switches the line off before a rise due at
        // the same instant, and a sample gives the period starting then its duty.
        if self.heat_due(t, emit) {
            return;
        }
        if let Some((level, at)) = self.line.held {
            if at == t && !(self.no_rise() && level == Level::High) {
                self.write_line(level, t, emit);
                return;
            }
        }
        // A step ending with the cut goes first: its fall is the schedule's, not a cut.
        if let Some(step) = self.step.filter(|s| s.end == t) {
            match (step.kind, step.level) {
                (StepKind::Run, Level::High) => self.end_on_step(t, emit),
                (StepKind::Run | StepKind::Align, _) => self.start_period(t, emit),
                // The on phase was placed for its length at the period start: a command since
                // takes effect with the next period (with `immediate`, on the running pulse).
                (StepKind::Lead, _) => self.begin_on(t, emit),
                (StepKind::Wait, _) => self.skip(t, emit),
            }
            return;
        }
        debug_assert_eq!(self.line.cut, Some(t), "a deadline at {t} with nothing due");
        if self.line.cut == Some(t) {
            self.cut(t, emit);
        }
    }

    /// The decision step before an on step: a new period begins at `t`.
    fn start_period(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        if let Some(p) = self.pending.take() {
            self.put_config(p, t);
        }
        let period = self.cfg.period;
        if self.place.grid && period > 0 && !t.is_multiple_of(period) {
            // Staggered: periods start on the grid of whole periods the channels with this
            // period share; off until its next instant.
            let next = (t / period).saturating_add(1).saturating_mul(period);
            self.step = Some(Step::off(StepKind::Align, t, next));
            self.set_level(Level::Low, t, emit);
            return;
        }
        self.cuts.roll();
        self.place.roll_marks();
        // Every decision of this period plans with the remainder the last period left.
        self.carry.period_starts();
        let duty = self.decide(t);
        // An extended period spans whole periods of the grid.
        let plan = self.capped_plan(t, duty, self.place.grid.then_some(period));
        self.latch(plan, emit);
        let end = (self.place.grid && period > 0).then(|| t.saturating_add(plan.period()));
        self.place.period_starts(t, plan.t_on, end);
        if period == 0 {
            // 000: period 0, no pulses; the output is held at 0.
            self.step = None;
            self.set_level(Level::Low, t, emit);
            return;
        }
        if plan.t_on == 0 {
            self.step = Some(Step::off(StepKind::Run, t, t + plan.t_off));
            self.set_level(Level::Low, t, emit);
            return;
        }
        // Staggered: the on phase starts after those already placed, if it fits there.
        // The on phase lies within the first period of the grid (an extended plan's rest of
        // its period is off).
        // The on phase starts no earlier than the line's minimum break allows, so its place
        // is where the line will really be on.
        let (after, others) = if self.place.grid {
            self.place.lead
        } else {
            (0, 0)
        };
        let guard = match self.break_ends_at() {
            Some(end) if self.place.grid => end.saturating_sub(t),
            _ => 0,
        };
        let after = after.max(guard);
        let room = period.saturating_sub(plan.t_on).min(plan.t_off);
        if after > room && others.saturating_add(plan.t_on) <= period {
            self.step = Some(Step::off(StepKind::Align, t, t.saturating_add(period)));
            self.set_level(Level::Low, t, emit);
            return;
        }
        let lead = after.min(room);
        self.place.on_at(lead);
        if lead > 0 {
            self.step = Some(Step::off(StepKind::Lead, t, t + lead));
            self.set_level(Level::Low, t, emit);
            return;
        }
        self.begin_on(t, emit);
    }

    /// The on step has run its time at `t`: decide the off step.
    fn end_on_step(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        if self.cfg.period == 0 {
            self.step = None;
            self.set_level(Level::Low, t, emit);
            return;
        }
        let t_off = match self.cfg.apply_at {
            // 000: the period completes with the times computed at its start.
            ApplyAt::NextPeriod => self.plan.t_off,
            // 002: each step's time comes from the command current when it starts; 003 likewise.
            ApplyAt::NextStep | ApplyAt::Immediate => {
                let duty = self.decide(t);
                let plan = self.break_plan(t, duty);
                self.latch(plan, emit);
                plan.t_off
            }
        };
        // A period with a fixed end (the stagger grid, an on phase delayed for a slot) keeps
        // it: the break is what is left of the period.
        let t_off = self
            .place
            .period_end
            .map_or(t_off, |end| end.saturating_sub(t));
        if t_off == 0 {
            // No break this period (100 % or a suppressed break): straight to the next period.
            self.start_period(t, emit);
            return;
        }
        self.step = Some(Step::off(StepKind::Run, t, t + t_off));
        self.set_level(Level::Low, t, emit);
    }

    /// 003: re-times the running step for the current command and configuration. A step whose
    /// new length has already passed ends now, but never before its minimum.
    fn reevaluate(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let duty = self.decide(now);
        // A break after the on phase keeps to what the period start allowed; elsewhere an on
        // phase may start or run from now.
        let plan = match self.step {
            Some(s) if s.level == Level::Low && s.kind == StepKind::Run => {
                self.break_plan(now, duty)
            }
            _ => self.capped_plan(now, duty, None),
        };
        self.latch(plan, emit);
        let Some(step) = self.step else {
            if self.enabled && self.cfg.period > 0 {
                // Pulses restart from idle (period 0 -> T): the break since the output last
                // went low must still reach the minimum off time.
                match self.break_ends_at() {
                    Some(end) if end > now => {
                        self.step = Some(Step::off(StepKind::Run, now, end));
                    }
                    _ => self.start_period(now, emit),
                }
            }
            return;
        };
        if step.kind == StepKind::Wait {
            self.rewait(now, emit);
        }
        if step.kind != StepKind::Run
            || (step.level == Level::Low && self.place.period_end.is_some())
        {
            // An off step placed by the stagger grid or a slot ends where it was placed.
            self.poll(now, emit);
            return;
        }
        let (len, min) = match step.level {
            Level::High => (plan.t_on, self.cfg.min_on),
            Level::Low => (plan.t_off, self.cfg.min_off),
        };
        // 003 compares with "the previous impulse/break length": the real length of the phase
        // on the line, from its last edge, not from the step the schedule restarted at a hidden
        // period boundary while the output was held constant.
        let end = if step.level == self.line.level {
            // With a time base, from the grid instant it was due (the guard still holds the
            // minimum from the real edge), so a late write does not push the end a tick on.
            let phase_start = self.phase_due().unwrap_or(0);
            phase_start
                .saturating_add(len)
                .max(now)
                .max(phase_start.saturating_add(min))
        } else {
            // The line has not followed this step yet (its change is held back): there is no
            // phase on the line to keep, and ending the step cancels the change.
            step.start.saturating_add(len).max(now)
        };
        self.step = Some(Step { end, ..step });
        self.poll(now, emit);
    }
}
