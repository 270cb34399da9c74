//! The rolling-average duty cap (`avg_duty_limit_pct` over `avg_window_s`): an
//! energy budget. Over every window of `avg_window_s` the line is on for at most the limit
//! times the window.
//!
//! The line's past on time is kept in a fixed ring of [`BUCKETS`] buckets, each
//! `ceil(W / (BUCKETS - 1))` long, so that every bucket overlapping a window of `W` ending now
//! is still in the ring. A high span is counted when it ends (a fall), each part in the bucket
//! it lies in; the running one is counted up to now when deciding (at most `W` of it). The
//! window ending at `t` counts every bucket that overlaps it whole, so the count only errs up:
//! the on time of the line within `(t - W, t]` is never more than [`Channel::avg_spent`] says,
//! and at most one bucket's worth less.
//!
//! A wake-up later than its deadlines handles them in one batch at their own instants, but no
//! edge of the batch reaches the line before the batch's `now`: a fall the batch takes leaves
//! the line on until then. Its span is counted up to `now` at once, so a decision later in the
//! same batch (the next period's start, when the late wake-up swallowed a short break) sees
//! the line on; and when the batch's edges cancel out (the break never reached the line), the
//! part counted is not counted again at the real fall.
//!
//! At each decision point where an on phase may start or run (a period start, a step start
//! under `next_step` and `immediate`, a re-evaluation), the budget is the limit times `W` less
//! the on time spent in the window ending now. The on time the plan commits the line to until
//! the next decision (its on time, or the rest of a running pulse's minimum on time, whichever
//! is longer) must fit in it: else the duty is lowered to `budget / T` before the minimum-time
//! rules, and if a rule still raises the on time above the budget, the period is planned off.
//! So every window ending between this decision and the next holds at most the past on time
//! counted plus the on time committed, which is within the limit: the cap is a promise about
//! the energy, exact in virtual time, and only ever holds the duty lower than an exact sliding
//! window would. A decision that only times a break (the end of an on step) keeps to what the
//! last decision allowed.

use super::super::plan::{Plan, Rule};
use super::{Channel, Level, Nanos};

/// The least margin kept for a fall's lateness on a line whose writes take time, ns: about what
/// one write takes here (tens of µs), with room; it covers the first fall, before any has been
/// seen.
pub(super) const FALL_LAG_FLOOR: Nanos = 100_000;

/// Buckets in the ring of past on time.
pub(super) const BUCKETS: usize = 64;

/// The line's on time over the rolling-average window, and what the cap decided last.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Budget {
    /// On time of finished high spans, ns, by the bucket of their fall: bucket `k` (time `k *
    /// width ..`) is at `k % BUCKETS`.
    on: [Nanos; BUCKETS],
    /// The newest bucket written; those more than `BUCKETS - 1` before it are gone.
    newest: u64,
    /// Bucket length, ns.
    width: Nanos,
    /// The window the buckets were laid out for, ns.
    window: Nanos,
    /// The on time the last decision allowed until the next one, ns (`Nanos::MAX`: no cap).
    allowance: Nanos,
    /// The cap holds the plan below what the other rules give.
    pub(super) acts: bool,
    /// How much later than scheduled falls reach the line (a late wake-up, the write itself),
    /// ns: the largest seen, decaying by a sixteenth at each fall, and at least
    /// [`FALL_LAG_FLOOR`] once the line has shown a write of its own (0 in virtual time, where
    /// edges take no time); kept as a margin for the next fall.
    fall_lag: Nanos,
    /// The line's on time before this instant is counted in the ring, ns: the end of the last
    /// span counted. A span is counted from here at the earliest, and so is the running one.
    counted_to: Nanos,
    /// While a late batch of deadlines is handled: its `now`, before which none of its edges
    /// reaches the line, ns (0 otherwise).
    batch_now: Nanos,
}

impl Budget {
    /// An empty ring for a window of `window` ns.
    pub(super) fn new(window: Nanos) -> Budget {
        let width = window.div_ceil(BUCKETS as Nanos - 1).max(1);
        Budget {
            on: [0; BUCKETS],
            newest: 0,
            width,
            window,
            allowance: Nanos::MAX,
            acts: false,
            fall_lag: 0,
            counted_to: 0,
            batch_now: 0,
        }
    }

