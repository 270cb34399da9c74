//! A heater as a first-order-plus-dead-time plant with a lagging sensor, driven by the real
//! line's edges: for the core's tests in virtual time and for the simulated heater
//! (`sim-heater`). Pure: the caller passes the instants.
//!
//! With the heater at power `u` (0 or 1: the line), after the dead time `L`:
//! `dT/dt = (ambient + rate·tau·u − T) / tau`, so at full power the block's temperature rises
//! at `rate` °C/s from ambient and settles `rate·tau` above it. The sensor lags its block with
//! its own time constant `tau_s` (a probe in a bore, a thermistor glued to a bed):
//! `dS/dt = (T − S) / tau_s`, and reads `S` with its noise (`tau_s` 0: it reads `T`). Between
//! changes of the delayed input the solution is exact: `T(t+h) = T∞ + (T − T∞)·a` and
//! `S(t+h) = T∞ + (T − T∞)·tau/(tau − tau_s)·(a − b) + (S − T∞)·b`, with `a = e^(−h/tau)`,
//! `b = e^(−h/tau_s)`.

use super::super::Nanos;
use std::collections::VecDeque;

/// A plant's constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantParams {
    /// Rise at 100 % from ambient, °C/s.
    pub rate_c_per_s: f64,
    /// Time constant, s.
    pub tau_s: f64,
    /// Dead time between the line and the sensor, s.
    pub dead_time_s: f64,
    /// Ambient, °C (and the start temperature).
    pub ambient_c: f64,
    /// Peak sensor noise, °C (uniform in ±noise).
    pub noise_c: f64,
    /// The sensor's own time constant behind its block, s; 0 = it reads the block.
    pub sensor_tau_s: f64,
}

impl Default for PlantParams {
    fn default() -> Self {
        PlantParams {
            rate_c_per_s: 2.0,
            tau_s: 60.0,
            dead_time_s: 2.0,
            ambient_c: 20.0,
            noise_c: 0.0,
            sensor_tau_s: 0.0,
        }
    }
}

/// A fault injected into the plant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PlantFault {
    /// None.
    #[default]
    None,
    /// The heater is disconnected: no power whatever the line.
    HeaterDisconnected,
    /// The heater is stuck on (a welded SSR): full power whatever the line.
    HeaterStuckOn,
    /// The heater delivers half its power (a burnt element of two, a supply at 71 % of its
    /// voltage).
    HeaterHalfPower,
    /// The sensor reports its last value for ever.
    SensorStuck,
    /// The sensor sends nothing.
    SensorSilent,
    /// The sensor is shorted to ambient (a thermocouple shorted at its connector reads the
    /// temperature there): it reads ambient, with its noise.
    SensorShorted,
    /// The sensor fell off the heater: it cools toward ambient with its own time constant,
    /// [`FALLEN_SENSOR_TAU_S`], and sees nothing of the heater any more.
    SensorFallenOff,
}

/// The time constant of a sensor that fell off its heater, s: a small probe in still air.
pub const FALLEN_SENSOR_TAU_S: f64 = 20.0;

/// Every fault's spelling, as `sim-heater` takes it.
pub const FAULT_NAMES: [&str; 8] = [
    "none",
    "heater_disconnected",
    "heater_stuck_on",
    "heater_half_power",
    "sensor_stuck",
    "sensor_silent",
    "sensor_shorted",
    "sensor_fallen_off",
];

impl PlantFault {
    /// The spelling used by `sim-heater`: one of [`FAULT_NAMES`].
    pub fn parse(s: &str) -> Option<PlantFault> {
        Some(match s {
            "none" => PlantFault::None,
            "heater_disconnected" => PlantFault::HeaterDisconnected,
            "heater_stuck_on" => PlantFault::HeaterStuckOn,
            "heater_half_power" => PlantFault::HeaterHalfPower,
            "sensor_stuck" => PlantFault::SensorStuck,
            "sensor_silent" => PlantFault::SensorSilent,
            "sensor_shorted" => PlantFault::SensorShorted,
            "sensor_fallen_off" => PlantFault::SensorFallenOff,
            _ => return None,
        })
    }

