//! What a channel tells its caller: the events it emits and the status it reports.

use super::super::command::{Command, CommandError};
use super::super::heater::{HeaterFault, HeaterStatus, Refusal, ResetRefusal};
use super::super::plan::{Plan, Rule};
use super::super::{Level, Nanos};
use super::Channel;

/// Something the channel did or noticed, in the order it happened.
#[derive(Debug, Clone, Copy, PartialEq)]
// Events travel by value through the wait-free ring buffer: boxing an autotune's outcome
// would allocate on the output thread.
#[allow(clippy::large_enum_variant)]
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
        /// E1: the commanded duty could not be reproduced because of a minimum time, or
        /// because the maximum on time cuts the line.
        e1: bool,
        /// The limit flag (bLmtSwiTi): a time was raised to its minimum, or the maximum on
        /// time cuts the line.
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
        /// The command as requested, with its unit.
        requested: Command,
        /// The duty fraction applied, 0..=1.
        applied: f64,
    },
    /// The on phase found no slot (`max_simultaneous_on`, or under stagger another line of its
    /// group on) before the latest start that fits it in its period, or gave its slot up to a
    /// lowered `max_simultaneous_on`: the channel stays off for the rest of the period.
    Skipped {
        /// When it was given up, ns.
        at: Nanos,
    },
    /// A heater input was refused (a duty command under `pid`, a setpoint under `open` or out
    /// of its range); what was in force stays.
    Refused(Refusal),
    /// A heater check latched a fault: the line went off at once and stays off until
    /// [`Channel::reset_heater_fault`] clears it.
    HeaterFault(HeaterFault),
    /// The answer to [`Channel::reset_heater_fault`] with the caller's `ticket`.
    FaultReset {
        /// The caller's number for the request.
        ticket: u32,
        /// Cleared, or why not.
        result: Result<(), ResetRefusal>,
    },
    /// A report of the autotune run started with `ticket`.
    Autotune {
        /// The caller's number for the run.
        ticket: u32,
        /// What happened.
        report: super::super::heater::autotune::Report,
    },
    /// The channel was polled so late that `edges` scheduled edges fell in the past together;
    /// they were merged so that no zero-width pulse reaches the output.
    Missed {
        /// How many scheduled edges were not emitted.
        edges: u32,
    },
}

/// Which of the load's protections act on a channel; each is off by default.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Protections {
    /// `max_on_ms` cuts the line: the plan keeps it high longer (a constant 1, or an on time
    /// above it), or a cut happened in this period or the one before. Sets E1 and the limit
    /// flag.
    pub max_on: bool,
    /// `max_duty_pct` lowers the command in force.
    pub max_duty: bool,
    /// `min_duty_pct` raises the command in force.
    pub min_duty: bool,
    /// The slew limit holds the duty applied short of the command in force.
    pub slew: bool,
    /// The dead band ignored the last valid command: an older one stays in force.
    pub deadband: bool,
    /// `phase` is `stagger`: the channel's periods run on the grid it shares with the channels
    /// of the same period, its on phase placed after theirs.
    pub stagger: bool,
    /// An on phase waited for another line to go off (`max_simultaneous_on`, or under stagger
    /// a line of its group still on) or was skipped, in this period or the one before (a skip
    /// sets E1 for those periods: the duty was not delivered).
    pub delayed: bool,
    /// The rolling-average cap (`avg_duty_limit_pct`) holds the on time planned in this period
    /// below what the other rules give: the line's energy budget over the window is spent.
    pub avg_duty: bool,
}

