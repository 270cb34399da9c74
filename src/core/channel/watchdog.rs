//! The command watchdog (SPEC §1, `command_timeout_ms`; §4): when it fires, what the fault
//! value does, and how the output goes off keeping the period grid.

use super::{Channel, Event, Level, Nanos, Plan, Step, StepKind};

/// The command watchdog's own state: when it was last fed, whether it has tripped, and until
/// when the fault value runs.
///
/// Invariant, checked at every change: the fault value runs only while the watchdog is
/// tripped (`fault_until` is `Some` only when `tripped`), and a tripped watchdog has no
/// deadline until it is fed and re-armed.
#[derive(Debug, Clone, Copy)]
pub(super) struct Watchdog {
    /// The last command, goal or fresh loop input, ns.
    last_fed: Nanos,
    tripped: bool,
    /// While the fault value runs: when it ends, ns (`Nanos::MAX`: until a command).
    fault_until: Option<Nanos>,
}

impl Watchdog {
    /// Armed, fed at `now` (ns).
    pub(super) fn new(now: Nanos) -> Watchdog {
        Watchdog {
            last_fed: now,
            tripped: false,
            fault_until: None,
        }
    }

    fn check(&self) {
        debug_assert!(
            self.fault_until.is_none() || self.tripped,
            "a fault value runs only while the watchdog is tripped: {self:?}"
        );
    }

    /// A command or goal at `now` (ns): counts from there.
    pub(super) fn feed(&mut self, now: Nanos) {
        self.last_fed = now;
    }

    /// A loop input taken at `at` (ns) feeds it, never moving the last feed back.
    pub(super) fn feed_no_earlier(&mut self, at: Nanos) {
        self.last_fed = self.last_fed.max(at);
    }

    /// Re-arms a tripped watchdog (the fault value ends with it); whether it was tripped.
    pub(super) fn rearm(&mut self) -> bool {
        let was = self.tripped;
        self.tripped = false;
        self.fault_until = None;
        self.check();
        was
    }

    /// Trips; with `fault_until` (ns, `Nanos::MAX`: until a command) the fault value runs.
    pub(super) fn trip(&mut self, fault_until: Option<Nanos>) {
        self.tripped = true;
        self.fault_until = fault_until;
        self.check();
    }

    /// The fault value stops (its hold ended, an e-stop, a heater fault); still tripped.
    pub(super) fn end_fault_value(&mut self) {
        self.fault_until = None;
        self.check();
    }

    /// It has tripped and not been fed since.
    pub(super) fn tripped(&self) -> bool {
        self.tripped
    }

    /// The fault value runs.
    pub(super) fn fault_value_runs(&self) -> bool {
        self.fault_until.is_some()
    }

    /// When the fault value's hold time ends, ns; `None` when none runs or it runs until a
    /// command.
    pub(super) fn fault_value_ends(&self) -> Option<Nanos> {
        self.fault_until.filter(|t| *t != Nanos::MAX)
    }

    /// When it trips with `timeout` (ns, 0: never) if not fed before; `None` once tripped.
    pub(super) fn deadline(&self, timeout: Nanos) -> Option<Nanos> {
        (timeout > 0 && !self.tripped).then(|| self.last_fed.saturating_add(timeout))
    }

    /// Whether input taken at `fed` (ns) is still fresh at `now` under `timeout` (ns, 0:
    /// always).
    pub(super) fn fresh(now: Nanos, fed: Nanos, timeout: Nanos) -> bool {
        timeout == 0 || now < fed.saturating_add(timeout)
    }
}

impl Channel {
    /// The watchdog guards every state in which the line is or will be high: enabled, or
    /// disabled with the line held on (004's hold).
    pub(super) fn watchdog_deadline(&self) -> Option<Nanos> {
        let guarding = self.enabled || self.level == Level::High || self.line.level == Level::High;
        guarding
            .then(|| self.watchdog.deadline(self.cfg.command_timeout))
            .flatten()
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
        if self.cfg.fault_duty > 0.0 && self.enabled && self.cfg.period > 0 {
            self.watchdog.trip(Some(match self.cfg.fault_hold {
                0 => Nanos::MAX,
                hold => t.saturating_add(hold),
            }));
            emit(Event::Watchdog { tripped: true });
            self.reevaluate(t, emit);
            return;
        }
        self.watchdog.trip(None);
        emit(Event::Watchdog { tripped: true });
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
                _ => self
                    .place
                    .period_end
                    .unwrap_or(self.place.period_start + period)
                    .max(t),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_watchdog_keeps_its_rules() {
        let mut w = Watchdog::new(100);
        assert_eq!(w.deadline(0), None, "0: no timeout");
        assert_eq!(w.deadline(50), Some(150));
        // A late reading's instant never moves the feed back.
        w.feed_no_earlier(90);
        assert_eq!(w.deadline(50), Some(150));
        w.feed_no_earlier(120);
        assert_eq!(w.deadline(50), Some(170));
        // Tripped with a fault value for a hold time: no deadline, the hold's end instead.
        w.trip(Some(400));
        assert!(w.tripped() && w.fault_value_runs());
        assert_eq!((w.deadline(50), w.fault_value_ends()), (None, Some(400)));
        // The hold ends: still tripped, duty 0 until fed.
        w.end_fault_value();
        assert!(w.tripped() && !w.fault_value_runs());
        // Until a command: runs, but has no end to wait for.
        w.trip(Some(Nanos::MAX));
        assert_eq!(w.fault_value_ends(), None);
        assert!(w.fault_value_runs());
        w.feed(500);
        assert!(w.rearm(), "it was tripped");
        assert!(!w.tripped() && !w.fault_value_runs());
        assert_eq!(w.deadline(50), Some(550));
        assert!(!w.rearm(), "already armed");
        assert!(
            Watchdog::fresh(10, 5, 0) && Watchdog::fresh(10, 5, 6) && !Watchdog::fresh(10, 5, 5)
        );
    }

    #[test]
    #[cfg(debug_assertions)]
    #[should_panic(expected = "only while the watchdog is tripped")]
    fn a_fault_value_without_a_trip_is_caught_where_it_is_kept() {
        let mut w = Watchdog::new(0);
        w.fault_until = Some(10);
        w.check();
    }
}
