//! Child processes for tests and tasks: killed on every path out unless stopped on purpose,
//! stdout read in a thread (a child never blocks on a full pipe) and offered line by line.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use super::error::{Error, Result, io};

/// A running child process. Dropping it kills it (also when a test panics).
#[derive(Debug)]
pub struct Proc {
    child: Child,
    name: String,
    lines: Option<Receiver<String>>,
}

impl Proc {
    /// Starts `cmd` with standard input closed and standard output piped into a line reader
    /// ([`Proc::wait_line`]); standard error is whatever `cmd` sets (inherited by default).
    pub fn spawn(cmd: &mut Command, name: &str) -> Result<Proc> {
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .spawn()
            .map_err(|source| Error::Spawn {
                program: PathBuf::from(cmd.get_program()),
                source,
            })?;
        let lines = child.stdout.take().map(read_lines);
        Ok(Proc {
            child,
            name: name.to_string(),
            lines,
        })
    }

    /// Takes over a child started elsewhere; its stdout, if piped and not yet taken, is read
    /// like [`Proc::spawn`]'s.
    pub fn adopt(mut child: Child, name: &str) -> Proc {
        let lines = child.stdout.take().map(read_lines);
        Proc {
            child,
            name: name.to_string(),
            lines,
        }
    }

    /// Process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The child, e.g. to write to its standard input.
    pub fn child_mut(&mut self) -> &mut Child {
        &mut self.child
    }

    /// Waits for a stdout line starting with `prefix`; earlier lines are skipped.
    pub fn wait_line(&mut self, prefix: &str, timeout: Duration) -> Result<String> {
        Ok(self.wait_lines(&[prefix], timeout)?.remove(0))
    }

    /// Waits until each prefix has started a stdout line, in any order; returns the lines in
    /// the order of `prefixes`.
    pub fn wait_lines(&mut self, prefixes: &[&str], timeout: Duration) -> Result<Vec<String>> {
        let deadline = Instant::now() + timeout;
        let mut found: Vec<Option<String>> = vec![None; prefixes.len()];
        while found.iter().any(Option::is_none) {
            let missing = || {
                prefixes
                    .iter()
                    .zip(&found)
                    .find(|(_, f)| f.is_none())
                    .map_or(String::new(), |(p, _)| p.to_string())
            };
            let Some(lines) = &self.lines else {
                return Err(self.no_line(missing(), timeout));
            };
            let left = deadline.saturating_duration_since(Instant::now());
            match lines.recv_timeout(left) {
                Ok(line) => {
                    if let Some(i) =
                        (0..prefixes.len()).find(|&i| found[i].is_none() && line.starts_with(prefixes[i]))
                    {
                        found[i] = Some(line);
                    }
                }
                Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => {
                    return Err(self.no_line(missing(), timeout));
                }
            }
        }
        Ok(found.into_iter().flatten().collect())
    }

    /// The next stdout line, or `None` when none came within `timeout` or the output ended
    /// (a JSON-lines child such as the interop clients: one message per line).
    pub fn next_line(&mut self, timeout: Duration) -> Option<String> {
        self.lines.as_ref()?.recv_timeout(timeout).ok()
    }

    fn no_line(&mut self, prefix: String, timeout: Duration) -> Error {
        let ended = match self.child.try_wait() {
            Ok(Some(s)) => format!(", it exited ({s})"),
            _ => String::new(),
        };
        Error::NoLine {
            process: self.name.clone(),
            prefix,
            timeout,
            ended,
        }
    }

