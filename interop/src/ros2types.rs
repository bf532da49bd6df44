//! The ROS 2 messages of [`crate::ros2msg`] as plain structs for serde-based CDR serializers
//! (the DDS stack behind irtrackd's `[outputs.ros2]` serializes them itself). Field order is
//! the message definitions' order, which is all CDR needs; names follow ROS.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Time {
    /// Seconds since the Unix epoch.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// From nanoseconds since the Unix epoch (saturating at 2038, as ROS does).
    pub fn from_ns(ns: u64) -> Self {
        Self {
            sec: i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Header {
    /// When the data was captured.
    pub stamp: Time,
    /// The frame the data is expressed in.
    pub frame_id: String,
}

/// `geometry_msgs/msg/Point` (and, with the same layout, `Vector3`).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Point {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// z, metres.
    pub z: f64,
}

impl From<[f64; 3]> for Point {
    fn from(v: [f64; 3]) -> Self {
        Self {
            x: v[0],
            y: v[1],
            z: v[2],
        }
    }
}

/// `geometry_msgs/msg/Vector3`.
pub type Vector3 = Point;

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self::from([0.0, 0.0, 0.0, 1.0])
    }
}

impl From<[f64; 4]> for Quaternion {
    /// From x y z w.
    fn from(q: [f64; 4]) -> Self {
        Self {
            x: q[0],
            y: q[1],
            z: q[2],
            w: q[3],
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Pose {
    /// Position, metres.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose in `header.frame_id`.
    pub pose: Pose,
}

/// `geometry_msgs/msg/PointStamped`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The point in `header.frame_id`, metres.
    pub point: Point,
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Transform {
    /// Translation, metres.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: `child_frame_id` in `header.frame_id`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and parent frame.
    pub header: Header,
    /// The frame this transform places.
    pub child_frame_id: String,
    /// Parent from child.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct TFMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `sensor_msgs/msg/PointField`: one field of a [`PointCloud2`]'s point.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `y`, `z`, ...).
    pub name: String,
    /// Byte offset within the point.
    pub offset: u32,
    /// Data type: one of the `POINT_FIELD_*` constants.
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

/// `sensor_msgs/msg/PointField` datatype `FLOAT32`.
pub const POINT_FIELD_FLOAT32: u8 = 7;
/// `sensor_msgs/msg/PointField` datatype `UINT32`.
pub const POINT_FIELD_UINT32: u8 = 6;

/// `sensor_msgs/msg/PointCloud2`: `height × width` points of `point_step` bytes each in `data`,
/// laid out as `fields` says.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1: an unordered cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The layout of one point.
    pub fields: Vec<PointField>,
    /// Multi-byte fields are big-endian.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    pub data: Vec<u8>,
    /// No invalid (NaN) points.
    pub is_dense: bool,
}
