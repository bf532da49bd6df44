//! MCAP recordings with ROS 2 schemas (docs/outputs.md, "MCAP"), so Foxglove and `ros2 bag`
//! open them: positions (`geometry_msgs/msg/PointStamped`), tool poses (`PoseStamped`), `/tf`
//! (`tf2_msgs/msg/TFMessage`) and per-record status (`diagnostic_msgs/msg/DiagnosticStatus`),
//! every payload CDR. Used by `host-tools record --mcap` and irtrackd's `[outputs.mcap]`.
//! The per-record path reuses one buffer; only the MCAP writer's own index grows.
//!
//! The file is written a closed chunk at a time ([`file`]): it is a readable MCAP after every
//! chunk, and a write that fails (a full disk) leaves every chunk before it readable.

pub mod file;

use std::collections::BTreeMap;

pub use file::{Kept, RecordingFile};
use file::CommitSink;

use irtrack_core::stream::{PositionRecord, TrackStatus};

use crate::ros2msg;
use crate::{InteropError, Result};

/// Topic of every tracked record's position (`geometry_msgs/msg/PointStamped`).
pub const TOPIC_POSITION: &str = "/irtrack/position";
/// Topic of every tracked 6-DOF record's pose (`geometry_msgs/msg/PoseStamped`).
pub const TOPIC_POSE: &str = "/irtrack/pose";
/// Topic of the transforms (`tf2_msgs/msg/TFMessage`).
pub const TOPIC_TF: &str = "/tf";
/// Topic of every record's status (`diagnostic_msgs/msg/DiagnosticStatus`).
pub const TOPIC_STATUS: &str = "/irtrack/status";

pub use crate::ros2msg::{FRAME_CAMERA0, FRAME_WORLD};

/// Child frame of `/tf` for a tool (6-DOF) and for the single LED.
pub const FRAME_TOOL: &str = "irtrack_tool";
/// Child frame of `/tf` for the single LED (identity rotation).
pub const FRAME_LED: &str = "irtrack_led";

/// Messages written per topic.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct McapCounts {
    /// On [`TOPIC_POSITION`].
    pub position: u64,
    /// On [`TOPIC_POSE`].
    pub pose: u64,
    /// On [`TOPIC_TF`].
    pub tf: u64,
    /// On [`TOPIC_STATUS`].
    pub status: u64,
}

/// A chunk is closed and written once it holds this many bytes of messages...
pub const CHUNK_MAX_BYTES: u64 = 256 * 1024;
/// ... or spans this much log time: at most about a second of recording is lost when the
/// disk fills or the power goes.
pub const CHUNK_MAX_SPAN_NS: u64 = 1_000_000_000;

/// Bytes a message record adds besides its payload (opcode, length, channel, sequence, two
/// times).
const MESSAGE_OVERHEAD_BYTES: u64 = 1 + 8 + 2 + 4 + 8 + 8;

/// Writes position records into an MCAP file.
pub struct McapRecorder<F: RecordingFile> {
    /// `None` once a write failed.
    writer: Option<mcap::Writer<CommitSink<F>>>,
    /// What the failed write left.
    stopped: Option<Kept>,
    /// Tells the sink the writer is writing its summary (see [`file`]).
    finishing: std::sync::Arc<std::sync::atomic::AtomicBool>,
    channels: [u16; 4],
    sequence: u32,
    /// Added to the records' monotonic capture times to give wall-clock stamps.
    offset_ns: i128,
    buf: Vec<u8>,
    /// Message bytes in the open chunk and the log time of its first message.
    chunk_bytes: u64,
    chunk_first_log_ns: Option<u64>,
    chunk_max_bytes: u64,
    chunk_max_span_ns: u64,
    /// Records given to [`Self::write`], and those of them on file (in closed chunks).
    records_written: u64,
    records_committed: u64,
    /// Messages written so far.
    pub counts: McapCounts,
}

fn err(what: &str) -> impl FnOnce(mcap::McapError) -> InteropError + '_ {
    move |e| InteropError::Mcap {
        what: what.to_string(),
        reason: e.to_string(),
    }
}

fn stopped_error(kept: Kept) -> InteropError {
    InteropError::RecordingStopped {
        reason: kept.reason,
        kept_bytes: kept.bytes,
        kept_chunks: kept.commits,
        end_written: kept.end_written,
    }
}

