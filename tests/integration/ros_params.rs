//! Parameters over ROS: the standard parameter services (get, set, refuse with a reason,
//! atomic sets, describe with descriptors and ranges, list), `/parameter_events`, the
//! `~/<ch>/params` topic sharing the same state, and start-up values from `-p` and
//! `--params-file`. The node runs as a process on its own ROS domain.

use crate::ros_harness::*;
use pwm_actuator::ros::interface::msg::{ChannelParams, DiagnosticArray};
use ros2_client::parameters::raw;
use ros2_client::ParameterValue as V;

fn event_has(e: &raw::ParameterEvent, name: &str, int: i64) -> bool {
    e.changed_parameters
        .iter()
        .any(|p| p.name == name && p.value.int_value == int && p.value.ptype == 2)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parameter_services_set_refuse_describe_and_announce() {
    let node = NodeProc::launch(&[]);
    let mut ros = Ros::new(node.domain);
    let events = ros.sub::<raw::ParameterEvent>("/parameter_events", default_qos());
    let p = ros.params("/pwm_actuator");
    p.ready(&ros).await;

    p.assert_values(&[
        ("pw01.period_ms", V::Integer(1000)),
        ("pw02.profile", V::String("pico_gfx".into())),
        ("channels", V::Integer(2)),
        ("nope", V::NotSet),
    ])
    .await;

    // Accepted, announced on /parameter_events.
    assert_eq!(
        p.set(&[("pw01.period_ms", V::Integer(500))]).await,
        vec![(true, String::new())]
    );
    let ev = wait_for(&events, LONG, |e| event_has(e, "pw01.period_ms", 500))
        .await
        .expect("the change is announced");
    assert_eq!(ev.node, "/pwm_actuator");

    // Refused with the core's reason; the old value stays.
    let r = p.set(&[("pw01.period_ms", V::Integer(4))]).await;
    assert!(!r[0].0);
    assert_eq!(
        r[0].1,
        "pw01: period_ms 4 is below the transistor minimum of 5 ms (0 stops the pulses)"
    );
    let (ok, reason) = p
        .set_atomically(&[
            ("pw01.output_kind", V::String("relay".into())),
            ("pw01.min_on_ms", V::Integer(30)),
        ])
        .await;
    assert!(!ok);
    assert!(
        reason.contains("min_on_ms 30 is below the relay minimum of 50 ms"),
        "{reason}"
    );
    p.assert_values(&[
        ("pw01.period_ms", V::Integer(500)),
        ("pw01.min_on_ms", V::Integer(0)),
        ("pw01.output_kind", V::String("transistor".into())),
    ])
    .await;
    // A minimum above the period is a valid vendor setting (000: ME up to 65 535 ms).
    assert!(p.set(&[("pw01.min_on_ms", V::Integer(600))]).await[0].0);
    assert!(p.set(&[("pw01.min_on_ms", V::Integer(0))]).await[0].0);

    // A whole double is taken as the integer; a fraction is refused.
    assert!(p.set(&[("pw01.period_ms", V::Double(800.0))]).await[0].0);
    p.assert_values(&[("pw01.period_ms", V::Integer(800))])
        .await;
    let r = p.set(&[("pw01.period_ms", V::Double(800.5))]).await;
    assert!(!r[0].0 && r[0].1.contains("not a whole number"), "{r:?}");

    // Atomic: both values together pass the cross-check, either alone would not.
    let (ok, why) = p
        .set_atomically(&[
            ("pw02.min_on_ms", V::Integer(1500)),
            ("pw02.period_ms", V::Integer(4000)),
        ])
        .await;
    assert!(ok, "{why}");
    p.assert_values(&[
        ("pw02.min_on_ms", V::Integer(1500)),
        ("pw02.period_ms", V::Integer(4000)),
    ])
    .await;
    let (ok, why) = p
        .set_atomically(&[
            ("pw02.period_ms", V::Integer(4)),
            ("pw02.profile", V::String("tcont_cp".into())),
        ])
        .await;
    assert!(!ok);
    assert!(why.contains("pw02:"), "{why}");
    p.assert_values(&[
        ("pw02.period_ms", V::Integer(4000)),
        ("pw02.profile", V::String("pico_gfx".into())),
    ])
    .await;

    // set_parameters takes each parameter on its own.
    let r = p
        .set(&[
            ("pw02.profile", V::String("twincat_ba".into())),
            ("pw02.short_pulse", V::String("wobble".into())),
        ])
        .await;
    assert!(r[0].0);
    assert!(!r[1].0 && r[1].1.contains("suppress|stretch|band"), "{r:?}");

    // Read-only, undeclared, wrong type.
    let r = p.set(&[("pw01.active_low", V::Boolean(true))]).await;
    assert!(!r[0].0 && r[0].1.contains("read-only"), "{r:?}");
    let r = p.set(&[("pw03.period_ms", V::Integer(100))]).await;
    assert!(!r[0].0 && r[0].1.contains("not declared"), "{r:?}");
    let r = p.set(&[("pw01.enable", V::String("yes".into()))]).await;
    assert!(!r[0].0 && r[0].1.contains("is a bool"), "{r:?}");
    let r = p.set(&[("use_sim_time", V::Boolean(true))]).await;
    assert!(!r[0].0, "{r:?}");

    // Node-level parameters that may change while running.
    let r = p
        .set(&[
            ("status_rate_hz", V::Double(2.0)),
            ("edge_log_rate", V::Integer(0)),
            ("use_sim_time", V::Boolean(false)),
        ])
        .await;
    assert!(r.iter().all(|(ok, _)| *ok), "{r:?}");
    let r = p.set(&[("status_rate_hz", V::Double(-1.0))]).await;
    assert!(!r[0].0 && r[0].1.contains("outside 0.0..1000.0"), "{r:?}");

    // Descriptors with descriptions and ranges.
    let d = p
        .describe(&[
            "pw01.period_ms",
            "pw01.edge_band",
            "pw01.active_low",
            "nope",
        ])
        .await;
    assert_eq!(d.len(), 4);
    assert_eq!(d[0].r#type, 2);
    assert!(d[0].description.contains("Period"), "{}", d[0].description);
    assert_eq!(
        (
            d[0].integer_range[0].from_value,
            d[0].integer_range[0].to_value
        ),
        (0, 3_600_000)
    );
    assert_eq!(d[1].floating_point_range[0].to_value, 1.0);
    assert!(d[2].read_only);
    assert_eq!(d[3].r#type, 0);

    let names = p.list(&["pw01"], 0).await;
    assert!(names.contains(&"pw01.period_ms".to_string()), "{names:?}");
    assert!(names.iter().all(|n| n.starts_with("pw01.")));
    let top = p.list(&[], 1).await;
    assert!(top.contains(&"status_rate_hz".to_string()) && !top.iter().any(|n| n.contains('.')));

    let mut node = node;
    assert!(node.running());
    assert_mentions(
        &node.stop_ok(),
        &[
            "parameter change refused (via set_parameters)",
            "pw01.period_ms: double 800.0 taken as integer 800",
        ],
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn params_topic_applies_whole_or_refuses_whole() {
    let node = NodeProc::launch(&[]);
    let mut ros = Ros::new(node.domain);
    let events = ros.sub::<raw::ParameterEvent>("/parameter_events", default_qos());
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
    let topic = ros.publisher::<ChannelParams>("/pwm_actuator/pw01/params");
    let p = ros.params("/pwm_actuator");
    p.ready(&ros).await;
    ros.matched(&topic).await;

    let good = ChannelParams {
        set: vec!["period_ms".into(), "min_on_ms".into(), "profile".into()],
        period_ms: 200,
        min_on_ms: 50,
        profile: "twincat_ba".into(),
        // Not in `set`: ignored.
        edge_band: 7.0,
        ..ChannelParams::default()
    };
    let ev = command_until(&topic, good, &events, |e| {
        event_has(e, "pw01.period_ms", 200)
    })
    .await
    .expect("accepted and announced");
    assert!(
        event_has(&ev, "pw01.min_on_ms", 50),
        "one event for the whole message: {ev:?}"
    );
    p.assert_values(&[
        ("pw01.period_ms", V::Integer(200)),
        ("pw01.min_on_ms", V::Integer(50)),
        ("pw01.profile", V::String("twincat_ba".into())),
        ("pw01.edge_band", V::Double(0.0)),
    ])
    .await;

    // One bad field refuses the whole message: a minimum above an hour under pico_gfx (under
    // twincat_ba it would be limited to the period, 002's nMinSwiTi).
    let bad = ChannelParams {
        set: vec!["period_ms".into(), "min_on_ms".into(), "profile".into()],
        period_ms: 300,
        min_on_ms: 4_000_000,
        profile: "pico_gfx".into(),
        ..ChannelParams::default()
    };
    let _ = topic.publish(bad);
    let a = wait_for(&diag, LONG, |a: &DiagnosticArray| {
        a.status.iter().any(|s| {
            s.name == "pwm_actuator: pw01"
                && kv(s, "last_refusal").contains("min_on_ms")
                && kv(s, "last_refusal").contains("4000000")
        })
    })
    .await
    .expect("the refusal and its reason on diagnostics");
    assert!(!a.status.is_empty());
    p.assert_values(&[
        ("pw01.period_ms", V::Integer(200)),
        ("pw01.min_on_ms", V::Integer(50)),
    ])
    .await;

    let _ = topic.publish(ChannelParams::default());
    assert!(node.wait_log("`set` is empty", LONG), "{}", node.log());
    let unknown = ChannelParams {
        set: vec!["period".into()],
        ..ChannelParams::default()
    };
    let _ = topic.publish(unknown);
    assert!(node.wait_log("`period` in `set` is not a ChannelParams field", LONG));
    let ro = ChannelParams {
        set: vec!["active_low".into()],
        active_low: true,
        ..ChannelParams::default()
    };
    let _ = topic.publish(ro);
    assert!(
        node.wait_log("pw01.active_low` is read-only", LONG),
        "{}",
        node.log()
    );
    p.assert_values(&[("pw01.active_low", V::Boolean(false))])
        .await;

    let mut node = node;
    assert!(node.running());
    node.stop_ok();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn start_up_values_from_params_file_and_p() {
    let dir = std::env::temp_dir().join(format!("pwm_actuator_ros_params_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("params.yaml");
    std::fs::write(
        &file,
        "/**:\n  ros__parameters:\n    status_rate_hz: 5\n    pw01:\n      period_ms: 2000\n      \
         edge_band: 1\n\
         pwm_actuator:\n  ros__parameters:\n    channels: 3\n    pw01.profile: tcont_cp\n    \
         pw03:\n      period_ms: 300\n\
         other_node:\n  ros__parameters:\n    pw01.period_ms: 7\n",
    )
    .unwrap();
    let f = file.to_string_lossy().to_string();
    let node = NodeProc::launch(&[
        "--status-rate",
        "2",
        "--ros-args",
        "--params-file",
        &f,
        "-p",
        "pw01.period_ms:=500.0",
        "-p",
        "other:pw02.period_ms:=9",
    ]);
    let mut ros = Ros::new(node.domain);
    let p = ros.params("/pwm_actuator");
    p.ready(&ros).await;
    p.assert_values(&[
        ("channels", V::Integer(3)),
        ("status_rate_hz", V::Double(5.0)),
        ("pw01.period_ms", V::Integer(500)),
        ("pw01.profile", V::String("tcont_cp".into())),
        ("pw01.edge_band", V::Double(1.0)),
        ("pw02.period_ms", V::Integer(1000)),
        ("pw03.period_ms", V::Integer(300)),
    ])
    .await;
    assert_mentions(
        &node.stop_ok(),
        &[
            "pw01.period_ms: double 500.0 taken as integer 500",
            "pw01.edge_band: integer 1 taken as double 1.0",
            "overrides --status-rate",
        ],
    );
    let _ = std::fs::remove_dir_all(&dir);
}
