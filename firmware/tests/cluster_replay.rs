//! Replaying a multi-board recording on the shared clock (docs/cluster.md, "Replaying a
//! multi-board recording").
//!
//! One four-camera recording (a ring rig at 120 fps, the marker on its circle) is replayed by
//! two irtrackd camera boards in this process (cameras 0–1 and 2–3 of the recording, each with
//! the whole `timestamps.csv`) into a solver, the boards started at random moments hundreds
//! of milliseconds apart, one of them after the shared start instant. Each solver position
//! from all four cameras must equal the single-board replay's position of the same recorded
//! frame, and the solver's `frame` must be the recording's frame number.
#![cfg(feature = "cluster")]

mod common;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::Arc;
use std::time::Duration;

use common::*;
use irtrack_core::params::{CameraPlace, RigParams};
use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::cluster::{ClusterConfig, Role};
use irtrack_firmware::config::SourceKind;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use irtrack_firmware::source::replay::{ReplayConfig, ReplaySource, ReplaySpeed};
use irtrack_firmware::source::sim::{SimRig, SimSourceConfig};
use irtrack_firmware::source::{Frame, FrameSource, Pixels};
use irtrack_firmware::status::SharedStatus;

const RIG: &str = "replay";
const FPS: f64 = 120.0;
const FRAMES: u64 = 300;
/// The recording's clock: CLOCK_REALTIME of a capture made earlier (as `host-tools capture`
/// writes it), so the replay's mapping onto now is a real shift.
const RECORDED_BASE_NS: u64 = 1_790_000_000_000_000_000;

fn sim() -> SimSourceConfig {
    SimSourceConfig {
        rig: SimRig::Ring,
        ring_cameras: 4,
        distance_mm: 600.0,
        radius_mm: 100.0,
        period_s: 1.5,
        fps: FPS,
        ..SimSourceConfig::default()
    }
}

