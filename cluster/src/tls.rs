//! TLS around the Zenoh links between camera boards and the solver (docs/cluster.md, "TLS:
//! the solver proves itself, the links are encrypted").
//!
//! User/password lets only known boards in, but the board never learns who it talks to, and
//! nothing is encrypted: a man-in-the-middle on the cell network reads the observations and
//! can alter them in a link it relays. With TLS the solver proves itself with its own
//! certificate, which every board pins (the only certificate a board trusts), and every byte
//! between them is encrypted and authenticated. User/password and the access control keep
//! working inside, so each board still proves who it is and publishes only its own cameras.
//!
//! **Why irtrackd terminates TLS itself** instead of using Zenoh's TLS link (`zenoh-link-tls`
//! 1.10.2, read in its source): its accept loop sleeps 100 ms after every failed handshake
//! (`TLS_ACCEPT_THROTTLE_TIME`), so a host sending ten bad handshakes a second keeps every
//! board out; and its client adds the public Web PKI roots to the configured one, so with the
//! name check off any publicly certified server would pass as the solver. Here:
//!
//! - the solver's tunnel accepts TLS on its `listen` address (at most [`MAX_HANDSHAKES`] at
//!   once, each within [`HANDSHAKE_TIMEOUT`]; a failure is counted with its address in
//!   [`crate::refusals`] and costs no pause) and hands the plain stream to its Zenoh, which
//!   listens on 127.0.0.1 only;
//! - a board's tunnel takes its Zenoh's connection on 127.0.0.1 and carries it to the solver
//!   over TLS 1.3, trusting the pinned solver certificate alone (name [`SOLVER_NAME`]); a
//!   solver that cannot prove itself gets nothing (counted in [`board_log`]).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;

use crate::error::{ClusterError, Result};
use crate::refusals::RefusalReason;

pub use crate::names::SOLVER_TLS_NAME as SOLVER_NAME;
/// A TLS handshake must finish within this (a LAN takes milliseconds).
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(1);
/// Handshakes in progress at once on the solver; a connection beyond them is closed at once.
pub const MAX_HANDSHAKES: usize = 500;
/// A board's tunnel gives up reaching the solver after this.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(2);
/// A board logs its tunnel's failures at most this often.
const BOARD_NOTICE_INTERVAL: Duration = Duration::from_secs(10);

/// A node's part in TLS.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TlsRole {
    /// The solver: its certificate (PEM, the one the boards pin) and private key (PEM).
    Solver {
        /// Certificate file.
        certificate_file: PathBuf,
        /// Private key file (mode 0600).
        key_file: PathBuf,
    },
    /// A camera board: the solver's certificate it pins (PEM).
    Board {
        /// The solver's certificate file.
        solver_certificate_file: PathBuf,
    },
}

fn bad(file: &Path, reason: impl Into<String>) -> ClusterError {
    ClusterError::Credentials {
        file: file.display().to_string(),
        reason: reason.into(),
    }
}

/// The certificates of a PEM file (at least one).
pub fn read_certificates(file: &Path) -> Result<Vec<CertificateDer<'static>>> {
    let pem = std::fs::read(file).map_err(|e| bad(file, format!("cannot read: {e}")))?;
    let certs = CertificateDer::pem_slice_iter(&pem)
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|e| bad(file, format!("not a PEM certificate: {e}")))?;
    if certs.is_empty() {
        return Err(bad(
            file,
            "holds no certificate (expected -----BEGIN CERTIFICATE-----)",
        ));
    }
    Ok(certs)
}

/// The private key of a PEM file; `true` besides when group or others may read it.
pub fn read_private_key(file: &Path) -> Result<(PrivateKeyDer<'static>, bool)> {
    use std::os::unix::fs::PermissionsExt;
    let pem = std::fs::read(file).map_err(|e| bad(file, format!("cannot read: {e}")))?;
    let loose = std::fs::metadata(file).is_ok_and(|m| m.permissions().mode() & 0o077 != 0);
    let key = PrivateKeyDer::from_pem_slice(&pem)
        .map_err(|e| bad(file, format!("holds no usable private key (PEM): {e}")))?;
    Ok((key, loose))
}

fn provider() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// The solver's TLS 1.3 server configuration; `true` besides when the key file is loose.
pub fn server_config(certificate_file: &Path, key_file: &Path) -> Result<(Arc<rustls::ServerConfig>, bool)> {
    let chain = read_certificates(certificate_file)?;
    let (key, loose) = read_private_key(key_file)?;
    let cfg = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| bad(certificate_file, e.to_string()))?
        .with_no_client_auth()
        .with_single_cert(chain, key)
        .map_err(|e| {
            bad(
                key_file,
                format!("does not go with {}: {e}", certificate_file.display()),
            )
        })?;
    Ok((Arc::new(cfg), loose))
}

