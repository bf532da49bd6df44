//! The A/B update test (`cargo xtask image update-test` and `cargo xtask image armv7
//! update-test`, CI opt-in phases `image-update` and `image-update-armv7`): boots a fresh copy
//! of the image in QEMU (`qemu-system-aarch64` or `qemu-system-arm`, by the image's
//! architecture) and, through the console shell and irtrackd's forwarded ports, installs RAUC
//! bundles that the guest downloads from a small HTTP server on the host (10.0.2.2 under QEMU
//! user networking). The same checks run on both images; docs/updates.md lists them.

use std::fs;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use super::bootenv;
use super::checks::{
    check_params_used, get_status, make_params, push_params, rig_id_of, set_operator_password,
};
use super::qemu::{BOOT_TIMEOUT, Qemu, free_ports, qemu_command_for};
use super::system::Report;
use super::update::{self, Release, UpdateKeys};
use super::{AB_VARIANTS, Image, image_dir, work_dir};
use crate::cross::Arch;
use crate::util::{Ctx, json};

/// The guest's health timeout in this test (a board's default is 120 s): a broken slot
/// reboots this long after its start, three times, before U-Boot falls back.
const HEALTH_TIMEOUT_S: u64 = 30;
/// Installing a bundle in QEMU (download from the host, signature check, copy into the slot).
const INSTALL_TIMEOUT: Duration = Duration::from_secs(300);

/// Serves the files of one directory over HTTP/1.0 GET until the process ends (the thread
/// is detached; the listener closes with the test).
fn serve_dir(dir: PathBuf) -> Result<u16> {
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?;
    let port = listener.local_addr()?.port();
    thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let dir = dir.clone();
            thread::spawn(move || {
                let _ = serve_one(stream, &dir);
            });
        }
    });
    Ok(port)
}

fn serve_one(mut stream: TcpStream, dir: &Path) -> Result<()> {
    stream.set_read_timeout(Some(Duration::from_secs(30)))?;
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut request = String::new();
    reader.read_line(&mut request)?;
    loop {
        let mut header = String::new();
        if reader.read_line(&mut header)? == 0 || header.trim().is_empty() {
            break;
        }
    }
    let name = request
        .split_whitespace()
        .nth(1)
        .unwrap_or("")
        .trim_start_matches('/');
    let path = dir.join(name);
    if name.is_empty() || name.contains('/') || name.contains("..") || !path.is_file() {
        stream.write_all(b"HTTP/1.0 404 Not Found\r\nContent-Length: 0\r\n\r\n")?;
        return Ok(());
    }
    let mut file = fs::File::open(&path)?;
    let len = file.metadata()?.len();
    stream.write_all(
        format!("HTTP/1.0 200 OK\r\nContent-Type: application/octet-stream\r\nContent-Length: {len}\r\n\r\n")
            .as_bytes(),
    )?;
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        stream.write_all(&buf[..n])?;
    }
    Ok(())
}

/// `X.Y.Z` → `X.Y.(Z+step)`.
fn bump(version: &str, step: u64) -> Result<String> {
    let core = version.split(['+', '-']).next().unwrap_or("");
    let (head, last) = core.rsplit_once('.').unwrap_or(("", core));
    let n: u64 = last
        .parse()
        .with_context(|| format!("version {version:?} does not end in a number"))?;
    Ok(if head.is_empty() {
        format!("{}", n + step)
    } else {
        format!("{head}.{}", n + step)
    })
}

/// The running image's release, read from the staged root file system of the last build.
fn image_release(work: &Path) -> Result<Release> {
    let text = fs::read_to_string(work.join("rootfs/etc/irtrack/release"))
        .context("no rootfs/etc/irtrack/release from the last build; run `cargo xtask image build`")?;
    let field = |k: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("{k}=")))
            .map(str::to_owned)
            .with_context(|| format!("release file without {k}"))
    };
    Ok(Release {
        version: field("VERSION")?,
        build: field("BUILD")?,
    })
}

/// A root file system image made from the last build's staged tree, with its release file
/// set to `release` (for the board type `compatible`) and `tweak` applied to a copy of the tree.
fn rootfs_variant(
    work: &Path,
    name: &str,
    release: &Release,
    compatible: &str,
    tweak: impl Fn(&Path) -> Result<()>,
) -> Result<PathBuf> {
    let stage = work.join(format!("rootfs-{name}"));
    if stage.exists() {
        fs::remove_dir_all(&stage)?;
    }
    let cp = Command::new("cp")
        .arg("-a")
        .arg(work.join("rootfs"))
        .arg(&stage)
        .status()?;
    if !cp.success() {
        bail!("copying the staged root file system to {}", stage.display());
    }
    update::write_release(&stage, release, compatible)?;
    tweak(&stage)?;
    let out = work.join(format!("rootfs-{name}.ext4"));
    super::make_root_partition(&out, &stage)?;
    fs::remove_dir_all(&stage)?;
    Ok(out)
}

/// The board type of the other A/B image (the armv7 one for the aarch64 image and the other
/// way round): its bundles must be refused here.
fn other_board(compatible: &str) -> Result<&'static str> {
    AB_VARIANTS
        .iter()
        .map(|v| v.compatible)
        .find(|c| *c != compatible)
        .with_context(|| format!("no A/B image other than {compatible:?}"))
}

