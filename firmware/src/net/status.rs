//! Status endpoint (default port 7704): `GET /status` (JSON) and `GET /metrics` (Prometheus
//! text). A deliberately tiny HTTP/1.1 server: one request per connection, bounded header size.
//!
//! With `[service] control = true` it also accepts `POST /robot/enable`, `POST /robot/disable`
//! and `POST /robot/deadman?pressed=1|0` (software deadman flag). These move the robot, so they
//! are refused (403) unless the config opts in; see docs/security.md.

use std::future::Future;
use std::sync::{Arc, Weak};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::robot::client::LinkState;
use crate::robot::{RobotLink, TcpRobotLink};
use crate::status::SharedStatus;

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

const MAX_REQUEST_BYTES: usize = 8 * 1024;
const READ_TIMEOUT: Duration = Duration::from_secs(5);

pub async fn serve(listener: TcpListener, status: Arc<SharedStatus>, shutdown: impl Future<Output = ()>) {
    serve_with_control(listener, status, RobotControl::default(), shutdown).await;
}

/// Like [`serve`], plus the robot control requests.
pub async fn serve_with_control(
    listener: TcpListener,
    status: Arc<SharedStatus>,
    control: RobotControl,
    shutdown: impl Future<Output = ()>,
) {
    let control = Arc::new(control);
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _peer)) => {
                    let (status, control) = (status.clone(), control.clone());
                    tokio::spawn(async move { handle(stream, &status, &control).await });
                }
                Err(e) => {
                    tracing::warn!(error = %e, "status accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
}

/// Reads up to the end of the request head.
async fn read_head(stream: &mut TcpStream) -> Option<String> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    while !buf.windows(4).any(|w| w == b"\r\n\r\n") && !buf.windows(2).any(|w| w == b"\n\n") {
        if buf.len() > MAX_REQUEST_BYTES {
            return None;
        }
        let n = stream.read(&mut chunk).await.ok()?;
        if n == 0 {
            break;
        }
        buf.extend_from_slice(&chunk[..n]);
    }
    String::from_utf8(buf).ok()
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

/// Answers a `POST /robot/...` request.
fn control(path: &str, query: Option<&str>, ctl: &RobotControl) -> (u16, &'static str, String) {
    if !ctl.allowed {
        return (
            403,
            "text/plain",
            "robot control is disabled; set `[service] control = true` to allow it\n".into(),
        );
    }
    let Some(link) = ctl.link.as_ref().and_then(Weak::upgrade) else {
        return (
            409,
            "text/plain",
            "no robot link: the config has no [robot] section\n".into(),
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
                return (
                    409,
                    "text/plain",
                    "the deadman is not the software flag ([robot.deadman] kind = \"flag\")\n".into(),
                );
            };
            let pressed = query
                .into_iter()
                .flat_map(|q| q.split('&'))
                .find_map(|kv| kv.strip_prefix("pressed="));
            match pressed {
                Some("1" | "true") => flag.set(true),
                Some("0" | "false") => flag.set(false),
                _ => return (400, "text/plain", "expected ?pressed=1 or ?pressed=0\n".into()),
            }
        }
        "/robot" => {}
        _ => {
            return (
                404,
                "text/plain",
                "not found; try /robot/enable, /robot/disable or /robot/deadman?pressed=1|0\n".into(),
            );
        }
    }
    tracing::info!(request = path, "robot control request");
    (200, "application/json", link_json(&link, flag_state(ctl)))
}

async fn handle(mut stream: TcpStream, status: &SharedStatus, ctl: &RobotControl) {
    let head = tokio::time::timeout(READ_TIMEOUT, read_head(&mut stream))
        .await
        .ok()
        .flatten();
    let (code, ctype, body) = match head.as_deref().and_then(|h| h.lines().next()) {
        None => (400, "text/plain", "bad request\n".to_string()),
        Some(line) => {
            let mut parts = line.split_whitespace();
            let method = parts.next();
            let target = parts.next();
            let query = target.and_then(|t| t.split_once('?')).map(|(_, q)| q);
            match (method, target.map(|p| p.split('?').next().unwrap_or(p))) {
                (Some("GET"), Some("/status")) => match serde_json::to_string_pretty(&status.report()) {
                    Ok(json) => (200, "application/json", json + "\n"),
                    Err(e) => (500, "text/plain", format!("status encoding failed: {e}\n")),
                },
                (Some("GET"), Some("/metrics")) => (200, "text/plain; version=0.0.4", status.prometheus()),
                (Some("GET"), Some(_)) => (404, "text/plain", "not found; try /status or /metrics\n".into()),
                (Some("POST"), Some(path)) if path.starts_with("/robot") => control(path, query, ctl),
                _ => (
                    405,
                    "text/plain",
                    "only GET (and POST /robot/... for control) is supported\n".into(),
                ),
            }
        }
    };
    let reason = match code {
        200 => "OK",
        400 => "Bad Request",
        403 => "Forbidden",
        404 => "Not Found",
        405 => "Method Not Allowed",
        409 => "Conflict",
        _ => "Internal Server Error",
    };
    let head = format!(
        "HTTP/1.1 {code} {reason}\r\nContent-Type: {ctype}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    let _ = stream.write_all(head.as_bytes()).await;
    let _ = stream.write_all(body.as_bytes()).await;
    let _ = stream.shutdown().await;
}
