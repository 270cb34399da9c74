//! The reporter: everything the node says about what it did, owned by the report thread.
//!
//! Reports from the output thread (edges, flags, status snapshots, faults) become ROS messages
//! (`~/<ch>/edges`, `~/<ch>/e1`, `~/<ch>/status`), `/diagnostics` and console lines. The
//! reporter also keeps the clocks of what is published periodically: the status messages at
//! `status_rate_hz`, `/diagnostics` once a second and at once when a level changes, and the
//! diagnostics run once a second that measures each channel's command rate
//! ([`FrequencyStatus`]) and closes the window of the output thread's lateness. It is owned by
//! one thread and works through `&mut self`: no lock is shared with the ROS callbacks, which
//! reach it through a small queue of [`Note`]s (parameter refusals and the changes of the rates
//! it keeps) and the atomics of [`NodeState`] (command counts, the rate check's settings, the
//! lifecycle state, the e-stop).
//!
//! Publishing never waits for a slow subscriber (see [`crate::ros::interface::qos`]); what cannot be published
//! is counted.

use crate::clock;
use crate::core::{Event, Nanos, Status};
use crate::output_thread::{EdgeReport, Report};
use crate::ros::config::logging;
use crate::ros::config::params::{MAX_STATUS_RATE_HZ, MIN_STATUS_RATE_HZ};
use crate::ros::inbound::inputs::Note;
use crate::ros::inbound::node_state::NodeState;
use crate::ros::interface::msg::{self, DiagnosticArray, DiagnosticStatus, Header};
use crate::ros::interface::qos::{self, MAX_SAMPLE_BYTES};
use crate::ros::outbound::console::EdgeLines;
use crate::ros::outbound::diagnostics::{
    clamp_text, status_changed, status_msg, ChannelHealth, NodeCounters,
};
use crate::ros::outbound::diagnostics::{
    frequency_status_name, LatenessHistogram, NodeHealth, LOSS_WARN_NS, REFUSAL_WARN_NS,
};
use crate::ros::outbound::frequency::{FrequencyReport, FrequencyStatus};
use crate::ros::outbound::mcap_trace::{McapTrace, TraceKey};
use crate::ros::outbound::traces::TraceReport;
use crate::ros::outbound::valve::ValveOut;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use crate::ros::wire::mw::Publisher;
use log::{debug, error, info, warn};
use ros2_client::builtin_interfaces::Time;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::sync::Arc;
use std::time::Duration;

/// The diagnostics run (command rates, the lateness window) comes this often, ns: one
/// diagnostic_updater run a second, so `command_hz_window` counts seconds. The periodic
/// `/diagnostics` follows each run, with its fresh figures, so `/diagnostics` is published at
/// least this often (the diagnostic_updater's 1 Hz).
const DIAGNOSTICS_RUN_NS: Nanos = 1_000_000_000;

/// At most one extra `/diagnostics` message per this interval when levels change, ns.
const DIAGNOSTICS_COALESCE_NS: Nanos = 50_000_000;

/// The periodic work (status, diagnostics run, periodic `/diagnostics`) waits at most this long
/// for an edge due just after it, so that one wake-up does both, ns; at most a twentieth of the
/// status period (see [`periodic_wake`]).
pub const PERIODIC_SLACK_NS: Nanos = 20_000_000;

