//! ptp4l's own view of the clock in `/status` (`clock.ptp`): a management client on ptp4l's
//! Unix socket, polled about once a second by a task of its own, off the frame path.
//!
//! The client binds a datagram socket of its own (ptp4l answers to the sender's address) in
//! irtrackd's runtime directory (`RUNTIME_DIRECTORY`, `/run/irtrackd` under systemd; else the
//! temp dir). It asks ptp4l's read-only socket `/var/run/ptp4lro` (linuxptp ≥ 4.0, mode 0666:
//! GETs only) when it exists, else the main `/var/run/ptp4l`, unless `[clock] ptp4l_socket`
//! names one.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::net::UnixDatagram;

use super::mgmt::{
    CurrentDataSet, GET_LEN, MAX_REPLY_LEN, ManagementId, PortDataSet, PortIdentity, PtpError, Reply,
    TimeStatus, clock_identity_text, encode_get, parse_reply,
};

/// ptp4l's read-only management socket (linuxptp 4.x default `uds_ro_address`).
pub const RO_SOCKET: &str = "/var/run/ptp4lro";
/// ptp4l's management socket (default `uds_address`).
pub const RW_SOCKET: &str = "/var/run/ptp4l";
/// How long one GET waits for its answer.
pub const REPLY_TIMEOUT: Duration = Duration::from_millis(300);
/// Time between polls.
pub const POLL_INTERVAL: Duration = Duration::from_secs(1);

/// The server socket to ask: the configured one, else the read-only socket when ptp4l made it.
pub fn server_socket(configured: Option<&Path>) -> PathBuf {
    match configured {
        Some(p) => p.to_path_buf(),
        None if Path::new(RO_SOCKET).exists() => PathBuf::from(RO_SOCKET),
        None => PathBuf::from(RW_SOCKET),
    }
}

/// Where the client's own socket goes: systemd's `RUNTIME_DIRECTORY` (first entry), else the
/// temp dir.
pub fn client_dir() -> PathBuf {
    std::env::var_os("RUNTIME_DIRECTORY")
        .and_then(|v| {
            let s = v.to_string_lossy().into_owned();
            s.split(':').next().filter(|p| !p.is_empty()).map(PathBuf::from)
        })
        .unwrap_or_else(std::env::temp_dir)
}

/// What one poll read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PtpSnapshot {
    /// CURRENT_DATA_SET.
    pub current: CurrentDataSet,
    /// PORT_DATA_SET of the first port answering.
    pub port: PortDataSet,
    /// TIME_STATUS_NP.
    pub time_status: TimeStatus,
}

/// A management client bound to a socket of its own (removed on drop).
pub struct PtpClient {
    sock: UnixDatagram,
    own: PathBuf,
    server: PathBuf,
    domain: u8,
    identity: PortIdentity,
    sequence: u16,
}

static CLIENTS: AtomicU32 = AtomicU32::new(0);

impl PtpClient {
    /// Binds `dir/irtrackd-ptp-<pid>-<n>.sock` to ask `server` (PTP domain `domain`). Must be
    /// called inside a tokio runtime.
    pub fn open(dir: &Path, server: &Path, domain: u8) -> Result<Self, PtpError> {
        let pid = std::process::id();
        let n = CLIENTS.fetch_add(1, Ordering::Relaxed);
        let own = dir.join(format!("irtrackd-ptp-{pid}-{n}.sock"));
        // A socket left by an earlier process of the same pid (after a crash) is in the way.
        let _ = std::fs::remove_file(&own);
        let sock = UnixDatagram::bind(&own).map_err(|source| PtpError::Io {
            what: "binding the PTP management client socket",
            path: own.display().to_string(),
            source,
        })?;
        Ok(PtpClient {
            sock,
            own,
            server: server.to_path_buf(),
            domain,
            identity: PortIdentity::local_client(pid as u16),
            sequence: 0,
        })
    }

    /// The server socket asked.
    pub fn server(&self) -> &Path {
        &self.server
    }

    /// One GET and its answer; replies to earlier requests (late ones) are skipped.
    pub async fn get(&mut self, id: ManagementId) -> Result<Reply, PtpError> {
        self.sequence = self.sequence.wrapping_add(1);
        let mut req = [0u8; GET_LEN];
        encode_get(&mut req, id, self.sequence, self.domain, self.identity);
        let path = || self.server.display().to_string();
        self.sock
            .send_to(&req, &self.server)
            .await
            .map_err(|source| PtpError::Io {
                what: "sending to ptp4l at",
                path: path(),
                source,
            })?;
        let deadline = tokio::time::Instant::now() + REPLY_TIMEOUT;
        let mut buf = [0u8; MAX_REPLY_LEN];
        loop {
            let n = match tokio::time::timeout_at(deadline, self.sock.recv(&mut buf)).await {
                Err(_) => {
                    return Err(PtpError::Timeout {
                        path: path(),
                        asked: id.name(),
                        timeout_ms: REPLY_TIMEOUT.as_millis() as u64,
                    });
                }
                Ok(r) => r.map_err(|source| PtpError::Io {
                    what: "reading ptp4l's answer from",
                    path: path(),
                    source,
                })?,
            };
            match parse_reply(&buf[..n], id, self.sequence) {
                Err(PtpError::Stale { .. }) => continue,
                other => return other,
            }
        }
    }

