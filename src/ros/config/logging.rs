//! The process logger: `log` records go to stderr in ROS's console format
//! (`[INFO] [1712345678.123456789] [pwm_actuator]: text`) and, once the node exists, the node's
//! own records also go to `/rosout`.
//!
//! Levels follow `--log-level`: the bare level sets the node's level (default info);
//! `--log-level NAME:=LEVEL` sets it for a logger, where the node's name (before or after
//! remapping) means this node and any other name is taken as a Rust log target prefix
//! (`rustdds`, `ros2_client`). Libraries log errors only, unless `--enable-external-lib-logs`
//! lets them log at the node's level, or a logger level names them.
//!
//! Every record is made safe to show before it goes anywhere ([`for_log`]): control characters
//! (newlines, ESC, ...) and the Unicode characters that reorder or hide text are written as
//! visible escapes (`\n`, `\u{1b}`), so input echoed in a message cannot forge log lines or
//! drive the terminal, and a record longer than [`MAX_RECORD_BYTES`] is cut, with its size
//! given. Code that echoes input in a message bounds it first with [`shown`]. Warnings and
//! errors are rate-limited per place in the code ([`RateLimiter`]): a flood of one kind
//! (malformed samples, refusals) gives a few lines and then one count of what was suppressed.
//! So are the informational lines that any participant's input causes (an enable toggled,
//! a parameter set, the e-stop; see [`rate_limited`]): an input flood cannot flood the log.
//!
//! Must not block for long or allocate without bound: it runs on every thread that logs, never
//! on the output thread's hot path (the output thread does not log there).

use crate::ros::config::args::RosArgs;
use log::{LevelFilter, Log, Metadata, Record};
use ros2_client::rosout::RosoutRaw;
use ros2_client::NodeLoggingHandle;
use std::borrow::Cow;
use std::cell::Cell;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, OnceLock};

/// The log target prefix of this crate.
const OWN_TARGET: &str = "pwm_actuator";

/// Longest text of one log record, in bytes (after escaping); the rest is cut and the size of
/// the whole given.
pub const MAX_RECORD_BYTES: usize = 2048;

/// Longest piece of input that [`shown`] echoes, in characters.
pub const MAX_ECHO_CHARS: usize = 64;

/// Warnings and errors shown per place in the code and per [`RATE_WINDOW_NS`]; the rest are
/// counted and summarised.
pub const RATE_BURST: u32 = 10;

/// The rate limiter's window, ns.
pub const RATE_WINDOW_NS: u64 = 10_000_000_000;

/// Whether `c` must not reach a terminal or a log as it is: control characters, and the
/// Unicode format characters that reorder (bidi overrides) or hide (zero-width) text.
fn needs_escape(c: char) -> bool {
    c.is_control()
        || matches!(c, '\u{200b}'..='\u{200f}' | '\u{2028}'..='\u{202e}' | '\u{2060}'..='\u{206f}' | '\u{feff}')
}

/// `s` with control characters written as visible escapes: `\n`, `\r`, `\t`, and `\u{1b}`
/// for the others (ESC, NUL, DEL, C1, bidi overrides, zero-width characters). Printable text,
/// quotes and backslashes are left as they are.
pub fn escape_controls(s: &str) -> Cow<'_, str> {
    if !s.chars().any(needs_escape) {
        return Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if needs_escape(c) => {
                let _ = write!(out, "\\u{{{:x}}}", c as u32);
            }
            c => out.push(c),
        }
    }
    Cow::Owned(out)
}

/// `s` escaped and cut to `max_chars` characters; a cut text ends with `… (N bytes)`, N the size
/// of the whole input.
fn cut(s: &str, max_chars: usize) -> String {
    match s.char_indices().nth(max_chars) {
        None => escape_controls(s).into_owned(),
        Some((end, _)) => format!("{}… ({} bytes)", escape_controls(&s[..end]), s.len()),
    }
}

