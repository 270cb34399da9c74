//! Where a channel's on phase goes, for the node-level planner ([`crate::core::Bank`]): the
//! stagger grid and lead, and the slot an on phase needs to start: under
//! `max_simultaneous_on` a free one, under stagger also no other line of its group on. An on
//! phase without a slot waits, off, keeping its whole length, and is skipped once it can no
//! longer fit its period.

use super::{Channel, Event, Level, Marks, Nanos, SlotUse, Step, StepKind};

/// Where a channel's running period and its on phase lie, and what the node-level planner
/// told it about them.
///
/// Rules, checked at every change: off the stagger grid there is no lead; a period's end, once
/// fixed, lies at or after its start; the count of skipped pulses never falls.
#[derive(Debug, Clone, Copy)]
pub(super) struct Placement {
    /// The stagger grid (see [`Channel::set_grid`]).
    pub(super) grid: bool,
    /// Where the on phases other channels placed in this staggered period end, ns after the
    /// period start, and the on time those of its group run per period, ns.
    pub(super) lead: (Nanos, Nanos),
    /// When the running period started, ns (monotonic).
    pub(super) period_start: Nanos,
    /// Where the on phase of the running period starts, ns after the period start (as placed
    /// on the stagger grid, or as started late for want of a slot), and how long it is, ns.
    pub(super) placed: Nanos,
    pub(super) on_len: Nanos,
    /// A slot is free under `max_simultaneous_on` (see [`Channel::set_slot`]).
    pub(super) slot: bool,
    /// The end of the running period, when it is fixed: by the stagger grid, or by an on phase
    /// delayed for a slot (the break after it shrinks so the period keeps its length).
    pub(super) period_end: Option<Nanos>,
    /// An on phase waited for a slot (or was skipped) in the running period, and in the one
    /// before.
    pub(super) slots: Marks<SlotUse>,
    /// Pulses skipped because no slot was free before their latest start.
    pub(super) skipped: u64,
}

impl Placement {
    /// Off the grid, a slot free, no period fixed; the first period counts from `now` (ns).
    pub(super) fn new(now: Nanos) -> Placement {
        Placement {
            grid: false,
            lead: (0, 0),
            period_start: now,
            placed: 0,
            on_len: 0,
            slot: true,
            period_end: None,
            slots: Marks::default(),
            skipped: 0,
        }
    }

    fn check(&self) {
        debug_assert!(
            self.grid || self.lead == (0, 0),
            "no lead off the stagger grid: {self:?}"
        );
        debug_assert!(
            self.period_end.is_none_or(|end| end >= self.period_start),
            "a period ends at or after its start: {self:?}"
        );
    }

    /// A period starts at `t` (ns) with an on phase of `on_len` (ns) at its start, its end
    /// fixed at `end` when the grid fixes it.
    pub(super) fn period_starts(&mut self, t: Nanos, on_len: Nanos, end: Option<Nanos>) {
        self.period_start = t;
        self.placed = 0;
        self.on_len = on_len;
        self.period_end = end;
        self.check();
    }

    /// The end of the running period, fixed from now on: the one fixed already, or `t_on +
    /// t_off` (ns) after its start.
    pub(super) fn fix_end(&mut self, t_on: Nanos, t_off: Nanos) -> Nanos {
        let end = self
            .period_end
            .unwrap_or(self.period_start.saturating_add(t_on).saturating_add(t_off));
        self.period_end = Some(end);
        self.check();
        end
    }

    /// The on phase of the running period starts `at` (ns) after the period's start: as placed
    /// on the stagger grid, or late for want of a slot.
    pub(super) fn on_at(&mut self, at: Nanos) {
        self.placed = at;
        self.check();
    }

    /// A new period: what waiting for a slot did in the last one becomes "the one before".
    pub(super) fn roll_marks(&mut self) {
        self.slots.roll();
    }

    /// The channel stops: no wait for a slot is remembered.
    pub(super) fn forget_marks(&mut self) {
        self.slots.clear();
    }

    /// A pulse of this period is skipped.
    pub(super) fn skip(&mut self) {
        self.skipped = self.skipped.saturating_add(1);
        self.slots.raise(SlotUse::Skipped);
    }
}

