//! Model-predictive control of the heater (`control` `mpc`), the way Kalico's `control: mpc`
//! and Marlin's MPC run it: the thermal model (gain, time constant, dead time, ambient, the
//! sensor's lag) predicts the heater over its dead time from the power the line really
//! delivered, and the duty is the one that brings the prediction to the target, with a
//! steady-state term for the loss to the ambient and for the disturbances it is told of.
//!
//! **The estimate.** The model's states are the block's temperature `T`, the sensor's `S` and
//! a disturbance `d` (% of full power taken away: a fan, an open door, a draught the model was
//! not told of). Between readings they run on the line's real on time, delayed by the dead
//! time, the ambient in force and the feed-forward in force (exact solutions, input piece by
//! input piece). At each fresh reading an observer corrects all three by the reading less the
//! model's sensor, with the gains that put the error's three poles at `e^(−h/T_o)` for the
//! time `h` since the last correction (Ackermann's formula for the current estimator), `T_o`
//! the model's total lag `L + τ_s` (at least [`MIN_PACE_S`]), or a hundredth of the time
//! constant `τ` where that is longer ([`OBSERVER_MIN_TAU_SHARE`]: a slow block behind a short
//! lag, whose readings' noise a faster observer would hand to the duty): the estimate of an
//! unannounced disturbance settles within a few of those.
//!
//! **The law.** At each sample the estimate runs forward over the dead time on the power
//! already sent (the ring of the line's on time), which gives the block's temperature `T_L`
//! when what is decided now starts to act. One constant duty over a horizon `H` then brings
//! the block from `T_L` onto a first-order path to the target with the time constant `T_r`
//! (predictive functional control, one coincidence point at `H = T_r`):
//!
//! ```text
//! T∞ = (target·(1 − λ) + T_L·(λ − a)) / (1 − a),  a = e^(−H/τ), λ = e^(−H/T_r)
//! duty = (T∞ − ambient)/gain + d + feed-forward
//! ```
//!
//! At the target `T∞` is the target and the duty is the steady-state term alone: what holds
//! the block against its loss to the ambient and the disturbances. `T_r` is the model's total
//! lag (at least [`MIN_PACE_S`]); the block never overshoots the path on its model.
//!
//! **Bumpless.** A start from a duty in force (a switch from `pid` or `open`, a new model) sets
//! the disturbance estimate so that the first duty is that duty; the observer then moves it to
//! what the readings say.
//!
//! Pure and bounded: the caller passes the instants and the line's cumulative on time; no
//! allocation; a reading's correction is one step per input piece since the last update plus
//! a fixed 3×3 computation; a sample is one pass over the ring's pieces within the dead time
//! ([`SLOTS`] at most) plus a few exponentials.

pub use super::super::config::heater::ModelParams;
use super::super::Nanos;

/// Snapshots of the line's cumulative on time kept for the dead time.
pub const SLOTS: usize = 128;
/// The shortest observer time constant and reference time constant, s.
pub const MIN_PACE_S: f64 = 1.0;

/// The observer's time constant in the model's total lags.
pub const OBSERVER_PACES: f64 = 1.0;
/// The observer's time constant is at least this share of the model's time constant: in that
/// time an unannounced disturbance moves the block by about this share of what it will, and an
/// observer much faster than that only hands the sensor's noise to the duty (on a block of
/// 600 s behind a 1.5 s total lag and ±0.2 °C of noise, the noise it passed at 1.5 s was most
/// of the loop's error).
pub const OBSERVER_MIN_TAU_SHARE: f64 = 0.01;

/// What the loop's last sample decided, for the status.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct MpcTerms {
    /// The block's temperature the model predicts one dead time ahead, °C.
    pub predicted_c: f64,
    /// The steady-state term: the duty that holds the target against the loss to the ambient,
    /// the estimated disturbance and the feed-forward, %.
    pub steady_pct: f64,
    /// The disturbance the observer estimates (not announced by the feed-forward), % of full
    /// power.
    pub disturbance_pct: f64,
    /// The output, limited, %.
    pub output: f64,
}

