//! The survey report: Markdown, CSV and the error-against-distance figure, ending in PASS or
//! FAIL.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use irtrack_core::camera::RigidTransform;
use nalgebra::Vector3;

use super::Args;
use super::analysis::{Analysis, Stats, stats};
use super::cell::Measured;
use super::plan::Role;

/// Orientation errors (degrees) of a set of points.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AngleStats {
    /// Number of points.
    pub n: usize,
    /// RMS of the error angles (deg).
    pub rms_deg: f64,
    /// Largest error angle (deg).
    pub max_deg: f64,
}

fn angle_stats(errors: &[[f64; 3]]) -> AngleStats {
    let a: Vec<f64> = errors.iter().map(|e| Vector3::from(*e).norm()).collect();
    AngleStats {
        n: a.len(),
        rms_deg: (a.iter().map(|x| x * x).sum::<f64>() / a.len().max(1) as f64).sqrt(),
        max_deg: a.iter().copied().fold(0.0, f64::max),
    }
}

/// The survey report.
pub struct Report {
    /// With `--tool`: orientation errors of the fit (and turned) points and of the held-out
    /// points, in robot base; the held-out maximum is judged against `--tolerance-deg`.
    pub orientation: Option<(AngleStats, AngleStats)>,
    /// Fiducial registration error: residuals of the fit and turned points.
    pub fre: Stats,
    /// Target registration error: residuals of the held-out points; judged against
    /// `--tolerance-mm`.
    pub tre: Stats,
    /// Umeyama scale on the fit points; 1 when the calibration's units are right.
    pub scale: f64,
    /// Every check passed (TRE within tolerance, scale within `--max-scale-error-ppm`, a held-out
    /// point measured).
    pub pass: bool,
    /// The verdict in one line: the figures when passed, else every failed check.
    pub verdict: String,
    md: String,
    csv: String,
    json: String,
    /// (distance from camera 0, 3-D error, held out) per point.
    fig: Vec<(f64, f64, bool)>,
}

