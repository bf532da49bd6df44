//! `cargo xtask bench-links [--quick] [--secs S] [--release]`: the three robot links side by
//! side in one run. For each of socket, EGM and RSI: irtrackd (simulated cameras, the marker on
//! a 100 mm circle at 250 mm/s) and `host-tools robot-sim` as separate processes on 127.0.0.1.
//!
//! Printed per link: capture-timestamp → packet-leaving-irtrackd latency (p50/p99/p99.9, logged
//! by irtrackd's link at shutdown), replies later than the controller's cycle (EGM/RSI; the
//! socket protocol has no cycle), and the simulated robot's tracking error against the tracked
//! marker at the same instant (mean/max) and its jerk (RMS/max), after a settling second.

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener, TcpStream, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::Ctx;
use crate::util::{self, Proc, addr_field, http_operator, json, operator_hash};

const RADIUS_MM: f64 = 100.0;
const SPEED_MM_S: f64 = 250.0;
/// Robot speed limit for every kind: above the marker's speed, so the link, not the arm, is
/// what the comparison shows.
const ROBOT_SPEED_MM_S: f64 = 1000.0;
const CYCLE_MS: f64 = 4.0;
/// Samples before this long after the enable are the pick-up transient, not tracking.
const SETTLE_S: f64 = 1.0;

/// `cargo xtask bench-links`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// 3 s of following per link instead of 20.
    #[arg(long)]
    quick: bool,
    /// Seconds of following per link (at least 2).
    #[arg(long, value_name = "S")]
    secs: Option<f64>,
    /// irtrackd in its release build.
    #[arg(long)]
    release: bool,
}

struct Opts {
    secs: f64,
    release: bool,
}

fn opts(args: &Args) -> Result<Opts> {
    let secs = args.secs.unwrap_or(if args.quick { 3.0 } else { 20.0 });
    if secs.is_nan() || secs < 2.0 {
        bail!("--secs needs a number >= 2, got {secs}");
    }
    Ok(Opts {
        secs,
        release: args.release,
    })
}

/// Runs the benchmark.
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let o = opts(args)?;
    let (irtrackd, host_tools) = build(ctx, o.release)?;
    let hash = operator_hash(&irtrackd)?;
    let dir = std::env::temp_dir().join(format!("irtrack-bench-links-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut rows = Vec::new();
    let result = (|| -> Result<()> {
        for kind in ["socket", "egm", "rsi"] {
            println!("-- {kind}: {} s following", o.secs);
            let run = Run {
                secs: o.secs,
                viewers: None,
                fifo_priority: None,
            };
            rows.push(run_one(
                kind,
                &irtrackd,
                &host_tools,
                &hash,
                &dir.join(kind),
                &run,
            )?);
        }
        Ok(())
    })();
    let _ = std::fs::remove_dir_all(&dir);
    result?;
    println!();
    println!(
        "marker: {RADIUS_MM} mm circle at {SPEED_MM_S} mm/s; robot-sim limits {ROBOT_SPEED_MM_S} mm/s, \
         5000 mm/s², servo lag 12 ms (EGM/RSI), cycle {CYCLE_MS} ms; irtrackd {} build",
        if o.release { "release" } else { "dev" }
    );
    println!(
        "| link | targets sent | latency p50 / p99 / p99.9 (ms) | of which protocol wait p50 / p99 / max (ms) | replies later than the cycle | tracking error mean / max (mm) | jerk RMS / max (m/s³) |"
    );
    println!("|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {} | {:.2} / {:.2} / {:.2} | {:.2} / {:.2} / {:.2} | {} | {:.1} / {:.1} | {:.0} / {:.0} |",
            r.kind,
            r.latency.n,
            r.latency.p50_us as f64 / 1e3,
            r.latency.p99_us as f64 / 1e3,
            r.latency.p999_us as f64 / 1e3,
            r.latency.wait_p50_us as f64 / 1e3,
            r.latency.wait_p99_us as f64 / 1e3,
            r.latency.wait_max_us as f64 / 1e3,
            r.late,
            r.err_mean_mm,
            r.err_max_mm,
            r.jerk_rms_m_s3,
            r.jerk_max_m_s3
        );
    }
    println!();
    crate::bench_cluster::run(ctx, o.release, &["--secs".into(), format!("{}", o.secs.min(5.0))])
}

