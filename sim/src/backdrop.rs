//! What real IR cameras see behind the markers: a background level that is not black (ambient
//! IR, sensor offset) with vignetting and extra noise, a textured floor with specular
//! reflections, and a ceiling lamp cut by the frame's top edge (docs/simulator.md).
//!
//! Each part is an option of [`Backdrop`]; a scene is a static map per camera, built once in
//! [`crate::Scenario::new`] and added to every rendered frame (with fresh noise per frame).
//! Values are 8-bit DN; 10-bit frames get them scaled by 1023/255.

use crate::error::SimError;
use crate::noise::{hash_words, unit_from_hash};

/// Realistic background options; all off (level 0, no floor, no lamp) by default.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Backdrop {
    /// Mean background at the frame's centre, 8-bit DN (30–60 is common on real IR cameras).
    pub level_dn: f64,
    /// Extra per-pixel noise, standard deviation in 8-bit DN.
    pub noise_dn: f64,
    /// Fraction of the level lost in the frame's corners (0: none, 0.4: a cheap wide lens).
    pub vignetting: f64,
    /// A textured floor over the lower third of the frame with elongated specular reflections.
    pub floor: bool,
    /// A saturated ceiling lamp cut by the top edge of the frame.
    pub lamp: bool,
}

/// Peak of the brightest floor reflection above the floor, 8-bit DN: bright enough to pass
/// a threshold set just above the background, so it must be rejected for its shape.
pub const REFLECTION_PEAK_DN: f64 = 190.0;

impl Backdrop {
    /// The background seen on real cameras (2026-11-25 recordings): 41 DN at the centre,
    /// ±3 DN extra noise, 35 % vignetting, floor with reflections and a lamp.
    pub fn realistic() -> Self {
        Backdrop {
            level_dn: 41.0,
            noise_dn: 3.0,
            vignetting: 0.35,
            floor: true,
            lamp: true,
        }
    }

    /// Whether this backdrop changes a frame at all.
    pub fn is_active(&self) -> bool {
        self.level_dn > 0.0 || self.noise_dn > 0.0 || self.floor || self.lamp
    }

