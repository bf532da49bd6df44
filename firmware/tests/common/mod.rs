//! Helpers shared by the firmware integration tests.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use irtrack_core::param_wire::{Verdict, encode_push};
use irtrack_core::stream::{BINARY_FRAME_LEN, PositionRecord};
use irtrack_firmware::config::Config;
use irtrack_firmware::source::sim::SimSourceConfig;
use irtrack_sim::Scenario;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

/// A fresh, empty directory under the system temp dir (removed on drop).
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(name: &str) -> Self {
        let p = std::env::temp_dir().join(format!("irtrackd-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Simulated source at a test-friendly rate (the convergent VGA rig of the defaults).
pub fn sim_cfg() -> SimSourceConfig {
    SimSourceConfig {
        fps: 100.0,
        ..SimSourceConfig::default()
    }
}

/// Config with every listener on 127.0.0.1:0, the given state dir and the simulated source.
pub fn test_config(state_dir: &Path) -> Config {
    let mut cfg = Config::default();
    cfg.service.state_dir = state_dir.to_path_buf();
    for a in [
        &mut cfg.listen.params,
        &mut cfg.listen.stream_ndjson,
        &mut cfg.listen.stream_binary,
        &mut cfg.listen.status,
    ] {
        *a = "127.0.0.1:0".into();
    }
    cfg.source.sim = Some(sim_cfg());
    // These tests push unsigned blobs; the signed path has its own tests (tests/signing.rs).
    cfg.params.allow_unsigned = true;
    cfg
}

/// The simulator scenario a config's sim source runs (same seed, so same truth).
pub fn scenario(cfg: &SimSourceConfig) -> Scenario {
    Scenario::new(cfg.scenario_config()).unwrap()
}

/// Pushes a blob and returns the server's verdict line.
pub async fn push(addr: SocketAddr, blob: &[u8]) -> String {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(&encode_push(blob)).await.unwrap();
    let mut line = String::new();
    s.read_to_string(&mut line).await.unwrap();
    line
}

pub async fn push_verdict(addr: SocketAddr, blob: &[u8]) -> Verdict {
    Verdict::parse_line(&push(addr, blob).await).unwrap()
}

/// An NDJSON stream client.
pub struct NdjsonClient {
    lines: tokio::io::Lines<BufReader<TcpStream>>,
}

impl NdjsonClient {
    pub async fn connect(addr: SocketAddr) -> Self {
        let s = TcpStream::connect(addr).await.unwrap();
        Self {
            lines: BufReader::new(s).lines(),
        }
    }

    /// Next record, failing the test after `timeout`.
    pub async fn next(&mut self) -> PositionRecord {
        let line = tokio::time::timeout(Duration::from_secs(10), self.lines.next_line())
            .await
            .expect("no record within 10 s")
            .unwrap()
            .expect("stream closed");
        PositionRecord::from_ndjson_line(&line).unwrap()
    }

    /// Reads until `pred` holds, at most `max` records.
    pub async fn until(&mut self, max: usize, pred: impl Fn(&PositionRecord) -> bool) -> PositionRecord {
        for _ in 0..max {
            let r = self.next().await;
            if pred(&r) {
                return r;
            }
        }
        panic!("no matching record within {max} records");
    }
}

/// Reads one binary record.
pub async fn read_binary(s: &mut TcpStream) -> PositionRecord {
    let mut buf = [0u8; BINARY_FRAME_LEN];
    tokio::time::timeout(Duration::from_secs(10), s.read_exact(&mut buf))
        .await
        .unwrap()
        .unwrap();
    PositionRecord::decode_binary(&buf).unwrap()
}

/// GET `path` from the status endpoint; returns (status code, body).
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut resp = String::new();
    s.read_to_string(&mut resp).await.unwrap();
    let code = resp.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = resp
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (code, body)
}

pub async fn status_json(addr: SocketAddr) -> serde_json::Value {
    let (code, body) = http_get(addr, "/status").await;
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Distance between two points, mm.
pub fn dist_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Set in the re-run test inside its network namespace.
const INSIDE: &str = "IRTRACK_TEST_NETNS";

/// Outside the namespace: runs `test` of this binary again inside a fresh one and checks it
/// passed; returns false (the caller returns). Inside: sets up loopback multicast and returns
/// true (the caller runs the test body).
pub fn in_own_netns(test: &str) -> bool {
    if std::env::var_os(INSIDE).is_some() {
        for args in [
            &["link", "set", "lo", "up", "multicast", "on"][..],
            &["route", "add", "239.0.0.0/8", "dev", "lo"][..],
        ] {
            let st = std::process::Command::new("ip")
                .args(args)
                .status()
                .expect("ip runs");
            assert!(st.success(), "ip {args:?} failed in the test's network namespace");
        }
        return true;
    }
    let exe = std::env::current_exe().unwrap();
    // Cross-built runs (aarch64 under QEMU) set IRTRACK_TEST_RUNNER: a foreign binary is
    // started through it.
    let runner = std::env::var("IRTRACK_TEST_RUNNER").unwrap_or_default();
    let out = std::process::Command::new("unshare")
        .arg("-rn")
        .args(runner.split_whitespace())
        .arg(exe)
        .args([test, "--exact", "--nocapture", "--test-threads=1"])
        .env(INSIDE, "1")
        .output()
        .expect("unshare (util-linux) runs");
    print!("{}", String::from_utf8_lossy(&out.stdout));
    eprint!("{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        out.status.success(),
        "{test} inside `unshare -rn` failed ({})",
        out.status
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("1 passed"),
        "{test} did not run inside the namespace"
    );
    false
}
