//! `cargo xtask bench --by-arch`: instructions per frame set of the tracking hot path on
//! x86-64, aarch64 and armv7 (Cortex-A9), for the full-frame VGA pair and the ROI path.
//!
//! x86-64 is counted by callgrind, as the main benchmark does. Debian's QEMU user mode is built
//! without TCG plugin support (`qemu-arm -plugin` is an unknown option; `dpkg -L qemu-user`
//! lists no plugin), so the ARM builds are counted from QEMU's own logs instead, read from a
//! pipe (nothing is written to disk): `-d in_asm` prints each translation block's guest
//! instructions once, when it is translated, and `-d exec,nochain` prints one `Trace` line
//! with the block's guest address every time a block runs (`nochain` stops QEMU from jumping
//! from block to block without the log seeing it). The count is the sum, over the `Trace`
//! lines, of the instructions of the block at that address. A first version ran QEMU with
//! `-one-insn-per-tb`, one `Trace` line per instruction: the same answer, but ~15 times the
//! log and about 2 minutes per run (the benchmark's set-up renders synthetic frames), far
//! too slow. The same counter runs the x86-64 binary under `qemu-x86_64`, so the method is
//! checked against callgrind on the same binary.
//!
//! Each case runs twice with different iteration counts; the difference divided by the extra
//! iterations removes set-up (the synthetic frames, the tracker's warm-up) and the runtime.
//! QEMU runs under `setarch -R` (no address randomisation), which makes the two runs' set-up
//! nearly identical (QEMU's full-frame figure still varied by ~2 % between runs); callgrind's
//! runs repeat exactly without it.

use std::collections::HashMap;
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

/// Sums executed guest instructions from QEMU's `in_asm` + `exec` log, line by line.
#[derive(Default)]
struct LogCounter {
    /// Instructions of the translation block at each guest address (the latest translation).
    block_len: HashMap<u64, u64>,
    /// The block being read from an `IN:` section: its address and instructions so far.
    reading: Option<(u64, u64)>,
    executed: u64,
    /// `Trace` lines of a block with no `IN:` section seen (would make the count too low).
    unknown: u64,
}

impl LogCounter {
    fn line(&mut self, line: &str) {
        if let Some(rest) = line.strip_prefix("Trace ") {
            self.finish_block();
            // `Trace 0: 0x7f..host [cs_base/pc/flags/cflags] symbol`.
            let pc = rest
                .split_once('[')
                .and_then(|(_, r)| r.split('/').nth(1))
                .and_then(|hex| u64::from_str_radix(hex, 16).ok());
            match pc.and_then(|pc| self.block_len.get(&pc)) {
                Some(n) => self.executed += n,
                None => self.unknown += 1,
            }
        } else if line.starts_with("IN:") {
            self.finish_block();
            self.reading = Some((u64::MAX, 0));
        } else if let Some((first, n)) = self.reading.as_mut() {
            // `0x00038770:  f04f 0b00  mov.w fp, #0`: one guest instruction.
            match line.strip_prefix("0x").and_then(|r| r.split_once(':')) {
                Some((hex, _)) => {
                    if *n == 0 {
                        *first = u64::from_str_radix(hex, 16).unwrap_or(u64::MAX);
                    }
                    *n += 1;
                }
                None => self.finish_block(),
            }
        }
    }

    fn finish_block(&mut self) {
        if let Some((pc, n)) = self.reading.take()
            && n > 0
            && pc != u64::MAX
        {
            self.block_len.insert(pc, n);
        }
    }
}

