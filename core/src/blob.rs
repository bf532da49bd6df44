//! Bright-blob detection with integer moments and sub-pixel centroids.
//!
//! One pass over the frame (or a region of interest) does everything:
//! - **Threshold + runs.** Each row is split into runs of pixels strictly above
//!   `threshold_dn`. A maximum (a branch-free reduction the compiler turns into SIMD max
//!   instructions) rejects dark rows, i.e. almost all of them, at memory speed: first for
//!   groups of 8 rows at once (one fold per group, which matters for narrow tracking
//!   windows, where per-row overhead outweighs the pixels), then per row inside a bright
//!   group. In the few rows with bright pixels, dark 32- and 8-pixel chunks are skipped too.
//! - **Fused moments.** While a run is walked, the weight `w = value − threshold` and its
//!   first and second x moments are summed in integers (`Σw`, `Σw·x`, `Σw·x²`); the run's
//!   y moments follow from the row index once per run. No floating point per pixel.
//! - **Row-run labelling.** A run is connected to the runs of the previous row it touches.
//!   A small union-find over run labels (not pixels) merges components, e.g. the two arms
//!   of a U that meet further down. Each run's moments go to its label; labels are folded
//!   into their roots after the last row.
//!
//! Connectivity is **8-connected**: runs touching only diagonally belong to the same blob.
//! A small, defocused LED spot can have a thin diagonal neck after thresholding; splitting
//! it would produce two biased half-centroids instead of one good one.
//!
//! Weighting by `value − threshold` (rather than by value above a background level) makes
//! a pixel's weight go continuously to zero as it crosses the threshold, so noise that
//! flips edge pixels in or out barely moves the centroid; for a symmetric spot the
//! weighted centroid stays unbiased, including when its core is saturated.
//!
//! All buffers are allocated by [`BlobDetector::new`]; [`BlobDetector::detect`] never
//! allocates.

use alloc::vec::Vec;

use crate::image::{GrayImage, Pixel, Roi};
use crate::simd;
use crate::{Error, Result};

/// Largest frame side the detector accepts. Keeps every moment sum well inside its
/// integer type (Σw·x² < 2^80 < u128, products in the covariance < 2^120).
pub const MAX_SIDE_PX: u32 = 16384;

/// Pixels per background-skip chunk (32 bytes of u8: one AVX2 or two NEON registers).
const SKIP_CHUNK_PX: usize = 32;

/// Sub-chunk that narrows down a bright chunk before the per-pixel walk.
const SUB_CHUNK_PX: usize = 8;

/// Rows whose maximum is taken together to skip dark rows (see [`BlobDetector::detect`]).
const ROW_GROUP: u32 = 8;

/// Which code scans 8-bit tracking windows (16..=64 pixels wide). Both give bit-identical
/// results (`blob::tests` compares them on random frames); the choice exists so that both
/// stay tested and can be compared in the benchmark.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Kernel {
    /// Generic code for every pixel type (what LLVM auto-vectorises).
    Portable,
    /// The explicit [`crate::simd`] kernels (SSE2 on x86_64, NEON on aarch64) where the
    /// build has them, else the portable code.
    #[default]
    Simd,
}

/// Detection settings (may change from frame to frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlobConfig {
    /// A pixel belongs to a blob when its value is strictly greater than this (DN of the
    /// frame's own scale: 0–255 for 8-bit, 0–1023 for 10-bit data in u16, ...). Set it
    /// as low as the background noise allows (≈ background + 8–10 σ): the centroid's
    /// systematic error grows with the fraction of the spot cut off (for a σ = 1 px spot
    /// peaking at 190 DN: ≤ 0.016 px at 30 DN, 0.04 px at 40 DN, 0.05 px at 60 DN).
    pub threshold_dn: u32,
    /// Pixels at or above this are counted as saturated; `None` = the pixel type's maximum.
    pub saturation_dn: Option<u32>,
    /// Blobs with fewer pixels are dropped (noise, hot pixels).
    pub min_area_px: u32,
    /// Blobs with more pixels are dropped (lamps, reflections from large surfaces).
    pub max_area_px: u32,
}

impl Default for BlobConfig {
    fn default() -> Self {
        BlobConfig {
            threshold_dn: 30,
            saturation_dn: None,
            min_area_px: 3,
            max_area_px: 20_000,
        }
    }
}

/// Buffer sizes fixed at construction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlobLimits {
    /// Widest blob (px) the detector keeps buffers for.
    pub max_width_px: u32,
    /// Tallest blob (px) the detector keeps buffers for.
    pub max_height_px: u32,
    /// Connected-component labels per frame (≈ number of runs that start a new component).
    /// A frame needing more is reported as overloaded, not as a partial result.
    pub max_labels: usize,
    /// Blobs kept per frame (the heaviest, by intensity sum); the rest are counted.
    pub max_blobs: usize,
}

impl BlobLimits {
    /// Limits for frames up to `width_px` × `height_px` with default label/blob counts.
    pub fn for_frame(width_px: u32, height_px: u32) -> Self {
        BlobLimits {
            max_width_px: width_px,
            max_height_px: height_px,
            max_labels: 4096,
            max_blobs: 16,
        }
    }
}

/// Raw intensity-weighted moments in ROI-local pixel coordinates
/// (`m_pq = Σ w · x^p · y^q`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Moments {
    /// Σ w (total weight).
    pub m00: u64,
    /// Σ w·x.
    pub m10: u64,
    /// Σ w·y.
    pub m01: u64,
    /// Σ w·x².
    pub m20: u128,
    /// Σ w·x·y.
    pub m11: u128,
    /// Σ w·y².
    pub m02: u128,
}

impl Moments {
    fn add(&mut self, o: &Moments) {
        self.m00 += o.m00;
        self.m10 += o.m10;
        self.m01 += o.m01;
        self.m20 += o.m20;
        self.m11 += o.m11;
        self.m02 += o.m02;
    }

    /// Weighted covariance (xx, xy, yy) in px², computed from exact integer numerators
    /// (`m00·m20 − m10²` etc.) so there is no cancellation for blobs far from the origin.
    pub fn covariance_px2(&self) -> (f64, f64, f64) {
        if self.m00 == 0 {
            return (0.0, 0.0, 0.0);
        }
        let n = self.m00 as u128;
        let (m10, m01) = (self.m10 as u128, self.m01 as u128);
        let d = (n as f64) * (n as f64);
        // Cauchy–Schwarz makes both diagonal numerators ≥ 0; saturate against rounding-free
        // but defensive underflow.
        let xx = u128_to_f64((n * self.m20).saturating_sub(m10 * m10)) / d;
        let yy = u128_to_f64((n * self.m02).saturating_sub(m01 * m01)) / d;
        let xy = i128_to_f64((n * self.m11) as i128 - (m10 * m01) as i128) / d;
        (xx, xy, yy)
    }
}

/// `v as f64`, through the (hardware) 64-bit conversion when `v` fits: the 128-bit one is
/// a software routine, and small spots' numerators nearly always fit. Same rounding.
#[inline]
fn u128_to_f64(v: u128) -> f64 {
    match u64::try_from(v) {
        Ok(v) => v as f64,
        Err(_) => v as f64,
    }
}

/// As [`u128_to_f64`] for signed values.
#[inline]
fn i128_to_f64(v: i128) -> f64 {
    match i64::try_from(v) {
        Ok(v) => v as f64,
        Err(_) => v as f64,
    }
}

/// Axis-aligned bounding box, inclusive, frame coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BBox {
    /// Leftmost column (inclusive).
    pub x_min_px: u32,
    /// Top row (inclusive).
    pub y_min_px: u32,
    /// Rightmost column (inclusive).
    pub x_max_px: u32,
    /// Bottom row (inclusive).
    pub y_max_px: u32,
}

