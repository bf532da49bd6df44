//! System test with the real binaries: `irtrackd` (simulated source) drives `host-tools
//! robot-sim` over the robot protocol after an explicit enable and deadman press on the status
//! port, and the robot's CSV log is checked against the simulator's marker path.
//!
//! The binaries belong to other packages, so cargo does not build them for this test: run
//! `cargo build -p irtrack-firmware -p irtrack-host-tools` first (same target dir).

mod common;

use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::*;
use irtrack_firmware::source::sim::SimSourceConfig;
use nalgebra::Vector3;

/// Marker circle radius used here: small, so the first target lies within `max_step_mm` of the
/// robot parked at the circle centre.
const RADIUS_MM: f64 = 15.0;
const MAX_STEP_MM: f64 = 20.0;

/// Points of the simulated marker's path (camera 0 frame), one per degree of the circle.
fn marker_path() -> Vec<Vector3<f64>> {
    let cfg = SimSourceConfig {
        radius_mm: RADIUS_MM,
        ..Default::default()
    }
    .scenario_config();
    let period_s = SimSourceConfig::default().period_s;
    (0..360)
        .map(|k| cfg.marker_position(&cfg.markers[0], period_s * f64::from(k) / 360.0))
        .collect()
}

#[test]
fn robot_follows_the_simulated_marker_after_network_enable() {
    let t_start = Instant::now();
    let dir = temp_dir("robot");
    let path = marker_path();
    let centre = path.iter().sum::<Vector3<f64>>() / path.len() as f64;
    let log = dir.join("robot.csv");

    let mut sim = spawn(
        Command::new(bin("host-tools"))
            .args(["robot-sim", "--listen", "127.0.0.1:0", "--home"])
            .arg(format!("{},{},{}", centre.x, centre.y, centre.z))
            .arg("--log")
            .arg(&log)
            .stderr(Stdio::null()),
        "robot-sim",
    );
    let line = sim
        .wait_line("robot-sim listening on ", Duration::from_secs(10))
        .unwrap();
    let robot_addr: SocketAddr = line
        .trim_start_matches("robot-sim listening on ")
        .trim()
        .parse()
        .unwrap();

    let (lo, hi) = (centre.add_scalar(-200.0), centre.add_scalar(200.0));
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            r#"
[service]
params_from_simulator = true
control = true
{}
[source.sim]
radius_mm = {RADIUS_MM}
[leds]
backend = "none"
[robot]
address = "{robot_addr}"
[robot.safety]
workspace_min_mm = [{}, {}, {}]
workspace_max_mm = [{}, {}, {}]
max_step_mm = {MAX_STEP_MM}
max_speed_mm_s = 250.0
max_gap_mm = 2.0
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "flag"
"#,
            operator_hash_line(),
            lo.x,
            lo.y,
            lo.z,
            hi.x,
            hi.y,
            hi.z
        ),
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");

    // Wait until the link is up (held, not enabled), then enable and press the deadman.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (code, body) = http_operator(status, "POST", "/robot");
        assert_eq!(code, 200, "{body}");
        if body.contains("\"state\":\"holding\"") {
            break;
        }
        assert!(Instant::now() < deadline, "robot link never came up: {body}");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (code, body) = http_operator(status, "POST", "/robot/deadman?pressed=maybe");
    assert_eq!(code, 400, "{body}");
    let (code, body) = http_operator(status, "POST", "/robot/enable");
    assert_eq!(code, 200, "{body}");
    let (code, body) = http_operator(status, "POST", "/robot/deadman?pressed=1");
    assert_eq!(code, 200, "{body}");
    assert!(body.contains("\"deadman_flag_pressed\":true"), "{body}");
    std::thread::sleep(Duration::from_secs(3));
    let (code, body) = http_operator(status, "POST", "/robot");
    assert_eq!(code, 200);
    assert!(
        body.contains("\"state\":\"moving\""),
        "link not moving after enable: {body}"
    );
    let (code, body) = http_operator(status, "POST", "/robot/disable");
    assert_eq!(code, 200, "{body}");
    std::thread::sleep(Duration::from_millis(300));
    drop(_irtrackd);
    drop(sim);

    // Targets from the CSV: distance to the marker path and steps between consecutive targets.
    let text = std::fs::read_to_string(&log).unwrap();
    let targets: Vec<Vector3<f64>> = text
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let xyz: Vec<f64> = f.get(4..7)?.iter().filter_map(|v| v.parse().ok()).collect();
            (xyz.len() == 3).then(|| Vector3::new(xyz[0], xyz[1], xyz[2]))
        })
        .collect();
    assert!(targets.len() >= 50, "only {} targets in 3 s", targets.len());
    let off: Vec<f64> = targets
        .iter()
        .map(|t| path.iter().map(|p| (t - p).norm()).fold(f64::INFINITY, f64::min))
        .collect();
    let mean = off.iter().sum::<f64>() / off.len() as f64;
    let max = off.iter().copied().fold(0.0, f64::max);
    let mut max_step = (targets[0] - centre).norm();
    for w in targets.windows(2) {
        max_step = max_step.max((w[1] - w[0]).norm());
    }
    let span = targets
        .iter()
        .map(|t| (t - targets[0]).norm())
        .fold(0.0, f64::max);
    println!(
        "robot e2e: {} targets, distance to marker path mean {mean:.3} mm max {max:.3} mm, \
         largest step {max_step:.3} mm (limit {MAX_STEP_MM}), span {span:.1} mm, {:.1} s",
        targets.len(),
        t_start.elapsed().as_secs_f64()
    );
    assert!(max < 2.0, "a target is {max:.3} mm off the marker path");
    assert!(
        max_step <= MAX_STEP_MM,
        "step {max_step:.3} mm exceeds max_step_mm"
    );
    // The robot really followed the circle, not one point of it.
    assert!(span > RADIUS_MM, "targets span only {span:.1} mm");
}

#[test]
fn robot_control_is_refused_unless_the_config_allows_it() {
    let dir = temp_dir("noctl");
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n",
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");
    for path in ["/robot/enable", "/robot/deadman?pressed=1"] {
        let (code, body) = http_operator(status, "POST", path);
        assert_eq!(code, 403, "{path}: {body}");
        assert!(body.contains("control = true"), "{path}: {body}");
    }
    // A stop is never refused for want of control (docs/security.md); with no robot link at
    // all there is nothing to stop, and the answer says so instead of pretending to act.
    let (code, body) = http_operator(status, "POST", "/robot/disable");
    assert_eq!(code, 409, "/robot/disable: {body}");
    assert!(body.contains("no robot link"), "/robot/disable: {body}");
    let (code, body) = http(status, "GET", "/status");
    assert_eq!(code, 200, "{body}");
}
