use super::*;
use crate::core::{ChannelConfig, MinTime, OutputKind};
use crate::output::{Backend, GpioLine, OutputSpec};
use crate::ros::interface::msg;
use ParameterValue as V;

fn sv(name: &str, value: V) -> StartValue {
    StartValue {
        name: name.into(),
        value,
        origin: "-p".into(),
    }
}

fn item(name: &str, value: V) -> (String, V) {
    (name.into(), value)
}

/// Checks setting `name` to `value` while the node runs.
fn live(s: &ParamStore, name: &str, value: V) -> Result<Accepted, ParamError> {
    s.check(&[item(name, value)], Stage::Live)
}

#[test]
fn declares_node_and_channel_parameters_with_defaults() {
    let s = ParamStore::new(2);
    assert_eq!(s.node().channels, 2);
    assert_eq!(s.get("pw01.period_ms"), Some(V::Integer(1000)));
    assert_eq!(s.channel(1).unwrap().min_off_ms, -1);
    assert_eq!(s.channel(1).unwrap().profile, "pico_gfx");
    assert_eq!(s.get("pw03.period_ms"), None);
    assert!(s.channel(2).is_none());
    assert_eq!(s.channel_config(0).unwrap(), ChannelConfig::default());
    let d = s.descriptor("pw01.period_ms").unwrap().to_raw();
    assert_eq!(d.r#type, raw::ParameterType::INTEGER);
    assert_eq!(d.integer_range[0].to_value, 3_600_000);
    assert!(!d.description.is_empty() && !d.read_only);
    assert!(s.descriptor("pw01.active_low").unwrap().read_only);
    let d = s.descriptor("pw01.edge_band").unwrap().to_raw();
    assert_eq!(d.floating_point_range[0].to_value, 1.0);
}

#[test]
fn coercion_is_lossless_or_refused() {
    let s = ParamStore::new(1);
    let a = live(&s, "pw01.period_ms", V::Double(500.0)).unwrap();
    assert_eq!(a.changes, vec![item("pw01.period_ms", V::Integer(500))]);
    assert_eq!(
        a.notes,
        vec!["pw01.period_ms: double 500.0 taken as integer 500"]
    );
    let a = live(&s, "pw01.edge_band", V::Integer(1)).unwrap();
    assert_eq!(a.changes, vec![item("pw01.edge_band", V::Double(1.0))]);
    let e = live(&s, "pw01.period_ms", V::Double(500.5)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `pw01.period_ms` is an integer; 500.5 is not a whole number"
    );
    let e = live(&s, "pw01.period_ms", V::String("500".into())).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `pw01.period_ms` is an integer; got the string \"500\""
    );
    assert!(matches!(
        live(&s, "pw01.period_ms", V::Double(f64::NAN)),
        Err(ParamError::WrongType { .. })
    ));
    assert!(matches!(
        s.check(&[item("pw01.active_low", V::Integer(1))], Stage::StartUp),
        Err(ParamError::WrongType { .. })
    ));
}

#[test]
fn the_core_judges_channel_settings_and_cross_rules() {
    let s = ParamStore::new(2);
    let e = live(&s, "pw01.period_ms", V::Integer(4)).unwrap_err();
    assert_eq!(
        e,
        ParamError::Channel {
            channel: "pw01".into(),
            source: ConfigError::PeriodTooShort {
                period_ms: 4,
                min_ms: 5,
                kind: OutputKind::Transistor
            }
        }
    );
    assert_eq!(
        e.to_string(),
        "pw01: period_ms 4 is below the transistor minimum of 5 ms (0 stops the pulses)"
    );
    // The relay minimum (000), whichever order the values come in.
    let e = s
        .check(
            &[
                item("pw02.min_on_ms", V::Integer(30)),
                item("pw02.output_kind", V::String("relay".into())),
            ],
            Stage::Live,
        )
        .unwrap_err();
    assert!(matches!(
        e,
        ParamError::Channel {
            source: ConfigError::RelayMinTimeTooShort {
                which: MinTime::On,
                ..
            },
            ..
        }
    ));
    let both = [
        item("pw02.min_on_ms", V::Integer(2000)),
        item("pw02.period_ms", V::Integer(5000)),
    ];
    let a = s.check(&both, Stage::Live).unwrap();
    assert_eq!(a.configs.len(), 1);
    assert_eq!(a.configs[0].0, 1);
    assert_eq!(a.configs[0].1.period, 5000 * crate::core::NS_PER_MS);
    // Negative times never reach the core.
    let e = live(&s, "pw01.period_ms", V::Integer(-5)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `pw01.period_ms`: -5 is outside 0..3600000"
    );
    let e = live(&s, "pw01.min_off_ms", V::Integer(-2)).unwrap_err();
    assert!(e.to_string().contains("(-1 = as the profile says)"), "{e}");
    let e = live(&s, "pw01.edge_band", V::Double(f64::NAN)).unwrap_err();
    assert!(
        e.to_string()
            .starts_with("pw01: edge_band NaN is outside 0..1"),
        "{e}"
    );
}

