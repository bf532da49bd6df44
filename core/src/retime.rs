//! Blobs moved to one reference instant (docs/timing.md, "Solving at one instant").
//!
//! Free-running cameras expose at their own phase and rolling-shutter cameras expose each row
//! at its own instant, so the blobs of one frame set were seen at different instants: a moving
//! marker's rays do not meet where the marker was. Each camera keeps the blob centroids of its
//! two previous frames with their exposure instants; a blob of the current frame is linked to
//! the nearest blob of the previous frame (and that one to the frame before), and its centroid
//! is interpolated (quadratic through three samples, linear through two) or extrapolated
//! (constant velocity) to the reference instant. Over a few milliseconds an image track is
//! smooth, so this is done in pixels; lens distortion varies far too slowly to matter.
//!
//! Everything is allocated by [`BlobHistory::new`]; per frame nothing allocates.

use alloc::vec::Vec;

use serde::{Deserialize, Serialize};

use crate::blob::Blob;

/// Which instant a frame set is solved for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TimeMode {
    /// Interpolate: the set is solved at the earliest exposure instant among its blobs, so
    /// every camera's track brackets it (its previous frame before, its current frame after).
    /// Latency grows by the cameras' spread (at most a frame period); accuracy is the best.
    #[default]
    Accurate,
    /// Extrapolate: the set is solved at the newest exposure instant among its blobs; the
    /// other cameras' tracks are carried forward at constant velocity. No added latency,
    /// noisier under acceleration.
    LowLatency,
    /// No retiming: every blob is used where it was seen (cameras assumed synchronous).
    Off,
}

impl TimeMode {
    /// The name used in configs, `/status` and reports.
    pub fn as_str(self) -> &'static str {
        match self {
            TimeMode::Accurate => "accurate",
            TimeMode::LowLatency => "low_latency",
            TimeMode::Off => "off",
        }
    }
}

/// A centroid with its exposure instant.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct TimedPoint {
    /// Column (px).
    pub x_px: f64,
    /// Row (px).
    pub y_px: f64,
    /// Exposure instant (ns on the camera's timestamp clock, corrected by its offset).
    pub t_ns: f64,
}

/// How a blob was brought to the reference instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Retimed {
    /// Seen within the tolerance of the reference instant: used as it is.
    AsSeen,
    /// Moved along its track (samples used: 2 or 3).
    Moved {
        /// Samples of the track used.
        samples: u8,
    },
    /// Seen too far from the reference instant and without a track to move it along (a blob
    /// that just appeared), or beyond the bridgeable span: not usable in this set.
    Unbridged,
}

/// The two previous frames' centroids of one camera.
#[derive(Debug, Clone)]
pub struct BlobHistory {
    /// `frames[0]` = the previous frame, `frames[1]` = the one before.
    frames: [Vec<TimedPoint>; 2],
}

impl BlobHistory {
    /// History for up to `max_blobs` blobs per frame.
    pub fn new(max_blobs: usize) -> Self {
        BlobHistory {
            frames: [Vec::with_capacity(max_blobs), Vec::with_capacity(max_blobs)],
        }
    }

    /// Forgets every track (camera restarted, parameters changed).
    pub fn clear(&mut self) {
        for f in &mut self.frames {
            f.clear();
        }
    }

    /// Pushes the blobs of a finished frame (`instant` gives each blob's exposure instant):
    /// the previous frame becomes the one before. Keeps at most the capacity; never allocates.
    pub fn push(&mut self, blobs: &[Blob], instant: impl Fn(&Blob) -> f64) {
        self.frames.swap(0, 1);
        let f = &mut self.frames[0];
        f.clear();
        let cap = f.capacity();
        for b in blobs.iter().take(cap) {
            f.push(TimedPoint {
                x_px: b.x_px,
                y_px: b.y_px,
                t_ns: instant(b),
            });
        }
    }

    /// The previous frames' points (`0` = previous).
    pub fn frame(&self, age: usize) -> &[TimedPoint] {
        self.frames.get(age).map_or(&[], |f| f.as_slice())
    }

    /// The image velocity (px/ns) of a blob seen at `now`, from the nearest blob of the previous
    /// frame within `gate_px` and less than twice `max_bridge_ns` before it (the samples
    /// [`BlobHistory::retime`] accepts); `None` without one.
    pub fn velocity_px_per_ns(&self, now: TimedPoint, gate_px: f64, max_bridge_ns: f64) -> Option<[f64; 2]> {
        let p1 = nearest(
            self.frame(0),
            now,
            gate_px,
            now.t_ns - 2.0 * max_bridge_ns,
            now.t_ns,
        )?;
        let dt = now.t_ns - p1.t_ns;
        let v = [(now.x_px - p1.x_px) / dt, (now.y_px - p1.y_px) / dt];
        (v[0].is_finite() && v[1].is_finite()).then_some(v)
    }

