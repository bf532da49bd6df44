//! Per-frame tracking: blobs in every camera → consistent marker → 3-D point.
//!
//! [`Tracker`] owns one [`BlobDetector`] per camera and all scratch space, allocated in
//! [`Tracker::new`]/[`Tracker::set_params`]; processing a frame set never allocates.
//!
//! Choosing the marker: every blob passing the quality gate (area, roundness, not cut by
//! the frame border) is a candidate. Each pair of candidates from two different cameras
//! is triangulated; a pair is *plausible* when its ray gap is ≤ `max_gap_mm` and the point
//! lies within the working range. A plausible pair is extended with the closest
//! candidate of every other camera whose ray passes within `max_gap_mm`; hypotheses are
//! ranked by number of cameras, then gap. If a second hypothesis with as many cameras is
//! also plausible but describes a different point, the frame is ambiguous (e.g. a lamp
//! lying on the marker's epipolar line) and no point is reported — never a guess.
//!
//! ROI tracking: after a tracked frame, each camera that contributed is searched only in a
//! window around its last centroid. A window with no usable blob falls back to the full
//! frame at once ([`Tracker::detect_u8`]); [`Tracker::process_u8`] also retries on the full
//! frames when the windows gave blobs but no consistent point.

use alloc::format;
use alloc::vec::Vec;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::blob::{Blob, BlobConfig, BlobDetector, BlobLimits};
use crate::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use crate::image::{GrayImage, Pixel, Roi};
use crate::params::RigParams;
use crate::retime::{BlobHistory, Retimed, TimeMode, TimedPoint};
use crate::timing::CameraTiming;
use crate::triangulate::{Ray, least_squares_rays, midpoint};
use crate::{Error, Result};

/// Most cameras a rig may have (keeps [`Measurement`] a fixed-size `Copy` value). The same
/// constant as the parameter set's limit, so validation and tracker agree.
pub use crate::params::MAX_CAMERAS;

/// Tracker settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackerConfig {
    /// Pixels strictly above this (frame DN) belong to blobs.
    pub threshold_dn: u32,
    /// Saturation level for the saturated-pixel count; `None` = the pixel type's maximum.
    pub saturation_dn: Option<u32>,
    /// Blob area limits (pixels above threshold).
    pub min_area_px: u32,
    /// Largest blob area (pixels above threshold).
    pub max_area_px: u32,
    /// Minimum blob roundness (σ_minor/σ_major): rejects streaks and reflections on edges.
    pub min_roundness: f64,
    /// Blobs kept per camera and frame (heaviest first); more are counted as dropped.
    pub max_blobs: usize,
    /// Connected-component labels per frame before a frame counts as overloaded.
    pub max_labels: usize,
    /// Ignore blobs touching the frame border (cut-off spots have biased centroids).
    pub reject_edge_blobs: bool,
    /// Largest ray gap (mm) of a consistent observation.
    pub max_gap_mm: f64,
    /// Working range: distance (mm) along each ray from its camera to the point.
    pub min_range_mm: f64,
    /// Largest distance (mm) along a ray from its camera to the point.
    pub max_range_mm: f64,
    /// Half size (px) of the tracking window around the last centroid; 0 disables ROI mode.
    pub roi_half_px: u32,
    /// Which instant a set is solved for when its frames carry timestamps
    /// ([`Tracker::set_frame_time`]): interpolated (accurate), extrapolated (low latency) or
    /// not retimed (docs/timing.md).
    pub time_mode: TimeMode,
    /// Longest time (ms) a blob's centroid may be carried along its track to the set's
    /// instant; a blob further away is not used (the cameras are too far apart in time).
    pub max_bridge_ms: f64,
    /// Furthest (px) a blob may move between two frames of its camera to be linked into a
    /// track.
    pub track_gate_px: f64,
    /// A blob exposed within this span (µs) of the set's instant is used as seen.
    pub as_seen_us: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            threshold_dn: 30,
            saturation_dn: None,
            min_area_px: 3,
            max_area_px: 20_000,
            min_roundness: 0.4,
            max_blobs: 8,
            max_labels: 4096,
            reject_edge_blobs: true,
            max_gap_mm: 3.0,
            min_range_mm: 50.0,
            max_range_mm: 20_000.0,
            roi_half_px: 24,
            time_mode: TimeMode::Accurate,
            // Three frame periods at 120 fps, most of one at 30 fps.
            max_bridge_ms: 25.0,
            // At 1 m/s and 1.4 m a marker moves ~4 px per frame at 120 fps, ~15 px at 30 fps.
            track_gate_px: 40.0,
            // 1 m/s × 5 µs = 5 µm: far below the centroid noise.
            as_seen_us: 5.0,
        }
    }
}

impl TrackerConfig {
    fn validate(&self) -> Result<()> {
        let bad = |reason: alloc::string::String| Err(Error::InvalidParams { reason });
        if self.min_area_px == 0 || self.min_area_px > self.max_area_px {
            return bad(format!(
                "blob area range {}..={} px is empty",
                self.min_area_px, self.max_area_px
            ));
        }
        if !(0.0..=1.0).contains(&self.min_roundness) {
            return bad(format!("min_roundness {} outside 0..=1", self.min_roundness));
        }
        if self.max_blobs == 0 || self.max_blobs > 64 || self.max_labels == 0 {
            return bad(format!(
                "max_blobs {} must be 1..=64, max_labels ≥ 1",
                self.max_blobs
            ));
        }
        if !(self.max_gap_mm > 0.0 && self.max_gap_mm.is_finite()) {
            return bad(format!("max_gap_mm {} must be positive", self.max_gap_mm));
        }
        if !(self.max_bridge_ms >= 0.0 && self.max_bridge_ms <= 1000.0) {
            return bad(format!("max_bridge_ms {} must be 0..=1000", self.max_bridge_ms));
        }
        if !(self.track_gate_px > 0.0 && self.track_gate_px.is_finite()) {
            return bad(format!("track_gate_px {} must be positive", self.track_gate_px));
        }
        if !(self.as_seen_us >= 0.0 && self.as_seen_us.is_finite()) {
            return bad(format!("as_seen_us {} must be ≥ 0", self.as_seen_us));
        }
        if !(self.min_range_mm >= 0.0 && self.max_range_mm > self.min_range_mm) {
            return bad(format!(
                "working range {}..{} mm is empty",
                self.min_range_mm, self.max_range_mm
            ));
        }
        Ok(())
    }

    fn blob_config(&self) -> BlobConfig {
        BlobConfig {
            threshold_dn: self.threshold_dn,
            saturation_dn: self.saturation_dn,
            min_area_px: self.min_area_px,
            max_area_px: self.max_area_px,
        }
    }
}

/// Outcome of one frame set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum TrackStatus {
    /// A consistent marker position was found.
    Tracked,
    /// Fewer than two cameras have a usable blob; `camera` is the first without one.
    NoBlob {
        /// The camera.
        camera: usize,
    },
    /// Blobs were found but no pair of them is consistent, or several inconsistent pairs
    /// are (ambiguous: see [`Measurement::ambiguous`]).
    NoConsistentPair,
    /// A camera's frame had too many separate bright regions to label (sunlight, threshold
    /// too low).
    Overloaded {
        /// The camera.
        camera: usize,
    },
    /// Not every camera's frame was detected since the last solve.
    MissingFrame {
        /// The camera.
        camera: usize,
    },
}

/// What one camera contributed to a measurement.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CameraObservation {
    /// Blobs found (after area limits, at most `max_blobs`).
    pub blob_count: u32,
    /// Blobs passing the quality gate.
    pub candidate_count: u32,
    /// Blobs beyond `max_blobs` that were dropped.
    pub dropped_blobs: u32,
    /// The detection ran in a tracking window, not the full frame.
    pub used_roi: bool,
    /// The blob used for the point (`None`: this camera did not contribute), where the
    /// camera saw it (not moved to the set's instant).
    pub marker: Option<Blob>,
    /// The set's instant minus the marker blob's exposure instant (ns): how far its centroid
    /// was carried (negative: back along its track). 0 without timestamps or marker.
    pub bridge_ns: f64,
    /// Gated blobs that could not be brought to the set's instant (no track yet, or too far
    /// in time) and were left out.
    pub unbridged: u32,
}

/// Result of one frame set.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measurement {
    /// Marker position in the camera-0 frame; `None` = no confident marker (never a guess).
    pub point_cam0_mm: Option<Vector3<f64>>,
    /// Ray gap (mm) of the reported point: two-view common-perpendicular length, or twice
    /// the RMS ray distance for more views. For a rejected frame: the smallest gap of any
    /// pair seen, `f64::INFINITY` if there was no pair.
    pub gap_mm: f64,
    /// What became of the frame set.
    pub status: TrackStatus,
    /// At least one contributing camera was detected in a tracking window.
    pub used_roi: bool,
    /// Rejected because several different points were plausible.
    pub ambiguous: bool,
    /// Cameras contributing to the point.
    pub cameras_used: u32,
    /// 1 − gap / max_gap_mm, clamped to 0..=1 (0 without a point).
    pub quality: f64,
    /// Number of valid entries of `cameras`.
    pub camera_count: usize,
    /// Per-camera observations (the first `camera_count`).
    pub cameras: [CameraObservation; MAX_CAMERAS],
    /// The instant (ns, on the frames' timestamp clock) the point is for, when the frames
    /// carried timestamps ([`Tracker::set_frame_time`]); `None` otherwise.
    pub instant_ns: Option<f64>,
}

