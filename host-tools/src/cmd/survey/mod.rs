//! `host-tools survey`: the cell survey with the robot (docs/teach-in.md, step 0).
//!
//! With the LED fixed to the robot's flange, the robot is driven through a grid of points
//! inside a box the user gives, over the robot protocol (`host-tools` is the link's client, as
//! irtrackd is in live following). Every target is checked before it is sent (inside the box,
//! steps no longer than `--max-step-mm`, rotation steps no larger than
//! `--max-rotation-step-deg`; longer moves are split) and every point is a standstill: after the
//! robot acknowledges it and `--settle-ms` passed, `--frames` tracked positions from irtrackd's
//! stream are averaged and the robot is asked for its pose (`POSE` → `A`, RAPID `CRobT`).
//!
//! The survey runs under the installation's safety limits: `--safety` names the board's
//! `irtrackd.toml`, whose `[robot.safety]` section governs it as it governs live following. The
//! survey box must lie inside the configured workspace (refused before anything moves), moves are
//! split to no more than the configured `max_step_mm` / `max_rotation_step_deg` (the smaller of
//! those and the CLI values), and every target passes irtrackd's own safety `Supervisor` before it
//! is sent; a `Hold` stops the survey at once, the robot stays where it is and the report says why.
//!
//! Then: a rigid registration (Kabsch) of the tracker positions onto the robot's on the fit
//! points, the Umeyama scale reported and checked against `--max-scale-error-ppm` (never
//! fitted), the target registration error (TRE) on the held-out points, per axis, the error
//! against the distance from the cameras (the paper's Fig. 11) and, when some points were
//! visited with the flange turned and the LED's offset on the flange is not given, that offset
//! solved jointly with the registration. The report (Markdown, CSV, PNG) ends in PASS or FAIL
//! against `--tolerance-mm`; with `--params`/`--out` the registration is written into the
//! parameter set (`world_from_cam0`) so that irtrackd streams robot-base coordinates.
//!
//! With `--tool NAME` the survey measures a 6-DOF tool instead of a single LED: the tool's
//! per-tool records give its pose, every grid point is visited in a few flange orientations,
//! the tool's origin on the flange is solved as the LED offset is, and its rotation on the
//! flange by a least-squares fit given the registration (the hand-eye problem `A X = X B` with
//! the tracker-to-base side already known from the positions); the report adds the
//! orientation errors in robot base (RMS and max, degrees).
//!
//! The jobs live in submodules: `plan` (the grid and split moves), `safety` (the
//! `[robot.safety]` gate), `cell` (the robot link and position stream, and the drive through
//! the plan), `analysis` (registration, LED offset, statistics) and `report`.

mod analysis;
mod cell;
mod plan;
mod report;
mod safety;

use std::path::PathBuf;

use anyhow::{Context, ensure};

