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
    /// Writing the recording's file failed (a full disk, a removed medium); the recording
    /// stopped. What was written before stays readable.
    #[error("writing the MCAP file failed: {reason}; {}", kept_words(*.kept_chunks, *.kept_bytes, *.end_written))]
    RecordingStopped {
        /// The I/O error, as the OS words it.
        reason: String,
        /// Bytes that stay readable.
        kept_bytes: u64,
        /// Chunks (and the header) that stay readable; 0: nothing.
        kept_chunks: u64,
        /// The file's end was written after them (readers open it as it is).
        end_written: bool,
    },
    /// A message type has no schema here.
    #[error("no ROS 2 message definition for {type_name}")]
    UnknownType {
        /// The type asked for.
        type_name: String,
    },
}

fn kept_words(chunks: u64, bytes: u64, end_written: bool) -> String {
    match (chunks, end_written) {
        (0, _) => "nothing of this file is readable".to_string(),
        (c, true) => format!("the {bytes} bytes written before ({c} chunks) stay readable"),
        (c, false) => format!(
            "the {bytes} bytes written before ({c} chunks) are whole but the file's end could not be written (`mcap recover` reads them)"
        ),
    }
}

/// This crate's result type.
pub type Result<T> = std::result::Result<T, InteropError>;
