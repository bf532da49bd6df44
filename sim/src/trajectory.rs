//! Marker trajectories in camera 0's frame (mm) as functions of time, and orientation
//! trajectories of a rigid multi-LED tool.

use nalgebra::{UnitQuaternion, Vector3};

use crate::SimError;

/// A path the marker follows. Parametric paths repeat with `period_s`; a recorded path is
/// linearly interpolated and holds its last sample afterwards.
#[derive(Debug, Clone, PartialEq)]
pub enum Trajectory {
    /// Smooth back-and-forth between two points (cosine easing, so velocity is continuous).
    Line {
        /// One end (mm).
        from_mm: Vector3<f64>,
        /// The other end (mm).
        to_mm: Vector3<f64>,
        /// Time for one full back-and-forth (s).
        period_s: f64,
    },
    /// Circle of `radius_mm` about `centre_mm` in the plane normal to `normal`.
    Circle {
        /// Centre (mm).
        centre_mm: Vector3<f64>,
        /// Radius (mm).
        radius_mm: f64,
        /// Normal of the circle's plane.
        normal: Vector3<f64>,
        /// Time for one turn (s).
        period_s: f64,
    },
    /// Figure-eight (lemniscate of Gerono) of half-width `size_mm` in the plane normal to `normal`.
    Figure8 {
        /// Centre (mm).
        centre_mm: Vector3<f64>,
        /// Half-width (mm).
        size_mm: f64,
        /// Normal of the figure's plane.
        normal: Vector3<f64>,
        /// Time for one figure (s).
        period_s: f64,
    },
    /// Recorded samples `(t_s, position)`, strictly increasing in time.
    Samples(Vec<(f64, Vector3<f64>)>),
    /// A marker that does not move.
    Fixed(Vector3<f64>),
    /// The origin of a tool turned about its fixed tip (pivot calibration): the tip, at
    /// `tip_tool_mm` in the tool frame, stays at `pivot_mm` while the tool turns as
    /// `orientation`, so the origin is at `pivot_mm − R(t) tip_tool_mm`. Use the same
    /// `orientation` for the tool ([`crate::tools::pivoting`] builds both).
    Pivot {
        /// The fixed pivot point (mm).
        pivot_mm: Vector3<f64>,
        /// The tip (pivot) in the tool frame (mm).
        tip_tool_mm: Vector3<f64>,
        /// How the tool turns about the pivot.
        orientation: Orientation,
    },
}

/// Two unit vectors spanning the plane normal to `n` (right-handed with `n`).
fn plane_basis(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let n = n.try_normalize(1e-12).unwrap_or_else(Vector3::z);
    let helper = if n.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let u = (helper - n * n.dot(&helper)).normalize();
    let v = n.cross(&u);
    (u, v)
}

