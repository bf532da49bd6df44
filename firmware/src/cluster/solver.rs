//! Solver role: a [`FrameSource`] whose cameras are other boards' cameras. It subscribes to
//! the rig's observations, checks them ([`ObservationGate`]), pairs them into sets
//! ([`Pairer`]) and delivers each set with the boards' blobs as [`FrameSource::remote_blobs`];
//! the processing loop then triangulates and runs everything downstream as for local cameras.
//!
//! The camera ↔ board mapping is the active parameter set's placement (blob version 4). The
//! frames carry no pixels worth looking at (zeros of the calibrated size, so the parameter
//! service checks image sizes as for local cameras). Buffers are allocated when the parameter
//! set changes; receiving, pairing and delivering a set does not allocate.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use irtrack_cluster::clock::{ClockEstimator, Taken};
use irtrack_cluster::pairing::{Pairer, PairingConfig, PairingMode, PushOutcome};
use irtrack_cluster::transport::{ClockProber, ObsSubscriber, ProbeReply, Received, Session, realtime_ns};
use irtrack_core::blob::Blob;
use irtrack_core::image::GrayImage;
use irtrack_core::observation::{MAX_OBS_BLOBS, ObsClock, ObservationGate, ObservationProblem, decode};
use irtrack_core::pipeline::{Tracker, TrackerConfig};

use super::agreement::{Agreement, Cause};
use super::camera::CameraPublisher;
use super::report::ClockProbeReport;
use super::{BoardReport, ClusterConfig, ClusterReport};
use crate::clock;
use crate::engine::ObservationSink;
use crate::engine::ParamsHandle;
use crate::error::{FirmwareError, Result};
use crate::source::{
    CameraControl, CameraControls, Frame, FrameSet, FrameSource, Pixels, SourceError, SourceStats,
};

/// Observations further than this from the solver's clock are refused outright (a board
/// with a clock this wrong is not synchronised at all).
const MAX_TIMESTAMP_OFFSET_NS: u64 = 1_000_000_000;
/// A board whose measured clock offset exceeds this (or a quarter of the tolerance) is taken
/// as the culprit when it and one other board disagree.
const CLOCK_OFF_NS: i64 = 1_000_000;

/// Per board: its measured clock offset is beyond `limit_ns` ahead (`.0`) or behind (`.1`).
/// The measured offset is the board's clock minus ours less the transit, so *ahead* is a lower
/// bound no network delay explains: its timestamps are late against the others' (its cameras
/// are left out), taken as evidence while another board is not ahead. *Behind* may be its
/// clock or a slow link (a warning), flagged while another board is within the limit. All
/// boards off alike (our own clock off) misaligns nothing and flags none.
fn clock_flags(
    boards: &[irtrack_cluster::pairing::BoardClock],
    limit_ns: i64,
) -> (
    [bool; irtrack_core::pipeline::MAX_CAMERAS],
    [bool; irtrack_core::pipeline::MAX_CAMERAS],
) {
    let mut ahead = [false; irtrack_core::pipeline::MAX_CAMERAS];
    let mut behind = [false; irtrack_core::pipeline::MAX_CAMERAS];
    let not_ahead = boards.iter().any(|b| b.offset_ns.is_some_and(|o| o <= limit_ns));
    let in_line = boards
        .iter()
        .any(|b| b.offset_ns.is_some_and(|o| o.abs() <= limit_ns));
    for ((a, bh), b) in ahead.iter_mut().zip(behind.iter_mut()).zip(boards) {
        *a = not_ahead && b.offset_ns.is_some_and(|o| o > limit_ns);
        *bh = in_line && b.offset_ns.is_some_and(|o| o < -limit_ns);
    }
    (ahead, behind)
}
/// How often `/status` gets a fresh copy of the counters.
const REPORT_INTERVAL_NS: u64 = 200_000_000;
/// With no observation at all for this long, the source reports a timeout (camera fault).
const SILENCE_TIMEOUT_NS: u64 = 1_000_000_000;
/// `cluster.refused` code of observations whose sequence jumps further ahead than the time
/// since that camera's last observation allows.
const SEQUENCE_JUMP_CODE: &str = "sequence_jump";
/// A camera's sequence may step ahead by at most twice the frames the time since its last
/// accepted observation holds at `[cluster] fps`, plus this many seconds of frames (a board
/// whose observations were lost for a moment, a replay passing over late sets).
const SEQUENCE_SLACK_S: f64 = 1.0;

/// The last accepted observation of a rig camera: what the next one's sequence is checked
/// against.
#[derive(Debug, Clone, Copy)]
struct SequenceSeen {
    sequence: u64,
    received_ns: u64,
    capture_ns: u64,
}

/// The largest step a camera's sequence may take ahead after `elapsed_ns` without
/// observations of it, at `fps` frames per second.
fn max_sequence_step(elapsed_ns: u64, fps: f64) -> u64 {
    let frames = (elapsed_ns as f64 / 1e9 * fps * 2.0 + SEQUENCE_SLACK_S * fps).ceil();
    (frames as u64).max(64)
}

/// The rig's layout from the active parameter set.
struct Layout {
    gate: ObservationGate,
    pairer: Pairer,
    /// Do the boards' rays agree (checked after every solve)?
    agreement: Agreement,
    boards: Vec<String>,
    board_cameras: Vec<Vec<usize>>,
}

/// The solver's [`FrameSource`].
pub struct ClusterSource {
    cfg: ClusterConfig,
    session: Session,
    sub: ObsSubscriber,
    rx: Receiver<Received>,
    params: Arc<ParamsHandle>,
    seen_generation: u64,
    layout: Option<Layout>,
    board_last_ns: Vec<Option<u64>>,
    remote: Vec<Vec<Blob>>,
    stats: SourceStats,
    report: Arc<Mutex<ClusterReport>>,
    refused: [u64; ObservationProblem::CODES.len()],
    received: u64,
    last_any_ns: u64,
    last_report_ns: u64,
    /// The report's hop histogram (recorded here, summarised by `/status`).
    hop: Arc<crate::metrics::LatencyHistogram>,
    /// Hops are recorded from this receive time on (1 s after the first observation: the
    /// links' set-up is not the steady state); `None` before the first.
    hop_from_ns: Option<u64>,
    /// The last set's frame number (`None` before the first set).
    last_index: Option<u64>,
    /// The solver's own cameras (`own_cameras = true`).
    own: Option<OwnCameras>,
    /// Per rig camera: its index among the solver's own cameras, when the parameter set
    /// places it on this board and its image size matches (`None`: a camera board's camera).
    own_index: Vec<Option<usize>>,
    /// Per rig camera: placed on this board but unusable (size mismatch, no such camera);
    /// its observations are refused.
    own_refused: Vec<bool>,
    /// Observations of the solver's own cameras refused for that reason.
    own_refused_count: u64,
    /// Camera controls asked for before a parameter set placed the own cameras (the saved
    /// tuning at start): applied once it does.
    deferred_controls: Vec<(usize, CameraControl, i64)>,
    /// A placed camera board (not the solver's own) has sent a usable observation since start.
    heard_from_boards: bool,
    /// When the solver started (realtime ns): how long it has waited for its boards.
    started_ns: u64,
    /// Refused observations by sender (board name, or "rig/board" of another rig) and the
    /// last problem; at most [`MAX_REFUSED_SENDERS`] senders, the rest counted together.
    refused_senders: Vec<(String, u64, &'static str)>,
    /// Trigger mode: observations without a trigger counter, per board of the layout.
    no_trigger: Vec<u64>,
    /// Per rig camera: its last accepted observation (the sequence-jump bound).
    seen: Vec<Option<SequenceSeen>>,
    /// Observations refused for a sequence jump.
    sequence_jumps: u64,
    /// Sequences that went back with a newer capture time: board restarts.
    sequence_restarts: u64,
    /// The clock probe (`correct_board_clocks`): its thread and its replies.
    prober: Option<(ClockProber, Receiver<ProbeReply>)>,
    /// What the probe knows of each board's clock, by board name (a few boards: a list).
    clocks: Vec<BoardProbe>,
    /// When a probe was last asked for out of turn (pairing clock, ns).
    last_fast_probe_ns: u64,
}

/// One camera board's clock as the probe measures it.
struct BoardProbe {
    board: String,
    estimator: ClockEstimator,
    /// The correction applied to its last observation (board clock − solver clock), ns.
    applied_ns: Option<i64>,
    replies: u64,
    refused: u64,
    /// Clock steps the probe saw, the last one's size and its bound (ns) and when it was seen
    /// (solver's monotonic clock, ns).
    steps: u64,
    last_step: Option<LastStep>,
    /// Stepped and not yet measured again: its cameras are left out of every set.
    settling: bool,
    /// Its last arrivals say its clock may have stepped back (the pairer's
    /// `stepped_back`), since this time on the pairing clock: left out until a probe sent
    /// after it answers (a step, or only a slow link), at most [`SUSPECT_MAX_NS`].
    suspect_at_ns: Option<u64>,
    /// Times that happened.
    suspected: u64,
    /// The offset before the last step and its bound, ns: the step's size is re-measured
    /// against the settled estimate (the sample that showed it carries its own round trip's
    /// error).
    pre_step_ns: Option<(i64, u64)>,

