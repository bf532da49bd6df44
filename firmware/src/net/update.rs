//! `POST /api/update`: a signed-in operator uploads a bundle (the request body, raw bytes),
//! which is streamed to the data partition — never held in memory — and then installed on a
//! thread of its own (`crate::update`). The answer comes when the upload is complete: 202 with
//! the job id while the install runs (progress and outcome in `/status` → `system.install`),
//! or the refusal as JSON `{"ok": false, "kind": ..., "reason": ...}`: 409 another install
//! runs, 413 too large, 507 no room, 422 the bundle itself (truncated, wrong signature,
//! downgrade, another board), 400 the upload stopped early.
//!
//! `POST /api/update?reboot=1` reboots the board into the new system once it is installed
//! (the root agent does it on the image; `/status` → `system.reboot` shows it pending). Any
//! other query parameter, or another `reboot` value, is refused with 400 before the upload.
//!
//! An upload takes longer than the listener's usual 30 s exchange: once signed in, the
//! connection's deadline is moved to [`UPLOAD_EXCHANGE_LIMIT`] ([`ExchangeDeadline`]); a body
//! that stalls still fails after the usual idle timeout.

use std::io::Write as _;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::Response;
use futures_util::StreamExt as _;
use tokio::sync::Notify;

use super::http::{ConnInfo, json_line, json_text, text};
use super::status::StatusService;
use crate::update::{Refusal, RefusalKind};

/// The whole exchange of an upload, from the request head to the answer.
pub const UPLOAD_EXCHANGE_LIMIT: Duration = Duration::from_secs(30 * 60);
/// Received bytes are written in pieces of about this size (one blocking write each).
const WRITE_PIECE_BYTES: usize = 1 << 20;

/// The deadline of one connection's HTTP exchange, which a handler may move (a request
/// extension set by the accept loop).
#[derive(Clone, Debug)]
pub struct ExchangeDeadline(Arc<(Mutex<tokio::time::Instant>, Notify)>);

impl ExchangeDeadline {
    /// Ends `limit` from now.
    pub fn new(limit: Duration) -> Self {
        Self(Arc::new((
            Mutex::new(tokio::time::Instant::now() + limit),
            Notify::new(),
        )))
    }

    /// When the exchange ends.
    pub fn at(&self) -> tokio::time::Instant {
        self.0
            .0
            .lock()
            .map_or_else(|_| tokio::time::Instant::now(), |d| *d)
    }

    /// Moves the end to `limit` from now.
    pub fn extend(&self, limit: Duration) {
        if let Ok(mut d) = self.0.0.lock() {
            *d = tokio::time::Instant::now() + limit;
        }
        self.0.1.notify_waiters();
    }

    /// Resolves when the end was moved.
    pub async fn moved(&self) {
        self.0.1.notified().await;
    }
}

fn refused(r: &Refusal) -> Response {
    let code = match r.kind {
        RefusalKind::Busy => StatusCode::CONFLICT,
        RefusalKind::TooLarge => StatusCode::PAYLOAD_TOO_LARGE,
        RefusalKind::DiskFull => StatusCode::INSUFFICIENT_STORAGE,
        RefusalKind::Interrupted => StatusCode::BAD_REQUEST,
        RefusalKind::Failed => StatusCode::INTERNAL_SERVER_ERROR,
        RefusalKind::Signature
        | RefusalKind::Truncated
        | RefusalKind::NotABundle
        | RefusalKind::Downgrade
        | RefusalKind::OtherBoard => StatusCode::UNPROCESSABLE_ENTITY,
    };
    json_text(
        code,
        json_line(&serde_json::json!({"ok": false, "kind": r.kind, "reason": r.reason})),
    )
}

/// The upload's query: whether it asks for a reboot after the install (`reboot=1`, also
/// `true`/`yes`; `0`/`false`/`no` or no query: no). Anything else is an error naming it.
pub fn parse_upload_query(query: Option<&str>) -> std::result::Result<bool, String> {
    let mut reboot = false;
    for pair in query.unwrap_or("").split('&').filter(|p| !p.is_empty()) {
        let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
        match key {
            "reboot" => {
                reboot = match value {
                    "1" | "true" | "yes" => true,
                    "0" | "false" | "no" => false,
                    other => {
                        return Err(format!(
                            "reboot={other:?} is not 1 or 0 (POST /api/update?reboot=1 reboots into the update once it is installed)"
                        ));
                    }
                };
            }
            other => {
                return Err(format!(
                    "unknown parameter {other:?} (POST /api/update takes only reboot=1)"
                ));
            }
        }
    }
    Ok(reboot)
}

/// Opens the part file: mode 0644, as RAUC refuses bundles others may write.
fn open_part(path: &std::path::Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt as _;
    std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .mode(0o644)
        .open(path)
}

