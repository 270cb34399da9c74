//! The simulated sink: an [`Output`] with no hardware behind it that records every edge with
//! its actual and scheduled time, and optionally writes the trace as VCD and CSV files.
//!
//! Threading: [`SimOutput::set_levels`] runs on the real-time output thread. It does no file
//! I/O and no allocation: it stores the levels in atomics and pushes records into preallocated
//! buffers under a mutex that other threads hold only for O(1) work (a buffer swap or a copy of
//! the bounded in-memory history), never across file I/O. File writing happens on a background
//! thread (only when a trace is configured) that swaps the buffer every [`WRITER_PERIOD`], and
//! in [`SimOutput::flush`]. The sink must not decide timing: it writes what it is told.

use super::panic_off::{lock_bounded, lock_ignore_poison as lock, warn, EMERGENCY_LOCK_BUDGET};
use super::trace::{validate_channel_names, EdgeRecord, TraceError, TraceSpec, TraceWriter};
use super::trace_files::{TraceHealth, TraceLimit};
use super::{EmergencyOff, LineChange, Output};
use crate::clock::monotonic_ns;
use crate::core::Level;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::Duration;

/// How often the background writer moves buffered records to the trace files.
pub const WRITER_PERIOD: Duration = Duration::from_millis(50);

/// Number of most recent edges kept in memory for inspection ([`SimProbe::recent_edges`]).
pub const RECENT_CAPACITY: usize = 4096;

/// Minimum capacity of the buffer between the output thread and the trace writer, in records.
/// At one swap per [`WRITER_PERIOD`] this holds 80 000 edges/s; edges beyond it are counted and
/// reported by [`SimOutput::flush`] as [`TraceError::Overflow`].
pub const PENDING_MIN_CAPACITY: usize = 4096;

/// Records shared between the output thread (producer) and the readers.
struct Recorder {
    /// Records not yet written to the trace files; only filled when a trace is configured.
    pending: Vec<EdgeRecord>,
    /// Capacity of `pending` (never exceeded, so pushing never allocates).
    pending_cap: usize,
    tracing: bool,
    /// The last [`RECENT_CAPACITY`] edges (preallocated ring).
    recent: VecDeque<EdgeRecord>,
}

impl Recorder {
    /// Returns `false` when the record could not be queued for the trace (buffer full).
    fn push(&mut self, rec: EdgeRecord) -> bool {
        if self.recent.len() == RECENT_CAPACITY {
            self.recent.pop_front();
        }
        self.recent.push_back(rec);
        if !self.tracing {
            return true;
        }
        if self.pending.len() < self.pending_cap {
            self.pending.push(rec);
            true
        } else {
            false
        }
    }
}

/// The trace side, used only off the output thread.
struct TraceIo {
    /// `None` once the trace is finished (the sink was dropped).
    writer: Option<TraceWriter>,
    /// The second buffer, swapped with [`Recorder::pending`].
    spare: Vec<EdgeRecord>,
    /// First write error not yet reported by a flush.
    error: Option<TraceError>,
    /// Dropped-record count already reported.
    reported_dropped: u64,
}

struct SimShared {
    levels: Box<[AtomicBool]>,
    edges: AtomicU64,
    dropped: AtomicU64,
    /// Set by the emergency handle: from then on the sink refuses to record anything but
    /// inactive levels, so a racing output thread cannot switch a line back on.
    tripped: AtomicBool,
    rec: Mutex<Recorder>,
    /// Lock order: `io` before `rec`.
    io: Option<Mutex<TraceIo>>,
}

impl SimShared {
    fn apply(&self, rec: &mut Recorder, changes: &[LineChange]) {
        // Checked under the `rec` lock: the emergency handle sets `tripped` before taking it,
        // so once it has driven the lines inactive no later write gets through.
        if self.tripped.load(Ordering::SeqCst) {
            return;
        }
        // Read once per call under the lock: records are in time order in the buffer.
        let now = monotonic_ns();
        for c in changes {
            // The output thread only hands bound lines; anything else is ignored, never a panic.
            let Some(level) = self.levels.get(c.line) else {
                continue;
            };
            level.store(c.level.is_high(), Ordering::SeqCst);
            self.record(
                rec,
                EdgeRecord {
                    t_ns: now,
                    channel: c.line,
                    level: c.level,
                    scheduled_ns: c.scheduled_ns,
                },
            );
        }
    }

