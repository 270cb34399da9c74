//! Every channel rule of SPEC §1 in virtual time, each test naming the seed it checks.

use super::harness::{Bench, Cause, MS};
use crate::core::{
    ApplyAt, ChannelParams, Command, CommandError, Event, Level, OnDisable, OutputKind, Profile,
    Rule,
};

fn p() -> ChannelParams {
    ChannelParams::default()
}

fn with(f: impl FnOnce(&mut ChannelParams)) -> ChannelParams {
    let mut params = p();
    f(&mut params);
    params
}

// ---- 1. period and duty ----------------------------------------------------------------------

#[test]
fn on_time_proportional_to_sv_period_unchanged_000() {
    let mut b = Bench::new(p());
    b.duty(37.0).enable().at(2500.0);
    assert_eq!(b.wave(), "H@0 L@370 H@1000 L@1370 H@2000 L@2370");
}

#[test]
fn sv_4095_is_full_scale_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.command(Command::Sv(2048)).enable().at(150.0);
    // 2048/4095 of 100 ms = 50.012 ms, to the ns.
    let t_on = (2048.0 / 4095.0 * 100.0 * MS as f64).round() as u64;
    assert_eq!(
        b.edges(),
        vec![
            (0, Level::High),
            (t_on, Level::Low),
            (100 * MS, Level::High)
        ]
    );
}

#[test]
fn fraction_command_004() {
    // 004: q_xOput TRUE for TimeBase * i_rIput, then FALSE for TimeBase * (1 - i_rIput).
    let mut b = Bench::new(with(|p| p.profile = Profile::FrequencyOutput));
    b.command(Command::Fraction(0.5)).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000 L@1500");
}

#[test]
fn period_zero_gives_no_pulses_and_holds_0_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 0));
    b.duty(50.0).enable().at(5000.0);
    assert_eq!(b.wave(), "");
    assert_eq!(b.ch.poll_at(), None);
    assert!(!b.status().active);
    // Setting a period starts pulsing at once: there is no period boundary to wait for.
    b.params(with(|p| p.period_ms = 100)).at(5150.0);
    assert_eq!(b.wave(), "H@5000 L@5050 H@5100 L@5150");
}

#[test]
fn period_to_zero_applies_at_the_boundary_and_holds_0_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(50.0).enable().at(20.0);
    b.params(with(|p| p.period_ms = 0)).at(500.0);
    assert_eq!(b.wave(), "H@0 L@50");
    assert_eq!(b.ch.level(), Level::Low);
}

// ---- 1.1 commands ----------------------------------------------------------------------------

#[test]
fn nan_and_inf_are_refused_and_last_command_stays_001() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(30.0).enable().at(10.0);
    b.duty(f64::NAN)
        .duty(f64::INFINITY)
        .duty(f64::NEG_INFINITY)
        .at(250.0);
    assert_eq!(b.wave(), "H@0 L@30 H@100 L@130 H@200 L@230");
    let notes = b.notes();
    assert!(notes.contains(&(10 * MS, Event::Rejected(CommandError::NotANumber))));
    assert_eq!(
        notes
            .iter()
            .filter(|(_, e)| *e == Event::Rejected(CommandError::Infinite))
            .count(),
        2
    );
    assert_eq!(b.status().duty_commanded, 0.3);
}

#[test]
fn out_of_range_is_clamped_and_flagged_002() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(150.0).enable().at(250.0);
    assert_eq!(b.wave(), "H@0", "clamped to 100 %: constant on");
    assert!(b.notes().contains(&(
        0,
        Event::Clamped {
            requested: Command::Percent(150.0),
            applied: 1.0
        }
    )));
    let s = b.status();
    assert!(s.command_clamped);
    assert_eq!(
        (s.duty_requested, s.duty_commanded),
        (Command::Percent(150.0), 1.0)
    );
    b.duty(-3.0).at(400.0);
    assert_eq!(b.wave(), "H@0 L@300", "clamped to 0 % from the next period");
    b.duty(20.0);
    assert!(
        !b.status().command_clamped,
        "a valid command clears the flag"
    );
}

#[test]
fn sv_above_4095_is_clamped_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.command(Command::Sv(60000)).enable();
    assert_eq!(b.status().duty_commanded, 1.0);
    assert!(b.status().command_clamped);
}

#[test]
fn each_clamp_report_carries_its_own_commands_unit() {
    // Two clamped commands back to back in different units: each report names its own, so a
    // reader never pairs a value with the other command's unit.
    let mut b = Bench::new(p());
    b.command(Command::Sv(5000)).duty(-7.0);
    let clamps: Vec<Command> = b
        .notes()
        .iter()
        .filter_map(|(_, e)| match e {
            Event::Clamped { requested, .. } => Some(*requested),
            _ => None,
        })
        .collect();
    assert_eq!(clamps, vec![Command::Sv(5000), Command::Percent(-7.0)]);
    assert_eq!(b.status().duty_requested, Command::Percent(-7.0));
}

// ---- 1.1 enable --------------------------------------------------------------------------------

#[test]
fn rising_enable_starts_a_period_with_its_on_phase_000_004() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(40.0).at(1234.5).enable().at(1400.0);
    assert_eq!(b.wave(), "H@1234.5 L@1274.5 H@1334.5 L@1374.5");
}

#[test]
fn rising_enable_at_0_and_100_goes_straight_there_without_minimum_rule_002() {
    // 002: at 0 % and 100 % no minimum-time rule changes the duty: 0 % is off and 100 % on,
    // straight from the enable. The line's own minima still hold.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 100;
        p.min_on_ms = 40;
        p.on_disable = Some(OnDisable::Hold);
    }));
    b.duty(50.0).enable().at(60.0).disable().at(61.0);
    b.duty(0.0).enable().at(62.0);
    assert_eq!(b.wave(), "H@0 L@50", "held low, stays low at 0 %");
    let mut b = Bench::new(with(|p| {
        p.period_ms = 100;
        p.min_on_ms = 40;
        p.on_disable = Some(OnDisable::Hold);
    }));
    b.duty(50.0)
        .enable()
        .at(45.0)
        .disable()
        .duty(0.0)
        .enable()
        .at(46.0);
    assert_eq!(
        b.wave(),
        "H@0 L@45",
        "0 %: straight off, the pulse had its 40 ms"
    );
    b.at(200.0).disable().duty(100.0).enable().at(201.0);
    assert_eq!(b.wave(), "H@0 L@45 H@200", "100 %: straight on");
    assert!(!b.status().e1);
}

#[test]
fn rising_enable_at_0_keeps_a_held_pulse_to_its_minimum() {
    // A pulse held by `hold` (004) and then ended by an enable at 0 % still lasts min on.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 100;
        p.min_on_ms = 40;
        p.on_disable = Some(OnDisable::Hold);
    }));
    b.duty(50.0).enable().at(10.0).disable().at(11.0);
    b.duty(0.0).enable().at(100.0);
    assert_eq!(b.wave(), "H@0 L@40");
    assert!(b
        .notes()
        .iter()
        .all(|(_, e)| !matches!(e, Event::Missed { .. })));
}

