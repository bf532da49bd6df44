//! The status listener's routes, limits and accept loop (axum on hyper).
//!
//! Every phase of a connection has a bound (docs/security.md, "Connections"):
//! - connections: at most [`STATUS_LIMITS`] at once per listener and per client address;
//!   over that they are closed right after `accept`, counted in `/metrics`; at the listener
//!   cap a new connection instead closes the oldest unanswered exchange of the address that
//!   holds the most slots (`ConnLimiter::admit_evicting`), so a flood spread over many
//!   addresses cannot keep a fresh `/status` client out;
//! - request head: 8 KiB within [`HEAD_TIMEOUT`] (hyper's header read timeout, which also
//!   covers a connection that never sends anything);
//! - request body: 64 KiB; a body that stops for [`BODY_IDLE_TIMEOUT`] fails (tower-http), and
//!   the handler with its body has [`HANDLER_TIMEOUT`] in all (tower-http); the update upload
//!   (`net::update`) alone has its own size cap and moves its exchange deadline once signed in;
//! - one request per connection (no idle keep-alive), and the whole HTTP exchange, answer
//!   included, within [`HTTP_EXCHANGE_LIMIT`]; a WebSocket keeps its connection and has its own
//!   send and pong timeouts (`live`).
//!
//! Before any handler runs, the Host and Origin rules (`http::check_request`) and, with
//! `[status] public_view = false`, the sign-in for previews, frames and positions apply.
//! Every answer carries the security headers of `http::security_headers`.

use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::Next;
use axum::response::Response;
use axum::routing::{get, post};
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tower::ServiceExt as _;
use tower_http::set_header::SetResponseHeaderLayer;
use tower_http::timeout::{RequestBodyTimeoutLayer, TimeoutLayer};

use super::http::{
    ConnInfo, MAX_REQUEST_BODY_BYTES, check_request, content_security_policy, security_headers,
};
use super::limit::{ConnLimiter, ConnSlot, STATUS_LIMITS};
use super::status::{self as st, StatusService};
use super::update::ExchangeDeadline;
use super::{live, status};
use crate::status::SharedStatus;

/// Largest request head (request line and headers); hyper's smallest allowed buffer.
pub const MAX_REQUEST_HEAD_BYTES: usize = 8 * 1024;
/// Time a client has to send its request head (from the moment it connects).
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(5);
/// A request body that delivers nothing for this long fails.
pub const BODY_IDLE_TIMEOUT: Duration = Duration::from_secs(5);
/// A request, its body read and answered, within this time (408 otherwise).
pub const HANDLER_TIMEOUT: Duration = Duration::from_secs(10);
/// The whole HTTP exchange of one connection, writing the answer included (a client that
/// does not read its answer is dropped then). A WebSocket leaves this phase at its upgrade.
pub const HTTP_EXCHANGE_LIMIT: Duration = Duration::from_secs(30);
/// Kernel send buffer of a status connection: a WebSocket reader that stops shows up as a
/// blocked send within a fraction of a second instead of after megabytes of stale previews.
pub const STATUS_SNDBUF_BYTES: libc::c_int = 64 * 1024;

type Shared = State<Arc<StatusService>>;

impl StatusService {
    /// The HTTP routes with their layers (also usable in-process with `tower::ServiceExt::oneshot`;
    /// a request without a connection then counts as coming from 127.0.0.1).
    pub fn router(self) -> Router {
        let state = Arc::new(self);
        // The bundle upload streams a large body for minutes: outside the body cap and the
        // handler timeout (it keeps the body idle timeout and sets its own exchange deadline).
        let upload = Router::new()
            .route("/api/update", post(super::update::upload))
            .layer(DefaultBodyLimit::disable());
        let mut router = Router::new()
            .route("/", get(st::index))
            .route("/web/{*path}", get(st::asset))
            .route("/status", get(st::status_json))
            .route("/metrics", get(st::metrics))
            .route("/robot", post(st::robot))
            .route("/robot/{*action}", post(st::robot))
            .route("/api/session", get(live::session))
            .route("/api/login", post(live::login))
            .route("/api/logout", post(live::logout))
            .route("/api/tuning", get(live::tuning_get).post(live::tuning_post))
            .route("/api/tuning/save", post(live::tuning_save))
            .route("/api/tuning/suggest", post(super::advice::suggest))
            .route("/api/scene", get(live::scene))
            .route("/api/frameset", get(live::frameset))
            .route("/api/live", get(live::live))
            .fallback(st::fallback)
            .method_not_allowed_fallback(st::fallback)
            .layer(DefaultBodyLimit::max(MAX_REQUEST_BODY_BYTES))
            .layer(TimeoutLayer::with_status_code(
                StatusCode::REQUEST_TIMEOUT,
                HANDLER_TIMEOUT,
            ))
            .merge(upload)
            .layer(axum::middleware::from_fn_with_state(state.clone(), guard))
            .layer(axum::middleware::map_response(one_request_per_connection))
            .layer(RequestBodyTimeoutLayer::new(BODY_IDLE_TIMEOUT));
        let csp = content_security_policy(&st::page_inline_script_hashes());
        for (name, value) in security_headers(&csp) {
            router = router.layer(SetResponseHeaderLayer::if_not_present(name, value));
        }
        router.with_state(state)
    }

    /// Serves `listener` until `shutdown` resolves, with the default caps
    /// ([`STATUS_LIMITS`]); open HTTP connections end then.
    pub async fn serve(self, listener: TcpListener, shutdown: impl Future<Output = ()>) {
        let limiter = ConnLimiter::new(STATUS_LIMITS, self.status.net.status.clone());
        serve_router(listener, self.router(), limiter, shutdown).await;
    }
}

