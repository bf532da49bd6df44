//! Position stream records: what irtrackd publishes per processed frame set and what
//! `host-tools record` (and robot controllers) read. Spec: docs/stream-protocol.md.
//!
//! Two framings of the same [`PositionRecord`]:
//! - NDJSON: one JSON object per line, stable field names (the Rust field names);
//! - binary: a fixed 104-byte little-endian frame with magic, length and CRC-32.
//!
//! Per-tool records ([`ToolRecord`], `IRTL` frames) and loose-LED records ([`LooseRecord`],
//! `IRLL` frames) extend the position record for clients that ask for every tool.
//!
//! Encoding writes into caller-owned buffers (a reused `String` or a fixed array), so the
//! publishing side does not allocate per frame once the string has its capacity.

use alloc::format;
use alloc::string::String;
use core::fmt::Write as _;
use serde::{Deserialize, Serialize};

use crate::camera::RigidTransform;
use crate::crc::Crc32;
use crate::pose6d::{LooseLed, Pose6d, PoseStatus};
use crate::{Error, Result};

/// Magic of a binary frame.
pub const BINARY_MAGIC: [u8; 4] = *b"IRPS";
/// Binary framing version.
pub const BINARY_VERSION: u8 = 1;
/// Payload bytes between the 8-byte header and the CRC.
pub const BINARY_PAYLOAD_LEN: usize = 92;
/// Total size of one binary frame.
pub const BINARY_FRAME_LEN: usize = 8 + BINARY_PAYLOAD_LEN + 4;
/// Upper bound of an NDJSON record line, newline included; readers may refuse longer lines.
pub const MAX_NDJSON_LINE: usize = 1024;

const FLAG_POSITION: u8 = 0x01;
const FLAG_ORIENTATION: u8 = 0x02;
const FLAG_WORLD_FRAME: u8 = 0x04;
const NDJSON: &str = "position-ndjson";
const BINARY: &str = "position-binary";

/// Tracking state of one record.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackStatus {
    /// Position valid and passed the quality gate.
    Ok,
    /// Marker not seen in enough cameras.
    Lost,
    /// Triangulated but refused by the quality gate (ray gap, blob shape).
    Rejected,
    /// No valid parameter set loaded; nothing can be triangulated.
    NoParams,
    /// Capture or processing fault (camera lost, deadline trouble).
    Fault,
}

impl TrackStatus {
    const ALL: [TrackStatus; 5] = [
        TrackStatus::Ok,
        TrackStatus::Lost,
        TrackStatus::Rejected,
        TrackStatus::NoParams,
        TrackStatus::Fault,
    ];

    /// Code used in NDJSON.
    pub fn as_str(self) -> &'static str {
        match self {
            TrackStatus::Ok => "ok",
            TrackStatus::Lost => "lost",
            TrackStatus::Rejected => "rejected",
            TrackStatus::NoParams => "no_params",
            TrackStatus::Fault => "fault",
        }
    }

    /// Code used in the binary framing.
    pub fn as_u8(self) -> u8 {
        match self {
            TrackStatus::Ok => 0,
            TrackStatus::Lost => 1,
            TrackStatus::Rejected => 2,
            TrackStatus::NoParams => 3,
            TrackStatus::Fault => 4,
        }
    }

    /// From the NDJSON code.
    pub fn from_code(s: &str) -> Option<TrackStatus> {
        TrackStatus::ALL.iter().copied().find(|t| t.as_str() == s)
    }

    /// From the binary code.
    pub fn from_u8(b: u8) -> Option<TrackStatus> {
        TrackStatus::ALL.iter().copied().find(|t| t.as_u8() == b)
    }
}

/// One output of the processing loop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PositionRecord {
    /// Frame-set number since service start.
    pub frame: u64,
    /// Capture timestamp of the frame set (camera 0's kernel timestamp), ns.
    pub capture_ts_ns: u64,
    /// Marker position, mm; `Some` exactly when `status` is [`TrackStatus::Ok`].
    /// World (robot) frame when `world_frame`, else the camera-0 frame.
    pub position_mm: Option<[f64; 3]>,
    /// Tool orientation as a unit quaternion (w, x, y, z) for 6-DOF tools; `None` for a
    /// single LED.
    pub orientation_wxyz: Option<[f64; 4]>,
    /// Quality: gap between the rays (two views) or RMS ray distance (N views), mm.
    /// NaN when nothing was triangulated (null in NDJSON).
    pub gap_mm: f64,
    /// What became of the frame set.
    pub status: TrackStatus,
    /// Cameras in which the marker was found.
    pub cameras_used: u8,
    /// Whether `position_mm` / `orientation_wxyz` are in the registered world frame.
    pub world_frame: bool,
    /// Capture timestamp to publication, µs.
    pub latency_us: u32,
    /// CRC-32 of the active parameter blob (its header CRC), 0 without parameters.
    pub params_crc: u32,
}

/// Quaternion of a rotation matrix by the closed form (a calibrated `world_from_cam0` is
/// orthonormal to rounding; the caller normalises the product).
fn quaternion_from_rotation(r: &nalgebra::Matrix3<f64>) -> nalgebra::Quaternion<f64> {
    let rot = nalgebra::Rotation3::from_matrix_unchecked(*r);
    nalgebra::UnitQuaternion::from_rotation_matrix(&rot).into_inner()
}

fn write_f64(out: &mut String, v: f64) {
    // Display of f64 is the shortest exact decimal without an exponent: valid JSON, but up to
    // ~330 digits for very large or tiny magnitudes, which would push the line past
    // MAX_NDJSON_LINE (found by fuzzing). Those use the shortest exponent form, also valid JSON.
    let a = v.abs();
    if v.is_finite() && a != 0.0 && !(1e-6..1e16).contains(&a) {
        let _ = write!(out, "{v:e}");
    } else if v.is_finite() {
        let _ = write!(out, "{v}");
    } else {
        out.push_str("null");
    }
}

fn write_array(out: &mut String, vals: Option<&[f64]>) {
    match vals {
        None => out.push_str("null"),
        Some(vals) => {
            out.push('[');
            for (i, v) in vals.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                write_f64(out, *v);
            }
            out.push(']');
        }
    }
}

