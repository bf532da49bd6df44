//! Cluster roles (docs/cluster.md): a camera board publishes its cameras' blobs, a solver
//! pairs every board's observations and runs the usual pipeline on them.
//!
//! `[cluster]` is always parsed; the roles other than `standalone` need the `cluster` feature
//! (Zenoh, through `irtrack-cluster`).

use serde::{Deserialize, Serialize};

use crate::error::{FirmwareError, Result};

#[cfg(feature = "cluster")]
pub mod agreement;
#[cfg(feature = "cluster")]
pub mod camera;
#[cfg(feature = "cluster")]
pub mod keys;
pub mod report;
pub use report::{BoardReport, ClusterReport};
#[cfg(feature = "cluster")]
pub mod solver;

/// What this irtrackd does in a multi-board rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// One board: its own cameras, its own solution (today's behaviour).
    #[default]
    Standalone,
    /// Captures and detects on its cameras and publishes the blobs; keeps its set-up view.
    Camera,
    /// Subscribes to the camera boards, pairs, triangulates all cameras, runs the outputs.
    Solver,
}

/// `[cluster]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClusterConfig {
    /// What this board does in the cluster (standalone by default).
    #[serde(default)]
    pub role: Role,
    /// The rig's name (the parameter set's rig id); part of every key expression.
    #[serde(default = "d_rig")]
    pub rig: String,
    /// This board's name (camera role); the solver's parameter set places cameras by it.
    #[serde(default = "d_board")]
    pub board: String,
    /// Zenoh endpoints to listen on, e.g. `["tcp/0.0.0.0:7447"]`.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Zenoh endpoints to connect to (the solver's, other boards', or a `zenohd` router).
    #[serde(default)]
    pub connect: Vec<String>,
    /// Find peers by UDP multicast instead of (or besides) the endpoints. Off by default.
    #[serde(default)]
    pub multicast_scouting: bool,
    /// Zenoh's low-latency transport (default off; negotiated per link, see docs/cluster.md).
    #[serde(default)]
    pub low_latency: bool,
    /// SCHED_FIFO priority 1..=99 for Zenoh's threads that carry observations (a camera
    /// board's transmit threads, the solver's receive threads; docs/cluster.md). Off by
    /// default; needs CAP_SYS_NICE or LimitRTPRIO (systemd/irtrackd-realtime.conf).
    #[serde(default)]
    pub transport_fifo_priority: Option<i32>,
    /// Solver: pair by the hardware trigger's frame counter (cameras triggered) instead of
    /// timestamps.
    #[serde(default)]
    pub trigger: bool,
    /// Solver: the boards' nominal frame rate; sets the default tolerance (half a period).
    #[serde(default = "d_fps")]
    pub fps: f64,
    /// Solver: timestamp tolerance, ms (default half a frame period).
    #[serde(default)]
    pub tolerance_ms: Option<f64>,
    /// Solver: a set closes this long after its first observation, ms (default two periods).
    #[serde(default)]
    pub set_deadline_ms: Option<f64>,
    /// Solver: a board whose clock is further off than this is faulted, ms (default: the
    /// tolerance).
    #[serde(default)]
    pub max_clock_offset_ms: Option<f64>,
    /// Solver: measure each camera board's clock by a two-way probe (four times a second) and
    /// put its observations' timestamps on the solver's clock (docs/cluster.md, "Clock
    /// probe"). On by default; off, a board's clock error is only judged from one-way
    /// arrival times (left out when ahead, warned when behind).
    #[serde(default = "d_true")]
    pub correct_board_clocks: bool,
    /// Solver: a board silent this long is reported down, ms.
    #[serde(default = "d_board_timeout")]
    pub board_timeout_ms: f64,
    /// Solver: image size of each of the rig's cameras, in the parameter set's camera order
    /// (what the parameter set must match, as a local source's cameras are).
    #[serde(default)]
    pub image_sizes_px: Vec<[u32; 2]>,
    /// Solver: it also captures on cameras of its own (`[source]`, sim or V4L2), placed in
    /// the parameter set under this board's name (`board`); their blobs join the same pairing
    /// as the camera boards' observations.
    #[serde(default)]
    pub own_cameras: bool,
    /// Camera role: this board's password for the solver (a file of one line, made by
    /// `host-tools cluster-keys`); its user name is `board`. Unset: the board connects without
    /// credentials (warned; docs/cluster.md, "Credentials").
    #[serde(default)]
    pub password_file: Option<std::path::PathBuf>,
    /// Solver: the camera boards' credentials (`board:password` lines, made by `host-tools
    /// cluster-keys`). Set: only those boards are accepted, each may publish only its own
    /// observations. Unset: any peer that reaches the port may publish (warned).
    #[serde(default)]
    pub credentials_file: Option<std::path::PathBuf>,
    /// Solver: its TLS certificate (PEM, made by `host-tools cluster-keys --tls`), which every
    /// board pins. Set with `tls_key_file`: the solver proves itself to the boards and every
    /// link is encrypted (docs/cluster.md, "TLS"). Needs `credentials_file`.
    #[serde(default)]
    pub tls_certificate_file: Option<std::path::PathBuf>,
    /// Solver: the private key of `tls_certificate_file` (PEM, mode 0600).
    #[serde(default)]
    pub tls_key_file: Option<std::path::PathBuf>,
    /// Camera role: the solver's TLS certificate this board pins (PEM). Set: the board talks
    /// only to a solver that proves itself with it, over TLS. Needs `password_file`.
    #[serde(default)]
    pub tls_solver_certificate_file: Option<std::path::PathBuf>,
    /// Camera role, tests: probability of not sending an observation (loss injection).
    #[serde(default)]
    pub inject_loss: f64,
    /// Camera role, tests: largest extra random delay before sending, ms (jitter injection).
    #[serde(default)]
    pub inject_jitter_ms: f64,
    /// Camera role, simulation and tests: this board's clock error, ms (added to the capture
    /// timestamps it sends, as a board with an unsynchronised clock would).
    #[serde(default)]
    pub clock_offset_ms: f64,
    /// Camera role, simulation and tests: this board's clock drift, ppm.
    #[serde(default)]
    pub clock_drift_ppm: f64,
    /// Camera role, simulation and tests: with `clock_step_every_s`, the board's clock steps by
    /// this much, ms, every `clock_step_every_s` seconds, and back again as often (two time
    /// services fighting over the clock).
    #[serde(default)]
    pub clock_step_ms: f64,
    /// See `clock_step_ms`; 0: never.
    #[serde(default)]
    pub clock_step_every_s: f64,
}

