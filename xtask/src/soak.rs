//! `cargo xtask soak [--sets N] [--fps F] [--quick]`: the service soak. The real `irtrackd`
//! (release build, simulated cameras paced at F fps, ending after N frame sets) drives the real
//! `host-tools robot-sim` over the robot protocol while one NDJSON client reads every record.
//!
//! Every 5 % of the sets one table row: sets processed and dropped, irtrackd's RSS and peak RSS
//! (/proc of the irtrackd process), latency percentiles of the records received in that window,
//! records received, robot targets sent, link state, deadline misses, machine load. At the end
//! the checks (memory flat, no latency creep, counter identities, the robot's log against the
//! link's counters and the step limit, no disconnects) print PASS/FAIL; any FAIL fails the task.
//!
//! Pacing matters: the robot link's safety check compares the sample's capture time with the
//! wall clock, so an unpaced source would make every sample look stale or from the future.
//! The source's frame limit (`[source.sim] frames = N`) ends the run, after which the loop is
//! idle and every counter is final, so the identities are checked exactly, not with slack.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::util::{self, Ctx, RunOpts};
use crate::util::{Irtrackd, Proc, http, http_operator, json, operator_hash};
use serde_json::Value;

const DEFAULT_SETS: u64 = 1_000_000;
const QUICK_SETS: u64 = 20_000;
const DEFAULT_FPS: f64 = 500.0;
/// Marker circle: small, so the robot parked at its centre can take the first target within
/// `max_step_mm` wherever the marker is when motion is enabled.
const RADIUS_MM: f64 = 15.0;
const PERIOD_S: f64 = 4.0;
const MAX_STEP_MM: f64 = 20.0;
/// robot-sim's credit window: targets the link may have sent that the robot has not logged.
const CREDITS: u64 = 1;
/// Per-client stream queue. The soak client measures, it is not the slow-client test: a
/// generous queue keeps a briefly descheduled driver on this shared machine from being dropped.
const CLIENT_QUEUE_RECORDS: u64 = 16_384;
const MEMORY_LIMIT_KIB: i64 = 1024;
const POLL: Duration = Duration::from_millis(250);

/// `cargo xtask soak`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Frame sets to run (underscores allowed: 1_000_000); at least 2000.
    #[arg(long, value_name = "N", value_parser = parse_sets)]
    sets: Option<u64>,
    /// Frame sets per second, 10..=5000.
    #[arg(long, value_name = "F", default_value_t = DEFAULT_FPS)]
    fps: f64,
    /// A short run (20 000 sets) unless --sets is given.
    #[arg(long)]
    quick: bool,
}

fn parse_sets(v: &str) -> std::result::Result<u64, String> {
    v.replace('_', "")
        .parse()
        .map_err(|_| format!("{v:?} is not a whole number"))
}

struct Opts {
    sets: u64,
    fps: f64,
}

fn opts(args: &Args) -> Result<Opts> {
    let opts = Opts {
        sets: args
            .sets
            .unwrap_or(if args.quick { QUICK_SETS } else { DEFAULT_SETS }),
        fps: args.fps,
    };
    // Fewer sets than one marker circle cannot show anything; 20 rows need 20 sets at least.
    if opts.sets < 2_000 {
        bail!("--sets must be at least 2000, got {}", opts.sets);
    }
    if !(opts.fps.is_finite() && (10.0..=5000.0).contains(&opts.fps)) {
        bail!("--fps must be in 10..=5000, got {}", opts.fps);
    }
    Ok(opts)
}

/// `cargo xtask soak ...`.
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let opts = opts(args)?;
    let (irtrackd, host_tools) = build(ctx)?;
    let dir = ctx.target_dir().join("soak");
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    println!(
        "soak: {} frame sets at {} fps (≈ {}), output in {}",
        opts.sets,
        opts.fps,
        util::fmt_duration(Duration::from_secs_f64(opts.sets as f64 / opts.fps)),
        dir.display()
    );

    let circle = probe_circle(&irtrackd, &dir, opts.fps)?;
    println!(
        "marker circle centre ({:.2}, {:.2}, {:.2}) mm, extent ±({:.1}, {:.1}, {:.1}) mm; robot parked at the centre",
        circle.centre[0],
        circle.centre[1],
        circle.centre[2],
        circle.half_extent[0],
        circle.half_extent[1],
        circle.half_extent[2]
    );
    let report = run_soak(&irtrackd, &host_tools, &dir, &opts, &circle)?;
    let table = report.markdown(&opts);
    println!();
    print!("{table}");
    let result = dir.join("result.md");
    std::fs::write(&result, &table).with_context(|| format!("writing {}", result.display()))?;
    println!("(table written to {})", result.display());
    let failed = report.checks.iter().filter(|c| !c.pass).count();
    if failed > 0 {
        bail!("soak: {failed} check(s) FAILED");
    }
    Ok(())
}