/// Input to echo in a message (a parameter name, a field, a string value): escaped, and cut to
/// its first [`MAX_ECHO_CHARS`] characters with its size (`aaaa… (4194304 bytes)`).
pub fn shown(s: &str) -> String {
    cut(s, MAX_ECHO_CHARS)
}

/// The text of a log record as it is written: escaped, and at most [`MAX_RECORD_BYTES`] bytes
/// plus the size note.
pub fn for_log(text: &str) -> Cow<'_, str> {
    let escaped = escape_controls(text);
    if escaped.len() <= MAX_RECORD_BYTES {
        return escaped;
    }
    let mut end = MAX_RECORD_BYTES;
    while !escaped.is_char_boundary(end) {
        end -= 1;
    }
    Cow::Owned(format!("{}… ({} bytes)", &escaped[..end], text.len()))
}

/// Set once the node has begun to tear down its ROS entities.
static SHUTTING_DOWN: AtomicBool = AtomicBool::new(false);

/// Says that the node is stopping: from now on rustdds's complaints about removing readers and
/// writers are taken as debug records (see [`effective_level`]).
pub fn shutting_down() {
    SHUTTING_DOWN.store(true, Ordering::SeqCst);
}

/// The level a record is written at. One exception to "as logged": rustdds 0.15 asks its event
/// loop to remove each dropped reader or writer through a queue of 4 and logs an ERROR
/// (`Cannot remove Reader ... TrySendError::Full`) when that queue stays full for 20 ms
/// (`remove_reader` in its `dds/pubsub.rs`). That happens when the node drops all its entities
/// at once on a loaded machine, and it does not matter then: the participant, with everything
/// in it, is dropped right after. During shutdown only, that message is taken as debug
/// (`--log-level rustdds:=debug` still shows it). The same for `leave_multicast_group: ...
/// AddrNotAvailable`: a listener that joined no multicast group (the discovery range
/// `LOCALHOST` or `OFF` leaves it none) still tries to leave one when it is dropped.
pub fn effective_level(
    level: log::Level,
    target: &str,
    text: &str,
    shutting_down: bool,
) -> log::Level {
    let removal = text.starts_with("Cannot remove Reader ")
        || text.starts_with("Cannot remove Writer ")
        || (text.starts_with("leave_multicast_group: ") && text.contains("AddrNotAvailable"));
    if shutting_down && level == log::Level::Error && target.starts_with("rustdds") && removal {
        log::Level::Debug
    } else {
        level
    }
}

/// A place in the code that logs (file and line), the unit of rate limiting.
pub type Site = (&'static str, u32);

#[derive(Debug, Clone)]
struct SiteWindow {
    start_ns: u64,
    shown: u32,
    suppressed: u64,
    level: log::Level,
    name: String,
    last: String,
}

/// What the rate limiter says about one record.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Admit {
    /// Write it, after the summary of the previous window's suppressed records if there is one.
    Show(Option<String>),
    /// Count it and write nothing.
    Suppress,
}

/// At most [`RATE_BURST`] records per site and [`RATE_WINDOW_NS`]; what is held back is counted
/// and summarised (`… 123 similar messages suppressed in 10 s; last: ...`) when the window
/// ends. Pure bookkeeping: the caller passes the time.
#[derive(Debug, Default)]
pub struct RateLimiter {
    sites: HashMap<Site, SiteWindow>,
}

/// Most sites the limiter keeps (sites are places in the code, so far fewer exist).
const MAX_SITES: usize = 4096;

impl RateLimiter {
    fn summary(w: &SiteWindow) -> String {
        format!(
            "… {} similar message{} suppressed in the last {} s; last: {}",
            w.suppressed,
            if w.suppressed == 1 { "" } else { "s" },
            RATE_WINDOW_NS / 1_000_000_000,
            w.last
        )
    }

