//! Quality gate of a checkerboard calibration (`host-tools calibrate`) and its likely causes
//! (docs/calibration.md, "Quality gates").

use super::Calibration;
use super::quality::{Check, Gate};
use super::report::overall_rms_px;

/// Largest RMS reprojection error of a camera's board corners (px), for its own intrinsic fit
/// and for every stereo pair. Simulated views give about 0.05 px; a board that bends, a blurred
/// or badly lit view, or a wrongly paired view set give pixels.
pub const MAX_RMS_PX: f64 = 1.0;
/// Fewest views with the board in every camera that are used (4 is the hard floor, 10–20 are
/// recommended).
pub const MIN_VIEWS_USED: usize = 6;
/// Smallest share of an 8×6 grid over each image holding a detected corner: distortion and
/// principal point are only determined where corners were seen.
pub const MIN_COVERAGE: f64 = 0.25;
/// Largest relative difference of the baseline cam0–cam1 from `--expect-baseline-mm`.
pub const MAX_BASELINE_REL: f64 = 0.01;
/// Coverage grid of the gate (columns, rows).
const GRID: (usize, usize) = (8, 6);

/// Share of grid cells holding a detected (and used) corner, per camera.
pub fn coverage(cal: &Calibration) -> Vec<f64> {
    let (gc, gr) = GRID;
    cal.detections
        .iter()
        .map(|d| {
            let (w, h) = (d.image_size.0.max(1) as f64, d.image_size.1.max(1) as f64);
            let mut hit = vec![false; gc * gr];
            for (view, corners) in &d.found {
                if cal.rejected.iter().any(|r| &r.view == view) {
                    continue;
                }
                for p in corners {
                    let i = ((p.x as f64 / w * gc as f64).max(0.0) as usize).min(gc - 1);
                    let j = ((p.y as f64 / h * gr as f64).max(0.0) as usize).min(gr - 1);
                    hit[j * gc + i] = true;
                }
            }
            hit.iter().filter(|v| **v).count() as f64 / (gc * gr) as f64
        })
        .collect()
}

/// Judges a checkerboard calibration. `expect_baseline_mm`: the distance between camera 0 and
/// camera 1 as measured on the rig, if given.
pub fn judge(cal: &Calibration, expect_baseline_mm: Option<f64>) -> anyhow::Result<Gate> {
    let mut gate = Gate::new("checkerboard");
    let n_cam = cal.rig.cameras.len();
    gate.rms_px = cal.intrinsics.iter().map(|f| f.rms_px).collect();
    for (c, f) in cal.intrinsics.iter().enumerate() {
        gate.checks.push(Check::at_most(
            format!("cam{c} board corners RMS"),
            f.rms_px,
            MAX_RMS_PX,
            "px",
        ));
    }
    let pairs = if cal.joint.is_empty() {
        &cal.pairs
    } else {
        &cal.joint
    };
    for (i, p) in pairs.iter().enumerate() {
        gate.checks.push(Check::at_most(
            format!("stereo cam0–cam{} RMS", i + 1),
            p.rms_px,
            MAX_RMS_PX,
            "px",
        ));
        gate.figure(&format!("stereo_rms_px_cam{}", i + 1), p.rms_px);
    }
    gate.checks.push(Check::at_least(
        "views used",
        cal.stereo_views.len() as f64,
        MIN_VIEWS_USED as f64,
        "",
    ));
    let cov = coverage(cal);
    for (c, v) in cov.iter().enumerate() {
        gate.checks.push(Check::at_least(
            format!("cam{c} image coverage"),
            v * 100.0,
            MIN_COVERAGE * 100.0,
            "%",
        ));
    }
    let baseline = if n_cam > 1 {
        cal.rig.baseline_mm(1)?
    } else {
        f64::NAN
    };
    if let Some(expected) = expect_baseline_mm {
        gate.checks.push(Check::at_most(
            "baseline cam0–cam1 off --expect-baseline-mm",
            (baseline - expected).abs() / expected * 100.0,
            MAX_BASELINE_REL * 100.0,
            "%",
        ));
        gate.figure("expected_baseline_mm", expected);
    }
    gate.figure("board_rms_px", overall_rms_px(cal));
    gate.figure("views_used", cal.stereo_views.len() as f64);
    gate.figure("square_mm", cal.board.square_mm);
    gate.figure("board_cols", f64::from(cal.board.cols));
    gate.figure("board_rows", f64::from(cal.board.rows));
    gate.figure("baseline_mm_cam1", baseline);
    gate.figure(
        "coverage_min_pct",
        cov.iter().copied().fold(f64::INFINITY, f64::min) * 100.0,
    );
    if gate.failed().is_empty() {
        return Ok(gate);
    }
    // Causes, most telling first.
    if let Some(expected) = expect_baseline_mm
        && (baseline - expected).abs() / expected > MAX_BASELINE_REL
    {
        // Every length of a checkerboard calibration scales with the square size.
        let square = cal.board.square_mm * expected / baseline;
        gate.causes.push(format!(
            "the board's square size: the baseline came out {baseline:.1} mm, you expect {expected:.1} mm; every \
             length scales with --square-mm, so the data fit squares of {square:.2} mm, you gave {} mm. Measure the \
             printed squares (or the baseline) again",
            cal.board.square_mm
        ));
    }
    for (c, f) in cal.intrinsics.iter().enumerate() {
        if f.rms_px > MAX_RMS_PX {
            let worst = f
                .per_view_rms_px
                .iter()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map(|(v, e)| format!(" (worst view {v}: {e:.2} px)"))
                .unwrap_or_default();
            gate.causes.push(format!(
                "cam{c}'s corners do not fit one camera model{worst}: a board that is not flat, blurred or \
                 overexposed views, or images of another camera in cam{c}'s folder; try --reject-outliers"
            ));
        }
    }
    for (i, p) in pairs.iter().enumerate() {
        let c = i + 1;
        if p.rms_px > MAX_RMS_PX && cal.intrinsics.iter().all(|f| f.rms_px <= MAX_RMS_PX) {
            gate.causes.push(format!(
                "each camera fits on its own but cam0 and cam{c} do not fit together (stereo RMS {:.2} px): the \
                 views are paired wrongly (file names of different moments), or the cameras moved between views",
                p.rms_px
            ));
        }
    }
    if cal.stereo_views.len() < MIN_VIEWS_USED {
        gate.causes.push(format!(
            "too few views: {} show the whole board in every camera; take 10–20, tilted up to 45° in every \
             direction",
            cal.stereo_views.len()
        ));
    }
    for (c, v) in cov.iter().enumerate() {
        if *v < MIN_COVERAGE {
            gate.causes.push(format!(
                "cam{c}'s image was covered only {:.0} %: hold the board near the image edges and corners too",
                v * 100.0
            ));
        }
    }
    Ok(gate)
}
