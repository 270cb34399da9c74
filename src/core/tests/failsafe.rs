//! The heater left alone: a channel under `pid` with only the parameters docs/heater.md
//! requires (`feedback_topic`, `control`, the gains, `temp_max_c`) and every other at its
//! default, driving a plant across the sizing range with noise, a drifting ambient and
//! disturbance steps, until a fault strikes at a random instant of the heat-up, of the settled
//! loop or of an autotune's relay phase. The fault must be named and the line switched off
//! within the bound its checks give, and the plant must never run more than 10 °C above
//! `max(setpoint, reading at the fault)`; healthy runs must never trip.

use super::heater::Rig;
use crate::core::heater::autotune::{Goal, Phase, Report};
use crate::core::heater::{Control, HeaterFault, HeaterParams, PlantFault, PlantParams};
use crate::core::{ChannelParams, Event, Level, Nanos};

pub(super) const S: Nanos = 1_000_000_000;

/// When the fault strikes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum When {
    /// While the loop heats toward its setpoint (the reading below setpoint − 5 °C).
    HeatUp,
    /// With the loop settled at its setpoint.
    Settled,
    /// During an autotune's relay cycles.
    Relay,
}

/// One run: the plant, its sensor, the setpoint as a share of the full-power rise, the fault
/// and when, the disturbances and the ambient drift.
#[derive(Debug, Clone, Copy)]
pub(super) struct Case {
    pub plant: PlantParams,
    pub quantum_c: f64,
    pub setpoint_share: f64,
    pub fault: PlantFault,
    pub when: When,
    /// Seconds into the phase the fault strikes.
    pub after_s: f64,
    /// A disturbance (share of full power) and when it comes and goes, s after start.
    pub disturbance: (f64, f64, f64),
    /// The ambient drift over the run, °C.
    pub drift_c: f64,
    pub seed: u64,
    /// The loop: `pid` with the SIMC gains, or `mpc` on the plant's true model.
    pub control: Control,
}

/// What a run showed.
#[derive(Debug, Clone)]
pub(super) struct Outcome {
    /// The fault named, and after how long, s.
    pub tripped: Option<(f64, HeaterFault)>,
    /// The setpoint, and the reading when the fault struck, °C.
    pub setpoint_c: f64,
    pub reading_at_fault_c: f64,
    /// The plant's highest true temperature from the fault on, °C.
    pub max_true_c: f64,
    /// The line rose after the trip.
    pub rose_after_trip: bool,
    /// A trip before the fault (a false alarm).
    pub early: Option<HeaterFault>,
    /// The duty commanded, sampled every 0.25 s from the fault on: (s after it, fraction).
    pub duty: Vec<(f64, f64)>,
    /// The duty commanded when the fault struck, fraction.
    pub duty_at_fault: f64,
    /// The PID's integral gain, % per °C·s (0 under `mpc`: no integral ramps on a frozen
    /// error there, the duty goes to full power within a few of the model's lags).
    pub ki: f64,
    /// `temp_max_c`.
    pub temp_max_c: f64,
    /// The ambient and the true temperature when the fault struck, °C.
    pub ambient_at_fault_c: f64,
    pub true_at_fault_c: f64,
    /// An autotune ran when the fault struck.
    pub relay_at_fault: bool,
}

/// The SIMC gains a user would set (docs/heater.md's tuning): kp = τ / (K·2L),
/// TI = min(τ, 8L), K = rate·τ / 100 °C per %.
pub(super) fn required(plant: &PlantParams, temp_max_c: f64) -> HeaterParams {
    let k = plant.rate_c_per_s * plant.tau_s / 100.0;
    let l = plant.dead_time_s.max(0.5);
    let kp = plant.tau_s / (k * 2.0 * l);
    let ti = plant.tau_s.min(8.0 * l);
    HeaterParams {
        feedback: true,
        control: Control::Pid,
        pid_kp: kp,
        pid_ki: kp / ti,
        temp_max_c,
        ..HeaterParams::default()
    }
}

