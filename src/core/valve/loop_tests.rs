//! The valve's own loop on the mixing plant, in virtual time: a day of supply steps against a
//! continuous PID on an ideal valve (the yardstick for the error) and against the same PID
//! sending positions every sample (the yardstick for the motor's starts), and the return from
//! manual mode. The valve's edges drive a true actuator ([`TrueValve`]) whose stem sets the
//! plant; the sensor reads the plant with its noise once a second.
//!
//! Run with `--nocapture` to see the figures.

use super::mixing::{Mixing, MixingParams};
use super::truth::{TrueValve, TruthParams};
use super::*;
use crate::core::heater::pid::{Gains, Pid};

const MS: Nanos = NS_PER_MS;
const S: Nanos = 1_000 * MS;
const H: Nanos = 3_600 * S;
/// The plant and the valve advance in ticks of this.
const TICK: Nanos = 100 * MS;
/// The sensor publishes, and the loops sample, once a second.
const SAMPLE: Nanos = S;
/// The mixed water's setpoint, °C.
const SETPOINT: f64 = 45.0;
/// The actuator's travel time, both ways, s.
const TRAVEL_S: u64 = 60;
const DEADBAND_PCT: f64 = 1.0;
/// The sensor's noise, ±K.
const NOISE_C: f64 = 0.5;
/// Half an actuator's common duty class for modulating service (1 200 starts an hour).
const BUDGET_PER_H: u64 = 600;

/// The gains for the plant (gain 0.55 K/%, τ 120 s, dead time 20 s) by the SIMC rule with a
/// closed-loop time constant of one dead time: kp = τ / (K · 2L), Ti = τ.
fn gains() -> Gains {
    Gains {
        kp: 5.0,
        ki: 5.0 / 120.0,
        kd: 0.0,
        d_filter_s: 0.0,
    }
}

/// The supplies over the day: (from, hot °C, cold °C).
const SUPPLY: [(Nanos, f64, f64); 6] = [
    (0, 70.0, 15.0),
    (3 * H, 60.0, 15.0),
    (8 * H, 75.0, 15.0),
    (12 * H, 75.0, 22.0),
    (17 * H, 65.0, 22.0),
    (21 * H, 65.0, 12.0),
];

fn supply_at(m: &mut Mixing, t: Nanos) {
    let (_, hot, cold) = SUPPLY
        .iter()
        .rev()
        .find(|(from, ..)| *from <= t)
        .expect("t ≥ 0");
    m.set_hot(*hot);
    m.set_cold(*cold);
}

/// The plant: 120 s, 20 s, ±`noise_c` K; settled at 50 % (42.5 °C), the seed fixed.
fn plant(noise_c: f64) -> Mixing {
    let p = MixingParams {
        noise_c,
        ..MixingParams::default()
    };
    assert_eq!((p.tau_s, p.dead_time_s), (120.0, 20.0));
    Mixing::new(p, 50.0, 0, 42)
}

fn truth() -> TrueValve {
    let travel = (TRAVEL_S * S) as f64;
    TrueValve::new(
        TruthParams {
            travel_ns: [travel, travel],
            lag_ns: 0.0,
            coast_ns: 0.0,
            backlash_pct: 0.0,
            switch_at_pct: 0.0,
        },
        50.0,
    )
}

fn valve_params(control: Control, budget: u64) -> ValveParams {
    ValveParams {
        travel_open_ms: TRAVEL_S * 1_000,
        travel_close_ms: TRAVEL_S * 1_000,
        deadband_pct: DEADBAND_PCT,
        min_pulse_ms: 300,
        reversal_pause_ms: 500,
        start_lag_ms: 0,
        backlash_pct: 0.0,
        end_overrun_pct: 10.0,
        reference_at_start: ReferenceAtStart::None,
        recalibrate_after_s: 0,
        exercise_every_h: 0,
        max_uncertainty_pct: 100.0,
        command_timeout_ms: 0,
        on_timeout: OnTimeout::Stop,
        feedback_tolerance_pct: 1.0,
        max_starts_per_h: budget,
        control: ControlParams {
            control,
            process: true,
            output: LoopOutput::Auto,
            pid_kp: gains().kp,
            pid_ki: gains().ki,
            pid_sample_ms: SAMPLE / MS,
            ..ControlParams::default()
        },
    }
}

