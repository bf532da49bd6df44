//! 6-DOF end to end: a rotating 4-LED tool rendered by the simulator in the convergent 90° VGA
//! rig at 1 m → `BlobDetector` + `PoseTracker` per frame → `PositionRecord` with orientation in
//! the world (robot) frame → the socket robot link (`irtrack_robot::LinkHandle`) (safety supervisor, `Q` lines) →
//! `SimRobotServer` on 127.0.0.1. The targets the robot received are compared with the
//! simulator's ground truth; the figures are printed (`cargo test -p irtrack-tests --test
//! sixdof_e2e -- --nocapture`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits};
use irtrack_core::camera::RigidTransform;
use irtrack_core::image::GrayImage;
use irtrack_core::params::ToolDefinition;
use irtrack_core::pose6d::{PoseConfig, PoseStatus, PoseTracker, quaternion_angle_rad};
use irtrack_core::robot_proto::HoldReason;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_robot::deadman::NoDeadman;
use irtrack_robot::sim::{SimRobotServer, SimServerConfig};
use irtrack_robot::sim_robot::SimRobotConfig;
use irtrack_robot::{Clock, DeadmanConfig, LinkHandle, LinkState, RobotConfig, RobotLink, SafetyConfig};
use irtrack_sim::{FrameTruth, Orientation, RigPreset, Scenario, SimConfig, Trajectory};
use nalgebra::{Rotation3, UnitQuaternion, Vector3};
use tokio::sync::watch;

const FRAMES: u64 = 720;
const MAX_ROTATION_STEP_DEG: f64 = 15.0;
const MAX_STEP_MM: f64 = 20.0;

/// The asymmetric, non-planar test tool of docs/six-dof.md (identification margin 13.9 mm).
fn probe4() -> ToolDefinition {
    ToolDefinition {
        name: "probe4".into(),
        leds_mm: vec![
            [0.0, 0.0, 0.0],
            [99.0, 0.0, 0.0],
            [3.0, 85.0, 0.0],
            [62.0, 11.0, 32.0],
        ],
        tip_mm: None,
    }
}

/// Robot base frame: the cameras look along the robot's +x from 600 mm behind its base.
fn world_from_cam0() -> RigidTransform {
    RigidTransform {
        r_row_major: [0.0, 0.0, 1.0, -1.0, 0.0, 0.0, 0.0, -1.0, 0.0],
        t_mm: [-600.0, 0.0, 500.0],
    }
}

fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}

/// Test clock: "now" is the newest frame's capture time plus 1 ms of processing, so the
/// safety checks (age, speed) see the simulated 120 fps timing however fast the test runs.
#[derive(Clone)]
struct FrameClock(Arc<AtomicU64>);

impl Clock for FrameClock {
    fn now_ns(&self) -> u64 {
        self.0.load(Ordering::SeqCst)
    }
}

