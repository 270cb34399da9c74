//! The heater's thermal model, run forward on the line's real on time: the prediction behind
//! `model_deviation`, the check that sees faults inside the band where the reading looks
//! plausible (a sensor stuck near the setpoint or fallen off its block, a heater that lost
//! power or heats too much, an SSR stuck on while the loop keeps switching). Prusa's firmware
//! runs such a model on the PWM it commands; this one runs on the on time the line really had,
//! which only the channel knows.
//!
//! The model is first order plus dead time: with the line on a share `u` (%) of the time,
//! `dX/dt = (ambient + gain·u − X) / tau`, and the sensor follows `X` one dead time later
//! through its own lag, `dS/dt = (X(t − L) − S) / sensor_tau` (0: it reads `X(t − L)`). Between
//! two updates `u` is the line's mean on share over the interval (exact for the energy, and the
//! interval — a reading's — is short against `tau`), and the step is the exact solution of
//! the linear equation; the sensor's, for its input moving linearly between two readings.
//!
//! The residual is the reading less the prediction. What a model cannot know shifts it slowly
//! (an ambient a few degrees off, a gain a few percent off, a draught): a slow offset, tracked
//! over [`OFFSET_TAUS`] time constants, is taken out, and the check looks at what is left. A
//! fault moves the residual within seconds; an offset takes minutes.
//!
//! Pure: the caller passes the instants and the cumulative on time. No allocation.

pub use super::super::config::heater::ModelParams;
use super::super::Nanos;

/// Snapshots of the undelayed state kept for the dead time.
const SLOTS: usize = 128;

/// The slow offset of the residual is tracked over this many model time constants.
pub const OFFSET_TAUS: f64 = 1.0;

/// The model's state (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Model {
    p: ModelParams,
    /// The undelayed temperature, °C, at `at`; the line's cumulative on time then, ns.
    x: f64,
    at: Nanos,
    on_at: Nanos,
    /// Snapshots of `(instant, x)`, oldest first from `head`, spaced by at least `spacing`.
    ring: [(Nanos, f64); SLOTS],
    head: usize,
    len: usize,
    spacing: Nanos,
    /// The residual's slow offset, °C.
    offset: f64,
    /// The sensor's temperature and its input (the delayed state) at the last reading, °C.
    sensor: f64,
    sensor_in: f64,
    sensor_at: Nanos,
    /// The ambient (°C) and the announced disturbance (feed-forward, %) in force.
    ambient: f64,
    ff: f64,
    started: bool,
}

/// What the model says at a reading.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Prediction {
    /// The model's temperature for the sensor now, °C (the slow offset included).
    pub predicted_c: f64,
    /// The reading less the prediction, °C.
    pub residual_c: f64,
}

