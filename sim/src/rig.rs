//! Virtual rigs: the paper's two set-ups as presets, or any N-camera rig given as parameters.
//!
//! Frames: camera 0 is the reference (x right, y down, z forward, mm). Each camera's pose is
//! `x_cam = R x_cam0 + t` (OpenCV's stereo R, T).

use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::params::{CameraParams, RigParams};
use nalgebra::{Matrix3, Vector3};

use crate::SimError;

/// Focal length (px) that reproduces both columns of the paper's Table I for a VGA sensor:
/// 659.84 mm / 681 px = 0.969 mm → 0.97, 2309.44 mm / 681 px = 3.391 mm → 3.39.
pub const TABLE_I_FOCAL_PX: f64 = 681.0;
/// Parallel baseline (mm) that reproduces Table I's depth column with `TABLE_I_FOCAL_PX`
/// (13.04 mm at 659.84 mm and 168.03 mm at 2309.44 mm; see `resolution`).
pub const TABLE_I_BASELINE_MM: f64 = 50.0;

/// Sensor and lens shared by the preset cameras.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraSpec {
    /// Focal length (px), the same for both axes.
    pub focal_px: f64,
    /// Image size.
    pub image_size: ImageSize,
    /// Radial/tangential distortion of a typical small M12 lens.
    pub distortion: Distortion,
}

impl Default for CameraSpec {
    fn default() -> Self {
        CameraSpec {
            focal_px: TABLE_I_FOCAL_PX,
            image_size: ImageSize {
                width_px: 640,
                height_px: 480,
            },
            // Mild barrel distortion: about 3 px at the VGA corners at f = 681 px.
            distortion: Distortion {
                k1: -0.08,
                k2: 0.02,
                p1: 0.0004,
                p2: -0.0003,
                k3: 0.0,
            },
        }
    }
}

impl CameraSpec {
    /// The model of camera `i`: principal points differ slightly between cameras, as real
    /// sensors' do, so that nothing accidentally relies on identical cameras.
    pub fn model(&self, i: usize) -> CameraModel {
        let w = self.image_size.width_px as f64;
        let h = self.image_size.height_px as f64;
        let (dx, dy, dfy) = match i % 3 {
            0 => (1.7, -1.2, 0.6),
            1 => (-2.3, 1.9, -0.4),
            _ => (0.8, 2.6, 0.3),
        };
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: self.focal_px,
                fy_px: self.focal_px + dfy,
                cx_px: (w - 1.0) / 2.0 + dx,
                cy_px: (h - 1.0) / 2.0 + dy,
            },
            distortion: self.distortion,
            image_size: self.image_size,
        }
    }
}

/// Which rig to build.
#[derive(Debug, Clone, PartialEq)]
pub enum RigPreset {
    /// Two cameras side by side, optical axes parallel, camera 1 at +x `baseline_mm`.
    Parallel {
        /// Distance between the camera centres (mm).
        baseline_mm: f64,
    },
    /// Two cameras whose optical axes cross at `distance_mm` in front of camera 0 with an
    /// angle `angle_deg` between them (90° in the paper); both at that distance from the
    /// crossing point. Camera 1 sits on the +x side.
    Convergent {
        /// Distance of each camera from the crossing point (mm).
        distance_mm: f64,
        /// Angle between the optical axes (degrees).
        angle_deg: f64,
    },
    /// Any rig given explicitly (N ≥ 2 cameras at arbitrary poses).
    Custom(RigParams),
}

impl RigPreset {
    /// Point the trajectory presets centre on by default: the crossing point (convergent) or
    /// the point on the rig's mid-line at `distance_mm` (parallel).
    pub fn workspace_centre_mm(&self, distance_mm: f64) -> Vector3<f64> {
        match self {
            RigPreset::Parallel { baseline_mm } => Vector3::new(baseline_mm / 2.0, 0.0, distance_mm),
            RigPreset::Convergent { distance_mm: d, .. } => Vector3::new(0.0, 0.0, *d),
            RigPreset::Custom(_) => Vector3::new(0.0, 0.0, distance_mm),
        }
    }
}