/// What was published for one frame and the truth for it (world frame).
struct Published {
    pos_mm: [f64; 3],
    truth_pos_mm: Vector3<f64>,
    truth_q: UnitQuaternion<f64>,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rotating_tool_tracked_in_6dof_to_the_simulated_robot() {
    // --- Scene: the tool circles the crossing point while turning about all three axes.
    let tool = probe4();
    let mut cfg = SimConfig::preset(
        RigPreset::Convergent {
            distance_mm: 1000.0,
            angle_deg: 90.0,
        },
        1000.0,
        50.0,
    );
    cfg.trajectory = Trajectory::Circle {
        centre_mm: Vector3::new(-40.0, -30.0, 1000.0),
        radius_mm: 50.0,
        normal: Vector3::new(0.3, 1.0, 0.4),
        period_s: 6.0,
    };
    cfg.set_tool(
        &tool.leds_mm,
        Orientation::Wobble {
            base: UnitQuaternion::from_euler_angles(0.2, -0.3, 0.4),
            amplitude_deg: Vector3::new(35.0, 30.0, 45.0),
            period_s: Vector3::new(4.0, 5.0, 6.5),
            phase_rad: Vector3::new(0.0, 1.0, 2.0),
        },
    );
    cfg.seed = 6;
    let mut sc = Scenario::new(cfg).unwrap();
    let rig = sc.rig().clone();
    let (w, h) = sc.image_size();
    let mut frames = [vec![0u8; (w * h) as usize], vec![0u8; (w * h) as usize]];
    let mut detectors = [
        BlobDetector::new(BlobLimits::for_frame(w, h)).unwrap(),
        BlobDetector::new(BlobLimits::for_frame(w, h)).unwrap(),
    ];
    let blob_cfg = BlobConfig::default();
    let mut tracker = PoseTracker::new(&rig, &tool, PoseConfig::default()).unwrap();
    let world = world_from_cam0();
    let r_world = world.rotation();
    let q_world = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r_world));
    let t_world = world.translation_mm();
    let truth_world = |t: &FrameTruth| {
        (
            r_world * t.tool_position_mm + t_world,
            q_world * t.tool_orientation,
        )
    };
    let home_mm: [f64; 3] = truth_world(&sc.truth(0)).0.into();

    // --- Robot side.
    let sim = SimRobotServer::start(SimServerConfig {
        robot: SimRobotConfig {
            speed_mm_s: 2000.0,
            window: 4,
            home_mm,
            beat_period_s: 0.05,
            ..Default::default()
        },
        ..Default::default()
    })
    .await
    .unwrap();
    let link_cfg = RobotConfig {
        tool: None,
        kind: Default::default(),
        stream: Default::default(),
        address: sim.addr.to_string(),
        name: "irtrackd-6dof".into(),
        connect_timeout_ms: 500,
        heartbeat_ms: 50,
        peer_timeout_ms: 2000,
        backoff_min_ms: 20,
        backoff_max_ms: 200,
        send_orientation: true,
        safety: SafetyConfig {
            workspace_min_mm: [0.0, -400.0, 100.0],
            workspace_max_mm: [800.0, 400.0, 900.0],
            max_step_mm: MAX_STEP_MM,
            max_speed_mm_s: 1000.0,
            max_gap_mm: 1.0,
            max_age_ms: 50,
            require_world_frame: true,
            max_rotation_step_deg: MAX_ROTATION_STEP_DEG,
        },
        deadman: DeadmanConfig::Flag,
    };
    let (tx, rx) = watch::channel::<Option<PositionRecord>>(None);
    let now = Arc::new(AtomicU64::new(1_000_000_000));
    let link = LinkHandle::spawn_socket(link_cfg, rx, FrameClock(now.clone()), Arc::new(NoDeadman)).unwrap();
    let mut status = link.subscribe();
    // Every state the link passes through; a latched safety stop would show here.
    let states = Arc::new(Mutex::new(Vec::<LinkState>::new()));
    let watcher = {
        let (mut st, states) = (link.subscribe(), states.clone());
        tokio::spawn(async move {
            while st.changed().await.is_ok() {
                let s = st.borrow_and_update().state;
                states.lock().unwrap().push(s);
            }
        })
    };
    tokio::time::timeout(Duration::from_secs(5), status.wait_for(|s| s.connects >= 1))
        .await
        .expect("link connects")
        .unwrap();
    link.enable();

    // --- Frames.
    let mut published: Vec<Published> = Vec::new();
    let (mut tracked, mut swaps, mut unsent) = (0usize, 0usize, 0usize);
    let (mut rot_sq, mut pos_sq, mut rot_max, mut pos_max) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut lost: Vec<PoseStatus> = Vec::new();
    for k in 0..FRAMES {
        for c in 0..2 {
            sc.render_u8(k, c, &mut frames[c]).unwrap();
            let img = GrayImage::new(&frames[c], w, h, w).unwrap();
            detectors[c].detect(&img, None, &blob_cfg).unwrap();
        }
        let pose = *tracker
            .process(&[detectors[0].blobs(), detectors[1].blobs()])
            .unwrap();
        let truth = sc.truth(k);
        if pose.status == PoseStatus::Tracked {
            tracked += 1;
            // Identification: every LED the tracker used must be nearest to the same LED's truth.
            let mut swapped = false;
            for i in (0..tool.leds_mm.len()).filter(|i| pose.led_mask & (1 << i) != 0) {
                let m = Vector3::from(pose.leds_mm[i]);
                let nearest = (0..truth.marker_count)
                    .min_by(|a, b| {
                        let da = (truth.markers[*a].p_cam0_mm - m).norm();
                        let db = (truth.markers[*b].p_cam0_mm - m).norm();
                        da.total_cmp(&db)
                    })
                    .unwrap();
                swapped |= nearest != i;
            }
            swaps += usize::from(swapped);
            let e_rot =
                quaternion_angle_rad(&pose.quaternion_wxyz, &truth.tool_quaternion_wxyz()).to_degrees();
            let e_pos = (Vector3::from(pose.position_mm) - truth.tool_position_mm).norm();
            rot_sq += e_rot * e_rot;
            pos_sq += e_pos * e_pos;
            rot_max = rot_max.max(e_rot);
            pos_max = pos_max.max(e_pos);
        } else {
            lost.push(pose.status);
        }
        let ts_ns = 1_000_000_000 + sc.timestamp_ns(k);
        let rec = PositionRecord::from_pose(k, ts_ns, &pose, Some(&world), 2);
        let sent_before = status.borrow().targets_sent;
        now.store(ts_ns + 1_000_000, Ordering::SeqCst);
        tx.send(Some(rec)).unwrap();
        if rec.status == TrackStatus::Ok {
            let (truth_pos_mm, truth_q) = truth_world(&truth);
            published.push(Published {
                pos_mm: rec.position_mm.unwrap(),
                truth_pos_mm,
                truth_q,
            });
            // Lock step: the next frame goes out once this one was sent as a target.
            let sent = tokio::time::timeout(
                Duration::from_secs(1),
                status.wait_for(|s| s.targets_sent > sent_before),
            )
            .await;
            unsent += usize::from(sent.is_err());
        } else {
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    let final_status = link.status();
    link.shutdown().await;
    watcher.abort();

    // --- What the robot received, matched to the published frame by position (0.01 mm
    // wire resolution), against the truth of that frame.
    let received = sim.received();
    let (mut rq_sq, mut rp_sq, mut rq_max, mut rp_max) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let (mut max_rot_step, mut max_step) = (0.0f64, 0.0f64);
    let mut prev: Option<([f64; 3], [f64; 4])> = None;
    for r in &received {
        // Six decimals per component leave |q| off 1 by up to ~1e-6, which would read as
        // 0.1° in acos(|q·q'|); the robot normalises (RAPID NOrient), and so does this check.
        let q = r.quat_wxyz.expect("6-DOF target sent as a Q line");
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((n - 1.0).abs() < 1e-5, "received quaternion {q:?} not unit");
        let q = q.map(|v| v / n);
        let p = Vector3::from(r.pos_mm);
        let best = published
            .iter()
            .min_by(|a, b| {
                let da = (Vector3::from(a.pos_mm) - p).norm();
                let db = (Vector3::from(b.pos_mm) - p).norm();
                da.total_cmp(&db)
            })
            .unwrap();
        assert!(
            (Vector3::from(best.pos_mm) - p).norm() < 0.01,
            "received target {r:?} matches no published record"
        );
        let e_rot = quaternion_angle_rad(&q, &wxyz(&best.truth_q)).to_degrees();
        let e_pos = (p - best.truth_pos_mm).norm();
        rq_sq += e_rot * e_rot;
        rp_sq += e_pos * e_pos;
        rq_max = rq_max.max(e_rot);
        rp_max = rp_max.max(e_pos);
        if let Some((pp, pq)) = prev {
            max_rot_step = max_rot_step.max(quaternion_angle_rad(&pq, &q).to_degrees());
            max_step = max_step.max((Vector3::from(pp) - p).norm());
        }
        prev = Some((r.pos_mm, q));
    }
    let n = received.len() as f64;
    let (rq_rms, rp_rms) = ((rq_sq / n).sqrt(), (rp_sq / n).sqrt());
    let (t_rot_rms, t_pos_rms) = ((rot_sq / tracked as f64).sqrt(), (pos_sq / tracked as f64).sqrt());
    let latched: Vec<LinkState> = states
        .lock()
        .unwrap()
        .iter()
        .copied()
        .filter(|s| {
            matches!(
                s,
                LinkState::Holding(
                    HoldReason::StepTooLarge
                        | HoldReason::TooFast
                        | HoldReason::Workspace
                        | HoldReason::PoorQuality
                )
            )
        })
        .collect();
    println!(
        "6-DOF e2e: {FRAMES} frames, {tracked} tracked ({:.1} %), {swaps} identification swaps",
        100.0 * tracked as f64 / FRAMES as f64
    );
    println!(
        "  tracker vs truth: orientation RMS {t_rot_rms:.3}° (max {rot_max:.3}°), position RMS \
         {t_pos_rms:.3} mm (max {pos_max:.3} mm)"
    );
    println!(
        "  robot received {} Q targets ({unsent} tracked frames not sent): orientation RMS {rq_rms:.3}° \
         (max {rq_max:.3}°), position RMS {rp_rms:.3} mm (max {rp_max:.3} mm)",
        received.len()
    );
    println!(
        "  largest step between received targets: {max_rot_step:.2}° (limit {MAX_ROTATION_STEP_DEG}°), \
         {max_step:.2} mm (limit {MAX_STEP_MM} mm); safety holds latched: {}; link {:?}",
        latched.len(),
        final_status.state
    );
    let mut kinds: Vec<String> = lost.iter().map(|s| format!("{s:?}")).collect();
    kinds.sort();
    kinds.dedup_by(|a, b| a.split(' ').next() == b.split(' ').next());
    println!("  untracked frames: {} ({})", lost.len(), kinds.join(", "));

    assert!(
        tracked as f64 >= 0.8 * FRAMES as f64,
        "only {tracked} of {FRAMES} frames tracked"
    );
    assert_eq!(swaps, 0, "identification swaps");
    assert!(t_rot_rms <= 0.2, "tracker orientation RMS {t_rot_rms}°");
    assert!(t_pos_rms <= 0.3, "tracker position RMS {t_pos_rms} mm");
    assert!(latched.is_empty(), "safety latched: {latched:?}");
    assert_eq!(unsent, 0, "tracked frames that never became targets");
    assert_eq!(
        received.len(),
        tracked,
        "every tracked frame reaches the robot once"
    );
    assert!(rq_rms <= 0.2, "robot orientation RMS {rq_rms}°");
    assert!(rp_rms <= 0.3, "robot position RMS {rp_rms} mm");
    assert!(max_rot_step <= MAX_ROTATION_STEP_DEG && max_step <= MAX_STEP_MM);
}
