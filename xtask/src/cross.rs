//! Cross builds for the boards: aarch64 (64-bit boards, the test image) and armv7 (the
//! Pandaboard's 32-bit Cortex-A9). The environment that makes cargo use Debian's rustc, the
//! cross linker and QEMU user mode as the test runner; and `cargo xtask cross`, the static
//! release build of `irtrackd` (`--cluster`: with Zenoh; `--arch armv7`: for the Cortex-A9).
//!
//! The two architectures get their standard library differently. aarch64 uses the prebuilt one
//! of Debian's `libstd-rust-web-dev:arm64`. Debian's armhf std is an older release than the
//! compiler, so for armv7 cargo builds std from `rust-web-src` (the same release's library
//! source) with `-Z build-std`, once per target directory and profile, and keeps it there.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Result, bail};

use crate::util::{self, Ctx, RunOpts};

/// A board architecture.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Arch {
    /// 64-bit ARMv8 (the test image, Raspberry Pi 3/4-class boards).
    #[default]
    Aarch64,
    /// 32-bit ARMv7-A hard-float, tuned for the Cortex-A9 with NEON (Pandaboard).
    Armv7,
}

/// Crates that cross-build. host-tools, tests and xtask stay on the host (OpenCV).
const CROSS_CRATES: &[&str] = &["irtrack-core", "irtrack-sim", "irtrack-robot", "irtrack-firmware"];

/// armv7 also tests irtrack-cluster (its pairing logic; Zenoh stays off by default): the
/// 32-bit frame-set arithmetic is new ground there.
const ARMV7_CRATES: &[&str] = &[
    "irtrack-core",
    "irtrack-sim",
    "irtrack-robot",
    "irtrack-cluster",
    "irtrack-firmware",
];

/// Where Debian's rustc-web keeps its aarch64 std.
const DEBIAN_AARCH64_STD: &str = "/usr/lib/rustlib/aarch64-unknown-linux-gnu";

/// The standard library's source from `rust-web-src`, matching `/usr/bin/rustc`.
const DEBIAN_STD_SOURCE: &str = "/usr/lib/rustlib/src/rust/library/std";

/// What `-Z build-std` builds: std and the test harness (unwinding for tests, abort for
/// `panic = "abort"` users). One list everywhere, so every armv7 build of a profile shares one
/// std in its target directory.
const BUILD_STD: &str = "-Zbuild-std=std,panic_abort,panic_unwind,test";

/// The Cortex-A9 tuning of every armv7 build (tests included, so the tests run the code the
/// board runs). The target's baseline is ARMv7-A + VFPv3-D16 without NEON; the Pandaboard's
/// OMAP4 has NEON (and with it 32 double registers), so it is switched on: LLVM vectorises the
/// pixel loops (row sums, thresholding) with it. `target-cpu` selects the A9's scheduling model
/// and keeps out what the A9 lacks (hardware integer division, VFPv4 fused multiply-add).
const ARMV7_TUNING: &str = "-C target-cpu=cortex-a9 -C target-feature=+neon";

/// QEMU runs the armv7 binaries as a Cortex-A9 (an instruction the A9 lacks is an illegal
/// instruction there, as on the board). The cross sysroot has the armhf glibc (there is no
/// armhf multiarch glibc on the machine; std comes from source, so nothing mixes).
const ARMV7_RUNNER: &str = "qemu-arm -cpu cortex-a9 -L /usr/arm-linux-gnueabihf";

