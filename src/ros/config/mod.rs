//! What the node is told before it runs: the command line ([`cli`], [`args`]), its names
//! ([`names`]), its parameters and their one table ([`params`]), split-range pairs
//! ([`split`]), the valves ([`valve`]) and their state files ([`valve_state`]), discovery ([`discovery`]), Zenoh session ([`zenoh`]) and security ([`security`]) settings, the logger
//! they set up ([`logging`]), and what the start-up makes of them all ([`start`]).
//!
//! Layer 2 of the ROS shell: may import [`interface`](super::interface) only. `safe-off`, which
//! must work when the node is dead, depends on this layer and nothing above it.

pub mod args;
pub mod cli;
pub mod discovery;
pub mod logging;
pub mod names;
pub mod params;
pub mod security;
pub mod split;
pub mod start;
pub mod valve;
pub mod valve_state;
pub mod zenoh;