#[test]
fn en_toggling_never_shortens_the_break_below_min_off_000_002() {
    // 000/002: EN's falling edge acts at once; a rising edge starts the on phase only once the
    // break since the last real fall has lasted min off (relay 500 ms).
    let relay = with(|p| {
        p.period_ms = 2000;
        p.output_kind = OutputKind::Relay;
        p.min_on_ms = 500;
    });
    let mut b = Bench::new(relay);
    b.duty(50.0)
        .enable()
        .at(100.0)
        .disable()
        .at(101.0)
        .enable()
        .at(3000.0);
    assert_eq!(b.wave(), "H@0 L@100 H@600 L@1600 H@2600");
    // Forty toggles 5 ms apart: one pulse that runs its time, never a 5 ms phase.
    let mut b = Bench::new(relay);
    b.duty(50.0).enable();
    for k in 1..=40u32 {
        b.at(f64::from(k) * 5.0);
        if k % 2 == 1 {
            b.disable();
        } else {
            b.enable();
        }
    }
    b.at(1000.0);
    let edges = b.edges();
    assert_eq!(b.wave(), "H@0 L@5 H@505");
    for w in edges.windows(2) {
        if w[0].1 == Level::Low {
            assert!(w[1].0 - w[0].0 >= 500 * MS, "{}", b.wave());
        }
    }
}

#[test]
fn en_toggling_with_hold_never_shortens_the_break() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.on_disable = Some(OnDisable::Hold);
    }));
    // The break from 500 is held by a disable at 501 and the enable at 503 starts the next
    // period only once it has lasted 100 ms.
    b.duty(50.0)
        .enable()
        .at(501.0)
        .disable()
        .at(503.0)
        .enable()
        .at(1000.0);
    assert_eq!(b.wave(), "H@0 L@500 H@600");
}

#[test]
fn falling_enable_sets_output_0_at_once_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(80.0).enable().at(30.0).disable().at(500.0);
    assert_eq!(b.wave(), "H@0 L@30");
    assert_eq!(b.ch.poll_at(), None, "no deadlines while disabled");
}

#[test]
fn disable_hold_keeps_the_level_until_enabled_004() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 100;
        p.profile = Profile::FrequencyOutput;
    }));
    b.duty(80.0).enable().at(30.0).disable().at(500.0);
    assert_eq!(b.wave(), "H@0", "held high");
    b.duty(20.0).enable().at(650.0);
    assert_eq!(
        b.wave(),
        "H@0 L@520 H@600 L@620",
        "new period from the enable"
    );
}

#[test]
fn disabled_channel_still_computes_on_and_off_times_002() {
    let mut b = Bench::new(with(|p| p.period_ms = 10_000));
    b.duty(25.0);
    let s = b.status();
    assert!(!s.enabled && !s.active);
    assert_eq!((s.t_on, s.t_off), (2500 * MS, 7500 * MS));
    assert_eq!(s.duty_applied, 0.25);
    assert_eq!(b.wave(), "");
}

// ---- 1.2 minimum on and off times -------------------------------------------------------------

#[test]
fn suppress_pulse_below_me_gives_0_and_e1_000() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
    }));
    b.duty(5.0).enable().at(3000.0);
    assert_eq!(b.wave(), "", "050 ms < ME 100 ms: no pulse");
    assert!(b.notes().contains(&(
        0,
        Event::Flags {
            e1: true,
            limited: false
        }
    )));
    assert_eq!(b.status().rule, Rule::SuppressedPulse);
}

#[test]
fn suppress_break_below_min_off_gives_1_and_e1_000() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
    }));
    b.duty(95.0).enable().at(3000.0);
    assert_eq!(
        b.wave(),
        "H@0",
        "50 ms break < min off = ME: permanently on"
    );
    assert!(b.status().e1);
}

#[test]
fn e1_is_a_state_updated_every_period_and_reported_on_change_000() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
    }));
    b.duty(5.0)
        .enable()
        .at(500.0)
        .duty(50.0)
        .at(2500.0)
        .duty(5.0)
        .at(3500.0);
    let flags: Vec<_> = b
        .notes()
        .into_iter()
        .filter_map(|(t, e)| match e {
            Event::Flags { e1, .. } => Some((t / MS, e1)),
            _ => None,
        })
        .collect();
    assert_eq!(flags, vec![(0, true), (1000, false), (3000, true)]);
    assert_eq!(b.wave(), "H@1000 L@1500 H@2000 L@2500");
}

#[test]
fn stretch_raises_pulse_to_min_and_sets_limit_flag_002() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::TwincatBa;
    }));
    b.duty(5.0).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@100 H@1000 L@1100");
    let s = b.status();
    assert!(s.limited && s.e1);
    assert_eq!((s.t_on, s.t_off), (100 * MS, 900 * MS));
}

#[test]
fn zero_and_hundred_percent_are_exact_and_never_flag_002() {
    for profile in Profile::ALL {
        let mut b = Bench::new(with(|p| {
            p.period_ms = 1000;
            p.min_on_ms = 300;
            p.profile = profile;
        }));
        b.duty(0.0).enable().at(2500.0);
        assert_eq!(b.wave(), "", "{profile}");
        b.duty(100.0).at(4500.0);
        // 003 ends a break at once when the new command leaves no room for it.
        let expect = if profile == Profile::TcontCp {
            "H@2500"
        } else {
            "H@3000"
        };
        assert_eq!(b.wave(), expect, "{profile}");
        assert!(
            !b.notes()
                .iter()
                .any(|(_, e)| matches!(e, Event::Flags { .. })),
            "{profile}: no E1 or limit flag at 0 / 100 %"
        );
    }
}

#[test]
fn band_below_half_follows_004_truth_table() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::FrequencyOutput;
        p.edge_band = 0.2;
    }));
    b.duty(10.0).enable().at(1500.0);
    assert_eq!(b.wave(), "", "i_rIput < i_rEdge: FALSE");
    b.duty(50.0).at(2500.0);
    assert_eq!(b.wave(), "H@2000 L@2500", "inside the band: PWM");
    b.duty(90.0).at(4500.0);
    assert_eq!(b.wave(), "H@2000 L@2500 H@3000", "above 1 - i_rEdge: TRUE");
    assert!(!b.status().e1, "the band is a policy, not a minimum time");
}

#[test]
fn band_at_or_above_half_follows_004_truth_table() {
    // 004's worked example: TimeBase 1 s, edge 0.5, input 0.5 gives 500 ms TRUE, 500 ms FALSE.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::FrequencyOutput;
        p.edge_band = 0.5;
    }));
    b.command(Command::Fraction(0.5)).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000 L@1500", "edge 0.5, input 0.5");
    // Edge 0.7: an input below the edge is FALSE, one at the edge TRUE.
    b.params(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::FrequencyOutput;
        p.edge_band = 0.7;
    }))
    .at(2500.0);
    assert_eq!(
        b.wave(),
        "H@0 L@500 H@1000 L@1500",
        "input 0.5 < edge 0.7: FALSE"
    );
    b.command(Command::Fraction(0.7)).at(3500.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000 L@1500 H@3000");
}

