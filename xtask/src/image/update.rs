//! A/B field updates of the CI images with RAUC (docs/updates.md): the update tools copied from
//! Debian's packages of the board's architecture (arm64 for the aarch64 image, armhf for the
//! armv7 one) into the busybox root file system (RAUC, D-Bus for its service,
//! fw_printenv/fw_setenv for U-Boot's boot counters, and every shared library they need), the
//! boot partition with `boot.scr` and the counters, the data partition, the update CA and
//! signed bundles.

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};

use super::{Variant, bootenv, find_deb, fresh_dir, run_quiet};
use crate::cross::Arch;
use crate::util::Ctx;

/// The aarch64 image's board type in RAUC's `system.conf` and in every bundle's manifest: RAUC
/// refuses a bundle made for another board. (The armv7 image's is
/// [`super::armv7::COMPATIBLE`].)
pub const COMPATIBLE: &str = "irtrack-qemu-arm64";
/// Boot partition (boot.scr and the boot counters only: kernels live in the slots).
pub const BOOT_MIB: u64 = 16;
/// Each root file system slot: room for a future system larger than today's (~160 MiB).
pub const SLOT_MIB: u64 = 256;
/// The data partition: parameter sets, tuning, RAUC's status, a downloaded bundle.
pub const DATA_MIB: u64 = 192;

/// Debian packages (the same names for arm64 and armhf) whose files the image carries: RAUC,
/// dbus-daemon (RAUC's command line talks
/// to `rauc service` over D-Bus), libubootenv's fw_printenv/fw_setenv, and the packages of the
/// shared libraries they load. [`install_tools`] resolves the libraries by DT_NEEDED and fails
/// naming any that none of these packages provides.
const TOOL_DEBS: &[&str] = &[
    "rauc",
    "dbus-daemon",
    "libubootenv-tool",
    "libubootenv0.1",
    "libc6",
    "libgcc-s1",
    "libglib2.0-0",
    "libffi8",
    "libpcre2-8-0",
    "libmount1",
    "libblkid1",
    "libselinux1",
    "libjson-glib-1.0-0",
    "libssl3",
    "libcurl3-gnutls",
    "libbrotli1",
    "libgnutls30",
    "libgmp10",
    "libhogweed6",
    "libnettle8",
    "libidn2-0",
    "libunistring2",
    "libp11-kit0",
    "libtasn1-6",
    "libgssapi-krb5-2",
    "libk5crypto3",
    "libkrb5-3",
    "libkrb5support0",
    "libkeyutils1",
    "libcom-err2",
    "libldap-2.5-0",
    "libsasl2-2",
    "libnghttp2-14",
    "libpsl5",
    "librtmp1",
    "libssh2-1",
    "zlib1g",
    "libzstd1",
    "libfdisk1",
    "libuuid1",
    "libdbus-1-3",
    "libexpat1",
    "libapparmor1",
    "libaudit1",
    "libcap-ng0",
    "libsystemd0",
    "libcap2",
    "libgcrypt20",
    "libgpg-error0",
    "liblz4-1",
    "liblzma5",
];

/// The programs installed from those packages.
const TOOL_BINARIES: &[&str] = &[
    "usr/bin/rauc",
    "usr/bin/dbus-daemon",
    "usr/bin/fw_printenv",
    "usr/bin/fw_setenv",
];

/// Where Debian's libraries of `arch` live (the loader's built-in search path).
fn lib_dirs(arch: Arch) -> [&'static str; 2] {
    match arch {
        Arch::Aarch64 => ["lib/aarch64-linux-gnu", "usr/lib/aarch64-linux-gnu"],
        Arch::Armv7 => ["lib/arm-linux-gnueabihf", "usr/lib/arm-linux-gnueabihf"],
    }
}

/// The dynamic loader of `arch` (glibc's, hard-float for armhf).
fn loader(arch: Arch) -> &'static str {
    match arch {
        Arch::Aarch64 => "ld-linux-aarch64.so.1",
        Arch::Armv7 => "ld-linux-armhf.so.3",
    }
}

/// The kernel's file name in each slot's `/boot` (what the board's part of boot.cmd loads):
/// an arm64 `Image` (booti) or an ARM `zImage` (bootz).
pub fn kernel_file(arch: Arch) -> &'static str {
    match arch {
        Arch::Aarch64 => "Image",
        Arch::Armv7 => "zImage",
    }
}

