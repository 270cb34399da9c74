//! What the ROS callbacks share with the report thread without a lock: the node's lifecycle
//! state (the cell the lifecycle itself keeps it in), the e-stop, the number of duty commands each channel received, and the settings of
//! the command-rate check (`expected_command_hz_min/max`, `command_hz_window`,
//! `command_hz_tolerance`), and the reply paths of the requests that wait for the output
//! thread's answer ([`replies`](super::replies)).
//!
//! Every other field is an atomic written by one side and read by the other: a callback never waits
//! for the report thread, and the report thread never waits for a callback. Nothing here
//! publishes or reads a clock. A change the report thread must show at once (the e-stop, a
//! note queued for it) wakes it ([`NodeState::wake_reporter`]): it sleeps until something is
//! due rather than looking again and again.

use crate::core::heater::ResetRefusal;
use crate::output_thread::ReportWaker;
use crate::ros::config::params::ParamStore;
pub use crate::ros::config::params::{
    DEFAULT_COMMAND_HZ_TOLERANCE, DEFAULT_COMMAND_HZ_WINDOW, MAX_COMMAND_HZ_WINDOW,
    MAX_EXPECTED_COMMAND_HZ,
};
use crate::ros::inbound::replies::{Mailbox, ReplySlots, Tickets};
use crate::ros::interface::lifecycle::{state, state_label};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicU8, AtomicUsize, Ordering};
use std::sync::Arc;

/// The bounds of one channel's command-rate check, Hz, with the node's window and tolerance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateSettings {
    /// `expected_command_hz_min`, Hz; 0 = no lower bound.
    pub min_hz: f64,
    /// `expected_command_hz_max`, Hz; 0 = no upper bound.
    pub max_hz: f64,
    /// `command_hz_tolerance`: the bounds are widened to `min * (1 - t)` and `max * (1 + t)`.
    pub tolerance: f64,
    /// `command_hz_window`, diagnostics runs (seconds), at least 1.
    pub window: usize,
}

impl RateSettings {
    /// Whether the rate is checked at all (either bound set).
    pub fn checked(&self) -> bool {
        self.min_hz > 0.0 || self.max_hz > 0.0
    }
}

impl Default for RateSettings {
    fn default() -> RateSettings {
        RateSettings {
            min_hz: 0.0,
            max_hz: 0.0,
            tolerance: DEFAULT_COMMAND_HZ_TOLERANCE,
            window: DEFAULT_COMMAND_HZ_WINDOW,
        }
    }
}

/// One channel's command stream: how many commands arrived, and its expected rate.
#[derive(Debug, Default)]
struct CommandStream {
    commands: AtomicU64,
    /// f64 bits, Hz.
    min_hz: AtomicU64,
    /// f64 bits, Hz.
    max_hz: AtomicU64,
}

/// The shared state (see the module documentation).
#[derive(Debug)]
pub struct NodeState {
    /// A managed (lifecycle) node.
    managed: bool,
    /// The lifecycle state's id (`lifecycle_msgs/State`), kept by the lifecycle itself.
    lifecycle: Arc<AtomicU8>,
    estop_latched: AtomicBool,
    estop_latches: AtomicU64,
    channels: Box<[CommandStream]>,
    window: AtomicUsize,
    /// f64 bits.
    tolerance: AtomicU64,
    /// `heater_fault_latches_estop`.
    heater_estop: AtomicBool,
    /// Tickets of the requests that wait for the output thread's answer.
    tickets: Tickets,
    /// Per channel, the reply path of the `~/<ch>/reset_fault` that waits.
    resets: ReplySlots<Result<(), ResetRefusal>>,
    /// Per channel, the reports of autotune runs the action has not taken yet.
    autotunes: Mailbox,
    /// Wakes the report thread, once it runs.
    reporter: std::sync::OnceLock<ReportWaker>,
}

