//! The command line of the node as a process: help, errors with their reasons and exit codes,
//! clean shutdown on SIGINT and SIGTERM with the trace flushed, `ROS_DOMAIN_ID` checking.

use crate::ros_harness::*;
use nix::sys::signal::Signal;
use pwm_actuator::core::Level;
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

/// Runs the node with `args` and asserts that it refuses them (exit 2) saying `why`.
fn assert_refused(args: &[&str], domain: Option<&str>, why: &str) {
    let (code, _, err) = run(args, domain);
    assert_eq!(code, Some(2), "{args:?}: {err}");
    assert!(err.contains(why), "{args:?}: expected {why:?} in:\n{err}");
}

#[test]
fn help_prints_the_synopsis() {
    let (code, out, _) = run(&["--help"], None);
    assert_eq!(code, Some(0));
    assert_mentions(
        &out,
        &[
            "--demo",
            "--ros-args",
            "__node",
            "--params-file",
            "ROS_DOMAIN_ID",
            "~/<ch>/duty",
            // Generated from the options, so every option is listed, and the subcommands too.
            "--output <sim|gpio>",
            "--status-rate <HZ>",
            "-V, --version",
            "bench",
        ],
    );
    let (code, out, _) = run(&["--version"], None);
    assert_eq!(code, Some(0));
    assert!(out.starts_with("pwm_actuator_node "));
}

#[test]
fn bench_has_its_own_help_and_usage_errors() {
    for help in ["--help", "-h"] {
        let (code, out, err) = run(&["bench", help], None);
        assert_eq!(code, Some(0), "{err}");
        assert_mentions(
            &out,
            &[
                "pwm_actuator_node bench",
                "--channels <N>",
                "--period-ms <MS>",
                "--duty <PCT>",
                "--offset-ms <MS>",
                "--seconds <S>",
                "--rt-priority <P>",
                "--json",
                "[default: 37]",
            ],
        );
        // The node's options are not the bench's.
        assert!(!out.contains("--demo"), "{out}");
    }
    for (args, why) in [
        (&["--bogus"][..], "--bogus"),
        (&["--channels", "x"], "`x` is not a valid number"),
        (&["--channels", "0"], "--channels 0 is outside 1..256"),
        (&["--seconds"], "a value is required"),
        (&["--ros-args", "-p", "x:=1"], "takes no ROS arguments"),
    ] {
        assert_refused(&[&["bench"], args].concat(), None, why);
    }
    // Subcommands come first; after the node's options a word is an unknown option.
    assert_refused(&["--demo", "bench"], None, "unknown option `bench`");
}

#[test]
fn bad_command_lines_exit_2_with_a_reason() {
    for (args, why) in [
        (&["--fast"][..], "unknown option `--fast`"),
        (&["--channels", "0"], "0 is outside 1..99"),
        (&["--output", "gpio"], "set pw01.gpio_line"),
        (
            &[
                "--output",
                "gpio",
                "--line",
                "pw01=3",
                "--line",
                "pw02=gpiochip0:3",
            ],
            "pw01 and pw02 are both bound to",
        ),
        (
            &[
                "--output", "gpio", "--line", "pw01=1", "--line", "pw02=2", "--trace", "x.txt",
            ],
            // Checked before any chip is opened (there is none here).
            "unknown extension",
        ),
        (&["--trace", "x.txt"], "unknown extension"),
    ] {
        assert_refused(args, None, why);
    }
    for (domain, why) in [
        ("999", "ROS_DOMAIN_ID `999` is not a domain id"),
        ("abc", "ROS_DOMAIN_ID `abc`"),
    ] {
        assert_refused(&[], Some(domain), why);
    }
    for (ros_args, why) in [
        (&["--fast"][..], "unknown ROS argument `--fast`"),
        (&["-r", "__ns:=plant"], "must be absolute"),
        (
            &["--params-file", "/nonexistent.yaml"],
            "cannot read parameter file /nonexistent.yaml",
        ),
    ] {
        assert_refused(&[&["--ros-args"], ros_args].concat(), None, why);
    }
    // Parameters (`-p NAME:=VALUE`): refused with the reason.
    for (param, why) in [
        ("pw01.period_ms", "expected NAME:=VALUE"),
        (
            "pw01.period_ms:=4",
            "pw01: period_ms 4 is below the transistor minimum",
        ),
        ("pw01.period_ms:=500.5", "not a whole number"),
        ("pw01.duty:=150", "150.0 is outside 0.0..100.0"),
        ("pw01.profile:=pico", "`pico` is not one of"),
        (
            "split:=zone:pw01:pw09",
            "split: `pw09` is not a channel of this node (pw01..pw02)",
        ),
        ("split:=zone:pw01:pw01", "used twice"),
    ] {
        assert_refused(&ros_params(&[param]), None, why);
    }
}

#[test]
fn bad_valve_end_switches_exit_2_with_a_reason() {
    let gpio = [
        "--output",
        "gpio",
        "--line",
        "pw01=/dev/gpiochip_none:1",
        "--line",
        "pw02=/dev/gpiochip_none:2",
    ];
    let valve = |p: &str| {
        let mut a: Vec<&str> = gpio.to_vec();
        a.extend(["--ros-args", "-p", "valve:=mix:pw01:pw02", "-p"]);
        a.push(p);
        a.iter().map(|s| s.to_string()).collect::<Vec<String>>()
    };
    for (param, why) in [
        (
            "mix.close_limit_line:=/dev/gpiochip_none:2",
            "close_limit_line /dev/gpiochip_none:2 is already the output line of pw02",
        ),
        (
            "mix.open_limit_line:=x:y",
            "`x:y` is not one of: empty or [CHIP:]OFFSET",
        ),
        ("mix.limit_debounce_ms:=1000", "outside 0..100"),
    ] {
        let args = valve(param);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_refused(&args, None, why);
    }
    // The simulated output has no GPIO chips.
    assert_refused(
        &ros_params(&["valve:=mix:pw01:pw02", "mix.close_limit_line:=gpiochip0:3"]),
        None,
        "end switch lines need --output gpio",
    );
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
        let params = ros_params(&["pw01.period_ms:=50", "pw02.period_ms:=50"]);
        let node =
            NodeProc::launch(&[&["--demo", "--trace", &v, "--trace", &c][..], &params].concat());
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