/// Downloads the tool packages of `arch` into `work/dl` (what is not there yet) and extracts
/// them all into `dest` (once per set of package files).
pub fn fetch_tools(arch: Arch, work: &Path, dest: &Path) -> Result<PathBuf> {
    let dl = &work.join("dl");
    fs::create_dir_all(dl)?;
    let missing: Vec<&str> = TOOL_DEBS
        .iter()
        .copied()
        .filter(|name| find_deb(dl, name).is_none())
        .collect();
    if !missing.is_empty() {
        // One apt-get run for all of them: each run costs seconds of its own.
        match arch {
            Arch::Aarch64 => {
                let names: Vec<String> = missing.iter().map(|n| format!("{n}:arm64")).collect();
                super::apt_download(dl, &names.join(" "))?;
            }
            // armhf through the armv7 image's private apt state (no dpkg architecture added).
            Arch::Armv7 => super::armv7::download(work, &missing)?,
        }
    }
    let mut debs = Vec::new();
    for name in TOOL_DEBS {
        debs.push(find_deb(dl, name).with_context(|| format!("{name} .deb missing after download"))?);
    }
    let stamp_text: String = debs
        .iter()
        .filter_map(|d| d.file_name().map(|n| format!("{}\n", n.to_string_lossy())))
        .collect();
    let stamp = dest.join(".extracted-from");
    if fs::read_to_string(&stamp).is_ok_and(|s| s == stamp_text) {
        return Ok(dest.to_path_buf());
    }
    fresh_dir(dest)?;
    for deb in &debs {
        run_quiet(Command::new("dpkg-deb").arg("-x").arg(deb).arg(dest))?;
    }
    fs::write(&stamp, stamp_text)?;
    Ok(dest.to_path_buf())
}

/// The DT_NEEDED entries of an ELF file (`readelf -d`, which reads any architecture).
fn needed(elf: &Path) -> Result<Vec<String>> {
    let out = run_quiet(Command::new("readelf").arg("-d").arg(elf))
        .with_context(|| format!("reading the dynamic section of {}", elf.display()))?;
    Ok(parse_needed(&out))
}

fn parse_needed(readelf: &str) -> Vec<String> {
    readelf
        .lines()
        .filter(|l| l.contains("(NEEDED)"))
        .filter_map(|l| {
            let start = l.find('[')? + 1;
            let end = l[start..].find(']')? + start;
            Some(l[start..end].to_owned())
        })
        .collect()
}

/// Private directory of the dynamically linked tools and their libraries. Not /lib: the rest
/// of the image (busybox, irtrackd) is static, and a second glibc in the system library path
/// is something a static program's NSS or iconv code may pick up; kept apart, only these
/// tools see it.
pub const TOOLS_DIR: &str = "usr/lib/irtrack-update";

/// Copies the tools and every shared library they need (transitively) from the extracted
/// packages into [`TOOLS_DIR`] of the staged root file system, and puts a wrapper for each
/// tool in /usr/bin that starts it through the loader with that library path. Returns the
/// number of libraries.
pub fn install_tools(arch: Arch, pkgs: &Path, stage: &Path) -> Result<usize> {
    use std::os::unix::fs::PermissionsExt;
    let dir = stage.join(TOOLS_DIR);
    let mut queue: Vec<(PathBuf, String)> = Vec::new();
    for bin in TOOL_BINARIES {
        let name = Path::new(bin)
            .file_name()
            .context("tool without a file name")?
            .to_string_lossy()
            .into_owned();
        super::copy_file_mode(&pkgs.join(bin), &dir.join("bin").join(&name), 0o755)?;
        let wrapper = stage.join("usr/bin").join(&name);
        fs::write(&wrapper, wrapper_script(&name, arch))?;
        fs::set_permissions(&wrapper, fs::Permissions::from_mode(0o755))?;
        queue.push((pkgs.join(bin), (*bin).to_owned()));
    }
    let mut seen = BTreeSet::new();
    while let Some((file, from)) = queue.pop() {
        for soname in needed(&file)? {
            if !seen.insert(soname.clone()) {
                continue;
            }
            let found = lib_dirs(arch)
                .iter()
                .map(|d| pkgs.join(d).join(&soname))
                .find(|p| p.exists())
                .with_context(|| {
                    format!("{soname} (needed by {from}) is in none of the image's update packages; add its package to TOOL_DEBS")
                })?;
            // Libraries are symlinks to versioned files in the packages; the image gets the file.
            let real = fs::canonicalize(&found)?;
            super::copy_file_mode(&real, &dir.join(&soname), 0o755)?;
            queue.push((real, soname));
        }
    }
    if !dir.join(loader(arch)).is_file() {
        bail!("the dynamic loader {} was not among the libraries", loader(arch));
    }
    Ok(seen.len())
}

