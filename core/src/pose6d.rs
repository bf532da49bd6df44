//! 6-DOF tracking of a rigid tool carrying several LEDs (see docs/six-dof.md).
//!
//! One frame set goes through three steps, all in buffers allocated by [`PoseTracker::new`]:
//! 1. **Correspondence** ([`PointMatcher`]): every usable blob becomes a ray in the camera-0
//!    frame; every pair of rays from two cameras whose gap (length of the common
//!    perpendicular, i.e. the epipolar constraint in 3-D form) is small gives a candidate
//!    point. With more than two cameras a candidate is extended by the closest ray of every
//!    other camera that passes through it, and candidates contained in a better-confirmed
//!    one are dropped. Ghost points (LED *i* in one camera matched with LED *j* in the other
//!    because both lie on the same epipolar plane) and reflections stay in the candidate set;
//!    the next step weeds them out.
//! 2. **Identification**: an interpretation-tree search assigns candidates to the tool's
//!    LEDs such that every pairwise distance matches the layout within `distance_tol_mm`,
//!    no blob is used twice and at most one LED is missing (tools with ≥ 4 LEDs). The
//!    layout is validated up front ([`ToolModel::new`]): every wrong assignment must miss
//!    some distance by at least `min_margin_mm`, so with a tolerance below half the margin
//!    a wrong assignment of true LED points cannot pass.
//! 3. **Pose**: Horn's closed-form quaternion fit of the layout onto the assigned points;
//!    the RMS residual is the quality. If two plausible assignments disagree about the pose,
//!    the one consistent with the previous pose wins; if that does not decide, the frame is
//!    [`PoseStatus::Ambiguous`] — a swapped identification is never reported.
//!
//! [`measure_tool_layout`] builds a [`ToolDefinition`] from triangulated points of a static
//! tool, so a new tool can be measured by the tracker itself.

use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;

use nalgebra::{Matrix3, Matrix4, Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::blob::Blob;
use crate::camera::RigidTransform;
use crate::params::{RigParams, ToolDefinition};
use crate::triangulate::{Ray, least_squares_rays, midpoint};
use crate::{Error, Result};

/// Most LEDs on one tool (keeps [`Pose6d`] a fixed-size `Copy` value and the
/// identification search small).
pub const MAX_TOOL_LEDS: usize = 8;
/// Most cameras the matcher handles (same limit as the single-marker tracker).
pub const MAX_CAMERAS: usize = crate::pipeline::MAX_CAMERAS;
/// Marks "no blob from this camera" in [`TriangulatedPoint::blobs`].
pub const NO_BLOB: u8 = u8::MAX;

/// Settings of the 6-DOF tracker.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PoseConfig {
    /// Blobs with roundness (σ_minor/σ_major) below this are ignored (streaks, glints).
    pub min_roundness: f64,
    /// Ignore blobs touching the frame border (cut-off spots have biased centroids).
    pub reject_edge_blobs: bool,
    /// Blobs used per camera and frame (the detector's order: heaviest first).
    pub max_blobs_per_camera: usize,
    /// Largest ray gap (mm) of a consistent two-view pair.
    pub max_gap_mm: f64,
    /// Working range: distance (mm) along each ray from its camera to the point.
    pub min_range_mm: f64,
    pub max_range_mm: f64,
    /// Candidate 3-D points kept per frame (the smallest gaps win when there are more).
    pub max_candidates: usize,
    /// A measured LED-to-LED distance matches the layout when within this (mm).
    pub distance_tol_mm: f64,
    /// Tool validation: every wrong LED assignment must miss some distance by at least this
    /// (mm). Must be ≥ 2 × `distance_tol_mm`.
    pub min_margin_mm: f64,
    /// Tool validation: LEDs closer than this (mm) would merge into one blob.
    pub min_led_separation_mm: f64,
    /// Largest RMS residual (mm) of the layout fit for a plausible pose.
    pub max_residual_mm: f64,
    /// Accept a pose with one LED missing (tools with ≥ 4 LEDs; ≥ 3 must remain).
    pub allow_missing_led: bool,
    /// Two poses agree when they differ by less than this rotation (deg) ...
    pub agree_rotation_deg: f64,
    /// ... and their LED centroids by less than this (mm).
    pub agree_translation_mm: f64,
    /// Largest rotation (deg) between consecutive tracked frames.
    pub max_rotation_step_deg: f64,
    /// Largest move (mm) of the LED centroid between consecutive tracked frames.
    pub max_step_mm: f64,
    /// The previous pose is used for continuity for this many frames after it was seen.
    pub max_coast_frames: u32,
    /// Plausible assignments kept per frame; more makes the frame ambiguous.
    pub max_hypotheses: usize,
    /// With one LED missing, a used LED whose image lies within this distance (px) of the
    /// missing LED's predicted image in some camera may share its blob (two spots merged
    /// into one with a centroid between them, i.e. a biased point): such a pose is refused.
    /// About twice the spot radius at the threshold plus a pixel.
    pub merge_radius_px: f64,
}

impl Default for PoseConfig {
    fn default() -> Self {
        PoseConfig {
            min_roundness: 0.4,
            reject_edge_blobs: true,
            max_blobs_per_camera: 16,
            max_gap_mm: 3.0,
            min_range_mm: 50.0,
            max_range_mm: 20_000.0,
            max_candidates: 64,
            distance_tol_mm: 2.5,
            min_margin_mm: 6.0,
            min_led_separation_mm: 15.0,
            max_residual_mm: 1.5,
            allow_missing_led: true,
            agree_rotation_deg: 2.0,
            agree_translation_mm: 3.0,
            max_rotation_step_deg: 30.0,
            max_step_mm: 100.0,
            max_coast_frames: 10,
            max_hypotheses: 32,
            merge_radius_px: 6.0,
        }
    }
}