/// Makes good.raucb, broken.raucb, foreign.raucb, older.raucb, other-board.raucb (for the
/// other A/B image's board type) and truncated.raucb for the board type `compatible`; returns
/// the good and the broken version and the seconds it took.
fn make_bundles(
    work: &Path,
    dir: &Path,
    base: &Release,
    keys: &UpdateKeys,
    compatible: &str,
) -> Result<(String, String, f64)> {
    let t0 = Instant::now();
    fs::create_dir_all(dir)?;
    let good = Release {
        version: bump(&base.version, 1)?,
        build: format!("{}.update-test", base.build),
    };
    let broken = Release {
        version: bump(&base.version, 2)?,
        build: format!("{}.broken", base.build),
    };
    let good_fs = rootfs_variant(work, "good", &good, compatible, |_| Ok(()))?;
    // irtrackd that cannot start: the supervisor restarts it forever, /status never answers.
    let broken_fs = rootfs_variant(work, "broken", &broken, compatible, |stage| {
        let bin = stage.join("usr/bin/irtrackd");
        fs::write(
            &bin,
            "#!/bin/sh\necho 'irtrackd: this build is broken on purpose (update test)' >&2\nexit 1\n",
        )?;
        Ok(())
    })?;
    let bundle = |fs: &Path, release: &Release, keys: &UpdateKeys, name: &str| {
        update::make_bundle_for(work, fs, release, keys, compatible, &dir.join(name))
    };
    bundle(&good_fs, &good, keys, "good.raucb")?;
    bundle(&broken_fs, &broken, keys, "broken.raucb")?;
    // Signed by a CA the board does not trust.
    let foreign = update::make_ca(&work.join("update-test-foreign-ca"), "someone else")?;
    bundle(&good_fs, &good, &foreign, "foreign.raucb")?;
    // Older than the running system.
    let older = Release {
        version: "0.0.0".into(),
        build: format!("{}.old", base.build),
    };
    if update::check_version(&base.version).is_err() || base.version.split(['+', '-']).next() == Some("0.0.0")
    {
        bail!(
            "the image's version {} leaves no room for an older bundle",
            base.version
        );
    }
    bundle(&good_fs, &older, keys, "older.raucb")?;
    // For the other A/B image's board, signed by the same CA (one CA signs for every board):
    // only the compatible string tells the board it is not meant for it.
    update::make_bundle_for(
        work,
        &good_fs,
        &good,
        keys,
        other_board(compatible)?,
        &dir.join("other-board.raucb"),
    )?;
    // Cut short, as an interrupted download leaves it.
    let whole = fs::read(dir.join("good.raucb"))?;
    fs::write(dir.join("truncated.raucb"), &whole[..whole.len() / 2])?;
    for f in [good_fs, broken_fs] {
        let _ = fs::remove_file(f);
    }
    Ok((good.version, broken.version, t0.elapsed().as_secs_f64()))
}

/// Boots and waits for irtrackd's ready line and the health check's verdict on the slot.
fn wait_healthy(q: &mut Qemu, from: usize, slot: &str) -> Result<f64> {
    let t0 = Instant::now();
    q.wait_for("irtrackd ready", from, BOOT_TIMEOUT)?;
    q.wait_for(
        &format!("irtrack-health: slot {slot} healthy"),
        from,
        BOOT_TIMEOUT,
    )?;
    Ok(t0.elapsed().as_secs_f64())
}

/// A console command's output with irtrackd's interleaved log lines left out.
fn console_clean(q: &mut Qemu, cmd: &str, timeout: Duration) -> Result<String> {
    let out = q.console(cmd, timeout)?;
    Ok(out
        .lines()
        .filter(|l| !l.contains(" INFO ") && !l.contains(" WARN ") && !l.starts_with("irtrack-"))
        .collect::<Vec<_>>()
        .join("\n"))
}

/// `key=value` from a console command's output.
fn value_of(out: &str, key: &str) -> Option<String> {
    out.lines()
        .find_map(|l| l.trim().strip_prefix(&format!("{key}=")))
        .map(str::to_owned)
}

/// Downloads a bundle into the guest and installs it; returns (exit status, output, seconds).
fn install(q: &mut Qemu, http_port: u16, name: &str) -> Result<(i32, String, f64)> {
    let t0 = Instant::now();
    let out = q.console(
        &format!(
            "rm -f /data/update.raucb; wget -q -O /data/update.raucb http://10.0.2.2:{http_port}/{name}.raucb; echo wget=$?; \
             rauc install /data/update.raucb 2>&1; echo rc=$?; rm -f /data/update.raucb"
        ),
        INSTALL_TIMEOUT,
    )?;
    let secs = t0.elapsed().as_secs_f64();
    if value_of(&out, "wget").as_deref() != Some("0") {
        bail!("the guest could not download {name}.raucb from the host: {out}");
    }
    let rc = value_of(&out, "rc")
        .and_then(|v| v.parse().ok())
        .with_context(|| format!("no exit status from rauc install: {out}"))?;
    Ok((rc, out, secs))
}

/// The boot counters and pending update, as the board sees them.
fn boot_state(q: &mut Qemu) -> Result<String> {
    let out = console_clean(
        q,
        "fw_printenv BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT; echo pending=$(cat /data/rauc/pending 2>/dev/null)",
        Duration::from_secs(20),
    )?;
    Ok(["BOOT_ORDER", "BOOT_A_LEFT", "BOOT_B_LEFT", "pending"]
        .iter()
        .map(|k| format!("{k}={}", value_of(&out, k).unwrap_or_default()))
        .collect::<Vec<_>>()
        .join(" "))
}

