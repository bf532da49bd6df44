//! Camera-rig calibration from chessboard images (behind `host-tools calibrate`).
//!
//! Pipeline: [`input::discover`] pairs image files into views, [`detect::detect_all`] finds the
//! board (OpenCV `findChessboardCorners` + `cornerSubPix`), [`calibrate`] fits each camera's
//! intrinsics with `calibrateCamera` on every view that camera saw, then each camera's pose
//! relative to camera 0 with `stereoCalibrate` (intrinsics fixed; optionally a joint refinement)
//! on the views every camera saw, rejecting outlier views if asked. [`report`] and [`plots`] turn
//! the result into report.md and PNGs.

pub mod board_quality;
pub mod detect;
pub mod input;
pub mod plots;
pub mod quality;
pub mod report;
pub mod solve;
pub mod wand;
pub mod wand_boards;
pub mod wand_quality;
pub mod wand_report;
pub mod wand_solve;
pub mod wand_time;

use std::collections::BTreeSet;

use anyhow::{Result, bail};
use irtrack_core::camera::RigidTransform;
use irtrack_core::params::{CameraParams, RigParams};

use detect::{Board, CameraDetections};
use input::ImageSet;
use solve::{IntrinsicFit, PairFit};

/// Fewest views (board found in every camera) a calibration accepts.
pub const MIN_VIEWS: usize = 4;
/// Fewer views than this still calibrate but the report warns.
pub const RECOMMENDED_VIEWS: usize = 10;
/// Rounds of outlier rejection (each followed by recalibration).
const MAX_REJECTION_ROUNDS: usize = 3;

/// Calibration options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Options {
    /// Reject views whose per-view RMS is an outlier, then recalibrate (`--reject-outliers`).
    pub reject_outliers: bool,
    /// Outlier rule factor k in median + k·1.4826·MAD.
    pub outlier_k: f64,
    /// After the fixed-intrinsics stereo fits, refine intrinsics and poses jointly
    /// (`--joint-refine`).
    pub joint_refine: bool,
    /// Keep k3 at 0 in the intrinsic fits (`--fix-k3`).
    pub fix_k3: bool,
}

/// Why a view was not used.
#[derive(Debug, Clone, PartialEq)]
pub enum SkipReason {
    /// No image for these cameras.
    MissingImage(Vec<usize>),
    /// The board was not found in these cameras' images.
    BoardNotFound(Vec<usize>),
}

impl std::fmt::Display for SkipReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (what, cams) = match self {
            SkipReason::MissingImage(c) => ("no image in", c),
            SkipReason::BoardNotFound(c) => ("board not found in", c),
        };
        let list: Vec<String> = cams.iter().map(|c| format!("cam{c}")).collect();
        write!(f, "{what} {}", list.join(", "))
    }
}

/// A view rejected as an outlier.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejection {
    /// Name of the rejected view.
    pub view: String,
    /// Rejection round that dropped it (1 = first).
    pub round: usize,
    /// What exceeded its threshold, e.g. "cam1 0.83 px > 0.31 px".
    pub why: String,
    /// The view's RMS in each camera's fit of the round that rejected it.
    pub per_camera_rms_px: Vec<Option<f64>>,
}

/// Everything a calibration produced.
#[derive(Debug, Clone)]
pub struct Calibration {
    /// The board geometry used.
    pub board: Board,
    /// How each camera's images were selected (`cam1/` or `right*.png`), for the report.
    pub camera_labels: Vec<String>,
    /// Corner detections per camera, camera 0 first.
    pub detections: Vec<CameraDetections>,
    /// Views found in every camera and kept.
    pub stereo_views: Vec<String>,
    /// Views left out before fitting (missing image or board not found), with the reason.
    pub skipped: Vec<(String, SkipReason)>,
    /// Views rejected as outliers, in rejection order.
    pub rejected: Vec<Rejection>,
    /// Per-camera intrinsic fits (after rejection).
    pub intrinsics: Vec<IntrinsicFit>,
    /// `pairs[i-1]`: camera i against camera 0 (after rejection, with fixed intrinsics).
    pub pairs: Vec<PairFit>,
    /// `joint[i-1]`: the joint refinement of camera i against camera 0, if requested.
    pub joint: Vec<PairFit>,
    /// Per-camera outlier thresholds used in the last round (intrinsic per-view RMS).
    pub thresholds_px: Vec<Option<f64>>,
    /// The options the calibration ran with.
    pub options: Options,
    /// The resulting rig parameters (what goes into the parameter blob).
    pub rig: RigParams,
}

