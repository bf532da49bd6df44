//! `cargo xtask bench --latency` (and the full `cargo xtask bench`): the latency tables of
//! issue 30, one section each, printed one after the other by [`table`]:
//!
//! 1. [`loop_section`]: the processing loop's stages with 0 and 3 live viewers, side by side
//!    in one run (`irtrack-firmware`'s `viewers` example, release, the loop SCHED_FIFO where
//!    permitted);
//! 2. [`links_section`]: capture → robot packet split into driver, ours and protocol wait per
//!    robot link kind (socket, EGM, RSI), with 0 and 3 viewers (irtrackd and `host-tools
//!    robot-sim` as separate processes, [`crate::bench_links::decomposition`]);
//! 3. [`prediction_section`]: EGM/RSI with `predict = true`, the extrapolated target's error
//!    at 250 mm/s against the simulator's truth at send time (the firmware's `prediction`
//!    test, release build, its result lines reprinted);
//! 4. [`output_latency_table`]: capture → sent per standard output (NatNet, MCAP, ROS 2).
//!
//! A further section is one more function here,
//! called from [`table`]; the sections share nothing but the run length.

use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::bench_links::{Quantiles, ViewerLoad};
use crate::util::{self, Ctx};

/// SCHED_FIFO priority the loop gets in these runs (applied only where permitted; the tables
/// say whether it was).
pub const FIFO_PRIORITY: u32 = 50;

/// Every latency section, `seconds` per measured condition.
pub fn table(ctx: &Ctx, seconds: u32) -> Result<()> {
    loop_section(ctx, seconds)?;
    links_section(ctx, seconds)?;
    prediction_section(ctx)?;
    output_latency_table(ctx)?;
    Ok(())
}

/// Quantiles (µs) of one row of the `viewers` example's output.
struct LatencyRow {
    sets: u64,
    p50: f64,
    p90: f64,
    p99: f64,
    p999: f64,
    max: f64,
}

/// Finds the row starting with `label` in the `viewers` example's table.
fn latency_row(text: &str, label: &str) -> Result<LatencyRow> {
    let line = text
        .lines()
        .find(|l| l.starts_with(label))
        .with_context(|| format!("no `{label}` row in the viewers example's output"))?;
    let v: Vec<f64> = line[label.len()..]
        .split_whitespace()
        .map(|w| w.parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("parsing `{line}`"))?;
    let [sets, p50, p90, p99, p999, max] = v[..] else {
        bail!("`{line}`: expected 6 numbers");
    };
    Ok(LatencyRow {
        sets: sets as u64,
        p50,
        p90,
        p99,
        p999,
        max,
    })
}

/// Section 1: the processing loop with 0 and 3 viewers (the firmware's `viewers` example,
/// `seconds` per condition in alternating slices, simulated 2 × VGA at 100 fps).
fn loop_section(ctx: &Ctx, seconds: u32) -> Result<()> {
    let mut cmd = ctx.cargo();
    cmd.args([
        "run",
        "--release",
        "-p",
        "irtrack-firmware",
        "--example",
        "viewers",
        "--",
        "--seconds",
        &seconds.to_string(),
        "--fps",
        "100",
        "--fifo-priority",
        &FIFO_PRIORITY.to_string(),
    ]);
    let out = util::run_ok(&mut cmd, "the viewers example", Duration::from_secs(1800), true)?;
    let mut rows = Vec::new();
    for v in [0, 3] {
        rows.extend([
            (
                format!("simulator rendering (ahead of capture), {v} viewers"),
                format!("render (simulator), {v} viewers"),
            ),
            (
                format!("driver: capture → dequeued, {v} viewers"),
                format!("driver, {v} viewers"),
            ),
            (
                format!("**ours: dequeued → published, {v} viewers**"),
                format!("ours, {v} viewers"),
            ),
            (
                format!("whole set incl. viewer copy, {v} viewers"),
                format!("process time, {v} viewers"),
            ),
            (
                format!("capture → published record, {v} viewers"),
                format!("capture→publish, {v} viewers"),
            ),
        ]);
    }
    let echo = |prefix: &str| {
        out.stdout
            .lines()
            .find(|l| l.starts_with(prefix))
            .unwrap_or("")
            .to_string()
    };
    println!();
    println!(
        "Latency of the loop (simulated 2 × VGA at 100 fps, {seconds} s per condition, 0 and 3 viewers alternating; viewers: 3 WebSockets asking for 30 fps full-width previews, 64 px zooms and every set's blobs):"
    );
    println!("{}", echo("scheduling of the loop thread:"));
    println!("{}", echo("viewer phases:"));
    println!();
    println!("| path | sets | p50 | p90 | p99 | p99.9 | max |");
    println!("|---|---|---|---|---|---|---|");
    for (name, label) in rows {
        let r = latency_row(&out.stdout, &label)?;
        println!(
            "| {name} | {} | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs |",
            r.sets, r.p50, r.p90, r.p99, r.p999, r.max
        );
    }
    println!(
        "(measured by `cargo run --release -p irtrack-firmware --example viewers -- --seconds {seconds} --fps 100 --fifo-priority {FIFO_PRIORITY}`)"
    );
    timing_rows(ctx, seconds)
}

