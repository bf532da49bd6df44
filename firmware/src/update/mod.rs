//! The system irtrackd runs on and its field updates (docs/updates.md).
//!
//! [`SystemUpdater`] is the narrow seam between irtrackd and the board's update tool: what the
//! slots hold, the last update's outcome, and installing one bundle. [`RaucUpdater`] talks to
//! RAUC through its command line (`rauc status`, `rauc install`) and the `last-update` file
//! its handlers write; [`SimUpdater`] is its twin for a PC or simulator run: two slots in a
//! directory, the same bundle checks made with `openssl cms` and `unsquashfs`, nothing flashed.
//!
//! [`Updates`] is what the status listener holds: it caches the slot report (asking RAUC costs
//! a process and a D-Bus round trip, `/status` is polled every second), tracks the one upload
//! or install that may run at a time, and runs every install on a thread of its own, so the
//! processing loop and the listener never wait for it.

mod bundle;
mod rauc;
mod sim;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

pub use bundle::{BundleLayout, inspect as inspect_bundle};
pub use rauc::{RaucUpdater, parse_progress_line, parse_rauc_status};
pub use sim::SimUpdater;

use crate::error::{FirmwareError, Result};

/// Which updater irtrackd uses (`[update] backend`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum UpdateBackend {
    /// RAUC when `rauc` is on PATH and its system.conf exists, else none.
    #[default]
    Auto,
    /// RAUC's command line.
    Rauc,
    /// Two slots in a directory (PC, simulator): checks bundles, writes no flash.
    Simulated,
    /// No updates: `/status` says so and uploads are refused.
    None,
}

/// `[update]` (docs/updates.md, "irtrackd and updates").
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UpdateConfig {
    /// The updater (default `auto`).
    #[serde(default)]
    pub backend: UpdateBackend,
    /// Largest bundle an upload may send, MiB.
    #[serde(default = "default_max_bundle_mib")]
    pub max_bundle_mib: u64,
    /// Where an uploaded bundle is written (default: `/data` with RAUC, the simulated
    /// system's directory otherwise). Must have room for one bundle.
    #[serde(default)]
    pub upload_dir: Option<PathBuf>,
    /// RAUC's system configuration (its presence selects RAUC under `auto`).
    #[serde(default = "default_system_conf")]
    pub system_conf: PathBuf,
    /// The program run as `rauc` (tests point it elsewhere).
    #[serde(default = "default_rauc")]
    pub rauc_command: PathBuf,
    /// The spool of the image's root agent (`irtrack-update-agent`): when irtrackd runs
    /// unprivileged and this directory exists, RAUC is run through the agent (RAUC's D-Bus
    /// API is root's only, and RAUC refuses a bundle owned by another user).
    #[serde(default = "default_agent_dir")]
    pub rauc_agent_dir: PathBuf,
    /// `key=value` outcome of the last update, written by the RAUC handlers and irtrackd.
    #[serde(default = "default_last_update")]
    pub last_update_file: PathBuf,
    /// The running release (`VERSION=`, `BUILD=`), written by the image build.
    #[serde(default = "default_release")]
    pub release_file: PathBuf,
    /// Simulated: the CA certificate bundles must be signed under (RAUC's keyring).
    #[serde(default = "default_ca")]
    pub ca_cert: PathBuf,
    /// Simulated: the board type bundles must name.
    #[serde(default = "default_compatible")]
    pub compatible: String,
    /// Simulated: the directory with the slots (default `<state_dir>/simulated-system`).
    #[serde(default)]
    pub sim_dir: Option<PathBuf>,
    /// Simulated: the version slot A starts with (default this irtrackd's version).
    #[serde(default = "default_version")]
    pub running_version: String,
    /// What reboots the board after an install with `reboot=1` when irtrackd runs RAUC itself
    /// (as root, without the root agent; the agent reboots on its own).
    #[serde(default = "default_reboot_command")]
    pub reboot_command: PathBuf,
}

