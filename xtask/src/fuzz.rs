//! `cargo xtask fuzz [--quick | --secs N] [--target NAME]...`: runs the cargo-fuzz targets in
//! `fuzz/` (docs/fuzzing.md) one after another and prints executions, coverage and crashes.
//!
//! CI runs `--quick` (10 s per target). The targets are built by plain `cargo build` with the
//! instrumentation flags cargo-fuzz would pass ([`SANCOV_RUSTFLAGS`]), on the pinned stable
//! toolchain: no nightly, and no cargo-fuzz to compile from source on a fresh machine.
//! Coverage comes from sanitizer-coverage instrumentation; AddressSanitizer is off because
//! the fuzzed crates are safe Rust (irtrack-core forbids `unsafe`) and it would halve the
//! execution rate. Debug assertions (and so overflow checks) are on.

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::report::Counts;
use crate::util::{self, Ctx, RunOpts};

/// Every target in fuzz/fuzz_targets, in run order.
pub const TARGETS: &[&str] = &[
    "param_blob",
    "robot_proto",
    "stream",
    "config",
    "param_wire",
    "egm",
    "rsi",
    "observation",
    "tool_stream",
];
const QUICK_SECS: u64 = 10;
/// The documented long run (docs/fuzzing.md).
const DEFAULT_SECS: u64 = 600;

/// CI entry point: every target for [`QUICK_SECS`]; any crash fails the phase.
pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    let results = run_targets(ctx, TARGETS, QUICK_SECS)?;
    let failed = results.iter().filter(|r| r.crash.is_some()).count() as u64;
    let counts = Counts {
        passed: results.len() as u64 - failed,
        failed,
        ignored: 0,
    };
    if failed > 0 {
        bail!("{failed} fuzz target(s) found a crash: {}", crash_list(&results));
    }
    Ok(counts)
}

/// `cargo xtask fuzz`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// CI's short run per target.
    #[arg(long, conflicts_with = "secs")]
    quick: bool,
    /// Seconds per target (default: the documented long run).
    #[arg(long, value_name = "N")]
    secs: Option<u64>,
    /// Only these targets (repeatable; default all).
    #[arg(long, value_name = "NAME", value_parser = clap::builder::PossibleValuesParser::new(TARGETS.iter().copied()))]
    target: Vec<String>,
}

/// `cargo xtask fuzz [--quick | --secs N] [--target NAME]...`
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let secs = match (args.quick, args.secs) {
        (true, _) => QUICK_SECS,
        (false, Some(s)) => s,
        (false, None) => DEFAULT_SECS,
    };
    let mut targets: Vec<&str> = TARGETS
        .iter()
        .copied()
        .filter(|t| args.target.iter().any(|a| a == t))
        .collect();
    if targets.is_empty() {
        targets = TARGETS.to_vec();
    }
    let results = run_targets(ctx, &targets, secs)?;
    if results.iter().any(|r| r.crash.is_some()) {
        bail!("crash(es) found: {}", crash_list(&results));
    }
    Ok(())
}

/// What one target's run reported.
#[derive(Debug, Default, PartialEq)]
struct RunResult {
    target: String,
    secs: u64,
    execs: Option<u64>,
    cov: Option<u64>,
    features: Option<u64>,
    corpus: Option<u64>,
    /// Artifact path (or the reason) when the run did not end cleanly.
    crash: Option<String>,
}

fn crash_list(results: &[RunResult]) -> String {
    results
        .iter()
        .filter_map(|r| r.crash.as_ref().map(|c| format!("{}: {c}", r.target)))
        .collect::<Vec<_>>()
        .join("; ")
}

/// Instrumentation flags, as `cargo fuzz build --sanitizer none --debug-assertions` passes
/// them (cargo-fuzz 0.12, Linux): sanitizer-coverage with inline 8-bit counters, PC table,
/// comparison tracing and stack depth (libFuzzer's `cov:`/`ft:` feedback), branch folding
/// off, `cfg(fuzzing)`, dead code kept, debug assertions (and with them overflow checks) on.
/// All are stable rustc options, so neither nightly nor cargo-fuzz itself is needed.
///
/// One deliberate difference: cargo-fuzz forces `-C codegen-units=1` for release builds
/// (better inlining, faster executions). On the 2-core CI machine that single-unit,
/// comparison-traced build of every dependency took 11.5 minutes; with the release profile's
/// default units the instrumentation, and so the coverage feedback, is the same.
const SANCOV_RUSTFLAGS: &[&str] = &[
    "-Cpasses=sancov-module",
    "-Cllvm-args=-sanitizer-coverage-level=4",
    "-Cllvm-args=-sanitizer-coverage-inline-8bit-counters",
    "-Cllvm-args=-sanitizer-coverage-pc-table",
    "-Cllvm-args=-sanitizer-coverage-trace-compares",
    "-Cllvm-args=-simplifycfg-branch-fold-threshold=0",
    "--cfg",
    "fuzzing",
    "-Clink-dead-code",
    "-Cllvm-args=-sanitizer-coverage-stack-depth",
    "-Cdebug-assertions",
];

