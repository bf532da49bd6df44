//! `host-tools pivot`: pivot calibration of a 6-DOF tool's tip.
//!
//! The tool is turned about its tip, which rests in a fixed divot. For every tracked pose
//! `(R_i, p_i)` the tip satisfies `R_i tip + p_i = pivot`: three linear equations in the six
//! unknowns (tip in the tool frame, pivot in the tracker frame). All poses together are solved
//! in the least-squares sense with nalgebra's SVD; poses far off the fit (a bad frame) are
//! dropped once and the fit repeated. The fit RMS is the distance of the per-pose tip positions
//! from the pivot. The tip goes into the tool definition (`ToolDefinition::tip_mm`, parameter
//! blob version 2), and irtrackd then reports the tip instead of the tool origin.
//!
//! Input: either recorded poses (the CSV of `host-tools record` with its quaternion columns,
//! or irtrackd's NDJSON stream records) or frames of the pivoting tool (`DIR/cam0/…`, as
//! `simulate` and a recording write them), tracked here with irtrackd's 6-DOF tracker.
//! Recorded poses are positions of the point irtrackd reported: the tool origin, or the old
//! tip if the tool already had one; the fitted offset is added to that point.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use irtrack_core::params::{RigParams, Verdict};
use irtrack_core::pose6d::{PoseConfig, PoseStatus, PoseTracker};
use irtrack_core::stream::{PositionRecord, TrackStatus};
use nalgebra::{DMatrix, DVector, Matrix3, Quaternion, UnitQuaternion, Vector3};

use crate::calib::quality::{Check, Gate};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Recorded poses: `host-tools record` CSV (with qw,qx,qy,qz) or NDJSON stream records.
    #[arg(long, conflicts_with = "frames", required_unless_present = "frames")]
    pub poses: Option<PathBuf>,
    /// Frames of the pivoting tool (cam0/, cam1/, …), tracked here.
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// Parameter set holding the tool (blob or OpenCV YAML); default with --frames:
    /// FRAMES/rig.irp. Needed with --poses (the tip is written into it).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Tool to calibrate (default: the first tool of the parameter set, the one irtrackd tracks).
    #[arg(long)]
    pub tool: Option<String>,
    /// Output: the parameter set with the tip (`.yaml`/`.yml`: OpenCV YAML, else a blob).
    #[arg(long)]
    pub out: PathBuf,
    /// Poses whose tip lands farther than this (and than 4× the median) from the pivot are
    /// dropped once and the fit repeated.
    #[arg(long, default_value_t = 1.0)]
    pub outlier_mm: f64,
    /// Fewest degrees the tool must have turned (largest angle from the mean orientation).
    #[arg(long, default_value_t = 10.0)]
    pub min_turn_deg: f64,
    /// Blob threshold in frame DN for --frames (default: 30 on the 8-bit scale).
    #[arg(long)]
    pub threshold_dn: Option<u32>,
    /// Write the result even when the fit fails a quality limit (docs/calibration.md, "Quality
    /// gates"); the parameters are then marked poor.
    #[arg(long)]
    pub accept_poor: bool,
}

/// Largest RMS distance of the per-pose tip positions from the pivot (mm): what the reported
/// tip position scatters by.
pub const MAX_PIVOT_RMS_MM: f64 = 0.5;
/// Largest share of poses dropped as off the fit (%).
pub const MAX_PIVOT_REJECTED_PCT: f64 = 20.0;
/// Fewest degrees the used poses must have turned for the tip to be well determined (the hard
/// floor is --min-turn-deg).
pub const MIN_PIVOT_TURN_DEG: f64 = 15.0;

