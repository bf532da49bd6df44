//! The harness's one error type.

use std::path::PathBuf;
use std::time::Duration;

/// Errors of the harness. Each names what was being done.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// A program could not be started.
    #[error("starting {program}: {source}")]
    Spawn {
        /// The program's path.
        program: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A process did not print the awaited line in time (or closed its output first).
    #[error("{process}: no `{prefix}` line within {timeout:?}{ended}")]
    NoLine {
        /// Which process.
        process: String,
        /// The line's expected start.
        prefix: String,
        /// How long we waited.
        timeout: Duration,
        /// ", it exited (...)" when the process ended meanwhile.
        ended: String,
    },
    /// A field of irtrackd's ready line (or a similar line) is missing or no address.
    #[error("`{key}` missing or not an address in {line:?}")]
    BadAddress {
        /// E.g. `status=`.
        key: String,
        /// The line.
        line: String,
    },
    /// A program ran but failed.
    #[error("{what} failed: {detail}")]
    Failed {
        /// What was run.
        what: String,
        /// Exit status and output.
        detail: String,
    },
    /// An HTTP request got no answer (connection, timeout, unreadable body).
    #[error("{method} {url}: {reason}")]
    Http {
        /// Request method.
        method: String,
        /// Request URL.
        url: String,
        /// Why.
        reason: String,
    },
    /// The WebSocket failed (handshake, read, a message that is not text).
    #[error("WebSocket {url}: {reason}")]
    WebSocket {
        /// The socket's URL.
        url: String,
        /// Why.
        reason: String,
    },
    /// Text that should be JSON is not.
    #[error("not JSON ({source}): {text:?}")]
    Json {
        /// Up to 200 characters of the text.
        text: String,
        /// The parser's complaint.
        source: serde_json::Error,
    },
    /// A config value could not be set (a key path through a non-table).
    #[error("config key `{key}`: {reason}")]
    Config {
        /// Dotted key path.
        key: String,
        /// Why.
        reason: String,
    },
    /// File system or pipe I/O.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// The error.
        source: std::io::Error,
    },
}

/// Result of the harness.
pub type Result<T> = std::result::Result<T, Error>;

/// `map_err` helper for I/O with a description.
pub(crate) fn io(what: impl Into<String>) -> impl FnOnce(std::io::Error) -> Error {
    let what = what.into();
    move |source| Error::Io { what, source }
}