impl Arch {
    /// The Rust target triple.
    pub fn triple(self) -> &'static str {
        match self {
            Arch::Aarch64 => "aarch64-unknown-linux-gnu",
            Arch::Armv7 => "armv7-unknown-linux-gnueabihf",
        }
    }

    /// Short name: build directories under `target/`, messages.
    pub fn name(self) -> &'static str {
        match self {
            Arch::Aarch64 => "aarch64",
            Arch::Armv7 => "armv7",
        }
    }

    /// The crates whose tests run under emulation.
    pub fn test_crates(self) -> &'static [&'static str] {
        match self {
            Arch::Aarch64 => CROSS_CRATES,
            Arch::Armv7 => ARMV7_CRATES,
        }
    }

    /// The QEMU user-mode emulator.
    pub fn qemu(self) -> &'static str {
        match self {
            Arch::Aarch64 => "qemu-aarch64",
            Arch::Armv7 => "qemu-arm",
        }
    }

    /// Prefix of the GNU cross tools (`<prefix>gcc`, `<prefix>strip`, ...).
    pub fn tool_prefix(self) -> &'static str {
        match self {
            Arch::Aarch64 => "aarch64-linux-gnu-",
            Arch::Armv7 => "arm-linux-gnueabihf-",
        }
    }

    /// The cross sysroot Debian's cross libc package installs.
    fn sysroot(self) -> &'static str {
        match self {
            Arch::Aarch64 => "/usr/aarch64-linux-gnu",
            Arch::Armv7 => "/usr/arm-linux-gnueabihf",
        }
    }

    /// The target subdirectory of the debug test builds.
    pub fn test_subdir(self) -> &'static str {
        self.name()
    }

    /// The target subdirectory of the static release builds (image, bench, cluster).
    pub fn static_subdir(self) -> &'static str {
        match self {
            Arch::Aarch64 => "aarch64-static",
            Arch::Armv7 => "armv7-static",
        }
    }

    /// RUSTFLAGS of the test builds. aarch64's is static like the image's: CI's image phase
    /// ships the irtrackd of that build ([`test_build_irtrackd`]), so a CI run compiles the
    /// aarch64 graph once, not once for the tests and again for the image.
    pub fn rustflags(self) -> &'static str {
        match self {
            Arch::Aarch64 => STATIC_RUSTFLAGS,
            Arch::Armv7 => ARMV7_TUNING,
        }
    }

    /// RUSTFLAGS of the static release builds (one value per architecture, or builds sharing
    /// [`Arch::static_subdir`] would rebuild each other's dependencies).
    pub fn static_rustflags(self) -> String {
        match self {
            Arch::Aarch64 => STATIC_RUSTFLAGS.to_string(),
            Arch::Armv7 => format!("{ARMV7_TUNING} {STATIC_RUSTFLAGS}"),
        }
    }

    /// `CARGO_TARGET_<TRIPLE>_` for cargo's per-target environment variables.
    fn env_prefix(self) -> String {
        format!(
            "CARGO_TARGET_{}_",
            self.triple().to_ascii_uppercase().replace('-', "_")
        )
    }
}

/// A cargo command for `arch` with the cross environment set, building in `target/<subdir>`
/// (a different rustc and RUSTFLAGS would otherwise invalidate the host build). RUSTFLAGS is
/// the architecture's test-build value; static builds override it.
pub fn cargo(ctx: &Ctx, arch: Arch, subdir: &str) -> Result<Command> {
    let mut cmd = match arch {
        Arch::Aarch64 => ctx.cargo(),
        Arch::Armv7 => {
            // `-Z build-std` reads the library's manifests: the cargo of the same release as
            // the library source (Debian's cargo-web) is the one certain to understand them.
            // rustup's cargo stays in use for everything else.
            let cargo = if Path::new("/usr/bin/cargo").is_file() {
                "/usr/bin/cargo"
            } else {
                "cargo"
            };
            let mut c = Command::new(cargo);
            c.current_dir(&ctx.root);
            if std::env::var_os("CARGO_INCREMENTAL").is_none() {
                c.env("CARGO_INCREMENTAL", "0");
            }
            c.arg(BUILD_STD);
            c
        }
    };
    apply_env(ctx, arch, &mut cmd, subdir)?;
    Ok(cmd)
}

/// Sets the cross environment of `arch` on `cmd` (see [`cargo`]).
fn apply_env(ctx: &Ctx, arch: Arch, cmd: &mut Command, subdir: &str) -> Result<()> {
    let runner = match arch {
        Arch::Aarch64 => aarch64_std(cmd)?,
        Arch::Armv7 => {
            if !Path::new(DEBIAN_STD_SOURCE).is_dir() {
                bail!(
                    "no standard library source for armv7 ({DEBIAN_STD_SOURCE}): install Debian's \
                     `rust-web-src` (`cargo xtask setup`)"
                );
            }
            debian_rustc(cmd);
            // `-Z build-std` is unstable; this lets the stable compiler accept it. Nothing
            // else unstable is used.
            cmd.env("RUSTC_BOOTSTRAP", "1");
            ARMV7_RUNNER
        }
    };
    let prefix = arch.env_prefix();
    cmd.env(format!("{prefix}LINKER"), format!("{}gcc", arch.tool_prefix()));
    cmd.env(format!("{prefix}RUNNER"), runner);
    // Tests that spawn a target binary (CARGO_BIN_EXE_*) must start it through the same
    // runner: there is no binfmt_misc registration on CI machines.
    cmd.env("IRTRACK_TEST_RUNNER", runner);
    // bindgen (v4l2-sys) must parse the target's headers, not the host's.
    cmd.env(
        "BINDGEN_EXTRA_CLANG_ARGS",
        format!("--sysroot={}", arch.sysroot()),
    );
    cmd.env("CARGO_TARGET_DIR", ctx.target_dir().join(subdir));
    if !arch.rustflags().is_empty() {
        cmd.env("RUSTFLAGS", arch.rustflags());
    }
    Ok(())
}

