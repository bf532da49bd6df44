//! Point-set registration (Kabsch / Umeyama): the rigid transform `to = R from + t` that best maps
//! corresponding points in the least-squares sense, e.g. tracker (camera-0) points onto robot-base
//! points touched with the robot's TCP.

use alloc::vec::Vec;
use nalgebra::{Matrix3, Vector3};

use crate::camera::RigidTransform;
use crate::error::{Error, Result};

/// Result of a fit.
#[derive(Debug, Clone, PartialEq)]
pub struct Registration {
    /// `to_from`: maps `from` points onto `to` points.
    pub transform: RigidTransform,
    /// Uniform scale (1 for a rigid fit; Umeyama's estimate when scale is allowed).
    pub scale: f64,
    /// RMS of the fit residuals over the points used.
    pub rms_mm: f64,
    /// Largest residual over the points used.
    pub max_mm: f64,
}

/// Fits `to ≈ s R from + t` from ≥ 4 pairs (3 suffice mathematically; 4 give a residual check).
/// With `with_scale = false` the fit is rigid (Kabsch, s = 1).
pub fn fit(from_mm: &[[f64; 3]], to_mm: &[[f64; 3]], with_scale: bool) -> Result<Registration> {
    if from_mm.len() != to_mm.len() {
        return Err(Error::InvalidParams {
            reason: alloc::format!(
                "{} tracker points but {} robot points",
                from_mm.len(),
                to_mm.len()
            ),
        });
    }
    if from_mm.len() < 4 {
        return Err(Error::TooFewViews {
            needed: 4,
            got: from_mm.len(),
        });
    }
    let n = from_mm.len() as f64;
    let a: Vec<Vector3<f64>> = from_mm.iter().map(|p| Vector3::from(*p)).collect();
    let b: Vec<Vector3<f64>> = to_mm.iter().map(|p| Vector3::from(*p)).collect();
    let ca = a.iter().sum::<Vector3<f64>>() / n;
    let cb = b.iter().sum::<Vector3<f64>>() / n;
    let mut h = Matrix3::zeros();
    let mut var_a = 0.0;
    for (pa, pb) in a.iter().zip(&b) {
        let (da, db) = (pa - ca, pb - cb);
        h += db * da.transpose();
        var_a += da.norm_squared();
    }
    h /= n;
    var_a /= n;
    if var_a < 1e-12 {
        return Err(Error::Degenerate {
            what: "registration: tracker points coincide",
        });
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(Error::Degenerate {
            what: "registration SVD",
        });
    };
    // Sorted singular values: a collinear set has two (near) zero ones and no unique rotation.
    let mut sv = [
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    ];
    sv.sort_by(|x, y| y.total_cmp(x));
    if sv[1] < 1e-9 * sv[0].max(1e-300) {
        return Err(Error::Degenerate {
            what: "registration: points are collinear",
        });
    }
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * v_t;
    let scale = if with_scale {
        (svd.singular_values.component_mul(&d.diagonal())).sum() / var_a
    } else {
        1.0
    };
    let t = cb - scale * r * ca;
    if !r.iter().chain(t.iter()).all(|v| v.is_finite()) || !scale.is_finite() {
        return Err(Error::Degenerate {
            what: "registration result",
        });
    }
    let transform = RigidTransform::from_parts(&r, &t);
    let mut sum2 = 0.0;
    let mut max_mm: f64 = 0.0;
    for (pa, pb) in a.iter().zip(&b) {
        let e = (scale * r * pa + t - pb).norm();
        sum2 += e * e;
        max_mm = max_mm.max(e);
    }
    Ok(Registration {
        transform,
        scale,
        rms_mm: libm::sqrt(sum2 / n),
        max_mm,
    })
}