/// /usr/bin/NAME: runs the tool through the loader with the private library path, which is
/// not passed on to the programs it starts (`--library-path`, unlike LD_LIBRARY_PATH).
/// `--argv0` keeps the name: fw_printenv and fw_setenv act by it.
fn wrapper_script(name: &str, arch: Arch) -> String {
    format!(
        "#!/bin/sh\n# {name} from Debian's {} package with its own libraries (xtask/src/image/update.rs).\n\
         exec /{TOOLS_DIR}/{} --library-path /{TOOLS_DIR} --argv0 {name} /{TOOLS_DIR}/bin/{name} \"$@\"\n",
        super::debian_arch(arch),
        loader(arch)
    )
}

/// The version and build written into `/etc/irtrack/release` and a bundle's manifest.
#[derive(Debug, Clone)]
pub struct Release {
    pub version: String,
    pub build: String,
}

impl Release {
    /// `IRTRACK_IMAGE_VERSION` or the workspace version; the build names the commit and date.
    pub fn current(ctx: &Ctx) -> Result<Self> {
        let version =
            std::env::var("IRTRACK_IMAGE_VERSION").unwrap_or_else(|_| env!("CARGO_PKG_VERSION").to_owned());
        check_version(&version)?;
        let git = |args: &[&str]| -> String {
            Command::new("git")
                .args(args)
                .current_dir(&ctx.root)
                .output()
                .ok()
                .filter(|o| o.status.success())
                .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
                .unwrap_or_default()
        };
        let mut commit = git(&["rev-parse", "--short=12", "HEAD"]);
        if commit.is_empty() {
            commit = "unknown".into();
        } else if !git(&["status", "--porcelain", "--untracked-files=no"]).is_empty() {
            commit.push_str("-dirty");
        }
        let date = run_quiet(Command::new("date").args(["-u", "+%Y%m%dT%H%M%SZ"]))?;
        Ok(Self {
            version,
            build: format!("{commit}.{}", date.trim()),
        })
    }

    /// The release file of an image for the board type `compatible`.
    pub fn file_text(&self, compatible: &str) -> String {
        format!(
            "# Written by `cargo xtask image build`; read by irtrack-health and RAUC's handlers.\nVERSION={}\nBUILD={}\nCOMPATIBLE={compatible}\n",
            self.version, self.build
        )
    }
}

/// Dotted numbers with an optional `+build` or `-pre` tail: what the board's downgrade check
/// (rauc-pre-install) compares.
pub fn check_version(v: &str) -> Result<()> {
    let core = v.split(['+', '-']).next().unwrap_or("");
    let ok = !core.is_empty()
        && core
            .split('.')
            .all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
        && v.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"+-.".contains(&b));
    if !ok {
        bail!("version {v:?} is not dotted numbers (e.g. 1.4.2, optionally +build)");
    }
    Ok(())
}

/// Writes `/etc/irtrack/release` into a staged root file system for the board type
/// `compatible`.
pub fn write_release(stage: &Path, release: &Release, compatible: &str) -> Result<()> {
    let path = stage.join("etc/irtrack/release");
    fs::write(&path, release.file_text(compatible)).with_context(|| format!("writing {}", path.display()))
}

/// Sets the board type in the staged `/etc/rauc/system.conf` (image/update/rootfs has the
/// aarch64 image's).
pub fn set_compatible(stage: &Path, compatible: &str) -> Result<()> {
    let path = stage.join("etc/rauc/system.conf");
    let text = fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let new = with_compatible(&text, compatible)
        .with_context(|| format!("{} has no compatible= line", path.display()))?;
    fs::write(&path, new).with_context(|| format!("writing {}", path.display()))
}

