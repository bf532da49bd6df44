//! Checkerboard views in the wand calibration (`wand-calibrate --boards DIR`).
//!
//! A wand wave fixes the cameras' relative poses well but each camera's principal point and
//! focal length only weakly: they trade against the relative rotation in a flat valley of the
//! adjustment (docs/calibration.md, "Accuracy on simulated wand waves"). Checkerboard views pin
//! the intrinsics with many corners. Every view in which one camera saw the board adds that
//! board's pose *in that camera's frame* (6 free parameters) and its corners' reprojection
//! errors to the same bundle adjustment: the corners constrain only that camera's intrinsics and
//! distortion, never the rig's poses, so views need not be shared between cameras, the board's
//! printed size does not matter (a scaled board at a scaled distance looks the same) and the
//! rig's scale still comes from the wand alone.
//!
//! The folder is laid out as `calibrate` reads it (`cam0/`, `cam1/`, ... or one pattern per
//! camera) and as `capture` writes it; the detection is `calibrate`'s.

use std::path::Path;

use anyhow::{Context, Result, anyhow, bail, ensure};
use irtrack_core::camera::CameraModel;
use nalgebra::{Matrix3, Rotation3, Vector2, Vector3};
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Point3f, Vector};
use opencv::prelude::*;

use super::detect::{self, Board};
use super::input;
use super::solve::{d_mat, k_mat};

/// Fewest views with the board found a camera must have: fewer corners than this pin no
/// intrinsics better than the wand alone.
pub const MIN_BOARD_VIEWS: usize = 3;

/// The board's corners as one camera saw them in one view.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardView {
    /// Index of the camera that saw it.
    pub camera: usize,
    /// View name (file stem or the pattern's wildcard text).
    pub view: String,
    /// Corners in the board's frame (mm, z = 0), in detection order.
    pub object_mm: Vec<Vector3<f64>>,
    /// Detected corners (distorted pixels), same order.
    pub corners_px: Vec<Vector2<f64>>,
}

/// The board in one camera's frame: `x_cam = r · x_board + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardPose {
    /// Rotation from the board's frame to the camera's.
    pub r: Matrix3<f64>,
    /// Board origin in the camera's frame (mm).
    pub t_mm: Vector3<f64>,
}

impl BoardPose {
    /// The pose moved by `[ωx, ωy, ωz, dx, dy, dz]`: rotated by the rotation vector ω (rad, in
    /// the camera's frame) and shifted by d (mm).
    pub fn perturbed(&self, p: &[f64]) -> BoardPose {
        let w = Rotation3::from_scaled_axis(Vector3::new(p[0], p[1], p[2])).into_inner();
        BoardPose {
            r: w * self.r,
            t_mm: self.t_mm + Vector3::new(p[3], p[4], p[5]),
        }
    }
}

/// Board views of every camera, and the images where the board was not found.
#[derive(Debug, Clone, Default)]
pub struct BoardViews {
    /// Every view with the board found, all cameras.
    pub views: Vec<BoardView>,
    /// (camera, view) pairs without a detected board.
    pub not_found: Vec<(usize, String)>,
}

impl BoardViews {
    /// Number of views with the board found, per camera.
    pub fn per_camera(&self, n_cam: usize) -> Vec<usize> {
        let mut n = vec![0; n_cam];
        for v in &self.views {
            n[v.camera] += 1;
        }
        n
    }
}

