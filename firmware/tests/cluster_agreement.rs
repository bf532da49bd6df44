//! Never a confident wrong position across boards (docs/cluster.md, "Do the boards agree?").
//!
//! The solver runs in process; camera boards simulated by this test publish observations of a
//! marker moving on a known path over real Zenoh sessions on 127.0.0.1, each board at its own
//! random phase within the frame period (free-running cameras). One board is made wrong: its
//! clock off (timestamps later than the exposures), or its frames one frame late against
//! honest timestamps (a replay started at another moment, a frame paired with its
//! neighbour), or its camera moved since calibration. Every published `ok` position is
//! compared with the path at the record's instant; `/status` and `/metrics` must name the
//! board and the likely cause. A healthy cell must keep publishing every set.
#![cfg(feature = "cluster")]

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use common::*;
use irtrack_cluster::transport::{ObsPublisher, Session, TransportConfig, realtime_ns};
use irtrack_core::observation::{ObsBlob, ObsClock, ObsHeader};
use irtrack_core::params::{CameraPlace, RigParams};
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_firmware::app::{self, Overrides};

use irtrack_firmware::source::sim::ring_rig;
use nalgebra::Vector3;

const RIG: &str = "agree";
const FPS: f64 = 30.0;
const PERIOD_NS: u64 = (1e9 / FPS) as u64;

/// The marker's path (camera-0 frame, mm) at `t_s` seconds from the test's epoch: a tilted
/// circle of 100 mm radius around the ring's centre, one turn per second (about 0.6 m/s).
fn path(t_s: f64, moving: bool) -> Vector3<f64> {
    if !moving {
        return Vector3::new(15.0, -10.0, 590.0);
    }
    let w = std::f64::consts::TAU * t_s;
    Vector3::new(100.0 * w.cos(), 40.0 * w.sin(), 600.0 + 100.0 * w.sin())
}

/// One simulated camera board.
#[derive(Clone)]
struct Board {
    name: &'static str,
    /// Rig camera of each of its cameras (its local index is the position here).
    cameras: Vec<usize>,
    /// Its clock minus the true time, ns (added to every timestamp it sends).
    clock_error_ns: i64,
    /// Its frames show the marker this long after their exposure instant, ns (a frame late
    /// against honest timestamps: negative).
    content_shift_ns: i64,
    /// Added to its blobs' x (px): a camera moved since calibration.
    offset_px: f32,
}

fn board(name: &'static str, cameras: &[usize]) -> Board {
    Board {
        name,
        cameras: cameras.to_vec(),
        clock_error_ns: 0,
        content_shift_ns: 0,
        offset_px: 0.0,
    }
}

fn placed_ring(boards: &[Board]) -> RigParams {
    let n: usize = boards.iter().map(|b| b.cameras.len()).sum();
    let mut r = ring_rig(n, 600.0);
    r.rig_id = RIG.into();
    r.placement = vec![
        CameraPlace {
            board: String::new(),
            local_index: 0,
        };
        n
    ];
    for b in boards {
        for (i, &c) in b.cameras.iter().enumerate() {
            r.placement[c] = CameraPlace {
                board: b.name.into(),
                local_index: i as u8,
            };
        }
    }
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

/// Publishes `b`'s observations from `epoch_rt_ns + phase_ns` on, one frame per period, until
/// `stop`.
fn run_board(
    port: u16,
    r: RigParams,
    b: Board,
    moving: bool,
    epoch_rt_ns: u64,
    phase_ns: u64,
    stop: Arc<AtomicBool>,
) {
    let tc = TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    };
    let session = Session::open(&tc).unwrap();
    let mut pubs: Vec<ObsPublisher> = (0..b.cameras.len())
        .map(|i| ObsPublisher::new(&session, RIG, b.name, i).unwrap())
        .collect();
    let mut k = 0u64;
    while !stop.load(Ordering::Relaxed) && k < (60.0 * FPS) as u64 {
        let t_rt = epoch_rt_ns + phase_ns + k * PERIOD_NS;
        let now = realtime_ns();
        if t_rt > now {
            std::thread::sleep(Duration::from_nanos(t_rt - now));
        }
        k += 1;
        let seen_ns = t_rt as i64 + b.content_shift_ns - epoch_rt_ns as i64;
        let p = path(seen_ns as f64 / 1e9, moving);
        let stamp = (t_rt as i64 + b.clock_error_ns) as u64;
        for (i, &c) in b.cameras.iter().enumerate() {
            let cam = &r.cameras[c];
            let px = cam.model.project(&cam.cam_from_cam0.apply(&p)).unwrap();
            let blob = ObsBlob {
                x_px: px.x as f32 + b.offset_px,
                y_px: px.y as f32,
                area_px: 9,
                peak_dn: 200,
                roundness: 1.0,
                touches_frame_edge: false,
                touches_roi_edge: false,
                saturated: false,
            };
            let header = ObsHeader {
                rig: RIG,
                board: b.name,
                camera: i as u8,
                sequence: k,
                trigger_count: None,
                capture_ts_ns: stamp,
                clock: ObsClock::Realtime,
                exposure_us: 0,
                dropped: 0,
                send_delay_us: 0,
            };
            pubs[i].publish(&header, &[blob]).unwrap();
        }
    }
    session.close();
}

