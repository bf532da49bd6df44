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

/// The processing loop over the simulated source (100 fps, unpaced, its own rig as the
/// parameter set) with `schedule` injected, and the truth of the same scenario.
struct Rig {
    engine: Engine,
    rx: tokio::sync::watch::Receiver<Option<irtrack_core::stream::PositionRecord>>,
    status: Arc<SharedStatus>,
    truth: Scenario,
}

fn rig(schedule: Vec<(u64, Fault)>) -> Rig {
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
    let source = FaultySource::new(Box::new(sim), schedule);
    let status = Arc::new(SharedStatus::new(2, source.describe(), "none".into()));
    let (tx, rx) = tokio::sync::watch::channel(None);
    let engine = Engine::new(
        Box::new(source),
        TrackerConfig::default(),
        handle,
        tx,
        Arc::clone(&status),
        Duration::from_millis(10),
    );
    Rig {
        engine,
        rx,
        status,
        truth,
    }
}

#[test]
fn injected_source_faults_never_publish_stale_or_wrong_positions() {
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
    let Rig {
        mut engine,
        rx,
        status,
        truth,
    } = rig(schedule);

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

/// One published record: frame, status, error vs truth (mm) when it had a position.
type Published = (u64, TrackStatus, Option<f64>);

/// Runs `sets` sets through the engine with `schedule` injected.
fn run_with_faults(schedule: Vec<(u64, Fault)>, sets: usize) -> (Vec<Published>, Arc<SharedStatus>) {
    let Rig {
        mut engine,
        status,
        truth,
        ..
    } = rig(schedule);
    let mut out = Vec::new();
    for _ in 0..sets {
        if let StepOutcome::Published(r) = engine.step().unwrap() {
            let err = r.position_mm.map(|p| {
                let t = truth.truth(r.frame).markers()[0].p_cam0_mm;
                ((p[0] - t.x).powi(2) + (p[1] - t.y).powi(2) + (p[2] - t.z).powi(2)).sqrt()
            });
            assert!(
                err.is_none() || r.status == TrackStatus::Ok,
                "frame {}: position without Ok",
                r.frame
            );
            out.push((r.frame, r.status, err));
        }
    }
    (out, status)
}

fn in_window(frame: u64, start: u64, len: u64) -> bool {
    (start..start + len).contains(&frame)
}

/// A reflection (second spot moving with the marker), a partly covered spot and a spot hidden
/// from one camera: no wrong position goes out, each stretch is visible in the records, and
/// tracking resumes by itself.
#[test]
fn reflections_and_occlusions_never_publish_a_wrong_position() {
    const LEN: u32 = 25;
    let schedule = vec![
        (
            10,
            Fault::Reflection {
                camera: 1,
                sets: LEN,
                du_px: 45,
                dv_px: 30,
            },
        ),
        (
            50,
            Fault::Reflection {
                camera: 0,
                sets: LEN,
                du_px: -60,
                dv_px: 0,
            },
        ),
        (90, Fault::HalfOccluded { camera: 0, sets: LEN }),
        (130, Fault::Hidden { camera: 1, sets: LEN }),
    ];
    let (records, status) = run_with_faults(schedule, 180);
    // Records in each stretch (the sim's frame number equals the request number here: no
    // frame drops, one set per request).
    let stretch = |start: u64| -> Vec<&Published> {
        records
            .iter()
            .filter(|r| in_window(r.0, start, u64::from(LEN)))
            .collect()
    };
    let summary = |name: &str, start: u64| {
        let s = stretch(start);
        let ok: Vec<f64> = s.iter().filter_map(|r| r.2).collect();
        let max = ok.iter().copied().fold(0.0f64, f64::max);
        println!(
            "{name}: {} sets, {} with a position (max error {max:.3} mm), others {:?}",
            s.len(),
            ok.len(),
            s.iter()
                .filter(|r| r.2.is_none())
                .map(|r| r.1)
                .collect::<Vec<_>>()
        );
        (s.len(), ok.len(), max)
    };
    let (n1, ok1, max1) = summary("reflection in camera 1, off the epipolar line", 10);
    // On (or near) the epipolar line the tracker may refuse the set as ambiguous instead of
    // guessing; it must never pick the reflection.
    let (n2, _, max2) = summary("reflection in camera 0, same image row", 50);
    let (n3, _, max3) = summary("left half of the spot covered in camera 0", 90);
    let (n4, ok4, _) = summary("spot hidden from camera 1", 130);
    assert!(n1 >= 20 && n2 >= 20 && n3 >= 20 && n4 >= 20);
    // A reflection's ray misses the other camera's ray: the true pair wins.
    assert!(
        ok1 * 10 >= n1 * 9,
        "reflection off the epipolar line lost the marker"
    );
    assert!(
        max1 < 1.0 && max2 < 1.0,
        "reflection pulled the position: {max1} / {max2} mm"
    );
    // A half-covered spot shifts its centroid by about a pixel: either the quality gate refuses
    // the set or the position stays within a few tenths of a millimetre per pixel of shift.
    assert!(max3 < 2.0, "half-occluded spot gave a position {max3} mm off");
    // Hidden from one camera: no position at all, records say Lost.
    assert_eq!(ok4, 0, "a position from one camera");
    // Every published position anywhere in the run was near the truth.
    let worst = records.iter().filter_map(|r| r.2).fold(0.0f64, f64::max);
    assert!(worst < 2.0, "worst published error {worst} mm");
    // Recovered after the last fault.
    let tail: Vec<_> = records.iter().filter(|r| r.0 >= 160).collect();
    assert!(
        tail.len() >= 15 && tail.iter().all(|r| r.1 == TrackStatus::Ok),
        "{tail:?}"
    );
    assert!(status.lost.load(Ordering::Relaxed) >= u64::from(LEN) - 1);
}

/// Camera timestamps further apart than the allowed pairing error: no position for that set,
/// counted in status; the next good set tracks again.
#[test]
fn skewed_timestamps_are_refused() {
    let schedule = vec![(
        20,
        Fault::Skew {
            camera: 1,
            // Solved at one instant, a set may spread up to `max_bridge_ms` (25 ms; a 5 ms skew
            // is bridged, see the test above); beyond it the set is refused.
            skew_ns: 30_000_000,
        },
    )];
    let (records, status) = run_with_faults(schedule, 40);
    let skewed = records.iter().find(|r| r.0 == 20).expect("skewed set published");
    assert_eq!(skewed.1, TrackStatus::Rejected);
    assert!(skewed.2.is_none());
    assert_eq!(status.skewed_sets.load(Ordering::Relaxed), 1);
    assert!(
        records
            .iter()
            .filter(|r| r.0 > 20)
            .all(|r| r.1 == TrackStatus::Ok)
    );
    let report = serde_json::to_value(status.report()).unwrap();
    assert_eq!(report["processing"]["skewed_sets"], 1);
}
