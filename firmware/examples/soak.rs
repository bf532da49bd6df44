//! Soak + loop latency: the real processing loop with the simulated source.
//!
//! `cargo run --release -p irtrack-firmware --example soak -- --frames 100000 --fps 120`
//! (`--unpaced`: the source delivers as fast as the loop takes sets; `--fifo-priority N`
//! and `--lock-memory`: the real-time settings irtrackd applies from `[realtime]`).

use anyhow::{Context, bail};
use clap::Parser;
use irtrack_firmware::config::RealtimeConfig;
use irtrack_firmware::soak::{self, SoakConfig};

#[derive(Parser, Debug)]
#[command(about = "Soak the irtrackd processing loop with the simulated source")]
struct Args {
    /// Frame sets to process.
    #[arg(long, default_value_t = 100_000)]
    frames: u64,
    /// Simulated frame rate (also the deadline).
    #[arg(long, default_value_t = 120.0)]
    fps: f64,
    /// Deliver sets as fast as the loop takes them.
    #[arg(long)]
    unpaced: bool,
    /// Run the loop thread SCHED_FIFO at this priority (as irtrackd's `[realtime]` does on
    /// the board); needs CAP_SYS_NICE. Without it the run shows a shared machine's
    /// scheduling delays.
    #[arg(long)]
    fifo_priority: Option<i32>,
    /// mlockall, as `[realtime] lock_memory` (needs CAP_IPC_LOCK).
    #[arg(long)]
    lock_memory: bool,
}

fn mib(b: u64) -> f64 {
    b as f64 / (1024.0 * 1024.0)
}

/// 1/5/15-minute load averages (the machine may be shared; latency depends on it).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|t| t.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "n/a".into())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let cfg = SoakConfig {
        frames: args.frames,
        fps: args.fps,
        paced: !args.unpaced,
    };
    println!(
        "soak: {} frame sets, {} fps, {}",
        cfg.frames,
        cfg.fps,
        if cfg.paced { "paced" } else { "unpaced" }
    );
    if args.fifo_priority.is_some() || args.lock_memory {
        let rt = RealtimeConfig {
            fifo_priority: args.fifo_priority,
            lock_memory: args.lock_memory,
            ..RealtimeConfig::default()
        };
        for line in irtrack_firmware::rt::apply(&rt) {
            println!("realtime: {line}");
        }
    }
    let r = soak::run(cfg, |done, rss| {
        println!(
            "  {done:>9} sets, RSS {:.2} MiB, load {}",
            mib(rss),
            load_average()
        );
    })
    .context("soak run")?;
    let [p50, p99, p999, max] = r.latency_us;
    println!("frame-set-ready -> position-published latency (us):");
    println!("  p50 {p50:.1}  p99 {p99:.1}  p99.9 {p999:.1}  max {max:.1}");
    println!(
        "deadline misses: engine (processing > period) {}, ready->published > period {}",
        r.engine_deadline_misses, r.latency_over_period
    );
    println!(
        "RSS MiB: start {:.2}  middle {:.2}  end {:.2}",
        mib(r.rss_bytes[0]),
        mib(r.rss_bytes[1]),
        mib(r.rss_bytes[2])
    );
    println!(
        "counters: published {} (tracked {}, lost {}, gated {}), source delivered {}, dropped {}, engine processed {} / published {}",
        r.sets_published,
        r.tracked,
        r.lost,
        r.gated,
        r.sets_delivered,
        r.sets_dropped,
        r.engine_sets_processed,
        r.engine_published
    );
    println!(
        "wall time {:.1} s ({:.0} sets/s)",
        r.wall_s,
        r.sets_published as f64 / r.wall_s
    );
    let errs = r.consistency_errors();
    if !errs.is_empty() {
        bail!("counter inconsistencies: {}", errs.join("; "));
    }
    println!("counters consistent; load average at end {}", load_average());
    Ok(())
}
