//! irtrackd configuration: a TOML file (every table rejects unknown keys), defaults for a PC
//! run with the simulated source, and validation with messages that name the offending key.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use irtrack_core::params::RigParams;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::timing::{CameraTiming, Shutter};

use crate::error::{FirmwareError, Result};
use crate::leds::gpio::GpioLedConfig;
use crate::source::replay::ReplayConfig;
use crate::source::sim::SimSourceConfig;
use crate::source::v4l2::V4l2Config;
use irtrack_robot::RobotConfig;

/// Default location of the config file on the board.
pub const DEFAULT_CONFIG_PATH: &str = "/etc/irtrack/irtrackd.toml";

/// Whole config file.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// `[service]`: state directory, robot control, operator password.
    #[serde(default)]
    pub service: ServiceConfig,
    /// `[listen]`: the addresses of the service's ports.
    #[serde(default)]
    pub listen: ListenConfig,
    /// Who may view the status port's live data, and the names it answers to.
    #[serde(default)]
    pub status: StatusConfig,
    /// Who may push parameter sets.
    #[serde(default)]
    pub params: ParamsConfig,
    /// `[source]`: which frame source runs, with its settings.
    #[serde(default)]
    pub source: SourceConfig,
    /// Blob detector and quality gate (irtrack-core's `TrackerConfig`; unknown keys rejected).
    #[serde(default)]
    pub tracking: TrackerConfig,
    /// 6-DOF tracker settings, used when the parameter set defines a tool (irtrack-core's
    /// `PoseConfig`; unknown keys rejected).
    #[serde(default)]
    pub pose: irtrack_core::pose6d::PoseConfig,
    /// `[leds]`: the status LED driver.
    #[serde(default)]
    pub leds: LedsConfig,
    /// `[realtime]`: scheduling, CPU affinity and deadline of the processing thread.
    #[serde(default)]
    pub realtime: RealtimeConfig,
    /// Robot link; absent means no robot client runs.
    #[serde(default)]
    pub robot: Option<RobotConfig>,
    /// Standard outputs (NatNet, ...), all off by default (docs/outputs.md).
    #[serde(default)]
    pub outputs: crate::outputs::OutputsConfig,
    /// Multi-board rigs (docs/cluster.md); standalone by default.
    #[serde(default)]
    pub cluster: crate::cluster::ClusterConfig,
    /// PTP for the boards' clocks (linuxptp; docs/cluster.md, "Clocks"); off by default.
    #[serde(default)]
    pub clock: crate::ptp::ClockConfig,
    /// `[[camera_timing]]`: per-camera shutter, line time, exposure and time offset of the
    /// cameras (V4L2), used while the parameter set carries no calibrated timing
    /// ([`effective_timing`], docs/timing.md "Camera timing settings"). Unlisted cameras keep
    /// the default (global shutter, timestamps are exposure instants).
    #[serde(default)]
    pub camera_timing: Vec<CameraTimingConfig>,
    /// `[update]`: which system updater irtrackd reports and installs with (docs/updates.md).
    #[serde(default)]
    pub update: crate::update::UpdateConfig,
}

/// `[service]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceConfig {
    /// Where parameter sets are stored (systemd's StateDirectory).
    #[serde(default = "default_state_dir")]
    pub state_dir: PathBuf,
    /// Simulated source only: use the simulator's own rig as the parameter set when none is
    /// stored (demo convenience; off by default so the no-parameters fault stays visible).
    #[serde(default)]
    pub params_from_simulator: bool,
    /// Accept robot control requests (`POST /robot/...`) on the status port. Whoever can reach
    /// that port can then enable motion, so it is off by default (docs/security.md).
    #[serde(default)]
    pub control: bool,
    /// Argon2id PHC string of the operator password (`irtrackd --hash-password`). Every
    /// change request on the status port (tuning, save, robot control) needs a sign-in with
    /// it; without it they are all refused (docs/security.md).
    #[serde(default)]
    pub operator_password_hash: Option<String>,
}