/// The host's target triple (`rustc -vV`).
fn host_triple() -> Result<String> {
    let rustc = std::env::var_os("RUSTC").unwrap_or_else(|| "rustc".into());
    let out = Command::new(&rustc)
        .arg("-vV")
        .output()
        .context("running `rustc -vV`")?;
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .find_map(|l| l.strip_prefix("host: ").map(str::to_string))
        .context("no `host:` line in `rustc -vV`")
}

/// Builds every fuzz target with libFuzzer and coverage instrumentation (plain `cargo build`,
/// see [`SANCOV_RUSTFLAGS`]); returns the directory holding the binaries.
fn build_targets(ctx: &Ctx) -> Result<PathBuf> {
    let mut build = build_command(ctx)?;
    let out = util::run(
        &mut build,
        RunOpts {
            timeout: Some(Duration::from_secs(3600)),
            ..RunOpts::default()
        },
    )?;
    if !out.success() {
        bail!("building the fuzz targets {}", out.describe());
    }
    Ok(ctx.target_dir().join("fuzz").join(host_triple()?).join("release"))
}

/// The instrumented build of every fuzz target (also started ahead of the phase by CI, see
/// `ci::Prebuilds`: one function, so both are the same build).
pub fn build_command(ctx: &Ctx) -> Result<Command> {
    let fuzz_dir = ctx.root.join("fuzz");
    let target_dir = ctx.target_dir().join("fuzz");
    let triple = host_triple()?;
    let mut build = ctx.cargo();
    build
        .current_dir(&fuzz_dir)
        // An explicit --target keeps RUSTFLAGS away from build scripts and proc macros, which
        // must not be instrumented (they would need libFuzzer to link).
        .args(["build", "--release", "--locked", "--bins", "--target", &triple])
        .arg("--target-dir")
        .arg(&target_dir)
        .env("RUSTFLAGS", SANCOV_RUSTFLAGS.join(" "));
    Ok(build)
}

fn run_targets(ctx: &Ctx, targets: &[&str], secs: u64) -> Result<Vec<RunResult>> {
    let bin_dir = build_targets(ctx)?;
    // libFuzzer runs on one thread, so one target per core: the targets are independent and
    // each is time-boxed, so running them side by side leaves every target its full time and
    // divides the phase's wall time by the cores (CI's 2-core machine: 9 targets in 5 rounds).
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(targets.len());
    let next = std::sync::atomic::AtomicUsize::new(0);
    let slots: Vec<std::sync::Mutex<Option<Result<RunResult>>>> =
        targets.iter().map(|_| std::sync::Mutex::new(None)).collect();
    std::thread::scope(|scope| {
        for _ in 0..workers {
            scope.spawn(|| {
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(target) = targets.get(i) else { break };
                    let r = run_target(ctx, &bin_dir, target, secs);
                    if let Ok(mut slot) = slots[i].lock() {
                        *slot = Some(r);
                    }
                }
            });
        }
    });
    let mut results = Vec::new();
    for (target, slot) in targets.iter().zip(slots) {
        let r = slot
            .into_inner()
            .ok()
            .flatten()
            .with_context(|| format!("fuzz target `{target}` did not report"))??;
        results.push(r);
    }
    print_table(&results);
    Ok(results)
}

/// One target for `secs` seconds on its corpus and seeds.
fn run_target(ctx: &Ctx, bin_dir: &std::path::Path, target: &str, secs: u64) -> Result<RunResult> {
    let fuzz_dir = ctx.root.join("fuzz");
    let corpus = fuzz_dir.join("corpus").join(target);
    std::fs::create_dir_all(&corpus)?;
    let seeds = fuzz_dir.join("seeds").join(target);
    let artifacts = fuzz_dir.join("artifacts").join(target);
    std::fs::create_dir_all(&artifacts)?;
    // The binary built above, run directly: `cargo fuzz run` would rebuild first whenever a
    // source file changed since, and a rebuild must not eat into the fuzzing time.
    let bin = bin_dir.join(target);
    if !bin.is_file() {
        bail!("fuzz target `{target}` was not built ({} missing)", bin.display());
    }
    let mut run = Command::new(bin);
    run.current_dir(&fuzz_dir)
        .arg(format!("-artifact_prefix={}/", artifacts.display()))
        // New inputs go to the first (git-ignored) directory; seeds are only read.
        .arg(&corpus)
        .arg(&seeds)
        .arg(format!("-max_total_time={secs}"))
        .arg("-print_final_stats=1")
        .arg("-max_len=4096")
        .arg("-timeout=10")
        .arg("-rss_limit_mb=1024");
    let out = util::run(
        &mut run,
        RunOpts {
            capture_stdout: true,
            capture_stderr: true,
            // Side by side with another target: its progress lines would interleave.
            quiet_stdout: true,
            quiet_stderr: true,
            // libFuzzer stops itself; the limit only catches a hang.
            timeout: Some(Duration::from_secs(secs + 300)),
        },
    )?;
    let mut r = parse_run(target, secs, &out.stderr);
    println!(
        "fuzz: {target}: {} executions in {secs} s, {}",
        r.execs.map_or("?".to_string(), |e| e.to_string()),
        r.crash.as_deref().unwrap_or("no crash")
    );
    if !out.success() && r.crash.is_none() {
        r.crash = Some(format!("fuzz target {}", out.describe()));
    }
    if r.crash.is_some() {
        // The whole log of a failing target: libFuzzer's report and the stack.
        eprintln!("{}", out.stderr);
    }
    Ok(r)
}

