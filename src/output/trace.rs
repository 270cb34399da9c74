//! Trace files of the simulated sink: every edge with its actual and scheduled time, as CSV and
//! as IEEE 1364 VCD (viewable in GTKWave or Surfer). A trace spec may also name MCAP files
//! (`.mcap`): those are written by the ROS side from what the node publishes, not here.
//!
//! Writers here do buffered file I/O and allocate: they must never run on the output thread.
//! Each trace keeps to a size limit by rotation, and says what it has come to (written, full,
//! failing, its file deleted) through a [`TraceHealth`] (see [`super::trace_files`]).
//! The simulated sink ([`super::sim`]) hands them records from a background thread or from an
//! explicit flush.

pub use super::trace_files::TraceFormat;
use super::trace_files::{
    self, Counted, TraceHealth, TraceLimit, TraceSlot, TraceState, CHECK_PERIOD_NS,
    RETRY_PERIOD_NS, TRACE_FILES,
};
use crate::core::{Level, Nanos};
use std::collections::HashSet;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::PathBuf;

/// Module name of the VCD scope holding one wire per channel.
pub const VCD_SCOPE: &str = "pwm_actuator";

/// Header line of the CSV trace.
pub const CSV_HEADER: &str = "t_ns,channel,level,scheduled_ns";

/// Errors of the trace layer.
#[derive(Debug, thiserror::Error)]
pub enum TraceError {
    /// A trace path has an extension other than `.vcd`, `.csv` or `.mcap`.
    #[error("trace file {path}: unknown extension, expected .vcd, .csv or .mcap")]
    UnknownExtension {
        /// The offending path.
        path: PathBuf,
    },
    /// The same trace path was given twice (two writers would garble the file).
    #[error("trace file {path} is given twice")]
    DuplicatePath {
        /// The repeated path.
        path: PathBuf,
    },
    /// A channel name cannot be written to a trace (empty, whitespace, control characters,
    /// `,` or `"`).
    #[error("channel name {name:?} cannot be used in a trace: it must be non-empty printable ASCII without spaces, commas or quotes")]
    InvalidChannelName {
        /// The offending name.
        name: String,
    },
    /// Two channels have the same name: their records could not be told apart.
    #[error("channel name {name:?} is used twice")]
    DuplicateChannelName {
        /// The repeated name.
        name: String,
    },
    /// A record names a channel index that the trace was not created with.
    #[error("edge record for channel index {channel}, but the trace has {count} channels")]
    UnknownChannel {
        /// The record's channel index.
        channel: usize,
        /// Number of channels of the trace.
        count: usize,
    },
    /// A trace file could not be created.
    #[error("cannot create trace file {path}")]
    Create {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// Writing or flushing a trace file failed; later records are not written to that file.
    #[error("cannot write trace file {path}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// Records were lost because the trace buffer was full when an edge happened.
    #[error("{dropped} edge records were not traced: the trace buffer was full")]
    Overflow {
        /// Records lost so far (total since start).
        dropped: u64,
    },
    /// The background trace writer thread could not be started.
    #[error("cannot start the trace writer thread")]
    Spawn(#[source] io::Error),
}

impl TraceError {
    /// The error in the node's own words, for the log: a file that cannot be created or
    /// written is named, and why is said in [`trace_files::io_reason`]'s words (not the
    /// system's text).
    pub fn said(&self) -> String {
        match self {
            TraceError::Create { path, source } => format!(
                "cannot create trace file {}: {}",
                path.display(),
                trace_files::io_reason(source)
            ),
            TraceError::Write { path, source } => format!(
                "cannot write trace file {}: {}",
                path.display(),
                trace_files::io_reason(source)
            ),
            other => other.to_string(),
        }
    }
}

/// One trace file to write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TraceFile {
    /// Where to write it (created or truncated at start).
    pub path: PathBuf,
    /// What to write.
    pub format: TraceFormat,
}

/// The set of trace files of a run (any number, any mix of VCD, CSV and MCAP).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct TraceSpec {
    files: Vec<TraceFile>,
}

impl TraceSpec {
    /// Builds the spec from paths ending in `.vcd`, `.csv` or `.mcap` (case-insensitive). Any other
    /// extension, or a path given twice, is an error naming the path. An empty slice gives an
    /// empty spec (no trace).
    pub fn from_paths(paths: &[PathBuf]) -> Result<TraceSpec, TraceError> {
        let mut files: Vec<TraceFile> = Vec::with_capacity(paths.len());
        for path in paths {
            let format = TraceFormat::from_path(path)
                .ok_or_else(|| TraceError::UnknownExtension { path: path.clone() })?;
            if files.iter().any(|f| f.path == *path) {
                return Err(TraceError::DuplicatePath { path: path.clone() });
            }
            files.push(TraceFile {
                path: path.clone(),
                format,
            });
        }
        Ok(TraceSpec { files })
    }

    /// The files, in the order given.
    pub fn files(&self) -> &[TraceFile] {
        &self.files
    }

    /// `true` when no file is to be written.
    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }

    /// The files of one format, in the order given.
    pub fn of_format(&self, format: TraceFormat) -> Vec<PathBuf> {
        self.files
            .iter()
            .filter(|f| f.format == format)
            .map(|f| f.path.clone())
            .collect()
    }

    /// The files the output side writes: the VCD and CSV ones (MCAP files are the ROS side's).
    pub fn line_traces(&self) -> TraceSpec {
        TraceSpec {
            files: self
                .files
                .iter()
                .filter(|f| f.format != TraceFormat::Mcap)
                .cloned()
                .collect(),
        }
    }
}

/// One edge as traced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EdgeRecord {
    /// When the level was actually written, monotonic ns.
    pub t_ns: Nanos,
    /// Channel (line) index, 0 = first channel.
    pub channel: usize,
    /// The new logical level.
    pub level: Level,
    /// When the core scheduled the edge, monotonic ns.
    pub scheduled_ns: Nanos,
}

/// One row of a CSV trace as read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CsvRow {
    /// When the level was actually written, monotonic ns.
    pub t_ns: Nanos,
    /// Channel name, e.g. `pw01`.
    pub channel: String,
    /// The new logical level.
    pub level: Level,
    /// When the core scheduled the edge, monotonic ns.
    pub scheduled_ns: Nanos,
}

/// Why a CSV trace could not be read back.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CsvReadError {
    /// The first line is not [`CSV_HEADER`].
    #[error("not a pwm_actuator CSV trace: the header is not `{CSV_HEADER}`")]
    Header,
    /// A row that is not `t_ns,channel,level,scheduled_ns`.
    #[error("line {line}: not a trace row")]
    Row {
        /// 1-based line number.
        line: usize,
    },
}