impl PositionRecord {
    /// The record of one 6-DOF frame set: the tool origin and orientation from `pose`
    /// (camera-0 frame), moved into the world frame when `world_from_cam0` is given.
    /// `gap_mm` carries the layout fit's RMS residual (the pose's quality figure). Status:
    /// `Tracked` → `Ok`, `TooFewLeds` → `Lost`, every refusal (ambiguous, residual, step,
    /// merged LEDs) → `Rejected`. `latency_us` and `params_crc` are left 0 for the caller.
    pub fn from_pose(
        frame: u64,
        capture_ts_ns: u64,
        pose: &Pose6d,
        world_from_cam0: Option<&RigidTransform>,
        cameras_used: u8,
    ) -> PositionRecord {
        let status = match pose.status {
            PoseStatus::Tracked => TrackStatus::Ok,
            PoseStatus::TooFewLeds { .. } => TrackStatus::Lost,
            PoseStatus::Ambiguous { .. }
            | PoseStatus::ResidualTooLarge
            | PoseStatus::StepTooLarge
            | PoseStatus::LedsMerged { .. } => TrackStatus::Rejected,
        };
        let tracked = status == TrackStatus::Ok;
        let (position_mm, orientation_wxyz) = match (tracked, world_from_cam0) {
            (false, _) => (None, None),
            (true, None) => (Some(pose.position_mm), Some(pose.quaternion_wxyz)),
            (true, Some(w)) => {
                let p = w.apply(&nalgebra::Vector3::from(pose.position_mm));
                let q = pose.quaternion_wxyz;
                let q_tool = nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]);
                let q_world = quaternion_from_rotation(&w.rotation()) * q_tool;
                let n = q_world.norm();
                let s = if q_world.w < 0.0 { -1.0 / n } else { 1.0 / n };
                (
                    Some([p.x, p.y, p.z]),
                    Some([s * q_world.w, s * q_world.i, s * q_world.j, s * q_world.k]),
                )
            }
        };
        PositionRecord {
            frame,
            capture_ts_ns,
            position_mm,
            orientation_wxyz,
            gap_mm: if tracked { pose.residual_rms_mm } else { f64::NAN },
            status,
            cameras_used: if tracked { cameras_used } else { 0 },
            world_frame: world_from_cam0.is_some(),
            latency_us: 0,
            params_crc: 0,
        }
    }

    /// Appends the NDJSON line (with `\n`) to `out`. Writing into a `String` cannot fail.
    pub fn write_ndjson(&self, out: &mut String) {
        let _ = write!(
            out,
            "{{\"frame\":{},\"capture_ts_ns\":{},\"position_mm\":",
            self.frame, self.capture_ts_ns
        );
        write_array(out, self.position_mm.as_ref().map(|p| &p[..]));
        out.push_str(",\"orientation_wxyz\":");
        write_array(out, self.orientation_wxyz.as_ref().map(|q| &q[..]));
        out.push_str(",\"gap_mm\":");
        write_f64(out, self.gap_mm);
        let _ = writeln!(
            out,
            ",\"status\":\"{}\",\"cameras_used\":{},\"world_frame\":{},\"latency_us\":{},\"params_crc\":{}}}",
            self.status.as_str(),
            self.cameras_used,
            self.world_frame,
            self.latency_us,
            self.params_crc
        );
    }

    /// The NDJSON line as a new string.
    pub fn to_ndjson_line(&self) -> String {
        let mut s = String::with_capacity(256);
        self.write_ndjson(&mut s);
        s
    }

    /// Parses one NDJSON line (trailing newline optional). Unknown keys are ignored so that
    /// newer servers can add fields; `orientation_wxyz`, `world_frame` and `params_crc` may
    /// be absent (None / false / 0); the other fields are required.
    pub fn from_ndjson_line(line: &str) -> Result<PositionRecord> {
        Self::parse_ndjson(line, |_, _| Ok(()))
    }

    /// [`PositionRecord::from_ndjson_line`], handing every key it does not know to `extra`.
    fn parse_ndjson<'a>(
        line: &'a str,
        mut extra: impl FnMut(&str, &Value<'a>) -> Result<()>,
    ) -> Result<PositionRecord> {
        if line.len() > MAX_NDJSON_LINE {
            return Err(ndjson_err(format!("line of {} bytes is too long", line.len())));
        }
        let mut p = JsonParser {
            s: line.as_bytes(),
            pos: 0,
        };
        let mut frame = None;
        let mut ts = None;
        let mut pos: Option<Option<[f64; 3]>> = None;
        let mut quat: Option<[f64; 4]> = None;
        let mut gap = None;
        let mut status = None;
        let mut cams = None;
        let mut world = false;
        let mut latency = None;
        let mut crc = 0u32;
        p.ws();
        p.expect(b'{')?;
        p.ws();
        if !p.eat(b'}') {
            loop {
                p.ws();
                let key = p.string()?;
                p.ws();
                p.expect(b':')?;
                p.ws();
                let v = p.value(0)?;
                match key {
                    "frame" => frame = Some(v.uint(key)?),
                    "capture_ts_ns" => ts = Some(v.uint(key)?),
                    "position_mm" => pos = Some(v.opt_array::<3>(key)?),
                    "orientation_wxyz" => quat = v.opt_array::<4>(key)?,
                    "gap_mm" => gap = Some(v.float_or_nan(key)?),
                    "status" => {
                        let code = v.str(key)?;
                        status = Some(
                            TrackStatus::from_code(code)
                                .ok_or_else(|| ndjson_err(format!("unknown status {code:?}")))?,
                        )
                    }
                    "cameras_used" => cams = Some(narrow(key, v.uint(key)?)?),
                    "world_frame" => world = v.bool(key)?,
                    "latency_us" => latency = Some(narrow(key, v.uint(key)?)?),
                    "params_crc" => crc = narrow(key, v.uint(key)?)?,
                    _ => extra(key, &v)?,
                }
                p.ws();
                if p.eat(b',') {
                    continue;
                }
                p.expect(b'}')?;
                break;
            }
        }
        p.ws();
        if p.pos != p.s.len() {
            return Err(ndjson_err(format!(
                "unexpected text after the object at byte {}",
                p.pos
            )));
        }
        let missing = |k: &str| ndjson_err(format!("missing field \"{k}\""));
        Ok(PositionRecord {
            frame: frame.ok_or_else(|| missing("frame"))?,
            capture_ts_ns: ts.ok_or_else(|| missing("capture_ts_ns"))?,
            position_mm: pos.ok_or_else(|| missing("position_mm"))?,
            orientation_wxyz: quat,
            gap_mm: gap.ok_or_else(|| missing("gap_mm"))?,
            status: status.ok_or_else(|| missing("status"))?,
            cameras_used: cams.ok_or_else(|| missing("cameras_used"))?,
            world_frame: world,
            latency_us: latency.ok_or_else(|| missing("latency_us"))?,
            params_crc: crc,
        })
    }

    /// Writes the binary frame into `out` (layout in docs/stream-protocol.md).
    pub fn encode_binary(&self, out: &mut [u8; BINARY_FRAME_LEN]) {
        self.write_common(
            &mut out[..COMMON_END],
            BINARY_MAGIC,
            BINARY_VERSION,
            BINARY_PAYLOAD_LEN,
        );
        seal(&mut out[..]);
    }

    /// Bytes 0..100 shared by the position, per-tool and loose-LED frames: the header with
    /// `magic`, `version` and `payload_len`, then every field of the record. The caller appends
    /// its own fields (if any) and the CRC ([`seal`]).
    fn write_common(&self, out: &mut [u8], magic: [u8; 4], version: u8, payload_len: usize) {
        let mut flags = 0u8;
        if self.position_mm.is_some() {
            flags |= FLAG_POSITION;
        }
        if self.orientation_wxyz.is_some() {
            flags |= FLAG_ORIENTATION;
        }
        if self.world_frame {
            flags |= FLAG_WORLD_FRAME;
        }
        out[0..4].copy_from_slice(&magic);
        out[4] = version;
        out[5] = flags;
        out[6..8].copy_from_slice(&(payload_len as u16).to_le_bytes());
        out[8..16].copy_from_slice(&self.frame.to_le_bytes());
        out[16..24].copy_from_slice(&self.capture_ts_ns.to_le_bytes());
        let pos = self.position_mm.unwrap_or([0.0; 3]);
        for (i, v) in pos.iter().enumerate() {
            out[24 + 8 * i..32 + 8 * i].copy_from_slice(&v.to_le_bytes());
        }
        let quat = self.orientation_wxyz.unwrap_or([0.0; 4]);
        for (i, v) in quat.iter().enumerate() {
            out[48 + 8 * i..56 + 8 * i].copy_from_slice(&v.to_le_bytes());
        }
        out[80..88].copy_from_slice(&self.gap_mm.to_le_bytes());
        out[88] = self.status.as_u8();
        out[89] = self.cameras_used;
        out[90..92].copy_from_slice(&[0, 0]);
        out[92..96].copy_from_slice(&self.latency_us.to_le_bytes());
        out[96..100].copy_from_slice(&self.params_crc.to_le_bytes());
    }

    /// Reads the record's fields from bytes 5 and 8..100 of a frame whose header and CRC
    /// [`check_frame`] accepted.
    fn read_common(bytes: &[u8]) -> Result<PositionRecord> {
        let flags = bytes[5];
        if flags & !(FLAG_POSITION | FLAG_ORIENTATION | FLAG_WORLD_FRAME) != 0 {
            return Err(binary_err(format!("unknown flags {flags:#04x}")));
        }
        let u64_at = |o: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&bytes[o..o + 8]);
            u64::from_le_bytes(b)
        };
        let f64_at = |o: usize| f64::from_bits(u64_at(o));
        let u32_at = |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        let status = TrackStatus::from_u8(bytes[88])
            .ok_or_else(|| binary_err(format!("unknown status code {}", bytes[88])))?;
        Ok(PositionRecord {
            frame: u64_at(8),
            capture_ts_ns: u64_at(16),
            position_mm: (flags & FLAG_POSITION != 0).then(|| [f64_at(24), f64_at(32), f64_at(40)]),
            orientation_wxyz: (flags & FLAG_ORIENTATION != 0)
                .then(|| [f64_at(48), f64_at(56), f64_at(64), f64_at(72)]),
            gap_mm: f64_at(80),
            status,
            cameras_used: bytes[89],
            world_frame: flags & FLAG_WORLD_FRAME != 0,
            latency_us: u32_at(92),
            params_crc: u32_at(96),
        })
    }

    /// The binary frame as a new array.
    pub fn to_binary(&self) -> [u8; BINARY_FRAME_LEN] {
        let mut out = [0u8; BINARY_FRAME_LEN];
        self.encode_binary(&mut out);
        out
    }

    /// Decodes one binary frame (exactly [`BINARY_FRAME_LEN`] bytes).
    pub fn decode_binary(bytes: &[u8]) -> Result<PositionRecord> {
        check_frame(bytes, BINARY_MAGIC, BINARY_VERSION, BINARY_PAYLOAD_LEN, "")?;
        PositionRecord::read_common(bytes)
    }
}

