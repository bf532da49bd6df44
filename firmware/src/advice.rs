//! What a camera's whole frame says about the detector's settings, in plain words: the
//! background level against the threshold, every bright region kept or rejected with its
//! reason, "overloaded" when there are more regions than the detector handles, and a
//! threshold suggestion from the frame's histogram and the marker's peak.
//!
//! Everything here runs on the viewer's side (the set-up view's copy of a frame set, at the
//! preview rate, or a sampler about once a second) — never in the processing loop. Contract of
//! the JSON: docs/http-api.md; the reasoning: docs/setup-view.md.

use irtrack_core::blob::{Blob, BlobConfig, BlobDetector, BlobLimits, DetectStats};
use irtrack_core::image::{GrayImage, Pixel};
use irtrack_core::pipeline::TrackerConfig;
use serde::Serialize;

use crate::blob_view::{BlobView, RejectReason};
use crate::source::{Frame, Pixels};

/// Share of the frame above the threshold beyond which the background, not a light, is the
/// problem (an LED covers well under 0.1 % of a frame).
pub const BACKGROUND_FRACTION: f64 = 0.05;
/// Percentile of the frame taken as "the brighter parts of the background": floor texture,
/// vignetting's bright centre. The marker, a lamp and reflections (compact: together well under
/// 2 % of a frame, ~6000 px at 640×480) stay above it.
pub const BRIGHT_BACKGROUND_PERCENTILE: f64 = 98.0;
/// Noise multiples kept between the background and a threshold.
pub const NOISE_MARGIN: f64 = 3.0;
/// Thresholds tried per camera when checking a suggestion against the frame.
const TRIAL_STEPS: u32 = 24;

/// Grey-level statistics of one frame.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Background {
    /// Median pixel (DN): the background level.
    pub median_dn: u32,
    /// Noise (DN): median minus the 15.9th percentile (one standard deviation for Gaussian
    /// noise), at least 1.
    pub noise_dn: f64,
    /// [`BRIGHT_BACKGROUND_PERCENTILE`] (DN).
    pub bright_dn: u32,
    /// Brightest pixel (DN).
    pub peak_dn: u32,
    /// Top code of the frame (255, 1023, …).
    pub max_dn: u32,
    /// Lowest threshold that keeps the background out: above its bright parts by
    /// [`NOISE_MARGIN`] noise (rounded up to 5 DN on 8-bit frames).
    pub safe_threshold_dn: u32,
}

/// Histogram of a frame (one bin per code).
fn histogram(frame: &Frame) -> Vec<u64> {
    let bins = 1usize << frame.bit_depth.clamp(1, 16);
    let mut h = vec![0u64; bins];
    let (w, rows, stride) = (
        frame.width_px as usize,
        frame.height_px as usize,
        frame.stride_px.max(1) as usize,
    );
    match &frame.pixels {
        Pixels::U8(p) => {
            for row in p.chunks(stride).take(rows) {
                for v in &row[..w.min(row.len())] {
                    h[usize::from(*v).min(bins - 1)] += 1;
                }
            }
        }
        Pixels::U16(p) => {
            for row in p.chunks(stride).take(rows) {
                for v in &row[..w.min(row.len())] {
                    h[usize::from(*v).min(bins - 1)] += 1;
                }
            }
        }
    }
    h
}

fn percentile(h: &[u64], total: u64, pct: f64) -> u32 {
    let want = ((pct / 100.0) * total as f64).ceil().max(1.0) as u64;
    let mut acc = 0;
    for (v, n) in h.iter().enumerate() {
        acc += n;
        if acc >= want {
            return v as u32;
        }
    }
    h.len().saturating_sub(1) as u32
}

impl Background {
    /// The statistics of `frame` and its histogram (one count per code); `None` for a frame without
    /// pixels.
    pub fn of(frame: &Frame) -> Option<(Self, Vec<u64>)> {
        let h = histogram(frame);
        let total: u64 = h.iter().sum();
        if total == 0 {
            return None;
        }
        let max_dn = (h.len() - 1) as u32;
        let median_dn = percentile(&h, total, 50.0);
        let low = percentile(&h, total, 15.87);
        let noise_dn = f64::from(median_dn - low.min(median_dn)).max(1.0);
        let bright_dn = percentile(&h, total, BRIGHT_BACKGROUND_PERCENTILE);
        let peak_dn = h.iter().rposition(|n| *n > 0).unwrap_or(0) as u32;
        let raw = (f64::from(bright_dn) + NOISE_MARGIN * noise_dn)
            .max(f64::from(median_dn) + 2.0 * NOISE_MARGIN * noise_dn)
            .ceil() as u32;
        // Round numbers are easier to type and remember; the step scales with the depth.
        let step = (max_dn + 1) / 51;
        let safe = if step > 1 { raw.div_ceil(step) * step } else { raw };
        Some((
            Background {
                median_dn,
                noise_dn,
                bright_dn,
                peak_dn,
                max_dn,
                safe_threshold_dn: safe.min(max_dn.saturating_sub(1)),
            },
            h,
        ))
    }