/// Debian's rustc (and its rustdoc, for cross doctests) instead of rustup's.
fn debian_rustc(cmd: &mut Command) {
    cmd.env("RUSTC", "/usr/bin/rustc");
    if Path::new("/usr/bin/rustdoc").is_file() {
        cmd.env("RUSTDOC", "/usr/bin/rustdoc");
    }
}

/// Picks the aarch64 std (setting RUSTC when it is Debian's); returns the QEMU runner.
fn aarch64_std(cmd: &mut Command) -> Result<&'static str> {
    if Path::new(DEBIAN_AARCH64_STD).is_dir() {
        // Debian rustc-web + libstd-rust-web-dev:arm64 (verified). `-L /` makes QEMU use the
        // multiarch glibc under /lib/aarch64-linux-gnu; `-L /usr/aarch64-linux-gnu` would mix
        // two glibc/libgcc sets and hang at the first thread spawn.
        debian_rustc(cmd);
        Ok("qemu-aarch64 -L /")
    } else if rustup_has(Arch::Aarch64) {
        // rustup-provided std (e.g. Ubuntu); runtime libs then come from the cross sysroot.
        // Not verified on this project's machines.
        Ok("qemu-aarch64 -L /usr/aarch64-linux-gnu")
    } else {
        bail!(
            "no aarch64 standard library: install Debian's `rustc-web libstd-rust-web-dev:arm64` \
             (`cargo xtask setup`) or run `rustup target add {}`",
            Arch::Aarch64.triple()
        );
    }
}

fn rustup_has(arch: Arch) -> bool {
    Command::new("rustup")
        .args(["target", "list", "--installed"])
        .output()
        .is_ok_and(|o| {
            String::from_utf8_lossy(&o.stdout)
                .lines()
                .any(|l| l.trim() == arch.triple())
        })
}

/// The test build of `arch` (`cargo test` of [`Arch::test_crates`] in `target/<arch>`); the
/// caller adds `--no-run` or the test arguments. One function, so the image phase and the
/// test phase run the same command and the second finds everything built.
pub fn test_command(ctx: &Ctx, arch: Arch) -> Result<Command> {
    let mut cmd = cargo(ctx, arch, arch.test_subdir())?;
    cmd.args(["test", "--no-fail-fast", "--target", arch.triple()]);
    for c in arch.test_crates() {
        cmd.args(["-p", c]);
    }
    Ok(cmd)
}

/// The irtrackd that the test build of `arch` links for the firmware's integration tests
/// (test profile: opt-level 1, most dependencies too, debug assertions and overflow checks on;
/// static for aarch64, see [`Arch::rustflags`]). CI's image runs it, so the system test
/// exercises the same compiled code as the aarch64 unit tests, with its assertions armed;
/// `cargo xtask image build` keeps the release binary ([`build_irtrackd`]).
pub fn test_build_irtrackd(ctx: &Ctx, arch: Arch) -> Result<PathBuf> {
    let mut cmd = test_command(ctx, arch)?;
    cmd.arg("--no-run");
    let out = util::run(&mut cmd, RunOpts::default())?;
    if !out.success() {
        bail!("{} test build {}", arch.name(), out.describe());
    }
    let bin = ctx
        .target_dir()
        .join(arch.test_subdir())
        .join(arch.triple())
        .join("debug/irtrackd");
    if !bin.is_file() {
        bail!("the {} test build made no {}", arch.name(), bin.display());
    }
    Ok(bin)
}

/// Builds `irtrackd` for `arch`, release, statically linked; returns the binary's path.
pub fn build_irtrackd(ctx: &Ctx, arch: Arch) -> Result<PathBuf> {
    build_irtrackd_with(ctx, arch, None)
}

/// Builds `irtrackd` for `arch` with the `cluster` feature (Zenoh) and copies it to
/// `irtrackd-cluster` beside the target directory, so the plain build, which shares the
/// directory (and so the dependencies), cannot replace it. Returns the copy's path.
pub fn build_irtrackd_cluster(ctx: &Ctx, arch: Arch) -> Result<PathBuf> {
    let built = build_irtrackd_with(ctx, arch, Some("cluster"))?;
    let copy = ctx
        .target_dir()
        .join(arch.static_subdir())
        .join("irtrackd-cluster");
    std::fs::copy(&built, &copy)?;
    Ok(copy)
}

