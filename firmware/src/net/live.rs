//! The set-up view's endpoints on the status listener: the live WebSocket (`/api/live`),
//! frame-set capture (`/api/frameset`), live tuning (`/api/tuning`), sign-in
//! (`/api/session`, `/api/login`, `/api/logout`) and the scene (`/api/scene`). Contract:
//! docs/http-api.md.
//!
//! Images are made only while someone watches, on the blocking pool, from the viewer tap's
//! latest copy (see [`crate::viewer`]); the processing loop never waits for any of this.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::State;
use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures_util::{SinkExt, StreamExt};
use serde::{Deserialize, Serialize};

use super::auth::{SESSION_COOKIE, SESSION_TTL};
use super::http::MAX_REQUEST_BODY_BYTES;
use super::http::{ConnInfo, json_line, json_text, text};
use super::limit::{ConnSlot, NetCounters};
use super::previews::{PREVIEW_EPOCH, PREVIEW_SHARE_WINDOW, PreviewShare, SharedPreviews};
use super::status::StatusService;
use crate::source::{Frame, Pixels};
use crate::tuning::TuningChange;
use crate::viewer::{BlobView, TapSet};
use irtrack_core::frameset;

type Shared = State<Arc<StatusService>>;

/// Preview rate a new subscription gets, and the most a viewer may ask for.
pub const DEFAULT_PREVIEW_FPS: f64 = 5.0;
/// The highest preview rate a viewer may ask for; higher requests are clamped to it.
pub const MAX_PREVIEW_FPS: f64 = 30.0;
/// Position messages per second at most.
pub const MAX_POSITIONS_PER_S: f64 = 30.0;
/// How often a session sends the status report.
pub const STATUS_PERIOD: Duration = Duration::from_millis(500);
/// How long `/api/frameset` waits for the loop's next set.
pub const FRAMESET_WAIT: Duration = Duration::from_secs(2);
/// Largest zoom crop side (px).
const MAX_ZOOM_PX: u32 = 256;
/// JPEG quality of previews (grey, downscaled: small and sharp enough to aim and focus).
const JPEG_QUALITY: u8 = 80;

// ---------------------------------------------------------------- sign-in

#[derive(Serialize)]
struct SessionInfo {
    signed_in: bool,
    operator_configured: bool,
    control_allowed: bool,
}

pub(super) async fn session(State(s): Shared, headers: HeaderMap) -> Response {
    let info = SessionInfo {
        signed_in: s.auth.signed_in(&headers),
        operator_configured: s.auth.configured(),
        control_allowed: s.control.allowed,
    };
    json_text(StatusCode::OK, json_line(&info))
}

#[derive(Deserialize)]
struct Login {
    password: String,
}

/// Reads a request body (after the caller checked what it could without it).
async fn read_body(body: axum::body::Body) -> Result<Bytes, Response> {
    axum::body::to_bytes(body, MAX_REQUEST_BODY_BYTES)
        .await
        .map_err(|_| {
            text(
                StatusCode::BAD_REQUEST,
                "the request body was too large, too slow or cut off\n",
            )
        })
}

pub(super) async fn login(
    State(s): Shared,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    body: axum::body::Body,
) -> Response {
    if !s.auth.configured() {
        return text(
            StatusCode::SERVICE_UNAVAILABLE,
            "no operator password is configured: run `irtrackd --hash-password` and put the result \
             in [service] operator_password_hash, then restart irtrackd\n",
        );
    }
    // Refused before the body is read while this address waits out a pause.
    if let Err(refusal) = s.auth.precheck(conn.peer.ip()) {
        return s.refusal(refusal);
    }
    let body = match read_body(body).await {
        Ok(b) => b,
        Err(r) => return r,
    };
    let Ok(Login { password }) = serde_json::from_slice::<Login>(&body) else {
        return text(
            StatusCode::BAD_REQUEST,
            "expected a JSON body {\"password\": \"...\"}\n",
        );
    };
    if let Err(refusal) = s.auth.check_password(password, conn.peer.ip()).await {
        tracing::warn!(peer = %conn.peer, ?refusal, "operator sign-in refused");
        return s.refusal(refusal);
    }
    let token = s.auth.open_session();
    tracing::info!("operator signed in");
    let cookie = format!(
        "{SESSION_COOKIE}={token}; HttpOnly; SameSite=Strict; Path=/; Max-Age={}",
        SESSION_TTL.as_secs()
    );
    let mut resp = json_text(StatusCode::OK, "{\"signed_in\":true}\n".into());
    if let Ok(v) = HeaderValue::from_str(&cookie) {
        resp.headers_mut().insert(header::SET_COOKIE, v);
    }
    resp
}