pub use analysis::{Analysis, Stats, analyse, stats};
pub use cell::Measured;
use cell::measure;
pub use plan::{Planned, Role, plan, split_move};
pub use report::Report;
pub use safety::{SafetyGate, apply_safety, load_safety};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// irtrackd's position stream (NDJSON), `host:port` (port 7702 on the board).
    #[arg(long)]
    pub stream: String,
    /// The robot controller's link (RAPID `IrTrack` in survey mode, or robot-sim), `host:port`.
    #[arg(long)]
    pub robot: String,
    /// Survey box, robot base frame: min corner `x,y,z` mm.
    #[arg(long, value_parser = parse_v3)]
    pub box_min: [f64; 3],
    /// Survey box: max corner `x,y,z` mm.
    #[arg(long, value_parser = parse_v3)]
    pub box_max: [f64; 3],
    /// The board's irtrackd config (`irtrackd.toml`, the same file the board uses): its
    /// `[robot.safety]` limits govern the survey. The box must lie inside the workspace, steps and
    /// turns are split to the configured limits, and every target passes the safety supervisor
    /// before it is sent (a hold stops the survey). Required: a survey never drives a robot
    /// without the installation's limits.
    #[arg(long)]
    pub safety: PathBuf,
    /// Grid points per axis `nx,ny,nz` (N = nx·ny·nz).
    #[arg(long, default_value = "3,3,3", value_parser = parse_grid)]
    pub grid: [usize; 3],
    /// Tracked frames averaged per point.
    #[arg(long, default_value_t = 20)]
    pub frames: usize,
    /// Wait after the robot reports a point reached before averaging (vibrations, stream lag).
    #[arg(long, default_value_t = 300)]
    pub settle_ms: u64,
    /// Every K-th grid point is held out of the fit and measures the TRE.
    #[arg(long, default_value_t = 3)]
    pub holdout_every: usize,
    /// Flange orientation at the grid points, quaternion `w,x,y,z` (robot base frame).
    #[arg(long, default_value = "0,0,1,0", value_parser = parse_quat)]
    pub orient: [f64; 4],
    /// Extra visits with the flange turned (about its x, y, z axes in turn), for the LED offset.
    #[arg(long, default_value_t = 0)]
    pub rotations: usize,
    /// Turn of those visits.
    #[arg(long, default_value_t = 25.0)]
    pub rotation_deg: f64,
    /// The LED's position in the flange (TCP) frame, `x,y,z` mm, when known; otherwise it is
    /// solved from the turned visits (or taken as 0 — LED at the TCP — without them).
    #[arg(long, value_parser = parse_v3)]
    pub led_offset_mm: Option<[f64; 3]>,
    /// Longest step between consecutive targets; longer moves are split (never longer than
    /// `[robot.safety] max_step_mm`).
    #[arg(long, default_value_t = 50.0)]
    pub max_step_mm: f64,
    /// Largest rotation between consecutive targets; larger turns are split (never larger than
    /// `[robot.safety] max_rotation_step_deg`).
    #[arg(long, default_value_t = 10.0)]
    pub max_rotation_step_deg: f64,
    /// Pass when the largest held-out error (TRE max) is at most this.
    #[arg(long, default_value_t = 1.0)]
    pub tolerance_mm: f64,
    /// Fail when the Umeyama scale differs from 1 by more than this (a calibration/units check).
    #[arg(long, default_value_t = 2000.0)]
    pub max_scale_error_ppm: f64,
    /// Time allowed per point (move, settle, frames).
    #[arg(long, default_value_t = 30.0)]
    pub point_timeout_s: f64,
    /// Parameter set (blob or YAML) the positions were tracked with; needed for `--out` and
    /// when the stream is already in a (previous) world frame.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Write the parameter set with the new registration here (then sign and push it).
    #[arg(long, requires = "params")]
    pub out: Option<PathBuf>,
    /// Report directory: survey.md, survey.csv, survey.json, error-vs-distance.png.
    #[arg(long)]
    pub report: PathBuf,
    /// Survey a 6-DOF tool of irtrackd's parameter set instead of a single LED: its per-tool
    /// records (`tools` on the stream) give position and orientation. At every grid point the
    /// flange is turned to `--tool-orientations` orientations; the tool's mount on the flange
    /// (rotation and origin, hand-eye) is solved and the orientation errors in robot base are
    /// reported beside FRE/TRE.
    #[arg(long)]
    pub tool: Option<String>,
    /// With `--tool`: orientations per grid point: `--orient`, then turns by `--rotation-deg`
    /// about the flange's x, y, z axes (then the same, negative).
    #[arg(long, default_value_t = 3)]
    pub tool_orientations: usize,
    /// With `--tool`: pass when the largest held-out orientation error is at most this.
    #[arg(long, default_value_t = 0.5)]
    pub tolerance_deg: f64,
}

fn parse_v3(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let a = <[f64; 3]>::try_from(v).map_err(|v| format!("need x,y,z, got {} values", v.len()))?;
    if a.iter().all(|x| x.is_finite()) {
        Ok(a)
    } else {
        Err("values must be finite".into())
    }
}

fn parse_quat(s: &str) -> Result<[f64; 4], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let q = <[f64; 4]>::try_from(v).map_err(|v| format!("need w,x,y,z, got {} values", v.len()))?;
    let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
    if !(n > 0.99 && n < 1.01) {
        return Err(format!("quaternion norm {n} is not 1"));
    }
    Ok(q)
}

fn parse_grid(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| p.trim().parse::<usize>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let g = <[usize; 3]>::try_from(v).map_err(|v| format!("need nx,ny,nz, got {} values", v.len()))?;
    if g.iter().any(|&n| n == 0 || n > 20) {
        return Err("each of nx,ny,nz must be 1..=20".into());
    }
    Ok(g)
}