/// One detected blob.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Blob {
    /// Intensity-weighted centroid, frame coordinates (pixel centres at integers).
    pub x_px: f64,
    /// Row of the centroid (see `x_px`).
    pub y_px: f64,
    /// Pixels above threshold.
    pub area_px: u32,
    /// Σ (value − threshold) over the blob.
    pub weight_sum: u64,
    /// Brightest pixel value.
    pub peak_dn: u32,
    /// Pixels at or above the saturation level.
    pub saturated_px: u32,
    /// Bounding box of the blob's pixels.
    pub bbox: BBox,
    /// Standard deviations along the principal axes of the weighted distribution.
    pub sigma_major_px: f64,
    /// Standard deviation along the minor principal axis.
    pub sigma_minor_px: f64,
    /// `sigma_minor / sigma_major` in [0, 1]: 1 for a round spot, → 0 for a streak.
    pub roundness: f64,
    /// The blob reaches the frame border: it may be cut off and its centroid biased.
    pub touches_frame_edge: bool,
    /// The blob reaches the edge of the region of interest (inside the frame): it may
    /// continue outside the region.
    pub touches_roi_edge: bool,
    /// Raw moments (ROI-local coordinates; `roi` gives the origin).
    pub moments: Moments,
}

/// What happened in the last call to [`BlobDetector::detect`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DetectStats {
    /// Region that was scanned.
    pub roi: Roi,
    /// Runs above threshold.
    pub runs: u32,
    /// Connected components found (before area filtering).
    pub components: u32,
    /// Components dropped by the area limits.
    pub rejected_area: u32,
    /// Components that passed the area limits but did not fit in `max_blobs`.
    pub dropped_blobs: u32,
    /// Label buffer exhausted: the frame has too many separate bright regions (sunlight,
    /// wrong threshold). No blobs are reported for such a frame.
    pub overloaded: bool,
    /// The region was scanned by the explicit SIMD kernels ([`Kernel::Simd`]; 8-bit windows
    /// 16..=64 pixels wide), not the portable code.
    pub simd_kernel: bool,
}

#[derive(Debug, Clone, Copy)]
struct Run {
    x0: u32,
    /// Exclusive end.
    x1: u32,
    label: u32,
}

#[derive(Debug, Clone, Copy, Default)]
struct Acc {
    m: Moments,
    area: u32,
    peak: u32,
    sat: u32,
    bbox: BBox,
}

/// Blob detector owning every buffer it needs.
#[derive(Debug, Clone)]
pub struct BlobDetector {
    limits: BlobLimits,
    prev_runs: Vec<Run>,
    cur_runs: Vec<Run>,
    parent: Vec<u32>,
    acc: Vec<Acc>,
    blobs: Vec<Blob>,
    /// The first components dropped by the area limits (up to `max_blobs`), for diagnostics
    /// (the set-up view shows why a spot was not used). Capacity fixed at construction.
    rejected_area: Vec<Blob>,
    stats: DetectStats,
    kernel: Kernel,
}

impl BlobDetector {
    /// Allocates all buffers for frames up to the given limits.
    pub fn new(limits: BlobLimits) -> Result<Self> {
        if limits.max_width_px == 0
            || limits.max_height_px == 0
            || limits.max_width_px > MAX_SIDE_PX
            || limits.max_height_px > MAX_SIDE_PX
        {
            return Err(Error::InvalidParams {
                reason: alloc::format!(
                    "blob detector frame limit {}x{} outside 1..={MAX_SIDE_PX}",
                    limits.max_width_px,
                    limits.max_height_px
                ),
            });
        }
        if limits.max_labels == 0 || limits.max_labels > u32::MAX as usize || limits.max_blobs == 0 {
            return Err(Error::InvalidParams {
                reason: alloc::format!(
                    "blob detector needs max_labels in 1..=2^32-1 and max_blobs ≥ 1 (got {} and {})",
                    limits.max_labels,
                    limits.max_blobs
                ),
            });
        }
        // A row of width w holds at most ceil(w/2) runs (runs are separated by ≥ 1 pixel).
        let max_runs_per_row = (limits.max_width_px as usize).div_ceil(2);
        Ok(BlobDetector {
            limits,
            prev_runs: Vec::with_capacity(max_runs_per_row),
            cur_runs: Vec::with_capacity(max_runs_per_row),
            parent: Vec::with_capacity(limits.max_labels),
            acc: Vec::with_capacity(limits.max_labels),
            blobs: Vec::with_capacity(limits.max_blobs),
            rejected_area: Vec::with_capacity(limits.max_blobs),
            stats: DetectStats::default(),
            kernel: Kernel::default(),
        })
    }

    /// Selects the code for 8-bit tracking windows (default [`Kernel::Simd`]).
    pub fn set_kernel(&mut self, kernel: Kernel) {
        self.kernel = kernel;
    }

    /// The kernel selected (see [`BlobDetector::set_kernel`]).
    pub fn kernel(&self) -> Kernel {
        self.kernel
    }

    /// The limits this detector was built with.
    pub fn limits(&self) -> BlobLimits {
        self.limits
    }

    /// Blobs of the last detection, heaviest (largest weight sum) first.
    pub fn blobs(&self) -> &[Blob] {
        &self.blobs
    }

    /// Components of the last detection dropped by the area limits (at most `max_blobs`
    /// of them, in scan order; [`DetectStats::rejected_area`] counts all).
    pub fn rejected_by_area(&self) -> &[Blob] {
        &self.rejected_area
    }

    /// Statistics of the last detection.
    pub fn stats(&self) -> DetectStats {
        self.stats
    }

    /// Detects blobs in `image`, restricted to `roi` if given. Returns the blobs, heaviest
    /// first. Errors on a malformed image, a region outside the frame, or a frame larger
    /// than the limits; an overloaded frame is not an error (see [`DetectStats`]).
    pub fn detect<P: Pixel>(
        &mut self,
        image: &GrayImage<'_, P>,
        roi: Option<Roi>,
        config: &BlobConfig,
    ) -> Result<&[Blob]> {
        image.validate()?;
        if image.width_px > self.limits.max_width_px || image.height_px > self.limits.max_height_px {
            return Err(Error::BadFrame {
                what: "frame larger than the blob detector's limits",
            });
        }
        let roi = roi.unwrap_or(image.full_roi());
        roi.check(image.width_px, image.height_px)?;
        self.blobs.clear();
        self.rejected_area.clear();
        self.parent.clear();
        self.acc.clear();
        self.prev_runs.clear();
        self.stats = DetectStats {
            roi,
            ..DetectStats::default()
        };

        // Nothing of type P can exceed a threshold at or above full scale.
        if config.threshold_dn >= P::MAX_DN {
            return Ok(&self.blobs);
        }
        let thr = P::from_dn_saturating(config.threshold_dn);
        let sat_level = config.saturation_dn.unwrap_or(P::MAX_DN);

        // 8-bit tracking windows: the explicit SIMD kernels.
        if self.kernel == Kernel::Simd
            && simd::AVAILABLE
            && (simd::MIN_W..=simd::MAX_W).contains(&(roi.width_px as usize))
            && let Some(data) = P::as_u8(image.data)
        {
            // `threshold_dn < P::MAX_DN` = 255 was checked above.
            let thr_u8 = config.threshold_dn as u8;
            self.stats.simd_kernel = true;
            if !self.scan_window_u8(data, image.stride_px as usize, roi, thr_u8, sat_level) {
                self.stats.overloaded = true;
                self.acc.clear();
                return Ok(&self.blobs);
            }
            self.finish(image, roi, config);
            return Ok(&self.blobs);
        }

        let mut ly = 0;
        while ly < roi.height_px {
            let group_end = (ly + ROW_GROUP).min(roi.height_px);
            // A group of dark rows is rejected by one lane-wise max over all of its pixels
            // and a single horizontal fold, instead of a fold plus the per-row set-up for
            // every row. For a narrow tracking window (49-pixel rows) that per-row overhead,
            // not the pixels, was most of the cost.
            if roi.width_px as usize >= SKIP_CHUNK_PX && group_max(image, roi, ly, group_end) <= thr {
                // Rows without runs: nothing below connects to them.
                self.prev_runs.clear();
                ly = group_end;
                continue;
            }
            for y in ly..group_end {
                let row = image.row(roi.y_px + y);
                let x_end = (roi.x_px + roi.width_px) as usize;
                let row = row.get(roi.x_px as usize..x_end).unwrap_or(&[]);
                // Most rows hold no marker at all: one vectorised max over the row decides
                // that at memory speed, and the run search only runs on the few rows that do.
                if row_max(row) <= thr {
                    self.prev_runs.clear();
                    continue;
                }
                if !self.label_row(row, y, thr, config.threshold_dn, sat_level) {
                    self.stats.overloaded = true;
                    self.acc.clear();
                    return Ok(&self.blobs);
                }
                core::mem::swap(&mut self.prev_runs, &mut self.cur_runs);
            }
            ly = group_end;
        }
        self.finish(image, roi, config);
        Ok(&self.blobs)
    }