impl<F: RecordingFile> McapRecorder<F> {
    /// Starts a recording: writes the header, schemas and channels to `out` at once, so a file
    /// that cannot be written fails here. `offset_ns` turns capture times (the tracker's
    /// monotonic clock) into the wall-clock stamps ROS tools expect: wall time now − capture
    /// clock now.
    pub fn new(out: F, offset_ns: i128) -> Result<Self> {
        let opts = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("irtrack ", env!("CARGO_PKG_VERSION")))
            // No compression: the appliance build stays free of C compression libraries.
            .compression(None)
            // Chunks are built in memory and written whole, front to back (never patched in
            // place), when this recorder closes them (no size of the writer's own).
            .disable_seeking(true)
            .chunk_size(None);
        let sink = CommitSink::new(out);
        let finishing = sink.finishing_flag();
        let mut writer = opts.create(sink).map_err(err("header"))?;
        let mut channels = [0u16; 4];
        for (slot, (topic, ty)) in channels.iter_mut().zip([
            (TOPIC_POSITION, ros2msg::POINT_STAMPED),
            (TOPIC_POSE, ros2msg::POSE_STAMPED),
            (TOPIC_TF, ros2msg::TF_MESSAGE),
            (TOPIC_STATUS, ros2msg::DIAGNOSTIC_STATUS),
        ]) {
            let text = ros2msg::schema(ty).ok_or_else(|| InteropError::UnknownType {
                type_name: ty.to_string(),
            })?;
            let schema = writer
                .add_schema(ty, "ros2msg", text.as_bytes())
                .map_err(err(ty))?;
            *slot = writer
                .add_channel(schema, topic, "cdr", &BTreeMap::new())
                .map_err(err(topic))?;
        }
        let mut rec = Self {
            writer: Some(writer),
            stopped: None,
            finishing,
            channels,
            sequence: 0,
            offset_ns,
            buf: Vec::with_capacity(256),
            chunk_bytes: 0,
            chunk_first_log_ns: None,
            chunk_max_bytes: CHUNK_MAX_BYTES,
            chunk_max_span_ns: CHUNK_MAX_SPAN_NS,
            records_written: 0,
            records_committed: 0,
            counts: McapCounts::default(),
        };
        // Header, schemas and channels on file now: a full disk or a bad path fails here.
        rec.commit()?;
        Ok(rec)
    }

    /// Closes chunks at other limits than [`CHUNK_MAX_BYTES`] and [`CHUNK_MAX_SPAN_NS`].
    pub fn with_chunk_limits(mut self, max_bytes: u64, max_span_ns: u64) -> Self {
        self.chunk_max_bytes = max_bytes;
        self.chunk_max_span_ns = max_span_ns;
        self
    }

    /// The writer, or the error of the write that stopped the recording.
    fn writer(&mut self) -> Result<&mut mcap::Writer<CommitSink<F>>> {
        match (&mut self.writer, &self.stopped) {
            (Some(w), _) => Ok(w),
            (None, Some(k)) => Err(stopped_error(k.clone())),
            (None, None) => Err(InteropError::Mcap {
                what: "message".into(),
                reason: "the recording is finished".into(),
            }),
        }
    }

    /// Drops the writer after a failed write and returns what was kept.
    fn stop(&mut self, fallback: String) -> InteropError {
        let kept = self
            .writer
            .take()
            .and_then(|w| w.into_inner().stopped().cloned())
            .unwrap_or(Kept {
                reason: fallback,
                bytes: 0,
                commits: 0,
                end_written: false,
            });
        self.stopped = Some(kept.clone());
        stopped_error(kept)
    }

    /// Closes the open chunk and writes it (followed by the file's end). On failure the
    /// recording stops; the error says what stays readable.
    pub fn commit(&mut self) -> Result<()> {
        if let Err(e) = self.writer()?.flush() {
            return Err(self.stop(e.to_string()));
        }
        self.chunk_bytes = 0;
        self.chunk_first_log_ns = None;
        self.records_committed = self.records_written;
        Ok(())
    }

    /// Records given to [`Self::write`] so far.
    pub fn records_written(&self) -> u64 {
        self.records_written
    }

    /// Records on file: in chunks closed and written (after a failure: those that stay
    /// readable).
    pub fn records_committed(&self) -> u64 {
        self.records_committed
    }

    /// Messages are waiting in an open chunk (not on file yet).
    pub fn has_open_chunk(&self) -> bool {
        self.chunk_first_log_ns.is_some()
    }

    /// What a failed write kept, once the recording stopped.
    pub fn stopped(&self) -> Option<&Kept> {
        self.stopped.as_ref()
    }

    fn put(&mut self, channel: usize, log_ns: u64, publish_ns: u64) -> Result<()> {
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: self.channels[channel],
            sequence: self.sequence,
            log_time: log_ns,
            publish_time: publish_ns,
        };
        let buf = std::mem::take(&mut self.buf);
        let res = self.writer().and_then(|w| {
            w.write_to_known_channel(&header, &buf)
                .map_err(err("message"))
        });
        self.chunk_bytes += buf.len() as u64 + MESSAGE_OVERHEAD_BYTES;
        self.chunk_first_log_ns.get_or_insert(log_ns);
        self.buf = buf;
        res
    }

    /// Commits the open chunk when it reached its size or time span.
    fn close_full_chunk(&mut self, log_ns: u64) -> Result<()> {
        let span = self
            .chunk_first_log_ns
            .map_or(0, |first| log_ns.saturating_sub(first));
        if self.chunk_bytes >= self.chunk_max_bytes || span >= self.chunk_max_span_ns {
            self.commit()?;
        }
        Ok(())
    }

    fn wall(&self, mono_ns: u64) -> u64 {
        u64::try_from(i128::from(mono_ns) + self.offset_ns).unwrap_or(0)
    }

    /// Writes one record: always its status; its position, `/tf` and (with an orientation)
    /// its pose when it is tracked. Positions in metres, in the record's own frame.
    pub fn write(&mut self, rec: &PositionRecord) -> Result<()> {
        self.writer()?;
        self.records_written += 1;
        let stamp = self.wall(rec.capture_ts_ns);
        let publish = self.wall(rec.capture_ts_ns + u64::from(rec.latency_us) * 1000);
        let frame_id = if rec.world_frame {
            FRAME_WORLD
        } else {
            FRAME_CAMERA0
        };
        if let (TrackStatus::Ok, Some(p)) = (rec.status, rec.position_mm) {
            let p_m = [p[0] / 1e3, p[1] / 1e3, p[2] / 1e3];
            ros2msg::point_stamped(stamp, frame_id, &p_m, &mut self.buf);
            self.put(0, stamp, publish)?;
            self.counts.position += 1;
            let (q, child) = match rec.orientation_wxyz {
                Some(q) => ([q[1], q[2], q[3], q[0]], FRAME_TOOL),
                None => ([0.0, 0.0, 0.0, 1.0], FRAME_LED),
            };
            if rec.orientation_wxyz.is_some() {
                ros2msg::pose_stamped(stamp, frame_id, &p_m, &q, &mut self.buf);
                self.put(1, stamp, publish)?;
                self.counts.pose += 1;
            }
            ros2msg::tf_message(stamp, frame_id, child, &p_m, &q, &mut self.buf);
            self.put(2, stamp, publish)?;
            self.counts.tf += 1;
        }
        ros2msg::record_status(rec, &mut self.buf);
        self.put(3, stamp, publish)?;
        self.counts.status += 1;
        self.close_full_chunk(stamp)
    }

    /// Writes the last chunk and the summary and index sections; the file is complete after
    /// this. On failure the chunks before stay readable (the error says how many).
    pub fn finish(mut self) -> Result<McapCounts> {
        let mut w = match self.writer.take() {
            Some(w) => w,
            None => return Err(self.writer().err().unwrap_or(InteropError::Mcap {
                what: "summary".into(),
                reason: "the recording is finished".into(),
            })),
        };
        if let Err(e) = w.flush() {
            self.writer = Some(w);
            return Err(self.stop(e.to_string()));
        }
        self.records_committed = self.records_written;
        // The summary goes into memory; the writer's closing flush writes it as the file's
        // last commit (no END after its own footer).
        self.finishing.store(true, std::sync::atomic::Ordering::Relaxed);
        let summary = w.finish();
        let mut sink = w.into_inner();
        if let Some(kept) = sink.stopped().cloned() {
            return Err(stopped_error(kept));
        }
        summary.map_err(err("summary"))?;
        if let Err(e) = sink.finish() {
            let kept = sink.stopped().cloned().unwrap_or(Kept {
                reason: e.to_string(),
                bytes: 0,
                commits: 0,
                end_written: false,
            });
            return Err(stopped_error(kept));
        }
        Ok(self.counts)
    }
}

