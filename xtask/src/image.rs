//! `cargo xtask image ...`: the aarch64 SD-card image that CI boots in QEMU, its system test,
//! and the Yocto layer's crate list.
//!
//! The image is assembled from Debian's arm64 packages (kernel, busybox-static) and the
//! statically cross-built `irtrackd`, without loop mounts or root-only tools: a vfat boot
//! partition (kernel, initramfs, extlinux.conf for U-Boot) written with mtools, an ext4 root
//! partition written by `mke2fs -d`, and an MBR from `sfdisk`. See docs/image.md.

use std::collections::{BTreeSet, HashMap};
use std::fs;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::cross::Arch;
use crate::report::Counts;
use crate::util::{self, Ctx};

pub mod armv7;
mod bootenv;
mod checks;
mod crates;
mod qemu;
mod system;
mod update;
mod update_test;

/// `cargo xtask image <command>`.
#[derive(Debug, clap::Subcommand)]
pub enum ImageCmd {
    /// Build target/image/irtrack-sd.img (kernel, initramfs, busybox, irtrackd).
    Build,
    /// Build (or reuse the last build), boot it in QEMU, run the system test.
    #[command(alias = "system-test")]
    Test {
        /// Reuse the last build.
        #[arg(long)]
        no_build: bool,
    },
    /// Build, then boot it interactively (console on this terminal; Ctrl-A X quits).
    Run,
    /// Build the image as VERSION and make a signed RAUC update bundle of its root file system
    /// (docs/updates.md).
    Bundle {
        /// The bundle's version (dotted numbers); boards refuse bundles older than what they run.
        #[arg(long)]
        version: String,
        /// Where to write it (default target/image/irtrack-VERSION.raucb).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Create (once) the update CA and signing certificate and print their paths.
    UpdateKeys,
    /// Build (or reuse the last build), then the A/B update test in QEMU: install, reboot,
    /// rollback, refused bundles, power cut (docs/updates.md).
    UpdateTest {
        /// Reuse the last build.
        #[arg(long)]
        no_build: bool,
    },
    /// The armv7 (Pandaboard, 32-bit) image: build, test or run it in qemu-system-arm
    /// (xtask/src/image/armv7.rs).
    Armv7 {
        #[command(subcommand)]
        cmd: armv7::Armv7Cmd,
    },
    /// Write (or check) yocto-layer's irtrackd-crates.inc from Cargo.lock.
    Crates {
        /// Only check that the file is up to date.
        #[arg(long)]
        check: bool,
    },
}

/// Modules the initramfs loads to reach the root filesystem on a virtio disk.
/// `crc32c_generic` is ext4's soft dependency (`softdep=pre: crypto-crc32c`, an alias that
/// `.modinfo` dependencies do not resolve): metadata checksums need it at mount time.
const INITRD_MODULES: &[&str] = &["virtio_mmio", "virtio_blk", "crc32c_generic", "ext4"];
/// Modules the root filesystem loads at start: network and the vivid test cameras. vivid makes
/// two instances with only a video capture node each (/dev/video0, /dev/video1).
const ROOT_MODULES: &[(&str, &str)] = &[("virtio_net", ""), ("vivid", "n_devs=2 node_types=0x1,0x1")];

/// What one kind of image carries beyond the common parts (kernel, initramfs, busybox,
/// image/rootfs).
pub struct Variant {
    /// Its build directory under target/.
    pub dir: &'static str,
    /// The board architecture: Debian packages, cross tools and the QEMU machine.
    pub arch: Arch,
    /// Builds the irtrackd it ships.
    pub irtrackd: fn(&Ctx) -> Result<PathBuf>,
    /// How that irtrackd is built, for the build's log line.
    pub irtrackd_profile: &'static str,
    /// Modules loaded at start after [`ROOT_MODULES`].
    pub extra_modules: &'static [(&'static str, &'static str)],
    /// A directory of the repository copied over image/rootfs (replacing files there).
    pub overlay: Option<&'static str>,
    /// Single-file Rust programs (source in the repository, path in the image) compiled for
    /// aarch64 by [`crate::cross::build_tool`].
    pub tools: &'static [(&'static str, &'static str)],
    /// Make (once) and install the build's parameter signing key.
    pub signing_keys: bool,
    /// A/B layout with RAUC (docs/updates.md): boot.scr and boot counters on the boot
    /// partition, two root slots carrying their own kernel, a data partition. Otherwise one
    /// root partition booted through extlinux.
    pub ab_updates: bool,
    /// The board type of the A/B image: RAUC's `compatible` in `system.conf` and in every
    /// bundle made for it, so that a bundle for another board is refused.
    pub compatible: &'static str,
    /// The board's part of the boot script (a file of the repository put before
    /// image/update/boot.cmd: disk, console, how to load and start the slot's kernel); None
    /// keeps boot.cmd's defaults, QEMU's arm64 virt machine.
    pub boot_board: Option<&'static str>,
}

/// Modules of an A/B image: it mounts the boot (vfat) and data partitions and loop-mounts
/// bundles (squashfs).
pub const AB_MODULES: &[(&str, &str)] = &[
    ("vfat", ""),
    ("nls_cp437", ""),
    ("nls_ascii", ""),
    ("loop", ""),
    ("squashfs", ""),
];

/// The CI image: a standalone board on two vivid V4L2 cameras.
pub const STANDARD: Variant = Variant {
    dir: "image",
    arch: Arch::Aarch64,
    irtrackd: |ctx| crate::cross::build_irtrackd(ctx, crate::cross::Arch::Aarch64),
    irtrackd_profile: "release",
    extra_modules: AB_MODULES,
    overlay: None,
    tools: &[],
    signing_keys: true,
    ab_updates: true,
    compatible: update::COMPATIBLE,
    boot_board: None,
};

/// The images with the A/B update layout: each refuses the others' bundles.
pub const AB_VARIANTS: &[&Variant] = &[&STANDARD, &armv7::ARMV7];

/// The cluster test image (`cargo xtask test --only cluster-qemu-system`): irtrackd built with
/// `cluster` (Zenoh) as a camera board on simulated cameras. QEMU's fw_cfg hands it the test's
/// board config and the host's SNTP port (image/cluster/etc/irtrack/rc.local).
pub const CLUSTER: Variant = Variant {
    dir: "image-cluster",
    arch: Arch::Aarch64,
    irtrackd: |ctx| crate::cross::build_irtrackd_cluster(ctx, crate::cross::Arch::Aarch64),
    irtrackd_profile: "release",
    extra_modules: &[("qemu_fw_cfg", "")],
    overlay: Some("image/cluster"),
    // Sets the guest's clock from the test's SNTP server (the image has no NTP client).
    tools: &[("image/tools/sntp-step.rs", "usr/sbin/sntp-step")],
    signing_keys: false,
    ab_updates: false,
    compatible: "",
    boot_board: None,
};
const UBOOT_QEMU: &str = "/usr/lib/u-boot/qemu_arm64/u-boot.bin";

pub fn cli(ctx: &Ctx, cmd: ImageCmd) -> Result<()> {
    match cmd {
        ImageCmd::Build => {
            let image = build(ctx)?;
            println!("{}", image.summary());
            println!("{}", image.sd_img.display());
            Ok(())
        }
        ImageCmd::Test { no_build } => {
            let image = if no_build {
                existing(ctx, &STANDARD)?
            } else {
                build(ctx)?
            };
            println!("{}", image.summary());
            let report = system::run(ctx, &image)?;
            println!("{report}");
            if report.failed() > 0 {
                bail!("system test: {} check(s) failed", report.failed());
            }
            Ok(())
        }
        ImageCmd::Run => {
            let image = build(ctx)?;
            qemu::interactive(ctx, &image)
        }
        ImageCmd::Crates { check } => crates::cli(ctx, check),
        ImageCmd::Armv7 { cmd } => armv7::cli(ctx, cmd),
        ImageCmd::Bundle { version, out } => bundle_cli(ctx, &STANDARD, &version, out),
        ImageCmd::UpdateKeys => {
            let keys = update::update_keys(&work_dir(ctx))?;
            println!("CA certificate (the boards' keyring): {}", keys.ca_cert.display());
            println!("signing certificate: {}", keys.signer_cert.display());
            println!("signing key: {}", keys.signer_key.display());
            Ok(())
        }
        ImageCmd::UpdateTest { no_build } => update_test_cli(ctx, &STANDARD, no_build),
    }
}

/// `cargo xtask image [armv7] bundle`: builds the A/B image `variant` as `version` and makes a
/// signed bundle of its root file system for that board.
fn bundle_cli(ctx: &Ctx, variant: &Variant, version: &str, out: Option<PathBuf>) -> Result<()> {
    update::check_version(version)?;
    let release = update::Release {
        version: version.to_owned(),
        build: update::Release::current(ctx)?.build,
    };
    let image = build_release(ctx, variant, Some(release.clone()))?;
    println!("{}", image.summary());
    let work = image_dir(ctx, &image);
    // One update CA for every board type (target/image/update-keys/): the CA says who may
    // sign, the compatible string which board a bundle is for.
    let keys = update::update_keys(&work_dir(ctx))?;
    let out = out.unwrap_or_else(|| work.join(format!("irtrack-{version}.raucb")));
    update::make_bundle_for(
        &work,
        &work.join("root.ext4"),
        &release,
        &keys,
        variant.compatible,
        &out,
    )?;
    println!(
        "bundle: {} ({:.1} MiB), version {version}, build {}, compatible {}, signed by {}",
        out.display(),
        mib(fs::metadata(&out)?.len()),
        release.build,
        variant.compatible,
        keys.signer_cert.display()
    );
    Ok(())
}

/// `cargo xtask image [armv7] update-test`.
fn update_test_cli(ctx: &Ctx, variant: &Variant, no_build: bool) -> Result<()> {
    let image = if no_build {
        existing(ctx, variant)?
    } else {
        build_variant(ctx, variant)?
    };
    println!("{}", image.summary());
    let report = update_test::run(ctx, &image)?;
    println!("{report}");
    if report.failed() > 0 {
        bail!(
            "{} update test: {} check(s) failed",
            variant.arch.name(),
            report.failed()
        );
    }
    Ok(())
}

/// CI: the crate list matches Cargo.lock, the image builds, and every system-test check passes.
pub fn ci_phase(ctx: &Ctx) -> Result<Counts> {
    let mut counts = Counts::default();
    // Failed checks are named again in the phase's error, which CI's summary prints last: the
    // per-check lines scroll away behind the later phases' output.
    let mut failed: Vec<String> = Vec::new();
    match crates::check(ctx) {
        Ok(()) => counts.passed += 1,
        Err(e) => {
            eprintln!("image: {e:#}");
            counts.failed += 1;
            failed.push(format!("crate list: {}", short(&format!("{e:#}"))));
        }
    }
    // The irtrackd of the aarch64 test build (aarch64-tests runs the same command and finds
    // it built): one aarch64 compile per CI run. `cargo xtask image build|test` ship release.
    let variant = Variant {
        irtrackd: |ctx| crate::cross::test_build_irtrackd(ctx, Arch::Aarch64),
        irtrackd_profile: "test profile, shared with aarch64-tests",
        ..STANDARD
    };
    let image = build_variant(ctx, &variant).context("building the image")?;
    println!("{}", image.summary());
    let report = system::run(ctx, &image)?;
    println!("{report}");
    counts.passed += report.passed();
    counts.failed += report.failed();
    for c in report.checks.iter().filter(|c| !c.ok) {
        failed.push(format!("{}: {}", c.name, short(&c.detail)));
    }
    if counts.failed > 0 {
        bail!("{} image check(s) failed: {}", counts.failed, failed.join("; "));
    }
    Ok(counts)
}

/// CI opt-in phases `image-update` (the aarch64 image) and `image-update-armv7`: builds the
/// A/B image `variant` and runs the update test on it.
pub fn update_phase(ctx: &Ctx, variant: &Variant) -> Result<Counts> {
    let image =
        build_variant(ctx, variant).with_context(|| format!("building the {} image", variant.arch.name()))?;
    println!("{}", image.summary());
    let report = update_test::run(ctx, &image)?;
    println!("{report}");
    let failed: Vec<String> = report
        .checks
        .iter()
        .filter(|c| !c.ok)
        .map(|c| format!("{}: {}", c.name, short(&c.detail)))
        .collect();
    if !failed.is_empty() {
        bail!(
            "{} {} update check(s) failed: {}",
            failed.len(),
            variant.arch.name(),
            failed.join("; ")
        );
    }
    Ok(Counts {
        passed: report.passed(),
        ..Counts::default()
    })
}

/// At most 400 characters of a check's detail, for one summary line.
fn short(detail: &str) -> String {
    let one_line = detail.replace('\n', " ");
    match one_line.char_indices().nth(400) {
        Some((i, _)) => format!("{}…", &one_line[..i]),
        None => one_line,
    }
}

/// A built SD-card image.
pub struct Image {
    pub sd_img: PathBuf,
    /// What it runs on (the QEMU machine that boots it).
    pub arch: Arch,
    pub kernel_version: String,
    pub size_bytes: u64,
    pub boot_bytes: u64,
    pub root_bytes: u64,
    pub irtrackd_bytes: u64,
    pub build_time: Duration,
    /// Secret half of the build's own signing key, whose public half the image trusts
    /// (`/etc/irtrack/trusted-keys/image-build.pub`); `push-params --sign-key` uses it. Empty
    /// for a variant without keys.
    pub signing_key: PathBuf,
    /// The board type bundles for it must name (A/B images; empty otherwise).
    pub compatible: &'static str,
}

/// The build's signing key pair in target/image/keys/, created once by `host-tools keygen` and
/// kept across builds, so that a board flashed earlier still accepts pushes signed with it.
/// Extra public keys (e.g. the calibration station's) come from `IRTRACK_IMAGE_TRUSTED_KEYS`,
/// a colon-separated list of `.pub` files.
fn signing_keys(ctx: &Ctx, work: &Path) -> Result<(PathBuf, Vec<PathBuf>)> {
    let dir = work.join("keys");
    let prefix = dir.join("image-build");
    let (secret, public) = (dir.join("image-build.key"), dir.join("image-build.pub"));
    if !secret.is_file() || !public.is_file() {
        fs::create_dir_all(&dir)?;
        let out = ctx
            .host_tools()
            .args(["keygen", "--force", "--out"])
            .arg(&prefix)
            .output()
            .context("running host-tools keygen")?;
        if !out.status.success() {
            bail!(
                "host-tools keygen failed: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            );
        }
    }
    let mut trusted = vec![public];
    if let Some(list) = std::env::var_os("IRTRACK_IMAGE_TRUSTED_KEYS") {
        for p in std::env::split_paths(&list).filter(|p| !p.as_os_str().is_empty()) {
            if !p.is_file() {
                bail!("IRTRACK_IMAGE_TRUSTED_KEYS: {} is not a file", p.display());
            }
            trusted.push(p);
        }
    }
    Ok((secret, trusted))
}

impl Image {
    pub fn summary(&self) -> String {
        format!(
            "image: {} — {:.1} MiB (boot {:.1} MiB, root {:.1} MiB; irtrackd {:.1} MiB stripped), \
             kernel {}, built in {}",
            self.sd_img.display(),
            mib(self.size_bytes),
            mib(self.boot_bytes),
            mib(self.root_bytes),
            mib(self.irtrackd_bytes),
            self.kernel_version,
            util::fmt_duration(self.build_time)
        )
    }
}

fn mib(bytes: u64) -> f64 {
    bytes as f64 / (1024.0 * 1024.0)
}

fn work_dir(ctx: &Ctx) -> PathBuf {
    ctx.target_dir().join("image")
}

/// The build directory of `image` (the system test's and QEMU's scratch files go there, so
/// the armv7 image's runs do not mix with the aarch64 image's).
fn image_dir(ctx: &Ctx, image: &Image) -> PathBuf {
    image
        .sd_img
        .parent()
        .map_or_else(|| work_dir(ctx), Path::to_path_buf)
}

/// Runs a command quietly; on failure the error shows the command and its output.
fn run_quiet(cmd: &mut Command) -> Result<String> {
    let shown = util::display_cmd(cmd);
    let out = cmd
        .output()
        .with_context(|| format!("could not start `{shown}`"))?;
    if !out.status.success() {
        bail!(
            "`{shown}` failed ({}):\n{}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

fn fresh_dir(dir: &Path) -> Result<()> {
    if dir.exists() {
        fs::remove_dir_all(dir).with_context(|| format!("removing {}", dir.display()))?;
    }
    fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))
}

/// The image of the last `build`, for re-running the system test without rebuilding.
pub fn existing(ctx: &Ctx, variant: &Variant) -> Result<Image> {
    let work = ctx.target_dir().join(variant.dir);
    let build_cmd = match variant.arch {
        Arch::Aarch64 => "cargo xtask image build",
        Arch::Armv7 => "cargo xtask image armv7 build",
    };
    let len = |name: &str| -> Result<u64> {
        let path = work.join(name);
        Ok(fs::metadata(&path)
            .with_context(|| format!("{} missing; run `{build_cmd}`", path.display()))?
            .len())
    };
    let (kernel_version, _) = kernel_modules_dir(&work.join("kernel"))?;
    Ok(Image {
        sd_img: work.join("irtrack-sd.img"),
        arch: variant.arch,
        compatible: if variant.ab_updates {
            variant.compatible
        } else {
            ""
        },
        kernel_version,
        size_bytes: len("irtrack-sd.img")?,
        boot_bytes: len("boot.vfat")?,
        root_bytes: len("root.ext4")?,
        irtrackd_bytes: len("irtrackd")?,
        build_time: Duration::ZERO,
        signing_key: work.join("keys").join("image-build.key"),
    })
}

/// Builds the whole CI image into target/image/.
pub fn build(ctx: &Ctx) -> Result<Image> {
    build_variant(ctx, &STANDARD)
}

/// Builds the image `variant` into target/<variant.dir>/.
pub fn build_variant(ctx: &Ctx, variant: &Variant) -> Result<Image> {
    build_release(ctx, variant, None)
}

/// Builds the image `variant` as `release` (default: [`update::Release::current`]).
pub fn build_release(ctx: &Ctx, variant: &Variant, release: Option<update::Release>) -> Result<Image> {
    let start = Instant::now();
    let work = ctx.target_dir().join(variant.dir);
    fs::create_dir_all(&work)?;
    let update_tools: &[&str] = if variant.ab_updates {
        &["rauc", "mksquashfs", "mkimage", "openssl", "readelf"]
    } else {
        &[]
    };
    for tool in [
        "dpkg-deb",
        "apt-get",
        "cpio",
        "gzip",
        "mkfs.vfat",
        "mcopy",
        "mmd",
        "mke2fs",
        "sfdisk",
        variant.arch.qemu(),
    ]
    .into_iter()
    .chain(update_tools.iter().copied())
    {
        if !util::on_path(tool)
            && !Path::new("/usr/sbin").join(tool).is_file()
            && !Path::new("/sbin").join(tool).is_file()
        {
            bail!("`{tool}` not found; run `cargo xtask setup`");
        }
    }

    println!("image: fetching Debian {} packages", debian_arch(variant.arch));
    let debs = match variant.arch {
        Arch::Aarch64 => fetch_debs(&work.join("dl"))?,
        Arch::Armv7 => armv7::fetch_debs(&work)?,
    };
    let kernel_root = extract_cached(&debs.kernel, &work.join("kernel"))?;
    let busybox_root = extract_cached(&debs.busybox, &work.join("busybox"))?;
    let (kver, modules_dir) = kernel_modules_dir(&kernel_root)?;
    let kernel_image = kernel_root.join("boot").join(format!("vmlinuz-{kver}"));
    let busybox = busybox_root.join("bin/busybox");
    if !kernel_image.is_file() || !busybox.is_file() {
        bail!(
            "{} or {} missing from the extracted packages",
            kernel_image.display(),
            busybox.display()
        );
    }

    println!(
        "image: cross-building irtrackd (static, {}, {})",
        variant.arch.name(),
        variant.irtrackd_profile
    );
    let irtrackd_built = (variant.irtrackd)(ctx)?;
    let irtrackd = work.join("irtrackd");
    fs::copy(&irtrackd_built, &irtrackd)?;
    // The release profile keeps line tables for backtraces; the image does not need them.
    run_quiet(Command::new(format!("{}strip", variant.arch.tool_prefix())).arg(&irtrackd))?;
    let irtrackd_bytes = fs::metadata(&irtrackd)?.len();

    let index = ModuleIndex::scan(&modules_dir)?;
    let initrd_mods = index.closure(INITRD_MODULES)?;
    let root_modules: Vec<(&str, &str)> = ROOT_MODULES
        .iter()
        .chain(variant.extra_modules)
        .copied()
        .collect();
    let root_names: Vec<&str> = root_modules.iter().map(|(m, _)| *m).collect();
    let root_mods: Vec<ModuleFile> = index
        .closure(&root_names)?
        .into_iter()
        .filter(|m| !initrd_mods.contains(m))
        .collect();

    println!("image: initramfs ({} modules)", initrd_mods.len());
    let initrd = work.join("initrd.gz");
    build_initramfs(
        ctx,
        &work.join("initramfs"),
        &busybox,
        &modules_dir,
        &kver,
        &initrd_mods,
        &initrd,
    )?;

    println!("image: root filesystem ({} modules)", root_mods.len());
    let rootfs = work.join("rootfs");
    stage_rootfs(
        ctx,
        variant.arch,
        &rootfs,
        &busybox,
        &irtrackd,
        &modules_dir,
        &kver,
        &root_mods,
        &root_modules,
    )?;
    if let Some(overlay) = variant.overlay {
        copy_tree(&ctx.root.join(overlay), &rootfs)?;
    }
    for (src, dest) in variant.tools {
        println!("image: compiling {src} for aarch64");
        crate::cross::build_tool(ctx, &ctx.root.join(src), &rootfs.join(dest))?;
    }
    // The cluster image's camera board takes its parameters from the simulator: no keys (and
    // no host-tools build, which needs OpenCV, for `keygen`).
    let signing_key = if variant.signing_keys {
        let (signing_key, trusted) = signing_keys(ctx, &work)?;
        let keys_dir = rootfs.join("etc/irtrack/trusted-keys");
        fs::create_dir_all(&keys_dir)?;
        for key in &trusted {
            let name = key.file_name().context("key file without a name")?;
            fs::copy(key, keys_dir.join(name)).with_context(|| format!("copying {}", key.display()))?;
        }
        println!(
            "image: {} trusted parameter signing key(s); sign pushes with {}",
            trusted.len(),
            signing_key.display()
        );
        signing_key
    } else {
        PathBuf::new()
    };

    let boot_img = work.join("boot.vfat");
    let root_img = work.join("root.ext4");
    let sd_img = work.join("irtrack-sd.img");
    let (boot_bytes, root_bytes);
    if variant.ab_updates {
        let release = match release {
            Some(r) => r,
            None => update::Release::current(ctx)?,
        };
        println!(
            "image: A/B update tools (RAUC), release {} build {}",
            release.version, release.build
        );
        let pkgs = update::fetch_tools(variant.arch, &work, &work.join("update-pkgs"))?;
        let libs = update::install_tools(variant.arch, &pkgs, &rootfs)?;
        copy_tree(&ctx.root.join("image/update/rootfs"), &rootfs)?;
        update::set_compatible(&rootfs, variant.compatible)?;
        // GDBus and libdbus look for the system bus under /var/run.
        std::os::unix::fs::symlink("../run", rootfs.join("var/run"))?;
        // One update CA for every board type (target/image/update-keys/).
        let keys = update::update_keys(&work_dir(ctx))?;
        copy_file_mode(&keys.ca_cert, &rootfs.join("etc/rauc/ca.cert.pem"), 0o644)?;
        update::write_release(&rootfs, &release, variant.compatible)?;
        // Each slot boots its own kernel and initramfs (boot.scr loads them from the slot), so
        // an update brings the kernel and its modules together.
        copy_file_mode(
            &kernel_image,
            &rootfs.join("boot").join(update::kernel_file(variant.arch)),
            0o644,
        )?;
        copy_file_mode(&initrd, &rootfs.join("boot/initrd.gz"), 0o644)?;
        println!(
            "image: RAUC, dbus-daemon, fw_printenv/fw_setenv and {libs} shared libraries ({}); board type {}; bundles signed under {}",
            debian_arch(variant.arch),
            variant.compatible,
            keys.ca_cert.display()
        );
        let scr = update::boot_script(ctx, &work, variant)?;
        let env = update::initial_env(&work)?;
        boot_bytes = update::make_boot_partition(&boot_img, &scr, &env)?;
        root_bytes = make_root_partition(&root_img, &rootfs)?;
        if root_bytes > update::SLOT_MIB << 20 {
            bail!(
                "root file system {} MiB exceeds the {} MiB slot",
                root_bytes >> 20,
                update::SLOT_MIB
            );
        }
        let data_img = work.join("data.ext4");
        let data_bytes = update::make_data_partition(&work, &data_img)?;
        assemble_sd(
            &sd_img,
            &[
                Partition {
                    file: Some(boot_img.as_path()),
                    bytes: boot_bytes,
                    kind: "c",
                    bootable: true,
                },
                Partition {
                    file: Some(root_img.as_path()),
                    bytes: update::SLOT_MIB << 20,
                    kind: "83",
                    bootable: false,
                },
                Partition {
                    file: None,
                    bytes: update::SLOT_MIB << 20,
                    kind: "83",
                    bootable: false,
                },
                Partition {
                    file: Some(data_img.as_path()),
                    bytes: data_bytes,
                    kind: "83",
                    bootable: false,
                },
            ],
        )?;
    } else {
        boot_bytes = make_boot_partition(ctx, &boot_img, &kernel_image, &initrd)?;
        root_bytes = make_root_partition(&root_img, &rootfs)?;
        assemble_sd(
            &sd_img,
            &[
                Partition {
                    file: Some(boot_img.as_path()),
                    bytes: boot_bytes,
                    kind: "c",
                    bootable: true,
                },
                Partition {
                    file: Some(root_img.as_path()),
                    bytes: root_bytes,
                    kind: "83",
                    bootable: false,
                },
            ],
        )?;
    }
    let size_bytes = fs::metadata(&sd_img)?.len();
    Ok(Image {
        sd_img,
        arch: variant.arch,
        kernel_version: kver,
        size_bytes,
        boot_bytes,
        root_bytes,
        irtrackd_bytes,
        build_time: start.elapsed(),
        signing_key,
        compatible: if variant.ab_updates {
            variant.compatible
        } else {
            ""
        },
    })
}

/// Debian's name of the architecture.
fn debian_arch(arch: Arch) -> &'static str {
    match arch {
        Arch::Aarch64 => "arm64",
        Arch::Armv7 => "armhf",
    }
}

struct Debs {
    kernel: PathBuf,
    busybox: PathBuf,
}

/// Finds `<name>_*.deb` in `dir`.
fn find_deb(dir: &Path, name: &str) -> Option<PathBuf> {
    let prefix = format!("{name}_");
    let mut found: Vec<PathBuf> = fs::read_dir(dir)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with(&prefix) && n.ends_with(".deb"))
        })
        .collect();
    found.sort();
    found.pop()
}