/// Judges a pivot fit; `rig_poor` says whether the parameter set's camera calibration is
/// already marked poor (then the likely cause of a poor fit).
pub fn judge(fit: &PivotFit, tool: &str, rig_poor: bool) -> Gate {
    let mut gate = Gate::new("pivot");
    let total = (fit.used + fit.rejected).max(1) as f64;
    let rejected_pct = fit.rejected as f64 / total * 100.0;
    gate.checks.push(Check::at_most(
        format!("tool {tool} pivot fit RMS"),
        fit.rms_mm,
        MAX_PIVOT_RMS_MM,
        "mm",
    ));
    gate.checks.push(Check::at_most(
        "poses off the fit",
        rejected_pct,
        MAX_PIVOT_REJECTED_PCT,
        "%",
    ));
    gate.checks.push(Check::at_least(
        "turn of the tool about its tip",
        fit.turn_deg,
        MIN_PIVOT_TURN_DEG,
        "°",
    ));
    gate.figure("pivot_rms_mm", fit.rms_mm);
    gate.figure("pivot_max_mm", fit.max_mm);
    gate.figure("pivot_turn_deg", fit.turn_deg);
    gate.figure("pivot_poses_used", fit.used as f64);
    if gate.failed().is_empty() {
        return gate;
    }
    if rejected_pct > MAX_PIVOT_REJECTED_PCT {
        gate.causes.push(format!(
            "the tip slipped: {} of {} poses put it more than the outlier limit from the pivot; keep the tip \
             in the divot while turning",
            fit.rejected,
            fit.used + fit.rejected
        ));
    }
    if fit.rms_mm > MAX_PIVOT_RMS_MM {
        gate.causes.push(if rig_poor {
            format!(
                "the rig's calibration is marked poor, and the tracked poses scatter by {:.2} mm RMS about the \
                 pivot: calibrate the cameras again first",
                fit.rms_mm
            )
        } else {
            format!(
                "the tracked poses scatter by {:.2} mm RMS about one pivot ({:.2} mm at most): the tool's LED \
                 layout does not fit its tracked spots (measure it again with measure-tool), the tool flexes, or \
                 the tip moved in a divot too wide for it",
                fit.rms_mm, fit.max_mm
            )
        });
    }
    if fit.turn_deg < MIN_PIVOT_TURN_DEG {
        gate.causes.push(format!(
            "the tool turned only {:.1}° about its tip: tilt it further (30° or more) in two directions",
            fit.turn_deg
        ));
    }
    gate
}

/// The parameter set's calibration record with the pivot fit added: its figures join the
/// record (replacing a previous pivot's), and a poor fit marks the whole set poor. A set without
/// a record gets one of method `pivot`.
pub fn add_to_record(rig: &mut RigParams, gate: &Gate) {
    let now = crate::calib::quality::now_unix_s();
    match &mut rig.calibration {
        None => rig.calibration = Some(Box::new(gate.record(now))),
        Some(rec) => {
            rec.figures
                .retain(|f| !gate.figures.iter().any(|g| g.name == f.name));
            rec.figures.extend(gate.figures.iter().cloned());
            if gate.verdict() == Verdict::Poor {
                rec.verdict = Verdict::Poor;
                let add = gate.summary();
                rec.summary = if rec.summary.is_empty() {
                    add
                } else {
                    format!("{}; {add}", rec.summary)
                };
                let max = irtrack_core::params::MAX_CALIBRATION_SUMMARY_LEN;
                if rec.summary.len() > max {
                    let mut cut = max - 3;
                    while !rec.summary.is_char_boundary(cut) {
                        cut -= 1;
                    }
                    rec.summary.truncate(cut);
                    rec.summary.push_str("...");
                }
            }
        }
    }
}

/// One tool pose: `p_tracker = rotation · p_tool + position_mm`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolPose {
    /// Rotation from the tool's frame to the poses' frame (camera 0 or world).
    pub rotation: Matrix3<f64>,
    /// The tool frame's origin in the poses' frame (mm).
    pub position_mm: Vector3<f64>,
}

/// Result of [`fit_pivot`].
#[derive(Debug, Clone, PartialEq)]
pub struct PivotFit {
    /// Tip in the tool frame, relative to the point the poses' positions give (mm).
    pub tip_tool_mm: Vector3<f64>,
    /// The fixed pivot point in the poses' frame (camera 0 or world), mm.
    pub pivot_mm: Vector3<f64>,
    /// RMS distance of the per-pose tip positions from the pivot (mm).
    pub rms_mm: f64,
    /// Largest such distance (mm).
    pub max_mm: f64,
    /// Poses the final fit used.
    pub used: usize,
    /// Poses dropped as outliers (tip farther than the outlier limit from the pivot).
    pub rejected: usize,
    /// Largest angle of a used pose from the mean orientation (deg).
    pub turn_deg: f64,
}

