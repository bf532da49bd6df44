//! `cargo xtask bench [--quick]`: builds `irtrack-bench` (host-only, release), prints its
//! timing table — every case hot (one frame set in cache) and cold (a ring of ≥ 16 frame sets
//! ≥ 2× the last-level cache, like a V4L2 buffer queue) side by side: ours vs OpenCV vs the
//! memory passes, ROI vs full frame, allocations, for synthetic 8- and 10-bit frames and the
//! simulator's realistic ones — then the several-tools tables (1, 3 and 8 tools, VGA and
//! 720p side by side, per set and per tool, allocations; issue 29's accuracy runs against the
//! simulator's truth, 60 s, 10 s with `--quick`), then instruction counts per stereo pair under callgrind,
//! which are stable on a loaded machine (including blob detection in the two tracking
//! windows with the SIMD and the portable kernel).
//!
//! Instruction counts: each case runs twice under callgrind with different iteration
//! counts; the difference divided by the extra iterations removes set-up and rendering.
//! CI runs `--quick` (shorter timing, VGA only under callgrind); nothing is a timed pass/fail.
//!
//! Latency (full run only, or `--latency` alone): one table of the loop's latency with 0 and
//! 3 live viewers (`irtrack-firmware`'s `viewers` example, run here and its figures reprinted)
//! and a row per robot link kind (socket protocol, ABB EGM, KUKA RSI) for the capture → robot
//! packet latency, which `cargo xtask bench-links` measures (docs/robot-streaming.md).
//!
//! Cluster (full run, or `--cluster` alone; `--cluster --quick` for a short one): camera
//! boards and a solver over Zenoh beside the standalone board (`irtrack-firmware`'s
//! `cluster_bench` example, release, feature `cluster`): observation hop p50/p99 for 2 and 4
//! boards, bytes per observation, solver CPU and allocations per set at 8 cameras, and
//! capture → published for a solver and a standalone board, side by side (docs/cluster.md).
//! Not in CI's quick run: its release build of Zenoh (about 200 crates) would cost the bench
//! phase several minutes cold; CI's host tests run the cluster's tests.
//!
//! `--aarch64`: the OpenCV-free benchmark (`--no-default-features`) and `irtrackd`, both
//! cross-built static for aarch64, run under QEMU user mode: the benchmark table there (its
//! ratios; absolute times are the emulator's), the binary size, and the resident memory of
//! `irtrackd` with the simulated source after it has run a while. QEMU user mode's resident
//! set includes the emulator and its translated code, so an idle static binary under the same
//! QEMU is measured too and the difference is printed as the guest's share.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::cross;
use crate::report::Counts;
use crate::util::{self, Ctx, Proc};

const CASES: &[&str] = &[
    "ours-full",
    "ours-roi",
    "opencv",
    "sum",
    "windows-simd",
    "windows-portable",
];

/// CI entry point: the quick benchmark; fails only if something does not build or run.
pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    cli(
        ctx,
        &Args {
            quick: true,
            ..Args::default()
        },
    )?;
    Ok(Counts::default())
}

/// The release build of `irtrack-bench` (also started ahead of the phase by CI, see
/// `ci::Prebuilds`: one function, so both are the same build).
pub fn build_command(ctx: &Ctx) -> Command {
    let mut build = ctx.cargo();
    build.args(["build", "--release", "-p", "irtrack-bench"]);
    build
}

/// `cargo xtask bench`.
#[derive(Debug, Default, clap::Args)]
pub struct Args {
    /// The short run CI does (no latency table unless --latency).
    #[arg(long)]
    pub quick: bool,
    /// Leave out the callgrind instruction counts.
    #[arg(long)]
    pub no_callgrind: bool,
    /// Only the latency table (loop with 0 and 3 viewers, robot links).
    #[arg(long, conflicts_with = "no_latency")]
    pub latency: bool,
    /// Leave out the latency table.
    #[arg(long)]
    pub no_latency: bool,
    /// The benchmark cross-built for aarch64, run under qemu-aarch64.
    #[arg(long)]
    pub aarch64: bool,
    /// Only instructions per VGA frame set (full frame, ROI) on x86-64, aarch64 and armv7
    /// (Cortex-A9), counted by callgrind and QEMU (xtask/src/bench_arch.rs).
    #[arg(long, conflicts_with = "aarch64")]
    pub by_arch: bool,
    /// Only the cluster section (camera boards and a solver beside the standalone board).
    #[arg(long, conflicts_with_all = ["latency", "no_cluster"])]
    pub cluster: bool,
    /// Leave out the cluster section.
    #[arg(long)]
    pub no_cluster: bool,
    /// Cluster section: only Zenoh's low-latency transport (default: both transports side by side).
    #[arg(long, conflicts_with = "default_transport")]
    pub low_latency: bool,
    /// Cluster section: only Zenoh's default transport.
    #[arg(long)]
    pub default_transport: bool,
}