/// A board's TLS 1.3 client configuration: it trusts the pinned solver certificate alone.
pub fn client_config(solver_certificate_file: &Path) -> Result<Arc<rustls::ClientConfig>> {
    let mut roots = rustls::RootCertStore::empty();
    for cert in read_certificates(solver_certificate_file)? {
        roots
            .add(cert)
            .map_err(|e| bad(solver_certificate_file, format!("cannot be pinned: {e}")))?;
    }
    let cfg = rustls::ClientConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])
        .map_err(|e| bad(solver_certificate_file, e.to_string()))?
        .with_root_certificates(roots)
        .with_no_client_auth();
    Ok(Arc::new(cfg))
}

/// `tcp/<host>:<port>` without metadata: `(host, port)`.
fn plain_tcp(endpoint: &str) -> Result<(String, u16)> {
    let wrong = || ClusterError::Config {
        reason: format!("endpoint {endpoint:?}: with TLS it must be tcp/<host>:<port> (no udp, no #options)"),
    };
    let rest = endpoint.strip_prefix("tcp/").ok_or_else(wrong)?;
    if rest.contains(['#', '?']) {
        return Err(wrong());
    }
    let (host, port) = rest.rsplit_once(':').ok_or_else(wrong)?;
    let port: u16 = port.parse().map_err(|_| wrong())?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    if host.is_empty() {
        return Err(wrong());
    }
    Ok((host.to_string(), port))
}

/// What a board's tunnel saw of the solver (`/status` → `cluster.tls`).
#[derive(Debug, Default)]
pub struct BoardTlsLog {
    /// Links carried to the solver after it proved itself.
    pub carried: AtomicU64,
    /// Handshakes in which the solver did not prove itself (wrong certificate, no TLS).
    pub solver_refused: AtomicU64,
    /// Connections to the solver that did not open (unreachable, timed out).
    pub unreachable: AtomicU64,
    last: Mutex<BoardLast>,
}

#[derive(Debug, Default)]
struct BoardLast {
    problem: Option<String>,
    at: Option<Instant>,
    notice_at: Option<Instant>,
    since_notice: u64,
}

/// A snapshot of [`BoardTlsLog`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BoardTlsSnapshot {
    /// Links carried after the solver proved itself.
    pub carried: u64,
    /// Handshakes in which the solver did not prove itself.
    pub solver_refused: u64,
    /// Connections that did not open.
    pub unreachable: u64,
    /// The newest problem in words, and how long ago, s.
    pub last_problem: Option<(String, f64)>,
}

impl BoardTlsLog {
    fn problem(&self, counter: &AtomicU64, words: String) {
        counter.fetch_add(1, Ordering::Relaxed);
        let now = Instant::now();
        let Ok(mut last) = self.last.lock() else { return };
        last.since_notice += 1;
        let due = last
            .notice_at
            .is_none_or(|t| now.saturating_duration_since(t) >= BOARD_NOTICE_INTERVAL);
        if due {
            tracing::warn!(
                "cluster TLS: {words} ({} such problems since the last line); nothing was sent to it",
                last.since_notice
            );
            last.notice_at = Some(now);
            last.since_notice = 0;
        }
        last.problem = Some(words);
        last.at = Some(now);
    }

    /// The counts and the newest problem.
    pub fn snapshot(&self) -> BoardTlsSnapshot {
        let last = self.last.lock().ok().and_then(|l| {
            let at = l.at?;
            Some((l.problem.clone()?, at.elapsed().as_secs_f64()))
        });
        BoardTlsSnapshot {
            carried: self.carried.load(Ordering::Relaxed),
            solver_refused: self.solver_refused.load(Ordering::Relaxed),
            unreachable: self.unreachable.load(Ordering::Relaxed),
            last_problem: last,
        }
    }
}

/// The process's board-side tunnel log.
pub fn board_log() -> &'static BoardTlsLog {
    static LOG: OnceLock<BoardTlsLog> = OnceLock::new();
    LOG.get_or_init(BoardTlsLog::default)
}

/// The tunnels of one Zenoh session; they stop when it is dropped.
pub struct Tunnels {
    runtime: Option<tokio::runtime::Runtime>,
    /// The addresses the tunnels listen on (the solver's TLS ports; a board's loopback ports).
    pub local_addrs: Vec<SocketAddr>,
}

impl std::fmt::Debug for Tunnels {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Tunnels({:?})", self.local_addrs)
    }
}

