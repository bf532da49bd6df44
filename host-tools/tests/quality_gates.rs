//! Quality gates of `wand-calibrate` and `calibrate` (docs/calibration.md, section 14): each
//! wrong input gives a non-zero exit that names the cause, computed from the data; the good
//! runs pass and their blobs carry a `good` calibration record; `--accept-poor` writes a set
//! marked poor, which `push-params` then refuses unless told `--accept-poor` too.
//!
//! The wand cases share one short wave (150 frames) of a 90° rig whose two cameras have
//! different lenses (so that swapped or wrong intrinsics show), rendered once.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use common::{lens, scratch};
use irtrack_core::params::{RigParams, Verdict};
use irtrack_host_tools::opencv_yaml::write_rig_yaml;
use irtrack_sim::checkerboard::{self, BoardSpec, PoseConfig, RenderSettings};
use irtrack_sim::rig::{CameraSpec, RigPreset, build_rig};
use irtrack_sim::wand::{WandConfig, WandWave};
use nalgebra::Vector3;

const DISTANCE_MM: f64 = 1200.0;

/// The 90° rig of wand_cli.rs, camera 1 with another lens (weaker barrel distortion).
fn rig() -> RigParams {
    let mut rig = build_rig(
        &RigPreset::Convergent {
            distance_mm: DISTANCE_MM,
            angle_deg: 90.0,
        },
        &lens(700.0, -0.30, 0.11),
    )
    .unwrap();
    rig.cameras[1].model = lens(640.0, -0.08, 0.01).model(1);
    rig.validate().unwrap();
    rig
}

fn wave(dir: &Path, frames: usize, tweak: impl FnOnce(&mut WandConfig)) {
    let mut cfg = WandConfig::new(rig(), Vector3::new(0.0, 0.0, DISTANCE_MM), frames);
    cfg.seed = 4;
    cfg.sweep_mm = Vector3::new(300.0, 170.0, 300.0);
    tweak(&mut cfg);
    WandWave::new(cfg).unwrap().write_wave(dir).unwrap();
}

/// The shared wave and the true intrinsics file, made once.
struct Shared {
    dir: PathBuf,
    wave: PathBuf,
    intrinsics: PathBuf,
}

fn shared() -> &'static Shared {
    static S: OnceLock<Shared> = OnceLock::new();
    S.get_or_init(|| {
        let dir = scratch("shared");
        let wave_dir = dir.join("wave");
        wave(&wave_dir, 150, |_| {});
        let intrinsics = dir.join("intrinsics.yaml");
        write_rig_yaml(&intrinsics, &rig()).unwrap();
        Shared {
            dir,
            wave: wave_dir,
            intrinsics,
        }
    })
}

fn host_tools(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args(args)
        .output()
        .unwrap()
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn wand_calibrate(frames: &Path, intrinsics: &Path, wand_mm: &str, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "wand-calibrate",
        "--frames",
        p(frames),
        "--intrinsics",
        p(intrinsics),
        "--wand-mm",
        wand_mm,
        "--out-dir",
        p(out),
    ];
    args.extend_from_slice(extra);
    host_tools(&args)
}

/// A refused run: non-zero exit, nothing written; returns stderr.
fn refused(o: &Output, out: &Path, what: &str) -> String {
    let (stdout, stderr) = text(o);
    assert!(!o.status.success(), "{what}: accepted\n{stdout}\n{stderr}");
    assert!(!out.join("rig.irp").exists(), "{what}: rig.irp written");
    println!("{what}: {stderr}");
    stderr
}

fn record(path: &Path) -> irtrack_core::params::CalibrationInfo {
    let rig = RigParams::from_blob(&std::fs::read(path).unwrap()).unwrap();
    rig.validate().unwrap();
    *rig.calibration.expect("a calibration record")
}

