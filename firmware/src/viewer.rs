//! The viewer tap: a latest-only copy of a frame set and its blob lists for the set-up view
//! (`/api/live`) and frame-set capture (`/api/frameset`).
//!
//! The processing loop never waits for a viewer: after publishing a set it copies into the tap
//! only what a viewer has asked for, into latest-value slots it fills only if it gets their
//! lock at once (`try_lock`); a viewer still reading the previous copy simply makes it skip
//! this set, and the skip is counted. Two slots, so a viewer never makes the loop copy more
//! than it needs:
//!
//! - the **frame copy** ([`TapSet`]: both frames and the loop's blob lists), made only at the
//!   fastest preview rate a viewer asked for (or once, on request: `/api/frameset`, the
//!   sampler) — never for every set;
//! - the **blob copy** ([`BlobCopy`]: the loop's blob lists and the cameras' timestamps, a few
//!   kB), made for every set while a viewer asks for every set's blobs.
//!
//! The buffers are allocated on the viewer's side when the first viewer arrives and freed when
//! the last leaves, so the loop only ever copies into memory that already exists (checked by
//! `tests/no_alloc.rs` with viewers attached).

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, TryLockError};
use std::time::{Duration, Instant};

use irtrack_core::pipeline::TrackerConfig;

use crate::advice::{CameraAnalysis, Suggestion};
pub use crate::blob_view::{BlobView, RejectReason};
use crate::source::{Frame, FrameSet, Pixels};

const R: Ordering = Ordering::Relaxed;

/// Blobs listed per camera in a copy; more are counted in [`TapSet::blobs_truncated`].
pub const MAX_TAP_BLOBS: usize = 32;

/// A copy of one processed frame set.
#[derive(Debug, Clone)]
pub struct TapSet {
    /// Index of the copied frame set (the source's count).
    pub set_index: u64,
    /// Timestamp spread between the set's cameras, ns.
    pub pairing_error_ns: u64,
    /// The cameras' frames, pixels included, in camera order.
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
    /// LEDs a camera may keep with the loop's parameter set (tools' LEDs and loose LEDs,
    /// [`crate::advice::expected_leds`]); `None` without tools.
    pub expected_leds: Option<usize>,
    /// Per camera: the frame holds the camera's pixels (false: a cluster solver's camera-board
    /// camera, blobs only; [`crate::source::FrameSource::has_pixels`]).
    pub has_pixels: Vec<bool>,
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
            expected_leds: None,
            has_pixels: vec![true; set.frames.len()],
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
                if !self.has_pixels.get(camera).copied().unwrap_or(true) {
                    // No pixels here (a camera board's camera at the solver): its blobs, no
                    // judgement of a blank frame.
                    return CameraAnalysis::blobs_only(camera, self.set_index, &self.tracker_cfg, listed);
                }
                CameraAnalysis::of(
                    camera,
                    self.set_index,
                    frame,
                    &self.tracker_cfg,
                    listed,
                    MAX_TAP_BLOBS,
                )
                .map(|a| a.expecting(self.expected_leds))
                .unwrap_or_else(|| CameraAnalysis::unreadable(camera, self.set_index, &self.tracker_cfg))
            })
            .collect()
    }
}

/// The loop's blob lists of one set, without its frames (for viewers that ask for every set's
/// blobs: a few kB copied instead of both full frames).
#[derive(Debug, Clone, PartialEq)]
pub struct BlobCopy {
    /// Index of the frame set the blobs come from.
    pub set_index: u64,
    /// Timestamp spread between the set's cameras, ns.
    pub pairing_error_ns: u64,
    /// Per camera: the frame's capture timestamp.
    pub timestamps_ns: Vec<u64>,
    /// Per camera: kept and rejected blobs (at most [`MAX_TAP_BLOBS`] each).
    pub blobs: Vec<Vec<BlobView>>,
    /// Blobs left out of `blobs` for lack of room.
    pub blobs_truncated: u32,
    /// `blobs` holds the loop's detection of this set (false before a parameter set exists).
    pub detected: bool,
}

impl BlobCopy {
    fn shaped_like(set: &FrameSet) -> Self {
        Self {
            set_index: 0,
            pairing_error_ns: 0,
            timestamps_ns: vec![0; set.frames.len()],
            blobs: set
                .frames
                .iter()
                .map(|_| Vec::with_capacity(MAX_TAP_BLOBS))
                .collect(),
            blobs_truncated: 0,
            detected: false,
        }
    }