/// `h` under `control`: under `mpc` with the plant's true model, and `model_tolerance_c`
/// above what an unannounced disturbance of `disturbance` (share of full power) moves the
/// model's residual by (docs/heater.md).
pub(super) fn for_loop(
    h: HeaterParams,
    plant: &PlantParams,
    control: Control,
    disturbance: f64,
) -> HeaterParams {
    if control != Control::Mpc {
        return h;
    }
    let gain = plant.rate_c_per_s * plant.tau_s / 100.0;
    HeaterParams {
        control,
        model: crate::core::heater::ModelParams {
            gain_c_per_pct: gain,
            tau_s: plant.tau_s,
            dead_time_s: plant.dead_time_s,
            ambient_c: plant.ambient_c,
            sensor_tau_s: plant.sensor_tau_s,
        },
        model_tolerance_c: h.model_tolerance_c + gain * disturbance * 100.0,
        ..h
    }
}

fn trips(r: &Rig) -> Option<(Nanos, HeaterFault)> {
    r.notes.iter().find_map(|(t, e)| match e {
        Event::HeaterFault(f) => Some((*t, *f)),
        _ => None,
    })
}

/// Runs `case`: heat up, settle, optionally start an autotune, strike, and watch for
/// `watch_s` after the strike (or until the trip plus the plant's dead time and 30 s).
pub(super) fn run(case: &Case, watch_s: f64) -> Outcome {
    let p = case.plant;
    let full = p.rate_c_per_s * p.tau_s;
    let setpoint = p.ambient_c + case.setpoint_share * full;
    // The user's maximum: the setpoint plus the margin the setpoint needs, and some.
    let temp_max = setpoint + 15.0 + 10.0;
    let ch = ChannelParams {
        period_ms: 1000,
        heater: for_loop(required(&p, temp_max), &p, case.control, case.disturbance.0),
        ..ChannelParams::default()
    };
    let mut r = Rig::new(ch, p, case.seed);
    r.plant.set_quantum(case.quantum_c);
    r.secs(1.0);
    r.setpoint(setpoint).enable();
    let (d_share, d_on, d_off) = case.disturbance;
    let drift_rate = case.drift_c / 3600.0;
    let ambient0 = p.ambient_c;
    // Advance in 1 s steps, applying the disturbance and the drift, until `until` holds or
    // `limit_s` passes.
    let step = |r: &mut Rig, until: &mut dyn FnMut(&Rig) -> bool, limit_s: f64| {
        let end = r.now + (limit_s * 1e9) as Nanos;
        while r.now < end && !until(r) {
            let t = r.now as f64 / 1e9;
            let d = if t >= d_on && t < d_off { d_share } else { 0.0 };
            if r.plant.disturbance() != d {
                r.plant.set_disturbance(d);
            }
            r.plant.set_ambient(ambient0 + drift_rate * t);
            r.secs(1.0);
        }
    };
    let strike_after = (case.after_s * 1e9) as Nanos;
    match case.when {
        When::HeatUp => {
            let t0 = r.now;
            step(
                &mut r,
                &mut |r| r.now >= t0 + strike_after || r.plant.temperature() >= setpoint - 5.0,
                3600.0,
            );
        }
        When::Settled => {
            // Settled: five time constants, then the offset.
            step(&mut r, &mut |_| false, 5.0 * p.tau_s + 60.0);
            step(&mut r, &mut |_| false, case.after_s);
        }
        When::Relay => {
            step(&mut r, &mut |_| false, 5.0 * p.tau_s + 60.0);
            let goal = Goal {
                target_c: setpoint,
                amplitude_pct: 100.0,
                noise_band_c: (p.noise_c * 2.0 + case.quantum_c).max(0.2),
            };
            r.act(|ch, now, emit| ch.start_autotune(now, 9, goal, emit));
            step(
                &mut r,
                &mut |r| {
                    r.notes.iter().any(|(_, e)| {
                        matches!(
                            e,
                            Event::Autotune {
                                report: Report::Progress(pr),
                                ..
                            } if pr.phase == Phase::Relay && pr.cycles >= 1
                        )
                    })
                },
                3600.0,
            );
            step(&mut r, &mut |_| false, case.after_s);
        }
    }
    let early = trips(&r).map(|(_, f)| f);
    let struck = r.now;
    let reading_at_fault =
        r.ch.status(r.now)
            .heater
            .reading
            .map_or(f64::NAN, |(c, _)| c);
    r.plant.set_fault(case.fault);
    let mut max_true = r.plant.temperature();
    let duty_at_fault = r.ch.status(r.now).duty_commanded;
    let ambient_at_fault = r.plant.params().ambient_c;
    let true_at_fault = r.plant.temperature();
    let relay_at_fault = r.ch.autotune_target().is_some();
    let mut duty = Vec::new();
    let settle = ((p.dead_time_s + 30.0) * 1e9) as Nanos;
    let end = struck + (watch_s * 1e9) as Nanos;
    let mut resumed = case.when != When::Relay;
    while r.now < end {
        if let Some((t, _)) = trips(&r) {
            if r.now >= t + settle {
                break;
            }
        }
        // An autotune that ends leaves the loop at 0 % until a new setpoint: the user sends
        // it again (docs/autotune.md).
        if !resumed && r.ch.autotune_target().is_none() && trips(&r).is_none() {
            resumed = true;
            r.setpoint(setpoint);
        }
        r.secs(0.25);
        max_true = max_true.max(r.plant.temperature());
        if trips(&r).is_none() {
            duty.push((
                (r.now - struck) as f64 / 1e9,
                r.ch.status(r.now).duty_commanded,
            ));
        }
    }
    let tripped = trips(&r)
        .filter(|(t, _)| *t >= struck)
        .map(|(t, f)| ((t - struck) as f64 / 1e9, f));
    let rose_after_trip = tripped.is_some_and(|(after, _)| {
        let t = struck + (after * 1e9) as Nanos;
        !r.no_rise_after(t) || r.ch.level() == Level::High
    });
    Outcome {
        tripped,
        setpoint_c: setpoint,
        reading_at_fault_c: reading_at_fault,
        max_true_c: max_true,
        rose_after_trip,
        early,
        duty,
        duty_at_fault,
        ki: if case.control == Control::Pid {
            r.ch.config().heater.gains.ki
        } else {
            0.0
        },
        temp_max_c: temp_max,
        ambient_at_fault_c: ambient_at_fault,
        true_at_fault_c: true_at_fault,
        relay_at_fault,
    }
}

