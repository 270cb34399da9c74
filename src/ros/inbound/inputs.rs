//! The input side of the ROS shell: what the ROS callbacks (topics and parameter services)
//! share. Commands and enables become requests to the output thread; parameter changes through
//! either door go through [`Inputs::set_params`].
//!
//! "One state, two doors": the parameter services and the `~/<ch>/params` topic both go through
//! [`Inputs::set_params`], which checks a change whole, hands the new channel configurations to
//! the output thread, and only then commits the values and announces them on
//! `/parameter_events`. A new planner goes to the output thread's safety path under the
//! store's lock, with the commit: concurrent changes reach the thread in the order the store
//! took them. A refused change leaves everything as it was and is told to the
//! reporter (for `/diagnostics`) through its small queue, as are the rates it keeps.
//!
//! The locks here (the parameter store, the request queue's producer, the last enables) are
//! shared by the callbacks only, never with the report thread, and are held for bounded work.
//! What the report thread reads of this side without a note (command counts, the command-rate
//! check's settings, the e-stop) is in the atomics of [`NodeState`].

use crate::clock;
use crate::core::{split_command, Command, Nanos};
use crate::output::panic_off::lock_ignore_poison as lock;
use crate::output_thread::{
    Acknowledgment, Input, OutputThreadError, Request, Requests, SafetyPath,
};
use crate::ros::config::params::ChannelStart;
use crate::ros::config::params::{self, show_value, Accepted, ParamError, ParamStore, Stage};
use crate::ros::config::split::SplitPair;
use crate::ros::inbound::node_state::NodeState;
use crate::ros::interface::msg;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use crate::ros::wire::mw::Publisher;
use log::{debug, info, warn};
use ros2_client::builtin_interfaces::Time;
use ros2_client::parameters::raw;
use ros2_client::ParameterValue;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::SyncSender;
use std::sync::{Arc, Mutex};
use tokio::task::JoinHandle;

/// What the ROS callbacks tell the reporter.
#[derive(Debug, Clone, PartialEq)]
pub enum Note {
    /// A parameter change was refused: the reason, shown as WARN on the channels it names.
    Refused {
        /// Channels the refused change named.
        channels: Vec<usize>,
        /// Why, as given to the client.
        reason: String,
        /// When, monotonic ns.
        at: Nanos,
    },
    /// `status_rate_hz` changed, Hz (0 = on change only).
    StatusRate(f64),
    /// `edge_log_rate` changed, lines per second and channel.
    EdgeLogRate(u32),
}

/// Notes that may wait for the reporter at once; more are dropped and counted.
pub const NOTE_QUEUE: usize = 64;

/// Why a parameter change was refused.
#[derive(Debug, thiserror::Error)]
pub enum ChangeError {
    /// The values were refused.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The output thread did not take the new configuration; nothing changed.
    #[error("the output thread did not take the new settings ({source}); nothing changed")]
    OutputThread {
        /// The output thread's error.
        #[source]
        source: OutputThreadError,
    },
}

/// A parameter change [`Inputs::apply_params`] has applied: committed to the store, its
/// channel and valve configurations queued for the output thread and its planner, if it
/// changed, stored for the thread. [`Inputs::announce`] finishes it.
pub struct AppliedChange {
    /// The door it came through, for the log.
    door: String,
    accepted: Accepted,
    /// The changed values, for `/parameter_events`.
    changed: Vec<raw::Parameter>,
    /// The output thread's acknowledgment of the new planner, when the planner changed.
    bank: Option<Acknowledgment>,
    /// The new `status_rate_hz`, Hz, when it changed.
    status_rate_hz: Option<f64>,
    /// The new `edge_log_rate`, lines per second and channel, when it changed.
    edge_log_rate: Option<u32>,
}

/// The state the ROS callbacks share (see the module documentation).
pub struct Inputs {
    /// Fully qualified node name, for `/parameter_events`.
    pub fqn: String,
    /// Channel names, index = channel.
    pub names: Vec<String>,
    params: Mutex<ParamStore>,
    requests: Mutex<Requests>,
    /// The safety inputs' own path, apart from the queue's lock (see [`SafetyPath`]).
    safety: SafetyPath,
    enables: Mutex<Vec<Option<bool>>>,
    param_events: Publisher<raw::ParameterEvent>,
    notes: SyncSender<Note>,
    notes_lost: AtomicU64,
    state: Arc<NodeState>,
}

