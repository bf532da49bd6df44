//! One camera limit for the whole system: a parameter set over `params::MAX_CAMERAS` is refused
//! where sets are accepted (`RigParams::validate`, which the service runs on every push), with
//! an error naming the limit; a set at the limit is accepted there and by every tracker.

use irtrack_core::Error;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::params::{CameraParams, MAX_CAMERAS, RigParams};
use irtrack_core::pipeline::{self, Tracker, TrackerConfig};
use irtrack_core::pose6d::{self, PointMatcher, PoseConfig};

/// `n` parallel cameras 100 mm apart along x (camera 0 at the origin).
fn rig_with(n: usize) -> RigParams {
    let identity = RigidTransform::IDENTITY.r_row_major;
    let cameras = (0..n)
        .map(|k| CameraParams {
            model: CameraModel {
                intrinsics: Intrinsics {
                    fx_px: 600.0,
                    fy_px: 600.0,
                    cx_px: 320.0,
                    cy_px: 240.0,
                },
                distortion: Distortion {
                    k1: 0.0,
                    k2: 0.0,
                    p1: 0.0,
                    p2: 0.0,
                    k3: 0.0,
                },
                image_size: ImageSize {
                    width_px: 640,
                    height_px: 480,
                },
            },
            // x_k = x_0 + t: camera k's centre is at (100 k, 0, 0) mm in camera 0's frame.
            cam_from_cam0: RigidTransform {
                r_row_major: identity,
                t_mm: [-100.0 * k as f64, 0.0, 0.0],
            },
        })
        .collect();
    RigParams {
        rig_id: format!("line-{n}"),
        created_unix_s: 1,
        cameras,
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

#[test]
fn the_limit_is_one_constant() {
    assert_eq!(pipeline::MAX_CAMERAS, MAX_CAMERAS);
    assert_eq!(pose6d::MAX_CAMERAS, MAX_CAMERAS);
}

#[test]
fn a_set_at_the_limit_is_accepted_everywhere() {
    let rig = rig_with(MAX_CAMERAS);
    rig.validate().unwrap();
    // Through the wire format too, as a pushed set arrives.
    let decoded = RigParams::from_blob(&rig.to_blob().unwrap()).unwrap();
    decoded.validate().unwrap();
    let tracker = Tracker::new(&decoded, TrackerConfig::default()).unwrap();
    assert_eq!(tracker.camera_count(), MAX_CAMERAS);
    PointMatcher::new(&decoded, &PoseConfig::default()).unwrap();
}

#[test]
fn a_set_over_the_limit_is_refused_with_a_clear_error() {
    let n = MAX_CAMERAS + 1;
    let rig = rig_with(n);
    // Decoding does not judge contents; validation, run on every accepted push, does.
    let decoded = RigParams::from_blob(&rig.to_blob().unwrap()).unwrap();
    match decoded.validate() {
        Err(Error::InvalidParams { reason }) => {
            assert_eq!(reason, format!("rig needs 2..={MAX_CAMERAS} cameras, has {n}"),)
        }
        other => panic!("a {n}-camera set must be refused, got {other:?}"),
    }
    // The trackers refuse it as well (they never see it in the service, but must not panic).
    assert!(matches!(
        Tracker::new(&decoded, TrackerConfig::default()),
        Err(Error::InvalidParams { .. })
    ));
}
