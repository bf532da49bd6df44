//! `host-tools track`: the firmware's tracking pipeline (irtrack-core's `Tracker`) run offline
//! on recorded or simulated frames.
//!
//! Frames are `DIR/cam0/NNNNNN.pgm`, `DIR/cam1/NNNNNN.pgm`, ... matched by index. A frame index
//! for which any camera's file is missing is reported as `missing_frame`; a frame without a
//! confident marker gets its status and empty coordinates, never a guessed point.

use std::collections::BTreeSet;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use irtrack_core::image::GrayImage;
use irtrack_core::params::RigParams;
use irtrack_core::pgm::{self, PgmPixels};
use irtrack_core::pipeline::{Measurement, TrackStatus, Tracker, TrackerConfig};
use nalgebra::Vector3;

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Scenario or recording directory holding cam0/, cam1/, ...
    #[arg(long)]
    pub frames: PathBuf,
    /// Rig parameters: a parameter blob or an OpenCV YAML calibration file.
    #[arg(long)]
    pub params: PathBuf,
    /// Output CSV.
    #[arg(long)]
    pub out: PathBuf,
    /// Blob threshold in frame DN (default: 40 for 8-bit frames, scaled for deeper ones).
    #[arg(long)]
    pub threshold_dn: Option<u32>,
    /// Largest ray gap (mm) of a consistent observation.
    #[arg(long)]
    pub max_gap_mm: Option<f64>,
    /// A tracked point farther than this from truth.csv counts as a wrong point.
    #[arg(long, default_value_t = 5.0)]
    pub wrong_point_mm: f64,
}

/// Status name used in the CSV.
pub fn status_name(m: &Measurement) -> &'static str {
    match m.status {
        TrackStatus::Tracked => "tracked",
        TrackStatus::NoBlob { .. } => "no_blob",
        TrackStatus::NoConsistentPair if m.ambiguous => "ambiguous",
        TrackStatus::NoConsistentPair => "no_consistent_pair",
        TrackStatus::Overloaded { .. } => "overloaded",
        TrackStatus::MissingFrame { .. } => "missing_frame",
    }
}

/// Default threshold for frames whose codes reach `maxval`: 40 DN on the 8-bit scale.
pub fn default_threshold_dn(maxval: u16) -> u32 {
    (40.0 * (maxval as f64 + 1.0) / 256.0).round() as u32
}

/// Error statistics of a set of 3-D errors (mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ErrorStats {
    /// Number of errors the figures are over.
    pub count: usize,
    /// RMS error (mm).
    pub rms_mm: f64,
    /// 95th percentile error, nearest rank (mm).
    pub p95_mm: f64,
    /// Largest error (mm).
    pub max_mm: f64,
}

/// RMS, 95th percentile (nearest rank) and maximum; `None` for no samples.
pub fn error_stats(errors_mm: &[f64]) -> Option<ErrorStats> {
    if errors_mm.is_empty() {
        return None;
    }
    let mut v = errors_mm.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((0.95 * v.len() as f64).ceil() as usize).clamp(1, v.len());
    Some(ErrorStats {
        count: v.len(),
        rms_mm: (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt(),
        p95_mm: v[rank - 1],
        max_mm: v[v.len() - 1],
    })
}

/// Marker 0's true position and whether every camera sees it.
pub type TruthRow = (Vector3<f64>, bool);

/// Reads `truth.csv` (frame,t_s,x_mm,y_mm,z_mm,visible) into frame → (position, visible).
pub fn read_truth(path: &Path) -> anyhow::Result<Vec<Option<TruthRow>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let header = text.lines().next().unwrap_or("");
    if !header.starts_with("frame,t_s,x_mm,y_mm,z_mm,visible") {
        bail!(
            "{}: header {header:?} is not the simulator's (frame,t_s,x_mm,y_mm,z_mm,visible,...)",
            path.display()
        );
    }
    let mut out: Vec<Option<TruthRow>> = Vec::new();
    for (n, line) in text.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        if f.len() < 6 {
            bail!(
                "{} line {}: expected 6 fields, got {}",
                path.display(),
                n + 1,
                f.len()
            );
        }
        let num = |i: usize| -> anyhow::Result<f64> {
            f[i].trim()
                .parse::<f64>()
                .with_context(|| format!("{} line {}: field {}", path.display(), n + 1, i + 1))
        };
        let frame = num(0)? as usize;
        if out.len() <= frame {
            out.resize(frame + 1, None);
        }
        out[frame] = Some((Vector3::new(num(2)?, num(3)?, num(4)?), f[5].trim() == "1"));
    }
    Ok(out)
}