fn apt_download(dir: &Path, package: &str) -> Result<()> {
    // apt warns that `_apt` cannot write here and downloads as root anyway; that is fine.
    // `package` may list several, separated by spaces.
    run_quiet(
        Command::new("apt-get")
            .args(["download", "-q"])
            .args(package.split_whitespace())
            .current_dir(dir),
    )
        .with_context(|| format!("downloading {package} (needs `dpkg --add-architecture arm64` and apt-get update; see `cargo xtask setup`)"))?;
    Ok(())
}

/// Downloads the arm64 kernel (through the `linux-image-arm64` meta package) and
/// busybox-static into `dir`, reusing what is already there.
fn fetch_debs(dir: &Path) -> Result<Debs> {
    fs::create_dir_all(dir)?;
    if find_deb(dir, "linux-image-arm64").is_none() {
        apt_download(dir, "linux-image-arm64:arm64")?;
    }
    let meta = find_deb(dir, "linux-image-arm64").context("linux-image-arm64 .deb missing after download")?;
    let depends = run_quiet(Command::new("dpkg-deb").args(["-f"]).arg(&meta).arg("Depends"))?;
    let kernel_pkg = depends
        .split([',', '|'])
        .map(|d| d.split_whitespace().next().unwrap_or(""))
        .find(|d| d.starts_with("linux-image-") && d.ends_with("-arm64"))
        .with_context(|| {
            format!(
                "no linux-image-*-arm64 in Depends of {}: {depends}",
                meta.display()
            )
        })?
        .to_owned();
    if find_deb(dir, &kernel_pkg).is_none() {
        apt_download(dir, &format!("{kernel_pkg}:arm64"))?;
    }
    if find_deb(dir, "busybox-static").is_none() {
        apt_download(dir, "busybox-static:arm64")?;
    }
    Ok(Debs {
        kernel: find_deb(dir, &kernel_pkg).context("kernel .deb missing after download")?,
        busybox: find_deb(dir, "busybox-static").context("busybox-static .deb missing after download")?,
    })
}

