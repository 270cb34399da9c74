//! The traces on `/diagnostics` and in the log: one status per trace (`<node>: trace <path>`)
//! from the state its writer thread tells ([`TraceHealth`]), and a log line when something
//! new happens to one.
//!
//! A trace is WARN while it cannot be written (a full disk, a read-only file system: what it
//! should hold is counted lost, and a new file is tried every second) or its file system is
//! full, and for [`LOSS_WARN_NS`] after any problem (its file deleted while written and begun
//! again, a failure that has ended). The report thread reads the state at least every
//! [`MAX_WAIT`](super::reporter::MAX_WAIT), so a failure reaches `/diagnostics` at once: a
//! changed level is published within 50 ms.
//!
//! The log says each failure, full file system and deleted file once when it is seen, what a
//! failure that lasts has lost at most every [`LOG_REPEAT_NS`], and when it ends; its words
//! are the node's own ([`crate::output::trace_files::io_reason`]), the path escaped.

use crate::core::Nanos;
use crate::output::trace::TraceFormat;
use crate::output::trace_files::BYTES_PER_MB;
use crate::output::{TraceHealth, TraceState};
use crate::ros::config::logging::escape_controls;
use crate::ros::interface::msg::DiagnosticStatus;
use crate::ros::outbound::diagnostics::{key_values, LOSS_WARN_NS};
use log::{info, warn};

/// The least time between two log lines about one lasting failure, or about rotations, ns.
pub const LOG_REPEAT_NS: Nanos = 10_000_000_000;

/// The longest path shown in a status name or a log line, in characters; a longer one keeps
/// its end (the file name).
const MAX_PATH_CHARS: usize = 160;

/// What the log last said of one trace.
#[derive(Debug, Clone, Default)]
struct Told {
    failing: Option<String>,
    no_room: bool,
    reopened: u64,
    rotations: u64,
    lost: u64,
    /// When a lasting failure or a rotation was last logged, monotonic ns.
    repeated_at: Option<Nanos>,
    rotated_at: Option<Nanos>,
}

/// The traces' statuses and log lines (see the module documentation).
#[derive(Debug, Clone, Default)]
pub struct TraceReport {
    health: TraceHealth,
    seen: Option<u64>,
    states: Vec<TraceState>,
    told: Vec<Told>,
}

/// A path as shown: control characters escaped, at most [`MAX_PATH_CHARS`] characters.
fn shown_path(state: &TraceState) -> String {
    let text = state.path.to_string_lossy();
    let escaped = escape_controls(&text);
    let n = escaped.chars().count();
    if n <= MAX_PATH_CHARS {
        return escaped.into_owned();
    }
    let tail: String = escaped.chars().skip(n - MAX_PATH_CHARS).collect();
    format!("…{tail}")
}

/// What a trace's records are.
fn records(state: &TraceState) -> &'static str {
    match state.format {
        TraceFormat::Mcap => "messages",
        TraceFormat::Csv | TraceFormat::Vcd => "edges",
    }
}

fn mb(bytes: u64) -> String {
    format!("{:.1}", bytes as f64 / BYTES_PER_MB as f64)
}

impl TraceReport {
    /// Reports the traces of `health`.
    pub fn new(health: TraceHealth) -> TraceReport {
        TraceReport {
            health,
            ..TraceReport::default()
        }
    }

    /// Reads the traces' state if something worth telling changed, or `always` (for their
    /// sizes), and logs what is new. Returns whether it read.
    pub fn poll(&mut self, now: Nanos, always: bool) -> bool {
        let changes = self.health.changes();
        if !always && self.seen == Some(changes) {
            return false;
        }
        self.seen = Some(changes);
        self.states = self.health.snapshot();
        self.told.resize(self.states.len(), Told::default());
        for (state, told) in self.states.iter().zip(self.told.iter_mut()) {
            log_news(state, told, now);
        }
        true
    }

    /// Each trace's level at `now`, in order.
    pub fn levels(&self, now: Nanos) -> impl Iterator<Item = u8> + '_ {
        self.states.iter().map(move |s| level(s, now))
    }

    /// Each trace's status at `now`, in order, named `<node_name>: trace <path>`.
    pub fn statuses(&self, node_name: &str, now: Nanos) -> Vec<DiagnosticStatus> {
        self.states
            .iter()
            .map(|s| status(s, node_name, now))
            .collect()
    }
}