fn default_max_bundle_mib() -> u64 {
    160
}
fn default_system_conf() -> PathBuf {
    PathBuf::from("/etc/rauc/system.conf")
}
fn default_rauc() -> PathBuf {
    PathBuf::from("rauc")
}
fn default_agent_dir() -> PathBuf {
    PathBuf::from("/data/rauc/spool")
}
fn default_last_update() -> PathBuf {
    PathBuf::from("/data/rauc/last-update")
}
fn default_release() -> PathBuf {
    PathBuf::from("/etc/irtrack/release")
}
fn default_ca() -> PathBuf {
    PathBuf::from("/etc/rauc/ca.cert.pem")
}
fn default_compatible() -> String {
    "irtrack-qemu-arm64".into()
}
fn default_version() -> String {
    env!("CARGO_PKG_VERSION").into()
}
fn default_reboot_command() -> PathBuf {
    PathBuf::from("reboot")
}

impl Default for UpdateConfig {
    fn default() -> Self {
        Self {
            backend: UpdateBackend::Auto,
            max_bundle_mib: default_max_bundle_mib(),
            upload_dir: None,
            system_conf: default_system_conf(),
            rauc_command: default_rauc(),
            rauc_agent_dir: default_agent_dir(),
            last_update_file: default_last_update(),
            release_file: default_release(),
            ca_cert: default_ca(),
            compatible: default_compatible(),
            sim_dir: None,
            running_version: default_version(),
            reboot_command: default_reboot_command(),
        }
    }
}

impl UpdateConfig {
    /// Checks the values (config validation).
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        if self.max_bundle_mib == 0 || self.max_bundle_mib > 4096 {
            return bad(format!(
                "update.max_bundle_mib = {} must be 1..=4096",
                self.max_bundle_mib
            ));
        }
        if self.compatible.trim().is_empty() {
            return bad("update.compatible must not be empty".into());
        }
        if version_key(&self.running_version).is_none() {
            return bad(format!(
                "update.running_version = {:?} is not dotted numbers (e.g. 1.4.2)",
                self.running_version
            ));
        }
        Ok(())
    }
}

/// One root file system slot as `/status` shows it.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct SlotInfo {
    /// `A` or `B` (the boot name).
    pub slot: String,
    /// The release it holds, when known (`None`: empty or never installed by an update).
    pub version: Option<String>,
    /// Its build (commit and date), when known.
    pub build: Option<String>,
    /// `booted`, `good` (boots if chosen), `bad` (failed or marked bad), `empty`.
    pub state: String,
}

/// Both slots and which one boots next.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct SystemSlots {
    /// The board type bundles must name.
    pub compatible: Option<String>,
    /// The slot running now.
    pub running: Option<SlotInfo>,
    /// The other slot (where the next update goes).
    pub other: Option<SlotInfo>,
    /// The slot the bootloader tries first on the next boot.
    pub boot_next: Option<String>,
}

/// The last update's outcome (`last-update`, `key=value` lines).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct LastUpdate {
    /// UTC time, RFC 3339.
    pub time: String,
    /// The bundle's version.
    pub version: String,
    /// `installed`, `healthy`, `rolled-back`, `refused` or `failed`.
    pub outcome: String,
    /// Whether it went in (installed or healthy).
    pub ok: bool,
    /// The slot it went to (`none` when refused).
    pub slot: Option<String>,
    /// What happened, in plain words.
    pub detail: String,
}

impl LastUpdate {
    /// Parses the `key=value` text of a `last-update` file (unknown keys ignored).
    pub fn parse(text: &str) -> Option<Self> {
        let mut lu = LastUpdate::default();
        for line in text.lines() {
            let Some((k, v)) = line.split_once('=') else {
                continue;
            };
            let v = v.trim().to_string();
            match k.trim() {
                "time" => lu.time = v,
                "version" => lu.version = v,
                "outcome" => lu.outcome = v,
                "slot" => lu.slot = (!v.is_empty() && v != "none").then_some(v),
                "detail" => lu.detail = v,
                _ => {}
            }
        }
        if lu.outcome.is_empty() {
            return None;
        }
        lu.ok = matches!(lu.outcome.as_str(), "installed" | "healthy");
        Some(lu)
    }

    /// The file text (one value per line; newlines in values become spaces).
    pub fn file_text(&self) -> String {
        let one = |s: &str| s.replace(['\n', '\r'], " ");
        format!(
            "outcome={}\nslot={}\nversion={}\ndetail={}\ntime={}\n",
            one(&self.outcome),
            one(self.slot.as_deref().unwrap_or("none")),
            one(&self.version),
            one(&self.detail),
            one(&self.time)
        )
    }

    /// Reads `path`; `None` when missing or without an outcome.
    pub fn read(path: &Path) -> Option<Self> {
        std::fs::read_to_string(path)
            .ok()
            .as_deref()
            .and_then(Self::parse)
    }