#[test]
fn band_upper_boundary_is_pwm_as_written_004() {
    // 67 % at edge 0.33 lies exactly on 1 - edge: PWM, like 20 % at edge 0.2 on the lower one.
    for (pct, edge) in [
        (67.0, 0.33),
        (66.0, 0.34),
        (68.0, 0.32),
        (93.0, 0.07),
        (80.0, 0.2),
    ] {
        let mut b = Bench::new(with(|p| {
            p.period_ms = 1000;
            p.profile = Profile::FrequencyOutput;
            p.edge_band = edge;
        }));
        b.duty(pct).enable().at(999.0);
        let on = format!("L@{}", pct * 10.0);
        assert_eq!(b.wave(), format!("H@0 {on}"), "{pct} % at edge {edge}");
        assert_eq!(b.status().rule, Rule::Exact);
    }
}

// ---- 1.3 apply_at ------------------------------------------------------------------------------

#[test]
fn next_period_completes_the_running_period_000() {
    let mut b = Bench::new(with(|p| p.period_ms = 1000));
    b.duty(60.0).enable().at(100.0).duty(20.0).at(2500.0);
    assert_eq!(b.wave(), "H@0 L@600 H@1000 L@1200 H@2000 L@2200");
    // applied stays 60 % until the period ends
    let mut b = Bench::new(with(|p| p.period_ms = 1000));
    b.duty(60.0).enable().at(100.0).duty(20.0);
    let s = b.status();
    assert_eq!((s.duty_commanded, s.duty_applied), (0.2, 0.6));
}

#[test]
fn next_step_completes_the_running_step_with_its_latched_time_002() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.apply_at = Some(ApplyAt::NextStep);
    }));
    // On step latched at 60 % (600 ms); during it the command drops to 20 %: the on step still
    // runs 600 ms, then the off step takes the new off time, 800 ms.
    b.duty(60.0).enable().at(100.0).duty(20.0).at(2500.0);
    assert_eq!(b.wave(), "H@0 L@600 H@1400 L@1600 H@2400");
}

#[test]
fn immediate_extends_a_running_pulse_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::TcontCp;
    }));
    b.duty(30.0).enable().at(200.0).duty(50.0).at(1100.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000", "pulse extended to 500 ms");
}

#[test]
fn immediate_ends_a_running_pulse_now_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::TcontCp;
    }));
    b.duty(60.0).enable().at(400.0).duty(30.0).at(1100.0);
    // 400 ms already elapsed >= the new 300 ms: the pulse ends now; the break then lasts its
    // full new length, 700 ms.
    assert_eq!(b.wave(), "H@0 L@400 H@1100");
}

#[test]
fn immediate_never_ends_a_pulse_below_min_on_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::TcontCp;
    }));
    b.duty(60.0).enable().at(30.0).duty(0.0).at(500.0);
    assert_eq!(b.wave(), "H@0 L@100", "P_B_TM: the pulse lasts its minimum");
}

#[test]
fn immediate_extends_and_ends_a_break_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::TcontCp;
    }));
    // Break from 500 ms, 500 ms long. At 600 ms the command drops to 20 %: the break is
    // extended to 800 ms (until 1300).
    b.duty(50.0).enable().at(600.0).duty(20.0).at(1350.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1300");
    // During the next break (from 1500), the command rises to 90 %: the 100 ms break has
    // already passed at 1700, so it ends now and a pulse starts.
    b.at(1700.0).duty(90.0).at(1750.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1300 L@1500 H@1700");
}

#[test]
fn immediate_never_ends_a_break_below_min_off_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::TcontCp;
    }));
    b.duty(50.0).enable().at(520.0).duty(100.0).at(700.0);
    assert_eq!(b.wave(), "H@0 L@500 H@600");
}

#[test]
fn immediate_measures_the_break_from_the_real_last_edge_003() {
    // 003 compares the new times with "the previous impulse/break length". 5 % is suppressed
    // (50 ms < P_B_TM 100 ms), so the line has been low since 0; at 2100 ms the command
    // rises to 50 %: the break has lasted 2.1 s, so the impulse starts at once.
    let tcont = with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::TcontCp;
    });
    let mut b = Bench::new(tcont);
    b.duty(5.0).enable().at(2100.0).duty(50.0).at(3000.0);
    assert_eq!(b.wave(), "H@2100 L@2600");
}

#[test]
fn immediate_measures_the_impulse_from_the_real_last_edge_003() {
    // The mirror case: 95 % (break 50 ms < 100 ms suppressed) holds the line high from 0; at
    // 2100 ms 50 %: the impulse has lasted 2.1 s, so it ends at once.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::TcontCp;
    }));
    b.duty(95.0).enable().at(2100.0).duty(50.0).at(2700.0);
    assert_eq!(b.wave(), "H@0 L@2100 H@2600");
}

#[test]
fn immediate_counts_p_b_tm_from_the_real_last_edge_003() {
    // P_B_TM 300 ms: after 2 s low, 100 % at 2000.05 ms switches on at once; the minimum
    // break is counted from the real fall, not from the hidden period boundary at 2000 ms.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 300;
        p.profile = Profile::TcontCp;
    }));
    b.duty(5.0).enable().at(2000.05).duty(100.0).at(2500.0);
    assert_eq!(b.wave(), "H@2000.05");
}

// ---- 1.5 parameter changes --------------------------------------------------------------------

#[test]
fn period_change_takes_effect_at_the_next_boundary() {
    let mut b = Bench::new(with(|p| p.period_ms = 1000));
    b.duty(50.0)
        .enable()
        .at(100.0)
        .params(with(|p| p.period_ms = 200))
        .at(1500.0);
    assert_eq!(
        b.wave(),
        "H@0 L@500 H@1000 L@1100 H@1200 L@1300 H@1400 L@1500"
    );
    assert!(b.ch.pending_config().is_none());
}

#[test]
fn minimum_change_takes_effect_at_the_next_boundary() {
    let mut b = Bench::new(with(|p| p.period_ms = 1000));
    b.duty(5.0)
        .enable()
        .at(10.0)
        .params(with(|p| p.min_on_ms = 100))
        .at(2500.0);
    assert_eq!(
        b.wave(),
        "H@0 L@50",
        "the running period keeps its 50 ms pulse"
    );
    assert!(b.status().e1);
}

#[test]
fn immediate_policy_applies_a_parameter_change_at_once_003() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::TcontCp;
    }));
    b.duty(50.0).enable().at(100.0);
    b.params(with(|p| {
        p.period_ms = 400;
        p.profile = Profile::TcontCp;
    }))
    .at(700.0);
    assert_eq!(b.wave(), "H@0 L@200 H@400 L@600");
}

#[test]
fn watchdog_timeout_change_applies_at_once() {
    let mut b = Bench::new(with(|p| p.period_ms = 1000));
    b.duty(50.0).enable().at(100.0);
    b.params(with(|p| {
        p.period_ms = 1000;
        p.command_timeout_ms = 200;
    }))
    .at(300.0);
    assert_eq!(
        b.wave(),
        "H@0 L@200",
        "tripped 200 ms after the last command"
    );
}

