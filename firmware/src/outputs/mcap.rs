//! MCAP recordings with ROS 2 schemas (docs/outputs.md, "MCAP"), so Foxglove and `ros2 bag`
//! open them: positions (`geometry_msgs/msg/PointStamped`), tool poses (`PoseStamped`), `/tf`
//! (`tf2_msgs/msg/TFMessage`) and per-record status (`diagnostic_msgs/msg/DiagnosticStatus`),
//! every payload CDR. Used by `host-tools record --mcap` and irtrackd's `[outputs.mcap]`.

use std::collections::BTreeMap;
use std::io::{Seek, Write};

use irtrack_core::stream::{PositionRecord, TrackStatus};

use super::ros2msg;
use crate::error::{FirmwareError, Result};

pub const TOPIC_POSITION: &str = "/irtrack/position";
pub const TOPIC_POSE: &str = "/irtrack/pose";
pub const TOPIC_TF: &str = "/tf";
pub const TOPIC_STATUS: &str = "/irtrack/status";

/// Frame id of records in camera 0's frame (REP 103's optical axes: x right, y down, z ahead).
pub const FRAME_CAMERA0: &str = "irtrack_camera0_optical";
/// Frame id of records in the registered world (robot base) frame.
pub const FRAME_WORLD: &str = "irtrack_world";
/// Child frame of `/tf` for a tool (6-DOF) and for the single LED.
pub const FRAME_TOOL: &str = "irtrack_tool";
pub const FRAME_LED: &str = "irtrack_led";

/// Messages written per topic.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct McapCounts {
    pub position: u64,
    pub pose: u64,
    pub tf: u64,
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
    pub counts: McapCounts,
}

fn err(e: impl std::fmt::Display) -> FirmwareError {
    FirmwareError::Output {
        what: "MCAP recording",
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
        let mut writer = opts.create(out).map_err(err)?;
        let mut channels = [0u16; 4];
        for (slot, (topic, ty)) in channels.iter_mut().zip([
            (TOPIC_POSITION, ros2msg::POINT_STAMPED),
            (TOPIC_POSE, ros2msg::POSE_STAMPED),
            (TOPIC_TF, ros2msg::TF_MESSAGE),
            (TOPIC_STATUS, ros2msg::DIAGNOSTIC_STATUS),
        ]) {
            let text = ros2msg::schema(ty).ok_or_else(|| err(format!("no schema for {ty}")))?;
            let schema = writer.add_schema(ty, "ros2msg", text.as_bytes()).map_err(err)?;
            *slot = writer
                .add_channel(schema, topic, "cdr", &BTreeMap::new())
                .map_err(err)?;
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
            .map_err(err)
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
        self.writer.finish().map_err(err)?;
        Ok(self.counts)
    }
}

/// Wall clock minus the monotonic clock, now: the offset for [`McapRecorder::new`] on the
/// machine whose clock stamped the records.
pub fn local_wall_offset_ns() -> i128 {
    let wall = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i128);
    wall - i128::from(crate::clock::monotonic_ns())
}