/// `truth.csv` if it describes the `frame_count` frames being tracked. A file that does not (a
/// recording copied next to an unrelated truth, a CSV of something else) is no reason to refuse
/// tracking: it is ignored with a warning on stderr that says why.
pub fn matching_truth(path: &Path, frame_count: usize) -> Option<Vec<Option<TruthRow>>> {
    if !path.is_file() {
        return None;
    }
    let why = match read_truth(path) {
        Ok(t) if t.len() == frame_count && t.iter().all(Option::is_some) => return Some(t),
        Ok(t) => format!(
            "it has rows for {} frame indices (up to {}), the recording has frames 0..{frame_count}",
            t.iter().flatten().count(),
            t.len().saturating_sub(1)
        ),
        Err(e) => format!("{e:#}"),
    };
    eprintln!(
        "track: warning: ignoring {}: {why}; tracking without a comparison to truth",
        path.display()
    );
    None
}

/// Loads rig parameters from a blob or an OpenCV YAML file.
pub fn load_params(path: &Path) -> anyhow::Result<RigParams> {
    let rig = crate::opencv_yaml::load_params_any(path)?;
    rig.validate()
        .with_context(|| format!("parameters in {}", path.display()))?;
    Ok(rig)
}

/// Frame indices present per camera directory.
fn list_frames(dir: &Path) -> anyhow::Result<BTreeSet<u64>> {
    let mut set = BTreeSet::new();
    for e in std::fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let name = e?.file_name();
        let name = name.to_string_lossy();
        if let Some(stem) = name.strip_suffix(".pgm")
            && let Ok(i) = stem.parse::<u64>()
        {
            set.insert(i);
        }
    }
    Ok(set)
}

/// Summary of a tracking run.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackSummary {
    /// Frame indices checked: 0 through the highest index found in any camera.
    pub frames: usize,
    /// Frames with a tracked position.
    pub tracked: usize,
    /// Frame indices missing in at least one camera (not tracked).
    pub missing_frames: usize,
    /// Complete frames without a tracked position.
    pub not_tracked: usize,
    /// Tracked frames compared against truth, and how many were farther than the tolerance.
    pub error: Option<ErrorStats>,
    /// Tracked frames farther than `--wrong-point-mm` from truth.
    pub wrong_points: usize,
}