impl Report {
    pub(super) fn new(
        args: &Args,
        points: &[Measured],
        a: &Analysis,
        old_world: Option<&RigidTransform>,
        skipped: &[String],
    ) -> Self {
        let pick = |holdout: bool| -> Vec<[f64; 3]> {
            points
                .iter()
                .zip(&a.residual_mm)
                .filter(|(m, _)| (m.role == Role::Holdout) == holdout)
                .map(|(_, r)| *r)
                .collect()
        };
        let fre = stats(&pick(false));
        let tre = stats(&pick(true));
        let orientation = a.orientation.as_ref().map(|o| {
            let pick = |holdout: bool| -> Vec<[f64; 3]> {
                points
                    .iter()
                    .zip(&o.error_deg)
                    .filter(|(m, _)| (m.role == Role::Holdout) == holdout)
                    .map(|(_, e)| *e)
                    .collect()
            };
            (angle_stats(&pick(false)), angle_stats(&pick(true)))
        });
        let cam0_from_tracker = old_world.map(RigidTransform::inverse);
        let dist = |m: &Measured| {
            let p = Vector3::from(m.tracker_mm);
            cam0_from_tracker.map_or(p, |t| t.apply(&p)).norm()
        };
        let scale_ppm = (a.scale - 1.0) * 1e6;
        let mut problems = Vec::new();
        if tre.n == 0 {
            problems.push("no held-out point was measured".to_string());
        }
        if tre.max_mm > args.tolerance_mm {
            problems.push(format!(
                "TRE max {:.3} mm exceeds the tolerance {:.3} mm",
                tre.max_mm, args.tolerance_mm
            ));
        }
        if scale_ppm.abs() > args.max_scale_error_ppm {
            problems.push(format!(
                "scale {:.6} is {:.0} ppm off 1 (limit {:.0} ppm): check the calibration's units",
                a.scale, scale_ppm, args.max_scale_error_ppm
            ));
        }
        if let Some((_, held)) = orientation
            && held.max_deg > args.tolerance_deg
        {
            problems.push(format!(
                "orientation error max {:.3}° (held out) exceeds the tolerance {:.3}°",
                held.max_deg, args.tolerance_deg
            ));
        }
        let pass = problems.is_empty();
        let verdict = if pass {
            let mut v = format!(
                "TRE max {:.3} mm within {:.3} mm, scale within {:.0} ppm",
                tre.max_mm, args.tolerance_mm, args.max_scale_error_ppm
            );
            if let Some((_, held)) = orientation {
                let _ = write!(
                    v,
                    ", orientation error max {:.3}° within {:.3}°",
                    held.max_deg, args.tolerance_deg
                );
            }
            v
        } else {
            problems.join("; ")
        };
        let fig: Vec<(f64, f64, bool)> = points
            .iter()
            .zip(&a.residual_mm)
            .map(|(m, r)| (dist(m), Vector3::from(*r).norm(), m.role == Role::Holdout))
            .collect();

        let mut md = String::new();
        let w = &mut md;
        let _ = writeln!(w, "# Cell survey\n");
        let _ = writeln!(w, "**{}** — {}\n", if pass { "PASS" } else { "FAIL" }, verdict);
        let _ = writeln!(
            w,
            "Box [{:.1}, {:.1}, {:.1}] … [{:.1}, {:.1}, {:.1}] mm, grid {}×{}×{}, {} turned visits, {} frames per point, settle {} ms. Measured {} points ({} skipped).\n",
            args.box_min[0],
            args.box_min[1],
            args.box_min[2],
            args.box_max[0],
            args.box_max[1],
            args.box_max[2],
            args.grid[0],
            args.grid[1],
            args.grid[2],
            args.rotations,
            args.frames,
            args.settle_ms,
            points.len(),
            skipped.len()
        );
        let _ = writeln!(
            w,
            "| | points | RMS (mm) | max (mm) | x RMS / max | y RMS / max | z RMS / max |"
        );
        let _ = writeln!(w, "|---|---|---|---|---|---|---|");
        for (name, s) in [("FRE (fit points)", fre), ("TRE (held out)", tre)] {
            let _ = writeln!(
                w,
                "| {name} | {} | {:.3} | {:.3} | {:.3} / {:.3} | {:.3} / {:.3} | {:.3} / {:.3} |",
                s.n,
                s.rms_mm,
                s.max_mm,
                s.axis_rms_mm[0],
                s.axis_max_mm[0],
                s.axis_rms_mm[1],
                s.axis_max_mm[1],
                s.axis_rms_mm[2],
                s.axis_max_mm[2]
            );
        }
        if let (Some((fit_o, held_o)), Some(o)) = (orientation, &a.orientation) {
            let _ = writeln!(
                w,
                "\nOrientation of tool {:?} in robot base (tracked, registered, against flange · mount):\n",
                args.tool.as_deref().unwrap_or("")
            );
            let _ = writeln!(w, "| | points | RMS (°) | max (°) |");
            let _ = writeln!(w, "|---|---|---|---|");
            for (name, s) in [("fit points", fit_o), ("held out", held_o)] {
                let _ = writeln!(w, "| {name} | {} | {:.4} | {:.4} |", s.n, s.rms_deg, s.max_deg);
            }
            let rv = super::plan::quat(o.mount_wxyz).scaled_axis().map(f64::to_degrees);
            let _ = writeln!(
                w,
                "\nTool rotation on the flange (flange ← tool): quaternion w, x, y, z [{:.6}, {:.6}, {:.6}, {:.6}], rotation vector [{:.3}, {:.3}, {:.3}]° (solved on the fit points). Its origin on the flange is the offset below.",
                o.mount_wxyz[0], o.mount_wxyz[1], o.mount_wxyz[2], o.mount_wxyz[3], rv.x, rv.y, rv.z
            );
        }
        let _ = writeln!(
            w,
            "\nUmeyama scale {:.6} ({scale_ppm:+.0} ppm; checked, not fitted — the registration is rigid).",
            a.scale
        );
        let _ = writeln!(
            w,
            "LED offset in the flange frame: [{:.3}, {:.3}, {:.3}] mm ({}).",
            a.led_offset_mm[0],
            a.led_offset_mm[1],
            a.led_offset_mm[2],
            if a.offset_solved {
                "solved jointly with the registration from the turned visits"
            } else if args.led_offset_mm.is_some() {
                "given"
            } else {
                "taken as 0: no turned visits"
            }
        );
        let t = a.all.translation_mm();
        let _ = writeln!(
            w,
            "Registration robot_from_tracker (all points): t = [{:.3}, {:.3}, {:.3}] mm.\n",
            t.x, t.y, t.z
        );
        let _ = writeln!(w, "## Worst points\n");
        let _ = writeln!(
            w,
            "| # | role | robot x, y, z (mm) | distance to camera 0 (mm) | error (mm) | ex, ey, ez (mm) |"
        );
        let _ = writeln!(w, "|---|---|---|---|---|---|");
        let mut order: Vec<usize> = (0..points.len()).collect();
        order.sort_by(|&i, &j| fig[j].1.total_cmp(&fig[i].1));
        for &i in order.iter().take(5) {
            let (m, r) = (&points[i], a.residual_mm[i]);
            let _ = writeln!(
                w,
                "| {} | {} | {:.2}, {:.2}, {:.2} | {:.0} | {:.3} | {:+.3}, {:+.3}, {:+.3} |",
                m.index + 1,
                m.role.name(),
                m.flange_mm[0],
                m.flange_mm[1],
                m.flange_mm[2],
                fig[i].0,
                fig[i].1,
                r[0],
                r[1],
                r[2]
            );
        }
        if !skipped.is_empty() {
            let _ = writeln!(w, "\n## Skipped\n");
            for s in skipped {
                let _ = writeln!(w, "- {s}");
            }
        }
        let _ = writeln!(
            w,
            "\n![error vs distance from the cameras](error-vs-distance.png)\n\nPer point: survey.csv."
        );

        // The tool's columns come last: readers of the single-LED columns are unaffected.
        let mut csv = String::from(
            "index,role,robot_x_mm,robot_y_mm,robot_z_mm,q1,q2,q3,q4,tracker_x_mm,tracker_y_mm,tracker_z_mm,tracker_sd_mm,frames,distance_cam0_mm,err_x_mm,err_y_mm,err_z_mm,err_mm",
        );
        if a.orientation.is_some() {
            csv.push_str(",tracker_qw,tracker_qx,tracker_qy,tracker_qz,orient_err_x_deg,orient_err_y_deg,orient_err_z_deg,orient_err_deg");
        }
        csv.push('\n');
        for (i, m) in points.iter().enumerate() {
            let r = a.residual_mm[i];
            let _ = write!(
                csv,
                "{},{},{:.3},{:.3},{:.3},{:.6},{:.6},{:.6},{:.6},{:.4},{:.4},{:.4},{:.4},{},{:.1},{:.4},{:.4},{:.4},{:.4}",
                m.index,
                m.role.name(),
                m.flange_mm[0],
                m.flange_mm[1],
                m.flange_mm[2],
                m.flange_wxyz[0],
                m.flange_wxyz[1],
                m.flange_wxyz[2],
                m.flange_wxyz[3],
                m.tracker_mm[0],
                m.tracker_mm[1],
                m.tracker_mm[2],
                Vector3::from(m.tracker_sd_mm).norm(),
                m.frames,
                fig[i].0,
                r[0],
                r[1],
                r[2],
                fig[i].1
            );
            if let (Some(o), Some(t)) = (&a.orientation, m.tracker_wxyz) {
                let e = o.error_deg[i];
                let _ = write!(
                    csv,
                    ",{:.8},{:.8},{:.8},{:.8},{:.5},{:.5},{:.5},{:.5}",
                    t[0],
                    t[1],
                    t[2],
                    t[3],
                    e[0],
                    e[1],
                    e[2],
                    Vector3::from(e).norm()
                );
            }
            csv.push('\n');
        }
        let s_json = |s: &Stats| {
            serde_json::json!({
                "points": s.n, "rms_mm": s.rms_mm, "max_mm": s.max_mm,
                "axis_rms_mm": s.axis_rms_mm, "axis_max_mm": s.axis_max_mm,
            })
        };
        let a_json =
            |s: &AngleStats| serde_json::json!({"points": s.n, "rms_deg": s.rms_deg, "max_deg": s.max_deg});
        let json = serde_json::json!({
            "pass": pass,
            "verdict": verdict,
            "fre": s_json(&fre),
            "tre": s_json(&tre),
            "scale": a.scale,
            "led_offset_mm": a.led_offset_mm,
            "led_offset_solved": a.offset_solved,
            "robot_from_tracker": {
                "rotation_row_major": a.all.rotation().transpose().as_slice(),
                "translation_mm": a.all.translation_mm().as_slice(),
            },
            "tool": args.tool,
            "orientation": match (orientation, &a.orientation) {
                (Some((f, h)), Some(o)) => serde_json::json!({
                    "fit": a_json(&f),
                    "holdout": a_json(&h),
                    "tolerance_deg": args.tolerance_deg,
                    "mount_wxyz": o.mount_wxyz,
                }),
                _ => serde_json::Value::Null,
            },
            "points_measured": points.len(),
            "points_skipped": skipped.len(),
        });
        Report {
            orientation,
            json: serde_json::to_string_pretty(&json).unwrap_or_default(),
            fre,
            tre,
            scale: a.scale,
            pass,
            verdict,
            md,
            csv,
            fig,
        }
    }