    /// Checks the values are usable; the error names the backdrop and the problem.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |reason: String| {
            Err(SimError::Config {
                field: "backdrop",
                reason,
            })
        };
        if !(self.level_dn.is_finite() && (0.0..=255.0).contains(&self.level_dn)) {
            return bad(format!("level_dn {} must be in 0..=255", self.level_dn));
        }
        if !(self.noise_dn.is_finite() && (0.0..=64.0).contains(&self.noise_dn)) {
            return bad(format!("noise_dn {} must be in 0..=64", self.noise_dn));
        }
        if !(self.vignetting.is_finite() && (0.0..=1.0).contains(&self.vignetting)) {
            return bad(format!("vignetting {} must be in 0..=1", self.vignetting));
        }
        Ok(())
    }

    /// The static part of camera `camera`'s scene, 8-bit DN per pixel (row-major `w`×`h`).
    /// Cameras see the same kind of scene from other places: texture, reflections and lamp
    /// positions depend on the camera index and `seed`.
    pub fn scene_dn(&self, w: usize, h: usize, camera: usize, seed: u64) -> Vec<f32> {
        let mut out = vec![0f32; w * h];
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let r_corner2 = cx * cx + cy * cy;
        let cam = camera as u64;
        // Level with vignetting (a smooth radial fall-off, ~cos⁴ of a moderate field).
        if self.level_dn > 0.0 {
            for y in 0..h {
                for x in 0..w {
                    let r2 = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / r_corner2.max(1.0);
                    out[y * w + x] = (self.level_dn * (1.0 - self.vignetting * r2)) as f32;
                }
            }
        }
        if self.floor {
            let y0 = (h as f64 * 0.68) as usize;
            // Concrete-like texture: value noise on an 8-px grid, bilinear, ±9 DN, brighter
            // towards the camera (lower rows).
            let cell = 8usize;
            let gw = w / cell + 2;
            let grid: Vec<f64> = (0..(h / cell + 2) * gw)
                .map(|i| unit_from_hash(hash_words(&[seed, cam, 0x0046_6c6f_6f72, i as u64])) * 2.0 - 1.0)
                .collect();
            for y in y0..h {
                let (gy, fy) = (y / cell, (y % cell) as f64 / cell as f64);
                let depth = (y - y0) as f64 / (h - y0).max(1) as f64;
                for x in 0..w {
                    let (gx, fx) = (x / cell, (x % cell) as f64 / cell as f64);
                    let g = |i: usize, j: usize| grid[(gy + j) * gw + gx + i];
                    let v = (g(0, 0) * (1.0 - fx) + g(1, 0) * fx) * (1.0 - fy)
                        + (g(0, 1) * (1.0 - fx) + g(1, 1) * fx) * fy;
                    out[y * w + x] += (6.0 + 8.0 * depth + 9.0 * v) as f32;
                }
            }
            // Specular reflections of the lamp and the machine: long thin streaks on the floor
            // (round spots would be indistinguishable from an LED; real ones are stretched).
            let streaks = [
                (0.22, 0.80, 22.0, 2.2, REFLECTION_PEAK_DN),
                (0.70, 0.88, 24.0, 2.6, 100.0),
                (0.46, 0.93, 16.0, 1.8, 80.0),
            ];
            for (k, (u, v, sx, sy, peak)) in streaks.into_iter().enumerate() {
                let jitter = unit_from_hash(hash_words(&[seed, cam, 0x5374_7265_616b, k as u64])) - 0.5;
                let u = (u + 0.1 * jitter) * w as f64;
                let v = v * h as f64;
                add_gaussian(&mut out, w, h, u, v, sx, sy, peak);
            }
        }
        if self.lamp {
            // A saturated disk whose centre is just above the frame: only its lower part shows,
            // touching the top edge, with a soft glow around it.
            let jitter = unit_from_hash(hash_words(&[seed, cam, 0x4c61_6d70])) - 0.5;
            let u = (0.78 + 0.08 * jitter) * w as f64;
            let v = -4.0;
            let radius = 0.025 * w as f64;
            let glow = 0.3 * radius;
            for y in 0..((v + radius + 4.0 * glow).max(0.0) as usize).min(h) {
                for x in 0..w {
                    let d = ((x as f64 - u).powi(2) + (y as f64 - v).powi(2)).sqrt();
                    let add = if d <= radius {
                        400.0
                    } else {
                        150.0 * (-(d - radius).powi(2) / (2.0 * glow * glow)).exp()
                    };
                    out[y * w + x] += add as f32;
                }
            }
        }
        out
    }
}

#[allow(clippy::too_many_arguments)]
fn add_gaussian(out: &mut [f32], w: usize, h: usize, u: f64, v: f64, sx: f64, sy: f64, peak: f64) {
    let (x0, x1) = (
        (u - 4.0 * sx).max(0.0) as usize,
        ((u + 4.0 * sx) as usize + 1).min(w),
    );
    let (y0, y1) = (
        (v - 4.0 * sy).max(0.0) as usize,
        ((v + 4.0 * sy) as usize + 1).min(h),
    );
    for y in y0..y1 {
        let gy = (-(y as f64 - v).powi(2) / (2.0 * sy * sy)).exp();
        for x in x0..x1 {
            let gx = (-(x as f64 - u).powi(2) / (2.0 * sx * sx)).exp();
            out[y * w + x] += (peak * gx * gy) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_falls_off_towards_the_corners() {
        let b = Backdrop {
            level_dn: 40.0,
            vignetting: 0.4,
            ..Backdrop::default()
        };
        let m = b.scene_dn(64, 48, 0, 1);
        let centre = m[24 * 64 + 32];
        assert!((centre - 40.0).abs() < 0.5, "centre {centre}");
        assert!((m[0] - 24.0).abs() < 0.5, "corner {}", m[0]);
    }

    #[test]
    fn lamp_touches_the_top_edge_and_reflections_are_long() {
        let b = Backdrop {
            floor: true,
            lamp: true,
            ..Backdrop::default()
        };
        let (w, h) = (640, 480);
        let m = b.scene_dn(w, h, 0, 1);
        assert!(m[..w].iter().any(|v| *v >= 255.0), "no saturated lamp on row 0");
        // The brightest reflection is a horizontal streak well inside the floor.
        let floor_max = m[(h * 3 / 4) * w..].iter().copied().fold(0f32, f32::max);
        assert!(floor_max > 150.0, "floor max {floor_max}");
        let other = b.scene_dn(w, h, 1, 1);
        assert_ne!(m, other, "cameras should see different scenes");
    }
}