pub(super) async fn logout(State(s): Shared, headers: HeaderMap) -> Response {
    if let Some(t) = super::auth::session_token(&headers) {
        s.auth.close_session(t);
    }
    let mut resp = json_text(StatusCode::OK, "{\"signed_in\":false}\n".into());
    resp.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static("irtrack_session=; HttpOnly; SameSite=Strict; Path=/; Max-Age=0"),
    );
    resp
}

// ---------------------------------------------------------------- tuning

pub(super) async fn tuning_get(State(s): Shared) -> Response {
    match &s.tuning {
        Some(t) => json_text(StatusCode::OK, json_line(&t.report())),
        None => text(StatusCode::NOT_FOUND, "live tuning is not available here\n"),
    }
}

pub(super) async fn tuning_post(
    State(s): Shared,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Response {
    // Credentials first: an unauthorized client's body is never read.
    if let Err(r) = s.auth.authorize(&headers, conn.peer.ip()).await {
        return s.refusal(r);
    }
    let Some(t) = &s.tuning else {
        return text(StatusCode::NOT_FOUND, "live tuning is not available here\n");
    };
    let body = match read_body(body).await {
        Ok(b) => b,
        Err(r) => return r,
    };
    let change: TuningChange = match serde_json::from_slice(&body) {
        Ok(c) => c,
        Err(e) => {
            // Where it failed, not what was sent: answers never repeat request input.
            return text(
                StatusCode::BAD_REQUEST,
                format!(
                    "bad tuning request: not a tuning change (JSON error at line {} column {}; \
                     fields: see docs/http-api.md)\n",
                    e.line(),
                    e.column()
                ),
            );
        }
    };
    match t.change(&change) {
        Ok(()) => {
            tracing::info!(?change, "tuning changed by the operator");
            // The loop applies camera values before its next set; give it that long so the
            // answer shows them (it does not fail if the loop is slower).
            tokio::time::sleep(Duration::from_millis(50)).await;
            json_text(StatusCode::OK, json_line(&t.report()))
        }
        Err(e) => text(StatusCode::BAD_REQUEST, format!("{e}\n")),
    }
}

pub(super) async fn tuning_save(
    State(s): Shared,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    headers: HeaderMap,
) -> Response {
    if let Err(r) = s.auth.authorize(&headers, conn.peer.ip()).await {
        return s.refusal(r);
    }
    let Some(t) = s.tuning.clone() else {
        return text(StatusCode::NOT_FOUND, "live tuning is not available here\n");
    };
    let saved = tokio::task::spawn_blocking(move || t.save().map(|p| (p, t.report()))).await;
    match saved {
        Ok(Ok((path, report))) => {
            tracing::info!(path = %path.display(), "tuning saved; applied at the next start");
            json_text(StatusCode::OK, json_line(&report))
        }
        Ok(Err(e)) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("cannot save the tuning: {e}; the live values stay applied\n"),
        ),
        Err(e) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("saving the tuning failed: {e}\n"),
        ),
    }
}

// ---------------------------------------------------------------- scene

pub(super) async fn scene(State(s): Shared) -> Response {
    json_text(StatusCode::OK, json_line(&s.scene_json()))
}

// ---------------------------------------------------------------- frame set

/// The frame-set body of `/api/frameset` (docs/frameset.md); `None` if a frame does not fit the
/// format (a bit depth the frame's samples cannot hold), which the handler answers with 500.
fn frameset_body(set: &TapSet) -> Option<Vec<u8>> {
    let frames: Vec<frameset::CameraFrame<'_>> = set
        .frames
        .iter()
        .map(|f| frameset::CameraFrame {
            image: f.image(),
            timestamp_ns: f.timestamp_ns,
            sequence: f.sequence,
        })
        .collect();
    // The clock difference lets `host-tools capture` pair sets of several boards on the
    // realtime clock PTP/chrony keep in agreement (the timestamps are CLOCK_MONOTONIC).
    let realtime_minus_monotonic_ns = i64::try_from(crate::clock::realtime_minus_mono_ns()).ok();
    match frameset::encode_with_clock(
        set.set_index,
        set.pairing_error_ns,
        realtime_minus_monotonic_ns,
        &frames,
    ) {
        Ok(body) => Some(body),
        Err(e) => {
            tracing::warn!("frame set {}: {e}", set.set_index);
            None
        }
    }
}

