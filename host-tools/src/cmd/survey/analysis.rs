//! Analysis: the rigid registration of tracker onto robot positions, the LED offset on the
//! flange when it is not given, the Umeyama scale and the error statistics.

use anyhow::{Context, ensure};
use irtrack_core::camera::RigidTransform;
use irtrack_core::registration;
use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3, Vector6};

use super::cell::Measured;
use super::plan::{Role, quat};

/// Results of the analysis.
#[derive(Debug, Clone)]
pub struct Analysis {
    /// `robot_from_tracker` fitted on the fit (and turned) points.
    pub fit: RigidTransform,
    /// The same fitted on every point (what gets written).
    pub all: RigidTransform,
    /// Umeyama scale on the fit points.
    pub scale: f64,
    /// LED offset in the flange frame (mm): solved, given with `--led-offset-mm`, or zero.
    pub led_offset_mm: [f64; 3],
    /// The offset was solved from the turned points (not given, not zero).
    pub offset_solved: bool,
    /// Residual vectors (robot frame: registered tracker − robot) per point, in `points` order.
    pub residual_mm: Vec<[f64; 3]>,
    /// With a tool (every point has a tracked orientation): its rotation on the flange and the
    /// orientation errors.
    pub orientation: Option<OrientationFit>,
}

/// The tool's rotation on the flange and the orientation errors in robot base.
#[derive(Debug, Clone)]
pub struct OrientationFit {
    /// `flange_from_tool` rotation (w, x, y, z), fitted on the fit (and turned) points.
    pub mount_wxyz: [f64; 4],
    /// Per point (in `points` order): the rotation taking the orientation the robot reports
    /// (flange · mount) to the tracked one (registered into robot base), as a rotation vector
    /// in the robot base frame, degrees. Its length is the orientation error.
    pub error_deg: Vec<[f64; 3]>,
}

/// The tool's rotation on the flange, `X`, given the registration `B` (robot ← tracker): at
/// every point the robot reports the flange's rotation `F` and the tracker the tool's `T`, and
/// `F X = B T` up to the errors. `X` is the rotation nearest (Frobenius) to `Σ Fᵀ B T` over the
/// fit and turned points — the least-squares solution of `min Σ ‖F X − B T‖²` — and every
/// point's error is the rotation from `F X` to `B T`.
pub fn orientation_fit(
    points: &[Measured],
    robot_from_tracker: &Matrix3<f64>,
) -> anyhow::Result<OrientationFit> {
    let rot = |m: &Measured| -> anyhow::Result<(Matrix3<f64>, Matrix3<f64>)> {
        let t = m
            .tracker_wxyz
            .with_context(|| format!("point {} has no tracked orientation", m.index))?;
        Ok((
            quat(m.flange_wxyz).to_rotation_matrix().into_inner(),
            robot_from_tracker * quat(t).to_rotation_matrix().into_inner(),
        ))
    };
    let mut sum = Matrix3::<f64>::zeros();
    let mut fit = 0;
    for m in points.iter().filter(|m| m.role != Role::Holdout) {
        let (f, bt) = rot(m)?;
        sum += f.transpose() * bt;
        fit += 1;
    }
    ensure!(fit >= 1, "no fit point with a tracked orientation");
    let x = nearest_rotation(&sum).context("tool rotation on the flange")?;
    let error_deg = points
        .iter()
        .map(|m| {
            let (f, bt) = rot(m)?;
            let e = UnitQuaternion::from_matrix(&(bt * (f * x).transpose())).scaled_axis();
            Ok([e.x.to_degrees(), e.y.to_degrees(), e.z.to_degrees()])
        })
        .collect::<anyhow::Result<_>>()?;
    let q = UnitQuaternion::from_matrix(&x).into_inner();
    let q = if q.w < 0.0 { -q } else { q };
    Ok(OrientationFit {
        mount_wxyz: [q.w, q.i, q.j, q.k],
        error_deg,
    })
}

/// The rotation nearest to `m` (polar decomposition by SVD, a reflection turned into a rotation).
fn nearest_rotation(m: &Matrix3<f64>) -> anyhow::Result<Matrix3<f64>> {
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u.context("SVD")?, svd.v_t.context("SVD")?);
    let d = (u * v_t).determinant().signum();
    Ok(u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t)
}

/// Error statistics of a set of residual vectors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    /// Number of residuals.
    pub n: usize,
    /// RMS of the 3-D residual lengths (mm).
    pub rms_mm: f64,
    /// Largest 3-D residual length (mm).
    pub max_mm: f64,
    /// RMS per axis x, y, z (mm).
    pub axis_rms_mm: [f64; 3],
    /// Largest absolute residual per axis x, y, z (mm).
    pub axis_max_mm: [f64; 3],
}

