//! RAUC through its command line (RAUC 1.8, docs/updates.md): `rauc status --detailed
//! --output-format=json` for the slots, `rauc install FILE` for an install — its progress
//! lines (`" 40% Copying image to rootfs.1"`) and `LastError: …` are parsed — and the
//! `last-update` file the image's pre- and post-install handlers write (RAUC reports a refusal
//! by the downgrade check only as "Pre-install handler error"; the handler's reason is there).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use super::{
    Installed, LastUpdate, Progress, Refusal, RefusalKind, SlotInfo, SystemSlots, SystemUpdater, UpdateConfig,
};

/// `rauc status` that does not answer within this is given up on (a stuck D-Bus service).
const STATUS_TIMEOUT: Duration = Duration::from_secs(20);

/// An install through the agent that shows no sign of life for this long is given up on.
const AGENT_SILENCE: Duration = Duration::from_secs(120);

/// Between asking for a reboot and running the reboot command here: `/status` shows the
/// pending reboot meanwhile (the root agent waits as long before it reboots).
const REBOOT_DELAY: Duration = Duration::from_secs(2);

/// Whether RAUC is reached through the root agent: irtrackd is not root and the agent's
/// spool exists.
pub fn use_agent(dir: &Path) -> bool {
    // SAFETY: geteuid has no preconditions.
    let root = unsafe { libc::geteuid() } == 0;
    !root && dir.is_dir()
}

/// See the module documentation.
pub struct RaucUpdater {
    rauc: PathBuf,
    last_update: PathBuf,
    release_file: PathBuf,
    /// The root agent's spool, when RAUC is run through it.
    agent: Option<PathBuf>,
    /// Reboots the board when RAUC runs here (not through the agent).
    reboot_command: PathBuf,
}

impl RaucUpdater {
    /// From `[update]`.
    pub fn new(cfg: &UpdateConfig) -> Self {
        Self {
            rauc: cfg.rauc_command.clone(),
            last_update: cfg.last_update_file.clone(),
            release_file: cfg.release_file.clone(),
            agent: use_agent(&cfg.rauc_agent_dir).then(|| cfg.rauc_agent_dir.clone()),
            reboot_command: cfg.reboot_command.clone(),
        }
    }

