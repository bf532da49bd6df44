//! The armv7 image (`cargo xtask image armv7 build|test|run|update-test|bundle`, CI opt-in
//! phases `image-armv7` and `image-update-armv7`): the image of docs/image.md for the
//! Pandaboard's 32-bit ARMv7-A, booted in `qemu-system-arm -M virt -cpu cortex-a15` and checked
//! by the same system test and the same A/B update test as the aarch64 image.
//!
//! What differs from the aarch64 image:
//! - Debian armhf packages: the `armmp` kernel (Debian's ARMv7 multiplatform flavour, the one
//!   that also boots a real Pandaboard; no LPAE, which the A9 lacks) and `busybox-static`.
//!   The machine has no armhf dpkg architecture (nothing armhf is installed), so the package
//!   lists are fetched into a private apt state under `target/image-armv7/apt/` with the
//!   machine's own apt sources: the system's apt configuration is left alone and no root is
//!   needed for that step.
//! - The armv7 irtrackd (`cargo xtask cross --arch armv7`: Cortex-A9 tuning with NEON).
//! - The same A/B layout as the aarch64 image (docs/updates.md): boot.scr and the boot counters
//!   on the boot partition, slots A and B, the data partition, RAUC 1.8 with dbus-daemon and
//!   libubootenv from Debian's armhf packages. U-Boot's `qemu_arm` build runs boot.scr with the
//!   board part [`BOOT_BOARD`] (the slot's `/boot/zImage`, started with `bootz`), and bundles
//!   name the board type [`COMPATIBLE`], so an aarch64 bundle is refused here and an armv7
//!   bundle on the aarch64 image.
//! - The QEMU machine: `virt` with a Cortex-A15 (see [`QEMU_CPU`]).

use std::fs;
use std::path::Path;
use std::process::Command;

use anyhow::{Context, Result, bail};

use super::{AB_MODULES, Debs, Variant, find_deb, run_quiet, system};
use crate::cross::Arch;
use crate::report::Counts;
use crate::util::Ctx;

/// QEMU's CPU for the armv7 image. The `virt` machine is the only 32-bit ARM machine QEMU has
/// with virtio-mmio disk and network, a PL061 GPIO controller and a device tree U-Boot
/// passes on, and it needs a CPU with the ARM generic timer: the Cortex-A7 or A15, not the
/// A9 (QEMU's A9 machines, vexpress-a9 and realview, have neither the PL061 nor the same
/// device set). The A15 is ARMv7-A like the A9 plus what irtrackd's Cortex-A9 build does not
/// use (integer division, VFPv4, LPAE), so the binary that runs here is the board's; the
/// instruction set the A9 lacks is kept out at compile time (`-C target-cpu=cortex-a9`) and
/// is checked by the user-mode tests under `qemu-arm -cpu cortex-a9`.
pub const QEMU_CPU: &str = "cortex-a15";

/// U-Boot for QEMU's 32-bit virt machine (Debian `u-boot-qemu`).
pub const UBOOT_QEMU_ARM: &str = "/usr/lib/u-boot/qemu_arm/u-boot.bin";

/// Debian's ARMv7 multiplatform kernel (meta package; it depends on the versioned one).
const KERNEL_META: &str = "linux-image-armmp";

/// The armv7 image's board type (RAUC's `compatible`): QEMU's 32-bit virt machine. A Yocto
/// Pandaboard image names its own (`irtrack-pandaboard`).
pub const COMPATIBLE: &str = "irtrack-qemu-armv7";

/// The board's part of boot.cmd for this image (the slot's zImage through `bootz`).
pub const BOOT_BOARD: &str = "image/update/board/qemu-armv7.cmd";

/// The armv7 image: the standalone board on two vivid cameras, A/B slots with RAUC.
pub const ARMV7: Variant = Variant {
    dir: "image-armv7",
    arch: Arch::Armv7,
    irtrackd: |ctx| crate::cross::build_irtrackd(ctx, Arch::Armv7),
    irtrackd_profile: "release",
    extra_modules: AB_MODULES,
    overlay: None,
    tools: &[],
    signing_keys: true,
    ab_updates: true,
    compatible: COMPATIBLE,
    boot_board: Some(BOOT_BOARD),
};