impl Trajectory {
    /// Checks parameters once so `position` never sees bad values.
    pub fn validate(&self) -> Result<(), SimError> {
        let period_ok = |p: f64| p > 0.0 && p.is_finite();
        let bad = |field, reason: String| Err(SimError::Config { field, reason });
        match self {
            Trajectory::Line { period_s, .. }
            | Trajectory::Circle { period_s, .. }
            | Trajectory::Figure8 { period_s, .. }
                if !period_ok(*period_s) =>
            {
                bad("period_s", format!("{period_s} must be > 0"))
            }
            Trajectory::Pivot {
                pivot_mm,
                tip_tool_mm,
                orientation,
            } => {
                if !pivot_mm.iter().chain(tip_tool_mm.iter()).all(|v| v.is_finite()) {
                    return bad("trajectory", "pivot and tip must be finite".into());
                }
                orientation.validate()
            }
            Trajectory::Samples(s) if s.is_empty() => {
                bad("trajectory", "recorded path has no samples".into())
            }
            Trajectory::Samples(s) => {
                for (i, w) in s.windows(2).enumerate() {
                    if w[1].0.partial_cmp(&w[0].0) != Some(core::cmp::Ordering::Greater) {
                        return bad(
                            "trajectory",
                            format!("sample {} time {} not after {}", i + 1, w[1].0, w[0].0),
                        );
                    }
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    /// Position at time `t_s` (camera 0 frame, mm).
    pub fn position(&self, t_s: f64) -> Vector3<f64> {
        use core::f64::consts::TAU;
        match self {
            Trajectory::Line {
                from_mm,
                to_mm,
                period_s,
            } => {
                let a = 0.5 - 0.5 * (TAU * t_s / period_s).cos();
                from_mm + (to_mm - from_mm) * a
            }
            Trajectory::Circle {
                centre_mm,
                radius_mm,
                normal,
                period_s,
            } => {
                let (u, v) = plane_basis(normal);
                let (s, c) = (TAU * t_s / period_s).sin_cos();
                centre_mm + (u * c + v * s) * *radius_mm
            }
            Trajectory::Figure8 {
                centre_mm,
                size_mm,
                normal,
                period_s,
            } => {
                let (u, v) = plane_basis(normal);
                let (s, c) = (TAU * t_s / period_s).sin_cos();
                centre_mm + (u * s + v * (s * c)) * *size_mm
            }
            Trajectory::Samples(s) => {
                let i = s.partition_point(|(t, _)| *t <= t_s);
                match i {
                    0 => s.first().map(|x| x.1).unwrap_or_else(Vector3::zeros),
                    i if i >= s.len() => s[s.len() - 1].1,
                    i => {
                        let (t0, p0) = s[i - 1];
                        let (t1, p1) = s[i];
                        p0 + (p1 - p0) * ((t_s - t0) / (t1 - t0))
                    }
                }
            }
            Trajectory::Fixed(p) => *p,
            Trajectory::Pivot {
                pivot_mm,
                tip_tool_mm,
                orientation,
            } => pivot_mm - orientation.rotation(t_s) * tip_tool_mm,
        }
    }

    /// Parses a recorded path: comma-separated `t_s,x_mm,y_mm,z_mm`. A header line naming the
    /// columns is optional; with one, those four columns are looked up by name (so a
    /// `truth.csv` written by the simulator replays as is). Lines starting with `#` are skipped.
    pub fn from_csv(text: &str) -> Result<Self, SimError> {
        let mut cols = [0usize, 1, 2, 3];
        let mut samples = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let line_no = n + 1;
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let fields: Vec<&str> = line.split(',').map(str::trim).collect();
            if samples.is_empty() && fields.iter().any(|f| f.parse::<f64>().is_err()) {
                // Header: find the named columns.
                for (k, name) in ["t_s", "x_mm", "y_mm", "z_mm"].iter().enumerate() {
                    cols[k] =
                        fields
                            .iter()
                            .position(|f| f == name)
                            .ok_or_else(|| SimError::TrajectoryCsv {
                                line: line_no,
                                reason: format!("header lacks column `{name}` (need t_s,x_mm,y_mm,z_mm)"),
                            })?;
                }
                continue;
            }
            let mut v = [0.0; 4];
            for (k, c) in cols.iter().enumerate() {
                let f = fields.get(*c).ok_or_else(|| SimError::TrajectoryCsv {
                    line: line_no,
                    reason: format!("has {} fields, need column {}", fields.len(), c + 1),
                })?;
                v[k] = f.parse::<f64>().map_err(|e| SimError::TrajectoryCsv {
                    line: line_no,
                    reason: format!("field `{f}`: {e}"),
                })?;
                if !v[k].is_finite() {
                    return Err(SimError::TrajectoryCsv {
                        line: line_no,
                        reason: format!("non-finite `{f}`"),
                    });
                }
            }
            samples.push((v[0], Vector3::new(v[1], v[2], v[3])));
        }
        let t = Trajectory::Samples(samples);
        t.validate().map_err(|e| SimError::TrajectoryCsv {
            line: 0,
            reason: e.to_string(),
        })?;
        Ok(t)
    }
}

/// How a rigid tool turns over time: `R(t)` maps tool-frame vectors into camera 0's frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Orientation {
    /// A tool that keeps one orientation.
    Fixed(UnitQuaternion<f64>),
    /// Smooth turning about the tool's own axes around a base orientation:
    /// `R(t) = base · Rz(az sin(2πt/Tz + φz)) · Ry(ay sin(2πt/Ty + φy)) · Rx(ax sin(2πt/Tx + φx))`.
    /// Different periods per axis give a Lissajous-like sweep through orientation space.
    Wobble {
        /// Orientation the wobble is centred on.
        base: UnitQuaternion<f64>,
        /// Amplitudes about the tool's x, y, z axes (degrees).
        amplitude_deg: Vector3<f64>,
        /// Periods per axis (s).
        period_s: Vector3<f64>,
        /// Phases per axis (rad).
        phase_rad: Vector3<f64>,
    },
}

impl Orientation {
    /// Checks parameters once so `rotation` never sees bad values.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |reason: String| {
            Err(SimError::Config {
                field: "orientation",
                reason,
            })
        };
        match self {
            Orientation::Fixed(q) if !q.coords.iter().all(|v| v.is_finite()) => {
                bad(format!("{q:?} is not finite"))
            }
            Orientation::Wobble {
                base,
                amplitude_deg,
                period_s,
                phase_rad,
            } => {
                let finite = base
                    .coords
                    .iter()
                    .chain(amplitude_deg.iter())
                    .chain(phase_rad.iter());
                if !finite.into_iter().all(|v| v.is_finite()) {
                    return bad("base, amplitudes and phases must be finite".into());
                }
                if !period_s.iter().all(|p| *p > 0.0 && p.is_finite()) {
                    return bad(format!("periods {period_s:?} must be > 0"));
                }
                Ok(())
            }
            Orientation::Fixed(_) => Ok(()),
        }
    }