#[test]
fn good_wave_passes_and_wrong_spacing_is_found() {
    let s = shared();
    let good = s.dir.join("good");
    let o = wand_calibrate(&s.wave, &s.intrinsics, "0,120,300", &good, &[]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("verdict: good"), "{stdout}");
    let r = record(&good.join("rig.irp"));
    assert_eq!((r.method.as_str(), r.verdict), ("wand", Verdict::Good), "{r:?}");
    assert_eq!(r.rms_px.len(), 2);
    assert!(r.figure("frames_used").is_some_and(|n| n >= 50.0), "{r:?}");
    // The YAML carries the same record.
    let yaml = irtrack_host_tools::opencv_yaml::read_rig_yaml(&good.join("rig.yaml")).unwrap();
    assert_eq!(yaml.calibration.as_deref(), Some(&r));

    // The asymmetric typo of the issue: 0/100/300 given for a 0/120/300 wand.
    let bad = s.dir.join("spacing");
    let o = wand_calibrate(&s.wave, &s.intrinsics, "0,100,300", &bad, &[]);
    let e = refused(&o, &bad, "wrong spacing");
    assert!(
        e.contains("POOR wand calibration") && e.contains("reprojection RMS"),
        "{e}"
    );
    let found = e
        .split("the data fit 0/")
        .nth(1)
        .and_then(|t| t.split('/').next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no fitted spacing in: {e}"));
    assert!(
        (found - 120.0).abs() < 1.5,
        "fitted middle LED {found} mm, truth 120: {e}"
    );
    assert!(e.contains("you gave 0/100/300 mm (--wand-mm)"), "{e}");

    // --accept-poor writes it, marked poor; push-params refuses it unless told the same.
    let o = wand_calibrate(&s.wave, &s.intrinsics, "0,100,300", &bad, &["--accept-poor"]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("verdict: POOR, written anyway"), "{stdout}");
    let r = record(&bad.join("rig.irp"));
    assert_eq!(r.verdict, Verdict::Poor);
    assert!(r.summary.contains("the data fit 0/"), "{}", r.summary);
    let o = host_tools(&["push-params", "--dry-run", p(&bad.join("rig.irp"))]);
    let (_, e) = text(&o);
    assert!(
        !o.status.success() && e.contains("marked poor") && e.contains("--accept-poor"),
        "{e}"
    );
    let o = host_tools(&[
        "push-params",
        "--dry-run",
        "--accept-poor",
        p(&bad.join("rig.irp")),
    ]);
    assert!(o.status.success(), "{:?}", text(&o));
    let o = host_tools(&["show-params", p(&bad.join("rig.irp"))]);
    assert!(text(&o).0.contains("verdict POOR"), "{}", text(&o).0);
}

#[test]
fn intrinsics_of_the_wrong_camera_or_order_are_named() {
    let s = shared();
    let truth = rig();
    // Camera 1 given camera 0's intrinsics (another lens).
    let mut wrong = truth.clone();
    wrong.cameras[1].model = truth.cameras[0].model;
    let wrong_yaml = s.dir.join("wrong-intrinsics.yaml");
    write_rig_yaml(&wrong_yaml, &wrong).unwrap();
    let out = s.dir.join("wrong-camera");
    let e = refused(
        &wand_calibrate(&s.wave, &wrong_yaml, "0,120,300", &out, &[]),
        &out,
        "wrong camera's intrinsics",
    );
    assert!(e.contains("cam1's intrinsics do not fit its images"), "{e}");
    assert!(!e.contains("the data fit 0/"), "blamed the spacing: {e}");

    // The two cameras' intrinsics in swapped order.
    let mut swapped = truth.clone();
    swapped.cameras[0].model = truth.cameras[1].model;
    swapped.cameras[1].model = truth.cameras[0].model;
    let swapped_yaml = s.dir.join("swapped.yaml");
    write_rig_yaml(&swapped_yaml, &swapped).unwrap();
    let out = s.dir.join("swapped");
    let e = refused(
        &wand_calibrate(&s.wave, &swapped_yaml, "0,120,300", &out, &[]),
        &out,
        "swapped cameras",
    );
    assert!(e.contains("swapped camera order"), "{e}");

    // Intrinsics for another image size (and aspect): refused at the first frame, naming the
    // camera; cam0's intrinsics have the frames' size but cam0's frames do not fit cam1's, so no
    // other order is suggested.
    let mut vga = truth.clone();
    vga.cameras[1].model = CameraSpec::default().model(1);
    let vga_yaml = s.dir.join("vga.yaml");
    write_rig_yaml(&vga_yaml, &vga).unwrap();
    let out = s.dir.join("vga");
    let e = refused(
        &wand_calibrate(&s.wave, &vga_yaml, "0,120,300", &out, &[]),
        &out,
        "intrinsics for another size",
    );
    assert!(
        e.contains("752x480 px, but the intrinsics of camera 1 are for 640x480 px")
            && e.contains("cannot tell which from the frames")
            && !e.contains("another order"),
        "{e}"
    );
}

#[test]
fn short_or_flat_waves_are_named() {
    let s = shared();
    // The first 40 frames of the shared wave.
    let short = s.dir.join("short-wave");
    for c in 0..2 {
        let dir = short.join(format!("cam{c}"));
        std::fs::create_dir_all(&dir).unwrap();
        let mut names: Vec<_> = std::fs::read_dir(s.wave.join(format!("cam{c}")))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        names.sort();
        for n in names.iter().take(40) {
            std::fs::copy(s.wave.join(format!("cam{c}")).join(n), dir.join(n)).unwrap();
        }
    }
    let out = s.dir.join("short");
    let e = refused(
        &wand_calibrate(&short, &s.intrinsics, "0,120,300", &out, &[]),
        &out,
        "short wave",
    );
    assert!(
        e.contains("frames used") && e.contains("the wave was too short"),
        "{e}"
    );

    // A wave that keeps the wand horizontal.
    let flat = s.dir.join("flat-wave");
    wave(&flat, 100, |c| c.max_elevation_deg = 0.0);
    let out = s.dir.join("flat");
    let e = refused(
        &wand_calibrate(&flat, &s.intrinsics, "0,120,300", &out, &[]),
        &out,
        "flat wave",
    );
    assert!(e.contains("the wave was too flat"), "{e}");
}

fn board_views(dir: &Path, truth: &RigParams, views: usize) {
    let board = BoardSpec::new(9, 6, 25.0).unwrap();
    let poses = checkerboard::generate_poses(
        truth,
        &board,
        &PoseConfig {
            count: views,
            seed: 8,
            ..Default::default()
        },
    )
    .unwrap();
    let settings = RenderSettings {
        seed: 8,
        ..Default::default()
    };
    checkerboard::write_set(dir, truth, &board, &poses, &settings).unwrap();
}

fn calibrate(images: &Path, out: &Path, cols: &str, rows: &str, square: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "calibrate",
        "--images",
        p(images),
        "--out-dir",
        p(out),
        "--board-cols",
        cols,
        "--board-rows",
        rows,
        "--square-mm",
        square,
    ];
    args.extend_from_slice(extra);
    host_tools(&args)
}