/// Pose of camera 1 of a convergent rig, as `x_cam1 = R x_cam0 + t`.
pub fn convergent_pose(distance_mm: f64, angle_deg: f64) -> RigidTransform {
    let th = angle_deg.to_radians();
    let (s, c) = th.sin_cos();
    // Camera 1's axes expressed in camera 0's frame: rotated about y by `th`.
    let x1 = Vector3::new(c, 0.0, s);
    let y1 = Vector3::new(0.0, 1.0, 0.0);
    let z1 = Vector3::new(-s, 0.0, c);
    let centre1 = Vector3::new(0.0, 0.0, distance_mm) - z1 * distance_mm;
    let cam0_from_cam1 = Matrix3::from_columns(&[x1, y1, z1]);
    let r = cam0_from_cam1.transpose();
    let t = -(r * centre1);
    RigidTransform::from_parts(&r, &t)
}

/// Builds the ground-truth rig parameters.
pub fn build_rig(preset: &RigPreset, spec: &CameraSpec) -> Result<RigParams, SimError> {
    let poses = match preset {
        RigPreset::Parallel { baseline_mm } => {
            if !(*baseline_mm > 0.0 && baseline_mm.is_finite()) {
                return Err(SimError::Config {
                    field: "baseline_mm",
                    reason: format!("{baseline_mm} must be > 0"),
                });
            }
            let t = RigidTransform {
                t_mm: [-baseline_mm, 0.0, 0.0],
                ..RigidTransform::IDENTITY
            };
            vec![RigidTransform::IDENTITY, t]
        }
        RigPreset::Convergent {
            distance_mm,
            angle_deg,
        } => {
            if !(*distance_mm > 0.0 && distance_mm.is_finite()) {
                return Err(SimError::Config {
                    field: "distance_mm",
                    reason: format!("{distance_mm} must be > 0"),
                });
            }
            if !(*angle_deg > 0.0 && *angle_deg < 180.0) {
                return Err(SimError::Config {
                    field: "angle_deg",
                    reason: format!("{angle_deg} must be in (0, 180)"),
                });
            }
            vec![
                RigidTransform::IDENTITY,
                convergent_pose(*distance_mm, *angle_deg),
            ]
        }
        RigPreset::Custom(rig) => {
            if rig.cameras.len() < 2 {
                return Err(SimError::Config {
                    field: "rig",
                    reason: format!("need at least 2 cameras, got {}", rig.cameras.len()),
                });
            }
            return Ok(rig.clone());
        }
    };
    let name = match preset {
        RigPreset::Parallel { baseline_mm } => format!("sim-parallel-b{baseline_mm}"),
        RigPreset::Convergent {
            distance_mm,
            angle_deg,
        } => format!("sim-convergent-{angle_deg}deg-d{distance_mm}"),
        RigPreset::Custom(_) => String::new(),
    };
    Ok(RigParams {
        rig_id: name,
        created_unix_s: 0,
        cameras: poses
            .into_iter()
            .enumerate()
            .map(|(i, pose)| CameraParams {
                model: spec.model(i),
                cam_from_cam0: pose,
            })
            .collect(),
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn convergent_axes_cross_at_distance_with_angle() {
        for &(d, a) in &[(659.84, 90.0), (1500.0, 60.0), (800.0, 120.0)] {
            let pose = convergent_pose(d, a);
            assert!(pose.is_proper_rotation(1e-12));
            // The crossing point lies on camera 1's optical axis at distance d.
            let p1 = pose.apply(&Vector3::new(0.0, 0.0, d));
            assert!(
                p1.x.abs() < 1e-9 && p1.y.abs() < 1e-9 && (p1.z - d).abs() < 1e-9,
                "{p1:?}"
            );
            // Angle between the optical axes.
            let z1_in_0 = pose.rotation().transpose() * Vector3::z();
            let ang = z1_in_0.dot(&Vector3::z()).acos().to_degrees();
            assert!((ang - a).abs() < 1e-9);
        }
    }

    #[test]
    fn parallel_rig_has_baseline_along_x() {
        let rig = build_rig(&RigPreset::Parallel { baseline_mm: 50.0 }, &CameraSpec::default()).unwrap();
        assert_eq!(rig.cameras.len(), 2);
        // Camera 1's centre is at +50 mm x in camera 0's frame.
        let c1 = rig.cameras[1].cam_from_cam0.inverse().apply(&Vector3::zeros());
        assert!((c1 - Vector3::new(50.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(build_rig(&RigPreset::Parallel { baseline_mm: -1.0 }, &CameraSpec::default()).is_err());
        assert!(
            build_rig(
                &RigPreset::Convergent {
                    distance_mm: 500.0,
                    angle_deg: 180.0
                },
                &CameraSpec::default()
            )
            .is_err()
        );
    }
}