/// Reads a CSV trace back: every complete row after the header. A last line without its
/// newline (a trace still being written) is left out.
pub fn read_csv(text: &str) -> Result<Vec<CsvRow>, CsvReadError> {
    let mut lines: Vec<&str> = text.split('\n').collect();
    // The element after the last newline is empty, or an incomplete row.
    lines.pop();
    let mut it = lines.into_iter().enumerate();
    match it.next() {
        Some((_, h)) if h == CSV_HEADER => {}
        _ => return Err(CsvReadError::Header),
    }
    it.map(|(i, l)| {
        let f: Vec<&str> = l.split(',').collect();
        let row = || -> Option<CsvRow> {
            if f.len() != 4 {
                return None;
            }
            Some(CsvRow {
                t_ns: f[0].parse().ok()?,
                channel: f[1].to_string(),
                level: match f[2] {
                    "0" => Level::Low,
                    "1" => Level::High,
                    _ => return None,
                },
                scheduled_ns: f[3].parse().ok()?,
            })
        };
        row().ok_or(CsvReadError::Row { line: i + 1 })
    })
    .collect()
}

/// Checks that channel names can be written to CSV and VCD unquoted and are unique.
pub fn validate_channel_names(names: &[String]) -> Result<(), TraceError> {
    let mut seen = HashSet::with_capacity(names.len());
    for name in names {
        let ok = !name.is_empty()
            && name
                .bytes()
                .all(|b| b.is_ascii_graphic() && b != b',' && b != b'"');
        if !ok {
            return Err(TraceError::InvalidChannelName { name: name.clone() });
        }
        if !seen.insert(name.as_str()) {
            return Err(TraceError::DuplicateChannelName { name: name.clone() });
        }
    }
    Ok(())
}

fn level_digit(level: Level) -> char {
    if level.is_high() {
        '1'
    } else {
        '0'
    }
}

fn unknown_channel(channel: usize, count: usize) -> io::Error {
    io::Error::new(
        io::ErrorKind::InvalidInput,
        TraceError::UnknownChannel { channel, count },
    )
}

/// CSV trace writer: header [`CSV_HEADER`], one row per edge, absolute monotonic ns, the channel
/// written by name and the level as 0/1 (logical).
#[derive(Debug)]
pub struct CsvTrace<W: Write> {
    out: W,
    names: Vec<String>,
}

impl<W: Write> CsvTrace<W> {
    /// Writes the header and one row per channel at `start_ns` with level 0 (every output starts
    /// inactive). Names must have passed [`validate_channel_names`].
    pub fn new(out: W, names: &[String], start_ns: Nanos) -> io::Result<CsvTrace<W>> {
        CsvTrace::with_levels(out, names, start_ns, &[])
    }

    /// [`CsvTrace::new`] with the channels at `levels` (index = channel; a channel beyond
    /// them at 0): the file a trace goes on in after a rotation.
    pub fn with_levels(
        mut out: W,
        names: &[String],
        start_ns: Nanos,
        levels: &[Level],
    ) -> io::Result<CsvTrace<W>> {
        writeln!(out, "{CSV_HEADER}")?;
        for (i, name) in names.iter().enumerate() {
            let level = level_digit(levels.get(i).copied().unwrap_or(Level::Low));
            writeln!(out, "{start_ns},{name},{level},{start_ns}")?;
        }
        Ok(CsvTrace {
            out,
            names: names.to_vec(),
        })
    }

    /// Appends one edge row.
    pub fn record(&mut self, rec: &EdgeRecord) -> io::Result<()> {
        let name = self
            .names
            .get(rec.channel)
            .ok_or_else(|| unknown_channel(rec.channel, self.names.len()))?;
        writeln!(
            self.out,
            "{},{},{},{}",
            rec.t_ns,
            name,
            level_digit(rec.level),
            rec.scheduled_ns
        )
    }

    /// Flushes buffered rows to the underlying writer.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// The underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

/// The VCD identifier code of wire `index`: printable ASCII `!`..`~` in base 94, shortest first
/// (`!`, `"`, ... `~`, `!!`, `"!`, ...).
pub fn vcd_id(index: usize) -> String {
    const FIRST: u8 = b'!';
    const RADIX: usize = (b'~' - b'!' + 1) as usize;
    let mut id = String::new();
    let mut n = index;
    loop {
        id.push((FIRST + (n % RADIX) as u8) as char);
        n /= RADIX;
        if n == 0 {
            break;
        }
        n -= 1;
    }
    id
}

/// VCD trace writer: `$timescale 1ns`, one 1-bit wire per channel in scope [`VCD_SCOPE`],
/// `$dumpvars` all 0 at `#0`, times relative to the start time.
///
/// Times written never decrease: a record older than the last written time (or than the start)
/// is written at the last time, because VCD readers reject time going backwards.
#[derive(Debug)]
pub struct VcdTrace<W: Write> {
    out: W,
    ids: Vec<String>,
    start_ns: Nanos,
    last_t: Nanos,
}

impl<W: Write> VcdTrace<W> {
    /// Writes the header, the definitions and the initial all-0 dump at `#0` (= `start_ns`).
    /// Names must have passed [`validate_channel_names`].
    pub fn new(out: W, names: &[String], start_ns: Nanos) -> io::Result<VcdTrace<W>> {
        VcdTrace::with_levels(out, names, start_ns, &[])
    }

    /// [`VcdTrace::new`] with the channels at `levels` in the initial dump (index = channel;
    /// a channel beyond them at 0): the file a trace goes on in after a rotation.
    pub fn with_levels(
        mut out: W,
        names: &[String],
        start_ns: Nanos,
        levels: &[Level],
    ) -> io::Result<VcdTrace<W>> {
        let ids: Vec<String> = (0..names.len()).map(vcd_id).collect();
        writeln!(
            out,
            "$version pwm_actuator {} $end",
            env!("CARGO_PKG_VERSION")
        )?;
        writeln!(out, "$comment time 0 = CLOCK_MONOTONIC {start_ns} ns $end")?;
        writeln!(out, "$timescale 1ns $end")?;
        writeln!(out, "$scope module {VCD_SCOPE} $end")?;
        for (name, id) in names.iter().zip(&ids) {
            writeln!(out, "$var wire 1 {id} {name} $end")?;
        }
        writeln!(out, "$upscope $end")?;
        writeln!(out, "$enddefinitions $end")?;
        writeln!(out, "#0")?;
        writeln!(out, "$dumpvars")?;
        for (i, id) in ids.iter().enumerate() {
            let level = level_digit(levels.get(i).copied().unwrap_or(Level::Low));
            writeln!(out, "{level}{id}")?;
        }
        writeln!(out, "$end")?;
        Ok(VcdTrace {
            out,
            ids,
            start_ns,
            last_t: 0,
        })
    }

