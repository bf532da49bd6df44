//! Pinhole camera with OpenCV's 5-coefficient distortion model.
//!
//! Conventions follow OpenCV (`projectPoints`, `undistortPoints`): camera frame x right,
//! y down, z forward (mm); pixel (0,0) is the centre of the top-left pixel.
#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > y)` is deliberate: also true for NaN, which must be rejected.

use nalgebra::{Matrix3, Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Pinhole intrinsics in pixels (no skew, as OpenCV's default calibration).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    /// Focal length along x (px).
    pub fx_px: f64,
    /// Focal length along y (px).
    pub fy_px: f64,
    /// Principal point column (px).
    pub cx_px: f64,
    /// Principal point row (px).
    pub cy_px: f64,
}

impl Intrinsics {
    /// The 3×3 camera matrix K.
    pub fn matrix(&self) -> Matrix3<f64> {
        Matrix3::new(
            self.fx_px, 0.0, self.cx_px, 0.0, self.fy_px, self.cy_px, 0.0, 0.0, 1.0,
        )
    }
}

/// OpenCV distortion coefficients in OpenCV's order (k1, k2, p1, p2, k3).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Distortion {
    /// Radial coefficient of r².
    pub k1: f64,
    /// Radial coefficient of r⁴.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r⁶.
    pub k3: f64,
}

impl Distortion {
    /// No distortion.
    pub const NONE: Distortion = Distortion {
        k1: 0.0,
        k2: 0.0,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };

    /// Coefficients as OpenCV's 1×5 vector.
    pub fn as_array(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// From OpenCV's vector (4, 5 or more entries; entries past k3 must be zero).
    pub fn from_slice(d: &[f64]) -> Result<Self> {
        if d.len() < 4 {
            return Err(Error::InvalidParams {
                reason: alloc::format!("distortion vector has {} entries, need 4 or 5", d.len()),
            });
        }
        if d.iter().skip(5).any(|v| *v != 0.0) {
            return Err(Error::InvalidParams {
                reason: "only k1,k2,p1,p2,k3 are supported; rational/thin-prism terms must be zero".into(),
            });
        }
        Ok(Distortion {
            k1: d[0],
            k2: d[1],
            p1: d[2],
            p2: d[3],
            k3: d.get(4).copied().unwrap_or(0.0),
        })
    }

    /// Apply distortion to a normalized, undistorted point.
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        (xd, yd)
    }
}

/// Image size in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ImageSize {
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
}

/// One camera: intrinsics, distortion and the image size they were calibrated for.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CameraModel {
    /// Pinhole intrinsics.
    pub intrinsics: Intrinsics,
    /// Lens distortion (OpenCV's five-coefficient model).
    pub distortion: Distortion,
    /// Image size the intrinsics belong to.
    pub image_size: ImageSize,
}

/// Iteration cap for [`CameraModel::undistort_point`]. OpenCV's default is 5, which leaves
/// visible error for strong distortion; we iterate until the fixed point stops moving.
pub const UNDISTORT_MAX_ITERATIONS: usize = 100;
/// Convergence threshold on the normalized coordinate step.
pub const UNDISTORT_EPS: f64 = 1e-14;

impl CameraModel {
    /// Projects a point given in this camera's frame (mm) to pixels, with distortion.
    /// Points at or behind the image plane are an error, never NaN.
    pub fn project(&self, p_cam_mm: &Vector3<f64>) -> Result<Vector2<f64>> {
        if !(p_cam_mm.z > 0.0) || !p_cam_mm.iter().all(|v| v.is_finite()) {
            return Err(Error::BehindCamera {
                camera: 0,
                z_mm: p_cam_mm.z,
            });
        }
        let x = p_cam_mm.x / p_cam_mm.z;
        let y = p_cam_mm.y / p_cam_mm.z;
        Ok(self.normalized_to_pixel(x, y))
    }

    /// Distorts a normalized, undistorted point and maps it to pixels.
    #[inline]
    pub fn normalized_to_pixel(&self, x: f64, y: f64) -> Vector2<f64> {
        let (xd, yd) = self.distortion.distort(x, y);
        let k = &self.intrinsics;
        Vector2::new(k.fx_px * xd + k.cx_px, k.fy_px * yd + k.cy_px)
    }

    /// Pixel → normalized, undistorted image coordinates (x/z, y/z), by OpenCV's
    /// fixed-point iteration (`undistortPoints` with no R/P), run to convergence.
    pub fn undistort_point(&self, u_px: f64, v_px: f64) -> Vector2<f64> {
        let k = &self.intrinsics;
        let d = &self.distortion;
        let x0 = (u_px - k.cx_px) / k.fx_px;
        let y0 = (v_px - k.cy_px) / k.fy_px;
        let (mut x, mut y) = (x0, y0);
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            let r2 = x * x + y * y;
            let icdist = 1.0 / (1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3)));
            let dx = 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x);
            let dy = d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y;
            let nx = (x0 - dx) * icdist;
            let ny = (y0 - dy) * icdist;
            let step = libm::fabs(nx - x) + libm::fabs(ny - y);
            x = nx;
            y = ny;
            if !(step > UNDISTORT_EPS) {
                break;
            }
        }
        Vector2::new(x, y)
    }

    /// Unit ray direction in the camera frame through a pixel.
    pub fn pixel_ray(&self, u_px: f64, v_px: f64) -> Vector3<f64> {
        let n = self.undistort_point(u_px, v_px);
        Vector3::new(n.x, n.y, 1.0).normalize()
    }

    /// Whether a pixel position lies inside the image.
    pub fn contains_px(&self, p: &Vector2<f64>) -> bool {
        p.x >= -0.5
            && p.y >= -0.5
            && p.x < self.image_size.width_px as f64 - 0.5
            && p.y < self.image_size.height_px as f64 - 0.5
    }
}