    /// The pairer's flag at the board's last observation (a suspicion starts on its rise).
    back_flag: bool,
}

/// A suspicion from arrivals that no probe answer settles is dropped after this, ns (a board
/// that does not answer the probe is not left out for good).
const SUSPECT_MAX_NS: u64 = 1_000_000_000;
/// A clock step the probe saw.
#[derive(Debug, Clone, Copy)]
struct LastStep {
    /// New offset minus the old one, ns.
    by_ns: i64,
    /// How far `by_ns` may be from the true step, ns.
    uncertainty_ns: u64,
    /// When it was seen, solver's monotonic clock, ns.
    at_ns: u64,
}

/// While a board is suspected, it is probed this often instead of every [`PROBE_INTERVAL`],
/// ns. Not while it settles after a step: probing faster then gave a worse new estimate
/// (positions 0.25–0.35 mm RMS in 3 of 10 runs of the stepping test, against 0.05 mm), as
/// probing every 100 ms did for a corrected board (docs/cluster.md).
const FAST_PROBE_NS: u64 = 25_000_000;

/// Time between probes of every board (each a request and a reply of 40 bytes). A step
/// ahead shows at once in the one-way check, one back in the last few arrivals (the
/// pairer's `stepped_back`), which hold the board out and ask for a probe at once. Probing
/// every 100 ms instead made a board corrected by 6 ms track worse (RMS 0.045 → 0.10 mm,
/// not yet understood), so 250 ms stays.
const PROBE_INTERVAL: Duration = Duration::from_millis(250);
/// A probe whose round trip is longer than this met a queue on the way: not used, ns.
const PROBE_MAX_RTT_NS: u64 = 20_000_000;
/// A board whose probe has not answered for this long is no longer corrected, ns.
const PROBE_MAX_AGE_NS: u64 = 5_000_000_000;
/// A board's clock is corrected once it is off by more than the probe's bound plus this, ns.
const PROBE_MARGIN_NS: u64 = 250_000;
/// A correction that moves by more than this at once (the board's clock stepped, or it
/// restarted) restarts the board's pairing state, ns.
const PROBE_STEP_NS: i64 = 1_000_000;

/// Senders of refused observations named one by one in `/status` (more are counted as
/// "other senders": a flood of forged names must not grow the list without bound).
const MAX_REFUSED_SENDERS: usize = 16;
/// `cluster.refused` code of observations without a trigger counter in trigger mode.
const NO_TRIGGER_CODE: &str = "no_trigger_count";

/// What the solver's own cameras' thread is asked to change (from the set-up view, through
/// the loop's tuning).
enum OwnRequest {
    /// A camera control of local camera `camera`.
    Control {
        camera: usize,
        control: CameraControl,
        value: i64,
    },
    /// New detector settings (threshold, area and roundness limits).
    Detection(TrackerConfig),
}

/// State shared between the solver's source and its own cameras' thread.
struct OwnShared {
    /// The newest captured set: the thread swaps its buffer with this one after each set (no
    /// copy, no allocation); the source copies pixels out only when a viewer's copy is due.
    latest: Mutex<FrameSet>,
    /// Exposure and gain of the own cameras, as the thread last read them.
    controls: Mutex<Vec<CameraControls>>,
}

/// The solver's handle on its own cameras.
struct OwnCameras {
    stop: Arc<AtomicBool>,
    shared: Arc<OwnShared>,
    requests: Sender<OwnRequest>,
    replies: Receiver<std::result::Result<(), String>>,
    /// Image sizes of the own cameras, in their local order.
    sizes_px: Vec<[u32; 2]>,
}

/// How long the loop waits for the own cameras' thread to apply a change (it applies between
/// two captures).
const OWN_REQUEST_WAIT: Duration = Duration::from_millis(500);

/// The solver's own cameras: captured and detected on a thread of their own, published as
/// observations of board `cfg.board` on the solver's session, so they reach its subscriber
/// and pairing exactly as a camera board's do (timestamps on the same CLOCK_REALTIME). Between
/// sets the thread applies the set-up view's changes (detector settings, exposure, gain) and
/// hands its newest set to [`OwnShared::latest`] by swapping buffers.
fn spawn_own_cameras(
    cfg: &ClusterConfig,
    session: &Session,
    mut source: Box<dyn FrameSource>,
    tracker_cfg: TrackerConfig,
) -> Result<OwnCameras> {
    let mut set = source.allocate_set();
    let sizes = set.image_sizes();
    let mut tracker = Tracker::detection_only(&sizes, tracker_cfg).map_err(|e| FirmwareError::Config {
        reason: format!("solver's own cameras: {e}"),
    })?;
    // Its counters are not the solver's: a report of their own, not shown.
    let mut sink = CameraPublisher::on_session(
        session.clone(),
        cfg,
        sizes.len(),
        Arc::new(Mutex::new(ClusterReport::default())),
    )?;
    let shared = Arc::new(OwnShared {
        latest: Mutex::new(source.allocate_set()),
        controls: Mutex::new(source.controls()),
    });
    let (requests, request_rx) = channel::<OwnRequest>();
    let (reply_tx, replies) = channel();
    let stop = Arc::new(AtomicBool::new(false));
    let (stop2, shared2) = (stop.clone(), shared.clone());
    let describe = source.describe();
    std::thread::Builder::new()
        .name("solver-own-cameras".into())
        .spawn(move || {
            let mut errors = 0u64;
            while !stop2.load(Ordering::Relaxed) {
                // Changes from the set-up view, between two captures (rare; may allocate).
                while let Ok(req) = request_rx.try_recv() {
                    let result = match req {
                        OwnRequest::Detection(c) => tracker.set_config(c).map_err(|e| e.to_string()),
                        OwnRequest::Control {
                            camera,
                            control,
                            value,
                        } => {
                            let r = source.set_control(camera, control, value).map_err(|e| e.to_string());
                            if let Ok(mut g) = shared2.controls.lock() {
                                *g = source.controls();
                            }
                            r
                        }
                    };
                    let _ = reply_tx.send(result);
                }
                match source.next_set(&mut set) {
                    Ok(()) => {}
                    Err(SourceError::EndOfStream) => {
                        tracing::warn!("the solver's own cameras ended");
                        break;
                    }
                    Err(e) => {
                        if errors == 0 {
                            tracing::warn!(error = %e, "the solver's own cameras: capture fault; retrying");
                        }
                        errors += 1;
                        std::thread::sleep(Duration::from_millis(20));
                        continue;
                    }
                }
                let dropped = source.stats().sets_dropped;
                for (c, frame) in set.frames.iter().enumerate() {
                    let detected = match &frame.pixels {
                        Pixels::U8(px) => GrayImage::new(px, frame.width_px, frame.height_px, frame.stride_px)
                            .and_then(|img| tracker.detect_u8(c, &img)),
                        Pixels::U16(px) => GrayImage::new(px, frame.width_px, frame.height_px, frame.stride_px)
                            .and_then(|img| tracker.detect_u16(c, &img)),
                    };
                    match detected {
                        Ok(_) => sink.observe(c, frame, tracker.blobs(c), dropped),
                        Err(e) => {
                            if errors == 0 {
                                tracing::warn!(camera = c, error = %e, "the solver's own cameras: detection failed");
                            }
                            errors += 1;
                        }
                    }
                }
                // The newest pixels for the set-up view: a buffer swap, never a wait (a
                // reader holding the slot makes this set skip it).
                if let Ok(mut latest) = shared2.latest.try_lock() {
                    std::mem::swap(&mut *latest, &mut set);
                }
            }
        })
        .map_err(|e| FirmwareError::Thread {
            what: "solver's own cameras",
            reason: e.to_string(),
        })?;
    tracing::info!(board = %cfg.board, source = %describe, cameras = sizes.len(), "cluster solver: own cameras feed the pairing");
    Ok(OwnCameras {
        stop,
        shared,
        requests,
        replies,
        sizes_px: sizes.iter().map(|s| [s.width_px, s.height_px]).collect(),
    })
}

/// Copies `src`'s pixels into `dst` (same size; 8-bit destination, deeper sources shifted
/// down). Returns false if the sizes differ.
fn copy_pixels_8bit(dst: &mut Frame, src: &Frame) -> bool {
    if (dst.width_px, dst.height_px) != (src.width_px, src.height_px) {
        return false;
    }
    let (w, h) = (src.width_px as usize, src.height_px as usize);
    let (ds, ss) = (dst.stride_px as usize, src.stride_px as usize);
    let Pixels::U8(d) = &mut dst.pixels else {
        return false;
    };
    for y in 0..h {
        let Some(drow) = d.get_mut(y * ds..y * ds + w) else {
            return false;
        };
        match &src.pixels {
            Pixels::U8(s) => match s.get(y * ss..y * ss + w) {
                Some(srow) => drow.copy_from_slice(srow),
                None => return false,
            },
            Pixels::U16(s) => {
                let shift = u32::from(src.bit_depth.saturating_sub(8));
                match s.get(y * ss..y * ss + w) {
                    Some(srow) => {
                        for (o, v) in drow.iter_mut().zip(srow) {
                            *o = (u32::from(*v) >> shift).min(255) as u8;
                        }
                    }
                    None => return false,
                }
            }
        }
    }
    dst.bit_depth = 8;
    true
}

impl ClusterSource {
    /// Opens the session and subscribes (blocking).
    /// With `own`, the solver's own cameras (a frame source and the detector's settings) feed
    /// the pairing as observations of board `cfg.board`.
    pub fn new(
        cfg: &ClusterConfig,
        params: Arc<ParamsHandle>,
        report: Arc<Mutex<ClusterReport>>,
        own: Option<(Box<dyn FrameSource>, TrackerConfig)>,
    ) -> Result<Self> {
        let session = super::camera::open_session(cfg)?;
        let (sub, rx) =
            ObsSubscriber::new(&session, &cfg.rig, 1024, realtime_ns).map_err(|e| FirmwareError::Config {
                reason: format!("cluster: {e}"),
            })?;
        let own = match own {
            Some((source, tracker_cfg)) => Some(spawn_own_cameras(cfg, &session, source, tracker_cfg)?),
            None => None,
        };
        let prober = if cfg.correct_board_clocks {
            Some(
                ClockProber::start(&session, &cfg.rig, PROBE_INTERVAL, realtime_ns).map_err(|e| {
                    FirmwareError::Config {
                        reason: format!("cluster: {e}"),
                    }
                })?,
            )
        } else {
            None
        };
        let n = cfg.image_sizes_px.len();
        let mut hop = Arc::default();
        if let Ok(mut r) = report.lock() {
            hop = r.hop.0.clone();
            r.role = "solver";
            r.rig = cfg.rig.clone();
            if own.is_some() {
                r.board = cfg.board.clone();
            }
            r.missing = vec![0; n];
        }
        tracing::info!(rig = %cfg.rig, cameras = n, "cluster solver: subscribed to the camera boards");
        Ok(ClusterSource {
            cfg: cfg.clone(),
            session,
            sub,
            rx,
            params,
            seen_generation: 0,
            layout: None,
            board_last_ns: Vec::new(),
            remote: (0..n).map(|_| Vec::with_capacity(MAX_OBS_BLOBS)).collect(),
            stats: SourceStats::default(),
            report,
            refused: [0; ObservationProblem::CODES.len()],
            received: 0,
            last_any_ns: realtime_ns(),
            last_report_ns: 0,
            hop,
            hop_from_ns: None,
            last_index: None,
            own,
            own_index: vec![None; n],
            own_refused: vec![false; n],
            own_refused_count: 0,
            deferred_controls: Vec::new(),
            heard_from_boards: false,
            started_ns: realtime_ns(),
            refused_senders: Vec::new(),
            no_trigger: Vec::new(),
            seen: vec![None; n],
            sequence_jumps: 0,
            sequence_restarts: 0,
            prober,
            clocks: Vec::new(),
            last_fast_probe_ns: 0,
        })
    }

