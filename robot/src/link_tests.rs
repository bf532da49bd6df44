//! End-to-end tests: simulated marker feed → socket link (`LinkHandle::spawn_socket`) → simulated robot over 127.0.0.1.
//! Every safety rule is exercised against the robot simulator, and the robot's own log is checked
//! for violations (targets outside the box, jumps).

use std::sync::Arc;
use std::time::Duration;

use irtrack_core::robot_proto::HoldReason;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::deadman::{DeadmanConfig, FlagDeadman};
use crate::safety::SafetyConfig;
use crate::sim::{SimLog, SimRobotServer, SimServerConfig};
use crate::sim_robot::{SimEvent, SimRobotConfig};
use crate::{LinkHandle, LinkState, LinkStatus, MonotonicClock, RobotConfig, RobotLink, monotonic_ns};

const CENTER: [f64; 3] = [0.0, 0.0, 200.0];
const RADIUS: f64 = 100.0;

fn safety() -> SafetyConfig {
    SafetyConfig {
        workspace_min_mm: [-300.0, -300.0, 0.0],
        workspace_max_mm: [300.0, 300.0, 400.0],
        max_step_mm: 15.0,
        max_speed_mm_s: 400.0,
        max_gap_mm: 1.0,
        max_age_ms: 60,
        require_world_frame: true,
        max_rotation_step_deg: 10.0,
    }
}

fn link_cfg(addr: std::net::SocketAddr) -> RobotConfig {
    RobotConfig {
        tool: None,
        address: addr.to_string(),
        name: "irtrackd-test".into(),
        connect_timeout_ms: 500,
        heartbeat_ms: 50,
        peer_timeout_ms: 300,
        backoff_min_ms: 20,
        backoff_max_ms: 200,
        send_orientation: false,
        safety: safety(),
        deadman: DeadmanConfig::Flag,
        kind: Default::default(),
        stream: Default::default(),
    }
}

fn sim_cfg(window: u8, home_mm: [f64; 3]) -> SimServerConfig {
    SimServerConfig {
        robot: SimRobotConfig {
            speed_mm_s: 300.0,
            window,
            home_mm,
            beat_period_s: 0.05,
            ..Default::default()
        },
        ..Default::default()
    }
}

/// What the marker does at time `t_s`: position (None = lost) and ray gap.
type Scenario = Arc<dyn Fn(f64) -> Option<(Option<[f64; 3]>, f64)> + Send + Sync>;

/// Publishes records at `rate_hz`; a scenario returning `None` stops publishing (stale feed).
fn spawn_feed(tx: watch::Sender<Option<PositionRecord>>, rate_hz: f64, scenario: Scenario) -> JoinHandle<()> {
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / rate_hz));
        let t0 = tokio::time::Instant::now();
        let mut frame = 0;
        loop {
            tick.tick().await;
            let t = t0.elapsed().as_secs_f64();
            let Some((pos, gap_mm)) = scenario(t) else {
                // Keep the sender alive: a stalled loop, not a closed one.
                std::future::pending::<()>().await;
                return;
            };
            frame += 1;
            let status = match pos {
                None => TrackStatus::Lost,
                Some(_) if gap_mm > 1.0 => TrackStatus::Rejected,
                Some(_) => TrackStatus::Ok,
            };
            let _ = tx.send(Some(PositionRecord {
                frame,
                capture_ts_ns: monotonic_ns(),
                position_mm: if status == TrackStatus::Ok { pos } else { None },
                orientation_wxyz: None,
                gap_mm: if pos.is_some() { gap_mm } else { f64::NAN },
                status,
                cameras_used: 2,
                world_frame: true,
                latency_us: 0,
                params_crc: 0,
            }));
        }
    })
}

fn circle(omega_rad_s: f64) -> impl Fn(f64) -> [f64; 3] + Send + Sync + Clone {
    move |t| {
        let a = omega_rad_s * t;
        [
            CENTER[0] + RADIUS * a.cos(),
            CENTER[1] + RADIUS * a.sin(),
            CENTER[2],
        ]
    }
}

struct Rig {
    sim: SimRobotServer,
    link: LinkHandle,
    deadman: FlagDeadman,
    _feed: JoinHandle<()>,
}

async fn rig(sim: SimServerConfig, rate_hz: f64, scenario: Scenario) -> Rig {
    rig_with(sim, rate_hz, scenario, |_| {}).await
}