    fn advance_to(&mut self, t_ns: Nanos) -> io::Result<()> {
        let t = t_ns.saturating_sub(self.start_ns);
        if t > self.last_t {
            writeln!(self.out, "#{t}")?;
            self.last_t = t;
        }
        Ok(())
    }

    /// Appends one value change; changes at the time of the previous one share its `#t`.
    pub fn record(&mut self, rec: &EdgeRecord) -> io::Result<()> {
        if rec.channel >= self.ids.len() {
            return Err(unknown_channel(rec.channel, self.ids.len()));
        }
        self.advance_to(rec.t_ns)?;
        writeln!(
            self.out,
            "{}{}",
            level_digit(rec.level),
            self.ids[rec.channel]
        )
    }

    /// Writes a final time marker at `end_ns` (if later than the last change), so viewers show
    /// the last levels lasting until then, and flushes.
    pub fn finish(&mut self, end_ns: Nanos) -> io::Result<()> {
        self.advance_to(end_ns)?;
        self.out.flush()
    }

    /// Flushes buffered changes to the underlying writer.
    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    /// The underlying writer.
    pub fn into_inner(self) -> W {
        self.out
    }
}

/// Where a trace goes: any byte sink (a file, a pipe, a buffer in tests).
pub type TraceOut = Box<dyn Write + Send>;

/// What a trace's format writes to: its output, buffered, with what went through counted.
type Out = Counted<BufWriter<TraceOut>>;

enum SinkKind {
    Csv(CsvTrace<Out>),
    Vcd(VcdTrace<Out>),
}

impl std::fmt::Debug for SinkKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SinkKind::Csv(_) => "Csv",
            SinkKind::Vcd(_) => "Vcd",
        })
    }
}

impl SinkKind {
    /// Begins a trace of `format` on `out` at `t_ns` with the channels at `levels`: its header
    /// and initial levels, flushed at once, so the file is a valid (empty) trace from the
    /// start.
    fn begin(
        format: TraceFormat,
        out: TraceOut,
        names: &[String],
        t_ns: Nanos,
        levels: &[Level],
    ) -> io::Result<SinkKind> {
        let out = Counted::new(BufWriter::new(out));
        match format {
            TraceFormat::Csv => CsvTrace::with_levels(out, names, t_ns, levels)
                .and_then(|mut t| t.flush().map(|()| SinkKind::Csv(t))),
            TraceFormat::Vcd => VcdTrace::with_levels(out, names, t_ns, levels)
                .and_then(|mut t| t.flush().map(|()| SinkKind::Vcd(t))),
            TraceFormat::Mcap => Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "MCAP traces are written by the ROS side, not by the edge recorder",
            )),
        }
    }

    fn record(&mut self, rec: &EdgeRecord) -> io::Result<()> {
        match self {
            SinkKind::Csv(t) => t.record(rec),
            SinkKind::Vcd(t) => t.record(rec),
        }
    }

    fn flush(&mut self) -> io::Result<()> {
        match self {
            SinkKind::Csv(t) => t.flush(),
            SinkKind::Vcd(t) => t.flush(),
        }
    }

    /// Ends the file at `end_ns` (VCD: the final time marker) and flushes it.
    fn finish(&mut self, end_ns: Nanos) -> io::Result<()> {
        match self {
            SinkKind::Csv(t) => t.flush(),
            SinkKind::Vcd(t) => t.finish(end_ns),
        }
    }

    /// Bytes written to the file so far, buffered or not.
    fn written(&self) -> u64 {
        match self {
            SinkKind::Csv(t) => t.out.written(),
            SinkKind::Vcd(t) => t.out.written(),
        }
    }
}

/// The most one record adds to a file beyond its channel's name, bytes: a CSV row (two times
/// of up to 20 digits, the level, three commas, the newline) or a VCD change with its time
/// marker, and then the VCD's final time marker.
const RECORD_BYTES: u64 = 80;

/// The regular file behind a sink the writer created: what its rotation and its checks need.
#[derive(Debug)]
struct OnDisk {
    /// A second handle on the file written, for the checks.
    handle: File,
    limit: TraceLimit,
    /// The older files' sizes, bytes (see [`trace_files::older_sizes`]).
    older: [Option<u64>; TRACE_FILES as usize - 1],
    /// Records in the file written.
    records: u64,
    /// When the next check is due, and the next try of a failed trace, monotonic ns.
    next_check: Nanos,
    next_retry: Nanos,
}

#[derive(Debug)]
struct Sink {
    path: PathBuf,
    format: TraceFormat,
    /// `None` after a failure: nothing is written until a new file begins.
    kind: Option<SinkKind>,
    disk: Option<OnDisk>,
    /// Where its state is told, for a trace the writer created at a path.
    slot: Option<TraceSlot>,
    /// Records lost since its state was last told.
    lost: u64,
    /// The time of the last check, monotonic ns: a failure between two checks is taken as
    /// seen then.
    now: Nanos,
}

impl Sink {
    /// A write, a flush or a new file failed with `e`: nothing more goes to this file; the
    /// failure is told at once. Returns the error to report.
    fn fail(&mut self, what: &str, e: io::Error) -> TraceError {
        self.kind = None;
        let now = self.now;
        if let Some(disk) = &mut self.disk {
            disk.next_retry = now.saturating_add(RETRY_PERIOD_NS);
        }
        if let Some(slot) = &self.slot {
            let text = format!("{what}: {}", trace_files::io_reason(&e));
            let lost = std::mem::take(&mut self.lost);
            slot.update(|s| {
                s.lost += lost;
                if s.failing.as_deref() != Some(text.as_str()) {
                    s.problem(text.clone(), now);
                }
                s.failing = Some(text);
            });
        }
        TraceError::Write {
            path: self.path.clone(),
            source: e,
        }
    }

