//! Camera time offsets from the wand wave (issue 39 item 5; docs/calibration.md, "Time offsets").
//!
//! Free-running cameras expose at their own instants, and a camera's timestamp is its exposure
//! instant only up to a constant offset (`CameraTiming::offset_ns`). The wand wave tells the
//! offsets: with the right offset of camera c against camera 0, camera c's LED tracks, moved
//! to the instants camera 0 saw each LED, meet camera 0's rays; with a wrong one they miss by
//! the wand's image speed × the error. For each camera c ≠ 0 the offset δ_c is the minimum of
//! that two-view reprojection cost (robust, Huber) over δ_c ∈ [−period, +period]: a coarse grid,
//! then a golden-section refinement. Its uncertainty comes from the cost's curvature and the
//! residual variance, checked against the spread between the wave's two halves. A wave too slow
//! for the cost to bend is reported as not observable, never as a number.
//!
//! Timestamps are first smoothed per camera by a straight line through them (frame period and
//! phase), as irtrackd's clock model does live, so that timestamp jitter averages out.
//!
//! [`retime_observations`] moves every identified LED along its own 2-D track to camera 0's
//! frame instant, so that the bundle adjustment sees each frame's wand at one instant.

use std::collections::BTreeMap;

use anyhow::{Result, anyhow};
use irtrack_core::camera::CameraModel;
use irtrack_core::params::CameraParams;
use irtrack_core::timing::{CameraTiming, Shutter};
use nalgebra::{Vector2, Vector3};

use super::wand::{LedPixels, Rejection, WandObservations};

/// An offset whose standard uncertainty exceeds this (ns) is reported as not observable.
pub const MAX_OBSERVABLE_SIGMA_NS: f64 = 100_000.0;
/// Frames farther apart than this (ns; 14 fps) are too far apart to follow a wand between them.
pub const MAX_FRAME_STEP_NS: f64 = 70_000_000.0;
/// Frames both cameras identified the wand in, at least, to estimate an offset.
pub const MIN_SHARED_FRAMES: usize = 30;
/// A sample this close (ns) to the wanted instant is used as seen.
const AS_SEEN_NS: f64 = 5_000.0;
/// Coarse grid steps per frame period.
const GRID_STEPS_PER_PERIOD: usize = 32;
/// Golden-section refinement stops at this bracket (ns).
const REFINE_TOL_NS: f64 = 1_000.0;
/// Half-width (ns) of the three-point curvature estimate at the minimum.
const CURVATURE_STEP_NS: f64 = 40_000.0;
/// Half-width (ns) of the curvature estimate in the line time.
const LINE_CURVATURE_STEP_NS: f64 = 200.0;

/// Each camera's frame instants from its timestamps, smoothed by a straight line.
#[derive(Debug, Clone)]
pub struct FrameClock {
    /// `instants_ns[camera][frame position]`: the line's value at the frame (ns, the recording's
    /// clock, before any offset); `None` for a frame without a timestamp or marked dropped.
    pub instants_ns: Vec<Vec<Option<f64>>>,
    /// Each camera's measured frame period (ns).
    pub period_ns: Vec<f64>,
    /// RMS distance (ns) of each camera's timestamps from its line.
    pub jitter_rms_ns: Vec<f64>,
    /// Why the frames are not a continuous stream a wand can be followed through (sets saved
    /// far apart, or irregularly, e.g. `capture` taking a set now and then); `None` when they are.
    pub not_continuous: Option<String>,
}

/// The frame number in a frame file's name (`000123.pgm` → 123).
fn frame_number(name: &str) -> Result<u64> {
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    stem.parse().map_err(|_| {
        anyhow!(
            "frame file {name:?} has no frame number to look up in timestamps.csv (expected e.g. 000123.pgm)"
        )
    })
}