/// Extracts a .deb into `dir` unless that exact package was extracted there already.
fn extract_cached(deb: &Path, dir: &Path) -> Result<PathBuf> {
    let stamp = dir.join(".extracted-from");
    let name = deb
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if fs::read_to_string(&stamp).is_ok_and(|s| s == name) {
        return Ok(dir.to_path_buf());
    }
    fresh_dir(dir)?;
    run_quiet(Command::new("dpkg-deb").arg("-x").arg(deb).arg(dir))?;
    fs::write(&stamp, &name)?;
    Ok(dir.to_path_buf())
}

fn kernel_modules_dir(kernel_root: &Path) -> Result<(String, PathBuf)> {
    let base = kernel_root.join("lib/modules");
    let mut versions: Vec<String> = fs::read_dir(&base)
        .with_context(|| format!("reading {}", base.display()))?
        .flatten()
        .filter(|e| e.path().join("kernel").is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    versions.sort();
    let kver = versions
        .pop()
        .with_context(|| format!("no kernel modules under {}", base.display()))?;
    let dir = base.join(&kver);
    Ok((kver, dir))
}

/// A module file, relative to /lib/modules/<kver>/.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct ModuleFile {
    name: String,
    rel: PathBuf,
}

/// All modules of a kernel by name, with dependencies read from each file's `.modinfo`
/// (what depmod does; kmod is not needed on the build host).
struct ModuleIndex {
    root: PathBuf,
    by_name: HashMap<String, PathBuf>,
}

