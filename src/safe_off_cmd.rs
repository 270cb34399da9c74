//! `pwm_actuator_node safe-off`: the command line of [`pwm_actuator::safe_off`] (part of the
//! binary only). Its options are translated into the node's own syntax, so that the lines are
//! read exactly as the node reads them.

use clap::{ArgAction, Args, FromArgMatches};
use pwm_actuator::ros::config::params::channel_index;
use std::path::PathBuf;

/// Options of `pwm_actuator_node safe-off`.
#[derive(Debug, Clone, PartialEq, Eq, Args)]
pub struct SafeOffOptions {
    /// GPIO line of a channel, as for the node: pw01=17 or pw02=/dev/gpiochip1:4; repeatable
    #[arg(long = "line", value_name = "CH=[CHIP:]OFFSET", action = ArgAction::Append)]
    pub lines: Vec<String>,
    /// A channel whose line is active-low (the node's CH.active_low); repeatable
    #[arg(long = "active-low", value_name = "CH", action = ArgAction::Append)]
    pub active_low: Vec<String>,
    /// The node's parameter file (its pwNN.gpio_chip, pwNN.gpio_line, pwNN.active_low, channels)
    #[arg(long, value_name = "FILE.yaml")]
    pub params_file: Option<PathBuf>,
    /// Number of channels [default: the highest channel given with --line, else the node's]
    #[arg(long, value_name = "N")]
    pub channels: Option<usize>,
}

/// The `safe-off` subcommand, for the whole command line.
pub fn command() -> clap::Command {
    SafeOffOptions::augment_args(clap::Command::new("safe-off"))
        .about(
            "Drive the node's GPIO lines inactive (honouring active_low) and release them; \
             refuses, naming the holder, while another process holds a line. For the service \
             manager after the node has ended (systemd ExecStopPost=).",
        )
        // The node's command turns clap's help flag off for its subcommands (see bench).
        .disable_help_flag(true)
        .arg(
            clap::Arg::new("help")
                .short('h')
                .long("help")
                .action(ArgAction::Help)
                .help("Print help"),
        )
        .after_help(
            "Exit status: 0 every line inactive; 1 a line is held by another process or could \
             not be written; 2 bad arguments or configuration (nothing touched). \
             --ros-args (-p, --params-file, -r __node:=NAME) are read as the node reads them.",
        )
}

/// Parses the subcommand's matches.
pub fn options(m: &clap::ArgMatches) -> Result<SafeOffOptions, clap::Error> {
    SafeOffOptions::from_arg_matches(m)
}

/// The node command line equivalent to `opts`, followed by `ros_blocks` (the original
/// `--ros-args ...` part of the command line, unchanged).
pub fn node_args(opts: &SafeOffOptions, ros_blocks: &[String]) -> Vec<String> {
    let mut args = Vec::new();
    for l in &opts.lines {
        args.extend(["--line".to_string(), l.clone()]);
    }
    let channels = opts.channels.or_else(|| {
        // With lines only, the channels are those named; a params file says its own.
        if opts.params_file.is_some() || !ros_blocks.is_empty() {
            return None;
        }
        opts.lines
            .iter()
            .filter_map(|l| {
                let (ch, _) = l.split_once('=')?;
                channel_index(ch).map(|i| i + 1)
            })
            .max()
    });
    if let Some(n) = channels {
        args.extend(["--channels".to_string(), n.to_string()]);
    }
    let mut ros = Vec::new();
    if let Some(f) = &opts.params_file {
        ros.extend([
            "--params-file".to_string(),
            f.to_string_lossy().into_owned(),
        ]);
    }
    for ch in &opts.active_low {
        ros.extend(["-p".to_string(), format!("{ch}.active_low:=true")]);
    }
    if !ros.is_empty() {
        args.push("--ros-args".into());
        args.extend(ros);
        args.push("--".into());
    }
    args.extend(ros_blocks.iter().cloned());
    args
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(a: &[&str]) -> SafeOffOptions {
        let m = command()
            .try_get_matches_from(std::iter::once("safe-off").chain(a.iter().copied()))
            .unwrap();
        options(&m).unwrap()
    }

    /// The words of a command line with no quoting.
    fn words(line: &str) -> Vec<&str> {
        line.split(' ').collect()
    }

    #[test]
    fn options_become_the_node_arguments() {
        for (options, node) in [
            // Lines alone set the channels they name.
            (
                "--line pw01=3 --line pw02=/dev/gpiochip1:4",
                "--line pw01=3 --line pw02=/dev/gpiochip1:4 --channels 2",
            ),
            // A parameter file and polarity become ROS arguments.
            (
                "--params-file p.yaml --active-low pw01",
                "--ros-args --params-file p.yaml -p pw01.active_low:=true --",
            ),
        ] {
            assert_eq!(
                node_args(&opts(&words(options)), &[]),
                words(node),
                "{options}"
            );
        }
    }

    #[test]
    fn help_is_generated_from_the_options() {
        let e = command()
            .try_get_matches_from(["safe-off", "--help"])
            .unwrap_err();
        assert_eq!(e.kind(), clap::error::ErrorKind::DisplayHelp);
        let text = e.to_string();
        for want in [
            "--line <CH=[CHIP:]OFFSET>",
            "--active-low <CH>",
            "--params-file",
        ] {
            assert!(text.contains(want), "{want} not in:\n{text}");
        }
    }

    #[test]
    fn the_command_passes_clap_checks() {
        command().debug_assert();
    }
}
