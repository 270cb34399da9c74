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
//! When the node stops, the writer closes the file with its summary and footer. A file that
//! reaches [`MAX_CHUNKS_PER_FILE`] chunks is closed and the trace goes on in `<stem>.1.mcap`,
//! `<stem>.2.mcap`, ...: the summary's index, kept in memory until the file is closed, stays
//! bounded.

use crate::output::TraceError;
use crate::ros::interface::schema;
use log::warn;
use mcap::records::MessageHeader;
use rustdds::no_key::SerializerAdapter;
use rustdds::{CDRSerializerAdapter, SerializedPayload};
use serde::Serialize;
use std::collections::BTreeMap;
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

/// One topic of the trace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topic {
    /// The resolved topic name, e.g. `/pwm_actuator/pw01/edges`.
    pub name: String,
    /// The message type's package, e.g. `pwm_actuator_msgs`.
    pub package: &'static str,
    /// The message type's name, e.g. `OutputEdge`.
    pub type_name: &'static str,
}

/// The CDR bytes of `msg` as the node publishes them: the encapsulation header (`CDR_LE`,
/// options 0), then the message.
pub fn cdr_bytes<M: Serialize>(msg: &M) -> Result<Vec<u8>, String> {
    type Adapter<M> = CDRSerializerAdapter<M>;
    let body = <Adapter<M> as SerializerAdapter<M>>::to_bytes(msg).map_err(|e| e.to_string())?;
    let payload = SerializedPayload::new_from_bytes(
        <Adapter<M> as SerializerAdapter<M>>::output_encoding(),
        body,
    );
    Ok(rustdds::bytes::Bytes::from(payload).to_vec())
}

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
    topics: usize,
    join: Option<JoinHandle<()>>,
}

impl McapTrace {
    /// Creates (truncates) every file of `paths`, writes its header, schemas and channels and
    /// flushes them (a valid, empty trace from the start), and starts the writer thread.
    pub fn create(paths: &[PathBuf], topics: Vec<Topic>) -> Result<McapTrace, TraceError> {
        McapTrace::create_with(paths, topics, FLUSH_PERIOD, MAX_CHUNKS_PER_FILE)
    }

    /// [`McapTrace::create`] with another flush period and number of chunks per file.
    fn create_with(
        paths: &[PathBuf],
        topics: Vec<Topic>,
        flush_period: Duration,
        max_chunks: u64,
    ) -> Result<McapTrace, TraceError> {
        let mut files = Vec::with_capacity(paths.len());
        for path in paths {
            files.push(TraceFile::create(path.clone(), &topics, max_chunks)?);
        }
        let (tx, rx) = mpsc::sync_channel(QUEUE_CAPACITY);
        let dropped = Arc::new(AtomicU64::new(0));
        let d = Arc::clone(&dropped);
        let n = topics.len();
        let join = std::thread::Builder::new()
            .name("pwm-mcap".into())
            .spawn(move || writer_loop(files, topics, rx, d, flush_period))
            .map_err(TraceError::Spawn)?;
        Ok(McapTrace {
            tx: Some(tx),
            dropped,
            topics: n,
            join: Some(join),
        })
    }