/// End of the fields shared by the position, per-tool and loose-LED frames.
const COMMON_END: usize = 100;

/// Writes the CRC-32 of everything before the last 4 bytes of `frame` into them.
fn seal(frame: &mut [u8]) {
    let end = frame.len() - 4;
    let mut c = Crc32::new();
    c.update(&frame[..end]);
    let crc = c.finish().to_le_bytes();
    frame[end..].copy_from_slice(&crc);
}

/// Checks a binary frame's length, magic, version, payload length and CRC (`what`: "" for the
/// position frame, "tool-frame " for the per-tool frame, "loose-frame " for the loose-LED
/// frame, as the messages say).
fn check_frame(bytes: &[u8], magic: [u8; 4], version: u8, payload_len: usize, what: &str) -> Result<()> {
    let frame_len = 8 + payload_len + 4;
    if bytes.len() != frame_len {
        let kind = match what {
            "" => "frame",
            "loose-frame " => "loose frame",
            _ => "tool frame",
        };
        return Err(binary_err(format!(
            "{kind} is {} bytes, expected {frame_len}",
            bytes.len()
        )));
    }
    if bytes[0..4] != magic {
        return Err(binary_err(format!("bad {what}magic {:02x?}", &bytes[0..4])));
    }
    if bytes[4] != version {
        return Err(binary_err(format!(
            "{what}version {} unsupported (this build reads {version})",
            bytes[4]
        )));
    }
    let found_len = usize::from(u16::from_le_bytes([bytes[6], bytes[7]]));
    if found_len != payload_len {
        return Err(binary_err(format!(
            "{what}payload length {found_len}, expected {payload_len}"
        )));
    }
    let end = frame_len - 4;
    let mut c = Crc32::new();
    c.update(&bytes[..end]);
    let computed = c.finish();
    let found = u32::from_le_bytes([bytes[end], bytes[end + 1], bytes[end + 2], bytes[end + 3]]);
    if found != computed {
        return Err(binary_err(format!("CRC-32 {found:08x}, computed {computed:08x}")));
    }
    Ok(())
}

