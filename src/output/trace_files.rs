//! Trace files on disk (`--trace`): the size limit each trace keeps to by rotation, the checks
//! that the file written is still the one at its path and that its file system has room, and
//! what each trace has come to ([`TraceHealth`]), which the ROS side reports on `/diagnostics`
//! and in the log.
//!
//! A trace's files are its path, the file written, and up to [`TRACE_FILES`] - 1 older ones:
//! `run.1.csv` the newest of them, `run.3.csv` the oldest ([`rotated_path`]). When the file
//! written would grow beyond its share of the limit (a [`TRACE_FILES`]th of `trace_max_mb`,
//! [`TraceLimit::file_bytes`]), it is closed whole, the older files move one number up, the
//! oldest is deleted (and counted), and a new file begins at the path with everything a reader
//! needs (a header, the levels in force). So the files of one trace never hold more than
//! `trace_max_mb` together. Only regular files rotate: a trace to a pipe or a device is
//! written as it is.
//!
//! Everything here runs on the trace writer threads (the sim recorder's, the MCAP writer's),
//! never on the output thread.

use crate::core::Nanos;
use std::fs::{self, File};
use std::io::{self, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Files a trace keeps: the one written and the older ones before it.
pub const TRACE_FILES: u32 = 4;

/// One MB, bytes (the unit of `trace_max_mb`).
pub const BYTES_PER_MB: u64 = 1_000_000;

/// The default of `trace_max_mb`: what the files of one trace may hold together, MB. A day of
/// the CSV of 4 channels at 100 ms (about 242 MB), or about 6 h of their MCAP trace.
pub const DEFAULT_TRACE_MAX_MB: u64 = 256;

/// The least `trace_max_mb`, MB.
pub const MIN_TRACE_MAX_MB: u64 = 1;

/// The most `trace_max_mb`, MB (1 TB).
pub const MAX_TRACE_MAX_MB: u64 = 1_000_000;

/// How often a writer checks that its file is still at its path and that its file system
/// has room, ns.
pub const CHECK_PERIOD_NS: Nanos = 250_000_000;

/// How often a trace that cannot be written tries a new file, ns.
pub const RETRY_PERIOD_NS: Nanos = 1_000_000_000;

/// The format of one trace file, chosen by its extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TraceFormat {
    /// `.vcd`: IEEE 1364 value change dump.
    Vcd,
    /// `.csv`: one row per edge, header [`CSV_HEADER`](super::trace::CSV_HEADER).
    Csv,
    /// `.mcap`: the ROS messages the node publishes about its edges, status and diagnostics,
    /// written by the ROS side (not by [`TraceWriter`](super::trace::TraceWriter)).
    Mcap,
}

impl TraceFormat {
    /// The format for a path's extension (case-insensitive), `None` when it is neither.
    pub fn from_path(path: &Path) -> Option<TraceFormat> {
        let ext = path.extension()?.to_str()?;
        if ext.eq_ignore_ascii_case("vcd") {
            Some(TraceFormat::Vcd)
        } else if ext.eq_ignore_ascii_case("csv") {
            Some(TraceFormat::Csv)
        } else if ext.eq_ignore_ascii_case("mcap") {
            Some(TraceFormat::Mcap)
        } else {
            None
        }
    }
}

/// What the files of one trace may hold together.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TraceLimit {
    /// Bytes over all its files.
    pub max_bytes: u64,
}

impl Default for TraceLimit {
    fn default() -> TraceLimit {
        TraceLimit::from_mb(DEFAULT_TRACE_MAX_MB)
    }
}

impl TraceLimit {
    /// The limit of `mb` MB (kept within [`MIN_TRACE_MAX_MB`]..=[`MAX_TRACE_MAX_MB`]).
    pub fn from_mb(mb: u64) -> TraceLimit {
        TraceLimit {
            max_bytes: mb.clamp(MIN_TRACE_MAX_MB, MAX_TRACE_MAX_MB) * BYTES_PER_MB,
        }
    }

