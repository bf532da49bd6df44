//! `cargo xtask setup`: installs what the build, the tests and the demo need, idempotently.
//!
//! Checks every package first (dpkg-query, no network). When nothing is missing it returns
//! at once; otherwise it says what it installs and why, then runs apt-get as root or through
//! `sudo -n`, and prints the exact commands when it can do neither. The package list is the
//! one verified on Debian 12 (see docs/development.md). On Debian 12 the backports suite is
//! added, when missing, with the mirror of the machine's own `bookworm` entry (no archive host
//! is written in this repository).

mod sources;

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Result, bail};

use crate::util::{self, RunOpts};
use sources::{Backports, NewEntry};

/// One system package, and why the project needs it.
struct Pkg {
    name: &'static str,
    why: &'static str,
    /// On Debian bookworm this comes from bookworm-backports (main has a too-old version).
    backports: bool,
    /// Debian-only (no Ubuntu equivalent with the same role).
    debian_only: bool,
}

const fn pkg(name: &'static str, why: &'static str) -> Pkg {
    Pkg {
        name,
        why,
        backports: false,
        debian_only: false,
    }
}

const PACKAGES: &[Pkg] = &[
    Pkg {
        debian_only: true,
        ..pkg(
            "rustc-web",
            "Debian's rustc 1.96 (/usr/bin/rustc); its aarch64 std is used for cross builds",
        )
    },
    Pkg {
        debian_only: true,
        ..pkg(
            "libstd-rust-web-dev:arm64",
            "aarch64 standard library for /usr/bin/rustc (+ arm64 glibc for QEMU)",
        )
    },
    pkg("gcc-aarch64-linux-gnu", "linker for aarch64-unknown-linux-gnu"),
    Pkg {
        debian_only: true,
        ..pkg(
            "cargo-web",
            "Debian's cargo 1.96 (/usr/bin/cargo): the same release as rust-web-src, for -Z build-std",
        )
    },
    Pkg {
        debian_only: true,
        ..pkg(
            "rust-web-src",
            "source of rustc-web's standard library: cargo builds the armv7 std from it (-Z build-std)",
        )
    },
    pkg(
        "gcc-arm-linux-gnueabihf",
        "linker for armv7-unknown-linux-gnueabihf (the Pandaboard's Cortex-A9)",
    ),
    pkg(
        "libc6-dev-armhf-cross",
        "armhf glibc for linking armv7 binaries and for qemu-arm to run them (-L /usr/arm-linux-gnueabihf)",
    ),
    pkg(
        "libopencv-dev",
        "OpenCV 4.6: calibration and cross-checks on the PC (opencv crate)",
    ),
    pkg("clang", "bindgen (opencv crate, v4l2-sys) needs clang"),
    pkg("libclang-dev", "bindgen needs libclang"),
    pkg(
        "valgrind",
        "callgrind instruction counts for repeatable benchmarks",
    ),
    pkg(
        "mtools",
        "copies files into the FAT boot partition of the SD image without mounting",
    ),
    pkg("dosfstools", "mkfs.vfat for the SD image's boot partition"),
    pkg("fdisk", "sfdisk writes the SD image's partition table"),
    pkg(
        "e2fsprogs",
        "mke2fs -d builds the ext4 root filesystem without mounting",
    ),
    pkg("cpio", "packs the initramfs of the QEMU system test"),
    pkg(
        "u-boot-qemu",
        "U-Boot (qemu_arm64, qemu_arm) for booting the SD images in qemu-system-aarch64 and qemu-system-arm",
    ),
    Pkg {
        debian_only: true,
        ..pkg("busybox-static:arm64", "aarch64 userland of the test image")
    },
    pkg(
        "rauc",
        "`rauc bundle` makes the signed A/B update bundles of the image (docs/updates.md)",
    ),
    pkg("squashfs-tools", "mksquashfs, which `rauc bundle` runs"),
    pkg(
        "openssl",
        "makes the update CA and signing certificate (cargo xtask image update-keys)",
    ),
    pkg(
        "u-boot-tools",
        "mkimage (boot.scr) for the A/B image; mkenvimage cross-checks its boot counter format in xtask's tests",
    ),
    pkg(
        "binutils",
        "readelf lists the shared libraries RAUC needs in the image",
    ),
    pkg("systemd", "systemd-analyze verifies the unit files in systemd/"),
    pkg(
        "linuxptp",
        "ptp4l reads the PTP config irtrackd generates (test); systemd-analyze resolves the PTP units' ptp4l/phc2sys",
    ),
    pkg(
        "strace",
        "traces ptp4l/phc2sys inside the PTP units' sandbox against their system call filters (firmware/tests/ptp_sandbox.rs)",
    ),
    pkg(
        "iproute2",
        "`ip` sets up loopback multicast in the DDS test's own network namespace (firmware/tests/ros2_dds.rs)",
    ),
    pkg(
        "util-linux",
        "`unshare -rn` gives the DDS test a network namespace of its own (firmware/tests/ros2_dds.rs)",
    ),
    Pkg {
        backports: true,
        ..pkg(
            "qemu-user",
            "qemu-aarch64 and qemu-arm run the aarch64 and armv7 test binaries",
        )
    },
    Pkg {
        backports: true,
        ..pkg(
            "qemu-system-arm",
            "qemu-system-aarch64 and qemu-system-arm boot the appliance images (aarch64, armv7)",
        )
    },
    // BitBake's host tools (openembedded-core scarthgap's HOSTTOOLS and its sanity checks),
    // for the yocto-bitbake phase: the list /work/shared/yocto's README gives, without the
    // transitional liblz4-tool (lz4 itself provides lz4c).
    pkg("gawk", BB_WHY),
    pkg("wget", BB_WHY),
    pkg("diffstat", BB_WHY),
    pkg("unzip", BB_WHY),
    pkg("texinfo", BB_WHY),
    pkg("build-essential", BB_WHY),
    pkg("chrpath", BB_WHY),
    pkg("socat", BB_WHY),
    pkg("xz-utils", BB_WHY),
    pkg("debianutils", BB_WHY),
    pkg("iputils-ping", BB_WHY),
    pkg("zstd", BB_WHY),
    pkg("lz4", BB_WHY),
    pkg("file", BB_WHY),
    pkg("python3-pexpect", BB_PY_WHY),
    pkg("python3-git", BB_PY_WHY),
    pkg("python3-jinja2", BB_PY_WHY),
    pkg("python3-subunit", BB_PY_WHY),
    pkg("locales", "locale-gen: BitBake needs the en_US.UTF-8 locale"),
    pkg("chromium", "headless browser test of the set-up page"),
    pkg(
        "chromium-driver",
        "headless browser test of the set-up page (WebDriver for chromium)",
    ),
    Pkg {
        debian_only: true,
        ..pkg("firefox-esr", "browser test of the set-up page in Firefox")
    },
    pkg(
        "xvfb",
        "virtual X display for the Firefox test (WebGL without a GPU)",
    ),
];

