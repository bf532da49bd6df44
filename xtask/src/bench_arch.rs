//! `cargo xtask bench --by-arch`: instructions per frame set of the tracking hot path on
//! x86-64, aarch64 and armv7 (Cortex-A9), for the full-frame VGA pair and the ROI path.
//!
//! x86-64 is counted by callgrind, as the main benchmark does. Debian's QEMU user mode is built
//! without TCG plugin support (`qemu-arm -plugin` is an unknown option; `dpkg -L qemu-user`
//! lists no plugin), so the ARM builds are counted with QEMU's own logging instead: with
//! `-one-insn-per-tb -d exec,nochain` every executed guest instruction is one translation block
//! and prints one `Trace` line, and the lines are counted from a pipe (nothing is written to
//! disk). The same counter runs the x86-64 binary under `qemu-x86_64`, so the method is checked
//! against callgrind on the same binary.
//!
//! Each case runs twice with different iteration counts; the difference divided by the extra
//! iterations removes set-up (the synthetic frames, the tracker's warm-up) and the runtime.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{Context, Result, bail};

use crate::cross::{self, Arch};
use crate::util::{self, Ctx};

/// The cases: the full-frame VGA stereo pair and the ROI (tracking windows) path.
const CASES: &[&str] = &["ours-full-vga", "ours-roi-vga"];
/// Iteration counts of the two runs of a case.
const ITERS: (u32, u32) = (2, 6);

/// Counts executed guest instructions of `<qemu words...> <bin> --run case --iterations n`.
fn qemu_instructions(qemu: &[&str], bin: &Path, case: &str, iters: u32) -> Result<u64> {
    let (prog, pre) = qemu.split_first().context("empty QEMU command")?;
    let mut child = Command::new(prog)
        .args(pre)
        .args(["-one-insn-per-tb", "-d", "exec,nochain"])
        .arg(bin)
        .args(["--run", case, "--iterations", &iters.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {prog}"))?;
    let stderr = child.stderr.take().context("no stderr pipe")?;
    let mut reader = BufReader::with_capacity(1 << 20, stderr);
    let mut line = Vec::with_capacity(256);
    let mut traces = 0u64;
    let mut other = Vec::new();
    loop {
        line.clear();
        if reader.read_until(b'\n', &mut line)? == 0 {
            break;
        }
        if line.starts_with(b"Trace ") {
            traces += 1;
        } else if other.len() < 20 {
            other.push(String::from_utf8_lossy(&line).into_owned());
        }
    }
    let status = child.wait()?;
    if !status.success() {
        bail!("{prog} run of `{case}` failed ({status}):\n{}", other.join(""));
    }
    Ok(traces)
}

/// Per-iteration instructions of `case` from two runs of `count`.
fn per_iteration(count: impl Fn(u32) -> Result<u64>) -> Result<f64> {
    let (n1, n2) = ITERS;
    let a = count(n1)?;
    let b = count(n2)?;
    Ok(b.saturating_sub(a) as f64 / f64::from(n2 - n1))
}

/// One row of the table.
struct Row {
    label: String,
    full: f64,
    roi: f64,
}

/// `cargo xtask bench --by-arch`.
pub fn run(ctx: &Ctx) -> Result<()> {
    for tool in ["valgrind", "qemu-x86_64", "qemu-aarch64", "qemu-arm"] {
        if !util::on_path(tool) {
            bail!("{tool} not found (`cargo xtask setup` installs valgrind and qemu-user)");
        }
    }
    // The host benchmark as `cargo xtask bench` builds it (its OpenCV cases are not run here).
    let mut build = ctx.cargo();
    build.args(["build", "--release", "-p", "irtrack-bench"]);
    util::run_ok(
        &mut build,
        "building irtrack-bench",
        Duration::from_secs(1800),
        false,
    )?;
    let host = ctx.target_dir().join("release").join("irtrack-bench");
    let aarch64 = cross::build_static(ctx, Arch::Aarch64, "irtrack-bench", &["--no-default-features"])?
        .join("irtrack-bench");
    let armv7 = cross::build_static(ctx, Arch::Armv7, "irtrack-bench", &["--no-default-features"])?
        .join("irtrack-bench");

    let scratch = ctx.target_dir().join("callgrind-by-arch.out");
    let mut rows = Vec::new();
    let mut measure = |label: &str, count: &dyn Fn(&str, u32) -> Result<u64>| -> Result<()> {
        let mut ir = [0.0; 2];
        for (i, case) in CASES.iter().enumerate() {
            println!("(counting {case} on {label})");
            ir[i] = per_iteration(|n| count(case, n))?;
        }
        rows.push(Row {
            label: label.to_string(),
            full: ir[0],
            roi: ir[1],
        });
        Ok(())
    };
    measure("x86-64 (callgrind)", &|case, n| {
        crate::bench::callgrind_instructions(&host, case, n, &scratch)
    })?;
    measure("x86-64 (qemu-x86_64 count)", &|case, n| {
        qemu_instructions(&["qemu-x86_64"], &host, case, n)
    })?;
    measure("aarch64 (qemu-aarch64 count)", &|case, n| {
        qemu_instructions(&["qemu-aarch64"], &aarch64, case, n)
    })?;
    measure("armv7 Cortex-A9 + NEON (qemu-arm count)", &|case, n| {
        qemu_instructions(&["qemu-arm", "-cpu", "cortex-a9"], &armv7, case, n)
    })?;
    let _ = std::fs::remove_file(&scratch);

    println!();
    println!(
        "Instructions per VGA stereo pair ((({}) − ({}) iterations) difference; x86-64 = callgrind):",
        ITERS.1, ITERS.0
    );
    println!();
    println!("| build | full frame | ROI | ROI/full | full vs x86-64 | ROI vs x86-64 |");
    println!("|---|---|---|---|---|---|");
    let (base_full, base_roi) = (rows[0].full, rows[0].roi);
    for r in &rows {
        println!(
            "| {} | {:.1} k | {:.1} k | {:.2} % | {:.2}x | {:.2}x |",
            r.label,
            r.full / 1e3,
            r.roi / 1e3,
            100.0 * r.roi / r.full,
            r.full / base_full,
            r.roi / base_roi
        );
    }
    if let Some(a9) = rows.last() {
        println!();
        println!(
            "Cortex-A9 at 1 GHz, estimate at 1.0–0.5 instructions per cycle (in-order-ish dual \
             issue; memory stalls of a cold frame not included): full frame {:.2}–{:.2} ms, ROI \
             {:.3}–{:.3} ms per pair",
            a9.full / 1e6,
            a9.full / 0.5e6,
            a9.roi / 1e6,
            a9.roi / 0.5e6
        );
    }
    Ok(())
}
