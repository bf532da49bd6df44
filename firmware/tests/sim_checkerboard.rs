//! The simulated source's checkerboard mode (`[source.sim.checkerboard]`): a board held in one
//! pose after another, for `host-tools capture` and `host-tools calibrate` without hardware.
//! Its frames are the simulator's checkerboard renderer's, and two sources that render
//! different shares of one rig (two camera boards) show the same pose in the same frame.

use irtrack_firmware::source::sim::{SimCheckerboardConfig, SimRig, SimSource, SimSourceConfig};
use irtrack_firmware::source::{FrameSource, Pixels};
use irtrack_sim::checkerboard::{BoardSpec, CameraRenderer, RenderSettings, corner_pixels};

const HOLD: u64 = 3;

/// Four cameras on a 90° arc at 600 mm, `cameras` of them rendered, 3 shared views and one
/// single-camera view per camera, each held `HOLD` frames.
fn cfg(cameras: Option<Vec<usize>>, bit_depth: u8) -> SimSourceConfig {
    SimSourceConfig {
        rig: SimRig::Ring,
        ring_cameras: 4,
        ring_arc_deg: 90.0,
        distance_mm: 600.0,
        paced: false,
        bit_depth,
        cameras,
        checkerboard: Some(Box::new(SimCheckerboardConfig {
            views: 3,
            single_views: 1,
            hold_frames: HOLD,
            ..Default::default()
        })),
        ..SimSourceConfig::default()
    }
}

fn u8_pixels(p: &Pixels) -> &[u8] {
    match p {
        Pixels::U8(v) => v,
        Pixels::U16(_) => panic!("expected 8-bit pixels"),
    }
}

#[test]
fn board_frames_are_the_renderers_and_every_board_shows_the_same_pose() {
    let whole = cfg(None, 8);
    whole.validate().unwrap();
    let mut all = SimSource::new(&whole).unwrap();
    let mut b0 = SimSource::new(&cfg(Some(vec![0, 1]), 8)).unwrap();
    let mut b1 = SimSource::new(&cfg(Some(vec![2, 3]), 8)).unwrap();
    let rig = all.scenario().rig().clone();
    let poses = whole.checkerboard_poses(&rig).unwrap();
    assert_eq!(poses.len(), 3 + 4, "3 shared views, one per camera");
    let board = BoardSpec::new(9, 6, 25.0).unwrap();
    let settings = RenderSettings {
        seed: 5,
        ..Default::default()
    };
    let (mut sa, mut s0, mut s1) = (all.allocate_set(), b0.allocate_set(), b1.allocate_set());
    let n = 640 * 480;
    let mut expected = vec![0u8; n];
    let views = poses.len() as u64;
    let mut previous: Option<Vec<u8>> = None;
    for index in 0..(views + 1) * HOLD {
        all.next_set(&mut sa).unwrap();
        b0.next_set(&mut s0).unwrap();
        b1.next_set(&mut s1).unwrap();
        assert_eq!((sa.index, s0.index, s1.index), (index, index, index));
        // The boards' shares are the whole rig's frames, camera for camera.
        for (c, frame) in sa.frames.iter().enumerate() {
            let share = if c < 2 { &s0.frames[c] } else { &s1.frames[c - 2] };
            assert!(
                u8_pixels(&frame.pixels) == u8_pixels(&share.pixels),
                "frame {index}, camera {c}: the board's share differs from the whole rig"
            );
        }
        let view = ((index / HOLD) % views) as usize;
        // Held: the same image for HOLD frames, then the next pose.
        let cam0 = u8_pixels(&sa.frames[0].pixels).to_vec();
        if let Some(p) = &previous {
            assert_eq!(
                *p == cam0,
                index % HOLD != 0,
                "frame {index}: a pose is held {HOLD} frames"
            );
        }
        previous = Some(cam0);
        if index % HOLD != 0 {
            continue;
        }
        for (c, frame) in sa.frames.iter().enumerate() {
            let cam = &rig.cameras[c];
            let pose = cam.cam_from_cam0.compose(&poses[view]);
            CameraRenderer::new(cam.model)
                .render(
                    &pose,
                    &board,
                    &settings,
                    ((c as u64) << 32) | view as u64,
                    &mut expected,
                )
                .unwrap();
            assert!(
                u8_pixels(&frame.pixels) == expected.as_slice(),
                "frame {index} camera {c} is not the renderer's view {view}"
            );
            // Shared views: the whole board in every camera's image.
            if view < 3 {
                let corners = corner_pixels(&cam.model, &pose, &board).unwrap();
                assert!(
                    corners.iter().all(|p| cam.model.contains_px(p)),
                    "view {view}: a corner outside camera {c}"
                );
            }
        }
    }
}

#[test]
fn ten_bit_board_frames_are_the_eight_bit_ones_shifted() {
    let mut s8 = SimSource::new(&cfg(Some(vec![1]), 8)).unwrap();
    let mut s10 = SimSource::new(&cfg(Some(vec![1]), 10)).unwrap();
    let (mut a, mut b) = (s8.allocate_set(), s10.allocate_set());
    s8.next_set(&mut a).unwrap();
    s10.next_set(&mut b).unwrap();
    let Pixels::U16(ten) = &b.frames[0].pixels else {
        panic!("expected 10-bit pixels")
    };
    let eight = u8_pixels(&a.frames[0].pixels);
    assert!(ten.iter().zip(eight).all(|(t, e)| *t == u16::from(*e) << 2));
    // Black squares and white paper are both there.
    assert!(eight.iter().any(|v| *v < 60) && eight.iter().any(|v| *v > 190));
}

#[test]
fn bad_checkerboard_settings_are_named() {
    // A full ring: no pose shows one board to cameras facing each other.
    let mut c = cfg(None, 8);
    c.ring_arc_deg = 360.0;
    c.validate().unwrap();
    let e = SimSource::new(&c)
        .err()
        .expect("a board all four ring cameras see")
        .to_string();
    assert!(
        e.contains("source.sim.checkerboard") && e.contains("seen_by"),
        "{e}"
    );

    let mut c = cfg(None, 8);
    c.wand_mm = Some(vec![0.0, 120.0, 300.0]);
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("excludes source.sim.wand_mm"), "{e}");

    let mut c = cfg(None, 8);
    c.checkerboard.as_mut().unwrap().seen_by = Some(vec![0, 4]);
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("seen_by") && e.contains("4 cameras"), "{e}");

    let mut c = cfg(None, 8);
    c.checkerboard.as_mut().unwrap().hold_frames = 0;
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("hold_frames"), "{e}");

    let mut c = cfg(None, 8);
    c.ring_arc_deg = 400.0;
    let e = c.validate().unwrap_err().to_string();
    assert!(e.contains("ring_arc_deg"), "{e}");

    // A TOML key the table does not know is refused by name.
    let e = toml::from_str::<SimSourceConfig>("[checkerboard]\ncolumns = 9\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("columns"), "{e}");
}
