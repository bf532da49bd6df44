//! Bright-blob detection with integer moments and sub-pixel centroids.
//!
//! One pass over the frame (or a region of interest) does everything:
//! - **Threshold + runs.** Each row is split into runs of pixels strictly above
//!   `threshold_dn`. Background is skipped a chunk at a time: the maximum of a fixed-size
//!   chunk is a branch-free reduction the compiler turns into a few SIMD max instructions,
//!   so dark pixels cost a fraction of a cycle each.
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
use crate::{Error, Result};

/// Largest frame side the detector accepts. Keeps every moment sum well inside its
/// integer type (Σw·x² < 2^80 < u128, products in the covariance < 2^120).
pub const MAX_SIDE_PX: u32 = 16384;

/// Pixels per background-skip chunk (32 bytes of u8: one AVX2 or two NEON registers).
const SKIP_CHUNK_PX: usize = 32;

/// Detection settings (may change from frame to frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlobConfig {
    /// A pixel belongs to a blob when its value is strictly greater than this (DN of the
    /// frame's own scale: 0–255 for 8-bit, 0–1023 for 10-bit data in u16, ...).
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
            threshold_dn: 40,
            saturation_dn: None,
            min_area_px: 3,
            max_area_px: 20_000,
        }
    }
}

/// Buffer sizes fixed at construction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlobLimits {
    pub max_width_px: u32,
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
    pub m00: u64,
    pub m10: u64,
    pub m01: u64,
    pub m20: u128,
    pub m11: u128,
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
        let xx = (n * self.m20).saturating_sub(m10 * m10) as f64 / d;
        let yy = (n * self.m02).saturating_sub(m01 * m01) as f64 / d;
        let xy = ((n * self.m11) as i128 - (m10 * m01) as i128) as f64 / d;
        (xx, xy, yy)
    }
}

/// Axis-aligned bounding box, inclusive, frame coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BBox {
    pub x_min_px: u32,
    pub y_min_px: u32,
    pub x_max_px: u32,
    pub y_max_px: u32,
}

/// One detected blob.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Blob {
    /// Intensity-weighted centroid, frame coordinates (pixel centres at integers).
    pub x_px: f64,
    pub y_px: f64,
    /// Pixels above threshold.
    pub area_px: u32,
    /// Σ (value − threshold) over the blob.
    pub weight_sum: u64,
    /// Brightest pixel value.
    pub peak_dn: u32,
    /// Pixels at or above the saturation level.
    pub saturated_px: u32,
    pub bbox: BBox,
    /// Standard deviations along the principal axes of the weighted distribution.
    pub sigma_major_px: f64,
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
    stats: DetectStats,
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
            stats: DetectStats::default(),
        })
    }

    /// The limits this detector was built with.
    pub fn limits(&self) -> BlobLimits {
        self.limits
    }

    /// Blobs of the last detection, heaviest (largest weight sum) first.
    pub fn blobs(&self) -> &[Blob] {
        &self.blobs
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

        for ly in 0..roi.height_px {
            let row = image.row(roi.y_px + ly);
            let x_end = (roi.x_px + roi.width_px) as usize;
            let row = row.get(roi.x_px as usize..x_end).unwrap_or(&[]);
            if !self.label_row(row, ly, thr, config.threshold_dn, sat_level) {
                self.stats.overloaded = true;
                self.acc.clear();
                return Ok(&self.blobs);
            }
            core::mem::swap(&mut self.prev_runs, &mut self.cur_runs);
        }
        self.finish(image, roi, config);
        Ok(&self.blobs)
    }

    /// Finds the runs of one row, accumulates their moments and connects them to the
    /// previous row's runs. Returns false when the label buffer is exhausted.
    #[inline]
    fn label_row<P: Pixel>(&mut self, row: &[P], ly: u32, thr: P, thr_dn: u32, sat_level: u32) -> bool {
        self.cur_runs.clear();
        let w = row.len();
        let mut x = 0usize;
        let mut j = 0usize; // first previous-row run that may touch the current run
        loop {
            // Skip background a chunk at a time (vectorised max reduction).
            while x + SKIP_CHUNK_PX <= w {
                let chunk = &row[x..x + SKIP_CHUNK_PX];
                if chunk.iter().fold(P::default(), |m, &v| m.max(v)) > thr {
                    break;
                }
                x += SKIP_CHUNK_PX;
            }
            let lim = (x + SKIP_CHUNK_PX).min(w);
            while x < lim && row[x] <= thr {
                x += 1;
            }
            if x >= w {
                break;
            }
            if x == lim {
                continue;
            }
            // A run starts at x: walk it, summing moments (fused with thresholding).
            let x0 = x;
            let (mut s0, mut sx, mut sxx) = (0u64, 0u64, 0u64);
            let (mut peak, mut sat) = (0u32, 0u32);
            while x < w && row[x] > thr {
                let v = row[x].dn();
                let wgt = (v - thr_dn) as u64;
                let xu = x as u64;
                s0 += wgt;
                sx += wgt * xu;
                sxx += wgt * xu * xu;
                peak = peak.max(v);
                sat += (v >= sat_level) as u32;
                x += 1;
            }
            let (x0, x1) = (x0 as u32, x as u32);

            // Connect to previous-row runs touching [x0-1, x1] (8-connectivity).
            while j < self.prev_runs.len() && self.prev_runs[j].x1 < x0 {
                j += 1;
            }
            let mut label = u32::MAX;
            let mut k = j;
            while k < self.prev_runs.len() && self.prev_runs[k].x0 <= x1 {
                let r = find(&mut self.parent, self.prev_runs[k].label);
                if label == u32::MAX {
                    label = r;
                } else if r != label {
                    // Keep the older (smaller) label as root; order does not matter for
                    // correctness, it only keeps trees shallow for top-down merges.
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
        }
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