/// Explores the checks over a grid of plants and faults, printing each outcome:
/// `cargo test --lib failsafe::explore -- --ignored --nocapture`.
#[test]
#[ignore]
fn explore() {
    let faults = [
        PlantFault::SensorStuck,
        PlantFault::SensorSilent,
        PlantFault::SensorShorted,
        PlantFault::SensorFallenOff,
        PlantFault::HeaterDisconnected,
        PlantFault::HeaterHalfPower,
        PlantFault::HeaterStuckOn,
    ];
    let plants = [
        (0.5, 30.0, 0.5),
        (0.5, 200.0, 3.0),
        (3.0, 30.0, 0.5),
        (3.0, 200.0, 3.0),
        (2.0, 60.0, 2.0),
        (1.0, 100.0, 1.0),
    ];
    for &(rate, tau, dead) in &plants {
        for share in [0.1, 0.35, 0.6] {
            for when in [When::HeatUp, When::Settled, When::Relay] {
                for fault in faults {
                    let case = Case {
                        plant: PlantParams {
                            rate_c_per_s: rate,
                            tau_s: tau,
                            dead_time_s: dead,
                            ambient_c: 20.0,
                            noise_c: 0.1,
                            sensor_tau_s: 0.0,
                        },
                        quantum_c: 0.0,
                        setpoint_share: share,
                        fault,
                        when,
                        after_s: 7.0,
                        disturbance: (0.0, 0.0, 0.0),
                        drift_c: 0.0,
                        seed: 7,
                        control: Control::Pid,
                    };
                    let o = run(&case, 600.0);
                    let bound = o.setpoint_c.max(o.reading_at_fault_c) + 10.0;
                    println!(
                        "r={rate} tau={tau} L={dead} sp={:.0} {:?} {:<20} -> {:<24} after {:>6} s, max {:.1} ({:+.1} over bound){}{}",
                        o.setpoint_c,
                        when,
                        fault.name(),
                        o.tripped.map_or("NONE".into(), |(_, f)| f.check().to_string()),
                        o.tripped.map_or("-".into(), |(t, _)| format!("{t:.1}")),
                        o.max_true_c,
                        o.max_true_c - bound,
                        if o.rose_after_trip { " ROSE" } else { "" },
                        o.early.map_or(String::new(), |f| format!(" EARLY {}", f.check())),
                    );
                }
            }
        }
    }
}

/// A small deterministic generator for the cases (xorshift64*), so a failing case is named by
/// its seed.
pub(super) struct Gen(u64);

