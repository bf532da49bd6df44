//! Per-camera simulated timing: free-running clocks, timestamp jitter, exposure time and
//! rolling shutter (issue 39, docs/simulator.md "Camera timing").
//!
//! The scenario has one true clock (ns since its start; truth is a function of it). Frame slot
//! `k` is nominally at `k / fps`. Camera `c` exposes on its own clock: the middle of row 0's
//! exposure of its `j`-th frame is at
//!
//! ```text
//! e_c(j) = phase_ns + j · period_c,      period_c = (1e9 / fps) · (1 + rate_ppm · 1e-6)
//! ```
//!
//! and slot `k` of camera `c` is its exposure nearest to `k / fps` (`j = round((k·T − phase)
//! / period_c)`; with |phase| < T/2 and no drift, `j = k`). Row `r` is exposed `r ×
//! line_time_ns` after row 0. The camera reports the timestamp
//!
//! ```text
//! reported_ns = round(e_c(j) + ts_offset_ns + jitter),   jitter ~ N(0, ts_jitter_ns²) clipped at ±3σ
//! ```
//!
//! on the scenario's clock, so `ts_offset_ns` = reported timestamp − middle of row 0's exposure
//! (jitter aside) = `−CameraTiming::offset_ns` of irtrack-core. Jitter moves only the reported
//! timestamp, never the exposure. All zero (the default) is today's synchronous global-shutter
//! camera, bit for bit.

use irtrack_core::timing::{CameraTiming, Shutter};

use crate::SimError;
use crate::noise::{hash_words, normal_quantile, unit_from_hash};

/// Sub-samples across the exposure when a camera has its own exposure time (motion blur):
/// at least this many, or `SimConfig::motion_blur_steps` if more.
pub const EXPOSURE_SUBSAMPLES: u32 = 8;
/// Fixed-point iterations of the rolling-shutter render (row → instant → row); three
/// converge to far below a micro-pixel for hand speeds.
pub const ROLLING_ITERATIONS: usize = 3;
/// Jitter draws are clipped at this many standard deviations (a hard bound for tests and
/// pairing limits).
pub const JITTER_CLIP_SIGMA: f64 = 3.0;

/// One simulated camera's clock, shutter and timestamping. `Default` = synchronous global
/// shutter stamped at mid-exposure (today's simulator).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SimCameraTiming {
    /// Middle of row 0's exposure of the camera's frame 0 against the nominal grid (ns).
    pub phase_ns: f64,
    /// Clock rate error: the camera's frame period is nominal × (1 + ppm·1e-6).
    pub rate_ppm: f64,
    /// Standard deviation (ns) of the noise on the *reported* timestamp (clipped at ±3σ).
    pub ts_jitter_ns: f64,
    /// Exposure time (ns); 0 = `SensorSpec::exposure_s` with `motion_blur_steps`. Non-zero: the
    /// spot is the average of at least [`EXPOSURE_SUBSAMPLES`] sub-samples across it.
    pub exposure_ns: f64,
    /// Rolling shutter: row `r` is exposed `r × line_time_ns` after row 0; 0 = global shutter.
    pub line_time_ns: f64,
    /// Reported timestamp minus the middle of row 0's exposure (ns) = −`CameraTiming::offset_ns`.
    pub ts_offset_ns: f64,
}

impl SimCameraTiming {
    /// Whether this is the synchronous default (rendering and stamping take today's path).
    pub fn is_synchronous(&self) -> bool {
        *self == SimCameraTiming::default()
    }

    /// The constants the tracker must be given for this camera (irtrack-core's model): rolling
    /// when a line time is set, `offset_ns = −ts_offset_ns`. Phase, drift and jitter are not
    /// constants of the camera but what the clock model has to estimate.
    pub fn core_timing(&self) -> CameraTiming {
        CameraTiming {
            shutter: if self.line_time_ns > 0.0 {
                Shutter::Rolling
            } else {
                Shutter::Global
            },
            line_time_ns: self.line_time_ns.round() as u32,
            exposure_ns: self.exposure_ns.round() as u32,
            offset_ns: -(self.ts_offset_ns.round() as i64),
        }
    }

