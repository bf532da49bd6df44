//! Demo step: irtrackd (simulated cameras) streams to a simulated robot controller, which
//! follows the marker after an explicit enable. Real binaries, real sockets on 127.0.0.1.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::util::{
    self, Irtrackd, IrtrackdConfig, Proc, addr_field, http, http_operator, json, operator_hash,
};
use anyhow::{Context, Result, bail};

const FOLLOW_S: u64 = 4;

/// Runs the step; `bin_dir` holds `irtrackd` and `host-tools`, `out` is the demo directory.
pub fn robot_follows(bin_dir: &Path, out: &Path) -> Result<()> {
    let dir = out.join("robot");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let log = dir.join("robot-sim.csv");
    let _ = std::fs::remove_file(&log);

    // A free port for the robot, so irtrackd's config can name it before robot-sim starts.
    let robot_addr = TcpListener::bind("127.0.0.1:0")?.local_addr()?;
    let config = dir.join("irtrackd.toml");
    let hash = operator_hash(&bin_dir.join("irtrackd"))?;
    irtrackd_config(robot_addr, &hash).write(&config)?;
    println!("starting irtrackd (simulated cameras, robot link to {robot_addr})");
    let (irtrackd, ready) = start_irtrackd(bin_dir, &config, &dir.join("state"))?;
    println!("{ready}");
    let status = addr_field(&ready, "status=")?;
    let stream = addr_field(&ready, "stream=")?;

    // Park the robot where the marker is now, as an operator would jog it there. The marker
    // circles 15 mm around its centre, so it stays within max_step_mm (40) of this point and the
    // first target after the enable is accepted.
    let start = first_position(stream)?;
    println!(
        "marker now at ({:.1}, {:.1}, {:.1}) mm; robot-sim starts there",
        start[0], start[1], start[2]
    );
    let mut robot = Proc::spawn(
        Command::new(bin_dir.join("host-tools"))
            .args(["robot-sim", "--listen", &robot_addr.to_string(), "--home"])
            .arg(format!("{},{},{}", start[0], start[1], start[2]))
            .arg("--log")
            .arg(&log)
            .stderr(Stdio::null()),
        "host-tools robot-sim",
    )?;
    robot.wait_line("robot-sim listening on ", Duration::from_secs(15))?;

    // The link connects (with backoff) and holds until explicitly enabled.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (_, body) = http_operator(status, "POST", "/robot")?;
        if body.contains("\"state\":\"holding\"") {
            println!("robot link up and holding: {}", short(&body));
            break;
        }
        if Instant::now() > deadline {
            bail!("the robot link did not come up: {body}");
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    for req in ["/robot/enable", "/robot/deadman?pressed=1"] {
        let (code, body) = http_operator(status, "POST", req)?;
        if code != 200 {
            bail!("POST {req} answered {code}: {body}");
        }
        println!("POST {req} -> {}", short(&body));
    }
    for _ in 0..FOLLOW_S {
        std::thread::sleep(Duration::from_secs(1));
        let (_, body) = http_operator(status, "POST", "/robot")?;
        println!("robot: {}", short(&body));
    }
    let (_, body) = http_operator(status, "POST", "/robot/disable")?;
    println!("POST /robot/disable -> {}", short(&body));
    std::thread::sleep(Duration::from_millis(300));
    drop(irtrackd);
    drop(robot);
    summarize(&log)
}

/// Demo step: the cell survey. robot-sim carries the LED on its flange with a simulated robot's
/// errors and tells irtrackd's simulated cameras where it really is (a simulator-only feed and a
/// base-to-camera transform the tracker never sees); `host-tools survey` drives the grid,
/// registers tracker to robot base and writes the report.
pub fn survey(bin_dir: &Path, out: &Path) -> Result<()> {
    let dir = out.join("survey");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let robot_addr = TcpListener::bind("127.0.0.1:0")?.local_addr()?;
    let feed_addr = std::net::UdpSocket::bind("127.0.0.1:0")?.local_addr()?;
    let mut robot = Proc::spawn(
        Command::new(bin_dir.join("host-tools"))
            .args(["robot-sim", "--listen", &robot_addr.to_string()])
            .args(["--cell-feed", &feed_addr.to_string(), "--home", "500,0,300"])
            .args(["--speed-mm-s", "300", "--led-offset-mm=12,-8,95"])
            .args(["--repeatability-mm", "0.02", "--abs-error-rms-mm", "0.3"])
            .args(["--abs-error-wavelength-mm", "300"])
            .stderr(Stdio::null()),
        "host-tools robot-sim",
    )?;
    robot.wait_line("robot-sim cell feed on ", Duration::from_secs(15))?;
    println!(
        "robot-sim: LED 12,-8,95 mm off the flange, repeatability 0.02 mm, absolute error field 0.3 mm RMS"
    );
    // Camera 0's pose in the robot base frame (rotation vector 20°, -150°, 35°), chosen so that the
    // survey box's middle lies where the simulated cameras' axes cross. Only the simulator knows it.
    let config = dir.join("irtrackd.toml");
    IrtrackdConfig::simulated()
        .comment("Written by `cargo xtask demo` (survey step).")
        .set("service.params_from_simulator", true)
        .set("source.sim.cell.robot", feed_addr.to_string())
        .set(
            "source.sim.cell.cam0_from_base_rotation_deg",
            vec![20.0, -150.0, 35.0],
        )
        .set(
            "source.sim.cell.cam0_from_base_translation_mm",
            vec![496.641, 173.055, 539.725],
        )
        .write(&config)?;
    // The board's config as the survey reads it (`--safety`): its [robot.safety] limits govern
    // the survey. A separate file, as this irtrackd must not connect to the robot itself (the
    // survey is the link's client). robot-sim moves at 300 mm/s, below max_speed_mm_s.
    let safety = dir.join("board-irtrackd.toml");
    IrtrackdConfig::new()
        .comment("Written by `cargo xtask demo` (survey step): the board's [robot] section.")
        .set("leds.backend", "none")
        .set("robot.address", robot_addr.to_string())
        .set("robot.safety.workspace_min_mm", vec![300.0, -300.0, 100.0])
        .set("robot.safety.workspace_max_mm", vec![700.0, 300.0, 500.0])
        .set("robot.safety.max_step_mm", 40.0)
        .set("robot.safety.max_speed_mm_s", 400.0)
        .set("robot.safety.max_gap_mm", 2.0)
        .set("robot.safety.max_age_ms", 200)
        .set("robot.safety.max_rotation_step_deg", 10.0)
        .set("robot.deadman.kind", "flag")
        .write(&safety)?;
    let (irtrackd, ready) = start_irtrackd(bin_dir, &config, &dir.join("state"))?;
    let stream = addr_field(&ready, "stream=")?;
    let scenario = out.join("scenario/rig.irp");
    let mut cmd = Command::new(bin_dir.join("host-tools"));
    cmd.args([
        "survey",
        "--stream",
        &stream.to_string(),
        "--robot",
        &robot_addr.to_string(),
    ])
    .arg("--safety")
    .arg(&safety)
    .args(["--box-min=420,-80,220", "--box-max=580,80,380", "--grid", "3,3,3"])
    .args([
        "--frames",
        "10",
        "--settle-ms",
        "150",
        "--rotations",
        "6",
        "--tolerance-mm",
        "1",
    ])
    .arg("--report")
    .arg(dir.join("report"));
    if scenario.is_file() {
        // The simulator's rig (the demo's first step wrote it): the registration goes into it.
        cmd.arg("--params")
            .arg(&scenario)
            .arg("--out")
            .arg(dir.join("rig-registered.irp"));
    }
    checked(&mut cmd, "host-tools survey")?;
    drop(irtrackd);
    drop(robot);
    println!("report: {}", dir.join("report/survey.md").display());
    Ok(())
}

/// Marker frames per circle in the calibration step: `[source.sim]` defaults (4 s period) at
/// the step's 30 fps.
const CIRCLE_FRAMES: u64 = 120;

/// Demo step: calibrate the simulated 90° rig from rendered checkerboard views, push the result
/// (signed) into an irtrackd that started without parameters, and show it taking effect.
/// `views_bin` is the `checkerboard_views` example of irtrack-tests.
pub fn calibrate_and_push(bin_dir: &Path, views_bin: &Path, out: &Path) -> Result<()> {
    let dir = out.join("calib");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let views = dir.join("views");
    let host_tools = bin_dir.join("host-tools");

    println!("-- 1. render checkerboard views of the simulated rig (and print its true parameters)");
    let rendered = checked(Command::new(views_bin).arg(&views), "checkerboard_views")?;
    let truth_circle = parse_truth_circle(&rendered);

    println!("-- 2. calibrate from the images alone (OpenCV), as on a real rig");
    let t = Instant::now();
    let mut cmd = Command::new(&host_tools);
    cmd.arg("calibrate")
        .arg("--images")
        .arg(&views)
        .args(["--board-cols", "9", "--board-rows", "6", "--square-mm", "25"])
        .args([
            "--joint-refine",
            "--fix-k3",
            "--rig-id",
            "demo-calibrated",
            "--out-dir",
        ])
        .arg(&dir);
    checked(&mut cmd, "host-tools calibrate")?;
    println!("calibrated in {:.1} s", t.elapsed().as_secs_f64());

    println!("-- 3. a signing key; irtrackd will trust only its public half");
    let key = dir.join("demo-key");
    let mut cmd = Command::new(&host_tools);
    cmd.args(["keygen", "--force", "--out"]).arg(&key);
    checked(&mut cmd, "host-tools keygen")?;

    println!("-- 4. irtrackd on the same simulated rig, started WITHOUT parameters");
    let state = dir.join("state");
    // A fresh state directory: a set stored by an earlier demo run would be loaded at start.
    if state.exists() {
        std::fs::remove_dir_all(&state).with_context(|| format!("removing {}", state.display()))?;
    }
    let config = dir.join("irtrackd.toml");
    calib_irtrackd_config(&dir.join("demo-key.pub")).write(&config)?;
    let (_irtrackd, ready) = start_irtrackd(bin_dir, &config, &state)?;
    println!("{ready}");
    let params = addr_field(&ready, "params=")?;
    let status = addr_field(&ready, "status=")?;
    let stream = addr_field(&ready, "stream=")?;
    let first = stream_lines(stream, Duration::from_secs(15), |_| Take::Last)?;
    let (_, body) = http(status, "GET", "/status")?;
    println!(
        "before the push: faults {}, stream record status {}, position {}",
        field(&body, "faults").unwrap_or_else(|| "?".into()),
        field(&first[0], "status").unwrap_or_else(|| "?".into()),
        field(&first[0], "position_mm").unwrap_or_else(|| "?".into())
    );

    println!("-- 5. push the calibration, signed");
    let mut cmd = Command::new(&host_tools);
    cmd.args(["push-params", "--to", &params.to_string(), "--sign-key"])
        .arg(dir.join("demo-key.key"))
        .arg(dir.join("rig.irp"));
    checked(&mut cmd, "host-tools push-params")?;

    println!("-- 6. the new set in use");
    // The loop switches sets before its next frame set; the fault clears then.
    let deadline = Instant::now() + Duration::from_secs(10);
    let body = loop {
        let (_, body) = http(status, "GET", "/status")?;
        if !body.contains("\"no_params\"") {
            break body;
        }
        if Instant::now() > deadline {
            bail!(
                "irtrackd still reports no_params 10 s after the push: {}",
                short(&body)
            );
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    println!(
        "status: rig {}, origin {}, signature policy {}, faults {}",
        field(&body, "params.rig_id").unwrap_or_else(|| "?".into()),
        field(&body, "params.origin").unwrap_or_else(|| "?".into()),
        field(&body, "params.signature_policy").unwrap_or_else(|| "?".into()),
        field(&body, "faults").unwrap_or_else(|| "?".into())
    );
    // One marker circle of positions (records of frames that were not tracked are shown too).
    let mut first_frame = None;
    let lines = stream_lines(stream, Duration::from_secs(30), |l| {
        let Some(frame) = field(l, "frame").and_then(|f| f.parse::<u64>().ok()) else {
            return Take::Skip;
        };
        let start = *first_frame.get_or_insert(frame);
        if frame + 1 < start + CIRCLE_FRAMES {
            Take::Keep
        } else {
            Take::Last
        }
    })?;
    summarize_circle(&lines, truth_circle)
}

/// Wand-wave frame sets the wand step captures: one full wave at 30 fps (10 s).
const WAND_SETS: u64 = 300;

/// Demo step: the 90° rig of the calibration step, now served by irtrackd showing a wand wave;
/// `host-tools capture --wand` saves the sets, `wand-calibrate` (intrinsics from the
/// checkerboard step, refined with its board views) gives the rig, and both calibrations are compared with the truth.
pub fn wand_calibration(bin_dir: &Path, out: &Path) -> Result<()> {
    let dir = out.join("wand");
    let intrinsics = out.join("calib/rig.yaml");
    let truth = out.join("calib/views/truth_rig.irp");
    for (f, from) in [
        (&intrinsics, "calibrate and push"),
        (&truth, "calibrate and push"),
    ] {
        if !f.is_file() {
            bail!("{} is missing: the `{from}` step makes it", f.display());
        }
    }
    let wave = dir.join("wave");
    // Capture numbers its sets after the ones already there; start from an empty wave.
    if wave.exists() {
        std::fs::remove_dir_all(&wave).with_context(|| format!("removing {}", wave.display()))?;
    }
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let host_tools = bin_dir.join("host-tools");

    println!("-- 1. irtrackd on the simulated 90-degree rig, showing a 0/120/300 mm wand being waved");
    let config = dir.join("irtrackd.toml");
    IrtrackdConfig::simulated()
        .comment("Written by `cargo xtask demo` (wand step).")
        .set("source.sim.fps", 30.0)
        .set("source.sim.wand_mm", vec![0.0, 120.0, 300.0])
        .set("source.sim.wand_frames", WAND_SETS as i64)
        .write(&config)?;
    let (irtrackd, ready) = start_irtrackd(bin_dir, &config, &dir.join("state"))?;
    let status = addr_field(&ready, "status=")?;

    println!("-- 2. host-tools capture --wand: {WAND_SETS} synchronised frame sets from the board");
    let mut cmd = Command::new(&host_tools);
    cmd.args(["capture", "--from", &status.to_string(), "--wand", "--count"])
        .arg(WAND_SETS.to_string())
        .arg("--out")
        .arg(&wave);
    checked(&mut cmd, "host-tools capture --wand")?;
    drop(irtrackd);

    println!(
        "-- 3. host-tools wand-calibrate: intrinsics from the checkerboard step; its board views \
         join the wand in one adjustment (--boards)"
    );
    let mut cmd = Command::new(&host_tools);
    cmd.arg("wand-calibrate")
        .arg("--frames")
        .arg(&wave)
        .arg("--intrinsics")
        .arg(&intrinsics)
        .arg("--boards")
        .arg(out.join("calib/views"))
        .args([
            "--board-cols",
            "9",
            "--board-rows",
            "6",
            "--square-mm",
            "25",
            "--wand-mm",
            "0,120,300",
            "--rig-id",
            "demo-wand",
        ])
        .arg("--out-dir")
        .arg(&dir);
    checked(&mut cmd, "host-tools wand-calibrate")?;

    println!("-- 4. both calibrations against the simulator's truth");
    for (label, file) in [
        ("checkerboard (stereo, OpenCV)", out.join("calib/rig.irp")),
        ("wand (bundle adjustment)", dir.join("rig.irp")),
    ] {
        let mut cmd = Command::new(&host_tools);
        cmd.arg("show-params").arg(&file).arg("--compare").arg(&truth);
        let text = crate::util::run(
            &mut cmd,
            crate::util::RunOpts {
                capture_stdout: true,
                quiet_stdout: true,
                ..Default::default()
            },
        )?;
        if !text.success() {
            bail!("`host-tools show-params --compare` failed ({})", text.describe());
        }
        let cmp = text
            .stdout
            .split_once("compared with")
            .map(|(_, c)| c)
            .context("show-params printed no comparison")?;
        println!("{label}:");
        for line in cmp.lines().skip(1) {
            println!("{line}");
        }
    }
    Ok(())
}

/// Starts the demo's irtrackd (`bin_dir/irtrackd`) with `config`; killed on drop.
fn start_irtrackd(bin_dir: &Path, config: &Path, state: &Path) -> Result<(Irtrackd, String)> {
    let d = util::start_irtrackd(&bin_dir.join("irtrackd"), config, state)?;
    let ready = d.ready().line.clone();
    Ok((d, ready))
}

/// Runs a command with its output shown; fails with its status if it fails. Returns stdout.
fn checked(cmd: &mut Command, what: &str) -> Result<String> {
    let out = crate::util::run(
        cmd,
        crate::util::RunOpts {
            capture_stdout: true,
            ..Default::default()
        },
    )?;
    if !out.success() {
        bail!("`{what}` failed ({}); see its output above", out.describe());
    }
    Ok(out.stdout)
}

fn calib_irtrackd_config(public_key: &Path) -> IrtrackdConfig {
    IrtrackdConfig::simulated()
        .comment("Written by `cargo xtask demo` (calibration step).")
        .set("service.params_from_simulator", false)
        .set("params.trusted_keys", vec![public_key.display().to_string()])
        .set("source.sim.fps", 30.0)
}

/// `(centre, radius)` from the `truth marker path: circle of radius R mm around (x, y, z) mm`
/// line of `checkerboard_views`.
fn parse_truth_circle(text: &str) -> Option<([f64; 3], f64)> {
    let line = text.lines().find(|l| l.starts_with("truth marker path:"))?;
    let radius = line
        .split("radius ")
        .nth(1)?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    let inner = line.split("around (").nth(1)?.split(')').next()?;
    let v: Vec<f64> = inner.split(',').filter_map(|x| x.trim().parse().ok()).collect();
    (v.len() == 3).then(|| ([v[0], v[1], v[2]], radius))
}

/// Centre and mean radius of the tracked positions, compared with the simulator's circle.
fn summarize_circle(lines: &[String], truth: Option<([f64; 3], f64)>) -> Result<()> {
    let points: Vec<[f64; 3]> = lines
        .iter()
        .filter_map(|l| json_array3(l, "position_mm"))
        .collect();
    // Positions missing from part of the circle would move the centre: demand most of them.
    if points.len() < lines.len() * 9 / 10 || lines.len() < CIRCLE_FRAMES as usize / 2 {
        bail!(
            "only {} tracked positions in {} records over one marker circle",
            points.len(),
            lines.len()
        );
    }
    let n = points.len() as f64;
    let c = [0, 1, 2].map(|k| points.iter().map(|p| p[k]).sum::<f64>() / n);
    let dist = |p: &[f64; 3], q: &[f64; 3]| {
        ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt()
    };
    let radius = points.iter().map(|p| dist(p, &c)).sum::<f64>() / n;
    let gaps: Vec<f64> = lines
        .iter()
        .filter_map(|l| field(l, "gap_mm").and_then(|g| g.parse().ok()))
        .collect();
    let gap = gaps.iter().sum::<f64>() / gaps.len().max(1) as f64;
    let crc = lines
        .first()
        .and_then(|l| field(l, "params_crc"))
        .and_then(|v| v.parse::<u32>().ok())
        .unwrap_or(0);
    println!(
        "stream: {} of {} records over one marker circle tracked, params_crc {crc:08x}: centre \
         ({:.2}, {:.2}, {:.2}) mm, radius {radius:.2} mm, mean ray gap {gap:.3} mm",
        points.len(),
        lines.len(),
        c[0],
        c[1],
        c[2]
    );
    if let Some((tc, tr)) = truth {
        println!(
            "simulator truth: centre ({:.2}, {:.2}, {:.2}) mm, radius {tr:.2} mm -> centre off by \
             {:.2} mm, radius off by {:+.2} mm (calibration error; tests/tests/calibrate_push_e2e.rs \
             measures it per position)",
            tc[0],
            tc[1],
            tc[2],
            dist(&c, &tc),
            radius - tr
        );
    }
    Ok(())
}

/// What to do with one stream line.
enum Take {
    Skip,
    Keep,
    /// Keep it and stop reading.
    Last,
}

/// Reads position stream lines as `take` decides, within `timeout`.
fn stream_lines(
    stream: SocketAddr,
    timeout: Duration,
    mut take: impl FnMut(&str) -> Take,
) -> Result<Vec<String>> {
    let s = TcpStream::connect(stream).context("connecting to the position stream")?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    let deadline = Instant::now() + timeout;
    let mut out = Vec::new();
    for line in BufReader::new(s).lines() {
        let line = line.context("reading the position stream")?;
        match take(&line) {
            Take::Skip => {}
            Take::Keep => out.push(line),
            Take::Last => {
                out.push(line);
                return Ok(out);
            }
        }
        if Instant::now() > deadline {
            bail!("the position stream did not deliver enough records within {timeout:?}");
        }
    }
    bail!("the position stream closed")
}

/// The value at a dotted `path` of a JSON document as text: a string without quotes, anything
/// else as compact JSON; `None` if the text is no JSON or has no such field.
pub(crate) fn field(body: &str, path: &str) -> Option<String> {
    let v = json::parse(body).ok()?;
    let f = json::at(&v, path)?;
    Some(f.as_str().map_or_else(|| f.to_string(), str::to_string))
}

fn irtrackd_config(robot: SocketAddr, operator_hash: &str) -> IrtrackdConfig {
    IrtrackdConfig::simulated()
        .comment("Written by `cargo xtask demo`.")
        .set("service.params_from_simulator", true)
        .set("service.control", true)
        .operator_hash(operator_hash)
        .set("source.sim.radius_mm", 15.0)
        .set("robot.address", robot.to_string())
        .set("robot.safety.workspace_min_mm", vec![-2000.0, -2000.0, 0.0])
        .set("robot.safety.workspace_max_mm", vec![2000.0, 2000.0, 4000.0])
        .set("robot.safety.max_step_mm", 40.0)
        .set("robot.safety.max_speed_mm_s", 400.0)
        .set("robot.safety.max_gap_mm", 2.0)
        .set("robot.safety.max_age_ms", 200)
        .set("robot.safety.require_world_frame", false)
        .set("robot.deadman.kind", "flag")
}

/// Reads robot-sim's CSV log and prints what the robot received and where it went.
fn summarize(log: &Path) -> Result<()> {
    let text = std::fs::read_to_string(log).with_context(|| format!("reading {}", log.display()))?;
    let mut targets: Vec<[f64; 3]> = Vec::new();
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let xyz: Vec<f64> = f
            .get(4..7)
            .unwrap_or(&[])
            .iter()
            .filter_map(|v| v.parse().ok())
            .collect();
        if xyz.len() == 3 {
            targets.push([xyz[0], xyz[1], xyz[2]]);
        }
    }
    if targets.len() < 10 {
        bail!(
            "the robot received only {} targets; see {}",
            targets.len(),
            log.display()
        );
    }
    let dist = |a: &[f64; 3], b: &[f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let max_step = targets.windows(2).map(|w| dist(&w[0], &w[1])).fold(0.0, f64::max);
    let extent = targets.iter().map(|t| dist(t, &targets[0])).fold(0.0, f64::max);
    println!(
        "robot received {} targets in {FOLLOW_S} s; path extent {extent:.1} mm (marker circle: 30 mm \
         diameter); largest step {max_step:.2} mm (limit 40 mm). Log: {}",
        targets.len(),
        log.display()
    );
    Ok(())
}

/// First tracked position from irtrackd's NDJSON stream.
fn first_position(stream: SocketAddr) -> Result<[f64; 3]> {
    let s = TcpStream::connect(stream).context("connecting to the position stream")?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    for line in BufReader::new(s).lines() {
        let line = line.context("reading the position stream")?;
        if let Some(p) = json_array3(&line, "position_mm") {
            return Ok(p);
        }
    }
    bail!("the position stream closed before a tracked position arrived")
}

/// `[x, y, z]` at `key` of one JSON line.
fn json_array3(line: &str, key: &str) -> Option<[f64; 3]> {
    json::vec3_at(&json::parse(line).ok()?, key)
}

fn short(body: &str) -> String {
    body.chars().take(160).collect()
}

/// Where the demo's binaries live.
pub fn bin_dir(host_tools: &Path) -> PathBuf {
    host_tools.parent().map(Path::to_path_buf).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_position_arrays_from_stream_lines() {
        let l = r#"{"frame":3,"position_mm":[1.5,-2,300.25],"gap_mm":0.1}"#;
        assert_eq!(json_array3(l, "position_mm"), Some([1.5, -2.0, 300.25]));
        assert_eq!(json_array3(r#"{"position_mm":null}"#, "position_mm"), None);
    }

    #[test]
    fn reads_fields_of_pretty_and_compact_json() {
        let status = "{\n  \"faults\": [\n    \"no_params\"\n  ],\n  \"params\": {\n    \"rig_id\": \"demo\",\n    \"swaps\": 1\n  }\n}";
        assert_eq!(field(status, "faults").as_deref(), Some("[\"no_params\"]"));
        assert_eq!(field(status, "params.rig_id").as_deref(), Some("demo"));
        assert_eq!(field(status, "params.swaps").as_deref(), Some("1"));
        let rec = r#"{"frame":7,"status":"ok","params_crc":3735928559}"#;
        assert_eq!(field(rec, "frame").as_deref(), Some("7"));
        assert_eq!(field(rec, "params_crc").as_deref(), Some("3735928559"));
        assert_eq!(field(rec, "missing"), None);
    }

    #[test]
    fn demo_configs_are_what_irtrackd_reads() {
        let text = irtrackd_config("127.0.0.1:9".parse().unwrap(), "$argon2id$h")
            .to_toml()
            .unwrap();
        let t: toml::Table = text.parse().unwrap();
        assert_eq!(t["robot"]["address"].as_str(), Some("127.0.0.1:9"));
        assert_eq!(t["robot"]["safety"]["max_age_ms"].as_integer(), Some(200));
        assert_eq!(
            t["service"]["operator_password_hash"].as_str(),
            Some("$argon2id$h")
        );
        assert_eq!(t["leds"]["backend"].as_str(), Some("none"));
        let calib: toml::Table = calib_irtrackd_config(Path::new("/k.pub"))
            .to_toml()
            .unwrap()
            .parse()
            .unwrap();
        assert_eq!(calib["params"]["trusted_keys"][0].as_str(), Some("/k.pub"));
    }

    #[test]
    fn reads_the_truth_circle_line() {
        let text = "rendered 16 views\ntruth marker path: circle of radius 40.0 mm around (0.0, -1.5, 600.0) mm (camera 0 frame)\n";
        assert_eq!(parse_truth_circle(text), Some(([0.0, -1.5, 600.0], 40.0)));
        assert_eq!(parse_truth_circle("truth cam0: fx 1\n"), None);
    }
}
