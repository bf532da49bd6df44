//! Parameter endpoint (default port 7701), protocol `irtrack_core::param_wire`: one push per
//! connection, answered with one verdict line.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use irtrack_core::param_wire::{PUSH_HEADER_LEN, RejectCode, Verdict, parse_push_header};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

use crate::params::ParamService;

/// A client must deliver its whole push within this time (stops idle connections hogging).
pub const READ_TIMEOUT: Duration = Duration::from_secs(10);

pub async fn serve(listener: TcpListener, service: Arc<ParamService>, shutdown: impl Future<Output = ()>) {
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    let service = service.clone();
                    tokio::spawn(async move {
                        let verdict = handle(stream, service).await;
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

async fn handle(mut stream: TcpStream, service: Arc<ParamService>) -> String {
    let framing_error = |v: Verdict| {
        service.note_rejection(&v);
        v
    };
    let verdict = match tokio::time::timeout(READ_TIMEOUT, read_push(&mut stream)).await {
        Err(_) => framing_error(Verdict::Rejected {
            code: RejectCode::Protocol,
            message: format!("push not received within {} s", READ_TIMEOUT.as_secs()),
        }),
        Ok(Err(v)) => framing_error(v),
        Ok(Ok(blob)) => tokio::task::spawn_blocking(move || service.push(&blob))
            .await
            .unwrap_or_else(|e| Verdict::Rejected {
                code: RejectCode::Internal,
                message: format!("push handler failed: {e}"),
            }),
    };
    let line = verdict.to_line();
    let _ = stream.write_all(line.as_bytes()).await;
    let _ = stream.shutdown().await;
    line
}

async fn read_push(stream: &mut TcpStream) -> Result<Vec<u8>, Verdict> {
    let closed = |what: &str, e: std::io::Error| Verdict::Rejected {
        code: RejectCode::Protocol,
        message: format!("connection ended while reading the {what}: {e}"),
    };
    let mut hdr = [0u8; PUSH_HEADER_LEN];
    stream
        .read_exact(&mut hdr)
        .await
        .map_err(|e| closed("push header", e))?;
    let len = parse_push_header(&hdr).map_err(|e| Verdict::from_error(&e))?;
    let mut blob = vec![0u8; len];
    stream
        .read_exact(&mut blob)
        .await
        .map_err(|e| closed("blob", e))?;
    Ok(blob)
}