// ---- watchdog ----------------------------------------------------------------------------------

#[test]
fn watchdog_forces_off_and_a_command_recovers() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.command_timeout_ms = 1500;
    }));
    b.duty(60.0).enable().at(1000.0).duty(60.0).at(2800.0);
    // last command at 1000 ms: trips at 2500 ms, mid-pulse (2000..2600): output off at once.
    assert_eq!(b.wave(), "H@0 L@600 H@1000 L@1600 H@2000 L@2500");
    assert!(b
        .notes()
        .contains(&(2500 * MS, Event::Watchdog { tripped: true })));
    let s = b.status();
    assert!(s.watchdog_tripped && !s.active);
    assert_eq!(s.duty_applied, 0.0);
    b.duty(60.0).at(3700.0);
    assert!(b
        .notes()
        .contains(&(2800 * MS, Event::Watchdog { tripped: false })));
    assert_eq!(
        b.wave(),
        "H@0 L@600 H@1000 L@1600 H@2000 L@2500 H@3000 L@3600",
        "resumes on the period grid"
    );
}

#[test]
fn enabling_with_a_stale_command_trips_at_once() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.command_timeout_ms = 500;
    }));
    b.duty(80.0).at(2000.0).enable().at(3000.0);
    assert_eq!(
        b.wave(),
        "",
        "the 2 s old command does not drive the heater"
    );
    assert!(b
        .notes()
        .contains(&(2000 * MS, Event::Watchdog { tripped: true })));
}

#[test]
fn watchdog_sleeps_while_disabled_and_off() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.command_timeout_ms = 500;
    }));
    b.duty(80.0).at(5000.0);
    assert!(!b
        .notes()
        .iter()
        .any(|(_, e)| matches!(e, Event::Watchdog { .. })));
}

#[test]
fn watchdog_switches_off_a_line_held_on_004() {
    // 004's hold keeps the line high while disabled; the watchdog covers every state in
    // which the line is high, so the held line goes off when commands stop.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.profile = Profile::FrequencyOutput;
        p.command_timeout_ms = 500;
    }));
    b.duty(80.0).enable().at(300.0).disable().at(5000.0);
    assert_eq!(b.wave(), "H@0 L@500");
    assert!(b
        .notes()
        .contains(&(500 * MS, Event::Watchdog { tripped: true })));
}

#[test]
fn a_held_line_goes_off_when_the_configuration_no_longer_holds_it() {
    let hold = with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.profile = Profile::FrequencyOutput;
    });
    // on_disable set to `off` while disabled and held high: off at once.
    let mut b = Bench::new(hold);
    b.duty(80.0).enable().at(300.0).disable().at(400.0);
    b.params(ChannelParams {
        on_disable: Some(OnDisable::Off),
        ..hold
    })
    .at(2000.0);
    assert_eq!(b.wave(), "H@0 L@400");
    // period 0 likewise, but never before the pulse has had its minimum on time.
    let mut b = Bench::new(hold);
    b.duty(80.0).enable().at(30.0).disable().at(40.0);
    b.params(ChannelParams {
        period_ms: 0,
        ..hold
    })
    .at(2000.0);
    assert_eq!(b.wave(), "H@0 L@100");
}

#[test]
fn the_watchdog_runs_the_fault_value_then_off_after_the_hold_time() {
    // Fault mode of PLC output modules: no command for 500 ms runs the channel at the fault
    // value (20 % of 1 s: frost protection) for fault_hold_ms 2.5 s, then off. The running
    // 80 % pulse is re-timed for 20 % at the trip as TCONT_CP re-times a new command: it has
    // been on for 500 ms, so it ends at once, and the break is the fault value's 800 ms.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.command_timeout_ms = 500;
        p.fault_duty_pct = 20.0;
        p.fault_hold_ms = 2500;
    }));
    b.duty(80.0).enable().at(5000.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1300 L@1500 H@2300 L@2500");
    assert!(b
        .notes()
        .contains(&(500 * MS, Event::Watchdog { tripped: true })));
    assert!(!b.status().fault_active, "off after the hold time");
    assert_eq!(b.status().duty_applied, 0.0);
    // Nothing after the hold time; a command recovers, from the next period (next_period),
    // and 500 ms later, with no command again, the fault value cuts that pulse to its 200 ms.
    b.duty(50.0).at(5900.0);
    assert_eq!(
        b.wave(),
        "H@0 L@500 H@1300 L@1500 H@2300 L@2500 H@5300 L@5500"
    );
}

#[test]
fn the_fault_value_keeps_the_minimum_times_and_runs_until_a_command() {
    // Fault hold 0: until the next command. 3 % of 1 s is below the 100 ms minimum: suppressed,
    // with E1, as any command would be.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.command_timeout_ms = 300;
        p.fault_duty_pct = 3.0;
    }));
    b.duty(50.0).enable().at(10_000.0);
    assert_eq!(b.wave(), "H@0 L@300");
    let s = b.status();
    assert!(s.fault_active && s.watchdog_tripped && s.e1, "{s:?}");
    assert_eq!(s.rule, Rule::SuppressedPulse);
    b.duty(50.0);
    assert!(!b.status().fault_active && !b.status().watchdog_tripped);
}

#[test]
fn a_pulse_running_at_the_trip_keeps_its_minimum_under_the_fault_value() {
    // The trip at 50 ms falls inside a pulse that has lasted 50 ms of its 100 ms minimum: the
    // fault value (10 % = 100 ms) ends it at its minimum, never below.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.command_timeout_ms = 50;
        p.fault_duty_pct = 10.0;
    }));
    b.duty(60.0).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@100 H@1000 L@1100");
}

// ---- late polling ------------------------------------------------------------------------------

#[test]
fn a_late_poll_merges_past_edges_and_reports_them() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(50.0).enable();
    // One poll 260 ms late: edges at 50, 100, 150, 200, 250 all lie in the past.
    let mut events = Vec::new();
    b.ch.poll(260 * MS, &mut |e| events.push(e));
    assert_eq!(
        events
            .iter()
            .filter(|e| matches!(e, Event::Edge { .. }))
            .count(),
        1
    );
    assert!(events.contains(&Event::Edge {
        at: 250 * MS,
        level: Level::Low
    }));
    assert!(events.contains(&Event::Missed { edges: 4 }));
    assert_eq!(b.ch.poll_at(), Some(300 * MS), "the grid is kept");
}

#[test]
fn a_late_edge_moves_the_next_one_so_the_break_keeps_its_minimum() {
    // Relay 200 ms at 50 %, minimum 50 ms: the fall due at 100 ms is written 58 ms late. The
    // rise due at 200 ms would leave a 42 ms break; it moves to 208 ms, and the grid resumes
    // (the pulse still ends at 300 ms).
    let mut b = Bench::new(with(|p| {
        p.period_ms = 200;
        p.output_kind = OutputKind::Relay;
    }));
    b.duty(50.0).enable().poll_late(158 * MS);
    assert_eq!(
        b.wave(),
        "H@0 L@100",
        "the fall is reported at its scheduled time"
    );
    b.at(201.0);
    assert_eq!(b.ch.poll_at(), Some(208 * MS), "held back to 158 + 50 ms");
    b.at(500.0);
    assert_eq!(b.wave(), "H@0 L@100 H@208 L@300 H@400 L@500");
}

