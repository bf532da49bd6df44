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
    /// The recording's cameras this source replays (`cam<N>/` of `dir`), in this board's
    /// camera order: a camera board's share of a multi-board recording (`[2, 3]`). Default:
    /// every `cam<N>/` from `cam0/` up. With it, `timestamps.csv` may (and for a shared time
    /// base should) hold the whole recording's rows: the other cameras' rows fix the origin.
    #[serde(default)]
    pub cameras: Option<Vec<usize>>,
    /// Play the recording on the shared clock: the recorded instant `origin_ns` plays at this
    /// CLOCK_REALTIME instant (Unix seconds), every other frame at its recorded distance from
    /// it, so boards replaying parts of one recording keep its time base (docs/cluster.md,
    /// "Replaying a multi-board recording"). A source started after it joins where the
    /// recording is then. Unset: the first set plays when the source starts.
    #[serde(default)]
    pub start_at_unix_s: Option<f64>,
    /// With `start_at_unix_s`: the recorded instant (ns, the recording's clock) that plays at
    /// it. Default: the earliest timestamp of `timestamps.csv` (every camera's rows, dropped
    /// ones left out), the same on every board that has the same file.
    #[serde(default)]
    pub origin_ns: Option<u64>,
    /// Hold at the first frame until a parameter set is active (said on `/status`), so the
    /// recording is not consumed before positions can be computed from it.
    #[serde(default)]
    pub wait_for_params: bool,
    /// Hold at the first frame until a position stream client (NDJSON or binary) is connected.
    #[serde(default)]
    pub wait_for_client: bool,
}

impl Default for ReplayConfig {
    fn default() -> Self {
        ReplayConfig {
            dir: PathBuf::new(),
            speed: ReplaySpeed::Recorded,
            repeat: false,
            fps: None,
            cameras: None,
            start_at_unix_s: None,
            origin_ns: None,
            wait_for_params: false,
            wait_for_client: false,
        }
    }
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

/// Where the replay's first set is played: when the source starts, or on the shared clock.
#[derive(Debug, Clone, Copy)]
struct SharedStart {
    /// CLOCK_REALTIME ns at which the recorded instant `origin_ns` plays.
    start_rt_ns: i128,
    /// The recorded instant played at `start_rt_ns`.
    origin_ns: u64,
    /// Length of one pass through the recording (its span plus one frame period), ns: a
    /// repeating replay's pass `k` plays `k` of these later.
    cycle_ns: u64,
    /// The pass being played (repeat), decided at the first set from the clock.
    cycle: Option<u64>,
}

/// A [`FrameSource`] over a recorded directory.
pub struct ReplaySource {
    cfg: ReplayConfig,
    sets: Vec<RecordedSet>,
    cameras: usize,
    /// The recording's camera (`cam<N>/`) of each of this source's cameras.
    recording_cameras: Vec<usize>,
    next: usize,
    buf: Vec<u8>,
    stats: SourceStats,
    /// Recorded timestamps that were dropped at recording time (frames skipped on replay).
    skipped_frames: u64,
    /// (monotonic ns at the first delivered set, its recorded timestamp)
    epoch: Option<(u64, u64)>,
    /// `start_at_unix_s`: the recording is played on the shared clock.
    shared: Option<SharedStart>,
    /// Sets passed over on the shared clock because their time had passed (a source started
    /// after `start_at_unix_s`, or a loop more than a frame behind).
    late_skipped: u64,
    /// Median interval between the recorded sets, ns.
    period_ns: u64,
    template: FrameSet,
    timing: ReplayTiming,
    /// Sets skipped because a frame file could not be read or decoded (first path and reason
    /// kept for the end-of-replay summary).
    unreadable: u64,
    first_unreadable: Option<String>,
    /// The loop's status: what `wait_for_params` / `wait_for_client` look at, and where the
    /// waiting is said.
    status: Option<std::sync::Arc<crate::status::SharedStatus>>,
    /// The first set has been released (nothing more to wait for).
    released: bool,
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

/// CLOCK_REALTIME now, ns since the Unix epoch.
fn realtime_ns() -> i128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as i128)
}