/// Every link kind with 0 and with `viewers.count` viewers, `secs` each, release build of
/// irtrackd: the rows of `cargo xtask bench --latency`'s decomposition.
/// The loop runs SCHED_FIFO at `fifo_priority` where permitted.
pub fn decomposition(ctx: &Ctx, secs: f64, viewers: &ViewerLoad, fifo_priority: u32) -> Result<Vec<Row>> {
    let (irtrackd, host_tools) = build(ctx, true)?;
    let hash = operator_hash(&irtrackd)?;
    let dir = std::env::temp_dir().join(format!("irtrack-bench-latency-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut rows = Vec::new();
    let result = (|| -> Result<()> {
        for kind in ["socket", "egm", "rsi"] {
            for v in [None, Some(viewers)] {
                let n = v.map_or(0, |v| v.count);
                println!("-- {kind}, {n} viewers: {secs} s following");
                let sub = dir.join(format!("{kind}-{n}"));
                let run = Run {
                    secs,
                    viewers: v,
                    fifo_priority: Some(fifo_priority),
                };
                rows.push(run_one(kind, &irtrackd, &host_tools, &hash, &sub, &run)?);
            }
        }
        Ok(())
    })();
    let _ = std::fs::remove_dir_all(&dir);
    result?;
    Ok(rows)
}

fn build(ctx: &Ctx, release: bool) -> Result<(PathBuf, PathBuf)> {
    let limit = Duration::from_secs(3600);
    let mut cmd = ctx.cargo();
    cmd.args(["build", "-p", "irtrack-firmware", "--bin", "irtrackd"]);
    if release {
        cmd.arg("--release");
    }
    util::run_ok(&mut cmd, "building irtrackd", limit, false)?;
    let mut cmd = ctx.cargo();
    cmd.args(["build", "-p", "irtrack-host-tools", "--bin", "host-tools"]);
    util::run_ok(&mut cmd, "building host-tools", limit, false)?;
    let t = ctx.target_dir();
    Ok((
        t.join(if release { "release" } else { "debug" }).join("irtrackd"),
        t.join("debug").join("host-tools"),
    ))
}

#[derive(Debug, Default, Clone, Copy)]
pub struct Latency {
    pub n: u64,
    pub p50_us: u64,
    pub p99_us: u64,
    pub p999_us: u64,
    /// Protocol wait: published → on the wire.
    pub wait_p50_us: u64,
    pub wait_p99_us: u64,
    pub wait_max_us: u64,
}

/// p50 and p99 (µs) of one processing-loop stage, read from irtrackd's `/status`.
#[derive(Debug, Default, Clone, Copy)]
pub struct Quantiles {
    pub p50_us: f64,
    pub p99_us: f64,
}

/// The loop's share of one run: `driver` (capture → dequeued), `ours` (dequeued →
/// published), and the simulator's rendering (ahead of the capture instant).
#[derive(Debug, Default, Clone, Copy)]
pub struct LoopSplit {
    pub render: Quantiles,
    pub driver: Quantiles,
    pub ours: Quantiles,
    pub end_to_end: Quantiles,
}

pub struct Row {
    pub kind: &'static str,
    pub viewers: usize,
    pub latency: Latency,
    pub split: LoopSplit,
    /// EGM/RSI: replies later than the cycle; socket: robot-sim's tick timing.
    pub late: String,
    err_mean_mm: f64,
    err_max_mm: f64,
    jerk_rms_m_s3: f64,
    jerk_max_m_s3: f64,
}

fn config(kind: &str, robot: SocketAddr, hash: &str, fifo_priority: Option<u32>) -> String {
    let period_s = 2.0 * std::f64::consts::PI * RADIUS_MM / SPEED_MM_S;
    let realtime = fifo_priority.map_or(String::new(), |p| format!("[realtime]\nfifo_priority = {p}\n"));
    format!(
        r#"# Written by `cargo xtask bench-links`.
[service]
params_from_simulator = true
control = true
operator_password_hash = "{hash}"
[source.sim]
radius_mm = {RADIUS_MM}
period_s = {period_s}
fps = 120.0
[leds]
backend = "none"
[robot]
kind = "{kind}"
address = "{robot}"
[robot.safety]
workspace_min_mm = [-2000.0, -2000.0, -4000.0]
workspace_max_mm = [2000.0, 2000.0, 4000.0]
# Larger than the circle: the enable picks the marker up wherever it is on it.
max_step_mm = 250.0
max_speed_mm_s = 1000.0
max_gap_mm = 2.0
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "flag"
{realtime}"#
    )
}

/// Lines a child prints, collected by a thread.
fn collect_lines(r: impl std::io::Read + Send + 'static) -> Arc<Mutex<Vec<String>>> {
    let lines = Arc::new(Mutex::new(Vec::new()));
    let l = lines.clone();
    std::thread::spawn(move || {
        for line in BufReader::new(r).lines().map_while(Result::ok) {
            if let Ok(mut v) = l.lock() {
                v.push(line);
            }
        }
    });
    lines
}

fn wait_for_line(lines: &Mutex<Vec<String>>, prefix: &str, timeout: Duration) -> Result<String> {
    let t0 = Instant::now();
    loop {
        if let Some(l) = lines
            .lock()
            .ok()
            .and_then(|v| v.iter().find(|l| l.starts_with(prefix)).cloned())
        {
            return Ok(l);
        }
        if t0.elapsed() > timeout {
            bail!("no line starting with {prefix:?} within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// (capture_ts_ns, position) of every stream record, recorded until the stream closes.
type Track = Arc<Mutex<Vec<(u64, [f64; 3])>>>;

fn record_stream(addr: SocketAddr) -> Result<Track> {
    let s = TcpStream::connect(addr).context("connecting to the position stream")?;
    let track: Track = Arc::new(Mutex::new(Vec::new()));
    let t = track.clone();
    std::thread::spawn(move || {
        for line in BufReader::new(s).lines().map_while(Result::ok) {
            let Ok(rec) = json::parse(&line) else { continue };
            let ts = json::at(&rec, "capture_ts_ns").and_then(serde_json::Value::as_u64);
            let p = json::vec3_at(&rec, "position_mm");
            if let (Some(ts), Some(p)) = (ts, p)
                && let Ok(mut v) = t.lock()
            {
                v.push((ts, p));
            }
        }
    });
    Ok(track)
}

fn free_port(kind: &str) -> Result<SocketAddr> {
    Ok(if kind == "socket" {
        TcpListener::bind("127.0.0.1:0")?.local_addr()?
    } else {
        UdpSocket::bind("127.0.0.1:0")?.local_addr()?
    })
}

/// The `viewers` example's binary (release), for runs with 3 viewers.
pub struct ViewerLoad<'a> {
    pub bin: &'a Path,
    pub count: usize,
}

/// One measured run's conditions.
struct Run<'a> {
    secs: f64,
    viewers: Option<&'a ViewerLoad<'a>>,
    fifo_priority: Option<u32>,
}

/// The number after `key` (e.g. `late=`) in a robot-sim summary line; 0 if absent.
fn summary_field(line: &str, key: &str) -> u64 {
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(key))
        .and_then(|v| v.parse::<u64>().ok())
        .unwrap_or(0)
}

fn run_one(
    kind: &'static str,
    irtrackd: &Path,
    host_tools: &Path,
    hash: &str,
    dir: &Path,
    run: &Run,
) -> Result<Row> {
    let (secs, viewers) = (run.secs, run.viewers);
    std::fs::create_dir_all(dir)?;
    let robot_addr = free_port(kind)?;
    let cfg_path = dir.join("irtrackd.toml");
    std::fs::write(&cfg_path, config(kind, robot_addr, hash, run.fifo_priority))?;
    let err_log = dir.join("irtrackd.log");
    let mut child = Command::new(irtrackd)
        .arg("-c")
        .arg(&cfg_path)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(dir.join("state"))
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&err_log)?)
        .spawn()
        .context("starting irtrackd")?;
    let out = collect_lines(child.stdout.take().context("irtrackd stdout")?);
    let mut ird = Proc::adopt(child, "irtrackd");
    let ready = wait_for_line(&out, "irtrackd ready", Duration::from_secs(30))?;
    let status = addr_field(&ready, "status=")?;
    let track = record_stream(addr_field(&ready, "stream=")?)?;
    let t0 = Instant::now();
    let home = loop {
        if let Some(p) = track.lock().ok().and_then(|v| v.last().map(|r| r.1)) {
            break p;
        }
        if t0.elapsed() > Duration::from_secs(20) {
            bail!("irtrackd published no position");
        }
        std::thread::sleep(Duration::from_millis(20));
    };

    let csv = dir.join("robot-sim.csv");
    let home_s = format!("{},{},{}", home[0], home[1], home[2]);
    let speed = ROBOT_SPEED_MM_S.to_string();
    let mut cmd = Command::new(host_tools);
    cmd.arg("robot-sim")
        .args(["--home", &home_s, "--speed-mm-s", &speed, "--log"])
        .arg(&csv);
    if kind == "socket" {
        cmd.args([
            "--listen",
            &robot_addr.to_string(),
            "--tick-ms",
            "4",
            "--log-every-ms",
            "4",
        ]);
    } else {
        cmd.args([
            if kind == "egm" { "--egm" } else { "--rsi" },
            "--sensor",
            &robot_addr.to_string(),
            "--listen",
            "127.0.0.1:0",
            "--cycle-ms",
            &CYCLE_MS.to_string(),
            "--duration-s",
            &(secs + 10.0).to_string(),
        ]);
    }
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .context("starting robot-sim")?;
    let sim_out = collect_lines(child.stdout.take().context("robot-sim stdout")?);
    let mut sim = Proc::adopt(child, "robot-sim");

    let t0 = Instant::now();
    loop {
        let (_, body) = http_operator(status, "POST", "/robot")?;
        if body.contains("\"state\":\"holding\"") {
            break;
        }
        if t0.elapsed() > Duration::from_secs(20) {
            bail!("the {kind} link did not come up: {body}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    for req in ["/robot/deadman?pressed=1", "/robot/enable"] {
        let (code, body) = http_operator(status, "POST", req)?;
        if code != 200 {
            bail!("POST {req} answered {code}: {body}");
        }
    }
    // Viewers watch the whole followed span (the example runs them against our status port).
    let viewer_proc = match viewers {
        Some(v) => Some(Proc::spawn(
            Command::new(v.bin)
                .args(["--connect", &status.to_string(), "--seconds"])
                .arg((secs + 5.0).to_string())
                .stderr(Stdio::null()),
            "viewers",
        )?),
        None => None,
    };
    let last_ts = |t: &Track| t.lock().ok().and_then(|v| v.last().map(|r| r.0)).unwrap_or(0);
    let t_enable = last_ts(&track);
    std::thread::sleep(Duration::from_secs_f64(secs));
    let t_end = last_ts(&track);
    let (code, status_json) = util::http(status, "GET", "/status")?;
    if code != 200 {
        bail!("GET /status answered {code}");
    }
    let split = LoopSplit {
        render: stage_quantiles(&status_json, "render")?,
        driver: stage_quantiles(&status_json, "driver")?,
        ours: stage_quantiles(&status_json, "ours")?,
        end_to_end: stage_quantiles(&status_json, "end_to_end")?,
    };
    if let Some(mut v) = viewer_proc {
        if let Some(st) = v.wait_timeout(Duration::ZERO)? {
            bail!("the viewers stopped early ({st})");
        }
        // Dropping the handle kills them.
        drop(v);
    }
    let (_, body) = http_operator(status, "POST", "/robot")?;
    if !body.contains("\"state\":\"moving\"") {
        bail!("the {kind} link is not moving at the end: {body}");
    }
    // SIGTERM: irtrackd shuts the link down, which logs its latency summary.
    let how = ird.terminate(Duration::from_secs(15))?;
    if how.starts_with("ignored") {
        bail!("irtrackd did not stop on SIGTERM: {how}");
    }
    // The socket robot-sim writes its log when the connection ends; the streaming one stops
    // after its missed-cycle limit once irtrackd is gone.
    sim.wait_timeout(Duration::from_secs(3))?;
    drop(sim);

    let log = std::fs::read_to_string(&err_log)?;
    let latency = parse_latency(&log)
        .with_context(|| format!("no latency line from irtrackd in {}", err_log.display()))?;
    let late = if kind == "socket" {
        // The socket robot has no cycle; its tick timing says whether it answered late.
        match wait_for_line(&sim_out, "robot-sim summary socket", Duration::from_secs(2)) {
            Ok(s) => {
                let f = |k: &str| summary_field(&s, k);
                format!(
                    "– (no cycle); robot-sim's 4 ms ticks woke late p50 {} / p99 {} / max {} µs, {} of {} over 1 ms",
                    f("tick_late_p50_us="),
                    f("tick_late_p99_us="),
                    f("tick_late_max_us="),
                    f("over_1ms="),
                    f("ticks=")
                )
            }
            Err(_) => "– (no cycle)".to_string(),
        }
    } else {
        let s = wait_for_line(&sim_out, "robot-sim summary", Duration::from_secs(5))?;
        let f = |k: &str| summary_field(&s, k);
        // Cycles after irtrackd stopped are missed by design; count only the followed span.
        format!(
            "{} late, {} missed of {} cycles (incl. shutdown)",
            f("late="),
            f("missed="),
            f("cycles=")
        )
    };
    let path = read_path(kind, &csv, &sim_out)?;
    let marker = track.lock().map(|v| v.clone()).unwrap_or_default();
    let from = t_enable + (SETTLE_S * 1e9) as u64;
    let to = t_end;
    let (err_mean_mm, err_max_mm) = tracking_error(&path, &marker, from, to)?;
    let (jerk_rms_m_s3, jerk_max_m_s3) = jerk(&path, from, to);
    Ok(Row {
        kind,
        viewers: viewers.map_or(0, |v| v.count),
        latency,
        split,
        late,
        err_mean_mm,
        err_max_mm,
        jerk_rms_m_s3,
        jerk_max_m_s3,
    })
}

fn parse_latency(log: &str) -> Option<Latency> {
    let line = log
        .lines()
        .rev()
        .find(|l| l.contains("robot link latency kind="))?;
    let f = |k: &str| {
        line.split_whitespace()
            .find_map(|w| w.strip_prefix(k))
            .and_then(|v| v.parse::<u64>().ok())
    };
    Some(Latency {
        n: f("n=")?,
        p50_us: f("p50_us=")?,
        p99_us: f("p99_us=")?,
        p999_us: f("p999_us=")?,
        wait_p50_us: f("wait_p50_us=")?,
        wait_p99_us: f("wait_p99_us=")?,
        // Older irtrackd logs lack it.
        wait_max_us: f("wait_max_us=").unwrap_or(0),
    })
}

/// p50/p99 of `stage` in the `/status` document (`"processing":{"latency_us":{"<stage>":{...}}}`).
fn stage_quantiles(status_json: &str, stage: &str) -> Result<Quantiles> {
    let doc = json::parse(status_json)?;
    let path = format!("processing.latency_us.{stage}");
    let obj = json::at(&doc, &path).with_context(|| format!("no stage {stage:?} in /status"))?;
    let num = |k: &str| -> f64 { json::f64_at(obj, k).unwrap_or(f64::NAN) };
    Ok(Quantiles {
        p50_us: num("p50_us"),
        p99_us: num("p99_us"),
    })
}

/// The robot's path as (CLOCK_MONOTONIC ns, TCP).
fn read_path(kind: &str, csv: &Path, sim_out: &Mutex<Vec<String>>) -> Result<Vec<(u64, [f64; 3])>> {
    let text = std::fs::read_to_string(csv).with_context(|| format!("reading {}", csv.display()))?;
    let num = |s: Option<&&str>| s.and_then(|v| v.parse::<f64>().ok());
    let mut path = Vec::new();
    if kind == "socket" {
        let l = wait_for_line(sim_out, "robot-sim clock t0_mono_ns=", Duration::from_secs(1))?;
        let t0: u64 = l
            .rsplit('=')
            .next()
            .and_then(|v| v.parse().ok())
            .context("robot-sim t0")?;
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split(',').collect();
            if f.get(2) != Some(&"pos") {
                continue;
            }
            if let (Some(t), Some(x), Some(y), Some(z)) =
                (num(f.first()), num(f.get(7)), num(f.get(8)), num(f.get(9)))
            {
                path.push((t0 + (t * 1e9) as u64, [x, y, z]));
            }
        }
    } else {
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split(',').collect();
            let t = f.get(1).and_then(|v| v.parse::<u64>().ok());
            if let (Some(t), Some(x), Some(y), Some(z)) = (t, num(f.get(3)), num(f.get(4)), num(f.get(5))) {
                path.push((t, [x, y, z]));
            }
        }
    }
    if path.len() < 10 {
        bail!(
            "robot-sim logged only {} positions ({})",
            path.len(),
            csv.display()
        );
    }
    Ok(path)
}

fn lerp(track: &[(u64, [f64; 3])], t: u64) -> Option<[f64; 3]> {
    let i = track.partition_point(|r| r.0 <= t);
    if i == 0 || i >= track.len() {
        return None;
    }
    let (t0, a) = track[i - 1];
    let (t1, b) = track[i];
    let k = if t1 > t0 {
        (t - t0) as f64 / (t1 - t0) as f64
    } else {
        0.0
    };
    Some([
        a[0] + (b[0] - a[0]) * k,
        a[1] + (b[1] - a[1]) * k,
        a[2] + (b[2] - a[2]) * k,
    ])
}

/// Distance from the robot to the tracked marker at the same instant.
fn tracking_error(
    path: &[(u64, [f64; 3])],
    marker: &[(u64, [f64; 3])],
    from: u64,
    to: u64,
) -> Result<(f64, f64)> {
    let mut errs = Vec::new();
    for &(t, p) in path.iter().filter(|r| r.0 >= from && r.0 <= to) {
        if let Some(m) = lerp(marker, t) {
            errs.push(((p[0] - m[0]).powi(2) + (p[1] - m[1]).powi(2) + (p[2] - m[2]).powi(2)).sqrt());
        }
    }
    if errs.len() < 10 {
        bail!("only {} robot positions inside the measured span", errs.len());
    }
    let mean = errs.iter().sum::<f64>() / errs.len() as f64;
    Ok((mean, errs.iter().copied().fold(0.0, f64::max)))
}

/// Jerk of the robot's path resampled every 4 ms (third differences), m/s³: RMS and max.
fn jerk(path: &[(u64, [f64; 3])], from: u64, to: u64) -> (f64, f64) {
    let dt_ns = (CYCLE_MS * 1e6) as u64;
    let mut pts = Vec::new();
    let mut t = from;
    while t <= to {
        if let Some(p) = lerp(path, t) {
            pts.push(p);
        }
        t += dt_ns;
    }
    let dt = CYCLE_MS * 1e-3;
    let mut js = Vec::new();
    for w in pts.windows(4) {
        let j2: f64 = (0..3)
            .map(|i| {
                let d3 = w[3][i] - 3.0 * w[2][i] + 3.0 * w[1][i] - w[0][i];
                (d3 / dt.powi(3) * 1e-3).powi(2)
            })
            .sum();
        js.push(j2.sqrt());
    }
    if js.is_empty() {
        return (0.0, 0.0);
    }
    let rms = (js.iter().map(|j| j * j).sum::<f64>() / js.len() as f64).sqrt();
    (rms, js.iter().copied().fold(0.0, f64::max))
}