#[test]
fn a_write_confirmed_late_moves_the_next_edge() {
    // The output thread says when the write really happened: a rise due at 0 that reached
    // the line at 60 us cannot be followed by a fall at 100 us (transistor floor 100 us).
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.command(Command::Percent(0.1)).enable();
    b.ch.edge_written(60_000);
    b.at(0.1);
    assert_eq!(b.ch.poll_at(), Some(160_000), "held back to 60 + 100 us");
    b.at(99.0);
    assert_eq!(b.edges(), vec![(0, Level::High), (160_000, Level::Low)]);
}

// ---- status ------------------------------------------------------------------------------------

#[test]
fn status_counts_down_the_running_step_002() {
    let mut b = Bench::new(with(|p| p.period_ms = 10_000));
    b.duty(30.0).enable().at(1000.0);
    let s = b.status();
    assert_eq!((s.remaining_on, s.remaining_off), (2000 * MS, 0));
    assert_eq!(s.remaining_at(2500 * MS), (500 * MS, 0));
    b.at(4000.0);
    let s = b.status();
    assert_eq!((s.remaining_on, s.remaining_off), (0, 6000 * MS));
    assert!(s.enabled && s.active);
    assert_eq!(s.level, Level::Low);
}

#[test]
fn relay_profile_limits_apply_000() {
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.output_kind = OutputKind::Relay;
    }));
    b.duty(3.0).enable().at(2000.0);
    assert_eq!(b.wave(), "", "30 ms < the relay's 50 ms floor: suppressed");
    assert!(b.status().e1);
}

#[test]
fn every_edge_is_logged_with_its_cause() {
    let mut b = Bench::new(with(|p| p.period_ms = 100));
    b.duty(50.0).enable().at(60.0).disable();
    let causes: Vec<_> = b
        .log
        .iter()
        .filter(|l| matches!(l.event, Event::Edge { .. }))
        .map(|l| l.cause)
        .collect();
    assert_eq!(causes, vec![Cause::Enable, Cause::Deadline]);
}

#[test]
fn restarting_pulses_from_period_zero_keeps_the_minimum_break() {
    let p100 = with(|p| {
        p.period_ms = 100;
        p.min_on_ms = 20;
    });
    let p0 = ChannelParams {
        period_ms: 0,
        ..p100
    };
    let mut b = Bench::new(p100);
    // 100 %: constant on; period 0 takes effect at the 100 ms boundary and drops the output.
    b.duty(100.0).enable().at(20.0).params(p0).at(105.0);
    assert_eq!(b.wave(), "H@0 L@100");
    // 5 ms later pulses are asked for again: the output waits for the 20 ms minimum break.
    b.params(p100).at(300.0);
    assert_eq!(b.wave(), "H@0 L@100 H@120");
}

#[test]
fn the_estop_cuts_a_pulse_at_once_and_holds_the_line_low_while_latched() {
    // A 300 ms minimum on time does not hold the e-stop back: the line goes low at once (a
    // safety off, as a falling EN). While latched, commands, enables and the fault value are
    // taken and reported, but no rise reaches the line.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 300;
        p.min_off_ms = Some(200);
        p.command_timeout_ms = 1500;
        p.fault_duty_pct = 50.0;
    }));
    b.duty(50.0).enable().at(100.0);
    b.estop(true);
    assert_eq!(b.wave(), "H@0 L@100");
    assert!(b.ch.estopped() && !b.status().enabled);
    b.enable().duty(80.0).at(5000.0);
    let s = b.status();
    assert!(s.enabled && s.estopped && !s.active, "{s:?}");
    assert!(
        s.watchdog_tripped,
        "the watchdog ran (its fault value held back)"
    );
    assert_eq!(
        b.wave(),
        "H@0 L@100",
        "nothing reached the line while latched"
    );
}

#[test]
fn after_an_estop_release_nothing_switches_on_until_a_fresh_enable() {
    let params = with(|p| {
        p.period_ms = 1000;
        p.min_off_ms = Some(400);
    });
    let mut b = Bench::new(params);
    b.duty(50.0).enable().at(100.0);
    b.estop(true).at(150.0); // latched at 100 ms
    b.enable().at(200.0); // an enable while latched is taken
    b.estop(false).at(3000.0); // released at 200 ms
    assert!(
        !b.status().enabled,
        "the release leaves the channel disabled"
    );
    assert_eq!(b.wave(), "H@0 L@100");
    b.enable().at(3600.0); // a fresh enable at 3000 ms runs it
    assert_eq!(b.wave(), "H@0 L@100 H@3000 L@3500");

    // Released and enabled at once: the first pulse waits out the 400 ms minimum break since
    // the line's real fall at 100 ms, whatever the e-stop did in between.
    let mut b = Bench::new(params);
    b.duty(50.0).enable().at(100.0);
    b.estop(true).at(150.0);
    b.estop(false).enable().at(1000.0);
    assert_eq!(b.wave(), "H@0 L@100 H@500 L@1000");
}

#[test]
fn a_held_line_stays_low_while_the_schedule_runs_and_follows_it_when_live() {
    // A managed node's INACTIVE state: the channel is enabled and commanded, its schedule runs
    // and is reported, but the line stays low. Activated at 1250 ms, inside an on step that
    // ends at 1500 ms: the held rise goes out at once (the minimum break since the line's
    // last fall has long passed), and from then on the line follows the grid.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 1000;
        p.min_off_ms = Some(100);
    }));
    b.live(false).duty(50.0).enable().at(1250.0);
    assert_eq!(b.wave(), "");
    let s = b.status();
    assert!(s.enabled && !s.active, "{s:?}");
    b.live(true).at(2600.0);
    assert_eq!(b.wave(), "H@1250 L@1500 H@2000 L@2500");
    // Deactivated inside a pulse: off at once, whatever its minimum on time.
    b.duty(90.0).at(3100.0);
    b.live(false).at(4000.0);
    assert_eq!(b.wave(), "H@1250 L@1500 H@2000 L@2500 H@3000 L@3100");
}

// ---- protections of the load -----------------------------------------------------------------