/// Module names use `_` where file names may use `-`.
fn module_name(file_name: &str) -> Option<String> {
    let stem = file_name.strip_suffix(".ko")?;
    Some(stem.replace('-', "_"))
}

impl ModuleIndex {
    fn scan(modules_dir: &Path) -> Result<Self> {
        let mut by_name = HashMap::new();
        let mut stack = vec![modules_dir.join("kernel")];
        while let Some(dir) = stack.pop() {
            for entry in fs::read_dir(&dir).with_context(|| format!("reading {}", dir.display()))? {
                let path = entry?.path();
                if path.is_dir() {
                    stack.push(path);
                } else if let Some(name) = path.file_name().and_then(|n| n.to_str()).and_then(module_name) {
                    let rel = path.strip_prefix(modules_dir)?.to_path_buf();
                    by_name.insert(name, rel);
                }
            }
        }
        if by_name.is_empty() {
            bail!("no uncompressed .ko modules under {}", modules_dir.display());
        }
        Ok(Self {
            root: modules_dir.to_path_buf(),
            by_name,
        })
    }

    fn depends(&self, name: &str) -> Result<Vec<String>> {
        let rel = self
            .by_name
            .get(name)
            .with_context(|| format!("kernel module {name} not found"))?;
        let bytes = fs::read(self.root.join(rel))?;
        modinfo_depends(&bytes).with_context(|| format!("reading .modinfo of {}", rel.display()))
    }

