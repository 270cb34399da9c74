//! The heater checks that need a history: `not_heating` (Klipper's `verify_heater`),
//! `stuck_on` (a rise while the line was held off), `sensor_stuck` (a reading that stands
//! still while the heater's power moves) and `sensor_jump` (a reading that moves faster than
//! a heater can). The range and sensor-timeout checks need none and live with the channel's
//! heater state; `model_deviation` lives with the model.
//!
//! Pure state machines: the caller passes the instant, the reading and what the line did.

pub use super::super::config::heater::{Runaway, StuckLimits};
use super::super::Nanos;

/// Snapshots of the line's cumulative on time kept for the delivered duty.
const ENERGY_SLOTS: usize = 128;

/// The line's cumulative on time at past instants, for the duty it really delivered over a
/// stretch of time. Snapshots are taken at readings, spaced to cover `span`; between two the
/// on time is interpolated (the error is at most the on time of one spacing).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Delivered {
    ring: [(Nanos, Nanos); ENERGY_SLOTS],
    head: usize,
    len: usize,
    spacing: Nanos,
}

impl Delivered {
    /// A history covering at least `span` ns.
    pub fn new(span: Nanos) -> Delivered {
        Delivered {
            ring: [(0, 0); ENERGY_SLOTS],
            head: 0,
            len: 0,
            spacing: (span / (ENERGY_SLOTS as Nanos / 2)).max(1),
        }
    }

    /// Records the cumulative on time `on_total` (ns) at `now`.
    pub fn record(&mut self, now: Nanos, on_total: Nanos) {
        let newest = (self.len > 0).then(|| self.ring[(self.head + self.len - 1) % ENERGY_SLOTS]);
        if newest.is_some_and(|(t, _)| now < t.saturating_add(self.spacing)) {
            return;
        }
        if self.len == ENERGY_SLOTS {
            self.head = (self.head + 1) % ENERGY_SLOTS;
            self.len -= 1;
        }
        self.ring[(self.head + self.len) % ENERGY_SLOTS] = (now, on_total);
        self.len += 1;
    }

    /// The cumulative on time at `t`, interpolated; `None` before the oldest snapshot.
    fn at(&self, t: Nanos, now: Nanos, on_now: Nanos) -> Option<Nanos> {
        let slot = |k: usize| self.ring[(self.head + k) % ENERGY_SLOTS];
        // The first snapshot at or after `t`: `record` keeps their times rising.
        let lo = super::first_at_or_after(self.len, |k| slot(k).0, t);
        let prev = lo.checked_sub(1).map(slot);
        if lo < self.len {
            let (tk, ek) = slot(lo);
            return match prev {
                Some((tp, ep)) if tk > tp => {
                    Some(ep + ((ek - ep) as u128 * (t - tp) as u128 / (tk - tp) as u128) as Nanos)
                }
                Some(_) => Some(ek),
                None => (tk == t).then_some(ek),
            };
        }
        match prev {
            Some((tp, ep)) if now > tp && t <= now => Some(
                ep + ((on_now.saturating_sub(ep)) as u128 * (t - tp) as u128 / (now - tp) as u128)
                    as Nanos,
            ),
            _ => None,
        }
    }

    /// The cumulative on time at `t` (at most `now`), interpolated; `None` before the oldest
    /// snapshot.
    pub fn at_time(&self, t: Nanos, now: Nanos, on_now: Nanos) -> Option<Nanos> {
        if t == now {
            Some(on_now)
        } else {
            self.at(t, now, on_now)
        }
    }

    /// How far the line's cumulative on time between `from` and `now` strays from the chord
    /// between its two ends, at most, in seconds of full power: 0 for a constant duty (up to
    /// the PWM's own ripple), `ρ·T²/8` for a duty ramping at `ρ` per second over `T` seconds.
    /// `None` when the history does not reach back to `from`.
    pub fn swing(&self, from: Nanos, now: Nanos, on_now: Nanos) -> Option<f64> {
        if from >= now {
            return None;
        }
        let e0 = self.at(from, now, on_now)? as f64;
        let slope = (on_now as f64 - e0) / (now - from) as f64;
        let mut worst: f64 = 0.0;
        for k in 0..self.len {
            let (tk, ek) = self.ring[(self.head + k) % ENERGY_SLOTS];
            if tk <= from || tk >= now {
                continue;
            }
            let chord = e0 + slope * (tk - from) as f64;
            worst = worst.max((ek as f64 - chord).abs());
        }
        Some(worst / 1e9)
    }