    /// Moves a blob seen at `now` to `t_ref_ns`.
    ///
    /// `gate_px` bounds how far a marker may move between frames for its samples to be linked;
    /// `max_bridge_ns` bounds how far in time a centroid may be carried; `as_seen_ns` is the
    /// span within which a blob is used as seen (no track needed). Returns the position and
    /// how it was obtained.
    pub fn retime(
        &self,
        now: TimedPoint,
        t_ref_ns: f64,
        mode: TimeMode,
        gate_px: f64,
        max_bridge_ns: f64,
        as_seen_ns: f64,
    ) -> (f64, f64, Retimed) {
        let dt = t_ref_ns - now.t_ns;
        if mode == TimeMode::Off || dt.abs() <= as_seen_ns {
            return (now.x_px, now.y_px, Retimed::AsSeen);
        }
        if dt.abs() > max_bridge_ns {
            return (now.x_px, now.y_px, Retimed::Unbridged);
        }
        // Samples must be older than `now` and recent enough that the track is current.
        let oldest_ns = now.t_ns - 2.0 * max_bridge_ns;
        let Some(p1) = nearest(self.frame(0), now, gate_px, oldest_ns, now.t_ns) else {
            return (now.x_px, now.y_px, Retimed::Unbridged);
        };
        let p2 = nearest(self.frame(1), p1, gate_px, oldest_ns, p1.t_ns);
        let (x, y, samples) = match (mode, p2) {
            // Interpolation (or a short backward step) through three samples: the track's
            // curvature is followed; noise gain stays below one inside the bracket.
            (TimeMode::Accurate, Some(p2)) => {
                let w = lagrange3([p2.t_ns, p1.t_ns, now.t_ns], t_ref_ns);
                (
                    w[0] * p2.x_px + w[1] * p1.x_px + w[2] * now.x_px,
                    w[0] * p2.y_px + w[1] * p1.y_px + w[2] * now.y_px,
                    3,
                )
            }
            // Two samples, or extrapolation forward (low latency): constant velocity, whose
            // noise gain stays moderate where a parabola's would grow fast.
            _ => {
                let span = now.t_ns - p1.t_ns;
                let s = dt / span;
                (
                    now.x_px + s * (now.x_px - p1.x_px),
                    now.y_px + s * (now.y_px - p1.y_px),
                    2,
                )
            }
        };
        if x.is_finite() && y.is_finite() {
            (x, y, Retimed::Moved { samples })
        } else {
            (now.x_px, now.y_px, Retimed::Unbridged)
        }
    }
}

/// The point of `pts` nearest to `to` within `gate_px`, with an instant in `(after, before)`.
fn nearest(pts: &[TimedPoint], to: TimedPoint, gate_px: f64, after: f64, before: f64) -> Option<TimedPoint> {
    let mut best: Option<(f64, TimedPoint)> = None;
    for p in pts {
        // Distinct instants are needed: a duplicated frame would divide by zero.
        if !(p.t_ns > after && p.t_ns < before - 1.0) {
            continue;
        }
        let (dx, dy) = (p.x_px - to.x_px, p.y_px - to.y_px);
        let d2 = dx * dx + dy * dy;
        if d2 <= gate_px * gate_px && best.is_none_or(|(b, _)| d2 < b) {
            best = Some((d2, *p));
        }
    }
    best.map(|(_, p)| p)
}