    /// Starts the copy of `set` (no allocation while the camera count matches): its index and
    /// timestamps, empty lists. Returns false if the shapes differ.
    pub fn begin(&mut self, set: &FrameSet) -> bool {
        if set.frames.len() != self.timestamps_ns.len() {
            return false;
        }
        for (t, f) in self.timestamps_ns.iter_mut().zip(&set.frames) {
            *t = f.timestamp_ns;
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

    /// Per camera: the loop's list plus the spots a recent whole-frame pass (`analysis`, made
    /// on the viewer's side at the preview rate or by the sampler, possibly of an earlier set)
    /// found outside it — a lamp, a reflection — so a blob list shows them as a preview does.
    /// A spot from the pass that lies on one of this set's listed blobs is the same spot and
    /// left out. Before a parameter set exists (nothing detected) the lists are the pass's.
    /// `None` when nothing was detected and there is no analysis to show instead.
    pub fn with_full_search(&self, analysis: Option<&[CameraAnalysis]>) -> Option<(Vec<Vec<BlobView>>, u32)> {
        let mut truncated = self.blobs_truncated;
        let mut out = Vec::with_capacity(self.blobs.len());
        for (camera, listed) in self.blobs.iter().enumerate() {
            let a = analysis.and_then(|a| a.iter().find(|c| c.camera == camera));
            if !self.detected {
                out.push(a?.blobs.clone());
                continue;
            }
            let mut list = listed.clone();
            for extra in a.map_or(&[][..], |a| &a.blobs[a.from_loop.min(a.blobs.len())..]) {
                let r_px = f64::from(extra.area_px).sqrt().max(3.0);
                let same = listed
                    .iter()
                    .any(|l| (l.x_px - extra.x_px).hypot(l.y_px - extra.y_px) <= r_px);
                if same {
                    continue;
                }
                let mut e = *extra;
                // Found by a pass made without the loop's list: usable, but not examined.
                if e.kept {
                    e.kept = false;
                    e.reason = Some(RejectReason::Window);
                }
                if list.len() < MAX_TAP_BLOBS {
                    list.push(e);
                } else {
                    truncated += 1;
                }
            }
            out.push(list);
        }
        Some((out, truncated))
    }
}

/// Shared between the loop (writer) and the viewers (readers).
#[derive(Debug)]
pub struct ViewerTap {
    slot: Mutex<Option<Box<TapSet>>>,
    /// Smallest preview interval (ns) any viewer asked for; 0 = none streams previews.
    interval_ns: AtomicU64,
    /// The blob copy of the latest set (see [`BlobCopy`]).
    blob_slot: Mutex<Option<Box<BlobCopy>>>,
    /// Viewers asking for every set's blob lists.
    blob_viewers: AtomicU64,
    /// Bumped after every completed blob copy.
    blob_seq: AtomicU64,
    blob_copies: AtomicU64,
    /// Sets whose blob copy the loop skipped because a viewer held the slot.
    blob_busy_skips: AtomicU64,
    /// Sets a blob viewer did not send (it was still sending an earlier one, or the loop
    /// skipped the copy): the viewers' side of the latest-value hand-off.
    viewer_dropped_sets: AtomicU64,
    /// A one-off copy was requested (`/api/frameset`).
    once: AtomicBool,
    /// Bumped after every completed copy.
    seq: AtomicU64,
    /// Sets skipped because a viewer held the copy.
    busy_skips: AtomicU64,
    copies: AtomicU64,
    /// Per viewer: its preview interval (ns, 0 = none) and whether it wants every set's blobs.
    viewers: Mutex<HashMap<u64, Want>>,
    next_viewer: AtomicU64,
    /// The loop's frame-set shape, for allocating the copy.
    template: Mutex<Option<FrameSet>>,
    /// The newest whole-frame analysis (by a viewer's render or the sampler).
    analysis: Mutex<Option<LatestAnalysis>>,
    /// The threshold suggestion made at first start (no saved tuning), if any.
    startup_suggestion: Mutex<Option<Suggestion>>,
}

/// What one viewer asked the loop for.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
struct Want {
    interval_ns: u64,
    blobs: bool,
}

/// An analysis and when it was made.
#[derive(Debug, Clone)]
pub struct LatestAnalysis {
    /// When the analysis was made.
    pub at: Instant,
    /// One analysis per camera, in camera order.
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
    /// Changes this viewer's wanted frame-copy interval (0 = no periodic frame copies for it);
    /// it keeps its blob wish.
    pub fn set_interval_ns(&self, interval_ns: u64) {
        let blobs = self
            .tap
            .viewers
            .lock()
            .map(|v| v.get(&self.id).is_some_and(|w| w.blobs))
            .unwrap_or(false);
        self.set_wants(interval_ns, blobs);
    }

    /// What this viewer wants: frame copies every `preview_interval_ns` (0 = none) and, with
    /// `every_set_blobs`, a blob copy of every set.
    pub fn set_wants(&self, preview_interval_ns: u64, every_set_blobs: bool) {
        if let Ok(mut v) = self.tap.viewers.lock() {
            v.insert(
                self.id,
                Want {
                    interval_ns: preview_interval_ns,
                    blobs: every_set_blobs,
                },
            );
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
        if empty {
            if let Ok(mut s) = self.tap.slot.lock() {
                *s = None;
            }
            if let Ok(mut s) = self.tap.blob_slot.lock() {
                *s = None;
            }
        }
    }
}

impl ViewerTap {
    /// A tap with no viewer, so the loop copies nothing.
    pub fn new() -> Self {
        Self {
            slot: Mutex::new(None),
            interval_ns: AtomicU64::new(0),
            blob_slot: Mutex::new(None),
            blob_viewers: AtomicU64::new(0),
            blob_seq: AtomicU64::new(0),
            blob_copies: AtomicU64::new(0),
            blob_busy_skips: AtomicU64::new(0),
            viewer_dropped_sets: AtomicU64::new(0),
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

    /// The threshold suggestion made at first start, when the configured threshold did not suit the
    /// cameras.
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
            v.insert(id, Want::default());
        }
        if let Ok(t) = self.template.lock()
            && let Some(t) = t.as_ref()
        {
            if let Ok(mut s) = self.slot.lock()
                && s.is_none()
            {
                *s = Some(Box::new(TapSet::shaped_like(t)));
            }
            if let Ok(mut s) = self.blob_slot.lock()
                && s.is_none()
            {
                *s = Some(Box::new(BlobCopy::shaped_like(t)));
            }
        }
        ViewerGuard {
            tap: self.clone(),
            id,
        }
    }

    fn update_interval(&self) {
        let (min, blobs) = self
            .viewers
            .lock()
            .map(|v| {
                (
                    v.values()
                        .map(|w| w.interval_ns)
                        .filter(|&i| i > 0)
                        .min()
                        .unwrap_or(0),
                    v.values().filter(|w| w.blobs).count() as u64,
                )
            })
            .unwrap_or((0, 0));
        self.interval_ns.store(min, R);
        self.blob_viewers.store(blobs, R);
    }

    /// The frame-copy interval the viewers asked for (ns; 0 = none).
    pub fn interval_ns(&self) -> u64 {
        self.interval_ns.load(R)
    }

    /// Asks the loop for one copy of its next set (in addition to any periodic copies).
    pub fn request_once(&self) {
        self.once.store(true, Ordering::Release);
    }

    /// Completed copies so far (a new value means a new copy is in the slot).
    pub fn seq(&self) -> u64 {
        self.seq.load(Ordering::Acquire)
    }

    /// Full frame-set copies the loop has made since start.
    pub fn copies(&self) -> u64 {
        self.copies.load(R)
    }

    /// Sets the loop skipped because a viewer was reading the copy.
    pub fn busy_skips(&self) -> u64 {
        self.busy_skips.load(R)
    }

    /// Viewers registered now.
    pub fn viewer_count(&self) -> usize {
        self.viewers.lock().map(|v| v.len()).unwrap_or(0)
    }

    /// Reader side: the current copy (blocks only other readers and makes the loop skip).
    pub fn read(&self) -> Option<MutexGuard<'_, Option<Box<TapSet>>>> {
        self.slot.lock().ok()
    }

    /// Completed blob copies so far (a new value means a new blob copy is in its slot).
    pub fn blob_seq(&self) -> u64 {
        self.blob_seq.load(Ordering::Acquire)
    }

    /// Blob-only copies the loop has made since start.
    pub fn blob_copies(&self) -> u64 {
        self.blob_copies.load(R)
    }

    /// Sets whose blob copy the loop skipped because a viewer was reading the slot.
    pub fn blob_busy_skips(&self) -> u64 {
        self.blob_busy_skips.load(R)
    }

    /// Sets the blob viewers did not send, summed over viewers.
    pub fn viewer_dropped_sets(&self) -> u64 {
        self.viewer_dropped_sets.load(R)
    }

    /// Viewer side: counts sets a viewer did not send.
    pub fn count_viewer_drops(&self, sets: u64) {
        self.viewer_dropped_sets.fetch_add(sets, R);
    }

    /// Reader side: a copy of the latest blob copy (holds the slot only for that copy).
    pub fn read_blobs(&self) -> Option<BlobCopy> {
        self.blob_slot.lock().ok()?.as_deref().cloned()
    }

    /// Loop side: whether a viewer wants this set's blob lists (an atomic load).
    pub fn wants_blobs(&self) -> bool {
        self.blob_viewers.load(R) > 0
    }

    /// Loop side: fills the blob copy through `fill` if its slot is free at once; never waits.
    pub fn try_fill_blobs(&self, fill: impl FnOnce(&mut BlobCopy) -> bool) -> bool {
        let mut guard = match self.blob_slot.try_lock() {
            Ok(g) => g,
            Err(TryLockError::WouldBlock) => {
                self.blob_busy_skips.fetch_add(1, R);
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
        self.blob_copies.fetch_add(1, R);
        self.blob_seq.fetch_add(1, Ordering::Release);
        true
    }

    /// Loop side: whether a frame copy is due now (cheap; atomics only).
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
            // Only when the configured threshold does not give one clean spot per camera (with
            // tools: at least one and at most the LEDs expected).
            let expected = set.expected_leds.unwrap_or(1);
            let suits = analysis
                .iter()
                .all(|a| a.kept >= 1 && a.kept as usize <= expected && a.advice.is_none());
            if suits {
                tracing::info!(
                    threshold_dn = set.tracker_cfg.threshold_dn,
                    "first start: the threshold suits these cameras"
                );
            } else {
                let s =
                    crate::advice::suggest_expecting(set.set_index, &set.frames, &set.tracker_cfg, expected);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::advice::Background;

    fn blob(x_px: f64, y_px: f64, reason: Option<RejectReason>) -> BlobView {
        BlobView {
            x_px,
            y_px,
            area_px: 30,
            peak_dn: 200,
            roundness: 0.9,
            kept: reason.is_none(),
            reason,
            tool: None,
            loose: false,
        }
    }

    fn analysis(camera: usize, blobs: Vec<BlobView>, from_loop: usize) -> CameraAnalysis {
        let mut a = CameraAnalysis::unreadable(camera, 7, &TrackerConfig::default());
        a.background = Some(Background {
            median_dn: 10,
            noise_dn: 1.0,
            bright_dn: 12,
            peak_dn: 200,
            max_dn: 255,
            safe_threshold_dn: 20,
        });
        a.advice = None;
        a.blobs = blobs;
        a.from_loop = from_loop;
        a
    }

    fn copy(detected: bool, lists: Vec<Vec<BlobView>>) -> BlobCopy {
        BlobCopy {
            set_index: 9,
            pairing_error_ns: 0,
            timestamps_ns: vec![1; lists.len()],
            blobs: lists,
            blobs_truncated: 0,
            detected,
        }
    }

    #[test]
    fn blob_lists_gain_the_full_search_spots_the_loop_did_not_list() {
        // Set 9: the LED moved 2 px since the analysed set 7; a lamp far away was found by the
        // whole-frame pass of set 7.
        let c = copy(true, vec![vec![blob(102.0, 50.0, None)]]);
        let a = [analysis(
            0,
            vec![
                blob(100.0, 50.0, None),                          // the loop's LED in set 7
                blob(101.0, 50.0, Some(RejectReason::Window)),    // the same spot, seen whole
                blob(400.0, 300.0, Some(RejectReason::Window)),   // a lamp
                blob(500.0, 20.0, Some(RejectReason::Roundness)), // a streak
            ],
            1,
        )];
        let (lists, truncated) = c.with_full_search(Some(&a)).unwrap();
        assert_eq!(truncated, 0);
        let l = &lists[0];
        assert_eq!(l.len(), 3, "{l:?}");
        assert_eq!(l[0], blob(102.0, 50.0, None), "the loop's own list comes first");
        assert_eq!(l[1].reason, Some(RejectReason::Window));
        assert_eq!(l[2].reason, Some(RejectReason::Roundness));
        // Without an analysis: the loop's list alone.
        assert_eq!(c.with_full_search(None).unwrap().0, c.blobs);
    }

    #[test]
    fn before_detection_the_lists_are_the_full_search() {
        let c = copy(false, vec![Vec::new(), Vec::new()]);
        assert!(c.with_full_search(None).is_none(), "nothing to list yet");
        let a = [
            analysis(0, vec![blob(10.0, 10.0, None)], 0),
            analysis(1, vec![blob(20.0, 20.0, None)], 0),
        ];
        let (lists, _) = c.with_full_search(Some(&a)).unwrap();
        assert_eq!(
            lists,
            vec![vec![blob(10.0, 10.0, None)], vec![blob(20.0, 20.0, None)]]
        );
        // Spots of a pass made without the loop's list are not "kept" once the loop detects.
        let c = copy(true, vec![vec![blob(10.0, 10.0, None)], Vec::new()]);
        let (lists, _) = c.with_full_search(Some(&a)).unwrap();
        assert_eq!(lists[0], vec![blob(10.0, 10.0, None)]);
        assert_eq!(lists[1].len(), 1);
        assert!(!lists[1][0].kept);
        assert_eq!(lists[1][0].reason, Some(RejectReason::Window));
    }
}
