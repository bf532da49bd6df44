//! The simulated system: two slots as files in a directory, for irtrackd on a PC or with the
//! simulator. It checks a bundle as the board would — layout, signature against the
//! configured CA (`openssl cms -verify`), board type and version from its manifest
//! (`unsquashfs -cat`) — and then "writes" the other slot by copying the bundle's image into
//! `slot-<X>.img`. Restarting irtrackd stands for the reboot: the slot installed last runs.
//!
//! A reboot asked for after an install (`reboot=1`) is recorded in [`REBOOT_REQUESTED`] (whoever
//! runs the simulated board restarts irtrackd on seeing it; tests assert it); the next start
//! removes it. [`FAIL_NEXT_BOOT`] stands for a new system that never becomes healthy: the next
//! start stays on the running slot and records a rollback, as the board's bootloader would.

use std::collections::BTreeMap;
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

use super::{
    Installed, LastUpdate, Progress, Refusal, RefusalKind, SlotInfo, SystemSlots, SystemUpdater,
    UpdateConfig, bundle, is_downgrade, utc_now,
};
use crate::error::{FirmwareError, Result};

const STATE_FILE: &str = "state.json";
/// Present in the directory: the next downgrade is allowed once (as `/data/rauc/allow-downgrade`).
pub const ALLOW_DOWNGRADE: &str = "allow-downgrade";
/// Written when a reboot is asked for after an install (`key=value`: `slot`, `version`,
/// `time`); removed by the next start, the simulated reboot.
pub const REBOOT_REQUESTED: &str = "reboot-requested";
/// Present at a start that would boot a newly installed slot: that slot "fails" its boots and
/// the running one stays (a simulated rollback). Removed when used.
pub const FAIL_NEXT_BOOT: &str = "fail-next-boot";

#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct SimSlot {
    version: Option<String>,
    build: Option<String>,
    good: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct SimState {
    booted: String,
    boot_next: String,
    slots: BTreeMap<String, SimSlot>,
}

/// See the module documentation.
pub struct SimUpdater {
    dir: PathBuf,
    ca_cert: PathBuf,
    compatible: String,
    last_update: PathBuf,
    state: Mutex<SimState>,
}

fn other(slot: &str) -> &'static str {
    if slot == "A" { "B" } else { "A" }
}