/// Least-squares line `t = a + b·i`; `None` when the indices do not spread.
fn fit_line(pts: &[(f64, f64)]) -> Option<(f64, f64)> {
    let n = pts.len() as f64;
    let mi = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let mt = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sii: f64 = pts.iter().map(|p| (p.0 - mi) * (p.0 - mi)).sum();
    let sit: f64 = pts.iter().map(|p| (p.0 - mi) * (p.1 - mt)).sum();
    (sii > 0.0).then(|| {
        let b = sit / sii;
        (mt - b * mi, b)
    })
}

impl FrameClock {
    /// From `timestamps.csv` (per camera, frame number → (timestamp_ns, dropped)) for the
    /// recording's frames.
    pub fn new(stamps: &[BTreeMap<u64, (u64, bool)>], frames: &[String]) -> Result<FrameClock> {
        let numbers: Vec<u64> = match frames.iter().map(|n| frame_number(n)).collect::<Result<_>>() {
            Ok(n) => n,
            Err(e) => {
                return Ok(FrameClock {
                    instants_ns: vec![vec![None; frames.len()]; stamps.len()],
                    period_ns: vec![f64::NAN; stamps.len()],
                    jitter_rms_ns: vec![f64::NAN; stamps.len()],
                    not_continuous: Some(e.to_string()),
                });
            }
        };
        let mut instants_ns = Vec::with_capacity(stamps.len());
        let mut period_ns = Vec::with_capacity(stamps.len());
        let mut jitter_rms_ns = Vec::with_capacity(stamps.len());
        let mut not_continuous = None;
        for (c, m) in stamps.iter().enumerate() {
            let raw: Vec<Option<f64>> = numbers
                .iter()
                .map(|n| match m.get(n) {
                    Some((ts, false)) => Some(*ts as f64),
                    _ => None,
                })
                .collect();
            let mut ts: Vec<f64> = raw.iter().flatten().copied().collect();
            ts.sort_by(f64::total_cmp);
            let mut steps: Vec<f64> = ts.windows(2).map(|w| w[1] - w[0]).filter(|d| *d > 0.0).collect();
            if steps.len() < 8 {
                not_continuous.get_or_insert(format!(
                    "camera {c} has {} timestamped frames of this recording, at least 9 are needed",
                    ts.len()
                ));
                instants_ns.push(raw);
                period_ns.push(f64::NAN);
                jitter_rms_ns.push(f64::NAN);
                continue;
            }
            steps.sort_by(f64::total_cmp);
            // The median step is the period even with dropped frames among them.
            let rough = steps[steps.len() / 2];
            // Frame index by whole periods between consecutive stamps (a dropped frame's slot
            // counted): robust to jitter in the rough period, unlike rounding from the start.
            let mut index_of: Vec<(f64, f64)> = Vec::with_capacity(ts.len());
            for (k, t) in ts.iter().enumerate() {
                let i = match k {
                    0 => 0.0,
                    _ => index_of[k - 1].1 + ((t - ts[k - 1]) / rough).round(),
                };
                index_of.push((*t, i));
            }
            let idx = |t: f64| {
                let k = index_of.partition_point(|(u, _)| *u < t);
                index_of.get(k).map_or(0.0, |e| e.1)
            };
            let mut pts: Vec<(f64, f64)> = raw.iter().flatten().map(|t| (idx(*t), *t)).collect();
            let Some(mut line) = fit_line(&pts) else {
                not_continuous.get_or_insert(format!("camera {c}'s timestamps do not advance"));
                instants_ns.push(raw);
                period_ns.push(f64::NAN);
                jitter_rms_ns.push(f64::NAN);
                continue;
            };
            // One pass without the outliers (a USB transfer held back).
            let rms = |pts: &[(f64, f64)], (a, b): (f64, f64)| {
                (pts.iter().map(|(i, t)| (t - a - b * i).powi(2)).sum::<f64>() / pts.len() as f64).sqrt()
            };
            let limit = (4.0 * rms(&pts, line)).max(100_000.0);
            pts.retain(|(i, t)| (t - line.0 - line.1 * i).abs() <= limit);
            if let Some(l) = fit_line(&pts) {
                line = l;
            }
            let jitter = rms(&pts, line);
            if not_continuous.is_none() && (rough > MAX_FRAME_STEP_NS || jitter > rough / 8.0) {
                not_continuous = Some(format!(
                    "camera {c}'s frames are {:.1} ms apart (median), {:.1} ms RMS off a steady rate: \
                     not a continuous stream to follow the wand through (need ≤ {:.0} ms apart, steady)",
                    rough * 1e-6,
                    jitter * 1e-6,
                    MAX_FRAME_STEP_NS * 1e-6
                ));
            }
            jitter_rms_ns.push(jitter);
            period_ns.push(line.1);
            instants_ns.push(raw.iter().map(|t| t.map(|t| line.0 + line.1 * idx(t))).collect());
        }
        Ok(FrameClock {
            instants_ns,
            period_ns,
            jitter_rms_ns,
            not_continuous,
        })
    }
}