    /// The duty the line delivered between `from` and `now`, fraction (`on_now`: the
    /// cumulative on time at `now`); `None` when the history does not reach back to `from`.
    pub fn duty(&self, from: Nanos, now: Nanos, on_now: Nanos) -> Option<f64> {
        self.duty_between(from, now, now, on_now)
    }

    /// The duty the line delivered between `from` and `to` (at most `now`), fraction.
    pub fn duty_between(&self, from: Nanos, to: Nanos, now: Nanos, on_now: Nanos) -> Option<f64> {
        if from >= to || to > now {
            return None;
        }
        let a = self.at(from, now, on_now)?;
        let b = if to == now {
            on_now
        } else {
            self.at(to, now, on_now)?
        };
        Some(b.saturating_sub(a) as f64 / (to - from) as f64)
    }
}

/// What `sensor_stuck` found: the reading stood still for `still_s` while the energy the
/// heater got swung by `swing_s` seconds of full power, or while it was at full power.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Still {
    /// The reading that stands still, °C.
    pub celsius: f64,
    /// How long it has, s.
    pub still_s: f64,
    /// The swing of the energy the heater got meanwhile, seconds of full power (see
    /// [`Delivered::swing`]; during an autotune, the surplus over the relay's mean).
    pub swing_s: f64,
    /// The heater was at full power all the while.
    pub full: bool,
}

/// `sensor_stuck`: a reading that has not moved by more than the band while the heater's
/// power moved enough that it must have. A frozen reading under a PI loop leaves the
/// proportional term standing and the integral ramping: the duty ramps, and the energy the
/// heater gets strays from a straight line by `ρ·T²/8` over `T` seconds. A healthy heater
/// whose power ramps through the one that holds it is moved by at least `r` times that
/// (`r`: its rise at full power, °C/s): a sensor that stays on one step through it is stuck.
/// A quantised sensor that repeats its value while settled passes (the duty stands still
/// with it), and so does one that stays on a step across the turning point of a transient
/// (the loop's reaction to the move before is a step of the duty, not a swing). At full power
/// all the while, a heater below its full-power temperature must rise: a reading frozen for
/// the check's time there is stuck too. The swing counts the energy up to half the check's
/// time ago: what came later may still be on its way through the heater's dead time, which
/// the check's time must therefore be at least twice. During an autotune's cycles the relay's mean power
/// holds the heater at the target: the energy beyond it, `reference_factor` times the swing
/// limit, must move the reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stuck {
    /// The reading the check compares against, since when it stands, the line's cumulative on
    /// time then, ns.
    anchor: Option<(f64, Nanos, Nanos)>,
    /// The line's cumulative on time since the anchor, `(instant, ns)`, thinned as it fills
    /// (every other point dropped, the spacing doubled): any stretch fits, at a resolution
    /// of a 32nd of it.
    trail: [(Nanos, Nanos); TRAIL],
    len: usize,
    stride: Nanos,
}

/// Points kept of the energy since a reading last moved.
const TRAIL: usize = 64;

impl Default for Stuck {
    fn default() -> Self {
        Stuck {
            anchor: None,
            trail: [(0, 0); TRAIL],
            len: 0,
            stride: 0,
        }
    }
}

/// Above this share of its upper limit (`max_duty_pct`) the delivered duty counts as full
/// power.
pub const FULL_POWER: f64 = 0.98;

/// During an autotune, the surplus over the relay's mean that makes a still reading stuck,
/// in multiples of `sensor_stuck_energy_s`: a ramp's swing is an eighth of its surplus over
/// the power it starts from, and half of it lies on each side of the power that holds the
/// heater; four swings are a ramp's surplus beyond that power.
pub const REFERENCE_FACTOR: f64 = 4.0;

impl Stuck {
    /// Forgets the anchor: the check starts afresh at the next reading.
    pub fn clear(&mut self) {
        self.anchor = None;
        self.len = 0;
    }

    fn start(&mut self, now: Nanos, celsius: f64, on_now: Nanos) {
        self.anchor = Some((celsius, now, on_now));
        self.trail[0] = (now, on_now);
        self.len = 1;
        self.stride = 250_000_000;
    }

