//! Analytic resolution planner: how far the marker must move along each axis before the
//! cameras can tell (one pixel of image motion).
//!
//! Criterion (the one the paper's Table I uses): a displacement is resolved once it moves some
//! camera's image of the marker by one pixel, or changes some camera pair's disparity (the
//! difference of the same image coordinate between the two cameras) by one pixel.
//!
//! Closed forms for ideal pinhole cameras of focal length f (px):
//! - lateral to a camera at range z: Δ = z / f (one pixel's footprint);
//! - parallel rig, baseline b, depth z: disparity d = f·b/z, and losing one pixel of disparity
//!   moves the point from z to f·b/(d − 1), i.e. Δz = z² / (f·b − z);
//! - convergent rig, axes crossing at angle θ at range D: x and y are lateral to camera 0
//!   (Δ = D/f); depth is lateral to camera 1 foreshortened by sin θ, Δz = D / (f·sin θ).
//!
//! With f = 681 px and b = 50 mm these reproduce Table I to its printed precision.

use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::params::{CameraParams, RigParams};
use nalgebra::Vector3;

use crate::SimError;
use crate::rig::convergent_pose;

/// Resolution along the axes of camera 0's frame (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AxisResolution {
    /// Along x.
    pub x_mm: f64,
    /// Along y.
    pub y_mm: f64,
    /// Along z (depth).
    pub z_mm: f64,
}

/// Closed form for a parallel rig (point on camera 0's axis at depth `z_mm`).
pub fn parallel_closed_form(focal_px: f64, baseline_mm: f64, z_mm: f64) -> AxisResolution {
    let lateral = z_mm / focal_px;
    let fb = focal_px * baseline_mm;
    let z = if fb > z_mm {
        z_mm * z_mm / (fb - z_mm)
    } else {
        f64::INFINITY
    };
    AxisResolution {
        x_mm: lateral,
        y_mm: lateral,
        z_mm: z,
    }
}

/// Closed form (first order) for a convergent rig at its crossing point.
pub fn convergent_closed_form(focal_px: f64, distance_mm: f64, angle_deg: f64) -> AxisResolution {
    let lateral = distance_mm / focal_px;
    AxisResolution {
        x_mm: lateral,
        y_mm: lateral,
        z_mm: lateral / angle_deg.to_radians().sin(),
    }
}

/// Ideal (distortion-free, centred) camera used by the planner.
pub fn ideal_camera(focal_px: f64, width_px: u32, height_px: u32) -> CameraModel {
    CameraModel {
        intrinsics: Intrinsics {
            fx_px: focal_px,
            fy_px: focal_px,
            cx_px: (width_px as f64 - 1.0) / 2.0,
            cy_px: (height_px as f64 - 1.0) / 2.0,
        },
        distortion: Distortion::NONE,
        image_size: ImageSize { width_px, height_px },
    }
}

