//! Parameter file tools: OpenCV YAML round trips, show/convert-params and push-params against
//! a fake irtrackd parameter endpoint built on `irtrack_core::param_wire`.

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::thread;
use std::time::Duration;

use common::*;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::param_wire::{self, RejectCode, Verdict};
use irtrack_core::params::{CameraParams, RigParams, ToolDefinition};
use irtrack_core::timing::{CameraTiming, Shutter};
use irtrack_host_tools::opencv_yaml::{load_params_any, read_rig_yaml, write_rig_yaml};

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("irtrack-params-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn camera(fx: f64, k1: f64, size: (u32, u32), pose: RigidTransform) -> CameraParams {
    CameraParams {
        model: CameraModel {
            intrinsics: Intrinsics {
                fx_px: fx,
                fy_px: fx * 1.001,
                cx_px: f64::from(size.0) / 2.0 - 0.3,
                cy_px: f64::from(size.1) / 2.0 + 0.7,
            },
            distortion: Distortion {
                k1,
                k2: 0.0123456789,
                p1: -1e-4,
                p2: 2.5e-4,
                k3: -0.001,
            },
            image_size: ImageSize {
                width_px: size.0,
                height_px: size.1,
            },
        },
        cam_from_cam0: pose,
    }
}

/// Three cameras: a parallel partner 120 mm to the right and a 90° convergent one, with a
/// registration and a tool, so every YAML key is exercised.
fn rig3() -> RigParams {
    let r90y = [0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0];
    // Centre (600, 0, 600) mm in camera 0: t = -R c.
    let t90 = [600.0, 0.0, -600.0];
    let c = 0.1f64.cos();
    let s = 0.1f64.sin();
    RigParams {
        rig_id: "lab-rig-3".into(),
        created_unix_s: 1_717_171_717,
        cameras: vec![
            camera(812.345678901, -0.2876543, (1280, 720), RigidTransform::IDENTITY),
            camera(
                800.1,
                -0.31,
                (1280, 720),
                RigidTransform {
                    t_mm: [-120.123456789, 0.5, -0.25],
                    ..RigidTransform::IDENTITY
                },
            ),
            camera(
                640.0 / 3.0,
                0.05,
                (640, 480),
                RigidTransform {
                    r_row_major: r90y,
                    t_mm: t90,
                },
            ),
        ],
        world_from_cam0: Some(RigidTransform {
            r_row_major: [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0],
            t_mm: [1000.0, -250.5, 80.0],
        }),
        tools: vec![ToolDefinition {
            name: "probe".into(),
            leds_mm: vec![[0.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, 35.5, 10.0]],
            tip_mm: None,
        }],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

fn rig2() -> RigParams {
    let mut r = rig3();
    r.cameras.truncate(2);
    r.world_from_cam0 = None;
    r.tools.clear();
    r.rig_id = "pair-1".into();
    r
}

#[test]
fn yaml_round_trip_is_exact() {
    let rig = rig3();
    rig.validate().unwrap();
    let path = tmp("rig3.yaml");
    write_rig_yaml(&path, &rig).unwrap();
    let yaml = std::fs::read_to_string(&path).unwrap();
    assert!(yaml.starts_with("%YAML:1.0"), "{yaml}");
    for key in [
        "K1: !!opencv-matrix",
        "D3: !!opencv-matrix",
        "\nR: !!opencv-matrix",
        "\nT3: !!opencv-matrix",
    ] {
        assert!(yaml.contains(key), "missing {key:?} in\n{yaml}");
    }
    assert!(
        yaml.contains("image_width: 1280") && yaml.contains("image_height_3: 480"),
        "{yaml}"
    );
    assert_eq!(read_rig_yaml(&path).unwrap(), rig);
    assert_eq!(load_params_any(&path).unwrap(), rig);
}

/// The layout OpenCV's stereo_calib sample and hand-written files use: `%YAML:1.0`,
/// `!!opencv-matrix`, M1/M2 for the camera matrices, 1×4 distortion, one image size.
const HANDWRITTEN: &str = "%YAML:1.0
---
rig_id: bench
image_width: 640
image_height: 480
M1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 6.8e+02, 0., 3.195e+02, 0., 6.81e+02, 2.395e+02, 0., 0., 1. ]
D1: !!opencv-matrix
   rows: 1
   cols: 4
   dt: d
   data: [ -2.8e-01, 9.e-02, 1.e-03, -5.e-04 ]
M2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: f
   data: [ 690., 0., 321., 0., 690., 241., 0., 0., 1. ]
D2: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -0.25, 0.08, 0., 0., -0.01 ]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ -150.5, 0., 0. ]
";

