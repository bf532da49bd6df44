//! The status listener's state ([`StatusService`]) and its own answers: `GET /status` (JSON),
//! `GET /metrics` (Prometheus text), the set-up page (`GET /`, `GET /web/<path>`, embedded at
//! compile time), and with `[service] control = true` the robot control requests
//! `POST /robot/enable`, `POST /robot/disable` (also `/robot/hold`),
//! `POST /robot/deadman?pressed=1|0` and `POST /robot` (link state). Robot control moves the
//! robot, so it is refused (403) unless the config opts in; requests that make the robot safer
//! (disable, hold, deadman released) need no sign-in and are never throttled. See
//! docs/security.md; the whole API is in docs/http-api.md. The routes, limits and accept loop
//! are in `server`; the set-up view's endpoints in `live`.

use std::sync::{Arc, Weak};

use axum::body::Body;
use axum::extract::State;
use axum::http::{HeaderValue, Method, StatusCode, Uri, header};
use axum::response::{IntoResponse, Response};

use irtrack_core::stream::PositionRecord;
use tokio::sync::watch;

use super::auth::OperatorAuth;
use super::http::{ConnInfo, HostPolicy, json_text, text};
use crate::engine::ParamsHandle;
use crate::status::SharedStatus;
use crate::tuning::TuningHandle;
use crate::viewer::ViewerTap;
use irtrack_robot::{LinkHandle, LinkState, RobotLink};

/// What the control requests may act on.
#[derive(Clone, Default)]
pub struct RobotControl {
    /// `[service] control`; false refuses every control request.
    pub allowed: bool,
    /// The robot link, owned by `Running` (weak so shutdown can still take it back).
    pub link: Option<Weak<LinkHandle>>,
    /// Software deadman flag, when `[robot.deadman] kind = "flag"`.
    pub deadman_flag: Option<irtrack_robot::deadman::FlagDeadman>,
}

/// Everything the status listener serves from.
pub struct StatusService {
    /// The counters and state `/status` reports.
    pub status: Arc<SharedStatus>,
    /// What the robot control requests act on (none by default).
    pub control: RobotControl,
    /// Operator credential and sessions (every change request needs a sign-in).
    pub auth: Arc<OperatorAuth>,
    /// The loop's viewer tap (live previews, frame-set capture); `None` = not offered.
    pub tap: Option<Arc<ViewerTap>>,
    /// Live tuning; `None` = not offered.
    pub tuning: Option<Arc<TuningHandle>>,
    /// Position records for the live view.
    pub positions: Option<watch::Receiver<Option<PositionRecord>>>,
    /// Every tool's record of the set (6-DOF mode), sent with each position.
    pub tools: Option<watch::Receiver<crate::engine::ToolSet>>,
    /// Active parameter set (camera poses for the 3-D view).
    pub params: Option<Arc<ParamsHandle>>,
    /// The robot's safety workspace box (`[robot.safety]`), for the 3-D view.
    pub workspace_mm: Option<([f64; 3], [f64; 3])>,
    /// `/api/frameset` serves one request at a time.
    pub(super) frameset_busy: tokio::sync::Mutex<()>,
    /// The newest encoded previews, shared by viewers with the same settings.
    pub previews: Arc<super::previews::PreviewShare>,
    /// Host names the board answers to besides its addresses (`[status] allowed_hosts`).
    pub hosts: HostPolicy,
    /// `[status] public_view`: previews, frames and positions without sign-in.
    pub public_view: bool,
    /// The system updater (`[update]`); `None` = updates off.
    pub updates: Option<Arc<crate::update::Updates>>,
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
            tools: None,
            params: None,
            workspace_mm: None,
            frameset_busy: tokio::sync::Mutex::new(()),
            previews: Arc::default(),
            hosts: HostPolicy::new(&[]),
            public_view: true,
            updates: None,
        }
    }

    /// The system updater `/status` reports and `POST /api/update` installs with.
    pub fn with_updates(mut self, updates: Option<Arc<crate::update::Updates>>) -> Self {
        self.updates = updates;
        self
    }

    /// `[status]`: extra host names and whether viewing needs a sign-in.
    pub fn with_view_policy(mut self, allowed_hosts: &[String], public_view: bool) -> Self {
        self.hosts = HostPolicy::new(allowed_hosts);
        self.public_view = public_view;
        self
    }

    /// Lets the control requests act on the robot link.
    pub fn with_control(mut self, control: RobotControl) -> Self {
        self.control = control;
        self
    }

    /// The operator credential that change requests are checked against.
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

    /// Every tool's pose for the live view (the loop's per-tool slot).
    pub fn with_tools(mut self, tools: watch::Receiver<crate::engine::ToolSet>) -> Self {
        self.tools = Some(tools);
        self
    }

    /// The safety workspace box (min, max corners, mm) to draw in the 3-D view.
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
            o.insert(
                "outputs".into(),
                self.status
                    .outputs
                    .get()
                    .map_or(serde_json::Value::Null, |s| s.report_json()),
            );
            o.insert("tuning".into(), serde_json::to_value(&tuning).unwrap_or_default());
            // The slots, the last update and an install in progress (crate::update).
            o.insert(
                "system".into(),
                self.updates
                    .as_ref()
                    .map_or_else(|| serde_json::json!({"backend": "none"}), |u| u.report_json()),
            );
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
                    "blob_copies": self.tap.as_ref().map_or(0, |t| t.blob_copies()),
                    "blob_busy_skips": self.tap.as_ref().map_or(0, |t| t.blob_busy_skips()),
                    "blob_sets_dropped": self.tap.as_ref().map_or(0, |t| t.viewer_dropped_sets()),
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
}