/// RMS and max of the 3-D errors and per axis.
pub fn stats(res: &[[f64; 3]]) -> Stats {
    let n = res.len();
    let nf = n.max(1) as f64;
    let mut s = Stats {
        n,
        rms_mm: 0.0,
        max_mm: 0.0,
        axis_rms_mm: [0.0; 3],
        axis_max_mm: [0.0; 3],
    };
    for r in res {
        let e = Vector3::from(*r).norm();
        s.rms_mm += e * e / nf;
        s.max_mm = s.max_mm.max(e);
        for (k, v) in r.iter().enumerate() {
            s.axis_rms_mm[k] += v * v / nf;
            s.axis_max_mm[k] = s.axis_max_mm[k].max(v.abs());
        }
    }
    s.rms_mm = s.rms_mm.sqrt();
    s.axis_rms_mm = s.axis_rms_mm.map(f64::sqrt);
    s
}

fn robot_points(points: &[Measured], offset: &Vector3<f64>) -> Vec<[f64; 3]> {
    points
        .iter()
        .map(|m| {
            let p = Vector3::from(m.flange_mm) + quat(m.flange_wxyz) * offset;
            [p.x, p.y, p.z]
        })
        .collect()
}

/// The LED offset given the registration: least squares of `R p + t = f + F o` in `(o, t)`.
fn solve_offset(points: &[Measured], r: &Matrix3<f64>) -> anyhow::Result<(Vector3<f64>, f64)> {
    let mut ata = Matrix6::<f64>::zeros();
    let mut atb = Vector6::<f64>::zeros();
    for m in points {
        // Row block: [F  -I] [o; t] = R p − f
        let f = quat(m.flange_wxyz).to_rotation_matrix().into_inner();
        let mut a = nalgebra::Matrix3x6::<f64>::zeros();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&f);
        a.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-Matrix3::identity()));
        let b = r * Vector3::from(m.tracker_mm) - Vector3::from(m.flange_mm);
        ata += a.transpose() * a;
        atb += a.transpose() * b;
    }
    let eig = ata.symmetric_eigen();
    let (lo, hi) = eig
        .eigenvalues
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    let x = ata
        .cholesky()
        .map(|c| c.solve(&atb))
        .context("LED offset: normal equations singular")?;
    Ok((Vector3::new(x[0], x[1], x[2]), lo / hi.max(1e-300)))
}

