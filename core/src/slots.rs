//! Which frames of free-running cameras belong to one set.
//!
//! Free-running cameras expose at their own phase anywhere in the frame period, drift by tens
//! of ppm against each other and stamp their frames with a few hundred µs of jitter. Grouping
//! their frames by "within half a period of the first one to arrive" depends on which one
//! arrived first: a camera half a period away from another is put with its frame before in
//! one set and its frame after in the next, sets fall apart into partial ones and a frame can
//! be solved beside one a whole period away.
//!
//! A [`SlotGrid`] gives every frame a *slot* instead: a cell of a grid with the frame period
//! as its pitch, centred on the reference camera's frames (camera 0 by default; its phase is
//! followed, so the grid drifts with it). A set is the frames of one slot, whatever order they
//! arrive in, so every receiver that sees the same frames forms the same sets. Each camera
//! keeps its place in the grid from frame to frame (its previous slot plus the frames between,
//! counted from the timestamps) as long as the frame lies within half a period plus a margin
//! (`hysteresis`) of that slot's centre: a camera whose phase sits on a cell boundary does not
//! hop between two slots with its timestamp jitter. When drift carries it beyond the margin it
//! moves to the nearest slot, once; that set misses it or has it twice (counted by the
//! caller's pairing).
//!
//! Nothing here allocates after [`SlotGrid::new`].

use alloc::vec;
use alloc::vec::Vec;

use crate::error::{Error, Result};

/// How fast the grid follows its reference camera's phase: each reference frame moves the grid
/// by this fraction of the frame's offset from its slot's centre (a first-order loop; with a
/// clock 0.1 % off the nominal rate the grid lags by 8 × 0.1 % of a period).
const FOLLOW: f64 = 1.0 / 8.0;

/// A frame's place in the grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Slot {
    /// Slot number; consecutive slots are one frame period apart. Only differences and order
    /// mean anything (the first slot is the first frame's time divided by the period).
    pub index: u64,
    /// The frame's time minus the slot's centre, ns (within ± (½ + hysteresis) periods).
    pub offset_ns: f64,
}

/// Slot assignment for a rig's cameras (see the module documentation).
#[derive(Debug, Clone)]
pub struct SlotGrid {
    period_ns: f64,
    hysteresis: f64,
    reference: usize,
    /// A slot centre: (time ns, slot number).
    anchor: Option<(u64, u64)>,
    /// The reference camera has been seen (until then the first frame of any camera centres
    /// the grid).
    reference_seen: bool,
    /// Per camera: timestamp and slot of its previous frame.
    cameras: Vec<Option<(u64, u64)>>,
    moves: u64,
}

impl SlotGrid {
    /// Default margin beyond half a period before a camera moves to another slot: an eighth of
    /// the period (2.1 ms at 60 fps, far more than the ±0.6 ms of 200 µs timestamp jitter).
    pub const DEFAULT_HYSTERESIS: f64 = 0.125;

    /// A grid of `period_ns` for `cameras` cameras, centred on `reference`'s frames.
    pub fn new(cameras: usize, period_ns: u64, reference: usize, hysteresis: f64) -> Result<SlotGrid> {
        if cameras == 0 || reference >= cameras {
            return Err(Error::InvalidParams {
                reason: alloc::format!("slot grid: reference camera {reference} of {cameras} cameras"),
            });
        }
        if period_ns == 0 || !(0.0..0.5).contains(&hysteresis) {
            return Err(Error::InvalidParams {
                reason: alloc::format!(
                    "slot grid: period {period_ns} ns must be > 0 and hysteresis {hysteresis} in 0..0.5"
                ),
            });
        }
        Ok(SlotGrid {
            period_ns: period_ns as f64,
            hysteresis,
            reference,
            anchor: None,
            reference_seen: false,
            cameras: vec![None; cameras],
            moves: 0,
        })
    }

    /// The grid's pitch, ns.
    pub fn period_ns(&self) -> f64 {
        self.period_ns
    }

    /// How often a camera moved to another slot than its previous frame's plus the frames
    /// between (drift across a cell boundary, a dropped run of frames, a clock jump).
    pub fn moves(&self) -> u64 {
        self.moves
    }

    /// Slots from the anchor to `ts_ns`, fractional.
    fn position(&self, anchor: (u64, u64), ts_ns: u64) -> f64 {
        (i128::from(ts_ns) - i128::from(anchor.0)) as f64 / self.period_ns
    }

    fn slot_at(anchor: (u64, u64), steps: i64) -> u64 {
        (i128::from(anchor.1) + i128::from(steps)).clamp(0, i128::from(u64::MAX)) as u64
    }

