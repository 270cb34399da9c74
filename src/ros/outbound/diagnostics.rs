//! What the node knows about each channel's health, and how it reads as a
//! `diagnostic_msgs/DiagnosticStatus` (one per channel, named `<node name>: <ch>`, hardware id
//! the line or `sim`), following the ROS diagnostics conventions: OK; WARN when E1 or the
//! minimum-time limit acts (the maximum on time included; not a cycle extension, which keeps
//! the duty: it is named in the message at OK), when the command in force was clamped, or for
//! a while after a command was refused; ERROR on a tripped watchdog, a latched
//! e-stop or an output fault. The other protections of the load (power limits, slew, dead
//! band, the rolling-average cap) are named in the message and the `protections` key while
//! they act, at level OK: they do what they were set for. Every condition, its level and its
//! message are one row of [`CONDITIONS`], in precedence order.
//!
//! The node itself has one more status, `<node name>: node` ([`NodeHealth`]): the output
//! thread's lateness over the last second, lost reports, the lifecycle state and the e-stop.
//!
//! Pure bookkeeping fed by the output thread's reports; it does not publish and does not read clocks (times
//! are passed in).

use crate::core::heater::autotune::{Phase, Progress};
use crate::core::{Command, Nanos, Status, NS_PER_MS};
use crate::ros::interface::msg::{ChannelStatus, DiagnosticStatus, KeyValue};
use crate::ros::outbound::decimal::Fixed;

/// How long a refused command keeps the channel at WARN, ns.
pub const REFUSAL_WARN_NS: Nanos = 5_000_000_000;

/// What a clamped command is said to have been: `requested` in its own unit, and the duty
/// fraction `applied`.
pub fn clamp_text(requested: Command, applied: f64) -> String {
    let value = show_number(requested.raw());
    let range = format!("0..{}", show_number(requested.full_scale()));
    let asked = match requested {
        Command::Percent(_) => format!("{value} %"),
        Command::Sv(_) => format!("SV {value}"),
        Command::Fraction(_) => format!("fraction {value}"),
    };
    format!(
        "{asked} is outside {range}, clamped to {:.1} %",
        percent(applied)
    )
}

/// A number from input, shown in a few characters: as written up to a million in size,
/// scientific beyond and for tiny fractions (`1e308`, not its 309 digits).
pub fn show_number(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-4..1e6).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// A duty fraction in percent, as reported: a command of -0.0 (which is in range, and kept
/// as given) reads as 0, not -0.
pub fn percent(fraction: f64) -> f64 {
    // -0.0 + 0.0 is +0.0; every other value is unchanged.
    fraction * 100.0 + 0.0
}

/// The reason of `event` if it happened less than [`REFUSAL_WARN_NS`] before `now`.
fn recent(event: &Option<(String, Nanos)>, now: Nanos) -> Option<&str> {
    event
        .as_ref()
        .filter(|(_, at)| now.saturating_sub(*at) < REFUSAL_WARN_NS)
        .map(|(r, _)| r.as_str())
}

fn ms(ns: Nanos) -> f64 {
    ns as f64 / NS_PER_MS as f64
}

/// The `ChannelStatus` message for a status snapshot; remaining times are taken at `now`
/// (monotonic ns) and the message is stamped `stamp_ns` (wall clock).
pub fn status_msg(channel: usize, s: &Status, now: Nanos, stamp_ns: i64) -> ChannelStatus {
    let (rem_on, rem_off) = s.remaining_at(now);
    ChannelStatus {
        stamp: ros2_client::builtin_interfaces::Time::from_nanos(stamp_ns),
        channel: (channel + 1).min(u8::MAX as usize) as u8,
        enabled: s.enabled,
        active: s.active,
        output: s.level.is_high(),
        duty_commanded: percent(s.duty_commanded),
        duty_applied: percent(s.duty_applied),
        command_clamped: s.command_clamped,
        period_ms: ms(s.period),
        on_time_ms: ms(s.t_on),
        off_time_ms: ms(s.t_off),
        remaining_on_ms: ms(rem_on),
        remaining_off_ms: ms(rem_off),
        e1: s.e1,
        min_time_limited: s.limited,
        watchdog_tripped: s.watchdog_tripped,
        rule: s.rule.as_str().to_string(),
        duty_target: percent(s.duty_target),
        protections: s.protections.names().map(str::to_string).collect(),
        time_base_ms: ms(s.time_base),
        on_time_input_ms: ms(s.t_on_input),
        off_time_input_ms: ms(s.t_off_input),
        remaining_on_s: whole_seconds(rem_on),
        remaining_off_s: whole_seconds(rem_off),
        control: s.heater.control.as_str().into(),
        temperature_c: s.heater.reading.map_or(f64::NAN, |(c, _)| c),
        temperature_age_ms: s
            .heater
            .reading
            .map_or(-1.0, |(_, at)| ms(now.saturating_sub(at))),
        setpoint_c: s.heater.setpoint.unwrap_or(f64::NAN),
        pid_p: s.heater.terms.p,
        pid_i: s.heater.terms.i,
        pid_d: s.heater.terms.d,
        pid_output: s.heater.terms.output,
        heater_fault: s
            .heater
            .fault
            .map_or(String::new(), |f| f.check().to_string()),
        heater_fault_message: s.heater.fault.map_or(String::new(), |f| f.to_string()),
        heater_fault_lasts: s.heater.fault_lasts,
        model_predicted_c: s.heater.model.map_or(f64::NAN, |m| m.predicted_c),
        model_residual_c: s.heater.model.map_or(f64::NAN, |m| m.residual_c),
        stale_readings: s.heater.stale.0,
        last_stale_age_ms: if s.heater.stale.0 == 0 {
            f64::NAN
        } else {
            s.heater.stale.1 as f64 / 1e6
        },
        target_c: s.heater.target.unwrap_or(f64::NAN),
    }
}

/// A remaining time in whole seconds, as 002's UDINT countdowns nRemTiOn / nRemTiOff show it:
/// truncated (a countdown shows 0 in its last second), saturating.
pub fn whole_seconds(ns: Nanos) -> u32 {
    u32::try_from(ns / 1_000_000_000).unwrap_or(u32::MAX)
}

/// Whether two snapshots differ in anything but the running step's remaining time (what
/// "on change" means for `~/<ch>/status`).
pub fn status_changed(a: &Status, b: &Status) -> bool {
    // The running step's remaining time and end move on their own; the requested command is
    // shown through `duty_commanded` (NaN never reaches a status: the core refuses it).
    let b_steady = Status {
        remaining_on: a.remaining_on,
        remaining_off: a.remaining_off,
        step_end: a.step_end,
        duty_requested: a.duty_requested,
        ..*b
    };
    *a != b_steady
}

/// Node-wide counters, shown in every channel's status.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct NodeCounters {
    /// Reports the output thread could not queue for the ROS side (the report thread fell
    /// behind): edges written to the line but never published.
    pub reports_dropped: u64,
    /// Input samples larger than [`crate::ros::interface::qos::MAX_SAMPLE_BYTES`], dropped before decoding.
    pub samples_too_large: u64,
}

/// How long lost reports or dropped input samples keep the node status at WARN, ns.
pub const LOSS_WARN_NS: Nanos = 5_000_000_000;

/// Sub-buckets per power of two in [`LatenessHistogram`]: a bucket spans at most 1/16 of its
/// lower bound (6.25 %).
const SUB_BUCKETS: u64 = 16;

/// Buckets of [`LatenessHistogram`]: exact below 16 ns, then 16 per power of two up to 2^64.
const BUCKETS: usize = (SUB_BUCKETS + (64 - 4) * SUB_BUCKETS) as usize;

/// The distribution of edge lateness (actual - scheduled write time) over a window, in a fixed
/// number of log-scaled buckets: constant memory and O(1) per edge however many edges a
/// second the channels write, percentiles within 6.25 % (rounded up: the bucket's upper end).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LatenessHistogram {
    counts: Vec<u32>,
    edges: u64,
    max_ns: u64,
}

