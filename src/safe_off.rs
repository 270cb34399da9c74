//! `pwm_actuator_node safe-off`: drives the node's GPIO lines inactive from a separate process,
//! for the ends of the node that it cannot handle itself (SIGKILL, the OOM killer, a hang ended
//! by a watchdog kill, a crash in foreign code). The service manager runs it after the node
//! (systemd `ExecStopPost=`).
//!
//! The lines are taken from the node's own configuration, read the node's way: `--line`,
//! `--channels` and `--ros-args` (`--params-file`, `-p`), so a unit file can pass safe-off the
//! very arguments the node got. Each line is requested as an output, inactive, with its
//! polarity (`active_low`), written inactive once more, and released. A line still held by
//! another process (the node, or anything else) is refused, naming the holder: two writers on
//! one line is never safe. This module must not drive anything active.

use crate::output::gpio::{plan_requests, request_plan, to_value, GpioError, GpioLine};
use crate::output::{Backend, Level};
use crate::ros::config::args;
use crate::ros::config::cli;
use crate::ros::config::names::NodeIdentity;
use crate::ros::config::params::{self, StartValue, StartupConfig};
use crate::ros::config::start::{start_values, StartupError};
use gpiocdev::line::Values;
use std::path::PathBuf;

/// The node name whose `--params-file` sections apply (the node's default name).
pub use crate::ros::config::names::NODE_NAME;

/// Exit status: every line driven inactive.
pub const EXIT_OK: i32 = 0;
/// Exit status: a line is held by another process (refused) or could not be written.
pub const EXIT_REFUSED: i32 = 1;
/// Exit status: the arguments or the configuration are wrong (nothing was touched), as for the
/// node.
pub use crate::ros::config::cli::EXIT_USAGE;

