//! `host-tools track`: the firmware's tracking pipeline (irtrack-core's `Tracker`) run offline
//! on recorded or simulated frames.
//!
//! Frames are `DIR/cam0/NNNNNN.pgm`, `DIR/cam1/NNNNNN.pgm`, ... With `DIR/timestamps.csv`
//! each camera's frames carry their own timestamps and are paired the way irtrackd pairs live
//! frames: every camera-0 frame with each other camera's frame of nearest timestamp, within
//! half of camera 0's median frame interval. Without it they are matched by index. A set for
//! which some camera has no frame is reported as `missing_frame`; a frame without a confident
//! marker gets its status and empty coordinates, never a guessed point.
//!
//! With timestamps each camera's frame is announced to the tracker at its own timestamp
//! (`Tracker::set_frame_time`) and the cameras' constants from `camera_timing.csv`
//! (`Tracker::set_timing`), so the set is solved at one reference instant. Truth (simulated
//! directories) is evaluated at the instant a position is for: the measurement's reference
//! instant, else camera 0's timestamp corrected by its offset; from `truth_dense.csv` when
//! present (timed scenarios), else `truth.csv` by frame.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use irtrack_core::image::GrayImage;
use irtrack_core::params::RigParams;
use irtrack_core::pgm::{self, PgmPixels};
use irtrack_core::pipeline::{Measurement, TrackStatus, Tracker, TrackerConfig};
use irtrack_core::timing::{CameraTiming, Shutter};
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

/// Per camera, frame index → (timestamp_ns, dropped) from `timestamps.csv`
/// (`frame,camera,timestamp_ns,dropped`, as `simulate` and `capture` write it).
pub fn read_timestamps(path: &Path, cameras: usize) -> anyhow::Result<Vec<BTreeMap<u64, (u64, bool)>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or("");
    if !header.starts_with("frame,camera,timestamp_ns") {
        bail!(
            "{}: header {header:?} is not frame,camera,timestamp_ns,dropped",
            path.display()
        );
    }
    let mut out = vec![BTreeMap::new(); cameras];
    for (n, line) in lines.enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let bad = || format!("{} line {}: {line:?}", path.display(), n + 2);
        if f.len() < 3 {
            bail!("{}: expected frame,camera,timestamp_ns[,dropped]", bad());
        }
        let frame: u64 = f[0].parse().with_context(bad)?;
        let camera: usize = f[1].parse().with_context(bad)?;
        let ts: u64 = f[2].parse().with_context(bad)?;
        let dropped = f.get(3).is_some_and(|d| *d == "1");
        if let Some(m) = out.get_mut(camera) {
            m.insert(frame, (ts, dropped));
        }
    }
    Ok(out)
}

/// Per camera the `offset_ns` of `camera_timing.csv` (middle of row 0's exposure − timestamp)
/// and its irtrack-core timing; `None` without the file.
pub fn read_camera_timing(path: &Path) -> anyhow::Result<Option<Vec<CameraTiming>>> {
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or("");
    if !header.starts_with("camera,shutter,line_time_ns,exposure_ns,offset_ns") {
        bail!("{}: header {header:?} is not the simulator's", path.display());
    }
    let mut out = Vec::new();
    for (n, line) in lines.enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        let bad = || format!("{} line {}: {line:?}", path.display(), n + 2);
        if f.len() < 5 || f[0].parse::<usize>().ok() != Some(out.len()) {
            bail!("{}: expected camera {} and five fields", bad(), out.len());
        }
        let shutter = match f[1] {
            "global" => Shutter::Global,
            "rolling" => Shutter::Rolling,
            _ => bail!("{}: shutter must be global or rolling", bad()),
        };
        out.push(CameraTiming {
            shutter,
            line_time_ns: f[2].parse().with_context(bad)?,
            exposure_ns: f[3].parse().with_context(bad)?,
            offset_ns: f[4].parse().with_context(bad)?,
        });
    }
    Ok(Some(out))
}

/// Marker 0's truth as a function of time: `truth_dense.csv` (`t_ns,x_mm,y_mm,z_mm`) or
/// `truth.csv`'s `t_s` column, linearly interpolated (exact at the samples).
#[derive(Debug, Clone)]
pub struct TimedTruth {
    /// (t_ns, position), increasing in time.
    samples: Vec<(f64, Vector3<f64>)>,
}