/// Least squares of `[R_i  −I] (tip, pivot)ᵀ = −p_i` over `poses`.
fn solve(poses: &[&ToolPose]) -> anyhow::Result<(Vector3<f64>, Vector3<f64>)> {
    let n = poses.len();
    let mut a = DMatrix::<f64>::zeros(3 * n, 6);
    let mut b = DVector::<f64>::zeros(3 * n);
    for (i, pose) in poses.iter().enumerate() {
        for r in 0..3 {
            for c in 0..3 {
                a[(3 * i + r, c)] = pose.rotation[(r, c)];
            }
            a[(3 * i + r, 3 + r)] = -1.0;
            b[3 * i + r] = -pose.position_mm[r];
        }
    }
    let svd = a.svd(true, true);
    let (s_max, s_min) = (svd.singular_values.max(), svd.singular_values.min());
    // Rotations about one axis only leave the tip's component along it undetermined.
    ensure!(
        s_min > 1e-3 * s_max,
        "the poses do not determine the tip (singular values {s_min:.2e} of {s_max:.2e}): \
         turn the tool about its tip in two directions, not about one axis"
    );
    let x = svd
        .solve(&b, 1e-12)
        .map_err(|e| anyhow::anyhow!("least-squares solve failed: {e}"))?;
    Ok((Vector3::new(x[0], x[1], x[2]), Vector3::new(x[3], x[4], x[5])))
}

fn residual_mm(pose: &ToolPose, tip: &Vector3<f64>, pivot: &Vector3<f64>) -> f64 {
    (pose.rotation * tip + pose.position_mm - pivot).norm()
}

/// Largest angle (deg) of a pose from the chordal mean orientation.
fn turn_deg(poses: &[&ToolPose]) -> f64 {
    let sum: Matrix3<f64> = poses.iter().map(|p| p.rotation).sum();
    let mean = UnitQuaternion::from_matrix(&sum);
    poses
        .iter()
        .map(|p| {
            UnitQuaternion::from_matrix(&p.rotation)
                .angle_to(&mean)
                .to_degrees()
        })
        .fold(0.0, f64::max)
}

/// Pivot fit of `poses` (see the module documentation).
pub fn fit_pivot(poses: &[ToolPose], outlier_mm: f64, min_turn_deg: f64) -> anyhow::Result<PivotFit> {
    ensure!(
        poses.len() >= 6,
        "{} tracked poses; a pivot fit needs at least 6 (turn the tool longer)",
        poses.len()
    );
    let all: Vec<&ToolPose> = poses.iter().collect();
    let turned = turn_deg(&all);
    ensure!(
        turned >= min_turn_deg,
        "the tool turned only {turned:.1}° from its mean orientation (need ≥ {min_turn_deg}°): \
         tilt it further about its tip"
    );
    let (tip, pivot) = solve(&all)?;
    let mut res: Vec<f64> = all.iter().map(|p| residual_mm(p, &tip, &pivot)).collect();
    let mut sorted = res.clone();
    sorted.sort_by(f64::total_cmp);
    let limit = outlier_mm.max(4.0 * sorted[sorted.len() / 2]);
    let kept: Vec<&ToolPose> = all
        .iter()
        .zip(&res)
        .filter(|(_, r)| **r <= limit)
        .map(|(p, _)| *p)
        .collect();
    let rejected = all.len() - kept.len();
    let (tip, pivot) = if rejected > 0 {
        ensure!(
            kept.len() >= 6,
            "only {} of {} poses lie within {limit:.2} mm of the fitted pivot: the tip slipped, \
             or the poses are not of a tool turned about a fixed tip",
            kept.len(),
            all.len()
        );
        let refit = solve(&kept)?;
        res = kept.iter().map(|p| residual_mm(p, &refit.0, &refit.1)).collect();
        refit
    } else {
        (tip, pivot)
    };
    let rms_mm = (res.iter().map(|r| r * r).sum::<f64>() / res.len() as f64).sqrt();
    Ok(PivotFit {
        tip_tool_mm: tip,
        pivot_mm: pivot,
        rms_mm,
        max_mm: res.iter().copied().fold(0.0, f64::max),
        used: kept.len(),
        rejected,
        turn_deg: turn_deg(&kept),
    })
}

fn pose_from(position_mm: [f64; 3], q_wxyz: [f64; 4]) -> anyhow::Result<ToolPose> {
    let q = Quaternion::new(q_wxyz[0], q_wxyz[1], q_wxyz[2], q_wxyz[3]);
    ensure!(
        q.norm() > 0.5 && position_mm.iter().chain(&q_wxyz).all(|v| v.is_finite()),
        "not a pose: position {position_mm:?}, quaternion {q_wxyz:?}"
    );
    Ok(ToolPose {
        rotation: UnitQuaternion::from_quaternion(q)
            .to_rotation_matrix()
            .into_inner(),
        position_mm: Vector3::from(position_mm),
    })
}