/// What one cell's run gave.
struct Run {
    records: Vec<PositionRecord>,
    /// Error (mm) of each `ok` record against the path at its instant.
    errors_mm: Vec<f64>,
    status: serde_json::Value,
    metrics: Metrics,
}

impl Run {
    fn ok_share(&self) -> f64 {
        let ok = self
            .records
            .iter()
            .filter(|r| r.status == TrackStatus::Ok)
            .count();
        ok as f64 / self.records.len().max(1) as f64
    }
    fn worst_mm(&self) -> f64 {
        self.errors_mm.iter().copied().fold(0.0, f64::max)
    }
    fn board(&self, name: &str) -> &serde_json::Value {
        self.status["cluster"]["boards"]
            .as_array()
            .unwrap()
            .iter()
            .find(|b| b["name"] == name)
            .unwrap_or_else(|| panic!("no board {name} in {}", self.status["cluster"]))
    }
    fn faults(&self) -> Vec<String> {
        self.status["fault_texts"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| {
                format!(
                    "{}: {}",
                    f["code"].as_str().unwrap_or(""),
                    f["message"].as_str().unwrap_or("")
                )
            })
            .collect()
    }
}

/// Runs a cell of `boards` (random phases from `seed`) for `seconds` after one second of
/// warm-up and returns the records of that span with their errors.
///
/// Phases are drawn over a whole period, or within half of one with `close` (three or more
/// boards spread over a whole period fall into different sets: pairing takes observations
/// within half a period of a set's first one).
async fn run_cell(test: &str, boards: &[Board], moving: bool, close: bool, seed: u64, seconds: f64) -> Run {
    let dir = TempDir::new(test);
    let r = placed_ring(boards);
    std::fs::write(dir.path().join("params.irp"), r.to_blob().unwrap()).unwrap();
    let port = free_tcp_port();
    let mut cfg = test_config(dir.path());
    cfg.cluster = solver_cluster(&r, RIG, port, FPS);
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    // Every board's session is open before the first frame (Zenoh may take 0.5 s or more to
    // start a session, more under load): a board that joins late is another scenario (while
    // it is missing, two one-camera boards' rays always "meet", and that agreement kept a
    // moved camera from being named in about one run in ten under load; docs/cluster.md).
    let epoch = realtime_ns() + 1_000_000_000;
    let mut rng = seed;
    let mut threads = Vec::new();
    let mut phases = Vec::new();
    for b in boards {
        let phase = splitmix(&mut rng) % if close { PERIOD_NS / 2 } else { PERIOD_NS };
        phases.push(format!("{} {:.2} ms", b.name, phase as f64 / 1e6));
        let (r, b, stop) = (r.clone(), b.clone(), stop.clone());
        threads.push(std::thread::spawn(move || {
            run_board(port, r, b, moving, epoch, phase, stop)
        }));
    }
    println!("{test}: seed {seed:#x}, phases {phases:?}");
    tokio::time::sleep(Duration::from_millis(2000)).await;
    let collector = NdjsonCollector::start(running.addrs.stream_ndjson).await;
    tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
    let status = status_json(running.addrs.status).await;
    let metrics = scrape_metrics(running.addrs.status).await;
    let records = collector.finish().await;
    stop.store(true, Ordering::Relaxed);
    for t in threads {
        t.join().unwrap();
    }
    // The records' instants are on this process's CLOCK_MONOTONIC.
    let rt_minus_mono = realtime_ns() as i128 - irtrack_firmware::clock::monotonic_ns() as i128;
    let errors_mm = records
        .iter()
        .filter(|r| r.status == TrackStatus::Ok)
        .map(|rec| {
            let rt = rec.capture_ts_ns as i128 + rt_minus_mono;
            let p = path((rt - epoch as i128) as f64 / 1e9, moving);
            dist_mm(rec.position_mm.unwrap(), [p.x, p.y, p.z])
        })
        .collect();
    Run {
        records,
        errors_mm,
        status,
        metrics,
    }
}