    /// Takes the probe's replies that came in: each board's estimator.
    fn take_probe_replies(&mut self) {
        let Some((_, rx)) = &self.prober else { return };
        while let Ok(r) = rx.try_recv() {
            if self.own.is_some() && r.board == self.cfg.board {
                continue;
            }
            let i = match self.clocks.iter().position(|c| c.board == r.board) {
                Some(i) => i,
                // Boards the parameter set places, and a few more (a board not yet placed):
                // replies from a flood of names do not grow the list without bound.
                None if self.clocks.len() < MAX_REFUSED_SENDERS => {
                    self.clocks.push(BoardProbe {
                        board: r.board.clone(),
                        estimator: ClockEstimator::new(PROBE_MAX_RTT_NS, PROBE_MAX_AGE_NS),
                        applied_ns: None,
                        replies: 0,
                        refused: 0,
                        steps: 0,
                        last_step: None,
                        settling: false,
                        suspect_at_ns: None,
                        suspected: 0,
                        pre_step_ns: None,
                        back_flag: false,
                    });
                    self.clocks.len() - 1
                }
                None => continue,
            };
            let c = &mut self.clocks[i];
            match c.estimator.push(&r.sample) {
                Ok(Taken::Added) => {
                    c.replies += 1;
                    // Asked after the suspicion and in line with the estimate: no step, the
                    // arrivals were late on the link.
                    if c.suspect_at_ns.is_some_and(|t| r.sample.t1_ns > t) {
                        c.suspect_at_ns = None;
                        tracing::info!(board = %c.board, "no clock step after all (the probe agrees): its observations arrived late on the link");
                    }
                }
                Ok(Taken::Stepped {
                    by_ns,
                    uncertainty_ns,
                }) => {
                    c.replies += 1;
                    c.suspect_at_ns = None;
                    let sample_bound_ns = r.sample.uncertainty_ns().unwrap_or(u64::MAX);
                    c.pre_step_ns = Some((
                        r.sample.offset_ns() - by_ns,
                        uncertainty_ns.saturating_sub(sample_bound_ns),
                    ));
                    c.steps += 1;
                    c.last_step = Some(LastStep {
                        by_ns,
                        uncertainty_ns,
                        at_ns: clock::monotonic_ns(),
                    });
                    // Observations stamped after the step carry the new offset: until the
                    // probe has measured it, the board's cameras are left out.
                    c.settling = true;
                    tracing::warn!(
                        board = %c.board,
                        by_ms = by_ns as f64 / 1e6,
                        steps = c.steps,
                        "camera board's clock stepped (clock probe): its cameras are left out until it is measured again"
                    );
                }
                Err(_) => c.refused += 1,
            }
        }
    }

