//! The node-level parameters as one typed struct, [`NodeSettings`], mapped from the parameter
//! table as channel parameters map into the core's [`ChannelParams`](crate::core::ChannelParams):
//! each node-level entry of the table says which field its value sets, and its default is
//! written there only. Code reads the settings, never a node-level parameter by name; a live
//! change is routed by comparing the settings before and after it.

use crate::core::{Bank, Phase};
use std::path::PathBuf;

/// Every node-level parameter, typed (see the table in `table.rs` for units, ranges and
/// defaults).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NodeSettings {
    /// `channels`: number of channels.
    pub channels: usize,
    /// `output`: `true` for the GPIO backend, `false` for the simulated sink.
    pub gpio: bool,
    /// `managed`: a managed (lifecycle) node.
    pub managed: bool,
    /// `trace`: trace files, in order.
    pub trace: Vec<PathBuf>,
    /// `trace_max_mb`: what the files of each trace may hold together, MB.
    pub trace_max_mb: u64,
    /// `status_rate_hz`: periodic status rate, Hz (0 = on change only).
    pub status_rate_hz: f64,
    /// `edge_log_rate`: edge lines per second and channel (0 = none).
    pub edge_log_rate: u32,
    /// `phase` and `max_simultaneous_on`: the node-level planner.
    pub bank: Bank,
    /// `command_hz_window`: window of the command-rate check, diagnostics runs.
    pub command_hz_window: usize,
    /// `command_hz_tolerance`: tolerance of the command-rate check, a fraction.
    pub command_hz_tolerance: f64,
    /// `split`: the split-range pairs, as written (parsed against the channels at start-up).
    pub split: String,
    /// `valve`: the three-point valves, as written (parsed against the channels at start-up).
    pub valve: String,
    /// `state_dir`: where the valves' state files live; empty for none.
    pub state_dir: String,
    /// `heartbeat_line`: the heartbeat line's offset, if there is one.
    pub heartbeat_line: Option<u32>,
    /// `heartbeat_chip`: the heartbeat line's chip.
    pub heartbeat_chip: PathBuf,
    /// `heartbeat_hz`: the heartbeat square wave's frequency, Hz.
    pub heartbeat_hz: f64,
    /// `estop_timeout_ms`: the heartbeat e-stop's timeout, ms (0 = off).
    pub estop_timeout_ms: u64,
    /// `rt_priority`: SCHED_FIFO priority of the output thread, if asked for.
    pub rt_priority: Option<i32>,
    /// `use_sim_time`: always false here.
    pub use_sim_time: bool,
    /// `heater_fault_latches_estop`: a heater fault of any channel latches the e-stop.
    pub heater_fault_latches_estop: bool,
}

impl NodeSettings {
    /// `phase` from its spelling (the table refused any other).
    pub(super) fn set_phase(&mut self, spelled: &str) {
        self.bank.phase = spelled.parse::<Phase>().unwrap_or_default();
    }
}
