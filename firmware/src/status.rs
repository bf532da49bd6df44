//! Shared run-time status: written by the processing loop (atomics only, so it never blocks or
//! allocates), the LED driver and the services; read by the status endpoint and the watchdog.

use std::sync::atomic::{AtomicBool, AtomicU8, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::Serialize;

use crate::leds::indication::{Fault, Indication, RobotIndication, TrackIndication};
use crate::metrics::{LatencyHistogram, LatencySummary};

const R: Ordering = Ordering::Relaxed;

/// Per-stage latency histograms of the processing loop, along a set's path (see
/// [`crate::engine::SetTimes`]): `driver` + `ours` = `end_to_end`.
#[derive(Debug, Default)]
pub struct StageHistograms {
    /// The simulator's rendering of a set, done ahead of its capture instant (not part of
    /// `end_to_end`; empty with cameras).
    pub render: LatencyHistogram,
    /// Capture timestamp → dequeued by the loop (driver, pairing, source queue).
    pub driver: LatencyHistogram,
    /// Dequeued → blobs done, all cameras of one set.
    pub detect: LatencyHistogram,
    /// Blobs → undistorted and triangulated.
    pub solve: LatencyHistogram,
    /// Quality gate, record building and publishing to the slot.
    pub publish: LatencyHistogram,
    /// Dequeued → published: irtrackd's own share.
    pub ours: LatencyHistogram,
    /// Whole processing of one set incl. a viewer copy (compared with the deadline).
    pub process: LatencyHistogram,
    /// Capture timestamp → published.
    pub end_to_end: LatencyHistogram,
}

/// Number of stage histograms.
pub const STAGES: usize = 8;

impl StageHistograms {
    /// The histograms with their stage names, in path order (the names used on `/status` and
    /// `/metrics`).
    pub fn stages(&self) -> [(&'static str, &LatencyHistogram); STAGES] {
        [
            ("render", &self.render),
            ("driver", &self.driver),
            ("detect", &self.detect),
            ("solve", &self.solve),
            ("publish", &self.publish),
            ("ours", &self.ours),
            ("process", &self.process),
            ("end_to_end", &self.end_to_end),
        ]
    }
}

/// Counters of one camera.
#[derive(Debug, Default)]
pub struct CameraCounters {
    /// Frames of this camera that reached the loop since start.
    pub frames: AtomicU64,
    /// Exponentially averaged frame interval (ns, from capture timestamps).
    pub interval_ewma_ns: AtomicU64,
    /// Capture timestamp of the newest frame, CLOCK_MONOTONIC ns (0 before the first).
    pub last_timestamp_ns: AtomicU64,
    /// Blobs found in the last processed frame.
    pub blobs_last: AtomicU64,
    /// Brightest pixel (DN) of the last processed frame.
    pub peak_dn: AtomicU64,
    /// Frame width, pixels (the source's frame shape, set when the loop starts).
    pub width_px: AtomicU64,
    /// Frame height, pixels (the source's frame shape, set when the loop starts).
    pub height_px: AtomicU64,
    /// The camera's clock model (written by [`crate::frame_clocks`] every few frames).
    pub clock: ClockCounters,
    /// How far the newest marker blob was carried along its track to the set's instant, ns
    /// (`f64` bits; docs/timing.md).
    pub bridge_ns_last_bits: AtomicU64,
    /// The largest such distance (absolute) since start, ns (`f64` bits).
    pub bridge_ns_max_bits: AtomicU64,
    /// Gated blobs left out because they could not be brought to the set's instant.
    pub unbridged: AtomicU64,
}

impl CameraCounters {
    /// Notes what time-true tracking did with this camera's blobs in one set.
    pub fn record_bridge(&self, bridge_ns: f64, unbridged: u32) {
        if bridge_ns.is_finite() {
            self.bridge_ns_last_bits.store(bridge_ns.to_bits(), R);
            let max = f64::from_bits(self.bridge_ns_max_bits.load(R));
            if bridge_ns.abs() > max {
                self.bridge_ns_max_bits.store(bridge_ns.abs().to_bits(), R);
            }
        }
        if unbridged > 0 {
            self.unbridged.fetch_add(u64::from(unbridged), R);
        }
    }
}

/// One camera's clock model figures (docs/timing.md, "Camera clocks"); `f64`s as bits, NaN =
/// not known yet.
#[derive(Debug, Default)]
pub struct ClockCounters {
    /// 0 = no model yet, 1 = warming up, 2 = locked, 3 = re-locking after a jump.
    pub state: AtomicU8,
    /// Measured frame period, ns.
    pub period_ns_bits: AtomicU64,
    /// Rate against the configured one, ppm (positive = fast).
    pub rate_error_ppm_bits: AtomicU64,
    /// RMS timestamp distance from the fitted line, ns.
    pub jitter_rms_ns_bits: AtomicU64,
    /// Largest timestamp distance from the line in the window, ns.
    pub jitter_max_ns_bits: AtomicU64,
    /// Exposure after camera 0's nearest frame, ns (−½…+½ period).
    pub phase_ns_bits: AtomicU64,
    /// Phase drift against camera 0, ppm of elapsed time (positive = later and later).
    pub drift_ppm_bits: AtomicU64,
    /// The same in µs of phase per minute.
    pub drift_us_per_min_bits: AtomicU64,
    /// Frames missing from the camera's frame sequence.
    pub drops: AtomicU64,
    /// Frames delivered twice.
    pub duplicates: AtomicU64,
    /// Timestamp steps the model could not explain (it re-locked).
    pub jumps: AtomicU64,
    /// Timestamps left out of the fit as too far from the line.
    pub outliers: AtomicU64,
    /// The camera's sequence numbers count its frames.
    pub sequence_used: AtomicBool,
}

impl ClockCounters {
    /// The figures for `/status`; `None` before the model has seen a frame.
    pub fn report(&self) -> Option<CameraClockReport> {
        let f = |a: &AtomicU64| Some(f64::from_bits(a.load(R))).filter(|v| v.is_finite());
        let state = match self.state.load(R) {
            1 => "warming_up",
            2 => "locked",
            3 => "relocking",
            _ => return None,
        };
        let period_ns = f(&self.period_ns_bits);
        Some(CameraClockReport {
            state,
            period_us: period_ns.map(|p| p / 1e3),
            fps: period_ns.filter(|p| *p > 0.0).map(|p| 1e9 / p),
            rate_error_ppm: f(&self.rate_error_ppm_bits),
            phase_us: f(&self.phase_ns_bits).map(|p| p / 1e3),
            drift_ppm: f(&self.drift_ppm_bits),
            drift_us_per_min: f(&self.drift_us_per_min_bits),
            jitter_rms_us: f(&self.jitter_rms_ns_bits).map(|j| j / 1e3),
            jitter_max_us: f(&self.jitter_max_ns_bits).map(|j| j / 1e3),
            drops: self.drops.load(R),
            duplicates: self.duplicates.load(R),
            jumps: self.jumps.load(R),
            outliers: self.outliers.load(R),
            sequence_used: self.sequence_used.load(R),
        })
    }
}

/// A camera's clock on `/status` (docs/timing.md, "Camera clocks").
#[derive(Debug, Clone, Serialize)]
pub struct CameraClockReport {
    /// "warming_up", "locked" or "relocking" (after a jump).
    pub state: &'static str,
    /// Measured frame period, µs.
    pub period_us: Option<f64>,
    /// The same as frames per second.
    pub fps: Option<f64>,
    /// Rate against the configured frame rate, ppm (positive = the camera runs fast).
    pub rate_error_ppm: Option<f64>,
    /// Exposure after camera 0's nearest frame, µs (negative = before it); camera 0: 0.
    pub phase_us: Option<f64>,
    /// How fast the phase changes, ppm of elapsed time (positive = later and later).
    pub drift_ppm: Option<f64>,
    /// The same in µs of phase per minute.
    pub drift_us_per_min: Option<f64>,
    /// Timestamp jitter: RMS distance of the stamps from the fitted line, µs.
    pub jitter_rms_us: Option<f64>,
    /// Largest distance of a recent stamp from the line, µs (late USB transfers show here).
    pub jitter_max_us: Option<f64>,
    /// Frames missing from the camera's sequence since start.
    pub drops: u64,
    /// Frames delivered twice since start.
    pub duplicates: u64,
    /// Timestamp jumps (clock reset, camera restart) since start.
    pub jumps: u64,
    /// Stamps left out of the fit as too far from the line since start.
    pub outliers: u64,
    /// The camera's sequence numbers count its frames (else frame indices come from time).
    pub sequence_used: bool,
}

/// Information about the active parameter set (changes rarely; behind a mutex).
#[derive(Debug, Clone, Default, Serialize)]
pub struct ParamsInfo {
    /// Whether a parameter set is active (without one nothing is triangulated).
    pub loaded: bool,
    /// The rig the active set was calibrated for, as named in the set.
    pub rig_id: Option<String>,
    /// When the active set was made, Unix seconds.
    pub created_unix_s: Option<u64>,
    /// Where the active set came from: "state_dir", "rollback", "pushed", "simulator".
    pub origin: Option<String>,
    /// Parameter sets activated since start (stored set at start included).
    pub swaps: u64,
    /// Parameter pushes refused since start.
    pub rejected: u64,
    /// Code and reason of the most recent refusal.
    pub last_rejection: Option<String>,
    /// The active set's serial (docs/param-blob.md; `None`: the set has none, version < 5).
    pub serial: Option<u64>,
    /// Pushes refused because the set was older than the active one (no `--allow-rollback`).
    pub rollbacks_refused: u64,
    /// Older sets activated because the push allowed a rollback.
    pub rollbacks_allowed: u64,
    /// The most recent rollback event in words: "refused: ..." or "allowed: ...", naming both
    /// sets (ids, serials, creation dates).
    pub last_rollback: Option<String>,
    /// "require_signed" (production) or "allow_unsigned" (development mode, config
    /// `[params] allow_unsigned = true`).
    pub signature_policy: &'static str,
    /// Ids (first 8 bytes of SHA-512, hex) of the public keys whose signatures are accepted.
    pub trusted_keys: Vec<String>,
    /// How the active set was authenticated: "key `<id>`" or "unsigned".
    pub signature: Option<String>,
    /// The active set's calibration record: method, age, quality, warning (crate::calibration).
    pub calibration: Option<crate::calibration::CalibrationStatus>,
    /// The record itself, to recompute the age when the status is built.
    #[serde(skip)]
    pub calibration_record: Option<irtrack_core::params::CalibrationInfo>,
    /// `[params] calibration_max_age_days` (None: the default).
    #[serde(skip)]
    pub calibration_max_age_days: Option<f64>,
}

impl ParamsInfo {
    /// Takes the active set's record (on activation).
    pub fn set_calibration(&mut self, record: Option<&irtrack_core::params::CalibrationInfo>) {
        self.calibration_record = record.cloned();
        self.calibration = None;
    }

    /// The info with the calibration's age and warning as of `now_unix_s`.
    pub fn aged(mut self, now_unix_s: u64) -> Self {
        let max = self
            .calibration_max_age_days
            .unwrap_or(crate::calibration::DEFAULT_MAX_AGE_DAYS);
        self.calibration = self
            .calibration_record
            .as_ref()
            .map(|r| crate::calibration::CalibrationStatus::of(r, now_unix_s, max));
        self
    }
}

/// All shared counters and state.
#[derive(Debug)]
pub struct SharedStatus {
    started: Instant,
    /// The frame source in words (kind, cameras, format), as shown on `/status`.
    pub source_description: String,
    /// Which LED driver runs (GPIO chip, Raspberry Pi, log only, ...).
    pub led_backend: String,
    /// One entry per camera, in camera order.
    pub cameras: Vec<CameraCounters>,

    // Processing loop.
    /// Passes of the processing loop (also errors and timeouts): the liveness the LED driver and
    /// the watchdog check.
    pub loop_iterations: AtomicU64,
    /// Frame sets run through detection and solving to publishing.
    pub sets_processed: AtomicU64,
    /// Records written to the latest-value slot.
    pub published: AtomicU64,
    /// Published records with a position (status `Ok`).
    pub tracked: AtomicU64,
    /// Published records without a position for lack of a marker or a fault (not gated).
    pub lost: AtomicU64,
    /// Published records whose position the quality gate refused (status `Rejected`).
    pub gated: AtomicU64,
    /// Time allowed for processing one set, ns (`[realtime] deadline_ms`, else the frame period).
    pub deadline_ns: AtomicU64,
    /// Sets whose processing took longer than `deadline_ns`.
    pub deadline_misses: AtomicU64,
    /// Errors returned by the frame source (lost camera, timeout, ...).
    pub source_errors: AtomicU64,
    /// Failures of blob detection or tracking on a delivered set.
    pub pipeline_errors: AtomicU64,
    /// Sets not newer than the last processed one (duplicated or reordered by the source),
    /// dropped unpublished so that no stale position goes out.
    pub stale_sets: AtomicU64,
    /// Sets whose cameras' capture times differ by more than the allowed pairing error: a
    /// moving marker would triangulate wrong, so they are published without a position.
    pub skewed_sets: AtomicU64,
    /// When the newest skewed set was seen (CLOCK_MONOTONIC ns, 0 = never): the
    /// `skewed_sets` fault lasts [`SKEW_FAULT_HOLD_NS`] after it.
    pub skewed_last_ns: AtomicU64,
    /// Timestamp spread of that set, ns.
    pub skewed_last_spread_ns: AtomicU64,
    /// The tracker's time mode and bridge limit, once the loop has started.
    pub timing: Mutex<Option<TimingReport>>,
    /// Latency of each stage of the loop.
    pub stages: StageHistograms,
    /// Ray gap of the latest triangulated position, mm, as `f64` bits (NaN before the first).
    pub last_gap_mm_bits: AtomicU64,

    // Source counters (copied from `FrameSource::stats`).
    /// Sets the source delivered ([`crate::source::SourceStats`]).
    pub sets_delivered: AtomicU64,
    /// Sets the source skipped.
    pub sets_dropped: AtomicU64,
    /// Frames the source dropped for lack of a partner in time.
    pub unpaired_dropped: AtomicU64,
    /// Times a camera was lost and reopened.
    pub reconnects: AtomicU64,
    /// Timestamp spread between the cameras of the latest set, ns.
    pub pairing_error_last_ns: AtomicU64,
    /// Largest timestamp spread of any set since start, ns.
    pub pairing_error_max_ns: AtomicU64,

    // Health inputs for the LEDs.
    /// A parameter set is active.
    pub params_loaded: AtomicBool,
    /// A cluster camera board detecting without a parameter set of its own (it needs none):
    /// the missing set is not a fault.
    pub detection_only: AtomicBool,
    /// The source reports a lost camera; cleared by the next good set.
    pub camera_lost: AtomicBool,
    track: AtomicU8,
    robot: AtomicU8,
    /// Too many deadline misses in the LED driver's last window (a fault on the LED).
    pub deadline_fault: AtomicBool,
    /// The loop has made progress recently (set by the LED driver's health monitor).
    pub alive: AtomicBool,
    /// The frame source ended (replay finished); the loop stopped on purpose.
    pub source_ended: AtomicBool,
    /// Why it ended, in words (set once, when it ends).
    pub end_reason: Mutex<Option<String>>,
    /// What the source holds its first set for, in words (a replay's `wait_for_params` /
    /// `wait_for_client`); `None` once it runs.
    pub source_waiting: Mutex<Option<String>>,

    // LED driver output.
    led_levels: AtomicU8,
    indication: Mutex<Indication>,

    // Outputs.
    /// Position stream clients connected now.
    pub stream_clients: AtomicU64,
    /// Position stream clients accepted since start.
    pub stream_clients_total: AtomicU64,
    /// Stream clients disconnected because they could not keep up.
    pub stream_dropped_slow: AtomicU64,
    /// Stream connections refused because the client limit was reached.
    pub stream_refused: AtomicU64,
    /// Connection caps and sign-in throttle of the listeners (`/metrics`).
    pub net: crate::net::limit::NetCounters,
    /// Position records written to stream clients, all clients together.
    pub stream_records_sent: AtomicU64,
    /// Published records the stream hub never saw because a newer one replaced them in the slot.
    pub slot_overwrites: AtomicU64,
    /// Open live WebSocket sessions (set-up view).
    pub live_viewers: AtomicU64,

    /// The active parameter set's description; read with [`Self::params_info`].
    pub params: Mutex<ParamsInfo>,
    /// Real-time settings applied or refused at start (scheduling, CPU affinity, memory lock), one
    /// line each.
    pub realtime: Mutex<Vec<String>>,
    /// `[cluster] transport_fifo_priority`: what the last pass over Zenoh's transport threads
    /// did (`rt::watch_transport_threads`); shown after `realtime`'s lines.
    pub realtime_transport: Mutex<Option<String>>,
    /// Counters of the standard outputs (set once by `app::start`).
    pub outputs: std::sync::OnceLock<crate::outputs::stats::OutputsStats>,
    /// The viewers' hand-off from the loop, for its copy and drop counters on `/metrics` (set
    /// once by `app::start`).
    pub viewer_tap: std::sync::OnceLock<Arc<crate::viewer::ViewerTap>>,
    /// Camera and solver roles: the cluster's state (docs/cluster.md); `None` standalone.
    pub cluster: Mutex<Option<Arc<Mutex<crate::cluster::report::ClusterReport>>>>,
    /// ptp4l's state as its management socket reports it (set once by `app::start` when
    /// `[clock] ptp` is on).
    pub ptp: std::sync::OnceLock<crate::ptp::monitor::SharedPtp>,
    /// The robot link's status (set once by `app::start` when `[robot]` is configured): its
    /// packet counters on `/metrics`, its refusals in the fault texts.
    pub robot_link: std::sync::OnceLock<tokio::sync::watch::Receiver<irtrack_robot::LinkStatus>>,
}

fn track_to_u8(t: TrackIndication) -> u8 {
    match t {
        TrackIndication::None => 0,
        TrackIndication::Partial => 1,
        TrackIndication::All => 2,
    }
}

fn robot_to_u8(r: RobotIndication) -> u8 {
    match r {
        RobotIndication::Disconnected => 0,
        RobotIndication::Connected => 1,
        RobotIndication::Holding => 2,
    }
}

impl SharedStatus {
    /// All counters zero for `camera_count` cameras, clock of `uptime_s` started now.
    pub fn new(camera_count: usize, source_description: String, led_backend: String) -> Self {
        Self {
            outputs: std::sync::OnceLock::new(),
            viewer_tap: std::sync::OnceLock::new(),
            started: Instant::now(),
            source_description,
            led_backend,
            cameras: (0..camera_count).map(|_| CameraCounters::default()).collect(),
            loop_iterations: AtomicU64::new(0),
            sets_processed: AtomicU64::new(0),
            published: AtomicU64::new(0),
            tracked: AtomicU64::new(0),
            lost: AtomicU64::new(0),
            gated: AtomicU64::new(0),
            deadline_ns: AtomicU64::new(0),
            deadline_misses: AtomicU64::new(0),
            source_errors: AtomicU64::new(0),
            pipeline_errors: AtomicU64::new(0),
            stale_sets: AtomicU64::new(0),
            skewed_sets: AtomicU64::new(0),
            skewed_last_ns: AtomicU64::new(0),
            skewed_last_spread_ns: AtomicU64::new(0),
            timing: Mutex::new(None),
            stages: StageHistograms::default(),
            last_gap_mm_bits: AtomicU64::new(f64::NAN.to_bits()),
            sets_delivered: AtomicU64::new(0),
            sets_dropped: AtomicU64::new(0),
            unpaired_dropped: AtomicU64::new(0),
            reconnects: AtomicU64::new(0),
            pairing_error_last_ns: AtomicU64::new(0),
            pairing_error_max_ns: AtomicU64::new(0),
            params_loaded: AtomicBool::new(false),
            detection_only: AtomicBool::new(false),
            camera_lost: AtomicBool::new(false),
            track: AtomicU8::new(0),
            robot: AtomicU8::new(0),
            deadline_fault: AtomicBool::new(false),
            alive: AtomicBool::new(false),
            source_ended: AtomicBool::new(false),
            end_reason: Mutex::new(None),
            source_waiting: Mutex::new(None),
            led_levels: AtomicU8::new(0),
            indication: Mutex::new(Indication::STARTING),
            stream_clients: AtomicU64::new(0),
            stream_clients_total: AtomicU64::new(0),
            stream_refused: AtomicU64::new(0),
            net: crate::net::limit::NetCounters::default(),
            stream_dropped_slow: AtomicU64::new(0),
            stream_records_sent: AtomicU64::new(0),
            slot_overwrites: AtomicU64::new(0),
            live_viewers: AtomicU64::new(0),
            params: Mutex::new(ParamsInfo::default()),
            realtime: Mutex::new(Vec::new()),
            realtime_transport: Mutex::new(None),
            cluster: Mutex::new(None),
            ptp: std::sync::OnceLock::new(),
            robot_link: std::sync::OnceLock::new(),
        }
    }

    /// Seconds since this status was created (the service's start).
    pub fn uptime_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Sets what the track LED shows; called by the loop after each set.
    pub fn set_track(&self, t: TrackIndication) {
        self.track.store(track_to_u8(t), R);
    }

    /// What the track LED should show.
    pub fn track(&self) -> TrackIndication {
        match self.track.load(R) {
            2 => TrackIndication::All,
            1 => TrackIndication::Partial,
            _ => TrackIndication::None,
        }
    }

    /// Robot LED state; called by the robot link client.
    pub fn set_robot(&self, r: RobotIndication) {
        self.robot.store(robot_to_u8(r), R);
    }

    /// What the robot LED should show.
    pub fn robot(&self) -> RobotIndication {
        match self.robot.load(R) {
            1 => RobotIndication::Connected,
            2 => RobotIndication::Holding,
            _ => RobotIndication::Disconnected,
        }
    }

    /// All active faults, most important first.
    pub fn active_faults(&self) -> Vec<Fault> {
        let mut f = Vec::new();
        if self.camera_lost.load(R) {
            f.push(Fault::CameraLost);
        }
        if !self.params_loaded.load(R) && !self.detection_only.load(R) {
            f.push(Fault::NoParams);
        }
        if self.deadline_fault.load(R) {
            f.push(Fault::DeadlineMisses);
        }
        f
    }

    /// The fault the LED shows (no allocation; called by the LED driver every tick).
    pub fn top_fault(&self) -> Option<Fault> {
        if self.camera_lost.load(R) {
            Some(Fault::CameraLost)
        } else if !self.params_loaded.load(R) && !self.detection_only.load(R) {
            Some(Fault::NoParams)
        } else if self.deadline_fault.load(R) {
            Some(Fault::DeadlineMisses)
        } else {
            None
        }
    }

    pub(crate) fn set_led_output(&self, ind: Indication, levels: [bool; 4]) {
        let bits = levels
            .iter()
            .enumerate()
            .fold(0u8, |acc, (i, &on)| acc | (u8::from(on) << i));
        self.led_levels.store(bits, R);
        if let Ok(mut g) = self.indication.lock() {
            *g = ind;
        }
    }

    /// The LEDs as last driven: run, track, robot, fault (on = `true`).
    pub fn led_levels(&self) -> [bool; 4] {
        let bits = self.led_levels.load(R);
        [bits & 1 != 0, bits & 2 != 0, bits & 4 != 0, bits & 8 != 0]
    }

    /// The state the LED driver last displayed.
    pub fn indication(&self) -> Indication {
        self.indication.lock().map(|g| *g).unwrap_or(Indication::STARTING)
    }

    /// A copy of the active parameter set's description.
    pub fn params_info(&self) -> ParamsInfo {
        self.params.lock().map(|g| g.clone()).unwrap_or_default()
    }

    /// Changes the parameter set's description under its lock.
    pub fn update_params_info(&self, f: impl FnOnce(&mut ParamsInfo)) {
        if let Ok(mut g) = self.params.lock() {
            f(&mut g);
        }
    }

    /// Per-camera frame rate from the averaged capture interval.
    pub fn camera_fps(&self, camera: usize) -> Option<f64> {
        let c = self.cameras.get(camera)?;
        let ns = f64::from_bits(c.interval_ewma_ns.load(R));
        (ns.is_finite() && ns > 0.0).then(|| 1e9 / ns)
    }

    /// Builds the JSON status document.
    pub fn report(&self) -> StatusReport {
        let latency_us = self
            .stages
            .stages()
            .map(|(name, h)| (name, h.snapshot().summary()));
        StatusReport {
            service: "irtrackd",
            versions: Versions {
                irtrackd: env!("CARGO_PKG_VERSION"),
                param_blob_format: irtrack_core::params::BLOB_FORMAT_VERSION,
                stream_binary: irtrack_core::stream::BINARY_VERSION,
            },
            uptime_s: self.uptime_s(),
            params: self.params_info().aged(crate::calibration::now_unix_s()),
            source: SourceReport {
                description: self.source_description.clone(),
                sets_delivered: self.sets_delivered.load(R),
                sets_dropped: self.sets_dropped.load(R),
                unpaired_dropped: self.unpaired_dropped.load(R),
                reconnects: self.reconnects.load(R),
                pairing_error_last_us: self.pairing_error_last_ns.load(R) as f64 / 1e3,
                pairing_error_max_us: self.pairing_error_max_ns.load(R) as f64 / 1e3,
                waiting: self.source_waiting.lock().ok().and_then(|w| w.clone()),
                cameras: self
                    .cameras
                    .iter()
                    .enumerate()
                    .map(|(i, c)| CameraReport {
                        index: i,
                        frames: c.frames.load(R),
                        fps: self.camera_fps(i),
                        width_px: c.width_px.load(R),
                        height_px: c.height_px.load(R),
                        blobs_last: c.blobs_last.load(R),
                        peak_dn: c.peak_dn.load(R),
                        clock: c.clock.report(),
                        bridge_ms_last: Some(f64::from_bits(c.bridge_ns_last_bits.load(R)) / 1e6)
                            .filter(|v| v.is_finite()),
                        bridge_ms_max: Some(f64::from_bits(c.bridge_ns_max_bits.load(R)) / 1e6)
                            .filter(|v| v.is_finite()),
                        unbridged: c.unbridged.load(R),
                    })
                    .collect(),
            },
            processing: LoopReport {
                iterations: self.loop_iterations.load(R),
                sets_processed: self.sets_processed.load(R),
                published: self.published.load(R),
                tracked: self.tracked.load(R),
                lost: self.lost.load(R),
                gated: self.gated.load(R),
                last_gap_mm: Some(f64::from_bits(self.last_gap_mm_bits.load(R))).filter(|g| g.is_finite()),
                deadline_us: self.deadline_ns.load(R) as f64 / 1e3,
                deadline_misses: self.deadline_misses.load(R),
                source_errors: self.source_errors.load(R),
                pipeline_errors: self.pipeline_errors.load(R),
                stale_sets: self.stale_sets.load(R),
                skewed_sets: self.skewed_sets.load(R),
                timing: self.timing.lock().ok().and_then(|g| g.clone()),
                source_ended: self.source_ended.load(R),
                end_reason: self.end_reason.lock().ok().and_then(|r| r.clone()),
                latency_us: latency_us.into_iter().collect(),
                realtime: {
                    let mut lines = self.realtime.lock().map(|g| g.clone()).unwrap_or_default();
                    if let Ok(g) = self.realtime_transport.lock() {
                        lines.extend(g.iter().cloned());
                    }
                    lines
                },
            },
            stream: StreamReport {
                clients: self.stream_clients.load(R),
                clients_total: self.stream_clients_total.load(R),
                dropped_slow: self.stream_dropped_slow.load(R),
                refused: self.stream_refused.load(R),
                records_sent: self.stream_records_sent.load(R),
                slot_overwrites: self.slot_overwrites.load(R),
            },
            leds: LedReport {
                backend: self.led_backend.clone(),
                indication: self.indication(),
                on: {
                    let l = self.led_levels();
                    LedLevels {
                        run: l[0],
                        track: l[1],
                        robot: l[2],
                        fault: l[3],
                    }
                },
            },
            faults: self.active_faults(),
            cluster: self.cluster_report(),
            clock: self.ptp_report().map(|ptp| ClockReport { ptp }),
        }
    }

    /// ptp4l's state, when irtrackd polls it (`[clock] ptp = true`).
    pub fn ptp_report(&self) -> Option<crate::ptp::monitor::PtpReport> {
        Some(self.ptp.get()?.lock().ok()?.report())
    }

    /// A copy of the cluster state, when this irtrackd is a camera board or a solver.
    pub fn cluster_report(&self) -> Option<crate::cluster::report::ClusterReport> {
        let shared = self.cluster.lock().ok()?.clone()?;
        let mut r = shared.lock().ok()?.clone();
        r.detection_only = self.detection_only.load(R);
        let hop = r.hop.0.snapshot();
        r.hop_us = (hop.count() > 0).then(|| hop.summary());
        Some(r)
    }

    /// OpenMetrics text exposition, encoded by `prometheus-client` from a snapshot of the
    /// counters (read once, so one scrape is consistent with itself).
    pub fn prometheus(&self) -> String {
        let info = self.params_info();
        // Counter names without `_total`: the encoder appends it.
        let counters: [(&'static str, &'static str, u64); 18] = [
            (
                "irtrackd_sets_processed",
                "frame sets processed",
                self.sets_processed.load(R),
            ),
            (
                "irtrackd_positions_published",
                "positions published",
                self.published.load(R),
            ),
            (
                "irtrackd_tracked",
                "sets with a gated 3-D position",
                self.tracked.load(R),
            ),
            ("irtrackd_lost", "sets without a position", self.lost.load(R)),
            (
                "irtrackd_gated",
                "positions rejected by the quality gate",
                self.gated.load(R),
            ),
            (
                "irtrackd_deadline_misses",
                "sets processed slower than the frame period",
                self.deadline_misses.load(R),
            ),
            (
                "irtrackd_stale_sets",
                "duplicated or reordered sets dropped",
                self.stale_sets.load(R),
            ),
            (
                "irtrackd_skewed_sets",
                "sets refused for camera timestamp skew",
                self.skewed_sets.load(R),
            ),
            (
                "irtrackd_source_errors",
                "frame source errors",
                self.source_errors.load(R),
            ),
            (
                "irtrackd_sets_dropped",
                "frame sets dropped by the source",
                self.sets_dropped.load(R),
            ),
            (
                "irtrackd_unpaired_dropped",
                "frames without a partner",
                self.unpaired_dropped.load(R),
            ),
            (
                "irtrackd_camera_reconnects",
                "camera reopen count",
                self.reconnects.load(R),
            ),
            (
                "irtrackd_stream_dropped_slow",
                "stream clients dropped as too slow",
                self.stream_dropped_slow.load(R),
            ),
            (
                "irtrackd_stream_refused",
                "stream connections refused at the client limit",
                self.stream_refused.load(R),
            ),
            (
                "irtrackd_stream_records_sent",
                "records queued to stream clients",
                self.stream_records_sent.load(R),
            ),
            (
                "irtrackd_slot_overwrites",
                "results replaced before the stream saw them",
                self.slot_overwrites.load(R),
            ),
            (
                "irtrackd_params_rejected",
                "parameter pushes rejected",
                info.rejected,
            ),
            (
                "irtrackd_signin_throttled",
                "operator sign-ins refused by the throttle",
                self.net.signin_throttled.load(R),
            ),
        ];
        let listeners = self.net.listeners().map(|(name, c)| ListenerSnapshot {
            name,
            open: c.open.load(R),
            accepted: c.accepted.load(R),
            refused_listener_cap: c.refused_listener_cap.load(R),
            refused_peer_cap: c.refused_peer_cap.load(R),
            timeouts: c.timeouts.load(R),
            evicted: c.evicted.load(R),
        });
        let mut counters = counters.to_vec();
        counters.extend([
            (
                "irtrackd_params_rollbacks_refused",
                "parameter pushes refused as older than the active set",
                info.rollbacks_refused,
            ),
            (
                "irtrackd_params_rollbacks_allowed",
                "older parameter sets activated because the push allowed a rollback",
                info.rollbacks_allowed,
            ),
        ]);
        if let Some(tap) = self.viewer_tap.get() {
            counters.extend([
                (
                    "irtrackd_viewer_frame_copies",
                    "frame copies the loop made for viewers (at the preview rate)",
                    tap.copies(),
                ),
                (
                    "irtrackd_viewer_frame_copy_skips",
                    "frame copies the loop skipped because a viewer held the copy",
                    tap.busy_skips(),
                ),
                (
                    "irtrackd_viewer_blob_copies",
                    "blob-only copies the loop made for viewers",
                    tap.blob_copies(),
                ),
                (
                    "irtrackd_viewer_blob_copy_skips",
                    "blob copies the loop skipped because a viewer held the copy",
                    tap.blob_busy_skips(),
                ),
                (
                    "irtrackd_viewer_sets_dropped",
                    "sets whose blob lists a viewer did not send (it saw only a newer set), summed over viewers",
                    tap.viewer_dropped_sets(),
                ),
            ]);
        }
        let snapshot = MetricsSnapshot {
            live_viewers: self.live_viewers.load(R),
            counters,
            version: env!("CARGO_PKG_VERSION"),
            rig_id: info.rig_id.unwrap_or_default(),
            params_loaded: info.loaded,
            stream_clients: self.stream_clients.load(R),
            pairing_error_s: self.pairing_error_last_ns.load(R) as f64 / 1e9,
            camera_fps: (0..self.cameras.len())
                .map(|i| self.camera_fps(i).unwrap_or(0.0))
                .collect(),
            camera_frames: self.cameras.iter().map(|c| c.frames.load(R)).collect(),
            camera_clocks: self.cameras.iter().map(|c| c.clock.report()).collect(),
            camera_bridges: self
                .cameras
                .iter()
                .map(|c| {
                    (
                        f64::from_bits(c.bridge_ns_last_bits.load(R)) / 1e9,
                        c.unbridged.load(R),
                    )
                })
                .collect(),
            leds: self.led_levels(),
            faults: self.active_faults(),
            stages: self.stages.stages().map(|(name, h)| (name, h.snapshot())),
            listeners,
            ws_timeouts: [
                ("send", self.net.ws_send_timeouts.load(R)),
                ("silence", self.net.ws_silence_timeouts.load(R)),
            ],
        };
        let mut registry = prometheus_client::registry::Registry::default();
        registry.register_collector(Box::new(snapshot));
        if let Some(outputs) = self.outputs.get() {
            registry.register_collector(Box::new(outputs.metrics()));
        }
        if let Some(cluster) = self.cluster_report() {
            registry.register_collector(Box::new(cluster));
        }
        if let Some(ptp) = self.ptp_report() {
            registry.register_collector(Box::new(ptp));
        }
        if let Some(link) = self.robot_link.get() {
            registry.register_collector(Box::new(crate::metrics::RobotLinkMetrics::from(&*link.borrow())));
        }
        let mut s = String::with_capacity(8 * 1024);
        // Writing into a String cannot fail; an encoder error would be a bug in a metric.
        if let Err(e) = prometheus_client::encoding::text::encode(&mut s, &registry) {
            s = format!("# metrics encoding failed: {e}\n");
        }
        s
    }
}

/// The `le` edges (µs) of the exported classic histogram (the former fixed buckets).
const PROMETHEUS_LE_US: [u64; 20] = [
    25, 50, 100, 200, 300, 500, 750, 1_000, 1_500, 2_000, 3_000, 5_000, 7_500, 10_000, 15_000, 20_000,
    33_000, 50_000, 100_000, 250_000,
];

/// Exemplar label type for histograms without exemplars.
type NoLabels = Vec<(String, String)>;

/// The values of one scrape, encoded by [`prometheus_client`].
#[derive(Debug)]
struct MetricsSnapshot {
    counters: Vec<(&'static str, &'static str, u64)>,
    version: &'static str,
    rig_id: String,
    params_loaded: bool,
    stream_clients: u64,
    live_viewers: u64,
    pairing_error_s: f64,
    camera_fps: Vec<f64>,
    camera_frames: Vec<u64>,
    camera_clocks: Vec<Option<CameraClockReport>>,
    /// Per camera: the newest bridge (s) and the unbridged blobs so far.
    camera_bridges: Vec<(f64, u64)>,
    leds: [bool; 4],
    faults: Vec<Fault>,
    stages: [(&'static str, crate::metrics::HistogramSnapshot); STAGES],
    listeners: [ListenerSnapshot; 4],
    /// Live WebSocket sessions ended by a timeout, by reason (`send`, `silence`).
    ws_timeouts: [(&'static str, u64); 2],
}

/// One listener's connection counters in a scrape.
#[derive(Debug)]
struct ListenerSnapshot {
    name: &'static str,
    open: u64,
    accepted: u64,
    refused_listener_cap: u64,
    refused_peer_cap: u64,
    timeouts: u64,
    evicted: u64,
}

impl MetricsSnapshot {
    /// Each camera's clock model (docs/timing.md, "Camera clocks"): gauges in seconds and
    /// ppm, counters of drops, duplicates and jumps. A camera whose model has no value yet is
    /// left out of that family.
    fn encode_camera_clocks(
        &self,
        enc: &mut prometheus_client::encoding::DescriptorEncoder<'_>,
    ) -> std::result::Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        type Pick = fn(&CameraClockReport) -> Option<f64>;
        let gauges: [(&str, &str, Pick); 6] = [
            (
                "irtrackd_camera_period_seconds",
                "measured frame period per camera (clock model)",
                |c| c.period_us.map(|v| v / 1e6),
            ),
            (
                "irtrackd_camera_phase_seconds",
                "exposure after camera 0's nearest frame (negative: before)",
                |c| c.phase_us.map(|v| v / 1e6),
            ),
            (
                "irtrackd_camera_jitter_rms_seconds",
                "RMS timestamp distance from the camera's clock line",
                |c| c.jitter_rms_us.map(|v| v / 1e6),
            ),
            (
                "irtrackd_camera_jitter_max_seconds",
                "largest recent timestamp distance from the camera's clock line",
                |c| c.jitter_max_us.map(|v| v / 1e6),
            ),
            (
                "irtrackd_camera_drift_ppm",
                "phase drift against camera 0, ppm of elapsed time (positive: later and later)",
                |c| c.drift_ppm,
            ),
            (
                "irtrackd_camera_rate_error_ppm",
                "frame rate against the configured one, ppm (positive: fast)",
                |c| c.rate_error_ppm,
            ),
        ];
        for (name, help, pick) in gauges {
            let mut m = enc.encode_descriptor(name, help, None, MetricType::Gauge)?;
            for (i, c) in self.camera_clocks.iter().enumerate() {
                if let Some(v) = c.as_ref().and_then(pick) {
                    ConstGauge::new(v).encode(m.encode_family(&[("camera", i.to_string())])?)?;
                }
            }
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_camera_clock_locked",
            "1 when the camera's clock model is locked (smoothed instants in use)",
            None,
            MetricType::Gauge,
        )?;
        for (i, c) in self.camera_clocks.iter().enumerate() {
            let locked = c.as_ref().is_some_and(|c| c.state == "locked");
            ConstGauge::new(i64::from(locked)).encode(m.encode_family(&[("camera", i.to_string())])?)?;
        }
        type Count = fn(&CameraClockReport) -> u64;
        let counters: [(&str, &str, Count); 3] = [
            (
                "irtrackd_camera_frames_dropped",
                "frames missing from the camera's sequence",
                |c| c.drops,
            ),
            (
                "irtrackd_camera_frames_duplicated",
                "frames the camera delivered twice",
                |c| c.duplicates,
            ),
            (
                "irtrackd_camera_clock_jumps",
                "timestamp steps the clock model could not explain (re-locked)",
                |c| c.jumps,
            ),
        ];
        for (name, help, count) in counters {
            let mut m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            for (i, c) in self.camera_clocks.iter().enumerate() {
                let n = c.as_ref().map_or(0, count);
                ConstCounter::new(n).encode(m.encode_family(&[("camera", i.to_string())])?)?;
            }
        }
        // Time-true tracking: how far each camera's track was carried, and what it could not.
        let mut m = enc.encode_descriptor(
            "irtrackd_camera_bridge_seconds",
            "how far the camera's newest marker blob was carried along its track to the set's instant",
            None,
            MetricType::Gauge,
        )?;
        for (i, (bridge_s, _)) in self.camera_bridges.iter().enumerate() {
            if bridge_s.is_finite() {
                ConstGauge::new(*bridge_s).encode(m.encode_family(&[("camera", i.to_string())])?)?;
            }
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_camera_unbridged_blobs",
            "gated blobs left out because they could not be brought to the set's instant",
            None,
            MetricType::Counter,
        )?;
        for (i, (_, n)) in self.camera_bridges.iter().enumerate() {
            ConstCounter::new(*n).encode(m.encode_family(&[("camera", i.to_string())])?)?;
        }
        Ok(())
    }
}

impl prometheus_client::collector::Collector for MetricsSnapshot {
    fn encode(
        &self,
        mut enc: prometheus_client::encoding::DescriptorEncoder,
    ) -> std::result::Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        for (name, help, v) in &self.counters {
            let c = ConstCounter::new(*v);
            c.encode(enc.encode_descriptor(name, help, None, c.metric_type())?)?;
        }
        let info = prometheus_client::metrics::info::Info::new(vec![
            ("version", self.version.to_string()),
            ("rig_id", self.rig_id.clone()),
        ]);
        // `Info` appends `_info`: the metric is `irtrackd_info`.
        info.encode(enc.encode_descriptor(
            "irtrackd",
            "build and parameter set",
            None,
            info.metric_type(),
        )?)?;
        let g = ConstGauge::new(i64::from(self.params_loaded));
        g.encode(enc.encode_descriptor(
            "irtrackd_params_loaded",
            "1 when a valid parameter set is in use",
            None,
            g.metric_type(),
        )?)?;
        let g = ConstGauge::new(self.stream_clients as i64);
        g.encode(enc.encode_descriptor(
            "irtrackd_stream_clients",
            "connected stream clients",
            None,
            g.metric_type(),
        )?)?;
        let g = ConstGauge::new(self.live_viewers as i64);
        g.encode(enc.encode_descriptor(
            "irtrackd_live_viewers",
            "open live WebSocket sessions (set-up views)",
            None,
            g.metric_type(),
        )?)?;
        let g = ConstGauge::new(self.pairing_error_s);
        g.encode(enc.encode_descriptor(
            "irtrackd_pairing_error_seconds",
            "capture time spread of the last frame set",
            None,
            g.metric_type(),
        )?)?;
        let mut m = enc.encode_descriptor(
            "irtrackd_camera_fps",
            "frames per second per camera",
            None,
            MetricType::Gauge,
        )?;
        for (i, fps) in self.camera_fps.iter().enumerate() {
            let labels = [("camera", i.to_string())];
            ConstGauge::new(*fps).encode(m.encode_family(&labels)?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_camera_frames",
            "frames received per camera",
            None,
            MetricType::Counter,
        )?;
        for (i, n) in self.camera_frames.iter().enumerate() {
            let labels = [("camera", i.to_string())];
            ConstCounter::new(*n).encode(m.encode_family(&labels)?)?;
        }
        self.encode_camera_clocks(&mut enc)?;
        let mut m = enc.encode_descriptor(
            "irtrackd_connections_open",
            "connections open per listener",
            None,
            MetricType::Gauge,
        )?;
        for l in &self.listeners {
            ConstGauge::new(l.open as i64).encode(m.encode_family(&[("listener", l.name)])?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_connections_accepted",
            "connections accepted per listener",
            None,
            MetricType::Counter,
        )?;
        for l in &self.listeners {
            ConstCounter::new(l.accepted).encode(m.encode_family(&[("listener", l.name)])?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_connections_refused",
            "connections closed by a cap (reason: listener or peer = refused at once; evicted = \
             an unanswered exchange closed to admit a new connection at the listener cap)",
            None,
            MetricType::Counter,
        )?;
        for l in &self.listeners {
            for (reason, n) in [
                ("listener", l.refused_listener_cap),
                ("peer", l.refused_peer_cap),
                ("evicted", l.evicted),
            ] {
                let labels = [("listener", l.name), ("reason", reason)];
                ConstCounter::new(n).encode(m.encode_family(&labels)?)?;
            }
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_connection_timeouts",
            "connections ended by a timeout per listener",
            None,
            MetricType::Counter,
        )?;
        for l in &self.listeners {
            ConstCounter::new(l.timeouts).encode(m.encode_family(&[("listener", l.name)])?)?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_websocket_timeouts",
            "live WebSocket sessions ended by a timeout (reason: send = a message not taken in \
             time, silence = no pong or message back in time)",
            None,
            MetricType::Counter,
        )?;
        for (reason, n) in self.ws_timeouts {
            ConstCounter::new(n).encode(m.encode_family(&[("reason", reason)])?)?;
        }
        let mut m = enc.encode_descriptor("irtrackd_led_on", "status LED levels", None, MetricType::Gauge)?;
        for (led, on) in ["run", "track", "robot", "fault"].iter().zip(self.leds) {
            let labels = [("led", *led)];
            ConstGauge::new(i64::from(on)).encode(m.encode_family(&labels)?)?;
        }
        let mut m = enc.encode_descriptor("irtrackd_fault", "active faults", None, MetricType::Gauge)?;
        for (f, name) in [
            (Fault::CameraLost, "camera_lost"),
            (Fault::NoParams, "no_params"),
            (Fault::DeadlineMisses, "deadline_misses"),
        ] {
            let labels = [("fault", name)];
            ConstGauge::new(i64::from(self.faults.contains(&f))).encode(m.encode_family(&labels)?)?;
        }
        // The loop records latencies into lock-free log-linear buckets (it must neither lock
        // nor allocate). Exported twice: as a classic histogram on fixed, coarse `le` edges
        // (counted from the fine buckets, so dashboards can aggregate it), and as the true
        // percentiles (within 1.6 %), which the coarse edges cannot give.
        let mut m = enc.encode_descriptor(
            "irtrackd_stage_latency_seconds",
            "processing stage latency",
            None,
            MetricType::Histogram,
        )?;
        for (name, h) in &self.stages {
            let mut buckets: Vec<(f64, u64)> = PROMETHEUS_LE_US
                .iter()
                .map(|&le_us| (le_us as f64 / 1e6, h.count_at_most_ns(le_us as f64 * 1e3)))
                .collect();
            // The encoder takes per-bucket counts and accumulates them itself.
            for i in (1..buckets.len()).rev() {
                buckets[i].1 -= buckets[i - 1].1;
            }
            let below: u64 = buckets.iter().map(|b| b.1).sum();
            buckets.push((f64::INFINITY, h.count() - below));
            let labels = [("stage", *name)];
            m.encode_family(&labels)?.encode_histogram::<NoLabels>(
                h.sum_ns as f64 / 1e9,
                h.count(),
                &buckets,
                None,
            )?;
        }
        let mut m = enc.encode_descriptor(
            "irtrackd_stage_latency_quantile_seconds",
            "processing stage latency percentiles since start (log-linear histogram, within 1.6 %)",
            None,
            MetricType::Gauge,
        )?;
        for (name, h) in &self.stages {
            for (q, label) in [
                (0.5, "0.5"),
                (0.9, "0.9"),
                (0.99, "0.99"),
                (0.999, "0.999"),
                (1.0, "1"),
            ] {
                if let Some(ns) = h.quantile_ns(q) {
                    let labels = [("stage", *name), ("quantile", label)];
                    ConstGauge::new(ns / 1e9).encode(m.encode_family(&labels)?)?;
                }
            }
        }
        Ok(())
    }
}

/// One fault in plain words with what to do about it (the set-up view's health panel).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FaultText {
    /// Stable code: `camera_lost`, `no_params`, `deadline_misses`, `no_led`, `no_usable_blob`,
    /// `skewed_sets`, `ptp_unavailable`, `ptp_faulty`, `robot_packets_refused` (the EGM/RSI
    /// link refused packets in the last 10 s), `recording_failed` (the MCAP recording cannot
    /// write), and from the whole-frame analysis
    /// `background_above_threshold`, `overloaded`, `too_many_spots`, `more_spots_than_leds`,
    /// `unreadable_frame`.
    pub code: &'static str,
    /// The camera concerned; `None` for faults of the whole board.
    pub camera: Option<usize>,
    /// What is wrong and the next step, one sentence.
    pub message: String,
}

/// The `skewed_sets` fault: within [`SKEW_FAULT_HOLD_NS`] of a set whose cameras' frames were
/// further apart than time-true tracking can bridge (or, with `time_mode = "off"`, than the
/// pairing limit).
fn skew_fault_text(st: &SharedStatus, now_ns: u64) -> Option<FaultText> {
    let last = st.skewed_last_ns.load(R);
    if last == 0 || now_ns.saturating_sub(last) > SKEW_FAULT_HOLD_NS {
        return None;
    }
    let spread_ms = st.skewed_last_spread_ns.load(R) as f64 / 1e6;
    let limit = match st.timing.lock().ok().and_then(|g| g.clone()) {
        Some(t) if t.mode != "off" => format!(
            "the {:.1} ms the cameras' tracks may be carried (`max_bridge_ms`)",
            t.max_bridge_ms
        ),
        _ => "the pairing limit (`time_mode = \"off\"` needs cameras exposing together)".to_string(),
    };
    Some(FaultText {
        code: "skewed_sets",
        camera: None,
        message: format!(
            "the cameras' frames of a set were {spread_ms:.1} ms apart, more than {limit}: those sets get no position ({} so far) — check that every camera runs at the same frame rate and none drops frames (the clock column)",
            st.skewed_sets.load(R)
        ),
    })
}

/// The active faults in plain words. `threshold_dn`: the detector's current threshold, when
/// known (enables the "threshold above the LED" diagnosis). `analysis`: the newest whole-frame
/// analysis of every camera, when fresh: it then describes each camera (background above the
/// threshold, overload, no LED, stray light only), with or without a parameter set, in the
/// same words the set-up view's camera cards show; without it the loop's counters are used.
pub fn fault_texts(
    st: &SharedStatus,
    threshold_dn: Option<u32>,
    analysis: Option<&[crate::advice::CameraAnalysis]>,
) -> Vec<FaultText> {
    let mut out = Vec::new();
    let reconnects = st.reconnects.load(R);
    // A solver's silent boards are its own faults (waiting_for_boards, board_down), not a cable.
    let silence_explained = st.cluster_report().is_some_and(|c| c.explains_silence());
    if st.camera_lost.load(R) && !silence_explained {
        out.push(FaultText {
            code: "camera_lost",
            camera: None,
            message: format!(
                "a camera is not delivering frames ({}) — check its cable and power; {reconnects} reconnect attempts so far",
                st.source_description
            ),
        });
    }
    if !st.params_loaded.load(R) && !st.detection_only.load(R) {
        out.push(FaultText {
            code: "no_params",
            camera: None,
            message: "no calibration (parameter set) is loaded, so no positions are computed — push one with `host-tools push-params`".into(),
        });
    }
    if st.deadline_fault.load(R) {
        out.push(FaultText {
            code: "deadline_misses",
            camera: None,
            message: format!(
                "processing is slower than the frame rate ({} deadline misses) — lower the frame rate or resolution, or close viewers",
                st.deadline_misses.load(R)
            ),
        });
    }
    if let Some(text) = skew_fault_text(st, crate::clock::monotonic_ns()) {
        out.push(text);
    }
    // A solver's own cameras it refuses (another image size than the parameter set's): the
    // `own_camera` fault names them; their missing blobs are no LED problem.
    let mut refused: Vec<usize> = Vec::new();
    if let Some(c) = st.cluster_report() {
        refused.clone_from(&c.own_refused_cameras);
        for (code, camera, message) in c.fault_texts() {
            out.push(FaultText {
                code,
                camera,
                message,
            });
        }
    }
    if let Some(p) = st.ptp_report() {
        if let Some(e) = p.error {
            out.push(FaultText {
                code: "ptp_unavailable",
                camera: None,
                message: format!("ptp4l's clock state cannot be read: {e}"),
            });
        } else if p.port_state == Some("FAULTY") {
            out.push(FaultText {
                code: "ptp_faulty",
                camera: None,
                message: "ptp4l's port is FAULTY — check the Ethernet link and `journalctl -u irtrack-ptp4l`"
                    .into(),
            });
        }
    }
    if let Some(link) = st.robot_link.get()
        && let Some(message) = link.borrow().refusal_fault(std::time::Instant::now())
    {
        out.push(FaultText {
            code: "robot_packets_refused",
            camera: None,
            message,
        });
    }
    // Outputs (a recording stopped by a full disk, ...): whatever the cameras do.
    if let Some(outputs) = st.outputs.get() {
        for (code, message) in outputs.fault_texts() {
            out.push(FaultText {
                code,
                camera: None,
                message,
            });
        }
    }
    if st.camera_lost.load(R) {
        return out;
    }
    if let Some(cams) = analysis {
        for a in cams.iter().filter(|a| !refused.contains(&a.camera)) {
            if let Some(adv) = &a.advice {
                out.push(FaultText {
                    code: adv.code,
                    camera: Some(a.camera),
                    message: adv.message.clone(),
                });
            }
        }
        return out;
    }
    let processing = st.sets_processed.load(R) > 0 && (st.params_loaded.load(R) || st.detection_only.load(R));
    if processing {
        for (i, c) in st.cameras.iter().enumerate() {
            if c.blobs_last.load(R) > 0 || c.frames.load(R) == 0 || refused.contains(&i) {
                continue;
            }
            let peak = c.peak_dn.load(R);
            match threshold_dn {
                Some(thr) if peak <= u64::from(thr) => out.push(FaultText {
                    code: "no_led",
                    camera: Some(i),
                    message: format!(
                        "camera {i}: no LED found: the threshold {thr} DN is above the brightest pixel {peak} DN — lower the threshold or raise exposure/gain"
                    ),
                }),
                _ => out.push(FaultText {
                    code: "no_usable_blob",
                    camera: Some(i),
                    message: format!(
                        "camera {i}: no usable blob although pixels reach {peak} DN — check the LED is in view and the blob area and roundness limits"
                    ),
                }),
            }
        }
    }
    out
}

/// Versions of this build and of the formats it speaks (`/status`).
#[derive(Debug, Clone, Serialize)]
pub struct Versions {
    /// This build's crate version.
    pub irtrackd: &'static str,
    /// Parameter blob format this build reads.
    pub param_blob_format: u16,
    /// Binary position framing version on the binary stream port.
    pub stream_binary: u8,
}

/// One camera's counters on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct CameraReport {
    /// Camera index, configuration order.
    pub index: usize,
    /// Frames received since start.
    pub frames: u64,
    /// Frame rate from the averaged capture interval, Hz; `None` before two frames.
    pub fps: Option<f64>,
    /// Frame width, pixels.
    pub width_px: u64,
    /// Frame height, pixels.
    pub height_px: u64,
    /// Blobs found in the latest frame.
    pub blobs_last: u64,
    /// Brightest pixel (DN) of the last processed frame.
    pub peak_dn: u64,
    /// The camera's clock model: period, phase against camera 0, jitter, drift, drops,
    /// duplicates and jumps; `None` before its first frame.
    pub clock: Option<CameraClockReport>,
    /// How far this camera's newest marker blob was carried along its track to the set's
    /// instant, ms (negative: back in time); 0 when solved as seen.
    pub bridge_ms_last: Option<f64>,
    /// The largest such distance since start, ms.
    pub bridge_ms_max: Option<f64>,
    /// Gated blobs left out because they could not be brought to the set's instant (no
    /// track yet, or further away in time than `max_bridge_ms`).
    pub unbridged: u64,
}

/// Time-true tracking on `/status` (`processing.timing`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimingReport {
    /// `accurate` (interpolated to the earliest exposure of the set), `low_latency`
    /// (extrapolated to the newest) or `off` (solved as seen).
    pub mode: &'static str,
    /// The mode in words, for the set-up page.
    pub mode_text: &'static str,
    /// How far a camera's track may be carried to the set's instant, ms.
    pub max_bridge_ms: f64,
}

impl TimingReport {
    /// The report for a tracker configuration.
    pub fn new(mode: irtrack_core::retime::TimeMode, max_bridge_ms: f64) -> Self {
        use irtrack_core::retime::TimeMode;
        let mode_text = match mode {
            TimeMode::Accurate => {
                "most accurate: each camera's track interpolated to the set's earliest exposure"
            }
            TimeMode::LowLatency => {
                "lowest latency: each camera's track extrapolated to the set's newest exposure"
            }
            TimeMode::Off => "off: blobs used where they were seen (only for cameras exposing together)",
        };
        Self {
            mode: mode.as_str(),
            mode_text,
            max_bridge_ms,
        }
    }
}

/// How long the `skewed_sets` fault stays after the last skewed set.
pub const SKEW_FAULT_HOLD_NS: u64 = 10_000_000_000;

/// The frame source's counters on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct SourceReport {
    /// The frame source in words.
    pub description: String,
    /// Sets the source delivered.
    pub sets_delivered: u64,
    /// Sets the source skipped.
    pub sets_dropped: u64,
    /// Frames dropped for lack of a partner in time.
    pub unpaired_dropped: u64,
    /// Times a camera was lost and reopened.
    pub reconnects: u64,
    /// Timestamp spread between the cameras of the latest set, µs.
    pub pairing_error_last_us: f64,
    /// Largest timestamp spread since start, µs.
    pub pairing_error_max_us: f64,
    /// What the source holds its first set for, in words (a replay waiting for a parameter
    /// set or a client); `null` while it runs.
    pub waiting: Option<String>,
    /// Per-camera counters, in camera order.
    pub cameras: Vec<CameraReport>,
}

/// The processing loop's counters and stage latencies on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct LoopReport {
    /// Passes of the processing loop.
    pub iterations: u64,
    /// Sets processed to publishing.
    pub sets_processed: u64,
    /// Records published.
    pub published: u64,
    /// Records with a position.
    pub tracked: u64,
    /// Records without a position (no marker, fault).
    pub lost: u64,
    /// Records the quality gate refused.
    pub gated: u64,
    /// Ray gap of the latest triangulated position, mm.
    pub last_gap_mm: Option<f64>,
    /// Processing time allowed per set, µs.
    pub deadline_us: f64,
    /// Sets that took longer than the deadline.
    pub deadline_misses: u64,
    /// Errors of the frame source.
    pub source_errors: u64,
    /// Detection or tracking failures.
    pub pipeline_errors: u64,
    /// Duplicated or reordered sets dropped unpublished.
    pub stale_sets: u64,
    /// Sets published without a position because their cameras' timestamps were too far apart.
    pub skewed_sets: u64,
    /// Time-true tracking: the mode sets are solved in and how far a track may be carried
    /// (docs/timing.md); `None` before the loop has started.
    pub timing: Option<TimingReport>,
    /// The source ended (replay finished) and the loop stopped.
    pub source_ended: bool,
    /// Why the source ended (replay: sets delivered of recorded, what was skipped and why).
    pub end_reason: Option<String>,
    /// Latency summary of each stage, µs, by stage name.
    pub latency_us: std::collections::BTreeMap<&'static str, LatencySummary>,
    /// Real-time settings applied or refused (one line each).
    pub realtime: Vec<String>,
}

/// The position stream's counters on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct StreamReport {
    /// Clients connected now.
    pub clients: u64,
    /// Clients accepted since start.
    pub clients_total: u64,
    /// Clients dropped for being too slow.
    pub dropped_slow: u64,
    /// Connections closed at once because `listen.max_stream_clients` were already connected.
    pub refused: u64,
    /// Records written to clients, all together.
    pub records_sent: u64,
    /// Records replaced in the slot before the stream hub read them.
    pub slot_overwrites: u64,
}

/// On/off state of each status LED.
#[derive(Debug, Clone, Serialize)]
pub struct LedLevels {
    /// Run LED (green): the loop is alive.
    pub run: bool,
    /// Track LED: markers seen.
    pub track: bool,
    /// Robot LED: robot link state.
    pub robot: bool,
    /// Fault LED (red).
    pub fault: bool,
}

/// The status LEDs on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct LedReport {
    /// The LED driver in use.
    pub backend: String,
    /// The state shown.
    pub indication: Indication,
    /// Which LEDs are on at this instant (blinking included).
    pub on: LedLevels,
}

/// The `/status` JSON document.
#[derive(Debug, Clone, Serialize)]
pub struct StatusReport {
    /// Always `"irtrackd"`.
    pub service: &'static str,
    /// Build and format versions.
    pub versions: Versions,
    /// Seconds since start.
    pub uptime_s: f64,
    /// The active parameter set.
    pub params: ParamsInfo,
    /// Frame source counters.
    pub source: SourceReport,
    /// Processing loop counters and latencies.
    pub processing: LoopReport,
    /// Position stream counters.
    pub stream: StreamReport,
    /// Status LEDs.
    pub leds: LedReport,
    /// Active faults, most important first.
    pub faults: Vec<Fault>,
    /// The cluster's state on a camera board or solver; absent standalone.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cluster: Option<crate::cluster::report::ClusterReport>,
    /// ptp4l's view of this board's clock; absent unless `[clock] ptp = true`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub clock: Option<ClockReport>,
}

/// `clock` on `/status`.
#[derive(Debug, Clone, Serialize)]
pub struct ClockReport {
    /// ptp4l's port state, offset and path delay (docs/cluster.md, "What `/status` shows").
    pub ptp: crate::ptp::monitor::PtpReport,
}