impl Default for LatenessHistogram {
    fn default() -> LatenessHistogram {
        LatenessHistogram {
            counts: vec![0; BUCKETS],
            edges: 0,
            max_ns: 0,
        }
    }
}

impl LatenessHistogram {
    fn bucket(ns: u64) -> usize {
        if ns < SUB_BUCKETS {
            return ns as usize;
        }
        let octave = 63 - u64::from(ns.leading_zeros()); // >= 4
        let sub = (ns >> (octave - 4)) & (SUB_BUCKETS - 1);
        (SUB_BUCKETS + (octave - 4) * SUB_BUCKETS + sub) as usize
    }

    /// The largest lateness that falls in `bucket`, ns.
    fn upper(bucket: usize) -> u64 {
        let b = bucket as u64;
        if b < SUB_BUCKETS {
            return b;
        }
        let octave = (b - SUB_BUCKETS) / SUB_BUCKETS + 4;
        let sub = (b - SUB_BUCKETS) % SUB_BUCKETS;
        let width = 1u64 << (octave - 4);
        ((SUB_BUCKETS + sub) << (octave - 4)).saturating_add(width - 1)
    }

    /// Records one edge's lateness, ns; an early write counts as 0.
    pub fn record(&mut self, lateness_ns: i64) {
        let ns = lateness_ns.max(0) as u64;
        let c = &mut self.counts[Self::bucket(ns)];
        *c = c.saturating_add(1);
        self.edges += 1;
        self.max_ns = self.max_ns.max(ns);
    }

    /// Edges recorded.
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// The largest lateness recorded, ns (0 with no edge).
    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }

    /// The `q` quantile (0..1) of the lateness, ns, rounded up to its bucket's end and never
    /// above the maximum; 0 with no edge.
    pub fn quantile_ns(&self, q: f64) -> u64 {
        if self.edges == 0 {
            return 0;
        }
        // The rank of the q-quantile, 1-based: the smallest value with at least q of the
        // edges at or below it.
        let rank = ((q.clamp(0.0, 1.0) * self.edges as f64).ceil() as u64).max(1);
        let mut seen = 0u64;
        for (b, c) in self.counts.iter().enumerate() {
            seen += u64::from(*c);
            if seen >= rank {
                return Self::upper(b).min(self.max_ns);
            }
        }
        self.max_ns
    }
}

/// The node's state as `/diagnostics` shows it in `<node name>: node`.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeHealth {
    /// Lifecycle state: a managed node's `lifecycle_msgs/State` label (`unconfigured`,
    /// `inactive`, `active`, `finalized`), `unmanaged` for a node that is not managed.
    pub lifecycle: &'static str,
    /// The e-stop is latched.
    pub estop_latched: bool,
    /// Times the e-stop latched since start-up.
    pub estop_latches: u64,
    /// Lateness of the edges written in the last whole window.
    pub lateness: LatenessHistogram,
    /// Length of that window, s.
    pub lateness_window_s: f64,
    /// The node-wide counters.
    pub counters: NodeCounters,
    /// When `reports_dropped` last rose, monotonic ns.
    pub last_drop: Option<Nanos>,
    /// When `samples_too_large` last rose, monotonic ns.
    pub last_too_large: Option<Nanos>,
    /// Messages the MCAP trace could not record (its queue was full); 0 without one.
    pub trace_dropped: u64,
}

impl Default for NodeHealth {
    fn default() -> NodeHealth {
        NodeHealth {
            lifecycle: "unmanaged",
            estop_latched: false,
            estop_latches: 0,
            lateness: LatenessHistogram::default(),
            lateness_window_s: 0.0,
            counters: NodeCounters::default(),
            last_drop: None,
            last_too_large: None,
            trace_dropped: 0,
        }
    }
}

impl NodeHealth {
    fn recent(at: Option<Nanos>, now: Nanos) -> bool {
        at.is_some_and(|at| now.saturating_sub(at) < LOSS_WARN_NS)
    }

    /// The diagnostic level at monotonic time `now`: ERROR while the e-stop is latched, WARN
    /// for [`LOSS_WARN_NS`] after reports were lost or input samples dropped, else OK.
    pub fn level(&self, now: Nanos) -> u8 {
        if self.estop_latched {
            DiagnosticStatus::ERROR
        } else if Self::recent(self.last_drop, now) || Self::recent(self.last_too_large, now) {
            DiagnosticStatus::WARN
        } else {
            DiagnosticStatus::OK
        }
    }

    /// The one-line summary at `now`.
    pub fn message(&self, now: Nanos) -> String {
        if self.estop_latched {
            return "e-stop latched: every line held inactive until ~/reset_estop".into();
        }
        if Self::recent(self.last_drop, now) {
            return format!(
                "reports from the output thread lost (the ROS side did not keep up): {} since \
                 start-up",
                self.counters.reports_dropped
            );
        }
        if Self::recent(self.last_too_large, now) {
            return format!(
                "input samples larger than {} KiB dropped: {} since start-up",
                crate::ros::interface::qos::MAX_SAMPLE_BYTES / 1024,
                self.counters.samples_too_large
            );
        }
        format!(
            "lifecycle {}, e-stop released, lateness p99 {} us",
            self.lifecycle,
            Fixed(self.lateness.quantile_ns(0.99) as f64 / 1000.0, 1)
        )
    }

    /// The diagnostic status at `now`, named `<node_name>: node`, hardware id the node name.
    pub fn to_status(&self, node_name: &str, now: Nanos) -> DiagnosticStatus {
        let us = |ns: u64| Fixed(ns as f64 / 1000.0, 1).to_string();
        let kv: Vec<(&str, String)> = vec![
            ("lifecycle_state", self.lifecycle.to_string()),
            ("estop_latched", self.estop_latched.to_string()),
            ("estop_latches", self.estop_latches.to_string()),
            ("lateness_p99_us", us(self.lateness.quantile_ns(0.99))),
            ("lateness_max_us", us(self.lateness.max_ns())),
            ("lateness_window_edges", self.lateness.edges().to_string()),
            (
                "lateness_window_s",
                Fixed(self.lateness_window_s, 3).to_string(),
            ),
            ("reports_dropped", self.counters.reports_dropped.to_string()),
            (
                "samples_too_large",
                self.counters.samples_too_large.to_string(),
            ),
            ("trace_messages_dropped", self.trace_dropped.to_string()),
        ];
        DiagnosticStatus {
            level: self.level(now),
            name: node_status_name(node_name),
            message: self.message(now),
            hardware_id: node_name.to_string(),
            values: key_values(kv),
        }
    }
}

/// Key-value pairs as a `DiagnosticStatus` carries them.
pub fn key_values(kv: Vec<(&str, String)>) -> Vec<KeyValue> {
    kv.into_iter()
        .map(|(k, v)| KeyValue {
            key: k.to_string(),
            value: v,
        })
        .collect()
}

/// The name of a channel's status: `<node name>: <ch>`.
pub fn channel_status_name(node_name: &str, channel: &str) -> String {
    format!("{node_name}: {channel}")
}

/// The name of a channel's command-rate status: `<node name>: <ch> command frequency`.
pub fn frequency_status_name(node_name: &str, channel: &str) -> String {
    format!("{node_name}: {channel} command frequency")
}

/// An autotune's progress in a few words: `approach`, `relay, 3 cycles`.
fn autotune_progress(p: &Progress) -> String {
    match p.phase {
        Phase::Approach => p.phase.as_str().to_string(),
        Phase::Relay => format!("{}, {} cycles", p.phase.as_str(), p.cycles),
        Phase::DeadTime => match p.dead_time {
            Some(d) => format!("{}, {} cycles, {d}", p.phase.as_str(), p.cycles),
            None => format!("{}, {} cycles", p.phase.as_str(), p.cycles),
        },
    }
}

/// The name of the node's own status: `<node name>: node`.
pub fn node_status_name(node_name: &str) -> String {
    format!("{node_name}: node")
}

