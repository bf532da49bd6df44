//! `host-tools pivot` against simulator truth: the `probe4` tool turned about a fixed tip in
//! the convergent 90° VGA rig at 1 m, rendered, tracked with the 6-DOF tracker and fitted.
//! Figures are printed (`-- --nocapture`).

mod common;

use std::path::Path;

use clap::Parser;
use common::*;
use irtrack_core::params::{BlobHeader, RigParams};
use irtrack_host_tools::cmd::simulate;
use irtrack_sim::Scenario;
use nalgebra::Vector3;

#[derive(Parser)]
struct SimCli {
    #[command(flatten)]
    sim: simulate::Args,
}

/// Renders the pivot motion; returns the true tip (tool frame) and pivot (camera 0 frame).
fn render_pivot(dir: &Path, frames: u64) -> (Vector3<f64>, Vector3<f64>) {
    let cli = SimCli::parse_from([
        "simulate",
        "--out",
        dir.to_str().unwrap(),
        "--distance-mm",
        "1000",
        "--radius-mm",
        "0",
        "--tool",
        "probe4",
        "--fps",
        "60",
        "--frames",
        &frames.to_string(),
        "--quiet",
    ]);
    let tool = simulate::tool_from_args(&cli.sim).unwrap().unwrap();
    let mut cfg = simulate::config_from_args(&cli.sim).unwrap();
    let centre = cfg.trajectory.position(0.0);
    let tip = Vector3::new(35.0, 20.0, -150.0);
    let amplitude_deg = 20.0;
    // The tool origin starts at the working point; the tip rests below it.
    let start = irtrack_sim::tools::turning(amplitude_deg, 1.0).rotation(0.0);
    let pivot = centre + start * tip;
    let (trajectory, orientation) = irtrack_sim::tools::pivoting(tip, pivot, amplitude_deg, 1.0);
    cfg.trajectory = trajectory;
    cfg.set_tool(&tool.leds_mm, orientation);
    let mut sc = Scenario::new(cfg).unwrap();
    simulate::write_scenario(&mut sc, dir, frames, Some(&tool), false).unwrap();
    (tip, pivot)
}

fn fitted_tip(out: &Path) -> Vector3<f64> {
    let rig = RigParams::from_blob(&std::fs::read(out).unwrap()).unwrap();
    Vector3::from(rig.tools[0].tip_mm.expect("the tool has a tip"))
}

#[test]
fn pivot_from_simulated_frames_finds_the_tip_within_0_1_mm() {
    let dir = scratch("frames");
    let (tip, pivot) = render_pivot(&dir, 300);
    let out = dir.join("with-tip.irp");
    let o = host_tools(&["pivot", "--frames", p(&dir), "--out", p(&out)]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    print!("{stdout}");
    let fitted = fitted_tip(&out);
    let err = (fitted - tip).norm();
    println!(
        "pivot vs truth: tip error {err:.4} mm (fitted [{:.3}, {:.3}, {:.3}], true [{:.1}, {:.1}, {:.1}]); \
         true pivot [{:.2}, {:.2}, {:.2}] mm",
        fitted.x, fitted.y, fitted.z, tip.x, tip.y, tip.z, pivot.x, pivot.y, pivot.z
    );
    assert!(err <= 0.1, "tip {err} mm from truth");
    assert!(stdout.contains("fit RMS"), "{stdout}");
    let blob = std::fs::read(&out).unwrap();
    // Version 5: pivot changed the set, so it carries a serial (the simulator's set had none)
    // besides the pivot fit's quality record (docs/param-blob.md).
    assert_eq!(BlobHeader::parse(&blob).unwrap().version, 5);
    let with_tip = RigParams::from_blob(&blob).unwrap();
    assert!(with_tip.serial >= 1_700_000_000, "serial {}", with_tip.serial);
    let record = with_tip.calibration.unwrap();
    assert_eq!(
        (record.method.as_str(), record.verdict),
        ("pivot", irtrack_core::params::Verdict::Good),
        "{record:?}"
    );
    assert!(
        record.figure("pivot_rms_mm").is_some_and(|v| v < 0.5),
        "{record:?}"
    );

    // show-params shows the tip; pivoting again from the truth poses, recorded at the new tip,
    // gives (nearly) zero extra offset: the fitted offset is added to the reported point.
    let o = host_tools(&["show-params", p(&out)]);
    assert!(text(&o).0.contains("tip ["), "{}", text(&o).0);

    let rec = record_from_truth(&dir, &fitted, |_| Vector3::zeros());
    let rec_path = dir.join("record.csv");
    std::fs::write(&rec_path, rec).unwrap();
    let out2 = dir.join("again.irp");
    let o = host_tools(&[
        "pivot",
        "--poses",
        p(&rec_path),
        "--params",
        p(&out),
        "--out",
        p(&out2),
    ]);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    let again = fitted_tip(&out2);
    assert!((again - tip).norm() < 1e-3, "again {again:?} vs {tip:?}");
}

/// A tracking record (`track --record` CSV) built from the simulator's truth poses as irtrackd
/// would report them with tip `tip_mm`, each pose's point moved by `slip_mm(pose index)`.
fn record_from_truth(dir: &Path, tip_mm: &Vector3<f64>, slip_mm: impl Fn(usize) -> Vector3<f64>) -> String {
    let truth = std::fs::read_to_string(dir.join("truth.csv")).unwrap();
    let mut rec = String::from("t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint,qw,qx,qy,qz\n");
    for (i, line) in truth.lines().skip(1).enumerate() {
        let f: Vec<f64> = line.split(',').map(|v| v.parse().unwrap()).collect();
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(f[6], f[7], f[8], f[9]));
        // What irtrackd would report with the tip: origin + R · tip.
        let at = Vector3::new(f[2], f[3], f[4]) + q * tip_mm + slip_mm(i);
        rec.push_str(&format!(
            "{},{},0,{},{},{},0.05,ok,0,{},{},{},{}\n",
            f[1], f[0], at.x, at.y, at.z, f[6], f[7], f[8], f[9]
        ));
    }
    rec
}

