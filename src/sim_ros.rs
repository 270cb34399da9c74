//! What the simulated plants (`sim-heater`, `sim-valve`) share as ROS participants: the tokio
//! runtime they run on, their node on the environment's domain and discovery settings, and
//! topic creation.

use pwm_actuator::ros::config::discovery;
use pwm_actuator::ros::config::start::domain_id_from;
use pwm_actuator::ros::interface::type_hash;
use ros2_client::{Context, NodeName, NodeOptions, QosProfile};
use std::future::Future;

/// Runs `serve` on a one-worker runtime; the exit status: 0 when it returns `Ok`, 1 when the
/// runtime cannot start or `serve` fails (the reason printed after `tool`).
pub fn block_on(tool: &str, serve: impl Future<Output = Result<(), String>>) -> i32 {
    let rt = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("{tool}: cannot start the runtime: {e}");
            return 1;
        }
    };
    match rt.block_on(serve) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("{tool}: {e}");
            1
        }
    }
}

/// The node `/<name>` on `ROS_DOMAIN_ID` with the environment's discovery settings, without
/// rosout, its endpoints announcing their type hashes as the node's do, spun on the runtime.
/// Call it inside [`block_on`]'s future.
pub fn start_node(name: &str) -> Result<ros2_client::Node, String> {
    let domain = domain_id_from(std::env::var("ROS_DOMAIN_ID").ok().as_deref())
        .map_err(|e| e.to_string())?;
    let disc = discovery::read(|k| std::env::var(k).ok()).map_err(|e| e.to_string())?;
    type_hash::announce().map_err(|e| e.to_string())?;
    let participant = disc
        .participant(domain, None)
        .map_err(|e| format!("the DDS participant: {e}"))?;
    let context = Context::from_domain_participant(participant)
        .map_err(|e| format!("the DDS participant: {e}"))?;
    let name = NodeName::new("/", name).map_err(|e| e.to_string())?;
    let mut node = context
        .new_node(name, NodeOptions::new().enable_rosout(false))
        .map_err(|e| format!("node: {e}"))?;
    let spinner = node.spinner().map_err(|e| format!("spinner: {e}"))?;
    tokio::spawn(async move {
        let _ = spinner.spin().await;
    });
    Ok(node)
}

/// The topic `name` (a full ROS name) of type `ty`.
pub fn make_topic(
    node: &ros2_client::Node,
    name: &str,
    ty: ros2_client::MessageTypeName,
    qos: &QosProfile,
) -> Result<rustdds::Topic, String> {
    let ros_name = ros2_client::Name::parse(name).map_err(|e| format!("topic {name}: {e}"))?;
    node.create_topic(&ros_name, ty, qos)
        .map_err(|e| format!("topic {name}: {e}"))
}
