//! Triangulation for parallel and convergent rigs.
//!
//! Rays are expressed in the rig frame (camera 0). The two-view midpoint works for any
//! convergence angle (the paper's 90° rig included) because it never rectifies; the ray gap
//! (length of the common perpendicular) is the quality figure: a true marker seen by both
//! cameras gives a gap of a few tenths of a millimetre, a mismatched blob gives centimetres.
#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > y)` is deliberate: also true for NaN, which must be rejected.

use nalgebra::{DMatrix, Matrix3, Vector2, Vector3, Vector4};

use crate::camera::{CameraModel, RigidTransform};
use crate::{Error, Result};

/// Rays closer to parallel than this (radians) are rejected.
pub const MIN_RAY_ANGLE_RAD: f64 = 1e-4;

/// A ray in the rig frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    /// Camera centre (mm).
    pub origin_mm: Vector3<f64>,
    /// Unit direction.
    pub dir: Vector3<f64>,
}

impl Ray {
    /// The ray through a pixel of a camera whose pose is `cam_from_rig` (x_cam = R x_rig + t).
    pub fn from_pixel(cam: &CameraModel, cam_from_rig: &RigidTransform, u_px: f64, v_px: f64) -> Ray {
        let n = cam.undistort_point(u_px, v_px);
        Self::from_normalized(cam_from_rig, &n)
    }

    /// The ray through normalized, undistorted image coordinates.
    pub fn from_normalized(cam_from_rig: &RigidTransform, n: &Vector2<f64>) -> Ray {
        let rt = cam_from_rig.rotation().transpose();
        let origin_mm = -(rt * cam_from_rig.translation_mm());
        let dir = (rt * Vector3::new(n.x, n.y, 1.0)).normalize();
        Ray { origin_mm, dir }
    }

    /// Point at distance `s_mm` along the ray.
    pub fn at(&self, s_mm: f64) -> Vector3<f64> {
        self.origin_mm + self.dir * s_mm
    }
}

/// Result of a two-view triangulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Midpoint {
    /// Midpoint of the common perpendicular, rig frame.
    pub point_mm: Vector3<f64>,
    /// Length of the common perpendicular (0 for intersecting rays).
    pub gap_mm: f64,
    /// Distance along each ray to its closest point.
    pub range_mm: [f64; 2],
    /// Angle between the rays.
    pub angle_rad: f64,
}

/// Midpoint of the common perpendicular of two rays.
///
/// Errors: [`Error::ParallelRays`] when the rays are within [`MIN_RAY_ANGLE_RAD`],
/// [`Error::BehindCamera`] when the closest point lies behind either ray origin.
pub fn midpoint(a: &Ray, b: &Ray) -> Result<Midpoint> {
    let w0 = a.origin_mm - b.origin_mm;
    let c = a.dir.dot(&b.dir);
    let sin2 = 1.0 - c * c;
    let angle_rad = libm::atan2(a.dir.cross(&b.dir).norm(), c);
    if !(sin2 > MIN_RAY_ANGLE_RAD * MIN_RAY_ANGLE_RAD) {
        return Err(Error::ParallelRays { angle_rad });
    }
    let d = a.dir.dot(&w0);
    let e = b.dir.dot(&w0);
    // Closest points a(s) and b(t): minimise |w0 + s da - t db|² for unit directions.
    let s = (c * e - d) / sin2;
    let t = (e - c * d) / sin2;
    if !(s > 0.0) {
        return Err(Error::BehindCamera { camera: 0, z_mm: s });
    }
    if !(t > 0.0) {
        return Err(Error::BehindCamera { camera: 1, z_mm: t });
    }
    let pa = a.at(s);
    let pb = b.at(t);
    let point_mm = (pa + pb) * 0.5;
    if !point_mm.iter().all(|v| v.is_finite()) {
        return Err(Error::Degenerate { what: "midpoint" });
    }
    Ok(Midpoint {
        point_mm,
        gap_mm: (pa - pb).norm(),
        range_mm: [s, t],
        angle_rad,
    })
}