#[cfg(test)]
mod tests {
    use super::file::tests::SmallDisk;
    use super::*;
    use irtrack_core::stream::{PositionRecord, TrackStatus};
    use std::sync::{Arc, Mutex};

    /// A [`SmallDisk`] the test can read while the recorder owns it.
    struct Shared(Arc<Mutex<SmallDisk>>);
    impl RecordingFile for Shared {
        fn write_all_at_offset(&mut self, o: u64, d: &[u8]) -> std::io::Result<()> {
            self.0.lock().unwrap().write_all_at_offset(o, d)
        }
        fn truncate_to(&mut self, l: u64) -> std::io::Result<()> {
            self.0.lock().unwrap().truncate_to(l)
        }
    }

    fn disk(capacity_bytes: usize) -> Arc<Mutex<SmallDisk>> {
        Arc::new(Mutex::new(SmallDisk {
            data: Vec::new(),
            capacity_bytes,
        }))
    }

    const PERIOD_NS: u64 = 8_333_333;

    fn record(frame: u64) -> PositionRecord {
        PositionRecord {
            frame,
            capture_ts_ns: 1_000_000_000 + frame * PERIOD_NS,
            position_mm: Some([1.0, 2.0, 1000.0 + frame as f64]),
            orientation_wxyz: Some([1.0, 0.0, 0.0, 0.0]),
            gap_mm: 0.1,
            status: TrackStatus::Ok,
            cameras_used: 2,
            world_frame: false,
            latency_us: 50,
            params_crc: 7,
        }
    }

