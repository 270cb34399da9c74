//! The model-predictive loop (`control` `mpc`) in virtual time, against the PID the autotune
//! gives for the same plant: a setpoint step, then a disturbance of 30 % of full power,
//! announced by the feed-forward or not; bumpless switches between the loops; the
//! feed-forward's bounds and staleness; setpoint ramps.

use super::autotune::{identify, lagging, LAGGING_PLANTS};
use super::heater::{heater, params, Rig};
use crate::core::heater::autotune::Stop;
use crate::core::heater::{Control, Gains, HeaterParams, ModelParams, PlantParams};
use crate::core::ChannelParams;

/// What a run of the scenario showed.
#[derive(Debug, Clone, Copy)]
pub(super) struct Run {
    /// The integrated absolute error of the block's true temperature against the setpoint from
    /// the step on, °C·s.
    pub iae: f64,
    /// Of the step alone (until the disturbance), and of the disturbance.
    pub iae_step: f64,
    pub iae_dist: f64,
    /// The block's largest excursion above the setpoint after the step, °C.
    pub overshoot: f64,
    /// The largest dip below the setpoint after the disturbance, °C.
    pub dip: f64,
    /// How long the block took to come back within 0.5 °C of the setpoint for good after
    /// the disturbance, s.
    pub recovery_s: f64,
}

/// The loops compared.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Loop {
    /// The PID with the autotune's gains.
    Pid,
    /// The model-predictive loop, the disturbance announced by the feed-forward.
    MpcFf,
    /// The model-predictive loop, the disturbance unannounced.
    Mpc,
}

/// The channel for `plant` under `which`, with the autotune's gains and model.
pub(super) fn channel(plant: &PlantParams, which: Loop, g: Gains, m: ModelParams) -> ChannelParams {
    let mut h = HeaterParams {
        pid_kp: g.kp,
        pid_ki: g.ki,
        pid_kd: g.kd,
        pid_d_filter_s: g.d_filter_s,
        model: m,
        feedforward: true,
        // An unannounced disturbance of 30 % shifts model_deviation's residual by up to
        // gain × 30 %: sized above it (docs/heater.md).
        model_tolerance_c: m.gain_c_per_pct * 30.0 + 5.0,
        ..heater(plant)
    };
    h.control = match which {
        Loop::Pid => Control::Pid,
        _ => Control::Mpc,
    };
    params(h)
}

/// Settles `plant` at `sp0` (the share of its full rise), steps the setpoint to `sp1`, and
/// after `step_s` takes 30 % of its power away (a fan), for `dist_s` more; the figures from
/// the step on.
pub(super) fn scenario(
    plant: PlantParams,
    ch: ChannelParams,
    which: Loop,
    (sp0, sp1): (f64, f64),
    (step_s, dist_s): (f64, f64),
    seed: u64,
) -> Run {
    let full = plant.rate_c_per_s * plant.tau_s;
    let (sp0, sp1) = (plant.ambient_c + sp0 * full, plant.ambient_c + sp1 * full);
    let mut r = Rig::new(ch, plant, seed);
    let ff = |r: &mut Rig, pct: f64| r.act(|c, now, emit| c.feedforward(now, pct, emit));
    ff(&mut r, 0.0);
    r.secs(1.0);
    r.setpoint(sp0).enable();
    // Settle: five time constants, the feed-forward kept fresh.
    let settle = 5.0 * plant.tau_s + 60.0;
    let mut t = 0.0;
    while t < settle {
        ff(&mut r, 0.0);
        r.secs(1.0);
        t += 1.0;
    }
    r.setpoint(sp1);
    let (mut iae_step, mut iae_dist, mut over, mut dip) = (0.0, 0.0, f64::NEG_INFINITY, 0.0f64);
    let (mut last_out, mut bias, mut bias_n) = (0.0, 0.0f64, 0.0f64);
    // The block's temperature averaged over each period (1 s, ten points): the PWM's own
    // ripple is not the loop's error.
    let dt = 0.1;
    let seconds = (step_s + dist_s) as u64;
    for k in 0..seconds {
        let t = k as f64;
        let disturbed = t >= step_s;
        if disturbed && r.plant.disturbance() == 0.0 {
            r.plant.advance(r.now);
            r.plant.set_disturbance(0.3);
        }
        let announced = if disturbed && which == Loop::MpcFf {
            30.0
        } else {
            0.0
        };
        ff(&mut r, announced);
        let mut mean = 0.0;
        for _ in 0..10 {
            r.secs(dt);
            mean += r.plant.temperature() / 10.0;
        }
        let e = mean - sp1;
        if disturbed {
            iae_dist += e.abs();
            dip = dip.max(-e);
            if e.abs() > 0.5 {
                last_out = t + 1.0 - step_s;
            }
        } else {
            iae_step += e.abs();
            if t >= step_s - 100.0 {
                bias += e;
                bias_n += 1.0;
            }
        }
        over = over.max(e);
    }
    let _ = bias / bias_n;
    assert!(r.faults().is_empty(), "{which:?}: {:?}", r.faults());
    Run {
        iae: iae_step + iae_dist,
        iae_step,
        iae_dist,
        overshoot: over,
        dip,
        recovery_s: last_out,
    }
}

