//! What a camera board or the solver reports in `/status` → `cluster` and on the set-up page.
//! Plain data in a file of its own: the status document takes it without importing the
//! cluster's roles (which themselves report into the status).

use std::sync::Arc;

use serde::Serialize;

use crate::metrics::{LatencyHistogram, LatencySummary};

/// The solver's hop histogram, recorded by its loop without locking and summarised when
/// `/status` is read. Two reports are equal in it when they share the histogram.
#[derive(Debug, Clone, Default)]
pub struct SharedHistogram(pub Arc<LatencyHistogram>);

impl PartialEq for SharedHistogram {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

/// A board whose probed clock is further off than this gets the warning `clock_corrected`, ms
/// (healthy boards on PTP or chrony are well under it).
pub const CLOCK_CORRECTED_WARN_MS: f64 = 1.0;

/// One board as the solver sees it (`/status` → `cluster.boards`).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct BoardReport {
    /// The board's name (`[cluster] board` in its config).
    pub name: String,
    /// The rig's cameras on this board.
    pub cameras: Vec<usize>,
    /// Time since its last observation, ms; `None`: never heard from.
    pub last_seen_ms: Option<f64>,
    /// Its timestamps minus the solver's clock at their arrival (less the smallest transit),
    /// ms, after the clock probe's correction when that applies (then what is left of the
    /// board's clock error: about minus the transit).
    pub clock_offset_ms: Option<f64>,
    /// The clock probe's measurement of the board's clock (`None`: probe off, or no answer
    /// yet; docs/cluster.md, "Clock probe").
    pub clock_probe: Option<ClockProbeReport>,
    /// Clock offset beyond the limit: its observations are kept out of every set.
    pub clock_fault: bool,
    /// Its clock is ahead of the solver's by more than 1 ms (or a quarter of the tolerance)
    /// while another board's is not: its timestamps are late by at least `clock_offset_ms`,
    /// so its cameras are left out of every set (fault `clock_ahead`; docs/cluster.md).
    pub clock_ahead: bool,
    /// Its observations arrive later than their timestamps say by more than that limit, while
    /// another board's do not: its clock is behind the solver's, or its link is slow. Only a
    /// warning (fault `clock_behind`): a slow link would not make its data wrong.
    pub clock_behind: bool,
    /// Silent longer than `board_timeout_ms`.
    pub down: bool,
    /// Its cameras' rays miss the other boards' point in too many recent sets: its cameras
    /// are left out of every set (fault `board_disagrees`; docs/cluster.md).
    pub disagreeing: bool,
    /// Share of its recent comparable sets in which it disagreed (0..=1).
    pub disagreement_share: f64,
    /// Sets in which it could be compared with another board, and those it disagreed in.
    pub compared_sets: u64,
    /// Sets in which its rays missed the other boards' point.
    pub disagreed_sets: u64,
    /// Sets published without its cameras (they disagreed, or it is `disagreeing`).
    pub dropped_sets: u64,
    /// How far its rays missed the others' point (mm) and its reprojection error there (px),
    /// averaged over its recent disagreements.
    pub miss_mm: Option<f64>,
    /// See `miss_mm`.
    pub miss_px: Option<f64>,
    /// The time shift that explains its misses along the marker's motion, ms (positive: its
    /// frames show later instants than their timestamps say, relative to the others).
    pub time_shift_ms: Option<f64>,
    /// While `disagreeing`: `"clock"` (the misses follow the motion), `"calibration"` (they
    /// stay while the marker stands still) or `"unknown"`.
    pub likely_cause: Option<&'static str>,
    /// While `disagreeing` with no third board to decide: the board it disagrees with.
    pub disagrees_with: Option<String>,
}

/// A board's clock as the solver's two-way probe measures it (`/status` →
/// `cluster.boards[].clock_probe`).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct ClockProbeReport {
    /// Its clock minus the solver's, ms (what its timestamps are corrected by).
    pub offset_ms: Option<f64>,
    /// The worst error an unequal split of transit could cause (the best sample's bound: half
    /// its round trip plus half the solver's send call), ms.
    pub uncertainty_ms: Option<f64>,
    /// Its clock's rate against the solver's, ppm.
    pub drift_ppm: Option<f64>,
    /// The best sample's round trip, ms.
    pub rtt_ms: Option<f64>,
    /// Samples used (of the last 32).
    pub samples: usize,
    /// Replies taken since start, and refused (negative spans, round trip over 20 ms).
    pub replies: u64,
    /// See `replies`.
    pub refused: u64,
    /// Its observations' timestamps are being corrected by `offset_ms` now.
    pub corrected: bool,
    /// Times its clock stepped since start (a probe sample outside the estimate's bound).
    pub steps: u64,
    /// The last step: new offset minus the old one, ms, and how long ago it was seen, s.
    /// First measured by the one probe sample that showed it, then by the settled estimate.
    pub last_step_ms: Option<f64>,
    /// How far `last_step_ms` may be from the true step, ms: the two measurements' bounds.
    pub last_step_uncertainty_ms: Option<f64>,
    /// See `last_step_ms`.
    pub last_step_ago_s: Option<f64>,
    /// Stepped and not yet measured again: its cameras are left out of every set.
    pub settling: bool,
    /// Times its observations suddenly arrived late by more than its link's jitter (a clock
    /// stepped back, or a queue on the link), each time left out until the probe answered.
    pub suspected_steps_back: u64,
    /// Left out now for that reason.
    pub suspect: bool,
}

/// A clock step stays a fault this long after it was seen, s (a clock stepping every few
/// seconds keeps it up; a single step is still shown for a minute).
pub const CLOCK_STEP_FAULT_S: f64 = 60.0;

