//! The likely causes `wand-calibrate` names when it refuses a calibration (docs/calibration.md,
//! "How the likely causes are computed"): one simulated wave per common mistake, each checked
//! for the cause it names — and for the wrong causes it must not name — plus the waves that must
//! be accepted (the right input, and the spacing read from the other end, which is the same wand).
//!
//! The rig: three cameras 1.2 m from the centre (the wand_cli.rs rig with a raised camera),
//! camera 1 with another lens and a rolling shutter, free-running at 30 fps — the set-up in
//! which a mistyped spacing used to be blamed on camera 1's intrinsics (its raw spots bend with
//! the shutter's row delays). Camera 2's lens differs again.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use common::{lens, scratch};
use irtrack_core::camera::{CameraModel, ImageSize};
use irtrack_core::params::{CameraParams, RigParams};
use irtrack_host_tools::opencv_yaml::write_rig_yaml;
use irtrack_sim::rig::{CameraSpec, RigPreset, build_rig};
use irtrack_sim::timing::SimCameraTiming;
use irtrack_sim::wand::{WandConfig, WandWave, look_at};
use nalgebra::Vector3;

const DISTANCE_MM: f64 = 1200.0;
/// Camera 1's rolling shutter: 15 µs per row (7.2 ms over its 480 rows).
const LINE_TIME_US: f64 = 15.0;
const TIMING: &str = "1:rolling:line_time_us=15";

fn centre() -> Vector3<f64> {
    Vector3::new(0.0, 0.0, DISTANCE_MM)
}

/// The 90° pair plus a raised camera; three different lenses.
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
    let c2 = centre() + Vector3::new(0.5, -0.75, -0.45).normalize() * DISTANCE_MM;
    rig.cameras.push(CameraParams {
        model: lens(760.0, -0.18, 0.05).model(2),
        cam_from_cam0: look_at(c2, centre(), Vector3::new(0.0, -1.0, 0.0)).unwrap(),
    });
    rig.rig_id = "causes".into();
    rig.validate().unwrap();
    rig
}

/// Free-running cameras at 30 fps; camera 1 with a rolling shutter.
fn timing() -> Vec<SimCameraTiming> {
    vec![
        SimCameraTiming::default(),
        SimCameraTiming {
            phase_ns: 2_100_000.0,
            line_time_ns: LINE_TIME_US * 1000.0,
            ..SimCameraTiming::default()
        },
        SimCameraTiming {
            phase_ns: -1_300_000.0,
            ..SimCameraTiming::default()
        },
    ]
}

fn wave(dir: &Path, truth: &RigParams, tweak: impl FnOnce(&mut WandConfig)) {
    let mut cfg = WandConfig::new(truth.clone(), centre(), 200);
    cfg.seed = 11;
    cfg.fps = 30.0;
    cfg.sweep_mm = Vector3::new(300.0, 170.0, 300.0);
    cfg.timing = timing();
    tweak(&mut cfg);
    WandWave::new(cfg).unwrap().write_wave(dir).unwrap();
}

struct Shared {
    dir: PathBuf,
    wave: PathBuf,
    intrinsics: PathBuf,
}

/// The shared 0/120/300 mm wave and the true intrinsics, made once.
fn shared() -> &'static Shared {
    static S: OnceLock<Shared> = OnceLock::new();
    S.get_or_init(|| {
        let dir = scratch("shared");
        let w = dir.join("wave");
        wave(&w, &rig(), |_| {});
        let intrinsics = dir.join("intrinsics.yaml");
        write_rig_yaml(&intrinsics, &rig()).unwrap();
        Shared {
            dir,
            wave: w,
            intrinsics,
        }
    })
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn wand_calibrate(frames: &Path, intrinsics: &Path, wand_mm: &str, out: &Path) -> Output {
    Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args(["wand-calibrate", "--frames"])
        .arg(frames)
        .arg("--intrinsics")
        .arg(intrinsics)
        .args(["--wand-mm", wand_mm, "--timing", TIMING, "--out-dir"])
        .arg(out)
        .output()
        .unwrap()
}