#[test]
fn a_tip_that_slips_in_its_divot_is_refused_then_written_marked_poor() {
    let dir = scratch("slip");
    let (tip, _) = render_pivot(&dir, 120);
    // A parameter set with the true tip, as a first good pivot would have left it.
    let good = dir.join("good.irp");
    let o = host_tools(&["pivot", "--frames", p(&dir), "--out", p(&good)]);
    assert!(o.status.success(), "{}", text(&o).1);
    // Every third pose the tip sits 3 mm beside the divot: the poses no longer share one pivot.
    let rec = record_from_truth(&dir, &tip, |i| {
        if i % 3 == 0 {
            Vector3::new(3.0, -2.0, 0.0)
        } else {
            Vector3::zeros()
        }
    });
    let rec_path = dir.join("slipped.csv");
    std::fs::write(&rec_path, rec).unwrap();
    let out = dir.join("slipped.irp");
    let args = [
        "pivot",
        "--poses",
        p(&rec_path),
        "--params",
        p(&good),
        "--out",
        p(&out),
    ];
    let o = host_tools(&args);
    let (stdout, stderr) = text(&o);
    assert!(
        !o.status.success(),
        "a slipping tip passed the gate:\n{stdout}\n{stderr}"
    );
    assert!(stderr.contains("Nothing was written"), "{stderr}");
    assert!(
        stderr.contains("the tip slipped") || stderr.contains("scatter by"),
        "the cause is not named:\n{stderr}"
    );
    assert!(!out.exists(), "a refused fit left {}", out.display());

    let mut poor_args = args.to_vec();
    poor_args.push("--accept-poor");
    let o = host_tools(&poor_args);
    let (stdout, stderr) = text(&o);
    assert!(o.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("verdict: POOR"), "{stdout}");
    let record = RigParams::from_blob(&std::fs::read(&out).unwrap())
        .unwrap()
        .calibration
        .unwrap();
    assert_eq!(record.verdict, irtrack_core::params::Verdict::Poor, "{record:?}");
}

#[test]
fn pivot_needs_a_tool_and_turning() {
    let dir = scratch("errors");
    // A scene without a tool: the parameters have nothing to calibrate.
    let o = host_tools(&["simulate", "--quiet", "--frames", "3", "--out", p(&dir)]);
    assert!(o.status.success());
    let o = host_tools(&["pivot", "--frames", p(&dir), "--out", p(&dir.join("x.irp"))]);
    let (_, err) = text(&o);
    assert!(!o.status.success() && err.contains("has no tool"), "{err}");
    // --poses without --params.
    let o = host_tools(&[
        "pivot",
        "--poses",
        p(&dir.join("truth.csv")),
        "--out",
        p(&dir.join("x.irp")),
    ]);
    let (_, err) = text(&o);
    assert!(!o.status.success() && err.contains("--params"), "{err}");
}
