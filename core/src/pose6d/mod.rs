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
mod multi;

use alloc::vec::Vec;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::Result;
use crate::blob::Blob;
use crate::camera::RigidTransform;
use crate::params::{RigParams, ToolDefinition};

pub use config::{MAX_CAMERAS, MAX_TOOL_LEDS, NO_BLOB, PoseConfig};
pub use fit::{RigidFit, fit_rigid_horn, quaternion_angle_rad};
pub use identify::ToolModel;
use identify::{Hypothesis, NO_LED};
use matching::CameraSlot;
pub use matching::{PointMatcher, TriangulatedPoint};
pub use measure::{LayoutOrigin, MeasuredLayout, measure_tool_layout};
pub use multi::{LOOSE_LED, LooseLed, MAX_LOOSE_LEDS, MAX_TOOLS, MultiTracker, NO_TOOL, check_tool_set};

/// Outcome of one frame set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum PoseStatus {
    /// A unique, plausible pose was found.
    Tracked,
    /// No LED assignment with at least `needed` LEDs matches the layout; `points` candidate
    /// 3-D points were found.
    TooFewLeds {
        /// Candidate 3-D points found.
        points: u32,
        /// LEDs a pose needs.
        needed: u32,
    },
    /// Several plausible assignments give different poses and the previous pose does not
    /// decide between them (symmetric view, ghost points): no pose rather than a swap.
    Ambiguous {
        /// Plausible assignments that disagree.
        hypotheses: u32,
    },
    /// Assignments were found but none fits the layout within `max_residual_mm`.
    ResidualTooLarge,
    /// The only plausible pose jumps further than the step limits from the previous one.
    StepTooLarge,
    /// One LED is missing and its predicted image in `camera` lies within
    /// `merge_radius_px` of LED `led`'s: the two spots probably merged into one blob whose
    /// centroid is biased, so the pose would be off by degrees.
    LedsMerged {
        /// The seen LED the missing one probably merged with.
        led: u32,
        /// The camera where the two images meet.
        camera: u32,
    },
}

/// Full pose of the tool in the camera-0 frame: `p_cam0 = R p_tool + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose6d {
    /// Whether a pose was found, and why not.
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
    /// Largest of those distances (mm).
    pub residual_max_mm: f64,
    /// Number of LEDs used, and which ones (bit i = LED i).
    pub leds_used: u32,
    /// Bit i set: LED i was used.
    pub led_mask: u32,
    /// Measured LED positions (camera-0 frame, mm), valid where `led_mask` is set.
    pub leds_mm: [[f64; 3]; MAX_TOOL_LEDS],
    /// Candidate 3-D points and plausible assignments of this frame (diagnostics).
    pub candidates: u32,
    /// Plausible assignments of this frame.
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

/// The last tracked pose of a tool and its motion: the constant-velocity predictor that
/// bridges short gaps (continuity decisions and step limits use the predicted pose).
#[derive(Debug, Clone, Copy)]
struct Reference {
    quaternion_wxyz: [f64; 4],
    centroid_mm: Vector3<f64>,
    /// LED-centroid velocity (mm per frame) from the last two tracked poses.
    velocity_mm: Vector3<f64>,
    /// Rotation rate (rotation vector in the camera-0 frame, rad per frame).
    omega_rad: Vector3<f64>,
    frames_ago: u32,
}