/// A peer the solver's Zenoh refused (`/status` → `cluster.refused_peers.recent`).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct RefusedPeerReport {
    /// `ip:port` it connected from; `None`: it sent nothing before its link ended.
    pub address: Option<String>,
    /// `credentials`, `handshake_timeout`, `accept_limit` or `tls`.
    pub reason: &'static str,
    /// For `credentials`: `missing`, `unknown_user`, `wrong_password` or `unreadable`.
    pub problem: Option<&'static str>,
    /// Refusals of this address for this reason.
    pub count: u64,
    /// Time since the newest, s.
    pub age_s: f64,
    /// The newest, Unix time, ms.
    pub last_unix_ms: u64,
    /// In plain words ("a peer at 10.0.0.66:51234 was refused: wrong or missing credentials
    /// (it sent no credentials)").
    pub words: String,
}

/// Peers the solver's Zenoh refused while they opened a link (`/status` →
/// `cluster.refused_peers`; docs/cluster.md, "Refused peers").
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct PeerRefusalsReport {
    /// Refusals are being counted (irtrackd's log layer is installed); `false`: every count is
    /// 0 because nothing looks, not because nothing was refused.
    pub counting: bool,
    /// Every refusal since start.
    pub total: u64,
    /// Per reason (`credentials`, `handshake_timeout`, `accept_limit`).
    pub by_reason: std::collections::BTreeMap<&'static str, u64>,
    /// Credential refusals per problem.
    pub credentials: std::collections::BTreeMap<&'static str, u64>,
    /// The latest refused addresses (at most 16), newest first.
    pub recent: Vec<RefusedPeerReport>,
    /// Publications the access control dropped: a peer let in with valid credentials put
    /// under a key its user may not use (another board's observations); one per message.
    pub denied_publications: u64,
    /// Their latest senders and keys (at most 16), newest first.
    pub denied_recent: Vec<DeniedPublicationReport>,
}

/// A sender whose publications on a key the solver's access control dropped (`/status` →
/// `cluster.refused_peers.denied_recent`).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct DeniedPublicationReport {
    /// Its Zenoh ID.
    pub zid: String,
    /// The user name it signed in with, once known.
    pub user: Option<String>,
    /// The access-control subject it matched (`Interface(lo)+Username(b1)+Transport(Tcp)+
    /// <zid>`), once known.
    pub subject: Option<String>,
    /// The key expression it published (or answered the clock probe) on.
    pub key: String,
    /// `put` (observations) or `reply` (clock probe answers).
    pub action: &'static str,
    /// Denials logged.
    pub count: u64,
    /// Time since the newest, s.
    pub age_s: f64,
    /// The newest, Unix time, ms.
    pub last_unix_ms: u64,
    /// In plain words.
    pub words: String,
}

/// TLS between the boards and the solver (`/status` → `cluster.tls`; docs/cluster.md, "TLS").
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct TlsReport {
    /// `solver` (proves itself with its certificate) or `board` (talks only to the solver
    /// that proves itself with the pinned one).
    pub side: &'static str,
    /// The certificate file (the solver's own, or the one a board pins).
    pub certificate_file: String,
    /// Board: links carried to the solver after it proved itself.
    pub carried: u64,
    /// Board: handshakes in which the peer at the solver's address did not prove itself.
    pub solver_refused: u64,
    /// Board: connections to the solver's address that did not open.
    pub unreachable: u64,
    /// Board: the newest problem, in words.
    pub last_problem: Option<String>,
    /// Board: how long ago, s.
    pub last_problem_age_s: Option<f64>,
}

/// The `solver_unverified` fault stays this long after the newest failed handshake, s.
pub const SOLVER_UNVERIFIED_FAULT_S: f64 = 60.0;

/// Credentials pushed to this board (`/status` → `cluster.pushed_credentials`).
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct PushedCredentialsReport {
    /// The accepted envelope's serial.
    pub serial: u64,
    /// The key id that signed it (known for a push since this start).
    pub signed_by: Option<String>,
    /// The Zenoh session runs with them (they were there at start).
    pub in_use: bool,
    /// In words ("stored (serial 7); takes effect at the next start of irtrackd").
    pub words: String,
}

/// How long the `peer_refused` fault stays after the newest refusal, s.
pub const PEER_REFUSED_FAULT_S: f64 = 60.0;

impl PeerRefusalsReport {
    /// The `peer_refused` fault while the newest refusal is under a minute old: who, why, how
    /// many, and what to do.
    pub fn fault_text(&self) -> Option<String> {
        let newest = self.recent.first().filter(|p| p.age_s < PEER_REFUSED_FAULT_S)?;
        let counts: Vec<String> = self
            .by_reason
            .iter()
            .filter(|(_, n)| **n > 0)
            .map(|(k, n)| format!("{} {n}", k.replace('_', " ")))
            .collect();
        let advice = match newest.reason {
            "tls" => {
                "the solver talks TLS only (docs/cluster.md \"TLS\"): if it is a camera board, give it the solver's certificate as [cluster] tls_solver_certificate_file; otherwise a host on the cell network tries to reach the solver: find it by its address"
            }
            "credentials" => {
                "if it is a camera board, give it its password file and list it in the solver's credentials file (host-tools cluster-keys, docs/cluster.md \"Credentials\"); otherwise a host on the cell network tries to publish observations: find it by its address"
            }
            _ => {
                "connections that never finish Zenoh's handshake are a port scan or a connection flood: keep the Zenoh port to the boards' addresses (docs/security.md, \"Cluster transport\")"
            }
        };
        Some(format!(
            "{}, {:.0} s ago; {} refused since start ({}) — nothing it sent was used; {advice}",
            newest.words,
            newest.age_s,
            self.total,
            counts.join(", ")
        ))
    }

