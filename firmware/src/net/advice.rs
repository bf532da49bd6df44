//! `POST /api/tuning/suggest` (operator only): a detection threshold computed from a fresh
//! frame set — each camera's histogram and its marker's peak — with the reasoning and the
//! predicted result, for the set-up view to show before the operator applies it (applying is
//! an ordinary `POST /api/tuning`). Nothing changes here. Method: [`crate::advice::suggest`].

use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use axum::response::Response;

use super::http::{ConnInfo, json_text, text};
use super::status::StatusService;

/// How long the suggestion waits for the loop's next set.
const SNAPSHOT_WAIT: Duration = Duration::from_secs(2);

pub(super) async fn suggest(
    State(s): State<Arc<StatusService>>,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    headers: HeaderMap,
) -> Response {
    if let Err(r) = s.auth.authorize(&headers, conn.peer.ip()).await {
        return s.refusal(r);
    }
    let (Some(tap), Some(tuning)) = (s.tap.clone(), s.tuning.clone()) else {
        return text(
            StatusCode::NOT_FOUND,
            "threshold suggestion is not available here\n",
        );
    };
    let result = tokio::task::spawn_blocking(move || {
        let set = tap.snapshot_blocking(SNAPSHOT_WAIT)?;
        // The detector's settings as the operator has them now (the copy may predate a change).
        let cfg = tuning.tracking().unwrap_or(set.tracker_cfg);
        Some(crate::advice::suggest_expecting(
            set.set_index,
            &set.frames,
            &cfg,
            set.expected_leds.unwrap_or(1),
        ))
    })
    .await;
    match result {
        Ok(Some(sug)) => {
            tracing::info!(suggested_dn = ?sug.threshold_dn, keeps_only_marker = sug.keeps_only_marker, "threshold suggested");
            json_text(
                StatusCode::OK,
                serde_json::to_string(&sug).unwrap_or_else(|_| "null".into()) + "\n",
            )
        }
        Ok(None) => text(
            StatusCode::GATEWAY_TIMEOUT,
            "no frame set within 2 s: the cameras are not delivering (see /status)\n",
        ),
        Err(e) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("the suggestion failed: {e}\n"),
        ),
    }
}