/// Everything the diagnostics say about one channel.
#[derive(Debug, Clone, Default)]
pub struct ChannelHealth {
    /// `pw01`, ...
    pub name: String,
    /// The output line, or `sim`.
    pub hardware_id: String,
    /// The latest snapshot from the output thread.
    pub status: Option<Status>,
    /// The watchdog has tripped (from the event, before any snapshot says so).
    pub watchdog: bool,
    /// Writing this channel's output failed.
    pub output_fault: bool,
    /// The last refused command: reason and monotonic time.
    pub last_rejection: Option<(String, Nanos)>,
    /// The last clamped command, described, and its monotonic time.
    pub last_clamp: Option<(String, Nanos)>,
    /// The last refused parameter change: reason and monotonic time.
    pub last_refusal: Option<(String, Nanos)>,
    /// Edges written.
    pub edges: u64,
    /// Largest lateness seen, ns.
    pub max_late_ns: i64,
    /// Edges merged because the output thread woke too late.
    pub missed: u64,
    /// Commands refused (NaN, infinite).
    pub rejected: u64,
    /// Commands clamped.
    pub clamped: u64,
    /// Messages that could not be published (a subscriber not keeping up).
    pub publish_failures: u64,
    /// An autotune runs on the channel: its last progress (the relay, not the loop or a
    /// command, sets the duty).
    pub autotune: Option<Progress>,
}

impl ChannelHealth {
    /// A channel with nothing known yet.
    pub fn new(name: &str, hardware_id: &str) -> ChannelHealth {
        ChannelHealth {
            name: name.to_string(),
            hardware_id: hardware_id.to_string(),
            ..ChannelHealth::default()
        }
    }

    fn watchdog_tripped(&self) -> bool {
        self.watchdog || self.status.is_some_and(|s| s.watchdog_tripped)
    }

    fn recent_rejection(&self, now: Nanos) -> Option<&str> {
        recent(&self.last_rejection, now)
    }

    fn recent_refusal(&self, now: Nanos) -> Option<&str> {
        recent(&self.last_refusal, now)
    }

    /// The conditions of [`CONDITIONS`] that hold at monotonic time `now`, in precedence
    /// order, each with what it says (not formatted yet).
    fn conditions(&self, now: Nanos) -> impl Iterator<Item = (&'static Condition, Says)> + '_ {
        CONDITIONS
            .iter()
            .filter_map(move |c| (c.check)(self, now).map(|m| (c, m)))
    }

    /// The diagnostic level at monotonic time `now`: the highest level of the conditions that
    /// hold ([`CONDITIONS`]). Formats nothing.
    pub fn level(&self, now: Nanos) -> u8 {
        self.conditions(now)
            .map(|(c, _)| c.level)
            .max()
            .unwrap_or(DiagnosticStatus::OK)
    }

    /// The one-line summary at `now`: the message of the first condition that holds
    /// ([`CONDITIONS`]).
    pub fn message(&self, now: Nanos) -> String {
        self.conditions(now)
            .next()
            .map_or_else(|| "starting".into(), |(_, says)| says.render(self, now))
    }

    /// What the channel does: enabled or not, its duty and times, the cycle extension, an
    /// autotune's relay said first, a vendor's sizing advice last.
    fn state_line(&self, s: &Status) -> String {
        let pct = percent;
        let state = if !s.enabled {
            "disabled".into()
        } else if s.period == 0 {
            "enabled, no pulses (period 0)".into()
        } else if s.rule.extended() {
            format!(
                "enabled, {} % ({} ms on / {} ms off); cycle extended to {} ms to keep the duty \
                 ({})",
                Fixed(pct(s.duty_applied), 1),
                Fixed(ms(s.t_on), 1),
                Fixed(ms(s.t_off), 1),
                Fixed(ms(s.period), 1),
                s.rule.as_str()
            )
        } else {
            format!(
                "enabled, {} % ({} ms on / {} ms off)",
                Fixed(pct(s.duty_applied), 1),
                Fixed(ms(s.t_on), 1),
                Fixed(ms(s.t_off), 1)
            )
        };
        // An autotune's relay sets the duty: said first, so the duty is not taken for the loop's.
        let state = match &self.autotune {
            Some(p) => format!("autotune running ({}); {state}", autotune_progress(p)),
            None => state,
        };
        // Sizing advice: the channel runs as set; a vendor recommends otherwise (WARN).
        match s.sizing {
            Some(advice) => format!("{state}; sizing: {advice}"),
            None => state,
        }
    }

    /// The newest of a recent parameter refusal, a recent command refusal and a clamp in
    /// force, with its text (empty for a clamp whose text is unknown): whichever happened
    /// last is the news.
    fn input_news(&self, now: Nanos) -> Option<(News, &str)> {
        let s = self.status.as_ref()?;
        let at = |e: &Option<(String, Nanos)>| e.as_ref().map_or(0, |(_, at)| *at);
        let refusal = self
            .recent_refusal(now)
            .map(|r| (at(&self.last_refusal), News::Refusal, r));
        let rejection = self
            .recent_rejection(now)
            .map(|r| (at(&self.last_rejection), News::Rejection, r));
        let clamp = s.command_clamped.then(|| {
            let text = self.last_clamp.as_ref().map_or("", |(c, _)| c.as_str());
            (at(&self.last_clamp), News::Clamp, text)
        });
        // Newest wins; at the same instant a refused parameter is said before a refused
        // command, which is said before a clamp.
        [refusal, rejection, clamp]
            .into_iter()
            .flatten()
            .max_by_key(|(at, kind, _)| (*at, std::cmp::Reverse(*kind)))
            .map(|(_, kind, text)| (kind, text))
    }

    /// The diagnostic status at `now`, named `<node_name>: <ch>`, with the node-wide
    /// `counters`.
    pub fn to_status(
        &self,
        node_name: &str,
        now: Nanos,
        counters: NodeCounters,
    ) -> DiagnosticStatus {
        let mut kv: Vec<(&str, String)> = Vec::new();
        if let Some(s) = &self.status {
            kv.extend([
                ("enabled", s.enabled.to_string()),
                ("active", s.active.to_string()),
                ("output", s.level.is_high().to_string()),
                (
                    "duty_commanded_pct",
                    Fixed(percent(s.duty_commanded), 3).to_string(),
                ),
                (
                    "duty_applied_pct",
                    Fixed(percent(s.duty_applied), 3).to_string(),
                ),
                ("command_clamped", s.command_clamped.to_string()),
                (
                    "duty_target_pct",
                    Fixed(percent(s.duty_target), 3).to_string(),
                ),
                ("period_ms", Fixed(ms(s.period), 3).to_string()),
                ("on_time_ms", Fixed(ms(s.t_on), 3).to_string()),
                ("off_time_ms", Fixed(ms(s.t_off), 3).to_string()),
                ("e1", s.e1.to_string()),
                ("min_time_limited", s.limited.to_string()),
                ("rule", s.rule.as_str().to_string()),
                ("cycle_extended", s.rule.extended().to_string()),
                (
                    "protections",
                    s.protections.names().collect::<Vec<_>>().join(","),
                ),
                ("ignored_commands", s.ignored_commands.to_string()),
                ("skipped_pulses", s.skipped_pulses.to_string()),
                ("avg_duty_pct", Fixed(percent(s.avg_duty), 3).to_string()),
                ("time_base_ms", Fixed(ms(s.time_base), 6).to_string()),
                (
                    "sizing_advice",
                    s.sizing.map(|a| a.to_string()).unwrap_or_default(),
                ),
            ]);
            let h = &s.heater;
            if h.feedback {
                let num = |v: Option<f64>| v.map_or("none".into(), |v| Fixed(v, 3).to_string());
                kv.extend([
                    ("control", h.control.as_str().to_string()),
                    ("temperature_c", num(h.reading.map(|(c, _)| c))),
                    (
                        "temperature_age_ms",
                        num(h.reading.map(|(_, at)| ms(now.saturating_sub(at)))),
                    ),
                    ("setpoint_c", num(h.setpoint)),
                    ("target_c", num(h.target)),
                    ("pid_p_pct", Fixed(h.terms.p, 3).to_string()),
                    ("pid_i_pct", Fixed(h.terms.i, 3).to_string()),
                    ("pid_d_pct", Fixed(h.terms.d, 3).to_string()),
                    ("pid_output_pct", Fixed(h.terms.output, 3).to_string()),
                    ("runaway_error", Fixed(h.runaway_error, 1).to_string()),
                    ("model_predicted_c", num(h.model.map(|m| m.predicted_c))),
                    ("model_residual_c", num(h.model.map(|m| m.residual_c))),
                    (
                        "model",
                        h.model_params.map_or("none".into(), |m| {
                            format!(
                                "gain {:.4} °C/%, tau {:.2} s, dead time {:.2} s, sensor {:.2} \
                                 s, ambient {:.2} °C",
                                m.gain_c_per_pct,
                                m.tau_s,
                                m.dead_time_s,
                                m.sensor_tau_s,
                                m.ambient_c
                            )
                        }),
                    ),
                    ("mpc_predicted_c", num(h.mpc.map(|m| m.predicted_c))),
                    ("mpc_steady_pct", num(h.mpc.map(|m| m.steady_pct))),
                    ("mpc_disturbance_pct", num(h.mpc.map(|m| m.disturbance_pct))),
                    ("mpc_output_pct", num(h.mpc.map(|m| m.output))),
                    ("feedforward_pct", Fixed(h.feedforward_pct, 3).to_string()),
                    ("feedforward_stale", h.feedforward_stale.to_string()),
                    ("ambient_c", num(h.ambient_c)),
                    ("ambient_stale", h.ambient_stale.to_string()),
                    ("stale_readings", h.stale.0.to_string()),
                    (
                        "last_stale_age_ms",
                        if h.stale.0 == 0 {
                            "none".into()
                        } else {
                            Fixed(h.stale.1 as f64 / 1e6, 1).to_string()
                        },
                    ),
                    (
                        "heater_fault",
                        h.fault.map_or(String::new(), |f| f.check().to_string()),
                    ),
                    ("heater_fault_lasts", h.fault_lasts.to_string()),
                    (
                        "autotune",
                        self.autotune
                            .as_ref()
                            .map_or(String::new(), autotune_progress),
                    ),
                    (
                        "sizing",
                        h.sizing
                            .iter()
                            .flatten()
                            .map(|r| r.to_string())
                            .collect::<Vec<_>>()
                            .join("; "),
                    ),
                ]);
            }
        }
        kv.extend([
            ("watchdog_tripped", self.watchdog_tripped().to_string()),
            (
                "fault_value_active",
                self.status.is_some_and(|s| s.fault_active).to_string(),
            ),
            ("output_fault", self.output_fault.to_string()),
            (
                "estop_latched",
                self.status.is_some_and(|s| s.estopped).to_string(),
            ),
            ("edges", self.edges.to_string()),
            (
                "max_lateness_us",
                Fixed(self.max_late_ns as f64 / 1000.0, 1).to_string(),
            ),
            ("missed_edges", self.missed.to_string()),
            ("rejected_commands", self.rejected.to_string()),
            ("clamped_commands", self.clamped.to_string()),
            (
                "last_rejection",
                self.last_rejection
                    .as_ref()
                    .map(|(r, _)| r.clone())
                    .unwrap_or_default(),
            ),
            (
                "last_clamp",
                self.last_clamp
                    .as_ref()
                    .map(|(c, _)| c.clone())
                    .unwrap_or_default(),
            ),
            (
                "last_refusal",
                self.last_refusal
                    .as_ref()
                    .map(|(r, _)| r.clone())
                    .unwrap_or_default(),
            ),
            ("publish_failures", self.publish_failures.to_string()),
            ("reports_dropped", counters.reports_dropped.to_string()),
            ("samples_too_large", counters.samples_too_large.to_string()),
            (
                "conditions",
                self.conditions(now)
                    .map(|(c, _)| c.name)
                    .collect::<Vec<_>>()
                    .join(","),
            ),
        ]);
        DiagnosticStatus {
            level: self.level(now),
            name: channel_status_name(node_name, &self.name),
            message: self.message(now),
            hardware_id: self.hardware_id.clone(),
            values: key_values(kv),
        }
    }
}

/// Which input was the news (see `ChannelHealth::input_news`), in the order they are said when
/// they happened at the same instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum News {
    Refusal,
    Rejection,
    Clamp,
}