impl Inputs {
    /// The input side over `store` and the output thread's `requests`; `notes` goes to the
    /// reporter (a bounded queue, see [`NOTE_QUEUE`]), and `state` is shared with it (the
    /// store's command-rate settings are applied to it now and after every change).
    pub fn new(
        fqn: String,
        store: ParamStore,
        requests: Requests,
        param_events: Publisher<raw::ParameterEvent>,
        notes: SyncSender<Note>,
        state: Arc<NodeState>,
    ) -> Inputs {
        let names: Vec<String> = (0..store.channels()).map(params::channel_name).collect();
        state.apply_params(&store);
        Inputs {
            fqn,
            enables: Mutex::new(vec![None; names.len()]),
            names,
            params: Mutex::new(store),
            safety: requests.safety(),
            requests: Mutex::new(requests),
            param_events,
            notes,
            notes_lost: AtomicU64::new(0),
            state,
        }
    }

    /// The state shared with the report thread.
    pub fn state(&self) -> &NodeState {
        &self.state
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.names.len()
    }

    /// The safety inputs' path to the output thread: never full, taken before any queued
    /// request, with an acknowledgment once the lines have it.
    pub fn safety(&self) -> &SafetyPath {
        &self.safety
    }

    /// Channel `channel`'s name (`pw01`, ...), `?` beyond the channels.
    pub(crate) fn name(&self, channel: usize) -> &str {
        self.names.get(channel).map_or("?", String::as_str)
    }

    /// Runs `f` on the parameter store (read access for the services).
    pub fn with_params<R>(&self, f: impl FnOnce(&ParamStore) -> R) -> R {
        f(&lock(&self.params))
    }

    /// Notes that could not be queued for the reporter (it did not keep up).
    pub fn notes_lost(&self) -> u64 {
        self.notes_lost.load(Ordering::Relaxed)
    }

    fn note(&self, note: Note) {
        if self.notes.try_send(note).is_err() {
            self.notes_lost.fetch_add(1, Ordering::Relaxed);
        }
        self.state.wake_reporter();
    }

    /// Queues a request for the output thread; a full or closed queue is logged.
    pub fn send(&self, channel: usize, input: Input) -> Result<(), OutputThreadError> {
        let r = lock(&self.requests).send(Request { channel, input });
        if let Err(e) = &r {
            warn!(
                "{}: request not delivered to the output thread: {e}",
                self.name(channel)
            );
        }
        r
    }

    /// A duty command from `~/<ch>/duty`, `~/<ch>/sv`, `~/<ch>/fraction` or a split-range pair, counted for the
    /// channel's command-rate check. The core refuses NaN and infinities and clamps
    /// out-of-range values; its verdict, with the command and its unit, comes back as a report.
    pub fn command(&self, channel: usize, command: Command) {
        debug!("{}: command {command:?}", self.name(channel));
        self.state.count_command(channel);
        let _ = self.send(channel, Input::Command(command));
    }

    /// Records that the channel is disabled without a request (an e-stop reset disables every
    /// channel in the output thread), so its next `enable=true` is logged as a change.
    pub fn note_disabled(&self, channel: usize) {
        if let Some(e) = lock(&self.enables).get_mut(channel) {
            *e = Some(false);
        }
    }

    /// EN from `~/<ch>/enable` (or from the start-up value). Logged when it changes.
    pub fn enable(&self, channel: usize, on: bool) {
        let was = lock(&self.enables)
            .get_mut(channel)
            .and_then(|e| e.replace(on));
        let name = self.name(channel);
        if was != Some(on) {
            info!("{name}: {}", if on { "enabled" } else { "disabled" });
        } else {
            debug!("{name}: enable {on} (unchanged)");
        }
        let _ = self.send(channel, Input::Enable(on));
    }

    /// Applies a parameter change through either door (`door` names it in the log), checked
    /// whole; see the module documentation. A change of the node's planner is answered only
    /// once the output thread has taken it (awaited, up to `SAFETY_TAKE_BOUND`, 250 ms).
    /// [`Inputs::apply_params`], then [`Inputs::announce`].
    pub async fn set_params(
        &self,
        items: Vec<(String, ParameterValue)>,
        door: &str,
    ) -> Result<(), ChangeError> {
        let change = self.apply_params(&items, door)?;
        self.announce(change).await;
        Ok(())
    }