/// A valve, its true actuator and the plant behind it, in virtual time.
struct Plant {
    v: Valve,
    truth: TrueValve,
    mix: Mixing,
    now: Nanos,
    /// The rises written, ns.
    starts: Vec<Nanos>,
    /// ∫|setpoint − true temperature| dt, K·s.
    iae: f64,
}

impl Plant {
    fn new(p: ValveParams, noise_c: f64) -> Plant {
        Plant {
            v: Valve::new(p.validate().expect("valid"), 0),
            truth: truth(),
            mix: plant(noise_c),
            now: 0,
            starts: Vec::new(),
            iae: 0.0,
        }
    }

    /// Runs `f` at the current time and writes its edges to the true actuator.
    fn act<R>(&mut self, f: impl FnOnce(&mut Valve, Nanos, &mut dyn FnMut(ValveEvent)) -> R) -> R {
        let mut out = Vec::new();
        let now = self.now;
        let r = f(&mut self.v, now, &mut |e| out.push(e));
        for ValveEvent::Edge { dir, level, at } in out {
            let at = at.max(now);
            self.v.edge_written(dir, level, at);
            self.truth.edge(dir.index(), level.is_high(), at as i64);
            if level.is_high() {
                self.starts.push(at);
            }
        }
        r
    }

    /// Polls every deadline up to `t`.
    fn run_to(&mut self, t: Nanos) {
        while let Some(at) = self.v.poll_at().filter(|&at| at <= t) {
            self.now = self.now.max(at);
            self.act(|v, now, e| v.poll(now, e));
        }
        self.now = t;
    }

    fn position(&self) -> f64 {
        self.truth.position(self.now as i64)
    }

    /// One tick to `t`: the supplies, the plant on the true position, the error; a reading
    /// (and the loop's sample) every second, `each_sample` after it.
    fn tick(&mut self, t: Nanos, each_sample: &mut dyn FnMut(&mut Plant, f64)) {
        self.run_to(t);
        supply_at(&mut self.mix, t);
        let x = self.position();
        self.mix.advance(t, x);
        self.iae += (SETPOINT - self.mix.temperature()).abs() * TICK as f64 / 1e9;
        if t.is_multiple_of(SAMPLE) {
            let r = self.mix.reading();
            self.v.process_value(t, r, Some(0)).expect("finite");
            each_sample(self, r);
            // The loop's sample due now acts on this reading.
            self.run_to(t);
        }
    }

    /// The most starts any hour holds (windows starting at each start).
    fn most_starts_in_an_hour(&self) -> usize {
        let mut most = 0;
        for (i, &s) in self.starts.iter().enumerate() {
            let n = self.starts[i..].iter().take_while(|&&x| x < s + H).count();
            most = most.max(n);
        }
        most
    }
}

/// The continuous PID on an ideal valve (the output is the position, at once), same plant,
/// same readings: the day's IAE, K·s.
fn ideal_iae(until: Nanos) -> f64 {
    let mut mix = plant(NOISE_C);
    let mut pid = Pid::new(gains());
    pid.start_from(50.0);
    let mut x = 50.0;
    let mut iae = 0.0;
    let mut t = 0;
    while t < until {
        t += TICK;
        supply_at(&mut mix, t);
        mix.advance(t, x);
        iae += (SETPOINT - mix.temperature()).abs() * TICK as f64 / 1e9;
        if t.is_multiple_of(SAMPLE) {
            let r = mix.reading();
            x = pid
                .step(SETPOINT, r, SAMPLE as f64 / 1e9, 0.0, 100.0)
                .output;
        }
    }
    iae
}

/// The valve's loop in step mode (no position feedback) with a budget, for `until`.
fn own_loop(until: Nanos, noise_c: f64) -> Plant {
    let mut p = Plant::new(valve_params(Control::Pid, BUDGET_PER_H), noise_c);
    p.act(|v, now, e| v.setpoint(now, SETPOINT, e))
        .expect("pid");
    let mut t = 0;
    while t < until {
        t += TICK;
        p.tick(t, &mut |_, _| {});
    }
    p
}

/// The same PID outside the valve, sending its output as a position command every sample to
/// a valve with the same dead band and minimum pulse and no budget.
fn positions_every_sample(until: Nanos) -> Plant {
    let mut p = Plant::new(valve_params(Control::Position, 0), NOISE_C);
    let mut pid = Pid::new(gains());
    pid.start_from(50.0);
    let mut t = 0;
    while t < until {
        t += TICK;
        p.tick(t, &mut |p, r| {
            let out = pid
                .step(SETPOINT, r, SAMPLE as f64 / 1e9, 0.0, 100.0)
                .output;
            p.act(|v, now, e| v.command(now, out, e)).expect("finite");
        });
    }
    p
}