pub(super) async fn frameset(State(s): Shared) -> Response {
    let Some(tap) = s.tap.clone() else {
        return text(StatusCode::NOT_FOUND, "frame-set capture is not available here\n");
    };
    let Ok(_one_at_a_time) = s.frameset_busy.try_lock() else {
        return text(
            StatusCode::SERVICE_UNAVAILABLE,
            "another frame-set request is being served; try again in a moment\n",
        );
    };
    let viewer = tap.attach();
    let seq0 = tap.seq();
    tap.request_once();
    let deadline = Instant::now() + FRAMESET_WAIT;
    while tap.seq() == seq0 {
        if Instant::now() >= deadline {
            return text(
                StatusCode::GATEWAY_TIMEOUT,
                "no frame set within 2 s: the cameras are not delivering (see /status)\n",
            );
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    let tap2 = tap.clone();
    let body = tokio::task::spawn_blocking(move || {
        let guard = tap2.read()?;
        guard.as_deref().and_then(frameset_body)
    })
    .await
    .ok()
    .flatten();
    drop(viewer);
    match body {
        Some(b) => (
            StatusCode::OK,
            [(header::CONTENT_TYPE, frameset::CONTENT_TYPE)],
            b,
        )
            .into_response(),
        None => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the frame-set copy was not available\n",
        ),
    }
}

// ---------------------------------------------------------------- live WebSocket

/// A viewer's wishes (`{"type": "subscribe", ...}`).
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(default)]
struct Subscription {
    preview_fps: f64,
    preview_max_width_px: u32,
    zoom_px: u32,
    positions: bool,
    blobs: bool,
}

impl Default for Subscription {
    fn default() -> Self {
        Self {
            preview_fps: DEFAULT_PREVIEW_FPS,
            preview_max_width_px: 640,
            zoom_px: 0,
            positions: true,
            blobs: false,
        }
    }
}

impl Subscription {
    fn sanitized(mut self) -> Self {
        if !self.preview_fps.is_finite() || self.preview_fps < 0.0 {
            self.preview_fps = DEFAULT_PREVIEW_FPS;
        }
        self.preview_fps = self.preview_fps.min(MAX_PREVIEW_FPS);
        self.preview_max_width_px = self.preview_max_width_px.clamp(32, 4096);
        self.zoom_px = self.zoom_px.min(MAX_ZOOM_PX);
        self
    }

    /// Interval at which this viewer needs the loop's frame copies (0 = none): its preview
    /// rate. Every set's blob lists come through the blob copy, without frames.
    fn tap_interval_ns(&self) -> u64 {
        if self.preview_fps > 0.0 {
            (1e9 / self.preview_fps) as u64
        } else {
            0
        }
    }
}

#[derive(Deserialize)]
struct ClientMessage {
    #[serde(rename = "type")]
    kind: String,
    #[serde(flatten)]
    rest: serde_json::Value,
}

/// Largest message or frame a viewer may send (a subscribe message is ~100 bytes).
pub const MAX_CLIENT_MESSAGE_BYTES: usize = 64 * 1024;
/// A send to a viewer that does not complete in this time ends the session (the viewer
/// stopped reading; nothing piles up for it).
pub const WS_SEND_TIMEOUT: Duration = Duration::from_secs(5);
/// The board pings a viewer this often ...
pub const WS_PING_PERIOD: Duration = Duration::from_secs(10);
/// ... and ends the session when nothing (pong or message) came back for this long.
pub const WS_SILENCE_LIMIT: Duration = Duration::from_secs(25);

