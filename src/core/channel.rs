//! One PWM channel as a sans-IO state machine: given `now` and inputs, it answers with edges,
//! flags and status, and says when it next needs to be polled. It never reads a clock, sleeps,
//! or touches an output; the output thread and the tests drive it.
//!
//! Time runs in steps. An on step is followed by an off step; the decision point before an on
//! step starts a new period (000: "period duration unchanged"). Which command a step uses depends
//! on [`ApplyAt`]: the one latched at the period start (000), the one current when the step
//! starts (002), or the one current right now, extending or ending the running step (003).

use super::command::{Command, CommandError, Duty};
use super::config::{ApplyAt, ChannelConfig, OnDisable};
use super::plan::{Plan, Rule};
use super::{Level, Nanos};

/// Something the channel did or noticed, in the order it happened.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    /// The output changes to `level` at scheduled time `at` (ns).
    Edge {
        /// Scheduled time, ns.
        at: Nanos,
        /// The new logical level.
        level: Level,
    },
    /// E1 (000) or the limit flag (002) changed.
    Flags {
        /// E1: the commanded duty could not be reproduced because of a minimum time.
        e1: bool,
        /// The minimum-time limit flag (bLmtSwiTi).
        limited: bool,
    },
    /// A new plan (applied duty, on and off times) is in force.
    Plan(Plan),
    /// The watchdog tripped (true: output forced off) or recovered (false: a command arrived).
    Watchdog {
        /// Whether the watchdog is now tripped.
        tripped: bool,
    },
    /// A command was refused; the last valid command stays in force.
    Rejected(CommandError),
    /// A command was out of range and was clamped.
    Clamped {
        /// The value as requested, in the command's unit.
        requested: f64,
        /// The duty fraction applied, 0..=1.
        applied: f64,
    },
    /// The channel was polled so late that `edges` scheduled edges fell in the past together;
    /// they were merged so that no zero-width pulse reaches the output.
    Missed {
        /// How many scheduled edges were not emitted.
        edges: u32,
    },
}

/// The running on or off step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Step {
    level: Level,
    start: Nanos,
    end: Nanos,
}

/// What a channel reports about itself (002's information outputs, 004's active flag).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Status {
    /// The channel is enabled (EN / bEn / i_xEn).
    pub enabled: bool,
    /// The block is producing output (004's q_xActv): enabled, a period set, watchdog not tripped.
    pub active: bool,
    /// The logical output level.
    pub level: Level,
    /// The commanded duty after clamping, 0..=1.
    pub duty_commanded: f64,
    /// The last valid command as requested, in its own unit.
    pub duty_requested: f64,
    /// The last valid command was out of range and clamped.
    pub command_clamped: bool,
    /// The duty delivered by the plan in force, 0..=1.
    pub duty_applied: f64,
    /// Period in force, ns.
    pub period: Nanos,
    /// On time of the plan in force, ns (002's fActTiOn).
    pub t_on: Nanos,
    /// Off time of the plan in force, ns (002's fActTiOff).
    pub t_off: Nanos,
    /// Remaining time of the running on step, ns (002's nRemTiOn); 0 when not in an on step.
    pub remaining_on: Nanos,
    /// Remaining time of the running off step, ns (002's nRemTiOff); 0 when not in an off step.
    pub remaining_off: Nanos,
    /// End of the running step, ns, if a step is running (lets a reader recompute the remaining
    /// times for a later instant).
    pub step_end: Option<Nanos>,
    /// E1 (000).
    pub e1: bool,
    /// Minimum-time limit flag (002's bLmtSwiTi).
    pub limited: bool,
    /// Watchdog tripped: no command for `command_timeout_ms`.
    pub watchdog_tripped: bool,
    /// The rule that shaped the plan in force.
    pub rule: Rule,
}

impl Status {
    /// The remaining on and off times at `now`, ns, from the step end recorded in this status.
    pub fn remaining_at(&self, now: Nanos) -> (Nanos, Nanos) {
        match self.step_end {
            Some(end) if self.remaining_on > 0 || self.remaining_off > 0 => {
                let left = end.saturating_sub(now);
                if self.remaining_on > 0 {
                    (left, 0)
                } else {
                    (0, left)
                }
            }
            _ => (0, 0),
        }
    }
}

/// One PWM channel (SPEC §1).
#[derive(Debug, Clone)]
pub struct Channel {
    cfg: ChannelConfig,
    pending: Option<ChannelConfig>,
    duty: Duty,
    enabled: bool,
    level: Level,
    step: Option<Step>,
    plan: Plan,
    period_start: Nanos,
    last_command_at: Nanos,
    watchdog_tripped: bool,
    flags: (bool, bool),
    /// When the output last went low, for the minimum break before pulses restart from idle.
    last_fall: Option<Nanos>,
}