/// The loop's state (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mpc {
    p: ModelParams,
    /// `(instant, line's cumulative on time)`, oldest first from `head`, at least `spacing`
    /// apart.
    ring: [(Nanos, Nanos); SLOTS],
    head: usize,
    len: usize,
    spacing: Nanos,
    /// The estimate `[T, S, d]` at `at`, and when it was last corrected.
    x: [f64; 3],
    at: Nanos,
    corrected_at: Nanos,
    started: bool,
    /// The ambient (°C) and feed-forward (%) in force.
    ambient: f64,
    ff: f64,
    /// The observer's gains for the last interval, and that interval, ns.
    gains: [f64; 3],
    gains_for: Nanos,
    /// The duty commanded for the period that began at the newest snapshot, %, when the loop
    /// samples: the model then runs on each period's mean power, not on the pulses inside it.
    period_duty: Option<f64>,
    terms: MpcTerms,
}

type M3 = [[f64; 3]; 3];

fn mul(a: &M3, b: &M3) -> M3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

impl Mpc {
    /// A loop on the model `p`, started at the first reading it is given.
    pub fn new(p: ModelParams) -> Mpc {
        let dead = (p.dead_time_s.max(0.0) * 1e9) as Nanos;
        Mpc {
            p,
            ring: [(0, 0); SLOTS],
            head: 0,
            len: 0,
            spacing: (dead / (SLOTS as Nanos / 2)).max(1_000_000),
            x: [p.ambient_c, p.ambient_c, 0.0],
            at: 0,
            corrected_at: 0,
            started: false,
            ambient: p.ambient_c,
            ff: 0.0,
            gains: [0.0; 3],
            gains_for: 0,
            period_duty: None,
            terms: MpcTerms::default(),
        }
    }

    /// The model.
    pub fn params(&self) -> &ModelParams {
        &self.p
    }

    /// Whether the estimate has started (it has seen a reading).
    pub fn started(&self) -> bool {
        self.started
    }

    /// The last sample's terms.
    pub fn terms(&self) -> MpcTerms {
        self.terms
    }

    /// The estimate `[block °C, sensor °C, disturbance %]` at its last update.
    pub fn estimate(&self) -> [f64; 3] {
        self.x
    }

    /// The time constant of the observer and of the reference path, s: the model's total
    /// lag, at least [`MIN_PACE_S`].
    pub fn pace_s(&self) -> f64 {
        (self.p.dead_time_s + self.p.sensor_tau_s).max(MIN_PACE_S)
    }

    /// The observer's time constant, s: [`OBSERVER_PACES`] times [`Mpc::pace_s`], at least
    /// [`OBSERVER_MIN_TAU_SHARE`] of the model's time constant.
    pub fn observer_s(&self) -> f64 {
        (OBSERVER_PACES * self.pace_s()).max(OBSERVER_MIN_TAU_SHARE * self.p.tau_s)
    }

    /// Restarts the estimate at `now` from the reading `celsius`, the heater taken at rest
    /// there, with no disturbance; `on_total` is the line's cumulative on time, ns.
    pub fn restart(&mut self, now: Nanos, on_total: Nanos, celsius: f64) {
        let (ambient, ff) = (self.ambient, self.ff);
        *self = Mpc::new(self.p);
        self.ambient = ambient;
        self.ff = ff;
        self.x = [celsius, celsius, 0.0];
        self.at = now;
        self.corrected_at = now;
        self.started = true;
        self.push(now, on_total);
    }

    /// Sets the ambient (°C) and the feed-forward (% of full power) in force from `now` on
    /// (the estimate advanced to `now` first, with the line's on time `on_total`).
    pub fn set_inputs(&mut self, now: Nanos, on_total: Nanos, ambient_c: f64, ff_pct: f64) {
        if self.started {
            self.advance(now, on_total);
        }
        self.ambient = ambient_c;
        self.ff = ff_pct;
    }

    /// The feed-forward in force, %.
    pub fn feedforward(&self) -> f64 {
        self.ff
    }

    /// The ambient in force, °C.
    pub fn ambient(&self) -> f64 {
        self.ambient
    }

    /// A period starts at `now` with the line's cumulative on time `on_total` (ns) and the
    /// duty `duty_pct` commanded for it: from here on the model runs on each period's mean
    /// power (the on time the line really delivered over the periods past, the commanded duty
    /// over the running one). The law then sees the period's mean temperature, not the
    /// PWM's ripple at the instant it samples (always the same point of the ripple).
    pub fn period(&mut self, now: Nanos, on_total: Nanos, duty_pct: f64) {
        if !self.started {
            return;
        }
        self.advance(now, on_total);
        self.push(now, on_total);
        self.period_duty = duty_pct.is_finite().then_some(duty_pct.clamp(0.0, 100.0));
    }