/// A refused run: non-zero exit, nothing written; returns the error line.
fn refused(o: &Output, out: &Path, what: &str) -> String {
    let (stdout, stderr) = text(o);
    assert!(!o.status.success(), "{what}: accepted\n{stdout}\n{stderr}");
    assert!(!out.join("rig.irp").exists(), "{what}: rig.irp written");
    let e = stderr
        .lines()
        .find(|l| l.starts_with("Error"))
        .unwrap_or(&stderr)
        .to_string();
    println!("{what}:\n  {e}");
    e
}

fn accepted(o: &Output, out: &Path, what: &str) -> RigParams {
    let (stdout, stderr) = text(o);
    assert!(o.status.success(), "{what}: refused\n{stdout}\n{stderr}");
    assert!(stdout.contains("verdict: good"), "{what}: {stdout}");
    RigParams::from_blob(&std::fs::read(out.join("rig.irp")).unwrap()).unwrap()
}

/// None of the other causes is named alongside the right one.
fn names_only(e: &str, right: &str, what: &str) {
    assert!(e.contains(right), "{what}: `{right}` not named: {e}");
    for wrong in [
        "the wand's LED spacing",
        "intrinsics do not fit",
        "swapped camera order",
        "another resolution",
        "the wand is not straight",
        "cannot tell",
    ] {
        if !right.contains(wrong) && !wrong.contains(right) {
            assert!(!e.contains(wrong), "{what}: also named `{wrong}`: {e}");
        }
    }
}