impl Model {
    /// A model of `p` that starts at the first reading it is given.
    pub fn new(p: ModelParams) -> Model {
        let dead = (p.dead_time_s * 1e9) as Nanos;
        Model {
            p,
            x: p.ambient_c,
            at: 0,
            on_at: 0,
            ring: [(0, p.ambient_c); SLOTS],
            head: 0,
            len: 0,
            spacing: (dead / (SLOTS as Nanos / 2)).max(1_000_000),
            offset: 0.0,
            sensor: p.ambient_c,
            sensor_in: p.ambient_c,
            sensor_at: 0,
            ambient: p.ambient_c,
            ff: 0.0,
            started: false,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &ModelParams {
        &self.p
    }

    /// Whether the model has started (it has seen a reading).
    pub fn started(&self) -> bool {
        self.started
    }

    /// Starts (or restarts) the model at `now` from the reading `celsius`, as if the heater had
    /// stood at it for the dead time; `on_total` is the line's cumulative on time, ns.
    pub fn restart(&mut self, now: Nanos, on_total: Nanos, celsius: f64) {
        let (ambient, ff) = (self.ambient, self.ff);
        *self = Model::new(self.p);
        self.ambient = ambient;
        self.ff = ff;
        self.x = celsius;
        self.sensor = celsius;
        self.sensor_in = celsius;
        self.sensor_at = now;
        self.at = now;
        self.on_at = on_total;
        self.started = true;
        self.push(now);
    }

    fn push(&mut self, now: Nanos) {
        let newest = (self.len > 0).then(|| self.ring[(self.head + self.len - 1) % SLOTS].0);
        if newest.is_some_and(|t| now < t.saturating_add(self.spacing)) {
            return;
        }
        if self.len == SLOTS {
            self.head = (self.head + 1) % SLOTS;
            self.len -= 1;
        }
        self.ring[(self.head + self.len) % SLOTS] = (now, self.x);
        self.len += 1;
    }

    /// The ambient in force, °C.
    pub fn ambient(&self) -> f64 {
        self.ambient
    }

    /// The announced disturbance in force, %.
    pub fn feedforward(&self) -> f64 {
        self.ff
    }

    /// Sets the ambient (°C, a measured one) and the disturbance announced by the
    /// feed-forward (% of full power) in force from `now` on, the model advanced to `now`
    /// first: what the model is told of does not move its residual.
    pub fn set_inputs(&mut self, now: Nanos, on_total: Nanos, ambient_c: f64, ff_pct: f64) {
        self.advance(now, on_total);
        self.ambient = ambient_c;
        self.ff = ff_pct;
    }

    /// Advances the undelayed state to `now`, with the line's cumulative on time `on_total`
    /// (ns) then.
    pub fn advance(&mut self, now: Nanos, on_total: Nanos) {
        if !self.started || now <= self.at {
            return;
        }
        let h = (now - self.at) as f64;
        let u_pct = (on_total.saturating_sub(self.on_at) as f64 / h * 100.0).clamp(0.0, 100.0);
        let target = self.ambient + self.p.gain_c_per_pct * (u_pct - self.ff);
        let tau_ns = self.p.tau_s * 1e9;
        self.x = target + (self.x - target) * (-h / tau_ns).exp();
        self.at = now;
        self.on_at = on_total;
        self.push(now);
    }

    /// The undelayed state at `t` (at most the last instant advanced to), by interpolation
    /// between the snapshots; before the oldest one, the oldest.
    fn x_at(&self, t: Nanos) -> f64 {
        if t >= self.at {
            return self.x;
        }
        let slot = |k: usize| self.ring[(self.head + k) % SLOTS];
        // The first snapshot at or after `t`: `push` keeps their times rising.
        let lo = super::first_at_or_after(self.len, |k| slot(k).0, t);
        let prev = lo.checked_sub(1).map(slot);
        if lo < self.len {
            let (tk, xk) = slot(lo);
            return match prev {
                Some((tp, xp)) if tk > tp => xp + (xk - xp) * (t - tp) as f64 / (tk - tp) as f64,
                _ => xk,
            };
        }
        // Between the newest snapshot and `at`.
        match prev {
            Some((tp, xp)) if self.at > tp => {
                xp + (self.x - xp) * (t - tp) as f64 / (self.at - tp) as f64
            }
            _ => self.x,
        }
    }

    /// A reading `celsius` at `now` (the model advanced to `now` first): the prediction and the
    /// residual with the slow offset taken out, and the offset moved toward the raw residual.
    pub fn reading(&mut self, now: Nanos, on_total: Nanos, celsius: f64) -> Prediction {
        if !self.started {
            self.restart(now, on_total, celsius);
        }
        let dt = now.saturating_sub(self.at) as f64 / 1e9;
        self.advance(now, on_total);
        let dead = (self.p.dead_time_s * 1e9) as Nanos;
        let input = self.x_at(now.saturating_sub(dead));
        let h = now.saturating_sub(self.sensor_at) as f64 / 1e9;
        self.sensor = lag(self.sensor, self.sensor_in, input, h, self.p.sensor_tau_s);
        self.sensor_in = input;
        self.sensor_at = now;
        let raw = celsius - self.sensor;
        let residual = raw - self.offset;
        let k = (dt / (OFFSET_TAUS * self.p.tau_s)).min(1.0);
        self.offset += k * residual;
        Prediction {
            predicted_c: celsius - residual,
            residual_c: residual,
        }
    }
}

/// A first-order lag `tau` (s) from `s` after `h` s, its input moving linearly from `from` to
/// `to`: `S(t) = X(t) − tau·k + (S − X₀ + tau·k)·e^(−t/tau)`, `k` the input's slope. A lag of 0
/// follows its input.
pub(crate) fn lag(s: f64, from: f64, to: f64, h: f64, tau: f64) -> f64 {
    if tau <= 0.0 || h <= 0.0 {
        return if tau <= 0.0 { to } else { s };
    }
    let k = (to - from) / h;
    to - tau * k + (s - from + tau * k) * (-h / tau).exp()
}

#[cfg(test)]
mod tests {
    use super::super::plant::{Plant, PlantParams};
    use super::*;

    const S: Nanos = 1_000_000_000;
    const MS: Nanos = 1_000_000;

    /// `x_at` finds the snapshots around an instant by bisection: the same state as a scan from
    /// the oldest snapshot, at each snapshot's instant, next to it, between two, before the
    /// oldest and after the last instant advanced to, with the ring filled and wrapped.
    #[test]
    fn the_state_at_an_instant_is_what_a_scan_finds() {
        fn scan(m: &Model, t: Nanos) -> f64 {
            if t >= m.at {
                return m.x;
            }
            let mut prev: Option<(Nanos, f64)> = None;
            for k in 0..m.len {
                let (tk, xk) = m.ring[(m.head + k) % SLOTS];
                if tk >= t {
                    return match prev {
                        Some((tp, xp)) if tk > tp => {
                            xp + (xk - xp) * (t - tp) as f64 / (tk - tp) as f64
                        }
                        _ => xk,
                    };
                }
                prev = Some((tk, xk));
            }
            match prev {
                Some((tp, xp)) if m.at > tp => {
                    xp + (m.x - xp) * (t - tp) as f64 / (m.at - tp) as f64
                }
                _ => m.x,
            }
        }
        let p = ModelParams {
            gain_c_per_pct: 1.0,
            tau_s: 60.0,
            dead_time_s: 4.0,
            ambient_c: 20.0,
            sensor_tau_s: 2.0,
        };
        let mut m = Model::new(p);
        m.restart(S, 0, 20.0);
        let (mut now, mut on) = (S, 0);
        let mut checked = 0;
        for i in 0..4 * SLOTS as u64 {
            let step = (i * 7_919 % 97) * MS;
            now += step;
            on += step * (i % 3) / 2;
            m.advance(now, on);
            let mut probes = vec![0, 1, now, now + 1, now - 1];
            for k in 0..m.len {
                let (tk, _) = m.ring[(m.head + k) % SLOTS];
                probes.extend([tk.saturating_sub(1), tk, tk + 1, tk + m.spacing / 3]);
            }
            for t in probes {
                assert_eq!(
                    m.x_at(t).to_bits(),
                    scan(&m, t).to_bits(),
                    "at {t}, now {now}"
                );
                checked += 1;
            }
        }
        assert!(
            m.len == SLOTS && checked > 50_000,
            "{} slots, {checked} probes",
            m.len
        );
    }

    fn model_of(p: &PlantParams) -> ModelParams {
        ModelParams {
            gain_c_per_pct: p.rate_c_per_s * p.tau_s / 100.0,
            tau_s: p.tau_s,
            dead_time_s: p.dead_time_s,
            ambient_c: p.ambient_c,
            sensor_tau_s: p.sensor_tau_s,
        }
    }

    /// Drives a plant and the model with a 1 s PWM at `duty` for `secs`, readings at 10 Hz;
    /// returns the largest |residual|.
    fn run(
        plant: &mut Plant,
        m: &mut Model,
        on_total: &mut Nanos,
        t: &mut Nanos,
        duty: f64,
        secs: u64,
    ) -> f64 {
        let mut worst: f64 = 0.0;
        for _ in 0..secs {
            let on = (duty * 1e9) as Nanos;
            for k in 0..10u64 {
                let at = *t + k * 100 * MS;
                let high = k * 100 * MS < on;
                plant.line(at, high);
                let c = plant.reading(at).unwrap();
                let r = m.reading(at, *on_total, c);
                worst = worst.max(r.residual_c.abs());
                if high {
                    *on_total += (100 * MS).min(on - k * 100 * MS);
                }
            }
            *t += S;
        }
        worst
    }

    #[test]
    fn an_exact_model_follows_the_plant_through_a_heat_up() {
        let p = PlantParams::default();
        let mut plant = Plant::new(p, 0, 1);
        let mut m = Model::new(model_of(&p));
        let (mut on, mut t) = (0, 0);
        let worst = run(&mut plant, &mut m, &mut on, &mut t, 1.0, 30);
        let worst2 = run(&mut plant, &mut m, &mut on, &mut t, 0.4, 200);
        // The mean of each interval stands for a PWM inside it: the ripple is the only error.
        assert!(worst.max(worst2) < 1.5, "{worst} {worst2}");
    }

    #[test]
    fn a_lagging_sensor_is_followed_through_its_own_lag() {
        let p = PlantParams {
            sensor_tau_s: 3.0,
            ..PlantParams::default()
        };
        let mut plant = Plant::new(p, 0, 1);
        let mut m = Model::new(model_of(&p));
        let (mut on, mut t) = (0, 0);
        let worst = run(&mut plant, &mut m, &mut on, &mut t, 1.0, 30);
        let worst2 = run(&mut plant, &mut m, &mut on, &mut t, 0.4, 200);
        assert!(worst.max(worst2) < 1.5, "{worst} {worst2}");
        // Without the sensor's lag the model is ahead of the reading by about rate × lag.
        let mut plant = Plant::new(p, 0, 1);
        let mut blind = Model::new(ModelParams {
            sensor_tau_s: 0.0,
            ..model_of(&p)
        });
        let (mut on, mut t) = (0, 0);
        let off = run(&mut plant, &mut blind, &mut on, &mut t, 1.0, 30);
        assert!(off > 4.0, "{off}");
    }

    #[test]
    fn a_stuck_on_heater_moves_the_residual_within_seconds() {
        let p = PlantParams::default();
        let mut plant = Plant::new(p, 0, 1);
        let mut m = Model::new(model_of(&p));
        let (mut on, mut t) = (0, 0);
        run(&mut plant, &mut m, &mut on, &mut t, 0.5, 300);
        plant.set_fault(super::super::plant::PlantFault::HeaterStuckOn);
        // The line keeps switching at 20 %, the heater is on all the time.
        let worst = run(&mut plant, &mut m, &mut on, &mut t, 0.2, 20);
        assert!(worst > 10.0, "{worst}");
    }

    #[test]
    fn a_slow_offset_is_taken_out() {
        let p = PlantParams::default();
        let mut plant = Plant::new(p, 0, 1);
        // The model's ambient is 4 °C off.
        let mut mp = model_of(&p);
        mp.ambient_c += 4.0;
        let mut m = Model::new(mp);
        let (mut on, mut t) = (0, 0);
        run(&mut plant, &mut m, &mut on, &mut t, 0.5, 600);
        let last = run(&mut plant, &mut m, &mut on, &mut t, 0.5, 10);
        assert!(last < 0.5, "{last}");
    }
}
