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
    spawn_traced_on(dir, file, cfgs, |sim| sim)
}

/// [`spawn_traced`] on the simulated output as `wrap` wraps it.
fn spawn_traced_on<O: Output + Send + 'static>(
    dir: &Path,
    file: &str,
    cfgs: Vec<ChannelConfig>,
    wrap: impl FnOnce(SimOutput) -> O,
) -> (PathBuf, output_thread::OutputThread) {
    let csv = dir.join(format!("{file}.csv"));
    let trace = TraceSpec::from_paths(std::slice::from_ref(&csv)).unwrap();
    let output = wrap(SimOutput::new(names(cfgs.len()), Some(trace)).unwrap());
    (
        csv,
        output_thread::spawn(cfgs, output, OutputThreadOptions::default()).unwrap(),
    )
}

/// An output whose every `every`-th write first takes `stall`: the thread that writes misses
/// the deadlines in between, as on a machine that does not run it for that long.
struct StallingOutput<O> {
    inner: O,
    every: u32,
    stall: Duration,
    writes: u32,
}

impl<O: Output> Output for StallingOutput<O> {
    type Error = O::Error;

    fn line_count(&self) -> usize {
        self.inner.line_count()
    }

    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        self.writes += 1;
        if self.writes.is_multiple_of(self.every) {
            std::thread::sleep(self.stall);
        }
        self.inner.set_levels(changes)
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        self.inner.set_all_inactive()
    }

    fn emergency_off(&self) -> std::sync::Arc<dyn EmergencyOff> {
        self.inner.emergency_off()
    }
}

fn send(requests: &mut output_thread::Requests, channel: usize, input: Input) {
    requests.send(Request { channel, input }).expect("queued");
}

/// What a channel core schedules for the inputs the output thread took, replayed in virtual
/// time: its edges and the edges it reports as missed.
struct Replay {
    want: Vec<(Nanos, Level)>,
    /// Edges reported missed, each with the number of edges written before them.
    missed: Vec<(usize, u32)>,
    /// The edges the core had scheduled after the last one written, up to the stop.
    tail: u32,
}

/// Replays channel `cfg`'s run on a core in virtual time: `duty` from the start, enabled at
/// `enable_at`, 70 % from the period that begins at `change_at`, polled at each deadline up to
/// `last`, the last edge written, then counting what it schedules up to the stop at `end`. The thread tells its core when each edge really reached the line (a late edge moves
/// the next one); the replay is told the same times, from `written`. A thread woken so late
/// that two deadlines had passed takes them in one poll: the replay does the same where the
/// line never saw the edge of the first, and so keeps the core's own account of what was
/// merged.
fn replay(
    cfg: ChannelConfig,
    duty: f64,
    enable_at: Nanos,
    change_at: Option<Nanos>,
    last: Nanos,
    end: Nanos,
    written: &std::collections::HashMap<(Nanos, u8), Nanos>,
) -> Replay {
    let key = |at: Nanos, level: Level| (at, u8::from(level.is_high()));
    let mut out = Replay {
        want: Vec::new(),
        missed: Vec::new(),
        tail: 0,
    };
    let take = |core: &mut Channel, events: Vec<Event>, out: &mut Replay| {
        // The thread reports what a poll missed before the edge that poll wrote.
        let before = out.want.len();
        for e in events {
            match e {
                Event::Edge { at, level } => {
                    out.want.push((at, level));
                    if let Some(actual) = written.get(&key(at, level)) {
                        core.edge_written(*actual);
                    }
                }
                Event::Missed { edges } => out.missed.push((before, edges)),
                _ => {}
            }
        }
    };
    let mut core = Channel::new(cfg, 0);
    let mut events = Vec::new();
    core.command(0, Command::Percent(duty), &mut |e| events.push(e));
    core.set_enable(enable_at, true, &mut |e| events.push(e));
    take(&mut core, std::mem::take(&mut events), &mut out);
    let mut changed = change_at.is_none();
    while let Some(t) = core.poll_at() {
        if let Some(c) = change_at.filter(|c| !changed && t >= *c) {
            core.command(c - 1, Command::Percent(70.0), &mut |e| events.push(e));
            take(&mut core, std::mem::take(&mut events), &mut out);
            changed = true;
        }
        if t > last {
            break;
        }
        // The earliest poll whose edge the line saw (or that wrote none).
        let mut now = t;
        let (polled, events) = loop {
            let mut trial = core.clone();
            let mut events = Vec::new();
            trial.poll(now, &mut |e| events.push(e));
            let unseen = events.iter().any(|e| {
                matches!(e, Event::Edge { at, level } if !written.contains_key(&key(*at, *level)))
            });
            match trial.poll_at().filter(|next| unseen && *next <= last) {
                Some(next) => now = next,
                None => break (trial, events),
            }
        };
        core = polled;
        take(&mut core, events, &mut out);
    }
    while let Some(t) = core.poll_at().filter(|t| *t <= end) {
        core.poll(t, &mut |e| {
            out.tail += u32::from(matches!(e, Event::Edge { .. }))
        });
    }
    out
}

