//! The viewer tap: a latest-only copy of a frame set and its blob lists for the set-up view
//! (`/api/live`) and frame-set capture (`/api/frameset`).
//!
//! The processing loop never waits for a viewer: after publishing a set it copies that set
//! into the tap only when a viewer has asked (a rate, or one set on request), and only if it
//! gets the tap's lock at once (`try_lock`); a viewer still reading the previous copy simply
//! makes it skip this set. The buffer is allocated on the viewer's side when the first viewer
//! arrives and freed when the last leaves, so the loop only ever copies into memory that
//! already exists (checked by `tests/no_alloc.rs` with a viewer attached).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

use irtrack_core::blob::Blob;
use irtrack_core::pipeline::TrackerConfig;
use serde::Serialize;

use crate::advice::{CameraAnalysis, Suggestion};
use crate::source::{Frame, FrameSet, Pixels};

const R: Ordering = Ordering::Relaxed;

/// Blobs listed per camera in a copy; more are counted in [`TapSet::blobs_truncated`].
pub const MAX_TAP_BLOBS: usize = 32;

/// Why a blob was not used for the position.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RejectReason {
    /// Outside `[min_area_px, max_area_px]`.
    Area,
    /// Less round than `min_roundness` (a streak or reflection).
    Roundness,
    /// Cut by the frame border (or the tracking window), so its centroid is biased.
    Edge,
    /// Usable, but not consistent with the other cameras (the ray gate chose another spot).
    Gate,
    /// Not examined by the loop for this set: outside the tracking window while the marker
    /// is tracked (the loop looks there again when it loses the marker), or beyond the blobs
    /// it keeps per camera. Found by the viewer's own full-frame search.
    Window,
}

/// One blob as the set-up view draws it (full-resolution pixel coordinates).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BlobView {
    pub x_px: f64,
    pub y_px: f64,
    pub area_px: u32,
    pub peak_dn: u32,
    pub roundness: f64,
    pub kept: bool,
    pub reason: Option<RejectReason>,
}

/// A copy of one processed frame set.
#[derive(Debug, Clone)]
pub struct TapSet {
    pub set_index: u64,
    pub pairing_error_ns: u64,
    pub frames: Vec<Frame>,
    /// Per camera: kept and rejected blobs (at most [`MAX_TAP_BLOBS`] each).
    pub blobs: Vec<Vec<BlobView>>,
    /// Blobs left out of `blobs` for lack of room.
    pub blobs_truncated: u32,
    /// Threshold the set was detected with (frame DN).
    pub threshold_dn: u32,
    /// The loop's detection settings when the set was copied (the viewer's full-frame search
    /// classifies with them).
    pub tracker_cfg: TrackerConfig,
    /// `blobs` holds the loop's detection of this set (false before a parameter set exists:
    /// the loop does not track then).
    pub detected: bool,
}

impl TapSet {
    fn shaped_like(set: &FrameSet) -> Self {
        Self {
            set_index: 0,
            pairing_error_ns: 0,
            frames: set.frames.clone(),
            blobs: set
                .frames
                .iter()
                .map(|_| Vec::with_capacity(MAX_TAP_BLOBS))
                .collect(),
            blobs_truncated: 0,
            threshold_dn: 0,
            tracker_cfg: TrackerConfig::default(),
            detected: false,
        }
    }

    /// Copies `set`'s frames in place (no allocation while shapes match). Returns false if
    /// the shapes differ (the copy is then left unchanged).
    pub fn copy_frames_from(&mut self, set: &FrameSet) -> bool {
        if set.frames.len() != self.frames.len() {
            return false;
        }
        for (dst, src) in self.frames.iter_mut().zip(&set.frames) {
            let same = match (&mut dst.pixels, &src.pixels) {
                (Pixels::U8(d), Pixels::U8(s)) if d.len() == s.len() => {
                    d.copy_from_slice(s);
                    true
                }
                (Pixels::U16(d), Pixels::U16(s)) if d.len() == s.len() => {
                    d.copy_from_slice(s);
                    true
                }
                _ => false,
            };
            if !same {
                return false;
            }
            dst.width_px = src.width_px;
            dst.height_px = src.height_px;
            dst.stride_px = src.stride_px;
            dst.bit_depth = src.bit_depth;
            dst.timestamp_ns = src.timestamp_ns;
            dst.sequence = src.sequence;
        }
        self.set_index = set.index;
        self.pairing_error_ns = set.pairing_error_ns;
        for b in &mut self.blobs {
            b.clear();
        }
        self.blobs_truncated = 0;
        self.detected = false;
        true
    }

