//! The cell survey end to end with the real binaries as separate processes: `host-tools
//! robot-sim` carries the LED on its flange with a simulated robot's errors (repeatability and a
//! smooth absolute error field) and tells irtrackd's simulated cameras where the LED really is
//! (`--cell-feed` / `[source.sim.cell]`, a transform only the simulator knows); `host-tools
//! survey` drives the robot through a grid, registers tracker to robot base with the LED's
//! flange offset solved from turned visits, and reports FRE/TRE. The figures are checked
//! against what the configured error model predicts for exactly these points, in both
//! directions, so a robot-sim that applied no error or a larger one fails the test. Finally the
//! registration is pushed (signed) and irtrackd streams robot-base coordinates.
//!
//! The binaries belong to other packages: run `cargo build -p irtrack-firmware -p
//! irtrack-host-tools` first (same target dir).

mod common;

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::*;
use irtrack_core::camera::RigidTransform;
use irtrack_core::params::RigParams;
use irtrack_core::registration;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_firmware::source::sim::{SimCellConfig, SimSourceConfig};
use irtrack_robot::cell::{RobotErrorModel, led_position_mm};
use irtrack_sim::Scenario;
use nalgebra::{UnitQuaternion, Vector3};

/// The simulated robot's errors (robot-sim's flags below say the same).
const MODEL: RobotErrorModel = RobotErrorModel {
    repeatability_mm: 0.02,
    field_rms_mm: 0.3,
    // Short enough that a rigid registration cannot absorb the field over the 160 mm box.
    field_wavelength_mm: 300.0,
    orientation_rms_deg: 0.0,
    seed: 7,
};
/// The LED on the flange (flange frame), unknown to the survey.
const LED_OFFSET_MM: [f64; 3] = [12.0, -8.0, 95.0];
/// Survey box (robot base frame) and the flange orientation: tool pointing down.
const BOX_MIN: [f64; 3] = [420.0, -80.0, 220.0];
const BOX_MAX: [f64; 3] = [580.0, 80.0, 380.0];
const ORIENT: [f64; 4] = [0.0, 0.0, 1.0, 0.0];
/// Tracker noise allowance per averaged point (exact simulated rig, ~0.02 mm per frame).
const TRACKER_MM: f64 = 0.05;

/// The cell's truth: camera 0's pose in the robot base frame, chosen so that the middle of the
/// survey volume's LED positions lies where the simulated cameras' axes cross.
fn cam0_from_base(centre_cam0: Vector3<f64>) -> (UnitQuaternion<f64>, Vector3<f64>) {
    let rot_deg = Vector3::new(20.0, -150.0, 35.0);
    let r = UnitQuaternion::from_scaled_axis(rot_deg.map(f64::to_radians));
    let mid = Vector3::from(BOX_MIN).lerp(&Vector3::from(BOX_MAX), 0.5);
    let led_mid = Vector3::from(led_position_mm([mid.x, mid.y, mid.z], ORIENT, LED_OFFSET_MM));
    (r, centre_cam0 - r * led_mid)
}

struct Row {
    role: String,
    robot: [f64; 3],
    quat: [f64; 4],
}

fn read_csv(path: &Path) -> Vec<Row> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            let n = |i: usize| f[i].parse::<f64>().unwrap();
            Row {
                role: f[1].to_string(),
                robot: [n(2), n(3), n(4)],
                quat: [n(5), n(6), n(7), n(8)],
            }
        })
        .collect()
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// The TRE the error field alone gives on these points: the LED's true positions with the field
/// applied, registered rigidly on the fit points onto the nominal ones, residuals on the rest.
fn predicted_tre(rows: &[Row]) -> (f64, f64) {
    let nominal: Vec<[f64; 3]> = rows
        .iter()
        .map(|r| led_position_mm(r.robot, r.quat, LED_OFFSET_MM))
        .collect();
    let actual: Vec<[f64; 3]> = rows
        .iter()
        .map(|r| {
            let f = MODEL.field_mm(r.robot);
            let p = [r.robot[0] + f[0], r.robot[1] + f[1], r.robot[2] + f[2]];
            led_position_mm(p, r.quat, LED_OFFSET_MM)
        })
        .collect();
    let fit: Vec<usize> = (0..rows.len()).filter(|&i| rows[i].role != "holdout").collect();
    let held: Vec<usize> = (0..rows.len()).filter(|&i| rows[i].role == "holdout").collect();
    let reg = registration::fit(
        &fit.iter().map(|&i| actual[i]).collect::<Vec<_>>(),
        &fit.iter().map(|&i| nominal[i]).collect::<Vec<_>>(),
        false,
    )
    .unwrap();
    let res = registration::residuals_mm(
        &reg,
        &held.iter().map(|&i| actual[i]).collect::<Vec<_>>(),
        &held.iter().map(|&i| nominal[i]).collect::<Vec<_>>(),
    );
    (rms(&res), res.iter().copied().fold(0.0, f64::max))
}

