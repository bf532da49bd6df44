//! The simulated source's robot-cell mode (`[source.sim.cell]`): every frame asks the cell feed
//! where the robot really put the LED and renders it there through the simulator-only
//! base-to-camera transform; without an answer the LED is dark. With `tool` the tool on the
//! flange is rendered at the pose the feed gives (`TOOL?`).

use std::net::UdpSocket;

use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimCellConfig, SimSource, SimSourceConfig};
use irtrack_robot::cell::{FEED_REQUEST, FEED_TOOL_REQUEST, encode_feed_answer, encode_tool_answer};
use nalgebra::{Point3, Quaternion, UnitQuaternion, Vector3};

fn cell_cfg(robot: String) -> SimSourceConfig {
    SimSourceConfig {
        paced: false,
        cell: Some(SimCellConfig {
            robot,
            cam0_from_base_rotation_deg: [10.0, -170.0, 25.0],
            cam0_from_base_translation_mm: [480.0, 150.0, 560.0],
            timeout_ms: 200,
        }),
        ..SimSourceConfig::default()
    }
}

#[test]
fn the_led_is_rendered_where_the_feed_says_and_dark_without_it() {
    let feed = UdpSocket::bind("127.0.0.1:0").unwrap();
    let addr = feed.local_addr().unwrap();
    let led_base = [500.0, -20.0, 210.0];
    let answers = std::thread::spawn(move || {
        let mut buf = [0u8; 16];
        for _ in 0..3 {
            let (n, from) = feed.recv_from(&mut buf).unwrap();
            assert_eq!(&buf[..n], FEED_REQUEST);
            feed.send_to(encode_feed_answer(Some(led_base)).as_bytes(), from)
                .unwrap();
        }
        // Then silence: the socket closes with the thread.
    });
    let mut cfg = cell_cfg(addr.to_string());
    // Put the LED where the cameras' axes cross (0, 0, 600) in camera 0's frame.
    if let Some(c) = cfg.cell.as_mut() {
        c.cam0_from_base_translation_mm = [0.0; 3];
        let r = c.cam0_from_base() * Point3::from(Vector3::from(led_base));
        c.cam0_from_base_translation_mm = [-r.x, -r.y, 600.0 - r.z];
    }
    cfg.validate().unwrap();
    let mut src = SimSource::new(&cfg).unwrap();
    let mut set = src.allocate_set();
    let want = cfg.cell.as_ref().unwrap().cam0_from_base() * Point3::from(Vector3::from(led_base));
    for _ in 0..3 {
        src.next_set(&mut set).unwrap();
        let truth = src.scenario().truth(set.index);
        let p = truth.markers()[0];
        assert!((p.p_cam0_mm - want.coords).norm() < 1e-9, "{:?}", p.p_cam0_mm);
        assert_eq!(p.visible_mask, 0b11, "the LED is in both cameras' view");
    }
    answers.join().unwrap();
    // No answer: the LED is put where it carries no light.
    src.next_set(&mut set).unwrap();
    let p = src.scenario().truth(set.index).markers()[0].p_cam0_mm;
    assert!(p.norm() > 1e8, "{p:?}");
}

#[test]
fn cell_config_errors_name_the_key() {
    let mut cfg = cell_cfg("not an address".into());
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("source.sim.cell.robot"), "{e}");
    cfg = cell_cfg("127.0.0.1:7750".into());
    cfg.tool = Some("probe4".into());
    cfg.validate().unwrap();
    cfg.extra_tools = vec!["tri3".into()];
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("excludes source.sim.extra_tools"), "{e}");
    cfg = cell_cfg("127.0.0.1:7750".into());
    if let Some(c) = cfg.cell.as_mut() {
        c.timeout_ms = 0;
    }
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("timeout_ms"), "{e}");
    // The section parses from TOML with the documented keys.
    let toml_text = "robot = \"127.0.0.1:7750\"\ncam0_from_base_rotation_deg = [20.0, -150.0, 35.0]\n\
                     cam0_from_base_translation_mm = [496.6, 173.1, 539.7]\n";
    let c: SimCellConfig = toml::from_str(toml_text).unwrap();
    assert_eq!(c.timeout_ms, 20);
}

#[test]
fn the_tool_is_rendered_at_the_pose_the_feed_says() {
    let feed = UdpSocket::bind("127.0.0.1:0").unwrap();
    let addr = feed.local_addr().unwrap();
    let tool_base = ([500.0, -20.0, 210.0], [0.5, 0.5, -0.5, 0.5]);
    let answers = std::thread::spawn(move || {
        let mut buf = [0u8; 16];
        for _ in 0..3 {
            let (n, from) = feed.recv_from(&mut buf).unwrap();
            assert_eq!(&buf[..n], FEED_TOOL_REQUEST);
            feed.send_to(encode_tool_answer(Some(tool_base)).as_bytes(), from)
                .unwrap();
        }
    });
    let mut cfg = cell_cfg(addr.to_string());
    cfg.tool = Some("probe4".into());
    if let Some(c) = cfg.cell.as_mut() {
        c.cam0_from_base_translation_mm = [0.0; 3];
        let r = c.cam0_from_base() * Point3::from(Vector3::from(tool_base.0));
        c.cam0_from_base_translation_mm = [-r.x, -r.y, 600.0 - r.z];
    }
    cfg.validate().unwrap();
    let mut src = SimSource::new(&cfg).unwrap();
    let mut set = src.allocate_set();
    let cam0_from_base = cfg.cell.as_ref().unwrap().cam0_from_base();
    let q = tool_base.1;
    let q_cam0 =
        cam0_from_base.rotation * UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
    let origin = cam0_from_base * Point3::from(Vector3::from(tool_base.0));
    let leds = cfg.tool_definition().unwrap().leds_mm;
    for _ in 0..3 {
        src.next_set(&mut set).unwrap();
        let truth = src.scenario().truth(set.index);
        assert_eq!(truth.markers().len(), leds.len());
        for (m, led) in truth.markers().iter().zip(&leds) {
            let want = origin.coords + q_cam0 * Vector3::from(*led);
            assert!(
                (m.p_cam0_mm - want).norm() < 1e-9,
                "{:?} vs {want:?}",
                m.p_cam0_mm
            );
        }
        let got = truth.tool_quaternion_wxyz();
        let got = UnitQuaternion::from_quaternion(Quaternion::new(got[0], got[1], got[2], got[3]));
        assert!(got.angle_to(&q_cam0) < 1e-9);
    }
    answers.join().unwrap();
    // No answer: the tool is put where it carries no light.
    src.next_set(&mut set).unwrap();
    let p = src.scenario().truth(set.index).markers()[0].p_cam0_mm;
    assert!(p.norm() > 1e8, "{p:?}");
}
