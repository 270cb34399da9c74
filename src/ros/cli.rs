//! The node's own options, given outside `--ros-args` (`--demo`, `--output sim`, `--trace
//! out.vcd`, ...). Each is a shorthand for a ROS parameter and sets that parameter's start-up
//! value; ROS arguments (`--params-file`, `-p`) given as well override it. So the precedence,
//! lowest first, is: built-in default, option, then `--params-file` and `-p` in the order they
//! appear.
//!
//! Parsing only: nothing here starts anything.

use super::params::{channel_of, StartValue};
use ros2_client::ParameterValue;

/// The command-line synopsis printed by `--help`.
pub const USAGE: &str = "\
pwm_actuator_node: time-proportioned pulses (software PWM) for heaters, valves and relays, as a
ROS 2 node.

Usage:
  pwm_actuator_node [OPTIONS] [--ros-args ROS_ARGUMENTS... [--]]
  pwm_actuator_node bench [BENCH_OPTIONS]

Options (each sets the start-up value of the ROS parameter in brackets; --params-file and -p
override it):
  --demo                    enable pw01 at 37 % and pw02 at 5 % [pwNN.enable, pwNN.duty]
  --output sim|gpio         output backend (default sim) [output]
  --trace FILE              trace of the sim output, FILE.vcd or FILE.csv; repeatable [trace]
  --line CH=[CHIP:]OFFSET   GPIO line of a channel, e.g. pw01=17 or pw02=/dev/gpiochip1:4
                            [CH.gpio_chip, CH.gpio_line]
  --channels N              number of channels pw01..pwNN (default 2) [channels]
  --status-rate HZ          periodic ~/<ch>/status rate, 0 = on change only (default 10)
                            [status_rate_hz]
  --rt-priority N           SCHED_FIFO priority of the output thread, 0 = off [rt_priority]
  -h, --help                print this text
  -V, --version             print the version

ROS arguments (standard, as for any ROS 2 node):
  --ros-args -r __node:=NAME -r __ns:=/NS -r FROM:=TO -p NAME:=VALUE --params-file FILE.yaml
             --log-level [LOGGER:=]LEVEL --disable-rosout-logs ... [--]

Environment: ROS_DOMAIN_ID (0..232, default 0).

Topics, relative to the node (<ch> = pw01, pw02, ...): in ~/<ch>/duty (std_msgs/Float64, %),
~/<ch>/sv (std_msgs/UInt16, 0..4095), ~/<ch>/enable (std_msgs/Bool), ~/<ch>/params
(pwm_actuator_msgs/ChannelParams); out ~/<ch>/edges, ~/<ch>/e1, ~/<ch>/status, /diagnostics.
";

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

/// The options given.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Flags {
    /// `--help`.
    pub help: bool,
    /// `--version`.
    pub version: bool,
    /// `--demo`.
    pub demo: bool,
    /// `--output`.
    pub output: Option<String>,
    /// `--trace`, in order.
    pub trace: Vec<String>,
    /// `--line CH=[CHIP:]OFFSET`: (channel, chip, offset).
    pub lines: Vec<(String, Option<String>, i64)>,
    /// `--channels`.
    pub channels: Option<i64>,
    /// `--status-rate`.
    pub status_rate_hz: Option<f64>,
    /// `--rt-priority`.
    pub rt_priority: Option<i64>,
}

/// The origin given to values set by `--demo` (they are not worth a warning when a channel
/// does not exist).
pub const DEMO_ORIGIN: &str = "--demo";

/// Parses the node's own options.
pub fn parse_flags(args: &[String]) -> Result<Flags, CliError> {
    let mut f = Flags::default();
    let mut it = args.iter();
    while let Some(arg) = it.next() {
        let (opt, inline) = match arg.split_once('=') {
            Some((o, v)) if o.starts_with("--") => (o, Some(v.to_string())),
            _ => (arg.as_str(), None),
        };
        let mut value = || -> Result<String, CliError> {
            match &inline {
                Some(v) => Ok(v.clone()),
                None => it
                    .next()
                    .cloned()
                    .ok_or_else(|| CliError::MissingValue(opt.to_string())),
            }
        };
        let bad = |reason: String| CliError::BadValue {
            option: opt.to_string(),
            reason,
        };
        match opt {
            "-h" | "--help" => f.help = true,
            "-V" | "--version" => f.version = true,
            "--demo" => f.demo = true,
            "--output" => {
                let v = value()?;
                if v != "sim" && v != "gpio" {
                    return Err(bad(format!("`{v}` is not one of: sim|gpio")));
                }
                f.output = Some(v);
            }
            "--trace" => f.trace.push(value()?),
            "--line" => {
                let v = value()?;
                f.lines.push(parse_line(&v).map_err(bad)?);
            }
            "--channels" => {
                let v = value()?;
                f.channels = Some(
                    v.parse()
                        .map_err(|_| bad(format!("`{v}` is not an integer")))?,
                );
            }
            "--status-rate" => {
                let v = value()?;
                f.status_rate_hz = Some(
                    v.parse()
                        .map_err(|_| bad(format!("`{v}` is not a number")))?,
                );
            }
            "--rt-priority" => {
                let v = value()?;
                f.rt_priority = Some(
                    v.parse()
                        .map_err(|_| bad(format!("`{v}` is not an integer")))?,
                );
            }
            _ => return Err(CliError::Unknown(arg.clone())),
        }
    }
    Ok(f)
}

/// Parses `CH=[CHIP:]OFFSET`.
fn parse_line(v: &str) -> Result<(String, Option<String>, i64), String> {
    let (ch, rest) = v
        .split_once('=')
        .ok_or_else(|| format!("`{v}`: expected CH=[CHIP:]OFFSET, e.g. pw01=17"))?;
    if channel_of(&format!("{ch}.x")).is_none() {
        return Err(format!("`{ch}` is not a channel name (pw01, pw02, ...)"));
    }
    let (chip, offset) = match rest.rsplit_once(':') {
        Some((chip, off)) if !chip.is_empty() => (Some(chip.to_string()), off),
        _ => (None, rest),
    };
    let offset: i64 = offset
        .parse()
        .ok()
        .filter(|o| (0..=u32::MAX as i64).contains(o))
        .ok_or_else(|| format!("`{offset}` is not a line offset"))?;
    Ok((ch.to_string(), chip, offset))
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
        if self.demo {
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
                "pw01.gpio_line",
                "pw02.gpio_chip",
                "pw02.gpio_line",
                "status_rate_hz",
                "rt_priority",
                "pw01.duty",
                "pw01.enable",
                "pw02.duty",
                "pw02.enable"
            ]
        );
        assert_eq!(v[2].value, ParameterValue::String("a.vcd,b.csv".into()));
        assert_eq!(v[8].value, ParameterValue::Double(37.0));
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
            (&["--line", "pw01=-3"][..], "not a line offset"),
            (&["--status-rate", "fast"][..], "not a number"),
        ] {
            let e = flags(a).unwrap_err();
            assert!(e.to_string().contains(why), "{a:?}: {e}");
        }
        assert!(flags(&["-h"]).unwrap().help);
    }
}