/// The loop's own latency with time-true tracking at work (issue 39's goal: dequeued →
/// published p99 ≤ 100 µs with no viewer, free-running rolling-shutter cameras retimed),
/// beside cameras exposing together in alternating slices of one run.
fn timing_rows(ctx: &Ctx, seconds: u32) -> Result<()> {
    let mut cmd = ctx.cargo();
    cmd.args([
        "run",
        "--release",
        "-p",
        "irtrack-firmware",
        "--example",
        "viewers",
        "--",
        "--timing-compare",
        "--seconds",
        &seconds.to_string(),
        "--fps",
        "100",
    ]);
    let out = util::run_ok(
        &mut cmd,
        "the viewers example (--timing-compare)",
        Duration::from_secs(1800),
        true,
    )?;
    println!();
    println!(
        "Latency of the loop with time-true tracking (simulated 2 × VGA at 100 fps, no viewers, {seconds} s per condition, alternating): cameras exposing together vs free-running (phases over the period, ±50 ppm, 200 µs jitter) with a 15 µs/row rolling shutter, retimed to one instant:"
    );
    println!();
    println!("| path | sets | p50 | p90 | p99 | p99.9 | max |");
    println!("|---|---|---|---|---|---|---|");
    for (name, label) in [
        (
            "**ours: dequeued → published, exposing together**",
            "ours, together",
        ),
        (
            "**ours: dequeued → published, free-running + rolling, retimed**",
            "ours, free-running",
        ),
        (
            "capture → published record, exposing together",
            "capture→publish, together",
        ),
        (
            "capture → published record, free-running, retimed",
            "capture→publish, free-running",
        ),
    ] {
        let r = latency_row(&out.stdout, label)?;
        println!(
            "| {name} | {} | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs | {:.1} µs |",
            r.sets, r.p50, r.p90, r.p99, r.p999, r.max
        );
    }
    for prefix in ["ratio free-running", "sets without a position"] {
        for l in out.stdout.lines().filter(|l| l.starts_with(prefix)) {
            println!("{l}");
        }
    }
    let free = latency_row(&out.stdout, "ours, free-running")?;
    println!(
        "goal: ours p99 ≤ 100 µs with time-true tracking: {} ({:.1} µs)",
        if free.p99 <= 100.0 { "met" } else { "NOT met" },
        free.p99
    );
    Ok(())
}

