//! Shared plumbing: the repository context, running child processes with live output,
//! capture and a time limit, and small formatting helpers.

use std::ffi::OsString;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};

/// What every task and phase gets: where the repository is and how to call cargo.
pub struct Ctx {
    /// Workspace root (the directory holding the root `Cargo.toml`).
    pub root: PathBuf,
    /// The cargo that started us (`$CARGO`), so a rustup toolchain override is respected.
    pub cargo: OsString,
}

impl Ctx {
    pub fn new() -> Result<Self> {
        // xtask lives in <root>/xtask; CARGO_MANIFEST_DIR is baked in at compile time.
        let root = Path::new(env!("CARGO_MANIFEST_DIR"))
            .parent()
            .context("xtask manifest directory has no parent")?
            .to_path_buf();
        let cargo = std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into());
        Ok(Self { root, cargo })
    }

    /// `cargo` with the working directory at the workspace root and no standard input.
    ///
    /// Incremental compilation is off unless the caller's environment sets
    /// `CARGO_INCREMENTAL`: xtask's builds are one-shot (CI, demo, image), where incremental
    /// state only costs disk (gigabytes over the workspace's test binaries) and link time.
    pub fn cargo(&self) -> Command {
        let mut cmd = Command::new(&self.cargo);
        cmd.current_dir(&self.root);
        // `cargo xtask` is `cargo run`, which gives xtask its package's variables. Build
        // scripts such as ring's rerun when these change (`rerun-if-env-changed=
        // CARGO_MANIFEST_DIR`, ...), so a build started from xtask and the same build typed by
        // hand would each recompile ring and everything above it (Zenoh, irtrackd) in turn.
        for (name, _) in std::env::vars_os() {
            if name.to_str().is_some_and(is_cargo_run_var) {
                cmd.env_remove(&name);
            }
        }
        if std::env::var_os("CARGO_INCREMENTAL").is_none() {
            cmd.env("CARGO_INCREMENTAL", "0");
        }
        // Zenoh stamps its version with `git describe` at compile time (the git-version macro),
        // run in its own source directory under CARGO_HOME, and depends on that repository's
        // `.git/index`. With CARGO_HOME inside a git work tree (a CI cache kept in the project,
        // or a clone that holds its own cargo home), every git command that refreshes the index
        // made the next build compile Zenoh and all above it again: the demo's last step
        // rebuilt irtrackd that way. Git must not look above cargo's source trees for a repository.
        if let Some(ceilings) =
            cargo_home().and_then(|home| git_ceilings(&home, std::env::var_os("GIT_CEILING_DIRECTORIES")))
        {
            cmd.env("GIT_CEILING_DIRECTORIES", ceilings);
        }
        cmd
    }

    /// The PC tools; the caller adds the subcommand and its arguments. In a CI run after the
    /// host build, that build's `host-tools` ([`use_built_host_tools`]); otherwise `cargo run
    /// -q -p irtrack-host-tools --`. `cargo run -p` resolves features for host-tools alone and
    /// runs rustc without the host build's clippy wrapper, so in CI it compiled host-tools and
    /// the workspace crates under it a second time (about a minute here, in the image phase).
    pub fn host_tools(&self) -> Command {
        if let Some(exe) = BUILT_HOST_TOOLS.get() {
            let mut cmd = Command::new(exe);
            cmd.current_dir(&self.root);
            return cmd;
        }
        let mut cmd = self.cargo();
        cmd.args(["run", "-q", "-p", "irtrack-host-tools", "--"]);
        cmd
    }

    /// Base target directory of host builds (`$CARGO_TARGET_DIR` or `<root>/target`).
    pub fn target_dir(&self) -> PathBuf {
        match std::env::var_os("CARGO_TARGET_DIR") {
            Some(dir) if !dir.is_empty() => {
                let dir = PathBuf::from(dir);
                if dir.is_absolute() {
                    dir
                } else {
                    self.root.join(dir)
                }
            }
            _ => self.root.join("target"),
        }
    }
}

/// `host-tools` of the host build that finished in this run, for [`Ctx::host_tools`].
static BUILT_HOST_TOOLS: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();

/// Called by CI once its host build (every workspace target, current sources) has succeeded:
/// later phases run that build's `host-tools` instead of compiling it again. No effect when the
/// build left no such binary.
pub fn use_built_host_tools(ctx: &Ctx) {
    let exe = ctx.target_dir().join("debug/host-tools");
    if exe.is_file() {
        let _ = BUILT_HOST_TOOLS.set(exe);
    }
}