#[test]
fn status_rate_is_off_or_a_rate_the_node_can_keep() {
    let s = ParamStore::new(1);
    for bad in [1e-20, 5e-324, 0.009, -0.5, 1000.5, f64::NAN, f64::INFINITY] {
        let e = live(&s, "status_rate_hz", V::Double(bad)).unwrap_err();
        assert!(
            matches!(&e, ParamError::OutOfRange { name, .. } if name == "status_rate_hz"),
            "{bad:?}: {e}"
        );
    }
    let e = live(&s, "status_rate_hz", V::Double(1e-20)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `status_rate_hz`: 1e-20 is outside 0.01..1000.0 (0 = on change only)"
    );
    for ok in [0.0, 0.01, 2.5, 1000.0] {
        assert!(live(&s, "status_rate_hz", V::Double(ok)).is_ok(), "{ok}");
    }
    // The same at start-up (`--status-rate 5e-324`, `-p`, a parameter file): a bad
    // configuration, exit 2.
    assert!(matches!(
        start_up(&[sv("status_rate_hz", V::Double(5e-324))]),
        Err(ParamError::OutOfRange { .. })
    ));
    let d = s.descriptor("status_rate_hz").unwrap().to_raw();
    assert_eq!(d.floating_point_range[0].to_value, 1000.0);
    assert!(d.additional_constraints.contains("0.01"), "{d:?}");
}

#[test]
fn choices_are_checked_with_the_accepted_spellings() {
    let s = ParamStore::new(1);
    let e = live(&s, "pw01.profile", V::String("pico".into())).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `pw01.profile`: `pico` is not one of: \
         pico_gfx|twincat_ba|tcont_cp|schneider_pwm|frequency_output"
    );
    assert!(live(&s, "pw01.short_pulse", V::String(String::new())).is_ok());
    assert!(live(&s, "pw01.short_pulse", V::String("band".into())).is_ok());
    assert!(s
        .check(&[item("output", V::String("spi".into()))], Stage::StartUp)
        .is_err());
}

#[test]
fn the_planners_parameters_are_checked() {
    let s = ParamStore::new(2);
    let e = live(&s, "phase", V::String("staggered".into())).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `phase`: `staggered` is not one of: sync|stagger"
    );
    assert!(live(&s, "phase", V::String(String::new())).is_err());
    assert!(live(&s, "phase", V::Integer(1)).is_err());
    assert!(live(&s, "phase", V::String("stagger".into())).is_ok());
    for bad in [-1, 100, i64::MAX] {
        assert!(
            live(&s, "max_simultaneous_on", V::Integer(bad)).is_err(),
            "{bad}"
        );
    }
    assert!(live(&s, "max_simultaneous_on", V::Double(1.5)).is_err());
    for ok in [0, 1, 99] {
        assert!(
            live(&s, "max_simultaneous_on", V::Integer(ok)).is_ok(),
            "{ok}"
        );
    }
}

#[test]
fn read_only_parameters_refuse_live_changes_but_accept_their_value() {
    let s = ParamStore::new(1);
    let e = live(&s, "pw01.active_low", V::Boolean(true)).unwrap_err();
    assert!(matches!(e, ParamError::ReadOnly { .. }));
    assert!(e.to_string().contains("glitch"), "{e}");
    let a = live(&s, "pw01.active_low", V::Boolean(false)).unwrap();
    assert!(a.changes.is_empty() && a.configs.is_empty());
    assert!(live(&s, "channels", V::Integer(3)).is_err());
    assert!(s
        .check(&[item("pw01.active_low", V::Boolean(true))], Stage::StartUp)
        .is_ok());
    assert_eq!(
        live(&s, "use_sim_time", V::Boolean(true)),
        Err(ParamError::SimTime)
    );
}

