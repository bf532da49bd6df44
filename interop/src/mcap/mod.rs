//! MCAP recordings with ROS 2 schemas (docs/outputs.md, "MCAP"), so Foxglove and `ros2 bag`
//! open them, on the topics and `/tf` frames irtrackd's live ROS 2 output uses (namespace
//! `/irtrack`): every tool's pose (`geometry_msgs/msg/PoseStamped` on `/irtrack/<tool>/pose`),
//! the single LED (`PointStamped` on `/irtrack/led/point`), the loose LEDs beside tools
//! (`sensor_msgs/msg/PointCloud2` on `/irtrack/loose/points`), `/tf` (tracker → `irtrack_<tool>`),
//! `/tf_static` (robot base → tracker) and every record's status as a
//! `diagnostic_msgs/msg/DiagnosticArray` on `/diagnostics`; every payload CDR, every channel
//! with the `offered_qos_profiles` the ros2 profile asks for. Used by `host-tools record
//! --mcap` and irtrackd's `[outputs.mcap]`. The per-record path reuses one buffer; only the
//! MCAP writer's own index grows.
//!
//! The file is written a closed chunk at a time ([`file`]): it is a readable MCAP after every
//! chunk, and a write that fails (a full disk) leaves every chunk before it readable.

pub mod file;

use std::collections::BTreeMap;

use file::CommitSink;
pub use file::{Kept, RecordingFile};

use irtrack_core::stream::{PositionRecord, TrackStatus};

use crate::ros2msg::{self, TfChild, ros_token};
use crate::{InteropError, Result};

/// Namespace of the per-model topics, as the live ROS 2 output's default.
pub const NAMESPACE: &str = "/irtrack";
/// Topic of the transforms (`tf2_msgs/msg/TFMessage`).
pub const TOPIC_TF: &str = "/tf";
/// Topic of the registration, robot base → tracker (`tf2_msgs/msg/TFMessage`).
pub const TOPIC_TF_STATIC: &str = "/tf_static";
/// Topic of every record's status (`diagnostic_msgs/msg/DiagnosticArray`).
pub const TOPIC_DIAGNOSTICS: &str = "/diagnostics";
/// Topic of the single LED's position (`geometry_msgs/msg/PointStamped`).
pub const TOPIC_LED_POINT: &str = "/irtrack/led/point";
/// Topic of the loose LEDs beside tools (`sensor_msgs/msg/PointCloud2`).
pub const TOPIC_LOOSE: &str = "/irtrack/loose/points";

pub use crate::ros2msg::{FRAME_CAMERA0, FRAME_WORLD};

/// Child frame of `/tf` for the single LED (identity rotation).
pub const FRAME_LED: &str = "irtrack_led";

/// The pose topic of a tool: `/irtrack/<tool>/pose` (name as a ROS token).
pub fn pose_topic(tool: &str) -> String {
    format!("{NAMESPACE}/{}/pose", ros_token(tool))
}

/// The `/tf` child frame of a tool: `irtrack_<tool>` (name as a ROS token).
pub fn child_frame(tool: &str) -> String {
    format!("irtrack_{}", ros_token(tool))
}

/// `offered_qos_profiles` (rosbag2's YAML) of a live publisher: keep last 5, best effort,
/// volatile (ROS 2's sensor-data profile, the live output's default); durations infinite.
const QOS_SENSOR_DATA: &str = "- history: 1\n  depth: 5\n  reliability: 2\n  durability: 2\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n";
/// `/tf_static`'s: keep last 1, reliable, transient local (late joiners get it).
const QOS_STATIC: &str = "- history: 1\n  depth: 1\n  reliability: 1\n  durability: 1\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n";
/// `/diagnostics`': keep last 10, reliable, volatile (as ROS 2's diagnostic updater).
const QOS_DIAGNOSTICS: &str = "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 2147483647\n    nsec: 4294967295\n  lifespan:\n    sec: 2147483647\n    nsec: 4294967295\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 2147483647\n    nsec: 4294967295\n  avoid_ros_namespace_conventions: false\n";

