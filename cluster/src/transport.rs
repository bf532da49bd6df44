//! Zenoh transport of observations: one publisher per board camera, one subscriber in the
//! solver. Peer mode with configured endpoints by default; multicast scouting only when asked
//! for (it floods the subnet and needs a multicast route), a `zenohd` router only across
//! subnets (docs/cluster.md).
//!
//! The solver's subscriber copies each payload into a fixed-size message and hands it to the
//! solver thread through a bounded channel, so the hand-over allocates nothing per
//! observation; when the solver falls behind, the newest observations are dropped and counted.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};

use irtrack_core::observation::{MAX_OBS_LEN, ObsBlob, ObsHeader, encode};
use zenoh::Wait;

use crate::clock::{ProbeKind, ProbeMessage, ProbeSample};
use crate::error::{ClusterError, Result};

pub use crate::names::{
    board_of_clock_key, check_name, clock_key, observation_key, rig_clock_key, rig_observations_key,
};

/// How a node joins the Zenoh network.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct TransportConfig {
    /// Endpoints this node listens on, e.g. `tcp/0.0.0.0:7447`.
    pub listen: Vec<String>,
    /// Endpoints of peers (or a router) to connect to, e.g. `tcp/10.0.0.2:7447`.
    pub connect: Vec<String>,
    /// Multicast scouting (off by default: endpoints are configured).
    pub multicast_scouting: bool,
    /// Zenoh's low-latency unicast transport (off by default: under heavy CPU load a burst of
    /// observations was seen not to arrive with it on; see docs/cluster.md).
    pub low_latency: bool,
    /// Who this node is on the transport (none: anyone who reaches the port is a peer).
    pub auth: Auth,
    /// TLS around every link (the solver proves itself; crate::tls). Needs `auth`.
    pub tls: Option<crate::tls::TlsRole>,
}

/// Authentication and access control of a node (docs/cluster.md, "Credentials").
///
/// Zenoh's user/password authentication: the side that opens a link proves it knows its
/// password (an HMAC of a nonce the other side chose; the password never travels), the side
/// that accepts checks it against its dictionary. So camera boards connect and the solver
/// listens. The solver's access control denies everything by default and lets user `X` put
/// only on `irtrack/<rig>/X/cam/*/obs`. The link is encrypted only with [`TransportConfig::tls`].
#[derive(Clone, PartialEq, Eq, Default)]
pub enum Auth {
    /// No credentials: every peer is accepted and may publish anything (the default, warned).
    #[default]
    None,
    /// A camera board: connects as user `board`.
    Board {
        /// The board's name, also its user name.
        board: String,
        /// Its password.
        password: String,
    },
    /// The solver: accepts only the boards of its dictionary, each on its own keys.
    Solver {
        /// The rig (key expressions).
        rig: String,
        /// The dictionary file Zenoh reads (`board:password` lines).
        dictionary_file: std::path::PathBuf,
        /// The boards listed in it (the access control's subjects).
        boards: Vec<String>,
    },
}

impl std::fmt::Debug for Auth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Auth::None => f.write_str("Auth::None"),
            Auth::Board { board, .. } => write!(f, "Auth::Board({board}, ***)"),
            Auth::Solver {
                rig,
                dictionary_file,
                boards,
            } => write!(
                f,
                "Auth::Solver({rig}, {}, {boards:?})",
                dictionary_file.display()
            ),
        }
    }
}

impl Auth {
    /// A camera board's credentials from its password file; `true` besides when group or
    /// others may read the file.
    pub fn board_from_file(board: &str, password_file: &std::path::Path) -> Result<(Auth, bool)> {
        check_name("board", board)?;
        let (password, loose) = crate::credentials::read_password_file(password_file)?;
        Ok((
            Auth::Board {
                board: board.to_string(),
                password,
            },
            loose,
        ))
    }

    /// The solver's from its dictionary file; `true` besides when group or others may read it.
    pub fn solver_from_file(rig: &str, dictionary_file: &std::path::Path) -> Result<(Auth, bool)> {
        check_name("rig", rig)?;
        let (entries, loose) = crate::credentials::read_dictionary_file(dictionary_file)?;
        json5_safe_path(dictionary_file)?;
        Ok((
            Auth::Solver {
                rig: rig.to_string(),
                dictionary_file: dictionary_file.to_path_buf(),
                boards: entries.into_iter().map(|c| c.board).collect(),
            },
            loose,
        ))
    }

