//! `host-tools update push`: upload a signed update bundle (`cargo xtask image bundle`) to a
//! board's irtrackd (`POST /api/update`, docs/updates.md), show the upload and install
//! progress, and exit non-zero with the board's reason when it refuses the bundle.
//!
//! The password is checked first (`POST /api/login`), so a wrong one is told before tens of
//! megabytes are sent; the board's `/status` tells whether it takes updates at all, its size
//! limit and whether another install runs. The upload then streams the file (HTTP Basic),
//! and the install's progress and outcome are read from `/status` → `system.install`.
//!
//! With `--reboot` the upload asks the board to reboot into the new system once it is
//! installed (`POST /api/update?reboot=1`); the command then waits, within
//! `--reboot-timeout-s`, for the board to go down and answer again, and reports the slot and
//! version it runs and whether the health check marked it good. Exit codes: 0 done (and with
//! `--reboot`: back on the new slot, marked good), 1 refused or any other error,
//! [`EXIT_ROLLED_BACK`] back on the old slot, [`EXIT_NOT_BACK`] not back healthy in time.

use std::fmt;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use base64::Engine as _;

use crate::cmd::capture::status_url;

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The action (`push`).
    #[command(subcommand)]
    pub action: Action,
}

/// What to do.
#[derive(clap::Subcommand, Debug)]
pub enum Action {
    /// Upload a bundle and install it into the board's other slot.
    Push(PushArgs),
}

/// `update push`.
#[derive(clap::Args, Debug)]
pub struct PushArgs {
    /// The board running irtrackd: HOST or HOST:PORT (port 7704 if left out).
    #[arg(long, value_name = "HOST[:PORT]")]
    pub board: String,
    /// File holding the board's operator password (first line).
    #[arg(long, value_name = "FILE")]
    pub password_file: PathBuf,
    /// The signed bundle (`.raucb`).
    pub bundle: PathBuf,
    /// Longest wait for the install after the upload, seconds.
    #[arg(long, default_value_t = 900.0)]
    pub install_timeout_s: f64,
    /// Reboot the board into the update once it is installed, wait for it to come back and
    /// report what it runs (exit 3: back on the old slot, rolled back; 4: not back healthy in
    /// time).
    #[arg(long)]
    pub reboot: bool,
    /// With --reboot: longest wait for the board to come back healthy, seconds (a rollback
    /// takes three failed boots of the new system, each up to its health timeout).
    #[arg(long, default_value_t = 900.0)]
    pub reboot_timeout_s: f64,
}

/// Exit code: the board came back on the slot it ran before (the update was rolled back).
pub const EXIT_ROLLED_BACK: u8 = 3;
/// Exit code: the board did not come back healthy within `--reboot-timeout-s` (or could not
/// reboot).
pub const EXIT_NOT_BACK: u8 = 4;

/// An end of `update push --reboot` with its own exit code ([`EXIT_ROLLED_BACK`],
/// [`EXIT_NOT_BACK`]); `main` exits with `code`.
#[derive(Debug)]
pub struct PushExit {
    /// The process exit code.
    pub code: u8,
    /// What happened, in plain words.
    pub message: String,
}

impl fmt::Display for PushExit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for PushExit {}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    match args.action {
        Action::Push(a) => push(&a, &mut |line| eprintln!("{line}")).map(|msg| println!("{msg}")),
    }
}

fn read_password(path: &Path) -> Result<String> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading the operator password from {}", path.display()))?;
    let pw = text.lines().next().unwrap_or("").to_string();
    if pw.is_empty() {
        bail!("{} holds no password (its first line is empty)", path.display());
    }
    Ok(pw)
}

/// The body of an error answer: the `reason` of a JSON refusal, else the text.
fn reason_of(body: &str) -> String {
    serde_json::from_str::<serde_json::Value>(body)
        .ok()
        .and_then(|v| v.get("reason").and_then(|r| r.as_str()).map(str::to_string))
        .unwrap_or_else(|| body.trim().to_string())
}

