//! The output thread on the simulated sink: what reaches the line is what the core scheduled,
//! a failing write leaves every line inactive, a lagging reader never stalls the thread, and a
//! shutdown leaves every output off.

use pwm_actuator::core::{Channel, ChannelConfig, ChannelParams, Command, Event, Level, Nanos};
use pwm_actuator::output::fault::FailingOutput;
use pwm_actuator::output::{
    CsvRow, EmergencyOff, ErrorKind, LineChange, Output, OutputError, SimOutput, SimProbe,
    TraceSpec,
};
use pwm_actuator::output_thread::{
    self, Input, OutputThreadError, OutputThreadOptions, Report, Request,
};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

fn params(period_ms: u64) -> ChannelParams {
    ChannelParams {
        period_ms,
        ..ChannelParams::default()
    }
}

fn names(n: usize) -> Vec<String> {
    (1..=n).map(|i| format!("pw{i:02}")).collect()
}

/// The rows of the CSV trace at `path`.
fn read_csv(path: &Path) -> Vec<CsvRow> {
    let text = std::fs::read_to_string(path).expect("trace written");
    pwm_actuator::output::read_csv(&text).expect("a CSV trace")
}

/// Two channels with `cfgs` on a simulated output traced to `dir/<file>.csv`, running; the
/// trace's path with it.
fn spawn_traced(
    dir: &Path,
    file: &str,
    cfgs: Vec<ChannelConfig>,
) -> (PathBuf, output_thread::OutputThread) {
    let csv = dir.join(format!("{file}.csv"));
    let trace = TraceSpec::from_paths(std::slice::from_ref(&csv)).unwrap();
    let output = SimOutput::new(names(cfgs.len()), Some(trace)).unwrap();
    (
        csv,
        output_thread::spawn(cfgs, output, OutputThreadOptions::default()).unwrap(),
    )
}

/// One input or poll of a channel core, handing its events to the given sink.
type CoreStep<'a> = &'a mut dyn FnMut(&mut Channel, &mut dyn FnMut(Event));

fn send(requests: &mut output_thread::Requests, channel: usize, input: Input) {
    requests.send(Request { channel, input }).expect("queued");
}