impl Gen {
    pub(super) fn new(seed: u64) -> Gen {
        Gen(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1)
    }
    pub(super) fn unit(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
    }
    pub(super) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
    pub(super) fn pick<T: Copy>(&mut self, xs: &[T]) -> T {
        xs[((self.unit() * xs.len() as f64) as usize).min(xs.len() - 1)]
    }
}

/// The sizing range the defaults promise within (docs/heater.md, "What the defaults
/// promise").
pub(super) fn arb_plant(g: &mut Gen) -> PlantParams {
    PlantParams {
        rate_c_per_s: g.range(0.3, 0.7),
        tau_s: g.range(30.0, 600.0),
        dead_time_s: g.range(0.5, 3.0),
        ambient_c: g.range(15.0, 25.0),
        noise_c: g.range(0.0, 0.2),
        sensor_tau_s: 0.0,
    }
}

const FAULTS: [PlantFault; 7] = [
    PlantFault::SensorStuck,
    PlantFault::SensorSilent,
    PlantFault::SensorShorted,
    PlantFault::SensorFallenOff,
    PlantFault::HeaterDisconnected,
    PlantFault::HeaterHalfPower,
    PlantFault::HeaterStuckOn,
];

/// The case of `seed`: a plant of the sizing range, a sensor with or without steps, a
/// setpoint that leaves 40 % of the rise after the largest disturbance, the fault `fault`
/// at a random instant of a random phase.
fn arb_case(seed: u64, fault: PlantFault, control: Control) -> Case {
    let mut g = Gen::new(seed);
    let plant = arb_plant(&mut g);
    let quantum_c = g.pick(&[0.0, 0.0, 0.0625, 0.25]);
    let when = g.pick(&[When::HeatUp, When::Settled, When::Relay]);
    let after_s = g.range(0.0, 120.0);
    let d = g.pick(&[0.0, 0.15, 0.3]);
    let disturbance = (d, g.range(0.0, 2000.0), g.range(2000.0, 4000.0));
    let drift_c = g.range(-5.0, 5.0);
    Case {
        plant,
        quantum_c,
        setpoint_share: g.range(0.1, 0.6 - d),
        fault,
        when,
        after_s,
        disturbance,
        drift_c,
        seed,
        control,
    }
}

/// From `t` on, every sample of the duty holds `pred` (and there is one).
fn holds_from(duty: &[(f64, f64)], pred: impl Fn(f64) -> bool) -> Option<f64> {
    let last_bad = duty.iter().rposition(|(_, d)| !pred(*d));
    match last_bad {
        None => duty.first().map(|(t, _)| *t),
        Some(i) => duty.get(i + 1).map(|(t, _)| *t),
    }
}