type Shared = State<Arc<StatusService>>;

pub(super) async fn status_json(State(s): Shared) -> Response {
    match serde_json::to_string_pretty(&s.report_json()) {
        Ok(json) => json_text(StatusCode::OK, json + "\n"),
        Err(e) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("status encoding failed: {e}\n"),
        ),
    }
}

pub(super) async fn metrics(State(s): Shared) -> Response {
    (
        StatusCode::OK,
        [(
            header::CONTENT_TYPE,
            "application/openmetrics-text; version=1.0.0; charset=utf-8",
        )],
        with_update_metrics(s.status.prometheus(), s.updates.as_deref()),
    )
        .into_response()
}

/// The update gauges, before the exposition's `# EOF`.
fn with_update_metrics(mut text: String, updates: Option<&crate::update::Updates>) -> String {
    let Some(u) = updates else { return text };
    let eof = text.ends_with("# EOF\n");
    if eof {
        text.truncate(text.len() - "# EOF\n".len());
    }
    text.push_str(&u.metrics_text());
    if eof {
        text.push_str("# EOF\n");
    }
    text
}

pub(super) async fn fallback(method: Method) -> Response {
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
        // Not the path itself: answers never repeat request input.
        None => text(
            StatusCode::NOT_FOUND,
            "no such file in this irtrackd build's set-up page\n",
        ),
    }
}

/// Hashes of the set-up page's inline scripts (its import map) for the CSP.
pub(super) fn page_inline_script_hashes() -> Vec<String> {
    WebAssets::get("index.html")
        .map(|f| super::http::inline_script_hashes(&String::from_utf8_lossy(&f.data)))
        .unwrap_or_default()
}

pub(super) async fn index() -> Response {
    embedded("index.html")
}

pub(super) async fn asset(axum::extract::Path(path): axum::extract::Path<String>) -> Response {
    embedded(&path)
}

/// JSON view of the link state (what a control request reports back).
fn link_json(link: &LinkHandle, deadman: Option<bool>) -> String {
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
        // EGM/RSI: the pinned controller, packets answered and refused (not answered) by reason.
        "controller": st.controller,
        "packets_answered": st.packets_answered,
        "refused": st.refused_by_reason().into_iter().collect::<std::collections::BTreeMap<_, _>>(),
        "last_refused": st.last_refused.as_ref().map(|r| &r.words),
        "deadman_flag_pressed": deadman,
        // Per target sent (µs): the sample's age when it left (capture → on the wire) and the
        // protocol wait (published → on the wire).
        "latency_us": st.latency,
    });
    v.to_string() + "\n"
}

pub(super) async fn robot(
    State(s): Shared,
    axum::Extension(conn): axum::Extension<ConnInfo>,
    uri: Uri,
    headers: axum::http::HeaderMap,
) -> Response {
    // Requests that make the robot safer are never refused by the sign-in or its throttle: a
    // stop must work while someone is guessing passwords (docs/security.md).
    let safe = is_safe_direction(uri.path(), uri.query());
    if !safe
        && s.control.allowed
        && let Err(r) = s.auth.authorize(&headers, conn.peer.ip()).await
    {
        return s.refusal(r);
    }
    control(uri.path(), uri.query(), &s.control, safe)
}

/// Whether a control request only ever makes the robot safer: disable, hold, deadman released.
pub fn is_safe_direction(path: &str, query: Option<&str>) -> bool {
    match path {
        "/robot/disable" | "/robot/hold" => true,
        "/robot/deadman" => matches!(deadman_query(query), Some("0" | "false")),
        _ => false,
    }
}

fn deadman_query(query: Option<&str>) -> Option<&str> {
    query
        .into_iter()
        .flat_map(|q| q.split('&'))
        .find_map(|kv| kv.strip_prefix("pressed="))
}

impl StatusService {
    /// The answer to a refused sign-in; throttled ones are counted in `/metrics`.
    pub(super) fn refusal(&self, r: super::auth::Refusal) -> Response {
        if matches!(r, super::auth::Refusal::Paused { .. }) {
            self.status
                .net
                .signin_throttled
                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        }
        r.response()
    }
}

/// Answers a `POST /robot/...` request.
/// `safe`: a safe-direction request, answered whenever a robot link exists.
fn control(path: &str, query: Option<&str>, ctl: &RobotControl, safe: bool) -> Response {
    if !ctl.allowed && !safe {
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
            .map(irtrack_robot::deadman::Deadman::pressed)
    };
    match path {
        "/robot/enable" => link.enable(),
        "/robot/disable" | "/robot/hold" => link.disable(),
        "/robot/deadman" => {
            let Some(flag) = &ctl.deadman_flag else {
                return text(
                    StatusCode::CONFLICT,
                    "the deadman is not the software flag ([robot.deadman] kind = \"flag\")\n",
                );
            };
            match deadman_query(query) {
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
                "not found; try /robot/enable, /robot/disable, /robot/hold or /robot/deadman?pressed=1|0\n",
            );
        }
    }
    tracing::info!(request = path, "robot control request");
    json_text(StatusCode::OK, link_json(&link, flag_state(ctl)))
}