fn d_rig() -> String {
    "rig".into()
}
fn d_board() -> String {
    "board0".into()
}
fn d_fps() -> f64 {
    60.0
}
fn d_true() -> bool {
    true
}
fn d_board_timeout() -> f64 {
    500.0
}

impl Default for ClusterConfig {
    fn default() -> Self {
        ClusterConfig {
            role: Role::Standalone,
            rig: d_rig(),
            board: d_board(),
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: false,
            low_latency: false,
            transport_fifo_priority: None,
            trigger: false,
            fps: d_fps(),
            tolerance_ms: None,
            set_deadline_ms: None,
            max_clock_offset_ms: None,
            correct_board_clocks: true,
            board_timeout_ms: d_board_timeout(),
            image_sizes_px: Vec::new(),
            own_cameras: false,
            password_file: None,
            credentials_file: None,
            tls_certificate_file: None,
            tls_key_file: None,
            tls_solver_certificate_file: None,
            inject_loss: 0.0,
            inject_jitter_ms: 0.0,
            clock_offset_ms: 0.0,
            clock_drift_ppm: 0.0,
            clock_step_ms: 0.0,
            clock_step_every_s: 0.0,
        }
    }
}

impl ClusterConfig {
    /// Checks the role's settings: the `cluster` feature is built in, rig and board names are
    /// valid, endpoints or scouting are given, rates are positive. Standalone needs nothing; the
    /// error names the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        if let Some(p) = self.transport_fifo_priority
            && !(1..=99).contains(&p)
        {
            return bad(format!("cluster.transport_fifo_priority must be 1..=99, got {p}"));
        }
        if self.role == Role::Standalone {
            return Ok(());
        }
        if !cfg!(feature = "cluster") {
            return bad(format!(
                "cluster.role = {:?} needs irtrackd built with the `cluster` feature",
                self.role
            ));
        }
        for (what, name) in [("cluster.rig", &self.rig), ("cluster.board", &self.board)] {
            let ok = !name.is_empty()
                && name.len() <= irtrack_core::params::MAX_BOARD_NAME_LEN
                && name
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
            if !ok {
                return bad(format!(
                    "{what} = {name:?} must be 1..=32 characters of A-Z a-z 0-9 _ -"
                ));
            }
        }
        if self.listen.is_empty() && self.connect.is_empty() && !self.multicast_scouting {
            return bad(
                "cluster: give listen and/or connect endpoints (or multicast_scouting = true)".into(),
            );
        }
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return bad(format!("cluster.fps must be > 0, got {}", self.fps));
        }
        for (key, v) in [
            ("tolerance_ms", self.tolerance_ms),
            ("set_deadline_ms", self.set_deadline_ms),
            ("max_clock_offset_ms", self.max_clock_offset_ms),
            ("board_timeout_ms", Some(self.board_timeout_ms)),
        ] {
            if let Some(v) = v
                && !(v.is_finite() && v > 0.0)
            {
                return bad(format!("cluster.{key} must be > 0, got {v}"));
            }
        }
        if !(0.0..1.0).contains(&self.inject_loss) {
            return bad(format!(
                "cluster.inject_loss must be in [0, 1), got {}",
                self.inject_loss
            ));
        }
        if !(self.inject_jitter_ms.is_finite() && (0.0..=1000.0).contains(&self.inject_jitter_ms)) {
            return bad(format!(
                "cluster.inject_jitter_ms must be in 0..=1000, got {}",
                self.inject_jitter_ms
            ));
        }
        if !(self.clock_offset_ms.is_finite() && self.clock_drift_ppm.is_finite()) {
            return bad("cluster.clock_offset_ms and clock_drift_ppm must be finite".into());
        }
        if !(self.clock_step_ms.is_finite()
            && self.clock_step_every_s.is_finite()
            && self.clock_step_every_s >= 0.0)
        {
            return bad(format!(
                "cluster.clock_step_ms must be finite and clock_step_every_s at least 0, got {} and {}",
                self.clock_step_ms, self.clock_step_every_s
            ));
        }
        if self.own_cameras && self.role != Role::Solver {
            return bad(
                "cluster.own_cameras is for role = \"solver\" (a camera board always captures on its own cameras)"
                    .into(),
            );
        }
        self.validate_credentials()?;
        if self.role == Role::Solver {
            let n = self.image_sizes_px.len();
            if !(2..=irtrack_core::params::MAX_CAMERAS).contains(&n) {
                return bad(format!(
                    "cluster.image_sizes_px lists {n} cameras; a solver needs 2..={} cameras in all (its own and the camera boards')",
                    irtrack_core::params::MAX_CAMERAS
                ));
            }
            if self.image_sizes_px.iter().any(|[w, h]| *w == 0 || *h == 0) {
                return bad("cluster.image_sizes_px: every size must be non-zero".into());
            }
        }
        Ok(())
    }

    /// The credentials keys fit the role and the endpoints (the side that opens a link proves
    /// its password, so boards connect and the solver listens), and the files parse.
    fn validate_credentials(&self) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        match self.role {
            Role::Camera if self.credentials_file.is_some() => {
                return bad(
                    "cluster.credentials_file is the solver's dictionary; a camera board takes its own password_file"
                        .into(),
                );
            }
            Role::Solver if self.password_file.is_some() => {
                return bad(
                    "cluster.password_file is a camera board's; the solver takes credentials_file (the boards' dictionary)"
                        .into(),
                );
            }
            _ => {}
        }
        let authenticated = match self.role {
            Role::Camera => self.password_file.is_some(),
            Role::Solver => self.credentials_file.is_some(),
            Role::Standalone => false,
        };
        self.validate_tls(authenticated)?;
        if !authenticated {
            return Ok(());
        }
        let endpoints_ok = match self.role {
            Role::Camera => self.listen.is_empty() && !self.connect.is_empty(),
            _ => !self.listen.is_empty() && self.connect.is_empty(),
        };
        if !endpoints_ok || self.multicast_scouting {
            return bad(
                "cluster: with credentials, camera boards connect to the solver (connect = [...], no listen) and the solver listens (listen = [...], no connect), without multicast_scouting: Zenoh checks the password of the side that opens a link"
                    .into(),
            );
        }
        #[cfg(feature = "cluster")]
        {
            let auth = self.transport_auth()?;
            if let irtrack_cluster::transport::Auth::Solver { boards, .. } = &auth
                && self.own_cameras
                && boards.contains(&self.board)
            {
                return bad(format!(
                    "cluster.credentials_file lists {:?}, the solver's own board name: a remote peer could publish as its own cameras",
                    self.board
                ));
            }
        }
        Ok(())
    }

    /// The TLS keys fit the role, come with credentials, and (cluster builds) the files load.
    fn validate_tls(&self, authenticated: bool) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        let solver_keys = self.tls_certificate_file.is_some() || self.tls_key_file.is_some();
        let board_key = self.tls_solver_certificate_file.is_some();
        match self.role {
            Role::Camera if solver_keys => {
                return bad("cluster.tls_certificate_file and tls_key_file are the solver's; a camera board takes tls_solver_certificate_file (the solver's certificate it pins)".into());
            }
            Role::Solver if board_key => {
                return bad("cluster.tls_solver_certificate_file is a camera board's; the solver takes tls_certificate_file and tls_key_file".into());
            }
            Role::Solver if self.tls_certificate_file.is_some() != self.tls_key_file.is_some() => {
                return bad("cluster.tls_certificate_file and tls_key_file go together".into());
            }
            Role::Standalone if solver_keys || board_key => {
                return bad("cluster TLS keys need role = \"camera\" or \"solver\"".into());
            }
            _ => {}
        }
        if (solver_keys || board_key) && !authenticated {
            return bad("cluster TLS needs credentials too (password_file on a camera board, credentials_file on the solver): TLS proves the solver, the password each board".into());
        }
        #[cfg(feature = "cluster")]
        self.transport_tls()?;
        Ok(())
    }

    /// The TLS role of this node from its files (none when not configured); the files are
    /// loaded here so that a bad one is a start error naming it.
    #[cfg(feature = "cluster")]
    pub fn transport_tls(&self) -> Result<Option<irtrack_cluster::tls::TlsRole>> {
        use irtrack_cluster::tls::{TlsRole, client_config, server_config};
        let to_err = |e: irtrack_cluster::ClusterError| FirmwareError::Config {
            reason: e.to_string(),
        };
        Ok(
            match (
                self.role,
                &self.tls_certificate_file,
                &self.tls_key_file,
                &self.tls_solver_certificate_file,
            ) {
                (Role::Solver, Some(c), Some(k), _) => {
                    server_config(c, k).map_err(to_err)?;
                    Some(TlsRole::Solver {
                        certificate_file: c.clone(),
                        key_file: k.clone(),
                    })
                }
                (Role::Camera, _, _, Some(c)) => {
                    client_config(c).map_err(to_err)?;
                    Some(TlsRole::Board {
                        solver_certificate_file: c.clone(),
                    })
                }
                _ => None,
            },
        )
    }

    /// The Zenoh credentials of this role from its files (none when not configured).
    #[cfg(feature = "cluster")]
    pub fn transport_auth(&self) -> Result<irtrack_cluster::transport::Auth> {
        use irtrack_cluster::transport::Auth;
        let to_err = |e: irtrack_cluster::ClusterError| FirmwareError::Config {
            reason: e.to_string(),
        };
        let (auth, loose, file) = match (self.role, &self.password_file, &self.credentials_file) {
            (Role::Camera, Some(f), _) => {
                let (a, l) = Auth::board_from_file(&self.board, f).map_err(to_err)?;
                (a, l, f)
            }
            (Role::Solver, _, Some(f)) => {
                let (a, l) = Auth::solver_from_file(&self.rig, f).map_err(to_err)?;
                (a, l, f)
            }
            _ => return Ok(Auth::None),
        };
        if loose {
            tracing::warn!(
                file = %file.display(),
                "cluster credentials file is readable by group or others; chmod 600 it"
            );
        }
        Ok(auth)
    }

    /// One line on the transport's authentication for `--check-config` and the log; `None`
    /// standalone. Unauthenticated says so and what it means.
    pub fn auth_summary(&self) -> Option<String> {
        Some(match self.role {
            Role::Standalone => return None,
            Role::Camera => match &self.password_file {
                Some(f) => format!(
                    "cluster transport: authenticated as board {:?} (password file {}); {}",
                    self.board,
                    f.display(),
                    match &self.tls_solver_certificate_file {
                        Some(c) => format!(
                            "TLS: talks only to the solver that proves itself with {}, encrypted",
                            c.display()
                        ),
                        None => "no TLS: the solver is not checked and links are not encrypted".to_string(),
                    }
                ),
                None => UNAUTHENTICATED.to_string(),
            },
            Role::Solver => match &self.credentials_file {
                Some(f) => format!(
                    "cluster transport: only the boards in {} are accepted, each on its own key expressions; {}",
                    f.display(),
                    match &self.tls_certificate_file {
                        Some(c) => format!("TLS: proves itself with {}, encrypted", c.display()),
                        None =>
                            "no TLS: boards cannot check the solver and links are not encrypted".to_string(),
                    }
                ),
                None => UNAUTHENTICATED.to_string(),
            },
        })
    }

    /// Frame period at `fps`, ns.
    pub fn period_ns(&self) -> u64 {
        (1e9 / self.fps) as u64
    }

    fn ms_ns(ms: f64) -> u64 {
        (ms * 1e6) as u64
    }

    /// Solver: timestamp tolerance (ns); `tolerance_ms`, else half a frame period.
    pub fn tolerance_ns(&self) -> u64 {
        self.tolerance_ms.map_or(self.period_ns() / 2, Self::ms_ns)
    }

    /// Solver: how long after its first observation a set closes (ns); `set_deadline_ms`,
    /// else two frame periods.
    pub fn set_deadline_ns(&self) -> u64 {
        self.set_deadline_ms.map_or(2 * self.period_ns(), Self::ms_ns)
    }

    /// Solver: largest clock offset a board may have before it is faulted (ns);
    /// `max_clock_offset_ms`, else the tolerance.
    pub fn max_clock_offset_ns(&self) -> u64 {
        self.max_clock_offset_ms.map_or(self.tolerance_ns(), Self::ms_ns)
    }
}

