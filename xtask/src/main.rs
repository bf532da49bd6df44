//! irtrack's task runner: `cargo xtask <task>` (alias in .cargo/config.toml).
//!
//! Std plus anyhow only, and no dependency on other workspace crates, so it builds first
//! and fast on a fresh machine.

mod bench;
mod bench_links;
mod ci;
mod cross;
mod demo;
mod demo_live;
mod demo_view;
mod disk;
mod fuzz;
mod image;
mod lint;
mod report;
mod setup;
mod soak;
mod util;
mod yocto;

pub use util::Ctx;

const USAGE: &str = "\
usage: cargo xtask <task> [options]

tasks:
  demo   [--skip-setup] [--view]
                               set up, then run the whole system on simulated cameras;
                               --view: only irtrackd and its set-up page, until Ctrl-C
  test   [--skip-setup] [--only <phase>[,...]] [--list]
                               every check CI runs (what .ci/run calls)
  setup                        install missing system packages (apt) and oelint-adv (pip)
  cross                        static aarch64 release build of irtrackd; prints its path
  image  ...                   image build (when xtask/src/image.rs exists)
  bench  ...                   benchmarks (when xtask/src/bench.rs exists)
  bench-links [--quick] [--secs S] [--release]
                               socket vs EGM vs RSI robot links side by side (docs/robot-streaming.md)
  fuzz   ...                   fuzzing (when xtask/src/fuzz.rs exists)
  yocto  check|check-layer|shell
                               the Yocto layer under real BitBake (docs/image.md)
  soak   [--sets N] [--fps F] [--quick]
                               irtrackd + robot-sim service soak (default 10^6 sets, 500 fps)
";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let code = match real_main(&args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("xtask: error: {e:#}");
            1
        }
    };
    std::process::exit(code);
}

fn real_main(args: &[String]) -> anyhow::Result<i32> {
    let ctx = Ctx::new()?;
    let (task, rest) = match args.split_first() {
        Some((t, r)) => (t.as_str(), r),
        None => {
            print!("{USAGE}");
            return Ok(2);
        }
    };
    match task {
        "test" => {
            let opts = ci::parse_options(rest)?;
            return Ok(ci::run(&ctx, &opts));
        }
        "demo" => demo::run(&ctx, rest)?,
        "setup" => setup::run(&ctx)?,
        "cross" => cross::cli(&ctx)?,
        "soak" => soak::cli(&ctx, rest)?,
        "bench-links" => bench_links::cli(&ctx, rest)?,
        "yocto" => yocto::cli(&ctx, rest)?,
        "image" => image::cli(&ctx, rest)?,
        "bench" => bench::cli(&ctx, rest)?,
        "fuzz" => fuzz::cli(&ctx, rest)?,
        "help" | "-h" | "--help" => print!("{USAGE}"),
        other => {
            eprint!("unknown task `{other}`\n\n{USAGE}");
            return Ok(2);
        }
    }
    Ok(0)
}