/// Two ideal cameras with the given pose of camera 1.
pub fn ideal_rig(cam: CameraModel, cam1_from_cam0: RigidTransform) -> RigParams {
    RigParams {
        rig_id: "plan".into(),
        created_unix_s: 0,
        cameras: vec![
            CameraParams {
                model: cam,
                cam_from_cam0: RigidTransform::IDENTITY,
            },
            CameraParams {
                model: cam,
                cam_from_cam0: cam1_from_cam0,
            },
        ],
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Ideal parallel rig, camera 1 at +x `baseline_mm`.
pub fn ideal_parallel(cam: CameraModel, baseline_mm: f64) -> RigParams {
    ideal_rig(
        cam,
        RigidTransform {
            t_mm: [-baseline_mm, 0.0, 0.0],
            ..RigidTransform::IDENTITY
        },
    )
}

/// Ideal convergent rig crossing at `distance_mm` with `angle_deg`.
pub fn ideal_convergent(cam: CameraModel, distance_mm: f64, angle_deg: f64) -> RigParams {
    ideal_rig(cam, convergent_pose(distance_mm, angle_deg))
}

/// Image positions of a point in every camera (`out[i]`); error if behind any camera.
fn project_all(rig: &RigParams, p: &Vector3<f64>, out: &mut [[f64; 2]]) -> Result<(), SimError> {
    for (i, c) in rig.cameras.iter().enumerate() {
        let q = c.model.project(&c.cam_from_cam0.apply(p)).map_err(|e| match e {
            irtrack_core::Error::BehindCamera { z_mm, .. } => {
                irtrack_core::Error::BehindCamera { camera: i, z_mm }
            }
            other => other,
        })?;
        out[i] = [q.x, q.y];
    }
    Ok(())
}

/// Largest image change (px) between two sets of projections, by the module's criterion.
fn image_change(a: &[[f64; 2]], b: &[[f64; 2]]) -> f64 {
    let mut m: f64 = 0.0;
    for i in 0..a.len() {
        for k in 0..2 {
            let di = b[i][k] - a[i][k];
            m = m.max(di.abs());
            for j in (i + 1)..a.len() {
                let dj = b[j][k] - a[j][k];
                m = m.max((di - dj).abs());
            }
        }
    }
    m
}

/// Smallest displacement (mm) of `p_cam0_mm` along `dir` (unit) that the rig resolves, by the
/// module's criterion, found by bracketing and bisection on the exact projections.
pub fn step_mm(rig: &RigParams, p_cam0_mm: &Vector3<f64>, dir: &Vector3<f64>) -> Result<f64, SimError> {
    let n = rig.cameras.len();
    let mut base = vec![[0.0; 2]; n];
    let mut moved = vec![[0.0; 2]; n];
    project_all(rig, p_cam0_mm, &mut base)?;
    let mut change = |s: f64| -> Result<f64, SimError> {
        project_all(rig, &(p_cam0_mm + dir * s), &mut moved)?;
        Ok(image_change(&base, &moved))
    };
    let (mut lo, mut hi) = (0.0, 1e-3);
    while change(hi)? < 1.0 {
        lo = hi;
        hi *= 2.0;
        if hi > 1e7 {
            return Ok(f64::INFINITY);
        }
    }
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if change(mid)? < 1.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(hi)
}

/// Resolution along x, y and z of camera 0's frame at a point.
pub fn resolution_at(rig: &RigParams, p_cam0_mm: &Vector3<f64>) -> Result<AxisResolution, SimError> {
    Ok(AxisResolution {
        x_mm: step_mm(rig, p_cam0_mm, &Vector3::x())?,
        y_mm: step_mm(rig, p_cam0_mm, &Vector3::y())?,
        z_mm: step_mm(rig, p_cam0_mm, &Vector3::z())?,
    })
}

/// Table I of the paper: (distance mm, convergent x=y=z mm, parallel x=y mm, parallel z mm).
pub const TABLE_I: [(f64, f64, f64, f64); 2] = [(659.84, 0.97, 0.97, 13.04), (2309.44, 3.39, 3.39, 168.03)];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{TABLE_I_BASELINE_MM, TABLE_I_FOCAL_PX};

    fn round2(v: f64) -> f64 {
        (v * 100.0).round() / 100.0
    }

    #[test]
    fn closed_forms_reproduce_table_i() {
        for (d, conv, par_xy, par_z) in TABLE_I {
            let c = convergent_closed_form(TABLE_I_FOCAL_PX, d, 90.0);
            let p = parallel_closed_form(TABLE_I_FOCAL_PX, TABLE_I_BASELINE_MM, d);
            assert_eq!(
                [round2(c.x_mm), round2(c.y_mm), round2(c.z_mm)],
                [conv; 3],
                "convergent at {d}"
            );
            assert_eq!(
                [round2(p.x_mm), round2(p.y_mm), round2(p.z_mm)],
                [par_xy, par_xy, par_z],
                "parallel at {d}"
            );
        }
    }

    #[test]
    fn exact_projection_agrees_with_closed_forms() {
        let cam = ideal_camera(TABLE_I_FOCAL_PX, 640, 480);
        for (d, conv, par_xy, par_z) in TABLE_I {
            let conv_rig = ideal_convergent(cam, d, 90.0);
            let r = resolution_at(&conv_rig, &Vector3::new(0.0, 0.0, d)).unwrap();
            for v in [r.x_mm, r.y_mm, r.z_mm] {
                assert!((v - conv).abs() < 0.006, "convergent {d}: {r:?}");
            }
            let par = ideal_parallel(cam, TABLE_I_BASELINE_MM);
            let r = resolution_at(&par, &Vector3::new(0.0, 0.0, d)).unwrap();
            assert!(
                (r.x_mm - par_xy).abs() < 0.006 && (r.y_mm - par_xy).abs() < 0.006,
                "{r:?}"
            );
            assert!((r.z_mm - par_z).abs() < 0.006, "parallel z at {d}: {r:?}");
            // On the rig's mid-line the disparity term gives the same depth figure.
            let mid = resolution_at(&par, &Vector3::new(TABLE_I_BASELINE_MM / 2.0, 0.0, d)).unwrap();
            assert!((mid.z_mm - par_z).abs() < 0.006, "{mid:?}");
        }
    }

    #[test]
    fn behind_camera_is_an_error() {
        let cam = ideal_camera(681.0, 640, 480);
        let par = ideal_parallel(cam, 50.0);
        assert!(resolution_at(&par, &Vector3::new(0.0, 0.0, -100.0)).is_err());
    }
}