    /// The access-control section of the solver's configuration (JSON5): deny by default;
    /// board `X` may put on its own observation keys, answer the clock probe on its own clock
    /// key, and receive the solver's subscription and probes.
    fn solver_acl(rig: &str, boards: &[String]) -> String {
        let mut rules = vec![
            format!(
                "{{id:\"solver-subscription\",messages:[\"declare_subscriber\"],flows:[\"egress\"],permission:\"allow\",key_exprs:[\"{}\"]}}",
                rig_observations_key(rig)
            ),
            format!(
                "{{id:\"solver-clock-probe\",messages:[\"query\"],flows:[\"egress\"],permission:\"allow\",key_exprs:[\"{}\"]}}",
                rig_clock_key(rig)
            ),
        ];
        let mut subjects = Vec::new();
        let mut policies = Vec::new();
        for b in boards {
            rules.push(format!(
                "{{id:\"obs-{b}\",messages:[\"put\"],flows:[\"ingress\"],permission:\"allow\",key_exprs:[\"irtrack/{rig}/{b}/cam/*/obs\"]}}"
            ));
            // Its clock probe answers only on its own key.
            rules.push(format!(
                "{{id:\"clock-{b}\",messages:[\"declare_queryable\",\"reply\"],flows:[\"ingress\"],permission:\"allow\",key_exprs:[\"{}\"]}}",
                clock_key(rig, b)
            ));
            subjects.push(format!("{{id:\"board-{b}\",usernames:[\"{b}\"]}}"));
            policies.push(format!(
                "{{rules:[\"obs-{b}\",\"clock-{b}\",\"solver-subscription\",\"solver-clock-probe\"],subjects:[\"board-{b}\"]}}"
            ));
        }
        format!(
            "{{enabled:true,default_permission:\"deny\",rules:[{}],subjects:[{}],policies:[{}]}}",
            rules.join(","),
            subjects.join(","),
            policies.join(",")
        )
    }
}

/// A path that can go into Zenoh's JSON5 configuration as a quoted string.
fn json5_safe_path(p: &std::path::Path) -> Result<&str> {
    p.to_str()
        .filter(|s| !s.chars().any(|c| c == '"' || c == '\\' || c.is_control()))
        .ok_or_else(|| ClusterError::Credentials {
            file: p.display().to_string(),
            reason: "the path must be UTF-8 without '\"', '\\' or control characters".into(),
        })
}

/// How long a new link may take to finish Zenoh's handshake before it is closed, ms.
pub const ACCEPT_TIMEOUT_MS: u64 = 1_000;
/// Links in their handshake at once; a further new link is closed at once.
pub const ACCEPT_PENDING: usize = 500;

