//! Replay of a recorded directory: `DIR/cam<N>/<frame:06>.pgm`, optional
//! `DIR/timestamps.csv` (`frame,camera,timestamp_ns,dropped`).
//!
//! All file paths are built when the source opens, and file contents are read into a retained
//! buffer, so replaying a frame does not allocate. Timestamps are mapped onto CLOCK_MONOTONIC
//! (recorded intervals kept at recorded speed; read time at maximum speed), each camera's frame
//! with its own recorded timestamp (free-running cameras' frames of one set differ; the set's
//! pairing error is their spread) so latency figures stay meaningful; the set index is the
//! recorded frame number, which matches `truth.csv` (a `simulate` slot holds each camera's
//! exposure nearest to it, a `capture` set the frames irtrackd paired live).

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use irtrack_core::pgm;

use super::{Frame, FrameSet, FrameSource, SourceError, SourceStats};
use crate::clock;

/// Playback speed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ReplaySpeed {
    /// Keep the recorded frame intervals (needs timestamps.csv; otherwise `fps`).
    #[default]
    Recorded,
    /// As fast as the loop consumes frames.
    Max,
}

/// `[source.replay]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplayConfig {
    /// Recording directory: `cam0/`, `cam1/`, ... with `NNNNNN.pgm` frames.
    pub dir: PathBuf,
    /// How fast the sets are delivered.
    #[serde(default)]
    pub speed: ReplaySpeed,
    /// Start again at the first frame after the last one instead of ending.
    #[serde(default)]
    pub repeat: bool,
    /// Frame rate used at recorded speed when the directory has no timestamps.csv
    /// (default [`DEFAULT_REPLAY_FPS`], said at start).
    #[serde(default)]
    pub fps: Option<f64>,
}

/// Pace of a recording without `timestamps.csv` when `[source.replay] fps` is not set: the
/// frame sets get this spacing, so each is newer than the one before (with period 0 the loop
/// would drop every set after the first as "not newer").
pub const DEFAULT_REPLAY_FPS: f64 = 30.0;

/// Where the replay's timing comes from (said at start and in the status's description).
#[derive(Debug, Clone, PartialEq)]
pub enum ReplayTiming {
    /// `timestamps.csv` of the recording.
    Recorded,
    /// No timestamps.csv: `[source.replay] fps`.
    ConfiguredFps(f64),
    /// No timestamps.csv and no `fps`: [`DEFAULT_REPLAY_FPS`].
    DefaultFps(f64),
}

impl std::fmt::Display for ReplayTiming {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ReplayTiming::Recorded => write!(f, "recorded timestamps (timestamps.csv)"),
            ReplayTiming::ConfiguredFps(fps) => {
                write!(f, "no timestamps.csv: paced at {fps} fps ([source.replay] fps)")
            }
            ReplayTiming::DefaultFps(fps) => write!(
                f,
                "no timestamps.csv: paced at the default {fps} fps (set [source.replay] fps for another rate)"
            ),
        }
    }
}

struct RecordedSet {
    frame: u64,
    /// Per-camera (path, recorded timestamp).
    files: Vec<(PathBuf, u64)>,
}

/// A [`FrameSource`] over a recorded directory.
pub struct ReplaySource {
    cfg: ReplayConfig,
    sets: Vec<RecordedSet>,
    cameras: usize,
    next: usize,
    buf: Vec<u8>,
    stats: SourceStats,
    /// Recorded timestamps that were dropped at recording time (frames skipped on replay).
    skipped_frames: u64,
    /// (monotonic ns at the first delivered set, its recorded timestamp)
    epoch: Option<(u64, u64)>,
    template: FrameSet,
    timing: ReplayTiming,
    /// Sets skipped because a frame file could not be read or decoded (first path and reason
    /// kept for the end-of-replay summary).
    unreadable: u64,
    first_unreadable: Option<String>,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> SourceError + '_ {
    move |source| SourceError::Io {
        path: path.display().to_string(),
        source,
    }
}

fn frame_path(dir: &Path, camera: usize, frame: u64) -> PathBuf {
    dir.join(format!("cam{camera}")).join(format!("{frame:06}.pgm"))
}

