//! The autotune through a channel in virtual time: the relay's duty takes the path of a duty
//! command to a first-order-plus-dead-time plant, the run converges, its gains hold the
//! setpoint, the protections act on the line throughout, and every abort path ends the run
//! with its reason, the line off and the old gains in force.

use super::heater::{heater, params, Rig};
use crate::core::heater::autotune::{Goal, GoalRefusal, Outcome, Report, Stop};
use crate::core::heater::{HeaterFault, PlantFault, PlantParams, Refusal};
use crate::core::{Channel, ChannelParams, Command, Event, Level, Nanos};

const S: Nanos = 1_000_000_000;

fn plant() -> PlantParams {
    PlantParams {
        rate_c_per_s: 2.0,
        tau_s: 60.0,
        dead_time_s: 3.0,
        ambient_c: 20.0,
        noise_c: 0.05,
        sensor_tau_s: 0.0,
    }
}

fn goal(amplitude_pct: f64) -> Goal {
    Goal {
        target_c: 68.0,
        amplitude_pct,
        noise_band_c: 0.5,
    }
}

/// A channel under `pid` with `p`, enabled, its plant at ambient, readings flowing.
fn rig(p: ChannelParams) -> Rig {
    let mut r = Rig::new(p, plant(), 3);
    r.secs(1.0).enable().secs(1.0);
    r
}

fn start(r: &mut Rig, g: Goal) {
    r.act(|ch, now, emit| ch.start_autotune(now, 5, g, emit));
}

fn reports(r: &Rig) -> Vec<Report> {
    r.notes
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Autotune { ticket: 5, report } => Some(*report),
            _ => None,
        })
        .collect()
}

fn outcome(r: &Rig) -> Option<(Nanos, Outcome)> {
    r.notes.iter().find_map(|(t, e)| match e {
        Event::Autotune {
            report: Report::Finished(o),
            ..
        } => Some((*t, *o)),
        _ => None,
    })
}

/// Runs until the run ends (at most `limit_s`).
fn until_done(r: &mut Rig, limit_s: u64) -> (Nanos, Outcome) {
    for _ in 0..limit_s {
        r.secs(1.0);
        if let Some(o) = outcome(r) {
            return o;
        }
    }
    panic!("no end within {limit_s} s: {:?}", reports(r).last());
}

/// The longest run of the line high.
fn longest_high(r: &Rig) -> Nanos {
    let mut longest = 0;
    let mut rose = None;
    for &(at, level) in &r.edges {
        match level {
            Level::High => rose = rose.or(Some(at)),
            Level::Low => {
                if let Some(t) = rose.take() {
                    longest = longest.max(at - t);
                }
            }
        }
    }
    longest
}

#[test]
fn a_run_through_the_channel_converges_and_its_gains_hold_the_setpoint() {
    let p = params(heater(&plant()));
    let mut r = rig(p);
    let old = r.ch.config().heater.gains;
    start(&mut r, goal(60.0));
    let (_, o) = until_done(&mut r, 5000);
    assert_eq!(o.stop, Stop::Converged, "{o:?}");
    let est = o.estimate.unwrap();
    // The describing function for the averaged 60 % relay (see autotune's tests), with the
    // period's time-proportioning as extra delay (a switch of the relay reaches the line at
    // the next period start, half a period later on average): within 10 %. The estimate
    // comes from the power the line really delivered.
    let delayed = PlantParams {
        dead_time_s: plant().dead_time_s + 0.5,
        ..plant()
    };
    let (ku, tu) =
        crate::core::heater::autotune::tests::describing_function(&delayed, 68.0, 60.0, 0.5);
    println!("through the channel: {est:?}; DF Ku {ku:.3} Tu {tu:.1}");
    assert!((est.ku / ku - 1.0).abs() < 0.1, "{} vs {ku}", est.ku);
    assert!((est.tu_s / tu - 1.0).abs() < 0.1, "{} vs {tu}", est.tu_s);
    // Progress: the approach, then every cycle, counted up.
    let cycles: Vec<u32> = reports(&r)
        .iter()
        .filter_map(|rep| match rep {
            Report::Progress(p) => Some(p.cycles),
            _ => None,
        })
        .collect();
    assert!(
        cycles.windows(2).all(|w| w[0] <= w[1]) && cycles.len() >= 6,
        "{cycles:?}"
    );
    // The last cycle is reported before the end.
    assert_eq!(cycles.last(), Some(&o.progress.cycles));
    // The run leaves the old gains, the line commanded to 0 % and no setpoint.
    assert_eq!(r.ch.config().heater.gains, old);
    assert_eq!(r.ch.status(r.now).duty_commanded, 0.0);
    let s = o.sizing.unwrap();
    assert!(s.period_ok && s.min_times_ok, "{s:?}");
    assert!(s.recommended_period_ms >= 1000, "{s:?}");
    // The gains in force (as `apply` does through the parameters): the loop settles.
    let g = o.gains.unwrap();
    let mut p2 = p;
    p2.heater.pid_kp = g.kp;
    p2.heater.pid_ki = g.ki;
    p2.heater.pid_kd = g.kd;
    r.act(|ch, now, emit| ch.set_config(now, p2.validate().unwrap(), emit));
    r.secs(30.0);
    let from = r.now;
    r.setpoint(68.0).secs(0.0);
    r.watch_from = from;
    r.secs(40.0 * est.tu_s);
    let overshoot = r.band.1 - 68.0;
    r.band = (f64::INFINITY, f64::NEG_INFINITY);
    r.secs(10.0 * est.tu_s);
    println!(
        "settled within {:?} of 68 °C, overshoot {overshoot:.2} °C",
        r.band
    );
    assert!(r.band.0 > 67.0 && r.band.1 < 69.0, "{:?}", r.band);
    assert!(overshoot < 2.0, "{overshoot}");
    assert!(r.faults().is_empty());
}