    /// `rauc status` JSON from the agent: asks for a fresh one and waits a little for it.
    fn agent_status(dir: &Path) -> Result<String, String> {
        let file = dir.join("status.json");
        let before = std::fs::metadata(&file).and_then(|m| m.modified()).ok();
        let _ = std::fs::write(dir.join("status-request"), b"");
        let start = std::time::Instant::now();
        while start.elapsed() < Duration::from_secs(5) {
            let now = std::fs::metadata(&file).and_then(|m| m.modified()).ok();
            if now.is_some() && now != before {
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        std::fs::read_to_string(&file).map_err(|e| {
            let why = std::fs::read_to_string(dir.join("status.err")).unwrap_or_default();
            format!(
                "no rauc status from the update agent ({}: {e}) {}",
                file.display(),
                why.trim()
            )
        })
    }

    /// `rauc install` through the agent: the request, then its output as it grows.
    fn agent_install(
        dir: &Path,
        bundle: &Path,
        progress: Progress,
    ) -> Result<(bool, String, Option<String>), Refusal> {
        let failed = |what: String| Refusal::new(RefusalKind::Failed, what);
        let log = dir.join("install.log");
        let rc = dir.join("install.rc");
        for f in [&log, &rc] {
            let _ = std::fs::remove_file(f);
        }
        std::fs::write(dir.join("install"), bundle.as_os_str().as_encoded_bytes())
            .map_err(|e| failed(format!("asking the update agent to install: {e}")))?;
        let mut seen = 0usize;
        let mut last_error = None;
        let mut output = String::new();
        let mut last_news = std::time::Instant::now();
        loop {
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            if text.len() > seen {
                last_news = std::time::Instant::now();
                // Whole lines only; a partial last line is read again next time.
                let upto = text[seen..].rfind('\n').map_or(seen, |i| seen + i + 1);
                for line in text[seen..upto].lines() {
                    scan_line(line, &mut last_error, progress);
                }
                output.push_str(&text[seen..upto]);
                seen = upto;
            }
            if let Ok(code) = std::fs::read_to_string(&rc) {
                let rest = std::fs::read_to_string(&log).unwrap_or_default();
                for line in rest.get(seen..).unwrap_or("").lines() {
                    scan_line(line, &mut last_error, progress);
                    output.push_str(line);
                    output.push('\n');
                }
                return Ok((code.trim() == "0", output, last_error));
            }
            if last_news.elapsed() > AGENT_SILENCE {
                return Err(failed(format!(
                    "the update agent did not answer within {} s (is irtrack-update-agent running?)",
                    AGENT_SILENCE.as_secs()
                )));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// `rauc install` run here: its output line by line.
    fn direct_install(
        &self,
        bundle: &Path,
        progress: Progress,
    ) -> Result<(bool, String, Option<String>), Refusal> {
        let mut child = Command::new(&self.rauc)
            .arg("install")
            .arg(bundle)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                Refusal::new(
                    RefusalKind::Failed,
                    format!("cannot run {}: {e}", self.rauc.display()),
                )
            })?;
        let stderr = child.stderr.take();
        let err_thread = std::thread::spawn(move || {
            let mut text = String::new();
            if let Some(e) = stderr {
                for line in BufReader::new(e).lines().map_while(Result::ok) {
                    text.push_str(&line);
                    text.push('\n');
                }
            }
            text
        });
        let mut last_error = None;
        if let Some(out) = child.stdout.take() {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                scan_line(&line, &mut last_error, progress);
            }
        }
        let status = child
            .wait()
            .map_err(|e| Refusal::new(RefusalKind::Failed, format!("waiting for rauc install: {e}")))?;
        let stderr = err_thread.join().unwrap_or_default();
        Ok((status.success(), stderr, last_error))
    }

    /// `VERSION` and `BUILD` of the running release file.
    fn release(&self) -> (Option<String>, Option<String>) {
        let text = std::fs::read_to_string(&self.release_file).unwrap_or_default();
        let get = |k: &str| {
            text.lines()
                .find_map(|l| l.strip_prefix(k))
                .map(|v| v.trim().trim_matches('"').to_string())
                .filter(|v| !v.is_empty())
        };
        (get("VERSION="), get("BUILD="))
    }
}

/// The slots from `rauc status --detailed --output-format=json` text (RAUC 1.8's layout:
/// `booted`, `boot_primary`, `slots: [{name: {bootname, state, boot_status, slot_status:
/// {bundle: {version, build}}}}]`). Only slots with a boot name count.
pub fn parse_rauc_status(json: &str) -> Result<SystemSlots, String> {
    let v: serde_json::Value =
        serde_json::from_str(json).map_err(|e| format!("rauc status is not JSON: {e}"))?;
    let s = |v: &serde_json::Value, k: &str| v.get(k).and_then(|x| x.as_str()).map(str::to_string);
    let booted = s(&v, "booted");
    let primary = s(&v, "boot_primary");
    let mut slots = Vec::new();
    for entry in v.get("slots").and_then(|x| x.as_array()).into_iter().flatten() {
        let Some((name, slot)) = entry.as_object().and_then(|o| o.iter().next()) else {
            continue;
        };
        let Some(bootname) = s(slot, "bootname") else {
            continue;
        };
        let bundle = slot.get("slot_status").and_then(|st| st.get("bundle"));
        let version = bundle.and_then(|b| s(b, "version"));
        let build = bundle.and_then(|b| s(b, "build"));
        let is_booted = booted.as_deref() == Some(bootname.as_str());
        let state = if is_booted {
            "booted"
        } else if s(slot, "boot_status").as_deref() == Some("bad") {
            "bad"
        } else if version.is_none() {
            "empty"
        } else {
            "good"
        };
        slots.push((
            name.clone(),
            SlotInfo {
                slot: bootname,
                version,
                build,
                state: state.into(),
            },
        ));
    }
    let running = slots
        .iter()
        .find(|(_, i)| i.state == "booted")
        .map(|(_, i)| i.clone());
    let other = slots
        .iter()
        .find(|(_, i)| i.state != "booted")
        .map(|(_, i)| i.clone());
    let boot_next = primary.and_then(|p| slots.iter().find(|(n, _)| *n == p).map(|(_, i)| i.slot.clone()));
    if running.is_none() && booted.is_none() {
        return Err("rauc status names no booted slot".into());
    }
    Ok(SystemSlots {
        compatible: s(&v, "compatible"),
        running,
        other,
        boot_next,
    })
}

/// One line of `rauc install` output: `Some((percent, step))` for a progress line.
pub fn parse_progress_line(line: &str) -> Option<(u8, String)> {
    let t = line.trim_start();
    let (pct, rest) = t.split_once("% ")?;
    let pct: u8 = pct.trim().parse().ok()?;
    Some((pct.min(100), rest.trim().to_string()))
}

/// RAUC's error text as a refusal in plain words.
fn classify(error: &str, handler_detail: Option<&LastUpdate>) -> Refusal {
    let e = error.to_ascii_lowercase();
    if e.contains("pre-install handler")
        && let Some(d) = handler_detail
    {
        let kind = if d.detail.contains("downgrade") {
            RefusalKind::Downgrade
        } else {
            RefusalKind::Failed
        };
        return Refusal::new(kind, d.detail.clone());
    }
    if e.contains("compatible mismatch") {
        return Refusal::new(
            RefusalKind::OtherBoard,
            format!("made for another board ({})", error.trim()),
        );
    }
    if e.contains("signature size")
        || e.contains("too small")
        || e.contains("payload size")
        || e.contains("squashfs")
    {
        return Refusal::new(
            RefusalKind::Truncated,
            format!(
                "the bundle is truncated or corrupted; copy or download it again ({})",
                error.trim()
            ),
        );
    }
    if e.contains("signature") || e.contains("verif") || e.contains("certificate") || e.contains("cms") {
        return Refusal::new(
            RefusalKind::Signature,
            format!(
                "wrong signature: the bundle is not signed by a key this board trusts, or it was changed after signing ({})",
                error.trim()
            ),
        );
    }
    Refusal::new(
        RefusalKind::Failed,
        format!("rauc install failed: {}", error.trim()),
    )
}

impl SystemUpdater for RaucUpdater {
    fn backend(&self) -> &'static str {
        "rauc"
    }

    fn slots(&self) -> Result<SystemSlots, String> {
        let json = match &self.agent {
            Some(dir) => Self::agent_status(dir)?,
            None => self.run_status()?,
        };
        let mut slots = parse_rauc_status(&json)?;
        // The running system's own release file is the truth for the booted slot (the first
        // image was flashed, not installed, so RAUC knows no version for it).
        let (version, build) = self.release();
        if let Some(r) = slots.running.as_mut() {
            r.version = version.or(r.version.take());
            r.build = build.or(r.build.take());
        }
        Ok(slots)
    }

    fn last_update_file(&self) -> &Path {
        &self.last_update
    }

    fn install(&self, bundle: &Path, progress: Progress) -> Result<Installed, Refusal> {
        self.install_bundle(bundle, progress)
    }

    fn request_reboot(&self, installed: &Installed) -> Result<String, String> {
        match &self.agent {
            // The agent (root) reboots, and only while an installed update is pending.
            Some(dir) => {
                let path = dir.join("reboot");
                std::fs::write(&path, format!("{} {}\n", installed.slot, installed.version))
                    .map_err(|e| format!("asking the update agent to reboot ({}): {e}", path.display()))?;
                Ok(format!(
                    "the update agent reboots the board into slot {}",
                    installed.slot
                ))
            }
            None => {
                std::thread::sleep(REBOOT_DELAY);
                let out = Command::new(&self.reboot_command)
                    .stdin(Stdio::null())
                    .output()
                    .map_err(|e| format!("cannot run {}: {e}", self.reboot_command.display()))?;
                if !out.status.success() {
                    return Err(format!(
                        "{} failed ({}): {}",
                        self.reboot_command.display(),
                        out.status,
                        String::from_utf8_lossy(&out.stderr).trim()
                    ));
                }
                Ok(format!(
                    "{} ran; the board reboots into slot {}",
                    self.reboot_command.display(),
                    installed.slot
                ))
            }
        }
    }
}

impl RaucUpdater {
    /// `rauc status --detailed --output-format=json`, run here.
    fn run_status(&self) -> Result<String, String> {
        let mut child = Command::new(&self.rauc)
            .args(["status", "--detailed", "--output-format=json"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| format!("cannot run {}: {e}", self.rauc.display()))?;
        let start = std::time::Instant::now();
        loop {
            match child.try_wait() {
                Ok(Some(_)) => break,
                Ok(None) if start.elapsed() > STATUS_TIMEOUT => {
                    let _ = child.kill();
                    let _ = child.wait();
                    return Err(format!(
                        "rauc status did not answer within {} s",
                        STATUS_TIMEOUT.as_secs()
                    ));
                }
                Ok(None) => std::thread::sleep(Duration::from_millis(50)),
                Err(e) => return Err(format!("waiting for rauc status: {e}")),
            }
        }
        let out = child
            .wait_with_output()
            .map_err(|e| format!("rauc status: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "rauc status failed: {}",
                String::from_utf8_lossy(&out.stderr).trim()
            ));
        }
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    }
}

impl RaucUpdater {
    /// `rauc install`, directly or through the agent, and its outcome in plain words.
    fn install_bundle(&self, bundle: &Path, progress: Progress) -> Result<Installed, Refusal> {
        let before = LastUpdate::read(&self.last_update);
        let (ok, output, last_error) = match &self.agent {
            Some(dir) => Self::agent_install(dir, bundle, progress)?,
            None => self.direct_install(bundle, progress)?,
        };
        let after = LastUpdate::read(&self.last_update).filter(|a| Some(a) != before.as_ref());
        if ok {
            let (slot, version) = after
                .filter(|a| a.outcome == "installed")
                .map(|a| (a.slot.unwrap_or_default(), a.version))
                .unwrap_or_default();
            return Ok(Installed { slot, version });
        }
        let error = last_error.unwrap_or_else(|| output.trim().to_string());
        Err(classify(&error, after.as_ref()))
    }
}

/// One output line of `rauc install`: progress, or the `LastError` it ends with.
fn scan_line(line: &str, last_error: &mut Option<String>, progress: Progress) {
    // A terminal-less run prints plain lines; drop any escape codes anyway.
    let line: String = line.chars().filter(|c| !c.is_control()).collect();
    let line = line.trim_start_matches("[J").trim_start_matches("[F");
    if let Some((_, msg)) = line.split_once("LastError: ") {
        *last_error = Some(msg.to_string());
    } else if let Some((pct, step)) = parse_progress_line(line) {
        progress(pct, &step);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Written in the layout RAUC 1.8's JSON status formatter produces (its src/main.c): slot
    /// B installed by an update and booted, slot A flashed (no slot_status).
    const STATUS: &str = r#"{"compatible":"irtrack-qemu-arm64","variant":"","booted":"B","boot_primary":"rootfs.1","slots":[{"rootfs.0":{"class":"rootfs","device":"/dev/vda2","type":"ext4","bootname":"A","state":"inactive","parent":null,"mountpoint":null,"boot_status":"good"}},{"rootfs.1":{"class":"rootfs","device":"/dev/vda3","type":"ext4","bootname":"B","state":"booted","parent":null,"mountpoint":"/","boot_status":"good","slot_status":{"bundle":{"compatible":"irtrack-qemu-arm64","version":"1.3.0","build":"abc123.20261128T030000Z"},"installed":{"timestamp":"2026-11-28T03:10:00Z","count":1},"status":"ok"}}}]}"#;

    #[test]
    fn status_json_gives_both_slots() {
        let s = parse_rauc_status(STATUS).unwrap();
        assert_eq!(s.compatible.as_deref(), Some("irtrack-qemu-arm64"));
        let running = s.running.unwrap();
        assert_eq!((running.slot.as_str(), running.state.as_str()), ("B", "booted"));
        assert_eq!(running.version.as_deref(), Some("1.3.0"));
        let other = s.other.unwrap();
        // Flashed, never installed by RAUC: no version known.
        assert_eq!((other.slot.as_str(), other.state.as_str()), ("A", "empty"));
        assert_eq!(s.boot_next.as_deref(), Some("B"));
        assert!(parse_rauc_status("{}").is_err());
        assert!(parse_rauc_status("not json").is_err());
    }

    #[test]
    fn progress_lines() {
        assert_eq!(
            parse_progress_line("  0% Installing"),
            Some((0, "Installing".into()))
        );
        assert_eq!(
            parse_progress_line(" 40% Copying image to rootfs.1"),
            Some((40, "Copying image to rootfs.1".into()))
        );
        assert_eq!(
            parse_progress_line("100% Installing done."),
            Some((100, "Installing done.".into()))
        );
        assert_eq!(
            parse_progress_line("Installing `/data/upload.raucb` succeeded"),
            None
        );
        assert_eq!(parse_progress_line("LastError: x"), None);
    }

    #[test]
    fn errors_in_plain_words() {
        let k = |e: &str| classify(e, None).kind;
        assert_eq!(
            k(
                "Failed to check bundle identifier: Compatible mismatch: Expected 'irtrack-qemu-arm64' but bundle manifest has 'other'"
            ),
            RefusalKind::OtherBoard
        );
        assert_eq!(
            k("Signature size (123456789) exceeds bundle size"),
            RefusalKind::Truncated
        );
        assert_eq!(
            k("signature verification failed: Verify error:unable to get local issuer certificate"),
            RefusalKind::Signature
        );
        let handler = LastUpdate::parse(
            "outcome=refused\nversion=0.0.0\ndetail=refused: downgrade from 1.2.0 to 0.0.0\n",
        );
        let r = classify("Installation error: Pre-install handler error", handler.as_ref());
        assert_eq!(r.kind, RefusalKind::Downgrade);
        assert_eq!(r.reason, "refused: downgrade from 1.2.0 to 0.0.0");
    }
}