    /// Decides about a record of `level` from `site`, logged as `name`, at `now_ns`.
    pub fn admit(
        &mut self,
        site: Site,
        level: log::Level,
        name: &str,
        text: &str,
        now_ns: u64,
    ) -> Admit {
        if !self.sites.contains_key(&site) && self.sites.len() >= MAX_SITES {
            self.sites.clear();
        }
        let fresh = || SiteWindow {
            start_ns: now_ns,
            shown: 1,
            suppressed: 0,
            level,
            name: name.to_string(),
            last: String::new(),
        };
        match self.sites.get_mut(&site) {
            None => {
                self.sites.insert(site, fresh());
                Admit::Show(None)
            }
            Some(w) if now_ns.saturating_sub(w.start_ns) >= RATE_WINDOW_NS => {
                let summary = (w.suppressed > 0).then(|| Self::summary(w));
                *w = fresh();
                Admit::Show(summary)
            }
            Some(w) if w.shown < RATE_BURST => {
                w.shown += 1;
                Admit::Show(None)
            }
            Some(w) => {
                w.suppressed += 1;
                w.level = w.level.min(level);
                // Only what the summary shows is kept.
                w.last = cut(text, 2 * MAX_ECHO_CHARS);
                Admit::Suppress
            }
        }
    }

    /// Summaries of the windows that ended before `now_ns` with records suppressed, as
    /// `(level, logger name, text)`; those windows are closed.
    pub fn flush(&mut self, now_ns: u64) -> Vec<(log::Level, String, String)> {
        let mut out = Vec::new();
        self.sites.retain(|_, w| {
            if now_ns.saturating_sub(w.start_ns) < RATE_WINDOW_NS {
                return true;
            }
            if w.suppressed > 0 {
                out.push((w.level, w.name.clone(), Self::summary(w)));
            }
            false
        });
        out
    }
}

/// Which records are written where.
#[derive(Debug, Clone, PartialEq)]
pub struct LogConfig {
    /// The node's level (this crate's records).
    pub node_level: LevelFilter,
    /// Level of other crates' records, unless a target rule names them.
    pub external_level: LevelFilter,
    /// Levels by target prefix; the longest matching prefix wins.
    pub targets: Vec<(String, LevelFilter)>,
    /// Write to stderr.
    pub stderr: bool,
    /// Forward the node's records to `/rosout`.
    pub rosout: bool,
    /// The logger name shown and sent to `/rosout` (the node's base name).
    pub name: String,
}

impl LogConfig {
    /// The configuration the ROS arguments ask for, for a node named `node_name` (after
    /// remapping) whose original name is `original_name`.
    pub fn from_args(ros: &RosArgs, original_name: &str, node_name: &str) -> LogConfig {
        let mut node_level = LevelFilter::Info;
        let mut targets = Vec::new();
        for l in &ros.log_levels {
            match l.logger.as_deref() {
                None => node_level = l.level.to_filter(),
                Some(n) if n == node_name || n == original_name => {
                    targets.push((OWN_TARGET.to_string(), l.level.to_filter()))
                }
                Some(n) => targets.push((n.replace('.', "::"), l.level.to_filter())),
            }
        }
        let external_level = if ros.external_lib_logs == Some(true) {
            node_level
        } else {
            LevelFilter::Error
        };
        LogConfig {
            node_level,
            external_level,
            targets,
            stderr: ros.stdout_logs != Some(false),
            rosout: ros.rosout_logs != Some(false),
            name: node_name.to_string(),
        }
    }

