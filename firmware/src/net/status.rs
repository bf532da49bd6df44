//! Status endpoint (default port 7704): `GET /status` (JSON) and `GET /metrics` (Prometheus
//! text). A deliberately tiny HTTP/1.1 server: one request per connection, bounded header size.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::status::SharedStatus;

const MAX_REQUEST_BYTES: usize = 8 * 1024;
const READ_TIMEOUT: Duration = Duration::from_secs(5);

pub async fn serve(listener: TcpListener, status: Arc<SharedStatus>, shutdown: impl Future<Output = ()>) {
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _peer)) => {
                    let status = status.clone();
                    tokio::spawn(async move { handle(stream, &status).await });
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

async fn handle(mut stream: TcpStream, status: &SharedStatus) {
    let head = tokio::time::timeout(READ_TIMEOUT, read_head(&mut stream))
        .await
        .ok()
        .flatten();
    let (code, ctype, body) = match head.as_deref().and_then(|h| h.lines().next()) {
        None => (400, "text/plain", "bad request\n".to_string()),
        Some(line) => {
            let mut parts = line.split_whitespace();
            match (
                parts.next(),
                parts.next().map(|p| p.split('?').next().unwrap_or(p)),
            ) {
                (Some("GET"), Some("/status")) => match serde_json::to_string_pretty(&status.report()) {
                    Ok(json) => (200, "application/json", json + "\n"),
                    Err(e) => (500, "text/plain", format!("status encoding failed: {e}\n")),
                },
                (Some("GET"), Some("/metrics")) => (200, "text/plain; version=0.0.4", status.prometheus()),
                (Some("GET"), Some(_)) => (404, "text/plain", "not found; try /status or /metrics\n".into()),
                _ => (405, "text/plain", "only GET is supported\n".into()),
            }
        }
    };
    let reason = match code {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
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