/// Whether a problem of `state` was seen within [`LOSS_WARN_NS`] before `now`.
fn recent(state: &TraceState, now: Nanos) -> bool {
    state
        .last_problem
        .as_ref()
        .is_some_and(|(_, at)| now.saturating_sub(*at) < LOSS_WARN_NS)
}

fn level(state: &TraceState, now: Nanos) -> u8 {
    if state.failing.is_some() || state.no_room || recent(state, now) {
        DiagnosticStatus::WARN
    } else {
        DiagnosticStatus::OK
    }
}

fn status(state: &TraceState, node_name: &str, now: Nanos) -> DiagnosticStatus {
    let path = shown_path(state);
    let what = records(state);
    let lost = match state.lost {
        0 => String::new(),
        n => format!("; {n} {what} lost since start-up"),
    };
    let message = if let Some(f) = &state.failing {
        format!("{f}: {what} are lost until it can be written again{lost}")
    } else if state.no_room {
        format!("its file system is full: what it cannot write is lost{lost}")
    } else if let (true, Some((p, at))) = (recent(state, now), &state.last_problem) {
        let ago = now.saturating_sub(*at) as f64 / 1e9;
        format!("{p} ({ago:.1} s ago){lost}")
    } else {
        let limit = match state.limit_bytes {
            0 => "no limit".to_string(),
            l => format!("at most {} MB", mb(l)),
        };
        format!(
            "written: {} MB in {} file(s), {limit}; {} older file(s) deleted{lost}",
            mb(state.bytes),
            state.files,
            state.files_dropped
        )
    };
    let state_word = if state.failing.is_some() {
        "failing"
    } else if state.no_room {
        "full"
    } else {
        "writing"
    };
    let kv = vec![
        ("path", path.clone()),
        ("state", state_word.to_string()),
        ("bytes", state.bytes.to_string()),
        ("files", state.files.to_string()),
        ("limit_bytes", state.limit_bytes.to_string()),
        ("rotations", state.rotations.to_string()),
        ("files_deleted", state.files_dropped.to_string()),
        (
            if state.format == TraceFormat::Mcap {
                "messages_lost"
            } else {
                "edges_lost"
            },
            state.lost.to_string(),
        ),
        ("problems", state.problems.to_string()),
        ("reopened", state.reopened.to_string()),
        (
            "last_problem",
            state
                .last_problem
                .as_ref()
                .map_or(String::new(), |(p, _)| p.clone()),
        ),
    ];
    DiagnosticStatus {
        level: level(state, now),
        name: format!("{node_name}: trace {path}"),
        message,
        hardware_id: node_name.to_string(),
        values: key_values(kv),
    }
}

