//! The node's own options, given outside `--ros-args` (`--demo`, `--output sim`, `--trace
//! out.vcd`, ...). Each is a shorthand for a ROS parameter and sets that parameter's start-up
//! value; ROS arguments (`--params-file`, `-p`) given as well override it. So the precedence,
//! lowest first, is: built-in default, option, then `--params-file` and `-p` in the order they
//! appear.
//!
//! Parsed with clap ([`command`]); the `--ros-args` blocks are split off before, by hand
//! ([`crate::ros::config::args`]), because they follow rcl's rules. Parsing only: nothing here starts
//! anything.

use crate::output::gpio::parse_line_addr;
use crate::ros::config::params::{channel_index, StartValue};
use clap::error::{ContextKind, ContextValue, ErrorKind};
use clap::{ArgAction, Args, FromArgMatches};
use ros2_client::ParameterValue;

/// Exit code for a bad command line or configuration.
pub const EXIT_USAGE: i32 = 2;

/// Exit code for a failure while running (output fault, ROS failure).
pub const EXIT_FAILURE: i32 = 1;

/// The usage line of the node (a program with subcommands adds its own).
pub const NODE_USAGE: &str = "pwm_actuator_node [OPTIONS] [--ros-args ROS_ARGUMENTS... [--]]";

/// The part of `--help` that is not generated from the options: the ROS arguments, which
/// follow rcl's rules and are split off by hand ([`crate::ros::config::args`]), the environment and the
/// topics.
pub const ROS_HELP: &str = "\
Each option sets the start-up value of the ROS parameter in brackets; --params-file and -p
override it.

ROS arguments (standard, as for any ROS 2 node):
  --ros-args -r __node:=NAME -r __ns:=/NS -r FROM:=TO -p NAME:=VALUE --params-file FILE.yaml
             --log-level [LOGGER:=]LEVEL --disable-rosout-logs ... [--]

Environment: ROS_DOMAIN_ID (0..232, default 0).

Topics, relative to the node (<ch> = pw01, pw02, ...): in ~/<ch>/duty (std_msgs/Float64, %),
~/<ch>/sv (std_msgs/UInt16, 0..4095), ~/<ch>/enable (std_msgs/Bool), ~/<ch>/params
(pwm_actuator_msgs/ChannelParams); out ~/<ch>/edges, ~/<ch>/e1, ~/<ch>/status, /diagnostics.";

/// A malformed option.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CliError {
    /// An option this node does not have.
    #[error("unknown option `{0}` (see --help; ROS arguments go after --ros-args)")]
    Unknown(String),
    /// An option without its value.
    #[error("`{0}` needs a value")]
    MissingValue(String),
    /// A value that does not parse.
    #[error("`{option}`: {reason}")]
    BadValue {
        /// The option.
        option: String,
        /// What is wrong.
        reason: String,
    },
}