impl PoseConfig {
    /// Checks ranges and the relation between tolerance and margin.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| Err(Error::InvalidParams { reason });
        let positive = [
            ("max_gap_mm", self.max_gap_mm),
            ("distance_tol_mm", self.distance_tol_mm),
            ("min_margin_mm", self.min_margin_mm),
            ("min_led_separation_mm", self.min_led_separation_mm),
            ("max_residual_mm", self.max_residual_mm),
            ("agree_rotation_deg", self.agree_rotation_deg),
            ("agree_translation_mm", self.agree_translation_mm),
            ("max_rotation_step_deg", self.max_rotation_step_deg),
            ("max_step_mm", self.max_step_mm),
            ("merge_radius_px", self.merge_radius_px),
        ];
        for (name, v) in positive {
            if !(v > 0.0 && v.is_finite()) {
                return bad(format!("6-DOF config: {name} = {v} must be positive and finite"));
            }
        }
        if !(0.0..=1.0).contains(&self.min_roundness) {
            return bad(format!(
                "6-DOF config: min_roundness {} outside 0..=1",
                self.min_roundness
            ));
        }
        if !(self.min_range_mm >= 0.0 && self.max_range_mm > self.min_range_mm) {
            return bad(format!(
                "6-DOF config: working range {}..{} mm is empty",
                self.min_range_mm, self.max_range_mm
            ));
        }
        // A wrong assignment misses by ≥ margin; measured distances err by ≤ tol each way.
        if self.min_margin_mm < 2.0 * self.distance_tol_mm {
            return bad(format!(
                "6-DOF config: min_margin_mm {} must be at least 2 × distance_tol_mm {}",
                self.min_margin_mm, self.distance_tol_mm
            ));
        }
        if !(1..=64).contains(&self.max_blobs_per_camera)
            || !(1..=255).contains(&self.max_candidates)
            || !(1..=1024).contains(&self.max_hypotheses)
        {
            return bad(format!(
                "6-DOF config: max_blobs_per_camera {} (1..=64), max_candidates {} (1..=255) and \
                 max_hypotheses {} (1..=1024) out of range",
                self.max_blobs_per_camera, self.max_candidates, self.max_hypotheses
            ));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// Tool model and validation
// ---------------------------------------------------------------------------------------

/// A validated tool layout with its distance table.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolModel {
    name: String,
    led_count: usize,
    leds_mm: [Vector3<f64>; MAX_TOOL_LEDS],
    dist_mm: [[f64; MAX_TOOL_LEDS]; MAX_TOOL_LEDS],
    margin_mm: f64,
    min_leds: usize,
    /// The tip in the tool frame (zero, i.e. the origin, for a tool without one).
    tip_mm: Vector3<f64>,
    has_tip: bool,
}

impl ToolModel {
    /// Validates `tool`: 3..=[`MAX_TOOL_LEDS`] finite LEDs, no two closer than
    /// `min_led_separation_mm`, not collinear (also with any one LED missing, when that is
    /// allowed), and asymmetric: the identification margin (see [`ToolModel::margin_mm`])
    /// must be ≥ `min_margin_mm`. Errors name the tool and the offending LEDs.
    pub fn new(tool: &ToolDefinition, config: &PoseConfig) -> Result<Self> {
        config.validate()?;
        let n = tool.leds_mm.len();
        let bad = |reason: String| Err(Error::InvalidParams { reason });
        if !(3..=MAX_TOOL_LEDS).contains(&n) {
            return bad(format!(
                "tool {:?} has {n} LEDs; 6-DOF tracking needs 3..={MAX_TOOL_LEDS}",
                tool.name
            ));
        }
        let mut leds_mm = [Vector3::zeros(); MAX_TOOL_LEDS];
        for (i, p) in tool.leds_mm.iter().enumerate() {
            if !p.iter().all(|v| v.is_finite()) {
                return bad(format!("tool {:?}: LED {i} has a non-finite position", tool.name));
            }
            leds_mm[i] = Vector3::from(*p);
        }
        let mut dist_mm = [[0.0; MAX_TOOL_LEDS]; MAX_TOOL_LEDS];
        for i in 0..n {
            for j in 0..n {
                dist_mm[i][j] = (leds_mm[i] - leds_mm[j]).norm();
            }
        }
        for (i, row) in dist_mm.iter().enumerate().take(n) {
            for (j, &d) in row.iter().enumerate().take(n).skip(i + 1) {
                if d < config.min_led_separation_mm {
                    return bad(format!(
                        "tool {:?}: LEDs {i} and {j} are {d:.1} mm apart, below min_led_separation_mm {} \
                         (their blobs would merge)",
                        tool.name, config.min_led_separation_mm
                    ));
                }
            }
        }
        let min_leds = if config.allow_missing_led && n >= 4 {
            n - 1
        } else {
            n
        };
        // Every LED subset the tracker may fit must fix a rotation.
        let mut subset = [0usize; MAX_TOOL_LEDS];
        for skip in (0..=n).filter(|&s| s == n || min_leds < n) {
            let mut k = 0;
            for i in (0..n).filter(|&i| i != skip) {
                subset[k] = i;
                k += 1;
            }
            let off = off_line_mm(&leds_mm, &subset[..k]);
            if off < config.min_margin_mm {
                return bad(format!(
                    "tool {:?}: LEDs {:?} are (nearly) collinear ({off:.1} mm off their line, need ≥ {}); \
                     the rotation about that line would be undetermined",
                    tool.name,
                    &subset[..k],
                    config.min_margin_mm
                ));
            }
        }
        let mut model = ToolModel {
            name: tool.name.clone(),
            led_count: n,
            leds_mm,
            dist_mm,
            margin_mm: f64::INFINITY,
            min_leds,
            tip_mm: tool.tip_mm.map_or_else(Vector3::zeros, Vector3::from),
            has_tip: tool.tip_mm.is_some(),
        };
        if !model.tip_mm.iter().all(|v| v.is_finite()) {
            return bad(format!("tool {:?}: the tip has a non-finite position", tool.name));
        }
        let (margin, worst) = model.identification_margin();
        model.margin_mm = margin;
        if margin < config.min_margin_mm {
            let shown: Vec<String> = worst
                .iter()
                .take(n)
                .enumerate()
                .filter(|(_, m)| **m != NO_LED)
                .map(|(i, m)| format!("{i}→{m}"))
                .collect();
            return bad(format!(
                "tool {:?} is ambiguous: the LED assignment [{}] reproduces every distance within \
                 {margin:.2} mm (need a margin ≥ {} mm); make the layout asymmetric",
                tool.name,
                shown.join(", "),
                config.min_margin_mm
            ));
        }
        Ok(model)
    }

    /// The tool's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Number of LEDs.
    pub fn led_count(&self) -> usize {
        self.led_count
    }

