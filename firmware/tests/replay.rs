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

fn realtime_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
}

/// Two sources replaying one camera each of the same recording on the shared clock (as two
/// camera boards do): opened at different moments, they stamp each recorded frame with the
/// same instant (recorded time + one offset); the one opened after the start instant joins
/// where the recording is, passing over the sets already past, without shifting.
#[test]
fn replay_on_the_shared_clock_keeps_the_time_base_across_sources() {
    let dir = TempDir::new("replay-shared");
    record(dir.path());
    // The recording's earliest timestamp: frame 0 at 1 s + its render instant.
    let start_rt_ns = realtime_ns() + 150_000_000;
    let cfg = |camera: usize| ReplayConfig {
        dir: dir.path().to_path_buf(),
        cameras: Some(vec![camera]),
        start_at_unix_s: Some(start_rt_ns as f64 / 1e9),
        ..Default::default()
    };
    let mut a = ReplaySource::open(&cfg(0)).unwrap();
    assert_eq!(a.camera_count(), 1);
    assert!(
        a.describe().contains("cameras [0] of the recording"),
        "{}",
        a.describe()
    );
    let origin = a.origin_ns().unwrap();
    let mut set = a.allocate_set();
    // Camera 0 from the start: waits for the start instant, then frame 0.
    let rt_minus_mono = realtime_ns() as i128 - irtrack_firmware::clock::monotonic_ns() as i128;
    let mut stamps_a = std::collections::BTreeMap::new();
    for _ in 0..5 {
        a.next_set(&mut set).unwrap();
        let rt = set.frames[0].timestamp_ns as i128 + rt_minus_mono;
        stamps_a.insert(set.index, rt);
    }
    assert_eq!(stamps_a.keys().copied().collect::<Vec<_>>(), vec![0, 1, 2, 3, 4]);
    // Frame 0 plays at the start instant (recorded time − origin + start), to a few µs.
    let off0 = stamps_a[&0] - start_rt_ns as i128;
    assert!(off0.abs() < 50_000, "frame 0 at {off0} ns from the start instant");
    // Camera 1 opened now, after frames 0–4 were due: it joins where the recording is.
    std::thread::sleep(Duration::from_millis(20));
    let mut b = ReplaySource::open(&cfg(1)).unwrap();
    assert_eq!(
        b.origin_ns(),
        Some(origin),
        "the same origin from the same timestamps.csv"
    );
    let mut set_b = b.allocate_set();
    b.next_set(&mut set_b).unwrap();
    let first_b = set_b.index;
    assert!(
        first_b >= 5,
        "the late source started at frame {first_b}, not at the beginning"
    );
    assert!(b.late_skipped() >= 5, "{}", b.late_skipped());
    // From there both stamp every frame alike (camera 1 drops frame 5: that set is skipped).
    for _ in 0..3 {
        a.next_set(&mut set).unwrap();
        stamps_a.insert(set.index, set.frames[0].timestamp_ns as i128 + rt_minus_mono);
    }
    let mut compared = 0;
    let mut check = |index: u64, mono: u64| {
        if let Some(ta) = stamps_a.get(&index) {
            let d = (mono as i128 + rt_minus_mono) - ta;
            assert!(
                d.abs() < 50_000,
                "frame {index}: the sources' stamps differ by {d} ns"
            );
            compared += 1;
        }
    };
    check(set_b.index, set_b.frames[0].timestamp_ns);
    for _ in 0..2 {
        b.next_set(&mut set_b).unwrap();
        check(set_b.index, set_b.frames[0].timestamp_ns);
    }
    assert!(compared >= 2, "{compared} frames compared");
    let end = b.end_summary().unwrap();
    assert!(
        end.contains("passed over because their time on the shared clock"),
        "{end}"
    );
}

