//! The managed node's state graph as rcl_lifecycle defines it (`lifecycle_msgs`): state ids,
//! their labels, and the transitions with their ids and labels. Data only; the state machine
//! that walks it is [`inbound::lifecycle`](crate::ros::inbound::lifecycle).

/// State ids (`lifecycle_msgs/State`).
pub mod state {
    /// Unknown.
    pub const UNKNOWN: u8 = 0;
    /// Unconfigured: no line requested.
    pub const UNCONFIGURED: u8 = 1;
    /// Inactive: lines requested, held inactive.
    pub const INACTIVE: u8 = 2;
    /// Active: lines follow their channels.
    pub const ACTIVE: u8 = 3;
    /// Finalized: lines released.
    pub const FINALIZED: u8 = 4;
    /// Transition state: configuring.
    pub const CONFIGURING: u8 = 10;
    /// Transition state: cleaning up.
    pub const CLEANINGUP: u8 = 11;
    /// Transition state: shutting down.
    pub const SHUTTINGDOWN: u8 = 12;
    /// Transition state: activating.
    pub const ACTIVATING: u8 = 13;
    /// Transition state: deactivating.
    pub const DEACTIVATING: u8 = 14;
    /// Transition state: processing an error.
    pub const ERRORPROCESSING: u8 = 15;
}

/// Every state, with its label, in rcl_lifecycle's order.
pub const STATES: [(u8, &str); 11] = [
    (state::UNKNOWN, "unknown"),
    (state::UNCONFIGURED, "unconfigured"),
    (state::INACTIVE, "inactive"),
    (state::ACTIVE, "active"),
    (state::FINALIZED, "finalized"),
    (state::CONFIGURING, "configuring"),
    (state::CLEANINGUP, "cleaningup"),
    (state::SHUTTINGDOWN, "shuttingdown"),
    (state::ACTIVATING, "activating"),
    (state::DEACTIVATING, "deactivating"),
    (state::ERRORPROCESSING, "errorprocessing"),
];

/// The label of state `id`.
pub fn state_label(id: u8) -> &'static str {
    STATES
        .iter()
        .find(|(s, _)| *s == id)
        .map_or("unknown", |(_, l)| l)
}

/// One edge of the graph: transition id, label, start state, goal state.
pub type Edge = (u8, &'static str, u8, u8);

/// rcl_lifecycle's default graph: the five requestable transitions from the primary states
/// and, from each transition state, where success, failure and error lead.
pub const GRAPH: [Edge; 25] = {
    use state::*;
    [
        (1, "configure", UNCONFIGURED, CONFIGURING),
        (10, "transition_success", CONFIGURING, INACTIVE),
        (11, "transition_failure", CONFIGURING, UNCONFIGURED),
        (12, "transition_error", CONFIGURING, ERRORPROCESSING),
        (2, "cleanup", INACTIVE, CLEANINGUP),
        (20, "transition_success", CLEANINGUP, UNCONFIGURED),
        (21, "transition_failure", CLEANINGUP, INACTIVE),
        (22, "transition_error", CLEANINGUP, ERRORPROCESSING),
        (3, "activate", INACTIVE, ACTIVATING),
        (30, "transition_success", ACTIVATING, ACTIVE),
        (31, "transition_failure", ACTIVATING, INACTIVE),
        (32, "transition_error", ACTIVATING, ERRORPROCESSING),
        (4, "deactivate", ACTIVE, DEACTIVATING),
        (40, "transition_success", DEACTIVATING, INACTIVE),
        (41, "transition_failure", DEACTIVATING, ACTIVE),
        (42, "transition_error", DEACTIVATING, ERRORPROCESSING),
        (5, "shutdown", UNCONFIGURED, SHUTTINGDOWN),
        (6, "shutdown", INACTIVE, SHUTTINGDOWN),
        (7, "shutdown", ACTIVE, SHUTTINGDOWN),
        (50, "transition_success", SHUTTINGDOWN, FINALIZED),
        (51, "transition_failure", SHUTTINGDOWN, FINALIZED),
        (52, "transition_error", SHUTTINGDOWN, ERRORPROCESSING),
        (60, "transition_success", ERRORPROCESSING, UNCONFIGURED),
        (61, "transition_failure", ERRORPROCESSING, FINALIZED),
        (62, "transition_error", ERRORPROCESSING, FINALIZED),
    ]
};
