//! What an outside watcher sees of the output thread's life: the heartbeat line toggles at its
//! rate while the thread runs and ends inactive; the liveness the systemd watchdog reads stays
//! on schedule while the thread runs and falls behind when it hangs; the node sends
//! `WATCHDOG=1` only while its output thread keeps its schedule, and a hung thread does not
//! keep a stop from switching the outputs off.

use crate::ros_harness::*;
use nix::sys::signal::Signal;
use pwm_actuator::core::{ChannelParams, Level, Nanos};
use pwm_actuator::output::fault::HangingOutput;
use pwm_actuator::output::{read_csv, CsvRow, SimOutput, TraceSpec};
use pwm_actuator::output_thread::{self, OutputThreadError, OutputThreadOptions, SHUTDOWN_WAIT};
use std::os::unix::net::UnixDatagram;
use std::time::{Duration, Instant};

fn one_channel() -> Vec<pwm_actuator::core::ChannelConfig> {
    vec![ChannelParams::default().validate().unwrap()]
}

/// The heartbeat rows of a CSV trace.
fn heartbeat_rows(csv: &std::path::Path) -> Vec<CsvRow> {
    let text = std::fs::read_to_string(csv).expect("trace written");
    read_csv(&text)
        .expect("a CSV trace")
        .into_iter()
        .filter(|r| r.channel == "heartbeat")
        .collect()
}

/// Intervals between successive rows, ns, sorted.
fn sorted_intervals(rows: &[CsvRow]) -> Vec<Nanos> {
    let mut d: Vec<Nanos> = rows.windows(2).map(|w| w[1].t_ns - w[0].t_ns).collect();
    d.sort_unstable();
    d
}

#[test]
fn the_output_thread_toggles_the_heartbeat_line_on_its_grid_and_ends_it_inactive() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("hb.csv");
    let spec = TraceSpec::from_paths(std::slice::from_ref(&csv)).unwrap();
    let sim = SimOutput::new(vec!["pw01".into(), "heartbeat".into()], Some(spec)).unwrap();
    let probe = sim.probe();
    let opts = OutputThreadOptions {
        heartbeat_half_period_ns: Some(10_000_000),
        ..OutputThreadOptions::default()
    };
    let e = output_thread::spawn(one_channel(), sim, opts).unwrap();
    std::thread::sleep(Duration::from_millis(400));
    let live = e.handle.liveness();
    let lag = live.lag_ns(pwm_actuator::clock::monotonic_ns());
    assert!(
        lag.is_some_and(|l| l < 1_000_000_000),
        "a running thread keeps its schedule: {lag:?}"
    );
    e.handle.shutdown().unwrap();
    assert_eq!(live.lag_ns(0), None, "a stopped thread is not alive");
    assert_eq!(probe.levels(), [Level::Low, Level::Low]);
    let rows = heartbeat_rows(&csv);
    // About 40 toggles in 400 ms; wide bounds for a loaded machine.
    assert!(rows.len() >= 20, "{} toggles", rows.len());
    for w in rows.windows(2) {
        assert_ne!(w[0].level, w[1].level, "every row is a toggle");
    }
    // Scheduled on an absolute grid: the scheduled times are exactly 10 ms apart (only a
    // stall longer than a half period restarts the grid).
    let on_grid = rows
        .windows(2)
        .filter(|w| w[1].scheduled_ns - w[0].scheduled_ns == 10_000_000)
        .count();
    assert!(
        on_grid * 10 >= (rows.len() - 1) * 8,
        "{on_grid} of {} on the grid",
        rows.len() - 1
    );
    let d = sorted_intervals(&rows);
    let median = d[d.len() / 2];
    assert!(
        (8_000_000..=12_000_000).contains(&median),
        "median interval {median} ns for a 10 ms half period"
    );
    assert_eq!(rows.last().unwrap().level, Level::Low, "ends inactive");
}

#[test]
fn a_hung_output_thread_falls_behind_and_a_stop_switches_off_without_it() {
    let sim = SimOutput::new(vec!["pw01".into(), "heartbeat".into()], None).unwrap();
    let probe = sim.probe();
    // The heartbeat writes every 5 ms; the first write after 300 ms never returns.
    let out = HangingOutput::new(sim, 300);
    let opts = OutputThreadOptions {
        heartbeat_half_period_ns: Some(5_000_000),
        ..OutputThreadOptions::default()
    };
    let e = output_thread::spawn(one_channel(), out, opts).unwrap();
    let live = e.handle.liveness();
    std::thread::sleep(Duration::from_millis(1300));
    let lag = live.lag_ns(pwm_actuator::clock::monotonic_ns()).unwrap();
    assert!(lag >= 500_000_000, "a hung thread falls behind: {lag} ns");
    let start = Instant::now();
    let r = e.handle.shutdown();
    assert!(matches!(r, Err(OutputThreadError::Hung { .. })), "{r:?}");
    assert!(start.elapsed() < SHUTDOWN_WAIT + Duration::from_secs(2));
    assert_eq!(
        probe.levels(),
        [Level::Low, Level::Low],
        "switched off by the emergency handle"
    );
}