    /// `roots` and everything they need, dependencies first (insmod order).
    fn closure(&self, roots: &[&str]) -> Result<Vec<ModuleFile>> {
        let mut order = Vec::new();
        let mut done = BTreeSet::new();
        for root in roots {
            self.visit(root, &mut done, &mut Vec::new(), &mut order)?;
        }
        Ok(order)
    }

    fn visit(
        &self,
        name: &str,
        done: &mut BTreeSet<String>,
        path: &mut Vec<String>,
        order: &mut Vec<ModuleFile>,
    ) -> Result<()> {
        if done.contains(name) {
            return Ok(());
        }
        if path.iter().any(|p| p == name) {
            bail!("module dependency cycle: {} -> {name}", path.join(" -> "));
        }
        path.push(name.to_owned());
        for dep in self.depends(name)? {
            self.visit(&dep, done, path, order)?;
        }
        path.pop();
        done.insert(name.to_owned());
        let rel = self.by_name[name].clone();
        order.push(ModuleFile {
            name: name.to_owned(),
            rel,
        });
        Ok(())
    }
}

fn le_u16(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(b.get(at..at + 2)?.try_into().ok()?))
}
fn le_u32(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(b.get(at..at + 4)?.try_into().ok()?))
}
fn le_u64(b: &[u8], at: usize) -> Option<u64> {
    Some(u64::from_le_bytes(b.get(at..at + 8)?.try_into().ok()?))
}

