//! A flood of malformed samples on a command topic, as any participant on the domain can send
//! it: the node keeps running and its log stays readable — a few lines per kind, then one count
//! of what was suppressed — instead of one WARN per sample.

use crate::ros_harness::*;
use serde::Serialize;
use std::time::Duration;

/// One byte where a std_msgs/Float64 has eight: not decodable as the topic's type.
#[derive(Serialize)]
struct Truncated(u8);

/// Published as the topic's own type, so it matches the node's subscription.
impl TopicType for Truncated {
    const PKG: &'static str = "std_msgs";
    const NAME: &'static str = "Float64";
}

const UNREADABLE: &str = "unreadable message";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_samples_give_a_few_lines_and_a_count() {
    let mut node = NodeProc::launch(&[]);
    let mut ros = Ros::new(node.domain);
    let bad = ros.publisher::<Truncated>("/pwm_actuator/pw01/duty");
    ros.matched(&bad).await;
    let sent = 300;
    for i in 0..sent {
        let _ = bad.publish(Truncated(i as u8));
        tokio::time::sleep(Duration::from_millis(3)).await;
    }
    assert!(
        node.wait_log(UNREADABLE, LONG),
        "the node never said it got unreadable samples:\n{}",
        node.log()
    );
    // The first window (10 s) ends; its count is written even though the flood has stopped.
    assert!(
        node.wait_log("similar messages suppressed", Duration::from_secs(25)),
        "no count of the suppressed lines:\n{}",
        node.log()
    );
    assert!(node.running(), "the node stopped:\n{}", node.log());
    let log = node.log();
    let lines = log.lines().filter(|l| l.contains(UNREADABLE)).count();
    // 10 lines, and the count (which quotes the last one).
    assert!(
        lines <= 11,
        "{lines} lines about unreadable samples of {sent} sent:\n{log}"
    );
    let count = log
        .lines()
        .find(|l| l.contains("similar messages suppressed"))
        .unwrap_or_default();
    assert!(count.contains(UNREADABLE), "{count}");
    node.stop_ok();
}
