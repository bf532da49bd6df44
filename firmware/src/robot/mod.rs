//! Robot link (owned by the robot-link work; placeholder seam until then).

use serde::Deserialize;

/// `[robot]` section of the irtrackd config.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RobotConfig {
    /// Robot controller address, `host:port` (the tracker is the TCP client).
    pub address: String,
}
