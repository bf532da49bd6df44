//! 6-DOF tracking of a rigid tool carrying several LEDs (see docs/six-dof.md).
//!
//! One frame set goes through three steps, all in buffers allocated by [`PoseTracker::new`]:
//! 1. **Correspondence** ([`PointMatcher`], `matching.rs`): every usable blob becomes a ray in the camera-0
//!    frame; every pair of rays from two cameras whose gap (length of the common
//!    perpendicular, i.e. the epipolar constraint in 3-D form) is small gives a candidate
//!    point. With more than two cameras a candidate is extended by the closest ray of every
//!    other camera that passes through it, and candidates contained in a better-confirmed
//!    one are dropped. Ghost points (LED *i* in one camera matched with LED *j* in the other
//!    because both lie on the same epipolar plane) and reflections stay in the candidate set;
//!    the next step weeds them out.
//! 2. **Identification** (`identify.rs`): an interpretation-tree search assigns candidates to the tool's
//!    LEDs such that every pairwise distance matches the layout within `distance_tol_mm`,
//!    no blob is used twice and at most one LED is missing (tools with ≥ 4 LEDs). The
//!    layout is validated up front ([`ToolModel::new`]): every wrong assignment must miss
//!    some distance by at least `min_margin_mm`, so with a tolerance below half the margin
//!    a wrong assignment of true LED points cannot pass.
//! 3. **Pose** (`fit.rs`, decided here): Horn's closed-form quaternion fit of the layout onto the assigned points;
//!    the RMS residual is the quality. If two plausible assignments disagree about the pose,
//!    the one consistent with the previous pose wins; if that does not decide, the frame is
//!    [`PoseStatus::Ambiguous`] — a swapped identification is never reported.
//!
//! [`measure_tool_layout`] (`measure.rs`) builds a [`ToolDefinition`] from triangulated points of a static
//! tool, so a new tool can be measured by the tracker itself.

mod config;
mod fit;
mod identify;
mod matching;
mod measure;

use alloc::vec::Vec;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::Result;
use crate::blob::Blob;
use crate::camera::RigidTransform;
use crate::params::{RigParams, ToolDefinition};

pub use config::{MAX_CAMERAS, MAX_TOOL_LEDS, NO_BLOB, PoseConfig};
pub use fit::{RigidFit, fit_rigid_horn, quaternion_angle_rad};
pub use identify::ToolModel;
use identify::{Hypothesis, NO_LED};
pub use matching::{PointMatcher, TriangulatedPoint};
pub use measure::{LayoutOrigin, MeasuredLayout, measure_tool_layout};

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
        self.overflow = identify::find_assignments(
            &self.tool,
            self.matcher.points(),
            self.config.distance_tol_mm,
            &mut self.hypotheses,
        );
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