#[test]
fn a_refused_change_leaves_the_store_as_it_was() {
    let mut s = ParamStore::new(1);
    let a = live(&s, "pw01.period_ms", V::Integer(500)).unwrap();
    let changed = s.commit(&a);
    assert_eq!(changed.len(), 1);
    assert_eq!(changed[0].name, "pw01.period_ms");
    assert_eq!(changed[0].value.int_value, 500);
    let bad = [
        item("pw01.period_ms", V::Integer(200)),
        item("pw01.min_on_ms", V::Integer(30)),
        item("pw01.output_kind", V::String("relay".into())),
    ];
    assert!(s.check(&bad, Stage::Live).is_err());
    assert_eq!(s.channel(0).unwrap().period_ms, 500);
    assert_eq!(s.channel(0).unwrap().min_on_ms, 0);
}

#[test]
fn undeclared_names_get_a_hint() {
    let s = ParamStore::new(2);
    let e = live(&s, "pw03.period_ms", V::Integer(1)).unwrap_err();
    assert_eq!(
        e.to_string(),
        "parameter `pw03.period_ms` is not declared (this node has 2 channels: pw01..pw02)"
    );
    let e = live(&s, "speed", V::Integer(1)).unwrap_err();
    assert_eq!(e.to_string(), "parameter `speed` is not declared");
}

#[test]
fn refusals_echo_input_escaped_and_bounded() {
    let s = ParamStore::new(1);
    let forged = "x\n[ERROR] [0] [pwm_actuator]: forged\u{1b}[2J";
    let long = "n".repeat(4 << 20);
    let reasons = [
        live(&s, forged, V::Integer(1)).unwrap_err().to_string(),
        live(&s, &long, V::Integer(1)).unwrap_err().to_string(),
        live(&s, "pw01.period_ms", V::String(format!("{forged}{long}")))
            .unwrap_err()
            .to_string(),
        live(&s, "pw01.profile", V::String(format!("{forged}{long}")))
            .unwrap_err()
            .to_string(),
        items_from_msg(
            0,
            &msg::ChannelParams {
                set: vec![format!("{forged}{long}")],
                ..Default::default()
            },
        )
        .unwrap_err()
        .to_string(),
    ];
    for r in &reasons {
        assert!(
            !r.chars().any(|c| c.is_control()),
            "{}",
            &r[..r.len().min(300)]
        );
        assert!(r.len() < 400, "{} bytes: {}", r.len(), &r[..300]);
    }
    assert_eq!(
        reasons[0],
        "parameter `x\\n[ERROR] [0] [pwm_actuator]: forged\\u{1b}[2J` is not declared"
    );
    assert!(
        reasons[1].contains(&format!("`{}… (4194304 bytes)`", "n".repeat(64))),
        "{}",
        reasons[1]
    );
}

#[test]
fn unchanged_values_are_not_changes() {
    let s = ParamStore::new(1);
    let a = live(&s, "pw01.period_ms", V::Integer(1000)).unwrap();
    assert_eq!(a, Accepted::default());
    // The last of repeated values wins.
    let a = s
        .check(
            &[
                item("pw01.period_ms", V::Integer(10)),
                item("pw01.period_ms", V::Integer(20)),
            ],
            Stage::Live,
        )
        .unwrap();
    assert_eq!(a.changes, vec![item("pw01.period_ms", V::Integer(20))]);
}

#[test]
fn list_follows_rclcpp() {
    let s = ParamStore::new(1);
    let (names, prefixes) = s.list(&[], 1);
    assert!(names.contains(&"channels".to_string()));
    assert!(!names.iter().any(|n| n.contains('.')));
    assert!(prefixes.is_empty());
    let (names, prefixes) = s.list(&["pw01".into()], 0);
    assert!(names.iter().all(|n| n.starts_with("pw01.")));
    assert!(names.contains(&"pw01.period_ms".to_string()));
    assert_eq!(prefixes, vec!["pw01".to_string()]);
}

/// The naive answer: every name checked against every prefix.
fn list_naive(s: &ParamStore, prefixes: &[String], depth: u64) -> Vec<String> {
    let within = |dots: usize| depth == 0 || (dots as u64) < depth;
    s.all()
        .into_iter()
        .map(|(n, _)| n)
        .filter(|n| {
            prefixes.iter().any(|p| {
                n == p
                    || n.strip_prefix(p.as_str())
                        .and_then(|r| r.strip_prefix('.'))
                        .is_some_and(|r| within(1 + r.matches('.').count()))
            })
        })
        .collect()
}