/// `system.conf` text with its `compatible=` line (in `[system]`) replaced.
fn with_compatible(text: &str, compatible: &str) -> Option<String> {
    let mut found = false;
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        if !found && line.trim_start().starts_with("compatible=") {
            found = true;
            out.push_str(&format!("compatible={compatible}"));
        } else {
            out.push_str(line);
        }
        out.push('\n');
    }
    found.then_some(out)
}

/// The update signing material on the PC: a CA (whose certificate the board trusts) and a
/// signing certificate issued by it. Made once by [`update_keys`] and kept, like the parameter
/// signing key: boards in the field trust the CA of the images they were flashed with.
pub struct UpdateKeys {
    pub ca_cert: PathBuf,
    pub signer_cert: PathBuf,
    pub signer_key: PathBuf,
}

/// `target/image/update-keys/` (or `IRTRACK_UPDATE_KEYS`): created with openssl if missing.
pub fn update_keys(work: &Path) -> Result<UpdateKeys> {
    let dir = match std::env::var_os("IRTRACK_UPDATE_KEYS") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => work.join("update-keys"),
    };
    make_ca(&dir, "irtrack update")
}

/// A CA and a signing certificate under `dir` (`ca.cert.pem`, `signer.{cert,key}.pem`), made
/// with openssl unless all three exist. Also used for the foreign CA of the refusal test.
pub fn make_ca(dir: &Path, name: &str) -> Result<UpdateKeys> {
    let keys = UpdateKeys {
        ca_cert: dir.join("ca.cert.pem"),
        signer_cert: dir.join("signer.cert.pem"),
        signer_key: dir.join("signer.key.pem"),
    };
    if keys.ca_cert.is_file() && keys.signer_cert.is_file() && keys.signer_key.is_file() {
        return Ok(keys);
    }
    fs::create_dir_all(dir)?;
    let ca_key = dir.join("ca.key.pem");
    // One openssl configuration for both steps: the CA may only sign certificates, the signer
    // only sign data. No extendedKeyUsage: RAUC verifies with OpenSSL's S/MIME signing purpose,
    // which refuses a codeSigning-only certificate ("unsuitable certificate purpose").
    fs::write(
        dir.join("openssl.cnf"),
        "[req]\ndistinguished_name=dn\n[dn]\n\
         [ca]\nbasicConstraints=critical,CA:TRUE\nkeyUsage=critical,keyCertSign,cRLSign\nsubjectKeyIdentifier=hash\n\
         [signer]\nbasicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n\
         subjectKeyIdentifier=hash\nauthorityKeyIdentifier=keyid\n",
    )?;
    let openssl =
        |args: &[&str]| -> Result<String> { run_quiet(Command::new("openssl").args(args).current_dir(dir)) };
    let ec = ["-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out"];
    openssl(&[&["genpkey"][..], &ec, &["ca.key.pem"]].concat())?;
    let ca_subject = format!("/O=irtrack/CN={name} CA");
    openssl(&[
        "req",
        "-new",
        "-x509",
        "-key",
        "ca.key.pem",
        "-out",
        "ca.cert.pem",
        "-days",
        "7300",
        "-subj",
        &ca_subject,
        "-config",
        "openssl.cnf",
        "-extensions",
        "ca",
    ])?;
    openssl(&[&["genpkey"][..], &ec, &["signer.key.pem"]].concat())?;
    let signer_subject = format!("/O=irtrack/CN={name} signer");
    openssl(&[
        "req",
        "-new",
        "-key",
        "signer.key.pem",
        "-out",
        "signer.csr",
        "-subj",
        &signer_subject,
        "-config",
        "openssl.cnf",
    ])?;
    openssl(&[
        "x509",
        "-req",
        "-in",
        "signer.csr",
        "-CA",
        "ca.cert.pem",
        "-CAkey",
        "ca.key.pem",
        "-CAcreateserial",
        "-out",
        "signer.cert.pem",
        "-days",
        "3650",
        "-extfile",
        "openssl.cnf",
        "-extensions",
        "signer",
    ])?;
    for f in ["signer.csr", "ca.cert.srl"] {
        let _ = fs::remove_file(dir.join(f));
    }
    if !ca_key.is_file() {
        bail!("openssl wrote no {}", ca_key.display());
    }
    Ok(keys)
}