impl Measurement {
    fn empty(camera_count: usize) -> Self {
        Measurement {
            point_cam0_mm: None,
            gap_mm: f64::INFINITY,
            status: TrackStatus::NoBlob { camera: 0 },
            used_roi: false,
            ambiguous: false,
            cameras_used: 0,
            quality: 0.0,
            camera_count,
            cameras: [CameraObservation::default(); MAX_CAMERAS],
            instant_ns: None,
        }
    }

    /// Per-camera observations of this measurement.
    pub fn cameras(&self) -> &[CameraObservation] {
        &self.cameras[..self.camera_count.min(MAX_CAMERAS)]
    }
}

#[derive(Debug, Clone, Copy)]
struct Candidate {
    blob: usize,
    ray: Ray,
    /// The centroid the ray goes through (moved to the set's instant when retimed).
    x_px: f64,
    y_px: f64,
}

/// How one camera's blobs agree with a point ([`Tracker::camera_residual`]): the candidate
/// whose ray passes closest to it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraResidual {
    /// Distance (mm) of that candidate's ray from the point: the quantity the tracker's gate
    /// (`max_gap_mm`) bounds for the cameras it uses.
    pub ray_mm: f64,
    /// The candidate's centroid (at the set's instant when retimed) minus the point's
    /// projection into the camera (px): the reprojection error.
    pub residual_px: [f64; 2],
    /// The candidate's image velocity (px/s) along its track, when it has one.
    pub velocity_px_s: Option<[f64; 2]>,
}

#[derive(Debug, Clone, Copy)]
struct Hypothesis {
    point_mm: Vector3<f64>,
    gap_mm: f64,
    /// Candidate index per camera (`u8::MAX` = camera not used).
    members: [u8; MAX_CAMERAS],
    count: u32,
}

#[derive(Debug, Clone)]
struct CameraState {
    detector: BlobDetector,
    /// Blobs given by [`Tracker::set_blobs`] (a camera board's observation), used instead of
    /// the detector's when `external` is set. Capacity `max_blobs`, allocated once.
    external_blobs: Vec<Blob>,
    external: bool,
    model: CameraModel,
    cam_from_cam0: RigidTransform,
    candidates: Vec<Candidate>,
    /// Centroid of the last tracked frame, for the ROI.
    last_px: Option<(f64, f64)>,
    used_roi: bool,
    detected: bool,
    /// Shutter, line time and offset: a blob's exposure instant from its row.
    timing: CameraTiming,
    /// Timestamp of the frame being processed (`None`: frames carry no time).
    frame_ts_ns: Option<u64>,
    /// The previous frames' centroids and instants (the tracks blobs are moved along).
    history: BlobHistory,
    /// The blobs moved to the set's instant (valid when `timed_active`). Capacity `max_blobs`.
    timed: Vec<Blob>,
    timed_active: bool,
    /// Left out of the solve ([`Tracker::solve_excluding`]): its blobs give no ray.
    excluded: bool,
}

/// The per-frame tracker (see the module documentation).
#[derive(Debug, Clone)]
pub struct Tracker {
    config: TrackerConfig,
    cams: Vec<CameraState>,
    rays: Vec<Ray>,
    measurement: Measurement,
    /// Built by [`Tracker::detection_only`]: no calibration, never a point.
    detection_only: bool,
    /// The last solve had every camera's frame: [`Tracker::solve_excluding`] may solve it again.
    resolvable: bool,
}

impl Tracker {
    /// Builds a tracker for `rig`, allocating every buffer.
    pub fn new(rig: &RigParams, config: TrackerConfig) -> Result<Self> {
        config.validate()?;
        let mut t = Tracker {
            config,
            cams: Vec::new(),
            rays: Vec::new(),
            measurement: Measurement::empty(0),
            detection_only: false,
            resolvable: false,
        };
        t.set_params(rig)?;
        Ok(t)
    }

    /// A tracker that only detects blobs, for cameras without a calibration (a cluster camera
    /// board: its observations carry distorted centroids, the solver has the calibration). It
    /// takes 1..=[`MAX_CAMERAS`] cameras of the given image sizes; detection, the quality gate
    /// and [`Tracker::blobs`] work as usual (always on the full frame: no tracking window
    /// without a point), [`Tracker::solve`] never gives a point. [`Tracker::set_params`] turns
    /// it into a full tracker.
    pub fn detection_only(image_sizes: &[ImageSize], config: TrackerConfig) -> Result<Self> {
        config.validate()?;
        let n = image_sizes.len();
        if !(1..=MAX_CAMERAS).contains(&n) {
            return Err(Error::InvalidParams {
                reason: format!("{n} cameras; blob detection needs 1..={MAX_CAMERAS}"),
            });
        }
        let mut cams = Vec::with_capacity(n);
        for (i, &size) in image_sizes.iter().enumerate() {
            // A stand-in pinhole model: the candidates' rays are computed but never used.
            let f = f64::from(size.width_px.max(size.height_px).max(1));
            let model = CameraModel {
                intrinsics: Intrinsics {
                    fx_px: f,
                    fy_px: f,
                    cx_px: f64::from(size.width_px) / 2.0,
                    cy_px: f64::from(size.height_px) / 2.0,
                },
                distortion: Distortion::NONE,
                image_size: size,
            };
            cams.push(CameraState::new(i, model, RigidTransform::IDENTITY, &config)?);
        }
        Ok(Tracker {
            config,
            cams,
            rays: Vec::with_capacity(n),
            measurement: Measurement::empty(n),
            detection_only: true,
            resolvable: false,
        })
    }

    /// Built by [`Tracker::detection_only`] and not given parameters since.
    pub fn is_detection_only(&self) -> bool {
        self.detection_only
    }

    /// Swaps in new rig parameters (calibration push, possibly new image sizes). Buffers
    /// are reallocated here, outside the per-frame path; tracking restarts from the full
    /// frame. On error the tracker keeps its previous parameters.
    pub fn set_params(&mut self, rig: &RigParams) -> Result<()> {
        let n = rig.cameras.len();
        if !(2..=MAX_CAMERAS).contains(&n) {
            return Err(Error::InvalidParams {
                reason: format!("rig has {n} cameras; the tracker needs 2..={MAX_CAMERAS}"),
            });
        }
        let mut cams = Vec::with_capacity(n);
        for (i, c) in rig.cameras.iter().enumerate() {
            let k = &c.model.intrinsics;
            if !(k.fx_px > 0.0 && k.fy_px > 0.0 && k.cx_px.is_finite() && k.cy_px.is_finite()) {
                return Err(Error::InvalidParams {
                    reason: format!("camera {i}: focal lengths must be positive and centre finite"),
                });
            }
            let mut cam = CameraState::new(i, c.model, c.cam_from_cam0, &self.config)?;
            // Timing belongs to the camera, not the calibration: kept across pushes.
            if let Some(old) = self.cams.get(i) {
                cam.timing = old.timing;
            }
            cams.push(cam);
        }
        self.cams = cams;
        self.rays = Vec::with_capacity(n);
        self.measurement = Measurement::empty(n);
        self.detection_only = false;
        Ok(())
    }

    /// Replaces the settings live (threshold, area limits, gate), effective from the next
    /// detection. Settings that size buffers (`max_blobs`, `max_labels`) cannot change here,
    /// so this never allocates; on error the previous settings stay.
    pub fn set_config(&mut self, config: TrackerConfig) -> Result<()> {
        config.validate()?;
        if config.max_blobs != self.config.max_blobs || config.max_labels != self.config.max_labels {
            return Err(Error::InvalidParams {
                reason: format!(
                    "max_blobs/max_labels ({}/{}) cannot change on a running tracker (is {}/{})",
                    config.max_blobs, config.max_labels, self.config.max_blobs, self.config.max_labels
                ),
            });
        }
        self.config = config;
        Ok(())
    }

    /// Blobs of `camera`'s last detection dropped by the area limits (diagnostics; a few at
    /// most, see [`BlobDetector::rejected_by_area`]).
    pub fn rejected_by_area(&self, camera: usize) -> &[Blob] {
        self.cams
            .get(camera)
            .map(|c| {
                if c.external {
                    &[]
                } else {
                    c.detector.rejected_by_area()
                }
            })
            .unwrap_or(&[])
    }

    /// The configuration in use.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// Number of cameras of the current rig.
    pub fn camera_count(&self) -> usize {
        self.cams.len()
    }

    /// All blobs of `camera`'s last detection (diagnostics; empty for a bad index).
    pub fn blobs(&self, camera: usize) -> &[Blob] {
        self.cams.get(camera).map(|c| c.blobs()).unwrap_or(&[])
    }

    /// The last measurement.
    pub fn measurement(&self) -> &Measurement {
        &self.measurement
    }