impl Drop for Tunnels {
    fn drop(&mut self) {
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("irtrack-tls")
        .enable_all()
        .build()
        .map_err(|e| ClusterError::Transport {
            what: "TLS tunnel",
            reason: e.to_string(),
        })
}

fn io_err(what: &'static str) -> impl Fn(std::io::Error) -> ClusterError {
    move |e| ClusterError::Transport {
        what,
        reason: e.to_string(),
    }
}

/// A free port on 127.0.0.1 for the solver's Zenoh (taken and let go; only local processes
/// could race for it).
fn free_loopback_port() -> Result<u16> {
    let l = std::net::TcpListener::bind(("127.0.0.1", 0)).map_err(io_err("TLS tunnel"))?;
    Ok(l.local_addr().map_err(io_err("TLS tunnel"))?.port())
}

impl Tunnels {
    /// The solver's tunnels: one TLS listener per `listen` endpoint, each handing its links
    /// to Zenoh on 127.0.0.1. Returns them and the endpoints Zenoh must listen on.
    pub fn solver(
        listen: &[String],
        certificate_file: &Path,
        key_file: &Path,
    ) -> Result<(Tunnels, Vec<String>)> {
        let (cfg, loose) = server_config(certificate_file, key_file)?;
        if loose {
            tracing::warn!(
                "cluster TLS: {} may be read by group or others: chmod 600 it",
                key_file.display()
            );
        }
        let acceptor = tokio_rustls::TlsAcceptor::from(cfg);
        let rt = runtime()?;
        let mut zenoh_listen = Vec::new();
        let mut local_addrs = Vec::new();
        for e in listen {
            let (host, port) = plain_tcp(e)?;
            let bind: SocketAddr = format!("{host}:{port}")
                .parse()
                .or_else(|_| format!("[{host}]:{port}").parse())
                .map_err(|_| ClusterError::Config {
                    reason: format!("listen endpoint {e:?}: the solver listens on an IP address"),
                })?;
            let std_listener = std::net::TcpListener::bind(bind).map_err(|err| ClusterError::Transport {
                what: "TLS listener",
                reason: format!("{bind}: {err}"),
            })?;
            std_listener
                .set_nonblocking(true)
                .map_err(io_err("TLS listener"))?;
            local_addrs.push(std_listener.local_addr().map_err(io_err("TLS listener"))?);
            let zenoh_port = free_loopback_port()?;
            zenoh_listen.push(format!("tcp/127.0.0.1:{zenoh_port}"));
            let forward = SocketAddr::from(([127, 0, 0, 1], zenoh_port));
            let acceptor = acceptor.clone();
            let _guard = rt.enter();
            let listener = TcpListener::from_std(std_listener).map_err(io_err("TLS listener"))?;
            rt.spawn(serve(listener, acceptor, forward));
        }
        Ok((
            Tunnels {
                runtime: Some(rt),
                local_addrs,
            },
            zenoh_listen,
        ))
    }

    /// A board's tunnels: one loopback listener per `connect` endpoint, each carrying its
    /// Zenoh's links to the solver over TLS. Returns them and the endpoints Zenoh must
    /// connect to.
    pub fn board(connect: &[String], solver_certificate_file: &Path) -> Result<(Tunnels, Vec<String>)> {
        let cfg = client_config(solver_certificate_file)?;
        let connector = tokio_rustls::TlsConnector::from(cfg);
        let name = ServerName::try_from(SOLVER_NAME).map_err(|e| ClusterError::Config {
            reason: format!("TLS server name: {e}"),
        })?;
        let rt = runtime()?;
        let mut zenoh_connect = Vec::new();
        let mut local_addrs = Vec::new();
        for e in connect {
            let (host, port) = plain_tcp(e)?;
            let std_listener = std::net::TcpListener::bind(("127.0.0.1", 0)).map_err(io_err("TLS tunnel"))?;
            std_listener.set_nonblocking(true).map_err(io_err("TLS tunnel"))?;
            let local = std_listener.local_addr().map_err(io_err("TLS tunnel"))?;
            local_addrs.push(local);
            zenoh_connect.push(format!("tcp/{local}"));
            let _guard = rt.enter();
            let listener = TcpListener::from_std(std_listener).map_err(io_err("TLS tunnel"))?;
            rt.spawn(carry(listener, connector.clone(), name.clone(), host, port));
        }
        Ok((
            Tunnels {
                runtime: Some(rt),
                local_addrs,
            },
            zenoh_connect,
        ))
    }
}

/// The solver's accept loop: never pauses for a peer's failure.
async fn serve(listener: TcpListener, acceptor: tokio_rustls::TlsAcceptor, forward: SocketAddr) {
    let slots = Arc::new(Semaphore::new(MAX_HANDSHAKES));
    loop {
        let (tcp, peer) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                // Out of file descriptors and the like: the process's problem, not a peer's.
                tracing::warn!("cluster TLS: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(10)).await;
                continue;
            }
        };
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            crate::refusals::global().record_tls(peer.to_string(), RefusalReason::AcceptLimit, None);
            drop(tcp);
            continue;
        };
        let acceptor = acceptor.clone();
        tokio::spawn(async move {
            let _ = tcp.set_nodelay(true);
            let mut tls = match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(tcp)).await {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => {
                    crate::refusals::global().record_tls(
                        peer.to_string(),
                        RefusalReason::Tls,
                        Some(e.to_string()),
                    );
                    return;
                }
                Err(_) => {
                    crate::refusals::global().record_tls(
                        peer.to_string(),
                        RefusalReason::HandshakeTimeout,
                        None,
                    );
                    return;
                }
            };
            drop(slot);
            let Ok(mut up) = TcpStream::connect(forward).await else {
                tracing::warn!("cluster TLS: the solver's Zenoh at {forward} does not answer");
                return;
            };
            let _ = up.set_nodelay(true);
            // Zenoh sees the tunnel's loopback address; the refusal log names the real peer.
            let alias = up.local_addr().ok().map(|a| a.to_string());
            if let Some(a) = &alias {
                crate::refusals::global().alias(a.clone(), peer.to_string());
            }
            let _ = tokio::io::copy_bidirectional(&mut tls, &mut up).await;
            if let Some(a) = &alias {
                crate::refusals::global().unalias(a);
            }
        });
    }
}

