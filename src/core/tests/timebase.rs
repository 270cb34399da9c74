//! The time base in virtual time: pulses and breaks in whole ticks on the tick grid,
//! the rounding remainder carried into the next period, the minima and the maximum on time
//! rounded to ticks, against 003's CYCLE_P and 001's task period.

use super::harness::{Bench, MS};
use crate::core::{
    ApplyAt, ChannelParams, ConfigError, Level, Nanos, OutputKind, Plan, Profile, Rule, ShortPulse,
};

fn ticked(period_ms: u64, time_base_ms: f64, f: impl FnOnce(&mut ChannelParams)) -> ChannelParams {
    let mut p = ChannelParams {
        period_ms,
        time_base_ms,
        ..ChannelParams::default()
    };
    f(&mut p);
    p
}

/// The on time of each period `[k T, (k + 1) T)`, ns, for `n` periods.
fn per_period(b: &Bench, period: Nanos, n: u64) -> Vec<Nanos> {
    (0..n)
        .map(|k| b.on_time(k * period, (k + 1) * period))
        .collect()
}

#[test]
fn every_pulse_is_whole_ticks_and_the_remainder_is_carried_003() {
    // 003: "The duration of the created impulse is always a whole number factor of this value"
    // (CYCLE_P). 33 % of 100 ms on a 10 ms tick is 3.3 ticks: 3, 4, 3, ... carrying the rest.
    let mut b = Bench::new(ticked(100, 10.0, |_| {}));
    b.duty(33.0).enable().at(1000.0);
    assert!(b
        .wave()
        .starts_with("H@0 L@30 H@100 L@140 H@200 L@230 H@300 L@330"));
    let on = per_period(&b, 100 * MS, 10);
    assert!(on.iter().all(|t| t % (10 * MS) == 0), "{on:?}");
    // 10 periods of 3.3 ticks: 33 ticks, exactly; plain rounding would give 30.
    assert_eq!(on.iter().sum::<Nanos>(), 330 * MS);
    assert!(b.edges().iter().all(|(t, _)| t % (10 * MS) == 0));
    let s = b.status();
    assert!(!s.e1 && !s.limited && s.rule == Rule::Exact, "{s:?}");
}

#[test]
fn the_delivered_on_time_stays_within_one_tick_of_the_command_over_any_run() {
    // 60 Hz half cycles, 2 s period (240 ticks), 37.1 %: 89.04 ticks a period.
    let params = ticked(2000, 8.333333, |_| {});
    let cfg = params.validate().unwrap();
    assert_eq!(cfg.tick, 8_333_333);
    assert_eq!(cfg.period, 240 * 8_333_333);
    let mut b = Bench::new(params);
    b.duty(37.1).enable();
    let n = 50;
    b.run_to(n * cfg.period);
    let on = per_period(&b, cfg.period, n);
    for i in 0..n as usize {
        for j in i + 1..=n as usize {
            let got: Nanos = on[i..j].iter().sum();
            let want = 0.371 * (j - i) as f64 * cfg.period as f64;
            assert!(
                (got as f64 - want).abs() <= cfg.tick as f64,
                "periods {i}..{j}: {got} ns against {want} ns"
            );
        }
    }
    // Each period is 89 or 90 ticks, and the line is on the grid.
    assert!(on
        .iter()
        .all(|t| *t == 89 * cfg.tick || *t == 90 * cfg.tick));
    assert!(b.edges().iter().all(|(t, _)| t % cfg.tick == 0));
}