/// Reads `dir` (layout as `calibrate --images`), detects the board in every image and checks
/// that every camera of `models` has images of the right size and at least
/// [`MIN_BOARD_VIEWS`] views with the board found. Views need not be shared between cameras.
pub fn read_board_views(
    dir: &Path,
    pattern: Option<&str>,
    board: &Board,
    models: &[CameraModel],
) -> Result<BoardViews> {
    let n_cam = models.len();
    ensure!(dir.is_dir(), "--boards {}: no such directory", dir.display());
    if pattern.is_none() {
        let present: Vec<String> = (0..64)
            .filter(|i| dir.join(format!("cam{i}")).is_dir())
            .map(|i| format!("cam{i}/"))
            .collect();
        if let Some(missing) = (0..n_cam).find(|i| !dir.join(format!("cam{i}")).is_dir()) {
            bail!(
                "--boards {}: cam{missing}/ is missing: the rig has {n_cam} cameras and every camera needs its \
                 own board views (they pin its intrinsics); the folder holds {}",
                dir.display(),
                if present.is_empty() {
                    "no cam<i>/ directories".to_string()
                } else {
                    present.join(", ")
                }
            );
        }
    }
    let set = input::discover(dir, pattern).with_context(|| format!("--boards {}", dir.display()))?;
    let labels: Vec<String> = set.cameras.iter().map(|c| c.label.clone()).collect();
    if set.cameras.len() < n_cam {
        bail!(
            "--boards {}: board views for {} camera(s) ({}), but the rig has {n_cam}: camera {} has no board \
             views; every camera needs its own (they pin its intrinsics)",
            dir.display(),
            set.cameras.len(),
            labels.join(", "),
            set.cameras.len()
        );
    }
    if set.cameras.len() > n_cam {
        bail!(
            "--boards {}: board views for {} cameras ({}), but the intrinsics describe {n_cam}",
            dir.display(),
            set.cameras.len(),
            labels.join(", ")
        );
    }
    let detections =
        detect::detect_all(&set, board).with_context(|| format!("--boards {}", dir.display()))?;
    let object_mm: Vec<Vector3<f64>> = board
        .object_points()
        .iter()
        .map(|p| Vector3::new(p.x as f64, p.y as f64, p.z as f64))
        .collect();
    let mut out = BoardViews::default();
    for (c, (det, model)) in detections.iter().zip(models).enumerate() {
        let size = model.image_size;
        ensure!(
            det.image_size == (size.width_px, size.height_px),
            "--boards {}: the images of camera {c} ({}) are {}x{} px, but its intrinsics are for {}x{} px",
            dir.display(),
            labels[c],
            det.image_size.0,
            det.image_size.1,
            size.width_px,
            size.height_px
        );
        ensure!(
            det.found.len() >= MIN_BOARD_VIEWS,
            "--boards {}: the board was found in only {} of {} images of camera {c} ({}), need at least \
             {MIN_BOARD_VIEWS}",
            dir.display(),
            det.found.len(),
            det.found.len() + det.not_found.len(),
            labels[c]
        );
        for (view, corners) in &det.found {
            out.views.push(BoardView {
                camera: c,
                view: view.clone(),
                object_mm: object_mm.clone(),
                corners_px: corners
                    .iter()
                    .map(|p| Vector2::new(p.x as f64, p.y as f64))
                    .collect(),
            });
        }
        out.not_found.extend(det.not_found.iter().map(|v| (c, v.clone())));
    }
    Ok(out)
}

/// The board's pose in its camera's frame from the corners (OpenCV `solvePnP`, iterative).
pub fn initial_board_pose(model: &CameraModel, view: &BoardView) -> Result<BoardPose> {
    let obj: Vector<Point3f> = view
        .object_mm
        .iter()
        .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
        .collect();
    let img: Vector<Point2f> = view
        .corners_px
        .iter()
        .map(|p| Point2f::new(p.x as f32, p.y as f32))
        .collect();
    let (mut rvec, mut tvec) = (Mat::default(), Mat::default());
    let ok = calib3d::solve_pnp(
        &obj,
        &img,
        &k_mat(model)?,
        &d_mat(model)?,
        &mut rvec,
        &mut tvec,
        false,
        calib3d::SOLVEPNP_ITERATIVE,
    )?;
    ensure!(
        ok,
        "camera {} board view {}: no board pose (solvePnP failed)",
        view.camera,
        view.view
    );
    let at = |m: &Mat, i: i32| -> Result<f64> {
        m.at::<f64>(i)
            .copied()
            .map_err(|e| anyhow!("solvePnP result: {}", e.message))
    };
    let w = Vector3::new(at(&rvec, 0)?, at(&rvec, 1)?, at(&rvec, 2)?);
    let t_mm = Vector3::new(at(&tvec, 0)?, at(&tvec, 1)?, at(&tvec, 2)?);
    ensure!(
        t_mm.z > 0.0,
        "camera {} board view {}: the board would be behind the camera",
        view.camera,
        view.view
    );
    Ok(BoardPose {
        r: Rotation3::from_scaled_axis(w).into_inner(),
        t_mm,
    })
}
