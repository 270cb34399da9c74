//! Properties of the channel over random sequences of commands, enables and parameter changes,
//! in exact virtual time.

use super::harness::{Bench, Cause, MS};
use crate::core::{
    ApplyAt, Channel, ChannelConfig, ChannelParams, Command, Event, Level, Nanos, OnDisable,
    OutputKind, Plan, Profile, Rule, ShortPulse,
};
use proptest::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering};

#[derive(Debug, Clone)]
#[allow(clippy::large_enum_variant)]
enum Op {
    Duty(f64),
    Sv(u16),
    Enable(bool),
    Params(ChannelParams),
    EStop(bool),
    Live(bool),
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
        prop_oneof![2 => Just(0u64), 3 => 0u64..120, 1 => 0u64..600],
        prop_oneof![2 => Just(None), 1 => (0u64..120).prop_map(Some), 1 => (0u64..600).prop_map(Some)],
        prop_oneof![4 => Just(OutputKind::Transistor), 1 => Just(OutputKind::Relay)],
        prop::sample::select(Profile::ALL.to_vec()),
        (
            prop::option::of(prop::sample::select(vec![
                ShortPulse::Suppress,
                ShortPulse::Stretch,
                ShortPulse::Band,
                ShortPulse::Extend,
            ])),
            prop_oneof![2 => Just(10.0f64), 1 => 1.0..=20.0f64],
        ),
        0.0..=1.0f64,
        prop::option::of(prop::sample::select(vec![
            ApplyAt::NextPeriod,
            ApplyAt::NextStep,
            ApplyAt::Immediate,
        ])),
        prop::option::of(prop::sample::select(vec![OnDisable::Off, OnDisable::Hold])),
        prop_oneof![2 => Just(0u64), 1 => 20u64..600],
        (
            prop_oneof![2 => Just(0.0f64), 1 => 0.0..=100.0f64],
            prop_oneof![1 => Just(0u64), 1 => 1u64..2000],
        ),
        arb_protections(),
    )
        .prop_map(
            |(period_ms, min_on_ms, min_off_ms, kind, profile, (sp, xm), e, aa, od, to, (fd, fh), pr)| ChannelParams {
                period_ms,
                min_on_ms,
                min_off_ms,
                output_kind: kind,
                profile,
                short_pulse: sp,
                edge_band: e,
                extend_max: xm,
                apply_at: aa,
                on_disable: od,
                command_timeout_ms: to,
                fault_duty_pct: fd,
                fault_hold_ms: fh,
                // Never below the minimum on time it must respect (the relay floor included).
                max_on_ms: if pr.0 == 0 { 0 } else { pr.0.max(min_on_ms).max(50) },
                max_duty_pct: pr.1.0,
                min_duty_pct: pr.1.1,
                zero_means_zero: pr.2,
                duty_slew_pct_per_s: pr.3,
                duty_deadband_pct: pr.4,
                avg_duty_limit_pct: pr.5.0,
                avg_window_s: pr.5.1,
                time_base_ms: 0.0,
                heater: Default::default(),
            },
        )
        .prop_filter("valid parameters", |p| p.validate().is_ok())
}

/// The load's protections: max on time (ms), (max, min) duty (%), zero means zero, slew (%/s),
/// dead band (%), rolling-average cap (%, window s); each off half of the time or more.
fn arb_protections() -> impl Strategy<Value = (u64, (f64, f64), bool, f64, f64, (f64, u64))> {
    (
        prop_oneof![2 => Just(0u64), 1 => 1u64..3000],
        prop_oneof![
            2 => Just((100.0, 0.0)),
            1 => (0.0..=100.0f64, 0.0..=100.0f64).prop_map(|(a, b)| (a.max(b), a.min(b))),
        ],
        any::<bool>(),
        prop_oneof![2 => Just(0.0f64), 1 => 0.0..500.0f64],
        prop_oneof![2 => Just(0.0f64), 1 => 0.0..20.0f64],
        prop_oneof![3 => Just((100.0f64, 60u64)), 1 => (0.0..100.0f64, 1u64..5)],
    )
}

fn arb_op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => arb_percent().prop_map(Op::Duty),
        1 => (0u16..=5000).prop_map(Op::Sv),
        2 => any::<bool>().prop_map(Op::Enable),
        2 => arb_params().prop_map(Op::Params),
        1 => any::<bool>().prop_map(Op::EStop),
        1 => any::<bool>().prop_map(Op::Live),
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
            Op::EStop(on) => b.estop(*on),
            Op::Live(on) => b.live(*on),
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

/// Edges with whether their timing is governed by the minimum-time rules: only the safety offs
/// act at once, as the seeds say (000 EN, 002 bEn: a falling enable; and a watchdog trip), and
/// the emergency stop.
/// Rising enables are governed: toggling EN never shortens a break.
fn timed_edges(b: &Bench) -> Vec<(Nanos, Level, bool)> {
    let mut out = Vec::new();
    let mut tripped_at = None;
    for l in &b.log {
        match l.event {
            Event::Watchdog { tripped: true } => tripped_at = Some(l.now),
            Event::Edge { at, level } => {
                let forced = level == Level::Low
                    && (matches!(l.cause, Cause::Disable | Cause::EStop | Cause::Live)
                        || tripped_at == Some(l.now));
                out.push((at, level, !forced));
            }
            _ => {}
        }
    }
    out
}