/// Runs the subcommand.
pub fn run(mut args: Args) -> anyhow::Result<()> {
    ensure!(args.frames >= 1, "--frames must be at least 1");
    ensure!(
        args.max_step_mm > 0.0 && args.max_rotation_step_deg > 0.0,
        "--max-step-mm and --max-rotation-step-deg must be > 0"
    );
    ensure!(args.tolerance_mm > 0.0, "--tolerance-mm must be > 0");
    if args.tool.is_some() {
        ensure!(
            (1..=7).contains(&args.tool_orientations),
            "--tool-orientations must be 1..=7, got {}",
            args.tool_orientations
        );
        ensure!(args.tolerance_deg > 0.0, "--tolerance-deg must be > 0");
    }
    let params = match &args.params {
        Some(p) => Some(crate::opencv_yaml::load_params_any(p)?),
        None => None,
    };
    let safety = load_safety(&args.safety)?;
    let plan = plan(&args)?;
    for note in apply_safety(&mut args, &safety)? {
        println!("survey: {note}");
    }
    println!(
        "survey: under the [robot.safety] limits of {} (workspace {:?}..{:?} mm, step {} mm, \
         rotation step {}°, speed {} mm/s)",
        args.safety.display(),
        safety.workspace_min_mm,
        safety.workspace_max_mm,
        args.max_step_mm,
        args.max_rotation_step_deg,
        safety.max_speed_mm_s
    );
    std::fs::create_dir_all(&args.report)
        .with_context(|| format!("{}: cannot create the report directory", args.report.display()))?;
    let (points, world, skipped) = match measure(&args, &plan, &safety) {
        Ok(r) => r,
        Err(e) => {
            let md = format!("# Cell survey\n\n**STOPPED**: {e:#}\n");
            let _ = std::fs::write(args.report.join("survey.md"), md);
            return Err(e.context("survey STOPPED"));
        }
    };
    // Positions in camera 0's frame, for the distance to the cameras (and the registration).
    let old_world = if world {
        let w = params
            .as_ref()
            .and_then(|p| p.world_from_cam0)
            .context("the stream is in a world frame already: give --params with that registration")?;
        Some(w)
    } else {
        None
    };
    let a = analyse(&points, args.led_offset_mm)?;
    let report = Report::new(&args, &points, &a, old_world.as_ref(), &skipped);
    report.write(&args.report)?;
    print!("{}", report.summary());
    if let (Some(out), Some(mut p)) = (&args.out, params) {
        // robot_from_cam0 = robot_from_tracker ∘ tracker_from_cam0.
        let robot_from_cam0 = match &old_world {
            Some(w) => a.all.compose(w),
            None => a.all,
        };
        p.world_from_cam0 = Some(robot_from_cam0);
        crate::cmd::convert_params::bump_serial(&mut p);
        p.validate().context("parameters with the registration")?;
        if crate::opencv_yaml::is_yaml_path(out) {
            crate::opencv_yaml::write_rig_yaml(out, &p)?;
        } else {
            let blob = p.to_blob().context("encode parameter blob")?;
            std::fs::write(out, blob).with_context(|| format!("{}: cannot write", out.display()))?;
        }
        println!(
            "survey: registration written to {} (sign and push it with host-tools push-params)",
            out.display()
        );
    }
    ensure!(report.pass, "survey FAILED: {}", report.verdict);
    Ok(())
}

#[cfg(test)]
pub(crate) mod test_support {
    use irtrack_core::camera::RigidTransform;
    use irtrack_robot::safety::SafetyConfig;
    use nalgebra::Vector3;

    use super::plan::quat;
    use super::*;

    pub(crate) fn measured(
        pts: &[([f64; 3], [f64; 4], Role)],
        robot_from_tracker: &RigidTransform,
        offset: [f64; 3],
        noise: impl Fn(usize) -> [f64; 3],
    ) -> Vec<Measured> {
        let tracker_from_robot = robot_from_tracker.inverse();
        pts.iter()
            .enumerate()
            .map(|(i, (p, q, role))| {
                let led = Vector3::from(*p) + quat(*q) * Vector3::from(offset);
                let n = Vector3::from(noise(i));
                let t = tracker_from_robot.apply(&(led + n));
                Measured {
                    index: i,
                    role: *role,
                    flange_mm: *p,
                    flange_wxyz: *q,
                    tracker_mm: [t.x, t.y, t.z],
                    tracker_sd_mm: [0.0; 3],
                    tracker_wxyz: None,
                    frames: 1,
                }
            })
            .collect()
    }

    pub(crate) fn safety_cfg() -> SafetyConfig {
        SafetyConfig {
            workspace_min_mm: [300.0, -200.0, 100.0],
            workspace_max_mm: [700.0, 200.0, 500.0],
            max_step_mm: 20.0,
            max_speed_mm_s: 250.0,
            max_gap_mm: 1.0,
            max_age_ms: 100,
            require_world_frame: true,
            max_rotation_step_deg: 5.0,
        }
    }

    pub(crate) fn args() -> Args {
        Args {
            stream: String::new(),
            robot: String::new(),
            safety: PathBuf::new(),
            box_min: [400.0, -100.0, 200.0],
            box_max: [600.0, 100.0, 400.0],
            grid: [3, 3, 3],
            frames: 10,
            settle_ms: 0,
            holdout_every: 3,
            orient: [0.0, 0.0, 1.0, 0.0],
            rotations: 6,
            rotation_deg: 25.0,
            led_offset_mm: None,
            max_step_mm: 50.0,
            max_rotation_step_deg: 10.0,
            tolerance_mm: 1.0,
            max_scale_error_ppm: 2000.0,
            point_timeout_s: 10.0,
            params: None,
            out: None,
            report: PathBuf::new(),
            tool: None,
            tool_orientations: 3,
            tolerance_deg: 0.5,
        }
    }
}