/// What `--check-config` and the log say of a cluster without credentials.
pub const UNAUTHENTICATED: &str = "cluster transport: UNAUTHENTICATED - any host that reaches the Zenoh port can publish observations as any board and steer the robot; set [cluster] password_file on the boards and credentials_file on the solver (host-tools cluster-keys, docs/cluster.md \"Credentials\")";

/// Shared cluster state (camera and solver roles); `None` standalone.
pub type SharedReport = std::sync::Arc<std::sync::Mutex<ClusterReport>>;

/// The cluster state for `/status`, when the role is not standalone.
pub fn new_report(cfg: &ClusterConfig) -> Option<SharedReport> {
    (cfg.role != Role::Standalone)
        .then(|| std::sync::Arc::new(std::sync::Mutex::new(ClusterReport::default())))
}

/// Shows `report` in `/status` and on the set-up page.
pub fn register(status: &crate::status::SharedStatus, report: &Option<SharedReport>) {
    if let (Some(r), Ok(mut g)) = (report, status.cluster.lock()) {
        *g = Some(r.clone());
    }
}

/// The parameter port's handler of pushed credential envelopes for a camera board or solver
/// (`keys::Inbox`; its key pair is made at the first start). `in_use`: the running credentials
/// came from an earlier push.
#[cfg(feature = "cluster")]
pub fn credential_inbox(
    cfg: &ClusterConfig,
    state_dir: &std::path::Path,
    report: &Option<SharedReport>,
    in_use: bool,
) -> Result<Option<std::sync::Arc<dyn crate::params::CredentialInbox>>> {
    let Some(report) = report else { return Ok(None) };
    let inbox = keys::Inbox::open(cfg, state_dir, report.clone(), in_use)?;
    Ok(Some(
        std::sync::Arc::new(inbox) as std::sync::Arc<dyn crate::params::CredentialInbox>
    ))
}