/// Counts bytes read and logs every further 10 %.
struct Counted<'a, R> {
    inner: R,
    done: u64,
    total: u64,
    next_pct: u64,
    log: &'a mut dyn FnMut(&str),
}

impl<R: Read> Read for Counted<'_, R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.done += n as u64;
        let pct = self.done * 100 / self.total.max(1);
        if pct >= self.next_pct {
            (self.log)(&format!(
                "upload: {pct:3}% ({:.1} of {:.1} MiB)",
                self.done as f64 / 1048576.0,
                self.total as f64 / 1048576.0
            ));
            self.next_pct = (pct / 10 + 1) * 10;
        }
        Ok(n)
    }
}

/// Pushes the bundle; `log` gets the progress lines. Returns the closing message.
pub fn push(a: &PushArgs, log: &mut dyn FnMut(&str)) -> Result<String> {
    let password = read_password(&a.password_file)?;
    let meta = std::fs::metadata(&a.bundle).with_context(|| format!("reading {}", a.bundle.display()))?;
    let total = meta.len();
    let status = status_url(&a.board);
    let base = status.trim_end_matches("/status").to_string();
    let agent = ureq::AgentBuilder::new()
        .timeout_connect(Duration::from_secs(10))
        .timeout_read(Duration::from_secs(60))
        .build();
    let unreachable = |e: ureq::Transport| {
        anyhow!(
            "cannot reach irtrackd on {} ({base}): {e}; is the board on and irtrackd running?",
            a.board
        )
    };
    let get_status = || -> Result<serde_json::Value> {
        match agent.get(&status).call() {
            Ok(r) => serde_json::from_str(&r.into_string()?).context("/status of irtrackd is not JSON"),
            Err(ureq::Error::Status(code, r)) => {
                bail!(
                    "irtrackd on {} answered {code} to /status: {}",
                    a.board,
                    r.into_string().unwrap_or_default()
                )
            }
            Err(ureq::Error::Transport(t)) => Err(unreachable(t)),
        }
    };
    let get_system = || -> Result<serde_json::Value> {
        Ok(get_status()?
            .get("system")
            .cloned()
            .unwrap_or(serde_json::Value::Null))
    };
    let sys = get_system()?;
    let slot_before = sys
        .get("running")
        .and_then(|r| r.get("slot"))
        .and_then(|s| s.as_str())
        .map(str::to_string);
    match sys.get("backend").and_then(|b| b.as_str()) {
        None => bail!(
            "irtrackd on {} does not report its system (/status has no system): update its firmware by hand once",
            a.board
        ),
        Some("none") => bail!(
            "irtrackd on {} has no system updater ([update] backend is none, or no RAUC on the board)",
            a.board
        ),
        Some(_) => {}
    }
    if let Some(max) = sys.get("max_bundle_bytes").and_then(|m| m.as_u64())
        && total > max
    {
        bail!(
            "{} is {:.1} MiB; the board accepts at most {} MiB ([update] max_bundle_mib)",
            a.bundle.display(),
            total as f64 / 1048576.0,
            max >> 20
        );
    }
    // The password first: a wrong one is told before the bundle is sent.
    let login = agent
        .post(&format!("{base}/api/login"))
        .set("Content-Type", "application/json")
        .send_string(&serde_json::json!({ "password": password }).to_string());
    match login {
        Ok(_) => {}
        Err(ureq::Error::Status(code, r)) => bail!(
            "irtrackd on {} refused the sign-in ({code}): {}",
            a.board,
            r.into_string().unwrap_or_default().trim()
        ),
        Err(ureq::Error::Transport(t)) => return Err(unreachable(t)),
    }

    log(&format!(
        "uploading {} ({:.1} MiB) to {}",
        a.bundle.display(),
        total as f64 / 1048576.0,
        a.board
    ));
    let file = std::fs::File::open(&a.bundle).with_context(|| format!("opening {}", a.bundle.display()))?;
    let body = Counted {
        inner: file,
        done: 0,
        total,
        next_pct: 10,
        log: &mut *log,
    };
    let cred = base64::engine::general_purpose::STANDARD.encode(format!("operator:{password}"));
    let started = Instant::now();
    let url = if a.reboot {
        format!("{base}/api/update?reboot=1")
    } else {
        format!("{base}/api/update")
    };
    let answer = agent
        .post(&url)
        .set("Authorization", &format!("Basic {cred}"))
        .set("Content-Type", "application/octet-stream")
        .set("Content-Length", &total.to_string())
        .send(body);
    let id = match answer {
        Ok(r) => {
            let v: serde_json::Value =
                serde_json::from_str(&r.into_string()?).context("upload answer is not JSON")?;
            v.get("id")
                .and_then(|i| i.as_u64())
                .ok_or_else(|| anyhow!("the board's upload answer has no job id: {v}"))?
        }
        Err(ureq::Error::Status(code, r)) => {
            let body = r.into_string().unwrap_or_default();
            bail!("the board refused the bundle ({code}): {}", reason_of(&body));
        }
        Err(ureq::Error::Transport(t)) => {
            // The board may have refused and closed while the body was still being sent.
            let why = get_system()
                .ok()
                .and_then(|s| s.get("install").cloned())
                .and_then(|j| {
                    j.get("refusal")
                        .and_then(|r| r.get("reason"))
                        .and_then(|r| r.as_str())
                        .map(str::to_string)
                });
            match why {
                Some(reason) => bail!("the board refused the bundle: {reason}"),
                None => bail!("the upload to {} failed: {t}", a.board),
            }
        }
    };
    log(&format!(
        "upload done in {:.1} s; installing",
        started.elapsed().as_secs_f64()
    ));

    let deadline = Instant::now() + Duration::from_secs_f64(a.install_timeout_s.max(1.0));
    let mut last_step = String::new();
    loop {
        let st = get_status()?;
        let sys = st.get("system").cloned().unwrap_or_default();
        let job = sys.get("install").cloned().unwrap_or_default();
        if job.get("id").and_then(|i| i.as_u64()) != Some(id) {
            bail!("the board no longer reports this install (irtrackd restarted?); check its /status");
        }
        let state = job.get("state").and_then(|s| s.as_str()).unwrap_or("");
        let step = format!(
            "install: {:3}% {}",
            job.get("percent").and_then(|p| p.as_u64()).unwrap_or(0),
            job.get("step").and_then(|s| s.as_str()).unwrap_or("")
        );
        if step != last_step && state == "installing" {
            log(&step);
            last_step = step;
        }
        match state {
            "installed" => {
                let version = job.get("version").and_then(|v| v.as_str()).unwrap_or("?");
                let slot = sys
                    .get("other")
                    .and_then(|o| o.get("slot"))
                    .and_then(|s| s.as_str())
                    .unwrap_or("?");
                let installed = format!(
                    "installed {version} into slot {slot} in {:.1} s",
                    started.elapsed().as_secs_f64()
                );
                if !a.reboot {
                    return Ok(format!(
                        "{installed}; reboot the board to start it (it falls back by itself if the new system does not come up healthy)"
                    ));
                }
                log(&format!("{installed}; the board reboots into it"));
                let target = Target {
                    slot: slot.to_string(),
                    version: version.to_string(),
                    slot_before: slot_before.clone(),
                };
                let uptime_s = st.get("uptime_s").and_then(|u| u.as_f64()).unwrap_or(0.0);
                let back = wait_for_reboot(a, &status, &target, uptime_s, log)?;
                return Ok(format!("{installed}; {back}"));
            }
            "refused" => {
                let reason = job
                    .get("refusal")
                    .and_then(|r| r.get("reason"))
                    .and_then(|r| r.as_str())
                    .unwrap_or("no reason given");
                bail!("the board refused the bundle: {reason}");
            }
            _ => {}
        }
        if Instant::now() > deadline {
            bail!(
                "the install did not finish within {} s; check the board's /status",
                a.install_timeout_s
            );
        }
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// What the board should come back running.
struct Target {
    slot: String,
    version: String,
    /// The slot it ran before the install (where a rollback lands).
    slot_before: Option<String>,
}

#[derive(Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// irtrackd of the old system still answers.
    NotYetDown,
    /// No answer.
    Down,
    /// irtrackd of a new boot answers.
    Up,
}

/// A string at `path` (dot-separated keys) in `v`.
fn str_at<'v>(v: &'v serde_json::Value, path: &str) -> Option<&'v str> {
    path.split('.')
        .try_fold(v, |v, k| v.get(k))
        .and_then(|x| x.as_str())
}