/// One camera's identified LEDs with their frame instants, and how to time a row.
struct Track<'a> {
    samples: Vec<Option<(f64, &'a LedPixels)>>,
    timing: CameraTiming,
    period_ns: f64,
    /// A sample this close (ns) to the wanted instant is used as seen.
    as_seen_ns: f64,
}

impl<'a> Track<'a> {
    fn new(obs: &'a WandObservations, clock: &FrameClock, camera: usize, timing: CameraTiming) -> Self {
        let samples = obs
            .views
            .iter()
            .zip(&clock.instants_ns[camera])
            .map(|(row, t)| match (&row[camera], t) {
                (Ok(px), Some(t)) => Some((*t, px)),
                _ => None,
            })
            .collect();
        Track {
            samples,
            timing,
            period_ns: clock.period_ns[camera],
            as_seen_ns: AS_SEEN_NS,
        }
    }

    /// Exposure instant of LED `k` in the sample at position `p`.
    fn instant(&self, p: usize, k: usize) -> Option<(f64, Vector2<f64>)> {
        let (t, px) = self.samples.get(p).copied().flatten()?;
        let led = *px.get(k)?;
        Some((
            self.timing.offset_ns as f64 + t + self.timing.row_delay_ns(led.y),
            led,
        ))
    }

    /// LED `k`'s pixel at instant `t_ns`, moved along its track (quadratic through the nearest
    /// sample and its neighbours, linear through two), searching near position `hint`.
    fn at(&self, k: usize, hint: usize, t_ns: f64) -> Option<Vector2<f64>> {
        let lo = hint.saturating_sub(3);
        let hi = (hint + 3).min(self.samples.len().saturating_sub(1));
        let (q, (tq, pq)) = (lo..=hi)
            .filter_map(|p| self.instant(p, k).map(|s| (p, s)))
            .min_by(|a, b| (a.1.0 - t_ns).abs().total_cmp(&(b.1.0 - t_ns).abs()))?;
        let dt = t_ns - tq;
        if dt.abs() <= self.as_seen_ns {
            return Some(pq);
        }
        if dt.abs() > 0.75 * self.period_ns {
            return None;
        }
        // Neighbours only across one frame period (not across a dropped frame).
        let near = |p: Option<usize>| {
            p.and_then(|p| self.instant(p, k))
                .filter(|(t, _)| (t - tq).abs() <= 1.5 * self.period_ns && (t - tq).abs() > 1.0)
        };
        let pts: Vec<(f64, Vector2<f64>)> = [near(q.checked_sub(1)), Some((tq, pq)), near(Some(q + 1))]
            .into_iter()
            .flatten()
            .collect();
        if pts.len() < 2 {
            return None;
        }
        // Lagrange through the samples (2 or 3), in ms to keep the products well scaled.
        let x = t_ns * 1e-6;
        let mut out = Vector2::zeros();
        for (i, (ti, pi)) in pts.iter().enumerate() {
            let mut w = 1.0;
            for (j, (tj, _)) in pts.iter().enumerate() {
                if i != j {
                    w *= (x - tj * 1e-6) / (ti * 1e-6 - tj * 1e-6);
                }
            }
            out += pi * w;
        }
        Some(out)
    }
}