    /// The `publication_denied` fault while the newest denial is under a minute old.
    pub fn denied_fault_text(&self) -> Option<String> {
        let newest = self
            .denied_recent
            .first()
            .filter(|d| d.age_s < PEER_REFUSED_FAULT_S)?;
        let does = if newest.action == "reply" {
            "answers the clock probe"
        } else {
            "publishes"
        };
        Some(format!(
            "{}, {:.0} s ago; {} dropped since start — none of it was used; a board {does} under another board's name: check its [cluster] board and that it has its own password file (host-tools cluster-keys, docs/cluster.md \"Credentials\")",
            newest.words, newest.age_s, self.denied_publications
        ))
    }
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
    /// Solver: the hop of the camera boards' observations, board publish → solver receive, µs
    /// (the solver's receive time minus the observation's capture time and the board's
    /// capture → send delay, both carried in the message; so it includes the board's clock
    /// offset from the solver's). From 1 s after the first observation on; the solver's own
    /// cameras are left out. `None` before the first sample.
    pub hop_us: Option<LatencySummary>,
    /// Solver: the histogram behind `hop_us` (not serialised).
    #[serde(skip)]
    pub hop: SharedHistogram,
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
    /// Solver: sets in which two or more boards saw the marker (their agreement was checked).
    pub sets_compared: u64,
    /// Solver: sets given no position because their boards' rays disagreed.
    pub sets_refused_disagreement: u64,
    /// Solver: sets published with a disagreeing board's cameras left out.
    pub sets_board_dropped: u64,
    /// Empty slots in closed sets, per camera.
    pub missing: Vec<u64>,
    /// Refused observations by problem code (docs/observation-protocol.md).
    pub refused: std::collections::BTreeMap<&'static str, u64>,
    /// The parameter set does not place the cameras on boards (solver cannot pair).
    pub no_placement: bool,
    /// Solver: the parameter set places cameras on the solver's own board that it cannot use
    /// (another image size than `image_sizes_px`, or no such camera), in words; their
    /// observations are refused (`own_camera` fault).
    pub own_camera_faults: Vec<String>,
    /// Solver: the rig cameras those faults are about (the same order): their observations
    /// are refused, so they have no blob and no LED fault of their own.
    pub own_refused_cameras: Vec<usize>,
    /// Solver: observations of its own cameras refused for that reason.
    pub own_refused: u64,
    /// Camera role: detecting and publishing without a parameter set of its own (a board
    /// with one camera needs none); its records carry no position.
    pub detection_only: bool,
    /// Solver: no placed camera board has sent a usable observation since start (fault
    /// `waiting_for_boards`, in words; the silence is no camera fault of the solver's).
    pub waiting_for_boards: Option<String>,
    /// Solver, trigger mode: boards sending observations without a trigger counter, and how
    /// many (each refused: no set can be made from them).
    pub no_trigger_boards: Vec<(String, u64)>,
    /// Solver: refused observations by sender (board name; `rig R board B` for another
    /// rig's; `?` when the payload could not be read), their count and the last problem.
    pub refused_senders: Vec<(String, u64, &'static str)>,
    /// Solver: camera sequences that went back while the capture time went on (a board
    /// restarted and counts from its start again): taken as a restart, not refused.
    pub sequence_restarts: u64,
    /// Solver: peers its Zenoh refused while they opened a link (wrong or missing
    /// credentials, handshake timeout, accept limit), with their addresses.
    pub refused_peers: Option<PeerRefusalsReport>,
    /// This board's X25519 public key for pushed credentials (64 hex digits), which
    /// `host-tools cluster-keys push` pins (docs/cluster.md, "Pushing credentials").
    pub box_public_key: Option<String>,
    /// Credentials pushed to this board, if any.
    pub pushed_credentials: Option<PushedCredentialsReport>,
    /// TLS, when configured.
    pub tls: Option<TlsReport>,
}

impl ClusterReport {
    /// The solver knows why no set arrives: it waits for boards that never sent, or its
    /// boards are down. The source's silence is then no `camera_lost` ("check its cable").
    pub fn explains_silence(&self) -> bool {
        self.role == "solver" && (self.waiting_for_boards.is_some() || self.boards.iter().any(|b| b.down))
    }
}

impl ClusterReport {
    /// Faults in plain words for the set-up view (`code`, the camera concerned, message).
    pub fn fault_texts(&self) -> Vec<(&'static str, Option<usize>, String)> {
        let mut out = Vec::new();
        if self.no_placement {
            out.push((
                "cluster_no_placement",
                None,
                "the parameter set does not say which board each camera is on — push a set with a placement (docs/cluster.md)".to_string(),
            ));
        }
        if let Some(w) = &self.waiting_for_boards {
            out.push(("waiting_for_boards", None, w.clone()));
        }
        if !self.no_trigger_boards.is_empty() {
            let list: Vec<String> = self
                .no_trigger_boards
                .iter()
                .map(|(b, n)| format!("{b} ({n} refused)"))
                .collect();
            out.push((
                "no_trigger_count",
                None,
                format!(
                    "[cluster] trigger = true pairs observations by the hardware trigger's counter, but camera board(s) {} send none, so no set can be made from them — wire the trigger to each board's counter input (docs/cluster.md, \"Topology and wiring\") or set trigger = false to pair by timestamps",
                    list.join(", ")
                ),
            ));
        }
        for (i, f) in self.own_camera_faults.iter().enumerate() {
            out.push(("own_camera", self.own_refused_cameras.get(i).copied(), f.clone()));
        }
        for b in &self.boards {
            // While no board has ever sent, `waiting_for_boards` says it once.
            if b.down && self.waiting_for_boards.is_none() {
                out.push((
                    "board_down",
                    None,
                    format!(
                        "camera board {} ({}) sends nothing{} — check its power and network; tracking goes on with the other cameras",
                        b.name,
                        camera_words(&b.cameras),
                        b.last_seen_ms.map_or(String::new(), |ms| format!(" for {:.1} s", ms / 1e3))
                    ),
                ));
            }
            if b.disagreeing {
                out.push(("board_disagrees", None, disagreement_words(b)));
            }
            if b.clock_ahead && !b.clock_fault {
                out.push((
                    "clock_ahead",
                    None,
                    format!(
                        "camera board {} ({}): its clock runs at least {:.1} ms ahead of the solver's while the other boards' do not — its timestamps would misplace the marker by that much of its motion, so its cameras are left out of the positions; check PTP/chrony on it (and [cluster] clock_offset_ms)",
                        b.name,
                        camera_words(&b.cameras),
                        b.clock_offset_ms.unwrap_or(f64::NAN)
                    ),
                ));
            }
            if b.clock_behind {
                out.push((
                    "clock_behind",
                    None,
                    format!(
                        "camera board {} ({}): its observations arrive at least {:.1} ms later than their timestamps say, while another board's arrive at once — its clock is behind the solver's, or its link is slow. If it is the clock, its cameras saw the marker that much earlier than their timestamps say (0.5 mm per ms at 0.5 m/s), which shows as disagreement only beyond the ray gate; check PTP/chrony on it (and [cluster] clock_offset_ms), and its network",
                        b.name,
                        camera_words(&b.cameras),
                        -b.clock_offset_ms.unwrap_or(f64::NAN)
                    ),
                ));
            }
            if let Some(p) = &b.clock_probe
                && p.corrected
                && let Some(off) = p.offset_ms.filter(|o| o.abs() > CLOCK_CORRECTED_WARN_MS)
            {
                out.push((
                    "clock_corrected",
                    None,
                    format!(
                        "camera board {} ({}): its clock is {:.1} ms {} the solver's (clock probe, ±{:.2} ms) — the solver puts its timestamps on its own clock, so positions are not affected; fix PTP/chrony on it all the same, as its own records and logs carry the wrong time",
                        b.name,
                        camera_words(&b.cameras),
                        off.abs(),
                        if off > 0.0 { "ahead of" } else { "behind" },
                        p.uncertainty_ms.unwrap_or(f64::NAN)
                    ),
                ));
            }
            if let Some(p) = &b.clock_probe
                && let (Some(by), Some(ago)) = (p.last_step_ms, p.last_step_ago_s)
                && (p.settling || ago < CLOCK_STEP_FAULT_S)
            {
                out.push((
                    "clock_stepped",
                    None,
                    format!(
                        "camera board {} ({}): its clock stepped by {:+.1}{} ms {:.0} s ago ({} step(s) since the solver started; clock probe) — {}; a clock that jumps while the cell runs usually has two time services setting it (ptp4l/phc2sys and chrony, NTP or systemd-timesyncd): let only one set it",
                        b.name,
                        camera_words(&b.cameras),
                        by,
                        p.last_step_uncertainty_ms
                            .map(|u| format!(" ± {u:.1}"))
                            .unwrap_or_default(),
                        ago,
                        p.steps,
                        if p.settling {
                            "its cameras are left out until the probe has measured its clock again (about a second)"
                        } else {
                            "its cameras were left out until the probe had measured its clock again"
                        }
                    ),
                ));
            }
            if b.clock_fault {
                out.push((
                    "clock_offset",
                    None,
                    format!(
                        "camera board {}: its clock is {:.1} ms off — its observations are left out; check PTP/chrony on it",
                        b.name,
                        b.clock_offset_ms.unwrap_or(f64::NAN)
                    ),
                ));
            }
        }
        if let Some(text) = self
            .refused_peers
            .as_ref()
            .and_then(PeerRefusalsReport::fault_text)
        {
            out.push(("peer_refused", None, text));
        }
        if let Some(text) = self
            .refused_peers
            .as_ref()
            .and_then(PeerRefusalsReport::denied_fault_text)
        {
            out.push(("publication_denied", None, text));
        }
        if let Some(t) = &self.tls
            && t.solver_refused > 0
            && let (Some(words), Some(age)) = (&t.last_problem, t.last_problem_age_s)
            && age < SOLVER_UNVERIFIED_FAULT_S
            && words.contains("did not prove itself")
        {
            out.push((
                "solver_unverified",
                None,
                format!(
                    "{words}, {age:.0} s ago; {} such handshakes since start, {} links carried — nothing was sent to it; if the solver was given a new certificate (cluster-keys --tls --force), give this board the new one as [cluster] tls_solver_certificate_file; otherwise a host at the solver's address pretends to be it (docs/security.md)",
                    t.solver_refused, t.carried
                ),
            ));
        }
        let refused: u64 = self.refused.values().sum();
        if refused > 0 {
            let list: Vec<String> = self.refused.iter().map(|(k, v)| format!("{k} {v}")).collect();
            let senders: Vec<String> = self
                .refused_senders
                .iter()
                .map(|(who, n, last)| match who.as_str() {
                    "?" => format!("{n} unreadable (sender unknown, last {last})"),
                    _ => format!("{n} from {who} (last {last})"),
                })
                .collect();
            let from = if senders.is_empty() {
                String::new()
            } else {
                format!("; by sender: {}", senders.join(", "))
            };
            out.push((
                "observations_refused",
                None,
                format!("{refused} observations refused ({}){from}", list.join(", ")),
            ));
        }
        out
    }
}

/// `/metrics` families of the camera and solver roles (a `prometheus-client` collector over
/// one copy of the report, so a scrape agrees with itself). Counter names without `_total`:
/// the encoder appends it.
impl prometheus_client::collector::Collector for ClusterReport {
    fn encode(
        &self,
        mut enc: prometheus_client::encoding::DescriptorEncoder,
    ) -> std::result::Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        let role = self.role;
        let counters: &[(&str, &str, u64)] = if role == "camera" {
            &[
                (
                    "irtrackd_cluster_observations_published",
                    "observations this camera board sent",
                    self.published,
                ),
                (
                    "irtrackd_cluster_publish_errors",
                    "observations Zenoh failed to send",
                    self.publish_errors,
                ),
            ]
        } else {
            &[
                (
                    "irtrackd_cluster_observations_received",
                    "observations the solver took from its queue",
                    self.received,
                ),
                (
                    "irtrackd_cluster_sets_complete",
                    "sets closed with every camera present",
                    self.sets_complete,
                ),
                (
                    "irtrackd_cluster_sets_incomplete",
                    "sets closed with a camera missing",
                    self.sets_incomplete,
                ),
                (
                    "irtrackd_cluster_observations_late",
                    "observations that arrived after their set was closed",
                    self.late,
                ),
                (
                    "irtrackd_cluster_observations_conflicting",
                    "second observations of one camera for the same open set",
                    self.conflicting,
                ),
                (
                    "irtrackd_cluster_observations_clock_refused",
                    "observations of a board with a clock fault, kept out of the sets",
                    self.refused_clock,
                ),
                (
                    "irtrackd_cluster_sequence_restarts",
                    "camera sequences that started again lower with a newer capture time (a board restart)",
                    self.sequence_restarts,
                ),
                (
                    "irtrackd_cluster_queue_overflow",
                    "observations dropped because the solver's receive queue was full",
                    self.queue_overflow,
                ),
                (
                    "irtrackd_cluster_sets_compared",
                    "sets in which two or more boards saw the marker (their agreement checked)",
                    self.sets_compared,
                ),
                (
                    "irtrackd_cluster_sets_refused_disagreement",
                    "sets given no position because their boards' rays disagreed",
                    self.sets_refused_disagreement,
                ),
                (
                    "irtrackd_cluster_sets_board_dropped",
                    "sets published with a disagreeing board's cameras left out",
                    self.sets_board_dropped,
                ),
                (
                    "irtrackd_cluster_own_camera_refused",
                    "observations of the solver's own cameras refused (own_camera fault: size or camera mismatch)",
                    self.own_refused,
                ),
            ]
        };
        for (name, help, value) in counters {
            let m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            ConstCounter::new(*value).encode(m)?;
        }
        if role == "camera" {
            return Ok(());
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_cluster_observations_refused",
            "refused observations by problem (docs/observation-protocol.md)",
            None,
            MetricType::Counter,
        )?;
        for (reason, n) in &self.refused {
            ConstCounter::new(*n).encode(m.encode_family(&[("reason", *reason)])?)?;
        }
        if let Some(p) = self.refused_peers.as_ref().filter(|p| p.counting) {
            let mut m = enc.encode_descriptor(
                "irtrackd_cluster_peers_refused",
                "links the solver's Zenoh refused while they opened, by reason (credentials, handshake_timeout, accept_limit)",
                None,
                MetricType::Counter,
            )?;
            for (reason, n) in &p.by_reason {
                ConstCounter::new(*n).encode(m.encode_family(&[("reason", *reason)])?)?;
            }
            let m = enc.encode_descriptor(
                "irtrackd_cluster_publications_denied",
                "publications the solver's Zenoh access control dropped (a peer let in put under a key its user may not use)",
                None,
                MetricType::Counter,
            )?;
            ConstCounter::new(p.denied_publications).encode(m)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_cluster_camera_missing",
            "empty slots of this camera in closed sets",
            None,
            MetricType::Counter,
        )?;
        for (camera, n) in self.missing.iter().enumerate() {
            let camera = camera.to_string();
            ConstCounter::new(*n).encode(m.encode_family(&[("camera", camera.as_str())])?)?;
        }
        let m = enc.encode_descriptor(
            "irtrackd_cluster_no_placement",
            "1 when the parameter set does not say which board each camera is on",
            None,
            MetricType::Gauge,
        )?;
        ConstGauge::new(i64::from(self.no_placement)).encode(m)?;
        type Get = fn(&BoardReport) -> Option<f64>;
        let gauges: [(&str, &str, Get); 10] = [
            (
                "irtrackd_cluster_board_disagreeing",
                "1 while the board's rays miss the other boards' point in too many sets (its cameras left out)",
                |b| Some(if b.disagreeing { 1.0 } else { 0.0 }),
            ),
            (
                "irtrackd_cluster_board_time_shift_seconds",
                "the time shift that explains the board's misses along the marker's motion",
                |b| b.time_shift_ms.map(|ms| ms / 1e3),
            ),
            (
                "irtrackd_cluster_board_up",
                "1 while the camera board is heard from within board_timeout_ms",
                |b| Some(if b.down { 0.0 } else { 1.0 }),
            ),
            (
                "irtrackd_cluster_board_clock_fault",
                "1 while the board's clock offset is beyond the limit (its observations are left out)",
                |b| Some(if b.clock_fault { 1.0 } else { 0.0 }),
            ),
            (
                "irtrackd_cluster_board_clock_ahead",
                "1 while the board's clock runs ahead of the solver's and the other boards' do not (its cameras are left out)",
                |b| Some(if b.clock_ahead { 1.0 } else { 0.0 }),
            ),
            (
                "irtrackd_cluster_board_clock_behind",
                "1 while the board's observations arrive later than their timestamps say and another board's do not (its clock behind, or a slow link)",
                |b| Some(if b.clock_behind { 1.0 } else { 0.0 }),
            ),
            (
                "irtrackd_cluster_board_clock_offset_seconds",
                "the board's clock minus the solver's, less the smallest transit",
                |b| b.clock_offset_ms.map(|ms| ms / 1e3),
            ),
            (
                "irtrackd_cluster_board_clock_probe_offset_seconds",
                "the board's clock minus the solver's as the two-way clock probe measures it (its timestamps are corrected by it)",
                |b| {
                    b.clock_probe
                        .as_ref()
                        .and_then(|p| p.offset_ms)
                        .map(|ms| ms / 1e3)
                },
            ),
            (
                "irtrackd_cluster_board_clock_steps",
                "clock steps the two-way clock probe saw on the board since the solver started",
                |b| b.clock_probe.as_ref().map(|p| p.steps as f64),
            ),
            (
                "irtrackd_cluster_board_last_seen_seconds",
                "time since the board's last observation",
                |b| b.last_seen_ms.map(|ms| ms / 1e3),
            ),
        ];
        for (name, help, get) in gauges {
            let mut m = enc.encode_descriptor(name, help, None, MetricType::Gauge)?;
            for b in &self.boards {
                if let Some(v) = get(b) {
                    ConstGauge::new(v).encode(m.encode_family(&[("board", b.name.as_str())])?)?;
                }
            }
        }
        type Count = fn(&BoardReport) -> u64;
        let per_board: [(&str, &str, Count); 2] = [
            (
                "irtrackd_cluster_board_disagreed_sets",
                "sets in which the board's rays missed the other boards' point",
                |b| b.disagreed_sets,
            ),
            (
                "irtrackd_cluster_board_dropped_sets",
                "sets published without the board's cameras (they disagreed)",
                |b| b.dropped_sets,
            ),
        ];
        for (name, help, get) in per_board {
            let mut m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            for b in &self.boards {
                ConstCounter::new(get(b)).encode(m.encode_family(&[("board", b.name.as_str())])?)?;
            }
        }
        Ok(())
    }
}

