//! irtrackd end to end over real sockets on 127.0.0.1 with the simulated source.

mod common;

use std::time::Duration;

use common::*;
use irtrack_core::camera::RigidTransform;
use irtrack_core::param_wire::{RejectCode, Verdict};
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::leds::Led;
use irtrack_firmware::storage::{ACTIVE_FILE, PREVIOUS_FILE};

/// Waits until `f` holds (polling), failing after `secs`.
async fn eventually(secs: u64, mut f: impl FnMut() -> bool) {
    let end = tokio::time::Instant::now() + Duration::from_secs(secs);
    while !f() {
        assert!(
            tokio::time::Instant::now() < end,
            "condition not reached within {secs} s"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sim_positions_match_truth_over_ndjson_and_binary() {
    let dir = TempDir::new("truth");
    let mut cfg = test_config(dir.path());
    cfg.service.params_from_simulator = true;
    let sim = cfg.source.sim.clone().unwrap();
    let truth = scenario(&sim);
    let running = app::start(cfg, Overrides::default()).await.unwrap();

    let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    let mut bin = tokio::net::TcpStream::connect(running.addrs.stream_binary)
        .await
        .unwrap();
    let mut errors = Vec::new();
    let mut n_ok = 0;
    for _ in 0..60 {
        let r = client.next().await;
        if r.status != TrackStatus::Ok {
            continue;
        }
        n_ok += 1;
        let p = r.position_mm.unwrap();
        let t = truth.truth(r.frame).markers()[0].p_cam0_mm;
        errors.push(dist_mm(p, [t.x, t.y, t.z]));
        assert!(!r.world_frame);
        assert!(
            r.latency_us > 0 && r.latency_us < 1_000_000,
            "latency {} us",
            r.latency_us
        );
    }
    assert!(n_ok >= 50, "only {n_ok} of 60 records tracked");
    let max = errors.iter().cloned().fold(0.0, f64::max);
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    eprintln!("sim → irtrackd → NDJSON: {n_ok} positions, mean error {mean:.3} mm, max {max:.3} mm");
    assert!(max < 1.0, "max error {max} mm");

    // The binary port carries the same records.
    let b = read_binary(&mut bin).await;
    assert_ne!(b.params_crc, 0);
    if b.status == TrackStatus::Ok {
        let t = truth.truth(b.frame).markers()[0].p_cam0_mm;
        assert!(dist_mm(b.position_mm.unwrap(), [t.x, t.y, t.z]) < 1.0);
    }
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn starts_without_params_then_push_swaps_live_and_bad_blobs_keep_last_good() {
    let dir = TempDir::new("params");
    let cfg = test_config(dir.path());
    let sim = cfg.source.sim.clone().unwrap();
    let truth = scenario(&sim);
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let addrs = running.addrs;

    // No parameters: records flow (the loop runs) but none carries a position.
    let mut client = NdjsonClient::connect(addrs.stream_ndjson).await;
    for _ in 0..10 {
        let r = client.next().await;
        assert_eq!(r.status, TrackStatus::NoParams);
        assert!(r.position_mm.is_none());
    }
    let st = status_json(addrs.status).await;
    assert_eq!(st["params"]["loaded"], false);
    assert!(
        st["faults"].as_array().unwrap().iter().any(|f| f == "no_params"),
        "{st}"
    );
    assert_eq!(st["processing"]["tracked"], 0);

    // Push the true rig: accepted and used without restart.
    let mut rig = truth.rig().clone();
    rig.rig_id = "rig-a".into();
    assert_eq!(push(addrs.params, &rig.to_blob().unwrap()).await, "OK rig-a\n");
    let r = client.until(100, |r| r.status == TrackStatus::Ok).await;
    let t = truth.truth(r.frame).markers()[0].p_cam0_mm;
    assert!(dist_mm(r.position_mm.unwrap(), [t.x, t.y, t.z]) < 1.0);
    assert!(!r.world_frame);

    // A second set with a world transform: positions switch to the world frame live.
    let world = RigidTransform {
        t_mm: [1000.0, -200.0, 50.0],
        ..RigidTransform::IDENTITY
    };
    let st = status_json(addrs.status).await;
    assert!(st["params"]["calibration"].is_null(), "{st}");
    let mut rig_b = rig.clone();
    rig_b.rig_id = "rig-b".into();
    rig_b.world_from_cam0 = Some(world);
    // rig-b carries a calibration record: written anyway as poor, a year ago.
    rig_b.calibration = Some(Box::new(irtrack_core::params::CalibrationInfo {
        method: "wand".into(),
        calibrated_unix_s: irtrack_firmware::calibration::now_unix_s() - 365 * 86_400,
        tool_version: "host-tools 0.1.0".into(),
        verdict: irtrack_core::params::Verdict::Poor,
        summary: "POOR wand calibration: cam1 reprojection RMS 3.71 px (limit ≤ 1 px)".into(),
        rms_px: vec![0.5, 3.71],
        figures: vec![],
    }));
    assert_eq!(push(addrs.params, &rig_b.to_blob().unwrap()).await, "OK rig-b\n");
    let r = client
        .until(100, |r| r.status == TrackStatus::Ok && r.world_frame)
        .await;
    let t = truth.truth(r.frame).markers()[0].p_cam0_mm;
    let p = r.position_mm.unwrap();
    assert!(
        dist_mm(p, [t.x + 1000.0, t.y - 200.0, t.z + 50.0]) < 1.0,
        "{p:?} vs {t:?}"
    );
    // The status shows the active set's calibration: method, age, quality and a warning.
    let st = status_json(addrs.status).await;
    let cal = &st["params"]["calibration"];
    assert_eq!(
        (cal["method"].as_str(), cal["verdict"].as_str()),
        (Some("wand"), Some("poor")),
        "{st}"
    );
    assert!((cal["age_days"].as_f64().unwrap() - 365.0).abs() < 0.1, "{st}");
    let warning = cal["warning"].as_str().unwrap();
    assert!(
        warning.contains("marked POOR")
            && warning.contains("cam1 reprojection RMS")
            && warning.contains("365 days old"),
        "{warning}"
    );

    // Bad blobs: each rejected with its exact reason; rig-b stays active.
    let good = rig.to_blob().unwrap();
    let mut corrupt = good.clone();
    let last = corrupt.len() - 1;
    corrupt[last] ^= 0x55;
    let v = push_verdict(addrs.params, &corrupt).await;
    let Verdict::Rejected { code, message } = v else {
        panic!("corrupt blob accepted")
    };
    assert_eq!(code, RejectCode::BadBlob);
    assert!(message.contains("CRC-32"), "{message}");

    let mut magic = good.clone();
    magic[0] = b'X';
    let line = push(addrs.params, &magic).await;
    assert!(
        line.starts_with("ERR BAD_BLOB not an irtrack parameter blob"),
        "{line}"
    );

    let mut three = rig.clone();
    three.rig_id = "three-cams".into();
    let mut cam2 = three.cameras[1].clone();
    cam2.cam_from_cam0.t_mm[1] += 300.0;
    three.cameras.push(cam2);
    let line = push(addrs.params, &three.to_blob().unwrap()).await;
    assert_eq!(
        line,
        "ERR RIG_MISMATCH parameter set \"three-cams\" has 3 cameras, this rig has 2\n"
    );

    let mut small = rig.clone();
    small.rig_id = "small".into();
    for c in &mut small.cameras {
        c.model.image_size.width_px = 320;
        c.model.image_size.height_px = 240;
        c.model.intrinsics.cx_px /= 2.0;
        c.model.intrinsics.cy_px /= 2.0;
    }
    let line = push(addrs.params, &small.to_blob().unwrap()).await;
    assert_eq!(
        line,
        "ERR RIG_MISMATCH camera 0: parameters are for 320x240 px images, the camera delivers 640x480\n"
    );

    let mut invalid = rig.clone();
    invalid.rig_id = "has space".into();
    let line = push(addrs.params, &invalid.to_blob().unwrap()).await;
    assert!(line.starts_with("ERR INVALID_PARAMS"), "{line}");

    // Wrong framing.
    let mut s = tokio::net::TcpStream::connect(addrs.params).await.unwrap();
    tokio::io::AsyncWriteExt::write_all(&mut s, b"HELO\x04\x00\x00\x00abcd")
        .await
        .unwrap();
    let mut reply = String::new();
    tokio::io::AsyncReadExt::read_to_string(&mut s, &mut reply)
        .await
        .unwrap();
    assert!(reply.starts_with("ERR PROTOCOL"), "{reply}");

    let st = status_json(addrs.status).await;
    assert_eq!(st["params"]["rig_id"], "rig-b");
    assert_eq!(st["params"]["rejected"], 6, "{}", st["params"]);
    let r = client.until(100, |r| r.status == TrackStatus::Ok).await;
    assert!(r.world_frame, "rig-b (world frame) must still be active");

    // Stored: active = rig-b, previous = rig-a.
    let active =
        irtrack_core::params::RigParams::from_blob(&std::fs::read(dir.path().join(ACTIVE_FILE)).unwrap())
            .unwrap();
    let prev =
        irtrack_core::params::RigParams::from_blob(&std::fs::read(dir.path().join(PREVIOUS_FILE)).unwrap())
            .unwrap();
    assert_eq!((active.rig_id.as_str(), prev.rig_id.as_str()), ("rig-b", "rig-a"));
    running.shutdown().await;

    // A restart picks up the stored set.
    let running = app::start(test_config(dir.path()), Overrides::default())
        .await
        .unwrap();
    let st = status_json(running.addrs.status).await;
    assert_eq!(st["params"]["rig_id"], "rig-b");
    assert_eq!(st["params"]["origin"], "state_dir");
    running.shutdown().await;

    // A corrupted active file falls back to the previous set.
    std::fs::write(dir.path().join(ACTIVE_FILE), b"IRPBgarbage").unwrap();
    let running = app::start(test_config(dir.path()), Overrides::default())
        .await
        .unwrap();
    let st = status_json(running.addrs.status).await;
    assert_eq!(st["params"]["rig_id"], "rig-a");
    assert_eq!(st["params"]["origin"], "rollback");
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn led_states_follow_faults_and_tracking() {
    let dir = TempDir::new("leds");
    let cfg = test_config(dir.path());
    let sim = cfg.source.sim.clone().unwrap();
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let record = running.led_record.clone().expect("sim LED back end");
    let status = running.status.clone();

    // No params: fault LED flashes once per 2 s cycle, heartbeat runs, track LED stays off.
    eventually(5, || status.indication().alive).await;
    assert_eq!(
        status.indication().fault,
        Some(irtrack_firmware::leds::indication::Fault::NoParams)
    );
    let start = record.changes().len();
    tokio::time::sleep(Duration::from_millis(2100)).await;
    let window: Vec<_> = record.changes()[start..].to_vec();
    let rises = |led: Led| window.iter().filter(|c| c.led == led && c.on).count();
    assert!((1..=2).contains(&rises(Led::Fault)), "fault flashes: {window:?}");
    // 2 s of heartbeat; a tick delayed by a loaded machine may swallow one 100 ms pulse.
    assert!((1..=3).contains(&rises(Led::Run)), "heartbeats: {window:?}");
    assert_eq!(rises(Led::Track), 0);

    // Params: fault clears, the marker is tracked in both cameras → track LED steady on.
    let rig = scenario(&sim).rig().clone();
    assert!(
        push(running.addrs.params, &rig.to_blob().unwrap())
            .await
            .starts_with("OK")
    );
    eventually(5, || status.indication().fault.is_none()).await;
    eventually(5, || status.led_levels()[1]).await;
    let before = record.changes().len();
    tokio::time::sleep(Duration::from_millis(600)).await;
    let window: Vec<_> = record.changes()[before..].to_vec();
    assert!(
        window.iter().all(|c| c.led != Led::Fault && c.led != Led::Track),
        "{window:?}"
    );
    assert!(status.led_levels()[1], "track LED on");

    // Robot LED follows the robot link's state.
    status.set_robot(irtrack_firmware::leds::indication::RobotIndication::Connected);
    eventually(2, || status.led_levels()[2]).await;
    let st = status_json(running.addrs.status).await;
    assert_eq!(st["leds"]["indication"]["robot"], "connected");
    assert_eq!(st["leds"]["on"]["robot"], true);
    running.shutdown().await;
    // Stopping switches everything off.
    let last = record.changes();
    for led in Led::ALL {
        let l = last.iter().rev().find(|c| c.led == led).map(|c| c.on);
        assert_ne!(l, Some(true), "{led:?} left on");
    }
}

/// A board without LEDs still shows what they would show: the page's LED row reads `/status`'s
/// levels, which stayed all off (grey) when no driver ran.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_leds_the_status_still_carries_the_indication() {
    let dir = TempDir::new("no-leds");
    let mut cfg = test_config(dir.path());
    cfg.leds.backend = irtrack_firmware::config::LedBackend::None;
    cfg.service.params_from_simulator = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    assert!(running.led_record.is_none(), "no LED back end was asked for");
    let status = running.status.clone();
    eventually(5, || status.indication().alive).await;
    // The marker is tracked in both cameras: the track level is on, as on a board with LEDs.
    eventually(5, || status.led_levels()[1]).await;
    let st = status_json(running.addrs.status).await;
    assert_eq!(st["leds"]["backend"], "none");
    assert_eq!(st["leds"]["indication"]["alive"], true);
    assert_eq!(st["leds"]["on"]["track"], true);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_stream_client_is_dropped_without_stalling_others() {
    let dir = TempDir::new("slow");
    let mut cfg = test_config(dir.path());
    cfg.service.params_from_simulator = true;
    cfg.listen.client_queue_records = 4;
    if let Some(s) = cfg.source.sim.as_mut() {
        s.fps = 400.0;
    }
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let status = running.status.clone();

    // A client with a tiny receive window that never reads.
    let sock = tokio::net::TcpSocket::new_v4().unwrap();
    sock.set_recv_buffer_size(2048).unwrap();
    let _slow = sock.connect(running.addrs.stream_ndjson).await.unwrap();
    let mut good = NdjsonClient::connect(running.addrs.stream_ndjson).await;

    let processed0 = status.sets_processed.load(std::sync::atomic::Ordering::Relaxed);
    let mut last_frame = 0;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(15);
    while status
        .stream_dropped_slow
        .load(std::sync::atomic::Ordering::Relaxed)
        == 0
    {
        assert!(
            tokio::time::Instant::now() < deadline,
            "slow client never dropped"
        );
        let r = good.next().await;
        assert!(r.frame > last_frame || last_frame == 0);
        last_frame = r.frame;
    }
    // The good client keeps getting fresh records and the loop kept running.
    let a = good.next().await.frame;
    let b = good.next().await.frame;
    assert!(b > a);
    let processed1 = status.sets_processed.load(std::sync::atomic::Ordering::Relaxed);
    assert!(
        processed1 > processed0 + 50,
        "loop stalled: {processed0} → {processed1}"
    );
    let st = status_json(running.addrs.status).await;
    assert_eq!(st["stream"]["dropped_slow"], 1);
    assert_eq!(st["stream"]["clients"], 1);
    running.shutdown().await;
}

/// A flood of stream connections (idle ones, ones that write garbage, far more than the limit):
/// connections over `listen.max_stream_clients` are closed at once and counted, a well-behaved
/// client keeps receiving fresh records, the loop keeps its pace, and freed slots are reusable.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stream_connection_flood_is_refused_without_disturbing_clients() {
    use std::sync::atomic::Ordering::Relaxed;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    const LIMIT: u64 = 8;
    const FLOOD: usize = 200;
    let dir = TempDir::new("flood");
    let mut cfg = test_config(dir.path());
    cfg.service.params_from_simulator = true;
    cfg.listen.max_stream_clients = LIMIT;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let status = running.status.clone();
    let mut good = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    good.until(200, |r| r.status == TrackStatus::Ok).await;

    // Fill the limit: idle clients on both ports, some writing garbage at the server.
    let mut held = Vec::new();
    for i in 0..(LIMIT - 1) as usize {
        let addr = if i % 2 == 0 {
            running.addrs.stream_ndjson
        } else {
            running.addrs.stream_binary
        };
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        if i % 3 == 0 {
            s.write_all(&[0xAB; 4096]).await.unwrap();
        }
        held.push(s);
    }
    eventually(5, || status.stream_clients.load(Relaxed) == LIMIT).await;

    // The flood: every further connection is closed by the server without a record.
    let processed0 = status.sets_processed.load(Relaxed);
    let mut closed_at_once = 0;
    for i in 0..FLOOD {
        let addr = if i % 2 == 0 {
            running.addrs.stream_ndjson
        } else {
            running.addrs.stream_binary
        };
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        let mut buf = [0u8; 64];
        if let Ok(Ok(0)) = tokio::time::timeout(Duration::from_secs(2), s.read(&mut buf)).await {
            closed_at_once += 1;
        }
    }
    assert_eq!(
        closed_at_once, FLOOD,
        "connections over the limit must be closed at once"
    );
    assert!(status.stream_refused.load(Relaxed) >= FLOOD as u64);
    assert_eq!(status.stream_clients.load(Relaxed), LIMIT);

    // The good client still gets fresh, tracked records; the loop kept running meanwhile.
    let a = good.until(50, |r| r.status == TrackStatus::Ok).await;
    let b = good.next().await;
    assert!(b.frame > a.frame);
    assert!(a.latency_us < 100_000, "stale record: {} µs", a.latency_us);
    // One more second of streaming with the limit still full: the 100 fps loop keeps its pace.
    let t0 = tokio::time::Instant::now();
    let mut last = b.frame;
    while t0.elapsed() < Duration::from_secs(1) {
        let r = good.next().await;
        assert!(r.frame > last);
        last = r.frame;
    }
    let processed1 = status.sets_processed.load(Relaxed);
    assert!(
        processed1 >= processed0 + 50,
        "loop slowed: {processed0} → {processed1} in > 1 s"
    );

    // Freed slots are usable again.
    drop(held);
    eventually(5, || status.stream_clients.load(Relaxed) == 1).await;
    let mut again = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    again.next().await;
    let st = status_json(running.addrs.status).await;
    assert!(st["stream"]["refused"].as_u64().unwrap() >= FLOOD as u64, "{st}");
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn status_json_and_metrics_report_the_running_service() {
    let dir = TempDir::new("status");
    let mut cfg = test_config(dir.path());
    cfg.service.params_from_simulator = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let status = running.status.clone();
    // Every stage's histogram, not only the tracked counter: the loop counts a set as tracked
    // before it records the later stages' latencies, so a snapshot can fall in between.
    eventually(10, || {
        status.tracked.load(std::sync::atomic::Ordering::Relaxed) >= 30
            && status
                .stages
                .stages()
                .iter()
                .all(|(_, h)| h.snapshot().count() >= 30)
            // Every camera's clock model has locked and published (every 8 frames).
            && status
                .cameras
                .iter()
                .all(|c| c.clock.state.load(std::sync::atomic::Ordering::Relaxed) == 2)
    })
    .await;

    let st = status_json(running.addrs.status).await;
    assert_eq!(st["service"], "irtrackd");
    assert_eq!(st["versions"]["irtrackd"], env!("CARGO_PKG_VERSION"));
    assert_eq!(
        st["versions"]["param_blob_format"],
        irtrack_core::params::BLOB_FORMAT_VERSION
    );
    assert_eq!(
        st["versions"]["stream_binary"],
        irtrack_core::stream::BINARY_VERSION
    );
    assert_eq!(st["params"]["loaded"], true);
    assert_eq!(st["params"]["origin"], "simulator");
    assert!(st["params"]["rig_id"].as_str().is_some());
    let cams = st["source"]["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), 2);
    // Delivered-frame rate: the nominal 100 fps unless the (loaded) machine made the source skip.
    let skipped = st["source"]["sets_dropped"].as_u64().unwrap();
    for c in cams {
        let fps = c["fps"].as_f64().unwrap();
        assert!(fps > 0.0 && fps < 115.0, "camera fps {fps}");
        assert!(
            skipped > 0 || (fps - 100.0).abs() < 15.0,
            "camera fps {fps} without skipped sets"
        );
        assert_eq!(c["width_px"], 640);
        // The camera's clock model (docs/timing.md, "Camera clocks"): the simulator's
        // 100 fps clock, phase against camera 0 within half a period, no jump.
        let clock = &c["clock"];
        assert_eq!(clock["state"], "locked", "{clock}");
        let period_us = clock["period_us"].as_f64().unwrap();
        assert!((period_us - 10_000.0).abs() < 10.0, "{clock}");
        assert!((clock["fps"].as_f64().unwrap() - 100.0).abs() < 0.1, "{clock}");
        assert!(
            clock["rate_error_ppm"].as_f64().unwrap().abs() < 1000.0,
            "{clock}"
        );
        let phase_us = clock["phase_us"].as_f64().unwrap();
        assert!(phase_us.abs() <= period_us / 2.0, "{clock}");
        if c["index"] == 0 {
            assert_eq!(phase_us, 0.0, "{clock}");
        }
        assert!(clock["jitter_rms_us"].as_f64().unwrap() >= 0.0, "{clock}");
        assert!(clock["jitter_max_us"].as_f64().is_some(), "{clock}");
        assert!(clock["drift_us_per_min"].as_f64().is_some(), "{clock}");
        assert!(clock["drops"].as_u64().is_some() && clock["duplicates"].as_u64().is_some());
        assert_eq!(clock["jumps"], 0, "{clock}");
    }
    assert!(st["source"]["pairing_error_last_us"].as_f64().is_some());
    assert!(st["source"]["sets_dropped"].as_u64().is_some());
    let lat = &st["processing"]["latency_us"];
    for stage in ["detect", "solve", "publish", "process", "end_to_end"] {
        assert!(
            lat[stage]["count"].as_u64().unwrap() >= 30,
            "{stage}: {}",
            lat[stage]
        );
        // True percentiles (µs with fractions), not bucket edges.
        let (p50, p99) = (
            lat[stage]["p50_us"].as_f64().unwrap(),
            lat[stage]["p99_us"].as_f64().unwrap(),
        );
        // Sets before the parameter set arrived skip detection (0 ns stages); the whole
        // set and capture → published always take time.
        assert!(p50 >= 0.0 && p99 >= p50, "{stage}: {}", lat[stage]);
        if matches!(stage, "process" | "end_to_end") {
            assert!(p50 > 0.0, "{stage}: {}", lat[stage]);
        }
        assert!(lat[stage]["max_us"].as_f64().unwrap() >= p99);
    }
    assert!((st["processing"]["deadline_us"].as_f64().unwrap() - 10_000.0).abs() < 1.0);
    assert!(st["processing"]["deadline_misses"].as_u64().is_some());
    assert!(st["processing"]["last_gap_mm"].as_f64().unwrap() < 3.0);
    assert!(st["leds"]["on"]["run"].is_boolean());
    assert_eq!(st["leds"]["backend"], "simulated LEDs (logged)");
    assert_eq!(st["faults"].as_array().unwrap().len(), 0, "{}", st["faults"]);
    eprintln!("latency: {}", st["processing"]["latency_us"]);

    let (code, metrics) = http_get(running.addrs.status, "/metrics").await;
    assert_eq!(code, 200);
    for want in [
        "irtrackd_stage_latency_seconds_bucket{le=\"+Inf\",stage=\"detect\"}",
        "irtrackd_params_loaded 1",
        "irtrackd_camera_fps{camera=\"1\"}",
        "irtrackd_camera_period_seconds{camera=\"1\"} 0.0",
        "irtrackd_camera_phase_seconds{camera=\"1\"}",
        "irtrackd_camera_jitter_rms_seconds{camera=\"0\"}",
        "irtrackd_camera_drift_ppm{camera=\"1\"}",
        "irtrackd_camera_clock_locked{camera=\"1\"} 1",
        "irtrackd_camera_frames_dropped_total{camera=\"0\"}",
        "irtrackd_camera_clock_jumps_total{camera=\"1\"} 0",
        "irtrackd_sets_processed_total ",
        "irtrackd_info{version=",
        "irtrackd_fault{fault=\"no_params\"} 0",
        "# TYPE irtrackd_stage_latency_seconds histogram",
        "irtrackd_stage_latency_quantile_seconds{stage=\"detect\",quantile=\"0.99\"} ",
        "# EOF",
    ] {
        assert!(metrics.contains(want), "no {want:?} in\n{metrics}");
    }
    // Cumulative buckets: the +Inf bucket of a stage equals its count.
    let value = |prefix: &str| -> f64 {
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(prefix))
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or_else(|| panic!("no {prefix:?} in\n{metrics}"))
    };
    let inf = value("irtrackd_stage_latency_seconds_bucket{le=\"+Inf\",stage=\"detect\"}");
    let count = value("irtrackd_stage_latency_seconds_count{stage=\"detect\"}");
    assert!(inf > 0.0 && inf == count, "+Inf bucket {inf}, count {count}");
    let (code, _) = http_get(running.addrs.status, "/nope").await;
    assert_eq!(code, 404);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robot_link_from_config_drives_the_robot_led() {
    use irtrack_robot::sim::{SimRobotServer, SimServerConfig};
    let robot = SimRobotServer::start(SimServerConfig::default()).await.unwrap();
    let dir = TempDir::new("robot");
    let toml = format!(
        r#"
[service]
params_from_simulator = true
[robot]
address = "{}"
[robot.safety]
workspace_min_mm = [-500.0, -500.0, 0.0]
workspace_max_mm = [500.0, 500.0, 1000.0]
max_step_mm = 20.0
max_speed_mm_s = 250.0
max_gap_mm = 2.0
max_age_ms = 100
[robot.deadman]
kind = "none"
"#,
        robot.addr
    );
    let base = test_config(dir.path());
    let mut cfg = irtrack_firmware::config::Config::from_toml(&toml, "robot.toml").unwrap();
    cfg.service.state_dir = base.service.state_dir;
    cfg.listen = base.listen;
    cfg.source = base.source;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    assert!(running.robot().is_some());
    let status = running.status.clone();
    // Connected but not enabled: the link holds, the Robot LED blinks slowly.
    let holding = irtrack_firmware::leds::indication::RobotIndication::Holding;
    eventually(10, || status.robot() == holding).await;
    // The LED driver (25 ms tick) picks it up and /status shows it.
    eventually(2, || status.indication().robot == holding).await;
    let mut shown = false;
    for _ in 0..50 {
        let st = status_json(running.addrs.status).await;
        if st["leds"]["indication"]["robot"] == "holding" {
            shown = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(shown, "/status never showed the robot holding");
    running.shutdown().await;
}