    /// The SIMD scan of an 8-bit window 16..=64 pixels wide: dark groups of 8 rows rejected
    /// by one vector maximum, then each row of a bright group turned into a bit mask of its
    /// pixels above threshold, whose runs are found with `trailing_zeros` (no chunk tests,
    /// no pixel walk). Runs go to the same `add_run` as the portable path. Returns false when
    /// the label buffer is exhausted.
    fn scan_window_u8(&mut self, data: &[u8], stride: usize, roi: Roi, thr: u8, sat_level: u32) -> bool {
        // One copy of the scan per block count, so each row's loads are unrolled.
        match simd::left_blocks(roi.width_px as usize) {
            0 => self.scan_window_k::<0>(data, stride, roi, thr, sat_level),
            1 => self.scan_window_k::<1>(data, stride, roi, thr, sat_level),
            2 => self.scan_window_k::<2>(data, stride, roi, thr, sat_level),
            _ => self.scan_window_k::<3>(data, stride, roi, thr, sat_level),
        }
    }

    fn scan_window_k<const K: usize>(
        &mut self,
        data: &[u8],
        stride: usize,
        roi: Roi,
        thr: u8,
        sat_level: u32,
    ) -> bool {
        let (x0, w) = (roi.x_px as usize, roi.width_px as usize);
        let t = simd::Threshold::new(thr);
        let mut ly = 0;
        while ly < roi.height_px {
            let group_end = (ly + ROW_GROUP).min(roi.height_px);
            let start = (roi.y_px + ly) as usize * stride + x0;
            let rows = (group_end - ly) as usize;
            // `None` (not reached for a checked frame and region) = treat as bright.
            if simd::group_has_bright::<K>(data, start, stride, rows, w, t) == Some(false) {
                self.prev_runs.clear();
                ly = group_end;
                continue;
            }
            for y in ly..group_end {
                let s = (roi.y_px + y) as usize * stride + x0;
                let row = data.get(s..s + w).unwrap_or(&[]);
                let mask = match simd::bright_mask::<K>(row, t) {
                    Some(m) => m,
                    // Not reached for a checked region (w in range, row inside the frame);
                    // if it were, the scalar definition gives the same mask.
                    None => row
                        .iter()
                        .take(64)
                        .enumerate()
                        .fold(0u64, |m, (i, &v)| m | (((v > thr) as u64) << i)),
                };
                if mask == 0 {
                    self.prev_runs.clear();
                    continue;
                }
                if !self.label_mask(row, mask, y, thr as u32, sat_level) {
                    return false;
                }
                core::mem::swap(&mut self.prev_runs, &mut self.cur_runs);
            }
            ly = group_end;
        }
        true
    }

    /// The runs of a row given as a bit mask of its bright pixels (bit i = `row[i]`).
    #[inline]
    fn label_mask(&mut self, row: &[u8], mut mask: u64, ly: u32, thr_dn: u32, sat_level: u32) -> bool {
        self.cur_runs.clear();
        let mut j = 0usize;
        while mask != 0 {
            let x0 = mask.trailing_zeros() as usize;
            // Ones from x0 upwards: the run's length (the shift brings in zeros above bit 63).
            let len = (!(mask >> x0)).trailing_zeros() as usize;
            let x1 = x0 + len;
            if !self.add_run(row, x0, x1, ly, &mut j, thr_dn, sat_level) {
                return false;
            }
            mask = if x1 >= 64 { 0 } else { mask & (u64::MAX << x1) };
        }
        true
    }

    /// Finds the runs of one row that has bright pixels, accumulates their moments and
    /// connects them to the previous row's runs. Returns false when the label buffer is
    /// exhausted.
    #[inline]
    fn label_row<P: Pixel>(&mut self, row: &[P], ly: u32, thr: P, thr_dn: u32, sat_level: u32) -> bool {
        self.cur_runs.clear();
        // Rows with bright pixels: skip dark 32-pixel chunks, narrow a bright chunk down by
        // 8-pixel sub-chunks (also skips dark tails shorter than 32), then walk to the first
        // bright pixel and hand each run to `add_run`. The chunk tests are "any pixel above
        // threshold" reductions (vector compare + OR, cheaper than a max and its fold); the
        // walk is per pixel, so it is kept to at most 8 pixels per run.
        let w = row.len();
        let mut x = 0usize;
        let mut j = 0usize; // first previous-row run that may touch the next run
        loop {
            while let Some(chunk) = row.get(x..).and_then(|r| r.first_chunk::<SKIP_CHUNK_PX>()) {
                if chunk.iter().fold(false, |a, &v| a | (v > thr)) {
                    break;
                }
                x += SKIP_CHUNK_PX;
            }
            while let Some(sub) = row
                .get(x..x + SUB_CHUNK_PX)
                .and_then(|c| <&[P; SUB_CHUNK_PX]>::try_from(c).ok())
            {
                if sub.iter().fold(false, |a, &v| a | (v > thr)) {
                    break;
                }
                x += SUB_CHUNK_PX;
            }
            let lim = (x + SUB_CHUNK_PX).min(w);
            while x < lim && row[x] <= thr {
                x += 1;
            }
            if x >= w {
                return true;
            }
            if x == lim {
                continue;
            }
            let x0 = x;
            while x < w && row[x] > thr {
                x += 1;
            }
            if !self.add_run(row, x0, x, ly, &mut j, thr_dn, sat_level) {
                return false;
            }
        }
    }

    /// Accumulates the moments of the run `row[x0..x1]` (all above threshold) and connects
    /// it to the previous row's runs (8-connectivity). `j` is the first previous-row run
    /// that can still touch this or a later run. Returns false when out of labels.
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn add_run<P: Pixel>(
        &mut self,
        row: &[P],
        x0: usize,
        x1: usize,
        ly: u32,
        j: &mut usize,
        thr_dn: u32,
        sat_level: u32,
    ) -> bool {
        // Weighted sums over the run: integers only.
        let (mut s0, mut sx, mut sxx) = (0u64, 0u64, 0u64);
        let (mut peak, mut sat) = (0u32, 0u32);
        for (x, &p) in (x0..x1).zip(&row[x0..x1]) {
            let v = p.dn();
            let wgt = v.saturating_sub(thr_dn) as u64;
            let xu = x as u64;
            s0 += wgt;
            sx += wgt * xu;
            sxx += wgt * xu * xu;
            peak = peak.max(v);
            sat += (v >= sat_level) as u32;
        }
        let (x0, x1) = (x0 as u32, x1 as u32);

        // Previous-row runs touching [x0-1, x1] share the component.
        while *j < self.prev_runs.len() && self.prev_runs[*j].x1 < x0 {
            *j += 1;
        }
        let mut label = u32::MAX;
        let mut k = *j;
        while k < self.prev_runs.len() && self.prev_runs[k].x0 <= x1 {
            let r = find(&mut self.parent, self.prev_runs[k].label);
            if label == u32::MAX {
                label = r;
            } else if r != label {
                // Keep the older (smaller) label as root; any choice is correct.
                let (lo, hi) = if r < label { (r, label) } else { (label, r) };
                self.parent[hi as usize] = lo;
                label = lo;
            }
            k += 1;
        }
        if label == u32::MAX {
            if self.acc.len() >= self.limits.max_labels {
                return false;
            }
            label = self.acc.len() as u32;
            self.parent.push(label);
            self.acc.push(Acc {
                bbox: BBox {
                    x_min_px: x0,
                    y_min_px: ly,
                    x_max_px: x1 - 1,
                    y_max_px: ly,
                },
                ..Acc::default()
            });
        }
        let a = &mut self.acc[label as usize];
        let y = ly as u64;
        a.m.add(&Moments {
            m00: s0,
            m10: sx,
            m01: s0 * y,
            m20: sxx as u128,
            m11: sx as u128 * y as u128,
            m02: s0 as u128 * (y * y) as u128,
        });
        a.area += x1 - x0;
        a.peak = a.peak.max(peak);
        a.sat += sat;
        a.bbox.x_min_px = a.bbox.x_min_px.min(x0);
        a.bbox.x_max_px = a.bbox.x_max_px.max(x1 - 1);
        a.bbox.y_max_px = ly;
        self.stats.runs += 1;
        // Capacity is ceil(w/2), the most runs a row can hold, so this never reallocates.
        self.cur_runs.push(Run { x0, x1, label });
        true
    }

