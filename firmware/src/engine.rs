//! The processing loop: a dedicated thread (not a tokio task) that turns frame sets into
//! position records.
//!
//! Per set: `next_set` → blob detection per camera → solve (centroids, undistort, triangulate,
//! the tracker's quality gate) → record → latest-value slot. Everything the loop touches per set
//! is allocated up front (frame buffers, tracker buffers) and shared state is atomics, so steady
//! state does not allocate (checked by `tests/no_alloc.rs`). Parameter swaps are picked up
//! between sets by comparing a generation counter; only then does the loop take a lock.
//!
//! When the active parameter set defines multi-LED tools (`RigParams.tools`), the loop runs
//! in 6-DOF mode: every frame is searched in full (the single-marker tracking window would
//! cut off the other LEDs) and the tracker's blob lists go to a [`MultiTracker`], which tracks
//! every tool of the set (up to [`MAX_TOOLS`]) plus loose single LEDs. The main record carries
//! the pose of the robot's tool (`[robot] tool`, default the first tool); the records of all
//! tools and of the loose LEDs (with their stable ids) go to the per-tool slot ([`ToolSet`], see
//! [`Engine::with_tool_slot`]).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use irtrack_core::blob::Blob;
use irtrack_core::camera::RigidTransform;
use irtrack_core::image::GrayImage;
use irtrack_core::params::RigParams;
use irtrack_core::pipeline::{
    MAX_CAMERAS, Measurement, TrackStatus as MeasureStatus, Tracker, TrackerConfig,
};
use irtrack_core::pose6d::{
    LOOSE_LED, MAX_LOOSE_LEDS, MAX_TOOLS, MultiTracker, NO_TOOL, Pose6d, PoseConfig, PoseStatus,
};
use irtrack_core::retime::TimeMode;
use irtrack_core::stream::{LooseRecord, PositionRecord, ToolRecord, TrackStatus};
use irtrack_core::timing::CameraTiming;
use tokio::sync::watch;

use crate::clock;
use crate::error::{FirmwareError, Result};
use crate::frame_clocks::FrameClocks;
use crate::leds::indication::TrackIndication;
use crate::source::{FrameSet, FrameSource, Pixels, SourceError};
use crate::status::SharedStatus;
use crate::tuning::TuningHandle;
use crate::viewer::{BlobCopy, BlobView, RejectReason, TapSet, ViewerTap};

const R: Ordering = Ordering::Relaxed;

/// A parameter set ready for the loop.
#[derive(Debug)]
pub struct ActiveParams {
    /// The validated rig parameters (cameras, registration, tools).
    pub rig: RigParams,
    /// Header CRC of the blob (the set's short id in records).
    pub crc: u32,
}

/// Hand-over point for parameter sets between the parameter service and the loop.
#[derive(Debug, Default)]
pub struct ParamsHandle {
    current: Mutex<Option<Arc<ActiveParams>>>,
    generation: AtomicU64,
}

impl ParamsHandle {
    /// A handle with no set installed yet (the loop tracks nothing until one is).
    pub fn new() -> Self {
        Self::default()
    }

    /// Makes `params` the active set; the loop switches before its next frame set.
    pub fn install(&self, params: ActiveParams) {
        if let Ok(mut g) = self.current.lock() {
            *g = Some(Arc::new(params));
            self.generation.fetch_add(1, Ordering::Release);
        }
    }

    /// Count of installs so far; the loop compares it with the one it last saw to notice a
    /// new set without taking the lock.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    /// The set installed last, if any.
    pub fn current(&self) -> Option<Arc<ActiveParams>> {
        self.current.lock().ok().and_then(|g| g.clone())
    }
}

/// The timestamps of one set's path through irtrackd (CLOCK_MONOTONIC ns; 0 = not reached).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SetTimes {
    /// The frame's capture timestamp: the V4L2 buffer's driver timestamp, or the simulator's
    /// hand-over instant (first camera).
    pub capture_ns: u64,
    /// Time the source spent producing the set before `capture_ns` (simulator rendering).
    pub render_ns: u64,
    /// The loop received the set from the source.
    pub dequeued_ns: u64,
    /// Blob detection done in every camera.
    pub blobs_ns: u64,
    /// Undistorted and triangulated (or the 6-DOF pose solved).
    pub triangulated_ns: u64,
    /// Record in the latest-value slot (the robot links and the stream can take it).
    pub published_ns: u64,
    /// The loop finished with the set (after the viewers' copy, if one was due).
    pub done_ns: u64,
}

impl SetTimes {
    /// Dequeued → published: irtrackd's own share of the latency.
    pub fn ours_ns(&self) -> u64 {
        self.published_ns.saturating_sub(self.dequeued_ns)
    }

    /// Capture → dequeued: the driver's (or the pairing's) share.
    pub fn driver_ns(&self) -> u64 {
        self.dequeued_ns.saturating_sub(self.capture_ns)
    }
}

/// The records of every tool and loose LED of one frame set (fixed size, `Copy`: handed over
/// through a latest-value slot without allocation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolSet {
    /// Frame-set number (the main record's `frame`).
    pub frame: u64,
    /// Tools of the parameter set; `tools[..count]` are filled, in definition order.
    pub count: u8,
    /// The records (`None` past `count`).
    pub tools: [Option<ToolRecord>; MAX_TOOLS],
    /// Loose single LEDs seen in this set (belonging to no tool); `loose[..loose_leds]` are
    /// filled, by increasing id.
    pub loose_leds: u8,
    /// The loose LEDs' records (`None` past `loose_leds`).
    pub loose: [Option<LooseRecord>; MAX_LOOSE_LEDS],
}

impl ToolSet {
    /// No set yet (the slot's initial value): no tools, no loose LEDs, a frame no set has.
    pub const EMPTY: ToolSet = ToolSet {
        frame: u64::MAX,
        count: 0,
        tools: [None; MAX_TOOLS],
        loose_leds: 0,
        loose: [None; MAX_LOOSE_LEDS],
    };