    /// Writes `path` atomically (temporary file, rename).
    pub fn write(&self, path: &Path) -> Result<()> {
        let storage = |source| FirmwareError::Storage {
            path: path.display().to_string(),
            source,
        };
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(storage)?;
        }
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, self.file_text()).map_err(storage)?;
        std::fs::rename(&tmp, path).map_err(storage)
    }
}

/// Why a bundle was not installed: a kind for programs, a sentence for people.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Refusal {
    /// What kind of refusal.
    pub kind: RefusalKind,
    /// What happened and what to do, in plain words.
    pub reason: String,
}

/// Kinds of [`Refusal`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RefusalKind {
    /// Not signed by a key this board trusts (or the signature does not match the content).
    Signature,
    /// The file ends early (an interrupted copy or download).
    Truncated,
    /// Not a RAUC bundle at all.
    NotABundle,
    /// Older than the running system.
    Downgrade,
    /// Made for another board type.
    OtherBoard,
    /// Larger than `[update] max_bundle_mib`.
    TooLarge,
    /// No room on the data partition.
    DiskFull,
    /// Another upload or install is running.
    Busy,
    /// The upload stopped before its end.
    Interrupted,
    /// The update tool failed for another reason (its message is in the reason).
    Failed,
}

impl Refusal {
    /// A refusal of `kind` saying `reason`.
    pub fn new(kind: RefusalKind, reason: impl Into<String>) -> Self {
        Self {
            kind,
            reason: reason.into(),
        }
    }
}

/// What an install put where.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Installed {
    /// The slot written.
    pub slot: String,
    /// The bundle's version.
    pub version: String,
}

/// A reboot asked for after an install (`POST /api/update?reboot=1`), as `/status` →
/// `system.reboot` shows it until the board goes down.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct RebootRequest {
    /// `pending` (asked for: the board goes down shortly) or `failed` (reboot it by hand).
    pub state: &'static str,
    /// UTC time it was asked for.
    pub requested: String,
    /// The slot that boots next.
    pub slot: String,
    /// The version installed there.
    pub version: String,
    /// Who reboots the board, or why that failed, in plain words.
    pub detail: String,
}

/// Progress callback of an install: percent (0..=100) and the step in words.
pub type Progress<'a> = &'a mut dyn FnMut(u8, &str);

/// The board's update tool, as irtrackd needs it.
pub trait SystemUpdater: Send + Sync {
    /// `rauc` or `simulated`.
    fn backend(&self) -> &'static str;
    /// Both slots now (may take a moment: called off the async threads).
    fn slots(&self) -> std::result::Result<SystemSlots, String>;
    /// Whether [`SystemUpdater::slots`] answers at once (read at start without a thread).
    fn slots_are_cheap(&self) -> bool {
        false
    }
    /// The `last-update` file this updater and its handlers share.
    fn last_update_file(&self) -> &Path;
    /// Installs `bundle` into the other slot, reporting progress; the running system is left
    /// unchanged when it refuses.
    fn install(&self, bundle: &Path, progress: Progress) -> std::result::Result<Installed, Refusal>;
    /// Reboots the board into what was just `installed`: asks whoever may do it and says who
    /// does it, in plain words. The board goes down shortly after (irtrackd with it).
    fn request_reboot(&self, installed: &Installed) -> std::result::Result<String, String>;
}

/// The updater `cfg` selects, or `None` (`none`, or `auto` without RAUC).
pub fn from_config(cfg: &UpdateConfig, state_dir: &Path) -> Result<Option<Arc<dyn SystemUpdater>>> {
    let rauc_here =
        || cfg.system_conf.is_file() && (on_path(&cfg.rauc_command) || rauc::use_agent(&cfg.rauc_agent_dir));
    Ok(match cfg.backend {
        UpdateBackend::None => None,
        UpdateBackend::Auto if !rauc_here() => None,
        UpdateBackend::Auto | UpdateBackend::Rauc => Some(Arc::new(RaucUpdater::new(cfg))),
        UpdateBackend::Simulated => {
            let dir = cfg
                .sim_dir
                .clone()
                .unwrap_or_else(|| state_dir.join("simulated-system"));
            Some(Arc::new(SimUpdater::open(cfg, &dir)?))
        }
    })
}

