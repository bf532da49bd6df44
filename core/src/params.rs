//! Rig parameters and their on-wire/on-disk blob format (see docs/param-blob.md).

use alloc::string::String;
use alloc::vec::Vec;
use serde::{Deserialize, Serialize};

use crate::camera::{CameraModel, RigidTransform};

/// One camera of the rig: model plus pose relative to camera 0
/// (`x_cam = R x_cam0 + t`, OpenCV stereoCalibrate's R, T). Camera 0 has the identity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraParams {
    pub model: CameraModel,
    pub cam_from_cam0: RigidTransform,
}

/// A rigid tool carrying several LEDs (6-DOF tracking); LED positions in the tool frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolDefinition {
    pub name: String,
    pub leds_mm: Vec<[f64; 3]>,
}

/// Everything the tracker needs to turn pixels into millimetres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigParams {
    /// Identifies the parameter set (shown in status, logged on swap).
    pub rig_id: String,
    /// Creation time, Unix seconds.
    pub created_unix_s: u64,
    /// N ≥ 2 cameras; index 0 is the reference frame.
    pub cameras: Vec<CameraParams>,
    /// Optional registration: robot/world frame from camera-0 frame.
    pub world_from_cam0: Option<RigidTransform>,
    /// Rigid multi-LED tools for 6-DOF tracking.
    pub tools: Vec<ToolDefinition>,
}