pub(super) async fn live(
    State(s): Shared,
    axum::Extension(slot): axum::Extension<ConnSlot>,
    ws: WebSocketUpgrade,
) -> Response {
    // Oversized frames and messages, and unmasked client frames, end the session with an
    // error (tungstenite's checks); the write buffer holds at most about one message because
    // every send waits for its flush.
    // A session holds its slot for long: within the listener's long-lived share, so the other
    // slots stay for plain requests (net::limit).
    if !slot.hold_long() {
        return text(
            StatusCode::SERVICE_UNAVAILABLE,
            "too many live sessions at once; try again later\n",
        );
    }
    ws.max_message_size(MAX_CLIENT_MESSAGE_BYTES)
        .max_frame_size(MAX_CLIENT_MESSAGE_BYTES)
        .on_upgrade(move |socket| async move {
            // The connection's slot stays taken while the session lives.
            let _slot = slot;
            live_session(socket, s).await;
        })
}

/// The sending half of a live session, with the counters its timeouts go to.
struct ViewerTx<'a> {
    tx: futures_util::stream::SplitSink<WebSocket, Message>,
    net: &'a NetCounters,
}

impl ViewerTx<'_> {
    /// Sends one message within [`WS_SEND_TIMEOUT`]; a send not taken in time is counted
    /// (`irtrackd_websocket_timeouts_total{reason="send"}`) and ends the session.
    async fn send(&mut self, m: Message) -> Result<(), axum::Error> {
        match tokio::time::timeout(WS_SEND_TIMEOUT, self.tx.send(m)).await {
            Ok(r) => r,
            Err(_) => {
                count_ws_timeout(self.net, &self.net.ws_send_timeouts);
                tracing::info!("live viewer did not take a message in time; session closed");
                Err(axum::Error::new(std::io::Error::new(
                    std::io::ErrorKind::TimedOut,
                    "viewer did not take a message in time",
                )))
            }
        }
    }
}

/// Counts a WebSocket timeout under its reason and as a status-listener timeout.
fn count_ws_timeout(net: &NetCounters, reason: &AtomicU64) {
    reason.fetch_add(1, Ordering::Relaxed);
    net.status.timeouts.fetch_add(1, Ordering::Relaxed);
}

/// What one frame copy turns into for one viewer.
struct Rendered {
    previews: Vec<(serde_json::Value, Bytes)>,
    zooms: Vec<(serde_json::Value, Bytes)>,
}

/// Previews for one viewer: from the shared cache when another viewer encoded them within
/// [`PREVIEW_SHARE_WINDOW`] (no frame touched at all), else encoded from a copy of the tap's
/// frame copy and offered to the others; the whole-frame analysis made on the way is kept by
/// the tap (for `/status` and the blob lists). `None` when the tap holds no set.
fn render_for_viewer(
    tap: &crate::viewer::ViewerTap,
    share: &PreviewShare,
    sub: &Subscription,
) -> Option<Rendered> {
    let key = (sub.preview_max_width_px, sub.zoom_px);
    // Held through the encode: viewers that become due together wait here for the first one's
    // encode instead of all encoding the same set. Only viewer threads take this lock.
    let mut cache = share.cache.lock().ok()?;
    if let Some(c) = cache
        .as_ref()
        .filter(|c| c.key == key && c.encoded_at.elapsed() < PREVIEW_SHARE_WINDOW)
    {
        share.shared.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        return Some(Rendered {
            previews: c.previews.clone(),
            zooms: c.zooms.clone(),
        });
    }
    // Hold the tap's copy only for a memcpy (the loop skips sets while it is held), then
    // analyse, downscale and encode outside that lock.
    let set = tap.read()?.as_deref()?.clone();
    let (r, analysis) = render(&set, sub);
    tap.store_analysis(analysis);
    share.encoded.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    *cache = Some(SharedPreviews {
        key,
        encoded_at: Instant::now(),
        previews: r.previews.clone(),
        zooms: r.zooms.clone(),
    });
    Some(r)
}

/// The `blobs` message of the tap's latest blob copy (see [`crate::viewer::BlobCopy`]), with
/// the spots of the newest whole-frame analysis added; `None` while there is nothing to list.
fn blob_message(tap: &crate::viewer::ViewerTap, copy: &crate::viewer::BlobCopy) -> Option<serde_json::Value> {
    let analysis = tap.analysis(crate::viewer::ANALYSIS_MAX_AGE);
    let (lists, truncated) = copy.with_full_search(analysis.as_deref().map(Vec::as_slice))?;
    let searched = analysis.as_deref().and_then(|a| a.first()).map(|a| a.set_index);
    Some(serde_json::json!({
        "type": "blobs",
        "set_index": copy.set_index,
        "timestamps_ns": copy.timestamps_ns,
        "pairing_error_ns": copy.pairing_error_ns,
        "cameras": lists,
        "truncated": truncated,
        "full_search_set_index": searched,
    }))
}