impl TransportConfig {
    fn zenoh_config(&self) -> Result<zenoh::Config> {
        let bad = |e: Box<dyn std::error::Error + Send + Sync>| ClusterError::Transport {
            what: "configuration",
            reason: e.to_string(),
        };
        let list = |v: &[String]| {
            let quoted: Vec<String> = v.iter().map(|e| format!("{e:?}")).collect();
            format!("[{}]", quoted.join(","))
        };
        for e in self.listen.iter().chain(&self.connect) {
            if !(e.starts_with("tcp/") || e.starts_with("udp/")) || e.contains('"') {
                return Err(ClusterError::Config {
                    reason: format!("endpoint {e:?} must look like tcp/<ip>:<port> (or udp/...)"),
                });
            }
        }
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"peer\"").map_err(bad)?;
        c.insert_json5("listen/endpoints", &list(&self.listen))
            .map_err(bad)?;
        c.insert_json5("connect/endpoints", &list(&self.connect))
            .map_err(bad)?;
        let scout = if self.multicast_scouting { "true" } else { "false" };
        c.insert_json5("scouting/multicast/enabled", scout).map_err(bad)?;
        // Express observations take one batch each, and the real-time priority's queue holds
        // 2 batches by default: with the transmit task kept off the CPU for over 1 ms
        // (`wait_before_drop`), the third observation of a burst was dropped (reproduced under
        // load, docs/cluster.md). 16, Zenoh's maximum, lets a board's burst wait instead.
        c.insert_json5("transport/link/tx/queue/size/real_time", "16")
            .map_err(bad)?;
        // A connection flood: Zenoh closes every new link at once while `accept_pending`
        // links are still in their handshake, each for up to `accept_timeout` (defaults 100
        // and 10 s). 150 idle connections renewed every 8 s kept a restarting board out for
        // 40 s (issue 40). A handshake on a LAN takes milliseconds, so a short timeout frees
        // a silent connection's slot soon, and more slots need a faster flood to fill
        // (docs/cluster.md, "A connection flood").
        c.insert_json5("transport/unicast/accept_timeout", &ACCEPT_TIMEOUT_MS.to_string())
            .map_err(bad)?;
        c.insert_json5("transport/unicast/accept_pending", &ACCEPT_PENDING.to_string())
            .map_err(bad)?;
        if self.low_latency {
            // Zenoh's low-latency unicast transport writes each message from the publishing
            // thread instead of handing it to a transmit task: hop p50/p99 on loopback fell
            // from ~200 µs / 1.5–3 ms to ~40–80 µs / 0.3–0.5 ms (docs/performance.md). It needs
            // QoS off; both are negotiated per link, so a peer without them (a default
            // `zenohd`, PyPI's `eclipse-zenoh`) still connects over the usual transport.
            c.insert_json5("transport/unicast/lowlatency", "true")
                .map_err(bad)?;
            c.insert_json5("transport/unicast/qos/enabled", "false")
                .map_err(bad)?;
        }
        if self.tls.is_some() {
            // Zenoh's gossip tells peers each other's locators and has them connect on their
            // own: with TLS every link goes through the tunnels, never to a locator gossiped
            // (the solver's Zenoh listens on 127.0.0.1 behind its tunnel).
            c.insert_json5("scouting/gossip/enabled", "false").map_err(bad)?;
        }
        match &self.auth {
            Auth::None => {}
            Auth::Board { board, password } => {
                // A board accepts no link (its dictionary is empty): it connects.
                check_name("board", board)?;
                crate::credentials::check_password(password).map_err(|reason| ClusterError::Config {
                    reason: format!("board {board}: {reason}"),
                })?;
                c.insert_json5("transport/auth/usrpwd/user", &format!("\"{board}\""))
                    .map_err(bad)?;
                c.insert_json5("transport/auth/usrpwd/password", &format!("\"{password}\""))
                    .map_err(bad)?;
            }
            Auth::Solver {
                rig,
                dictionary_file,
                boards,
            } => {
                check_name("rig", rig)?;
                for b in boards {
                    check_name("board", b)?;
                }
                if boards.is_empty() {
                    return Err(ClusterError::Config {
                        reason: "the solver's dictionary lists no board".into(),
                    });
                }
                let path = json5_safe_path(dictionary_file)?;
                c.insert_json5("transport/auth/usrpwd/dictionary_file", &format!("\"{path}\""))
                    .map_err(bad)?;
                c.insert_json5("access_control", &Auth::solver_acl(rig, boards))
                    .map_err(bad)?;
            }
        }
        Ok(c)
    }
}

/// An open Zenoh session.
#[derive(Clone)]
pub struct Session {
    inner: zenoh::Session,
    /// Its TLS tunnels, when it has any (stopped with the last clone).
    tunnels: Option<Arc<crate::tls::Tunnels>>,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("zenoh::Session")
    }
}

fn transport(what: &'static str) -> impl Fn(Box<dyn std::error::Error + Send + Sync>) -> ClusterError {
    move |e| ClusterError::Transport {
        what,
        reason: e.to_string(),
    }
}