/// The recording cameras a source replays: `cfg.cameras` checked, else `cam0/`, `cam1/`, ...
fn recording_cameras(cfg: &ReplayConfig) -> Result<Vec<usize>, SourceError> {
    let dir = &cfg.dir;
    match &cfg.cameras {
        Some(list) => {
            if list.is_empty() {
                return Err(SourceError::Config(
                    "[source.replay] cameras is empty: list the recording's cameras this board replays, e.g. [2, 3]".into(),
                ));
            }
            for (i, c) in list.iter().enumerate() {
                if list[..i].contains(c) {
                    return Err(SourceError::Config(format!(
                        "[source.replay] cameras lists camera {c} twice"
                    )));
                }
                if !dir.join(format!("cam{c}")).is_dir() {
                    return Err(SourceError::Config(format!(
                        "[source.replay] cameras lists camera {c}, but {} has no cam{c}/ subdirectory",
                        dir.display()
                    )));
                }
            }
            Ok(list.clone())
        }
        None => {
            let mut n = 0;
            while dir.join(format!("cam{n}")).is_dir() {
                n += 1;
            }
            if n == 0 {
                return Err(SourceError::Config(format!(
                    "replay directory {} has no cam0/ subdirectory",
                    dir.display()
                )));
            }
            Ok((0..n).collect())
        }
    }
}

/// Median of the positive intervals between the sets' latest timestamps, ns.
fn median_interval_ns(sets: &[RecordedSet]) -> Option<u64> {
    let t = |s: &RecordedSet| s.files.iter().map(|(_, ts)| *ts).max().unwrap_or(0);
    let mut intervals: Vec<u64> = sets
        .windows(2)
        .filter_map(|w| t(&w[1]).checked_sub(t(&w[0])).filter(|d| *d > 0))
        .collect();
    if intervals.is_empty() {
        return None;
    }
    intervals.sort_unstable();
    Some(intervals[intervals.len() / 2])
}