impl ReplaySource {
    /// Finds the camera directories and the complete sets under `cfg.dir`; refuses a
    /// directory without any.
    pub fn open(cfg: &ReplayConfig) -> Result<Self, SourceError> {
        let dir = &cfg.dir;
        let mut cameras = 0;
        while dir.join(format!("cam{cameras}")).is_dir() {
            cameras += 1;
        }
        if cameras == 0 {
            return Err(SourceError::Config(format!(
                "replay directory {} has no cam0/ subdirectory",
                dir.display()
            )));
        }
        let ts_path = dir.join("timestamps.csv");
        let mut skipped_frames = 0;
        let timing = if ts_path.exists() {
            ReplayTiming::Recorded
        } else {
            match cfg.fps {
                Some(f) if f.is_finite() && f > 0.0 => ReplayTiming::ConfiguredFps(f),
                Some(f) => {
                    return Err(SourceError::Config(format!(
                        "[source.replay] fps = {f} must be a positive number of frame sets per second"
                    )));
                }
                None => ReplayTiming::DefaultFps(DEFAULT_REPLAY_FPS),
            }
        };
        let sets = if ts_path.exists() {
            let text = std::fs::read_to_string(&ts_path).map_err(io(&ts_path))?;
            // frame -> per-camera (timestamp, dropped)
            let mut by_frame: BTreeMap<u64, Vec<Option<(u64, bool)>>> = BTreeMap::new();
            for (lineno, line) in text.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with("frame") || line.starts_with('#') {
                    continue;
                }
                let bad = || {
                    SourceError::Config(format!(
                        "{}:{}: expected `frame,camera,timestamp_ns,dropped`, got `{line}`",
                        ts_path.display(),
                        lineno + 1
                    ))
                };
                let mut it = line.split(',').map(str::trim);
                let mut num = || it.next().and_then(|s| s.parse::<u64>().ok()).ok_or_else(bad);
                let (frame, camera, ts, dropped) = (num()?, num()?, num()?, num()?);
                let camera = usize::try_from(camera).map_err(|_| bad())?;
                if camera >= cameras {
                    return Err(bad());
                }
                by_frame.entry(frame).or_insert_with(|| vec![None; cameras])[camera] =
                    Some((ts, dropped != 0));
            }
            let mut sets = Vec::with_capacity(by_frame.len());
            for (frame, cams) in by_frame {
                if cams.iter().any(|c| c.is_none_or(|(_, dropped)| dropped)) {
                    skipped_frames += 1;
                    continue;
                }
                let files = cams
                    .iter()
                    .enumerate()
                    .map(|(c, v)| (frame_path(dir, c, frame), v.map_or(0, |(ts, _)| ts)))
                    .collect();
                sets.push(RecordedSet { frame, files });
            }
            sets
        } else {
            // No timestamps: every frame number present in cam0, spaced by `fps`.
            let cam0 = dir.join("cam0");
            let mut frames: Vec<u64> = std::fs::read_dir(&cam0)
                .map_err(io(&cam0))?
                .filter_map(|e| e.ok())
                .filter_map(|e| e.file_name().to_str()?.strip_suffix(".pgm")?.parse().ok())
                .collect();
            frames.sort_unstable();
            let fps = match timing {
                ReplayTiming::ConfiguredFps(f) | ReplayTiming::DefaultFps(f) => f,
                ReplayTiming::Recorded => DEFAULT_REPLAY_FPS,
            };
            let period_ns = (1e9 / fps) as u64;
            frames
                .into_iter()
                .map(|frame| RecordedSet {
                    frame,
                    files: (0..cameras)
                        .map(|c| (frame_path(dir, c, frame), frame * period_ns))
                        .collect(),
                })
                .collect()
        };
        let first = sets.first().ok_or_else(|| {
            SourceError::Config(format!(
                "replay directory {} holds no complete frame set",
                dir.display()
            ))
        })?;
        if let ReplayTiming::DefaultFps(_) = timing
            && cfg.speed == ReplaySpeed::Recorded
        {
            tracing::warn!(dir = %dir.display(), "replay: {timing}");
        }
        let mut buf = Vec::new();
        let mut frames = Vec::with_capacity(cameras);
        for (path, _) in &first.files {
            read_file(path, &mut buf)?;
            let h = pgm::parse_header(&buf)
                .map_err(|e| SourceError::Config(format!("{}: {e}", path.display())))?;
            frames.push(Frame::shaped_like_pgm(&h));
        }
        let template = FrameSet {
            index: 0,
            frames,
            pairing_error_ns: 0,
            render_ns: 0,
        };
        Ok(Self {
            cfg: cfg.clone(),
            sets,
            cameras,
            next: 0,
            buf,
            stats: SourceStats::default(),
            skipped_frames,
            epoch: None,
            template,
            timing,
            unreadable: 0,
            first_unreadable: None,
        })
    }

    /// Where the replay's timing comes from.
    pub fn timing(&self) -> &ReplayTiming {
        &self.timing
    }

    /// The recording's frame rate: the median interval between its sets' timestamps
    /// (`timestamps.csv`, or the configured pace without one); `None` with fewer than two sets.
    pub fn recorded_fps(&self) -> Option<f64> {
        let mut intervals: Vec<u64> = self
            .sets
            .windows(2)
            .filter_map(|w| {
                let t = |s: &RecordedSet| s.files.iter().map(|(_, ts)| *ts).max().unwrap_or(0);
                t(&w[1]).checked_sub(t(&w[0])).filter(|d| *d > 0)
            })
            .collect();
        if intervals.is_empty() {
            return None;
        }
        intervals.sort_unstable();
        let median = intervals[intervals.len() / 2];
        Some(1e9 / median as f64)
    }

    /// Number of complete recorded sets.
    pub fn len(&self) -> usize {
        self.sets.len()
    }

    /// True when no complete set was found.
    pub fn is_empty(&self) -> bool {
        self.sets.is_empty()
    }
}