impl Session {
    /// Opens a session (blocking; call from a plain thread or with `spawn_blocking`).
    pub fn open(cfg: &TransportConfig) -> Result<Session> {
        use crate::tls::{TlsRole, Tunnels};
        let mut cfg = cfg.clone();
        let tunnels = match cfg.tls.clone() {
            None => None,
            Some(role) => {
                // TLS proves the solver to the boards; the boards still prove themselves by
                // user/password inside it, without which any TLS client would be let in.
                match (&role, &cfg.auth) {
                    (TlsRole::Solver { .. }, Auth::Solver { .. })
                    | (TlsRole::Board { .. }, Auth::Board { .. }) => {}
                    _ => {
                        return Err(ClusterError::Config {
                            reason: "TLS needs the credentials of the same role (a board's password_file, the solver's credentials_file)".into(),
                        });
                    }
                }
                if cfg.multicast_scouting {
                    return Err(ClusterError::Config {
                        reason: "TLS works with configured endpoints, not multicast scouting".into(),
                    });
                }
                let t = match &role {
                    TlsRole::Solver {
                        certificate_file,
                        key_file,
                    } => {
                        if cfg.listen.is_empty() || !cfg.connect.is_empty() {
                            return Err(ClusterError::Config {
                                reason: "with TLS the solver listens (listen endpoints, no connect)".into(),
                            });
                        }
                        let (t, eps) = Tunnels::solver(&cfg.listen, certificate_file, key_file)?;
                        cfg.listen = eps;
                        t
                    }
                    TlsRole::Board {
                        solver_certificate_file,
                    } => {
                        if cfg.connect.is_empty() || !cfg.listen.is_empty() {
                            return Err(ClusterError::Config {
                                reason: "with TLS a camera board connects (connect endpoints, no listen)"
                                    .into(),
                            });
                        }
                        let (t, eps) = Tunnels::board(&cfg.connect, solver_certificate_file)?;
                        cfg.connect = eps;
                        t
                    }
                };
                Some(Arc::new(t))
            }
        };
        let inner = zenoh::open(cfg.zenoh_config()?)
            .wait()
            .map_err(transport("open"))?;
        Ok(Session { inner, tunnels })
    }

    /// The addresses its TLS tunnels listen on (the solver's TLS ports; empty without TLS).
    pub fn tls_addrs(&self) -> Vec<std::net::SocketAddr> {
        self.tunnels
            .as_ref()
            .map_or_else(Vec::new, |t| t.local_addrs.clone())
    }

    /// Closes the session (blocking).
    pub fn close(&self) {
        let _ = self.inner.close().wait();
    }
}

/// Publishes one camera's observations; encodes into its own buffer.
pub struct ObsPublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
    buf: Box<[u8; MAX_OBS_LEN]>,
    sent: u64,
}

impl std::fmt::Debug for ObsPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ObsPublisher({})", self.publisher.key_expr())
    }
}

impl ObsPublisher {
    /// Declares the publisher of `irtrack/<rig>/<board>/cam/<camera>/obs` (blocking).
    pub fn new(session: &Session, rig: &str, board: &str, camera: usize) -> Result<ObsPublisher> {
        check_name("rig", rig)?;
        check_name("board", board)?;
        let publisher = session
            .inner
            .declare_publisher(observation_key(rig, board, camera))
            // Low latency: an observation is small and stale after one frame.
            .congestion_control(zenoh::qos::CongestionControl::Drop)
            .priority(zenoh::qos::Priority::RealTime)
            .express(true)
            .wait()
            .map_err(transport("declare publisher"))?;
        Ok(ObsPublisher {
            publisher,
            buf: Box::new([0u8; MAX_OBS_LEN]),
            sent: 0,
        })
    }

    /// Encodes and sends one observation; returns its size in bytes.
    pub fn publish(&mut self, header: &ObsHeader<'_>, blobs: &[ObsBlob]) -> Result<usize> {
        let n = encode(header, blobs, &mut self.buf[..])?;
        // Zenoh takes an owned payload: one small copy per observation on the board.
        self.publisher
            .put(self.buf[..n].to_vec())
            .wait()
            .map_err(transport("put"))?;
        self.sent += 1;
        Ok(n)
    }

    /// Sends bytes as they are (tests of the solver's handling of bad input).
    pub fn publish_raw(&mut self, bytes: &[u8]) -> Result<()> {
        self.publisher
            .put(bytes.to_vec())
            .wait()
            .map_err(transport("put"))?;
        self.sent += 1;
        Ok(())
    }

    /// Observations (and raw payloads) put so far.
    pub fn sent(&self) -> u64 {
        self.sent
    }
}

/// One received observation, copied out of Zenoh's buffer.
#[derive(Clone)]
pub struct Received {
    /// Valid bytes in `bytes`.
    pub len: usize,
    /// Receive time on the solver's pairing clock, ns.
    pub received_ns: u64,
    /// The payload (fixed storage: no allocation per observation).
    pub bytes: [u8; MAX_OBS_LEN],
    /// The payload did not fit: longer than any valid observation (decoding names it).
    pub oversize: bool,
}