/// Reads tracked poses from a `record` CSV or NDJSON stream records. Rows or records without
/// a tracked position and orientation (lost frames, single-marker records) are skipped.
pub fn read_poses(path: &Path) -> anyhow::Result<Vec<ToolPose>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut poses = Vec::new();
    let mut without_orientation = 0usize;
    if text.trim_start().starts_with('{') {
        for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
            let r = PositionRecord::from_ndjson_line(line)
                .with_context(|| format!("{} line {}", path.display(), n + 1))?;
            match (r.status, r.position_mm, r.orientation_wxyz) {
                (TrackStatus::Ok, Some(p), Some(q)) => {
                    poses.push(pose_from(p, q).with_context(|| format!("{} line {}", path.display(), n + 1))?)
                }
                (TrackStatus::Ok, Some(_), None) => without_orientation += 1,
                _ => {}
            }
        }
    } else {
        let mut lines = text.lines().enumerate();
        let header: Vec<&str> = lines
            .next()
            .map(|(_, l)| l.split(',').collect())
            .unwrap_or_default();
        let col = |name: &str| -> anyhow::Result<usize> {
            header.iter().position(|h| h.trim() == name).ok_or_else(|| {
                anyhow::anyhow!(
                    "{}: no `{name}` column; expected the CSV of `host-tools record` (x_mm,y_mm,z_mm,…,qw,qx,qy,qz) or NDJSON records",
                    path.display()
                )
            })
        };
        let cols: Vec<usize> = ["x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz"]
            .iter()
            .map(|c| col(c))
            .collect::<anyhow::Result<_>>()?;
        let status = header.iter().position(|h| h.trim() == "status");
        for (n, line) in lines.filter(|(_, l)| !l.trim().is_empty()) {
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            if status.is_some_and(|s| f.get(s).is_some_and(|v| *v != TrackStatus::Ok.as_str())) {
                continue;
            }
            let field = |i: usize| f.get(cols[i]).copied().unwrap_or("");
            if field(0).is_empty() {
                continue;
            }
            if field(3).is_empty() {
                without_orientation += 1;
                continue;
            }
            let mut v = [0.0; 7];
            for (i, slot) in v.iter_mut().enumerate() {
                *slot = field(i).parse().with_context(|| {
                    format!(
                        "{} line {}: `{}` is not a number",
                        path.display(),
                        n + 1,
                        field(i)
                    )
                })?;
            }
            poses.push(
                pose_from([v[0], v[1], v[2]], [v[3], v[4], v[5], v[6]])
                    .with_context(|| format!("{} line {}", path.display(), n + 1))?,
            );
        }
    }
    if poses.is_empty() && without_orientation > 0 {
        bail!(
            "{}: {without_orientation} tracked positions but no orientation: the parameter set \
             irtrackd ran has no multi-LED tool (pivot calibration needs 6-DOF poses)",
            path.display()
        );
    }
    Ok(poses)
}

/// Tracks the tool in every frame of `dir` with the 6-DOF tracker; returns the tracked poses
/// (origin and rotation, camera-0 frame) and the number of frames looked at.
pub fn track_poses(
    dir: &Path,
    rig: &RigParams,
    tool_index: usize,
    threshold_dn: Option<u32>,
) -> anyhow::Result<(Vec<ToolPose>, usize)> {
    let n_cam = rig.cameras.len();
    let indices = crate::frames::common_frames(dir, n_cam)?;
    ensure!(
        !indices.is_empty(),
        "{}: no frame index present in every cam*/ directory",
        dir.display()
    );
    let mut tracker = PoseTracker::new(rig, &rig.tools[tool_index], PoseConfig::default())
        .with_context(|| format!("tool {:?}", rig.tools[tool_index].name))?;
    let mut detector = crate::frames::FolderDetector::new(dir, rig, threshold_dn);
    let mut poses = Vec::new();
    for &index in &indices {
        let blobs = detector.detect(index)?;
        let pose = tracker
            .process(&blobs)
            .with_context(|| format!("6-DOF tracking of frame {index}"))?;
        if pose.status == PoseStatus::Tracked {
            poses.push(ToolPose {
                rotation: Matrix3::from_row_slice(&pose.r_row_major),
                position_mm: Vector3::from(pose.position_mm),
            });
        }
    }
    Ok((poses, indices.len()))
}

