//! Position stream (NDJSON on 7702, binary framing on 7703) for any number of clients.
//!
//! The processing loop only ever writes the latest-value slot. A distributor task copies each
//! new record into a broadcast ring of `client_queue_records` entries; every client task reads
//! the ring at its own pace. A client that falls a whole ring behind, or whose socket does not
//! take a write within [`WRITE_TIMEOUT`], is disconnected and counted as dropped: one slow
//! reader can delay nobody but itself.
//!
//! Per-tool records (docs/stream-protocol.md): a client that sends the line `tools\n` gets,
//! from then on, before each main record the records of every tool of the set (NDJSON lines
//! with `tool_id`/`tool`, or `IRTL` binary frames), then one record per loose single LED with
//! its stable id (NDJSON lines with `loose_id`, or `IRLL` binary frames). Clients that send
//! nothing get exactly the main records as before, so existing readers keep working.

use std::future::Future;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use irtrack_core::stream::{BINARY_FRAME_LEN, LOOSE_BINARY_FRAME_LEN, PositionRecord, TOOL_BINARY_FRAME_LEN};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{broadcast, watch};

use crate::engine::ToolSet;
use crate::status::SharedStatus;

/// What a client asks for by sending this line: per-tool records as well.
pub const TOOLS_REQUEST: &[u8] = b"tools\n";

/// One set in the broadcast ring: the main record and, in 6-DOF mode, every tool's record.
#[derive(Debug, Clone, Copy)]
pub struct StreamItem {
    /// The set's position record, as the loop published it (what every client gets).
    pub main: PositionRecord,
    /// Every tool's and loose LED's record, in 6-DOF mode; sent to clients that asked with
    /// [`TOOLS_REQUEST`].
    pub tools: Option<ToolSet>,
}

/// A client whose socket accepts nothing for this long is dropped.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(2);

/// Wire format of a stream port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamFormat {
    /// Newline-delimited JSON, one record per line (docs/stream-protocol.md).
    Ndjson,
    /// Fixed-size binary frames (docs/stream-protocol.md).
    Binary,
}

/// Fan-out point shared by both stream ports.
#[derive(Debug, Clone)]
pub struct StreamHub {
    tx: broadcast::Sender<StreamItem>,
    status: Arc<SharedStatus>,
    /// Clients served at once over both ports; more are closed at once and counted.
    max_clients: u64,
}

/// Default for [`StreamHub::with_max_clients`] (`listen.max_stream_clients`).
pub const DEFAULT_MAX_CLIENTS: u64 = 32;

impl StreamHub {
    /// Starts the distributor task reading `slot`; it ends when the slot's sender is dropped.
    pub fn start(
        slot: watch::Receiver<Option<PositionRecord>>,
        queue_records: usize,
        status: Arc<SharedStatus>,
    ) -> Self {
        Self::start_with_tools(slot, None, queue_records, status)
    }

    /// [`StreamHub::start`], also carrying the per-tool records of `tools` (the engine's
    /// tool slot, written just before the main record of the same set).
    pub fn start_with_tools(
        mut slot: watch::Receiver<Option<PositionRecord>>,
        tools: Option<watch::Receiver<ToolSet>>,
        queue_records: usize,
        status: Arc<SharedStatus>,
    ) -> Self {
        let (tx, _) = broadcast::channel(queue_records.max(1));
        let hub = Self {
            tx: tx.clone(),
            status: status.clone(),
            max_clients: DEFAULT_MAX_CLIENTS,
        };
        tokio::spawn(async move {
            let mut received = 0u64;
            while slot.changed().await.is_ok() {
                let rec = *slot.borrow_and_update();
                if let Some(rec) = rec {
                    received += 1;
                    // Results the loop published that this task never saw were overwritten.
                    let published = status.published.load(Ordering::Relaxed);
                    status
                        .slot_overwrites
                        .store(published.saturating_sub(received), Ordering::Relaxed);
                    // The engine writes a set's tool records before its main record, so the
                    // tool slot holds this frame's (or a newer one's: then none are sent).
                    let tools = tools
                        .as_ref()
                        .map(|t| *t.borrow())
                        .filter(|t| t.frame == rec.frame);
                    // No subscribers is fine: nothing to deliver.
                    let _ = tx.send(StreamItem { main: rec, tools });
                }
            }
        });
        hub
    }

