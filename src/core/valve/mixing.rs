//! A mixing plant behind a three-point valve, for the loop's tests in virtual time and for
//! `sim-valve --mix`: the valve's true position sets the share of hot supply water, the rest
//! is cold; the mixed water reaches the sensor after a dead time (the pipe) and the sensor sees
//! it through a first-order lag (the pipe's and the sensor well's heat capacity):
//!
//! `T_in(t) = cold + (hot − cold) · x(t − L) / 100`, `dT/dt = (T_in − T) / tau`.
//!
//! Pure: the caller passes the instants and the valve's position; the noise comes from a
//! seeded generator, so a run is repeated exactly.

use crate::core::Nanos;
use std::collections::VecDeque;

/// The plant's constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MixingParams {
    /// Hot supply, °C.
    pub hot_c: f64,
    /// Cold supply (or return), °C.
    pub cold_c: f64,
    /// Time constant of the mixed water at the sensor, s.
    pub tau_s: f64,
    /// Dead time from the valve to the sensor, s.
    pub dead_time_s: f64,
    /// Peak sensor noise, °C (uniform in ±noise).
    pub noise_c: f64,
}

impl Default for MixingParams {
    fn default() -> Self {
        MixingParams {
            hot_c: 70.0,
            cold_c: 15.0,
            tau_s: 120.0,
            dead_time_s: 20.0,
            noise_c: 0.5,
        }
    }
}

/// The plant (see the module documentation).
#[derive(Debug, Clone)]
pub struct Mixing {
    p: MixingParams,
    /// The mixed water at the sensor, °C, at `at`.
    temp: f64,
    at: Nanos,
    /// The valve's positions told, oldest first: (instant, percent); kept for the dead time.
    history: VecDeque<(Nanos, f64)>,
    rng: u64,
}

impl Mixing {
    /// A plant settled at valve position `pct` at `now`; `seed` drives the noise.
    pub fn new(p: MixingParams, pct: f64, now: Nanos, seed: u64) -> Mixing {
        let mut m = Mixing {
            p,
            temp: 0.0,
            at: now,
            history: VecDeque::new(),
            rng: seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1,
        };
        m.temp = m.inlet(pct);
        m.history.push_back((now, pct));
        m
    }

    /// The constants in force.
    pub fn params(&self) -> &MixingParams {
        &self.p
    }

    /// A new hot supply temperature from now on, °C.
    pub fn set_hot(&mut self, c: f64) {
        self.p.hot_c = c;
    }

    /// A new cold supply temperature from now on, °C.
    pub fn set_cold(&mut self, c: f64) {
        self.p.cold_c = c;
    }

    fn inlet(&self, pct: f64) -> f64 {
        let x = pct.clamp(0.0, 100.0) / 100.0;
        self.p.cold_c + (self.p.hot_c - self.p.cold_c) * x
    }

    /// The valve's position that reaches the sensor at `t` (told at `t − L`).
    fn delayed(&self, t: Nanos) -> f64 {
        let l = (self.p.dead_time_s * 1e9) as Nanos;
        let when = t.saturating_sub(l);
        self.history
            .iter()
            .rev()
            .find(|(at, _)| *at <= when)
            .or_else(|| self.history.front())
            .map_or(0.0, |&(_, x)| x)
    }