    /// Adds a blob to `camera`'s list within the fixed capacity.
    pub fn push_blob(&mut self, camera: usize, blob: BlobView) {
        match self.blobs.get_mut(camera) {
            Some(list) if list.len() < list.capacity() => list.push(blob),
            _ => self.blobs_truncated += 1,
        }
    }

    /// Per camera: the loop's blob list plus every spot a full-frame search finds that the
    /// list lacks. While the marker is tracked the loop only looks inside its tracking window,
    /// so a lamp or a reflection elsewhere would not be drawn; the person aiming the cameras
    /// must see it (it competes with the LED as soon as the marker is lost). Before a parameter
    /// set exists the loop detects nothing and every spot comes from this search: the ones the
    /// area, roundness and edge limits would use are marked kept. Runs on the viewer's side, at
    /// the preview rate, never in the loop.
    pub fn blobs_with_full_search(&self) -> Vec<Vec<BlobView>> {
        self.analyse().into_iter().map(|a| a.blobs).collect()
    }

    /// The whole-frame pass of every camera ([`crate::advice::CameraAnalysis`]): background,
    /// every bright region kept or rejected with its reason, overload, advice in words.
    pub fn analyse(&self) -> Vec<CameraAnalysis> {
        self.frames
            .iter()
            .enumerate()
            .map(|(camera, frame)| {
                let listed = if self.detected {
                    self.blobs.get(camera).map(Vec::as_slice)
                } else {
                    None
                };
                CameraAnalysis::of(
                    camera,
                    self.set_index,
                    frame,
                    &self.tracker_cfg,
                    listed,
                    MAX_TAP_BLOBS,
                )
                .unwrap_or_else(|| CameraAnalysis::unreadable(camera, self.set_index, &self.tracker_cfg))
            })
            .collect()
    }
}

impl BlobView {
    /// A detected blob, kept when there is no reason against it.
    pub fn of(b: &Blob, reason: Option<RejectReason>) -> Self {
        BlobView {
            x_px: b.x_px,
            y_px: b.y_px,
            area_px: b.area_px,
            peak_dn: b.peak_dn,
            roundness: b.roundness,
            kept: reason.is_none(),
            reason,
        }
    }
}

/// Shared between the loop (writer) and the viewers (readers).
#[derive(Debug)]
pub struct ViewerTap {
    slot: Mutex<Option<Box<TapSet>>>,
    /// Smallest interval (ns) any streaming viewer asked for; 0 = none streams.
    interval_ns: AtomicU64,
    /// A one-off copy was requested (`/api/frameset`).
    once: AtomicBool,
    /// Bumped after every completed copy.
    seq: AtomicU64,
    /// Sets skipped because a viewer held the copy.
    busy_skips: AtomicU64,
    copies: AtomicU64,
    viewers: Mutex<HashMap<u64, u64>>,
    next_viewer: AtomicU64,
    /// The loop's frame-set shape, for allocating the copy.
    template: Mutex<Option<FrameSet>>,
    /// The newest whole-frame analysis (by a viewer's render or the sampler).
    analysis: Mutex<Option<LatestAnalysis>>,
    /// The threshold suggestion made at first start (no saved tuning), if any.
    startup_suggestion: Mutex<Option<Suggestion>>,
}

/// An analysis and when it was made.
#[derive(Debug, Clone)]
pub struct LatestAnalysis {
    pub at: Instant,
    pub cameras: Arc<Vec<CameraAnalysis>>,
}

impl Default for ViewerTap {
    fn default() -> Self {
        Self::new()
    }
}

/// A registered viewer; leaving (drop) updates the copy rate and frees the buffer after the
/// last one.
pub struct ViewerGuard {
    tap: Arc<ViewerTap>,
    id: u64,
}