/// Section 2: capture → robot packet per link kind, with 0 and 3 viewers.
fn links_section(ctx: &Ctx, seconds: u32) -> Result<()> {
    // The same example, `--connect`, against irtrackd's status port: built by section 1 or here.
    let mut build = ctx.cargo();
    build.args([
        "build",
        "--release",
        "-p",
        "irtrack-firmware",
        "--example",
        "viewers",
    ]);
    util::run_ok(
        &mut build,
        "building the viewers example",
        Duration::from_secs(1800),
        false,
    )?;
    let viewers_bin = ctx.target_dir().join("release").join("examples").join("viewers");
    let load = ViewerLoad {
        bin: &viewers_bin,
        count: 3,
    };
    let links = crate::bench_links::decomposition(ctx, f64::from(seconds), &load, FIFO_PRIORITY)?;
    println!();
    println!(
        "Capture → robot packet, decomposed (irtrackd release with [realtime] fifo_priority = {FIFO_PRIORITY} where permitted, and robot-sim, as separate processes; marker on a 100 mm circle at 250 mm/s, 120 fps; the socket robot asks every 4 ms, EGM/RSI cycle 4 ms; {seconds} s per row). \
         driver = capture → dequeued, ours = dequeued → published, protocol wait = published → on the wire; p50 / p99 in µs:"
    );
    println!();
    println!(
        "| link | viewers | targets | driver | ours | capture → published | protocol wait | wait max | capture → packet (sample age when it left) | p99.9 age | (simulator rendering, ahead of capture) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    let q = |x: Quantiles| format!("{:.1} / {:.1}", x.p50_us, x.p99_us);
    for r in &links {
        println!(
            "| {} | {} | {} | {} | {} | {} | {} / {} | {} | {} / {} | {} | {} |",
            r.kind,
            r.viewers,
            r.latency.n,
            q(r.split.driver),
            q(r.split.ours),
            q(r.split.end_to_end),
            r.latency.wait_p50_us,
            r.latency.wait_p99_us,
            r.latency.wait_max_us,
            r.latency.p50_us,
            r.latency.p99_us,
            r.latency.p999_us,
            q(r.split.render),
        );
    }
    for r in links.iter().filter(|r| r.kind == "socket") {
        println!(
            "socket link, {} viewers: protocol wait p99 {:.2} ms, max {:.2} ms against the robot's request period 4 ms ({}); {}",
            r.viewers,
            r.latency.wait_p99_us as f64 / 1e3,
            r.latency.wait_max_us as f64 / 1e3,
            if r.latency.wait_p99_us <= 4000 {
                "p99 within"
            } else {
                "p99 NOT within"
            },
            r.late
        );
    }
    Ok(())
}

/// Section 3: the prediction error of EGM and RSI against the simulator's truth.
fn prediction_section(ctx: &Ctx) -> Result<()> {
    let mut cmd = ctx.cargo();
    cmd.args([
        "test",
        "--release",
        "-p",
        "irtrack-firmware",
        "--test",
        "prediction",
        "--",
        "--nocapture",
        "--test-threads",
        "1",
    ]);
    let out = util::run_ok(&mut cmd, "the prediction test", Duration::from_secs(1800), true)?;
    println!();
    println!(
        "EGM/RSI target error against the simulator's truth at send time (marker on a 100 mm circle at 250 mm/s, 120 fps, controller cycle 4 ms, irtrackd in-process, release; goal with predict = true: ≤ 0.3 mm RMS):"
    );
    println!();
    println!("| link | predict | answered cycles | RMS | p99 | max |");
    println!("|---|---|---|---|---|---|");
    let mut rows = 0;
    for line in out.stdout.lines() {
        // libtest may print `test NAME ... ` before a line the test prints.
        const MARK: &str = "prediction error vs simulator truth: ";
        let Some(rest) = line.find(MARK).map(|i| &line[i + MARK.len()..]) else {
            continue;
        };
        let f = |k: &str| {
            rest.split_whitespace()
                .find_map(|w| w.strip_prefix(k))
                .unwrap_or("?")
                .to_string()
        };
        println!(
            "| {} | {} | {} | {} mm | {} mm | {} mm |",
            f("kind="),
            f("predict="),
            f("cycles="),
            f("rms_mm="),
            f("p99_mm="),
            f("max_mm=")
        );
        rows += 1;
    }
    if rows == 0 {
        bail!("the prediction test printed no result line");
    }
    println!("(measured by `cargo test --release -p irtrack-firmware --test prediction -- --nocapture`)");
    Ok(())
}

/// Capture → sent per standard output (NatNet, MCAP, ROS 2), from the outputs' own
/// histograms in their stalled-consumer tests (release build, like the other sections; irtrackd
/// on the simulated cameras at 120 fps; the ROS 2 test runs in a network namespace of its own).
/// A section of [`table`].
fn output_latency_table(ctx: &Ctx) -> Result<()> {
    let mut cmd = ctx.cargo();
    cmd.args([
        "test",
        "--release",
        "-p",
        "irtrack-firmware",
        "--features",
        "mcap,ros2",
        "--test",
        "outputs_stalled",
        "--test",
        "ros2_dds",
        "slow",
        "--",
        "--nocapture",
        "--test-threads=1",
    ]);
    let out = util::run_ok(
        &mut cmd,
        "the outputs' stalled-consumer tests",
        Duration::from_secs(1800),
        true,
    )?;
    let rows: Vec<Vec<&str>> = out
        .stdout
        .lines()
        // libtest may print `test NAME ... ` before the line a test prints.
        .filter_map(|l| {
            l.find("OUTPUT-LATENCY|")
                .map(|i| &l[i + "OUTPUT-LATENCY|".len()..])
        })
        .map(|l| l.split('|').collect::<Vec<_>>())
        .filter(|v| v.len() == 6)
        .collect();
    if rows.len() < 3 {
        bail!("expected 3 output latency rows, got {}", rows.len());
    }
    println!();
    println!(
        "Capture → sent per output (handed to the kernel / DDS stack / file buffer; release build, simulated 120 fps, with a stalled consumer):"
    );
    println!();
    println!("| output | records | p50 | p90 | p99 | max | measured by |");
    println!("|---|---|---|---|---|---|---|");
    for r in rows {
        println!(
            "| {} | {} | {} µs | {} µs | {} µs | {} µs | `cargo test --release -p irtrack-firmware --features mcap,ros2 --test outputs_stalled --test ros2_dds slow` |",
            r[0], r[1], r[2], r[3], r[4], r[5]
        );
    }
    Ok(())
}
