//! Replay source: reads a recorded directory (PGM frames + timestamps.csv) and the loop turns it
//! into positions matching the simulator's truth.

mod common;

use std::fmt::Write as _;
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use irtrack_firmware::source::replay::{ReplayConfig, ReplaySource, ReplaySpeed};
use irtrack_firmware::source::{Frame, FrameSource, Pixels};
use irtrack_firmware::status::SharedStatus;

const FRAMES: u64 = 12;
const DROPPED_FRAME: u64 = 5;

/// Records `FRAMES` frames of the test scenario; camera 1 drops frame `DROPPED_FRAME`.
fn record(dir: &std::path::Path) -> irtrack_sim::Scenario {
    let mut sc = scenario(&sim_cfg());
    let (w, h) = sc.image_size();
    let mut csv = String::from("frame,camera,timestamp_ns,dropped\n");
    for c in 0..sc.camera_count() {
        std::fs::create_dir_all(dir.join(format!("cam{c}"))).unwrap();
    }
    for f in 0..FRAMES {
        for c in 0..sc.camera_count() {
            let mut px = vec![0u8; (w * h) as usize];
            let info = sc.render_u8(f, c, &mut px).unwrap();
            let dropped = f == DROPPED_FRAME && c == 1;
            writeln!(
                csv,
                "{f},{c},{},{}",
                info.timestamp_ns + 1_000_000_000,
                u8::from(dropped)
            )
            .unwrap();
            if dropped {
                continue;
            }
            let frame = Frame {
                width_px: w,
                height_px: h,
                stride_px: w,
                bit_depth: 8,
                pixels: Pixels::U8(px),
                timestamp_ns: 0,
                sequence: f,
            };
            std::fs::write(
                dir.join(format!("cam{c}/{f:06}.pgm")),
                irtrack_core::pgm::encode(&frame.image()).unwrap(),
            )
            .unwrap();
        }
    }
    std::fs::write(dir.join("timestamps.csv"), csv).unwrap();
    sc
}

#[test]
fn replay_directory_gives_positions_matching_truth() {
    let dir = TempDir::new("replay");
    let sc = record(dir.path());
    let cfg = ReplayConfig {
        dir: dir.path().to_path_buf(),
        speed: ReplaySpeed::Max,
        repeat: false,
        fps: None,
        ..Default::default()
    };
    let source = ReplaySource::open(&cfg).unwrap();
    assert_eq!(source.camera_count(), 2);
    assert_eq!(
        source.len() as u64,
        FRAMES - 1,
        "the dropped frame's set is skipped"
    );

    let handle = Arc::new(ParamsHandle::new());
    let rig = sc.rig().clone();
    let crc = irtrack_core::params::BlobHeader::parse(&rig.to_blob().unwrap())
        .unwrap()
        .crc32;
    handle.install(ActiveParams { rig, crc });
    let status = Arc::new(SharedStatus::new(2, source.describe(), "none".into()));
    status
        .params_loaded
        .store(false, std::sync::atomic::Ordering::Relaxed);
    let (tx, rx) = tokio::sync::watch::channel(None);
    let mut engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        handle,
        tx,
        status.clone(),
        Duration::from_millis(10),
    );
    let mut frames = Vec::new();
    loop {
        match engine.step().unwrap() {
            StepOutcome::Published(r) => {
                assert_eq!(r.status, TrackStatus::Ok, "frame {}", r.frame);
                let t = sc.truth(r.frame).markers()[0].p_cam0_mm;
                let e = dist_mm(r.position_mm.unwrap(), [t.x, t.y, t.z]);
                assert!(e < 1.0, "frame {}: error {e} mm", r.frame);
                assert_eq!(r.params_crc, crc);
                frames.push(r.frame);
            }
            StepOutcome::EndOfStream => break,
            StepOutcome::SourceError => panic!("source error"),
        }
    }
    let expected: Vec<u64> = (0..FRAMES).filter(|&f| f != DROPPED_FRAME).collect();
    assert_eq!(frames, expected);
    assert_eq!(rx.borrow().unwrap().frame, FRAMES - 1);
    assert_eq!(status.report().source.sets_dropped, 1);
}

