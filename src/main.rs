//! `pwm_actuator_node`: the ROS 2 node (see `pwm_actuator::ros`), `pwm_actuator_node bench ...`
//! for the timing benchmark, or `pwm_actuator_node safe-off ...` to drive the node's lines
//! inactive after it ended (see `pwm_actuator::safe_off`), or `pwm_actuator_node sim-heater ...`
//! for a simulated heater driven by a channel's edges.
//!
//! One command line, parsed by clap: the node's options ([`cli::Flags`]) and a subcommand per
//! other job, each with its own generated `--help`. The `--ros-args` blocks are split off
//! first, by hand, because they follow rcl's rules rather than clap's.

mod bench;
mod safe_off_cmd;
mod sim_heater;
mod sim_ros;
mod sim_valve;

use clap::error::ErrorKind;
use clap::FromArgMatches;
use pwm_actuator::ros;
use pwm_actuator::ros::config::{
    args::{self, RosArgs},
    cli,
};
use std::process::ExitCode;

/// What the command line asks for.
enum Invocation {
    /// Run the node; it parses and reports its own options and ROS arguments.
    Node,
    /// Run the benchmark.
    Bench(bench::BenchOptions),
    /// Drive the lines inactive; the node command line equivalent to the options.
    SafeOff(Vec<String>),
    /// Run the simulated heater.
    SimHeater(Box<sim_heater::SimHeaterOptions>),
    /// Run the simulated valve.
    SimValve(Box<sim_valve::SimValveOptions>),
    /// Already answered (help, or a subcommand's usage error): exit with this code.
    Exit(u8),
}

/// The whole command line: the node's options, and the subcommands.
fn command() -> clap::Command {
    cli::command()
        .override_usage(format!(
            "{}\n       pwm_actuator_node <COMMAND> [OPTIONS]",
            cli::NODE_USAGE
        ))
        .subcommand(bench::command())
        .subcommand(safe_off_cmd::command())
        .subcommand(sim_heater::command())
        .subcommand(sim_valve::command())
        .args_conflicts_with_subcommands(true)
        .disable_help_subcommand(true)
}

fn invocation(args: &[String]) -> Invocation {
    // A malformed ROS argument is the node's to report, in its own format.
    let Ok(split) = args::parse(args) else {
        return Invocation::Node;
    };
    let mut cmd = command();
    let argv = std::iter::once("pwm_actuator_node").chain(split.app.iter().map(String::as_str));
    match cmd.try_get_matches_from_mut(argv) {
        Ok(m) => match m.subcommand() {
            Some(("bench", sub)) => {
                if split.ros != RosArgs::default() {
                    eprintln!("bench: takes no ROS arguments (--ros-args)");
                    return Invocation::Exit(2);
                }
                match bench::BenchOptions::from_arg_matches(sub) {
                    Ok(o) => Invocation::Bench(o),
                    Err(e) => {
                        let _ = e.print();
                        Invocation::Exit(2)
                    }
                }
            }
            Some(("safe-off", sub)) => match safe_off_cmd::options(sub) {
                Ok(o) => {
                    let ros_blocks = args
                        .iter()
                        .position(|a| a == "--ros-args")
                        .map_or(&[][..], |i| &args[i..]);
                    Invocation::SafeOff(safe_off_cmd::node_args(&o, ros_blocks))
                }
                Err(e) => {
                    let _ = e.print();
                    Invocation::Exit(2)
                }
            },
            Some(("sim-heater", sub)) => match sim_heater::options(sub) {
                Ok(o) => Invocation::SimHeater(Box::new(o)),
                Err(e) => {
                    let _ = e.print();
                    Invocation::Exit(2)
                }
            },
            Some(("sim-valve", sub)) => match sim_valve::options(sub) {
                Ok(o) => Invocation::SimValve(Box::new(o)),
                Err(e) => {
                    let _ = e.print();
                    Invocation::Exit(2)
                }
            },
            _ if m.get_flag("help") => {
                println!("{}", cmd.render_help().to_string().trim_end());
                Invocation::Exit(0)
            }
            _ => Invocation::Node,
        },
        // A subcommand's own `--help`.
        Err(e) if e.kind() == ErrorKind::DisplayHelp => {
            let _ = e.print();
            Invocation::Exit(0)
        }
        Err(e)
            if split.app.first().is_some_and(|a| {
                a == "bench" || a == "safe-off" || a == "sim-heater" || a == "sim-valve"
            }) =>
        {
            let _ = e.print();
            Invocation::Exit(2)
        }
        // The node's own options: the node reports the error in its format.
        Err(_) => Invocation::Node,
    }
}

fn main() -> ExitCode {
    let mut args = Vec::new();
    for a in std::env::args_os().skip(1) {
        match a.into_string() {
            Ok(s) => args.push(s),
            Err(bad) => {
                eprintln!("[ERROR] [pwm_actuator]: argument {bad:?} is not valid UTF-8");
                return ExitCode::from(2);
            }
        }
    }
    let code = match invocation(&args) {
        Invocation::Node => ros::run(&args),
        Invocation::Bench(opts) => bench::run(opts),
        Invocation::SafeOff(node_args) => pwm_actuator::safe_off::run(&node_args),
        Invocation::SimHeater(opts) => sim_heater::run(*opts),
        Invocation::SimValve(opts) => sim_valve::run(*opts),
        Invocation::Exit(code) => return ExitCode::from(code),
    };
    ExitCode::from(u8::try_from(code).unwrap_or(1))
}

#[cfg(test)]
mod tests {
    /// clap's own consistency checks (unique names, valid settings) on the whole command line
    /// and on the bench subcommand alone, as its tests build it.
    #[test]
    fn the_command_line_passes_clap_checks() {
        super::command().debug_assert();
        super::bench::command().debug_assert();
        super::safe_off_cmd::command().debug_assert();
        super::sim_heater::command().debug_assert();
        super::sim_valve::command().debug_assert();
    }
}
