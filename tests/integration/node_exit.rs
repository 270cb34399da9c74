//! Every exit path of the real node leaves every output inactive: SIGTERM, SIGINT, SIGHUP and
//! SIGQUIT while an output is on (exit 0), a panic in any thread (exit 101), a failing output write (exit 1).
//! Faults are injected with `PWM_ACTUATOR_FAULT` (see `output::fault`).

use crate::ros_harness::*;
use nix::sys::signal::Signal;
use pwm_actuator::core::Level;
use std::path::{Path, PathBuf};

/// A trace path in a fresh directory for this test (removed when the guard is dropped).
fn trace(name: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(format!("{name}.csv"));
    (dir, path)
}

/// The last level written to each channel, from the CSV trace.
fn last_levels(csv: &Path) -> Vec<(String, Level)> {
    let text = std::fs::read_to_string(csv).expect("trace written");
    let rows = pwm_actuator::output::read_csv(&text).expect("a CSV trace");
    ["pw01", "pw02"]
        .iter()
        .map(|ch| {
            let last = rows
                .iter()
                .rev()
                .find(|r| r.channel == *ch)
                .unwrap_or_else(|| panic!("no rows for {ch}:\n{text}"));
            (ch.to_string(), last.level)
        })
        .collect()
}

fn all_off() -> Vec<(String, Level)> {
    vec![("pw01".into(), Level::Low), ("pw02".into(), Level::Low)]
}

/// Starts the node with pw01 constantly on (100 %), pw02 pulsing, sim output traced to `csv`.
fn start(csv: &Path, env: &[(&str, &str)]) -> NodeProc {
    let csv = csv.to_string_lossy();
    let params = ros_params(&[
        "pw01.enable:=true",
        "pw01.duty:=100.0",
        "pw02.enable:=true",
        "pw02.duty:=50.0",
        "pw02.period_ms:=20",
        "edge_log_rate:=10",
    ]);
    NodeProc::start_with(&[&["--trace", &csv][..], &params].concat(), env)
}

/// Waits for the node to exit by itself; checks its exit code, that its log says `says`, and
/// that it left every output off.
fn exits_with_every_output_off(mut node: NodeProc, csv: &Path, code: i32, says: &str) {
    let status = node.wait_exit(LONG);
    let log = node.log();
    assert_eq!(status.code(), Some(code), "{log}");
    assert!(log.contains(says), "{says:?} is not reported:\n{log}");
    assert_eq!(last_levels(csv), all_off(), "{log}");
}

#[test]
fn stop_signals_with_an_output_on_exit_0_with_every_output_off() {
    for sig in [
        Signal::SIGTERM,
        Signal::SIGINT,
        Signal::SIGHUP,
        Signal::SIGQUIT,
    ] {
        let (_dir, csv) = trace(&format!("{sig:?}"));
        let node = start(&csv, &[]);
        node.wait_running();
        assert!(
            node.wait_log("pw01 ↑", LONG),
            "pw01 never went on:\n{}",
            node.log()
        );
        assert!(node.wait_log("pw02 ↓", LONG), "{}", node.log());
        let (status, log) = node.stop_with(sig);
        assert_eq!(status.code(), Some(0), "{sig:?}:\n{log}");
        assert_eq!(last_levels(&csv), all_off(), "{sig:?}:\n{log}");
    }
}

#[test]
fn a_panic_drives_every_output_off_and_exits_101() {
    let (_dir, csv) = trace("panic");
    let node = start(&csv, &[("PWM_ACTUATOR_FAULT", "panic-after-ms=1500")]);
    node.wait_running();
    assert!(node.wait_log("pw01 ↑", LONG), "{}", node.log());
    exits_with_every_output_off(node, &csv, 101, "injected panic");
}

#[test]
fn a_failing_output_write_drives_the_others_off_and_exits_nonzero() {
    let (_dir, csv) = trace("write");
    let node = start(&csv, &[("PWM_ACTUATOR_FAULT", "fail-write-after=40")]);
    node.wait_running();
    exits_with_every_output_off(node, &csv, 1, "injected output write failure");
}

#[test]
fn a_malformed_fault_variable_is_refused() {
    let (_dir, csv) = trace("malformed");
    let mut node = start(&csv, &[("PWM_ACTUATOR_FAULT", "explode=1")]);
    let status = node.wait_exit(LONG);
    assert_eq!(status.code(), Some(2), "{}", node.log());
    assert!(
        node.log().contains("expected panic-after-ms=N"),
        "{}",
        node.log()
    );
}
