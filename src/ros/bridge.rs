//! The state the ROS side shares between its tasks, and the two directions through it:
//! ROS inputs (commands, parameter changes through either door) become engine requests, and
//! engine reports become ROS messages, diagnostics and log lines.
//!
//! "One state, two doors": the parameter services and the `~/<ch>/params` topic both go through
//! [`Bridge::set_params`], which checks a change whole, hands the new channel configurations to
//! the output thread, and only then commits the values and announces them on
//! `/parameter_events`. A refused change leaves everything as it was.
//!
//! Nothing here blocks for long: locks are held for bounded work, publishes never wait for a
//! slow subscriber (see [`super::qos`]), and the output thread is only ever reached through its
//! wait-free request queue.

use super::console::EdgeLines;
use super::diagnostics::{clamp_text, percent, status_changed, status_msg, ChannelHealth};
use super::msg::{self, DiagnosticArray, DiagnosticStatus, Header};
use super::params::{self, show_value, ParamError, ParamStore, Phase};
use crate::clock;
use crate::core::{Channel, Command, Event, Nanos};
use crate::engine::{EngineError, Input, Report, Request, Requests};
use log::{debug, error, info, warn};
use ros2_client::builtin_interfaces::Time;
use ros2_client::parameters::raw;
use ros2_client::{ParameterValue, Publisher};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

/// Locks a mutex; a poisoned lock (a panic elsewhere, which ends the process anyway through
/// the panic hook) still gives access to the data.
pub fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Why a parameter change was refused.
#[derive(Debug, thiserror::Error)]
pub enum ChangeError {
    /// The values were refused.
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The output thread did not take the new configuration; nothing changed.
    #[error("the output thread did not take the new settings ({source}); nothing changed")]
    Engine {
        /// The engine's error.
        #[source]
        source: EngineError,
    },
}

/// The per-channel publishers.
pub struct ChannelPubs {
    /// `~/<ch>/edges`.
    pub edges: Publisher<msg::OutputEdge>,
    /// `~/<ch>/e1`.
    pub e1: Publisher<msg::Bool>,
    /// `~/<ch>/status`.
    pub status: Publisher<msg::ChannelStatus>,
}

/// What the pump remembers between reports.
struct PumpState {
    lines: EdgeLines,
    e1_published: Vec<Option<bool>>,
    levels_published: Vec<u8>,
    dropped_seen: u64,
    /// Edges of the current batch, shown at its end with the status that follows them.
    batch_edges: Vec<crate::engine::EdgeReport>,
}

/// The shared state of the ROS side.
pub struct Bridge {
    /// Node base name (after remapping), for diagnostics names.
    pub node_name: String,
    /// Fully qualified node name, for `/parameter_events`.
    pub fqn: String,
    /// Channel names, index = channel.
    pub names: Vec<String>,
    /// Monotonic ns at start, the origin of console times.
    pub start_ns: Nanos,
    params: Mutex<ParamStore>,
    requests: Mutex<Requests>,
    param_events: Publisher<raw::ParameterEvent>,
    pubs: Vec<ChannelPubs>,
    diagnostics: Publisher<DiagnosticArray>,
    health: Mutex<Vec<ChannelHealth>>,
    pump: Mutex<PumpState>,
    status_rate_bits: AtomicU64,
    dropped: AtomicU64,
    /// Set when an output fault stopped the output thread.
    pub fault: AtomicBool,
    /// Woken when diagnostics should be published at once (a level changed).
    pub diag_now: tokio::sync::Notify,
    /// Woken when the node must stop (output fault, output thread gone).
    pub stop: tokio::sync::Notify,
    /// Woken when `status_rate_hz` changes.
    pub status_rate_changed: tokio::sync::Notify,
}

