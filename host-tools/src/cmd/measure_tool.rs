//! `host-tools measure-tool`: measures a new multi-LED tool's layout with the tracker itself.
//!
//! Input: a directory of frames of the tool held still (`DIR/cam0/NNNNNN.pgm`, `DIR/cam1/...`,
//! the layout `host-tools simulate` writes and a recording uses) and the rig's parameters.
//! Per frame the blobs are detected and matched across cameras (`PointMatcher`); the candidate
//! points of all frames go to `irtrack_core::pose6d::measure_tool_layout`, which clusters them,
//! refuses persistent extra points and ambiguous layouts, and builds the tool frame
//! (docs/six-dof.md). The parameters are written back with the new `ToolDefinition` added to
//! `RigParams.tools`.

use std::path::PathBuf;

use anyhow::{Context, ensure};
use irtrack_core::params::RigParams;
use irtrack_core::pose6d::{
    LayoutOrigin, MeasuredLayout, PointMatcher, PoseConfig, TriangulatedPoint, measure_tool_layout,
};

/// Origin of the measured tool frame.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum OriginArg {
    /// Centroid of the LEDs.
    Centroid,
    /// LED 0 (the LED farthest from the centroid).
    FirstLed,
}

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Directory holding cam0/, cam1/, ... with frames of the static tool.
    #[arg(long)]
    pub frames: PathBuf,
    /// Rig parameters (blob or OpenCV YAML); default: FRAMES/rig.irp.
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// Output parameter blob: the input parameters plus the measured tool.
    #[arg(long)]
    pub out: PathBuf,
    /// Name of the new tool.
    #[arg(long)]
    pub name: String,
    /// Number of LEDs on the tool.
    #[arg(long)]
    pub leds: usize,
    /// Where the new tool's frame has its origin.
    #[arg(long, value_enum, default_value_t = OriginArg::Centroid)]
    pub origin: OriginArg,
    /// Points of different frames closer than this belong to the same LED.
    #[arg(long, default_value_t = 3.0)]
    pub cluster_radius_mm: f64,
    /// Use at most this many frames (from the first).
    #[arg(long, default_value_t = 60)]
    pub max_frames: usize,
    /// Blob threshold in frame DN (default: 30 on the 8-bit scale).
    #[arg(long)]
    pub threshold_dn: Option<u32>,
    /// Replace a tool of the same name instead of refusing.
    #[arg(long)]
    pub replace: bool,
}

