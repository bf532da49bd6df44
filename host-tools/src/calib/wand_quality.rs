//! Quality gate of a wand calibration and its likely causes (docs/calibration.md, "Quality
//! gates"). The causes are computed: the LED spacing the data fit (the middle LEDs triangulated
//! freely with the calibrated rig, checked by solving again with that spacing), which camera's
//! intrinsics disagree with its images (how straight the straight wand's spots lie after undistortion with
//! its own intrinsics and with every other camera's), and the wave's length, tilt and image coverage.

use irtrack_core::camera::CameraModel;
use nalgebra::{Matrix3, SymmetricEigen, Vector3};

use super::quality::{Check, Gate, median};
use super::wand::{Wand, WandObservations, identify};
use super::wand_boards::BoardView;
use super::wand_report::Figures;
use super::wand_solve::{self, SolveOptions, WandSolution};

/// Largest reprojection RMS of any camera (px). Protects the tracked positions: 1 px at 1.2 m
/// with f = 700 px is about 1.7 mm sideways. Correct simulated waves give 0.01–0.03 px; the
/// asymmetric spacing typo (0/100/300 for a 0/120/300 wand) 3.7–5.4 px.
pub const MAX_RMS_PX: f64 = 1.0;
/// Largest RMS of the freely triangulated wand length against the given one (mm). Protects the
/// scale: the length is the only distance the wand fixes.
pub const MAX_LENGTH_RMS_MM: f64 = 0.5;
/// Fewest frames used (the wand identified in two or more cameras and kept by the adjustment).
pub const MIN_FRAMES_USED: usize = 40;
/// Smallest share of a camera's frames with the wand in view (at least as many spots as LEDs)
/// in which the wand was identified.
pub const MIN_IDENTIFIED: f64 = 0.5;
/// Smallest share of the coverage grid's cells (8×6) holding a used LED, per camera. Protects
/// the distortion and principal points where the image was never seen.
pub const MIN_COVERAGE: f64 = 0.25;
/// Smallest RMS tilt of the wand out of the plane its directions span most (degrees): a wave
/// kept flat determines the rig poorly across that plane.
pub const MIN_TILT_DEG: f64 = 10.0;
/// A spacing that differs from the given one by more than this (mm, or 0.5 % of the length if
/// larger) is reported as the likely cause, once a solve with it fits.
const SPACING_TOL_MM: f64 = 1.0;

/// Distances along the wand (mm from end 0) at which the data put the LEDs: every LED
/// triangulated freely with the calibrated rig, its position projected onto the line through
/// the ends as a fraction of the end-to-end distance (median over frames), times the given
/// length. `None` with fewer than 5 usable frames.
pub fn fitted_spacing_mm(sol: &WandSolution, wand: &Wand) -> Option<Vec<f64>> {
    let k = wand.len();
    let mut fractions: Vec<Vec<f64>> = vec![Vec::new(); k];
    for row in &sol.views {
        let Some(pts) = wand_solve::free_leds_mm(sol, row, k) else {
            continue;
        };
        let axis = pts[k - 1] - pts[0];
        let l2 = axis.norm_squared();
        if l2 < 1e-6 {
            continue;
        }
        for (i, p) in pts.iter().enumerate() {
            fractions[i].push((p - pts[0]).dot(&axis) / l2);
        }
    }
    if fractions[0].len() < 5 {
        return None;
    }
    let (s0, len) = (wand.leds_mm[0], wand.length_mm());
    Some(fractions.iter_mut().map(|f| s0 + median(f) * len).collect())
}

/// `0/119.8/300` (mm values, one decimal unless integral).
pub fn spacing_text(leds_mm: &[f64]) -> String {
    leds_mm
        .iter()
        .map(|v| {
            if (v - v.round()).abs() < 0.05 {
                format!("{v:.0}")
            } else {
                format!("{v:.1}")
            }
        })
        .collect::<Vec<_>>()
        .join("/")
}

/// A camera's wand spots bending by more than this after undistortion (upper quartile over
/// frames, px) point at its intrinsics, when another camera's leave STRAIGHT_FACTOR times less.
/// Simulated: 0.03 px with the right intrinsics, 0.27 px with a camera's intrinsics swapped for
/// another lens's (f 700 px, k1 −0.30 instead of f 640 px, k1 −0.08).
const STRAIGHT_PX: f64 = 0.15;
const STRAIGHT_FACTOR: f64 = 3.0;