/// The checks that may name `fault`, and the bound the defaults give on when one does (s
/// after the fault), with how it was derived; `None`: the fault cannot be seen in this run
/// (it does not change what the heater or its reading do, as a heater at half power that
/// still holds its setpoint), and only the temperature bound applies.
fn derived_bound(case: &Case, o: &Outcome) -> (&'static [&'static str], Option<(f64, String)>) {
    let d = HeaterParams::default();
    let dt_r = 0.25;
    let tick = 1.0;
    let period = 1.0;
    let p = &case.plant;
    // The loop holds full power from `t_full` on: no_rise (or the stuck check at full power)
    // trips within its time, plus a bucket and a reading.
    let t_full = holds_from(&o.duty, |u| u >= 0.995);
    let saturated = t_full.map(|t| {
        (
            t + d.no_rise_time_s + tick + dt_r,
            format!("full power from {t:.1} s + no_rise_time_s + 1 s + a reading"),
        )
    });
    match case.fault {
        PlantFault::SensorSilent => (
            &["sensor_timeout"],
            Some((
                d.feedback_timeout_ms as f64 / 1000.0 + dt_r,
                "feedback_timeout_ms + a reading".into(),
            )),
        ),
        PlantFault::SensorShorted
            if (o.reading_at_fault_c - o.ambient_at_fault_c).abs()
                > d.sensor_max_rate_c_per_s + 2.0 * p.noise_c + case.quantum_c =>
        {
            (
                &["sensor_jump"],
                Some((
                    2.0 * dt_r,
                    "a jump beyond sensor_max_rate_c_per_s × 1 s: the next reading".into(),
                )),
            )
        }
        PlantFault::SensorShorted
        | PlantFault::SensorFallenOff
        | PlantFault::HeaterDisconnected => (
            &["no_rise", "not_heating", "sensor_stuck", "sensor_jump"],
            saturated,
        ),
        // A heater at half power still rises at full power below its half-power temperature:
        // it cannot overheat, and it shows only where the loop can no longer hold the
        // setpoint (not_heating, or no_rise once it cannot rise any more). No bound on when.
        PlantFault::HeaterHalfPower => (&["no_rise", "not_heating", "sensor_stuck"], None),
        PlantFault::SensorStuck => {
            // At full power: the check's time. Else the integral ramps at ki·|e| on the
            // frozen error, and the energy's swing reaches sensor_stuck_energy_s (beyond the
            // PWM's ripple) after W = √(8·(E + P/4)/ρ), counted up to half the check's time
            // ago; a fifth more for the thinned trail. During an autotune's cycles the
            // surplus over the relay's mean (on 10..90 % of a cycle) reaches four times E
            // within 4E/0.1 s.
            let e = (o.setpoint_c - o.reading_at_fault_c).abs() - 2.0 * p.noise_c;
            let rho = o.ki * e / 100.0;
            let swing = (e > 0.0 && rho > 0.0).then(|| {
                let w = (8.0 * (d.sensor_stuck_energy_s + period / 4.0) / rho).sqrt();
                (
                    1.2 * w + d.sensor_stuck_time_s / 2.0 + d.sensor_stuck_time_s + 2.0 * tick,
                    format!("swing of a ramp at ki·|e| = {:.4} %/s", rho * 100.0),
                )
            });
            let full = t_full.map(|t| {
                (
                    t + d.sensor_stuck_time_s.max(d.no_rise_time_s) + tick + dt_r,
                    format!("full power from {t:.1} s + the check's time"),
                )
            });
            let relay = o.relay_at_fault.then(|| {
                (
                    4.0 * d.sensor_stuck_energy_s / 0.1 + d.sensor_stuck_time_s + 2.0 * tick,
                    "autotune: 4·E over the relay's mean at ≥ 10 % off it".into(),
                )
            });
            // A reading frozen above the setpoint leaves the loop at 0 %: the heater only
            // cools, and nothing can tell a still reading from a heater at its ambient. It is
            // named once the loop asks for heat again.
            let off = holds_from(&o.duty, |u| u <= 0.005).is_some();
            // A frozen reading holds the relay where it is: the run's reference applies, not
            // the loop's ramp.
            let bound = if off && !o.relay_at_fault {
                [None, None]
            } else if relay.is_some() {
                [full, relay]
            } else {
                [swing, full]
            }
            .into_iter()
            .flatten()
            .min_by(|a, b| a.0.total_cmp(&b.0));
            (&["sensor_stuck", "no_rise", "not_heating"], bound)
        }
        PlantFault::HeaterStuckOn => {
            // The loop holds the line off from `t_off`; stuck_on sees the rise over its window
            // when the stuck heater rises by more than the limit (a fifth of margin) within
            // it, its dead time aside. Else temperature_out_of_range once the plant reaches
            // temp_max_c.
            let t_off = holds_from(&o.duty, |u| u <= 0.005);
            // The largest disturbance of the run may come during the watch: it slows the rise.
            let hot = o.ambient_at_fault_c + p.rate_c_per_s * p.tau_s * (1.0 - case.disturbance.0);
            let window = d.stuck_on_time_s;
            let rise = (hot - o.setpoint_c - 10.0).max(0.0)
                * (1.0 - (-(window - p.dead_time_s) / p.tau_s).exp());
            let stuck_on = t_off.filter(|_| rise > 1.2 * d.stuck_on_rise_c).map(|t| {
                (
                    t + window + tick + dt_r,
                    format!("line off from {t:.1} s + stuck_on_time_s"),
                )
            });
            let range = (hot > o.temp_max_c).then(|| {
                let t = p.dead_time_s
                    + p.tau_s
                        * ((hot - o.true_at_fault_c) / (hot - o.temp_max_c))
                            .ln()
                            .max(0.0);
                // The ambient drifts by up to 5 °C an hour: a tenth more.
                (1.1 * t + dt_r, "the plant reaching temp_max_c".into())
            });
            let bound = [stuck_on, range]
                .into_iter()
                .flatten()
                .min_by(|a, b| a.0.total_cmp(&b.0));
            (
                &[
                    "stuck_on",
                    "temperature_out_of_range",
                    "model_deviation",
                    "sensor_stuck",
                ],
                bound,
            )
        }
        PlantFault::None => (&[], None),
    }
}

