//! V4L2 capture (owned by the hardware/image work; config seam defined here first).

use serde::Deserialize;

/// `[source.v4l2]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct V4l2Config {
    /// Device paths or /dev/v4l/by-id links, one per camera, camera 0 first.
    pub devices: Vec<String>,
    pub width_px: u32,
    pub height_px: u32,
    pub fps: u32,
}
