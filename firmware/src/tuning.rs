//! Live tuning from the set-up view: detection threshold, blob area limits, and each camera's
//! exposure and gain.
//!
//! The status listener validates a change and installs it here; the processing loop picks it
//! up before its next frame set by comparing a generation counter (the lock is taken only
//! when the counter moved), applies the detector settings to its tracker and the camera
//! settings through [`crate::source::FrameSource::set_control`], and reports the cameras'
//! actual values back. `POST /api/tuning/save` writes the values to `tuning.toml` in the
//! state directory, which irtrackd applies at its next start on top of the config file.

use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use irtrack_core::pipeline::TrackerConfig;
use serde::{Deserialize, Serialize};

use crate::error::{FirmwareError, Result};
use crate::source::{CameraControl, CameraControls};

/// File name of the saved tuning in the state directory.
pub const TUNING_FILE: &str = "tuning.toml";

/// Requested exposure/gain of one camera (`None`: leave as it is).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraRequest {
    /// Camera index, configuration order.
    pub camera: usize,
    /// Exposure time in the camera's units (V4L2: 100 µs).
    #[serde(default)]
    pub exposure: Option<i64>,
    /// Analogue gain in the camera's units.
    #[serde(default)]
    pub gain: Option<i64>,
}

/// The saved tuning file (`tuning.toml`).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TuningFile {
    /// Blob detection threshold, DN; `None` keeps the config file's value.
    pub threshold_dn: Option<u32>,
    /// Smallest blob area accepted, pixels; `None` keeps the config file's value.
    pub min_area_px: Option<u32>,
    /// Largest blob area accepted, pixels; `None` keeps the config file's value.
    pub max_area_px: Option<u32>,
    /// Exposure and gain per camera (`[[camera]]` tables).
    #[serde(default)]
    pub camera: Vec<CameraRequest>,
}

impl TuningFile {
    /// Reads `dir/tuning.toml`; `Ok(None)` when there is none.
    pub fn load(dir: &Path) -> Result<Option<TuningFile>> {
        let path = dir.join(TUNING_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => {
                return Err(FirmwareError::ConfigFile {
                    path: path.display().to_string(),
                    reason: format!("cannot read: {e}"),
                });
            }
        };
        toml::from_str(&text)
            .map(Some)
            .map_err(|e| FirmwareError::ConfigFile {
                path: path.display().to_string(),
                reason: e.to_string(),
            })
    }

    /// `tracking` with this file's detector values applied (validated like a live change).
    pub fn apply_to(&self, tracking: &TrackerConfig) -> std::result::Result<TrackerConfig, String> {
        let mut t = *tracking;
        if let Some(v) = self.threshold_dn {
            t.threshold_dn = v;
        }
        if let Some(v) = self.min_area_px {
            t.min_area_px = v;
        }
        if let Some(v) = self.max_area_px {
            t.max_area_px = v;
        }
        check_detector(&t)?;
        Ok(t)
    }
}

/// Checks the live-tunable detector values (what a 400 answer says).
pub fn check_detector(t: &TrackerConfig) -> std::result::Result<(), String> {
    if t.min_area_px == 0 {
        return Err("min_area_px must be at least 1".into());
    }
    if t.min_area_px > t.max_area_px {
        return Err(format!(
            "min_area_px {} is above max_area_px {}",
            t.min_area_px, t.max_area_px
        ));
    }
    Ok(())
}

/// A change request (`POST /api/tuning`): absent fields stay as they are.
#[derive(Debug, Clone, PartialEq, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TuningChange {
    /// New detection threshold, DN.
    pub threshold_dn: Option<u32>,
    /// New smallest blob area, pixels.
    pub min_area_px: Option<u32>,
    /// New largest blob area, pixels.
    pub max_area_px: Option<u32>,
    /// Camera settings to change.
    #[serde(default)]
    pub cameras: Vec<CameraRequest>,
}

/// What the loop should apply.
#[derive(Debug, Clone, PartialEq)]
pub struct Requested {
    /// Detector settings with every accepted change applied.
    pub tracking: TrackerConfig,
    /// Camera settings not yet applied by the loop.
    pub pending: Vec<(usize, CameraControl, i64)>,
}

/// Shared between the status listener and the processing loop.
#[derive(Debug)]
pub struct TuningHandle {
    requested: Mutex<Requested>,
    generation: AtomicU64,
    /// The cameras' values as the loop last read them from the source.
    cameras: Mutex<Vec<CameraControls>>,
    /// Errors of the last camera changes (shown by `GET /api/tuning`).
    last_error: Mutex<Option<String>>,
    /// Max DN of the frames (255 for 8-bit, 1023 for 10-bit, ...).
    max_dn: AtomicU64,
    unsaved: AtomicBool,
    state_dir: PathBuf,
    /// Whether a tuning file was applied at start.
    pub loaded_from_file: bool,
}

