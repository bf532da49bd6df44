//! OpenCV calibration calls: per-camera `calibrateCamera`, pairwise `stereoCalibrate` against
//! camera 0, and the outlier rule for per-view errors.

use std::collections::BTreeMap;

use anyhow::{Context, Result, bail};
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use nalgebra::{Matrix3, Vector3};
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::prelude::*;

use super::detect::Board;

/// Result of one camera's `calibrateCamera`.
#[derive(Debug, Clone)]
pub struct IntrinsicFit {
    /// Fitted intrinsics and distortion.
    pub model: CameraModel,
    /// Overall RMS reprojection error (px) as `calibrateCamera` reports it.
    pub rms_px: f64,
    /// RMS reprojection error of every view used.
    pub per_view_rms_px: BTreeMap<String, f64>,
    /// Corners used in the fit (views × corners per board); weights the cameras' RMS in the report.
    pub corner_count: usize,
}

/// Result of `stereoCalibrate` of camera `i` against camera 0.
#[derive(Debug, Clone)]
pub struct PairFit {
    /// `x_cam_i = R x_cam0 + t`.
    pub cam_from_cam0: RigidTransform,
    /// Overall RMS reprojection error of the stereo fit (px), over both cameras.
    pub rms_px: f64,
    /// Per view: RMS in camera 0 and in camera i.
    pub per_view_rms_px: BTreeMap<String, [f64; 2]>,
    /// With joint refinement: the refined models of camera 0 and camera i.
    pub refined: Option<[CameraModel; 2]>,
}

fn criteria() -> Result<TermCriteria> {
    // More iterations and a tighter tolerance than OpenCV's defaults (30, DBL_EPSILON):
    // Levenberg–Marquardt stops on its own once converged.
    Ok(TermCriteria::new(
        TermCriteria_Type::COUNT as i32 | TermCriteria_Type::EPS as i32,
        200,
        1e-12,
    )?)
}

pub(crate) fn k_mat(m: &CameraModel) -> Result<Mat> {
    let k = m.intrinsics.matrix();
    Ok(Mat::from_slice_2d(&[
        [k[(0, 0)], k[(0, 1)], k[(0, 2)]],
        [k[(1, 0)], k[(1, 1)], k[(1, 2)]],
        [k[(2, 0)], k[(2, 1)], k[(2, 2)]],
    ])?)
}

pub(crate) fn d_mat(m: &CameraModel) -> Result<Mat> {
    Ok(Mat::from_slice_2d(&[m.distortion.as_array()])?)
}

fn values(m: &Mat) -> Result<Vec<f64>> {
    let m = if m.is_continuous() {
        m.clone()
    } else {
        m.try_clone()?
    };
    Ok(m.data_typed::<f64>()?.to_vec())
}

fn model_from(k: &Mat, d: &Mat, size: (u32, u32)) -> Result<CameraModel> {
    let k = values(k)?;
    if k.len() != 9 {
        bail!("OpenCV returned a camera matrix with {} entries", k.len());
    }
    Ok(CameraModel {
        intrinsics: Intrinsics {
            fx_px: k[0],
            fy_px: k[4],
            cx_px: k[2],
            cy_px: k[5],
        },
        distortion: Distortion::from_slice(&values(d)?)?,
        image_size: ImageSize {
            width_px: size.0,
            height_px: size.1,
        },
    })
}

fn point_sets(
    board: &Board,
    corners: &[(&String, &Vec<Point2f>)],
) -> (Vector<Vector<Point3f>>, Vector<Vector<Point2f>>) {
    let obj = board.object_points();
    let objs = corners.iter().map(|_| obj.clone()).collect();
    let imgs = corners
        .iter()
        .map(|(_, c)| c.iter().copied().collect::<Vector<Point2f>>())
        .collect();
    (objs, imgs)
}

/// `calibrateCamera` on the given views of one camera (5 distortion terms, or k3 fixed at 0).
pub fn calibrate_intrinsics(
    board: &Board,
    corners: &BTreeMap<String, Vec<Point2f>>,
    views: &[String],
    image_size: (u32, u32),
    fix_k3: bool,
) -> Result<IntrinsicFit> {
    let used: Vec<(&String, &Vec<Point2f>)> = views.iter().filter_map(|v| corners.get_key_value(v)).collect();
    let (objs, imgs) = point_sets(board, &used);
    let mut k = Mat::default();
    let mut d = Mat::default();
    let (mut rvecs, mut tvecs) = (Vector::<Mat>::new(), Vector::<Mat>::new());
    let (mut std_i, mut std_e, mut per_view) = (Mat::default(), Mat::default(), Mat::default());
    let flags = if fix_k3 { calib3d::CALIB_FIX_K3 } else { 0 };
    let rms_px = calib3d::calibrate_camera_extended(
        &objs,
        &imgs,
        Size::new(image_size.0 as i32, image_size.1 as i32),
        &mut k,
        &mut d,
        &mut rvecs,
        &mut tvecs,
        &mut std_i,
        &mut std_e,
        &mut per_view,
        flags,
        criteria()?,
    )
    .context("OpenCV calibrateCamera failed")?;
    let errs = values(&per_view)?;
    Ok(IntrinsicFit {
        model: model_from(&k, &d, image_size)?,
        rms_px,
        per_view_rms_px: used.iter().map(|(v, _)| (*v).clone()).zip(errs).collect(),
        corner_count: used.len() * board.corner_count(),
    })
}