/// The booted slot (kernel command line) and the running release's version.
fn running(q: &mut Qemu) -> Result<(String, String)> {
    let out = console_clean(
        q,
        "echo slot=$(sed -n 's/.*rauc\\.slot=\\([AB]\\).*/\\1/p' /proc/cmdline); . /etc/irtrack/release; echo version=$VERSION",
        Duration::from_secs(20),
    )?;
    Ok((
        value_of(&out, "slot").unwrap_or_default(),
        value_of(&out, "version").unwrap_or_default(),
    ))
}

fn last_update(q: &mut Qemu) -> Result<String> {
    console_clean(q, "cat /data/rauc/last-update", Duration::from_secs(20))
}

fn rig_now(status_port: u16) -> Result<Option<String>> {
    let s = get_status(status_port)?;
    Ok(json::str_at(&s, "params.rig_id").map(str::to_owned))
}

/// What `host-tools update push --reboot` reported.
struct Pushed {
    /// Upload and install, as host-tools timed it.
    install_s: f64,
    /// From the reboot request to the new slot marked good, as host-tools timed it.
    reboot_s: f64,
    /// The whole command.
    total_s: f64,
    /// Its progress lines (standard error) and closing message.
    stderr: String,
    stdout: String,
}

/// The number just before `marker` in `text` ("... in 26.1 s; rebooted" → 26.1 for " s; rebooted").
fn number_before(text: &str, marker: &str) -> Option<f64> {
    let at = text.find(marker)?;
    text[..at].rsplit(' ').next()?.parse().ok()
}

/// `host-tools update push --reboot` against the forwarded status port, as an operator would
/// push from the PC: upload, install through the root agent, reboot, wait for the board.
fn push_with_reboot(ctx: &Ctx, dir: &Path, status_port: u16, bundle: &Path) -> Result<Pushed> {
    let pw = dir.join("operator-password");
    fs::write(&pw, format!("{}\n", crate::util::OPERATOR_PASSWORD))?;
    let t0 = Instant::now();
    let out = ctx
        .host_tools()
        .args(["update", "push", "--board"])
        .arg(format!("127.0.0.1:{status_port}"))
        .arg("--password-file")
        .arg(&pw)
        .args(["--reboot", "--reboot-timeout-s", "600"])
        .arg(bundle)
        .output()
        .context("running host-tools update push --reboot")?;
    let total_s = t0.elapsed().as_secs_f64();
    let stdout = String::from_utf8_lossy(&out.stdout).trim().to_owned();
    let stderr = String::from_utf8_lossy(&out.stderr).trim().to_owned();
    if !out.status.success() {
        bail!(
            "host-tools update push --reboot exited with {}: {stdout}\n{stderr}",
            out.status
        );
    }
    let install_s = number_before(&stdout, " s; rebooted")
        .with_context(|| format!("no install time in host-tools' answer: {stdout}"))?;
    let reboot_s = number_before(&stdout, " s after the reboot was asked for")
        .with_context(|| format!("no reboot time in host-tools' answer: {stdout}"))?;
    Ok(Pushed {
        install_s,
        reboot_s,
        total_s,
        stderr,
        stdout,
    })
}

/// `/status` → `system.running` as (slot, version) once it names `want_slot` (irtrackd reads
/// the slots from RAUC in the background after its start), or what it last said.
fn status_running(status_port: u16, want_slot: &str) -> Result<(String, String)> {
    let t0 = Instant::now();
    loop {
        let st = get_status(status_port)?;
        let field = |k: &str| {
            json::str_at(&st, &format!("system.running.{k}"))
                .unwrap_or("")
                .to_owned()
        };
        let got = (field("slot"), field("version"));
        if got.0 == want_slot || t0.elapsed() > Duration::from_secs(60) {
            return Ok(got);
        }
        thread::sleep(Duration::from_secs(1));
    }
}

