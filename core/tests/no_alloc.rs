//! Proves the per-frame path allocates nothing: a counting global allocator watches
//! `Tracker::process_u8/u16` (detection, ROI tracking, full-frame fallback, loss,
//! ambiguity, 16-bit) after a warm-up frame.

use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::image::GrayImage;
use irtrack_core::params::{CameraParams, RigParams};
use irtrack_core::pipeline::{TrackStatus, Tracker, TrackerConfig};
use nalgebra::{Matrix3, Vector3};

#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

use irtrack_testkit::allocations;

const W: u32 = 320;
const H: u32 = 240;

fn rig() -> RigParams {
    let model = CameraModel {
        intrinsics: Intrinsics {
            fx_px: 400.0,
            fy_px: 400.0,
            cx_px: 160.0,
            cy_px: 120.0,
        },
        distortion: Distortion {
            k1: -0.1,
            k2: 0.02,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
        },
        image_size: ImageSize {
            width_px: W,
            height_px: H,
        },
    };
    let t1 = RigidTransform::from_parts(&Matrix3::identity(), &Vector3::new(-120.0, 0.0, 0.0));
    RigParams {
        rig_id: "alloc".into(),
        created_unix_s: 0,
        cameras: vec![
            CameraParams {
                model,
                cam_from_cam0: RigidTransform::IDENTITY,
            },
            CameraParams {
                model,
                cam_from_cam0: t1,
            },
        ],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Gaussian spots on a dark, slightly noisy background (values 0..=max).
fn render(spots: &[(f64, f64)], peak: f64, bg: f64, max: f64, seed: u32) -> Vec<u32> {
    let mut s = seed.wrapping_mul(2_654_435_761).max(1);
    (0..W * H)
        .map(|i| {
            let (x, y) = ((i % W) as f64, (i / W) as f64);
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            let noise = (s % 5) as f64 - 2.0;
            let v: f64 = spots
                .iter()
                .map(|(sx, sy)| peak * (-((x - sx).powi(2) + (y - sy).powi(2)) / (2.0 * 1.5 * 1.5)).exp())
                .sum();
            (bg + v + noise).clamp(0.0, max) as u32
        })
        .collect()
}

fn project(r: &RigParams, cam: usize, p: &Vector3<f64>) -> (f64, f64) {
    let c = &r.cameras[cam];
    let px = c.model.project(&c.cam_from_cam0.apply(p)).unwrap();
    (px.x, px.y)
}

#[test]
fn steady_state_processing_allocates_nothing() {
    let r = rig();
    let points = [
        Vector3::new(0.0, 0.0, 600.0),
        Vector3::new(2.0, -1.0, 602.0),   // small step: ROI
        Vector3::new(-80.0, 40.0, 560.0), // jump: full-frame fallback
        Vector3::new(-78.0, 41.0, 561.0), // ROI again
    ];
    // Pre-render every frame set (rendering allocates; processing must not).
    let mut sets8: Vec<[Vec<u8>; 2]> = Vec::new();
    for (k, p) in points.iter().enumerate() {
        let f = |c: usize| render(&[project(&r, c, p)], 190.0, 10.0, 255.0, k as u32 * 2 + c as u32);
        sets8.push([0, 1].map(|c| f(c).into_iter().map(|v| v as u8).collect()));
    }
    // Loss (empty frames) and an ambiguous pair (second spot on camera 0's epipolar line).
    sets8.push([0, 1].map(|c| {
        render(&[], 0.0, 10.0, 255.0, 90 + c)
            .into_iter()
            .map(|v| v as u8)
            .collect()
    }));
    let (x0, y0) = project(&r, 0, &points[0]);
    let amb0 = render(&[(x0, y0), (x0 - 40.0, y0)], 190.0, 10.0, 255.0, 95);
    let amb1 = render(&[project(&r, 1, &points[0])], 190.0, 10.0, 255.0, 96);
    sets8.push([amb0, amb1].map(|v| v.into_iter().map(|v| v as u8).collect()));
    let sets16: Vec<Vec<u16>> = (0..2)
        .map(|c| {
            render(&[project(&r, c, &points[0])], 3000.0, 40.0, 4095.0, 97 + c as u32)
                .into_iter()
                .map(|v| v as u16)
                .collect()
        })
        .collect();

    let mut t8 = Tracker::new(&r, TrackerConfig::default()).unwrap();
    let mut t16 = Tracker::new(
        &r,
        TrackerConfig {
            threshold_dn: 160,
            ..TrackerConfig::default()
        },
    )
    .unwrap();
    let views8: Vec<[GrayImage<'_, u8>; 2]> = sets8
        .iter()
        .map(|s| [0, 1].map(|c| GrayImage::new(&s[c], W, H, W).unwrap()))
        .collect();
    let views16: [GrayImage<'_, u16>; 2] = [0, 1].map(|c| GrayImage::new(&sets16[c], W, H, W).unwrap());

    // Warm-up: one pass over every case.
    for v in &views8 {
        t8.process_u8(v).unwrap();
    }
    t16.process_u16(&views16).unwrap();

    let before = allocations();
    let mut statuses = [0u32; 4];
    for _ in 0..20 {
        for v in &views8 {
            let m = t8.process_u8(v).unwrap();
            statuses[match m.status {
                TrackStatus::Tracked if m.used_roi => 0,
                TrackStatus::Tracked => 1,
                TrackStatus::NoConsistentPair => 2,
                _ => 3,
            }] += 1;
        }
        assert_eq!(t16.process_u16(&views16).unwrap().status, TrackStatus::Tracked);
        let _ = t8.detect_u8(0, &views8[0][0]).unwrap();
        let _ = t8.detect_u8(1, &views8[0][1]).unwrap();
        let _ = t8.solve();
    }
    let after = allocations();
    // Every path was exercised: ROI-tracked, full-frame tracked, ambiguous, lost.
    assert!(statuses.iter().all(|&n| n > 0), "statuses {statuses:?}");
    assert_eq!(
        after - before,
        0,
        "allocations in {} frame sets",
        20 * (views8.len() + 2)
    );
}

/// Several tools and a loose LED through `MultiTracker` (identification per tool, blob claims,
/// loose-LED association, the predictor over a gap): no allocation per frame set.
#[test]
fn multi_tool_tracking_allocates_nothing() {
    use irtrack_core::blob::Blob;
    use irtrack_core::params::ToolDefinition;
    use irtrack_core::pose6d::{MultiTracker, PoseConfig, PoseStatus};
    use nalgebra::UnitQuaternion;

    let r = rig();
    let tool = |name: &str, leds: &[[f64; 3]]| ToolDefinition {
        name: name.into(),
        leds_mm: leds.to_vec(),
        tip_mm: None,
    };
    let tools = [
        tool(
            "probe4",
            &[
                [0.0, 0.0, 0.0],
                [99.0, 0.0, 0.0],
                [3.0, 85.0, 0.0],
                [62.0, 11.0, 32.0],
            ],
        ),
        tool("tri3", &[[0.0, 0.0, 0.0], [110.0, 0.0, 0.0], [81.8, 60.0, 0.0]]),
    ];
    // Pre-compute every frame set's blobs (building them allocates; processing must not).
    let sets: Vec<[Vec<Blob>; 2]> = (0..40)
        .map(|k| {
            let f = k as f64;
            let mut pts = Vec::new();
            let poses = [
                (
                    UnitQuaternion::from_euler_angles(0.3, -0.2 + 0.01 * f, 0.1),
                    Vector3::new(-150.0 + f, -60.0, 900.0),
                ),
                (
                    UnitQuaternion::from_euler_angles(-0.4, 0.2, 0.7 + 0.01 * f),
                    Vector3::new(40.0 - f, 40.0, 950.0),
                ),
            ];
            for (t, (q, p)) in tools.iter().zip(&poses) {
                // The first tool disappears for frames 20..24 (the predictor coasts).
                if t.name == "probe4" && (20..24).contains(&k) {
                    continue;
                }
                for l in &t.leds_mm {
                    pts.push(q * Vector3::from(*l) + p);
                }
            }
            pts.push(Vector3::new(-10.0 + f, -100.0, 1000.0));
            [0, 1].map(|c| {
                pts.iter()
                    .map(|p| {
                        let (x, y) = project(&r, c, p);
                        Blob {
                            x_px: x,
                            y_px: y,
                            area_px: 9,
                            roundness: 1.0,
                            ..Blob::default()
                        }
                    })
                    .collect()
            })
        })
        .collect();
    let mut tracker = MultiTracker::new(&r, &tools, PoseConfig::default()).unwrap();
    fn lists(s: &[Vec<Blob>; 2]) -> [&[Blob]; 2] {
        [s[0].as_slice(), s[1].as_slice()]
    }
    tracker.process(&lists(&sets[0])).unwrap();
    let before = allocations();
    let mut tracked = [0; 2];
    let mut loose = 0;
    for s in &sets[1..] {
        tracker.process(&lists(s)).unwrap();
        for (i, n) in tracked.iter_mut().enumerate() {
            if tracker.pose(i).unwrap().status == PoseStatus::Tracked {
                *n += 1;
            }
        }
        loose += tracker.loose_leds().len();
    }
    let n = allocations() - before;
    assert_eq!(n, 0, "{n} allocations in 39 multi-tool frame sets");
    assert!(tracked[0] >= 30 && tracked[1] >= 35, "tracked {tracked:?} of 39");
    assert!(loose >= 35, "loose LED reported {loose} times");
}
