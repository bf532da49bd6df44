//! The crate's one error type.

use crate::leds::LedError;
use crate::source::SourceError;

/// Errors of irtrackd's library. Each variant names what failed and where.
#[derive(Debug, thiserror::Error)]
pub enum FirmwareError {
    /// The config file could not be read.
    #[error("config file {path}: {reason}")]
    ConfigFile { path: String, reason: String },
    /// The config parsed but is not usable.
    #[error("config: {reason}")]
    Config { reason: String },
    /// A frame source failed.
    #[error("frame source: {0}")]
    Source(#[from] SourceError),
    /// An LED back end failed.
    #[error("status LEDs: {0}")]
    Leds(#[from] LedError),
    /// A parameter blob or a tracking stage was rejected by irtrack-core.
    #[error("{0}")]
    Core(#[from] irtrack_core::Error),
    /// Parameters are valid but describe a different rig than the running source.
    #[error("parameters do not fit the rig: {reason}")]
    RigMismatch { reason: String },
    /// Reading or writing the state directory failed.
    #[error("state storage {path}: {source}")]
    Storage { path: String, source: std::io::Error },
    /// A listener could not be bound.
    #[error("cannot listen for {what} on {addr}: {source}")]
    Bind {
        what: &'static str,
        addr: String,
        source: std::io::Error,
    },
    /// The robot link could not be started.
    #[error("{0}")]
    Robot(#[from] irtrack_robot::RobotError),
    /// An output (NatNet, recording) could not encode or refused input.
    #[error("{what}: {reason}")]
    Output { what: &'static str, reason: String },
    /// A worker thread could not be started or died.
    #[error("thread {what}: {reason}")]
    Thread { what: &'static str, reason: String },
}

/// Result alias for the firmware library.
pub type Result<T> = std::result::Result<T, FirmwareError>;