    /// Folds labels into their roots and turns components into blobs.
    fn finish<P>(&mut self, image: &GrayImage<'_, P>, roi: Roi, config: &BlobConfig) {
        for i in 0..self.acc.len() {
            let r = find(&mut self.parent, i as u32) as usize;
            if r != i {
                let a = self.acc[i];
                let root = &mut self.acc[r];
                root.m.add(&a.m);
                root.area += a.area;
                root.peak = root.peak.max(a.peak);
                root.sat += a.sat;
                root.bbox.x_min_px = root.bbox.x_min_px.min(a.bbox.x_min_px);
                root.bbox.x_max_px = root.bbox.x_max_px.max(a.bbox.x_max_px);
                root.bbox.y_min_px = root.bbox.y_min_px.min(a.bbox.y_min_px);
                root.bbox.y_max_px = root.bbox.y_max_px.max(a.bbox.y_max_px);
            }
        }
        for i in 0..self.acc.len() {
            if self.parent[i] as usize != i {
                continue;
            }
            self.stats.components += 1;
            let a = self.acc[i];
            if a.area < config.min_area_px || a.area > config.max_area_px || a.m.m00 == 0 {
                self.stats.rejected_area += 1;
                // Within the fixed capacity only: never allocates.
                if a.m.m00 != 0 && self.rejected_area.len() < self.rejected_area.capacity() {
                    self.rejected_area
                        .push(make_blob(&a, roi, image.width_px, image.height_px));
                }
                continue;
            }
            let blob = make_blob(&a, roi, image.width_px, image.height_px);
            self.keep(blob);
        }
    }

    /// Inserts into the heaviest-first list, dropping the lightest when full.
    fn keep(&mut self, blob: Blob) {
        let pos = self.blobs.partition_point(|b| b.weight_sum >= blob.weight_sum);
        if self.blobs.len() == self.limits.max_blobs {
            self.stats.dropped_blobs += 1;
            if pos == self.blobs.len() {
                return;
            }
            self.blobs.pop();
        }
        self.blobs.insert(pos, blob);
    }
}

/// Maximum of a row. Lane-wise maxima over 32-pixel blocks, then a halving tree over the
/// lanes: compiles to one load and one `pmaxub`/`umax` per vector with no per-pixel branch.
/// The last block is taken flush with the row end (overlapping is harmless for a maximum),
/// so rows of 32 pixels or more have no scalar tail.
#[inline]
fn row_max<P: Pixel>(row: &[P]) -> P {
    const N: usize = SKIP_CHUNK_PX;
    if row.len() < N {
        return row.iter().fold(P::default(), |m, &v| m.max(v));
    }
    // Tracking-window rows (32..=64 pixels): exactly two, possibly overlapping, blocks.
    if row.len() <= 2 * N
        && let (Some(a), Some(b)) = (row.first_chunk::<N>(), row.last_chunk::<N>())
    {
        return fold_lanes(merge_max(*a, b));
    }
    let mut lanes = [P::default(); N];
    let mut chunks = row.chunks_exact(N);
    for c in &mut chunks {
        for (l, &v) in lanes.iter_mut().zip(c) {
            *l = (*l).max(v);
        }
    }
    if !chunks.remainder().is_empty() {
        for (l, &v) in lanes.iter_mut().zip(&row[row.len() - N..]) {
            *l = (*l).max(v);
        }
    }
    // Constant bounds so each step unrolls into a few vector max instructions.
    fold_half::<P, 16>(&mut lanes);
    fold_half::<P, 8>(&mut lanes);
    fold_half::<P, 4>(&mut lanes);
    fold_half::<P, 2>(&mut lanes);
    fold_half::<P, 1>(&mut lanes);
    lanes[0]
}

/// Maximum over rows `ly0..ly1` of `roi` (at least 32 pixels wide): lane-wise maxima of
/// every 32-pixel block of every row (the last block of a row flush with its end), then one
/// fold. The group's rows are cut from one slice (one bounds check per row) and windows up
/// to 64 pixels wide, the usual tracking window, take exactly two blocks per row.
#[inline(never)]
fn group_max<P: Pixel>(image: &GrayImage<'_, P>, roi: Roi, ly0: u32, ly1: u32) -> P {
    const N: usize = SKIP_CHUNK_PX;
    let bright = P::from_dn_saturating(P::MAX_DN);
    let (stride, w) = (image.stride_px as usize, roi.width_px as usize);
    let rows = ly1.saturating_sub(ly0) as usize;
    let start = (roi.y_px + ly0) as usize * stride + roi.x_px as usize;
    // Within the frame checked by `GrayImage::validate` and `Roi::check`; if not, report
    // "bright" so the rows go through the checked per-row path.
    let Some(region) = rows
        .checked_sub(1)
        .and_then(|r| image.data.get(start..start + r * stride + w))
    else {
        return bright;
    };
    let mut lanes = [P::default(); N];
    if w <= 2 * N {
        for row in region.chunks(stride) {
            let (Some(a), Some(b)) = (
                row.first_chunk::<N>(),
                row.get(..w).and_then(|r| r.last_chunk::<N>()),
            ) else {
                return bright;
            };
            lanes = merge_max(lanes, a);
            lanes = merge_max(lanes, b);
        }
    } else {
        for row in region.chunks(stride) {
            let row = row.get(..w).unwrap_or(&[]);
            let (blocks, tail) = row.as_chunks::<N>();
            for b in blocks {
                lanes = merge_max(lanes, b);
            }
            if !tail.is_empty()
                && let Some(b) = row.last_chunk::<N>()
            {
                lanes = merge_max(lanes, b);
            }
        }
    }
    fold_lanes(lanes)
}

/// Lane-wise maximum of two 32-pixel blocks (constant length: unrolled into vector maxima).
#[inline(always)]
fn merge_max<P: Pixel>(mut lanes: [P; SKIP_CHUNK_PX], block: &[P; SKIP_CHUNK_PX]) -> [P; SKIP_CHUNK_PX] {
    for i in 0..SKIP_CHUNK_PX {
        lanes[i] = lanes[i].max(block[i]);
    }
    lanes
}

/// Maximum over the lanes: a halving tree with constant bounds, so each step unrolls into a
/// few vector max instructions.
#[inline(always)]
fn fold_lanes<P: Pixel>(mut lanes: [P; SKIP_CHUNK_PX]) -> P {
    fold_half::<P, 16>(&mut lanes);
    fold_half::<P, 8>(&mut lanes);
    fold_half::<P, 4>(&mut lanes);
    fold_half::<P, 2>(&mut lanes);
    fold_half::<P, 1>(&mut lanes);
    lanes[0]
}

/// `lanes[i] = max(lanes[i], lanes[i + H])` for i < H.
#[inline(always)]
fn fold_half<P: Pixel, const H: usize>(lanes: &mut [P; SKIP_CHUNK_PX]) {
    let (lo, hi) = lanes.split_at_mut(H);
    for (a, &b) in lo.iter_mut().zip(&hi[..H]) {
        *a = (*a).max(b);
    }
}

/// Root of `i` with path halving.
#[inline]
fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let gp = parent[parent[i as usize] as usize];
        parent[i as usize] = gp;
        i = gp;
    }
    i
}