fn check_board_found(set: &ImageSet, det: &[CameraDetections], board: &Board) -> Result<()> {
    for (ci, d) in det.iter().enumerate() {
        if d.found.is_empty() {
            bail!(
                "the {}x{} board (inner corners) was found in none of the {} images of camera {ci} ({}). \
                 Check --board-cols/--board-rows: they count inner corners (squares per row minus one), \
                 and the whole board with a white border must be in view",
                board.cols,
                board.rows,
                d.not_found.len(),
                set.cameras[ci].label
            );
        }
    }
    Ok(())
}

/// Runs the calibration on detected corners. `rig_id` and `created_unix_s` go into the result.
pub fn calibrate(
    set: &ImageSet,
    det: Vec<CameraDetections>,
    board: Board,
    options: Options,
    rig_id: &str,
    created_unix_s: u64,
) -> Result<Calibration> {
    check_board_found(set, &det, &board)?;
    let n_cam = det.len();
    let mut skipped: Vec<(String, SkipReason)> = set
        .incomplete_views
        .iter()
        .map(|(v, m)| (v.clone(), SkipReason::MissingImage(m.clone())))
        .collect();
    let mut stereo_views = Vec::new();
    for v in &set.complete_views {
        let not_found: Vec<usize> = (0..n_cam).filter(|&c| !det[c].found.contains_key(v)).collect();
        if not_found.is_empty() {
            stereo_views.push(v.clone());
        } else {
            skipped.push((v.clone(), SkipReason::BoardNotFound(not_found)));
        }
    }
    skipped.sort_by(|a, b| a.0.cmp(&b.0));
    if stereo_views.len() < MIN_VIEWS {
        let per_cam: Vec<String> = det
            .iter()
            .enumerate()
            .map(|(ci, d)| format!("cam{ci} {}/{}", d.found.len(), d.found.len() + d.not_found.len()))
            .collect();
        bail!(
            "too few views: need at least {MIN_VIEWS} views with the board found in every camera (10–20 \
             recommended), found {} of {} (board found per camera: {})",
            stereo_views.len(),
            set.complete_views.len() + set.incomplete_views.len(),
            per_cam.join(", ")
        );
    }

    let mut rejected_set: BTreeSet<String> = BTreeSet::new();
    let mut rejected = Vec::new();
    let mut round = 0;
    let (intrinsics, pairs, thresholds_px) = loop {
        let intrinsics: Vec<IntrinsicFit> = det
            .iter()
            .map(|d| {
                let views: Vec<String> = d
                    .found
                    .keys()
                    .filter(|v| !rejected_set.contains(*v))
                    .cloned()
                    .collect();
                solve::calibrate_intrinsics(&board, &d.found, &views, d.image_size, options.fix_k3)
            })
            .collect::<Result<_>>()?;
        let views: Vec<String> = stereo_views
            .iter()
            .filter(|v| !rejected_set.contains(*v))
            .cloned()
            .collect();
        let pairs: Vec<PairFit> = (1..n_cam)
            .map(|i| {
                solve::calibrate_pair(
                    &board,
                    &intrinsics[0].model,
                    &intrinsics[i].model,
                    &det[0].found,
                    &det[i].found,
                    &views,
                    false,
                )
            })
            .collect::<Result<_>>()?;
        if !options.reject_outliers {
            break (intrinsics, pairs, vec![None; n_cam]);
        }
        let thresholds: Vec<f64> = intrinsics
            .iter()
            .map(|f| {
                solve::outlier_threshold(
                    &f.per_view_rms_px.values().copied().collect::<Vec<_>>(),
                    options.outlier_k,
                )
            })
            .collect();
        let mut new: Vec<Rejection> = Vec::new();
        let mut flag = |view: &String, why: String| {
            if let Some(r) = new.iter_mut().find(|r| &r.view == view) {
                r.why.push_str(&format!("; {why}"));
            } else {
                let per_camera_rms_px = intrinsics
                    .iter()
                    .map(|f| f.per_view_rms_px.get(view).copied())
                    .collect();
                new.push(Rejection {
                    view: view.clone(),
                    round: round + 1,
                    why,
                    per_camera_rms_px,
                });
            }
        };
        for (ci, f) in intrinsics.iter().enumerate() {
            for (v, e) in &f.per_view_rms_px {
                if *e > thresholds[ci] {
                    flag(v, format!("cam{ci} {e:.3} px > {:.3} px", thresholds[ci]));
                }
            }
        }
        for (pi, p) in pairs.iter().enumerate() {
            let errs: Vec<f64> = p
                .per_view_rms_px
                .values()
                .flat_map(|e| e.iter().copied())
                .collect();
            let th = solve::outlier_threshold(&errs, options.outlier_k);
            for (v, e) in &p.per_view_rms_px {
                let worst = e[0].max(e[1]);
                if worst > th {
                    flag(v, format!("stereo cam0–cam{} {worst:.3} px > {th:.3} px", pi + 1));
                }
            }
        }
        let remaining = views
            .iter()
            .filter(|v| !new.iter().any(|r| &r.view == *v))
            .count();
        if new.is_empty() || round + 1 > MAX_REJECTION_ROUNDS || remaining < MIN_VIEWS {
            break (intrinsics, pairs, thresholds.into_iter().map(Some).collect());
        }
        for r in new {
            rejected_set.insert(r.view.clone());
            rejected.push(r);
        }
        round += 1;
    };

    let views: Vec<String> = stereo_views
        .iter()
        .filter(|v| !rejected_set.contains(*v))
        .cloned()
        .collect();
    let joint: Vec<PairFit> = if options.joint_refine {
        (1..n_cam)
            .map(|i| {
                solve::calibrate_pair(
                    &board,
                    &intrinsics[0].model,
                    &intrinsics[i].model,
                    &det[0].found,
                    &det[i].found,
                    &views,
                    true,
                )
            })
            .collect::<Result<_>>()?
    } else {
        Vec::new()
    };

    // Final parameters: fixed-intrinsic stereo, or the joint refinement (camera 0's refined
    // intrinsics come from its pair with camera 1; the report lists every pair's value).
    let mut cameras = Vec::with_capacity(n_cam);
    for i in 0..n_cam {
        let (model, pose) = match (i, joint.is_empty()) {
            (0, true) => (intrinsics[0].model, RigidTransform::IDENTITY),
            (0, false) => (
                joint[0].refined.map_or(intrinsics[0].model, |m| m[0]),
                RigidTransform::IDENTITY,
            ),
            (i, true) => (intrinsics[i].model, pairs[i - 1].cam_from_cam0),
            (i, false) => (
                joint[i - 1].refined.map_or(intrinsics[i].model, |m| m[1]),
                joint[i - 1].cam_from_cam0,
            ),
        };
        cameras.push(CameraParams {
            model,
            cam_from_cam0: pose,
        });
    }
    let rig = RigParams {
        rig_id: rig_id.to_string(),
        created_unix_s,
        cameras,
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    };
    rig.validate()
        .map_err(|e| anyhow::anyhow!("calibration produced unusable parameters: {e}"))?;
    let stereo_views: Vec<String> = views;
    Ok(Calibration {
        board,
        camera_labels: set.cameras.iter().map(|c| c.label.clone()).collect(),
        detections: det,
        stereo_views,
        skipped,
        rejected,
        intrinsics,
        pairs,
        joint,
        thresholds_px,
        options,
        rig,
    })
}