/// Two-view triangulation reprojection error (px, both cameras' errors in quadrature).
struct Pair<'a> {
    m0: &'a CameraModel,
    mc: &'a CameraModel,
    c: &'a CameraParams,
}

impl Pair<'_> {
    fn error_px(&self, p0: &Vector2<f64>, pc: &Vector2<f64>) -> Option<f64> {
        let x0 = self.m0.undistort_point(p0.x, p0.y);
        let xc = self.mc.undistort_point(pc.x, pc.y);
        let d0 = Vector3::new(x0.x, x0.y, 1.0);
        let r = self.c.cam_from_cam0.rotation();
        let t = self.c.cam_from_cam0.translation_mm();
        let centre = -(r.transpose() * t);
        let dc = r.transpose() * Vector3::new(xc.x, xc.y, 1.0);
        // Midpoint of the shortest segment between the rays.
        let (a, b, cc) = (d0.dot(&d0), d0.dot(&dc), dc.dot(&dc));
        let w = -centre;
        let (d, e) = (d0.dot(&w), dc.dot(&w));
        let den = a * cc - b * b;
        if den.abs() < 1e-12 {
            return None;
        }
        let s = (b * e - cc * d) / den;
        let u = (a * e - b * d) / den;
        let p = (d0 * s + centre + dc * u) * 0.5;
        let e0 = self.m0.project(&p).ok()? - p0;
        let ec = self.mc.project(&self.c.cam_from_cam0.apply(&p)).ok()? - pc;
        Some((e0.norm_squared() + ec.norm_squared()).sqrt())
    }
}

/// One camera's estimated offset against camera 0.
#[derive(Debug, Clone, PartialEq)]
pub struct OffsetEstimate {
    /// The camera.
    pub camera: usize,
    /// Frames both this camera and camera 0 identified the wand in (with timestamps).
    pub shared_frames: usize,
    /// `offset_ns` of this camera minus camera 0's (ns); `None` when not observable.
    pub offset_vs_cam0_ns: Option<f64>,
    /// Standard uncertainty (ns): the larger of the curvature's and the halves' spread.
    pub sigma_ns: f64,
    /// The estimate from each half of the wave (ns), when both could be made.
    pub halves_ns: Option<(f64, f64)>,
    /// Two-view reprojection RMS (px) at the estimate.
    pub rms_px: f64,
    /// Median image speed of the LEDs in this camera (px per ms).
    pub image_speed_px_per_ms: f64,
    /// Why the offset is not observable (plain words), when it is not.
    pub not_observable: Option<String>,
    /// The estimated line time (ns) of a rolling shutter, when asked for and observable.
    pub line_time_ns: Option<f64>,
    /// Its standard uncertainty (ns), when estimated.
    pub line_time_sigma_ns: Option<f64>,
}

/// What the timing estimation found.
#[derive(Debug, Clone, PartialEq)]
pub struct TimingResult {
    /// Camera 1, 2, … (camera 0 is the reference).
    pub offsets: Vec<OffsetEstimate>,
    /// Each camera's measured frame period (ns).
    pub period_ns: Vec<f64>,
    /// Each camera's timestamp jitter against its line (RMS, ns).
    pub jitter_rms_ns: Vec<f64>,
}

