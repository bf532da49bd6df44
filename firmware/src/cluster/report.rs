//! What a camera board or the solver reports in `/status` → `cluster` and on the set-up page.
//! Plain data in a file of its own: the status document takes it without importing the
//! cluster's roles (which themselves report into the status).

use serde::Serialize;

/// One board as the solver sees it (`/status` → `cluster.boards`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BoardReport {
    /// The board's name (`[cluster] board` in its config).
    pub name: String,
    /// The rig's cameras on this board.
    pub cameras: Vec<usize>,
    /// Time since its last observation, ms; `None`: never heard from.
    pub last_seen_ms: Option<f64>,
    /// Its clock minus the solver's (less the smallest transit), ms.
    pub clock_offset_ms: Option<f64>,
    /// Clock offset beyond the limit: its observations are kept out of every set.
    pub clock_fault: bool,
    /// Silent longer than `board_timeout_ms`.
    pub down: bool,
}

/// `/status` → `cluster` (camera and solver roles).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct ClusterReport {
    /// `"camera"` or `"solver"`.
    pub role: &'static str,
    /// The rig's name, the parameter set's rig id (`[cluster] rig`).
    pub rig: String,
    /// This board's name (`[cluster] board`).
    pub board: String,
    /// Camera role: observations sent, and those dropped by loss injection.
    pub published: u64,
    /// Camera role: observations Zenoh failed to send.
    pub publish_errors: u64,
    /// Camera role: observations deliberately not sent (loss injection for tests).
    pub injected_losses: u64,
    /// Solver.
    pub boards: Vec<BoardReport>,
    /// Solver: observation messages taken from the queue.
    pub received: u64,
    /// Solver: sets closed with every camera present.
    pub sets_complete: u64,
    /// Solver: sets closed with a camera missing (deadline passed or room needed).
    pub sets_incomplete: u64,
    /// Solver: observations that arrived after their set was closed.
    pub late: u64,
    /// Solver: second observations of one camera for the same open set.
    pub conflicting: u64,
    /// Solver: observations of a board with a clock fault, kept out of the sets.
    pub refused_clock: u64,
    /// Solver: observations dropped because its receive queue was full.
    pub queue_overflow: u64,
    /// Empty slots in closed sets, per camera.
    pub missing: Vec<u64>,
    /// Refused observations by problem code (docs/observation-protocol.md).
    pub refused: std::collections::BTreeMap<&'static str, u64>,
    /// The parameter set does not place the cameras on boards (solver cannot pair).
    pub no_placement: bool,
    /// Camera role: detecting and publishing without a parameter set of its own (a board
    /// with one camera needs none); its records carry no position.
    pub detection_only: bool,
}

impl ClusterReport {
    /// Faults in plain words for the set-up view (`code`, message).
    pub fn fault_texts(&self) -> Vec<(&'static str, String)> {
        let mut out = Vec::new();
        if self.no_placement {
            out.push((
                "cluster_no_placement",
                "the parameter set does not say which board each camera is on — push a set with a placement (docs/cluster.md)".to_string(),
            ));
        }
        for b in &self.boards {
            if b.down {
                out.push((
                    "board_down",
                    format!(
                        "camera board {} (cameras {:?}) sends nothing{} — check its power and network; tracking goes on with the other cameras",
                        b.name,
                        b.cameras,
                        b.last_seen_ms.map_or(String::new(), |ms| format!(" for {:.1} s", ms / 1e3))
                    ),
                ));
            }
            if b.clock_fault {
                out.push((
                    "clock_offset",
                    format!(
                        "camera board {}: its clock is {:.1} ms off — its observations are left out; check PTP/chrony on it",
                        b.name,
                        b.clock_offset_ms.unwrap_or(f64::NAN)
                    ),
                ));
            }
        }
        let refused: u64 = self.refused.values().sum();
        if refused > 0 {
            let list: Vec<String> = self.refused.iter().map(|(k, v)| format!("{k} {v}")).collect();
            out.push((
                "observations_refused",
                format!("{refused} observations refused ({})", list.join(", ")),
            ));
        }
        out
    }
}