    /// The level for records of `target`.
    pub fn level_for(&self, target: &str) -> LevelFilter {
        // tracing's log bridge (turned on by a crate in the tree, e.g. with the `zenoh`
        // feature) writes a record when a span is entered or left, at the span's level, with
        // the span's name for a message: no event, never written.
        if target == "tracing::span" || target.starts_with("tracing::span::") {
            return LevelFilter::Off;
        }
        let matches = |prefix: &str| {
            target == prefix
                || target
                    .strip_prefix(prefix)
                    .is_some_and(|rest| rest.starts_with("::"))
        };
        self.targets
            .iter()
            .filter(|(p, _)| matches(p))
            // `max_by_key` keeps the last of equal keys: a later rule for a prefix wins.
            .max_by_key(|(p, _)| p.len())
            .map(|(_, l)| *l)
            .unwrap_or(if matches(OWN_TARGET) {
                self.node_level
            } else {
                self.external_level
            })
    }

    /// The most verbose level any record may have (for `log::set_max_level`).
    pub fn max_level(&self) -> LevelFilter {
        self.targets
            .iter()
            .map(|(_, l)| *l)
            .chain([self.node_level, self.external_level])
            .max()
            .unwrap_or(LevelFilter::Info)
    }
}

struct Logger {
    config: LogConfig,
    limiter: Mutex<RateLimiter>,
}

/// One of the node's own records as `/rosout` carries it (`rcl_interfaces/msg/Log`'s fields
/// but the stamp, which the sink takes when it sends).
pub struct RosoutRecord<'a> {
    /// The record's level (ROS's DEBUG for `log`'s debug and trace).
    pub level: log::Level,
    /// The logger's name (the node's base name).
    pub name: &'a str,
    /// The text, escaped as on stderr.
    pub text: &'a str,
    /// The source file, or empty.
    pub file: &'a str,
    /// The module, or empty.
    pub function: &'a str,
    /// The source line, or 0.
    pub line: u32,
}

/// Where the node's own records go on `/rosout`: a publisher on the middleware in use. It is
/// called on the thread that logs, so it must not wait.
pub type RosoutSink = Box<dyn Fn(RosoutRecord<'_>) + Send + Sync>;

/// `rcl_interfaces/msg/Log`'s level for `level`.
pub fn ros_level(level: log::Level) -> u8 {
    match level {
        log::Level::Error => 40,
        log::Level::Warn => 30,
        log::Level::Info => 20,
        log::Level::Debug | log::Level::Trace => 10,
    }
}

static ROSOUT: OnceLock<RosoutSink> = OnceLock::new();

thread_local! {
    // Publishing to /rosout may log (DDS internals); such records are never forwarded again.
    static IN_ROSOUT: Cell<bool> = const { Cell::new(false) };
}

/// ROS's level names.
fn level_name(l: log::Level) -> &'static str {
    match l {
        log::Level::Error => "ERROR",
        log::Level::Warn => "WARN",
        log::Level::Info => "INFO",
        log::Level::Debug | log::Level::Trace => "DEBUG",
    }
}

impl Logger {
    /// Writes one line to stderr and, for the node's own records, to `/rosout`.
    fn write(&self, level: log::Level, name: &str, own: bool, text: &str, record: &Record) {
        let text = for_log(text);
        if self.config.stderr {
            let now = crate::clock::wall_ns();
            let line = format!(
                "[{}] [{}.{:09}] [{}]: {}\n",
                level_name(level),
                now.div_euclid(1_000_000_000),
                now.rem_euclid(1_000_000_000),
                escape_controls(name),
                text
            );
            // One write per line so lines from several threads do not interleave.
            let _ = std::io::stderr().lock().write_all(line.as_bytes());
        }
        if own && self.config.rosout {
            if let Some(h) = ROSOUT.get() {
                if !IN_ROSOUT.with(Cell::get) {
                    IN_ROSOUT.with(|c| c.set(true));
                    h(RosoutRecord {
                        level,
                        name: &self.config.name,
                        text: &text,
                        file: record.file().unwrap_or(""),
                        function: record.module_path().unwrap_or(""),
                        line: record.line().unwrap_or(0),
                    });
                    IN_ROSOUT.with(|c| c.set(false));
                }
            }
        }
    }