    /// Messages a reader finds in `bytes` (the mcap crate's linear reader, to the end magic)
    /// and the frame numbers of the position messages (z = 1 m + frame mm), in file order.
    fn read_back(bytes: &[u8]) -> (usize, Vec<u64>) {
        let mut n = 0;
        let mut frames = Vec::new();
        for m in mcap::MessageStream::new(bytes).unwrap() {
            let m = m.unwrap();
            n += 1;
            if m.channel.topic == TOPIC_POSITION {
                // CDR: header 4, stamp 8, frame id (u32 length + text + NUL), pad to 8, x y z.
                let id_len = u32::from_le_bytes(m.data[12..16].try_into().unwrap()) as usize;
                let at = (16 + id_len - 4).div_ceil(8) * 8 + 4 + 16;
                let z = f64::from_le_bytes(m.data[at..at + 8].try_into().unwrap());
                frames.push((z * 1e3 - 1000.0).round() as u64);
            }
        }
        (n, frames)
    }

    #[test]
    fn the_file_reads_after_every_chunk_and_is_complete_after_finish() {
        let disk = disk(usize::MAX);
        // Chunks of 10 records (4 messages each).
        let mut rec = McapRecorder::new(Shared(disk.clone()), 0)
            .unwrap()
            .with_chunk_limits(u64::MAX, 10 * PERIOD_NS - 1);
        // The header alone is a readable, empty recording.
        assert_eq!(read_back(&disk.lock().unwrap().data).0, 0);
        for f in 0..35 {
            rec.write(&record(f)).unwrap();
            let (n, frames) = read_back(&disk.lock().unwrap().data);
            // Whole chunks only: the records of the chunks closed so far.
            assert_eq!(n % 40, 0, "frame {f}: {n} messages on file");
            assert_eq!(frames, (0..(n / 4) as u64).collect::<Vec<_>>());
            assert_eq!(n / 40, (f as usize + 1) / 10, "frame {f}");
        }
        assert!(rec.has_open_chunk());
        let counts = rec.finish().unwrap();
        assert_eq!(counts.status, 35);
        let data = disk.lock().unwrap().data.clone();
        assert_eq!(read_back(&data).1, (0..35).collect::<Vec<_>>());
        // The finished file has its summary: statistics and chunk indexes.
        let summary = mcap::Summary::read(&data).unwrap().unwrap();
        assert_eq!(summary.stats.unwrap().message_count, 35 * 4);
        assert_eq!(summary.chunk_indexes.len(), 5);
    }

    #[test]
    fn a_full_disk_stops_the_recording_and_keeps_every_whole_chunk() {
        let disk = disk(6000);
        let mut rec = McapRecorder::new(Shared(disk.clone()), 0)
            .unwrap()
            .with_chunk_limits(u64::MAX, 5 * PERIOD_NS - 1);
        let mut written = 0u64;
        let err = loop {
            match rec.write(&record(written)) {
                Ok(()) => written += 1,
                Err(e) => break e,
            }
            assert!(written < 1000, "the disk never filled");
        };
        let text = err.to_string();
        assert!(
            text.starts_with("writing the MCAP file failed:") && text.contains("stay readable"),
            "{text}"
        );
        let kept = rec.stopped().unwrap().clone();
        assert!(kept.end_written && kept.commits > 2, "{kept:?}");
        // Later records are refused with the same reason.
        assert!(matches!(
            rec.write(&record(written)),
            Err(InteropError::RecordingStopped { .. })
        ));
        let data = disk.lock().unwrap().data.clone();
        assert_eq!(data.len() as u64, kept.bytes + file::END_LEN as u64);
        let (n, frames) = read_back(&data);
        // Every record of every whole chunk, in order: chunks of 5 records, 4 messages each.
        assert!(n >= 40, "{n}");
        assert_eq!(n % 20, 0);
        assert_eq!(frames, (0..(n / 4) as u64).collect::<Vec<_>>());
        assert!((n / 4) as u64 <= written + 1);
        // The recorder's finish reports the same failure.
        assert!(matches!(
            rec.finish(),
            Err(InteropError::RecordingStopped { .. })
        ));
    }

    #[test]
    fn a_disk_too_full_for_the_header_fails_at_start_and_leaves_an_empty_file() {
        let disk = disk(100);
        let e = McapRecorder::new(Shared(disk.clone()), 0).err().unwrap();
        assert!(e.to_string().contains("nothing of this file is readable"), "{e}");
        assert!(disk.lock().unwrap().data.is_empty());
    }
}