/// `host-tools robot-sim` with its robot and cell-feed listeners on 127.0.0.1:0 (home
/// 500,0,300, 300 mm/s), the LED (or the tool's origin) at `led_offset_mm` on the flange, the
/// tool turned by `mount_deg` (a rotation vector; zero for a lone LED) and the errors of
/// `model`. Returns the process, the robot's address and the cell feed's.
fn start_robot_sim(
    led_offset_mm: [f64; 3],
    mount_deg: [f64; 3],
    model: &RobotErrorModel,
) -> (Proc, String, String) {
    let xyz = |v: [f64; 3]| format!("{},{},{}", v[0], v[1], v[2]);
    let mut sim = spawn(
        Command::new(bin("host-tools"))
            .args([
                "robot-sim",
                "--listen",
                "127.0.0.1:0",
                "--cell-feed",
                "127.0.0.1:0",
            ])
            .args(["--home", "500,0,300", "--speed-mm-s", "300"])
            .arg(format!("--led-offset-mm={}", xyz(led_offset_mm)))
            .arg(format!("--tool-mount-rotation-deg={}", xyz(mount_deg)))
            .arg(format!("--repeatability-mm={}", model.repeatability_mm))
            .arg(format!("--abs-error-rms-mm={}", model.field_rms_mm))
            .arg(format!("--abs-error-wavelength-mm={}", model.field_wavelength_mm))
            .arg(format!(
                "--abs-orientation-error-rms-deg={}",
                model.orientation_rms_deg
            ))
            .arg(format!("--error-seed={}", model.seed))
            .stderr(Stdio::null()),
        "robot-sim",
    );
    let prefixes = ["robot-sim listening on ", "robot-sim cell feed on "];
    let lines = sim.wait_lines(&prefixes, Duration::from_secs(10)).unwrap();
    let addr = |i: usize| lines[i].trim_start_matches(prefixes[i]).trim().to_string();
    let (robot, feed) = (addr(0), addr(1));
    (sim, robot, feed)
}

/// The board's irtrackd.toml as the survey reads it: its [robot.safety] limits govern the
/// survey (robot-sim moves at 300 mm/s).
fn board_toml(robot_addr: &str, max_speed_mm_s: f64) -> String {
    format!(
        "[leds]\nbackend = \"none\"\n[robot]\naddress = {robot_addr:?}\n[robot.safety]\n\
         workspace_min_mm = [300.0, -300.0, 100.0]\nworkspace_max_mm = [700.0, 300.0, 500.0]\n\
         max_step_mm = 40.0\nmax_speed_mm_s = {max_speed_mm_s:?}\nmax_gap_mm = 2.0\n\
         max_age_ms = 200\nmax_rotation_step_deg = 10.0\n[robot.deadman]\nkind = \"flag\"\n"
    )
}