    /// Forget the tracking windows: the next frames are searched in full.
    pub fn reset_tracking(&mut self) {
        for c in &mut self.cams {
            c.last_px = None;
        }
    }

    /// Sets `camera`'s shutter, line time and time offset (config or parameter set); tracks
    /// restart. Refused with the reason when the constants are not plausible.
    pub fn set_timing(&mut self, camera: usize, timing: CameraTiming) -> Result<()> {
        timing.validate().map_err(|reason| Error::InvalidParams {
            reason: format!("camera {camera} timing: {reason}"),
        })?;
        let cam = self.cams.get_mut(camera).ok_or(Error::BadFrame {
            what: "camera index beyond the rig's camera count",
        })?;
        if cam.timing != timing {
            cam.timing = timing;
            cam.history.clear();
        }
        Ok(())
    }

    /// `camera`'s timing constants.
    pub fn timing(&self, camera: usize) -> Option<CameraTiming> {
        self.cams.get(camera).map(|c| c.timing)
    }

    /// Announces the timestamp (ns) of `camera`'s next frame; call it before that frame's
    /// detection ([`Tracker::detect_u8`], [`Tracker::set_blobs`]). The previous frame's blobs
    /// join the camera's track history. With timestamps on every camera, [`Tracker::solve`]
    /// solves the set at one instant ([`TrackerConfig::time_mode`]); without, as seen.
    /// Calling it again with the same timestamp (the same frame detected twice) changes
    /// nothing; a timestamp going backwards restarts the tracks.
    pub fn set_frame_time(&mut self, camera: usize, timestamp_ns: u64) -> Result<()> {
        let cam = self.cams.get_mut(camera).ok_or(Error::BadFrame {
            what: "camera index beyond the rig's camera count",
        })?;
        match cam.frame_ts_ns {
            Some(old) if old == timestamp_ns => return Ok(()),
            Some(old) if old < timestamp_ns => {
                let timing = cam.timing;
                let blobs = if cam.external {
                    &cam.external_blobs[..]
                } else {
                    cam.detector.blobs()
                };
                cam.history.push(blobs, |b| timing.blob_instant_ns(old, b.y_px));
            }
            _ => cam.history.clear(),
        }
        cam.frame_ts_ns = Some(timestamp_ns);
        cam.timed_active = false;
        Ok(())
    }

    /// `camera`'s blobs moved to the last solved set's instant (blobs that could not be
    /// moved are left out); the blobs as seen when the set was not retimed. For multi-LED
    /// tools, which take every blob rather than one marker.
    pub fn timed_blobs(&self, camera: usize) -> &[Blob] {
        match self.cams.get(camera) {
            Some(c) if c.timed_active => &c.timed,
            Some(c) => c.blobs(),
            None => &[],
        }
    }

    /// Brings every camera's blobs to one instant (see [`crate::retime`]) without solving for
    /// a point, for callers that use [`Tracker::timed_blobs`] (6-DOF tools); [`Tracker::solve`]
    /// does this itself. Returns the instant, `None` when the frames carry no timestamps or
    /// retiming is off.
    pub fn retime(&mut self) -> Option<f64> {
        retime_cameras(&mut self.cams, &self.config)
    }

    /// Detects blobs in one camera's 8-bit frame (in its tracking window if it has one,
    /// falling back to the full frame when the window holds no usable blob). Returns the
    /// number of usable candidate blobs.
    pub fn detect_u8(&mut self, camera: usize, image: &GrayImage<'_, u8>) -> Result<usize> {
        self.detect_impl(camera, image, true)
    }

    /// As [`Tracker::detect_u8`] for 16-bit frames (10/12/16-bit sensors; the threshold is in
    /// the frame's DN).
    pub fn detect_u16(&mut self, camera: usize, image: &GrayImage<'_, u16>) -> Result<usize> {
        self.detect_impl(camera, image, true)
    }

    /// Gives `camera` blobs found elsewhere (a camera board's observation, in the distorted
    /// image of this camera) instead of detecting them in a frame: the cluster solver's path.
    /// An empty list means the camera saw nothing or its observation did not arrive; the solve
    /// goes on with the others. Keeps at most `max_blobs` and never allocates. Returns the
    /// number of usable candidates.
    pub fn set_blobs(&mut self, camera: usize, blobs: impl IntoIterator<Item = Blob>) -> Result<usize> {
        let cfg = self.config;
        let cam = self.cams.get_mut(camera).ok_or(Error::BadFrame {
            what: "camera index beyond the rig's camera count",
        })?;
        cam.external_blobs.clear();
        let cap = cam.external_blobs.capacity();
        for b in blobs.into_iter().take(cap) {
            cam.external_blobs.push(b);
        }
        cam.external = true;
        cam.used_roi = false;
        cam.detected = true;
        Ok(cam.collect_candidates(&cfg))
    }

    /// Undistorts, triangulates and gates the blobs of the frames detected since the last
    /// call. Every camera must have been detected; otherwise the status is
    /// [`TrackStatus::MissingFrame`].
    pub fn solve(&mut self) -> &Measurement {
        self.solve_impl();
        &self.measurement
    }

    /// Solves the last solved set again with the cameras whose bit is set in `exclude_mask`
    /// left out (bit `i` = camera `i`): their blobs stay and they give no ray. The set's
    /// instant is still chosen from every camera's blobs, so the points of several solves of
    /// one set are for the same instant and can be compared. A cluster solver drops a board whose cameras disagree with the
    /// others this way. Without a complete last set (or on a detection-only tracker) the last
    /// measurement is returned unchanged. Never allocates.
    pub fn solve_excluding(&mut self, exclude_mask: u32) -> &Measurement {
        if !self.resolvable || self.detection_only {
            return &self.measurement;
        }
        let cfg = self.config;
        for (i, c) in self.cams.iter_mut().enumerate() {
            c.excluded = exclude_mask & (1u32 << i) != 0;
            c.detected = true;
            c.collect_candidates(&cfg);
        }
        self.solve_impl();
        for c in &mut self.cams {
            c.excluded = false;
        }
        &self.measurement
    }

    /// How `camera`'s current candidates agree with `point_cam0_mm` (camera-0 frame): the
    /// candidate whose ray passes closest, its ray distance and reprojection error, and its
    /// image velocity along its track. Valid after a solve (the candidates are then the
    /// set's, moved to its instant when retimed); `None` for a camera without candidates,
    /// a bad index or a point behind the camera.
    pub fn camera_residual(&self, camera: usize, point_cam0_mm: &Vector3<f64>) -> Option<CameraResidual> {
        let c = self.cams.get(camera)?;
        let (cand, ray_mm) = c
            .candidates
            .iter()
            .filter_map(|cd| ray_distance_mm(&cd.ray, point_cam0_mm).map(|d| (cd, d)))
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        let px = c.model.project(&c.cam_from_cam0.apply(point_cam0_mm)).ok()?;
        let velocity_px_s = match (c.blobs().get(cand.blob), c.frame_ts_ns) {
            (Some(b), Some(ts)) => {
                let now = TimedPoint {
                    x_px: b.x_px,
                    y_px: b.y_px,
                    t_ns: c.timing.blob_instant_ns(ts, b.y_px),
                };
                c.history
                    .velocity_px_per_ns(now, self.config.track_gate_px, self.config.max_bridge_ms * 1e6)
                    .map(|[vx, vy]| [vx * 1e9, vy * 1e9])
            }
            _ => None,
        };
        Some(CameraResidual {
            ray_mm,
            residual_px: [cand.x_px - px.x, cand.y_px - px.y],
            velocity_px_s,
        })
    }