/// Magic of a per-tool binary frame.
pub const TOOL_BINARY_MAGIC: [u8; 4] = *b"IRTL";
/// Per-tool binary framing version.
pub const TOOL_BINARY_VERSION: u8 = 1;
/// Payload bytes of a per-tool frame between the 8-byte header and the CRC.
pub const TOOL_BINARY_PAYLOAD_LEN: usize = 128;
/// Total size of one per-tool binary frame.
pub const TOOL_BINARY_FRAME_LEN: usize = 8 + TOOL_BINARY_PAYLOAD_LEN + 4;
/// Bytes of the name field of a per-tool record (`params::MAX_TOOL_NAME_LEN`).
pub const TOOL_NAME_FIELD_LEN: usize = crate::params::MAX_TOOL_NAME_LEN;

/// The pose of one tool of the parameter set in one frame set: a [`PositionRecord`] with the
/// tool's index (`tool_id`, definition order in the parameter set) and name. Sent to stream
/// clients that ask for per-tool records (docs/stream-protocol.md). Fixed size, `Copy`: the
/// name lives in a fixed field, so publishing needs no allocation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolRecord {
    /// Index of the tool in the parameter set's tool list.
    pub tool_id: u8,
    /// Number of tools in the parameter set (records of one frame set: ids 0..tool_count).
    pub tool_count: u8,
    name: [u8; TOOL_NAME_FIELD_LEN],
    name_len: u8,
    /// The tool's pose, status and quality, as in the main record.
    pub record: PositionRecord,
}

impl ToolRecord {
    /// A record for tool `tool_id` called `name` (at most [`TOOL_NAME_FIELD_LEN`] bytes of
    /// printable ASCII without `"` or `\`, as `RigParams::validate` demands).
    pub fn new(tool_id: u8, tool_count: u8, name: &str, record: PositionRecord) -> Result<ToolRecord> {
        if name.is_empty()
            || name.len() > TOOL_NAME_FIELD_LEN
            || !name
                .bytes()
                .all(|b| (0x20..0x7f).contains(&b) && b != b'"' && b != b'\\')
        {
            return Err(Error::InvalidParams {
                reason: format!(
                    "tool name {name:?} must be 1..={TOOL_NAME_FIELD_LEN} printable ASCII characters without \" or \\"
                ),
            });
        }
        let mut field = [0u8; TOOL_NAME_FIELD_LEN];
        field[..name.len()].copy_from_slice(name.as_bytes());
        Ok(ToolRecord {
            tool_id,
            tool_count,
            name: field,
            name_len: name.len() as u8,
            record,
        })
    }

    /// The tool's name.
    pub fn name(&self) -> &str {
        // Only ASCII is ever stored (checked in `new` and when decoding).
        core::str::from_utf8(&self.name[..usize::from(self.name_len)]).unwrap_or("")
    }

    /// Appends the NDJSON line (with `\n`) to `out`: the tool's keys first, then the
    /// position record's keys in their usual order.
    pub fn write_ndjson(&self, out: &mut String) {
        let _ = write!(
            out,
            "{{\"tool_id\":{},\"tool\":\"{}\",\"tool_count\":{},",
            self.tool_id,
            self.name(),
            self.tool_count
        );
        let start = out.len();
        self.record.write_ndjson(out);
        // The record's own opening brace is replaced by the tool keys written above.
        out.remove(start);
    }

    /// The NDJSON line as a new string.
    pub fn to_ndjson_line(&self) -> String {
        let mut s = String::with_capacity(320);
        self.write_ndjson(&mut s);
        s
    }

    /// Parses a per-tool NDJSON line; `tool_id`, `tool` and `tool_count` are required besides
    /// the position record's required keys.
    pub fn from_ndjson_line(line: &str) -> Result<ToolRecord> {
        let mut id = None;
        let mut name: Option<&str> = None;
        let mut count = None;
        let record = PositionRecord::parse_ndjson(line, |key, v| {
            match key {
                "tool_id" => id = Some(narrow::<u8>(key, v.uint(key)?)?),
                "tool_count" => count = Some(narrow::<u8>(key, v.uint(key)?)?),
                "tool" => name = Some(v.str(key)?),
                _ => {}
            }
            Ok(())
        })?;
        let missing = |k: &str| ndjson_err(format!("missing field \"{k}\""));
        let name = name.ok_or_else(|| missing("tool"))?;
        ToolRecord::new(
            id.ok_or_else(|| missing("tool_id"))?,
            count.ok_or_else(|| missing("tool_count"))?,
            name,
            record,
        )
        .map_err(|_| ndjson_err(format!("bad tool name {name:?}")))
    }

    /// Writes the per-tool binary frame into `out` (layout in docs/stream-protocol.md): the
    /// position frame's fields at the same offsets, then tool id, count and name.
    pub fn encode_binary(&self, out: &mut [u8; TOOL_BINARY_FRAME_LEN]) {
        self.record.write_common(
            &mut out[..COMMON_END],
            TOOL_BINARY_MAGIC,
            TOOL_BINARY_VERSION,
            TOOL_BINARY_PAYLOAD_LEN,
        );
        out[100] = self.tool_id;
        out[101] = self.tool_count;
        out[102] = self.name_len;
        out[103] = 0;
        out[104..136].copy_from_slice(&self.name);
        seal(&mut out[..]);
    }