const BB_WHY: &str = "host tool BitBake needs (yocto-bitbake phase)";
const BB_PY_WHY: &str = "Python module of OE's scripts (yocto-bitbake phase, yocto-check-layer)";

/// A machine set-up step beyond packages: checked first, done only when missing.
struct Step {
    what: &'static str,
    why: &'static str,
    present: fn() -> bool,
    /// Shell commands, run as root (idempotent themselves).
    script: &'static str,
    /// Only needed when setup runs as root (else the step is skipped).
    root_only: bool,
}

const STEPS: &[Step] = &[
    Step {
        what: "en_US.UTF-8 locale",
        why: "BitBake refuses to run without it",
        present: has_en_us_utf8,
        // Enabled in /etc/locale.gen (not just `localedef`), so a later locale-gen keeps it.
        script: "sed -i 's/^# *en_US.UTF-8 UTF-8/en_US.UTF-8 UTF-8/' /etc/locale.gen\n\
                 grep -q '^en_US.UTF-8 UTF-8' /etc/locale.gen || echo 'en_US.UTF-8 UTF-8' >> /etc/locale.gen\n\
                 locale-gen",
        root_only: false,
    },
    Step {
        what: crate::yocto::BITBAKE_USER,
        why: "unprivileged system user that runs BitBake when CI runs as root (BitBake refuses root)",
        present: has_bitbake_user,
        script: BITBAKE_USERADD,
        root_only: true,
    },
];