fn seed() -> u64 {
    std::env::var("IRTRACK_AGREEMENT_SEED")
        .ok()
        .and_then(|s| u64::from_str_radix(s.trim_start_matches("0x"), 16).ok())
        .unwrap_or_else(realtime_ns)
}

fn summary(name: &str, run: &Run) {
    let ok = run.records.iter().filter(|r| r.status == TrackStatus::Ok).count();
    let rms = (run.errors_mm.iter().map(|e| e * e).sum::<f64>() / run.errors_mm.len().max(1) as f64).sqrt();
    println!(
        "{name}: {} records, {ok} ok ({:.1} %), RMS {rms:.3} mm, worst {:.3} mm; compared {}, refused {}, board dropped {}",
        run.records.len(),
        100.0 * run.ok_share(),
        run.worst_mm(),
        run.status["cluster"]["sets_compared"],
        run.status["cluster"]["sets_refused_disagreement"],
        run.status["cluster"]["sets_board_dropped"],
    );
    for b in run.status["cluster"]["boards"].as_array().unwrap() {
        println!(
            "  board {}: disagreeing {}, share {:.2}, disagreed {}/{}, dropped {}, miss {} mm / {} px, shift {} ms, cause {}, with {}, clock offset {} ms",
            b["name"],
            b["disagreeing"],
            b["disagreement_share"].as_f64().unwrap_or(f64::NAN),
            b["disagreed_sets"],
            b["compared_sets"],
            b["dropped_sets"],
            b["miss_mm"],
            b["miss_px"],
            b["time_shift_ms"],
            b["likely_cause"],
            b["disagrees_with"],
            b["clock_offset_ms"]
        );
    }
    for f in run.faults() {
        println!("  fault {f}");
    }
}