    /// The spelling of the fault (see [`FAULT_NAMES`]).
    pub fn name(self) -> &'static str {
        match self {
            PlantFault::None => "none",
            PlantFault::HeaterDisconnected => "heater_disconnected",
            PlantFault::HeaterStuckOn => "heater_stuck_on",
            PlantFault::HeaterHalfPower => "heater_half_power",
            PlantFault::SensorStuck => "sensor_stuck",
            PlantFault::SensorSilent => "sensor_silent",
            PlantFault::SensorShorted => "sensor_shorted",
            PlantFault::SensorFallenOff => "sensor_fallen_off",
        }
    }
}

/// The plant (see the module documentation).
#[derive(Debug, Clone)]
pub struct Plant {
    p: PlantParams,
    temp: f64,
    /// The sensor's temperature (behind the block by its time constant), °C.
    sensor: f64,
    at: Nanos,
    /// The power in effect at the heater now (after the dead time), 0 or 1.
    power: f64,
    /// Changes of the line that have not reached the heater yet: (when they do, level).
    pending: VecDeque<(Nanos, bool)>,
    /// The line as last told, and since when.
    line: bool,
    line_since: Nanos,
    fault: PlantFault,
    stuck_reading: Option<f64>,
    /// A fallen-off sensor's own temperature, °C, and the instant it was advanced to.
    fallen: Option<(f64, Nanos)>,
    /// The share of full power a disturbance takes away (a fan, an open door), 0..=1.
    disturbance: f64,
    /// The sensor's resolution, °C; 0 = none.
    quantum_c: f64,
    rng: u64,
}

impl Plant {
    /// A plant at ambient at instant `now`, its line off; `seed` drives the noise.
    pub fn new(p: PlantParams, now: Nanos, seed: u64) -> Plant {
        Plant {
            p,
            temp: p.ambient_c,
            sensor: p.ambient_c,
            at: now,
            power: 0.0,
            pending: VecDeque::new(),
            line: false,
            line_since: now,
            fault: PlantFault::None,
            stuck_reading: None,
            fallen: None,
            disturbance: 0.0,
            quantum_c: 0.0,
            rng: seed | 1,
        }
    }

    /// The constants.
    pub fn params(&self) -> &PlantParams {
        &self.p
    }

    /// Injects `fault` from now on.
    pub fn set_fault(&mut self, fault: PlantFault) {
        self.fault = fault;
        self.stuck_reading = None;
        self.fallen = None;
    }

    /// A disturbance that takes `share` (0..=1) of the heater's full power away from now on
    /// (a fan blowing on it, a door opened), down to the ambient and no further; 0 removes it.
    /// The caller advances the plant to the instant first.
    pub fn set_disturbance(&mut self, share: f64) {
        self.disturbance = share.clamp(0.0, 1.0);
    }

    /// The disturbance in force, share of full power.
    pub fn disturbance(&self) -> f64 {
        self.disturbance
    }

    /// Moves the ambient temperature to `celsius` from now on (the room warms or cools).
    pub fn set_ambient(&mut self, celsius: f64) {
        self.p.ambient_c = celsius;
    }

    /// Rounds every reading to a multiple of `quantum_c` °C (a MAX6675 board reads in 0.25 °C
    /// steps, a DS18B20 in 0.0625 °C); 0 = none.
    pub fn set_quantum(&mut self, quantum_c: f64) {
        self.quantum_c = quantum_c.max(0.0);
    }

    /// The fault injected.
    pub fn fault(&self) -> PlantFault {
        self.fault
    }

    /// The block's true temperature at the last instant advanced to, °C.
    pub fn temperature(&self) -> f64 {
        self.temp
    }