/// Lagrange weights of three nodes `t` at `x`: `f(x) ≈ Σ w_i f(t_i)`.
fn lagrange3(t: [f64; 3], x: f64) -> [f64; 3] {
    let [a, b, c] = t;
    [
        (x - b) * (x - c) / ((a - b) * (a - c)),
        (x - a) * (x - c) / ((b - a) * (b - c)),
        (x - a) * (x - b) / ((c - a) * (c - b)),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob(x: f64, y: f64) -> Blob {
        Blob {
            x_px: x,
            y_px: y,
            ..Blob::default()
        }
    }

    /// A marker moving on a parabola in the image: x = 100 + 0.2 px/ms·t + 0.001 px/ms²·t².
    fn pos(t_ms: f64) -> (f64, f64) {
        (100.0 + 0.2 * t_ms + 0.001 * t_ms * t_ms, 50.0 - 0.1 * t_ms)
    }

    fn history_at(times_ms: &[f64]) -> BlobHistory {
        let mut h = BlobHistory::new(4);
        for &t in times_ms {
            let (x, y) = pos(t);
            h.push(&[blob(x, y), blob(400.0, 400.0)], |_| t * 1e6);
        }
        h
    }

    #[test]
    fn quadratic_interpolation_is_exact_on_a_parabola() {
        let h = history_at(&[0.0, 8.0]);
        let (x, y) = pos(16.0);
        let now = TimedPoint {
            x_px: x,
            y_px: y,
            t_ns: 16e6,
        };
        let (rx, ry, how) = h.retime(now, 11.5e6, TimeMode::Accurate, 20.0, 20e6, 1e3);
        let (tx, ty) = pos(11.5);
        assert_eq!(how, Retimed::Moved { samples: 3 });
        assert!(
            (rx - tx).abs() < 1e-9 && (ry - ty).abs() < 1e-9,
            "{rx},{ry} vs {tx},{ty}"
        );
    }

    #[test]
    fn low_latency_extrapolates_at_constant_velocity() {
        let h = history_at(&[0.0, 8.0]);
        let (x, y) = pos(16.0);
        let now = TimedPoint {
            x_px: x,
            y_px: y,
            t_ns: 16e6,
        };
        let (rx, _, how) = h.retime(now, 20e6, TimeMode::LowLatency, 20.0, 20e6, 1e3);
        assert_eq!(how, Retimed::Moved { samples: 2 });
        // Velocity over 8..16 ms is 0.2 + 0.001·24 px/ms; 4 ms on from x(16).
        let expected = x + 4.0 * (0.2 + 0.001 * 24.0);
        assert!((rx - expected).abs() < 1e-9);
    }

    #[test]
    fn blobs_without_a_track_are_not_moved_and_not_used_when_far_in_time() {
        let h = history_at(&[0.0, 8.0]);
        // A blob far from every earlier one (just appeared).
        let now = TimedPoint {
            x_px: 300.0,
            y_px: 20.0,
            t_ns: 16e6,
        };
        let (x, _, how) = h.retime(now, 12e6, TimeMode::Accurate, 20.0, 20e6, 1e3);
        assert_eq!((x, how), (300.0, Retimed::Unbridged));
        // Within the as-seen tolerance it is used as seen.
        let (_, _, how) = h.retime(now, 16e6 - 500.0, TimeMode::Accurate, 20.0, 20e6, 1e3);
        assert_eq!(how, Retimed::AsSeen);
        // Beyond the bridgeable span nothing is moved.
        let (x, y) = pos(16.0);
        let tracked = TimedPoint {
            x_px: x,
            y_px: y,
            t_ns: 16e6,
        };
        let (_, _, how) = h.retime(tracked, -10e6, TimeMode::Accurate, 20.0, 20e6, 1e3);
        assert_eq!(how, Retimed::Unbridged);
    }

    #[test]
    fn duplicated_and_stale_frames_are_not_samples() {
        // The previous frame has the current instant (a duplicate): no division by zero, no
        // track; an old history beyond twice the bridge span is ignored too.
        let mut h = BlobHistory::new(2);
        h.push(&[blob(100.0, 50.0)], |_| 16e6);
        let now = TimedPoint {
            x_px: 100.5,
            y_px: 50.0,
            t_ns: 16e6,
        };
        assert_eq!(
            h.retime(now, 12e6, TimeMode::Accurate, 20.0, 20e6, 1e3).2,
            Retimed::Unbridged
        );
        let mut h = BlobHistory::new(2);
        h.push(&[blob(100.0, 50.0)], |_| -100e6);
        assert_eq!(
            h.retime(now, 12e6, TimeMode::Accurate, 20.0, 20e6, 1e3).2,
            Retimed::Unbridged
        );
    }

    #[test]
    fn off_mode_and_synchronous_sets_leave_blobs_untouched() {
        let h = history_at(&[0.0, 8.0]);
        let (x, y) = pos(16.0);
        let now = TimedPoint {
            x_px: x,
            y_px: y,
            t_ns: 16e6,
        };
        assert_eq!(
            h.retime(now, 12e6, TimeMode::Off, 20.0, 20e6, 1e3),
            (x, y, Retimed::AsSeen)
        );
        assert_eq!(
            h.retime(now, 16e6, TimeMode::Accurate, 20.0, 20e6, 0.0),
            (x, y, Retimed::AsSeen)
        );
    }

    #[test]
    fn history_keeps_two_frames_without_growing() {
        let mut h = BlobHistory::new(2);
        for k in 0..5 {
            let t = f64::from(k);
            h.push(&[blob(t, 0.0), blob(t, 1.0), blob(t, 2.0)], |_| t);
        }
        assert_eq!(h.frame(0).len(), 2);
        assert_eq!(h.frame(0)[0].t_ns, 4.0);
        assert_eq!(h.frame(1)[0].t_ns, 3.0);
        assert!(h.frame(2).is_empty());
    }
}
