//! irtrack-cluster: camera boards and one solver over Zenoh (docs/cluster.md).
//!
//! - [`credentials`]: the boards' password files and the solver's dictionary (plain code);
//! - [`pairing`]: grouping observations of many boards into frame sets (plain code, no
//!   network), with clock-offset faults;
//! - [`transport`] (feature `zenoh`): a publisher per board camera on
//!   `irtrack/<rig>/<board>/cam/<i>/obs` and the solver's subscriber, in peer mode with
//!   configured endpoints (multicast scouting optional).
//!
//! The message itself is `irtrack_core::observation` (docs/observation-protocol.md).

// Every public item says what it is for (issue 24).
#![deny(missing_docs)]

pub mod credentials;
pub mod error;
pub mod names;
pub mod pairing;
#[cfg(feature = "zenoh")]
pub mod transport;

pub use error::{ClusterError, Result};