const BITBAKE_USERADD: &str = concat!(
    "id -u irtrack-yocto >/dev/null 2>&1 || useradd --system --create-home \\\n",
    "  --home-dir /var/lib/irtrack-yocto --shell /bin/sh \\\n",
    "  --comment 'irtrack BitBake runner (BitBake refuses root)' irtrack-yocto"
);

fn has_en_us_utf8() -> bool {
    Command::new("locale").arg("-a").output().is_ok_and(|o| {
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .any(|l| l.eq_ignore_ascii_case("en_US.utf8") || l.eq_ignore_ascii_case("en_US.UTF-8"))
    })
}

fn has_bitbake_user() -> bool {
    crate::yocto::bitbake_user_uid().is_some()
}

const PIP_PACKAGE: &str = "oelint-adv";
const PIP_WHY: &str = "lints the Yocto layer's BitBake recipes";

/// Python modules the interop tests import: (PyPI package, module to import, why).
const PY_MODULES: &[(&str, &str, &str)] = &[
    (
        "natnet",
        "natnet",
        "independent NatNet client for irtrackd's NatNet output (firmware/tests/natnet.rs)",
    ),
    (
        "mcap",
        "mcap",
        "independent MCAP reader for the recordings (testkit/py/check_mcap.py)",
    ),
    (
        "mcap-ros2-support",
        "mcap_ros2",
        "decodes the recordings' ROS 2 messages (testkit/py/check_mcap.py)",
    ),
    (
        "cyclonedds==11.0.1",
        "cyclonedds",
        "independent DDS (ROS 2's rmw_cyclonedds) subscribing to irtrackd's ROS 2 output (firmware/tests/ros2_dds.rs)",
    ),
    (
        "rosbags==0.11.9",
        "rosbags",
        "CDR decoding of ROS 2 messages without ROS for the DDS subscriber (firmware/tests/py/ros2_subscriber.py)",
    ),
    (
        "prometheus-client==0.26.0",
        "prometheus_client",
        "independent OpenMetrics parser for irtrackd's /metrics (firmware/tests/py/scrape_metrics.py)",
    ),
    (
        "eclipse-zenoh==1.10.2",
        "zenoh",
        "independent Zenoh subscriber of the cluster tests (docs/cluster.md)",
    ),
];

/// The PyPI packages of [`PY_MODULES`] whose module python3 cannot import.
fn missing_py_modules() -> Vec<&'static (&'static str, &'static str, &'static str)> {
    PY_MODULES
        .iter()
        .filter(|(_, module, _)| {
            !Command::new("python3")
                .args(["-c", &format!("import {module}")])
                .output()
                .is_ok_and(|o| o.status.success())
        })
        .collect()
}

/// Which kind of system we are on, from /etc/os-release.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Distro {
    DebianBookworm,
    /// Another Debian release: same package names, qemu new enough in main (not verified here).
    DebianOther(String),
    Ubuntu(String),
    Unknown(String),
}

fn detect_distro(os_release: &str) -> Distro {
    let field = |key: &str| {
        os_release.lines().find_map(|l| {
            l.strip_prefix(key)
                .and_then(|r| r.strip_prefix('='))
                .map(|v| v.trim().trim_matches('"').to_string())
        })
    };
    let id = field("ID").unwrap_or_default();
    let codename = field("VERSION_CODENAME").unwrap_or_default();
    match id.as_str() {
        "debian" if codename == "bookworm" => Distro::DebianBookworm,
        "debian" => Distro::DebianOther(codename),
        "ubuntu" => Distro::Ubuntu(codename),
        other => Distro::Unknown(other.to_string()),
    }
}