/// The largest rotation (degrees) and centre (mm) difference of any camera between two rigs.
fn pose_difference(a: &RigParams, b: &RigParams) -> (f64, f64) {
    let mut worst: (f64, f64) = (0.0, 0.0);
    for c in 1..a.cameras.len() {
        let (ta, tb) = (&a.cameras[c].cam_from_cam0, &b.cameras[c].cam_from_cam0);
        let r = ta.rotation().transpose() * tb.rotation();
        let angle = ((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        let centre = (a.camera_centre_cam0_mm(c).unwrap() - b.camera_centre_cam0_mm(c).unwrap()).norm();
        worst.0 = worst.0.max(angle);
        worst.1 = worst.1.max(centre);
    }
    worst
}

#[test]
fn the_right_wave_and_the_spacing_read_from_the_other_end_are_accepted() {
    let s = shared();
    let out = s.dir.join("good");
    let good = accepted(
        &wand_calibrate(&s.wave, &s.intrinsics, "0,120,300", &out),
        &out,
        "right spacing",
    );
    let truth = rig();
    let (deg, mm) = pose_difference(&truth, &good);
    println!("right spacing: poses within {deg:.4}° and {mm:.3} mm of the truth");
    assert!(deg < 0.05 && mm < 1.0, "{deg}° {mm} mm");
    // LED order reversed: 0/180/300 is the same wand measured from its other end. The
    // identification takes that end as end 0 and the rig comes out the same.
    let out = s.dir.join("reversed");
    let reversed = accepted(
        &wand_calibrate(&s.wave, &s.intrinsics, "0,180,300", &out),
        &out,
        "LED order reversed",
    );
    let (deg, mm) = pose_difference(&good, &reversed);
    println!("reversed order: poses within {deg:.5}° and {mm:.4} mm of the right spacing's");
    assert!(deg < 0.005 && mm < 0.05, "{deg}° {mm} mm");
}

#[test]
fn a_mistyped_spacing_is_named_with_the_spacing_the_data_fit() {
    let s = shared();
    // The typo: 0/100/300 for a 0/120/300 wand, on a rig with a rolling-shutter camera.
    let out = s.dir.join("typo");
    let e = refused(
        &wand_calibrate(&s.wave, &s.intrinsics, "0,100,300", &out),
        &out,
        "spacing 0,100,300",
    );
    names_only(&e, "the wand's LED spacing", "spacing 0,100,300");
    assert!(e.contains("you gave 0/100/300 mm (--wand-mm)"), "{e}");
    let middle = |e: &str| -> f64 {
        e.split("the data fit 0/")
            .nth(1)
            .and_then(|t| t.split('/').next())
            .and_then(|v| v.parse().ok())
            .unwrap_or_else(|| panic!("no fitted spacing in: {e}"))
    };
    let m = middle(&e);
    assert!(
        (m - 120.0).abs() < 1.5,
        "fitted middle LED {m} mm, truth 120: {e}"
    );
    // A typo that reads better from the other end: 0/170/300. The LED nearer the middle is
    // then taken as 180 mm from the first; both readings are given.
    let out = s.dir.join("typo-other-end");
    let e = refused(
        &wand_calibrate(&s.wave, &s.intrinsics, "0,170,300", &out),
        &out,
        "spacing 0,170,300",
    );
    names_only(&e, "the wand's LED spacing", "spacing 0,170,300");
    let m = middle(&e);
    assert!(
        (m - 180.0).abs() < 1.5,
        "fitted middle LED {m} mm, truth 180: {e}"
    );
    let other = e
        .split("read from the other end: 0/")
        .nth(1)
        .and_then(|t| t.split('/').next())
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no reading from the other end: {e}"));
    assert!((other - 120.0).abs() < 1.5, "{e}");
}

/// Writes the true rig with `change` applied as the intrinsics file.
fn intrinsics_with(name: &str, change: impl FnOnce(&mut RigParams)) -> PathBuf {
    let mut r = rig();
    change(&mut r);
    let p = shared().dir.join(format!("{name}.yaml"));
    write_rig_yaml(&p, &r).unwrap();
    p
}

#[test]
fn intrinsics_of_another_camera_are_named() {
    let s = shared();
    let truth = rig();
    // Camera 2 given camera 0's lens: its spots bend, and without it the others fit.
    let wrong = intrinsics_with("cam2-given-cam0", |r| r.cameras[2].model = truth.cameras[0].model);
    let out = s.dir.join("cam2-wrong");
    let e = refused(
        &wand_calibrate(&s.wave, &wrong, "0,120,300", &out),
        &out,
        "cam2 given cam0's intrinsics",
    );
    names_only(&e, "cam2's intrinsics do not fit its images", "cam2 wrong");
    assert!(
        !e.contains("cam0's intrinsics do not") && !e.contains("cam1's intrinsics do not"),
        "{e}"
    );
    // Cameras 0 and 2 swapped.
    let swapped = intrinsics_with("swapped", |r| {
        r.cameras[0].model = truth.cameras[2].model;
        r.cameras[2].model = truth.cameras[0].model;
    });
    let out = s.dir.join("swapped");
    let e = refused(
        &wand_calibrate(&s.wave, &swapped, "0,120,300", &out),
        &out,
        "cameras 0 and 2 swapped",
    );
    names_only(&e, "swapped camera order", "swapped");
    assert!(
        e.contains("cam0") && e.contains("cam2") && !e.contains("cam1's"),
        "{e}"
    );
}

#[test]
fn intrinsics_of_another_resolution_are_named() {
    let s = shared();
    let truth = rig();
    // Camera 1's intrinsics as calibrated at twice the resolution (1504x960, before 2x2
    // binning): the same lens, scaled.
    let full = intrinsics_with("cam1-full-resolution", |r| {
        let m = &truth.cameras[1].model;
        let mut k = m.intrinsics;
        k.fx_px *= 2.0;
        k.fy_px *= 2.0;
        k.cx_px = (k.cx_px + 0.5) * 2.0 - 0.5;
        k.cy_px = (k.cy_px + 0.5) * 2.0 - 0.5;
        r.cameras[1].model = CameraModel {
            intrinsics: k,
            distortion: m.distortion,
            image_size: ImageSize {
                width_px: 1504,
                height_px: 960,
            },
        };
    });
    let out = s.dir.join("resolution");
    let e = refused(
        &wand_calibrate(&s.wave, &full, "0,120,300", &out),
        &out,
        "cam1 intrinsics for 1504x960",
    );
    assert!(
        e.contains("752x480 px, but the intrinsics of camera 1 are for 1504x960 px")
            && e.contains("the same camera at another resolution")
            && e.contains("scale fx, fy, cx, cy by 0.500"),
        "{e}"
    );
    assert!(!e.contains("another order"), "{e}");
    // VGA intrinsics (another aspect) for camera 1: no scaling can fit and no other order of
    // the cameras fits every frame size, so nothing is left to test: it says it cannot tell
    // another camera's intrinsics from another sensor mode's (and does not guess an order).
    let vga = intrinsics_with("cam1-vga", |r| {
        r.cameras[1].model = CameraSpec::default().model(1)
    });
    let out = s.dir.join("vga");
    let e = refused(
        &wand_calibrate(&s.wave, &vga, "0,120,300", &out),
        &out,
        "cam1 intrinsics for 640x480",
    );
    assert!(
        e.contains("the intrinsics of camera 1 are for 640x480 px")
            && e.contains("cannot tell which from the frames")
            && e.contains("calibrate cam1's intrinsics at 752x480 px"),
        "{e}"
    );
    assert!(!e.contains("another order"), "{e}");
}

#[test]
fn a_wand_that_is_not_straight_is_named() {
    let s = shared();
    let dir = s.dir.join("bent-wave");
    wave(&dir, &rig(), |c| c.bend_mm = 4.0);
    let out = s.dir.join("bent");
    let e = refused(
        &wand_calibrate(&dir, &s.intrinsics, "0,120,300", &out),
        &out,
        "wand bent by 4 mm",
    );
    names_only(&e, "the wand is not straight", "bent");
    // 4 mm of bow puts the middle LED (0.4 of the way) 3.84 mm off the line.
    let mm: f64 = e
        .split("inner LEDs lie ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no offset in: {e}"));
    assert!((mm - 3.84).abs() < 0.5, "{mm} mm: {e}");
}

/// Camera 1 knocked half-way through the wave: the first 100 frames from the rig, the rest with
/// camera 1 turned by 1°. Returns the recording.
fn knocked_wave() -> PathBuf {
    let s = shared();
    let truth = rig();
    let mut knocked = truth.clone();
    let turn = nalgebra::Rotation3::from_axis_angle(&Vector3::y_axis(), 1f64.to_radians());
    let t = knocked.cameras[1].cam_from_cam0;
    knocked.cameras[1].cam_from_cam0 = irtrack_core::camera::RigidTransform::from_parts(
        &(turn.matrix() * t.rotation()),
        &(turn.matrix() * t.translation_mm()),
    );
    let (a, b) = (s.dir.join("knock-a"), s.dir.join("knock-b"));
    wave(&a, &truth, |_| {});
    wave(&b, &knocked, |_| {});
    let dir = s.dir.join("knocked");
    for c in 0..3 {
        let to = dir.join(format!("cam{c}"));
        std::fs::create_dir_all(&to).unwrap();
        for f in 0..200 {
            let from = if f < 100 { &a } else { &b };
            let name = format!("{f:06}.pgm");
            std::fs::copy(from.join(format!("cam{c}")).join(&name), to.join(&name)).unwrap();
        }
    }
    std::fs::copy(a.join("timestamps.csv"), dir.join("timestamps.csv")).unwrap();
    dir
}

#[test]
fn a_camera_that_moved_is_named_with_three_cameras_and_undetermined_with_two() {
    let s = shared();
    let dir = knocked_wave();
    let out = s.dir.join("knocked-3");
    let e = refused(
        &wand_calibrate(&dir, &s.intrinsics, "0,120,300", &out),
        &out,
        "camera 1 knocked mid-wave",
    );
    names_only(&e, "cam1 disagrees with the other cameras", "knocked, 3 cameras");
    // Cameras 0 and 1 alone: nothing tells a moved camera from the rest, and it says so.
    let two = s.dir.join("knocked-two");
    for c in 0..2 {
        let to = two.join(format!("cam{c}"));
        std::fs::create_dir_all(&to).unwrap();
        for e in std::fs::read_dir(dir.join(format!("cam{c}"))).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
    let stamps = std::fs::read_to_string(dir.join("timestamps.csv")).unwrap();
    let kept: Vec<&str> = stamps
        .lines()
        .filter(|l| l.split(',').nth(1) != Some("2"))
        .collect();
    std::fs::write(two.join("timestamps.csv"), kept.join("\n") + "\n").unwrap();
    let intrinsics = intrinsics_with("two-cameras", |r| {
        r.cameras.truncate(2);
    });
    let out = s.dir.join("knocked-2");
    let e = refused(
        &wand_calibrate(&two, &intrinsics, "0,120,300", &out),
        &out,
        "camera 1 knocked mid-wave, two cameras",
    );
    names_only(&e, "cannot tell", "knocked, 2 cameras");
}
