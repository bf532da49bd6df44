//! The A/B update test (`cargo xtask image update-test`, CI opt-in phase `image-update`):
//! boots a fresh copy of the image in QEMU and, through the console shell and irtrackd's
//! forwarded ports, installs RAUC bundles that the guest downloads from a small HTTP server
//! on the host (10.0.2.2 under QEMU user networking). docs/updates.md lists the checks.

use std::fs;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Ipv4Addr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use super::checks::{
    check_params_used, get_status, make_params, push_params, rig_id_of, set_operator_password,
};
use super::qemu::{BOOT_TIMEOUT, Qemu, free_ports, qemu_command};
use super::system::Report;
use super::update::{self, Release, UpdateKeys};
use super::{Image, work_dir};
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
/// set to `release` and `tweak` applied to a copy of the tree.
fn rootfs_variant(
    work: &Path,
    name: &str,
    release: &Release,
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
    update::write_release(&stage, release)?;
    tweak(&stage)?;
    let out = work.join(format!("rootfs-{name}.ext4"));
    super::make_root_partition(&out, &stage)?;
    fs::remove_dir_all(&stage)?;
    Ok(out)
}

/// Makes good.raucb, broken.raucb, foreign.raucb, older.raucb, other-board.raucb and
/// truncated.raucb; returns the good and the broken version and the seconds it took.
fn make_bundles(work: &Path, dir: &Path, base: &Release, keys: &UpdateKeys) -> Result<(String, String, f64)> {
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
    let good_fs = rootfs_variant(work, "good", &good, |_| Ok(()))?;
    // irtrackd that cannot start: the supervisor restarts it forever, /status never answers.
    let broken_fs = rootfs_variant(work, "broken", &broken, |stage| {
        let bin = stage.join("usr/bin/irtrackd");
        fs::write(
            &bin,
            "#!/bin/sh\necho 'irtrackd: this build is broken on purpose (update test)' >&2\nexit 1\n",
        )?;
        Ok(())
    })?;
    update::make_bundle(work, &good_fs, &good, keys, &dir.join("good.raucb"))?;
    update::make_bundle(work, &broken_fs, &broken, keys, &dir.join("broken.raucb"))?;
    // Signed by a CA the board does not trust.
    let foreign = update::make_ca(&work.join("update-test-foreign-ca"), "someone else")?;
    update::make_bundle(work, &good_fs, &good, &foreign, &dir.join("foreign.raucb"))?;
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
    update::make_bundle(work, &good_fs, &older, keys, &dir.join("older.raucb"))?;
    // For another board.
    update::make_bundle_for(
        work,
        &good_fs,
        &good,
        keys,
        "irtrack-other-board",
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

/// Uploads `bundle` to irtrackd's `POST /api/update` as the operator (raw HTTP, the file
/// streamed), then follows `/status` → `system.install` to its end. Returns (seconds, the
/// install steps seen) or the board's refusal.
fn upload_install(status_port: u16, bundle: &Path) -> Result<(f64, String)> {
    let t0 = Instant::now();
    let len = fs::metadata(bundle)?.len();
    let mut s = TcpStream::connect((Ipv4Addr::LOCALHOST, status_port))?;
    s.set_read_timeout(Some(INSTALL_TIMEOUT))?;
    s.write_all(
        format!(
            "POST /api/update HTTP/1.1\r\nHost: 127.0.0.1:{status_port}\r\nAuthorization: {}\r\n\
             Content-Type: application/octet-stream\r\nContent-Length: {len}\r\n\r\n",
            irtrack_testkit::harness::http::basic_authorization(crate::util::OPERATOR_PASSWORD)
        )
        .as_bytes(),
    )?;
    std::io::copy(&mut fs::File::open(bundle)?, &mut s)?;
    let mut answer = String::new();
    s.read_to_string(&mut answer)?;
    let upload_s = t0.elapsed().as_secs_f64();
    let code = answer.split_whitespace().nth(1).unwrap_or("");
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b).trim();
    if code != "202" {
        bail!("upload answered {code}: {body}");
    }
    let id = json::parse(body)?
        .get("id")
        .and_then(|i| i.as_u64())
        .with_context(|| format!("upload answer without a job id: {body}"))?;
    let mut steps: Vec<String> = Vec::new();
    loop {
        let st = get_status(status_port)?;
        let job = st
            .get("system")
            .and_then(|s| s.get("install"))
            .cloned()
            .unwrap_or_default();
        if job.get("id").and_then(|i| i.as_u64()) != Some(id) {
            bail!("/status no longer shows install {id}: {job}");
        }
        let step = format!(
            "{}% {}",
            job.get("percent").and_then(|p| p.as_u64()).unwrap_or(0),
            job.get("step").and_then(|p| p.as_str()).unwrap_or("")
        );
        if steps.last() != Some(&step) {
            steps.push(step);
        }
        match job.get("state").and_then(|p| p.as_str()) {
            Some("installed") => break,
            Some("refused") => bail!("the board refused the upload: {job}"),
            _ => {}
        }
        if t0.elapsed() > INSTALL_TIMEOUT {
            bail!(
                "install {id} did not end within {} s: {job}",
                INSTALL_TIMEOUT.as_secs()
            );
        }
        thread::sleep(Duration::from_millis(500));
    }
    Ok((
        t0.elapsed().as_secs_f64(),
        format!(
            "upload {upload_s:.1} s; {} install steps seen, e.g. {}",
            steps.len(),
            steps[steps.len() / 2]
        ),
    ))
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
    let work = work_dir(ctx);
    let dir = work.join("update-test");
    fs::create_dir_all(&dir)?;
    let mut report = Report::default();
    let base = image_release(&work)?;
    let keys = update::update_keys(&work)?;
    let bundle_dir = dir.join("bundles");
    let (good_version, broken_version, bundle_s) = make_bundles(&work, &bundle_dir, &base, &keys)?;
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
    let mut q = Qemu::spawn(qemu_command(&disk, &ports), &dir.join("serial-1.log"))?;
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
        ("other-board", "bundle for another board refused", "compatible"),
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

    // 3. A good update, uploaded to irtrackd as the operator would from the set-up page or
    //    `host-tools update push`: installed through irtrackd's updater (the root agent runs
    //    RAUC), then reboot into slot B, healthy, parameters kept.
    let password = set_operator_password(&mut q, status_port);
    let good = password.and_then(|_| {
        let (secs, seen) = upload_install(status_port, &bundle_dir.join("good.raucb"))?;
        let state = boot_state(&mut q)?;
        if !state.contains("BOOT_ORDER=B A") || !state.contains(&format!("pending=B {good_version}")) {
            bail!("after the install: {state}");
        }
        Ok((secs, format!("{seen}; {state}")))
    });
    let installed = good.is_ok();
    if let Ok((secs, _)) = &good {
        report.figures.push(format!(
            "install of the good bundle uploaded to irtrackd (upload over QEMU user networking included): {secs:.1} s"
        ));
    }
    report.check(
        "signed update uploaded to irtrackd (POST /api/update) and installed into slot B",
        good.map(|(secs, state)| format!("{secs:.1} s; {state}")),
    );
    if installed {
        let from = q.log_len();
        let t0 = Instant::now();
        q.type_line("reboot")?;
        let res = wait_healthy(&mut q, from, "B").and_then(|_| {
            let secs = t0.elapsed().as_secs_f64();
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
            Ok((
                secs,
                format!(
                    "slot B version {version} healthy {secs:.1} s after `reboot`; rig {} kept; {state}",
                    rig.clone().unwrap_or_default()
                ),
            ))
        });
        if let Ok((secs, _)) = &res {
            report.figures.push(format!(
                "reboot into the updated slot to healthy (marked good): {secs:.1} s"
            ));
        }
        report.check(
            "reboot into the update: irtrackd healthy, parameters kept, marked good",
            res.map(|(_, d)| d),
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
        &disk,
        &ports,
        &dir,
        status_port,
        rig.as_deref(),
        &good_version,
    );
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
    let mut q2 = Qemu::spawn(qemu_command(disk, ports), &dir.join("serial-after-power-cut.log"))?;
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

#[cfg(test)]
mod tests {
    use super::*;

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