#[test]
fn list_answers_as_the_naive_reading_does() {
    let s = ParamStore::new(3);
    for (prefixes, depth) in [
        (vec!["pw01"], 0),
        (vec!["pw01", "pw02", "pw01"], 1),
        (vec!["pw0", "pw03", ""], 2),
        (vec!["channels", "pw02.period_ms"], 0),
    ] {
        let prefixes: Vec<String> = prefixes.into_iter().map(String::from).collect();
        let (mut names, _) = s.list(&prefixes, depth);
        let mut naive = list_naive(&s, &prefixes, depth);
        names.sort();
        naive.sort();
        assert_eq!(names, naive, "{prefixes:?} depth {depth}");
    }
}

#[test]
fn a_list_request_costs_the_distinct_prefixes_not_prefixes_times_parameters() {
    // 99 channels (about 4,000 parameters) and a request of 32,000 prefixes: once 6 s of CPU
    // under the parameter lock. Distinct prefixes are looked up, each once; more than the bound
    // list nothing.
    let s = ParamStore::new(MAX_CHANNELS);
    let repeated: Vec<String> = (0..32_000)
        .map(|k| format!("pw{:02}", 1 + k % 99))
        .collect();
    let start = std::time::Instant::now();
    let (names, prefixes) = s.list(&repeated, 0);
    assert_eq!(prefixes.len(), 99);
    assert!(names.len() > 99 * 20);
    let distinct: Vec<String> = (0..32_000).map(|k| format!("x{k}")).collect();
    assert_eq!(s.list(&distinct, 0), (Vec::new(), Vec::new()));
    let many: Vec<String> = (0..super::store::MAX_LIST_PREFIXES)
        .map(|k| format!("pw{:02}.{k}", 1 + k % 99))
        .collect();
    assert_eq!(s.list(&many, 0).0.len(), 0);
    // A bound with a wide margin (unoptimised build): the naive reading took seconds here.
    assert!(
        start.elapsed() < std::time::Duration::from_secs(2),
        "{:?}",
        start.elapsed()
    );
}

#[test]
fn msg_items_use_only_the_fields_in_set() {
    let m = msg::ChannelParams {
        set: vec!["period_ms".into(), "profile".into()],
        period_ms: 500,
        profile: "tcont_cp".into(),
        min_on_ms: 99_999,
        ..Default::default()
    };
    assert_eq!(
        items_from_msg(0, &m).unwrap(),
        vec![
            item("pw01.period_ms", V::Integer(500)),
            item("pw01.profile", V::String("tcont_cp".into()))
        ]
    );
    assert_eq!(
        items_from_msg(1, &msg::ChannelParams::default()),
        Err(ParamError::EmptySet {
            channel: "pw02".into()
        })
    );
    let bad = msg::ChannelParams {
        set: vec!["period".into()],
        ..Default::default()
    };
    assert!(matches!(
        items_from_msg(0, &bad),
        Err(ParamError::UnknownField { .. })
    ));
}

#[test]
fn start_up_reads_channels_first_and_ignores_unknown_names() {
    let su = start_up(&[
        sv("pw03.period_ms", V::Integer(300)),
        sv("channels", V::Integer(3)),
        sv("other_node_param", V::Integer(1)),
        sv("pw01.duty", V::Integer(37)),
        sv("pw01.enable", V::Boolean(true)),
        sv("pw04.period_ms", V::Integer(1)),
    ])
    .unwrap();
    assert_eq!(su.store.channels(), 3);
    assert_eq!(su.store.channel(2).unwrap().period_ms, 300);
    assert_eq!(
        su.ignored,
        vec!["other_node_param (-p)", "pw04.period_ms (-p)"]
    );
    assert_eq!(su.notes, vec!["pw01.duty: integer 37 taken as double 37.0"]);
    let cfg = StartupConfig::from_store(&su.store).unwrap();
    assert_eq!(cfg.channels.len(), 3);
    assert!(cfg.channels[0].enable);
    assert_eq!(cfg.channels[0].duty_percent, 37.0);
    assert_eq!(
        cfg.output,
        OutputSpec {
            backend: Backend::Sim {
                names: vec!["pw01".into(), "pw02".into(), "pw03".into()]
            },
            trace: vec![],
            trace_limit: crate::output::TraceLimit::default(),
            fault: None,
        }
    );
    assert_eq!(cfg.settings.rt_priority, None);
    assert!(start_up(&[sv("channels", V::Integer(0))]).is_err());
    assert!(start_up(&[sv("channels", V::Integer(100))]).is_err());
    assert!(start_up(&[sv("pw01.duty", V::Double(150.0))]).is_err());
    let su = start_up(&[sv("use_sim_time", V::Boolean(true))]).unwrap();
    assert!(!su.store.node().use_sim_time);
    assert!(su.warnings[0].starts_with("use_sim_time true (-p) ignored: "));
}