/// The least integrated absolute error any loop can reach on the step from `sp0` to `sp1`
/// (°C) of `plant` from rest at `sp0`, °C·s: full power from the step on, acting after the
/// dead time, up to the setpoint (the block's first-order rise at full power, exactly).
pub(super) fn least_step_iae(plant: &PlantParams, sp0: f64, sp1: f64) -> f64 {
    let hot = plant.ambient_c + plant.rate_c_per_s * plant.tau_s;
    let s1 = plant.tau_s * ((hot - sp0) / (hot - sp1)).ln();
    (sp1 - sp0) * plant.dead_time_s
        + (sp1 - hot) * s1
        + (hot - sp0) * plant.tau_s * (1.0 - (-s1 / plant.tau_s).exp())
}

/// On every plant of the sizing range with a lagging, noisy sensor: the model the autotune
/// identifies is within 10 % of the plant in gain, time constant and the two lags' sum, and in
/// its dead time wherever the run does not say that is uncertain (then within three of the
/// standard errors it gives); on a setpoint step (20 % to 30 % of the full rise)
/// and then a fan taking 30 % of full power, `mpc` with the fan announced by the feed-forward
/// errs by at most half of what the autotune's PID errs beyond the least any loop can (full
/// power from the first sample after the step), on every plant; overshoot below 1 °C; with
/// the fan unannounced, no worse than the PID.
#[test]
fn mpc_against_the_autotuned_pid_on_a_step_and_a_fan() {
    let mut lines = Vec::new();
    for i in 0..LAGGING_PLANTS.len() {
        let plant = lagging(i);
        let o = identify(plant, 3 + i as u64);
        assert_eq!(o.stop, Stop::Converged, "{plant:?}: {o:?}");
        let est = o.estimate.unwrap();
        let (g, m) = (o.gains.unwrap(), est.model.unwrap());
        let se = est.dead_time_se_s.unwrap();
        let err = |a: f64, b: f64| (a / b - 1.0) * 100.0;
        let k = plant.rate_c_per_s * plant.tau_s / 100.0;
        let lags = plant.dead_time_s + plant.sensor_tau_s;
        let (e_gain, e_tau) = (err(m.gain_c_per_pct, k), err(m.tau_s, plant.tau_s));
        let e_lags = err(m.dead_time_s + m.sensor_tau_s, lags);
        let e_dead = err(m.dead_time_s, plant.dead_time_s);
        assert!(
            e_gain.abs() <= 10.0 && e_tau.abs() <= 10.0,
            "{plant:?}: {m:?}"
        );
        // The dead time within 10 %, unless the run says it is uncertain (the split between
        // the dead time and the sensor's lag is what the noise hides): then within three of
        // the standard errors it gives, and the two lags together within 10 %.
        if e_dead.abs() > 10.0 {
            assert!(!est.dead_time_certain(), "{plant:?}: {m:?} ± {se}");
            assert!(
                (m.dead_time_s - plant.dead_time_s).abs() <= 3.0 * se,
                "{plant:?}: {m:?} ± {se}"
            );
        }
        assert!(e_lags.abs() <= 10.0, "{plant:?}: {m:?}");
        let step_s = 3.0 * plant.tau_s.min(200.0) + 100.0;
        let full = plant.rate_c_per_s * plant.tau_s;
        let (sp0, sp1) = (plant.ambient_c + 0.2 * full, plant.ambient_c + 0.3 * full);
        // The step comes right after a sample: the first sample that sees it is a period on.
        let least = least_step_iae(&plant, sp0, sp1) + (sp1 - sp0) * 1.0;
        let run = |which| {
            let ch = channel(&plant, which, g, m);
            scenario(plant, ch, which, (0.2, 0.3), (step_s, step_s), 7)
        };
        let (pid, ff, blind) = (run(Loop::Pid), run(Loop::MpcFf), run(Loop::Mpc));
        let ratio = (ff.iae - least) / (pid.iae - least);
        for (name, r) in [("mpc+ff", ff), ("mpc", blind)] {
            assert!(r.overshoot < 1.0, "{name} {plant:?}: {r:?}");
        }
        assert!(
            blind.iae <= pid.iae,
            "{plant:?}: mpc {blind:?}, pid {pid:?}"
        );
        assert!(
            ratio <= 0.5,
            "{plant:?}: mpc+ff {ff:?}, pid {pid:?}, least {least}"
        );
        lines.push(format!(
            "  {i}: rate {} tau {} L {} sensor {} noise {}: model gain {e_gain:+.1} % tau \
             {e_tau:+.1} % L {e_dead:+.1} % (± {:.1} %{}) L+sensor {e_lags:+.1} %\n     IAE °C·s (least \
             {least:.0}): pid {:.0} (step {:.0}, fan {:.0}), mpc+ff {:.0} ({:.0}, {:.0}), mpc \
             {:.0} ({:.0}, {:.0}); beyond the least mpc+ff/pid {ratio:.2}; overshoot pid \
             {:.2} mpc {:.2} °C; fan dip pid {:.2} mpc+ff {:.2} mpc {:.2} °C, back within 0.5 °C after pid {:.0} \
             mpc+ff {:.0} mpc {:.0} s",
            plant.rate_c_per_s,
            plant.tau_s,
            plant.dead_time_s,
            plant.sensor_tau_s,
            plant.noise_c,
            se / m.dead_time_s * 100.0,
            if est.dead_time_certain() {
                ""
            } else {
                ", said uncertain"
            },
            pid.iae,
            pid.iae_step,
            pid.iae_dist,
            ff.iae,
            ff.iae_step,
            ff.iae_dist,
            blind.iae,
            blind.iae_step,
            blind.iae_dist,
            pid.overshoot,
            ff.overshoot,
            pid.dip,
            ff.dip,
            blind.dip,
            pid.recovery_s,
            ff.recovery_s,
            blind.recovery_s,
        ));
    }
    println!(
        "mpc against the autotuned PID, {} plants:\n{}",
        LAGGING_PLANTS.len(),
        lines.join("\n")
    );
}