/// Whether `cmd` names an existing file (a path) or a program on `PATH`.
fn on_path(cmd: &Path) -> bool {
    if cmd.components().count() > 1 {
        return cmd.is_file();
    }
    std::env::var_os("PATH").is_some_and(|p| std::env::split_paths(&p).any(|d| d.join(cmd).is_file()))
}

/// Dotted numeric version as numbers (`+build`/`-pre` tails ignored); `None` if not one.
pub fn version_key(v: &str) -> Option<Vec<u64>> {
    let core = v.trim().split(['+', '-']).next()?;
    core.split('.').map(|p| p.parse::<u64>().ok()).collect()
}

/// Whether `new` is older than `running` (both dotted numbers; unknown counts as not older).
pub fn is_downgrade(new: &str, running: &str) -> bool {
    match (version_key(new), version_key(running)) {
        (Some(mut a), Some(mut b)) => {
            let n = a.len().max(b.len());
            a.resize(n, 0);
            b.resize(n, 0);
            a < b
        }
        _ => false,
    }
}

/// UTC now as RFC 3339 (seconds).
pub fn utc_now() -> String {
    let s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let days = s / 86_400;
    let (h, m, sec) = ((s % 86_400) / 3600, (s % 3600) / 60, s % 60);
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let mo = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(mo <= 2);
    format!("{y:04}-{mo:02}-{d:02}T{h:02}:{m:02}:{sec:02}Z")
}

/// The state of the current (or last) upload and install of this irtrackd.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Job {
    /// Counts up per upload, so a client can tell its own job from a later one.
    pub id: u64,
    /// `receiving`, `installing`, `installed`, `refused`.
    pub state: &'static str,
    /// 0..=100 of the current state (receiving: of the upload, installing: of the install).
    pub percent: u8,
    /// The step in words.
    pub step: String,
    /// Bytes of the bundle received so far.
    pub bytes_received: u64,
    /// The upload's announced length, if it gave one.
    pub bytes_total: Option<u64>,
    /// The installed version (when installed).
    pub version: Option<String>,
    /// Why it was not installed.
    pub refusal: Option<Refusal>,
    /// UTC time it started.
    pub started: String,
    /// The upload asked for a reboot into the new system once it is installed (`reboot=1`).
    pub reboot: bool,
}

impl Job {
    /// Whether it still runs (an upload or install in progress).
    pub fn running(&self) -> bool {
        matches!(self.state, "receiving" | "installing")
    }
}

/// How long a slot report is reused before RAUC is asked again.
pub const SLOTS_MAX_AGE: Duration = Duration::from_secs(30);
/// How soon a failed slot read is tried again.
pub const SLOTS_RETRY_AFTER_ERROR: Duration = Duration::from_secs(3);
/// Name of the uploaded bundle in the upload directory (one at a time).
pub const UPLOAD_NAME: &str = "upload.raucb";

#[derive(Default)]
struct SlotsCache {
    slots: Option<std::result::Result<SystemSlots, String>>,
    at: Option<Instant>,
    refreshing: bool,
}

/// The updater as the status listener uses it (see the module documentation).
pub struct Updates {
    updater: Arc<dyn SystemUpdater>,
    upload_dir: PathBuf,
    /// Largest bundle accepted, bytes.
    pub max_bundle_bytes: u64,
    job: Mutex<Option<Job>>,
    slots: Mutex<SlotsCache>,
    next_id: AtomicU64,
    reboot: Mutex<Option<RebootRequest>>,
}

impl Updates {
    /// Wraps `updater`; uploads go to `upload_dir` (created if missing). Starts reading the
    /// slots in the background.
    pub fn new(
        updater: Arc<dyn SystemUpdater>,
        upload_dir: PathBuf,
        max_bundle_bytes: u64,
    ) -> Result<Arc<Self>> {
        std::fs::create_dir_all(&upload_dir).map_err(|source| FirmwareError::Storage {
            path: upload_dir.display().to_string(),
            source,
        })?;
        // A bundle left by an earlier run (power cut during an upload) is not installed.
        for name in [UPLOAD_NAME, ".upload.part"] {
            let _ = std::fs::remove_file(upload_dir.join(name));
        }
        let u = Arc::new(Self {
            updater,
            upload_dir,
            max_bundle_bytes,
            job: Mutex::new(None),
            slots: Mutex::new(SlotsCache::default()),
            next_id: AtomicU64::new(1),
            reboot: Mutex::new(None),
        });
        if u.updater.slots_are_cheap() {
            u.refresh_slots_now();
        } else {
            u.refresh_slots_in_background();
        }
        Ok(u)
    }