    fn record(&mut self, now: Nanos, on_now: Nanos) {
        if now < self.trail[self.len - 1].0.saturating_add(self.stride) {
            return;
        }
        if self.len == TRAIL {
            // Thin: keep every other point (the first one stays), double the spacing.
            for k in 1..TRAIL / 2 {
                self.trail[k] = self.trail[2 * k];
            }
            self.len = TRAIL / 2;
            self.stride = self.stride.saturating_mul(2);
        }
        self.trail[self.len] = (now, on_now);
        self.len += 1;
    }

    /// How far the energy since the anchor, up to `to`, strays from its chord, at most, s of
    /// full power (see [`Delivered::swing`]).
    fn swing(&self, to: Nanos) -> f64 {
        let pts = &self.trail[..self.len];
        let Some(end) = pts.iter().rposition(|(t, _)| *t <= to) else {
            return 0.0;
        };
        let (t0, e0) = pts[0];
        let (t1, e1) = pts[end];
        if t1 <= t0 {
            return 0.0;
        }
        let slope = (e1 as f64 - e0 as f64) / (t1 - t0) as f64;
        let worst = pts[..=end]
            .iter()
            .map(|(t, e)| (*e as f64 - (e0 as f64 + slope * (t - t0) as f64)).abs())
            .fold(0.0, f64::max);
        worst / 1e9
    }

    /// A fresh reading `celsius` at `now` while the heater is driven. `period` is the PWM
    /// period (its own ripple in the energy, a quarter period at most, is allowed for),
    /// `delivered` the line's history and `on_now` its cumulative on time now, ns;
    /// `reference`, during an autotune's cycles, the relay's mean power, fraction. Returns
    /// what it found when the check trips.
    #[allow(clippy::too_many_arguments)]
    pub fn reading(
        &mut self,
        now: Nanos,
        celsius: f64,
        limits: &StuckLimits,
        period: Nanos,
        delivered: &Delivered,
        on_now: Nanos,
        reference: Option<f64>,
    ) -> Option<Still> {
        if limits.time == 0 {
            return None;
        }
        let Some((value, since, on_at)) = self.anchor else {
            self.start(now, celsius, on_now);
            return None;
        };
        if (celsius - value).abs() > limits.band_c {
            self.start(now, celsius, on_now);
            return None;
        }
        self.record(now, on_now);
        let still = now.saturating_sub(since);
        if still < limits.time {
            return None;
        }
        let ripple = period as f64 / 1e9 / 4.0;
        let swing_s = match reference {
            Some(u) => {
                let got = on_now.saturating_sub(on_at) as f64;
                ((got - u * still as f64) / 1e9).abs() / REFERENCE_FACTOR
            }
            // The energy of the last half of the check's time has not all reached the
            // sensor yet (the heater's dead time is at most that): the swing counts up to
            // there.
            None => self.swing(now.saturating_sub(limits.time / 2)),
        };
        let swung = swing_s - ripple >= limits.energy_s;
        let full = delivered
            .duty(now.saturating_sub(limits.time), now, on_now)
            .is_some_and(|d| d >= FULL_POWER * limits.full);
        (swung || full).then_some(Still {
            celsius: value,
            still_s: still as f64 / 1e9,
            swing_s,
            full,
        })
    }
}

/// Buckets of readings kept for `no_rise`.
const RISE_BUCKETS: usize = 64;

/// What `no_rise` found: at full power for `full_s`, the reading's mean went from
/// `start_c` to `now_c`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Flat {
    /// The mean reading at the start of the stretch, °C.
    pub start_c: f64,
    /// The mean reading at its end, °C.
    pub now_c: f64,
    /// How long the heater was at full power, s.
    pub full_s: f64,
}

/// `no_rise`: the heater at full power for the check's time (the loop or an autotune asking
/// for more heat), and the reading's mean over the last bucket no higher than the lowest mean
/// of the window's first half plus the band and twice the scatter of that difference (from
/// the readings' own scatter within the buckets). The check's time must be at least twice
/// the heater's dead time. A heater below its full-power temperature rises once its dead time has
/// passed; a sensor that fell off its block or is shorted to ambient, or a heater that lost
/// its power, does not. Means over buckets of at least a second keep the sensor's noise out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NoRise {
    /// Per bucket: its index (instant / width), the sum, the sum of squares and the count of
    /// its readings.
    ring: [(u64, f64, f64, u32); RISE_BUCKETS],
    width: Nanos,
}