/// Release irtrackd (what runs on the board); robot-sim only simulates the peer, so
/// host-tools is built in the dev profile (its release build links OpenCV and takes long).
fn build(ctx: &Ctx) -> Result<(PathBuf, PathBuf)> {
    let opts = RunOpts {
        timeout: Some(Duration::from_secs(3600)),
        ..RunOpts::default()
    };
    let mut cmd = ctx.cargo();
    cmd.args([
        "build",
        "--release",
        "-p",
        "irtrack-firmware",
        "--bin",
        "irtrackd",
    ]);
    let out = util::run(&mut cmd, opts)?;
    if !out.success() {
        bail!("building irtrackd {}", out.describe());
    }
    let mut cmd = ctx.cargo();
    cmd.args(["build", "-p", "irtrack-host-tools", "--bin", "host-tools"]);
    let out = util::run(&mut cmd, opts)?;
    if !out.success() {
        bail!("building host-tools {}", out.describe());
    }
    let target = ctx.target_dir();
    Ok((
        target.join("release").join("irtrackd"),
        target.join("debug").join("host-tools"),
    ))
}

/// Starts irtrackd with `config` (written to `dir/<name>.toml`), stderr into `dir/<name>.log`.
fn start_irtrackd(bin: &Path, dir: &Path, name: &str, config: &str) -> Result<Irtrackd> {
    let config_path = dir.join(format!("{name}.toml"));
    std::fs::write(&config_path, config)?;
    let state = dir.join(format!("{name}-state"));
    // A stored parameter set of an earlier run would replace the simulator's rig.
    if state.exists() {
        std::fs::remove_dir_all(&state).with_context(|| format!("removing {}", state.display()))?;
    }
    let log = File::create(dir.join(format!("{name}.log")))?;
    let mut cmd = Irtrackd::command(bin, &config_path, &state);
    cmd.stderr(log);
    Ok(Irtrackd::spawn(&mut cmd, Duration::from_secs(30))?)
}

/// Reads a child's pipe to the end in a thread (so it never blocks on a full pipe), sending
/// every line on the returned channel and appending it to `copy` if given.
fn drain_lines(pipe: impl Read + Send + 'static, copy: Option<File>) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let mut copy = copy;
        for line in BufReader::new(pipe).lines().map_while(Result::ok) {
            if let Some(f) = copy.as_mut() {
                let _ = writeln!(f, "{line}");
            }
            // The receiver may have stopped listening; keep draining anyway.
            let _ = tx.send(line);
        }
    });
    rx
}

struct Circle {
    centre: [f64; 3],
    half_extent: [f64; 3],
}

/// Runs irtrackd briefly (same simulated rig and rate, no robot) and takes the bounding box of
/// one full marker circle from its stream. A circle is symmetric about its centre, so the box's
/// midpoint is the centre: where the robot is parked, and what the workspace box surrounds.
fn probe_circle(bin: &Path, dir: &Path, fps: f64) -> Result<Circle> {
    let config = format!(
        r#"# Written by `cargo xtask soak` (marker circle probe).
[service]
params_from_simulator = true
[source.sim]
radius_mm = {RADIUS_MM}
period_s = {PERIOD_S}
fps = {fps}
[leds]
backend = "none"
"#
    );
    let probe = start_irtrackd(bin, dir, "probe", &config)?;
    let s = TcpStream::connect(probe.ready().stream).context("connecting to the probe's stream")?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    let circle_frames = (fps * PERIOD_S).ceil() as u64 + 2;
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    let mut first = None;
    for line in BufReader::new(s).lines() {
        let line = line.context("reading the probe's stream")?;
        let (Some(frame), Some(p)) = (json_num(&line, "frame"), json_array3(&line, "position_mm")) else {
            continue;
        };
        let frame = frame as u64;
        let start = *first.get_or_insert(frame);
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
        if frame >= start + circle_frames {
            break;
        }
    }
    probe.shutdown(Duration::from_secs(5))?;
    if first.is_none() || lo.iter().any(|v| !v.is_finite()) {
        bail!("the probe's stream delivered no tracked positions");
    }
    let centre = [0, 1, 2].map(|k| (lo[k] + hi[k]) / 2.0);
    let half_extent = [0, 1, 2].map(|k| (hi[k] - lo[k]) / 2.0);
    // The circle's extent in its widest direction is its diameter.
    let widest = half_extent.iter().copied().fold(0.0, f64::max);
    if (widest - RADIUS_MM).abs() > 0.2 * RADIUS_MM {
        bail!("probe saw a marker path of half-width {widest:.1} mm, expected a {RADIUS_MM} mm circle");
    }
    Ok(Circle { centre, half_extent })
}

fn soak_config(opts: &Opts, robot: SocketAddr, circle: &Circle, operator_hash: &str) -> String {
    let lo = circle.centre.map(|c| c - 200.0);
    let hi = circle.centre.map(|c| c + 200.0);
    format!(
        r#"# Written by `cargo xtask soak`.
[service]
params_from_simulator = true
control = true
operator_password_hash = "{operator_hash}"
[listen]
client_queue_records = {CLIENT_QUEUE_RECORDS}
[source.sim]
radius_mm = {RADIUS_MM}
period_s = {PERIOD_S}
fps = {fps}
paced = true
frames = {sets}
[leds]
backend = "none"
[robot]
address = "{robot}"
[robot.safety]
workspace_min_mm = [{}, {}, {}]
workspace_max_mm = [{}, {}, {}]
max_step_mm = {MAX_STEP_MM}
max_speed_mm_s = 250.0
max_gap_mm = 2.0
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "none"
"#,
        lo[0],
        lo[1],
        lo[2],
        hi[0],
        hi[1],
        hi[2],
        fps = opts.fps,
        sets = opts.sets,
    )
}

