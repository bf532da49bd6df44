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