    /// Boards suspected of a step back are probed every [`FAST_PROBE_NS`] until a probe
    /// answers; a suspicion no probe answer settles ends after [`SUSPECT_MAX_NS`].
    fn probe_unsettled(&mut self, now_ns: u64) {
        let Some((prober, _)) = &self.prober else { return };
        let mut unsettled = false;
        for c in &mut self.clocks {
            if c.suspect_at_ns
                .is_some_and(|t| now_ns.saturating_sub(t) > SUSPECT_MAX_NS)
            {
                c.suspect_at_ns = None;
                tracing::warn!(board = %c.board, "its clock may have stepped back, but the probe did not answer within 1 s: taken again as before");
            }
            unsettled |= c.suspect_at_ns.is_some();
        }
        if unsettled && now_ns.saturating_sub(self.last_fast_probe_ns) >= FAST_PROBE_NS {
            prober.probe_now();
            self.last_fast_probe_ns = now_ns;
        }
    }

    /// Puts a camera board's capture time on the solver's clock by the probe's estimate of its
    /// clock; restarts the board's pairing state when the correction starts, stops or steps.
    fn correct_capture_time(&mut self, board: &str, capture_ts_ns: u64, now_ns: u64) -> u64 {
        if self.prober.is_none() || (self.own.is_some() && board == self.cfg.board) {
            return capture_ts_ns;
        }
        let Some(c) = self.clocks.iter_mut().find(|c| c.board == board) else {
            return capture_ts_ns;
        };
        // Only a clock surely off: by more than the probe's bound plus a margin to start, by
        // more than the bound to go on. A board already on the solver's time (PTP, chrony, or
        // the same machine) is left alone: correcting it by the probe's own error (50–80 µs
        // here) made positions worse (RMS 0.043 → 0.055–0.070 mm, measured 2026-11-28).
        let estimate = c.estimator.estimate(now_ns);
        if let Some(e) = &estimate {
            c.settling = false;
            if let (Some((pre_ns, pre_bound_ns)), Some(step)) = (c.pre_step_ns.take(), c.last_step) {
                c.last_step = Some(LastStep {
                    by_ns: e.offset_ns - pre_ns,
                    uncertainty_ns: e.uncertainty_ns.saturating_add(pre_bound_ns),
                    at_ns: step.at_ns,
                });
            }
        }
        let offset = estimate.and_then(|e| {
            let surely_off_ns = e.offset_ns.unsigned_abs().saturating_sub(e.uncertainty_ns);
            let start = if c.applied_ns.is_some() {
                0
            } else {
                PROBE_MARGIN_NS
            };
            (surely_off_ns > start).then_some(e.offset_ns)
        });
        let stepped = match (c.applied_ns, offset) {
            (Some(a), Some(o)) => (a - o).abs() > PROBE_STEP_NS,
            (None, None) => false,
            _ => true,
        };
        if stepped {
            tracing::info!(
                board,
                from_ms = c.applied_ns.map(|o| o as f64 / 1e6),
                to_ms = offset.map(|o| o as f64 / 1e6),
                "camera board's clock correction (clock probe) changed"
            );
            if let Some(layout) = self.layout.as_mut()
                && let Some(b) = layout.boards.iter().position(|n| n == board)
            {
                layout.pairer.reset_board(b);
            }
        }
        c.applied_ns = offset;
        match offset {
            Some(o) => (i128::from(capture_ts_ns) - i128::from(o)).max(0) as u64,
            None => capture_ts_ns,
        }
    }

    /// Rebuilds gate and pairer when the parameter set changed (allocates; only then).
    fn refresh_layout(&mut self) {
        let generation = self.params.generation();
        if generation == self.seen_generation {
            return;
        }
        self.seen_generation = generation;
        self.layout = None;
        self.own_index.iter_mut().for_each(|o| *o = None);
        self.own_refused.iter_mut().for_each(|r| *r = false);
        self.seen.iter_mut().for_each(|s| *s = None);
        let Some(p) = self.params.current() else { return };
        let placement = &p.rig.placement;
        self.check_own_cameras(placement);
        self.stats.controls_generation += 1;
        for (camera, control, value) in std::mem::take(&mut self.deferred_controls) {
            match self.set_control(camera, control, value) {
                Ok(()) => tracing::info!(
                    camera,
                    ?control,
                    value,
                    "saved camera setting applied to the solver's own camera"
                ),
                Err(e) => {
                    tracing::warn!(camera, ?control, value, error = %e, "saved camera setting not applied")
                }
            }
        }
        if placement.len() != self.remote.len() {
            tracing::error!(
                rig_id = %p.rig.rig_id,
                placed = placement.len(),
                cameras = self.remote.len(),
                "parameter set does not place every camera on a board; the solver cannot pair"
            );
            return;
        }
        let mut boards: Vec<String> = Vec::new();
        let mut camera_board = Vec::with_capacity(placement.len());
        for pl in placement {
            let b = match boards.iter().position(|b| *b == pl.board) {
                Some(b) => b,
                None => {
                    boards.push(pl.board.clone());
                    boards.len() - 1
                }
            };
            camera_board.push(b);
        }
        let agreement = Agreement::new(&camera_board);
        let board_cameras = (0..boards.len())
            .map(|b| {
                (0..camera_board.len())
                    .filter(|&c| camera_board[c] == b)
                    .collect()
            })
            .collect();
        let mode = if self.cfg.trigger {
            PairingMode::Trigger
        } else {
            PairingMode::Timestamp {
                period_ns: self.cfg.period_ns(),
            }
        };
        let pairing = PairingConfig {
            camera_board,
            mode,
            deadline_ns: self.cfg.set_deadline_ns(),
            max_clock_offset_ns: self.cfg.max_clock_offset_ns(),
            offset_window: 64,
        };
        let built = ObservationGate::new(
            &self.cfg.rig,
            placement,
            ObsClock::Realtime,
            MAX_TIMESTAMP_OFFSET_NS,
        )
        .map_err(|e| e.to_string())
        .and_then(|gate| {
            Pairer::new(pairing)
                .map(|pairer| (gate, pairer))
                .map_err(|e| e.to_string())
        });
        match built {
            Ok((gate, pairer)) => {
                tracing::info!(rig_id = %p.rig.rig_id, boards = ?boards, "cluster solver: camera placement loaded");
                self.board_last_ns = vec![None; boards.len()];
                self.no_trigger = vec![0; boards.len()];
                self.layout = Some(Layout {
                    gate,
                    pairer,
                    agreement,
                    boards,
                    board_cameras,
                });
            }
            Err(e) => tracing::error!(error = %e, "cluster solver: placement refused"),
        }
    }