/// Why safe-off did not drive every line inactive.
#[derive(Debug, thiserror::Error)]
pub enum SafeOffError {
    /// The node's command line or configuration is refused, as the node would refuse it.
    #[error(transparent)]
    Config(#[from] StartupError),
    /// A line cannot be requested (busy: names the holder) or written.
    #[error(transparent)]
    Gpio(#[from] GpioError),
    /// The kernel reports a line still active after it was written inactive.
    #[error("{} line {offset} ({name}) reads back active after being written inactive", chip.display())]
    StillActive {
        /// The chip.
        chip: PathBuf,
        /// The line offset.
        offset: u32,
        /// The channel.
        name: String,
    },
}

impl SafeOffError {
    /// The process exit status for this error.
    pub fn exit_code(&self) -> i32 {
        match self {
            SafeOffError::Gpio(GpioError::LineBusy { .. } | GpioError::Write { .. })
            | SafeOffError::StillActive { .. } => EXIT_REFUSED,
            SafeOffError::Config(_) => EXIT_USAGE,
            SafeOffError::Gpio(_) => EXIT_USAGE,
        }
    }
}

/// The GPIO lines the node would drive with the command line `args` (node syntax, without the
/// program name); `--output gpio` is implied.
pub fn lines_from_node_args(args: &[String]) -> Result<Vec<GpioLine>, SafeOffError> {
    let parsed = args::parse(args).map_err(StartupError::from)?;
    let flags = cli::parse_flags(&parsed.app).map_err(StartupError::from)?;
    let id = NodeIdentity::from_remaps(NODE_NAME, "/", &parsed.ros.remaps)
        .map_err(StartupError::from)?;
    let mut values = start_values(&flags, &parsed.ros, &id, &id.fully_qualified())?;
    values.push(StartValue {
        name: "output".into(),
        value: ros2_client::ParameterValue::String("gpio".into()),
        origin: "safe-off".into(),
    });
    let su = params::start_up(&values).map_err(StartupError::from)?;
    let cfg = StartupConfig::from_store(&su.store).map_err(StartupError::from)?;
    let Backend::Gpio { lines } = cfg.output.backend else {
        unreachable!("output gpio was set last");
    };
    Ok(lines)
}

/// Requests every line (all chips first, so that nothing is written unless every line is
/// free), writes every line inactive, reads each back from the kernel, and releases them.
/// Returns the lines driven.
///
/// Errors: a missing chip, a line held by another process ([`GpioError::LineBusy`], naming
/// the holder), a failed write, a line that reads back active.
pub fn drive_inactive(lines: &[GpioLine]) -> Result<Vec<GpioLine>, SafeOffError> {
    let plans = plan_requests(lines)?;
    let mut requests = Vec::with_capacity(plans.len());
    for plan in &plans {
        // Requested as outputs, inactive: the kernel drives them inactive here already.
        requests.push(request_plan(plan)?);
    }
    for (plan, request) in plans.iter().zip(&requests) {
        let mut values = Values::from_offsets(&plan.offsets());
        for offset in plan.offsets() {
            values.set(offset, to_value(Level::Low));
        }
        request
            .set_values(&values)
            .map_err(|source| GpioError::Write {
                chip: plan.chip.clone(),
                offsets: plan.offsets(),
                line: plan.lines[0].index,
                source,
            })?;
        // Read back what the kernel drives now (the driver's value for an output line).
        for line in &plan.lines {
            let v = request
                .value(line.offset)
                .map_err(|source| GpioError::Write {
                    chip: plan.chip.clone(),
                    offsets: vec![line.offset],
                    line: line.index,
                    source,
                })?;
            if v != to_value(Level::Low) {
                return Err(SafeOffError::StillActive {
                    chip: plan.chip.clone(),
                    offset: line.offset,
                    name: line.name.clone(),
                });
            }
        }
    }
    drop(requests);
    Ok(lines.to_vec())
}

/// Runs safe-off for the node command line `args`; prints what it did (stdout) or why not
/// (stderr) and returns the exit status ([`EXIT_OK`], [`EXIT_REFUSED`], [`EXIT_USAGE`]).
pub fn run(args: &[String]) -> i32 {
    let result = lines_from_node_args(args).and_then(|lines| drive_inactive(&lines));
    match result {
        Ok(lines) => {
            for l in &lines {
                println!(
                    "safe-off: {} line {} ({}) inactive (read back){}",
                    l.chip.display(),
                    l.offset,
                    l.name,
                    if l.active_low {
                        " (active-low: electrically high)"
                    } else {
                        ""
                    }
                );
            }
            EXIT_OK
        }
        Err(e) => {
            eprintln!("safe-off: {}", crate::error::chain(&e));
            e.exit_code()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(a: &[&str]) -> Vec<String> {
        a.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn lines_come_from_the_node_options_and_ros_args() {
        let lines = lines_from_node_args(&args(&[
            "--line",
            "pw01=/dev/gpiochip3:4",
            "--line",
            "pw02=7",
            "--ros-args",
            "-p",
            "pw02.active_low:=true",
        ]))
        .unwrap();
        assert_eq!(
            lines,
            [
                GpioLine {
                    name: "pw01".into(),
                    chip: "/dev/gpiochip3".into(),
                    offset: 4,
                    active_low: false,
                },
                GpioLine {
                    name: "pw02".into(),
                    chip: "/dev/gpiochip0".into(),
                    offset: 7,
                    active_low: true,
                },
            ]
        );
    }

    #[test]
    fn lines_come_from_a_params_file() {
        let dir = std::env::temp_dir().join(format!("pwm_safe_off_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("p.yaml");
        std::fs::write(
            &file,
            "/**:\n  ros__parameters:\n    channels: 1\n    pw01.gpio_chip: /dev/gpiochip2\n    \
             pw01.gpio_line: 5\n    pw01.active_low: true\n",
        )
        .unwrap();
        let lines = lines_from_node_args(&args(&[
            "--ros-args",
            "--params-file",
            file.to_str().unwrap(),
        ]))
        .unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        assert_eq!(lines.len(), 1);
        assert_eq!(lines[0].chip, PathBuf::from("/dev/gpiochip2"));
        assert_eq!((lines[0].offset, lines[0].active_low), (5, true));
    }

    #[test]
    fn configuration_errors_touch_nothing_and_exit_2() {
        // A channel without a line, a bad option.
        for a in [
            &["--channels", "2", "--line", "pw01=3"][..],
            &["--frobnicate"][..],
        ] {
            let e = lines_from_node_args(&args(a)).unwrap_err();
            assert_eq!(e.exit_code(), EXIT_USAGE, "{a:?}: {e}");
        }
        // A line bound twice: refused by the one binding check before any chip is opened.
        let lines =
            lines_from_node_args(&args(&["--line", "pw01=3", "--line", "pw02=gpiochip0:3"]))
                .unwrap();
        let e = drive_inactive(&lines).unwrap_err();
        assert_eq!(e.exit_code(), EXIT_USAGE);
        assert!(e.to_string().contains("both bound to"), "{e}");
        let e = drive_inactive(&[GpioLine {
            name: "pw01".into(),
            chip: "/dev/gpiochip-safe-off-none".into(),
            offset: 1,
            active_low: false,
        }])
        .unwrap_err();
        assert_eq!(e.exit_code(), EXIT_USAGE);
        assert!(e.to_string().contains("gpiochip-safe-off-none"), "{e}");
    }
}