    /// Checks ranges (units: a second is far beyond any camera's value).
    pub fn validate(&self, camera: usize) -> Result<(), SimError> {
        let bad = |reason: String| {
            Err(SimError::Config {
                field: "timing",
                reason: format!("camera {camera}: {reason}"),
            })
        };
        let all = [
            self.phase_ns,
            self.rate_ppm,
            self.ts_jitter_ns,
            self.exposure_ns,
            self.line_time_ns,
            self.ts_offset_ns,
        ];
        if all.iter().any(|v| !v.is_finite()) {
            return bad(format!("{self:?}: values must be finite"));
        }
        if self.phase_ns.abs() > 1e9 || self.ts_offset_ns.abs() > 1e9 {
            return bad("phase and timestamp offset must be within ±1 s".into());
        }
        if self.rate_ppm.abs() > 1000.0 {
            return bad(format!("rate {} ppm beyond ±1000 ppm", self.rate_ppm));
        }
        if !(0.0..=1e8).contains(&self.ts_jitter_ns) {
            return bad(format!(
                "timestamp jitter {} ns must be in 0..=0.1 s",
                self.ts_jitter_ns
            ));
        }
        if !(0.0..=1e9).contains(&self.exposure_ns) {
            return bad(format!("exposure {} ns must be in 0..=1 s", self.exposure_ns));
        }
        if !(0.0..=1e7).contains(&self.line_time_ns) {
            return bad(format!(
                "line time {} ns must be in 0..=10 ms (a row takes µs)",
                self.line_time_ns
            ));
        }
        Ok(())
    }
}

/// When one camera's frame of one slot was exposed and what it reports.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTime {
    /// The camera's own frame counter for this slot (`j` above; may differ from the slot after
    /// drift has accumulated a period, and be negative before the start).
    pub exposure_index: i64,
    /// Middle of row 0's exposure on the scenario's clock (s).
    pub exposure_s: f64,
    /// The timestamp the camera gives (ns on the scenario's clock; negative when the exposure
    /// was before the scenario's start).
    pub reported_ns: i64,
}

/// Camera `camera`'s exposure for slot `index` and the timestamp it reports.
pub(crate) fn frame_time(t: &SimCameraTiming, fps: f64, seed: u64, index: u64, camera: usize) -> FrameTime {
    // Exact today's arithmetic for the default: index / fps and round(index · 1e9 / fps).
    let cam_fps = fps / (1.0 + t.rate_ppm * 1e-6);
    let j = if t.phase_ns == 0.0 && t.rate_ppm == 0.0 {
        index as i64
    } else {
        let nominal_ns = index as f64 * 1e9 / fps;
        ((nominal_ns - t.phase_ns) * cam_fps / 1e9).round() as i64
    };
    let exposure_s = t.phase_ns * 1e-9 + j as f64 / cam_fps;
    let jitter_ns = if t.ts_jitter_ns > 0.0 {
        jitter_sigmas(seed, camera, j) * t.ts_jitter_ns
    } else {
        0.0
    };
    let reported = j as f64 * 1e9 / cam_fps + (t.phase_ns + t.ts_offset_ns + jitter_ns);
    FrameTime {
        exposure_index: j,
        exposure_s,
        reported_ns: reported.round() as i64,
    }
}

/// A standard normal deviate clipped at ±[`JITTER_CLIP_SIGMA`], a function of (seed, camera,
/// exposure) only: the same exposure always reports the same timestamp.
fn jitter_sigmas(seed: u64, camera: usize, exposure_index: i64) -> f64 {
    let h = hash_words(&[seed, camera as u64, exposure_index as u64, 0x4a49_5454]);
    // Mid-bin, so never 0 or 1.
    let p = ((h >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64);
    normal_quantile(p).clamp(-JITTER_CLIP_SIGMA, JITTER_CLIP_SIGMA)
}

/// Per-camera values given as one list per quantity: each list is empty (all 0), one value
/// (every camera) or one value per camera. Times in ns.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TimingLists {
    /// Phase of each camera (ns).
    pub phase_ns: Vec<f64>,
    /// Clock rate error (ppm).
    pub rate_ppm: Vec<f64>,
    /// Timestamp jitter, standard deviation (ns).
    pub ts_jitter_ns: Vec<f64>,
    /// Exposure time (ns).
    pub exposure_ns: Vec<f64>,
    /// Rolling-shutter line time (ns per row).
    pub line_time_ns: Vec<f64>,
    /// Reported timestamp − middle of row 0's exposure (ns).
    pub ts_offset_ns: Vec<f64>,
}