/// The maximum on time in force during [a, b], if one and the same non-zero maximum was in
/// force throughout.
fn max_on_during(history: &[(Nanos, ChannelConfig)], a: Nanos, b: Nanos) -> Option<Nanos> {
    let first = history.iter().rposition(|(t, _)| *t <= a).unwrap_or(0);
    let mut values = history[first..]
        .iter()
        .take_while(|(t, _)| *t <= b)
        .map(|(_, c)| c.max_on);
    let v = values.next()?;
    (v > 0 && values.all(|x| x == v)).then_some(v)
}

/// The spans, in the times `play` uses, from an op that `starts` one to the next that
/// `releases` it, or, with `then`, to the first op after the release that `then` matches
/// (`Nanos::MAX` when none comes).
fn spans(
    ops: &[(Nanos, Op)],
    starts: impl Fn(&Op) -> bool,
    releases: impl Fn(&Op) -> bool,
    then: Option<&dyn Fn(&Op) -> bool>,
) -> Vec<(Nanos, Nanos)> {
    let (mut out, mut t, mut open) = (Vec::new(), 0, None);
    // Released spans waiting for `then`.
    let mut pending: Vec<Nanos> = Vec::new();
    for (dt, op) in ops {
        t += dt;
        match open {
            None if starts(op) => open = Some(t),
            Some(s) if releases(op) => {
                match then {
                    None => out.push((s, t)),
                    Some(_) => pending.push(s),
                }
                open = None;
            }
            None if then.is_some_and(|f| f(op)) => out.extend(pending.drain(..).map(|s| (s, t))),
            _ => {}
        }
    }
    out.extend(pending.into_iter().chain(open).map(|s| (s, Nanos::MAX)));
    out
}