    /// CURRENT_DATA_SET, PORT_DATA_SET and TIME_STATUS_NP.
    pub async fn poll(&mut self) -> Result<PtpSnapshot, PtpError> {
        let unexpected = |what: &'static str| PtpError::Value { what, value: 0 };
        let Reply::Current(current) = self.get(ManagementId::CurrentDataSet).await? else {
            return Err(unexpected("reply kind to CURRENT_DATA_SET"));
        };
        let Reply::Port(port) = self.get(ManagementId::PortDataSet).await? else {
            return Err(unexpected("reply kind to PORT_DATA_SET"));
        };
        let Reply::TimeStatus(time_status) = self.get(ManagementId::TimeStatusNp).await? else {
            return Err(unexpected("reply kind to TIME_STATUS_NP"));
        };
        Ok(PtpSnapshot {
            current,
            port,
            time_status,
        })
    }
}

impl Drop for PtpClient {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.own);
    }
}

/// One poll of ptp4l at `server` from a client socket in `dir` (tests, tools).
pub async fn query(dir: &Path, server: &Path, domain: u8) -> Result<PtpSnapshot, PtpError> {
    PtpClient::open(dir, server, domain)?.poll().await
}

/// The monitor's state, shared with `/status`.
#[derive(Debug, Default)]
pub struct PtpState {
    server: String,
    last: Option<(PtpSnapshot, Instant)>,
    error: Option<String>,
    polls: u64,
    failures: u64,
}

/// Shared handle on the monitor's state.
pub type SharedPtp = Arc<Mutex<PtpState>>;

/// `clock.ptp` on `/status`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PtpReport {
    /// The ptp4l socket asked.
    pub socket: String,
    /// The port's state (`SLAVE`, `MASTER`, `UNCALIBRATED`, `LISTENING`, …), from the last
    /// good answer.
    pub port_state: Option<&'static str>,
    /// ptp4l's offset from the master, ns (currentDS.offsetFromMaster; 0 on the master).
    pub offset_ns: Option<f64>,
    /// Mean path delay to the master, ns.
    pub mean_path_delay_ns: Option<f64>,
    /// Boundary clocks to the grandmaster.
    pub steps_removed: Option<u16>,
    /// A grandmaster is known.
    pub gm_present: Option<bool>,
    /// The grandmaster's clock identity.
    pub gm_identity: Option<String>,
    /// Age of the last good answer, ms.
    pub age_ms: Option<u64>,
    /// Why the latest poll failed (ptp4l absent, not answering, a malformed reply); `None`
    /// when it succeeded.
    pub error: Option<String>,
    /// Polls since start.
    pub polls: u64,
    /// Polls that failed.
    pub failures: u64,
}

impl PtpState {
    /// The report as of now.
    pub fn report(&self) -> PtpReport {
        let snap = self.last.as_ref().map(|(s, _)| s);
        PtpReport {
            socket: self.server.clone(),
            port_state: snap.map(|s| s.port.state.name()),
            offset_ns: snap.map(|s| s.current.offset_from_master_ns),
            mean_path_delay_ns: snap.map(|s| s.current.mean_path_delay_ns),
            steps_removed: snap.map(|s| s.current.steps_removed),
            gm_present: snap.map(|s| s.time_status.gm_present),
            gm_identity: snap.map(|s| clock_identity_text(&s.time_status.gm_identity)),
            age_ms: self.last.as_ref().map(|(_, t)| t.elapsed().as_millis() as u64),
            error: self.error.clone(),
            polls: self.polls,
            failures: self.failures,
        }
    }

    fn record(&mut self, server: &Path, result: Result<PtpSnapshot, String>) {
        self.server = server.display().to_string();
        self.polls += 1;
        match result {
            Ok(s) => {
                self.last = Some((s, Instant::now()));
                self.error = None;
            }
            Err(e) => {
                self.failures += 1;
                self.error = Some(e);
            }
        }
    }
}

