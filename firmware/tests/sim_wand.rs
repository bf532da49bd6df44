//! The simulated source's wand mode (`[source.sim] wand_mm = [...]`): irtrackd serves a wand
//! wave, so `host-tools capture --wand` and `wand-calibrate` can be tried end to end without
//! hardware. Its frames are the simulator's wand renderer's, frame for frame.

use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::source::{FrameSource, Pixels};
use irtrack_sim::wand::{WandConfig, WandWave};

fn wand_cfg(bit_depth: u8) -> SimSourceConfig {
    SimSourceConfig {
        paced: false,
        distance_mm: 1200.0,
        bit_depth,
        wand_mm: Some(vec![0.0, 120.0, 300.0]),
        wand_frames: 50,
        ..SimSourceConfig::default()
    }
}

fn u8_pixels(p: &Pixels) -> &[u8] {
    match p {
        Pixels::U8(v) => v,
        Pixels::U16(_) => panic!("expected 8-bit pixels"),
    }
}

#[test]
fn wand_frames_are_the_wand_renderers_and_the_wave_repeats() {
    let cfg = wand_cfg(8);
    cfg.validate().unwrap();
    let mut src = SimSource::new(&cfg).unwrap();
    // The same wave, built the way the source documents it.
    let rig = src.scenario().rig().clone();
    let centre = cfg.scenario_config().rig.workspace_centre_mm(cfg.distance_mm);
    let wcfg = WandConfig::new(rig, centre, 50); // at 1.2 m the default sweep is kept
    let mut wave = WandWave::new(wcfg).unwrap();

    let mut set = src.allocate_set();
    let mut expected = vec![0u8; set.frames[0].width_px as usize * set.frames[0].height_px as usize];
    let mut spots_seen = 0;
    for index in 0..55u64 {
        src.next_set(&mut set).unwrap();
        assert_eq!(set.index, index);
        for (camera, frame) in set.frames.iter().enumerate() {
            let truth = wave.render((index % 50) as usize, camera, &mut expected).unwrap();
            assert!(
                u8_pixels(&frame.pixels) == expected.as_slice(),
                "set {index} camera {camera} differs from the wand renderer"
            );
            // The LEDs are really there: the pixel nearest each visible LED is bright.
            for px in truth.leds_px.iter().flatten() {
                let (x, y) = (px.x.round() as usize, px.y.round() as usize);
                let v = u8_pixels(&frame.pixels)[y * frame.width_px as usize + x];
                assert!(
                    v > 60,
                    "LED at {px:?} in camera {camera}, set {index}: only {v} DN"
                );
                spots_seen += 1;
            }
        }
    }
    // Three LEDs, two cameras, 55 sets, a few hidden or out of view.
    assert!(spots_seen > 250, "only {spots_seen} LED spots in view");
}

#[test]
fn ten_bit_wand_frames_are_the_eight_bit_ones_shifted() {
    let mut s8 = SimSource::new(&wand_cfg(8)).unwrap();
    let mut s10 = SimSource::new(&wand_cfg(10)).unwrap();
    let (mut a, mut b) = (s8.allocate_set(), s10.allocate_set());
    for _ in 0..3 {
        s8.next_set(&mut a).unwrap();
        s10.next_set(&mut b).unwrap();
    }
    let Pixels::U16(ten) = &b.frames[1].pixels else {
        panic!("expected 10-bit pixels")
    };
    let eight = u8_pixels(&a.frames[1].pixels);
    assert!(ten.iter().zip(eight).all(|(t, e)| *t == u16::from(*e) << 2));
    assert!(ten.iter().any(|t| *t > 400), "no LED in the 10-bit frame");
}

#[test]
fn bad_wand_settings_are_named() {
    let mut cfg = wand_cfg(8);
    cfg.wand_mm = Some(vec![0.0, 120.0]);
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("source.sim.wand_mm") && e.contains("3 or more"), "{e}");

    let mut cfg = wand_cfg(8);
    cfg.wand_mm = Some(vec![0.0, 300.0, 120.0]);
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("increasing"), "{e}");

    let mut cfg = wand_cfg(8);
    cfg.tool = Some("probe4".into());
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("exclude each other"), "{e}");

    let mut cfg = wand_cfg(8);
    cfg.wand_frames = 3;
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("wand_frames"), "{e}");
}
