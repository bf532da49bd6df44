//! Faults held safely: the real processing loop with the simulated source wrapped in the
//! fault-injecting `FaultySource`. For each fault the loop keeps running, status shows it, no
//! stale, duplicated or wrong position is published, and tracking recovers by itself.

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use irtrack_firmware::leds::indication::Fault as LedFault;
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::faulty::{Fault, FaultySource};
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_sim::Scenario;

#[test]
fn injected_source_faults_never_publish_stale_or_wrong_positions() {
    let cfg = SimSourceConfig {
        paced: false,
        fps: 100.0,
        ..SimSourceConfig::default()
    };
    let truth = Scenario::new(cfg.scenario_config()).unwrap();
    let sim = SimSource::new(&cfg).unwrap();
    let handle = Arc::new(ParamsHandle::new());
    handle.install(ActiveParams {
        rig: sim.scenario().rig().clone(),
        crc: 1,
    });
    const LOST_SETS: u32 = 5;
    let schedule = vec![
        (10, Fault::Drop),
        (20, Fault::Duplicate),
        (30, Fault::Reorder),
        (
            40,
            Fault::Skew {
                camera: 1,
                skew_ns: 5_000_000,
            },
        ),
        (
            50,
            Fault::Disappear {
                camera: 1,
                sets: LOST_SETS,
            },
        ),
        (70, Fault::Duplicate),
    ];
    let source = FaultySource::new(Box::new(sim), schedule);
    let status = Arc::new(SharedStatus::new(2, source.describe(), "none".into()));
    let (tx, rx) = tokio::sync::watch::channel(None);
    let mut engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        handle,
        tx,
        Arc::clone(&status),
        Duration::from_millis(10),
    );

    let mut frames = Vec::new();
    let (mut source_errors, mut fault_seen_in_status) = (0u32, false);
    let mut max_err_mm: f64 = 0.0;
    for _ in 0..90 {
        match engine.step().unwrap() {
            StepOutcome::Published(r) => {
                if r.status == TrackStatus::Ok {
                    let p = r.position_mm.unwrap();
                    let t = truth.truth(r.frame).markers()[0].p_cam0_mm;
                    let e = ((p[0] - t.x).powi(2) + (p[1] - t.y).powi(2) + (p[2] - t.z).powi(2)).sqrt();
                    max_err_mm = max_err_mm.max(e);
                    assert!(e < 1.0, "frame {}: {e} mm from truth", r.frame);
                } else {
                    assert!(r.position_mm.is_none(), "frame {}: position without Ok", r.frame);
                }
                frames.push(r.frame);
            }
            StepOutcome::SourceError => {
                source_errors += 1;
                // While the camera is gone: fault in status and on the Fault LED, and the
                // latest record carries no position.
                fault_seen_in_status |= status.camera_lost.load(Ordering::Relaxed)
                    && status.top_fault() == Some(LedFault::CameraLost);
                let latest = rx.borrow().unwrap();
                assert_eq!(latest.status, TrackStatus::Fault);
                assert!(latest.position_mm.is_none());
            }
            StepOutcome::EndOfStream => panic!("sim ended"),
        }
    }
    assert_eq!(
        source_errors, LOST_SETS,
        "camera loss lasts the injected number of sets"
    );
    assert!(
        fault_seen_in_status,
        "camera loss not shown in status/LED indication"
    );
    // Recovered: fault cleared, tracking again.
    assert!(!status.camera_lost.load(Ordering::Relaxed));
    assert_eq!(status.top_fault(), None);
    assert_eq!(rx.borrow().unwrap().status, TrackStatus::Ok);
    // Published frame numbers strictly increase: duplicates and the late set were dropped.
    assert!(
        frames.windows(2).all(|w| w[0] < w[1]),
        "frames not monotonic: {frames:?}"
    );
    assert_eq!(
        status.stale_sets.load(Ordering::Relaxed),
        3,
        "2 duplicates + 1 reordered"
    );
    // Skew is visible in status.
    assert!(status.pairing_error_max_ns.load(Ordering::Relaxed) >= 5_000_000);
    println!(
        "faults: {} records published, max error {max_err_mm:.3} mm, {} stale sets dropped, {source_errors} camera-lost sets",
        frames.len(),
        status.stale_sets.load(Ordering::Relaxed)
    );
}