fn figure(out: &str, key: &str) -> f64 {
    out.lines()
        .find_map(|l| l.split(key).nth(1))
        .and_then(|r| r.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no {key:?} in the survey output:\n{out}"))
}

#[test]
fn survey_registers_the_simulated_cell_and_measures_its_error_model() {
    let t_start = Instant::now();
    let dir = temp_dir("survey");
    let sim_cfg = SimSourceConfig::default();
    let scenario = Scenario::new(sim_cfg.scenario_config()).unwrap();
    let rig: RigParams = scenario.rig().clone();
    std::fs::write(dir.join("rig.irp"), rig.to_blob().unwrap()).unwrap();
    let centre = sim_cfg
        .scenario_config()
        .rig
        .workspace_centre_mm(sim_cfg.distance_mm);
    let (r_cb, t_cb) = cam0_from_base(centre);

    // The robot with its errors and the LED on its flange.
    let (_sim, robot_addr, feed_addr) = start_robot_sim(LED_OFFSET_MM, [0.0; 3], &MODEL);

    // irtrackd on the cell's cameras; the transform is the simulator's secret.
    let o = Command::new(bin("host-tools"))
        .args(["keygen", "--out"])
        .arg(dir.join("site"))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "keygen: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let cell = SimCellConfig {
        robot: feed_addr.clone(),
        cam0_from_base_rotation_deg: r_cb.scaled_axis().map(f64::to_degrees).into(),
        cam0_from_base_translation_mm: t_cb.into(),
        timeout_ms: 20,
    };
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            "[service]\nparams_from_simulator = true\n[params]\ntrusted_keys = [{:?}]\n\
             [leds]\nbackend = \"none\"\n[source.sim]\n[source.sim.cell]\nrobot = {:?}\n\
             cam0_from_base_rotation_deg = {:?}\ncam0_from_base_translation_mm = {:?}\n",
            dir.join("site.pub").display().to_string(),
            cell.robot,
            cell.cam0_from_base_rotation_deg,
            cell.cam0_from_base_translation_mm
        ),
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let stream = addr_field(&ready, "stream=");
    let params_addr = addr_field(&ready, "params=");

    // robot-sim moves at 300 mm/s, below max_speed_mm_s (400) here.
    let board = |max_speed_mm_s: f64| board_toml(&robot_addr, max_speed_mm_s);
    let safety = dir.join("board-irtrackd.toml");
    std::fs::write(&safety, board(400.0)).unwrap();
    let report = dir.join("report");
    let survey = |tolerance_mm: f64, grid: &str, rotations: &str, params: &str, out: &str| {
        Command::new(bin("host-tools"))
            .args(["survey", "--stream", &stream.to_string(), "--robot", &robot_addr])
            .arg("--safety")
            .arg(&safety)
            .arg(format!("--box-min={},{},{}", BOX_MIN[0], BOX_MIN[1], BOX_MIN[2]))
            .arg(format!("--box-max={},{},{}", BOX_MAX[0], BOX_MAX[1], BOX_MAX[2]))
            .arg(format!(
                "--orient={},{},{},{}",
                ORIENT[0], ORIENT[1], ORIENT[2], ORIENT[3]
            ))
            .args(["--grid", grid, "--frames", "10", "--settle-ms", "150"])
            .args(["--rotations", rotations, "--rotation-deg", "25"])
            .arg(format!("--tolerance-mm={tolerance_mm}"))
            .arg("--params")
            .arg(dir.join(params))
            .arg("--out")
            .arg(dir.join(out))
            .arg("--report")
            .arg(&report)
            .output()
            .unwrap()
    };
    let o = survey(1.0, "3,3,3", "6", "rig.irp", "registered.irp");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "survey failed:\n{out}\n{err}");
    assert!(
        out.contains("under the [robot.safety] limits") && out.contains("step limit 40 mm"),
        "{out}"
    );
    for l in out.lines().filter(|l| !l.contains("point ")) {
        println!("{l}");
    }

    // What the error model predicts for exactly the points the robot reported.
    let rows = read_csv(&report.join("survey.csv"));
    assert_eq!(rows.len(), 27 + 6, "every point measured:\n{out}");
    let (pred_rms, pred_max) = predicted_tre(&rows);
    let tre_line = out.lines().find(|l| l.starts_with("survey: TRE")).unwrap();
    let tre_rms = figure(tre_line, "RMS ");
    let tre_max = figure(tre_line, "max ");
    let fre_rms = figure(&out, "FRE RMS ");
    // Noise on top of the field: repeatability and the tracker's per-point noise.
    let noise = (MODEL.repeatability_mm.powi(2) + TRACKER_MM.powi(2)).sqrt();
    let upper = (MODEL.field_rms_mm.powi(2) + noise.powi(2)).sqrt();
    println!(
        "survey e2e: FRE RMS {fre_rms:.3} mm, TRE RMS {tre_rms:.3} mm (error field alone predicts \
         {pred_rms:.3}, max {pred_max:.3}; noise allowance {noise:.3}; model bound {upper:.3}), {:.1} s",
        t_start.elapsed().as_secs_f64()
    );
    // The field is visible at these points: otherwise the check below could not fail.
    assert!(
        pred_rms > 3.0 * noise,
        "the error field is too small to check ({pred_rms:.3} mm)"
    );
    assert!(
        (tre_rms - pred_rms).abs() <= 2.0 * noise + 0.15 * pred_rms,
        "TRE RMS {tre_rms:.3} mm does not match the error model's {pred_rms:.3} mm"
    );
    assert!(
        tre_rms <= upper,
        "TRE RMS {tre_rms:.3} mm above the model bound {upper:.3} mm"
    );
    assert!(
        fre_rms <= upper,
        "FRE RMS {fre_rms:.3} mm above the model bound {upper:.3} mm"
    );
    assert!(tre_max <= 1.0, "pass/fail used a tolerance of 1 mm");
    let md = std::fs::read_to_string(report.join("survey.md")).unwrap();
    assert!(md.contains("**PASS**"), "{md}");
    assert!(
        std::fs::metadata(report.join("error-vs-distance.png"))
            .unwrap()
            .len()
            > 1000
    );

    // The LED offset solved from the turned visits.
    let offset_line = md.lines().find(|l| l.starts_with("LED offset")).unwrap();
    let nums: Vec<f64> = offset_line
        .split(['[', ']'])
        .nth(1)
        .unwrap()
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect();
    let off_err = (Vector3::from_column_slice(&nums) - Vector3::from(LED_OFFSET_MM)).norm();
    println!("survey e2e: LED offset {offset_line:?}, {off_err:.3} mm from the truth");
    assert!(off_err < 1.0, "LED offset {off_err:.3} mm off");

    // The written registration against the cell's truth (it also absorbs the field's rigid part).
    let reg = RigParams::from_blob(&std::fs::read(dir.join("registered.irp")).unwrap()).unwrap();
    let w = reg.world_from_cam0.expect("registration written");
    let truth = RigidTransform::from_parts(&r_cb.to_rotation_matrix().into_inner(), &t_cb).inverse();
    let d_rot_deg = UnitQuaternion::from_matrix(&(w.rotation() * truth.rotation().transpose()))
        .angle()
        .to_degrees();
    let d_t = (w.apply(&centre) - truth.apply(&centre)).norm();
    println!("survey e2e: registration vs truth: rotation {d_rot_deg:.4}°, at the volume centre {d_t:.3} mm");
    assert!(d_rot_deg < 0.2 && d_t < 1.0);

    // Signed push: irtrackd now streams robot-base coordinates, where the robot put the LED.
    let o = Command::new(bin("host-tools"))
        .args(["push-params", "--retries", "0", "--to", &params_addr.to_string()])
        .arg(dir.join("registered.irp"))
        .arg("--sign-key")
        .arg(dir.join("site.key"))
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "push-params: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let last = rows.last().unwrap();
    let led_nominal = Vector3::from(led_position_mm(last.robot, last.quat, LED_OFFSET_MM));
    let s = TcpStream::connect(stream).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut world = Vec::new();
    for line in BufReader::new(s).lines() {
        let r = PositionRecord::from_ndjson_line(&line.unwrap()).unwrap();
        if r.world_frame && r.status == TrackStatus::Ok {
            world.push(Vector3::from(r.position_mm.unwrap()));
            if world.len() == 20 {
                break;
            }
        }
        assert!(Instant::now() < deadline, "no world-frame records after the push");
    }
    let mean = world.iter().sum::<Vector3<f64>>() / world.len() as f64;
    let off = (mean - led_nominal).norm();
    println!("survey e2e: streamed robot-base position {off:.3} mm from where the robot put the LED");
    assert!(off < 1.0);

    // Surveying again, now against the registered stream (a quick grid): a tolerance the cell
    // cannot meet fails (non-zero exit, FAIL in the report).
    let o = survey(0.05, "2,2,2", "0", "registered.irp", "again.irp");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(!o.status.success() && out.contains("FAIL"), "{out}");

    // Under a speed limit the survey's targets break, the supervisor holds the second target: the
    // survey stops at once, non-zero, with the reason on stderr and in the report.
    std::fs::write(&safety, board(1.0)).unwrap();
    let o = survey(1.0, "2,2,2", "0", "registered.irp", "held.irp");
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("safety supervisor") && err.contains("TooFast") && err.contains("stopped"),
        "{err}"
    );
    let md = std::fs::read_to_string(report.join("survey.md")).unwrap();
    assert!(md.contains("STOPPED") && md.contains("TooFast"), "{md}");
    assert!(!dir.join("held.irp").exists());
    // A box outside the workspace is refused before anything moves.
    std::fs::write(&safety, board(400.0).replace("500.0]", "350.0]")).unwrap();
    let o = survey(1.0, "2,2,2", "0", "registered.irp", "held.irp");
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success() && err.contains("axis z"), "{err}");
    println!("survey e2e: total {:.1} s", t_start.elapsed().as_secs_f64());
}

