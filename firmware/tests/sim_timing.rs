//! The simulated source's per-camera timing (`[source.sim.timing]`, issue 39): each camera's
//! frames carry the timestamp that camera would give, the set's pairing error is their
//! spread, and the pixels are the simulator's render of that camera's own exposure.

use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::source::{FrameSource, Pixels};
use irtrack_sim::Scenario;

fn timed_cfg(timing: &str) -> SimSourceConfig {
    toml::from_str(&format!(
        r#"
paced = false
rig = "ring"
ring_cameras = 4
distance_mm = 1400.0
frames = 40
[timing]
{timing}
"#
    ))
    .unwrap()
}

#[test]
fn each_camera_stamps_its_own_exposure_and_the_pairing_error_is_their_spread() {
    let cfg = timed_cfg(
        "phase_ms = [0.0, 3.1, -2.4, 3.9]\nppm = [0.0, 30.0, -45.0, 12.0]\nts_jitter_us = 200.0\nline_time_us = 15.0",
    );
    cfg.validate().unwrap();
    let mut src = SimSource::new(&cfg).unwrap();
    // The same scenario, for the expected timestamps and pixels.
    let mut reference = Scenario::new(cfg.scenario_config()).unwrap();
    let mut set = src.allocate_set();
    let (w, h) = reference.image_size();
    let mut expected = vec![0u8; (w * h) as usize];
    for _ in 0..40 {
        src.next_set(&mut set).unwrap();
        let k = set.index;
        let nominal = reference.timestamp_ns(k) as i64;
        let base = set.frames[0].timestamp_ns as i64 - (reference.frame_time(k, 0).reported_ns - nominal);
        let mut skews = Vec::new();
        for (c, frame) in set.frames.iter().enumerate() {
            let skew = reference.frame_time(k, c).reported_ns - nominal;
            assert_eq!(frame.timestamp_ns as i64 - base, skew, "set {k} camera {c}");
            skews.push(skew);
            reference.render_u8(k, c, &mut expected).unwrap();
            let Pixels::U8(px) = &frame.pixels else {
                panic!("8-bit expected")
            };
            assert!(px == &expected, "set {k} camera {c}: not the timed render");
        }
        let spread = skews.iter().max().unwrap() - skews.iter().min().unwrap();
        assert_eq!(set.pairing_error_ns, spread as u64);
        // 3.9 − (−2.4) ms of phase, within 3σ of jitter each side.
        assert!((spread - 6_300_000).abs() < 1_300_000, "spread {spread}");
    }
}

#[test]
fn free_running_preset_and_bad_tables_are_named() {
    let cfg = timed_cfg("preset = \"free_running\"");
    cfg.validate().unwrap();
    let sc = cfg.scenario_config();
    assert_eq!(sc.timing.len(), 4);
    assert!(
        sc.timing
            .iter()
            .all(|t| t.ts_jitter_ns == 200_000.0 && t.rate_ppm.abs() <= 50.0)
    );
    let phases: Vec<f64> = sc.timing.iter().map(|t| t.phase_ns).collect();
    let period = 1e9 / cfg.fps;
    assert!((phases[2] - period / 2.0).abs() < 1.0, "{phases:?}");

    // The constants the tracker is given: a rolling shutter and the negated timestamp offset.
    let rolling = timed_cfg("line_time_us = 15.0\nts_offset_us = [0.0, 250.0, 0.0, 0.0]");
    let ct = rolling.camera_timings();
    assert_eq!(ct.len(), 4);
    assert_eq!(ct[1].shutter, irtrack_core::timing::Shutter::Rolling);
    assert_eq!((ct[1].line_time_ns, ct[1].offset_ns), (15_000, -250_000));
    assert!(
        SimSourceConfig::default()
            .camera_timings()
            .iter()
            .all(|t| *t == irtrack_core::timing::CameraTiming::SYNCHRONOUS)
    );

    let wrong = timed_cfg("phase_ms = [0.0, 1.0]");
    let e = wrong.validate().unwrap_err().to_string();
    assert!(
        e.contains("source.sim.timing") && e.contains("2 values for 4 cameras"),
        "{e}"
    );
    let preset = timed_cfg("preset = \"sync\"");
    assert!(
        preset
            .validate()
            .unwrap_err()
            .to_string()
            .contains("free_running")
    );
    let mut wand = timed_cfg("ppm = 10.0");
    wand.wand_mm = Some(vec![0.0, 120.0, 300.0]);
    assert!(wand.validate().unwrap_err().to_string().contains("wand"));
    let unknown: Result<SimSourceConfig, _> = toml::from_str("[timing]\nphase = 1.0\n");
    assert!(unknown.is_err(), "unknown keys are refused");
}

/// Replay keeps each camera's recorded timestamp: the skew between the frames of one set, at
/// recorded and at maximum speed, from the very first set on.
#[test]
fn replay_keeps_each_cameras_recorded_skew() {
    use irtrack_firmware::source::replay::{ReplayConfig, ReplaySource, ReplaySpeed};
    let dir = std::env::temp_dir().join(format!("irtrack-replay-skew-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let pgm = irtrack_core::pgm::encode_u8(4, 4, &[7u8; 16]).unwrap();
    // Camera 1 3.1 ms after camera 0, which jitters by ±0.2 ms; 10 ms frames.
    let stamps: [[u64; 2]; 3] = [
        [1_000_000_000, 1_003_100_000],
        [1_010_200_000, 1_013_100_000],
        [1_019_800_000, 1_023_100_000],
    ];
    let mut csv = String::from("frame,camera,timestamp_ns,dropped\n");
    for (f, s) in stamps.iter().enumerate() {
        for (c, ts) in s.iter().enumerate() {
            std::fs::create_dir_all(dir.join(format!("cam{c}"))).unwrap();
            std::fs::write(dir.join(format!("cam{c}/{f:06}.pgm")), &pgm).unwrap();
            csv += &format!("{f},{c},{ts},0\n");
        }
    }
    std::fs::write(dir.join("timestamps.csv"), csv).unwrap();
    for speed in [ReplaySpeed::Recorded, ReplaySpeed::Max] {
        let mut src = ReplaySource::open(&ReplayConfig {
            dir: dir.clone(),
            speed,
            repeat: false,
            fps: None,
            ..Default::default()
        })
        .unwrap();
        let mut set = src.allocate_set();
        let mut first = None;
        for s in &stamps {
            src.next_set(&mut set).unwrap();
            let (a, b) = (set.frames[0].timestamp_ns, set.frames[1].timestamp_ns);
            assert_eq!(b - a, s[1] - s[0], "{speed:?}");
            assert_eq!(set.pairing_error_ns, s[1] - s[0]);
            let f = *first.get_or_insert(a);
            if speed == ReplaySpeed::Recorded {
                assert_eq!(a - f, s[0] - stamps[0][0], "recorded intervals kept");
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
