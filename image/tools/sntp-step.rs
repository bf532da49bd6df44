//! `sntp-step HOST:PORT`: steps CLOCK_REALTIME to an SNTP server's time, once.
//!
//! The cluster test image's stand-in for chrony or ptp4l (docs/cluster.md, "Clocks"): the
//! busybox image has no NTP client (Debian's busybox-static leaves out `ntpd`), and its RTC
//! sets the clock only to the second. The cluster test runs an SNTP server on the QEMU host;
//! rc.local runs this before irtrackd starts, so the camera board's capture timestamps are on
//! the host's clock, as PTP would keep them on a real cell.
//!
//! A single file with std only, compiled by `cargo xtask` with rustc for aarch64 (static), no
//! cargo package: it belongs to the test image, not to the workspace. Eight request/reply
//! exchanges (RFC 4330); the one with the shortest round trip gives the offset
//! `((t2 − t1) + (t3 − t4)) / 2`, whose error is at most half that round trip.

use std::net::UdpSocket;
use std::process::ExitCode;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

/// Seconds from 1900-01-01 (NTP's era 0) to 1970-01-01.
const NTP_UNIX_S: u64 = 2_208_988_800;
const SAMPLES: usize = 8;
const CLOCK_REALTIME: i32 = 0;

#[repr(C)]
struct Timespec {
    tv_sec: i64,
    tv_nsec: i64,
}

unsafe extern "C" {
    fn clock_settime(clock: i32, ts: *const Timespec) -> i32;
}

fn now_ns() -> i128 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i128)
}

fn to_ntp(unix_ns: i128) -> [u8; 8] {
    let secs = (unix_ns / 1_000_000_000) as u64 + NTP_UNIX_S;
    let frac = (((unix_ns % 1_000_000_000) as u128) << 32) / 1_000_000_000;
    let mut b = [0u8; 8];
    b[..4].copy_from_slice(&(secs as u32).to_be_bytes());
    b[4..].copy_from_slice(&(frac as u32).to_be_bytes());
    b
}

fn from_ntp(b: &[u8]) -> i128 {
    let secs = u32::from_be_bytes([b[0], b[1], b[2], b[3]]) as i128;
    let frac = u32::from_be_bytes([b[4], b[5], b[6], b[7]]) as i128;
    (secs - NTP_UNIX_S as i128) * 1_000_000_000 + ((frac * 1_000_000_000) >> 32)
}

/// One exchange: (offset, round trip) in ns.
fn exchange(sock: &UdpSocket) -> Result<(i128, i128), String> {
    let mut req = [0u8; 48];
    req[0] = 0x23; // LI 0, version 4, mode 3 (client)
    let t1 = now_ns();
    req[40..48].copy_from_slice(&to_ntp(t1));
    sock.send(&req).map_err(|e| format!("send: {e}"))?;
    let mut rep = [0u8; 64];
    let n = sock.recv(&mut rep).map_err(|e| format!("no reply: {e}"))?;
    let t4 = now_ns();
    if n < 48 {
        return Err(format!("reply of {n} bytes, need 48"));
    }
    if rep[0] & 0x07 != 4 || rep[1] == 0 || rep[0] >> 6 == 3 {
        return Err(format!(
            "not a usable server reply (mode {}, stratum {}, leap {})",
            rep[0] & 7,
            rep[1],
            rep[0] >> 6
        ));
    }
    if rep[24..32] != req[40..48] {
        return Err("reply does not answer this request (origin timestamp differs)".into());
    }
    let t2 = from_ntp(&rep[32..40]);
    let t3 = from_ntp(&rep[40..48]);
    Ok((((t2 - t1) + (t3 - t4)) / 2, (t4 - t1) - (t3 - t2)))
}

fn run(server: &str) -> Result<String, String> {
    let sock = UdpSocket::bind("0.0.0.0:0").map_err(|e| format!("bind: {e}"))?;
    sock.connect(server)
        .map_err(|e| format!("{server}: {e}"))?;
    sock.set_read_timeout(Some(Duration::from_secs(1)))
        .map_err(|e| e.to_string())?;
    let mut best: Option<(i128, i128)> = None;
    let mut last_err = String::new();
    for _ in 0..SAMPLES {
        match exchange(&sock) {
            Ok(s) if best.is_none_or(|b| s.1 < b.1) => best = Some(s),
            Ok(_) => {}
            Err(e) => last_err = e,
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let (offset, delay) = best.ok_or(format!("no reply from {server} in {SAMPLES} tries: {last_err}"))?;
    let target = now_ns() + offset;
    let ts = Timespec {
        tv_sec: (target / 1_000_000_000) as i64,
        tv_nsec: (target % 1_000_000_000) as i64,
    };
    // SAFETY: `ts` is a valid timespec for the duration of the call.
    if unsafe { clock_settime(CLOCK_REALTIME, &ts) } != 0 {
        return Err(format!("clock_settime: {}", std::io::Error::last_os_error()));
    }
    Ok(format!(
        "stepped the clock by {:+.3} ms (round trip {:.3} ms) from {server}",
        offset as f64 / 1e6,
        delay as f64 / 1e6
    ))
}

fn main() -> ExitCode {
    let Some(server) = std::env::args().nth(1) else {
        eprintln!("usage: sntp-step HOST:PORT");
        return ExitCode::from(2);
    };
    match run(&server) {
        Ok(msg) => {
            println!("sntp-step: {msg}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("sntp-step: {e}");
            ExitCode::FAILURE
        }
    }
}
