//! irtrack's task runner: `cargo xtask <task>` (alias in .cargo/config.toml).
//!
//! Few dependencies (anyhow, clap, serde_json, toml and the light test harness
//! `irtrack-testkit`), none of them heavy, so it builds first and fast on a fresh machine.

mod bench;
mod bench_arch;
mod bench_cluster;
mod bench_latency;
mod bench_links;
mod ci;
mod cross;
mod demo;
mod demo_live;
mod demo_outputs;
mod demo_view;
mod disk;
mod fuzz;
mod image;
mod lint;
mod report;
mod setup;
mod soak;
mod test_pool;
mod util;
mod yocto;

use clap::{Parser, Subcommand};

pub use util::Ctx;

/// irtrack's task runner (`cargo xtask <task>`).
#[derive(Debug, Parser)]
#[command(name = "cargo xtask", bin_name = "cargo xtask")]
struct Cli {
    #[command(subcommand)]
    task: Task,
}

#[derive(Debug, Subcommand)]
enum Task {
    /// Set up, then run the whole system on simulated cameras (outputs in out/demo/).
    Demo(demo::Args),
    /// Every check CI runs (what .ci/run calls).
    Test(ci::Args),
    /// Install missing system packages (apt) and oelint-adv (pip).
    Setup,
    /// Static aarch64 release build of irtrackd; prints its path.
    Cross(cross::Args),
    /// The aarch64 SD image: build, QEMU system test, crate list.
    #[command(subcommand)]
    Image(image::ImageCmd),
    /// Benchmarks (docs/performance.md).
    Bench(bench::Args),
    /// Socket vs EGM vs RSI robot links side by side (docs/robot-streaming.md).
    BenchLinks(bench_links::Args),
    /// Fuzzing (docs/fuzzing.md).
    Fuzz(fuzz::Args),
    /// The Yocto layer under real BitBake (docs/image.md).
    #[command(subcommand)]
    Yocto(yocto::YoctoCmd),
    /// irtrackd + robot-sim service soak (default 10^6 sets at 500 fps).
    Soak(soak::Args),
}

fn main() {
    let cli = Cli::parse();
    let code = match real_main(cli.task) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("xtask: error: {e:#}");
            1
        }
    };
    std::process::exit(code);
}

fn real_main(task: Task) -> anyhow::Result<i32> {
    let ctx = Ctx::new()?;
    match task {
        Task::Test(args) => return ci::cli(&ctx, &args),
        Task::Demo(args) => demo::run(&ctx, &args)?,
        Task::Setup => setup::run(&ctx)?,
        Task::Cross(args) => cross::cli(&ctx, &args)?,
        Task::Soak(args) => soak::cli(&ctx, &args)?,
        Task::BenchLinks(args) => bench_links::cli(&ctx, &args)?,
        Task::Yocto(cmd) => yocto::cli(&ctx, cmd)?,
        Task::Image(cmd) => image::cli(&ctx, cmd)?,
        Task::Bench(args) => bench::cli(&ctx, &args)?,
        Task::Fuzz(args) => fuzz::cli(&ctx, &args)?,
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_is_consistent() {
        use clap::CommandFactory;
        Cli::command().debug_assert();
    }

    #[test]
    fn tasks_parse() {
        let p = |args: &[&str]| Cli::try_parse_from(std::iter::once("xtask").chain(args.iter().copied()));
        assert!(matches!(p(&["setup"]).unwrap().task, Task::Setup));
        assert!(matches!(
            p(&["image", "test", "--no-build"]).unwrap().task,
            Task::Image(image::ImageCmd::Test { no_build: true })
        ));
        assert!(matches!(
            p(&["yocto", "check-layer"]).unwrap().task,
            Task::Yocto(yocto::YoctoCmd::CheckLayer)
        ));
        assert!(p(&["nope"]).is_err());
        assert!(p(&["image", "test", "--bogus"]).is_err());
    }
}