    /// A parameter change's first half, all under the store's lock and never blocking: checks
    /// it whole, queues the new channel and valve configurations for the output thread (all or
    /// none: if it cannot take them, nothing changes), commits the values, and stores a changed
    /// planner in the safety path. The planner is stored under the same lock as the commit, so
    /// the output thread takes the planners of concurrent changes in the order the store
    /// committed them, and ends with the store's. A refusal is logged and told to the reporter
    /// here.
    pub fn apply_params(
        &self,
        items: &[(String, ParameterValue)],
        door: &str,
    ) -> Result<AppliedChange, ChangeError> {
        let mut store = lock(&self.params);
        let accepted = match store.check(items, Stage::Live) {
            Ok(a) => a,
            Err(e) => {
                drop(store);
                self.refused(items, door, &e.to_string());
                return Err(e.into());
            }
        };
        // The output thread first, all the new configurations or none: if it cannot take them,
        // nothing changes.
        let new: Vec<Request> = accepted
            .configs
            .iter()
            .map(|&(channel, cfg)| Request {
                channel,
                input: Input::Config(cfg),
            })
            .chain(
                accepted
                    .valve_configs
                    .iter()
                    .map(|&(valve, config)| Request {
                        channel: 0,
                        input: Input::ValveConfig { valve, config },
                    }),
            )
            .collect();
        if let Err(source) = lock(&self.requests).send_all(&new) {
            drop(store);
            let e = ChangeError::OutputThread { source };
            self.refused(items, door, &e.to_string());
            return Err(e);
        }
        let before = store.node_settings();
        let changed = store.commit(&accepted);
        self.state.apply_params(&store);
        let after = store.node_settings();
        // Through the safety path (a lowered limit must not wait behind commands): storing
        // never blocks, and its check begins now; the acknowledgment is awaited once the lock
        // is released.
        let bank = (after.bank != before.bank).then(|| {
            self.safety
                .acknowledgment(self.safety.store(Input::Bank(after.bank)))
        });
        drop(store);
        Ok(AppliedChange {
            door: door.to_string(),
            accepted,
            changed,
            bank,
            status_rate_hz: (after.status_rate_hz != before.status_rate_hz)
                .then_some(after.status_rate_hz),
            edge_log_rate: (after.edge_log_rate != before.edge_log_rate)
                .then_some(after.edge_log_rate),
        })
    }

    /// A parameter change's second half, after [`Inputs::apply_params`]: awaits the output
    /// thread's acknowledgment of a changed planner (a lowered limit acts at once, the phase
    /// at each channel's next period start; one not taken within `SAFETY_TAKE_BOUND`, 250 ms,
    /// has every output switched off through the emergency handle), then logs the change,
    /// tells the reporter of changed rates and announces it on `/parameter_events`. A change
    /// dropped before this is neither logged nor announced, but its planner is checked all the
    /// same ([`SafetyPath::acknowledgment`]).
    pub async fn announce(&self, change: AppliedChange) {
        let AppliedChange {
            door,
            accepted,
            changed,
            bank,
            status_rate_hz,
            edge_log_rate,
        } = change;
        if let Some(ack) = bank {
            if let Err(e) = ack.await {
                log::error!(
                    "the planner's new settings were not taken: {e}; every output switched off \
                     by the emergency handle"
                );
            }
        }
        for note in &accepted.notes {
            info!("{note}");
        }
        for (name, value) in &accepted.changes {
            info!("parameter {name} = {} (via {door})", show_value(value));
        }
        if let Some(hz) = status_rate_hz {
            self.note(Note::StatusRate(hz));
        }
        if let Some(rate) = edge_log_rate {
            self.note(Note::EdgeLogRate(rate));
        }
        if accepted.changes.is_empty() {
            debug!("parameters unchanged (via {door})");
        }
        self.publish_param_event(Vec::new(), changed);
    }

    /// Logs a refusal and tells the reporter, for the diagnostics of the channels it names.
    fn refused(&self, items: &[(String, ParameterValue)], door: &str, reason: &str) {
        warn!("parameter change refused (via {door}): {reason}");
        let mut channels: Vec<usize> = items
            .iter()
            .filter_map(|(n, _)| params::channel_of(n).map(|(c, _)| c))
            .filter(|c| *c < self.channels())
            .collect();
        channels.sort_unstable();
        channels.dedup();
        self.note(Note::Refused {
            channels,
            reason: reason.to_string(),
            at: clock::monotonic_ns(),
        });
    }

    /// Records a refusal that names no parameter (e.g. an empty `set`) for `channel`.
    pub fn refused_message(&self, channel: usize, door: &str, reason: &str) {
        warn!("parameter change refused (via {door}): {reason}");
        self.note(Note::Refused {
            channels: vec![channel],
            reason: reason.to_string(),
            at: clock::monotonic_ns(),
        });
    }