    /// LED positions in the tool frame (mm).
    pub fn leds_mm(&self) -> &[Vector3<f64>] {
        &self.leds_mm[..self.led_count]
    }

    /// The tip in the tool frame (mm), if the tool has one (pivot calibration).
    pub fn tip_mm(&self) -> Option<Vector3<f64>> {
        self.has_tip.then_some(self.tip_mm)
    }

    /// Fewest LEDs a pose is computed from.
    pub fn min_leds(&self) -> usize {
        self.min_leds
    }

    /// Identification margin (mm): over every wrong assignment of the LEDs the tracker may
    /// see (all, or all but one when a missing LED is allowed) onto the tool's LEDs, the
    /// smallest "largest distance mismatch". Zero for a symmetric layout.
    pub fn margin_mm(&self) -> f64 {
        self.margin_mm
    }

    /// Exhaustive search of injective maps σ from a visible subset to the LEDs; returns the
    /// smallest max |d(i,j) − d(σi,σj)| over non-identity maps and the map reaching it.
    fn identification_margin(&self) -> (f64, [u8; MAX_TOOL_LEDS]) {
        struct Search<'a> {
            m: &'a ToolModel,
            map: [u8; MAX_TOOL_LEDS],
            best: f64,
            best_map: [u8; MAX_TOOL_LEDS],
        }
        fn rec(s: &mut Search<'_>, led: usize, missing: usize, used: u32, worst: f64) {
            let n = s.m.led_count;
            if worst >= s.best {
                return;
            }
            if led == n {
                let identity = (0..n).all(|i| s.map[i] == NO_LED || s.map[i] as usize == i);
                if !identity {
                    s.best = worst;
                    s.best_map = s.map;
                }
                return;
            }
            if n - missing > s.m.min_leds {
                s.map[led] = NO_LED;
                rec(s, led + 1, missing + 1, used, worst);
            }
            for target in 0..n {
                if used & (1 << target) != 0 {
                    continue;
                }
                let mut w = worst;
                for prev in 0..led {
                    let tp = s.map[prev];
                    if tp != NO_LED {
                        let d = libm::fabs(s.m.dist_mm[prev][led] - s.m.dist_mm[tp as usize][target]);
                        w = w.max(d);
                    }
                }
                s.map[led] = target as u8;
                rec(s, led + 1, missing, used | (1 << target), w);
            }
            s.map[led] = NO_LED;
        }
        let mut s = Search {
            m: self,
            map: [NO_LED; MAX_TOOL_LEDS],
            best: f64::INFINITY,
            best_map: [NO_LED; MAX_TOOL_LEDS],
        };
        rec(&mut s, 0, 0, 0, 0.0);
        (s.best, s.best_map)
    }
}

const NO_LED: u8 = u8::MAX;

/// Largest distance (mm) of a point of `idx` from the line through its two farthest points.
fn off_line_mm(p: &[Vector3<f64>], idx: &[usize]) -> f64 {
    let (mut a, mut b, mut dmax) = (0, 0, -1.0);
    for (k, &i) in idx.iter().enumerate() {
        for &j in &idx[k + 1..] {
            let d = (p[i] - p[j]).norm();
            if d > dmax {
                (a, b, dmax) = (i, j, d);
            }
        }
    }
    if dmax.is_nan() || dmax <= 0.0 {
        return 0.0;
    }
    let u = (p[b] - p[a]) / dmax;
    idx.iter()
        .map(|&i| {
            let v = p[i] - p[a];
            (v - u * v.dot(&u)).norm()
        })
        .fold(0.0, f64::max)
}

// ---------------------------------------------------------------------------------------
// Rigid fit (Horn's quaternion method)
// ---------------------------------------------------------------------------------------

/// Result of [`fit_rigid_horn`]: `measured ≈ R · model + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigidFit {
    /// Unit quaternion of R, (w, x, y, z) with w ≥ 0.
    pub quaternion_wxyz: [f64; 4],
    pub rotation: Matrix3<f64>,
    pub translation_mm: Vector3<f64>,
    pub rms_mm: f64,
    pub max_mm: f64,
}

/// Least-squares rigid fit of ≥ 3 point pairs without allocation (Horn 1987, closed form
/// via the 4×4 symmetric matrix; always a proper rotation). `registration::fit` solves the
/// same problem for the robot calibration but allocates and needs ≥ 4 pairs; a tool with a
/// missing LED has 3, and the per-frame path must not allocate.
/// Returns `None` for fewer than 3 pairs, mismatched lengths or (nearly) collinear points.
pub fn fit_rigid_horn(model_mm: &[Vector3<f64>], measured_mm: &[Vector3<f64>]) -> Option<RigidFit> {
    let n = model_mm.len();
    if n < 3 || measured_mm.len() != n {
        return None;
    }
    let nf = n as f64;
    let ca = model_mm.iter().sum::<Vector3<f64>>() / nf;
    let cb = measured_mm.iter().sum::<Vector3<f64>>() / nf;
    let mut s = Matrix3::zeros();
    let mut spread = 0.0;
    for (a, b) in model_mm.iter().zip(measured_mm) {
        s += (a - ca) * (b - cb).transpose();
        spread += (a - ca).norm_squared();
    }
    if spread.is_nan() || spread <= 1e-12 {
        return None;
    }
    let (sxx, sxy, sxz) = (s[(0, 0)], s[(0, 1)], s[(0, 2)]);
    let (syx, syy, syz) = (s[(1, 0)], s[(1, 1)], s[(1, 2)]);
    let (szx, szy, szz) = (s[(2, 0)], s[(2, 1)], s[(2, 2)]);
    #[rustfmt::skip]
    let nm = Matrix4::new(
        sxx + syy + szz, syz - szy,        szx - sxz,        sxy - syx,
        syz - szy,       sxx - syy - szz,  sxy + syx,        szx + sxz,
        szx - sxz,       sxy + syx,        -sxx + syy - szz, syz + szy,
        sxy - syx,       szx + sxz,        syz + szy,        -sxx - syy + szz,
    );
    let eig = nm.symmetric_eigen();
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
    // Collinear points leave a one-parameter family of rotations: the top two eigenvalues
    // coincide. Relative to the spread this is scale-free.
    let eigen_gap = l0 - l1;
    if eigen_gap.is_nan() || eigen_gap <= 1e-9 * spread {
        return None;
    }
    let v = eig.eigenvectors.column(order[0]);
    let sign = if v[0] < 0.0 { -1.0 } else { 1.0 };
    let q = UnitQuaternion::from_quaternion(Quaternion::new(
        sign * v[0],
        sign * v[1],
        sign * v[2],
        sign * v[3],
    ));
    let rotation = *q.to_rotation_matrix().matrix();
    let translation_mm = cb - rotation * ca;
    let mut sum2 = 0.0;
    let mut max_mm: f64 = 0.0;
    for (a, b) in model_mm.iter().zip(measured_mm) {
        let e = (rotation * a + translation_mm - b).norm();
        sum2 += e * e;
        max_mm = max_mm.max(e);
    }
    let rms_mm = libm::sqrt(sum2 / nf);
    if !(rms_mm.is_finite() && translation_mm.iter().all(|x| x.is_finite())) {
        return None;
    }
    Some(RigidFit {
        quaternion_wxyz: [q.w, q.i, q.j, q.k],
        rotation,
        translation_mm,
        rms_mm,
        max_mm,
    })
}

