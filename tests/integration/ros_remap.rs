//! Remapping over ROS: `-r __node:=`, `-r __ns:=` and a topic remap, as a launch file passes
//! them. Topics, services, diagnostics names and `/parameter_events` all follow.

use crate::ros_harness::*;
use pwm_actuator::ros::interface::msg::{ChannelStatus, DiagnosticArray, Float64};
use ros2_client::parameters::raw;
use ros2_client::ParameterValue as V;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn node_name_namespace_and_topic_remaps() {
    let node = NodeProc::launch(&[
        "--ros-args",
        "-r",
        "__node:=heater",
        "-r",
        "__ns:=/plant",
        "-r",
        "heater:~/pw01/duty:=/heater_duty",
        "-r",
        "other_node:~/pw01/status:=/never",
        "-p",
        "pw01.enable:=true",
        "-p",
        "pw01.period_ms:=100",
    ]);
    assert!(
        node.log().contains("/plant/heater running"),
        "{}",
        node.log()
    );
    let mut ros = Ros::new(node.domain);
    let status = ros.sub::<ChannelStatus>("/plant/heater/pw01/status", default_qos());
    let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
    let events = ros.sub::<raw::ParameterEvent>("/parameter_events", default_qos());
    let duty = ros.publisher::<Float64>("/heater_duty");
    ros.matched(&duty).await;
    let s = command_until(&duty, Float64 { data: 60.0 }, &status, |s| {
        s.duty_commanded == 60.0
    })
    .await
    .expect("the remapped duty topic drives pw01");
    assert!(s.enabled);

    let a = wait_for(&diag, LONG, |a: &DiagnosticArray| !a.status.is_empty())
        .await
        .expect("diagnostics");
    let names: Vec<&str> = a.status.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "heater: pw01",
            "heater: pw02",
            "heater: pw01 command frequency",
            "heater: pw02 command frequency",
            "heater: node"
        ]
    );

    let p = ros.params("/plant/heater");
    p.ready(&ros).await;
    assert!(p.set(&[("pw02.period_ms", V::Integer(250))]).await[0].0);
    let ev = wait_for(&events, LONG, |e: &raw::ParameterEvent| {
        !e.changed_parameters.is_empty()
    })
    .await
    .expect("parameter event");
    assert_eq!(ev.node, "/plant/heater");

    let log = node.stop_ok();
    assert!(
        log.contains("[heater]: "),
        "the logger is named after the node: {log}"
    );
}