/// Robust cost of camera c's track against camera 0 for a trial offset, over `frames`.
fn cost(
    pair: &Pair<'_>,
    t0: &Track<'_>,
    tc: &Track<'_>,
    frames: &[usize],
    leds: usize,
    huber_px: f64,
) -> (f64, usize, f64) {
    let (mut s, mut n, mut sq) = (0.0, 0, 0.0);
    for &p in frames {
        for k in 0..leds {
            let Some((t, p0)) = t0.instant(p, k) else { continue };
            let Some(pc) = tc.at(k, p, t) else { continue };
            let Some(e) = pair.error_px(&p0, &pc) else {
                continue;
            };
            s += if e <= huber_px {
                e * e
            } else {
                2.0 * huber_px * e - huber_px * huber_px
            };
            sq += e * e;
            n += 1;
        }
    }
    (s, n, sq)
}

/// Mean cost per term (comparable across trial offsets that bridge different numbers of LEDs).
fn mean_cost(
    pair: &Pair<'_>,
    t0: &Track<'_>,
    tc: &Track<'_>,
    frames: &[usize],
    leds: usize,
    huber_px: f64,
) -> f64 {
    let (s, n, _) = cost(pair, t0, tc, frames, leds, huber_px);
    if n < leds * frames.len() / 2 {
        f64::INFINITY
    } else {
        s / n as f64
    }
}

/// Minimum of the mean cost over δ ∈ [−period, +period]: (δ, mean cost at δ).
fn minimise(f: &dyn Fn(f64) -> f64, period_ns: f64) -> Option<(f64, f64)> {
    let n = GRID_STEPS_PER_PERIOD as i64;
    minimise_on(f, -period_ns, period_ns, 2 * n as usize, REFINE_TOL_NS)
}

/// Minimum of `f` over [lo, hi]: a grid of `steps` intervals, then golden section to `tol` in
/// the two intervals around the best grid point. `None` when the best is at either end.
fn minimise_on(f: &dyn Fn(f64) -> f64, lo: f64, hi: f64, steps: usize, tol: f64) -> Option<(f64, f64)> {
    let step = (hi - lo) / steps as f64;
    let grid: Vec<(f64, f64)> = (0..=steps)
        .map(|i| {
            let x = lo + i as f64 * step;
            (x, f(x))
        })
        .collect();
    let (best, _) = grid
        .iter()
        .enumerate()
        .filter(|(_, g)| g.1.is_finite())
        .min_by(|a, b| a.1.1.total_cmp(&b.1.1))?;
    if best == 0 || best == grid.len() - 1 {
        return None;
    }
    // Golden section in the two grid steps around the best grid point.
    let (mut a, mut b) = (grid[best - 1].0, grid[best + 1].0);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut x1, mut x2) = (b - g * (b - a), a + g * (b - a));
    let (mut f1, mut f2) = (f(x1), f(x2));
    while b - a > tol {
        if f1 < f2 {
            b = x2;
            x2 = x1;
            f2 = f1;
            x1 = b - g * (b - a);
            f1 = f(x1);
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            x2 = a + g * (b - a);
            f2 = f(x2);
        }
    }
    let x = (a + b) / 2.0;
    Some((x, f(x)))
}