#[test]
fn max_on_cuts_a_line_stuck_at_100_percent_and_keeps_it_off_for_min_off() {
    // A controller stuck at 100 %: the line goes off after max_on_ms 2.5 s for its 100 ms
    // minimum break, then on again, and so on. E1 and the limit flag say so from the start
    // (100 % cannot be delivered), unlike a plain 100 %.
    let mut b = Bench::new(with(|p| {
        p.min_on_ms = 100;
        p.max_on_ms = 2500;
    }));
    b.duty(100.0).enable().at(5500.0);
    assert_eq!(b.wave(), "H@0 L@2500 H@2600 L@5100 H@5200");
    assert!(b.notes().contains(&(
        0,
        Event::Flags {
            e1: true,
            limited: true
        }
    )));
    let s = b.status();
    assert!(s.e1 && s.limited && s.protections.max_on, "{s:?}");
    assert_eq!(s.protections.names().collect::<Vec<_>>(), ["max_on"]);
    // 50 % from the next period: the pulses fit, but E1 stays for the period after the last
    // cut (at 5100 ms, in the period from 5000 ms) and clears at 7000 ms.
    b.duty(50.0).at(7900.0);
    assert_eq!(
        b.wave(),
        "H@0 L@2500 H@2600 L@5100 H@5200 L@6500 H@7000 L@7500"
    );
    assert!(b.notes().contains(&(
        7000 * MS,
        Event::Flags {
            e1: false,
            limited: false
        }
    )));
    assert!(!b.status().protections.max_on);
}

#[test]
fn max_on_cuts_a_pulse_longer_than_itself_inside_the_period() {
    // 90 % of 10 s is a 9 s pulse; max_on_ms 3 s cuts it, the 500 ms minimum break follows,
    // and the schedule's own fall at 9 s ends the last piece.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 10_000;
        p.min_on_ms = 500;
        p.max_on_ms = 3000;
    }));
    b.duty(90.0).enable().at(10_500.0);
    assert_eq!(b.wave(), "H@0 L@3000 H@3500 L@6500 H@7000 L@9000 H@10000");
    assert!(b.status().e1);
    assert!(
        !b.notes()
            .iter()
            .any(|(_, e)| matches!(e, Event::Missed { .. })),
        "a cut is not a missed edge"
    );
}

#[test]
fn max_on_leaves_pulses_within_it_alone() {
    let mut b = Bench::new(with(|p| p.max_on_ms = 600));
    b.duty(50.0).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000 L@1500");
    let s = b.status();
    assert!(!s.e1 && !s.limited && !s.protections.any(), "{s:?}");
}

#[test]
fn max_on_counts_from_the_real_rise() {
    // The rise reached the line 30 ms late: the cut comes 2.5 s after that, not after the
    // scheduled rise.
    let mut b = Bench::new(with(|p| p.max_on_ms = 2500));
    b.duty(100.0).enable();
    b.ch.edge_written(30 * MS);
    b.at(2600.0);
    assert_eq!(b.wave(), "H@0 L@2530 H@2530.1");
}

#[test]
fn max_on_switches_off_a_line_held_on_for_good_004() {
    // 004's hold keeps the line on after a disable; max_on_ms still cuts it, and with the
    // channel disabled nothing switches it on again.
    let mut b = Bench::new(with(|p| {
        p.profile = Profile::FrequencyOutput;
        p.max_on_ms = 2500;
    }));
    b.duty(100.0).enable().at(500.0).disable().at(10_000.0);
    assert_eq!(b.wave(), "H@0 L@2500");
}

#[test]
fn a_shorter_max_on_cuts_a_long_run_when_it_comes_into_force() {
    // Set while the line has been on for 3.2 s: it takes effect at the next period boundary
    // (next_period), and the line has been on longer than 1 s by then: it goes off there.
    let mut b = Bench::new(p());
    b.duty(100.0).enable().at(3200.0);
    b.params(with(|p| p.max_on_ms = 1000)).at(4500.0);
    assert_eq!(b.wave(), "H@0 L@4000 H@4000.1");
}

#[test]
fn max_duty_limits_the_command_before_the_minimum_time_rules() {
    // A heater's maximum power: 100 % commanded, 60 % applied; no E1, the plan is exact.
    let mut b = Bench::new(with(|p| p.max_duty_pct = 60.0));
    b.duty(100.0).enable().at(1700.0);
    assert_eq!(b.wave(), "H@0 L@600 H@1000 L@1600");
    let s = b.status();
    assert_eq!(
        (s.duty_commanded, s.duty_target, s.duty_applied),
        (1.0, 0.6, 0.6)
    );
    assert!(s.protections.max_duty && !s.e1, "{s:?}");
    // The minimum-time rules act on the limited duty: 95 % leaves a 50 ms break, below the
    // 100 ms minimum, so suppress keeps the line on for the period, with E1.
    let mut b = Bench::new(with(|p| {
        p.min_on_ms = 100;
        p.max_duty_pct = 95.0;
    }));
    b.duty(100.0).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0");
    assert_eq!(b.status().rule, Rule::SuppressedBreak);
}

#[test]
fn min_duty_raises_small_commands_and_zero_unless_zero_means_zero() {
    let mut b = Bench::new(with(|p| p.min_duty_pct = 20.0));
    b.duty(5.0).enable().at(1500.0);
    assert_eq!(b.wave(), "H@0 L@200 H@1000 L@1200");
    assert!(b.status().protections.min_duty);
    // 0 % is raised too (the load keeps its minimum while enabled)...
    b.duty(0.0).at(2500.0);
    assert_eq!(b.wave(), "H@0 L@200 H@1000 L@1200 H@2000 L@2200");
    // ...unless zero_means_zero: then 0 % is off, and 5 % is still 20 %.
    let mut b = Bench::new(with(|p| {
        p.min_duty_pct = 20.0;
        p.zero_means_zero = true;
    }));
    b.duty(0.0).enable().at(1500.0);
    assert_eq!(b.wave(), "");
    assert!(!b.status().protections.any());
    b.duty(5.0).at(2500.0);
    assert_eq!(b.wave(), "H@2000 L@2200");
    // The minimum-time rules act on the raised duty: 20 % of 100 ms is 20 ms < 30 ms.
    let mut b = Bench::new(with(|p| {
        p.period_ms = 100;
        p.min_on_ms = 30;
        p.min_duty_pct = 20.0;
    }));
    b.duty(1.0).enable().at(250.0);
    assert_eq!(b.wave(), "");
    assert_eq!(b.status().rule, Rule::SuppressedPulse);
}

#[test]
fn the_fault_value_is_limited_by_max_duty_too() {
    let mut b = Bench::new(with(|p| {
        p.command_timeout_ms = 1500;
        p.fault_duty_pct = 80.0;
        p.max_duty_pct = 50.0;
    }));
    b.duty(30.0).enable().at(1600.0);
    let s = b.status();
    assert!(s.fault_active, "{s:?}");
    assert_eq!((s.duty_applied, s.t_on), (0.5, 500 * MS));
}

/// 25 % over 10 s at a 1 s period.
fn avg_capped(f: impl FnOnce(&mut ChannelParams)) -> ChannelParams {
    with(|p| {
        p.avg_duty_limit_pct = 25.0;
        p.avg_window_s = 10;
        f(p);
    })
}

