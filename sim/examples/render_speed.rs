//! Measures render time per frame (run with `--release`): VGA, two cameras, both bit depths.

use std::time::Instant;

use irtrack_sim::{RigPreset, Scenario, SimConfig};

fn main() -> Result<(), irtrack_sim::SimError> {
    for (name, blur) in [("no blur", 1), ("motion blur x8", 8)] {
        let mut cfg = SimConfig::preset(
            RigPreset::Convergent {
                distance_mm: 659.84,
                angle_deg: 90.0,
            },
            659.84,
            100.0,
        );
        cfg.add_glare();
        cfg.motion_blur_steps = blur;
        let mut sc = Scenario::new(cfg)?;
        let (w, h) = sc.image_size();
        let mut f8 = vec![0u8; (w * h) as usize];
        let mut f16 = vec![0u16; (w * h) as usize];
        let n = 600u64;
        let t0 = Instant::now();
        for i in 0..n {
            for cam in 0..sc.camera_count() {
                sc.render_u8(i, cam, &mut f8)?;
            }
        }
        let per8 = t0.elapsed().as_secs_f64() / (n as f64 * 2.0);
        let t0 = Instant::now();
        for i in 0..n {
            for cam in 0..sc.camera_count() {
                sc.render_u16(i, cam, &mut f16)?;
            }
        }
        let per16 = t0.elapsed().as_secs_f64() / (n as f64 * 2.0);
        println!(
            "{name}: {:.3} ms per 8-bit VGA frame, {:.3} ms per 10-bit frame; 2 cameras at 120 fps need < 4.17 ms",
            per8 * 1e3,
            per16 * 1e3
        );
    }
    Ok(())
}
