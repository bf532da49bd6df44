//! End to end over real UDP sockets on 127.0.0.1: a simulated marker feed → irtrackd's EGM or
//! RSI link (`robot::spawn_link`, the same safety gate as the socket protocol) → the simulated
//! controller (`robot::ctrl_sim`, what `host-tools robot-sim --egm/--rsi` runs).
//!
//! Checked from the controller's own record: nothing moves before the enable; after it the robot
//! follows the marker (every commanded point lies on the marker's path); on marker loss and on
//! disable the command freezes at the robot's own position (never an older target) and the
//! robot comes to rest there. Timing is not asserted tightly: these run under qemu too.

use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Duration;

use irtrack_core::robot_proto::HoldReason;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_robot::MonotonicClock;
use irtrack_robot::ctrl_sim::{CtrlConfig, CtrlCycle, CtrlKind, SimController};
use irtrack_robot::deadman::FlagDeadman;
use irtrack_robot::monotonic_ns;
use irtrack_robot::udp::{RsiMode, StreamConfig};
use irtrack_robot::{
    DeadmanConfig, LinkHandle, LinkKind, LinkState, LinkStatus, RobotConfig, RobotLink, SafetyConfig,
    spawn_link,
};
use tokio::sync::watch;

const CENTER: [f64; 3] = [400.0, 0.0, 300.0];
const RADIUS_MM: f64 = 100.0;
/// 250 mm/s on the circle.
const OMEGA_RAD_S: f64 = 2.5;
const MAX_STEP_MM: f64 = 15.0;

fn circle(t_s: f64) -> [f64; 3] {
    let a = OMEGA_RAD_S * t_s;
    [
        CENTER[0] + RADIUS_MM * a.cos(),
        CENTER[1] + RADIUS_MM * a.sin(),
        CENTER[2],
    ]
}

/// Distance of `p` from the marker's circle.
fn off_circle_mm(p: [f64; 3]) -> f64 {
    let r = ((p[0] - CENTER[0]).powi(2) + (p[1] - CENTER[1]).powi(2)).sqrt();
    ((r - RADIUS_MM).powi(2) + (p[2] - CENTER[2]).powi(2)).sqrt()
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

fn cfg(kind: LinkKind, mode: RsiMode) -> RobotConfig {
    RobotConfig {
        tool: None,
        kind,
        address: "127.0.0.1:0".into(),
        name: "irtrackd-test".into(),
        connect_timeout_ms: 500,
        heartbeat_ms: 50,
        peer_timeout_ms: 300,
        backoff_min_ms: 20,
        backoff_max_ms: 200,
        send_orientation: false,
        safety: SafetyConfig {
            workspace_min_mm: [0.0, -400.0, 0.0],
            workspace_max_mm: [800.0, 400.0, 800.0],
            max_step_mm: MAX_STEP_MM,
            max_speed_mm_s: 600.0,
            max_gap_mm: 1.0,
            // Generous: under qemu a sample can wait a while before its packet comes.
            max_age_ms: 500,
            require_world_frame: true,
            max_rotation_step_deg: 10.0,
        },
        deadman: DeadmanConfig::Flag,
        stream: StreamConfig {
            rsi_mode: mode,
            // A loaded test machine may pause the controller thread; do not end sessions then.
            session_timeout_ms: 5000,
            ..StreamConfig::default()
        },
    }
}

/// The marker rests at `circle(0)` (where the robot starts) until the test says go.
const REST: u8 = 0;
const FOLLOW: u8 = 1;
const LOST: u8 = 2;
/// The marker at the circle's centre: `RADIUS_MM` from wherever the robot is on the circle.
const CENTRE: u8 = 3;

/// Publishes the marker at 100 Hz: at rest, moving on the circle, or lost, as `mode` says.
fn spawn_feed(tx: watch::Sender<Option<PositionRecord>>, mode: Arc<AtomicU8>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let mut t0 = None;
        let mut tick = tokio::time::interval(Duration::from_millis(10));
        let mut frame = 0;
        loop {
            tick.tick().await;
            frame += 1;
            let m = mode.load(Ordering::SeqCst);
            let lost = m == LOST;
            if m != REST && t0.is_none() {
                t0 = Some(tokio::time::Instant::now());
            }
            let p = if m == CENTRE {
                CENTER
            } else {
                circle(t0.map_or(0.0, |t| t.elapsed().as_secs_f64()))
            };
            let _ = tx.send(Some(PositionRecord {
                frame,
                capture_ts_ns: monotonic_ns(),
                position_mm: (!lost).then_some(p),
                orientation_wxyz: None,
                gap_mm: if lost { f64::NAN } else { 0.2 },
                status: if lost { TrackStatus::Lost } else { TrackStatus::Ok },
                cameras_used: 2,
                world_frame: true,
                latency_us: 0,
                params_crc: 0,
            }));
        }
    })
}