/// What the stream reader thread has seen.
#[derive(Default)]
struct StreamState {
    received: u64,
    /// `latency_us` of the records received since the last row.
    window_us: Vec<u32>,
    first_frame: Option<u64>,
    last_frame: Option<u64>,
    /// Records whose frame index was not above the previous one.
    not_increasing: u64,
    /// Lines without a frame or latency.
    malformed: u64,
    /// Why the stream ended, if it did before irtrackd was stopped.
    ended: Option<String>,
    /// Set by the driver just before it stops irtrackd: the end of the stream is expected then.
    stopping: bool,
}

fn spawn_stream_reader(addr: SocketAddr) -> Result<Arc<Mutex<StreamState>>> {
    let s = TcpStream::connect(addr).context("connecting to the NDJSON stream")?;
    let state = Arc::new(Mutex::new(StreamState::default()));
    let shared = state.clone();
    std::thread::spawn(move || {
        let mut reader = BufReader::new(s);
        let mut line = String::new();
        loop {
            line.clear();
            let end = match reader.read_line(&mut line) {
                Ok(0) => Some("closed by irtrackd".to_string()),
                Ok(_) => None,
                Err(e) => Some(format!("read error: {e}")),
            };
            let Ok(mut st) = shared.lock() else { return };
            if let Some(why) = end {
                if !st.stopping {
                    st.ended = Some(why);
                }
                return;
            }
            let (Some(frame), Some(lat)) = (json_num(&line, "frame"), json_num(&line, "latency_us")) else {
                st.malformed += 1;
                continue;
            };
            let frame = frame as u64;
            st.received += 1;
            st.window_us.push(lat as u32);
            st.first_frame.get_or_insert(frame);
            if st.last_frame.is_some_and(|l| frame <= l) {
                st.not_increasing += 1;
            }
            st.last_frame = Some(frame);
        }
    });
    Ok(state)
}

/// Window latency percentiles (µs, nearest rank).
#[derive(Clone, Copy, Default)]
struct Lat {
    n: usize,
    p50: u32,
    p99: u32,
    p999: u32,
    max: u32,
}

fn percentiles(mut v: Vec<u32>) -> Lat {
    if v.is_empty() {
        return Lat::default();
    }
    v.sort_unstable();
    let rank = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
    Lat {
        n: v.len(),
        p50: rank(0.50),
        p99: rank(0.99),
        p999: rank(0.999),
        max: v[v.len() - 1],
    }
}

struct Row {
    pct: u32,
    elapsed: Duration,
    processed: u64,
    dropped: u64,
    rss_kib: i64,
    hwm_kib: i64,
    lat: Lat,
    received: u64,
    targets: u64,
    link: String,
    misses: u64,
    load1: f64,
}

struct Check {
    name: String,
    pass: bool,
    detail: String,
}

struct Report {
    rows: Vec<Row>,
    checks: Vec<Check>,
    wall: Duration,
    notes: Vec<String>,
}

impl Report {
    fn check(&mut self, name: &str, pass: bool, detail: String) {
        println!("{} {name}: {detail}", if pass { "PASS" } else { "FAIL" });
        self.checks.push(Check {
            name: name.into(),
            pass,
            detail,
        });
    }

    fn markdown(&self, opts: &Opts) -> String {
        let mut s = String::new();
        s.push_str(&format!(
            "{} frame sets, simulated source paced at {} fps, wall time {}.\n\n",
            opts.sets,
            opts.fps,
            util::fmt_duration(self.wall)
        ));
        s.push_str(ROW_HEADER);
        for r in &self.rows {
            s.push_str(&r.markdown());
        }
        s.push('\n');
        for c in &self.checks {
            s.push_str(&format!(
                "- **{}** {}: {}\n",
                if c.pass { "PASS" } else { "FAIL" },
                c.name,
                c.detail
            ));
        }
        for n in &self.notes {
            s.push_str(&format!("- {n}\n"));
        }
        s
    }
}

const ROW_HEADER: &str = "| % | time | sets processed | dropped | RSS MiB | peak RSS MiB | latency p50 / p99 / p99.9 / max µs | records rx | robot targets | link | deadline misses | load 1m |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n";

impl Row {
    fn markdown(&self) -> String {
        let lat = if self.lat.n == 0 {
            "–".to_string()
        } else {
            format!(
                "{} / {} / {} / {}",
                self.lat.p50, self.lat.p99, self.lat.p999, self.lat.max
            )
        };
        format!(
            "| {} | {} | {} | {} | {:.2} | {:.2} | {lat} | {} | {} | {} | {} | {:.2} |\n",
            self.pct,
            util::fmt_duration(self.elapsed),
            self.processed,
            self.dropped,
            self.rss_kib as f64 / 1024.0,
            self.hwm_kib as f64 / 1024.0,
            self.received,
            self.targets,
            self.link,
            self.misses,
            self.load1
        )
    }
}

