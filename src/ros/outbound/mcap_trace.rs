//! MCAP traces (`--trace run.mcap`): what the reporter publishes — every edge, every status
//! message and `/diagnostics` — recorded as ROS 2 messages, so Foxglove, PlotJuggler and
//! rosbag2 open the file.
//!
//! Each topic is an MCAP channel with the topic's resolved name, message encoding `cdr` (the
//! bytes the node publishes: the 4-byte encapsulation header, then little-endian CDR) and a
//! schema `<package>/msg/<Type>` in the `ros2msg` encoding ([`schema`]). A message's log and
//! publish time are its stamp, wall-clock ns since the Unix epoch; the sequence counts the
//! messages of its channel from 1.
//!
//! Threading: [`McapTrace::record`] runs on the report thread; it serializes the message and
//! hands it to the writer thread through a bounded queue without waiting: when the queue is
//! full the message is dropped and counted ([`McapTrace::dropped`]). The output thread never
//! sees any of it. The writer thread does all file I/O: chunks of at most [`CHUNK_SIZE`]
//! bytes (LZ4), each closed and written out at least every [`FLUSH_PERIOD`] while messages
//! come, so after a SIGKILL a reader in recovery mode reads everything up to the last second.
//! When the node stops, the writer closes the file with its summary and footer.
//!
//! A trace keeps to its size limit by rotation, as the VCD and CSV traces do
//! ([`crate::output::trace_files`]): before a message would take the file written beyond its
//! share of `trace_max_mb` once its open chunk and summary are written, the file is closed
//! whole, becomes `<stem>.1.mcap` (the older ones move up, the oldest of four is deleted), and
//! the trace goes on in a new file at its path, with the schemas and channels again and the
//! sequences from 1. So does a file that reaches [`MAX_CHUNKS_PER_FILE`] chunks: the summary's
//! index, kept in memory until the file is closed, stays bounded. A file that cannot be
//! written (a full disk) is told at once ([`TraceHealth`]), its messages counted lost, and a
//! new file tried every second; a file deleted while written is begun again at its path.

use crate::output::trace::TraceFormat;
use crate::output::trace_files::{
    self, Counted, TraceHealth, TraceLimit, TraceSlot, TraceState, CHECK_PERIOD_NS,
    RETRY_PERIOD_NS, TRACE_FILES,
};
use crate::output::{Nanos, TraceError};
use crate::ros::interface::schema;
use log::warn;
use mcap::records::MessageHeader;
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Messages waiting for the writer thread, at most. Edges come at most a few hundred a second
/// per channel; the writer takes them in well under a millisecond each.
pub const QUEUE_CAPACITY: usize = 4096;

/// The longest a written message stays in an open chunk: the chunk is then closed and written
/// out, so a killed node loses at most this much of the trace.
pub const FLUSH_PERIOD: Duration = Duration::from_secs(1);

/// Uncompressed size at which a chunk is closed, bytes.
pub const CHUNK_SIZE: u64 = 256 * 1024;

/// Chunks of one file before the trace goes on in the next file (a day at one chunk a second).
pub const MAX_CHUNKS_PER_FILE: u64 = 86_400;

/// The message encoding of every channel.
pub const MESSAGE_ENCODING: &str = "cdr";

/// What a topic of the trace carries: the key its messages are recorded under
/// ([`McapTrace::record`]), whatever the order the topics were given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TraceKey {
    /// Channel `n`'s edges (`~/<ch>/edges`; 0 = pw01).
    Edges(usize),
    /// Channel `n`'s status (`~/<ch>/status`; 0 = pw01).
    Status(usize),
    /// `/diagnostics`.
    Diagnostics,
}

/// One topic of the trace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topic {
    /// What it carries.
    pub key: TraceKey,
    /// The resolved topic name, e.g. `/pwm_actuator/pw01/edges`.
    pub name: String,
    /// The message type's package, e.g. `pwm_actuator_msgs`.
    pub package: &'static str,
    /// The message type's name, e.g. `OutputEdge`.
    pub type_name: &'static str,
}

pub use crate::ros::interface::cdr::cdr_bytes;

/// A message on its way to the writer thread.
struct Item {
    topic: usize,
    time_ns: u64,
    data: Vec<u8>,
}

/// The MCAP trace files of a run (see the module documentation).
pub struct McapTrace {
    tx: Option<SyncSender<Item>>,
    dropped: Arc<AtomicU64>,
    /// Each topic's place among the topics the files were made with.
    topics: HashMap<TraceKey, usize>,
    join: Option<JoinHandle<()>>,
}