#[test]
fn board_of_wrong_size_or_square_is_named() {
    let dir = scratch("board");
    let truth = build_rig(
        &RigPreset::Parallel {
            baseline_mm: irtrack_sim::rig::TABLE_I_BASELINE_MM,
        },
        &CameraSpec::default(),
    )
    .unwrap();
    let baseline = format!("{}", irtrack_sim::rig::TABLE_I_BASELINE_MM);
    let images = dir.join("views");
    board_views(&images, &truth, 10);
    // The good run passes its gate, with the measured baseline, and carries the record.
    let good = dir.join("good");
    let o = calibrate(
        &images,
        &good,
        "9",
        "6",
        "25",
        &["--expect-baseline-mm", &baseline],
    );
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("verdict: good"), "{stdout}");
    let r = record(&good.join("rig.irp"));
    assert_eq!((r.method.as_str(), r.verdict), ("checkerboard", Verdict::Good));
    // Squares counted instead of inner corners: one more each way (two views: OpenCV takes
    // seconds per image to give up on a wrongly sized board).
    let two = dir.join("two-views");
    board_views(&two, &truth, 2);
    let out = dir.join("squares");
    let e = refused(
        &calibrate(&two, &out, "10", "7", "25", &[]),
        &out,
        "board size off by one",
    );
    assert!(
        e.contains("shows a board of 9x6 inner corners") && e.contains("--board-cols 9 --board-rows 6"),
        "{e}"
    );
    // A wrong square size scales every length: found against the expected baseline.
    let out = dir.join("square-mm");
    let e = refused(
        &calibrate(
            &images,
            &out,
            "9",
            "6",
            "30",
            &["--expect-baseline-mm", &baseline],
        ),
        &out,
        "wrong --square-mm",
    );
    assert!(e.contains("the data fit squares of 25.0"), "{e}");
}
