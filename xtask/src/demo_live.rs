//! Demo step: irtrackd (simulated cameras) streams to a simulated robot controller, which
//! follows the marker after an explicit enable. Real binaries, real sockets on 127.0.0.1.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

/// Kills a child process on every path out of the step.
struct Guard(Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

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
    std::fs::write(&config, irtrackd_config(robot_addr))?;
    println!("starting irtrackd (simulated cameras, robot link to {robot_addr})");
    let mut child = Command::new(bin_dir.join("irtrackd"))
        .arg("-c")
        .arg(&config)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(dir.join("state"))
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting irtrackd")?;
    let ready = wait_line(&mut child, "irtrackd ready", Duration::from_secs(30))?;
    let irtrackd = Guard(child);
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
    let mut child = Command::new(bin_dir.join("host-tools"))
        .args(["robot-sim", "--listen", &robot_addr.to_string(), "--home"])
        .arg(format!("{},{},{}", start[0], start[1], start[2]))
        .arg("--log")
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting host-tools robot-sim")?;
    wait_line(&mut child, "robot-sim listening on ", Duration::from_secs(15))?;
    let robot = Guard(child);

    // The link connects (with backoff) and holds until explicitly enabled.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (_, body) = http(status, "POST", "/robot")?;
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
        let (code, body) = http(status, "POST", req)?;
        if code != 200 {
            bail!("POST {req} answered {code}: {body}");
        }
        println!("POST {req} -> {}", short(&body));
    }
    for _ in 0..FOLLOW_S {
        std::thread::sleep(Duration::from_secs(1));
        let (_, body) = http(status, "POST", "/robot")?;
        println!("robot: {}", short(&body));
    }
    let (_, body) = http(status, "POST", "/robot/disable")?;
    println!("POST /robot/disable -> {}", short(&body));
    std::thread::sleep(Duration::from_millis(300));
    drop(irtrackd);
    drop(robot);
    summarize(&log)
}

fn irtrackd_config(robot: SocketAddr) -> String {
    format!(
        r#"# Written by `cargo xtask demo`.
[service]
params_from_simulator = true
control = true
[source.sim]
radius_mm = 15.0
[leds]
backend = "none"
[robot]
address = "{robot}"
[robot.safety]
workspace_min_mm = [-2000.0, -2000.0, 0.0]
workspace_max_mm = [2000.0, 2000.0, 4000.0]
max_step_mm = 40.0
max_speed_mm_s = 400.0
max_gap_mm = 2.0
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "flag"
"#
    )
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

fn wait_line(child: &mut Child, prefix: &str, timeout: Duration) -> Result<String> {
    let stdout = child.stdout.take().context("child stdout")?;
    let (tx, rx) = mpsc::channel();
    let wanted = prefix.to_string();
    std::thread::spawn(move || {
        let mut sent = false;
        // Keep draining so the child never blocks on a full pipe.
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if !sent && line.starts_with(&wanted) {
                let _ = tx.send(line);
                sent = true;
            }
        }
    });
    rx.recv_timeout(timeout)
        .map_err(|_| anyhow::anyhow!("no `{prefix}` line within {timeout:?}"))
}

fn addr_field(line: &str, key: &str) -> Result<SocketAddr> {
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(key))
        .with_context(|| format!("`{key}` missing in {line:?}"))?
        .parse()
        .with_context(|| format!("bad address for `{key}` in {line:?}"))
}

/// First tracked position from irtrackd's NDJSON stream.
fn first_position(stream: SocketAddr) -> Result<[f64; 3]> {
    let s = TcpStream::connect(stream).context("connecting to the position stream")?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    for line in BufReader::new(s).lines() {
        let line = line.context("reading the position stream")?;
        if let Some(p) = json_array3(&line, "\"position_mm\":") {
            return Ok(p);
        }
    }
    bail!("the position stream closed before a tracked position arrived")
}

/// Extracts `"key":[a,b,c]` from one JSON line (the stream's documented field layout).
fn json_array3(line: &str, key: &str) -> Option<[f64; 3]> {
    let rest = &line[line.find(key)? + key.len()..];
    let inner = rest.strip_prefix('[')?.split(']').next()?;
    let v: Vec<f64> = inner.split(',').filter_map(|x| x.trim().parse().ok()).collect();
    (v.len() == 3).then(|| [v[0], v[1], v[2]])
}

fn http(addr: SocketAddr, method: &str, path: &str) -> Result<(u16, String)> {
    let mut s = TcpStream::connect(addr).with_context(|| format!("connecting to {addr}"))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(s, "{method} {path} HTTP/1.0\r\nHost: demo\r\n\r\n")?;
    let mut resp = String::new();
    s.read_to_string(&mut resp)?;
    let code = resp
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = resp
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.trim().to_string())
        .unwrap_or_default();
    Ok((code, body))
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
        assert_eq!(json_array3(l, "\"position_mm\":"), Some([1.5, -2.0, 300.25]));
        assert_eq!(json_array3(r#"{"position_mm":null}"#, "\"position_mm\":"), None);
    }
}
