//! The cluster section of `cargo xtask bench --cluster` and `bench-links`: camera boards and a
//! solver over Zenoh beside a standalone board (`firmware/examples/cluster_bench.rs`). Its own
//! module so that both benchmark commands call it without importing each other.

use std::time::Duration;

use anyhow::Result;

use crate::util::{self, Ctx};

/// Camera boards and a solver beside the standalone board: `irtrack-firmware`'s
/// `cluster_bench` example (its table is printed as it runs) with `args`; `release` for the
/// figures in docs/performance.md (`cargo xtask bench-links` without `--release` runs it in a
/// test build).
pub fn run(ctx: &Ctx, release: bool, args: &[String]) -> Result<()> {
    println!();
    // The example's process rows run this irtrackd (found beside the example's directory).
    let mut build = ctx.cargo();
    build.arg("build");
    if release {
        build.arg("--release");
    }
    build.args([
        "-p",
        "irtrack-firmware",
        "--features",
        "cluster",
        "--bin",
        "irtrackd",
    ]);
    util::run_ok(
        &mut build,
        "irtrackd for the cluster benchmark",
        Duration::from_secs(3600),
        false,
    )?;
    let mut cmd = ctx.cargo();
    cmd.arg("run");
    if release {
        cmd.arg("--release");
    }
    cmd.args([
        "-p",
        "irtrack-firmware",
        "--features",
        "cluster",
        "--example",
        "cluster_bench",
        "--",
    ]);
    cmd.args(args);
    util::run_ok(&mut cmd, "cluster benchmark", Duration::from_secs(3600), false)?;
    Ok(())
}