/// The initial boot counters: slot A first with all its attempts; slot B is empty until the
/// first update, so it is neither in BOOT_ORDER nor given attempts. Both copies of the
/// redundant environment (bootenv.rs) hold them; copy 0 is the newer (flags 1 against 0).
/// Returns the two files, copy 0 first.
pub fn initial_env(work: &Path) -> Result<[PathBuf; 2]> {
    let vars = [("BOOT_ORDER", "A"), ("BOOT_A_LEFT", "3"), ("BOOT_B_LEFT", "0")];
    let mut out = [PathBuf::new(), PathBuf::new()];
    for (i, name) in bootenv::COPY_FILES.iter().enumerate() {
        let path = work.join(name);
        let flags = if i == 0 { 1 } else { 0 };
        fs::write(&path, bootenv::encode(&vars, flags)?)
            .with_context(|| format!("writing {}", path.display()))?;
        out[i] = path;
    }
    Ok(out)
}

/// boot.scr from the board's part ([`Variant::boot_board`], if any) followed by
/// image/update/boot.cmd, whose defaults are QEMU's arm64 virt machine.
pub fn boot_script(ctx: &Ctx, work: &Path, variant: &Variant) -> Result<PathBuf> {
    let scr = work.join("boot.scr");
    let generic = ctx.root.join("image/update/boot.cmd");
    let source = match variant.boot_board {
        None => generic,
        Some(board) => {
            let board = ctx.root.join(board);
            let mut text =
                fs::read_to_string(&board).with_context(|| format!("reading {}", board.display()))?;
            text.push('\n');
            text.push_str(
                &fs::read_to_string(&generic).with_context(|| format!("reading {}", generic.display()))?,
            );
            let joined = work.join("boot.cmd");
            fs::write(&joined, text)?;
            joined
        }
    };
    let mkimage_arch = match variant.arch {
        Arch::Aarch64 => "arm64",
        Arch::Armv7 => "arm",
    };
    run_quiet(
        Command::new("mkimage")
            .args([
                "-A",
                mkimage_arch,
                "-O",
                "linux",
                "-T",
                "script",
                "-C",
                "none",
                "-n",
                "irtrack A/B boot",
                "-d",
            ])
            .arg(&source)
            .arg(&scr),
    )
    .context("mkimage (u-boot-tools; run `cargo xtask setup`)")?;
    Ok(scr)
}

/// vfat boot partition of the A/B image: boot.scr and the two copies of the boot counters.
pub fn make_boot_partition(out: &Path, boot_scr: &Path, env: &[PathBuf; 2]) -> Result<u64> {
    let _ = fs::remove_file(out);
    run_quiet(
        Command::new("mkfs.vfat")
            .args(["-C", "-n", "IRTRACKBOOT"])
            .arg(out)
            .arg((BOOT_MIB * 1024).to_string()),
    )?;
    let img = out.to_string_lossy().into_owned();
    let mut files = vec![(boot_scr.to_path_buf(), "::/boot.scr".to_owned())];
    for (path, name) in env.iter().zip(bootenv::COPY_FILES) {
        files.push((path.clone(), format!("::/{name}")));
    }
    for (src, dest) in files {
        run_quiet(Command::new("mcopy").args(["-i", &img]).arg(src).arg(dest))?;
    }
    Ok(BOOT_MIB << 20)
}

/// The data partition: empty directories for irtrackd's state and RAUC's status.
pub fn make_data_partition(work: &Path, out: &Path) -> Result<u64> {
    let stage = work.join("data");
    fresh_dir(&stage)?;
    fs::create_dir_all(stage.join("irtrackd"))?;
    fs::create_dir_all(stage.join("rauc"))?;
    let _ = fs::remove_file(out);
    run_quiet(
        Command::new("mke2fs")
            .args([
                "-q",
                "-F",
                "-t",
                "ext4",
                "-L",
                "irtrack-data",
                "-E",
                "root_owner=0:0",
                "-d",
            ])
            .arg(&stage)
            .arg(out)
            .arg(format!("{DATA_MIB}M")),
    )?;
    Ok(DATA_MIB << 20)
}