    /// Share of pixels above `threshold_dn`.
    pub fn fraction_above(h: &[u64], threshold_dn: u32) -> f64 {
        let total: u64 = h.iter().sum();
        let above: u64 = h.iter().skip(threshold_dn as usize + 1).sum();
        if total == 0 {
            0.0
        } else {
            above as f64 / total as f64
        }
    }
}

/// A whole-frame detection with every region classified.
#[derive(Debug, Clone)]
pub struct Detection {
    /// Regions within the area limits, with the reason each is rejected (`None`: kept).
    pub blobs: Vec<(Blob, Option<RejectReason>)>,
    /// Regions outside the area limits.
    pub by_area: Vec<Blob>,
    /// The detector's own counters for this pass (labels used, regions found, ...).
    pub stats: DetectStats,
    /// Regions the loop would consider (within the area limits): more than `max_blobs` of
    /// them means the loop drops some.
    pub candidates: u32,
}

impl Detection {
    /// The regions that pass every rule: what the loop would use.
    pub fn kept(&self) -> impl Iterator<Item = &Blob> {
        self.blobs.iter().filter(|(_, r)| r.is_none()).map(|(b, _)| b)
    }
}

/// Runs the detector over the whole of `frame` at `threshold_dn` with the loop's limits
/// (labels) and classifies every region by the loop's area, roundness and edge rules. `None`
/// for a malformed frame.
pub fn detect_whole(
    frame: &Frame,
    cfg: &TrackerConfig,
    threshold_dn: u32,
    list_max: usize,
) -> Option<Detection> {
    fn run<P: Pixel>(
        data: &[P],
        frame: &Frame,
        cfg: &TrackerConfig,
        threshold_dn: u32,
        list_max: usize,
    ) -> Option<Detection> {
        let image = GrayImage::new(data, frame.width_px, frame.height_px, frame.stride_px).ok()?;
        let mut limits = BlobLimits::for_frame(frame.width_px, frame.height_px);
        limits.max_labels = cfg.max_labels.max(1);
        limits.max_blobs = list_max.max(cfg.max_blobs).max(1);
        let mut detector = BlobDetector::new(limits).ok()?;
        let config = BlobConfig {
            threshold_dn,
            saturation_dn: cfg.saturation_dn,
            min_area_px: cfg.min_area_px,
            max_area_px: cfg.max_area_px,
        };
        let found = detector.detect(&image, None, &config).ok()?.to_vec();
        let stats = detector.stats();
        let blobs = found
            .into_iter()
            .map(|b| {
                let reason = if b.roundness < cfg.min_roundness {
                    Some(RejectReason::Roundness)
                } else if cfg.reject_edge_blobs && b.touches_frame_edge {
                    Some(RejectReason::Edge)
                } else {
                    None
                };
                (b, reason)
            })
            .collect::<Vec<_>>();
        let candidates = stats.components.saturating_sub(stats.rejected_area);
        Some(Detection {
            blobs,
            by_area: detector.rejected_by_area().to_vec(),
            stats,
            candidates,
        })
    }
    match &frame.pixels {
        Pixels::U8(p) => run(p, frame, cfg, threshold_dn, list_max),
        Pixels::U16(p) => run(p, frame, cfg, threshold_dn, list_max),
    }
}

/// One piece of advice about a camera.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Advice {
    /// `background_above_threshold`, `overloaded`, `too_many_spots`, `no_led`,
    /// `no_usable_blob`, `unreadable_frame`. (Several kept spots are normal for a multi-LED
    /// tool; the page warns about them for a single marker.)
    pub code: &'static str,
    /// What is wrong and the next step, one sentence.
    pub message: String,
}

/// What the whole-frame pass found in one camera (the set-up view's one account of it: the
/// health table, the camera's header and the fault list all show this).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraAnalysis {
    /// Camera index, configuration order.
    pub camera: usize,
    /// Index of the frame set analysed.
    pub set_index: u64,
    /// Detection threshold the frame was analysed at, DN.
    pub threshold_dn: u32,
    /// Whether this irtrackd has the camera's pixels. `false`: a camera board's camera at the
    /// cluster solver — its pixels stay on its board, the analysis lists the blobs it reported.
    pub pixels: bool,
    /// Grey-level statistics of the frame; `None` (JSON `null`) without pixels or for a frame
    /// that could not be read — never zeros that read as a dark camera.
    pub background: Option<Background>,
    /// Share of the frame above the threshold, percent.
    pub above_threshold_pct: f64,
    /// Bright regions (connected areas above the threshold) in the whole frame.
    pub regions: u32,
    /// Regions that pass every rule.
    pub kept: u32,
    /// Regions refused, for area, roundness, the frame edge or the gate.
    pub rejected: u32,
    /// More separate regions than the detector's label limit: it reports none at all.
    pub overloaded: bool,
    /// The detector's label limit (regions per frame).
    pub max_labels: usize,
    /// More usable-sized regions than the loop keeps per camera (`max_blobs`).
    pub too_many_spots: bool,
    /// Blobs the loop keeps per camera at most (`[tracking] max_blobs`).
    pub max_blobs: usize,
    /// LEDs the parameter set expects a camera to see at most: every tool's LEDs plus the
    /// loose single LEDs the loop tracks ([`CameraAnalysis::expecting`]); `None` without tools
    /// (one marker: the page itself warns about several kept spots).
    pub expected_leds: Option<usize>,
    /// More kept spots than `expected_leds`: stray light beside the tools' LEDs.
    pub more_spots_than_leds: bool,
    /// The most important problem found, if any.
    pub advice: Option<Advice>,
    /// Every region marked kept or rejected with its reason (the preview's overlay).
    #[serde(skip)]
    pub blobs: Vec<BlobView>,
    /// How many of `blobs` (the first ones) are the loop's own list; the rest come from the
    /// whole-frame pass.
    #[serde(skip)]
    pub from_loop: usize,
}

