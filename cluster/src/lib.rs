//! irtrack-cluster: camera boards and one solver over Zenoh (docs/cluster.md).
//!
//! - [`clock`]: the clock probe's message and the estimator of a board's clock against the
//!   solver's (two-way exchange; plain code);
//! - [`credentials`]: the boards' password files and the solver's dictionary (plain code);
//! - [`envelope`]: sealed credential envelopes pushed from the PC (encrypted to a board's
//!   X25519 key, signed by a trusted Ed25519 key; docs/cluster-envelope.md);
//! - [`pairing`]: grouping observations of many boards into frame sets (plain code, no
//!   network), with clock-offset faults;
//! - [`transport`] (feature `zenoh`): a publisher per board camera on
//!   `irtrack/<rig>/<board>/cam/<i>/obs` and the solver's subscriber, in peer mode with
//!   configured endpoints (multicast scouting optional);
//! - [`refusals`] (feature `zenoh`): the peers Zenoh refuses (credentials, handshake time,
//!   accept limit), counted with their address from Zenoh's own `tracing` events;
//! - [`tls`] (feature `zenoh`): TLS tunnels around the Zenoh links (the solver proves itself
//!   with a certificate the boards pin; every link encrypted).
//!
//! The message itself is `irtrack_core::observation` (docs/observation-protocol.md).

// Every public item says what it is for (issue 24).
#![deny(missing_docs)]

pub mod clock;
pub mod credentials;
pub mod envelope;
pub mod error;
pub mod names;
pub mod pairing;
#[cfg(feature = "zenoh")]
pub mod refusals;
#[cfg(feature = "zenoh")]
pub mod tls;
#[cfg(feature = "zenoh")]
pub mod transport;

pub use error::{ClusterError, Result};