/// Every fault of a heater in the sizing range, at a random instant of the heat-up, the
/// settled loop or an autotune's relay, with only the required parameters: named by a check
/// that can see it within the bound the defaults give, the line off from then on, and — for
/// every fault the line can stop — the plant never more than 10 °C above
/// `max(setpoint, reading at the fault)`.
#[test]
fn every_fault_is_named_within_its_bound_and_the_plant_kept_within_10_c() {
    let per_fault: u64 = std::env::var("PWM_FAULT_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(12);
    fault_cases(Control::Pid, per_fault);
}

/// The same faults, cases and bounds under `control` `mpc` on the plant's model: every check
/// holds under the model-predictive loop as under the PID.
#[test]
fn under_mpc_every_fault_is_named_within_its_bound_and_the_plant_kept_within_10_c() {
    let per_fault: u64 = std::env::var("PWM_FAULT_CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(12);
    fault_cases(Control::Mpc, per_fault);
}

fn fault_cases(control: Control, per_fault: u64) {
    let mut lines = Vec::new();
    let mut unseen = 0;
    for fault in FAULTS {
        let (mut worst_t, mut worst_bound, mut worst_excess) = (0.0f64, 0.0f64, f64::NEG_INFINITY);
        let mut named = std::collections::BTreeMap::new();
        for k in 0..per_fault {
            let seed = k * 31 + fault as u64;
            let case = arb_case(seed, fault, control);
            let o = run(&case, 900.0);
            let ctx = format!("seed {seed} {case:?}");
            assert!(
                o.early.is_none(),
                "a trip before the fault: {:?}; {ctx}",
                o.early
            );
            let (allowed, bound) = derived_bound(&case, &o);
            if let (Some((t, f)), PlantFault::HeaterHalfPower) = (o.tripped, fault) {
                assert!(allowed.contains(&f.check()), "{f} named {fault:?}; {ctx}");
                *named.entry(f.check()).or_insert(0) += 1;
                worst_t = worst_t.max(t);
                assert!(!o.rose_after_trip, "the line rose after {f}; {ctx}");
            } else if let Some((t, f)) = o.tripped {
                assert!(allowed.contains(&f.check()), "{f} named {fault:?}; {ctx}");
                *named.entry(f.check()).or_insert(0) += 1;
                if let Some((b, how)) = &bound {
                    assert!(t <= *b, "{f} after {t:.1} s, bound {b:.1} s ({how}); {ctx}");
                    worst_bound = worst_bound.max(*b);
                }
                worst_t = worst_t.max(t);
                assert!(!o.rose_after_trip, "the line rose after {f}; {ctx}");
            } else {
                assert!(
                    bound.is_none(),
                    "{fault:?} not named within {:?}; {ctx}",
                    bound
                );
                unseen += 1;
            }
            let excess = o.max_true_c - o.setpoint_c.max(o.reading_at_fault_c);
            if fault != PlantFault::HeaterStuckOn {
                assert!(
                    excess <= 10.0,
                    "{fault:?}: true {:.2} °C, {excess:.2} °C above max(setpoint {:.2}, \
                     reading {:.2}); {ctx}",
                    o.max_true_c,
                    o.setpoint_c,
                    o.reading_at_fault_c
                );
            }
            worst_excess = worst_excess.max(excess);
        }
        lines.push(format!(
            "  {:<20} named {:?}; slowest {worst_t:.1} s (largest bound {worst_bound:.1} s); \
             hottest {worst_excess:+.1} °C over max(setpoint, reading)",
            fault.name(),
            named
        ));
    }
    println!(
        "heater faults under {}, {per_fault} cases each (sizing range r 0.3..0.7 °C/s, tau 30..600 s, \
         L 0.5..3 s), {unseen} harmless and unseen:\n{}",
        control.as_str(),
        lines.join("\n")
    );
}

#[test]
#[ignore]
fn explore_random() {
    let n: u64 = std::env::var("CASES")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(200);
    for seed in 0..n {
        let mut g = Gen::new(seed ^ 77);
        let case = arb_case(seed, g.pick(&FAULTS), Control::Pid);
        let plant = case.plant;
        let o = run(&case, 900.0);
        let bound = o.setpoint_c.max(o.reading_at_fault_c) + 10.0;
        println!(
            "seed {seed:4} r={:.2} tau={:.0} L={:.1} q={} sp={:.0} {:?} {:<20} -> {:<24} after {:>6} s, max {:.1} ({:+.1} over bound){}{}",
            plant.rate_c_per_s, plant.tau_s, plant.dead_time_s, case.quantum_c,
            o.setpoint_c,
            case.when,
            case.fault.name(),
            o.tripped.map_or("NONE".into(), |(_, f)| f.check().to_string()),
            o.tripped.map_or("-".into(), |(t, _)| format!("{t:.1}")),
            o.max_true_c,
            o.max_true_c - bound,
            if o.rose_after_trip { " ROSE" } else { "" },
            o.early.map_or(String::new(), |f| format!(" EARLY {f}")),
        );
    }
}

/// A channel and its plant in virtual time, keeping nothing but what the healthy runs check
/// (hours of edges would not fit in memory).
struct Lean {
    ch: crate::core::Channel,
    plant: crate::core::heater::Plant,
    now: Nanos,
    next_reading: Nanos,
    every: Nanos,
    fault: Option<(Nanos, HeaterFault)>,
    autotunes: u32,
    finished: bool,
}

impl Lean {
    fn act(&mut self, f: impl FnOnce(&mut crate::core::Channel, Nanos, &mut dyn FnMut(Event))) {
        let (now, plant, fault, finished) = (
            self.now,
            &mut self.plant,
            &mut self.fault,
            &mut self.finished,
        );
        f(&mut self.ch, now, &mut |e| match e {
            Event::Edge { level, .. } => plant.line(now, level.is_high()),
            Event::HeaterFault(h) => {
                fault.get_or_insert((now, h));
            }
            Event::Autotune {
                report: Report::Finished(_),
                ..
            } => *finished = true,
            _ => {}
        });
    }

    fn run_to(&mut self, t: Nanos) {
        loop {
            let due = self.ch.poll_at().unwrap_or(Nanos::MAX);
            let next = due.min(self.next_reading);
            if next > t {
                break;
            }
            self.now = next;
            if next == self.next_reading {
                self.next_reading += self.every;
                if let Some(c) = self.plant.reading(next) {
                    self.act(|ch, now, emit| ch.feedback(now, c, emit));
                }
            } else {
                self.act(|ch, now, emit| ch.poll(now, emit));
            }
        }
        self.now = t;
        self.plant.advance(t);
    }
}

/// One healthy run of `hours` simulated hours: setpoint changes, disturbance steps of up to
/// 30 % of full power, the ambient drifting by up to ±5 °C, autotunes, the channel disabled
/// and enabled again. Returns the fault if one latched (none may), with what was going on.
fn healthy_run(seed: u64, hours: f64, control: Control) -> Result<u32, String> {
    let mut g = Gen::new(seed ^ 0xA5A5);
    let plant = arb_plant(&mut g);
    let quantum = g.pick(&[0.0, 0.0, 0.0625, 0.25]);
    let dist_max = g.pick(&[0.0, 0.15, 0.3]);
    let top_share = 0.6 - dist_max;
    let full = plant.rate_c_per_s * plant.tau_s;
    let temp_max = plant.ambient_c + top_share * full + 15.0 + 10.0;
    let ch = ChannelParams {
        period_ms: 1000,
        heater: for_loop(required(&plant, temp_max), &plant, control, dist_max),
        ..ChannelParams::default()
    };
    let cfg = ch.validate().map_err(|e| e.to_string())?;
    let mut l = Lean {
        ch: crate::core::Channel::new(cfg, 0),
        plant: crate::core::heater::Plant::new(plant, 0, seed),
        now: 0,
        next_reading: 0,
        every: 250_000_000,
        fault: None,
        autotunes: 0,
        finished: false,
    };
    l.plant.set_quantum(quantum);
    let drift = g.range(-5.0, 5.0);
    let end = (hours * 3600.0 * 1e9) as Nanos;
    let mut setpoint = plant.ambient_c + g.range(0.1, top_share) * full;
    l.run_to(S);
    l.act(|ch, now, emit| ch.set_setpoint(now, setpoint, emit));
    l.act(|ch, now, emit| ch.set_enable(now, true, emit));
    let mut log = Vec::new();
    while l.now < end {
        let segment = (g.range(600.0, 3600.0) * 1e9) as Nanos;
        let action = g.pick(&[0, 0, 1, 1, 2, 3]);
        let what = match action {
            0 => {
                setpoint = plant.ambient_c + g.range(0.1, top_share) * full;
                l.act(|ch, now, emit| ch.set_setpoint(now, setpoint, emit));
                format!("setpoint {setpoint:.1}")
            }
            1 => {
                let d = if l.plant.disturbance() > 0.0 {
                    0.0
                } else {
                    g.range(0.0, dist_max)
                };
                l.plant.set_disturbance(d);
                format!("disturbance {d:.2}")
            }
            2 if l.ch.enabled() => {
                let goal = Goal {
                    target_c: setpoint,
                    amplitude_pct: 100.0,
                    noise_band_c: (2.0 * plant.noise_c + quantum).max(0.2),
                };
                l.finished = false;
                l.act(|ch, now, emit| ch.start_autotune(now, 1, goal, emit));
                l.autotunes += 1;
                format!("autotune at {setpoint:.1}")
            }
            _ => {
                let on = !l.ch.enabled();
                l.act(|ch, now, emit| ch.set_enable(now, on, emit));
                format!("enable {on}")
            }
        };
        log.push(format!("{:.0} s: {what}", l.now as f64 / 1e9));
        let stop = (l.now + segment).min(end);
        while l.now < stop {
            let t = (l.now + 60 * S).min(stop);
            l.plant
                .set_ambient(plant.ambient_c + drift * l.now as f64 / end as f64);
            l.run_to(t);
            if l.finished {
                // An autotune ended: the user sends the setpoint again.
                l.finished = false;
                l.act(|ch, now, emit| ch.set_setpoint(now, setpoint, emit));
            }
            if let Some((t, f)) = l.fault {
                return Err(format!(
                    "seed {seed}: {f} at {:.0} s on a healthy heater {plant:?}, quantum \
                     {quantum}; true {:.2} °C; last actions: {:?}",
                    t as f64 / 1e9,
                    l.plant.temperature(),
                    &log[log.len().saturating_sub(4)..]
                ));
            }
        }
    }
    Ok(l.autotunes)
}

#[test]
fn healthy_heaters_never_trip() {
    let runs: u64 = std::env::var("PWM_HEALTHY_RUNS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(125);
    let hours = 8.0;
    let start = std::time::Instant::now();
    let mut autotunes = 0;
    for seed in 0..runs {
        match healthy_run(seed, hours, Control::Pid) {
            Ok(n) => autotunes += n,
            Err(e) => panic!("{e}"),
        }
    }
    println!(
        "healthy heaters: {runs} runs, {:.0} simulated hours, {autotunes} autotunes, 0 trips \
         ({:.1} s)",
        runs as f64 * hours,
        start.elapsed().as_secs_f64()
    );
}

/// The same healthy runs under `mpc` on the plant's model.
#[test]
fn healthy_heaters_never_trip_under_mpc() {
    let runs: u64 = std::env::var("PWM_HEALTHY_RUNS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(125);
    let hours = 8.0;
    let mut autotunes = 0;
    for seed in 0..runs {
        match healthy_run(seed, hours, Control::Mpc) {
            Ok(n) => autotunes += n,
            Err(e) => panic!("{e}"),
        }
    }
    println!(
        "healthy heaters under mpc: {runs} runs, {:.0} simulated hours, {autotunes} autotunes, \
         0 trips",
        runs as f64 * hours
    );
}

#[test]
#[ignore]
fn one_case() {
    let seed: u64 = std::env::var("SEED").unwrap().parse().unwrap();
    let fault = PlantFault::parse(&std::env::var("FAULT").unwrap()).unwrap();
    let control = match std::env::var("CONTROL").as_deref() {
        Ok("mpc") => Control::Mpc,
        _ => Control::Pid,
    };
    let case = arb_case(seed, fault, control);
    let o = run(&case, 900.0);
    println!(
        "{case:?}\n tripped {:?}\n sp {} reading {} relay {} duty0 {}",
        o.tripped, o.setpoint_c, o.reading_at_fault_c, o.relay_at_fault, o.duty_at_fault
    );
    for (t, d) in o.duty.iter().step_by(8) {
        print!("{t:.0}:{:.0} ", d * 100.0);
    }
    println!();
}
