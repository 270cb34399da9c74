//! Properties of the channel over random sequences of commands, enables and parameter changes,
//! in exact virtual time.

use super::harness::{Bench, Cause, MS};
use crate::core::{
    ApplyAt, ChannelConfig, ChannelParams, Command, Event, Level, Nanos, OnDisable, OutputKind,
    Plan, Profile, ShortPulse,
};
use proptest::prelude::*;

#[derive(Debug, Clone)]
enum Op {
    Duty(f64),
    Sv(u16),
    Enable(bool),
    Params(ChannelParams),
}

fn arb_percent() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => 0.0..=100.0f64,
        1 => Just(0.0),
        1 => Just(100.0),
        1 => -50.0..150.0f64,
        1 => 0.0..2.0f64,
        1 => 98.0..100.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
    ]
}

fn arb_params() -> impl Strategy<Value = ChannelParams> {
    (
        prop_oneof![1 => Just(0u64), 8 => 5u64..400],
        prop_oneof![2 => Just(0u64), 3 => 0u64..120],
        prop_oneof![2 => Just(None), 1 => (0u64..120).prop_map(Some)],
        prop_oneof![4 => Just(OutputKind::Transistor), 1 => Just(OutputKind::Relay)],
        prop::sample::select(Profile::ALL.to_vec()),
        prop::option::of(prop::sample::select(vec![
            ShortPulse::Suppress,
            ShortPulse::Stretch,
            ShortPulse::Band,
        ])),
        0.0..=1.0f64,
        prop::option::of(prop::sample::select(vec![
            ApplyAt::NextPeriod,
            ApplyAt::NextStep,
            ApplyAt::Immediate,
        ])),
        prop::option::of(prop::sample::select(vec![OnDisable::Off, OnDisable::Hold])),
        prop_oneof![2 => Just(0u64), 1 => 20u64..600],
    )
        .prop_map(
            |(period_ms, min_on_ms, min_off_ms, kind, profile, sp, e, aa, od, to)| ChannelParams {
                period_ms,
                min_on_ms,
                min_off_ms,
                output_kind: kind,
                profile,
                short_pulse: sp,
                edge_band: e,
                apply_at: aa,
                on_disable: od,
                command_timeout_ms: to,
                active_low: false,
            },
        )
        .prop_filter("valid parameters", |p| p.validate().is_ok())
}

fn arb_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => arb_percent().prop_map(Op::Duty),
        1 => (0u16..=5000).prop_map(Op::Sv),
        2 => any::<bool>().prop_map(Op::Enable),
        2 => arb_params().prop_map(Op::Params),
    ]
}

/// Microsecond-resolution gaps up to 1.5 s between inputs.
fn arb_ops() -> impl Strategy<Value = Vec<(Nanos, Op)>> {
    prop::collection::vec(
        ((0u64..1_500_000).prop_map(|us| us * 1000), arb_op()),
        1..40,
    )
}

/// Runs the ops and returns the bench plus the configuration history (time, config in force).
fn play(start: ChannelParams, ops: &[(Nanos, Op)]) -> (Bench, Vec<(Nanos, ChannelConfig)>) {
    let mut b = Bench::new(start);
    let mut history = vec![(0, *b.ch.config())];
    let note = |b: &Bench, h: &mut Vec<(Nanos, ChannelConfig)>| {
        if h.last().map(|(_, c)| c) != Some(b.ch.config()) {
            h.push((b.now, *b.ch.config()));
        }
    };
    for (dt, op) in ops {
        let target = b.now + dt;
        // Step deadline by deadline so config changes at boundaries are recorded when they
        // happen.
        while let Some(d) = b.ch.poll_at().filter(|d| *d <= target) {
            b.run_to(d);
            note(&b, &mut history);
        }
        b.run_to(target);
        match op {
            Op::Duty(v) => b.duty(*v),
            Op::Sv(v) => b.command(Command::Sv(*v)),
            Op::Enable(on) if *on => b.enable(),
            Op::Enable(_) => b.disable(),
            Op::Params(p) => b.params(*p),
        };
        note(&b, &mut history);
    }
    let end = b.now + 3000 * MS;
    while let Some(d) = b.ch.poll_at().filter(|d| *d <= end) {
        b.run_to(d);
        note(&b, &mut history);
    }
    (b, history)
}

/// Edges with whether their timing is governed by the minimum-time rules: edges made by an
/// enable change or by a watchdog trip act at once, as the seeds say (000 EN, 002 bEn).
fn timed_edges(b: &Bench) -> Vec<(Nanos, Level, bool)> {
    let mut out = Vec::new();
    let mut tripped_at = None;
    for l in &b.log {
        match l.event {
            Event::Watchdog { tripped: true } => tripped_at = Some(l.now),
            Event::Edge { at, level } => {
                let governed = l.cause != Cause::Enable && tripped_at != Some(l.now);
                out.push((at, level, governed));
            }
            _ => {}
        }
    }
    out
}

/// The smallest minimum (on or off) of any configuration in force during [a, b].
fn min_during(history: &[(Nanos, ChannelConfig)], a: Nanos, b: Nanos, on: bool) -> Nanos {
    let first = history.iter().rposition(|(t, _)| *t <= a).unwrap_or(0);
    history[first..]
        .iter()
        .take_while(|(t, _)| *t <= b)
        .map(|(_, c)| if on { c.min_on } else { c.min_off })
        .min()
        .unwrap_or(0)
}