    /// Begins a new file at the path at `t_ns` with the channels at `levels` (a regular
    /// file's sink only).
    fn begin(&mut self, names: &[String], t_ns: Nanos, levels: &[Level]) -> Result<(), TraceError> {
        self.kind = None;
        let file = match File::create(&self.path) {
            Ok(f) => f,
            Err(e) => return Err(self.fail("cannot create", e)),
        };
        let handle = match file.try_clone() {
            Ok(h) => h,
            Err(e) => return Err(self.fail("cannot create", e)),
        };
        match SinkKind::begin(self.format, Box::new(file), names, t_ns, levels) {
            Ok(kind) => self.kind = Some(kind),
            Err(e) => return Err(self.fail("cannot write", e)),
        }
        if let Some(disk) = &mut self.disk {
            disk.handle = handle;
            disk.records = 0;
        }
        Ok(())
    }

    /// Closes the file written whole at `t_ns`, moves the older ones up (the oldest deleted)
    /// and begins a new one. `full`: because the file reached its share of the limit (counted
    /// as a rotation), not to keep a failed file beside the new one.
    fn rotate(
        &mut self,
        names: &[String],
        t_ns: Nanos,
        levels: &[Level],
        full: bool,
    ) -> Result<(), TraceError> {
        if let Some(mut kind) = self.kind.take() {
            if let Err(e) = kind.finish(t_ns) {
                return Err(self.fail("cannot write", e));
            }
        }
        let dropped = match trace_files::shift_files(&self.path) {
            Ok(d) => d,
            Err(e) => return Err(self.fail("cannot rotate", e)),
        };
        if let Some(disk) = &mut self.disk {
            disk.older = trace_files::older_sizes(&self.path);
        }
        if let Some(slot) = &self.slot {
            slot.update(|s| {
                s.rotations += u64::from(full);
                s.files_dropped += u64::from(dropped);
            });
        }
        self.begin(names, t_ns, levels)
    }

    /// Writes `rec`, first rotating when it could take the file beyond its share of the
    /// limit (a record is at most [`RECORD_BYTES`] and the longest name, `longest`); a sink
    /// that failed counts it lost.
    fn write(
        &mut self,
        rec: &EdgeRecord,
        names: &[String],
        longest: u64,
        t_ns: Nanos,
        levels: &[Level],
    ) -> Result<(), TraceError> {
        let Some(kind) = &self.kind else {
            self.lost += 1;
            return Ok(());
        };
        if let Some(disk) = &self.disk {
            let full = kind.written() + RECORD_BYTES + longest > disk.limit.file_bytes();
            if full && disk.records > 0 {
                if let Err(e) = self.rotate(names, t_ns, levels, true) {
                    self.lost += 1;
                    return Err(e);
                }
            }
        }
        let Some(kind) = &mut self.kind else {
            self.lost += 1;
            return Ok(());
        };
        match kind.record(rec) {
            Ok(()) => {
                if let Some(disk) = &mut self.disk {
                    disk.records += 1;
                }
                Ok(())
            }
            Err(e) => {
                self.lost += 1;
                Err(self.fail("cannot write", e))
            }
        }
    }

    /// Runs `f` on the trace's format unless it failed; a failure is told.
    fn run(&mut self, f: impl FnOnce(&mut SinkKind) -> io::Result<()>) -> Result<(), TraceError> {
        let Some(kind) = &mut self.kind else {
            return Ok(());
        };
        f(kind).map_err(|e| self.fail("cannot write", e))
    }

    /// The checks due at `now` of a regular file's sink: a file deleted or replaced while
    /// written begins again at its path; a failed one tries a new file every
    /// [`RETRY_PERIOD_NS`]; its file system's room; then its state is told.
    fn check(&mut self, now: Nanos, names: &[String], t_ns: Nanos, levels: &[Level]) {
        self.now = now;
        let Some(disk) = &mut self.disk else {
            self.tell();
            return;
        };
        if now < disk.next_check {
            self.tell();
            return;
        }
        disk.next_check = now.saturating_add(CHECK_PERIOD_NS);
        let gone = self.kind.is_some() && !trace_files::still_at(&disk.handle, &self.path);
        if gone {
            if let Some(slot) = &self.slot {
                slot.update(|s| {
                    s.reopened += 1;
                    s.problem(
                        "the file was deleted or replaced while written; begun again at its path"
                            .into(),
                        now,
                    );
                });
            }
            // The records in the file deleted went with it; what follows goes to the new one.
            let _ = self.begin(names, t_ns, levels);
        } else if self.kind.is_none() && now >= disk.next_retry {
            // A file that holds records is kept whole: the new one comes after it.
            let result = if disk.records > 0 {
                self.rotate(names, t_ns, levels, false)
            } else {
                self.begin(names, t_ns, levels)
            };
            if result.is_ok() {
                if let Some(slot) = &self.slot {
                    slot.update(|s| s.failing = None);
                }
            }
        }
        let no_room = self
            .disk
            .as_ref()
            .is_some_and(|d| trace_files::no_room(&d.handle));
        if let Some(slot) = &self.slot {
            slot.update(|s| {
                if no_room && !s.no_room {
                    s.problem("its file system is full".into(), now);
                }
                s.no_room = no_room;
            });
        }
        self.tell();
    }

    /// Tells the trace's size and its lost records.
    fn tell(&mut self) {
        let Some(slot) = &self.slot else {
            return;
        };
        let lost = std::mem::take(&mut self.lost);
        // A file that failed stays on disk as far as it was written.
        let written = match (&self.kind, &self.disk) {
            (Some(kind), _) => kind.written(),
            (None, Some(d)) => d.handle.metadata().map_or(0, |m| m.len()),
            (None, None) => 0,
        };
        let (older, files) = match &self.disk {
            Some(d) => (
                d.older.iter().flatten().sum::<u64>(),
                1 + d.older.iter().flatten().count() as u32,
            ),
            None => (0, 1),
        };
        slot.update(|s| {
            s.lost += lost;
            s.bytes = written + older;
            s.files = files;
        });
    }
}

/// Writes edge records to every file of a [`TraceSpec`], buffered.
///
/// A file whose write fails is left as it is (the error is returned once) while the others go
/// on; what it should have held is counted lost. A file the writer created at a path tries a
/// new file every [`RETRY_PERIOD_NS`], and keeps to its size limit by rotation (see
/// [`trace_files`]).
#[derive(Debug)]
pub struct TraceWriter {
    sinks: Vec<Sink>,
    names: Vec<String>,
    /// Every channel's level after the records written so far.
    levels: Vec<Level>,
    /// The time of the last record written (the start before any), monotonic ns.
    last_t: Nanos,
    /// The longest channel name, bytes.
    longest: u64,
}