impl ViewerGuard {
    /// Changes this viewer's wanted interval (0 = no periodic copies for it).
    pub fn set_interval_ns(&self, interval_ns: u64) {
        if let Ok(mut v) = self.tap.viewers.lock() {
            v.insert(self.id, interval_ns);
        }
        self.tap.update_interval();
    }
}

impl Drop for ViewerGuard {
    fn drop(&mut self) {
        let empty = match self.tap.viewers.lock() {
            Ok(mut v) => {
                v.remove(&self.id);
                v.is_empty()
            }
            Err(_) => false,
        };
        self.tap.update_interval();
        if empty && let Ok(mut s) = self.tap.slot.lock() {
            *s = None;
        }
    }
}

impl ViewerTap {
    pub fn new() -> Self {
        Self {
            slot: Mutex::new(None),
            interval_ns: AtomicU64::new(0),
            once: AtomicBool::new(false),
            seq: AtomicU64::new(0),
            busy_skips: AtomicU64::new(0),
            copies: AtomicU64::new(0),
            viewers: Mutex::new(HashMap::new()),
            next_viewer: AtomicU64::new(1),
            template: Mutex::new(None),
            analysis: Mutex::new(None),
            startup_suggestion: Mutex::new(None),
        }
    }

    /// Keeps `cameras` as the newest analysis (unless a newer set's is already there).
    pub fn store_analysis(&self, cameras: Vec<CameraAnalysis>) {
        if let Ok(mut a) = self.analysis.lock() {
            let newer = a.as_ref().is_none_or(|old| {
                old.cameras.first().map(|c| c.set_index) <= cameras.first().map(|c| c.set_index)
            });
            if newer {
                *a = Some(LatestAnalysis {
                    at: Instant::now(),
                    cameras: Arc::new(cameras),
                });
            }
        }
    }

    /// The newest analysis if it is younger than `max_age`.
    pub fn analysis(&self, max_age: Duration) -> Option<Arc<Vec<CameraAnalysis>>> {
        let a = self.analysis.lock().ok()?;
        a.as_ref()
            .filter(|a| a.at.elapsed() <= max_age)
            .map(|a| a.cameras.clone())
    }

    pub fn startup_suggestion(&self) -> Option<Suggestion> {
        self.startup_suggestion.lock().ok().and_then(|s| s.clone())
    }

    /// Takes a copy of the loop's next set (attaching as a viewer for the moment), waiting up
    /// to `wait`. Blocking: call from a blocking thread.
    pub fn snapshot_blocking(self: &Arc<Self>, wait: Duration) -> Option<TapSet> {
        let viewer = self.attach();
        let seq0 = self.seq();
        self.request_once();
        let deadline = Instant::now() + wait;
        while self.seq() == seq0 {
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let set = self.read()?.as_deref().cloned();
        drop(viewer);
        set
    }

    /// Called once by the loop's owner with the loop's (empty) frame set shape.
    pub fn set_template(&self, set: FrameSet) {
        if let Ok(mut t) = self.template.lock() {
            *t = Some(set);
        }
    }

    /// Registers a viewer; the first one allocates the copy buffer (here, not in the loop).
    pub fn attach(self: &Arc<Self>) -> ViewerGuard {
        let id = self.next_viewer.fetch_add(1, R);
        if let Ok(mut v) = self.viewers.lock() {
            v.insert(id, 0);
        }
        if let Ok(mut s) = self.slot.lock()
            && s.is_none()
            && let Ok(t) = self.template.lock()
            && let Some(t) = t.as_ref()
        {
            *s = Some(Box::new(TapSet::shaped_like(t)));
        }
        ViewerGuard {
            tap: self.clone(),
            id,
        }
    }

    fn update_interval(&self) {
        let min = self
            .viewers
            .lock()
            .map(|v| v.values().copied().filter(|&i| i > 0).min().unwrap_or(0))
            .unwrap_or(0);
        self.interval_ns.store(min, R);
    }

    /// Asks the loop for one copy of its next set (in addition to any periodic copies).
    pub fn request_once(&self) {
        self.once.store(true, Ordering::Release);
    }

    /// Completed copies so far (a new value means a new copy is in the slot).
    pub fn seq(&self) -> u64 {
        self.seq.load(Ordering::Acquire)
    }

    pub fn copies(&self) -> u64 {
        self.copies.load(R)
    }

    /// Sets the loop skipped because a viewer was reading the copy.
    pub fn busy_skips(&self) -> u64 {
        self.busy_skips.load(R)
    }

    pub fn viewer_count(&self) -> usize {
        self.viewers.lock().map(|v| v.len()).unwrap_or(0)
    }

    /// Reader side: the current copy (blocks only other readers and makes the loop skip).
    pub fn read(&self) -> Option<MutexGuard<'_, Option<Box<TapSet>>>> {
        self.slot.lock().ok()
    }

