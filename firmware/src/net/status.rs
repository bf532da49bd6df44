//! Status listener (default port 7704) on axum/hyper: `GET /status` (JSON), `GET /metrics`
//! (Prometheus text), the set-up page (`GET /`, `GET /web/<path>`, embedded at compile time),
//! and with `[service] control = true` the robot control requests `POST /robot/enable`,
//! `POST /robot/disable`, `POST /robot/deadman?pressed=1|0` and `POST /robot` (link state).
//! Robot control moves the robot, so it is refused (403) unless the config opts in; see
//! docs/security.md. The whole API is described in docs/http-api.md.
//!
//! Limits kept from the hand-written server this replaced: a request head of at most 8 KiB,
//! 5 s to send it, and one request per connection (a WebSocket upgrade keeps its connection).

use std::future::Future;
use std::sync::{Arc, Weak};
use std::time::Duration;

use axum::Router;
use axum::body::Body;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{HeaderValue, Method, StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;

use irtrack_core::stream::PositionRecord;
use tokio::sync::watch;

use super::auth::OperatorAuth;
use super::live;
use crate::engine::ParamsHandle;
use crate::robot::client::LinkState;
use crate::robot::{RobotLink, TcpRobotLink};
use crate::status::SharedStatus;
use crate::tuning::TuningHandle;
use crate::viewer::ViewerTap;

/// What the control requests may act on.
#[derive(Clone, Default)]
pub struct RobotControl {
    /// `[service] control`; false refuses every control request.
    pub allowed: bool,
    /// The robot link, owned by `Running` (weak so shutdown can still take it back).
    pub link: Option<Weak<TcpRobotLink>>,
    /// Software deadman flag, when `[robot.deadman] kind = "flag"`.
    pub deadman_flag: Option<crate::robot::deadman::FlagDeadman>,
}

/// Largest request head (request line and headers); hyper's smallest allowed buffer.
pub const MAX_REQUEST_HEAD_BYTES: usize = 8 * 1024;
/// Largest request body (tuning and login JSON are a few hundred bytes).
pub const MAX_REQUEST_BODY_BYTES: usize = 64 * 1024;
/// Time a client has to send its request head.
pub const READ_TIMEOUT: Duration = Duration::from_secs(5);

/// Everything the status listener serves from.
pub struct StatusService {
    pub status: Arc<SharedStatus>,
    pub control: RobotControl,
    /// Operator credential and sessions (every change request needs a sign-in).
    pub auth: Arc<OperatorAuth>,
    /// The loop's viewer tap (live previews, frame-set capture); `None` = not offered.
    pub tap: Option<Arc<ViewerTap>>,
    /// Live tuning; `None` = not offered.
    pub tuning: Option<Arc<TuningHandle>>,
    /// Position records for the live view.
    pub positions: Option<watch::Receiver<Option<PositionRecord>>>,
    /// Active parameter set (camera poses for the 3-D view).
    pub params: Option<Arc<ParamsHandle>>,
    /// The robot's safety workspace box (`[robot.safety]`), for the 3-D view.
    pub workspace_mm: Option<([f64; 3], [f64; 3])>,
    /// `/api/frameset` serves one request at a time.
    pub(super) frameset_busy: tokio::sync::Mutex<()>,
    /// The newest encoded previews, shared by viewers with the same settings.
    pub previews: Arc<super::live::PreviewShare>,
}

impl StatusService {
    /// Status and metrics only, control refused, no operator configured.
    pub fn new(status: Arc<SharedStatus>) -> Self {
        Self {
            status,
            control: RobotControl::default(),
            auth: Arc::new(OperatorAuth::default()),
            tap: None,
            tuning: None,
            positions: None,
            params: None,
            workspace_mm: None,
            frameset_busy: tokio::sync::Mutex::new(()),
            previews: Arc::default(),
        }
    }

    pub fn with_control(mut self, control: RobotControl) -> Self {
        self.control = control;
        self
    }

    pub fn with_auth(mut self, auth: OperatorAuth) -> Self {
        self.auth = Arc::new(auth);
        self
    }

    /// The set-up view's data sources.
    pub fn with_live(
        mut self,
        tap: Arc<ViewerTap>,
        tuning: Arc<TuningHandle>,
        positions: watch::Receiver<Option<PositionRecord>>,
        params: Arc<ParamsHandle>,
    ) -> Self {
        self.tap = Some(tap);
        self.tuning = Some(tuning);
        self.positions = Some(positions);
        self.params = Some(params);
        self
    }

    pub fn with_workspace(mut self, workspace_mm: Option<([f64; 3], [f64; 3])>) -> Self {
        self.workspace_mm = workspace_mm;
        self
    }

    /// The `/status` document plus what only the listener knows (robot link, tuning,
    /// viewers) and the faults in plain words.
    pub fn report_json(&self) -> serde_json::Value {
        let report = self.status.report();
        let tuning = self.tuning.as_ref().map(|t| t.report());
        let threshold_dn = tuning.as_ref().map(|t| t.threshold_dn);
        let analysis = self
            .tap
            .as_ref()
            .and_then(|t| t.analysis(crate::viewer::ANALYSIS_MAX_AGE))
            // Made before a threshold change: out of date (the next one comes within a second).
            .filter(|a| threshold_dn.is_none_or(|thr| a.iter().all(|c| c.threshold_dn == thr)));
        let fault_texts =
            crate::status::fault_texts(&self.status, threshold_dn, analysis.as_deref().map(Vec::as_slice));
        let mut v = serde_json::to_value(&report).unwrap_or_default();
        let robot = self
            .control
            .link
            .as_ref()
            .and_then(Weak::upgrade)
            .and_then(|l| serde_json::from_str::<serde_json::Value>(&link_json(&l, None)).ok());
        if let Some(o) = v.as_object_mut() {
            o.insert("fault_texts".into(), serde_json::json!(fault_texts));
            o.insert("robot".into(), robot.unwrap_or(serde_json::Value::Null));
            o.insert("tuning".into(), serde_json::to_value(&tuning).unwrap_or_default());
            // The whole-frame analysis every part of the set-up view shows (crate::advice).
            o.insert(
                "frame_analysis".into(),
                serde_json::to_value(analysis.as_deref()).unwrap_or_default(),
            );
            o.insert(
                "threshold_suggestion".into(),
                serde_json::to_value(self.tap.as_ref().and_then(|t| t.startup_suggestion()))
                    .unwrap_or_default(),
            );
            o.insert(
                "viewers".into(),
                serde_json::json!({
                    "live": self.status.live_viewers.load(std::sync::atomic::Ordering::Relaxed),
                    "copies": self.tap.as_ref().map_or(0, |t| t.copies()),
                    "busy_skips": self.tap.as_ref().map_or(0, |t| t.busy_skips()),
                    "previews_encoded": self.previews.encoded.load(std::sync::atomic::Ordering::Relaxed),
                    "previews_shared": self.previews.shared.load(std::sync::atomic::Ordering::Relaxed),
                }),
            );
        }
        v
    }

    /// Camera poses and the workspace box (`GET /api/scene`).
    pub fn scene_json(&self) -> serde_json::Value {
        let active = self.params.as_ref().and_then(|p| p.current());
        let cameras: Vec<serde_json::Value> = active
            .as_ref()
            .map(|p| {
                p.rig
                    .cameras
                    .iter()
                    .enumerate()
                    .map(|(i, c)| {
                        let k = &c.model.intrinsics;
                        serde_json::json!({
                            "camera": i,
                            "width_px": c.model.image_size.width_px,
                            "height_px": c.model.image_size.height_px,
                            "fx_px": k.fx_px, "fy_px": k.fy_px, "cx_px": k.cx_px, "cy_px": k.cy_px,
                            "r_cam_from_cam0_row_major": c.cam_from_cam0.r_row_major,
                            "t_cam_from_cam0_mm": c.cam_from_cam0.t_mm,
                        })
                    })
                    .collect()
            })
            .unwrap_or_default();
        serde_json::json!({
            "rig_id": active.as_ref().map(|p| p.rig.rig_id.clone()),
            "params_crc": active.as_ref().map(|p| format!("{:08x}", p.crc)),
            "cameras": cameras,
            "world_from_cam0": active.as_ref().and_then(|p| p.rig.world_from_cam0).map(|w| serde_json::json!({
                "r_row_major": w.r_row_major, "t_mm": w.t_mm,
            })),
            "tools": active.as_ref().map(|p| p.rig.tools.iter().map(|t| serde_json::json!({
                "name": t.name, "leds_mm": t.leds_mm,
            })).collect::<Vec<_>>()),
            "workspace_mm": self.workspace_mm.map(|(lo, hi)| serde_json::json!({"min": lo, "max": hi})),
        })
    }

    /// The HTTP routes (also usable in-process with `tower::ServiceExt::oneshot`).
    pub fn router(self) -> Router {
        let state = Arc::new(self);
        Router::new()
            .route("/", get(index))
            .route("/web/{*path}", get(asset))
            .route("/status", get(status_json))
            .route("/metrics", get(metrics))
            .route("/robot", post(robot))
            .route("/robot/{*action}", post(robot))
            .route("/api/session", get(live::session))
            .route("/api/login", post(live::login))
            .route("/api/logout", post(live::logout))
            .route("/api/tuning", get(live::tuning_get).post(live::tuning_post))
            .route("/api/tuning/save", post(live::tuning_save))
            .route("/api/tuning/suggest", post(super::advice::suggest))
            .route("/api/scene", get(live::scene))
            .route("/api/frameset", get(live::frameset))
            .route("/api/live", get(live::live))
            .fallback(fallback)
            .method_not_allowed_fallback(fallback)
            .layer(DefaultBodyLimit::max(MAX_REQUEST_BODY_BYTES))
            .layer(axum::middleware::map_response(one_request_per_connection))
            .with_state(state)
    }

    /// Serves `listener` until `shutdown` resolves; open connections (WebSockets too) end then.
    pub async fn serve(self, listener: TcpListener, shutdown: impl Future<Output = ()>) {
        serve_router(listener, self.router(), shutdown).await;
    }
}

/// Accept loop with the listener's limits; `router` answers every request.
pub async fn serve_router(listener: TcpListener, router: Router, shutdown: impl Future<Output = ()>) {
    let mut conns = tokio::task::JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _peer)) => {
                    let svc = TowerToHyperService::new(router.clone());
                    conns.spawn(async move {
                        let mut http = hyper::server::conn::http1::Builder::new();
                        http.timer(TokioTimer::new())
                            .header_read_timeout(READ_TIMEOUT)
                            .max_buf_size(MAX_REQUEST_HEAD_BYTES);
                        let conn = http.serve_connection(TokioIo::new(stream), svc).with_upgrades();
                        if let Err(e) = conn.await {
                            tracing::debug!(error = %e, "status connection ended with an error");
                        }
                    });
                }
                Err(e) => {
                    tracing::warn!(error = %e, "status accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            },
            Some(_) = conns.join_next(), if !conns.is_empty() => {}
        }
    }
    conns.abort_all();
    while conns.join_next().await.is_some() {}
}