/// Runs every update check on a fresh copy of `image`. Errors only for setup failures.
pub fn run(ctx: &Ctx, image: &Image) -> Result<Report> {
    if image.compatible.is_empty() {
        bail!(
            "{} has no A/B update layout (RAUC, slots A and B)",
            image.sd_img.display()
        );
    }
    let work = image_dir(ctx, image);
    let dir = work.join("update-test");
    fs::create_dir_all(&dir)?;
    let mut report = Report::default();
    let base = image_release(&work)?;
    // The CA every A/B image trusts (target/image/update-keys/, or IRTRACK_UPDATE_KEYS).
    let keys = update::update_keys(&work_dir(ctx))?;
    let bundle_dir = dir.join("bundles");
    let (good_version, broken_version, bundle_s) =
        make_bundles(&work, &bundle_dir, &base, &keys, image.compatible)?;
    let size = fs::metadata(bundle_dir.join("good.raucb"))?.len();
    report.figures.push(format!(
        "bundles made in {bundle_s:.0} s; good bundle {:.1} MiB (version {good_version})",
        size as f64 / (1 << 20) as f64
    ));
    let http_port = serve_dir(bundle_dir.clone())?;
    let params = make_params(ctx, &dir).and_then(|f| Ok((rig_id_of(ctx, &f)?, f)));

    let disk = dir.join("sd.img");
    let _ = fs::remove_file(&disk);
    let cp = Command::new("cp")
        .arg("--sparse=always")
        .arg(&image.sd_img)
        .arg(&disk)
        .status()?;
    if !cp.success() {
        bail!("copying the image to {}", disk.display());
    }
    let ports = free_ports::<4>()?;
    let [params_port, _, _, status_port] = ports;
    let mut q = Qemu::spawn(
        qemu_command_for(image.arch, &disk, &ports),
        &dir.join("serial-1.log"),
    )?;
    let test_start = Instant::now();

    // 1. First boot: slot A, marked good by the health check.
    let first = wait_healthy(&mut q, 0, "A").and_then(|s| {
        let (slot, version) = running(&mut q)?;
        if slot != "A" || version != base.version {
            bail!(
                "booted slot {slot:?} version {version:?}, want A {}",
                base.version
            );
        }
        let state = boot_state(&mut q)?;
        Ok(format!(
            "slot A, version {version}, healthy {s:.1} s after QEMU start; {state}"
        ))
    });
    let booted = first.is_ok();
    report.check("first boot from slot A, marked good by irtrack-health", first);
    if !booted {
        return Ok(report);
    }
    q.console(
        &format!("echo {HEALTH_TIMEOUT_S} > /data/rauc/health-timeout-s"),
        Duration::from_secs(10),
    )?;
    let rig_id = match &params {
        Ok((rig, file)) => push_params(ctx, params_port, file, Some(&image.signing_key))
            .and_then(|_| check_params_used(status_port, rig))
            .map(|d| (rig.clone(), d)),
        Err(e) => Err(anyhow::anyhow!("no parameter set to push: {e:#}")),
    };
    let rig = rig_id.as_ref().ok().map(|(r, _)| r.clone());
    report.check(
        "signed parameter set pushed (kept on the data partition)",
        rig_id.map(|(_, d)| d),
    );

    // 2. Refused bundles leave the system as it was.
    let state_before = boot_state(&mut q)?;
    for (name, what, reason) in [
        (
            "foreign",
            "bundle signed by a CA the board does not trust refused",
            "signature",
        ),
        ("truncated", "truncated bundle refused", ""),
        (
            "older",
            "downgrade refused with its reason",
            "refused: downgrade from",
        ),
        (
            "other-board",
            "bundle for another board (the other A/B image's board type) refused",
            "compatible",
        ),
    ] {
        let res = install(&mut q, http_port, name).and_then(|(rc, out, _)| {
            if rc == 0 {
                bail!("rauc install succeeded: {out}");
            }
            let msg = out
                .lines()
                .filter(|l| l.contains("rror") || l.contains("refused") || l.contains("ailed"))
                .collect::<Vec<_>>()
                .join(" | ");
            // The downgrade check is the board's pre-install handler: RAUC reports only that
            // the handler failed; the handler puts its reason in last-update.
            let said = if name == "older" {
                last_update(&mut q)?
            } else {
                out.clone()
            };
            if !reason.is_empty() && !said.to_lowercase().contains(&reason.to_lowercase()) {
                bail!("refused, but it does not say {reason:?}: {said}");
            }
            let state = boot_state(&mut q)?;
            if state != state_before {
                bail!("boot state changed: before {state_before}, after {state}");
            }
            let (slot, version) = running(&mut q)?;
            if slot != "A" || version != base.version || rig_now(status_port)? != rig {
                bail!("running system changed: slot {slot}, version {version}");
            }
            let msg = if name == "older" {
                value_of(&said, "detail").unwrap_or_default()
            } else {
                msg
            };
            Ok(format!("exit {rc}: {msg}; boot state unchanged ({state})"))
        });
        report.check(what, res);
    }

    // 3. A good update pushed from the PC with `host-tools update push --reboot`: uploaded to
    //    irtrackd's POST /api/update?reboot=1, installed through its updater (the root agent
    //    runs RAUC), the agent reboots the board, host-tools waits for it and reports slot B
    //    marked good. Then: slot B runs the new version, healthy, parameters kept.
    let password = set_operator_password(&mut q, status_port);
    let from = q.log_len();
    let good = password.and_then(|_| {
        let pushed = push_with_reboot(ctx, &dir, status_port, &bundle_dir.join("good.raucb"))?;
        if !q
            .log_since(from)
            .contains("irtrack-update-agent: rebooting into the installed update")
        {
            bail!(
                "host-tools reported success, but the root agent did not reboot: {}",
                pushed.stdout
            );
        }
        Ok(pushed)
    });
    let pushed = good.is_ok();
    if let Ok(p) = &good {
        report.figures.push(format!(
            "install of the good bundle with host-tools update push --reboot (upload over QEMU user networking included): {:.1} s",
            p.install_s
        ));
        report.figures.push(format!(
            "reboot into the updated slot to healthy (marked good), timed by host-tools from the reboot request: {:.1} s; the whole push {:.1} s",
            p.reboot_s, p.total_s
        ));
    }
    report.check(
        "signed update pushed with host-tools update push --reboot: installed into slot B, rebooted by the root agent, back on slot B marked good",
        good.map(|p| {
            let steps = p.stderr.lines().filter(|l| l.starts_with("install:")).count();
            let reboot: Vec<&str> = p.stderr.lines().filter(|l| l.starts_with("reboot:")).collect();
            format!("{}; {steps} install steps shown; {}", p.stdout, reboot.join(" | "))
        }),
    );
    if pushed {
        let res = (|| {
            let (slot, version) = running(&mut q)?;
            if slot != "B" || version != good_version {
                bail!("running slot {slot:?} version {version:?}, want B {good_version}");
            }
            // What an operator sees: /status names the new slot and version.
            let (st_slot, st_version) = status_running(status_port, "B")?;
            if st_slot != "B" || st_version != good_version {
                bail!(
                    "/status system.running: slot {st_slot:?} version {st_version:?}, want B {good_version}"
                );
            }
            let now = rig_now(status_port)?;
            if now != rig || rig.is_none() {
                bail!("parameter set after the update: {now:?}, before: {rig:?}");
            }
            let outcome = last_update(&mut q)?;
            if value_of(&outcome, "outcome").as_deref() != Some("healthy") {
                bail!("last update: {outcome}");
            }
            let state = boot_state(&mut q)?;
            if !state.contains("BOOT_ORDER=B A")
                || !state.contains("BOOT_B_LEFT=3")
                || !state.ends_with("pending=")
            {
                bail!("boot state after the update: {state}");
            }
            Ok(format!(
                "slot B version {version} healthy; rig {} kept; {state}",
                rig.clone().unwrap_or_default()
            ))
        })();
        report.check(
            "reboot into the update: irtrackd healthy, parameters kept, marked good",
            res,
        );
    }

    // 4. An update whose irtrackd cannot start: installed into slot A, never healthy, the
    //    health check reboots it until its attempts run out, U-Boot falls back to slot B.
    let broken = install(&mut q, http_port, "broken").and_then(|(rc, out, _)| {
        if rc != 0 {
            bail!("rauc install failed ({rc}): {out}");
        }
        Ok(())
    });
    let broken_ok = broken.is_ok();
    report.check(
        "update with an irtrackd that cannot start installed into slot A",
        broken.map(|_| format!("version {broken_version}")),
    );
    if broken_ok {
        let from = q.log_len();
        let t0 = Instant::now();
        q.type_line("reboot")?;
        let res = q
            .wait_for("irtrack-health: rolled back", from, Duration::from_secs(600))
            .and_then(|_| {
                let rollback_s = t0.elapsed().as_secs_f64();
                q.wait_for("irtrack-health: slot B healthy", from, BOOT_TIMEOUT)?;
                let log = q.log_since(from);
                let trials = log.matches("irtrack-boot: slot A").count();
                let (slot, version) = running(&mut q)?;
                if slot != "B" || version != good_version {
                    bail!("after the rollback: slot {slot:?} version {version:?}, want B {good_version}");
                }
                let now = rig_now(status_port)?;
                if now != rig {
                    bail!("parameter set after the rollback: {now:?}, before: {rig:?}");
                }
                let outcome = last_update(&mut q)?;
                if value_of(&outcome, "outcome").as_deref() != Some("rolled-back") {
                    bail!("last update: {outcome}");
                }
                let state = boot_state(&mut q)?;
                Ok((
                    rollback_s,
                    format!(
                        "{trials} boot(s) of slot A, back on slot B version {version} after {rollback_s:.0} s; rig kept; {}; {state}",
                        value_of(&outcome, "detail").unwrap_or_default()
                    ),
                ))
            });
        if let Ok((secs, _)) = &res {
            report.figures.push(format!(
                "rollback from the broken update (3 attempts, {HEALTH_TIMEOUT_S} s health timeout): {secs:.0} s"
            ));
        }
        report.check(
            "broken update rolled back by itself (boot counter runs out, U-Boot boots slot B)",
            res.map(|(_, d)| d),
        );
    }

    // 5. Power cut while the good bundle is being written into slot A: the board boots the
    //    slot it ran before, unharmed.
    let res = power_cut(
        &mut q,
        http_port,
        image.arch,
        &disk,
        &ports,
        &dir,
        status_port,
        rig.as_deref(),
        &good_version,
    );
    let mut env_ok = res.is_ok();
    match res {
        Ok((new_q, detail)) => {
            q = new_q;
            report.check(
                "power cut during an install: the running slot boots unharmed",
                Ok(detail),
            );
        }
        Err(e) => report.check(
            "power cut during an install: the running slot boots unharmed",
            Err(e),
        ),
    }

    // 6. The boot counters (two copies in libubootenv's redundant layout, bootenv.rs) survive
    //    a damaged copy and a cut in the middle of fw_setenv. Slot A now holds the half-written
    //    system of the power cut: a board that fell back to the defaults ("A B") or trusted a
    //    broken copy would boot slot A, so only slot B with the valid copy's counters passes.
    let rig_disk = EnvDisk {
        arch: image.arch,
        disk: &disk,
        ports: &ports,
        dir: &dir,
    };
    type EnvStep = fn(&mut Qemu, &EnvDisk) -> Result<String>;
    let env_steps: [(&'static str, EnvStep); 3] = [
        (
            "boot counters: the newer copy damaged (bad CRC): U-Boot boots the slot the other copy says, with its counters",
            env_damaged,
        ),
        (
            "boot counters: a copy truncated: U-Boot boots from the other and writes the short one whole again (fw_printenv works)",
            env_truncated,
        ),
        (
            "boot counters: power cut in a fw_setenv loop, then a half-written newer copy: the newest valid copy wins, not the defaults",
            env_setenv_cut,
        ),
    ];
    for (name, step) in env_steps {
        if !env_ok {
            break;
        }
        let t0 = Instant::now();
        let res = step(&mut q, &rig_disk);
        env_ok = res.is_ok();
        if env_ok {
            report.figures.push(format!(
                "{}: {:.1} s (power off, edit, boot to healthy)",
                name.split(':').nth(1).unwrap_or(name).trim(),
                t0.elapsed().as_secs_f64()
            ));
        }
        report.check(name, res);
    }
    report.figures.push(format!(
        "update test in QEMU: {:.0} s (first boot to the last check)",
        test_start.elapsed().as_secs_f64()
    ));
    drop(q);
    Ok(report)
}

#[allow(clippy::too_many_arguments)]
fn power_cut(
    q: &mut Qemu,
    http_port: u16,
    arch: Arch,
    disk: &Path,
    ports: &[u16; 4],
    dir: &Path,
    status_port: u16,
    rig: Option<&str>,
    good_version: &str,
) -> Result<(Qemu, String)> {
    let (slot_before, version_before) = running(q)?;
    let state_before = boot_state(q)?;
    q.console(
        &format!("rm -f /data/update.raucb; wget -q -O /data/update.raucb http://10.0.2.2:{http_port}/good.raucb; sync"),
        INSTALL_TIMEOUT,
    )?;
    let from = q.log_len();
    q.type_line("rauc install /data/update.raucb")?;
    // RAUC reports the copy into the slot as it starts; cut the power a moment into it.
    q.wait_for("Copying image", from, INSTALL_TIMEOUT)?;
    thread::sleep(Duration::from_secs(2));
    q.kill();
    let mut q2 = Qemu::spawn(
        qemu_command_for(arch, disk, ports),
        &dir.join("serial-after-power-cut.log"),
    )?;
    let healthy_s = wait_healthy(&mut q2, 0, &slot_before)?;
    let (slot, version) = running(&mut q2)?;
    if slot != slot_before || version != version_before || version != good_version {
        bail!(
            "after the power cut: slot {slot:?} version {version:?}, before {slot_before} {version_before}"
        );
    }
    let now = rig_now(status_port)?;
    if now.as_deref() != rig {
        bail!("parameter set after the power cut: {now:?}, before: {rig:?}");
    }
    let state = boot_state(&mut q2)?;
    Ok((
        q2,
        format!(
            "cut during the copy; slot {slot} version {version} healthy {healthy_s:.1} s after power-on; rig kept; before {state_before}, after {state}"
        ),
    ))
}

/// The stopped guest's disk, for the boot counter checks.
struct EnvDisk<'a> {
    arch: Arch,
    disk: &'a Path,
    ports: &'a [u16; 4],
    dir: &'a Path,
}