impl ReplaySource {
    /// Finds the camera directories and the complete sets under `cfg.dir`; refuses a
    /// directory without any.
    pub fn open(cfg: &ReplayConfig) -> Result<Self, SourceError> {
        let dir = &cfg.dir;
        let recording_cameras = recording_cameras(cfg)?;
        let cameras = recording_cameras.len();
        let local = |c: usize| recording_cameras.iter().position(|&x| x == c);
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
        if let Some(s) = cfg.start_at_unix_s {
            if !(s.is_finite() && s > 0.0) {
                return Err(SourceError::Config(format!(
                    "[source.replay] start_at_unix_s = {s} must be a positive CLOCK_REALTIME instant in seconds since 1970"
                )));
            }
            if cfg.speed == ReplaySpeed::Max {
                return Err(SourceError::Config(
                    "[source.replay] start_at_unix_s plays the recording on the shared clock; it needs speed = \"recorded\"".into(),
                ));
            }
        }
        // Earliest and latest recorded instant of the whole recording (every camera's rows):
        // the shared origin and the length of one pass.
        let (mut earliest_ns, mut latest_ns) = (u64::MAX, 0u64);
        let sets = if ts_path.exists() {
            let text = std::fs::read_to_string(&ts_path).map_err(io(&ts_path))?;
            // frame -> per-camera (timestamp, dropped)
            let mut by_frame: BTreeMap<u64, Vec<Option<(u64, bool)>>> = BTreeMap::new();
            for (lineno, line) in text.lines().enumerate() {
                let line = line.trim();
                if line.is_empty() || line.starts_with("frame") || line.starts_with('#') {
                    continue;
                }
                let bad = |why: &str| {
                    SourceError::Config(format!(
                        "{}:{}: expected `frame,camera,timestamp_ns,dropped`, got `{line}`{why}",
                        ts_path.display(),
                        lineno + 1
                    ))
                };
                let mut it = line.split(',').map(str::trim);
                let mut num = || {
                    it.next()
                        .and_then(|s| s.parse::<u64>().ok())
                        .ok_or_else(|| bad(""))
                };
                let (frame, camera, ts, dropped) = (num()?, num()?, num()?, num()?);
                let camera = usize::try_from(camera).map_err(|_| bad(""))?;
                if dropped == 0 {
                    earliest_ns = earliest_ns.min(ts);
                    latest_ns = latest_ns.max(ts);
                }
                let Some(local) = local(camera) else {
                    if cfg.cameras.is_some() {
                        // Another board's camera: its rows only fix the shared origin.
                        continue;
                    }
                    return Err(bad(&format!(
                        " (camera {camera} has no cam{camera}/ directory; to replay some cameras of a larger recording, list them in [source.replay] cameras)"
                    )));
                };
                by_frame.entry(frame).or_insert_with(|| vec![None; cameras])[local] =
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
                    .zip(&recording_cameras)
                    .map(|(v, &c)| (frame_path(dir, c, frame), v.map_or(0, |(ts, _)| ts)))
                    .collect();
                sets.push(RecordedSet { frame, files });
            }
            sets
        } else {
            // No timestamps: every frame number present in the first camera, spaced by `fps`.
            let cam0 = dir.join(format!("cam{}", recording_cameras[0]));
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
            if let (Some(first), Some(last)) = (frames.first(), frames.last()) {
                earliest_ns = first.saturating_mul(period_ns);
                latest_ns = last.saturating_mul(period_ns);
            }
            frames
                .into_iter()
                .map(|frame| RecordedSet {
                    frame,
                    files: recording_cameras
                        .iter()
                        .map(|&c| (frame_path(dir, c, frame), frame.saturating_mul(period_ns)))
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
        let period_ns = median_interval_ns(&sets).unwrap_or((1e9 / DEFAULT_REPLAY_FPS) as u64);
        let shared = cfg.start_at_unix_s.map(|s| {
            let origin_ns = cfg.origin_ns.unwrap_or(earliest_ns.min(latest_ns));
            SharedStart {
                start_rt_ns: (s * 1e9).round() as i128,
                origin_ns,
                cycle_ns: latest_ns.saturating_sub(origin_ns).saturating_add(period_ns),
                cycle: None,
            }
        });
        if let Some(sh) = &shared {
            tracing::info!(
                dir = %dir.display(),
                origin_ns = sh.origin_ns,
                start_at_unix_s = cfg.start_at_unix_s.unwrap_or(0.0),
                "replay on the shared clock: recorded instant origin_ns plays at start_at_unix_s"
            );
        }
        Ok(Self {
            cfg: cfg.clone(),
            sets,
            cameras,
            recording_cameras,
            next: 0,
            buf,
            stats: SourceStats::default(),
            skipped_frames,
            epoch: None,
            shared,
            late_skipped: 0,
            period_ns,
            template,
            timing,
            unreadable: 0,
            first_unreadable: None,
            status: None,
            released: !(cfg.wait_for_params || cfg.wait_for_client),
        })
    }

    /// The recorded instant played at `start_at_unix_s` (ns on the recording's clock), when
    /// the replay runs on the shared clock.
    pub fn origin_ns(&self) -> Option<u64> {
        self.shared.map(|s| s.origin_ns)
    }

    /// Sets passed over on the shared clock because their time had already passed.
    pub fn late_skipped(&self) -> u64 {
        self.late_skipped
    }

    /// Where the replay's timing comes from.
    pub fn timing(&self) -> &ReplayTiming {
        &self.timing
    }

    /// The recording's frame rate: the median interval between its sets' timestamps
    /// (`timestamps.csv`, or the configured pace without one); `None` with fewer than two sets.
    pub fn recorded_fps(&self) -> Option<f64> {
        median_interval_ns(&self.sets).map(|ns| 1e9 / ns as f64)
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
            self.stats.sets_dropped = self.skipped_frames + self.unreadable + self.late_skipped;
        }
        result
    }

    fn attach_status(&mut self, status: &std::sync::Arc<crate::status::SharedStatus>) {
        self.status = Some(status.clone());
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    fn describe(&self) -> String {
        let cameras = if self.cfg.cameras.is_some() {
            format!("cameras {:?} of the recording", self.recording_cameras)
        } else {
            format!("{} cameras", self.cameras)
        };
        format!(
            "replay of {} ({cameras}, {} sets, {:?} speed{}; {})",
            self.cfg.dir.display(),
            self.sets.len(),
            self.cfg.speed,
            if self.cfg.repeat { ", repeating" } else { "" },
            if self.cfg.speed == ReplaySpeed::Max {
                "as fast as processed".to_string()
            } else if let Some(sh) = &self.shared {
                format!(
                    "{}; on the shared clock: recorded {} ns plays at Unix {:.3} s",
                    self.timing,
                    sh.origin_ns,
                    sh.start_rt_ns as f64 / 1e9
                )
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
        if self.late_skipped > 0 {
            s += &format!(
                "; {} sets passed over because their time on the shared clock (start_at_unix_s) had passed when they were due",
                self.late_skipped
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

/// How long `next_set` waits at the first frame before returning to the loop with
/// [`SourceError::Waiting`] (so the loop stays responsive to shutdown).
const WAIT_POLL_MS: u64 = 100;

impl ReplaySource {
    /// What the first set still waits for, in words (`wait_for_params`, `wait_for_client`);
    /// `None` when nothing.
    fn waiting_for(&self) -> Option<String> {
        let status = self.status.as_ref()?;
        let mut missing = Vec::new();
        if self.cfg.wait_for_params && !status.params_loaded.load(std::sync::atomic::Ordering::Relaxed) {
            missing.push("a parameter set (push one with host-tools push-params)");
        }
        if self.cfg.wait_for_client && status.stream_clients.load(std::sync::atomic::Ordering::Relaxed) == 0 {
            missing.push("a position stream client (NDJSON or binary)");
        }
        if missing.is_empty() {
            return None;
        }
        Some(format!(
            "replay of {} holds at its first frame until {} ([source.replay] {})",
            self.cfg.dir.display(),
            missing.join(" and "),
            match (self.cfg.wait_for_params, self.cfg.wait_for_client) {
                (true, true) => "wait_for_params, wait_for_client",
                (true, false) => "wait_for_params",
                _ => "wait_for_client",
            }
        ))
    }

    /// Holds the first set while something it waits for is missing; sets and clears the
    /// status's words.
    fn hold_first_set(&mut self) -> Result<(), SourceError> {
        let until = clock::monotonic_ns() + WAIT_POLL_MS * 1_000_000;
        loop {
            let Some(reason) = self.waiting_for() else {
                self.released = true;
                if let Some(st) = &self.status
                    && let Ok(mut w) = st.source_waiting.lock()
                    && w.take().is_some()
                {
                    tracing::info!(dir = %self.cfg.dir.display(), "replay released: starting at its first frame");
                }
                return Ok(());
            };
            if clock::monotonic_ns() >= until {
                if let Some(st) = &self.status
                    && let Ok(mut w) = st.source_waiting.lock()
                    && w.as_deref() != Some(reason.as_str())
                {
                    tracing::info!("{reason}");
                    *w = Some(reason.clone());
                }
                return Err(SourceError::Waiting { reason });
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
    }

    /// On the shared clock: moves `next` to the first set not yet past (counting the ones
    /// passed over) and returns the offset that maps a recorded timestamp onto
    /// CLOCK_MONOTONIC for it.
    fn shared_place(&mut self) -> Result<i128, SourceError> {
        let Some(mut sh) = self.shared else {
            return Ok(0);
        };
        let rt_minus_mono = clock::realtime_minus_mono_ns();
        if sh.cycle.is_none() {
            // A repeating replay started several passes after start_at joins the pass now
            // playing, not the first.
            let behind_ns = realtime_ns() - sh.start_rt_ns;
            sh.cycle = Some(if self.cfg.repeat && behind_ns > 0 && sh.cycle_ns > 0 {
                (behind_ns / i128::from(sh.cycle_ns)) as u64
            } else {
                0
            });
        }
        let now_mono = i128::from(clock::monotonic_ns());
        loop {
            if self.next >= self.sets.len() {
                if !self.cfg.repeat {
                    self.shared = Some(sh);
                    return Err(SourceError::EndOfStream);
                }
                self.next = 0;
                sh.cycle = Some(sh.cycle.unwrap_or(0) + 1);
            }
            let to_mono = sh.start_rt_ns - i128::from(sh.origin_ns)
                + i128::from(sh.cycle.unwrap_or(0)) * i128::from(sh.cycle_ns)
                - rt_minus_mono;
            let set = &self.sets[self.next];
            let rec_ts = set.files.iter().map(|(_, ts)| *ts).max().unwrap_or(0);
            let due_mono = i128::from(rec_ts) + to_mono;
            // More than a frame period past: its time is gone; the boards that played it
            // on time have paired it without this one. Pass over it (no file is read).
            if now_mono > due_mono + i128::from(self.period_ns) {
                self.late_skipped += 1;
                self.next += 1;
                continue;
            }
            self.shared = Some(sh);
            return Ok(to_mono);
        }
    }

    fn try_next_set(&mut self, out: &mut FrameSet) -> Result<(), SourceError> {
        if !self.released {
            self.hold_first_set()?;
        }
        if self.shared.is_some() {
            let to_mono = self.shared_place()?;
            return self.deliver(out, |ts| (i128::from(ts) + to_mono).max(0) as u64, true);
        }
        if self.next >= self.sets.len() {
            if !self.cfg.repeat {
                return Err(SourceError::EndOfStream);
            }
            self.next = 0;
            self.epoch = None;
        }
        let rec_ts = self.sets[self.next]
            .files
            .iter()
            .map(|(_, ts)| *ts)
            .max()
            .unwrap_or(0);
        let now = clock::monotonic_ns();
        let (epoch_mono, epoch_rec) = *self.epoch.get_or_insert((now, rec_ts));
        match self.cfg.speed {
            // Signed: a camera stamped before the first set's latest frame (free-running
            // cameras' skew, docs/simulator.md "Camera timing") keeps its offset instead of
            // clamping to it.
            ReplaySpeed::Recorded => self.deliver(
                out,
                |ts| epoch_mono.saturating_add_signed(ts.wrapping_sub(epoch_rec) as i64),
                true,
            ),
            // At maximum speed the set is stamped now, each camera keeping its recorded skew
            // from the set's latest frame (the tracker places every camera's frame at its own
            // instant).
            ReplaySpeed::Max => {
                let now_max = clock::monotonic_ns();
                self.deliver(out, |ts| now_max.saturating_sub(rec_ts.saturating_sub(ts)), false)
            }
        }
    }

    /// Reads set `next` into `out`, each camera's timestamp mapped by `mapped`; with `pace`
    /// it waits until the set's latest frame is due.
    fn deliver(
        &mut self,
        out: &mut FrameSet,
        mapped: impl Fn(u64) -> u64,
        pace: bool,
    ) -> Result<(), SourceError> {
        if out.frames.len() != self.cameras {
            return Err(SourceError::Config(format!(
                "frame set has {} frames, source has {} cameras",
                out.frames.len(),
                self.cameras
            )));
        }
        let set = &self.sets[self.next];
        let rec_ts = set.files.iter().map(|(_, ts)| *ts).max().unwrap_or(0);
        if pace {
            clock::sleep_until_ns(mapped(rec_ts));
        }
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
            frame.timestamp_ns = mapped(*ts);
            frame.sequence = set.frame;
            min_ts = min_ts.min(*ts);
            max_ts = max_ts.max(*ts);
        }
        out.index = set.frame;
        out.pairing_error_ns = max_ts.saturating_sub(min_ts);
        self.next += 1;
        self.stats.sets_delivered += 1;
        self.stats.sets_dropped = self.skipped_frames + self.unreadable + self.late_skipped;
        Ok(())
    }
}