impl TimingLists {
    /// The per-camera timings for `cameras` cameras; a list of another length is an error
    /// naming it. Every list empty gives an empty vector (the synchronous default).
    pub fn build(&self, cameras: usize) -> Result<Vec<SimCameraTiming>, SimError> {
        let lists: [(&'static str, &Vec<f64>); 6] = [
            ("phase", &self.phase_ns),
            ("ppm", &self.rate_ppm),
            ("timestamp jitter", &self.ts_jitter_ns),
            ("exposure", &self.exposure_ns),
            ("line time", &self.line_time_ns),
            ("timestamp offset", &self.ts_offset_ns),
        ];
        if lists.iter().all(|(_, l)| l.is_empty()) {
            return Ok(Vec::new());
        }
        for (name, l) in &lists {
            if l.len() > 1 && l.len() != cameras {
                return Err(SimError::Config {
                    field: "timing",
                    reason: format!(
                        "{name}: {} values for {cameras} cameras (give one value for all, or one per camera)",
                        l.len()
                    ),
                });
            }
        }
        let at = |l: &Vec<f64>, c: usize| match l.len() {
            0 => 0.0,
            1 => l[0],
            _ => l[c],
        };
        let out: Vec<SimCameraTiming> = (0..cameras)
            .map(|c| SimCameraTiming {
                phase_ns: at(&self.phase_ns, c),
                rate_ppm: at(&self.rate_ppm, c),
                ts_jitter_ns: at(&self.ts_jitter_ns, c),
                exposure_ns: at(&self.exposure_ns, c),
                line_time_ns: at(&self.line_time_ns, c),
                ts_offset_ns: at(&self.ts_offset_ns, c),
            })
            .collect();
        for (c, t) in out.iter().enumerate() {
            t.validate(c)?;
        }
        Ok(out)
    }

    /// The "free-running" preset: phases spread evenly over the whole frame period (camera `i`
    /// at `i/n` of it, wrapped into ±half a period, camera 0 at 0), clock rates drawn
    /// uniformly in ±50 ppm (seeded), 200 µs timestamp jitter. The cameras of the issue's
    /// measurement (issue 39 item 7). Lists already set are kept.
    pub fn free_running(mut self, cameras: usize, fps: f64, seed: u64) -> Self {
        let period_ns = 1e9 / fps;
        if self.phase_ns.is_empty() {
            self.phase_ns = (0..cameras)
                .map(|i| {
                    let p = period_ns * i as f64 / cameras.max(1) as f64;
                    if p > period_ns / 2.0 { p - period_ns } else { p }
                })
                .collect();
        }
        if self.rate_ppm.is_empty() {
            self.rate_ppm = (0..cameras)
                .map(|i| {
                    let u = unit_from_hash(hash_words(&[seed, i as u64, 0x5050_4d00]));
                    ((u * 2.0 - 1.0) * 50.0 * 10.0).round() / 10.0
                })
                .collect();
        }
        if self.ts_jitter_ns.is_empty() {
            self.ts_jitter_ns = vec![200_000.0];
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_todays_timing_exactly() {
        let t = SimCameraTiming::default();
        for index in [0u64, 1, 7, 119, 120, 12345] {
            let f = frame_time(&t, 120.0, 1, index, 1);
            assert_eq!(f.exposure_index, index as i64);
            assert_eq!(f.exposure_s, index as f64 / 120.0);
            assert_eq!(f.reported_ns, (index as f64 * 1e9 / 120.0).round() as i64);
        }
    }

    #[test]
    fn phase_and_ppm_give_the_expected_timestamps() {
        let t = SimCameraTiming {
            phase_ns: 3_100_000.0,
            rate_ppm: 40.0,
            ..SimCameraTiming::default()
        };
        let period = 1e9 / 100.0 * (1.0 + 40e-6);
        let mut prev = None;
        for index in 0..1000u64 {
            let f = frame_time(&t, 100.0, 9, index, 2);
            let expect = 3_100_000.0 + f.exposure_index as f64 * period;
            assert!((f.reported_ns as f64 - expect).abs() <= 0.5, "{index}");
            assert!((f.exposure_s * 1e9 - expect).abs() < 1e-3);
            if let Some(p) = prev {
                // Consecutive frames one drifted period apart (± rounding).
                assert!(((f.reported_ns - p) as f64 - period).abs() <= 1.0);
            }
            prev = Some(f.reported_ns);
        }
        // After 1000 frames the drift is 1000 · 10 ms · 40 ppm = 400 µs.
        let last = frame_time(&t, 100.0, 9, 999, 2);
        let drift = last.reported_ns as f64 - (999.0 * 1e7 + 3_100_000.0);
        assert!((drift - 999.0 * 1e7 * 40e-6).abs() < 1.0, "drift {drift}");
    }

    #[test]
    fn the_slot_takes_the_nearest_exposure() {
        // −2.4 ms: frame k pairs with slot k; after enough drift the camera's counter slips.
        let t = SimCameraTiming {
            phase_ns: -2_400_000.0,
            rate_ppm: 500.0,
            ..SimCameraTiming::default()
        };
        let mut slipped = false;
        for index in 0..5000u64 {
            let f = frame_time(&t, 120.0, 1, index, 1);
            let nominal = index as f64 / 120.0;
            assert!((f.exposure_s - nominal).abs() <= 0.5 / 120.0 * 1.001, "{index}");
            slipped |= f.exposure_index != index as i64;
        }
        assert!(slipped, "500 ppm over 5000 frames must slip a frame");
        assert!(frame_time(&t, 120.0, 1, 0, 1).reported_ns < 0);
    }

    #[test]
    fn jitter_is_bounded_deterministic_and_only_on_the_timestamp() {
        let sigma = 200_000.0;
        let t = SimCameraTiming {
            ts_jitter_ns: sigma,
            ..SimCameraTiming::default()
        };
        let (mut sum, mut sum_sq, n) = (0.0, 0.0, 5000);
        for index in 0..n {
            let f = frame_time(&t, 120.0, 3, index, 1);
            // The exposure is on the grid, untouched.
            assert_eq!(f.exposure_s, index as f64 / 120.0);
            let d = f.reported_ns as f64 - index as f64 * 1e9 / 120.0;
            assert!(d.abs() <= JITTER_CLIP_SIGMA * sigma + 1.0, "{d}");
            sum += d;
            sum_sq += d * d;
            assert_eq!(f, frame_time(&t, 120.0, 3, index, 1));
        }
        let mean = sum / n as f64;
        let sd = (sum_sq / n as f64 - mean * mean).sqrt();
        assert!(mean.abs() < 10_000.0, "mean {mean}");
        assert!((sd / sigma - 1.0).abs() < 0.05, "sd {sd}");
        // Another camera or seed: other draws.
        assert_ne!(
            frame_time(&t, 120.0, 3, 5, 1).reported_ns,
            frame_time(&t, 120.0, 3, 5, 2).reported_ns
        );
    }

    #[test]
    fn offset_is_the_negated_core_offset() {
        let t = SimCameraTiming {
            ts_offset_ns: 1_250_000.0,
            line_time_ns: 15_000.0,
            exposure_ns: 1e6,
            ..SimCameraTiming::default()
        };
        let f = frame_time(&t, 120.0, 1, 10, 0);
        let core = t.core_timing();
        assert_eq!(core.shutter, Shutter::Rolling);
        // The core's instant of row 0 from the reported timestamp is the true exposure.
        let row0 = core.blob_instant_ns(f.reported_ns as u64, 0.0);
        assert!((row0 - f.exposure_s * 1e9).abs() < 1.0);
        assert!(core.validate().is_ok());
    }

    #[test]
    fn lists_broadcast_and_name_a_wrong_length() {
        let l = TimingLists {
            phase_ns: vec![0.0, 1e6, -1e6],
            ts_jitter_ns: vec![5.0],
            ..TimingLists::default()
        };
        let v = l.build(3).unwrap();
        assert_eq!(v[2].phase_ns, -1e6);
        assert!(v.iter().all(|t| t.ts_jitter_ns == 5.0 && t.rate_ppm == 0.0));
        let e = l.build(4).unwrap_err().to_string();
        assert!(e.contains("phase") && e.contains("4 cameras"), "{e}");
        assert!(TimingLists::default().build(4).unwrap().is_empty());
        let bad = TimingLists {
            line_time_ns: vec![2e7],
            ..TimingLists::default()
        };
        assert!(bad.build(2).unwrap_err().to_string().contains("line time"));
        let free = TimingLists::default().free_running(4, 120.0, 1).build(4).unwrap();
        let period = 1e9 / 120.0;
        assert_eq!(free[0].phase_ns, 0.0);
        assert!((free[2].phase_ns - period / 2.0).abs() < 1e-6);
        assert!((free[3].phase_ns + period / 4.0).abs() < 1e-6);
        assert!(
            free.iter()
                .all(|t| t.rate_ppm.abs() <= 50.0 && t.ts_jitter_ns == 200_000.0)
        );
    }
}
