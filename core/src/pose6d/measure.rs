//! Measuring a new tool's layout with the tracker itself, from triangulated points of a static
//! tool ([`measure_tool_layout`]).

use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use super::config::{MAX_TOOL_LEDS, PoseConfig};
use super::identify::ToolModel;
use super::matching::TriangulatedPoint;
use crate::camera::RigidTransform;
use crate::params::ToolDefinition;
use crate::{Error, Result};

/// Where the measured tool frame has its origin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum LayoutOrigin {
    /// Centroid of the LEDs.
    Centroid,
    /// LED 0 (the LED farthest from the centroid).
    FirstLed,
}

/// Result of [`measure_tool_layout`].
#[derive(Debug, Clone, PartialEq)]
pub struct MeasuredLayout {
    /// The layout in the tool frame. LED 0 is the LED farthest from the centroid, the rest
    /// follow by decreasing distance. Axes: x along the largest principal direction (LED 0
    /// on its positive side), z along the smallest (normal of a planar layout), y = z × x.
    pub tool: ToolDefinition,
    /// Where the tool frame was during the measurement (camera-0 from tool).
    pub cam0_from_tool: RigidTransform,
    /// Per LED: frames in which it was seen, and RMS scatter (mm) around its mean.
    pub observations: Vec<usize>,
    /// Per LED: RMS scatter (mm) around its mean position.
    pub spread_rms_mm: Vec<f64>,
    /// Largest per-LED RMS scatter (mm).
    pub max_spread_rms_mm: f64,
    /// Identification margin of the measured layout (mm) under the config used.
    pub margin_mm: f64,
}