/// Angle (rad) between two unit quaternions (w, x, y, z), ignoring the sign ambiguity.
pub fn quaternion_angle_rad(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let dot = libm::fabs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]).min(1.0);
    2.0 * libm::acos(dot)
}

// ---------------------------------------------------------------------------------------
// Multi-blob correspondence
// ---------------------------------------------------------------------------------------

/// A candidate 3-D point: blobs of two or more cameras whose rays meet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulatedPoint {
    /// Camera-0 frame (mm).
    pub point_mm: Vector3<f64>,
    /// Two views: the ray gap; more: RMS distance of the rays from the point (mm).
    pub gap_mm: f64,
    /// Blob index (into the slice given for that camera) per camera, [`NO_BLOB`] if unused.
    pub blobs: [u8; MAX_CAMERAS],
    /// Number of cameras contributing.
    pub cameras: u8,
}

impl TriangulatedPoint {
    fn shares_blob(&self, other: &TriangulatedPoint) -> bool {
        self.blobs
            .iter()
            .zip(&other.blobs)
            .any(|(a, b)| *a != NO_BLOB && a == b)
    }

    /// Whether every blob of `self` is also used by `other`.
    fn is_subset_of(&self, other: &TriangulatedPoint) -> bool {
        self.blobs
            .iter()
            .zip(&other.blobs)
            .all(|(a, b)| *a == NO_BLOB || a == b)
    }
}

#[derive(Debug, Clone, Copy)]
struct BlobRay {
    blob: u8,
    ray: Ray,
}

#[derive(Debug, Clone)]
struct CameraSlot {
    model: crate::camera::CameraModel,
    cam_from_cam0: RigidTransform,
    rays: Vec<BlobRay>,
}

/// Multi-camera correspondence of many blobs by the epipolar constraint (ray gap).
#[derive(Debug, Clone)]
pub struct PointMatcher {
    config: PoseConfig,
    cams: Vec<CameraSlot>,
    points: Vec<TriangulatedPoint>,
    scratch_rays: Vec<Ray>,
    dropped: u32,
}

impl PointMatcher {
    /// Allocates every buffer for `rig` (2..=[`MAX_CAMERAS`] cameras).
    pub fn new(rig: &RigParams, config: &PoseConfig) -> Result<Self> {
        config.validate()?;
        let n = rig.cameras.len();
        if !(2..=MAX_CAMERAS).contains(&n) {
            return Err(Error::InvalidParams {
                reason: format!("rig has {n} cameras; 6-DOF tracking needs 2..={MAX_CAMERAS}"),
            });
        }
        let cams = rig
            .cameras
            .iter()
            .map(|c| CameraSlot {
                model: c.model,
                cam_from_cam0: c.cam_from_cam0,
                rays: Vec::with_capacity(config.max_blobs_per_camera),
            })
            .collect();
        Ok(PointMatcher {
            config: *config,
            cams,
            points: Vec::with_capacity(config.max_candidates),
            scratch_rays: Vec::with_capacity(n),
            dropped: 0,
        })
    }

    /// Number of cameras.
    pub fn camera_count(&self) -> usize {
        self.cams.len()
    }

    /// Candidate points of the last [`PointMatcher::solve`].
    pub fn points(&self) -> &[TriangulatedPoint] {
        &self.points
    }

    /// Candidates dropped in the last frame because `max_candidates` was reached.
    pub fn dropped(&self) -> u32 {
        self.dropped
    }

    /// Finds candidate points from one blob list per camera (camera order). Blobs with
    /// non-finite centroids, low roundness or (optionally) touching the border are skipped.
    /// Errors when the number of blob lists differs from the rig's camera count.
    pub fn solve(&mut self, blobs: &[&[Blob]]) -> Result<&[TriangulatedPoint]> {
        if blobs.len() != self.cams.len() {
            return Err(Error::BadFrame {
                what: "6-DOF: number of blob lists differs from the rig's camera count",
            });
        }
        let cfg = self.config;
        for (cam, list) in self.cams.iter_mut().zip(blobs) {
            cam.rays.clear();
            for (i, b) in list
                .iter()
                .enumerate()
                .take(cfg.max_blobs_per_camera.min(NO_BLOB as usize))
            {
                let usable = b.x_px.is_finite()
                    && b.y_px.is_finite()
                    && b.roundness >= cfg.min_roundness
                    && !(cfg.reject_edge_blobs && b.touches_frame_edge);
                if usable {
                    let ray = Ray::from_pixel(&cam.model, &cam.cam_from_cam0, b.x_px, b.y_px);
                    if ray.dir.iter().all(|v| v.is_finite()) {
                        cam.rays.push(BlobRay { blob: i as u8, ray });
                    }
                }
            }
        }
        self.points.clear();
        self.dropped = 0;
        let n = self.cams.len();
        for ca in 0..n {
            for cb in ca + 1..n {
                for ra in &self.cams[ca].rays {
                    for rb in &self.cams[cb].rays {
                        let Ok(m) = midpoint(&ra.ray, &rb.ray) else {
                            continue;
                        };
                        let in_range = m
                            .range_mm
                            .iter()
                            .all(|r| (cfg.min_range_mm..=cfg.max_range_mm).contains(r));
                        if !(m.gap_mm <= cfg.max_gap_mm && in_range) {
                            continue;
                        }
                        let mut p = TriangulatedPoint {
                            point_mm: m.point_mm,
                            gap_mm: m.gap_mm,
                            blobs: [NO_BLOB; MAX_CAMERAS],
                            cameras: 2,
                        };
                        p.blobs[ca] = ra.blob;
                        p.blobs[cb] = rb.blob;
                        if n > 2 {
                            extend_with_other_cameras(&self.cams, &cfg, &mut p, &mut self.scratch_rays);
                        }
                        insert_candidate(&mut self.points, &mut self.dropped, p);
                    }
                }
            }
        }
        Ok(&self.points)
    }
}