#[test]
fn reads_handwritten_opencv_yaml() {
    let path = tmp("handwritten.yml");
    std::fs::write(&path, HANDWRITTEN).unwrap();
    let rig = read_rig_yaml(&path).unwrap();
    assert_eq!(rig.rig_id, "bench");
    assert_eq!(rig.created_unix_s, 0);
    assert_eq!(rig.cameras.len(), 2);
    let c0 = &rig.cameras[0].model;
    assert_eq!(
        c0.intrinsics,
        Intrinsics {
            fx_px: 680.0,
            fy_px: 681.0,
            cx_px: 319.5,
            cy_px: 239.5
        }
    );
    assert_eq!(
        c0.distortion,
        Distortion {
            k1: -0.28,
            k2: 0.09,
            p1: 0.001,
            p2: -0.0005,
            k3: 0.0
        }
    );
    assert_eq!(
        c0.image_size,
        ImageSize {
            width_px: 640,
            height_px: 480
        }
    );
    assert_eq!(rig.cameras[1].model.intrinsics.fx_px, 690.0);
    assert_eq!(rig.cameras[1].model.distortion.k3, -0.01);
    assert_eq!(rig.cameras[1].cam_from_cam0.t_mm, [-150.5, 0.0, 0.0]);
    assert_eq!(rig.cameras[0].cam_from_cam0, RigidTransform::IDENTITY);
    rig.validate().unwrap();
    assert!((rig.baseline_mm(1).unwrap() - 150.5).abs() < 1e-12);
}

#[test]
fn yaml_errors_name_file_and_key() {
    let path = tmp("missing_t.yaml");
    std::fs::write(&path, HANDWRITTEN.split("T: !!").next().unwrap()).unwrap();
    let e = format!("{:#}", read_rig_yaml(&path).unwrap_err());
    assert!(
        e.contains("missing_t.yaml") && e.contains("missing `T` (camera 2 pose)"),
        "{e}"
    );

    let path = tmp("skew.yaml");
    std::fs::write(
        &path,
        HANDWRITTEN.replace("6.8e+02, 0., 3.195e+02", "6.8e+02, 2., 3.195e+02"),
    )
    .unwrap();
    let e = format!("{:#}", read_rig_yaml(&path).unwrap_err());
    assert!(e.contains("skew"), "{e}");

    let path = tmp("k_shape.yaml");
    std::fs::write(
        &path,
        HANDWRITTEN.replacen(
            "rows: 3\n   cols: 3\n   dt: f\n   data: [ 690., 0., 321., 0., 690., 241., 0., 0., 1. ]",
            "rows: 1\n   cols: 3\n   dt: f\n   data: [ 690., 0., 321. ]",
            1,
        ),
    )
    .unwrap();
    let e = format!("{:#}", read_rig_yaml(&path).unwrap_err());
    assert!(e.contains("`M2`") && e.contains("1×3"), "{e}");

    let path = tmp("garbage.yaml");
    std::fs::write(&path, "%YAML:1.0\n---\nK1: [ unclosed\n").unwrap();
    let e = format!("{:#}", read_rig_yaml(&path).unwrap_err());
    assert!(e.contains("garbage.yaml"), "{e}");

    let path = tmp("neither.bin");
    std::fs::write(&path, b"hello world").unwrap();
    let e = format!("{:#}", load_params_any(&path).unwrap_err());
    assert!(
        e.contains("neither.bin") && e.contains("neither a parameter blob"),
        "{e}"
    );
}