impl McapTrace {
    /// Creates (truncates) every file of `paths`, writes its header, schemas and channels and
    /// flushes them (a valid, empty trace from the start), and starts the writer thread. Each
    /// trace keeps to `limit` (a regular file: a pipe or a device is written as it is) and
    /// tells its state in `health`.
    pub fn create(
        paths: &[PathBuf],
        topics: Vec<Topic>,
        limit: TraceLimit,
        health: &TraceHealth,
    ) -> Result<McapTrace, TraceError> {
        McapTrace::create_with(
            paths,
            topics,
            FLUSH_PERIOD,
            MAX_CHUNKS_PER_FILE,
            limit,
            health,
        )
    }

    /// [`McapTrace::create`] with another flush period and number of chunks per file.
    fn create_with(
        paths: &[PathBuf],
        topics: Vec<Topic>,
        flush_period: Duration,
        max_chunks: u64,
        limit: TraceLimit,
        health: &TraceHealth,
    ) -> Result<McapTrace, TraceError> {
        let mut files = Vec::with_capacity(paths.len());
        for path in paths {
            files.push(TraceFile::create(
                path.clone(),
                &topics,
                max_chunks,
                limit,
                health,
            )?);
        }
        let (tx, rx) = mpsc::sync_channel(QUEUE_CAPACITY);
        let dropped = Arc::new(AtomicU64::new(0));
        let d = Arc::clone(&dropped);
        let keys = topics.iter().enumerate().map(|(i, t)| (t.key, i)).collect();
        let join = std::thread::Builder::new()
            .name("pwm-mcap".into())
            .spawn(move || writer_loop(files, topics, rx, d, flush_period))
            .map_err(TraceError::Spawn)?;
        Ok(McapTrace {
            tx: Some(tx),
            dropped,
            topics: keys,
            join: Some(join),
        })
    }

    /// Queues `msg` for the topic with `key` at `stamp_ns` (wall-clock ns since the epoch); a
    /// key none of the topics given to [`McapTrace::create`] has is ignored. Never waits: a
    /// full queue drops it.
    pub fn record<M: Serialize>(&self, key: TraceKey, stamp_ns: i64, msg: &M) {
        let Some(tx) = &self.tx else { return };
        let Some(&topic) = self.topics.get(&key) else {
            return;
        };
        let data = match cdr_bytes(msg) {
            Ok(d) => d,
            Err(_) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
                return;
            }
        };
        let item = Item {
            topic,
            time_ns: stamp_ns.max(0) as u64,
            data,
        };
        match tx.try_send(item) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Messages not recorded so far: the queue was full (or the writer thread is gone).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Writes what is queued, closes every file with its summary and footer, and waits for
    /// the writer thread. Dropping the trace does the same.
    pub fn finish(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        drop(self.tx.take());
        if let Some(join) = self.join.take() {
            if join.join().is_err() {
                warn!("MCAP trace: the writer thread panicked");
            }
        }
    }
}

impl Drop for McapTrace {
    fn drop(&mut self) {
        self.stop();
    }
}

/// What the MCAP writer writes to: the file, buffered, with what went through counted.
type Out = Counted<BufWriter<File>>;

/// The bytes a message record adds to its chunk beyond its data: opcode, record length,
/// channel id, sequence, log and publish time.
const MESSAGE_RECORD_BYTES: u64 = 31;

/// The most of an open chunk's uncompressed bytes not yet in the file, bytes: the writer
/// writes a chunk to the file as LZ4 compresses it, and LZ4 holds back at most a block
/// (64 KiB); twice that, to be sure.
const LZ4_HELD: u64 = 2 * 64 * 1024;

/// One MCAP trace: the file written at its path and the older ones (see
/// [`crate::output::trace_files`]).
struct TraceFile {
    /// The path given: the file written.
    base: PathBuf,
    writer: Option<mcap::Writer<Out>>,
    /// Bytes the writer has written to the file written, buffered or not.
    written: Arc<AtomicU64>,
    /// A second handle on the file written, for the checks; `None` for a pipe or a device.
    handle: Option<File>,
    /// The MCAP channel id of each topic.
    channels: Vec<u16>,
    /// The last sequence number written per topic.
    sequences: Vec<u32>,
    /// The open chunk's messages and their uncompressed bytes: what closing it writes, at
    /// most, with their index.
    pending_messages: u64,
    pending_bytes: u64,
    chunks: u64,
    /// Chunks after which the file is closed and the next one begun.
    max_chunks: u64,
    limit: TraceLimit,
    /// The bytes of the header, schemas and channels: the summary repeats the last two.
    header_bytes: u64,
    /// The older files' sizes, bytes.
    older: [Option<u64>; TRACE_FILES as usize - 1],
    /// Messages in the file written.
    messages: u64,
    /// Where its state is told, and the messages lost since it was last told.
    slot: TraceSlot,
    lost: u64,
    /// When the next check is due, and the next try of a failed trace, monotonic ns.
    next_check: Nanos,
    next_retry: Nanos,
}

