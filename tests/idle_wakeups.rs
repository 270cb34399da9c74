//! An idle output thread costs nothing: without a liveness tick (a node without a systemd
//! watchdog) it sleeps until its next deadline or request, with one only every tick. Its own
//! file, so that no other test's output thread runs in the process while the wake-ups of the
//! thread named `pwm-output` are counted. And the node's report thread, with nothing but its
//! clocks to keep, wakes once a second for all of them, as does its DDS event loop.

#[path = "common/ros_harness.rs"]
mod ros_harness;

use pwm_actuator::core::{ChannelParams, Nanos};
use pwm_actuator::output::SimOutput;
use pwm_actuator::output_thread::{self, OutputThreadOptions};
use std::time::Duration;

fn one_channel() -> Vec<pwm_actuator::core::ChannelConfig> {
    vec![ChannelParams::default().validate().unwrap()]
}

/// The voluntary context switches (sleeps) so far of this process's thread named `name`.
fn sleeps_of_thread(name: &str) -> u64 {
    sleeps_of_thread_in("self", name)
}

/// The voluntary context switches (sleeps) so far of the thread named `name` of process `pid`
/// (`self` for this one).
fn sleeps_of_thread_in(pid: &str, name: &str) -> u64 {
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .unwrap()
        .flatten()
    {
        let comm = std::fs::read_to_string(task.path().join("comm")).unwrap_or_default();
        if comm.trim() != name {
            continue;
        }
        let status = std::fs::read_to_string(task.path().join("status")).unwrap();
        return status
            .lines()
            .find_map(|l| l.strip_prefix("voluntary_ctxt_switches:"))
            .map(|v| v.trim().parse().unwrap())
            .unwrap();
    }
    panic!("no thread named {name}");
}

#[test]
fn without_a_liveness_tick_an_idle_output_thread_sleeps_until_a_request() {
    // One disabled channel: nothing is ever due. With the tick the thread wakes every 100 ms
    // (about 10 times in a second); without it, not once until a request or the stop.
    let run = |tick: Option<Nanos>| {
        let sim = SimOutput::new(vec!["pw01".into()], None).unwrap();
        let opts = OutputThreadOptions {
            liveness_tick_ns: tick,
            ..OutputThreadOptions::default()
        };
        let e = output_thread::spawn(one_channel(), sim, opts).unwrap();
        std::thread::sleep(Duration::from_millis(200));
        let before = sleeps_of_thread("pwm-output");
        std::thread::sleep(Duration::from_millis(1000));
        let woke = sleeps_of_thread("pwm-output") - before;
        let lag = e
            .handle
            .liveness()
            .lag_ns(pwm_actuator::clock::monotonic_ns());
        e.handle.shutdown().unwrap();
        (woke, lag)
    };
    let (woke, lag) = run(None);
    assert!(woke <= 1, "woke {woke} times in 1 s with nothing to do");
    assert_eq!(lag, Some(0), "asleep with nothing due is on schedule");
    let (woke, _) = run(Some(output_thread::LIVENESS_TICK_NS));
    assert!(woke >= 5, "with the tick: woke {woke} times in 1 s");
}

#[test]
fn a_reader_waiting_less_than_a_millisecond_sleeps_rather_than_spins() {
    // A wait shorter than the poll's millisecond resolution is rounded up, never down to 0:
    // a reader with a deadline 0.3 ms away sleeps once instead of spinning until it.
    let sim = SimOutput::new(vec!["pw01".into()], None).unwrap();
    let opts = OutputThreadOptions {
        liveness_tick_ns: None,
        ..OutputThreadOptions::default()
    };
    let mut e = output_thread::spawn(one_channel(), sim, opts).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    e.reports.clear_wake();
    while e.reports.try_recv().is_some() {}
    for _ in 0..20 {
        let start = std::time::Instant::now();
        let woken = e.reports.wait(Duration::from_micros(300));
        assert!(!woken, "no report is coming");
        assert!(
            start.elapsed() >= Duration::from_micros(300),
            "returned after {:?}, before its deadline",
            start.elapsed()
        );
    }
    e.handle.shutdown().unwrap();
}

#[test]
fn an_idle_node_reports_its_status_and_diagnostics_in_one_wake_up_a_second() {
    // Two disabled channels: no edge, no command. What the report thread keeps is the status
    // (1 Hz by default), the diagnostics run and the periodic /diagnostics, all once a second:
    // they fall due together, so one wake-up a second does all three (two a second when the
    // periodic /diagnostics counted its second from its own last publication).
    let node = ros_harness::NodeProc::launch(&["--channels", "2"]);
    let pid = node.pid().to_string();
    std::thread::sleep(Duration::from_secs(2));
    let before = sleeps_of_thread_in(&pid, "pwm-reports");
    std::thread::sleep(Duration::from_secs(6));
    let woke = sleeps_of_thread_in(&pid, "pwm-reports") - before;
    let log = node.stop_ok();
    assert!(
        (3..=8).contains(&woke),
        "the report thread woke {woke} times in 6 s; log:\n{log}"
    );
}

#[test]
fn an_idle_nodes_dds_event_loop_wakes_for_its_heartbeats_and_little_else() {
    // Two disabled channels and nobody subscribed: the status and /diagnostics written once a
    // second reach no reader, so they do not wake the participant's event loop thread, and its
    // own periodic work (the writers' HEARTBEATs and cache cleaning, the preemptive ACKNACKs,
    // the DDS cache's garbage collection) falls due on one 1 s grid: about 6 wake-ups in 6 s
    // (rustdds's fifteenth and sixteenth changes, vendor/rustdds/README.pwm_actuator.md);
    // about 15 when each write woke it and its periodic work had instants of its own.
    let node = ros_harness::NodeProc::launch(&["--channels", "2"]);
    let pid = node.pid().to_string();
    std::thread::sleep(Duration::from_secs(3));
    let before = sleeps_of_thread_in(&pid, "RustDDS Partici");
    std::thread::sleep(Duration::from_secs(6));
    let woke = sleeps_of_thread_in(&pid, "RustDDS Partici") - before;
    let log = node.stop_ok();
    assert!(
        woke <= 11,
        "the DDS event loop woke {woke} times in 6 s; log:\n{log}"
    );
}
