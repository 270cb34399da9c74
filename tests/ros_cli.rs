//! The command line of the node as a process: help, errors with their reasons and exit codes,
//! clean shutdown on SIGINT and SIGTERM with the trace flushed, `ROS_DOMAIN_ID` checking.

#[path = "common/ros_harness.rs"]
mod ros_harness;

use nix::sys::signal::Signal;
use pwm_actuator::core::Level;
use ros_harness::*;
use std::process::Command;

/// Runs the node to completion. `domain` is the `ROS_DOMAIN_ID` text; `None` takes a free
/// domain (the node may get as far as joining it).
fn run(args: &[&str], domain: Option<&str>) -> (Option<i32>, String, String) {
    let held = Domain::acquire();
    let id = held.id.to_string();
    let out = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"))
        .args(args)
        .env("ROS_DOMAIN_ID", domain.unwrap_or(&id))
        .output()
        .expect("the node binary runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn help_prints_the_synopsis() {
    let (code, out, _) = run(&["--help"], None);
    assert_eq!(code, Some(0));
    for s in [
        "--demo",
        "--ros-args",
        "__node",
        "--params-file",
        "ROS_DOMAIN_ID",
        "~/<ch>/duty",
    ] {
        assert!(out.contains(s), "{s} missing from:\n{out}");
    }
    // Generated from the options, so every option is listed, and the subcommands too.
    for s in [
        "--output <sim|gpio>",
        "--status-rate <HZ>",
        "-V, --version",
        "bench",
    ] {
        assert!(out.contains(s), "{s} missing from:\n{out}");
    }
    let (code, out, _) = run(&["--version"], None);
    assert_eq!(code, Some(0));
    assert!(out.starts_with("pwm_actuator_node "));
}

#[test]
fn bench_has_its_own_help_and_usage_errors() {
    for help in ["--help", "-h"] {
        let (code, out, err) = run(&["bench", help], None);
        assert_eq!(code, Some(0), "{err}");
        assert!(out.contains("pwm_actuator_node bench"), "{out}");
        for s in [
            "--channels <N>",
            "--period-ms <MS>",
            "--duty <PCT>",
            "--offset-ms <MS>",
            "--seconds <S>",
            "--rt-priority <P>",
            "--json",
            "[default: 37]",
        ] {
            assert!(out.contains(s), "{s} missing from:\n{out}");
        }
        // The node's options are not the bench's.
        assert!(!out.contains("--demo"), "{out}");
    }
    let cases: &[(&[&str], &str)] = &[
        (&["bench", "--bogus"], "--bogus"),
        (&["bench", "--channels", "x"], "`x` is not a valid number"),
        (
            &["bench", "--channels", "0"],
            "--channels 0 is outside 1..256",
        ),
        (&["bench", "--seconds"], "a value is required"),
        (
            &["bench", "--ros-args", "-p", "x:=1"],
            "takes no ROS arguments",
        ),
        // Subcommands come first; after the node's options a word is an unknown option.
        (&["--demo", "bench"], "unknown option `bench`"),
    ];
    for (args, why) in cases {
        let (code, _, err) = run(args, None);
        assert_eq!(code, Some(2), "{args:?}: {err}");
        assert!(err.contains(why), "{args:?}: expected {why:?} in:\n{err}");
    }
}

#[test]
fn bad_command_lines_exit_2_with_a_reason() {
    let cases: &[(&[&str], Option<&str>, &str)] = &[
        (&["--fast"], None, "unknown option `--fast`"),
        (
            &["--ros-args", "--fast"],
            None,
            "unknown ROS argument `--fast`",
        ),
        (
            &["--ros-args", "-p", "pw01.period_ms"],
            None,
            "expected NAME:=VALUE",
        ),
        (
            &["--ros-args", "-r", "__ns:=plant"],
            None,
            "must be absolute",
        ),
        (
            &["--ros-args", "--params-file", "/nonexistent.yaml"],
            None,
            "cannot read parameter file /nonexistent.yaml",
        ),
        (&[], Some("999"), "ROS_DOMAIN_ID `999` is not a domain id"),
        (&[], Some("abc"), "ROS_DOMAIN_ID `abc`"),
        (
            &["--ros-args", "-p", "pw01.period_ms:=4"],
            None,
            "pw01: period_ms 4 is below the transistor minimum",
        ),
        (
            &["--ros-args", "-p", "pw01.period_ms:=500.5"],
            None,
            "not a whole number",
        ),
        (
            &["--ros-args", "-p", "pw01.duty:=150"],
            None,
            "150.0 is outside 0.0..100.0",
        ),
        (
            &["--ros-args", "-p", "pw01.profile:=pico"],
            None,
            "`pico` is not one of",
        ),
        (&["--channels", "0"], None, "0 is outside 1..99"),
        (&["--output", "gpio"], None, "set pw01.gpio_line"),
        (
            &[
                "--output",
                "gpio",
                "--line",
                "pw01=3",
                "--line",
                "pw02=gpiochip0:3",
            ],
            None,
            "pw01 and pw02 are both bound to",
        ),
        (
            &[
                "--output", "gpio", "--line", "pw01=1", "--line", "pw02=2", "--trace", "x.txt",
            ],
            None,
            // Checked before any chip is opened (there is none here).
            "unknown extension",
        ),
        (&["--trace", "x.txt"], None, "unknown extension"),
        (
            &["--ros-args", "-p", "split:=zone:pw01:pw09"],
            None,
            "split: `pw09` is not a channel of this node (pw01..pw02)",
        ),
        (
            &["--ros-args", "-p", "split:=zone:pw01:pw01"],
            None,
            "used twice",
        ),
    ];
    for (args, domain, why) in cases {
        let (code, _, err) = run(args, *domain);
        assert_eq!(code, Some(2), "{args:?}: {err}");
        assert!(err.contains(why), "{args:?}: expected {why:?} in:\n{err}");
    }
}

#[test]
fn a_missing_gpio_chip_is_a_configuration_error_that_names_it() {
    let (code, _, err) = run(
        &[
            "--output",
            "gpio",
            "--line",
            "pw01=/dev/gpiochip_none:1",
            "--line",
            "pw02=/dev/gpiochip_none:2",
        ],
        None,
    );
    // No GPIO hardware here: opening fails before any output is driven, and it is the
    // configuration that is wrong (exit 2), not a fault while running (exit 1).
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("gpiochip_none"), "{err}");
}