    /// Advances the plant to `now` with the valve at `pct` from now on (call it at least every
    /// 100 ms while the valve moves: the position between calls is taken as constant).
    pub fn advance(&mut self, now: Nanos, pct: f64) {
        if now > self.at {
            // The delayed position changes only at the instants told: integrate exactly
            // between them.
            let l = (self.p.dead_time_s * 1e9) as Nanos;
            let mut t = self.at;
            while t < now {
                let x = self.delayed(t);
                // The next change of the delayed input, or `now`.
                let next = self
                    .history
                    .iter()
                    .map(|(at, _)| at.saturating_add(l))
                    .find(|&arrives| arrives > t)
                    .unwrap_or(now)
                    .min(now);
                let h = (next - t) as f64 / 1e9;
                let target = self.inlet(x);
                self.temp = target + (self.temp - target) * (-h / self.p.tau_s).exp();
                t = next;
            }
            self.at = now;
        }
        self.history.push_back((now, pct));
        // Keep what the dead time still needs: everything after `now − L`, and the one before.
        let l = (self.p.dead_time_s * 1e9) as Nanos;
        let keep_from = now.saturating_sub(l);
        while self.history.len() > 2 && self.history[1].0 <= keep_from {
            self.history.pop_front();
        }
    }

    /// The mixed water's true temperature at the last instant advanced to, °C.
    pub fn temperature(&self) -> f64 {
        self.temp
    }

    /// What the sensor reads now: the true temperature with its noise, °C.
    pub fn reading(&mut self) -> f64 {
        // xorshift64*: uniform in [0, 1).
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        let u = (self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64;
        self.temp + self.p.noise_c * (2.0 * u - 1.0)
    }

    /// The valve position that holds `celsius` at the present supplies, percent (clamped).
    pub fn position_for(&self, celsius: f64) -> f64 {
        let span = self.p.hot_c - self.p.cold_c;
        if span.abs() < 1e-9 {
            return 0.0;
        }
        ((celsius - self.p.cold_c) / span * 100.0).clamp(0.0, 100.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    #[test]
    fn a_step_of_the_valve_arrives_after_the_dead_time_then_follows_the_lag() {
        let p = MixingParams {
            noise_c: 0.0,
            ..MixingParams::default()
        };
        // Settled at 50 %: 42.5 °C.
        let mut m = Mixing::new(p, 50.0, 0, 1);
        assert!((m.temperature() - 42.5).abs() < 1e-9);
        m.advance(10 * S, 50.0);
        // The valve opens fully at 10 s.
        m.advance(10 * S, 100.0);
        m.advance(29 * S, 100.0);
        assert!(
            (m.temperature() - 42.5).abs() < 1e-9,
            "within the dead time"
        );
        m.advance(30 * S + 120 * S, 100.0);
        // One time constant after the dead time: 63 % of the way to 70 °C.
        let expected = 70.0 + (42.5 - 70.0) * (-1.0f64).exp();
        assert!(
            (m.temperature() - expected).abs() < 1e-6,
            "{}",
            m.temperature()
        );
        assert!((m.position_for(42.5) - 50.0).abs() < 1e-9);
    }

    #[test]
    fn the_noise_is_bounded_and_centred() {
        let mut m = Mixing::new(MixingParams::default(), 50.0, 0, 7);
        let n = 10_000;
        let mut sum = 0.0;
        for _ in 0..n {
            let r = m.reading() - m.temperature();
            assert!(r.abs() <= 0.5);
            sum += r;
        }
        assert!((sum / n as f64).abs() < 0.02);
    }

    #[test]
    fn the_history_holds_no_more_than_the_dead_time_needs() {
        // Advanced every 100 ms for an hour with a 20 s dead time: at most 20 s / 100 ms
        // positions, plus the one before the window and the newest.
        let mut m = Mixing::new(MixingParams::default(), 0.0, 0, 1);
        let mut most = 0;
        for k in 1..=36_000u64 {
            m.advance(k * S / 10, (k % 100) as f64);
            most = most.max(m.history.len());
        }
        assert!(most <= 200 + 2, "{most}");
    }

    #[test]
    fn a_supply_step_moves_the_mixed_water() {
        let p = MixingParams {
            noise_c: 0.0,
            dead_time_s: 0.0,
            ..MixingParams::default()
        };
        let mut m = Mixing::new(p, 50.0, 0, 1);
        m.set_hot(60.0);
        m.advance(1200 * S, 50.0);
        assert!((m.temperature() - 37.5).abs() < 1e-3);
    }
}