    /// Loop side: whether a copy is due now (cheap; atomics only).
    pub fn wants_copy(&self, now_ns: u64, last_copy_ns: u64) -> bool {
        if self.once.load(Ordering::Acquire) {
            return true;
        }
        let interval = self.interval_ns.load(R);
        interval != 0 && now_ns.saturating_sub(last_copy_ns) >= interval
    }

    /// Loop side: fills the copy through `fill` if the slot is free at once; never waits.
    /// Returns whether a copy was made.
    pub fn try_fill(&self, fill: impl FnOnce(&mut TapSet) -> bool) -> bool {
        let mut guard = match self.slot.try_lock() {
            Ok(g) => g,
            Err(TryLockError::WouldBlock) => {
                self.busy_skips.fetch_add(1, R);
                return false;
            }
            Err(TryLockError::Poisoned(_)) => return false,
        };
        let Some(buf) = guard.as_mut() else {
            return false;
        };
        if !fill(buf) {
            return false;
        }
        drop(guard);
        self.once.store(false, Ordering::Release);
        self.copies.fetch_add(1, R);
        self.seq.fetch_add(1, Ordering::Release);
        true
    }
}

/// How old an analysis may be and still describe a camera (status, faults).
pub const ANALYSIS_MAX_AGE: Duration = Duration::from_secs(3);
/// How often the sampler analyses a set when no page does.
pub const SAMPLE_PERIOD: Duration = Duration::from_secs(1);

/// Keeps the whole-frame analysis fresh when no set-up page is rendering previews (so `/status`
/// and its faults describe what the cameras see with or without a viewer and a parameter set),
/// and at first start (`first_start`: no saved tuning) suggests a threshold once, in the log and
/// on the page. Runs on its own thread, off the processing loop; stops when `stop` is set.
pub fn run_sampler(tap: Arc<ViewerTap>, first_start: bool, stop: Arc<AtomicBool>) {
    let mut suggested = !first_start;
    while !stop.load(R) {
        std::thread::sleep(SAMPLE_PERIOD / 4);
        let fresh = tap.analysis(SAMPLE_PERIOD).is_some();
        if fresh && suggested {
            continue;
        }
        if tap.template.lock().map(|t| t.is_none()).unwrap_or(true) {
            continue;
        }
        let Some(set) = tap.snapshot_blocking(Duration::from_secs(2)) else {
            continue;
        };
        let analysis = set.analyse();
        for a in &analysis {
            if let Some(adv) = a.advice.as_ref().filter(|_| !suggested) {
                tracing::warn!(camera = a.camera, code = adv.code, "{}", adv.message);
            }
        }
        if !suggested {
            suggested = true;
            // Only when the configured threshold does not give one clean spot per camera.
            let suits = analysis.iter().all(|a| a.kept == 1 && a.advice.is_none());
            if suits {
                tracing::info!(
                    threshold_dn = set.tracker_cfg.threshold_dn,
                    "first start: the threshold suits these cameras"
                );
            } else {
                let s = crate::advice::suggest(set.set_index, &set.frames, &set.tracker_cfg);
                if let Some(v) = s.threshold_dn {
                    tracing::warn!(
                        current_dn = s.current_threshold_dn,
                        suggested_dn = v,
                        keeps_only_marker = s.keeps_only_marker,
                        "first start: the threshold {} DN does not suit these cameras; suggested {v} DN ({}) — apply it on the set-up page (Suggest threshold) or set [tracking] threshold_dn",
                        s.current_threshold_dn,
                        s.reasoning.join("; ")
                    );
                }
                if let Ok(mut g) = tap.startup_suggestion.lock() {
                    *g = Some(s);
                }
            }
        }
        tap.store_analysis(analysis);
    }
}