impl Args {
    /// The cluster benchmark's arguments: the hop rows also with every thread SCHED_FIFO
    /// where permitted (the priority of the latency table), the transports asked for.
    fn cluster_args(&self, quick: bool) -> Vec<String> {
        let mut a = vec![
            "--fifo".to_string(),
            crate::bench_latency::FIFO_PRIORITY.to_string(),
        ];
        if quick {
            a.push("--quick".into());
        }
        if self.low_latency {
            a.push("--low-latency".into());
        }
        if self.default_transport {
            a.push("--default-transport".into());
        }
        a
    }
}

/// `cargo xtask bench [--quick] [--no-callgrind] [--no-latency] [--latency] [--aarch64]`.
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let (quick, callgrind, aarch64) = (args.quick, !args.no_callgrind, args.aarch64);
    let latency = if args.latency {
        Some(true)
    } else if args.no_latency {
        Some(false)
    } else {
        None
    };
    if aarch64 {
        return aarch64_bench(ctx, quick);
    }
    if args.by_arch {
        return crate::bench_arch::run(ctx);
    }
    if latency == Some(true) {
        return crate::bench_latency::table(ctx, 8);
    }
    if args.cluster {
        return crate::bench_cluster::run(ctx, true, &args.cluster_args(quick));
    }
    // The latency run builds the firmware in release and takes ~20 s of wall time: not in the
    // quick (CI) run.
    let latency = latency.unwrap_or(!quick);
    let mut build = build_command(ctx);
    util::run_ok(
        &mut build,
        "building irtrack-bench",
        Duration::from_secs(1800),
        false,
    )?;
    let bin = ctx.target_dir().join("release").join("irtrack-bench");

    print_table(Command::new(&bin), quick, 600, "irtrack-bench")?;

    if callgrind {
        instruction_table(&bin, ctx, quick)?;
    }
    if latency {
        crate::bench_latency::table(ctx, 8)?;
    } else {
        println!();
        println!(
            "Latency table (loop with 0 and 3 viewers, robot links) skipped: `cargo xtask bench --latency`."
        );
    }
    if !quick && !args.no_cluster {
        crate::bench_cluster::run(ctx, true, &args.cluster_args(false))?;
    } else {
        println!();
        println!(
            "Cluster section (boards and a solver beside the standalone board) skipped: `cargo xtask bench --cluster [--quick]`."
        );
    }
    Ok(())
}

/// Instruction counts per stereo pair under callgrind.
fn instruction_table(bin: &Path, ctx: &Ctx, quick: bool) -> Result<()> {
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
    println!(
        "| frames | ours full | OpenCV | OpenCV/ours | sum pass | ours/sum | ours ROI | ROI/full | 2 windows, SIMD | 2 windows, portable | SIMD/portable |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for res in resolutions {
        let mut ir = [0f64; 6];
        for (i, case) in CASES.iter().enumerate() {
            let name = format!("{case}-{res}");
            // The two runs of a case are independent: run them side by side (instruction
            // counts do not depend on what else runs; wall time halves on two cores).
            let scratch2 = scratch.with_extension("out2");
            let (a, b) = std::thread::scope(|sc| {
                let a = sc.spawn(|| callgrind_instructions(bin, &name, n1, &scratch));
                let b = callgrind_instructions(bin, &name, n2, &scratch2);
                (a.join(), b)
            });
            let a = a.map_err(|_| anyhow::anyhow!("callgrind thread panicked"))??;
            let b = b?;
            let _ = std::fs::remove_file(&scratch2);
            ir[i] = b.saturating_sub(a) as f64 / (n2 - n1) as f64;
        }
        let [full, roi, ocv, sum, win_simd, win_portable] = ir;
        println!(
            "| {res} | {} | {} | {:.1}x | {} | {:.2}x | {} | {:.2} % | {} | {} | {:.2} |",
            fmt_ir(full),
            fmt_ir(ocv),
            ocv / full,
            fmt_ir(sum),
            full / sum,
            fmt_ir(roi),
            100.0 * roi / full,
            fmt_ir(win_simd),
            fmt_ir(win_portable),
            win_simd / win_portable
        );
    }
    let _ = std::fs::remove_file(&scratch);
    Ok(())
}