impl Received {
    /// The received bytes.
    pub fn payload(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
}

/// Counters of a subscriber.
#[derive(Debug, Default)]
pub struct SubscriberStats {
    /// Samples received from Zenoh.
    pub received: AtomicU64,
    /// Dropped because the solver's queue was full.
    pub overflow: AtomicU64,
}

/// The solver's subscription to every camera of a rig.
pub struct ObsSubscriber {
    _subscriber: zenoh::pubsub::Subscriber<()>,
    /// Its counters (shared with Zenoh's callback).
    pub stats: Arc<SubscriberStats>,
}

impl std::fmt::Debug for ObsSubscriber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ObsSubscriber")
    }
}

impl ObsSubscriber {
    /// Subscribes to `irtrack/<rig>/*/cam/*/obs`; observations arrive on the returned
    /// receiver (capacity `queue`), stamped by `clock_ns` on arrival (blocking).
    pub fn new(
        session: &Session,
        rig: &str,
        queue: usize,
        clock_ns: fn() -> u64,
    ) -> Result<(ObsSubscriber, Receiver<Received>)> {
        check_name("rig", rig)?;
        let (tx, rx): (SyncSender<Received>, Receiver<Received>) = sync_channel(queue.max(1));
        let stats = Arc::new(SubscriberStats::default());
        let st = stats.clone();
        let subscriber = session
            .inner
            .declare_subscriber(rig_observations_key(rig))
            .callback(move |sample| {
                let received_ns = clock_ns();
                let payload = sample.payload().to_bytes();
                let mut msg = Received {
                    len: payload.len().min(MAX_OBS_LEN),
                    received_ns,
                    bytes: [0u8; MAX_OBS_LEN],
                    oversize: payload.len() > MAX_OBS_LEN,
                };
                msg.bytes[..msg.len].copy_from_slice(&payload[..msg.len]);
                st.received.fetch_add(1, Ordering::Relaxed);
                if let Err(TrySendError::Full(_)) = tx.try_send(msg) {
                    st.overflow.fetch_add(1, Ordering::Relaxed);
                }
            })
            .wait()
            .map_err(transport("declare subscriber"))?;
        Ok((
            ObsSubscriber {
                _subscriber: subscriber,
                stats,
            },
            rx,
        ))
    }
}

/// A board's answer to the solver's clock probe (cluster::clock): a queryable on
/// `irtrack/<rig>/<board>/clock` that stamps each request as it arrives and its reply as it
/// leaves, on `clock_ns` (the clock its observations carry).
pub struct ClockResponder {
    _queryable: zenoh::query::Queryable<()>,
    /// Probes answered.
    pub answered: Arc<AtomicU64>,
}

impl std::fmt::Debug for ClockResponder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ClockResponder")
    }
}

impl ClockResponder {
    /// Declares the queryable (blocking).
    pub fn new(
        session: &Session,
        rig: &str,
        board: &str,
        clock_ns: impl Fn() -> u64 + Send + Sync + 'static,
    ) -> Result<ClockResponder> {
        check_name("rig", rig)?;
        check_name("board", board)?;
        let key = clock_key(rig, board);
        let answered = Arc::new(AtomicU64::new(0));
        let count = answered.clone();
        let reply_key = key.clone();
        let queryable = session
            .inner
            .declare_queryable(key)
            .callback(move |query| {
                let t2 = clock_ns();
                let Some(req) = query
                    .payload()
                    .and_then(|p| ProbeMessage::decode(&p.to_bytes()).ok())
                    .filter(|m| m.kind == ProbeKind::Request)
                else {
                    return;
                };
                let t3 = clock_ns();
                let reply = req.reply(t2, t3).encode();
                if query
                    .reply(reply_key.as_str(), reply.to_vec())
                    .express(true)
                    .wait()
                    .is_ok()
                {
                    count.fetch_add(1, Ordering::Relaxed);
                }
            })
            .wait()
            .map_err(transport("declare clock queryable"))?;
        Ok(ClockResponder {
            _queryable: queryable,
            answered,
        })
    }
}

/// One board's completed probe, as the solver received it.
#[derive(Debug, Clone)]
pub struct ProbeReply {
    /// The board (from the reply's key).
    pub board: String,
    /// The exchange's times.
    pub sample: ProbeSample,
}