    /// The sensor's own temperature at the last instant advanced to (what a healthy sensor
    /// reads before its noise), °C.
    pub fn sensor_temperature(&self) -> f64 {
        self.sensor
    }

    /// The line as last told, and since when (ns).
    pub fn line_state(&self) -> (bool, Nanos) {
        (self.line, self.line_since)
    }

    /// The line changed to `on` at `at` (not before the last instant advanced to).
    pub fn line(&mut self, at: Nanos, on: bool) {
        self.advance(at);
        if on != self.line {
            self.line = on;
            self.line_since = at;
            let dead = (self.p.dead_time_s * 1e9) as Nanos;
            self.pending.push_back((at.saturating_add(dead), on));
        }
    }

    fn dt_to(&mut self, t: Nanos) {
        if t <= self.at {
            return;
        }
        let h = (t - self.at) as f64 / 1e9;
        let power = match self.fault {
            PlantFault::HeaterDisconnected => 0.0,
            PlantFault::HeaterStuckOn => 1.0,
            PlantFault::HeaterHalfPower => self.power / 2.0,
            _ => self.power,
        } - self.disturbance;
        let target = self.p.ambient_c + self.p.rate_c_per_s * self.p.tau_s * power;
        let (tau, tau_s) = (self.p.tau_s, self.p.sensor_tau_s);
        let a = (-h / tau).exp();
        let from = self.temp - target;
        self.temp = target + from * a;
        self.sensor = if tau_s <= 0.0 {
            self.temp
        } else {
            let b = (-h / tau_s).exp();
            // The block's part of the sensor's response: tau/(tau − tau_s)·(a − b), and its
            // limit (h/tau)·a when the two time constants meet.
            let block = if (tau - tau_s).abs() > 1e-9 * tau {
                tau / (tau - tau_s) * (a - b)
            } else {
                h / tau * a
            };
            target + from * block + (self.sensor - target) * b
        };
        if target < self.p.ambient_c {
            // A disturbance takes heat away, down to the ambient, never below it.
            self.temp = self.temp.max(self.p.ambient_c);
            self.sensor = self.sensor.max(self.p.ambient_c);
        }
        self.at = t;
    }

    /// Advances the plant to `t`.
    pub fn advance(&mut self, t: Nanos) {
        while let Some(&(when, on)) = self.pending.front() {
            if when > t {
                break;
            }
            self.dt_to(when);
            self.power = if on { 1.0 } else { 0.0 };
            self.pending.pop_front();
        }
        self.dt_to(t);
    }

    fn noise(&mut self) -> f64 {
        // xorshift64*: deterministic per seed.
        self.rng ^= self.rng >> 12;
        self.rng ^= self.rng << 25;
        self.rng ^= self.rng >> 27;
        let x = self.rng.wrapping_mul(0x2545_F491_4F6C_DD1D);
        let unit = (x >> 11) as f64 / (1u64 << 53) as f64;
        (2.0 * unit - 1.0) * self.p.noise_c
    }

