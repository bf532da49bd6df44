//! Calibration across camera boards (docs/cluster.md, "Calibration across boards"): two
//! `irtrackd` processes in the camera role, each rendering its share of one simulated
//! four-camera ring rig (board b0 cameras 0 and 1, b1 cameras 2 and 3) while a 0/120/300 mm wand
//! is waved through the shared scene on the wall clock. `host-tools capture --from b0 --from b1
//! --wand` pairs their frame sets on CLOCK_REALTIME into one folder (cam0..cam3, cameras.csv),
//! `host-tools wand-calibrate` solves the whole rig from it, and the relative poses of all four
//! cameras are compared with the simulator's truth.
//!
//! Build the binaries first, with the same features as this test:
//! `cargo build -p irtrack-firmware -p irtrack-tests --features irtrack-tests/cluster
//! --bin irtrackd --example cluster_demo` and `cargo build -p irtrack-host-tools --bin
//! host-tools`. CI's workspace test build does this by itself.

#![cfg(feature = "cluster")]

mod common;

use std::process::Command;
use std::time::Instant;

use common::cluster::{
    DISTANCE_MM, FPS, RIG, assert_placed_by_capture, capture_from, two_calibration_boards,
};
use common::{bin, temp_dir};
use irtrack_core::params::RigParams;
use irtrack_firmware::source::sim::ring_rig;
use nalgebra::Rotation3;

/// Sets captured across the two boards.
const SETS: usize = 240;
/// Frames of one wand wave (it repeats): 10 s at 30 fps.
const WAVE_FRAMES: u64 = 300;
/// The single-board wand test's goals (host-tools/tests/wand_cli.rs, issue 15).
const MAX_ROTATION_DEG: f64 = 0.02;
const MAX_CENTRE_MM: f64 = 1.0;

/// A camera board rendering `cameras` of the ring rig with the wand, in the camera role.
fn board_config(board: &str, cameras: [usize; 2], zenoh: &str) -> String {
    format!(
        "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n\
         [source.sim]\nrig = \"ring\"\nring_cameras = 4\ndistance_mm = {DISTANCE_MM}\nfps = {FPS}\n\
         wall_clock = true\ncameras = [{}, {}]\nwand_mm = [0.0, 120.0, 300.0]\nwand_frames = {WAVE_FRAMES}\n\
         [cluster]\nrole = \"camera\"\nrig = \"{RIG}\"\nboard = \"{board}\"\n{zenoh}\nfps = {FPS}\n",
        cameras[0], cameras[1]
    )
}

/// (rotation error °, camera centre error mm) of camera `i` ≥ 1 relative to camera 0.
fn pose_error(truth: &RigParams, got: &RigParams, i: usize) -> (f64, f64) {
    let (t, g) = (&truth.cameras[i].cam_from_cam0, &got.cameras[i].cam_from_cam0);
    let r = Rotation3::from_matrix_unchecked(g.rotation() * t.rotation().transpose())
        .angle()
        .to_degrees();
    let c = (truth.camera_centre_cam0_mm(i).unwrap() - got.camera_centre_cam0_mm(i).unwrap()).norm();
    (r, c)
}