/// Result of a finished (or killed) child process.
pub struct Output {
    pub status: Option<ExitStatus>,
    pub timed_out: bool,
    /// Captured standard output (empty unless capture was requested).
    pub stdout: String,
    /// Captured standard error (empty unless capture was requested).
    pub stderr: String,
}

impl Output {
    pub fn success(&self) -> bool {
        !self.timed_out && self.status.is_some_and(|s| s.success())
    }

    /// Short description of how the process ended, for error messages.
    pub fn describe(&self) -> String {
        if self.timed_out {
            return "timed out and was killed".into();
        }
        match self.status {
            Some(s) => match s.code() {
                Some(code) => format!("exited with code {code}"),
                None => format!("ended by a signal ({s})"),
            },
            None => "did not finish".into(),
        }
    }
}

/// How to run a child process.
#[derive(Clone, Copy, Default)]
pub struct RunOpts {
    /// Keep a copy of stdout (it is still echoed live).
    pub capture_stdout: bool,
    /// Keep a copy of stderr (it is still echoed live).
    pub capture_stderr: bool,
    /// Kill the whole process tree after this long.
    pub timeout: Option<Duration>,
    /// Do not echo stdout (capture only).
    pub quiet_stdout: bool,
    /// Do not echo stderr (capture only).
    pub quiet_stderr: bool,
}

/// Quotes a command for display so it can be copied into a shell.
pub fn display_cmd(cmd: &Command) -> String {
    let mut parts = Vec::new();
    for (k, v) in cmd.get_envs() {
        if let Some(v) = v {
            parts.push(format!(
                "{}={}",
                k.to_string_lossy(),
                shell_quote(&v.to_string_lossy())
            ));
        }
    }
    parts.push(shell_quote(&cmd.get_program().to_string_lossy()));
    parts.extend(cmd.get_args().map(|a| shell_quote(&a.to_string_lossy())));
    parts.join(" ")
}

pub fn shell_quote(s: &str) -> String {
    let plain = !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./=:,+@%".contains(c));
    if plain {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

/// [`run`] with a time limit, for a step that must succeed: an error naming `what` (and how
/// it failed) unless the command exited successfully.
pub fn run_ok(cmd: &mut Command, what: &str, timeout: Duration, capture_stdout: bool) -> Result<Output> {
    let out = run(
        cmd,
        RunOpts {
            capture_stdout,
            timeout: Some(timeout),
            ..RunOpts::default()
        },
    )?;
    if !out.success() {
        anyhow::bail!("{what} {}", out.describe());
    }
    Ok(out)
}

/// Runs `cmd` with no standard input (CI has none; nothing may prompt), echoing its output
/// live and optionally capturing it. Returns an error only if the process could not start.
pub fn run(cmd: &mut Command, opts: RunOpts) -> Result<Output> {
    println!("$ {}", display_cmd(cmd));
    cmd.stdin(Stdio::null());
    // Always pipe: lines are echoed as they arrive, so output interleaves sensibly.
    cmd.stdout(Stdio::piped()).stderr(Stdio::piped());
    let mut child = cmd
        .spawn()
        .with_context(|| format!("could not start `{}`", display_cmd(cmd)))?;
    let out_pipe = child.stdout.take().context("child stdout missing")?;
    let err_pipe = child.stderr.take().context("child stderr missing")?;
    let echo_stdout = !opts.quiet_stdout;
    let out_thread = thread::spawn(move || pump(out_pipe, false, echo_stdout, opts.capture_stdout));
    let echo_stderr = !opts.quiet_stderr;
    let err_thread = thread::spawn(move || pump(err_pipe, true, echo_stderr, opts.capture_stderr));

    let start = Instant::now();
    let mut timed_out = false;
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break Some(status);
        }
        if opts.timeout.is_some_and(|t| start.elapsed() > t) {
            timed_out = true;
            eprintln!(
                "xtask: time limit reached, killing process tree of pid {}",
                child.id()
            );
            kill_tree(child.id());
            break child.wait().ok();
        }
        thread::sleep(Duration::from_millis(100));
    };
    // Grandchildren could keep the pipes open after a kill; they were killed with the tree.
    let stdout = out_thread.join().unwrap_or_default();
    let stderr = err_thread.join().unwrap_or_default();
    Ok(Output {
        status,
        timed_out,
        stdout,
        stderr,
    })
}