/// Runs the fit the arguments describe; returns the parameter set with the tip, the index of
/// the calibrated tool and the fit.
pub fn calibrate(args: &Args) -> anyhow::Result<(RigParams, usize, PivotFit)> {
    let params_path = match (&args.params, &args.frames) {
        (Some(p), _) => p.clone(),
        (None, Some(f)) => f.join("rig.irp"),
        (None, None) => bail!("--poses needs --params: the parameter set whose tool gets the tip"),
    };
    let mut rig = crate::cmd::track::load_params(&params_path)?;
    ensure!(
        !rig.tools.is_empty(),
        "{}: the parameter set has no tool (add one with `host-tools measure-tool`)",
        params_path.display()
    );
    let tool_index = match &args.tool {
        None => 0,
        Some(name) => rig.tools.iter().position(|t| &t.name == name).ok_or_else(|| {
            let names: Vec<&str> = rig.tools.iter().map(|t| t.name.as_str()).collect();
            anyhow::anyhow!(
                "{}: no tool {name:?} (tools: {})",
                params_path.display(),
                names.join(", ")
            )
        })?,
    };
    // Recorded positions are of the point irtrackd reported: the old tip if there was one.
    let (poses, base_tool_mm) = match (&args.poses, &args.frames) {
        (Some(p), _) => (
            read_poses(p)?,
            rig.tools[tool_index]
                .tip_mm
                .map_or_else(Vector3::zeros, Vector3::from),
        ),
        (None, Some(dir)) => {
            let (poses, frames) = track_poses(dir, &rig, tool_index, args.threshold_dn)?;
            eprintln!("pivot: tracked the tool in {} of {frames} frames", poses.len());
            (poses, Vector3::zeros())
        }
        (None, None) => bail!("give --poses FILE or --frames DIR"),
    };
    let fit = fit_pivot(&poses, args.outlier_mm, args.min_turn_deg)?;
    let tip = base_tool_mm + fit.tip_tool_mm;
    rig.tools[tool_index].tip_mm = Some([tip.x, tip.y, tip.z]);
    let rig_poor = rig
        .calibration
        .as_ref()
        .is_some_and(|c| c.verdict == Verdict::Poor);
    let gate = judge(&fit, &rig.tools[tool_index].name, rig_poor);
    print_fit(&rig, tool_index, &fit);
    gate.enforce(args.accept_poor)?;
    add_to_record(&mut rig, &gate);
    crate::cmd::convert_params::bump_serial(&mut rig);
    rig.validate().context("parameters with the tool tip")?;
    Ok((rig, tool_index, fit))
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let (rig, _, _) = calibrate(&args)?;
    if crate::opencv_yaml::is_yaml_path(&args.out) {
        crate::opencv_yaml::write_rig_yaml(&args.out, &rig)?;
    } else {
        crate::cmd::convert_params::write_atomically(&args.out, &rig.to_blob()?)?;
    }
    println!(
        "written to {} (irtrackd reports the tip once these parameters are pushed)",
        args.out.display()
    );
    Ok(())
}