impl TraceWriter {
    /// Creates (truncates) every file of `spec` and writes and flushes its header and initial
    /// levels (all 0 at `start_ns`, monotonic ns); each keeps to the default [`TraceLimit`].
    pub fn create(
        spec: &TraceSpec,
        channel_names: &[String],
        start_ns: Nanos,
    ) -> Result<TraceWriter, TraceError> {
        TraceWriter::create_watched(
            spec,
            channel_names,
            start_ns,
            TraceLimit::default(),
            &TraceHealth::new(),
        )
    }

    /// [`TraceWriter::create`] with each trace keeping to `limit` (a regular file: a pipe or
    /// a device is written as it is), its state told in `health`.
    pub fn create_watched(
        spec: &TraceSpec,
        channel_names: &[String],
        start_ns: Nanos,
        limit: TraceLimit,
        health: &TraceHealth,
    ) -> Result<TraceWriter, TraceError> {
        validate_channel_names(channel_names)?;
        let mut sinks = Vec::with_capacity(spec.files.len());
        // MCAP files are written by the ROS side.
        for file in spec.files.iter().filter(|f| f.format != TraceFormat::Mcap) {
            let create = |source| TraceError::Create {
                path: file.path.clone(),
                source,
            };
            let out = File::create(&file.path).map_err(create)?;
            let disk = match trace_files::is_regular(&out) {
                true => Some(OnDisk {
                    handle: out.try_clone().map_err(create)?,
                    limit,
                    older: trace_files::older_sizes(&file.path),
                    records: 0,
                    next_check: 0,
                    next_retry: 0,
                }),
                false => None,
            };
            let kind = SinkKind::begin(file.format, Box::new(out), channel_names, start_ns, &[])
                .map_err(create)?;
            let limit_bytes = disk.as_ref().map_or(0, |d| d.limit.max_bytes);
            let slot = health.register(TraceState::new(&file.path, file.format, limit_bytes));
            sinks.push(Sink {
                path: file.path.clone(),
                format: file.format,
                kind: Some(kind),
                disk,
                slot: Some(slot),
                lost: 0,
                now: start_ns,
            });
        }
        let mut w = TraceWriter::with_sinks(sinks, channel_names, start_ns);
        w.sinks.iter_mut().for_each(Sink::tell);
        Ok(w)
    }

    /// Like [`TraceWriter::create`] with already opened outputs: (name used in error
    /// messages, format, output). They neither rotate nor are checked.
    pub fn from_writers(
        targets: Vec<(PathBuf, TraceFormat, TraceOut)>,
        channel_names: &[String],
        start_ns: Nanos,
    ) -> Result<TraceWriter, TraceError> {
        validate_channel_names(channel_names)?;
        let mut sinks = Vec::with_capacity(targets.len());
        for (path, format, out) in targets {
            let kind =
                SinkKind::begin(format, out, channel_names, start_ns, &[]).map_err(|source| {
                    TraceError::Create {
                        path: path.clone(),
                        source,
                    }
                })?;
            sinks.push(Sink {
                path,
                format,
                kind: Some(kind),
                disk: None,
                slot: None,
                lost: 0,
                now: start_ns,
            });
        }
        Ok(TraceWriter::with_sinks(sinks, channel_names, start_ns))
    }

    fn with_sinks(sinks: Vec<Sink>, channel_names: &[String], start_ns: Nanos) -> TraceWriter {
        TraceWriter {
            sinks,
            names: channel_names.to_vec(),
            levels: vec![Level::Low; channel_names.len()],
            last_t: start_ns,
            longest: channel_names
                .iter()
                .map(|n| n.len() as u64)
                .max()
                .unwrap_or(0),
        }
    }

    fn each(
        &mut self,
        mut f: impl FnMut(&mut SinkKind) -> io::Result<()>,
    ) -> Result<(), TraceError> {
        let mut first = Ok(());
        for sink in &mut self.sinks {
            let r = sink.run(&mut f);
            if first.is_ok() {
                first = r;
            }
        }
        first
    }

    /// Appends records in order to every file; returns the first error (after trying all).
    pub fn write_records(&mut self, recs: &[EdgeRecord]) -> Result<(), TraceError> {
        let mut first = Ok(());
        for rec in recs {
            for sink in &mut self.sinks {
                let r = sink.write(rec, &self.names, self.longest, self.last_t, &self.levels);
                if first.is_ok() {
                    first = r;
                }
            }
            if let Some(level) = self.levels.get_mut(rec.channel) {
                *level = rec.level;
            }
            self.last_t = self.last_t.max(rec.t_ns);
        }
        first
    }

    /// Flushes every file.
    pub fn flush(&mut self) -> Result<(), TraceError> {
        self.each(SinkKind::flush)
    }

    /// The checks due at `now` (monotonic ns) of every file the writer created: a file deleted
    /// or replaced begins again at its path, a failed one tries a new file, a full file system
    /// is told; and every trace's state is told. The trace writer thread calls this after each
    /// batch.
    pub fn check(&mut self, now: Nanos) {
        for sink in &mut self.sinks {
            sink.check(now, &self.names, self.last_t, &self.levels);
        }
    }

    /// `n` edges never reached the writer (its buffer was full): each trace counts them lost
    /// and says so.
    pub fn lost_before(&mut self, n: u64) {
        for sink in &mut self.sinks {
            let now = sink.now;
            if let Some(slot) = &sink.slot {
                slot.update(|s| {
                    s.lost += n;
                    s.problem(
                        format!(
                            "{n} edges not traced: the writer fell behind and its buffer was full"
                        ),
                        now,
                    );
                });
            }
        }
    }