async fn rig_with(
    sim: SimServerConfig,
    rate_hz: f64,
    scenario: Scenario,
    tweak: impl FnOnce(&mut RobotConfig),
) -> Rig {
    let sim = SimRobotServer::start(sim).await.unwrap();
    let (tx, rx) = watch::channel(None);
    let feed = spawn_feed(tx, rate_hz, scenario);
    let deadman = FlagDeadman::new();
    deadman.set(true);
    let mut cfg = link_cfg(sim.addr);
    tweak(&mut cfg);
    let dm = cfg.deadman.open(&deadman).unwrap();
    let link = LinkHandle::spawn_socket(cfg, rx, MonotonicClock, dm).unwrap();
    Rig {
        sim,
        link,
        deadman,
        _feed: feed,
    }
}

async fn wait_for(link: &LinkHandle, what: &str, cond: impl Fn(&LinkStatus) -> bool) {
    let mut rx = link.subscribe();
    let r = tokio::time::timeout(Duration::from_secs(3), rx.wait_for(|s| cond(s))).await;
    assert!(
        r.is_ok(),
        "timed out waiting for {what}; status {:?}",
        link.status()
    );
}

/// Waits until the robot's log shows a HOLD with `reason`.
async fn wait_robot_hold(sim: &SimRobotServer, reason: HoldReason) {
    let t0 = std::time::Instant::now();
    while !holds(&sim.log()).iter().any(|h| h.1 == reason) {
        assert!(
            t0.elapsed() < Duration::from_secs(2),
            "robot never got HOLD {reason:?}: {:?}",
            holds(&sim.log())
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

async fn connect_and_enable(r: &Rig) {
    wait_for(&r.link, "connection", |s| {
        s.state == LinkState::Holding(HoldReason::NotEnabled)
    })
    .await;
    r.link.enable();
}

fn targets(log: &[(f64, u32, SimLog, [f64; 3])]) -> Vec<(f64, u32, u32, [f64; 3])> {
    log.iter()
        .filter_map(|(t, c, e, _)| match e {
            SimLog::Event(SimEvent::Target { seq, target_mm }) => Some((*t, *c, *seq, *target_mm)),
            _ => None,
        })
        .collect()
}

fn holds(log: &[(f64, u32, SimLog, [f64; 3])]) -> Vec<(f64, HoldReason)> {
    log.iter()
        .filter_map(|(t, _, e, _)| match e {
            SimLog::Event(SimEvent::Hold { reason }) => Some((*t, *reason)),
            _ => None,
        })
        .collect()
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The robot's view: every target inside the box, no step above the limit (the first target of a
/// connection measured from where the robot stood).
fn assert_no_violation(sim: &SimRobotServer) {
    let log = sim.log();
    let cfg = safety();
    let mut prev: Option<(u32, [f64; 3])> = None;
    for (_, conn, e, pos) in &log {
        if let SimLog::Event(SimEvent::Target { target_mm: p, .. }) = e {
            for i in 0..3 {
                assert!(
                    p[i] >= cfg.workspace_min_mm[i] && p[i] <= cfg.workspace_max_mm[i],
                    "outside box: {p:?}"
                );
            }
            let from = match prev {
                Some((c, q)) if c == *conn => q,
                _ => *pos,
            };
            assert!(dist(*p, from) <= cfg.max_step_mm + 1e-6, "jump {from:?} -> {p:?}");
            prev = Some((*conn, *p));
        }
    }
}

/// Distance of a point from the circle path.
fn path_error(p: [f64; 3]) -> f64 {
    let r = ((p[0] - CENTER[0]).powi(2) + (p[1] - CENTER[1]).powi(2)).sqrt();
    ((r - RADIUS).powi(2) + (p[2] - CENTER[2]).powi(2)).sqrt()
}

async fn follow_circle(window: u8) -> (f64, f64, usize) {
    let c = circle(1.5); // 150 mm/s tangential
    let scen: Scenario = Arc::new(move |t| Some((Some(c(t)), 0.2)));
    let r = rig(
        sim_cfg(window, [CENTER[0] + RADIUS, CENTER[1], CENTER[2]]),
        100.0,
        scen,
    )
    .await;
    connect_and_enable(&r).await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let c = circle(1.5);
    let trace = r.sim.trace();
    let worst_path = trace.iter().map(|(_, p)| path_error(*p)).fold(0.0, f64::max);
    // Lag: robot's final position against the marker's newest position.
    let status = r.link.status();
    assert_eq!(status.state, LinkState::Moving, "{status:?}");
    let last_target = targets(&r.sim.log()).last().map(|t| t.3).unwrap();
    let robot = r.sim.trace().last().unwrap().1;
    let lag = dist(robot, last_target);
    assert_no_violation(&r.sim);
    let n = targets(&r.sim.log()).len();
    let _ = c;
    (worst_path, lag, n)
}

#[tokio::test]
async fn circle_followed_step_by_step_with_bounded_error() {
    let (worst_path, lag, n) = follow_circle(1).await;
    eprintln!("window 1: {n} targets, worst path error {worst_path:.3} mm, lag to last target {lag:.2} mm");
    // Chords of a 100 mm circle between targets a few mm apart deviate by well under 0.5 mm.
    assert!(worst_path < 0.5, "path error {worst_path} mm");
    assert!(lag < 15.0, "lag {lag} mm");
    assert!(n > 40, "only {n} targets in 1.5 s");
}

#[tokio::test]
async fn circle_followed_blended_with_credit_window() {
    let (worst_path, lag, n) = follow_circle(3).await;
    eprintln!("window 3: {n} targets, worst path error {worst_path:.3} mm, lag {lag:.2} mm");
    assert!(worst_path < 0.5, "path error {worst_path} mm");
    assert!(n > 40);
}

fn still(p: [f64; 3]) -> Scenario {
    Arc::new(move |_| Some((Some(p), 0.2)))
}

#[tokio::test]
async fn no_motion_before_explicit_enable() {
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, still([5.0, 0.0, 200.0])).await;
    r.link.enable(); // before the connection exists: must not count
    wait_for(&r.link, "connection", |s| {
        s.state == LinkState::Holding(HoldReason::NotEnabled)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(targets(&r.sim.log()).is_empty());
    assert_eq!(holds(&r.sim.log())[0].1, HoldReason::NotEnabled);
    r.link.enable();
    wait_for(&r.link, "motion", |s| s.targets_sent > 0).await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(dist(r.sim.trace().last().unwrap().1, [5.0, 0.0, 200.0]) < 1e-6);
    r.link.disable();
    wait_for(&r.link, "hold on disable", |s| {
        s.state == LinkState::Holding(HoldReason::Stop)
    })
    .await;
}

#[tokio::test]
async fn reconnect_resets_sequence_and_holds_until_enable() {
    // 10 mm/s: the marker stays within the step limit of the tool while the link is held.
    let c = circle(0.1);
    let scen: Scenario = Arc::new(move |t| Some((Some(c(t)), 0.2)));
    let mut sim = sim_cfg(1, [CENTER[0] + RADIUS, 0.0, 200.0]);
    sim.disconnect_after = 20;
    let r = rig(sim, 100.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "second connection", |s| {
        s.connects == 2 && s.state != LinkState::Connecting
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let t = targets(&r.sim.log());
    assert_eq!(t.len(), 20, "targets after reconnect without enable: {t:?}");
    assert_eq!(r.link.status().state, LinkState::Holding(HoldReason::NotEnabled));
    r.link.enable();
    wait_for(&r.link, "motion after enable", |s| s.state == LinkState::Moving).await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let t = targets(&r.sim.log());
    let second: Vec<_> = t.iter().filter(|x| x.1 == 2).collect();
    assert_eq!(second.first().map(|x| x.2), Some(1), "sequence restarts at 1");
    assert!(second.windows(2).all(|w| w[1].2 == w[0].2 + 1));
    assert_no_violation(&r.sim);
}

/// Slow line along x from the robot's home; `f` decorates it per time.
fn line_scenario(
    f: impl Fn(f64, [f64; 3]) -> Option<(Option<[f64; 3]>, f64)> + Send + Sync + 'static,
) -> Scenario {
    Arc::new(move |t| f(t, [20.0 * t, 0.0, 200.0]))
}

#[tokio::test]
async fn marker_loss_holds_and_resumes_without_jump() {
    let scen = line_scenario(|t, p| Some((if (0.5..0.8).contains(&t) { None } else { Some(p) }, 0.2)));
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, scen).await;
    connect_and_enable(&r).await;
    tokio::time::sleep(Duration::from_millis(1200)).await;
    let h = holds(&r.sim.log());
    assert!(h.iter().any(|x| x.1 == HoldReason::MarkerLost), "{h:?}");
    let t_hold = h.iter().find(|x| x.1 == HoldReason::MarkerLost).unwrap().0;
    let t = targets(&r.sim.log());
    // Nothing between the hold and the marker's return (~0.3 s later), then motion again.
    let after: Vec<_> = t.iter().filter(|x| x.0 > t_hold).collect();
    assert!(after.first().is_some_and(|x| x.0 > t_hold + 0.2), "{after:?}");
    assert!(after.len() > 10);
    assert_eq!(r.link.status().state, LinkState::Moving);
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn poor_quality_holds() {
    let scen = line_scenario(|t, p| Some((Some(p), if t > 0.4 { 2.5 } else { 0.2 })));
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "quality hold", |s| {
        s.state == LinkState::Holding(HoldReason::PoorQuality)
    })
    .await;
    let n = targets(&r.sim.log()).len();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(targets(&r.sim.log()).len(), n);
    wait_robot_hold(&r.sim, HoldReason::PoorQuality).await;
}

#[tokio::test]
async fn stalled_feed_holds_as_stale() {
    let scen = line_scenario(|t, p| (t < 0.4).then_some((Some(p), 0.2)));
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "stale hold", |s| {
        s.state == LinkState::Holding(HoldReason::Stale)
    })
    .await;
    wait_robot_hold(&r.sim, HoldReason::Stale).await;
    // No target goes out while the feed is stalled.
    let n = targets(&r.sim.log()).len();
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(targets(&r.sim.log()).len(), n);
}

#[tokio::test]
async fn leaving_the_workspace_latches_a_hold() {
    // From x = 250 towards the +300 boundary and back, at 100 mm/s.
    let scen: Scenario = Arc::new(|t| {
        let x = if t < 1.0 {
            250.0 + 100.0 * t
        } else {
            350.0 - 100.0 * (t - 1.0)
        };
        Some((Some([x, 0.0, 200.0]), 0.2))
    });
    let r = rig(sim_cfg(1, [250.0, 0.0, 200.0]), 100.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "workspace hold", |s| {
        s.state == LinkState::Holding(HoldReason::Workspace)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(1500)).await; // marker back inside: stays held
    assert_eq!(r.link.status().state, LinkState::Holding(HoldReason::Workspace));
    assert!(targets(&r.sim.log()).iter().all(|t| t.3[0] <= 300.0));
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn a_jump_latches_and_enable_requires_the_marker_at_the_tool() {
    let scen: Scenario = Arc::new(|t| {
        let p = if (0.4..1.2).contains(&t) {
            [60.0, 0.0, 200.0]
        } else {
            [0.0, 0.0, 200.0]
        };
        Some((Some(p), 0.2))
    });
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "step hold", |s| {
        s.state == LinkState::Holding(HoldReason::StepTooLarge)
    })
    .await;
    r.link.enable(); // marker still 60 mm from the tool: must stay held
    tokio::time::sleep(Duration::from_millis(200)).await;
    assert_eq!(
        r.link.status().state,
        LinkState::Holding(HoldReason::StepTooLarge)
    );
    wait_for(&r.link, "marker back", |_| true).await;
    tokio::time::sleep(Duration::from_millis(900)).await; // marker returned to the tool at 1.2 s
    r.link.enable();
    wait_for(&r.link, "motion again", |s| s.state == LinkState::Moving).await;
    assert!(targets(&r.sim.log()).iter().all(|t| t.3[0] < 1.0));
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn too_fast_motion_latches() {
    // 600 mm/s at 200 Hz: 3 mm per frame, under the step limit but over the speed limit.
    let scen: Scenario = Arc::new(|t| {
        let x = if t < 0.4 {
            20.0 * t
        } else {
            8.0 + 600.0 * (t - 0.4)
        };
        Some((Some([x.min(250.0), 0.0, 200.0]), 0.2))
    });
    let mut sim = sim_cfg(3, [0.0, 0.0, 200.0]);
    sim.robot.speed_mm_s = 1000.0;
    let r = rig(sim, 200.0, scen).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "speed hold", |s| {
        s.state == LinkState::Holding(HoldReason::TooFast)
    })
    .await;
    wait_robot_hold(&r.sim, HoldReason::TooFast).await;
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn deadman_release_holds_and_press_resumes() {
    let r = rig(
        sim_cfg(1, [0.0, 0.0, 200.0]),
        100.0,
        line_scenario(|_, p| Some((Some(p), 0.2))),
    )
    .await;
    connect_and_enable(&r).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    r.deadman.set(false);
    wait_for(&r.link, "deadman hold", |s| {
        s.state == LinkState::Holding(HoldReason::Deadman)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let stopped_at = r.sim.trace().last().unwrap().1;
    let n = targets(&r.sim.log()).len();
    tokio::time::sleep(Duration::from_millis(150)).await;
    assert_eq!(targets(&r.sim.log()).len(), n);
    assert!(
        dist(r.sim.trace().last().unwrap().1, stopped_at) < 1e-9,
        "robot moved while deadman released"
    );
    // 0.2 s at 20 mm/s = 4 mm away: within the step limit, so pressing again resumes.
    r.deadman.set(true);
    wait_for(&r.link, "resume", |s| s.state == LinkState::Moving).await;
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn silent_robot_times_out_and_link_reconnects() {
    let mut sim = sim_cfg(1, [0.0, 0.0, 200.0]);
    sim.silent_after = 5;
    let r = rig(sim, 100.0, line_scenario(|_, p| Some((Some(p), 0.2)))).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "timeout", |s| {
        s.last_error.as_deref().is_some_and(|e| e.contains("no message"))
    })
    .await;
    wait_for(&r.link, "reconnect", |s| s.connects >= 2).await;
    assert_eq!(r.link.status().state, LinkState::Holding(HoldReason::NotEnabled));
}

#[tokio::test]
async fn garbage_from_the_robot_ends_the_session_and_motion_needs_a_new_enable() {
    let mut sim = sim_cfg(1, [0.0, 0.0, 200.0]);
    sim.garbage_after = 10;
    let r = rig(sim, 100.0, line_scenario(|_, p| Some((Some(p), 0.2)))).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "protocol error", |s| {
        s.last_error.as_deref().is_some_and(|e| e.contains("robot"))
    })
    .await;
    wait_for(&r.link, "reconnect", |s| s.connects >= 2).await;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let log = r.sim.log();
    // Nothing was sent on the garbled connection after the garbage arrived.
    let garbage_at = log
        .iter()
        .find(|e| e.2 == SimLog::GarbageSent)
        .map(|e| e.0)
        .expect("garbage sent");
    let after: Vec<_> = r
        .sim
        .received()
        .into_iter()
        .filter(|t| t.conn == 1 && t.t_s > garbage_at + 0.01)
        .collect();
    assert!(after.is_empty(), "targets after garbage: {after:?}");
    // Reconnected, but held until enabled again: no target on the new connection.
    assert_eq!(r.link.status().state, LinkState::Holding(HoldReason::NotEnabled));
    assert!(r.sim.received().iter().all(|t| t.conn == 1));
    let err = r.link.status().last_error.unwrap_or_default();
    println!("link error after garbage: {err}");
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn heartbeats_flow_while_idle() {
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, still([0.0, 0.0, 200.0])).await;
    wait_for(&r.link, "connection", |s| {
        s.state == LinkState::Holding(HoldReason::NotEnabled)
    })
    .await;
    // Idle for 3 peer timeouts: both sides' heartbeats keep the link up.
    tokio::time::sleep(Duration::from_millis(900)).await;
    let s = r.link.status();
    assert_eq!(s.connects, 1, "{s:?}");
    assert_eq!(s.last_error, None);
}

#[tokio::test]
async fn rejected_targets_are_counted_and_motion_continues() {
    let mut sim = sim_cfg(1, [0.0, 0.0, 200.0]);
    sim.robot.reject_every = 5;
    sim.inject_delay_ms = 5;
    let r = rig(sim, 100.0, line_scenario(|_, p| Some((Some(p), 0.2)))).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "rejects", |s| s.rejects >= 3).await;
    assert_eq!(r.link.status().state, LinkState::Moving);
    assert_no_violation(&r.sim);
}

#[tokio::test]
async fn shutdown_holds_and_says_bye() {
    let r = rig(sim_cfg(1, [0.0, 0.0, 200.0]), 100.0, still([0.0, 0.0, 200.0])).await;
    connect_and_enable(&r).await;
    wait_for(&r.link, "moving", |s| s.state == LinkState::Moving).await;
    let Rig { sim, link, .. } = r;
    link.shutdown().await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let log = sim.log();
    assert_eq!(holds(&log).last().map(|h| h.1), Some(HoldReason::Stop));
    assert!(matches!(log.last(), Some((_, _, SimLog::Disconnected, _))));
}

#[tokio::test]
async fn unreachable_robot_backs_off_and_reports() {
    // Bind and drop to get a port nobody listens on.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let (_tx, rx) = watch::channel(None);
    let link = LinkHandle::spawn_socket(
        link_cfg(port),
        rx,
        MonotonicClock,
        Arc::new(crate::deadman::NoDeadman),
    )
    .unwrap();
    wait_for(&link, "connect error", |s| {
        s.last_error.as_deref().is_some_and(|e| e.contains("connect"))
    })
    .await;
    assert_eq!(link.status().connects, 0);
}