/// The robot-sim process and its stderr lines (connections opened and ended).
struct Robot {
    proc: Proc,
    stderr: mpsc::Receiver<String>,
    log: PathBuf,
}

fn start_robot_sim(bin: &Path, dir: &Path, home: [f64; 3]) -> Result<(Robot, SocketAddr)> {
    let log = dir.join("robot-sim.csv");
    let _ = std::fs::remove_file(&log);
    let mut proc = Proc::spawn(
        Command::new(bin)
            .args([
                "robot-sim",
                "--listen",
                "127.0.0.1:0",
                "--credits",
                &CREDITS.to_string(),
            ])
            .arg("--home")
            .arg(format!("{},{},{}", home[0], home[1], home[2]))
            .arg("--log")
            .arg(&log)
            .stderr(Stdio::piped()),
        "robot-sim",
    )?;
    let stderr = proc.child_mut().stderr.take().context("robot-sim stderr")?;
    let stderr = drain_lines(stderr, File::create(dir.join("robot-sim.log")).ok());
    let line = proc.wait_line("robot-sim listening on ", Duration::from_secs(15))?;
    let addr = line
        .trim_start_matches("robot-sim listening on ")
        .trim()
        .parse()
        .with_context(|| format!("bad robot-sim address in {line:?}"))?;
    Ok((Robot { proc, stderr, log }, addr))
}