/// `GET /api/tuning` answer.
#[derive(Debug, Clone, Serialize)]
pub struct TuningReport {
    /// Detection threshold in force, DN.
    pub threshold_dn: u32,
    /// Smallest blob area in force, pixels.
    pub min_area_px: u32,
    /// Largest blob area in force, pixels.
    pub max_area_px: u32,
    /// Each camera's controls as last read back, in camera order.
    pub cameras: Vec<CameraReport>,
    /// Path of the tuning file `save` writes.
    pub saved_to: String,
    /// Values were changed since the last save (or start).
    pub unsaved_changes: bool,
    /// Whether a tuning file was applied at start.
    pub loaded_from_file: bool,
    /// Why the last camera change failed, if it did.
    pub last_error: Option<String>,
}

/// One camera in [`TuningReport`] (contract: docs/http-api.md).
#[derive(Debug, Clone, Serialize)]
pub struct CameraReport {
    /// Camera index, configuration order.
    pub camera: usize,
    /// Exposure as read back, camera units; `None` if the camera has no such control.
    pub exposure: Option<i64>,
    /// Allowed exposure range, `[min, max]`.
    pub exposure_range: Option<[i64; 2]>,
    /// Gain as read back, camera units; `None` if the camera has no such control.
    pub gain: Option<i64>,
    /// Allowed gain range, `[min, max]`.
    pub gain_range: Option<[i64; 2]>,
    /// The camera has exposure or gain control at all.
    pub supported: bool,
}

impl TuningHandle {
    /// `tracking`: the settings the loop starts with; `start_cameras`: camera values from a
    /// saved tuning file, applied by the loop before its first set.
    pub fn new(
        tracking: TrackerConfig,
        start_cameras: &[CameraRequest],
        state_dir: &Path,
        loaded_from_file: bool,
    ) -> Self {
        let mut pending = Vec::new();
        for c in start_cameras {
            if let Some(v) = c.exposure {
                pending.push((c.camera, CameraControl::Exposure, v));
            }
            if let Some(v) = c.gain {
                pending.push((c.camera, CameraControl::Gain, v));
            }
        }
        Self {
            requested: Mutex::new(Requested { tracking, pending }),
            generation: AtomicU64::new(1),
            cameras: Mutex::new(Vec::new()),
            last_error: Mutex::new(None),
            max_dn: AtomicU64::new(255),
            unsaved: AtomicBool::new(false),
            state_dir: state_dir.to_path_buf(),
            loaded_from_file,
        }
    }

    /// Where the tuning file is saved: `tuning.toml` in the state directory.
    pub fn path(&self) -> PathBuf {
        self.state_dir.join(TUNING_FILE)
    }

    /// Counter bumped by every installed change; the loop compares it to decide whether to `take`.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    /// Loop side: takes the requested settings and the camera changes to apply.
    pub fn take(&self) -> Option<Requested> {
        let mut g = self.requested.lock().ok()?;
        let out = Requested {
            tracking: g.tracking,
            pending: std::mem::take(&mut g.pending),
        };
        Some(out)
    }

    /// Loop side: the cameras' values after applying (and errors, if any).
    pub fn report_cameras(&self, cameras: Vec<CameraControls>, error: Option<String>) {
        self.refresh_cameras(cameras);
        if let Ok(mut e) = self.last_error.lock() {
            *e = error;
        }
    }

    /// Replaces the cameras' reported values, keeping the last error (after a reopen).
    pub fn refresh_cameras(&self, cameras: Vec<CameraControls>) {
        if let Ok(mut c) = self.cameras.lock() {
            *c = cameras;
        }
    }

    /// Sets the frames' largest sample value (DN), the bound for the threshold.
    pub fn set_max_dn(&self, max_dn: u32) {
        self.max_dn.store(u64::from(max_dn), Ordering::Relaxed);
    }

    /// The detector settings in force.
    pub fn tracking(&self) -> Option<TrackerConfig> {
        self.requested.lock().ok().map(|g| g.tracking)
    }