/// Missed edges by the number of edges written before them, those at one place added up (a
/// poll that took four deadlines at once reports four; polls that took two each, two and two).
fn by_place(missed: &[(usize, u32)]) -> Vec<(usize, u32)> {
    let mut out: Vec<(usize, u32)> = Vec::new();
    for &(at, n) in missed {
        match out.last_mut() {
            Some((place, sum)) if *place == at => *sum += n,
            _ => out.push((at, n)),
        }
    }
    out
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
    // Now and then the thread stalls past two or more deadlines (2.5 periods of channel 2).
    let (csv, mut e) = spawn_traced_on(dir.path(), "run", cfgs.clone(), |sim| StallingOutput {
        inner: sim,
        every: 25,
        stall: Duration::from_millis(25),
        writes: 0,
    });
    send(&mut e.requests, 0, Input::Command(Command::Percent(40.0)));
    send(&mut e.requests, 1, Input::Command(Command::Percent(45.0)));
    send(&mut e.requests, 0, Input::Enable(true));
    send(&mut e.requests, 1, Input::Enable(true));
    std::thread::sleep(Duration::from_millis(300));
    send(&mut e.requests, 1, Input::Command(Command::Percent(70.0)));
    std::thread::sleep(Duration::from_millis(600));
    e.handle.shutdown().unwrap();
    // No poll of the thread comes after this.
    let end = pwm_actuator::clock::monotonic_ns();

    let mut reports = Vec::new();
    while let Some(r) = e.reports.try_recv() {
        reports.push(r);
    }
    assert_eq!(e.reports.dropped(), 0);
    let rows = read_csv(&csv);
    for (ch, name) in names(2).iter().enumerate() {
        let edges: Vec<_> = rows.iter().filter(|r| &r.channel == name).skip(1).collect();
        assert!(edges.len() > 20, "{name}: {} edges", edges.len());
        // The first edge of a channel is its enable.
        let enable_at = edges[0].scheduled_ns;
        let written: std::collections::HashMap<(Nanos, u8), Nanos> = reports
            .iter()
            .filter_map(|r| match r {
                Report::Edge(e) if e.channel == ch => {
                    Some(((e.scheduled_ns, u8::from(e.level.is_high())), e.actual_ns))
                }
                _ => None,
            })
            .collect();
        // The core scheduled every edge the thread reported; the shutdown's fall, written if
        // the line was on, is not reported and comes last.
        let got: Vec<(Nanos, Level)> = edges
            .iter()
            .map(|r| (r.scheduled_ns, r.level))
            .take_while(|(at, level)| written.contains_key(&(*at, u8::from(level.is_high()))))
            .collect();
        assert!(
            edges.len() - got.len() <= 1,
            "{name}: unreported edges before the shutdown: {:?}",
            &edges[got.len()..]
        );
        let last = got.last().unwrap().0;
        // A thread stalled past two deadlines merges that pulse or break rather than write a
        // zero-width one, and reports it as Missed: as many as the core's own account.
        let mut reported_missed = Vec::new();
        let mut edges_before = 0;
        for r in &reports {
            match r {
                Report::Edge(e) if e.channel == ch => edges_before += 1,
                Report::Core {
                    channel,
                    event: Event::Missed { edges },
                } if *channel == ch => reported_missed.push((edges_before, *edges)),
                _ => {}
            }
        }
        let duty = [40.0, 45.0][ch];
        let run = if ch == 0 {
            replay(cfgs[ch], duty, enable_at, None, last, end, &written)
        } else {
            // Channel 2's duty change takes effect at a period boundary: the first one the
            // thread reached after taking the 70 % command, which its status report dates.
            // That is the period's start at which the replay, told the same, matches the trace;
            // late only if the thread was stalled past it with the command already in hand.
            // A start the thread stalled through wrote no rise (its pulse is merged and
            // counted missed), so the candidates are the rises written and the starts of the
            // periods after them, on the channel's grid.
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
            let period = cfgs[ch].period;
            let mut starts: Vec<Nanos> = got
                .iter()
                .filter(|(_, level)| level.is_high())
                .flat_map(|(at, _)| (0..4).map(move |k| at + k * period))
                .filter(|at| at + 100_000_000 >= applied && *at <= applied + 10_000_000)
                .collect();
            starts.sort_unstable();
            starts.dedup();
            let runs: Vec<Replay> = starts
                .iter()
                .map(|c| replay(cfgs[ch], duty, enable_at, Some(*c), last, end, &written))
                .collect();
            let agree = |r: &Replay| got.iter().zip(&r.want).take_while(|(g, w)| g == w).count();
            let Some(best) = runs.into_iter().max_by_key(|r| agree(r)) else {
                panic!("{name}: no period start within 100 ms of the 70 % command at {applied}")
            };
            if best.want != got {
                let k = agree(&best);
                panic!(
                    "{name}: from no period start near the 70 % command (applied at {applied}, \
                     starts tried {starts:?}) does the core's schedule match the trace: at best \
                     edge {k} differs, trace {:?}, core {:?}",
                    &got[k..got.len().min(k + 3)],
                    &best.want[k..best.want.len().min(k + 3)]
                );
            }
            best
        };
        let first_difference = got.iter().zip(&run.want).position(|(g, w)| g != w);
        assert_eq!(
            first_difference, None,
            "{name}: the trace's edge is not the core's"
        );
        assert_eq!(
            got.len(),
            run.want.len(),
            "{name}: edges the trace lacks or the core lacks"
        );
        // Merged where the core merges them, as many, in the same places; after the last edge
        // written, no more than the core had scheduled before the stop.
        let (reported, after): (Vec<_>, Vec<_>) = reported_missed
            .into_iter()
            .partition(|(place, _)| *place < got.len());
        assert_eq!(
            by_place(&run.missed),
            by_place(&reported),
            "{name}: merged edges are the reported ones"
        );
        assert!(
            !reported.is_empty(),
            "{name}: the stalls merged no edge: nothing above was put to the test"
        );
        let after: u32 = after.iter().map(|(_, n)| n).sum();
        assert!(
            after <= run.tail,
            "{name}: {after} edges reported missed after the last one written, of {} scheduled",
            run.tail
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