fn make_blob(a: &Acc, roi: Roi, frame_w: u32, frame_h: u32) -> Blob {
    let m = &a.m;
    let n = m.m00 as f64;
    let (xx, xy, yy) = m.covariance_px2();
    // Eigenvalues of the 2x2 covariance.
    let mean = 0.5 * (xx + yy);
    let dev = libm::sqrt(0.25 * (xx - yy) * (xx - yy) + xy * xy);
    let l_major = (mean + dev).max(0.0);
    let l_minor = (mean - dev).max(0.0);
    let roundness = if l_major > 0.0 {
        libm::sqrt(l_minor / l_major)
    } else {
        1.0
    };
    let bbox = BBox {
        x_min_px: a.bbox.x_min_px + roi.x_px,
        x_max_px: a.bbox.x_max_px + roi.x_px,
        y_min_px: a.bbox.y_min_px + roi.y_px,
        y_max_px: a.bbox.y_max_px + roi.y_px,
    };
    let touches_frame_edge = bbox.x_min_px == 0
        || bbox.y_min_px == 0
        || bbox.x_max_px + 1 == frame_w
        || bbox.y_max_px + 1 == frame_h;
    let touches_roi_edge = (bbox.x_min_px == roi.x_px && roi.x_px > 0)
        || (bbox.y_min_px == roi.y_px && roi.y_px > 0)
        || (bbox.x_max_px + 1 == roi.x_px + roi.width_px && roi.x_px + roi.width_px < frame_w)
        || (bbox.y_max_px + 1 == roi.y_px + roi.height_px && roi.y_px + roi.height_px < frame_h);
    Blob {
        x_px: roi.x_px as f64 + m.m10 as f64 / n,
        y_px: roi.y_px as f64 + m.m01 as f64 / n,
        area_px: a.area,
        weight_sum: m.m00,
        peak_dn: a.peak,
        saturated_px: a.sat,
        bbox,
        sigma_major_px: libm::sqrt(l_major),
        sigma_minor_px: libm::sqrt(l_minor),
        roundness,
        touches_frame_edge,
        touches_roi_edge,
        moments: *m,
    }
}

/// Test frame rendering shared by the blob and pipeline tests.
#[cfg(test)]
pub(crate) mod render {
    /// Deterministic generator (SplitMix64) so tests need no extra dependencies.
    pub struct Rng(pub u64);

    impl Rng {
        pub fn next_u64(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^ (z >> 31)
        }
        /// Uniform in [0, 1).
        pub fn uniform(&mut self) -> f64 {
            (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
        }
        /// Standard normal (Box–Muller).
        pub fn normal(&mut self) -> f64 {
            let u1 = self.uniform().max(1e-300);
            let u2 = self.uniform();
            libm::sqrt(-2.0 * libm::log(u1)) * libm::cos(2.0 * core::f64::consts::PI * u2)
        }
    }

    /// A Gaussian spot, integrated over each pixel's area.
    #[derive(Clone, Copy, Debug)]
    pub struct Spot {
        pub x_px: f64,
        pub y_px: f64,
        pub sigma_x_px: f64,
        pub sigma_y_px: f64,
        /// Peak of the continuous profile above background (DN).
        pub peak_dn: f64,
    }

    fn cdf(x: f64) -> f64 {
        0.5 * (1.0 + libm::erf(x * core::f64::consts::FRAC_1_SQRT_2))
    }

    impl Spot {
        pub fn round(x_px: f64, y_px: f64, sigma_px: f64, peak_dn: f64) -> Self {
            Spot {
                x_px,
                y_px,
                sigma_x_px: sigma_px,
                sigma_y_px: sigma_px,
                peak_dn,
            }
        }
        /// Mean signal (DN above background) of pixel (x, y).
        pub fn pixel(&self, x: u32, y: u32) -> f64 {
            let (sx, sy) = (self.sigma_x_px, self.sigma_y_px);
            let fx = cdf((x as f64 + 0.5 - self.x_px) / sx) - cdf((x as f64 - 0.5 - self.x_px) / sx);
            let fy = cdf((y as f64 + 0.5 - self.y_px) / sy) - cdf((y as f64 - 0.5 - self.y_px) / sy);
            // Flux normalised so that the continuous peak is `peak_dn`.
            self.peak_dn * 2.0 * core::f64::consts::PI * sx * sy * fx * fy
        }
    }

    /// Renders spots on a background with read noise and shot noise, clipped to `max_dn`.
    /// Camera model: IR-filtered, dark background `bg_dn ± read_sd_dn`, shot noise with
    /// variance `gain · signal`.
    #[allow(clippy::too_many_arguments)]
    pub fn render(
        w: u32,
        h: u32,
        spots: &[Spot],
        bg_dn: f64,
        read_sd_dn: f64,
        gain: f64,
        max_dn: u32,
        rng: &mut Rng,
    ) -> alloc::vec::Vec<u32> {
        let mut out = alloc::vec![0u32; (w * h) as usize];
        for y in 0..h {
            for x in 0..w {
                let s: f64 = spots
                    .iter()
                    .filter(|sp| {
                        libm::fabs(x as f64 - sp.x_px) < 8.0 * sp.sigma_x_px + 2.0
                            && libm::fabs(y as f64 - sp.y_px) < 8.0 * sp.sigma_y_px + 2.0
                    })
                    .map(|sp| sp.pixel(x, y))
                    .sum();
                let sd = libm::sqrt(read_sd_dn * read_sd_dn + gain * s);
                let v = bg_dn + s + sd * rng.normal();
                out[(y * w + x) as usize] = libm::round(v).clamp(0.0, max_dn as f64) as u32;
            }
        }
        out
    }

    pub fn to_u8(v: &[u32]) -> alloc::vec::Vec<u8> {
        v.iter().map(|&p| p.min(255) as u8).collect()
    }

