//! aarch64 cross builds: the environment that makes rustup's cargo use Debian's rustc (which
//! has an aarch64 std), the cross linker and QEMU user mode as the test runner; and
//! `cargo xtask cross`, the static release build of `irtrackd` that the image build uses
//! (`--cluster`: with Zenoh, for the QEMU user-mode cluster test).

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Result, bail};

use crate::util::{self, Ctx, RunOpts};

pub const TARGET: &str = "aarch64-unknown-linux-gnu";

/// Crates that cross-build. host-tools, tests and xtask stay on the host (OpenCV).
pub const CROSS_CRATES: &[&str] = &["irtrack-core", "irtrack-sim", "irtrack-robot", "irtrack-firmware"];

/// Where Debian's rustc-web keeps its aarch64 std.
const DEBIAN_AARCH64_STD: &str = "/usr/lib/rustlib/aarch64-unknown-linux-gnu";

/// Sets the cross environment on `cmd`. `target_subdir` keeps cross builds in their own target
/// directory: a different rustc (and RUSTFLAGS) would otherwise invalidate the host build.
pub fn apply_env(ctx: &Ctx, cmd: &mut Command, target_subdir: &str) -> Result<()> {
    let runner = if Path::new(DEBIAN_AARCH64_STD).is_dir() {
        // Debian rustc-web + libstd-rust-web-dev:arm64 (verified). `-L /` makes QEMU use the
        // multiarch glibc under /lib/aarch64-linux-gnu; `-L /usr/aarch64-linux-gnu` would mix
        // two glibc/libgcc sets and hang at the first thread spawn.
        cmd.env("RUSTC", "/usr/bin/rustc");
        if Path::new("/usr/bin/rustdoc").is_file() {
            // Cross doctests must be compiled by the rustdoc matching that rustc.
            cmd.env("RUSTDOC", "/usr/bin/rustdoc");
        }
        "qemu-aarch64 -L /"
    } else if rustup_has_aarch64() {
        // rustup-provided std (e.g. Ubuntu); runtime libs then come from the cross sysroot.
        // Not verified on this project's machines.
        "qemu-aarch64 -L /usr/aarch64-linux-gnu"
    } else {
        bail!(
            "no aarch64 standard library: install Debian's `rustc-web libstd-rust-web-dev:arm64` \
             (`cargo xtask setup`) or run `rustup target add {TARGET}`"
        );
    };
    cmd.env(
        "CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER",
        "aarch64-linux-gnu-gcc",
    );
    cmd.env("CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER", runner);
    // Tests that spawn a target binary (CARGO_BIN_EXE_*) must start it through the same
    // runner: there is no binfmt_misc registration on CI machines.
    cmd.env("IRTRACK_TEST_RUNNER", runner);
    // bindgen (v4l2-sys) must parse the aarch64 headers, not the host's.
    cmd.env("BINDGEN_EXTRA_CLANG_ARGS", "--sysroot=/usr/aarch64-linux-gnu");
    cmd.env("CARGO_TARGET_DIR", ctx.target_dir().join(target_subdir));
    Ok(())
}

fn rustup_has_aarch64() -> bool {
    Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output()
        .is_ok_and(|o| {
            String::from_utf8_lossy(&o.stdout)
                .lines()
                .any(|l| l.trim() == TARGET)
        })
}

/// Builds `irtrackd` for aarch64, release, statically linked; returns the binary's path.
pub fn build_irtrackd(ctx: &Ctx) -> Result<PathBuf> {
    build_irtrackd_with(ctx, None)
}

/// Builds the aarch64 `irtrackd` with the `cluster` feature (Zenoh) and copies it to
/// `irtrackd-cluster` beside the target directory, so the image's plain build, which shares
/// the directory (and so the dependencies), cannot replace it. Returns the copy's path.
pub fn build_irtrackd_cluster(ctx: &Ctx) -> Result<PathBuf> {
    let built = build_irtrackd_with(ctx, Some("cluster"))?;
    let copy = ctx.target_dir().join(STATIC_SUBDIR).join("irtrackd-cluster");
    std::fs::copy(&built, &copy)?;
    Ok(copy)
}

/// The target subdirectory of the static release builds (image, bench, cluster).
const STATIC_SUBDIR: &str = "aarch64-static";

/// RUSTFLAGS of the static release builds (one value, or builds sharing [`STATIC_SUBDIR`]
/// would rebuild each other's dependencies). getrandom 0.3/0.4 look `getrandom` up with
/// dlsym, which finds nothing in a static glibc binary, and then read /dev/urandom — refused
/// to a service user where the device is 0660 (the test image's mdev before its rule), so the
/// cluster irtrackd panicked opening Zenoh. This backend calls the getrandom(2) syscall
/// directly (Linux ≥ 3.17).
pub const STATIC_RUSTFLAGS: &str =
    "-C target-feature=+crt-static --cfg getrandom_backend=\"linux_getrandom\"";

fn build_irtrackd_with(ctx: &Ctx, features: Option<&str>) -> Result<PathBuf> {
    let subdir = STATIC_SUBDIR;
    let mut cmd = ctx.cargo();
    cmd.args([
        "build",
        "--release",
        "--target",
        TARGET,
        "-p",
        "irtrack-firmware",
        "--bin",
        "irtrackd",
    ]);
    if let Some(f) = features {
        cmd.args(["--features", f]);
    }
    apply_env(ctx, &mut cmd, subdir)?;
    // With --target, RUSTFLAGS applies to target artifacts only, not to build scripts.
    cmd.env("RUSTFLAGS", STATIC_RUSTFLAGS);
    let out = util::run(&mut cmd, RunOpts::default())?;
    if !out.success() {
        bail!("aarch64 release build of irtrackd {}", out.describe());
    }
    let bin = ctx
        .target_dir()
        .join(subdir)
        .join(TARGET)
        .join("release")
        .join("irtrackd");
    if !bin.is_file() {
        bail!("build reported success but {} does not exist", bin.display());
    }
    Ok(bin)
}

/// Compiles a single-file, std-only Rust program for aarch64 (static, stripped) into `out`:
/// the image's small helpers (image/tools/), which are no cargo packages.
pub fn build_tool(ctx: &Ctx, src: &Path, out: &Path) -> Result<()> {
    let rustc = if Path::new(DEBIAN_AARCH64_STD).is_dir() {
        "/usr/bin/rustc"
    } else {
        "rustc"
    };
    let mut cmd = Command::new(rustc);
    cmd.args(["--edition", "2024", "-O", "--target", TARGET])
        .args(["-C", "linker=aarch64-linux-gnu-gcc"])
        .args(["-C", "target-feature=+crt-static"])
        .args(["-C", "strip=symbols"])
        .arg("-o")
        .arg(out)
        .arg(src)
        .current_dir(&ctx.root);
    let res = util::run(&mut cmd, RunOpts::default())?;
    if !res.success() {
        bail!("compiling {} for aarch64 {}", src.display(), res.describe());
    }
    Ok(())
}

/// `cargo xtask cross [--cluster]`.
#[derive(Debug, Default, clap::Args)]
pub struct Args {
    /// Build with the `cluster` feature (camera board / solver over Zenoh); the binary is
    /// copied to `target/aarch64-static/irtrackd-cluster`.
    #[arg(long)]
    pub cluster: bool,
}

/// `cargo xtask cross`: prints the binary path as the last line (for scripts).
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let bin = if args.cluster {
        build_irtrackd_cluster(ctx)?
    } else {
        build_irtrackd(ctx)?
    };
    println!("{}", bin.display());
    Ok(())
}
