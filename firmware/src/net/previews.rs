//! The newest encoded previews, shared by the set-up view's viewers (see `live`).

use std::time::{Duration, Instant};

use axum::body::Bytes;

/// A viewer reuses previews another viewer encoded this recently (with the same size and zoom)
/// instead of encoding its own: N viewers cost about one encode per preview period, not N.
/// Shorter than the fastest preview period, so nobody gets a stale picture twice.
pub(super) const PREVIEW_SHARE_WINDOW: Duration = Duration::from_millis(30);

/// Start of the preview slots (see `live_session`).
pub(super) static PREVIEW_EPOCH: std::sync::OnceLock<Instant> = std::sync::OnceLock::new();

/// Previews and zooms of one set, encoded once for every viewer with these settings.
pub(super) struct SharedPreviews {
    pub(super) key: (u32, u32),
    pub(super) encoded_at: Instant,
    pub(super) previews: Vec<(serde_json::Value, Bytes)>,
    pub(super) zooms: Vec<(serde_json::Value, Bytes)>,
}

/// The cache viewers share, and how often it saved an encode (reported under `viewers`).
#[derive(Default)]
pub struct PreviewShare {
    pub(super) cache: std::sync::Mutex<Option<SharedPreviews>>,
    /// Preview sets encoded.
    pub encoded: std::sync::atomic::AtomicU64,
    /// Preview sets a viewer took from another viewer's encode.
    pub shared: std::sync::atomic::AtomicU64,
}