    /// Writes the summaries of rate-limited records whose window has ended.
    fn flush_suppressed(&self) {
        let due = match self.limiter.lock() {
            Ok(mut l) => l.flush(crate::clock::monotonic_ns()),
            Err(_) => return,
        };
        for (level, name, text) in due {
            let own = name == self.config.name;
            let record = Record::builder()
                .level(level)
                .target(if own { OWN_TARGET } else { "" })
                .build();
            self.write(level, &name, own, &text, &record);
        }
    }
}

impl Log for Logger {
    fn enabled(&self, m: &Metadata) -> bool {
        m.level() <= self.config.level_for(m.target())
    }

    fn log(&self, record: &Record) {
        if !self.enabled(record.metadata()) {
            return;
        }
        let own = record.target() == OWN_TARGET || record.target().starts_with("pwm_actuator::");
        let name = if own {
            self.config.name.as_str()
        } else {
            record.target()
        };
        let text = record.args().to_string();
        let level = effective_level(
            record.level(),
            record.target(),
            &text,
            SHUTTING_DOWN.load(Ordering::Relaxed),
        );
        if level > self.config.level_for(record.target()) {
            return;
        }
        if rate_limited(level, record.target()) {
            let site = (
                record.file_static().unwrap_or("?"),
                record.line().unwrap_or(0),
            );
            let admit = self
                .limiter
                .lock()
                .map(|mut l| l.admit(site, level, name, &text, crate::clock::monotonic_ns()));
            match admit {
                Ok(Admit::Suppress) => return,
                Ok(Admit::Show(Some(summary))) => self.write(level, name, own, &summary, record),
                _ => {}
            }
        }
        self.write(level, name, own, &text, record);
    }

    fn flush(&self) {
        let _ = std::io::stderr().flush();
    }
}

/// The modules whose informational lines are caused by input from the ROS graph, one per
/// message (an enable, a parameter change, an e-stop input).
const INPUT_TARGETS: [&str; 2] = [
    "pwm_actuator::ros::inbound::inputs",
    "pwm_actuator::ros::inbound::estop",
];

/// Whether records of `level` from `target` go through the rate limiter: warnings and errors
/// from anywhere, and any record from the modules input drives (`INPUT_TARGETS`).
pub fn rate_limited(level: log::Level, target: &str) -> bool {
    level <= log::Level::Warn || INPUT_TARGETS.contains(&target)
}

/// Installs the logger for the process. Fails only if a logger is already installed.
pub fn init(config: LogConfig) -> Result<(), log::SetLoggerError> {
    let max = config.max_level();
    let logger: &'static Logger = Box::leak(Box::new(Logger {
        config,
        limiter: Mutex::new(RateLimiter::default()),
    }));
    log::set_logger(logger)?;
    let _ = LOGGER.set(logger);
    log::set_max_level(max);
    Ok(())
}

static LOGGER: OnceLock<&'static Logger> = OnceLock::new();

/// Writes the "… N similar messages suppressed" lines that are due, so a flood that has
/// stopped is still counted; called about once a second.
pub fn flush_suppressed() {
    if let Some(l) = LOGGER.get() {
        l.flush_suppressed();
    }
}

/// From now on, the node's records also go to `/rosout` through `handle`, its DDS writer
/// (once per process).
pub fn attach_rosout(handle: NodeLoggingHandle) {
    attach_rosout_sink(Box::new(move |r: RosoutRecord<'_>| {
        let level = match r.level {
            log::Level::Error => ros2_client::ros2::LogLevel::Error,
            log::Level::Warn => ros2_client::ros2::LogLevel::Warn,
            log::Level::Info => ros2_client::ros2::LogLevel::Info,
            log::Level::Debug | log::Level::Trace => ros2_client::ros2::LogLevel::Debug,
        };
        handle.rosout_raw(
            ros2_client::builtin_interfaces::Time::now(),
            level,
            r.name,
            r.text,
            r.file,
            r.function,
            r.line,
        );
    }));
}