/// Total instructions of one `irtrack-bench --run` under callgrind.
pub fn callgrind_instructions(bin: &Path, case: &str, iters: u32, scratch: &Path) -> Result<u64> {
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

/// `cargo xtask bench --aarch64 [--quick]` (see the module documentation).
fn aarch64_bench(ctx: &Ctx, quick: bool) -> Result<()> {
    if !util::on_path("qemu-aarch64") {
        bail!("qemu-aarch64 not found (`cargo xtask setup` installs qemu-user)");
    }
    // Same target subdirectory and flags as `cross::build_irtrackd`: shared dependencies.
    let arch = cross::Arch::Aarch64;
    let bench =
        cross::build_static(ctx, arch, "irtrack-bench", &["--no-default-features"])?.join("irtrack-bench");
    let irtrackd = cross::build_irtrackd(ctx, arch)?;

    println!();
    println!(
        "irtrack-bench on aarch64 under qemu-aarch64 (user mode; emulated, so only the ratios mean much):"
    );
    let mut under_qemu = Command::new("qemu-aarch64");
    under_qemu.arg(&bench);
    print_table(under_qemu, quick, 1200, "irtrack-bench under qemu-aarch64")?;

    println!();
    let size = std::fs::metadata(&irtrackd)
        .with_context(|| format!("reading {}", irtrackd.display()))?
        .len();
    println!(
        "irtrackd (aarch64, static, release): {} bytes ({:.2} MiB), {}",
        size,
        size as f64 / (1024.0 * 1024.0),
        irtrackd.display()
    );
    // The release profile keeps debug information; what a board needs is the stripped file.
    let stripped = irtrackd.with_extension("stripped");
    if util::on_path("aarch64-linux-gnu-strip")
        && Command::new("aarch64-linux-gnu-strip")
            .arg("-o")
            .arg(&stripped)
            .arg(&irtrackd)
            .status()?
            .success()
    {
        let len = std::fs::metadata(&stripped)?.len();
        println!(
            "stripped: {} bytes ({:.2} MiB)",
            len,
            len as f64 / (1024.0 * 1024.0)
        );
        let _ = std::fs::remove_file(&stripped);
    }
    if util::on_path("aarch64-linux-gnu-size") {
        let o = Command::new("aarch64-linux-gnu-size").arg(&irtrackd).output()?;
        print!("{}", String::from_utf8_lossy(&o.stdout));
    }

    let settle = Duration::from_secs(if quick { 10 } else { 30 });
    let daemon = irtrackd_memory(&irtrackd, settle)?;
    let idle = idle_memory(&bench, Duration::from_secs(3))?;
    println!();
    println!(
        "Resident memory under qemu-aarch64 (host /proc/<pid>/status of the QEMU process, {} s):",
        settle.as_secs()
    );
    println!();
    println!("| process | VmRSS | VmHWM | note |");
    println!("|---|---|---|---|");
    println!(
        "| irtrackd, simulated VGA rig at 30 fps | {} | {} | {} frame sets processed, {} published |",
        kib(daemon.rss_kib),
        kib(daemon.hwm_kib),
        daemon.sets_processed,
        daemon.published
    );
    println!(
        "| idle static Rust binary (QEMU baseline) | {} | {} | `irtrack-bench --idle` |",
        kib(idle.rss_kib),
        kib(idle.hwm_kib)
    );
    println!(
        "| difference ≈ irtrackd's own share | {} | {} | includes code QEMU translated for it |",
        kib(daemon.rss_kib.saturating_sub(idle.rss_kib)),
        kib(daemon.hwm_kib.saturating_sub(idle.hwm_kib))
    );
    println!(
        "| first → last sample of irtrackd (steady state?) | {} → {} | | sampled at {} s and {} s |",
        kib(daemon.first_rss_kib),
        kib(daemon.rss_kib),
        settle.as_secs() / 2,
        settle.as_secs()
    );
    Ok(())
}

fn kib(v: u64) -> String {
    format!("{:.1} MiB", v as f64 / 1024.0)
}

/// VmRSS and VmHWM (KiB) of a process from /proc.
fn vm_kib(pid: u32) -> Result<(u64, u64)> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status"))
        .with_context(|| format!("reading /proc/{pid}/status"))?;
    let field = |name: &str| -> Result<u64> {
        text.lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|v| v.parse().ok())
            .with_context(|| format!("no {name} in /proc/{pid}/status"))
    };
    Ok((field("VmRSS:")?, field("VmHWM:")?))
}