    /// The most one file may hold, bytes: a [`TRACE_FILES`]th of the limit.
    pub fn file_bytes(&self) -> u64 {
        self.max_bytes / u64::from(TRACE_FILES)
    }
}

/// The path of a trace's `k`th older file: the path itself for 0, then `run.1.csv`,
/// `run.2.csv`, ... (the number before the extension).
pub fn rotated_path(base: &Path, k: u32) -> PathBuf {
    if k == 0 {
        return base.to_path_buf();
    }
    let stem = base.file_stem().unwrap_or_default().to_string_lossy();
    match base.extension() {
        Some(ext) => base.with_file_name(format!("{stem}.{k}.{}", ext.to_string_lossy())),
        None => base.with_file_name(format!("{stem}.{k}")),
    }
}

/// Makes room for a new file at `base`: the oldest of the [`TRACE_FILES`] is deleted and the
/// others move one number up (`run.csv` becomes `run.1.csv`). Returns whether a file was
/// deleted. A file missing on the way (deleted by someone else) is skipped.
pub fn shift_files(base: &Path) -> io::Result<bool> {
    let dropped = match fs::remove_file(rotated_path(base, TRACE_FILES - 1)) {
        Ok(()) => true,
        Err(e) if e.kind() == io::ErrorKind::NotFound => false,
        Err(e) => return Err(e),
    };
    for k in (0..TRACE_FILES - 1).rev() {
        match fs::rename(rotated_path(base, k), rotated_path(base, k + 1)) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(e),
        }
    }
    Ok(dropped)
}

/// The sizes of a trace's older files on disk now, bytes, index `k - 1` for
/// [`rotated_path`]`(k)`; `None` where there is none. What an earlier run left counts until
/// it is rotated out.
pub fn older_sizes(base: &Path) -> [Option<u64>; TRACE_FILES as usize - 1] {
    std::array::from_fn(|k| {
        fs::metadata(rotated_path(base, k as u32 + 1))
            .ok()
            .map(|m| m.len())
    })
}

/// Whether `file` is a regular file: only those rotate and are checked.
pub fn is_regular(file: &File) -> bool {
    file.metadata().is_ok_and(|m| m.file_type().is_file())
}

/// Whether `file` is still the file at `path`: not deleted, not replaced by another. When
/// that cannot be told (an error other than a missing path), it is taken as still there.
pub fn still_at(file: &File, path: &Path) -> bool {
    use std::os::unix::fs::MetadataExt;
    let Ok(open) = file.metadata() else {
        return true;
    };
    if open.nlink() == 0 {
        return false;
    }
    match fs::metadata(path) {
        Ok(m) => m.dev() == open.dev() && m.ino() == open.ino(),
        Err(e) => e.kind() != io::ErrorKind::NotFound,
    }
}

/// Whether the file system holding `file` has no free block left (for anyone: the blocks a
/// file system keeps for root count as free; a write that fails for want of them is reported
/// as it fails).
pub fn no_room(file: &File) -> bool {
    nix::sys::statvfs::fstatvfs(file).is_ok_and(|s| s.blocks_free() == 0)
}

/// Why a trace file could not be written, in a few words of our own (the kind of error and the
/// OS error number, not the system's text): `no space left on the file system (os error 28)`.
pub fn io_reason(e: &io::Error) -> String {
    use io::ErrorKind as K;
    let what = match e.kind() {
        K::StorageFull => "no space left on the file system",
        K::QuotaExceeded => "the disk quota is used up",
        K::FileTooLarge => "the file is too large for its file system",
        K::ReadOnlyFilesystem => "the file system is read-only",
        K::PermissionDenied => "permission denied",
        K::NotFound => "the directory is gone",
        K::IsADirectory => "the path is a directory",
        K::BrokenPipe => "the reading end is closed",
        _ => "I/O error",
    };
    match e.raw_os_error() {
        Some(code) => format!("{what} (os error {code})"),
        None => what.to_string(),
    }
}