    /// From the config: `None` when updates are off.
    pub fn from_config(cfg: &UpdateConfig, state_dir: &Path) -> Result<Option<Arc<Self>>> {
        let Some(updater) = from_config(cfg, state_dir)? else {
            return Ok(None);
        };
        let upload_dir = cfg.upload_dir.clone().unwrap_or_else(|| {
            if updater.backend() == "rauc" {
                if rauc::use_agent(&cfg.rauc_agent_dir) {
                    cfg.rauc_agent_dir.clone()
                } else {
                    PathBuf::from("/data")
                }
            } else {
                cfg.sim_dir
                    .clone()
                    .unwrap_or_else(|| state_dir.join("simulated-system"))
            }
        });
        Self::new(updater, upload_dir, cfg.max_bundle_mib << 20).map(Some)
    }

    /// `rauc` or `simulated`.
    pub fn backend(&self) -> &'static str {
        self.updater.backend()
    }

    /// Where an upload is written while it arrives.
    pub fn part_path(&self) -> PathBuf {
        self.upload_dir.join(".upload.part")
    }

    /// Where a complete upload waits for its install.
    pub fn bundle_path(&self) -> PathBuf {
        self.upload_dir.join(UPLOAD_NAME)
    }

    fn refresh_slots_in_background(self: &Arc<Self>) {
        {
            let Ok(mut c) = self.slots.lock() else { return };
            if c.refreshing {
                return;
            }
            c.refreshing = true;
        }
        let me = Arc::clone(self);
        let spawned = std::thread::Builder::new()
            .name("update-slots".into())
            .spawn(move || me.refresh_slots_now());
        if spawned.is_err()
            && let Ok(mut c) = self.slots.lock()
        {
            c.refreshing = false;
        }
    }

    /// Asks the updater for the slots now (blocking).
    pub fn refresh_slots_now(&self) {
        let slots = self.updater.slots();
        if let Err(e) = &slots {
            tracing::warn!(error = %e, "reading the system slots failed");
        }
        if let Ok(mut c) = self.slots.lock() {
            c.slots = Some(slots);
            c.at = Some(Instant::now());
            c.refreshing = false;
        }
    }

    /// The current or last job.
    pub fn job(&self) -> Option<Job> {
        self.job.lock().ok().and_then(|j| j.clone())
    }

    /// The reboot asked for after an install, if any (until irtrackd ends with the board).
    pub fn reboot(&self) -> Option<RebootRequest> {
        self.reboot.lock().ok().and_then(|r| r.clone())
    }

    fn set_reboot(&self, req: RebootRequest) {
        if let Ok(mut r) = self.reboot.lock() {
            *r = Some(req);
        }
    }

    /// Asks the updater to reboot into `inst` (job `id` asked for it) and records the outcome
    /// where `/status` shows it.
    fn reboot_into(&self, id: u64, inst: &Installed) {
        let mut req = RebootRequest {
            state: "pending",
            requested: utc_now(),
            slot: inst.slot.clone(),
            version: inst.version.clone(),
            detail: "asking for the reboot".into(),
        };
        self.set_reboot(req.clone());
        match self.updater.request_reboot(inst) {
            Ok(how) => {
                tracing::info!(slot = %inst.slot, version = %inst.version, how = %how, "rebooting into the update");
                req.detail = how;
                self.update_job(id, |j| {
                    j.step = format!("installed into slot {}; rebooting into it", inst.slot);
                });
            }
            Err(why) => {
                tracing::warn!(error = %why, "the reboot after the install failed");
                req.state = "failed";
                req.detail = format!("{why}; reboot the board by hand");
                self.update_job(id, |j| {
                    j.step = format!(
                        "installed into slot {}; the reboot failed ({why}): reboot the board by hand",
                        inst.slot
                    );
                });
            }
        }
        self.set_reboot(req);
    }

    fn update_job(&self, id: u64, f: impl FnOnce(&mut Job)) {
        if let Ok(mut j) = self.job.lock()
            && let Some(job) = j.as_mut()
            && job.id == id
        {
            f(job);
        }
    }

    /// The `/status` `system` object: slots (cached, refreshed in the background when
    /// older than [`SLOTS_MAX_AGE`]), the last update's outcome, the current job.
    pub fn report_json(self: &Arc<Self>) -> serde_json::Value {
        let (slots, stale) = match self.slots.lock() {
            Ok(c) => {
                // A failed read (RAUC's service still starting) is tried again soon.
                let max_age = if matches!(c.slots, Some(Err(_))) {
                    SLOTS_RETRY_AFTER_ERROR
                } else {
                    SLOTS_MAX_AGE
                };
                (
                    c.slots.clone(),
                    !c.refreshing && c.at.is_none_or(|t| t.elapsed() > max_age),
                )
            }
            Err(_) => (None, false),
        };
        if stale {
            self.refresh_slots_in_background();
        }
        let (slots, slots_error) = match slots {
            Some(Ok(s)) => (s, None),
            Some(Err(e)) => (SystemSlots::default(), Some(e)),
            None => (SystemSlots::default(), None),
        };
        serde_json::json!({
            "backend": self.backend(),
            "compatible": slots.compatible,
            "running": slots.running,
            "other": slots.other,
            "boot_next": slots.boot_next,
            "slots_error": slots_error,
            "last_update": LastUpdate::read(self.updater.last_update_file()),
            "install": self.job(),
            "reboot": self.reboot(),
            "max_bundle_bytes": self.max_bundle_bytes,
        })
    }

    /// Prometheus lines (OpenMetrics) of the update state.
    pub fn metrics_text(&self) -> String {
        let job = self.job();
        let running = job.as_ref().is_some_and(Job::running);
        let pct = job.as_ref().filter(|j| j.running()).map_or(0, |j| j.percent);
        let last_ok = LastUpdate::read(self.updater.last_update_file()).map(|l| u8::from(l.ok));
        let mut s = format!(
            "# HELP irtrackd_update_in_progress 1 while a bundle is uploaded or installed.\n# TYPE irtrackd_update_in_progress gauge\nirtrackd_update_in_progress {}\n\
             # HELP irtrackd_update_progress_percent Percent of the running upload or install.\n# TYPE irtrackd_update_progress_percent gauge\nirtrackd_update_progress_percent {pct}\n",
            u8::from(running)
        );
        let pending = self.reboot().is_some_and(|r| r.state == "pending");
        s.push_str(&format!(
            "# HELP irtrackd_update_reboot_pending 1 once a reboot into an installed update was asked for.\n# TYPE irtrackd_update_reboot_pending gauge\nirtrackd_update_reboot_pending {}\n",
            u8::from(pending)
        ));
        if let Some(ok) = last_ok {
            s.push_str(&format!(
                "# HELP irtrackd_update_last_ok 1 if the last update went in, 0 if refused or rolled back.\n# TYPE irtrackd_update_last_ok gauge\nirtrackd_update_last_ok {ok}\n"
            ));
        }
        s
    }

    /// Starts an upload of `length` bytes (if announced), to be followed by a reboot into it
    /// when `reboot`: refused while another runs, when too large, or when the upload directory
    /// has no room for it.
    pub fn begin_upload(
        self: &Arc<Self>,
        length: Option<u64>,
        reboot: bool,
    ) -> std::result::Result<UploadTicket, Refusal> {
        if let Some(len) = length
            && len > self.max_bundle_bytes
        {
            return Err(too_large(len, self.max_bundle_bytes));
        }
        if let Some(len) = length
            && let Some(free) = free_bytes(&self.upload_dir)
            && free < len + (1 << 20)
        {
            return Err(disk_full(&self.upload_dir, Some(free)));
        }
        let mut j = self.job.lock().map_err(|_| {
            Refusal::new(
                RefusalKind::Failed,
                "the update state is unusable; restart irtrackd",
            )
        })?;
        if let Some(cur) = j.as_ref()
            && cur.running()
        {
            return Err(Refusal::new(
                RefusalKind::Busy,
                format!(
                    "another update is {} ({}%, {}); wait until it is done",
                    cur.state, cur.percent, cur.step
                ),
            ));
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        *j = Some(Job {
            id,
            state: "receiving",
            percent: 0,
            step: "receiving the bundle".into(),
            bytes_received: 0,
            bytes_total: length,
            version: None,
            refusal: None,
            started: utc_now(),
            reboot,
        });
        Ok(UploadTicket {
            updates: Arc::clone(self),
            id,
            total: length,
            received: 0,
            done: false,
            reboot,
        })
    }

    fn finish_job(&self, id: u64, result: std::result::Result<Installed, Refusal>) {
        match result {
            Ok(inst) => {
                tracing::info!(slot = %inst.slot, version = %inst.version, "update installed");
                self.update_job(id, |j| {
                    j.state = "installed";
                    j.percent = 100;
                    j.step = if j.reboot {
                        format!("installed into slot {}; rebooting into it", inst.slot)
                    } else {
                        format!("installed into slot {}; reboot to start it", inst.slot)
                    };
                    j.version = Some(inst.version);
                });
            }
            Err(r) => {
                tracing::warn!(kind = ?r.kind, reason = %r.reason, "update refused");
                // RAUC itself records nothing for most refusals: say it where operators look.
                let prior = LastUpdate::read(self.updater.last_update_file());
                let version = prior
                    .filter(|p| p.outcome == "refused" && p.detail == r.reason)
                    .map(|p| p.version)
                    .unwrap_or_default();
                let lu = LastUpdate {
                    time: utc_now(),
                    version,
                    outcome: "refused".into(),
                    ok: false,
                    slot: None,
                    detail: r.reason.clone(),
                };
                // Under the root agent the file is root's; the agent records the refusal then.
                if let Err(e) = lu.write(self.updater.last_update_file()) {
                    tracing::debug!(error = %e, "recording the refusal failed");
                }
                self.update_job(id, |j| {
                    j.state = "refused";
                    j.step = "refused".into();
                    j.refusal = Some(r);
                });
            }
        }
    }
}

