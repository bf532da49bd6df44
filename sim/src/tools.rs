//! Built-in multi-LED tools and the standard "turning tool" motion, shared by
//! `host-tools simulate --tool` and irtrackd's simulated source (`[source.sim] tool`).

use irtrack_core::params::ToolDefinition;
use nalgebra::{UnitQuaternion, Vector3};

use crate::trajectory::{Orientation, Trajectory};

/// Names accepted by [`builtin_tool`].
pub const BUILTIN_TOOLS: &[&str] = &[
    "probe4", "tri3", "wing4", "hook4", "fan4", "kite4", "step4", "arc4",
];

/// A built-in tool definition by name (tool frame, mm; the origin is LED 0).
/// `probe4`: four LEDs, non-planar, asymmetric (identification margin 13.9 mm).
/// `tri3`: a scalene triangle with sides of 110, 101.4 and 66.3 mm (all three LEDs needed).
/// `wing4`: four LEDs whose layout is far from the other two (cross-tool margin 21 mm), so
/// all three can be tracked together.
/// `hook4`, `fan4`, `kite4`, `step4`, `arc4`: four non-planar LEDs each, found by a seeded
/// search so that all eight built-in tools form a set `MultiTracker` accepts with room to
/// spare: every tool's own margin ≥ 8.6 mm (tri3; the four-LED ones ≥ 11 mm), and no three
/// LEDs of one tool reproduce another tool's distances within 10 mm (cross-tool margin ≥ 10.1
/// mm, over every pair of the eight). Used for the eight-tool benchmark.
pub fn builtin_tool(name: &str) -> Option<ToolDefinition> {
    let leds_mm = match name {
        "probe4" => vec![
            [0.0, 0.0, 0.0],
            [99.0, 0.0, 0.0],
            [3.0, 85.0, 0.0],
            [62.0, 11.0, 32.0],
        ],
        "tri3" => vec![[0.0, 0.0, 0.0], [110.0, 0.0, 0.0], [81.8, 60.0, 0.0]],
        "wing4" => vec![
            [0.0, 0.0, 0.0],
            [166.0, 66.0, 27.0],
            [15.0, -75.0, 24.0],
            [122.0, 20.0, 1.0],
        ],
        "hook4" => vec![
            [0.0, 0.0, 0.0],
            [57.0, 27.0, -3.0],
            [126.0, -44.0, 24.0],
            [10.0, -34.0, 30.0],
        ],
        "fan4" => vec![
            [0.0, 0.0, 0.0],
            [60.0, -28.0, 8.0],
            [-5.0, 77.0, 9.0],
            [145.0, 10.0, 31.0],
        ],
        "kite4" => vec![
            [0.0, 0.0, 0.0],
            [103.0, 81.0, 12.0],
            [-10.0, 98.0, 30.0],
            [5.0, -43.0, 28.0],
        ],
        "step4" => vec![
            [0.0, 0.0, 0.0],
            [86.0, -7.0, 23.0],
            [112.0, 46.0, 10.0],
            [-14.0, -49.0, 2.0],
        ],
        "arc4" => vec![
            [0.0, 0.0, 0.0],
            [118.0, 3.0, 33.0],
            [118.0, -58.0, 26.0],
            [-31.0, -71.0, -3.0],
        ],
        _ => return None,
    };
    Some(ToolDefinition {
        name: name.into(),
        leds_mm,
        tip_mm: None,
    })
}

/// The tool turning about its own axes with amplitude `amplitude_deg` (x; y and z get 0.85 and
/// 1.3 of it) and a basic period `period_s`. The rest orientation is tilted so that no two LEDs
/// of the built-in tools share an image row in the 90° rig; the incommensurate periods per axis
/// sweep the orientation space instead of repeating one path.
pub fn turning(amplitude_deg: f64, period_s: f64) -> Orientation {
    Orientation::Wobble {
        base: UnitQuaternion::from_euler_angles(0.2, -0.3, 0.4),
        amplitude_deg: Vector3::new(amplitude_deg, 0.85 * amplitude_deg, 1.3 * amplitude_deg),
        period_s: Vector3::new(2.0, 2.5, 3.25) * period_s,
        phase_rad: Vector3::new(0.0, 1.0, 2.0),
    }
}

/// Pivot calibration motion: the tool turned about its tip, which stays at `pivot_mm`
/// (camera 0 frame), with the [`turning`] orientation. Returns the trajectory of the tool origin
/// and the orientation, to be used together (`SimConfig::set_tool` with the orientation, the
/// trajectory as `SimConfig::trajectory`).
pub fn pivoting(
    tip_tool_mm: Vector3<f64>,
    pivot_mm: Vector3<f64>,
    amplitude_deg: f64,
    period_s: f64,
) -> (Trajectory, Orientation) {
    let orientation = turning(amplitude_deg, period_s);
    (
        Trajectory::Pivot {
            pivot_mm,
            tip_tool_mm,
            orientation: orientation.clone(),
        },
        orientation,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_tools_are_valid_and_unknown_names_are_none() {
        for name in BUILTIN_TOOLS {
            let tool = builtin_tool(name).unwrap();
            assert_eq!(tool.name, *name);
            irtrack_core::pose6d::ToolModel::new(&tool, &Default::default()).unwrap();
        }
        assert!(builtin_tool("wand").is_none());
    }

    #[test]
    fn the_eight_builtin_tools_are_one_set_with_a_cross_tool_margin_of_10_mm() {
        use irtrack_core::pose6d::{PoseConfig, ToolModel, check_tool_set};
        let cfg = PoseConfig::default();
        let models: Vec<ToolModel> = BUILTIN_TOOLS
            .iter()
            .map(|n| ToolModel::new(&builtin_tool(n).unwrap(), &cfg).unwrap())
            .collect();
        assert_eq!(models.len(), irtrack_core::pose6d::MAX_TOOLS);
        // The push-time check (default margin 6 mm) accepts them, and with 10 mm as well.
        check_tool_set(&models, &cfg).unwrap();
        let strict = PoseConfig {
            min_margin_mm: 10.0,
            ..cfg
        };
        check_tool_set(&models, &strict).unwrap();
        for m in &models {
            assert!(m.margin_mm() >= 8.5, "{}: own margin {}", m.name(), m.margin_mm());
        }
    }

    #[test]
    fn pivoting_tool_keeps_its_tip_on_the_pivot() {
        let tip = Vector3::new(30.0, 40.0, -140.0);
        let pivot = Vector3::new(0.0, 0.0, 1000.0);
        let (trajectory, orientation) = pivoting(tip, pivot, 20.0, 4.0);
        trajectory.validate().unwrap();
        for i in 0..30 {
            let t = i as f64 * 0.21;
            let tip_cam0 = trajectory.position(t) + orientation.rotation(t) * tip;
            assert!((tip_cam0 - pivot).norm() < 1e-9);
        }
    }

    #[test]
    fn turning_is_a_valid_orientation_that_turns() {
        let o = turning(30.0, 4.0);
        o.validate().unwrap();
        let angle = o.rotation(0.0).angle_to(&o.rotation(1.3));
        assert!(angle.to_degrees() > 5.0, "{}", angle.to_degrees());
    }
}