async fn live_session(socket: WebSocket, s: Arc<StatusService>) {
    let (tx, mut rx) = socket.split();
    let mut tx = ViewerTx {
        tx,
        net: &s.status.net,
    };
    let viewer = s.tap.as_ref().map(|t| t.attach());
    // Status reports only until the client says what it wants: nothing is encoded for a
    // client that is about to ask for other sizes (the page subscribes on open).
    let mut sub = Subscription {
        preview_fps: 0.0,
        positions: false,
        ..Subscription::default()
    };
    if let Some(v) = &viewer {
        v.set_wants(sub.tap_interval_ns(), sub.blobs);
    }
    s.status
        .live_viewers
        .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let mut status_tick = tokio::time::interval(STATUS_PERIOD);
    status_tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut poll = tokio::time::interval(Duration::from_millis(5));
    poll.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut last_seq = s.tap.as_ref().map_or(0, |t| t.seq());
    let mut last_blob_seq = s.tap.as_ref().map_or(0, |t| t.blob_seq());
    // Preview slots on one clock for every viewer: viewers at the same rate become due together,
    // so the first one's encode is shared by the others (see PREVIEW_SHARE_WINDOW).
    let epoch = *PREVIEW_EPOCH.get_or_init(Instant::now);
    let mut last_slot: Option<u64> = None;
    let mut last_position: Option<Instant> = None;
    let mut last_blob_set: Option<u64> = None;
    let mut dropped_sets = 0u64;
    let mut positions = s.positions.clone();
    // The first ping one period in (an interval's first tick would come at once).
    let mut ping = tokio::time::interval_at(tokio::time::Instant::now() + WS_PING_PERIOD, WS_PING_PERIOD);
    ping.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut last_heard = Instant::now();
    loop {
        let result = tokio::select! {
            msg = rx.next() => match msg {
                Some(Ok(Message::Text(t))) => {
                    last_heard = Instant::now();
                    match parse_subscribe(t.as_str()) {
                        Ok(new) => {
                            sub = new;
                            if let Some(v) = &viewer {
                                v.set_wants(sub.tap_interval_ns(), sub.blobs);
                            }
                            Ok(())
                        }
                        Err(e) => {
                            let m = serde_json::json!({"type": "error", "message": e});
                            tx.send(Message::Text(m.to_string().into())).await
                        }
                    }
                }
                Some(Ok(Message::Close(_))) | None | Some(Err(_)) => break,
                Some(Ok(_)) => {
                    last_heard = Instant::now();
                    Ok(())
                }
            },
            _ = ping.tick() => {
                if last_heard.elapsed() > WS_SILENCE_LIMIT {
                    count_ws_timeout(&s.status.net, &s.status.net.ws_silence_timeouts);
                    tracing::info!("live viewer silent too long (no pong); session closed");
                    break;
                }
                tx.send(Message::Ping(Bytes::new())).await
            }
            _ = status_tick.tick() => {
                let mut v = s.report_json();
                if let Some(o) = v.as_object_mut() {
                    o.insert("type".into(), "status".into());
                }
                tx.send(Message::Text(v.to_string().into())).await
            }
            changed = async {
                match positions.as_mut() {
                    Some(p) => p.changed().await,
                    None => std::future::pending().await,
                }
            }, if sub.positions => {
                if changed.is_err() {
                    positions = None;
                    continue;
                }
                let due = last_position.is_none_or(|t| t.elapsed().as_secs_f64() >= 1.0 / MAX_POSITIONS_PER_S);
                let rec = positions.as_mut().and_then(|p| *p.borrow_and_update());
                match (due, rec) {
                    (true, Some(rec)) => {
                        last_position = Some(Instant::now());
                        let mut m = format!("{{\"type\":\"position\",\"record\":{}", rec.to_ndjson_line().trim_end());
                        // Every tool of this set (6-DOF mode): each with its id and name.
                        let tools = s.tools.as_ref().map(|t| *t.borrow()).filter(|t| t.frame == rec.frame);
                        if let Some(set) = tools {
                            m.push_str(",\"tools\":[");
                            for (i, t) in set.records().enumerate() {
                                if i > 0 {
                                    m.push(',');
                                }
                                m.push_str(t.to_ndjson_line().trim_end());
                            }
                            m.push(']');
                            // The loose single LEDs of this set, each with its stable id.
                            m.push_str(",\"loose\":[");
                            let mut line = String::new();
                            for (i, l) in set.loose_records().enumerate() {
                                if i > 0 {
                                    m.push(',');
                                }
                                line.clear();
                                l.write_ndjson(&mut line);
                                m.push_str(line.trim_end());
                            }
                            m.push(']');
                        }
                        m.push('}');
                        tx.send(Message::Text(m.into())).await
                    }
                    _ => Ok(()),
                }
            }
            _ = poll.tick(), if viewer.is_some() => {
                let Some(tap) = s.tap.clone() else { continue };
                // Every set's blob lists: a small copy, turned into JSON here.
                let blob_seq = tap.blob_seq();
                if sub.blobs && blob_seq != last_blob_seq {
                    last_blob_seq = blob_seq;
                    let msg = tap.read_blobs().and_then(|copy| {
                        let m = blob_message(&tap, &copy)?;
                        Some((copy.set_index, m))
                    });
                    if let Some((set_index, mut m)) = msg {
                        if let Some(prev) = last_blob_set {
                            let gap = set_index.saturating_sub(prev + 1);
                            dropped_sets += gap;
                            tap.count_viewer_drops(gap);
                        }
                        last_blob_set = Some(set_index);
                        if let Some(o) = m.as_object_mut() {
                            o.insert("dropped".into(), dropped_sets.into());
                        }
                        if tx.send(Message::Text(m.to_string().into())).await.is_err() {
                            break;
                        }
                    }
                }
                // Previews from the frame copy, at the viewer's preview rate.
                let seq = tap.seq();
                if seq == last_seq {
                    continue;
                }
                last_seq = seq;
                let slot = (epoch.elapsed().as_secs_f64() * sub.preview_fps) as u64;
                if sub.preview_fps <= 0.0 || last_slot == Some(slot) {
                    continue;
                }
                let sub_now = sub;
                let share = s.previews.clone();
                let rendered = tokio::task::spawn_blocking(move || {
                    render_for_viewer(&tap, &share, &sub_now)
                })
                .await
                .ok()
                .flatten();
                let Some(mut r) = rendered else { continue };
                last_slot = Some(slot);
                send_rendered(&mut tx, &mut r).await
            }
        };
        if result.is_err() {
            break;
        }
    }
    s.status
        .live_viewers
        .fetch_sub(1, std::sync::atomic::Ordering::Relaxed);
    drop(viewer);
}

