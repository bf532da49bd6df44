//! The crate's one error type.

use crate::leds::LedError;
use crate::source::SourceError;

/// Errors of irtrackd's library. Each variant names what failed and where.
#[derive(Debug, thiserror::Error)]
pub enum FirmwareError {
    /// The config file could not be read.
    #[error("config file {path}: {reason}")]
    ConfigFile {
        /// The config file's path as given.
        path: String,
        /// Why it could not be read or parsed.
        reason: String,
    },
    /// The config parsed but is not usable.
    #[error("config: {reason}")]
    Config {
        /// What is wrong, naming the key.
        reason: String,
    },
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
    RigMismatch {
        /// What in the parameters does not match the source.
        reason: String,
    },
    /// Reading or writing the state directory failed.
    #[error("state storage {path}: {source}")]
    Storage {
        /// The file or directory the operation was on.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A listener could not be bound.
    #[error("cannot listen for {what} on {addr}: {source}")]
    Bind {
        /// The service the listener is for (`status`, `NDJSON stream`, ...).
        what: &'static str,
        /// The address that could not be bound (`?` when the bound address could not be read).
        addr: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The robot link could not be started.
    #[error("{0}")]
    Robot(#[from] irtrack_robot::RobotError),
    /// An output (NatNet, recording) could not encode or refused input.
    #[error("{what}: {reason}")]
    Output {
        /// The output and step that failed (`NatNet packet`, `MCAP recording`, ...).
        what: &'static str,
        /// What it refused or failed at.
        reason: String,
    },
    /// A worker thread could not be started or died.
    #[error("thread {what}: {reason}")]
    Thread {
        /// The worker (`processing loop`, `LED driver`, ...).
        what: &'static str,
        /// Why it could not start or how it died.
        reason: String,
    },
}

/// Result alias for the firmware library.
pub type Result<T> = std::result::Result<T, FirmwareError>;
