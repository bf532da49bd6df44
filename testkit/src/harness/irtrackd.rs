//! irtrackd under test: its config, start with every endpoint on an ephemeral port of
//! 127.0.0.1 up to its ready line, the ready line's addresses, shutdown, the operator password.

use std::io::Write;
use std::net::SocketAddr;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::Duration;

use super::error::{Error, Result, io};
use super::process::Proc;

/// User name of the operator sign-in (HTTP Basic); irtrackd checks only the password.
pub const OPERATOR_USER: &str = "operator";

/// The addresses of irtrackd's ready line
/// (`irtrackd ready params=... stream=... binary=... status=...`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Ready {
    /// Parameter push listener.
    pub params: SocketAddr,
    /// NDJSON position stream.
    pub stream: SocketAddr,
    /// Binary position stream.
    pub binary: SocketAddr,
    /// HTTP status listener (status, set-up page, `/api/...`, robot control).
    pub status: SocketAddr,
    /// The whole line.
    pub line: String,
}

impl Ready {
    /// Parses a ready line.
    pub fn parse(line: &str) -> Result<Ready> {
        Ok(Ready {
            params: addr_field(line, "params=")?,
            stream: addr_field(line, "stream=")?,
            binary: addr_field(line, "binary=")?,
            status: addr_field(line, "status=")?,
            line: line.to_string(),
        })
    }
}

/// The socket address after `key` (e.g. `status=`) in a line of space-separated fields.
pub fn addr_field(line: &str, key: &str) -> Result<SocketAddr> {
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(key))
        .and_then(|a| a.parse().ok())
        .ok_or_else(|| Error::BadAddress {
            key: key.to_string(),
            line: line.to_string(),
        })
}

/// An irtrackd config file (docs/irtrackd.md), built key by key.
///
/// ```
/// # use irtrack_testkit::harness::IrtrackdConfig;
/// let text = IrtrackdConfig::simulated()
///     .set("service.control", true)
///     .set("source.sim.fps", 30.0)
///     .to_toml()
///     .unwrap();
/// assert!(text.contains("[source.sim]") && text.contains("fps = 30.0"));
/// ```
#[derive(Debug, Clone, Default)]
pub struct IrtrackdConfig {
    table: toml::Table,
    header: String,
    /// A key that could not be set: (key, reason), reported by `to_toml`.
    error: Option<(String, String)>,
}

impl IrtrackdConfig {
    /// An empty config (irtrackd's defaults).
    pub fn new() -> Self {
        Self::default()
    }

    /// Simulated cameras (`[source.sim]` with its defaults) and no status LEDs: what most
    /// tests and demos run.
    pub fn simulated() -> Self {
        Self::new()
            .set("source.sim", toml::Table::new())
            .set("leds.backend", "none")
    }

    /// Starts from TOML text.
    pub fn parse(text: &str) -> Result<Self> {
        let table = text.parse::<toml::Table>().map_err(|e| Error::Config {
            key: String::new(),
            reason: e.to_string(),
        })?;
        Ok(Self {
            table,
            ..Self::default()
        })
    }

    /// A comment line at the top of the file (who wrote it).
    pub fn comment(mut self, text: &str) -> Self {
        for line in text.lines() {
            self.header.push_str(&format!("# {line}\n"));
        }
        self
    }

    /// Sets `key` (dotted: `robot.safety.max_step_mm`), creating the tables on the way.
    pub fn set(mut self, key: &str, value: impl Into<toml::Value>) -> Self {
        if self.error.is_some() {
            return self;
        }
        let mut parts: Vec<&str> = key.split('.').collect();
        let Some(last) = parts.pop() else {
            return self;
        };
        let mut t = &mut self.table;
        for p in parts {
            let entry = t
                .entry(p.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            match entry {
                toml::Value::Table(inner) => t = inner,
                _ => {
                    self.error = Some((key.to_string(), format!("`{p}` is a value, not a table")));
                    return self;
                }
            }
        }
        t.insert(last.to_string(), value.into());
        self
    }

    /// The operator's Argon2id PHC string (`[service] operator_password_hash`, from
    /// [`operator_hash`]): change requests then need a sign-in.
    pub fn operator_hash(self, phc: &str) -> Self {
        self.set("service.operator_password_hash", phc)
    }

    /// The file's text.
    pub fn to_toml(&self) -> Result<String> {
        if let Some((key, reason)) = &self.error {
            return Err(Error::Config {
                key: key.clone(),
                reason: reason.clone(),
            });
        }
        let body = toml::to_string(&self.table).map_err(|e| Error::Config {
            key: String::new(),
            reason: e.to_string(),
        })?;
        Ok(format!("{}{body}", self.header))
    }

    /// Writes the file.
    pub fn write(&self, path: &Path) -> Result<()> {
        std::fs::write(path, self.to_toml()?).map_err(io(format!("writing {}", path.display())))
    }
}

/// A running irtrackd, killed on drop.
#[derive(Debug)]
pub struct Irtrackd {
    proc: Proc,
    ready: Ready,
}

impl Irtrackd {
    /// `irtrackd -c <config> --ephemeral-ports 127.0.0.1 --state-dir <state_dir>`, standard
    /// error discarded; add to it (environment, a log file for stderr) before [`Irtrackd::spawn`].
    pub fn command(bin: &Path, config: &Path, state_dir: &Path) -> Command {
        let mut cmd = Command::new(bin);
        cmd.arg("-c")
            .arg(config)
            .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
            .arg(state_dir)
            .stderr(Stdio::null());
        cmd
    }