/// The `depends=` list of a little-endian kernel module's `.modinfo` section: ELF64 (arm64)
/// or ELF32 (armhf, the armv7 image).
fn modinfo_depends(elf: &[u8]) -> Result<Vec<String>> {
    let is64 = match (elf.get(..4), elf.get(4), elf.get(5)) {
        (Some(b"\x7fELF"), Some(&2), Some(&1)) => true,
        (Some(b"\x7fELF"), Some(&1), Some(&1)) => false,
        _ => bail!("not a little-endian ELF32 or ELF64 file"),
    };
    // A word of the file's class (section header offsets and sizes).
    let word = |at: usize| -> Option<usize> {
        if is64 {
            usize::try_from(le_u64(elf, at)?).ok()
        } else {
            usize::try_from(le_u32(elf, at)?).ok()
        }
    };
    let parse = || -> Option<Vec<String>> {
        // e_shoff, e_shentsize, e_shnum, e_shstrndx; sh_offset, sh_size.
        let (shoff_at, sh_at, off_at, size_at) = if is64 {
            (0x28, 0x3a, 0x18, 0x20)
        } else {
            (0x20, 0x2e, 0x10, 0x14)
        };
        let shoff = word(shoff_at)?;
        let shentsize = usize::from(le_u16(elf, sh_at)?);
        let shnum = usize::from(le_u16(elf, sh_at + 2)?);
        let shstrndx = usize::from(le_u16(elf, sh_at + 4)?);
        let section = |i: usize| -> Option<(u32, usize, usize)> {
            let h = shoff + i * shentsize;
            let name = le_u32(elf, h)?;
            Some((name, word(h + off_at)?, word(h + size_at)?))
        };
        let (_, str_off, str_size) = section(shstrndx)?;
        let names = elf.get(str_off..str_off + str_size)?;
        for i in 0..shnum {
            let (name, offset, size) = section(i)?;
            let name = names.get(name as usize..)?;
            let end = name.iter().position(|&c| c == 0)?;
            if &name[..end] != b".modinfo" {
                continue;
            }
            let data = elf.get(offset..offset + size)?;
            let deps = data
                .split(|&c| c == 0)
                .filter_map(|entry| entry.strip_prefix(b"depends="))
                .flat_map(|list| list.split(|&c| c == b','))
                .filter(|d| !d.is_empty())
                .map(|d| String::from_utf8_lossy(d).replace('-', "_"))
                .collect();
            return Some(deps);
        }
        Some(Vec::new())
    };
    parse().context("malformed ELF section headers")
}

fn copy_modules(modules_dir: &Path, dest_modules: &Path, mods: &[ModuleFile]) -> Result<()> {
    for m in mods {
        let dest = dest_modules.join(&m.rel);
        fs::create_dir_all(dest.parent().context("module path has no parent")?)?;
        fs::copy(modules_dir.join(&m.rel), &dest).with_context(|| format!("copying {}", m.rel.display()))?;
    }
    Ok(())
}

/// `insmod` list: absolute path in the target and module arguments, one module per line.
fn modules_list(kver: &str, mods: &[ModuleFile], args: &[(&str, &str)]) -> String {
    let mut out = String::new();
    for m in mods {
        let arg = args
            .iter()
            .find(|(n, _)| *n == m.name)
            .map(|(_, a)| *a)
            .unwrap_or("");
        out.push_str(&format!("/lib/modules/{kver}/{} {arg}\n", m.rel.display()).replace(" \n", "\n"));
    }
    out
}

fn copy_file_mode(src: &Path, dest: &Path, mode: u32) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    if let Some(parent) = dest.parent() {
        fs::create_dir_all(parent)?;
    }
    fs::copy(src, dest).with_context(|| format!("copying {} to {}", src.display(), dest.display()))?;
    fs::set_permissions(dest, fs::Permissions::from_mode(mode))?;
    Ok(())
}