    /// The sensor's reading at `t`, °C, or `None` when it is silent.
    pub fn reading(&mut self, t: Nanos) -> Option<f64> {
        self.advance(t);
        let sensed = match self.fault {
            PlantFault::SensorShorted => self.p.ambient_c,
            PlantFault::SensorFallenOff => {
                // The probe cools toward ambient from where it fell off.
                let (c, at) = *self.fallen.get_or_insert((self.sensor, t));
                let h = t.saturating_sub(at) as f64 / 1e9;
                let amb = self.p.ambient_c;
                let c = amb + (c - amb) * (-h / FALLEN_SENSOR_TAU_S).exp();
                self.fallen = Some((c, t));
                c
            }
            _ => self.sensor,
        };
        let mut noisy = sensed + self.noise();
        if self.quantum_c > 0.0 {
            noisy = (noisy / self.quantum_c).round() * self.quantum_c;
        }
        match self.fault {
            PlantFault::SensorSilent => None,
            PlantFault::SensorStuck => Some(*self.stuck_reading.get_or_insert(noisy)),
            _ => Some(noisy),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    #[test]
    fn full_power_after_the_dead_time_then_first_order() {
        let p = PlantParams {
            rate_c_per_s: 1.0,
            tau_s: 100.0,
            dead_time_s: 5.0,
            ambient_c: 20.0,
            noise_c: 0.0,
            sensor_tau_s: 0.0,
        };
        let mut plant = Plant::new(p, 0, 1);
        plant.line(0, true);
        assert_eq!(plant.reading(5 * S), Some(20.0));
        // 100 s after the dead time: 20 + 100·(1 − e^−1).
        let t = plant.reading(105 * S).unwrap();
        assert!(
            (t - (20.0 + 100.0 * (1.0 - (-1.0f64).exp()))).abs() < 1e-9,
            "{t}"
        );
        plant.line(105 * S, false);
        // Still heating for the dead time.
        assert!(plant.reading(110 * S).unwrap() > t);
        assert!(plant.reading(200 * S).unwrap() < t);
    }

    #[test]
    fn the_sensor_lags_its_block_by_its_own_time_constant() {
        let p = PlantParams {
            rate_c_per_s: 1.0,
            tau_s: 100.0,
            dead_time_s: 0.0,
            ambient_c: 20.0,
            noise_c: 0.0,
            sensor_tau_s: 5.0,
        };
        let mut plant = Plant::new(p, 0, 1);
        plant.line(0, true);
        // The two-pole step response: 100·(1 − (τ·e^(−t/τ) − τs·e^(−t/τs))/(τ − τs)).
        let step = |t: f64| {
            20.0 + 100.0 * (1.0 - (100.0 * (-t / 100.0).exp() - 5.0 * (-t / 5.0).exp()) / 95.0)
        };
        for t in [1u64, 3, 10, 50, 200] {
            let c = plant.reading(t * S).unwrap();
            assert!(
                (c - step(t as f64)).abs() < 1e-9,
                "{t}: {c} vs {}",
                step(t as f64)
            );
            assert!(c < plant.temperature());
        }
        // Small steps agree with one large one (the solution is exact between edges).
        let mut fine = Plant::new(p, 0, 1);
        fine.line(0, true);
        for k in 1..=2000u64 {
            fine.advance(k * S / 10);
        }
        assert!((fine.reading(200 * S).unwrap() - step(200.0)).abs() < 1e-9);
        // Equal time constants: the limit.
        let q = PlantParams {
            sensor_tau_s: 100.0,
            ..p
        };
        let mut eq = Plant::new(q, 0, 1);
        eq.line(0, true);
        let t = 100.0;
        let want = 20.0 + 100.0 * (1.0 - (1.0 + t / 100.0) * (-t / 100.0f64).exp());
        assert!((eq.reading(100 * S).unwrap() - want).abs() < 1e-9);
    }

    #[test]
    fn faults() {
        let mut plant = Plant::new(PlantParams::default(), 0, 1);
        plant.set_fault(PlantFault::HeaterStuckOn);
        let a = plant.reading(10 * S).unwrap();
        assert!(a > 30.0, "{a}");
        plant.set_fault(PlantFault::SensorStuck);
        let b = plant.reading(20 * S).unwrap();
        assert_eq!(plant.reading(30 * S), Some(b));
        plant.set_fault(PlantFault::SensorShorted);
        assert_eq!(plant.reading(40 * S), Some(20.0));
        plant.set_fault(PlantFault::SensorFallenOff);
        let c = plant.reading(40 * S).unwrap();
        let later = plant.reading(40 * S + 20 * S).unwrap();
        // One time constant toward ambient.
        assert!((later - (20.0 + (c - 20.0) / std::f64::consts::E)).abs() < 1e-9);
        plant.set_fault(PlantFault::SensorSilent);
        assert_eq!(plant.reading(50 * S), None);
    }
}