#[test]
fn gpio_needs_lines_and_takes_a_trace() {
    let su = start_up(&[
        sv("channels", V::Integer(1)),
        sv("output", V::String("gpio".into())),
    ])
    .unwrap();
    assert_eq!(
        StartupConfig::from_store(&su.store),
        Err(ParamError::MissingLine {
            channel: "pw01".into()
        })
    );
    let su = start_up(&[
        sv("channels", V::Integer(1)),
        sv("output", V::String("gpio".into())),
        sv("pw01.gpio_line", V::Integer(17)),
        sv("pw01.active_low", V::Boolean(true)),
    ])
    .unwrap();
    let cfg = StartupConfig::from_store(&su.store).unwrap();
    assert_eq!(
        cfg.output,
        OutputSpec {
            backend: Backend::Gpio {
                lines: vec![GpioLine {
                    name: "pw01".into(),
                    chip: "/dev/gpiochip0".into(),
                    offset: 17,
                    active_low: true
                }],
            },
            trace: vec![],
            trace_limit: crate::output::TraceLimit::default(),
            fault: None,
        }
    );
    let su = start_up(&[
        sv("channels", V::Integer(1)),
        sv("output", V::String("gpio".into())),
        sv("pw01.gpio_line", V::Integer(17)),
        sv("trace", V::String("a.vcd".into())),
    ])
    .unwrap();
    // Any output can be traced: with gpio the trace records what was written to the lines.
    let output = StartupConfig::from_store(&su.store).unwrap().output;
    assert!(matches!(output.backend, Backend::Gpio { .. }));
    assert_eq!(output.trace, [std::path::PathBuf::from("a.vcd")]);
    let su = start_up(&[sv("trace", V::String("a.vcd, b.csv".into()))]).unwrap();
    assert_eq!(
        StartupConfig::from_store(&su.store).unwrap().output.trace,
        [std::path::PathBuf::from("a.vcd"), "b.csv".into()]
    );
    // The traces' size limit: 256 MB unless set, in MB, 1 at least.
    assert_eq!(
        StartupConfig::from_store(&su.store)
            .unwrap()
            .output
            .trace_limit
            .max_bytes,
        256_000_000
    );
    let su = start_up(&[sv("trace_max_mb", V::Integer(64))]).unwrap();
    let limit = StartupConfig::from_store(&su.store)
        .unwrap()
        .output
        .trace_limit;
    assert_eq!(limit.max_bytes, 64_000_000);
    assert!(start_up(&[sv("trace_max_mb", V::Integer(0))]).is_err());
}

#[test]
fn channel_names() {
    assert_eq!(channel_name(0), "pw01");
    assert_eq!(channel_name(98), "pw99");
    assert_eq!(channel_of("pw01.period_ms"), Some((0, "period_ms")));
    assert_eq!(channel_of("pw12.duty"), Some((11, "duty")));
    assert_eq!(channel_of("pw1.duty"), None);
    assert_eq!(channel_of("pw00.duty"), None);
    assert_eq!(channel_of("channels"), None);
    assert_eq!(channel_index("pw01"), Some(0));
    assert_eq!(channel_index("pw99"), Some(98));
    assert_eq!(channel_index("pw1"), None);
    assert_eq!(channel_index("pw00"), None);
    assert_eq!(channel_index("pw100"), None);
    assert_eq!(channel_index("mix"), None);
}

#[test]
fn twincat_ba_limits_a_minimum_of_any_size_to_the_period_002() {
    // 002: nMinSwiTi is "internally limited to values between 0 and nPrd": under twincat_ba a
    // minimum above an hour is limited to the period, not refused; elsewhere it still is.
    let s = ParamStore::new(1);
    let e = live(&s, "pw01.min_on_ms", V::Integer(5_000_000)).unwrap_err();
    assert!(e.to_string().contains("5000000"), "{e}");
    let both = [
        item("pw01.profile", V::String("twincat_ba".into())),
        item("pw01.min_on_ms", V::Integer(5_000_000)),
    ];
    let a = s.check(&both, Stage::Live).unwrap();
    assert_eq!(a.changes.len(), 2);
    assert!(live(&s, "pw01.min_on_ms", V::Integer(-1)).is_err());
}