    /// Maps the rig's cameras placed on this board to the solver's own cameras and checks
    /// their image sizes against `image_sizes_px` (what the parameter set was checked
    /// against): a camera placed here that does not exist or has another size is reported
    /// (`own_camera` fault) and its observations are refused — its centroids would be in
    /// another image's pixels, a wrong position.
    fn check_own_cameras(&mut self, placement: &[irtrack_core::params::CameraPlace]) {
        let mut faults = Vec::new();
        let mut refused = Vec::new();
        if let Some(own) = &self.own {
            for (c, pl) in placement.iter().enumerate().take(self.own_index.len()) {
                if pl.board != self.cfg.board {
                    continue;
                }
                let i = usize::from(pl.local_index);
                let expected = self.cfg.image_sizes_px[c];
                match own.sizes_px.get(i) {
                    Some(&size) if size == expected => self.own_index[c] = Some(i),
                    Some(&[w, h]) => {
                        self.own_refused[c] = true;
                        refused.push(c);
                        faults.push(format!(
                            "camera {c} (the solver's own camera {i} on board {}) delivers {w}x{h} px but cluster.image_sizes_px[{c}] (the parameter set's size) is {}x{} px — its observations are refused; fix [source] or image_sizes_px and the parameter set",
                            self.cfg.board, expected[0], expected[1]
                        ));
                    }
                    None => {
                        self.own_refused[c] = true;
                        refused.push(c);
                        faults.push(format!(
                            "camera {c} is placed on the solver's own board {} as camera {i}, but the solver has only {} camera(s) of its own — check [source] and the parameter set's placement",
                            self.cfg.board,
                            own.sizes_px.len()
                        ));
                    }
                }
            }
        }
        for f in &faults {
            tracing::error!("{f}");
        }
        if let Ok(mut r) = self.report.lock() {
            r.own_camera_faults = faults;
            r.own_refused_cameras = refused;
        }
    }

    /// Counts a refused observation by problem and by sender (`None`: its header could not be
    /// read, so nothing says who sent it).
    fn refuse(&mut self, problem: ObservationProblem, sender: Option<(&str, &str)>) {
        let i = problem.index();
        if self.refused[i] == 0 {
            tracing::warn!(problem = %problem, sender = ?sender, "observation refused");
        }
        self.refused[i] += 1;
        let code = ObservationProblem::CODES.get(i).copied().unwrap_or("refused");
        self.count_sender(code, sender);
    }

    /// Counts a refused observation under its sender (see [`Self::refuse`]), `code` its
    /// last problem.
    fn count_sender(&mut self, code: &'static str, sender: Option<(&str, &str)>) {
        let name = match sender {
            Some((rig, board)) if rig == self.cfg.rig => board,
            Some(_) => "",
            None => "?",
        };
        let same = |n: &str| match sender {
            Some((rig, board)) if name.is_empty() => {
                n.strip_prefix("rig ")
                    .and_then(|r| r.strip_prefix(rig))
                    .and_then(|r| r.strip_prefix(" board "))
                    == Some(board)
            }
            _ => n == name,
        };
        if let Some(e) = self.refused_senders.iter_mut().find(|(n, _, _)| same(n)) {
            e.1 += 1;
            e.2 = code;
            return;
        }
        // Allocates only for a sender not seen before, at most MAX_REFUSED_SENDERS times.
        let label = match (sender, name) {
            (Some((rig, board)), "") => format!("rig {rig} board {board}"),
            (_, "?") => "?".to_string(),
            _ => name.to_string(),
        };
        if self.refused_senders.len() < MAX_REFUSED_SENDERS {
            self.refused_senders.push((label, 1, code));
        } else if let Some(last) = self.refused_senders.last_mut() {
            last.0 = "other senders".into();
            last.1 += 1;
        }
    }

    fn handle(&mut self, m: &Received) {
        self.received += 1;
        self.last_any_ns = m.received_ns;
        if self.layout.is_none() {
            return;
        }
        let mut obs = match decode(m.payload()) {
            Ok(o) => o,
            Err(irtrack_core::Error::Observation { problem }) => return self.refuse(problem, None),
            Err(_) => return,
        };
        // On the solver's clock from here on: pairing, the clock checks, the loop's timing.
        if obs.header.clock == ObsClock::Realtime {
            obs.header.capture_ts_ns =
                self.correct_capture_time(obs.header.board, obs.header.capture_ts_ns, m.received_ns);
        }
        let Some(layout) = self.layout.as_mut() else {
            return;
        };
        record_hop(
            &self.hop,
            &mut self.hop_from_ns,
            self.own.is_some().then_some(self.cfg.board.as_str()),
            &obs.header,
            m.received_ns,
        );
        // A board heard again after being silent restarted: forget its sequences and clock.
        if let Some(c) = layout.gate.camera_of(obs.header.board, obs.header.camera) {
            let board = layout.pairer.boards().len().min(self.board_last_ns.len());
            let b = (0..board).find(|&b| layout.board_cameras[b].contains(&c));
            if let Some(b) = b {
                let silent = self.board_last_ns[b].is_none_or(|t| {
                    m.received_ns.saturating_sub(t) > (self.cfg.board_timeout_ms * 1e6) as u64
                });
                if silent && self.board_last_ns[b].is_some() {
                    tracing::info!(board = %layout.boards[b], "camera board back");
                    for &cam in &layout.board_cameras[b] {
                        layout.gate.reset_camera(cam);
                        if let Some(s) = self.seen.get_mut(cam) {
                            *s = None;
                        }
                    }
                    layout.pairer.reset_board(b);
                    // Its clock may be another after a restart: measured afresh.
                    if let Some(c) = self.clocks.iter_mut().find(|c| c.board == layout.boards[b]) {
                        c.estimator.reset();
                    }
                }
            }
        }
        // Sequence order is judged here, not by the gate (which would take a board's restart,
        // counting from 1 again, for duplicates until it times out, and would remember a
        // forged sequence near 2^64 for good: every real one after it "not newer").
        if let Some(c) = layout.gate.camera_of(obs.header.board, obs.header.camera) {
            layout.gate.reset_camera(c);
        }
        let camera = match layout.gate.check(&obs, m.received_ns) {
            Ok(c) => c,
            Err(irtrack_core::Error::Observation { problem }) => {
                return self.refuse(problem, Some((obs.header.rig, obs.header.board)));
            }
            Err(_) => return,
        };
        if let Some(Some(seen)) = self.seen.get(camera).copied() {
            let seq = obs.header.sequence;
            if seq > seen.sequence {
                // Ahead by more than the time since the last one allows: refused, and the
                // camera's sequence stays where it was.
                let step = seq - seen.sequence;
                let limit = max_sequence_step(m.received_ns.saturating_sub(seen.received_ns), self.cfg.fps);
                if step > limit {
                    if self.sequence_jumps == 0 {
                        tracing::warn!(
                            board = %obs.header.board,
                            camera,
                            sequence = seq,
                            last = seen.sequence,
                            limit,
                            "observation refused: its sequence jumps further ahead than the time since the camera's last observation allows"
                        );
                    }
                    self.sequence_jumps += 1;
                    return self.count_sender(SEQUENCE_JUMP_CODE, Some((obs.header.rig, obs.header.board)));
                }
            } else if seq < seen.sequence && obs.header.capture_ts_ns > seen.capture_ns {
                // Back, with a newer capture time: the board restarted and counts from its
                // start again.
                tracing::info!(
                    board = %obs.header.board,
                    camera,
                    sequence = seq,
                    last = seen.sequence,
                    "camera sequence started again with a newer capture time: its board restarted"
                );
                self.sequence_restarts += 1;
            } else {
                return self.refuse(
                    ObservationProblem::DuplicateSequence {
                        camera,
                        sequence: seq,
                        last: seen.sequence,
                    },
                    Some((obs.header.rig, obs.header.board)),
                );
            }
        }
        if let Some(s) = self.seen.get_mut(camera) {
            *s = Some(SequenceSeen {
                sequence: obs.header.sequence,
                received_ns: m.received_ns,
                capture_ns: obs.header.capture_ts_ns,
            });
        }
        if self.own.is_none() || obs.header.board != self.cfg.board {
            self.heard_from_boards = true;
        }
        if let Some(b) = (0..layout.board_cameras.len()).find(|&b| layout.board_cameras[b].contains(&camera))
        {
            self.board_last_ns[b] = Some(m.received_ns);
        }
        if self.own_refused.get(camera).copied().unwrap_or(false) {
            // Placed on this board but not matching the parameter set: never paired.
            self.own_refused_count += 1;
            return;
        }
        // Late, conflicting or clock-faulted observations are counted by the pairer.
        let pushed = layout.pairer.push(camera, &obs, m.received_ns);
        let board = (0..layout.board_cameras.len()).find(|&b| layout.board_cameras[b].contains(&camera));
        if pushed == PushOutcome::NoTrigger
            && let Some(b) = board
            && let Some(n) = self.no_trigger.get_mut(b)
        {
            *n += 1;
        }
        // Its last arrivals all late by more than its link's jitter: its clock may have
        // stepped back, which the probe would see only at its next round. Left out from now,
        // and probed at once.
        if let Some(b) = board
            && let Some(name) = layout.boards.get(b)
            && let Some(c) = self.clocks.iter_mut().find(|c| c.board == *name)
        {
            let back = layout.pairer.boards().get(b).is_some_and(|k| k.stepped_back);
            if back && !c.back_flag && c.suspect_at_ns.is_none() && !c.settling {
                c.suspect_at_ns = Some(m.received_ns);
                c.suspected += 1;
                tracing::info!(board = %c.board, "its observations suddenly arrive late: its clock may have stepped back; left out until the probe has measured it");
                if let Some((p, _)) = &self.prober {
                    p.probe_now();
                }
            }
            c.back_flag = back;
        }
    }

