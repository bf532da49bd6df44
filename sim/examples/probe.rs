use irtrack_core::image::GrayImage;
use irtrack_core::pipeline::{Tracker, TrackerConfig};
use irtrack_sim::*;
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let psf: f64 = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(0.9);
    for &d in &[659.84, 1500.0, 2309.44] {
        for conv in [true, false] {
            let rig = if conv { RigPreset::Convergent { distance_mm: d, angle_deg: 90.0 } } else { RigPreset::Parallel { baseline_mm: 50.0 } };
            let mut cfg = SimConfig::preset(rig, d, 0.08 * d);
            let m = MarkerSpec { psf_sigma_px: psf, ..MarkerSpec::default() };
            let flux = m.flux_for_peak(0.6, cfg.sensor.full_well_e, d, cfg.camera.focal_px);
            cfg.markers = vec![MarkerSpec { flux_e_at_1m: flux, ..m }];
            cfg.motion_blur_steps = 4;
            let mut sc = Scenario::new(cfg).unwrap();
            let (w, h) = sc.image_size();
            let mut bufs = vec![vec![0u8; (w * h) as usize]; 2];
            let mut tr = Tracker::new(sc.rig(), TrackerConfig::default()).unwrap();
            let mut errs = vec![];
            let mut axes = [0.0f64; 3];
            for i in 0..240 {
                for c in 0..2 { sc.render_u8(i, c, &mut bufs[c]).unwrap(); }
                let imgs: Vec<_> = bufs.iter().map(|b| GrayImage::new(b, w, h, w).unwrap()).collect();
                let m = tr.process_u8(&imgs).unwrap();
                if let Some(p) = m.point_cam0_mm {
                    let e = p - sc.truth(i).markers()[0].p_cam0_mm;
                    for k in 0..3 { axes[k] += e[k] * e[k]; }
                    errs.push(e.norm());
                }
            }
            errs.sort_by(f64::total_cmp);
            let n = errs.len() as f64;
            let rms = (errs.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
            println!("conv={conv} d={d} n={} rms={rms:.4} p95={:.4} axes_rms={:.4?}", errs.len(), errs[(0.95 * n) as usize - 1], axes.map(|a| (a / n).sqrt()));
        }
    }
}