    pub fn to_u16(v: &[u32]) -> alloc::vec::Vec<u16> {
        v.iter().map(|&p| p.min(65535) as u16).collect()
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::render::*;
    use super::*;
    use std::println;
    use std::vec;
    use std::vec::Vec;

    const W: u32 = 160;
    const H: u32 = 120;

    fn detector() -> BlobDetector {
        BlobDetector::new(BlobLimits::for_frame(W, H)).unwrap()
    }

    fn cfg(threshold_dn: u32) -> BlobConfig {
        BlobConfig {
            threshold_dn,
            saturation_dn: None,
            min_area_px: 1,
            max_area_px: 100_000,
        }
    }

    /// The IR camera of the brief: background 10 ± 2 DN, LED peak ≈ 200 DN, shot noise.
    fn ir_frame(spots: &[Spot], rng: &mut Rng) -> Vec<u8> {
        to_u8(&render(W, H, spots, 10.0, 2.0, 0.05, 255, rng))
    }

    /// Centroid error over many random sub-pixel positions and spot sizes: (rms, max) px.
    fn centroid_errors(
        seed: u64,
        read_sd_dn: f64,
        gain: f64,
        sigmas: &[f64],
        per_sigma: usize,
    ) -> (f64, f64) {
        let mut rng = Rng(seed);
        let mut det = detector();
        let (mut sum2, mut max_err, mut n) = (0.0f64, 0.0f64, 0usize);
        for &sigma in sigmas {
            for _ in 0..per_sigma {
                let x = 40.0 + 80.0 * rng.uniform();
                let y = 30.0 + 60.0 * rng.uniform();
                let raw = render(
                    W,
                    H,
                    &[Spot::round(x, y, sigma, 190.0)],
                    10.0,
                    read_sd_dn,
                    gain,
                    255,
                    &mut rng,
                );
                let img = to_u8(&raw);
                let g = GrayImage::new(&img, W, H, W).unwrap();
                let blobs = det.detect(&g, None, &cfg(30)).unwrap();
                assert_eq!(blobs.len(), 1, "sigma {sigma} at ({x}, {y})");
                let e = libm::hypot(blobs[0].x_px - x, blobs[0].y_px - y);
                sum2 += e * e;
                max_err = max_err.max(e);
                n += 1;
            }
        }
        (libm::sqrt(sum2 / n as f64), max_err)
    }

    /// Systematic error (pixel sampling, truncation at the threshold, 8-bit quantisation)
    /// with the noise switched off.
    #[test]
    fn centroid_bias_without_noise_is_tiny() {
        let (rms, max) = centroid_errors(12, 0.0, 0.0, &[1.0, 1.5, 2.0, 3.0], 50);
        println!("noise-free centroid error: rms {rms:.4} px, max {max:.4} px");
        assert!(max <= 0.02, "bias {max} px");
    }

    /// The brief's IR camera: background 10 ± 2 DN, LED peak 200 DN, plus shot noise of a
    /// small-pixel sensor (20 e-/DN, i.e. variance 0.05 DN per DN of signal).
    #[test]
    fn centroid_error_below_0_05_px_at_ir_camera_snr() {
        let (rms, max) = centroid_errors(1, 2.0, 0.05, &[1.0, 1.5, 2.0, 3.0], 100);
        println!("8-bit centroid error, 400 spots, sigma 1-3 px: rms {rms:.4} px, max {max:.4} px");
        assert!(max <= 0.05, "max centroid error {max} px");
        // Twice the shot noise (10 e-/DN): the rms stays inside the budget.
        let (rms2, max2) = centroid_errors(13, 2.0, 0.1, &[1.0, 1.5, 2.0, 3.0], 100);
        println!("8-bit centroid error at 10 e-/DN: rms {rms2:.4} px, max {max2:.4} px");
        assert!(rms2 <= 0.05, "rms centroid error {rms2} px");
    }

    #[test]
    fn centroid_error_16_bit_frames() {
        // 12-bit sensor in u16: background 40 ± 8 DN, peak ≈ 3000 DN.
        let mut rng = Rng(2);
        let mut det = detector();
        let mut max_err = 0.0f64;
        for _ in 0..100 {
            let x = 30.0 + 100.0 * rng.uniform();
            let y = 30.0 + 60.0 * rng.uniform();
            let raw = render(
                W,
                H,
                &[Spot::round(x, y, 1.6, 3000.0)],
                40.0,
                8.0,
                0.5,
                4095,
                &mut rng,
            );
            let img = to_u16(&raw);
            let g = GrayImage::new(&img, W, H, W).unwrap();
            let blobs = det.detect(&g, None, &cfg(160)).unwrap();
            assert_eq!(blobs.len(), 1);
            assert!(blobs[0].peak_dn > 2000 && blobs[0].peak_dn <= 4095);
            max_err = max_err.max(libm::hypot(blobs[0].x_px - x, blobs[0].y_px - y));
        }
        println!("16-bit centroid max error {max_err:.4} px");
        assert!(max_err <= 0.05, "max centroid error {max_err} px");
    }

    #[test]
    fn saturated_symmetric_spot_keeps_its_centroid() {
        let mut rng = Rng(3);
        let mut det = detector();
        let mut max_err = 0.0f64;
        for _ in 0..50 {
            let x = 40.0 + 80.0 * rng.uniform();
            let y = 30.0 + 60.0 * rng.uniform();
            // Ten times over full scale: a flat-topped disc of clipped pixels.
            let img = ir_frame(&[Spot::round(x, y, 2.0, 2000.0)], &mut rng);
            let g = GrayImage::new(&img, W, H, W).unwrap();
            let blobs = det.detect(&g, None, &cfg(40)).unwrap();
            assert_eq!(blobs.len(), 1);
            assert!(blobs[0].saturated_px >= 9, "saturated {}", blobs[0].saturated_px);
            assert_eq!(blobs[0].peak_dn, 255);
            max_err = max_err.max(libm::hypot(blobs[0].x_px - x, blobs[0].y_px - y));
        }
        println!("saturated-spot centroid max error {max_err:.4} px");
        assert!(max_err <= 0.05, "max centroid error {max_err} px");
        // A custom saturation level counts more pixels.
        let img = ir_frame(&[Spot::round(80.0, 60.0, 2.0, 190.0)], &mut rng);
        let g = GrayImage::new(&img, W, H, W).unwrap();
        let c = BlobConfig {
            saturation_dn: Some(150),
            ..cfg(40)
        };
        let b = det.detect(&g, None, &c).unwrap()[0];
        assert!(b.saturated_px >= 1 && b.saturated_px < b.area_px);
    }

    #[test]
    fn empty_and_noise_only_frames_have_no_blobs() {
        let mut det = detector();
        let zeros = vec![0u8; (W * H) as usize];
        let g = GrayImage::new(&zeros, W, H, W).unwrap();
        assert!(det.detect(&g, None, &cfg(40)).unwrap().is_empty());
        assert_eq!(det.stats().runs, 0);
        let noise = ir_frame(&[], &mut Rng(4));
        let g = GrayImage::new(&noise, W, H, W).unwrap();
        assert!(det.detect(&g, None, &cfg(40)).unwrap().is_empty());
        // Threshold at full scale: nothing can exceed it.
        let full = vec![255u8; (W * H) as usize];
        let g = GrayImage::new(&full, W, H, W).unwrap();
        assert!(det.detect(&g, None, &cfg(255)).unwrap().is_empty());
        // A threshold just below full scale: the whole frame is one blob touching the edge.
        let b = det.detect(&g, None, &cfg(254)).unwrap();
        assert_eq!(b.len(), 1);
        assert_eq!(b[0].area_px, W * H);
        assert!(b[0].touches_frame_edge);
        assert!((b[0].x_px - (W - 1) as f64 / 2.0).abs() < 1e-12);
    }

    #[test]
    fn blobs_touching_the_border_are_found_and_flagged() {
        let mut rng = Rng(5);
        let mut det = detector();
        for (x, y) in [
            (0.3, 60.0),
            (159.2, 60.0),
            (80.0, 0.0),
            (80.0, 119.4),
            (0.0, 0.0),
            (159.0, 119.0),
        ] {
            let img = ir_frame(&[Spot::round(x, y, 1.5, 190.0)], &mut rng);
            let g = GrayImage::new(&img, W, H, W).unwrap();
            let blobs = det.detect(&g, None, &cfg(40)).unwrap();
            assert_eq!(blobs.len(), 1, "at ({x}, {y})");
            assert!(blobs[0].touches_frame_edge);
            assert!(!blobs[0].touches_roi_edge);
            assert!(blobs[0].x_px >= 0.0 && blobs[0].x_px <= 159.0);
            assert!(libm::hypot(blobs[0].x_px - x, blobs[0].y_px - y) < 2.0);
        }
        let img = ir_frame(&[Spot::round(80.0, 60.0, 1.5, 190.0)], &mut rng);
        let g = GrayImage::new(&img, W, H, W).unwrap();
        assert!(!det.detect(&g, None, &cfg(40)).unwrap()[0].touches_frame_edge);
    }

    #[test]
    fn several_blobs_heaviest_first_and_capped() {
        let mut rng = Rng(6);
        let spots = [
            Spot::round(20.0, 20.0, 1.5, 60.0),
            Spot::round(60.3, 30.7, 1.5, 190.0),
            Spot::round(100.0, 90.0, 2.5, 120.0),
            Spot::round(140.5, 20.5, 1.0, 150.0),
            Spot::round(30.0, 100.0, 2.0, 200.0),
        ];
        let img = ir_frame(&spots, &mut rng);
        let g = GrayImage::new(&img, W, H, W).unwrap();
        let mut det = detector();
        let blobs = det.detect(&g, None, &cfg(30)).unwrap().to_vec();
        assert_eq!(blobs.len(), 5);
        assert!(blobs.windows(2).all(|p| p[0].weight_sum >= p[1].weight_sum));
        for s in &spots {
            let found = blobs
                .iter()
                .filter(|b| libm::hypot(b.x_px - s.x_px, b.y_px - s.y_px) < 0.1)
                .count();
            assert_eq!(found, 1, "spot {s:?}");
        }
        let mut small = BlobDetector::new(BlobLimits {
            max_blobs: 3,
            ..BlobLimits::for_frame(W, H)
        })
        .unwrap();
        let kept = small.detect(&g, None, &cfg(30)).unwrap().to_vec();
        assert_eq!(kept.len(), 3);
        assert_eq!(small.stats().dropped_blobs, 2);
        assert_eq!(small.stats().components, 5);
        for (k, b) in kept.iter().zip(&blobs) {
            assert_eq!(k, b);
        }
        // Area limits.
        let c = BlobConfig {
            min_area_px: 12,
            max_area_px: 30,
            ..cfg(30)
        };
        let n = det.detect(&g, None, &c).unwrap().len();
        assert!(n < 5);
        assert_eq!(det.stats().rejected_area as usize, 5 - n);
        assert!(det.blobs().iter().all(|b| (12..=30).contains(&b.area_px)));
        // The dropped components are listed with their real areas (outside the limits).
        assert_eq!(det.rejected_by_area().len(), 5 - n);
        assert!(
            det.rejected_by_area()
                .iter()
                .all(|b| !(12..=30).contains(&b.area_px))
        );
    }

    #[test]
    fn roi_restricts_search_and_reports_frame_coordinates() {
        let mut rng = Rng(7);
        let spots = [
            Spot::round(50.4, 40.6, 1.5, 190.0),
            Spot::round(120.0, 90.0, 1.5, 190.0),
        ];
        let img = ir_frame(&spots, &mut rng);
        let g = GrayImage::new(&img, W, H, W).unwrap();
        let mut det = detector();
        let full = det.detect(&g, None, &cfg(40)).unwrap().to_vec();
        assert_eq!(full.len(), 2);
        let roi = Roi::around(50.0, 41.0, 10, W, H);
        let b = det.detect(&g, Some(roi), &cfg(40)).unwrap().to_vec();
        assert_eq!(b.len(), 1);
        let same = full.iter().find(|f| (f.x_px - 50.4).abs() < 0.2).unwrap();
        // Identical pixels give identical centroids, whatever the ROI origin.
        assert!((b[0].x_px - same.x_px).abs() < 1e-9 && (b[0].y_px - same.y_px).abs() < 1e-9);
        assert_eq!(b[0].bbox, same.bbox);
        assert!(!b[0].touches_roi_edge);
        // A window cutting through the spot flags it.
        let cut = Roi {
            x_px: 51,
            y_px: 30,
            width_px: 20,
            height_px: 20,
        };
        let b = det.detect(&g, Some(cut), &cfg(40)).unwrap();
        assert_eq!(b.len(), 1);
        assert!(b[0].touches_roi_edge && !b[0].touches_frame_edge);
        assert_eq!(b[0].bbox.x_min_px, 51);
        let bad = Roi {
            x_px: 150,
            y_px: 0,
            width_px: 20,
            height_px: 10,
        };
        assert!(matches!(
            det.detect(&g, Some(bad), &cfg(40)),
            Err(Error::BadRoi { .. })
        ));
    }

    /// Builds a binary test frame from ASCII art ('#' = 200 DN, '.' = 0).
    fn art(rows: &[&str]) -> (Vec<u8>, u32, u32) {
        let w = rows[0].len() as u32;
        let data = rows
            .iter()
            .flat_map(|r| r.bytes().map(|c| if c == b'#' { 200u8 } else { 0 }))
            .collect();
        (data, w, rows.len() as u32)
    }

    fn count_blobs(rows: &[&str]) -> Vec<u32> {
        let (data, w, h) = art(rows);
        let g = GrayImage::new(&data, w, h, w).unwrap();
        let mut det = BlobDetector::new(BlobLimits::for_frame(w, h)).unwrap();
        let mut areas: Vec<u32> = det
            .detect(&g, None, &cfg(100))
            .unwrap()
            .iter()
            .map(|b| b.area_px)
            .collect();
        areas.sort_unstable();
        areas
    }

    #[test]
    fn u_shapes_and_combs_merge_into_one_blob() {
        let one_blob = |rows: &[&str]| {
            let n = rows
                .iter()
                .map(|r| r.bytes().filter(|&c| c == b'#').count() as u32)
                .sum::<u32>();
            assert_eq!(count_blobs(rows), [n], "{rows:?}");
        };
        one_blob(&[
            "........", ".#....#.", ".#....#.", ".#....#.", ".######.", "........",
        ]);
        // Upside-down U, a W (four arms merging at the bottom) and a spiral.
        one_blob(&[".######.", ".#....#.", ".#....#."]);
        one_blob(&["#.#.#.#", "#.#.#.#", "#######"]);
        one_blob(&["#######", "#.....#", "#.###.#", "#.#.#.#", "#.#...#", "#.#####"]);
        // Arms whose labels meet at different rows, merged again via an older label.
        one_blob(&["#.#..#", "#.#..#", "###..#", "#....#", "######"]);
        // A U next to a separate bar stays two blobs.
        assert_eq!(count_blobs(&["#.#.#", "###.#"]), [2, 5]);
    }

    /// Connectivity is 8-connected: diagonal neighbours join.
    #[test]
    fn diagonal_neighbours_are_connected() {
        assert_eq!(count_blobs(&["#...", ".#..", "..#.", "...#"]), [4]);
        assert_eq!(count_blobs(&["...#", "..#.", ".#..", "#..."]), [4]);
        assert_eq!(count_blobs(&["##..", "##..", "..##", "..##"]), [8]);
        // One pixel apart (no touching corner) stays separate.
        assert_eq!(count_blobs(&["#.#", "...", "#.#"]), [1, 1, 1, 1]);
    }

    /// Row groups (8 rows) of at least 32-pixel-wide frames are skipped when dark: a blob
    /// ending on a group's last row and one starting right after a dark group stay apart,
    /// and a blob crossing a group boundary stays whole.
    #[test]
    fn dark_row_groups_separate_and_boundaries_connect() {
        // Bars in column 5 over the given row spans (start, end exclusive).
        let frame = |bar_rows: &[(usize, usize)]| -> Vec<String> {
            (0..32)
                .map(|y| {
                    let bar = bar_rows.iter().any(|&(a, b)| (a..b).contains(&y));
                    (0..40).map(|x| if bar && x == 5 { '#' } else { '.' }).collect()
                })
                .collect()
        };
        let areas = |rows: Vec<String>| count_blobs(&rows.iter().map(String::as_str).collect::<Vec<_>>());
        assert_eq!(areas(frame(&[(0, 8), (16, 21)])), [5, 8]);
        assert_eq!(areas(frame(&[(3, 8), (16, 24), (24, 30)])), [5, 14]);
        assert_eq!(areas(frame(&[(4, 13)])), [9]);
    }

    /// Reference labelling: per-pixel flood fill with 8-connectivity.
    fn flood_fill_reference(img: &[u8], w: usize, h: usize, thr: u8) -> Vec<(u32, u64, u64, u64)> {
        let mut seen = vec![false; w * h];
        let mut out = Vec::new();
        for start in 0..w * h {
            if seen[start] || img[start] <= thr {
                continue;
            }
            let (mut area, mut m00, mut m10, mut m01) = (0u32, 0u64, 0u64, 0u64);
            let mut stack = vec![start];
            seen[start] = true;
            while let Some(p) = stack.pop() {
                let (x, y) = (p % w, p / w);
                let wgt = (img[p] - thr) as u64;
                area += 1;
                m00 += wgt;
                m10 += wgt * x as u64;
                m01 += wgt * y as u64;
                for dy in -1i64..=1 {
                    for dx in -1i64..=1 {
                        let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                        if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                            continue;
                        }
                        let q = ny as usize * w + nx as usize;
                        if !seen[q] && img[q] > thr {
                            seen[q] = true;
                            stack.push(q);
                        }
                    }
                }
            }
            out.push((area, m00, m10, m01));
        }
        out.sort_unstable();
        out
    }

