//! Quality gate of a wand calibration and its likely causes (docs/calibration.md, "Quality
//! gates"). Each cause of a poor fit is a hypothesis tested against the data by solving the wave
//! again with the input it blames changed: the LED spacing the data fit (the inner LEDs
//! triangulated freely with the calibrated rig), another camera's intrinsics or the cameras
//! swapped (suspected from how straight each camera's identified LEDs lie after undistortion),
//! the rig without one camera. Named only when that solve fits; a wand that is not straight is
//! found from the freely triangulated LEDs; otherwise it says it cannot tell. The wave's length,
//! tilt and image coverage are named from their own figures.

use irtrack_core::camera::CameraModel;
use nalgebra::{Matrix3, SymmetricEigen, Vector2, Vector3};

use super::quality::{Check, Gate, median};
use super::wand::{LedPixels, Wand, WandObservations, identify};
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

/// How far the identified LEDs of the given views lie from a straight line after undistortion
/// with `model` (px at the model's focal length): per view the RMS distance of the inner LEDs
/// from the line through the two ends, the upper quartile over views (weighted towards the image
/// edges, where distortion shows). The wand is straight, so with the right intrinsics this is
/// the centroid noise, whatever the LED spacing or the rig. Only identified views count (a stray
/// spot is never taken for an LED), and with timestamps they are the retimed LEDs (a rolling
/// shutter's row delays taken out). `None` with fewer than 5 views.
pub fn bend_px<'a>(views: impl Iterator<Item = &'a LedPixels>, model: &CameraModel) -> Option<f64> {
    let f = model.intrinsics.fx_px;
    let mut per_view = Vec::new();
    for px in views {
        let k = px.len();
        if k < 3 {
            continue;
        }
        let und: Vec<Vector2<f64>> = px.iter().map(|p| model.undistort_point(p.x, p.y) * f).collect();
        let ab = und[k - 1] - und[0];
        let len = ab.norm();
        if len < 1e-6 {
            continue;
        }
        let dir = ab / len;
        let s2: f64 = und[1..k - 1]
            .iter()
            .map(|p| {
                let v = p - und[0];
                (v.x * dir.y - v.y * dir.x).powi(2)
            })
            .sum();
        per_view.push((s2 / (k - 2) as f64).sqrt());
    }
    if per_view.len() < 5 {
        return None;
    }
    per_view.sort_by(f64::total_cmp);
    Some(per_view[per_view.len() * 3 / 4])
}