impl Channel {
    /// Puts the channel on the stagger grid (`true`) or takes it off (node parameter `phase`):
    /// on it, every period starts at a whole multiple of the period on the monotonic clock
    /// (a first period waits, off, for the next one), and its on phase starts at the lead set
    /// by [`Channel::set_lead`]. Takes effect at the next period start.
    pub fn set_grid(&mut self, on: bool) {
        self.place.grid = on;
        if !on {
            self.place.lead = (0, 0);
        }
        self.place.check();
    }

    /// Where the next staggered period's on phase goes, read when a period starts: `after`,
    /// where the on phases of the other channels of its group end in that period (ns after its
    /// start), and `others`, the on time those channels run per period (ns). The phase starts
    /// at `after` (or where the line's minimum break ends, if later) if it ends within the
    /// period there. If not, and all the phases would fit in one period (the space is there,
    /// cut up by a channel that stopped), the channel waits for the next period, where the
    /// group is laid out afresh; if they cannot fit (duties above 100 % together), it is
    /// placed to end with the period, where it waits for the line before it to go off.
    pub fn set_lead(&mut self, after: Nanos, others: Nanos) {
        self.place.lead = (after, others);
        self.place.check();
    }

    /// Whether acting at `now` may start a period: no schedule runs (an enable, a command
    /// from idle), or a step that can end a period (an off step, the alignment to the grid,
    /// an on step with no break after it) is due. A lead set for the next period matters only
    /// then.
    pub fn may_start_period(&self, now: Nanos) -> bool {
        match self.step {
            None => true,
            Some(s) => s.end <= now && matches!(s.kind, StepKind::Run | StepKind::Align),
        }
    }

    /// Where the on phase of the running period ends, ns (monotonic), as placed or as started
    /// late; `None` when it has none.
    pub fn on_end(&self) -> Option<Nanos> {
        (self.running() && self.place.on_len > 0).then(|| {
            self.place
                .period_start
                .saturating_add(self.place.placed)
                .saturating_add(self.place.on_len)
        })
    }

    /// Whether an on phase may start now (see [`Channel::occupies`]): a slot is free under
    /// `max_simultaneous_on` and, under stagger, no other line of its group is on. One that
    /// starts without it waits, off, until [`Channel::grant`].
    pub fn set_slot(&mut self, free: bool) {
        self.place.slot = free;
    }

    /// The channel holds a slot: its line is high, or its schedule asks for high.
    pub fn occupies(&self) -> bool {
        self.level == Level::High || self.line.level == Level::High
    }

    /// When the on phase waiting for a slot began to wait, ns, if one waits and may still
    /// start at `at` (ns) and fit its period.
    pub fn waiting_at(&self, at: Nanos) -> Option<Nanos> {
        self.step
            .filter(|s| s.kind == StepKind::Wait && s.end >= at)
            .map(|s| s.start)
    }

    /// A slot was given at `at` (ns; the instant it freed, which may lie a little before the
    /// caller's clock) to the on phase waiting for one: it starts then (not before it began
    /// to wait), with its whole length, and the break after it shrinks so the period keeps its
    /// end. A wait whose latest start has passed is skipped at that instant instead.
    pub fn grant(&mut self, at: Nanos, emit: &mut dyn FnMut(Event)) {
        let Some(wait) = self.step.filter(|s| s.kind == StepKind::Wait) else {
            return;
        };
        self.place.slot = true;
        if wait.end < at {
            return self.skip(wait.end, emit);
        }
        let t = at.max(wait.start);
        if t > wait.start {
            self.place.slots.raise(SlotUse::Delayed);
        }
        self.begin_on(t, emit);
    }

    /// Gives up the running on phase at `at` (ns) to bring the lines on under a lowered
    /// `max_simultaneous_on`: the schedule goes off for the rest of the period (the line
    /// follows once it has kept its minimum on time), and the shortened pulse sets E1. Does
    /// nothing without a running on phase.
    pub fn yield_slot(&mut self, at: Nanos, emit: &mut dyn FnMut(Event)) {
        if !self.step.is_some_and(|s| s.level == Level::High) {
            return;
        }
        let end = self.fix_period_end().max(at);
        self.place.slots.raise(SlotUse::Skipped);
        self.report_flags(emit);
        self.step = Some(Step::off(StepKind::Run, at, end));
        self.set_level(Level::Low, at, emit);
    }