/// `cargo xtask image armv7 <command>`.
#[derive(Debug, clap::Subcommand)]
pub enum Armv7Cmd {
    /// Build target/image-armv7/irtrack-sd.img.
    Build,
    /// Build (or reuse the last build), boot in qemu-system-arm, run the system test.
    Test {
        /// Reuse the last build.
        #[arg(long)]
        no_build: bool,
    },
    /// Build, then boot it interactively (console on this terminal; Ctrl-A X quits).
    Run,
    /// Build (or reuse the last build), then the A/B update test in qemu-system-arm (the
    /// aarch64 image's checks, docs/updates.md).
    UpdateTest {
        /// Reuse the last build.
        #[arg(long)]
        no_build: bool,
    },
    /// Build the image as VERSION and make a signed RAUC bundle of its root file system for
    /// the armv7 board (compatible irtrack-qemu-armv7).
    Bundle {
        /// The bundle's version (dotted numbers); boards refuse bundles older than what they run.
        #[arg(long)]
        version: String,
        /// Where to write it (default target/image-armv7/irtrack-VERSION.raucb).
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
}

pub fn cli(ctx: &Ctx, cmd: Armv7Cmd) -> Result<()> {
    let build_or_reuse = |no_build: bool| {
        if no_build {
            super::existing(ctx, &ARMV7)
        } else {
            super::build_variant(ctx, &ARMV7)
        }
    };
    match cmd {
        Armv7Cmd::Build => {
            let image = super::build_variant(ctx, &ARMV7)?;
            println!("{}", image.summary());
            println!("{}", image.sd_img.display());
            Ok(())
        }
        Armv7Cmd::Test { no_build } => {
            let image = build_or_reuse(no_build)?;
            println!("{}", image.summary());
            let report = system::run(ctx, &image)?;
            println!("{report}");
            if report.failed() > 0 {
                bail!("armv7 system test: {} check(s) failed", report.failed());
            }
            Ok(())
        }
        Armv7Cmd::Run => {
            let image = super::build_variant(ctx, &ARMV7)?;
            println!("{}", image.summary());
            super::qemu::interactive(ctx, &image)
        }
        Armv7Cmd::UpdateTest { no_build } => super::update_test_cli(ctx, &ARMV7, no_build),
        Armv7Cmd::Bundle { version, out } => super::bundle_cli(ctx, &ARMV7, &version, out),
    }
}

/// CI opt-in phase `image-update-armv7`: the A/B update test on the armv7 image.
pub fn update_phase(ctx: &Ctx) -> Result<Counts> {
    super::update_phase(ctx, &ARMV7)
}

/// CI opt-in phase `image-armv7`: builds the armv7 image and runs the system test on it.
pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    let image = super::build_variant(ctx, &ARMV7).context("building the armv7 image")?;
    println!("{}", image.summary());
    let report = system::run(ctx, &image)?;
    println!("{report}");
    let failed: Vec<String> = report
        .checks
        .iter()
        .filter(|c| !c.ok)
        .map(|c| format!("{}: {}", c.name, super::short(&c.detail)))
        .collect();
    if !failed.is_empty() {
        bail!(
            "{} armv7 image check(s) failed: {}",
            failed.len(),
            failed.join("; ")
        );
    }
    Ok(Counts {
        passed: report.passed(),
        ..Counts::default()
    })
}

/// `apt-get` with a private armhf state under `apt_dir`: the machine's sources, armhf as the
/// only architecture, lists and cache of its own, and an empty dpkg status (nothing is
/// installed from it, only downloaded).
fn apt(apt_dir: &Path) -> Command {
    let mut cmd = Command::new("apt-get");
    cmd.args([
        "-q",
        "-o",
        "APT::Architecture=armhf",
        "-o",
        "APT::Architectures::=armhf",
    ])
    .arg("-o")
    .arg(format!("Dir::State::Lists={}", apt_dir.join("lists").display()))
    .arg("-o")
    .arg(format!("Dir::Cache={}", apt_dir.join("cache").display()))
    .args(["-o", "Dir::State::status=/dev/null"]);
    cmd
}

