//! Helpers shared by the host-tools CLI tests.
#![allow(dead_code)] // each test binary uses a different subset

use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::thread;
use std::time::Duration;

use irtrack_core::camera::{Distortion, ImageSize};
use irtrack_core::param_wire::{self, Verdict};
use irtrack_sim::rig::CameraSpec;

/// Runs the host-tools binary built for this test run.
pub fn host_tools(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args(args)
        .output()
        .unwrap()
}

/// stdout and stderr as text.
pub fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

pub fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// One connection of a parameter endpoint (docs/param-protocol.md): reads the push header and
/// blob, answers with the verdict `judge` gives for the blob, and returns what `judge` kept.
/// A header that does not parse is answered with its error and `on_bad_header`'s value.
pub fn serve_push_once<T: Send + 'static>(
    listener: TcpListener,
    judge: impl FnOnce(&[u8]) -> (Verdict, T) + Send + 'static,
    on_bad_header: T,
) -> thread::JoinHandle<T> {
    thread::spawn(move || {
        let (mut s, _) = listener.accept().unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        let mut hdr = [0u8; param_wire::PUSH_HEADER_LEN];
        s.read_exact(&mut hdr).unwrap();
        let (verdict, kept) = match param_wire::parse_push_header(&hdr) {
            Err(e) => (Verdict::from_error(&e), on_bad_header),
            Ok(len) => {
                let mut blob = vec![0u8; len];
                s.read_exact(&mut blob).unwrap();
                judge(&blob)
            }
        };
        s.write_all(verdict.to_line().as_bytes()).unwrap();
        kept
    })
}

/// A fresh, empty scratch directory `name` in this test binary's own folder under
/// `CARGO_TARGET_TMPDIR` (`CARGO_CRATE_NAME` is the test file's name, so binaries never share
/// one).
pub fn scratch(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(env!("CARGO_CRATE_NAME"))
        .join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A 752×480 camera of focal length `focal_px` with radial distortion `k1`, `k2` only.
pub fn lens(focal_px: f64, k1: f64, k2: f64) -> CameraSpec {
    CameraSpec {
        focal_px,
        image_size: ImageSize {
            width_px: 752,
            height_px: 480,
        },
        distortion: Distortion {
            k1,
            k2,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        },
    }
}