/// The node's own options. Each sets the start-up value of the ROS parameter in brackets;
/// `--params-file` and `-p` override it.
#[derive(Debug, Clone, Default, PartialEq, Args)]
pub struct Flags {
    /// Print this help
    #[arg(short = 'h', long = "help", action = ArgAction::SetTrue)]
    pub help: bool,
    /// Print the version
    #[arg(short = 'V', long = "version", action = ArgAction::SetTrue)]
    pub version: bool,
    /// Enable pw01 at 37 % and pw02 at 5 % and show their edges on the console; sets the
    /// start-up value of `pwNN.enable`, `pwNN.duty`, `edge_log_rate`.
    #[arg(help = "Enable pw01 at 37 % and pw02 at 5 %, edges on the console \
                  [pwNN.enable, pwNN.duty, edge_log_rate]")]
    #[arg(long)]
    pub demo: bool,
    /// Run as a managed (lifecycle) node: lines requested on configure and live only while
    /// active; sets the start-up value of `managed`.
    #[arg(help = "Run as a managed (lifecycle) node: lines live only while ACTIVE [managed]")]
    #[arg(long)]
    pub managed: bool,
    /// Output backend (default sim); sets the start-up value of `output`.
    #[arg(help = "Output backend (default sim) [output]")]
    #[arg(long, value_name = "sim|gpio", value_parser = parse_output, allow_hyphen_values = true)]
    pub output: Option<String>,
    /// Trace of every edge written (sim or gpio output), FILE.vcd or FILE.csv, or of every
    /// edge, status and diagnostics message as ROS 2 messages, FILE.mcap; repeatable; sets the
    /// start-up value of `trace`.
    #[arg(
        help = "Trace: FILE.vcd or FILE.csv (every edge written), FILE.mcap (edges, status and \
                /diagnostics as ROS 2 messages); repeatable [trace]"
    )]
    #[arg(long, value_name = "FILE", action = ArgAction::Append, allow_hyphen_values = true)]
    pub trace: Vec<String>,
    /// What the files of each trace may hold together, MB; sets the start-up value of
    /// `trace_max_mb`.
    #[arg(
        help = "What the files of each trace may hold together, MB (default 256) [trace_max_mb]"
    )]
    #[arg(
        long = "trace-max-mb",
        value_name = "MB",
        value_parser = parse_integer,
        allow_hyphen_values = true
    )]
    pub trace_max_mb: Option<i64>,
    /// GPIO line of a channel, e.g. pw01=17 or pw02=/dev/gpiochip1:4; repeatable; sets the start-up
    /// value of `CH.gpio_chip`, `CH.gpio_line`.
    #[arg(
        help = "GPIO line of a channel, e.g. pw01=17 or pw02=/dev/gpiochip1:4; repeatable [CH.gpio_chip, CH.gpio_line]"
    )]
    #[arg(
        long = "line",
        value_name = "CH=[CHIP:]OFFSET",
        value_parser = parse_line,
        action = ArgAction::Append,
        allow_hyphen_values = true
    )]
    pub lines: Vec<(String, Option<String>, i64)>,
    /// Number of channels pw01..pwNN (default 2); sets the start-up value of `channels`.
    #[arg(help = "Number of channels pw01..pwNN (default 2) [channels]")]
    #[arg(long, value_name = "N", value_parser = parse_integer, allow_hyphen_values = true)]
    pub channels: Option<i64>,
    /// Periodic `~/<ch>/status` rate in Hz, 0 = on change only (default 10); sets the start-up
    /// value of `status_rate_hz`.
    #[arg(
        help = "Periodic ~/<ch>/status rate in Hz, 0 = on change only (default 1) [status_rate_hz]"
    )]
    #[arg(
        long = "status-rate",
        value_name = "HZ",
        value_parser = parse_number,
        allow_hyphen_values = true
    )]
    pub status_rate_hz: Option<f64>,
    /// SCHED_FIFO priority of the output thread, 0 = off; sets the start-up value of `rt_priority`.
    #[arg(help = "SCHED_FIFO priority of the output thread, 0 = off [rt_priority]")]
    #[arg(
        long = "rt-priority",
        value_name = "N",
        value_parser = parse_integer,
        allow_hyphen_values = true
    )]
    pub rt_priority: Option<i64>,
}

/// The origin given to values set by `--demo` (they are not worth a warning when a channel
/// does not exist).
pub const DEMO_ORIGIN: &str = "--demo";

/// The node's command line as clap sees it: the options of [`Flags`] (ROS arguments are split
/// off before), its `--help` text, and last-one-wins for repeated single-valued options.
pub fn command() -> clap::Command {
    Flags::augment_args(clap::Command::new("pwm_actuator_node"))
        .about(
            "pwm_actuator_node: time-proportioned pulses (software PWM) for heaters, valves and \
             relays, as a ROS 2 node.",
        )
        .override_usage(NODE_USAGE)
        .after_help(ROS_HELP)
        .disable_help_flag(true)
        .disable_version_flag(true)
        .args_override_self(true)
}

/// The `--help` text of the node.
pub fn help() -> String {
    command().render_help().to_string()
}

/// Parses the node's own options (the command line without the program name and without the
/// `--ros-args` blocks).
pub fn parse_flags(args: &[String]) -> Result<Flags, CliError> {
    let matches = command()
        .no_binary_name(true)
        .try_get_matches_from(args)
        .map_err(|e| CliError::from_clap(&e))?;
    Flags::from_arg_matches(&matches).map_err(|e| CliError::from_clap(&e))
}