/// Logs what is new of `state` since `told`, and remembers it.
fn log_news(state: &TraceState, told: &mut Told, now: Nanos) {
    let path = shown_path(state);
    let what = records(state);
    match (&told.failing, &state.failing) {
        (old, Some(f)) if old.as_deref() != Some(f.as_str()) => {
            warn!(
                "trace {path}: {f}; its {what} are lost until it can be written again (a new \
                 file is tried every second)"
            );
            told.repeated_at = Some(now);
            told.lost = state.lost;
        }
        (Some(_), Some(f)) => {
            let due = told
                .repeated_at
                .is_none_or(|at| now.saturating_sub(at) >= LOG_REPEAT_NS);
            if due && state.lost > told.lost {
                warn!(
                    "trace {path}: still {f}; {} {what} lost since start-up",
                    state.lost
                );
                told.repeated_at = Some(now);
                told.lost = state.lost;
            }
        }
        (Some(_), None) => {
            info!(
                "trace {path}: written again; {} {what} lost since start-up",
                state.lost
            );
            told.lost = state.lost;
        }
        (None, _) => {}
    }
    told.failing = state.failing.clone();
    if state.no_room && !told.no_room {
        warn!("trace {path}: its file system is full");
    } else if !state.no_room && told.no_room {
        info!("trace {path}: its file system has room again");
    }
    told.no_room = state.no_room;
    if state.reopened > told.reopened {
        warn!(
            "trace {path}: the file was deleted or replaced while written; begun again at its \
             path"
        );
        told.reopened = state.reopened;
    }
    if state.rotations > told.rotations {
        let due = told
            .rotated_at
            .is_none_or(|at| now.saturating_sub(at) >= LOG_REPEAT_NS);
        if due {
            info!(
                "trace {path}: the file written is full and goes on in a new one ({} rotation(s) \
                 so far, {} oldest file(s) deleted; limit {} MB)",
                state.rotations,
                state.files_dropped,
                mb(state.limit_bytes)
            );
            told.rotated_at = Some(now);
            told.rotations = state.rotations;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::trace_files::TraceState;
    use std::path::Path;

    const S: Nanos = 1_000_000_000;

    fn kv(d: &DiagnosticStatus, key: &str) -> String {
        d.values
            .iter()
            .find(|v| v.key == key)
            .map(|v| v.value.clone())
            .unwrap_or_else(|| panic!("no {key}"))
    }

    #[test]
    fn a_failing_trace_is_warn_naming_it_until_it_writes_again_and_a_while_after() {
        let health = TraceHealth::new();
        let csv = health.register(TraceState::new(
            Path::new("/t/run.csv"),
            TraceFormat::Csv,
            256_000_000,
        ));
        let mcap = health.register(TraceState::new(
            Path::new("/t/run.mcap"),
            TraceFormat::Mcap,
            256_000_000,
        ));
        let mut r = TraceReport::new(health.clone());
        assert!(r.poll(0, false));
        assert!(!r.poll(S, false), "nothing new");
        let st = r.statuses("pwm_actuator", S);
        assert_eq!(st[0].name, "pwm_actuator: trace /t/run.csv");
        assert_eq!(st[1].name, "pwm_actuator: trace /t/run.mcap");
        assert!(st.iter().all(|s| s.level == DiagnosticStatus::OK));
        assert!(st[0]
            .message
            .starts_with("written: 0.0 MB in 1 file(s), at most 256.0 MB"));

        csv.update(|s| {
            s.failing = Some("cannot write: no space left on the file system (os error 28)".into());
            s.problem(s.failing.clone().unwrap(), 2 * S);
            s.lost = 12;
        });
        assert!(r.poll(2 * S, false), "a failure is read at once");
        let st = r.statuses("pwm_actuator", 2 * S);
        assert_eq!(st[0].level, DiagnosticStatus::WARN);
        assert_eq!(
            st[0].message,
            "cannot write: no space left on the file system (os error 28): edges are lost until \
             it can be written again; 12 edges lost since start-up"
        );
        assert_eq!(kv(&st[0], "state"), "failing");
        assert_eq!(kv(&st[0], "edges_lost"), "12");
        assert_eq!(st[1].level, DiagnosticStatus::OK);
        assert_eq!(kv(&st[1], "messages_lost"), "0");

        // Written again: WARN for a while, then OK with the count kept.
        csv.update(|s| s.failing = None);
        r.poll(3 * S, false);
        assert_eq!(r.levels(3 * S).collect::<Vec<_>>(), [1, 0]);
        let later = 2 * S + LOSS_WARN_NS;
        assert_eq!(r.levels(later).collect::<Vec<_>>(), [0, 0]);
        let st = r.statuses("pwm_actuator", later);
        assert!(
            st[0].message.ends_with("; 12 edges lost since start-up"),
            "{}",
            st[0].message
        );

        // A full file system and a deleted file are WARN too.
        mcap.update(|s| {
            s.no_room = true;
            s.problem("its file system is full".into(), 20 * S);
        });
        r.poll(20 * S, false);
        assert_eq!(r.levels(20 * S).collect::<Vec<_>>(), [0, 1]);
        assert_eq!(kv(&r.statuses("n", 20 * S)[1], "state"), "full");
    }

    #[test]
    fn a_long_path_keeps_its_end_and_control_characters_are_escaped() {
        let health = TraceHealth::new();
        let long = format!("/{}/run\n.csv", "d".repeat(300));
        health.register(TraceState::new(Path::new(&long), TraceFormat::Csv, 0));
        let mut r = TraceReport::new(health);
        r.poll(0, true);
        let st = r.statuses("n", 0);
        assert!(st[0].name.ends_with("run\\n.csv"), "{}", st[0].name);
        assert!(st[0].name.chars().count() < 200);
        assert!(st[0].message.contains("no limit"), "{}", st[0].message);
    }
}