/// N-view linear least squares: the point minimising the sum of squared perpendicular
/// distances to all rays. Returns the point and the RMS distance of the rays from it.
pub fn least_squares_rays(rays: &[Ray]) -> Result<(Vector3<f64>, f64)> {
    if rays.len() < 2 {
        return Err(Error::TooFewViews {
            needed: 2,
            got: rays.len(),
        });
    }
    let mut a = Matrix3::zeros();
    let mut b = Vector3::zeros();
    for r in rays {
        let m = Matrix3::identity() - r.dir * r.dir.transpose();
        a += m;
        b += m * r.origin_mm;
    }
    // Condition check: all rays parallel makes A rank-deficient.
    let eig = a.symmetric_eigenvalues();
    let (min, max) = (eig.min(), eig.max());
    if !(min > max * MIN_RAY_ANGLE_RAD * MIN_RAY_ANGLE_RAD) {
        return Err(Error::ParallelRays {
            angle_rad: libm::sqrt((min / max).max(0.0)),
        });
    }
    let p = a.try_inverse().ok_or(Error::Degenerate {
        what: "least-squares normal matrix",
    })? * b;
    let mut sum2 = 0.0;
    for (i, r) in rays.iter().enumerate() {
        let v = p - r.origin_mm;
        let along = v.dot(&r.dir);
        if !(along > 0.0) {
            return Err(Error::BehindCamera {
                camera: i,
                z_mm: along,
            });
        }
        sum2 += (v - r.dir * along).norm_squared();
    }
    Ok((p, libm::sqrt(sum2 / rays.len() as f64)))
}