/// What one `/status` of the board after its reboot means.
#[derive(Debug, PartialEq, Eq)]
enum Verdict {
    /// Back on the new slot and marked good.
    Good(String),
    /// Back on the old slot.
    RolledBack(String),
    /// Not decided yet: what it shows now.
    Waiting(String),
}

/// Judges the `/status` of a new boot against what was installed.
fn judge(st: &serde_json::Value, t: &Target) -> Verdict {
    let slot = str_at(st, "system.running.slot");
    let version = str_at(st, "system.running.version").unwrap_or("?");
    let outcome = str_at(st, "system.last_update.outcome").unwrap_or("");
    let detail = str_at(st, "system.last_update.detail").unwrap_or("");
    match slot {
        None => Verdict::Waiting("irtrackd answers; it does not know its slots yet".into()),
        Some(s) if s == t.slot => {
            if outcome == "healthy" && version == t.version {
                Verdict::Good(format!("slot {s} runs {version}, healthy and marked good"))
            } else {
                Verdict::Waiting(format!(
                    "slot {s} runs {version}; waiting for the health check to mark it good (last update: {})",
                    if outcome.is_empty() { "none" } else { outcome }
                ))
            }
        }
        Some(s) => Verdict::RolledBack(format!(
            "the board came back on slot {s} (version {version}), not on slot {}: the update did not come up healthy and was rolled back{}",
            t.slot,
            if detail.is_empty() {
                String::new()
            } else {
                format!(" ({detail})")
            }
        )),
    }
}