/// How far the spots of camera `c`'s frames showing exactly `k` spots lie from a straight line
/// after undistortion with `model` (px at the model's focal length): per frame the RMS distance
/// of the inner spots from the line through the outermost two, the upper quartile over frames
/// (robust to the odd frame whose spots are not the wand, yet weighted towards the image edges
/// where distortion shows). The wand is straight, so with the right intrinsics this is the
/// centroid noise. `None` with fewer than 5 such frames.
pub fn straightness_px(obs: &WandObservations, c: usize, model: &CameraModel, k: usize) -> Option<f64> {
    let f = model.intrinsics.fx_px;
    let mut per_frame = Vec::new();
    for row in &obs.blobs {
        let blobs = &row[c];
        if blobs.len() != k || k < 3 {
            continue;
        }
        let und: Vec<nalgebra::Vector2<f64>> = blobs
            .iter()
            .map(|p| model.undistort_point(p.x, p.y) * f)
            .collect();
        // The outermost pair: the two spots farthest apart.
        let (mut a, mut b, mut far) = (0, 1, 0.0);
        for i in 0..k {
            for j in i + 1..k {
                let d = (und[i] - und[j]).norm();
                if d > far {
                    (a, b, far) = (i, j, d);
                }
            }
        }
        if far < 1e-6 {
            continue;
        }
        let dir = (und[b] - und[a]) / far;
        let s2: f64 = (0..k)
            .filter(|i| *i != a && *i != b)
            .map(|i| {
                let v = und[i] - und[a];
                (v.x * dir.y - v.y * dir.x).powi(2)
            })
            .sum();
        per_frame.push((s2 / (k - 2) as f64).sqrt());
    }
    if per_frame.len() < 5 {
        return None;
    }
    per_frame.sort_by(f64::total_cmp);
    Some(per_frame[per_frame.len() * 3 / 4])
}

/// Share of camera `c`'s frames with the wand in view (≥ as many spots as LEDs) in which
/// `model` identifies the wand; `None` if the camera never had that many spots.
fn identified_share(obs: &WandObservations, c: usize, model: &CameraModel, wand: &Wand) -> Option<f64> {
    let mut in_view = 0usize;
    let mut ok = 0usize;
    for row in &obs.blobs {
        let blobs = &row[c];
        if blobs.len() < wand.len() {
            continue;
        }
        in_view += 1;
        ok += usize::from(identify(model, wand, blobs).is_ok());
    }
    (in_view > 0).then(|| ok as f64 / in_view as f64)
}

/// RMS tilt (degrees) of the wand's directions out of the plane they span most.
fn tilt_deg(sol: &WandSolution) -> f64 {
    let dirs: Vec<Vector3<f64>> = sol.poses.iter().flatten().map(|p| p.dir).collect();
    if dirs.is_empty() {
        return 0.0;
    }
    let scatter: Matrix3<f64> =
        dirs.iter().map(|d| d * d.transpose()).sum::<Matrix3<f64>>() / dirs.len() as f64;
    let e = SymmetricEigen::new(scatter).eigenvalues;
    let smallest = e.iter().copied().fold(f64::INFINITY, f64::min).clamp(0.0, 1.0);
    smallest.sqrt().asin().to_degrees()
}

/// Everything the wand gate looks at.
pub struct WandRun<'a> {
    /// Input intrinsics per camera (before any refinement).
    pub models: &'a [CameraModel],
    /// The wand's identification in every frame and camera.
    pub obs: &'a WandObservations,
    /// The wand's LED layout.
    pub wand: &'a Wand,
    /// Checkerboard views given alongside the wand (may be empty).
    pub boards: &'a [BoardView],
    /// Options the bundle adjustment ran with.
    pub options: SolveOptions,
    /// The bundle adjustment's result.
    pub sol: &'a WandSolution,
    /// The report's summary figures.
    pub fig: &'a Figures,
}

