//! irtrack-cluster: camera boards and one solver (docs/cluster.md, issue 27).
//!
//! - [`pairing`]: grouping observations of many boards into frame sets (plain code, no
//!   network), with clock-offset faults.
//!
//! The message itself is `irtrack_core::observation` (docs/observation-protocol.md). The Zenoh
//! transport and irtrackd's camera/solver roles are not on main yet (docs/observation-protocol.md
//! says what is missing).

pub mod error;
pub mod pairing;

pub use error::{ClusterError, Result};