/// A day of supply steps: the valve's loop, without position feedback and within a budget of
/// 600 starts an hour, holds the mixed water within 10 % of the error a continuous PID on an
/// ideal valve leaves, never starts the motor more than the budget in any hour, and starts it
/// at most half as often as the same PID sending positions every sample.
#[test]
fn a_day_on_the_mixing_plant_holds_the_error_and_spares_the_motor() {
    let day = 24 * H;
    let ideal = ideal_iae(day);
    let own = own_loop(day, NOISE_C);
    let every = positions_every_sample(day);
    let hours = day as f64 / H as f64;
    let own_rate = own.starts.len() as f64 / hours;
    let every_rate = every.starts.len() as f64 / hours;
    println!(
        "24 h mixing loop (tau 120 s, dead time 20 s, ±0.5 K noise, {} supply steps):",
        SUPPLY.len() - 1
    );
    println!(
        "  IAE: ideal valve, continuous PID {:.0} K·s; the valve's loop (step mode, budget \
         {}/h) {:.0} K·s ({:+.1} %); positions every sample {:.0} K·s",
        ideal,
        BUDGET_PER_H,
        own.iae,
        (own.iae / ideal - 1.0) * 100.0,
        every.iae
    );
    println!(
        "  starts: the valve's loop {} ({own_rate:.0}/h, most in an hour {}); positions every \
         sample {} ({every_rate:.0}/h, most in an hour {})",
        own.starts.len(),
        own.most_starts_in_an_hour(),
        every.starts.len(),
        every.most_starts_in_an_hour()
    );
    assert_eq!(own.v.status(own.now).starts, own.starts.len() as u64);
    assert!(
        own.iae <= 1.10 * ideal,
        "IAE {:.0} K·s against {ideal:.0} K·s",
        own.iae
    );
    assert!(
        own.most_starts_in_an_hour() as u64 <= BUDGET_PER_H,
        "{} starts within an hour",
        own.most_starts_in_an_hour()
    );
    assert!(
        2 * own.starts.len() <= every.starts.len(),
        "{} starts against {} sending positions",
        own.starts.len(),
        every.starts.len()
    );
    // The loop did its work: the mixed water is at the setpoint at the end of the day.
    assert!((own.mix.temperature() - SETPOINT).abs() < 1.0);
}

/// Manual mode and back, on a sensor without noise (with it the loop's every sample may move
/// the valve by a dead band, transfer or not): an operator jogs the valve closed for three seconds (5 % of its
/// travel) and stops it there for five minutes; back in automatic the loop starts from where the
/// valve stands, and the valve moves by less than the dead band over the next five samples,
/// although the water is now about 2.75 K below the setpoint.
#[test]
fn manual_to_auto_moves_the_valve_less_than_the_dead_band() {
    let mut p = own_loop(H, 0.0);
    let held = p.position();
    p.act(|v, now, e| v.manual(now, Manual::Close, e))
        .expect("manual");
    // The state says so at once, not a sample later.
    assert_eq!(p.v.status(p.now).control.state, LoopState::Manual);
    p.run_to(p.now + 3 * S);
    p.act(|v, now, e| v.manual(now, Manual::Stop, e))
        .expect("manual");
    let until = p.now + 5 * 60 * S;
    let mut t = p.now;
    while t < until {
        t += TICK;
        p.tick(t, &mut |_, _| {});
    }
    assert_eq!(p.v.status(p.now).control.state, LoopState::Manual);
    assert_eq!(p.v.status(p.now).control.manual, Some(Manual::Stop));
    let before = p.position();
    assert!(
        (held - before - 5.0).abs() < 0.5,
        "the jog closed the valve {held:.2} → {before:.2} %"
    );
    p.act(|v, now, e| v.manual(now, Manual::Auto, e))
        .expect("auto");
    assert_eq!(p.v.status(p.now).control.state, LoopState::Running);
    let off = SETPOINT - p.mix.temperature();
    assert!(off > 2.0, "the water is {off:.2} K below the setpoint");
    let until = p.now + 5 * SAMPLE;
    let mut t = p.now;
    let mut most = 0.0f64;
    while t < until {
        t += TICK;
        p.tick(t, &mut |_, _| {});
        most = most.max((p.position() - before).abs());
    }
    println!(
        "manual → auto: valve at {before:.2} % ({off:.2} K below the setpoint), moved {most:.3} % \
         in the first 5 s of automatic (dead band {DEADBAND_PCT} %)"
    );
    assert_eq!(p.v.status(p.now).control.state, LoopState::Running);
    assert!(
        most < DEADBAND_PCT,
        "the return to automatic moved the valve {most:.3} %"
    );
    // And the loop brings the water back.
    let until = p.now + 30 * 60 * S;
    let mut t = p.now;
    while t < until {
        t += TICK;
        p.tick(t, &mut |_, _| {});
    }
    assert!((p.mix.temperature() - SETPOINT).abs() < 1.0);
}