#[test]
fn convert_blob_yaml_blob_is_byte_identical() {
    let rig = rig3();
    let blob = tmp("c.irp");
    std::fs::write(&blob, rig.to_blob().unwrap()).unwrap();
    let yaml = tmp("c.yaml");
    let back = tmp("c_back.irp");
    let o = host_tools(&["convert-params", p(&blob), p(&yaml)]);
    assert!(o.status.success(), "{:?}", text(&o));
    let o = host_tools(&["convert-params", p(&yaml), p(&back)]);
    assert!(o.status.success(), "{:?}", text(&o));
    assert_eq!(std::fs::read(&back).unwrap(), rig.to_blob().unwrap());
}

#[test]
fn convert_refuses_invalid_unless_forced() {
    let mut rig = rig2();
    rig.cameras[1].model.intrinsics.fx_px = -1.0;
    let blob = tmp("bad_fx.irp");
    std::fs::write(&blob, rig.to_blob().unwrap()).unwrap();
    let out = tmp("bad_fx.yaml");
    let o = host_tools(&["convert-params", p(&blob), p(&out)]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("bad_fx.irp") && err.contains("focal length"),
        "{err}"
    );
    let o = host_tools(&["convert-params", "--force", p(&blob), p(&out)]);
    assert!(o.status.success(), "{:?}", text(&o));
    assert_eq!(read_rig_yaml(&out).unwrap(), rig);
}