fn reason_words(r: RejectReason) -> &'static str {
    match r {
        RejectReason::Area => "area",
        RejectReason::Roundness => "roundness",
        RejectReason::Edge => "cut by the frame edge",
        RejectReason::Gate => "not matched by the other cameras",
        RejectReason::Window => "outside the tracking window",
    }
}

/// Counts per reason, e.g. "2 for roundness, 1 cut by the frame edge".
pub fn reasons_summary(blobs: &[BlobView]) -> String {
    let mut counts: Vec<(RejectReason, u32)> = Vec::new();
    for r in blobs.iter().filter_map(|b| b.reason) {
        match counts.iter_mut().find(|(k, _)| *k == r) {
            Some((_, n)) => *n += 1,
            None => counts.push((r, 1)),
        }
    }
    counts
        .iter()
        .map(|(r, n)| format!("{n} {}", reason_words(*r)))
        .collect::<Vec<_>>()
        .join(", ")
}

impl CameraAnalysis {
    /// A camera whose pixels are not here (a camera board's camera at the cluster solver):
    /// the blobs it reported, no background and no advice (its own board's set-up view judges
    /// its pixels).
    pub fn blobs_only(
        camera: usize,
        set_index: u64,
        cfg: &TrackerConfig,
        listed: Option<&[BlobView]>,
    ) -> Self {
        let blobs: Vec<BlobView> = listed.map(<[BlobView]>::to_vec).unwrap_or_default();
        let kept = blobs.iter().filter(|b| b.kept).count() as u32;
        CameraAnalysis {
            regions: blobs.len() as u32,
            kept,
            rejected: blobs.len() as u32 - kept,
            advice: None,
            from_loop: blobs.len(),
            blobs,
            pixels: false,
            ..Self::unreadable(camera, set_index, cfg)
        }
    }

    /// A frame that could not be analysed (malformed); says so.
    pub fn unreadable(camera: usize, set_index: u64, cfg: &TrackerConfig) -> Self {
        CameraAnalysis {
            camera,
            set_index,
            threshold_dn: cfg.threshold_dn,
            pixels: true,
            background: None,
            above_threshold_pct: 0.0,
            regions: 0,
            kept: 0,
            rejected: 0,
            overloaded: false,
            max_labels: cfg.max_labels,
            too_many_spots: false,
            max_blobs: cfg.max_blobs,
            expected_leds: None,
            more_spots_than_leds: false,
            advice: Some(Advice {
                code: "unreadable_frame",
                message: format!(
                    "camera {camera}: its frame could not be analysed (malformed size or stride)"
                ),
            }),
            blobs: Vec::new(),
            from_loop: 0,
        }
    }

    /// Analyses `frame` at `cfg.threshold_dn`. `listed`: the loop's own blob list for this
    /// frame when it detected (kept/rejected by the loop, gate included); regions it did not
    /// examine are added from the whole-frame pass.
    pub fn of(
        camera: usize,
        set_index: u64,
        frame: &Frame,
        cfg: &TrackerConfig,
        listed: Option<&[BlobView]>,
        list_max: usize,
    ) -> Option<Self> {
        let (background, hist) = Background::of(frame)?;
        let thr = cfg.threshold_dn;
        let above = Background::fraction_above(&hist, thr);
        let det = detect_whole(frame, cfg, thr, list_max)?;
        let mut blobs: Vec<BlobView> = listed.map(<[BlobView]>::to_vec).unwrap_or_default();
        let from_loop = listed.is_some();
        let listed_copy = blobs.clone();
        // A listed blob inside a found blob's box is the same spot (a blob cut by the tracking
        // window has another centroid than the whole spot).
        let is_listed = |b: &Blob| {
            listed_copy.iter().any(|l| {
                l.x_px >= f64::from(b.bbox.x_min_px) - 1.0
                    && l.x_px <= f64::from(b.bbox.x_max_px) + 1.0
                    && l.y_px >= f64::from(b.bbox.y_min_px) - 1.0
                    && l.y_px <= f64::from(b.bbox.y_max_px) + 1.0
            })
        };
        for (b, reason) in det.blobs.iter().filter(|(b, _)| !is_listed(b)) {
            // The loop looked only inside its tracking window (or kept its max_blobs): a
            // usable spot it did not list was not examined.
            let reason = match reason {
                None if from_loop => Some(RejectReason::Window),
                r => *r,
            };
            blobs.push(BlobView::of(b, reason));
        }
        for b in det.by_area.iter().filter(|b| !is_listed(b)) {
            blobs.push(BlobView::of(b, Some(RejectReason::Area)));
        }
        blobs.truncate(list_max);
        let loop_listed = listed.map_or(0, |l| l.len().min(blobs.len()));
        let kept = blobs.iter().filter(|b| b.kept).count() as u32;
        let regions = det.stats.components.max(blobs.len() as u32);
        let rejected = regions.saturating_sub(kept);
        let mut a = CameraAnalysis {
            camera,
            set_index,
            threshold_dn: thr,
            pixels: true,
            background: Some(background),
            above_threshold_pct: 100.0 * above,
            regions,
            kept,
            rejected,
            overloaded: det.stats.overloaded,
            max_labels: cfg.max_labels,
            too_many_spots: det.candidates as usize > cfg.max_blobs,
            max_blobs: cfg.max_blobs,
            expected_leds: None,
            more_spots_than_leds: false,
            advice: None,
            blobs,
            from_loop: loop_listed,
        };
        a.advice = a.advise(above);
        Some(a)
    }

