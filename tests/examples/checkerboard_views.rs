//! Renders checkerboard calibration views of irtrackd's simulated rig, for `cargo xtask demo`
//! (which may not depend on workspace crates) and for trying `host-tools calibrate` by hand:
//!
//! ```text
//! cargo run -p irtrack-tests --example checkerboard_views -- OUT_DIR [convergent|parallel]
//! host-tools calibrate --images OUT_DIR --board-cols 9 --board-rows 6 --square-mm 25 ...
//! ```
//!
//! The rig is the one irtrackd's `[source.sim]` builds with default settings (convergent 90° at
//! 600 mm, or the parallel 50 mm one), so the calibration can be pushed into such an irtrackd.
//! Views: 10 that both cameras see, plus (convergent) 3 per camera that only it sees, which pin
//! the principal points (docs/calibration.md).

use std::path::PathBuf;
use std::process::ExitCode;

use irtrack_firmware::source::sim::{SimRig, SimSourceConfig};
use irtrack_sim::checkerboard::{self, BoardSpec, PoseConfig, RenderSettings};
use irtrack_sim::{Scenario, Trajectory};

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (out, rig) = match args.as_slice() {
        [out] => (PathBuf::from(out), SimRig::Convergent),
        [out, r] if r == "convergent" => (PathBuf::from(out), SimRig::Convergent),
        [out, r] if r == "parallel" => (PathBuf::from(out), SimRig::Parallel),
        _ => {
            eprintln!("usage: checkerboard_views OUT_DIR [convergent|parallel]");
            return ExitCode::from(2);
        }
    };
    match render(&out, rig) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("checkerboard_views: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Renders the views and prints what it wrote and the rig's true parameters.
fn render(out: &std::path::Path, rig: SimRig) -> Result<(), Box<dyn std::error::Error>> {
    let cfg = SimSourceConfig {
        rig,
        ..Default::default()
    };
    let scenario = Scenario::new(cfg.scenario_config())?;
    let truth = scenario.rig();
    let board = BoardSpec::new(9, 6, 25.0)?;
    let shared = PoseConfig {
        count: 10,
        seed: 5,
        ..Default::default()
    };
    let mut poses = checkerboard::generate_poses(truth, &board, &shared)?;
    if rig == SimRig::Convergent {
        for cam in 0..truth.cameras.len() {
            let own = PoseConfig {
                count: 3,
                seed: 50 + cam as u64,
                ..Default::default()
            };
            poses.extend(checkerboard::generate_single_camera_poses(
                truth, &board, cam, &own,
            )?);
        }
    }
    // Start from an empty directory so views of an earlier run cannot pair with these.
    if out.exists() {
        std::fs::remove_dir_all(out)?;
    }
    let settings = RenderSettings {
        seed: 5,
        ..Default::default()
    };
    checkerboard::write_set(out, truth, &board, &poses, &settings)?;
    // The true rig, for `host-tools show-params CALIBRATION --compare truth_rig.irp`.
    std::fs::write(out.join("truth_rig.irp"), truth.to_blob()?)?;
    println!(
        "rendered {} views per camera of the simulated {rig:?} rig into {}/cam<i>/ ({} that every \
         camera sees, the rest for one camera's intrinsics only; board: 9x6 inner corners, 25 mm \
         squares); the true rig in {}/truth_rig.irp",
        poses.len(),
        out.display(),
        shared.count,
        out.display()
    );
    // The truth, in the format `host-tools calibrate` prints its results, for comparison.
    for (i, c) in truth.cameras.iter().enumerate() {
        let k = &c.model.intrinsics;
        println!(
            "truth cam{i}: fx {:.3} fy {:.3} cx {:.3} cy {:.3}",
            k.fx_px, k.fy_px, k.cx_px, k.cy_px
        );
    }
    for i in 1..truth.cameras.len() {
        println!(
            "truth cam{i}: baseline {:.3} mm, optical axes {:.3}° apart",
            truth.baseline_mm(i)?,
            truth.optical_axis_angle_deg(i)?
        );
    }
    if let Trajectory::Circle {
        centre_mm, radius_mm, ..
    } = cfg.scenario_config().trajectory
    {
        println!(
            "truth marker path: circle of radius {radius_mm:.1} mm around ({:.1}, {:.1}, {:.1}) mm \
             (camera 0 frame)",
            centre_mm.x, centre_mm.y, centre_mm.z
        );
    }
    Ok(())
}