    fn update_report(&mut self, now_ns: u64) {
        if now_ns.saturating_sub(self.last_report_ns) < REPORT_INTERVAL_NS {
            return;
        }
        self.last_report_ns = now_ns;
        let Ok(mut r) = self.report.try_lock() else { return };
        r.refused_peers = Some(peer_refusals_report(irtrack_cluster::refusals::global()));
        if r.tls.is_none()
            && let Some(c) = &self.cfg.tls_certificate_file
        {
            r.tls = Some(super::report::TlsReport {
                side: "solver",
                certificate_file: c.display().to_string(),
                ..super::report::TlsReport::default()
            });
        }
        r.received = self.received;
        r.queue_overflow = self.sub.stats.overflow.load(std::sync::atomic::Ordering::Relaxed);
        for (i, code) in ObservationProblem::CODES.iter().enumerate() {
            if self.refused[i] > 0 {
                r.refused.insert(*code, self.refused[i]);
            }
        }
        r.no_placement = self.params.current().is_some() && self.layout.is_none();
        r.own_refused = self.own_refused_count;
        r.refused_senders.clone_from(&self.refused_senders);
        if self.sequence_jumps > 0 {
            r.refused.insert(SEQUENCE_JUMP_CODE, self.sequence_jumps);
        }
        r.sequence_restarts = self.sequence_restarts;
        let names: Vec<&str> = self
            .layout
            .iter()
            .flat_map(|l| l.boards.iter())
            .filter(|b| self.own.is_none() || **b != self.cfg.board)
            .map(String::as_str)
            .collect();
        // A solver with only its own cameras waits for no board.
        r.waiting_for_boards = (!self.heard_from_boards && !names.is_empty()).then(|| {
            format!(
                "waiting for camera boards: none of {} has sent an observation in the {:.0} s since the solver started — check that each runs irtrackd with [cluster] role = \"camera\", rig = \"{}\" and its board name, and that it reaches this solver (listen {:?}, connect {:?})",
                names.join(", "),
                now_ns.saturating_sub(self.started_ns) as f64 / 1e9,
                self.cfg.rig,
                self.cfg.listen,
                self.cfg.connect,
            )
        });
        let Some(layout) = &self.layout else {
            r.boards.clear();
            return;
        };
        let st = layout.pairer.stats();
        r.sets_complete = st.sets_complete;
        r.sets_incomplete = st.sets_incomplete;
        r.late = st.late;
        r.conflicting = st.conflicting;
        r.refused_clock = st.refused_clock;
        r.missing = st.missing[..layout.pairer.camera_count()].to_vec();
        if st.no_trigger > 0 {
            r.refused.insert(NO_TRIGGER_CODE, st.no_trigger);
        }
        r.no_trigger_boards = layout
            .boards
            .iter()
            .zip(&self.no_trigger)
            .filter(|(_, n)| **n > 0)
            .map(|(b, n)| (b.clone(), *n))
            .collect();
        let ag = &layout.agreement;
        r.sets_compared = ag.sets_compared;
        r.sets_refused_disagreement = ag.sets_refused;
        r.sets_board_dropped = ag.sets_board_dropped;
        let timeout_ns = (self.cfg.board_timeout_ms * 1e6) as u64;
        let limit_ns = CLOCK_OFF_NS.max(self.cfg.tolerance_ns() as i64 / 4);
        let (_, behind) = clock_flags(layout.pairer.boards(), limit_ns);
        r.boards = layout
            .boards
            .iter()
            .enumerate()
            .map(|(b, name)| {
                let clock = layout.pairer.boards().get(b).copied().unwrap_or_default();
                let last = self.board_last_ns.get(b).copied().flatten();
                let a = layout.agreement.boards.get(b).cloned().unwrap_or_default();
                BoardReport {
                    disagreeing: a.suspect,
                    clock_ahead: a.clock_ahead,
                    clock_behind: behind.get(b).copied().unwrap_or(false) && !clock.faulted,
                    disagreement_share: a.share,
                    compared_sets: a.compared,
                    disagreed_sets: a.disagreed,
                    dropped_sets: a.dropped,
                    miss_mm: a.miss_mm,
                    miss_px: a.miss_px,
                    time_shift_ms: a.shift_ms,
                    likely_cause: a.suspect.then(|| match a.cause() {
                        Cause::Clock => "clock",
                        Cause::Calibration => "calibration",
                        Cause::Unknown => "unknown",
                    }),
                    disagrees_with: a
                        .peer
                        .filter(|_| a.suspect)
                        .and_then(|p| layout.boards.get(p).cloned()),
                    name: name.clone(),
                    cameras: layout.board_cameras[b].clone(),
                    last_seen_ms: last.map(|t| now_ns.saturating_sub(t) as f64 / 1e6),
                    clock_offset_ms: clock.offset_ns.map(|o| o as f64 / 1e6),
                    clock_probe: self.clocks.iter().find(|c| c.board == *name).map(|c| {
                        let e = c.estimator.estimate(now_ns);
                        ClockProbeReport {
                            offset_ms: e.map(|e| e.offset_ns as f64 / 1e6),
                            uncertainty_ms: e.map(|e| e.uncertainty_ns as f64 / 1e6),
                            drift_ppm: e.map(|e| e.drift_ppm),
                            rtt_ms: e.map(|e| e.rtt_ns as f64 / 1e6),
                            samples: e.map_or(0, |e| e.samples),
                            replies: c.replies,
                            refused: c.refused,
                            corrected: c.applied_ns.is_some(),
                            steps: c.steps,
                            last_step_ms: c.last_step.map(|s| s.by_ns as f64 / 1e6),
                            last_step_uncertainty_ms: c.last_step.map(|s| s.uncertainty_ns as f64 / 1e6),
                            last_step_ago_s: c
                                .last_step
                                .map(|s| clock::monotonic_ns().saturating_sub(s.at_ns) as f64 / 1e9),
                            settling: c.settling,
                            suspected_steps_back: c.suspected,
                            suspect: c.suspect_at_ns.is_some(),
                        }
                    }),
                    clock_fault: clock.faulted,
                    down: last.is_none_or(|t| now_ns.saturating_sub(t) > timeout_ns),
                }
            })
            .collect();
    }