    /// Ends the trace at `end_ns` (VCD: final time marker) and flushes every file.
    pub fn finish(&mut self, end_ns: Nanos) -> Result<(), TraceError> {
        let r = self.each(|kind| kind.finish(end_ns));
        self.sinks.iter_mut().for_each(Sink::tell);
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn names(n: &[&str]) -> Vec<String> {
        n.iter().map(|s| s.to_string()).collect()
    }

    fn rec(t_ns: Nanos, channel: usize, high: bool, scheduled_ns: Nanos) -> EdgeRecord {
        EdgeRecord {
            t_ns,
            channel,
            level: Level::from_bool(high),
            scheduled_ns,
        }
    }

    #[test]
    fn spec_accepts_vcd_and_csv_in_any_number() {
        let paths: Vec<PathBuf> = ["a.vcd", "b.CSV", "dir/c.csv", "d.Vcd"]
            .iter()
            .map(PathBuf::from)
            .collect();
        let spec = TraceSpec::from_paths(&paths).unwrap();
        let formats: Vec<TraceFormat> = spec.files().iter().map(|f| f.format).collect();
        assert_eq!(
            formats,
            [
                TraceFormat::Vcd,
                TraceFormat::Csv,
                TraceFormat::Csv,
                TraceFormat::Vcd
            ]
        );
        assert_eq!(spec.files()[2].path, PathBuf::from("dir/c.csv"));
        assert!(TraceSpec::from_paths(&[]).unwrap().is_empty());
    }

    #[test]
    fn spec_accepts_mcap_and_keeps_it_from_the_line_traces() {
        let paths: Vec<PathBuf> = ["a.csv", "run.mcap", "b.MCAP", "c.vcd"]
            .iter()
            .map(PathBuf::from)
            .collect();
        let spec = TraceSpec::from_paths(&paths).unwrap();
        assert_eq!(
            spec.of_format(TraceFormat::Mcap),
            [PathBuf::from("run.mcap"), PathBuf::from("b.MCAP")]
        );
        let lines = spec.line_traces();
        let kept: Vec<&Path> = lines.files().iter().map(|f| f.path.as_path()).collect();
        assert_eq!(kept, [Path::new("a.csv"), Path::new("c.vcd")]);
        let only_mcap = TraceSpec::from_paths(&[PathBuf::from("x.mcap")]).unwrap();
        assert!(only_mcap.line_traces().is_empty());
    }

    #[test]
    fn spec_rejects_other_extensions_naming_the_path() {
        for bad in ["trace.txt", "trace", "vcd", "trace.vcd.gz"] {
            let err =
                TraceSpec::from_paths(&[PathBuf::from("ok.csv"), PathBuf::from(bad)]).unwrap_err();
            assert!(
                matches!(&err, TraceError::UnknownExtension { path } if path == Path::new(bad))
            );
            assert!(err.to_string().contains(bad), "{err}");
        }
    }

    #[test]
    fn spec_rejects_a_path_given_twice() {
        let p = PathBuf::from("t.vcd");
        let err = TraceSpec::from_paths(&[p.clone(), p]).unwrap_err();
        assert!(matches!(err, TraceError::DuplicatePath { .. }));
    }

    #[test]
    fn channel_names_must_be_plain_and_unique() {
        assert!(validate_channel_names(&names(&["pw01", "pw02", "heater_1"])).is_ok());
        for bad in ["", "a b", "a,b", "a\"b", "tab\t", "é"] {
            assert!(
                matches!(
                    validate_channel_names(&names(&["pw01", bad])),
                    Err(TraceError::InvalidChannelName { .. })
                ),
                "{bad:?}"
            );
        }
        assert!(matches!(
            validate_channel_names(&names(&["pw01", "pw01"])),
            Err(TraceError::DuplicateChannelName { .. })
        ));
    }

    #[test]
    fn csv_rows_read_back() {
        let start = 5_000_000_000;
        let mut t = CsvTrace::new(Vec::new(), &names(&["pw01", "pw02"]), start).unwrap();
        for r in [
            rec(start + 1_000_100, 0, true, start + 1_000_000),
            rec(start + 2_000_050, 1, true, start + 2_000_000),
            rec(start + 3_000_000, 0, false, start + 3_000_000),
        ] {
            t.record(&r).unwrap();
        }
        assert!(t.record(&rec(start, 2, true, start)).is_err());
        let text = String::from_utf8(t.into_inner()).unwrap();
        assert!(text.starts_with("t_ns,channel,level,scheduled_ns\n"));
        let rows: Vec<(Nanos, &str, Level, Nanos)> = read_csv(&text)
            .unwrap()
            .iter()
            .map(|r| {
                (
                    r.t_ns,
                    if r.channel == "pw01" { "pw01" } else { "pw02" },
                    r.level,
                    r.scheduled_ns,
                )
            })
            .collect();
        assert_eq!(
            rows,
            [
                (5_000_000_000, "pw01", Level::Low, 5_000_000_000),
                (5_000_000_000, "pw02", Level::Low, 5_000_000_000),
                (5_001_000_100, "pw01", Level::High, 5_001_000_000),
                (5_002_000_050, "pw02", Level::High, 5_002_000_000),
                (5_003_000_000, "pw01", Level::Low, 5_003_000_000),
            ]
        );
        assert_eq!(read_csv("x\n"), Err(CsvReadError::Header));
        assert_eq!(
            read_csv("t_ns,channel,level,scheduled_ns\n1,pw01,2,1\n"),
            Err(CsvReadError::Row { line: 2 })
        );
        assert_eq!(
            read_csv("t_ns,channel,level,scheduled_ns\n1,pw01,1,1\n2,pw0")
                .unwrap()
                .len(),
            1,
            "an incomplete last row is left out"
        );
    }

    #[test]
    fn vcd_ids_are_unique_printable_and_short_first() {
        assert_eq!(vcd_id(0), "!");
        assert_eq!(vcd_id(1), "\"");
        assert_eq!(vcd_id(93), "~");
        assert_eq!(vcd_id(94), "!!");
        let ids: Vec<String> = (0..20_000).map(vcd_id).collect();
        let set: HashSet<&String> = ids.iter().collect();
        assert_eq!(set.len(), ids.len());
        assert!(ids
            .iter()
            .all(|id| id.bytes().all(|b| (b'!'..=b'~').contains(&b))));
        assert!(ids[..94].iter().all(|id| id.len() == 1));
    }

    /// A small VCD reader: definitions, and the value changes as (time, id, value).
    struct ParsedVcd {
        timescale: String,
        scope: String,
        vars: Vec<(String, String)>, // (id, reference)
        dumpvars: Vec<(String, char)>,
        changes: Vec<(u64, String, char)>,
        times: Vec<u64>,
    }

    fn parse_vcd(text: &str) -> ParsedVcd {
        let mut p = ParsedVcd {
            timescale: String::new(),
            scope: String::new(),
            vars: Vec::new(),
            dumpvars: Vec::new(),
            changes: Vec::new(),
            times: Vec::new(),
        };
        let mut in_defs = true;
        let mut in_dumpvars = false;
        let mut now = None;
        for line in text.lines() {
            let tok: Vec<&str> = line.split_whitespace().collect();
            if in_defs {
                match tok.first().copied() {
                    Some("$timescale") => p.timescale = tok[1..tok.len() - 1].join(" "),
                    Some("$scope") => {
                        assert_eq!(tok[1], "module");
                        p.scope = tok[2].to_string();
                    }
                    Some("$var") => {
                        assert_eq!(tok.len(), 6, "{line}");
                        assert_eq!(&tok[1..3], ["wire", "1"]);
                        assert_eq!(tok[5], "$end");
                        p.vars.push((tok[3].to_string(), tok[4].to_string()));
                    }
                    Some("$enddefinitions") => in_defs = false,
                    Some("$version" | "$comment" | "$upscope") => {
                        assert_eq!(tok.last(), Some(&"$end"), "{line}");
                    }
                    other => panic!("unexpected definition {other:?}"),
                }
                continue;
            }
            if let Some(t) = line.strip_prefix('#') {
                let t: u64 = t.parse().unwrap();
                if let Some(prev) = now {
                    assert!(t > prev, "time #{t} after #{prev}");
                }
                now = Some(t);
                p.times.push(t);
            } else if line == "$dumpvars" {
                assert_eq!(now, Some(0));
                in_dumpvars = true;
            } else if line == "$end" {
                in_dumpvars = false;
            } else {
                let (v, id) = line.split_at(1);
                let v = v.chars().next().unwrap();
                assert!(v == '0' || v == '1', "{line}");
                if in_dumpvars {
                    p.dumpvars.push((id.to_string(), v));
                } else {
                    p.changes.push((now.unwrap(), id.to_string(), v));
                }
            }
        }
        assert!(!in_defs && !in_dumpvars);
        p
    }

    #[test]
    fn vcd_structure_ids_and_relative_grouped_times() {
        let start = 7_000_000_000;
        let mut t = VcdTrace::new(Vec::new(), &names(&["pw01", "pw02", "pw03"]), start).unwrap();
        for r in [
            rec(start + 1_000, 0, true, start + 900),
            rec(start + 1_000, 1, true, start + 1_000),
            rec(start + 5_000, 0, false, start + 5_000),
            // Older than the last written time: kept at the last time, never going back.
            rec(start + 4_000, 2, true, start + 4_000),
        ] {
            t.record(&r).unwrap();
        }
        t.finish(start + 9_000).unwrap();
        assert!(t.record(&rec(start + 9_500, 3, true, 0)).is_err());
        let text = String::from_utf8(t.into_inner()).unwrap();
        let p = parse_vcd(&text);
        assert_eq!(p.timescale, "1ns");
        assert_eq!(p.scope, VCD_SCOPE);
        assert_eq!(
            p.vars,
            [
                ("!".to_string(), "pw01".to_string()),
                ("\"".to_string(), "pw02".to_string()),
                ("#".to_string(), "pw03".to_string())
            ]
        );
        assert_eq!(
            p.dumpvars,
            [
                ("!".to_string(), '0'),
                ("\"".to_string(), '0'),
                ("#".to_string(), '0')
            ]
        );
        assert_eq!(p.times, [0, 1_000, 5_000, 9_000]);
        assert_eq!(
            p.changes,
            [
                (1_000, "!".to_string(), '1'),
                (1_000, "\"".to_string(), '1'),
                (5_000, "!".to_string(), '0'),
                (5_000, "#".to_string(), '1'),
            ]
        );
    }

    #[test]
    fn vcd_record_before_start_is_written_at_zero() {
        let start = 1_000;
        let mut t = VcdTrace::new(Vec::new(), &names(&["pw01"]), start).unwrap();
        t.record(&rec(10, 0, true, 10)).unwrap();
        let p = parse_vcd(&String::from_utf8(t.into_inner()).unwrap());
        assert_eq!(p.times, [0]);
        assert_eq!(p.changes, [(0, "!".to_string(), '1')]);
    }

    #[test]
    fn writer_writes_every_file_of_the_spec() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let paths = [dir.join("a.csv"), dir.join("b.vcd"), dir.join("c.csv")];
        let spec = TraceSpec::from_paths(&paths).unwrap();
        let mut w = TraceWriter::create(&spec, &names(&["pw01", "pw02"]), 100).unwrap();
        w.write_records(&[rec(150, 1, true, 140), rec(170, 1, false, 170)])
            .unwrap();
        w.finish(200).unwrap();
        for csv in [&paths[0], &paths[2]] {
            let text = std::fs::read_to_string(csv).unwrap();
            assert_eq!(
                text,
                "t_ns,channel,level,scheduled_ns\n100,pw01,0,100\n100,pw02,0,100\n\
                 150,pw02,1,140\n170,pw02,0,170\n"
            );
        }
        let p = parse_vcd(&std::fs::read_to_string(&paths[1]).unwrap());
        assert_eq!(
            p.changes,
            [(50, "\"".to_string(), '1'), (70, "\"".to_string(), '0')]
        );
        assert_eq!(p.times, [0, 50, 70, 100]);
    }