/// Switching `pid` → `mpc` → `pid` on a settled heater moves the duty by no more than the
/// noise does: each loop starts from the duty the other left.
#[test]
fn pid_to_mpc_and_back_is_bumpless() {
    let plant = lagging(3);
    let g = Gains {
        kp: 8.0,
        ki: 0.2,
        kd: 0.0,
        d_filter_s: 0.0,
    };
    let m = ModelParams {
        gain_c_per_pct: plant.rate_c_per_s * plant.tau_s / 100.0,
        tau_s: plant.tau_s,
        dead_time_s: plant.dead_time_s,
        ambient_c: plant.ambient_c,
        sensor_tau_s: plant.sensor_tau_s,
    };
    let pid = channel(&plant, Loop::Pid, g, m);
    let mpc = channel(&plant, Loop::Mpc, g, m);
    let mut r = Rig::new(pid, plant, 5);
    r.secs(1.0).setpoint(40.0).enable().secs(600.0);
    let duty = |r: &Rig| r.ch.status(r.now).duty_commanded * 100.0;
    let mut jumps = Vec::new();
    for (name, to) in [("pid→mpc", mpc), ("mpc→pid", pid), ("pid→mpc", mpc)] {
        let before = duty(&r);
        let cfg = to.validate().unwrap();
        r.act(|ch, now, emit| ch.set_config(now, cfg, emit));
        r.secs(1.0);
        let after = duty(&r);
        r.secs(300.0);
        let band = r.plant.temperature() - 40.0;
        println!("{name}: duty {before:.1} % -> {after:.1} %, then {band:+.2} °C off");
        jumps.push((after - before).abs());
        assert!((after - before).abs() < 5.0, "{name}: {before} -> {after}");
        assert!(band.abs() < 1.0, "{name}: {band}");
        assert!(r.faults().is_empty(), "{:?}", r.faults());
    }
}