#[test]
fn the_trace_matches_the_core_schedule_edge_for_edge() {
    let dir = tempdir();
    let p1 = params(20);
    let p2 = ChannelParams {
        min_on_ms: 3,
        ..params(10)
    };
    let cfgs = vec![p1.validate().unwrap(), p2.validate().unwrap()];
    let (csv, mut e) = spawn_traced(dir.path(), "run", cfgs.clone());
    send(&mut e.requests, 0, Input::Command(Command::Percent(40.0)));
    send(&mut e.requests, 1, Input::Command(Command::Percent(45.0)));
    send(&mut e.requests, 0, Input::Enable(true));
    send(&mut e.requests, 1, Input::Enable(true));
    std::thread::sleep(Duration::from_millis(300));
    send(&mut e.requests, 1, Input::Command(Command::Percent(70.0)));
    // Some 60 periods at 70 %: a late write may shift a pulse (the core counts the minimum
    // break from the real fall), but not all of them, even on a loaded machine.
    std::thread::sleep(Duration::from_millis(600));
    e.handle.shutdown().unwrap();

    // Collect The output thread's own account of when each input was applied: the first edge of a
    // channel is its enable; the duty change shows in a Plan report.
    let mut reports = Vec::new();
    while let Some(r) = e.reports.try_recv() {
        reports.push(r);
    }
    let rows = read_csv(&csv);
    for (ch, name) in names(2).iter().enumerate() {
        let edges: Vec<_> = rows.iter().filter(|r| &r.channel == name).skip(1).collect();
        assert!(edges.len() > 20, "{name}: {} edges", edges.len());
        // Replay the same inputs on a core in virtual time.
        let enable_at = edges[0].scheduled_ns;
        let mut core = Channel::new(cfgs[ch], 0);
        let mut want: Vec<(Nanos, Level)> = Vec::new();
        // The thread tells its cores when each edge really reached the line, and a late edge
        // moves the next one; the replay is told the same times, from the edge reports.
        let written: std::collections::HashMap<(Nanos, u8), Nanos> = reports
            .iter()
            .filter_map(|r| match r {
                Report::Edge(e) if e.channel == ch => {
                    Some(((e.scheduled_ns, u8::from(e.level.is_high())), e.actual_ns))
                }
                _ => None,
            })
            .collect();
        let mut step = |core: &mut Channel, f: CoreStep| {
            let mut events = Vec::new();
            f(core, &mut |e| events.push(e));
            for e in events {
                if let Event::Edge { at, level } = e {
                    want.push((at, level));
                    if let Some(actual) = written.get(&(at, u8::from(level.is_high()))) {
                        core.edge_written(*actual);
                    }
                }
            }
        };
        step(&mut core, &mut |c, emit| {
            c.command(0, Command::Percent([40.0, 45.0][ch]), emit)
        });
        step(&mut core, &mut |c, emit| {
            c.set_enable(enable_at, true, emit)
        });
        // Channel 2's duty change: under next_period it takes effect at the first period
        // boundary after the output thread applied it. That boundary is where the on time first
        // becomes 7 ms; The output thread's own status report of the 70 % command must lie in the
        // period before it.
        let change_at = (ch == 1).then(|| {
            let rises: Vec<Nanos> = edges
                .iter()
                .filter(|r| r.level.is_high())
                .map(|r| r.scheduled_ns)
                .collect();
            let falls: Vec<Nanos> = edges
                .iter()
                .filter(|r| !r.level.is_high())
                .map(|r| r.scheduled_ns)
                .collect();
            let k = rises
                .iter()
                .zip(&falls)
                .position(|(r, f)| f - r == 7_000_000)
                .expect("a 7 ms pulse after the change");
            let applied = reports
                .iter()
                .find_map(|r| match r {
                    Report::Status {
                        channel: 1,
                        status,
                        at_ns,
                    } if status.duty_commanded == 0.7 => Some(*at_ns),
                    _ => None,
                })
                .expect("the 70 % command was reported");
            // Applied within the period before that boundary; later only if the thread was
            // stalled past the boundary and caught up with the command already in hand.
            assert!(
                applied + 10_000_000 >= rises[k] && applied <= rises[k] + 100_000_000,
                "command applied at {applied}, first 70 % period at {}",
                rises[k]
            );
            rises[k]
        });
        let last_scheduled = edges[edges.len() - 2].scheduled_ns;
        let mut changed = false;
        while let Some(t) = core.poll_at() {
            if let Some(c) = change_at {
                if !changed && t >= c {
                    step(&mut core, &mut |c, emit| {
                        c.command(t - 1, Command::Percent(70.0), emit)
                    });
                    changed = true;
                }
            }
            if t > last_scheduled {
                break;
            }
            step(&mut core, &mut |c, emit| c.poll(t, emit));
        }
        // All but the shutdown edge were scheduled by the core.
        let got: Vec<(Nanos, Level)> = edges[..edges.len() - 1]
            .iter()
            .map(|r| (r.scheduled_ns, r.level))
            .collect();
        // A thread stalled past two deadlines merges that pulse or break rather than write a
        // zero-width one, and reports it as Missed. Everything else matches exactly.
        let reported_missed: u32 = reports
            .iter()
            .map(|r| match r {
                Report::Core {
                    channel,
                    event: Event::Missed { edges },
                } if *channel == ch => *edges,
                _ => 0,
            })
            .sum();
        let (mut i, mut j, mut merged) = (0, 0, 0u32);
        while i < got.len() && j < want.len() {
            if got[i] == want[j] {
                i += 1;
                j += 1;
            } else if j + 1 < want.len() && want[j + 1].0 < got[i].0 {
                j += 2;
                merged += 2;
            } else {
                panic!(
                    "{name}: trace edge {i} {:?} is not the core's {:?}",
                    got[i], want[j]
                );
            }
        }
        assert_eq!(i, got.len(), "{name}: the replay ran out at edge {i}");
        assert!(
            want.len() - j <= 2,
            "{name}: edges the trace lacks: {:?}",
            &want[j..]
        );
        assert_eq!(e.reports.dropped(), 0);
        assert_eq!(
            merged, reported_missed,
            "{name}: merged edges are the reported ones"
        );
        for r in &edges {
            assert!(
                r.t_ns >= r.scheduled_ns,
                "{name}: written before its schedule: {r:?}"
            );
            // Very generous: only a stalled machine comes near this.
            assert!(
                r.t_ns - r.scheduled_ns < 100_000_000,
                "{name}: 100 ms late: {r:?}"
            );
        }
        assert_eq!(
            edges.last().unwrap().level,
            Level::Low,
            "{name}: ends inactive"
        );
    }
}

