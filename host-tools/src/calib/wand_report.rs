//! Outputs of a wand calibration: rig.irp, rig.yaml, report.md, observations.csv and a coverage
//! image per camera.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail};
use irtrack_core::params::RigParams;
use opencv::core::{CV_8UC3, Mat, Point, Scalar};
use opencv::{imgcodecs, imgproc};

use super::wand::Wand;
use super::wand_solve::{WandSolution, length_errors_mm};

/// Coverage grid: the image is split into this many columns and rows.
pub const COVERAGE_GRID: (usize, usize) = (8, 6);

/// Summary figures of a wand calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Figures {
    /// RMS reprojection error per camera over its used views (px).
    pub per_camera_rms_px: Vec<f64>,
    /// Mean wand length error over the used frames (mm; freely triangulated minus true length).
    pub length_mean_mm: f64,
    /// Standard deviation of the wand length error (mm).
    pub length_std_mm: f64,
    /// Largest absolute wand length error (mm).
    pub length_max_abs_mm: f64,
    /// Frames whose length error could be measured (both ends triangulated).
    pub frames_used: usize,
    /// Share of coverage-grid cells with at least one used LED, per camera.
    pub coverage: Vec<f64>,
}

fn coverage(sol: &WandSolution, rig: &RigParams) -> Vec<f64> {
    let (gc, gr) = COVERAGE_GRID;
    (0..rig.cameras.len())
        .map(|c| {
            let s = rig.cameras[c].model.image_size;
            let mut hit = vec![false; gc * gr];
            for row in &sol.views {
                if let Ok(px) = &row[c] {
                    for p in px {
                        let i = ((p.x / s.width_px as f64 * gc as f64) as usize).min(gc - 1);
                        let j = ((p.y / s.height_px as f64 * gr as f64) as usize).min(gr - 1);
                        hit[j * gc + i] = true;
                    }
                }
            }
            hit.iter().filter(|h| **h).count() as f64 / (gc * gr) as f64
        })
        .collect()
}