#[test]
fn the_relay_goes_through_max_on_and_the_minimum_times() {
    let mut p = params(heater(&plant()));
    p.max_on_ms = 4000;
    p.min_on_ms = 50;
    let mut r = rig(p);
    start(&mut r, goal(100.0));
    let (_, o) = until_done(&mut r, 5000);
    // 100 % relay: the line would stay high for the whole on half; max_on_ms cuts it.
    assert!(longest_high(&r) <= 4 * S, "{}", longest_high(&r));
    assert!(
        matches!(o.stop, Stop::Converged | Stop::NotConverged { .. }),
        "{o:?}"
    );
    // No pulse below min_on.
    let mut rose = None;
    for &(at, level) in &r.edges {
        match level {
            Level::High => rose = Some(at),
            Level::Low => {
                if let Some(t) = rose.take() {
                    assert!(at - t >= 50_000_000, "{}", at - t);
                }
            }
        }
    }
}

/// Starts a run, lets it go `after_s`, applies `stop`, and checks: the run ended with
/// `expect`, the line is low and never rises afterwards (without a new enable), the duty
/// commanded is 0 % and the gains are the old ones.
fn aborts(
    p: ChannelParams,
    after_s: f64,
    stop: impl FnOnce(&mut Rig),
    expect: impl Fn(&Stop) -> bool,
) {
    let mut r = rig(p);
    let old = r.ch.config().heater.gains;
    start(&mut r, goal(60.0));
    r.secs(after_s);
    assert!(outcome(&r).is_none(), "{:?}", outcome(&r));
    stop(&mut r);
    r.secs(2.0);
    let (t, o) = outcome(&r).expect("the run ended");
    assert!(expect(&o.stop), "{o:?}");
    assert_eq!(o.gains, None);
    assert_eq!(r.ch.config().heater.gains, old);
    assert_eq!(r.ch.status(r.now).duty_commanded, 0.0);
    r.secs(120.0);
    assert!(r.no_rise_after(t), "the line rose after the end");
    assert!(r.ch.autotune_target().is_none());
}

#[test]
fn a_cancel_ends_the_run_with_the_line_off() {
    aborts(
        params(heater(&plant())),
        100.0,
        |r| r.act(|ch, now, emit| ch.cancel_autotune(now, 5, emit)),
        |s| *s == Stop::Canceled,
    );
    // A cancel with another ticket is ignored.
    let mut r = rig(params(heater(&plant())));
    start(&mut r, goal(60.0));
    r.act(|ch, now, emit| ch.cancel_autotune(now, 6, emit));
    r.secs(5.0);
    assert!(outcome(&r).is_none());
}

#[test]
fn the_estop_deactivate_disable_and_reconfigure_end_the_run() {
    let p = params(heater(&plant()));
    aborts(
        p,
        100.0,
        |r| r.act(|ch, now, emit| ch.set_estop(now, true, emit)),
        |s| *s == Stop::EStop,
    );
    aborts(
        p,
        100.0,
        |r| r.act(|ch, now, emit| ch.set_live(now, false, emit)),
        |s| *s == Stop::Deactivated,
    );
    aborts(
        p,
        100.0,
        |r| r.act(|ch, now, emit| ch.set_enable(now, false, emit)),
        |s| *s == Stop::Disabled,
    );
    let mut open = p;
    open.heater.control = crate::core::heater::Control::Open;
    aborts(
        p,
        100.0,
        |r| r.act(|ch, now, emit| ch.set_config(now, open.validate().unwrap(), emit)),
        |s| *s == Stop::Reconfigured,
    );
}

