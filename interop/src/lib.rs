//! Formats that tools outside irtrack read, written once for irtrackd and the PC tools:
//!
//! - [`ros2msg`]: ROS 2 message definitions (`ros2msg` schema text) and their CDR encoding,
//!   without ROS; [`ros2types`]: the same messages as structs for serde-based serializers;
//! - [`mcap`] (feature `mcap`): MCAP recordings of position records with those schemas, which
//!   Foxglove and `ros2 bag` open.
//!
//! Specs: docs/outputs.md. Depends on `irtrack-core` only (the position record).

#![deny(missing_docs)]

#[cfg(feature = "mcap")]
pub mod mcap;
pub mod ros2msg;
pub mod ros2types;

/// Errors of this crate; each names what was being written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InteropError {
    /// The MCAP writer refused an operation (I/O error, bad record).
    #[error("MCAP recording: {what}: {reason}")]
    Mcap {
        /// What was being written (`header`, `schema geometry_msgs/msg/PoseStamped`, ...).
        what: String,
        /// The writer's message.
        reason: String,
    },
    /// A message type has no schema here.
    #[error("no ROS 2 message definition for {type_name}")]
    UnknownType {
        /// The type asked for.
        type_name: String,
    },
}

/// This crate's result type.
pub type Result<T> = std::result::Result<T, InteropError>;