/// Bad shared-clock settings are named.
#[test]
fn replay_camera_selection_and_start_are_checked() {
    let dir = TempDir::new("replay-select");
    record(dir.path());
    let open_err = |cfg: ReplayConfig| ReplaySource::open(&cfg).err().unwrap().to_string();
    let base = ReplayConfig {
        dir: dir.path().to_path_buf(),
        ..Default::default()
    };
    let e = open_err(ReplayConfig {
        cameras: Some(vec![1, 1]),
        ..base.clone()
    });
    assert!(e.contains("lists camera 1 twice"), "{e}");
    let e = open_err(ReplayConfig {
        cameras: Some(vec![3]),
        ..base.clone()
    });
    assert!(e.contains("lists camera 3") && e.contains("no cam3/"), "{e}");
    let e = open_err(ReplayConfig {
        start_at_unix_s: Some(1.8e9),
        speed: ReplaySpeed::Max,
        ..base.clone()
    });
    assert!(e.contains("start_at_unix_s") && e.contains("recorded"), "{e}");
    // A folder with only camera 0's directory but the whole recording's timestamps.csv:
    // refused with the hint, accepted with `cameras`.
    std::fs::rename(dir.path().join("cam1"), dir.path().join("other")).unwrap();
    let e = open_err(base.clone());
    assert!(
        e.contains("no cam1/ directory") && e.contains("[source.replay] cameras"),
        "{e}"
    );
    let s = ReplaySource::open(&ReplayConfig {
        cameras: Some(vec![0]),
        ..base
    })
    .unwrap();
    // Camera 1's dropped frame no longer removes a set of camera 0.
    assert_eq!(s.len() as u64, FRAMES);
}

/// `wait_for_params` and `wait_for_client`: the replay holds its first frame, says why on
/// `/status`, and starts at frame 0 once both are there.
#[test]
fn replay_waits_for_a_parameter_set_and_a_client() {
    runtime().block_on(async {
        let dir = TempDir::new("replay-wait");
        let state = TempDir::new("replay-wait-state");
        let sc = record(dir.path());
        let mut cfg = test_config(state.path());
        cfg.source.kind = irtrack_firmware::config::SourceKind::Replay;
        cfg.source.sim = None;
        cfg.source.replay = Some(ReplayConfig {
            dir: dir.path().to_path_buf(),
            wait_for_params: true,
            wait_for_client: true,
            ..Default::default()
        });
        let running = irtrack_firmware::app::start(cfg, irtrack_firmware::app::Overrides::default())
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(600)).await;
        let st = status_json(running.addrs.status).await;
        let waiting = st["source"]["waiting"].as_str().unwrap_or_default().to_string();
        assert!(
            waiting.contains("holds at its first frame")
                && waiting.contains("a parameter set")
                && waiting.contains("a position stream client"),
            "{waiting}"
        );
        assert_eq!(st["source"]["sets_delivered"], 0);
        assert_eq!(st["processing"]["source_errors"], 0, "waiting is no camera fault");
        let codes: Vec<&str> = st["faults"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|f| f.as_str())
            .collect();
        assert!(!codes.contains(&"camera_lost"), "{codes:?}");

        // A parameter set: it still waits for a client, and says only that.
        let verdict = push_verdict(running.addrs.params, &sc.rig().to_blob().unwrap()).await;
        assert!(
            matches!(verdict, irtrack_core::param_wire::Verdict::Accepted { .. }),
            "{verdict:?}"
        );
        tokio::time::sleep(Duration::from_millis(400)).await;
        let st = status_json(running.addrs.status).await;
        let waiting = st["source"]["waiting"].as_str().unwrap_or_default().to_string();
        assert!(
            waiting.contains("a position stream client") && !waiting.contains("a parameter set"),
            "{waiting}"
        );
        assert_eq!(st["source"]["sets_delivered"], 0);

        // A client: the replay starts at its first frame, so the client gets frame 0 on.
        let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
        let first = client.next().await;
        assert_eq!(first.status, TrackStatus::Ok);
        tokio::time::sleep(Duration::from_millis(200)).await;
        let st = status_json(running.addrs.status).await;
        // Frame 0 comes first unless the hub task was slower than the 10 ms frames (QEMU under
        // load): then the records it missed were overwritten in the latest-value slot, and
        // counted there; none were consumed before the client came.
        let overwritten = st["stream"]["slot_overwrites"].as_u64().unwrap();
        assert!(
            first.frame <= overwritten,
            "the recording was consumed before the client came: first frame {} with {overwritten} \
             records overwritten in the slot",
            first.frame
        );
        assert!(st["source"]["waiting"].is_null(), "{}", st["source"]["waiting"]);
        running.shutdown().await;
    });
}