/// Likely causes in the intrinsics, from the spots alone (no solution needed, so they can be
/// given when the adjustment itself fails): a camera whose spots lie straight with another
/// camera's intrinsics but not with its own. Returns the causes and which cameras they name.
pub fn intrinsics_causes(
    models: &[CameraModel],
    obs: &WandObservations,
    wand: &Wand,
) -> (Vec<String>, Vec<bool>) {
    let n_cam = models.len();
    let mut out = Vec::new();
    // Intrinsics: how straight the wand's spots lie after undistortion with each camera's own
    // intrinsics and with every other camera's (of the same image size).
    let straight: Vec<Vec<Option<f64>>> = (0..n_cam)
        .map(|c| {
            (0..n_cam)
                .map(|m| {
                    (models[m].image_size == models[c].image_size)
                        .then(|| straightness_px(obs, c, &models[m], wand.len()))
                        .flatten()
                })
                .collect()
        })
        .collect();
    let own_s = |c: usize| straight[c][c];
    // A camera's own fit is bad when its spots bend by more than STRAIGHT_PX and by more than
    // STRAIGHT_FACTOR times what another camera's intrinsics leave.
    let better = |c: usize| -> Option<(usize, f64)> {
        let mine = own_s(c)?;
        (0..n_cam)
            .filter(|m| *m != c)
            .filter_map(|m| straight[c][m].map(|s| (m, s)))
            .filter(|(_, s)| mine > STRAIGHT_PX && mine > STRAIGHT_FACTOR * s)
            .min_by(|a, b| a.1.total_cmp(&b.1))
    };
    let mut named = vec![false; n_cam];
    for c in 0..n_cam {
        if named[c] {
            continue;
        }
        let Some((m, s)) = better(c) else { continue };
        let mine = own_s(c).unwrap_or(f64::NAN);
        if better(m).is_some_and(|(back, _)| back == c) {
            let (sm, mm) = (straight[m][c].unwrap_or(f64::NAN), own_s(m).unwrap_or(f64::NAN));
            out.push(format!(
                "swapped camera order: cam{c}'s wand spots lie straight with the intrinsics given for cam{m} \
                 ({s:.2} px off a straight line, {mine:.2} px with its own) and cam{m}'s with cam{c}'s ({sm:.2} px, \
                 {mm:.2} px with its own): --intrinsics lists the cameras in another order than the cam \
                 directories of --frames"
            ));
            named[m] = true;
        } else {
            out.push(format!(
                "cam{c}'s intrinsics do not fit its images: its wand spots lie {mine:.2} px off a straight line \
                 (upper quartile) after undistortion with them, {s:.2} px with cam{m}'s: intrinsics of another camera or lens"
            ));
        }
        named[c] = true;
    }
    for (c, named_c) in named.iter_mut().enumerate() {
        let Some(mine) = own_s(c) else { continue };
        let mut others: Vec<f64> = (0..n_cam).filter(|d| *d != c).filter_map(own_s).collect();
        let typical = median(&mut others);
        if !*named_c && mine > STRAIGHT_PX && mine > STRAIGHT_FACTOR * typical {
            out.push(format!(
                "cam{c}'s intrinsics do not fit its images: the spots of the straight wand lie {mine:.2} px off a \
                 straight line after undistortion (upper quartile over frames; the other cameras: {typical:.2} px): intrinsics \
                 (distortion) of another camera or lens, or for another resolution or binning"
            ));
            *named_c = true;
        }
    }
    (out, named)
}

/// Judges a wand calibration and, when a limit fails, computes the likely causes.
pub fn judge(run: &WandRun) -> Gate {
    let WandRun {
        models,
        obs,
        wand,
        sol,
        fig,
        ..
    } = *run;
    let n_cam = models.len();
    let mut gate = Gate::new(if run.boards.is_empty() {
        "wand"
    } else {
        "wand+checkerboard"
    });
    gate.rms_px = fig.per_camera_rms_px.clone();
    for (c, rms) in fig.per_camera_rms_px.iter().enumerate() {
        gate.checks.push(Check::at_most(
            format!("cam{c} reprojection RMS"),
            *rms,
            MAX_RMS_PX,
            "px",
        ));
    }
    let length_rms = (fig.length_mean_mm.powi(2) + fig.length_std_mm.powi(2)).sqrt();
    gate.checks.push(Check::at_most(
        "wand length error RMS",
        length_rms,
        MAX_LENGTH_RMS_MM,
        "mm",
    ));
    gate.checks.push(Check::at_least(
        "frames used",
        fig.frames_used as f64,
        MIN_FRAMES_USED as f64,
        "",
    ));
    let own: Vec<Option<f64>> = (0..n_cam)
        .map(|c| identified_share(obs, c, &models[c], wand))
        .collect();
    for (c, share) in own.iter().enumerate() {
        gate.checks.push(Check::at_least(
            format!("cam{c} wand identified in frames showing it"),
            share.unwrap_or(0.0) * 100.0,
            MIN_IDENTIFIED * 100.0,
            "%",
        ));
    }
    for (c, cov) in fig.coverage.iter().enumerate() {
        gate.checks.push(Check::at_least(
            format!("cam{c} image coverage"),
            cov * 100.0,
            MIN_COVERAGE * 100.0,
            "%",
        ));
    }
    let tilt = tilt_deg(sol);
    gate.checks.push(Check::at_least(
        "wand tilt out of its main plane",
        tilt,
        MIN_TILT_DEG,
        "°",
    ));
    gate.figure("wand_length_mm", wand.length_mm());
    gate.figure("wand_length_mean_mm", fig.length_mean_mm);
    gate.figure("wand_length_std_mm", fig.length_std_mm);
    gate.figure("wand_length_max_abs_mm", fig.length_max_abs_mm);
    gate.figure("frames_used", fig.frames_used as f64);
    gate.figure(
        "coverage_min_pct",
        fig.coverage.iter().copied().fold(f64::INFINITY, f64::min) * 100.0,
    );
    gate.figure("wand_tilt_deg", tilt);
    let boards: Vec<f64> = sol
        .boards
        .iter()
        .filter(|b| b.rejected.is_none())
        .map(|b| b.rms_px * b.rms_px)
        .collect();
    if !boards.is_empty() {
        gate.figure(
            "board_rms_px",
            (boards.iter().sum::<f64>() / boards.len() as f64).sqrt(),
        );
    }
    if gate.failed().is_empty() {
        return gate;
    }
    gate.causes = causes(run, length_rms, tilt);
    gate
}