/// Every `ok` position within this of the path (the tracker's own ray gate is 3 mm).
const LIMIT_MM: f64 = 3.0;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_healthy_two_board_cell_publishes_every_set() {
    let boards = [board("b0", &[0, 1]), board("b1", &[2, 3])];
    let run = run_cell("agree-healthy", &boards, true, false, seed(), 4.0).await;
    summary("healthy", &run);
    assert!(
        run.records.len() as f64 >= 3.0 * FPS,
        "{} records",
        run.records.len()
    );
    assert!(run.ok_share() >= 0.98, "only {:.1} % ok", 100.0 * run.ok_share());
    let four = run.records.iter().filter(|r| r.cameras_used == 4).count();
    assert!(
        four as f64 >= 0.98 * run.records.len() as f64,
        "{four} of {} from four cameras",
        run.records.len()
    );
    // Measured over 8 runs (2026-11-28): worst 0.13–0.51 mm, RMS 0.09–0.31 mm; the error of a
    // run is mostly one bias, the solver's estimate of the boards' clock offsets (−0.2 to
    // −0.3 ms here) times the marker's speed. 0.5 mm failed once in CI-like runs.
    assert!(run.worst_mm() < 1.0, "worst {} mm", run.worst_mm());
    assert_eq!(run.status["cluster"]["sets_refused_disagreement"], 0);
    for b in ["b0", "b1"] {
        assert_eq!(run.board(b)["disagreeing"], false, "{b}");
    }
    assert!(
        !run.faults().iter().any(|f| f.starts_with("board_disagrees")),
        "{:?}",
        run.faults()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_board_with_a_wrong_clock_is_named_and_left_out() {
    // b1's clock 10 ms ahead: inside the pairing tolerance (16.7 ms at 30 fps), so its frames
    // pair and its clock is not faulted, but its timestamps say 10 ms later than its
    // exposures — 6 mm of the marker's motion.
    let mut b1 = board("b1", &[2, 3]);
    b1.clock_error_ns = 10_000_000;
    let boards = [board("b0", &[0, 1]), b1];
    let run = run_cell("agree-clock", &boards, true, false, seed(), 4.0).await;
    summary("wrong clock", &run);
    for (r, e) in run
        .records
        .iter()
        .filter(|r| r.status == TrackStatus::Ok)
        .zip(&run.errors_mm)
        .filter(|(_, e)| **e > 1.0)
        .take(5)
    {
        println!(
            "  {:?} {} cams gap {} err {e}",
            r.position_mm, r.cameras_used, r.gap_mm
        );
    }
    assert!(
        run.worst_mm() < LIMIT_MM,
        "an ok position {} mm off",
        run.worst_mm()
    );
    let b1 = run.board("b1");
    assert_eq!(b1["disagreeing"], true, "{b1}");
    assert_eq!(b1["clock_fault"], false, "inside the clock limit: {b1}");
    assert_eq!(b1["likely_cause"], "clock", "{b1}");
    let shift = b1["time_shift_ms"].as_f64().unwrap();
    assert!(
        (shift + 10.0).abs() < 2.0,
        "time shift {shift} ms (its frames 10 ms earlier than stamped)"
    );
    assert_eq!(run.board("b0")["disagreeing"], false);
    let faults = run.faults();
    assert!(
        faults.iter().any(|f| f.starts_with("board_disagrees")
            && f.contains("camera board b1")
            && f.contains("clock")),
        "{faults:?}"
    );
    // b0's two cameras still give positions (b1's measured offset tells which board is off).
    assert!(run.ok_share() > 0.8, "{:.1} % ok", 100.0 * run.ok_share());
    let m = &run.metrics;
    assert_eq!(
        m.value("irtrackd_cluster_board_disagreeing", &[("board", "b1")]),
        Some(1.0)
    );
    assert_eq!(
        m.value("irtrackd_cluster_board_disagreeing", &[("board", "b0")]),
        Some(0.0)
    );
    assert!(
        m.value("irtrackd_cluster_board_dropped_sets_total", &[("board", "b1")])
            .is_some_and(|n| n > 0.0)
    );
    let shift_s = m
        .value("irtrackd_cluster_board_time_shift_seconds", &[("board", "b1")])
        .unwrap();
    assert!((shift_s + 0.010).abs() < 0.002, "{shift_s}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn boards_a_frame_apart_give_no_position_and_are_both_named() {
    // The case: clocks right, but b1's frames are a frame older than their stamps (a
    // replay restarted at another moment, a frame paired with its neighbour). No measured
    // clock offset says which board is wrong: neither gives positions.
    let mut b1 = board("b1", &[2, 3]);
    b1.content_shift_ns = -(PERIOD_NS as i64);
    let boards = [board("b0", &[0, 1]), b1];
    let run = run_cell("agree-frame", &boards, true, false, seed(), 4.0).await;
    summary("a frame apart", &run);
    assert!(
        run.worst_mm() < LIMIT_MM,
        "an ok position {} mm off",
        run.worst_mm()
    );
    for (b, peer) in [("b0", "b1"), ("b1", "b0")] {
        let st = run.board(b);
        assert_eq!(st["disagreeing"], true, "{st}");
        assert_eq!(st["disagrees_with"], peer, "{st}");
    }
    assert_eq!(run.board("b1")["likely_cause"], "clock");
    let shift = run.board("b1")["time_shift_ms"].as_f64().unwrap();
    assert!(
        (shift + 1e3 / FPS).abs() < 5.0,
        "b1's shift {shift} ms, a frame is {} ms",
        1e3 / FPS
    );
    let faults = run.faults();
    assert!(
        faults
            .iter()
            .any(|f| f.contains("camera boards b0 and b1 disagree")
                || f.contains("camera boards b1 and b0 disagree")),
        "{faults:?}"
    );
    let refused = run.status["cluster"]["sets_refused_disagreement"]
        .as_u64()
        .unwrap();
    assert!(refused > 0, "no set refused");
    assert!(
        run.metrics
            .value("irtrackd_cluster_sets_refused_disagreement_total", &[])
            .is_some_and(|n| n >= refused as f64)
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_majority_drops_a_board_a_frame_late() {
    // Three boards: b2's camera a frame late. b0 and b1 agree: positions go on from their
    // three cameras, b2 is named and left out.
    let mut b2 = board("b2", &[3]);
    b2.content_shift_ns = -(PERIOD_NS as i64);
    let boards = [board("b0", &[0, 1]), board("b1", &[2]), b2];
    let run = run_cell("agree-majority", &boards, true, true, seed(), 4.0).await;
    summary("majority", &run);
    assert!(
        run.worst_mm() < LIMIT_MM,
        "an ok position {} mm off",
        run.worst_mm()
    );
    assert!(run.ok_share() > 0.9, "{:.1} % ok", 100.0 * run.ok_share());
    let three = run
        .records
        .iter()
        .filter(|r| r.status == TrackStatus::Ok && r.cameras_used == 3)
        .count();
    assert!(
        three as f64 > 0.9 * run.records.len() as f64,
        "{three} from three cameras"
    );
    let b2 = run.board("b2");
    assert_eq!(b2["disagreeing"], true, "{b2}");
    assert!(b2["disagrees_with"].is_null(), "outvoted, not a pair: {b2}");
    assert_eq!(b2["likely_cause"], "clock");
    for b in ["b0", "b1"] {
        assert_eq!(run.board(b)["disagreeing"], false, "{b}");
    }
    assert!(run.board("b2")["dropped_sets"].as_u64().unwrap() > 0);
    assert!(
        run.faults()
            .iter()
            .any(|f| f.starts_with("board_disagrees: camera board b2 (camera 3)")),
        "{:?}",
        run.faults()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_moved_camera_on_a_still_marker_is_a_calibration_fault() {
    // The marker stands still; b2's camera sees it 8 px off (moved since calibration).
    let mut b2 = board("b2", &[3]);
    b2.offset_px = 8.0;
    let boards = [board("b0", &[0, 1]), board("b1", &[2]), b2];
    let run = run_cell("agree-calibration", &boards, false, true, seed(), 3.0).await;
    summary("moved camera", &run);
    for r in run.records.iter().filter(|r| r.status == TrackStatus::Ok).take(5) {
        println!("  {:?} {} cams gap {}", r.position_mm, r.cameras_used, r.gap_mm);
    }
    assert!(
        run.worst_mm() < LIMIT_MM,
        "an ok position {} mm off",
        run.worst_mm()
    );
    let b2 = run.board("b2");
    assert_eq!(b2["disagreeing"], true, "{b2}");
    assert_eq!(b2["likely_cause"], "calibration", "{b2}");
    assert!(
        run.faults()
            .iter()
            .any(|f| f.starts_with("board_disagrees: camera board b2") && f.contains("calibration")),
        "{:?}",
        run.faults()
    );
    assert!(run.ok_share() > 0.9);
}
