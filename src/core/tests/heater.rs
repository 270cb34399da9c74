//! The heater loop in virtual time: a channel under `pid` driving a first-order-plus-dead-time
//! plant through its real edges, the plant's sensor read at a fixed rate. The PID's behaviour
//! in the channel (bumpless switches, limits), then the heater checks against healthy and
//! broken plants, as examples and as properties.

use crate::core::heater::{
    Control, HeaterFault, HeaterParams, Plant, PlantFault, PlantParams, ResetRefusal,
};
use crate::core::{Channel, ChannelParams, Event, Level, Nanos, NS_PER_MS};
use proptest::prelude::*;

const S: Nanos = 1_000_000_000;

/// A channel, its plant and the sensor's reading clock, run together in virtual time.
pub(super) struct Rig {
    pub(super) ch: Channel,
    pub(super) plant: Plant,
    pub(super) now: Nanos,
    pub(super) next_reading: Nanos,
    pub(super) reading_every: Nanos,
    /// Every event except edges and plans, with its instant.
    pub(super) notes: Vec<(Nanos, Event)>,
    /// Line changes: (instant, level).
    pub(super) edges: Vec<(Nanos, Level)>,
    /// The highest and lowest true temperature after `watch_from`.
    pub(super) watch_from: Nanos,
    pub(super) band: (f64, f64),
}

pub(super) fn heater(plant: &PlantParams) -> HeaterParams {
    // SIMC tuning (Skogestad) with tc = dead time: kp = tau / (K·2L), TI = min(tau, 8L),
    // K = rate·tau / 100 °C per %.
    let k = plant.rate_c_per_s * plant.tau_s / 100.0;
    let l = plant.dead_time_s.max(0.5);
    let kp = plant.tau_s / (k * 2.0 * l);
    let ti = plant.tau_s.min(8.0 * l);
    HeaterParams {
        feedback: true,
        control: Control::Pid,
        pid_kp: kp,
        pid_ki: kp / ti,
        pid_kd: 0.0,
        temp_min_c: -20.0,
        temp_max_c: 1000.0,
        ..HeaterParams::default()
    }
}

pub(super) fn params(h: HeaterParams) -> ChannelParams {
    ChannelParams {
        period_ms: 1000,
        heater: h,
        ..ChannelParams::default()
    }
}

impl Rig {
    pub(super) fn new(p: ChannelParams, plant: PlantParams, seed: u64) -> Rig {
        Rig {
            ch: Channel::new(p.validate().expect("valid test parameters"), 0),
            plant: Plant::new(plant, 0, seed),
            now: 0,
            next_reading: 0,
            reading_every: 250 * NS_PER_MS,
            notes: Vec::new(),
            edges: Vec::new(),
            watch_from: Nanos::MAX,
            band: (f64::INFINITY, f64::NEG_INFINITY),
        }
    }

    pub(super) fn act(&mut self, f: impl FnOnce(&mut Channel, Nanos, &mut dyn FnMut(Event))) {
        let (now, plant, notes, edges) =
            (self.now, &mut self.plant, &mut self.notes, &mut self.edges);
        f(&mut self.ch, now, &mut |e| match e {
            Event::Edge { at, level } => {
                plant.line(now, level.is_high());
                edges.push((at, level));
            }
            Event::Plan(_) => {}
            other => notes.push((now, other)),
        });
    }

    /// Runs every deadline and reading up to `t`.
    pub(super) fn run_to(&mut self, t: Nanos) -> &mut Self {
        loop {
            let due = self.ch.poll_at().unwrap_or(Nanos::MAX);
            let next = due.min(self.next_reading);
            if next > t {
                break;
            }
            self.now = next;
            if next == self.next_reading {
                self.next_reading += self.reading_every;
                if let Some(c) = self.plant.reading(next) {
                    self.act(|ch, now, emit| ch.feedback(now, c, emit));
                }
                if next >= self.watch_from {
                    let temp = self.plant.temperature();
                    self.band = (self.band.0.min(temp), self.band.1.max(temp));
                }
            } else {
                self.act(|ch, now, emit| ch.poll(now, emit));
            }
        }
        self.now = t;
        self.plant.advance(t);
        self
    }