#[test]
fn a_split_range_pair_is_never_high_together_on_the_line() {
    // 001's split range: hot and cold change sign every 35 ms while both pulse at 10 ms
    // periods with different phases; on the trace (written times) the two lines never overlap.
    let dir = tempdir();
    let hot = params(10);
    let cold = ChannelParams {
        apply_at: Some(pwm_actuator::core::ApplyAt::Immediate),
        ..params(7)
    };
    let cfgs = vec![hot.validate().unwrap(), cold.validate().unwrap()];
    let (csv, mut e) = spawn_traced(dir.path(), "pair", cfgs);
    send(&mut e.requests, 0, Input::Pair(1));
    send(&mut e.requests, 1, Input::Pair(0));
    send(&mut e.requests, 0, Input::Enable(true));
    send(&mut e.requests, 1, Input::Enable(true));
    for k in 0..12 {
        let signed = if k % 2 == 0 { 70.0 } else { -80.0 };
        let (h, c) = pwm_actuator::core::split_command(signed, 0.0);
        send(&mut e.requests, 0, Input::Command(h));
        send(&mut e.requests, 1, Input::Command(c));
        std::thread::sleep(Duration::from_millis(35));
    }
    e.handle.shutdown().unwrap();
    let rows = read_csv(&csv);
    let mut high = [false; 2];
    let (mut rises, mut overlaps) = ([0; 2], Vec::new());
    for r in &rows {
        let i = usize::from(r.channel == "pw02");
        high[i] = r.level.is_high();
        rises[i] += usize::from(high[i]);
        if high[0] && high[1] {
            overlaps.push(r.t_ns);
        }
    }
    assert!(overlaps.is_empty(), "both high at {overlaps:?}");
    assert!(rises[0] >= 6 && rises[1] >= 6, "both sides ran: {rises:?}");
    assert_eq!(high, [false, false], "both end inactive");
}

#[test]
fn a_failing_write_drives_the_other_outputs_inactive_and_stops() {
    let sim = SimOutput::new(names(3), None).unwrap();
    let probe = sim.probe();
    let out = FailingOutput::new(sim, 5).on_line(1);
    let cfgs = vec![params(10).validate().unwrap(); 3];
    let mut e = output_thread::spawn(cfgs, out, OutputThreadOptions::default()).unwrap();
    // Channels 0 and 2 at 100 %: constantly on, until the fault.
    for (ch, duty) in [(0, 100.0), (1, 50.0), (2, 100.0)] {
        send(&mut e.requests, ch, Input::Command(Command::Percent(duty)));
        send(&mut e.requests, ch, Input::Enable(true));
    }
    let start = Instant::now();
    while !e.handle.is_finished() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the fault never stopped the thread"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(probe.levels(), vec![Level::Low; 3], "nothing left on");
    let mut fault = None;
    while let Some(r) = e.reports.try_recv() {
        if let Report::OutputFault { channel } = r {
            fault = Some(channel);
        }
    }
    assert_eq!(fault, Some(1), "the fault is reported with its channel");
    let kept = e
        .handle
        .fault()
        .expect("the fault is kept for the exit message");
    assert_eq!((kept.channel, kept.kind), (1, ErrorKind::Injected));
    assert_eq!(
        kept.error.to_string(),
        "injected output write failure on line 1 after 5 writes (PWM_ACTUATOR_FAULT)"
    );
    assert!(matches!(
        e.requests.send(Request {
            channel: 0,
            input: Input::Enable(false)
        }),
        Err(OutputThreadError::Stopped)
    ));
    match e.handle.shutdown() {
        Err(OutputThreadError::OutputFault {
            channel: 1,
            kind: ErrorKind::Injected,
            source,
        }) => {
            assert!(source.to_string().contains("injected"))
        }
        other => panic!("shutdown after a fault: {other:?}"),
    }
}

/// Fails to switch off the line of one channel, as a backend whose driver broke might.
struct OffFails {
    sim: SimOutput,
    line: usize,
}

#[derive(Debug, thiserror::Error)]
#[error("line {0} cannot be driven inactive")]
struct OffFailed(usize);

impl OutputError for OffFailed {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Write
    }
    fn line(&self) -> Option<usize> {
        Some(self.0)
    }
}

impl Output for OffFails {
    type Error = OffFailed;
    fn line_count(&self) -> usize {
        self.sim.line_count()
    }
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), OffFailed> {
        let Ok(()) = self.sim.set_levels(changes);
        Ok(())
    }
    fn set_all_inactive(&mut self) -> Result<(), OffFailed> {
        let Ok(()) = self.sim.set_all_inactive();
        Err(OffFailed(self.line))
    }
    fn emergency_off(&self) -> std::sync::Arc<dyn EmergencyOff> {
        self.sim.emergency_off()
    }
}