    /// Counts the high span `[from, to)` (ended by a fall at `to`), each part in its bucket.
    /// Parts older than the ring lie before every window still to come and are dropped; parts
    /// in buckets the ring no longer holds apart (a span counted late) go to its oldest.
    fn count(&mut self, from: Nanos, to: Nanos) {
        let last = to / self.width;
        if last > self.newest {
            let fresh = (last - self.newest).min(BUCKETS as u64);
            for i in 0..fresh {
                self.on[((last - i) % BUCKETS as u64) as usize] = 0;
            }
            self.newest = last;
        }
        let oldest = self.newest.saturating_sub(BUCKETS as u64 - 1);
        let from = from.max(oldest.saturating_mul(self.width));
        let mut at = from;
        while at < to {
            let k = at / self.width;
            let end = k.saturating_add(1).saturating_mul(self.width).min(to);
            let slot = &mut self.on[(k.max(oldest) % BUCKETS as u64) as usize];
            *slot = slot.saturating_add(end - at);
            at = end;
        }
    }

    /// Counts the on time `[from, to)` of the line, less what is counted already (before
    /// `counted_to`).
    fn count_span(&mut self, from: Nanos, to: Nanos) {
        let from = from.max(self.counted_to);
        if to > from {
            self.count(from, to);
            self.counted_to = to;
        }
    }

    /// The on time counted in the buckets that overlap `(t - window, t]`, ns.
    fn within(&self, t: Nanos) -> Nanos {
        let first = t.saturating_sub(self.window) / self.width;
        let oldest = self.newest.saturating_sub(BUCKETS as u64 - 1);
        (first.max(oldest)..=self.newest)
            .map(|k| self.on[(k % BUCKETS as u64) as usize])
            .fold(0, Nanos::saturating_add)
    }

    /// Lays the ring out for a window of `window` ns at `now`: the on time counted in the old
    /// window ending now is counted as if it ran just before `now` (later, so never less).
    fn relayout(&mut self, window: Nanos, now: Nanos) {
        if window == self.window {
            return;
        }
        let total = self.within(now).min(window);
        *self = Budget {
            allowance: self.allowance,
            acts: self.acts,
            fall_lag: self.fall_lag,
            counted_to: self.counted_to,
            batch_now: self.batch_now,
            ..Budget::new(window)
        };
        self.count(now.saturating_sub(total), now);
    }
}

impl Channel {
    /// Whether the rolling-average cap is set.
    fn avg_capped(&self) -> bool {
        self.cfg.avg_limit < 1.0
    }

    /// The line fell at `at` after being high since `since`: counts the span, in a late batch
    /// up to the batch's `now` (the fall reaches the line no earlier).
    pub(super) fn avg_fall(&mut self, since: Nanos, at: Nanos) {
        let to = at.max(self.avg.batch_now);
        self.avg.count_span(since.min(at), to);
        // The heater got that on time too (its checks and model count what the line did).
        self.heat_on_time(since.min(at), to);
    }

    /// A batch of deadlines handled at `now` begins (`now`) or ends (what this returned when
    /// it began): see [`Channel::avg_fall`].
    pub(super) fn avg_batch(&mut self, now: Nanos) -> Nanos {
        std::mem::replace(&mut self.avg.batch_now, now)
    }

    /// An edge reached the line after it was emitted: the line's writes take time, so every
    /// fall keeps at least [`FALL_LAG_FLOOR`] as a margin from now on.
    pub(super) fn avg_write_seen(&mut self) {
        self.avg.fall_lag = self.avg.fall_lag.max(FALL_LAG_FLOOR);
    }

    /// A fall scheduled at `scheduled` reached the line only at `actual`: the line was on
    /// until then, and the next fall may be as late (kept as a margin, see `committed`).
    pub(super) fn avg_late_fall(&mut self, scheduled: Nanos, actual: Nanos) {
        if actual <= scheduled {
            return;
        }
        self.avg.count_span(scheduled, actual);
        self.heat_on_time(scheduled, actual);
        let lag = actual - scheduled;
        self.avg.fall_lag = lag
            .max(self.avg.fall_lag - self.avg.fall_lag / 16)
            .max(FALL_LAG_FLOOR);
    }

    /// Lays the ring out for the window in force at `now` (after a configuration change).
    pub(super) fn avg_relayout(&mut self, now: Nanos) {
        self.avg.relayout(self.cfg.avg_window, now);
    }

