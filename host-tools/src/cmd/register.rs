//! `host-tools register`: tracker-to-robot-base registration from corresponding points.
//!
//! Input: a CSV of pairs — the marker position reported by the tracker in the camera-0 frame
//! (`tracker_*`, i.e. recorded with no registration active) and the robot TCP position touching the
//! same spot (`robot_*`). A rigid Kabsch fit (Umeyama with `--scale`) gives `world_from_cam0`,
//! written into the parameter set so irtrackd streams robot coordinates.
//!
//! `--holdout K` keeps the last K pairs out of a first fit and reports their error (an honest
//! estimate of accuracy on new points); the transform written is then fitted on all pairs.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use irtrack_core::registration::{self, Registration};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// CSV with header tracker_x_mm,tracker_y_mm,tracker_z_mm,robot_x_mm,robot_y_mm,robot_z_mm.
    #[arg(long)]
    pub pairs: PathBuf,
    /// Hold out the last K pairs to measure the error on points not used in the fit.
    #[arg(long, default_value_t = 0)]
    pub holdout: usize,
    /// Also estimate a uniform scale (Umeyama); the stored transform stays rigid, so this is a
    /// diagnostic: a scale far from 1 means a calibration or unit problem.
    #[arg(long)]
    pub scale: bool,
    /// Input parameters (blob or OpenCV YAML).
    #[arg(long)]
    pub params: PathBuf,
    /// Output parameters (blob; OpenCV YAML when the name ends in .yaml/.yml).
    #[arg(long)]
    pub out: PathBuf,
    /// Refuse to write when the fit RMS exceeds this.
    #[arg(long, default_value_t = 2.0)]
    pub max_rms_mm: f64,
}

/// Corresponding points read from the pairs file.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pairs {
    /// Tracker positions (mm, the tracker's frame), one per pair.
    pub tracker_mm: Vec<[f64; 3]>,
    /// The same points in the robot's frame (mm), same order.
    pub robot_mm: Vec<[f64; 3]>,
}

const COLUMNS: [&str; 6] = [
    "tracker_x_mm",
    "tracker_y_mm",
    "tracker_z_mm",
    "robot_x_mm",
    "robot_y_mm",
    "robot_z_mm",
];

/// Reads the pairs CSV (header required, `#` comments and blank lines ignored).
pub fn read_pairs(path: &Path) -> anyhow::Result<Pairs> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((_, header)) = lines.next() else {
        bail!("{}: empty file", path.display())
    };
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let idx: Vec<usize> = COLUMNS
        .iter()
        .map(|c| {
            names
                .iter()
                .position(|n| n == c)
                .with_context(|| format!("{}: no column {c}", path.display()))
        })
        .collect::<anyhow::Result<_>>()?;
    let mut pairs = Pairs::default();
    for (lineno, line) in lines {
        let cells: Vec<&str> = line.split(',').map(str::trim).collect();
        let mut v = [0.0f64; 6];
        for (k, &i) in idx.iter().enumerate() {
            let cell = cells
                .get(i)
                .with_context(|| format!("{}:{}: missing {}", path.display(), lineno + 1, COLUMNS[k]))?;
            v[k] = cell.parse().with_context(|| {
                format!(
                    "{}:{}: {} = {cell:?} is not a number",
                    path.display(),
                    lineno + 1,
                    COLUMNS[k]
                )
            })?;
            ensure!(
                v[k].is_finite(),
                "{}:{}: {} is not finite",
                path.display(),
                lineno + 1,
                COLUMNS[k]
            );
        }
        pairs.tracker_mm.push([v[0], v[1], v[2]]);
        pairs.robot_mm.push([v[3], v[4], v[5]]);
    }
    Ok(pairs)
}

/// Result of a registration run.
#[derive(Debug, Clone)]
pub struct Report {
    /// Fit on all pairs (what gets written).
    pub all: Registration,
    /// Fit without the held-out pairs and their residuals.
    pub holdout: Option<(Registration, Vec<f64>)>,
}

/// Fits with optional hold-out.
pub fn register(pairs: &Pairs, holdout: usize, with_scale: bool) -> anyhow::Result<Report> {
    let n = pairs.tracker_mm.len();
    ensure!(n >= 4, "need at least 4 pairs, got {n}");
    let holdout_fit = if holdout > 0 {
        ensure!(
            n >= 4 + holdout,
            "--holdout {holdout} leaves {} pairs to fit; need at least 4",
            n - holdout.min(n)
        );
        let k = n - holdout;
        let fit = registration::fit(&pairs.tracker_mm[..k], &pairs.robot_mm[..k], with_scale)
            .context("fit without the held-out pairs")?;
        let res = registration::residuals_mm(&fit, &pairs.tracker_mm[k..], &pairs.robot_mm[k..]);
        Some((fit, res))
    } else {
        None
    };
    let all =
        registration::fit(&pairs.tracker_mm, &pairs.robot_mm, with_scale).context("fit on all pairs")?;
    Ok(Report {
        all,
        holdout: holdout_fit,
    })
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|x| x * x).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let pairs = read_pairs(&args.pairs)?;
    let report = register(&pairs, args.holdout, args.scale)?;
    let a = &report.all;
    println!("pairs: {}", pairs.tracker_mm.len());
    println!(
        "fit on all pairs: RMS {:.3} mm, max {:.3} mm, scale {:.6}",
        a.rms_mm, a.max_mm, a.scale
    );
    if let Some((fit, res)) = &report.holdout {
        println!(
            "held-out {} pairs (fit on the rest: RMS {:.3} mm): RMS {:.3} mm, max {:.3} mm",
            res.len(),
            fit.rms_mm,
            rms(res),
            res.iter().copied().fold(0.0, f64::max)
        );
    }
    ensure!(
        a.rms_mm <= args.max_rms_mm,
        "fit RMS {:.3} mm exceeds --max-rms-mm {}: check the pairs (order, units, frame)",
        a.rms_mm,
        args.max_rms_mm
    );
    // The stored transform is rigid: refit without scale when --scale was only a diagnostic.
    let rigid = if args.scale {
        registration::fit(&pairs.tracker_mm, &pairs.robot_mm, false)?
    } else {
        a.clone()
    };
    let mut params = crate::opencv_yaml::load_params_any(&args.params)?;
    params.world_from_cam0 = Some(rigid.transform);
    crate::cmd::convert_params::bump_serial(&mut params);
    params.validate().context("parameters with the registration")?;
    if crate::opencv_yaml::is_yaml_path(&args.out) {
        crate::opencv_yaml::write_rig_yaml(&args.out, &params)?;
    } else {
        let blob = params.to_blob().context("encode parameter blob")?;
        std::fs::write(&args.out, blob).with_context(|| format!("{}: cannot write", args.out.display()))?;
    }
    let t = rigid.transform.translation_mm();
    println!(
        "world_from_cam0: t = [{:.3}, {:.3}, {:.3}] mm; written to {}",
        t[0],
        t[1],
        t[2],
        args.out.display()
    );
    Ok(())
}