    /// The binary frame as a new array.
    pub fn to_binary(&self) -> [u8; TOOL_BINARY_FRAME_LEN] {
        let mut out = [0u8; TOOL_BINARY_FRAME_LEN];
        self.encode_binary(&mut out);
        out
    }

    /// Decodes one per-tool binary frame (exactly [`TOOL_BINARY_FRAME_LEN`] bytes).
    pub fn decode_binary(bytes: &[u8]) -> Result<ToolRecord> {
        check_frame(
            bytes,
            TOOL_BINARY_MAGIC,
            TOOL_BINARY_VERSION,
            TOOL_BINARY_PAYLOAD_LEN,
            "tool-frame ",
        )?;
        let record = PositionRecord::read_common(bytes)?;
        let name_len = usize::from(bytes[102]);
        let name = bytes
            .get(104..104 + name_len)
            .filter(|_| name_len <= TOOL_NAME_FIELD_LEN)
            .and_then(|n| core::str::from_utf8(n).ok())
            .ok_or_else(|| binary_err(format!("tool name length {name_len} out of range")))?;
        if bytes[104 + name_len..136].iter().any(|&b| b != 0) || bytes[103] != 0 {
            return Err(binary_err(
                "tool frame: padding after the name is not zero".into(),
            ));
        }
        ToolRecord::new(bytes[100], bytes[101], name, record)
            .map_err(|_| binary_err(format!("bad tool name {name:?}")))
    }
}

/// Magic of a loose-LED binary frame.
pub const LOOSE_BINARY_MAGIC: [u8; 4] = *b"IRLL";
/// Loose-LED binary framing version.
pub const LOOSE_BINARY_VERSION: u8 = 1;
/// Payload bytes of a loose-LED frame between the 8-byte header and the CRC.
pub const LOOSE_BINARY_PAYLOAD_LEN: usize = 104;
/// Total size of one loose-LED binary frame.
pub const LOOSE_BINARY_FRAME_LEN: usize = 8 + LOOSE_BINARY_PAYLOAD_LEN + 4;

/// One loose single LED (an LED of no tool, `pose6d::LooseLed`) in one frame set: a
/// [`PositionRecord`] without orientation, with the LED's stable id. Sent with the per-tool
/// records to stream clients that ask for them (docs/stream-protocol.md). Fixed size, `Copy`.
///
/// A loose LED has no orientation: the encoders never send `record.orientation_wxyz` and the
/// decoders refuse one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LooseRecord {
    /// Stable id: the same LED keeps it while it is tracked (a new LED, or one reacquired
    /// beyond the tracker's gate, gets a new id).
    pub loose_id: u32,
    /// Number of loose LEDs reported in this frame set (records of one set: `loose_count`).
    pub loose_count: u8,
    /// Consecutive frame sets the LED has been tracked in, this one included (1 = new).
    pub frames_tracked: u32,
    /// The LED's position, status and quality, as in the main record (no orientation).
    pub record: PositionRecord,
}

impl LooseRecord {
    /// The record of loose LED `led` (camera-0 frame) in one frame set, moved into the world
    /// frame when `world_from_cam0` is given. `gap_mm` is the LED's ray gap, `cameras_used` the
    /// cameras that saw it. `latency_us` and `params_crc` are left 0 for the caller.
    pub fn from_loose_led(
        frame: u64,
        capture_ts_ns: u64,
        led: &LooseLed,
        world_from_cam0: Option<&RigidTransform>,
        loose_count: u8,
    ) -> LooseRecord {
        let p = match world_from_cam0 {
            None => led.position_mm,
            Some(w) => {
                let p = w.apply(&nalgebra::Vector3::from(led.position_mm));
                [p.x, p.y, p.z]
            }
        };
        LooseRecord {
            loose_id: led.id,
            loose_count,
            frames_tracked: led.frames_tracked,
            record: PositionRecord {
                frame,
                capture_ts_ns,
                position_mm: Some(p),
                orientation_wxyz: None,
                gap_mm: led.gap_mm,
                status: TrackStatus::Ok,
                cameras_used: led.cameras,
                world_frame: world_from_cam0.is_some(),
                latency_us: 0,
                params_crc: 0,
            },
        }
    }

    /// The record as it is sent: without orientation.
    fn sent(&self) -> PositionRecord {
        PositionRecord {
            orientation_wxyz: None,
            ..self.record
        }
    }

    /// Appends the NDJSON line (with `\n`) to `out`: the loose LED's keys first, then the
    /// position record's keys in their usual order (`orientation_wxyz` always null).
    pub fn write_ndjson(&self, out: &mut String) {
        let _ = write!(
            out,
            "{{\"loose_id\":{},\"loose_count\":{},\"frames_tracked\":{},",
            self.loose_id, self.loose_count, self.frames_tracked
        );
        let start = out.len();
        self.sent().write_ndjson(out);
        // The record's own opening brace is replaced by the keys written above.
        out.remove(start);
    }

    /// The NDJSON line as a new string.
    pub fn to_ndjson_line(&self) -> String {
        let mut s = String::with_capacity(320);
        self.write_ndjson(&mut s);
        s
    }

    /// Parses a loose-LED NDJSON line; `loose_id`, `loose_count` and `frames_tracked` are
    /// required besides the position record's required keys, and `orientation_wxyz` must be
    /// null or absent.
    pub fn from_ndjson_line(line: &str) -> Result<LooseRecord> {
        let mut id = None;
        let mut count = None;
        let mut frames = None;
        let record = PositionRecord::parse_ndjson(line, |key, v| {
            match key {
                "loose_id" => id = Some(narrow::<u32>(key, v.uint(key)?)?),
                "loose_count" => count = Some(narrow::<u8>(key, v.uint(key)?)?),
                "frames_tracked" => frames = Some(narrow::<u32>(key, v.uint(key)?)?),
                _ => {}
            }
            Ok(())
        })?;
        if record.orientation_wxyz.is_some() {
            return Err(ndjson_err(
                "a loose LED has no orientation; \"orientation_wxyz\" must be null".into(),
            ));
        }
        let missing = |k: &str| ndjson_err(format!("missing field \"{k}\""));
        Ok(LooseRecord {
            loose_id: id.ok_or_else(|| missing("loose_id"))?,
            loose_count: count.ok_or_else(|| missing("loose_count"))?,
            frames_tracked: frames.ok_or_else(|| missing("frames_tracked"))?,
            record,
        })
    }