/// The `board_disagrees` fault: which board, by how much, the likely cause and the next step.
fn disagreement_words(b: &BoardReport) -> String {
    let whom = match &b.disagrees_with {
        Some(peer) => format!(
            "camera boards {} and {peer} disagree (no third board decides which is right, so neither gives positions)",
            b.name
        ),
        None => format!(
            "camera board {} ({}) disagrees with the other boards (its cameras are left out of the positions)",
            b.name,
            camera_words(&b.cameras)
        ),
    };
    let miss = match (b.miss_mm, b.miss_px) {
        (Some(mm), Some(px)) => format!(": its rays miss their point by {mm:.1} mm ({px:.1} px)"),
        (Some(mm), None) => format!(": their rays miss each other by {mm:.1} mm"),
        _ => String::new(),
    };
    let share = format!(" in {:.0} % of recent sets", b.disagreement_share * 100.0);
    let cause = match (b.likely_cause, b.time_shift_ms) {
        (Some("clock"), Some(ms)) => format!(
            " — the misses follow the marker's motion, as if its frames were {:.1} ms {} than their timestamps say: check its clock (PTP/chrony, [cluster] clock_offset_ms) and, for recordings, that the boards' replays share one start",
            ms.abs(),
            if ms >= 0.0 { "later" } else { "earlier" }
        ),
        (Some("clock"), None) => " — the misses follow the marker's motion: check its clock (PTP/chrony) and the pairing of its frames".into(),
        (Some("calibration"), _) => " — the misses stay while the marker stands still: its calibration does not fit (a camera moved, or the parameter set is not this rig's); calibrate again".into(),
        _ => " — move the marker to tell a clock fault (misses along the motion) from a calibration fault (misses at rest)".into(),
    };
    format!("{whom}{miss}{share}{cause}")
}

