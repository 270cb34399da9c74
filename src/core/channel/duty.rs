//! The load's protections between a command and the plan: the power limits, the dead band and
//! the slew limit (what the channel plans for), and whether the maximum on time acts. The
//! rolling-average cap comes after them (`budget`): it limits the duty applied, not the
//! command in force.

use super::{Channel, Nanos};

impl Channel {
    /// The command in force after the power limits: what the slew limit moves toward.
    pub(super) fn target(&self) -> f64 {
        self.cfg.limit_duty(self.accepted)
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
            (false, _) if self.slewing() => self.slewed,
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
        let elapsed = self.slewed_at.map_or(0, |at| t.saturating_sub(at));
        self.slewed_at = Some(self.slewed_at.map_or(t, |at| at.max(t)));
        if self.slewing() && !self.watchdog.tripped() {
            let step = self.cfg.slew_per_s * elapsed as f64 / 1e9;
            let target = self.target();
            self.slewed = if self.slewed < target {
                (self.slewed + step).min(target)
            } else {
                (self.slewed - step).max(target)
            };
        } else if !self.enabled || self.cfg.period == 0 {
            self.slewed = 0.0;
            self.slewed_at = None;
        } else {
            self.slewed = self.effective_duty();
        }
        self.effective_duty()
    }

    /// Whether the maximum on time acts: the plan in force keeps the line high longer, or it
    /// cut the line in this period or the one before.
    pub(super) fn max_on_acts(&self) -> bool {
        self.plan.max_on || self.cut_now || self.cut_before
    }
}
