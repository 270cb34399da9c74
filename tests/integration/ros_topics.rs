//! The node's topics over ROS: commands in, edges / status / e1 / diagnostics out, and bad
//! input leaving the node running with its last good state. The node runs as a process on its
//! own ROS domain; this test talks to it with a ros2-client node.

use crate::ros_harness::*;
use pwm_actuator::ros::interface::msg::{
    Bool, ChannelStatus, DiagnosticArray, DiagnosticStatus, Float64, OutputEdge, UInt16,
};
use ros2_client::{Log, Subscription};
use std::time::Duration;

fn pw01_diag(a: &DiagnosticArray) -> Option<&DiagnosticStatus> {
    a.status.iter().find(|s| s.name == "pwm_actuator: pw01")
}

/// The first /diagnostics message in which pw01's status satisfies `pred`.
async fn pw01_until(
    diag: &Subscription<DiagnosticArray>,
    what: &str,
    pred: impl Fn(&DiagnosticStatus) -> bool,
) -> DiagnosticArray {
    wait_for(diag, LONG, |a: &DiagnosticArray| {
        pw01_diag(a).is_some_and(&pred)
    })
    .await
    .unwrap_or_else(|| panic!("pw01 on /diagnostics: {what}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_in_edges_and_status_out() {
    let node = NodeProc::launch(&ros_params(&["pw01.period_ms:=100", "edge_log_rate:=10"]));
    let mut ros = Ros::new(node.domain);
    let ChannelTopics {
        edges,
        status,
        duty,
        enable,
        ..
    } = ros.channel("pw01");
    let ChannelTopics {
        status: status2,
        sv,
        enable: enable2,
        ..
    } = ros.channel("pw02");
    let rosout = ros.sub::<Log>("/rosout", latched_qos());
    ros.matched(&duty).await;
    ros.matched(&enable).await;

    let s = command_until(&duty, Float64 { data: 30.0 }, &status, |s| {
        s.duty_commanded == 30.0
    })
    .await
    .expect("status shows the commanded duty");
    assert!(!s.enabled, "the channel starts disabled");
    assert_eq!(s.period_ms, 100.0);
    assert_eq!(
        s.on_time_ms, 30.0,
        "t_on = d * T is computed while disabled (002)"
    );
    assert_eq!(s.off_time_ms, 70.0);

    let s = command_until(&enable, Bool { data: true }, &status, |s| s.enabled)
        .await
        .expect("status shows the channel enabled");
    assert!(s.active);
    assert_eq!(s.channel, 1);
    assert_eq!(s.rule, "exact");

    // Several edges in order: alternating levels, consecutive sequence numbers.
    let mut got: Vec<OutputEdge> = Vec::new();
    while got.len() < 4 {
        let e = next(&edges, LONG).await.expect("edges keep coming");
        got.push(e);
    }
    for w in got.windows(2) {
        assert_eq!(w[1].seq, w[0].seq + 1, "{got:?}");
        assert_ne!(w[1].level, w[0].level, "{got:?}");
        assert_eq!(w[0].channel, 1);
    }
    assert!(got.iter().all(|e| e.stamp.to_nanos() > 0));

    // Raw SV on pw02: 4095 is 100 %.
    ros.matched(&sv).await;
    command_until(&sv, UInt16 { data: 4095 }, &status2, |s| {
        s.duty_commanded == 100.0
    })
    .await
    .expect("SV 4095 is 100 %");
    ros.matched(&enable2).await;
    let s = command_until(&enable2, Bool { data: true }, &status2, |s| {
        s.enabled && s.output
    })
    .await
    .expect("100 % is constant on");
    assert_eq!(s.duty_applied, 100.0);
    assert_eq!(s.channel, 2);

    // The node's log reaches /rosout.
    let log = wait_for(&rosout, LONG, |l: &Log| l.name == "pwm_actuator")
        .await
        .expect("a /rosout message from the node");
    assert!(!log.msg.is_empty());

    let log = node.stop_ok();
    assert!(log.contains("pw01 ↑ t="), "console edge lines:\n{log}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn e1_is_latched_and_diagnostics_warn() {
    // 5 % of 100 ms is a 5 ms pulse, below min_on_ms 20: suppressed, E1 (000).
    let node = NodeProc::launch(&ros_params(&[
        "pw01.period_ms:=100",
        "pw01.min_on_ms:=20",
        "pw01.duty:=5.0",
        "pw01.enable:=true",
    ]));
    // Subscribed after the node set E1: transient local delivers the current value.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut ros = Ros::new(node.domain);
    let ChannelTopics { e1, .. } = ros.channel("pw01");
    let ChannelTopics { e1: e1_pw02, .. } = ros.channel("pw02");
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
    let v = wait_for(&e1, LONG, |b: &Bool| b.data).await;
    assert!(v.is_some(), "latched E1 = true for pw01");
    let v = next(&e1_pw02, LONG).await.expect("latched E1 for pw02");
    assert!(!v.data);

    let a = pw01_until(&diag, "at WARN", |d| d.level == DiagnosticStatus::WARN).await;
    let d = pw01_diag(&a).unwrap();
    assert!(d.message.starts_with("E1:"), "{}", d.message);
    assert_eq!(d.hardware_id, "sim");
    assert_eq!(kv(d, "e1"), "true");
    assert_eq!(kv(d, "rule"), "suppressed_pulse");
    let pw02 = a
        .status
        .iter()
        .find(|s| s.name == "pwm_actuator: pw02")
        .expect("pw02 listed");
    assert_eq!(pw02.level, DiagnosticStatus::OK);
    assert_eq!(pw02.message, "disabled");
    node.stop_ok();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_leaves_the_node_running_with_its_last_good_state() {
    let node = NodeProc::launch(&ros_params(&["pw01.period_ms:=100", "pw01.enable:=true"]));
    let mut ros = Ros::new(node.domain);
    let ChannelTopics {
        status, duty, sv, ..
    } = ros.channel("pw01");
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
    ros.matched(&duty).await;
    command_until(&duty, Float64 { data: 40.0 }, &status, |s| {
        s.duty_commanded == 40.0
    })
    .await
    .expect("a good command first");

    // NaN and infinities: refused, the last valid command stays in force (001).
    for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let _ = duty.publish(Float64 { data: bad });
    }
    let a = pw01_until(&diag, "three refusals reported", |d| {
        kv(d, "rejected_commands") == "3"
    })
    .await;
    let d = pw01_diag(&a).unwrap();
    assert_eq!(d.level, DiagnosticStatus::WARN);
    assert!(
        d.message.starts_with("last duty command refused"),
        "{}",
        d.message
    );
    assert!(
        kv(d, "last_rejection").contains("infinite"),
        "{:?}",
        d.values
    );
    // A status sent after the refusals were reported, not one queued from before them.
    let reported = a.header.stamp.to_nanos();
    let s = wait_for(&status, LONG, |s: &ChannelStatus| {
        s.stamp.to_nanos() > reported
    })
    .await
    .expect("status still published after the refusals");
    assert_eq!(s.duty_commanded, 40.0, "the last good command is in force");
    assert!(node
        .log()
        .contains("duty command refused: duty command is NaN"));

    // Out of range: clamped and flagged (001, 002), reported with the reason.
    let s = command_until(&duty, Float64 { data: 150.0 }, &status, |s| {
        s.command_clamped
    })
    .await
    .expect("150 % clamped");
    assert_eq!(s.duty_commanded, 100.0);
    let a = pw01_until(&diag, "clamping", |d| d.message.contains("clamped")).await;
    assert_eq!(pw01_diag(&a).unwrap().level, DiagnosticStatus::WARN);
    let s = command_until(&duty, Float64 { data: -5.0 }, &status, |s| {
        s.command_clamped && s.duty_commanded == 0.0
    })
    .await
    .expect("-5 % clamped to 0");
    assert_eq!(s.duty_commanded, 0.0);
    // The running period completes first (next_period), then the output stays off.
    wait_for(&status, LONG, |s: &ChannelStatus| {
        !s.output && s.duty_applied == 0.0
    })
    .await
    .expect("0 % applied");
    ros.matched(&sv).await;
    let s = command_until(&sv, UInt16 { data: 5000 }, &status, |s| {
        s.command_clamped && s.duty_commanded == 100.0
    })
    .await
    .expect("SV 5000 clamped to 4095");
    assert!(s.enabled);
    // The line is written by the report thread and read from the node's stderr by a thread of
    // this test: it can come a moment after the status that says the same.
    assert!(
        node.log_until(LONG, |log| log.contains("SV 5000 is outside 0..4095"))
            .await,
        "no log line for the clamped SV:\n{}",
        node.log()
    );

    // A good command clears the flag.
    command_until(&duty, Float64 { data: 20.0 }, &status, |s| {
        !s.command_clamped && s.duty_commanded == 20.0
    })
    .await
    .expect("back to a good command");
    let mut node = node;
    assert!(node.running());
    node.stop_ok();
}

/// Wall-clock time now, ns since the Unix epoch (the clock of the node's stamps).
fn wall_ns() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as i64
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_watchdog_trips_to_error() {
    let node = NodeProc::launch(&ros_params(&[
        "pw01.period_ms:=100",
        "pw01.command_timeout_ms:=300",
    ]));
    let mut ros = Ros::new(node.domain);
    let ChannelTopics {
        status,
        duty,
        enable,
        ..
    } = ros.channel("pw01");
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
    ros.matched(&enable).await;
    command_until(&enable, Bool { data: true }, &status, |s| s.enabled)
        .await
        .expect("enabled");
    ros.matched(&duty).await;
    // The watchdog counts from the channel's creation, so it has tripped before now: the duty
    // command recovers it, and only a trip after that recovery is the one it must cause.
    let trips_before = node.log().matches("watchdog tripped").count();
    let mut sent = 0;
    let mut recovered = None;
    for _ in 0..10 {
        sent = wall_ns();
        let _ = duty.publish(Float64 { data: 50.0 });
        recovered = wait_for(&status, Duration::from_secs(1), |s: &ChannelStatus| {
            s.duty_commanded == 50.0 && !s.watchdog_tripped
        })
        .await;
        if recovered.is_some() {
            break;
        }
    }
    let recovered = recovered.expect("the duty command recovers the watchdog");
    // No further command: 300 ms after the node took it (after it was sent), the watchdog
    // forces the output off.
    let s = wait_for(&status, LONG, |s: &ChannelStatus| s.watchdog_tripped)
        .await
        .expect("watchdog trips after the command");
    assert!(!s.active);
    assert_eq!(s.duty_commanded, 50.0);
    let after_ms = (s.stamp.to_nanos() - sent) as f64 / 1e6;
    assert!(
        (300.0..2300.0).contains(&after_ms),
        "tripped {after_ms:.1} ms after the command was sent, expected 300 ms after it was taken"
    );
    let a = pw01_until(&diag, "ERROR after the command", |d| {
        d.level == DiagnosticStatus::ERROR && kv(d, "duty_commanded_pct") == "50.000"
    })
    .await;
    assert!(a.header.stamp.to_nanos() >= recovered.stamp.to_nanos());
    assert!(pw01_diag(&a).unwrap().message.starts_with("watchdog"));
    assert!(
        node.log_until(LONG, |log| log.matches("watchdog tripped").count()
            > trips_before)
            .await,
        "no log line for the trip after the command:\n{}",
        node.log()
    );
    node.stop_ok();
}