#[test]
fn a_fractional_tick_is_rounded_to_the_ns_and_the_period_to_whole_ticks() {
    // 8.3333 ms is 8 333 300 ns; 1000 ms is 120.0005 of them: 120 ticks, 999.996 ms.
    let cfg = ticked(1000, 8.3333, |_| {}).validate().unwrap();
    assert_eq!((cfg.tick, cfg.period), (8_333_300, 120 * 8_333_300));
    let mut b = Bench::new(ticked(1000, 8.3333, |_| {}));
    b.duty(50.0).enable();
    assert_eq!(b.status().period, 999_996_000);
    b.run_to(2 * cfg.period);
    assert_eq!(
        b.edges(),
        vec![
            (0, Level::High),
            (60 * 8_333_300, Level::Low),
            (cfg.period, Level::High),
            (cfg.period + 60 * 8_333_300, Level::Low),
            (2 * cfg.period, Level::High),
        ]
    );
    // A 10 ms tick in a 1000 ms period is exact; 75 ms in 1000 ms rounds to 13 ticks.
    assert_eq!(
        ticked(1000, 10.0, |_| {}).validate().unwrap().period,
        1000 * MS
    );
    assert_eq!(
        ticked(1000, 75.0, |_| {}).validate().unwrap().period,
        975 * MS
    );
    // Period 0 stays 0: no pulses.
    assert_eq!(ticked(0, 10.0, |_| {}).validate().unwrap().period, 0);
}

#[test]
fn an_enable_between_ticks_starts_on_the_next_tick() {
    let mut b = Bench::new(ticked(100, 10.0, |_| {}));
    b.duty(50.0).at(3.3).enable().at(250.0);
    assert_eq!(b.wave(), "H@10 L@60 H@110 L@160 H@210");
}

#[test]
fn minima_count_in_whole_ticks_rounded_up_and_e1_acts_on_the_rounded_times_000() {
    // min on 25 ms on a 10 ms tick is 3 ticks; the floor of 0.1 ms is one tick.
    let cfg = ticked(100, 10.0, |p| p.min_on_ms = 25).validate().unwrap();
    assert_eq!((cfg.min_on, cfg.min_off), (30 * MS, 30 * MS));
    let cfg = ticked(100, 10.0, |_| {}).validate().unwrap();
    assert_eq!((cfg.min_on, cfg.min_off), (10 * MS, 10 * MS));
    // 20 % is 2 ticks, below 3: suppressed, E1, every period. The carry is only the rounding
    // remainder (0 here): it does not build up behind the minimum and release a pulse later.
    let mut b = Bench::new(ticked(100, 10.0, |p| p.min_on_ms = 25));
    b.duty(20.0).enable().at(2000.0);
    assert_eq!(b.wave(), "");
    assert!(b.status().e1);
    assert_eq!(b.status().rule, Rule::SuppressedPulse);
    // 27 % is 2.7 ticks: 3 (kept), then 2.4 -> 2 (suppressed, E1), then 3.1 -> 3, ...: every
    // pulse is at least the rounded minimum, and E1 marks the periods it acted in.
    let mut b = Bench::new(ticked(100, 10.0, |p| p.min_on_ms = 25));
    b.duty(27.0).enable().at(300.0);
    assert_eq!(b.wave(), "H@0 L@30 H@200 L@230 H@300");
    // stretch (002) raises the 2-tick pulse to the 3-tick minimum, with the limit flag.
    let mut b = Bench::new(ticked(100, 10.0, |p| {
        p.min_on_ms = 25;
        p.profile = Profile::TwincatBa;
    }));
    b.duty(20.0).enable().at(100.0);
    assert_eq!(b.wave(), "H@0 L@30 H@100");
    let s = b.status();
    assert!(s.e1 && s.limited && s.rule == Rule::StretchedPulse, "{s:?}");
}

#[test]
fn the_carry_stays_within_half_a_tick() {
    let cfg = ticked(100, 10.0, |p| p.min_on_ms = 25).validate().unwrap();
    let mut carry = 0.0;
    for pct in (1..100).map(|p| f64::from(p) * 0.997) {
        for _ in 0..50 {
            let plan = Plan::carried(pct / 100.0, &cfg, carry);
            assert!(plan.carry.abs() <= 0.5, "{pct} %: {plan:?}");
            assert_eq!(plan.t_on % cfg.tick, 0);
            assert_eq!(plan.t_off % cfg.tick, 0);
            carry = plan.carry;
        }
    }
    // 0 % and 100 % are exact whatever the carry.
    let p = Plan::carried(0.0, &cfg, 0.5);
    assert_eq!((p.t_on, p.carry, p.e1), (0, 0.0, false));
    let p = Plan::carried(1.0, &cfg, -0.5);
    assert_eq!((p.t_off, p.carry, p.e1), (0, 0.0, false));
}