fn default_state_dir() -> PathBuf {
    // systemd sets STATE_DIRECTORY for StateDirectory=; fall back to the FHS path.
    std::env::var_os("STATE_DIRECTORY")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/var/lib/irtrackd"))
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            state_dir: default_state_dir(),
            params_from_simulator: false,
            control: false,
            operator_password_hash: None,
        }
    }
}

/// `[status]`: viewing and naming rules of the status port (docs/security.md).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StatusConfig {
    /// Previews, frame sets and positions without sign-in (default). `false`: only to a
    /// signed-in operator.
    #[serde(default = "default_true")]
    pub public_view: bool,
    /// Host names (DNS or mDNS names) the board is reached by, besides its addresses and its
    /// own host name; requests naming any other host are refused (DNS rebinding).
    #[serde(default)]
    pub allowed_hosts: Vec<String>,
}

fn default_true() -> bool {
    true
}

impl Default for StatusConfig {
    fn default() -> Self {
        Self {
            public_view: true,
            allowed_hosts: Vec::new(),
        }
    }
}

/// `[params]`: who may push parameter sets. By default nothing is trusted, so a board fresh out
/// of the box rejects every push until a public key is installed (docs/security.md).
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct ParamsConfig {
    /// Public key files written by `host-tools keygen` (`NAME.pub`), or directories whose
    /// `*.pub` files are all trusted. Blobs signed by one of these keys are accepted.
    #[serde(default)]
    pub trusted_keys: Vec<PathBuf>,
    /// Development mode: also accept unsigned blobs. Shown in the status as
    /// `params.signature_policy = "allow_unsigned"` and logged as a warning at start.
    #[serde(default)]
    pub allow_unsigned: bool,
    /// Days after which the status and the set-up page say the calibration should be checked
    /// (default 180, `calibration::DEFAULT_MAX_AGE_DAYS`).
    #[serde(default)]
    pub calibration_max_age_days: Option<f64>,
}

impl ParamsConfig {
    /// The signature policy these settings ask for.
    pub fn policy(&self) -> irtrack_core::signing::SignaturePolicy {
        if self.allow_unsigned {
            irtrack_core::signing::SignaturePolicy::AllowUnsigned
        } else {
            irtrack_core::signing::SignaturePolicy::RequireSigned
        }
    }

    /// Reads every trusted key; a missing or malformed key file is an error naming the file
    /// (a typo must not silently leave the board unable to accept, or worse, mis-trusting).
    pub fn load_keys(&self) -> Result<Vec<irtrack_core::signing::VerifyingKey>> {
        let mut files = Vec::new();
        for path in &self.trusted_keys {
            let bad = |reason: String| FirmwareError::Config {
                reason: format!("params.trusted_keys: {}: {reason}", path.display()),
            };
            if path.is_dir() {
                let entries = std::fs::read_dir(path).map_err(|e| bad(format!("cannot list: {e}")))?;
                let mut found: Vec<PathBuf> = entries
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|x| x == "pub"))
                    .collect();
                found.sort();
                files.extend(found);
            } else {
                files.push(path.clone());
            }
        }
        let mut keys = Vec::with_capacity(files.len());
        for file in files {
            let text = std::fs::read_to_string(&file).map_err(|e| FirmwareError::Config {
                reason: format!("params.trusted_keys: cannot read {}: {e}", file.display()),
            })?;
            let key =
                irtrack_core::signing::parse_public_key_file(&text).map_err(|e| FirmwareError::Config {
                    reason: format!("params.trusted_keys: {}: {e}", file.display()),
                })?;
            if !keys.contains(&key) {
                keys.push(key);
            }
        }
        Ok(keys)
    }
}