/// Partition 1, the FAT boot partition, starts 1 MiB into the SD image (`assemble_sd`).
const BOOT_PARTITION_OFFSET: u64 = 1 << 20;

impl EnvDisk<'_> {
    /// `mtools` image argument for the boot partition inside the disk image.
    fn mtools_image(&self) -> String {
        format!("{}@@{BOOT_PARTITION_OFFSET}", self.disk.display())
    }

    fn mcopy(&self, from: &str, to: &str) -> Result<()> {
        let out = Command::new("mcopy")
            .env("MTOOLS_SKIP_CHECK", "1")
            .args(["-n", "-o", "-i", &self.mtools_image(), from, to])
            .output()
            .context("running mcopy (mtools; run `cargo xtask setup`)")?;
        if !out.status.success() {
            bail!(
                "mcopy {from} {to}: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            );
        }
        Ok(())
    }

    /// Both copies' bytes as the boot partition holds them (any length).
    fn read(&self) -> Result<[Vec<u8>; 2]> {
        let mut out = [Vec::new(), Vec::new()];
        for (i, name) in bootenv::COPY_FILES.iter().enumerate() {
            let local = self.dir.join(format!("env-read-{name}"));
            let _ = fs::remove_file(&local);
            self.mcopy(&format!("::/{name}"), &local.to_string_lossy())?;
            out[i] = fs::read(&local)?;
        }
        Ok(out)
    }

    /// Replaces copy `i` with `bytes`.
    fn write(&self, i: usize, bytes: &[u8]) -> Result<()> {
        let name = bootenv::COPY_FILES[i];
        let local = self.dir.join(format!("env-write-{name}"));
        fs::write(&local, bytes)?;
        self.mcopy(&local.to_string_lossy(), &format!("::/{name}"))
    }

    fn power_on(&self, q: &mut Qemu, log: &str) -> Result<()> {
        *q = Qemu::spawn(
            qemu_command_for(self.arch, self.disk, self.ports),
            &self.dir.join(log),
        )?;
        Ok(())
    }
}

