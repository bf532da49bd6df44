//! Each camera's clock model in the processing loop (docs/timing.md, "Camera clocks").
//!
//! Every frame's sequence and timestamp go to its camera's [`ClockModel`]. While a model is
//! locked, the frame's `timestamp_ns` is replaced by the smoothed instant for the rest of the
//! set's processing (blob instants, observations sent to a cluster solver); the driver's own
//! stamp is kept and put back before the viewers' copy, so frame sets (`/api/frameset`,
//! `host-tools capture`'s `timestamps.csv`) and the record's `capture_ts_ns` keep reporting raw
//! driver time. The models are allocated once, with the engine; the figures go to the shared
//! status (atomics) every few frames.

use std::sync::atomic::Ordering;

use irtrack_core::clock_model::{CameraClocks, ClockConfig, ClockState};

use crate::source::Frame;
use crate::status::{ClockCounters, SharedStatus};

const R: Ordering = Ordering::Relaxed;

/// A camera's figures reach the status every this many of its frames (the window scan for the
/// largest residual is not worth doing per frame); cameras take turns.
const PUBLISH_EVERY: u64 = 8;

/// The clock models of the engine's cameras and each frame's raw timestamp.
pub struct FrameClocks {
    clocks: CameraClocks,
    raw_ns: Vec<u64>,
    duplicate: Vec<bool>,
    sets: u64,
}

impl FrameClocks {
    /// Models for `cameras` cameras; `nominal_fps` (the source's configured rate) only for the
    /// rate error in ppm.
    pub fn new(cameras: usize, nominal_fps: Option<f64>) -> irtrack_core::Result<Self> {
        Ok(Self {
            clocks: CameraClocks::new(cameras, ClockConfig::with_nominal_fps(nominal_fps))?,
            raw_ns: vec![0; cameras],
            duplicate: vec![false; cameras],
            sets: 0,
        })
    }

    /// Feeds each frame to its camera's model and, where the model is locked, replaces the
    /// frame's timestamp by its smoothed instant. No allocation.
    pub fn apply(&mut self, frames: &mut [Frame], status: &SharedStatus) {
        self.sets = self.sets.wrapping_add(1);
        for (c, f) in frames.iter_mut().enumerate().take(self.raw_ns.len()) {
            let Ok(out) = self.clocks.observe(c, Some(f.sequence), f.timestamp_ns) else {
                continue;
            };
            self.raw_ns[c] = f.timestamp_ns;
            self.duplicate[c] = out.duplicate;
            // Logged at the 1st, 2nd, 4th, 8th ... jump: a camera that keeps jumping does not
            // flood the log (the count is on /status).
            let jumps = self.clocks.model(c).map_or(0, |m| m.jumps());
            if out.jump && jumps.is_power_of_two() {
                tracing::warn!(
                    camera = c,
                    jumps,
                    timestamp_ns = f.timestamp_ns,
                    sequence = f.sequence,
                    "camera clock jumped (driver clock reset or camera restart); re-locking"
                );
            }
            if out.smoothed {
                f.timestamp_ns = out.instant_ns;
            }
        }
        for (c, counters) in status.cameras.iter().enumerate().take(self.raw_ns.len()) {
            if (self.sets + c as u64).is_multiple_of(PUBLISH_EVERY) {
                self.publish(c, &counters.clock);
            }
        }
    }

    /// Puts each frame's raw driver timestamp back (frame sets report driver time).
    pub fn restore_raw(&self, frames: &mut [Frame]) {
        for (f, raw) in frames.iter_mut().zip(&self.raw_ns) {
            f.timestamp_ns = *raw;
        }
    }

    /// Whether camera `camera`'s frame of the current set repeats its previous one.
    pub fn is_duplicate(&self, camera: usize) -> bool {
        self.duplicate.get(camera).copied().unwrap_or(false)
    }

    /// The models (phase and drift between cameras: [`CameraClocks::relative_to_first`]).
    pub fn clocks(&self) -> &CameraClocks {
        &self.clocks
    }

    fn publish(&self, camera: usize, out: &ClockCounters) {
        let Some(model) = self.clocks.model(camera) else {
            return;
        };
        let r = model.report();
        let rel = self.clocks.relative_to_first(camera);
        let bits = |v: Option<f64>| v.unwrap_or(f64::NAN).to_bits();
        out.state.store(
            match r.state {
                ClockState::WarmingUp => 1,
                ClockState::Locked => 2,
                ClockState::Relocking => 3,
            },
            R,
        );
        out.period_ns_bits.store(bits(r.period_ns), R);
        out.rate_error_ppm_bits.store(bits(r.rate_error_ppm), R);
        out.jitter_rms_ns_bits.store(bits(r.jitter_rms_ns), R);
        out.jitter_max_ns_bits.store(bits(r.jitter_max_ns), R);
        out.phase_ns_bits.store(bits(rel.map(|x| x.phase_ns)), R);
        out.drift_ppm_bits.store(bits(rel.map(|x| x.drift_ppm)), R);
        out.drift_us_per_min_bits
            .store(bits(rel.map(|x| x.drift_us_per_min)), R);
        out.drops.store(r.drops, R);
        out.duplicates.store(r.duplicates, R);
        out.jumps.store(r.jumps, R);
        out.outliers.store(r.outliers, R);
        out.sequence_used.store(r.sequence_used, R);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::source::Pixels;

    fn frame(seq: u64, ts: u64) -> Frame {
        Frame {
            width_px: 1,
            height_px: 1,
            stride_px: 1,
            bit_depth: 8,
            pixels: Pixels::U8(vec![0]),
            timestamp_ns: ts,
            sequence: seq,
        }
    }

    #[test]
    fn locked_frames_carry_smoothed_instants_and_raw_ones_come_back() {
        let status = SharedStatus::new(2, "test".into(), "none".into());
        let mut clocks = FrameClocks::new(2, Some(100.0)).unwrap();
        let mut frames = vec![frame(0, 0), frame(0, 0)];
        let mut smoothed_seen = 0;
        for k in 0..200u64 {
            // Camera 1: 2.5 ms after camera 0, every other stamp 150 µs late.
            let raw = [
                1_000_000_000 + k * 10_000_000,
                1_002_500_000 + k * 10_000_000 + (k % 2) * 150_000,
            ];
            for (f, t) in frames.iter_mut().zip(raw) {
                *f = frame(k, t);
            }
            clocks.apply(&mut frames, &status);
            if k > 50 {
                // The line runs through the middle of the two stamp levels.
                let d = frames[1].timestamp_ns as i64 - (1_002_575_000 + k as i64 * 10_000_000);
                assert!(d.abs() < 5_000, "{k}: {d} ns off");
                smoothed_seen += 1;
            }
            clocks.restore_raw(&mut frames);
            assert_eq!(frames[1].timestamp_ns, raw[1]);
        }
        assert!(smoothed_seen > 0);
        let c1 = &status.cameras[1].clock;
        assert_eq!(c1.state.load(R), 2);
        let phase_us = f64::from_bits(c1.phase_ns_bits.load(R)) / 1e3;
        assert!((phase_us - 2575.0).abs() < 5.0, "{phase_us}");
        let period = f64::from_bits(c1.period_ns_bits.load(R));
        assert!((period - 10_000_000.0).abs() < 10.0, "{period}");
        assert!(f64::from_bits(status.cameras[0].clock.phase_ns_bits.load(R)).abs() < 1.0);
        assert!(!clocks.is_duplicate(1));
    }
}
