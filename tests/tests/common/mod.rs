//! Running the real `irtrackd` and `host-tools` binaries from the system tests.
#![allow(dead_code)] // each test binary uses a different subset

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// Kills the child on every path (also when an assertion fails).
pub struct Guard(pub Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A workspace binary next to this test: the test runs as target/<profile>/deps/<test>-<hash>,
/// the binaries sit in target/<profile>.
pub fn bin(name: &str) -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let p = exe.parent().and_then(Path::parent).unwrap().join(name);
    assert!(
        p.is_file(),
        "{} not found: build it first with `cargo build -p irtrack-firmware -p irtrack-host-tools` \
         (same CARGO_TARGET_DIR and profile as this test)",
        p.display()
    );
    p
}

/// A fresh, empty temporary directory for this process, removed when the test passes (kept
/// after a failure, for its logs and outputs).
pub fn temp_dir(name: &str) -> TempDir {
    let d = std::env::temp_dir().join(format!("irtrack-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TempDir(d)
}

/// See [`temp_dir`].
pub struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = PathBuf;
    fn deref(&self) -> &PathBuf {
        &self.0
    }
}

impl AsRef<std::path::Path> for TempDir {
    fn as_ref(&self) -> &std::path::Path {
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

/// Reads stdout lines until one starts with `prefix`; the rest of stdout is drained in a thread
/// so the child never blocks on a full pipe.
pub fn wait_line(child: &mut Child, prefix: &str, timeout: Duration) -> String {
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    let wanted = prefix.to_string();
    std::thread::spawn(move || {
        let mut sent = false;
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if !sent && line.starts_with(&wanted) {
                let _ = tx.send(line);
                sent = true;
            }
        }
    });
    rx.recv_timeout(timeout)
        .unwrap_or_else(|_| panic!("no `{prefix}` line within {timeout:?}"))
}

/// The address after `key` (e.g. `status=`) in a line such as irtrackd's ready line.
pub fn addr_field(line: &str, key: &str) -> SocketAddr {
    line.split_whitespace()
        .find_map(|w| w.strip_prefix(key))
        .unwrap_or_else(|| panic!("{key} missing in {line:?}"))
        .parse()
        .unwrap()
}

/// Starts irtrackd with every endpoint on a free port of 127.0.0.1; returns its ready line.
pub fn start_irtrackd(config: &Path, state: &Path) -> (Guard, String) {
    let mut child = Command::new(bin("irtrackd"))
        .arg("-c")
        .arg(config)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(state)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let line = wait_line(&mut child, "irtrackd ready", Duration::from_secs(20));
    (Guard(child), line)
}

/// One HTTP/1.0 request over a raw socket; returns the status code and body.
pub fn http(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    http_with(addr, method, path, "")
}

/// Operator password of the system tests' irtrackd configs.
pub const OPERATOR_PASSWORD: &str = "system-test-operator";

/// `operator_password_hash = "..."` line for a `[service]` table.
pub fn operator_hash_line() -> String {
    let phc = irtrack_firmware::net::auth::hash_password(OPERATOR_PASSWORD).unwrap();
    format!("operator_password_hash = \"{phc}\"")
}

/// [`http`] with the operator's HTTP Basic credentials (change requests need a sign-in).
pub fn http_operator(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    let auth = irtrack_firmware::net::auth::basic_header(OPERATOR_PASSWORD);
    http_with(addr, method, path, &format!("Authorization: {auth}\r\n"))
}

fn http_with(addr: SocketAddr, method: &str, path: &str, extra_headers: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "{method} {path} HTTP/1.0\r\nHost: test\r\n{extra_headers}\r\n").unwrap();
    let mut resp = String::new();
    s.read_to_string(&mut resp).unwrap();
    let code = resp.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = resp
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (code, body)
}