    /// Fills `out` from the pairer's closed set, if one is ready.
    fn take_set(&mut self, now_ns: u64, out: &mut FrameSet) -> bool {
        let Some(layout) = self.layout.as_mut() else {
            return false;
        };
        // A board silent past its timeout (the same rule as `/status`'s `down`) is not waited
        // for: the remaining cameras' sets close as soon as they are complete, not at the
        // deadline, so positions stay prompt while a board is down.
        let timeout_ns = (self.cfg.board_timeout_ms * 1e6) as u64;
        for (b, last) in self.board_last_ns.iter().enumerate() {
            let down = last.is_none_or(|t| now_ns.saturating_sub(t) > timeout_ns);
            layout.pairer.set_board_down(b, down);
        }
        let Some(set) = layout.pairer.poll(now_ns) else {
            return false;
        };
        let rt_minus_mono = clock::realtime_minus_mono_ns();
        let to_mono = |rt: u64| (i128::from(rt) - rt_minus_mono).max(0) as u64;
        let (mut lo, mut hi) = (u64::MAX, 0u64);
        let mut index = None;
        for (c, (frame, remote)) in out.frames.iter_mut().zip(self.remote.iter_mut()).enumerate() {
            let e = &set.cameras[c];
            remote.clear();
            if e.present {
                remote.extend(e.blobs().iter().map(|b| b.to_blob()));
                lo = lo.min(e.capture_ts_ns);
                hi = hi.max(e.capture_ts_ns);
                index.get_or_insert(e.sequence);
                frame.sequence = e.sequence;
                frame.timestamp_ns = to_mono(e.capture_ts_ns);
            } else if c == 0 {
                // Camera 0's time is the set's for the loop (stale-set check, latency).
                frame.timestamp_ns = to_mono(set.capture_ts_ns);
            }
            // An absent camera other than 0 keeps its last frame's time and sequence: its clock
            // model takes it as a repeat, not as a frame on a wrong instant, and it has no blobs.
        }
        // Every camera keeps its own capture time: the loop solves the set at one instant from
        // them (docs/timing.md), and camera 0's is the set's time when solving as seen.
        // The boards' frame counter (simulated boards share one) as it is; our own count only
        // when a set has none or repeats the last one (sets must be numbered upwards). A
        // board's first sequence may be anything (even 2^64 − 1): the count wraps, never panics.
        let index = match (index, self.last_index) {
            (Some(i), Some(last)) if i > last => i,
            (Some(i), None) => i,
            (_, Some(last)) => last.wrapping_add(1),
            (None, None) => 0,
        };
        self.last_index = Some(index);
        out.index = index;
        out.pairing_error_ns = hi.saturating_sub(lo.min(hi));
        self.stats.sets_delivered += 1;
        true
    }
}

impl Drop for ClusterSource {
    fn drop(&mut self) {
        if let Some(own) = &self.own {
            own.stop.store(true, Ordering::Relaxed);
        }
        self.session.close();
    }
}

impl FrameSource for ClusterSource {
    fn camera_count(&self) -> usize {
        self.cfg.image_sizes_px.len()
    }

    fn allocate_set(&self) -> FrameSet {
        FrameSet {
            index: 0,
            frames: self
                .cfg
                .image_sizes_px
                .iter()
                .map(|&[w, h]| Frame {
                    width_px: w,
                    height_px: h,
                    stride_px: w,
                    bit_depth: 8,
                    pixels: Pixels::U8(vec![0; w as usize * h as usize]),
                    timestamp_ns: 0,
                    sequence: 0,
                })
                .collect(),
            pairing_error_ns: 0,
            render_ns: 0,
        }
    }