impl SimUpdater {
    /// Opens (or creates) the simulated system in `dir`. If an install chose the other slot
    /// to boot next, this start is its boot.
    pub fn open(cfg: &UpdateConfig, dir: &Path) -> Result<Self> {
        let storage = |source| FirmwareError::Storage {
            path: dir.display().to_string(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(storage)?;
        let path = dir.join(STATE_FILE);
        let last_update = dir.join("last-update");
        let mut state = match std::fs::read_to_string(&path) {
            Ok(text) => serde_json::from_str::<SimState>(&text).map_err(|e| FirmwareError::Config {
                reason: format!(
                    "simulated system {}: {e}; remove the directory to start over",
                    path.display()
                ),
            })?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => SimState {
                booted: "A".into(),
                boot_next: "A".into(),
                slots: BTreeMap::from([
                    (
                        "A".to_string(),
                        SimSlot {
                            version: Some(cfg.running_version.clone()),
                            build: Some("simulated".into()),
                            good: true,
                        },
                    ),
                    ("B".to_string(), SimSlot::default()),
                ]),
            },
            Err(e) => return Err(storage(e)),
        };
        // This start is the reboot that was asked for.
        let _ = std::fs::remove_file(dir.join(REBOOT_REQUESTED));
        let fail = dir.join(FAIL_NEXT_BOOT);
        if state.boot_next != state.booted && fail.exists() {
            let _ = std::fs::remove_file(&fail);
            let failed = std::mem::replace(&mut state.boot_next, state.booted.clone());
            let failed_version = match state.slots.get_mut(&failed) {
                Some(slot) => {
                    slot.good = false;
                    slot.version.clone().unwrap_or_default()
                }
                None => String::new(),
            };
            let version = state
                .slots
                .get(&state.booted)
                .and_then(|s| s.version.clone())
                .unwrap_or_default();
            let lu = LastUpdate {
                time: utc_now(),
                version: version.clone(),
                outcome: "rolled-back".into(),
                ok: false,
                slot: Some(state.booted.clone()),
                detail: format!(
                    "slot {failed} (version {failed_version}) did not become healthy (simulated, {FAIL_NEXT_BOOT}); back on slot {} (version {version})",
                    state.booted
                ),
            };
            lu.write(&last_update)?;
        } else if state.boot_next != state.booted {
            state.booted = state.boot_next.clone();
            let slot = state.slots.get(&state.booted).cloned().unwrap_or_default();
            let version = slot.version.unwrap_or_default();
            let lu = LastUpdate {
                time: utc_now(),
                version: version.clone(),
                outcome: "healthy".into(),
                ok: true,
                slot: Some(state.booted.clone()),
                detail: format!("simulated reboot: slot {} runs {version}", state.booted),
            };
            lu.write(&last_update)?;
        }
        let me = Self {
            dir: dir.to_path_buf(),
            ca_cert: cfg.ca_cert.clone(),
            compatible: cfg.compatible.clone(),
            last_update,
            state: Mutex::new(state),
        };
        me.save()?;
        Ok(me)
    }

    fn save(&self) -> Result<()> {
        let path = self.dir.join(STATE_FILE);
        let storage = |source| FirmwareError::Storage {
            path: path.display().to_string(),
            source,
        };
        let text = {
            let st = self.state.lock().map_err(|_| FirmwareError::Thread {
                what: "simulated system",
                reason: "state lock poisoned".into(),
            })?;
            serde_json::to_string_pretty(&*st).unwrap_or_default()
        };
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, text).map_err(storage)?;
        std::fs::rename(&tmp, &path).map_err(storage)
    }

    fn running_version(&self) -> Option<String> {
        let st = self.state.lock().ok()?;
        st.slots.get(&st.booted).and_then(|s| s.version.clone())
    }

    /// Records a refusal found after the manifest was read (so the version is known).
    fn refuse(&self, kind: RefusalKind, version: &str, reason: String) -> Refusal {
        let lu = LastUpdate {
            time: utc_now(),
            version: version.to_string(),
            outcome: "refused".into(),
            ok: false,
            slot: None,
            detail: reason.clone(),
        };
        let _ = lu.write(&self.last_update);
        Refusal::new(kind, reason)
    }

    fn verify_signature(
        &self,
        path: &Path,
        layout: bundle::BundleLayout,
    ) -> std::result::Result<(), Refusal> {
        let failed = |what: String| Refusal::new(RefusalKind::Failed, what);
        if !self.ca_cert.is_file() {
            return Err(failed(format!(
                "this board has no update CA certificate at {} ([update] ca_cert)",
                self.ca_cert.display()
            )));
        }
        let mut f = std::fs::File::open(path).map_err(|e| failed(format!("reading the bundle: {e}")))?;
        let mut sig = vec![0u8; layout.signature_len as usize];
        f.seek(SeekFrom::Start(layout.payload_len))
            .and_then(|_| f.read_exact(&mut sig))
            .map_err(|e| failed(format!("reading the signature: {e}")))?;
        let sig_path = self.dir.join(".signature.der");
        std::fs::write(&sig_path, &sig)
            .map_err(|e| failed(format!("writing {}: {e}", sig_path.display())))?;
        let mut child = Command::new("openssl")
            .args(["cms", "-verify", "-binary", "-inform", "DER", "-in"])
            .arg(&sig_path)
            .args(["-content", "/dev/stdin", "-CAfile"])
            .arg(&self.ca_cert)
            .args(["-out", "/dev/null"])
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| failed(format!("cannot run openssl to check the signature: {e}")))?;
        // The signed content is the image part of the file; feed exactly that.
        if let Some(mut stdin) = child.stdin.take() {
            let _ = f.seek(SeekFrom::Start(0));
            let mut image = (&mut f).take(layout.payload_len);
            let _ = std::io::copy(&mut image, &mut stdin);
            let _ = stdin.flush();
        }
        let out = child
            .wait_with_output()
            .map_err(|e| failed(format!("openssl did not finish: {e}")))?;
        let _ = std::fs::remove_file(&sig_path);
        if out.status.success() {
            return Ok(());
        }
        let why = String::from_utf8_lossy(&out.stderr);
        let first = why
            .lines()
            .find(|l| l.contains("error") || l.contains("fail"))
            .unwrap_or("")
            .trim();
        Err(Refusal::new(
            RefusalKind::Signature,
            format!(
                "wrong signature: the bundle is not signed by a key this board trusts (CA {}), or it was changed after signing{}",
                self.ca_cert.display(),
                if first.is_empty() {
                    String::new()
                } else {
                    format!(" (openssl: {first})")
                }
            ),
        ))
    }
}

/// `[update]` values of a RAUC manifest (INI text).
fn manifest_values(text: &str) -> BTreeMap<String, String> {
    let mut section = String::new();
    let mut out = BTreeMap::new();
    for line in text.lines().map(str::trim) {
        if let Some(s) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            section = s.to_string();
        } else if section == "update"
            && let Some((k, v)) = line.split_once('=')
        {
            out.insert(k.trim().to_string(), v.trim().to_string());
        }
    }
    out
}