/// Messages written per kind.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct McapCounts {
    /// Single-LED points ([`TOPIC_LED_POINT`]).
    pub position: u64,
    /// Tool poses (every tool's topic).
    pub pose: u64,
    /// Loose-LED clouds ([`TOPIC_LOOSE`]).
    pub loose: u64,
    /// On [`TOPIC_TF`].
    pub tf: u64,
    /// On [`TOPIC_DIAGNOSTICS`] (one per record).
    pub status: u64,
}

/// A tracked tool in one frame set: its reported point (tip, else origin) in the record's
/// frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolPose<'a> {
    /// The tool's name in the parameter set.
    pub name: &'a str,
    /// Position, metres.
    pub position_m: [f64; 3],
    /// Orientation, x y z w.
    pub orientation_xyzw: [f64; 4],
}

/// One frame set as recorded.
#[derive(Debug, Clone, Copy)]
pub struct FrameSet<'a> {
    /// The set's main record: stamps, status (`/diagnostics`), frame.
    pub record: &'a PositionRecord,
    /// The tools tracked in this set.
    pub tools: &'a [ToolPose<'a>],
    /// The single LED (a set without tools), when tracked; metres.
    pub led_m: Option<[f64; 3]>,
    /// The loose LEDs beside tools, (stable id, metres); `Some(&[])` records an empty cloud,
    /// `None` none (no per-tool records for this set).
    pub loose: Option<&'a [(u32, [f64; 3])]>,
    /// Records the recorder skipped so far (a `/diagnostics` value).
    pub skipped: u64,
}

/// A rotation (x y z w) applied to a vector.
fn rotate(q: [f64; 4], v: [f64; 3]) -> [f64; 3] {
    let (u, w) = ([q[0], q[1], q[2]], q[3]);
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let t = cross(u, v).map(|c| 2.0 * c);
    let ut = cross(u, t);
    [
        v[0] + w * t[0] + ut[0],
        v[1] + w * t[1] + ut[1],
        v[2] + w * t[2] + ut[2],
    ]
}

/// Quaternion product a ⊗ b (x y z w).
fn quat_mul(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
    [
        a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
        a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
        a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
        a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
    ]
}