/// A writer that counts what goes through it: the position and the end of what was written
/// (for a file written from its start: its size once written out). The end can be read
/// through [`Counted::counter`] while something else owns the writer.
#[derive(Debug)]
pub struct Counted<W> {
    inner: W,
    pos: u64,
    end: Arc<AtomicU64>,
}

impl<W> Counted<W> {
    /// Counts from 0.
    pub fn new(inner: W) -> Counted<W> {
        Counted {
            inner,
            pos: 0,
            end: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Bytes written so far (the end of what was written), whether still buffered below or
    /// not.
    pub fn written(&self) -> u64 {
        self.end.load(Ordering::Relaxed)
    }

    /// The count of [`Counted::written`], to read from elsewhere.
    pub fn counter(&self) -> Arc<AtomicU64> {
        Arc::clone(&self.end)
    }

    /// The writer below.
    pub fn into_inner(self) -> W {
        self.inner
    }
}

impl<W: Write> Write for Counted<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.pos += n as u64;
        self.end.fetch_max(self.pos, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

impl<W: Seek> Seek for Counted<W> {
    fn seek(&mut self, to: SeekFrom) -> io::Result<u64> {
        self.pos = self.inner.seek(to)?;
        Ok(self.pos)
    }
}

/// What one trace has come to, as its writer last said.
#[derive(Debug, Clone, PartialEq)]
pub struct TraceState {
    /// The path given.
    pub path: PathBuf,
    /// Its format.
    pub format: TraceFormat,
    /// What its files may hold together, bytes (0: no limit, a pipe or a device).
    pub limit_bytes: u64,
    /// What its files hold now, bytes: the one written, as far as written, and the older ones.
    pub bytes: u64,
    /// Files it keeps now.
    pub files: u32,
    /// Times the file written was full (its share of the limit; for MCAP also its most
    /// chunks), closed and a new one begun.
    pub rotations: u64,
    /// Files the rotation deleted (the oldest, each time the limit was reached).
    pub files_dropped: u64,
    /// Records lost to a failure: edges (CSV, VCD) or messages (MCAP) that could not be
    /// written.
    pub lost: u64,
    /// Why nothing is written now, if so (`cannot write: no space left on the file system (os
    /// error 28)`); it tries a new file every second.
    pub failing: Option<String>,
    /// Its file system has no free block left.
    pub no_room: bool,
    /// The last problem (a failure, the file deleted or replaced, the file system full) and
    /// when it was seen, monotonic ns.
    pub last_problem: Option<(String, Nanos)>,
    /// Problems since start-up.
    pub problems: u64,
    /// Times the file was found deleted or replaced while written and begun again at its path.
    pub reopened: u64,
}

impl TraceState {
    /// A trace at `path` that has written nothing yet.
    pub fn new(path: &Path, format: TraceFormat, limit_bytes: u64) -> TraceState {
        TraceState {
            path: path.to_path_buf(),
            format,
            limit_bytes,
            bytes: 0,
            files: 1,
            rotations: 0,
            files_dropped: 0,
            lost: 0,
            failing: None,
            no_room: false,
            last_problem: None,
            problems: 0,
            reopened: 0,
        }
    }

    /// Notes a problem seen at `now` (monotonic ns).
    pub fn problem(&mut self, what: String, now: Nanos) {
        self.problems += 1;
        self.last_problem = Some((what, now));
    }
}

#[derive(Debug, Default)]
struct HealthInner {
    traces: Mutex<Vec<TraceState>>,
    /// Counts the changes worth telling at once: a failure or its end, a full file system, a
    /// deleted file, a rotation.
    changes: AtomicU64,
    /// Called after each change worth telling (see [`TraceHealth::on_change`]).
    hook: ChangeHook,
}

/// What a [`TraceHealth`] calls after a change worth telling: set once.
#[derive(Default)]
struct ChangeHook(std::sync::OnceLock<Box<dyn Fn() + Send + Sync>>);

impl std::fmt::Debug for ChangeHook {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(if self.0.get().is_some() {
            "ChangeHook(set)"
        } else {
            "ChangeHook"
        })
    }
}

impl HealthInner {
    /// Counts a change worth telling and tells whoever asked ([`TraceHealth::on_change`]).
    fn changed(&self) {
        self.changes.fetch_add(1, Ordering::Relaxed);
        if let Some(f) = self.hook.0.get() {
            f();
        }
    }
}

/// The state of every trace of the node, shared by their writer threads (which update it) and
/// the report thread (which reads it). The lock is held only to copy or update a few fields,
/// never across I/O, and never by the output thread.
#[derive(Debug, Clone, Default)]
pub struct TraceHealth {
    inner: Arc<HealthInner>,
}

impl TraceHealth {
    /// No trace yet.
    pub fn new() -> TraceHealth {
        TraceHealth::default()
    }

    /// Calls `f` after every change worth telling from now on, on the thread that made it (a
    /// trace's writer thread), after the count of [`TraceHealth::changes`] moved: the reader
    /// of the state sleeps until told instead of looking again and again. Only the first call
    /// sets it; `f` must be quick and must not block.
    pub fn on_change(&self, f: impl Fn() + Send + Sync + 'static) {
        let _ = self.inner.hook.0.set(Box::new(f));
    }

    /// Adds a trace; its writer updates it through the slot returned.
    pub fn register(&self, state: TraceState) -> TraceSlot {
        let mut traces = super::panic_off::lock_ignore_poison(&self.inner.traces);
        traces.push(state);
        self.inner.changed();
        TraceSlot {
            health: self.clone(),
            index: traces.len() - 1,
        }
    }

    /// Every trace's state, in the order they were added.
    pub fn snapshot(&self) -> Vec<TraceState> {
        super::panic_off::lock_ignore_poison(&self.inner.traces).clone()
    }

    /// How many changes worth telling at once there have been: a new value means a new
    /// snapshot says something new.
    pub fn changes(&self) -> u64 {
        self.inner.changes.load(Ordering::Relaxed)
    }
}

/// One trace's place in a [`TraceHealth`].
#[derive(Debug, Clone)]
pub struct TraceSlot {
    health: TraceHealth,
    index: usize,
}

impl TraceSlot {
    /// Changes the trace's state; a change of anything but its size counts as one worth
    /// telling ([`TraceHealth::changes`]).
    pub fn update(&self, f: impl FnOnce(&mut TraceState)) {
        let mut traces = super::panic_off::lock_ignore_poison(&self.health.inner.traces);
        let Some(state) = traces.get_mut(self.index) else {
            return;
        };
        let before = (
            state.failing.is_some(),
            state.no_room,
            state.problems,
            state.reopened,
            state.files_dropped,
            state.rotations,
        );
        f(state);
        let after = (
            state.failing.is_some(),
            state.no_room,
            state.problems,
            state.reopened,
            state.files_dropped,
            state.rotations,
        );
        if before != after {
            self.health.inner.changed();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotated_paths_number_the_older_files_before_the_extension() {
        let p = Path::new("/tmp/x/run.csv");
        assert_eq!(rotated_path(p, 0), p);
        assert_eq!(rotated_path(p, 1), Path::new("/tmp/x/run.1.csv"));
        assert_eq!(rotated_path(p, 3), Path::new("/tmp/x/run.3.csv"));
        assert_eq!(
            rotated_path(Path::new("trace"), 2),
            Path::new("trace.2"),
            "no extension"
        );
    }

    #[test]
    fn shifting_moves_every_file_up_and_deletes_the_oldest() {
        let tmp = tempfile::tempdir().unwrap();
        let base = tmp.path().join("run.csv");
        let write = |k: u32, text: &str| fs::write(rotated_path(&base, k), text).unwrap();
        let read = |k: u32| fs::read_to_string(rotated_path(&base, k)).ok();
        write(0, "a");
        assert!(!shift_files(&base).unwrap(), "nothing to delete yet");
        assert_eq!((read(0), read(1)), (None, Some("a".into())));
        write(0, "b");
        shift_files(&base).unwrap();
        write(0, "c");
        shift_files(&base).unwrap();
        write(0, "d");
        assert_eq!(
            (0..4).map(read).collect::<Vec<_>>(),
            ["d", "c", "b", "a"].map(|s| Some(s.to_string()))
        );
        // The fourth shift deletes the oldest, "a".
        assert!(shift_files(&base).unwrap());
        assert_eq!(
            (0..5).map(read).collect::<Vec<_>>(),
            [
                None,
                Some("d".into()),
                Some("c".into()),
                Some("b".into()),
                None
            ]
        );
        // A file deleted by someone else is skipped: "c" is gone, "b" the oldest.
        fs::remove_file(rotated_path(&base, 2)).unwrap();
        write(0, "e");
        assert!(shift_files(&base).unwrap());
        assert_eq!(read(1), Some("e".into()));
        assert_eq!(read(2), Some("d".into()));
        assert_eq!(read(3), None);
        assert_eq!(older_sizes(&base), [Some(1), Some(1), None]);
    }

    #[test]
    fn a_deleted_or_replaced_file_is_no_longer_at_its_path() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.csv");
        let f = File::create(&path).unwrap();
        assert!(is_regular(&f));
        assert!(still_at(&f, &path));
        fs::remove_file(&path).unwrap();
        assert!(!still_at(&f, &path));
        // Another file at the path.
        File::create(&path).unwrap();
        assert!(!still_at(&f, &path));
        assert!(!is_regular(&File::open("/dev/null").unwrap()));
    }

    #[test]
    fn the_limit_is_shared_by_the_files_and_kept_in_range() {
        assert_eq!(TraceLimit::default().max_bytes, 256_000_000);
        assert_eq!(TraceLimit::default().file_bytes(), 64_000_000);
        assert_eq!(
            TraceLimit::from_mb(0).max_bytes,
            MIN_TRACE_MAX_MB * BYTES_PER_MB
        );
        assert_eq!(
            TraceLimit::from_mb(u64::MAX).max_bytes,
            MAX_TRACE_MAX_MB * BYTES_PER_MB
        );
    }

    #[test]
    fn reasons_are_our_words_with_the_error_number() {
        let full = io::Error::from_raw_os_error(libc::ENOSPC);
        assert_eq!(
            io_reason(&full),
            "no space left on the file system (os error 28)"
        );
        let ro = io::Error::from_raw_os_error(libc::EROFS);
        assert_eq!(io_reason(&ro), "the file system is read-only (os error 30)");
        assert_eq!(io_reason(&io::Error::other("x\ny")), "I/O error");
    }

    #[test]
    fn counted_counts_what_was_written_and_follows_seeks() {
        let mut c = Counted::new(io::Cursor::new(Vec::new()));
        c.write_all(b"hello world").unwrap();
        c.seek(SeekFrom::Start(0)).unwrap();
        c.write_all(b"J").unwrap();
        assert_eq!(c.written(), 11);
        c.seek(SeekFrom::End(0)).unwrap();
        c.write_all(b"!").unwrap();
        assert_eq!(c.written(), 12);
        assert_eq!(c.into_inner().into_inner(), b"Jello world!");
    }

    #[test]
    fn a_change_other_than_the_size_counts_as_one_to_tell() {
        let health = TraceHealth::new();
        let slot = health.register(TraceState::new(Path::new("a.csv"), TraceFormat::Csv, 1));
        let c0 = health.changes();
        slot.update(|s| s.bytes += 100);
        assert_eq!(health.changes(), c0);
        slot.update(|s| s.failing = Some("cannot write".into()));
        assert_eq!(health.changes(), c0 + 1);
        assert_eq!(health.snapshot()[0].bytes, 100);
    }
}