    /// Sets the limit of clients served at once (both ports together).
    pub fn with_max_clients(mut self, max_clients: u64) -> Self {
        self.max_clients = max_clients.max(1);
        self
    }

    /// A receiver of every set published from now on (a slow one loses the oldest).
    pub fn subscribe(&self) -> broadcast::Receiver<StreamItem> {
        self.tx.subscribe()
    }
}

/// Accepts stream clients until `shutdown` resolves.
pub async fn serve(
    listener: TcpListener,
    format: StreamFormat,
    hub: StreamHub,
    shutdown: impl Future<Output = ()>,
) {
    let counters = match format {
        StreamFormat::Ndjson => hub.status.net.stream_ndjson.clone(),
        StreamFormat::Binary => hub.status.net.stream_binary.clone(),
    };
    let limiter = super::limit::ConnLimiter::new(super::limit::STREAM_LIMITS, counters);
    let label = match format {
        StreamFormat::Ndjson => "stream_ndjson",
        StreamFormat::Binary => "stream_binary",
    };
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            _ = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, peer)) => {
                    // Per port and per client address first (a client never sends anything,
                    // so holding a slot costs a descriptor and a queue cursor, no more).
                    let permit = match limiter.admit(peer.ip()) {
                        Ok(p) => p,
                        Err(over) => {
                            limiter.log_refusal(label, over);
                            hub.status.stream_refused.fetch_add(1, Ordering::Relaxed);
                            drop(stream);
                            continue;
                        }
                    };
                    // Only this task and its twin on the other port add clients, so the check
                    // can overshoot by at most one connection per port.
                    if hub.status.stream_clients.load(Ordering::Relaxed) >= hub.max_clients {
                        let refused = hub.status.stream_refused.fetch_add(1, Ordering::Relaxed);
                        if refused.is_multiple_of(1000) {
                            tracing::warn!(%peer, max = hub.max_clients, refused = refused + 1, "stream client limit reached; connection closed");
                        }
                        drop(stream);
                        continue;
                    }
                    let _ = stream.set_nodelay(true);
                    limit_send_buffer(&stream, CLIENT_SNDBUF_BYTES);
                    let rx = hub.subscribe();
                    let status = hub.status.clone();
                    status.stream_clients.fetch_add(1, Ordering::Relaxed);
                    status.stream_clients_total.fetch_add(1, Ordering::Relaxed);
                    tracing::info!(%peer, ?format, "stream client connected");
                    tokio::spawn(async move {
                        let _permit = permit;
                        let end = client(stream, format, rx, &status).await;
                        status.stream_clients.fetch_sub(1, Ordering::Relaxed);
                        match end {
                            ClientEnd::TooSlow(why) => {
                                status.stream_dropped_slow.fetch_add(1, Ordering::Relaxed);
                                tracing::warn!(%peer, %why, "stream client too slow; dropped");
                            }
                            ClientEnd::Gone => tracing::info!(%peer, "stream client disconnected"),
                            ClientEnd::Closed => {}
                        }
                    });
                }
                Err(e) => {
                    tracing::warn!(error = %e, "stream accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
        }
    }
}

/// Kernel send buffer per client. Without a limit Linux grows it to megabytes, which would hide
/// a stalled reader for many seconds behind stale data; with it, a reader that stops shows up
/// in our own bounded queue within a fraction of a second.
pub const CLIENT_SNDBUF_BYTES: libc::c_int = 32 * 1024;