/// When the report thread wakes for periodic work due at `due`: at `due`, unless an edge (the
/// end of a channel's running step, in `step_ends`) is due at the same instant or after it by no
/// more than the slack — [`PERIODIC_SLACK_NS`], and at most a twentieth of `status_period` — in
/// which case the edge's report wakes the thread and the periodic work is done with it; it then
/// waits at most the slack, should the edge not come. Periodic messages keep their grid: each is
/// at most the slack late, never early, and the rate is unchanged.
pub fn periodic_wake(
    due: Nanos,
    step_ends: impl Iterator<Item = Nanos>,
    status_period: Option<Nanos>,
) -> Nanos {
    let slack = status_period.map_or(PERIODIC_SLACK_NS, |p| (p / 20).min(PERIODIC_SLACK_NS));
    let edge_soon = step_ends
        .filter(|e| *e >= due && *e - due <= slack)
        .min()
        .is_some();
    if edge_soon {
        due + slack
    } else {
        due
    }
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

impl ChannelPubs {
    /// The publishers of each channel (`names` in order) and `/diagnostics`.
    pub fn create(
        ep: &mut Endpoints<'_>,
        names: &[String],
    ) -> Result<(Vec<ChannelPubs>, Publisher<DiagnosticArray>), EndpointError> {
        let mut pubs = Vec::with_capacity(names.len());
        for name in names {
            pubs.push(ChannelPubs {
                edges: ep.publisher(&format!("~/{name}/edges"), qos::edges())?,
                e1: ep.publisher(&format!("~/{name}/e1"), qos::e1())?,
                status: ep.publisher(&format!("~/{name}/status"), qos::status())?,
            });
        }
        let diagnostics = ep.publisher("/diagnostics", qos::diagnostics())?;
        Ok((pubs, diagnostics))
    }
}

/// What the reporter shares with the node's main task: the request to stop, and whether an
/// output fault caused it.
#[derive(Debug, Default)]
pub struct StopSignal {
    /// Woken when the node must stop (output fault, output thread gone).
    pub stop: tokio::sync::Notify,
    /// Set when an output fault stopped the output thread.
    pub fault: AtomicBool,
}

/// The period of the periodic status at `rate_hz`, or `None` for no periodic status (0, and
/// anything that is not a positive finite rate). Never panics: the parameter checks keep the
/// rate in 0.01..1000 Hz, and whatever reaches here is clamped to that.
pub fn status_period(rate_hz: f64) -> Option<Duration> {
    if !(rate_hz > 0.0 && rate_hz.is_finite()) {
        return None;
    }
    let rate = rate_hz.clamp(MIN_STATUS_RATE_HZ, MAX_STATUS_RATE_HZ);
    // 1/rate is within 1 ms..100 s here, so the conversion cannot fail; the fallback is the
    // slowest period all the same.
    Some(Duration::try_from_secs_f64(1.0 / rate).unwrap_or(Duration::from_secs(100)))
}

/// When the periodic status messages are due.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StatusClock {
    period: Option<Nanos>,
    next: Nanos,
}

impl StatusClock {
    /// A clock at `rate_hz` (0: no periodic status) from `now` (monotonic ns).
    pub fn new(rate_hz: f64, now: Nanos) -> StatusClock {
        let mut c = StatusClock {
            period: None,
            next: now,
        };
        c.set_rate(rate_hz, now);
        c
    }

    /// A new rate applies at once: the next status is one new period from `now`, never at the
    /// end of a period an old, slow rate started.
    pub fn set_rate(&mut self, rate_hz: f64, now: Nanos) {
        self.period = status_period(rate_hz).map(|d| d.as_nanos() as Nanos);
        self.next = now.saturating_add(self.period.unwrap_or(0));
    }

    /// Whether a status is due at `now`; if so, the next one is scheduled a period later (from
    /// `now` after a stall, rather than in a burst).
    pub fn take_due(&mut self, now: Nanos) -> bool {
        match self.period {
            Some(period) if now >= self.next => {
                self.next = self.next.saturating_add(period).max(now);
                true
            }
            _ => false,
        }
    }

    /// When the next status is due, if any.
    pub fn next(&self) -> Option<Nanos> {
        self.period.map(|_| self.next)
    }

    /// The period of the periodic status, ns, if any.
    pub fn period(&self) -> Option<Nanos> {
        self.period
    }

    /// Moves the grid so that the next status is due one period after `at`.
    pub fn restart_at(&mut self, at: Nanos) {
        if let Some(period) = self.period {
            self.next = at.saturating_add(period);
        }
    }
}

/// Where the report thread's once-a-second grid (the periodic status, the diagnostics run and
/// the periodic `/diagnostics`) moves to when the first edge since the start is scheduled at
/// `edge_ns`: to that edge, when it comes before the first diagnostics run (`first_run`), so
/// that the periodic work falls due together with the edges of the first channel to start,
/// whatever the time between the report thread's start and that channel's (whenever the
/// channel's period is a whole number of seconds, or divides one, one wake-up a second does
/// both); `None` (the grid stays) otherwise. The first periodic status and run then come at most
/// a period later than they would have, once; after that the grid is as steady as before.
pub fn grid_for_first_edge(start_ns: Nanos, first_run: Nanos, edge_ns: Nanos) -> Option<Nanos> {
    (edge_ns > start_ns && edge_ns < first_run).then_some(edge_ns)
}