/// Copies a directory tree, keeping permissions.
fn copy_tree(src: &Path, dest: &Path) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    for entry in fs::read_dir(src).with_context(|| format!("reading {}", src.display()))? {
        let entry = entry?;
        let from = entry.path();
        let to = dest.join(entry.file_name());
        if from.is_dir() {
            fs::create_dir_all(&to)?;
            copy_tree(&from, &to)?;
        } else {
            let mode = entry.metadata()?.permissions().mode() & 0o7777;
            copy_file_mode(&from, &to, mode)?;
        }
    }
    Ok(())
}

fn build_initramfs(
    ctx: &Ctx,
    stage: &Path,
    busybox: &Path,
    modules_dir: &Path,
    kver: &str,
    mods: &[ModuleFile],
    out: &Path,
) -> Result<()> {
    fresh_dir(stage)?;
    for d in ["bin", "dev", "proc", "sys", "newroot", "etc"] {
        fs::create_dir_all(stage.join(d))?;
    }
    copy_file_mode(busybox, &stage.join("bin/busybox"), 0o755)?;
    copy_file_mode(&ctx.root.join("image/initramfs/init"), &stage.join("init"), 0o755)?;
    copy_modules(modules_dir, &stage.join("lib/modules").join(kver), mods)?;
    fs::write(stage.join("etc/modules.list"), modules_list(kver, mods, &[]))?;
    let script = format!(
        "cd {} && find . | LC_ALL=C sort | cpio -o -H newc -R 0:0 --quiet | gzip -9n > {}",
        util::shell_quote(&stage.to_string_lossy()),
        util::shell_quote(&out.to_string_lossy())
    );
    run_quiet(Command::new("sh").args(["-c", &script]))?;
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn stage_rootfs(
    ctx: &Ctx,
    arch: Arch,
    stage: &Path,
    busybox: &Path,
    irtrackd: &Path,
    modules_dir: &Path,
    kver: &str,
    mods: &[ModuleFile],
    module_args: &[(&str, &str)],
) -> Result<()> {
    use std::os::unix::fs::PermissionsExt;
    fresh_dir(stage)?;
    for d in [
        "bin",
        "sbin",
        "usr/bin",
        "usr/sbin",
        "dev",
        "proc",
        "sys",
        "run",
        "tmp",
        "root",
        "mnt",
        "var/lib/irtrackd",
        "var/log",
    ] {
        fs::create_dir_all(stage.join(d))?;
    }
    fs::set_permissions(stage.join("tmp"), fs::Permissions::from_mode(0o1777))?;
    copy_tree(&ctx.root.join("image/rootfs"), stage)?;
    copy_file_mode(busybox, &stage.join("bin/busybox"), 0o755)?;
    // Applet links as busybox itself lists them (run through qemu-user on the x86 host).
    let list = run_quiet(Command::new(arch.qemu()).arg(busybox).arg("--list-full"))?;
    for applet in list.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let link = stage.join(applet);
        if link.exists() || applet == "bin/busybox" {
            continue;
        }
        let depth = applet.matches('/').count();
        let target = format!("{}bin/busybox", "../".repeat(depth));
        std::os::unix::fs::symlink(&target, &link).with_context(|| format!("linking {applet}"))?;
    }
    copy_file_mode(irtrackd, &stage.join("usr/bin/irtrackd"), 0o755)?;
    copy_modules(modules_dir, &stage.join("lib/modules").join(kver), mods)?;
    fs::write(
        stage.join("etc/irtrack/modules.list"),
        modules_list(kver, mods, module_args),
    )?;
    Ok(())
}

/// vfat boot partition: kernel, initramfs and extlinux.conf, written with mtools.
fn make_boot_partition(ctx: &Ctx, out: &Path, kernel: &Path, initrd: &Path) -> Result<u64> {
    let payload = fs::metadata(kernel)?.len() + fs::metadata(initrd)?.len();
    // FAT overhead plus room for a second kernel during an update.
    let size_mib = (payload / (1 << 20) + 9).max(48);
    let _ = fs::remove_file(out);
    run_quiet(
        Command::new("mkfs.vfat")
            .args(["-C", "-n", "IRTRACKBOOT"])
            .arg(out)
            .arg((size_mib * 1024).to_string()),
    )?;
    let img = out.to_string_lossy().into_owned();
    run_quiet(Command::new("mmd").args(["-i", &img, "::/extlinux"]))?;
    run_quiet(
        Command::new("mcopy")
            .args(["-i", &img])
            .arg(kernel)
            .arg("::/Image"),
    )?;
    run_quiet(
        Command::new("mcopy")
            .args(["-i", &img])
            .arg(initrd)
            .arg("::/initrd.gz"),
    )?;
    run_quiet(
        Command::new("mcopy")
            .args(["-i", &img])
            .arg(ctx.root.join("image/boot/extlinux.conf"))
            .arg("::/extlinux/extlinux.conf"),
    )?;
    Ok(size_mib << 20)
}

fn dir_bytes(dir: &Path) -> Result<u64> {
    let mut total = 0;
    for entry in fs::read_dir(dir)? {
        let entry = entry?;
        let meta = fs::symlink_metadata(entry.path())?;
        total += if meta.is_dir() {
            dir_bytes(&entry.path())? + 4096
        } else {
            meta.len().max(1024)
        };
    }
    Ok(total)
}

/// ext4 root partition populated from the staging directory by `mke2fs -d` (no mount).
fn make_root_partition(out: &Path, stage: &Path) -> Result<u64> {
    let used_mib = dir_bytes(stage)? / (1 << 20) + 1;
    // Free space for parameter sets, logs and a service update; rounded to 16 MiB.
    let size_mib = ((used_mib * 3 / 2 + 48).div_ceil(16) * 16).max(96);
    let _ = fs::remove_file(out);
    run_quiet(
        Command::new("mke2fs")
            .args([
                "-q",
                "-F",
                "-t",
                "ext4",
                "-L",
                "irtrack-root",
                "-E",
                "root_owner=0:0",
                "-d",
            ])
            .arg(stage)
            .arg(out)
            .arg(format!("{size_mib}M")),
    )?;
    Ok(size_mib << 20)
}

/// Copies `src` into `dest` at `offset`, skipping all-zero blocks so the image stays sparse.
fn write_at(dest: &mut fs::File, offset: u64, src: &Path) -> Result<()> {
    let mut input = fs::File::open(src)?;
    let mut buf = vec![0u8; 1 << 16];
    let mut pos = offset;
    loop {
        let n = input.read(&mut buf)?;
        if n == 0 {
            break;
        }
        if buf[..n].iter().any(|&b| b != 0) {
            dest.seek(SeekFrom::Start(pos))?;
            dest.write_all(&buf[..n])?;
        }
        pos += n as u64;
    }
    Ok(())
}