impl CliError {
    /// The error clap reported, in this node's words.
    pub fn from_clap(e: &clap::Error) -> CliError {
        let context = |kind| match e.get(kind) {
            Some(ContextValue::String(s)) => s.clone(),
            _ => String::new(),
        };
        // clap names an option with its value placeholder: `--trace <FILE>`.
        let arg = context(ContextKind::InvalidArg);
        let option = arg
            .split_whitespace()
            .next()
            .unwrap_or_default()
            .to_string();
        let value = context(ContextKind::InvalidValue);
        match e.kind() {
            ErrorKind::UnknownArgument => CliError::Unknown(arg),
            ErrorKind::InvalidValue if value.is_empty() => CliError::MissingValue(option),
            _ => CliError::BadValue {
                option,
                reason: match std::error::Error::source(e) {
                    Some(why) => why.to_string(),
                    None => e.kind().as_str().unwrap_or("invalid").to_string(),
                },
            },
        }
    }
}

/// Why an option's value does not parse; each holds the text as given.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ValueError {
    /// Not an output backend's name.
    #[error("`{0}` is not one of: sim|gpio")]
    NotAnOutput(String),
    /// Not an integer.
    #[error("`{0}` is not an integer")]
    NotAnInteger(String),
    /// Not a number.
    #[error("`{0}` is not a number")]
    NotANumber(String),
    /// A `--line` value without `=`.
    #[error("`{0}`: expected CH=[CHIP:]OFFSET, e.g. pw01=17")]
    NotALineAssignment(String),
    /// A `--line` value whose channel is not a channel name.
    #[error("`{0}` is not a channel name (pw01, pw02, ...)")]
    NotAChannel(String),
    /// A `--line` value whose line is not `[CHIP:]OFFSET`.
    #[error("`{0}` is not a line: expected [CHIP:]OFFSET, e.g. 17")]
    NotALine(String),
}

fn parse_output(v: &str) -> Result<String, ValueError> {
    match v {
        "sim" | "gpio" => Ok(v.to_string()),
        _ => Err(ValueError::NotAnOutput(v.to_string())),
    }
}

fn parse_integer(v: &str) -> Result<i64, ValueError> {
    v.parse()
        .map_err(|_| ValueError::NotAnInteger(v.to_string()))
}

fn parse_number(v: &str) -> Result<f64, ValueError> {
    v.parse().map_err(|_| ValueError::NotANumber(v.to_string()))
}

/// Parses `CH=[CHIP:]OFFSET`.
fn parse_line(v: &str) -> Result<(String, Option<String>, i64), ValueError> {
    let (ch, rest) = v
        .split_once('=')
        .ok_or_else(|| ValueError::NotALineAssignment(v.to_string()))?;
    if channel_index(ch).is_none() {
        return Err(ValueError::NotAChannel(ch.to_string()));
    }
    let (chip, offset) =
        parse_line_addr(rest).ok_or_else(|| ValueError::NotALine(rest.to_string()))?;
    Ok((ch.to_string(), chip.map(str::to_string), i64::from(offset)))
}

