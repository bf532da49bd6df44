//! The whole-frame analysis and the threshold suggestion on the simulator's realistic scene
//! (`[source.sim.backdrop]`: background 41 DN with noise and vignetting, a textured floor with
//! reflections, a lamp cut by the top edge): the default threshold is reported as a background
//! problem in plain words, never as an area problem, and the suggested threshold keeps exactly
//! the marker in every camera while the lamp and the reflections are marked rejected.

use irtrack_core::pipeline::TrackerConfig;
use irtrack_firmware::advice::{CameraAnalysis, suggest};
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimBackdropConfig, SimSource, SimSourceConfig};
use irtrack_firmware::viewer::RejectReason;

fn realistic_set() -> irtrack_firmware::source::FrameSet {
    let cfg = SimSourceConfig {
        paced: false,
        backdrop: Some(SimBackdropConfig::default()),
        ..SimSourceConfig::default()
    };
    let mut src = SimSource::new(&cfg).unwrap();
    let mut set = src.allocate_set();
    src.next_set(&mut set).unwrap();
    set
}

#[test]
fn default_threshold_on_a_bright_background_is_reported_as_such() {
    let set = realistic_set();
    let cfg = TrackerConfig::default();
    for (i, f) in set.frames.iter().enumerate() {
        let a = CameraAnalysis::of(i, set.index, f, &cfg, None, 32).unwrap();
        let adv = a.advice.clone().expect("advice for a bright background");
        assert!(a.pixels);
        let bg = a.background.expect("pixel figures from a frame");
        println!(
            "camera {i}: background {} DN (noise {:.1}, 98 % level {} DN), {:.0} % above {} DN: {}",
            bg.median_dn, bg.noise_dn, bg.bright_dn, a.above_threshold_pct, cfg.threshold_dn, adv.message
        );
        assert_eq!(adv.code, "background_above_threshold");
        let prefix = format!(
            "camera {i}: background {} DN is above the threshold 30 DN — raise it to about ",
            bg.median_dn
        );
        assert!(adv.message.starts_with(&prefix), "{}", adv.message);
        assert!((35..=50).contains(&bg.median_dn), "{a:?}");
        assert!(a.above_threshold_pct > 50.0);
        assert!(!adv.message.contains("area"), "{}", adv.message);
    }
}

#[test]
fn suggested_threshold_keeps_exactly_the_marker_and_marks_the_rest() {
    let set = realistic_set();
    let cfg = TrackerConfig::default();
    let s = suggest(set.index, &set.frames, &cfg);
    for c in &s.cameras {
        for r in &c.reasoning {
            println!("camera {}: {r}", c.camera);
        }
    }
    for r in s.reasoning.iter().chain(&s.predicted) {
        println!("{r}");
    }
    let v = s.threshold_dn.expect("a threshold");
    assert!(s.keeps_only_marker, "{s:#?}");
    assert!(v > 60 && v < 255, "{v}");
    let mut at = cfg;
    at.threshold_dn = v;
    let mut reasons = Vec::new();
    for (i, f) in set.frames.iter().enumerate() {
        let a = CameraAnalysis::of(i, set.index, f, &at, None, 32).unwrap();
        assert_eq!(a.kept, 1, "camera {i} at {v} DN: {a:#?}");
        assert_eq!(a.advice, None, "camera {i}");
        reasons.extend(a.blobs.iter().filter_map(|b| b.reason));
    }
    // The lamp is cut by the top edge; the brightest reflection is a streak.
    assert!(reasons.contains(&RejectReason::Edge), "{reasons:?}");
    assert!(reasons.contains(&RejectReason::Roundness), "{reasons:?}");
}
