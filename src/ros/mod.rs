//! The ROS 2 shell around the output thread: topics, parameters, diagnostics, logging and the
//! command line.
//!
//! It only translates: ROS messages and parameter changes become engine requests, engine
//! reports become ROS messages and log lines. It never decides timing (the core does) and
//! never writes an output (the engine does).
//!
//! - [`args`]: `--ros-args` and parameter files; [`cli`]: the node's own options.
//! - [`name_clash`]: a warning when another node on the domain has this node's name.
//! - [`names`]: node identity, `~` expansion and remapping.
//! - [`params`]: parameter declarations and the one store both parameter doors write through.
//! - [`msg`]: the messages; [`qos`]: their QoS.
//! - [`inputs`]: ROS callbacks -> output thread (commands, enables, parameter changes);
//!   [`services`]: the parameter services.
//! - [`reporter`]: output thread -> ROS (edges, E1, status, `/diagnostics`), owned by the report
//!   thread.
//! - [`discovery`]: the discovery range and static peers, applied or refused.
//! - [`security`]: the SROS2 environment, refused or warned about.
//! - [`split`]: split-range pairs (one signed command for a hot and a cold channel).
//! - [`estop`]: the latched emergency stop (`~/estop`, `~/reset_estop`, `estop_timeout_ms`).
//! - [`lifecycle`]: the managed node (`--managed`): states, transitions, services.
//! - [`diagnostics`], [`console`], [`logging`]: what the node says about itself;
//!   [`frequency`]: the command-rate check of each channel; [`node_state`]: what the callbacks
//!   share with the report thread without a lock (command counts, lifecycle state, e-stop).
//! - [`node`]: start-up, wiring, shutdown ([`run`]).

pub mod args;
pub mod cli;
pub mod console;
pub mod diagnostics;
pub mod discovery;
pub mod endpoints;
pub mod estop;
pub mod frequency;
pub mod inputs;
pub mod lifecycle;
pub mod logging;
pub mod msg;
pub mod name_clash;
pub mod names;
pub mod node;
pub mod node_state;
pub mod params;
pub mod qos;
pub mod reporter;
pub mod security;
pub mod services;
pub mod split;

pub use node::run;