    /// Writes the loose-LED binary frame into `out` (layout in docs/stream-protocol.md): the
    /// position frame's fields at the same offsets (orientation flag clear, orientation zero),
    /// then id, count and frames tracked.
    pub fn encode_binary(&self, out: &mut [u8; LOOSE_BINARY_FRAME_LEN]) {
        self.sent().write_common(
            &mut out[..COMMON_END],
            LOOSE_BINARY_MAGIC,
            LOOSE_BINARY_VERSION,
            LOOSE_BINARY_PAYLOAD_LEN,
        );
        out[100..104].copy_from_slice(&self.loose_id.to_le_bytes());
        out[104] = self.loose_count;
        out[105..108].copy_from_slice(&[0; 3]);
        out[108..112].copy_from_slice(&self.frames_tracked.to_le_bytes());
        seal(&mut out[..]);
    }

    /// The binary frame as a new array.
    pub fn to_binary(&self) -> [u8; LOOSE_BINARY_FRAME_LEN] {
        let mut out = [0u8; LOOSE_BINARY_FRAME_LEN];
        self.encode_binary(&mut out);
        out
    }

    /// Decodes one loose-LED binary frame (exactly [`LOOSE_BINARY_FRAME_LEN`] bytes).
    pub fn decode_binary(bytes: &[u8]) -> Result<LooseRecord> {
        check_frame(
            bytes,
            LOOSE_BINARY_MAGIC,
            LOOSE_BINARY_VERSION,
            LOOSE_BINARY_PAYLOAD_LEN,
            "loose-frame ",
        )?;
        let record = PositionRecord::read_common(bytes)?;
        if record.orientation_wxyz.is_some() || bytes[48..80].iter().any(|&b| b != 0) {
            return Err(binary_err(
                "loose frame: a loose LED has no orientation (flag bit 1 and bytes 48..80 must be 0)".into(),
            ));
        }
        if bytes[105..108].iter().any(|&b| b != 0) {
            return Err(binary_err(
                "loose frame: reserved bytes 105..108 are not zero".into(),
            ));
        }
        let u32_at = |o: usize| u32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
        Ok(LooseRecord {
            loose_id: u32_at(100),
            loose_count: bytes[104],
            frames_tracked: u32_at(108),
            record,
        })
    }
}

fn ndjson_err(reason: String) -> Error {
    Error::Protocol {
        protocol: NDJSON,
        reason,
    }
}

fn binary_err(reason: String) -> Error {
    Error::Protocol {
        protocol: BINARY,
        reason,
    }
}

fn narrow<T: TryFrom<u64>>(key: &str, v: u64) -> Result<T> {
    T::try_from(v).map_err(|_| ndjson_err(format!("\"{key}\" = {v} out of range")))
}

/// A JSON value as far as records need it; numbers stay text until their field's type is known.
enum Value<'a> {
    Null,
    Bool(bool),
    Num(&'a str),
    Str(&'a str),
    /// Up to four numbers or nulls (null read as NaN).
    Nums {
        vals: [f64; 4],
        len: usize,
    },
    /// Anything else (nested objects, long arrays): only allowed under unknown keys.
    Other,
}

impl<'a> Value<'a> {
    fn uint(&self, key: &str) -> Result<u64> {
        match self {
            Value::Num(s) if s.bytes().all(|b| b.is_ascii_digit()) => s
                .parse()
                .map_err(|_| ndjson_err(format!("\"{key}\" = {s} out of range"))),
            _ => Err(ndjson_err(format!("\"{key}\" must be a non-negative integer"))),
        }
    }

    fn float_or_nan(&self, key: &str) -> Result<f64> {
        match self {
            Value::Null => Ok(f64::NAN),
            Value::Num(s) => parse_f64(key, s),
            _ => Err(ndjson_err(format!("\"{key}\" must be a number or null"))),
        }
    }

    fn str(&self, key: &str) -> Result<&'a str> {
        match *self {
            Value::Str(s) => Ok(s),
            _ => Err(ndjson_err(format!("\"{key}\" must be a string"))),
        }
    }

    fn bool(&self, key: &str) -> Result<bool> {
        match self {
            Value::Bool(b) => Ok(*b),
            _ => Err(ndjson_err(format!("\"{key}\" must be true or false"))),
        }
    }

    fn opt_array<const N: usize>(&self, key: &str) -> Result<Option<[f64; N]>> {
        match self {
            Value::Null => Ok(None),
            Value::Nums { vals, len } if *len == N => {
                let mut out = [0.0; N];
                out.copy_from_slice(&vals[..N]);
                Ok(Some(out))
            }
            _ => Err(ndjson_err(format!(
                "\"{key}\" must be null or an array of {N} numbers"
            ))),
        }
    }
}

fn parse_f64(key: &str, s: &str) -> Result<f64> {
    s.parse::<f64>()
        .map_err(|_| ndjson_err(format!("\"{key}\": bad number {s:?}")))
}

/// Just enough JSON for flat records; rejects what it does not understand with a position.
struct JsonParser<'a> {
    s: &'a [u8],
    pos: usize,
}

const MAX_DEPTH: usize = 16;

impl<'a> JsonParser<'a> {
    fn ws(&mut self) {
        while self.pos < self.s.len() && matches!(self.s[self.pos], b' ' | b'\t' | b'\r' | b'\n') {
            self.pos += 1;
        }
    }

    fn eat(&mut self, b: u8) -> bool {
        if self.s.get(self.pos) == Some(&b) {
            self.pos += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, b: u8) -> Result<()> {
        if self.eat(b) {
            Ok(())
        } else {
            Err(ndjson_err(format!(
                "expected '{}' at byte {}",
                b as char, self.pos
            )))
        }
    }

    fn text(&self, start: usize, end: usize) -> Result<&'a str> {
        core::str::from_utf8(&self.s[start..end])
            .map_err(|_| ndjson_err(format!("bad UTF-8 at byte {start}")))
    }