#[test]
fn a_valves_parameters_exist_once_the_valve_parameter_names_it() {
    let su = start_up(&[
        sv("valve", V::String("mix:pw01:pw02".into())),
        sv("mix.travel_open_ms", V::Integer(45_000)),
        sv("mix.on_timeout", V::String("close".into())),
        sv("other.travel_open_ms", V::Integer(45_000)),
    ])
    .unwrap();
    let p = su.store.valve_params("mix");
    assert_eq!(p.travel_open_ms, 45_000);
    assert_eq!(p.on_timeout, crate::core::valve::OnTimeout::Close);
    assert_eq!(p.travel_close_ms, 60_000, "the default");
    assert!(!su.store.descriptor("mix.min_pulse_ms").unwrap().read_only);
    assert!(
        su.store
            .descriptor("mix.open_limit_line")
            .unwrap()
            .read_only
    );
    assert_eq!(su.ignored, ["other.travel_open_ms (-p)"], "no such valve");
    // Out of its range, or not a spelling: refused at start-up.
    for bad in [
        sv("mix.travel_open_ms", V::Integer(10)),
        sv("mix.on_timeout", V::String("hold".into())),
        sv("mix.deadband_pct", V::Double(f64::NAN)),
    ] {
        assert!(
            start_up(&[sv("valve", V::String("mix:pw01:pw02".into())), bad.clone()]).is_err(),
            "{bad:?}"
        );
    }
    // Without a valve, no valve parameters.
    let su = start_up(&[sv("mix.travel_open_ms", V::Integer(45_000))]).unwrap();
    assert!(su.store.descriptor("mix.travel_open_ms").is_none());
}

#[test]
fn a_valves_motion_settings_change_while_running_checked_whole() {
    let su = start_up(&[
        sv("valve", V::String("mix:pw01:pw02,hot:pw03:pw04".into())),
        sv("channels", V::Integer(4)),
        sv("hot.travel_open_ms", V::Integer(30_000)),
    ])
    .unwrap();
    let s = &su.store;
    // A change goes to the valve it names, as its whole validated configuration.
    let a = live(s, "hot.deadband_pct", V::Double(2.0)).unwrap();
    assert!(a.configs.is_empty());
    assert_eq!(a.valve_configs.len(), 1);
    let (k, cfg) = a.valve_configs[0];
    assert_eq!(k, 1, "hot is the second valve");
    assert_eq!(cfg.deadband_pct, 2.0);
    assert_eq!(
        cfg.travel[0],
        30_000 * crate::core::NS_PER_MS,
        "the rest in force"
    );
    // The same value again: nothing to send.
    let a = live(s, "hot.deadband_pct", V::Double(1.0)).unwrap();
    assert!(a.changes.is_empty() && a.valve_configs.is_empty(), "{a:?}");
    // Refused as a whole, with the core's reason: a minimum pulse above the travel time.
    let e = live(s, "hot.min_pulse_ms", V::Integer(40_000)).unwrap_err();
    assert!(
        matches!(e, ParamError::Valve { ref valve, .. } if valve == "hot"),
        "{e}"
    );
    assert!(e.to_string().starts_with("valve hot: "), "{e}");
    // Several at once: all or none.
    let two = [
        item("mix.reversal_pause_ms", V::Integer(500)),
        item("mix.min_pulse_ms", V::Integer(2_000)),
    ];
    let a = s.check(&two, Stage::Live).unwrap();
    assert_eq!(
        a.valve_configs[0].1.min_pulse,
        2_000 * crate::core::NS_PER_MS
    );
    // A reversal pause below the floor is refused with the core's reason.
    let e = live(s, "mix.reversal_pause_ms", V::Integer(5)).unwrap_err();
    assert!(e.to_string().contains("below 20 ms"), "{e}");
    // The travel times, the end switches, the feedback, the backlash and the reference at
    // start stay start-up only.
    for (name, v) in [
        ("mix.travel_open_ms", V::Integer(120_000)),
        ("mix.open_limit_line", V::String("5".into())),
        ("mix.limit_debounce_ms", V::Integer(20)),
        ("mix.reference_at_start", V::String("none".into())),
        ("mix.feedback_topic", V::String("/pot".into())),
        ("mix.backlash_pct", V::Double(2.0)),
    ] {
        let e = live(s, name, v).unwrap_err();
        assert!(matches!(e, ParamError::ReadOnly { .. }), "{name}: {e}");
    }
    assert_eq!(s.valve_params("hot").travel_open_ms, 30_000);
}

