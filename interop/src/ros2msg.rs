//! ROS 2 messages without ROS: the message definitions (`ros2msg` schema text, as ROS 2 tools
//! store them in bags) and their CDR encoding (XCDR1, little-endian), for MCAP recordings.
//!
//! CDR rules used here: a 4-byte encapsulation header `00 01 00 00` (CDR_LE); every primitive
//! aligned to its size relative to the end of that header; strings as u32 length (including
//! the NUL), bytes, NUL; sequences as u32 count then elements.

use irtrack_core::stream::PositionRecord;

/// Frame id of records in camera 0's frame, the tracker frame (REP 103's optical axes: x
/// right, y down, z ahead).
pub const FRAME_CAMERA0: &str = "irtrack_camera0_optical";
/// Frame id of records in the registered world (robot base) frame.
pub const FRAME_WORLD: &str = "irtrack_world";

/// `geometry_msgs/msg/PointStamped`.
pub const POINT_STAMPED: &str = "geometry_msgs/msg/PointStamped";
/// `geometry_msgs/msg/PoseStamped`.
pub const POSE_STAMPED: &str = "geometry_msgs/msg/PoseStamped";
/// `tf2_msgs/msg/TFMessage`.
pub const TF_MESSAGE: &str = "tf2_msgs/msg/TFMessage";
/// `diagnostic_msgs/msg/DiagnosticStatus`.
pub const DIAGNOSTIC_STATUS: &str = "diagnostic_msgs/msg/DiagnosticStatus";
/// `diagnostic_msgs/msg/DiagnosticArray` (what `/diagnostics` carries).
pub const DIAGNOSTIC_ARRAY: &str = "diagnostic_msgs/msg/DiagnosticArray";
/// `sensor_msgs/msg/PointCloud2`.
pub const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";

/// A name as a ROS name token: characters outside `[A-Za-z0-9_]` become `_`, a leading digit
/// (or an empty name) gets a `t` in front (`my tool-2` → `my_tool_2`).
pub fn ros_token(name: &str) -> String {
    let mut t: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    if t.is_empty() || t.starts_with(|c: char| c.is_ascii_digit()) {
        t.insert(0, 't');
    }
    t
}

const SEP: &str = "================================================================================\n";

const HEADER_DEF: &str = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n";
const TIME_DEF: &str = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n";
const POINT_DEF: &str = "MSG: geometry_msgs/Point\nfloat64 x\nfloat64 y\nfloat64 z\n";
const QUAT_DEF: &str = "MSG: geometry_msgs/Quaternion\nfloat64 x\nfloat64 y\nfloat64 z\nfloat64 w\n";
const DIAG_STATUS_FIELDS: &str = "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\nstring hardware_id\ndiagnostic_msgs/KeyValue[] values\n";
const KEY_VALUE_DEF: &str = "MSG: diagnostic_msgs/KeyValue\nstring key\nstring value\n";

/// The `ros2msg` schema text of one of the message types above (the type's own fields, then
/// every type it uses after a separator line, as `ros2 bag` writes them).
pub fn schema(type_name: &str) -> Option<String> {
    let parts: Vec<&str> = match type_name {
        POINT_STAMPED => vec![
            "std_msgs/Header header\ngeometry_msgs/Point point\n",
            HEADER_DEF,
            TIME_DEF,
            POINT_DEF,
        ],
        POSE_STAMPED => vec![
            "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
            HEADER_DEF,
            TIME_DEF,
            "MSG: geometry_msgs/Pose\ngeometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
            POINT_DEF,
            QUAT_DEF,
        ],
        TF_MESSAGE => vec![
            "geometry_msgs/TransformStamped[] transforms\n",
            "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n",
            HEADER_DEF,
            TIME_DEF,
            "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n",
            "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n",
            QUAT_DEF,
        ],
        DIAGNOSTIC_STATUS => vec![DIAG_STATUS_FIELDS, KEY_VALUE_DEF],
        DIAGNOSTIC_ARRAY => {
            return Some(format!(
                "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status\n{SEP}{HEADER_DEF}{SEP}{TIME_DEF}{SEP}MSG: diagnostic_msgs/DiagnosticStatus\n{DIAG_STATUS_FIELDS}{SEP}{KEY_VALUE_DEF}"
            ));
        }
        POINT_CLOUD2 => vec![
            "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\nbool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
            HEADER_DEF,
            TIME_DEF,
            "MSG: sensor_msgs/PointField\nuint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\nuint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\nstring name\nuint32 offset\nuint8 datatype\nuint32 count\n",
        ],
        _ => return None,
    };
    Some(parts.join(SEP))
}