fn too_large(len: u64, max: u64) -> Refusal {
    Refusal::new(
        RefusalKind::TooLarge,
        format!(
            "the bundle is {:.1} MiB, more than this board accepts ({} MiB, [update] max_bundle_mib)",
            len as f64 / 1048576.0,
            max >> 20
        ),
    )
}

fn disk_full(dir: &Path, free: Option<u64>) -> Refusal {
    let free = free.map_or(String::new(), |f| {
        format!(" ({:.1} MiB free)", f as f64 / 1048576.0)
    });
    Refusal::new(
        RefusalKind::DiskFull,
        format!(
            "no room for the bundle in {}{free}; free space on the data partition",
            dir.display()
        ),
    )
}

/// Free bytes for an unprivileged writer in `dir`.
fn free_bytes(dir: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt as _;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `c` is a NUL-terminated path, `st` a valid out-pointer.
    let rc = unsafe { libc::statvfs(c.as_ptr(), &mut st) };
    (rc == 0).then(|| st.f_bavail as u64 * st.f_frsize as u64)
}

/// One upload in progress: count its bytes, then [`UploadTicket::install`]. Dropped without
/// it (the client went away, too large), the job ends as refused and the slot is free.
pub struct UploadTicket {
    updates: Arc<Updates>,
    id: u64,
    total: Option<u64>,
    received: u64,
    done: bool,
    reboot: bool,
}