/// Estimates each camera's offset against camera 0 with the solved geometry `cameras`, the raw
/// identified LEDs `obs` and the smoothed frame instants. `timing` gives each camera's shutter
/// and line time (and camera 0's offset, the reference).
pub fn estimate(
    cameras: &[CameraParams],
    obs: &WandObservations,
    clock: &FrameClock,
    timing: &[CameraTiming],
    huber_px: f64,
    estimate_line_time: bool,
) -> TimingResult {
    let leds = obs
        .views
        .iter()
        .flat_map(|r| r.iter())
        .find_map(|v| v.as_ref().ok().map(Vec::len))
        .unwrap_or(0);
    let t0 = Track::new(obs, clock, 0, timing[0]);
    let mut offsets = Vec::new();
    for c in 1..cameras.len() {
        let base = CameraTiming {
            offset_ns: 0,
            ..timing[c]
        };
        let track_lt = |delta_ns: f64, line_ns: f64| {
            let mut t = Track::new(obs, clock, c, base);
            t.timing.offset_ns = (timing[0].offset_ns as f64 + delta_ns).round() as i64;
            t.timing.line_time_ns = line_ns.round().max(0.0) as u32;
            // Always moved: a tolerance would flatten the cost around zero offset.
            t.as_seen_ns = 0.5;
            t
        };
        let mut line_ns = f64::from(timing[c].line_time_ns);
        let pair = Pair {
            m0: &cameras[0].model,
            mc: &cameras[c].model,
            c: &cameras[c],
        };
        let probe = track_lt(0.0, line_ns);
        let shared: Vec<usize> = (0..obs.views.len())
            .filter(|p| t0.samples[*p].is_some() && probe.samples[*p].is_some())
            .collect();
        let speed = image_speed(&probe);
        let period = clock.period_ns[0].max(clock.period_ns[c]);
        let mut est = OffsetEstimate {
            camera: c,
            shared_frames: shared.len(),
            offset_vs_cam0_ns: None,
            sigma_ns: f64::INFINITY,
            halves_ns: None,
            rms_px: f64::NAN,
            image_speed_px_per_ms: speed,
            not_observable: None,
            line_time_ns: None,
            line_time_sigma_ns: None,
        };
        if shared.len() < MIN_SHARED_FRAMES {
            est.not_observable = Some(format!(
                "only {} frames shared with camera 0 (need {MIN_SHARED_FRAMES})",
                shared.len()
            ));
            offsets.push(est);
            continue;
        }
        let solve_on = |frames: &[usize], line_ns: f64| {
            let f = |d: f64| mean_cost(&pair, &t0, &track_lt(d, line_ns), frames, leds, huber_px);
            minimise(&f, period)
        };
        let Some((delta, _)) = solve_on(&shared, line_ns) else {
            est.not_observable = Some(format!(
                "the two-view cost has no minimum within ±{:.1} ms (one frame period): too little motion \
                 (the wand moved {speed:.2} px/ms in camera {c}'s images) or an offset beyond a frame period",
                period * 1e-6
            ));
            offsets.push(est);
            continue;
        };
        let rows = f64::from(cameras[c].model.image_size.height_px);
        let fit_line = estimate_line_time && timing[c].shutter == Shutter::Rolling;
        let mut delta = delta;
        if fit_line {
            // The offset and the line time trade against each other through the LEDs' mean
            // row: for each trial line time the offset is minimised again, starting from the
            // offset that keeps the mean row's instant (a profile of the cost over line time).
            let row_mid = mean_row(&probe);
            let (delta_start, line_start) = (delta, line_ns);
            let best_delta = |l: f64| {
                let d0 = delta_start + (line_start - l) * row_mid;
                let f = |d: f64| mean_cost(&pair, &t0, &track_lt(d, l), &shared, leds, huber_px);
                minimise_on(&f, d0 - 0.15 * period, d0 + 0.15 * period, 6, REFINE_TOL_NS)
            };
            let profile = |l: f64| best_delta(l).map_or(f64::INFINITY, |(_, v)| v);
            let hi = 2.0 * line_ns.max(period / rows / 2.0);
            if let Some((l, _)) = minimise_on(&profile, 0.0, hi, 16, 5.0)
                && let Some((d, _)) = best_delta(l)
            {
                line_ns = l;
                delta = d;
            }
        }
        let track_with = |delta_ns: f64| track_lt(delta_ns, line_ns);
        let (s0, n0, sq0) = cost(&pair, &t0, &track_with(delta), &shared, leds, huber_px);
        let (sp, _, _) = cost(
            &pair,
            &t0,
            &track_with(delta + CURVATURE_STEP_NS),
            &shared,
            leds,
            huber_px,
        );
        let (sm, _, _) = cost(
            &pair,
            &t0,
            &track_with(delta - CURVATURE_STEP_NS),
            &shared,
            leds,
            huber_px,
        );
        let h = CURVATURE_STEP_NS;
        let curvature = (sp + sm - 2.0 * s0) / (h * h);
        est.rms_px = (sq0 / n0.max(1) as f64).sqrt();
        // var = 2 s² H⁻¹ with s² the residual variance per term (an LED seen by both cameras).
        let s2 = s0 / (n0.max(2) - 1) as f64;
        let mut sigma_curv = if curvature > 0.0 {
            (2.0 * s2 / curvature).sqrt()
        } else {
            f64::INFINITY
        };
        if fit_line {
            // The 2×2 Hessian in (offset, line time), by central differences.
            let hl = LINE_CURVATURE_STEP_NS;
            let at = |d: f64, l: f64| cost(&pair, &t0, &track_lt(d, l), &shared, leds, huber_px).0;
            let hll = (at(delta, line_ns + hl) + at(delta, line_ns - hl) - 2.0 * s0) / (hl * hl);
            let hdl =
                (at(delta + h, line_ns + hl) - at(delta + h, line_ns - hl) - at(delta - h, line_ns + hl)
                    + at(delta - h, line_ns - hl))
                    / (4.0 * h * hl);
            let det = curvature * hll - hdl * hdl;
            let (var_d, var_l) = if det > 0.0 && curvature > 0.0 {
                (2.0 * s2 * hll / det, 2.0 * s2 * curvature / det)
            } else {
                (f64::INFINITY, f64::INFINITY)
            };
            sigma_curv = var_d.sqrt();
            let sigma_l = var_l.sqrt();
            est.line_time_sigma_ns = Some(sigma_l);
            // Observable when the timing of the bottom row is known to the offset's limit.
            if sigma_l * rows <= MAX_OBSERVABLE_SIGMA_NS {
                est.line_time_ns = Some(line_ns);
            }
        }
        let mid = shared.len() / 2;
        let halves = solve_on(&shared[..mid], line_ns).zip(solve_on(&shared[mid..], line_ns));
        est.halves_ns = halves.map(|(a, b)| (a.0, b.0));
        // Two independent halves differ by 2σ of the whole on average.
        let sigma_halves = halves.map_or(f64::INFINITY, |(a, b)| (a.0 - b.0).abs() / 2.0);
        est.sigma_ns = sigma_curv.max(sigma_halves);
        if est.sigma_ns > MAX_OBSERVABLE_SIGMA_NS {
            est.not_observable = Some(format!(
                "the wand moved {speed:.2} px/ms in camera {c}'s images: too little motion to tell its \
                 time offset (uncertainty {} > {:.0} µs)",
                if est.sigma_ns.is_finite() {
                    format!("{:.0} µs", est.sigma_ns * 1e-3)
                } else {
                    "unbounded".to_string()
                },
                MAX_OBSERVABLE_SIGMA_NS * 1e-3
            ));
        } else {
            est.offset_vs_cam0_ns = Some(delta);
        }
        offsets.push(est);
    }
    TimingResult {
        offsets,
        period_ns: clock.period_ns.clone(),
        jitter_rms_ns: clock.jitter_rms_ns.clone(),
    }
}