    #[test]
    fn labelling_matches_flood_fill_on_random_frames() {
        let mut rng = Rng(8);
        let (w, h) = (77usize, 41usize);
        let mut det = BlobDetector::new(BlobLimits {
            max_labels: 4096,
            max_blobs: 4096,
            ..BlobLimits::for_frame(w as u32, h as u32)
        })
        .unwrap();
        for round in 0..200 {
            let density = 0.05 + 0.6 * rng.uniform();
            let img: Vec<u8> = (0..w * h)
                .map(|_| {
                    if rng.uniform() < density {
                        50 + (rng.next_u64() % 200) as u8
                    } else {
                        10
                    }
                })
                .collect();
            let reference = flood_fill_reference(&img, w, h, 40);
            let g = GrayImage::new(&img, w as u32, h as u32, w as u32).unwrap();
            let mut ours: Vec<(u32, u64, u64, u64)> = det
                .detect(&g, None, &cfg(40))
                .unwrap()
                .iter()
                .map(|b| (b.area_px, b.moments.m00, b.moments.m10, b.moments.m01))
                .collect();
            ours.sort_unstable();
            assert_eq!(ours, reference, "round {round}, density {density}");
        }
    }

    /// Sparse frames (mostly dark rows, so whole row groups are skipped) in random windows
    /// of every width class (< 32, 32..=64, > 64 pixels): the same components as a flood
    /// fill of the window, including components spanning several row groups.
    #[test]
    fn sparse_frames_in_random_windows_match_flood_fill() {
        let mut rng = Rng(81);
        let (w, h) = (150usize, 90usize);
        let mut det = BlobDetector::new(BlobLimits {
            max_labels: 4096,
            max_blobs: 4096,
            ..BlobLimits::for_frame(w as u32, h as u32)
        })
        .unwrap();
        let mut skipped_rows = 0u64;
        for round in 0..300 {
            let mut img = vec![10u8; w * h];
            for _ in 0..(rng.next_u64() % 6) {
                // A random blotch: up to 14 rows tall, so it often spans two row groups.
                let (cx, cy) = (rng.next_u64() as usize % w, rng.next_u64() as usize % h);
                let (rx, ry) = (1 + rng.next_u64() as usize % 5, 1 + rng.next_u64() as usize % 7);
                for y in cy.saturating_sub(ry)..(cy + ry + 1).min(h) {
                    for x in cx.saturating_sub(rx)..(cx + rx + 1).min(w) {
                        if rng.uniform() < 0.8 {
                            img[y * w + x] = 50 + (rng.next_u64() % 200) as u8;
                        }
                    }
                }
            }
            let rw = [
                1 + rng.next_u64() % 31,
                32 + rng.next_u64() % 33,
                65 + rng.next_u64() % 86,
            ][round % 3];
            let rh = 1 + rng.next_u64() % h as u64;
            let roi = Roi {
                x_px: (rng.next_u64() % (w as u64 - rw + 1)) as u32,
                y_px: (rng.next_u64() % (h as u64 - rh + 1)) as u32,
                width_px: rw as u32,
                height_px: rh as u32,
            };
            let (rx0, ry0, rw, rh) = (roi.x_px as usize, roi.y_px as usize, rw as usize, rh as usize);
            let crop: Vec<u8> = (ry0..ry0 + rh)
                .flat_map(|y| img[y * w + rx0..y * w + rx0 + rw].iter().copied())
                .collect();
            let reference = flood_fill_reference(&crop, rw, rh, 40);
            skipped_rows += crop.chunks(rw).filter(|r| r.iter().all(|&v| v <= 40)).count() as u64;
            let g = GrayImage::new(&img, w as u32, h as u32, w as u32).unwrap();
            let mut ours: Vec<(u32, u64, u64, u64)> = det
                .detect(&g, Some(roi), &cfg(40))
                .unwrap()
                .iter()
                .map(|b| (b.area_px, b.moments.m00, b.moments.m10, b.moments.m01))
                .collect();
            ours.sort_unstable();
            assert_eq!(ours, reference, "round {round}, window {roi:?}");
        }
        assert!(
            skipped_rows > 5000,
            "frames not sparse enough: {skipped_rows} dark rows"
        );
    }