fn unit_quaternion(q: &[f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

impl Reference {
    /// The reference after a tracked pose; the velocities come from the previous reference
    /// (zero after a loss: the predictor starts again from rest).
    fn after(prev: Option<&Reference>, quaternion_wxyz: [f64; 4], centroid_mm: Vector3<f64>) -> Self {
        let (mut velocity_mm, mut omega_rad) = (Vector3::zeros(), Vector3::zeros());
        if let Some(p) = prev
            && p.frames_ago >= 1
        {
            let k = f64::from(p.frames_ago);
            velocity_mm = (centroid_mm - p.centroid_mm) / k;
            let dq = unit_quaternion(&quaternion_wxyz) * unit_quaternion(&p.quaternion_wxyz).inverse();
            omega_rad = dq.scaled_axis() / k;
        }
        Reference {
            quaternion_wxyz,
            centroid_mm,
            velocity_mm,
            omega_rad,
            frames_ago: 0,
        }
    }

    /// Pose predicted for the current frame: (quaternion, LED centroid).
    fn predicted(&self) -> ([f64; 4], Vector3<f64>) {
        let k = f64::from(self.frames_ago);
        let q = UnitQuaternion::from_scaled_axis(self.omega_rad * k) * unit_quaternion(&self.quaternion_wxyz);
        ([q.w, q.i, q.j, q.k], self.centroid_mm + self.velocity_mm * k)
    }

    /// One more frame without a tracked pose; `false` once older than `max_coast_frames`.
    fn age(&mut self, max_coast_frames: u32) -> bool {
        self.frames_ago = self.frames_ago.saturating_add(1);
        self.frames_ago <= max_coast_frames
    }
}

/// Everything the per-tool decision needs (shared by [`PoseTracker`] and [`MultiTracker`]).
struct Decide<'a> {
    cfg: &'a PoseConfig,
    tool: &'a ToolModel,
    tool_centroid_mm: Vector3<f64>,
    points: &'a [TriangulatedPoint],
    hypotheses: &'a [Hypothesis],
    overflow: bool,
    reference: Option<&'a Reference>,
    cams: &'a [CameraSlot],
}

impl Decide<'_> {
    /// Step 4 of docs/six-dof.md: the pose and the chosen assignment (candidate per LED).
    fn run(&self) -> (Pose6d, Option<[u8; MAX_TOOL_LEDS]>) {
        let cfg = self.cfg;
        let points = self.points;
        let mut pose = Pose6d::empty(PoseStatus::ResidualTooLarge);
        pose.candidates = points.len() as u32;
        if self.hypotheses.is_empty() {
            pose.status = PoseStatus::TooFewLeds {
                points: points.len() as u32,
                needed: self.tool.min_leds as u32,
            };
            return (pose, None);
        }
        let plausible = || {
            self.hypotheses
                .iter()
                .filter(|h| h.fit.rms_mm <= cfg.max_residual_mm)
        };
        let Some(max_count) = plausible().map(|h| h.count).max() else {
            pose.hypotheses = self.hypotheses.len() as u32;
            return (pose, None);
        };
        let top = || plausible().filter(move |h| h.count == max_count);
        pose.hypotheses = top().count() as u32;
        if self.overflow {
            pose.status = PoseStatus::Ambiguous {
                hypotheses: self.hypotheses.len() as u32,
            };
            return (pose, None);
        }
        let Some(best) = top().min_by(|a, b| a.fit.rms_mm.total_cmp(&b.fit.rms_mm)) else {
            return (pose, None);
        };
        let predicted = self.reference.map(Reference::predicted);
        let disagreeing = top().any(|h| !self.agree(&h.fit, &best.fit));
        let chosen = if !disagreeing {
            if let Some(r) = &predicted
                && !self.within_step(&best.fit, r)
            {
                pose.status = PoseStatus::StepTooLarge;
                return (pose, None);
            }
            best
        } else {
            // Continuity decides only if exactly one group of agreeing hypotheses is
            // consistent with the (predicted) previous pose.
            let ambiguous = PoseStatus::Ambiguous {
                hypotheses: pose.hypotheses,
            };
            let Some(r) = &predicted else {
                pose.status = ambiguous;
                return (pose, None);
            };
            let mut consistent = top().filter(|h| self.within_step(&h.fit, r));
            let Some(first) = consistent.next() else {
                pose.status = ambiguous;
                return (pose, None);
            };
            let mut pick = first;
            for h in consistent {
                if !self.agree(&h.fit, &first.fit) {
                    pose.status = ambiguous;
                    return (pose, None);
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
            return (pose, None);
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
        (pose, Some(chosen.assign))
    }

    /// For a pose with missing LEDs: a used LED whose predicted image is within
    /// `merge_radius_px` of a missing LED's in some camera, as (led, camera).
    fn merged_with_missing(&self, h: &Hypothesis) -> Option<(u32, u32)> {
        let n = self.tool.led_count;
        let leds = self.tool.leds_mm();
        let predict = |i: usize| h.fit.rotation * leds[i] + h.fit.translation_mm;
        for missing in (0..n).filter(|&i| h.assign[i] == NO_LED) {
            let pm = predict(missing);
            for (c, cam) in self.cams.iter().enumerate() {
                let Ok(px_m) = cam.model.project(&cam.cam_from_cam0.apply(&pm)) else {
                    continue;
                };
                for u in (0..n).filter(|&u| h.assign[u] != NO_LED) {
                    let Ok(px_u) = cam.model.project(&cam.cam_from_cam0.apply(&predict(u))) else {
                        continue;
                    };
                    if (px_u - px_m).norm() < self.cfg.merge_radius_px {
                        return Some((u as u32, c as u32));
                    }
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
            <= self.cfg.agree_rotation_deg.to_radians()
            && (self.centroid_of(a) - self.centroid_of(b)).norm() <= self.cfg.agree_translation_mm
    }

    fn within_step(&self, f: &RigidFit, predicted: &([f64; 4], Vector3<f64>)) -> bool {
        quaternion_angle_rad(&f.quaternion_wxyz, &predicted.0) <= self.cfg.max_rotation_step_deg.to_radians()
            && (self.centroid_of(f) - predicted.1).norm() <= self.cfg.max_step_mm
    }
}

/// Centroid of a pose's LED layout (camera-0 frame).
fn layout_centroid(pose: &Pose6d, tool_centroid_mm: &Vector3<f64>) -> Vector3<f64> {
    let r = nalgebra::Matrix3::from_row_slice(&pose.r_row_major);
    r * tool_centroid_mm + Vector3::from(pose.position_mm)
}

/// The 6-DOF tracker for one tool (see the module documentation; [`MultiTracker`] tracks
/// several tools and loose LEDs in one frame set).
#[derive(Debug, Clone)]
pub struct PoseTracker {
    config: PoseConfig,
    tool: ToolModel,
    /// Centroid of the layout in the tool frame: poses are compared where the LEDs are.
    tool_centroid_mm: Vector3<f64>,
    matcher: PointMatcher,
    hypotheses: Vec<Hypothesis>,
    reference: Option<Reference>,
    pose: Pose6d,
}

impl PoseTracker {
    /// Validates the tool and the configuration and allocates every buffer.
    pub fn new(rig: &RigParams, tool: &ToolDefinition, config: PoseConfig) -> Result<Self> {
        let tool = ToolModel::new(tool, &config)?;
        let matcher = PointMatcher::new(rig, &config)?;
        let tool_centroid_mm = tool.centroid_mm();
        Ok(PoseTracker {
            config,
            tool,
            tool_centroid_mm,
            matcher,
            hypotheses: Vec::with_capacity(config.max_hypotheses),
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
        if let Some(r) = &mut self.reference
            && !r.age(self.config.max_coast_frames)
        {
            self.reference = None;
        }
        let overflow = identify::find_assignments(
            &self.tool,
            self.matcher.points(),
            self.config.distance_tol_mm,
            &mut self.hypotheses,
        );
        let (pose, _) = Decide {
            cfg: &self.config,
            tool: &self.tool,
            tool_centroid_mm: self.tool_centroid_mm,
            points: self.matcher.points(),
            hypotheses: &self.hypotheses,
            overflow,
            reference: self.reference.as_ref(),
            cams: &self.matcher.cams,
        }
        .run();
        self.pose = pose;
        if self.pose.status == PoseStatus::Tracked {
            self.reference = Some(Reference::after(
                self.reference.as_ref(),
                self.pose.quaternion_wxyz,
                layout_centroid(&self.pose, &self.tool_centroid_mm),
            ));
        }
        Ok(&self.pose)
    }
}