/// Writes `piece` on a blocking thread, handing the file back.
async fn write_piece(mut file: std::fs::File, piece: Vec<u8>) -> std::io::Result<std::fs::File> {
    tokio::task::spawn_blocking(move || file.write_all(&piece).map(|()| file))
        .await
        .map_err(|e| std::io::Error::other(format!("writer thread: {e}")))?
}

pub(super) async fn upload(
    State(s): State<Arc<StatusService>>,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    deadline: Option<axum::Extension<ExchangeDeadline>>,
    axum::extract::RawQuery(query): axum::extract::RawQuery,
    headers: HeaderMap,
    body: Body,
) -> Response {
    let Some(updates) = s.updates.clone() else {
        return text(
            StatusCode::CONFLICT,
            "this irtrackd has no system updater: [update] backend is none, or auto found no RAUC \
             (docs/updates.md)\n",
        );
    };
    if let Err(r) = s.auth.authorize(&headers, conn.peer.ip()).await {
        return s.refusal(r);
    }
    let reboot = match parse_upload_query(query.as_deref()) {
        Ok(r) => r,
        Err(why) => {
            return json_text(
                StatusCode::BAD_REQUEST,
                json_line(&serde_json::json!({"ok": false, "kind": "bad_request", "reason": why})),
            );
        }
    };
    let length = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let mut ticket = match updates.begin_upload(length, reboot) {
        Ok(t) => t,
        Err(r) => return refused(&r),
    };
    if let Some(axum::Extension(d)) = deadline {
        d.extend(UPLOAD_EXCHANGE_LIMIT);
    }
    tracing::info!(peer = %conn.peer, bytes = ?length, reboot, "update upload started");
    let part = updates.part_path();
    let mut file = match open_part(&part) {
        Ok(f) => f,
        Err(e) => {
            let r = ticket.write_failed(&e);
            ticket.refuse(r.clone());
            return refused(&r);
        }
    };
    let mut stream = body.into_data_stream();
    let mut piece = Vec::with_capacity(WRITE_PIECE_BYTES);
    loop {
        let next = stream.next().await;
        let end = next.is_none();
        match next {
            Some(Ok(bytes)) => {
                if let Err(r) = ticket.received(bytes.len() as u64) {
                    ticket.refuse(r.clone());
                    return refused(&r);
                }
                piece.extend_from_slice(&bytes);
            }
            Some(Err(e)) => {
                tracing::info!(error = %e, "update upload stopped");
                // Dropping the ticket ends the job as interrupted.
                drop(ticket);
                return refused(&Refusal::new(
                    RefusalKind::Interrupted,
                    "the upload stopped before the bundle's end; send it again",
                ));
            }
            None => {}
        }
        if piece.len() >= WRITE_PIECE_BYTES || (end && !piece.is_empty()) {
            file = match write_piece(file, std::mem::take(&mut piece)).await {
                Ok(f) => f,
                Err(e) => {
                    let r = ticket.write_failed(&e);
                    ticket.refuse(r.clone());
                    return refused(&r);
                }
            };
        }
        if end {
            break;
        }
    }
    let synced = tokio::task::spawn_blocking(move || file.sync_all()).await;
    if let Ok(Err(e)) | Err(e) = synced.map_err(std::io::Error::other) {
        let r = ticket.write_failed(&e);
        ticket.refuse(r.clone());
        return refused(&r);
    }
    let id = ticket.id();
    match ticket.install() {
        Ok(_) => json_text(
            StatusCode::ACCEPTED,
            json_line(&serde_json::json!({
                "ok": true,
                "id": id,
                "state": "installing",
                "reboot": reboot,
                "message": if reboot {
                    "bundle received; installing, then rebooting into it (progress in /status → system.install and system.reboot)"
                } else {
                    "bundle received; installing (progress in /status → system.install)"
                },
            })),
        ),
        Err(r) => refused(&r),
    }
}

#[cfg(test)]
mod tests {
    use super::parse_upload_query;

    #[test]
    fn the_upload_query_asks_for_a_reboot_or_is_refused_by_name() {
        assert_eq!(parse_upload_query(None), Ok(false));
        assert_eq!(parse_upload_query(Some("")), Ok(false));
        for yes in ["reboot=1", "reboot=true", "reboot=yes", "reboot=0&reboot=1"] {
            assert_eq!(parse_upload_query(Some(yes)), Ok(true), "{yes}");
        }
        for no in ["reboot=0", "reboot=false", "reboot=no"] {
            assert_eq!(parse_upload_query(Some(no)), Ok(false), "{no}");
        }
        let e = parse_upload_query(Some("reboot=maybe")).unwrap_err();
        assert!(e.contains("reboot=\"maybe\" is not 1 or 0"), "{e}");
        let e = parse_upload_query(Some("rebot=1")).unwrap_err();
        assert!(e.contains("unknown parameter \"rebot\""), "{e}");
        assert!(parse_upload_query(Some("reboot")).is_err());
    }
}