impl TimedTruth {
    /// Reads `truth_dense.csv`.
    pub fn read_dense(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut lines = text.lines();
        if lines.next() != Some("t_ns,x_mm,y_mm,z_mm") {
            bail!("{}: header is not t_ns,x_mm,y_mm,z_mm", path.display());
        }
        let mut samples = Vec::new();
        for (n, line) in lines.enumerate() {
            if line.trim().is_empty() {
                continue;
            }
            let v: Vec<f64> = line
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<Result<_, _>>()
                .with_context(|| format!("{} line {}", path.display(), n + 2))?;
            if v.len() != 4 {
                bail!("{} line {}: expected 4 fields", path.display(), n + 2);
            }
            samples.push((v[0], Vector3::new(v[1], v[2], v[3])));
        }
        Self::new(samples).with_context(|| format!("{}", path.display()))
    }

    /// From (t_ns, position) samples strictly increasing in time.
    pub fn new(samples: Vec<(f64, Vector3<f64>)>) -> anyhow::Result<Self> {
        if samples.is_empty() {
            bail!("no truth samples");
        }
        if samples.windows(2).any(|w| w[1].0 <= w[0].0) {
            bail!("truth samples are not strictly increasing in time");
        }
        Ok(TimedTruth { samples })
    }

    /// Position at `t_ns`; `None` outside the sampled span.
    pub fn at(&self, t_ns: f64) -> Option<Vector3<f64>> {
        let s = &self.samples;
        let i = s.partition_point(|(t, _)| *t <= t_ns);
        if i == 0 {
            return None;
        }
        let (t0, p0) = s[i - 1];
        if t_ns == t0 {
            return Some(p0);
        }
        let (t1, p1) = *s.get(i)?;
        let a = (t_ns - t0) / (t1 - t0);
        Some(p0 + (p1 - p0) * a)
    }
}

/// Camera `c`'s frames with a file and a timestamp (not dropped), sorted by timestamp.
fn stamped_frames(present: &BTreeSet<u64>, stamps: &BTreeMap<u64, (u64, bool)>) -> Vec<(u64, u64)> {
    let mut v: Vec<(u64, u64)> = present
        .iter()
        .filter_map(|i| match stamps.get(i) {
            Some((ts, false)) => Some((*ts, *i)),
            _ => None,
        })
        .collect();
    v.sort_unstable();
    v
}

/// Half of the median interval between consecutive frames (the pairing tolerance, as live).
fn half_median_interval_ns(frames: &[(u64, u64)]) -> u64 {
    let mut d: Vec<u64> = frames.windows(2).map(|w| w[1].0 - w[0].0).collect();
    if d.is_empty() {
        return u64::MAX;
    }
    d.sort_unstable();
    d[d.len() / 2] / 2
}