/// A signed RAUC bundle for the board type `compatible`, holding `rootfs_ext4` as the image of
/// the `rootfs` slot class.
pub fn make_bundle_for(
    work: &Path,
    rootfs_ext4: &Path,
    release: &Release,
    keys: &UpdateKeys,
    compatible: &str,
    out: &Path,
) -> Result<()> {
    check_version(&release.version)?;
    let dir = work.join(format!(
        "bundle-{}",
        out.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    ));
    fresh_dir(&dir)?;
    // A hard link where possible: the image can be a few hundred MiB.
    let image = dir.join("rootfs.ext4");
    if fs::hard_link(rootfs_ext4, &image).is_err() {
        fs::copy(rootfs_ext4, &image)?;
    }
    fs::write(
        dir.join("manifest.raucm"),
        format!(
            "[update]\ncompatible={compatible}\nversion={}\nbuild={}\ndescription=irtrack appliance root file system\n\n\
             [bundle]\nformat=plain\n\n[image.rootfs]\nfilename=rootfs.ext4\n",
            release.version, release.build
        ),
    )?;
    let _ = fs::remove_file(out);
    run_quiet(
        Command::new("rauc")
            .arg("bundle")
            // lz4: several times faster to make than the default gzip on the PC and to unpack
            // on the board (QEMU's emulated CPU); the bundle is about a third larger.
            .arg("--mksquashfs-args=-comp lz4")
            .arg("--cert")
            .arg(&keys.signer_cert)
            .arg("--key")
            .arg(&keys.signer_key)
            .arg("--keyring")
            .arg(&keys.ca_cert)
            .arg(&dir)
            .arg(out),
    )
    .context("rauc bundle (Debian's rauc and squashfs-tools; run `cargo xtask setup`)")?;
    fs::remove_dir_all(&dir)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn needed_entries_are_read_from_readelf_output() {
        let out = "Dynamic section at offset 0x5d6e8 contains 31 entries:\n  Tag        Type                         Name/Value\n \
                   0x0000000000000001 (NEEDED)             Shared library: [libglib-2.0.so.0]\n \
                   0x0000000000000001 (NEEDED)             Shared library: [libc.so.6]\n \
                   0x000000000000000e (SONAME)             Library soname: [librauc.so]\n";
        assert_eq!(parse_needed(out), vec!["libglib-2.0.so.0", "libc.so.6"]);
        assert!(parse_needed("not an ELF file").is_empty());
    }

    #[test]
    fn the_board_type_is_set_in_system_conf() {
        let conf = "[system]\ncompatible=irtrack-qemu-arm64\nbootloader=uboot\n\n[slot.rootfs.0]\ndevice=/dev/vda2\n";
        let armv7 = with_compatible(conf, "irtrack-qemu-armv7").unwrap();
        assert_eq!(
            armv7,
            "[system]\ncompatible=irtrack-qemu-armv7\nbootloader=uboot\n\n[slot.rootfs.0]\ndevice=/dev/vda2\n"
        );
        assert!(with_compatible("[system]\nbootloader=uboot\n", "x").is_none());
        // The repository's system.conf has the line this replaces.
        let repo = include_str!("../../../image/update/rootfs/etc/rauc/system.conf");
        let set = with_compatible(repo, "irtrack-qemu-armv7").unwrap();
        assert!(set.contains("\ncompatible=irtrack-qemu-armv7\n") && !set.contains("arm64"));
    }

    #[test]
    fn wrappers_start_the_architecture_loader() {
        let arm = wrapper_script("rauc", Arch::Armv7);
        assert!(
            arm.contains("exec /usr/lib/irtrack-update/ld-linux-armhf.so.3 --library-path /usr/lib/irtrack-update --argv0 rauc /usr/lib/irtrack-update/bin/rauc \"$@\""),
            "{arm}"
        );
        assert!(wrapper_script("fw_setenv", Arch::Aarch64).contains("/ld-linux-aarch64.so.1 "));
        assert_eq!(kernel_file(Arch::Armv7), "zImage");
    }

    #[test]
    fn versions_must_be_dotted_numbers() {
        for ok in ["1", "0.1.0", "1.4.2+20261128", "2.0.0-rc1"] {
            check_version(ok).unwrap();
        }
        for bad in ["", "v1.0", "1..2", "1.0 beta", "1.0;rm"] {
            let err = check_version(bad).unwrap_err().to_string();
            assert!(err.contains("dotted numbers"), "{bad}: {err}");
        }
    }
}