    /// The slot of `camera`'s frame stamped `ts_ns` (a shared clock for all cameras). Frames of
    /// one camera must come in capture order; an earlier timestamp is taken as a restart.
    /// `None` for a camera index beyond the grid.
    pub fn assign(&mut self, camera: usize, ts_ns: u64) -> Option<Slot> {
        let last = *self.cameras.get(camera)?;
        let is_reference = camera == self.reference;
        let anchor = match self.anchor {
            Some(a) if self.reference_seen || !is_reference => a,
            // First frame, or the reference camera's first: it centres the grid (keeping the
            // slot numbering continuous).
            other => {
                let index = match other {
                    Some(a) => Self::slot_at(a, libm::round(self.position(a, ts_ns)) as i64),
                    None => libm::round(ts_ns as f64 / self.period_ns) as u64,
                };
                self.reference_seen |= is_reference;
                self.anchor = Some((ts_ns, index));
                (ts_ns, index)
            }
        };
        let x = self.position(anchor, ts_ns);
        let nearest = libm::round(x) as i64;
        // The camera's place continued: its previous slot plus the frames since (counted from
        // the timestamps, so a dropped frame is a step of two).
        let continued = last.and_then(|(last_ts, last_slot)| {
            (ts_ns > last_ts).then(|| {
                let frames = libm::round((ts_ns - last_ts) as f64 / self.period_ns) as i128;
                (i128::from(last_slot) - i128::from(anchor.1) + frames) as i64
            })
        });
        let steps = match continued {
            Some(k) if libm::fabs(x - k as f64) <= 0.5 + self.hysteresis => k,
            _ => nearest,
        };
        if last.is_some() && continued != Some(steps) {
            self.moves += 1;
        }
        let index = Self::slot_at(anchor, steps);
        let offset = x - steps as f64;
        self.cameras[camera] = Some((ts_ns, index));
        if is_reference && self.reference_seen {
            // Follow the reference camera's phase (and so its rate).
            let centre = i128::from(anchor.0) + libm::round(steps as f64 * self.period_ns) as i128;
            let moved = centre + libm::round(FOLLOW * offset * self.period_ns) as i128;
            self.anchor = Some((moved.clamp(0, i128::from(u64::MAX)) as u64, index));
        }
        Some(Slot {
            index,
            offset_ns: offset * self.period_ns,
        })
    }