impl NodeState {
    /// The state of a node with `channels` channels: unmanaged (and so always `active`),
    /// e-stop released, no command yet, the rate check off with the default window and
    /// tolerance.
    pub fn new(channels: usize) -> NodeState {
        NodeState {
            managed: false,
            lifecycle: Arc::new(AtomicU8::new(state::ACTIVE)),
            estop_latched: AtomicBool::new(false),
            estop_latches: AtomicU64::new(0),
            channels: (0..channels).map(|_| CommandStream::default()).collect(),
            window: AtomicUsize::new(DEFAULT_COMMAND_HZ_WINDOW),
            tolerance: AtomicU64::new(DEFAULT_COMMAND_HZ_TOLERANCE.to_bits()),
            heater_estop: AtomicBool::new(false),
            tickets: Tickets::default(),
            resets: ReplySlots::new(channels),
            autotunes: Mailbox::new(channels),
            reporter: std::sync::OnceLock::new(),
        }
    }

    /// Whether a heater fault latches the e-stop of every channel.
    pub fn heater_estop(&self) -> bool {
        self.heater_estop.load(Ordering::Acquire)
    }

    /// A fresh ticket for a request that waits for the output thread's answer (a heater
    /// fault reset, an autotune goal).
    pub fn ticket(&self) -> u32 {
        self.tickets.next()
    }

    /// Per channel, the reply paths of `~/<ch>/reset_fault`: filed by the service, answered by
    /// the report thread with the core's `FaultReset` event.
    pub fn resets(&self) -> &ReplySlots<Result<(), ResetRefusal>> {
        &self.resets
    }

    /// Per channel, the autotune reports for the action: filed by the report thread, taken by
    /// the action's task.
    pub fn autotunes(&self) -> &Mailbox {
        &self.autotunes
    }

    /// The state of a node with the store's channels, managed if `managed` says so, the rate
    /// check set as the store says.
    pub fn from_store(store: &ParamStore) -> NodeState {
        let mut s = NodeState::new(store.channels());
        s.managed = store.node_settings().managed;
        s.heater_estop.store(
            store.node_settings().heater_fault_latches_estop,
            Ordering::Release,
        );
        s.apply_params(store);
        s
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.channels.len()
    }

    /// The cell the lifecycle keeps its current state id in (`lifecycle_msgs/State`), for
    /// [`Lifecycle::new`](crate::ros::inbound::lifecycle::Lifecycle::new).
    pub fn lifecycle_cell(&self) -> Arc<AtomicU8> {
        Arc::clone(&self.lifecycle)
    }