/// The frame of `frames` (sorted by timestamp) nearest to `ts_ns`: (index, |Δt|).
fn nearest(frames: &[(u64, u64)], ts_ns: u64) -> Option<(u64, u64)> {
    let i = frames.partition_point(|(t, _)| *t < ts_ns);
    [i.checked_sub(1), Some(i)]
        .into_iter()
        .flatten()
        .filter_map(|j| frames.get(j))
        .map(|(t, idx)| (*idx, t.abs_diff(ts_ns)))
        .min_by_key(|(_, d)| *d)
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

    // Timestamps per camera (pairing by nearest timestamp) and the cameras' timing constants.
    let stamps_path = args.frames.join("timestamps.csv");
    let stamped: Option<Vec<Vec<(u64, u64)>>> = if stamps_path.is_file() {
        let stamps = read_timestamps(&stamps_path, n_cam)?;
        Some(
            per_cam
                .iter()
                .zip(&stamps)
                .map(|(present, st)| stamped_frames(present, st))
                .collect(),
        )
    } else {
        None
    };
    // Index → timestamp of every usable frame, per camera.
    let ts_of: Vec<BTreeMap<u64, u64>> = stamped.as_ref().map_or_else(Vec::new, |st| {
        st.iter()
            .map(|v| v.iter().map(|(t, i)| (*i, *t)).collect())
            .collect()
    });
    let tolerance_ns = stamped
        .as_ref()
        .map_or(u64::MAX, |s| half_median_interval_ns(&s[0]));
    let timing = read_camera_timing(&args.frames.join(crate::cmd::simulate::CAMERA_TIMING_FILE))?
        .filter(|t| t.len() == n_cam);
    let dense_path = args.frames.join(crate::cmd::simulate::TRUTH_DENSE_FILE);
    let dense = if dense_path.is_file() {
        Some(TimedTruth::read_dense(&dense_path)?)
    } else {
        None
    };
    // A timed scenario (own clocks or shutters): the instants are written and truth is taken there.
    let timed = dense.is_some()
        || timing
            .as_ref()
            .is_some_and(|t| t.iter().any(|c| *c != CameraTiming::SYNCHRONOUS));

    let mut tracker: Option<Tracker> = None;
    let mut maxval_seen: Option<u16> = None;
    let truth_path = args.frames.join("truth.csv");
    let truth = usize::try_from(last + 1)
        .ok()
        .and_then(|n| matching_truth(&truth_path, n));
    // Timed scenarios say which instant each position is compared at.
    let mut csv = String::from(if timed {
        "frame,x_mm,y_mm,z_mm,gap_mm,status,cameras_used,quality,used_roi,instant_ns\n"
    } else {
        "frame,x_mm,y_mm,z_mm,gap_mm,status,cameras_used,quality,used_roi\n"
    });
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
    let missing_row = if timed { "," } else { "" };
    let mut pick: Vec<u64> = vec![0; n_cam];
    let mut frame_ts: Vec<Option<u64>> = vec![None; n_cam];
    for index in 0..=last {
        s.frames += 1;
        // Each camera's frame of this set: the same index, or the nearest timestamp.
        let complete = match &stamped {
            None => {
                pick.fill(index);
                per_cam.iter().all(|set| set.contains(&index))
            }
            Some(st) => match ts_of[0].get(&index) {
                None => false,
                Some(&ts0) => {
                    let mut ok = true;
                    for c in 0..n_cam {
                        match nearest(&st[c], ts0) {
                            Some((i, d)) if d <= tolerance_ns => {
                                pick[c] = i;
                                frame_ts[c] = ts_of[c].get(&i).copied();
                            }
                            _ => ok = false,
                        }
                    }
                    ok
                }
            },
        };
        if !complete {
            s.missing_frames += 1;
            let _ = writeln!(csv, "{index},,,,,missing_frame,0,0,0{missing_row}");
            continue;
        }
        let mut maxval = 0u16;
        let mut size = (0u32, 0u32);
        for c in 0..n_cam {
            let path = args.frames.join(format!("cam{c}/{:06}.pgm", pick[c]));
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
                let mut t = Tracker::new(&rig, cfg).context("building the tracker")?;
                // The cameras' known timing constants (the simulator's truth), as irtrackd
                // takes them from its config or parameter set.
                for (c, ct) in timing.iter().flatten().enumerate() {
                    t.set_timing(c, *ct)
                        .with_context(|| format!("camera_timing.csv camera {c}"))?;
                }
                tracker.insert(t)
            }
        };
        // Each camera's frame at its own timestamp: the tracker solves the set at one instant.
        if stamped.is_some() {
            for (c, ts) in frame_ts.iter().enumerate() {
                if let Some(ts) = ts {
                    tr.set_frame_time(c, *ts).with_context(|| format!("frame {index}"))?;
                }
            }
        }
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
        // The instant this position is for: the tracker's reference instant, else camera 0's
        // exposure by its timestamp and offset.
        let instant_ns = m.instant_ns.or_else(|| {
            frame_ts[0].map(|ts| {
                let offset = timing.as_ref().map_or(0, |t| t[0].offset_ns);
                ts as f64 + offset as f64
            })
        });
        let instant_col = match (timed, instant_ns) {
            (false, _) => String::new(),
            (true, Some(t)) => format!(",{t:.0}"),
            (true, None) => ",".to_string(),
        };
        match m.point_cam0_mm {
            Some(p) => {
                s.tracked += 1;
                let _ = writeln!(
                    csv,
                    "{index},{:.4},{:.4},{:.4},{:.4},{status},{},{:.3},{}{instant_col}",
                    p.x, p.y, p.z, m.gap_mm, m.cameras_used, m.quality, m.used_roi as u8
                );
                let at_instant = match (&dense, instant_ns) {
                    (Some(d), Some(t)) => d.at(t),
                    _ => None,
                };
                let by_frame = || {
                    truth
                        .as_ref()
                        .and_then(|t| t.get(index as usize))
                        .and_then(|r| r.as_ref())
                        .map(|(p, _)| *p)
                };
                if let Some(t) = at_instant.or_else(by_frame) {
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
                let _ = writeln!(
                    csv,
                    "{index},,,,{gap},{status},0,0,{}{instant_col}",
                    m.used_roi as u8
                );
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