fn read_file(path: &Path, buf: &mut Vec<u8>) -> Result<(), SourceError> {
    buf.clear();
    std::fs::File::open(path)
        .and_then(|mut f| f.read_to_end(buf))
        .map_err(io(path))?;
    Ok(())
}

impl FrameSource for ReplaySource {
    fn camera_count(&self) -> usize {
        self.cameras
    }

    fn nominal_fps(&self) -> Option<f64> {
        self.recorded_fps()
    }

    fn allocate_set(&self) -> FrameSet {
        self.template.clone()
    }

    fn next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError> {
        let result = self.try_next_set(out);
        // A frame file that cannot be read or decoded is reported (with its path) and its set
        // passed over: the loop's retry then gets the next set instead of the same bad file.
        if let Err(SourceError::CameraLost { device, reason, .. }) = &result {
            if self.unreadable == 0 {
                self.first_unreadable = Some(format!("{device}: {reason}"));
            }
            self.unreadable += 1;
            self.next += 1;
            self.stats.sets_dropped = self.skipped_frames + self.unreadable;
        }
        result
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    fn describe(&self) -> String {
        format!(
            "replay of {} ({} cameras, {} sets, {:?} speed{}; {})",
            self.cfg.dir.display(),
            self.cameras,
            self.sets.len(),
            self.cfg.speed,
            if self.cfg.repeat { ", repeating" } else { "" },
            if self.cfg.speed == ReplaySpeed::Max {
                "as fast as processed".to_string()
            } else {
                self.timing.to_string()
            }
        )
    }

    fn end_summary(&self) -> Option<String> {
        let mut s = format!(
            "replay of {} ended: {} of {} recorded sets delivered",
            self.cfg.dir.display(),
            self.stats.sets_delivered,
            self.sets.len() as u64 + self.skipped_frames
        );
        if self.skipped_frames > 0 {
            s += &format!(
                "; {} sets skipped because timestamps.csv marks a camera's frame dropped or missing",
                self.skipped_frames
            );
        }
        if let Some(first) = &self.first_unreadable {
            s += &format!(
                "; {} sets skipped for unreadable frame files (first: {first})",
                self.unreadable
            );
        }
        Some(s)
    }
}

impl ReplaySource {
    fn try_next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError> {
        if self.next >= self.sets.len() {
            if !self.cfg.repeat {
                return Err(SourceError::EndOfStream);
            }
            self.next = 0;
            self.epoch = None;
        }
        let set = &self.sets[self.next];
        if out.frames.len() != self.cameras {
            return Err(SourceError::Config(format!(
                "frame set has {} frames, source has {} cameras",
                out.frames.len(),
                self.cameras
            )));
        }
        let rec_ts = set.files.iter().map(|(_, ts)| *ts).max().unwrap_or(0);
        let now = clock::monotonic_ns();
        let (epoch_mono, epoch_rec) = *self.epoch.get_or_insert((now, rec_ts));
        // Signed: a camera stamped before the first set's latest frame (free-running cameras'
        // skew, docs/simulator.md "Camera timing") keeps its offset instead of clamping to it.
        let mapped = |ts: u64| epoch_mono.saturating_add_signed(ts.wrapping_sub(epoch_rec) as i64);
        if self.cfg.speed == ReplaySpeed::Recorded {
            clock::sleep_until_ns(mapped(rec_ts));
        }
        // At maximum speed the set is stamped now, each camera keeping its recorded skew from
        // the set's latest frame (the tracker places every camera's frame at its own instant).
        let now_max = clock::monotonic_ns();
        let (mut min_ts, mut max_ts) = (u64::MAX, 0);
        for (camera, ((path, ts), frame)) in set.files.iter().zip(out.frames.iter_mut()).enumerate() {
            read_file(path, &mut self.buf).map_err(|e| SourceError::CameraLost {
                camera,
                device: path.display().to_string(),
                reason: e.to_string(),
            })?;
            frame.decode_pgm(&self.buf).map_err(|e| SourceError::CameraLost {
                camera,
                device: path.display().to_string(),
                reason: e.to_string(),
            })?;
            frame.timestamp_ns = match self.cfg.speed {
                ReplaySpeed::Recorded => mapped(*ts),
                ReplaySpeed::Max => now_max.saturating_sub(rec_ts - *ts),
            };
            frame.sequence = set.frame;
            min_ts = min_ts.min(*ts);
            max_ts = max_ts.max(*ts);
        }
        out.index = set.frame;
        out.pairing_error_ns = max_ts.saturating_sub(min_ts);
        self.next += 1;
        self.stats.sets_delivered += 1;
        self.stats.sets_dropped = self.skipped_frames + self.unreadable;
        Ok(())
    }
}
