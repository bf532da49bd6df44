//! Path conditioning for teach-in: One-Euro low-pass filter, 3-D Ramer-Douglas-Peucker
//! simplification and arc-length resampling.
//!
//! The One-Euro filter (Casiez et al., CHI 2012) adapts its cut-off to speed: slow hand motion is
//! smoothed strongly (jitter removed), fast motion lightly (little lag).

use alloc::vec::Vec;
use core::f64::consts::PI;

use crate::error::{Error, Result};

/// One-Euro parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OneEuroConfig {
    /// Cut-off at zero speed.
    pub min_cutoff_hz: f64,
    /// How fast the cut-off rises with speed (per mm/s).
    pub beta: f64,
    /// Cut-off of the speed estimate.
    pub d_cutoff_hz: f64,
}

impl Default for OneEuroConfig {
    fn default() -> Self {
        Self {
            min_cutoff_hz: 1.0,
            beta: 0.01,
            d_cutoff_hz: 1.0,
        }
    }
}

impl OneEuroConfig {
    fn validate(&self) -> Result<()> {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        let beta_ok = self.beta.is_finite() && self.beta >= 0.0;
        if !(ok(self.min_cutoff_hz) && ok(self.d_cutoff_hz) && beta_ok) {
            return Err(Error::InvalidParams {
                reason: alloc::format!("One-Euro parameters must be positive: {self:?}"),
            });
        }
        Ok(())
    }
}

fn alpha(cutoff_hz: f64, dt_s: f64) -> f64 {
    let tau = 1.0 / (2.0 * PI * cutoff_hz);
    1.0 / (1.0 + tau / dt_s)
}

/// One-Euro filter for 3-D points (one speed estimate from the vector norm).
#[derive(Debug, Clone)]
pub struct OneEuro3 {
    cfg: OneEuroConfig,
    prev: Option<(f64, [f64; 3], [f64; 3])>,
}

impl OneEuro3 {
    /// A new filter; parameters are validated.
    pub fn new(cfg: OneEuroConfig) -> Result<Self> {
        cfg.validate()?;
        Ok(Self { cfg, prev: None })
    }

    /// Forgets the state (e.g. after a tracking gap).
    pub fn reset(&mut self) {
        self.prev = None;
    }

