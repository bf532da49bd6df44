//! Step 3, the pose: Horn's closed-form quaternion fit of the layout onto measured points.

use nalgebra::{Matrix3, Matrix4, Quaternion, UnitQuaternion, Vector3};

/// Result of [`fit_rigid_horn`]: `measured ≈ R · model + t`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RigidFit {
    /// Unit quaternion of R, (w, x, y, z) with w ≥ 0.
    pub quaternion_wxyz: [f64; 4],
    /// R as a matrix.
    pub rotation: Matrix3<f64>,
    /// t (mm).
    pub translation_mm: Vector3<f64>,
    /// RMS distance between `R · model + t` and the measured points (mm).
    pub rms_mm: f64,
    /// Largest of those distances (mm).
    pub max_mm: f64,
}

/// Least-squares rigid fit of ≥ 3 point pairs without allocation (Horn 1987, closed form
/// via the 4×4 symmetric matrix; always a proper rotation). `registration::fit` solves the
/// same problem for the robot calibration but allocates and needs ≥ 4 pairs; a tool with a
/// missing LED has 3, and the per-frame path must not allocate.
/// Returns `None` for fewer than 3 pairs, mismatched lengths or (nearly) collinear points.
pub fn fit_rigid_horn(model_mm: &[Vector3<f64>], measured_mm: &[Vector3<f64>]) -> Option<RigidFit> {
    let n = model_mm.len();
    if n < 3 || measured_mm.len() != n {
        return None;
    }
    let nf = n as f64;
    let ca = model_mm.iter().sum::<Vector3<f64>>() / nf;
    let cb = measured_mm.iter().sum::<Vector3<f64>>() / nf;
    let mut s = Matrix3::zeros();
    let mut spread = 0.0;
    for (a, b) in model_mm.iter().zip(measured_mm) {
        s += (a - ca) * (b - cb).transpose();
        spread += (a - ca).norm_squared();
    }
    if spread.is_nan() || spread <= 1e-12 {
        return None;
    }
    let (sxx, sxy, sxz) = (s[(0, 0)], s[(0, 1)], s[(0, 2)]);
    let (syx, syy, syz) = (s[(1, 0)], s[(1, 1)], s[(1, 2)]);
    let (szx, szy, szz) = (s[(2, 0)], s[(2, 1)], s[(2, 2)]);
    #[rustfmt::skip]
    let nm = Matrix4::new(
        sxx + syy + szz, syz - szy,        szx - sxz,        sxy - syx,
        syz - szy,       sxx - syy - szz,  sxy + syx,        szx + sxz,
        szx - sxz,       sxy + syx,        -sxx + syy - szz, syz + szy,
        sxy - syx,       szx + sxz,        syz + szy,        -sxx - syy + szz,
    );
    let eig = nm.symmetric_eigen();
    let mut order = [0usize, 1, 2, 3];
    order.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let (l0, l1) = (eig.eigenvalues[order[0]], eig.eigenvalues[order[1]]);
    // Collinear points leave a one-parameter family of rotations: the top two eigenvalues
    // coincide. Relative to the spread this is scale-free.
    let eigen_gap = l0 - l1;
    if eigen_gap.is_nan() || eigen_gap <= 1e-9 * spread {
        return None;
    }
    let v = eig.eigenvectors.column(order[0]);
    let sign = if v[0] < 0.0 { -1.0 } else { 1.0 };
    let q = UnitQuaternion::from_quaternion(Quaternion::new(
        sign * v[0],
        sign * v[1],
        sign * v[2],
        sign * v[3],
    ));
    let rotation = *q.to_rotation_matrix().matrix();
    let translation_mm = cb - rotation * ca;
    let mut sum2 = 0.0;
    let mut max_mm: f64 = 0.0;
    for (a, b) in model_mm.iter().zip(measured_mm) {
        let e = (rotation * a + translation_mm - b).norm();
        sum2 += e * e;
        max_mm = max_mm.max(e);
    }
    let rms_mm = libm::sqrt(sum2 / nf);
    if !(rms_mm.is_finite() && translation_mm.iter().all(|x| x.is_finite())) {
        return None;
    }
    Some(RigidFit {
        quaternion_wxyz: [q.w, q.i, q.j, q.k],
        rotation,
        translation_mm,
        rms_mm,
        max_mm,
    })
}