    /// The filled records, in definition order.
    pub fn records(&self) -> impl Iterator<Item = &ToolRecord> {
        self.tools.iter().take(usize::from(self.count)).flatten()
    }

    /// The loose LEDs' records, by increasing id.
    pub fn loose_records(&self) -> impl Iterator<Item = &LooseRecord> {
        self.loose.iter().take(usize::from(self.loose_leds)).flatten()
    }
}

/// Index of the robot's tool among `names`: the one called `wanted`, else the first. An
/// unknown name is an error naming it and the known names.
pub fn robot_tool_index<'a>(
    wanted: Option<&str>,
    names: impl Iterator<Item = &'a str> + Clone,
) -> std::result::Result<usize, String> {
    let Some(w) = wanted else { return Ok(0) };
    names.clone().position(|n| n == w).ok_or_else(|| {
        let known: Vec<&str> = names.collect();
        format!(
            "[robot] tool = {w:?} is not a tool of the parameter set (its tools: {})",
            if known.is_empty() {
                "none".to_string()
            } else {
                known
                    .iter()
                    .map(|n| format!("{n:?}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        )
    })
}

/// What one [`Engine::step`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum StepOutcome {
    /// A set was processed and a record published.
    Published(PositionRecord),
    /// The source reported a (retried) error, and a fault record was published; or it holds
    /// its first set on purpose (a replay waiting, `SourceError::Waiting`), publishing nothing.
    SourceError,
    /// The source has no more frames (replay end, frame limit).
    EndOfStream,
}

/// The processing loop's state. Build with [`Engine::new`], then [`Engine::run`] on a thread
/// (or [`Engine::step`] from tests).
pub struct Engine {
    source: Box<dyn FrameSource>,
    set: FrameSet,
    tracker_cfg: TrackerConfig,
    tracker: Option<Tracker>,
    /// 6-DOF mode: the tracker of every tool of the active set.
    pose_cfg: PoseConfig,
    pose: Option<MultiTracker>,
    /// `[robot] tool`: the tool whose pose the main record carries (None: the first).
    robot_tool_name: Option<String>,
    /// Its index in the active set (None: the set lacks it; the main record is a fault).
    robot_tool: Option<usize>,
    /// Every tool's record per set (see [`ToolSet`]).
    tool_out: Option<watch::Sender<ToolSet>>,
    params: Arc<ParamsHandle>,
    seen_generation: u64,
    world_from_cam0: Option<RigidTransform>,
    params_crc: u32,
    out: watch::Sender<Option<PositionRecord>>,
    status: Arc<SharedStatus>,
    deadline_ns: u64,
    /// Sets whose cameras' capture times differ by more than this give no position.
    max_pairing_error_ns: u64,
    consecutive_errors: u32,
    /// Capture time of the last processed set: older or repeated sets are never published.
    /// (Time, not index: a repeating replay restarts its indices with newer timestamps.)
    last_capture_ns: Option<u64>,
    /// Latest-only copies for the set-up view (see [`crate::viewer`]).
    tap: Option<Arc<ViewerTap>>,
    tap_last_ns: u64,
    /// Live tuning from the set-up view (see [`crate::tuning`]).
    tuning: Option<Arc<TuningHandle>>,
    tuning_seen: u64,
    /// Source reconnects already reflected in the tuning report.
    reconnects_seen: u64,
    /// The source's `controls_generation` already reflected in the tuning report.
    controls_seen: u64,
    /// Timestamps of the last processed set.
    times: SetTimes,
    /// Cluster camera role: every camera's blobs go to the solver (docs/cluster.md).
    observation_sink: Option<Box<dyn ObservationSink>>,
    /// Cluster camera role without a parameter set of its own (e.g. one camera): the tracker
    /// only detects; the records carry no position.
    detection_only: bool,
    /// Each camera's clock model (docs/timing.md, "Camera clocks"); allocated with the set.
    clocks: Option<FrameClocks>,
    /// Each camera's timing from the config (`[[camera_timing]]`, or the simulated source's
    /// own); a parameter set that carries timing wins (docs/timing.md, "Which win").
    config_timing: Vec<CameraTiming>,
}

/// Receives each camera's blobs right after detection (cluster role "camera": publishes them).
pub trait ObservationSink: Send {
    /// `camera`'s `frame` was detected with `blobs`; `dropped`: sets the source skipped so far.
    fn observe(&mut self, camera: usize, frame: &crate::source::Frame, blobs: &[Blob], dropped: u64);
}

impl Engine {
    /// A loop over `source` that tracks with the set in `params`, publishes each record to
    /// `out` and its counters to `status`; a set whose processing exceeds `deadline` counts
    /// as late. Allocates the frame-set buffers once, here.
    pub fn new(
        source: Box<dyn FrameSource>,
        tracker_cfg: TrackerConfig,
        params: Arc<ParamsHandle>,
        out: watch::Sender<Option<PositionRecord>>,
        status: Arc<SharedStatus>,
        deadline: Duration,
    ) -> Self {
        let mut source = source;
        source.attach_status(&status);
        let set = source.allocate_set();
        for (c, f) in status.cameras.iter().zip(&set.frames) {
            c.width_px.store(u64::from(f.width_px), R);
            c.height_px.store(u64::from(f.height_px), R);
        }
        let deadline_ns = u64::try_from(deadline.as_nanos()).unwrap_or(u64::MAX);
        status.deadline_ns.store(deadline_ns, R);
        let clocks = FrameClocks::new(set.frames.len(), None).ok();
        publish_timing(&status, &tracker_cfg);
        Self {
            source,
            set,
            tracker_cfg,
            tracker: None,
            pose_cfg: PoseConfig::default(),
            pose: None,
            robot_tool_name: None,
            robot_tool: Some(0),
            tool_out: None,
            params,
            seen_generation: 0,
            world_from_cam0: None,
            params_crc: 0,
            out,
            status,
            deadline_ns,
            max_pairing_error_ns: deadline_ns / 2,
            consecutive_errors: 0,
            last_capture_ns: None,
            tap: None,
            tap_last_ns: 0,
            tuning: None,
            tuning_seen: 0,
            reconnects_seen: 0,
            controls_seen: 0,
            times: SetTimes::default(),
            observation_sink: None,
            detection_only: false,
            clocks,
            config_timing: Vec::new(),
        }
    }

    /// Each camera's timing from the config (camera order; missing cameras: global shutter,
    /// no offset). Used while the parameter set carries no timing of its own.
    pub fn with_camera_timing(mut self, timing: Vec<CameraTiming>) -> Self {
        self.config_timing = timing;
        self
    }

    /// The source's configured frame rate, for the cameras' rate error in ppm (`/status`).
    pub fn with_nominal_fps(mut self, fps: Option<f64>) -> Self {
        self.clocks = FrameClocks::new(self.set.frames.len(), fps).ok();
        self
    }

    /// Timestamps of the last processed set's path.
    pub fn last_times(&self) -> SetTimes {
        self.times
    }

    /// Hands every camera's detected blobs to `sink` (cluster camera role).
    pub fn with_observation_sink(mut self, sink: Box<dyn ObservationSink>) -> Self {
        self.observation_sink = Some(sink);
        self
    }

    /// Feeds `tap` with copies of processed sets while viewers ask for them.
    pub fn with_viewer_tap(mut self, tap: Arc<ViewerTap>) -> Self {
        tap.set_template(self.source.allocate_set());
        self.tap = Some(tap);
        self
    }

    /// Applies live tuning from `tuning` between sets.
    pub fn with_tuning(mut self, tuning: Arc<TuningHandle>) -> Self {
        let bits = self.set.frames.first().map_or(8, |f| f.bit_depth);
        tuning.set_max_dn((1u32 << bits.min(16)) - 1);
        tuning.report_cameras(self.source.controls(), None);
        self.tuning = Some(tuning);
        self
    }

    /// Picks up a tuning change (locks and may allocate only when the operator changed
    /// something).
    fn refresh_tuning(&mut self) {
        let Some(tuning) = &self.tuning else { return };
        let generation = tuning.generation();
        if generation == self.tuning_seen {
            return;
        }
        self.tuning_seen = generation;
        let Some(req) = tuning.take() else { return };
        let mut error = None;
        let mut tracking = req.tracking;
        let six_dof = self.pose.is_some();
        match &mut self.tracker {
            Some(t) => match t.set_config({
                // In 6-DOF mode the blob limit follows the tools (see `refresh_params`).
                if six_dof {
                    tracking.max_blobs = t.config().max_blobs;
                }
                tracking
            }) {
                Ok(()) => self.tracker_cfg = req.tracking,
                Err(e) => error = Some(format!("detector settings refused: {e}")),
            },
            None => self.tracker_cfg = req.tracking,
        }
        publish_timing(&self.status, &self.tracker_cfg);
        // A solver's own cameras detect on a thread of their own: they take the settings too.
        if let Err(e) = self.source.set_detection(&req.tracking) {
            tracing::warn!(error = %e, "detector settings refused by the source");
            error = Some(e.to_string());
        }
        for (camera, control, value) in req.pending {
            match self.source.set_control(camera, control, value) {
                Ok(()) => tracing::info!(camera, ?control, value, "camera control changed"),
                Err(e) => {
                    tracing::warn!(camera, ?control, value, error = %e, "camera control refused");
                    error = Some(e.to_string());
                }
            }
        }
        tuning.report_cameras(self.source.controls(), error);
        tracing::info!(
            threshold_dn = self.tracker_cfg.threshold_dn,
            min_area_px = self.tracker_cfg.min_area_px,
            max_area_px = self.tracker_cfg.max_area_px,
            "tuning applied"
        );
    }

    /// Copies what viewers asked for into the viewer tap (never waits): the blob lists of
    /// every set while a viewer wants them (a few kB), the frames only when a frame copy is
    /// due (the fastest preview rate asked for, or a one-off request). `detected`: the
    /// tracker's blob lists belong to this set.
    fn feed_tap(&mut self, detected: bool) {
        let Some(tap) = &self.tap else { return };
        // Pixels captured elsewhere (a solver's own cameras) are brought in only for a frame
        // copy, never per set.
        if tap.wants_copy(clock::monotonic_ns(), self.tap_last_ns) {
            self.source.refresh_pixels(&mut self.set);
        }
        let Some(tap) = &self.tap else { return };
        let source = self.source.as_ref();
        let (set, tracker, six_dof) = (&self.set, self.tracker.as_ref(), self.pose.as_ref());
        let lists = tracker.filter(|_| detected);
        if tap.wants_blobs() {
            tap.try_fill_blobs(|buf: &mut BlobCopy| {
                if !buf.begin(set) {
                    return false;
                }
                if let Some(tracker) = lists {
                    fill_blob_views(tracker, six_dof, |c, b| buf.push_blob(c, b));
                    buf.detected = true;
                }
                true
            });
        }
        let now_ns = clock::monotonic_ns();
        if !tap.wants_copy(now_ns, self.tap_last_ns) {
            return;
        }
        // The limits in force (6-DOF mode raises the blob limit): what the advice must judge by.
        let tracker_cfg = self.tracker.as_ref().map_or(self.tracker_cfg, |t| *t.config());
        let copied = tap.try_fill(|buf: &mut TapSet| {
            if !buf.copy_frames_from(set) {
                return false;
            }
            buf.threshold_dn = tracker_cfg.threshold_dn;
            buf.tracker_cfg = tracker_cfg;
            for (c, p) in buf.has_pixels.iter_mut().enumerate() {
                *p = source.has_pixels(c);
            }
            buf.expected_leds = crate::advice::expected_leds(six_dof);
            if let Some(tracker) = lists {
                fill_blob_views(tracker, six_dof, |c, b| buf.push_blob(c, b));
                buf.detected = true;
            }
            true
        });
        if copied {
            // Due times on a grid of the interval, so the copies keep the asked rate on
            // average even though sets arrive at the camera's rate; after a pause (no
            // viewer, a skipped copy) the grid restarts now.
            let interval = tap.interval_ns();
            let next_from_grid = self.tap_last_ns.saturating_add(interval);
            self.tap_last_ns = if interval > 0 && now_ns.saturating_sub(self.tap_last_ns) < 2 * interval {
                next_from_grid
            } else {
                now_ns
            };
        }
    }

    /// The tool the main record (and so the robot link) follows: `[robot] tool`; None = the
    /// set's first tool.
    pub fn with_robot_tool(mut self, name: Option<String>) -> Self {
        self.robot_tool_name = name;
        self
    }

    /// Publishes every tool's record of each set to `slot` (6-DOF mode only), just before the
    /// main record.
    pub fn with_tool_slot(mut self, slot: watch::Sender<ToolSet>) -> Self {
        self.tool_out = Some(slot);
        self
    }

    /// Settings of the 6-DOF tracker (`[pose]`), used for sets that define a tool.
    pub fn with_pose_config(mut self, cfg: PoseConfig) -> Self {
        self.pose_cfg = cfg;
        self
    }

    /// Largest capture-time difference between the cameras of one set that still gives a
    /// position (default: half the deadline).
    pub fn with_max_pairing_error(mut self, max: Duration) -> Self {
        self.max_pairing_error_ns = u64::try_from(max.as_nanos()).unwrap_or(u64::MAX);
        self
    }

    /// Detects blobs without a parameter set (cluster camera role: 1..=8 cameras of any
    /// image size) until one is installed; the records meanwhile carry no position and the
    /// missing set is not a fault. A set installed later (a board with two or more cameras)
    /// makes it a full tracker with positions of its own.
    pub fn with_detection_only(mut self) -> Result<Self> {
        if self.tracker.is_some() || self.params.current().is_some() {
            return Ok(self);
        }
        let sizes = self.set.image_sizes();
        let tracker =
            Tracker::detection_only(&sizes, self.tracker_cfg).map_err(|e| FirmwareError::Config {
                reason: format!("camera board detection: {e}"),
            })?;
        self.tracker = Some(tracker);
        self.detection_only = true;
        self.status.detection_only.store(true, R);
        tracing::info!(
            cameras = sizes.len(),
            "camera board without a parameter set: detecting and publishing blobs only"
        );
        Ok(self)
    }

    /// Whether the active set runs in 6-DOF mode.
    pub fn tracks_pose(&self) -> bool {
        self.pose.is_some()
    }

    /// Builds the 6-DOF tracker for every tool of a set (none without tools). Tools the
    /// tracker refuses leave single-marker tracking on, loudly: the set itself is usable (the
    /// parameter service refuses such sets, so this is for sets loaded otherwise).
    fn pose_tracker_for(&self, rig: &RigParams) -> Option<MultiTracker> {
        if rig.tools.is_empty() {
            return None;
        }
        match MultiTracker::new(rig, &rig.tools, self.pose_cfg) {
            Ok(t) => {
                let names: Vec<&str> = rig.tools.iter().map(|t| t.name.as_str()).collect();
                tracing::info!(tools = ?names, "6-DOF tracking of every tool");
                Some(t)
            }
            Err(e) => {
                tracing::error!(error = %e, "tools refused; tracking a single marker instead");
                None
            }
        }
    }

    /// Picks up a newly installed parameter set (allocates; only on swaps).
    fn refresh_params(&mut self) {
        let generation = self.params.generation();
        if generation == self.seen_generation {
            return;
        }
        self.seen_generation = generation;
        let Some(p) = self.params.current() else { return };
        // In 6-DOF mode the detector must keep every LED of every tool (plus a few spares):
        // the blob limit is raised to what the pose tracker takes per camera.
        let pose = self.pose_tracker_for(&p.rig);
        let mut cfg = self.tracker_cfg;
        if let Some(pt) = &pose {
            cfg.max_blobs = cfg.max_blobs.max(pt.config().max_blobs_per_camera);
        }
        let result = match &mut self.tracker {
            Some(t) if t.config().max_blobs == cfg.max_blobs => t.set_params(&p.rig),
            _ => Tracker::new(&p.rig, cfg).map(|t| self.tracker = Some(t)),
        };
        // Timing: the parameter set's calibrated values win over the config's.
        if let (Ok(()), Some(tracker)) = (&result, self.tracker.as_mut()) {
            for camera in 0..tracker.camera_count() {
                let timing = if p.rig.has_timing() {
                    p.rig.camera_timing(camera)
                } else {
                    self.config_timing.get(camera).copied().unwrap_or_default()
                };
                if let Err(e) = tracker.set_timing(camera, timing) {
                    tracing::error!(camera, error = %e, "camera timing refused; global shutter, no offset");
                    let _ = tracker.set_timing(camera, CameraTiming::default());
                }
            }
        }
        match result {
            Ok(()) => {
                if self.detection_only {
                    self.detection_only = false;
                    self.status.detection_only.store(false, R);
                }
                self.pose = pose;
                self.robot_tool = match robot_tool_index(
                    self.robot_tool_name.as_deref(),
                    p.rig.tools.iter().map(|t| t.name.as_str()),
                ) {
                    Ok(i) => Some(i),
                    Err(e) => {
                        // The parameter service and the start-up check refuse this; a set
                        // that still lacks the tool sends no pose rather than another tool's.
                        tracing::error!(error = %e, "robot tool missing; main record without a pose");
                        None
                    }
                };
                self.world_from_cam0 = p.rig.world_from_cam0;
                self.params_crc = p.crc;
                self.status.params_loaded.store(true, R);
                tracing::info!(rig_id = %p.rig.rig_id, crc = format_args!("{:08x}", p.crc), "processing loop switched parameter set");
            }
            // The parameter service builds a tracker before accepting a set, so this means a
            // bug; keep the previous set rather than stop tracking.
            Err(e) => {
                tracing::error!(rig_id = %p.rig.rig_id, error = %e, "tracker refused parameter set; keeping the previous one")
            }
        }
    }

    /// Processes one frame set (blocking in the source until it is available).
    pub fn step(&mut self) -> Result<StepOutcome> {
        self.refresh_tuning();
        self.refresh_params();
        self.status.loop_iterations.fetch_add(1, R);
        // Sets not newer than the last processed one (duplicated or reordered by the source)
        // are dropped unpublished and the next one is fetched: no stale position goes out.
        loop {
            match self.source.next_set(&mut self.set) {
                Ok(()) => {}
                Err(SourceError::EndOfStream) => return Ok(StepOutcome::EndOfStream),
                // Held on purpose (a replay waiting for a parameter set or a client): no
                // fault, no record; the source already waited a little and says why on /status.
                Err(SourceError::Waiting { .. }) => {
                    self.status.set_track(TrackIndication::None);
                    return Ok(StepOutcome::SourceError);
                }
                Err(e @ (SourceError::CameraLost { .. } | SourceError::Timeout { .. })) => {
                    self.status.source_errors.fetch_add(1, R);
                    if !self.status.camera_lost.swap(true, R) {
                        tracing::warn!(error = %e, "camera fault; retrying");
                    }
                    self.status.set_track(TrackIndication::None);
                    let rec = self.empty_record(TrackStatus::Fault, clock::monotonic_ns());
                    self.out.send_replace(Some(rec));
                    self.consecutive_errors = self.consecutive_errors.saturating_add(1);
                    // Sources back off themselves; this only stops a tight loop on instant errors.
                    std::thread::sleep(Duration::from_millis(
                        u64::from(self.consecutive_errors.min(50)) * 10,
                    ));
                    return Ok(StepOutcome::SourceError);
                }
                Err(e) => return Err(e.into()),
            }
            if self.status.camera_lost.swap(false, R) {
                tracing::info!("cameras delivering frames again");
            }
            self.consecutive_errors = 0;
            let capture_ns = self.set.frames.first().map_or(0, |f| f.timestamp_ns);
            if self.last_capture_ns.is_some_and(|last| capture_ns <= last) {
                if self.status.stale_sets.fetch_add(1, R) == 0 {
                    tracing::warn!(
                        index = self.set.index,
                        "frame set not newer than the last one; dropped"
                    );
                }
                continue;
            }
            break;
        }
        let t_start = Instant::now();
        let dequeued_ns = clock::monotonic_ns();
        let capture_ns = self.set.frames.first().map_or(0, |f| f.timestamp_ns);
        self.last_capture_ns = Some(capture_ns);
        self.account_source();
        // Each camera's clock model: from here on a frame's timestamp is its smoothed instant
        // (the record keeps camera 0's raw stamp, `capture_ns`; docs/timing.md).
        if let Some(clocks) = self.clocks.as_mut() {
            clocks.apply(&mut self.set.frames, &self.status);
        }

        // Sets solved at one instant bridge the cameras' spread along their tracks, up to
        // `max_bridge_ms`; only sets solved as seen need frames exposed together.
        let max_skew_ns = if self.tracker_cfg.time_mode == TimeMode::Off {
            self.max_pairing_error_ns
        } else {
            self.max_pairing_error_ns
                .max((self.tracker_cfg.max_bridge_ms * 1e6) as u64)
        };
        let skewed = self.set.pairing_error_ns > max_skew_ns;
        let mut detected = false;
        let mut tools: Option<ToolSet> = None;
        let (mut rec, t_detect, t_solve) = match self
            .tracker
            .as_mut()
            .filter(|_| self.detection_only || self.status.params_loaded.load(R))
        {
            // The cameras saw a moving marker at different instants: their rays do not meet
            // where the marker was. No position rather than a wrong one.
            Some(_) if skewed => {
                self.status.skewed_last_ns.store(dequeued_ns.max(1), R);
                self.status
                    .skewed_last_spread_ns
                    .store(self.set.pairing_error_ns, R);
                if self.status.skewed_sets.fetch_add(1, R) == 0 {
                    tracing::warn!(
                        pairing_error_us = self.set.pairing_error_ns / 1000,
                        max_us = max_skew_ns / 1000,
                        "camera timestamps too far apart; set published without a position"
                    );
                }
                self.status.set_track(TrackIndication::None);
                (
                    self.empty_record(TrackStatus::Rejected, capture_ns),
                    t_start,
                    t_start,
                )
            }
            None => {
                self.status.set_track(TrackIndication::None);
                (
                    self.empty_record(TrackStatus::NoParams, capture_ns),
                    t_start,
                    t_start,
                )
            }
            Some(tracker) => {
                let mut failed = false;
                if self.pose.is_some() {
                    // All LEDs must be found, not only those near the last single marker.
                    tracker.reset_tracking();
                }
                let dropped = self.status.sets_dropped.load(R);
                for (camera, frame) in self.set.frames.iter().enumerate() {
                    // The frame's own timestamp: the set is solved at one instant from them.
                    if let Err(e) = tracker.set_frame_time(camera, frame.timestamp_ns) {
                        tracing::error!(camera, error = %e, "frame time refused");
                    }
                    // A cluster solver's source brings other boards' blobs (no pixels).
                    let remote = self.source.remote_blobs(camera);
                    let detected = match (&frame.pixels, remote) {
                        (_, Some(blobs)) => tracker.set_blobs(camera, blobs.iter().copied()),
                        (Pixels::U8(px), None) => {
                            GrayImage::new(px, frame.width_px, frame.height_px, frame.stride_px)
                                .and_then(|img| tracker.detect_u8(camera, &img))
                        }
                        (Pixels::U16(px), None) => {
                            GrayImage::new(px, frame.width_px, frame.height_px, frame.stride_px)
                                .and_then(|img| tracker.detect_u16(camera, &img))
                        }
                    };
                    match detected {
                        Ok(n) => {
                            if let Some(c) = self.status.cameras.get(camera) {
                                c.blobs_last.store(n as u64, R);
                                let peak = match remote {
                                    Some(b) => b.iter().map(|b| b.peak_dn).max().unwrap_or(0),
                                    None => peak_dn(tracker.blobs(camera), frame),
                                };
                                c.peak_dn.store(u64::from(peak), R);
                            }
                            if let Some(sink) = self.observation_sink.as_mut() {
                                sink.observe(camera, frame, tracker.blobs(camera), dropped);
                            }
                        }
                        Err(e) => {
                            if self.status.pipeline_errors.fetch_add(1, R) == 0 {
                                tracing::error!(camera, error = %e, "blob detection failed");
                            }
                            failed = true;
                        }
                    }
                }
                detected = !failed;
                let t_detect = Instant::now();
                if self.detection_only {
                    // A camera board's blobs went to the solver; it has no position itself.
                    let seen = (0..tracker.camera_count()).any(|c| !tracker.blobs(c).is_empty());
                    self.status.set_track(if seen {
                        TrackIndication::Partial
                    } else {
                        TrackIndication::None
                    });
                    (
                        Self::blank_record(self.set.index, capture_ns, 0, TrackStatus::NoParams),
                        t_detect,
                        t_detect,
                    )
                } else if let Some(pose_tracker) = self.pose.as_mut() {
                    let rec = if failed {
                        Self::fault_record(&self.status, self.set.index, capture_ns, self.params_crc)
                    } else {
                        let cameras = tracker.camera_count().min(MAX_CAMERAS);
                        // Every LED moved to one instant (free-running or rolling-shutter
                        // cameras); the tools' records are for that instant.
                        let capture_ns = tracker.retime().map_or(capture_ns, instant_to_ns);
                        let mut lists: [&[Blob]; MAX_CAMERAS] = [&[]; MAX_CAMERAS];
                        for (c, list) in lists.iter_mut().enumerate().take(cameras) {
                            *list = tracker.timed_blobs(c);
                        }
                        let seen = lists[..cameras].iter().filter(|l| !l.is_empty()).count();
                        match pose_tracker.process(&lists[..cameras]) {
                            Ok(()) => {
                                let seen_u8 = u8::try_from(seen).unwrap_or(u8::MAX);
                                let count = pose_tracker.tool_count().min(MAX_TOOLS);
                                let loose = pose_tracker.loose_leds();
                                let loose_n = loose.len().min(MAX_LOOSE_LEDS);
                                let mut set = ToolSet {
                                    frame: self.set.index,
                                    count: count as u8,
                                    loose_leds: loose_n as u8,
                                    ..ToolSet::EMPTY
                                };
                                for (slot, led) in set.loose.iter_mut().zip(loose) {
                                    let mut rec = LooseRecord::from_loose_led(
                                        self.set.index,
                                        capture_ns,
                                        led,
                                        self.world_from_cam0.as_ref(),
                                        loose_n as u8,
                                    );
                                    rec.record.params_crc = self.params_crc;
                                    *slot = Some(rec);
                                }
                                // By id, so that a reader sees the same order every set (the
                                // tracker lists them longest-tracked first). In place: no
                                // allocation.
                                set.loose[..loose_n].sort_unstable_by_key(|r| r.map(|r| r.loose_id));
                                for (i, slot) in set.tools.iter_mut().enumerate().take(count) {
                                    let (Some(pose), Some(tool)) =
                                        (pose_tracker.pose(i), pose_tracker.tool(i))
                                    else {
                                        continue;
                                    };
                                    // A pivot-calibrated tool is reported (and sent) at its tip.
                                    let mut rec = PositionRecord::from_pose(
                                        self.set.index,
                                        capture_ns,
                                        &pose.at_tip(),
                                        self.world_from_cam0.as_ref(),
                                        seen_u8,
                                    );
                                    rec.params_crc = self.params_crc;
                                    // Names were checked when the set was accepted.
                                    *slot = ToolRecord::new(i as u8, count as u8, tool.name(), rec).ok();
                                }
                                tools = Some(set);
                                let robot = self
                                    .robot_tool
                                    .and_then(|i| Some((pose_tracker.pose(i)?, set.tools[i]?)));
                                match robot {
                                    Some((pose, tr)) => {
                                        self.status.set_track(pose_indication(pose, seen, cameras));
                                        tr.record
                                    }
                                    None => Self::fault_record(
                                        &self.status,
                                        self.set.index,
                                        capture_ns,
                                        self.params_crc,
                                    ),
                                }
                            }
                            Err(e) => {
                                if self.status.pipeline_errors.fetch_add(1, R) == 0 {
                                    tracing::error!(error = %e, "6-DOF tracking failed");
                                }
                                Self::fault_record(&self.status, self.set.index, capture_ns, self.params_crc)
                            }
                        }
                    };
                    (rec, t_detect, Instant::now())
                } else {
                    tracker.solve();
                    // A cluster solver checks that its boards agree (it may solve again
                    // without a board's cameras, or refuse the set: no position).
                    let vetted = self.source.vet_solution(tracker);
                    let m = tracker.measurement();
                    let t_solve = Instant::now();
                    for (c, o) in self.status.cameras.iter().zip(&m.cameras) {
                        c.record_bridge(o.bridge_ns, o.unbridged);
                    }
                    // The record is for the instant the set was solved at.
                    let capture_ns = m.instant_ns.map_or(capture_ns, instant_to_ns);
                    let rec = if failed {
                        self.status.set_track(TrackIndication::None);
                        Self::record_from(
                            m,
                            self.set.index,
                            capture_ns,
                            self.params_crc,
                            None,
                            TrackStatus::Fault,
                        )
                    } else {
                        let status = if vetted {
                            self.status.set_track(track_indication(m));
                            map_status(m)
                        } else {
                            self.status.set_track(TrackIndication::Partial);
                            TrackStatus::Rejected
                        };
                        Self::record_from(
                            m,
                            self.set.index,
                            capture_ns,
                            self.params_crc,
                            self.world_from_cam0.as_ref(),
                            status,
                        )
                    };
                    (rec, t_detect, t_solve)
                }
            }
        };
        match rec.status {
            TrackStatus::Ok => self.status.tracked.fetch_add(1, R),
            TrackStatus::Rejected => self.status.gated.fetch_add(1, R),
            _ => self.status.lost.fetch_add(1, R),
        };
        if rec.gap_mm.is_finite() {
            self.status.last_gap_mm_bits.store(rec.gap_mm.to_bits(), R);
        }
        // The stamp the record carries is taken just before the hand-over to the slot; the
        // `published` stage ends just after it.
        let now_ns = clock::monotonic_ns();
        let e2e_ns = now_ns.saturating_sub(capture_ns);
        rec.latency_us = u32::try_from(e2e_ns / 1000).unwrap_or(u32::MAX);
        if let (Some(out), Some(mut set)) = (&self.tool_out, tools) {
            for r in set.tools.iter_mut().flatten() {
                r.record.latency_us = rec.latency_us;
            }
            for r in set.loose.iter_mut().flatten() {
                r.record.latency_us = rec.latency_us;
            }
            out.send_replace(set);
        }
        self.out.send_replace(Some(rec));
        let t_published = Instant::now();
        self.status.published.fetch_add(1, R);
        // Frame sets report the driver's own timestamps.
        if let Some(clocks) = &self.clocks {
            clocks.restore_raw(&mut self.set.frames);
        }
        // After publishing: a viewer's copy never delays the position.
        self.feed_tap(detected);
        let t_end = Instant::now();

        let at = |t: Instant| dequeued_ns + u64::try_from((t - t_start).as_nanos()).unwrap_or(u64::MAX);
        self.times = SetTimes {
            capture_ns,
            render_ns: self.set.render_ns,
            dequeued_ns,
            blobs_ns: at(t_detect),
            triangulated_ns: at(t_solve.max(t_detect)),
            published_ns: at(t_published),
            done_ns: at(t_end),
        };
        let st = &self.status.stages;
        if self.set.render_ns > 0 {
            st.render.record_ns(self.set.render_ns);
        }
        st.driver.record_ns(self.times.driver_ns());
        st.detect.record(t_detect - t_start);
        st.solve.record(t_solve.max(t_detect) - t_detect);
        st.publish.record(t_published - t_solve.max(t_detect));
        st.ours.record(t_published - t_start);
        let process = t_end - t_start;
        st.process.record(process);
        st.end_to_end
            .record_ns(self.times.published_ns.saturating_sub(capture_ns));
        if u64::try_from(process.as_nanos()).unwrap_or(u64::MAX) > self.deadline_ns {
            self.status.deadline_misses.fetch_add(1, R);
        }
        self.status.sets_processed.fetch_add(1, R);
        Ok(StepOutcome::Published(rec))
    }

    /// Copies source counters and per-camera rates into the shared status (no allocation).
    fn account_source(&mut self) {
        let s = self.source.stats();
        self.status.sets_delivered.store(s.sets_delivered, R);
        self.status.sets_dropped.store(s.sets_dropped, R);
        self.status.unpaired_dropped.store(s.unpaired_dropped, R);
        self.status.reconnects.store(s.reconnects, R);
        if s.reconnects != self.reconnects_seen || s.controls_generation != self.controls_seen {
            self.reconnects_seen = s.reconnects;
            self.controls_seen = s.controls_generation;
            // A reopened camera may not hold the values it had (the source writes the live
            // ones again; a driver may still refuse them): show what it has now. Rare, so the
            // device queries here do not matter to the loop's timing.
            if let Some(tuning) = &self.tuning {
                tuning.refresh_cameras(self.source.controls());
            }
        }
        self.status
            .pairing_error_last_ns
            .store(self.set.pairing_error_ns, R);
        self.status
            .pairing_error_max_ns
            .fetch_max(self.set.pairing_error_ns, R);
        for (c, f) in self.status.cameras.iter().zip(&self.set.frames) {
            c.frames.fetch_add(1, R);
            let last = c.last_timestamp_ns.swap(f.timestamp_ns, R);
            if last != 0 && f.timestamp_ns > last {
                let interval = (f.timestamp_ns - last) as f64;
                let old = f64::from_bits(c.interval_ewma_ns.load(R));
                let new = if old > 0.0 {
                    0.9 * old + 0.1 * interval
                } else {
                    interval
                };
                c.interval_ewma_ns.store(new.to_bits(), R);
            }
        }
    }

    /// A 6-DOF set that produced no pose (detection or tracking failed, or the robot's tool
    /// is not seen): the LED shows no track and the record says `Fault`. Takes the status
    /// alone, not `&self`, because the caller still holds the trackers mutably.
    fn fault_record(status: &SharedStatus, frame: u64, capture_ns: u64, params_crc: u32) -> PositionRecord {
        status.set_track(TrackIndication::None);
        Self::blank_record(frame, capture_ns, params_crc, TrackStatus::Fault)
    }

    fn empty_record(&self, status: TrackStatus, capture_ns: u64) -> PositionRecord {
        Self::blank_record(self.set.index, capture_ns, self.params_crc, status)
    }

    /// A record without a position.
    fn blank_record(frame: u64, capture_ns: u64, params_crc: u32, status: TrackStatus) -> PositionRecord {
        PositionRecord {
            frame,
            capture_ts_ns: capture_ns,
            position_mm: None,
            orientation_wxyz: None,
            gap_mm: f64::NAN,
            status,
            cameras_used: 0,
            world_frame: false,
            latency_us: 0,
            params_crc,
        }
    }

    /// `[tracking]`'s time mode (the set-up page shows it).
    pub fn time_mode(&self) -> TimeMode {
        self.tracker_cfg.time_mode
    }

    fn record_from(
        m: &Measurement,
        frame: u64,
        capture_ns: u64,
        params_crc: u32,
        world: Option<&RigidTransform>,
        status: TrackStatus,
    ) -> PositionRecord {
        let position_mm = match (status, m.point_cam0_mm) {
            (TrackStatus::Ok, Some(p)) => {
                let p = world.map_or(p, |w| w.apply(&p));
                Some([p.x, p.y, p.z])
            }
            _ => None,
        };
        PositionRecord {
            frame,
            capture_ts_ns: capture_ns,
            // A record without a point can never claim status Ok.
            status: if position_mm.is_none() && status == TrackStatus::Ok {
                TrackStatus::Lost
            } else {
                status
            },
            position_mm,
            orientation_wxyz: None,
            gap_mm: if m.gap_mm.is_finite() { m.gap_mm } else { f64::NAN },
            cameras_used: u8::try_from(m.cameras_used).unwrap_or(u8::MAX),
            world_frame: world.is_some() && position_mm.is_some(),
            latency_us: 0,
            params_crc,
        }
    }

    /// Runs until `stop` is set, the source ends, or a fatal source error.
    pub fn run(mut self, stop: &AtomicBool) -> Result<()> {
        tracing::info!(source = %self.source.describe(), deadline_us = self.deadline_ns / 1000, "processing loop started");
        while !stop.load(R) {
            match self.step() {
                Ok(StepOutcome::EndOfStream) => {
                    let why = self.end_reason();
                    tracing::info!(summary = %why, "frame source ended; processing loop stops");
                    if let Ok(mut r) = self.status.end_reason.lock() {
                        *r = Some(why);
                    }
                    self.status.source_ended.store(true, R);
                    return Ok(());
                }
                Ok(_) => {}
                Err(e) => {
                    tracing::error!(error = %e, "processing loop stopped by a fatal source error");
                    self.status.camera_lost.store(true, R);
                    return Err(e);
                }
            }
        }
        Ok(())
    }

    /// Why the stream ended, in words: the source's own summary plus the sets the loop
    /// dropped as not newer than the one before (a recording whose timestamps do not rise).
    fn end_reason(&self) -> String {
        let mut s = self
            .source
            .end_summary()
            .unwrap_or_else(|| format!("{} ended", self.source.describe()));
        let processed = self.status.sets_processed.load(R);
        s += &format!("; {processed} sets processed");
        let stale = self.status.stale_sets.load(R);
        if stale > 0 {
            s += &format!(
                "; {stale} sets dropped because their timestamps were not newer than the set before                  (check the recording's timestamps.csv, or its [source.replay] fps)"
            );
        }
        s
    }

    /// The frame source the loop reads.
    pub fn source(&self) -> &dyn FrameSource {
        self.source.as_ref()
    }
}

/// Brightest pixel of a camera's frame: the brightest blob's peak when there are blobs (free),
/// else a scan of the frame (only in frames without any blob, where the set-up view needs it
/// to tell "threshold above the LED" from "no LED in view").
fn peak_dn(blobs: &[Blob], frame: &crate::source::Frame) -> u32 {
    if let Some(p) = blobs.iter().map(|b| b.peak_dn).max() {
        return p;
    }
    match &frame.pixels {
        Pixels::U8(px) => px.iter().copied().max().map_or(0, u32::from),
        Pixels::U16(px) => px.iter().copied().max().map_or(0, u32::from),
    }
}

/// Lists every blob of the tracker's last detection with why it was (not) used, through
/// `push(camera, blob)`.
fn fill_blob_views(tracker: &Tracker, pose: Option<&MultiTracker>, mut push: impl FnMut(usize, BlobView)) {
    // Without a point to compare with (6-DOF, or a camera board's detection only), every
    // usable blob counts as used.
    let six_dof = pose.is_some() || tracker.is_detection_only();
    let cfg = *tracker.config();
    let m = tracker.measurement();
    for camera in 0..tracker.camera_count() {
        let marker = m.cameras().get(camera).and_then(|o| o.marker);
        for (index, b) in tracker.blobs(camera).iter().enumerate() {
            let reason = if b.roundness < cfg.min_roundness {
                Some(RejectReason::Roundness)
            } else if (cfg.reject_edge_blobs && b.touches_frame_edge) || b.touches_roi_edge {
                Some(RejectReason::Edge)
            } else if six_dof || marker.is_some_and(|mk| mk.x_px == b.x_px && mk.y_px == b.y_px) {
                None
            } else {
                Some(RejectReason::Gate)
            };
            let mut view = BlobView::of(b, reason);
            if let Some(p) = pose {
                match p.blob_owner(camera, index) {
                    LOOSE_LED => view.loose = true,
                    NO_TOOL => {}
                    t => view.tool = Some(t),
                }
            }
            push(camera, view);
        }
        for b in tracker.rejected_by_area(camera) {
            push(camera, BlobView::of(b, Some(RejectReason::Area)));
        }
    }
}

/// Stream status for a tracker result.
/// Puts the tracker's time mode and bridge limit on `/status`.
fn publish_timing(status: &SharedStatus, cfg: &TrackerConfig) {
    if let Ok(mut g) = status.timing.lock() {
        *g = Some(crate::status::TimingReport::new(cfg.time_mode, cfg.max_bridge_ms));
    }
}

fn map_status(m: &Measurement) -> TrackStatus {
    match m.status {
        MeasureStatus::Tracked => TrackStatus::Ok,
        MeasureStatus::NoBlob { .. } => TrackStatus::Lost,
        MeasureStatus::NoConsistentPair | MeasureStatus::Overloaded { .. } => TrackStatus::Rejected,
        MeasureStatus::MissingFrame { .. } => TrackStatus::Fault,
    }
}

/// LED indication in 6-DOF mode: the pose is tracked, or LED blobs are seen somewhere.
fn pose_indication(pose: &Pose6d, cameras_with_blobs: usize, cameras: usize) -> TrackIndication {
    if pose.status == PoseStatus::Tracked && cameras_with_blobs == cameras {
        TrackIndication::All
    } else if cameras_with_blobs > 0 {
        TrackIndication::Partial
    } else {
        TrackIndication::None
    }
}

/// LED indication: marker candidates in all, some or none of the cameras.
fn track_indication(m: &Measurement) -> TrackIndication {
    let cams = m.cameras();
    let seen = cams.iter().filter(|c| c.candidate_count > 0).count();
    if matches!(m.status, MeasureStatus::Tracked) && m.cameras_used as usize == cams.len() {
        TrackIndication::All
    } else if seen > 0 {
        TrackIndication::Partial
    } else {
        TrackIndication::None
    }
}

/// A set's instant (f64 ns) as a record's timestamp.
fn instant_to_ns(t_ns: f64) -> u64 {
    if t_ns.is_finite() && t_ns > 0.0 {
        t_ns.round() as u64
    } else {
        0
    }
}