    /// SIGTERM, then up to `grace` for the process to exit; SIGKILL after that. Says how it
    /// ended.
    pub fn terminate(&mut self, grace: Duration) -> Result<String> {
        let what = format!("stopping {}", self.name);
        if let Some(s) = self.child.try_wait().map_err(io(what.clone()))? {
            return Ok(format!("had already exited ({s})"));
        }
        // `kill` the command: no libc binding for one signal.
        let _ = Command::new("kill")
            .args(["-TERM", &self.pid().to_string()])
            .stderr(Stdio::null())
            .status();
        let start = Instant::now();
        while start.elapsed() < grace {
            if let Some(s) = self.child.try_wait().map_err(io(what.clone()))? {
                return Ok(format!("exited after SIGTERM ({s})"));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        self.child.kill().map_err(io(what.clone()))?;
        let s = self.child.wait().map_err(io(what))?;
        Ok(format!("ignored SIGTERM for {grace:?}, killed ({s})"))
    }

    /// Waits up to `timeout` for the process to exit by itself; `None` if it still runs.
    pub fn wait_timeout(&mut self, timeout: Duration) -> Result<Option<ExitStatus>> {
        let what = format!("waiting for {}", self.name);
        let start = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().map_err(io(what.clone()))? {
                return Ok(Some(s));
            }
            if start.elapsed() >= timeout {
                return Ok(None);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits for the process to exit by itself.
    pub fn wait(mut self) -> Result<ExitStatus> {
        let what = format!("waiting for {}", self.name);
        self.child.wait().map_err(io(what))
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Reads a pipe to its end in a thread, offering every line on the channel.
fn read_lines(pipe: impl std::io::Read + Send + 'static) -> Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(pipe).lines().map_while(std::result::Result::ok) {
            // The receiver may be gone; keep draining so the child never blocks.
            let _ = tx.send(line);
        }
    });
    rx
}

/// A workspace binary beside the running test executable: tests run as
/// `target/<profile>/deps/<test>-<hash>`, the binaries sit in `target/<profile>/`.
pub fn workspace_bin(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().map_err(io("locating the test executable"))?;
    let dir = exe.parent().and_then(Path::parent).ok_or_else(|| Error::Failed {
        what: format!("locating {name}"),
        detail: format!("{} has no grandparent directory", exe.display()),
    })?;
    let p = dir.join(name);
    if !p.is_file() {
        return Err(Error::Failed {
            what: format!("locating {name}"),
            detail: format!(
                "{} not found: build it first (`cargo build -p irtrack-firmware -p \
                 irtrack-host-tools`, same CARGO_TARGET_DIR and profile as this test)",
                p.display()
            ),
        });
    }
    Ok(p)
}

/// A fresh, empty directory under the system's temporary directory, removed on drop unless the
/// thread is panicking (a failed test's logs and outputs are kept, and their place printed).
#[derive(Debug)]
pub struct TempDir(PathBuf);

impl TempDir {
    /// `irtrack-<name>-<pid>` under the temporary directory, emptied if it exists.
    pub fn new(name: &str) -> Result<TempDir> {
        let d = std::env::temp_dir().join(format!("irtrack-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).map_err(io(format!("creating {}", d.display())))?;
        Ok(TempDir(d))
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl std::ops::Deref for TempDir {
    type Target = PathBuf;
    fn deref(&self) -> &PathBuf {
        &self.0
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("test failed: its files are kept in {}", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lines_in_any_order_and_a_named_timeout() {
        let mut p = Proc::spawn(
            Command::new("sh").args(["-c", "echo noise; echo b=2; echo a=1; sleep 5"]),
            "sh",
        )
        .unwrap();
        let l = p.wait_lines(&["a=", "b="], Duration::from_secs(5)).unwrap();
        assert_eq!(l, ["a=1", "b=2"]);
        let e = p.wait_line("never", Duration::from_millis(200)).unwrap_err();
        assert!(e.to_string().contains("sh: no `never` line"), "{e}");
        let how = p.terminate(Duration::from_secs(2)).unwrap();
        assert!(how.contains("SIGTERM"), "{how}");
    }

    #[test]
    fn lines_one_by_one_until_the_output_ends() {
        let mut p = Proc::spawn(Command::new("sh").args(["-c", "echo one; echo two"]), "sh").unwrap();
        let t = Duration::from_secs(5);
        assert_eq!(p.next_line(t).as_deref(), Some("one"));
        assert_eq!(p.next_line(t).as_deref(), Some("two"));
        assert_eq!(p.next_line(t), None);
    }

    #[test]
    fn an_exited_process_is_reported_as_such() {
        let mut p = Proc::spawn(Command::new("sh").args(["-c", "exit 3"]), "sh").unwrap();
        let e = p.wait_line("x", Duration::from_secs(5)).unwrap_err().to_string();
        // The pipe closes when the process ends; the status may not be collected yet.
        assert!(e.contains("no `x` line"), "{e}");
        assert!(Proc::spawn(&mut Command::new("/nonexistent/x"), "x").is_err());
    }

    #[test]
    fn temp_dirs_are_removed_after_success() {
        let d = TempDir::new("testkit-selftest").unwrap();
        std::fs::write(d.join("f"), b"x").unwrap();
        let p = d.path().to_path_buf();
        drop(d);
        assert!(!p.exists());
    }
}