#[test]
fn avg_duty_caps_the_on_time_of_every_window_and_recovers_as_it_slides() {
    const S: u64 = 1000 * MS;
    let mut b = Bench::new(avg_capped(|_| ()));
    b.duty(100.0).enable().at(2200.0);
    // The budget (2.5 s) runs out in the third period: its on phase is the rest of it.
    assert_eq!(b.status().t_on, 500 * MS);
    b.at(5000.0);
    assert_eq!(b.wave(), "H@0 L@2500");
    let s = b.status();
    assert!(s.protections.avg_duty && !s.e1, "{s:?}");
    assert_eq!(s.protections.names().collect::<Vec<_>>(), ["avg_duty"]);
    assert_eq!((s.duty_target, s.duty_applied, s.t_on), (1.0, 0.0, 0));
    assert_eq!(s.avg_duty, 0.25);
    // Off until on time leaves the window; then on again, and never more than 2.5 s in any
    // window of 10 s.
    b.at(10_500.0);
    assert_eq!(b.wave(), "H@0 L@2500");
    b.at(120_000.0);
    let (most, _) = b.max_window_on(10 * S);
    assert!(most <= 2500 * MS, "{} ms in 10 s: {}", most / MS, b.wave());
    assert!(b.on_time(10 * S, 12 * S) > 0, "{}", b.wave());
    // Conservative, but not by much: the budget is released at period starts, so about one
    // period of each window is lost (2.5 s per 11 s).
    let avg = b.on_time(20 * S, 120 * S) as f64 / (100 * S) as f64;
    assert!((0.22..=0.25).contains(&avg), "{avg}");
    // The cap limits the duty applied, not the command in force.
    assert_eq!(b.status().duty_target, 1.0);
}

#[test]
fn a_command_within_the_avg_duty_budget_runs_as_it_is() {
    let mut b = Bench::new(avg_capped(|_| ()));
    b.duty(20.0).enable().at(30_500.0);
    let mut free = Bench::new(p());
    free.duty(20.0).enable().at(30_500.0);
    assert_eq!(b.edges(), free.edges());
    let s = b.status();
    assert!(!s.protections.any(), "{s:?}");
    assert!((0.19..=0.21).contains(&s.avg_duty), "{}", s.avg_duty);
}

#[test]
fn a_minimum_time_rule_never_takes_the_line_past_the_avg_duty_budget() {
    // 0.5 s are left in the third period, but stretch would raise that to the 600 ms minimum:
    // the period is off instead.
    let mut b = Bench::new(avg_capped(|p| {
        p.min_on_ms = 600;
        p.short_pulse = Some(crate::core::ShortPulse::Stretch);
    }));
    b.duty(100.0).enable().at(3500.0);
    assert_eq!(b.wave(), "H@0 L@2000");
    assert!(b.status().protections.avg_duty);
    b.at(60_000.0);
    assert!(b.max_window_on(10_000 * MS).0 <= 2500 * MS, "{}", b.wave());
}

#[test]
fn the_fault_value_is_capped_by_avg_duty_too() {
    let mut b = Bench::new(avg_capped(|p| {
        p.command_timeout_ms = 500;
        p.fault_duty_pct = 100.0;
        p.avg_window_s = 4;
    }));
    b.duty(0.0).enable().at(30_000.0);
    assert!(b.status().fault_active);
    assert!(b.on_time(0, 30_000 * MS) > 0);
    assert!(b.max_window_on(4000 * MS).0 <= 1000 * MS, "{}", b.wave());
}

#[test]
fn avg_duty_holds_under_next_step_and_immediate() {
    for apply_at in [ApplyAt::NextStep, ApplyAt::Immediate] {
        let mut b = Bench::new(avg_capped(|p| {
            p.apply_at = Some(apply_at);
            p.period_ms = 300;
        }));
        b.duty(70.0).enable();
        for i in 0..40 {
            b.at(1000.0 * i as f64 + 130.0)
                .duty(if i % 2 == 0 { 100.0 } else { 40.0 });
        }
        b.at(50_000.0);
        let (most, end) = b.max_window_on(10_000 * MS);
        assert!(
            most <= 2500 * MS,
            "{apply_at:?}: {} ms up to {} ms",
            most / MS,
            end / MS
        );
    }
}

#[test]
fn slew_ramps_the_duty_from_each_enable_soft_start() {
    // 10 %/s at T = 1 s: the duty applied rises 10 % a period toward 35 %, from 0 at the
    // enable, and falls the same way; exact in virtual time.
    let mut b = Bench::new(with(|p| p.duty_slew_pct_per_s = 10.0));
    b.duty(35.0).enable().at(2500.0);
    let s = b.status();
    assert!(s.protections.slew, "{s:?}");
    assert_eq!((s.duty_target, s.duty_applied), (0.35, 0.2));
    b.at(5500.0);
    assert_eq!(
        b.wave(),
        "H@1000 L@1100 H@2000 L@2200 H@3000 L@3300 H@4000 L@4350 H@5000 L@5350"
    );
    assert!(!b.status().protections.slew);
    b.duty(5.0).at(8500.0);
    assert_eq!(
        &b.wave()[b.wave().find("H@6000").unwrap()..],
        "H@6000 L@6250 H@7000 L@7150 H@8000 L@8050"
    );
    // A disable is a safety off, at once; the next enable ramps from 0 again.
    b.at(9020.0)
        .duty(35.0)
        .disable()
        .at(10_000.0)
        .enable()
        .at(12_500.0);
    assert_eq!(
        &b.wave()[b.wave().find("H@9000").unwrap()..],
        "H@9000 L@9020 H@11000 L@11100 H@12000 L@12200"
    );
}

#[test]
fn a_change_inside_the_dead_band_is_ignored() {
    // Relay wear: with a 5 % band, 53 % after 50 % changes nothing; 56 % does. A change of
    // exactly the band passes, as do 0 % and the maximum.
    let mut b = Bench::new(with(|p| p.duty_deadband_pct = 5.0));
    b.duty(50.0).enable().at(500.0);
    b.duty(53.0).at(1600.0);
    assert_eq!(b.wave(), "H@0 L@500 H@1000 L@1500");
    let s = b.status();
    assert_eq!((s.duty_commanded, s.duty_target), (0.53, 0.5));
    assert!(s.protections.deadband && s.ignored_commands == 1, "{s:?}");
    b.duty(56.0).at(2600.0);
    assert!(!b.status().protections.deadband);
    // 52 % is 4 % away: ignored; 51 % is exactly the band: taken.
    b.duty(52.0).duty(51.0).at(3600.0);
    assert_eq!(b.status().ignored_commands, 2);
    // 47 % is ignored; 0 % always passes.
    b.duty(47.0).duty(0.0).at(4600.0);
    assert_eq!(
        b.wave(),
        "H@0 L@500 H@1000 L@1500 H@2000 L@2560 H@3000 L@3510"
    );
    assert_eq!(b.status().ignored_commands, 3);
    // 2 % is ignored; 100 % (the maximum) always passes.
    b.duty(2.0).duty(100.0).at(5500.0);
    assert_eq!(b.status().ignored_commands, 4);
    assert!(b.wave().ends_with("L@3510 H@5000"), "{}", b.wave());
}

#[test]
fn an_ignored_command_still_feeds_the_watchdog() {
    let mut b = Bench::new(with(|p| {
        p.duty_deadband_pct = 5.0;
        p.command_timeout_ms = 1000;
    }));
    b.duty(50.0).enable().at(800.0).duty(51.0).at(2000.0);
    let trips: Vec<_> = b
        .notes()
        .into_iter()
        .filter(|(_, e)| *e == Event::Watchdog { tripped: true })
        .map(|(t, _)| t)
        .collect();
    assert_eq!(trips, [1800 * MS]);
}