/// Sets the kernel send buffer of `stream` to `bytes` (see [`CLIENT_SNDBUF_BYTES`]).
pub(crate) fn limit_send_buffer(stream: &TcpStream, bytes: libc::c_int) {
    use std::os::fd::AsRawFd;
    let v = bytes;
    // SAFETY: valid socket fd owned by `stream`; option value is a c_int of the stated size.
    let rc = unsafe {
        libc::setsockopt(
            stream.as_raw_fd(),
            libc::SOL_SOCKET,
            libc::SO_SNDBUF,
            (&v as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if rc != 0 {
        tracing::debug!(error = %std::io::Error::last_os_error(), "SO_SNDBUF not set");
    }
}

enum ClientEnd {
    TooSlow(String),
    Gone,
    Closed,
}

async fn client(
    stream: TcpStream,
    format: StreamFormat,
    mut rx: broadcast::Receiver<StreamItem>,
    status: &SharedStatus,
) -> ClientEnd {
    let (mut reader, mut writer) = stream.into_split();
    let mut text = String::with_capacity(512);
    let mut bin = [0u8; BINARY_FRAME_LEN];
    let mut tool_bin = [0u8; TOOL_BINARY_FRAME_LEN];
    let mut loose_bin = [0u8; LOOSE_BINARY_FRAME_LEN];
    // What the client sent so far (only `tools\n` means anything; the rest is ignored).
    let mut request = [0u8; 64];
    let mut request_len = 0usize;
    let mut want_tools = false;
    let mut reading = true;
    loop {
        let item = tokio::select! {
            r = rx.recv() => match r {
                Ok(r) => r,
                Err(broadcast::error::RecvError::Lagged(n)) => {
                    return ClientEnd::TooSlow(format!("fell {n} records behind the queue"));
                }
                Err(broadcast::error::RecvError::Closed) => return ClientEnd::Closed,
            },
            n = reader.read(&mut request[request_len..]), if reading => {
                match n {
                    // A half-closed socket still takes records.
                    Ok(0) | Err(_) => reading = false,
                    Ok(n) => {
                        request_len += n;
                        if request[..request_len].windows(TOOLS_REQUEST.len()).any(|w| w == TOOLS_REQUEST) {
                            want_tools = true;
                        }
                        // Keep the tail in case the request is split across reads.
                        if request_len == request.len() {
                            let keep = TOOLS_REQUEST.len() - 1;
                            request.copy_within(request_len - keep.., 0);
                            request_len = keep;
                        }
                    }
                }
                continue;
            }
        };
        if want_tools && let Some(tools) = &item.tools {
            for t in tools.records() {
                let bytes: &[u8] = match format {
                    StreamFormat::Ndjson => {
                        text.clear();
                        t.write_ndjson(&mut text);
                        text.as_bytes()
                    }
                    StreamFormat::Binary => {
                        t.encode_binary(&mut tool_bin);
                        &tool_bin
                    }
                };
                if let Some(end) = write(&mut writer, bytes, status).await {
                    return end;
                }
            }
            for l in tools.loose_records() {
                let bytes: &[u8] = match format {
                    StreamFormat::Ndjson => {
                        text.clear();
                        l.write_ndjson(&mut text);
                        text.as_bytes()
                    }
                    StreamFormat::Binary => {
                        l.encode_binary(&mut loose_bin);
                        &loose_bin
                    }
                };
                if let Some(end) = write(&mut writer, bytes, status).await {
                    return end;
                }
            }
        }
        let rec = item.main;
        let bytes: &[u8] = match format {
            StreamFormat::Ndjson => {
                text.clear();
                rec.write_ndjson(&mut text);
                text.as_bytes()
            }
            StreamFormat::Binary => {
                rec.encode_binary(&mut bin);
                &bin
            }
        };
        if let Some(end) = write(&mut writer, bytes, status).await {
            return end;
        }
    }
}

/// Writes one record; `Some` when the client is to be dropped.
async fn write(
    writer: &mut tokio::net::tcp::OwnedWriteHalf,
    bytes: &[u8],
    status: &SharedStatus,
) -> Option<ClientEnd> {
    match tokio::time::timeout(WRITE_TIMEOUT, writer.write_all(bytes)).await {
        Err(_) => Some(ClientEnd::TooSlow(format!(
            "socket blocked for {} s",
            WRITE_TIMEOUT.as_secs()
        ))),
        Ok(Err(_)) => Some(ClientEnd::Gone),
        Ok(Ok(())) => {
            status.stream_records_sent.fetch_add(1, Ordering::Relaxed);
            None
        }
    }
}