    pub(super) fn secs(&mut self, s: f64) -> &mut Self {
        self.run_to(self.now + (s * 1e9) as Nanos)
    }

    pub(super) fn enable(&mut self) -> &mut Self {
        self.act(|ch, now, emit| ch.set_enable(now, true, emit));
        self
    }

    pub(super) fn setpoint(&mut self, c: f64) -> &mut Self {
        self.act(|ch, now, emit| ch.set_setpoint(now, c, emit));
        self
    }

    pub(super) fn faults(&self) -> Vec<(Nanos, HeaterFault)> {
        self.notes
            .iter()
            .filter_map(|(t, e)| match e {
                Event::HeaterFault(f) => Some((*t, *f)),
                _ => None,
            })
            .collect()
    }

    pub(super) fn first_fault(&self) -> Option<(Nanos, HeaterFault)> {
        self.faults().first().copied()
    }

    pub(super) fn reset(&mut self) -> Result<(), ResetRefusal> {
        self.act(|ch, now, emit| ch.reset_heater_fault(now, 7, emit));
        match self.notes.last() {
            Some((_, Event::FaultReset { ticket: 7, result })) => *result,
            other => panic!("no answer to the reset: {other:?}"),
        }
    }

    /// No rise of the line after `t`.
    pub(super) fn no_rise_after(&self, t: Nanos) -> bool {
        !self
            .edges
            .iter()
            .any(|(at, l)| *at > t && *l == Level::High)
    }
}

#[test]
fn the_loop_holds_its_setpoint_within_one_degree() {
    let plant = PlantParams {
        noise_c: 0.05,
        ..PlantParams::default()
    };
    let mut r = Rig::new(params(heater(&plant)), plant, 1);
    r.setpoint(80.0).enable().secs(300.0);
    r.watch_from = r.now;
    r.secs(300.0);
    let (lo, hi) = r.band;
    assert!(lo > 79.0 && hi < 81.0, "settled between {lo} and {hi}");
    assert!(r.faults().is_empty(), "{:?}", r.faults());
    let s = r.ch.status(r.now).heater;
    assert_eq!(s.setpoint, Some(80.0));
    // At 80 °C the plant needs (80 − 20) / 120 = 50 % on average: the integral carries it.
    assert!((s.terms.output - 50.0).abs() < 10.0, "{s:?}");
    assert!((s.terms.i - 50.0).abs() < 10.0, "{s:?}");
}

#[test]
fn duty_and_setpoint_are_refused_in_the_wrong_mode() {
    let plant = PlantParams::default();
    let mut r = Rig::new(params(heater(&plant)), plant, 1);
    r.act(|ch, now, emit| ch.command(now, crate::core::Command::Percent(50.0), emit));
    assert!(matches!(
        r.notes.last(),
        Some((
            _,
            Event::Refused(crate::core::heater::Refusal::DutyUnderPid)
        ))
    ));
    for bad in [f64::NAN, f64::INFINITY, 2000.0, -50.0] {
        r.setpoint(bad);
        assert!(
            matches!(r.notes.last(), Some((_, Event::Refused(_)))),
            "{bad}"
        );
    }
    assert_eq!(r.ch.status(0).heater.setpoint, None);
    let mut open = HeaterParams {
        control: Control::Open,
        ..heater(&plant)
    };
    open.feedback = true;
    let mut r = Rig::new(params(open), plant, 1);
    r.setpoint(50.0);
    assert!(matches!(
        r.notes.last(),
        Some((
            _,
            Event::Refused(crate::core::heater::Refusal::SetpointUnderOpen)
        ))
    ));
}

