//! ROS → output thread: commands, enables and parameter changes ([`inputs`]), the e-stop
//! ([`estop`]), the heater loop's readings, setpoints and fault resets ([`heater`]), its
//! autotune action ([`autotune`]), the valves' positions ([`valve`]), the managed node
//! ([`lifecycle`]), the parameter services ([`param_services`]),
//! what the callbacks share with the report side ([`node_state`], the notes of [`inputs`]),
//! and the reply paths of the requests that wait for the output thread's answer ([`replies`]).
//!
//! Layer 4 of the ROS shell: may import [`interface`](super::interface),
//! [`config`](super::config) and [`wire`](super::wire); never the outbound side.

pub mod autotune;
pub mod estop;
pub mod heater;
pub mod inputs;
pub mod lifecycle;
pub mod node_state;
pub mod param_services;
pub mod replies;
pub mod valve;
