//! Making the node's endpoints: subscriptions, publishers and the tasks that listen
//! ([`endpoints`]), with the one service maker every service goes through, the action
//! server with its goals ([`action`]), the watch for another node with this node's
//! name ([`name_clash`]), and rmw_zenoh's wire format: keys, liveliness tokens, attachments
//! and GIDs ([`zenoh_keys`]), and with the `zenoh` feature the node's Zenoh session
//! ([`zenoh_session`]) its publishers ([`zenoh_pub`]), subscriptions
//! ([`zenoh_sub`]) and service servers ([`zenoh_srv`]).
//!
//! Layer 3 of the ROS shell: may import [`interface`](super::interface) and
//! [`config`](super::config).

pub mod action;
pub mod endpoints;
pub mod mw;
pub mod name_clash;
pub mod zenoh_keys;
#[cfg(feature = "zenoh")]
pub mod zenoh_pub;
#[cfg(feature = "zenoh")]
pub mod zenoh_session;
#[cfg(feature = "zenoh")]
pub mod zenoh_srv;
#[cfg(feature = "zenoh")]
pub mod zenoh_sub;