#[test]
fn open_to_pid_and_back_is_bumpless() {
    let plant = PlantParams::default();
    let pid = heater(&plant);
    let open = HeaterParams {
        control: Control::Open,
        ..pid
    };
    let mut r = Rig::new(params(open), plant, 1);
    r.act(|ch, now, emit| ch.command(now, crate::core::Command::Percent(40.0), emit));
    r.enable().secs(200.0);
    let temp = r.plant.temperature();
    // Switch to pid: the duty in force stays until a setpoint, and the first sample with the
    // setpoint at the current temperature gives the same duty.
    let cfg = params(pid).validate().unwrap();
    r.act(|ch, now, emit| ch.set_config(now, cfg, emit));
    r.secs(2.0);
    assert_eq!(r.ch.status(r.now).duty_commanded, 0.4);
    r.setpoint(temp).secs(1.0);
    let d = r.ch.status(r.now).duty_commanded * 100.0;
    assert!((d - 40.0).abs() < 3.0, "duty jumped to {d} %");
    // And back to open: open loop heats on commands only, 0 % until the first one.
    let cfg = params(open).validate().unwrap();
    r.act(|ch, now, emit| ch.set_config(now, cfg, emit));
    r.secs(5.0);
    assert_eq!(r.ch.status(r.now).duty_commanded, 0.0);
    let t = r.now;
    r.secs(3.0);
    assert!(r.no_rise_after(t), "no open-loop heating without a command");
    r.act(|ch, now, emit| ch.command(now, crate::core::Command::Percent(30.0), emit));
    r.secs(3.0);
    assert!(!r.no_rise_after(t), "a command runs again");
}

#[test]
fn a_gain_change_under_pid_does_not_jump_the_duty() {
    let plant = PlantParams::default();
    let h = heater(&plant);
    let mut r = Rig::new(params(h), plant, 1);
    r.setpoint(80.0).enable().secs(400.0);
    let before = r.ch.status(r.now).heater.terms.output;
    let stronger = HeaterParams {
        pid_kp: h.pid_kp * 3.0,
        pid_ki: h.pid_ki * 2.0,
        ..h
    };
    let cfg = params(stronger).validate().unwrap();
    r.act(|ch, now, emit| ch.set_config(now, cfg, emit));
    r.secs(1.0);
    let after = r.ch.status(r.now).heater.terms.output;
    assert!((after - before).abs() < 5.0, "{before} -> {after}");
}

#[test]
fn the_integral_stays_within_max_duty() {
    let plant = PlantParams::default();
    let mut p = params(heater(&plant));
    p.max_duty_pct = 30.0;
    let mut r = Rig::new(p, plant, 1);
    // 30 % gives at most 56 °C: 150 °C is never reached, the output sits at 30 %.
    r.setpoint(150.0).enable().secs(120.0);
    let t = r.ch.status(r.now).heater.terms;
    assert_eq!(t.output, 30.0);
    assert!(t.i <= 30.0, "{t:?}");
    // A setpoint below the temperature: the output leaves the limit at the next sample.
    r.setpoint(25.0).secs(1.0);
    assert_eq!(r.ch.status(r.now).heater.terms.output, 0.0);
}

#[test]
fn out_of_range_and_nan_latch_with_the_line_off_at_once() {
    let plant = PlantParams::default();
    let mut h = heater(&plant);
    h.temp_max_c = 100.0;
    let mut r = Rig::new(params(h), plant, 1);
    r.setpoint(85.0).enable().secs(20.0);
    assert_eq!(r.ch.level(), Level::High);
    let now = r.now;
    r.act(|ch, now, emit| ch.feedback(now, f64::NAN, emit));
    assert_eq!(r.ch.level(), Level::Low, "off at once");
    let (at, f) = r.first_fault().unwrap();
    assert_eq!(at, now);
    assert_eq!(f.check(), "temperature_out_of_range");
    assert!(r.ch.heater_fault().is_some());
    // The NaN lasts: refused. The next (good) reading clears the condition.
    assert!(matches!(r.reset(), Err(ResetRefusal::Lasts(_))));
    r.secs(5.0);
    assert!(r.no_rise_after(now));
    // Enable while latched: taken, no rise.
    r.enable().secs(5.0);
    assert!(r.no_rise_after(now));
    assert_eq!(r.reset(), Ok(()));
    assert!(
        !r.ch.enabled(),
        "disabled after a reset until the next enable"
    );
    r.secs(3.0);
    assert!(r.no_rise_after(now));
    r.enable().secs(3.0);
    assert!(!r.no_rise_after(now));
    assert_eq!(r.reset(), Err(ResetRefusal::NoFault));
}