/// Measures the layout; returns it with the parameters it was measured in.
pub fn measure(args: &Args) -> anyhow::Result<(RigParams, MeasuredLayout, usize)> {
    let params_path = args.params.clone().unwrap_or_else(|| args.frames.join("rig.irp"));
    let rig = crate::cmd::track::load_params(&params_path)?;
    let n_cam = rig.cameras.len();
    ensure!(n_cam >= 2, "{}: need at least 2 cameras", params_path.display());
    ensure!(args.max_frames >= 2, "--max-frames must be at least 2");
    let indices = crate::frames::common_frames(&args.frames, n_cam)?;
    ensure!(
        indices.len() >= 2,
        "{}: need frames of at least 2 indices present in every cam*/ directory, found {}",
        args.frames.display(),
        indices.len()
    );
    let config = PoseConfig::default();
    let mut matcher = PointMatcher::new(&rig, &config)?;
    let mut detector = crate::frames::FolderDetector::new(&args.frames, &rig, args.threshold_dn);
    let mut frames: Vec<Vec<TriangulatedPoint>> = Vec::new();
    for &index in indices.iter().take(args.max_frames) {
        let blobs = detector.detect(index)?;
        let points = matcher
            .solve(&blobs)
            .with_context(|| format!("matching blobs of frame {index}"))?;
        frames.push(points.to_vec());
    }
    let refs: Vec<&[TriangulatedPoint]> = frames.iter().map(|f| f.as_slice()).collect();
    let origin = match args.origin {
        OriginArg::Centroid => LayoutOrigin::Centroid,
        OriginArg::FirstLed => LayoutOrigin::FirstLed,
    };
    let layout = measure_tool_layout(
        &args.name,
        &refs,
        args.leds,
        origin,
        args.cluster_radius_mm,
        &config,
    )
    .with_context(|| format!("measuring tool {:?} from {} frames", args.name, refs.len()))?;
    Ok((rig, layout, refs.len()))
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let (mut rig, layout, used) = measure(&args)?;
    if let Some(i) = rig.tools.iter().position(|t| t.name == args.name) {
        ensure!(
            args.replace,
            "the parameters already define tool {:?}: pass --replace to overwrite it",
            args.name
        );
        rig.tools.remove(i);
    }
    rig.tools.push(layout.tool.clone());
    crate::cmd::convert_params::bump_serial(&mut rig);
    rig.validate().context("parameters with the measured tool")?;
    std::fs::write(&args.out, rig.to_blob()?).with_context(|| format!("writing {}", args.out.display()))?;
    println!(
        "tool {:?} from {used} frames: {} LEDs, identification margin {:.1} mm, worst scatter {:.3} mm RMS",
        args.name,
        layout.tool.leds_mm.len(),
        layout.margin_mm,
        layout.max_spread_rms_mm
    );
    for (i, p) in layout.tool.leds_mm.iter().enumerate() {
        println!(
            "  LED {i}: [{:8.2}, {:8.2}, {:8.2}] mm  seen in {} frames, scatter {:.3} mm",
            p[0], p[1], p[2], layout.observations[i], layout.spread_rms_mm[i]
        );
    }
    println!("written to {}", args.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cmd::simulate;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        sim: simulate::Args,
    }

    /// Pairwise LED distances, sorted (independent of LED order and tool frame).
    fn distances(leds: &[[f64; 3]]) -> Vec<f64> {
        let mut d = Vec::new();
        for i in 0..leds.len() {
            for j in i + 1..leds.len() {
                let v: f64 = (0..3).map(|k| (leds[i][k] - leds[j][k]).powi(2)).sum();
                d.push(v.sqrt());
            }
        }
        d.sort_by(f64::total_cmp);
        d
    }

    #[test]
    fn measures_a_simulated_static_tool() {
        let dir = std::env::temp_dir().join(format!("irtrack-measure-tool-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let out = dir.join("scene");
        let cli = Cli::parse_from([
            "x",
            "--out",
            out.to_str().unwrap(),
            "--distance-mm",
            "1000",
            "--tool",
            "probe4",
            "--tool-rotation-deg",
            "0",
            "--trajectory",
            "line",
            "--radius-mm",
            "0",
            "--frames",
            "12",
            "--quiet",
        ]);
        simulate::run(cli.sim).unwrap();
        let args = Args {
            frames: out.clone(),
            params: None,
            out: dir.join("with-tool.irp"),
            name: "probe4".into(),
            leds: 4,
            origin: OriginArg::Centroid,
            cluster_radius_mm: 3.0,
            max_frames: 60,
            threshold_dn: None,
            replace: false,
        };
        // simulate --tool already put probe4 into the parameters: same name needs --replace.
        let e = run(args.clone()).unwrap_err().to_string();
        assert!(e.contains("--replace"), "{e}");
        let args = Args {
            name: "probe4-measured".into(),
            ..args
        };
        run(args.clone()).unwrap();
        let rig = RigParams::from_blob(&std::fs::read(&args.out).unwrap()).unwrap();
        let measured = rig.tools.iter().find(|t| t.name == "probe4-measured").unwrap();
        let truth = simulate::builtin_tool("probe4").unwrap();
        let (dm, dt) = (distances(&measured.leds_mm), distances(&truth.leds_mm));
        for (m, t) in dm.iter().zip(&dt) {
            assert!((m - t).abs() < 0.5, "measured distances {dm:?} vs {dt:?}");
        }
        // A 3-LED expectation for a 4-LED tool is refused, not silently truncated.
        let e = measure(&Args { leds: 3, ..args }).unwrap_err();
        assert!(format!("{e:#}").contains("probe4"), "{e:#}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