/// The simulated robot's errors in the tool survey: the position errors above and a smooth
/// orientation error of the flange (0.1° RMS, as joint offsets give a small robot).
const TOOL_MODEL: RobotErrorModel = RobotErrorModel {
    orientation_rms_deg: 0.1,
    seed: 11,
    ..MODEL
};
/// The tool survey's box: smaller than the LED's, so that the tool's LEDs (up to 100 mm from
/// its origin) stay in both cameras' view at every corner and turn.
const TOOL_BOX_MIN: [f64; 3] = [450.0, -50.0, 250.0];
const TOOL_BOX_MAX: [f64; 3] = [550.0, 50.0, 350.0];
/// The tool's origin on the flange (flange frame), unknown to the survey.
const TOOL_ORIGIN_MM: [f64; 3] = [10.0, -5.0, 120.0];
/// Tracker noise allowance per averaged orientation: probe4's LEDs ~100 mm apart, ~0.02 mm per
/// LED and frame, 10 frames averaged: ~0.004°; allowed 0.02°.
const TRACKER_DEG: f64 = 0.02;

/// The rotation nearest to `m` (SVD).
fn nearest_rotation(m: &nalgebra::Matrix3<f64>) -> nalgebra::Matrix3<f64> {
    let svd = m.svd(true, true);
    let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
    let d = (u * v_t).determinant().signum();
    u * nalgebra::Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t
}