async fn wait_for(link: &LinkHandle, what: &str, cond: impl Fn(&LinkStatus) -> bool) {
    let mut rx = link.subscribe();
    let r = tokio::time::timeout(Duration::from_secs(10), rx.wait_for(|s| cond(s))).await;
    assert!(
        r.is_ok(),
        "timed out waiting for {what}; status {:?}",
        link.status()
    );
}

async fn wait_cycles(ctrl: &SimController, n: u64) {
    let start = ctrl.record().cycles;
    let t0 = std::time::Instant::now();
    while ctrl.record().cycles < start + n {
        assert!(
            t0.elapsed() < Duration::from_secs(20),
            "controller stalled: {:?}",
            ctrl.record().stopped
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

struct Rig {
    link: LinkHandle,
    ctrl: SimController,
    mode: Arc<AtomicU8>,
    _deadman: FlagDeadman,
    _feed: tokio::task::JoinHandle<()>,
}

async fn rig(kind: LinkKind, ctrl_kind: CtrlKind, mode: RsiMode, cycle_ms: f64) -> Rig {
    let (tx, rx) = watch::channel(None);
    let feed_mode = Arc::new(AtomicU8::new(REST));
    let feed = spawn_feed(tx, feed_mode.clone());
    let deadman = FlagDeadman::new();
    deadman.set(true);
    let c = cfg(kind, mode);
    let dm = c.deadman.open(&deadman).unwrap();
    let link = spawn_link(c, rx, MonotonicClock, dm).unwrap();
    wait_for(&link, "the UDP bind", |s| s.local_addr.is_some()).await;
    let sensor = link.status().local_addr.unwrap();
    let ctrl = SimController::spawn(
        CtrlConfig {
            cycle_ms,
            home_mm: circle(0.0),
            // Missed cycles on a loaded machine must not end the test's session.
            max_missed: 0,
            keep_path: true,
            ..CtrlConfig::new(ctrl_kind, sensor)
        },
        None,
    )
    .unwrap();
    Rig {
        link,
        ctrl,
        mode: feed_mode,
        _deadman: deadman,
        _feed: feed,
    }
}

/// The cycles from the first one at or after `t_ns`.
fn since(path: &[CtrlCycle], t_ns: u64) -> Vec<CtrlCycle> {
    path.iter().filter(|c| c.t_ns >= t_ns).copied().collect()
}

/// Asserts that from `t_ns` (a little after the hold was reported) every command is one point,
/// that this point was the robot's position when the hold began (not an earlier target), and
/// that the robot has come to rest at it.
fn assert_holds(path: &[CtrlCycle], t_ns: u64, what: &str) {
    // From the first answered cycle: an unanswered one keeps the command it had before.
    let after: Vec<CtrlCycle> = since(path, t_ns)
        .into_iter()
        .skip_while(|c| !c.answered)
        .collect();
    assert!(
        after.len() >= 20,
        "{what}: only {} cycles after the hold",
        after.len()
    );
    let hold = after[0].cmd_mm;
    for c in &after {
        assert!(
            dist(c.cmd_mm, hold) < 1e-3,
            "{what}: command moved during the hold: {:?} vs {hold:?}",
            c.cmd_mm
        );
    }
    // The held point is one the robot actually occupied in the cycles before the hold.
    let before: Vec<_> = path.iter().filter(|c| c.t_ns < t_ns).rev().take(200).collect();
    let nearest = before
        .iter()
        .map(|c| dist(c.pos_mm, hold))
        .fold(f64::INFINITY, f64::min);
    assert!(
        nearest < 0.5,
        "{what}: hold point {hold:?} is {nearest} mm from where the robot was"
    );
    // At rest at the held point (a lagging servo settles within ~10 time constants).
    let last = after[after.len() - 1];
    assert!(
        dist(last.pos_mm, hold) < 0.2,
        "{what}: robot at {:?}, hold {hold:?}",
        last.pos_mm
    );
}

async fn follows_and_holds(kind: LinkKind, ctrl_kind: CtrlKind, mode: RsiMode, cycle_ms: f64) {
    let r = rig(kind, ctrl_kind, mode, cycle_ms).await;
    wait_for(&r.link, "a held session", |s| {
        s.state == LinkState::Holding(HoldReason::NotEnabled)
    })
    .await;
    // Not enabled: the robot is held where it is.
    wait_cycles(&r.ctrl, 30).await;
    let rec = r.ctrl.record();
    let home = circle(0.0);
    assert!(rec.answered >= 20, "answers: {rec:?}");
    for c in &rec.path {
        assert!(dist(c.cmd_mm, home) < 1e-3, "moved before the enable: {c:?}");
    }

    // Enable with the marker at the robot: the robot picks it up and follows.
    r.link.enable();
    wait_for(&r.link, "motion", |s| s.state == LinkState::Moving).await;
    r.mode.store(FOLLOW, Ordering::SeqCst);
    let t_move = monotonic_ns();
    wait_cycles(&r.ctrl, (800.0 / cycle_ms) as u64).await;
    let rec = r.ctrl.record();
    let moving = since(&rec.path, t_move);
    let mut travelled = 0.0;
    for w in moving.windows(2) {
        let step = dist(w[0].cmd_mm, w[1].cmd_mm);
        assert!(step <= MAX_STEP_MM, "command step {step} mm");
        travelled += dist(w[0].pos_mm, w[1].pos_mm);
    }
    // Commands are marker samples (RSI rounds to 0.1 µm on the wire).
    for c in &moving {
        assert!(
            off_circle_mm(c.cmd_mm) < 0.01,
            "command off the marker path: {c:?}"
        );
    }
    let (worst_i, worst_pos) = moving
        .iter()
        .map(|c| off_circle_mm(c.pos_mm))
        .enumerate()
        .fold((0, 0.0), |a, (i, d)| if d > a.1 { (i, d) } else { a });
    assert!(
        worst_pos < 3.0,
        "robot left the path by {worst_pos} mm at cycle {worst_i}: {:?}",
        &moving[worst_i.saturating_sub(3)..(worst_i + 3).min(moving.len())]
    );
    assert!(travelled > 100.0, "robot travelled only {travelled} mm");

    // Marker lost: hold at the robot's position.
    r.mode.store(LOST, Ordering::SeqCst);
    wait_for(&r.link, "hold on marker loss", |s| {
        s.state == LinkState::Holding(HoldReason::MarkerLost)
    })
    .await;
    let t_lost = monotonic_ns();
    wait_cycles(&r.ctrl, (400.0 / cycle_ms) as u64).await;
    assert_holds(&r.ctrl.record().path, t_lost, "marker lost");
    let st = r.link.status();
    assert!(st.holds_sent >= 1 && st.targets_sent > 0, "{st:?}");
    drop(r.ctrl.stop());
}

async fn disable_holds(kind: LinkKind, ctrl_kind: CtrlKind, mode: RsiMode) {
    let r = rig(kind, ctrl_kind, mode, 4.0).await;
    wait_for(&r.link, "a held session", |s| {
        s.state == LinkState::Holding(HoldReason::NotEnabled)
    })
    .await;
    r.link.enable();
    wait_for(&r.link, "motion", |s| s.state == LinkState::Moving).await;
    r.mode.store(FOLLOW, Ordering::SeqCst);
    wait_cycles(&r.ctrl, 100).await;
    r.link.disable();
    wait_for(&r.link, "hold on disable", |s| {
        s.state == LinkState::Holding(HoldReason::Stop)
    })
    .await;
    let t = monotonic_ns();
    wait_cycles(&r.ctrl, 100).await;
    assert_holds(&r.ctrl.record().path, t, "disable");
    // A fresh enable needs the marker within max_step of the robot: with the marker now
    // RADIUS_MM away, the link latches a step stop instead of jumping.
    r.mode.store(CENTRE, Ordering::SeqCst);
    tokio::time::sleep(Duration::from_millis(50)).await;
    r.link.enable();
    wait_for(&r.link, "step latch", |s| {
        s.state == LinkState::Holding(HoldReason::StepTooLarge)
    })
    .await;
    let t = monotonic_ns();
    wait_cycles(&r.ctrl, 50).await;
    assert_holds(&r.ctrl.record().path, t, "step latch");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn egm_follows_the_marker_and_holds_on_loss() {
    follows_and_holds(LinkKind::Egm, CtrlKind::Egm, RsiMode::Absolute, 4.0).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn egm_holds_on_disable_and_never_jumps_on_reenable() {
    disable_holds(LinkKind::Egm, CtrlKind::Egm, RsiMode::Absolute).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rsi_absolute_follows_the_marker_and_holds_on_loss() {
    follows_and_holds(
        LinkKind::Rsi,
        CtrlKind::Rsi(RsiMode::Absolute),
        RsiMode::Absolute,
        4.0,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rsi_relative_at_12_ms_follows_the_marker_and_holds_on_loss() {
    follows_and_holds(
        LinkKind::Rsi,
        CtrlKind::Rsi(RsiMode::Relative),
        RsiMode::Relative,
        12.0,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rsi_relative_holds_on_disable_and_never_jumps_on_reenable() {
    disable_holds(LinkKind::Rsi, CtrlKind::Rsi(RsiMode::Relative), RsiMode::Relative).await;
}