    /// Starts `cmd` (from [`Irtrackd::command`]) and waits up to `timeout` for the ready line.
    pub fn spawn(cmd: &mut Command, timeout: Duration) -> Result<Irtrackd> {
        let mut proc = Proc::spawn(cmd, "irtrackd")?;
        let line = proc.wait_line("irtrackd ready", timeout)?;
        Ok(Irtrackd {
            proc,
            ready: Ready::parse(&line)?,
        })
    }

    /// [`Irtrackd::command`] + [`Irtrackd::spawn`].
    pub fn start(bin: &Path, config: &Path, state_dir: &Path, timeout: Duration) -> Result<Irtrackd> {
        Self::spawn(&mut Self::command(bin, config, state_dir), timeout)
    }

    /// The ready line's addresses.
    pub fn ready(&self) -> &Ready {
        &self.ready
    }

    /// The process (pid, further stdout lines).
    pub fn proc_mut(&mut self) -> &mut Proc {
        &mut self.proc
    }

    /// Process id.
    pub fn pid(&self) -> u32 {
        self.proc.pid()
    }

    /// SIGTERM and up to `grace` for a clean exit (SIGKILL after); says how it ended.
    pub fn shutdown(mut self, grace: Duration) -> Result<String> {
        self.proc.terminate(grace)
    }
}

/// `[service] operator_password_hash` for `password`, made by the irtrackd binary itself
/// (`irtrackd --hash-password`, password on standard input), as an integrator would.
pub fn operator_hash(irtrackd: &Path, password: &str) -> Result<String> {
    let what = format!("{} --hash-password", irtrackd.display());
    let mut child = Command::new(irtrackd)
        .arg("--hash-password")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|source| Error::Spawn {
            program: irtrackd.to_path_buf(),
            source,
        })?;
    if let Some(mut stdin) = child.stdin.take() {
        stdin
            .write_all(format!("{password}\n").as_bytes())
            .map_err(io(what.clone()))?;
    }
    let out = child.wait_with_output().map_err(io(what.clone()))?;
    let phc = String::from_utf8_lossy(&out.stdout).trim().to_string();
    if !out.status.success() || !phc.starts_with("$argon2id$") {
        return Err(Error::Failed {
            what,
            detail: format!(
                "{}: {phc:?} {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        });
    }
    Ok(phc)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ready_line_addresses() {
        let r = Ready::parse(
            "irtrackd ready params=127.0.0.1:1 stream=127.0.0.1:2 binary=127.0.0.1:3 status=127.0.0.1:4",
        )
        .unwrap();
        assert_eq!(r.status.port(), 4);
        assert_eq!(r.binary.port(), 3);
        let e = Ready::parse("irtrackd ready params=x").unwrap_err().to_string();
        assert!(e.contains("`params=` missing or not an address"), "{e}");
    }

    #[test]
    fn config_builder_writes_nested_tables() {
        let text = IrtrackdConfig::simulated()
            .comment("written by a test")
            .operator_hash("$argon2id$x")
            .set("robot.address", "127.0.0.1:9")
            .set("robot.safety.workspace_min_mm", vec![-1.0, -2.0, 0.0])
            .set("robot.safety.max_age_ms", 200)
            .to_toml()
            .unwrap();
        assert!(text.starts_with("# written by a test\n"), "{text}");
        let back: toml::Table = text.parse().unwrap();
        assert_eq!(back["robot"]["safety"]["max_age_ms"].as_integer(), Some(200));
        assert_eq!(back["leds"]["backend"].as_str(), Some("none"));
        assert!(back["source"]["sim"].as_table().unwrap().is_empty());
        assert_eq!(
            back["service"]["operator_password_hash"].as_str(),
            Some("$argon2id$x")
        );
        let bad = IrtrackdConfig::new()
            .set("a", 1)
            .set("a.b", 2)
            .to_toml()
            .unwrap_err();
        assert!(bad.to_string().contains("`a` is a value"), "{bad}");
        let parsed = IrtrackdConfig::parse("[service]\ncontrol = true\n")
            .unwrap()
            .set("service.params_from_simulator", false)
            .to_toml()
            .unwrap();
        assert!(parsed.contains("control = true") && parsed.contains("params_from_simulator = false"));
    }
}