    /// The lifecycle state as shown on `/diagnostics`: its `lifecycle_msgs/State` label
    /// (`unconfigured`, `inactive`, `active`, `configuring`, ...) for a managed node,
    /// `unmanaged` otherwise.
    pub fn lifecycle_label(&self) -> &'static str {
        if self.managed {
            state_label(self.lifecycle.load(Ordering::Acquire))
        } else {
            "unmanaged"
        }
    }

    /// Whether the e-stop is latched.
    pub fn estop_latched(&self) -> bool {
        self.estop_latched.load(Ordering::Acquire)
    }

    /// How many times the e-stop latched since start-up.
    pub fn estop_latches(&self) -> u64 {
        self.estop_latches.load(Ordering::Relaxed)
    }

    /// The e-stop latched (`true`, counted) or was reset (`false`); the report thread is woken
    /// to publish the new level.
    pub fn set_estop(&self, latched: bool) {
        if latched {
            self.estop_latches.fetch_add(1, Ordering::Relaxed);
        }
        self.estop_latched.store(latched, Ordering::Release);
        self.wake_reporter();
    }

    /// From now on [`NodeState::wake_reporter`] wakes the report thread through `waker` (set
    /// once, when the report thread starts).
    pub fn set_reporter_waker(&self, waker: ReportWaker) {
        let _ = self.reporter.set(waker);
    }

    /// Wakes the report thread (nothing before it runs): something it must look at now has
    /// changed here, or was queued for it.
    pub fn wake_reporter(&self) {
        if let Some(w) = self.reporter.get() {
            w.wake();
        }
    }

    /// Counts a duty command for `channel` (any of `~/<ch>/duty`, `~/<ch>/sv`, a split-range
    /// command), whatever the core then makes of it.
    pub fn count_command(&self, channel: usize) {
        if let Some(c) = self.channels.get(channel) {
            c.commands.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Commands `channel` received since start-up (0 for a channel that does not exist).
    pub fn commands(&self, channel: usize) -> u64 {
        self.channels
            .get(channel)
            .map_or(0, |c| c.commands.load(Ordering::Relaxed))
    }

    /// The rate check's settings for `channel`.
    pub fn rate_settings(&self, channel: usize) -> RateSettings {
        let load = |a: &AtomicU64| f64::from_bits(a.load(Ordering::Relaxed));
        let (min_hz, max_hz) = self
            .channels
            .get(channel)
            .map_or((0.0, 0.0), |c| (load(&c.min_hz), load(&c.max_hz)));
        RateSettings {
            min_hz,
            max_hz,
            tolerance: load(&self.tolerance),
            window: self.window.load(Ordering::Relaxed).max(1),
        }
    }

    /// Takes the rate check's settings from the parameter store (at start-up and after every
    /// accepted change); values the store does not hold keep their defaults.
    pub fn apply_params(&self, store: &ParamStore) {
        for (ch, c) in self.channels.iter().enumerate() {
            let (min, max) = store.channel(ch).map_or((0.0, 0.0), |v| {
                (v.expected_command_hz_min, v.expected_command_hz_max)
            });
            c.min_hz.store(min.to_bits(), Ordering::Relaxed);
            c.max_hz.store(max.to_bits(), Ordering::Relaxed);
        }
        let settings = store.node_settings();
        self.window
            .store(settings.command_hz_window, Ordering::Relaxed);
        self.tolerance
            .store(settings.command_hz_tolerance.to_bits(), Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::config::params::Stage;
    use ros2_client::ParameterValue as V;

    #[test]
    fn counts_and_settings_are_shared() {
        let s = NodeState::new(2);
        assert_eq!(s.lifecycle_label(), "unmanaged");
        s.count_command(1);
        s.count_command(1);
        s.count_command(7);
        assert_eq!((s.commands(0), s.commands(1), s.commands(7)), (0, 2, 0));
        s.set_estop(true);
        s.set_estop(false);
        s.set_estop(true);
        assert!(s.estop_latched());
        assert_eq!(s.estop_latches(), 2);

        assert_eq!(s.rate_settings(0), RateSettings::default());
        assert!(!s.rate_settings(0).checked());
        let mut store = ParamStore::new(2);
        let a = store
            .check(
                &[
                    ("pw02.expected_command_hz_min".into(), V::Double(5.0)),
                    ("pw02.expected_command_hz_max".into(), V::Double(20.0)),
                    ("command_hz_window".into(), V::Integer(10)),
                    ("command_hz_tolerance".into(), V::Double(0.25)),
                ],
                Stage::Live,
            )
            .unwrap();
        store.commit(&a);
        let a = store
            .check(&[("managed".into(), V::Boolean(true))], Stage::StartUp)
            .unwrap();
        store.commit(&a);
        let s = NodeState::from_store(&store);
        // A managed node shows the state its lifecycle keeps in the shared cell.
        s.lifecycle_cell().store(state::INACTIVE, Ordering::Release);
        assert_eq!(s.lifecycle_label(), "inactive");
        s.lifecycle_cell()
            .store(state::CONFIGURING, Ordering::Release);
        assert_eq!(s.lifecycle_label(), "configuring");
        let r = s.rate_settings(1);
        assert_eq!(
            r,
            RateSettings {
                min_hz: 5.0,
                max_hz: 20.0,
                tolerance: 0.25,
                window: 10
            }
        );
        assert!(r.checked());
        assert!(!s.rate_settings(0).checked());
    }
}
