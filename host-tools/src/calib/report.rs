//! The calibration report (Markdown) and the output directory.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use nalgebra::Rotation3;
use opencv::core::{MatTraitConst, MatTraitConstManual};

use super::{Calibration, RECOMMENDED_VIEWS, plots};

/// Overall RMS of the per-camera fits, weighting each by its corner count.
pub fn overall_rms_px(cal: &Calibration) -> f64 {
    let (sum, n) = cal.intrinsics.iter().fold((0.0, 0usize), |(s, n), f| {
        (
            s + f.rms_px * f.rms_px * f.corner_count as f64,
            n + f.corner_count,
        )
    });
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// The report as Markdown.
pub fn markdown(cal: &Calibration, images_dir: &Path) -> Result<String> {
    let mut s = String::new();
    let rig = &cal.rig;
    let b = &cal.board;
    writeln!(s, "# irtrack calibration report\n")?;
    writeln!(s, "- rig id: `{}`", rig.rig_id)?;
    writeln!(
        s,
        "- created: {} ({} Unix s)",
        crate::opencv_yaml::iso_utc(rig.created_unix_s),
        rig.created_unix_s
    )?;
    writeln!(s, "- images: `{}`", images_dir.display())?;
    writeln!(
        s,
        "- board: {}x{} inner corners, {} mm squares",
        b.cols, b.rows, b.square_mm
    )?;
    writeln!(
        s,
        "- options: outlier rejection {}, joint refinement {}, k3 {}",
        if cal.options.reject_outliers {
            format!("on (k = {})", cal.options.outlier_k)
        } else {
            "off".into()
        },
        if cal.options.joint_refine { "on" } else { "off" },
        if cal.options.fix_k3 {
            "fixed at 0"
        } else {
            "estimated"
        }
    )?;
    writeln!(s, "- views used for the rig: {}", cal.stereo_views.len())?;
    if cal.stereo_views.len() < RECOMMENDED_VIEWS {
        writeln!(
            s,
            "- **warning**: fewer than {RECOMMENDED_VIEWS} views; take more for a reliable calibration"
        )?;
    }
    writeln!(s, "\n## Reprojection error\n")?;
    writeln!(
        s,
        "Overall RMS (all cameras' fits): **{:.4} px**\n",
        overall_rms_px(cal)
    )?;
    writeln!(
        s,
        "| camera | images | board found | views used | RMS px | fx px | fy px | cx px | cy px | k1 | k2 | p1 | p2 | k3 |"
    )?;
    writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")?;
    for (ci, f) in cal.intrinsics.iter().enumerate() {
        let d = &cal.detections[ci];
        let m = &rig.cameras[ci].model;
        let k = &m.intrinsics;
        let dd = &m.distortion;
        writeln!(
            s,
            "| cam{ci} (`{}`) | {} | {} | {} | {:.4} | {:.3} | {:.3} | {:.3} | {:.3} | {:.5} | {:.5} | {:.6} | {:.6} | {:.5} |",
            cal.camera_labels[ci],
            d.found.len() + d.not_found.len(),
            d.found.len(),
            f.per_view_rms_px.len(),
            f.rms_px,
            k.fx_px,
            k.fy_px,
            k.cx_px,
            k.cy_px,
            dd.k1,
            dd.k2,
            dd.p1,
            dd.p2,
            dd.k3
        )?;
    }
    writeln!(
        s,
        "\nRMS is each camera's own `calibrateCamera` fit; the intrinsics are the final values{}.",
        if cal.joint.is_empty() {
            ""
        } else {
            " (after joint refinement)"
        }
    )?;
    writeln!(s, "\n## Rig geometry (relative to cam0)\n")?;
    writeln!(
        s,
        "| camera | baseline mm | angle between optical axes ° | stereo RMS px | rotation (axis·angle) ° | T mm |"
    )?;
    writeln!(s, "|---|---|---|---|---|---|")?;
    for i in 1..rig.cameras.len() {
        let pose = &rig.cameras[i].cam_from_cam0;
        let rv =
            Rotation3::from_matrix_unchecked(pose.rotation()).scaled_axis() * (180.0 / std::f64::consts::PI);
        let rms = cal.joint.get(i - 1).unwrap_or(&cal.pairs[i - 1]).rms_px;
        writeln!(
            s,
            "| cam{i} | {:.3} | {:.3} | {:.4} | ({:.3}, {:.3}, {:.3}) | ({:.3}, {:.3}, {:.3}) |",
            rig.baseline_mm(i)?,
            rig.optical_axis_angle_deg(i)?,
            rms,
            rv.x,
            rv.y,
            rv.z,
            pose.t_mm[0],
            pose.t_mm[1],
            pose.t_mm[2]
        )?;
    }
    if !cal.joint.is_empty() {
        writeln!(
            s,
            "\nJoint refinement (intrinsics and pose refined together; the table above shows its result):\n"
        )?;
        writeln!(
            s,
            "| pair | RMS fixed px | RMS joint px | cam0 fx fixed → joint | cami fx fixed → joint |"
        )?;
        writeln!(s, "|---|---|---|---|---|")?;
        for (k, (p, j)) in cal.pairs.iter().zip(&cal.joint).enumerate() {
            let i = k + 1;
            let (f0, fi) = j.refined.map_or((f64::NAN, f64::NAN), |m| {
                (m[0].intrinsics.fx_px, m[1].intrinsics.fx_px)
            });
            writeln!(
                s,
                "| cam0–cam{i} | {:.4} | {:.4} | {:.3} → {:.3} | {:.3} → {:.3} |",
                p.rms_px,
                j.rms_px,
                cal.intrinsics[0].model.intrinsics.fx_px,
                f0,
                cal.intrinsics[i].model.intrinsics.fx_px,
                fi
            )?;
        }
        if cal.joint.len() > 1 {
            writeln!(
                s,
                "\nWith more than two cameras, cam0's refined intrinsics are taken from its pair with cam1."
            )?;
        }
    }
    writeln!(s, "\n## Per-view RMS (px)\n")?;
    write!(s, "| view |")?;
    for ci in 0..cal.intrinsics.len() {
        write!(s, " cam{ci} |")?;
    }
    for i in 1..cal.intrinsics.len() {
        write!(s, " stereo cam0/cam{i} |")?;
    }
    writeln!(s, " status |")?;
    writeln!(s, "|{}", "---|".repeat(2 * cal.intrinsics.len() + 1))?;
    let mut all_views: Vec<&String> = cal.detections.iter().flat_map(|d| d.files.keys()).collect();
    all_views.sort();
    all_views.dedup();
    for v in all_views {
        write!(s, "| {v} |")?;
        let rejection = cal.rejected.iter().find(|r| &r.view == v);
        for (ci, f) in cal.intrinsics.iter().enumerate() {
            let before = rejection.and_then(|r| r.per_camera_rms_px.get(ci).copied().flatten());
            match f.per_view_rms_px.get(v).copied().or(before) {
                Some(e) => write!(s, " {e:.4} |")?,
                None => write!(s, " – |")?,
            }
        }
        for p in &cal.pairs {
            match p.per_view_rms_px.get(v) {
                Some(e) => write!(s, " {:.4} / {:.4} |", e[0], e[1])?,
                None => write!(s, " – |")?,
            }
        }
        let status = if let Some(r) = cal.rejected.iter().find(|r| &r.view == v) {
            format!("rejected (round {}): {}", r.round, r.why)
        } else if let Some((_, why)) = cal.skipped.iter().find(|(w, _)| w == v) {
            format!("skipped: {why}")
        } else {
            "used".into()
        };
        writeln!(s, " {status} |")?;
    }
    if !cal.skipped.is_empty() {
        writeln!(s, "\n## Skipped views\n")?;
        for (v, why) in &cal.skipped {
            writeln!(s, "- `{v}`: {why}")?;
        }
        writeln!(
            s,
            "\nViews skipped for the rig still count for the intrinsics of the cameras that saw the board."
        )?;
    }
    if cal.options.reject_outliers {
        writeln!(s, "\n## Outlier rejection\n")?;
        writeln!(
            s,
            "A view is rejected when its RMS exceeds max(median + k·1.4826·MAD, 2·median) in any camera or stereo pair; the rest is recalibrated.\n"
        )?;
        for (ci, th) in cal.thresholds_px.iter().enumerate() {
            if let Some(th) = th {
                writeln!(s, "- cam{ci} threshold (last round): {th:.4} px")?;
            }
        }
        if cal.rejected.is_empty() {
            writeln!(s, "- no view rejected")?;
        }
        for r in &cal.rejected {
            writeln!(s, "- `{}` rejected in round {}: {}", r.view, r.round, r.why)?;
        }
    }
    writeln!(s, "\n## Files\n")?;
    writeln!(s, "- `rig.irp`: parameter blob for `host-tools push-params`")?;
    writeln!(
        s,
        "- `rig.yaml`: OpenCV FileStorage (K1, D1, K2, D2, R, T, image size)"
    )?;
    for ci in 0..cal.intrinsics.len() {
        writeln!(
            s,
            "- `coverage_cam{ci}.png`: detected corners of every view in cam{ci} over its first image (red crosses: rejected)"
        )?;
    }
    writeln!(s, "- `view_errors.png`: per-view RMS per camera")?;
    Ok(s)
}

/// Writes rig.irp, rig.yaml, report.md and the PNGs into `out_dir`; returns the paths written.
pub fn write_outputs(cal: &Calibration, out_dir: &Path, images_dir: &Path) -> Result<Vec<PathBuf>> {
    std::fs::create_dir_all(out_dir)
        .with_context(|| format!("{}: cannot create directory", out_dir.display()))?;
    let mut written = Vec::new();
    let blob = cal.rig.to_blob().context("encoding the parameter blob")?;
    let p = out_dir.join("rig.irp");
    std::fs::write(&p, blob).with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    let p = out_dir.join("rig.yaml");
    crate::opencv_yaml::write_rig_yaml(&p, &cal.rig)?;
    written.push(p);
    let p = out_dir.join("report.md");
    std::fs::write(&p, markdown(cal, images_dir)?)
        .with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    for (ci, d) in cal.detections.iter().enumerate() {
        let views: Vec<plots::CoverageView<'_>> = d
            .found
            .iter()
            .map(|(v, c)| plots::CoverageView {
                corners: c,
                rejected: cal.rejected.iter().any(|r| &r.view == v),
            })
            .collect();
        let p = out_dir.join(format!("coverage_cam{ci}.png"));
        let title = format!(
            "cam{ci} ({}): {} views with the board",
            cal.camera_labels[ci],
            d.found.len()
        );
        // The camera's first image under the corners shows what the coverage is relative to.
        let first = match d.files.values().next() {
            Some(f) => {
                let m = super::detect::load_grey(f)?;
                let (w, h) = (m.cols() as u32, m.rows() as u32);
                let bytes = if m.is_continuous() {
                    m.data_bytes()?.to_vec()
                } else {
                    m.try_clone()?.data_bytes()?.to_vec()
                };
                Some((w, h, bytes))
            }
            None => None,
        };
        let background = first.as_ref().map(|(w, h, px)| plots::Background {
            width_px: *w,
            height_px: *h,
            pixels: px,
        });
        plots::coverage_png(
            &p,
            d.image_size,
            cal.board.cols,
            &views,
            &title,
            background.as_ref(),
        )?;
        written.push(p);
    }
    let mut views: Vec<String> = cal
        .detections
        .iter()
        .flat_map(|d| d.found.keys().cloned())
        .collect();
    views.sort();
    views.dedup();
    let series: Vec<(String, Vec<Option<f64>>)> = cal
        .intrinsics
        .iter()
        .enumerate()
        .map(|(ci, f)| {
            let value = |v: &String| {
                let before = cal
                    .rejected
                    .iter()
                    .find(|r| &r.view == v)
                    .and_then(|r| r.per_camera_rms_px.get(ci).copied().flatten());
                f.per_view_rms_px.get(v).copied().or(before)
            };
            (format!("cam{ci}"), views.iter().map(value).collect())
        })
        .collect();
    let rejected: Vec<bool> = views
        .iter()
        .map(|v| cal.rejected.iter().any(|r| &r.view == v))
        .collect();
    let threshold = cal
        .thresholds_px
        .iter()
        .flatten()
        .copied()
        .fold(None, |a: Option<f64>, t| Some(a.map_or(t, |a| a.min(t))));
    let p = out_dir.join("view_errors.png");
    plots::view_errors_png(&p, &views, &series, &rejected, threshold)?;
    written.push(p);
    Ok(written)
}
