//! The load's protections between a command and the plan: the power limits, the dead band and
//! the slew limit (what the channel plans for), and whether the maximum on time acts. The
//! rolling-average cap comes after them (`budget`): it limits the duty applied, not the
//! command in force.

use super::super::config::ChannelConfig;
use super::super::plan::definitely_less;
use super::{Channel, Nanos};

/// The slew limit's own state: the duty it has brought the channel to and the decision
/// instant it was advanced to.
///
/// Invariant, checked at every change: the duty lies in 0..=1, and the instant never moves
/// back (a ramp is exact in virtual time: each step is the rate times the time since the last
/// decision).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Slew {
    /// The duty reached, fraction.
    reached: f64,
    /// The last decision instant, ns; `None` while no pulses run.
    at: Option<Nanos>,
}

impl Slew {
    fn check(&self) {
        debug_assert!(
            (0.0..=1.0).contains(&self.reached),
            "the slew limit's duty lies in 0..=1: {self:?}"
        );
    }

    /// Takes `t` (ns) as the new decision instant; the time since the last one, ns.
    fn decision(&mut self, t: Nanos) -> Nanos {
        let elapsed = self.at.map_or(0, |at| t.saturating_sub(at));
        self.at = Some(self.at.map_or(t, |at| at.max(t)));
        elapsed
    }

    /// A decision at `t` (ns) while the limit acts: the duty moves toward `target` (fraction)
    /// by at most `rate_per_s` (fraction per second) times the time since the last decision.
    pub(super) fn ramp(&mut self, t: Nanos, rate_per_s: f64, target: f64) {
        let step = rate_per_s * self.decision(t) as f64 / 1e9;
        self.reached = if self.reached < target {
            (self.reached + step).min(target)
        } else {
            (self.reached - step).max(target)
        };
        self.check();
    }

    /// A decision at `t` (ns) while the limit does not act: the duty that runs (fraction) is
    /// where a later ramp starts.
    pub(super) fn follow(&mut self, t: Nanos, duty: f64) {
        self.decision(t);
        self.reached = duty;
        self.check();
    }

    /// No pulses run: the next ramp starts from 0 at the next decision.
    pub(super) fn stop(&mut self) {
        *self = Slew::default();
    }

    /// The duty reached, fraction.
    pub(super) fn reached(&self) -> f64 {
        self.reached
    }
}

/// The dead band (relay wear): the command in force, and the valid commands it ignored.
///
/// Rule: a change of the limited duty smaller than the band is ignored; the ends (at or beyond
/// `min_duty_pct` or `max_duty_pct`) always pass, so the load can always be switched fully off
/// or to its maximum. The command in force lies in 0..=1 (checked at every change).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct DeadBand {
    /// The fraction of the command in force: the last valid command let through, before the
    /// power limits.
    accepted: f64,
    /// Valid commands ignored.
    ignored: u64,
    /// The last valid command was ignored.
    last_ignored: bool,
}

impl DeadBand {
    /// A valid command of `fraction` (0..=1, before the power limits) under `cfg`: taken, or
    /// ignored and counted. Whether it was taken.
    pub(super) fn offer(&mut self, fraction: f64, cfg: &ChannelConfig) -> bool {
        let candidate = cfg.limit_duty(fraction);
        let in_force = cfg.limit_duty(self.accepted);
        let end = candidate <= cfg.min_duty || candidate >= cfg.max_duty;
        self.last_ignored = cfg.deadband > 0.0
            && candidate != in_force
            && !end
            && definitely_less((candidate - in_force).abs(), cfg.deadband);
        if self.last_ignored {
            self.ignored += 1;
        } else {
            self.accepted = fraction;
        }
        debug_assert!(
            (0.0..=1.0).contains(&self.accepted),
            "the command in force lies in 0..=1: {self:?}"
        );
        !self.last_ignored
    }

    /// The command in force, fraction before the power limits.
    pub(super) fn accepted(&self) -> f64 {
        self.accepted
    }

    /// Valid commands ignored since start.
    pub(super) fn ignored(&self) -> u64 {
        self.ignored
    }

    /// The last valid command was ignored.
    pub(super) fn last_ignored(&self) -> bool {
        self.last_ignored
    }
}

impl Channel {
    /// The command in force after the power limits: what the slew limit moves toward.
    pub(super) fn target(&self) -> f64 {
        self.cfg.limit_duty(self.band.accepted())
    }

    /// Whether the slew limit shapes the duty applied: set, and the channel pulsing.
    pub(super) fn slewing(&self) -> bool {
        self.cfg.slew_per_s > 0.0 && self.enabled && self.cfg.period > 0
    }

    /// The duty the plans are made for: the command in force (as far as the slew limit has
    /// brought it), or the watchdog's fault value (limited to `max_duty_pct`) or 0. A disabled
    /// channel computes for the command in force (002), which it ramps toward once enabled.
    pub(super) fn effective_duty(&self) -> f64 {
        match (self.watchdog.tripped(), self.watchdog.fault_value_runs()) {
            (false, _) if self.slewing() => self.slew.reached(),
            (false, _) => self.target(),
            (true, true) => self.cfg.fault_duty.min(self.cfg.max_duty),
            (true, false) => 0.0,
        }
    }

    /// A decision point at `t` (a period or step start, a re-evaluation): the slew limit moves
    /// the duty applied toward the target by at most its rate times the time since the last
    /// decision, so it is exact in virtual time. Returns the duty to plan for. Where nothing
    /// ramps, the duty applied is what runs (0 with no pulses), and a later ramp starts there.
    pub(super) fn decide(&mut self, t: Nanos) -> f64 {
        if self.slewing() && !self.watchdog.tripped() {
            self.slew.ramp(t, self.cfg.slew_per_s, self.target());
        } else if !self.enabled || self.cfg.period == 0 {
            self.slew.stop();
        } else {
            let runs = self.effective_duty();
            self.slew.follow(t, runs);
        }
        self.effective_duty()
    }

    /// Whether the maximum on time acts: the plan in force keeps the line high longer, or it
    /// cut the line in this period or the one before.
    pub(super) fn max_on_acts(&self) -> bool {
        self.plan.max_on || self.cuts.recent()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_slew_limit_ramps_exactly_in_virtual_time_and_restarts_from_zero() {
        const S: Nanos = 1_000_000_000;
        let mut s = Slew::default();
        // The first decision only starts the clock.
        s.ramp(10 * S, 0.1, 1.0);
        assert_eq!(s.reached(), 0.0);
        s.ramp(12 * S, 0.1, 1.0);
        assert!((s.reached() - 0.2).abs() < 1e-12);
        // An instant before the last one moves nothing and keeps the clock.
        s.ramp(11 * S, 0.1, 1.0);
        assert!((s.reached() - 0.2).abs() < 1e-12);
        s.ramp(13 * S, 0.1, 1.0);
        assert!((s.reached() - 0.3).abs() < 1e-12);
        // Down toward a lower target, never past it.
        s.ramp(23 * S, 0.1, 0.25);
        assert_eq!(s.reached(), 0.25);
        // Not acting: the running duty is where the next ramp starts.
        s.follow(24 * S, 0.6);
        s.ramp(25 * S, 0.1, 1.0);
        assert!((s.reached() - 0.7).abs() < 1e-12);
        s.stop();
        s.ramp(30 * S, 0.1, 1.0);
        assert_eq!(s.reached(), 0.0);
    }
}