/// What the valve reports of its loop is true when it is taken: manual mode and its end change
/// the loop's state in the same call, the hold comes at the first sample after
/// `process_timeout_ms` without a fresh reading, a command timeout shows at once, and each
/// refused input is counted under its kind.
#[test]
fn the_loop_state_is_reported_as_it_changes_and_refusals_are_counted_by_kind() {
    let mut p = Plant::new(valve_params(Control::Pid, 0), 0.0);
    p.act(|v, now, e| v.setpoint(now, SETPOINT, e))
        .expect("setpoint");
    let mut t = 0;
    while t < 10 * S {
        t += TICK;
        p.tick(t, &mut |_, _| {});
    }
    let s = p.v.status(p.now);
    assert_eq!(
        (s.control.state, s.control.manual, s.control.process_age),
        (LoopState::Running, None, Some(0))
    );
    p.act(|v, now, e| v.manual(now, Manual::Position(30.0), e))
        .expect("manual");
    let s = p.v.status(p.now);
    assert_eq!(
        (s.control.state, s.control.manual),
        (LoopState::Manual, Some(Manual::Position(30.0)))
    );
    p.act(|v, now, e| v.manual(now, Manual::Auto, e))
        .expect("auto");
    let s = p.v.status(p.now);
    assert_eq!(
        (s.control.state, s.control.manual),
        (LoopState::Running, None)
    );

    p.act(|v, now, e| v.setpoint(now, f64::NAN, e))
        .expect_err("NaN setpoint");
    p.act(|v, now, e| v.setpoint(now, 2e9, e))
        .expect_err("setpoint beyond 1e9");
    p.v.process_value(p.now, f64::INFINITY, None)
        .expect_err("infinite reading");
    p.act(|v, now, e| v.command(now, 40.0, e))
        .expect_err("a position under pid");
    let bad = "wide open".parse::<Manual>().expect_err("no such word");
    p.v.manual_refused(bad).expect_err("counted");
    let s = p.v.status(p.now);
    assert_eq!(
        s.refused,
        Refused {
            position: 1,
            setpoint: 2,
            process_value: 1,
            manual: 1
        }
    );
    assert_eq!(s.refused.total(), 5);
    assert_eq!(s.last_refusal, Some(ValveRefusal::BadManual(bad)));
    assert_eq!(s.control.setpoint, SETPOINT, "the setpoint in force stays");

    // The readings stop: running until the timeout, holding at the first sample after it.
    let last = p.now;
    let timeout = control::DEFAULT_PROCESS_TIMEOUT_MS * MS;
    p.run_to(last + timeout - MS);
    assert_eq!(p.v.status(p.now).control.state, LoopState::Running);
    p.run_to(last + timeout + SAMPLE);
    let s = p.v.status(p.now);
    assert_eq!(s.control.state, LoopState::Holding);
    assert_eq!(s.control.process_age, Some(timeout + SAMPLE));
    assert_eq!(s.control.timeout, timeout);

    // A command timeout shows in the same call that acts on it.
    let mut q = valve_params(Control::Pid, 0);
    q.command_timeout_ms = 5_000;
    let mut p = Plant::new(q, 0.0);
    p.act(|v, now, e| v.setpoint(now, SETPOINT, e))
        .expect("setpoint");
    p.run_to(5 * S - MS);
    assert_ne!(p.v.status(p.now).control.state, LoopState::TimedOut);
    p.run_to(5 * S);
    let s = p.v.status(p.now);
    assert!(s.timed_out);
    assert_eq!(s.control.state, LoopState::TimedOut);
}