/// With `setpoint_ramp_c_per_s` the loop's target moves at that rate from the reading, the
/// status shows it, and the heater follows it (`not_heating` against a ramped target:
/// `checks::tests::a_ramp_is_one_approach_not_one_per_tick`).
#[test]
fn a_setpoint_ramp_is_followed_and_watched() {
    let plant = lagging(4);
    let m = ModelParams {
        gain_c_per_pct: plant.rate_c_per_s * plant.tau_s / 100.0,
        tau_s: plant.tau_s,
        dead_time_s: plant.dead_time_s,
        ambient_c: plant.ambient_c,
        sensor_tau_s: plant.sensor_tau_s,
    };
    let g = Gains {
        kp: 8.0,
        ki: 0.2,
        kd: 0.0,
        d_filter_s: 0.0,
    };
    for which in [Loop::Pid, Loop::Mpc] {
        let mut ch = channel(&plant, which, g, m);
        ch.heater.setpoint_ramp_c_per_s = 0.1;
        let mut r = Rig::new(ch, plant, 9);
        r.secs(2.0).enable().setpoint(30.0).secs(10.0);
        let st = r.ch.status(r.now).heater;
        let target = st.target.unwrap();
        assert!((target - 21.0).abs() < 0.5, "{which:?}: {target}");
        assert_eq!(st.setpoint, Some(30.0));
        let mut worst = 0.0f64;
        for _ in 0..80 {
            r.secs(1.0);
            let t = r.ch.status(r.now).heater.target.unwrap();
            worst = worst.max((r.plant.temperature() - t).abs());
        }
        let t = r.ch.status(r.now).heater.target.unwrap();
        assert!((t - 29.0).abs() < 0.5, "{which:?}: {t}");
        println!("{which:?}: ramp 0.1 °C/s, heater within {worst:.2} °C of the ramped target");
        // A PI lags a ramp by rate/(K·ki); the model-predictive loop runs ahead of its lags.
        let bound = if which == Loop::Pid { 2.5 } else { 0.75 };
        assert!(worst < bound, "{which:?}: {worst}");
        assert!(r.faults().is_empty());
    }
}

/// A feed-forward beyond ±100 % or not a number is refused; one older than
/// `feedforward_timeout_ms` is stale: shown, and no longer used.
#[test]
fn the_feedforward_is_bounded_and_goes_stale() {
    let plant = lagging(4);
    let m = ModelParams {
        gain_c_per_pct: plant.rate_c_per_s * plant.tau_s / 100.0,
        tau_s: plant.tau_s,
        dead_time_s: plant.dead_time_s,
        ambient_c: plant.ambient_c,
        sensor_tau_s: plant.sensor_tau_s,
    };
    let g = Gains {
        kp: 8.0,
        ki: 0.2,
        kd: 0.0,
        d_filter_s: 0.0,
    };
    let mut r = Rig::new(channel(&plant, Loop::Mpc, g, m), plant, 9);
    r.secs(1.0).setpoint(40.0).enable().secs(100.0);
    assert!(r.ch.status(r.now).heater.feedforward_stale);
    for bad in [f64::NAN, 100.5, -101.0, f64::INFINITY] {
        r.act(|c, now, emit| c.feedforward(now, bad, emit));
        assert!(
            matches!(
                r.notes.last(),
                Some((
                    _,
                    crate::core::Event::Refused(crate::core::heater::Refusal::Feedforward(_))
                ))
            ),
            "{bad}"
        );
    }
    r.act(|c, now, emit| c.feedforward(now, 20.0, emit));
    r.secs(1.0);
    let st = r.ch.status(r.now).heater;
    assert_eq!(st.feedforward_pct, 20.0);
    assert!(!st.feedforward_stale);
    let timeout = r.ch.config().heater.params.feedforward_timeout_ms as f64 / 1000.0;
    r.secs(timeout + 1.0);
    let st = r.ch.status(r.now).heater;
    assert_eq!(st.feedforward_pct, 0.0);
    assert!(st.feedforward_stale);
    assert!(r.faults().is_empty());
}