#[test]
fn replay_at_recorded_speed_keeps_intervals_and_reports_bad_files() {
    let dir = TempDir::new("replay-speed");
    record(dir.path());
    let cfg = ReplayConfig {
        dir: dir.path().to_path_buf(),
        speed: ReplaySpeed::Recorded,
        repeat: false,
        fps: None,
        ..Default::default()
    };
    let mut source = ReplaySource::open(&cfg).unwrap();
    let mut set = source.allocate_set();
    let t0 = Instant::now();
    let mut stamps = Vec::new();
    for _ in 0..4 {
        source.next_set(&mut set).unwrap();
        stamps.push(set.frames[0].timestamp_ns);
        assert_eq!(set.pairing_error_ns, 0);
    }
    // Frames are 10 ms apart (100 fps): three intervals take at least 30 ms.
    assert!(t0.elapsed() >= Duration::from_millis(29), "{:?}", t0.elapsed());
    let intervals: Vec<u64> = stamps.windows(2).map(|w| w[1] - w[0]).collect();
    assert!(intervals.iter().all(|&i| i == 10_000_000), "{intervals:?}");
    // The loop's deadline follows the recording's rate (100 fps: 10 ms), not the 30 fps of a
    // replay without one.
    let fps = source.nominal_fps().unwrap();
    assert!((fps - 100.0).abs() < 1e-6, "{fps}");
    assert_eq!(
        irtrack_firmware::app::deadline_at(&Default::default(), source.nominal_fps()),
        Duration::from_millis(10)
    );

    // A truncated frame file is reported with its path.
    std::fs::write(dir.path().join("cam0/000004.pgm"), b"P5\n640 480\n255\n").unwrap();
    let err = source.next_set(&mut set).unwrap_err().to_string();
    assert!(
        err.contains("000004.pgm") && err.contains("bytes, header needs"),
        "{err}"
    );

    // No cam0/ directory at all.
    let empty = TempDir::new("replay-empty");
    let cfg = ReplayConfig {
        dir: empty.path().to_path_buf(),
        speed: ReplaySpeed::Max,
        repeat: false,
        fps: None,
        ..Default::default()
    };
    let err = ReplaySource::open(&cfg).err().unwrap().to_string();
    assert!(err.contains("has no cam0/"), "{err}");
}

/// Without timestamps.csv and without `[source.replay] fps` the recording is paced at the
/// stated default rate (said in the description), every set is processed, and the end says
/// how many of how many were delivered.
#[test]
fn replay_without_timestamps_paces_at_the_default_rate_and_says_why_it_ended() {
    use irtrack_firmware::source::replay::{DEFAULT_REPLAY_FPS, ReplayTiming};
    let dir = TempDir::new("replay-no-ts");
    record(dir.path());
    std::fs::remove_file(dir.path().join("timestamps.csv")).unwrap();
    // cam1 has no frame DROPPED_FRAME: that set is unreadable and skipped with a reason.
    let cfg = ReplayConfig {
        dir: dir.path().to_path_buf(),
        speed: ReplaySpeed::Recorded,
        repeat: false,
        fps: None,
        ..Default::default()
    };
    let source = ReplaySource::open(&cfg).unwrap();
    assert_eq!(source.timing(), &ReplayTiming::DefaultFps(DEFAULT_REPLAY_FPS));
    let described = source.describe();
    assert!(
        described.contains("no timestamps.csv: paced at the default 30 fps"),
        "{described}"
    );
    let status = Arc::new(SharedStatus::new(2, described, "none".into()));
    let (tx, _rx) = tokio::sync::watch::channel(None);
    let mut engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        Arc::new(ParamsHandle::new()),
        tx,
        status.clone(),
        Duration::from_millis(33),
    );
    let t0 = Instant::now();
    let mut published = 0;
    let mut source_errors = 0;
    loop {
        match engine.step().unwrap() {
            StepOutcome::Published(_) => published += 1,
            StepOutcome::SourceError => source_errors += 1,
            StepOutcome::EndOfStream => break,
        }
    }
    // 12 frames, one unreadable: 11 sets at 30 fps take at least 10 intervals of 33 ms.
    assert_eq!(published, FRAMES - 1);
    assert_eq!(source_errors, 1);
    assert_eq!(status.stale_sets.load(std::sync::atomic::Ordering::Relaxed), 0);
    assert!(t0.elapsed() >= Duration::from_millis(320), "{:?}", t0.elapsed());
    let end = engine.source().end_summary().unwrap();
    assert!(
        end.contains("11 of 12 recorded sets delivered")
            && end.contains("1 sets skipped for unreadable frame files")
            && end.contains("000005.pgm"),
        "{end}"
    );
}