    /// Orientation at time `t_s` (tool frame to camera 0 frame).
    pub fn rotation(&self, t_s: f64) -> UnitQuaternion<f64> {
        use core::f64::consts::TAU;
        match self {
            Orientation::Fixed(q) => *q,
            Orientation::Wobble {
                base,
                amplitude_deg,
                period_s,
                phase_rad,
            } => {
                let angle =
                    |k: usize| amplitude_deg[k].to_radians() * (TAU * t_s / period_s[k] + phase_rad[k]).sin();
                let rx = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), angle(0));
                let ry = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle(1));
                let rz = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle(2));
                base * rz * ry * rx
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wobble_stays_within_amplitude_and_repeats() {
        let base = UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0);
        let o = Orientation::Wobble {
            base,
            amplitude_deg: Vector3::new(20.0, 0.0, 0.0),
            period_s: Vector3::new(2.0, 3.0, 5.0),
            phase_rad: Vector3::zeros(),
        };
        o.validate().unwrap();
        assert!(o.rotation(0.0).angle_to(&base) < 1e-12);
        // Only x turns: the angle from the base is |20° sin(2πt/2)|, largest at t = 0.5 s.
        assert!((o.rotation(0.5).angle_to(&base).to_degrees() - 20.0).abs() < 1e-9);
        for i in 0..40 {
            let t = i as f64 * 0.113;
            assert!(o.rotation(t).angle_to(&base).to_degrees() <= 20.0 + 1e-9);
            assert!(o.rotation(t).angle_to(&o.rotation(t + 2.0)) < 1e-9);
        }
        let bad = Orientation::Wobble {
            base,
            amplitude_deg: Vector3::new(20.0, 0.0, 0.0),
            period_s: Vector3::new(2.0, 0.0, 5.0),
            phase_rad: Vector3::zeros(),
        };
        assert!(bad.validate().unwrap_err().to_string().contains("orientation"));
    }

    #[test]
    fn pivot_keeps_the_tip_fixed_while_the_origin_moves() {
        let o = Orientation::Wobble {
            base: UnitQuaternion::from_euler_angles(0.2, -0.3, 0.4),
            amplitude_deg: Vector3::new(20.0, 17.0, 26.0),
            period_s: Vector3::new(2.0, 2.5, 3.25),
            phase_rad: Vector3::new(0.0, 1.0, 2.0),
        };
        let pivot = Vector3::new(5.0, -10.0, 1000.0);
        let tip = Vector3::new(20.0, 30.0, -150.0);
        let tr = Trajectory::Pivot {
            pivot_mm: pivot,
            tip_tool_mm: tip,
            orientation: o.clone(),
        };
        tr.validate().unwrap();
        let mut moved: f64 = 0.0;
        for i in 0..60 {
            let t = i as f64 * 0.05;
            let origin = tr.position(t);
            assert!((origin + o.rotation(t) * tip - pivot).norm() < 1e-9);
            moved = moved.max((origin - tr.position(0.0)).norm());
        }
        assert!(moved > 30.0, "origin moved only {moved} mm");
        let bad = Trajectory::Pivot {
            pivot_mm: Vector3::new(f64::NAN, 0.0, 0.0),
            tip_tool_mm: tip,
            orientation: o,
        };
        assert!(bad.validate().is_err());
    }

    #[test]
    fn circle_stays_on_radius_and_in_plane() {
        let c = Vector3::new(10.0, -5.0, 800.0);
        let n = Vector3::new(1.0, 1.0, 1.0);
        let tr = Trajectory::Circle {
            centre_mm: c,
            radius_mm: 120.0,
            normal: n,
            period_s: 2.0,
        };
        for i in 0..50 {
            let p = tr.position(i as f64 * 0.07);
            assert!(((p - c).norm() - 120.0).abs() < 1e-9);
            assert!((p - c).dot(&n.normalize()).abs() < 1e-9);
        }
        assert!((tr.position(0.0) - tr.position(2.0)).norm() < 1e-9);
    }

    #[test]
    fn line_reaches_both_ends() {
        let a = Vector3::new(0.0, 0.0, 600.0);
        let b = Vector3::new(100.0, 20.0, 900.0);
        let tr = Trajectory::Line {
            from_mm: a,
            to_mm: b,
            period_s: 4.0,
        };
        assert!((tr.position(0.0) - a).norm() < 1e-9);
        assert!((tr.position(2.0) - b).norm() < 1e-9);
    }

    #[test]
    fn figure8_crosses_centre_twice_per_period() {
        let c = Vector3::new(0.0, 0.0, 1000.0);
        let tr = Trajectory::Figure8 {
            centre_mm: c,
            size_mm: 100.0,
            normal: Vector3::z(),
            period_s: 1.0,
        };
        assert!((tr.position(0.0) - c).norm() < 1e-9);
        assert!((tr.position(0.5) - c).norm() < 1e-9);
        assert!(((tr.position(0.25) - c).norm() - 100.0).abs() < 1e-9);
    }

    #[test]
    fn csv_replay_interpolates_and_reads_truth_header() {
        let text = "frame,t_s,x_mm,y_mm,z_mm,visible\n0,0.0,0,0,500,1\n1,1.0,10,20,600,1\n";
        let tr = Trajectory::from_csv(text).unwrap();
        assert!((tr.position(0.5) - Vector3::new(5.0, 10.0, 550.0)).norm() < 1e-12);
        assert!((tr.position(9.0) - Vector3::new(10.0, 20.0, 600.0)).norm() < 1e-12);
        let plain = Trajectory::from_csv("# comment\n0,1,2,3\n0.5,2,3,4\n").unwrap();
        assert!((plain.position(0.25) - Vector3::new(1.5, 2.5, 3.5)).norm() < 1e-12);
    }

    #[test]
    fn csv_errors_name_the_line() {
        let e = Trajectory::from_csv("0,1,2,3\n1,1,x,3\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2"), "{e}");
        assert!(Trajectory::from_csv("t,a,b\n").is_err());
        assert!(Trajectory::from_csv("1,0,0,0\n0.5,0,0,0\n").is_err());
        assert!(Trajectory::from_csv("").is_err());
    }
}