/// Mean row (px) of a track's LEDs.
fn mean_row(t: &Track<'_>) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for (_, px) in t.samples.iter().flatten() {
        for p in px.iter() {
            sum += p.y;
            n += 1;
        }
    }
    if n == 0 { 0.0 } else { sum / n as f64 }
}

/// Median LED image speed (px/ms) between consecutive identified frames of a track.
fn image_speed(t: &Track<'_>) -> f64 {
    let mut v: Vec<f64> = t
        .samples
        .windows(2)
        .filter_map(|w| {
            let ((ta, a), (tb, b)) = (w[0]?, w[1]?);
            let dt_ms = (tb - ta) * 1e-6;
            (dt_ms > 0.0 && dt_ms < 1.5 * t.period_ns * 1e-6).then(|| (b[0] - a[0]).norm() / dt_ms)
        })
        .collect();
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The identified LEDs of every camera moved to camera 0's frame instant (middle of row 0's
/// exposure) of their frame. A view whose LEDs cannot be moved (no neighbouring frame to
/// interpolate with) is rejected as [`Rejection::Unbridged`].
pub fn retime_observations(
    obs: &WandObservations,
    clock: &FrameClock,
    timing: &[CameraTiming],
) -> WandObservations {
    let n_cam = timing.len();
    let tracks: Vec<Track<'_>> = (0..n_cam).map(|c| Track::new(obs, clock, c, timing[c])).collect();
    let mut out = obs.clone();
    for (p, row) in out.views.iter_mut().enumerate() {
        let t_ref = clock.instants_ns[0][p].map(|t| t + timing[0].offset_ns as f64);
        for (c, view) in row.iter_mut().enumerate() {
            let Ok(px) = view else { continue };
            let moved: Option<LedPixels> =
                t_ref.and_then(|t| (0..px.len()).map(|k| tracks[c].at(k, p, t)).collect());
            *view = match moved {
                Some(m) => Ok(m),
                None => Err(Rejection::Unbridged),
            };
        }
    }
    out
}

/// Reads `timestamps.csv` of a recording when present.
pub fn read_clock(
    frames_dir: &std::path::Path,
    n_cameras: usize,
    frames: &[String],
) -> Result<Option<FrameClock>> {
    let path = frames_dir.join("timestamps.csv");
    if !path.is_file() {
        return Ok(None);
    }
    let stamps = crate::cmd::track::read_timestamps(&path, n_cameras)?;
    FrameClock::new(&stamps, frames)
        .map(Some)
        .map_err(|e| anyhow!("{}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_numbers_come_from_file_names() {
        assert_eq!(frame_number("000123.pgm").unwrap(), 123);
        assert!(
            frame_number("left.pgm")
                .unwrap_err()
                .to_string()
                .contains("frame number")
        );
        let mut m = BTreeMap::new();
        m.insert(0, (0, false));
        let c = FrameClock::new(&[m], &["left.pgm".to_string()]).unwrap();
        assert!(c.not_continuous.unwrap().contains("frame number"));
    }

    #[test]
    fn sparse_sets_are_not_a_continuous_stream() {
        let frames: Vec<String> = (0..40).map(|i| format!("{i:06}.pgm")).collect();
        let mut m = BTreeMap::new();
        for i in 0..40u64 {
            // A set now and then: 150–400 ms apart.
            m.insert(i, (i * 250_000_000 + (i * 7919 % 11) * 15_000_000, false));
        }
        let c = FrameClock::new(&[m], &frames).unwrap();
        assert!(c.not_continuous.unwrap().contains("not a continuous stream"));
    }

    #[test]
    fn clock_smooths_jitter_and_bridges_drops() {
        let frames: Vec<String> = (0..200).map(|i| format!("{i:06}.pgm")).collect();
        let period = 8_333_333.0;
        let mut m = BTreeMap::new();
        for i in 0..200u64 {
            // ±150 µs alternating jitter, frame 50 dropped, 3 ms phase.
            let jitter = if i % 2 == 0 { 150_000.0 } else { -150_000.0 };
            let ts = 3_000_000.0 + i as f64 * period + jitter;
            m.insert(i, (ts as u64, i == 50));
        }
        let clock = FrameClock::new(&[m], &frames).unwrap();
        assert!(clock.instants_ns[0][50].is_none());
        assert!(
            (clock.period_ns[0] - period).abs() < 100.0,
            "{}",
            clock.period_ns[0]
        );
        let t = clock.instants_ns[0][120].unwrap();
        assert!((t - (3_000_000.0 + 120.0 * period)).abs() < 5_000.0, "{t}");
        assert!((clock.jitter_rms_ns[0] - 150_000.0).abs() < 2_000.0);
    }
}
