//! Property tests: projection/undistortion round trips and triangulation on random rigs.

use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::triangulate::{Ray, least_squares_rays, midpoint};
use nalgebra::{Rotation3, Vector3};
use proptest::prelude::*;

fn camera(fx: f64, k1: f64, k2: f64, p1: f64, p2: f64) -> CameraModel {
    CameraModel {
        intrinsics: Intrinsics {
            fx_px: fx,
            fy_px: fx * 1.002,
            cx_px: 321.3,
            cy_px: 238.7,
        },
        distortion: Distortion {
            k1,
            k2,
            p1,
            p2,
            k3: 0.0,
        },
        image_size: ImageSize {
            width_px: 640,
            height_px: 480,
        },
    }
}

/// Largest radius `r (1 + k1 r² + k2 r⁴)` reaches while still increasing (r ≤ 3).
fn max_distorted_radius(k1: f64, k2: f64) -> f64 {
    let mut best = 0.0;
    for i in 1..=3000 {
        let r = f64::from(i) * 1e-3;
        let rd = r * (1.0 + k1 * r * r + k2 * r.powi(4));
        if rd <= best {
            break;
        }
        best = rd;
    }
    best
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// Any pixel inside a VGA image undistorts to a ray that projects back onto the same pixel.
    #[test]
    fn undistort_then_project_returns_the_pixel(
        u in 0.0f64..640.0, v in 0.0f64..480.0,
        fx in 500.0f64..900.0, k1 in -0.3f64..0.1, k2 in -0.05f64..0.12,
        p1 in -0.002f64..0.002, p2 in -0.002f64..0.002,
    ) {
        let cam = camera(fx, k1, k2, p1, p2);
        // Strong barrel distortion folds over beyond some radius: pixels past the largest
        // distorted radius the model reaches have no preimage. Only invertible pixels count.
        let xd = (u - cam.intrinsics.cx_px) / cam.intrinsics.fx_px;
        let yd = (v - cam.intrinsics.cy_px) / cam.intrinsics.fy_px;
        prop_assume!((xd * xd + yd * yd).sqrt() < 0.9 * max_distorted_radius(k1, k2));
        let n = cam.undistort_point(u, v);
        let back = cam.normalized_to_pixel(n.x, n.y);
        prop_assert!((back.x - u).abs() < 1e-6 && (back.y - v).abs() < 1e-6,
            "({u},{v}) -> {n:?} -> {back:?}");
    }

    /// Two cameras with random relative pose (10°..150° convergence) see a random point;
    /// triangulating the exact pixels returns the point.
    #[test]
    fn triangulation_recovers_points_for_any_convergence(
        angle_deg in 10.0f64..150.0, dist_mm in 400.0f64..3000.0,
        px in -0.15f64..0.15, py in -0.15f64..0.15, pz in -0.15f64..0.15,
        tilt in -0.2f64..0.2,
    ) {
        let cam = camera(680.0, -0.2, 0.05, 0.0005, -0.0003);
        // Camera 1 orbits the crossing point (0,0,dist) about the y axis.
        let r = Rotation3::from_euler_angles(tilt, -angle_deg.to_radians(), 0.0).into_inner();
        let target = Vector3::new(0.0, 0.0, dist_mm);
        let centre1 = target - r.transpose() * Vector3::new(0.0, 0.0, dist_mm);
        let pose1 = RigidTransform::from_parts(&r, &(-(r * centre1)));
        let pose0 = RigidTransform::IDENTITY;
        let p = target + Vector3::new(px, py, pz) * dist_mm;
        let mut rays = Vec::new();
        for pose in [&pose0, &pose1] {
            let pix = cam.project(&pose.apply(&p));
            prop_assume!(pix.is_ok());
            let pix = pix.unwrap();
            prop_assume!(cam.contains_px(&pix));
            rays.push(Ray::from_pixel(&cam, pose, pix.x, pix.y));
        }
        let m = midpoint(&rays[0], &rays[1]).unwrap();
        prop_assert!((m.point_mm - p).norm() < 1e-6 * dist_mm, "{:?} vs {p:?}", m.point_mm);
        prop_assert!(m.gap_mm < 1e-6 * dist_mm);
        let (q, _) = least_squares_rays(&rays).unwrap();
        prop_assert!((q - p).norm() < 1e-6 * dist_mm);
    }
}