/// Datagrams received on a notify socket, with when they arrived.
fn collect(sock: &UnixDatagram, for_: Duration) -> Vec<(Instant, String)> {
    sock.set_read_timeout(Some(Duration::from_millis(50)))
        .unwrap();
    let end = Instant::now() + for_;
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    while Instant::now() < end {
        if let Ok(n) = sock.recv(&mut buf) {
            got.push((
                Instant::now(),
                String::from_utf8_lossy(&buf[..n]).into_owned(),
            ));
        }
    }
    got
}

#[test]
fn the_node_pings_the_systemd_watchdog_only_while_its_output_thread_keeps_time() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notify.sock");
    let sock = UnixDatagram::bind(&path).unwrap();
    let started = Instant::now();
    let node = NodeProc::start_with(
        &[
            "--ros-args",
            "-p",
            "heartbeat_line:=7",
            "-p",
            "heartbeat_hz:=50",
        ],
        &[
            ("NOTIFY_SOCKET", path.to_str().unwrap()),
            // WatchdogSec=400ms: a ping every 200 ms while alive.
            ("WATCHDOG_USEC", "400000"),
            ("PWM_ACTUATOR_FAULT", "hang-write-after-ms=2500"),
        ],
    );
    // Long enough for a slow start (the node's start-up competes with the other tests), the
    // hang, and a silence after it.
    let got = collect(&sock, Duration::from_millis(8000));
    let log = node.log();
    let ready = got
        .iter()
        .position(|(_, m)| m.contains("READY=1"))
        .unwrap_or_else(|| panic!("no READY=1: {got:?}\n{log}"));
    let pings: Vec<Instant> = got[ready..]
        .iter()
        .filter(|(_, m)| m.contains("WATCHDOG=1"))
        .map(|(t, _)| *t)
        .collect();
    assert!(pings.len() >= 3, "pings while alive: {got:?}\n{log}");
    let last = *pings.last().unwrap();
    // The hang begins 2.5 s after the output opened, which is before READY=1; the pings stop
    // within the grace (200 ms) after it. Nothing later than 3.5 s after READY=1, and
    // silence until the end.
    let ready_at = got[ready].0;
    assert!(
        last.duration_since(ready_at) < Duration::from_millis(3500),
        "pings went on after the hang: last {:?} after READY=1\n{log}",
        last.duration_since(ready_at)
    );
    assert!(
        started.elapsed() - last.duration_since(started) >= Duration::from_millis(1500),
        "silence after the hang: last ping {:?} after the start\n{log}",
        last.duration_since(started)
    );
    assert!(
        node.wait_log("not telling the service manager it is alive", LONG),
        "{log}"
    );
    // A stop still ends the process, with the outputs switched off by the emergency handle.
    let (status, log) = node.stop_with(Signal::SIGTERM);
    assert_eq!(status.code(), Some(1), "{log}");
    assert!(log.contains("did not stop within"), "{log}");
}

#[test]
fn the_node_traces_its_heartbeat_line_at_the_rate_asked() {
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("node-hb.csv");
    let node = NodeProc::start(&[
        "--trace",
        csv.to_str().unwrap(),
        "--ros-args",
        "-p",
        "heartbeat_line:=9",
        "-p",
        "heartbeat_hz:=20",
    ]);
    node.wait_running();
    std::thread::sleep(Duration::from_millis(1000));
    let (status, log) = node.stop_with(Signal::SIGTERM);
    assert_eq!(status.code(), Some(0), "{log}");
    let rows = heartbeat_rows(&csv);
    // 20 Hz: a toggle every 25 ms, about 40 in the second.
    assert!(rows.len() >= 20, "{} toggles\n{log}", rows.len());
    let d = sorted_intervals(&rows);
    let median = d[d.len() / 2];
    assert!(
        (20_000_000..=30_000_000).contains(&median),
        "median interval {median} ns at 20 Hz"
    );
    assert_eq!(rows.last().unwrap().level, Level::Low, "ends inactive");
}