/// An integrator's set calibrated on one board gets its placement without recalibrating:
/// `convert-params --placement` writes a blob whose placement decodes as given (version 5: the
/// changed set gets the next serial), replaces an existing one, and names wrong lists.
#[test]
fn convert_params_places_the_cameras_on_boards() {
    let rig = rig2();
    let blob = tmp("unplaced.irp");
    std::fs::write(&blob, rig.to_blob().unwrap()).unwrap();
    let placed = tmp("placed.irp");
    let o = host_tools(&["convert-params", p(&blob), p(&placed), "--placement", "b1:0,b0:1"]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(out.contains("placement: cam0 = b1/0, cam1 = b0/1\n"), "{out}");
    let bytes = std::fs::read(&placed).unwrap();
    assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 5, "blob format version");
    let got = RigParams::from_blob(&bytes).unwrap();
    assert!(
        got.serial >= 1_700_000_000,
        "changed set gets a serial, got {}",
        got.serial
    );
    let places: Vec<(&str, u8)> = got
        .placement
        .iter()
        .map(|p| (p.board.as_str(), p.local_index))
        .collect();
    assert_eq!(places, [("b1", 0), ("b0", 1)]);
    assert_eq!(got.cameras, rig.cameras);
    // Replaced, and said what it was.
    let again = tmp("replaced.irp");
    let o = host_tools(&[
        "convert-params",
        p(&placed),
        p(&again),
        "--placement",
        "b0:0,b1:0",
    ]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(
        out.contains("placement: cam0 = b0/0, cam1 = b1/0 (was: cam0 = b1/0, cam1 = b0/1)"),
        "{out}"
    );
    for (spec, want) in [
        ("b0:0", "--placement places 1 camera, the parameter set has 2"),
        (
            "b0:1,b0:1",
            "--placement: cameras 0 and 1 are both placed on board b0 camera 1",
        ),
        ("b0:0,b1", "--placement entry 1 (\"b1\") is not BOARD:INDEX"),
        ("b0:0,b1:x", "camera index \"x\" is not a number 0..=255"),
        (
            "b0:0,b 1:0",
            "camera 1: board name \"b 1\" must be 1..=32 characters",
        ),
    ] {
        let out = tmp("never.irp");
        let o = host_tools(&["convert-params", p(&blob), p(&out), "--placement", spec]);
        let (_, err) = text(&o);
        assert!(!o.status.success() && err.contains(want), "{spec}: {err}");
        assert!(!out.exists(), "{spec}: wrote {}", out.display());
    }
    let o = host_tools(&[
        "convert-params",
        p(&blob),
        p(&tmp("placed.yaml")),
        "--placement",
        "b0:0,b1:0",
    ]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("OpenCV YAML carries no camera placement"),
        "{err}"
    );
}

/// `convert-params --timing` / `--serial` write a camera's timing and the serial into a set
/// (blob and YAML), `show-params` prints the timing, the serial and the placement.
#[test]
fn convert_params_sets_timing_and_serial_and_show_params_prints_them() {
    let rig = rig2();
    let blob = tmp("untimed.irp");
    std::fs::write(&blob, rig.to_blob().unwrap()).unwrap();
    let timed = tmp("timed.irp");
    let o = host_tools(&[
        "convert-params",
        p(&blob),
        p(&timed),
        "--timing",
        "1:rolling:line_time_us=15.2:offset_us=-120",
        "--timing",
        "0:global:exposure_us=500",
    ]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(
        out.contains("timing: camera 1: rolling shutter, line time 15.200 us, offset -120.000 us"),
        "{out}"
    );
    let got = RigParams::from_blob(&std::fs::read(&timed).unwrap()).unwrap();
    assert_eq!(
        got.camera_timing(1),
        CameraTiming {
            shutter: Shutter::Rolling,
            line_time_ns: 15_200,
            exposure_ns: 0,
            offset_ns: -120_000,
        }
    );
    assert_eq!(got.camera_timing(0).exposure_ns, 500_000);
    assert!(got.serial >= 1_700_000_000, "serial {}", got.serial);
    assert_eq!(got.cameras, rig.cameras);
    assert!(out.contains(&format!("serial: {} (was 0)", got.serial)), "{out}");

    // Through YAML and back: the same set, byte for byte; a plain conversion keeps the serial.
    let yaml = tmp("timed.yaml");
    let back = tmp("timed-back.irp");
    assert!(
        host_tools(&["convert-params", p(&timed), p(&yaml)])
            .status
            .success()
    );
    assert!(
        host_tools(&["convert-params", p(&yaml), p(&back)])
            .status
            .success()
    );
    assert_eq!(std::fs::read(&back).unwrap(), std::fs::read(&timed).unwrap());

    // --serial sets it explicitly; with --placement, show-params prints all three.
    let placed = tmp("timed-placed.irp");
    let o = host_tools(&[
        "convert-params",
        p(&timed),
        p(&placed),
        "--serial",
        "42",
        "--placement",
        "b0:0,b1:3",
    ]);
    assert!(o.status.success(), "{}", text(&o).1);
    assert_eq!(
        RigParams::from_blob(&std::fs::read(&placed).unwrap())
            .unwrap()
            .serial,
        42
    );
    let o = host_tools(&["show-params", p(&placed)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    for want in [
        "serial:       42\n",
        "timing:     global shutter, exposure 500.000 us, offset +0.000 us\n",
        "timing:     rolling shutter, line time 15.200 us, offset -120.000 us\n",
        "placement:  board \"b1\", camera 3 there",
        "placement:    2 cameras on 2 boards (b0, b1)",
        "camera 0 = board \"b0\" camera 0",
        "parameter blob v5",
    ] {
        assert!(out.contains(want), "missing {want:?} in\n{out}");
    }
    // A set without timing or serial says so.
    let o = host_tools(&["show-params", p(&blob)]);
    let out = text(&o).0;
    assert!(out.contains("serial:       none"), "{out}");
    assert!(out.contains("the set carries no timing"), "{out}");
    assert!(out.contains("placement:    one board"), "{out}");

    let o = host_tools(&[
        "convert-params",
        p(&blob),
        p(&tmp("never-timed.irp")),
        "--timing",
        "1:rolling",
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success() && err.contains("line_time_ns > 0"), "{err}");
}

/// `push-params --allow-rollback` sends the flagged request (docs/param-protocol.md); without
/// it the plain request goes out and the device's ROLLBACK refusal is reported.
#[test]
fn push_params_allow_rollback_sends_the_flag() {
    let blob = tmp("rollback.irp");
    std::fs::write(&blob, rig2().to_blob().unwrap()).unwrap();
    for allow in [false, true] {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        // A device whose active set is newer: refuses unless the request allows a rollback.
        let server = thread::spawn(move || {
            let (mut s, _) = listener.accept().unwrap();
            let mut hdr = [0u8; param_wire::PUSH_HEADER_LEN];
            s.read_exact(&mut hdr).unwrap();
            let head = param_wire::parse_push_head(&hdr).unwrap();
            let mut options = param_wire::PushOptions::default();
            if head.has_flags {
                let mut flags = [0u8; param_wire::PUSH_FLAGS_LEN];
                s.read_exact(&mut flags).unwrap();
                options = param_wire::PushOptions::from_flags(u32::from_le_bytes(flags)).unwrap();
            }
            let mut body = vec![0u8; head.blob_len];
            s.read_exact(&mut body).unwrap();
            let rig = RigParams::from_blob(&body).unwrap();
            let v = if options.allow_rollback {
                Verdict::Accepted { rig_id: rig.rig_id }
            } else {
                Verdict::Rejected {
                    code: RejectCode::Rollback,
                    message: "parameter set pair-1 (no serial, created 2024-05-31 16:08 UTC) is older than the active set cell-v2".into(),
                }
            };
            s.write_all(v.to_line().as_bytes()).unwrap();
            (head.has_flags, options.allow_rollback)
        });
        let mut args = vec!["push-params", "--to", &addr, p(&blob)];
        if allow {
            args.push("--allow-rollback");
        }
        let o = host_tools(&args);
        let (out, err) = text(&o);
        assert_eq!(server.join().unwrap(), (allow, allow));
        if allow {
            assert!(o.status.success(), "{out}\n{err}");
            assert!(
                out.contains("--allow-rollback") && out.contains("rig pair-1 is active"),
                "{out}"
            );
        } else {
            assert!(!o.status.success());
            assert!(
                err.contains("ROLLBACK") && err.contains("older than the active set"),
                "{err}"
            );
        }
    }
}

#[test]
fn show_params_reports_geometry() {
    let blob = tmp("show.irp");
    std::fs::write(&blob, rig3().to_blob().unwrap()).unwrap();
    let o = host_tools(&["show-params", p(&blob)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    for want in [
        "rig id:       lab-rig-3",
        "created:      2024-05-31T16:08:37Z",
        "cameras:      3",
        "fx 812.346 px",
        "1280 x 720 px",
        "optical axes 90.000 deg apart",
        "baseline 848.528 mm",
        "centre:     (600.000, 0.000, 600.000) mm",
        "registration: world from camera 0",
        "tool \"probe\": 3 LEDs",
        "validation:   OK",
        "parameter blob v1",
    ] {
        assert!(out.contains(want), "missing {want:?} in\n{out}");
    }
    // Camera 1: 120.12 mm (plus small y/z offsets) from camera 0, parallel axes.
    let b1 = (120.123456789f64.powi(2) + 0.25 + 0.0625).sqrt();
    assert!(
        out.contains(&format!(
            "baseline {b1:.3} mm from camera 0, optical axes 0.000 deg"
        )),
        "{out}"
    );

    let bad = tmp("show_truncated.irp");
    std::fs::write(&bad, &rig3().to_blob().unwrap()[..40]).unwrap();
    let o = host_tools(&["show-params", p(&bad)]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("show_truncated.irp") && err.contains("truncated"),
        "{err}"
    );
}

#[test]
fn show_params_compares_two_calibrations() {
    let a = rig3();
    // The same rig with camera 2 turned 0.5° about its own vertical axis and moved 2 mm.
    let mut b = rig3();
    let old = b.cameras[2].cam_from_cam0;
    let centre = b.camera_centre_cam0_mm(2).unwrap();
    let turn = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::y_axis(), 0.5f64.to_radians());
    let r = turn.matrix() * old.rotation();
    let moved = centre + nalgebra::Vector3::new(0.0, 2.0, 0.0);
    b.cameras[2].cam_from_cam0 = RigidTransform::from_parts(&r, &(-(r * moved)));
    b.cameras[1].model.intrinsics.fx_px += 1.25;
    let (fa, fb) = (tmp("cmp_a.irp"), tmp("cmp_b.irp"));
    std::fs::write(&fa, a.to_blob().unwrap()).unwrap();
    std::fs::write(&fb, b.to_blob().unwrap()).unwrap();
    let o = host_tools(&["show-params", p(&fb), "--compare", p(&fa)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    let cmp = out
        .split_once("compared with")
        .unwrap_or_else(|| panic!("no comparison in\n{out}"))
        .1;
    let line = |cam: &str| {
        cmp.lines()
            .find(|l| l.trim_start().starts_with(cam))
            .unwrap_or_else(|| panic!("no {cam} line in\n{out}"))
            .to_string()
    };
    assert!(line("camera 1:").contains("focal +1.250 px"), "{out}");
    assert!(
        line("camera 1:").contains("rotation 0.0000 deg, centre 0.000 mm"),
        "{out}"
    );
    assert!(
        line("camera 2:").contains("rotation 0.5000 deg, centre 2.000 mm"),
        "{out}"
    );

    // A rig with another camera count cannot be compared; the message says why.
    let mut two = rig3();
    two.cameras.truncate(2);
    let f2 = tmp("cmp_two.irp");
    std::fs::write(&f2, two.to_blob().unwrap()).unwrap();
    let o = host_tools(&["show-params", p(&fa), "--compare", p(&f2)]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("has 2 cameras, this file 3"),
        "{err}"
    );
}

/// The server side of docs/param-protocol.md, as irtrackd implements it, for one connection:
/// refuses blobs that do not decode or validate, and rigs whose camera count differs.
fn serve_one(listener: TcpListener, expected_cameras: usize) -> thread::JoinHandle<Option<RigParams>> {
    serve_push_once(
        listener,
        move |blob| match RigParams::from_blob(blob).and_then(|r| r.validate().map(|()| r)) {
            Err(e) => (Verdict::from_error(&e), None),
            Ok(r) if r.cameras.len() != expected_cameras => (
                Verdict::Rejected {
                    code: RejectCode::RigMismatch,
                    message: format!(
                        "rig has {expected_cameras} cameras, parameters have {}",
                        r.cameras.len()
                    ),
                },
                None,
            ),
            Ok(r) => (
                Verdict::Accepted {
                    rig_id: r.rig_id.clone(),
                },
                Some(r),
            ),
        },
        None,
    )
}

#[test]
fn push_accepted_from_yaml() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, 2);
    let yaml = tmp("push_ok.yaml");
    write_rig_yaml(&yaml, &rig2()).unwrap();
    let o = host_tools(&["push-params", "--to", &addr, p(&yaml)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(
        out.contains(&format!("accepted by {addr}: rig pair-1 is active")),
        "{out}"
    );
    assert_eq!(server.join().unwrap(), Some(rig2()));
}

#[test]
fn push_rejected_gives_reason_and_failure() {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, 2);
    let blob = tmp("push_three.irp");
    std::fs::write(&blob, rig3().to_blob().unwrap()).unwrap();
    let o = host_tools(&["push-params", "--to", &addr, p(&blob)]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert!(
        err.contains("RIG_MISMATCH") && err.contains("rig has 2 cameras, parameters have 3"),
        "{err}"
    );
    assert_eq!(server.join().unwrap(), None);
}

#[test]
fn push_retries_until_server_starts() {
    // Reserve a free port and release it; the server starts on it only once the client has
    // reported its first failed attempt (timing independent of machine load).
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let addr = format!("127.0.0.1:{port}");
    let blob = tmp("push_late.irp");
    std::fs::write(&blob, rig2().to_blob().unwrap()).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args(["push-params", "--to", &addr, "--retries", "6", p(&blob)])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut first = String::new();
    stderr.read_line(&mut first).unwrap();
    assert!(
        first.contains("Connection refused") && first.contains("retry 1/6 in 0.25 s"),
        "{first}"
    );
    let server = serve_one(TcpListener::bind(("127.0.0.1", port)).unwrap(), 2);
    let mut rest = String::new();
    stderr.read_to_string(&mut rest).unwrap();
    let out = child.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{first}{rest}");
    assert!(
        stdout.contains("accepted by") && stdout.contains("rig pair-1"),
        "{stdout}"
    );
    // Normally no further failure: the bind happens well within the 0.25 s backoff.
    assert!(rest.matches("; retry ").count() <= 3, "{rest}");
    assert_eq!(server.join().unwrap(), Some(rig2()));
}

#[test]
fn push_gives_up_after_retries() {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let blob = tmp("push_nobody.irp");
    std::fs::write(&blob, rig2().to_blob().unwrap()).unwrap();
    let o = host_tools(&[
        "push-params",
        "--to",
        &format!("127.0.0.1:{port}"),
        "--retries",
        "2",
        p(&blob),
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success());
    assert_eq!(err.matches("; retry ").count(), 2, "{err}");
    assert!(
        err.contains("retry 2/2 in 0.50 s") && err.contains("giving up") && err.contains("after 3 attempts"),
        "{err}"
    );
}

#[test]
fn push_dry_run_validates_locally() {
    let blob = tmp("dry.irp");
    std::fs::write(&blob, rig2().to_blob().unwrap()).unwrap();
    let o = host_tools(&["push-params", "--dry-run", p(&blob)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        out.contains("rig pair-1 with 2 cameras") && out.contains("dry run: nothing sent"),
        "{out}"
    );

    let mut bad = rig2();
    bad.cameras[1].cam_from_cam0.r_row_major[4] = 2.0;
    let bad_path = tmp("dry_bad.irp");
    std::fs::write(&bad_path, bad.to_blob().unwrap()).unwrap();
    let o = host_tools(&["push-params", "--dry-run", p(&bad_path)]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("dry_bad.irp") && err.contains("proper rotation"),
        "{err}"
    );

    let mut corrupt = rig2().to_blob().unwrap();
    corrupt[30] ^= 0x40;
    let corrupt_path = tmp("dry_corrupt.irp");
    std::fs::write(&corrupt_path, corrupt).unwrap();
    let o = host_tools(&["push-params", "--dry-run", p(&corrupt_path)]);
    let (_, err) = text(&o);
    assert!(
        !o.status.success() && err.contains("dry_corrupt.irp") && err.contains("CRC-32"),
        "{err}"
    );
}

#[test]
fn client_library_reads_early_rejection() {
    // A server that refuses from the header alone (BUSY, TOO_LARGE) answers before reading the
    // body; it then drains the request so that closing does not reset the connection.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = thread::spawn(move || {
        let (mut s, _) = listener.accept().unwrap();
        let mut hdr = [0u8; 8];
        s.read_exact(&mut hdr).unwrap();
        let v = Verdict::Rejected {
            code: RejectCode::Busy,
            message: "another push in progress".into(),
        };
        s.write_all(v.to_line().as_bytes()).unwrap();
        let mut rest = Vec::new();
        s.read_to_end(&mut rest).unwrap();
        hdr.len() + rest.len()
    });
    let opts = irtrack_host_tools::cmd::push_params::PushOptions {
        retries: 0,
        timeout: Duration::from_secs(5),
        first_backoff: Duration::from_millis(10),
        allow_rollback: false,
    };
    let blob = vec![0x55u8; 200_000];
    let v = irtrack_host_tools::cmd::push_params::push_blob(&addr, &blob, &opts, &mut |_| {}).unwrap();
    assert_eq!(
        v,
        Verdict::Rejected {
            code: RejectCode::Busy,
            message: "another push in progress".into()
        }
    );
    assert_eq!(server.join().unwrap(), 8 + 200_000);
}

/// What OpenCV's stereo_calib sample (or a user's own `cv::FileStorage` code) writes: the two
/// cameras, R and T, the image size, nothing of irtrack's own (no `rig_id`).
const PLAIN_OPENCV_STEREO: &str = "%YAML:1.0
---
image_width: 752
image_height: 480
K1: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 7.1e+02, 0., 3.755e+02, 0., 7.1e+02, 2.395e+02, 0., 0., 1. ]
D1: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -3.1e-01, 1.2e-01, 0., 0., -2.e-02 ]
K2: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 7.05e+02, 0., 3.76e+02, 0., 7.05e+02, 2.4e+02, 0., 0., 1. ]
D2: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -3.e-01, 1.1e-01, 0., 0., -1.e-02 ]
R: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 0., 0., -1., 0., 1., 0., 1., 0., 0. ]
T: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 8.e+02, 0., -8.e+02 ]
";

#[test]
fn plain_opencv_stereo_file_is_accepted_everywhere_with_rig_id_from_its_name() {
    let yaml = tmp("lab_stereo.yml");
    std::fs::write(&yaml, PLAIN_OPENCV_STEREO).unwrap();
    let rig = load_params_any(&yaml).unwrap();
    assert_eq!(rig.rig_id, "lab_stereo");
    assert_eq!(rig.cameras.len(), 2);
    assert_eq!(rig.cameras[1].model.image_size.width_px, 752);
    rig.validate().unwrap();
    assert!((rig.optical_axis_angle_deg(1).unwrap() - 90.0).abs() < 1e-9);

    let note = "has no `rig_id` (a plain OpenCV calibration); using rig id \"lab_stereo\" from the file name";
    // show-params
    let o = host_tools(&["show-params", p(&yaml)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{err}");
    assert!(
        out.contains("rig id:       lab_stereo") && out.contains("validation:   OK"),
        "{out}"
    );
    assert!(err.contains(note), "{err}");
    // convert-params: to a blob and back to YAML; the YAML now carries the rig id.
    let blob = tmp("lab_stereo.irp");
    let o = host_tools(&["convert-params", p(&yaml), p(&blob)]);
    assert!(o.status.success(), "{}", text(&o).1);
    assert!(text(&o).1.contains(note));
    assert_eq!(RigParams::from_blob(&std::fs::read(&blob).unwrap()).unwrap(), rig);
    let back = tmp("lab_stereo_back.yaml");
    let o = host_tools(&["convert-params", p(&blob), p(&back)]);
    assert!(o.status.success(), "{}", text(&o).1);
    let (again, from_name) = irtrack_host_tools::opencv_yaml::read_rig_yaml_noting(&back).unwrap();
    assert!(!from_name);
    assert_eq!(again, rig);
    // push-params: sent as the blob of the named rig.
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    let server = serve_one(listener, 2);
    let o = host_tools(&["push-params", "--to", &addr, p(&yaml)]);
    let (out, err) = text(&o);
    assert!(o.status.success(), "{out}\n{err}");
    assert!(out.contains("rig lab_stereo is active"), "{out}");
    assert!(err.contains(note), "{err}");
    assert_eq!(server.join().unwrap(), Some(rig));
}