/// The static part of [`Arch::static_rustflags`]. getrandom 0.3/0.4 look `getrandom` up with
/// dlsym, which finds nothing in a static glibc binary, and then read /dev/urandom — refused
/// to a service user where the device is 0660 (the test image's mdev before its rule), so the
/// cluster irtrackd panicked opening Zenoh. This backend calls the getrandom(2) syscall
/// directly (Linux ≥ 3.17).
const STATIC_RUSTFLAGS: &str = "-C target-feature=+crt-static --cfg getrandom_backend=\"linux_getrandom\"";

/// A static release build of package `package` for `arch` in [`Arch::static_subdir`];
/// `extra` is appended (`--bin x`, `--features y`, ...). Returns the release directory.
pub fn build_static(ctx: &Ctx, arch: Arch, package: &str, extra: &[&str]) -> Result<PathBuf> {
    let subdir = arch.static_subdir();
    let mut cmd = cargo(ctx, arch, subdir)?;
    cmd.args(["build", "--release", "--target", arch.triple(), "-p", package]);
    cmd.args(extra);
    // With --target, RUSTFLAGS applies to target artifacts only, not to build scripts.
    cmd.env("RUSTFLAGS", arch.static_rustflags());
    let out = util::run(&mut cmd, RunOpts::default())?;
    if !out.success() {
        bail!("{} release build of {package} {}", arch.name(), out.describe());
    }
    Ok(ctx.target_dir().join(subdir).join(arch.triple()).join("release"))
}

fn build_irtrackd_with(ctx: &Ctx, arch: Arch, features: Option<&str>) -> Result<PathBuf> {
    let mut extra = vec!["--bin", "irtrackd"];
    if let Some(f) = features {
        extra.extend(["--features", f]);
    }
    let bin = build_static(ctx, arch, "irtrack-firmware", &extra)?.join("irtrackd");
    if !bin.is_file() {
        bail!("build reported success but {} does not exist", bin.display());
    }
    Ok(bin)
}

/// Compiles a single-file, std-only Rust program for aarch64 (static, stripped) into `out`:
/// the image's small helpers (image/tools/), which are no cargo packages.
pub fn build_tool(ctx: &Ctx, src: &Path, out: &Path) -> Result<()> {
    let arch = Arch::Aarch64;
    let rustc = if Path::new(DEBIAN_AARCH64_STD).is_dir() {
        "/usr/bin/rustc"
    } else {
        "rustc"
    };
    let mut cmd = Command::new(rustc);
    cmd.args(["--edition", "2024", "-O", "--target", arch.triple()])
        .args(["-C", &format!("linker={}gcc", arch.tool_prefix())])
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

/// `cargo xtask cross [--arch armv7] [--cluster]`.
#[derive(Debug, Default, clap::Args)]
pub struct Args {
    /// The board architecture.
    #[arg(long, value_enum, default_value_t = Arch::Aarch64)]
    pub arch: Arch,
    /// Build with the `cluster` feature (camera board / solver over Zenoh); the binary is
    /// copied to `target/<arch>-static/irtrackd-cluster`.
    #[arg(long)]
    pub cluster: bool,
}

/// `cargo xtask cross`: prints the binary path as the last line (for scripts).
pub fn cli(ctx: &Ctx, args: &Args) -> Result<()> {
    let bin = if args.cluster {
        build_irtrackd_cluster(ctx, args.arch)?
    } else {
        build_irtrackd(ctx, args.arch)?
    };
    println!("{}", bin.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arch_names_and_environment() {
        assert_eq!(
            Arch::Armv7.env_prefix(),
            "CARGO_TARGET_ARMV7_UNKNOWN_LINUX_GNUEABIHF_"
        );
        assert_eq!(
            Arch::Aarch64.env_prefix(),
            "CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_"
        );
        // The aarch64 static flags are unchanged; armv7's add the Cortex-A9 tuning to them.
        assert_eq!(Arch::Aarch64.static_rustflags(), STATIC_RUSTFLAGS);
        let armv7 = Arch::Armv7.static_rustflags();
        assert!(armv7.starts_with(ARMV7_TUNING) && armv7.ends_with(STATIC_RUSTFLAGS));
        assert!(ARMV7_RUNNER.starts_with(Arch::Armv7.qemu()));
        assert!(Arch::Armv7.test_crates().contains(&"irtrack-cluster"));
        assert_ne!(Arch::Armv7.static_subdir(), Arch::Aarch64.static_subdir());
    }
}