    /// Judges the kept spots against the LEDs the parameter set expects (`Some(n)` with tools:
    /// all tools' LEDs plus the loose LEDs tracked; see [`expected_leds`]): up to `n` kept spots
    /// are the tools' LEDs, more are stray light (`more_spots_than_leds`). The advice is
    /// recomputed.
    pub fn expecting(mut self, expected_leds: Option<usize>) -> Self {
        self.expected_leds = expected_leds;
        self.more_spots_than_leds = expected_leds.is_some_and(|n| self.kept as usize > n);
        if self.advice.as_ref().is_none_or(|a| a.code != "unreadable_frame") {
            self.advice = self.advise(self.above_threshold_pct / 100.0);
        }
        self
    }

    fn advise(&self, above: f64) -> Option<Advice> {
        let i = self.camera;
        let thr = self.threshold_dn;
        // Without pixels there is nothing to judge (the camera board judges its own).
        let bg = self.background.as_ref()?;
        let safe = bg.safe_threshold_dn;
        let advice = |code, message| Some(Advice { code, message });
        if above > BACKGROUND_FRACTION {
            let raise = if safe > thr {
                format!("raise it to about {safe}")
            } else {
                "lower exposure or gain".to_string()
            };
            return if bg.median_dn > thr {
                advice(
                    "background_above_threshold",
                    format!(
                        "camera {i}: background {} DN is above the threshold {thr} DN — {raise}",
                        bg.median_dn
                    ),
                )
            } else {
                advice(
                    "background_above_threshold",
                    format!(
                        "camera {i}: {:.0} % of the frame is above the threshold {thr} DN (background {} DN, its brighter parts up to {} DN) — {raise}",
                        100.0 * above,
                        bg.median_dn,
                        bg.bright_dn
                    ),
                )
            };
        }
        if self.overloaded {
            return advice(
                "overloaded",
                format!(
                    "camera {i} is overloaded: more than {} separate bright regions above the threshold {thr} DN, the detector's limit, so it finds none — raise the threshold (the background needs about {safe}) or shade the light",
                    self.max_labels
                ),
            );
        }
        if self.too_many_spots {
            return advice(
                "too_many_spots",
                format!(
                    "camera {i} is overloaded: it sees {} bright spots, more than the {} the detector keeps per frame — raise the threshold or cover the stray lights",
                    self.regions, self.max_blobs
                ),
            );
        }
        if self.more_spots_than_leds {
            return advice(
                "more_spots_than_leds",
                format!(
                    "camera {i} keeps {} spots, more than the {} LEDs the parameter set expects (its tools' LEDs and the loose LEDs tracked) — raise the threshold or cover the stray lights",
                    self.kept,
                    self.expected_leds.unwrap_or(1)
                ),
            );
        }
        if self.regions == 0 {
            return if bg.peak_dn <= thr {
                advice(
                    "no_led",
                    format!(
                        "camera {i}: no LED found: the threshold {thr} DN is above the brightest pixel {} DN — lower the threshold or raise exposure/gain",
                        bg.peak_dn
                    ),
                )
            } else {
                None
            };
        }
        if self.kept == 0 {
            let why = reasons_summary(&self.blobs);
            let only_area = self.blobs.iter().all(|b| b.reason == Some(RejectReason::Area));
            let next = if only_area {
                "check the blob area limits against the LED's size, or remove the stray light"
            } else {
                "bring the LED into view; the rejected regions are stray light (cover it or leave it: it is ignored)"
            };
            return advice(
                "no_usable_blob",
                format!(
                    "camera {i}: no usable spot: {} bright region(s), all rejected ({why}) — {next}",
                    self.regions
                ),
            );
        }
        None
    }
}

/// One camera's part of a threshold suggestion.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraSuggestion {
    /// Camera index, configuration order.
    pub camera: usize,
    /// Grey-level statistics of the frame.
    pub background: Background,
    /// The brightest usable spot at the background-safe threshold (the marker), if any.
    pub marker_peak_dn: Option<u32>,
    /// Column of that spot's centroid, pixels from the image's left edge.
    pub marker_x_px: Option<f64>,
    /// Row of that spot's centroid, pixels from the image's top edge.
    pub marker_y_px: Option<f64>,
    /// This camera's own best value.
    pub suggested_dn: u32,
    /// Thresholds (inclusive) at which exactly the marker is kept in this frame, if found.
    pub works_from_dn: Option<u32>,
    /// Highest such threshold, DN (see `works_from_dn`).
    pub works_to_dn: Option<u32>,
    /// The reasoning, one step a line.
    pub reasoning: Vec<String>,
}