/// Both copies in a few words.
fn describe(c: &[bootenv::EnvCopy; 2]) -> String {
    c.iter()
        .zip(bootenv::COPY_FILES)
        .map(|(c, name)| {
            if c.valid {
                format!(
                    "{name} valid, flags {:#04x} (BOOT_ORDER={}, A {}, B {}{})",
                    c.flags,
                    c.get("BOOT_ORDER").unwrap_or("-"),
                    c.get("BOOT_A_LEFT").unwrap_or("-"),
                    c.get("BOOT_B_LEFT").unwrap_or("-"),
                    c.get("irtrack_env_test")
                        .map(|v| format!(", test {v}"))
                        .unwrap_or_default()
                )
            } else {
                format!("{name} invalid ({})", c.problem.as_deref().unwrap_or("?"))
            }
        })
        .collect::<Vec<_>>()
        .join("; ")
}

fn decode_both(bytes: &[Vec<u8>; 2]) -> [bootenv::EnvCopy; 2] {
    [bootenv::decode(&bytes[0]), bootenv::decode(&bytes[1])]
}

/// The whole console line that starts with `needle` (after log offset `from`).
fn console_line(q: &mut Qemu, needle: &str, from: usize) -> Result<String> {
    let end = q.wait_for(needle, from, BOOT_TIMEOUT)?;
    let start = end - needle.len();
    let nl = q.wait_for("\n", end, Duration::from_secs(10))?;
    Ok(q.log_since(start)
        .get(..nl - 1 - start)
        .unwrap_or("")
        .trim()
        .to_owned())
}