/// A board's loop: each link its Zenoh opens is carried to the solver once it proves itself.
async fn carry(
    listener: TcpListener,
    connector: tokio_rustls::TlsConnector,
    name: ServerName<'static>,
    host: String,
    port: u16,
) {
    loop {
        let Ok((mut local, _)) = listener.accept().await else {
            tokio::time::sleep(Duration::from_millis(10)).await;
            continue;
        };
        let connector = connector.clone();
        let name = name.clone();
        let host = host.clone();
        tokio::spawn(async move {
            let _ = local.set_nodelay(true);
            let log = board_log();
            let tcp = match tokio::time::timeout(CONNECT_TIMEOUT, TcpStream::connect((host.as_str(), port)))
                .await
            {
                Ok(Ok(t)) => t,
                Ok(Err(e)) => {
                    log.problem(
                        &log.unreachable,
                        format!("the solver at {host}:{port} cannot be reached: {e}"),
                    );
                    return;
                }
                Err(_) => {
                    log.problem(
                        &log.unreachable,
                        format!("the solver at {host}:{port} did not answer within {CONNECT_TIMEOUT:?}"),
                    );
                    return;
                }
            };
            let _ = tcp.set_nodelay(true);
            let mut tls = match tokio::time::timeout(HANDSHAKE_TIMEOUT, connector.connect(name, tcp)).await {
                Ok(Ok(s)) => s,
                Ok(Err(e)) => {
                    log.problem(
                        &log.solver_refused,
                        format!("the peer at {host}:{port} did not prove itself as this cell's solver ({e}): is it the solver, with the certificate this board pins?"),
                    );
                    return;
                }
                Err(_) => {
                    log.problem(
                        &log.solver_refused,
                        format!("the peer at {host}:{port} did not finish the TLS handshake within {HANDSHAKE_TIMEOUT:?}: is it the solver, with TLS on?"),
                    );
                    return;
                }
            };
            log.carried.fetch_add(1, Ordering::Relaxed);
            let _ = tokio::io::copy_bidirectional(&mut local, &mut tls).await;
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_with_tls_are_plain_tcp() {
        assert_eq!(
            plain_tcp("tcp/10.0.0.10:7447").unwrap(),
            ("10.0.0.10".into(), 7447)
        );
        assert_eq!(
            plain_tcp("tcp/solver.cell:7447").unwrap(),
            ("solver.cell".into(), 7447)
        );
        assert_eq!(plain_tcp("tcp/[::1]:7447").unwrap(), ("::1".into(), 7447));
        for bad in [
            "udp/10.0.0.10:7447",
            "tcp/10.0.0.10",
            "tcp/10.0.0.10:x",
            "tcp/:7447",
            "tcp/1.2.3.4:7447#bind=1.2.3.4:0",
        ] {
            let e = plain_tcp(bad).unwrap_err().to_string();
            assert!(e.contains("with TLS it must be tcp/<host>:<port>"), "{bad}: {e}");
        }
    }
}