    /// Queues `msg` for topic `topic` (index into the topics given to [`McapTrace::create`]) at
    /// `stamp_ns` (wall-clock ns since the epoch). Never waits: a full queue drops it.
    pub fn record<M: Serialize>(&self, topic: usize, stamp_ns: i64, msg: &M) {
        let Some(tx) = &self.tx else { return };
        if topic >= self.topics {
            return;
        }
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

/// One MCAP file being written, and the files after it when it fills up.
struct TraceFile {
    /// The path given (the first file).
    base: PathBuf,
    /// The file written now.
    path: PathBuf,
    /// Files closed so far because they were full.
    rotations: u32,
    writer: Option<mcap::Writer<BufWriter<File>>>,
    /// The MCAP channel id of each topic.
    channels: Vec<u16>,
    /// The last sequence number written per topic.
    sequences: Vec<u32>,
    /// Messages written since the last flush.
    unflushed: bool,
    chunks: u64,
    /// Chunks after which the file is closed and the next one begun.
    max_chunks: u64,
    /// Set after the first error: the file is left as it is from then on.
    failed: bool,
}

fn write_options() -> mcap::WriteOptions {
    mcap::WriteOptions::new()
        .profile("ros2")
        .library(format!("pwm_actuator {}", env!("CARGO_PKG_VERSION")))
        .compression(Some(mcap::Compression::Lz4))
        .chunk_size(Some(CHUNK_SIZE))
}

fn mcap_io(path: &Path, e: mcap::McapError) -> TraceError {
    TraceError::Write {
        path: path.to_path_buf(),
        source: std::io::Error::other(e),
    }
}

/// The path of the file after `rotations` full ones: `run.mcap`, `run.1.mcap`, ...
pub fn rotated_path(base: &Path, rotations: u32) -> PathBuf {
    if rotations == 0 {
        return base.to_path_buf();
    }
    let stem = base.file_stem().unwrap_or_default().to_string_lossy();
    let ext = base.extension().unwrap_or_default().to_string_lossy();
    base.with_file_name(format!("{stem}.{rotations}.{ext}"))
}

impl TraceFile {
    fn create(path: PathBuf, topics: &[Topic], max_chunks: u64) -> Result<TraceFile, TraceError> {
        let mut f = TraceFile {
            base: path.clone(),
            path,
            rotations: 0,
            writer: None,
            channels: Vec::new(),
            sequences: vec![0; topics.len()],
            unflushed: false,
            chunks: 0,
            max_chunks,
            failed: false,
        };
        f.open(topics)?;
        Ok(f)
    }

    /// Opens `self.path` and writes the header, the schemas and the channels.
    fn open(&mut self, topics: &[Topic]) -> Result<(), TraceError> {
        let file = File::create(&self.path).map_err(|source| TraceError::Create {
            path: self.path.clone(),
            source,
        })?;
        let mut w = write_options()
            .create(BufWriter::new(file))
            .map_err(|e| mcap_io(&self.path, e))?;
        let mut channels = Vec::with_capacity(topics.len());
        for t in topics {
            let text = schema::ros2msg(t.package, t.type_name).ok_or_else(|| {
                mcap_io(
                    &self.path,
                    mcap::McapError::UnknownSchema(t.name.clone(), 0),
                )
            })?;
            let id = w
                .add_schema(
                    &schema::schema_name(t.package, t.type_name),
                    schema::SCHEMA_ENCODING,
                    text.as_bytes(),
                )
                .map_err(|e| mcap_io(&self.path, e))?;
            let ch = w
                .add_channel(id, &t.name, MESSAGE_ENCODING, &BTreeMap::new())
                .map_err(|e| mcap_io(&self.path, e))?;
            channels.push(ch);
        }
        w.flush().map_err(|e| mcap_io(&self.path, e))?;
        self.writer = Some(w);
        self.channels = channels;
        // The flush above closed the chunk that holds the schemas and channels.
        self.chunks = 1;
        self.unflushed = false;
        Ok(())
    }

    fn fail(&mut self, e: TraceError) {
        warn!(
            "MCAP trace: {}; nothing more is written to it",
            crate::error::chain(&e)
        );
        self.failed = true;
        // Dropping the writer tries to write the summary of what is in the file.
        self.writer = None;
    }

    fn write(&mut self, item: &Item, topics: &[Topic]) {
        if self.failed {
            return;
        }
        if self.chunks >= self.max_chunks {
            self.rotate(topics);
        }
        let Some(w) = self.writer.as_mut() else {
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
            Ok(()) => self.unflushed = true,
            Err(e) => {
                let e = mcap_io(&self.path, e);
                self.fail(e);
            }
        }
    }

    /// Closes the open chunk and writes it out, if anything was written since the last flush.
    fn flush(&mut self) {
        if self.failed || !self.unflushed {
            return;
        }
        let Some(w) = self.writer.as_mut() else {
            return;
        };
        match w.flush() {
            Ok(()) => {
                self.unflushed = false;
                self.chunks += 1;
            }
            Err(e) => {
                let e = mcap_io(&self.path, e);
                self.fail(e);
            }
        }
    }

    /// Closes the file with its summary and footer.
    fn finish(&mut self) {
        if self.failed {
            return;
        }
        if let Some(mut w) = self.writer.take() {
            let r = w.finish().and_then(|_| {
                use std::io::Write;
                w.into_inner().flush().map_err(mcap::McapError::from)
            });
            if let Err(e) = r {
                let e = mcap_io(&self.path, e);
                self.fail(e);
            }
        }
    }

    /// Closes the full file and goes on in the next one.
    fn rotate(&mut self, topics: &[Topic]) {
        self.finish();
        if self.failed {
            return;
        }
        self.rotations += 1;
        self.path = rotated_path(&self.base, self.rotations);
        log::info!(
            "MCAP trace: {} holds {} chunks; going on in {}",
            rotated_path(&self.base, self.rotations - 1).display(),
            self.max_chunks,
            self.path.display()
        );
        self.sequences.iter_mut().for_each(|s| *s = 0);
        if let Err(e) = self.open(topics) {
            self.fail(e);
        }
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
    loop {
        let wait = flush_period.saturating_sub(last_flush.elapsed());
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
    }
    for f in &mut files {
        f.finish();
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
                name: "/pwm_actuator/pw01/edges".into(),
                package: "pwm_actuator_msgs",
                type_name: "OutputEdge",
            },
            Topic {
                name: "/pwm_actuator/pw01/status".into(),
                package: "pwm_actuator_msgs",
                type_name: "ChannelStatus",
            },
            Topic {
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

    /// Decodes CDR bytes as a subscriber of the node does.
    fn decode<M: DeserializeOwned>(bytes: &[u8]) -> M {
        let payload =
            SerializedPayload::from_bytes(&rustdds::bytes::Bytes::copy_from_slice(bytes)).unwrap();
        CDRDeserializerAdapter::<M>::from_bytes(&payload.value, payload.representation_identifier)
            .unwrap()
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
    fn rotated_paths_number_the_files_after_the_first() {
        let p = Path::new("/tmp/x/run.mcap");
        assert_eq!(rotated_path(p, 0), p);
        assert_eq!(rotated_path(p, 1), Path::new("/tmp/x/run.1.mcap"));
        assert_eq!(rotated_path(p, 12), Path::new("/tmp/x/run.12.mcap"));
    }

    #[test]
    fn a_trace_reads_back_with_schemas_channels_and_every_message() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let trace = McapTrace::create(std::slice::from_ref(&path), topics()).unwrap();
        let edges: Vec<OutputEdge> = (1..=50).map(|s| edge(s, s % 2 == 1)).collect();
        let core = crate::core::Channel::new(Default::default(), 0).status(0);
        let status = status_msg(0, &core, 0, 1_700_000_000_000_000_123);
        for e in &edges {
            trace.record(0, e.stamp.to_nanos(), e);
        }
        trace.record(1, status.stamp.to_nanos(), &status);
        let diag = diagnostics();
        trace.record(2, diag.header.stamp.to_nanos(), &diag);
        trace.record(3, 0, &diag); // no such topic: ignored
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
        assert_eq!(cdr_bytes(&got_status[0]), cdr_bytes(&status));
        assert_eq!(got_diag, [diag]);
    }

    #[test]
    fn a_full_queue_drops_and_counts_without_waiting() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let trace = McapTrace::create(std::slice::from_ref(&path), topics()).unwrap();
        let n = QUEUE_CAPACITY as u64 * 8;
        let t0 = Instant::now();
        for s in 1..=n {
            trace.record(0, s as i64, &edge(s, true));
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
        let trace = McapTrace::create(std::slice::from_ref(&path), topics()).unwrap();
        for s in 1..=10 {
            trace.record(0, s, &edge(s as u64, true));
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

    #[test]
    fn a_full_file_is_closed_whole_and_the_trace_goes_on_in_the_next() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("run.mcap");
        let period = Duration::from_millis(20);
        let trace =
            McapTrace::create_with(std::slice::from_ref(&path), topics(), period, 3).unwrap();
        // One message per flush period: a chunk each, three chunks a file.
        let sent = 10;
        for s in 1..=sent {
            trace.record(0, s, &edge(s as u64, true));
            std::thread::sleep(period * 3);
        }
        trace.finish();
        let mut total = 0;
        let mut files = 0;
        for k in 0.. {
            let p = rotated_path(&path, k);
            if !p.exists() {
                break;
            }
            files += 1;
            let bytes = std::fs::read(&p).unwrap();
            assert!(
                bytes.ends_with(mcap::MAGIC),
                "{} is not closed",
                p.display()
            );
            let summary = mcap::Summary::read(&bytes).unwrap().expect("a summary");
            assert!(summary.chunk_indexes.len() <= 3, "{}", p.display());
            assert_eq!(summary.channels.len(), 3, "every file has every channel");
            let seqs: Vec<u32> = mcap::MessageStream::new(&bytes)
                .unwrap()
                .map(|m| m.unwrap().sequence)
                .collect();
            assert_eq!(seqs, (1..=seqs.len() as u32).collect::<Vec<_>>());
            total += seqs.len();
        }
        assert!(files >= 3, "{files} file(s)");
        assert_eq!(total, sent as usize);
    }

    #[test]
    fn an_unwritable_path_is_refused_naming_it() {
        let err = McapTrace::create(&[PathBuf::from("/nonexistent-dir-pwm/run.mcap")], topics())
            .err()
            .unwrap();
        assert!(
            err.to_string().contains("/nonexistent-dir-pwm/run.mcap"),
            "{err}"
        );
    }
}