/// Builds a tool definition from triangulated points of a **static** tool seen in several
/// frames (copies of [`super::PointMatcher::points`] or [`super::PoseTracker::points`] per frame).
///
/// Within a frame, candidates are taken in order of increasing ray gap and a candidate
/// sharing a blob with one already taken is dropped: a ghost (LED *i* in one camera paired
/// with LED *j* in the other) shares blobs with both true points and has the larger gap.
/// Points of all frames are then clustered (radius `cluster_radius_mm`); clusters seen in at
/// least 80 % of the frames are LEDs. Exactly `expected_leds` such clusters must exist —
/// a persistent reflection or ghost gives a clear error instead of a wrong tool. The result
/// is validated like any tool ([`ToolModel::new`]) so an ambiguous layout is refused here.
pub fn measure_tool_layout(
    name: &str,
    frames: &[&[TriangulatedPoint]],
    expected_leds: usize,
    origin: LayoutOrigin,
    cluster_radius_mm: f64,
    config: &PoseConfig,
) -> Result<MeasuredLayout> {
    let bad = |reason: String| Err(Error::InvalidParams { reason });
    if frames.len() < 2 {
        return bad(format!(
            "measuring tool {name:?}: need ≥ 2 frames, got {}",
            frames.len()
        ));
    }
    if !(3..=MAX_TOOL_LEDS).contains(&expected_leds) {
        return bad(format!(
            "measuring tool {name:?}: expected_leds {expected_leds} outside 3..={MAX_TOOL_LEDS}"
        ));
    }
    if !(cluster_radius_mm > 0.0 && cluster_radius_mm.is_finite()) {
        return bad(format!(
            "measuring tool {name:?}: cluster radius {cluster_radius_mm} mm must be positive"
        ));
    }
    // (sum, count, sum of squared norms) per cluster; the running mean is the centre.
    struct Cluster {
        sum: Vector3<f64>,
        sum_sq: f64,
        count: usize,
        last_frame: usize,
    }
    let mut clusters: Vec<Cluster> = Vec::new();
    let mut taken: Vec<TriangulatedPoint> = Vec::new();
    for (fi, frame) in frames.iter().enumerate() {
        let mut by_gap: Vec<&TriangulatedPoint> = frame.iter().collect();
        by_gap.sort_by(|a, b| a.gap_mm.total_cmp(&b.gap_mm));
        taken.clear();
        for p in by_gap {
            if !taken.iter().any(|q| q.shares_blob(p)) {
                taken.push(*p);
            }
        }
        for p in &taken {
            if !p.point_mm.iter().all(|v| v.is_finite()) {
                return bad(format!(
                    "measuring tool {name:?}: frame {fi} has a non-finite point"
                ));
            }
            let v = p.point_mm;
            let near = clusters
                .iter_mut()
                .map(|c| {
                    let d = (c.sum / c.count as f64 - v).norm();
                    (d, c)
                })
                .filter(|(d, _)| *d <= cluster_radius_mm)
                .min_by(|a, b| a.0.total_cmp(&b.0));
            match near {
                Some((_, c)) if c.last_frame == fi => {
                    return bad(format!(
                        "measuring tool {name:?}: frame {fi} has two points within {cluster_radius_mm} mm of \
                         each other; LEDs too close or the cluster radius too large"
                    ));
                }
                Some((_, c)) => {
                    c.sum += v;
                    c.sum_sq += v.norm_squared();
                    c.count += 1;
                    c.last_frame = fi;
                }
                None => clusters.push(Cluster {
                    sum: v,
                    sum_sq: v.norm_squared(),
                    count: 1,
                    last_frame: fi,
                }),
            }
        }
    }
    let needed = frames.len() * 4 / 5;
    clusters.retain(|c| c.count >= needed.max(1));
    if clusters.len() != expected_leds {
        return bad(format!(
            "measuring tool {name:?}: {} points were seen in ≥ 80 % of {} frames, expected {expected_leds} LEDs \
             (remove reflections, check that every LED is visible in two cameras)",
            clusters.len(),
            frames.len()
        ));
    }
    let means: Vec<Vector3<f64>> = clusters.iter().map(|c| c.sum / c.count as f64).collect();
    let centroid = means.iter().sum::<Vector3<f64>>() / expected_leds as f64;
    let mut order: Vec<usize> = (0..expected_leds).collect();
    order.sort_by(|&a, &b| {
        (means[b] - centroid)
            .norm()
            .total_cmp(&(means[a] - centroid).norm())
    });
    let mut cov = Matrix3::zeros();
    for m in &means {
        let d = m - centroid;
        cov += d * d.transpose();
    }
    let eig = cov.symmetric_eigen();
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&i, &j| eig.eigenvalues[j].total_cmp(&eig.eigenvalues[i]));
    let mut x: Vector3<f64> = eig.eigenvectors.column(axes[0]).into();
    let mut y: Vector3<f64> = eig.eigenvectors.column(axes[1]).into();
    if (means[order[0]] - centroid).dot(&x) < 0.0 {
        x = -x;
    }
    // y sign: the LED farthest from the x axis lies on the positive side.
    let far_y = order
        .iter()
        .map(|&i| (means[i] - centroid).dot(&y))
        .max_by(|a, b| libm::fabs(*a).total_cmp(&libm::fabs(*b)))
        .unwrap_or(1.0);
    if far_y < 0.0 {
        y = -y;
    }
    let z = x.cross(&y);
    // Rows are the tool axes in camera-0 coordinates: p_tool = R_tc (p_cam0 − origin).
    let r_tool_cam0 = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let origin_cam0 = match origin {
        LayoutOrigin::Centroid => centroid,
        LayoutOrigin::FirstLed => means[order[0]],
    };
    let leds_mm: Vec<[f64; 3]> = order
        .iter()
        .map(|&i| (r_tool_cam0 * (means[i] - origin_cam0)).into())
        .collect();
    let observations: Vec<usize> = order.iter().map(|&i| clusters[i].count).collect();
    let spread_rms_mm: Vec<f64> = order
        .iter()
        .map(|&i| {
            let c = &clusters[i];
            let var = c.sum_sq / c.count as f64 - means[i].norm_squared();
            libm::sqrt(var.max(0.0))
        })
        .collect();
    let tool = ToolDefinition {
        name: name.into(),
        leds_mm,
        tip_mm: None,
    };
    let model = ToolModel::new(&tool, config)?;
    let r_cam0_tool = r_tool_cam0.transpose();
    Ok(MeasuredLayout {
        tool,
        cam0_from_tool: RigidTransform::from_parts(&r_cam0_tool, &origin_cam0),
        max_spread_rms_mm: spread_rms_mm.iter().copied().fold(0.0, f64::max),
        observations,
        spread_rms_mm,
        margin_mm: model.margin_mm(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose6d::config::{MAX_CAMERAS, NO_BLOB};

    /// A 4-LED layout (identification margin about 25 mm) and where it sits in camera 0
    /// (rotated 90° about z, 1 m away).
    const LAYOUT: [[f64; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [140.0, 0.0, 0.0],
        [0.0, 90.0, 0.0],
        [-50.0, -10.0, 40.0],
    ];

    fn placed() -> Vec<Vector3<f64>> {
        let r = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let t = Vector3::new(20.0, -10.0, 1000.0);
        LAYOUT.iter().map(|p| r * Vector3::from(*p) + t).collect()
    }

    /// `n` frames; LED points jittered by ±`jitter_mm` along x, alternating per frame.
    fn frames(points: &[Vector3<f64>], n: usize, jitter_mm: f64) -> Vec<Vec<TriangulatedPoint>> {
        (0..n)
            .map(|f| {
                let dx = if f % 2 == 0 { jitter_mm } else { -jitter_mm };
                points
                    .iter()
                    .enumerate()
                    .map(|(i, p)| {
                        let mut blobs = [NO_BLOB; MAX_CAMERAS];
                        blobs[0] = i as u8;
                        blobs[1] = i as u8;
                        TriangulatedPoint {
                            point_mm: p + Vector3::new(dx, 0.0, 0.0),
                            gap_mm: 0.1,
                            blobs,
                            cameras: 2,
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
        (Vector3::from(*a) - Vector3::from(*b)).norm()
    }

    #[test]
    fn measured_layout_reproduces_the_true_distances() {
        let f = frames(&placed(), 10, 0.05);
        let refs: Vec<&[TriangulatedPoint]> = f.iter().map(|v| v.as_slice()).collect();
        let m = measure_tool_layout(
            "probe",
            &refs,
            4,
            LayoutOrigin::Centroid,
            5.0,
            &PoseConfig::default(),
        )
        .unwrap();
        let leds = &m.tool.leds_mm;
        assert_eq!(leds.len(), 4);
        // Every true distance appears among the measured ones (LEDs are reordered).
        for (i, a) in LAYOUT.iter().enumerate() {
            for b in &LAYOUT[i + 1..] {
                let want = dist(a, b);
                let found =
                    (0..4).any(|x| (0..4).any(|y| x != y && (dist(&leds[x], &leds[y]) - want).abs() < 1e-6));
                assert!(found, "distance {want} missing from {leds:?}");
            }
        }
        // Centroid origin; LEDs by decreasing distance from it, LED 0 on the +x side.
        let c: Vector3<f64> = leds.iter().map(|p| Vector3::from(*p)).sum::<Vector3<f64>>() / 4.0;
        assert!(c.norm() < 1e-6, "{c}");
        let r: Vec<f64> = leds.iter().map(|p| Vector3::from(*p).norm()).collect();
        assert!(r.windows(2).all(|w| w[0] >= w[1]), "{r:?}");
        assert!(leds[0][0] > 0.0, "{leds:?}");
        assert!((m.margin_mm - 25.19).abs() < 0.01, "{}", m.margin_mm);
        // The ±0.05 mm jitter is exactly the per-LED RMS scatter.
        assert_eq!(m.observations, alloc::vec![10; 4]);
        for s in &m.spread_rms_mm {
            assert!((s - 0.05).abs() < 1e-6, "{:?}", m.spread_rms_mm);
        }
        // The tool frame maps back onto where the LEDs were seen.
        let seen = m.cam0_from_tool.apply(&Vector3::from(leds[0]));
        assert!(placed().iter().any(|p| (p - seen).norm() < 1e-6), "{seen}");
    }

    #[test]
    fn a_persistent_reflection_is_an_error_a_passing_one_is_not() {
        let mut pts = placed();
        let f = frames(&pts, 10, 0.0);
        let mut with_glint = f.clone();
        let mut blobs = [NO_BLOB; MAX_CAMERAS];
        blobs[0] = 9;
        blobs[1] = 9;
        with_glint[3].push(TriangulatedPoint {
            point_mm: Vector3::new(300.0, 300.0, 1000.0),
            gap_mm: 0.1,
            blobs,
            cameras: 2,
        });
        let refs: Vec<&[TriangulatedPoint]> = with_glint.iter().map(|v| v.as_slice()).collect();
        let cfg = PoseConfig::default();
        assert!(measure_tool_layout("probe", &refs, 4, LayoutOrigin::FirstLed, 5.0, &cfg).is_ok());
        pts.push(Vector3::new(300.0, 300.0, 1000.0));
        let f = frames(&pts, 10, 0.0);
        let refs: Vec<&[TriangulatedPoint]> = f.iter().map(|v| v.as_slice()).collect();
        let e = measure_tool_layout("probe", &refs, 4, LayoutOrigin::FirstLed, 5.0, &cfg)
            .unwrap_err()
            .to_string();
        assert!(e.contains("5 points") && e.contains("expected 4"), "{e}");
        let e = measure_tool_layout("probe", &refs[..1], 4, LayoutOrigin::FirstLed, 5.0, &cfg)
            .unwrap_err()
            .to_string();
        assert!(e.contains("need ≥ 2 frames"), "{e}");
    }
}