    fn next_set(&mut self, out: &mut FrameSet) -> std::result::Result<(), SourceError> {
        self.refresh_layout();
        let period = Duration::from_nanos(self.cfg.period_ns().max(1));
        loop {
            let now = realtime_ns();
            self.take_probe_replies();
            self.probe_unsettled(now);
            self.update_report(now);
            if self.take_set(now, out) {
                return Ok(());
            }
            if self.layout.is_none() {
                // Nothing to pair with: drain, and deliver an empty set per period so the
                // loop reports the state (no parameters / no placement) instead of hanging.
                while let Ok(m) = self.rx.try_recv() {
                    self.received += 1;
                    self.last_any_ns = m.received_ns;
                }
                std::thread::sleep(period);
                for r in &mut self.remote {
                    r.clear();
                }
                let i = self.last_index.map_or(0, |l| l.wrapping_add(1));
                self.last_index = Some(i);
                out.index = i;
                let t = clock::monotonic_ns();
                for f in &mut out.frames {
                    f.timestamp_ns = t;
                }
                out.pairing_error_ns = 0;
                return Ok(());
            }
            match self.rx.recv_timeout(Duration::from_millis(2)) {
                Ok(m) => self.handle(&m),
                Err(RecvTimeoutError::Timeout) => {
                    if now.saturating_sub(self.last_any_ns) > SILENCE_TIMEOUT_NS {
                        // Every board is silent: a camera fault (the robot link holds).
                        self.last_any_ns = now;
                        return Err(SourceError::Timeout {
                            timeout_ms: SILENCE_TIMEOUT_NS / 1_000_000,
                        });
                    }
                }
                Err(RecvTimeoutError::Disconnected) => {
                    return Err(SourceError::CameraLost {
                        camera: 0,
                        device: format!("zenoh subscription irtrack/{}/**", self.cfg.rig),
                        reason: "subscriber closed".into(),
                    });
                }
            }
        }
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    fn describe(&self) -> String {
        format!(
            "cluster solver of rig {} ({} cameras over Zenoh)",
            self.cfg.rig,
            self.cfg.image_sizes_px.len()
        )
    }

    fn remote_blobs(&self, camera: usize) -> Option<&[Blob]> {
        self.remote.get(camera).map(|v| &v[..])
    }

    fn vet_solution(&mut self, tracker: &mut Tracker) -> bool {
        let Some(layout) = self.layout.as_mut() else {
            return true;
        };
        // A measured clock offset this large tells which of two disagreeing boards is off
        // (healthy boards on PTP or chrony measure well under 1 ms).
        let limit_ns = CLOCK_OFF_NS.max(self.cfg.tolerance_ns() as i64 / 4);
        let mut clock_off = [false; irtrack_core::pipeline::MAX_CAMERAS];
        for (off, b) in clock_off.iter_mut().zip(layout.pairer.boards()) {
            *off = b.offset_ns.is_some_and(|o| o.abs() > limit_ns);
        }
        let (clock_ahead, _) = clock_flags(layout.pairer.boards(), limit_ns);
        // A board whose clock just stepped: its newest observations may carry either offset.
        let mut settling = [false; irtrack_core::pipeline::MAX_CAMERAS];
        for (s, name) in settling.iter_mut().zip(&layout.boards) {
            *s = self
                .clocks
                .iter()
                .any(|c| (c.settling || c.suspect_at_ns.is_some()) && c.board == *name);
        }
        for (off, s) in clock_off.iter_mut().zip(settling) {
            *off |= s;
        }
        layout.agreement.vet(tracker, &clock_off, &clock_ahead, &settling)
    }

    fn has_pixels(&self, camera: usize) -> bool {
        self.own_index.get(camera).is_some_and(Option::is_some)
    }

    fn refresh_pixels(&mut self, out: &mut FrameSet) {
        let Some(own) = &self.own else { return };
        // A viewer's copy, at the preview rate: the thread's newest set (it never waits for
        // this lock; it skips one hand-over if it finds it held).
        let Ok(latest) = own.shared.latest.lock() else {
            return;
        };
        for (c, frame) in out.frames.iter_mut().enumerate() {
            if let Some(src) = self
                .own_index
                .get(c)
                .copied()
                .flatten()
                .and_then(|i| latest.frames.get(i))
            {
                copy_pixels_8bit(frame, src);
            }
        }
    }

    fn controls(&self) -> Vec<CameraControls> {
        let own = self
            .own
            .as_ref()
            .and_then(|o| o.shared.controls.lock().ok().map(|g| g.clone()))
            .unwrap_or_default();
        self.own_index
            .iter()
            .map(|i| i.and_then(|i| own.get(i).copied()).unwrap_or_default())
            .collect()
    }

    fn set_control(
        &mut self,
        camera: usize,
        control: CameraControl,
        value: i64,
    ) -> std::result::Result<(), SourceError> {
        self.refresh_layout();
        if self.own.is_some() && self.params.current().is_none() {
            // Which rig camera is which own camera is the parameter set's placement: keep
            // the setting until one is installed.
            self.deferred_controls
                .retain(|&(c, k, _)| (c, k) != (camera, control));
            self.deferred_controls.push((camera, control, value));
            return Ok(());
        }
        let Some(i) = self.own_index.get(camera).copied().flatten() else {
            return Err(SourceError::Config(format!(
                "camera {camera}: {control:?} is set on the camera board that carries it (its own set-up view), not on the solver"
            )));
        };
        self.own_request(OwnRequest::Control {
            camera: i,
            control,
            value,
        })
        .map_err(|e| SourceError::Config(format!("camera {camera} (the solver's own camera {i}): {e}")))
    }

    fn set_detection(&mut self, cfg: &TrackerConfig) -> std::result::Result<(), SourceError> {
        if self.own.is_none() {
            return Ok(());
        }
        self.own_request(OwnRequest::Detection(*cfg)).map_err(|e| {
            SourceError::Config(format!(
                "the solver's own cameras: detector settings refused: {e}"
            ))
        })
    }
}

impl ClusterSource {
    /// Hands `req` to the own cameras' thread and waits (up to [`OWN_REQUEST_WAIT`]) for its
    /// answer. Only on an operator's change, between sets.
    fn own_request(&mut self, req: OwnRequest) -> std::result::Result<(), String> {
        let Some(own) = &self.own else {
            return Err("the solver has no cameras of its own".into());
        };
        // Answers to earlier requests that timed out.
        while own.replies.try_recv().is_ok() {}
        own.requests
            .send(req)
            .map_err(|_| "its capture thread has stopped".to_string())?;
        match own.replies.recv_timeout(OWN_REQUEST_WAIT) {
            Ok(r) => r,
            Err(_) => Err(format!(
                "its capture thread did not answer within {} ms",
                OWN_REQUEST_WAIT.as_millis()
            )),
        }
    }
}

/// Board publish → solver receive of a camera board's observation (see
/// `ClusterReport::hop_us`), from `*from_ns` on (set to 1 s after the first call); `own`: the
/// solver's own board, left out. Lock-free, allocation-free.
fn record_hop(
    hop: &crate::metrics::LatencyHistogram,
    from_ns: &mut Option<u64>,
    own: Option<&str>,
    h: &irtrack_core::observation::ObsHeader<'_>,
    received_ns: u64,
) {
    let from = *from_ns.get_or_insert(received_ns + 1_000_000_000);
    if received_ns < from || h.clock != ObsClock::Realtime || own == Some(h.board) {
        return;
    }
    let sent_ns = h.capture_ts_ns.saturating_add(u64::from(h.send_delay_us) * 1000);
    hop.record_ns(received_ns.saturating_sub(sent_ns));
}

/// The peers Zenoh refused, as `/status` shows them; logs a line about new refusals at most
/// every 10 s (a flood must not flood the journal).
fn peer_refusals_report(log: &irtrack_cluster::refusals::PeerRefusals) -> super::report::PeerRefusalsReport {
    let now = std::time::Instant::now();
    if let Some(line) = log.take_notice(now) {
        tracing::warn!("{line}");
    }
    let snap = log.snapshot();
    super::report::PeerRefusalsReport {
        counting: snap.counting,
        total: snap.total,
        by_reason: snap.by_reason.iter().map(|(r, n)| (r.code(), *n)).collect(),
        credentials: snap.by_problem.iter().map(|(p, n)| (p.code(), *n)).collect(),
        recent: snap
            .recent
            .iter()
            .map(|p| super::report::RefusedPeerReport {
                address: p.address.clone(),
                reason: p.reason.code(),
                problem: p.problem.map(|x| x.code()),
                count: p.count,
                age_s: now.saturating_duration_since(p.last).as_secs_f64(),
                last_unix_ms: p.last_unix_ms,
                words: p.words(),
            })
            .collect(),
        denied_publications: snap.denied_publications,
        denied_recent: snap
            .denied_recent
            .iter()
            .map(|d| super::report::DeniedPublicationReport {
                zid: d.zid.clone(),
                user: d.user().map(str::to_string),
                subject: d.subject.clone(),
                key: d.key.clone(),
                action: d.action.code(),
                count: d.count,
                age_s: now.saturating_duration_since(d.last).as_secs_f64(),
                last_unix_ms: d.last_unix_ms,
                words: d.words(),
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn boards(offsets_ms: &[Option<f64>]) -> Vec<irtrack_cluster::pairing::BoardClock> {
        offsets_ms
            .iter()
            .map(|o| {
                let mut b = irtrack_cluster::pairing::BoardClock::default();
                b.offset_ns = o.map(|ms| (ms * 1e6) as i64);
                b
            })
            .collect()
    }

    /// Ahead is flagged while another board is not ahead, behind while another is in line;
    /// every board off alike (the solver's own clock off) flags none; no offset yet, no flag.
    #[test]
    fn clock_flags_name_the_board_out_of_line_only() {
        let limit = 2_000_000;
        let (ahead, behind) = clock_flags(&boards(&[Some(0.1), Some(6.0), None]), limit);
        assert_eq!(
            (&ahead[..3], &behind[..3]),
            (&[false, true, false][..], &[false; 3][..])
        );
        let (ahead, behind) = clock_flags(&boards(&[Some(-0.2), Some(-6.0)]), limit);
        assert_eq!((&ahead[..2], &behind[..2]), (&[false; 2][..], &[false, true][..]));
        // All ahead, or all behind, alike: nothing to compare with.
        let (ahead, behind) = clock_flags(&boards(&[Some(6.0), Some(6.5)]), limit);
        assert!(ahead.iter().chain(&behind).all(|f| !f));
        let (ahead, behind) = clock_flags(&boards(&[Some(-6.0), Some(-6.5)]), limit);
        assert!(ahead.iter().chain(&behind).all(|f| !f));
        // One behind, one ahead: the ahead one is still evidence (transit cannot explain it);
        // the behind one is not warned about, nothing being in line.
        let (ahead, behind) = clock_flags(&boards(&[Some(-6.0), Some(6.0)]), limit);
        assert_eq!((&ahead[..2], &behind[..2]), (&[false, true][..], &[false; 2][..]));
    }
}
