//! One blob as the set-up view shows it, kept or rejected with its reason: what the loop's
//! copies for viewers ([`crate::viewer`]) and the whole-frame analysis ([`crate::advice`]) both
//! list. Its own module so that neither of the two has to import the other for it.

use irtrack_core::blob::Blob;
use serde::Serialize;

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
    /// Column of the intensity-weighted centroid, pixels (pixel centres at integers).
    pub x_px: f64,
    /// Row of the intensity-weighted centroid, pixels (pixel centres at integers).
    pub y_px: f64,
    /// Pixels above the threshold.
    pub area_px: u32,
    /// Brightest pixel of the blob, DN.
    pub peak_dn: u32,
    /// Minor over major spread, 0..=1: 1 for a round spot, towards 0 for a streak.
    pub roundness: f64,
    /// The loop would use this blob (no reason to reject it).
    pub kept: bool,
    /// Why the blob is rejected; `None` when kept.
    pub reason: Option<RejectReason>,
    /// 6-DOF mode: the tool (index in the parameter set) this blob was assigned to.
    pub tool: Option<u8>,
    /// 6-DOF mode: the blob is a loose single LED (belongs to no tool).
    pub loose: bool,
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
            tool: None,
            loose: false,
        }
    }
}