#[test]
fn a_valves_loop_parameters_reach_the_core_and_bad_ones_are_refused() {
    use crate::core::valve::{Control, LoopOutput};
    let base = || {
        vec![
            sv("valve", V::String("mix:pw01:pw02".into())),
            sv("mix.process_topic", V::String("/supply".into())),
            sv("mix.process_type", V::String("float64".into())),
        ]
    };
    // By default the position commands set the target: today's behaviour.
    let su = start_up(&base()).unwrap();
    let c = su.store.valve_params("mix").control;
    assert_eq!(c.control, Control::Position);
    assert!(c.process, "a process topic is configured");
    // Every loop parameter is handed to the core.
    let mut all = base();
    all.extend([
        sv("mix.control", V::String("pid".into())),
        sv("mix.loop_output", V::String("step".into())),
        sv("mix.pid_kp", V::Double(5.0)),
        sv("mix.pid_ki", V::Double(0.04)),
        sv("mix.pid_kd", V::Double(1.5)),
        sv("mix.pid_d_filter_s", V::Double(2.0)),
        sv("mix.pid_reverse", V::Boolean(true)),
        sv("mix.pid_sample_ms", V::Integer(500)),
        sv("mix.process_timeout_ms", V::Integer(4_000)),
        sv("mix.process_max_skew_ms", V::Integer(200)),
        sv("mix.safe_position_pct", V::Double(30.0)),
        sv("mix.safe_after_ms", V::Integer(10_000)),
    ]);
    let su = start_up(&all).unwrap();
    let c = su.store.valve_params("mix").control;
    assert_eq!(
        (c.control, c.output, c.pid_reverse),
        (Control::Pid, LoopOutput::Step, true)
    );
    assert_eq!(
        (c.pid_kp, c.pid_ki, c.pid_kd, c.pid_d_filter_s),
        (5.0, 0.04, 1.5, 2.0)
    );
    assert_eq!(
        (c.pid_sample_ms, c.process_timeout_ms, c.process_max_skew_ms),
        (500, 4_000, 200)
    );
    assert_eq!((c.safe_position_pct, c.safe_after_ms), (30.0, 10_000));
    let cfg = su.store.valve_params("mix").validate().unwrap();
    assert_eq!(cfg.control.safe, Some(30.0));
    assert_eq!(cfg.control.sample, 500 * crate::core::NS_PER_MS);
    // The loop can be switched and tuned while running; the topic and its type cannot.
    let s = &su.store;
    let a = live(s, "mix.control", V::String("position".into())).unwrap();
    assert_eq!(
        a.valve_configs[0].1.control.params.control,
        Control::Position
    );
    let a = live(s, "mix.pid_kp", V::Double(2.0)).unwrap();
    assert_eq!(a.valve_configs[0].1.control.gains.kp, 2.0);
    for (name, v) in [
        ("mix.process_topic", V::String("/other".into())),
        ("mix.process_type", V::String("temperature".into())),
    ] {
        let e = live(s, name, v).unwrap_err();
        assert!(matches!(e, ParamError::ReadOnly { .. }), "{name}: {e}");
    }
    // Gains to zero under pid: refused whole with the core's reason, the rest stays.
    let two = [
        item("mix.pid_kp", V::Double(0.0)),
        item("mix.pid_ki", V::Double(0.0)),
    ];
    let e = s.check(&two, Stage::Live).unwrap_err();
    assert!(e.to_string().contains("pid_kp or pid_ki above 0"), "{e}");
    // Refused at start-up: out of range, a bad spelling, pid without a topic.
    for bad in [
        sv("mix.control", V::String("pi".into())),
        sv("mix.process_type", V::String("pressure".into())),
        sv("mix.loop_output", V::String("servo".into())),
        sv("mix.pid_kp", V::Double(-1.0)),
        sv("mix.pid_ki", V::Double(f64::NAN)),
        sv("mix.pid_sample_ms", V::Integer(5)),
        sv("mix.process_timeout_ms", V::Integer(0)),
        sv("mix.safe_position_pct", V::Double(100.5)),
    ] {
        let mut v = base();
        v.push(bad.clone());
        assert!(start_up(&v).is_err(), "{bad:?}");
    }
    let e = start_up(&[
        sv("valve", V::String("mix:pw01:pw02".into())),
        sv("mix.control", V::String("pid".into())),
        sv("mix.pid_kp", V::Double(5.0)),
    ])
    .unwrap_err();
    assert!(e.to_string().contains("needs a process_topic"), "{e}");
}