/// The report thread's state (see the module documentation).
pub struct Reporter {
    node_name: String,
    names: Vec<String>,
    start_ns: Nanos,
    pubs: Vec<ChannelPubs>,
    diagnostics: Publisher<DiagnosticArray>,
    health: Vec<ChannelHealth>,
    lines: EdgeLines,
    e1_published: Vec<Option<bool>>,
    levels_published: Vec<u8>,
    counters: NodeCounters,
    dropped_seen: u64,
    too_large_seen: u64,
    notes: Receiver<Note>,
    status: StatusClock,
    last_diagnostics: Nanos,
    /// When the next periodic `/diagnostics` is due: at the start, then at each diagnostics
    /// run (on the grid of `next_run`), monotonic ns.
    next_periodic: Nanos,
    /// Whether an edge was reported since the start (see [`grid_for_first_edge`]).
    edge_seen: bool,
    signal: Arc<StopSignal>,
    state: Arc<NodeState>,
    /// Per channel: the rate check and its latest result as a status.
    rates: Vec<FrequencyStatus>,
    rate_statuses: Vec<DiagnosticStatus>,
    /// The lateness of the edges written since the last diagnostics run.
    lateness: LatenessHistogram,
    node: NodeHealth,
    next_run: Nanos,
    last_run: Nanos,
    /// The MCAP trace of what is published, if any.
    mcap: Option<McapTrace>,
    /// The valves, in the order the output thread numbers them.
    valves: Vec<ValveOut>,
    /// Every trace's state.
    traces: TraceReport,
}