#[test]
fn a_shutdown_failure_names_the_channel_whose_line_failed() {
    let sim = SimOutput::new(names(3), None).unwrap();
    let out = OffFails { sim, line: 2 };
    let cfgs = vec![params(10).validate().unwrap(); 3];
    let e = output_thread::spawn(cfgs, out, OutputThreadOptions::default()).unwrap();
    match e.handle.shutdown() {
        Err(err @ OutputThreadError::ShutdownFault { .. }) => {
            assert_eq!(err.channel(), Some(2));
            assert!(
                matches!(
                    err,
                    OutputThreadError::ShutdownFault {
                        kind: ErrorKind::Write,
                        ..
                    }
                ),
                "{err:?}"
            );
            let text = pwm_actuator::error::chain(&err);
            assert!(
                text.contains("at channel index 2") && text.contains("line 2 cannot"),
                "{text}"
            );
        }
        other => panic!("shutdown with a failing switch-off: {other:?}"),
    }
}

#[test]
fn a_lagging_reader_loses_reports_but_never_stalls_the_thread() {
    let sim = SimOutput::new(names(1), None).unwrap();
    let probe = sim.probe();
    let cfgs = vec![params(5).validate().unwrap()];
    let opts = OutputThreadOptions {
        queue_capacity: 16,
        ..OutputThreadOptions::default()
    };
    let mut e = output_thread::spawn(cfgs, sim, opts).unwrap();
    send(&mut e.requests, 0, Input::Command(Command::Percent(50.0)));
    send(&mut e.requests, 0, Input::Enable(true));
    // 400 edges a second with their status reports go into a 16-entry queue nobody reads; the
    // thread must keep writing (a loaded machine may take longer than the nominal 0.25 s).
    let deadline = Instant::now() + Duration::from_secs(10);
    while probe.edge_count() <= 100 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        probe.edge_count() > 100,
        "edges kept coming: {}",
        probe.edge_count()
    );
    assert!(e.reports.dropped() > 50, "dropped {}", e.reports.dropped());
    e.handle.shutdown().unwrap();
}

/// Commands every channel to `duty` % and enables it, then waits until every line is high.
fn switch_on(e: &mut output_thread::OutputThread, probe: &SimProbe, duty: f64) {
    let n = probe.levels().len();
    for ch in 0..n {
        send(&mut e.requests, ch, Input::Command(Command::Percent(duty)));
        send(&mut e.requests, ch, Input::Enable(true));
    }
    let start = Instant::now();
    while probe.levels() != vec![Level::High; n] {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "never switched on"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn shutdown_leaves_every_output_inactive() {
    let sim = SimOutput::new(names(2), None).unwrap();
    let probe = sim.probe();
    let cfgs = vec![params(1000).validate().unwrap(); 2];
    let mut e = output_thread::spawn(cfgs, sim, OutputThreadOptions::default()).unwrap();
    switch_on(&mut e, &probe, 90.0);
    e.handle.shutdown().unwrap();
    assert_eq!(probe.levels(), vec![Level::Low; 2]);
    let last: Vec<_> = probe
        .recent_edges()
        .iter()
        .rev()
        .take(2)
        .map(|r| r.level)
        .collect();
    assert_eq!(last, vec![Level::Low; 2], "the shutdown edges are recorded");
}

fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap()
}

#[test]
fn a_loop_that_fails_still_leaves_every_output_inactive() {
    // A sleeping loop that ends with a failed system call (here a made-up EIO after the lines
    // went high) must not leave the lines where they were.
    let sim = SimOutput::new(names(2), None).unwrap();
    let probe = sim.probe();
    let cfgs = vec![params(1000).validate().unwrap(); 2];
    let seen_high = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let fail_now = std::sync::Arc::clone(&seen_high);
    let mut e =
        output_thread::spawn_with(cfgs, sim, OutputThreadOptions::default(), move |thread| {
            let start = Instant::now();
            while !fail_now.load(std::sync::atomic::Ordering::SeqCst)
                && start.elapsed() < Duration::from_secs(20)
            {
                thread.work()?;
                std::thread::sleep(Duration::from_millis(2));
            }
            Err(OutputThreadError::Sys {
                what: "poll",
                source: nix::errno::Errno::EIO,
            })
        })
        .unwrap();
    switch_on(&mut e, &probe, 100.0);
    seen_high.store(true, std::sync::atomic::Ordering::SeqCst);
    let r = e.handle.shutdown();
    assert!(
        matches!(r, Err(OutputThreadError::Sys { what: "poll", .. })),
        "{r:?}"
    );
    assert_eq!(probe.levels(), vec![Level::Low; 2]);
}