/// Checks that the line is low right after each span's start (every edge at that instant
/// included) and that no rise reaches it before the span's end.
fn low_throughout(
    edges: &[(Nanos, Level)],
    spans: &[(Nanos, Nanos)],
    what: &str,
) -> Result<(), TestCaseError> {
    for &(s, e) in spans {
        let after = edges
            .iter()
            .rev()
            .find(|(at, _)| *at <= s)
            .map_or(Level::Low, |x| x.1);
        prop_assert_eq!(
            after,
            Level::Low,
            "high after the line was {} at {} us",
            what,
            s / 1000
        );
        let rise = edges
            .iter()
            .find(|(at, l)| *at > s && *at < e && l.is_high());
        prop_assert!(
            rise.is_none(),
            "rise at {:?} us, the line {} from {} us",
            rise.map(|r| r.0 / 1000),
            what,
            s / 1000
        );
    }
    Ok(())
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

/// No pulse or break of `edges` (time, level, governed) that ends in a governed edge is shorter
/// than the minimum in force during it; `context` ends the failure message.
fn minima_held(
    edges: &[(Nanos, Level, bool)],
    history: &[(Nanos, ChannelConfig)],
    context: &str,
) -> Result<(), TestCaseError> {
    for w in edges.windows(2) {
        let ((a, la, _), (z, _, gz)) = (w[0], w[1]);
        if gz {
            let min = min_during(history, a, z, la.is_high());
            prop_assert!(
                z - a >= min,
                "{} of {} us at {} us is below the minimum {} us{context}",
                if la.is_high() { "pulse" } else { "break" },
                (z - a) / 1000,
                a / 1000,
                min / 1000
            );
        }
    }
    Ok(())
}

/// Runs `ops` with a thread that wakes late and writes late by `delays`, and checks that no
/// pulse or break on the line (between the instants edges were really written) is shorter than
/// its minimum, except where a safety off ends it, and that the maximum on time counts from the
/// real rise.
fn late_run(
    start: ChannelParams,
    ops: &[(Nanos, Op)],
    delays: &[(Nanos, Nanos)],
) -> Result<(), TestCaseError> {
    let mut ch = Channel::new(start.validate().unwrap(), 0);
    let mut now: Nanos = 0;
    let mut k = 0usize;
    // (written at, level, governed)
    let mut line: Vec<(Nanos, Level, bool)> = Vec::new();
    // Falls: (written at, scheduled at, merged with other edges by a late poll).
    let mut falls: Vec<(Nanos, Nanos, bool)> = Vec::new();
    let mut history = vec![(0, *ch.config())];
    // PWM_TRACE=1 puts the whole run in the failure message.
    let trace = std::env::var_os("PWM_TRACE").is_some();
    let mut dbg_log: Vec<String> = Vec::new();
    let write = |ch: &mut Channel,
                 at: Nanos,
                 events: &[Event],
                 forced_cause: bool,
                 line: &mut Vec<(Nanos, Level, bool)>,
                 falls: &mut Vec<(Nanos, Nanos, bool)>,
                 k: &mut usize|
     -> Nanos {
        let tripped = events.contains(&Event::Watchdog { tripped: true });
        let merged = events.iter().any(|e| matches!(e, Event::Missed { .. }));
        let mut written = at;
        for e in events {
            if let Event::Edge {
                level,
                at: scheduled,
            } = e
            {
                written = at + delays[*k % delays.len()].1;
                *k += 1;
                ch.edge_written(written);
                let forced = *level == Level::Low && (forced_cause || tripped);
                line.push((written, *level, !forced));
                if *level == Level::Low {
                    falls.push((written, *scheduled, merged));
                }
            }
        }
        written
    };
    let mut ends = ops.to_vec();
    ends.push((3000 * MS, Op::Duty(f64::NAN)));
    for (dt, op) in &ends {
        let target = now + dt;
        while let Some(d) = ch.poll_at().filter(|d| *d <= target) {
            let wake = d.max(now) + delays[k % delays.len()].0;
            k += 1;
            let mut ev = Vec::new();
            ch.poll(wake, &mut |e| ev.push(e));
            if trace {
                dbg_log.push(format!(
                    "poll d={} wake={} {:?} since={:?}",
                    d / 1000,
                    wake / 1000,
                    ev,
                    ch.line_since()
                ));
            }
            now = write(&mut ch, wake, &ev, false, &mut line, &mut falls, &mut k);
            history.push((now, *ch.config()));
        }
        let t = target.max(now);
        let mut ev = Vec::new();
        let mut disable = false;
        match op {
            Op::Duty(v) => ch.command(t, Command::Percent(*v), &mut |e| ev.push(e)),
            Op::Sv(v) => ch.command(t, Command::Sv(*v), &mut |e| ev.push(e)),
            Op::Enable(on) => {
                disable = !*on;
                ch.set_enable(t, *on, &mut |e| ev.push(e))
            }
            Op::Params(p) => ch.set_config(t, p.validate().unwrap(), &mut |e| ev.push(e)),
            Op::EStop(on) => {
                disable = *on;
                ch.set_estop(t, *on, &mut |e| ev.push(e))
            }
            Op::Live(on) => {
                disable = !*on;
                ch.set_live(t, *on, &mut |e| ev.push(e))
            }
        }
        if trace {
            dbg_log.push(format!("op t={} {:?} {:?}", t / 1000, op, ev));
        }
        now = write(&mut ch, t, &ev, disable, &mut line, &mut falls, &mut k);
        history.push((now, *ch.config()));
    }
    for w in line.windows(2) {
        let ((a, la, _), (z, lz, _)) = (w[0], w[1]);
        prop_assert_ne!(la, lz, "levels alternate");
        // The maximum on time counts from the real rise: the cut is scheduled no later
        // than max_on_ms after the instant the rise was written (unless a late poll
        // merged it with later edges), while one maximum stays in force.
        if la == Level::High {
            let fall = falls.iter().find(|f| f.0 == z).copied();
            let max_on = max_on_during(&history, a, z);
            if let (Some((_, scheduled, false)), Some(max_on)) = (fall, max_on) {
                prop_assert!(
                    scheduled <= a + max_on,
                    "high written at {} us, its fall scheduled at {} us: beyond max_on {} us\n{}",
                    a / 1000,
                    scheduled / 1000,
                    max_on / 1000,
                    dbg_log.join("\n")
                );
            }
        }
    }
    // Times here are when the edges were written.
    minima_held(&line, &history, &format!("\n{}", dbg_log.join("\n")))?;
    Ok(())
}

/// `p` without what acts over time rather than per period: the watchdog, the maximum on time,
/// the slew limit, the dead band and the average cap (the power limits stay), so a constant
/// command gives the same pulse every period.
fn steady(p: ChannelParams) -> ChannelParams {
    ChannelParams {
        command_timeout_ms: 0,
        max_on_ms: 0,
        duty_slew_pct_per_s: 0.0,
        duty_deadband_pct: 0.0,
        avg_duty_limit_pct: 100.0,
        ..p
    }
}

proptest! {
    /// Levels alternate, and no pulse or break ending in a governed edge is shorter than the
    /// minimum in force (000, 002, 003: "no pulse and no break shorter than its minimum"),
    /// whatever enables, commands and parameter changes came in between.
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
            prop_assert!(w[1].0 >= w[0].0, "edges in time order");
        }
        minima_held(&edges, &history, "")?;
    }

    /// With `next_period`, every rising edge lies exactly on the period grid from the enable
    /// (`extend` moves the grid by design: see
    /// `extend_delivers_the_exact_duty_over_n_extended_periods`).
    #[test]
    fn next_period_rising_edges_lie_on_the_grid(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        ops in prop::collection::vec(
            ((0u64..1_500_000).prop_map(|us| us * 1000), arb_percent()), 1..40),
    ) {
        // The maximum on time cuts the line off the grid; the rest keeps it.
        let params = ChannelParams {
            apply_at: Some(ApplyAt::NextPeriod),
            command_timeout_ms: 0,
            max_on_ms: 0,
            short_pulse: start.short_pulse.filter(|sp| *sp != ShortPulse::Extend),
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
    /// reproducible on time (integer ns) of the command after the power limits, under every
    /// policy (over N extended periods under `extend`); and E1 is set exactly when the
    /// delivered on time differs from the limited one for a minimum-time reason (an extended
    /// period keeps the duty: no E1, the limit flag).
    #[test]
    fn delivered_on_time_is_exact_and_e1_means_not_reproduced(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        pct in arb_percent().prop_filter("finite", |v| v.is_finite()),
        n in 1u64..20,
    ) {
        let params = steady(start);
        let cfg = params.validate().unwrap();
        let mut b = Bench::new(params);
        b.duty(pct).enable();
        let duty = cfg.limit_duty(b.status().duty_commanded);
        prop_assert_eq!(b.status().duty_target, duty);
        let plan = Plan::new(duty, &cfg);
        let period = plan.period();
        prop_assert!(period == cfg.period || plan.rule.extended(), "{:?}", plan);
        b.run_to(n * period);
        prop_assert_eq!(b.on_time(0, n * period), n * plan.t_on);
        let ideal = (duty * cfg.period as f64).round() as Nanos;
        let s = b.status();
        prop_assert_eq!(s.period, period);
        let extended = plan.rule.extended();
        if cfg.short_pulse != ShortPulse::Band {
            prop_assert_eq!(s.e1, plan.t_on != ideal.min(cfg.period) && !extended, "duty {} plan {:?}", duty, plan);
        }
        prop_assert_eq!(
            s.limited,
            (plan.t_on != ideal && cfg.short_pulse == ShortPulse::Stretch) || extended
        );
    }

    /// `extend` (cycle extension): a duty whose pulse or break is below its minimum gets a
    /// longer period in which that phase is exactly its minimum and the duty is kept; over N
    /// such periods the line shows exactly the plan's edges, on the extended grid, and the on
    /// time delivered is the duty times the time within half a ns per period. The period
    /// never grows beyond `extend_max` times the configured one: a duty that would need more
    /// is suppressed (E1), and only then.
    #[test]
    fn extend_delivers_the_exact_duty_over_n_extended_periods(
        period_ms in 5u64..400,
        min_on_ms in 0u64..600,
        min_off_ms in prop::option::of(0u64..600),
        kind in prop_oneof![3 => Just(OutputKind::Transistor), 1 => Just(OutputKind::Relay)],
        extend_max in prop_oneof![2 => Just(10.0f64), 1 => 1.0..=20.0f64],
        apply_at in prop::sample::select(vec![ApplyAt::NextPeriod, ApplyAt::NextStep, ApplyAt::Immediate]),
        pct in prop_oneof![2 => 0.001..1.0f64, 3 => 0.001..99.999f64, 2 => 99.0..99.999f64],
        n in 1u64..20,
    ) {
        // Within the output kind's limits: a relay's period from 100 ms, its minima 0 or from
        // 50 ms.
        let relay = kind == OutputKind::Relay;
        let floor = |ms: u64| if relay && ms > 0 { ms.max(50) } else { ms };
        let params = ChannelParams {
            period_ms: if relay { period_ms.max(100) } else { period_ms },
            min_on_ms: floor(min_on_ms),
            min_off_ms: min_off_ms.map(floor),
            output_kind: kind,
            short_pulse: Some(ShortPulse::Extend),
            extend_max,
            apply_at: Some(apply_at),
            ..ChannelParams::default()
        };
        let cfg = params.validate().unwrap();
        let d = pct / 100.0;
        let plan = Plan::new(d, &cfg);
        let period = plan.period();
        let mut b = Bench::new(params);
        b.duty(pct).enable();
        b.run_to(n * period);
        let s = b.status();
        let ideal = (cfg.min_on as f64 / d).max(cfg.min_off as f64 / (1.0 - d));
        let limit = cfg.params.extend_max * cfg.period as f64;
        if plan.rule.extended() {
            prop_assert!(period >= cfg.period && period as f64 <= limit, "{:?}", plan);
            prop_assert!(plan.t_on >= cfg.min_on && plan.t_off >= cfg.min_off, "{:?}", plan);
            if plan.rule == Rule::ExtendedPulse {
                prop_assert_eq!(plan.t_on, cfg.min_on);
            } else {
                prop_assert_eq!(plan.t_off, cfg.min_off);
            }
            // The line: exactly the plan's edges, period after period, and the next rise.
            let want: Vec<(Nanos, Level)> = (0..n)
                .flat_map(|k| [(k * period, Level::High), (k * period + plan.t_on, Level::Low)])
                .chain([(n * period, Level::High)])
                .collect();
            prop_assert_eq!(b.edges(), want);
            let on = b.on_time(0, n * period);
            prop_assert_eq!(on, n * plan.t_on);
            let error = (on as f64 - d * (n * period) as f64).abs();
            prop_assert!(error <= 0.5 * n as f64 + 1e-3, "{} ns off over {} periods", error, n);
            prop_assert!(!s.e1 && s.limited, "{:?}", s);
            prop_assert_eq!((s.period, s.rule), (period, plan.rule));
        } else if plan.rule == Rule::Exact {
            prop_assert_eq!(period, cfg.period);
            prop_assert!(!s.e1 && !s.limited);
        } else {
            // Suppressed: only because the extension would exceed extend_max.
            prop_assert!(matches!(plan.rule, Rule::SuppressedPulse | Rule::SuppressedBreak), "{:?}", plan);
            prop_assert!(ideal >= limit - 1.0, "suppressed though {} ns <= {} ns", ideal, limit);
            prop_assert!(s.e1 && !s.limited);
            prop_assert_eq!(s.period, cfg.period);
        }
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
        // Without a fault value: the output stays off after a trip.
        let params = ChannelParams { command_timeout_ms: timeout_ms, fault_duty_pct: 0.0, ..start };
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

    /// With a thread that wakes late and writes late at random, no pulse or break on the line
    /// (between the instants edges were really written) is shorter than its minimum, except
    /// where a safety off ends it. A late edge moves the next one (issue: late wake-ups).
    #[test]
    fn late_wakeups_and_writes_never_shorten_a_phase_below_its_minimum(
        start in arb_params(),
        ops in arb_ops(),
        delays in prop::collection::vec((0u64..80_000_000, 0u64..200_000), 64),
    ) {
        late_run(start, &ops, &delays)?;
    }

    /// The maximum on time: no high run on the line lasts longer than `max_on_ms`
    /// from its rise, whatever commands (100 % included), enables, parameters and policies come
    /// in between. A maximum set or shortened during a run cuts it when it comes into force at
    /// the latest.
    #[test]
    fn no_high_run_longer_than_max_on(start in arb_params(), ops in arb_ops()) {
        let (b, history) = play(start, &ops);
        let mut runs = Vec::new();
        let mut rise = None;
        for (t, level) in b.edges() {
            match level {
                Level::High => rise = Some(t),
                Level::Low => runs.extend(rise.take().map(|a| (a, t))),
            }
        }
        runs.extend(rise.map(|a| (a, b.now)));
        for (a, z) in runs {
            // The configuration in force at the end of the run, and since when.
            let i = history.iter().rposition(|(t, _)| *t < z).unwrap_or(0);
            let (since, cfg) = history[i];
            if cfg.max_on > 0 {
                let bound = (a + cfg.max_on).max(since);
                prop_assert!(
                    z <= bound,
                    "high from {} us to {} us: beyond max_on {} us (in force since {} us)",
                    a / 1000, z / 1000, cfg.max_on / 1000, since / 1000
                );
            }
        }
    }

    /// The rolling-average cap: no window of `avg_window_s` (any start) holds more
    /// on time than the limit times the window, to the nanosecond, whatever commands (100 %
    /// included), enables, e-stops, holds, parameters, policies, minima and the other
    /// protections come in between. The cap decides only where an on phase may start or run,
    /// and what it lets the line commit to (an on time, or the rest of a running pulse's
    /// minimum) fits the budget then, so no pulse planned within it can overrun it: the bound
    /// is exact (tolerance 0). One thing can: a minimum on time raised while a pulse runs
    /// keeps the line on for the new minimum (a promise about the line, like the old one), so
    /// a window that overlaps the raise or the new minimum after it may hold the raise more.
    /// Parameter changes keep the cap and `on_disable: off` (a line held on by `hold` is not
    /// pulsed, and not capped).
    #[test]
    fn no_window_holds_more_on_time_than_the_avg_duty_cap(
        start in arb_params(),
        limit in prop_oneof![1 => 0.0..100.0f64, 1 => Just(25.0f64)],
        window_s in 1u64..4,
        ops in arb_ops(),
    ) {
        let capped = |p: ChannelParams| ChannelParams {
            avg_duty_limit_pct: limit,
            avg_window_s: window_s,
            on_disable: Some(OnDisable::Off),
            ..p
        };
        let ops: Vec<_> = ops
            .into_iter()
            .map(|(dt, op)| match op {
                Op::Params(p) => (dt, Op::Params(capped(p))),
                op => (dt, op),
            })
            .collect();
        let (b, history) = play(capped(start), &ops);
        let window = window_s * 1000 * MS;
        let allowed = (limit / 100.0 * window as f64).floor() as Nanos;
        // Where the minimum on time grew, and by how much.
        let raises: Vec<(Nanos, Nanos, Nanos)> = history
            .windows(2)
            .filter(|h| h[1].1.min_on > h[0].1.min_on)
            .map(|h| (h[1].0, h[1].1.min_on, h[1].1.min_on - h[0].1.min_on))
            .collect();
        for (on, end) in b.windows_on(window) {
            let slack: Nanos = raises
                .iter()
                .filter(|(t, min_on, _)| end > *t && end.saturating_sub(window) < t + min_on)
                .map(|r| r.2)
                .sum();
            prop_assert!(
                on <= allowed + slack,
                "{} us on in the {} s window ending at {} us, {} us allowed (+{} us): {}",
                on / 1000, window_s, end / 1000, allowed / 1000, slack / 1000, b.wave()
            );
        }
    }

    /// A line held on by 004's hold is switched off by the watchdog: at no instant is the line
    /// high longer than the timeout after the last valid command, enabled or not.
    #[test]
    fn the_watchdog_covers_a_held_line(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        timeout_ms in 20u64..800,
        ops in arb_ops(),
    ) {
        let guarded = |p: ChannelParams| ChannelParams {
            command_timeout_ms: timeout_ms,
            fault_duty_pct: 0.0,
            on_disable: Some(OnDisable::Hold),
            ..p
        };
        let ops: Vec<(Nanos, Op)> = ops
            .into_iter()
            .map(|(dt, op)| match op {
                Op::Params(p) => (dt, Op::Params(guarded(p))),
                op => (dt, op),
            })
            .collect();
        let (b, _) = play(guarded(start), &ops);
        // Valid commands, at the instants `play` applied them (the channel counts from 0).
        let mut commands = vec![0];
        let mut t = 0;
        for (dt, op) in &ops {
            t += dt;
            if matches!(op, Op::Sv(_)) || matches!(op, Op::Duty(v) if v.is_finite()) {
                commands.push(t);
            }
        }
        let timeout = timeout_ms * MS;
        let stale = |x: Nanos, strictly_before: bool| {
            let last = commands
                .iter()
                .copied()
                .filter(|c| if strictly_before { *c < x } else { *c <= x })
                .max()
                .unwrap_or(0);
            x - last > timeout
        };
        let mut runs = Vec::new();
        let mut high_since = None;
        for (t, level) in b.edges() {
            match (level, high_since) {
                (Level::High, None) => high_since = Some(t),
                (Level::Low, Some(s)) => {
                    runs.push((s, t));
                    high_since = None;
                }
                _ => {}
            }
        }
        if let Some(s) = high_since {
            runs.push((s, b.now));
        }
        for (s, e) in runs {
            prop_assert!(!stale(e, true), "high until {} us, no command for over {} ms", e / 1000, timeout_ms);
            for c in commands.iter().copied().filter(|c| *c > s && *c <= e) {
                prop_assert!(!stale(c, true), "high at {} us, no command for over {} ms", c / 1000, timeout_ms);
            }
        }
    }

    /// While the line is held inactive (a managed node not ACTIVE) it is low: it goes low at
    /// the instant of the hold and no rise reaches it until the release.
    #[test]
    fn no_line_is_high_while_held_inactive(start in arb_params(), ops in arb_ops()) {
        let (b, _) = play(start, &ops);
        let spans = spans(&ops, |op| matches!(op, Op::Live(false)), |op| matches!(op, Op::Live(true)), None);
        low_throughout(&b.edges(), &spans, "held")?;
    }

    /// While the e-stop is latched the line is low: it goes low at the instant of the latch and
    /// no rise reaches it until the release; after the release nothing rises before a fresh
    /// enable. Whatever commands, enables, parameters and fault values come in between.
    #[test]
    fn no_line_is_high_while_the_estop_is_latched(start in arb_params(), ops in arb_ops()) {
        let (b, _) = play(start, &ops);
        let fresh_enable = |op: &Op| matches!(op, Op::Enable(true));
        let spans = spans(&ops, |op| matches!(op, Op::EStop(true)), |op| matches!(op, Op::EStop(false)), Some(&fresh_enable));
        low_throughout(&b.edges(), &spans, "latched")?;
    }

    /// 004's band is symmetric: duty d at edge e gives the mirror of 1 - d, for every pair
    /// written in whole percent.
    #[test]
    fn the_band_boundary_is_symmetric(pct in 0u32..=100, edge_pct in 0u32..=100) {
        let cfg = ChannelParams {
            period_ms: 1000,
            short_pulse: Some(ShortPulse::Band),
            edge_band: f64::from(edge_pct) / 100.0,
            ..ChannelParams::default()
        }.validate().unwrap();
        let p = Plan::new(f64::from(pct) / 100.0, &cfg);
        let q = Plan::new(f64::from(100 - pct) / 100.0, &cfg);
        if 2 * edge_pct <= 100 {
            prop_assert_eq!((p.t_on, p.t_off), (q.t_off, q.t_on), "{} % / {} %", pct, 100 - pct);
        }
    }
}

/// A time base for a channel of `period_ms`: a 60 Hz or 50 Hz half cycle, a round tick, or any
/// one from 0.1 ms with four decimals; never above the period.
fn arb_time_base() -> impl Strategy<Value = f64> {
    prop_oneof![
        1 => Just(8.3333f64),
        1 => Just(8.333333f64),
        1 => Just(10.0f64),
        1 => Just(1.0f64),
        2 => (1_000u64..500_000).prop_map(|x| x as f64 / 10_000.0),
    ]
}

/// `p` with the time base `tb` (kept within its period), if that is valid.
fn with_time_base(p: ChannelParams, tb: f64) -> Option<ChannelParams> {
    let tb = if p.period_ms > 0 {
        tb.min(p.period_ms as f64)
    } else {
        tb
    };
    exactly(p, tb)
}

/// `p` with the time base `tb` as it is, if that is valid.
fn exactly(p: ChannelParams, tb: f64) -> Option<ChannelParams> {
    let q = ChannelParams {
        time_base_ms: tb,
        ..p
    };
    q.validate().is_ok().then_some(q)
}

proptest! {
    /// The time base: every edge the schedule asks for lies on the tick grid (a
    /// whole multiple of the tick on the monotonic clock), so every pulse and break between
    /// two of them is a whole number of ticks, and none is shorter than its minimum (whole
    /// ticks too) — whatever the policies, profiles, protections, minima, commands, enables,
    /// e-stops, holds and parameter changes. Only the safety offs (a falling enable, a
    /// watchdog trip, the e-stop, a hold) act at once, off the grid.
    #[test]
    fn with_a_time_base_every_edge_is_on_the_tick_grid(
        start in arb_params(),
        tb in arb_time_base(),
        ops in arb_ops(),
    ) {
        let start = with_time_base(start, tb);
        prop_assume!(start.is_some(), "the time base does not fit these parameters");
        let start = start.unwrap();
        // One time base throughout; a parameter set it does not fit is left out.
        let ops: Vec<(Nanos, Op)> = ops
            .into_iter()
            .map(|(dt, op)| match op {
                Op::Params(p) => (dt, exactly(p, start.time_base_ms).map_or(Op::Duty(50.0), Op::Params)),
                op => (dt, op),
            })
            .collect();
        let tick = start.validate().unwrap().tick;
        let (b, history) = play(start, &ops);
        let edges = timed_edges(&b);
        // A maximum on time lowered during a run cuts the line at once when it comes into
        // force: a promise about the line, like the safety offs.
        let lowered: Vec<Nanos> = history
            .windows(2)
            .filter(|h| h[1].1.max_on != h[0].1.max_on)
            .map(|h| h[1].0)
            .collect();
        let scheduled = |(t, level, governed): &(Nanos, Level, bool)| {
            *governed && !(*level == Level::Low && lowered.contains(t))
        };
        for e in &edges {
            if scheduled(e) {
                prop_assert_eq!(e.0 % tick, 0, "{:?} edge at {} ns off the {} ns grid: {}", e.1, e.0, tick, b.wave());
            }
        }
        // So every pulse and break between two of them is whole ticks.
        for w in edges.windows(2) {
            if scheduled(&w[0]) && scheduled(&w[1]) {
                prop_assert_eq!((w[1].0 - w[0].0) % tick, 0);
            }
        }
        minima_held(&edges, &history, "")?;
    }

    /// The cases of [`with_a_time_base_the_delivered_on_time_is_within_one_tick_over_any_run`]
    /// (which counts how many reach the sum's check).
    fn within_one_tick_cases(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        tb in arb_time_base(),
        pct in 0.0..=100.0f64,
        n in 2u64..40,
    ) {
        let params = steady(start);
        let params = with_time_base(params, tb);
        prop_assume!(params.is_some(), "the time base does not fit these parameters");
        let params = params.unwrap();
        let cfg = params.validate().unwrap();
        let (tick, period) = (cfg.tick, cfg.period);
        prop_assert_eq!(period % tick, 0);
        let mut b = Bench::new(params);
        b.duty(pct).enable();
        let d = cfg.limit_duty(b.status().duty_commanded);
        b.run_to(n * period);
        let on: Vec<Nanos> = (0..n).map(|k| b.on_time(k * period, (k + 1) * period)).collect();
        prop_assert!(on.iter().all(|t| t % tick == 0), "{:?}", on);
        prop_assert!(b.edges().iter().all(|(t, _)| t % tick == 0), "{}", b.wave());
        // The rounded on times lie within a tick of d × P either way: if every one of them
        // passes the rules, the duty is delivered.
        let ticks = (period / tick) as f64;
        let x = d * ticks;
        let untouched = (x.floor() as i64 - 1..=x.ceil() as i64 + 1).all(|m| {
            m > 0
                && (m as f64) < ticks
                && m as u64 * tick >= cfg.min_on
                && period - m as u64 * tick >= cfg.min_off
        });
        let band = cfg.short_pulse == ShortPulse::Band
            && (crate::core::plan::definitely_less(d, cfg.edge_band)
                || crate::core::plan::definitely_less(1.0 - cfg.edge_band, d));
        if d > 0.0 && d < 1.0 && untouched && !band {
            WITHIN_ONE_TICK_CHECKED.fetch_add(1, Ordering::Relaxed);
            for i in 0..n as usize {
                for j in i + 1..=n as usize {
                    let got: Nanos = on[i..j].iter().sum();
                    let want = d * (j - i) as f64 * period as f64;
                    prop_assert!(
                        (got as f64 - want).abs() <= tick as f64 + 1e-6 * want,
                        "periods {}..{}: {} ns on, {} ns commanded, tick {} ns",
                        i, j, got, want, tick
                    );
                }
            }
            prop_assert!(!b.status().e1);
        }
    }

    /// Late wake-ups and late writes with a time base: the line still never holds a pulse or
    /// a break shorter than its minimum (counted from the real edges); an edge written late is
    /// off the grid by its lateness, and the next one is back on it.
    #[test]
    fn with_a_time_base_late_edges_never_shorten_a_phase_below_its_minimum(
        start in arb_params(),
        tb in arb_time_base(),
        ops in arb_ops(),
        delays in prop::collection::vec((0u64..80_000_000, 0u64..200_000), 64),
    ) {
        let start = with_time_base(start, tb);
        prop_assume!(start.is_some(), "the time base does not fit these parameters");
        let start = start.unwrap();
        let ops: Vec<(Nanos, Op)> = ops
            .into_iter()
            .map(|(dt, op)| match op {
                Op::Params(p) => (dt, exactly(p, start.time_base_ms).map_or(Op::Duty(50.0), Op::Params)),
                op => (dt, op),
            })
            .collect();
        late_run(start, &ops, &delays)?;
    }
}

/// How many cases of `within_one_tick_cases` reached the sum's check (the others: a duty of 0
/// or 100 %, or one where a minimum-time rule or `band` acts, which E1 covers).
static WITHIN_ONE_TICK_CHECKED: AtomicU32 = AtomicU32::new(0);

/// The time base's error diffusion: over any run of consecutive periods of a constant command
/// the on time delivered is within one tick of the command's (the duty after the power limits
/// times the period in force), each period's on time a whole number of ticks, under every
/// policy and profile — wherever the minimum-time rules leave the rounded pulses alone (where
/// they act, E1 says so, as without a time base). At least an eighth of the cases reach the
/// sum's check, so the property cannot pass on cases that all step around it (from 52 to 83
/// of 256 did in 16 runs with random seeds: a quarter failed one run in four).
#[test]
fn with_a_time_base_the_delivered_on_time_is_within_one_tick_over_any_run() {
    WITHIN_ONE_TICK_CHECKED.store(0, Ordering::Relaxed);
    within_one_tick_cases();
    let cases = ProptestConfig::default().cases;
    let checked = WITHIN_ONE_TICK_CHECKED.load(Ordering::Relaxed);
    eprintln!("{checked} of {cases} cases reached the sum's check");
    assert!(
        checked >= cases / 8,
        "only {checked} of {cases} cases reached the sum's check"
    );
}

proptest! {
    /// The cases of
    /// [`with_a_time_base_late_writes_keep_the_delivered_on_time_or_e1_names_the_rule`]
    /// (which counts how many reach the sums' check).
    fn late_writes_cases(
        start in arb_params().prop_filter("pulsing", |p| p.period_ms > 0),
        tb in arb_time_base(),
        pct in 0.0..=100.0f64,
        near in prop::option::of((any::<bool>(), -1.5..1.5f64)),
        n in 2u64..40,
        repeat in prop::option::of(1u64..200),
        late in prop::collection::vec((0.0..=1.0f64, 0.0..=1.0f64), 1..16),
    ) {
        let params = steady(start);
        let params = with_time_base(params, tb);
        prop_assume!(params.is_some(), "the time base does not fit these parameters");
        let params = params.unwrap();
        let cfg = params.validate().unwrap();
        let (tick, period) = (cfg.tick, cfg.period);
        let ticks = (period / tick) as f64;
        // Half the time the duty lies within a tick and a half of a minimum, where the
        // rounded pulses or breaks are exactly it.
        let pct = match near {
            Some((true, u)) => 100.0 * ((cfg.min_on / tick) as f64 + u) / ticks,
            Some((false, u)) => 100.0 * (1.0 - ((cfg.min_off / tick) as f64 + u) / ticks),
            None => pct,
        }
        .clamp(0.0, 100.0);
        // Each edge late by up to a thousandth of a tick, at least 1 ns in all: every edge
        // is late, and the lateness of a whole run stays well under a tick.
        let most = (tick / 2000).max(1);
        let late: Vec<(Nanos, Nanos)> = late
            .iter()
            .map(|(w, x)| ((w * most as f64) as Nanos, (x * most as f64) as Nanos + 1))
            .collect();
        let lateness = 2 * most + 1;
        let (spans, plans) = super::harness::late_steady(params, pct, n, repeat.map(|ms| ms * MS), &late);
        let d = cfg.limit_duty(pct / 100.0);
        // E1 always names the rule that set it.
        for p in &plans {
            prop_assert!(!p.e1 || p.rule != Rule::Exact, "E1 with rule exact: {:?}", p);
        }
        let named = plans.iter().any(|p| {
            (p.e1 && p.rule != Rule::Exact)
                || p.rule.extended()
                || matches!(p.rule, Rule::BandLow | Rule::BandHigh)
        });
        if named {
            return Ok(());
        }
        LATE_WRITES_CHECKED.fetch_add(1, Ordering::Relaxed);
        let on = |a: Nanos, z: Nanos| -> Nanos {
            spans.iter().map(|(r, f)| (*f).min(z).saturating_sub((*r).max(a))).sum()
        };
        let per: Vec<Nanos> = (0..n).map(|k| on(k * period, (k + 1) * period)).collect();
        for i in 0..n as usize {
            for j in i + 1..=n as usize {
                let got: Nanos = per[i..j].iter().sum();
                let want = d * (j - i) as f64 * period as f64;
                let slack = tick as f64 + (2 * (j - i + 1) as u64 * lateness) as f64 + 1e-6 * want;
                prop_assert!(
                    (got as f64 - want).abs() <= slack,
                    "periods {}..{} of {} ticks of {} ns at {} %: {} ticks on, {} commanded, \
                     no E1, rule exact (min on {} ticks, min off {})",
                    i, j, ticks, tick, pct, got as f64 / tick as f64, want / tick as f64,
                    cfg.min_on / tick, cfg.min_off / tick
                );
            }
        }
    }
}

/// How many cases of `late_writes_cases` reached the sums' check (the others: a rule acted and
/// E1 or the rule says so).
static LATE_WRITES_CHECKED: AtomicU32 = AtomicU32::new(0);

/// The time base's error diffusion on a line whose edges are written late, as every edge
/// of the output thread is (by its wake-up and the write, tens of µs): over any run of
/// consecutive periods of a constant command the on time on the line is within one tick of
/// the command's, give or take the lateness of the edges, for every period, tick, duty and
/// pair of minima — or a rule acted and says so: E1 set with the rule named (suppressed,
/// stretched), or the policy's rule named (`band`'s constants, `extend`'s longer period).
/// A pulse or break of exactly its minimum is not lengthened a whole tick by its edge's
/// microseconds of lateness, nor is a phase 003's re-evaluation re-times (the command
/// sent again at a rate).
/// At least an eighth of the cases reach the sums' check (82 to 106 of 256 did in 16 runs).
#[test]
fn with_a_time_base_late_writes_keep_the_delivered_on_time_or_e1_names_the_rule() {
    LATE_WRITES_CHECKED.store(0, Ordering::Relaxed);
    late_writes_cases();
    let cases = ProptestConfig::default().cases;
    let checked = LATE_WRITES_CHECKED.load(Ordering::Relaxed);
    eprintln!("{checked} of {cases} cases reached the sums' check");
    assert!(
        checked >= cases / 8,
        "only {checked} of {cases} cases reached the sums' check"
    );
}
