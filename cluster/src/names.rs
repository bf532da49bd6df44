//! Key expressions and the names in them (plain code: the credentials need them without
//! the transport).

use crate::error::{ClusterError, Result};

/// The DNS name in the solver's TLS certificate, which boards check whatever address they
/// connect to (the certificate is pinned, so the name only ties it to its role; crate::tls).
pub const SOLVER_TLS_NAME: &str = "irtrack-solver";

/// Key expression of one camera's observations.
pub fn observation_key(rig: &str, board: &str, camera: usize) -> String {
    format!("irtrack/{rig}/{board}/cam/{camera}/obs")
}

/// Key expression the solver subscribes to: every board and camera of the rig.
pub fn rig_observations_key(rig: &str) -> String {
    format!("irtrack/{rig}/*/cam/*/obs")
}

/// Key expression of a board's clock probe queryable (cluster::clock).
pub fn clock_key(rig: &str, board: &str) -> String {
    format!("irtrack/{rig}/{board}/clock")
}

/// Key expression the solver's clock probe asks: every board of the rig.
pub fn rig_clock_key(rig: &str) -> String {
    format!("irtrack/{rig}/*/clock")
}

/// The board named by a clock reply's key `irtrack/<rig>/<board>/clock`.
pub fn board_of_clock_key<'k>(rig: &str, key: &'k str) -> Option<&'k str> {
    let board = key
        .strip_prefix("irtrack/")?
        .strip_prefix(rig)?
        .strip_prefix('/')?
        .strip_suffix("/clock")?;
    (!board.is_empty() && !board.contains('/')).then_some(board)
}

/// Checks a rig or board name for use in a key expression: 1..=32 bytes of `[A-Za-z0-9_-]`.
pub fn check_name(what: &str, name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name.len() <= irtrack_core::observation::MAX_OBS_ID_LEN
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    if ok {
        Ok(())
    } else {
        Err(ClusterError::Config {
            reason: format!("{what} name {name:?} must be 1..=32 characters of A-Z a-z 0-9 _ -"),
        })
    }
}
