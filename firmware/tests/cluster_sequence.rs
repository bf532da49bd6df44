//! Sequence numbers across boards (issue 40): an observation whose sequence jumps absurdly far
//! ahead is refused and counted (`cluster.refused.sequence_jump`) without locking the real
//! camera out; a board that restarts and counts from 1 again within the board timeout is
//! recognised as restarted (its sequences go back, its capture times go on); the solver's
//! `frame` is the boards' frame counter.
#![cfg(feature = "cluster")]

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use common::*;
use irtrack_cluster::transport::{ObsPublisher, Session, TransportConfig, realtime_ns};
use irtrack_core::observation::ObsBlob;
use irtrack_core::params::RigParams;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};
use nalgebra::Vector3;

const RIG: &str = "seq";
const FPS: f64 = 30.0;
const PERIOD_NS: u64 = (1e9 / FPS) as u64;

/// The phases of the run, driven by the boards' thread.
const FORGE_AT: u64 = 30;
const RESTART_AT: u64 = 60;

/// Boards b0 (cameras 0, 1) and b1 (camera 0) publishing a still point, frame `k` captured at
/// `epoch + k·period` with sequence `k`. At frame `FORGE_AT` a forger publishes as b0's
/// camera 0 with sequence 2^64−1 and with `k + 1 000 000` (a blob far off); at `RESTART_AT`
/// b1 stops for 100 ms (under the 300 ms board timeout) and starts counting from 1 again.
fn boards(
    port: u16,
    r: RigParams,
    p: Vector3<f64>,
    epoch: u64,
    stop: Arc<AtomicBool>,
    frame: Arc<AtomicU64>,
) {
    let tc = TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    };
    let (s0, s1, forger) = (
        Session::open(&tc).unwrap(),
        Session::open(&tc).unwrap(),
        Session::open(&tc).unwrap(),
    );
    let mut c00 = ObsPublisher::new(&s0, RIG, "b0", 0).unwrap();
    let mut c01 = ObsPublisher::new(&s0, RIG, "b0", 1).unwrap();
    let mut c10 = ObsPublisher::new(&s1, RIG, "b1", 0).unwrap();
    let mut forged = ObsPublisher::new(&forger, RIG, "b0", 0).unwrap();
    let blobs = [obs_blob(&r, 0, &p), obs_blob(&r, 1, &p), obs_blob(&r, 2, &p)];
    let far = [ObsBlob {
        x_px: 20.0,
        y_px: 20.0,
        ..blobs[0]
    }];
    let start = Instant::now();
    let mut b1_seq = 0u64;
    let mut k = 0u64;
    while !stop.load(Ordering::Relaxed) && start.elapsed() < Duration::from_secs(60) {
        k += 1;
        let ts = epoch + k * PERIOD_NS;
        std::thread::sleep(Duration::from_nanos(ts.saturating_sub(realtime_ns())));
        frame.store(k, Ordering::Relaxed);
        if k == FORGE_AT {
            forged
                .publish(&obs_header(RIG, "b0", 0, u64::MAX, ts), &far)
                .unwrap();
            forged
                .publish(&obs_header(RIG, "b0", 0, k + 1_000_000, ts), &far)
                .unwrap();
        }
        c00.publish(&obs_header(RIG, "b0", 0, k, ts), &blobs[..1])
            .unwrap();
        c01.publish(&obs_header(RIG, "b0", 1, k, ts), &blobs[1..2])
            .unwrap();
        if k == RESTART_AT {
            // b1's irtrackd restarts: 100 ms silent, then its counter starts again at 1.
            std::thread::sleep(Duration::from_millis(100));
            b1_seq = 0;
            continue;
        }
        if (RESTART_AT..RESTART_AT + 4).contains(&k) {
            continue;
        }
        b1_seq += 1;
        c10.publish(&obs_header(RIG, "b1", 0, b1_seq, ts), &blobs[2..])
            .unwrap();
    }
    for s in [s0, s1, forger] {
        s.close();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sequence_jumps_are_refused_and_restarts_recognised() {
    let dir = TempDir::new("cluster-sequence");
    let r = placed_ring(RIG, &[("b0", 0), ("b0", 1), ("b1", 0)]);
    std::fs::write(dir.path().join("params.irp"), r.to_blob().unwrap()).unwrap();
    let port = free_tcp_port();
    let mut cfg = test_config(dir.path());
    cfg.cluster = solver_cluster(&r, RIG, port, FPS);
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let p = Vector3::new(20.0, -15.0, 600.0);
    let stop = Arc::new(AtomicBool::new(false));
    let frame = Arc::new(AtomicU64::new(0));
    let epoch = realtime_ns() + 300_000_000;
    let t = {
        let (r, stop, frame) = (r.clone(), stop.clone(), frame.clone());
        std::thread::spawn(move || boards(port, r, p, epoch, stop, frame))
    };
    // Collect from before the forgery to well after the restart.
    while frame.load(Ordering::Relaxed) < FORGE_AT - 15 {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let collector = NdjsonCollector::start(running.addrs.stream_ndjson).await;
    while frame.load(Ordering::Relaxed) < RESTART_AT + 40 {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(400)).await;
    let status = status_json(running.addrs.status).await;
    let metrics = scrape_metrics(running.addrs.status).await;
    let records = collector.finish().await;
    stop.store(true, Ordering::Relaxed);
    t.join().unwrap();

    let cl = &status["cluster"];
    println!(
        "refused {}, senders {}, sequence_restarts {}",
        cl["refused"], cl["refused_senders"], cl["sequence_restarts"]
    );
    assert_eq!(
        cl["refused"]["sequence_jump"], 2,
        "both forged jumps refused and counted"
    );
    assert!(
        cl["refused"].get("duplicate_sequence").is_none(),
        "no real observation refused as a duplicate"
    );
    assert_eq!(cl["sequence_restarts"], 1, "b1's restart recognised once");
    assert!(
        cl["refused_senders"]
            .as_array()
            .unwrap()
            .iter()
            .any(|s| s[0] == "b0" && s[2] == "sequence_jump"),
        "the sender is named"
    );
    assert_eq!(
        metrics
            .value(
                "irtrackd_cluster_observations_refused_total",
                &[("reason", "sequence_jump")]
            )
            .unwrap_or(0.0),
        2.0
    );

    // Positions: every ok one at the point; after the forgery b0's camera 0 still counts, and
    // after b1's restart its camera is back. The record's frame is the boards' counter k:
    // its instant is epoch + k·period.
    let rt_minus_mono = realtime_ns() as i128 - irtrack_firmware::clock::monotonic_ns() as i128;
    let mut three_after_forgery = 0;
    let mut three_after_restart = 0;
    let mut after_forgery = 0;
    for rec in &records {
        let k = ((rec.capture_ts_ns as i128 + rt_minus_mono - epoch as i128) as f64 / PERIOD_NS as f64)
            .round() as u64;
        if rec.status == TrackStatus::Ok {
            assert_eq!(rec.frame, k, "the solver's frame is the boards' frame counter");
            let e = dist_mm(rec.position_mm.unwrap(), [p.x, p.y, p.z]);
            assert!(e < 0.5, "frame {}: {e} mm off", rec.frame);
        }
        if rec.frame > FORGE_AT && rec.frame < RESTART_AT {
            after_forgery += 1;
            three_after_forgery += usize::from(rec.cameras_used == 3);
        }
        if rec.frame > RESTART_AT + 8 {
            three_after_restart += usize::from(rec.cameras_used == 3);
        }
    }
    println!(
        "{} records; frames {FORGE_AT}..{RESTART_AT}: {three_after_forgery} of {after_forgery} from three cameras; after b1's restart: {three_after_restart} from three cameras",
        records.len()
    );
    assert!(
        three_after_forgery + 2 >= after_forgery && after_forgery > 20,
        "the forged sequences locked a camera out"
    );
    assert!(
        three_after_restart >= 20,
        "b1's camera did not come back after its restart"
    );
    running.shutdown().await;
}