    /// Announces every declared parameter as new on `/parameter_events`, as rclcpp does.
    pub fn announce_declared(&self) {
        let declared = self.with_params(|s| {
            s.all()
                .into_iter()
                .map(|(name, value)| raw::Parameter {
                    name,
                    value: value.into(),
                })
                .collect()
        });
        self.publish_param_event(declared, Vec::new());
    }

    /// The start-up duty and enable of each channel: the duty first, so the first period
    /// already uses it.
    pub fn start_up(&self, channels: &[ChannelStart]) {
        for (ch, c) in channels.iter().enumerate() {
            if c.duty_percent != 0.0 {
                let _ = self.send(ch, Input::Command(Command::Percent(c.duty_percent)));
            }
            if c.enable {
                info!(
                    "{}: enabled at start-up, duty {:.1} %",
                    c.name,
                    c.duty_percent + 0.0
                );
                let _ = self.send(ch, Input::Enable(true));
            }
        }
    }

    /// Publishes a `/parameter_events` message (nothing when both lists are empty).
    pub fn publish_param_event(&self, new: Vec<raw::Parameter>, changed: Vec<raw::Parameter>) {
        if new.is_empty() && changed.is_empty() {
            return;
        }
        let ev = raw::ParameterEvent {
            stamp: Time::from_nanos(clock::wall_ns()),
            node: self.fqn.clone(),
            new_parameters: new,
            changed_parameters: changed,
            deleted_parameters: Vec::new(),
        };
        if let Err(e) = self.param_events.publish(ev) {
            warn!("cannot publish /parameter_events: {e}");
        }
    }
}

/// The inputs of each channel, `~/<ch>/duty`, `~/<ch>/sv`, `~/<ch>/fraction` (004's i_rIput,
/// 0..1), `~/<ch>/enable` and `~/<ch>/params`, and the tasks that hand them to `inputs`; `names`: the channels in order.
pub fn listen_channels(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    names: &[String],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for (ch, name) in names.iter().enumerate() {
        let to_thread = Arc::clone(inputs);
        tasks.push(
            ep.listen(&format!("~/{name}/duty"), move |m: msg::Float64| {
                to_thread.command(ch, Command::Percent(m.data))
            })?,
        );
        let to_thread = Arc::clone(inputs);
        tasks.push(ep.listen(&format!("~/{name}/sv"), move |m: msg::UInt16| {
            to_thread.command(ch, Command::Sv(m.data))
        })?);
        let to_thread = Arc::clone(inputs);
        tasks.push(
            ep.listen(&format!("~/{name}/fraction"), move |m: msg::Float64| {
                to_thread.command(ch, Command::Fraction(m.data))
            })?,
        );
        let to_thread = Arc::clone(inputs);
        tasks.push(ep.listen(&format!("~/{name}/enable"), move |m: msg::Bool| {
            to_thread.enable(ch, m.data)
        })?);
        let to_thread = Arc::clone(inputs);
        let door = format!("~/{name}/params");
        let topic = door.clone();
        tasks.push(ep.listen_async(&topic, move |m: msg::ChannelParams| {
            let (to_thread, door) = (Arc::clone(&to_thread), door.clone());
            async move {
                match params::items_from_msg(ch, &m) {
                    Ok(items) => {
                        // A refusal is logged and recorded by `set_params` itself.
                        let _ = to_thread.set_params(items, &door).await;
                    }
                    Err(e) => to_thread.refused_message(ch, &door, &e.to_string()),
                }
            }
        })?);
    }
    Ok(tasks)
}

/// 001's split range: pairs each hot and cold channel in the output thread (their lines are
/// never high together from the start) and listens on `~/split/<name>/command`.
pub fn listen_splits(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    pairs: &[SplitPair],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for pair in pairs {
        info!(
            "split {}: {} hot, {} cold, dead band {} %",
            pair.name,
            inputs.name(pair.hot),
            inputs.name(pair.cold),
            pair.deadband_pct
        );
        let _ = inputs.send(pair.hot, Input::Pair(pair.cold));
        let _ = inputs.send(pair.cold, Input::Pair(pair.hot));
        let to_thread = Arc::clone(inputs);
        let (hot, cold, band) = (pair.hot, pair.cold, pair.deadband_pct);
        let topic = format!("~/split/{}/command", pair.name);
        tasks.push(ep.listen(&topic, move |m: msg::Float64| {
            let (h, c) = split_command(m.data, band);
            to_thread.command(hot, h);
            to_thread.command(cold, c);
        })?);
    }
    Ok(tasks)
}