#[test]
fn zero_and_hundred_percent_stay_exact_002() {
    let mut b = Bench::new(ticked(100, 10.0, |p| p.min_on_ms = 25));
    b.duty(100.0).enable().at(500.0);
    assert_eq!(b.wave(), "H@0");
    // 0 % from the next period on, exactly.
    b.duty(0.0).at(1000.0);
    assert_eq!(b.wave(), "H@0 L@600");
    assert!(!b.status().e1);
}

#[test]
fn max_on_is_rounded_down_and_refused_below_the_rounded_minimum() {
    let cfg = ticked(1000, 10.0, |p| p.max_on_ms = 35).validate().unwrap();
    assert_eq!(cfg.max_on, 30 * MS);
    assert_eq!(
        ticked(1000, 10.0, |p| {
            p.min_on_ms = 35;
            p.max_on_ms = 35;
        })
        .validate(),
        Err(ConfigError::MaxOnBelowMinOn {
            max_on_ms: 35,
            min_on_ms: 40.0
        })
    );
    // The cut lands on the grid: 100 % with max on 35 ms -> 30 ms on, a 1-tick break.
    let mut b = Bench::new(ticked(1000, 10.0, |p| p.max_on_ms = 35));
    b.duty(100.0).enable().at(100.0);
    assert_eq!(b.wave(), "H@0 L@30 H@40 L@70 H@80");
}

#[test]
fn the_time_base_is_checked() {
    for v in [-1.0, 0.05, f64::NAN, f64::INFINITY, 3_600_001.0] {
        assert!(
            matches!(
                ticked(1000, v, |_| {}).validate(),
                Err(ConfigError::TimeBaseOutOfRange { .. })
            ),
            "{v}"
        );
    }
    assert_eq!(
        ticked(100, 150.0, |_| {}).validate(),
        Err(ConfigError::TimeBaseAbovePeriod {
            value: 150.0,
            period_ms: 100
        })
    );
    assert_eq!(
        ticked(100, 150.0, |_| {})
            .validate()
            .unwrap_err()
            .to_string(),
        "time_base_ms 150 is above period_ms 100"
    );
    assert!(ticked(100, 100.0, |_| {}).validate().is_ok());
    assert!(ticked(100, 0.1, |_| {}).validate().is_ok());
    // Relay minima round up as well.
    let cfg = ticked(1000, 30.0, |p| p.output_kind = OutputKind::Relay)
        .validate()
        .unwrap();
    assert_eq!((cfg.min_on, cfg.min_off), (60 * MS, 60 * MS));
}