/// The solver's clock probe: a thread asking every board of the rig every `interval`,
/// handing each completed exchange to the returned receiver. Stops when dropped.
pub struct ClockProber {
    stop: Arc<std::sync::atomic::AtomicBool>,
    /// Probes sent.
    pub sent: Arc<AtomicU64>,
    /// Wakes the thread for a probe before its interval is over.
    wake: SyncSender<()>,
}

impl std::fmt::Debug for ClockProber {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ClockProber")
    }
}

impl Drop for ClockProber {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl ClockProber {
    /// Starts the probing thread; `clock_ns` must be the clock the solver pairs on.
    pub fn start(
        session: &Session,
        rig: &str,
        interval: std::time::Duration,
        clock_ns: fn() -> u64,
    ) -> Result<(ClockProber, Receiver<ProbeReply>)> {
        check_name("rig", rig)?;
        let (tx, rx) = sync_channel::<ProbeReply>(64);
        let (wake, woken) = sync_channel::<()>(1);
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let sent = Arc::new(AtomicU64::new(0));
        let (session, rig, st, sn) = (session.inner.clone(), rig.to_string(), stop.clone(), sent.clone());
        std::thread::Builder::new()
            .name("cluster-clock-probe".into())
            .spawn(move || {
                let key = rig_clock_key(&rig);
                let mut id = 0u64;
                while !st.load(Ordering::Relaxed) {
                    id += 1;
                    let (tx, rig) = (tx.clone(), rig.clone());
                    let t1 = clock_ns();
                    // Zenoh builds, routes and queues the query within the call, which took
                    // 90–320 µs here (debug build): stamped before it, that time counted as
                    // transit towards the board and offsets came out ~100 µs high; stamped
                    // after it, a query that had left early looked like a 30 µs round trip
                    // and won, 240 µs off. So the sample keeps both ends of the call.
                    let sent = Arc::new(AtomicU64::new(0));
                    let sent_cb = sent.clone();
                    let asked = session
                        .get(key.as_str())
                        .payload(ProbeMessage::request(id, t1).encode().to_vec())
                        .target(zenoh::query::QueryTarget::All)
                        // Each reply as it comes: its arrival time is the measurement.
                        .consolidation(zenoh::query::ConsolidationMode::None)
                        .express(true)
                        .timeout(interval)
                        .callback(move |reply| {
                            let t4 = clock_ns();
                            let Ok(sample) = reply.result() else { return };
                            let Some(board) = board_of_clock_key(&rig, sample.key_expr().as_str()) else {
                                return;
                            };
                            let Ok(m) = ProbeMessage::decode(&sample.payload().to_bytes()) else {
                                return;
                            };
                            // Only the answer to this request, with the time it left.
                            if m.kind != ProbeKind::Reply || m.id != id || m.t1_ns != t1 {
                                return;
                            }
                            // Answered before the call returned: it lasted until now at most.
                            let span = match sent_cb.load(Ordering::Relaxed) {
                                0 => t4.saturating_sub(t1),
                                t => t.saturating_sub(t1),
                            };
                            let _ = tx.try_send(ProbeReply {
                                board: board.to_string(),
                                sample: ProbeSample {
                                    t1_ns: t1,
                                    send_span_ns: span,
                                    t2_ns: m.t2_ns,
                                    t3_ns: m.t3_ns,
                                    t4_ns: t4,
                                },
                            });
                        })
                        .wait();
                    sent.store(clock_ns(), Ordering::Relaxed);
                    if asked.is_ok() {
                        sn.fetch_add(1, Ordering::Relaxed);
                    }
                    // The interval, or less when asked for a probe now; gone when the
                    // prober is dropped (its sender with it).
                    if let Err(std::sync::mpsc::RecvTimeoutError::Disconnected) = woken.recv_timeout(interval)
                    {
                        break;
                    }
                }
            })
            .map_err(|e| ClusterError::Transport {
                what: "clock probe thread",
                reason: e.to_string(),
            })?;
        Ok((ClockProber { stop, sent, wake }, rx))
    }

    /// Sends the next probe now instead of at the end of the interval (a board's clock looks
    /// stepped, or is being measured again after a step).
    pub fn probe_now(&self) {
        let _ = self.wake.try_send(());
    }
}

/// CLOCK_REALTIME in ns (the boards' shared clock when PTP or chrony disciplines it).
pub fn realtime_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}