    #[test]
    fn moments_are_exact_integers() {
        // Weights above threshold 10: 5 at (1,1), 3 at (2,1), 2 at (1,2).
        let (w, h) = (4u32, 4u32);
        let mut img = vec![0u8; 16];
        img[5] = 15;
        img[6] = 13;
        img[9] = 12;
        let g = GrayImage::new(&img, w, h, w).unwrap();
        let mut det = BlobDetector::new(BlobLimits::for_frame(w, h)).unwrap();
        let b = det.detect(&g, None, &cfg(10)).unwrap()[0];
        let m = b.moments;
        assert_eq!((m.m00, m.m10, m.m01), (10, 5 + 6 + 2, 5 + 3 + 4));
        assert_eq!((m.m20, m.m11, m.m02), (5 + 12 + 2, 5 + 6 + 4, 5 + 3 + 8));
        assert!((b.x_px - 1.3).abs() < 1e-12 && (b.y_px - 1.2).abs() < 1e-12);
        assert_eq!(b.area_px, 3);
        assert_eq!(b.peak_dn, 15);
        assert_eq!(
            b.bbox,
            BBox {
                x_min_px: 1,
                y_min_px: 1,
                x_max_px: 2,
                y_max_px: 2
            }
        );
    }

    #[test]
    fn roundness_separates_spots_from_streaks() {
        let mut rng = Rng(9);
        let mut det = detector();
        let round = ir_frame(&[Spot::round(80.0, 60.0, 2.0, 190.0)], &mut rng);
        let g = GrayImage::new(&round, W, H, W).unwrap();
        let b = det.detect(&g, None, &cfg(40)).unwrap()[0];
        assert!(b.roundness > 0.9, "round spot roundness {}", b.roundness);
        let streak = Spot {
            x_px: 80.0,
            y_px: 60.0,
            sigma_x_px: 8.0,
            sigma_y_px: 1.5,
            peak_dn: 190.0,
        };
        let img = ir_frame(&[streak], &mut rng);
        let g = GrayImage::new(&img, W, H, W).unwrap();
        let b = det.detect(&g, None, &cfg(40)).unwrap()[0];
        assert!(b.roundness < 0.35, "streak roundness {}", b.roundness);
        assert!(b.sigma_major_px > 3.0 * b.sigma_minor_px);
    }

    #[test]
    fn padded_stride_gives_identical_results() {
        let mut rng = Rng(10);
        let img = ir_frame(
            &[
                Spot::round(77.7, 33.3, 1.5, 190.0),
                Spot::round(10.0, 100.0, 2.0, 150.0),
            ],
            &mut rng,
        );
        let stride = W + 13;
        let mut padded = vec![255u8; (stride * H) as usize];
        for y in 0..H as usize {
            padded[y * stride as usize..][..W as usize].copy_from_slice(&img[y * W as usize..][..W as usize]);
        }
        let mut det = detector();
        let a = det
            .detect(&GrayImage::new(&img, W, H, W).unwrap(), None, &cfg(40))
            .unwrap()
            .to_vec();
        let b = det
            .detect(&GrayImage::new(&padded, W, H, stride).unwrap(), None, &cfg(40))
            .unwrap()
            .to_vec();
        assert_eq!(a, b);
        assert_eq!(a.len(), 2);
    }

    #[test]
    fn too_many_regions_is_reported_as_overload() {
        // A grid of isolated bright pixels: one label each.
        let img: Vec<u8> = (0..W * H)
            .map(|i| {
                if (i % W).is_multiple_of(2) && (i / W).is_multiple_of(2) {
                    200
                } else {
                    0
                }
            })
            .collect();
        let g = GrayImage::new(&img, W, H, W).unwrap();
        let mut det = BlobDetector::new(BlobLimits {
            max_labels: 100,
            ..BlobLimits::for_frame(W, H)
        })
        .unwrap();
        assert!(det.detect(&g, None, &cfg(40)).unwrap().is_empty());
        assert!(det.stats().overloaded);
        // The same detector recovers on a normal frame.
        let ok = ir_frame(&[Spot::round(80.0, 60.0, 1.5, 190.0)], &mut Rng(11));
        let g = GrayImage::new(&ok, W, H, W).unwrap();
        assert_eq!(det.detect(&g, None, &cfg(40)).unwrap().len(), 1);
        assert!(!det.stats().overloaded);
    }

    #[test]
    fn bad_inputs_are_errors() {
        assert!(BlobDetector::new(BlobLimits::for_frame(0, 10)).is_err());
        assert!(BlobDetector::new(BlobLimits::for_frame(MAX_SIDE_PX + 1, 10)).is_err());
        assert!(
            BlobDetector::new(BlobLimits {
                max_labels: 0,
                ..BlobLimits::for_frame(10, 10)
            })
            .is_err()
        );
        let mut det = BlobDetector::new(BlobLimits::for_frame(10, 10)).unwrap();
        let big = vec![0u8; 400];
        let g = GrayImage::new(&big, 20, 20, 20).unwrap();
        assert!(matches!(
            det.detect(&g, None, &cfg(40)),
            Err(Error::BadFrame { .. })
        ));
        let short = GrayImage {
            data: &big[..50],
            width_px: 10,
            height_px: 10,
            stride_px: 10,
        };
        assert!(matches!(
            det.detect(&short, None, &cfg(40)),
            Err(Error::BufferTooSmall { .. })
        ));
    }
}
