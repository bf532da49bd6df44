//! The solver role in process (docs/cluster.md): two camera boards simulated by this test
//! publish observations of a known point over real Zenoh sessions on 127.0.0.1; the solver
//! pairs and triangulates them. Bad input — an unknown camera, another rig, a timestamp far
//! off, a truncated payload, garbage, a duplicate sequence — is counted and named in
//! `/status`, never gives a wrong position and never stops the service.
#![cfg(feature = "cluster")]

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use common::*;
use irtrack_cluster::transport::{ObsPublisher, Session, TransportConfig, realtime_ns};
use irtrack_core::observation::{MAX_OBS_LEN, ObsBlob, ObsClock, ObsHeader, encode};
use irtrack_core::params::{CameraPlace, RigParams};
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::cluster::{ClusterConfig, Role};
use irtrack_firmware::source::sim::ring_rig;
use nalgebra::Vector3;

const RIG: &str = "cellx";
const FPS: f64 = 30.0;

fn rig() -> RigParams {
    let mut r = ring_rig(3, 600.0);
    r.rig_id = RIG.into();
    r.placement = [("b0", 0), ("b0", 1), ("b1", 0)]
        .iter()
        .map(|&(b, i)| CameraPlace {
            board: b.into(),
            local_index: i,
        })
        .collect();
    r.validate().unwrap();
    r
}

/// Camera `cam`'s blob of the point `p` (camera-0 frame, mm).
fn blob(r: &RigParams, cam: usize, p: &Vector3<f64>) -> ObsBlob {
    let c = &r.cameras[cam];
    let px = c.model.project(&c.cam_from_cam0.apply(p)).unwrap();
    ObsBlob {
        x_px: px.x as f32,
        y_px: px.y as f32,
        area_px: 9,
        peak_dn: 200,
        roundness: 1.0,
        touches_frame_edge: false,
        touches_roi_edge: false,
        saturated: false,
    }
}

fn header<'a>(rig: &'a str, board: &'a str, camera: u8, seq: u64, ts: u64) -> ObsHeader<'a> {
    ObsHeader {
        rig,
        board,
        camera,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: ts,
        clock: ObsClock::Realtime,
        exposure_us: 0,
        dropped: 0,
        send_delay_us: 0,
    }
}