/// Homogeneous DLT triangulation from normalized image coordinates and camera poses —
/// the method of OpenCV's `triangulatePoints` (with P = [R|t] since coordinates are
/// normalized). Used to cross-check against OpenCV; the midpoint is what the tracker runs.
pub fn dlt(views: &[(RigidTransform, Vector2<f64>)]) -> Result<Vector3<f64>> {
    if views.len() < 2 {
        return Err(Error::TooFewViews {
            needed: 2,
            got: views.len(),
        });
    }
    // SVD of the 2N×4 system itself, as OpenCV does: forming AᵀA squares the condition
    // number and its eigenvectors for the near-zero eigenvalue are unreliable.
    let mut a = DMatrix::<f64>::zeros(2 * views.len(), 4);
    for (k, (pose, n)) in views.iter().enumerate() {
        let r = pose.rotation();
        let t = pose.translation_mm();
        let row = |i: usize| Vector4::new(r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]);
        let (p0, p1, p2) = (row(0), row(1), row(2));
        a.set_row(2 * k, &(p2 * n.x - p0).transpose());
        a.set_row(2 * k + 1, &(p2 * n.y - p1).transpose());
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t.ok_or(Error::Degenerate { what: "DLT SVD" })?;
    let mut imin = 0;
    for i in 1..svd.singular_values.len() {
        if svd.singular_values[i] < svd.singular_values[imin] {
            imin = i;
        }
    }
    let h = v_t.row(imin);
    if !(libm::fabs(h[3]) > 1e-12 * h.norm()) {
        return Err(Error::Degenerate {
            what: "DLT point at infinity",
        });
    }
    let p = Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]);
    for (i, (pose, _)) in views.iter().enumerate() {
        let z = pose.apply(&p).z;
        if !(z > 0.0) {
            return Err(Error::BehindCamera { camera: i, z_mm: z });
        }
    }
    Ok(p)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Distortion, ImageSize, Intrinsics};
    use nalgebra::Rotation3;

    fn cam() -> CameraModel {
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: 680.0,
                fy_px: 680.0,
                cx_px: 320.0,
                cy_px: 240.0,
            },
            distortion: Distortion {
                k1: -0.2,
                k2: 0.05,
                p1: 0.0,
                p2: 0.0,
                k3: 0.0,
            },
            image_size: ImageSize {
                width_px: 640,
                height_px: 480,
            },
        }
    }

    /// The paper's orthogonal rig: camera 1 sits on camera 0's x axis at the crossing
    /// distance and looks back along -x, so the optical axes cross at 90°.
    fn orthogonal_pose(d_mm: f64) -> RigidTransform {
        // cam1 axes expressed in cam0: x1 = -z0... choose z1 = -x0 (looks toward -x).
        let r_rig_cam1 = Matrix3::from_columns(&[
            Vector3::new(0.0, 0.0, 1.0),  // x1
            Vector3::new(0.0, 1.0, 0.0),  // y1
            Vector3::new(-1.0, 0.0, 0.0), // z1
        ]);
        let c1 = Vector3::new(d_mm, 0.0, d_mm);
        let r = r_rig_cam1.transpose();
        RigidTransform::from_parts(&r, &(-(r * c1)))
    }

    fn observe(c: &CameraModel, pose: &RigidTransform, p: &Vector3<f64>) -> Ray {
        let px = c.project(&pose.apply(p)).unwrap();
        Ray::from_pixel(c, pose, px.x, px.y)
    }

    #[test]
    fn orthogonal_rig_recovers_points_exactly() {
        let c = cam();
        let p0 = RigidTransform::IDENTITY;
        let p1 = orthogonal_pose(1000.0);
        for p in [
            Vector3::new(0.0, 0.0, 1000.0),
            Vector3::new(50.0, -80.0, 950.0),
            Vector3::new(-120.0, 60.0, 1100.0),
        ] {
            let m = midpoint(&observe(&c, &p0, &p), &observe(&c, &p1, &p)).unwrap();
            assert!((m.point_mm - p).norm() < 1e-7, "{p:?} -> {:?}", m.point_mm);
            assert!(m.gap_mm < 1e-7);
            assert!((m.angle_rad.to_degrees() - 90.0).abs() < 15.0);
            let (q, rms) = least_squares_rays(&[observe(&c, &p0, &p), observe(&c, &p1, &p)]).unwrap();
            assert!((q - p).norm() < 1e-7 && rms < 1e-7);
            let n0 = c.undistort_point(
                c.project(&p0.apply(&p)).unwrap().x,
                c.project(&p0.apply(&p)).unwrap().y,
            );
            let n1 = c.undistort_point(
                c.project(&p1.apply(&p)).unwrap().x,
                c.project(&p1.apply(&p)).unwrap().y,
            );
            let d = dlt(&[(p0, n0), (p1, n1)]).unwrap();
            assert!((d - p).norm() < 1e-6, "dlt {d:?}");
        }
    }

    #[test]
    fn obtuse_convergence_beyond_90_degrees_works() {
        let c = cam();
        let r = Rotation3::from_axis_angle(&Vector3::y_axis(), -120f64.to_radians()).into_inner();
        // Camera 1 at 120° around the target at z = 800.
        let target = Vector3::new(0.0, 0.0, 800.0);
        let c1 = target + r.transpose() * Vector3::new(0.0, 0.0, -800.0);
        let pose1 = RigidTransform::from_parts(&r, &(-(r * c1)));
        let p = Vector3::new(20.0, 10.0, 790.0);
        let m = midpoint(
            &observe(&c, &RigidTransform::IDENTITY, &p),
            &observe(&c, &pose1, &p),
        )
        .unwrap();
        assert!((m.point_mm - p).norm() < 1e-7);
        assert!(m.angle_rad.to_degrees() > 100.0);
    }

    #[test]
    fn parallel_rays_are_an_error_not_nan() {
        let a = Ray {
            origin_mm: Vector3::zeros(),
            dir: Vector3::z(),
        };
        let b = Ray {
            origin_mm: Vector3::new(100.0, 0.0, 0.0),
            dir: Vector3::z(),
        };
        assert!(matches!(midpoint(&a, &b), Err(Error::ParallelRays { .. })));
        assert!(matches!(
            least_squares_rays(&[a, b]),
            Err(Error::ParallelRays { .. })
        ));
    }

    #[test]
    fn point_behind_camera_is_an_error() {
        // Rays diverge: they meet only behind the origins.
        let a = Ray {
            origin_mm: Vector3::zeros(),
            dir: Vector3::new(-0.1, 0.0, 1.0).normalize(),
        };
        let b = Ray {
            origin_mm: Vector3::new(100.0, 0.0, 0.0),
            dir: Vector3::new(0.1, 0.0, 1.0).normalize(),
        };
        assert!(matches!(midpoint(&a, &b), Err(Error::BehindCamera { .. })));
    }

    #[test]
    fn gap_measures_skew_rays() {
        let a = Ray {
            origin_mm: Vector3::zeros(),
            dir: Vector3::z(),
        };
        let b = Ray {
            origin_mm: Vector3::new(0.0, 5.0, 1000.0),
            dir: Vector3::x(),
        };
        let b = Ray {
            origin_mm: b.origin_mm - b.dir * 500.0,
            ..b
        };
        let m = midpoint(&a, &b).unwrap();
        assert!((m.gap_mm - 5.0).abs() < 1e-9);
        assert!((m.point_mm - Vector3::new(0.0, 2.5, 1000.0)).norm() < 1e-9);
    }

    #[test]
    fn too_few_views() {
        assert!(matches!(least_squares_rays(&[]), Err(Error::TooFewViews { .. })));
        assert!(matches!(dlt(&[]), Err(Error::TooFewViews { .. })));
    }
}