fn write_options() -> mcap::WriteOptions {
    mcap::WriteOptions::new()
        .profile("ros2")
        .library(format!("pwm_actuator {}", env!("CARGO_PKG_VERSION")))
        .compression(Some(mcap::Compression::Lz4))
        .chunk_size(Some(CHUNK_SIZE))
}

/// The I/O error inside an MCAP error — from the file directly, or from the record encoder
/// that writes to it — or the MCAP error as one. The writer wraps its record encoder's errors
/// in an I/O error of its own (`io::Error::other(binrw::Error::Io(..))`): the error of the
/// file, with its OS error number, is looked for inside that too.
fn io_error(e: mcap::McapError) -> std::io::Error {
    match e {
        mcap::McapError::Io(e) | mcap::McapError::Parse(binrw::Error::Io(e)) => innermost_io(e),
        e => std::io::Error::other(e),
    }
}

/// `e`, or the I/O error with an OS error number it wraps (at most a few levels deep).
fn innermost_io(e: std::io::Error) -> std::io::Error {
    fn os_code(e: &(dyn std::error::Error + 'static), depth: usize) -> Option<i32> {
        if depth == 0 {
            return None;
        }
        if let Some(io) = e.downcast_ref::<std::io::Error>() {
            return io
                .raw_os_error()
                .or_else(|| io.get_ref().and_then(|r| os_code(r, depth - 1)));
        }
        match e.downcast_ref::<binrw::Error>() {
            Some(binrw::Error::Io(io)) => os_code(io, depth - 1),
            Some(binrw::Error::Backtrace(bt)) => os_code(&*bt.error, depth - 1),
            _ => match e.downcast_ref::<mcap::McapError>() {
                Some(mcap::McapError::Io(io) | mcap::McapError::Parse(binrw::Error::Io(io))) => {
                    os_code(io, depth - 1)
                }
                _ => e.source().and_then(|s| os_code(s, depth - 1)),
            },
        }
    }
    match os_code(&e, 8) {
        Some(code) if e.raw_os_error().is_none() => std::io::Error::from_raw_os_error(code),
        _ => e,
    }
}

fn mcap_io(path: &Path, e: mcap::McapError) -> TraceError {
    TraceError::Write {
        path: path.to_path_buf(),
        source: io_error(e),
    }
}

impl TraceFile {
    fn create(
        path: PathBuf,
        topics: &[Topic],
        max_chunks: u64,
        limit: TraceLimit,
        health: &TraceHealth,
    ) -> Result<TraceFile, TraceError> {
        let file = File::create(&path).map_err(|source| TraceError::Create {
            path: path.clone(),
            source,
        })?;
        let regular = trace_files::is_regular(&file);
        let slot = health.register(TraceState::new(
            &path,
            TraceFormat::Mcap,
            if regular { limit.max_bytes } else { 0 },
        ));
        let mut f = TraceFile {
            older: trace_files::older_sizes(&path),
            base: path,
            writer: None,
            written: Arc::new(AtomicU64::new(0)),
            handle: None,
            channels: Vec::new(),
            sequences: vec![0; topics.len()],
            pending_messages: 0,
            pending_bytes: 0,
            chunks: 0,
            max_chunks,
            limit,
            header_bytes: 0,
            messages: 0,
            slot,
            lost: 0,
            next_check: 0,
            next_retry: 0,
        };
        f.begin(file, topics)
            .map_err(|e| mcap_io(&f.base, e))
            .map(|()| f)
    }

    /// Starts the file `file` (at the path) with the header, the schemas and the channels.
    fn begin(&mut self, file: File, topics: &[Topic]) -> Result<(), mcap::McapError> {
        self.handle = match trace_files::is_regular(&file) {
            true => Some(file.try_clone()?),
            false => None,
        };
        let out = Counted::new(BufWriter::new(file));
        self.written = out.counter();
        let mut w = write_options().create(out)?;
        let mut channels = Vec::with_capacity(topics.len());
        for t in topics {
            let text = schema::ros2msg(t.package, t.type_name)
                .ok_or_else(|| mcap::McapError::UnknownSchema(t.name.clone(), 0))?;
            let id = w.add_schema(
                &schema::schema_name(t.package, t.type_name),
                schema::SCHEMA_ENCODING,
                text.as_bytes(),
            )?;
            channels.push(w.add_channel(id, &t.name, MESSAGE_ENCODING, &BTreeMap::new())?);
        }
        w.flush()?;
        self.header_bytes = self.written();
        self.writer = Some(w);
        self.channels = channels;
        self.sequences.iter_mut().for_each(|s| *s = 0);
        // The flush above closed the chunk that holds the schemas and channels.
        self.chunks = 1;
        self.messages = 0;
        self.pending_messages = 0;
        self.pending_bytes = 0;
        Ok(())
    }

    /// Opens a new file at the path and begins it; a failure is told.
    fn restart(&mut self, topics: &[Topic]) -> bool {
        let file = match File::create(&self.base) {
            Ok(f) => f,
            Err(e) => {
                self.fail("cannot create", e);
                return false;
            }
        };
        match self.begin(file, topics) {
            Ok(()) => true,
            Err(e) => {
                self.fail("cannot write", io_error(e));
                false
            }
        }
    }

    /// A write failed with `e`: nothing more goes to this file; the failure is told at once,
    /// a new file tried every [`RETRY_PERIOD_NS`].
    fn fail(&mut self, what: &str, e: std::io::Error) {
        let text = format!("{what}: {}", trace_files::io_reason(&e));
        // Dropping the writer tries to write the summary of what is in the file.
        self.writer = None;
        let now = crate::clock::monotonic_ns();
        self.next_retry = now.saturating_add(RETRY_PERIOD_NS);
        let lost = std::mem::take(&mut self.lost);
        self.slot.update(|s| {
            s.lost += lost;
            if s.failing.as_deref() != Some(text.as_str()) {
                s.problem(text.clone(), now);
            }
            s.failing = Some(text);
        });
    }

    /// The most the file written can come to once its open chunk and its summary are
    /// written, with a message of `record` uncompressed bytes more, bytes: what of the open
    /// chunk is not in the file yet ([`LZ4_HELD`] at most; LZ4 never grows data by more than
    /// 1/255 and a frame's few bytes), each message's index entry (16 bytes, written when the
    /// chunk closes), and the summary, which repeats the schemas and channels and indexes each
    /// chunk.
    fn projected(&self, record: u64) -> u64 {
        if self.writer.is_none() {
            return 0;
        }
        let n = self.channels.len() as u64;
        let held = (self.pending_bytes + record).min(LZ4_HELD + record);
        let open_chunk = held + held / 255 + 128 + 16 * (self.pending_messages + 1) + 16 * n;
        let summary = self.header_bytes + (self.chunks + 2) * (128 + 10 * n) + 512;
        self.written() + open_chunk + summary
    }

    fn write(&mut self, item: &Item, topics: &[Topic]) {
        if self.writer.is_none() {
            self.lost += 1;
            return;
        }
        let record = MESSAGE_RECORD_BYTES + item.data.len() as u64;
        let too_big = self.handle.is_some() && self.projected(record) > self.limit.file_bytes();
        if self.messages > 0 && (self.chunks >= self.max_chunks || too_big) {
            self.rotate(topics, true);
        } else if self.pending_bytes + record > CHUNK_SIZE {
            // Closed here rather than by the writer, so the count of the open chunk stays
            // true.
            self.flush();
        }
        let Some(w) = self.writer.as_mut() else {
            self.lost += 1;
            return;
        };
        let seq = &mut self.sequences[item.topic];
        *seq = seq.wrapping_add(1);
        let header = MessageHeader {
            channel_id: self.channels[item.topic],
            sequence: *seq,
            log_time: item.time_ns,
            publish_time: item.time_ns,
        };
        match w.write_to_known_channel(&header, &item.data) {
            Ok(()) => {
                self.pending_messages += 1;
                self.pending_bytes += record;
                self.messages += 1;
            }
            Err(e) => {
                self.lost += 1;
                self.fail("cannot write", io_error(e));
            }
        }
    }

    /// Bytes written to the file written so far, buffered or not.
    fn written(&self) -> u64 {
        self.written.load(Ordering::Relaxed)
    }

    /// Closes the open chunk and writes it out, if anything was written since the last flush.
    fn flush(&mut self) {
        if self.pending_messages == 0 {
            return;
        }
        let Some(w) = self.writer.as_mut() else {
            return;
        };
        match w.flush() {
            Ok(()) => {
                self.pending_messages = 0;
                self.pending_bytes = 0;
                self.chunks += 1;
            }
            Err(e) => self.fail("cannot write", io_error(e)),
        }
    }

    /// Closes the file with its summary and footer; `false` if that failed (and was told).
    fn finish(&mut self) -> bool {
        if let Some(mut w) = self.writer.take() {
            let r = w.finish().and_then(|_| {
                use std::io::Write;
                w.into_inner().flush().map_err(mcap::McapError::from)
            });
            if let Err(e) = r {
                self.fail("cannot write", io_error(e));
                return false;
            }
        }
        true
    }

    /// Closes the file written whole, moves the older ones up (the oldest deleted) and goes
    /// on in a new file at the path. `full`: because the file is full (its share of the limit,
    /// or its most chunks; counted as a rotation), not to keep a failed file beside the new
    /// one.
    fn rotate(&mut self, topics: &[Topic], full: bool) {
        if !self.finish() {
            return;
        }
        let dropped = match trace_files::shift_files(&self.base) {
            Ok(d) => d,
            Err(e) => {
                self.fail("cannot rotate", e);
                return;
            }
        };
        self.older = trace_files::older_sizes(&self.base);
        self.slot.update(|s| {
            s.rotations += u64::from(full);
            s.files_dropped += u64::from(dropped);
        });
        log::debug!(
            "MCAP trace: {} closed at {} chunks, now {}; going on in a new {}",
            self.base.display(),
            self.chunks,
            trace_files::rotated_path(&self.base, 1).display(),
            self.base.display()
        );
        self.restart(topics);
    }

    /// The checks due at `now`: a file deleted or replaced while written begins again at its
    /// path; a failed one tries a new file every [`RETRY_PERIOD_NS`]; its file system's room;
    /// then its state is told.
    fn check(&mut self, now: Nanos, topics: &[Topic]) {
        if now >= self.next_check && self.handle.is_some() {
            self.next_check = now.saturating_add(CHECK_PERIOD_NS);
            let gone = self.writer.is_some()
                && self
                    .handle
                    .as_ref()
                    .is_some_and(|h| !trace_files::still_at(h, &self.base));
            if gone {
                self.slot.update(|s| {
                    s.reopened += 1;
                    s.problem(
                        "the file was deleted or replaced while written; begun again at its path"
                            .into(),
                        now,
                    );
                });
                // Its summary goes to the deleted file, which closes and frees its space.
                self.writer = None;
                self.restart(topics);
            } else if self.writer.is_none() && now >= self.next_retry {
                // A file that holds messages is kept: the new one comes after it.
                let begun = if self.messages > 0 {
                    self.rotate(topics, false);
                    self.writer.is_some()
                } else {
                    self.restart(topics)
                };
                if begun {
                    self.slot.update(|s| s.failing = None);
                }
            }
            let no_room = self.handle.as_ref().is_some_and(trace_files::no_room);
            self.slot.update(|s| {
                if no_room && !s.no_room {
                    s.problem("its file system is full".into(), now);
                }
                s.no_room = no_room;
            });
        }
        let lost = std::mem::take(&mut self.lost);
        // The file written as far as written (its summary too, once closed).
        let written = self.written();
        let older = self.older.iter().flatten().sum::<u64>();
        let files = 1 + self.older.iter().flatten().count() as u32;
        self.slot.update(|s| {
            s.lost += lost;
            s.bytes = written + older;
            s.files = files;
        });
    }
}

fn writer_loop(
    mut files: Vec<TraceFile>,
    topics: Vec<Topic>,
    rx: mpsc::Receiver<Item>,
    dropped: Arc<AtomicU64>,
    flush_period: Duration,
) {
    let mut last_flush = Instant::now();
    let mut reported_dropped = 0;
    let check = Duration::from_nanos(CHECK_PERIOD_NS);
    loop {
        let wait = flush_period.saturating_sub(last_flush.elapsed()).min(check);
        match rx.recv_timeout(wait) {
            Ok(item) => {
                for f in &mut files {
                    f.write(&item, &topics);
                }
            }
            Err(RecvTimeoutError::Timeout) => {}
            Err(RecvTimeoutError::Disconnected) => break,
        }
        if last_flush.elapsed() >= flush_period {
            files.iter_mut().for_each(TraceFile::flush);
            last_flush = Instant::now();
            let d = dropped.load(Ordering::Relaxed);
            if d > reported_dropped {
                warn!(
                    "MCAP trace: {} message(s) not recorded: the queue to the writer was full",
                    d - reported_dropped
                );
                reported_dropped = d;
            }
        }
        let now = crate::clock::monotonic_ns();
        for f in &mut files {
            f.check(now, &topics);
        }
    }
    for f in &mut files {
        f.finish();
        f.check(crate::clock::monotonic_ns(), &topics);
    }
    let d = dropped.load(Ordering::Relaxed);
    if d > 0 {
        warn!("MCAP trace: {d} message(s) were not recorded: the queue to the writer was full");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::interface::msg::{
        ChannelStatus, DiagnosticArray, DiagnosticStatus, Header, KeyValue, OutputEdge,
    };
    use crate::ros::outbound::diagnostics::status_msg;
    use ros2_client::builtin_interfaces::Time;
    use rustdds::no_key::DeserializerAdapter;
    use rustdds::CDRDeserializerAdapter;
    use serde::de::DeserializeOwned;

    fn topics() -> Vec<Topic> {
        vec![
            Topic {
                key: TraceKey::Edges(0),
                name: "/pwm_actuator/pw01/edges".into(),
                package: "pwm_actuator_msgs",
                type_name: "OutputEdge",
            },
            Topic {
                key: TraceKey::Status(0),
                name: "/pwm_actuator/pw01/status".into(),
                package: "pwm_actuator_msgs",
                type_name: "ChannelStatus",
            },
            Topic {
                key: TraceKey::Diagnostics,
                name: "/diagnostics".into(),
                package: "diagnostic_msgs",
                type_name: "DiagnosticArray",
            },
        ]
    }

    fn edge(seq: u64, level: bool) -> OutputEdge {
        OutputEdge {
            stamp: Time::from_nanos(1_700_000_000_000_000_000 + seq as i64 * 1000),
            channel: 1,
            level,
            seq,
            lateness_ns: -12 + seq as i64,
        }
    }

    fn diagnostics() -> DiagnosticArray {
        DiagnosticArray {
            header: Header {
                stamp: Time::from_nanos(1_700_000_000_500_000_000),
                frame_id: String::new(),
            },
            status: vec![DiagnosticStatus {
                level: DiagnosticStatus::WARN,
                name: "pwm_actuator: pw01".into(),
                message: "E1".into(),
                hardware_id: "sim".into(),
                values: vec![KeyValue {
                    key: "duty".into(),
                    value: "42.0".into(),
                }],
            }],
        }
    }

    /// A trace of [`topics`] at `path`, with the default limit.
    fn create(path: &Path) -> McapTrace {
        McapTrace::create(
            &[path.to_path_buf()],
            topics(),
            TraceLimit::default(),
            &TraceHealth::new(),
        )
        .unwrap()
    }

    /// Decodes CDR bytes as a subscriber of the node does.
    fn decode<M: DeserializeOwned>(bytes: &[u8]) -> M {
        let payload =
            rustdds::SerializedPayload::from_bytes(&rustdds::bytes::Bytes::copy_from_slice(bytes))
                .unwrap();
        CDRDeserializerAdapter::<M>::from_bytes(&payload.value, payload.representation_identifier)
            .unwrap()
    }

    #[test]
    fn a_full_file_system_keeps_its_error_number_wherever_the_write_failed() {
        let full = || std::io::Error::from_raw_os_error(libc::ENOSPC);
        for e in [
            mcap::McapError::Io(full()),
            mcap::McapError::Parse(binrw::Error::Io(full())),
            // A message's header, written by the MCAP writer through its record encoder.
            mcap::McapError::Io(std::io::Error::other(binrw::Error::Io(full()))),
        ] {
            let shown = format!("{e:?}");
            assert_eq!(io_error(e).raw_os_error(), Some(libc::ENOSPC), "{shown}");
        }
        let other = io_error(mcap::McapError::BadMagic);
        assert_eq!(other.raw_os_error(), None);
    }

    #[test]
    fn cdr_bytes_are_little_endian_cdr_with_its_header_and_round_trip() {
        let e = edge(7, true);
        let b = cdr_bytes(&e).unwrap();
        assert_eq!(&b[..4], [0x00, 0x01, 0x00, 0x00], "CDR_LE, options 0");
        // Time (8) + channel (1) + level (1) + pad to 8 (6) + seq (8) + lateness (8).
        assert_eq!(b.len(), 4 + 32);
        assert_eq!(&b[4 + 16..4 + 24], 7u64.to_le_bytes());
        assert_eq!(decode::<OutputEdge>(&b), e);
        let d = diagnostics();
        assert_eq!(decode::<DiagnosticArray>(&cdr_bytes(&d).unwrap()), d);
    }

    #[test]
    fn each_message_goes_to_its_key_topic_whatever_the_topics_order() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let mut reversed = topics();
        reversed.reverse();
        let trace = McapTrace::create(
            std::slice::from_ref(&path),
            reversed,
            TraceLimit::default(),
            &TraceHealth::new(),
        )
        .unwrap();
        let diag = diagnostics();
        trace.record(TraceKey::Diagnostics, diag.header.stamp.to_nanos(), &diag);
        trace.record(TraceKey::Edges(0), 5, &edge(3, true));
        trace.record(TraceKey::Status(1), 0, &diag); // no such topic: ignored
        trace.finish();
        let bytes = std::fs::read(&path).unwrap();
        let got: Vec<(String, u64)> = mcap::MessageStream::new(&bytes)
            .unwrap()
            .map(|m| {
                let m = m.unwrap();
                (m.channel.topic.clone(), m.log_time)
            })
            .collect();
        assert_eq!(
            got,
            [
                ("/diagnostics".to_string(), 1_700_000_000_500_000_000),
                ("/pwm_actuator/pw01/edges".to_string(), 5),
            ]
        );
    }

    #[test]
    fn a_trace_reads_back_with_schemas_channels_and_every_message() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let trace = create(&path);
        let edges: Vec<OutputEdge> = (1..=50).map(|s| edge(s, s % 2 == 1)).collect();
        let core = crate::core::Channel::new(Default::default(), 0).status(0);
        let status = status_msg(0, &core, 0, 1_700_000_000_000_000_123);
        for e in &edges {
            trace.record(TraceKey::Edges(0), e.stamp.to_nanos(), e);
        }
        trace.record(TraceKey::Status(0), status.stamp.to_nanos(), &status);
        let diag = diagnostics();
        trace.record(TraceKey::Diagnostics, diag.header.stamp.to_nanos(), &diag);
        trace.record(TraceKey::Edges(1), 0, &diag); // no such topic: ignored
        assert_eq!(trace.dropped(), 0);
        trace.finish();

        let bytes = std::fs::read(&path).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
        let stats = summary.stats.as_ref().unwrap();
        assert_eq!(stats.message_count, 52);
        assert_eq!(summary.channels.len(), 3);
        for (i, t) in topics().iter().enumerate() {
            let ch = summary
                .channels
                .values()
                .find(|c| c.topic == t.name)
                .unwrap_or_else(|| panic!("channel {}", t.name));
            assert_eq!(ch.message_encoding, "cdr");
            let s = ch.schema.as_ref().unwrap();
            assert_eq!(s.name, format!("{}/msg/{}", t.package, t.type_name));
            assert_eq!(s.encoding, "ros2msg");
            assert_eq!(
                std::str::from_utf8(&s.data).unwrap(),
                schema::ros2msg(t.package, t.type_name).unwrap(),
                "topic {i}"
            );
        }
        let mut got_edges = Vec::new();
        let mut got_status = Vec::new();
        let mut got_diag = Vec::new();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            match m.channel.topic.as_str() {
                "/pwm_actuator/pw01/edges" => {
                    let e: OutputEdge = decode(&m.data);
                    assert_eq!(m.log_time, e.stamp.to_nanos() as u64);
                    assert_eq!(m.publish_time, m.log_time);
                    assert_eq!(m.sequence as u64, e.seq);
                    got_edges.push(e);
                }
                "/pwm_actuator/pw01/status" => got_status.push(decode::<ChannelStatus>(&m.data)),
                "/diagnostics" => got_diag.push(decode::<DiagnosticArray>(&m.data)),
                other => panic!("unexpected topic {other}"),
            }
        }
        assert_eq!(got_edges, edges);
        // NaN fields (no temperature): compared by their bytes.
        assert_eq!(got_status.len(), 1);
        assert_eq!(got_status[0].stamp, status.stamp);
        assert!(got_status[0].temperature_c.is_nan());
        assert_eq!(
            cdr_bytes(&got_status[0]).unwrap(),
            cdr_bytes(&status).unwrap()
        );
        assert_eq!(got_diag, [diag]);
    }

    #[test]
    fn a_full_queue_drops_and_counts_without_waiting() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let trace = create(&path);
        let n = QUEUE_CAPACITY as u64 * 8;
        let t0 = Instant::now();
        for s in 1..=n {
            trace.record(TraceKey::Edges(0), s as i64, &edge(s, true));
        }
        // Far more than the queue holds, faster than a disk: nothing waited for the writer.
        assert!(t0.elapsed() < Duration::from_secs(5));
        let dropped = trace.dropped();
        trace.finish();
        let bytes = std::fs::read(&path).unwrap();
        let written = mcap::MessageStream::new(&bytes).unwrap().count() as u64;
        assert_eq!(written + dropped, n, "each message written or counted");
    }

    #[test]
    fn chunks_are_written_out_while_the_trace_is_open() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let trace = create(&path);
        for s in 1..=10 {
            trace.record(TraceKey::Edges(0), s, &edge(s as u64, true));
        }
        // Within a flush period and a margin, the messages are in the file, before the footer.
        let deadline = Instant::now() + FLUSH_PERIOD * 5;
        let read = loop {
            let bytes = std::fs::read(&path).unwrap();
            let n = mcap::MessageStream::new_with_options(
                &bytes,
                mcap::read::Options::IgnoreEndMagic.into(),
            )
            .unwrap()
            .take_while(Result::is_ok)
            .count();
            if n == 10 || Instant::now() > deadline {
                break n;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        assert_eq!(read, 10);
        trace.finish();
    }

    /// The files of a trace at `path`, newest first, each read whole: (path, its messages'
    /// sequences per topic in order, its chunks).
    fn read_files(path: &Path) -> Vec<(PathBuf, Vec<u32>, usize)> {
        (0..TRACE_FILES)
            .map(|k| trace_files::rotated_path(path, k))
            .filter(|p| p.exists())
            .map(|p| {
                let bytes = std::fs::read(&p).unwrap();
                assert!(
                    bytes.ends_with(mcap::MAGIC),
                    "{} is not closed",
                    p.display()
                );
                let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
                assert_eq!(summary.channels.len(), 3, "every file has every channel");
                let seqs: Vec<u32> = mcap::MessageStream::new(&bytes)
                    .unwrap()
                    .map(|m| m.unwrap().sequence)
                    .collect();
                assert_eq!(seqs, (1..=seqs.len() as u32).collect::<Vec<_>>());
                (p, seqs, summary.chunk_indexes.len())
            })
            .collect()
    }

    #[test]
    fn a_full_file_is_closed_whole_and_the_trace_goes_on_in_the_next() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let period = Duration::from_millis(20);
        let health = TraceHealth::new();
        let trace = McapTrace::create_with(
            std::slice::from_ref(&path),
            topics(),
            period,
            3,
            TraceLimit::default(),
            &health,
        )
        .unwrap();
        // One message per flush period: a chunk each, three chunks a file (the first holds
        // the schemas and channels): two messages a file, three files.
        let sent = 6;
        for s in 1..=sent {
            trace.record(TraceKey::Edges(0), s, &edge(s as u64, true));
            std::thread::sleep(period * 3);
        }
        trace.finish();
        let files = read_files(&path);
        assert_eq!(files.len(), 3, "{files:?}");
        assert!(files.iter().all(|(_, _, chunks)| *chunks <= 3), "{files:?}");
        let total: usize = files.iter().map(|(_, s, _)| s.len()).sum();
        assert_eq!(total, sent as usize);
        let state = &health.snapshot()[0];
        assert_eq!((state.files, state.files_dropped, state.lost), (3, 0, 0));
    }

    #[test]
    fn rotation_keeps_the_files_within_the_limit_and_drops_the_oldest() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let health = TraceHealth::new();
        // 200 kB over four files: 50 kB each.
        let limit = TraceLimit { max_bytes: 200_000 };
        let trace = McapTrace::create_with(
            std::slice::from_ref(&path),
            topics(),
            Duration::from_millis(20),
            MAX_CHUNKS_PER_FILE,
            limit,
            &health,
        )
        .unwrap();
        // Diagnostics that LZ4 cannot shrink much: about 1 MB in all.
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut noise = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            format!("{x:016x}")
        };
        let sent = 2_000;
        for s in 0..sent {
            let mut d = diagnostics();
            d.status[0].message = (0..30).map(|_| noise()).collect();
            trace.record(TraceKey::Diagnostics, s, &d);
            if s % 200 == 0 {
                // Room for the writer: nothing is dropped for a full queue.
                std::thread::sleep(Duration::from_millis(30));
            }
        }
        assert_eq!(trace.dropped(), 0);
        trace.finish();
        let files = read_files(&path);
        let sizes: Vec<u64> = files
            .iter()
            .map(|(p, _, _)| std::fs::metadata(p).unwrap().len())
            .collect();
        assert_eq!(files.len(), TRACE_FILES as usize, "{sizes:?}");
        assert!(
            sizes.iter().all(|s| *s <= limit.file_bytes()),
            "a file above 50 kB: {sizes:?}"
        );
        assert!(sizes.iter().sum::<u64>() <= limit.max_bytes);
        let state = &health.snapshot()[0];
        assert!(state.files_dropped > 0, "{state:?}");
        assert_eq!(state.bytes, sizes.iter().sum::<u64>(), "{state:?}");
        assert_eq!(state.lost, 0);
        // The newest messages are kept: the last file ends with the last one sent.
        let kept: usize = files.iter().map(|(_, s, _)| s.len()).sum();
        assert!(kept > 0 && kept < sent as usize);
    }

    #[test]
    fn an_unwritable_path_is_refused_naming_it() {
        let err = McapTrace::create(
            &[PathBuf::from("/nonexistent-dir-pwm/run.mcap")],
            topics(),
            TraceLimit::default(),
            &TraceHealth::new(),
        )
        .err()
        .unwrap();
        assert!(
            err.to_string().contains("/nonexistent-dir-pwm/run.mcap"),
            "{err}"
        );
    }
}
