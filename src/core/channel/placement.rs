//! Where a channel's on phase goes, for the node-level planner ([`crate::core::Bank`]): the
//! stagger grid and lead, and the slots of `max_simultaneous_on`: an on phase without a slot
//! waits, off, keeping its whole length, and is skipped once it can no longer fit its period.

use super::{Channel, Event, Level, Nanos, SlotUse, Step, StepKind};

impl Channel {
    /// Puts the channel on the stagger grid (`true`) or takes it off (node parameter `phase`):
    /// on it, every period starts at a whole multiple of the period on the monotonic clock
    /// (a first period waits, off, for the next one), and its on phase starts at the lead set
    /// by [`Channel::set_lead`]. Takes effect at the next period start.
    pub fn set_grid(&mut self, on: bool) {
        self.grid = on;
        if !on {
            self.lead = (0, 0);
        }
    }

    /// Where the next staggered period's on phase goes, read when a period starts: `after`,
    /// where the on phases the other channels of its group placed in that period end (ns after
    /// its start), and `others`, the on time those channels run per period (ns). The phase
    /// starts at `after` if it ends within the period there. If not, and all the phases would
    /// fit in one period (the space is there, cut up by a channel that stopped), the channel
    /// waits for the next period, where the group is laid out afresh; if they cannot fit
    /// (duties above 100 % together), it ends with the period and overlaps.
    pub fn set_lead(&mut self, after: Nanos, others: Nanos) {
        self.lead = (after, others);
    }

    /// Where the on phase of the running staggered period ends, ns after the period start
    /// (0 when it has none).
    pub fn placed_end(&self) -> Nanos {
        if self.plan.t_on == 0 {
            0
        } else {
            self.placed + self.plan.t_on
        }
    }

    /// Whether a slot is free for this channel under `max_simultaneous_on`: an on phase that
    /// starts without one waits, off, until [`Channel::grant`] (see [`Channel::occupies`]).
    pub fn set_slot(&mut self, free: bool) {
        self.slot = free;
    }

    /// The channel holds a slot: its line is high, or its schedule asks for high.
    pub fn occupies(&self) -> bool {
        self.level == Level::High || self.line.level == Level::High
    }

    /// When the on phase now waiting for a slot began to wait, ns; `None` when none waits.
    pub fn waiting_since(&self) -> Option<Nanos> {
        self.step
            .filter(|s| s.kind == StepKind::Wait)
            .map(|s| s.start)
    }

    /// A slot was given at `now` (ns; the instant the slot freed, which may lie a little before
    /// the caller's clock) to the on phase waiting for one: it starts then (not before it
    /// began to wait), with its whole length, and the break after it shrinks so the period
    /// keeps its end.
    pub fn grant(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        self.slot = true;
        if let Some(since) = self.waiting_since() {
            self.begin_on(now.max(since), emit);
        }
    }

    /// The on phase of the running period starts at `t`, if a slot is free under
    /// `max_simultaneous_on`; else it waits for one, as long as the whole pulse still fits in
    /// its period, and is skipped after that.
    pub(super) fn begin_on(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let len = self.plan.t_on;
        if !self.slot {
            let end = self.fix_period_end();
            self.slot_now = self.slot_now.max(SlotUse::Delayed);
            match end.checked_sub(len) {
                Some(latest) if latest > t => {
                    self.step = Some(Step::off(StepKind::Wait, t, latest));
                    self.set_level(Level::Low, t, emit);
                }
                _ => self.skip(t, emit),
            }
            return;
        }
        self.step = Some(Step {
            level: Level::High,
            start: t,
            end: t.saturating_add(len),
            kind: StepKind::Run,
        });
        self.set_level(Level::High, t, emit);
    }

    /// The end of the running period, fixed from now on: an on phase that starts late keeps
    /// its length and the break after it shrinks.
    fn fix_period_end(&mut self) -> Nanos {
        let end = self.period_end.unwrap_or(
            self.period_start
                .saturating_add(self.plan.t_on)
                .saturating_add(self.plan.t_off),
        );
        self.period_end = Some(end);
        end
    }

    /// No slot came before the latest start of the on phase: the pulse is skipped, off for
    /// the rest of the period.
    pub(super) fn skip(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        self.skipped += 1;
        self.slot_now = SlotUse::Skipped;
        emit(Event::Skipped);
        self.report_flags(emit);
        let end = self.fix_period_end();
        if end > t {
            self.step = Some(Step::off(StepKind::Run, t, end));
            self.set_level(Level::Low, t, emit);
        } else {
            self.start_period(t, emit);
        }
    }
}
