//! Parameter endpoint (default port 7701), protocol `irtrack_core::param_wire`: one push per
//! connection, answered with one verdict line (docs/param-protocol.md).
//!
//! Bounds: at most [`PARAMS_LIMITS`] connections at once (per listener and per client
//! address; over that a connection gets a best-effort `ERR BUSY` and is closed at once, counted
//! in `/metrics`), the whole push within [`READ_TIMEOUT`], and a blob buffer that grows only as
//! bytes arrive (an announced megabyte that never comes costs nothing). After an answer given
//! before the whole body arrived (`TOO_LARGE`) the rest is read and discarded for at most
//! [`DRAIN_TIMEOUT`] / [`DRAIN_MAX_BYTES`], so the close does not reset the verdict away.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use irtrack_core::param_wire::{
    MAX_BLOB_BYTES, PUSH_FLAGS_LEN, PUSH_HEADER_LEN, PushOptions, RejectCode, Verdict, parse_push_head,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use super::limit::{ConnLimiter, PARAMS_LIMITS};
use crate::params::ParamService;

/// A client must deliver its whole push within this time (stops idle connections hogging).
pub const READ_TIMEOUT: Duration = Duration::from_secs(10);
/// How long the rest of a refused upload is read and discarded before closing.
pub const DRAIN_TIMEOUT: Duration = Duration::from_secs(2);
/// How much of a refused upload is read and discarded at most.
pub const DRAIN_MAX_BYTES: u64 = 2 * MAX_BLOB_BYTES as u64;
/// The verdict write may take this long (a client that does not read is dropped).
const WRITE_TIMEOUT: Duration = Duration::from_secs(2);

/// Serves with the default caps ([`PARAMS_LIMITS`]), counting in the service's status.
pub async fn serve(listener: TcpListener, service: Arc<ParamService>, shutdown: impl Future<Output = ()>) {
    let limiter = ConnLimiter::new(PARAMS_LIMITS, service.status().net.params.clone());
    serve_limited(listener, service, limiter, shutdown).await;
}

/// Accepts pushes until `shutdown` resolves, within `limiter`'s caps.
pub async fn serve_limited(
    listener: TcpListener,
    service: Arc<ParamService>,
    limiter: Arc<ConnLimiter>,
    shutdown: impl Future<Output = ()>,
) {
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let permit = match limiter.admit(peer.ip()) {
                        Ok(p) => p,
                        Err(over) => {
                            limiter.log_refusal("params", over);
                            // Best effort, never waiting: the slot is not ours to hold.
                            let busy = Verdict::Rejected {
                                code: RejectCode::Busy,
                                message: "too many pushes at once; try again shortly".into(),
                            };
                            let _ = stream.try_write(busy.to_line().as_bytes());
                            drop(stream);
                            continue;
                        }
                    };
                    let service = service.clone();
                    let limiter = limiter.clone();
                    tokio::spawn(async move {
                        let _permit = permit;
                        let (verdict, timed_out) = handle(stream, service).await;
                        if timed_out {
                            limiter
                                .counters()
                                .timeouts
                                .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        }
                        tracing::info!(%peer, verdict = %verdict.trim_end(), "parameter push");
                    });
                }
                Err(e) => {
                    tracing::warn!(error = %e, "parameter endpoint accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
}

/// How a push's reading ended when it did not deliver a blob.
struct Refused {
    verdict: Verdict,
    /// The body was not read to its end: drain before closing.
    drain: bool,
}

async fn handle(mut stream: TcpStream, service: Arc<ParamService>) -> (String, bool) {
    let framing_error = |v: Verdict| {
        service.note_rejection(&v);
        v
    };
    let mut drain = false;
    let mut timed_out = false;
    let verdict = match tokio::time::timeout(READ_TIMEOUT, read_push(&mut stream)).await {
        Err(_) => {
            timed_out = true;
            framing_error(Verdict::Rejected {
                code: RejectCode::Protocol,
                message: format!("push not received within {} s", READ_TIMEOUT.as_secs()),
            })
        }
        Ok(Err(r)) => {
            drain = r.drain;
            framing_error(r.verdict)
        }
        Ok(Ok((blob, options))) => tokio::task::spawn_blocking(move || service.push_with(&blob, options))
            .await
            .unwrap_or_else(|e| Verdict::Rejected {
                code: RejectCode::Internal,
                message: format!("push handler failed: {e}"),
            }),
    };
    let line = verdict.to_line();
    let _ = tokio::time::timeout(WRITE_TIMEOUT, stream.write_all(line.as_bytes())).await;
    if drain {
        // The client may still be sending the body it announced: take it (bounded), so the
        // close is a clean FIN and the verdict reaches the client (docs/param-protocol.md).
        let _ = stream.shutdown().await;
        let mut sink = tokio::io::sink();
        let mut rest = (&mut stream).take(DRAIN_MAX_BYTES);
        let _ = tokio::time::timeout(DRAIN_TIMEOUT, tokio::io::copy(&mut rest, &mut sink)).await;
    } else {
        let _ = stream.shutdown().await;
    }
    (line, timed_out)
}

/// Reads one request (`IRPP`, or `IRPF` with its flags word): the blob and what it asks.
async fn read_push(stream: &mut TcpStream) -> Result<(Vec<u8>, PushOptions), Refused> {
    let closed = |what: &str, e: std::io::Error| Refused {
        verdict: Verdict::Rejected {
            code: RejectCode::Protocol,
            message: format!("connection ended while reading the {what}: {e}"),
        },
        drain: false,
    };
    let mut hdr = [0u8; PUSH_HEADER_LEN];
    stream
        .read_exact(&mut hdr)
        .await
        .map_err(|e| closed("push header", e))?;
    let head = parse_push_head(&hdr).map_err(|e| {
        let verdict = Verdict::from_error(&e);
        let drain = matches!(
            &verdict,
            Verdict::Rejected {
                code: RejectCode::TooLarge,
                ..
            }
        );
        Refused { verdict, drain }
    })?;
    let len = head.blob_len;
    let mut options = PushOptions::default();
    if head.has_flags {
        let mut flags = [0u8; PUSH_FLAGS_LEN];
        stream
            .read_exact(&mut flags)
            .await
            .map_err(|e| closed("request flags", e))?;
        // Unknown flags: refused before the body, which is then drained like TOO_LARGE's.
        options = PushOptions::from_flags(u32::from_le_bytes(flags)).map_err(|e| Refused {
            verdict: Verdict::from_error(&e),
            drain: true,
        })?;
    }
    // Grows as bytes arrive, not by what the header announced.
    let mut blob = Vec::with_capacity(len.min(64 * 1024));
    let got = (&mut *stream)
        .take(len as u64)
        .read_to_end(&mut blob)
        .await
        .map_err(|e| closed("blob", e))?;
    if got < len {
        return Err(closed(
            "blob",
            std::io::Error::new(std::io::ErrorKind::UnexpectedEof, format!("{got} of {len} bytes")),
        ));
    }
    Ok((blob, options))
}