/// Counts executed guest instructions of `<qemu words...> <bin> --run case --iterations n`.
fn qemu_instructions(qemu: &[&str], bin: &Path, case: &str, iters: u32) -> Result<u64> {
    let (prog, pre) = qemu.split_first().context("empty QEMU command")?;
    // The log goes to stdout (buffered by QEMU, unlike stderr); the benchmark's `--run` mode
    // prints nothing itself.
    // Without address randomisation: where the heap and stacks land changes the paths of
    // memcpy/memset (alignment) and so the count, by about as much as the whole ROI path
    // (measured: 1.1 k instead of 11.0 k per iteration from one pair of randomised runs).
    let mut child = Command::new("setarch")
        .args(["-R", prog])
        .args(pre)
        .args(["-d", "in_asm,exec,nochain", "-D", "/dev/stdout"])
        .arg(bin)
        .args(["--run", case, "--iterations", &iters.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {prog}"))?;
    let stdout = child.stdout.take().context("no stdout pipe")?;
    let mut stderr = child.stderr.take().context("no stderr pipe")?;
    let errors = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut text);
        text
    });
    let mut reader = BufReader::with_capacity(1 << 20, stdout);
    let mut counter = LogCounter::default();
    let mut line = Vec::with_capacity(256);
    loop {
        line.clear();
        if reader.read_until(b'\n', &mut line)? == 0 {
            break;
        }
        counter.line(String::from_utf8_lossy(&line).trim_end());
    }
    let status = child.wait()?;
    let errors = errors.join().unwrap_or_default();
    if !status.success() {
        bail!("{prog} run of `{case}` failed ({status}):\n{errors}");
    }
    if counter.unknown > 0 {
        bail!(
            "{prog} run of `{case}`: {} executed blocks had no translation in the log",
            counter.unknown
        );
    }
    Ok(counter.executed)
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
    for tool in ["valgrind", "setarch", "qemu-x86_64", "qemu-aarch64", "qemu-arm"] {
        if !util::on_path(tool) {
            bail!("{tool} not found (`cargo xtask setup` installs valgrind and qemu-user)");
        }
    }
    // The host benchmark without OpenCV, as the ARM builds are: the same code on all three,
    // and no OpenCV build for cases that do not use it.
    let mut build = ctx.cargo();
    build.args([
        "build",
        "--release",
        "-p",
        "irtrack-bench",
        "--no-default-features",
    ]);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn executed_blocks_are_summed_from_the_log() {
        // Two blocks translated (3 and 2 instructions), run 2 and 1 times; the first block is
        // then translated again with 1 instruction (QEMU re-translating a block) and runs once.
        let log = "\
----------------
IN: main
0x00010000:  e92d4800  push     {fp, lr}
0x00010004:  e28db004  add      fp, sp, #4
0x00010008:  eb000002  bl       #0x10018

Trace 0: 0x7f1200000100 [00000000/00010000/00000000/ff200000] main
IN: 
0x00010018:  e3a00000  mov      r0, #0
0x0001001c:  e12fff1e  bx       lr

Trace 0: 0x7f1200000200 [00000000/00010018/00000000/ff200000] 
Trace 0: 0x7f1200000100 [00000000/00010000/00000000/ff200000] main
IN: main
0x00010000:  e92d4800  push     {fp, lr}

Trace 0: 0x7f1200000300 [00000000/00010000/00000000/ff200000] main
";
        let mut c = LogCounter::default();
        for line in log.lines() {
            c.line(line);
        }
        assert_eq!(c.executed, 3 + 2 + 3 + 1);
        assert_eq!(c.unknown, 0);
        // A block that runs without its translation in the log is noticed, not counted as 0.
        c.line("Trace 0: 0x7f1200000400 [00000000/00020000/00000000/ff200000] ");
        assert_eq!(c.unknown, 1);
        // x86-64's 64-bit addresses.
        let mut x = LogCounter::default();
        for line in [
            "IN: ",
            "0x7f09bb781b70:  48 89 e7                 movq     %rsp, %rdi",
            "0x7f09bb781b73:  e8 f8 0b 00 00           callq    0x7f09bb782770",
            "",
            "Trace 0: 0x7f09ac000100 [00000000/00007f09bb781b70/1040c0b3/00000200] ",
        ] {
            x.line(line);
        }
        assert_eq!((x.executed, x.unknown), (2, 0));
    }
}