/// Errors name the problem but never repeat what the client sent.
fn parse_subscribe(text: &str) -> Result<Subscription, String> {
    let msg: ClientMessage = serde_json::from_str(text).map_err(|e| {
        format!(
            "not a JSON message with a \"type\" (error at line {} column {})",
            e.line(),
            e.column()
        )
    })?;
    if msg.kind != "subscribe" {
        return Err("unknown message type; only \"subscribe\" exists".into());
    }
    let sub: Subscription = serde_json::from_value(msg.rest).map_err(|_| {
        "bad subscribe message: expected preview_fps, preview_max_width_px, zoom_px (numbers), \
         positions, blobs (true/false)"
            .to_string()
    })?;
    Ok(sub.sanitized())
}

async fn send_rendered(tx: &mut ViewerTx<'_>, r: &mut Rendered) -> Result<(), axum::Error> {
    for (meta, jpeg) in r.previews.drain(..) {
        tx.send(Message::Text(meta.to_string().into())).await?;
        tx.send(Message::Binary(jpeg)).await?;
    }
    for (meta, png) in r.zooms.drain(..) {
        tx.send(Message::Text(meta.to_string().into())).await?;
        tx.send(Message::Binary(png)).await?;
    }
    Ok(())
}

/// 8-bit value of a pixel (deeper frames shifted down).
fn px8(frame: &Frame, x: usize, y: usize) -> u8 {
    let i = y * frame.stride_px as usize + x;
    match &frame.pixels {
        Pixels::U8(p) => p.get(i).copied().unwrap_or(0),
        Pixels::U16(p) => {
            let shift = u32::from(frame.bit_depth.saturating_sub(8));
            p.get(i).map_or(0, |v| (u32::from(*v) >> shift).min(255) as u8)
        }
    }
}