    /// Filters one sample at time `t_s`; timestamps must increase (equal ones return the last output).
    pub fn filter(&mut self, t_s: f64, x_mm: [f64; 3]) -> [f64; 3] {
        let Some((t0, x0, dx0)) = self.prev else {
            self.prev = Some((t_s, x_mm, [0.0; 3]));
            return x_mm;
        };
        let dt = t_s - t0;
        if dt <= 0.0 || !dt.is_finite() {
            return x0;
        }
        let ad = alpha(self.cfg.d_cutoff_hz, dt);
        let mut dx = [0.0; 3];
        for i in 0..3 {
            dx[i] = ad * (x_mm[i] - x0[i]) / dt + (1.0 - ad) * dx0[i];
        }
        let speed = libm::sqrt(dx.iter().map(|v| v * v).sum::<f64>());
        let a = alpha(self.cfg.min_cutoff_hz + self.cfg.beta * speed, dt);
        let mut x = [0.0; 3];
        for i in 0..3 {
            x[i] = a * x_mm[i] + (1.0 - a) * x0[i];
        }
        self.prev = Some((t_s, x, dx));
        x
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
/// Euclidean distance.
pub fn dist_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    let d = sub(a, b);
    libm::sqrt(dot(d, d))
}

/// Distance of `p` from the segment `a`–`b`.
pub fn point_segment_dist_mm(p: [f64; 3], a: [f64; 3], b: [f64; 3]) -> f64 {
    let ab = sub(b, a);
    let len2 = dot(ab, ab);
    if len2 == 0.0 {
        return dist_mm(p, a);
    }
    let t = (dot(sub(p, a), ab) / len2).clamp(0.0, 1.0);
    dist_mm(p, [a[0] + t * ab[0], a[1] + t * ab[1], a[2] + t * ab[2]])
}

/// Ramer-Douglas-Peucker in 3-D: indices of the points kept (first and last always), such that
/// every dropped point lies within `tol_mm` of the simplified polyline. Iterative (no recursion
/// depth limit on long paths).
pub fn rdp_indices(points: &[[f64; 3]], tol_mm: f64) -> Result<Vec<usize>> {
    if !(tol_mm.is_finite() && tol_mm >= 0.0) {
        return Err(Error::InvalidParams {
            reason: alloc::format!("RDP tolerance {tol_mm} mm"),
        });
    }
    let n = points.len();
    if n <= 2 {
        return Ok((0..n).collect());
    }
    let mut keep = alloc::vec![false; n];
    keep[0] = true;
    keep[n - 1] = true;
    let mut stack = alloc::vec![(0usize, n - 1)];
    while let Some((a, b)) = stack.pop() {
        let (mut worst, mut worst_d) = (0, -1.0);
        for i in a + 1..b {
            let d = point_segment_dist_mm(points[i], points[a], points[b]);
            if d > worst_d {
                worst = i;
                worst_d = d;
            }
        }
        if worst_d > tol_mm {
            keep[worst] = true;
            stack.push((a, worst));
            stack.push((worst, b));
        }
    }
    Ok(keep
        .iter()
        .enumerate()
        .filter_map(|(i, k)| k.then_some(i))
        .collect())
}

/// Resamples a polyline at equal arc-length spacing `step_mm` (last point always included).
pub fn resample(points: &[[f64; 3]], step_mm: f64) -> Result<Vec<[f64; 3]>> {
    if !(step_mm.is_finite() && step_mm > 0.0) {
        return Err(Error::InvalidParams {
            reason: alloc::format!("resample step {step_mm} mm"),
        });
    }
    let Some(&first) = points.first() else {
        return Ok(Vec::new());
    };
    let mut out = alloc::vec![first];
    // Distance already travelled past the last emitted sample.
    let mut carry = 0.0;
    for w in points.windows(2) {
        let (a, b) = (w[0], w[1]);
        let seg = dist_mm(a, b);
        if seg == 0.0 {
            continue;
        }
        let mut s = step_mm - carry;
        while s <= seg {
            let t = s / seg;
            out.push([
                a[0] + t * (b[0] - a[0]),
                a[1] + t * (b[1] - a[1]),
                a[2] + t * (b[2] - a[2]),
            ]);
            s += step_mm;
        }
        carry = seg - (s - step_mm);
    }
    if let (Some(&last), Some(&end)) = (out.last(), points.last())
        && dist_mm(last, end) > 1e-9
    {
        out.push(end);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_euro_removes_jitter_on_still_marker() {
        let mut f = OneEuro3::new(OneEuroConfig {
            min_cutoff_hz: 0.5,
            beta: 0.0,
            d_cutoff_hz: 1.0,
        })
        .unwrap();
        let mut worst: f64 = 0.0;
        for i in 0..600 {
            // ±0.5 mm alternating jitter at 60 Hz around (10, 20, 30).
            let j = if i % 2 == 0 { 0.5 } else { -0.5 };
            let y = f.filter(i as f64 / 60.0, [10.0 + j, 20.0 - j, 30.0]);
            if i > 100 {
                worst = worst.max(dist_mm(y, [10.0, 20.0, 30.0]));
            }
        }
        assert!(worst < 0.05, "residual jitter {worst} mm");
    }

    #[test]
    fn one_euro_beta_reduces_lag_on_fast_motion() {
        let lag = |beta: f64| {
            let mut f = OneEuro3::new(OneEuroConfig {
                min_cutoff_hz: 0.5,
                beta,
                d_cutoff_hz: 1.0,
            })
            .unwrap();
            let mut last = 0.0;
            for i in 0..120 {
                let t = i as f64 / 60.0;
                let y = f.filter(t, [200.0 * t, 0.0, 0.0]);
                last = 200.0 * t - y[0];
            }
            last
        };
        let (slow, fast) = (lag(0.0), lag(0.05));
        assert!(fast < 0.3 * slow, "lag beta=0: {slow} mm, beta=0.05: {fast} mm");
        assert!(
            OneEuro3::new(OneEuroConfig {
                min_cutoff_hz: -1.0,
                ..Default::default()
            })
            .is_err()
        );
    }

    #[test]
    fn rdp_keeps_corners_and_respects_tolerance() {
        // An L with small noise on each leg.
        let mut pts = Vec::new();
        for i in 0..=100 {
            pts.push([i as f64, if i % 2 == 0 { 0.1 } else { -0.1 }, 0.0]);
        }
        for i in 1..=100 {
            pts.push([100.0, i as f64, if i % 3 == 0 { 0.1 } else { 0.0 }]);
        }
        let keep = rdp_indices(&pts, 0.5).unwrap();
        assert_eq!(keep, alloc::vec![0, 100, 200]);
        let simp: Vec<_> = keep.iter().map(|&i| pts[i]).collect();
        for p in &pts {
            let d = simp
                .windows(2)
                .map(|w| point_segment_dist_mm(*p, w[0], w[1]))
                .fold(f64::MAX, f64::min);
            assert!(d <= 0.5);
        }
        // A tighter tolerance keeps more points.
        assert!(rdp_indices(&pts, 0.05).unwrap().len() > 3);
    }

    #[test]
    fn resample_spacing_is_uniform() {
        let pts = [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 7.0, 0.0]];
        let r = resample(&pts, 2.0).unwrap();
        // 17 mm of path: samples at 0,2,..,16 plus the end point.
        assert_eq!(r.len(), 10);
        assert!(dist_mm(r[5], [10.0, 0.0, 0.0]) < 1e-9);
        assert!(dist_mm(r[6], [10.0, 2.0, 0.0]) < 1e-9);
        assert_eq!(*r.last().unwrap(), [10.0, 7.0, 0.0]);
        assert!(resample(&pts, 0.0).is_err());
    }
}