/// Fetches the armhf package lists once into the private state (`work/apt/`).
fn apt_update(apt_dir: &Path) -> Result<()> {
    let lists = apt_dir.join("lists");
    let have_lists = fs::read_dir(&lists)
        .map(|d| {
            d.flatten()
                .any(|e| e.file_name().to_string_lossy().contains("binary-armhf"))
        })
        .unwrap_or(false);
    if have_lists {
        return Ok(());
    }
    fs::create_dir_all(lists.join("partial"))?;
    fs::create_dir_all(apt_dir.join("cache/archives/partial"))?;
    let out = apt(apt_dir)
        .arg("update")
        .output()
        .context("running apt-get update for armhf")?;
    // One failed index (a mirror mid-sync, e.g. the security suite) is not fatal: the kernel and
    // busybox come from the main suite. A missing package is reported by the download below.
    if !out.status.success() {
        eprintln!(
            "image: apt-get update (armhf) reported errors, continuing with what it fetched:\n{}",
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    Ok(())
}

fn apt_download(apt_dir: &Path, dl: &Path, packages: &[&str]) -> Result<()> {
    run_quiet(apt(apt_dir).arg("download").args(packages).current_dir(dl))
        .with_context(|| format!("downloading {} (armhf)", packages.join(" ")))?;
    Ok(())
}

/// Downloads armhf `packages` into `work/dl/` through the private apt state (the update tools
/// of the A/B image, xtask/src/image/update.rs).
pub(super) fn download(work: &Path, packages: &[&str]) -> Result<()> {
    let dl = work.join("dl");
    let apt_dir = work.join("apt");
    fs::create_dir_all(&dl)?;
    apt_update(&apt_dir)?;
    apt_download(&apt_dir, &dl, packages)
}

/// The armhf kernel (through [`KERNEL_META`]) and busybox-static in `work/dl/`, reusing what is
/// there.
pub(super) fn fetch_debs(work: &Path) -> Result<Debs> {
    let dl = work.join("dl");
    let apt_dir = work.join("apt");
    fs::create_dir_all(&dl)?;
    let have = |name: &str| find_deb(&dl, name).is_some();
    if !have(KERNEL_META) || !have("busybox-static") {
        apt_update(&apt_dir)?;
    }
    if !have(KERNEL_META) {
        apt_download(&apt_dir, &dl, &[KERNEL_META])?;
    }
    let meta = find_deb(&dl, KERNEL_META).context("kernel meta package missing after download")?;
    let depends = run_quiet(Command::new("dpkg-deb").args(["-f"]).arg(&meta).arg("Depends"))?;
    let kernel_pkg = versioned_kernel(&depends).with_context(|| {
        format!(
            "no linux-image-*-armmp in Depends of {}: {depends}",
            meta.display()
        )
    })?;
    if !have(&kernel_pkg) {
        apt_update(&apt_dir)?;
        apt_download(&apt_dir, &dl, &[&kernel_pkg])?;
    }
    if !have("busybox-static") {
        apt_download(&apt_dir, &dl, &["busybox-static"])?;
    }
    Ok(Debs {
        kernel: find_deb(&dl, &kernel_pkg).context("kernel .deb missing after download")?,
        busybox: find_deb(&dl, "busybox-static").context("busybox-static .deb missing after download")?,
    })
}

/// The versioned kernel package in the meta package's `Depends` (`linux-image-6.1.0-50-armmp`),
/// not the LPAE flavour.
fn versioned_kernel(depends: &str) -> Option<String> {
    depends
        .split([',', '|'])
        .filter_map(|d| d.split_whitespace().next())
        .find(|d| d.starts_with("linux-image-") && d.ends_with("-armmp"))
        .map(str::to_owned)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_plain_armmp_kernel_is_picked() {
        assert_eq!(
            versioned_kernel("linux-image-6.1.0-50-armmp (= 6.1.176-1)").as_deref(),
            Some("linux-image-6.1.0-50-armmp")
        );
        // The LPAE flavour does not boot on the A9.
        assert_eq!(
            versioned_kernel("linux-image-6.1.0-50-armmp-lpae (= 6.1.176-1)"),
            None
        );
        assert_eq!(versioned_kernel("busybox"), None);
    }

    /// A minimal little-endian ELF32 (an armhf kernel module's class) with a section-name
    /// table and a `.modinfo` section.
    fn fake_module32(modinfo: &[u8]) -> Vec<u8> {
        let shstr = b"\0.shstrtab\0.modinfo\0";
        let mut elf = vec![0u8; 52];
        elf[..6].copy_from_slice(b"\x7fELF\x01\x01");
        let shstr_off = elf.len();
        elf.extend_from_slice(shstr);
        let modinfo_off = elf.len();
        elf.extend_from_slice(modinfo);
        let shoff = elf.len();
        let mut header = |name: u32, off: usize, size: usize| {
            let mut h = vec![0u8; 40];
            h[..4].copy_from_slice(&name.to_le_bytes());
            h[0x10..0x14].copy_from_slice(&(off as u32).to_le_bytes());
            h[0x14..0x18].copy_from_slice(&(size as u32).to_le_bytes());
            elf.extend_from_slice(&h);
        };
        header(0, 0, 0);
        header(1, shstr_off, shstr.len());
        header(11, modinfo_off, modinfo.len());
        elf[0x20..0x24].copy_from_slice(&(shoff as u32).to_le_bytes());
        elf[0x2e..0x30].copy_from_slice(&40u16.to_le_bytes());
        elf[0x30..0x32].copy_from_slice(&3u16.to_le_bytes());
        elf[0x32..0x34].copy_from_slice(&1u16.to_le_bytes());
        elf
    }

    #[test]
    fn elf32_modinfo_depends_are_read() {
        let elf = fake_module32(b"license=GPL\0depends=videobuf2-vmalloc,v4l2-dv-timings\0");
        assert_eq!(
            super::super::modinfo_depends(&elf).unwrap(),
            vec!["videobuf2_vmalloc", "v4l2_dv_timings"]
        );
        let mut truncated = fake_module32(b"depends=a\0");
        truncated.truncate(80);
        assert!(super::super::modinfo_depends(&truncated).is_err());
        // Big-endian is refused, not misread.
        let mut big = fake_module32(b"depends=a\0");
        big[5] = 2;
        assert!(super::super::modinfo_depends(&big).is_err());
    }

    #[test]
    fn the_variant_is_armv7_with_ab_for_its_own_board() {
        assert_eq!(ARMV7.arch, Arch::Armv7);
        assert!(ARMV7.ab_updates && ARMV7.tools.is_empty());
        assert_ne!(ARMV7.dir, super::super::STANDARD.dir);
        // Bundles for one board are refused by the other.
        assert_ne!(ARMV7.compatible, super::super::STANDARD.compatible);
        assert_eq!(ARMV7.extra_modules, super::super::STANDARD.extra_modules);
    }

    #[test]
    fn the_board_part_sets_every_board_variable_and_boots_a_zimage() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let board = fs::read_to_string(root.join(BOOT_BOARD)).unwrap();
        let generic = fs::read_to_string(root.join("image/update/boot.cmd")).unwrap();
        // Every variable boot.cmd lets a board set is set here, so none of its arm64 defaults
        // (booti of /boot/Image) applies.
        for var in [
            "irtrack_iface",
            "irtrack_devnum",
            "irtrack_root",
            "irtrack_console",
            "irtrack_boot",
        ] {
            assert!(
                generic.contains(&format!("test -n \"${{{var}}}\" || setenv {var} ")),
                "boot.cmd no longer defaults {var}"
            );
            assert!(
                board.lines().any(|l| l.starts_with(&format!("setenv {var} "))),
                "{BOOT_BOARD} does not set {var}"
            );
        }
        let boot = board
            .lines()
            .find(|l| l.starts_with("setenv irtrack_boot "))
            .unwrap();
        assert!(boot.contains("/boot/zImage") && boot.contains("bootz ") && !boot.contains("booti"));
        assert!(boot.contains(&format!(
            "/boot/{}",
            super::super::update::kernel_file(Arch::Armv7)
        )));
    }
}
