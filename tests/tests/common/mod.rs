//! Running the real `irtrackd` and `host-tools` binaries from the system tests: the shared
//! harness (`irtrack_testkit::harness`), unwrapped for tests, plus the operator password of the
//! tests' configs; `chromium`: driving the set-up page in headless Chromium (browser tests).
#![allow(dead_code)] // each test binary uses a different subset

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use irtrack_testkit::harness::{self, irtrackd};

pub mod chromium;
pub mod cluster;
#[allow(unused_imports)] // each test binary uses a different subset
pub use irtrack_testkit::harness::{Http, Irtrackd, IrtrackdConfig, Proc, TempDir};

/// A workspace binary next to this test (target/<profile>/).
pub fn bin(name: &str) -> PathBuf {
    harness::workspace_bin(name).unwrap_or_else(|e| panic!("{e}"))
}

/// A fresh, empty temporary directory for this process, removed when the test passes (kept
/// after a failure, for its logs and outputs).
pub fn temp_dir(name: &str) -> TempDir {
    TempDir::new(&format!("e2e-{name}")).unwrap()
}

/// Starts `cmd` as a child that is killed when the returned handle drops.
pub fn spawn(cmd: &mut std::process::Command, name: &str) -> Proc {
    Proc::spawn(cmd, name).unwrap_or_else(|e| panic!("{e}"))
}

/// The address after `key` (e.g. `status=`) in a line such as irtrackd's ready line.
pub fn addr_field(line: &str, key: &str) -> SocketAddr {
    irtrackd::addr_field(line, key).unwrap_or_else(|e| panic!("{e}"))
}

/// Starts irtrackd with every endpoint on a free port of 127.0.0.1; returns it (killed on
/// drop) and its ready line.
pub fn start_irtrackd(config: &Path, state: &Path) -> (Irtrackd, String) {
    let d = Irtrackd::start(&bin("irtrackd"), config, state, Duration::from_secs(20))
        .unwrap_or_else(|e| panic!("{e}"));
    let line = d.ready().line.clone();
    (d, line)
}

/// Operator password of the system tests' irtrackd configs.
pub const OPERATOR_PASSWORD: &str = "system-test-operator";

/// `operator_password_hash = "..."` line for a `[service]` table, made by `irtrackd
/// --hash-password`.
pub fn operator_hash_line() -> String {
    let phc = harness::operator_hash(&bin("irtrackd"), OPERATOR_PASSWORD).unwrap_or_else(|e| panic!("{e}"));
    format!("operator_password_hash = \"{phc}\"")
}

/// Long enough for a password check on a loaded machine.
const HTTP_TIMEOUT: Duration = Duration::from_secs(30);

/// One HTTP request; returns the status code and body.
pub fn http(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    Http::new(HTTP_TIMEOUT)
        .request(addr, method, path, None)
        .unwrap_or_else(|e| panic!("{e}"))
}

/// [`http`] signed in as the operator (change requests need a sign-in).
pub fn http_operator(addr: SocketAddr, method: &str, path: &str) -> (u16, String) {
    Http::new(HTTP_TIMEOUT)
        .signed_in(OPERATOR_PASSWORD)
        .request(addr, method, path, None)
        .unwrap_or_else(|e| panic!("{e}"))
}
