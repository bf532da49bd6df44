//! Limits and settings of the 6-DOF tracker ([`PoseConfig`], the `[pose]` config section).

use alloc::format;
use alloc::string::String;

use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Most LEDs on one tool (keeps [`super::Pose6d`] a fixed-size `Copy` value and the
/// identification search small).
pub const MAX_TOOL_LEDS: usize = 8;
/// Most cameras the matcher handles (same limit as the single-marker tracker).
pub const MAX_CAMERAS: usize = crate::pipeline::MAX_CAMERAS;
/// Marks "no blob from this camera" in [`super::TriangulatedPoint::blobs`].
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
    /// Far end of the working range (mm).
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
    /// Several tools: a pose from 4 or more LEDs whose RMS residual exceeds this (mm) has
    /// probably one LED biased by another tool's spot merging with it in some camera; the LED
    /// whose removal fits best is dropped when the rest then fits within this (a 3-LED pose
    /// above it is refused: it cannot tell which LED is off).
    pub outlier_residual_mm: f64,
    /// Accept a pose with LEDs missing (tools with ≥ 4 LEDs; ≥ 3 must remain).
    pub allow_missing_led: bool,
    /// With `allow_missing_led`: at most this many LEDs may be missing (poses from any 3 or
    /// more LEDs by default). Every LED subset of that size must identify the tool, so a
    /// large tool that is ambiguous from 3 of its LEDs needs a smaller value.
    pub max_missing_leds: usize,
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
    /// Loose single LEDs: a known LED takes the candidate nearest its predicted position
    /// (constant velocity) only within this distance (mm), also after a gap of up to
    /// `max_coast_frames`; farther, the candidate is a new LED with a new id. Much smaller than
    /// `max_step_mm`, so a loose LED's id does not jump to a nearby tool LED or ghost.
    pub loose_gate_mm: f64,
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
            outlier_residual_mm: 0.15,
            allow_missing_led: true,
            max_missing_leds: MAX_TOOL_LEDS,
            agree_rotation_deg: 2.0,
            agree_translation_mm: 3.0,
            max_rotation_step_deg: 30.0,
            max_step_mm: 100.0,
            max_coast_frames: 10,
            max_hypotheses: 32,
            merge_radius_px: 6.0,
            loose_gate_mm: 10.0,
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
            ("outlier_residual_mm", self.outlier_residual_mm),
            ("agree_rotation_deg", self.agree_rotation_deg),
            ("agree_translation_mm", self.agree_translation_mm),
            ("max_rotation_step_deg", self.max_rotation_step_deg),
            ("max_step_mm", self.max_step_mm),
            ("merge_radius_px", self.merge_radius_px),
            ("loose_gate_mm", self.loose_gate_mm),
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