impl UploadTicket {
    /// The job's id.
    pub fn id(&self) -> u64 {
        self.id
    }

    /// `n` more bytes arrived; refused once the total passes the cap.
    pub fn received(&mut self, n: u64) -> std::result::Result<(), Refusal> {
        self.received += n;
        if self.received > self.updates.max_bundle_bytes {
            return Err(too_large(self.received, self.updates.max_bundle_bytes));
        }
        let (got, total) = (self.received, self.total);
        self.updates.update_job(self.id, |j| {
            j.bytes_received = got;
            j.percent = total.map_or(0, |t| (got.saturating_mul(100) / t.max(1)).min(100) as u8);
        });
        Ok(())
    }

    /// The write failed: a full disk is said as such.
    pub fn write_failed(&self, e: &std::io::Error) -> Refusal {
        if e.raw_os_error() == Some(libc::ENOSPC) {
            disk_full(&self.updates.upload_dir, free_bytes(&self.updates.upload_dir))
        } else {
            Refusal::new(
                RefusalKind::Failed,
                format!(
                    "writing the bundle to {} failed: {e}",
                    self.updates.upload_dir.display()
                ),
            )
        }
    }

    /// Ends the job as refused (recorded in `last-update`).
    pub fn refuse(mut self, r: Refusal) {
        self.done = true;
        let _ = std::fs::remove_file(self.updates.part_path());
        self.updates.finish_job(self.id, Err(r));
    }