/// `camera 2`, `cameras 0, 1` (no cameras: `no camera placed`), for messages a person reads.
fn camera_words(cameras: &[usize]) -> String {
    let list: Vec<String> = cameras.iter().map(usize::to_string).collect();
    match cameras.len() {
        0 => "no camera placed".into(),
        1 => format!("camera {}", list[0]),
        _ => format!("cameras {}", list.join(", ")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Asserts that `report` gives exactly one fault, `code`, whose text starts with `start`;
    /// returns its text.
    fn the_one_fault(report: &ClusterReport, code: &str, start: &str) -> String {
        let texts = report.fault_texts();
        assert_eq!(texts.len(), 1, "{texts:?}");
        assert_eq!(texts[0].0, code);
        assert!(texts[0].2.starts_with(start), "{}", texts[0].2);
        texts[0].2.clone()
    }

    #[test]
    fn a_solver_that_does_not_prove_itself_is_a_board_fault_for_a_minute() {
        let problem = "the peer at 10.0.0.10:7447 did not prove itself as this cell's solver (invalid peer certificate: BadSignature): is it the solver, with the certificate this board pins?";
        let mut report = ClusterReport {
            role: "camera",
            tls: Some(TlsReport {
                side: "board",
                certificate_file: "/var/lib/irtrack/cluster-credentials/solver.tls.crt".into(),
                carried: 3,
                solver_refused: 2,
                unreachable: 0,
                last_problem: Some(problem.into()),
                last_problem_age_s: Some(4.2),
            }),
            ..ClusterReport::default()
        };
        let text = the_one_fault(&report, "solver_unverified", problem);
        assert!(
            text.contains("4 s ago; 2 such handshakes since start, 3 links carried — nothing was sent to it"),
            "{text}"
        );
        // A minute later it is gone; an unreachable solver is not this fault (no proof failed).
        if let Some(t) = report.tls.as_mut() {
            t.last_problem_age_s = Some(61.0);
        }
        assert!(report.fault_texts().is_empty(), "{:?}", report.fault_texts());
        report.tls = Some(TlsReport {
            side: "board",
            unreachable: 5,
            last_problem: Some("the solver at 10.0.0.10:7447 cannot be reached: Connection refused".into()),
            last_problem_age_s: Some(1.0),
            ..TlsReport::default()
        });
        assert!(report.fault_texts().is_empty(), "{:?}", report.fault_texts());
    }

    /// The report's `/metrics` families as OpenMetrics text.
    fn metrics_text(report: ClusterReport) -> String {
        let mut text = String::new();
        let mut reg = prometheus_client::registry::Registry::default();
        reg.register_collector(Box::new(report));
        prometheus_client::encoding::text::encode(&mut text, &reg).unwrap();
        text
    }

    #[test]
    fn a_refused_peer_is_a_fault_for_a_minute_and_a_metric() {
        let mut p = PeerRefusalsReport {
            counting: true,
            total: 3,
            by_reason: [("accept_limit", 0), ("credentials", 2), ("handshake_timeout", 1)].into(),
            credentials: [("missing", 2)].into(),
            recent: vec![RefusedPeerReport {
                address: Some("10.0.0.66:51234".into()),
                reason: "credentials",
                problem: Some("missing"),
                count: 2,
                age_s: 4.2,
                last_unix_ms: 0,
                words: "a peer at 10.0.0.66:51234 was refused: wrong or missing credentials (it sent no credentials)".into(),
            }],
            denied_publications: 0,
            denied_recent: Vec::new(),
        };
        let report = ClusterReport {
            role: "solver",
            refused_peers: Some(p.clone()),
            ..ClusterReport::default()
        };
        the_one_fault(
            &report,
            "peer_refused",
            "a peer at 10.0.0.66:51234 was refused: wrong or missing credentials (it sent no credentials), 4 s ago; 3 refused since start (credentials 2, handshake timeout 1) — nothing it sent was used; if it is a camera board, give it its password file",
        );
        let text = metrics_text(report);
        assert!(
            text.contains("irtrackd_cluster_peers_refused_total{reason=\"credentials\"} 2"),
            "{text}"
        );
        assert!(
            text.contains("irtrackd_cluster_peers_refused_total{reason=\"accept_limit\"} 0"),
            "{text}"
        );
        // A minute later the fault is gone; the counts stay.
        p.recent[0].age_s = PEER_REFUSED_FAULT_S + 1.0;
        assert_eq!(p.fault_text(), None);
        p.recent[0].age_s = 1.0;
        p.recent[0].reason = "handshake_timeout";
        assert!(
            p.fault_text()
                .unwrap()
                .contains("port scan or a connection flood")
        );
    }

    #[test]
    fn a_denied_publication_is_its_own_fault_for_a_minute_and_a_metric() {
        let mut p = PeerRefusalsReport {
            counting: true,
            denied_publications: 41,
            denied_recent: vec![DeniedPublicationReport {
                zid: "4f2a9c".into(),
                user: Some("b1".into()),
                subject: Some("Interface(lo)+Username(b1)+Transport(Tcp)+4f2a9c".into()),
                key: "irtrack/cell1/b0/cam/0/obs".into(),
                action: "put",
                count: 41,
                age_s: 2.0,
                last_unix_ms: 0,
                words: "a peer signed in as b1 (Zenoh ID 4f2a9c) published on irtrack/cell1/b0/cam/0/obs, which its credentials do not allow: dropped by the access control".into(),
            }],
            ..PeerRefusalsReport::default()
        };
        let report = ClusterReport {
            role: "solver",
            refused_peers: Some(p.clone()),
            ..ClusterReport::default()
        };
        let texts = report.fault_texts();
        assert_eq!(
            texts.len(),
            1,
            "no link was refused, so no peer_refused: {texts:?}"
        );
        assert_eq!(texts[0].0, "publication_denied");
        assert!(
            texts[0].2.starts_with(
                "a peer signed in as b1 (Zenoh ID 4f2a9c) published on irtrack/cell1/b0/cam/0/obs, which its credentials do not allow: dropped by the access control, 2 s ago; 41 dropped since start — none of it was used; a board publishes under another board's name"
            ),
            "{}",
            texts[0].2
        );
        let text = metrics_text(report);
        assert!(
            text.contains("irtrackd_cluster_publications_denied_total 41"),
            "{text}"
        );
        p.denied_recent[0].age_s = PEER_REFUSED_FAULT_S + 1.0;
        assert_eq!(p.denied_fault_text(), None);
    }

    #[test]
    fn a_down_board_is_named_with_its_cameras_in_words() {
        assert_eq!(camera_words(&[]), "no camera placed");
        assert_eq!(camera_words(&[2]), "camera 2");
        assert_eq!(camera_words(&[0, 1]), "cameras 0, 1");
        let report = ClusterReport {
            boards: vec![BoardReport {
                name: "b1".into(),
                cameras: vec![2],
                last_seen_ms: Some(4400.0),
                clock_offset_ms: None,
                clock_fault: false,
                down: true,
                ..BoardReport::default()
            }],
            ..ClusterReport::default()
        };
        the_one_fault(
            &report,
            "board_down",
            "camera board b1 (camera 2) sends nothing for 4.4 s — check its power",
        );
    }

    /// A board whose clock is ahead: its own fault naming the board, its cameras and the
    /// measured offset, and a metric; not a second fault once the offset faults it outright.
    #[test]
    fn a_board_ahead_is_a_fault_and_a_metric() {
        let ahead = BoardReport {
            name: "b1".into(),
            cameras: vec![2, 3],
            last_seen_ms: Some(3.0),
            clock_offset_ms: Some(6.53),
            clock_ahead: true,
            ..BoardReport::default()
        };
        let report = ClusterReport {
            boards: vec![ahead.clone()],
            ..ClusterReport::default()
        };
        let fault = the_one_fault(
            &report,
            "clock_ahead",
            "camera board b1 (cameras 2, 3): its clock runs at least 6.5 ms ahead",
        );
        assert!(fault.contains("left out"), "{fault}");
        let text = metrics_text(report);
        assert!(
            text.contains("irtrackd_cluster_board_clock_ahead{board=\"b1\"} 1"),
            "{text}"
        );
        let faulted = ClusterReport {
            boards: vec![BoardReport {
                clock_fault: true,
                clock_offset_ms: Some(50.0),
                ..ahead
            }],
            ..ClusterReport::default()
        };
        let codes: Vec<&str> = faulted.fault_texts().iter().map(|t| t.0).collect();
        assert_eq!(codes, ["clock_offset"]);
        let behind = ClusterReport {
            boards: vec![BoardReport {
                name: "b2".into(),
                cameras: vec![4],
                clock_offset_ms: Some(-5.96),
                clock_behind: true,
                ..BoardReport::default()
            }],
            ..ClusterReport::default()
        };
        the_one_fault(
            &behind,
            "clock_behind",
            "camera board b2 (camera 4): its observations arrive at least 6.0 ms later than their timestamps say",
        );
        let text = metrics_text(behind);
        assert!(
            text.contains("irtrackd_cluster_board_clock_behind{board=\"b2\"} 1"),
            "{text}"
        );
    }

    /// A board the clock probe corrects: a warning naming it, which way and how far its clock
    /// is off and the probe's uncertainty, and the probed offset as a metric; none while the
    /// correction is under the warning limit or not applied.
    #[test]
    fn a_corrected_board_is_a_warning_and_a_metric() {
        let probe = ClockProbeReport {
            offset_ms: Some(-6.02),
            uncertainty_ms: Some(0.08),
            drift_ppm: Some(1.5),
            rtt_ms: Some(0.16),
            samples: 12,
            replies: 40,
            refused: 0,
            corrected: true,
            ..ClockProbeReport::default()
        };
        let board = BoardReport {
            name: "b1".into(),
            cameras: vec![2, 3],
            last_seen_ms: Some(3.0),
            clock_offset_ms: Some(-0.1),
            clock_probe: Some(probe.clone()),
            ..BoardReport::default()
        };
        let report = ClusterReport {
            boards: vec![board.clone()],
            ..ClusterReport::default()
        };
        the_one_fault(
            &report,
            "clock_corrected",
            "camera board b1 (cameras 2, 3): its clock is 6.0 ms behind the solver's (clock probe, ±0.08 ms)",
        );
        let text = metrics_text(report);
        let value: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("irtrackd_cluster_board_clock_probe_offset_seconds{board=\"b1\"} "))
            .unwrap_or_else(|| panic!("{text}"))
            .parse()
            .unwrap();
        assert!((value + 0.00602).abs() < 1e-9, "{value}");
        for quiet in [
            ClockProbeReport {
                offset_ms: Some(0.4),
                ..probe.clone()
            },
            ClockProbeReport {
                corrected: false,
                ..probe
            },
        ] {
            let r = ClusterReport {
                boards: vec![BoardReport {
                    clock_probe: Some(quiet),
                    ..board.clone()
                }],
                ..ClusterReport::default()
            };
            assert!(r.fault_texts().is_empty(), "{:?}", r.fault_texts());
        }
    }

    /// A board whose clock stepped: a fault with the step, how long ago, how many, and whether
    /// its cameras are still left out; the count as a metric; no fault once a single step is a
    /// minute old.
    #[test]
    fn a_clock_step_is_a_fault_naming_the_board_and_the_step() {
        let probe = ClockProbeReport {
            offset_ms: None,
            samples: 1,
            replies: 30,
            steps: 3,
            last_step_ms: Some(-8.04),
            last_step_uncertainty_ms: Some(1.26),
            last_step_ago_s: Some(0.3),
            settling: true,
            ..ClockProbeReport::default()
        };
        let board = |p: &ClockProbeReport| BoardReport {
            name: "b1".into(),
            cameras: vec![2, 3],
            clock_probe: Some(p.clone()),
            ..BoardReport::default()
        };
        let report = ClusterReport {
            boards: vec![board(&probe)],
            ..ClusterReport::default()
        };
        the_one_fault(
            &report,
            "clock_stepped",
            "camera board b1 (cameras 2, 3): its clock stepped by -8.0 ± 1.3 ms 0 s ago (3 step(s) since the solver started; clock probe) — its cameras are left out until",
        );
        assert!(metrics_text(report).contains("irtrackd_cluster_board_clock_steps{board=\"b1\"} 3"));
        // Re-measured against the settled estimate: a tighter bound.
        let after = ClockProbeReport {
            settling: false,
            last_step_ms: Some(-7.97),
            last_step_uncertainty_ms: Some(0.18),
            last_step_ago_s: Some(20.0),
            ..probe.clone()
        };
        let fault = the_one_fault(
            &ClusterReport {
                boards: vec![board(&after)],
                ..ClusterReport::default()
            },
            "clock_stepped",
            "camera board b1 (cameras 2, 3): its clock stepped by -8.0 ± 0.2 ms 20 s ago",
        );
        assert!(
            fault.contains("were left out until the probe had measured"),
            "{fault}"
        );
        let old = ClockProbeReport {
            last_step_ago_s: Some(CLOCK_STEP_FAULT_S + 1.0),
            ..after
        };
        let r = ClusterReport {
            boards: vec![board(&old)],
            ..ClusterReport::default()
        };
        assert!(r.fault_texts().is_empty(), "{:?}", r.fault_texts());
    }
}
