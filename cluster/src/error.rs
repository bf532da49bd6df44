//! The crate's one error type.

/// Errors of irtrack-cluster.
#[derive(Debug, thiserror::Error)]
pub enum ClusterError {
    /// Settings that cannot work (camera count, endpoints, names).
    #[error("cluster configuration: {reason}")]
    Config {
        /// What is wrong.
        reason: String,
    },
    /// Zenoh refused to open a session or declare a publisher/subscriber.
    #[error("zenoh {what}: {reason}")]
    Transport {
        /// What was being opened or declared.
        what: &'static str,
        /// Zenoh's error text.
        reason: String,
    },
    /// A password file or the solver's dictionary cannot be used (the reason never quotes a
    /// password).
    #[error("cluster credentials {file}: {reason}")]
    Credentials {
        /// The file.
        file: String,
        /// What is wrong.
        reason: String,
    },
    /// A pushed credential envelope is refused (docs/cluster-envelope.md); `why` gives the
    /// parameter port's verdict code.
    #[error("credential envelope refused: {reason}")]
    Envelope {
        /// The kind of refusal.
        why: crate::envelope::Refusal,
        /// What is wrong, in words (never the secret).
        reason: String,
    },
    /// A clock probe message that cannot be read (cluster::clock).
    #[error("clock probe: {reason}")]
    Probe {
        /// What is wrong.
        reason: String,
    },
    /// An observation did not encode (id too long, too many blobs).
    #[error("observation: {0}")]
    Observation(#[from] irtrack_core::Error),
}

/// Result alias for irtrack-cluster.
pub type Result<T> = std::result::Result<T, ClusterError>;