/// `[listen]`: socket addresses (`host:port`; port 0 picks a free port).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ListenConfig {
    /// Parameter push port (`host:port`).
    #[serde(default = "default_params_addr")]
    pub params: String,
    /// Position stream port, one JSON record per line.
    #[serde(default = "default_ndjson_addr")]
    pub stream_ndjson: String,
    /// Position stream port, binary framing (irtrack-core's `stream`).
    #[serde(default = "default_binary_addr")]
    pub stream_binary: String,
    /// Status port: `/status`, `/metrics`, the set-up view and its API.
    #[serde(default = "default_status_addr")]
    pub status: String,
    /// Records queued per stream client before it counts as too slow and is dropped.
    #[serde(default = "default_client_queue")]
    pub client_queue_records: usize,
    /// Stream clients (both formats together) served at once; further connections are closed
    /// at once and counted, so a flood of connections cannot exhaust memory or descriptors.
    #[serde(default = "default_max_stream_clients")]
    pub max_stream_clients: u64,
}

fn default_params_addr() -> String {
    "0.0.0.0:7701".into()
}
fn default_ndjson_addr() -> String {
    "0.0.0.0:7702".into()
}
fn default_binary_addr() -> String {
    "0.0.0.0:7703".into()
}
fn default_status_addr() -> String {
    "0.0.0.0:7704".into()
}
fn default_client_queue() -> usize {
    256
}
fn default_max_stream_clients() -> u64 {
    32
}

impl Default for ListenConfig {
    fn default() -> Self {
        Self {
            params: default_params_addr(),
            stream_ndjson: default_ndjson_addr(),
            stream_binary: default_binary_addr(),
            status: default_status_addr(),
            client_queue_records: default_client_queue(),
            max_stream_clients: default_max_stream_clients(),
        }
    }
}

/// Which frame source runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum SourceKind {
    /// Simulated cameras rendering a scene (`[source.sim]`).
    #[default]
    Sim,
    /// A recorded directory of PGM frames (`[source.replay]`).
    Replay,
    /// Two or more V4L2 cameras (`[source.v4l2]`).
    V4l2,
}

/// `[source]` with one optional sub-table per kind.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SourceConfig {
    /// Which of the tables below is used.
    #[serde(default)]
    pub kind: SourceKind,
    /// Largest capture-time difference (µs) between the cameras of one set that still gives a
    /// position; default half the loop's deadline (the frame period unless configured).
    #[serde(default)]
    pub max_pairing_error_us: Option<u64>,
    /// `[source.sim]`, used with `kind = "sim"`.
    #[serde(default)]
    pub sim: Option<SimSourceConfig>,
    /// `[source.replay]`, needed with `kind = "replay"`.
    #[serde(default)]
    pub replay: Option<ReplayConfig>,
    /// `[source.v4l2]`, needed with `kind = "v4l2"`.
    #[serde(default)]
    pub v4l2: Option<V4l2Config>,
}

/// LED back end.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LedBackend {
    /// Log changes (PC runs, tests).
    #[default]
    Sim,
    /// gpiocdev lines from `[leds.gpio]`.
    Gpio,
    /// rppal pins from `[leds.rppal]` (Raspberry Pi; needs the `rpi` cargo feature).
    Rppal,
    /// No LEDs at all.
    None,
}

/// `[leds]`
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct LedsConfig {
    /// Which LED driver runs.
    #[serde(default)]
    pub backend: LedBackend,
    /// `[leds.gpio]`, needed with `backend = "gpio"`.
    #[serde(default)]
    pub gpio: Option<GpioLedConfig>,
    /// `[leds.rppal]`, needed with `backend = "rppal"`.
    #[cfg(feature = "rpi")]
    #[serde(default)]
    pub rppal: Option<crate::leds::rppal::RppalLedConfig>,
}

/// `[realtime]`: applied to the processing thread when permitted.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct RealtimeConfig {
    /// SCHED_FIFO priority 1..=99 (needs CAP_SYS_NICE or LimitRTPRIO).
    #[serde(default)]
    pub fifo_priority: Option<i32>,
    /// CPUs the processing thread may run on.
    #[serde(default)]
    pub cpu_affinity: Option<Vec<usize>>,
    /// Lock all memory (mlockall) so page faults cannot stall the loop (needs CAP_IPC_LOCK or
    /// LimitMEMLOCK).
    #[serde(default)]
    pub lock_memory: bool,
    /// Processing deadline per frame set, ms; default: the source's frame period.
    #[serde(default)]
    pub deadline_ms: Option<f64>,
}