/// Writes CDR (little-endian) into a reused buffer.
pub struct CdrWriter<'a> {
    buf: &'a mut Vec<u8>,
}

impl<'a> CdrWriter<'a> {
    /// Clears `buf` and writes the encapsulation header.
    pub fn new(buf: &'a mut Vec<u8>) -> Self {
        buf.clear();
        buf.extend_from_slice(&[0, 1, 0, 0]);
        Self { buf }
    }
    fn align(&mut self, n: usize) {
        let pos = self.buf.len() - 4;
        let pad = (n - pos % n) % n;
        self.buf.resize(self.buf.len() + pad, 0);
    }
    /// A `byte`/`uint8`.
    pub fn u8(&mut self, v: u8) {
        self.buf.push(v);
    }
    /// An `int32`, 4-aligned.
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    /// A `uint32`, 4-aligned.
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    /// A `float64`, 8-aligned.
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.buf.extend_from_slice(&v.to_le_bytes());
    }
    /// Raw bytes (a `uint8[]`'s elements), no alignment.
    pub fn bytes(&mut self, b: &[u8]) {
        self.buf.extend_from_slice(b);
    }
    /// A `string`: u32 length including the NUL, the bytes, NUL.
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.buf.extend_from_slice(s.as_bytes());
        self.buf.push(0);
    }
    /// `builtin_interfaces/Time` + frame id: a `std_msgs/Header`.
    pub fn header(&mut self, stamp_ns: u64, frame_id: &str) {
        self.i32(i32::try_from(stamp_ns / 1_000_000_000).unwrap_or(i32::MAX));
        self.u32((stamp_ns % 1_000_000_000) as u32);
        self.string(frame_id);
    }
    /// Three `float64` (`geometry_msgs/Point` or `Vector3`).
    pub fn vec3(&mut self, v: &[f64; 3]) {
        for c in v {
            self.f64(*c);
        }
    }
}

/// `geometry_msgs/msg/PointStamped`.
pub fn point_stamped(stamp_ns: u64, frame_id: &str, p_m: &[f64; 3], out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    w.header(stamp_ns, frame_id);
    w.vec3(p_m);
}

/// `geometry_msgs/msg/PoseStamped`; `q` is x y z w.
pub fn pose_stamped(stamp_ns: u64, frame_id: &str, p_m: &[f64; 3], q: &[f64; 4], out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    w.header(stamp_ns, frame_id);
    w.vec3(p_m);
    for c in q {
        w.f64(*c);
    }
}

/// `tf2_msgs/msg/TFMessage` with one transform `frame_id` → `child`.
pub fn tf_message(
    stamp_ns: u64,
    frame_id: &str,
    child: &str,
    t_m: &[f64; 3],
    q: &[f64; 4],
    out: &mut Vec<u8>,
) {
    let mut w = CdrWriter::new(out);
    w.u32(1);
    w.header(stamp_ns, frame_id);
    w.string(child);
    w.vec3(t_m);
    for c in q {
        w.f64(*c);
    }
}

/// One transform of a `/tf` message: parent frame → `child`, translation (metres) and
/// rotation (x y z w).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TfChild<'a> {
    /// The child frame.
    pub child: &'a str,
    /// Translation, metres.
    pub t_m: [f64; 3],
    /// Rotation, x y z w.
    pub q_xyzw: [f64; 4],
}