    /// Validates and installs a change; on error nothing changes (answer 400 with the text).
    pub fn change(&self, ch: &TuningChange) -> std::result::Result<(), String> {
        let max_dn = self.max_dn.load(Ordering::Relaxed);
        let cameras = self.cameras.lock().map(|c| c.clone()).unwrap_or_default();
        let mut g = self
            .requested
            .lock()
            .map_err(|_| "tuning state unavailable".to_string())?;
        let mut t = g.tracking;
        if let Some(v) = ch.threshold_dn {
            if u64::from(v) >= max_dn {
                return Err(format!(
                    "threshold_dn {v} is not below the frame's maximum {max_dn}; use 0..{max_dn}"
                ));
            }
            t.threshold_dn = v;
        }
        if let Some(v) = ch.min_area_px {
            t.min_area_px = v;
        }
        if let Some(v) = ch.max_area_px {
            t.max_area_px = v;
        }
        check_detector(&t)?;
        let mut pending = Vec::new();
        for c in &ch.cameras {
            let Some(ctl) = cameras.get(c.camera) else {
                return Err(format!(
                    "camera {} does not exist (there are {})",
                    c.camera,
                    cameras.len()
                ));
            };
            for (kind, value) in [
                (CameraControl::Exposure, c.exposure),
                (CameraControl::Gain, c.gain),
            ] {
                let Some(value) = value else { continue };
                let Some(range) = ctl.get(kind) else {
                    return Err(format!(
                        "camera {}: {kind:?} is not supported by this camera",
                        c.camera
                    ));
                };
                if !(range.min..=range.max).contains(&value) {
                    return Err(format!(
                        "camera {}: {kind:?} {value} is outside {}..={}",
                        c.camera, range.min, range.max
                    ));
                }
                pending.push((c.camera, kind, value));
            }
        }
        g.tracking = t;
        g.pending.extend(pending);
        drop(g);
        self.unsaved.store(true, Ordering::Relaxed);
        self.generation.fetch_add(1, Ordering::Release);
        Ok(())
    }

    /// The `GET /api/tuning` answer.
    pub fn report(&self) -> TuningReport {
        let t = self.tracking().unwrap_or_default();
        let cameras = self.cameras.lock().map(|c| c.clone()).unwrap_or_default();
        TuningReport {
            threshold_dn: t.threshold_dn,
            min_area_px: t.min_area_px,
            max_area_px: t.max_area_px,
            cameras: cameras
                .iter()
                .enumerate()
                .map(|(i, c)| CameraReport {
                    camera: i,
                    exposure: c.exposure.map(|v| v.value),
                    exposure_range: c.exposure.map(|v| [v.min, v.max]),
                    gain: c.gain.map(|v| v.value),
                    gain_range: c.gain.map(|v| [v.min, v.max]),
                    supported: c.exposure.is_some() || c.gain.is_some(),
                })
                .collect(),
            saved_to: self.path().display().to_string(),
            unsaved_changes: self.unsaved.load(Ordering::Relaxed),
            loaded_from_file: self.loaded_from_file,
            last_error: self.last_error.lock().ok().and_then(|e| e.clone()),
        }
    }

    /// Writes the current values to `tuning.toml` (via a temporary file and rename, so a
    /// failed write never leaves half a file). The live values stay applied either way.
    pub fn save(&self) -> Result<PathBuf> {
        let t = self.tracking().unwrap_or_default();
        let cameras = self.cameras.lock().map(|c| c.clone()).unwrap_or_default();
        let file = TuningFile {
            threshold_dn: Some(t.threshold_dn),
            min_area_px: Some(t.min_area_px),
            max_area_px: Some(t.max_area_px),
            camera: cameras
                .iter()
                .enumerate()
                .filter(|(_, c)| c.exposure.is_some() || c.gain.is_some())
                .map(|(i, c)| CameraRequest {
                    camera: i,
                    exposure: c.exposure.map(|v| v.value),
                    gain: c.gain.map(|v| v.value),
                })
                .collect(),
        };
        let path = self.path();
        let storage = |source: std::io::Error| FirmwareError::Storage {
            path: path.display().to_string(),
            source,
        };
        let text = toml::to_string(&file).map_err(|e| FirmwareError::Config {
            reason: format!("encoding the tuning: {e}"),
        })?;
        let tmp = self.state_dir.join(format!("{TUNING_FILE}.tmp"));
        let body = format!(
            "# Written by irtrackd (set-up view \"Save\"); applied at the next start on top of\n\
             # [tracking] and the cameras' exposure/gain of the config file.\n{text}"
        );
        std::fs::write(&tmp, body).map_err(storage)?;
        std::fs::rename(&tmp, &path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            storage(e)
        })?;
        self.unsaved.store(false, Ordering::Relaxed);
        Ok(path)
    }
}