#[test]
fn a_silent_sensor_latches_sensor_timeout() {
    let plant = PlantParams::default();
    let mut h = heater(&plant);
    h.feedback_timeout_ms = 2000;
    let mut r = Rig::new(params(h), plant, 1);
    r.setpoint(60.0).enable().secs(10.0);
    assert!(r.faults().is_empty());
    r.plant.set_fault(PlantFault::SensorSilent);
    let silent = r.now;
    r.secs(5.0);
    let (at, f) = r.first_fault().expect("sensor_timeout");
    assert_eq!(f.check(), "sensor_timeout");
    // The last reading came at most one reading interval before the silence.
    assert!(
        at <= silent + 2 * S && at + 250 * NS_PER_MS >= silent + 2 * S,
        "{at}"
    );
    assert_eq!(r.ch.level(), Level::Low);
    assert!(matches!(r.reset(), Err(ResetRefusal::Lasts(_))));
    r.plant.set_fault(PlantFault::None);
    r.secs(1.0);
    assert_eq!(r.reset(), Ok(()));
}

#[test]
fn enabling_with_a_stale_sensor_latches_at_once() {
    let plant = PlantParams::default();
    let mut h = heater(&plant);
    h.feedback_timeout_ms = 1000;
    let mut r = Rig::new(params(h), plant, 1);
    r.plant.set_fault(PlantFault::SensorSilent);
    r.secs(3.0).setpoint(50.0).enable();
    assert_eq!(r.first_fault().map(|f| f.1.check()), Some("sensor_timeout"));
    assert!(r.edges.is_empty(), "the line never rose");
}

/// What a sizing rule allows: plants, setpoints and changes for which the checks must stay
/// quiet (docs/heater.md, "Sizing the checks").
fn arb_plant() -> impl Strategy<Value = PlantParams> {
    (
        0.5f64..3.0,
        30.0f64..200.0,
        0.5f64..3.0,
        15.0f64..25.0,
        0.0f64..0.2,
    )
        .prop_map(|(rate, tau, dead, ambient, noise)| PlantParams {
            rate_c_per_s: rate,
            tau_s: tau,
            dead_time_s: dead,
            ambient_c: ambient,
            noise_c: noise,
            sensor_tau_s: 0.0,
        })
}

/// Setpoints as fractions of the plant's full-power rise above ambient, at most 60 %.
fn arb_setpoints() -> impl Strategy<Value = Vec<(f64, f64)>> {
    prop::collection::vec((0.1f64..0.6, 30.0f64..200.0), 1..4)
}

