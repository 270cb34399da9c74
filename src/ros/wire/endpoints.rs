//! The node's topics, publishers and subscriptions, created with its identity and remapping
//! rules, and the task that hands each received message to a callback.

use crate::ros::config::args::Remap;
use crate::ros::config::names::{to_ros_name, NameError, NameKind, NodeIdentity};
use crate::ros::interface::msg::RosMessage;
use crate::ros::interface::qos;
use futures::StreamExt;
use log::{debug, warn};
use ros2_client::{Message, Node, Publisher, QosProfile, Subscription};
use tokio::task::JoinHandle;

/// Why an endpoint (a topic, publisher, subscription or service) of the node cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum EndpointError {
    /// Its name does not resolve (e.g. a bad remap).
    #[error(transparent)]
    Name(#[from] NameError),
    /// DDS refused to create it.
    #[error("ROS: cannot create {what}")]
    Create {
        /// What: `topic /pwm_actuator/pw01/duty`, `service /pwm_actuator/reset_estop`, ...
        what: String,
        /// Why (ros2-client's error).
        #[source]
        source: ros2_client::CreateError,
    },
}

/// Maps a creation error of ros2-client to [`EndpointError::Create`] naming `what`.
pub(crate) fn create_err(
    what: impl Into<String>,
) -> impl FnOnce(ros2_client::CreateError) -> EndpointError {
    let what = what.into();
    move |source| EndpointError::Create { what, source }
}

/// Resolves a topic name of this node.
pub(crate) fn topic(
    node: &Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    type_name: ros2_client::MessageTypeName,
    qos: &QosProfile,
) -> Result<(String, rustdds::Topic), EndpointError> {
    let full = id.resolve(name, NameKind::Topic, remaps)?;
    let t = node
        .create_topic(&to_ros_name(&full)?, type_name, qos)
        .map_err(create_err(format!("topic {full}")))?;
    Ok((full, t))
}

pub(crate) fn publisher<M: RosMessage>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    qos: QosProfile,
) -> Result<Publisher<M>, EndpointError> {
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("publishing {full}");
    node.create_publisher(&t, Some(qos))
        .map_err(create_err(format!("publisher {full}")))
}

pub(crate) fn subscription<M: RosMessage + 'static>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
) -> Result<(String, Subscription<M>), EndpointError> {
    let qos = qos::commands();
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("subscribing {full}");
    let s = node
        .create_subscription(&t, Some(qos))
        .map_err(create_err(format!("subscription {full}")))?;
    Ok((full, s))
}

/// Runs `on_msg` for every message of `sub`, until the task is aborted.
pub(crate) fn listen<M, F>(full: String, sub: Subscription<M>, mut on_msg: F) -> JoinHandle<()>
where
    M: Message + Send + Sync + 'static,
    F: FnMut(M) + Send + 'static,
{
    tokio::spawn(async move {
        let stream = sub.async_stream();
        futures::pin_mut!(stream);
        while let Some(r) = stream.next().await {
            match r {
                Ok((m, _info)) => on_msg(m),
                Err(e) => warn!("{full}: unreadable message: {e}"),
            }
        }
    })
}
