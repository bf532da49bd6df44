//! The crate's one error type.

use thiserror::Error;

/// Errors of irtrack-sim. Variants name the offending input so a caller can fix it.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum SimError {
    /// A configuration value is out of range or inconsistent.
    #[error("invalid simulator configuration: {field}: {reason}")]
    Config {
        /// The key.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// Camera index past the rig's camera count.
    #[error("camera {camera} does not exist (rig has {count} cameras)")]
    NoSuchCamera {
        /// The index asked for.
        camera: usize,
        /// Cameras of the rig.
        count: usize,
    },
    /// The caller's output buffer does not match the image size.
    #[error("output buffer has {have} pixels, frame needs {needed}")]
    BufferSize {
        /// Pixels of the frame.
        needed: usize,
        /// Pixels of the buffer.
        have: usize,
    },
    /// A rendering window (blob plus motion-blur streak) exceeds the preallocated scratch.
    #[error(
        "marker footprint {width_px}x{height_px} px exceeds the {max_px} px render window (too much motion blur or too large a blob)"
    )]
    WindowTooLarge {
        /// Window width.
        width_px: usize,
        /// Window height.
        height_px: usize,
        /// Largest window area.
        max_px: usize,
    },
    /// A trajectory CSV line does not parse.
    #[error("trajectory CSV line {line}: {reason}")]
    TrajectoryCsv {
        /// Line number (1-based).
        line: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// Error from the core library (camera model, parameters).
    #[error("core: {0}")]
    Core(#[from] irtrack_core::Error),
    /// I/O while reading or writing simulator files.
    #[error("I/O: {0}")]
    Io(#[from] std::io::Error),
}