    /// The whole bundle is in `part_path()`: checks its layout now (a truncated file is
    /// refused at once) and installs it on a thread of its own; then, if the upload asked for
    /// it, reboots into it.
    pub fn install(mut self) -> std::result::Result<u64, Refusal> {
        self.done = true;
        let reboot = self.reboot;
        let u = Arc::clone(&self.updates);
        let id = self.id;
        if let Some(t) = self.total
            && self.received < t
        {
            let r = Refusal::new(
                RefusalKind::Interrupted,
                format!("the upload ended after {} of {} bytes", self.received, t),
            );
            let _ = std::fs::remove_file(u.part_path());
            u.finish_job(id, Err(r.clone()));
            return Err(r);
        }
        let bundle = u.bundle_path();
        if let Err(e) = std::fs::rename(u.part_path(), &bundle) {
            let r = Refusal::new(
                RefusalKind::Failed,
                format!("keeping the uploaded bundle failed: {e}"),
            );
            u.finish_job(id, Err(r.clone()));
            return Err(r);
        }
        if let Err(r) = bundle::inspect(&bundle) {
            let _ = std::fs::remove_file(&bundle);
            u.finish_job(id, Err(r.clone()));
            return Err(r);
        }
        u.update_job(id, |j| {
            j.state = "installing";
            j.percent = 0;
            j.step = "starting the install".into();
        });
        let worker = Arc::clone(&u);
        let spawned = std::thread::Builder::new()
            .name("update-install".into())
            .spawn(move || {
                let mut progress = |pct: u8, step: &str| {
                    worker.update_job(id, |j| {
                        j.percent = pct.min(100);
                        j.step = step.to_string();
                    });
                };
                let result = worker.updater.install(&bundle, &mut progress);
                let _ = std::fs::remove_file(&bundle);
                let installed = result.as_ref().ok().cloned();
                worker.finish_job(id, result);
                worker.refresh_slots_now();
                if reboot && let Some(inst) = installed {
                    worker.reboot_into(id, &inst);
                }
            });
        if let Err(e) = spawned {
            let r = Refusal::new(
                RefusalKind::Failed,
                format!("cannot start the install thread: {e}"),
            );
            u.finish_job(id, Err(r.clone()));
            return Err(r);
        }
        Ok(id)
    }
}

impl Drop for UploadTicket {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_file(self.updates.part_path());
            self.updates.finish_job(
                self.id,
                Err(Refusal::new(
                    RefusalKind::Interrupted,
                    format!(
                        "the upload stopped after {} bytes; send the bundle again",
                        self.received
                    ),
                )),
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn last_update_round_trips_and_reads_the_handlers_format() {
        let text = "outcome=refused\nslot=none\nversion=0.0.0\ndetail=refused: downgrade from 1.2.0 to 0.0.0 (touch /data/rauc/allow-downgrade to allow one)\ntime=2026-11-28T03:00:00Z\n";
        let lu = LastUpdate::parse(text).unwrap();
        assert_eq!(lu.outcome, "refused");
        assert!(!lu.ok);
        assert_eq!(lu.slot, None);
        assert!(lu.detail.starts_with("refused: downgrade from 1.2.0"));
        assert_eq!(LastUpdate::parse(&lu.file_text()).unwrap(), lu);
        let healthy = LastUpdate::parse("outcome=healthy\nslot=B\nversion=1.3.0\n").unwrap();
        assert!(healthy.ok);
        assert_eq!(healthy.slot.as_deref(), Some("B"));
        assert_eq!(LastUpdate::parse("nothing here\n"), None);
    }

    #[test]
    fn versions_compare_as_numbers() {
        assert!(is_downgrade("1.9.0", "1.10.0"));
        assert!(!is_downgrade("1.10.0", "1.9.0"));
        assert!(!is_downgrade("1.2", "1.2.0"));
        assert!(is_downgrade("0.0.0", "0.1.0+abc"));
        assert!(!is_downgrade("x", "1.0"));
        assert_eq!(version_key("1.2.3-rc1"), Some(vec![1, 2, 3]));
        assert_eq!(version_key("1..2"), None);
    }

    #[test]
    fn utc_now_is_rfc3339() {
        let t = utc_now();
        assert_eq!(t.len(), 20, "{t}");
        assert!(t.starts_with("20") && t.ends_with('Z') && t.as_bytes()[10] == b'T');
    }
}