/// Reads libFuzzer's final statistics and its last progress line from stderr.
fn parse_run(target: &str, secs: u64, stderr: &str) -> RunResult {
    let mut r = RunResult {
        target: target.to_string(),
        secs,
        ..RunResult::default()
    };
    for line in stderr.lines() {
        if let Some(v) = line.strip_prefix("stat::number_of_executed_units:") {
            r.execs = v.trim().parse().ok();
        }
        // Progress lines look like `#123456\tREDUCE cov: 812 ft: 2301 corp: 160/4873b ...`.
        if line.starts_with('#') {
            let mut words = line.split_whitespace();
            while let Some(w) = words.next() {
                let value = || {
                    words
                        .clone()
                        .next()
                        .and_then(|v| v.split('/').next()?.parse().ok())
                };
                match w {
                    "cov:" => r.cov = value().or(r.cov),
                    "ft:" => r.features = value().or(r.features),
                    "corp:" => r.corpus = value().or(r.corpus),
                    _ => {}
                }
            }
        }
        if let Some(rest) = line.split("Test unit written to ").nth(1) {
            r.crash = Some(rest.trim().to_string());
        }
    }
    r
}

fn print_table(results: &[RunResult]) {
    let opt = |v: Option<u64>| v.map_or("-".to_string(), |v| v.to_string());
    println!();
    println!("| target | time | executions | exec/s | cov (edges) | features | corpus | result |");
    println!("|---|---|---|---|---|---|---|---|");
    for r in results {
        let rate = r
            .execs
            .map_or("-".to_string(), |e| (e / r.secs.max(1)).to_string());
        println!(
            "| {} | {} s | {} | {rate} | {} | {} | {} | {} |",
            r.target,
            r.secs,
            opt(r.execs),
            opt(r.cov),
            opt(r.features),
            opt(r.corpus),
            r.crash.as_deref().unwrap_or("no crash")
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn final_stats_and_last_progress_line_are_read() {
        let stderr = "INFO: Seed: 1\n\
            #2\tINITED cov: 90 ft: 100 corp: 5/300b exec/s: 0 rss: 30Mb\n\
            #4096\tpulse  cov: 120 ft: 340 corp: 40/1200b lim: 43 exec/s: 2048 rss: 33Mb\n\
            #9000\tREDUCE cov: 131 ft: 351 corp: 44/1300b lim: 43 exec/s: 3000 rss: 33Mb L: 7/60 MS: 1 \n\
            Done 9000 runs in 3 second(s)\n\
            stat::number_of_executed_units: 9000\n";
        let r = parse_run("stream", 3, stderr);
        assert_eq!(r.execs, Some(9000));
        assert_eq!(r.cov, Some(131));
        assert_eq!(r.features, Some(351));
        assert_eq!(r.corpus, Some(44));
        assert_eq!(r.crash, None);
    }

    #[test]
    fn crash_artifact_is_reported() {
        let stderr = "==1== ERROR: libFuzzer: deadly signal\n\
            artifact_prefix='/x/artifacts/stream/'; Test unit written to /x/artifacts/stream/crash-ab12\n";
        let r = parse_run("stream", 25, stderr);
        assert_eq!(r.crash.as_deref(), Some("/x/artifacts/stream/crash-ab12"));
    }

    #[test]
    fn every_target_has_a_source_and_seeds() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
        for t in TARGETS {
            let src = root.join("fuzz/fuzz_targets").join(format!("{t}.rs"));
            assert!(src.is_file(), "{} missing", src.display());
            let seeds = root.join("fuzz/seeds").join(t);
            let n = std::fs::read_dir(&seeds).map(|d| d.count()).unwrap_or(0);
            assert!(n > 0, "no seeds in {}", seeds.display());
        }
    }
}