/// The channels of one tool.
struct ToolChannel {
    name: String,
    pose: u16,
    child: String,
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
    /// `/tf` and `/diagnostics`; the others once first used.
    tf: u16,
    diagnostics: u16,
    led: Option<u16>,
    loose: Option<u16>,
    tools: Vec<ToolChannel>,
    /// Tracker (camera 0) from robot base, x y z w and metres: `/tf` hangs world-frame poses
    /// under the tracker frame with it.
    cam0_from_world: Option<([f64; 4], [f64; 3])>,
    /// The tool name [`McapRecorder::write`] gives a 6-DOF record.
    default_tool: String,
    transforms: Vec<([f64; 3], [f64; 4])>,
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

/// Adds `topic` of type `ty` with its schema and QoS metadata.
fn add_channel<W: std::io::Write + std::io::Seek>(
    writer: &mut mcap::Writer<W>,
    topic: &str,
    ty: &str,
    qos: &str,
) -> Result<u16> {
    let text = ros2msg::schema(ty).ok_or_else(|| InteropError::UnknownType {
        type_name: ty.to_string(),
    })?;
    let schema = writer
        .add_schema(ty, "ros2msg", text.as_bytes())
        .map_err(err(ty))?;
    let metadata = BTreeMap::from([("offered_qos_profiles".to_string(), qos.to_string())]);
    writer
        .add_channel(schema, topic, "cdr", &metadata)
        .map_err(err(topic))
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
        let tf = add_channel(&mut writer, TOPIC_TF, ros2msg::TF_MESSAGE, QOS_SENSOR_DATA)?;
        let diagnostics = add_channel(
            &mut writer,
            TOPIC_DIAGNOSTICS,
            ros2msg::DIAGNOSTIC_ARRAY,
            QOS_DIAGNOSTICS,
        )?;
        let mut rec = Self {
            writer: Some(writer),
            stopped: None,
            finishing,
            tf,
            diagnostics,
            led: None,
            loose: None,
            tools: Vec::new(),
            cam0_from_world: None,
            default_tool: "tool".into(),
            transforms: Vec::new(),
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

    /// The name [`Self::write`] gives the tool of a 6-DOF record (default `tool`): a
    /// client of the position stream's main records does not learn the tool's name.
    pub fn with_tool_name(mut self, name: &str) -> Self {
        self.default_tool = name.to_string();
        self
    }

    /// The registration (robot base from tracker: rotation x y z w, translation metres), or
    /// none: written once on `/tf_static` (`irtrack_world` → `irtrack_camera0_optical`, stamp
    /// `stamp_ns` on the monotonic clock) and used to hang world-frame poses under the tracker
    /// in `/tf`.
    pub fn set_registration(
        &mut self,
        world_from_cam0: Option<([f64; 4], [f64; 3])>,
        stamp_ns: u64,
    ) -> Result<()> {
        self.cam0_from_world = world_from_cam0.map(|(q, t)| {
            let inv = [-q[0], -q[1], -q[2], q[3]];
            let t_inv = rotate(inv, t).map(|c| -c);
            (inv, t_inv)
        });
        let Some((q, t)) = world_from_cam0 else {
            return Ok(());
        };
        let w = self.writer()?;
        let channel = add_channel(w, TOPIC_TF_STATIC, ros2msg::TF_MESSAGE, QOS_STATIC)?;
        let stamp = self.wall(stamp_ns);
        let child = [TfChild {
            child: FRAME_CAMERA0,
            t_m: t,
            q_xyzw: q,
        }];
        ros2msg::tf_message_of(stamp, FRAME_WORLD, &child, &mut self.buf);
        self.put(channel, stamp, stamp)
    }

    fn put(&mut self, channel_id: u16, log_ns: u64, publish_ns: u64) -> Result<()> {
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: self.sequence,
            log_time: log_ns,
            publish_time: publish_ns,
        };
        let buf = std::mem::take(&mut self.buf);
        let res = self
            .writer()
            .and_then(|w| w.write_to_known_channel(&header, &buf).map_err(err("message")));
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

    /// Writes one record (the position stream's main record): a tracked 6-DOF record as the
    /// pose of the tool named by [`Self::with_tool_name`], a tracked position without
    /// orientation as the single LED; always its status.
    pub fn write(&mut self, rec: &PositionRecord) -> Result<()> {
        let tracked = rec.status == TrackStatus::Ok;
        let p_m = rec.position_mm.map(|p| [p[0] / 1e3, p[1] / 1e3, p[2] / 1e3]);
        let name = std::mem::take(&mut self.default_tool);
        let tool = match (tracked, p_m, rec.orientation_wxyz) {
            (true, Some(p), Some(q)) => Some(ToolPose {
                name: &name,
                position_m: p,
                orientation_xyzw: [q[1], q[2], q[3], q[0]],
            }),
            _ => None,
        };
        let led_m = match (tracked, p_m, rec.orientation_wxyz) {
            (true, Some(p), None) => Some(p),
            _ => None,
        };
        let res = self.write_set(&FrameSet {
            record: rec,
            tools: tool.as_slice(),
            led_m,
            loose: None,
            skipped: 0,
        });
        self.default_tool = name;
        res
    }

    /// The pose channel of `tool` (added on first use).
    fn tool_channel(&mut self, tool: &str) -> Result<usize> {
        if let Some(i) = self.tools.iter().position(|t| t.name == tool) {
            return Ok(i);
        }
        let topic = pose_topic(tool);
        let pose = add_channel(self.writer()?, &topic, ros2msg::POSE_STAMPED, QOS_SENSOR_DATA)?;
        self.tools.push(ToolChannel {
            name: tool.to_string(),
            pose,
            child: child_frame(tool),
        });
        Ok(self.tools.len() - 1)
    }

    /// A pose in the record's frame as `/tf` gives it: under the tracker frame.
    fn tracker_pose(&self, world: bool, p_m: [f64; 3], q: [f64; 4]) -> ([f64; 3], [f64; 4]) {
        match (world, self.cam0_from_world) {
            (true, Some((rq, rt))) => {
                let p = rotate(rq, p_m);
                ([p[0] + rt[0], p[1] + rt[1], p[2] + rt[2]], quat_mul(rq, q))
            }
            _ => (p_m, q),
        }
    }

    /// Writes one frame set: each tracked tool's pose, the single LED's point, the loose
    /// LEDs' cloud, one `/tf` message with every transform, and the status on
    /// `/diagnostics`. Positions in metres, in the record's own frame.
    pub fn write_set(&mut self, set: &FrameSet<'_>) -> Result<()> {
        self.writer()?;
        self.records_written += 1;
        let rec = set.record;
        let stamp = self.wall(rec.capture_ts_ns);
        let publish = self.wall(rec.capture_ts_ns + u64::from(rec.latency_us) * 1000);
        let frame_id = if rec.world_frame {
            FRAME_WORLD
        } else {
            FRAME_CAMERA0
        };
        let mut transforms = std::mem::take(&mut self.transforms);
        transforms.clear();
        let mut tool_idx = [0usize; 16];
        for (k, tool) in set.tools.iter().enumerate() {
            let i = self.tool_channel(tool.name)?;
            if let Some(slot) = tool_idx.get_mut(k) {
                *slot = i;
            }
            ros2msg::pose_stamped(
                stamp,
                frame_id,
                &tool.position_m,
                &tool.orientation_xyzw,
                &mut self.buf,
            );
            self.put(self.tools[i].pose, stamp, publish)?;
            self.counts.pose += 1;
            transforms.push(self.tracker_pose(rec.world_frame, tool.position_m, tool.orientation_xyzw));
        }
        if let Some(p) = set.led_m {
            let channel = match self.led {
                Some(c) => c,
                None => {
                    let c = add_channel(
                        self.writer()?,
                        TOPIC_LED_POINT,
                        ros2msg::POINT_STAMPED,
                        QOS_SENSOR_DATA,
                    )?;
                    self.led = Some(c);
                    c
                }
            };
            ros2msg::point_stamped(stamp, frame_id, &p, &mut self.buf);
            self.put(channel, stamp, publish)?;
            self.counts.position += 1;
            transforms.push(self.tracker_pose(rec.world_frame, p, [0.0, 0.0, 0.0, 1.0]));
        }
        if let Some(points) = set.loose {
            let channel = match self.loose {
                Some(c) => c,
                None => {
                    let c = add_channel(
                        self.writer()?,
                        TOPIC_LOOSE,
                        ros2msg::POINT_CLOUD2,
                        QOS_SENSOR_DATA,
                    )?;
                    self.loose = Some(c);
                    c
                }
            };
            ros2msg::loose_cloud(stamp, frame_id, points, &mut self.buf);
            self.put(channel, stamp, publish)?;
            self.counts.loose += 1;
        }
        if !transforms.is_empty() {
            // Children: the tools in order, then the LED (`transforms` has that order).
            let n_tools = set.tools.len().min(tool_idx.len());
            let children: Vec<TfChild<'_>> = transforms
                .iter()
                .enumerate()
                .map(|(k, (t, q))| TfChild {
                    child: if k < n_tools {
                        self.tools[tool_idx[k]].child.as_str()
                    } else {
                        FRAME_LED
                    },
                    t_m: *t,
                    q_xyzw: *q,
                })
                .collect();
            // Under the tracker frame; world-frame records without a registration (a stream
            // client's recording) under the world frame they are in.
            let parent = if rec.world_frame && self.cam0_from_world.is_none() {
                FRAME_WORLD
            } else {
                FRAME_CAMERA0
            };
            let mut buf = std::mem::take(&mut self.buf);
            ros2msg::tf_message_of(stamp, parent, &children, &mut buf);
            drop(children);
            self.buf = buf;
            self.put(self.tf, stamp, publish)?;
            self.counts.tf += 1;
        }
        self.transforms = transforms;
        let extra = [
            ("tools_tracked", set.tools.len() as u64),
            ("loose_leds", set.loose.map_or(0, |l| l.len() as u64)),
            ("records_skipped", set.skipped),
        ];
        ros2msg::diagnostic_array(stamp, rec, &extra, &mut self.buf);
        self.put(self.diagnostics, stamp, publish)?;
        self.counts.status += 1;
        self.close_full_chunk(stamp)
    }

    /// Adds a metadata record (`name` and key/value pairs) to the recording, e.g. the
    /// recorder's counts at the end.
    pub fn write_metadata(&mut self, name: &str, entries: BTreeMap<String, String>) -> Result<()> {
        let metadata = mcap::records::Metadata {
            name: name.to_string(),
            metadata: entries,
        };
        self.writer()?
            .write_metadata(&metadata)
            .map_err(err("metadata"))?;
        // The writer closed the open chunk before the metadata: both go on file now.
        self.commit()
    }

    /// Writes the last chunk and the summary and index sections; the file is complete after
    /// this. On failure the chunks before stay readable (the error says how many).
    pub fn finish(mut self) -> Result<McapCounts> {
        let mut w = match self.writer.take() {
            Some(w) => w,
            None => {
                return Err(self.writer().err().unwrap_or(InteropError::Mcap {
                    what: "summary".into(),
                    reason: "the recording is finished".into(),
                }));
            }
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
    /// and the frame numbers of the tool's poses (z = 1 m + frame mm), in file order.
    fn read_back(bytes: &[u8]) -> (usize, Vec<u64>) {
        let mut n = 0;
        let mut frames = Vec::new();
        for m in mcap::MessageStream::new(bytes).unwrap() {
            let m = m.unwrap();
            n += 1;
            if m.channel.topic == "/irtrack/tool/pose" {
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
        // Chunks of 10 records (3 messages each: pose, /tf, /diagnostics).
        let mut rec = McapRecorder::new(Shared(disk.clone()), 0)
            .unwrap()
            .with_chunk_limits(u64::MAX, 9 * PERIOD_NS);
        // The header alone is a readable, empty recording.
        assert_eq!(read_back(&disk.lock().unwrap().data).0, 0);
        for f in 0..35 {
            rec.write(&record(f)).unwrap();
            let (n, frames) = read_back(&disk.lock().unwrap().data);
            // Whole chunks only: the records of the chunks closed so far.
            assert_eq!(n % 30, 0, "frame {f}: {n} messages on file");
            assert_eq!(frames, (0..(n / 3) as u64).collect::<Vec<_>>());
            assert_eq!(n / 30, (f as usize + 1) / 10, "frame {f}");
        }
        assert!(rec.has_open_chunk());
        let counts = rec.finish().unwrap();
        assert_eq!(counts.status, 35);
        let data = disk.lock().unwrap().data.clone();
        assert_eq!(read_back(&data).1, (0..35).collect::<Vec<_>>());
        // The finished file has its summary: statistics and chunk indexes.
        let summary = mcap::Summary::read(&data).unwrap().unwrap();
        assert_eq!(summary.stats.unwrap().message_count, 35 * 3);
        assert_eq!(summary.chunk_indexes.len(), 5);
    }

    #[test]
    fn a_full_disk_stops_the_recording_and_keeps_every_whole_chunk() {
        let disk = disk(12_000);
        let mut rec = McapRecorder::new(Shared(disk.clone()), 0)
            .unwrap()
            .with_chunk_limits(u64::MAX, 4 * PERIOD_NS);
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
        // Every record of every whole chunk, in order: chunks of 5 records, 3 messages each.
        assert!(n >= 30, "{n}");
        assert_eq!(n % 15, 0);
        assert_eq!(frames, (0..(n / 3) as u64).collect::<Vec<_>>());
        assert!((n / 3) as u64 <= written + 1);
        // The recorder's finish reports the same failure.
        assert!(matches!(rec.finish(), Err(InteropError::RecordingStopped { .. })));
    }

    #[test]
    fn a_disk_too_full_for_the_header_fails_at_start_and_leaves_an_empty_file() {
        let disk = disk(100);
        let e = McapRecorder::new(Shared(disk.clone()), 0).err().unwrap();
        assert!(e.to_string().contains("nothing of this file is readable"), "{e}");
        assert!(disk.lock().unwrap().data.is_empty());
    }

    #[test]
    fn every_tool_and_the_loose_leds_go_on_live_ros2_topics_with_qos_metadata() {
        let disk = disk(usize::MAX);
        let mut rec = McapRecorder::new(Shared(disk.clone()), 0).unwrap();
        // Robot base from tracker: 90° about z, 1 m along x.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        rec.set_registration(Some(([0.0, 0.0, h, h], [1.0, 0.0, 0.0])), 1_000)
            .unwrap();
        let mut main = record(1);
        main.world_frame = true;
        let tools = [
            ToolPose {
                name: "probe4",
                position_m: [1.0, 2.0, 0.0],
                orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            },
            ToolPose {
                name: "my tool-2",
                position_m: [0.0, 0.0, 1.0],
                orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
            },
        ];
        let loose = [(7u32, [0.5, 0.25, 2.0])];
        rec.write_set(&FrameSet {
            record: &main,
            tools: &tools,
            led_m: None,
            loose: Some(&loose),
            skipped: 3,
        })
        .unwrap();
        rec.write_metadata(
            "irtrack_recorder",
            BTreeMap::from([("records_skipped".into(), "3".into())]),
        )
        .unwrap();
        rec.finish().unwrap();
        let data = disk.lock().unwrap().data.clone();
        let mut topics = BTreeMap::new();
        for m in mcap::MessageStream::new(&data).unwrap() {
            let m = m.unwrap();
            let qos = m
                .channel
                .metadata
                .get("offered_qos_profiles")
                .cloned()
                .unwrap_or_default();
            assert!(
                qos.starts_with("- history: 1\n  depth: "),
                "{}: {qos}",
                m.channel.topic
            );
            let ty = m.channel.schema.as_ref().unwrap().name.clone();
            topics.insert(m.channel.topic.clone(), (ty, m.data.to_vec()));
        }
        let names: Vec<&str> = topics.keys().map(String::as_str).collect();
        assert_eq!(
            names,
            [
                "/diagnostics",
                "/irtrack/loose/points",
                "/irtrack/my_tool_2/pose",
                "/irtrack/probe4/pose",
                "/tf",
                "/tf_static"
            ]
        );
        assert_eq!(topics["/diagnostics"].0, ros2msg::DIAGNOSTIC_ARRAY);
        assert_eq!(topics["/irtrack/loose/points"].0, ros2msg::POINT_CLOUD2);
        // /tf: both tools under the tracker frame, world poses turned back: tracker from
        // world is -90° about z after -1 m along x, so (1, 2, 0) → (2, 0, 0).
        let tf = &topics["/tf"].1;
        let text = String::from_utf8_lossy(tf);
        assert!(
            text.contains("irtrack_probe4") && text.contains("irtrack_my_tool_2"),
            "{text}"
        );
        let f64_at = |b: &[u8], at: usize| f64::from_le_bytes(b[at..at + 8].try_into().unwrap());
        let child_at = tf.windows(15).position(|w| w == b"irtrack_probe4\0").unwrap();
        let t_at = (child_at + 15 - 4).div_ceil(8) * 8 + 4;
        let t = [f64_at(tf, t_at), f64_at(tf, t_at + 8), f64_at(tf, t_at + 16)];
        for (got, want) in t.iter().zip([2.0, 0.0, 0.0]) {
            assert!((got - want).abs() < 1e-12, "{t:?}");
        }
        let metadata: Vec<_> = mcap::read::LinearReader::new(&data)
            .unwrap()
            .filter_map(|r| match r.unwrap() {
                mcap::records::Record::Metadata(m) => Some(m),
                _ => None,
            })
            .collect();
        assert_eq!(metadata.len(), 1);
        assert_eq!(metadata[0].metadata["records_skipped"], "3");
    }

    #[test]
    fn quaternion_helpers_agree_with_turning_by_hand() {
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let z90 = [0.0, 0.0, h, h];
        let v = rotate(z90, [1.0, 0.0, 0.0]);
        assert!((v[0]).abs() < 1e-12 && (v[1] - 1.0).abs() < 1e-12, "{v:?}");
        let z180 = quat_mul(z90, z90);
        assert!(
            (z180[2].abs() - 1.0).abs() < 1e-12 && z180[3].abs() < 1e-12,
            "{z180:?}"
        );
    }
}