#[test]
fn wand_wave_captured_across_two_camera_boards_calibrates_the_whole_rig() {
    let t0 = Instant::now();
    let dir = temp_dir("cluster-wand");
    let (b0, b1) = two_calibration_boards(&dir, 0, board_config);

    let (a, b) = (b0.status.to_string(), b1.status.to_string());
    let wave = dir.join("wave");
    let sets = SETS.to_string();
    let (stdout, _, capture_s) = capture_from(&b0, &b1, &["--wand", "--count", &sets], &wave);
    println!("capture ({capture_s:.1} s):\n{stdout}");
    assert!(
        stdout.contains(&format!("board {a}: 2 cameras, 640x480 8-bit → cam0..cam1"))
            && stdout.contains(&format!("board {b}: 2 cameras, 640x480 8-bit → cam2..cam3")),
        "{stdout}"
    );
    assert!(stdout.contains(&format!("saved {SETS} sets")), "{stdout}");
    drop((b0, b1));
    assert_eq!(
        std::fs::read_to_string(wave.join("cameras.csv")).unwrap(),
        format!("camera,board,board_camera,from\n0,b0,0,{a}\n1,b0,1,{a}\n2,b1,0,{b}\n3,b1,1,{b}\n")
    );
    // Every saved set: the four cameras' frames within the pairing tolerance on CLOCK_REALTIME
    // (half a period), and the same simulated frame on both boards (their frames fall on the
    // wall clock's k / fps).
    let csv = std::fs::read_to_string(wave.join("timestamps.csv")).unwrap();
    let mut per_set: std::collections::BTreeMap<u64, Vec<u64>> = Default::default();
    for l in csv.lines().skip(1) {
        let v: Vec<u64> = l.split(',').map(|x| x.parse().unwrap()).collect();
        per_set.entry(v[0]).or_default().push(v[2]);
    }
    assert_eq!(per_set.len(), SETS);
    let mut worst_ns = 0;
    for (set, ts) in &per_set {
        assert_eq!(ts.len(), 4, "set {set}: {ts:?}");
        let spread = ts.iter().max().unwrap() - ts.iter().min().unwrap();
        worst_ns = worst_ns.max(spread);
    }
    println!(
        "largest spread of a saved set's four timestamps: {:.3} ms",
        worst_ns as f64 / 1e6
    );
    assert!(
        (worst_ns as f64) < 0.5e9 / FPS,
        "a set's frames are {worst_ns} ns apart"
    );

    // wand-calibrate on the folder as capture wrote it; intrinsics from the simulator's rig (the
    // poses are what is solved).
    let truth = ring_rig(4, DISTANCE_MM);
    let intrinsics = dir.join("intrinsics.irp");
    std::fs::write(&intrinsics, truth.to_blob().unwrap()).unwrap();
    let out = dir.join("calib");
    let started = Instant::now();
    let o = Command::new(bin("host-tools"))
        .arg("wand-calibrate")
        .arg("--frames")
        .arg(&wave)
        .arg("--intrinsics")
        .arg(&intrinsics)
        .args(["--wand-mm", "0,120,300", "--rig-id", "cluster-wand", "--out-dir"])
        .arg(&out)
        .output()
        .unwrap();
    let calib_s = started.elapsed().as_secs_f64();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert!(o.status.success(), "wand-calibrate failed:\n{stdout}\n{stderr}");
    println!("wand-calibrate ({calib_s:.1} s):\n{stderr}{stdout}");
    let got = RigParams::from_blob(&std::fs::read(out.join("rig.irp")).unwrap()).unwrap();
    assert_eq!(got.cameras.len(), 4);
    // The boards' names from cameras.csv, as the set's placement (ready for the solver).
    assert_placed_by_capture(&stdout, &wave, &got);
    for i in 1..4 {
        let (rot_deg, centre_mm) = pose_error(&truth, &got, i);
        let (b_true, b_got) = (truth.baseline_mm(i).unwrap(), got.baseline_mm(i).unwrap());
        println!(
            "cam{i} (board {}): rotation error {rot_deg:.4}°, centre error {centre_mm:.3} mm, \
             baseline {b_got:.3} mm (truth {b_true:.3} mm)",
            if i < 2 { "b0" } else { "b1" }
        );
        assert!(
            rot_deg <= MAX_ROTATION_DEG,
            "cam{i}: rotation error {rot_deg:.4}° > {MAX_ROTATION_DEG}°"
        );
        assert!(
            centre_mm <= MAX_CENTRE_MM,
            "cam{i}: centre error {centre_mm:.3} mm > {MAX_CENTRE_MM} mm"
        );
    }
    println!("whole test {:.1} s", t0.elapsed().as_secs_f64());
}