impl Reporter {
    /// A reporter for the channels of `health` (in order), publishing on `pubs` and
    /// `diagnostics`, reading `notes` and `state`, at `status_rate_hz` and `edge_log_rate` to
    /// begin with. Publishes E1 = false for every channel (latched), so a late subscriber gets
    /// a state.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        node_name: String,
        health: Vec<ChannelHealth>,
        pubs: Vec<ChannelPubs>,
        diagnostics: Publisher<DiagnosticArray>,
        notes: Receiver<Note>,
        status_rate_hz: f64,
        edge_log_rate: u32,
        signal: Arc<StopSignal>,
        state: Arc<NodeState>,
    ) -> Reporter {
        let n = health.len();
        let now = clock::monotonic_ns();
        let rates: Vec<FrequencyStatus> = (0..n)
            .map(|ch| FrequencyStatus::new(state.rate_settings(ch).window, state.commands(ch), now))
            .collect();
        // Until the first run, a second from now, there is nothing to judge.
        let rate_statuses = health
            .iter()
            .enumerate()
            .map(|(ch, h)| {
                FrequencyReport::starting(state.commands(ch), state.rate_settings(ch))
                    .to_status(frequency_status_name(&node_name, &h.name), &h.hardware_id)
            })
            .collect();
        let mut r = Reporter {
            node_name,
            names: health.iter().map(|h| h.name.clone()).collect(),
            start_ns: now,
            pubs,
            diagnostics,
            health,
            lines: EdgeLines::new(n, edge_log_rate),
            e1_published: vec![None; n],
            levels_published: vec![u8::MAX; n],
            counters: NodeCounters::default(),
            dropped_seen: 0,
            too_large_seen: 0,
            notes,
            status: StatusClock::new(status_rate_hz, now),
            last_diagnostics: 0,
            next_periodic: 0,
            edge_seen: false,
            signal,
            state,
            rates,
            rate_statuses,
            lateness: LatenessHistogram::default(),
            node: NodeHealth::default(),
            next_run: now + DIAGNOSTICS_RUN_NS,
            last_run: now,
            mcap: None,
            valves: Vec::new(),
            traces: TraceReport::default(),
        };
        for ch in 0..n {
            r.publish_e1(ch, false);
        }
        r
    }

    /// Records from now on every edge, status and `/diagnostics` message published, as
    /// published, to `trace`, under its topics' keys ([`TraceKey`]); a message whose topic the
    /// trace lacks is not recorded.
    pub fn record_to(&mut self, trace: McapTrace) {
        self.mcap = Some(trace);
    }

    /// Reports on `/diagnostics` and in the log the traces whose state `traces` holds.
    pub fn watch_traces(&mut self, traces: TraceReport) {
        self.traces = traces;
    }

    /// The valves whose snapshots are published and judged on `/diagnostics`.
    pub fn set_valves(&mut self, valves: Vec<ValveOut>) {
        self.valves = valves;
    }

    /// Publishes E1 = `e1` for `channel` (latched).
    fn publish_e1(&mut self, channel: usize, e1: bool) {
        if let Some(p) = self.pubs.get(channel) {
            if let Err(e) = p.e1.publish(msg::Bool { data: e1 }) {
                warn!("{}: cannot publish e1: {e}", self.names[channel]);
            }
        }
        self.e1_published[channel] = Some(e1);
    }

    /// Handles one report from the output thread.
    pub fn handle(&mut self, report: Report) {
        match report {
            Report::Edge(e) => self.on_edge(&e),
            Report::Core { channel, event } => self.on_event(channel, event),
            Report::Status {
                channel, status, ..
            } => {
                let Some(h) = self.health.get_mut(channel) else {
                    return;
                };
                let changed = h.status.is_none_or(|old| status_changed(&old, &status));
                h.status = Some(status);
                if changed {
                    self.publish_status(channel, &status);
                }
            }
            Report::Valve {
                valve,
                status,
                at_ns,
            } => {
                if let Some(v) = self.valves.get_mut(valve) {
                    v.on_status(status, at_ns);
                }
            }
            Report::OutputFault { channel } => {
                if let Some(h) = self.health.get_mut(channel) {
                    h.output_fault = true;
                }
                error!(
                    "{}: writing the output failed; every output was driven off and the output \
                     thread stopped",
                    self.names.get(channel).map_or("?", String::as_str)
                );
                self.signal.fault.store(true, Ordering::SeqCst);
                self.publish_diagnostics(clock::monotonic_ns());
                self.signal.stop.notify_one();
            }
        }
    }

    fn on_edge(&mut self, e: &EdgeReport) {
        let ch = e.channel;
        if ch >= self.names.len() {
            return;
        }
        if !self.edge_seen {
            self.edge_seen = true;
            if let Some(at) = grid_for_first_edge(self.start_ns, self.next_run, e.scheduled_ns) {
                self.next_run = at + DIAGNOSTICS_RUN_NS;
                self.status.restart_at(at);
            }
        }
        let h = &mut self.health[ch];
        h.edges += 1;
        h.max_late_ns = h.max_late_ns.max(e.lateness_ns());
        self.lateness.record(e.lateness_ns());
        let m = msg::OutputEdge {
            stamp: Time::from_nanos(e.wall_ns),
            channel: (ch + 1).min(u8::MAX as usize) as u8,
            level: e.level.is_high(),
            seq: e.seq,
            lateness_ns: e.lateness_ns(),
        };
        if let Some(t) = &self.mcap {
            t.record(TraceKey::Edges(ch), e.wall_ns, &m);
        }
        if self.pubs[ch].edges.publish(m).is_err() {
            self.health[ch].publish_failures += 1;
        }
        // The output thread sends the status snapshot an edge belongs to ahead of the edge.
        let (duty, e1) = self.health[ch].status.map_or((0.0, false), |s| {
            (
                crate::ros::outbound::diagnostics::percent(s.duty_commanded),
                s.e1,
            )
        });
        for line in self
            .lines
            .edge(ch, &self.names[ch], e, self.start_ns, duty, e1)
        {
            info!("{line}");
        }
    }

    fn on_event(&mut self, ch: usize, event: Event) {
        let Some(name) = self.names.get(ch).cloned() else {
            return;
        };
        let now = clock::monotonic_ns();
        match event {
            Event::Flags { e1, limited } => {
                if self.e1_published[ch] != Some(e1) {
                    self.publish_e1(ch, e1);
                    if e1 {
                        info!(
                            "{name}: E1 set: the duty cannot be reproduced because of a \
                             minimum time or max_on_ms"
                        );
                    } else {
                        info!("{name}: E1 cleared");
                    }
                }
                debug!("{name}: flags e1={e1} limited={limited}");
            }
            Event::Watchdog { tripped } => {
                self.health[ch].watchdog = tripped;
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
                let h = &mut self.health[ch];
                h.rejected += 1;
                h.last_rejection = Some((err.to_string(), now));
                warn!("{name}: duty command refused: {err}");
            }
            Event::Clamped { requested, applied } => {
                let text = clamp_text(requested, applied);
                let h = &mut self.health[ch];
                h.clamped += 1;
                h.last_clamp = Some((text.clone(), now));
                warn!("{name}: duty command out of range: {text}");
            }
            Event::Missed { edges } => {
                self.health[ch].missed += u64::from(edges);
                warn!("{name}: the output thread woke late; {edges} scheduled edges were merged");
            }
            Event::Skipped { .. } => {
                warn!(
                    "{name}: a pulse was skipped: no line went off before its latest start in \
                     its period (max_simultaneous_on, or another channel of its stagger group \
                     still on)"
                );
            }
            Event::Refused(r) => {
                let h = &mut self.health[ch];
                h.rejected += 1;
                h.last_rejection = Some((r.to_string(), now));
                warn!("{name}: {r}");
            }
            Event::HeaterFault(f) => {
                error!("{name}: heater fault latched: {f}; line off, held off until ~/{name}/reset_fault");
                if self.state.heater_estop() {
                    // The output thread latched the e-stop of every channel with it.
                    self.state.set_estop(true);
                    error!("heater_fault_latches_estop: e-stop latched for every channel");
                }
            }
            Event::FaultReset { ticket, result } => {
                match &result {
                    Ok(()) => info!(
                        "{name}: heater fault reset; the channel is disabled until its next enable"
                    ),
                    Err(e) => warn!("{name}: heater fault reset refused: {e}"),
                }
                // Dropped when the reset's request has given up.
                self.state.resets().answer(ch, ticket, result);
            }
            Event::Autotune { ticket, report } => {
                use crate::core::heater::autotune::{Phase, Progress, Report};
                match &report {
                    Report::Refused(r) => warn!("{name}: autotune refused: {r}"),
                    Report::Started => info!("{name}: autotune started"),
                    Report::Progress(p) => info!(
                        "{name}: autotune {}: {} cycles, last amplitude {:.2} °C, period {:.1} \
                         s{}",
                        p.phase.as_str(),
                        p.cycles,
                        p.amplitude_c,
                        p.period_s,
                        p.dead_time
                            .map(|d| format!("; the cycles agree, the relay goes on {d}"))
                            .unwrap_or_default()
                    ),
                    Report::Finished(o) => match (o.estimate, o.gains) {
                        (Some(e), Some(g)) => info!(
                            "{name}: autotune {}: Ku {:.4} %/°C, Tu {:.2} s; pid_kp {:.4} \
                             pid_ki {:.5} pid_kd {:.4}",
                            o.stop, e.ku, e.tu_s, g.kp, g.ki, g.kd
                        ),
                        _ => warn!("{name}: autotune ended without gains: {}", o.stop),
                    },
                }
                // While a run lasts, the channel's diagnostics say so.
                match &report {
                    Report::Refused(_) => {}
                    Report::Started => {
                        self.health[ch].autotune = Some(Progress {
                            phase: Phase::Approach,
                            cycles: 0,
                            amplitude_c: 0.0,
                            period_s: 0.0,
                            dead_time: None,
                        })
                    }
                    Report::Progress(p) => self.health[ch].autotune = Some(*p),
                    Report::Finished(_) => self.health[ch].autotune = None,
                }
                self.state.autotunes().file(ch, ticket, report);
            }
            Event::Plan(_) | Event::Edge { .. } => {}
        }
    }

    fn publish_status(&mut self, ch: usize, s: &Status) {
        let m = status_msg(ch, s, clock::monotonic_ns(), clock::wall_ns());
        if let Some(t) = &self.mcap {
            t.record(TraceKey::Status(ch), m.stamp.to_nanos(), &m);
        }
        if self.pubs[ch].status.publish(m).is_err() {
            self.health[ch].publish_failures += 1;
        }
    }

    /// Takes the notes the ROS callbacks queued.
    fn take_notes(&mut self, now: Nanos) {
        loop {
            match self.notes.try_recv() {
                Ok(Note::Refused {
                    channels,
                    reason,
                    at,
                }) => {
                    for c in channels {
                        if let Some(h) = self.health.get_mut(c) {
                            h.last_refusal = Some((reason.clone(), at));
                        }
                    }
                }
                Ok(Note::StatusRate(r)) => self.status.set_rate(r, now),
                Ok(Note::EdgeLogRate(r)) => self.lines.set_rate(r),
                Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
            }
        }
    }

    /// After a batch of reports, a wake-up ([`NodeState::wake_reporter`], a trace's change) or
    /// when the time it last returned has passed: notes, summaries of held-back edge lines, lost
    /// reports, the periodic status, and `/diagnostics` when due or when a level changed.
    /// Returns how long the thread may sleep before the next call: until the earliest of the
    /// next periodic `/diagnostics`, diagnostics run, status, edge-line summary, coalesced
    /// level change and the end of a WARN that lasts a while (a refusal's, a loss's) — computed,
    /// so an idle node sleeps a second at a time.
    pub fn after_batch(&mut self, dropped_total: u64) -> Duration {
        let now = clock::monotonic_ns();
        self.take_notes(now);
        self.counters = NodeCounters {
            reports_dropped: dropped_total,
            samples_too_large: rustdds::received_samples_too_large() + qos::zenoh_too_large(),
        };
        if now >= self.next_run {
            self.run_diagnostics(now);
        }
        for s in self.lines.flush(&self.names, now) {
            info!("{s}");
        }
        if dropped_total > self.dropped_seen {
            warn!(
                "{} reports from the output thread were lost (the ROS side did not keep up)",
                dropped_total - self.dropped_seen
            );
            self.dropped_seen = dropped_total;
            self.node.last_drop = Some(now);
        }
        let too_large = self.counters.samples_too_large;
        if too_large > self.too_large_seen {
            warn!(
                "{} input samples larger than {} KiB were dropped before decoding ({too_large} \
                 since start)",
                too_large - self.too_large_seen,
                MAX_SAMPLE_BYTES / 1024
            );
            self.too_large_seen = too_large;
            self.node.last_too_large = Some(now);
        }
        if self.status.take_due(now) {
            for ch in 0..self.health.len() {
                if let Some(s) = self.health[ch].status {
                    self.publish_status(ch, &s);
                }
            }
        }
        self.node_from_state();
        // A trace that fails wakes this thread, and is on /diagnostics as its level changes.
        self.traces.poll(now, false);
        let since = now.saturating_sub(self.last_diagnostics);
        let levels_changed = self.levels(now) != self.levels_published;
        let periodic = now >= self.periodic_due();
        if periodic || (since >= DIAGNOSTICS_COALESCE_NS && levels_changed) {
            if periodic {
                logging::flush_suppressed();
                release_free_memory();
                // The next one with the next run, which falls due with the periodic status
                // (both count from the reporter's start): one wake-up for the three.
                self.next_periodic = if self.next_run > now {
                    self.next_run
                } else {
                    now + DIAGNOSTICS_RUN_NS
                };
            }
            self.publish_diagnostics(now);
        }
        // A change held back by the coalescing is published as soon as the interval has passed.
        let coalesced = (self.levels_published != self.levels(now))
            .then_some(self.last_diagnostics + DIAGNOSTICS_COALESCE_NS);
        let periodic = [
            Some(self.periodic_due()),
            Some(self.next_run),
            self.status.next(),
        ]
        .into_iter()
        .flatten()
        .min()
        .map(|due| {
            let step_ends = self
                .health
                .iter()
                .filter_map(|h| h.status.and_then(|s| s.step_end));
            periodic_wake(due, step_ends, self.status.period())
        });
        let next = [
            coalesced,
            periodic,
            self.lines.next_flush(),
            self.next_level_change(now),
        ]
        .into_iter()
        .flatten()
        .min()
        .unwrap_or(now);
        Duration::from_nanos(next.saturating_sub(now))
    }

    /// When the periodic `/diagnostics` is due: at the next diagnostics run, but never sooner
    /// than [`DIAGNOSTICS_COALESCE_NS`] after the last `/diagnostics` (one a level change
    /// brought), so two never come closer than that and at most a period lies between two.
    fn periodic_due(&self) -> Nanos {
        self.next_periodic.max(
            self.last_diagnostics
                .saturating_add(DIAGNOSTICS_COALESCE_NS),
        )
    }

    /// When a level `/diagnostics` carries will next change by itself after `now`, with no
    /// report or note (a WARN for a while after a refusal, a lost report, a dropped sample or a
    /// trace's problem ends), monotonic ns; `None` when none will.
    fn next_level_change(&self, now: Nanos) -> Option<Nanos> {
        let channel_ends = self.health.iter().flat_map(|h| {
            [&h.last_rejection, &h.last_refusal]
                .into_iter()
                .filter_map(|e| e.as_ref().map(|(_, at)| at.saturating_add(REFUSAL_WARN_NS)))
        });
        let node_ends = [self.node.last_drop, self.node.last_too_large]
            .into_iter()
            .flatten()
            .map(|at| at.saturating_add(LOSS_WARN_NS));
        channel_ends
            .chain(node_ends)
            .filter(|t| *t > now)
            .chain(self.traces.next_change(now))
            .min()
    }

    /// The diagnostics run, once a second: each channel's command rate against its expected
    /// rate (a new window when `command_hz_window` changed), and the lateness window closes.
    fn run_diagnostics(&mut self, now: Nanos) {
        for ch in 0..self.rates.len() {
            let settings = self.state.rate_settings(ch);
            let count = self.state.commands(ch);
            if self.rates[ch].window() != settings.window {
                self.rates[ch] = self.rates[ch].resized(settings.window);
            }
            let h = &self.health[ch];
            self.rate_statuses[ch] = self.rates[ch].run(count, now, settings).to_status(
                frequency_status_name(&self.node_name, &h.name),
                &h.hardware_id,
            );
        }
        self.node.lateness = std::mem::take(&mut self.lateness);
        self.node.lateness_window_s = now.saturating_sub(self.last_run) as f64 / 1e9;
        self.last_run = now;
        // A second after this one; a second from now when the thread was held up.
        self.next_run += DIAGNOSTICS_RUN_NS;
        if self.next_run <= now {
            self.next_run = now + DIAGNOSTICS_RUN_NS;
        }
    }

    /// Reads the node state the callbacks keep (lifecycle, e-stop) into the node's health.
    fn node_from_state(&mut self) {
        self.node.lifecycle = self.state.lifecycle_label();
        self.node.estop_latched = self.state.estop_latched();
        self.node.estop_latches = self.state.estop_latches();
        self.node.counters = self.counters;
        self.node.trace_dropped = self.mcap.as_ref().map_or(0, McapTrace::dropped);
    }

    /// The levels of every status `/diagnostics` carries, in its order.
    fn levels(&self, now: Nanos) -> Vec<u8> {
        self.health
            .iter()
            .map(|h| h.level(now))
            .chain(self.rate_statuses.iter().map(|d| d.level))
            .chain(self.valves.iter().map(ValveOut::level))
            .chain(std::iter::once(self.node.level(now)))
            .chain(self.traces.levels(now))
            .collect()
    }

    /// Publishes `/diagnostics` now: each channel's status, then each channel's command rate,
    /// then the node's status, then each trace's.
    pub fn publish_diagnostics(&mut self, now: Nanos) {
        self.node_from_state();
        self.traces.poll(now, true);
        for v in &mut self.valves {
            v.periodic();
        }
        let status: Vec<DiagnosticStatus> = self
            .health
            .iter()
            .map(|h| h.to_status(&self.node_name, now, self.counters))
            .chain(self.rate_statuses.iter().cloned())
            .chain(self.valves.iter().map(|v| v.to_status(&self.node_name)))
            .chain(std::iter::once(self.node.to_status(&self.node_name, now)))
            .chain(self.traces.statuses(&self.node_name, now))
            .collect();
        let levels = status.iter().map(|d| d.level).collect();
        let arr = DiagnosticArray {
            header: Header {
                stamp: Time::from_nanos(clock::wall_ns()),
                frame_id: String::new(),
            },
            status,
        };
        if let Some(t) = &self.mcap {
            t.record(TraceKey::Diagnostics, arr.header.stamp.to_nanos(), &arr);
        }
        if let Err(e) = self.diagnostics.publish(arr) {
            debug!("cannot publish /diagnostics: {e}");
        }
        self.levels_published = levels;
        self.last_diagnostics = now;
    }
}