/// `tf2_msgs/msg/TFMessage` with every transform of `children`, each `frame_id` → child.
pub fn tf_message_of(stamp_ns: u64, frame_id: &str, children: &[TfChild<'_>], out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    w.u32(children.len() as u32);
    for c in children {
        w.header(stamp_ns, frame_id);
        w.string(c.child);
        w.vec3(&c.t_m);
        for v in c.q_xyzw {
            w.f64(v);
        }
    }
}

/// Bytes per point of [`loose_cloud`]: x, y, z (float32, metres) and `loose_id` (uint32).
pub const LOOSE_POINT_STEP: u32 = 16;

/// `sensor_msgs/msg/PointCloud2` of loose LEDs, as irtrackd's live ROS 2 output sends it: one
/// row, fields `x` `y` `z` (float32, metres; 7) and `loose_id` (uint32; 6), little-endian,
/// dense. `points`: (loose id, position in metres).
pub fn loose_cloud(stamp_ns: u64, frame_id: &str, points: &[(u32, [f64; 3])], out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    w.header(stamp_ns, frame_id);
    w.u32(1); // height
    w.u32(points.len() as u32); // width
    w.u32(4);
    for (name, offset, datatype) in [("x", 0, 7u8), ("y", 4, 7), ("z", 8, 7), ("loose_id", 12, 6)] {
        w.string(name);
        w.u32(offset);
        w.u8(datatype);
        w.u32(1);
    }
    w.u8(0); // is_bigendian
    w.u32(LOOSE_POINT_STEP);
    w.u32(LOOSE_POINT_STEP * points.len() as u32);
    w.u32(LOOSE_POINT_STEP * points.len() as u32);
    for (id, p) in points {
        for c in p {
            w.bytes(&(*c as f32).to_le_bytes());
        }
        w.bytes(&id.to_le_bytes());
    }
    w.u8(1); // is_dense
}

/// `diagnostic_msgs/msg/DiagnosticArray` with one status for `rec` (as [`record_status`]),
/// its values followed by `extra` key/value pairs; header stamp `stamp_ns`, no frame.
pub fn diagnostic_array(stamp_ns: u64, rec: &PositionRecord, extra: &[(&str, u64)], out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    w.header(stamp_ns, "");
    w.u32(1);
    status_fields(&mut w, rec, extra);
}

/// `diagnostic_msgs/msg/DiagnosticStatus` for one position record: level OK for a tracked
/// record, WARN for lost/rejected, ERROR for no parameters or a fault; message = the status
/// word; values: frame, gap, cameras, latency, parameter CRC, world frame.
pub fn record_status(rec: &PositionRecord, out: &mut Vec<u8>) {
    let mut w = CdrWriter::new(out);
    status_fields(&mut w, rec, &[]);
}

fn status_fields(w: &mut CdrWriter<'_>, rec: &PositionRecord, extra: &[(&str, u64)]) {
    use irtrack_core::stream::TrackStatus;
    let level = match rec.status {
        TrackStatus::Ok => 0,
        TrackStatus::Lost | TrackStatus::Rejected => 1,
        TrackStatus::NoParams | TrackStatus::Fault => 2,
    };
    w.u8(level);
    w.string("irtrack");
    w.string(rec.status.as_str());
    w.string("irtrackd");
    let gap = if rec.gap_mm.is_finite() {
        format!("{}", rec.gap_mm)
    } else {
        String::new()
    };
    let values = [
        ("frame", rec.frame.to_string()),
        ("gap_mm", gap),
        ("cameras_used", rec.cameras_used.to_string()),
        ("latency_us", rec.latency_us.to_string()),
        ("params_crc", format!("{:08x}", rec.params_crc)),
        ("world_frame", rec.world_frame.to_string()),
    ];
    w.u32((values.len() + extra.len()) as u32);
    for (k, v) in &values {
        w.string(k);
        w.string(v);
    }
    for (k, v) in extra {
        w.string(k);
        w.string(&v.to_string());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_stamped_cdr_is_aligned_as_ros_writes_it() {
        let mut out = Vec::new();
        point_stamped(1_500_000_000, "map", &[1.0, 2.0, 3.0], &mut out);
        let mut want = vec![0, 1, 0, 0];
        want.extend_from_slice(&1i32.to_le_bytes()); // sec
        want.extend_from_slice(&500_000_000u32.to_le_bytes()); // nanosec
        want.extend_from_slice(&4u32.to_le_bytes());
        want.extend_from_slice(b"map\0"); // offset 12..16
        // x is 8-aligned: offset 16 after the encapsulation header, no padding needed.
        for v in [1.0f64, 2.0, 3.0] {
            want.extend_from_slice(&v.to_le_bytes());
        }
        assert_eq!(out, want);
        // A 2-byte frame id needs 1 byte of padding before the string ends at 15 -> x at 16.
        point_stamped(0, "ab", &[0.0; 3], &mut out);
        assert_eq!(out.len(), 4 + 12 + 3 + 1 + 24);
    }

    #[test]
    fn schemas_name_every_used_type() {
        let s = schema(TF_MESSAGE).unwrap();
        for t in [
            "MSG: geometry_msgs/TransformStamped",
            "MSG: std_msgs/Header",
            "MSG: geometry_msgs/Vector3",
        ] {
            assert!(s.contains(t), "{t}");
        }
        assert!(schema("nope/msg/X").is_none());
    }
}