/// [`bend_px`] of camera `c`'s identified views, undistorted with `model`.
pub fn straightness_px(obs: &WandObservations, c: usize, model: &CameraModel) -> Option<f64> {
    bend_px(obs.views.iter().filter_map(|row| row[c].as_ref().ok()), model)
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

/// A camera whose wand spots do not lie straight with its own intrinsics.
struct Suspect {
    camera: usize,
    /// [`straightness_px`] with its own intrinsics.
    own_px: f64,
    /// The median of the other cameras' own figures.
    others_px: f64,
    /// Other cameras whose intrinsics straighten its spots (camera, px), best first.
    better: Vec<(usize, f64)>,
}

/// The cameras the spots point at: own figure above STRAIGHT_PX and STRAIGHT_FACTOR times what
/// another camera's intrinsics (of the same image size) leave, or what the other cameras show
/// with their own. A wand that is not straight bends every camera's spots alike and names none.
fn suspects(models: &[CameraModel], obs: &WandObservations) -> Vec<Suspect> {
    let n_cam = models.len();
    let straight: Vec<Vec<Option<f64>>> = (0..n_cam)
        .map(|c| {
            (0..n_cam)
                .map(|m| {
                    (models[m].image_size == models[c].image_size)
                        .then(|| straightness_px(obs, c, &models[m]))
                        .flatten()
                })
                .collect()
        })
        .collect();
    let mut out = Vec::new();
    for c in 0..n_cam {
        let Some(own_px) = straight[c][c] else { continue };
        let mut others: Vec<f64> = (0..n_cam)
            .filter(|d| *d != c)
            .filter_map(|d| straight[d][d])
            .collect();
        let others_px = median(&mut others);
        let mut better: Vec<(usize, f64)> = (0..n_cam)
            .filter(|m| *m != c && models[*m] != models[c])
            .filter_map(|m| straight[c][m].map(|s| (m, s)))
            .filter(|(_, s)| own_px > STRAIGHT_FACTOR * s)
            .collect();
        better.sort_by(|a, b| a.1.total_cmp(&b.1));
        if own_px > STRAIGHT_PX && (!better.is_empty() || own_px > STRAIGHT_FACTOR * others_px) {
            out.push(Suspect {
                camera: c,
                own_px,
                others_px,
                better,
            });
        }
    }
    out
}

/// Whether suspect `s`'s best substitute is itself a suspect straightened by `s`'s intrinsics.
fn swapped_with(s: &Suspect, all: &[Suspect]) -> Option<usize> {
    let &(m, _) = s.better.first()?;
    all.iter()
        .find(|t| t.camera == m && t.better.first().is_some_and(|(b, _)| *b == s.camera))
        .map(|t| t.camera)
}

fn swap_text(s: &Suspect, all: &[Suspect]) -> Option<String> {
    let m = swapped_with(s, all)?;
    let t = all.iter().find(|t| t.camera == m)?;
    let (c, sc) = (s.camera, s.better[0].1);
    Some(format!(
        "swapped camera order: cam{c}'s wand spots lie straight with the intrinsics given for cam{m} \
         ({sc:.2} px off a straight line, {:.2} px with its own) and cam{m}'s with cam{c}'s ({:.2} px, \
         {:.2} px with its own): --intrinsics lists the cameras in another order than the cam \
         directories of --frames",
        s.own_px, t.better[0].1, t.own_px
    ))
}

fn suspect_text(s: &Suspect) -> String {
    let c = s.camera;
    match s.better.first() {
        Some((m, sm)) => format!(
            "cam{c}'s intrinsics do not fit its images: its wand spots lie {:.2} px off a straight line \
             (upper quartile) after undistortion with them, {sm:.2} px with cam{m}'s: intrinsics of another \
             camera or lens, or a rolling shutter not given with --timing",
            s.own_px
        ),
        None => format!(
            "cam{c}'s intrinsics do not fit its images: the spots of the straight wand lie {:.2} px off a \
             straight line after undistortion (upper quartile over frames; the other cameras: {:.2} px): \
             intrinsics (distortion) of another camera or lens, or a rolling shutter not given with --timing",
            s.own_px, s.others_px
        ),
    }
}

/// Likely causes in the intrinsics, from the spots alone (no solution needed, so they can be
/// given when the adjustment itself fails): a camera whose identified spots lie straight with
/// another camera's intrinsics but not with its own, or far less straight than the others'.
pub fn intrinsics_causes(models: &[CameraModel], obs: &WandObservations) -> Vec<String> {
    let all = suspects(models, obs);
    let mut named = vec![false; models.len()];
    let mut out = Vec::new();
    for s in &all {
        if named[s.camera] {
            continue;
        }
        named[s.camera] = true;
        match (swapped_with(s, &all), swap_text(s, &all)) {
            (Some(m), Some(t)) => {
                named[m] = true;
                out.push(t);
            }
            _ => out.push(suspect_text(s)),
        }
    }
    out
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
    let fig = run.fig;
    let rms = &fig.per_camera_rms_px;
    let fit_failed = rms.iter().any(|r| r.is_nan() || *r > MAX_RMS_PX)
        || length_rms.is_nan()
        || length_rms > MAX_LENGTH_RMS_MM;
    let identified = |c: usize| identified_share(run.obs, c, &run.models[c], run.wand).unwrap_or(1.0);
    let poorly_identified: Vec<usize> = (0..run.models.len())
        .filter(|c| identified(*c) < MIN_IDENTIFIED)
        .collect();
    let mut out = if fit_failed {
        fit_causes(run)
    } else if !poorly_identified.is_empty() {
        identification_causes(run, &poorly_identified)
    } else {
        Vec::new()
    };
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

/// How well the wave fits once one input is changed: solved again (intrinsics held, without
/// boards) and judged by the gate's two fit limits.
#[derive(Debug, Clone, Copy)]
struct Trial {
    /// Largest per-camera reprojection RMS (px; infinite when a camera kept no view).
    worst_rms_px: f64,
    /// RMS of the freely triangulated wand length against the given one (mm).
    length_rms_mm: f64,
}

impl Trial {
    fn fits(&self) -> bool {
        self.worst_rms_px <= MAX_RMS_PX && self.length_rms_mm <= MAX_LENGTH_RMS_MM
    }
}

fn trial(
    models: &[CameraModel],
    obs: &WandObservations,
    wand: &Wand,
    options: SolveOptions,
) -> Option<(Trial, WandSolution)> {
    let sol = wand_solve::solve(models, obs, wand, &[], options, |_| {}).ok()?;
    let worst_rms_px = sol
        .per_camera_rms_px
        .iter()
        .map(|r| if r.is_nan() { f64::INFINITY } else { *r })
        .fold(0.0, f64::max);
    let e = wand_solve::length_errors_mm(&sol, wand);
    let length_rms_mm = if e.is_empty() {
        f64::INFINITY
    } else {
        (e.iter().map(|v| v * v).sum::<f64>() / e.len() as f64).sqrt()
    };
    Some((
        Trial {
            worst_rms_px,
            length_rms_mm,
        },
        sol,
    ))
}

/// The observations of the cameras in `keep` only (in that order).
fn cameras_only(obs: &WandObservations, keep: &[usize]) -> WandObservations {
    WandObservations {
        frames: obs.frames.clone(),
        views: obs
            .views
            .iter()
            .map(|row| keep.iter().map(|c| row[*c].clone()).collect())
            .collect(),
        blobs: obs
            .blobs
            .iter()
            .map(|row| keep.iter().map(|c| row[*c].clone()).collect())
            .collect(),
    }
}

/// A hypothesis the data confirmed: its text and the fit with it.
struct Confirmed {
    text: String,
    trial: Trial,
}

/// Causes of a wave that does not fit (reprojection or length over the limit). Each hypothesis
/// is tested against the data by solving again with the input it blames changed; only those
/// whose solve fits are named, the best if one fits clearly better (half the RMS), else all of
/// them as undecided. When none does, what the spots and the freely triangulated wand show is
/// named (a camera whose spots alone do not lie straight, a wand that is not straight), and
/// otherwise it says it cannot tell.
fn fit_causes(run: &WandRun) -> Vec<String> {
    let WandRun {
        models, obs, wand, ..
    } = *run;
    let n_cam = models.len();
    let held = SolveOptions {
        refine_intrinsics: false,
        fix_k3: false,
        ..run.options
    };
    // A wand that is not straight bends every camera's spots alike; nothing else does, and no
    // change of spacing or intrinsics can make it fit.
    if let Some(bent) = bent_wand(run) {
        return vec![bent];
    }
    let given_rms = run.fig.per_camera_rms_px.iter().copied().fold(0.0, f64::max);
    let mut confirmed: Vec<Confirmed> = Vec::new();
    let mut partial: Vec<String> = Vec::new();
    let mut tried: Vec<String> = Vec::new();
    // The spacing the data fit.
    if let Some((found, t)) = spacing_hypothesis(run, held) {
        let mirrored = mirror(&found);
        let text = format!(
            "the wand's LED spacing: the data fit {} mm (read from the other end: {} mm), you gave {} mm \
             (--wand-mm); with the spacing the data fit, the reprojection RMS is {:.3} px instead of \
             {given_rms:.2} px. Measure the LEDs again (distances from one end, end to end as given)",
            spacing_text(&found),
            spacing_text(&mirrored),
            spacing_text(&wand.leds_mm),
            t.worst_rms_px
        );
        if t.fits() {
            confirmed.push(Confirmed { text, trial: t });
        } else if t.worst_rms_px <= MAX_RMS_PX {
            // The spacing explains the reprojection; something else (named after it) the length.
            partial.push(format!(
                "{text}; the wand length error stays {:.2} mm with it",
                t.length_rms_mm
            ));
        } else {
            tried.push(format!(
                "the LED spacing the data fit, {} mm (RMS {:.2} px, length error {:.2} mm)",
                spacing_text(&found),
                t.worst_rms_px,
                t.length_rms_mm
            ));
        }
    }
    // The intrinsics the spots point at, each change solved.
    let all = suspects(models, obs);
    let mut done = vec![false; n_cam];
    let mut spots_only: Vec<String> = Vec::new();
    for s in &all {
        let c = s.camera;
        if done[c] {
            continue;
        }
        done[c] = true;
        let (text, t) = if let (Some(m), Some(text)) = (swapped_with(s, &all), swap_text(s, &all)) {
            done[m] = true;
            let mut swapped = models.to_vec();
            swapped.swap(c, m);
            (text, trial(&swapped, obs, wand, held))
        } else if let Some(&(m, _)) = s.better.first() {
            let mut given = models.to_vec();
            given[c] = models[m];
            (suspect_text(s), trial(&given, obs, wand, held))
        } else if n_cam >= 3 {
            let keep: Vec<usize> = (0..n_cam).filter(|d| *d != c).collect();
            let sub: Vec<CameraModel> = keep.iter().map(|d| models[*d]).collect();
            (
                format!("{}; without cam{c} the other cameras fit", suspect_text(s)),
                trial(&sub, &cameras_only(obs, &keep), wand, held),
            )
        } else {
            // Two cameras: let the adjustment refine the intrinsics; right ones need no change.
            let refine = SolveOptions {
                refine_intrinsics: true,
                fix_k3: true,
                ..held
            };
            (
                format!(
                    "{}; with the intrinsics refined from the wave the rig fits",
                    suspect_text(s)
                ),
                trial(models, obs, wand, refine),
            )
        };
        match t {
            Some((t, _)) if t.fits() => confirmed.push(Confirmed {
                text: format!("{text} (reprojection RMS {:.3} px)", t.worst_rms_px),
                trial: t,
            }),
            _ => spots_only.push(suspect_text(s)),
        }
    }
    // With three or more cameras and nothing else explaining the wave: one camera that
    // disagrees with the rest (it moved, or its frames or intrinsics are another camera's),
    // found by solving without each camera in turn.
    let rms = &run.fig.per_camera_rms_px;
    if confirmed.is_empty() && spots_only.is_empty() && n_cam >= 3 {
        for c in (0..n_cam).filter(|c| !done[*c]) {
            let keep: Vec<usize> = (0..n_cam).filter(|d| *d != c).collect();
            let sub: Vec<CameraModel> = keep.iter().map(|d| models[*d]).collect();
            if let Some((t, _)) = trial(&sub, &cameras_only(obs, &keep), wand, held)
                && t.fits()
            {
                confirmed.push(Confirmed {
                    text: format!(
                        "cam{c} disagrees with the other cameras: without it they fit (reprojection RMS {:.3} px, \
                         length error {:.2} mm; with it {:.2} px and {:.2} mm): it moved during the wave, or its \
                         frames or intrinsics are another camera's",
                        t.worst_rms_px, t.length_rms_mm, rms[c], run.fig.length_mean_mm.hypot(run.fig.length_std_mm)
                    ),
                    trial: t,
                });
            }
        }
    }
    confirmed.sort_by(|a, b| a.trial.worst_rms_px.total_cmp(&b.trial.worst_rms_px));
    match confirmed.as_slice() {
        [one] => return vec![one.text.clone()],
        [best, next, ..] if 2.0 * best.trial.worst_rms_px < next.trial.worst_rms_px => {
            return vec![best.text.clone()];
        }
        [_, _, ..] => {
            let each: Vec<String> = confirmed.iter().map(|c| c.text.clone()).collect();
            return vec![format!(
                "cannot tell which of these it is, each alone makes the wave fit: {}",
                each.join("; or ")
            )];
        }
        [] => {}
    }
    if !partial.is_empty() {
        partial.extend(spots_only);
        return partial;
    }
    if !spots_only.is_empty() {
        return spots_only;
    }
    let mut own: Vec<f64> = (0..n_cam)
        .filter_map(|c| straightness_px(obs, c, &models[c]))
        .collect();
    own.sort_by(f64::total_cmp);
    let spots = match (own.first(), own.last()) {
        (Some(lo), Some(hi)) => format!(
            "no camera's intrinsics stand out (the wand's spots lie {lo:.2}–{hi:.2} px off a straight line)"
        ),
        _ => "too few identified views to judge the intrinsics".to_string(),
    };
    tried.push(spots);
    vec![format!(
        "cannot tell from the data: {}; check the LED spacing (--wand-mm), each camera's intrinsics, and that \
         no camera moved during the wave",
        tried.join("; ")
    )]
}

/// Causes of a camera identifying the wand in too few of the frames that show it (the fit
/// itself within its limits): a wand that is not straight, intrinsics the spots do not lie
/// straight with, or undetermined.
fn identification_causes(run: &WandRun, cameras: &[usize]) -> Vec<String> {
    if let Some(bent) = bent_wand(run) {
        return vec![bent];
    }
    let intrinsics = intrinsics_causes(run.models, run.obs);
    if !intrinsics.is_empty() {
        return intrinsics;
    }
    let names: Vec<String> = cameras.iter().map(|c| format!("cam{c}")).collect();
    vec![format!(
        "cannot tell from the data why {} identifies the wand in so few frames: its identified spots lie \
         straight and the wand does too; look at its frames for reflections or stray lights on the wand's \
         line and LEDs that merge",
        names.join(", ")
    )]
}

/// The spacing read from the other end.
fn mirror(leds_mm: &[f64]) -> Vec<f64> {
    let (first, last) = (leds_mm[0], leds_mm[leds_mm.len() - 1]);
    leds_mm.iter().rev().map(|s| first + last - s).collect()
}

/// Inner LEDs lying further than this off the line through the end LEDs (median over frames,
/// freely triangulated) name a wand that is not straight, when every camera's spots bend too.
const BENT_MM: f64 = 1.0;

/// A wand that is not straight: its inner LEDs, triangulated freely with the calibrated rig, lie
/// off the line through its end LEDs by about the same distance in every frame, and every
/// camera's spots bend (a wrong lens bends one camera's, not all).
fn bent_wand(run: &WandRun) -> Option<String> {
    let WandRun {
        models,
        obs,
        wand,
        sol,
        ..
    } = *run;
    let k = wand.len();
    let mut off: Vec<f64> = sol
        .views
        .iter()
        .filter_map(|row| wand_solve::free_leds_mm(sol, row, k))
        .filter_map(|pts| {
            let axis = pts[k - 1] - pts[0];
            let len = axis.norm();
            (len > 1e-6).then(|| {
                let d = axis / len;
                let s2: f64 = pts[1..k - 1]
                    .iter()
                    .map(|p| {
                        let v = p - pts[0];
                        (v - d * v.dot(&d)).norm_squared()
                    })
                    .sum();
                (s2 / (k - 2) as f64).sqrt()
            })
        })
        .collect();
    if off.len() < 5 {
        return None;
    }
    off.sort_by(f64::total_cmp);
    let n = off.len();
    let (q1, med, q3) = (off[n / 4], off[n / 2], off[n * 3 / 4]);
    let bends: Vec<f64> = (0..models.len())
        .map(|c| straightness_px(obs, c, &models[c]).unwrap_or(0.0))
        .collect();
    let lo = bends.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = bends.iter().copied().fold(0.0, f64::max);
    (med >= BENT_MM && q1 >= 0.5 * med && lo > STRAIGHT_PX).then(|| {
        format!(
            "the wand is not straight: its inner LEDs lie {med:.1} mm off the line through its end LEDs \
             (median over {n} frames, quartiles {q1:.1}–{q3:.1} mm), and every camera sees its spots bent \
             ({lo:.2}–{hi:.2} px off a straight line; a straight wand leaves about 0.03 px): straighten or \
             replace the wand, the calibration takes its LEDs to lie on one line"
        )
    })
}

/// When the data fit another LED spacing: solves again with it (intrinsics held, without
/// boards, for speed) until the spacing settles. Returns that spacing and its fit; `None` when
/// the data fit the given spacing (within 1 mm or 0.5 % of the length) or no solve succeeds.
fn spacing_hypothesis(run: &WandRun, options: SolveOptions) -> Option<(Vec<f64>, Trial)> {
    let wand = run.wand;
    let tol = SPACING_TOL_MM.max(0.005 * wand.length_mm());
    let mut found = fitted_spacing_mm(run.sol, wand)?;
    let off_by = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
    let off = |s: &[f64]| off_by(s, &wand.leds_mm);
    if off(&found) <= tol {
        return None;
    }
    // Ends stay where they were given: the wand's length is what the user measured end to end.
    let ends = |mut s: Vec<f64>| {
        let last = s.len() - 1;
        s[0] = wand.leds_mm[0];
        s[last] = wand.leds_mm[last];
        s
    };
    found = ends(found);
    let mut last = None;
    for _ in 0..3 {
        if found.windows(2).any(|w| w[1] - w[0] < 1.0) {
            return None;
        }
        let trial_wand = Wand {
            leds_mm: found.clone(),
        };
        let (t, sol) = trial(run.models, run.obs, &trial_wand, options)?;
        last = Some(t);
        let next = ends(fitted_spacing_mm(&sol, &trial_wand)?);
        let moved = off_by(&next, &found);
        found = next;
        if moved < 0.1 {
            break;
        }
    }
    let t = last?;
    (off(&found) > tol).then_some((found, t))
}