/// Host and Origin rules, then the sign-in for viewing when `public_view = false`.
async fn guard(State(s): Shared, mut req: Request, next: Next) -> Response {
    let conn = match req.extensions().get::<ConnInfo>() {
        Some(c) => *c,
        None => {
            let lo = std::net::SocketAddr::from(([127, 0, 0, 1], 0));
            let c = ConnInfo { peer: lo, local: lo };
            req.extensions_mut().insert(c);
            c
        }
    };
    if req.extensions().get::<ConnSlot>().is_none() {
        req.extensions_mut().insert(ConnSlot::default());
    }
    if let Err(refused) = check_request(&s.hosts, req.method(), req.headers(), conn.local.ip()) {
        tracing::debug!(peer = %conn.peer, ?refused, "request refused by the Host/Origin rules");
        return refused.response();
    }
    let path = req.uri().path();
    if !s.public_view
        && matches!(path, "/api/live" | "/api/frameset")
        && let Err(r) = s.auth.authorize(req.headers(), conn.peer.ip()).await
    {
        return s.refusal(r);
    }
    next.run(req).await
}

/// One request per connection, as before the move to hyper: raw-socket clients read the answer
/// to the end of the stream, and no connection idles between requests. `Connection: close`
/// makes hyper end the connection after the answer; a WebSocket upgrade (101) keeps it (hyper's
/// own keep-alive switch would add `close` to the upgrade answer too, which WebSocket clients
/// reject).
async fn one_request_per_connection(mut resp: Response) -> Response {
    if resp.status() != StatusCode::SWITCHING_PROTOCOLS {
        resp.headers_mut()
            .insert(header::CONNECTION, HeaderValue::from_static("close"));
    }
    resp
}

/// Accept loop with the listener's caps and timeouts; `router` answers every request.
pub async fn serve_router(
    listener: TcpListener,
    router: Router,
    limiter: Arc<ConnLimiter>,
    shutdown: impl Future<Output = ()>,
) {
    let mut conns = tokio::task::JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    // At the cap, the oldest unanswered exchange of the biggest holder makes
                    // room (net::limit): a fresh client is answered during a slot flood.
                    let (permit, evict) = match limiter.admit_evicting(peer.ip()) {
                        Ok((p, evict)) => (Arc::new(p), evict),
                        Err(over) => {
                            limiter.log_refusal("status", over);
                            drop(stream);
                            continue;
                        }
                    };
                    let local = stream.local_addr().unwrap_or(peer);
                    let _ = stream.set_nodelay(true);
                    super::stream::limit_send_buffer(&stream, STATUS_SNDBUF_BYTES);
                    let info = ConnInfo { peer, local };
                    let slot = ConnSlot(Some(permit.clone()));
                    let deadline = ExchangeDeadline::new(HTTP_EXCHANGE_LIMIT);
                    let handler_deadline = deadline.clone();
                    let svc = router.clone().map_request(move |mut req: Request<hyper::body::Incoming>| {
                        req.extensions_mut().insert(info);
                        req.extensions_mut().insert(slot.clone());
                        req.extensions_mut().insert(handler_deadline.clone());
                        req
                    });
                    let svc = TowerToHyperService::new(svc);
                    let limiter = limiter.clone();
                    conns.spawn(async move {
                        let _permit = permit;
                        let mut http = hyper::server::conn::http1::Builder::new();
                        http.timer(TokioTimer::new())
                            .header_read_timeout(HEAD_TIMEOUT)
                            .max_buf_size(MAX_REQUEST_HEAD_BYTES);
                        let conn = http.serve_connection(TokioIo::new(stream), svc).with_upgrades();
                        tokio::pin!(conn);
                        // The exchange's deadline, which an upload may move (net::update).
                        let ended = loop {
                            tokio::select! {
                                r = &mut conn => break Some(r),
                                _ = tokio::time::sleep_until(deadline.at()) => {
                                    if tokio::time::Instant::now() >= deadline.at() {
                                        break None;
                                    }
                                }
                                _ = deadline.moved() => {}
                                _ = evict.notified() => {
                                    tracing::debug!(%peer, "status exchange closed for a fresh client at the cap");
                                    return;
                                }
                            }
                        };
                        match ended {
                            None => {
                                limiter.counters().timeouts.fetch_add(1, Ordering::Relaxed);
                                tracing::debug!(%peer, "status connection timed out");
                            }
                            Some(Err(e)) if e.is_timeout() => {
                                limiter.counters().timeouts.fetch_add(1, Ordering::Relaxed);
                                tracing::debug!(%peer, "status connection sent no request head in time");
                            }
                            Some(Err(e)) => {
                                tracing::debug!(error = %e, "status connection ended with an error");
                            }
                            Some(Ok(())) => {}
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

/// Serves the status endpoints from `status` alone (no robot control, no operator password, no live view) until
/// `shutdown` resolves.
pub async fn serve(listener: TcpListener, status: Arc<SharedStatus>, shutdown: impl Future<Output = ()>) {
    StatusService::new(status).serve(listener, shutdown).await;
}

/// Like [`serve`], plus the robot control requests.
pub async fn serve_with_control(
    listener: TcpListener,
    status: Arc<SharedStatus>,
    control: status::RobotControl,
    shutdown: impl Future<Output = ()>,
) {
    StatusService::new(status)
        .with_control(control)
        .serve(listener, shutdown)
        .await;
}