struct DaemonMemory {
    first_rss_kib: u64,
    rss_kib: u64,
    hwm_kib: u64,
    sets_processed: u64,
    published: u64,
}

/// Runs `irtrackd` under QEMU with the simulated source, waits for its ready line, samples
/// its memory at `settle / 2` and `settle`, and reads its frame counters from `/status`.
fn irtrackd_memory(irtrackd: &Path, settle: Duration) -> Result<DaemonMemory> {
    let state = std::env::temp_dir().join(format!("irtrack-bench-aarch64-{}", std::process::id()));
    std::fs::create_dir_all(&state)?;
    let mut child = Proc::spawn(
        Command::new("qemu-aarch64")
            .arg(irtrackd)
            .args([
                "--ephemeral-ports",
                "127.0.0.1",
                "--params-from-simulator",
                "--sim-fps",
                "30",
            ])
            .arg("--state-dir")
            .arg(&state)
            .stderr(Stdio::null()),
        "irtrackd under qemu-aarch64",
    )?;
    let pid = child.pid();
    let ready = child.wait_line("irtrackd ready", Duration::from_secs(120))?;
    let status_addr = util::addr_field(&ready, "status=")?;
    let t0 = Instant::now();
    std::thread::sleep(settle / 2);
    let (first_rss_kib, _) = vm_kib(pid)?;
    std::thread::sleep(settle.saturating_sub(t0.elapsed()));
    let (rss_kib, hwm_kib) = vm_kib(pid)?;
    let (_, report) = util::http(status_addr, "GET", "/status")?;
    let doc = util::json::parse(&report)?;
    let counter = |name: &str| {
        util::json::at(&doc, name)
            .and_then(serde_json::Value::as_u64)
            .unwrap_or(0)
    };
    let (sets_processed, published) = (
        counter("processing.sets_processed"),
        counter("processing.published"),
    );
    if let Some(status) = child.wait_timeout(Duration::ZERO)? {
        bail!("irtrackd under qemu-aarch64 exited early ({status})");
    }
    drop(child);
    let _ = std::fs::remove_dir_all(&state);
    if sets_processed == 0 {
        bail!("irtrackd under qemu-aarch64 processed no frame sets:\n{report}");
    }
    Ok(DaemonMemory {
        first_rss_kib,
        rss_kib,
        hwm_kib,
        sets_processed,
        published,
    })
}

struct Idle {
    rss_kib: u64,
    hwm_kib: u64,
}

/// Memory of the idle benchmark binary under QEMU (the emulator's own baseline).
fn idle_memory(bench: &PathBuf, wait: Duration) -> Result<Idle> {
    let child = Proc::spawn(
        Command::new("qemu-aarch64")
            .arg(bench)
            .args(["--idle", &(wait.as_secs() + 5).to_string()]),
        "the idle binary under qemu-aarch64",
    )?;
    std::thread::sleep(wait);
    let (rss_kib, hwm_kib) = vm_kib(child.pid())?;
    Ok(Idle { rss_kib, hwm_kib })
}

/// Runs the benchmark binary (`cmd`) that prints the table, `--quick` if asked.
fn print_table(mut cmd: Command, quick: bool, timeout_s: u64, what: &str) -> Result<()> {
    if quick {
        cmd.arg("--quick");
    }
    util::run_ok(&mut cmd, what, Duration::from_secs(timeout_s), false)?;
    Ok(())
}