/// An ambient reading outside `temp_min_c..=temp_max_c` or not a number is refused; a fresh
/// one is the ambient in force; one older than `ambient_timeout_ms` is stale, and the model's
/// ambient is back in force.
#[test]
fn the_ambient_is_bounded_and_goes_stale() {
    let plant = lagging(4);
    let m = ModelParams {
        gain_c_per_pct: plant.rate_c_per_s * plant.tau_s / 100.0,
        tau_s: plant.tau_s,
        dead_time_s: plant.dead_time_s,
        ambient_c: plant.ambient_c,
        sensor_tau_s: plant.sensor_tau_s,
    };
    let g = Gains {
        kp: 8.0,
        ki: 0.2,
        kd: 0.0,
        d_filter_s: 0.0,
    };
    let mut ch = channel(&plant, Loop::Mpc, g, m);
    ch.heater.ambient = true;
    ch.heater.ambient_timeout_ms = 10_000;
    let max = ch.heater.temp_max_c;
    let mut r = Rig::new(ch, plant, 9);
    r.secs(1.0).setpoint(40.0).enable().secs(20.0);
    assert!(r.ch.status(r.now).heater.ambient_stale);
    for bad in [f64::NAN, max + 1.0, -300.0] {
        r.act(|c, now, emit| c.ambient_reading(now, bad, None, emit));
        assert!(
            matches!(
                r.notes.last(),
                Some((
                    _,
                    crate::core::Event::Refused(crate::core::heater::Refusal::Ambient { .. })
                ))
            ),
            "{bad}"
        );
    }
    r.act(|c, now, emit| c.ambient_reading(now, 25.0, None, emit));
    r.secs(1.0);
    let st = r.ch.status(r.now).heater;
    assert_eq!(st.ambient_c, Some(25.0));
    assert!(!st.ambient_stale);
    r.secs(10.0);
    let st = r.ch.status(r.now).heater;
    assert_eq!(st.ambient_c, Some(plant.ambient_c));
    assert!(st.ambient_stale);
    assert!(r.faults().is_empty());
}

#[test]
#[ignore]
fn explore() {
    let only: Option<usize> = std::env::var("PLANT").ok().and_then(|s| s.parse().ok());
    for i in (0..LAGGING_PLANTS.len()).filter(|i| only.is_none_or(|o| o == *i)) {
        let plant = lagging(i);
        let o = identify(plant, 3 + i as u64);
        assert_eq!(o.stop, Stop::Converged);
        let (g, m) = (o.gains.unwrap(), o.estimate.unwrap().model.unwrap());
        let step_s = 3.0 * plant.tau_s.min(200.0) + 100.0;
        let dist_s = step_s;
        let full = plant.rate_c_per_s * plant.tau_s;
        let least = least_step_iae(
            &plant,
            plant.ambient_c + 0.2 * full,
            plant.ambient_c + 0.3 * full,
        );
        println!("{i} least {least:.1}");
        for which in [Loop::Pid, Loop::MpcFf, Loop::Mpc] {
            let ch = channel(&plant, which, g, m);
            let run = scenario(plant, ch, which, (0.2, 0.3), (step_s, dist_s), 7);
            println!("{i} {which:?}: {run:?}");
        }
    }
}