    /// A string; escapes are skipped over correctly but returned raw (our keys and codes
    /// never contain them).
    fn string(&mut self) -> Result<&'a str> {
        self.expect(b'"')?;
        let start = self.pos;
        while self.pos < self.s.len() {
            match self.s[self.pos] {
                b'"' => {
                    let t = self.text(start, self.pos)?;
                    self.pos += 1;
                    return Ok(t);
                }
                b'\\' => self.pos += 2,
                _ => self.pos += 1,
            }
        }
        Err(ndjson_err(format!(
            "unterminated string starting at byte {start}"
        )))
    }

    fn number(&mut self) -> Result<&'a str> {
        let start = self.pos;
        while self.pos < self.s.len()
            && matches!(self.s[self.pos], b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E')
        {
            self.pos += 1;
        }
        if start == self.pos {
            return Err(ndjson_err(format!("unexpected character at byte {start}")));
        }
        self.text(start, self.pos)
    }

    fn literal(&mut self, word: &str) -> bool {
        if self.s[self.pos..].starts_with(word.as_bytes()) {
            self.pos += word.len();
            true
        } else {
            false
        }
    }

    fn value(&mut self, depth: usize) -> Result<Value<'a>> {
        if depth > MAX_DEPTH {
            return Err(ndjson_err("nesting too deep".into()));
        }
        match self.s.get(self.pos) {
            None => Err(ndjson_err("line ends where a value should be".into())),
            Some(b'"') => Ok(Value::Str(self.string()?)),
            Some(b'[') => self.array(depth),
            Some(b'{') => {
                self.pos += 1;
                self.ws();
                if !self.eat(b'}') {
                    loop {
                        self.ws();
                        self.string()?;
                        self.ws();
                        self.expect(b':')?;
                        self.ws();
                        self.value(depth + 1)?;
                        self.ws();
                        if !self.eat(b',') {
                            self.expect(b'}')?;
                            break;
                        }
                    }
                }
                Ok(Value::Other)
            }
            Some(_) => {
                if self.literal("null") {
                    Ok(Value::Null)
                } else if self.literal("true") {
                    Ok(Value::Bool(true))
                } else if self.literal("false") {
                    Ok(Value::Bool(false))
                } else {
                    let n = self.number()?;
                    // Validate the number's syntax here so that garbage fails even under unknown keys.
                    parse_f64("number", n)?;
                    Ok(Value::Num(n))
                }
            }
        }
    }

    fn array(&mut self, depth: usize) -> Result<Value<'a>> {
        self.pos += 1;
        let mut vals = [0.0; 4];
        let mut len = 0usize;
        let mut numeric = true;
        self.ws();
        if !self.eat(b']') {
            loop {
                self.ws();
                let v = self.value(depth + 1)?;
                let x = match v {
                    Value::Num(s) => Some(parse_f64("array element", s)?),
                    Value::Null => Some(f64::NAN),
                    _ => None,
                };
                match x {
                    Some(x) if numeric && len < 4 => vals[len] = x,
                    _ => numeric = false,
                }
                len += 1;
                self.ws();
                if !self.eat(b',') {
                    self.expect(b']')?;
                    break;
                }
            }
        }
        if numeric && len <= 4 {
            Ok(Value::Nums { vals, len })
        } else {
            Ok(Value::Other)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tracked() -> PositionRecord {
        PositionRecord {
            frame: 42,
            capture_ts_ns: 1_700_000_000_123_456_789,
            position_mm: Some([12.5, -3.25, 1500.0]),
            orientation_wxyz: None,
            gap_mm: 0.125,
            status: TrackStatus::Ok,
            cameras_used: 2,
            world_frame: false,
            latency_us: 4321,
            params_crc: 0xDEAD_BEEF,
        }
    }

    #[test]
    fn pose_record_in_world_frame() {
        use crate::pose6d::MAX_TOOL_LEDS;
        // Tool turned 90° about z in cam0, at (10, 20, 1000); world = cam0 turned 90° about x
        // and shifted.
        let h = core::f64::consts::FRAC_1_SQRT_2;
        let mut pose = Pose6d {
            status: PoseStatus::Tracked,
            position_mm: [10.0, 20.0, 1000.0],
            tip_mm: [10.0, 20.0, 1000.0],
            quaternion_wxyz: [h, 0.0, 0.0, h],
            r_row_major: [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
            residual_rms_mm: 0.07,
            residual_max_mm: 0.1,
            leds_used: 4,
            led_mask: 0b1111,
            leds_mm: [[0.0; 3]; MAX_TOOL_LEDS],
            candidates: 4,
            hypotheses: 1,
            resolved_by_continuity: false,
        };
        let r = PositionRecord::from_pose(7, 99, &pose, None, 2);
        assert_eq!(r.position_mm, Some([10.0, 20.0, 1000.0]));
        assert_eq!(r.orientation_wxyz, Some([h, 0.0, 0.0, h]));
        assert_eq!(
            (r.status, r.gap_mm, r.world_frame),
            (TrackStatus::Ok, 0.07, false)
        );
        let world = RigidTransform {
            r_row_major: [1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0],
            t_mm: [100.0, 0.0, 50.0],
        };
        let r = PositionRecord::from_pose(7, 99, &pose, Some(&world), 2);
        let p = r.position_mm.unwrap();
        for (a, b) in p.iter().zip([110.0, -1000.0, 70.0]) {
            assert!((a - b).abs() < 1e-9, "{p:?}");
        }
        // Rx(90°)·Rz(90°) = (w, x, y, z) = (½, ½, −½, ½).
        let q = r.orientation_wxyz.unwrap();
        for (v, e) in q.iter().zip([0.5, 0.5, -0.5, 0.5]) {
            assert!((v - e).abs() < 1e-12, "{q:?}");
        }
        assert!(r.world_frame);
        pose.status = PoseStatus::LedsMerged { led: 1, camera: 0 };
        let r = PositionRecord::from_pose(8, 99, &pose, Some(&world), 2);
        assert_eq!(
            (r.status, r.position_mm, r.orientation_wxyz),
            (TrackStatus::Rejected, None, None)
        );
        assert!(r.gap_mm.is_nan());
        pose.status = PoseStatus::TooFewLeds { points: 1, needed: 3 };
        assert_eq!(
            PositionRecord::from_pose(9, 99, &pose, None, 2).status,
            TrackStatus::Lost
        );
    }

    #[test]
    fn ndjson_exact_text() {
        assert_eq!(
            tracked().to_ndjson_line(),
            "{\"frame\":42,\"capture_ts_ns\":1700000000123456789,\"position_mm\":[12.5,-3.25,1500],\
             \"orientation_wxyz\":null,\"gap_mm\":0.125,\"status\":\"ok\",\"cameras_used\":2,\
             \"world_frame\":false,\"latency_us\":4321,\"params_crc\":3735928559}\n"
        );
    }

    #[test]
    fn ndjson_round_trips() {
        let mut r = tracked();
        assert_eq!(PositionRecord::from_ndjson_line(&r.to_ndjson_line()).unwrap(), r);
        r.orientation_wxyz = Some([0.5, -0.5, 0.5, 0.1 + 0.2]);
        r.world_frame = true;
        r.position_mm = Some([1e-300, 1.0 / 3.0, -7e12]);
        assert_eq!(PositionRecord::from_ndjson_line(&r.to_ndjson_line()).unwrap(), r);
        let lost = PositionRecord {
            position_mm: None,
            gap_mm: f64::NAN,
            status: TrackStatus::Lost,
            cameras_used: 1,
            ..tracked()
        };
        let line = lost.to_ndjson_line();
        assert!(
            line.contains("\"position_mm\":null") && line.contains("\"gap_mm\":null"),
            "{line}"
        );
        let back = PositionRecord::from_ndjson_line(&line).unwrap();
        assert!(back.gap_mm.is_nan());
        assert_eq!(
            PositionRecord { gap_mm: 0.0, ..back },
            PositionRecord { gap_mm: 0.0, ..lost }
        );
    }

    #[test]
    fn ndjson_reuses_the_buffer() {
        let mut buf = String::with_capacity(MAX_NDJSON_LINE);
        let cap = buf.capacity();
        for f in 0..100 {
            buf.clear();
            PositionRecord {
                frame: f,
                ..tracked()
            }
            .write_ndjson(&mut buf);
            assert!(buf.len() < MAX_NDJSON_LINE);
        }
        assert_eq!(buf.capacity(), cap);
    }

    #[test]
    fn ndjson_tolerates_unknown_keys_and_whitespace() {
        let line = " { \"extra\" : {\"a\":[1,2,3,4,5,{\"b\":null}]}, \"frame\":7,\"capture_ts_ns\":8,\
                    \"position_mm\":[1,2,3],\"gap_mm\":0.5,\"status\":\"rejected\",\"cameras_used\":3,\
                    \"latency_us\":9, \"note\":\"x\\\"y\" }\r\n";
        let r = PositionRecord::from_ndjson_line(line).unwrap();
        assert_eq!(r.frame, 7);
        assert_eq!(r.status, TrackStatus::Rejected);
        assert_eq!(r.position_mm, Some([1.0, 2.0, 3.0]));
        assert_eq!(
            (r.orientation_wxyz, r.world_frame, r.params_crc),
            (None, false, 0)
        );
    }

    #[test]
    fn ndjson_errors_are_protocol_errors() {
        let good = tracked().to_ndjson_line();
        let cases = [
            String::new(),
            "[]".into(),
            good.replace("\"frame\":42,", ""),
            good.replace("\"ok\"", "\"great\""),
            good.replace("[12.5,-3.25,1500]", "[12.5,-3.25]"),
            good.replace("42", "-42"),
            good.replace("42", "4.2"),
            good.replace("\"cameras_used\":2", "\"cameras_used\":300"),
            good.replace("0.125", "0.1.2"),
            good.replace('}', "} x"),
            good[..good.len() - 5].into(),
            "x".repeat(MAX_NDJSON_LINE + 1),
        ];
        for line in &cases {
            match PositionRecord::from_ndjson_line(line) {
                Err(Error::Protocol { protocol, .. }) => assert_eq!(protocol, NDJSON),
                other => panic!("{line:?} gave {other:?}"),
            }
        }
    }

    #[test]
    fn binary_layout_and_round_trip() {
        let r = PositionRecord {
            orientation_wxyz: Some([1.0, 0.0, 0.0, 0.0]),
            world_frame: true,
            ..tracked()
        };
        let b = r.to_binary();
        assert_eq!(&b[0..8], b"IRPS\x01\x07\x5c\x00");
        assert_eq!(&b[8..16], &42u64.to_le_bytes());
        assert_eq!(&b[24..32], &12.5f64.to_le_bytes());
        assert_eq!((b[88], b[89]), (0, 2));
        assert_eq!(&b[96..100], &0xDEAD_BEEFu32.to_le_bytes());
        assert_eq!(
            u32::from_le_bytes(b[100..104].try_into().unwrap()),
            crate::crc::crc32(&b[..100])
        );
        assert_eq!(PositionRecord::decode_binary(&b).unwrap(), r);
        let lost = PositionRecord {
            position_mm: None,
            status: TrackStatus::NoParams,
            ..tracked()
        };
        let b = lost.to_binary();
        assert_eq!(b[5], 0);
        assert_eq!(PositionRecord::decode_binary(&b).unwrap(), lost);
    }

    #[test]
    fn binary_detects_every_single_byte_corruption() {
        let b = tracked().to_binary();
        for i in 0..BINARY_FRAME_LEN {
            for x in [0x01u8, 0x80, 0xFF] {
                let mut c = b;
                c[i] ^= x;
                assert!(
                    matches!(
                        PositionRecord::decode_binary(&c),
                        Err(Error::Protocol { protocol: BINARY, .. })
                    ),
                    "byte {i} ^ {x:#x} undetected"
                );
            }
        }
        assert!(PositionRecord::decode_binary(&b[..103]).is_err());
    }

    #[test]
    fn status_codes_round_trip() {
        for s in TrackStatus::ALL {
            assert_eq!(TrackStatus::from_code(s.as_str()), Some(s));
            assert_eq!(TrackStatus::from_u8(s.as_u8()), Some(s));
        }
        assert_eq!(TrackStatus::from_u8(5), None);
    }
}