/// Copies a pipe to our stdout/stderr line by line (if `echo`), returning the text if `keep`.
fn pump(pipe: impl Read, to_stderr: bool, echo: bool, keep: bool) -> String {
    let mut reader = BufReader::new(pipe);
    let mut kept = String::new();
    let mut buf = Vec::new();
    loop {
        buf.clear();
        match reader.read_until(b'\n', &mut buf) {
            Ok(0) | Err(_) => break,
            Ok(_) => {
                let line = String::from_utf8_lossy(&buf);
                if echo && to_stderr {
                    let mut e = std::io::stderr().lock();
                    let _ = e.write_all(line.as_bytes());
                    let _ = e.flush();
                } else if echo {
                    let mut o = std::io::stdout().lock();
                    let _ = o.write_all(line.as_bytes());
                    let _ = o.flush();
                }
                if keep {
                    kept.push_str(&line);
                }
            }
        }
    }
    kept
}

/// Kills `pid` and all its descendants (found through /proc; test binaries run by cargo under
/// qemu would otherwise survive). The whole tree is listed before anything is killed, and
/// parents die first so none of them can react to a child's death.
fn kill_tree(pid: u32) {
    let mut pids = vec![pid];
    let mut i = 0;
    while i < pids.len() {
        let parent = pids[i];
        pids.extend(children_of(parent));
        i += 1;
    }
    let args: Vec<String> = pids.iter().map(|p| p.to_string()).collect();
    let _ = Command::new("kill")
        .arg("-KILL")
        .args(&args)
        .stderr(Stdio::null())
        .status();
}

fn children_of(parent: u32) -> Vec<u32> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for entry in entries.flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        if parse_ppid(&stat) == Some(parent) {
            out.push(pid);
        }
    }
    out
}

/// Parent pid from a /proc/<pid>/stat line; the command name may contain spaces and
/// parentheses, so fields are counted after the last ')'.
fn parse_ppid(stat: &str) -> Option<u32> {
    let rest = &stat[stat.rfind(')')? + 1..];
    rest.split_whitespace().nth(1)?.parse().ok()
}

/// Human-readable duration: `0.4s`, `12.3s`, `4m05s`.
pub fn fmt_duration(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s < 60.0 {
        format!("{s:.1}s")
    } else {
        format!("{}m{:02}s", d.as_secs() / 60, d.as_secs() % 60)
    }
}

/// CPU time (user + system) of every child process this process has waited for, as the kernel
/// sums it (`cutime` + `cstime` of /proc/self/stat): a child's own waited-for children are
/// included, daemons that were never reaped are not. `None` off Linux.
pub fn children_cpu() -> Option<Duration> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    children_cpu_from_stat(&stat)
}

/// Parses `cutime` and `cstime` (fields 16 and 17) of a /proc/PID/stat line. The command name
/// (field 2) may hold spaces and parentheses, so fields are counted after its last `)`.
fn children_cpu_from_stat(stat: &str) -> Option<Duration> {
    // USER_HZ, the unit of these fields, is 100 on every Linux architecture.
    const TICKS_PER_S: u64 = 100;
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut fields = rest.split_whitespace().skip(13); // state is field 3 -> index 0
    let cutime: u64 = fields.next()?.parse().ok()?;
    let cstime: u64 = fields.next()?.parse().ok()?;
    Some(Duration::from_millis((cutime + cstime) * 1000 / TICKS_PER_S))
}

/// Whether an executable named `name` is on PATH.
pub fn on_path(name: &str) -> bool {
    find_on_path(name).is_some()
}

pub fn find_on_path(name: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
}