    /// Lines printed at the end of a run (the test reads them).
    pub fn summary(&self) -> String {
        let orientation = match self.orientation {
            Some((f, h)) => format!(
                "survey: orientation error RMS {:.4}° max {:.4}° ({} points, fit)\n\
                 survey: orientation held out RMS {:.4}° max {:.4}° ({} points)\n",
                f.rms_deg, f.max_deg, f.n, h.rms_deg, h.max_deg, h.n
            ),
            None => String::new(),
        };
        format!(
            "survey: FRE RMS {:.3} mm max {:.3} mm ({} points)\n\
             survey: TRE RMS {:.3} mm max {:.3} mm ({} points); per axis RMS x {:.3} y {:.3} z {:.3} mm\n\
             {}survey: scale {:.6}\n\
             survey: {} — {}\n",
            self.fre.rms_mm,
            self.fre.max_mm,
            self.fre.n,
            self.tre.rms_mm,
            self.tre.max_mm,
            self.tre.n,
            self.tre.axis_rms_mm[0],
            self.tre.axis_rms_mm[1],
            self.tre.axis_rms_mm[2],
            orientation,
            self.scale,
            if self.pass { "PASS" } else { "FAIL" },
            self.verdict
        )
    }

    pub(super) fn write(&self, dir: &Path) -> anyhow::Result<()> {
        std::fs::write(dir.join("survey.md"), &self.md).context("write survey.md")?;
        std::fs::write(dir.join("survey.csv"), &self.csv).context("write survey.csv")?;
        std::fs::write(dir.join("survey.json"), &self.json).context("write survey.json")?;
        plot::error_vs_distance(&dir.join("error-vs-distance.png"), &self.fig)
    }
}