impl Flags {
    /// The start-up parameter values these options stand for, in a fixed order.
    pub fn start_values(&self) -> Vec<StartValue> {
        let mut v = Vec::new();
        let mut push = |name: String, value: ParameterValue, origin: &str| {
            v.push(StartValue {
                name,
                value,
                origin: origin.to_string(),
            })
        };
        if let Some(c) = self.channels {
            push("channels".into(), ParameterValue::Integer(c), "--channels");
        }
        if let Some(o) = &self.output {
            push(
                "output".into(),
                ParameterValue::String(o.clone()),
                "--output",
            );
        }
        if !self.trace.is_empty() {
            push(
                "trace".into(),
                ParameterValue::String(self.trace.join(",")),
                "--trace",
            );
        }
        if let Some(mb) = self.trace_max_mb {
            push(
                "trace_max_mb".into(),
                ParameterValue::Integer(mb),
                "--trace-max-mb",
            );
        }
        for (ch, chip, offset) in &self.lines {
            if let Some(chip) = chip {
                push(
                    format!("{ch}.gpio_chip"),
                    ParameterValue::String(chip.clone()),
                    "--line",
                );
            }
            push(
                format!("{ch}.gpio_line"),
                ParameterValue::Integer(*offset),
                "--line",
            );
        }
        if let Some(r) = self.status_rate_hz {
            push(
                "status_rate_hz".into(),
                ParameterValue::Double(r),
                "--status-rate",
            );
        }
        if let Some(p) = self.rt_priority {
            push(
                "rt_priority".into(),
                ParameterValue::Integer(p),
                "--rt-priority",
            );
        }
        if self.managed {
            push("managed".into(), ParameterValue::Boolean(true), "--managed");
        }
        if self.demo {
            // The demo shows its edges on the console; an always-on node logs none by default.
            push(
                "edge_log_rate".into(),
                ParameterValue::Integer(10),
                DEMO_ORIGIN,
            );
            for (ch, duty) in [("pw01", 37.0), ("pw02", 5.0)] {
                push(
                    format!("{ch}.duty"),
                    ParameterValue::Double(duty),
                    DEMO_ORIGIN,
                );
                push(
                    format!("{ch}.enable"),
                    ParameterValue::Boolean(true),
                    DEMO_ORIGIN,
                );
            }
        }
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flags(a: &[&str]) -> Result<Flags, CliError> {
        parse_flags(&a.iter().map(|s| s.to_string()).collect::<Vec<_>>())
    }

    #[test]
    fn options() {
        let f = flags(&[
            "--demo",
            "--output",
            "sim",
            "--trace",
            "a.vcd",
            "--trace=b.csv",
            "--trace-max-mb",
            "64",
            "--line",
            "pw01=17",
            "--line=pw02=/dev/gpiochip1:4",
            "--channels",
            "3",
            "--status-rate",
            "2.5",
            "--rt-priority",
            "50",
        ])
        .unwrap();
        assert!(f.demo);
        assert_eq!(f.trace, vec!["a.vcd", "b.csv"]);
        assert_eq!(f.trace_max_mb, Some(64));
        assert_eq!(
            f.lines,
            vec![
                ("pw01".into(), None, 17),
                ("pw02".into(), Some("/dev/gpiochip1".into()), 4)
            ]
        );
        let v = f.start_values();
        let names: Vec<&str> = v.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "channels",
                "output",
                "trace",
                "trace_max_mb",
                "pw01.gpio_line",
                "pw02.gpio_chip",
                "pw02.gpio_line",
                "status_rate_hz",
                "rt_priority",
                "edge_log_rate",
                "pw01.duty",
                "pw01.enable",
                "pw02.duty",
                "pw02.enable"
            ]
        );
        assert_eq!(v[2].value, ParameterValue::String("a.vcd,b.csv".into()));
        assert_eq!(v[3].value, ParameterValue::Integer(64));
        assert_eq!(v[9].value, ParameterValue::Integer(10));
        assert_eq!(v[10].value, ParameterValue::Double(37.0));
    }

    #[test]
    fn errors() {
        assert_eq!(flags(&["--fast"]), Err(CliError::Unknown("--fast".into())));
        assert_eq!(
            flags(&["--trace"]),
            Err(CliError::MissingValue("--trace".into()))
        );
        for (a, why) in [
            (&["--output", "spi"][..], "sim|gpio"),
            (&["--channels", "two"][..], "not an integer"),
            (&["--line", "pw01"][..], "expected CH="),
            (&["--line", "q1=3"][..], "not a channel"),
            (
                &["--line", "pw01=-3"][..],
                "not a line: expected [CHIP:]OFFSET",
            ),
            (&["--status-rate", "fast"][..], "not a number"),
        ] {
            let e = flags(a).unwrap_err();
            assert!(e.to_string().contains(why), "{a:?}: {e}");
        }
        assert!(flags(&["-h"]).unwrap().help);
    }

    #[test]
    fn repeated_options_keep_the_last_and_values_may_start_with_a_dash() {
        let f = flags(&[
            "--channels",
            "2",
            "--channels",
            "4",
            "--demo",
            "--demo",
            "--rt-priority",
            "-1",
        ])
        .unwrap();
        assert_eq!(
            (f.channels, f.demo, f.rt_priority),
            (Some(4), true, Some(-1))
        );
        // A value is whatever follows the option, as before.
        assert_eq!(flags(&["--trace", "--demo"]).unwrap().trace, vec!["--demo"]);
        assert!(flags(&["-V"]).unwrap().version);
        assert_eq!(
            flags(&["--demo", "extra"]),
            Err(CliError::Unknown("extra".into()))
        );
    }

    #[test]
    fn help_is_generated_from_the_options_and_keeps_the_ros_part() {
        let h = help();
        for s in [
            "--demo",
            "--output <sim|gpio>",
            "--line <CH=[CHIP:]OFFSET>",
            "[status_rate_hz]",
            "--ros-args",
            "ROS_DOMAIN_ID",
            "~/<ch>/duty",
        ] {
            assert!(h.contains(s), "{s} missing from:\n{h}");
        }
    }
}