/// What a condition says when its message is the one shown: a fixed text, or a text formatted
/// from the channel's status then (and only then: a level is found without formatting).
#[derive(Clone, Copy)]
pub enum Says {
    /// A fixed message.
    Text(&'static str),
    /// A message formatted from the channel and its latest status at the time passed.
    Status(fn(&ChannelHealth, &Status, Nanos) -> String),
}

impl Says {
    fn render(self, h: &ChannelHealth, now: Nanos) -> String {
        match self {
            Says::Text(t) => t.to_string(),
            Says::Status(f) => h.status.as_ref().map_or_else(String::new, |s| f(h, s, now)),
        }
    }
}

/// A condition a channel's diagnostics report: its name (listed under the `conditions` key
/// while it holds), its level, and its check, which says whether it holds at the monotonic
/// time passed and what its message would be.
pub struct Condition {
    /// Short name, `snake_case`.
    pub name: &'static str,
    /// [`DiagnosticStatus::OK`], `WARN` or `ERROR`.
    pub level: u8,
    /// What the condition says when it holds at `now` (monotonic ns), `None` when it does not.
    pub check: fn(&ChannelHealth, Nanos) -> Option<Says>,
}

/// The status when it satisfies `f`.
fn status_if(h: &ChannelHealth, f: impl Fn(&Status) -> bool) -> Option<&Status> {
    h.status.as_ref().filter(|s| f(s))
}

/// Every condition of a channel's diagnostics, in precedence order: the status's level is the
/// highest level of those that hold, its message the first one's, and the `conditions` key
/// names them all. A new condition is one more row here.
pub static CONDITIONS: &[Condition] = &[
    Condition {
        name: "output_fault",
        level: DiagnosticStatus::ERROR,
        check: |h, _| {
            h.output_fault.then_some(Says::Text(
                "output fault: writing the line failed; every output driven off",
            ))
        },
    },
    Condition {
        name: "heater_fault",
        level: DiagnosticStatus::ERROR,
        check: |h, _| {
            status_if(h, |s| s.heater.fault.is_some())?;
            Some(Says::Status(|_, s, _| {
                let after = if s.heater.fault_lasts {
                    "the condition lasts; ~/<ch>/reset_fault is refused until it is gone"
                } else {
                    "the condition is gone; ~/<ch>/reset_fault clears it"
                };
                match s.heater.fault {
                    Some(f) => format!("heater fault {f}; line off and held off ({after})"),
                    None => String::new(),
                }
            }))
        },
    },
    Condition {
        name: "estop",
        level: DiagnosticStatus::ERROR,
        check: |h, _| {
            status_if(h, |s| s.estopped)?;
            Some(Says::Text(
                "e-stop latched: output held off until ~/reset_estop and a fresh enable",
            ))
        },
    },
    Condition {
        name: "watchdog",
        level: DiagnosticStatus::ERROR,
        check: |h, _| {
            if !h.watchdog_tripped() {
                return None;
            }
            Some(match status_if(h, |s| s.fault_active) {
                Some(_) => Says::Status(|_, s, _| {
                    format!(
                        "watchdog: no duty command within command_timeout_ms; running the fault \
                         value {:.1} % until the next command or fault_hold_ms",
                        percent(s.duty_applied)
                    )
                }),
                None => Says::Text(
                    "watchdog: no duty command within command_timeout_ms; output forced off \
                     until the next command",
                ),
            })
        },
    },
    Condition {
        name: "starting",
        level: DiagnosticStatus::OK,
        check: |h, _| h.status.is_none().then_some(Says::Text("starting")),
    },
    Condition {
        name: "feedback_stale",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.heater.stale_now)?;
            Some(Says::Status(|_, s, _| {
                let age = s.heater.stale.1 as f64 / 1e6;
                let (how, ms_) = if age < 0.0 {
                    ("ahead of this node's clock", -age)
                } else {
                    ("old on arrival", age)
                };
                format!(
                    "feedback readings refused as stale: {} so far, the last stamped {ms_:.0} \
                     ms {how}; the loop holds off them (check the hosts' clocks; \
                     feedback_max_skew_ms, feedback_timeout_ms)",
                    s.heater.stale.0
                )
            }))
        },
    },
    Condition {
        name: "setpoint_lowered",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| {
                s.heater.setpoint_lowered_from.is_some() && s.heater.setpoint.is_some()
            })?;
            Some(Says::Status(|_, s, _| {
                let num = |v: Option<f64>| v.unwrap_or(f64::NAN);
                format!(
                    "setpoint lowered from {} °C to {} °C: temp_max_c was lowered below it \
                     (the setpoint stays setpoint_margin_c under temp_max_c)",
                    num(s.heater.setpoint_lowered_from),
                    num(s.heater.setpoint)
                )
            }))
        },
    },
    Condition {
        name: "input_stale",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.heater.feedforward_stale || s.heater.ambient_stale)?;
            Some(Says::Status(|_, s, _| {
                let which = match (s.heater.feedforward_stale, s.heater.ambient_stale) {
                    (true, true) => "feed-forward and ambient",
                    (true, false) => "feed-forward",
                    _ => "ambient",
                };
                format!(
                    "{which} input stale (none yet, or older than its timeout): ignored; the \
                     feed-forward counts as 0 %, the ambient is model_ambient_c"
                )
            }))
        },
    },
    Condition {
        name: "input_refused",
        level: DiagnosticStatus::WARN,
        check: |h, now| {
            h.input_news(now)?;
            Some(Says::Status(|h, s, now| match h.input_news(now) {
                Some((News::Refusal, r)) => format!("parameter change refused: {r}"),
                Some((News::Rejection, r)) => format!("last duty command refused: {r}"),
                Some((News::Clamp, "")) => format!(
                    "duty command out of range, clamped to {:.1} %",
                    percent(s.duty_commanded)
                ),
                Some((News::Clamp, c)) => format!("duty command out of range: {c}"),
                None => String::new(),
            }))
        },
    },
    Condition {
        name: "e1_max_on",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.e1 && s.protections.max_on)?;
            Some(Says::Status(|_, s, _| {
                format!(
                    "E1: max_on_ms cuts the line: {:.1} % cannot be held on that long; it goes \
                     off for its minimum off time",
                    percent(s.duty_applied)
                )
            }))
        },
    },
    Condition {
        name: "e1_skipped_pulse",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.e1 && s.protections.delayed && !s.limited)?;
            Some(Says::Status(|_, s, _| {
                format!(
                    "E1: a pulse was skipped: no line went off in time for it \
                     (max_simultaneous_on, or another channel of its stagger group still on); \
                     {} skipped so far",
                    s.skipped_pulses
                )
            }))
        },
    },
    Condition {
        name: "e1",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.e1)?;
            Some(Says::Status(|_, s, _| {
                format!(
                    "E1: {:.1} % cannot be reproduced because of a minimum time ({}); {:.1} % \
                     applied",
                    percent(s.duty_commanded),
                    s.rule.as_str(),
                    percent(s.duty_applied)
                )
            }))
        },
    },
    Condition {
        name: "min_time_limited",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.limited && !s.rule.extended())?;
            Some(Says::Status(|_, s, _| {
                format!(
                    "minimum time limit acts ({}); {:.1} % applied for {:.1} % commanded",
                    s.rule.as_str(),
                    percent(s.duty_applied),
                    percent(s.duty_commanded)
                )
            }))
        },
    },
    Condition {
        name: "heater_sizing",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.heater.sizing[0].is_some())?;
            Some(Says::Status(|h, s, _| match s.heater.sizing[0] {
                Some(rule) => format!("{}; {rule}", h.state_line(s)),
                None => h.state_line(s),
            }))
        },
    },
    Condition {
        name: "protections",
        level: DiagnosticStatus::OK,
        check: |h, _| {
            status_if(h, |s| s.protections.any())?;
            Some(Says::Status(|h, s, _| {
                let acting: Vec<&str> = s.protections.names().collect();
                format!(
                    "{}; {:.1} % commanded, {:.1} % in force; protections acting: {}",
                    h.state_line(s),
                    percent(s.duty_commanded),
                    percent(s.duty_target),
                    acting.join(", ")
                )
            }))
        },
    },
    Condition {
        name: "sizing",
        level: DiagnosticStatus::WARN,
        check: |h, _| {
            status_if(h, |s| s.sizing.is_some())?;
            Some(Says::Status(|h, s, _| h.state_line(s)))
        },
    },
    Condition {
        name: "running",
        level: DiagnosticStatus::OK,
        check: |h, _| {
            h.status.as_ref()?;
            Some(Says::Status(|h, s, _| h.state_line(s)))
        },
    },
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Level;
    use crate::core::{Protections, Rule};

    fn status() -> Status {
        Status {
            enabled: true,
            active: true,
            level: Level::High,
            duty_commanded: 0.37,
            duty_requested: Command::Percent(37.0),
            command_clamped: false,
            duty_target: 0.37,
            duty_applied: 0.37,
            period: 1000 * NS_PER_MS,
            t_on: 370 * NS_PER_MS,
            t_off: 630 * NS_PER_MS,
            remaining_on: 100 * NS_PER_MS,
            remaining_off: 0,
            step_end: Some(1_100 * NS_PER_MS),
            e1: false,
            limited: false,
            watchdog_tripped: false,
            fault_active: false,
            estopped: false,
            rule: Rule::Exact,
            protections: Protections::default(),
            ignored_commands: 0,
            skipped_pulses: 0,
            avg_duty: 0.0,
            time_base: 0,
            t_on_input: 370 * NS_PER_MS,
            t_off_input: 630 * NS_PER_MS,
            sizing: None,
            heater: Default::default(),
        }
    }

    fn kv<'a>(d: &'a DiagnosticStatus, key: &str) -> &'a str {
        d.values
            .iter()
            .find(|k| k.key == key)
            .map(|k| k.value.as_str())
            .unwrap_or_else(|| panic!("no key {key}"))
    }

    /// A health in which the condition named holds, from the plain running channel.
    fn holding(name: &str) -> ChannelHealth {
        use crate::core::heater::{HeaterFault, Sizing};
        let mut h = ChannelHealth::new("pw01", "sim");
        let mut s = status();
        match name {
            "output_fault" => h.output_fault = true,
            "heater_fault" => {
                s.heater.fault = Some(HeaterFault::SensorTimeout {
                    silent_ms: 3_000,
                    timeout_ms: 2_000,
                })
            }
            "estop" => s.estopped = true,
            "watchdog" => h.watchdog = true,
            "starting" => {
                h.status = None;
                return h;
            }
            "feedback_stale" => {
                s.heater.stale_now = true;
                s.heater.stale = (2, 5_000_000_000);
            }
            "setpoint_lowered" => {
                s.heater.setpoint = Some(90.0);
                s.heater.setpoint_lowered_from = Some(120.0);
            }
            "input_stale" => s.heater.ambient_stale = true,
            "input_refused" => h.last_refusal = Some(("bad".into(), 1_000)),
            "e1_max_on" => {
                s.e1 = true;
                s.protections.max_on = true;
            }
            "e1_skipped_pulse" => {
                s.e1 = true;
                s.protections.delayed = true;
            }
            "e1" => s.e1 = true,
            "min_time_limited" => {
                s.limited = true;
                s.rule = Rule::SuppressedPulse;
            }
            "heater_sizing" => {
                s.heater.sizing[0] = Some(Sizing::PeriodAboveTi5 {
                    period_ms: 10_000.0,
                    ti_s: 20.0,
                })
            }
            "protections" => s.protections.slew = true,
            "sizing" => {
                s.sizing = crate::core::ChannelParams {
                    profile: crate::core::Profile::TcontCp,
                    period_ms: 1000,
                    time_base_ms: 100.0,
                    ..crate::core::ChannelParams::default()
                }
                .validate()
                .unwrap()
                .sizing()
            }
            "running" => {}
            other => panic!("no case for the condition {other}: add one here"),
        }
        h.status = Some(s);
        h
    }

    #[test]
    fn each_condition_of_the_table_sets_its_level_message_and_name() {
        for c in CONDITIONS {
            let h = holding(c.name);
            let d = h.to_status("n", 2_000, NodeCounters::default());
            let holds: Vec<&str> = kv(&d, "conditions").split(',').collect();
            assert!(holds.contains(&c.name), "{}: {holds:?}", c.name);
            // Alone or with the conditions below it (a plain running channel): first in line.
            assert_eq!(holds[0], c.name, "{}", c.name);
            assert_eq!(
                d.message,
                (c.check)(&h, 2_000).unwrap().render(&h, 2_000),
                "{}",
                c.name
            );
            let highest = CONDITIONS
                .iter()
                .filter(|b| holds.contains(&b.name))
                .map(|b| b.level)
                .max()
                .unwrap();
            assert_eq!(d.level, highest, "{}", c.name);
            assert!(d.level >= c.level, "{}", c.name);
        }
        // The names are distinct: each is one row.
        let mut names: Vec<&str> = CONDITIONS.iter().map(|c| c.name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), CONDITIONS.len());
    }

    #[test]
    fn the_interface_page_lists_the_conditions_in_their_order() {
        let page = include_str!("../../../docs/interface.md");
        let line = page
            .split("- Conditions, in precedence order:")
            .nth(1)
            .and_then(|rest| rest.split("\n- ").next())
            .expect("docs/interface.md lists the channel's conditions");
        let listed: Vec<&str> = line
            .split('`')
            .skip(1)
            .step_by(2)
            .take(CONDITIONS.len())
            .collect();
        let names: Vec<&str> = CONDITIONS.iter().map(|c| c.name).collect();
        assert_eq!(listed, names);
    }

    #[test]
    fn the_first_condition_speaks_and_the_highest_level_counts() {
        // A protection acting (OK) over a sizing advice (WARN): the message names the
        // protection and the advice; the level is the advice's.
        let mut h = holding("sizing");
        h.status.as_mut().unwrap().protections.slew = true;
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::WARN);
        assert_eq!(kv(&d, "conditions"), "protections,sizing,running");
        assert!(d.message.contains("sizing: 003"), "{}", d.message);
        assert!(
            d.message.contains("protections acting: slew"),
            "{}",
            d.message
        );
        // A watchdog tripped before the first snapshot: ERROR, and the message says why.
        let mut h = holding("starting");
        h.watchdog = true;
        assert_eq!(h.level(0), DiagnosticStatus::ERROR);
        assert!(h.message(0).starts_with("watchdog: "), "{}", h.message(0));
        // A refused parameter newer than a clamp no longer in force is the news.
        let mut h = holding("running");
        h.last_clamp = Some(("150 % is outside 0..100, clamped to 100.0 %".into(), 500));
        h.last_refusal = Some(("period_ms 4 is below 5 ms".into(), 400));
        assert_eq!(h.level(1_000), DiagnosticStatus::WARN);
        assert_eq!(
            h.message(1_000),
            "parameter change refused: period_ms 4 is below 5 ms"
        );
    }

    #[test]
    fn ok_warn_error() {
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(status());
        let d = h.to_status("pwm_actuator", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::OK);
        assert_eq!(d.name, "pwm_actuator: pw01");
        assert_eq!(d.hardware_id, "sim");
        assert_eq!(d.message, "enabled, 37.0 % (370.0 ms on / 630.0 ms off)");
        assert_eq!(kv(&d, "duty_applied_pct"), "37.000");

        h.status = Some(Status {
            e1: true,
            rule: Rule::SuppressedPulse,
            duty_applied: 0.0,
            ..status()
        });
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::WARN);
        assert!(d.message.starts_with("E1:"), "{}", d.message);
        assert!(d.message.contains("suppressed_pulse"));

        h.watchdog = true;
        assert_eq!(h.level(0), DiagnosticStatus::ERROR);
        assert!(h.message(0).starts_with("watchdog"));
        h.watchdog = false;
        h.output_fault = true;
        assert_eq!(h.level(0), DiagnosticStatus::ERROR);
        assert!(h.message(0).starts_with("output fault"));
    }

    #[test]
    fn a_cycle_extension_is_named_at_ok_and_max_on_still_warns() {
        // 5 % of 1 s with a 100 ms minimum: the period grew to 2 s; the duty is delivered.
        let extended = Status {
            duty_commanded: 0.05,
            duty_target: 0.05,
            duty_applied: 0.05,
            period: 2000 * NS_PER_MS,
            t_on: 100 * NS_PER_MS,
            t_off: 1900 * NS_PER_MS,
            limited: true,
            rule: Rule::ExtendedPulse,
            ..status()
        };
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(extended);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::OK);
        assert_eq!(
            d.message,
            "enabled, 5.0 % (100.0 ms on / 1900.0 ms off); cycle extended to 2000.0 ms to keep \
             the duty (extended_pulse)"
        );
        assert_eq!(kv(&d, "cycle_extended"), "true");
        assert_eq!(kv(&d, "period_ms"), "2000.000");
        assert_eq!(kv(&d, "rule"), "extended_pulse");
        assert_eq!(kv(&d, "min_time_limited"), "true");
        // The maximum on time cutting an extended pulse is E1: WARN.
        h.status = Some(Status {
            e1: true,
            protections: Protections {
                max_on: true,
                ..Protections::default()
            },
            ..extended
        });
        assert_eq!(h.level(0), DiagnosticStatus::WARN);
        h.status = Some(status());
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "cycle_extended"), "false");
    }

    #[test]
    fn a_refusal_warns_for_a_while_and_stays_listed() {
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(status());
        h.last_rejection = Some(("duty command is NaN; last valid command kept".into(), 1_000));
        h.rejected = 1;
        assert_eq!(h.level(2_000), DiagnosticStatus::WARN);
        assert_eq!(
            h.message(2_000),
            "last duty command refused: duty command is NaN; last valid command kept"
        );
        let later = 1_000 + REFUSAL_WARN_NS;
        assert_eq!(h.level(later), DiagnosticStatus::OK);
        let d = h.to_status(
            "n",
            later,
            NodeCounters {
                reports_dropped: 3,
                samples_too_large: 5,
            },
        );
        assert_eq!(
            kv(&d, "last_rejection"),
            "duty command is NaN; last valid command kept"
        );
        assert_eq!(kv(&d, "rejected_commands"), "1");
        assert_eq!(kv(&d, "reports_dropped"), "3");
        assert_eq!(kv(&d, "samples_too_large"), "5");
    }

    #[test]
    fn a_refused_parameter_warns_for_a_while_and_stays_listed() {
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(status());
        let reason = "pw01: period_ms 4 is below the transistor minimum of 5 ms";
        h.last_refusal = Some((reason.into(), 1_000));
        assert_eq!(h.level(2_000), DiagnosticStatus::WARN);
        assert_eq!(
            h.message(2_000),
            format!("parameter change refused: {reason}")
        );
        let later = 1_000 + REFUSAL_WARN_NS;
        assert_eq!(h.level(later), DiagnosticStatus::OK);
        assert_eq!(
            kv(
                &h.to_status("n", later, NodeCounters::default()),
                "last_refusal"
            ),
            reason
        );
        // A command refused after the parameter is the newer news.
        h.last_rejection = Some(("duty command is NaN; last valid command kept".into(), 3_000));
        assert!(h.message(4_000).starts_with("last duty command refused"));
    }

    #[test]
    fn the_protections_acting_are_named() {
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(Status {
            duty_commanded: 1.0,
            duty_target: 0.6,
            duty_applied: 0.6,
            t_on: 600 * NS_PER_MS,
            t_off: 400 * NS_PER_MS,
            protections: Protections {
                max_duty: true,
                slew: true,
                ..Protections::default()
            },
            ignored_commands: 3,
            skipped_pulses: 2,
            ..status()
        });
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(
            d.level,
            DiagnosticStatus::OK,
            "they do what they were set for"
        );
        assert_eq!(
            d.message,
            "enabled, 60.0 % (600.0 ms on / 400.0 ms off); 100.0 % commanded, 60.0 % in \
             force; protections acting: max_duty, slew"
        );
        assert_eq!(kv(&d, "protections"), "max_duty,slew");
        assert_eq!(kv(&d, "duty_target_pct"), "60.000");
        assert_eq!(kv(&d, "ignored_commands"), "3");
        assert_eq!(kv(&d, "skipped_pulses"), "2");
        let m = status_msg(0, h.status.as_ref().unwrap(), 0, 0);
        assert_eq!(m.protections, ["max_duty", "slew"]);
        assert_eq!(m.duty_target, 60.0);
        // The maximum on time sets E1: WARN, and the message says why.
        h.status = Some(Status {
            e1: true,
            limited: true,
            protections: Protections {
                max_on: true,
                ..Protections::default()
            },
            ..status()
        });
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::WARN);
        assert!(
            d.message.starts_with("E1: max_on_ms cuts the line"),
            "{}",
            d.message
        );
        assert_eq!(kv(&d, "protections"), "max_on");
    }

    #[test]
    fn clamped_command_in_force_warns() {
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(Status {
            command_clamped: true,
            duty_commanded: 1.0,
            ..status()
        });
        h.last_clamp = Some(("150 % clamped to 100.0 %".into(), 10));
        assert_eq!(h.level(20), DiagnosticStatus::WARN);
        let clamped = "duty command out of range: 150 % clamped to 100.0 %";
        assert_eq!(h.message(20), clamped);
        // The more recent of a refusal and a clamp is the message.
        h.last_rejection = Some(("duty command is NaN; last valid command kept".into(), 5));
        assert_eq!(h.message(20), clamped);
        h.last_rejection = Some(("duty command is NaN; last valid command kept".into(), 15));
        assert!(h.message(20).starts_with("last duty command refused"));
    }

    #[test]
    fn clamped_commands_are_described_in_a_few_characters() {
        assert_eq!(
            clamp_text(Command::Percent(1e308), 1.0),
            "1e308 % is outside 0..100, clamped to 100.0 %"
        );
        assert_eq!(
            clamp_text(Command::Percent(-1.5e300), 0.0),
            "-1.5e300 % is outside 0..100, clamped to 0.0 %"
        );
        assert_eq!(
            clamp_text(Command::Percent(150.5), 1.0),
            "150.5 % is outside 0..100, clamped to 100.0 %"
        );
        assert_eq!(
            clamp_text(Command::Percent(-5e-324), 0.0),
            "-5e-324 % is outside 0..100, clamped to 0.0 %"
        );
        assert_eq!(
            clamp_text(Command::Sv(5000), 1.0),
            "SV 5000 is outside 0..4095, clamped to 100.0 %"
        );
    }

    #[test]
    fn the_status_carries_the_input_s_times_and_whole_second_countdowns_002() {
        // 002: fActTiOn / fActTiOff from the current input beside the times in force, and the
        // countdowns nRemTiOn / nRemTiOff in whole seconds (UDINT), truncated.
        let s = Status {
            remaining_on: 2_999 * NS_PER_MS,
            step_end: Some(3_000 * NS_PER_MS),
            t_on_input: 600 * NS_PER_MS,
            t_off_input: 400 * NS_PER_MS,
            time_base: 8_333_333,
            ..status()
        };
        let m = status_msg(0, &s, 0, 5);
        assert_eq!((m.on_time_ms, m.off_time_ms), (370.0, 630.0));
        assert_eq!((m.on_time_input_ms, m.off_time_input_ms), (600.0, 400.0));
        assert_eq!((m.remaining_on_ms, m.remaining_on_s), (3_000.0, 3));
        let m = status_msg(0, &s, NS_PER_MS, 5);
        assert_eq!((m.remaining_on_s, m.remaining_off_s), (2, 0));
        assert_eq!(m.time_base_ms, 8.333333);
        assert_eq!(whole_seconds(999_999_999), 0);
        assert_eq!(whole_seconds(Nanos::MAX), u32::MAX);
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(s);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "time_base_ms"), "8.333333");
    }

    #[test]
    fn sizing_advice_is_a_warn_naming_the_rule_and_the_figures_003_001() {
        let cfg = crate::core::ChannelParams {
            profile: crate::core::Profile::TcontCp,
            period_ms: 1000,
            time_base_ms: 100.0,
            ..crate::core::ChannelParams::default()
        }
        .validate()
        .unwrap();
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(Status {
            sizing: cfg.sizing(),
            ..status()
        });
        assert_eq!(h.level(0), DiagnosticStatus::WARN);
        let m = h.message(0);
        assert!(
            m.starts_with(
                "enabled, 37.0 % (370.0 ms on / 630.0 ms off); sizing: 003 recommends \
                           CYCLE_P <= PER_TM/50: time_base_ms 100 is above period_ms 1000 / 50 \
                           = 20 ms"
            ),
            "{m}"
        );
        let d = h.to_status("n", 0, NodeCounters::default());
        assert!(kv(&d, "sizing_advice").starts_with("003 recommends CYCLE_P"));
        // Without it: OK and an empty value.
        h.status = Some(status());
        assert_eq!(h.level(0), DiagnosticStatus::OK);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "sizing_advice"), "");
    }

    #[test]
    fn mpc_shows_its_model_target_and_terms_and_a_stale_input_warns() {
        let mut h = ChannelHealth::new("pw01", "sim");
        let mut s = status();
        s.heater.feedback = true;
        s.heater.control = crate::core::heater::Control::Mpc;
        s.heater.setpoint = Some(80.0);
        s.heater.target = Some(61.5);
        s.heater.model_params = Some(crate::core::heater::ModelParams {
            gain_c_per_pct: 1.8,
            tau_s: 120.0,
            dead_time_s: 2.0,
            ambient_c: 21.0,
            sensor_tau_s: 0.5,
        });
        s.heater.mpc = Some(crate::core::heater::MpcTerms {
            predicted_c: 60.0,
            steady_pct: 22.0,
            disturbance_pct: 3.0,
            output: 100.0,
        });
        h.status = Some(s);
        assert_eq!(h.level(0), DiagnosticStatus::OK);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "control"), "mpc");
        assert_eq!(kv(&d, "target_c"), "61.500");
        assert_eq!(
            kv(&d, "model"),
            "gain 1.8000 °C/%, tau 120.00 s, dead time 2.00 s, sensor 0.50 s, ambient 21.00 °C"
        );
        assert_eq!(kv(&d, "mpc_disturbance_pct"), "3.000");
        assert_eq!(status_msg(0, &s, 0, 5).control, "mpc");
        s.heater.feedforward_stale = true;
        h.status = Some(s);
        assert_eq!(h.level(0), DiagnosticStatus::WARN);
        assert!(
            h.message(0).starts_with("feed-forward input stale"),
            "{}",
            h.message(0)
        );
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "feedforward_stale"), "true");
    }

    #[test]
    fn a_running_autotune_is_said_first_and_listed() {
        let mut h = ChannelHealth::new("pw01", "sim");
        let mut s = status();
        s.heater.feedback = true;
        h.status = Some(s);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "autotune"), "");
        assert!(d.message.starts_with("enabled, 37.0 %"), "{}", d.message);

        h.autotune = Some(Progress {
            phase: Phase::Relay,
            cycles: 3,
            amplitude_c: 1.5,
            period_s: 4.0,
            dead_time: None,
        });
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(d.level, DiagnosticStatus::OK);
        assert_eq!(kv(&d, "autotune"), "relay, 3 cycles");
        assert!(
            d.message
                .starts_with("autotune running (relay, 3 cycles); enabled, 37.0 %"),
            "{}",
            d.message
        );
        // Past its agreeing cycles, for the dead time: why, and how far.
        h.autotune = Some(Progress {
            phase: Phase::DeadTime,
            cycles: 30,
            amplitude_c: 1.5,
            period_s: 4.0,
            dead_time: Some(crate::core::heater::autotune::DeadTimeProgress {
                dead_time_s: 0.52,
                se_s: 0.041,
                extended_s: 300.0,
                bound_s: 2400.0,
            }),
        });
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(
            kv(&d, "autotune"),
            "dead_time, 30 cycles, telling the dead time: 0.52 ± 0.041 s so far, going on \
             until its standard error is within 4 % of it or autotune_extend_s 2400 s has \
             passed (300 s)"
        );
        // A fault outranks it.
        h.status = Some(Status {
            estopped: true,
            ..s
        });
        assert!(
            h.message(0).starts_with("e-stop latched"),
            "{}",
            h.message(0)
        );
    }

    #[test]
    fn a_negative_zero_command_is_reported_as_zero() {
        let s = Status {
            duty_commanded: -0.0,
            duty_applied: -0.0,
            ..status()
        };
        let m = status_msg(0, &s, 1_050 * NS_PER_MS, 5);
        assert!(
            m.duty_commanded == 0.0 && m.duty_commanded.is_sign_positive(),
            "{:?}",
            m.duty_commanded
        );
        assert!(m.duty_applied.is_sign_positive(), "{:?}", m.duty_applied);
        let mut h = ChannelHealth::new("pw01", "sim");
        h.status = Some(s);
        let d = h.to_status("n", 0, NodeCounters::default());
        assert_eq!(kv(&d, "duty_commanded_pct"), "0.000");
        assert_eq!(kv(&d, "duty_applied_pct"), "0.000");
    }

    #[test]
    fn lateness_percentiles_within_a_bucket() {
        let mut h = LatenessHistogram::default();
        assert_eq!((h.quantile_ns(0.99), h.edges(), h.max_ns()), (0, 0, 0));
        // 990 edges 10 us late, 10 edges 500 us late: p99 is 10 us (rounded up to the end
        // of its bucket, within 6.25 %), p99.9 is 500 us, never above the maximum.
        for _ in 0..990 {
            h.record(10_000);
        }
        for _ in 0..10 {
            h.record(500_000);
        }
        let p99 = h.quantile_ns(0.99);
        assert!((10_000..=10_625).contains(&p99), "{p99}");
        assert_eq!(h.quantile_ns(0.999), 500_000);
        assert_eq!((h.edges(), h.max_ns()), (1000, 500_000));
        // Early writes count as on time; tiny values are exact.
        let mut h = LatenessHistogram::default();
        h.record(-5);
        h.record(7);
        assert_eq!((h.quantile_ns(0.5), h.quantile_ns(1.0)), (0, 7));
        // Every bucket's end is in the bucket, and the next value starts the next one.
        for ns in [15u64, 16, 17, 31, 32, 33, 1_000_000, u64::MAX / 3, u64::MAX] {
            let b = LatenessHistogram::bucket(ns);
            let end = LatenessHistogram::upper(b);
            assert!(end >= ns, "{ns}");
            assert_eq!(LatenessHistogram::bucket(end), b, "{ns}");
            if end < u64::MAX {
                assert_eq!(LatenessHistogram::bucket(end + 1), b + 1, "{ns}");
            }
            assert!((end - ns) as f64 <= ns as f64 / 16.0, "{ns}");
        }
    }

    #[test]
    fn the_node_status_says_estop_losses_and_lifecycle() {
        let mut n = NodeHealth::default();
        for _ in 0..100 {
            n.lateness.record(42_000);
        }
        n.lateness_window_s = 1.0;
        let d = n.to_status("pwm_actuator", 0);
        assert_eq!(d.name, "pwm_actuator: node");
        assert_eq!(d.level, DiagnosticStatus::OK);
        assert!(
            d.message
                .starts_with("lifecycle unmanaged, e-stop released"),
            "{}",
            d.message
        );
        let p99: f64 = kv(&d, "lateness_p99_us").parse().unwrap();
        assert!((42.0..=44.7).contains(&p99), "{p99}");
        assert_eq!(kv(&d, "lateness_max_us"), "42.0");
        assert_eq!(kv(&d, "lateness_window_edges"), "100");
        assert_eq!(kv(&d, "lateness_window_s"), "1.000");
        assert_eq!(kv(&d, "lifecycle_state"), "unmanaged");
        assert_eq!(kv(&d, "estop_latched"), "false");
        assert_eq!(kv(&d, "reports_dropped"), "0");
        assert_eq!(kv(&d, "trace_messages_dropped"), "0");
        n.trace_dropped = 5;
        assert_eq!(
            kv(&n.to_status("pwm_actuator", 0), "trace_messages_dropped"),
            "5"
        );

        n.counters.reports_dropped = 12;
        n.last_drop = Some(1_000);
        assert_eq!(n.level(2_000), DiagnosticStatus::WARN);
        assert!(n.message(2_000).contains("12 since start-up"));
        assert_eq!(n.level(1_000 + LOSS_WARN_NS), DiagnosticStatus::OK);

        n.estop_latched = true;
        n.estop_latches = 1;
        n.lifecycle = "inactive";
        let d = n.to_status("pwm_actuator", 2_000);
        assert_eq!(d.level, DiagnosticStatus::ERROR);
        assert!(d.message.starts_with("e-stop latched"), "{}", d.message);
        assert_eq!(kv(&d, "estop_latched"), "true");
        assert_eq!(kv(&d, "estop_latches"), "1");
        assert_eq!(kv(&d, "lifecycle_state"), "inactive");
    }

    /// launch-notes/diagnostic_analyzers.yaml takes the statuses by the prefix the node's
    /// names start with (tests/rclpy/test_diagnostics.py checks it against a running node).
    #[test]
    fn the_analyzers_file_names_the_node_s_prefix() {
        use yaml_rust2::YamlLoader;
        let text = include_str!("../../../launch-notes/diagnostic_analyzers.yaml");
        let docs = YamlLoader::load_from_str(text).expect("valid YAML");
        let a = &docs[0]["analyzers"]["ros__parameters"]["pwm_actuator"];
        assert_eq!(
            a["type"].as_str(),
            Some("diagnostic_aggregator/GenericAnalyzer")
        );
        let node = crate::ros::config::names::NODE_NAME;
        let prefix = format!("{node}:");
        let prefixes: Vec<&str> = a["find_and_remove_prefix"]
            .as_vec()
            .expect("a list")
            .iter()
            .filter_map(|y| y.as_str())
            .collect();
        assert_eq!(prefixes, [prefix.as_str()]);
        for name in [
            channel_status_name(node, "pw01"),
            frequency_status_name(node, "pw01"),
            node_status_name(node),
        ] {
            assert!(name.starts_with(&prefix), "{name}");
        }
        let expected = a["expected"].as_vec().expect("a list");
        assert_eq!(expected[0].as_str(), Some(node_status_name(node).as_str()));
    }

    #[test]
    fn status_message_and_change_detection() {
        let s = status();
        let m = status_msg(0, &s, 1_050 * NS_PER_MS, 5);
        assert_eq!(m.channel, 1);
        assert_eq!(m.duty_commanded, 37.0);
        assert_eq!(m.on_time_ms, 370.0);
        assert_eq!(m.remaining_on_ms, 50.0);
        assert_eq!(m.rule, "exact");
        let later = Status {
            remaining_on: 10,
            ..s
        };
        assert!(!status_changed(&s, &later));
        let off = Status {
            level: Level::Low,
            ..s
        };
        assert!(status_changed(&s, &off));
    }
}