    /// The on time of the line within the window ending at `t`, ns, as the channel counts it
    /// (never less than the real one): the finished spans and the running one (from where the
    /// ring's count ends).
    pub(super) fn avg_spent(&self, t: Nanos) -> Nanos {
        let running = match (self.line.level, self.line.since) {
            (Level::High, Some(since)) => t
                .saturating_sub(since.max(self.avg.counted_to))
                .min(self.avg.window),
            _ => 0,
        };
        self.avg.within(t).saturating_add(running)
    }

    /// The rolling average of the line over the window ending at `t`, fraction, as the
    /// channel counts it.
    pub(super) fn avg_duty(&self, t: Nanos) -> f64 {
        (self.avg_spent(t) as f64 / self.avg.window as f64).min(1.0)
    }

    /// The most on time the line can have from `t` until the next decision under `plan`, ns:
    /// its on time, or what is left of the running pulse's minimum on time, whichever is
    /// longer (a rise also lasts its minimum); and if `max_on_ms` can cut the on phase, one
    /// more minimum on time (the pulse that resumes after the cut lasts its minimum, and may
    /// outlast the on phase by that much); and for each fall, the lateness falls have shown.
    fn committed(&self, plan: &Plan, t: Nanos) -> Nanos {
        let (on, high_since) = match (self.line.level, self.line.since) {
            (Level::High, Some(since)) => (
                plan.t_on
                    .max(since.saturating_add(self.cfg.min_on).saturating_sub(t)),
                since,
            ),
            _ if plan.t_on > 0 => (plan.t_on.max(self.cfg.min_on), t),
            _ => return 0,
        };
        // Each fall may reach the line as late as the falls before it did.
        let lag = self.avg.fall_lag;
        let max_on = self.cfg.max_on;
        if max_on > 0 && high_since.saturating_add(max_on) < t.saturating_add(on) {
            on.saturating_add(self.cfg.min_on)
                .saturating_add(lag.saturating_mul(2))
        } else {
            on.saturating_add(lag)
        }
    }

    /// The plan for `duty` at a decision `t` where an on phase may start or run, under the
    /// cap: fresh budget from the window ending at `t`. `grid`: lay an extended plan on the
    /// stagger grid of this period.
    pub(super) fn capped_plan(&mut self, t: Nanos, duty: f64, grid: Option<Nanos>) -> Plan {
        self.avg.allowance = if self.avg_capped() {
            let limit = (self.cfg.avg_limit * self.avg.window as f64).floor() as Nanos;
            limit.saturating_sub(self.avg_spent(t))
        } else {
            Nanos::MAX
        };
        self.allowed_plan(t, duty, grid)
    }

    /// The plan for `duty` at a decision `t` that only times a break: within what the last
    /// decision allowed.
    pub(super) fn break_plan(&mut self, t: Nanos, duty: f64) -> Plan {
        self.allowed_plan(t, duty, None)
    }

    /// The plan for `duty` whose committed on time fits the allowance: the duty lowered to
    /// `allowance / T`, or 0 if a minimum-time rule would still exceed it.
    fn allowed_plan(&mut self, t: Nanos, duty: f64, grid: Option<Nanos>) -> Plan {
        let shape = |duty: f64| {
            let plan = Plan::carried(duty, &self.cfg, self.carry.taken());
            grid.map_or(plan, |g| plan.on_grid(g, self.cfg.tick))
        };
        let plan = shape(duty);
        let allowance = self.avg.allowance;
        let fits = |p: &Plan| self.committed(p, t) <= allowance;
        let period = self.cfg.period as f64;
        let allowed = if fits(&plan) || self.cfg.period == 0 {
            plan
        } else {
            let capped = shape(duty.min(allowance as f64 / period));
            // What the line may add beyond the on time (a minimum, a resume after a cut)
            // comes off the on time too.
            let extra = self.committed(&capped, t).saturating_sub(capped.t_on);
            let tighter = shape(duty.min(allowance.saturating_sub(extra) as f64 / period));
            match (fits(&capped), fits(&tighter)) {
                (true, _) => capped,
                (false, true) => tighter,
                (false, false) => shape(0.0),
            }
        };
        // A duty the cap lowered below what a pulse can be (a sliver of budget left): the
        // period is off by the cap, not E1 — the cap is a configured limit.
        let allowed = if allowed.t_on < plan.t_on && allowed.rule == Rule::SuppressedPulse {
            shape(0.0)
        } else {
            allowed
        };
        self.avg.acts = allowed.t_on < plan.t_on;
        self.carry.leave(allowed.carry);
        allowed
    }
}