impl Default for NoRise {
    fn default() -> Self {
        NoRise::new(1_000_000_000)
    }
}

impl NoRise {
    /// A check for a time of `time` ns: buckets of a second, or of a 32nd of it.
    pub fn new(time: Nanos) -> NoRise {
        NoRise {
            ring: [(u64::MAX, 0.0, 0.0, 0); RISE_BUCKETS],
            width: (time / 32).max(1_000_000_000),
        }
    }

    /// Forgets the readings: the check starts afresh.
    pub fn clear(&mut self) {
        *self = NoRise {
            ring: [(u64::MAX, 0.0, 0.0, 0); RISE_BUCKETS],
            width: self.width,
        };
    }

    /// Bucket `k`'s mean, its count, and the sum of squared deviations of its readings.
    fn bucket(&self, k: u64) -> Option<(f64, f64, f64)> {
        let (i, sum, squares, n) = self.ring[(k % RISE_BUCKETS as u64) as usize];
        (i == k && n > 0).then(|| {
            let n = f64::from(n);
            let mean = sum / n;
            (mean, n, (squares - n * mean * mean).max(0.0))
        })
    }

    /// A fresh reading `celsius` at `now`; `full` says the heater has been at full power (the
    /// loop or an autotune asking for it) for the last `time` ns (0 = off). Returns what it
    /// found when the check trips; a rise of at most `band_c` is no rise.
    pub fn reading(
        &mut self,
        now: Nanos,
        celsius: f64,
        time: Nanos,
        band_c: f64,
        full: bool,
    ) -> Option<Flat> {
        let k = now / self.width;
        let slot = &mut self.ring[(k % RISE_BUCKETS as u64) as usize];
        if slot.0 != k {
            *slot = (k, 0.0, 0.0, 0);
        }
        slot.1 += celsius;
        slot.2 += celsius * celsius;
        slot.3 += 1;
        if time == 0 || !full {
            return None;
        }
        let first = now.saturating_sub(time) / self.width;
        let half = now.saturating_sub(time / 2) / self.width;
        // The lowest mean of the window's first half: a heater whose reading still fell when
        // its power came (its dead time, at most half the check's time) turns there.
        let (start, n0) = (first..half)
            .filter_map(|j| self.bucket(j))
            .map(|(m, n, _)| (m, n))
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        let (end, n1, _) = self.bucket(k)?;
        // The sensor's own scatter, pooled over the window's buckets: a rise within twice
        // the scatter of the difference of two means is none.
        let (mut ss, mut dof) = (0.0, 0.0);
        for j in first..=k {
            if let Some((_, n, sq)) = self.bucket(j) {
                ss += sq;
                dof += n - 1.0;
            }
        }
        let var = if dof > 0.0 { ss / dof } else { 0.0 };
        let noise = 2.0 * (var / n0 + var / n1).sqrt();
        (end - start <= band_c + noise).then_some(Flat {
            start_c: start,
            now_c: end,
            full_s: time as f64 / 1e9,
        })
    }
}

/// What `sensor_jump` found: the reading moved by `change_c` within `within_s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Jump {
    /// The change, °C (signed).
    pub change_c: f64,
    /// Over this time, s.
    pub within_s: f64,
}

/// `sensor_jump`: a reading that moved by more than `max_rate × max(Δt, 1 s)` against the one
/// before it, or against the one that began the running second. A heater's block cannot cool or
/// heat that fast; a shorted or disconnected sensor, a wrong topic, a broken cable can.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Leap {
    prev: Option<(Nanos, f64)>,
    base: Option<(Nanos, f64)>,
}

impl Leap {
    /// Forgets the readings before: the check starts afresh at the next one.
    pub fn clear(&mut self) {
        *self = Leap::default();
    }