/// A value of `v`'s type other than `v`.
fn other(v: &V) -> V {
    match v {
        V::Integer(i) => V::Integer(i.wrapping_add(1)),
        V::Double(x) => V::Double(x + 0.5),
        V::Boolean(b) => V::Boolean(!b),
        V::String(s) => V::String(format!("{s}x")),
        other => panic!("no parameter is {other:?}"),
    }
}

/// Round-trips every entry of `decls` through its field of the settings `S`: the entry's type
/// is its default's, a value set is the value read back, and no other field changes.
fn round_trip<S: Default>(
    decls: &[table::Decl],
    fields: &[&str],
    field: fn(&table::Decl) -> table::Field<S>,
) {
    let names: Vec<&str> = decls.iter().map(|d| d.suffix).collect();
    assert_eq!(
        names, fields,
        "every field has one entry, in the order written"
    );
    let mut s = S::default();
    for d in decls {
        let f = field(d);
        assert_eq!(f.name, d.suffix);
        let default = (d.default)();
        assert!(
            coerce(&make(d.suffix.into(), d, 0), &default)
                .unwrap()
                .1
                .is_none(),
            "{}: type",
            d.suffix
        );
        for v in [default.clone(), other(&default)] {
            let before: Vec<V> = decls.iter().map(|e| (field(e).get)(&s)).collect();
            (f.set)(&mut s, &v);
            assert_eq!((f.get)(&s), v, "{}", d.suffix);
            for (e, was) in decls.iter().zip(before) {
                if e.suffix != d.suffix {
                    assert_eq!((field(e).get)(&s), was, "{} wrote {}", d.suffix, e.suffix);
                }
            }
        }
    }
}

#[test]
fn every_table_entry_round_trips_through_its_typed_field() {
    round_trip(&table::node_decls(), NodeValues::FIELDS, |d| {
        match d.access {
            table::Access::Node(f) => f,
            _ => panic!("{} is not a node field", d.suffix),
        }
    });
    round_trip(
        &table::channel_decls(),
        ChannelValues::FIELDS,
        |d| match d.access {
            table::Access::Channel(f) => f,
            _ => panic!("{} is not a channel field", d.suffix),
        },
    );
    round_trip(&table::valve_decls(), ValveValues::FIELDS, |d| {
        match d.access {
            table::Access::Valve(f) => f,
            _ => panic!("{} is not a valve field", d.suffix),
        }
    });
}

#[test]
fn the_store_holds_every_parameter_in_its_typed_settings() {
    let mut s = ParamStore::new(2);
    s.declare_valves(&["mix".to_string()]);
    let all = s.all();
    assert_eq!(
        all.len(),
        table::node_decls().len() + 2 * table::channel_decls().len() + table::valve_decls().len()
    );
    for (name, v) in &all {
        assert_eq!(Some(v), s.descriptor(name).map(|d| &d.default), "{name}");
    }
    // Each parameter set alone changes it and nothing else, and reads back.
    for (name, v) in &all {
        let d = s.descriptor(name).unwrap();
        let mut working = s.clone();
        let w = other(v);
        working.commit(&Accepted {
            changes: vec![(name.clone(), w.clone())],
            ..Accepted::default()
        });
        assert_eq!(working.get(name), Some(w), "{name}");
        let changed: Vec<String> = working
            .all()
            .into_iter()
            .zip(&all)
            .filter(|(now, was)| now != *was)
            .map(|(now, _)| now.0)
            .collect();
        assert_eq!(changed, vec![d.name.clone()]);
    }
    assert_eq!(s.check(&all, Stage::Live).unwrap().changes, vec![]);
}

#[test]
fn the_node_settings_follow_each_committed_change() {
    let mut s = ParamStore::new(2);
    let before = s.node_settings();
    let a = live(&s, "pw01.period_ms", V::Integer(500)).unwrap();
    s.commit(&a);
    assert_eq!(s.node_settings(), before);
    let a = s
        .check(
            &[
                item("status_rate_hz", V::Double(5.0)),
                item("phase", V::String("stagger".into())),
                item("max_simultaneous_on", V::Integer(1)),
            ],
            Stage::Live,
        )
        .unwrap();
    s.commit(&a);
    let after = s.node_settings();
    assert_eq!(after.status_rate_hz, 5.0);
    assert_eq!(after.bank.phase, crate::core::Phase::Stagger);
    assert_eq!(after.bank.max_on, 1);
    assert_eq!(
        after,
        NodeSettings {
            status_rate_hz: 5.0,
            bank: after.bank,
            ..before
        }
    );
}