fn causes(run: &WandRun, length_rms: f64, tilt: f64) -> Vec<String> {
    let WandRun {
        models,
        obs,
        wand,
        fig,
        ..
    } = *run;
    let n_cam = models.len();
    let (mut out, mut named) = intrinsics_causes(models, obs, wand);
    // One camera's reprojection error far above the others'.
    let rms = &fig.per_camera_rms_px;
    if n_cam >= 3 {
        for c in 0..n_cam {
            let mut others: Vec<f64> = (0..n_cam).filter(|d| *d != c).map(|d| rms[d]).collect();
            let typical = median(&mut others).max(0.05);
            if !named[c] && rms[c] > MAX_RMS_PX && rms[c] > 3.0 * typical {
                out.push(format!(
                    "cam{c} disagrees with the other cameras: reprojection RMS {:.2} px against {typical:.2} px: \
                     its intrinsics are from another camera, or its frames are another camera's",
                    rms[c]
                ));
                named[c] = true;
            }
        }
    }
    // Spacing: where the data put the LEDs, confirmed by solving with that spacing.
    let fit_failed = rms.iter().any(|r| r.is_nan() || *r > MAX_RMS_PX)
        || length_rms.is_nan()
        || length_rms > MAX_LENGTH_RMS_MM;
    if fit_failed
        && !named.iter().any(|n| *n)
        && let Some(found) = spacing_cause(run)
    {
        out.insert(0, found);
    }
    if fig.frames_used < MIN_FRAMES_USED {
        out.push(format!(
            "the wave was too short: {} frames show the identified wand in two or more cameras, {} are needed; \
             wave longer (about 10 s at 30 fps) and keep the wand in view of at least two cameras",
            fig.frames_used, MIN_FRAMES_USED
        ));
    }
    if tilt < MIN_TILT_DEG {
        out.push(format!(
            "the wave was too flat: the wand stayed within {tilt:.1}° RMS of one plane; tilt it up and down \
             (up to about 45°) while turning it"
        ));
    }
    for (c, cov) in fig.coverage.iter().enumerate() {
        if *cov < MIN_COVERAGE {
            out.push(format!(
                "cam{c}'s image was covered only {:.0} %: wave through the whole field of view of every camera, \
                 near the image edges too",
                cov * 100.0
            ));
        }
    }
    out
}

/// When the data fit another LED spacing: solves again with it (intrinsics held, without
/// boards, for speed) until the spacing settles, and reports it if that solve fits.
fn spacing_cause(run: &WandRun) -> Option<String> {
    let wand = run.wand;
    let tol = SPACING_TOL_MM.max(0.005 * wand.length_mm());
    let mut found = fitted_spacing_mm(run.sol, wand)?;
    let off_by = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
    let off = |s: &[f64]| off_by(s, &wand.leds_mm);
    if off(&found) <= tol {
        return None;
    }
    let options = SolveOptions {
        refine_intrinsics: false,
        fix_k3: false,
        ..run.options
    };
    // Ends stay where they were given: the wand's length is what the user measured end to end.
    let ends = |mut s: Vec<f64>| {
        let last = s.len() - 1;
        s[0] = wand.leds_mm[0];
        s[last] = wand.leds_mm[last];
        s
    };
    found = ends(found);
    let mut rms = f64::NAN;
    for _ in 0..3 {
        if found.windows(2).any(|w| w[1] - w[0] < 1.0) {
            return None;
        }
        let trial = Wand {
            leds_mm: found.clone(),
        };
        let sol = wand_solve::solve(run.models, run.obs, &trial, &[], options, |_| {}).ok()?;
        rms = sol.per_camera_rms_px.iter().copied().fold(0.0, f64::max);
        let next = ends(fitted_spacing_mm(&sol, &trial)?);
        let moved = off_by(&next, &found);
        found = next;
        if moved < 0.1 {
            break;
        }
    }
    let given_rms = run.fig.per_camera_rms_px.iter().copied().fold(0.0, f64::max);
    (rms <= MAX_RMS_PX && off(&found) > tol).then(|| {
        format!(
            "the wand's LED spacing: the data fit {} mm, you gave {} mm (--wand-mm); with the spacing the data \
             fit, the reprojection RMS is {rms:.3} px instead of {given_rms:.2} px. Measure the LEDs again \
             (distances from one end, end to end as given)",
            spacing_text(&found),
            spacing_text(&wand.leds_mm)
        )
    })
}