    fn record(&self, rec: &mut Recorder, r: EdgeRecord) {
        self.edges.fetch_add(1, Ordering::Relaxed);
        if !rec.push(r) {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Drives every line inactive, recording an edge (scheduled = now) for each line that was
    /// active. With `rec == None` (lock not obtained) the levels still go inactive but the
    /// edges are not recorded.
    fn all_inactive(&self, mut rec: Option<&mut Recorder>) {
        let now = monotonic_ns();
        for (i, level) in self.levels.iter().enumerate() {
            if level.swap(false, Ordering::SeqCst) {
                if let Some(rec) = rec.as_deref_mut() {
                    self.record(
                        rec,
                        EdgeRecord {
                            t_ns: now,
                            channel: i,
                            level: Level::Low,
                            scheduled_ns: now,
                        },
                    );
                }
            }
        }
    }

    /// Moves pending records to the trace files and flushes them. `lock_rec` takes the `rec`
    /// lock (blocking or bounded); when it fails nothing is moved.
    fn drain<'a>(
        &'a self,
        io: &mut TraceIo,
        lock_rec: impl FnOnce(&'a Mutex<Recorder>) -> Option<MutexGuard<'a, Recorder>>,
    ) {
        let Some(writer) = io.writer.as_mut() else {
            return;
        };
        if let Some(mut rec) = lock_rec(&self.rec) {
            std::mem::swap(&mut rec.pending, &mut io.spare);
        }
        let written = writer.write_records(&io.spare);
        io.spare.clear();
        let flushed = writer.flush();
        if let Err(e) = written.and(flushed) {
            io.error.get_or_insert(e);
        }
        let dropped = self.dropped.load(Ordering::Relaxed);
        if dropped > io.reported_dropped {
            writer.lost_before(dropped - io.reported_dropped);
            io.reported_dropped = dropped;
            io.error.get_or_insert(TraceError::Overflow { dropped });
        }
    }

    /// Drains synchronously and reports the first error not yet reported.
    fn flush(&self) -> Result<(), TraceError> {
        let Some(io) = &self.io else {
            return Ok(());
        };
        let mut io = lock(io);
        self.drain(&mut io, |m| Some(lock(m)));
        io.error.take().map_or(Ok(()), Err)
    }

    fn levels(&self) -> Vec<Level> {
        self.levels
            .iter()
            .map(|l| Level::from_bool(l.load(Ordering::SeqCst)))
            .collect()
    }
}

/// The background writer thread; stopped by dropping `stop`.
struct WriterThread {
    stop: mpsc::Sender<()>,
    join: JoinHandle<()>,
}

fn writer_loop(shared: Arc<SimShared>, stop: mpsc::Receiver<()>) {
    let Some(io) = &shared.io else {
        return;
    };
    loop {
        match stop.recv_timeout(WRITER_PERIOD) {
            Err(RecvTimeoutError::Timeout) => {
                let mut io = lock(io);
                shared.drain(&mut io, |m| Some(lock(m)));
                // Deleted files, full file systems, failed files' retries: here only, never
                // in a drain the emergency handle runs.
                if let Some(writer) = io.writer.as_mut() {
                    writer.check(monotonic_ns());
                }
            }
            Ok(()) | Err(RecvTimeoutError::Disconnected) => return,
        }
    }
}

/// Simulated output lines: records every edge, optionally traces them to VCD/CSV files.
///
/// Dropping it drives every line inactive (recorded), stops the writer thread and finishes the
/// trace files.
pub struct SimOutput {
    shared: Arc<SimShared>,
    writer: Option<WriterThread>,
}

impl SimOutput {
    /// Creates the sink for the channels `channel_names` (index = line), all inactive, with the
    /// trace files of `trace` created and their headers written now (start time = now).
    ///
    /// Errors: a channel name unusable in a trace, a trace file that cannot be created, or the
    /// writer thread that cannot be started.
    pub fn new(
        channel_names: Vec<String>,
        trace: Option<TraceSpec>,
    ) -> Result<SimOutput, TraceError> {
        SimOutput::traced(
            channel_names,
            trace,
            TraceLimit::default(),
            &TraceHealth::new(),
        )
    }

    /// [`SimOutput::new`] with each trace file keeping to `limit` and its state told in
    /// `health` (see [`TraceWriter::create_watched`]).
    pub fn traced(
        channel_names: Vec<String>,
        trace: Option<TraceSpec>,
        limit: TraceLimit,
        health: &TraceHealth,
    ) -> Result<SimOutput, TraceError> {
        validate_channel_names(&channel_names)?;
        let writer = match trace.filter(|t| !t.is_empty()) {
            Some(spec) => Some(TraceWriter::create_watched(
                &spec,
                &channel_names,
                monotonic_ns(),
                limit,
                health,
            )?),
            None => None,
        };
        SimOutput::with_trace_writer(channel_names, writer)
    }

    /// Like [`SimOutput::new`] with a trace writer already created (for the same channel
    /// names, in the same order), e.g. on other outputs than files.
    pub fn with_trace_writer(
        channel_names: Vec<String>,
        writer: Option<TraceWriter>,
    ) -> Result<SimOutput, TraceError> {
        validate_channel_names(&channel_names)?;
        let pending_cap = PENDING_MIN_CAPACITY.max(256 * channel_names.len());
        let io = writer.map(|writer| {
            Mutex::new(TraceIo {
                writer: Some(writer),
                spare: Vec::with_capacity(pending_cap),
                error: None,
                reported_dropped: 0,
            })
        });
        let tracing = io.is_some();
        let shared = Arc::new(SimShared {
            levels: channel_names
                .iter()
                .map(|_| AtomicBool::new(false))
                .collect(),
            edges: AtomicU64::new(0),
            dropped: AtomicU64::new(0),
            tripped: AtomicBool::new(false),
            rec: Mutex::new(Recorder {
                pending: Vec::with_capacity(if tracing { pending_cap } else { 0 }),
                pending_cap,
                tracing,
                recent: VecDeque::with_capacity(RECENT_CAPACITY),
            }),
            io,
        });
        let writer = if tracing {
            let (stop, rx) = mpsc::channel();
            let s = Arc::clone(&shared);
            let join = std::thread::Builder::new()
                .name("pwm-trace".into())
                .spawn(move || writer_loop(s, rx))
                .map_err(TraceError::Spawn)?;
            Some(WriterThread { stop, join })
        } else {
            None
        };
        Ok(SimOutput { shared, writer })
    }

    /// The current logical level of every line (index = line).
    pub fn levels(&self) -> Vec<Level> {
        self.shared.levels()
    }

    /// A handle for inspecting the sink from other threads (tests, benchmarks).
    pub fn probe(&self) -> SimProbe {
        SimProbe {
            shared: Arc::clone(&self.shared),
        }
    }

    /// Writes every record so far to the trace files and flushes them. Returns the first trace
    /// error not yet reported (write failure, or [`TraceError::Overflow`]); `Ok` without trace.
    pub fn flush(&self) -> Result<(), TraceError> {
        self.shared.flush()
    }
}

impl Output for SimOutput {
    type Error = std::convert::Infallible;

    fn line_count(&self) -> usize {
        self.shared.levels.len()
    }

    /// Records the changes with the actual time read now. Lines out of range are ignored; after
    /// the emergency handle ran, nothing is recorded.
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        let mut rec = lock(&self.shared.rec);
        self.shared.apply(&mut rec, changes);
        Ok(())
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        let mut rec = lock(&self.shared.rec);
        self.shared.all_inactive(Some(&mut rec));
        Ok(())
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(SimEmergencyOff {
            shared: Arc::clone(&self.shared),
        })
    }
}

impl Drop for SimOutput {
    fn drop(&mut self) {
        {
            let mut rec = lock(&self.shared.rec);
            self.shared.all_inactive(Some(&mut rec));
        }
        if let Some(w) = self.writer.take() {
            drop(w.stop);
            if w.join.join().is_err() {
                warn(format_args!("sim output: the trace writer thread panicked"));
            }
        }
        if let Some(io) = &self.shared.io {
            let mut io = lock(io);
            self.shared.drain(&mut io, |m| Some(lock(m)));
            if let Some(mut writer) = io.writer.take() {
                if let Err(e) = writer.finish(monotonic_ns()) {
                    io.error.get_or_insert(e);
                }
            }
            if let Some(e) = io.error.take() {
                warn(format_args!("sim output: {}", e.said()));
            }
        }
    }
}

/// The emergency handle of a [`SimOutput`].
///
/// Safe in a panic hook: it never calls a blocking lock (only `try_lock` for at most
/// [`EMERGENCY_LOCK_BUDGET`] per lock, which also covers a lock held by the panicking thread
/// itself), ignores poisoning, drives the levels through atomics that need no lock, and reports
/// problems on stderr without panicking.
struct SimEmergencyOff {
    shared: Arc<SimShared>,
}

impl EmergencyOff for SimEmergencyOff {
    fn all_inactive(&self) {
        let s = &self.shared;
        s.tripped.store(true, Ordering::SeqCst);
        match lock_bounded(&s.rec, EMERGENCY_LOCK_BUDGET) {
            Some(mut rec) => s.all_inactive(Some(&mut rec)),
            None => {
                s.all_inactive(None);
                warn(format_args!(
                    "sim output: emergency off: record lock busy, edges to inactive not recorded"
                ));
            }
        }
        let Some(io) = &s.io else {
            return;
        };
        match lock_bounded(io, EMERGENCY_LOCK_BUDGET) {
            Some(mut io) => {
                s.drain(&mut io, |m| lock_bounded(m, EMERGENCY_LOCK_BUDGET));
                if let Some(e) = io.error.take() {
                    warn(format_args!("sim output: emergency off: {}", e.said()));
                }
            }
            None => warn(format_args!(
                "sim output: emergency off: trace writer busy, trace files not flushed"
            )),
        }
    }
}

/// A clonable, thread-safe view of a [`SimOutput`] for tests and benchmarks.
#[derive(Clone)]
pub struct SimProbe {
    shared: Arc<SimShared>,
}

impl SimProbe {
    /// The current logical level of every line (index = line).
    pub fn levels(&self) -> Vec<Level> {
        self.shared.levels()
    }

