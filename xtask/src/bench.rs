//! `cargo xtask bench [--quick]`: builds `irtrack-bench` (host-only, release), prints its
//! timing table (ours vs OpenCV vs the memory pass, ROI vs full frame, allocations), then
//! instruction counts per stereo pair under callgrind, which are stable on a loaded machine.
//!
//! Instruction counts: each case runs twice under callgrind with different iteration
//! counts; the difference divided by the extra iterations removes set-up and rendering.
//! CI runs `--quick` (shorter timing, VGA only under callgrind); nothing is a timed pass/fail.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::ci::Counts;
use crate::util::{self, Ctx, RunOpts};

const CASES: &[&str] = &["ours-full", "ours-roi", "opencv", "sum"];

/// CI entry point: the quick benchmark; fails only if something does not build or run.
pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    cli(ctx, &["--quick".to_string()])?;
    Ok(Counts::default())
}

/// `cargo xtask bench [--quick] [--no-callgrind]`.
pub fn cli(ctx: &Ctx, args: &[String]) -> Result<()> {
    let mut quick = false;
    let mut callgrind = true;
    for a in args {
        match a.as_str() {
            "--quick" => quick = true,
            "--no-callgrind" => callgrind = false,
            other => bail!("unknown option `{other}` (usage: cargo xtask bench [--quick] [--no-callgrind])"),
        }
    }
    let mut build = ctx.cargo();
    build.args(["build", "--release", "-p", "irtrack-bench"]);
    let out = util::run(
        &mut build,
        RunOpts {
            timeout: Some(Duration::from_secs(1800)),
            ..RunOpts::default()
        },
    )?;
    if !out.success() {
        bail!("building irtrack-bench {}", out.describe());
    }
    let bin = ctx.target_dir().join("release").join("irtrack-bench");

    let mut table = Command::new(&bin);
    if quick {
        table.arg("--quick");
    }
    let out = util::run(
        &mut table,
        RunOpts {
            timeout: Some(Duration::from_secs(600)),
            ..RunOpts::default()
        },
    )?;
    if !out.success() {
        bail!("irtrack-bench {}", out.describe());
    }

    if !callgrind {
        return Ok(());
    }
    if !util::on_path("valgrind") {
        println!("valgrind not found: instruction counts skipped (`cargo xtask setup` installs it)");
        return Ok(());
    }
    let resolutions: &[&str] = if quick { &["vga"] } else { &["vga", "720p"] };
    let (n1, n2) = if quick { (2, 6) } else { (4, 16) };
    let scratch = ctx.target_dir().join("callgrind-bench.out");
    println!();
    println!("Instructions per stereo pair (callgrind, ({n2} − {n1} iterations) difference):");
    println!();
    println!("| frames | ours full | OpenCV | OpenCV/ours | sum pass | ours/sum | ours ROI | ROI/full |");
    println!("|---|---|---|---|---|---|---|---|");
    for res in resolutions {
        let mut ir = [0f64; 4];
        for (i, case) in CASES.iter().enumerate() {
            let name = format!("{case}-{res}");
            let a = instructions(&bin, &name, n1, &scratch)?;
            let b = instructions(&bin, &name, n2, &scratch)?;
            ir[i] = b.saturating_sub(a) as f64 / (n2 - n1) as f64;
        }
        let [full, roi, ocv, sum] = ir;
        println!(
            "| {res} | {} | {} | {:.1}x | {} | {:.2}x | {} | {:.2} % |",
            fmt_ir(full),
            fmt_ir(ocv),
            ocv / full,
            fmt_ir(sum),
            full / sum,
            fmt_ir(roi),
            100.0 * roi / full
        );
    }
    let _ = std::fs::remove_file(&scratch);
    Ok(())
}

/// Total instructions of one `irtrack-bench --run` under callgrind.
fn instructions(bin: &Path, case: &str, iters: u32, scratch: &Path) -> Result<u64> {
    let out = Command::new("valgrind")
        .arg("--tool=callgrind")
        .arg(format!("--callgrind-out-file={}", scratch.display()))
        .arg(bin)
        .args(["--run", case, "--iterations", &iters.to_string()])
        .stdin(std::process::Stdio::null())
        .output()
        .context("starting valgrind")?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    if !out.status.success() {
        bail!("callgrind run of `{case}` failed ({}):\n{stderr}", out.status);
    }
    // callgrind prints "==PID== Collected : <Ir>" at exit.
    stderr
        .lines()
        .find_map(|l| l.split_once("Collected :").map(|(_, v)| v.trim().to_string()))
        .context("no `Collected :` line in callgrind's output")?
        .parse::<u64>()
        .context("parsing callgrind's instruction total")
}

fn fmt_ir(ir: f64) -> String {
    if ir >= 1e6 {
        format!("{:.2} M", ir / 1e6)
    } else {
        format!("{:.1} k", ir / 1e3)
    }
}