#[test]
fn heater_faults_end_the_run_and_the_checks_stay_armed() {
    let p = params(heater(&plant()));
    // A NaN reading: temperature_out_of_range.
    aborts(
        p,
        100.0,
        |r| r.act(|ch, now, emit| ch.feedback(now, f64::NAN, emit)),
        |s| matches!(s, Stop::HeaterFault(HeaterFault::OutOfRange { .. })),
    );
    // The heater falls off during the run: not_heating, against the run's target.
    aborts(
        p,
        30.0,
        |r| {
            r.plant.set_fault(PlantFault::HeaterDisconnected);
            r.secs(600.0);
        },
        |s| matches!(s, Stop::HeaterFault(HeaterFault::NotHeating { target_c, .. }) if *target_c == 68.0),
    );
    // A silent sensor: sensor_timeout.
    let mut timeout = p;
    timeout.heater.feedback_timeout_ms = 3000;
    aborts(
        timeout,
        100.0,
        |r| {
            r.plant.set_fault(PlantFault::SensorSilent);
            r.secs(5.0);
        },
        |s| matches!(s, Stop::HeaterFault(HeaterFault::SensorTimeout { .. })),
    );
}

#[test]
fn the_watchdog_ends_the_run_when_readings_stop() {
    let mut p = params(heater(&plant()));
    p.command_timeout_ms = 5000;
    // The sensor timeout would end the run first (3 s): the watchdog's turn here.
    p.heater.feedback_timeout_ms = 10_000;
    // Readings feed the watchdog while the run goes (the setpoint does not come).
    let mut r = rig(p);
    r.setpoint(30.0);
    start(&mut r, goal(60.0));
    r.secs(200.0);
    assert_eq!(outcome(&r).map(|o| o.1.stop), Some(Stop::Converged));
    aborts(
        p,
        20.0,
        |r| {
            r.plant.set_fault(PlantFault::SensorSilent);
            r.secs(6.0);
        },
        |s| *s == Stop::Watchdog,
    );
}

#[test]
fn overshoot_and_timeout_end_the_run_through_the_channel() {
    let mut p = params(heater(&plant()));
    p.heater.autotune_max_overshoot_c = 1.0;
    let mut r = rig(p);
    start(&mut r, goal(100.0));
    let (_, o) = until_done(&mut r, 2000);
    assert!(
        matches!(o.stop, Stop::Overshoot { limit_c, .. } if limit_c == 69.0),
        "{o:?}"
    );
    let mut p = params(heater(&plant()));
    p.heater.autotune_timeout_s = 60.0;
    let mut r = rig(p);
    start(&mut r, goal(60.0));
    let (t, o) = until_done(&mut r, 2000);
    assert_eq!(o.stop, Stop::Timeout { timeout_s: 60.0 });
    assert!(t <= 63 * S + r.edges.first().map_or(0, |e| e.0), "{t}");
}