/// Without the `cluster` feature no credentials are taken.
#[cfg(not(feature = "cluster"))]
pub fn credential_inbox(
    _cfg: &ClusterConfig,
    _state_dir: &std::path::Path,
    _report: &Option<SharedReport>,
    _in_use: bool,
) -> Result<Option<std::sync::Arc<dyn crate::params::CredentialInbox>>> {
    Ok(None)
}

/// Without the `cluster` feature there are no pushed credentials to adopt.
#[cfg(not(feature = "cluster"))]
impl ClusterConfig {
    /// Always `None` without the `cluster` feature.
    pub fn adopt_pushed_credentials(&mut self, _state_dir: &std::path::Path) -> Option<std::path::PathBuf> {
        None
    }
}

/// Runs a blocking Zenoh call on a plain thread: Zenoh's blocking API must not run on a
/// tokio worker (irtrackd's start is async).
#[cfg(feature = "cluster")]
fn off_runtime<T: Send>(f: impl FnOnce() -> Result<T> + Send) -> Result<T> {
    std::thread::scope(|s| {
        s.spawn(f).join().unwrap_or_else(|_| {
            Err(FirmwareError::Thread {
                what: "zenoh session",
                reason: "panicked while opening".into(),
            })
        })
    })
}

/// Solver role: the frame source made of the camera boards.
#[cfg(feature = "cluster")]
pub fn solver_source(
    cfg: &ClusterConfig,
    params: std::sync::Arc<crate::engine::ParamsHandle>,
    report: SharedReport,
    own: Option<(
        Box<dyn crate::source::FrameSource>,
        irtrack_core::pipeline::TrackerConfig,
    )>,
) -> Result<Box<dyn crate::source::FrameSource>> {
    off_runtime(|| {
        Ok(Box::new(solver::ClusterSource::new(cfg, params, report, own)?)
            as Box<dyn crate::source::FrameSource>)
    })
}