/// One request per connection, as before the move to hyper: raw-socket clients read the answer
/// to the end of the stream. `Connection: close` makes hyper end the connection after the
/// answer; a WebSocket upgrade (101) keeps it (hyper's own keep-alive switch would add
/// `close` to the upgrade answer too, which WebSocket clients reject).
async fn one_request_per_connection(mut resp: Response) -> Response {
    if resp.status() != StatusCode::SWITCHING_PROTOCOLS {
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    resp
}

pub async fn serve(listener: TcpListener, status: Arc<SharedStatus>, shutdown: impl Future<Output = ()>) {
    StatusService::new(status).serve(listener, shutdown).await;
}

/// Like [`serve`], plus the robot control requests.
pub async fn serve_with_control(
    listener: TcpListener,
    status: Arc<SharedStatus>,
    control: RobotControl,
    shutdown: impl Future<Output = ()>,
) {
    StatusService::new(status)
        .with_control(control)
        .serve(listener, shutdown)
        .await;
}

type Shared = State<Arc<StatusService>>;

/// A plain-text answer (every error is a sentence ending in a newline).
pub(crate) fn text(code: StatusCode, body: impl Into<String>) -> Response {
    (
        code,
        [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
        body.into(),
    )
        .into_response()
}

/// A JSON answer with a trailing newline.
pub(crate) fn json_text(code: StatusCode, body: String) -> Response {
    (code, [(header::CONTENT_TYPE, "application/json")], body).into_response()
}

async fn status_json(State(s): Shared) -> Response {
    match serde_json::to_string_pretty(&s.report_json()) {
        Ok(json) => json_text(StatusCode::OK, json + "\n"),
        Err(e) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("status encoding failed: {e}\n"),
        ),
    }
}

async fn metrics(State(s): Shared) -> Response {
    (
        StatusCode::OK,
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        s.status.prometheus(),
    )
        .into_response()
}

async fn fallback(method: Method) -> Response {
    if method == Method::GET || method == Method::HEAD {
        text(StatusCode::NOT_FOUND, "not found; try /, /status or /metrics\n")
    } else {
        text(
            StatusCode::METHOD_NOT_ALLOWED,
            "only GET (and POST for changes, see docs/http-api.md) is supported here\n",
        )
    }
}

/// Files of `firmware/web/`, embedded at compile time (no files to install on the board).
#[derive(rust_embed::RustEmbed)]
#[folder = "web/"]
struct WebAssets;

fn embedded(path: &str) -> Response {
    match WebAssets::get(path) {
        Some(file) => {
            let mime = file.metadata.mimetype();
            let mut resp = Response::new(Body::from(file.data.into_owned()));
            if let Ok(v) = HeaderValue::from_str(mime) {
                resp.headers_mut().insert(header::CONTENT_TYPE, v);
            }
            // The page changes with the binary; make the browser ask again after an update.
            resp.headers_mut()
                .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
            resp
        }
        None => text(
            StatusCode::NOT_FOUND,
            format!("no file web/{path} in this irtrackd build\n"),
        ),
    }
}

async fn index() -> Response {
    embedded("index.html")
}

async fn asset(axum::extract::Path(path): axum::extract::Path<String>) -> Response {
    embedded(&path)
}

/// JSON view of the link state (what a control request reports back).
fn link_json(link: &TcpRobotLink, deadman: Option<bool>) -> String {
    let st = link.status();
    let (state, hold_reason) = match st.state {
        LinkState::Disconnected => ("disconnected", None),
        LinkState::Connecting => ("connecting", None),
        LinkState::Holding(r) => ("holding", Some(format!("{r:?}"))),
        LinkState::Moving => ("moving", None),
    };
    let v = serde_json::json!({
        "state": state,
        "hold_reason": hold_reason,
        "robot_name": st.robot_name,
        "robot_pos_mm": st.robot_pos_mm,
        "connects": st.connects,
        "targets_sent": st.targets_sent,
        "holds_sent": st.holds_sent,
        "rejects": st.rejects,
        "last_error": st.last_error,
        "deadman_flag_pressed": deadman,
    });
    v.to_string() + "\n"
}

async fn robot(State(s): Shared, uri: Uri, headers: axum::http::HeaderMap) -> Response {
    // Refused outright when control is off (403), whoever asks; otherwise a sign-in is needed.
    if s.control.allowed
        && let Err(r) = s.auth.authorize(&headers).await
    {
        return r.response();
    }
    control(uri.path(), uri.query(), &s.control)
}

/// Answers a `POST /robot/...` request.
fn control(path: &str, query: Option<&str>, ctl: &RobotControl) -> Response {
    if !ctl.allowed {
        return text(
            StatusCode::FORBIDDEN,
            "robot control is disabled; set `[service] control = true` to allow it\n",
        );
    }
    let Some(link) = ctl.link.as_ref().and_then(Weak::upgrade) else {
        return text(
            StatusCode::CONFLICT,
            "no robot link: the config has no [robot] section\n",
        );
    };
    let flag_state = |ctl: &RobotControl| {
        ctl.deadman_flag
            .as_ref()
            .map(crate::robot::deadman::Deadman::pressed)
    };
    match path {
        "/robot/enable" => link.enable(),
        "/robot/disable" => link.disable(),
        "/robot/deadman" => {
            let Some(flag) = &ctl.deadman_flag else {
                return text(
                    StatusCode::CONFLICT,
                    "the deadman is not the software flag ([robot.deadman] kind = \"flag\")\n",
                );
            };
            let pressed = query
                .into_iter()
                .flat_map(|q| q.split('&'))
                .find_map(|kv| kv.strip_prefix("pressed="));
            match pressed {
                Some("1" | "true") => flag.set(true),
                Some("0" | "false") => flag.set(false),
                _ => {
                    return text(StatusCode::BAD_REQUEST, "expected ?pressed=1 or ?pressed=0\n");
                }
            }
        }
        "/robot" => {}
        _ => {
            return text(
                StatusCode::NOT_FOUND,
                "not found; try /robot/enable, /robot/disable or /robot/deadman?pressed=1|0\n",
            );
        }
    }
    tracing::info!(request = path, "robot control request");
    json_text(StatusCode::OK, link_json(&link, flag_state(ctl)))
}