fn frame_peak(frame: &Frame) -> u32 {
    match &frame.pixels {
        Pixels::U8(p) => p.iter().copied().max().map_or(0, u32::from),
        Pixels::U16(p) => p.iter().copied().max().map_or(0, u32::from),
    }
}

/// Analyses the frames in full, downscales (box filter, integer factor) and encodes previews,
/// crops zooms.
fn render(set: &TapSet, sub: &Subscription) -> (Rendered, Vec<crate::advice::CameraAnalysis>) {
    let mut out = Rendered {
        previews: Vec::new(),
        zooms: Vec::new(),
    };
    let analysis = set.analyse();
    for (camera, frame) in set.frames.iter().enumerate() {
        let blobs: &[BlobView] = analysis.get(camera).map_or(&[], |a| a.blobs.as_slice());
        let (w, h) = (frame.width_px as usize, frame.height_px as usize);
        let factor = w.div_ceil(sub.preview_max_width_px as usize).max(1);
        let (pw, ph) = (w / factor, h / factor);
        let mut small = Vec::with_capacity(pw * ph);
        for py in 0..ph {
            for px in 0..pw {
                let mut sum = 0u32;
                for dy in 0..factor {
                    for dx in 0..factor {
                        sum += u32::from(px8(frame, px * factor + dx, py * factor + dy));
                    }
                }
                small.push((sum / (factor * factor) as u32) as u8);
            }
        }
        let mut jpeg = Vec::new();
        let encoded = jpeg_encoder::Encoder::new(&mut jpeg, JPEG_QUALITY).encode(
            &small,
            pw as u16,
            ph as u16,
            jpeg_encoder::ColorType::Luma,
        );
        // A cluster solver's camera-board camera: no pixels here, its blobs only.
        let pixels = set.has_pixels.get(camera).copied().unwrap_or(true);
        let peak_dn = if pixels {
            frame_peak(frame)
        } else {
            blobs.iter().map(|b| b.peak_dn).max().unwrap_or(0)
        };
        if encoded.is_ok() {
            let meta = serde_json::json!({
                "type": "preview",
                "camera": camera,
                "set_index": set.set_index,
                "timestamp_ns": frame.timestamp_ns,
                "width_px": pw,
                "height_px": ph,
                "scale": 1.0 / factor as f64,
                "threshold_dn": set.threshold_dn,
                "peak_dn": peak_dn,
                "pixels": pixels,
                "bit_depth": frame.bit_depth,
                "blobs": blobs,
                "analysis": analysis.get(camera),
            });
            out.previews.push((meta, Bytes::from(jpeg)));
        }
        if sub.zoom_px > 0
            && pixels
            && let Some(b) = blobs.iter().find(|b| b.kept)
            && let Some(z) = zoom(frame, camera, set.set_index, b, sub.zoom_px)
        {
            out.zooms.push(z);
        }
    }
    (out, analysis)
}

/// A full-resolution crop around `blob` as an 8-bit grey PNG.
fn zoom(
    frame: &Frame,
    camera: usize,
    set_index: u64,
    blob: &BlobView,
    size: u32,
) -> Option<(serde_json::Value, Bytes)> {
    let size = size.min(frame.width_px).min(frame.height_px);
    let half = f64::from(size) / 2.0;
    let clamp = |c: f64, max: u32| (c - half).round().clamp(0.0, f64::from(max - size)) as u32;
    let (x0, y0) = (
        clamp(blob.x_px, frame.width_px),
        clamp(blob.y_px, frame.height_px),
    );
    let mut crop = Vec::with_capacity((size * size) as usize);
    for y in y0..y0 + size {
        for x in x0..x0 + size {
            crop.push(px8(frame, x as usize, y as usize));
        }
    }
    let mut png_bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut png_bytes, size, size);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().ok()?;
        w.write_image_data(&crop).ok()?;
    }
    let meta = serde_json::json!({
        "type": "zoom",
        "camera": camera,
        "set_index": set_index,
        "x0_px": x0,
        "y0_px": y0,
        "size_px": size,
    });
    Some((meta, Bytes::from(png_bytes)))
}