/// The stuck-on sizing: a healthy plant keeps rising for its dead time after the line goes
/// off, at most at its full-power rate, and the noise adds twice its peak.
fn stuck_rise(plant: &PlantParams) -> f64 {
    1.5 * (plant.rate_c_per_s * plant.dead_time_s + 2.0 * plant.noise_c) + 0.5
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    /// `not_heating` and `stuck_on` never trip while a healthy plant is heated to setpoints
    /// within the sizing, through setpoint changes up and down.
    #[test]
    fn healthy_heating_never_trips(plant in arb_plant(), sps in arb_setpoints(), seed in 1u64..1000) {
        let mut h = heater(&plant);
        h.stuck_on_rise_c = stuck_rise(&plant);
        h.stuck_on_time_s = 10.0;
        h.feedback_timeout_ms = 1000;
        let mut r = Rig::new(params(h), plant, seed);
        r.enable();
        for (fraction, hold_s) in sps {
            let sp = plant.ambient_c + fraction * plant.rate_c_per_s * plant.tau_s;
            r.setpoint(sp).secs(hold_s);
            prop_assert!(r.faults().is_empty(), "{:?} at setpoint {sp}, {:.1} °C", r.faults(), r.plant.temperature());
        }
    }

    /// A heater that comes loose trips within `not_heating`'s bound (a response check may be
    /// first):
    /// once the reading lies `m` below setpoint − hysteresis and falls (one dead time after
    /// the disconnection at the latest, as the plant then only cools), a running approach
    /// ends within `runaway_gain_time_s` (it cannot gain), and each tick after adds at least
    /// `m` to the error: `gain_time + ceil(max_error / m) + 2` ticks.
    #[test]
    fn a_disconnected_heater_always_trips_not_heating(plant in arb_plant(), fraction in 0.2f64..0.6, after_s in 0.0f64..200.0) {
        let plant = PlantParams { noise_c: 0.0, ..plant };
        let h = heater(&plant);
        let mut r = Rig::new(params(h), plant, 1);
        let sp = plant.ambient_c + fraction * plant.rate_c_per_s * plant.tau_s;
        // A setpoint the cold heater is below the band of (else there is nothing to see).
        prop_assume!(sp - h.runaway_hysteresis_c - 2.0 > plant.ambient_c);
        r.setpoint(sp).enable().secs(after_s);
        r.plant.set_fault(PlantFault::HeaterDisconnected);
        let cut = r.now;
        let m = 1.0;
        // Find when the reading first lies m below the band and the dead time has passed.
        let mut below = None;
        while r.first_fault().is_none() && r.now < cut + 3600 * S {
            r.secs(0.25);
            if below.is_none() && r.now >= cut + (plant.dead_time_s * 1e9) as Nanos
                && r.plant.temperature() < sp - h.runaway_hysteresis_c - m {
                below = Some(r.now);
            }
        }
        let (at, f) = r.first_fault().expect("a check must trip");
        // not_heating (Klipper's), or earlier the response checks: at full power the reading
        // does not rise (no_rise), or stands still while the power swings (sensor_stuck).
        prop_assert!(["not_heating", "no_rise", "sensor_stuck"].contains(&f.check()), "{}", f);
        let below = below.unwrap_or(at);
        let bound = below
            + (h.runaway_gain_time_s * 1e9) as Nanos
            + ((h.runaway_max_error / m).ceil() as Nanos + 2) * S;
        prop_assert!(at <= bound, "tripped {:.1} s after the reading was below the band, bound {:.1} s",
            (at - below) as f64 / 1e9, (bound - below) as f64 / 1e9);
        prop_assert_eq!(r.ch.level(), Level::Low);
        prop_assert!(r.no_rise_after(at));
    }

    /// A welded SSR (the heater on whatever the line) trips `stuck_on` once the loop holds the
    /// line off and the rise over the window exceeds the limit; the reset is refused while
    /// the temperature still rises.
    #[test]
    fn a_stuck_heater_always_trips_stuck_on(plant in arb_plant(), fraction in 0.1f64..0.4) {
        let mut h = heater(&plant);
        h.stuck_on_rise_c = stuck_rise(&plant);
        h.stuck_on_time_s = 10.0;
        h.temp_max_c = 2999.0;
        let mut r = Rig::new(params(h), plant, 1);
        let sp = plant.ambient_c + fraction * plant.rate_c_per_s * plant.tau_s;
        // Detectable at all: from the setpoint, the stuck heater's rise over the window (less
        // its dead time) exceeds the limit with a margin. A weak heater near its full-power
        // temperature rises too little to tell from a healthy one (docs/heater.md).
        let full = plant.ambient_c + plant.rate_c_per_s * plant.tau_s;
        let window = h.stuck_on_time_s - plant.dead_time_s;
        prop_assume!((full - sp) * (1.0 - (-window / plant.tau_s).exp()) > 1.2 * h.stuck_on_rise_c);
        r.setpoint(sp).enable().secs(60.0);
        r.plant.set_fault(PlantFault::HeaterStuckOn);
        let stuck = r.now;
        while r.first_fault().is_none() && r.now < stuck + 600 * S {
            r.secs(0.25);
        }
        let (at, f) = r.first_fault().expect("stuck_on must trip");
        prop_assert_eq!(f.check(), "stuck_on", "{:?}", f);
        prop_assert_eq!(r.ch.level(), Level::Low);
        // While it still rises, the reset is refused; once the power is cut (the contactor
        // the stopped heartbeat drops) and the window has passed, it is taken.
        prop_assert!(matches!(r.reset(), Err(ResetRefusal::Lasts(_))));
        r.plant.set_fault(PlantFault::None);
        r.secs(h.stuck_on_time_s + plant.dead_time_s + 1.0);
        prop_assert_eq!(r.reset(), Ok(()));
        prop_assert!(r.no_rise_after(at));
    }
}

