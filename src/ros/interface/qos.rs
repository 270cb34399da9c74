//! The QoS of every topic and service of the node, in one place so docs/interface.md can state
//! them.
//!
//! | topic / service | reliability | durability | history | notes |
//! |---|---|---|---|---|
//! | `~/<ch>/duty`, `~/<ch>/sv`, `~/<ch>/enable`, `~/<ch>/params` (in) | reliable | volatile | keep last 10 | rclpy's default (`create_publisher(..., 10)`); best-effort publishers do not match |
//! | `feedback_topic` (in, `sensor_msgs/Temperature`) | best effort | volatile | keep last 10 | matches best-effort and reliable publishers |
//! | `~/<ch>/setpoint` (in) | reliable | volatile | keep last 10 | as the commands |
//! | `~/<ch>/edges` (out) | reliable | volatile | keep last 100 | never blocks the node: a full send window drops and counts |
//! | `~/<ch>/status` (out) | reliable | volatile | keep last 10 | as above |
//! | `~/<ch>/e1` (out) | reliable | transient local | keep last 1 | a late subscriber asking for transient local gets the current E1 |
//! | `/diagnostics` (out) | reliable | volatile | keep last 10 | as `diagnostic_updater` publishes |
//! | parameter services | reliable | volatile | keep last 10 | `rmw_qos_profile_services_default` |
//! | `/parameter_events` (out) | reliable | transient local | keep last 1 | ros2-client's topic QoS; rclpy's volatile subscribers match |
//! | `/rosout` (out) | reliable | transient local | keep last 1 | ros2-client's topic QoS |
//!
//! Only QoS values and the input size bound here; no entities are created.

use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::QosProfile;
use std::time::Duration;

/// The largest sample the node accepts on any input (its topics and its parameter services),
/// in bytes of serialized payload. Anything larger is dropped by the DDS layer before it is
/// reassembled from fragments, cached or decoded (on Zenoh: before it is copied or decoded),
/// and counted (`samples_too_large` on `/diagnostics`). The largest legitimate input is a `set_parameters` request naming every
/// parameter of 99 channels: 1 691 parameters, 141 600 bytes; a `ChannelParams` naming every
/// field is under 400 bytes.
pub const MAX_SAMPLE_BYTES: usize = 256 * 1024;

/// Samples and requests larger than [`MAX_SAMPLE_BYTES`] that the node's Zenoh endpoints
/// dropped since start (RustDDS counts the DDS side's).
static ZENOH_TOO_LARGE: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Held by the tests that drop oversize Zenoh inputs, so that each counts only its own.
#[cfg(all(test, feature = "zenoh"))]
pub(crate) static ZENOH_TOO_LARGE_TESTS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Counts one sample or request a Zenoh endpoint dropped for its size.
pub fn note_zenoh_too_large() {
    ZENOH_TOO_LARGE.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
}

/// Samples and requests the node's Zenoh endpoints dropped for their size since start; 0 on
/// DDS. Added to RustDDS's count in `samples_too_large` on `/diagnostics`.
pub fn zenoh_too_large() -> u64 {
    ZENOH_TOO_LARGE.load(std::sync::atomic::Ordering::Relaxed)
}

/// `/rosout` on Zenoh, as ros2-client makes it on DDS (the table above): reliable, transient
/// local, keep last 1.
pub fn rosout() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 1 })
        .durability(Durability::TransientLocal)
}

/// Subscriptions to commands: rclpy's default profile (reliable, volatile, keep last 10).
pub fn commands() -> QosProfile {
    QosProfile::publisher_default().history(History::KeepLast { depth: 10 })
}

/// Edge events: reliable, keep last 100; a publish never waits for a slow subscriber.
pub fn edges() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 100 })
        .reliability_reliable(WhenFull::Fail)
}

/// Status snapshots: reliable, keep last 10, never waiting.
pub fn status() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 10 })
        .reliability_reliable(WhenFull::Fail)
}

/// E1: latched (transient local, keep last 1).
pub fn e1() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 1 })
        .durability(Durability::TransientLocal)
        .reliability_reliable(WhenFull::Wait(Duration::from_millis(10)))
}

/// `/diagnostics`: reliable, volatile, keep last 10.
pub fn diagnostics() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 10 })
        .reliability_reliable(WhenFull::Wait(Duration::from_millis(10)))
}

/// Sensor readings (`feedback_topic`): best effort, volatile, keep last 10, as rclpy's
/// `qos_profile_sensor_data` asks; a best-effort reader matches best-effort and reliable
/// writers alike.
pub fn sensor() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 10 })
        .reliability(ros2_client::qos::Reliability::BestEffort)
}

/// Parameter services: `rmw_qos_profile_services_default` (reliable, volatile, keep last 10).
pub fn services() -> QosProfile {
    QosProfile::publisher_default().history(History::KeepLast { depth: 10 })
}

/// `/parameter_events` on Zenoh: rclcpp's `rmw_qos_profile_parameter_events` (reliable,
/// volatile, keep last 1000). On DDS the topic is ros2-client's own (reliable, transient local,
/// keep last 1).
pub fn parameter_events() -> QosProfile {
    QosProfile::publisher_default()
        .history(History::KeepLast { depth: 1000 })
        .durability(Durability::Volatile)
}

/// An action server's endpoints as ROS 2's defaults: its three services as
/// [`services`], volatile; feedback reliable, volatile, keep last 10; the status
/// transient-local keep last 1 (`rcl_action_qos_profile_status_default`), which action
/// clients ask for.
pub fn action_server() -> ros2_client::action::ActionServerQosPolicies {
    let service = services().durability(Durability::Volatile);
    ros2_client::action::ActionServerQosPolicies {
        goal_service: service.clone(),
        result_service: service.clone(),
        cancel_service: service,
        feedback_publisher: QosProfile::publisher_default()
            .history(History::KeepLast { depth: 10 })
            .durability(Durability::Volatile),
        status_publisher: QosProfile::publisher_default()
            .history(History::KeepLast { depth: 1 })
            .durability(Durability::TransientLocal),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::qos::Reliability;

    #[test]
    fn profiles() {
        assert!(matches!(
            commands().reliability,
            Reliability::Reliable { .. }
        ));
        assert_eq!(commands().durability, Durability::Volatile);
        assert_eq!(commands().history, History::KeepLast { depth: 10 });
        assert_eq!(e1().durability, Durability::TransientLocal);
        assert_eq!(
            edges().reliability,
            Reliability::Reliable {
                when_full: WhenFull::Fail
            }
        );
    }
}
