//! MCAP recordings with ROS 2 schemas (docs/outputs.md, "MCAP"), so Foxglove and `ros2 bag`
//! open them: positions (`geometry_msgs/msg/PointStamped`), tool poses (`PoseStamped`), `/tf`
//! (`tf2_msgs/msg/TFMessage`) and per-record status (`diagnostic_msgs/msg/DiagnosticStatus`),
//! every payload CDR. Used by `host-tools record --mcap` and irtrackd's `[outputs.mcap]`.
//! The per-record path reuses one buffer; only the MCAP writer's own index grows.

use std::collections::BTreeMap;
use std::io::{Seek, Write};

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

/// Writes position records into an MCAP file.
pub struct McapRecorder<W: Write + Seek> {
    writer: mcap::Writer<W>,
    channels: [u16; 4],
    sequence: u32,
    /// Added to the records' monotonic capture times to give wall-clock stamps.
    offset_ns: i128,
    buf: Vec<u8>,
    /// Messages written so far.
    pub counts: McapCounts,
}

fn err(what: &str) -> impl FnOnce(mcap::McapError) -> InteropError + '_ {
    move |e| InteropError::Mcap {
        what: what.to_string(),
        reason: e.to_string(),
    }
}

impl<W: Write + Seek> McapRecorder<W> {
    /// Starts a recording. `offset_ns` turns capture times (the tracker's monotonic clock) into
    /// the wall-clock stamps ROS tools expect: wall time now − capture clock now.
    pub fn new(out: W, offset_ns: i128) -> Result<Self> {
        let opts = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("irtrack ", env!("CARGO_PKG_VERSION")))
            // No compression: the appliance build stays free of C compression libraries.
            .compression(None);
        let mut writer = opts.create(out).map_err(err("header"))?;
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
        Ok(Self {
            writer,
            channels,
            sequence: 0,
            offset_ns,
            buf: Vec::with_capacity(256),
            counts: McapCounts::default(),
        })
    }

    fn put(&mut self, channel: usize, log_ns: u64, publish_ns: u64) -> Result<()> {
        self.sequence = self.sequence.wrapping_add(1);
        let header = mcap::records::MessageHeader {
            channel_id: self.channels[channel],
            sequence: self.sequence,
            log_time: log_ns,
            publish_time: publish_ns,
        };
        self.writer
            .write_to_known_channel(&header, &self.buf)
            .map_err(err("message"))
    }

    fn wall(&self, mono_ns: u64) -> u64 {
        u64::try_from(i128::from(mono_ns) + self.offset_ns).unwrap_or(0)
    }

    /// Writes one record: always its status; its position, `/tf` and (with an orientation)
    /// its pose when it is tracked. Positions in metres, in the record's own frame.
    pub fn write(&mut self, rec: &PositionRecord) -> Result<()> {
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
        Ok(())
    }

    /// Writes the summary and index sections; the file is complete after this.
    pub fn finish(mut self) -> Result<McapCounts> {
        self.writer.finish().map_err(err("summary"))?;
        Ok(self.counts)
    }
}
