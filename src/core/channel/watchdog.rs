//! The command watchdog (SPEC §1, `command_timeout_ms`; §4): when it fires, what the fault
//! value does, and how the output goes off keeping the period grid.

use super::{Channel, Event, Level, Nanos, Plan, Step, StepKind};

impl Channel {
    /// The watchdog guards every state in which the line is or will be high: enabled, or
    /// disabled with the line held on (004's hold).
    pub(super) fn watchdog_deadline(&self) -> Option<Nanos> {
        let guarding = self.enabled || self.level == Level::High || self.line.level == Level::High;
        (guarding && self.cfg.command_timeout > 0 && !self.watchdog_tripped).then(|| {
            self.last_command_at
                .saturating_add(self.cfg.command_timeout)
        })
    }

    /// Trips at once when the watchdog deadline already lies in the past (a timeout set, or a
    /// channel enabled, long after the last command).
    pub(super) fn trip_if_stale(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        if self.watchdog_deadline().is_some_and(|d| d <= now) {
            self.trip(now, emit);
        }
    }

    /// The watchdog fired at `t`. With a fault value (and the channel enabled) the channel
    /// runs at it from now, re-timing the running step as TCONT_CP does a new command, so the
    /// minimum times hold; without one the output goes off at once, duty 0 until a command.
    pub(super) fn trip(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        self.finish_autotune(t, crate::core::heater::autotune::Stop::Watchdog, emit);
        self.watchdog_tripped = true;
        emit(Event::Watchdog { tripped: true });
        if self.cfg.fault_duty > 0.0 && self.enabled && self.cfg.period > 0 {
            self.fault_until = Some(match self.cfg.fault_hold {
                0 => Nanos::MAX,
                hold => t.saturating_add(hold),
            });
            self.reevaluate(t, emit);
            return;
        }
        self.trip_off(t, true, emit);
    }

    /// Output off at `t` after a trip, keeping the period grid: duty 0 until a command.
    /// `forced`: the trip itself, a safety off at once; otherwise the end of the fault value's
    /// hold time, which leaves a running fault pulse its minimum on time.
    pub(super) fn trip_off(&mut self, t: Nanos, forced: bool, emit: &mut dyn FnMut(Event)) {
        // The running period's length, extended or not, before the plan for 0 % replaces it.
        let period = self.period();
        self.avg.acts = false;
        self.latch(Plan::new(0.0, &self.cfg), emit);
        if let Some(step) = self.step {
            // Keep the period grid: stay off for the rest of this period.
            let end = match (step.level, step.kind) {
                (Level::Low, StepKind::Run | StepKind::Align) => step.end,
                _ => self.period_end.unwrap_or(self.period_start + period).max(t),
            };
            let start = if step.level == Level::High {
                t
            } else {
                step.start
            };
            let kind = if step.kind == StepKind::Align {
                StepKind::Align
            } else {
                StepKind::Run
            };
            self.step = Some(Step {
                level: Level::Low,
                start,
                end,
                kind,
            });
        }
        if forced {
            self.force_low(t, emit);
        } else {
            self.set_level(Level::Low, t, emit);
        }
    }
}