/// Checks U-Boot's lines of a boot: the counters came from copy `copy` and slot B was booted
/// with `order` and, after taking the attempt, `a_left`/`b_left`. Returns the slot line.
fn expect_boot(q: &mut Qemu, copy: usize, order: &str, a_left: &str, b_left: u32) -> Result<String> {
    let line = console_line(q, "irtrack-boot: slot ", 0)?;
    let want = format!("irtrack-boot: slot B (BOOT_ORDER={order}, A left {a_left}, B left {b_left};");
    if !line.starts_with(&want) {
        bail!("U-Boot said {line:?}, want {want:?}");
    }
    let log = q.log_since(0);
    let from = log
        .lines()
        .find(|l| l.contains("irtrack-boot: boot counters from") || l.contains("no valid boot counter copy"))
        .unwrap_or("(no line about the copies)")
        .trim()
        .to_owned();
    if !from.contains(&format!("from copy {copy} ")) {
        bail!("U-Boot took the counters from another copy than {copy}: {from}");
    }
    Ok(line)
}

/// The values of the copy that counts, for writing it again with distinct counters.
fn slot_b_env(order: &str, a_left: &str, b_left: &str) -> [(&'static str, String); 3] {
    [
        ("BOOT_ORDER", order.to_owned()),
        ("BOOT_A_LEFT", a_left.to_owned()),
        ("BOOT_B_LEFT", b_left.to_owned()),
    ]
}

fn encode_owned(vars: &[(&str, String)], flags: u8) -> Result<Vec<u8>> {
    let v: Vec<(&str, &str)> = vars.iter().map(|(k, v)| (*k, v.as_str())).collect();
    bootenv::encode(&v, flags)
}

/// Power off after `sync`; the copy that counts says slot B (A 0, B 2 attempts); the other is
/// newer (flags + 1) but has a bad CRC and says "A B". U-Boot must boot B with B left 1.
fn env_damaged(q: &mut Qemu, d: &EnvDisk) -> Result<String> {
    q.console("sync", Duration::from_secs(30))?;
    q.kill();
    let c = decode_both(&d.read()?);
    let before = describe(&c);
    let w =
        bootenv::winner(&c[0], &c[1]).with_context(|| format!("no valid copy before the test: {before}"))?;
    let f = c[w].flags;
    d.write(w, &encode_owned(&slot_b_env("B A", "0", "2"), f)?)?;
    let mut bad = bootenv::encode(
        &[("BOOT_ORDER", "A B"), ("BOOT_A_LEFT", "3"), ("BOOT_B_LEFT", "3")],
        bootenv::next_flags(f),
    )?;
    bad[40] ^= 0x5a;
    d.write(1 - w, &bad)?;
    d.power_on(q, "serial-env-damaged.log")?;
    let line = expect_boot(q, w, "B A", "0", 1)?;
    let healthy_s = wait_healthy(q, 0, "B")?;
    Ok(format!(
        "before: {before}; then copy {w} says B A / A 0 / B 2 (flags {f:#04x}), copy {} newer (flags {:#04x}) with a bad CRC; {line}; slot B healthy {healthy_s:.1} s after power-on",
        1 - w,
        bootenv::next_flags(f)
    ))
}

/// Both copies must be valid again (U-Boot rewrote the damaged one, fw_setenv the other); then
/// the newer one is cut to 1000 bytes. U-Boot must boot from the whole one and write the short
/// file whole again, which libubootenv needs (it refuses a short copy outright).
fn env_truncated(q: &mut Qemu, d: &EnvDisk) -> Result<String> {
    q.console("sync", Duration::from_secs(30))?;
    q.kill();
    let c = decode_both(&d.read()?);
    let before = describe(&c);
    if !(c[0].valid && c[1].valid) {
        bail!("the damaged copy was not written whole again by the last boot: {before}");
    }
    let w = bootenv::winner(&c[0], &c[1]).context("no winner of two valid copies")?;
    let f = c[w].flags;
    d.write(w, &encode_owned(&slot_b_env("B A", "0", "3"), f)?)?;
    let newer = bootenv::encode(
        &[("BOOT_ORDER", "A B"), ("BOOT_A_LEFT", "3"), ("BOOT_B_LEFT", "3")],
        bootenv::next_flags(f),
    )?;
    d.write(1 - w, &newer[..1000])?;
    d.power_on(q, "serial-env-truncated.log")?;
    let line = expect_boot(q, w, "B A", "0", 2)?;
    let short = format!("{} is 3e8 bytes, not 4000", bootenv::COPY_FILES[1 - w]);
    if !q.log_since(0).contains(&short) {
        bail!("U-Boot did not report the short copy ({short:?})");
    }
    let healthy_s = wait_healthy(q, 0, "B")?;
    let env = console_clean(
        q,
        "fw_printenv BOOT_ORDER BOOT_A_LEFT BOOT_B_LEFT; echo rc=$?",
        Duration::from_secs(20),
    )?;
    if value_of(&env, "rc").as_deref() != Some("0") || value_of(&env, "BOOT_ORDER").as_deref() != Some("B A")
    {
        bail!("fw_printenv after the boot: {env}");
    }
    Ok(format!(
        "before: both copies valid ({before}); copy {} cut to 1000 bytes; {line}; healthy {healthy_s:.1} s after power-on; fw_printenv then: {}",
        1 - w,
        env.split_whitespace().collect::<Vec<_>>().join(" ")
    ))
}

/// A loop rewrites the environment with fw_setenv (a harmless variable; the counters stay) and
/// the power is cut in the middle of it, at no chosen moment. The copies are then inspected,
/// and the next write is cut short on purpose: the first half of a newer copy that says "A B"
/// over the copy that lost. U-Boot must take the newest valid copy's counters.
fn env_setenv_cut(q: &mut Qemu, d: &EnvDisk) -> Result<String> {
    q.console(
        "(i=0; while [ $i -lt 100000 ]; do i=$((i+1)); fw_setenv irtrack_env_test $i || break; done) >/dev/null 2>&1 & echo loop=$!",
        Duration::from_secs(10),
    )?;
    thread::sleep(Duration::from_secs(4));
    q.kill();
    let c = decode_both(&d.read()?);
    let after_cut = describe(&c);
    let w =
        bootenv::winner(&c[0], &c[1]).with_context(|| format!("no valid copy after the cut: {after_cut}"))?;
    let writes: u64 = c[w]
        .get("irtrack_env_test")
        .and_then(|v| v.parse().ok())
        .with_context(|| format!("the fw_setenv loop wrote nothing before the cut: {after_cut}"))?;
    let order = c[w].get("BOOT_ORDER").unwrap_or("").to_owned();
    let a_left = c[w].get("BOOT_A_LEFT").unwrap_or("").to_owned();
    let b_left: u32 = c[w]
        .get("BOOT_B_LEFT")
        .and_then(|v| v.parse().ok())
        .with_context(|| format!("BOOT_B_LEFT missing: {after_cut}"))?;
    if order != "B A" || b_left == 0 {
        bail!("the counters changed during the fw_setenv loop: {after_cut}");
    }
    let torn_by_cut = !(c[0].valid && c[1].valid);
    let seq = (writes + 1).to_string();
    // Its data reaches past the tear, so the half that did not arrive differs from what the
    // old copy holds there (bytes both share would tear nothing).
    let pad = "x".repeat(bootenv::ENV_BYTES * 3 / 4);
    let next = bootenv::encode(
        &[
            ("BOOT_ORDER", "A B"),
            ("BOOT_A_LEFT", "3"),
            ("BOOT_B_LEFT", "3"),
            ("irtrack_env_test", seq.as_str()),
            ("irtrack_env_pad", pad.as_str()),
        ],
        bootenv::next_flags(c[w].flags),
    )?;
    let mut torn = d.read()?[1 - w].clone();
    torn.resize(bootenv::ENV_BYTES, 0);
    torn[..bootenv::ENV_BYTES / 2].copy_from_slice(&next[..bootenv::ENV_BYTES / 2]);
    if bootenv::decode(&torn).valid {
        bail!("the half-written copy is valid; the test cannot tell anything");
    }
    d.write(1 - w, &torn)?;
    d.power_on(q, "serial-env-setenv-cut.log")?;
    let line = expect_boot(q, w, &order, &a_left, b_left - 1)?;
    let healthy_s = wait_healthy(q, 0, "B")?;
    Ok(format!(
        "{writes} fw_setenv writes before the cut; after it: {after_cut} ({}); then the first half of a newer copy (flags {:#04x}, A B) over copy {}; {line}; healthy {healthy_s:.1} s after power-on",
        if torn_by_cut {
            "the cut tore a copy"
        } else {
            "the cut fell between two writes"
        },
        bootenv::next_flags(c[w].flags),
        1 - w
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_are_read_before_their_unit() {
        let out = "installed 0.1.1 into slot B in 26.1 s; rebooted: slot B runs 0.1.1, healthy and marked good 17.5 s after the reboot was asked for";
        assert_eq!(number_before(out, " s; rebooted"), Some(26.1));
        assert_eq!(
            number_before(out, " s after the reboot was asked for"),
            Some(17.5)
        );
        assert_eq!(number_before(out, " s; missing"), None);
    }

    #[test]
    fn each_board_refuses_the_other_boards_bundles() {
        assert_eq!(
            other_board(update::COMPATIBLE).unwrap(),
            super::super::armv7::COMPATIBLE
        );
        assert_eq!(
            other_board(super::super::armv7::COMPATIBLE).unwrap(),
            update::COMPATIBLE
        );
    }

    #[test]
    fn versions_bump_in_their_last_number() {
        assert_eq!(bump("0.1.0", 1).unwrap(), "0.1.1");
        assert_eq!(bump("1.9+abc", 2).unwrap(), "1.11");
        assert_eq!(bump("7", 1).unwrap(), "8");
        assert!(bump("1.x", 1).is_err());
    }

    #[test]
    fn values_are_read_from_console_lines() {
        let out = "BOOT_ORDER=B A\n  rc=1\nnoise";
        assert_eq!(value_of(out, "BOOT_ORDER").as_deref(), Some("B A"));
        assert_eq!(value_of(out, "rc").as_deref(), Some("1"));
        assert_eq!(value_of(out, "missing"), None);
    }

    #[test]
    fn the_file_server_serves_files_and_nothing_else() {
        let dir = std::env::temp_dir().join(format!("xtask-serve-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        fs::write(dir.join("a.raucb"), b"bundle bytes").unwrap();
        let port = serve_dir(dir.clone()).unwrap();
        let get = |path: &str| {
            let mut s = TcpStream::connect((Ipv4Addr::LOCALHOST, port)).unwrap();
            s.write_all(format!("GET {path} HTTP/1.0\r\n\r\n").as_bytes())
                .unwrap();
            let mut reply = String::new();
            s.read_to_string(&mut reply).unwrap();
            reply
        };
        let ok = get("/a.raucb");
        assert!(
            ok.starts_with("HTTP/1.0 200") && ok.ends_with("bundle bytes"),
            "{ok}"
        );
        assert!(get("/../etc/passwd").starts_with("HTTP/1.0 404"));
        assert!(get("/missing").starts_with("HTTP/1.0 404"));
        fs::remove_dir_all(&dir).unwrap();
    }
}
