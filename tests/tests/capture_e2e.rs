//! `host-tools capture` against a real `irtrackd` on the simulated source (its
//! `GET /api/frameset`, docs/http-api.md): checkerboard mode saves synchronised sets in the layout
//! `calibrate` reads and reports per camera whether a board was seen (the simulated scene shows
//! an LED, no board); wand mode saves distinct sets as fast as irtrackd serves them.
//!
//! The binaries belong to other packages: run
//! `cargo build -p irtrack-firmware --bin irtrackd -p irtrack-host-tools --bin host-tools` first.

mod common;

use std::process::Command;

use common::*;

fn pgm_size(bytes: &[u8]) -> (u32, u32) {
    let text = String::from_utf8_lossy(&bytes[..bytes.len().min(40)]).into_owned();
    let mut it = text.split_ascii_whitespace();
    assert_eq!(it.next(), Some("P5"));
    (
        it.next().unwrap().parse().unwrap(),
        it.next().unwrap().parse().unwrap(),
    )
}

#[test]
fn capture_takes_synchronised_sets_from_a_running_irtrackd() {
    let dir = temp_dir("capture");
    let config = dir.join("irtrackd.toml");
    std::fs::write(&config, "[source.sim]\nrig = \"convergent\"\nfps = 30.0\n").unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let board = addr_field(&ready, "status=").to_string();

    let shots = dir.join("shots");
    let o = Command::new(bin("host-tools"))
        .args(["capture", "--from", &board, "--out"])
        .arg(&shots)
        .args(["--every", "0.2", "--count", "3"])
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{stdout}\n{stderr}");
    print!("{stdout}");
    assert!(
        stdout.contains(&format!("board {board}: 2 cameras, 640x480 8-bit")),
        "{stdout}"
    );
    for c in 0..2 {
        for i in 0..3 {
            let f = shots.join(format!("cam{c}/{i:06}.pgm"));
            let bytes = std::fs::read(&f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
            assert_eq!(pgm_size(&bytes), (640, 480), "{}", f.display());
        }
        assert!(!shots.join(format!("cam{c}/000003.pgm")).exists());
    }
    assert_eq!(stdout.matches("cam0 no board").count(), 3, "{stdout}");
    assert_eq!(stdout.matches("cam1 no board").count(), 3, "{stdout}");
    assert!(stdout.contains("saved 3 sets"), "{stdout}");

    let wand = dir.join("wand");
    let t0 = std::time::Instant::now();
    let o = Command::new(bin("host-tools"))
        .args(["capture", "--from", &board, "--out"])
        .arg(&wand)
        .args(["--wand", "--count", "20"])
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "{stdout}\n{stderr}");
    println!(
        "wand capture of 20 sets took {:.2} s: {stdout}",
        t0.elapsed().as_secs_f64()
    );
    let files = std::fs::read_dir(wand.join("cam1")).unwrap().count();
    assert_eq!(files, 20);
    // Distinct sets: the simulated LED moves, so consecutive frames differ.
    let a = std::fs::read(wand.join("cam0/000000.pgm")).unwrap();
    let b = std::fs::read(wand.join("cam0/000019.pgm")).unwrap();
    assert_ne!(a, b, "wand mode saved the same set twice");
}

/// Waits until irtrackd's status says the source ended; returns the status document.
fn wait_ended(status: std::net::SocketAddr, secs: u64) -> serde_json::Value {
    let end = std::time::Instant::now() + std::time::Duration::from_secs(secs);
    loop {
        let (_, body) = http(status, "GET", "/status");
        let v: serde_json::Value = serde_json::from_str(&body).unwrap();
        if v["processing"]["source_ended"] == true {
            return v;
        }
        assert!(
            std::time::Instant::now() < end,
            "replay did not end within {secs} s: {v}"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
}

/// A folder written by `host-tools capture` replays whole: capture writes `timestamps.csv`,
/// so irtrackd (`--replay-dir`) keeps the recorded intervals and processes every set; without
/// the file it paces at the stated default rate (in its source description) and still processes
/// every set, and the end says how many of how many.
#[test]
fn a_capture_by_host_tools_replays_every_set() {
    let dir = temp_dir("capture-replay");
    let config = dir.join("irtrackd.toml");
    std::fs::write(&config, "[source.sim]\nfps = 30.0\n").unwrap();
    let (irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let board = addr_field(&ready, "status=").to_string();
    let shots = dir.join("wave");
    let o = Command::new(bin("host-tools"))
        .args(["capture", "--from", &board, "--out"])
        .arg(&shots)
        .args(["--wand", "--count", "8"])
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    drop(irtrackd);

    // timestamps.csv: a header and one row per camera and set, rising per camera.
    let csv = std::fs::read_to_string(shots.join("timestamps.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("frame,camera,timestamp_ns,dropped"));
    let rows: Vec<Vec<u64>> = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 16, "{csv}");
    for cam in 0..2u64 {
        let ts: Vec<u64> = rows.iter().filter(|r| r[1] == cam).map(|r| r[2]).collect();
        assert!(ts.windows(2).all(|w| w[1] > w[0]), "camera {cam}: {ts:?}");
        assert!(rows.iter().all(|r| r[3] == 0));
    }

    // As a person would: `irtrackd --replay-dir DIR`, no config file.
    let run = |label: &str| {
        let mut cmd = Command::new(bin("irtrackd"));
        cmd.arg("--replay-dir")
            .arg(&shots)
            .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
            .arg(dir.join(format!("state-{label}")));
        let d =
            Irtrackd::spawn(&mut cmd, std::time::Duration::from_secs(20)).unwrap_or_else(|e| panic!("{e}"));
        let st = wait_ended(addr_field(&d.ready().line, "status="), 20);
        drop(d);
        st
    };
    let st = run("recorded");
    println!(
        "replay with timestamps.csv: {}; {}",
        st["source"]["description"], st["processing"]["end_reason"]
    );
    assert_eq!(st["processing"]["sets_processed"], 8, "{st}");
    assert_eq!(st["processing"]["stale_sets"], 0, "{st}");
    assert!(
        st["source"]["description"]
            .as_str()
            .unwrap()
            .contains("recorded timestamps (timestamps.csv)"),
        "{st}"
    );
    assert!(
        st["processing"]["end_reason"]
            .as_str()
            .unwrap()
            .contains("8 of 8 recorded sets delivered"),
        "{st}"
    );

    std::fs::remove_file(shots.join("timestamps.csv")).unwrap();
    let st = run("paced");
    println!(
        "replay without timestamps.csv: {}; {}",
        st["source"]["description"], st["processing"]["end_reason"]
    );
    assert_eq!(st["processing"]["sets_processed"], 8, "{st}");
    assert!(
        st["source"]["description"]
            .as_str()
            .unwrap()
            .contains("no timestamps.csv: paced at the default 30 fps"),
        "{st}"
    );
}