/// `/metrics` families of `clock.ptp` (a `prometheus-client` collector over one report).
/// The offset and delay are those of ptp4l's last good answer; `irtrackd_ptp_answer_age_seconds`
/// says how old that is, so an alert can tell a stale value from a good one.
impl prometheus_client::collector::Collector for PtpReport {
    fn encode(
        &self,
        mut enc: prometheus_client::encoding::DescriptorEncoder,
    ) -> std::result::Result<(), std::fmt::Error> {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::MetricType;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        // Counter names without `_total`: the encoder appends it.
        for (name, help, value) in [
            ("irtrackd_ptp_polls", "ptp4l management polls", self.polls),
            (
                "irtrackd_ptp_poll_failures",
                "ptp4l polls without a good answer (absent, silent, malformed)",
                self.failures,
            ),
        ] {
            let m = enc.encode_descriptor(name, help, None, MetricType::Counter)?;
            ConstCounter::new(value).encode(m)?;
        }
        let gauges = [
            (
                "irtrackd_ptp_offset_seconds",
                "ptp4l's offset from its master (0 on the master)",
                self.offset_ns.map(|ns| ns / 1e9),
            ),
            (
                "irtrackd_ptp_mean_path_delay_seconds",
                "ptp4l's mean path delay to its master",
                self.mean_path_delay_ns.map(|ns| ns / 1e9),
            ),
            (
                "irtrackd_ptp_steps_removed",
                "boundary clocks between this board and the grandmaster",
                self.steps_removed.map(f64::from),
            ),
            (
                "irtrackd_ptp_grandmaster_present",
                "1 when ptp4l knows a grandmaster",
                self.gm_present.map(|p| if p { 1.0 } else { 0.0 }),
            ),
            (
                "irtrackd_ptp_answer_age_seconds",
                "age of ptp4l's last good answer",
                self.age_ms.map(|ms| ms as f64 / 1e3),
            ),
        ];
        for (name, help, value) in gauges {
            if let Some(v) = value {
                let m = enc.encode_descriptor(name, help, None, MetricType::Gauge)?;
                ConstGauge::new(v).encode(m)?;
            }
        }
        if let Some(state) = self.port_state {
            let mut m = enc.encode_descriptor(
                "irtrackd_ptp_port_state",
                "ptp4l's port state (the one present is 1)",
                None,
                MetricType::Gauge,
            )?;
            ConstGauge::new(1i64).encode(m.encode_family(&[("state", state)])?)?;
        }
        Ok(())
    }
}

/// Words for a failed poll, with the likely cause.
fn explain(e: &PtpError) -> String {
    let hint = match e {
        PtpError::Io { source, .. } => match source.kind() {
            std::io::ErrorKind::NotFound => {
                " — no ptp4l socket there: is ptp4l running (irtrack-ptp4l.service)?"
            }
            std::io::ErrorKind::ConnectionRefused => " — the socket is left over: ptp4l is not running",
            std::io::ErrorKind::PermissionDenied => {
                " — irtrackd may not write ptp4l's socket (linuxptp < 4.0 has no read-only socket; set [clock] ptp4l_socket)"
            }
            _ => "",
        },
        PtpError::Timeout { .. } => " — ptp4l is not answering (wrong [clock] domain?)",
        _ => "",
    };
    format!("{e}{hint}")
}

/// Polls ptp4l until `shutdown` resolves, keeping `state` up to date (the last good answer
/// stays with its age when a poll fails). `socket`: `[clock] ptp4l_socket`.
pub async fn run(
    state: SharedPtp,
    socket: Option<PathBuf>,
    domain: u8,
    shutdown: impl std::future::Future<Output = ()>,
) {
    tokio::pin!(shutdown);
    let dir = client_dir();
    let mut client: Option<PtpClient> = None;
    loop {
        let server = server_socket(socket.as_deref());
        // Re-open when the server path changes (ptp4l started after irtrackd, 4.x's read-only
        // socket appearing).
        if client.as_ref().is_some_and(|c| c.server() != server) {
            client = None;
        }
        let result = match &mut client {
            Some(c) => c.poll().await,
            None => match PtpClient::open(&dir, &server, domain) {
                Ok(mut c) => {
                    let r = c.poll().await;
                    client = Some(c);
                    r
                }
                Err(e) => Err(e),
            },
        };
        let result = result.map_err(|e| explain(&e));
        if let Err(e) = &result
            && state
                .lock()
                .map(|s| s.error.as_deref() != Some(e.as_str()))
                .unwrap_or(true)
        {
            tracing::warn!(error = %e, "PTP status");
        }
        if let Ok(mut s) = state.lock() {
            s.record(&server, result);
        }
        tokio::select! {
            _ = &mut shutdown => return,
            _ = tokio::time::sleep(POLL_INTERVAL) => {}
        }
    }
}
