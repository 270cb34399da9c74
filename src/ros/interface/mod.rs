//! The ROS interface's types: the messages the node exchanges ([`msg`]) and the bytes they
//! travel as ([`cdr`]), their QoS ([`qos`]),
//! the managed node's state graph ([`lifecycle`]), the type hashes its endpoints announce
//! ([`type_hash`]) and the message definitions written into MCAP traces ([`schema`]).
//!
//! Layer 1 of the ROS shell: imports nothing else of it.

pub mod cdr;
pub mod lifecycle;
pub mod msg;
pub mod qos;
pub mod schema;
pub mod type_hash;