impl Config {
    /// Parses TOML text (`origin` names it in errors) and validates.
    pub fn from_toml(text: &str, origin: &str) -> Result<Config> {
        let cfg: Config = toml::from_str(text).map_err(|e| FirmwareError::ConfigFile {
            path: origin.to_string(),
            reason: e.to_string(),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads, parses and validates a config file.
    pub fn load(path: &Path) -> Result<Config> {
        let text = std::fs::read_to_string(path).map_err(|e| FirmwareError::ConfigFile {
            path: path.display().to_string(),
            reason: format!("cannot read: {e}"),
        })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// Cross-field checks that serde cannot express. Returns the file's "kind + tables"
    /// choices resolved into typed sections ([`Resolved`]): the only place they are matched.
    pub fn validate(&self) -> Result<Resolved> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        for (key, addr) in [
            ("listen.params", &self.listen.params),
            ("listen.stream_ndjson", &self.listen.stream_ndjson),
            ("listen.stream_binary", &self.listen.stream_binary),
            ("listen.status", &self.listen.status),
        ] {
            if addr.parse::<std::net::SocketAddr>().is_err() {
                return bad(format!("{key} = {addr:?} is not an IP:port socket address"));
            }
        }
        if self.listen.client_queue_records == 0 {
            return bad("listen.client_queue_records must be at least 1".into());
        }
        if self.listen.max_stream_clients == 0 {
            return bad("listen.max_stream_clients must be at least 1".into());
        }
        if self.source.max_pairing_error_us == Some(0) {
            return bad("source.max_pairing_error_us must be > 0".into());
        }
        if let Some(d) = self.params.calibration_max_age_days
            && !(d.is_finite() && d > 0.0)
        {
            return bad(format!(
                "params.calibration_max_age_days = {d} must be a positive number of days"
            ));
        }
        check_tracker_config(&self.tracking)?;
        self.update.validate()?;
        self.outputs.validate()?;
        self.cluster.validate()?;
        self.clock.validate()?;
        if let Some(h) = &self.service.operator_password_hash {
            crate::net::auth::check_hash(h)?;
        }
        self.pose.validate().map_err(|e| FirmwareError::Config {
            reason: format!("[pose]: {e}"),
        })?;
        if let Some(d) = self.realtime.deadline_ms
            && !(d.is_finite() && d > 0.0)
        {
            return bad(format!("realtime.deadline_ms must be > 0, got {d}"));
        }
        let source = self.source.resolve()?;
        self.check_camera_count(&source)?;
        self.check_camera_timing(&source)?;
        if self.service.params_from_simulator && !matches!(source, Source::Sim(_)) {
            return bad("service.params_from_simulator only works with source.kind = \"sim\"".into());
        }
        let leds = self.leds.resolve()?;
        if let Some(robot) = &self.robot {
            robot.validate().map_err(|e| FirmwareError::Config {
                reason: e.to_string(),
            })?;
        }
        if let Some(p) = self.realtime.fifo_priority
            && !(1..=99).contains(&p)
        {
            return bad(format!("realtime.fifo_priority must be 1..=99, got {p}"));
        }
        Ok(Resolved { source, leds })
    }
}

impl Config {
    /// Each `[[camera_timing]]` names a camera once (one the source has, when it is known)
    /// and gives timing a sensor can have, in µs.
    fn check_camera_timing(&self, source: &Source) -> Result<()> {
        let local = match source {
            Source::V4l2(v) => Some(v.devices.len()),
            Source::Sim(_) | Source::Replay(_) => None,
        };
        for (k, t) in self.camera_timing.iter().enumerate() {
            let bad = |reason: String| FirmwareError::Config {
                reason: format!("camera_timing[{k}] (camera {}): {reason}", t.camera),
            };
            if self.camera_timing[..k].iter().any(|o| o.camera == t.camera) {
                return Err(bad("the camera is listed twice".into()));
            }
            if let Some(n) = local
                && t.camera >= n
            {
                return Err(bad(format!(
                    "[source] has {n} cameras (0..={}); timing is per camera of this board",
                    n.saturating_sub(1)
                )));
            }
            t.to_timing(None).map_err(bad)?;
        }
        Ok(())
    }

    /// Triangulation needs two cameras: a standalone board needs two of its own, a camera
    /// board one (the solver has the others), a solver two in all (`image_sizes_px`).
    fn check_camera_count(&self, source: &Source) -> Result<()> {
        use crate::cluster::Role;
        let local = match source {
            Source::Sim(s) => Some(match (&s.cameras, s.rig) {
                (Some(c), _) => c.len(),
                (None, crate::source::sim::SimRig::Ring) => s.ring_cameras,
                (None, _) => 2,
            }),
            Source::V4l2(v) => Some(v.devices.len()),
            // A recording's camera count is known once it is opened.
            Source::Replay(_) => None,
        };
        let Some(n) = local else { return Ok(()) };
        if self.cluster.role == Role::Standalone && n < 2 {
            return Err(FirmwareError::Config {
                reason: format!(
                    "[source] gives {n} camera; a standalone board needs at least 2 to triangulate. \
                     A board with one camera runs as a camera board ([cluster] role = \"camera\") \
                     feeding a solver (docs/cluster.md)"
                ),
            });
        }
        if self.cluster.role == Role::Solver
            && self.cluster.own_cameras
            && n > self.cluster.image_sizes_px.len()
        {
            return Err(FirmwareError::Config {
                reason: format!(
                    "cluster.image_sizes_px lists {} cameras but the solver's own [source] has {n}: \
                     image_sizes_px lists every camera of the rig, the solver's own and the boards'",
                    self.cluster.image_sizes_px.len()
                ),
            });
        }
        Ok(())
    }
}

/// What [`Config::validate`] resolves: each "`kind` + one optional table per kind" choice of
/// the file as one typed value, so later code never matches on the kind again.
#[derive(Debug, Clone, PartialEq)]
pub struct Resolved {
    /// The frame source to open.
    pub source: Source,
    /// The LED driver to start.
    pub leds: Leds,
}

/// `[source]` after validation: the kind with its own, checked settings.
#[derive(Debug, Clone, PartialEq)]
// Resolved once at start-up and matched, never stored in bulk: boxing the simulator's config
// (which grew with `[source.sim.timing]`) would only cost every caller a `Box`.
#[allow(clippy::large_enum_variant)]
pub enum Source {
    /// `[source.sim]` (defaults when the table is absent).
    Sim(SimSourceConfig),
    /// `[source.replay]`, checked.
    Replay(ReplayConfig),
    /// `[source.v4l2]`, checked (at least two cameras).
    V4l2(V4l2Config),
}

impl Source {
    /// The source's nominal frame rate, when it has one.
    pub fn nominal_fps(&self) -> Option<f64> {
        match self {
            Source::Sim(s) => Some(s.fps),
            Source::Replay(r) => r.fps,
            Source::V4l2(v) => Some(f64::from(v.fps)),
        }
    }
}

impl SourceConfig {
    /// Checks the table `kind` names and returns it typed.
    pub fn resolve(&self) -> Result<Source> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        Ok(match self.kind {
            SourceKind::Sim => {
                let sim = self.sim.clone().unwrap_or_default();
                if self.sim.is_some() {
                    sim.validate()?;
                }
                Source::Sim(sim)
            }
            SourceKind::Replay => match &self.replay {
                None => {
                    return bad("source.kind = \"replay\" needs a [source.replay] table with `dir`".into());
                }
                Some(r) => {
                    if r.fps.is_some_and(|f| !(f.is_finite() && f > 0.0)) {
                        return bad("source.replay.fps must be > 0".into());
                    }
                    Source::Replay(r.clone())
                }
            },
            SourceKind::V4l2 => match &self.v4l2 {
                None => return bad("source.kind = \"v4l2\" needs a [source.v4l2] table".into()),
                Some(v) if v.devices.is_empty() => {
                    return bad("source.v4l2.devices lists no camera".into());
                }
                Some(v) => {
                    v.validate().map_err(|e| FirmwareError::Config {
                        reason: format!("[source.v4l2]: {e}"),
                    })?;
                    Source::V4l2(v.clone())
                }
            },
        })
    }
}

/// `[leds]` after validation: the back end with its own settings.
#[derive(Debug, Clone, PartialEq)]
pub enum Leds {
    /// LED changes are logged only.
    Sim,
    /// No LED driver.
    None,
    /// GPIO lines through the character device.
    Gpio(GpioLedConfig),
    /// Raspberry Pi pins through rppal.
    #[cfg(feature = "rpi")]
    Rppal(crate::leds::rppal::RppalLedConfig),
}

impl LedsConfig {
    /// Checks the table `backend` names and returns it typed.
    pub fn resolve(&self) -> Result<Leds> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        Ok(match self.backend {
            LedBackend::Sim => Leds::Sim,
            LedBackend::None => Leds::None,
            LedBackend::Gpio => match &self.gpio {
                Some(g) => Leds::Gpio(g.clone()),
                None => return bad("leds.backend = \"gpio\" needs a [leds.gpio] table".into()),
            },
            #[cfg(feature = "rpi")]
            LedBackend::Rppal => match &self.rppal {
                Some(r) => Leds::Rppal(r.clone()),
                None => return bad("leds.backend = \"rppal\" needs a [leds.rppal] table".into()),
            },
            #[cfg(not(feature = "rpi"))]
            LedBackend::Rppal => {
                return bad("leds.backend = \"rppal\" needs irtrackd built with the `rpi` feature".into());
            }
        })
    }
}

/// Lets irtrack-core check the `[tracking]` values by building a tracker for a tiny dummy rig
/// (the core keeps its validation private; this way `--check-config` catches bad values).
fn check_tracker_config(cfg: &TrackerConfig) -> Result<()> {
    use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
    use irtrack_core::params::CameraParams;
    let model = CameraModel {
        intrinsics: Intrinsics {
            fx_px: 100.0,
            fy_px: 100.0,
            cx_px: 31.5,
            cy_px: 23.5,
        },
        distortion: Distortion::NONE,
        image_size: ImageSize {
            width_px: 64,
            height_px: 48,
        },
    };
    let shifted = RigidTransform {
        t_mm: [-100.0, 0.0, 0.0],
        ..RigidTransform::IDENTITY
    };
    let rig = RigParams {
        rig_id: "config-check".into(),
        created_unix_s: 0,
        cameras: vec![
            CameraParams {
                model,
                cam_from_cam0: RigidTransform::IDENTITY,
            },
            CameraParams {
                model,
                cam_from_cam0: shifted,
            },
        ],
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    };
    irtrack_core::pipeline::Tracker::new(&rig, *cfg)
        .map(|_| ())
        .map_err(|e| FirmwareError::Config {
            reason: format!("[tracking]: {e}"),
        })
}

/// One `[[camera_timing]]` table: a camera's timing as an operator writes it (µs; docs/timing.md,
/// "Camera timing settings").
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraTimingConfig {
    /// The camera (index in `[source]`, camera 0 first).
    pub camera: usize,
    /// `"global"` (default) or `"rolling"`.
    #[serde(default)]
    pub shutter: Shutter,
    /// Rolling shutter: time from one row's exposure start to the next row's, µs (the sensor's
    /// row time: HTS / pixel clock). Needed for `"rolling"`.
    #[serde(default)]
    pub line_time_us: f64,
    /// Exposure time, µs (informative); default `[source.v4l2] exposure_us` when set.
    #[serde(default)]
    pub exposure_us: Option<f64>,
    /// Middle of row 0's exposure minus the frame's timestamp, µs (signed; e.g. negative for
    /// a driver that stamps the end of the frame).
    #[serde(default)]
    pub offset_us: f64,
}

impl CameraTimingConfig {
    /// The timing in ns; `default_exposure_us` fills a missing `exposure_us`. Errors name the
    /// key: values must be finite, line and exposure times ≥ 0, and pass
    /// `CameraTiming::validate` (a rolling shutter needs a line time; no unit mistakes).
    pub fn to_timing(&self, default_exposure_us: Option<u32>) -> std::result::Result<CameraTiming, String> {
        // ±1 s bounds every value validate accepts, so the conversions below cannot overflow.
        let ns = |key: &str, us: f64, signed: bool| -> std::result::Result<f64, String> {
            if !us.is_finite() || (!signed && us < 0.0) || us.abs() > 1.0e6 {
                return Err(format!(
                    "{key} = {us} must be a finite number of µs{} within one second",
                    if signed { "" } else { " ≥ 0" }
                ));
            }
            Ok((us * 1000.0).round())
        };
        let exposure_us = self
            .exposure_us
            .or_else(|| default_exposure_us.map(f64::from))
            .unwrap_or(0.0);
        let timing = CameraTiming {
            shutter: self.shutter,
            line_time_ns: ns("line_time_us", self.line_time_us, false)? as u32,
            exposure_ns: ns("exposure_us", exposure_us, false)? as u32,
            offset_ns: ns("offset_us", self.offset_us, true)? as i64,
        };
        timing.validate().map_err(|e| {
            // The core speaks ns; the config is written in µs.
            format!("{e} (config values are in µs: line_time_us, exposure_us, offset_us)")
        })?;
        Ok(timing)
    }
}

/// Where each camera's timing comes from (docs/timing.md, "Camera timing settings").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimingOrigin {
    /// The parameter set carries timing (calibrated by `host-tools wand-calibrate` or set with
    /// `convert-params --timing`): it wins over the config.
    ParameterSet,
    /// The config's `[[camera_timing]]` tables.
    Config,
    /// Neither: every camera global shutter, timestamps taken as exposure instants.
    Default,
}