/// Writes the recording: `cam0/` … `cam3/` and one `timestamps.csv` for all four cameras.
fn record(dir: &std::path::Path) -> (irtrack_sim::Scenario, RigParams) {
    let cfg = sim();
    let mut sc = scenario(&cfg);
    let rig = cfg.rendered_rig(sc.rig());
    let (w, h) = sc.image_size();
    let mut csv = String::from("frame,camera,timestamp_ns,dropped\n");
    for c in 0..sc.camera_count() {
        std::fs::create_dir_all(dir.join(format!("cam{c}"))).unwrap();
    }
    for f in 0..FRAMES {
        for c in 0..sc.camera_count() {
            let mut px = vec![0u8; (w * h) as usize];
            let info = sc.render_u8(f, c, &mut px).unwrap();
            writeln!(csv, "{f},{c},{},0", RECORDED_BASE_NS + info.timestamp_ns).unwrap();
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
    (sc, rig)
}

/// The single-board replay of the whole recording: frame → position (mm), status ok.
fn single_board(dir: &std::path::Path, rig: &RigParams) -> BTreeMap<u64, [f64; 3]> {
    let source = ReplaySource::open(&ReplayConfig {
        dir: dir.to_path_buf(),
        speed: ReplaySpeed::Max,
        ..ReplayConfig::default()
    })
    .unwrap();
    let handle = Arc::new(ParamsHandle::new());
    let crc = irtrack_core::params::BlobHeader::parse(&rig.to_blob().unwrap())
        .unwrap()
        .crc32;
    handle.install(ActiveParams {
        rig: rig.clone(),
        crc,
    });
    let status = Arc::new(SharedStatus::new(4, source.describe(), "none".into()));
    let (tx, _rx) = tokio::sync::watch::channel(None);
    let mut engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        handle,
        tx,
        status,
        Duration::from_millis(10),
    );
    let mut out = BTreeMap::new();
    loop {
        match engine.step().unwrap() {
            StepOutcome::Published(r) => {
                if r.status == TrackStatus::Ok {
                    out.insert(r.frame, r.position_mm.unwrap());
                }
            }
            StepOutcome::EndOfStream => break,
            StepOutcome::SourceError => panic!("source error"),
        }
    }
    out
}

fn placed(rig: &RigParams) -> RigParams {
    let mut r = rig.clone();
    r.rig_id = RIG.into();
    r.placement = [("b0", 0), ("b0", 1), ("b1", 0), ("b1", 1)]
        .iter()
        .map(|(b, i)| CameraPlace {
            board: (*b).into(),
            local_index: *i,
        })
        .collect();
    r.validate().unwrap();
    r
}

fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

fn realtime_s() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// A camera board replaying `cameras` of the recording on the shared clock from `start_at`.
async fn camera_board(
    state: &TempDir,
    rec: &std::path::Path,
    name: &str,
    cameras: &[usize],
    port: u16,
    start_at: Option<f64>,
) -> app::Running {
    let mut cfg = test_config(state.path());
    cfg.source.kind = SourceKind::Replay;
    cfg.source.sim = None;
    cfg.source.replay = Some(ReplayConfig {
        dir: rec.to_path_buf(),
        cameras: Some(cameras.to_vec()),
        start_at_unix_s: start_at,
        ..ReplayConfig::default()
    });
    cfg.cluster = ClusterConfig {
        role: Role::Camera,
        rig: RIG.into(),
        board: name.into(),
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        fps: FPS,
        ..ClusterConfig::default()
    };
    app::start(cfg, Overrides::default()).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_boards_started_apart_replay_like_one_board() {
    let rec = TempDir::new("cluster-replay-rec");
    let t0 = std::time::Instant::now();
    let (sc, rig) = record(rec.path());
    let reference = single_board(rec.path(), &rig);
    let truth_rms = {
        let e: Vec<f64> = reference
            .iter()
            .map(|(f, p)| {
                let t = sc.truth(*f).markers()[0].p_cam0_mm;
                dist_mm(*p, [t.x, t.y, t.z])
            })
            .collect();
        (e.iter().map(|e| e * e).sum::<f64>() / e.len() as f64).sqrt()
    };
    println!(
        "recorded {FRAMES} frames × 4 cameras and replayed them on one board in {:.1} s: {} ok positions, RMS {truth_rms:.4} mm against truth",
        t0.elapsed().as_secs_f64(),
        reference.len()
    );
    assert!(reference.len() as u64 > FRAMES * 9 / 10);

    let seed = std::env::var("IRTRACK_REPLAY_SEED")
        .ok()
        .and_then(|s| u64::from_str_radix(s.trim_start_matches("0x"), 16).ok())
        .unwrap_or_else(|| realtime_s().to_bits());
    let mut rng = seed;
    // b1 starts 200–800 ms after b0; the shared start lies between them, so b1 joins late.
    let gap_ms = 200 + splitmix(&mut rng) % 600;
    let start_after_ms = 100 + splitmix(&mut rng) % (gap_ms - 100);
    println!("seed {seed:#x}: b1 starts {gap_ms} ms after b0, the recording {start_after_ms} ms after b0");

    let solver_dir = TempDir::new("cluster-replay-solver");
    let r = placed(&rig);
    std::fs::write(solver_dir.path().join("params.irp"), r.to_blob().unwrap()).unwrap();
    let port = free_tcp_port();
    let mut cfg = test_config(solver_dir.path());
    cfg.cluster = solver_cluster(&r, RIG, port, FPS);
    let solver = app::start(cfg, Overrides::default()).await.unwrap();
    let collector_task = {
        let addr = solver.addrs.stream_ndjson;
        tokio::spawn(async move { NdjsonCollector::start(addr).await })
    };

    let (s0, s1) = (
        TempDir::new("cluster-replay-b0"),
        TempDir::new("cluster-replay-b1"),
    );
    let start_at = realtime_s() + start_after_ms as f64 / 1e3;
    let b0 = camera_board(&s0, rec.path(), "b0", &[0, 1], port, Some(start_at)).await;
    tokio::time::sleep(Duration::from_millis(gap_ms)).await;
    let b1 = camera_board(&s1, rec.path(), "b1", &[2, 3], port, Some(start_at)).await;
    let collector = collector_task.await.unwrap();
    // The recording lasts FRAMES / FPS s from the start instant.
    let end = start_at + FRAMES as f64 / FPS + 0.5;
    tokio::time::sleep(Duration::from_secs_f64((end - realtime_s()).max(0.0))).await;
    let records = collector.finish().await;
    let st1 = status_json(b1.addrs.status).await;
    let solver_status = status_json(solver.addrs.status).await;

    let mut four = Vec::new();
    let mut worst_any = 0.0f64;
    let mut frames_off = 0;
    for rec in records.iter().filter(|r| r.status == TrackStatus::Ok) {
        let p = rec.position_mm.unwrap();
        // Every ok position, from any number of cameras, is near the truth of its frame:
        // the frame number is the recording's.
        let t = sc.truth(rec.frame).markers()[0].p_cam0_mm;
        let e_truth = dist_mm(p, [t.x, t.y, t.z]);
        worst_any = worst_any.max(e_truth);
        if e_truth > 1.0 {
            frames_off += 1;
        }
        if rec.cameras_used == 4
            && let Some(q) = reference.get(&rec.frame)
        {
            four.push(dist_mm(p, *q));
        }
    }
    let ok = records.iter().filter(|r| r.status == TrackStatus::Ok).count();
    let rms = (four.iter().map(|e| e * e).sum::<f64>() / four.len().max(1) as f64).sqrt();
    let worst = four.iter().copied().fold(0.0, f64::max);
    println!(
        "solver: {} records, {ok} ok, {} from four cameras; against the single-board replay RMS {rms:.5} mm, worst {worst:.5} mm; worst ok position against truth {worst_any:.3} mm",
        records.len(),
        four.len()
    );
    println!(
        "b1: {} / dropped {} — {}",
        st1["source"]["sets_delivered"], st1["source"]["sets_dropped"], st1["source"]["description"]
    );
    println!(
        "solver cluster: sets_refused_disagreement {}, sets_board_dropped {}",
        solver_status["cluster"]["sets_refused_disagreement"], solver_status["cluster"]["sets_board_dropped"]
    );
    assert_eq!(
        frames_off, 0,
        "ok positions more than 1 mm off their frame's truth"
    );
    assert!(
        four.len() > 100,
        "only {} four-camera positions: the boards did not pair",
        four.len()
    );
    assert!(
        rms < 0.01 && worst < 0.05,
        "RMS {rms} mm, worst {worst} mm against one board"
    );
    // b1 started after the start instant: it joined where the recording was, passing over
    // the sets already played (counted as dropped), and did not shift.
    assert!(st1["source"]["sets_dropped"].as_u64().unwrap() > 0);
    assert_eq!(solver_status["cluster"]["sets_refused_disagreement"], 0);
    for running in [b0, b1, solver] {
        running.shutdown().await;
    }
}