#[test]
fn slew_ramps_again_when_pulses_restart_from_period_zero() {
    // Period 0 holds the line off; when a period is set again the ramp starts there, not
    // from the time the pulses stopped.
    let mut b = Bench::new(with(|p| p.duty_slew_pct_per_s = 50.0));
    b.duty(100.0).enable().at(3500.0);
    assert_eq!(b.wave(), "H@1000 L@1500 H@2000");
    b.params(with(|p| {
        p.period_ms = 0;
        p.duty_slew_pct_per_s = 50.0;
    }))
    .at(10_000.0);
    b.params(with(|p| p.duty_slew_pct_per_s = 50.0))
        .at(12_600.0);
    assert_eq!(
        b.wave(),
        "H@1000 L@1500 H@2000 L@4000 H@11000 L@11500 H@12000"
    );
}

// ---- cycle extension -------------------------------------------------------------------------

/// 1 s period, 100 ms minimum on and off time, `extend`.
fn extending(f: impl FnOnce(&mut ChannelParams)) -> ChannelParams {
    with(|p| {
        p.period_ms = 1000;
        p.min_on_ms = 100;
        p.short_pulse = Some(crate::core::ShortPulse::Extend);
        f(p);
    })
}

#[test]
fn extend_grows_the_period_so_a_short_pulse_is_exactly_min_on() {
    // 5 % of 1 s is a 50 ms pulse, below the 100 ms minimum: the period grows to
    // 100 ms / 0.05 = 2 s, the pulse is exactly 100 ms, the duty is 5 % as commanded.
    let mut b = Bench::new(extending(|_| {}));
    b.duty(5.0).enable().at(6500.0);
    assert_eq!(
        b.wave(),
        "H@0 L@100 H@2000 L@2100 H@4000 L@4100 H@6000 L@6100"
    );
    assert_eq!(b.on_time(0, 6000 * MS), 300 * MS, "5 % of 6 s");
    let s = b.status();
    assert_eq!(s.rule, Rule::ExtendedPulse);
    assert_eq!(
        (s.period, s.t_on, s.t_off),
        (2000 * MS, 100 * MS, 1900 * MS)
    );
    assert_eq!(s.duty_applied, 0.05);
    // The duty is delivered: no E1; the limit flag says a minimum time set the period.
    assert!(!s.e1 && s.limited, "{s:?}");
    assert_eq!(
        b.notes(),
        vec![(
            0,
            Event::Flags {
                e1: false,
                limited: true
            }
        )]
    );
}

#[test]
fn extend_grows_the_period_so_a_short_break_is_exactly_min_off() {
    let mut b = Bench::new(extending(|_| {}));
    b.duty(95.0).enable().at(4500.0);
    assert_eq!(b.wave(), "H@0 L@1900 H@2000 L@3900 H@4000");
    let s = b.status();
    assert_eq!((s.rule, s.period), (Rule::ExtendedBreak, 2000 * MS));
    assert!(!s.e1 && s.limited);
}

#[test]
fn extend_holds_both_minima_where_no_period_could_000() {
    // PD 150 ms, ME 100 ms (000's relay table): suppress gives 0 or 1 for every duty. Extended,
    // 40 % is 100 ms on / 150 ms off and 60 % 150 ms on / 100 ms off.
    let relay = |p: &mut ChannelParams| {
        p.period_ms = 150;
        p.output_kind = OutputKind::Relay;
    };
    let mut b = Bench::new(extending(relay));
    b.duty(40.0).enable().at(500.0);
    assert_eq!(b.wave(), "H@0 L@100 H@250 L@350 H@500");
    let mut b = Bench::new(extending(relay));
    b.duty(60.0).enable().at(500.0);
    assert_eq!(b.wave(), "H@0 L@150 H@250 L@400 H@500");
    let mut b = Bench::new(with(|p| {
        relay(p);
        p.min_on_ms = 100;
    }));
    b.duty(40.0).enable().at(500.0);
    assert_eq!(b.wave(), "", "suppress: the 60 ms pulse is dropped");
}

#[test]
fn extend_beyond_extend_max_suppresses_with_e1() {
    // 1 % needs 100 ms / 0.01 = 10 s: allowed at extend_max 10 (the default), not at 5.
    let mut b = Bench::new(extending(|_| {}));
    b.duty(1.0).enable().at(10_500.0);
    assert_eq!(b.wave(), "H@0 L@100 H@10000 L@10100");
    assert!(!b.status().e1);
    let mut b = Bench::new(extending(|p| p.extend_max = 5.0));
    b.duty(1.0).enable().at(10_500.0);
    assert_eq!(b.wave(), "");
    let s = b.status();
    assert_eq!((s.rule, s.period), (Rule::SuppressedPulse, 1000 * MS));
    assert!(s.e1 && !s.limited);
    // 3 % needs 3.33 s: within 5 x.
    b.duty(3.0).at(16_000.0);
    assert_eq!(b.wave(), "H@11000 L@11100 H@14333.3333 L@14433.3333");
}

#[test]
fn an_extended_period_completes_before_a_new_command_000() {
    // next_period: a command during an extended period takes effect at its end, and the
    // period returns to 1 s once the pulse is long enough.
    let mut b = Bench::new(extending(|_| {}));
    b.duty(5.0).enable().at(500.0).duty(50.0).at(3700.0);
    assert_eq!(b.wave(), "H@0 L@100 H@2000 L@2500 H@3000 L@3500");
    let s = b.status();
    assert_eq!(
        (s.rule, s.period, s.limited),
        (Rule::Exact, 1000 * MS, false)
    );
    assert!(b.notes().contains(&(
        2000 * MS,
        Event::Flags {
            e1: false,
            limited: false
        }
    )));
}

#[test]
fn a_trip_keeps_the_extended_period_grid() {
    // 16 % with a 400 ms minimum extends the period to 2.5 s. The watchdog trips inside the
    // first pulse: off at once for the rest of that extended period, so commands from 1.2 s
    // on restart the pulses at 2.5 s, not on the 1 s grid.
    let mut b = Bench::new(extending(|p| {
        p.min_on_ms = 400;
        p.command_timeout_ms = 300;
    }));
    b.duty(16.0).enable().at(1200.0);
    for t in [
        1200.0, 1400.0, 1600.0, 1800.0, 2000.0, 2200.0, 2400.0, 2600.0, 2800.0,
    ] {
        b.at(t).duty(16.0);
    }
    b.at(3000.0);
    assert_eq!(b.wave(), "H@0 L@300 H@2500 L@2900");
}

#[test]
fn extend_is_off_by_default() {
    let mut b = Bench::new(with(|p| p.min_on_ms = 100));
    b.duty(5.0).enable().at(3000.0);
    assert_eq!(b.wave(), "");
    assert_eq!(b.status().period, 1000 * MS);
    assert_eq!(
        crate::core::ChannelConfig::default().params.extend_max,
        10.0
    );
}