#[test]
fn goals_commands_and_setpoints_are_refused_with_a_reason() {
    let p = params(heater(&plant()));
    let refused = |r: &Rig| {
        reports(r).iter().rev().find_map(|rep| match rep {
            Report::Refused(x) => Some(*x),
            _ => None,
        })
    };
    // Disabled.
    let mut r = Rig::new(p, plant(), 3);
    r.secs(1.0);
    start(&mut r, goal(60.0));
    assert_eq!(refused(&r), Some(GoalRefusal::NotRunning));
    // Above max_duty_pct.
    let mut q = p;
    q.max_duty_pct = 50.0;
    let mut r = rig(q);
    start(&mut r, goal(60.0));
    assert!(matches!(refused(&r), Some(GoalRefusal::Amplitude { .. })));
    // Twice.
    let mut r = rig(p);
    start(&mut r, goal(60.0));
    start(&mut r, goal(60.0));
    assert_eq!(refused(&r), Some(GoalRefusal::Busy));
    // Setpoints while it runs; under open, duty commands.
    r.setpoint(50.0);
    assert!(r
        .notes
        .iter()
        .any(|(_, e)| *e == Event::Refused(Refusal::Autotuning)));
    let mut open = p;
    open.heater.control = crate::core::heater::Control::Open;
    let mut r = rig(open);
    start(&mut r, goal(60.0));
    r.act(|ch, now, emit| ch.command(now, Command::Percent(10.0), emit));
    assert!(r
        .notes
        .iter()
        .any(|(_, e)| *e == Event::Refused(Refusal::Autotuning)));
    r.secs(100.0);
    assert!(
        outcome(&r).is_none_or(|(_, o)| o.stop == Stop::Converged),
        "a run under open goes on"
    );
    // No feedback.
    let mut r = Rig::new(ChannelParams::default(), plant(), 3);
    r.ch = Channel::new(
        ChannelParams {
            period_ms: 1000,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap(),
        0,
    );
    r.enable();
    start(&mut r, goal(60.0));
    assert_eq!(refused(&r), Some(GoalRefusal::NoFeedback));
}

#[test]
fn a_goal_clears_a_tripped_watchdog_like_a_command() {
    let mut p = params(heater(&plant()));
    p.command_timeout_ms = 2000;
    // Under pid with no setpoint the watchdog trips.
    let mut r = rig(p);
    r.secs(3.0);
    assert!(r
        .notes
        .iter()
        .any(|(_, e)| *e == Event::Watchdog { tripped: true }));
    let t = r.now;
    start(&mut r, goal(60.0));
    r.secs(2.0);
    assert!(
        r.edges.iter().any(|(at, l)| *at >= t && *l == Level::High),
        "the relay's duty reaches the line"
    );
    let (_, o) = until_done(&mut r, 5000);
    assert_eq!(o.stop, Stop::Converged, "{o:?}");
}

/// A slow bed (time constant 300 s, dead time 60 s): its relay swings about 10 °C below the
/// band, long enough that `not_heating` with Klipper's defaults latches during the run — the
/// check stays armed. Sized for the plant (`runaway_gain_time_s` above the dead time,
/// `runaway_max_error` for the dips, `no_rise_time_s` and `sensor_stuck_time_s` at least
/// twice the dead time, `stuck_on_rise_c` above its rise after the line goes off,
/// docs/heater.md), the run converges in about 25 min.
#[test]
fn a_slow_bed_needs_its_runaway_settings_sized_for_the_run() {
    let bed = PlantParams {
        rate_c_per_s: 0.5,
        tau_s: 300.0,
        dead_time_s: 60.0,
        ambient_c: 20.0,
        noise_c: 0.05,
        sensor_tau_s: 0.0,
    };
    let g = Goal {
        target_c: 80.0,
        amplitude_pct: 100.0,
        noise_band_c: 0.5,
    };
    let run = |gain_time_s: f64, max_error: f64| {
        let mut p = params(heater(&bed));
        p.heater.runaway_gain_time_s = gain_time_s;
        p.heater.runaway_max_error = max_error;
        // The response checks, sized for its dead time too: at least twice it.
        p.heater.no_rise_time_s = 150.0;
        p.heater.sensor_stuck_time_s = 150.0;
        // And stuck_on above what it rises after its line goes off: 1.5·(r·L + 2n) + 0.5.
        p.heater.stuck_on_rise_c = 1.5 * (bed.rate_c_per_s * bed.dead_time_s + 0.1) + 0.5;
        let mut r = Rig::new(p, bed, 3);
        r.secs(1.0).enable().secs(1.0);
        start(&mut r, g);
        until_done(&mut r, 20_000)
    };
    let (_, o) = run(120.0, 120.0);
    assert!(
        matches!(o.stop, Stop::HeaterFault(HeaterFault::NotHeating { target_c, .. }) if target_c == 80.0),
        "{o:?}"
    );
    let (t, o) = run(120.0, 3000.0);
    assert_eq!(o.stop, Stop::Converged, "{o:?}");
    println!("bed: converged after {} s, {:?}", t / S, o.estimate);
    assert!(t < 30 * 60 * S, "{t}");
}

/// The plants of the identification: the sizing range (a rise of 0.3..0.7 °C/s, a time
/// constant of 30..600 s, a dead time of 0.5..3 s, noise up to ±0.2 °C), a fast cartridge and
/// a slow block, each with a sensor that lags its block by 0.5..3 s: `(rate, tau, dead time,
/// sensor lag, noise)`.
pub(super) const LAGGING_PLANTS: [(f64, f64, f64, f64, f64); 8] = [
    (0.3, 600.0, 0.5, 1.0, 0.2),
    (0.5, 300.0, 1.0, 3.0, 0.2),
    (0.7, 30.0, 3.0, 1.0, 0.2),
    (0.4, 120.0, 2.0, 0.5, 0.1),
    (0.6, 60.0, 0.5, 2.0, 0.05),
    (2.0, 60.0, 3.0, 2.0, 0.05),
    (3.0, 40.0, 1.0, 1.0, 0.05),
    (0.4, 300.0, 4.0, 0.0, 0.05),
];

/// A plant of [`LAGGING_PLANTS`].
pub(super) fn lagging(i: usize) -> PlantParams {
    let (rate, tau, dead, lag, noise) = LAGGING_PLANTS[i];
    PlantParams {
        rate_c_per_s: rate,
        tau_s: tau,
        dead_time_s: dead,
        ambient_c: 20.0,
        noise_c: noise,
        sensor_tau_s: lag,
    }
}

/// A run with `apply` on `plant` through a channel under `pid` (the period 1 s, readings at
/// 4 Hz), from ambient to a target at 40 % of its full rise: the outcome.
pub(super) fn identify(plant: PlantParams, seed: u64) -> Outcome {
    identify_within(plant, seed, 0.0).1
}

/// [`identify`] with `autotune_extend_s` `extend_s`: the rig (its reports) and the outcome.
fn identify_within(plant: PlantParams, seed: u64, extend_s: f64) -> (Rig, Outcome) {
    let mut h = heater(&plant);
    h.autotune_extend_s = extend_s;
    let p = params(h);
    let mut r = Rig::new(p, plant, seed);
    r.secs(1.0).enable().secs(1.0);
    let target = plant.ambient_c + 0.4 * plant.rate_c_per_s * plant.tau_s;
    let g = Goal {
        target_c: target,
        amplitude_pct: 100.0,
        noise_band_c: (1.1 * plant.noise_c).max(0.2),
    };
    r.act(|ch, now, emit| ch.start_autotune(now, 5, g, emit));
    let o = until_done(&mut r, 20_000).1;
    (r, o)
}

/// The model a run identifies from its approach and its cycles, through the channel (the
/// line's real on time, the PWM's period), on heaters across the sizing range and beyond,
/// each with noise and most with a sensor that lags its block, started from ambient: within
/// 10 % of the plant's gain and time constant, its dead time and sensor lag together within
/// 10 % of theirs, its ambient within 2 °C. The split between the two lags shows in how the
/// relay's corners round off (about `r·min(L, tau_s)`, `r` the rise at full power): where that
/// stands out of the noise (at least 2.5 times it) the dead time comes out within 10 % and the
/// sensor's lag within 20 % (or 0.2 s); below, only their sum is promised.
#[test]
fn a_run_identifies_the_heaters_model() {
    for i in 0..LAGGING_PLANTS.len() {
        let plant = lagging(i);
        let o = identify(plant, 3 + i as u64);
        assert_eq!(o.stop, Stop::Converged, "{plant:?}: {o:?}");
        let est = o.estimate.unwrap();
        let m = est.model.expect("a model");
        let se = est.dead_time_se_s.expect("the dead time's standard error");
        let k = plant.rate_c_per_s * plant.tau_s / 100.0;
        let err = |a: f64, b: f64| (a / b - 1.0) * 100.0;
        let lags = plant.dead_time_s + plant.sensor_tau_s;
        let snr = plant.rate_c_per_s * plant.dead_time_s.min(plant.sensor_tau_s) / plant.noise_c;
        let split = snr >= 2.5 || plant.sensor_tau_s == 0.0;
        println!(
            "rate {} °C/s, tau {} s, L {} s, sensor {} s, noise {} °C: gain {:+.1} %, tau \
             {:+.1} %, L {:.2} ± {se:.2} s ({:+.1} %{}), sensor {:.2} s, L + sensor {:+.1} %, \
             ambient {:.2} °C{}",
            plant.rate_c_per_s,
            plant.tau_s,
            plant.dead_time_s,
            plant.sensor_tau_s,
            plant.noise_c,
            err(m.gain_c_per_pct, k),
            err(m.tau_s, plant.tau_s),
            m.dead_time_s,
            err(m.dead_time_s, plant.dead_time_s),
            if est.dead_time_certain() {
                ""
            } else {
                ", said uncertain"
            },
            m.sensor_tau_s,
            err(m.dead_time_s + m.sensor_tau_s, lags),
            m.ambient_c,
            if split {
                String::new()
            } else {
                format!(" (corners {snr:.1} x the noise: the sum only)")
            }
        );
        assert!(err(m.gain_c_per_pct, k).abs() < 10.0, "{plant:?}: {m:?}");
        assert!(err(m.tau_s, plant.tau_s).abs() < 10.0, "{plant:?}: {m:?}");
        assert!(
            err(m.dead_time_s + m.sensor_tau_s, lags).abs() < 10.0,
            "{plant:?}: {m:?}"
        );
        assert!(
            (m.ambient_c - plant.ambient_c).abs() < 2.0,
            "{plant:?}: {m:?}"
        );
        // The dead time: within 10 % wherever the run claims it; where the run says it is
        // uncertain, its error within three of the standard errors it gives.
        let e_dead = err(m.dead_time_s, plant.dead_time_s).abs();
        if est.dead_time_certain() {
            assert!(e_dead < 10.0, "{plant:?}: {m:?} ± {se}");
        } else {
            assert!(
                (m.dead_time_s - plant.dead_time_s).abs() <= 3.0 * se,
                "{plant:?}: {m:?} ± {se}"
            );
        }
        let summary = est.model_summary().unwrap();
        assert!(summary.contains(&format!("dead time {:.2} ± ", m.dead_time_s)));
        assert_eq!(summary.contains("uncertain"), !est.dead_time_certain());
        assert!(e_dead < 10.0 || !est.dead_time_certain());
        if split {
            assert!(e_dead < 10.0, "{plant:?}: {m:?}");
            assert!(
                (m.sensor_tau_s - plant.sensor_tau_s).abs() < (0.2 * plant.sensor_tau_s).max(0.2),
                "{plant:?}: {m:?}"
            );
        }
    }
}

/// Ku comes from the power the line really delivered: a 100 % relay whose line `max_on_ms`
/// cuts after 1.5 s for a 1 s break delivers about 60 % while on, and the estimate is the
/// describing function of that power, not of the commanded relay: against the commanded
/// relay's value (`2·A·sin(π·D)/(π·a)` with A = 100 %), lower by about the share the line
/// delivered while on.
#[test]
fn ku_comes_from_the_power_the_line_delivered() {
    let mut p = params(heater(&plant()));
    p.max_on_ms = 1500;
    p.min_off_ms = Some(1000);
    let mut r = rig(p);
    // 40 °C needs about 17 % on average: within the cap.
    let g = Goal {
        target_c: 40.0,
        ..goal(100.0)
    };
    start(&mut r, g);
    let (_, o) = until_done(&mut r, 5000);
    assert_eq!(o.stop, Stop::Converged, "{o:?}");
    let est = o.estimate.unwrap();
    let share = est.delivered_on_pct / 100.0;
    assert!(share < 0.8, "{est:?}");
    let commanded = 2.0 * 100.0 * (std::f64::consts::PI * est.on_fraction).sin()
        / (std::f64::consts::PI * est.amplitude_c);
    println!("capped: {est:?}; commanded relay's Ku {commanded:.3}");
    assert!(
        (est.ku / commanded / share - 1.0).abs() < 0.2,
        "Ku {} against the commanded {commanded} at a delivered share {share}",
        est.ku
    );
}

/// The fast cartridge of the ROS tests (5 °C/s at full power, τ 20 s, 0.5 s of dead time
/// behind a 0.5 s sensor, ±0.05 °C; the PWM at 200 ms, readings at 20 Hz), tuned to 60 °C
/// from ambient at 40 seeds and start instants: every run identifies a model, within 10 % of
/// the plant's gain and time constant. (The approach's test for a curvature once compared its
/// fit with a straight line computed from sums that cancel: about one run in four then gave
/// no model.)
#[test]
fn a_fast_cartridge_gives_a_model_at_every_seed() {
    let plant = PlantParams {
        rate_c_per_s: 5.0,
        tau_s: 20.0,
        dead_time_s: 0.5,
        ambient_c: 20.0,
        noise_c: 0.05,
        sensor_tau_s: 0.5,
    };
    for seed in 0..40u64 {
        let mut h = heater(&plant);
        h.pid_kp = 20.0;
        h.pid_ki = 5.0;
        h.temp_min_c = 0.0;
        h.temp_max_c = 150.0;
        let mut p = params(h);
        p.period_ms = 200;
        let mut r = Rig::new(p, plant, seed);
        r.reading_every = 50_000_000;
        r.secs(1.0 + (seed % 7) as f64 * 0.13)
            .enable()
            .secs(0.25 + (seed % 5) as f64 * 0.05);
        let g = Goal {
            target_c: 60.0,
            amplitude_pct: 100.0,
            noise_band_c: 0.5,
        };
        r.act(|ch, now, emit| ch.start_autotune(now, 5, g, emit));
        let (_, o) = until_done(&mut r, 2000);
        assert_eq!(o.stop, Stop::Converged, "seed {seed}: {o:?}");
        let m = o.estimate.and_then(|e| e.model);
        let m = m.unwrap_or_else(|| panic!("seed {seed}: no model: {o:?}"));
        let k = plant.rate_c_per_s * plant.tau_s / 100.0;
        assert!(
            (m.gain_c_per_pct / k - 1.0).abs() <= 0.1 && (m.tau_s / plant.tau_s - 1.0).abs() <= 0.1,
            "seed {seed}: {m:?}"
        );
    }
}

/// The relay's extra cycles for the dead time on the slowest, noisiest heater of the sizing
/// range (plant 0: 0.3 °C/s, τ 600 s, dead time 0.5 s behind a 1 s sensor, ±0.2 °C), whose
/// agreeing cycles leave its dead time uncertain (33 % off at seed 3, see
/// [`a_run_identifies_the_heaters_model`]): with `autotune_extend_s` an hour, over five noise
/// seeds, the relay goes on until the dead time is told within 10 % (its standard error at
/// most 4 % of it), about 40 minutes; then the dead time, the gain and the time constant are
/// within 10 % of the plant's. The progress says why it goes on, and how far it has come.
#[test]
fn extra_cycles_tell_the_dead_time() {
    use crate::core::heater::autotune::{Phase, MAX_CYCLES};
    let plant = lagging(0);
    for seed in [1u64, 3, 5, 7, 9] {
        let started = std::time::Instant::now();
        let (r, o) = identify_within(plant, seed, 3600.0);
        assert_eq!(o.stop, Stop::Converged, "seed {seed}: {o:?}");
        let est = o.estimate.unwrap();
        let m = est.model.unwrap();
        let se = est.dead_time_se_s.unwrap();
        let x = est.extended.expect("the relay went on");
        let k = plant.rate_c_per_s * plant.tau_s / 100.0;
        let err = |a: f64, b: f64| (a / b - 1.0) * 100.0;
        println!(
            "seed {seed}: dead time {:.3} ± {se:.3} s ({:+.1} %), sensor {:.2} s, gain {:+.1} %, \
             tau {:+.1} %; {} more cycles, {:.0} s; {:.1} s to test",
            m.dead_time_s,
            err(m.dead_time_s, plant.dead_time_s),
            m.sensor_tau_s,
            err(m.gain_c_per_pct, k),
            err(m.tau_s, plant.tau_s),
            x.cycles,
            x.secs,
            started.elapsed().as_secs_f64()
        );
        assert!(est.dead_time_certain(), "seed {seed}: {est:?}");
        assert!(x.secs < 3600.0 && x.cycles > 50, "seed {seed}: {x:?}");
        assert!(err(m.dead_time_s, plant.dead_time_s).abs() < 10.0, "{m:?}");
        assert!(err(m.gain_c_per_pct, k).abs() < 10.0, "{m:?}");
        assert!(err(m.tau_s, plant.tau_s).abs() < 10.0, "{m:?}");
        assert!(
            (m.sensor_tau_s - plant.sensor_tau_s).abs() < 0.2 * plant.sensor_tau_s,
            "{m:?}"
        );
        let summary = est.model_summary().unwrap();
        assert!(!summary.contains("uncertain"), "{summary}");
        assert!(
            summary.contains(&format!("the relay went on {} more cycles", x.cycles)),
            "{summary}"
        );
        // The progress: the relay's phase, then the dead time's, its cycles counted on past
        // the agreeing ones, with the dead time so far, its standard error and the time.
        let progress: Vec<_> = reports(&r)
            .into_iter()
            .filter_map(|rep| match rep {
                Report::Progress(p) => Some(p),
                _ => None,
            })
            .collect();
        let first = progress
            .iter()
            .position(|p| p.phase == Phase::DeadTime)
            .expect("a dead_time phase");
        assert!(progress[..first].iter().all(|p| p.phase != Phase::DeadTime));
        if let Some(p) = progress[first..]
            .iter()
            .find(|p| p.dead_time.is_some_and(|d| d.extended_s >= 300.0))
        {
            println!("  {} cycles, {}", p.cycles, p.dead_time.unwrap());
        }
        let last = progress.last().unwrap();
        assert_eq!(last.phase, Phase::DeadTime);
        assert!(last.cycles as usize > MAX_CYCLES, "{last:?}");
        assert_eq!(o.progress.cycles, last.cycles);
        let d = last.dead_time.unwrap();
        assert!(
            d.se_s > 0.0 && d.extended_s > 0.0 && d.bound_s == 3600.0,
            "{d:?}"
        );
        assert!(progress[first..]
            .windows(2)
            .all(|w| w[0].cycles <= w[1].cycles && w[1].dead_time.is_some()));
    }
}

/// The bound holds: with `autotune_extend_s` 300 s, plant 0's relay goes on for 300 s (and
/// the last window's evaluation, a few readings), then the run gives its model, the dead time
/// told better than without the extra cycles but still uncertain, and says so and why.
#[test]
fn the_extra_cycles_end_at_their_bound_with_the_model_said_uncertain() {
    let plant = lagging(0);
    let (_, before) = identify_within(plant, 3, 0.0);
    let se_before = before.estimate.unwrap().dead_time_se_s.unwrap();
    assert_eq!(before.estimate.unwrap().extended, None);
    let (_, o) = identify_within(plant, 3, 300.0);
    assert_eq!(o.stop, Stop::Converged, "{o:?}");
    let est = o.estimate.unwrap();
    let m = est.model.expect("the model is given");
    let x = est.extended.unwrap();
    let se = est.dead_time_se_s.unwrap();
    println!(
        "bound 300 s: dead time {:.3} ± {se:.3} s (without: ± {se_before:.3}), {x:?}",
        m.dead_time_s
    );
    assert!(x.secs >= 300.0 && x.secs < 310.0, "{x:?}");
    assert_eq!(x.bound_s, 300.0);
    assert!(!est.dead_time_certain());
    assert!(se < se_before, "{se} against {se_before}");
    assert!(
        (m.dead_time_s - plant.dead_time_s).abs() <= 3.0 * se,
        "{m:?} ± {se}"
    );
    let k = plant.rate_c_per_s * plant.tau_s / 100.0;
    assert!((m.gain_c_per_pct / k - 1.0).abs() < 0.1, "{m:?}");
    let summary = est.model_summary().unwrap();
    assert!(
        summary.contains("the dead time is uncertain")
            && summary.contains(
                "autotune_extend_s 300 s ended the relay before the dead time \
                                 was told within 10 %"
            ),
        "{summary}"
    );
}

/// A run in its extra cycles for plant 0's dead time (`autotune_extend_s` an hour), a minute
/// into them.
fn in_extra_cycles() -> Rig {
    use crate::core::heater::autotune::Phase;
    let plant = lagging(0);
    let mut h = heater(&plant);
    h.autotune_extend_s = 3600.0;
    let mut r = Rig::new(params(h), plant, 3);
    r.secs(1.0).enable().secs(1.0);
    let g = Goal {
        target_c: plant.ambient_c + 0.4 * plant.rate_c_per_s * plant.tau_s,
        amplitude_pct: 100.0,
        noise_band_c: 0.22,
    };
    r.act(|ch, now, emit| ch.start_autotune(now, 5, g, emit));
    for _ in 0..3000 {
        r.secs(1.0);
        let extra = reports(&r)
            .iter()
            .any(|rep| matches!(rep, Report::Progress(p) if p.phase == Phase::DeadTime));
        if extra {
            r.secs(60.0);
            assert!(outcome(&r).is_none(), "{:?}", outcome(&r));
            return r;
        }
    }
    panic!("no extra cycles: {:?}", reports(&r).last());
}

/// In the extra cycles, a cancel ends the run at once with the line off and no gains, and the
/// heater checks stay armed: a NaN reading, a heater that falls off (no_rise), a silent sensor
/// each end it with their fault, the line off.
#[test]
fn the_extra_cycles_stop_at_once_and_keep_every_check() {
    let ended = |r: &mut Rig, expect: &dyn Fn(&Stop) -> bool| {
        let (t, o) = outcome(r).expect("the run ended");
        assert!(expect(&o.stop), "{o:?}");
        assert_eq!(o.gains, None);
        assert_eq!(r.ch.status(r.now).duty_commanded, 0.0);
        r.secs(60.0);
        assert!(r.no_rise_after(t), "the line rose after the end");
        assert!(r.ch.autotune_target().is_none());
        t
    };
    let mut r = in_extra_cycles();
    let at = r.now;
    r.act(|ch, now, emit| ch.cancel_autotune(now, 5, emit));
    let t = ended(&mut r, &|s| *s == Stop::Canceled);
    assert_eq!(t, at, "the cancel ends the run at once");

    let mut r = in_extra_cycles();
    r.act(|ch, now, emit| ch.feedback(now, f64::NAN, emit));
    ended(&mut r, &|s| {
        matches!(s, Stop::HeaterFault(HeaterFault::OutOfRange { .. }))
    });

    // The heater falls off: no_rise (the relay at full power, the reading not rising).
    let mut r = in_extra_cycles();
    r.plant.set_fault(PlantFault::HeaterDisconnected);
    r.secs(60.0);
    ended(&mut r, &|s| {
        matches!(s, Stop::HeaterFault(HeaterFault::NoRise { .. }))
    });

    let mut r = in_extra_cycles();
    r.plant.set_fault(PlantFault::SensorSilent);
    r.secs(10.0);
    ended(&mut r, &|s| {
        matches!(s, Stop::HeaterFault(HeaterFault::SensorTimeout { .. }))
    });
}