/// Solver role without the `cluster` feature: an error saying irtrackd must be built with it.
#[cfg(not(feature = "cluster"))]
pub fn solver_source(
    _cfg: &ClusterConfig,
    _params: std::sync::Arc<crate::engine::ParamsHandle>,
    _report: SharedReport,
    _own: Option<(
        Box<dyn crate::source::FrameSource>,
        irtrack_core::pipeline::TrackerConfig,
    )>,
) -> Result<Box<dyn crate::source::FrameSource>> {
    Err(FirmwareError::Config {
        reason: "cluster.role = \"solver\" needs irtrackd built with the `cluster` feature".into(),
    })
}

/// The loop's part of the role: a camera board publishes every camera's blobs; a solver
/// refuses sets whose observations are further apart than the pairing tolerance.
#[cfg(feature = "cluster")]
pub fn with_role(
    engine: crate::engine::Engine,
    cfg: &ClusterConfig,
    report: &Option<SharedReport>,
) -> Result<crate::engine::Engine> {
    let Some(report) = report else { return Ok(engine) };
    Ok(match cfg.role {
        Role::Camera => {
            let cameras = engine.source().camera_count();
            let r = report.clone();
            let sink = off_runtime(|| {
                Ok(Box::new(camera::CameraPublisher::new(cfg, cameras, r)?)
                    as Box<dyn crate::engine::ObservationSink>)
            })?;
            // A board without a parameter set of its own (one camera needs none) still
            // detects and publishes.
            engine.with_detection_only()?.with_observation_sink(sink)
        }
        Role::Solver => engine.with_max_pairing_error(std::time::Duration::from_nanos(cfg.tolerance_ns())),
        Role::Standalone => engine,
    })
}

/// Without the `cluster` feature the loop is returned unchanged.
#[cfg(not(feature = "cluster"))]
pub fn with_role(
    engine: crate::engine::Engine,
    _cfg: &ClusterConfig,
    _report: &Option<SharedReport>,
) -> Result<crate::engine::Engine> {
    Ok(engine)
}