    #[test]
    fn create_error_names_the_path() {
        let spec =
            TraceSpec::from_paths(&[PathBuf::from("/nonexistent-dir-pwm/trace.vcd")]).unwrap();
        let err = TraceWriter::create(&spec, &names(&["pw01"]), 0).unwrap_err();
        assert!(matches!(err, TraceError::Create { .. }));
        assert!(
            err.to_string().contains("/nonexistent-dir-pwm/trace.vcd"),
            "{err}"
        );
    }

    /// A writer of `paths` for pw01 and pw02 from 0, keeping to `max_bytes`, and its health.
    fn watched(paths: &[PathBuf], max_bytes: u64) -> (TraceWriter, TraceHealth) {
        let health = TraceHealth::new();
        let spec = TraceSpec::from_paths(paths).unwrap();
        let limit = TraceLimit { max_bytes };
        let w = TraceWriter::create_watched(&spec, &names(&["pw01", "pw02"]), 0, limit, &health)
            .unwrap();
        (w, health)
    }

    #[test]
    fn a_trace_rotates_at_its_share_of_the_limit_and_keeps_four_whole_files() {
        let tmp = tempfile::tempdir().unwrap();
        let csv = tmp.path().join("run.csv");
        let vcd = tmp.path().join("run.vcd");
        // 8 kB over four files: 2 kB each.
        let (mut w, health) = watched(&[csv.clone(), vcd.clone()], 8_000);
        let recs: Vec<EdgeRecord> = (1..=2_000u64)
            .map(|k| {
                rec(
                    1_000_000 * k,
                    (k % 2) as usize,
                    k % 4 < 2,
                    1_000_000 * k - 7,
                )
            })
            .collect();
        for chunk in recs.chunks(100) {
            w.write_records(chunk).unwrap();
            w.check(0);
        }
        w.finish(3_000_000_000).unwrap();
        let states = health.snapshot();
        for (base, state) in [&csv, &vcd].into_iter().zip(&states) {
            let files: Vec<PathBuf> = (0..TRACE_FILES)
                .map(|k| trace_files::rotated_path(base, k))
                .filter(|p| p.exists())
                .collect();
            assert_eq!(files.len(), TRACE_FILES as usize);
            let sizes: Vec<u64> = files
                .iter()
                .map(|p| std::fs::metadata(p).unwrap().len())
                .collect();
            assert!(sizes.iter().all(|s| *s <= 2_000), "{sizes:?}");
            assert_eq!(state.bytes, sizes.iter().sum::<u64>(), "{state:?}");
            assert_eq!((state.files, state.lost), (4, 0), "{state:?}");
            assert!(state.files_dropped > 0, "{state:?}");
            assert_eq!(state.failing, None);
        }
        // Each CSV file is whole: its header, then every channel's level where the one
        // before ended, then its rows; together, in order, the last records written.
        let mut rows = Vec::new();
        let mut levels = [Level::Low; 2];
        for k in (0..TRACE_FILES).rev() {
            let text = std::fs::read_to_string(trace_files::rotated_path(&csv, k)).unwrap();
            let file = read_csv(&text).unwrap();
            let (start, edges) = file.split_at(2);
            if !rows.is_empty() {
                assert_eq!([start[0].level, start[1].level], levels, "file {k}");
            }
            for r in edges {
                levels[usize::from(r.channel == "pw02")] = r.level;
            }
            rows.extend(edges.iter().map(|r| r.t_ns));
        }
        let want: Vec<Nanos> = recs[recs.len() - rows.len()..]
            .iter()
            .map(|r| r.t_ns)
            .collect();
        assert_eq!(rows, want);
        // Each VCD file is a VCD of its own, its dump the levels it began with.
        for k in 0..TRACE_FILES {
            let p =
                parse_vcd(&std::fs::read_to_string(trace_files::rotated_path(&vcd, k)).unwrap());
            assert_eq!(p.vars.len(), 2);
            assert_eq!(p.dumpvars.len(), 2);
        }
    }