impl Bridge {
    /// Assembles the bridge. `hardware_ids` names each channel's line (or `sim`).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        node_name: String,
        fqn: String,
        store: ParamStore,
        requests: Requests,
        param_events: Publisher<raw::ParameterEvent>,
        pubs: Vec<ChannelPubs>,
        diagnostics: Publisher<DiagnosticArray>,
        hardware_ids: Vec<String>,
    ) -> Bridge {
        let names: Vec<String> = (0..store.channels()).map(params::channel_name).collect();
        let now = clock::monotonic_ns();
        let health = names
            .iter()
            .zip(
                hardware_ids
                    .iter()
                    .map(String::as_str)
                    .chain(std::iter::repeat("sim")),
            )
            .enumerate()
            .map(|(ch, (n, hw))| {
                let mut h = ChannelHealth::new(n, hw);
                // Until the output thread reports, the channel is as the core creates it:
                // disabled, output off, duty 0.
                h.status = store
                    .channel_config(ch)
                    .ok()
                    .map(|cfg| Channel::new(cfg, now).status(now));
                h
            })
            .collect();
        let rate = store.double("status_rate_hz").unwrap_or(10.0);
        let lines = store.int("edge_log_rate").unwrap_or(10).clamp(0, 1000) as u32;
        let n = names.len();
        Bridge {
            node_name,
            fqn,
            start_ns: clock::monotonic_ns(),
            params: Mutex::new(store),
            requests: Mutex::new(requests),
            param_events,
            pubs,
            diagnostics,
            health: Mutex::new(health),
            pump: Mutex::new(PumpState {
                lines: EdgeLines::new(n, lines),
                e1_published: vec![None; n],
                levels_published: vec![u8::MAX; n],
                dropped_seen: 0,
                batch_edges: Vec::new(),
            }),
            status_rate_bits: AtomicU64::new(rate.to_bits()),
            dropped: AtomicU64::new(0),
            fault: AtomicBool::new(false),
            diag_now: tokio::sync::Notify::new(),
            stop: tokio::sync::Notify::new(),
            status_rate_changed: tokio::sync::Notify::new(),
            names,
        }
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.names.len()
    }

    /// The periodic status rate, Hz (0 = on change only).
    pub fn status_rate_hz(&self) -> f64 {
        f64::from_bits(self.status_rate_bits.load(Ordering::Relaxed))
    }

    /// Runs `f` on the parameter store (read access for the services).
    pub fn with_params<R>(&self, f: impl FnOnce(&ParamStore) -> R) -> R {
        f(&lock(&self.params))
    }

    // ---------------------------------------------------------------- inputs

    /// Queues a request for the output thread; a full or closed queue is logged.
    pub fn send(&self, channel: usize, input: Input) -> Result<(), EngineError> {
        let r = lock(&self.requests).send(Request { channel, input });
        if let Err(e) = &r {
            warn!(
                "{}: request not delivered to the output thread: {e}",
                self.names.get(channel).map_or("?", String::as_str)
            );
        }
        r
    }

    /// A duty command from `~/<ch>/duty` or `~/<ch>/sv`. The core refuses NaN and infinities
    /// and clamps out-of-range values; its verdict comes back as a report.
    pub fn command(&self, channel: usize, command: Command) {
        debug!(
            "{}: command {command:?}",
            self.names.get(channel).map_or("?", String::as_str)
        );
        let _ = self.send(channel, Input::Command(command));
    }

    /// EN from `~/<ch>/enable` (or from the start-up value). Logged when it changes.
    pub fn enable(&self, channel: usize, on: bool) {
        let was = lock(&self.health)
            .get_mut(channel)
            .and_then(|h| h.last_enable.replace(on));
        let name = self.names.get(channel).map_or("?", String::as_str);
        if was != Some(on) {
            info!("{name}: {}", if on { "enabled" } else { "disabled" });
        } else {
            debug!("{name}: enable {on} (unchanged)");
        }
        let _ = self.send(channel, Input::Enable(on));
    }

    /// Applies a parameter change through either door (`door` names it in the log), checked
    /// whole; see the module documentation.
    pub fn set_params(
        &self,
        items: Vec<(String, ParameterValue)>,
        door: &str,
    ) -> Result<(), ChangeError> {
        let mut store = lock(&self.params);
        let accepted = match store.check(&items, Phase::Live) {
            Ok(a) => a,
            Err(e) => {
                drop(store);
                self.refused(&items, door, &e.to_string());
                return Err(e.into());
            }
        };
        // The output thread first: if it cannot take the new configurations, nothing changes.
        let mut sent = Vec::new();
        for (ch, cfg) in &accepted.configs {
            if let Err(source) = lock(&self.requests).send(Request {
                channel: *ch,
                input: Input::Config(*cfg),
            }) {
                for done in sent {
                    if let Ok(old) = store.channel_config(done) {
                        let _ = lock(&self.requests).send(Request {
                            channel: done,
                            input: Input::Config(old),
                        });
                    }
                }
                drop(store);
                let e = ChangeError::Engine { source };
                self.refused(&items, door, &e.to_string());
                return Err(e);
            }
            sent.push(*ch);
        }
        let changed = store.commit(&accepted);
        drop(store);
        for note in &accepted.notes {
            info!("{note}");
        }
        for (name, value) in &accepted.changes {
            info!("parameter {name} = {} (via {door})", show_value(value));
            match name.as_str() {
                "status_rate_hz" => {
                    if let ParameterValue::Double(r) = value {
                        self.status_rate_bits.store(r.to_bits(), Ordering::Relaxed);
                        self.status_rate_changed.notify_one();
                    }
                }
                "edge_log_rate" => {
                    if let ParameterValue::Integer(r) = value {
                        lock(&self.pump).lines.set_rate((*r).clamp(0, 1000) as u32);
                    }
                }
                _ => {}
            }
        }
        if accepted.changes.is_empty() {
            debug!("parameters unchanged (via {door})");
        }
        self.publish_param_event(Vec::new(), changed);
        Ok(())
    }

    /// Logs a refusal and records it in the diagnostics of the channels it concerns.
    fn refused(&self, items: &[(String, ParameterValue)], door: &str, reason: &str) {
        warn!("parameter change refused (via {door}): {reason}");
        let mut health = lock(&self.health);
        let mut chans: Vec<usize> = items
            .iter()
            .filter_map(|(n, _)| params::channel_of(n).map(|(c, _)| c))
            .filter(|c| *c < health.len())
            .collect();
        chans.sort_unstable();
        chans.dedup();
        let now = clock::monotonic_ns();
        for c in chans {
            health[c].last_refusal = Some((reason.to_string(), now));
        }
        drop(health);
        self.diag_now.notify_one();
    }

    /// Records a refusal that names no parameter (e.g. an empty `set`) for `channel`.
    pub fn refused_message(&self, channel: usize, door: &str, reason: &str) {
        warn!("parameter change refused (via {door}): {reason}");
        if let Some(h) = lock(&self.health).get_mut(channel) {
            h.last_refusal = Some((reason.to_string(), clock::monotonic_ns()));
        }
        self.diag_now.notify_one();
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

    // --------------------------------------------------------------- outputs

    /// Publishes E1 = `e1` for `channel` (latched).
    pub fn publish_e1(&self, channel: usize, e1: bool) {
        if let Some(p) = self.pubs.get(channel) {
            if let Err(e) = p.e1.publish(msg::Bool { data: e1 }) {
                warn!("{}: cannot publish e1: {e}", self.names[channel]);
            }
        }
        lock(&self.pump).e1_published[channel] = Some(e1);
    }

    /// Handles one report from the output thread.
    pub fn handle(&self, report: Report) {
        match report {
            Report::Edge(e) => self.on_edge(&e),
            Report::Core { channel, event } => self.on_event(channel, event),
            Report::Status {
                channel,
                status,
                at_ns: _,
            } => {
                let changed = {
                    let mut health = lock(&self.health);
                    let Some(h) = health.get_mut(channel) else {
                        return;
                    };
                    let changed = h.status.is_none_or(|old| status_changed(&old, &status));
                    h.status = Some(status);
                    changed
                };
                if changed {
                    self.publish_status(channel, &status);
                }
            }
            Report::OutputFault { channel } => {
                if let Some(h) = lock(&self.health).get_mut(channel) {
                    h.output_fault = true;
                }
                error!(
                    "{}: writing the output failed; every output was driven off and the output \
                     thread stopped",
                    self.names.get(channel).map_or("?", String::as_str)
                );
                self.fault.store(true, Ordering::SeqCst);
                self.publish_diagnostics();
                self.stop.notify_one();
            }
        }
    }

    fn on_edge(&self, e: &crate::engine::EdgeReport) {
        let ch = e.channel;
        if ch >= self.names.len() {
            return;
        }
        {
            let mut health = lock(&self.health);
            let h = &mut health[ch];
            h.edges += 1;
            h.max_late_ns = h.max_late_ns.max(e.lateness_ns());
        }
        let m = msg::OutputEdge {
            stamp: Time::from_nanos(e.wall_ns),
            channel: (ch + 1).min(u8::MAX as usize) as u8,
            level: e.level.is_high(),
            seq: e.seq,
            lateness_ns: e.lateness_ns(),
        };
        if self.pubs[ch].edges.publish(m).is_err() {
            lock(&self.health)[ch].publish_failures += 1;
        }
        // Its console line is written after the batch, from the status snapshot the output
        // thread sends ahead of the edges it explains.
        lock(&self.pump).batch_edges.push(*e);
    }

    /// The console lines for the edges of the batch just handled.
    fn edge_lines(&self) {
        let edges = std::mem::take(&mut lock(&self.pump).batch_edges);
        if edges.is_empty() {
            return;
        }
        let snapshots: Vec<(f64, bool)> = lock(&self.health)
            .iter()
            .map(|h| {
                h.status
                    .map_or((0.0, false), |s| (percent(s.duty_commanded), s.e1))
            })
            .collect();
        let mut lines = Vec::new();
        {
            let mut pump = lock(&self.pump);
            for e in &edges {
                let (duty, e1) = snapshots.get(e.channel).copied().unwrap_or((0.0, false));
                lines.extend(pump.lines.edge(
                    e.channel,
                    &self.names[e.channel],
                    e,
                    self.start_ns,
                    duty,
                    e1,
                ));
            }
        }
        for l in lines {
            info!("{l}");
        }
    }

    fn on_event(&self, ch: usize, event: Event) {
        let Some(name) = self.names.get(ch) else {
            return;
        };
        let now = clock::monotonic_ns();
        match event {
            Event::Flags { e1, limited } => {
                let last = lock(&self.pump).e1_published[ch];
                if last != Some(e1) {
                    self.publish_e1(ch, e1);
                    if e1 {
                        info!("{name}: E1 set: the duty cannot be reproduced because of a minimum time");
                    } else {
                        info!("{name}: E1 cleared");
                    }
                }
                debug!("{name}: flags e1={e1} limited={limited}");
            }
            Event::Watchdog { tripped } => {
                lock(&self.health)[ch].watchdog = tripped;
                if tripped {
                    warn!(
                        "{name}: watchdog tripped: no duty command within command_timeout_ms; \
                         output forced off"
                    );
                } else {
                    info!("{name}: watchdog cleared: a command arrived");
                }
            }
            Event::Rejected(err) => {
                {
                    let mut health = lock(&self.health);
                    health[ch].rejected += 1;
                    health[ch].last_rejection = Some((err.to_string(), now));
                }
                warn!("{name}: duty command refused: {err}");
            }
            Event::Clamped { requested, applied } => {
                let text = {
                    let mut health = lock(&self.health);
                    let h = &mut health[ch];
                    let text = clamp_text(requested, applied);
                    h.clamped += 1;
                    h.last_clamp = Some((text.clone(), now));
                    text
                };
                warn!("{name}: duty command out of range: {text}");
            }
            Event::Missed { edges } => {
                lock(&self.health)[ch].missed += u64::from(edges);
                warn!("{name}: the output thread woke late; {edges} scheduled edges were merged");
            }
            Event::Plan(_) | Event::Edge { .. } => {}
        }
    }

    fn publish_status(&self, ch: usize, s: &crate::core::Status) {
        let m = status_msg(ch, s, clock::monotonic_ns(), clock::wall_ns());
        if self.pubs[ch].status.publish(m).is_err() {
            lock(&self.health)[ch].publish_failures += 1;
        }
    }

    /// Publishes every channel's latest status (the periodic `status_rate_hz` messages).
    pub fn publish_all_status(&self) {
        let snapshots: Vec<_> = lock(&self.health).iter().map(|h| h.status).collect();
        for (ch, s) in snapshots.into_iter().enumerate() {
            if let Some(s) = s {
                self.publish_status(ch, &s);
            }
        }
    }

    /// After a batch of reports: summaries of held-back edge lines, lost reports, and an
    /// immediate diagnostics message if a level changed.
    pub fn after_batch(&self, dropped_total: u64) {
        self.edge_lines();
        let now = clock::monotonic_ns();
        self.dropped.store(dropped_total, Ordering::Relaxed);
        let summaries = lock(&self.pump).lines.flush(&self.names, now);
        for s in summaries {
            info!("{s}");
        }
        let levels: Vec<u8> = lock(&self.health).iter().map(|h| h.level(now)).collect();
        let mut pump = lock(&self.pump);
        if dropped_total > pump.dropped_seen {
            warn!(
                "{} reports from the output thread were lost (the ROS side did not keep up)",
                dropped_total - pump.dropped_seen
            );
            pump.dropped_seen = dropped_total;
        }
        if levels != pump.levels_published {
            drop(pump);
            self.diag_now.notify_one();
        }
    }

    /// Publishes `/diagnostics` now.
    pub fn publish_diagnostics(&self) {
        let now = clock::monotonic_ns();
        let dropped = self.dropped.load(Ordering::Relaxed);
        let (status, levels): (Vec<DiagnosticStatus>, Vec<u8>) = lock(&self.health)
            .iter()
            .map(|h| {
                let d = h.to_status(&self.node_name, now, dropped);
                let l = d.level;
                (d, l)
            })
            .unzip();
        let arr = DiagnosticArray {
            header: Header {
                stamp: Time::from_nanos(clock::wall_ns()),
                frame_id: String::new(),
            },
            status,
        };
        if let Err(e) = self.diagnostics.publish(arr) {
            debug!("cannot publish /diagnostics: {e}");
        }
        lock(&self.pump).levels_published = levels;
    }
}