#[test]
fn sigterm_and_sigint_stop_cleanly_and_flush_the_trace() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    for (i, sig) in [Signal::SIGTERM, Signal::SIGINT].into_iter().enumerate() {
        let vcd = dir.join(format!("t{i}.vcd"));
        let csv = dir.join(format!("t{i}.csv"));
        let (v, c) = (
            vcd.to_string_lossy().to_string(),
            csv.to_string_lossy().to_string(),
        );
        let dom = Domain::acquire();
        let node = NodeProc::start(
            dom.id,
            &[
                "--demo",
                "--trace",
                &v,
                "--trace",
                &c,
                "--ros-args",
                "-p",
                "pw01.period_ms:=50",
                "-p",
                "pw02.period_ms:=50",
            ],
        );
        node.wait_running();
        assert!(node.wait_log("pw02 ↓", LONG), "{}", node.log());
        let (status, log) = node.stop_with(sig);
        assert_eq!(status.code(), Some(0), "{log}");
        assert!(log.contains(&format!("{sig:?}: stopping")), "{log}");
        assert!(log.contains("all outputs off"), "{log}");
        let vcd = std::fs::read_to_string(&vcd).expect("VCD written");
        assert!(vcd.contains("$var wire 1 ! pw01 $end"), "{vcd}");
        assert!(
            vcd.lines().filter(|l| *l == "1!").count() >= 1,
            "pw01 went on:\n{vcd}"
        );
        let csv = std::fs::read_to_string(&csv).expect("CSV written");
        let rows = pwm_actuator::output::read_csv(&csv).expect("a CSV trace");
        assert!(rows.len() >= 4, "{csv}");
        // Every line ends inactive.
        for ch in ["pw01", "pw02"] {
            let last = rows
                .iter()
                .rev()
                .find(|r| r.channel == ch)
                .expect("rows for the channel");
            assert_eq!(last.level, Level::Low, "{ch} ends off: {last:?}");
        }
    }
}
