//! `host-tools update push`: upload a signed update bundle (`cargo xtask image bundle`) to a
//! board's irtrackd (`POST /api/update`, docs/updates.md), show the upload and install
//! progress, and exit non-zero with the board's reason when it refuses the bundle.
//!
//! The password is checked first (`POST /api/login`), so a wrong one is told before tens of
//! megabytes are sent; the board's `/status` tells whether it takes updates at all, its size
//! limit and whether another install runs. The upload then streams the file (HTTP Basic),
//! and the install's progress and outcome are read from `/status` → `system.install`.

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
}

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
    let get_system = || -> Result<serde_json::Value> {
        match agent.get(&status).call() {
            Ok(r) => {
                let v: serde_json::Value =
                    serde_json::from_str(&r.into_string()?).context("/status of irtrackd is not JSON")?;
                Ok(v.get("system").cloned().unwrap_or(serde_json::Value::Null))
            }
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
    let sys = get_system()?;
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
    let answer = agent
        .post(&format!("{base}/api/update"))
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
        let sys = get_system()?;
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
                return Ok(format!(
                    "installed {version} into slot {slot} in {:.1} s; reboot the board to start it (it falls back by itself if the new system does not come up healthy)",
                    started.elapsed().as_secs_f64()
                ));
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