/// Angle (rad) between two unit quaternions (w, x, y, z), ignoring the sign ambiguity.
pub fn quaternion_angle_rad(a: &[f64; 4], b: &[f64; 4]) -> f64 {
    let dot = libm::fabs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]).min(1.0);
    2.0 * libm::acos(dot)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn layout() -> [Vector3<f64>; 4] {
        [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(100.0, 0.0, 0.0),
            Vector3::new(0.0, 60.0, 0.0),
            Vector3::new(20.0, 30.0, 40.0),
        ]
    }

    #[test]
    fn recovers_a_known_rotation_and_translation() {
        // 90° about z: (x, y, z) -> (-y, x, z); quaternion (cos 45°, 0, 0, sin 45°).
        let r = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let t = Vector3::new(10.0, -20.0, 500.0);
        let model = layout();
        let measured: [Vector3<f64>; 4] = model.map(|p| r * p + t);
        let fit = fit_rigid_horn(&model, &measured).unwrap();
        let h = core::f64::consts::FRAC_1_SQRT_2;
        for (got, want) in fit.quaternion_wxyz.iter().zip([h, 0.0, 0.0, h]) {
            assert!((got - want).abs() < 1e-12, "{:?}", fit.quaternion_wxyz);
        }
        assert!((fit.rotation - r).norm() < 1e-12);
        assert!((fit.translation_mm - t).norm() < 1e-9, "{}", fit.translation_mm);
        assert!(fit.rms_mm < 1e-9 && fit.max_mm < 1e-9);
        // Three pairs (a tool with one LED missing) fix the pose as well.
        let three = fit_rigid_horn(&model[..3], &measured[..3]).unwrap();
        assert!((three.translation_mm - t).norm() < 1e-9);
    }

    #[test]
    fn residual_of_a_scaled_layout_is_known() {
        // measured = centroid + 1.01 (model − centroid): the best rotation is the identity
        // (the cross-covariance is symmetric positive), so every residual is 1 % of the
        // point's distance from the centroid.
        let model = layout();
        let c = model.iter().sum::<Vector3<f64>>() / 4.0;
        let measured = model.map(|p| c + (p - c) * 1.01);
        let fit = fit_rigid_horn(&model, &measured).unwrap();
        assert!((fit.rotation - Matrix3::identity()).norm() < 1e-12);
        let d2: f64 = model.iter().map(|p| (p - c).norm_squared()).sum::<f64>() / 4.0;
        let dmax = model.iter().map(|p| (p - c).norm()).fold(0.0, f64::max);
        assert!((fit.rms_mm - 0.01 * d2.sqrt()).abs() < 1e-9, "{}", fit.rms_mm);
        assert!((fit.max_mm - 0.01 * dmax).abs() < 1e-9, "{}", fit.max_mm);
    }

    #[test]
    fn refuses_too_few_mismatched_or_collinear_points() {
        let model = layout();
        assert!(fit_rigid_horn(&model[..2], &model[..2]).is_none());
        assert!(fit_rigid_horn(&model[..3], &model[..4]).is_none());
        let line = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(50.0, 0.0, 0.0),
            Vector3::new(120.0, 0.0, 0.0),
        ];
        assert!(fit_rigid_horn(&line, &line).is_none());
    }

    #[test]
    fn quaternion_angle_ignores_the_sign() {
        let h = core::f64::consts::FRAC_1_SQRT_2;
        let id = [1.0, 0.0, 0.0, 0.0];
        let z90 = [h, 0.0, 0.0, h];
        assert!((quaternion_angle_rad(&id, &z90) - core::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!(quaternion_angle_rad(&z90, &[-h, 0.0, 0.0, -h]) < 1e-6);
    }
}