/// `GET /api/tuning/suggest`: a threshold for all cameras (the detector has one), with each
/// camera's reasoning and the predicted result, shown before anything is applied.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Suggestion {
    /// Index of the frame set the suggestion is computed from.
    pub set_index: u64,
    /// Detection threshold in force, DN.
    pub current_threshold_dn: u32,
    /// The value to apply; `None` when no value can be given (see `reasoning`).
    pub threshold_dn: Option<u32>,
    /// Whether, in this frame set, the value keeps exactly the marker in every camera.
    pub keeps_only_marker: bool,
    /// Each camera's analysis, in camera order.
    pub cameras: Vec<CameraSuggestion>,
    /// Per camera at the suggested value: kept and rejected spots with reasons.
    pub predicted: Vec<String>,
    /// How the value was chosen, one step a line.
    pub reasoning: Vec<String>,
}

/// Whether `det` keeps the marker at `(x, y)` and at most `expected_leds` spots in all (1: exactly
/// the marker; with tools, their LEDs may be kept beside it but nothing more).
fn only_marker(det: &Detection, x: f64, y: f64, expected_leds: usize) -> bool {
    let mut n = 0usize;
    let mut marker = false;
    for b in det.kept() {
        n += 1;
        marker |= (b.x_px - x).hypot(b.y_px - y) < 3.0;
    }
    marker && n <= expected_leds.max(1) && !det.stats.overloaded
}

/// LEDs a camera may see with the loop's parameter set: every tool's LEDs plus the loose single
/// LEDs it tracks now; `None` without tools (a single marker).
pub fn expected_leds(pose: Option<&irtrack_core::pose6d::MultiTracker>) -> Option<usize> {
    let p = pose.filter(|p| p.tool_count() > 0)?;
    let tools: usize = (0..p.tool_count())
        .filter_map(|i| p.tool(i))
        .map(|t| t.led_count())
        .sum();
    Some(tools + p.loose_leds().len())
}

/// A per-camera suggestion from the histogram and the marker's peak.
///
/// `expected_leds`: spots the camera may keep (1 for a single marker; with tools every tool's LED
/// and the loose LEDs, [`expected_leds`]): a threshold "works" when it keeps the marker (the
/// brightest spot) and no more than that many spots.
pub fn suggest_camera(
    camera: usize,
    frame: &Frame,
    cfg: &TrackerConfig,
    expected_leds: usize,
) -> Option<CameraSuggestion> {
    let expected = expected_leds.max(1);
    let alone = if expected == 1 {
        "exactly the marker is kept".to_string()
    } else {
        format!(
            "the marker and at most {expected} spots in all (the LEDs the parameter set expects) are kept"
        )
    };
    let (bg, _) = Background::of(frame)?;
    let safe = bg.safe_threshold_dn;
    let mut reasoning = vec![format!(
        "background: median {} DN, noise ±{:.0} DN, {} % of the pixels at or below {} DN — a threshold of at least {safe} DN keeps the background out",
        bg.median_dn, bg.noise_dn, BRIGHT_BACKGROUND_PERCENTILE, bg.bright_dn
    )];
    let mut out = CameraSuggestion {
        camera,
        background: bg,
        marker_peak_dn: None,
        marker_x_px: None,
        marker_y_px: None,
        suggested_dn: safe,
        works_from_dn: None,
        works_to_dn: None,
        reasoning: Vec::new(),
    };
    if safe + 2 >= bg.max_dn {
        reasoning.push(format!(
            "the background reaches {} DN of {}: no threshold separates the marker — lower exposure or gain first",
            bg.bright_dn, bg.max_dn
        ));
        out.reasoning = reasoning;
        return Some(out);
    }
    let det = detect_whole(frame, cfg, safe, 64)?;
    let marker = det
        .kept()
        .max_by(|a, b| a.peak_dn.cmp(&b.peak_dn).then(a.area_px.cmp(&b.area_px)))
        .copied();
    let Some(m) = marker else {
        reasoning.push(format!(
            "no round spot of a usable size above {safe} DN (the LED out of view, or too dim): this value only keeps the background out"
        ));
        out.reasoning = reasoning;
        return Some(out);
    };
    out.marker_peak_dn = Some(m.peak_dn);
    out.marker_x_px = Some(m.x_px);
    out.marker_y_px = Some(m.y_px);
    reasoning.push(format!(
        "marker: the brightest round spot above {safe} DN, at ({:.0}, {:.0}) px, peak {} DN",
        m.x_px, m.y_px, m.peak_dn
    ));
    let target = safe + (m.peak_dn.saturating_sub(safe)) / 2;
    reasoning.push(format!(
        "halfway between the background's {safe} DN and the marker's {} DN: {target} DN (room for the marker dimming at the edge of the volume and for a brighter background)",
        m.peak_dn
    ));
    // Check thresholds from the background-safe value to the marker's peak on this frame.
    let span = m.peak_dn.saturating_sub(safe).max(1);
    let step = span.div_ceil(TRIAL_STEPS).max(1);
    // (threshold, spots kept) of the values that work.
    let mut trials: Vec<(u32, usize)> = Vec::new();
    let mut t = safe;
    while t < m.peak_dn {
        if let Some(d) = detect_whole(frame, cfg, t, 64).filter(|d| only_marker(d, m.x_px, m.y_px, expected))
        {
            trials.push((t, d.kept().count()));
        }
        t += step;
    }
    // With several LEDs expected, a higher value that drops some of them also "works": keep
    // only the values that keep the most spots (all the tools' LEDs when nothing else is as
    // bright), so the choice never trades LEDs away.
    let most = trials.iter().map(|&(_, n)| n).max().unwrap_or(0);
    let works: Vec<u32> = trials
        .iter()
        .filter(|&&(_, n)| n == most)
        .map(|&(t, _)| t)
        .collect();
    out.works_from_dn = works.first().copied();
    out.works_to_dn = works.last().copied();
    out.suggested_dn = works
        .iter()
        .copied()
        .min_by_key(|v| v.abs_diff(target))
        .unwrap_or(target);
    match (out.works_from_dn, out.works_to_dn) {
        (Some(lo), Some(hi)) => reasoning.push(format!(
            "checked on this frame: from {lo} to {hi} DN {alone}; {} DN is chosen",
            out.suggested_dn
        )),
        _ => reasoning.push(format!(
            "checked on this frame: no threshold between {safe} and {} DN keeps the marker with at most {expected} spot(s) — other spots look like it (cover them) or the marker is cut by the edge",
            m.peak_dn
        )),
    }
    out.reasoning = reasoning;
    Some(out)
}