proptest! {
    /// Levels alternate, and no pulse or break between two governed edges is shorter than the
    /// minimum in force (000, 002, 003: "no pulse and no break shorter than its minimum").
    #[test]
    fn no_pulse_or_break_below_its_minimum(start in arb_params(), ops in arb_ops()) {
        let (b, history) = play(start, &ops);
        let edges = timed_edges(&b);
        let mut level = Level::Low;
        for (_, l, _) in &edges {
            prop_assert_ne!(*l, level, "levels alternate");
            level = *l;
        }
        for w in edges.windows(2) {
            let ((a, la, ga), (z, _, gz)) = (w[0], w[1]);
            prop_assert!(z >= a, "edges in time order");
            if ga && gz {
                let min = min_during(&history, a, z, la.is_high());
                prop_assert!(
                    z - a >= min,
                    "{} of {} us at {} us is below the minimum {} us",
                    if la.is_high() { "pulse" } else { "break" },
                    (z - a) / 1000, a / 1000, min / 1000
                );
            }
        }
    }

    /// With `next_period`, every rising edge lies exactly on the period grid from the enable.
    #[test]
    fn next_period_rising_edges_lie_on_the_grid(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        ops in prop::collection::vec(
            ((0u64..1_500_000).prop_map(|us| us * 1000), arb_percent()), 1..40),
    ) {
        let params = ChannelParams {
            apply_at: Some(ApplyAt::NextPeriod),
            command_timeout_ms: 0,
            ..start
        };
        let period = params.period_ms * MS;
        let mut b = Bench::new(params);
        b.at(3.3).enable();
        let origin = b.now;
        for (dt, pct) in &ops {
            let t = b.now + dt;
            b.run_to(t).duty(*pct);
        }
        let t = b.now + 10 * period;
        b.run_to(t);
        for (t, level) in b.edges() {
            if level.is_high() {
                prop_assert_eq!((t - origin) % period, 0, "rising edge at {} ns off the grid", t);
            }
        }
    }

    /// Over N periods of a constant command the delivered on time is exactly N times the
    /// reproducible on time (integer ns), under every policy; and E1 is set exactly when the
    /// delivered on time differs from the commanded one for a minimum-time reason.
    #[test]
    fn delivered_on_time_is_exact_and_e1_means_not_reproduced(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        pct in arb_percent().prop_filter("finite", |v| v.is_finite()),
        n in 1u64..20,
    ) {
        let params = ChannelParams { command_timeout_ms: 0, ..start };
        let cfg = params.validate().unwrap();
        let mut b = Bench::new(params);
        b.duty(pct).enable();
        let duty = b.status().duty_commanded;
        let plan = Plan::new(duty, &cfg);
        b.run_to(n * cfg.period);
        prop_assert_eq!(b.on_time(0, n * cfg.period), n * plan.t_on);
        let ideal = (duty * cfg.period as f64).round() as Nanos;
        let s = b.status();
        if cfg.short_pulse != ShortPulse::Band {
            prop_assert_eq!(s.e1, plan.t_on != ideal.min(cfg.period), "duty {} plan {:?}", duty, plan);
        }
        prop_assert_eq!(s.limited, plan.t_on != ideal && cfg.short_pulse == ShortPulse::Stretch);
    }

    /// The watchdog fires exactly at last command + timeout, and the output stays off from
    /// then until the next command.
    #[test]
    fn watchdog_always_fires_by_its_deadline(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        timeout_ms in 20u64..800,
        gaps in prop::collection::vec((0u64..1_500_000).prop_map(|us| us * 1000), 1..20),
        pct in 1.0..100.0f64,
    ) {
        let params = ChannelParams { command_timeout_ms: timeout_ms, ..start };
        let timeout = timeout_ms * MS;
        let mut b = Bench::new(params);
        b.duty(pct).enable();
        let mut commands = vec![0];
        for g in &gaps {
            let t = b.now + g;
            b.run_to(t).duty(pct);
            commands.push(t);
        }
        let end = b.now + 2 * timeout;
        b.run_to(end);
        commands.push(Nanos::MAX);
        let trips: Vec<Nanos> = b.notes().iter()
            .filter(|(_, e)| *e == Event::Watchdog { tripped: true })
            .map(|(t, _)| *t)
            .collect();
        let edges = b.edges();
        for w in commands.windows(2) {
            let (last, next) = (w[0], w[1]);
            let deadline = last + timeout;
            if next.saturating_sub(last) > timeout {
                prop_assert!(trips.contains(&deadline), "trip at {} expected, got {:?}", deadline, trips);
                // Level after everything at the deadline is low, and nothing rises before next.
                let level_at = edges.iter().rev().find(|(t, _)| *t <= deadline).map(|e| e.1);
                prop_assert_ne!(level_at, Some(Level::High));
                prop_assert!(!edges.iter().any(|(t, l)| *t > deadline && *t < next && l.is_high()));
            } else {
                prop_assert!(!trips.iter().any(|t| *t > last && *t < next));
            }
        }
    }
}