    #[test]
    fn a_file_deleted_while_written_begins_again_at_its_path_and_is_told() {
        let tmp = tempfile::tempdir().unwrap();
        let csv = tmp.path().join("run.csv");
        let (mut w, health) = watched(std::slice::from_ref(&csv), 256_000_000);
        w.write_records(&[rec(100, 0, true, 90)]).unwrap();
        w.flush().unwrap();
        w.check(0);
        std::fs::remove_file(&csv).unwrap();
        w.check(CHECK_PERIOD_NS);
        w.write_records(&[rec(200, 1, true, 190)]).unwrap();
        w.flush().unwrap();
        let rows = read_csv(&std::fs::read_to_string(&csv).unwrap()).unwrap();
        // Begun again with the levels in force (pw01 on since 100), then the new edge.
        let got: Vec<(Nanos, &str, Level)> = rows
            .iter()
            .map(|r| (r.t_ns, r.channel.as_str(), r.level))
            .collect();
        assert_eq!(
            got,
            [
                (100, "pw01", Level::High),
                (100, "pw02", Level::Low),
                (200, "pw02", Level::High)
            ]
        );
        let state = &health.snapshot()[0];
        assert_eq!((state.reopened, state.problems), (1, 1), "{state:?}");
        assert!(state.last_problem.as_ref().unwrap().0.contains("deleted"));
    }

    #[test]
    fn a_file_that_cannot_be_begun_is_tried_again_every_second_and_its_edges_counted_lost() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("traces");
        std::fs::create_dir(&dir).unwrap();
        let csv = dir.join("run.csv");
        let (mut w, health) = watched(std::slice::from_ref(&csv), 256_000_000);
        w.write_records(&[rec(100, 0, true, 90)]).unwrap();
        // The directory goes: the file is deleted, and a new one cannot be created.
        std::fs::remove_dir_all(&dir).unwrap();
        w.check(0);
        let state = health.snapshot()[0].clone();
        assert_eq!(
            state.failing.as_deref(),
            Some("cannot create: the directory is gone (os error 2)")
        );
        w.write_records(&[rec(200, 0, false, 190), rec(300, 0, true, 290)])
            .unwrap();
        w.check(RETRY_PERIOD_NS / 2);
        assert_eq!(health.snapshot()[0].lost, 2);
        // Back: the next try, a second after the failure, begins a new file.
        std::fs::create_dir(&dir).unwrap();
        w.check(RETRY_PERIOD_NS / 2 + CHECK_PERIOD_NS);
        assert!(
            health.snapshot()[0].failing.is_some(),
            "not before a second"
        );
        w.check(RETRY_PERIOD_NS + CHECK_PERIOD_NS);
        let state = health.snapshot()[0].clone();
        assert_eq!(state.failing, None, "{state:?}");
        // The directory went with the first file: the new one is alone, and no rotation.
        assert_eq!(
            (state.files, state.rotations, state.lost),
            (1, 0, 2),
            "{state:?}"
        );
        w.write_records(&[rec(400, 1, true, 390)]).unwrap();
        w.flush().unwrap();
        let rows = read_csv(&std::fs::read_to_string(&csv).unwrap()).unwrap();
        assert_eq!(rows.len(), 3, "{rows:?}");
        assert_eq!(rows[0].level, Level::High, "pw01 on since 300");
    }

    #[test]
    fn a_trace_to_a_device_is_written_as_it_is_never_rotated() {
        let tmp = tempfile::tempdir().unwrap();
        let csv = tmp.path().join("null.csv");
        std::os::unix::fs::symlink("/dev/null", &csv).unwrap();
        let (mut w, health) = watched(std::slice::from_ref(&csv), 8_000);
        let recs: Vec<EdgeRecord> = (1..=2_000u64).map(|k| rec(k, 0, k % 2 == 0, k)).collect();
        w.write_records(&recs).unwrap();
        w.check(0);
        w.finish(3_000).unwrap();
        assert!(std::fs::symlink_metadata(&csv)
            .unwrap()
            .file_type()
            .is_symlink());
        assert!(!trace_files::rotated_path(&csv, 1).exists());
        let state = &health.snapshot()[0];
        assert_eq!(
            (state.limit_bytes, state.files_dropped),
            (0, 0),
            "{state:?}"
        );
    }
}