/// From now on, the node's records also go to `/rosout` through `sink` (once per process).
pub fn attach_rosout_sink(sink: RosoutSink) {
    let _ = ROSOUT.set(sink);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::config::args::parse;

    fn config(a: &[&str]) -> LogConfig {
        let args: Vec<String> = a.iter().map(|s| s.to_string()).collect();
        LogConfig::from_args(&parse(&args).unwrap().ros, "pwm_actuator", "heater")
    }

    #[test]
    fn defaults() {
        let c = config(&[]);
        assert_eq!(c.level_for("pwm_actuator::ros::node"), LevelFilter::Info);
        assert_eq!(c.level_for("pwm_actuator"), LevelFilter::Info);
        assert_eq!(c.level_for("rustdds::rtps"), LevelFilter::Error);
        assert_eq!(c.level_for("pwm_actuatorx"), LevelFilter::Error);
        assert_eq!(c.level_for("tracing::span"), LevelFilter::Off);
        assert_eq!(c.level_for("tracing::span::active"), LevelFilter::Off);
        assert!(c.stderr && c.rosout);
        assert_eq!(c.name, "heater");
    }

    #[test]
    fn control_characters_are_written_as_escapes() {
        assert_eq!(
            escape_controls("plain \"text\" \\ ok"),
            "plain \"text\" \\ ok"
        );
        assert!(matches!(escape_controls("plain"), Cow::Borrowed(_)));
        assert_eq!(
            escape_controls("a\n[ERROR] b\r\t\u{1b}[2J\0\u{7f}\u{85}\u{202e}\u{200b}é"),
            "a\\n[ERROR] b\\r\\t\\u{1b}[2J\\u{0}\\u{7f}\\u{85}\\u{202e}\\u{200b}é"
        );
    }

    #[test]
    fn echoed_input_and_records_are_bounded() {
        assert_eq!(shown("pw01.period_ms"), "pw01.period_ms");
        let long = "é".repeat(1 << 20);
        assert_eq!(
            shown(&long),
            format!("{}… (2097152 bytes)", "é".repeat(MAX_ECHO_CHARS))
        );
        // Escapes count in the bound of a record, and a cut never splits a character.
        let rec = for_log(&"\u{1b}é".repeat(1 << 20)).into_owned();
        assert!(rec.len() <= MAX_RECORD_BYTES + 32, "{}", rec.len());
        assert!(
            rec.ends_with("… (3145728 bytes)"),
            "{}",
            &rec[rec.len() - 40..]
        );
        assert!(!rec.chars().any(char::is_control));
        assert_eq!(for_log("short"), "short");
    }

    #[test]
    fn input_driven_info_lines_are_limited_and_other_info_lines_are_not() {
        use log::Level::{Debug, Error, Info, Warn};
        assert!(rate_limited(Info, "pwm_actuator::ros::inbound::inputs"));
        assert!(rate_limited(Debug, "pwm_actuator::ros::inbound::estop"));
        assert!(rate_limited(Warn, "pwm_actuator::ros::node"));
        assert!(rate_limited(Error, "rustdds::rtps"));
        // Edge lines have a rate of their own (edge_log_rate); start-up lines are few.
        assert!(!rate_limited(Info, "pwm_actuator::ros::outbound::console"));
        assert!(!rate_limited(Info, "pwm_actuator::ros::node"));
    }

    #[test]
    fn repeated_warnings_are_limited_per_site_and_counted() {
        const S: u64 = 1_000_000_000;
        let mut l = RateLimiter::default();
        let (a, b) = (("src/x.rs", 10), ("src/x.rs", 20));
        let w = log::Level::Warn;
        let mut shown = 0;
        // A flood from one site: 1000 records in a second.
        for i in 0..1000u64 {
            match l.admit(a, w, "node", &format!("bad sample {i}"), S + i * 1_000_000) {
                Admit::Show(None) => shown += 1,
                Admit::Suppress => {}
                other => panic!("{i}: {other:?}"),
            }
        }
        assert_eq!(shown, RATE_BURST);
        // Another site is not held back by it.
        assert_eq!(l.admit(b, w, "node", "other", 2 * S), Admit::Show(None));
        // The window has not ended: nothing to summarise yet.
        assert!(l.flush(S + RATE_WINDOW_NS - 1).is_empty());
        // When it ends, the count comes out once, with the last text suppressed.
        let due = l.flush(S + RATE_WINDOW_NS);
        assert_eq!(
            due,
            vec![(
                w,
                "node".to_string(),
                "… 990 similar messages suppressed in the last 10 s; last: bad sample 999"
                    .to_string()
            )]
        );
        assert!(l.flush(S + 2 * RATE_WINDOW_NS).is_empty());
        // Without a flush, the next record after the window carries the summary.
        for i in 0..=RATE_BURST {
            let _ = l.admit(a, w, "node", "again", 30 * S + u64::from(i));
        }
        assert_eq!(
            l.admit(a, w, "node", "later", 30 * S + RATE_WINDOW_NS),
            Admit::Show(Some(
                "… 1 similar message suppressed in the last 10 s; last: again".to_string()
            ))
        );
    }

    #[test]
    fn rustdds_entity_removal_errors_are_debug_during_shutdown_only() {
        use log::Level::{Debug, Error, Warn};
        let full = "Cannot remove Reader GUID {0112b35f EntityId {[0, 0, 85] \
                    EntityKind::READER_NO_KEY_USER_DEFINED}} : TrySendError::Full(..)";
        let t = "rustdds::dds::pubsub";
        assert_eq!(effective_level(Error, t, full, true), Debug);
        assert_eq!(
            effective_level(Error, t, "Cannot remove Writer GUID {..} : Full", true),
            Debug
        );
        let leave = "leave_multicast_group: Os { code: 99, kind: AddrNotAvailable, message: \
                     \"Cannot assign requested address\" }";
        let l = "rustdds::network::udp_listener";
        assert_eq!(effective_level(Error, l, leave, true), Debug);
        assert_eq!(effective_level(Error, l, leave, false), Error);
        // While running it is an error like any other, and nothing else is touched.
        assert_eq!(effective_level(Error, t, full, false), Error);
        assert_eq!(effective_level(Error, t, "some other failure", true), Error);
        assert_eq!(
            effective_level(Error, "pwm_actuator::ros", full, true),
            Error
        );
        assert_eq!(effective_level(Warn, t, full, true), Warn);
    }

    #[test]
    fn levels_by_logger() {
        let c = config(&[
            "--ros-args",
            "--log-level",
            "warn",
            "--log-level",
            "rustdds:=info",
            "--log-level",
            "rustdds.rtps:=debug",
            "--log-level",
            "heater:=debug",
            "--disable-rosout-logs",
        ]);
        assert_eq!(c.level_for("pwm_actuator::x"), LevelFilter::Debug);
        assert_eq!(c.level_for("rustdds::dds"), LevelFilter::Info);
        assert_eq!(c.level_for("rustdds::rtps::writer"), LevelFilter::Debug);
        assert_eq!(c.level_for("ros2_client::node"), LevelFilter::Error);
        assert_eq!(c.max_level(), LevelFilter::Debug);
        assert!(!c.rosout);
        let c = config(&["--ros-args", "--log-level", "pwm_actuator:=error"]);
        assert_eq!(c.level_for("pwm_actuator::x"), LevelFilter::Error);
        let c = config(&[
            "--ros-args",
            "--log-level",
            "debug",
            "--enable-external-lib-logs",
        ]);
        assert_eq!(c.level_for("ros2_client"), LevelFilter::Debug);
    }
}