/// Installed version of a package, if dpkg says it is installed ("ii").
fn installed_version(name: &str) -> Option<String> {
    let out = Command::new("dpkg-query")
        .args(["-W", "-f=${db:Status-Abbrev}|${Version}", name])
        .output()
        .ok()?;
    parse_dpkg_query(&String::from_utf8_lossy(&out.stdout))
}

fn parse_dpkg_query(out: &str) -> Option<String> {
    let (status, version) = out.trim_end().split_once('|')?;
    (status.trim() == "ii").then(|| version.to_string())
}

/// The package is present and, on bookworm, a backports package really comes from there.
fn satisfied(pkg: &Pkg, distro: &Distro) -> bool {
    match installed_version(pkg.name) {
        None => false,
        Some(v) => !(pkg.backports && *distro == Distro::DebianBookworm && !v.contains("bpo")),
    }
}

/// Finds `oelint-adv` on PATH or in pip's --user location.
pub fn oelint_adv() -> Option<PathBuf> {
    util::find_on_path(PIP_PACKAGE).or_else(|| {
        let home = std::env::var_os("HOME")?;
        let p = Path::new(&home).join(".local/bin").join(PIP_PACKAGE);
        p.is_file().then_some(p)
    })
}

fn has_pip() -> bool {
    Command::new("python3")
        .args(["-m", "pip", "--version"])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// How privileged commands are run.
enum Privilege {
    Root,
    Sudo,
    /// Neither: print the commands for the user.
    None,
}

fn privilege() -> Privilege {
    if util::is_root() {
        return Privilege::Root;
    }
    let sudo_ok = util::on_path("sudo")
        && Command::new("sudo")
            .args(["-n", "true"])
            .stdin(std::process::Stdio::null())
            .output()
            .is_ok_and(|o| o.status.success());
    if sudo_ok { Privilege::Sudo } else { Privilege::None }
}

/// A privileged shell command; kept as text so it can also be printed for the user.
fn privileged(script: &str, how: &Privilege) -> Command {
    let mut cmd = match how {
        Privilege::Sudo => {
            let mut c = Command::new("sudo");
            c.args(["-n", "sh", "-c"]);
            c
        }
        _ => {
            let mut c = Command::new("sh");
            c.arg("-c");
            c
        }
    };
    cmd.arg(script);
    cmd
}

pub fn run(_ctx: &util::Ctx) -> Result<()> {
    let os_release = std::fs::read_to_string("/etc/os-release").unwrap_or_default();
    let distro = detect_distro(&os_release);
    let has_apt = util::on_path("apt-get") && util::on_path("dpkg-query");

    let wanted: Vec<&Pkg> = PACKAGES
        .iter()
        .filter(|p| !(p.debian_only && matches!(distro, Distro::Ubuntu(_))))
        .collect();

    if !has_apt {
        print_manual_instructions(&wanted);
        bail!("no apt-get/dpkg on this machine: install the packages above by hand, then re-run");
    }

    let mut missing: Vec<&Pkg> = wanted
        .iter()
        .copied()
        .filter(|p| !satisfied(p, &distro))
        .collect();
    let need_pip_pkg = oelint_adv().is_none();
    let py_missing = missing_py_modules();
    let pip_missing = (need_pip_pkg || !py_missing.is_empty()) && !has_pip();
    let pip3 = Pkg {
        name: "python3-pip",
        why: "pip, to install oelint-adv from PyPI",
        ..pkg("", "")
    };
    if pip_missing {
        missing.push(&pip3);
    }

    let root = util::is_root();
    let steps: Vec<&Step> = STEPS
        .iter()
        .filter(|s| (root || !s.root_only) && !(s.present)())
        .collect();

    if missing.is_empty() && !need_pip_pkg && py_missing.is_empty() && steps.is_empty() {
        println!(
            "setup: all {} system packages, {PIP_PACKAGE} and the BitBake prerequisites are \
             present; nothing to install",
            wanted.len()
        );
        return Ok(());
    }

    println!("setup: distribution: {distro:?}");
    if !missing.is_empty() {
        println!("setup: installing {} missing system package(s):", missing.len());
        for p in &missing {
            println!("  {:<28} {}", p.name, p.why);
        }
        let new_entry = backports_entry(&missing, &distro)?;
        let script = apt_script(&missing, &distro, new_entry.as_ref());
        let how = privilege();
        if let Privilege::None = how {
            println!("\nsetup: not root and `sudo -n` is not available. Run as root:\n\n{script}\n");
            bail!("missing system packages (see the commands above)");
        }
        let mut cmd = privileged(&script, &how);
        let out = util::run(&mut cmd, RunOpts::default())?;
        if !out.success() {
            bail!(
                "installing system packages failed: `{}` {}",
                script.replace('\n', "; "),
                out.describe()
            );
        }
        if let Distro::Ubuntu(_) = distro {
            ubuntu_rust_target()?;
        }
    }
    if !steps.is_empty() {
        run_steps(&steps)?;
    }
    if need_pip_pkg {
        install_oelint()?;
    }
    for (package, _, why) in &py_missing {
        println!("setup: installing {package} from PyPI: {why}");
        pip_install(package)?;
    }
    println!("setup: done");
    Ok(())
}

/// On Debian 12, when a backports package is missing: the apt entry to add for the suite (None
/// when it is configured already), explaining what is done.
fn backports_entry(missing: &[&Pkg], distro: &Distro) -> Result<Option<NewEntry>> {
    if *distro != Distro::DebianBookworm || !missing.iter().any(|p| p.backports) {
        return Ok(None);
    }
    let etc_apt = Path::new("/etc/apt");
    let all = sources::read_all(etc_apt);
    match sources::plan_backports(&all, "bookworm", &etc_apt.join("sources.list.d"))? {
        Backports::Configured(file) => {
            println!(
                "setup: bookworm-backports is configured already ({})",
                file.display()
            );
            Ok(None)
        }
        Backports::Add(entry) => {
            println!(
                "setup: qemu comes from bookworm-backports, which apt does not list yet: writing \
                 {} with the mirror of this machine's `bookworm` entry ({}, from {})",
                entry.file.display(),
                entry.uri,
                entry.from.display()
            );
            Ok(Some(entry))
        }
    }
}

/// The shell commands that install `missing` (idempotent: each step checks first).
/// `backports` is the apt entry to write first, if any.
fn apt_script(missing: &[&Pkg], distro: &Distro, backports: Option<&NewEntry>) -> String {
    let mut lines = vec![
        "set -e".to_string(),
        "export DEBIAN_FRONTEND=noninteractive".to_string(),
    ];
    if missing.iter().any(|p| p.name.ends_with(":arm64")) {
        lines.push(
            "dpkg --print-foreign-architectures | grep -qx arm64 || dpkg --add-architecture arm64".into(),
        );
    }
    let bookworm = *distro == Distro::DebianBookworm;
    let (bpo, main): (Vec<&&Pkg>, Vec<&&Pkg>) = missing.iter().partition(|p| p.backports && bookworm);
    if let (false, Some(entry)) = (bpo.is_empty(), backports) {
        // A quoted here-document: the text is written exactly, nothing in it is expanded.
        lines.push(format!(
            "cat > {} <<'IRTRACK_APT_EOF'\n{}IRTRACK_APT_EOF",
            util::shell_quote(&entry.file.to_string_lossy()),
            entry.text
        ));
    }
    lines.push("apt-get update".into());
    let names = |v: &[&&Pkg]| v.iter().map(|p| p.name).collect::<Vec<_>>().join(" ");
    if !main.is_empty() {
        lines.push(format!("apt-get install -y {}", names(&main)));
    }
    if !bpo.is_empty() {
        lines.push(format!(
            "apt-get install -y -t bookworm-backports {}",
            names(&bpo)
        ));
    }
    lines.join("\n")
}

/// Runs the missing set-up steps (after the packages they need are installed).
fn run_steps(steps: &[&Step]) -> Result<()> {
    println!("setup: {} set-up step(s) missing:", steps.len());
    for s in steps {
        println!("  {:<28} {}", s.what, s.why);
    }
    let script = std::iter::once("set -e")
        .chain(steps.iter().map(|s| s.script))
        .collect::<Vec<_>>()
        .join("\n");
    let how = privilege();
    if let Privilege::None = how {
        println!("\nsetup: not root and `sudo -n` is not available. Run as root:\n\n{script}\n");
        bail!("missing set-up steps (see the commands above)");
    }
    let out = util::run(&mut privileged(&script, &how), RunOpts::default())?;
    if !out.success() {
        bail!(
            "set-up steps failed: `{}` {}",
            script.replace('\n', "; "),
            out.describe()
        );
    }
    for s in steps {
        if !(s.present)() {
            bail!("set-up step `{}` ran but its check still fails", s.what);
        }
    }
    Ok(())
}

/// Ubuntu has no rustc-web / arm64 std package in the same archive; rustup can provide the
/// aarch64 std there (not verified on this project's machines, which are Debian).
fn ubuntu_rust_target() -> Result<()> {
    println!(
        "setup: Ubuntu: the aarch64 standard library comes from rustup here \
         (Debian's rustc-web is not available); running `rustup target add aarch64-unknown-linux-gnu`"
    );
    let out = util::run(
        Command::new("rustup").args(["target", "add", "aarch64-unknown-linux-gnu"]),
        RunOpts::default(),
    )?;
    if !out.success() {
        bail!("`rustup target add aarch64-unknown-linux-gnu` {}", out.describe());
    }
    Ok(())
}

fn install_oelint() -> Result<()> {
    println!("setup: installing {PIP_PACKAGE} from PyPI: {PIP_WHY}");
    pip_install(PIP_PACKAGE)
}

/// `pip install PACKAGE`, for this user when the system Python is externally managed.
fn pip_install(package: &str) -> Result<()> {
    let base = ["-m", "pip", "install", "--disable-pip-version-check", package];
    let out = util::run(
        Command::new("python3").args(base),
        RunOpts {
            capture_stderr: true,
            ..RunOpts::default()
        },
    )?;
    if out.success() {
        return Ok(());
    }
    if out.stderr.contains("externally-managed-environment") {
        // Debian's system Python refuses global installs; a --user install touches no
        // dpkg-owned file and lands in ~/.local/bin, where oelint_adv() looks.
        println!("setup: system Python is externally managed; installing for this user instead");
        let out = util::run(
            Command::new("python3")
                .args(base)
                .args(["--user", "--break-system-packages"]),
            RunOpts::default(),
        )?;
        if out.success() {
            return Ok(());
        }
        bail!("`pip install --user {package}` {}", out.describe());
    }
    bail!("`python3 -m pip install {package}` {}", out.describe())
}

fn print_manual_instructions(wanted: &[&Pkg]) {
    println!("setup: this machine has no apt-get. The project needs these Debian packages (or equivalents):");
    for p in wanted {
        let src = if p.backports {
            " (Debian 12: from bookworm-backports)"
        } else {
            ""
        };
        println!("  {:<28} {}{src}", p.name, p.why);
    }
    println!("and from PyPI: {PIP_PACKAGE} ({PIP_WHY}).");
    for (package, _, why) in PY_MODULES {
        println!("and from PyPI: {package} ({why}).");
    }
    for s in STEPS {
        println!("Also: {} ({}):\n{}\n", s.what, s.why, s.script);
    }
    println!(
        "Exact commands on Debian 12 (MIRROR: the URI of your `bookworm` apt entry, if \
         bookworm-backports is not configured yet):\n"
    );
    let all: Vec<&Pkg> = wanted.to_vec();
    let entry = NewEntry {
        file: "/etc/apt/sources.list.d/bookworm-backports.list".into(),
        text: "deb MIRROR bookworm-backports main\n".into(),
        uri: "MIRROR".into(),
        from: PathBuf::new(),
    };
    println!(
        "{}\npython3 -m pip install {PIP_PACKAGE}\n",
        apt_script(&all, &Distro::DebianBookworm, Some(&entry))
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distro_detection() {
        let deb = "PRETTY_NAME=\"Debian GNU/Linux 12 (bookworm)\"\nID=debian\nVERSION_CODENAME=bookworm\n";
        assert_eq!(detect_distro(deb), Distro::DebianBookworm);
        let trixie = "ID=debian\nVERSION_CODENAME=trixie\n";
        assert_eq!(detect_distro(trixie), Distro::DebianOther("trixie".into()));
        let ubuntu = "ID=ubuntu\nID_LIKE=debian\nVERSION_CODENAME=noble\n";
        assert_eq!(detect_distro(ubuntu), Distro::Ubuntu("noble".into()));
        assert_eq!(detect_distro(""), Distro::Unknown(String::new()));
    }

    #[test]
    fn bitbake_user_step_creates_the_user_the_phase_runs_as() {
        let user = crate::yocto::BITBAKE_USER;
        assert!(BITBAKE_USERADD.starts_with(&format!("id -u {user} ")));
        assert!(BITBAKE_USERADD.ends_with(&format!(" {user}")));
        // The locale step enables the locale persistently before generating it.
        let locale = STEPS.iter().find(|s| s.what.contains("locale")).unwrap();
        let gen_at = locale.script.find("locale-gen").unwrap();
        assert!(locale.script[..gen_at].contains("/etc/locale.gen"));
    }

    #[test]
    fn dpkg_query_output() {
        assert_eq!(
            parse_dpkg_query("ii |1:10.0.2+ds-2~bpo12+1"),
            Some("1:10.0.2+ds-2~bpo12+1".into())
        );
        // Removed but config files left: not installed.
        assert_eq!(parse_dpkg_query("rc |1.0"), None);
        assert_eq!(parse_dpkg_query(""), None);
    }

    #[test]
    fn apt_script_for_bookworm_uses_backports_and_arm64() {
        let missing: Vec<&Pkg> = PACKAGES.iter().collect();
        let entry = NewEntry {
            file: "/etc/apt/sources.list.d/bookworm-backports.sources".into(),
            text: "Types: deb\nURIs: http://m.example.invalid/debian\nSuites: bookworm-backports\n".into(),
            uri: "http://m.example.invalid/debian".into(),
            from: "/etc/apt/sources.list.d/debian.sources".into(),
        };
        let s = apt_script(&missing, &Distro::DebianBookworm, Some(&entry));
        assert!(s.contains("dpkg --add-architecture arm64"));
        assert!(s.contains(
            "cat > /etc/apt/sources.list.d/bookworm-backports.sources <<'IRTRACK_APT_EOF'\n\
             Types: deb\nURIs: http://m.example.invalid/debian\nSuites: bookworm-backports\n\
             IRTRACK_APT_EOF\napt-get update\n"
        ));
        // The entry is written before apt-get update reads it.
        let without = apt_script(&missing, &Distro::DebianBookworm, None);
        assert!(!without.contains("IRTRACK_APT_EOF"));
        assert!(s.contains("apt-get install -y -t bookworm-backports qemu-user qemu-system-arm"));
        let main_line = s
            .lines()
            .find(|l| l.starts_with("apt-get install -y rustc-web"))
            .unwrap();
        assert!(!main_line.contains("qemu-user") && !main_line.contains("qemu-system-arm"));
        assert!(main_line.contains("libstd-rust-web-dev:arm64"));
    }

    #[test]
    fn apt_script_without_arm64_or_backports_needs() {
        let clang = PACKAGES.iter().find(|p| p.name == "clang").unwrap();
        let s = apt_script(&[clang], &Distro::DebianBookworm, None);
        assert!(!s.contains("add-architecture"));
        assert!(!s.contains("backports"));
        assert!(s.ends_with("apt-get install -y clang"));
        // Outside bookworm qemu comes from the main archive.
        let qemu = PACKAGES.iter().find(|p| p.name == "qemu-user").unwrap();
        let s = apt_script(&[qemu], &Distro::DebianOther("trixie".into()), None);
        assert!(s.ends_with("apt-get install -y qemu-user"));
    }
}