#[test]
fn under_pid_the_watchdog_watches_the_setpoint_and_the_feedback() {
    let plant = PlantParams::default();
    let mut p = params(heater(&plant));
    p.command_timeout_ms = 3000;
    let mut r = Rig::new(p, plant, 1);
    r.setpoint(60.0).enable().secs(2.0);
    let tripped = |r: &Rig| r.ch.status(r.now).watchdog_tripped;
    assert!(!tripped(&r));
    // Readings keep coming, the setpoint is not repeated: it trips 3 s after the setpoint.
    r.secs(1.1);
    assert!(tripped(&r));
    assert_eq!(r.ch.level(), Level::Low);
    // A fresh setpoint (the readings are fresh): recovered, the loop runs again.
    r.setpoint(60.0).secs(1.0);
    assert!(!tripped(&r));
    assert!(r.ch.status(r.now).heater.terms.output > 0.0);
    // Now the sensor falls silent while the setpoint is repeated: it trips on the feedback.
    r.plant.set_fault(PlantFault::SensorSilent);
    let silent = r.now;
    while r.now < silent + 5 * S && !tripped(&r) {
        r.setpoint(60.0).secs(0.5);
    }
    assert!(tripped(&r), "the silent feedback tripped the watchdog");
    assert!(r.now <= silent + 4 * S);
}

/// A heater in the sizing range docs/heater.md states for the defaults.
fn envelope_plant() -> PlantParams {
    PlantParams {
        rate_c_per_s: 0.6,
        tau_s: 60.0,
        dead_time_s: 1.5,
        ambient_c: 20.0,
        noise_c: 0.05,
        sensor_tau_s: 0.0,
    }
}

#[test]
fn a_reading_stamped_long_ago_or_in_the_future_is_not_fresh() {
    let plant = envelope_plant();
    let mut r = Rig::new(params(heater(&plant)), plant, 1);
    r.setpoint(40.0).enable().secs(5.0);
    let before = r.ch.status(r.now).heater.reading.unwrap();
    // Older than the feedback timeout (3 s) on arrival: refused, counted.
    r.act(|ch, now, emit| ch.feedback_stamped(now, 99.0, Some(3_500 * NS_PER_MS as i64), emit));
    // Ahead of this node's clock by more than feedback_max_skew_ms (1 s): refused.
    r.act(|ch, now, emit| ch.feedback_stamped(now, 98.0, Some(-1_500 * NS_PER_MS as i64), emit));
    let s = r.ch.status(r.now).heater;
    assert_eq!(s.reading, Some(before), "a stale reading moved nothing");
    assert_eq!(s.stale, (2, -1_500 * NS_PER_MS as i64));
    assert!(s.stale_now);
    // Within the skew, and a second old: fresh.
    r.act(|ch, now, emit| ch.feedback_stamped(now, 30.5, Some(-500 * NS_PER_MS as i64), emit));
    r.act(|ch, now, emit| ch.feedback_stamped(now, 30.6, Some(1_000 * NS_PER_MS as i64), emit));
    let s = r.ch.status(r.now).heater;
    assert_eq!(s.reading.map(|(c, _)| c), Some(30.6));
    assert!(!s.stale_now);
    assert!(r.faults().is_empty(), "{:?}", r.faults());
    // A sensor whose every reading comes stale: sensor_timeout after 3 s, the line off.
    r.plant.set_fault(PlantFault::SensorSilent);
    let from = r.now;
    while r.now < from + 5 * S && r.first_fault().is_none() {
        r.act(|ch, now, emit| ch.feedback_stamped(now, 30.0, Some(10 * S as i64), emit));
        r.secs(0.25);
    }
    let (at, f) = r.first_fault().expect("sensor_timeout");
    assert_eq!(f.check(), "sensor_timeout");
    assert!(at - from <= 3 * S + 250 * NS_PER_MS, "{}", at - from);
    assert_eq!(r.ch.level(), Level::Low);
}

