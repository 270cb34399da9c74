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
//! Must not block for long or allocate without bound: it runs on every thread that logs, never
//! on the output thread's hot path (the engine does not log there).

use super::args::RosArgs;
use log::{LevelFilter, Log, Metadata, Record};
use ros2_client::rosout::RosoutRaw;
use ros2_client::NodeLoggingHandle;
use std::cell::Cell;
use std::io::Write;
use std::sync::OnceLock;

/// The log target prefix of this crate.
const OWN_TARGET: &str = "pwm_actuator";

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
}

static ROSOUT: OnceLock<NodeLoggingHandle> = OnceLock::new();

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
        if self.config.stderr {
            let now = crate::clock::wall_ns();
            let line = format!(
                "[{}] [{}.{:09}] [{}]: {}\n",
                level_name(record.level()),
                now.div_euclid(1_000_000_000),
                now.rem_euclid(1_000_000_000),
                name,
                text
            );
            // One write per line so lines from several threads do not interleave.
            let _ = std::io::stderr().lock().write_all(line.as_bytes());
        }
        if own && self.config.rosout {
            if let Some(h) = ROSOUT.get() {
                if !IN_ROSOUT.with(Cell::get) {
                    IN_ROSOUT.with(|c| c.set(true));
                    let level = match record.level() {
                        log::Level::Error => ros2_client::ros2::LogLevel::Error,
                        log::Level::Warn => ros2_client::ros2::LogLevel::Warn,
                        log::Level::Info => ros2_client::ros2::LogLevel::Info,
                        log::Level::Debug | log::Level::Trace => ros2_client::ros2::LogLevel::Debug,
                    };
                    h.rosout_raw(
                        ros2_client::builtin_interfaces::Time::now(),
                        level,
                        &self.config.name,
                        &text,
                        record.file().unwrap_or(""),
                        record.module_path().unwrap_or(""),
                        record.line().unwrap_or(0),
                    );
                    IN_ROSOUT.with(|c| c.set(false));
                }
            }
        }
    }

    fn flush(&self) {
        let _ = std::io::stderr().flush();
    }
}

/// Installs the logger for the process. Fails only if a logger is already installed.
pub fn init(config: LogConfig) -> Result<(), log::SetLoggerError> {
    let max = config.max_level();
    log::set_boxed_logger(Box::new(Logger { config }))?;
    log::set_max_level(max);
    Ok(())
}

/// From now on, the node's records also go to `/rosout` through `handle` (once per process).
pub fn attach_rosout(handle: NodeLoggingHandle) {
    let _ = ROSOUT.set(handle);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::args::parse;

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
        assert!(c.stderr && c.rosout);
        assert_eq!(c.name, "heater");
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