    /// A fresh finite reading `celsius` at `now`; `max_rate` °C/s (0 = off). Returns what it
    /// found when the check trips.
    pub fn reading(&mut self, now: Nanos, celsius: f64, max_rate: f64) -> Option<Jump> {
        const SECOND: Nanos = 1_000_000_000;
        let check = |(t, c): (Nanos, f64)| {
            let dt = now.saturating_sub(t);
            let allowed = max_rate * dt.max(SECOND) as f64 / 1e9;
            ((celsius - c).abs() > allowed).then_some(Jump {
                change_c: celsius - c,
                within_s: dt as f64 / 1e9,
            })
        };
        let found = if max_rate > 0.0 {
            self.prev
                .and_then(check)
                .or_else(|| self.base.and_then(check))
        } else {
            None
        };
        if self
            .base
            .is_none_or(|(t, _)| now.saturating_sub(t) >= SECOND)
        {
            self.base = Some((now, celsius));
        }
        self.prev = Some((now, celsius));
        found
    }
}

/// Klipper's `verify_heater` state, ticked once a second (see
/// [`NotHeating::tick`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotHeating {
    approaching: bool,
    starting: bool,
    last_target: f64,
    goal_temp: f64,
    goal_time: Nanos,
    error: f64,
}

impl Default for NotHeating {
    fn default() -> Self {
        NotHeating {
            approaching: false,
            starting: false,
            last_target: 0.0,
            goal_temp: 0.0,
            goal_time: Nanos::MAX,
            error: 0.0,
        }
    }
}

impl NotHeating {
    /// The error summed so far, °C·s.
    pub fn error(&self) -> f64 {
        self.error
    }

    /// Whether an approach to a new target is being watched.
    pub fn approaching(&self) -> bool {
        self.approaching
    }

    /// One tick at `now` with reading `temp` and `target` (°C; 0 or below: no target, as a
    /// heater switched off in Klipper). Returns true when the heater is not heating at the
    /// expected rate. Follows `klippy/extras/verify_heater.py` `check_event` step for step.
    pub fn tick(&mut self, now: Nanos, temp: f64, target: f64, p: &Runaway) -> bool {
        self.tick_ramped(now, temp, target, target, p)
    }

    /// [`NotHeating::tick`] with a target on its way to the setpoint `goal` (a setpoint ramp):
    /// the error is summed against `target`, and a new approach starts only when `goal`
    /// changes, so a ramp's every step is not a new target that would re-arm the approach for
    /// ever.
    pub fn tick_ramped(
        &mut self,
        now: Nanos,
        temp: f64,
        target: f64,
        goal: f64,
        p: &Runaway,
    ) -> bool {
        if temp >= target - p.hysteresis_c || target <= 0.0 {
            // Near the target (or none): the approach ends. Above the band the error is held,
            // not reset: a heater that overshot and then falls keeps what it had.
            self.approaching = false;
            self.starting = false;
            if temp <= target + p.hysteresis_c {
                self.error = 0.0;
            }
            self.last_target = goal;
            return false;
        }
        self.error += (target - p.hysteresis_c) - temp;
        let mut fault = false;
        if !self.approaching {
            if goal != self.last_target {
                // A new target: watch the approach; it must gain heating_gain within
                // check_gain_time, again and again.
                self.approaching = true;
                self.starting = true;
                self.goal_temp = temp + p.heating_gain_c;
                self.goal_time = now.saturating_add(p.gain_time);
            } else if self.error >= p.max_error {
                fault = true;
            }
        } else if temp >= self.goal_temp {
            // Gained: the error starts again and the goal is re-armed.
            self.starting = false;
            self.error = 0.0;
            self.goal_temp = temp + p.heating_gain_c;
            self.goal_time = now.saturating_add(p.gain_time);
        } else if now >= self.goal_time {
            // No longer approaching: the summed error decides from now on.
            self.approaching = false;
        } else if self.starting {
            // Right after a new target the temperature may still fall: the goal follows it.
            self.goal_temp = self.goal_temp.min(temp + p.heating_gain_c);
        }
        self.last_target = goal;
        fault
    }
}

/// Readings kept for `stuck_on`'s window (decimated to about 1/16 of the window).
const STUCK_SLOTS: usize = 32;

/// The readings taken while the line was off, for `stuck_on`: a rise of more than
/// `stuck_on_rise_c` within `stuck_on_time_s` while the line has been held off the whole time.
/// A fixed ring: no allocation after construction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StuckOn {
    ring: [(Nanos, f64); STUCK_SLOTS],
    head: usize,
    len: usize,
}