/// A threshold for every camera of `frames` (they share one): each camera's suggestion, then
/// the value nearest their middle that keeps exactly the marker in all of them.
pub fn suggest(set_index: u64, frames: &[Frame], cfg: &TrackerConfig) -> Suggestion {
    suggest_expecting(set_index, frames, cfg, 1)
}

/// [`suggest`] for a parameter set whose cameras may keep up to `expected_leds` spots (every
/// tool's LEDs and the loose LEDs, [`expected_leds`]): a value works in a camera when it keeps
/// the marker (the brightest spot) and no more than `expected_leds` spots; more is stray light.
pub fn suggest_expecting(
    set_index: u64,
    frames: &[Frame],
    cfg: &TrackerConfig,
    expected_leds: usize,
) -> Suggestion {
    let expected = expected_leds.max(1);
    let cameras: Vec<CameraSuggestion> = frames
        .iter()
        .enumerate()
        .filter_map(|(i, f)| suggest_camera(i, f, cfg, expected))
        .collect();
    let mut reasoning = Vec::new();
    let with_marker: Vec<&CameraSuggestion> = cameras.iter().filter(|c| c.marker_peak_dn.is_some()).collect();
    let lo = cameras.iter().map(|c| c.background.safe_threshold_dn).max();
    let threshold = if with_marker.is_empty() {
        reasoning.push(
            "no camera sees the marker: the value only keeps the background out; suggest again with the LED in view"
                .to_string(),
        );
        lo
    } else {
        // The range every camera accepts, if any.
        let from = with_marker.iter().filter_map(|c| c.works_from_dn).max();
        let to = with_marker.iter().filter_map(|c| c.works_to_dn).min();
        let all_have_range = with_marker.iter().all(|c| c.works_from_dn.is_some());
        let mid = (with_marker.iter().map(|c| u64::from(c.suggested_dn)).sum::<u64>()
            / with_marker.len() as u64) as u32;
        match (from, to) {
            (Some(f), Some(t)) if all_have_range && f <= t => {
                let v = mid.clamp(f, t).max(lo.unwrap_or(0));
                reasoning.push(format!(
                    "one threshold serves all cameras: each keeps {} from {f} to {t} DN; {v} DN is nearest their own suggestions",
                    if expected == 1 { "exactly the marker".to_string() } else { format!("the marker and at most the {expected} LEDs expected") }
                ));
                Some(v)
            }
            _ => {
                let v = with_marker.iter().map(|c| c.suggested_dn).max().unwrap_or(mid);
                reasoning.push(format!(
                    "the cameras' ranges do not overlap: {v} DN (the highest camera suggestion) keeps the background out everywhere; check the cameras whose prediction shows other spots"
                ));
                Some(v)
            }
        }
    };
    let mut predicted = Vec::new();
    let mut keeps_only_marker = threshold.is_some() && !with_marker.is_empty();
    if let Some(v) = threshold {
        for (i, f) in frames.iter().enumerate() {
            let Some(det) = detect_whole(f, cfg, v, 64) else {
                continue;
            };
            let views: Vec<BlobView> = det
                .blobs
                .iter()
                .map(|(b, r)| BlobView::of(b, *r))
                .chain(
                    det.by_area
                        .iter()
                        .map(|b| BlobView::of(b, Some(RejectReason::Area))),
                )
                .collect();
            let kept = det.kept().count();
            let rejected = views.len() - kept;
            let marker = cameras
                .iter()
                .find(|c| c.camera == i)
                .and_then(|c| c.marker_x_px.zip(c.marker_y_px));
            let only = marker.is_some_and(|(x, y)| only_marker(&det, x, y, expected));
            keeps_only_marker &= only;
            let why = reasons_summary(&views);
            let what = match (only, expected) {
                (true, 1) => " (the marker)".to_string(),
                (true, n) => format!(" (at most the {n} LEDs expected)"),
                (false, n) if n > 1 && kept > n => format!(" (more than the {n} LEDs expected: stray light)"),
                _ => String::new(),
            };
            predicted.push(format!(
                "camera {i} at {v} DN: {kept} kept{what}, {rejected} rejected{}",
                if why.is_empty() {
                    String::new()
                } else {
                    format!(" ({why})")
                }
            ));
        }
    }
    Suggestion {
        set_index,
        current_threshold_dn: cfg.threshold_dn,
        threshold_dn: threshold,
        keeps_only_marker,
        cameras,
        predicted,
        reasoning,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(w: u32, h: u32, px: Vec<u8>) -> Frame {
        Frame {
            width_px: w,
            height_px: h,
            stride_px: w,
            bit_depth: 8,
            timestamp_ns: 0,
            sequence: 0,
            pixels: Pixels::U8(px),
        }
    }

    /// A flat background of `bg` with one LED-like spot (peak 250) at (60, 40).
    fn scene(bg: u8) -> Frame {
        let (w, h) = (120u32, 90u32);
        let mut px = vec![bg; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                let d2 = (f64::from(x) - 60.0).powi(2) + (f64::from(y) - 40.0).powi(2);
                let v = f64::from(bg) + 230.0 * (-d2 / (2.0 * 1.5 * 1.5)).exp();
                px[(y * w + x) as usize] = v.min(255.0) as u8;
            }
        }
        frame(w, h, px)
    }

    #[test]
    fn background_above_threshold_is_said_with_the_level_and_a_value() {
        let cfg = TrackerConfig::default(); // threshold 30
        let a = CameraAnalysis::of(0, 1, &scene(41), &cfg, None, 32).unwrap();
        let adv = a.advice.unwrap();
        assert_eq!(adv.code, "background_above_threshold");
        assert!(
            adv.message
                .starts_with("camera 0: background 41 DN is above the threshold 30 DN — raise it to about"),
            "{}",
            adv.message
        );
        let bg = a.background.as_ref().unwrap();
        assert!(bg.safe_threshold_dn > 41 && bg.safe_threshold_dn < 60);
        assert!(!adv.message.contains("area"), "{}", adv.message);
    }

    #[test]
    fn suggestion_keeps_exactly_the_marker() {
        let cfg = TrackerConfig::default();
        let f = scene(41);
        let s = suggest(7, std::slice::from_ref(&f), &cfg);
        let v = s.threshold_dn.unwrap();
        assert!(s.keeps_only_marker, "{s:#?}");
        assert!(v > 45 && v < 250, "{v}");
        let mut at = cfg;
        at.threshold_dn = v;
        let a = CameraAnalysis::of(0, 7, &f, &at, None, 32).unwrap();
        assert_eq!((a.kept, a.advice.clone()), (1, None), "{a:#?}");
        assert!(s.cameras[0].reasoning.len() >= 3, "{:?}", s.cameras[0].reasoning);
    }

    /// A dark frame with an LED-like spot (peak `peak`) at each of `spots`.
    fn spots(spots: &[(f64, f64, f64)]) -> Frame {
        let (w, h) = (320u32, 240u32);
        let mut px = vec![12u8; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                let mut v = 12.0;
                for &(cx, cy, peak) in spots {
                    let d2 = (f64::from(x) - cx).powi(2) + (f64::from(y) - cy).powi(2);
                    v += (peak - 12.0) * (-d2 / (2.0 * 1.5 * 1.5)).exp();
                }
                px[(y * w + x) as usize] = v.min(255.0) as u8;
            }
        }
        frame(w, h, px)
    }

    #[test]
    fn with_three_tools_their_leds_are_expected_and_only_more_spots_are_advised() {
        // The simulator's three tools (probe4, tri3, wing4: 4 + 3 + 4 LEDs) in the loop's
        // 6-DOF tracker: 11 LEDs expected per camera.
        let (sim_cfg, tools) = irtrack_sim::multibody::scene(irtrack_sim::rig::RigPreset::Convergent {
            distance_mm: 1000.0,
            angle_deg: 90.0,
        })
        .unwrap();
        let rig = irtrack_sim::Scenario::new(sim_cfg).unwrap().rig().clone();
        let tracker = irtrack_core::pose6d::MultiTracker::new(
            &rig,
            &tools,
            irtrack_core::pose6d::PoseConfig::default(),
        )
        .unwrap();
        let expected = expected_leds(Some(&tracker));
        assert_eq!(expected, Some(11));
        assert_eq!(expected_leds(None), None);
        // The loop's limits in 6-DOF mode (the engine raises max_blobs to all LEDs + 8).
        let cfg = TrackerConfig {
            threshold_dn: 100,
            max_blobs: tracker.config().max_blobs_per_camera,
            ..TrackerConfig::default()
        };
        // 11 LED images, the brightest first.
        let mut leds: Vec<(f64, f64, f64)> = (0..11)
            .map(|i| {
                (
                    30.0 + 25.0 * f64::from(i),
                    60.0 + 10.0 * f64::from(i % 3),
                    240.0 - 3.0 * f64::from(i),
                )
            })
            .collect();
        let a = CameraAnalysis::of(0, 1, &spots(&leds), &cfg, None, 32)
            .unwrap()
            .expecting(expected);
        assert_eq!(a.kept, 11, "{a:#?}");
        assert!(!a.more_spots_than_leds && !a.too_many_spots, "{a:#?}");
        assert_eq!(a.advice, None, "11 spots for 11 expected LEDs: no advice");
        // Without the tools (one marker expected) the same frame is judged by the page, not here.
        let single = CameraAnalysis::of(0, 1, &spots(&leds), &cfg, None, 32).unwrap();
        assert_eq!(single.expected_leds, None);
        // Two stray lights beside the tools' LEDs: 13 spots, more than the 11 expected.
        leds.push((60.0, 180.0, 200.0));
        leds.push((250.0, 200.0, 190.0));
        let a = CameraAnalysis::of(0, 1, &spots(&leds), &cfg, None, 32)
            .unwrap()
            .expecting(expected);
        assert_eq!(a.kept, 13);
        let adv = a
            .advice
            .clone()
            .expect("advice for 13 spots where 11 LEDs are expected");
        assert_eq!(adv.code, "more_spots_than_leds");
        assert!(
            adv.message
                .starts_with("camera 0 keeps 13 spots, more than the 11 LEDs the parameter set expects"),
            "{}",
            adv.message
        );

        // The suggestion counts the same LEDs: 11 spots are the tools', so a threshold keeping
        // all 11 works; expecting one marker, none does.
        leds.truncate(11);
        let f = spots(&leds);
        let s = suggest_expecting(1, std::slice::from_ref(&f), &cfg, 11);
        assert!(s.keeps_only_marker, "{s:#?}");
        let v = s.threshold_dn.unwrap();
        assert!(
            s.predicted[0].contains("11 kept (at most the 11 LEDs expected)"),
            "{:?}",
            s.predicted
        );
        let mut at = cfg;
        at.threshold_dn = v;
        let a = CameraAnalysis::of(0, 1, &f, &at, None, 32)
            .unwrap()
            .expecting(expected);
        assert_eq!((a.kept, a.advice.clone()), (11, None), "at {v} DN: {a:#?}");
        let one = suggest(1, std::slice::from_ref(&f), &cfg);
        assert!(
            !one.keeps_only_marker,
            "one marker expected, 11 spots seen: {one:#?}"
        );
        // Two dimmer stray lights beside the 11 LEDs: at the current threshold 13 spots (advised
        // above); the suggestion finds a value above the strays that keeps exactly the 11.
        leds.push((60.0, 180.0, 170.0));
        leds.push((250.0, 200.0, 160.0));
        let f = spots(&leds);
        let s = suggest_expecting(1, std::slice::from_ref(&f), &cfg, 11);
        assert!(s.keeps_only_marker, "{s:#?}");
        let v = s.threshold_dn.unwrap();
        at.threshold_dn = v;
        let a = CameraAnalysis::of(0, 1, &f, &at, None, 32)
            .unwrap()
            .expecting(expected);
        println!("11 LEDs + 2 stray lights: suggested {v} DN; {:?}", s.predicted);
        assert_eq!((a.kept, a.advice.clone()), (11, None), "at {v} DN: {a:#?}");
        assert!(v > cfg.threshold_dn, "{v}");
    }

    #[test]
    fn no_led_keeps_its_words() {
        let cfg = TrackerConfig {
            threshold_dn: 254,
            ..TrackerConfig::default()
        };
        let a = CameraAnalysis::of(1, 1, &scene(10), &cfg, None, 32).unwrap();
        let m = a.advice.unwrap().message;
        assert!(
            m.contains("threshold 254 DN is above the brightest pixel 240 DN"),
            "{m}"
        );
    }

    #[test]
    fn too_many_regions_is_said_as_overloaded() {
        // Single bright pixels every 5 px (4 % of the frame, not a bright background): far
        // more regions than 64 labels.
        let (w, h) = (64u32, 64u32);
        let px: Vec<u8> = (0..w * h)
            .map(|i| {
                if (i % w) % 5 == 2 && (i / w) % 5 == 2 {
                    200
                } else {
                    10
                }
            })
            .collect();
        let cfg = TrackerConfig {
            max_labels: 64,
            min_area_px: 1,
            ..TrackerConfig::default()
        };
        let a = CameraAnalysis::of(0, 1, &frame(w, h, px), &cfg, None, 32).unwrap();
        assert!(a.overloaded);
        let m = a.advice.unwrap();
        assert_eq!(m.code, "overloaded", "{m:?}");
        assert!(
            m.message
                .starts_with("camera 0 is overloaded: more than 64 separate bright regions"),
            "{}",
            m.message
        );
    }
}