fn uq(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// What the error model predicts for the survey's orientation errors on exactly these points
/// (RMS over the fit points, RMS over the held-out ones, the registration's rotation error):
/// the tool's true poses (error fields applied, repeatability left out), a rigid registration
/// of their origins onto the nominal ones on the fit points, the tool's rotation on the flange
/// fitted as the survey fits it, and the angles left.
fn predicted_orientation(rows: &[Row], mount: &UnitQuaternion<f64>) -> (f64, f64, f64) {
    let nominal: Vec<[f64; 3]> = rows
        .iter()
        .map(|r| led_position_mm(r.robot, r.quat, TOOL_ORIGIN_MM))
        .collect();
    let actual: Vec<([f64; 3], UnitQuaternion<f64>)> = rows
        .iter()
        .map(|r| {
            let (p, q) = TOOL_MODEL.actual_pose(r.robot, r.quat, None);
            (led_position_mm(p, q, TOOL_ORIGIN_MM), uq(q) * mount)
        })
        .collect();
    let fit: Vec<usize> = (0..rows.len()).filter(|&i| rows[i].role != "holdout").collect();
    let reg = registration::fit(
        &fit.iter().map(|&i| actual[i].0).collect::<Vec<_>>(),
        &fit.iter().map(|&i| nominal[i]).collect::<Vec<_>>(),
        false,
    )
    .unwrap();
    let b = reg.transform.rotation();
    let f = |i: usize| uq(rows[i].quat).to_rotation_matrix().into_inner();
    let bt = |i: usize| b * actual[i].1.to_rotation_matrix().into_inner();
    let sum = fit.iter().fold(nalgebra::Matrix3::zeros(), |acc, &i| {
        acc + f(i).transpose() * bt(i)
    });
    let x = nearest_rotation(&sum);
    let err = |i: usize| {
        UnitQuaternion::from_matrix(&(bt(i) * (f(i) * x).transpose()))
            .angle()
            .to_degrees()
    };
    let held: Vec<f64> = (0..rows.len())
        .filter(|&i| rows[i].role == "holdout")
        .map(err)
        .collect();
    let fitted: Vec<f64> = fit.iter().map(|&i| err(i)).collect();
    let b_deg = UnitQuaternion::from_matrix(&b).angle().to_degrees();
    (rms(&fitted), rms(&held), b_deg)
}

#[test]
fn survey_with_a_tool_solves_its_mount_and_measures_orientation_errors() {
    let t_start = Instant::now();
    let dir = temp_dir("survey-tool");
    let sim_cfg = SimSourceConfig {
        tool: Some("probe4".into()),
        ..SimSourceConfig::default()
    };
    let centre = sim_cfg
        .scenario_config()
        .rig
        .workspace_centre_mm(sim_cfg.distance_mm);
    // The cell's truth: camera 0 turned as in the LED survey, the middle of the volume's tool
    // origins where the cameras' axes cross.
    let r_cb = UnitQuaternion::from_scaled_axis(Vector3::new(20.0, -150.0, 35.0).map(f64::to_radians));
    let mid = Vector3::from(TOOL_BOX_MIN).lerp(&Vector3::from(TOOL_BOX_MAX), 0.5);
    let origin_mid = Vector3::from(led_position_mm([mid.x, mid.y, mid.z], ORIENT, TOOL_ORIGIN_MM));
    let t_cb = centre - r_cb * origin_mid;
    // The tool's rotation on the flange: at `--orient` the tool faces the cameras as the
    // simulator's turning tool does at rest (no two LEDs on one image row in the 90° pair).
    let rest_cam0 = UnitQuaternion::from_euler_angles(0.2, -0.3, 0.4);
    let mount = uq(ORIENT).inverse() * r_cb.inverse() * rest_cam0;
    let mount_deg = mount.scaled_axis().map(f64::to_degrees);

    let (_sim, robot_addr, feed_addr) = start_robot_sim(
        TOOL_ORIGIN_MM,
        [mount_deg.x, mount_deg.y, mount_deg.z],
        &TOOL_MODEL,
    );

    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n\
             [source.sim]\ntool = \"probe4\"\n[source.sim.cell]\nrobot = {feed_addr:?}\n\
             cam0_from_base_rotation_deg = {:?}\ncam0_from_base_translation_mm = {:?}\n",
            <[f64; 3]>::from(r_cb.scaled_axis().map(f64::to_degrees)),
            <[f64; 3]>::from(t_cb),
        ),
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let stream = addr_field(&ready, "stream=");
    let safety = dir.join("board-irtrackd.toml");
    std::fs::write(&safety, board_toml(&robot_addr, 400.0)).unwrap();
    let report = dir.join("report");
    let survey = |tool: &str| {
        Command::new(bin("host-tools"))
            .args(["survey", "--stream", &stream.to_string(), "--robot", &robot_addr])
            .arg("--safety")
            .arg(&safety)
            .arg(format!(
                "--orient={},{},{},{}",
                ORIENT[0], ORIENT[1], ORIENT[2], ORIENT[3]
            ))
            .arg(format!(
                "--box-min={},{},{}",
                TOOL_BOX_MIN[0], TOOL_BOX_MIN[1], TOOL_BOX_MIN[2]
            ))
            .arg(format!(
                "--box-max={},{},{}",
                TOOL_BOX_MAX[0], TOOL_BOX_MAX[1], TOOL_BOX_MAX[2]
            ))
            .args(["--grid", "2,2,2", "--frames", "10", "--settle-ms", "150"])
            .args(["--rotations", "0", "--rotation-deg", "15"])
            .args([
                "--tool",
                tool,
                "--tool-orientations",
                "3",
                "--point-timeout-s",
                "8",
            ])
            .args(["--tolerance-mm", "1.0", "--tolerance-deg", "0.5"])
            .arg("--report")
            .arg(&report)
            .output()
            .unwrap()
    };
    // A tool the parameter set lacks is named, with the set's tools.
    let o = survey("wand9");
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(
        !o.status.success() && err.contains("no tool \"wand9\"") && err.contains("probe4"),
        "{err}"
    );

    let o = survey("probe4");
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "survey failed:\n{out}\n{err}");
    for l in out.lines().filter(|l| !l.contains("point ")) {
        println!("{l}");
    }
    let rows = read_csv(&report.join("survey.csv"));
    assert_eq!(rows.len(), 8 * 3, "every point in three orientations:\n{out}");
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(report.join("survey.json")).unwrap()).unwrap();
    let o_fit = j["orientation"]["fit"]["rms_deg"].as_f64().unwrap();
    let o_held = j["orientation"]["holdout"]["rms_deg"].as_f64().unwrap();
    let o_held_max = j["orientation"]["holdout"]["max_deg"].as_f64().unwrap();
    // The printed summary says the same as the JSON.
    let held_line = out
        .lines()
        .find(|l| l.starts_with("survey: orientation held out"))
        .unwrap();
    let printed = held_line
        .split("RMS ")
        .nth(1)
        .and_then(|r| r.split('°').next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap();
    assert!((printed - o_held).abs() < 1e-4, "{held_line} vs {o_held}");
    let m: Vec<f64> = j["orientation"]["mount_wxyz"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let mount_err_deg = uq([m[0], m[1], m[2], m[3]]).angle_to(&mount).to_degrees();
    let origin: Vec<f64> = j["led_offset_mm"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    let origin_err = (Vector3::from_column_slice(&origin) - Vector3::from(TOOL_ORIGIN_MM)).norm();

    // The bound: what the model predicts for these points, ± the tracker's noise. The robot's
    // orientation field (0.1° RMS) is what the errors measure; the fitted rotation on the flange
    // absorbs its mean, and the registration (fitted on positions, whose 0.3 mm field turns it
    // by `reg_deg`) adds at most that much. So the RMS lies at or below
    // 0.1° + reg_deg + noise, and within the noise of the exact prediction.
    let (pred_fit, pred_held, reg_deg) = predicted_orientation(&rows, &mount);
    let upper = TOOL_MODEL.orientation_rms_deg + reg_deg + TRACKER_DEG;
    println!(
        "survey tool e2e: orientation RMS fit {o_fit:.4}° (predicted {pred_fit:.4}°), held out \
         {o_held:.4}° max {o_held_max:.4}° (predicted {pred_held:.4}°); registration turned by the \
         position field {reg_deg:.4}°; bound {upper:.4}°; mount {mount_err_deg:.4}° and origin \
         {origin_err:.3} mm from the truth; {:.1} s",
        t_start.elapsed().as_secs_f64()
    );
    assert!(
        pred_held > 3.0 * TRACKER_DEG,
        "the orientation field is too small to check ({pred_held:.4}°)"
    );
    for (got, want, what) in [(o_fit, pred_fit, "fit"), (o_held, pred_held, "held out")] {
        assert!(
            (got - want).abs() <= 2.0 * TRACKER_DEG + 0.15 * want,
            "orientation RMS ({what}) {got:.4}° does not match the model's {want:.4}°"
        );
        assert!(
            got <= upper,
            "orientation RMS ({what}) {got:.4}° above the bound {upper:.4}°"
        );
    }
    assert!(mount_err_deg < 0.3, "mount rotation {mount_err_deg:.4}° off");
    assert!(origin_err < 1.0, "tool origin {origin_err:.3} mm off");
    assert_eq!(j["pass"], true, "{j}");
    let md = std::fs::read_to_string(report.join("survey.md")).unwrap();
    assert!(
        md.contains("**PASS**") && md.contains("Orientation of tool \"probe4\""),
        "{md}"
    );
}