/// Residuals of `to ≈ s T(from)` for held-out checks.
pub fn residuals_mm(reg: &Registration, from_mm: &[[f64; 3]], to_mm: &[[f64; 3]]) -> Vec<f64> {
    let r = reg.transform.rotation();
    let t = reg.transform.translation_mm();
    from_mm
        .iter()
        .zip(to_mm)
        .map(|(a, b)| (reg.scale * r * Vector3::from(*a) + t - Vector3::from(*b)).norm())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Unit};

    /// Small deterministic generator (core has no `rand` dependency).
    struct Lcg(u64);
    impl Lcg {
        fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            lo + (hi - lo) * ((self.0 >> 11) as f64 / (1u64 << 53) as f64)
        }
    }

    fn truth() -> (Matrix3<f64>, Vector3<f64>) {
        let axis = Unit::new_normalize(Vector3::new(0.3, -0.5, 0.8));
        (
            *Rotation3::from_axis_angle(&axis, 1.1).matrix(),
            Vector3::new(850.0, -120.0, 430.0),
        )
    }

    #[test]
    fn recovers_known_transform_from_noisy_points() {
        let (r, t) = truth();
        let mut rng = Lcg(7);
        let mut from = Vec::new();
        let mut to = Vec::new();
        for _ in 0..12 {
            let p = Vector3::new(
                rng.uniform(-300.0, 300.0),
                rng.uniform(-300.0, 300.0),
                rng.uniform(500.0, 1200.0),
            );
            let q = r * p
                + t
                + Vector3::new(
                    rng.uniform(-0.2, 0.2),
                    rng.uniform(-0.2, 0.2),
                    rng.uniform(-0.2, 0.2),
                );
            from.push(p.into());
            to.push(q.into());
        }
        let reg = fit(&from, &to, false).unwrap();
        let angle_err = Rotation3::from_matrix_unchecked(reg.transform.rotation() * r.transpose()).angle();
        assert!(angle_err < 1e-3, "rotation error {angle_err} rad");
        assert!((reg.transform.translation_mm() - t).norm() < 1.0);
        assert!(reg.rms_mm > 0.01 && reg.rms_mm < 0.3, "rms {}", reg.rms_mm);
        assert_eq!(reg.scale, 1.0);
        let scaled = fit(&from, &to, true).unwrap();
        assert!((scaled.scale - 1.0).abs() < 1e-3);
    }

    #[test]
    fn umeyama_recovers_scale_and_handles_reflection_case() {
        let (r, t) = truth();
        let from: Vec<[f64; 3]> = [
            [0.0, 0.0, 0.0],
            [100.0, 0.0, 0.0],
            [0.0, 100.0, 0.0],
            [0.0, 0.0, 100.0],
            [50.0, 50.0, 20.0],
        ]
        .into();
        let to: Vec<[f64; 3]> = from
            .iter()
            .map(|p| (1.5 * r * Vector3::from(*p) + t).into())
            .collect();
        let reg = fit(&from, &to, true).unwrap();
        assert!((reg.scale - 1.5).abs() < 1e-9);
        assert!(reg.rms_mm < 1e-9);
        assert!(reg.transform.rotation().determinant() > 0.0);
        // Coplanar points: still a proper rotation.
        let flat: Vec<[f64; 3]> = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]].into();
        let flat_to: Vec<[f64; 3]> = flat.iter().map(|p| (r * Vector3::from(*p) + t).into()).collect();
        let f = fit(&flat, &flat_to, false).unwrap();
        assert!((f.transform.rotation() - r).norm() < 1e-9);
    }

    #[test]
    fn rejects_too_few_and_degenerate() {
        let p = [[0.0; 3]; 3];
        assert!(matches!(
            fit(&p, &p, false),
            Err(Error::TooFewViews { needed: 4, got: 3 })
        ));
        let line: Vec<[f64; 3]> = (0..5).map(|i| [i as f64, 0.0, 0.0]).collect();
        assert!(matches!(fit(&line, &line, false), Err(Error::Degenerate { .. })));
        assert!(fit(&line, &line[..4], false).is_err());
    }
}