/// Rigid transform `p_to = r_to_from * p_from + t_to_from_mm` (OpenCV's R, T convention:
/// for a stereo pair, `x_cam1 = R * x_cam0 + T`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RigidTransform {
    /// Row-major rotation matrix.
    pub r_row_major: [f64; 9],
    /// Translation (mm).
    pub t_mm: [f64; 3],
}

impl RigidTransform {
    /// No rotation, no translation.
    pub const IDENTITY: RigidTransform = RigidTransform {
        r_row_major: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        t_mm: [0.0; 3],
    };

    /// From a rotation matrix and a translation (mm).
    pub fn from_parts(r: &Matrix3<f64>, t_mm: &Vector3<f64>) -> Self {
        let mut r_row_major = [0.0; 9];
        for i in 0..3 {
            for j in 0..3 {
                r_row_major[i * 3 + j] = r[(i, j)];
            }
        }
        RigidTransform {
            r_row_major,
            t_mm: [t_mm.x, t_mm.y, t_mm.z],
        }
    }

    /// The rotation matrix.
    pub fn rotation(&self) -> Matrix3<f64> {
        Matrix3::from_row_slice(&self.r_row_major)
    }

    /// The translation (mm).
    pub fn translation_mm(&self) -> Vector3<f64> {
        Vector3::new(self.t_mm[0], self.t_mm[1], self.t_mm[2])
    }

    /// Applies the transform to a point.
    pub fn apply(&self, p_from_mm: &Vector3<f64>) -> Vector3<f64> {
        self.rotation() * p_from_mm + self.translation_mm()
    }

    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rt = self.rotation().transpose();
        let t = -(rt * self.translation_mm());
        Self::from_parts(&rt, &t)
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &RigidTransform) -> Self {
        let r = self.rotation() * other.rotation();
        let t = self.rotation() * other.translation_mm() + self.translation_mm();
        Self::from_parts(&r, &t)
    }

    /// Checks that the rotation is orthonormal with determinant +1 (within `tol`).
    pub fn is_proper_rotation(&self, tol: f64) -> bool {
        let r = self.rotation();
        let should_be_identity = r.transpose() * r;
        (should_be_identity - Matrix3::identity()).abs().max() < tol && (r.determinant() - 1.0).abs() < tol
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vga() -> CameraModel {
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: 680.0,
                fy_px: 681.0,
                cx_px: 320.5,
                cy_px: 239.5,
            },
            distortion: Distortion {
                k1: -0.28,
                k2: 0.09,
                p1: 0.001,
                p2: -0.0005,
                k3: -0.01,
            },
            image_size: ImageSize {
                width_px: 640,
                height_px: 480,
            },
        }
    }

    #[test]
    fn project_then_undistort_round_trips() {
        let cam = vga();
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.45, 0.33), (0.1, 0.35)] {
            let px = cam.normalized_to_pixel(x, y);
            let back = cam.undistort_point(px.x, px.y);
            assert!(
                (back.x - x).abs() < 1e-10 && (back.y - y).abs() < 1e-10,
                "{x},{y} -> {back:?}"
            );
        }
    }

    #[test]
    fn behind_camera_is_an_error() {
        let cam = vga();
        assert!(matches!(
            cam.project(&Vector3::new(1.0, 2.0, -5.0)),
            Err(Error::BehindCamera { .. })
        ));
        assert!(matches!(
            cam.project(&Vector3::new(1.0, 2.0, 0.0)),
            Err(Error::BehindCamera { .. })
        ));
        assert!(cam.project(&Vector3::new(f64::NAN, 0.0, 1.0)).is_err());
    }

    #[test]
    fn principal_point_projects_to_centre() {
        let cam = vga();
        let p = cam.project(&Vector3::new(0.0, 0.0, 1000.0)).unwrap();
        assert_eq!((p.x, p.y), (320.5, 239.5));
    }

    #[test]
    fn transform_inverse_and_compose() {
        let r = nalgebra::Rotation3::from_euler_angles(0.1, -0.4, 1.2).into_inner();
        let t = RigidTransform::from_parts(&r, &Vector3::new(10.0, -20.0, 300.0));
        let p = Vector3::new(1.0, 2.0, 3.0);
        let back = t.inverse().apply(&t.apply(&p));
        assert!((back - p).norm() < 1e-9);
        let id = t.compose(&t.inverse());
        assert!(id.is_proper_rotation(1e-12));
        assert!((id.translation_mm()).norm() < 1e-9);
    }

    #[test]
    fn distortion_from_slice_rejects_rational_terms() {
        assert!(Distortion::from_slice(&[0.1, 0.0, 0.0, 0.0]).is_ok());
        assert!(Distortion::from_slice(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.2]).is_err());
        assert!(Distortion::from_slice(&[0.1]).is_err());
    }
}