/// One MBR partition: its content (None: left empty), size, type and boot flag.
struct Partition<'a> {
    file: Option<&'a Path>,
    bytes: u64,
    kind: &'a str,
    bootable: bool,
}

/// MBR disk with the partitions in order from 1 MiB, each file copied in at its offset (the
/// disk stays sparse). Partition 1 is the vfat boot partition.
fn assemble_sd(out: &Path, parts: &[Partition]) -> Result<()> {
    const SECTOR: u64 = 512;
    let mut layout = String::from("label: dos\nunit: sectors\n\n");
    let mut start = 2048;
    let mut offsets = Vec::new();
    for p in parts {
        if let Some(file) = p.file {
            let len = fs::metadata(file)?.len();
            if len > p.bytes {
                bail!(
                    "{} ({len} bytes) does not fit its {} byte partition",
                    file.display(),
                    p.bytes
                );
            }
        }
        let sectors = p.bytes / SECTOR;
        layout.push_str(&format!(
            "start={start}, size={sectors}, type={}{}\n",
            p.kind,
            if p.bootable { ", bootable" } else { "" }
        ));
        offsets.push(start * SECTOR);
        start += sectors;
    }
    let total = start * SECTOR;
    let _ = fs::remove_file(out);
    let mut file = fs::File::create(out)?;
    file.set_len(total)?;
    let mut sfdisk = Command::new("sfdisk");
    sfdisk
        .args(["--quiet", "--no-reread", "--no-tell-kernel"])
        .arg(out);
    sfdisk
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    let mut child = sfdisk.spawn().context("starting sfdisk")?;
    child
        .stdin
        .take()
        .context("sfdisk stdin")?
        .write_all(layout.as_bytes())?;
    let res = child.wait_with_output()?;
    if !res.status.success() {
        bail!("sfdisk failed: {}", String::from_utf8_lossy(&res.stderr));
    }
    for (p, offset) in parts.iter().zip(offsets) {
        if let Some(src) = p.file {
            write_at(&mut file, offset, src)?;
        }
    }
    file.sync_all()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A minimal ELF64 with a section-name table and a `.modinfo` section.
    fn fake_module(modinfo: &[u8]) -> Vec<u8> {
        let shstr = b"\0.shstrtab\0.modinfo\0";
        let mut elf = vec![0u8; 64];
        elf[..6].copy_from_slice(b"\x7fELF\x02\x01");
        let shstr_off = elf.len();
        elf.extend_from_slice(shstr);
        let modinfo_off = elf.len();
        elf.extend_from_slice(modinfo);
        let shoff = elf.len();
        let mut header = |name: u32, off: usize, size: usize| {
            let mut h = vec![0u8; 64];
            h[..4].copy_from_slice(&name.to_le_bytes());
            h[0x18..0x20].copy_from_slice(&(off as u64).to_le_bytes());
            h[0x20..0x28].copy_from_slice(&(size as u64).to_le_bytes());
            elf.extend_from_slice(&h);
        };
        header(0, 0, 0);
        header(1, shstr_off, shstr.len());
        header(11, modinfo_off, modinfo.len());
        elf[0x28..0x30].copy_from_slice(&(shoff as u64).to_le_bytes());
        elf[0x3a..0x3c].copy_from_slice(&64u16.to_le_bytes());
        elf[0x3c..0x3e].copy_from_slice(&3u16.to_le_bytes());
        elf[0x3e..0x40].copy_from_slice(&1u16.to_le_bytes());
        elf
    }

    #[test]
    fn modinfo_depends_are_read_and_normalised() {
        let elf = fake_module(b"license=GPL\0depends=videobuf2-common,v4l2_tpg,mc\0vermagic=6.1\0");
        assert_eq!(
            modinfo_depends(&elf).unwrap(),
            vec!["videobuf2_common", "v4l2_tpg", "mc"]
        );
        let none = fake_module(b"license=GPL\0depends=\0");
        assert!(modinfo_depends(&none).unwrap().is_empty());
        assert!(modinfo_depends(b"not an elf").is_err());
        let mut truncated = fake_module(b"depends=a\0");
        truncated.truncate(100);
        assert!(modinfo_depends(&truncated).is_err());
    }

    #[test]
    fn closure_lists_dependencies_first_once() {
        let dir = std::env::temp_dir().join(format!("xtask-modules-{}", std::process::id()));
        let kernel = dir.join("kernel/drivers");
        fs::create_dir_all(&kernel).unwrap();
        for (file, deps) in [
            ("a.ko", "b,c"),
            ("b.ko", "c"),
            ("c-x.ko", ""),
            ("c.ko", ""),
            ("d.ko", "c_x"),
        ] {
            fs::write(
                kernel.join(file),
                fake_module(format!("depends={deps}\0").as_bytes()),
            )
            .unwrap();
        }
        let index = ModuleIndex::scan(&dir).unwrap();
        let order: Vec<String> = index
            .closure(&["a", "d"])
            .unwrap()
            .into_iter()
            .map(|m| m.name)
            .collect();
        assert_eq!(order, vec!["c", "b", "a", "c_x", "d"]);
        assert!(
            index
                .closure(&["missing"])
                .unwrap_err()
                .to_string()
                .contains("missing")
        );
        fs::write(kernel.join("c.ko"), fake_module(b"depends=a\0")).unwrap();
        let err = ModuleIndex::scan(&dir)
            .unwrap()
            .closure(&["a"])
            .unwrap_err()
            .to_string();
        fs::remove_dir_all(&dir).unwrap();
        assert!(err.contains("cycle"), "{err}");
    }

    #[test]
    fn modules_list_adds_arguments() {
        let mods = vec![
            ModuleFile {
                name: "mc".into(),
                rel: "kernel/mc.ko".into(),
            },
            ModuleFile {
                name: "vivid".into(),
                rel: "kernel/vivid.ko".into(),
            },
        ];
        let list = modules_list("6.1", &mods, &[("vivid", "n_devs=2")]);
        assert_eq!(
            list,
            "/lib/modules/6.1/kernel/mc.ko\n/lib/modules/6.1/kernel/vivid.ko n_devs=2\n"
        );
    }
}