    /// Forgets `camera`'s place (its board or device restarted); its next frame takes the
    /// nearest slot.
    pub fn reset_camera(&mut self, camera: usize) {
        if let Some(p) = self.cameras.get_mut(camera) {
            *p = None;
        }
        if camera == self.reference {
            self.reference_seen = false;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PERIOD: u64 = 16_666_667; // 60 fps

    /// Uniform in [-1, 1) from a 64-bit LCG.
    fn uniform(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    /// A camera's `j`-th timestamp: phase, drift and ± `jitter_ns` (uniform).
    fn stamp(t0: u64, phase_ns: f64, ppm: f64, j: u64, jitter_ns: f64, rng: &mut u64) -> u64 {
        let t = t0 as f64 + phase_ns + j as f64 * PERIOD as f64 * (1.0 + ppm * 1e-6);
        (t + jitter_ns * uniform(rng)) as u64
    }

    /// Four free-running cameras, one with its phase on a cell boundary, drifting ±50 ppm
    /// against each other with ±600 µs timestamp jitter, fed in a shuffled order: each camera
    /// steps one slot per frame except when drift carries it across a boundary (once per
    /// crossing), and no slot holds frames further apart than the grid allows.
    #[test]
    fn free_running_cameras_keep_their_slots_through_jitter_and_drift() {
        let mut grid = SlotGrid::new(4, PERIOD, 0, SlotGrid::DEFAULT_HYSTERESIS).unwrap();
        let t0 = 1_795_000_000_000_000_000u64;
        let phases = [0.0, 0.25, 0.5, -0.25].map(|f| f * PERIOD as f64);
        let ppm = [0.0, 50.0, -50.0, 20.0];
        let mut rng = 7u64;
        let frames = 12_000u64; // 200 s: camera 1 and 2 drift 1.2 and 0.6 periods
        let mut last: [Option<u64>; 4] = [None; 4];
        let mut steps_not_one = [0u32; 4];
        let mut by_slot: std::collections::BTreeMap<u64, Vec<(usize, u64)>> = Default::default();
        for j in 0..frames {
            let mut order = [0usize, 1, 2, 3];
            for i in (1..4).rev() {
                let k = ((uniform(&mut rng) + 1.0) * 0.5 * (i + 1) as f64) as usize;
                order.swap(i, k.min(i));
            }
            for c in order {
                let ts = stamp(t0, phases[c], ppm[c], j, 600_000.0, &mut rng);
                let s = grid.assign(c, ts).unwrap();
                assert!(
                    s.offset_ns.abs() <= (0.5 + SlotGrid::DEFAULT_HYSTERESIS) * PERIOD as f64 + 1.0,
                    "camera {c} frame {j}: {s:?}"
                );
                if let Some(l) = last[c]
                    && s.index != l + 1
                {
                    steps_not_one[c] += 1;
                }
                last[c] = Some(s.index);
                by_slot.entry(s.index).or_default().push((c, ts));
            }
        }
        // Camera 0 is the reference; cameras 1 and 2 cross a boundary about once each (the
        // drift relative to camera 0 is 1.2 and 0.6 periods); camera 3 at most once.
        assert_eq!(steps_not_one[0], 0, "{steps_not_one:?}");
        assert!(steps_not_one.iter().all(|&n| n <= 2), "{steps_not_one:?}");
        assert!(grid.moves() <= 5, "moves {}", grid.moves());
        let mut complete = 0;
        for frames in by_slot.values() {
            let lo = frames.iter().map(|f| f.1).min().unwrap();
            let hi = frames.iter().map(|f| f.1).max().unwrap();
            assert!(
                (hi - lo) as f64 <= (1.0 + 2.0 * SlotGrid::DEFAULT_HYSTERESIS) * PERIOD as f64,
                "slot spread {} ns",
                hi - lo
            );
            let mut cams: Vec<usize> = frames.iter().map(|f| f.0).collect();
            cams.sort_unstable();
            cams.dedup();
            if cams.len() == 4 && frames.len() == 4 {
                complete += 1;
            }
        }
        assert!(
            complete as u64 >= frames - 10,
            "{complete} complete slots of {frames}"
        );
    }

    /// Synchronised cameras (same phase, jitter only) share every slot, whichever camera's
    /// frame comes first, even when that is not the reference.
    #[test]
    fn synchronised_cameras_share_every_slot() {
        let mut grid = SlotGrid::new(3, PERIOD, 0, SlotGrid::DEFAULT_HYSTERESIS).unwrap();
        let mut rng = 3u64;
        // A phase half a period off the epoch grid: the first frame (camera 2's) must not
        // leave the cameras on two sides of a cell boundary.
        let t0 = 1_000 * PERIOD + PERIOD / 2;
        for j in 0..2_000u64 {
            let order = if j % 2 == 0 { [2, 1, 0] } else { [0, 2, 1] };
            let slots: Vec<u64> = order
                .iter()
                .map(|&c| {
                    grid.assign(c, stamp(t0, 0.0, 0.0, j, 300_000.0, &mut rng))
                        .unwrap()
                        .index
                })
                .collect();
            assert!(slots.iter().all(|&s| s == slots[0]), "frame {j}: {slots:?}");
        }
        assert_eq!(grid.moves(), 0);
    }

    /// A dropped frame is a step of two slots, not a move; a restart (an earlier timestamp)
    /// takes the nearest slot and is counted as a move.
    #[test]
    fn dropped_frames_and_restarts() {
        let mut grid = SlotGrid::new(2, PERIOD, 0, SlotGrid::DEFAULT_HYSTERESIS).unwrap();
        let t0 = 5_000 * PERIOD;
        let a = grid.assign(1, t0 + PERIOD / 3).unwrap().index;
        let b = grid.assign(1, t0 + 3 * PERIOD + PERIOD / 3).unwrap().index;
        assert_eq!(b, a + 3);
        assert_eq!(grid.moves(), 0);
        let c = grid.assign(1, t0 + PERIOD + PERIOD / 3).unwrap().index;
        assert_eq!(c, a + 1);
        assert_eq!(grid.moves(), 1);
        assert!(grid.assign(2, t0).is_none(), "camera beyond the grid");
    }

    #[test]
    fn refuses_bad_settings() {
        assert!(SlotGrid::new(0, PERIOD, 0, 0.1).is_err());
        assert!(SlotGrid::new(2, PERIOD, 2, 0.1).is_err());
        assert!(SlotGrid::new(2, 0, 0, 0.1).is_err());
        assert!(SlotGrid::new(2, PERIOD, 0, 0.5).is_err());
    }
}
