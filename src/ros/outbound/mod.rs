//! Output thread → ROS: the reporter on the report thread ([`reporter`]): edges, E1, status,
//! `/diagnostics` ([`diagnostics`]), the command-rate check ([`frequency`]) and the console
//! ([`console`]), the valves' state and diagnostics ([`valve`]); the MCAP trace of what it
//! publishes ([`mcap_trace`]); every trace's state on `/diagnostics` and in the log
//! ([`traces`]).
//!
//! Layer 5 of the ROS shell: may import every layer before it.

pub mod console;
pub mod decimal;
pub mod diagnostics;
pub mod frequency;
pub mod mcap_trace;
pub mod reporter;
pub mod traces;
pub mod valve;
