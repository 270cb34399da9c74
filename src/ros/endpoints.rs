//! The node's topics, publishers and subscriptions, created with its identity and remapping
//! rules, and the task that hands each received message to a callback.

use super::args::Remap;
use super::msg::RosMessage;
use super::names::{to_ros_name, NameKind, NodeIdentity};
use super::node::NodeError;
use super::qos;
use futures::StreamExt;
use log::{debug, warn};
use ros2_client::{Message, Node, Publisher, QosProfile, Subscription};
use tokio::task::JoinHandle;

/// Maps a creation error of ros2-client to [`NodeError::Ros`] naming `what`.
pub(crate) fn ros_err(
    what: impl Into<String>,
) -> impl FnOnce(ros2_client::CreateError) -> NodeError {
    let what = what.into();
    move |e| NodeError::Ros {
        what,
        source: Box::new(e),
    }
}

/// Resolves a topic name of this node.
pub(crate) fn topic(
    node: &Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    type_name: ros2_client::MessageTypeName,
    qos: &QosProfile,
) -> Result<(String, rustdds::Topic), NodeError> {
    let full = id.resolve(name, NameKind::Topic, remaps)?;
    let t = node
        .create_topic(&to_ros_name(&full)?, type_name, qos)
        .map_err(ros_err(format!("topic {full}")))?;
    Ok((full, t))
}

pub(crate) fn publisher<M: RosMessage>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    qos: QosProfile,
) -> Result<Publisher<M>, NodeError> {
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("publishing {full}");
    node.create_publisher(&t, Some(qos))
        .map_err(ros_err(format!("publisher {full}")))
}

pub(crate) fn subscription<M: RosMessage + 'static>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
) -> Result<(String, Subscription<M>), NodeError> {
    let qos = qos::commands();
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("subscribing {full}");
    let s = node
        .create_subscription(&t, Some(qos))
        .map_err(ros_err(format!("subscription {full}")))?;
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