/// Registration (and LED offset) from the fit and turned points; residuals of every point.
pub fn analyse(points: &[Measured], led_offset_mm: Option<[f64; 3]>) -> anyhow::Result<Analysis> {
    let fit_pts: Vec<Measured> = points
        .iter()
        .filter(|m| m.role != Role::Holdout)
        .cloned()
        .collect();
    ensure!(
        fit_pts.len() >= 4,
        "only {} fit points measured; need 4",
        fit_pts.len()
    );
    let turned = fit_pts.iter().filter(|m| m.role == Role::Turned).count();
    let tracker_fit: Vec<[f64; 3]> = fit_pts.iter().map(|m| m.tracker_mm).collect();
    let (offset, solved) = match led_offset_mm {
        Some(o) => (Vector3::from(o), false),
        None if turned >= 2 => {
            // Alternate: rigid fit for a given offset, offset (and translation) for a given fit.
            let mut o = Vector3::zeros();
            let mut converged = false;
            for _ in 0..200 {
                let reg = registration::fit(&tracker_fit, &robot_points(&fit_pts, &o), false)
                    .context("registration (LED offset solve)")?;
                let (o_new, cond) = solve_offset(&fit_pts, &reg.transform.rotation())?;
                ensure!(
                    cond > 1e-6,
                    "the LED offset is not observable from these turns (condition {cond:.1e}): turn the flange about at least two axes (--rotations 3 or more)"
                );
                let step = (o_new - o).norm();
                o = o_new;
                if step < 1e-5 {
                    converged = true;
                    break;
                }
            }
            ensure!(converged, "the LED offset solve did not converge");
            (o, true)
        }
        None => (Vector3::zeros(), false),
    };
    let robot_fit = robot_points(&fit_pts, &offset);
    let fit = registration::fit(&tracker_fit, &robot_fit, false).context("registration on the fit points")?;
    let scaled = registration::fit(&tracker_fit, &robot_fit, true).context("scale check")?;
    let tracker_all: Vec<[f64; 3]> = points.iter().map(|m| m.tracker_mm).collect();
    let robot_all = robot_points(points, &offset);
    let all = registration::fit(&tracker_all, &robot_all, false).context("registration on all points")?;
    let residual_mm = tracker_all
        .iter()
        .zip(&robot_all)
        .map(|(p, q)| {
            let e = fit.transform.apply(&Vector3::from(*p)) - Vector3::from(*q);
            [e.x, e.y, e.z]
        })
        .collect();
    // A tool: its rotation on the flange, given the registration on the fit points.
    let orientation = if !points.is_empty() && points.iter().all(|m| m.tracker_wxyz.is_some()) {
        Some(orientation_fit(points, &fit.transform.rotation())?)
    } else {
        None
    };
    Ok(Analysis {
        orientation,
        fit: fit.transform,
        all: all.transform,
        scale: scaled.scale,
        led_offset_mm: [offset.x, offset.y, offset.z],
        offset_solved: solved,
        residual_mm,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use irtrack_core::camera::RigidTransform;
    use nalgebra::UnitQuaternion;

    use crate::cmd::survey::plan::plan;
    use crate::cmd::survey::test_support::{args, measured};

    #[test]
    fn the_tool_rotation_on_the_flange_is_recovered_and_errors_are_measured_in_robot_base() {
        let mut a = args();
        a.tool = Some("probe4".into());
        a.rotations = 0;
        let planned = plan(&a).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let r = UnitQuaternion::from_euler_angles(0.3, -2.0, 0.7);
        let truth = RigidTransform::from_parts(
            &r.to_rotation_matrix().into_inner(),
            &Vector3::new(450.0, -30.0, 900.0),
        );
        let offset = [12.0, -8.0, 95.0];
        let mount = UnitQuaternion::from_euler_angles(0.4, 1.1, -0.6);
        // The tracker sees the tool turned `tracker ← base · flange · mount`, and at one
        // held-out point 0.2° more about the base's z.
        let odd = pts.iter().position(|p| p.2 == Role::Holdout).unwrap();
        let extra = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.2f64.to_radians());
        let mut m = measured(&pts, &truth, offset, |_| [0.0; 3]);
        for (i, x) in m.iter_mut().enumerate() {
            let e = if i == odd {
                extra
            } else {
                UnitQuaternion::identity()
            };
            let t = r.inverse() * e * quat(x.flange_wxyz) * mount;
            x.tracker_wxyz = Some([t.w, t.i, t.j, t.k]);
        }
        let an = analyse(&m, None).unwrap();
        let o = an.orientation.expect("orientation solved");
        assert!(
            quat(o.mount_wxyz).angle_to(&mount).to_degrees() < 1e-6,
            "{:?}",
            o.mount_wxyz
        );
        for (i, e) in o.error_deg.iter().enumerate() {
            let v = Vector3::from(*e);
            if i == odd {
                // 0.2° about the robot base's z axis.
                assert!((v - Vector3::new(0.0, 0.0, 0.2)).norm() < 1e-6, "{v:?}");
            } else {
                assert!(v.norm() < 1e-6, "point {i}: {v:?}");
            }
        }
        for (got, want) in an.led_offset_mm.iter().zip(offset) {
            assert!((got - want).abs() < 1e-6, "{:?}", an.led_offset_mm);
        }
        // Without orientations (a single LED) there is no orientation fit.
        let plain = measured(&pts, &truth, offset, |_| [0.0; 3]);
        assert!(analyse(&plain, None).unwrap().orientation.is_none());
    }

    #[test]
    fn registration_and_led_offset_are_recovered_and_tre_sees_errors() {
        let a = args();
        let planned = plan(&a).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let r = UnitQuaternion::from_euler_angles(0.3, -2.0, 0.7)
            .to_rotation_matrix()
            .into_inner();
        let truth = RigidTransform::from_parts(&r, &Vector3::new(450.0, -30.0, 900.0));
        let offset = [12.0, -8.0, 95.0];
        let exact = measured(&pts, &truth, offset, |_| [0.0; 3]);
        let an = analyse(&exact, None).unwrap();
        assert!(an.offset_solved);
        for (got, want) in an.led_offset_mm.iter().zip(offset) {
            assert!((got - want).abs() < 1e-6, "{:?}", an.led_offset_mm);
        }
        assert!(stats(&an.residual_mm).max_mm < 1e-6);
        assert!((an.scale - 1.0).abs() < 1e-9);
        // Known offset, no turns: same registration.
        let grid_only: Vec<Measured> = exact.iter().filter(|m| m.role != Role::Turned).cloned().collect();
        let an2 = analyse(&grid_only, Some(offset)).unwrap();
        assert!((an2.fit.translation_mm() - truth.translation_mm()).norm() < 1e-6);
        // Errors on the held-out points only show up in the TRE.
        let noisy = measured(&pts, &truth, offset, |i| {
            if pts[i].2 == Role::Holdout {
                [0.5, 0.0, 0.0]
            } else {
                [0.0; 3]
            }
        });
        let an3 = analyse(&noisy, None).unwrap();
        let held: Vec<[f64; 3]> = noisy
            .iter()
            .zip(&an3.residual_mm)
            .filter(|(m, _)| m.role == Role::Holdout)
            .map(|(_, r)| *r)
            .collect();
        let s = stats(&held);
        assert!(
            (s.rms_mm - 0.5).abs() < 1e-6 && (s.axis_rms_mm[0] - 0.5).abs() < 1e-6,
            "{s:?}"
        );
        // A turn about one axis only leaves the offset along it unobservable.
        let mut one_axis = a.clone();
        one_axis.rotations = 1;
        let planned = plan(&one_axis).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let m = measured(&pts, &truth, offset, |_| [0.0; 3]);
        assert!(
            analyse(&m, None).is_err() || {
                // One turned visit is below the two the solve needs: the offset is taken as 0.
                !analyse(&m, None).unwrap().offset_solved
            }
        );
    }
}
