//! The ROS 2 shell around the output thread: topics, services, parameters, diagnostics,
//! logging and the command line.
//!
//! It only translates: ROS messages and parameter changes become requests to the output thread, its
//! reports become ROS messages and log lines. It never decides timing (the core does) and
//! never writes an output (the output thread does).
//!
//! Five folders, each a layer that may import only the layers before it (checked by
//! `scripts/check-layers.py`, run by the test command), and [`node`], which wires them:
//!
//! 1. [`interface`]: the ROS interface's types — messages, QoS, the lifecycle graph.
//! 2. [`config`]: what the node is told before it runs — command line, `--ros-args`, names,
//!    parameters and their table, split-range pairs, discovery, security, the logger.
//! 3. [`wire`]: making endpoints — subscriptions, publishers, the one service maker, the
//!    name-clash watch.
//! 4. [`inbound`]: ROS → output thread — commands, enables and parameter changes
//!    ([`inbound::inputs`]), the e-stop, the lifecycle, the parameter services, and the state
//!    the callbacks share with the report side.
//! 5. [`outbound`]: output thread → ROS — edges, status, E1, `/diagnostics`, the command-rate
//!    check, the console.
//!
//! The inbound side never imports the outbound side: what it tells the reporter goes through
//! the notes queue and the shared state it owns.

pub mod config;
pub mod inbound;
pub mod interface;
pub mod node;
pub mod outbound;
pub mod wire;

pub use node::run;