#[test]
fn a_setpoint_keeps_its_margin_below_temp_max_and_a_lowered_maximum_takes_it_down() {
    let plant = envelope_plant();
    let mut h = heater(&plant);
    h.temp_max_c = 100.0;
    let mut r = Rig::new(params(h), plant, 1);
    // setpoint_margin_c 15: at most 85 °C.
    r.setpoint(86.0);
    assert!(matches!(
        r.notes.last(),
        Some((_, Event::Refused(crate::core::heater::Refusal::SetpointOutOfRange { max_c, .. }))) if *max_c == 85.0
    ));
    r.setpoint(85.0).enable().secs(2.0);
    assert_eq!(r.ch.status(r.now).heater.setpoint, Some(85.0));
    // temp_max_c lowered to 80: the setpoint in force follows to 65, and says so.
    let mut lower = params(h);
    lower.heater.temp_max_c = 80.0;
    let cfg = lower.validate().unwrap();
    r.act(|ch, now, emit| ch.set_config(now, cfg, emit));
    let s = r.ch.status(r.now).heater;
    assert_eq!(s.setpoint, Some(65.0));
    assert_eq!(s.setpoint_lowered_from, Some(85.0));
    // A new setpoint ends the note.
    r.setpoint(60.0);
    assert_eq!(r.ch.status(r.now).heater.setpoint_lowered_from, None);
}

#[test]
fn under_pid_a_fault_value_needs_its_hold_and_ends_with_it() {
    let plant = envelope_plant();
    let mut p = params(heater(&plant));
    p.command_timeout_ms = 2000;
    p.fault_duty_pct = 30.0;
    let e = p.validate().unwrap_err();
    assert!(e.to_string().contains("needs fault_hold_ms above 0"), "{e}");
    p.fault_hold_ms = 3000;
    let mut r = Rig::new(p, plant, 1);
    r.setpoint(35.0).enable().secs(2.5);
    // The setpoint is not repeated: the watchdog trips at 2 s and runs 30 % for 3 s, then off.
    assert!(r.ch.status(r.now).watchdog_tripped);
    let tripped = r.now;
    r.secs(4.0);
    assert!(
        r.no_rise_after(tripped + 3 * S + S),
        "the fault value outlived its hold"
    );
    assert_eq!(r.ch.level(), Level::Low);
}

#[test]
fn after_a_reset_the_loop_starts_from_zero_and_the_present_reading() {
    let plant = envelope_plant();
    let mut h = heater(&plant);
    h.temp_max_c = 60.0;
    let mut r = Rig::new(params(h), plant, 1);
    r.setpoint(40.0).enable().secs(200.0);
    let before = r.ch.status(r.now).heater.terms.output;
    assert!(before > 20.0, "{before}");
    r.act(|ch, now, emit| ch.feedback(now, f64::NAN, emit));
    assert_eq!(
        r.ch.status(r.now).duty_commanded,
        0.0,
        "no duty survives the fault"
    );
    r.secs(1.0);
    assert_eq!(r.reset(), Ok(()));
    r.secs(30.0);
    let t = r.now - 1;
    r.enable();
    // The first sample after the enable starts from 0 % plus the proportional term of the
    // present reading: the integral of before the fault is gone.
    let s = r.ch.status(r.now).heater;
    assert!(s.terms.i.abs() < 1e-9 || s.terms.i < before / 2.0, "{s:?}");
    r.secs(5.0);
    assert!(!r.no_rise_after(t), "the loop runs again after the enable");
}