/// [`release_free_memory`] trims the heap only when its free memory is at least this much,
/// bytes. Below it there is little to give back, and a trim every second would hand back the
/// few pages the next second's messages touch again (7 `madvise` calls a second, each page
/// then faulted in again, in an idle node).
const TRIM_FROM_FREE_BYTES: usize = 1 << 20;

/// Hands the heap's free pages back to the kernel (glibc's `malloc_trim`), once a second from
/// this thread, when at least [`TRIM_FROM_FREE_BYTES`] of the heap are free (glibc's
/// `mallinfo2().fordblks`, over every arena); returns whether it trimmed. A burst of input that
/// logs a line per message (an enable flood: 270 000 toggles in 10 s) leaves tens of MiB freed
/// but scattered among live allocations; glibc returns only the free memory at the top of a heap
/// by itself, so RSS stayed 70 MiB above its steady state until this call (measured: 88 MiB,
/// then 18.6 MiB). So RSS stays at most about [`TRIM_FROM_FREE_BYTES`] above what the heap
/// uses, a second after a burst. It runs on the report thread; the output thread does not
/// allocate, so it never waits for the allocator's locks.
fn release_free_memory() -> bool {
    #[cfg(target_env = "gnu")]
    // SAFETY: mallinfo2 and malloc_trim only take the allocator's own locks and touch no Rust
    // state.
    unsafe {
        if libc::mallinfo2().fordblks >= TRIM_FROM_FREE_BYTES {
            libc::malloc_trim(0);
            return true;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Nanos = 1_000_000;

    #[cfg(target_env = "gnu")]
    #[test]
    fn free_memory_goes_back_once_there_is_enough_of_it() {
        // 8 MiB in 4 KiB blocks (below glibc's mmap threshold: on the heap), every other one
        // freed: 4 MiB free, scattered among live blocks, which glibc keeps by itself.
        let mut blocks: Vec<Vec<u8>> = (0..2048).map(|i| vec![i as u8; 4096]).collect();
        let mut n = 0;
        blocks.retain(|_| {
            n += 1;
            n % 2 == 0
        });
        // SAFETY: mallinfo2 only reads the allocator's statistics under its locks.
        let free = unsafe { libc::mallinfo2().fordblks };
        assert!(free >= TRIM_FROM_FREE_BYTES, "{free} bytes free");
        assert!(release_free_memory(), "not trimmed with {free} bytes free");
        assert_eq!(blocks.len(), 1024);
    }

    #[test]
    fn a_new_status_rate_does_not_wait_for_the_old_period() {
        // 0.01 Hz is due every 100 s; after the change to 10 Hz at 50 ms the first status is
        // due 100 ms later, then every 100 ms.
        let mut c = StatusClock::new(0.01, 0);
        assert!(!c.take_due(50 * MS));
        c.set_rate(10.0, 50 * MS);
        assert_eq!(c.next(), Some(150 * MS));
        let due: Vec<Nanos> = (50..=1050)
            .map(|ms| ms * MS)
            .filter(|t| c.take_due(*t))
            .map(|t| t / MS)
            .collect();
        assert_eq!(due, (1..=10).map(|k| 50 + 100 * k).collect::<Vec<_>>());
        c.set_rate(0.0, 2000 * MS);
        assert_eq!(c.next(), None);
        assert!(!c.take_due(u64::MAX));
    }

    #[test]
    fn periodic_work_waits_for_an_edge_just_after_it_and_no_longer() {
        let due = 1_000 * MS;
        let slack = PERIODIC_SLACK_NS;
        // No edge, an edge before, an edge too far after: at its time.
        assert_eq!(periodic_wake(due, [].into_iter(), Some(1_000 * MS)), due);
        assert_eq!(periodic_wake(due, [due - MS].into_iter(), None), due);
        // An edge due at the same instant: its report does it.
        assert_eq!(
            periodic_wake(due, [due].into_iter(), None),
            due + PERIODIC_SLACK_NS
        );
        assert_eq!(
            periodic_wake(due, [due + slack + 1].into_iter(), Some(1_000 * MS)),
            due
        );
        // An edge 7 ms after it: the edge's wake-up does it, or the slack's end does.
        assert_eq!(
            periodic_wake(
                due,
                [due + slack + 1, due + 7 * MS].into_iter(),
                Some(1_000 * MS)
            ),
            due + slack
        );
        assert_eq!(
            periodic_wake(due, [due + slack].into_iter(), None),
            due + slack
        );
        // At 10 Hz the slack is 5 ms, at 1 kHz 50 us.
        assert_eq!(
            periodic_wake(due, [due + 7 * MS].into_iter(), Some(100 * MS)),
            due
        );
        assert_eq!(
            periodic_wake(due, [due + 4 * MS].into_iter(), Some(100 * MS)),
            due + 5 * MS
        );
        assert_eq!(
            periodic_wake(due, [due + 40_000].into_iter(), Some(MS)),
            due + 50_000
        );
    }

    #[test]
    fn the_grid_moves_to_the_first_edge_before_the_first_run() {
        let start = 5_000 * MS;
        let first_run = start + 1_000 * MS;
        // A channel started 30 ms after the report thread: the grid moves to its first edge.
        assert_eq!(
            grid_for_first_edge(start, first_run, start + 30 * MS),
            Some(start + 30 * MS)
        );
        // An edge at or before the start, or from the first run on: the grid stays.
        assert_eq!(grid_for_first_edge(start, first_run, start), None);
        assert_eq!(grid_for_first_edge(start, first_run, first_run), None);
        // The status follows it: one period after the edge, then a period apart.
        let mut c = StatusClock::new(1.0, start);
        c.restart_at(start + 30 * MS);
        assert_eq!(c.next(), Some(start + 1_030 * MS));
        assert!(!c.take_due(start + 1_000 * MS));
        assert!(c.take_due(start + 1_030 * MS));
        assert_eq!(c.next(), Some(start + 2_030 * MS));
        // Without a periodic status there is nothing to move.
        let mut off = StatusClock::new(0.0, start);
        off.restart_at(start + 30 * MS);
        assert_eq!(off.next(), None);
    }

    #[test]
    fn any_status_rate_gives_a_usable_period_or_none() {
        for r in [1e-20, 5e-324, f64::MIN_POSITIVE, -0.0, f64::MAX] {
            let mut c = StatusClock::new(r, u64::MAX - 1);
            let _ = c.take_due(u64::MAX);
        }
        for r in [0.0, -1.0, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            assert_eq!(status_period(r), None, "{r}");
        }
        assert_eq!(status_period(10.0), Some(Duration::from_millis(100)));
        assert_eq!(status_period(1e-20), Some(Duration::from_secs(100)));
        assert_eq!(status_period(5e-324), Some(Duration::from_secs(100)));
        assert_eq!(status_period(1e300), Some(Duration::from_millis(1)));
    }
}