impl Channel {
    /// A disabled channel with output low and a commanded duty of 0, created at `now` (ns); the
    /// watchdog counts from `now` until the first command.
    pub fn new(cfg: ChannelConfig, now: Nanos) -> Channel {
        let duty = Duty {
            fraction: 0.0,
            requested: 0.0,
            clamped: false,
        };
        Channel {
            cfg,
            pending: None,
            duty,
            enabled: false,
            level: Level::Low,
            step: None,
            plan: Plan::new(0.0, &cfg),
            period_start: now,
            last_command_at: now,
            watchdog_tripped: false,
            flags: (false, false),
            last_fall: None,
        }
    }

    /// The logical output level.
    pub fn level(&self) -> Level {
        self.level
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

    /// Whether the channel is enabled.
    pub fn enabled(&self) -> bool {
        self.enabled
    }

    /// The next instant (ns) at which [`Channel::poll`] has work, if any.
    pub fn poll_at(&self) -> Option<Nanos> {
        match (self.step.map(|s| s.end), self.watchdog_deadline()) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Processes every deadline at or before `now`. When several edges fall due together (the
    /// caller was late by more than a step), only the net level change is emitted, at the time
    /// of the last one, and the rest are reported as [`Event::Missed`].
    pub fn poll(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let before = self.level;
        let mut edges = 0u32;
        let mut last_at = now;
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
        let changed = self.level != before;
        if changed {
            emit(Event::Edge {
                at: last_at,
                level: self.level,
            });
        }
        let missed = edges - u32::from(changed);
        if missed > 0 {
            emit(Event::Missed { edges: missed });
        }
    }

    /// Takes a duty command at `now` (SPEC §1.1). NaN and infinities are refused and the last
    /// valid command stays; out-of-range values are clamped and flagged.
    pub fn command(&mut self, now: Nanos, command: Command, emit: &mut dyn FnMut(Event)) {
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
        self.last_command_at = now;
        if self.watchdog_tripped {
            self.watchdog_tripped = false;
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
        self.enabled = enable;
        if enable {
            // A stale command does not get a fresh lease: the watchdog counts from the last
            // command, not from the enable.
            self.trip_if_stale(now, emit);
            // 002: 0 % straight to off, 100 % straight to on, no minimum time; otherwise 000/004:
            // a new period starting with its on phase.
            self.start_period(now, emit);
        } else {
            self.step = None;
            if let Some(p) = self.pending.take() {
                self.cfg = p;
            }
            if self.cfg.on_disable == OnDisable::Off {
                self.set_level(Level::Low, now, emit);
            }
            self.latch(Plan::new(self.effective_duty(), &self.cfg), emit);
        }
    }

    /// Takes a validated configuration at `now` (SPEC §1.5). Timing and policies take effect at
    /// the next period boundary (with `immediate` in force: at once); the watchdog timeout
    /// takes effect at once, since it guards safety, not timing.
    pub fn set_config(&mut self, now: Nanos, cfg: ChannelConfig, emit: &mut dyn FnMut(Event)) {
        self.cfg.command_timeout = cfg.command_timeout;
        self.cfg.params.command_timeout_ms = cfg.params.command_timeout_ms;
        self.cfg.params.active_low = cfg.params.active_low;
        self.trip_if_stale(now, emit);
        if !self.enabled {
            self.pending = None;
            self.cfg = cfg;
            self.latch(Plan::new(self.effective_duty(), &self.cfg), emit);
        } else if self.step.is_none() || self.cfg.apply_at == ApplyAt::Immediate {
            self.pending = None;
            self.cfg = cfg;
            self.reevaluate(now, emit);
        } else {
            self.pending = Some(cfg);
        }
    }

    /// The channel's report at `now` (ns).
    pub fn status(&self, now: Nanos) -> Status {
        let (remaining_on, remaining_off) = match self.step {
            Some(s) if s.level == Level::High => (s.end.saturating_sub(now), 0),
            Some(s) => (0, s.end.saturating_sub(now)),
            None => (0, 0),
        };
        Status {
            enabled: self.enabled,
            active: self.enabled && self.cfg.period > 0 && !self.watchdog_tripped,
            level: self.level,
            duty_commanded: self.duty.fraction,
            duty_requested: self.duty.requested,
            command_clamped: self.duty.clamped,
            duty_applied: self.plan.applied_duty(),
            period: self.cfg.period,
            t_on: self.plan.t_on,
            t_off: self.plan.t_off,
            remaining_on,
            remaining_off,
            step_end: self.step.map(|s| s.end),
            e1: self.plan.e1,
            limited: self.plan.limited,
            watchdog_tripped: self.watchdog_tripped,
            rule: self.plan.rule,
        }
    }

    fn effective_duty(&self) -> f64 {
        if self.watchdog_tripped {
            0.0
        } else {
            self.duty.fraction
        }
    }

    fn watchdog_deadline(&self) -> Option<Nanos> {
        (self.enabled && self.cfg.command_timeout > 0 && !self.watchdog_tripped).then(|| {
            self.last_command_at
                .saturating_add(self.cfg.command_timeout)
        })
    }

    fn set_level(&mut self, level: Level, at: Nanos, emit: &mut dyn FnMut(Event)) {
        if level != self.level {
            self.level = level;
            if level == Level::Low {
                self.last_fall = Some(at);
            }
            emit(Event::Edge { at, level });
        }
    }

    /// Makes `plan` the plan in force and reports what changed.
    fn latch(&mut self, plan: Plan, emit: &mut dyn FnMut(Event)) {
        if plan != self.plan {
            self.plan = plan;
            emit(Event::Plan(plan));
        }
        let flags = (plan.e1, plan.limited);
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
        let Some(step) = self.step else { return };
        debug_assert_eq!(step.end, t);
        match step.level {
            Level::High => self.end_on_step(t, emit),
            Level::Low => self.start_period(t, emit),
        }
    }

    /// The decision step before an on step: a new period begins at `t`.
    fn start_period(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        if let Some(p) = self.pending.take() {
            self.cfg = p;
        }
        let plan = Plan::new(self.effective_duty(), &self.cfg);
        self.latch(plan, emit);
        self.period_start = t;
        if self.cfg.period == 0 {
            // 000: period 0, no pulses; the output is held at 0.
            self.step = None;
            self.set_level(Level::Low, t, emit);
            return;
        }
        let (level, len) = if plan.t_on > 0 {
            (Level::High, plan.t_on)
        } else {
            (Level::Low, plan.t_off)
        };
        self.step = Some(Step {
            level,
            start: t,
            end: t + len,
        });
        self.set_level(level, t, emit);
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
                let plan = Plan::new(self.effective_duty(), &self.cfg);
                self.latch(plan, emit);
                plan.t_off
            }
        };
        if t_off == 0 {
            // No break this period (100 % or a suppressed break): straight to the next period.
            self.start_period(t, emit);
            return;
        }
        self.step = Some(Step {
            level: Level::Low,
            start: t,
            end: t + t_off,
        });
        self.set_level(Level::Low, t, emit);
    }

    /// 003: re-times the running step for the current command and configuration. A step whose
    /// new length has already passed ends now, but never before its minimum.
    fn reevaluate(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let plan = Plan::new(self.effective_duty(), &self.cfg);
        self.latch(plan, emit);
        let Some(step) = self.step else {
            if self.enabled && self.cfg.period > 0 {
                // Pulses restart from idle (period 0 -> T): the break since the output last
                // went low must still reach the minimum off time.
                match self.last_fall.map(|t| t + self.cfg.min_off) {
                    Some(earliest) if earliest > now => {
                        self.step = Some(Step {
                            level: Level::Low,
                            start: earliest - self.cfg.min_off,
                            end: earliest,
                        });
                    }
                    _ => self.start_period(now, emit),
                }
            }
            return;
        };
        let (len, min) = match step.level {
            Level::High => (plan.t_on, self.cfg.min_on),
            Level::Low => (plan.t_off, self.cfg.min_off),
        };
        let end = (step.start + len).max(now).max(step.start + min);
        self.step = Some(Step { end, ..step });
        self.poll(now, emit);
    }

    /// Trips at once when the watchdog deadline already lies in the past (a timeout set, or a
    /// channel enabled, long after the last command).
    fn trip_if_stale(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        if self.watchdog_deadline().is_some_and(|d| d <= now) {
            self.trip(now, emit);
        }
    }

    /// The watchdog fired at `t`: output off at once, duty 0 until a command arrives.
    fn trip(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        self.watchdog_tripped = true;
        emit(Event::Watchdog { tripped: true });
        self.latch(Plan::new(0.0, &self.cfg), emit);
        if let Some(step) = self.step {
            // Keep the period grid: stay off for the rest of this period.
            let end = match step.level {
                Level::High => (self.period_start + self.cfg.period).max(t),
                Level::Low => step.end,
            };
            self.step = Some(Step {
                level: Level::Low,
                start: if step.level == Level::High {
                    t
                } else {
                    step.start
                },
                end,
            });
        }
        self.set_level(Level::Low, t, emit);
    }
}
