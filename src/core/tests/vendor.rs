//! The last vendor details, each against its document's sentence.

use super::harness::{Bench, MS};
use crate::core::{
    ApplyAt, ChannelParams, Command, ConfigError, Level, MinTime, OutputKind, Profile,
};

#[test]
fn the_status_shows_the_times_the_input_gives_beside_those_in_force_002() {
    // 002: fActTiOn / fActTiOff are "continuously calculated" from the input, while "the on-
    // or off-step is completed with the calculated time, irrespective of whether the
    // pulse/pause ratio changes in the meantime".
    let mut b = Bench::new(ChannelParams {
        profile: Profile::TwincatBa,
        ..ChannelParams::default()
    });
    assert_eq!(b.ch.config().apply_at, ApplyAt::NextStep);
    b.duty(30.0).enable().at(100.0).duty(60.0);
    let s = b.status();
    assert_eq!((s.t_on, s.t_off), (300 * MS, 700 * MS), "the step in force");
    assert_eq!(
        (s.t_on_input, s.t_off_input),
        (600 * MS, 400 * MS),
        "the input's"
    );
    // The on step ends with its latched 300 ms; the off step takes the new input's time.
    b.at(1000.0);
    assert_eq!(b.wave(), "H@0 L@300 H@700");
    let s = b.status();
    assert_eq!((s.t_off, s.t_off_input), (400 * MS, 400 * MS));
    // Disabled, the block still calculates them (002: "Only the switch-on and switch-off times
    // are continuously calculated and displayed").
    b.disable().command(Command::Fraction(0.25));
    let s = b.status();
    assert_eq!((s.t_on_input, s.t_off_input), (250 * MS, 750 * MS));
}

#[test]
fn twincat_ba_limits_a_minimum_of_any_size_to_the_period_002() {
    // 002: nMinSwiTi "Internally limited to values between 0 and nPrd".
    for min_on_ms in [1500, 3_600_000, 3_600_001, 1 << 40, u64::MAX] {
        let c = ChannelParams {
            period_ms: 1000,
            min_on_ms,
            profile: Profile::TwincatBa,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        assert_eq!(c.min_on, 1000 * MS, "{min_on_ms}");
    }
    // With no period to limit it to, an hour.
    let c = ChannelParams {
        period_ms: 0,
        min_on_ms: u64::MAX,
        profile: Profile::TwincatBa,
        ..ChannelParams::default()
    }
    .validate()
    .unwrap();
    assert_eq!(c.min_on, 3_600_000 * MS);
    // Elsewhere above an hour is still refused, with its reason.
    assert_eq!(
        ChannelParams {
            min_on_ms: 3_600_001,
            ..ChannelParams::default()
        }
        .validate(),
        Err(ConfigError::MinTimeTooLong {
            which: MinTime::On,
            value_ms: 3_600_001,
            max_ms: 3_600_000
        })
    );
}

#[test]
fn schneider_pwm_t_mini_is_a_minimum_pulse_only_001() {
    // 001: "the user is able to define a minimum pulse that is greater using the T_MINI
    // parameter": an unset min_off_ms is the hardware floor, not a copy of min_on_ms.
    let c = ChannelParams {
        min_on_ms: 30,
        profile: Profile::SchneiderPwm,
        ..ChannelParams::default()
    }
    .validate()
    .unwrap();
    assert_eq!((c.min_on, c.min_off), (30 * MS, 100_000));
    let c = ChannelParams {
        min_on_ms: 300,
        output_kind: OutputKind::Relay,
        profile: Profile::SchneiderPwm,
        ..ChannelParams::default()
    }
    .validate()
    .unwrap();
    assert_eq!(c.min_off, 50 * MS, "the relay floor");
    // 95 % of 1 s is a 50 ms break: kept, where a 30 ms minimum break would drop it.
    let mut b = Bench::new(ChannelParams {
        min_on_ms: 30,
        profile: Profile::SchneiderPwm,
        ..ChannelParams::default()
    });
    b.duty(95.0).enable().at(1000.0);
    assert_eq!(b.wave(), "H@0 L@950 H@1000");
    // Set explicitly, it is kept.
    let c = ChannelParams {
        min_on_ms: 30,
        min_off_ms: Some(30),
        profile: Profile::SchneiderPwm,
        ..ChannelParams::default()
    }
    .validate()
    .unwrap();
    assert_eq!(c.min_off, 30 * MS);
}

#[test]
fn a_rising_enable_at_100_percent_waits_for_the_minimum_break_a_departure_from_002() {
    // 002 on a rising bEn at 0 or 100 %: "The minimum switching time is deactivated for these
    // two cases". The node keeps the rules off the duty (a constant 1, no E1) but not off the
    // line: no break on the line is shorter than its minimum, so the line rises once the break
    // since the last real fall has lasted min off (docs/time-base.md says so).
    let mut b = Bench::new(ChannelParams {
        period_ms: 1000,
        min_on_ms: 200,
        min_off_ms: Some(200),
        profile: Profile::TwincatBa,
        ..ChannelParams::default()
    });
    b.duty(50.0).enable().at(300.0).disable().at(350.0);
    b.duty(100.0).enable().at(1000.0);
    assert_eq!(b.wave(), "H@0 L@300 H@500");
    assert_eq!(b.edges()[2], (500 * MS, Level::High));
    assert!(!b.status().e1);
}
