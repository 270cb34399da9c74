//! The node's endpoints whichever middleware carries them: DDS (RustDDS through ros2-client)
//! or, built with the `zenoh` feature, Zenoh as rmw_zenoh speaks it. The rest of the ROS shell
//! holds these types and never names a middleware.

use serde::Serialize;

/// A publisher of `M`.
pub enum Publisher<M: Serialize> {
    /// On DDS.
    Dds(ros2_client::Publisher<M>),
    /// On Zenoh.
    #[cfg(feature = "zenoh")]
    Zenoh(crate::ros::wire::zenoh_pub::ZenohPublisher<M>),
}

/// Why a sample was not sent.
#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    /// DDS did not take it (the writer's error, as text: it holds the message).
    #[error("{0}")]
    Dds(String),
    /// Zenoh did not take it.
    #[cfg(feature = "zenoh")]
    #[error(transparent)]
    Zenoh(#[from] crate::ros::wire::zenoh_pub::PublisherError),
}

impl<M: Serialize> Publisher<M> {
    /// Sends `msg` to every matched subscriber; never waits longer than the QoS allows.
    pub fn publish(&self, msg: M) -> Result<(), PublishError> {
        match self {
            Publisher::Dds(p) => p.publish(msg).map_err(|e| PublishError::Dds(e.to_string())),
            #[cfg(feature = "zenoh")]
            Publisher::Zenoh(p) => Ok(p.publish(&msg)?),
        }
    }
}
