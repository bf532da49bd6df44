//! The survey's poses: a serpentine grid in the box with held-out and turned points, and moves
//! split to the step limits.

use anyhow::ensure;
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use super::Args;

pub(super) fn quat(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

pub(super) fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    // w ≥ 0: one sign for the same rotation on the wire.
    let q = if q.w < 0.0 {
        -q.into_inner()
    } else {
        q.into_inner()
    };
    [q.w, q.i, q.j, q.k]
}

/// Role of a survey point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Used in the registration fit.
    Fit,
    /// Held out: measures the target registration error.
    Holdout,
    /// Fit point visited with the flange turned (carries the LED offset).
    Turned,
}

impl Role {
    pub(super) fn name(self) -> &'static str {
        match self {
            Role::Fit => "fit",
            Role::Holdout => "holdout",
            Role::Turned => "turned",
        }
    }
}

/// A planned survey pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Planned {
    /// What the pose is for: fit, held out, or turned.
    pub role: Role,
    /// Flange position to move to, in the robot's frame (mm).
    pub pos_mm: [f64; 3],
    /// Flange orientation (w, x, y, z), in the robot's frame.
    pub quat_wxyz: [f64; 4],
}

/// The survey poses: a serpentine grid in the box (every `holdout_every`-th held out), then
/// `rotations` turned visits spread over the grid.
pub fn plan(args: &Args) -> anyhow::Result<Vec<Planned>> {
    for i in 0..3 {
        ensure!(
            args.box_min[i] < args.box_max[i],
            "--box-min must be below --box-max on every axis (axis {i}: {} >= {})",
            args.box_min[i],
            args.box_max[i]
        );
    }
    ensure!(args.holdout_every >= 2, "--holdout-every must be at least 2");
    let coord = |axis: usize, k: usize| {
        let n = args.grid[axis];
        if n == 1 {
            0.5 * (args.box_min[axis] + args.box_max[axis])
        } else {
            args.box_min[axis] + (args.box_max[axis] - args.box_min[axis]) * k as f64 / (n - 1) as f64
        }
    };
    let [nx, ny, nz] = args.grid;
    let mut grid = Vec::with_capacity(nx * ny * nz);
    for iz in 0..nz {
        for jy in 0..ny {
            let iy = if iz % 2 == 0 { jy } else { ny - 1 - jy };
            for jx in 0..nx {
                let ix = if (iz * ny + jy) % 2 == 0 { jx } else { nx - 1 - jx };
                grid.push([coord(0, ix), coord(1, iy), coord(2, iz)]);
            }
        }
    }
    let base = quat(args.orient);
    // A tool is turned at every grid point (its orientation on the flange needs turns, and its
    // orientation errors are measured everywhere): `--orient`, then ±`--rotation-deg` about the
    // flange's x, y, z in turn. The turns of a held-out point are held out too.
    let turns_per_point = if args.tool.is_some() {
        args.tool_orientations.max(1)
    } else {
        1
    };
    let turn = |k: usize| {
        let axis = [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()][k % 3];
        let sign = if (k / 3).is_multiple_of(2) { 1.0 } else { -1.0 };
        wxyz(&(base * UnitQuaternion::from_axis_angle(&axis, sign * args.rotation_deg.to_radians())))
    };
    let mut out: Vec<Planned> = Vec::with_capacity(grid.len() * turns_per_point + args.rotations);
    for (i, p) in grid.iter().enumerate() {
        let held = i % args.holdout_every == args.holdout_every / 2;
        out.push(Planned {
            role: if held { Role::Holdout } else { Role::Fit },
            pos_mm: *p,
            quat_wxyz: args.orient,
        });
        for k in 0..turns_per_point - 1 {
            out.push(Planned {
                role: if held { Role::Holdout } else { Role::Turned },
                pos_mm: *p,
                quat_wxyz: turn(k),
            });
        }
    }
    let fit = out.iter().filter(|p| p.role == Role::Fit).count();
    ensure!(
        fit >= 4 && out.len() > fit,
        "a grid of {} points with --holdout-every {} leaves {fit} fit and {} held-out points; need at least 4 and 1",
        out.len(),
        args.holdout_every,
        out.len() - fit
    );
    for k in 0..args.rotations {
        // Spread over the grid, in the same serpentine order.
        let at = grid[(k * grid.len()) / args.rotations.max(1) % grid.len()];
        out.push(Planned {
            role: Role::Turned,
            pos_mm: at,
            quat_wxyz: turn(k),
        });
    }
    Ok(out)
}

/// Intermediate targets from `from` to `to` so that no step exceeds the limits (the last is `to`).
pub fn split_move(
    from: ([f64; 3], [f64; 4]),
    to: ([f64; 3], [f64; 4]),
    max_step_mm: f64,
    max_rot_deg: f64,
) -> Vec<([f64; 3], [f64; 4])> {
    let (p0, p1) = (Vector3::from(from.0), Vector3::from(to.0));
    let (q0, q1) = (quat(from.1), quat(to.1));
    let dist = (p1 - p0).norm();
    let angle = q0.angle_to(&q1).to_degrees();
    let n = ((dist / max_step_mm).ceil().max((angle / max_rot_deg).ceil()) as usize).max(1);
    (1..=n)
        .map(|k| {
            let f = k as f64 / n as f64;
            let p = p0 + (p1 - p0) * f;
            let q = q0.try_slerp(&q1, f, 1e-9).unwrap_or(q1);
            ([p.x, p.y, p.z], if k == n { to.1 } else { wxyz(&q) })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd::survey::test_support::args;

    #[test]
    fn plan_holds_out_a_third_and_splits_long_moves() {
        let p = plan(&args()).unwrap();
        assert_eq!(p.len(), 27 + 6);
        assert_eq!(p.iter().filter(|x| x.role == Role::Holdout).count(), 9);
        // Serpentine: consecutive grid points are one grid step apart.
        for w in p[..27].windows(2) {
            let d = (Vector3::from(w[1].pos_mm) - Vector3::from(w[0].pos_mm)).norm();
            assert!((d - 100.0).abs() < 1e-9, "{d}");
        }
        let steps = split_move(
            ([0.0; 3], [1.0, 0.0, 0.0, 0.0]),
            (
                [120.0, 0.0, 0.0],
                wxyz(&UnitQuaternion::from_euler_angles(0.0, 0.0, 0.6)),
            ),
            50.0,
            10.0,
        );
        // 0.6 rad = 34.4° needs 4 steps; 120 mm needs 3.
        assert_eq!(steps.len(), 4);
        assert_eq!(steps[3].0, [120.0, 0.0, 0.0]);
        // A tool: every grid point in three orientations, the turns of held-out points held out.
        let mut tool = args();
        tool.tool = Some("probe4".into());
        tool.rotations = 0;
        let p = plan(&tool).unwrap();
        assert_eq!(p.len(), 27 * 3);
        assert_eq!(p.iter().filter(|x| x.role == Role::Holdout).count(), 27);
        assert_eq!(p.iter().filter(|x| x.role == Role::Turned).count(), 36);
        for w in p.chunks(3) {
            assert!(w.iter().all(|x| x.pos_mm == w[0].pos_mm));
            let a = quat(w[1].quat_wxyz).angle_to(&quat(w[0].quat_wxyz)).to_degrees();
            assert!((a - tool.rotation_deg).abs() < 1e-9, "{a}");
        }
        let mut bad = args();
        bad.box_max[1] = -200.0;
        assert!(plan(&bad).unwrap_err().to_string().contains("axis 1"));
    }
}