    /// Number of edges recorded since creation (every change handed to the sink, plus the
    /// inactive edges of shutdown and emergency off).
    pub fn edge_count(&self) -> u64 {
        self.shared.edges.load(Ordering::Relaxed)
    }

    /// The last [`RECENT_CAPACITY`] edges, oldest first.
    pub fn recent_edges(&self) -> Vec<EdgeRecord> {
        lock(&self.shared.rec).recent.iter().copied().collect()
    }

    /// Edges that could not be queued for the trace files because the buffer was full.
    pub fn dropped_records(&self) -> u64 {
        self.shared.dropped.load(Ordering::Relaxed)
    }

    /// `true` once the emergency handle has run (the sink then records nothing active).
    pub fn is_tripped(&self) -> bool {
        self.shared.tripped.load(Ordering::SeqCst)
    }

    /// Same as [`SimOutput::flush`].
    pub fn flush(&self) -> Result<(), TraceError> {
        self.shared.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Nanos;
    use std::path::PathBuf;
    use std::time::Instant;

    fn names() -> Vec<String> {
        vec!["pw01".into(), "pw02".into()]
    }

    fn change(line: usize, high: bool, scheduled_ns: Nanos) -> LineChange {
        LineChange {
            line,
            level: Level::from_bool(high),
            scheduled_ns,
        }
    }

    fn tmp_dir() -> tempfile::TempDir {
        tempfile::tempdir().unwrap()
    }

    /// A simulated output of [`names`] traced to `paths`.
    fn traced(paths: &[PathBuf]) -> SimOutput {
        SimOutput::new(names(), Some(TraceSpec::from_paths(paths).unwrap())).unwrap()
    }

    /// CSV rows after the header as (t_ns, channel, level, scheduled_ns).
    fn csv_rows(path: &std::path::Path) -> Vec<(u64, String, u8, u64)> {
        let text = std::fs::read_to_string(path).unwrap();
        crate::output::read_csv(&text)
            .unwrap()
            .into_iter()
            .map(|r| {
                (
                    r.t_ns,
                    r.channel,
                    u8::from(r.level.is_high()),
                    r.scheduled_ns,
                )
            })
            .collect()
    }

    #[test]
    fn records_levels_edges_and_times() {
        let mut out = SimOutput::new(names(), None).unwrap();
        let probe = out.probe();
        assert_eq!(out.line_count(), 2);
        assert_eq!(out.levels(), [Level::Low, Level::Low]);
        let before = monotonic_ns();
        out.set_levels(&[change(0, true, 111), change(1, true, 222)])
            .unwrap();
        let after = monotonic_ns();
        assert_eq!(probe.levels(), [Level::High, Level::High]);
        out.set_levels(&[change(1, false, 333)]).unwrap();
        assert_eq!(out.levels(), [Level::High, Level::Low]);
        assert_eq!(probe.edge_count(), 3);
        let e = probe.recent_edges();
        assert_eq!(e.len(), 3);
        assert_eq!(
            (e[0].channel, e[0].level, e[0].scheduled_ns),
            (0, Level::High, 111)
        );
        assert_eq!(
            (e[1].channel, e[1].level, e[1].scheduled_ns),
            (1, Level::High, 222)
        );
        assert_eq!(
            (e[2].channel, e[2].level, e[2].scheduled_ns),
            (1, Level::Low, 333)
        );
        assert!(before <= e[0].t_ns && e[0].t_ns <= after);
        assert_eq!(e[0].t_ns, e[1].t_ns, "one call, one time");
        assert!(e[2].t_ns >= e[1].t_ns);
    }

    #[test]
    fn out_of_range_lines_are_ignored() {
        let mut out = SimOutput::new(names(), None).unwrap();
        out.set_levels(&[change(5, true, 1), change(0, true, 2)])
            .unwrap();
        assert_eq!(out.levels(), [Level::High, Level::Low]);
        assert_eq!(out.probe().edge_count(), 1);
    }

    #[test]
    fn set_all_inactive_records_only_real_changes() {
        let mut out = SimOutput::new(names(), None).unwrap();
        let probe = out.probe();
        out.set_levels(&[change(1, true, 5)]).unwrap();
        out.set_all_inactive().unwrap();
        assert_eq!(probe.levels(), [Level::Low, Level::Low]);
        let e = probe.recent_edges();
        assert_eq!(e.len(), 2);
        assert_eq!((e[1].channel, e[1].level), (1, Level::Low));
        assert_eq!(e[1].scheduled_ns, e[1].t_ns);
    }

    #[test]
    fn recent_history_is_bounded() {
        let mut out = SimOutput::new(names(), None).unwrap();
        let n = RECENT_CAPACITY + 10;
        for i in 0..n {
            out.set_levels(&[change(0, i % 2 == 0, i as Nanos)])
                .unwrap();
        }
        let probe = out.probe();
        let e = probe.recent_edges();
        assert_eq!(e.len(), RECENT_CAPACITY);
        assert_eq!(e[0].scheduled_ns, 10);
        assert_eq!(e.last().unwrap().scheduled_ns, (n - 1) as Nanos);
        assert_eq!(probe.edge_count(), n as u64);
    }

    #[test]
    fn traces_to_csv_and_vcd_and_flushes_on_demand() {
        let dir = tmp_dir();
        let csv = dir.path().join("t.csv");
        let vcd = dir.path().join("t.vcd");
        let mut out = traced(&[csv.clone(), vcd.clone()]);
        out.set_levels(&[change(0, true, 10)]).unwrap();
        out.set_levels(&[change(0, false, 20), change(1, true, 20)])
            .unwrap();
        out.flush().unwrap();
        let rows = csv_rows(&csv);
        assert_eq!(rows.len(), 5);
        let start = rows[0].0;
        assert_eq!(rows[0], (start, "pw01".into(), 0, start));
        assert_eq!(rows[1], (start, "pw02".into(), 0, start));
        assert_eq!(
            (&rows[2].1, rows[2].2, rows[2].3),
            (&"pw01".to_string(), 1, 10)
        );
        assert_eq!(
            (&rows[3].1, rows[3].2, rows[3].3),
            (&"pw01".to_string(), 0, 20)
        );
        assert_eq!(
            (&rows[4].1, rows[4].2, rows[4].3),
            (&"pw02".to_string(), 1, 20)
        );
        assert!(rows[2].0 >= start && rows[3].0 >= rows[2].0 && rows[4].0 == rows[3].0);
        let vcd_text = std::fs::read_to_string(&vcd).unwrap();
        assert!(vcd_text.contains("$var wire 1 ! pw01 $end"));
        assert!(vcd_text.ends_with("1\"\n"), "{vcd_text}");

        // Dropping drives pw02 inactive, records it and finishes the files.
        drop(out);
        let rows = csv_rows(&csv);
        assert_eq!(rows.len(), 6);
        assert_eq!((&rows[5].1, rows[5].2), (&"pw02".to_string(), 0));
        let vcd_text = std::fs::read_to_string(&vcd).unwrap();
        let tail: Vec<&str> = vcd_text.lines().rev().take(2).collect();
        assert!(tail[0].starts_with('#'), "final time marker: {vcd_text}");
    }

    #[test]
    fn background_writer_writes_without_flush() {
        let dir = tmp_dir();
        let csv = dir.path().join("bg.csv");
        let mut out = traced(std::slice::from_ref(&csv));
        out.set_levels(&[change(1, true, 42)]).unwrap();
        // Wide margin: the writer runs every 50 ms; allow 10 s on a loaded machine.
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if csv_rows(&csv).len() == 3 {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "writer thread never wrote the edge"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        assert_eq!(csv_rows(&csv)[2].3, 42);
        drop(out);
    }

    #[test]
    fn emergency_off_drives_inactive_records_flushes_and_latches() {
        let dir = tmp_dir();
        let csv = dir.path().join("e.csv");
        let mut out = traced(std::slice::from_ref(&csv));
        let probe = out.probe();
        out.set_levels(&[change(0, true, 1), change(1, true, 1)])
            .unwrap();
        let off = out.emergency_off();
        off.all_inactive();
        assert_eq!(probe.levels(), [Level::Low, Level::Low]);
        assert!(probe.is_tripped());
        // Flushed synchronously: the inactive edges are in the file now.
        let rows = csv_rows(&csv);
        assert_eq!(rows.len(), 6, "{rows:?}");
        assert_eq!((rows[4].2, rows[5].2), (0, 0));
        assert_eq!(rows[4].0, rows[4].3, "scheduled = now");
        // Latched: a racing output thread cannot switch a line back on.
        out.set_levels(&[change(0, true, 2)]).unwrap();
        assert_eq!(probe.levels(), [Level::Low, Level::Low]);
        assert_eq!(probe.edge_count(), 4);
        // Running it twice is harmless.
        off.all_inactive();
        assert_eq!(probe.edge_count(), 4);
        drop(out);
        assert_eq!(csv_rows(&csv).len(), 6);
    }

    /// An output of [`names`] with `line` switched on, and its probe.
    fn with_line_on(line: usize) -> (SimOutput, SimProbe) {
        let mut out = SimOutput::new(names(), None).unwrap();
        out.set_levels(&[change(line, true, 1)]).unwrap();
        let probe = out.probe();
        (out, probe)
    }

    #[test]
    fn emergency_off_does_not_deadlock_on_a_held_lock() {
        let (out, probe) = with_line_on(0);
        let off = out.emergency_off();
        // As if the panicking thread held the record lock.
        let guard = lock(&probe.shared.rec);
        off.all_inactive();
        drop(guard);
        assert_eq!(probe.levels(), [Level::Low, Level::Low]);
    }

    #[test]
    fn emergency_off_works_on_a_poisoned_lock() {
        let (out, probe) = with_line_on(1);
        let p2 = probe.clone();
        let _ = std::thread::spawn(move || {
            let _g = p2.shared.rec.lock();
            panic!("poison the record lock (expected in this test)");
        })
        .join();
        assert!(probe.shared.rec.is_poisoned());
        out.emergency_off().all_inactive();
        assert_eq!(probe.levels(), [Level::Low, Level::Low]);
        assert_eq!(probe.recent_edges().last().unwrap().level, Level::Low);
    }

    /// Accepts `room` bytes, then fails every write.
    struct FailingAfter {
        room: usize,
    }

    impl std::io::Write for FailingAfter {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            if buf.len() > self.room {
                return Err(std::io::Error::other("device full (test)"));
            }
            self.room -= buf.len();
            Ok(buf.len())
        }

        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn flush_reports_write_errors_once_and_keeps_recording() {
        use crate::output::trace::{TraceFormat, TraceOut};
        let writer = TraceWriter::from_writers(
            vec![(
                PathBuf::from("failing.csv"),
                TraceFormat::Csv,
                Box::new(FailingAfter { room: 4096 }) as TraceOut,
            )],
            &names(),
            0,
        )
        .unwrap();
        let mut out = SimOutput::with_trace_writer(names(), Some(writer)).unwrap();
        // 4096 bytes hold about 150 rows: write more than that.
        for i in 0..400u64 {
            out.set_levels(&[change(0, i % 2 == 0, i)]).unwrap();
        }
        let err = out.flush().unwrap_err();
        assert!(matches!(err, TraceError::Write { .. }), "{err}");
        assert!(err.to_string().contains("failing.csv"), "{err}");
        assert!(out.flush().is_ok(), "reported once");
        // Edges are still recorded in memory and levels still follow.
        out.set_levels(&[change(1, true, 500)]).unwrap();
        assert!(out.flush().is_ok());
        assert_eq!(out.probe().edge_count(), 401);
        assert_eq!(out.levels(), [Level::Low, Level::High]);
    }
}