/// Computes the report's figures.
pub fn figures(sol: &WandSolution, rig: &RigParams, wand: &Wand) -> Figures {
    let e = length_errors_mm(sol, wand);
    let n = e.len().max(1) as f64;
    let mean = e.iter().sum::<f64>() / n;
    let std = (e.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    Figures {
        per_camera_rms_px: sol.per_camera_rms_px.clone(),
        length_mean_mm: mean,
        length_std_mm: std,
        length_max_abs_mm: e.iter().fold(0.0, |a, v| a.max(v.abs())),
        frames_used: e.len(),
        coverage: coverage(sol, rig),
    }
}

fn coverage_png(path: &Path, sol: &WandSolution, rig: &RigParams, c: usize) -> Result<()> {
    let s = rig.cameras[c].model.image_size;
    let mut img = Mat::new_rows_cols_with_default(
        s.height_px as i32,
        s.width_px as i32,
        CV_8UC3,
        Scalar::new(250.0, 250.0, 250.0, 0.0),
    )?;
    let (gc, gr) = COVERAGE_GRID;
    let grey = Scalar::new(200.0, 200.0, 200.0, 0.0);
    for i in 1..gc {
        let x = (i * s.width_px as usize / gc) as i32;
        imgproc::line(
            &mut img,
            Point::new(x, 0),
            Point::new(x, s.height_px as i32),
            grey,
            1,
            imgproc::LINE_8,
            0,
        )?;
    }
    for j in 1..gr {
        let y = (j * s.height_px as usize / gr) as i32;
        imgproc::line(
            &mut img,
            Point::new(0, y),
            Point::new(s.width_px as i32, y),
            grey,
            1,
            imgproc::LINE_8,
            0,
        )?;
    }
    for row in &sol.views {
        if let Ok(px) = &row[c] {
            {
                let pts: Vec<Point> = px
                    .iter()
                    .map(|p| Point::new(p.x.round() as i32, p.y.round() as i32))
                    .collect();
                for w in pts.windows(2) {
                    imgproc::line(
                        &mut img,
                        w[0],
                        w[1],
                        Scalar::new(230.0, 200.0, 170.0, 0.0),
                        1,
                        imgproc::LINE_AA,
                        0,
                    )?;
                }
                for (k, p) in pts.iter().enumerate() {
                    let colour = if k == 0 {
                        Scalar::new(180.0, 119.0, 31.0, 0.0)
                    } else {
                        Scalar::new(14.0, 127.0, 255.0, 0.0)
                    };
                    imgproc::circle(&mut img, *p, 2, colour, imgproc::FILLED, imgproc::LINE_AA, 0)?;
                }
            }
        }
    }
    imgproc::put_text(
        &mut img,
        &format!("cam{c}: used wand LEDs (blue: end 0)"),
        Point::new(8, 18),
        imgproc::FONT_HERSHEY_SIMPLEX,
        0.5,
        Scalar::new(20.0, 20.0, 20.0, 0.0),
        1,
        imgproc::LINE_AA,
        false,
    )?;
    let name = path
        .to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8", path.display()))?;
    if !imgcodecs::imwrite_def(name, &img)? {
        bail!("{}: OpenCV could not write the PNG", path.display());
    }
    Ok(())
}

fn markdown(
    sol: &WandSolution,
    rig: &RigParams,
    wand: &Wand,
    fig: &Figures,
    frames: &[String],
) -> Result<String> {
    let mut s = String::new();
    writeln!(s, "# Wand calibration `{}`\n", rig.rig_id)?;
    writeln!(
        s,
        "Wand LEDs at {:?} mm ({} mm end to end); {} frames, {} cameras; {} frames used.\n",
        wand.leds_mm,
        wand.length_mm(),
        frames.len(),
        rig.cameras.len(),
        fig.frames_used
    )?;
    writeln!(s, "## World error (wand length)\n")?;
    writeln!(
        s,
        "Both ends triangulated freely with the calibrated rig in every used frame: length error mean \
         {:+.4} mm, std {:.4} mm, max |error| {:.4} mm over {} frames.\n",
        fig.length_mean_mm, fig.length_std_mm, fig.length_max_abs_mm, fig.frames_used
    )?;
    writeln!(s, "## Cameras\n")?;
    writeln!(
        s,
        "| camera | reprojection RMS px | views used | coverage | baseline to cam0 mm | angle between optical axes ° |"
    )?;
    writeln!(s, "|---|---|---|---|---|---|")?;
    for c in 0..rig.cameras.len() {
        let (b, a) = if c == 0 {
            ("–".to_string(), "–".to_string())
        } else {
            (
                format!("{:.3}", rig.baseline_mm(c)?),
                format!("{:.3}", rig.optical_axis_angle_deg(c)?),
            )
        };
        writeln!(
            s,
            "| cam{c} | {:.4} | {} | {:.0} % of {}×{} cells | {b} | {a} |",
            fig.per_camera_rms_px[c],
            sol.per_camera_views[c],
            fig.coverage[c] * 100.0,
            COVERAGE_GRID.0,
            COVERAGE_GRID.1
        )?;
    }
    writeln!(s, "\n## Intrinsics\n")?;
    writeln!(s, "| camera | fx | fy | cx | cy | k1 | k2 | p1 | p2 | k3 |")?;
    writeln!(s, "|---|---|---|---|---|---|---|---|---|---|")?;
    for (c, cam) in rig.cameras.iter().enumerate() {
        let k = &cam.model.intrinsics;
        let d = cam.model.distortion.as_array();
        writeln!(
            s,
            "| cam{c} | {:.3} | {:.3} | {:.3} | {:.3} | {:.5} | {:.5} | {:.6} | {:.6} | {:.5} |",
            k.fx_px, k.fy_px, k.cx_px, k.cy_px, d[0], d[1], d[2], d[3], d[4]
        )?;
    }
    writeln!(s, "\n## Initial poses (essential matrices)\n")?;
    for p in &sol.init_pairs {
        writeln!(
            s,
            "- cam{} from cam{}: {} shared frames, {} of {} LED correspondences inliers, scale {:.3} mm",
            p.camera, p.reference, p.shared_frames, p.inliers, p.correspondences, p.scale_mm
        )?;
    }
    writeln!(s, "\n## Bundle adjustment rounds\n")?;
    for (i, r) in sol.rounds.iter().enumerate() {
        let boards = if r.board_views > 0 {
            format!(", {} board views at {:.4} px", r.board_views, r.board_rms_px)
        } else {
            String::new()
        };
        writeln!(
            s,
            "- round {}: {} views, RMS {:.4} px{boards}, {} evaluations ({}), {} outlier views rejected",
            i + 1,
            r.views,
            r.rms_px,
            r.evaluations,
            r.termination,
            r.rejected
        )?;
    }
    if !sol.boards.is_empty() {
        writeln!(s, "\n## Checkerboard views\n")?;
        writeln!(
            s,
            "Each camera's board views took part in the adjustment that refined the intrinsics, \
             every view with its own board pose.\n"
        )?;
        writeln!(s, "| camera | board views used | rejected | corner RMS px |")?;
        writeln!(s, "|---|---|---|---|")?;
        for c in 0..rig.cameras.len() {
            let used: Vec<f64> = sol
                .boards
                .iter()
                .filter(|b| b.camera == c && b.rejected.is_none())
                .map(|b| b.rms_px)
                .collect();
            let rejected = sol
                .boards
                .iter()
                .filter(|b| b.camera == c && b.rejected.is_some())
                .count();
            let rms = (used.iter().map(|e| e * e).sum::<f64>() / used.len().max(1) as f64).sqrt();
            writeln!(s, "| cam{c} | {} | {rejected} | {rms:.4} |", used.len())?;
        }
        for b in sol.boards.iter().filter(|b| b.rejected.is_some()) {
            writeln!(
                s,
                "\n- cam{} view {}: {}",
                b.camera,
                b.view,
                b.rejected.as_deref().unwrap_or_default()
            )?;
        }
    }
    writeln!(s, "\n## Observations used and rejected\n")?;
    writeln!(s, "| camera | used | rejected | reasons |")?;
    writeln!(s, "|---|---|---|---|")?;
    for c in 0..rig.cameras.len() {
        let mut reasons: BTreeMap<&str, usize> = BTreeMap::new();
        let mut used = 0;
        for row in &sol.views {
            match &row[c] {
                Ok(_) => used += 1,
                Err(r) => *reasons.entry(r.kind()).or_insert(0) += 1,
            }
        }
        let list: Vec<String> = reasons.iter().map(|(k, v)| format!("{v} {k}")).collect();
        writeln!(
            s,
            "| cam{c} | {used} | {} | {} |",
            reasons.values().sum::<usize>(),
            list.join(", ")
        )?;
    }
    writeln!(
        s,
        "\nEvery camera view's status is in `observations.csv`; `coverage_cam<i>.png` shows the used LEDs."
    )?;
    Ok(s)
}

fn observations_csv(sol: &WandSolution, frames: &[String]) -> String {
    let mut s = String::from("frame,camera,status,reason\n");
    for (f, row) in sol.views.iter().enumerate() {
        for (c, r) in row.iter().enumerate() {
            let (status, why) = match r {
                Ok(_) => ("used", String::new()),
                Err(e) => ("rejected", e.to_string().replace(',', ";")),
            };
            let _ = writeln!(s, "{},{c},{status},{why}", frames[f]);
        }
    }
    s
}

/// Writes every output into `out_dir`; returns the paths written.
pub fn write_outputs(
    out_dir: &Path,
    sol: &WandSolution,
    rig: &RigParams,
    wand: &Wand,
    frames: &[String],
) -> Result<(Vec<PathBuf>, Figures)> {
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("{}: cannot create directory", out_dir.display()))?;
    let mut written = Vec::new();
    let p = out_dir.join("rig.irp");
    std::fs::write(&p, rig.to_blob().context("encoding the parameter blob")?)
        .with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    let p = out_dir.join("rig.yaml");
    crate::opencv_yaml::write_rig_yaml(&p, rig)?;
    written.push(p);
    let fig = figures(sol, rig, wand);
    let p = out_dir.join("report.md");
    std::fs::write(&p, markdown(sol, rig, wand, &fig, frames)?)
        .with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    let p = out_dir.join("observations.csv");
    std::fs::write(&p, observations_csv(sol, frames))
        .with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    for c in 0..rig.cameras.len() {
        let p = out_dir.join(format!("coverage_cam{c}.png"));
        coverage_png(&p, sol, rig, c)?;
        written.push(p);
    }
    Ok((written, fig))
}