fn run_soak(irtrackd: &Path, host_tools: &Path, dir: &Path, opts: &Opts, circle: &Circle) -> Result<Report> {
    let (mut robot, robot_addr) = start_robot_sim(host_tools, dir, circle.centre)?;
    println!("robot-sim listening on {robot_addr}, log {}", robot.log.display());
    let mut daemon = start_irtrackd(
        irtrackd,
        dir,
        "irtrackd",
        &soak_config(opts, robot_addr, circle, &operator_hash(irtrackd)?),
    )?;
    let t0 = Instant::now();
    let pid = daemon.pid();
    let ready = daemon.ready().clone();
    let stream = spawn_stream_reader(ready.stream)?;
    let status = ready.status;
    println!(
        "irtrackd pid {pid}: status {status}, stream {}; log {}",
        ready.stream,
        dir.join("irtrackd.log").display()
    );

    // Link up (held), then enable motion.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let (_, body) = http_operator(status, "POST", "/robot")?;
        if json_str(&body, "state").as_deref() == Some("holding") {
            break;
        }
        if Instant::now() > deadline {
            bail!("the robot link did not come up within 20 s: {body}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let (code, body) = http_operator(status, "POST", "/robot/enable")?;
    if code != 200 {
        bail!("POST /robot/enable answered {code}: {body}");
    }
    println!("motion enabled after {:.1} s", t0.elapsed().as_secs_f64());
    println!();
    print!("{ROW_HEADER}");

    let mut report = Report {
        rows: Vec::new(),
        checks: Vec::new(),
        wall: Duration::ZERO,
        notes: Vec::new(),
    };
    let expected = Duration::from_secs_f64(opts.sets as f64 / opts.fps);
    let give_up = expected + expected / 2 + Duration::from_secs(120);
    let mut next_pct = 5u32;
    let mut targets_stalled = Vec::new();
    let mut last_targets = 0u64;
    loop {
        std::thread::sleep(POLL);
        let (_, body) = http(status, "GET", "/status").context("polling /status")?;
        if json_bool(&body, "source_ended") == Some(true) {
            break;
        }
        let n = |k: &str| json_num(&body, k).unwrap_or(0.0) as u64;
        let simulated = n("sets_delivered") + n("sets_dropped");
        // The 100 % row is taken after the end, with the stream drained.
        if next_pct < 100 && simulated * 100 >= u64::from(next_pct) * opts.sets {
            let row = make_row(next_pct, t0, pid, &body, status, &stream)?;
            print!("{}", row.markdown());
            if row.targets == last_targets {
                targets_stalled.push(row.pct);
            }
            last_targets = row.targets;
            report.rows.push(row);
            while next_pct < 100 && simulated * 100 >= u64::from(next_pct) * opts.sets {
                next_pct += 5;
            }
        }
        if let Ok(Some(s)) = daemon.proc_mut().wait_timeout(Duration::ZERO) {
            bail!(
                "irtrackd exited during the soak ({s}); see {}",
                dir.join("irtrackd.log").display()
            );
        }
        if t0.elapsed() > give_up {
            bail!(
                "the source did not end within {} (expected {}); irtrackd's log: {}",
                util::fmt_duration(give_up),
                util::fmt_duration(expected),
                dir.join("irtrackd.log").display()
            );
        }
    }
    report.wall = t0.elapsed();

    // The loop is idle now: let the stream drain, then read the final counters.
    let drain_deadline = Instant::now() + Duration::from_secs(10);
    let final_status = loop {
        let (_, body) = http(status, "GET", "/status")?;
        let sent = json_num(&body, "records_sent").unwrap_or(0.0) as u64;
        let received = stream.lock().map(|s| s.received).unwrap_or(0);
        if received >= sent || Instant::now() > drain_deadline {
            break body;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let (_, link) = http_operator(status, "POST", "/robot")?;
    let row = make_row(100, t0, pid, &final_status, status, &stream)?;
    print!("{}", row.markdown());
    // Only the targets sent while frames were flowing count; after the end the link holds.
    if row.targets == last_targets {
        targets_stalled.push(row.pct);
    }
    report.rows.push(row);

    // Stop: irtrackd first (its link says HOLD and BYE, so robot-sim ends the connection and
    // flushes its log), then robot-sim.
    if let Ok(mut st) = stream.lock() {
        st.stopping = true;
    }
    let how = daemon.shutdown(Duration::from_secs(10))?;
    report.notes.push(format!("irtrackd {how}"));
    let mut robot_lines = Vec::new();
    let wait_end = Instant::now() + Duration::from_secs(10);
    while Instant::now() < wait_end {
        match robot.stderr.recv_timeout(Duration::from_millis(200)) {
            Ok(l) => {
                let ended = l.contains("ended:");
                robot_lines.push(l);
                let opened = robot_lines
                    .iter()
                    .filter(|l| l.contains(": connection ") && l.contains(" from "))
                    .count();
                let closed = robot_lines.iter().filter(|l| l.contains("ended:")).count();
                if ended && closed >= opened {
                    break;
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
    }
    let how = robot.proc.terminate(Duration::from_secs(5))?;
    report.notes.push(format!(
        "robot-sim {how}; its stderr: {}",
        robot_lines.join(" | ")
    ));

    checks(
        &mut report,
        opts,
        &final_status,
        &link,
        &stream,
        &robot.log,
        circle,
        &targets_stalled,
    )?;
    report.notes.push(format!(
        "files: {} (irtrackd.toml, irtrackd.log, robot-sim.csv, robot-sim.log)",
        dir.display()
    ));
    Ok(report)
}

fn make_row(
    pct: u32,
    t0: Instant,
    pid: u32,
    body: &str,
    status: SocketAddr,
    stream: &Arc<Mutex<StreamState>>,
) -> Result<Row> {
    let n = |k: &str| json_num(body, k).unwrap_or(0.0) as u64;
    let (rss_kib, hwm_kib) = proc_memory(pid)?;
    let (window, received) = {
        let mut st = stream
            .lock()
            .map_err(|_| anyhow::anyhow!("stream reader panicked"))?;
        (std::mem::take(&mut st.window_us), st.received)
    };
    let (_, link) = http_operator(status, "POST", "/robot")?;
    Ok(Row {
        pct,
        elapsed: t0.elapsed(),
        processed: n("sets_processed"),
        dropped: n("sets_dropped"),
        rss_kib,
        hwm_kib,
        lat: percentiles(window),
        received,
        targets: json_num(&link, "targets_sent").unwrap_or(0.0) as u64,
        link: json_str(&link, "state").unwrap_or_else(|| "?".to_string()),
        misses: n("deadline_misses"),
        load1: load_average(),
    })
}

#[allow(clippy::too_many_arguments)]
fn checks(
    report: &mut Report,
    opts: &Opts,
    st: &str,
    link: &str,
    stream: &Arc<Mutex<StreamState>>,
    robot_log: &Path,
    circle: &Circle,
    targets_stalled: &[u32],
) -> Result<()> {
    let n = |k: &str| json_num(st, k).unwrap_or(f64::NAN) as u64;
    // Memory: the 10 % row is past start-up (buffers, first clients, link) by design. The
    // 100 % row comes after the source ended, when the loop has freed its frame buffers, so it
    // would hide growth: the rows taken while sets were flowing are compared (the last one and
    // the largest one). VmHWM is shown but not judged: the kernel updates it lazily.
    let rows = &report.rows;
    let rss10 = rows.iter().find(|r| r.pct >= 10).map(|r| r.rss_kib);
    let running: Vec<&Row> = rows.iter().filter(|r| r.pct >= 10 && r.pct < 100).collect();
    let last_running = running.last().map(|r| (r.pct, r.rss_kib));
    let max_running = running.iter().map(|r| r.rss_kib).max();
    let end = rows.last().map(|r| (r.rss_kib, r.hwm_kib));
    let first = rows.first().map(|r| (r.lat, r.load1));
    let last = rows.iter().rev().find(|r| r.lat.n > 0).map(|r| (r.lat, r.load1));
    if let (Some(rss10), Some((pct, rss_last)), Some(rss_max), Some((rss_end, hwm_end))) =
        (rss10, last_running, max_running, end)
    {
        let mib = |k: i64| k as f64 / 1024.0;
        report.check(
            "memory flat",
            rss_last - rss10 < MEMORY_LIMIT_KIB && rss_max - rss10 < MEMORY_LIMIT_KIB,
            format!(
                "irtrackd RSS {:.2} MiB at the 10 % row, {:.2} MiB at the {pct} % row (last while running): {:+} KiB; largest while running {:.2} MiB: {:+} KiB (limit < {MEMORY_LIMIT_KIB} KiB); after the source ended (frame buffers freed) {:.2} MiB, VmHWM {:.2} MiB",
                mib(rss10),
                mib(rss_last),
                rss_last - rss10,
                mib(rss_max),
                rss_max - rss10,
                mib(rss_end),
                mib(hwm_end)
            ),
        );
    } else {
        report.check("memory flat", false, "too few rows recorded".into());
    }

    // Latency creep: last window against the first, with the machine's load beside each.
    match (first, last) {
        (Some((f, f_load)), Some((l, l_load))) if f.n > 0 => {
            let limit = 2 * u64::from(f.p99) + 200;
            report.check(
                "no latency creep",
                u64::from(l.p99) <= limit,
                format!(
                    "p99 capture→published {} µs in the last window ({} records, load {:.2}) vs {} µs in the first ({} records, load {:.2}); limit 2 × first + 200 = {limit} µs",
                    l.p99, l.n, l_load, f.p99, f.n, f_load
                ),
            );
        }
        _ => report.check("no latency creep", false, "no latency windows".into()),
    }

    // Counter identities of the final, idle state (see firmware/src/engine.rs).
    let processed = n("sets_processed");
    let published = n("published");
    let (tracked, lost, gated) = (n("tracked"), n("lost"), n("gated"));
    let (delivered, dropped, stale) = (n("sets_delivered"), n("sets_dropped"), n("stale_sets"));
    let source_errors = n("source_errors");
    let s = stream
        .lock()
        .map_err(|_| anyhow::anyhow!("stream reader panicked"))?;
    let last_frame = s.last_frame.unwrap_or(u64::MAX);
    report.check(
        "counters: published == sets_processed",
        published == processed,
        format!("published {published}, sets_processed {processed}"),
    );
    report.check(
        "counters: tracked + lost + gated == published",
        tracked + lost + gated == published,
        format!(
            "{tracked} + {lost} + {gated} = {}, published {published}",
            tracked + lost + gated
        ),
    );
    report.check(
        "counters: sets_delivered == sets_processed + stale_sets",
        delivered == processed + stale,
        format!("delivered {delivered}, processed {processed}, stale {stale}"),
    );
    // Every scenario index up to the last one published was either delivered or skipped.
    report.check(
        "counters: sets_delivered + sets_dropped == last frame index + 1 <= N",
        last_frame != u64::MAX && delivered + dropped == last_frame + 1 && last_frame < opts.sets,
        format!(
            "{delivered} + {dropped} = {}, last frame received {last_frame}, N = {}",
            delivered + dropped,
            opts.sets
        ),
    );
    let cameras = camera_frames(st);
    report.check(
        "counters: every camera's frames == sets_processed",
        !cameras.is_empty() && cameras.iter().all(|&f| f == processed),
        format!("cameras {cameras:?}, processed {processed}"),
    );
    let e2e_count = json::parse(st)
        .ok()
        .and_then(|doc| find(find(&doc, "end_to_end")?, "count")?.as_f64())
        .unwrap_or(f64::NAN) as u64;
    report.check(
        "counters: end_to_end histogram count == sets_processed",
        e2e_count == processed,
        format!("count {e2e_count}, processed {processed}"),
    );
    let iterations = n("iterations");
    report.check(
        "counters: loop iterations == processed + source errors + 1 (the end-of-stream step)",
        iterations == processed + source_errors + 1,
        format!("iterations {iterations}, processed {processed}, source errors {source_errors}"),
    );
    let (pipeline_errors, skewed) = (n("pipeline_errors"), n("skewed_sets"));
    report.check(
        "no source, pipeline or pairing faults",
        source_errors == 0 && pipeline_errors == 0 && skewed == 0 && stale == 0,
        format!(
            "source errors {source_errors}, pipeline errors {pipeline_errors}, skewed {skewed}, stale {stale}"
        ),
    );
    let (sent, slow, clients_total) = (n("records_sent"), n("dropped_slow"), n("clients_total"));
    report.check(
        "stream: records received == records_sent, frames increasing, client never dropped",
        s.received == sent
            && s.not_increasing == 0
            && s.malformed == 0
            && slow == 0
            && clients_total == 1
            && s.ended.is_none(),
        format!(
            "received {}, records_sent {sent}, not increasing {}, malformed {}, dropped_slow {slow}, clients_total {clients_total}, stream end {:?}; slot overwrites {} (latest-value slot, not a loss of the loop)",
            s.received,
            s.not_increasing,
            s.malformed,
            s.ended,
            n("slot_overwrites")
        ),
    );
    drop(s);

    // Robot: the link's counters against what robot-sim logged.
    let targets_sent = json_num(link, "targets_sent").unwrap_or(f64::NAN) as u64;
    let connects = json_num(link, "connects").unwrap_or(f64::NAN) as u64;
    let rejects = json_num(link, "rejects").unwrap_or(f64::NAN) as u64;
    let text =
        std::fs::read_to_string(robot_log).with_context(|| format!("reading {}", robot_log.display()))?;
    let log = parse_robot_log(&text);
    let step_from_home = log.first_target.map(|t| dist(&t, &circle.centre)).unwrap_or(0.0);
    report.check(
        "robot: targets logged == link targets_sent (minus at most the credit window)",
        log.targets > 0 && log.targets <= targets_sent && targets_sent - log.targets <= CREDITS,
        format!(
            "robot-sim logged {} targets, link sent {targets_sent} (window {CREDITS})",
            log.targets
        ),
    );
    let max_step = log.max_step_mm.max(step_from_home);
    report.check(
        "robot: largest step between consecutive targets <= max_step_mm",
        max_step <= MAX_STEP_MM,
        format!(
            "largest step {max_step:.3} mm: between consecutive targets {:.3} mm, parked TCP to the first target {step_from_home:.3} mm; limit {MAX_STEP_MM} mm",
            log.max_step_mm
        ),
    );
    report.check(
        "robot: no disconnects, rejects or malformed lines",
        connects == 1 && log.connected == 1 && log.disconnected <= 1 && rejects == 0 && log.rejected == 0 && log.malformed == 0,
        format!(
            "link connects {connects}, robot-sim connections {} (ended {}), rejects {rejects}/{}, malformed {}",
            log.connected, log.disconnected, log.rejected, log.malformed
        ),
    );
    // The robot followed throughout: targets went out in every window after the first.
    let stalled: Vec<u32> = targets_stalled.iter().copied().filter(|&p| p > 5).collect();
    report.check(
        "robot: targets sent in every window",
        stalled.is_empty(),
        if stalled.is_empty() {
            format!("{targets_sent} targets, holds logged by robot-sim {}", log.holds)
        } else {
            format!("no new targets in the windows ending at {stalled:?} %")
        },
    );
    report.notes.push(format!(
        "tracked {tracked} of {processed} processed sets ({:.4} %), lost {lost}, gated {gated}; sets dropped by the paced source (loop more than one period late) {dropped} ({:.3} % of N); deadline misses {} (deadline {} µs)",
        100.0 * tracked as f64 / processed.max(1) as f64,
        100.0 * dropped as f64 / opts.sets as f64,
        n("deadline_misses"),
        json_num(st, "deadline_us").unwrap_or(f64::NAN)
    ));
    Ok(())
}

/// What robot-sim's CSV log says.
#[derive(Debug, Default, PartialEq)]
struct RobotLog {
    targets: u64,
    connected: u64,
    disconnected: u64,
    rejected: u64,
    malformed: u64,
    holds: u64,
    first_target: Option<[f64; 3]>,
    max_step_mm: f64,
}

/// Columns: t_s,conn,event,seq,target_x_mm,target_y_mm,target_z_mm,robot_x..z_mm,detail.
fn parse_robot_log(text: &str) -> RobotLog {
    let mut log = RobotLog::default();
    let mut prev: Option<[f64; 3]> = None;
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        match f.get(2).copied() {
            Some("target") => {
                let xyz: Vec<f64> = f
                    .get(4..7)
                    .unwrap_or(&[])
                    .iter()
                    .filter_map(|v| v.parse().ok())
                    .collect();
                let Ok(t) = <[f64; 3]>::try_from(xyz) else {
                    log.malformed += 1;
                    continue;
                };
                log.targets += 1;
                log.first_target.get_or_insert(t);
                if let Some(p) = prev {
                    log.max_step_mm = log.max_step_mm.max(dist(&p, &t));
                }
                prev = Some(t);
            }
            Some("connected") => log.connected += 1,
            Some("disconnected") => log.disconnected += 1,
            Some("rejected") => log.rejected += 1,
            Some("malformed") => log.malformed += 1,
            Some("hold") => log.holds += 1,
            _ => {}
        }
    }
    log
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// `frames` of every entry of the status's `source.cameras` array.
fn camera_frames(body: &str) -> Vec<u64> {
    let Ok(doc) = json::parse(body) else {
        return Vec::new();
    };
    find(&doc, "cameras")
        .and_then(Value::as_array)
        .map(|cams| cams.iter().filter_map(|c| c.get("frames")?.as_u64()).collect())
        .unwrap_or_default()
}

/// VmRSS and VmHWM (KiB) of a process.
fn proc_memory(pid: u32) -> Result<(i64, i64)> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse::<i64>().ok())
            .with_context(|| format!("{name} missing in /proc/{pid}/status"))
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

fn load_average() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(f64::NAN)
}

/// The first `key` in `doc`, searched level by level (the status document's counter names are
/// unique; the shallowest one wins).
fn find<'a>(doc: &'a Value, key: &str) -> Option<&'a Value> {
    let mut level = vec![doc];
    while !level.is_empty() {
        let mut next = Vec::new();
        for v in level {
            match v {
                Value::Object(m) => {
                    if let Some(found) = m.get(key) {
                        return Some(found);
                    }
                    next.extend(m.values());
                }
                Value::Array(a) => next.extend(a.iter()),
                _ => {}
            }
        }
        level = next;
    }
    None
}

/// The number at the first `key` of a JSON text (see [`find`]).
fn json_num(body: &str, key: &str) -> Option<f64> {
    find(&json::parse(body).ok()?, key)?.as_f64()
}

fn json_str(body: &str, key: &str) -> Option<String> {
    find(&json::parse(body).ok()?, key)?.as_str().map(str::to_string)
}

fn json_bool(body: &str, key: &str) -> Option<bool> {
    find(&json::parse(body).ok()?, key)?.as_bool()
}

fn json_array3(body: &str, key: &str) -> Option<[f64; 3]> {
    let doc = json::parse(body).ok()?;
    match find(&doc, key)?.as_array()?.as_slice() {
        [x, y, z] => Some([x.as_f64()?, y.as_f64()?, z.as_f64()?]),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn options() {
        use clap::Parser;
        #[derive(Parser)]
        struct T {
            #[command(flatten)]
            a: Args,
        }
        let a = |v: &[&str]| {
            T::try_parse_from(std::iter::once("t").chain(v.iter().copied()))
                .map_err(anyhow::Error::from)
                .and_then(|t| opts(&t.a))
        };
        let o = a(&[]).unwrap();
        assert_eq!((o.sets, o.fps), (1_000_000, 500.0));
        let o = a(&["--quick", "--fps", "700"]).unwrap();
        assert_eq!((o.sets, o.fps), (20_000, 700.0));
        assert_eq!(a(&["--sets", "50_000"]).unwrap().sets, 50_000);
        assert!(a(&["--sets"]).is_err());
        assert!(a(&["--sets", "10"]).is_err());
        assert!(a(&["--fps", "0"]).is_err());
        assert!(a(&["--bogus"]).is_err());
    }

    #[test]
    fn percentiles_nearest_rank() {
        let l = percentiles((1..=1000).rev().collect());
        assert_eq!((l.n, l.p50, l.p99, l.p999, l.max), (1000, 500, 990, 999, 1000));
        assert_eq!(percentiles(Vec::new()).n, 0);
        let one = percentiles(vec![7]);
        assert_eq!((one.p50, one.p999, one.max), (7, 7, 7));
    }

    #[test]
    fn json_fields_pretty_and_compact() {
        let pretty = "{\n  \"processing\": {\n    \"sets_processed\": 400,\n    \"source_ended\": true,\n    \"last_gap_mm\": 2.5e-3\n  },\n  \"state\": \"moving\"\n}";
        assert_eq!(json_num(pretty, "sets_processed"), Some(400.0));
        assert_eq!(json_num(pretty, "last_gap_mm"), Some(0.0025));
        assert_eq!(json_bool(pretty, "source_ended"), Some(true));
        assert_eq!(json_str(pretty, "state").as_deref(), Some("moving"));
        assert_eq!(json_num(pretty, "processed"), None);
        let rec = r#"{"frame":456,"position_mm":[24.5,5.0,-568.8],"latency_us":31127}"#;
        assert_eq!(json_num(rec, "frame"), Some(456.0));
        assert_eq!(json_num(rec, "latency_us"), Some(31127.0));
        assert_eq!(json_array3(rec, "position_mm"), Some([24.5, 5.0, -568.8]));
        assert_eq!(json_array3(r#"{"position_mm":null}"#, "position_mm"), None);
    }

    #[test]
    fn camera_frames_from_status() {
        let st = "{\"source\": {\"cameras\": [\n {\"index\": 0, \"frames\": 12},\n {\"index\": 1, \"frames\": 13}\n ]},\n \"processing\": {\"frames\": 99}}";
        assert_eq!(camera_frames(st), vec![12, 13]);
        assert!(camera_frames("{}").is_empty());
    }

    #[test]
    fn the_shallowest_key_wins() {
        let st = r#"{"processing":{"latency_us":{"detect":{"count":5},"end_to_end":{"count":7}}},"count":1}"#;
        assert_eq!(json_num(st, "count"), Some(1.0));
        let doc = json::parse(st).unwrap();
        assert_eq!(
            find(find(&doc, "end_to_end").unwrap(), "count").and_then(Value::as_f64),
            Some(7.0)
        );
    }

    #[test]
    fn robot_log_counts_and_steps() {
        let csv = "t_s,conn,event,seq,target_x_mm,target_y_mm,target_z_mm,robot_x_mm,robot_y_mm,robot_z_mm,detail\n\
            0.1,1,connected,,,,,0,0,0,127.0.0.1:5\n\
            0.2,1,target,1,1.000,0.000,0.000,0,0,0,\n\
            0.3,1,pos,,,,,0.5,0,0,\n\
            0.4,1,target,2,4.000,4.000,0.000,1,0,0,\n\
            0.5,1,hold,,,,,4,4,0,not enabled\n\
            0.6,1,target,3,4.000,5.000,0.000,4,4,0,\n\
            0.7,1,rejected,3,,,,4,4,0,05\n\
            0.8,1,disconnected,,,,,4,5,0,BYE\n";
        let log = parse_robot_log(csv);
        assert_eq!(
            (
                log.targets,
                log.connected,
                log.disconnected,
                log.rejected,
                log.holds
            ),
            (3, 1, 1, 1, 1)
        );
        assert_eq!(log.first_target, Some([1.0, 0.0, 0.0]));
        assert!((log.max_step_mm - 5.0).abs() < 1e-12);
    }
}