/// Runs the tracker over a frame directory and writes the CSV; returns the summary.
pub fn track_dir(args: &Args) -> anyhow::Result<TrackSummary> {
    let rig = load_params(&args.params)?;
    let n_cam = rig.cameras.len();
    let mut per_cam = Vec::with_capacity(n_cam);
    for c in 0..n_cam {
        let dir = args.frames.join(format!("cam{c}"));
        if !dir.is_dir() {
            bail!(
                "{} is missing: the parameters describe {n_cam} cameras",
                dir.display()
            );
        }
        per_cam.push(list_frames(&dir)?);
    }
    let last = per_cam.iter().filter_map(|s| s.iter().next_back()).max().copied();
    let Some(last) = last else {
        bail!("no NNNNNN.pgm frames under {}/cam*/", args.frames.display())
    };

    let mut tracker: Option<Tracker> = None;
    let mut maxval_seen: Option<u16> = None;
    let truth_path = args.frames.join("truth.csv");
    let truth = usize::try_from(last + 1)
        .ok()
        .and_then(|n| matching_truth(&truth_path, n));
    let mut csv = String::from("frame,x_mm,y_mm,z_mm,gap_mm,status,cameras_used,quality,used_roi\n");
    let mut s = TrackSummary {
        frames: 0,
        tracked: 0,
        missing_frames: 0,
        not_tracked: 0,
        error: None,
        wrong_points: 0,
    };
    let mut errors = Vec::new();
    let mut images8: Vec<Vec<u8>> = vec![Vec::new(); n_cam];
    let mut images16: Vec<Vec<u16>> = vec![Vec::new(); n_cam];
    for index in 0..=last {
        s.frames += 1;
        if per_cam.iter().any(|set| !set.contains(&index)) {
            s.missing_frames += 1;
            let _ = writeln!(csv, "{index},,,,,missing_frame,0,0,0");
            continue;
        }
        let mut maxval = 0u16;
        let mut size = (0u32, 0u32);
        for c in 0..n_cam {
            let path = args.frames.join(format!("cam{c}/{index:06}.pgm"));
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let pgm = pgm::decode(&bytes).with_context(|| format!("decoding {}", path.display()))?;
            if c > 0 && (pgm.width_px, pgm.height_px, pgm.maxval) != (size.0, size.1, maxval) {
                bail!("{}: size/depth differs from cam0's frame {index}", path.display());
            }
            maxval = pgm.maxval;
            size = (pgm.width_px, pgm.height_px);
            match pgm.pixels {
                PgmPixels::U8(v) => images8[c] = v,
                PgmPixels::U16(v) => images16[c] = v,
            }
        }
        if *maxval_seen.get_or_insert(maxval) != maxval {
            bail!("frame {index}: maxval {maxval} differs from earlier frames");
        }
        let tr = match &mut tracker {
            Some(t) => t,
            None => {
                let mut cfg = TrackerConfig {
                    threshold_dn: default_threshold_dn(maxval),
                    ..TrackerConfig::default()
                };
                if maxval > 255 {
                    cfg.saturation_dn = Some(maxval as u32);
                }
                if let Some(t) = args.threshold_dn {
                    cfg.threshold_dn = t;
                }
                if let Some(g) = args.max_gap_mm {
                    cfg.max_gap_mm = g;
                }
                tracker.insert(Tracker::new(&rig, cfg).context("building the tracker")?)
            }
        };
        let m = if maxval > 255 {
            let frames: Vec<GrayImage<'_, u16>> = images16
                .iter()
                .map(|d| GrayImage::new(d, size.0, size.1, size.0))
                .collect::<Result<_, _>>()?;
            *tr.process_u16(&frames)
                .with_context(|| format!("frame {index}"))?
        } else {
            let frames: Vec<GrayImage<'_, u8>> = images8
                .iter()
                .map(|d| GrayImage::new(d, size.0, size.1, size.0))
                .collect::<Result<_, _>>()?;
            *tr.process_u8(&frames).with_context(|| format!("frame {index}"))?
        };
        let status = status_name(&m);
        match m.point_cam0_mm {
            Some(p) => {
                s.tracked += 1;
                let _ = writeln!(
                    csv,
                    "{index},{:.4},{:.4},{:.4},{:.4},{status},{},{:.3},{}",
                    p.x, p.y, p.z, m.gap_mm, m.cameras_used, m.quality, m.used_roi as u8
                );
                if let Some(Some((t, _))) = truth.as_ref().and_then(|t| t.get(index as usize)) {
                    let e = (p - t).norm();
                    if e > args.wrong_point_mm {
                        s.wrong_points += 1;
                    }
                    errors.push(e);
                }
            }
            None => {
                s.not_tracked += 1;
                let gap = if m.gap_mm.is_finite() {
                    format!("{:.4}", m.gap_mm)
                } else {
                    String::new()
                };
                let _ = writeln!(csv, "{index},,,,{gap},{status},0,0,{}", m.used_roi as u8);
            }
        }
    }
    std::fs::write(&args.out, csv).with_context(|| format!("writing {}", args.out.display()))?;
    s.error = error_stats(&errors);
    Ok(s)
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let s = track_dir(&args)?;
    println!(
        "frames {}: tracked {}, missing frames {}, no confident marker {}; written {}",
        s.frames,
        s.tracked,
        s.missing_frames,
        s.not_tracked,
        args.out.display()
    );
    if let Some(e) = s.error {
        println!(
            "vs truth.csv ({} points): RMS {:.4} mm, p95 {:.4} mm, max {:.4} mm; wrong points (> {} mm): {}",
            e.count, e.rms_mm, e.p95_mm, e.max_mm, args.wrong_point_mm, s.wrong_points
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_stats_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(|i| i as f64).collect();
        let s = error_stats(&v).unwrap();
        assert_eq!((s.count, s.p95_mm, s.max_mm), (100, 95.0, 100.0));
        assert!((s.rms_mm - (338350.0f64 / 100.0).sqrt()).abs() < 1e-9);
        assert!(error_stats(&[]).is_none());
    }

    #[test]
    fn threshold_scales_with_depth() {
        assert_eq!(default_threshold_dn(255), 40);
        assert_eq!(default_threshold_dn(1023), 160);
    }
}