    /// Detects and solves a complete 8-bit frame set (one frame per camera, in camera
    /// order), retrying on the full frames if the tracking windows gave no consistent point.
    pub fn process_u8(&mut self, frames: &[GrayImage<'_, u8>]) -> Result<&Measurement> {
        self.process_impl(frames)
    }

    /// As [`Tracker::process_u8`] for 16-bit frames.
    pub fn process_u16(&mut self, frames: &[GrayImage<'_, u16>]) -> Result<&Measurement> {
        self.process_impl(frames)
    }

    fn process_impl<P: Pixel>(&mut self, frames: &[GrayImage<'_, P>]) -> Result<&Measurement> {
        if frames.len() != self.cams.len() {
            return Err(Error::BadFrame {
                what: "frame set size differs from the rig's camera count",
            });
        }
        for (c, f) in frames.iter().enumerate() {
            self.detect_impl(c, f, true)?;
        }
        self.solve_impl();
        if self.measurement.status != TrackStatus::Tracked && self.cams.iter().any(|c| c.used_roi) {
            for (c, f) in frames.iter().enumerate() {
                self.detect_impl(c, f, false)?;
            }
            self.solve_impl();
        }
        Ok(&self.measurement)
    }

    fn detect_impl<P: Pixel>(
        &mut self,
        camera: usize,
        image: &GrayImage<'_, P>,
        allow_roi: bool,
    ) -> Result<usize> {
        let cfg = self.config;
        let blob_cfg = cfg.blob_config();
        let cam = self.cams.get_mut(camera).ok_or(Error::BadFrame {
            what: "camera index beyond the rig's camera count",
        })?;
        let size = cam.model.image_size;
        if image.width_px != size.width_px || image.height_px != size.height_px {
            return Err(Error::BadFrame {
                what: "frame size differs from the calibrated image size",
            });
        }
        cam.detected = false;
        cam.used_roi = false;
        cam.external = false;
        cam.candidates.clear();
        if let (true, true, Some((x, y))) = (allow_roi, cfg.roi_half_px > 0, cam.last_px) {
            let roi = Roi::around(x, y, cfg.roi_half_px, size.width_px, size.height_px);
            cam.detector.detect(image, Some(roi), &blob_cfg)?;
            if cam.collect_candidates(&cfg) > 0 {
                cam.used_roi = true;
                cam.detected = true;
                return Ok(cam.candidates.len());
            }
        }
        cam.detector.detect(image, None, &blob_cfg)?;
        cam.detected = true;
        Ok(cam.collect_candidates(&cfg))
    }

    fn solve_impl(&mut self) {
        let n = self.cams.len();
        let cfg = self.config;
        // Built in place: the measurement is ~1.5 KB, and building a copy then moving it
        // cost a noticeable share of a tracking-window frame.
        let m = &mut self.measurement;
        *m = Measurement::empty(n);
        let gated: [u32; MAX_CAMERAS] =
            core::array::from_fn(|i| self.cams.get(i).map_or(0, |c| c.candidates.len() as u32));
        m.instant_ns = if self.detection_only {
            None
        } else {
            retime_cameras(&mut self.cams, &cfg)
        };
        for (i, (o, c)) in m.cameras.iter_mut().zip(&self.cams).enumerate() {
            let st = c.stats();
            let unbridged = gated[i].saturating_sub(c.candidates.len() as u32);
            *o = CameraObservation {
                blob_count: c.blobs().len() as u32,
                candidate_count: c.candidates.len() as u32,
                dropped_blobs: st.dropped_blobs,
                used_roi: c.used_roi,
                marker: None,
                bridge_ns: 0.0,
                unbridged,
            };
        }
        if self.detection_only {
            // No calibration: the blobs are the result (a camera board's observations).
            return;
        }
        let missing = self.cams.iter().position(|c| !c.detected);
        self.resolvable = missing.is_none();
        let with_candidates = self.cams.iter().filter(|c| !c.candidates.is_empty()).count();
        let mut best: Option<Hypothesis> = None;
        if let Some(camera) = missing {
            m.status = TrackStatus::MissingFrame { camera };
        } else if with_candidates < 2 {
            let camera = self
                .cams
                .iter()
                .position(|c| c.candidates.is_empty())
                .unwrap_or(0);
            m.status = if self
                .cams
                .iter()
                .any(|c| c.candidates.is_empty() && c.stats().overloaded)
            {
                let camera = self
                    .cams
                    .iter()
                    .position(|c| c.candidates.is_empty() && c.stats().overloaded)
                    .unwrap_or(camera);
                TrackStatus::Overloaded { camera }
            } else {
                TrackStatus::NoBlob { camera }
            };
        } else {
            // Pass 1: the best hypothesis (most cameras, then smallest gap).
            let mut min_gap = f64::INFINITY;
            let mut plausible = 0usize;
            for_each_hypothesis(&self.cams, &cfg, &mut self.rays, &mut min_gap, |h| {
                plausible += 1;
                let better = match &best {
                    None => true,
                    Some(b) => h.count > b.count || (h.count == b.count && h.gap_mm < b.gap_mm),
                };
                if better {
                    best = Some(*h);
                }
            });
            m.gap_mm = min_gap;
            // Pass 2: is another, different point just as plausible? With a single
            // plausible hypothesis (the usual tracked frame) there is no other one, so the
            // pass and its triangulations are skipped.
            if let Some(b) = best
                && plausible > 1
            {
                let mut ambiguous = false;
                for_each_hypothesis(&self.cams, &cfg, &mut self.rays, &mut min_gap, |h| {
                    if h.count == b.count && (h.point_mm - b.point_mm).norm() > cfg.max_gap_mm {
                        ambiguous = true;
                    }
                });
                if ambiguous {
                    m.ambiguous = true;
                    best = None;
                }
            }
            m.status = if best.is_some() {
                TrackStatus::Tracked
            } else {
                TrackStatus::NoConsistentPair
            };
        }

        match best {
            Some(h) => {
                m.point_cam0_mm = Some(h.point_mm);
                m.gap_mm = h.gap_mm;
                m.cameras_used = h.count;
                m.quality = (1.0 - h.gap_mm / cfg.max_gap_mm).clamp(0.0, 1.0);
                for (i, c) in self.cams.iter_mut().enumerate() {
                    let member = h.members[i];
                    let blob = c
                        .candidates
                        .get(member as usize)
                        .and_then(|cd| c.blobs().get(cd.blob));
                    m.cameras[i].marker = blob.copied();
                    if let (Some(b), Some(t_ref), Some(ts)) = (blob, m.instant_ns, c.frame_ts_ns) {
                        m.cameras[i].bridge_ns = t_ref - c.timing.blob_instant_ns(ts, b.y_px);
                    }
                    m.used_roi |= blob.is_some() && c.used_roi;
                    c.last_px = blob.map(|b| (b.x_px, b.y_px));
                }
            }
            None => {
                // `reset_tracking`, spelled out: `m` still borrows `self.measurement`.
                for c in &mut self.cams {
                    c.last_px = None;
                }
            }
        }
        for c in &mut self.cams {
            c.detected = false;
        }
    }
}

impl CameraState {
    /// A camera's state with every buffer allocated for `config`.
    fn new(
        i: usize,
        model: CameraModel,
        cam_from_cam0: RigidTransform,
        config: &TrackerConfig,
    ) -> Result<Self> {
        let size = model.image_size;
        let limits = BlobLimits {
            max_width_px: size.width_px,
            max_height_px: size.height_px,
            max_labels: config.max_labels,
            max_blobs: config.max_blobs,
        };
        let detector = BlobDetector::new(limits).map_err(|e| Error::InvalidParams {
            reason: format!("camera {i}: image size {}x{}: {e}", size.width_px, size.height_px),
        })?;
        Ok(CameraState {
            detector,
            model,
            cam_from_cam0,
            candidates: Vec::with_capacity(config.max_blobs),
            external_blobs: Vec::with_capacity(config.max_blobs),
            external: false,
            last_px: None,
            used_roi: false,
            detected: false,
            timing: CameraTiming::default(),
            frame_ts_ns: None,
            history: BlobHistory::new(config.max_blobs),
            timed: Vec::with_capacity(config.max_blobs),
            timed_active: false,
            excluded: false,
        })
    }

    fn blobs(&self) -> &[Blob] {
        if self.external {
            &self.external_blobs
        } else {
            self.detector.blobs()
        }
    }

    fn stats(&self) -> crate::blob::DetectStats {
        if self.external {
            crate::blob::DetectStats::default()
        } else {
            self.detector.stats()
        }
    }

    /// Quality gate and ray for each blob of the last detection. Returns the count.
    fn collect_candidates(&mut self, cfg: &TrackerConfig) -> usize {
        self.candidates.clear();
        self.timed_active = false;
        let blobs = if self.external {
            &self.external_blobs[..]
        } else {
            self.detector.blobs()
        };
        if self.excluded {
            return 0;
        }
        for (i, b) in blobs.iter().enumerate() {
            if usable(b, cfg) && self.candidates.len() < self.candidates.capacity() {
                let ray = Ray::from_pixel(&self.model, &self.cam_from_cam0, b.x_px, b.y_px);
                self.candidates.push(Candidate {
                    blob: i,
                    ray,
                    x_px: b.x_px,
                    y_px: b.y_px,
                });
            }
        }
        self.candidates.len()
    }
}

/// Whether a blob passes the quality gate (round, not cut by a border).
fn usable(b: &Blob, cfg: &TrackerConfig) -> bool {
    b.roundness >= cfg.min_roundness
        && !(cfg.reject_edge_blobs && b.touches_frame_edge)
        && !b.touches_roi_edge
}

/// Moves every camera's blobs to one instant and rebuilds the candidates' rays from the moved
/// centroids. The instant is the earliest (accurate) or newest (low latency) exposure instant
/// among the gated blobs; `None` (nothing changed) when a camera's frame carries no timestamp,
/// retiming is off, or no camera has a gated blob.
fn retime_cameras(cams: &mut [CameraState], cfg: &TrackerConfig) -> Option<f64> {
    if cfg.time_mode == TimeMode::Off || cams.iter().any(|c| c.frame_ts_ns.is_none()) {
        return None;
    }
    let mut t_ref: Option<f64> = None;
    for c in cams.iter() {
        let Some(ts) = c.frame_ts_ns else { continue };
        // Every gated blob, an excluded camera's too: the solves of one set without one or
        // another camera are all for the same instant, so their points compare.
        for b in c
            .blobs()
            .iter()
            .filter(|b| usable(b, cfg))
            .take(c.candidates.capacity())
        {
            let t = c.timing.blob_instant_ns(ts, b.y_px);
            t_ref = Some(match (t_ref, cfg.time_mode) {
                (None, _) => t,
                (Some(r), TimeMode::LowLatency) => r.max(t),
                (Some(r), _) => r.min(t),
            });
        }
    }
    let t_ref = t_ref?;
    let max_bridge_ns = cfg.max_bridge_ms * 1e6;
    let as_seen_ns = cfg.as_seen_us * 1e3;
    for c in cams.iter_mut() {
        let Some(ts) = c.frame_ts_ns else { continue };
        c.timed.clear();
        c.candidates.clear();
        let blobs = if c.external {
            &c.external_blobs[..]
        } else {
            c.detector.blobs()
        };
        for (i, b) in blobs.iter().enumerate() {
            let now = TimedPoint {
                x_px: b.x_px,
                y_px: b.y_px,
                t_ns: c.timing.blob_instant_ns(ts, b.y_px),
            };
            let (x_px, y_px, how) = c.history.retime(
                now,
                t_ref,
                cfg.time_mode,
                cfg.track_gate_px,
                max_bridge_ns,
                as_seen_ns,
            );
            if how == Retimed::Unbridged || c.timed.len() >= c.timed.capacity() {
                continue;
            }
            c.timed.push(Blob { x_px, y_px, ..*b });
            if !c.excluded && usable(b, cfg) && c.candidates.len() < c.candidates.capacity() {
                let ray = Ray::from_pixel(&c.model, &c.cam_from_cam0, x_px, y_px);
                c.candidates.push(Candidate {
                    blob: i,
                    ray,
                    x_px,
                    y_px,
                });
            }
        }
        c.timed_active = true;
    }
    Some(t_ref)
}

/// Perpendicular distance (mm) of `p` from a ray, `None` if `p` is behind its origin.
fn ray_distance_mm(ray: &Ray, p: &Vector3<f64>) -> Option<f64> {
    let v = p - ray.origin_mm;
    let along = v.dot(&ray.dir);
    (along > 0.0).then(|| (v - ray.dir * along).norm())
}

/// Calls `f` with every plausible hypothesis: each gated camera pair, extended by the
/// nearest consistent candidate of every other camera. `min_gap` receives the smallest
/// two-view gap seen (diagnostics).
fn for_each_hypothesis(
    cams: &[CameraState],
    cfg: &TrackerConfig,
    rays: &mut Vec<Ray>,
    min_gap: &mut f64,
    mut f: impl FnMut(&Hypothesis),
) {
    let n = cams.len();
    for i in 0..n {
        for j in i + 1..n {
            for (a, ca) in cams[i].candidates.iter().enumerate() {
                for (b, cb) in cams[j].candidates.iter().enumerate() {
                    let Ok(mp) = midpoint(&ca.ray, &cb.ray) else {
                        continue;
                    };
                    *min_gap = min_gap.min(mp.gap_mm);
                    let in_range = mp
                        .range_mm
                        .iter()
                        .all(|r| (cfg.min_range_mm..=cfg.max_range_mm).contains(r));
                    if !(mp.gap_mm <= cfg.max_gap_mm && in_range) {
                        continue;
                    }
                    let mut h = Hypothesis {
                        point_mm: mp.point_mm,
                        gap_mm: mp.gap_mm,
                        members: [u8::MAX; MAX_CAMERAS],
                        count: 2,
                    };
                    h.members[i] = a as u8;
                    h.members[j] = b as u8;
                    if n > 2 {
                        extend(cams, cfg, rays, &mut h, i, j);
                    }
                    f(&h);
                }
            }
        }
    }
}

/// Adds to a two-view hypothesis the closest candidate of each other camera whose ray
/// passes within `max_gap_mm` of the point, then re-solves by least squares over all rays.
/// Falls back to the pair if the combined solution fails the gap gate.
fn extend(
    cams: &[CameraState],
    cfg: &TrackerConfig,
    rays: &mut Vec<Ray>,
    h: &mut Hypothesis,
    i: usize,
    j: usize,
) {
    let pair = *h;
    for (k, cam) in cams.iter().enumerate() {
        if k == i || k == j {
            continue;
        }
        let mut nearest: Option<(usize, f64)> = None;
        for (c, cand) in cam.candidates.iter().enumerate() {
            if let Some(d) = ray_distance_mm(&cand.ray, &h.point_mm)
                && d <= cfg.max_gap_mm
                && nearest.is_none_or(|(_, best)| d < best)
            {
                nearest = Some((c, d));
            }
        }
        if let Some((c, _)) = nearest {
            h.members[k] = c as u8;
            h.count += 1;
        }
    }
    if h.count == 2 {
        return;
    }
    // Capacity is the camera count, so this never reallocates.
    rays.clear();
    for (k, cam) in cams.iter().enumerate() {
        if let Some(c) = cam.candidates.get(h.members[k] as usize) {
            rays.push(c.ray);
        }
    }
    match least_squares_rays(rays) {
        Ok((p, rms_mm)) if 2.0 * rms_mm <= cfg.max_gap_mm => {
            h.point_mm = p;
            h.gap_mm = 2.0 * rms_mm;
        }
        _ => *h = pair,
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::blob::render::{Rng, Spot, render, to_u8, to_u16};
    use crate::camera::{Distortion, ImageSize, Intrinsics};
    use crate::params::CameraParams;
    use alloc::string::String;
    use alloc::vec;
    use nalgebra::{Matrix3, Vector2};
    use std::println;

    const W: u32 = 320;
    const H: u32 = 240;

    fn model() -> CameraModel {
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: 400.0,
                fy_px: 400.0,
                cx_px: 160.0,
                cy_px: 120.0,
            },
            distortion: Distortion {
                k1: -0.15,
                k2: 0.04,
                p1: 0.001,
                p2: -0.0005,
                k3: 0.0,
            },
            image_size: ImageSize {
                width_px: W,
                height_px: H,
            },
        }
    }

    fn rig(poses: &[RigidTransform]) -> RigParams {
        RigParams {
            rig_id: String::from("test"),
            created_unix_s: 0,
            cameras: poses
                .iter()
                .map(|p| CameraParams {
                    model: model(),
                    cam_from_cam0: *p,
                })
                .collect(),
            world_from_cam0: None,
            tools: vec![],
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }

    /// Camera at `centre_mm` (cam0 frame) looking at `target_mm`, y axis roughly down.
    fn looking_at(centre_mm: Vector3<f64>, target_mm: Vector3<f64>) -> RigidTransform {
        let z = (target_mm - centre_mm).normalize();
        let x = Vector3::new(0.0, 1.0, 0.0).cross(&z).normalize();
        let y = z.cross(&x);
        let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
        RigidTransform::from_parts(&r, &(-(r * centre_mm)))
    }

    /// Parallel stereo pair, 120 mm baseline.
    fn parallel() -> RigParams {
        let t1 = RigidTransform::from_parts(&Matrix3::identity(), &Vector3::new(-120.0, 0.0, 0.0));
        rig(&[RigidTransform::IDENTITY, t1])
    }

    /// The paper's 90° rig: camera 1 on camera 0's x axis, both looking at (0, 0, 600).
    fn orthogonal() -> RigParams {
        let target = Vector3::new(0.0, 0.0, 600.0);
        rig(&[
            RigidTransform::IDENTITY,
            looking_at(Vector3::new(600.0, 0.0, 600.0), target),
        ])
    }

    /// A marker moving at about 0.5 m/s on a smooth curve around (0, 0, 600) mm, at `t_ns`.
    fn moving_marker_mm(t_ns: f64) -> Vector3<f64> {
        let t = t_ns * 1e-9;
        Vector3::new(
            80.0 * (2.0 * t).sin(),
            60.0 * (3.1 * t + 0.4).sin(),
            600.0 + 70.0 * (2.6 * t + 1.0).cos(),
        )
    }

    /// Feeds `frames` sets of exact projections to a tracker: camera `c`'s frame `k` is stamped
    /// `k·period + phase[c]` and, with a rolling shutter, each blob is where the marker was when
    /// its row was exposed. Returns the largest error against the truth at the set's instant
    /// (or at camera 0's timestamp without one) over the sets after the first three.
    fn run_timed(rig: &RigParams, phase_ns: &[f64], timing: CameraTiming, mode: TimeMode) -> f64 {
        let config = TrackerConfig {
            time_mode: mode,
            ..TrackerConfig::default()
        };
        run_timed_with(rig, phase_ns, timing, config)
    }

    fn run_timed_with(rig: &RigParams, phase_ns: &[f64], timing: CameraTiming, config: TrackerConfig) -> f64 {
        let mut t = Tracker::new(rig, config).unwrap();
        for c in 0..rig.cameras.len() {
            t.set_timing(c, timing).unwrap();
        }
        let period_ns = 1e9 / 120.0;
        let mut worst: f64 = 0.0;
        for k in 0..40u32 {
            for (c, cam) in rig.cameras.iter().enumerate() {
                let ts = f64::from(k) * period_ns + phase_ns[c] + 1e9;
                // The row a blob lands on depends on when it was exposed: iterate.
                let mut instant = ts + timing.offset_ns as f64;
                let mut px = Vector2::zeros();
                for _ in 0..4 {
                    let p = cam.cam_from_cam0.apply(&moving_marker_mm(instant));
                    px = cam.model.project(&p).unwrap();
                    instant = timing.blob_instant_ns(ts as u64, px.y);
                }
                t.set_frame_time(c, ts as u64).unwrap();
                let blob = Blob {
                    x_px: px.x,
                    y_px: px.y,
                    area_px: 20,
                    roundness: 1.0,
                    ..Blob::default()
                };
                t.set_blobs(c, [blob]).unwrap();
            }
            let m = *t.solve();
            if k < 3 {
                continue;
            }
            let p = m.point_cam0_mm.expect("tracked");
            let at = m
                .instant_ns
                .unwrap_or(f64::from(k) * period_ns + phase_ns[0] + 1e9);
            worst = worst.max((p - moving_marker_mm(at)).norm());
        }
        worst
    }

    /// Free-running cameras (4 ms apart at 120 fps) and a rolling shutter (15 µs per row): the
    /// rays of a moving marker miss each other by millimetres when the set is solved as if
    /// exposed together; moved to one instant the error drops below a few micrometres.
    #[test]
    fn free_running_and_rolling_shutter_cameras_are_solved_at_one_instant() {
        let rig = orthogonal();
        let sync = CameraTiming::default();
        let rolling = CameraTiming {
            shutter: crate::timing::Shutter::Rolling,
            line_time_ns: 15_000,
            exposure_ns: 0,
            offset_ns: 0,
        };
        let skew = [0.0, 4.0e6];
        // Without retiming the rays do not meet (the default 3 mm gate would refuse the set),
        // so retiming off is measured with a loose gate.
        let loose = TrackerConfig {
            max_gap_mm: 50.0,
            ..TrackerConfig::default()
        };
        let off_skew = run_timed_cfg(&rig, &skew, sync, TimeMode::Off, loose);
        let acc_skew = run_timed(&rig, &skew, sync, TimeMode::Accurate);
        let low_skew = run_timed(&rig, &skew, sync, TimeMode::LowLatency);
        let off_roll = run_timed_cfg(&rig, &[0.0, 0.0], rolling, TimeMode::Off, loose);
        let acc_roll = run_timed(&rig, &[0.0, 0.0], rolling, TimeMode::Accurate);
        let acc_sync = run_timed(&rig, &[0.0, 0.0], sync, TimeMode::Accurate);
        println!(
            "skew 4 ms: off {off_skew:.4} acc {acc_skew:.5} low {low_skew:.5} mm; rolling: off \
             {off_roll:.4} acc {acc_roll:.5} mm; synchronous {acc_sync:.6} mm"
        );
        assert!(
            off_skew > 0.2 && off_roll > 0.2,
            "the skew must matter: {off_skew} {off_roll}"
        );
        assert!(acc_skew < 0.005 && acc_roll < 0.005, "{acc_skew} {acc_roll}");
        assert!(low_skew < 0.1, "{low_skew}");
        assert!(
            acc_sync < 1e-6,
            "synchronous sets are solved as before: {acc_sync}"
        );
    }

    fn run_timed_cfg(
        rig: &RigParams,
        phase_ns: &[f64],
        timing: CameraTiming,
        mode: TimeMode,
        config: TrackerConfig,
    ) -> f64 {
        run_timed_with(
            rig,
            phase_ns,
            timing,
            TrackerConfig {
                time_mode: mode,
                ..config
            },
        )
    }

    /// The cluster solver's path: blobs given per camera (no frames) triangulate like detected
    /// ones; a camera with no blobs (its board stopped) leaves the others to carry on.
    #[test]
    fn a_camera_that_disagrees_is_measured_and_can_be_left_out() {
        // Four cameras; camera 3 sees the marker 2 mm away from where the others see it (a
        // board whose frames are from another instant): its ray misses the point by more
        // than the gate, the others' residuals are ~0, and leaving out 0 and 1 leaves a
        // pair (2, 3) that agrees with itself on the other point.
        let target = Vector3::new(0.0, 0.0, 600.0);
        let r = rig(&[
            RigidTransform::IDENTITY,
            looking_at(Vector3::new(600.0, 0.0, 600.0), target),
            looking_at(Vector3::new(-600.0, 0.0, 600.0), target),
            looking_at(Vector3::new(0.0, -400.0, 300.0), target),
        ]);
        let mut t = Tracker::new(&r, TrackerConfig::default()).unwrap();
        let p = Vector3::new(10.0, -5.0, 590.0);
        let q = p + Vector3::new(8.0, 0.0, 6.0);
        let blob = |cam: usize, at: &Vector3<f64>| {
            let (x, y) = project(&r, cam, at);
            Blob {
                x_px: x,
                y_px: y,
                area_px: 9,
                peak_dn: 200,
                roundness: 1.0,
                sigma_major_px: 1.0,
                sigma_minor_px: 1.0,
                ..Blob::default()
            }
        };
        for c in 0..3 {
            t.set_blobs(c, [blob(c, &p)]).unwrap();
        }
        t.set_blobs(3, [blob(3, &q)]).unwrap();
        let m = *t.solve();
        assert_eq!((m.status, m.cameras_used), (TrackStatus::Tracked, 3));
        let point = m.point_cam0_mm.unwrap();
        assert!((point - p).norm() < 1e-6);
        for c in 0..3 {
            let res = t.camera_residual(c, &point).unwrap();
            assert!(
                res.ray_mm < 1e-6 && res.residual_px[0].abs() < 1e-6,
                "{c}: {res:?}"
            );
        }
        let res = t.camera_residual(3, &point).unwrap();
        assert!(res.ray_mm > 3.0, "{res:?}");
        let (qx, _) = project(&r, 3, &q);
        let (px, _) = project(&r, 3, &p);
        assert!((res.residual_px[0] - (qx - px)).abs() < 1e-6, "{res:?}");
        assert!(res.velocity_px_s.is_none(), "no track without timestamps");
        assert!(t.camera_residual(3, &Vector3::new(0.0, 0.0, -500.0)).is_none());
        // Cameras 0 and 1 left out: 2 alone cannot meet 3 within the gate here, so no point;
        // 0 left out: 1 and 2 still give p.
        let m = *t.solve_excluding(0b0011);
        assert!(m.point_cam0_mm.is_none() || m.cameras_used == 2, "{m:?}");
        let m = *t.solve_excluding(0b0001);
        assert_eq!(m.cameras_used, 2);
        assert!((m.point_cam0_mm.unwrap() - p).norm() < 1e-6);
        assert!(m.cameras()[0].marker.is_none() && m.cameras()[3].marker.is_none());
        // The full set again: the exclusion does not stick.
        let m = *t.solve_excluding(0);
        assert_eq!(m.cameras_used, 3);
        // With timestamps, the track gives each candidate's image velocity: camera 3's blob
        // moving 2 px per 10 ms frame in x is 200 px/s.
        let mut t = Tracker::new(&r, TrackerConfig::default()).unwrap();
        for k in 0..3u64 {
            for c in 0..4 {
                t.set_frame_time(c, 1_000_000_000 + k * 10_000_000).unwrap();
                let mut b = blob(c, &p);
                b.x_px += 2.0 * k as f64;
                t.set_blobs(c, [b]).unwrap();
            }
            t.solve();
        }
        let v = t.camera_residual(3, &p).unwrap().velocity_px_s.unwrap();
        assert!((v[0] - 200.0).abs() < 1e-6 && v[1].abs() < 1e-6, "{v:?}");
        // After a solve with a camera missing there is nothing to solve again.
        t.set_blobs(0, [blob(0, &p)]).unwrap();
        let m = *t.solve();
        assert_eq!(m.status, TrackStatus::MissingFrame { camera: 1 });
        assert_eq!(
            t.solve_excluding(0b1000).status,
            TrackStatus::MissingFrame { camera: 1 }
        );
    }

    #[test]
    fn set_blobs_triangulates_and_survives_a_missing_camera() {
        let target = Vector3::new(0.0, 0.0, 600.0);
        let r = rig(&[
            RigidTransform::IDENTITY,
            looking_at(Vector3::new(600.0, 0.0, 600.0), target),
            looking_at(Vector3::new(-600.0, 0.0, 600.0), target),
        ]);
        let mut t = Tracker::new(&r, TrackerConfig::default()).unwrap();
        let p = Vector3::new(10.0, -5.0, 590.0);
        let blob = |cam: usize| {
            let (x, y) = project(&r, cam, &p);
            Blob {
                x_px: x,
                y_px: y,
                area_px: 9,
                peak_dn: 200,
                roundness: 1.0,
                sigma_major_px: 1.0,
                sigma_minor_px: 1.0,
                ..Blob::default()
            }
        };
        for c in 0..3 {
            assert_eq!(t.set_blobs(c, [blob(c)]).unwrap(), 1);
        }
        let m = *t.solve();
        assert_eq!((m.status, m.cameras_used), (TrackStatus::Tracked, 3));
        assert!((m.point_cam0_mm.unwrap() - p).norm() < 1e-6);
        t.set_blobs(0, [blob(0)]).unwrap();
        t.set_blobs(1, [blob(1)]).unwrap();
        t.set_blobs(2, []).unwrap();
        let m = *t.solve();
        assert_eq!((m.status, m.cameras_used), (TrackStatus::Tracked, 2));
        assert!((m.point_cam0_mm.unwrap() - p).norm() < 1e-6);
        t.set_blobs(0, [blob(0)]).unwrap();
        t.set_blobs(1, []).unwrap();
        t.set_blobs(2, []).unwrap();
        assert!(
            t.solve().point_cam0_mm.is_none(),
            "one camera never gives a point"
        );
    }

    fn project(r: &RigParams, cam: usize, p: &Vector3<f64>) -> (f64, f64) {
        let c = &r.cameras[cam];
        let px = c.model.project(&c.cam_from_cam0.apply(p)).unwrap();
        (px.x, px.y)
    }

    fn led(x: f64, y: f64) -> Spot {
        Spot::round(x, y, 1.5, 190.0)
    }

    /// Renders one 8-bit frame per camera: the marker (if visible) plus extra spots.
    fn frames(
        r: &RigParams,
        marker: Option<Vector3<f64>>,
        extra: &[(usize, Spot)],
        seed: u64,
    ) -> Vec<Vec<u8>> {
        let mut rng = Rng(seed);
        (0..r.cameras.len())
            .map(|c| {
                let mut spots: Vec<Spot> = extra.iter().filter(|(k, _)| *k == c).map(|(_, s)| *s).collect();
                if let Some(p) = marker {
                    let (x, y) = project(r, c, &p);
                    spots.push(led(x, y));
                }
                to_u8(&render(W, H, &spots, 10.0, 2.0, 0.05, 255, &mut rng))
            })
            .collect()
    }

    fn views(f: &[Vec<u8>]) -> Vec<GrayImage<'_, u8>> {
        f.iter().map(|d| GrayImage::new(d, W, H, W).unwrap()).collect()
    }

    fn tracker(r: &RigParams) -> Tracker {
        Tracker::new(r, TrackerConfig::default()).unwrap()
    }

    fn assert_tracked(m: &Measurement, truth: &Vector3<f64>, tol_mm: f64) {
        assert_eq!(m.status, TrackStatus::Tracked, "{m:?}");
        let p = m.point_cam0_mm.unwrap();
        let err = (p - truth).norm();
        assert!(err < tol_mm, "error {err} mm: got {p:?}, truth {truth:?}");
        assert!(m.gap_mm <= TrackerConfig::default().max_gap_mm && m.quality > 0.0);
    }

    #[test]
    fn detection_only_finds_blobs_of_one_camera_and_never_a_point() {
        let size = ImageSize {
            width_px: W,
            height_px: H,
        };
        let mut rng = Rng(7);
        let frame = to_u8(&render(
            W,
            H,
            &[led(100.25, 80.5)],
            10.0,
            2.0,
            0.05,
            255,
            &mut rng,
        ));
        let mut t = Tracker::detection_only(&[size], TrackerConfig::default()).unwrap();
        assert!(t.is_detection_only());
        assert_eq!(t.camera_count(), 1);
        let n = t.detect_u8(0, &GrayImage::new(&frame, W, H, W).unwrap()).unwrap();
        assert_eq!(n, 1);
        let b = t.blobs(0)[0];
        assert!(
            (b.x_px - 100.25).abs() < 0.1 && (b.y_px - 80.5).abs() < 0.1,
            "{b:?}"
        );
        let m = *t.solve();
        assert!(m.point_cam0_mm.is_none(), "{m:?}");
        assert_eq!(m.cameras()[0].blob_count, 1);
        // Two uncalibrated cameras seeing the same spot still give no point.
        let mut t2 = Tracker::detection_only(&[size, size], TrackerConfig::default()).unwrap();
        for c in 0..2 {
            t2.detect_u8(c, &GrayImage::new(&frame, W, H, W).unwrap())
                .unwrap();
        }
        assert!(t2.solve().point_cam0_mm.is_none());
        // Sizes are checked as for calibrated cameras; parameters make it a full tracker.
        assert!(Tracker::detection_only(&[], TrackerConfig::default()).is_err());
        assert!(
            t.detect_u8(0, &GrayImage::new(&frame[..W as usize * 10], W, 10, W).unwrap())
                .is_err()
        );
        t2.set_params(&orthogonal()).unwrap();
        assert!(!t2.is_detection_only());
    }

    #[test]
    fn tracks_a_marker_with_parallel_and_orthogonal_rigs() {
        let mut rng = Rng(100);
        for (name, r) in [("parallel", parallel()), ("orthogonal", orthogonal())] {
            let mut t = tracker(&r);
            let mut max_err = 0.0f64;
            for i in 0..20 {
                let p = Vector3::new(
                    -60.0 + 120.0 * rng.uniform(),
                    -40.0 + 80.0 * rng.uniform(),
                    560.0 + 80.0 * rng.uniform(),
                );
                let f = frames(&r, Some(p), &[], 1000 + i);
                t.reset_tracking();
                let m = *t.process_u8(&views(&f)).unwrap();
                assert_tracked(&m, &p, 1.0);
                assert_eq!(m.cameras_used, 2);
                assert!(!m.used_roi);
                assert!(
                    m.cameras()
                        .iter()
                        .all(|c| c.marker.is_some() && c.blob_count == 1)
                );
                max_err = max_err.max((m.point_cam0_mm.unwrap() - p).norm());
            }
            println!("{name} rig: max 3-D error {max_err:.3} mm over 20 points");
        }
    }

    #[test]
    fn a_reflection_seen_by_one_camera_is_ignored() {
        let r = parallel();
        let p = Vector3::new(10.0, -5.0, 600.0);
        // A lamp in camera 0 only, far from the marker's epipolar line (different row).
        let f = frames(&r, Some(p), &[(0, Spot::round(60.0, 200.0, 2.0, 220.0))], 1);
        let mut t = tracker(&r);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_tracked(&m, &p, 1.0);
        assert_eq!(m.cameras[0].blob_count, 2);
        let (x0, y0) = project(&r, 0, &p);
        let chosen = m.cameras[0].marker.unwrap();
        assert!((chosen.x_px - x0).abs() < 0.1 && (chosen.y_px - y0).abs() < 0.1);
    }

    #[test]
    fn ambiguous_pairs_are_not_guessed() {
        let r = parallel();
        let p = Vector3::new(10.0, -5.0, 600.0);
        let (x0, y0) = project(&r, 0, &p);
        // A second spot in camera 0 on the same epipolar line (same row), 40 px further
        // left: it also pairs with camera 1's marker at a plausible depth.
        let f = frames(&r, Some(p), &[(0, led(x0 - 40.0, y0))], 2);
        let mut t = tracker(&r);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_eq!(m.status, TrackStatus::NoConsistentPair);
        assert!(m.ambiguous);
        assert!(m.point_cam0_mm.is_none());
        assert!(
            m.gap_mm < 1.0,
            "both pairs are individually plausible: {}",
            m.gap_mm
        );
    }

    #[test]
    fn inconsistent_blobs_give_no_point() {
        let r = parallel();
        // Camera 1's spot is 40 rows away from camera 0's epipolar line.
        let f = frames(&r, None, &[(0, led(150.0, 100.0)), (1, led(110.0, 140.0))], 3);
        let mut t = tracker(&r);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_eq!(m.status, TrackStatus::NoConsistentPair);
        assert!(!m.ambiguous);
        assert!(m.point_cam0_mm.is_none());
        assert!(m.gap_mm > 10.0 && m.gap_mm.is_finite(), "gap {}", m.gap_mm);
    }

    #[test]
    fn missing_blob_is_reported_per_camera() {
        let r = parallel();
        let mut t = tracker(&r);
        let f = frames(&r, None, &[(0, led(150.0, 100.0))], 4);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_eq!(m.status, TrackStatus::NoBlob { camera: 1 });
        assert!(m.point_cam0_mm.is_none());
        assert_eq!(m.gap_mm, f64::INFINITY);
        let f = frames(&r, None, &[], 5);
        assert_eq!(
            t.process_u8(&views(&f)).unwrap().status,
            TrackStatus::NoBlob { camera: 0 }
        );
        // A blob cut by the frame border is not a candidate.
        let f = frames(&r, None, &[(0, led(0.2, 100.0)), (1, led(150.0, 100.0))], 6);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_eq!(m.status, TrackStatus::NoBlob { camera: 0 });
        assert_eq!(m.cameras[0].blob_count, 1);
        assert_eq!(m.cameras[0].candidate_count, 0);
    }

    #[test]
    fn roi_tracking_and_fallback_to_full_frame() {
        let r = parallel();
        let mut t = tracker(&r);
        let p1 = Vector3::new(0.0, 0.0, 600.0);
        let m = *t.process_u8(&views(&frames(&r, Some(p1), &[], 10))).unwrap();
        assert_tracked(&m, &p1, 1.0);
        assert!(!m.used_roi);
        // Small motion: found inside the windows, same accuracy.
        let p2 = Vector3::new(3.0, -2.0, 605.0);
        let m = *t.process_u8(&views(&frames(&r, Some(p2), &[], 11))).unwrap();
        assert_tracked(&m, &p2, 1.0);
        assert!(m.used_roi && m.cameras().iter().all(|c| c.used_roi));
        // A distractor outside the windows is not even seen while tracking.
        let f = frames(&r, Some(p2), &[(0, led(20.0, 200.0))], 12);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert!(m.used_roi && m.cameras[0].blob_count == 1);
        // A jump out of the windows: full frame in the same call.
        let p3 = Vector3::new(-80.0, 40.0, 560.0);
        let m = *t.process_u8(&views(&frames(&r, Some(p3), &[], 13))).unwrap();
        assert_tracked(&m, &p3, 1.0);
        assert!(!m.used_roi);
        // The marker leaves, a reflection appears inside camera 0's window: the window
        // result is inconsistent, the full-frame retry finds the marker elsewhere.
        let (x3, y3) = project(&r, 0, &p3);
        let p4 = Vector3::new(60.0, -30.0, 620.0);
        let f = frames(&r, Some(p4), &[(0, led(x3 + 3.0, y3 - 2.0))], 14);
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_tracked(&m, &p4, 1.0);
        assert!(!m.used_roi);
        assert_eq!(m.cameras[0].blob_count, 2);
        // Loss: no point, and the next frame searches the full frame.
        let m = *t.process_u8(&views(&frames(&r, None, &[], 15))).unwrap();
        assert!(m.point_cam0_mm.is_none());
        let m = *t.process_u8(&views(&frames(&r, Some(p1), &[], 16))).unwrap();
        assert_tracked(&m, &p1, 1.0);
        assert!(!m.used_roi);
    }

    #[test]
    fn three_cameras_use_all_consistent_views_and_resolve_ambiguity() {
        let target = Vector3::new(0.0, 0.0, 600.0);
        let t1 = RigidTransform::from_parts(&Matrix3::identity(), &Vector3::new(-120.0, 0.0, 0.0));
        let t2 = looking_at(Vector3::new(0.0, -400.0, 300.0), target);
        let r = rig(&[RigidTransform::IDENTITY, t1, t2]);
        let p = Vector3::new(15.0, 10.0, 590.0);
        let mut t = tracker(&r);
        let m = *t.process_u8(&views(&frames(&r, Some(p), &[], 20))).unwrap();
        assert_tracked(&m, &p, 1.0);
        assert_eq!(m.cameras_used, 3);
        // The epipolar ghost of the parallel pair: camera 2 says which one is real.
        let (x0, y0) = project(&r, 0, &p);
        let f = frames(&r, Some(p), &[(0, led(x0 - 40.0, y0))], 21);
        t.reset_tracking();
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_tracked(&m, &p, 1.0);
        assert_eq!(m.cameras_used, 3);
        // Camera 2 loses the marker: the pair alone is ambiguous again.
        let mut f = frames(&r, Some(p), &[(0, led(x0 - 40.0, y0))], 22);
        f[2] = frames(&r, None, &[], 23).swap_remove(2);
        t.reset_tracking();
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_eq!(m.status, TrackStatus::NoConsistentPair);
        assert!(m.ambiguous);
        // Camera 1 loses it instead: cameras 0 and 2 still track.
        let mut f = frames(&r, Some(p), &[], 24);
        f[1] = frames(&r, None, &[], 25).swap_remove(1);
        t.reset_tracking();
        let m = *t.process_u8(&views(&f)).unwrap();
        assert_tracked(&m, &p, 1.5);
        assert_eq!(m.cameras_used, 2);
        assert!(m.cameras[1].marker.is_none());
    }

    #[test]
    fn sixteen_bit_frames_track() {
        let r = parallel();
        let cfg = TrackerConfig {
            threshold_dn: 160,
            ..TrackerConfig::default()
        };
        let mut t = Tracker::new(&r, cfg).unwrap();
        let p = Vector3::new(-20.0, 15.0, 640.0);
        let mut rng = Rng(30);
        let data: Vec<Vec<u16>> = (0..2)
            .map(|c| {
                let (x, y) = project(&r, c, &p);
                to_u16(&render(
                    W,
                    H,
                    &[Spot::round(x, y, 1.5, 3000.0)],
                    40.0,
                    8.0,
                    0.5,
                    4095,
                    &mut rng,
                ))
            })
            .collect();
        let v: Vec<GrayImage<'_, u16>> = data.iter().map(|d| GrayImage::new(d, W, H, W).unwrap()).collect();
        let m = *t.process_u16(&v).unwrap();
        assert_tracked(&m, &p, 1.0);
    }

    #[test]
    fn detect_and_solve_separately_and_bad_input() {
        let r = parallel();
        let mut t = tracker(&r);
        let p = Vector3::new(0.0, 0.0, 600.0);
        let f = frames(&r, Some(p), &[], 40);
        let v = views(&f);
        assert_eq!(t.detect_u8(0, &v[0]).unwrap(), 1);
        // Camera 1 not detected yet.
        assert_eq!(t.solve().status, TrackStatus::MissingFrame { camera: 1 });
        t.detect_u8(0, &v[0]).unwrap();
        t.detect_u8(1, &v[1]).unwrap();
        assert_tracked(&t.solve().clone(), &p, 1.0);
        // Solving again without new frames is a missing frame, not a stale point.
        assert_eq!(t.solve().status, TrackStatus::MissingFrame { camera: 0 });
        assert!(matches!(t.detect_u8(2, &v[0]), Err(Error::BadFrame { .. })));
        assert!(matches!(t.process_u8(&v[..1]), Err(Error::BadFrame { .. })));
        let small = vec![0u8; 100];
        let g = GrayImage::new(&small, 10, 10, 10).unwrap();
        assert!(matches!(t.detect_u8(0, &g), Err(Error::BadFrame { .. })));
        // Bad configuration and rigs.
        assert!(
            Tracker::new(
                &r,
                TrackerConfig {
                    max_gap_mm: 0.0,
                    ..TrackerConfig::default()
                }
            )
            .is_err()
        );
        assert!(
            Tracker::new(
                &r,
                TrackerConfig {
                    min_area_px: 10,
                    max_area_px: 5,
                    ..Default::default()
                }
            )
            .is_err()
        );
        let mut one = parallel();
        one.cameras.truncate(1);
        assert!(matches!(
            Tracker::new(&one, TrackerConfig::default()),
            Err(Error::InvalidParams { .. })
        ));
        // A failed swap keeps the old parameters.
        assert!(t.set_params(&one).is_err());
        assert_eq!(t.camera_count(), 2);
        assert_tracked(t.process_u8(&v).unwrap(), &p, 1.0);
    }

    #[test]
    fn hot_swap_to_a_new_image_size() {
        let r = parallel();
        let mut t = tracker(&r);
        let p = Vector3::new(0.0, 0.0, 600.0);
        assert_tracked(
            t.process_u8(&views(&frames(&r, Some(p), &[], 50))).unwrap(),
            &p,
            1.0,
        );
        // Same cameras at half resolution.
        let mut half = r.clone();
        for c in &mut half.cameras {
            let k = &mut c.model.intrinsics;
            (k.fx_px, k.fy_px, k.cx_px, k.cy_px) = (200.0, 200.0, 80.0, 60.0);
            c.model.image_size = ImageSize {
                width_px: W / 2,
                height_px: H / 2,
            };
        }
        t.set_params(&half).unwrap();
        let mut rng = Rng(51);
        let data: Vec<Vec<u8>> = (0..2)
            .map(|c| {
                let (x, y) = project(&half, c, &p);
                to_u8(&render(
                    W / 2,
                    H / 2,
                    &[led(x, y)],
                    10.0,
                    2.0,
                    0.05,
                    255,
                    &mut rng,
                ))
            })
            .collect();
        let v: Vec<GrayImage<'_, u8>> = data
            .iter()
            .map(|d| GrayImage::new(d, W / 2, H / 2, W / 2).unwrap())
            .collect();
        assert_tracked(t.process_u8(&v).unwrap(), &p, 2.0);
        // Old-size frames are now rejected.
        assert!(t.process_u8(&views(&frames(&r, Some(p), &[], 52))).is_err());
    }

    #[test]
    fn overloaded_frame_is_reported() {
        let r = parallel();
        let cfg = TrackerConfig {
            max_labels: 50,
            ..TrackerConfig::default()
        };
        let mut t = Tracker::new(&r, cfg).unwrap();
        let speckle: Vec<u8> = (0..W * H)
            .map(|i| {
                if (i % W).is_multiple_of(4) && (i / W).is_multiple_of(4) {
                    200
                } else {
                    10
                }
            })
            .collect();
        let ok = frames(&r, Some(Vector3::new(0.0, 0.0, 600.0)), &[], 60);
        let v = [
            GrayImage::new(&speckle, W, H, W).unwrap(),
            GrayImage::new(&ok[1], W, H, W).unwrap(),
        ];
        let m = *t.process_u8(&v).unwrap();
        assert_eq!(m.status, TrackStatus::Overloaded { camera: 0 });
        assert!(m.point_cam0_mm.is_none());
    }

    #[test]
    fn config_round_trips_through_serde_with_defaults() {
        let c: TrackerConfig =
            postcard::from_bytes(&postcard::to_allocvec(&TrackerConfig::default()).unwrap()).unwrap();
        assert_eq!(c, TrackerConfig::default());
    }
}