    /// Moves the disturbance estimate by `pct` (% of full power): a feed-forward handing its
    /// value to the estimate when it goes stale, or taking it back when it returns.
    pub fn shift_disturbance(&mut self, pct: f64) {
        self.x[2] += pct;
    }

    fn push(&mut self, now: Nanos, on_total: Nanos) {
        let newest = (self.len > 0).then(|| self.ring[(self.head + self.len - 1) % SLOTS].0);
        if newest.is_some_and(|t| now < t.saturating_add(self.spacing)) {
            return;
        }
        if self.len == SLOTS {
            self.head = (self.head + 1) % SLOTS;
            self.len -= 1;
        }
        self.ring[(self.head + self.len) % SLOTS] = (now, on_total);
        self.len += 1;
    }

    /// The ring's `k`-th snapshot, oldest first.
    fn snap(&self, k: usize) -> (Nanos, Nanos) {
        self.ring[(self.head + k) % SLOTS]
    }

    /// The first snapshot at or after `t` (the ring's length when none is).
    fn first_from(&self, t: Nanos) -> usize {
        let (mut lo, mut hi) = (0, self.len);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if self.snap(mid).0 < t {
                lo = mid + 1;
            } else {
                hi = mid;
            }
        }
        lo
    }

    /// The line's cumulative on time at `t`, ns, by interpolation between the snapshots;
    /// after the newest, at the running period's commanded duty or toward `(now, now_on)`;
    /// before the oldest snapshot the line was off.
    fn on_at(&self, t: Nanos, now: Nanos, now_on: Nanos) -> f64 {
        let k = self.first_from(t);
        if let (true, Some(u), Some(j)) = (k == self.len, self.period_duty, k.checked_sub(1)) {
            let (tp, ep) = self.snap(j);
            return ep as f64 + u / 100.0 * t.saturating_sub(tp) as f64;
        }
        let next = if k < self.len {
            self.snap(k)
        } else {
            (now.max(t), now_on)
        };
        match k.checked_sub(1).map(|j| self.snap(j)) {
            Some((tp, ep)) if next.0 > tp => {
                ep as f64
                    + next.1.saturating_sub(ep) as f64 * (t.min(next.0) - tp) as f64
                        / (next.0 - tp) as f64
            }
            Some((_, ep)) => ep as f64,
            None => next.1 as f64,
        }
    }

    /// The exact step of the block and the sensor over `h` s at the duty `u` % with the
    /// disturbance `d` %.
    fn step(&self, tb: f64, ts: f64, u: f64, d: f64, h: f64) -> (f64, f64) {
        let p = &self.p;
        let target = self.ambient + p.gain_c_per_pct * (u - d - self.ff);
        let a = (-h / p.tau_s).exp();
        let tb1 = target + (tb - target) * a;
        let tau_s = p.sensor_tau_s;
        let ts1 = if tau_s <= 1e-9 {
            tb1
        } else {
            let b = (-h / tau_s).exp();
            let beta = if (p.tau_s - tau_s).abs() > 1e-9 * p.tau_s {
                p.tau_s / (p.tau_s - tau_s) * (a - b)
            } else {
                h / p.tau_s * a
            };
            target + (tb - target) * beta + (ts - target) * b
        };
        (tb1, ts1)
    }

    /// Runs `[T, S]` from `from` to `to` (ns) on the line's on time a dead time earlier, piece
    /// by piece between the ring's snapshots; `now`/`now_on` is the newest on time known.
    fn run(
        &self,
        mut s: (f64, f64),
        from: Nanos,
        to: Nanos,
        now: Nanos,
        now_on: Nanos,
    ) -> (f64, f64) {
        if to <= from {
            return s;
        }
        let dead = (self.p.dead_time_s * 1e9) as Nanos;
        let d = self.x[2];
        let (mut t, mut e_t) = (from, self.on_at(from.saturating_sub(dead), now, now_on));
        let mut k = self.first_from(from.saturating_sub(dead).saturating_add(1));
        while t < to {
            let (end, e_end) = match (k < self.len).then(|| self.snap(k)) {
                Some((tk, ek)) if tk.saturating_add(dead) < to => {
                    (tk.saturating_add(dead), ek as f64)
                }
                _ => (to, self.on_at(to.saturating_sub(dead), now, now_on)),
            };
            if end > t {
                let h = (end - t) as f64;
                let u = ((e_end - e_t) / h * 100.0).clamp(0.0, 100.0);
                s = self.step(s.0, s.1, u, d, h / 1e9);
                t = end;
                e_t = e_end;
            }
            k += 1;
        }
        s
    }

    /// Advances the estimate to `now` with the line's cumulative on time `on_total`, ns.
    pub fn advance(&mut self, now: Nanos, on_total: Nanos) {
        if !self.started || now <= self.at {
            return;
        }
        let s = self.run((self.x[0], self.x[1]), self.at, now, now, on_total);
        self.x[0] = s.0;
        self.x[1] = s.1;
        self.at = now;
        if self.period_duty.is_none() {
            self.push(now, on_total);
        }
    }

    /// The observer's gains for a correction `h` s after the last one (see the module
    /// documentation); zeros where the model gives none.
    fn observer_gains(&self, h: f64) -> [f64; 3] {
        let p = &self.p;
        let k = p.gain_c_per_pct;
        let a = (-h / p.tau_s).exp();
        let (b, beta) = if p.sensor_tau_s <= 1e-9 {
            (0.0, a)
        } else {
            let b = (-h / p.sensor_tau_s).exp();
            let beta = if (p.tau_s - p.sensor_tau_s).abs() > 1e-9 * p.tau_s {
                p.tau_s / (p.tau_s - p.sensor_tau_s) * (a - b)
            } else {
                h / p.tau_s * a
            };
            (b, beta)
        };
        let lambda = (-h / self.observer_s()).exp();
        if p.sensor_tau_s <= 1e-9 {
            // The sensor reads the block: two states, `[T, d]`, the reading `T`; the gains
            // of `(p(Φ)·[CΦ; CΦ²]⁻¹·e₂)` with `p(z) = (z − λ)²`, the sensor's row following
            // the block's.
            let c = -k * (1.0 - a);
            // CΦ = [a, c], CΦ² = [a², a·c + c].
            let (m00, m01, m10, m11) = (a, c, a * a, a * c + c);
            let det = m00 * m11 - m01 * m10;
            if det.abs() < 1e-300 {
                return [0.0; 3];
            }
            let z = [-m01 / det, m00 / det];
            // (Φ − λI)² with Φ = [[a, c], [0, 1]].
            let (p00, p01, p11) = (a - lambda, c, 1.0 - lambda);
            let q = [[p00 * p00, p00 * p01 + p01 * p11], [0.0, p11 * p11]];
            let g0 = q[0][0] * z[0] + q[0][1] * z[1];
            let g1 = q[1][0] * z[0] + q[1][1] * z[1];
            return if g0.is_finite() && g1.is_finite() {
                [g0, g0, g1]
            } else {
                [0.0; 3]
            };
        }
        let phi: M3 = [
            [a, 0.0, -k * (1.0 - a)],
            [beta, b, -k * (1.0 - beta - b)],
            [0.0, 0.0, 1.0],
        ];
        // The rows CΦ, CΦ², CΦ³ (C picks the sensor).
        let r1 = phi[1];
        let row = |r: [f64; 3]| -> [f64; 3] {
            [
                r[0] * phi[0][0] + r[1] * phi[1][0] + r[2] * phi[2][0],
                r[0] * phi[0][1] + r[1] * phi[1][1] + r[2] * phi[2][1],
                r[0] * phi[0][2] + r[1] * phi[1][2] + r[2] * phi[2][2],
            ]
        };
        let r2 = row(r1);
        let r3 = row(r2);
        let Some(z) = super::fit::solve3([r1, r2, r3], [0.0, 0.0, 1.0]) else {
            return [0.0; 3];
        };
        // (Φ − λI)³ z.
        let mut m = phi;
        for (i, r) in m.iter_mut().enumerate() {
            r[i] -= lambda;
        }
        let m3 = mul(&mul(&m, &m), &m);
        let g = [0, 1, 2].map(|i| m3[i][0] * z[0] + m3[i][1] * z[1] + m3[i][2] * z[2]);
        if g.iter().all(|v| v.is_finite()) {
            g
        } else {
            [0.0; 3]
        }
    }

    /// A fresh reading `celsius` at `now` (the line's cumulative on time `on_total`): the
    /// estimate runs to `now` and is corrected by the reading less its sensor.
    pub fn reading(&mut self, now: Nanos, on_total: Nanos, celsius: f64) {
        if !self.started {
            self.restart(now, on_total, celsius);
            return;
        }
        if !celsius.is_finite() {
            return;
        }
        self.advance(now, on_total);
        let h = now.saturating_sub(self.corrected_at);
        if h == 0 {
            return;
        }
        if h != self.gains_for {
            self.gains = self.observer_gains(h as f64 / 1e9);
            self.gains_for = h;
        }
        let r = celsius - self.x[1];
        for (x, g) in self.x.iter_mut().zip(self.gains) {
            *x += g * r;
        }
        self.corrected_at = now;
    }

    /// The block's temperature one dead time after `now`, on the power already sent, and the
    /// estimate at `now` (not stored).
    fn predict(&self, now: Nanos, on_total: Nanos) -> (f64, f64) {
        let at = (self.x[0], self.x[1]);
        let present = self.run(at, self.at, now.max(self.at), now, on_total);
        let dead = (self.p.dead_time_s * 1e9) as Nanos;
        self.run(present, now, now.saturating_add(dead), now, on_total)
    }

    /// The duty the law gives at `now` for `target` (°C) before the limits, with the
    /// disturbance estimate `d` (%), and the block's temperature one dead time ahead.
    fn law(&self, now: Nanos, on_total: Nanos, target: f64) -> (f64, f64, f64) {
        let p = &self.p;
        let (t_l, _) = self.predict(now, on_total);
        let h = self.pace_s();
        let a = (-h / p.tau_s).exp();
        let lambda = (-1.0f64).exp();
        let t_inf = (target * (1.0 - lambda) + t_l * (lambda - a)) / (1.0 - a).max(1e-12);
        let steady = (target - self.ambient) / p.gain_c_per_pct + self.x[2] + self.ff;
        let duty = (t_inf - self.ambient) / p.gain_c_per_pct + self.x[2] + self.ff;
        (duty, steady, t_l)
    }

    /// One sample at `now` for `target` (°C): the duty within `lo..=hi` %.
    pub fn sample(
        &mut self,
        now: Nanos,
        on_total: Nanos,
        target: f64,
        lo: f64,
        hi: f64,
    ) -> MpcTerms {
        if !self.started {
            return self.terms;
        }
        let (duty, steady, t_l) = self.law(now, on_total, target);
        let output = if duty.is_finite() {
            duty.clamp(lo, hi)
        } else {
            lo
        };
        self.terms = MpcTerms {
            predicted_c: t_l,
            steady_pct: steady,
            disturbance_pct: self.x[2],
            output,
        };
        self.terms
    }

    /// Makes the next sample at `now` for `target` give `output` % (a bumpless start): the
    /// disturbance estimate takes up the difference.
    pub fn start_from(&mut self, now: Nanos, on_total: Nanos, target: f64, output: f64) {
        if !self.started {
            return;
        }
        let (duty, _, _) = self.law(now, on_total, target);
        if duty.is_finite() && output.is_finite() {
            self.x[2] += output - duty;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::plant::{Plant, PlantParams};
    use super::*;

    const MS: Nanos = 1_000_000;

    fn model(p: &PlantParams) -> ModelParams {
        ModelParams {
            gain_c_per_pct: p.rate_c_per_s * p.tau_s / 100.0,
            tau_s: p.tau_s,
            dead_time_s: p.dead_time_s,
            ambient_c: p.ambient_c,
            sensor_tau_s: p.sensor_tau_s,
        }
    }

    #[test]
    fn the_observers_error_has_its_three_poles_where_they_were_put() {
        for lag in [0.0, 2.0] {
            let p = PlantParams {
                sensor_tau_s: lag,
                ..PlantParams::default()
            };
            let m = Mpc::new(model(&p));
            for h in [0.05, 0.25, 1.0, 5.0] {
                let g = m.observer_gains(h);
                let k = m.p.gain_c_per_pct;
                let a = (-h / p.tau_s).exp();
                let (b, beta) = if lag == 0.0 {
                    (0.0, a)
                } else {
                    let b = (-h / lag).exp();
                    (b, p.tau_s / (p.tau_s - lag) * (a - b))
                };
                let phi: M3 = [
                    [a, 0.0, -k * (1.0 - a)],
                    [beta, b, -k * (1.0 - beta - b)],
                    [0.0, 0.0, 1.0],
                ];
                // (I − g·C)·Φ
                let mut ic: M3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
                for i in 0..3 {
                    ic[i][1] -= g[i];
                }
                let e = mul(&ic, &phi);
                let lambda = (-h / m.observer_s()).exp();
                if lag == 0.0 {
                    // Two states, [T, d]: the block's and the disturbance's rows and columns.
                    let e2 = [[e[0][0], e[0][2]], [e[2][0], e[2][2]]];
                    let trace = e2[0][0] + e2[1][1];
                    let det = e2[0][0] * e2[1][1] - e2[0][1] * e2[1][0];
                    assert!((trace - 2.0 * lambda).abs() < 1e-6, "{h}: {trace}");
                    assert!((det - lambda * lambda).abs() < 1e-6, "{h}: {det}");
                    continue;
                }
                let trace = e[0][0] + e[1][1] + e[2][2];
                let minors = e[0][0] * e[1][1] - e[0][1] * e[1][0] + e[0][0] * e[2][2]
                    - e[0][2] * e[2][0]
                    + e[1][1] * e[2][2]
                    - e[1][2] * e[2][1];
                let det = e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
                    - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
                    + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0]);
                assert!((trace - 3.0 * lambda).abs() < 1e-6, "{lag} {h}: {trace}");
                assert!((minors - 3.0 * lambda * lambda).abs() < 1e-6, "{minors}");
                assert!((det - lambda.powi(3)).abs() < 1e-6, "{det}");
            }
        }
    }

    /// The plant under the loop in virtual time: 1 s PWM, readings at 4 Hz, a sample per
    /// period; returns the true block temperatures each second.
    fn closed(p: PlantParams, target: f64, secs: u64, fan: Option<(u64, f64)>) -> Vec<f64> {
        closed_with(p, model(&p), target, secs, fan).0
    }

    fn closed_with(
        p: PlantParams,
        m: ModelParams,
        target: f64,
        secs: u64,
        fan: Option<(u64, f64)>,
    ) -> (Vec<f64>, Mpc) {
        let mut plant = Plant::new(p, 0, 1);
        let mut mpc = Mpc::new(m);
        let (mut on_total, mut duty, mut out) = (0u64, 0.0, Vec::new());
        for k in 0..secs * 4 {
            let t = k * 250 * MS;
            if let Some((at, share)) = fan {
                if k == at * 4 {
                    plant.advance(t);
                    plant.set_disturbance(share);
                }
            }
            if k % 4 == 0 {
                duty = mpc.sample(t, on_total, target, 0.0, 100.0).output;
            }
            out.push(plant.temperature());
            // The period's pulse: on for the duty's share of the second.
            let phase = (k % 4) as f64 * 0.25;
            let on = phase < duty / 100.0;
            plant.line(t, on);
            let on_end = ((duty / 100.0 - phase).clamp(0.0, 0.25) * 1e9) as u64;
            let c = plant.reading(t).unwrap();
            mpc.reading(t, on_total, c);
            if on_end > 0 && on_end < 250 * MS {
                plant.line(t + on_end, false);
            }
            on_total += on_end;
        }
        (out, mpc)
    }

    #[test]
    #[ignore]
    fn explore_bias() {
        for (lag, dead, noise) in [(0.0, 2.0, 0.0), (0.0, 0.0, 0.0), (2.0, 2.0, 0.0)] {
            let p = PlantParams {
                sensor_tau_s: lag,
                dead_time_s: dead,
                noise_c: noise,
                ..PlantParams::default()
            };
            let (temps, m) = closed_with(p, model(&p), 80.0, 400, None);
            let mean = temps[800..1600].iter().sum::<f64>() / 800.0;
            println!(
                "lag {lag} dead {dead}: mean {mean:.3}, estimate {:?}, terms {:?}",
                m.estimate(),
                m.terms()
            );
        }
    }

    #[test]
    #[ignore]
    fn explore() {
        for lag in [0.0, 2.0] {
            let p = PlantParams {
                sensor_tau_s: lag,
                noise_c: 0.05,
                ..PlantParams::default()
            };
            let temps = closed(p, 80.0, 600, Some((300, 0.3)));
            for (s, t) in temps.iter().enumerate().step_by(10) {
                print!("{s}:{t:.2} ");
            }
            println!();
            let mean = temps[800..1200].iter().sum::<f64>() / 400.0;
            println!("mean of the block 200..300 s: {mean:.3}");
        }
    }
}