impl Default for StuckOn {
    fn default() -> Self {
        StuckOn {
            ring: [(0, 0.0); STUCK_SLOTS],
            head: 0,
            len: 0,
        }
    }
}

/// What `stuck_on` found at a reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rise {
    /// The rise within the window, °C (the reading less the lowest one kept in the window).
    pub rise_c: f64,
    /// Whether the line has been off for the whole window.
    pub off_whole_window: bool,
}

impl StuckOn {
    /// Forgets every reading (the line went high, or the check was reconfigured).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    fn get(&self, k: usize) -> (Nanos, f64) {
        self.ring[(self.head + k) % STUCK_SLOTS]
    }

    /// Takes a finite reading `temp` at `now`, with the line off since `off_since` (`None`:
    /// the line is high), over a window of `window` ns. Returns the rise within the window.
    pub fn reading(
        &mut self,
        now: Nanos,
        temp: f64,
        off_since: Option<Nanos>,
        window: Nanos,
    ) -> Rise {
        let Some(off_since) = off_since else {
            self.clear();
            return Rise {
                rise_c: 0.0,
                off_whole_window: false,
            };
        };
        let start = now.saturating_sub(window).max(off_since);
        // Drop what lies before the window or before the line went off.
        while self.len > 0 && self.get(0).0 < start {
            self.head = (self.head + 1) % STUCK_SLOTS;
            self.len -= 1;
        }
        let lowest = (0..self.len).map(|k| self.get(k).1).fold(temp, f64::min);
        let spacing = (window / (STUCK_SLOTS as Nanos / 2)).max(1);
        let newest = (self.len > 0).then(|| self.get(self.len - 1).0);
        if newest.is_none_or(|t| now >= t.saturating_add(spacing)) {
            if self.len == STUCK_SLOTS {
                self.head = (self.head + 1) % STUCK_SLOTS;
                self.len -= 1;
            }
            self.ring[(self.head + self.len) % STUCK_SLOTS] = (now, temp);
            self.len += 1;
        }
        Rise {
            rise_c: temp - lowest,
            off_whole_window: now.saturating_sub(off_since) >= window,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    /// `Delivered::at` finds the snapshots around an instant by bisection: the same answer as a
    /// scan from the oldest snapshot, at each snapshot's instant, next to it, between two,
    /// before the oldest and after `now`, with the ring filled and wrapped several times and
    /// some records too close to the last to be kept.
    #[test]
    fn the_delivered_history_at_an_instant_is_what_a_scan_finds() {
        fn scan(d: &Delivered, t: Nanos, now: Nanos, on_now: Nanos) -> Option<Nanos> {
            let mut prev: Option<(Nanos, Nanos)> = None;
            for k in 0..d.len {
                let (tk, ek) = d.ring[(d.head + k) % ENERGY_SLOTS];
                if tk >= t {
                    return match prev {
                        Some((tp, ep)) if tk > tp => Some(
                            ep + ((ek - ep) as u128 * (t - tp) as u128 / (tk - tp) as u128)
                                as Nanos,
                        ),
                        Some(_) => Some(ek),
                        None => (tk == t).then_some(ek),
                    };
                }
                prev = Some((tk, ek));
            }
            match prev {
                Some((tp, ep)) if now > tp && t <= now => Some(
                    ep + ((on_now.saturating_sub(ep)) as u128 * (t - tp) as u128
                        / (now - tp) as u128) as Nanos,
                ),
                _ => None,
            }
        }
        let mut d = Delivered::new(60 * S);
        let mut rng = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = move |below: u64| {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            rng % below.max(1)
        };
        let (mut now, mut on) = (5 * S, 0);
        let mut checked = 0;
        for _ in 0..4 * ENERGY_SLOTS {
            let step = next(2 * d.spacing);
            now += step;
            on += next(step + 1);
            d.record(now, on);
            let on_now = on + next(S);
            let mut probes = vec![0, 1, now, now + 1, now.saturating_sub(1)];
            for k in 0..d.len {
                let (tk, _) = d.ring[(d.head + k) % ENERGY_SLOTS];
                probes.extend([tk.saturating_sub(1), tk, tk + 1, tk + next(d.spacing)]);
            }
            for t in probes {
                assert_eq!(
                    d.at(t, now, on_now),
                    scan(&d, t, now, on_now),
                    "at {t}, now {now}"
                );
                checked += 1;
            }
        }
        assert!(
            d.len == ENERGY_SLOTS && checked > 100_000,
            "{} slots, {checked} probes",
            d.len
        );
    }

    fn klipper() -> Runaway {
        Runaway {
            hysteresis_c: 5.0,
            max_error: 120.0,
            gain_time: 20 * S,
            heating_gain_c: 2.0,
        }
    }

    #[test]
    fn a_new_target_starts_an_approach_that_must_gain() {
        let p = klipper();
        let mut v = NotHeating::default();
        // Heater at 20 °C, target 200: an approach starts, goal 22 within 20 s.
        assert!(!v.tick(0, 20.0, 200.0, &p));
        assert!(v.approaching());
        // Gains 2 °C every 10 s: never a fault, the error restarts at each gain.
        let mut temp = 20.0;
        for s in 1..=300 {
            temp += 0.2;
            assert!(!v.tick(s * S, temp, 200.0, &p), "tick {s}");
        }
        assert!(v.approaching());
    }

    #[test]
    fn a_cold_heater_trips_after_the_approach_and_max_error() {
        let p = klipper();
        let mut v = NotHeating::default();
        let mut tripped = None;
        for s in 0..100 {
            if v.tick(s * S, 20.0, 200.0, &p) {
                tripped = Some(s);
                break;
            }
        }
        // The approach runs out at 20 s; the error (175 °C per tick) then exceeds 120 at the
        // next tick.
        assert_eq!(tripped, Some(21));
    }

    /// A ramped target changes every tick; only a new setpoint starts an approach, so a dead
    /// heater under a ramp trips as it would on a step (a target taken as new every tick would
    /// re-arm the approach for ever).
    #[test]
    fn a_ramp_is_one_approach_not_one_per_tick() {
        let p = klipper();
        let (mut ramped, mut naive) = (NotHeating::default(), NotHeating::default());
        let (mut tripped, mut naive_tripped) = (None, None);
        for s in 0..200 {
            // From 30 °C at 1 °C/s toward 200 °C; the heater stays at 20 °C.
            let target = (30.0 + s as f64).min(200.0);
            if tripped.is_none() && ramped.tick_ramped(s * S, 20.0, target, 200.0, &p) {
                tripped = Some(s);
            }
            if naive_tripped.is_none() && naive.tick(s * S, 20.0, target, &p) {
                naive_tripped = Some(s);
            }
        }
        // The approach runs out at 20 s; the error reaches 120 °C·s soon after.
        assert!(tripped.is_some_and(|s| s <= 22), "{tripped:?}");
        // Taken tick by tick, each new target restarts the approach: only once the ramp has
        // reached its setpoint (170 s) does the error decide.
        assert!(naive_tripped.is_some_and(|s| s > 170), "{naive_tripped:?}");
    }

    #[test]
    fn the_error_is_held_above_the_band_and_reset_within_it() {
        let p = klipper();
        let mut v = NotHeating::default();
        v.tick(0, 100.0, 100.0, &p); // in the band: error 0, last target 100
        v.tick(S, 90.0, 100.0, &p); // below the band, same target: error 5
        assert_eq!(v.error(), 5.0);
        v.tick(2 * S, 110.0, 100.0, &p); // above the band: held
        assert_eq!(v.error(), 5.0);
        v.tick(3 * S, 100.0, 100.0, &p); // within: reset
        assert_eq!(v.error(), 0.0);
    }

    #[test]
    fn stuck_on_sees_a_rise_only_over_a_whole_window_off() {
        let mut s = StuckOn::default();
        let w = 10 * S;
        // The line went off at 0; the temperature rises 1 °C/s.
        for k in 0..=20u64 {
            let r = s.reading(k * S, 20.0 + k as f64, Some(0), w);
            assert_eq!(r.off_whole_window, k >= 10, "{k}");
            if k >= 10 {
                assert!((r.rise_c - 10.0).abs() < 1.0, "{k}: {r:?}");
            }
        }
        // The line goes high: everything is forgotten.
        let r = s.reading(21 * S, 41.0, None, w);
        assert_eq!(r.rise_c, 0.0);
        let r = s.reading(22 * S, 42.0, Some(21 * S + S / 2), w);
        assert_eq!((r.rise_c, r.off_whole_window), (0.0, false));
    }
}