impl SystemUpdater for SimUpdater {
    fn backend(&self) -> &'static str {
        "simulated"
    }

    fn slots(&self) -> std::result::Result<SystemSlots, String> {
        let st = self.state.lock().map_err(|_| "state lock poisoned".to_string())?;
        let info = |name: &str, booted: bool| {
            let s = st.slots.get(name).cloned().unwrap_or_default();
            let state = match (booted, s.version.is_some(), s.good) {
                (true, _, _) => "booted",
                (false, false, _) => "empty",
                (false, true, true) => "good",
                (false, true, false) => "bad",
            };
            SlotInfo {
                slot: name.to_string(),
                version: s.version,
                build: s.build,
                state: state.into(),
            }
        };
        Ok(SystemSlots {
            compatible: Some(self.compatible.clone()),
            running: Some(info(&st.booted, true)),
            other: Some(info(other(&st.booted), false)),
            boot_next: Some(st.boot_next.clone()),
        })
    }

    fn slots_are_cheap(&self) -> bool {
        true
    }

    fn last_update_file(&self) -> &Path {
        &self.last_update
    }

    fn install(&self, path: &Path, progress: Progress) -> std::result::Result<Installed, Refusal> {
        progress(2, "checking the bundle");
        let layout = bundle::inspect(path)?;
        progress(5, "checking the signature");
        self.verify_signature(path, layout)?;
        progress(30, "reading the manifest");
        let out = Command::new("unsquashfs")
            .args(["-cat"])
            .arg(path)
            .arg("manifest.raucm")
            .output()
            .map_err(|e| Refusal::new(RefusalKind::Failed, format!("cannot run unsquashfs: {e}")))?;
        let manifest = manifest_values(&String::from_utf8_lossy(&out.stdout));
        let (Some(compatible), Some(version)) = (manifest.get("compatible"), manifest.get("version")) else {
            return Err(Refusal::new(
                RefusalKind::NotABundle,
                "the bundle has no manifest with a compatible and a version",
            ));
        };
        if *compatible != self.compatible {
            return Err(self.refuse(
                RefusalKind::OtherBoard,
                version,
                format!(
                    "made for another board: the bundle is for '{compatible}', this board is '{}'",
                    self.compatible
                ),
            ));
        }
        let running = self.running_version().unwrap_or_default();
        if is_downgrade(version, &running) {
            let flag = self.dir.join(ALLOW_DOWNGRADE);
            if flag.exists() {
                let _ = std::fs::remove_file(&flag);
            } else {
                return Err(self.refuse(
                    RefusalKind::Downgrade,
                    version,
                    format!(
                        "refused: downgrade from {running} to {version} (create {} to allow one)",
                        flag.display()
                    ),
                ));
            }
        }
        let target = {
            let st = self
                .state
                .lock()
                .map_err(|_| Refusal::new(RefusalKind::Failed, "state lock poisoned"))?;
            other(&st.booted)
        };
        // "Write" the slot: copy the image with progress, as RAUC copies it to the partition.
        let io = |e: std::io::Error| Refusal::new(RefusalKind::Failed, format!("writing slot {target}: {e}"));
        let mut src = std::fs::File::open(path).map_err(io)?;
        let slot_path = self.dir.join(format!("slot-{target}.img"));
        let mut dst = std::fs::File::create(&slot_path).map_err(io)?;
        let mut left = layout.payload_len;
        let mut buf = vec![0u8; 1 << 20];
        while left > 0 {
            let n = (left as usize).min(buf.len());
            src.read_exact(&mut buf[..n]).map_err(io)?;
            dst.write_all(&buf[..n]).map_err(io)?;
            left -= n as u64;
            let done = layout.payload_len - left;
            let pct = 40 + (done * 55 / layout.payload_len.max(1)) as u8;
            progress(pct, &format!("writing slot {target}"));
        }
        dst.sync_all().map_err(io)?;
        {
            let mut st = self
                .state
                .lock()
                .map_err(|_| Refusal::new(RefusalKind::Failed, "state lock poisoned"))?;
            st.slots.insert(
                target.to_string(),
                SimSlot {
                    version: Some(version.clone()),
                    build: manifest.get("build").cloned(),
                    good: true,
                },
            );
            st.boot_next = target.to_string();
        }
        self.save()
            .map_err(|e| Refusal::new(RefusalKind::Failed, format!("saving the slot state: {e}")))?;
        let lu = LastUpdate {
            time: utc_now(),
            version: version.clone(),
            outcome: "installed".into(),
            ok: true,
            slot: Some(target.to_string()),
            detail: format!(
                "installed into slot {target}; restart irtrackd (the simulated reboot) to start it"
            ),
        };
        let _ = lu.write(&self.last_update);
        progress(100, "installed");
        Ok(Installed {
            slot: target.to_string(),
            version: version.clone(),
        })
    }

    fn request_reboot(&self, installed: &Installed) -> std::result::Result<String, String> {
        let path = self.dir.join(REBOOT_REQUESTED);
        let text = format!(
            "slot={}\nversion={}\ntime={}\n",
            installed.slot,
            installed.version,
            utc_now()
        );
        std::fs::write(&path, text)
            .map_err(|e| format!("recording the reboot in {}: {e}", path.display()))?;
        Ok(format!(
            "simulated: recorded in {}; restart irtrackd (the simulated reboot) to boot slot {}",
            path.display(),
            installed.slot
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifest_update_section() {
        let m = manifest_values(
            "[update]\ncompatible=irtrack-qemu-arm64\nversion=1.2.0\nbuild=abc\n\n[image.rootfs]\nfilename=rootfs.ext4\nversion=9\n",
        );
        assert_eq!(
            m.get("compatible").map(String::as_str),
            Some("irtrack-qemu-arm64")
        );
        assert_eq!(m.get("version").map(String::as_str), Some("1.2.0"));
        assert_eq!(m.get("filename"), None);
    }
}