#[test]
fn an_autotune_needs_a_fresh_reading_and_its_margin_and_a_stale_one_ends_it() {
    use crate::core::heater::autotune::{Goal, GoalRefusal, Report, Stop};
    let plant = envelope_plant();
    // Open loop with the timeout off: a run still holds its readings to 3 s.
    let mut h = heater(&plant);
    h.control = Control::Open;
    h.feedback_timeout_ms = 0;
    h.temp_max_c = 60.0;
    let mut r = Rig::new(params(h), plant, 1);
    r.secs(1.0).enable().secs(1.0);
    let goal = |t| Goal {
        target_c: t,
        amplitude_pct: 100.0,
        noise_band_c: 0.3,
    };
    let answer = |r: &Rig| {
        r.notes.iter().rev().find_map(|(_, e)| match e {
            Event::Autotune { report, .. } => Some(*report),
            _ => None,
        })
    };
    // Within autotune_margin_c (15) of temp_max_c: refused.
    r.act(|ch, now, emit| ch.start_autotune(now, 1, goal(50.0), emit));
    assert!(
        matches!(answer(&r), Some(Report::Refused(GoalRefusal::Target { max_c, .. })) if max_c == 45.0)
    );
    // A reading older than 3 s: refused.
    r.plant.set_fault(PlantFault::SensorSilent);
    r.secs(4.0);
    r.act(|ch, now, emit| ch.start_autotune(now, 2, goal(35.0), emit));
    assert!(matches!(
        answer(&r),
        Some(Report::Refused(GoalRefusal::NoReading))
    ));
    // Fresh: it runs; the sensor stalls mid-run: sensor_timeout ends it within 3 s, line off.
    r.plant.set_fault(PlantFault::None);
    r.secs(1.0);
    r.act(|ch, now, emit| ch.start_autotune(now, 3, goal(35.0), emit));
    assert!(matches!(answer(&r), Some(Report::Progress(_))));
    r.secs(20.0);
    r.plant.set_fault(PlantFault::SensorSilent);
    let stalled = r.now;
    r.secs(4.0);
    match answer(&r) {
        Some(Report::Finished(o)) => {
            assert!(
                matches!(o.stop, Stop::HeaterFault(HeaterFault::SensorTimeout { .. })),
                "{o:?}"
            )
        }
        other => panic!("{other:?}"),
    }
    let (at, _) = r.first_fault().unwrap();
    assert!(at <= stalled + 3 * S + 250 * NS_PER_MS);
    assert!(r.no_rise_after(at));
}

#[test]
fn the_thermal_model_sees_an_ssr_stuck_on_while_the_loop_switches() {
    let plant = envelope_plant();
    let mut h = heater(&plant);
    // The model the plant has; stuck_on off, so the model is the check that sees it.
    h.model = crate::core::heater::ModelParams {
        gain_c_per_pct: plant.rate_c_per_s * plant.tau_s / 100.0,
        tau_s: plant.tau_s,
        dead_time_s: plant.dead_time_s,
        ambient_c: plant.ambient_c,
        sensor_tau_s: 0.0,
    };
    h.stuck_on_rise_c = 0.0;
    let mut r = Rig::new(params(h), plant, 1);
    r.setpoint(35.0).enable().secs(400.0);
    assert!(r.faults().is_empty(), "{:?}", r.faults());
    let s =
        r.ch.status(r.now)
            .heater
            .model
            .expect("the model's prediction");
    assert!(s.residual_c.abs() < 1.0, "{s:?}");
    r.plant.set_fault(PlantFault::HeaterStuckOn);
    let stuck = r.now;
    while r.first_fault().is_none() && r.now < stuck + 300 * S {
        r.secs(0.25);
    }
    let (at, f) = r.first_fault().expect("model_deviation");
    assert_eq!(f.check(), "model_deviation", "{f}");
    // The residual grows at the plant's rise above the model's prediction, about
    // (36 − 15) / 60 °C/s at first: 10 °C within half a minute, plus model_time_s.
    assert!(at - stuck < 60 * S, "{}", (at - stuck) / S);
}