/// Adds the closest consistent ray of every camera not yet in `p` and re-solves the point.
fn extend_with_other_cameras(
    cams: &[CameraSlot],
    cfg: &PoseConfig,
    p: &mut TriangulatedPoint,
    rays: &mut Vec<Ray>,
) {
    for (c, cam) in cams.iter().enumerate() {
        if p.blobs[c] != NO_BLOB {
            continue;
        }
        let mut best: Option<(f64, u8)> = None;
        for br in &cam.rays {
            let v = p.point_mm - br.ray.origin_mm;
            let along = v.dot(&br.ray.dir);
            if along.is_nan() || along <= 0.0 {
                continue;
            }
            let d = (v - br.ray.dir * along).norm();
            if d <= cfg.max_gap_mm && best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, br.blob));
            }
        }
        if let Some((_, b)) = best {
            p.blobs[c] = b;
            p.cameras += 1;
        }
    }
    if p.cameras > 2 {
        rays.clear();
        for (c, cam) in cams.iter().enumerate() {
            if let Some(br) = cam.rays.iter().find(|r| r.blob == p.blobs[c]) {
                rays.push(br.ray);
            }
        }
        if let Ok((q, rms)) = least_squares_rays(rays) {
            p.point_mm = q;
            p.gap_mm = rms;
        }
    }
}

/// Inserts `p` unless an equal or better-confirmed candidate already covers its blobs;
/// removes candidates it covers. When full, the largest gap gives way.
fn insert_candidate(points: &mut Vec<TriangulatedPoint>, dropped: &mut u32, p: TriangulatedPoint) {
    if points.iter().any(|q| p.is_subset_of(q)) {
        return;
    }
    points.retain(|q| !q.is_subset_of(&p));
    if points.len() < points.capacity() {
        points.push(p);
        return;
    }
    *dropped += 1;
    let worst = points
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.gap_mm.total_cmp(&b.1.gap_mm))
        .map(|(i, q)| (i, q.gap_mm));
    if let Some((i, g)) = worst
        && p.gap_mm < g
    {
        points[i] = p;
    }
}

// ---------------------------------------------------------------------------------------
// Pose tracker
// ---------------------------------------------------------------------------------------

/// Outcome of one frame set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum PoseStatus {
    /// A unique, plausible pose was found.
    Tracked,
    /// No LED assignment with at least `needed` LEDs matches the layout; `points` candidate
    /// 3-D points were found.
    TooFewLeds { points: u32, needed: u32 },
    /// Several plausible assignments give different poses and the previous pose does not
    /// decide between them (symmetric view, ghost points): no pose rather than a swap.
    Ambiguous { hypotheses: u32 },
    /// Assignments were found but none fits the layout within `max_residual_mm`.
    ResidualTooLarge,
    /// The only plausible pose jumps further than the step limits from the previous one.
    StepTooLarge,
    /// One LED is missing and its predicted image in `camera` lies within
    /// `merge_radius_px` of LED `led`'s: the two spots probably merged into one blob whose
    /// centroid is biased, so the pose would be off by degrees.
    LedsMerged { led: u32, camera: u32 },
}

/// Full pose of the tool in the camera-0 frame: `p_cam0 = R p_tool + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose6d {
    pub status: PoseStatus,
    /// Tool origin in the camera-0 frame (mm), i.e. t.
    pub position_mm: [f64; 3],
    /// The point the tool is reported at, in the camera-0 frame (mm): its tip `R tip + t` for
    /// a tool with a tip ([`ToolDefinition::tip_mm`]), else the origin (= `position_mm`).
    pub tip_mm: [f64; 3],
    /// Orientation as a unit quaternion (w, x, y, z), w ≥ 0.
    pub quaternion_wxyz: [f64; 4],
    /// The same rotation, row-major.
    pub r_row_major: [f64; 9],
    /// RMS and largest distance (mm) between the fitted layout and the measured LEDs.
    pub residual_rms_mm: f64,
    pub residual_max_mm: f64,
    /// Number of LEDs used, and which ones (bit i = LED i).
    pub leds_used: u32,
    pub led_mask: u32,
    /// Measured LED positions (camera-0 frame, mm), valid where `led_mask` is set.
    pub leds_mm: [[f64; 3]; MAX_TOOL_LEDS],
    /// Candidate 3-D points and plausible assignments of this frame (diagnostics).
    pub candidates: u32,
    pub hypotheses: u32,
    /// The previous pose decided between disagreeing assignments.
    pub resolved_by_continuity: bool,
}

impl Pose6d {
    fn empty(status: PoseStatus) -> Self {
        Pose6d {
            status,
            position_mm: [0.0; 3],
            tip_mm: [0.0; 3],
            quaternion_wxyz: [1.0, 0.0, 0.0, 0.0],
            r_row_major: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            residual_rms_mm: 0.0,
            residual_max_mm: 0.0,
            leds_used: 0,
            led_mask: 0,
            leds_mm: [[0.0; 3]; MAX_TOOL_LEDS],
            candidates: 0,
            hypotheses: 0,
            resolved_by_continuity: false,
        }
    }

    /// The pose as reported to clients and the robot: the same orientation, the position moved
    /// to the tool's tip (unchanged for a tool without a tip). A copy, no allocation.
    pub fn at_tip(&self) -> Pose6d {
        Pose6d {
            position_mm: self.tip_mm,
            ..*self
        }
    }