pub fn is_root() -> bool {
    // `id -u` avoids a libc dependency; failure to run it means "assume not root".
    Command::new("id")
        .arg("-u")
        .output()
        .ok()
        .is_some_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

// ------------------------------------------------------------------ irtrackd harness
//
// The shared harness (`irtrack_testkit::harness`: processes, irtrackd, HTTP, WebSocket, JSON)
// with the demo's operator password; errors become anyhow errors with the harness's message.

pub use irtrack_testkit::harness::{Http, Irtrackd, IrtrackdConfig, LiveSocket, Proc, json};

/// Operator password the demo and soak configure on their irtrackd (changes need a sign-in).
pub const OPERATOR_PASSWORD: &str = "xtask-operator";

/// Long enough for a password check under full-system emulation (Argon2 in QEMU TCG).
pub const HTTP_TIMEOUT: Duration = Duration::from_secs(30);

/// `[service] operator_password_hash` for [`OPERATOR_PASSWORD`], made by the irtrackd binary
/// itself (`irtrackd --hash-password`), as an operator would.
pub fn operator_hash(irtrackd: &Path) -> Result<String> {
    Ok(irtrack_testkit::harness::operator_hash(
        irtrackd,
        OPERATOR_PASSWORD,
    )?)
}

/// One request to irtrackd's status listener; the status code and the trimmed body.
pub fn http(addr: SocketAddr, method: &str, path: &str) -> Result<(u16, String)> {
    let (code, body) = Http::new(HTTP_TIMEOUT).request(addr, method, path, None)?;
    Ok((code, body.trim().to_string()))
}

/// [`http`] signed in as the operator (HTTP Basic with [`OPERATOR_PASSWORD`]).
pub fn http_operator(addr: SocketAddr, method: &str, path: &str) -> Result<(u16, String)> {
    http_as(addr, method, path, OPERATOR_PASSWORD, "")
}

/// One request with a JSON body (none if empty), signed in with `password`.
pub fn http_as(
    addr: SocketAddr,
    method: &str,
    path: &str,
    password: &str,
    json_body: &str,
) -> Result<(u16, String)> {
    let body = (!json_body.is_empty()).then_some(json_body);
    let (code, answer) = Http::new(HTTP_TIMEOUT)
        .signed_in(password)
        .request(addr, method, path, body)?;
    Ok((code, answer.trim().to_string()))
}

/// The socket address after `key` (e.g. `status=`) in a line such as irtrackd's ready line.
pub fn addr_field(line: &str, key: &str) -> Result<SocketAddr> {
    Ok(irtrack_testkit::harness::irtrackd::addr_field(line, key)?)
}

/// Starts irtrackd with `config`, every port ephemeral on 127.0.0.1, and waits for its ready
/// line; killed when dropped.
pub fn start_irtrackd(irtrackd: &Path, config: &Path, state: &Path) -> Result<Irtrackd> {
    Irtrackd::start(irtrackd, config, state, Duration::from_secs(30))
        .with_context(|| format!("starting {} -c {}", irtrackd.display(), config.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn children_cpu_fields_parsed_after_command_name() {
        // pid (comm) state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt
        // utime stime cutime cstime ...
        let stat = "77 (a) b) c) S 1 77 77 0 -1 0 10 20 0 0 5 6 250 130 20 0";
        assert_eq!(children_cpu_from_stat(stat), Some(Duration::from_millis(3800)));
        assert_eq!(children_cpu_from_stat("77 (short) S 1 2"), None);
    }

    /// A child that burns CPU shows up in the sum once it has been waited for.
    #[test]
    fn children_cpu_grows_by_a_waited_for_childs_cpu() {
        let before = children_cpu().expect("Linux /proc");
        let status = Command::new("sh")
            .args(["-c", "i=0; while [ $i -lt 300000 ]; do i=$((i+1)); done"])
            .status()
            .unwrap();
        assert!(status.success());
        let grown = children_cpu().unwrap() - before;
        assert!(grown >= Duration::from_millis(50), "child CPU {grown:?}");
    }

    #[test]
    fn ppid_parsed_after_command_name_with_spaces_and_parens() {
        let stat = "1234 (my (odd) prog) S 42 1234 1234 0 -1 4194560";
        assert_eq!(parse_ppid(stat), Some(42));
        assert_eq!(parse_ppid("garbage"), None);
    }

    #[test]
    fn quoting_only_where_needed() {
        assert_eq!(shell_quote("qemu-aarch64"), "qemu-aarch64");
        assert_eq!(shell_quote("qemu-aarch64 -L /"), "'qemu-aarch64 -L /'");
        assert_eq!(shell_quote("it's"), r"'it'\''s'");
        assert_eq!(shell_quote(""), "''");
    }

    #[test]
    fn durations_format() {
        assert_eq!(fmt_duration(Duration::from_millis(400)), "0.4s");
        assert_eq!(fmt_duration(Duration::from_secs(245)), "4m05s");
    }

    #[test]
    fn run_captures_output_and_status() {
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo out; echo err >&2; exit 3"]);
        let opts = RunOpts {
            capture_stdout: true,
            capture_stderr: true,
            ..RunOpts::default()
        };
        let out = run(&mut cmd, opts).unwrap();
        assert_eq!(out.stdout, "out\n");
        assert_eq!(out.stderr, "err\n");
        assert_eq!(out.status.and_then(|s| s.code()), Some(3));
        assert!(!out.success());
    }

    #[test]
    fn run_kills_process_tree_on_timeout() {
        // The grandchild `sleep` holds the pipe open; the run must still return promptly.
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "sleep 30 & sleep 30; echo never"]);
        let opts = RunOpts {
            capture_stdout: true,
            timeout: Some(Duration::from_millis(300)),
            ..RunOpts::default()
        };
        let start = Instant::now();
        let out = run(&mut cmd, opts).unwrap();
        assert!(out.timed_out);
        assert!(!out.success());
        assert!(!out.stdout.contains("never"));
        assert!(start.elapsed() < Duration::from_secs(10));
    }
}

/// Variables `cargo run` sets for the program it runs (xtask), not for the cargo we start.
/// Cargo's home (`$CARGO_HOME`, else `~/.cargo`), absolute, if it can be known.
fn cargo_home() -> Option<PathBuf> {
    let home = match std::env::var_os("CARGO_HOME") {
        Some(h) if !h.is_empty() => PathBuf::from(h),
        _ => PathBuf::from(std::env::var_os("HOME")?).join(".cargo"),
    };
    if home.is_absolute() {
        Some(home)
    } else {
        std::env::current_dir().ok().map(|d| d.join(home))
    }
}

/// `GIT_CEILING_DIRECTORIES` with cargo's source trees under `home` added to `old`.
fn git_ceilings(home: &Path, old: Option<OsString>) -> Option<OsString> {
    let mut ceilings: Vec<PathBuf> = ["registry/src", "git/checkouts"]
        .iter()
        .map(|d| home.join(d))
        .collect();
    if let Some(old) = old {
        ceilings.extend(std::env::split_paths(&old));
    }
    std::env::join_paths(ceilings).ok()
}

fn is_cargo_run_var(name: &str) -> bool {
    name.starts_with("CARGO_PKG_")
        || matches!(
            name,
            "CARGO_MANIFEST_DIR"
                | "CARGO_MANIFEST_PATH"
                | "CARGO_MANIFEST_LINKS"
                | "CARGO_CRATE_NAME"
                | "CARGO_BIN_NAME"
                | "CARGO_PRIMARY_PACKAGE"
                | "OUT_DIR"
        )
}

#[cfg(test)]
mod cargo_env_tests {
    use super::{git_ceilings, is_cargo_run_var};
    use std::ffi::OsString;
    use std::process::Command;

    /// With cargo's home inside a git work tree, git run in a crate's source directory (as
    /// Zenoh's version macro does) must not find that work tree's repository.
    #[test]
    fn git_does_not_find_a_repository_above_cargo_sources() {
        let dir = std::env::temp_dir().join(format!("xtask-ceiling-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let home = dir.join("cargo-home");
        let krate = home.join("registry/src/index.example/some-crate-1.0.0");
        std::fs::create_dir_all(&krate).unwrap();
        let git = |envs: Option<OsString>| {
            let mut cmd = Command::new("git");
            cmd.args(["rev-parse", "--git-dir"]).current_dir(&krate);
            cmd.env_remove("GIT_DIR");
            if let Some(c) = envs {
                cmd.env("GIT_CEILING_DIRECTORIES", c);
            }
            cmd.output().unwrap()
        };
        let init = Command::new("git")
            .arg("init")
            .arg("-q")
            .arg(&dir)
            .status()
            .unwrap();
        assert!(init.success());
        // Without the ceiling git finds the work tree's repository (the failure mode)...
        assert!(git(None).status.success());
        // ...with it, none, as for a cargo home outside any repository.
        let ceilings = git_ceilings(&home, Some(OsString::from("/nonexistent/a"))).unwrap();
        assert!(
            ceilings.to_string_lossy().ends_with(":/nonexistent/a"),
            "{ceilings:?}"
        );
        let out = git(Some(ceilings));
        assert!(!out.status.success(), "{}", String::from_utf8_lossy(&out.stdout));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn only_the_variables_cargo_run_gives_xtask_are_dropped() {
        for v in [
            "CARGO_MANIFEST_DIR",
            "CARGO_PKG_NAME",
            "CARGO_PKG_VERSION_MAJOR",
            "OUT_DIR",
        ] {
            assert!(is_cargo_run_var(v), "{v}");
        }
        for v in [
            "CARGO_HOME",
            "CARGO_TARGET_DIR",
            "CARGO_INCREMENTAL",
            "CARGO",
            "RUSTFLAGS",
            "PATH",
        ] {
            assert!(!is_cargo_run_var(v), "{v}");
        }
    }
}