mod plot {
    use std::path::Path;

    use plotters::prelude::*;

    use crate::calib::plots::{FONT, draw_err, draw_legend, ensure_font, write_rgb_png};

    const W: u32 = 900;
    const H: u32 = 560;

    /// The paper's Fig. 11: 3-D error of every point against its distance from the cameras.
    pub fn error_vs_distance(path: &Path, pts: &[(f64, f64, bool)]) -> anyhow::Result<()> {
        ensure_font()?;
        anyhow::ensure!(!pts.is_empty(), "no survey points to plot");
        let (dmin, dmax) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        });
        let emax = pts.iter().map(|p| p.1).fold(0.0, f64::max).max(1e-3);
        let pad = ((dmax - dmin) * 0.1).max(10.0);
        let mut rgb = vec![255u8; (W * H * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (W, H)).into_drawing_area();
            let mut chart = ChartBuilder::on(&root)
                .caption("survey: error vs distance from camera 0", (FONT, 20))
                .margin(14)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d((dmin - pad)..(dmax + pad), 0.0..emax * 1.15)
                .map_err(draw_err)?;
            chart
                .configure_mesh()
                .x_desc("distance from camera 0 (mm)")
                .y_desc("3-D error after registration (mm)")
                .x_label_formatter(&|d| format!("{d:.0}"))
                .y_label_formatter(&|v| format!("{v:.2}"))
                .label_style((FONT, 14))
                .draw()
                .map_err(draw_err)?;
            for (held, colour, label) in [
                (false, RGBColor(20, 80, 220), "fit points (FRE)"),
                (true, RGBColor(210, 30, 30), "held-out points (TRE)"),
            ] {
                chart
                    .draw_series(
                        pts.iter()
                            .filter(|p| p.2 == held)
                            .map(|p| Circle::new((p.0, p.1), 5, colour.filled())),
                    )
                    .map_err(draw_err)?
                    .label(label)
                    .legend(move |(x, y)| Circle::new((x + 10, y), 5, colour.filled()));
            }
            draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 14)?;
            root.present().map_err(draw_err)?;
        }
        write_rgb_png(path, W, H, &rgb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use irtrack_core::camera::RigidTransform;

    use crate::cmd::survey::analysis::analyse;
    use crate::cmd::survey::plan::plan;
    use crate::cmd::survey::test_support::{args, measured};

    #[test]
    fn report_fails_on_tolerance_and_scale() {
        let mut a = args();
        a.rotations = 0;
        let planned = plan(&a).unwrap();
        let pts: Vec<_> = planned.iter().map(|p| (p.pos_mm, p.quat_wxyz, p.role)).collect();
        let m = measured(&pts, &RigidTransform::IDENTITY, [0.0; 3], |i| {
            if i % 3 == 1 { [0.0, 0.0, 0.4] } else { [0.0; 3] }
        });
        let an = analyse(&m, None).unwrap();
        let r = Report::new(&a, &m, &an, None, &[]);
        assert!(r.pass, "{}", r.verdict);
        a.tolerance_mm = 0.2;
        let r = Report::new(&a, &m, &an, None, &[]);
        assert!(!r.pass && r.verdict.contains("TRE max"), "{}", r.verdict);
        // Tracker 1 % too large: the scale check fails even with a generous tolerance.
        let big: Vec<Measured> = m
            .iter()
            .map(|x| Measured {
                tracker_mm: x.tracker_mm.map(|v| v * 1.01),
                ..x.clone()
            })
            .collect();
        a.tolerance_mm = 50.0;
        let an = analyse(&big, None).unwrap();
        let r = Report::new(&a, &big, &an, None, &[]);
        assert!(!r.pass && r.verdict.contains("ppm"), "{}", r.verdict);
        let dir = std::env::temp_dir().join(format!("survey-report-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        r.write(&dir).unwrap();
        assert!(
            std::fs::metadata(dir.join("error-vs-distance.png"))
                .unwrap()
                .len()
                > 1000
        );
        assert!(
            std::fs::read_to_string(dir.join("survey.md"))
                .unwrap()
                .contains("FAIL")
        );
        let j: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("survey.json")).unwrap()).unwrap();
        assert_eq!(j["pass"], false);
        assert_eq!(j["tre"]["points"], r.tre.n);
        assert!(j["orientation"].is_null() && r.orientation.is_none());
        let _ = std::fs::remove_dir_all(&dir);
    }
}