impl TimingOrigin {
    /// In words, for logs and status.
    pub fn as_str(self) -> &'static str {
        match self {
            TimingOrigin::ParameterSet => "parameter set",
            TimingOrigin::Config => "config",
            TimingOrigin::Default => "default",
        }
    }
}

/// Each of `rig`'s cameras' timing, as the loop should use it: the parameter set's when it
/// carries timing (calibrated values win), else the config's `[[camera_timing]]` (cameras it
/// does not list, and any it cannot convert, get the default), else the default. One entry
/// per camera of `rig`.
pub fn effective_timing(config: &Config, rig: &RigParams) -> Vec<CameraTiming> {
    effective_timing_with_origin(config, rig).0
}

/// [`effective_timing`] and where it came from.
pub fn effective_timing_with_origin(config: &Config, rig: &RigParams) -> (Vec<CameraTiming>, TimingOrigin) {
    let n = rig.camera_count();
    if rig.has_timing() {
        return (
            (0..n).map(|i| rig.camera_timing(i)).collect(),
            TimingOrigin::ParameterSet,
        );
    }
    if config.camera_timing.is_empty() {
        return (vec![CameraTiming::default(); n], TimingOrigin::Default);
    }
    let exposure = config.source.v4l2.as_ref().and_then(|v| v.exposure_us);
    let timing = (0..n)
        .map(|i| {
            config
                .camera_timing
                .iter()
                .find(|t| t.camera == i)
                // `Config::validate` already refused what does not convert.
                .and_then(|t| t.to_timing(exposure).ok())
                .unwrap_or_default()
        })
        .collect();
    (timing, TimingOrigin::Config)
}