impl Protections {
    /// The names of the protections acting, as reported on `~/<ch>/status` and
    /// `/diagnostics`: `max_on`, `max_duty`, `min_duty`, `slew`, `deadband`, `stagger`,
    /// `delayed`, `avg_duty`.
    pub fn names(&self) -> impl Iterator<Item = &'static str> {
        [
            (self.max_on, "max_on"),
            (self.max_duty, "max_duty"),
            (self.min_duty, "min_duty"),
            (self.slew, "slew"),
            (self.deadband, "deadband"),
            (self.stagger, "stagger"),
            (self.delayed, "delayed"),
            (self.avg_duty, "avg_duty"),
        ]
        .into_iter()
        .filter_map(|(on, name)| on.then_some(name))
    }

    /// Whether any protection acts.
    pub fn any(&self) -> bool {
        self.names().next().is_some()
    }
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
    /// The last valid command as requested, with its unit.
    pub duty_requested: Command,
    /// The last valid command was out of range and clamped.
    pub command_clamped: bool,
    /// The command in force after the power limits and the dead band, 0..=1: what the slew
    /// limit moves the duty applied toward.
    pub duty_target: f64,
    /// The duty delivered by the plan in force, 0..=1.
    pub duty_applied: f64,
    /// Period in force, ns: the configured one, or the longer one `extend` grew it to.
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
    /// E1 (000); also set while the maximum on time acts.
    pub e1: bool,
    /// Limit flag (002's bLmtSwiTi); also set while the maximum on time acts.
    pub limited: bool,
    /// Watchdog tripped: no command for `command_timeout_ms`.
    pub watchdog_tripped: bool,
    /// The watchdog's fault value (`fault_duty_pct`) is running.
    pub fault_active: bool,
    /// The emergency stop is latched: the line is held low.
    pub estopped: bool,
    /// The rule that shaped the plan in force.
    pub rule: Rule,
    /// The protections of the load acting now.
    pub protections: Protections,
    /// Valid commands the dead band ignored since the channel was created.
    pub ignored_commands: u64,
    /// On phases skipped since the channel was created (see [`Event::Skipped`]).
    pub skipped_pulses: u64,
    /// The line's average duty over the window of the rolling-average cap ending now, 0..=1, as
    /// the channel counts it (never less than the real one).
    pub avg_duty: f64,
    /// The time base in force, ns (`time_base_ms` rounded to the ns); 0 = off.
    pub time_base: Nanos,
    /// On time the current input gives, ns: 002's fActTiOn, "continuously calculated" from the
    /// command in force through the minimum-time rules and the time base (not the
    /// rolling-average cap, which decides at a period start), while `t_on` is the time the
    /// running period or step latched.
    pub t_on_input: Nanos,
    /// Off time the current input gives, ns (002's fActTiOff); see `t_on_input`.
    pub t_off_input: Nanos,
    /// A vendor recommendation the settings in force do not follow (003, 001).
    pub sizing: Option<crate::core::Sizing>,
    /// The heater loop: reading, setpoint, the PID's terms, a latched heater fault.
    pub heater: HeaterStatus,
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

impl Channel {
    /// The channel's report at `now` (ns).
    pub fn status(&self, now: Nanos) -> Status {
        // 002: the times are computed continuously from the input, whatever the running step
        // latched.
        let input = Plan::carried(self.effective_duty(), &self.cfg, self.carry.taken());
        let (remaining_on, remaining_off) = match self.step {
            Some(s) if s.level == Level::High => (s.end.saturating_sub(now), 0),
            Some(s) => (0, s.end.saturating_sub(now)),
            None => (0, 0),
        };
        Status {
            enabled: self.enabled,
            active: self.enabled
                && self.cfg.period > 0
                && !self.watchdog.tripped()
                && !self.latched()
                && self.live,
            level: self.line.level,
            duty_commanded: self.duty.fraction,
            duty_requested: self.duty.requested,
            command_clamped: self.duty.clamped,
            duty_target: self.target(),
            duty_applied: self.plan.applied_duty(),
            period: self.period(),
            t_on: self.plan.t_on,
            t_off: self.plan.t_off,
            remaining_on,
            remaining_off,
            step_end: self.step.map(|s| s.end),
            e1: self.flags.0,
            limited: self.flags.1,
            watchdog_tripped: self.watchdog.tripped(),
            fault_active: self.watchdog.fault_value_runs(),
            estopped: self.estop,
            rule: self.plan.rule,
            protections: Protections {
                max_on: self.max_on_acts(),
                max_duty: self.target() < self.band.accepted(),
                min_duty: self.target() > self.band.accepted(),
                slew: self.slewing()
                    && !self.watchdog.tripped()
                    && self.slew.reached() != self.target(),
                deadband: self.band.last_ignored(),
                stagger: self.place.grid && self.enabled && self.cfg.period > 0,
                delayed: self.place.slots.recent() != super::SlotUse::None,
                avg_duty: self.avg.acts && self.running(),
            },
            ignored_commands: self.band.ignored(),
            skipped_pulses: self.place.skipped,
            avg_duty: self.avg_duty(now),
            time_base: self.cfg.tick,
            t_on_input: input.t_on,
            t_off_input: input.t_off,
            sizing: self.cfg.sizing(),
            heater: self.heater_status(now),
        }
    }
}