    /// When the running on step started, ns, if one runs.
    pub fn on_since(&self) -> Option<Nanos> {
        self.step
            .filter(|s| s.level == Level::High)
            .map(|s| s.start)
    }

    /// The on phase of the running period starts at `t`, if it has a slot (see
    /// [`Channel::set_slot`]); else it waits for one, as long as the whole pulse still fits in
    /// its period, and is skipped after that.
    pub(super) fn begin_on(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let len = self.place.on_len;
        if !self.place.slot {
            let end = self.fix_period_end();
            match end.checked_sub(len) {
                Some(latest) if latest > t => {
                    self.step = Some(Step::off(StepKind::Wait, t, latest));
                    self.set_level(Level::Low, t, emit);
                }
                _ => self.skip(t, emit),
            }
            return;
        }
        if self
            .place
            .period_end
            .is_some_and(|end| t.saturating_add(len) > end)
        {
            // A pulse that grew while it waited no longer fits its period.
            return self.skip(t, emit);
        }
        self.place.on_at(t.saturating_sub(self.place.period_start));
        self.step = Some(Step {
            level: Level::High,
            start: t,
            end: t.saturating_add(len),
            kind: StepKind::Run,
        });
        self.set_level(Level::High, t, emit);
    }

    /// A re-evaluation (003) while the on phase waits: it waits for its new length, and is
    /// skipped at `now` if that can no longer fit.
    pub(super) fn rewait(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let Some(wait) = self.step.filter(|s| s.kind == StepKind::Wait) else {
            return;
        };
        self.place.on_len = self.plan.t_on;
        match self.fix_period_end().checked_sub(self.place.on_len) {
            _ if self.place.on_len == 0 => {
                let end = self.fix_period_end();
                self.step = Some(Step::off(StepKind::Run, wait.start, end));
            }
            Some(latest) if latest > now => {
                self.step = Some(Step {
                    end: latest,
                    ..wait
                })
            }
            _ => self.skip(now, emit),
        }
    }

    /// The end of the running period, fixed from now on: an on phase that starts late keeps
    /// its length and the break after it shrinks.
    fn fix_period_end(&mut self) -> Nanos {
        self.place.fix_end(self.plan.t_on, self.plan.t_off)
    }

    /// No slot came before the latest start of the on phase: the pulse is skipped, off for
    /// the rest of the period.
    pub(super) fn skip(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        self.place.skip();
        emit(Event::Skipped { at: t });
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A period's end is fixed once, from its start and plan, and then kept; a skip counts and
    /// marks the period.
    #[test]
    fn a_fixed_end_is_kept_and_a_skip_counts() {
        let mut p = Placement::new(0);
        p.period_starts(1_000, 300, None);
        assert_eq!(p.fix_end(300, 700), 2_000);
        assert_eq!(p.fix_end(500, 900), 2_000, "fixed once, then kept");
        p.skip();
        assert_eq!((p.skipped, p.slots.recent()), (1, SlotUse::Skipped));
        p.period_starts(2_000, 300, Some(3_000));
        assert_eq!(p.fix_end(300, 700), 3_000, "the grid's end");
    }

    /// The rules are checked where the placement is kept: a lead off the grid is caught.
    #[cfg(debug_assertions)]
    #[test]
    #[should_panic(expected = "no lead off the stagger grid")]
    fn a_lead_off_the_grid_is_caught() {
        let mut p = Placement::new(0);
        p.lead = (5, 5);
        p.check();
    }

    /// A period's end before its start is caught.
    #[cfg(debug_assertions)]
    #[test]
    #[should_panic(expected = "a period ends at or after its start")]
    fn an_end_before_the_start_is_caught() {
        let mut p = Placement::new(0);
        p.period_starts(1_000, 0, Some(999));
    }
}