    /// The pose as a rigid transform (camera-0 frame from tool frame).
    pub fn cam0_from_tool(&self) -> RigidTransform {
        RigidTransform {
            r_row_major: self.r_row_major,
            t_mm: self.position_mm,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Hypothesis {
    /// Candidate index per LED, [`NO_LED`] when missing.
    assign: [u8; MAX_TOOL_LEDS],
    count: u32,
    fit: RigidFit,
}

#[derive(Debug, Clone, Copy)]
struct Reference {
    quaternion_wxyz: [f64; 4],
    centroid_mm: Vector3<f64>,
    frames_ago: u32,
}

/// The 6-DOF tracker for one tool (see the module documentation).
#[derive(Debug, Clone)]
pub struct PoseTracker {
    config: PoseConfig,
    tool: ToolModel,
    /// Centroid of the layout in the tool frame: poses are compared where the LEDs are.
    tool_centroid_mm: Vector3<f64>,
    matcher: PointMatcher,
    hypotheses: Vec<Hypothesis>,
    overflow: bool,
    reference: Option<Reference>,
    pose: Pose6d,
}

impl PoseTracker {
    /// Validates the tool and the configuration and allocates every buffer.
    pub fn new(rig: &RigParams, tool: &ToolDefinition, config: PoseConfig) -> Result<Self> {
        let tool = ToolModel::new(tool, &config)?;
        let matcher = PointMatcher::new(rig, &config)?;
        let tool_centroid_mm = tool.leds_mm().iter().sum::<Vector3<f64>>() / tool.led_count() as f64;
        Ok(PoseTracker {
            config,
            tool,
            tool_centroid_mm,
            matcher,
            hypotheses: Vec::with_capacity(config.max_hypotheses),
            overflow: false,
            reference: None,
            pose: Pose6d::empty(PoseStatus::TooFewLeds { points: 0, needed: 3 }),
        })
    }

    /// The validated tool.
    pub fn tool(&self) -> &ToolModel {
        &self.tool
    }

    /// The configuration in use.
    pub fn config(&self) -> &PoseConfig {
        &self.config
    }

    /// The last pose.
    pub fn pose(&self) -> &Pose6d {
        &self.pose
    }

    /// Candidate 3-D points of the last frame (e.g. for [`measure_tool_layout`]).
    pub fn points(&self) -> &[TriangulatedPoint] {
        self.matcher.points()
    }

    /// Forget the previous pose (after a parameter swap or a long gap).
    pub fn reset(&mut self) {
        self.reference = None;
    }

    /// Processes one frame set: one blob list per camera, in camera order.
    pub fn process(&mut self, blobs: &[&[Blob]]) -> Result<&Pose6d> {
        self.matcher.solve(blobs)?;
        if let Some(r) = &mut self.reference {
            r.frames_ago = r.frames_ago.saturating_add(1);
            if r.frames_ago > self.config.max_coast_frames {
                self.reference = None;
            }
        }
        self.search();
        self.pose = self.decide();
        if self.pose.status == PoseStatus::Tracked {
            let r = Matrix3::from_row_slice(&self.pose.r_row_major);
            self.reference = Some(Reference {
                quaternion_wxyz: self.pose.quaternion_wxyz,
                centroid_mm: r * self.tool_centroid_mm + Vector3::from(self.pose.position_mm),
                frames_ago: 0,
            });
        }
        Ok(&self.pose)
    }

    /// Interpretation-tree search: fills `hypotheses` with every complete assignment.
    fn search(&mut self) {
        self.hypotheses.clear();
        self.overflow = false;
        let mut st = SearchState {
            tool: &self.tool,
            points: self.matcher.points(),
            tol: self.config.distance_tol_mm,
            assign: [NO_LED; MAX_TOOL_LEDS],
            out: &mut self.hypotheses,
            overflow: &mut self.overflow,
        };
        assign_rec(&mut st, 0, 0);
    }

    fn decide(&self) -> Pose6d {
        let cfg = &self.config;
        let points = self.matcher.points();
        let mut pose = Pose6d::empty(PoseStatus::ResidualTooLarge);
        pose.candidates = points.len() as u32;
        if self.hypotheses.is_empty() {
            pose.status = PoseStatus::TooFewLeds {
                points: points.len() as u32,
                needed: self.tool.min_leds as u32,
            };
            return pose;
        }
        let plausible = || {
            self.hypotheses
                .iter()
                .filter(|h| h.fit.rms_mm <= cfg.max_residual_mm)
        };
        let Some(max_count) = plausible().map(|h| h.count).max() else {
            pose.hypotheses = self.hypotheses.len() as u32;
            return pose;
        };
        let top = || plausible().filter(move |h| h.count == max_count);
        pose.hypotheses = top().count() as u32;
        if self.overflow {
            pose.status = PoseStatus::Ambiguous {
                hypotheses: self.hypotheses.len() as u32,
            };
            return pose;
        }
        let Some(best) = top().min_by(|a, b| a.fit.rms_mm.total_cmp(&b.fit.rms_mm)) else {
            return pose;
        };
        let disagreeing = top().any(|h| !self.agree(&h.fit, &best.fit));
        let chosen = if !disagreeing {
            if let Some(r) = &self.reference
                && !self.within_step(&best.fit, r)
            {
                pose.status = PoseStatus::StepTooLarge;
                return pose;
            }
            best
        } else {
            // Continuity decides only if exactly one group of agreeing hypotheses is
            // consistent with the previous pose.
            let Some(r) = &self.reference else {
                pose.status = PoseStatus::Ambiguous {
                    hypotheses: pose.hypotheses,
                };
                return pose;
            };
            let mut consistent = top().filter(|h| self.within_step(&h.fit, r));
            let Some(first) = consistent.next() else {
                pose.status = PoseStatus::Ambiguous {
                    hypotheses: pose.hypotheses,
                };
                return pose;
            };
            let mut pick = first;
            for h in consistent {
                if !self.agree(&h.fit, &first.fit) {
                    pose.status = PoseStatus::Ambiguous {
                        hypotheses: pose.hypotheses,
                    };
                    return pose;
                }
                if h.fit.rms_mm < pick.fit.rms_mm {
                    pick = h;
                }
            }
            pose.resolved_by_continuity = true;
            pick
        };
        let f = &chosen.fit;
        if let Some((led, camera)) = self.merged_with_missing(chosen) {
            pose.status = PoseStatus::LedsMerged { led, camera };
            return pose;
        }
        pose.status = PoseStatus::Tracked;
        pose.position_mm = f.translation_mm.into();
        pose.tip_mm = (f.rotation * self.tool.tip_mm + f.translation_mm).into();
        pose.quaternion_wxyz = f.quaternion_wxyz;
        for i in 0..3 {
            for j in 0..3 {
                pose.r_row_major[i * 3 + j] = f.rotation[(i, j)];
            }
        }
        pose.residual_rms_mm = f.rms_mm;
        pose.residual_max_mm = f.max_mm;
        pose.leds_used = chosen.count;
        for (led, &c) in chosen.assign.iter().enumerate().take(self.tool.led_count) {
            if let Some(p) = points.get(c as usize) {
                pose.led_mask |= 1 << led;
                pose.leds_mm[led] = p.point_mm.into();
            }
        }
        pose
    }

    /// For a pose with a missing LED: a used LED whose predicted image is within
    /// `merge_radius_px` of the missing LED's in some camera, as (led, camera).
    fn merged_with_missing(&self, h: &Hypothesis) -> Option<(u32, u32)> {
        let n = self.tool.led_count;
        let missing = (0..n).find(|&i| h.assign[i] == NO_LED)?;
        let leds = self.tool.leds_mm();
        let predict = |i: usize| h.fit.rotation * leds[i] + h.fit.translation_mm;
        let pm = predict(missing);
        for (c, cam) in self.matcher.cams.iter().enumerate() {
            let Ok(px_m) = cam.model.project(&cam.cam_from_cam0.apply(&pm)) else {
                continue;
            };
            for u in (0..n).filter(|&u| u != missing) {
                let Ok(px_u) = cam.model.project(&cam.cam_from_cam0.apply(&predict(u))) else {
                    continue;
                };
                if (px_u - px_m).norm() < self.config.merge_radius_px {
                    return Some((u as u32, c as u32));
                }
            }
        }
        None
    }

    fn centroid_of(&self, f: &RigidFit) -> Vector3<f64> {
        f.rotation * self.tool_centroid_mm + f.translation_mm
    }

    fn agree(&self, a: &RigidFit, b: &RigidFit) -> bool {
        quaternion_angle_rad(&a.quaternion_wxyz, &b.quaternion_wxyz)
            <= self.config.agree_rotation_deg.to_radians()
            && (self.centroid_of(a) - self.centroid_of(b)).norm() <= self.config.agree_translation_mm
    }

    fn within_step(&self, f: &RigidFit, r: &Reference) -> bool {
        quaternion_angle_rad(&f.quaternion_wxyz, &r.quaternion_wxyz)
            <= self.config.max_rotation_step_deg.to_radians()
            && (self.centroid_of(f) - r.centroid_mm).norm() <= self.config.max_step_mm
    }
}

struct SearchState<'a> {
    tool: &'a ToolModel,
    points: &'a [TriangulatedPoint],
    tol: f64,
    assign: [u8; MAX_TOOL_LEDS],
    out: &'a mut Vec<Hypothesis>,
    overflow: &'a mut bool,
}

fn assign_rec(st: &mut SearchState<'_>, led: usize, missing: usize) {
    let n = st.tool.led_count;
    if *st.overflow {
        return;
    }
    if led == n {
        emit_hypothesis(st);
        return;
    }
    if n - missing > st.tool.min_leds {
        st.assign[led] = NO_LED;
        assign_rec(st, led + 1, missing + 1);
    }
    for (ci, cand) in st.points.iter().enumerate().take(NO_LED as usize) {
        let ok = (0..led).all(|prev| {
            let pc = st.assign[prev];
            if pc == NO_LED {
                return true;
            }
            let other = &st.points[pc as usize];
            if pc as usize == ci || cand.shares_blob(other) {
                return false;
            }
            let d = (cand.point_mm - other.point_mm).norm();
            libm::fabs(d - st.tool.dist_mm[prev][led]) <= st.tol
        });
        if ok {
            st.assign[led] = ci as u8;
            assign_rec(st, led + 1, missing);
        }
    }
    st.assign[led] = NO_LED;
}

fn emit_hypothesis(st: &mut SearchState<'_>) {
    let mut model = [Vector3::zeros(); MAX_TOOL_LEDS];
    let mut measured = [Vector3::zeros(); MAX_TOOL_LEDS];
    let mut k = 0;
    for led in 0..st.tool.led_count {
        let c = st.assign[led];
        if c != NO_LED {
            model[k] = st.tool.leds_mm[led];
            measured[k] = st.points[c as usize].point_mm;
            k += 1;
        }
    }
    let Some(fit) = fit_rigid_horn(&model[..k], &measured[..k]) else {
        return;
    };
    if st.out.len() == st.out.capacity() {
        *st.overflow = true;
        return;
    }
    st.out.push(Hypothesis {
        assign: st.assign,
        count: k as u32,
        fit,
    });
}

// ---------------------------------------------------------------------------------------
// Measuring a tool's layout
// ---------------------------------------------------------------------------------------

/// Where the measured tool frame has its origin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum LayoutOrigin {
    /// Centroid of the LEDs.
    Centroid,
    /// LED 0 (the LED farthest from the centroid).
    FirstLed,
}

/// Result of [`measure_tool_layout`].
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredLayout {
    /// The layout in the tool frame. LED 0 is the LED farthest from the centroid, the rest
    /// follow by decreasing distance. Axes: x along the largest principal direction (LED 0
    /// on its positive side), z along the smallest (normal of a planar layout), y = z × x.
    pub tool: ToolDefinition,
    /// Where the tool frame was during the measurement (camera-0 from tool).
    pub cam0_from_tool: RigidTransform,
    /// Per LED: frames in which it was seen, and RMS scatter (mm) around its mean.
    pub observations: Vec<usize>,
    pub spread_rms_mm: Vec<f64>,
    /// Largest per-LED RMS scatter (mm).
    pub max_spread_rms_mm: f64,
    /// Identification margin of the measured layout (mm) under the config used.
    pub margin_mm: f64,
}

/// Builds a tool definition from triangulated points of a **static** tool seen in several
/// frames (copies of [`PointMatcher::points`] or [`PoseTracker::points`] per frame).
///
/// Within a frame, candidates are taken in order of increasing ray gap and a candidate
/// sharing a blob with one already taken is dropped: a ghost (LED *i* in one camera paired
/// with LED *j* in the other) shares blobs with both true points and has the larger gap.
/// Points of all frames are then clustered (radius `cluster_radius_mm`); clusters seen in at
/// least 80 % of the frames are LEDs. Exactly `expected_leds` such clusters must exist —
/// a persistent reflection or ghost gives a clear error instead of a wrong tool. The result
/// is validated like any tool ([`ToolModel::new`]) so an ambiguous layout is refused here.
pub fn measure_tool_layout(
    name: &str,
    frames: &[&[TriangulatedPoint]],
    expected_leds: usize,
    origin: LayoutOrigin,
    cluster_radius_mm: f64,
    config: &PoseConfig,
) -> Result<MeasuredLayout> {
    let bad = |reason: String| Err(Error::InvalidParams { reason });
    if frames.len() < 2 {
        return bad(format!(
            "measuring tool {name:?}: need ≥ 2 frames, got {}",
            frames.len()
        ));
    }
    if !(3..=MAX_TOOL_LEDS).contains(&expected_leds) {
        return bad(format!(
            "measuring tool {name:?}: expected_leds {expected_leds} outside 3..={MAX_TOOL_LEDS}"
        ));
    }
    if !(cluster_radius_mm > 0.0 && cluster_radius_mm.is_finite()) {
        return bad(format!(
            "measuring tool {name:?}: cluster radius {cluster_radius_mm} mm must be positive"
        ));
    }
    // (sum, count, sum of squared norms) per cluster; the running mean is the centre.
    struct Cluster {
        sum: Vector3<f64>,
        sum_sq: f64,
        count: usize,
        last_frame: usize,
    }
    let mut clusters: Vec<Cluster> = Vec::new();
    let mut taken: Vec<TriangulatedPoint> = Vec::new();
    for (fi, frame) in frames.iter().enumerate() {
        let mut by_gap: Vec<&TriangulatedPoint> = frame.iter().collect();
        by_gap.sort_by(|a, b| a.gap_mm.total_cmp(&b.gap_mm));
        taken.clear();
        for p in by_gap {
            if !taken.iter().any(|q| q.shares_blob(p)) {
                taken.push(*p);
            }
        }
        for p in &taken {
            if !p.point_mm.iter().all(|v| v.is_finite()) {
                return bad(format!(
                    "measuring tool {name:?}: frame {fi} has a non-finite point"
                ));
            }
            let v = p.point_mm;
            let near = clusters
                .iter_mut()
                .map(|c| {
                    let d = (c.sum / c.count as f64 - v).norm();
                    (d, c)
                })
                .filter(|(d, _)| *d <= cluster_radius_mm)
                .min_by(|a, b| a.0.total_cmp(&b.0));
            match near {
                Some((_, c)) if c.last_frame == fi => {
                    return bad(format!(
                        "measuring tool {name:?}: frame {fi} has two points within {cluster_radius_mm} mm of \
                         each other; LEDs too close or the cluster radius too large"
                    ));
                }
                Some((_, c)) => {
                    c.sum += v;
                    c.sum_sq += v.norm_squared();
                    c.count += 1;
                    c.last_frame = fi;
                }
                None => clusters.push(Cluster {
                    sum: v,
                    sum_sq: v.norm_squared(),
                    count: 1,
                    last_frame: fi,
                }),
            }
        }
    }
    let needed = frames.len() * 4 / 5;
    clusters.retain(|c| c.count >= needed.max(1));
    if clusters.len() != expected_leds {
        return bad(format!(
            "measuring tool {name:?}: {} points were seen in ≥ 80 % of {} frames, expected {expected_leds} LEDs \
             (remove reflections, check that every LED is visible in two cameras)",
            clusters.len(),
            frames.len()
        ));
    }
    let means: Vec<Vector3<f64>> = clusters.iter().map(|c| c.sum / c.count as f64).collect();
    let centroid = means.iter().sum::<Vector3<f64>>() / expected_leds as f64;
    let mut order: Vec<usize> = (0..expected_leds).collect();
    order.sort_by(|&a, &b| {
        (means[b] - centroid)
            .norm()
            .total_cmp(&(means[a] - centroid).norm())
    });
    let mut cov = Matrix3::zeros();
    for m in &means {
        let d = m - centroid;
        cov += d * d.transpose();
    }
    let eig = cov.symmetric_eigen();
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let mut x: Vector3<f64> = eig.eigenvectors.column(axes[0]).into();
    let mut y: Vector3<f64> = eig.eigenvectors.column(axes[1]).into();
    if (means[order[0]] - centroid).dot(&x) < 0.0 {
        x = -x;
    }
    // y sign: the LED farthest from the x axis lies on the positive side.
    let far_y = order
        .iter()
        .map(|&i| (means[i] - centroid).dot(&y))
        .max_by(|a, b| libm::fabs(*a).total_cmp(&libm::fabs(*b)))
        .unwrap_or(1.0);
    if far_y < 0.0 {
        y = -y;
    }
    let z = x.cross(&y);
    // Rows are the tool axes in camera-0 coordinates: p_tool = R_tc (p_cam0 − origin).
    let r_tool_cam0 = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let origin_cam0 = match origin {
        LayoutOrigin::Centroid => centroid,
        LayoutOrigin::FirstLed => means[order[0]],
    };
    let leds_mm: Vec<[f64; 3]> = order
        .iter()
        .map(|&i| (r_tool_cam0 * (means[i] - origin_cam0)).into())
        .collect();
    let observations: Vec<usize> = order.iter().map(|&i| clusters[i].count).collect();
    let spread_rms_mm: Vec<f64> = order
        .iter()
        .map(|&i| {
            let c = &clusters[i];
            let var = c.sum_sq / c.count as f64 - means[i].norm_squared();
            libm::sqrt(var.max(0.0))
        })
        .collect();
    let tool = ToolDefinition {
        name: name.into(),
        leds_mm,
        tip_mm: None,
    };
    let model = ToolModel::new(&tool, config)?;
    let r_cam0_tool = r_tool_cam0.transpose();
    Ok(MeasuredLayout {
        tool,
        cam0_from_tool: RigidTransform::from_parts(&r_cam0_tool, &origin_cam0),
        max_spread_rms_mm: spread_rms_mm.iter().copied().fold(0.0, f64::max),
        observations,
        spread_rms_mm,
        margin_mm: model.margin_mm(),
    })
}