/// `stereoCalibrate` of camera i against camera 0 on their common views: intrinsics fixed, or
/// refined jointly with the pose (`joint`).
#[allow(clippy::too_many_arguments)]
pub fn calibrate_pair(
    board: &Board,
    cam0: &CameraModel,
    cami: &CameraModel,
    corners0: &BTreeMap<String, Vec<Point2f>>,
    cornersi: &BTreeMap<String, Vec<Point2f>>,
    views: &[String],
    joint: bool,
) -> Result<PairFit> {
    let used0: Vec<(&String, &Vec<Point2f>)> =
        views.iter().filter_map(|v| corners0.get_key_value(v)).collect();
    let usedi: Vec<(&String, &Vec<Point2f>)> =
        views.iter().filter_map(|v| cornersi.get_key_value(v)).collect();
    if used0.len() != views.len() || usedi.len() != views.len() {
        bail!("internal: stereo views must have corners in both cameras");
    }
    let (objs, imgs0) = point_sets(board, &used0);
    let (_, imgsi) = point_sets(board, &usedi);
    let (mut k0, mut d0, mut ki, mut di) = (k_mat(cam0)?, d_mat(cam0)?, k_mat(cami)?, d_mat(cami)?);
    let (mut r, mut t, mut e, mut f, mut per_view) = (
        Mat::default(),
        Mat::default(),
        Mat::default(),
        Mat::default(),
        Mat::default(),
    );
    let flags = if joint {
        calib3d::CALIB_USE_INTRINSIC_GUESS
    } else {
        calib3d::CALIB_FIX_INTRINSIC
    };
    let size = Size::new(cam0.image_size.width_px as i32, cam0.image_size.height_px as i32);
    let rms_px = calib3d::stereo_calibrate_extended(
        &objs,
        &imgs0,
        &imgsi,
        &mut k0,
        &mut d0,
        &mut ki,
        &mut di,
        size,
        &mut r,
        &mut t,
        &mut e,
        &mut f,
        &mut per_view,
        flags,
        criteria()?,
    )
    .context("OpenCV stereoCalibrate failed")?;
    let rv = values(&r)?;
    let tv = values(&t)?;
    if rv.len() != 9 || tv.len() != 3 {
        bail!(
            "OpenCV stereoCalibrate returned R with {} and T with {} entries",
            rv.len(),
            tv.len()
        );
    }
    let cam_from_cam0 =
        RigidTransform::from_parts(&Matrix3::from_row_slice(&rv), &Vector3::new(tv[0], tv[1], tv[2]));
    let errs = values(&per_view)?;
    let per_view_rms_px = views
        .iter()
        .cloned()
        .zip(errs.chunks_exact(2).map(|c| [c[0], c[1]]))
        .collect();
    let refined = if joint {
        Some([
            model_from(&k0, &d0, (cam0.image_size.width_px, cam0.image_size.height_px))?,
            model_from(&ki, &di, (cami.image_size.width_px, cami.image_size.height_px))?,
        ])
    } else {
        None
    };
    Ok(PairFit {
        cam_from_cam0,
        rms_px,
        per_view_rms_px,
        refined,
    })
}

/// Median of a non-empty slice (0 for an empty one).
pub fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// Outlier threshold for per-view RMS errors: median + k·σ, with σ = 1.4826·MAD (the MAD scaled
/// to a Gaussian standard deviation), but never below twice the median so that uniformly tiny
/// errors (simulated or excellent data) do not get views rejected for noise.
pub fn outlier_threshold(errors: &[f64], k: f64) -> f64 {
    let med = median(errors);
    let dev: Vec<f64> = errors.iter().map(|e| (e - med).abs()).collect();
    let sigma = 1.4826 * median(&dev);
    (med + k * sigma).max(2.0 * med)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn threshold_flags_a_clear_outlier_only() {
        let mut e = vec![0.21, 0.19, 0.23, 0.2, 0.22, 0.18, 0.2, 0.24];
        let th = outlier_threshold(&e, 3.0);
        assert!(e.iter().all(|v| *v <= th), "threshold {th}");
        e.push(1.5);
        let th = outlier_threshold(&e, 3.0);
        assert!(th < 1.5 && th > 0.24, "threshold {th}");
        // Identical tiny errors: the 2×median floor applies.
        assert!((outlier_threshold(&[0.05; 6], 3.0) - 0.1).abs() < 1e-12);
        assert_eq!(median(&[3.0, 1.0, 2.0, 10.0]), 2.5);
    }
}