/// The two boards: good observations of `p` at `FPS`, and after `bad_after` frames one of
/// each kind of bad input per frame. Runs until `stop`.
fn boards(port: u16, r: RigParams, p: Vector3<f64>, bad_after: u64, stop: Arc<AtomicBool>) {
    let tc = TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    };
    let (s0, s1) = (Session::open(&tc).unwrap(), Session::open(&tc).unwrap());
    let mut c00 = ObsPublisher::new(&s0, RIG, "b0", 0).unwrap();
    let mut c01 = ObsPublisher::new(&s0, RIG, "b0", 1).unwrap();
    let mut c10 = ObsPublisher::new(&s1, RIG, "b1", 0).unwrap();
    let mut c05 = ObsPublisher::new(&s0, RIG, "b0", 5).unwrap();
    let blobs = [blob(&r, 0, &p), blob(&r, 1, &p), blob(&r, 2, &p)];
    let period_ns = (1e9 / FPS) as u64;
    let mut buf = [0u8; MAX_OBS_LEN];
    let mut seq = 0u64;
    let start = Instant::now();
    while !stop.load(Ordering::Relaxed) && start.elapsed() < Duration::from_secs(60) {
        seq += 1;
        let ts = realtime_ns();
        c00.publish(&header(RIG, "b0", 0, seq, ts), &blobs[..1]).unwrap();
        c01.publish(&header(RIG, "b0", 1, seq, ts), &blobs[1..2]).unwrap();
        c10.publish(&header(RIG, "b1", 0, seq, ts), &blobs[2..]).unwrap();
        if seq > bad_after {
            // An unknown camera of a known board, with a blob that would pull the point away.
            let far = [ObsBlob {
                x_px: 10.0,
                y_px: 10.0,
                ..blobs[0]
            }];
            c05.publish(&header(RIG, "b0", 5, seq, ts), &far).unwrap();
            // Another rig's observation on this rig's key.
            c00.publish(&header("other", "b0", 0, seq + 1_000_000, ts), &far)
                .unwrap();
            // A capture time an hour ahead.
            c10.publish(
                &header(RIG, "b1", 0, seq + 2_000_000, ts + 3_600_000_000_000),
                &far,
            )
            .unwrap();
            // The same sequence again (a duplicate of the good observation, other content).
            c01.publish(&header(RIG, "b0", 1, seq, ts), &far).unwrap();
            // Truncated and garbage payloads.
            let n = encode(&header(RIG, "b0", 0, seq + 3_000_000, ts), &far, &mut buf).unwrap();
            c00.publish_raw(&buf[..n - 7]).unwrap();
            c00.publish_raw(b"definitely not an observation").unwrap();
        }
        let next = start + Duration::from_nanos(seq * period_ns);
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
    s0.close();
    s1.close();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn solver_pairs_two_boards_and_refuses_bad_observations() {
    let dir = TempDir::new("cluster-solver");
    let r = rig();
    std::fs::write(dir.path().join("params.irp"), r.to_blob().unwrap()).unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut cfg = test_config(dir.path());
    cfg.cluster = ClusterConfig {
        role: Role::Solver,
        rig: RIG.into(),
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        fps: FPS,
        board_timeout_ms: 300.0,
        image_sizes_px: r
            .cameras
            .iter()
            .map(|c| [c.model.image_size.width_px, c.model.image_size.height_px])
            .collect(),
        ..ClusterConfig::default()
    };
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let p = Vector3::new(20.0, -10.0, 580.0);
    let stop = Arc::new(AtomicBool::new(false));
    let bad_after = (2.0 * FPS) as u64;
    let publisher = {
        let (r, stop) = (r.clone(), stop.clone());
        std::thread::spawn(move || boards(port, r, p, bad_after, stop))
    };

    // Good observations only: three cameras, the point.
    let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    let first = client
        .until(10 * FPS as usize, |rec| {
            rec.status == TrackStatus::Ok && rec.cameras_used == 3
        })
        .await;
    let err = dist_mm(first.position_mm.unwrap(), [p.x, p.y, p.z]);
    assert!(err < 0.05, "position {:?}, error {err} mm", first.position_mm);

    // Then with bad input on every frame: positions stay right, every problem is named.
    let deadline = Instant::now() + Duration::from_secs(20);
    let expected = [
        "unknown_camera",
        "unknown_rig",
        "timestamp_off",
        "duplicate_sequence",
        "truncated",
        "bad_magic",
    ];
    let st = loop {
        let rec = client.next().await;
        if let Some(pos) = rec.position_mm {
            let e = dist_mm(pos, [p.x, p.y, p.z]);
            assert!(e < 0.05, "a wrong position under bad input: {pos:?} ({e} mm)");
        }
        let st = status_json(running.addrs.status).await;
        let refused = &st["cluster"]["refused"];
        if expected
            .iter()
            .all(|c| refused[c].as_u64().is_some_and(|n| n > 0))
        {
            break st;
        }
        assert!(Instant::now() < deadline, "not every problem counted: {refused}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    let faults = st["fault_texts"].to_string();
    assert!(faults.contains("observations_refused"), "{faults}");
    for code in expected {
        assert!(faults.contains(code), "{code} not named in {faults}");
    }
    assert_eq!(st["cluster"]["role"], "solver");
    let boards = st["cluster"]["boards"].as_array().unwrap();
    assert_eq!(boards.len(), 2, "{boards:?}");
    assert!(
        boards
            .iter()
            .all(|b| b["down"] == false && b["clock_fault"] == false)
    );
    // The same counts in /metrics, read by an independent OpenMetrics parser: every refusal
    // by reason (scraped after /status, so at least its counts), both boards up with a
    // measured clock offset, sets being made.
    let m = scrape_metrics(running.addrs.status).await;
    assert_eq!(
        m.family_type("irtrackd_cluster_observations_refused"),
        Some("counter")
    );
    for code in expected {
        let in_status = st["cluster"]["refused"][code].as_f64().unwrap();
        let scraped = m
            .value("irtrackd_cluster_observations_refused_total", &[("reason", code)])
            .unwrap_or_else(|| panic!("no refused counter for {code} in {}", m.0));
        assert!(
            scraped >= in_status,
            "{code}: /metrics {scraped} < /status {in_status}"
        );
    }
    for b in ["b0", "b1"] {
        assert_eq!(
            m.value("irtrackd_cluster_board_up", &[("board", b)]),
            Some(1.0),
            "{b}"
        );
        assert_eq!(
            m.value("irtrackd_cluster_board_clock_fault", &[("board", b)]),
            Some(0.0)
        );
        let offset_s = m
            .value("irtrackd_cluster_board_clock_offset_seconds", &[("board", b)])
            .unwrap_or_else(|| panic!("no clock offset for {b}"));
        assert!(
            offset_s.abs() < 0.05,
            "{b}: clock offset {offset_s} s on one host"
        );
    }
    assert!(
        m.value("irtrackd_cluster_sets_complete_total", &[])
            .is_some_and(|n| n > 0.0)
    );
    assert!(
        m.value("irtrackd_cluster_observations_received_total", &[])
            .is_some_and(|n| n > 0.0)
    );

    // Still tracking with all three cameras after the bad input.
    let rec = client
        .until(3 * FPS as usize, |rec| {
            rec.status == TrackStatus::Ok && rec.cameras_used == 3
        })
        .await;
    assert!(dist_mm(rec.position_mm.unwrap(), [p.x, p.y, p.z]) < 0.05);

    // The boards stop: both reported down, no position is made up.
    stop.store(true, Ordering::Relaxed);
    publisher.join().unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let st = status_json(running.addrs.status).await;
        let down = st["cluster"]["boards"]
            .as_array()
            .is_some_and(|b| b.iter().all(|b| b["down"] == true));
        if down {
            assert!(st["fault_texts"].to_string().contains("board_down"));
            let m = scrape_metrics(running.addrs.status).await;
            for b in ["b0", "b1"] {
                assert_eq!(
                    m.value("irtrackd_cluster_board_up", &[("board", b)]),
                    Some(0.0),
                    "{b}"
                );
                let silent_s = m
                    .value("irtrackd_cluster_board_last_seen_seconds", &[("board", b)])
                    .unwrap_or(0.0);
                assert!(silent_s >= 0.3, "{b} down after only {silent_s} s of silence");
            }
            break;
        }
        assert!(
            Instant::now() < deadline,
            "boards not reported down: {}",
            st["cluster"]
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    running.shutdown().await;
}