#[test]
fn the_profiles_leave_the_time_base_off_unless_set_001_003() {
    for profile in Profile::ALL {
        let cfg = ChannelParams {
            profile,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        assert_eq!(cfg.tick, 0, "{profile}");
    }
}

#[test]
fn immediate_ends_a_pulse_on_the_next_tick_003() {
    // 003: a shorter impulse ends at once — on a CYCLE_P grid, at the next tick.
    let mut b = Bench::new(ticked(100, 10.0, |p| p.profile = Profile::TcontCp));
    b.duty(50.0).enable().at(23.3).duty(10.0).at(125.0);
    assert_eq!(b.wave(), "H@0 L@30 H@120");
    assert!(b.edges().iter().all(|(t, _)| t % (10 * MS) == 0));
}

#[test]
fn schneider_task_period_resolution_10_001() {
    // 001: "the smallest available pulse lasts for the task period"; period / task period
    // = 10. 15 % is 1.5 task periods: 2, 1, 2, 1, ...: 15 % over every two periods.
    let mut b = Bench::new(ticked(1000, 100.0, |p| p.profile = Profile::SchneiderPwm));
    b.duty(15.0).enable().at(4000.0);
    assert_eq!(
        b.wave(),
        "H@0 L@200 H@1000 L@1100 H@2000 L@2200 H@3000 L@3100 H@4000"
    );
    // 4 % is 0.4 of the task period: no pulse (E1) or one every so often, the shortest
    // pulse one task period; 4 % over 5 periods.
    let mut b = Bench::new(ticked(1000, 100.0, |p| p.profile = Profile::SchneiderPwm));
    b.duty(4.0).enable().at(5000.0);
    assert_eq!(b.on_time(0, 5000 * MS), 200 * MS);
}

#[test]
fn every_policy_runs_on_the_grid() {
    for sp in [
        ShortPulse::Suppress,
        ShortPulse::Stretch,
        ShortPulse::Band,
        ShortPulse::Extend,
    ] {
        for aa in [ApplyAt::NextPeriod, ApplyAt::NextStep, ApplyAt::Immediate] {
            let mut b = Bench::new(ticked(100, 7.0, |p| {
                p.short_pulse = Some(sp);
                p.apply_at = Some(aa);
                p.min_on_ms = 12;
                p.edge_band = 0.05;
            }));
            b.duty(3.0).at(1.1).enable();
            for (k, pct) in [41.0, 8.0, 97.0, 55.5, 0.0, 100.0, 23.0].iter().enumerate() {
                b.at(1.1 + 137.7 * (k + 1) as f64).duty(*pct);
            }
            b.at(2000.0);
            let edges = b.edges();
            assert!(
                edges.iter().all(|(t, _)| t % (7 * MS) == 0),
                "{sp} {aa}: {}",
                b.wave()
            );
            for w in edges.windows(2) {
                // Both minima are 12 ms rounded up to 2 ticks.
                assert!(w[1].0 - w[0].0 >= 14 * MS, "{sp} {aa}: {}", b.wave());
            }
        }
    }
}

#[test]
fn a_pulse_of_exactly_its_minimum_keeps_its_ticks_when_its_rise_is_written_late() {
    // 33 % of 98 ms on a 7 ms tick is 4.62 ticks: pulses of 4 and 5 ticks. With the minimum
    // on time 22..28 ms (4 ticks) the 4-tick pulses are exactly the minimum; every rise is
    // written 50 µs late, as on the output thread. The fall of a 4-tick pulse then comes 4
    // ticks after the real rise, off the grid by those 50 µs, not a whole tick later: over
    // 133 periods the line is on 614 ticks (614.46 commanded), not 665.
    let tick = 7 * MS;
    for min_on_ms in [0, 22, 25, 28] {
        let params = ticked(98, 7.0, |p| p.min_on_ms = min_on_ms);
        let (spans, plans) = super::harness::late_steady(params, 33.0, 133, None, &[(0, 50_000)]);
        let on: Nanos = spans.iter().map(|(r, f)| f - r).sum();
        let want = 0.33 * 133.0 * 98.0 * MS as f64;
        assert!(
            (on as f64 - want).abs() <= tick as f64,
            "min on {min_on_ms} ms: {} ticks on, {} commanded",
            on as f64 / tick as f64,
            want / tick as f64
        );
        // A 4-tick pulse lasts its minimum from the real rise and is written 50 µs late
        // itself; a 5-tick one is whole ticks between two edges as late.
        for (r, f) in &spans {
            let len = f - r;
            assert!(
                len == 5 * tick || (4 * tick..=4 * tick + 50_000).contains(&len),
                "min on {min_on_ms} ms: a pulse of {len} ns"
            );
        }
        assert!(plans.iter().all(|p| !p.e1 && p.rule == Rule::Exact));
    }
}