fn print_fit(rig: &RigParams, tool_index: usize, fit: &PivotFit) {
    let tool = &rig.tools[tool_index];
    let tip = tool.tip_mm.unwrap_or_default();
    println!(
        "pivot fit of tool {:?}: {} poses used, {} rejected, turned up to {:.1}°",
        tool.name, fit.used, fit.rejected, fit.turn_deg
    );
    println!(
        "  tip in the tool frame: [{:.3}, {:.3}, {:.3}] mm",
        tip[0], tip[1], tip[2]
    );
    println!(
        "  pivot point:           [{:.3}, {:.3}, {:.3}] mm (frame of the poses)",
        fit.pivot_mm.x, fit.pivot_mm.y, fit.pivot_mm.z
    );
    println!("  fit RMS {:.3} mm, max {:.3} mm", fit.rms_mm, fit.max_mm);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn synthetic(tip: Vector3<f64>, pivot: Vector3<f64>, n: usize, noise_mm: f64) -> Vec<ToolPose> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 0.37;
                let r = UnitQuaternion::from_euler_angles(0.4 * t.sin(), 0.3 * (1.3 * t).cos(), 0.2 * t)
                    .to_rotation_matrix()
                    .into_inner();
                // Deterministic "noise" that does not average to exactly zero.
                let wiggle = Vector3::new((7.1 * t).sin(), (5.3 * t).cos(), (3.7 * t).sin()) * noise_mm;
                ToolPose {
                    rotation: r,
                    position_mm: pivot - r * tip + wiggle,
                }
            })
            .collect()
    }

    #[test]
    fn exact_poses_give_the_tip_and_pivot() {
        let tip = Vector3::new(12.0, -30.0, -155.0);
        let pivot = Vector3::new(40.0, 5.0, 980.0);
        let fit = fit_pivot(&synthetic(tip, pivot, 50, 0.0), 1.0, 10.0).unwrap();
        assert!((fit.tip_tool_mm - tip).norm() < 1e-9, "{fit:?}");
        assert!((fit.pivot_mm - pivot).norm() < 1e-9, "{fit:?}");
        assert!(fit.rms_mm < 1e-9 && fit.rejected == 0);
    }

    #[test]
    fn one_bad_pose_is_rejected() {
        let tip = Vector3::new(0.0, 20.0, -120.0);
        let pivot = Vector3::new(0.0, 0.0, 1000.0);
        let mut poses = synthetic(tip, pivot, 40, 0.05);
        poses[7].position_mm.x += 25.0;
        let fit = fit_pivot(&poses, 1.0, 10.0).unwrap();
        assert_eq!(fit.rejected, 1);
        assert!((fit.tip_tool_mm - tip).norm() < 0.1, "{fit:?}");
        assert!(fit.rms_mm < 0.1, "{fit:?}");
    }

    #[test]
    fn too_little_turning_is_refused() {
        let r = Matrix3::identity();
        let poses: Vec<ToolPose> = (0..10)
            .map(|i| ToolPose {
                rotation: r,
                position_mm: Vector3::new(i as f64 * 0.01, 0.0, 900.0),
            })
            .collect();
        let e = fit_pivot(&poses, 1.0, 10.0).unwrap_err().to_string();
        assert!(e.contains("turned only"), "{e}");
        // Turning about one axis only leaves the tip along it undetermined.
        let one_axis: Vec<ToolPose> = (0..20)
            .map(|i| {
                let r = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), (i as f64 - 10.0) * 0.04)
                    .to_rotation_matrix()
                    .into_inner();
                ToolPose {
                    rotation: r,
                    position_mm: Vector3::new(0.0, 0.0, 900.0) - r * Vector3::new(10.0, 0.0, -100.0),
                }
            })
            .collect();
        let e = fit_pivot(&one_axis, 1.0, 10.0).unwrap_err().to_string();
        assert!(e.contains("two directions"), "{e}");
        let e = fit_pivot(&one_axis[..4], 1.0, 10.0).unwrap_err().to_string();
        assert!(e.contains("at least 6"), "{e}");
    }

    #[test]
    fn reads_record_csv_and_ndjson() {
        let dir = std::env::temp_dir().join(format!("irtrack-pivot-read-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let csv = dir.join("rec.csv");
        std::fs::write(
            &csv,
            format!(
                "t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint,qw,qx,qy,qz\n\
                 0.0,1,100,1.0,2.0,3.0,0.05,ok,0,{h},0,0,{h}\n\
                 0.1,2,200,,,,,lost,0,,,,\n\
                 0.2,3,300,4.0,5.0,6.0,0.05,ok,0,1,0,0,0\n"
            ),
        )
        .unwrap();
        let poses = read_poses(&csv).unwrap();
        assert_eq!(poses.len(), 2);
        assert!((poses[0].rotation * Vector3::x() - Vector3::y()).norm() < 1e-12);
        assert_eq!(poses[1].position_mm, Vector3::new(4.0, 5.0, 6.0));

        let mut rec = PositionRecord {
            frame: 1,
            capture_ts_ns: 5,
            position_mm: Some([1.0, 2.0, 3.0]),
            orientation_wxyz: Some([1.0, 0.0, 0.0, 0.0]),
            gap_mm: 0.1,
            status: TrackStatus::Ok,
            cameras_used: 2,
            world_frame: false,
            latency_us: 900,
            params_crc: 7,
        };
        let mut nd = rec.to_ndjson_line();
        rec.status = TrackStatus::Lost;
        rec.position_mm = None;
        rec.orientation_wxyz = None;
        nd.push_str(&rec.to_ndjson_line());
        let path = dir.join("rec.ndjson");
        std::fs::write(&path, nd).unwrap();
        let poses = read_poses(&path).unwrap();
        assert_eq!(poses.len(), 1);
        assert_eq!(poses[0].position_mm, Vector3::new(1.0, 2.0, 3.0));

        let single = dir.join("single.csv");
        std::fs::write(
            &single,
            "t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint,qw,qx,qy,qz\n\
             0.0,1,100,1.0,2.0,3.0,0.05,ok,0,,,,\n",
        )
        .unwrap();
        let e = read_poses(&single).unwrap_err().to_string();
        assert!(e.contains("no orientation"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