/// Waits for the board to reboot into `t` and says how it came back: Ok when on the new slot
/// and marked good, [`PushExit`] otherwise.
fn wait_for_reboot(
    a: &PushArgs,
    status: &str,
    t: &Target,
    uptime_before_s: f64,
    log: &mut dyn FnMut(&str),
) -> Result<String> {
    // Short timeouts: a board that is down must not hold a request for a minute.
    let agent = ureq::AgentBuilder::new()
        .timeout_connect(Duration::from_secs(2))
        .timeout_read(Duration::from_secs(5))
        .build();
    let timeout = Duration::from_secs_f64(a.reboot_timeout_s.max(1.0));
    let t0 = Instant::now();
    let mut phase = Phase::NotYetDown;
    let mut last_uptime = uptime_before_s;
    let mut seen = "irtrackd of the old system still answers".to_string();
    let mut said = String::new();
    let mut last_progress = Instant::now();
    loop {
        let answer = agent
            .get(status)
            .call()
            .ok()
            .and_then(|r| r.into_string().ok())
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok());
        let secs = t0.elapsed().as_secs_f64();
        match answer {
            None => {
                if phase != Phase::Down {
                    log(&format!("reboot: the board is down ({secs:.1} s)"));
                    phase = Phase::Down;
                }
                seen = format!("no answer since {secs:.0} s");
            }
            Some(st) => {
                let uptime = st.get("uptime_s").and_then(|u| u.as_f64()).unwrap_or(0.0);
                // A fresh irtrackd: seen down, or its uptime started over.
                if phase == Phase::Down || (phase == Phase::NotYetDown && uptime + 1.0 < last_uptime) {
                    log(&format!("reboot: irtrackd answers again after {secs:.1} s"));
                    phase = Phase::Up;
                }
                last_uptime = uptime;
                if phase == Phase::NotYetDown && str_at(&st, "system.reboot.state") == Some("failed") {
                    return Err(PushExit {
                        code: EXIT_NOT_BACK,
                        message: format!(
                            "the board could not reboot: {}",
                            str_at(&st, "system.reboot.detail").unwrap_or("no reason given")
                        ),
                    }
                    .into());
                }
                if phase == Phase::Up {
                    match judge(&st, t) {
                        Verdict::Good(what) => {
                            return Ok(format!(
                                "rebooted: {what} {secs:.1} s after the reboot was asked for"
                            ));
                        }
                        Verdict::RolledBack(what) => {
                            return Err(PushExit {
                                code: EXIT_ROLLED_BACK,
                                message: format!("{what}; {secs:.0} s after the reboot was asked for"),
                            }
                            .into());
                        }
                        Verdict::Waiting(what) => {
                            if what != said {
                                log(&format!("reboot: {what}"));
                                said = what.clone();
                            }
                            seen = what;
                        }
                    }
                }
            }
        }
        if t0.elapsed() > timeout {
            let before = t.slot_before.as_deref().unwrap_or("?");
            return Err(PushExit {
                code: EXIT_NOT_BACK,
                message: format!(
                    "the board did not come back healthy within {:.0} s after the reboot was asked for (slot {before} before, {} {} installed): {seen}",
                    timeout.as_secs_f64(),
                    t.slot,
                    t.version
                ),
            }
            .into());
        }
        if last_progress.elapsed() >= Duration::from_secs(15) {
            log(&format!("reboot: {seen} ({secs:.0} s)"));
            last_progress = Instant::now();
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn target() -> Target {
        Target {
            slot: "B".into(),
            version: "1.2.0".into(),
            slot_before: Some("A".into()),
        }
    }

    fn status(slot: Option<&str>, version: &str, outcome: &str) -> serde_json::Value {
        serde_json::json!({
            "uptime_s": 3.0,
            "system": {
                "running": slot.map(|s| serde_json::json!({"slot": s, "version": version})),
                "last_update": {"outcome": outcome, "detail": "slot B did not become healthy"},
            }
        })
    }

    #[test]
    fn a_new_boot_is_judged_by_slot_version_and_health() {
        let t = target();
        assert!(matches!(
            judge(&status(Some("B"), "1.2.0", "healthy"), &t),
            Verdict::Good(w) if w == "slot B runs 1.2.0, healthy and marked good"
        ));
        // On the new slot, not yet marked good: keep waiting.
        assert!(matches!(
            judge(&status(Some("B"), "1.2.0", "installed"), &t),
            Verdict::Waiting(w) if w.contains("waiting for the health check")
        ));
        // Healthy, but another version than installed: not this update.
        assert!(matches!(
            judge(&status(Some("B"), "1.1.0", "healthy"), &t),
            Verdict::Waiting(_)
        ));
        match judge(&status(Some("A"), "1.1.0", "rolled-back"), &t) {
            Verdict::RolledBack(w) => {
                assert!(
                    w.contains("came back on slot A (version 1.1.0), not on slot B"),
                    "{w}"
                );
                assert!(w.contains("(slot B did not become healthy)"), "{w}");
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            judge(&status(None, "", ""), &t),
            Verdict::Waiting(w) if w.contains("does not know its slots")
        ));
    }

    #[test]
    fn exits_carry_their_code() {
        let e: anyhow::Error = PushExit {
            code: EXIT_ROLLED_BACK,
            message: "rolled back".into(),
        }
        .into();
        assert_eq!(e.downcast_ref::<PushExit>().map(|x| x.code), Some(3));
        assert_eq!(e.to_string(), "rolled back");
    }
}
