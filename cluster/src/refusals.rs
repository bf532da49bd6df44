//! Peers the solver's Zenoh refuses, counted with their address (docs/cluster.md, "Refused
//! peers").
//!
//! Zenoh's API reports only links that finished the handshake (`session.info()`, its transport
//! events); a link refused by the user/password check, one that ran out of handshake time and
//! one closed at the accept limit are seen only in Zenoh's own `tracing` events. So this
//! module is a `tracing` layer that recognises those events of the pinned `zenoh-transport`
//! ([`ZENOH_TRANSPORT_VERSION`]; read in its `unicast/establishment/accept.rs`,
//! `unicast/manager.rs` and `unicast/establishment/ext/auth/usrpwd.rs`):
//!
//! - every accepted link's handshake runs in a tokio task of its own, which traces
//!   `Establishment Accept InitSyn: <local> => <remote>. Received: …` (and `… OpenSyn: …`)
//!   when a handshake message arrives: the remote address, keyed by that task's id;
//! - a failed step logs the error at debug level in the same task; the user/password check's
//!   errors start with `UsrPwd extension - Recv` and end in `Expected extension.` (the peer
//!   sent no credentials), `Invalid user.` or `Invalid password.`;
//! - the task's deadline: `Failed to accept link before deadline (…ms)` (target
//!   `…::unicast::manager`, same task);
//! - the accept limit: `Closing link for preventing potential DoS: <local> => <remote>`
//!   (trace, `…::unicast::manager`).
//!
//! The access control's refusals are per message, not per link: a peer whose credentials are
//! valid but that publishes under a key its user may not use (a board under another board's
//! name) is let in, and each such put is dropped by Zenoh's ingress interceptor (`zenoh`
//! [`ZENOH_VERSION`], `net/routing/interceptor/access_control.rs`), which traces
//! `<zid> on <subject> is unauthorized to Put (ingress) on <key>` when it first decides for a
//! key and `Using cached result: <zid> is unauthorized to Put (ingress) on <key>` for each
//! message after. Those are counted as denied publications, by sender and key.
//!
//! Matching log text is brittle by nature, so it is pinned twice: a test checks that the
//! lock file still has this `zenoh-transport` version, and a test over real Zenoh sessions
//! checks that a peer without credentials and one with a wrong password are counted with the
//! address they connected from. An upgrade that changes the events fails those tests instead
//! of counting zero.

use std::collections::{HashMap, VecDeque};
use std::fmt::Write as _;
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use tracing::{Level, Subscriber};
use tracing_subscriber::Layer;
use tracing_subscriber::filter::Targets;
use tracing_subscriber::layer::Context;

/// The `zenoh-transport` version whose events [`classify`] recognises.
pub const ZENOH_TRANSPORT_VERSION: &str = "1.10.2";
/// Target of the accept handshake's events.
pub const ACCEPT_TARGET: &str = "zenoh_transport::unicast::establishment::accept";
/// Target of the transport manager's events (accept limit, handshake deadline).
pub const MANAGER_TARGET: &str = "zenoh_transport::unicast::manager";
/// The `zenoh` version whose access-control events [`classify`] recognises.
pub const ZENOH_VERSION: &str = "1.10.2";
/// Target of the access control's decisions (trace level, one per message).
pub const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";
/// Senders of denied publications remembered (the oldest first out when full).
pub const MAX_DENIED_RECENT: usize = 16;

/// Refused peers remembered by address (the newest first out when full).
pub const MAX_RECENT: usize = 16;
/// Handshakes in flight remembered (Zenoh's `accept_pending` is 500 in irtrackd).
const MAX_PENDING: usize = 1024;
/// A handshake entry older than this is forgotten (Zenoh's accept timeout is 1 s).
const PENDING_TTL: Duration = Duration::from_secs(30);
/// A log line about refusals at most this often.
pub const NOTICE_INTERVAL: Duration = Duration::from_secs(10);

/// Why a link was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub enum RefusalReason {
    /// The user/password check failed: no credentials, an unknown user or a wrong password.
    #[default]
    Credentials,
    /// The handshake did not finish within Zenoh's `accept_timeout`.
    HandshakeTimeout,
    /// Closed at once: `accept_pending` links were already in their handshake (a flood).
    AcceptLimit,
    /// Its TLS handshake with the solver's tunnel failed (a peer without TLS, or not speaking
    /// TLS 1.3; crate::tls).
    Tls,
}

impl RefusalReason {
    /// Every reason, in the order of [`RefusalSnapshot::by_reason`].
    pub const ALL: [RefusalReason; 4] = [
        RefusalReason::Credentials,
        RefusalReason::HandshakeTimeout,
        RefusalReason::AcceptLimit,
        RefusalReason::Tls,
    ];

    /// Its code in `/status` and `/metrics`.
    pub fn code(self) -> &'static str {
        match self {
            RefusalReason::Credentials => "credentials",
            RefusalReason::HandshakeTimeout => "handshake_timeout",
            RefusalReason::AcceptLimit => "accept_limit",
            RefusalReason::Tls => "tls",
        }
    }

    /// In plain words.
    pub fn words(self) -> &'static str {
        match self {
            RefusalReason::Credentials => "wrong or missing credentials",
            RefusalReason::HandshakeTimeout => "it did not finish Zenoh's handshake in time",
            RefusalReason::AcceptLimit => "too many links were opening at once (a connection flood?)",
            RefusalReason::Tls => "its TLS handshake failed (no TLS, or not TLS 1.3)",
        }
    }
}

/// What was wrong with a refused peer's credentials.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum CredentialProblem {
    /// It sent none.
    Missing,
    /// Its user name is not in the solver's dictionary.
    UnknownUser,
    /// Its password's HMAC did not match.
    WrongPassword,
    /// They could not be decoded.
    Unreadable,
}

impl CredentialProblem {
    /// Its code in `/status`.
    pub fn code(self) -> &'static str {
        match self {
            CredentialProblem::Missing => "missing",
            CredentialProblem::UnknownUser => "unknown_user",
            CredentialProblem::WrongPassword => "wrong_password",
            CredentialProblem::Unreadable => "unreadable",
        }
    }

    /// In plain words.
    pub fn words(self) -> &'static str {
        match self {
            CredentialProblem::Missing => "it sent no credentials",
            CredentialProblem::UnknownUser => "its user name is not in the solver's credentials file",
            CredentialProblem::WrongPassword => "its password is wrong",
            CredentialProblem::Unreadable => "its credentials could not be read",
        }
    }
}

/// What one of Zenoh's events says about a link being accepted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ZenohEvent {
    /// A handshake message arrived on an accepted link from this remote address.
    HandshakeFrom(String),
    /// The user/password check refused the link.
    CredentialsRefused(CredentialProblem),
    /// Another handshake step failed (not a refusal this module counts).
    HandshakeFailed,
    /// The handshake ran out of time.
    HandshakeTimeout,
    /// A link from this remote address was closed at the accept limit.
    AcceptLimit(String),
    /// The link was accepted.
    Accepted,
    /// The access control decides, for a key a peer declared, every action at once (the
    /// decisions traced next in the same task are that, not messages).
    AclCaching {
        /// The key expression.
        key: String,
    },
    /// The last decision of that batch (Zenoh 1.10.2 decides "Declare Liveliness
    /// Subscriber" last): the decisions after it are messages again.
    AclCachingEnd {
        /// The key expression.
        key: String,
    },
    /// The access control refused a put (or a reply) of a peer that is let in.
    PublishDenied {
        /// The peer's Zenoh ID, as Zenoh prints it.
        zid: String,
        /// The ACL subject it matched (`Interface(lo)+Username(b1)+Transport(Tcp)+<zid>`);
        /// `None` on the per-message events, which do not name it.
        subject: Option<String>,
        /// The key expression it published on.
        key: String,
        /// Decided from the cache (`Using cached result: …`): always a message.
        cached: bool,
        /// A put (an observation) or a reply (an answer to the solver's clock probe).
        action: DeniedAction,
    },
}

/// What a denied message of a peer that is let in was.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DeniedAction {
    /// A put: an observation under a key its user may not use.
    Put,
    /// A reply: an answer to a query (the clock probe) under a key its user may not use.
    Reply,
}

impl DeniedAction {
    /// Its code in `/status`.
    pub fn code(self) -> &'static str {
        match self {
            DeniedAction::Put => "put",
            DeniedAction::Reply => "reply",
        }
    }
}

/// The remote end of a link as Zenoh displays it, `<local> => <remote>` with locators such as
/// `tcp/127.0.0.1:7447`: the remote's `ip:port` (`[v6]:port`), without protocol or metadata.
fn remote_of(link: &str) -> Option<String> {
    let (_, remote) = link.split_once(" => ")?;
    let remote = remote.split_whitespace().next()?;
    let addr = remote.split_once('/').map_or(remote, |(_, a)| a);
    let addr = addr.split(['?', '#']).next()?;
    (!addr.is_empty()).then(|| addr.to_string())
}

/// Recognises an event of `zenoh-transport` [`ZENOH_TRANSPORT_VERSION`] by its target, level
/// and message (the formatted text); `None` for every other event.
pub fn classify(target: &str, level: Level, message: &str) -> Option<ZenohEvent> {
    if target == ACL_TARGET {
        if level != Level::TRACE {
            return None;
        }
        return publish_denied(message);
    }
    if target == ACCEPT_TARGET {
        if level == Level::TRACE {
            for prefix in ["Establishment Accept InitSyn: ", "Establishment Accept OpenSyn: "] {
                if let Some(rest) = message.strip_prefix(prefix) {
                    // "<local> => <remote>. Received: …"
                    let link = rest.split(". Received").next().unwrap_or(rest);
                    return remote_of(link).map(ZenohEvent::HandshakeFrom);
                }
            }
            return None;
        }
        if level != Level::DEBUG {
            return None;
        }
        if message.starts_with("New transport link accepted from") {
            return Some(ZenohEvent::Accepted);
        }
        if message.contains("UsrPwd extension - Recv") {
            let problem = if message.contains("Expected extension") {
                CredentialProblem::Missing
            } else if message.contains("Invalid user") {
                CredentialProblem::UnknownUser
            } else if message.contains("Invalid password") {
                CredentialProblem::WrongPassword
            } else {
                CredentialProblem::Unreadable
            };
            return Some(ZenohEvent::CredentialsRefused(problem));
        }
        // The step error of any other handshake step (`accept_link`'s `step!`).
        return Some(ZenohEvent::HandshakeFailed);
    }
    if target == MANAGER_TARGET {
        if level == Level::TRACE
            && let Some(link) = message.strip_prefix("Closing link for preventing potential DoS: ")
        {
            return remote_of(link).map(ZenohEvent::AcceptLimit);
        }
        if level == Level::DEBUG && message.starts_with("Failed to accept link before deadline") {
            return Some(ZenohEvent::HandshakeTimeout);
        }
    }
    None
}

/// `[Using cached result: ]<zid>[ on <subject>] is unauthorized to Put (ingress) on <key>`:
/// the access control's refusal of a peer's publication, or `ACL (ingress): caching
/// permissions for `<key>` ...`. Egress decisions (what the solver may send) and other
/// actions are not a peer's publications. When a peer declares a key (its observation key,
/// or a prefix such as `irtrack/<rig>` for compressed keys), Zenoh traces the caching line
/// and then decides every action for that key at once: a genuine board's prefix gets a
/// "denied put" that no message caused. [`PeerRefusals::observe`] takes those decisions
/// only for the subject's name.
fn publish_denied(message: &str) -> Option<ZenohEvent> {
    // "ACL (ingress): caching permissions for `<key>` ..."
    if let Some(rest) = message.strip_prefix("ACL (ingress): caching permissions for `") {
        let key = rest.split('`').next()?;
        return Some(ZenohEvent::AclCaching { key: key.to_string() });
    }
    for last in [
        " is authorized to Declare Liveliness Subscriber (ingress) on ",
        " is unauthorized to Declare Liveliness Subscriber (ingress) on ",
    ] {
        if let Some((_, key)) = message.split_once(last) {
            return Some(ZenohEvent::AclCachingEnd {
                key: key.trim().to_string(),
            });
        }
    }
    let (cached, rest) = match message.strip_prefix("Using cached result: ") {
        Some(rest) => (true, rest),
        None => (false, message),
    };
    let (action, (who, key)) = [
        (DeniedAction::Put, " is unauthorized to Put (ingress) on "),
        (DeniedAction::Reply, " is unauthorized to Reply (ingress) on "),
    ]
    .into_iter()
    .find_map(|(a, marker)| rest.split_once(marker).map(|parts| (a, parts)))?;
    let (zid, subject) = match who.split_once(" on ") {
        Some((zid, subject)) if !cached => (zid, Some(subject.trim().to_string())),
        _ => (who, None),
    };
    let (zid, key) = (zid.trim(), key.trim());
    if zid.is_empty() || key.is_empty() {
        return None;
    }
    Some(ZenohEvent::PublishDenied {
        zid: zid.to_string(),
        subject,
        key: key.to_string(),
        cached,
        action,
    })
}

/// Which handshake an event belongs to: Zenoh runs each accepted link's handshake in a tokio
/// task of its own; outside a task, the thread (never seen with 1.10.2).
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum HandshakeKey {
    /// The tokio task.
    Task(tokio::task::Id),
    /// The thread.
    Thread(std::thread::ThreadId),
}

impl HandshakeKey {
    /// The key of the code running now.
    pub fn current() -> HandshakeKey {
        tokio::task::try_id().map_or_else(
            || HandshakeKey::Thread(std::thread::current().id()),
            HandshakeKey::Task,
        )
    }
}

/// One address's refusals.
#[derive(Debug, Clone, PartialEq)]
pub struct RefusedPeer {
    /// `ip:port` it connected from; `None` when it sent nothing before its link ended (a
    /// silent connection timing out).
    pub address: Option<String>,
    /// Why.
    pub reason: RefusalReason,
    /// For credentials: what was wrong.
    pub problem: Option<CredentialProblem>,
    /// For TLS: the handshake's error, as rustls gives it.
    pub detail: Option<String>,
    /// Refusals of this address for this reason.
    pub count: u64,
    /// The newest, on the monotonic clock.
    pub last: Instant,
    /// The newest, Unix time in ms.
    pub last_unix_ms: u64,
}

impl RefusedPeer {
    /// "a peer at 10.0.0.66:51234 was refused: wrong or missing credentials (it sent no
    /// credentials)".
    pub fn words(&self) -> String {
        let who = match &self.address {
            Some(a) => format!("a peer at {a}"),
            None => "a peer whose address Zenoh did not log (it sent nothing)".to_string(),
        };
        let detail = match (self.problem, &self.detail) {
            (Some(p), _) => format!(" ({})", p.words()),
            (None, Some(d)) => format!(" ({d})"),
            (None, None) => String::new(),
        };
        format!("{who} was refused: {}{detail}", self.reason.words())
    }
}

/// One sender's publications on one key that the access control dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct DeniedPublication {
    /// The sender's Zenoh ID.
    pub zid: String,
    /// The ACL subject it signed in as (its user name and Zenoh's other subject fields), once
    /// known.
    pub subject: Option<String>,
    /// The key expression it published (or answered) on.
    pub key: String,
    /// A put (observations) or a reply (clock probe answers).
    pub action: DeniedAction,
    /// Dropped messages (the decision Zenoh makes when the key is declared is not one).
    pub count: u64,
    /// The newest, on the monotonic clock.
    pub last: Instant,
    /// The newest, Unix time in ms.
    pub last_unix_ms: u64,
}

impl DeniedPublication {
    /// The user name in the subject (`…+Username(b1)+…`).
    pub fn user(&self) -> Option<&str> {
        self.subject.as_deref().and_then(user_of)
    }

    /// "a peer signed in as b1 (Zenoh ID 4f2a…) published on cell1/obs/b0/0, which its
    /// credentials do not allow: dropped by the access control".
    pub fn words(&self) -> String {
        let who = match (self.user(), &self.subject) {
            (Some(u), _) => format!("a peer signed in as {u} (Zenoh ID {})", self.zid),
            (None, Some(s)) => format!("a peer matching {s} (Zenoh ID {})", self.zid),
            (None, None) => format!("a peer with Zenoh ID {}", self.zid),
        };
        let did = match self.action {
            DeniedAction::Put => "published on",
            DeniedAction::Reply => "answered the clock probe on",
        };
        format!(
            "{who} {did} {}, which its credentials do not allow: dropped by the access control",
            self.key
        )
    }
}

/// `b1` of an access-control subject `Interface(lo)+Username(b1)+Transport(Tcp)+<zid>`.
pub fn user_of(subject: &str) -> Option<&str> {
    subject
        .split('+')
        .find_map(|part| part.strip_prefix("Username(")?.strip_suffix(')'))
}

#[derive(Debug, Default)]
struct State {
    pending: HashMap<HandshakeKey, (String, Instant)>,
    counts: [u64; 4],
    /// The real peer behind each loopback address the TLS tunnel connects to Zenoh from.
    aliases: HashMap<String, String>,
    by_problem: [u64; 4],
    recent: VecDeque<RefusedPeer>,
    denied: u64,
    denied_recent: VecDeque<DeniedPublication>,
    /// Subjects by Zenoh ID, from the first decision for each key (bounded like `pending`).
    subjects: HashMap<String, String>,
    /// The key whose permissions the access control is caching, by task or thread.
    acl_caching: HashMap<HandshakeKey, String>,
    last_notice: Option<Instant>,
    /// Refused links since the last notice.
    since_notice: u64,
    /// Denied publications since the last notice.
    since_denied: u64,
}

/// The refusal counts and the latest refused peers (`/status` → `cluster.refused_peers`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RefusalSnapshot {
    /// The layer is installed: refusals are being counted (otherwise every count is 0 because
    /// nobody looks, not because nothing was refused).
    pub counting: bool,
    /// Every refusal.
    pub total: u64,
    /// Per reason, in [`RefusalReason::ALL`]'s order.
    pub by_reason: [(RefusalReason, u64); 4],
    /// Credential refusals per problem.
    pub by_problem: Vec<(CredentialProblem, u64)>,
    /// The latest refused addresses, newest first.
    pub recent: Vec<RefusedPeer>,
    /// Publications the access control dropped (peers let in, keys not theirs).
    pub denied_publications: u64,
    /// Their latest senders and keys, newest first.
    pub denied_recent: Vec<DeniedPublication>,
}

impl RefusalSnapshot {
    /// The newest refusal.
    pub fn newest(&self) -> Option<&RefusedPeer> {
        self.recent.first()
    }
}

/// Refusals seen by the layer. One per process ([`global`]): `tracing`'s subscriber is global,
/// and so are Zenoh's sessions' events.
#[derive(Debug, Default)]
pub struct PeerRefusals {
    counting: std::sync::atomic::AtomicBool,
    state: Mutex<State>,
}

/// The process's refusal log (the one [`refusal_layer`] fills).
pub fn global() -> &'static PeerRefusals {
    static LOG: OnceLock<PeerRefusals> = OnceLock::new();
    LOG.get_or_init(PeerRefusals::default)
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

impl PeerRefusals {
    /// Marks the log as filled by an installed layer.
    pub fn set_counting(&self) {
        self.counting.store(true, std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether a layer fills it.
    pub fn counting(&self) -> bool {
        self.counting.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Takes one recognised event of handshake `key` at `now`.
    pub fn observe(&self, key: HandshakeKey, event: ZenohEvent, now: Instant) {
        let Ok(mut st) = self.state.lock() else { return };
        match event {
            ZenohEvent::HandshakeFrom(addr) => {
                let addr = st.aliases.get(&addr).cloned().unwrap_or(addr);
                if st.pending.len() >= MAX_PENDING {
                    st.pending
                        .retain(|_, (_, at)| now.saturating_duration_since(*at) < PENDING_TTL);
                }
                if st.pending.len() < MAX_PENDING {
                    st.pending.insert(key, (addr, now));
                }
            }
            ZenohEvent::Accepted | ZenohEvent::HandshakeFailed => {
                st.pending.remove(&key);
            }
            ZenohEvent::CredentialsRefused(problem) => {
                let addr = st.pending.remove(&key).map(|(a, _)| a);
                st.by_problem[problem as usize] += 1;
                st.record(addr, RefusalReason::Credentials, Some(problem), now);
            }
            ZenohEvent::HandshakeTimeout => {
                let addr = st.pending.remove(&key).map(|(a, _)| a);
                st.record(addr, RefusalReason::HandshakeTimeout, None, now);
            }
            ZenohEvent::AcceptLimit(addr) => {
                let addr = st.aliases.get(&addr).cloned().unwrap_or(addr);
                st.record(Some(addr), RefusalReason::AcceptLimit, None, now);
            }
            ZenohEvent::AclCaching { key: k } => {
                if st.acl_caching.len() >= MAX_PENDING {
                    st.acl_caching.clear();
                }
                st.acl_caching.insert(key, k);
            }
            ZenohEvent::AclCachingEnd { key: k } => {
                if st.acl_caching.get(&key) == Some(&k) {
                    st.acl_caching.remove(&key);
                }
            }
            ZenohEvent::PublishDenied {
                zid,
                subject,
                key: k,
                cached,
                action,
            } => {
                // When a peer declares a key, Zenoh decides every action for it at once
                // (query, reply, put, …) after one "caching permissions" line: those are no
                // messages. The marker stays for the whole batch, until its last decision or
                // a decision from the cache (a message) in the same task. Replies are decided
                // without the cache, message by message.
                let at_declaration = !cached && st.acl_caching.get(&key) == Some(&k);
                if cached {
                    st.acl_caching.remove(&key);
                }
                if at_declaration {
                    // A decision made when the key was declared, not a message: learn who.
                    if let Some(s) = subject {
                        st.remember_subject(zid, s);
                    }
                } else {
                    st.record_denied(zid, subject, k, action, now);
                }
            }
        }
    }

    /// A refusal by the TLS tunnel (crate::tls), which knows the peer's address itself.
    pub fn record_tls(&self, address: String, reason: RefusalReason, detail: Option<String>) {
        let Ok(mut st) = self.state.lock() else { return };
        st.record(Some(address), reason, None, Instant::now());
        if let Some(p) = st.recent.front_mut() {
            p.detail = detail;
        }
    }

    /// Zenoh will see `peer` at `loopback` (the TLS tunnel's own end): name `peer` instead.
    pub fn alias(&self, loopback: String, peer: String) {
        let Ok(mut st) = self.state.lock() else { return };
        if st.aliases.len() >= MAX_PENDING {
            st.aliases.clear();
        }
        st.aliases.insert(loopback, peer);
    }

    /// The tunnel's link from `loopback` ended.
    pub fn unalias(&self, loopback: &str) {
        if let Ok(mut st) = self.state.lock() {
            st.aliases.remove(loopback);
        }
    }

    /// The counts and the latest refused peers.
    pub fn snapshot(&self) -> RefusalSnapshot {
        let counting = self.counting();
        let Ok(st) = self.state.lock() else {
            return RefusalSnapshot {
                counting,
                ..RefusalSnapshot::default()
            };
        };
        let by_reason = RefusalReason::ALL.map(|r| (r, st.counts[r as usize]));
        RefusalSnapshot {
            counting,
            total: st.counts.iter().sum(),
            by_reason,
            by_problem: [
                CredentialProblem::Missing,
                CredentialProblem::UnknownUser,
                CredentialProblem::WrongPassword,
                CredentialProblem::Unreadable,
            ]
            .into_iter()
            .map(|p| (p, st.by_problem[p as usize]))
            .filter(|(_, n)| *n > 0)
            .collect(),
            recent: st.recent.iter().cloned().collect(),
            denied_publications: st.denied,
            denied_recent: st.denied_recent.iter().cloned().collect(),
        }
    }

    /// A line for the log when refusals happened since the last one, at most every
    /// [`NOTICE_INTERVAL`] (a flood must not flood the journal too).
    pub fn take_notice(&self, now: Instant) -> Option<String> {
        let mut st = self.state.lock().ok()?;
        if st.since_notice + st.since_denied == 0
            || st
                .last_notice
                .is_some_and(|t| now.saturating_duration_since(t) < NOTICE_INTERVAL)
        {
            return None;
        }
        let refused = std::mem::take(&mut st.since_notice);
        let denied = std::mem::take(&mut st.since_denied);
        st.last_notice = Some(now);
        // The newest of each kind in words, and how many there were when more than one.
        let part = |words: Option<String>, n: u64, what: &str| {
            let mut part = words.filter(|_| n > 0)?;
            if n > 1 {
                let _ = write!(part, "; {n} {what} since the last such line");
            }
            Some(part)
        };
        let parts: Vec<String> = [
            part(
                st.recent.front().map(RefusedPeer::words),
                refused,
                "peers refused",
            ),
            part(
                st.denied_recent.front().map(DeniedPublication::words),
                denied,
                "publications dropped",
            ),
        ]
        .into_iter()
        .flatten()
        .collect();
        (!parts.is_empty()).then(|| format!("cluster transport: {}", parts.join("; ")))
    }
}

impl State {
    fn record(
        &mut self,
        address: Option<String>,
        reason: RefusalReason,
        problem: Option<CredentialProblem>,
        now: Instant,
    ) {
        self.counts[reason as usize] += 1;
        self.since_notice += 1;
        let at_ms = unix_ms();
        if let Some(i) = self
            .recent
            .iter()
            .position(|p| p.address == address && p.reason == reason)
            && let Some(mut p) = self.recent.remove(i)
        {
            p.count += 1;
            p.problem = problem;
            p.last = now;
            p.last_unix_ms = at_ms;
            self.recent.push_front(p);
            return;
        }
        if self.recent.len() >= MAX_RECENT {
            self.recent.pop_back();
        }
        let peer = RefusedPeer {
            address,
            reason,
            problem,
            detail: None,
            count: 1,
            last: now,
            last_unix_ms: at_ms,
        };
        self.recent.push_front(peer);
    }

    fn remember_subject(&mut self, zid: String, subject: String) {
        if self.subjects.len() >= MAX_PENDING && !self.subjects.contains_key(&zid) {
            self.subjects.clear();
        }
        self.subjects.insert(zid, subject);
    }

    fn record_denied(
        &mut self,
        zid: String,
        subject: Option<String>,
        key: String,
        action: DeniedAction,
        now: Instant,
    ) {
        self.denied += 1;
        self.since_denied += 1;
        if let Some(s) = &subject {
            self.remember_subject(zid.clone(), s.clone());
        }
        let subject = subject.or_else(|| self.subjects.get(&zid).cloned());
        let at_ms = unix_ms();
        let mut entry = match self
            .denied_recent
            .iter()
            .position(|d| d.zid == zid && d.key == key && d.action == action)
            .and_then(|i| self.denied_recent.remove(i))
        {
            Some(mut d) => {
                d.count += 1;
                d.last = now;
                d.last_unix_ms = at_ms;
                d
            }
            None => DeniedPublication {
                zid,
                subject: None,
                key,
                action,
                count: 1,
                last: now,
                last_unix_ms: at_ms,
            },
        };
        if subject.is_some() {
            entry.subject = subject;
        }
        if self.denied_recent.len() >= MAX_DENIED_RECENT {
            self.denied_recent.pop_back();
        }
        self.denied_recent.push_front(entry);
    }
}

/// Takes an event's `message` field as text.
struct MessageText<'a>(&'a mut String);

impl tracing::field::Visit for MessageText<'_> {
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            let _ = write!(self.0, "{value:?}");
        }
    }

    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        if field.name() == "message" {
            self.0.push_str(value);
        }
    }
}

thread_local! {
    /// [`RefusalLayer::on_event`]'s text buffer.
    static TEXT: std::cell::RefCell<String> = const { std::cell::RefCell::new(String::new()) };
}

/// The `tracing` layer that feeds [`global`].
#[derive(Debug, Clone, Copy)]
pub struct RefusalLayer {
    log: &'static PeerRefusals,
}

impl<S: Subscriber> Layer<S> for RefusalLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: Context<'_, S>) {
        let meta = event.metadata();
        let target = meta.target();
        if target != ACCEPT_TARGET && target != MANAGER_TARGET && target != ACL_TARGET {
            return;
        }
        // One access-control event per message a peer sends: the text goes into a buffer
        // kept per thread (Zenoh's receive threads), not a new string each time. A nested
        // event on the same thread (none expected) gets its own.
        TEXT.with(|buf| {
            let mut own = String::new();
            let mut held = buf.try_borrow_mut();
            let text = match held.as_deref_mut() {
                Ok(t) => t,
                Err(_) => &mut own,
            };
            text.clear();
            event.record(&mut MessageText(text));
            if let Some(e) = classify(target, *meta.level(), text) {
                self.log.observe(HandshakeKey::current(), e, Instant::now());
            }
        });
    }
}

/// The layer and the events it needs, whatever the log's own filter: Zenoh's accept path at
/// trace level (a few events per new link) and the access control's decisions at trace level
/// (one per message received from a peer, formatted and matched here: about a microsecond
/// each, off the frame path). Add it to the subscriber beside the log's layer; it marks
/// [`global`] as counting.
pub fn refusal_layer<S>() -> impl Layer<S>
where
    S: Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
{
    let log = global();
    log.set_counting();
    RefusalLayer { log }.with_filter(
        Targets::new()
            .with_target(ACCEPT_TARGET, Level::TRACE)
            .with_target(MANAGER_TARGET, Level::TRACE)
            .with_target(ACL_TARGET, Level::TRACE),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    // The texts zenoh-transport 1.10.2 logs, as its source formats them (`ZError`'s Display
    // appends " at <file>:<line>.").
    const INIT_SYN: &str = "Establishment Accept InitSyn: tcp/127.0.0.1:7447 => tcp/127.0.0.66:51234. Received: TransportMessage { body: InitSyn(..) }";
    const NO_EXT: &str = "UsrPwd extension - Recv InitSyn. Expected extension. at /root/.cargo/registry/src/x/zenoh-transport-1.10.2/src/unicast/establishment/ext/auth/usrpwd.rs:380.";
    const BAD_PW: &str = "UsrPwd extension - Recv OpenSyn. Invalid password. at /x/usrpwd.rs:424.";
    const BAD_USER: &str = "UsrPwd extension - Recv OpenSyn. Invalid user. at /x/usrpwd.rs:418.";

    #[test]
    fn zenoh_events_are_recognised() {
        assert_eq!(
            classify(ACCEPT_TARGET, Level::TRACE, INIT_SYN),
            Some(ZenohEvent::HandshakeFrom("127.0.0.66:51234".into()))
        );
        let v6 = "Establishment Accept OpenSyn: tcp/[::1]:7447 => tcp/[::1]:40000. Received: x";
        assert_eq!(
            classify(ACCEPT_TARGET, Level::TRACE, v6),
            Some(ZenohEvent::HandshakeFrom("[::1]:40000".into()))
        );
        for (text, p) in [
            (NO_EXT, CredentialProblem::Missing),
            (BAD_PW, CredentialProblem::WrongPassword),
            (BAD_USER, CredentialProblem::UnknownUser),
            (
                "UsrPwd extension - Recv OpenSyn. Decoding error. at x:1.",
                CredentialProblem::Unreadable,
            ),
        ] {
            assert_eq!(
                classify(ACCEPT_TARGET, Level::DEBUG, text),
                Some(ZenohEvent::CredentialsRefused(p)),
                "{text}"
            );
        }
        assert_eq!(
            classify(
                ACCEPT_TARGET,
                Level::DEBUG,
                "New transport link accepted from abc to def: x"
            ),
            Some(ZenohEvent::Accepted)
        );
        assert_eq!(
            classify(
                ACCEPT_TARGET,
                Level::DEBUG,
                "Received invalid message instead of an InitSyn"
            ),
            Some(ZenohEvent::HandshakeFailed)
        );
        assert_eq!(
            classify(
                MANAGER_TARGET,
                Level::TRACE,
                "Closing link for preventing potential DoS: tcp/10.0.0.10:7447 => tcp/10.0.0.66:40001"
            ),
            Some(ZenohEvent::AcceptLimit("10.0.0.66:40001".into()))
        );
        assert_eq!(
            classify(
                MANAGER_TARGET,
                Level::DEBUG,
                "Failed to accept link before deadline (1000ms)"
            ),
            Some(ZenohEvent::HandshakeTimeout)
        );
        // Other targets, levels and texts are not refusals.
        assert_eq!(
            classify(
                "zenoh_transport::unicast::establishment::open",
                Level::DEBUG,
                BAD_PW
            ),
            None
        );
        assert_eq!(classify(ACCEPT_TARGET, Level::INFO, BAD_PW), None);
        assert_eq!(
            classify(
                ACCEPT_TARGET,
                Level::TRACE,
                "Establishment Accept InitAck: a => b. Sent: x"
            ),
            None
        );
        assert_eq!(
            classify(MANAGER_TARGET, Level::TRACE, "Accepting link... a => b"),
            None
        );
    }

    #[test]
    fn refusals_are_counted_per_handshake_with_the_address() {
        let log = PeerRefusals::default();
        let t0 = Instant::now();
        let (a, b) = (
            HandshakeKey::Thread(std::thread::current().id()),
            HandshakeKey::Thread(std::thread::spawn(|| std::thread::current().id()).join().unwrap()),
        );
        // Two handshakes interleaved: each refusal gets its own task's address.
        log.observe(a.clone(), ZenohEvent::HandshakeFrom("10.0.0.66:51234".into()), t0);
        log.observe(b.clone(), ZenohEvent::HandshakeFrom("10.0.0.11:40000".into()), t0);
        log.observe(b.clone(), ZenohEvent::Accepted, t0);
        log.observe(
            a.clone(),
            ZenohEvent::CredentialsRefused(CredentialProblem::Missing),
            t0,
        );
        log.observe(a.clone(), ZenohEvent::HandshakeTimeout, t0);
        log.observe(b, ZenohEvent::AcceptLimit("10.0.0.67:1".into()), t0);
        let s = log.snapshot();
        assert!(!s.counting, "no layer installed");
        assert_eq!(s.total, 3);
        assert_eq!(
            s.by_reason,
            [
                (RefusalReason::Credentials, 1),
                (RefusalReason::HandshakeTimeout, 1),
                (RefusalReason::AcceptLimit, 1),
                (RefusalReason::Tls, 0)
            ]
        );
        assert_eq!(s.by_problem, vec![(CredentialProblem::Missing, 1)]);
        let words: Vec<String> = s.recent.iter().map(RefusedPeer::words).collect();
        assert_eq!(
            words,
            [
                "a peer at 10.0.0.67:1 was refused: too many links were opening at once (a connection flood?)",
                "a peer whose address Zenoh did not log (it sent nothing) was refused: it did not finish Zenoh's handshake in time",
                "a peer at 10.0.0.66:51234 was refused: wrong or missing credentials (it sent no credentials)",
            ]
        );
        // The same address again: one entry, counted twice, moved to the front.
        log.observe(a.clone(), ZenohEvent::HandshakeFrom("10.0.0.66:51234".into()), t0);
        log.observe(
            a,
            ZenohEvent::CredentialsRefused(CredentialProblem::WrongPassword),
            t0,
        );
        let s = log.snapshot();
        assert_eq!(s.recent.len(), 3);
        assert_eq!(s.recent[0].count, 2);
        assert_eq!(s.recent[0].problem, Some(CredentialProblem::WrongPassword));
        // One notice, then none within the interval, then one saying how many since.
        let first = log.take_notice(t0).unwrap();
        assert!(first.contains("a peer at 10.0.0.66:51234 was refused"), "{first}");
        assert!(
            first.contains("4 peers refused since the last such line"),
            "{first}"
        );
        assert_eq!(log.take_notice(t0 + Duration::from_secs(20)), None, "nothing new");
        log.observe(
            HandshakeKey::Thread(std::thread::current().id()),
            ZenohEvent::AcceptLimit("10.0.0.68:2".into()),
            t0,
        );
        assert_eq!(log.take_notice(t0 + Duration::from_secs(5)), None, "rate-limited");
        let next = log.take_notice(t0 + Duration::from_secs(11)).unwrap();
        assert!(
            next.ends_with(
                "a peer at 10.0.0.68:2 was refused: too many links were opening at once (a connection flood?)"
            ),
            "{next}"
        );
    }

    /// The access control's texts as zenoh 1.10.2 formats them (`{zid} on {subject} is
    /// unauthorized to {action} on {key}`, the subject being Zenoh's `SubjectQuery` display,
    /// as seen in `cluster/tests/zenoh_refusals.rs`).
    #[test]
    fn behind_the_tls_tunnel_a_refusal_names_the_real_peer() {
        let log = PeerRefusals::default();
        let t0 = Instant::now();
        let k = HandshakeKey::Thread(std::thread::current().id());
        // Zenoh sees the tunnel's loopback end; the tunnel told the log whom it carries.
        log.alias("127.0.0.1:40001".into(), "10.0.0.66:51234".into());
        log.observe(k.clone(), ZenohEvent::HandshakeFrom("127.0.0.1:40001".into()), t0);
        log.observe(
            k.clone(),
            ZenohEvent::CredentialsRefused(CredentialProblem::WrongPassword),
            t0,
        );
        // A handshake the tunnel itself refused, with rustls's words.
        log.record_tls(
            "10.0.0.67:5000".into(),
            RefusalReason::Tls,
            Some("received corrupt message of type InvalidContentType".into()),
        );
        log.unalias("127.0.0.1:40001");
        log.observe(k.clone(), ZenohEvent::HandshakeFrom("127.0.0.1:40001".into()), t0);
        log.observe(k, ZenohEvent::CredentialsRefused(CredentialProblem::Missing), t0);
        let s = log.snapshot();
        let words: Vec<String> = s.recent.iter().map(RefusedPeer::words).collect();
        assert_eq!(
            words,
            [
                "a peer at 127.0.0.1:40001 was refused: wrong or missing credentials (it sent no credentials)",
                "a peer at 10.0.0.67:5000 was refused: its TLS handshake failed (no TLS, or not TLS 1.3) (received corrupt message of type InvalidContentType)",
                "a peer at 10.0.0.66:51234 was refused: wrong or missing credentials (its password is wrong)",
            ]
        );
        assert_eq!(s.by_reason[3], (RefusalReason::Tls, 1));
        assert_eq!(s.total, 3);
    }

    #[test]
    fn denied_clock_answers_are_counted_but_not_the_decisions_of_a_declaration() {
        const B1: &str = "Interface(lo)+Username(b1)+Transport(Tcp)+4f2a9c";
        let key = "irtrack/cell1/b0/clock";
        let log = PeerRefusals::default();
        let t0 = Instant::now();
        let here = HandshakeKey::Thread(std::thread::current().id());
        let feed = |text: &str| {
            let e = classify(ACL_TARGET, Level::TRACE, text).unwrap_or_else(|| panic!("{text}"));
            log.observe(here.clone(), e, t0);
        };
        // b1 declares b0's clock key: Zenoh decides query, reply, put, … at once. None of
        // those is a message, whatever their order (reply comes before put in 1.10.2).
        feed(&format!("ACL (ingress): caching permissions for `{key}` ..."));
        feed(&format!(
            "4f2a9c on {B1} is unauthorized to Reply (ingress) on {key}"
        ));
        feed(&format!(
            "4f2a9c on {B1} is unauthorized to Put (ingress) on {key}"
        ));
        assert_eq!(
            log.snapshot().denied_publications,
            0,
            "a declaration is no message"
        );
        // The batch's last decision; then each answer is decided anew (replies are not
        // taken from the cache in 1.10.2) and counted, as a reply.
        feed(&format!(
            "4f2a9c on {B1} is unauthorized to Declare Liveliness Subscriber (ingress) on {key}"
        ));
        let answer = format!("4f2a9c on {B1} is unauthorized to Reply (ingress) on {key}");
        feed(&answer);
        feed(&answer);
        feed(&answer);
        feed(&format!(
            "Using cached result: 4f2a9c is unauthorized to Reply (ingress) on {key}"
        ));
        let s = log.snapshot();
        assert_eq!(s.denied_publications, 4);
        assert_eq!(s.denied_recent.len(), 1);
        let d = &s.denied_recent[0];
        assert_eq!(
            (d.action, d.count, d.user()),
            (DeniedAction::Reply, 4, Some("b1"))
        );
        assert_eq!(
            d.words(),
            "a peer signed in as b1 (Zenoh ID 4f2a9c) answered the clock probe on irtrack/cell1/b0/clock, which its credentials do not allow: dropped by the access control"
        );
    }

    #[test]
    fn access_control_denials_are_recognised_and_counted_by_sender_and_key() {
        const B1: &str = "Interface(lo)+Username(b1)+Transport(Tcp)+4f2a9c";
        let caching = "ACL (ingress): caching permissions for `cell1/obs/b0/0` ...";
        let first = format!("4f2a9c on {B1} is unauthorized to Put (ingress) on cell1/obs/b0/0");
        let cached = "Using cached result: 4f2a9c is unauthorized to Put (ingress) on cell1/obs/b0/0";
        assert_eq!(
            classify(ACL_TARGET, Level::TRACE, caching),
            Some(ZenohEvent::AclCaching {
                key: "cell1/obs/b0/0".into()
            })
        );
        assert_eq!(
            classify(ACL_TARGET, Level::TRACE, &first),
            Some(ZenohEvent::PublishDenied {
                zid: "4f2a9c".into(),
                subject: Some(B1.into()),
                key: "cell1/obs/b0/0".into(),
                cached: false,
                action: DeniedAction::Put,
            })
        );
        assert_eq!(
            classify(ACL_TARGET, Level::TRACE, cached),
            Some(ZenohEvent::PublishDenied {
                zid: "4f2a9c".into(),
                subject: None,
                key: "cell1/obs/b0/0".into(),
                cached: true,
                action: DeniedAction::Put,
            })
        );
        assert_eq!(user_of(B1), Some("b1"));
        assert_eq!(user_of("Interface(lo)+Transport(Tcp)"), None);
        // Allowed messages, egress decisions, other actions and other levels are not denials.
        for (level, text) in [
            (
                Level::TRACE,
                "Using cached result: 4f2a9c is authorized to Put (ingress) on cell1/obs/b0/0",
            ),
            (
                Level::TRACE,
                "4f2a9c on b0 is authorized to Put (ingress) on cell1/obs/b0/0",
            ),
            (
                Level::TRACE,
                "Using cached result: 11 is unauthorized to Put (egress) on cell1/status",
            ),
            (
                Level::TRACE,
                "ACL (egress): caching permissions for `cell1/status` ...",
            ),
            (
                Level::TRACE,
                "11 on b0 is unauthorized to Query (ingress) on cell1/**",
            ),
            (
                Level::TRACE,
                "11 on b0 is unauthorized to Delete (ingress) on cell1/obs/b0/0",
            ),
            (Level::DEBUG, cached),
        ] {
            assert_eq!(classify(ACL_TARGET, level, text), None, "{text}");
        }

        let log = PeerRefusals::default();
        let t0 = Instant::now();
        let here = HandshakeKey::Thread(std::thread::current().id());
        let feed = |text: &str| {
            let e = classify(ACL_TARGET, Level::TRACE, text).unwrap();
            log.observe(here.clone(), e, t0);
        };
        // b1 declares b0's key: the decision made then is no message, only b1's name.
        feed(caching);
        feed(&first);
        assert_eq!(
            log.snapshot().denied_publications,
            0,
            "a declaration is not a put"
        );
        // A genuine board's prefix declaration: the same, never counted.
        feed("ACL (ingress): caching permissions for `cell1` ...");
        feed("77 on Interface(lo)+Username(b0)+Transport(Tcp)+77 is unauthorized to Put (ingress) on cell1");
        assert_eq!(log.snapshot().denied_publications, 0);
        // Each put b1 then makes is decided from the cache and counted, under b1's name.
        feed(cached);
        feed(cached);
        // A put decided without a cache (no declaration before it) is a message too.
        feed(
            "88 on Interface(lo)+Username(b2)+Transport(Tcp)+88 is unauthorized to Put (ingress) on cell1/obs/b0/1",
        );
        let s = log.snapshot();
        assert_eq!(s.denied_publications, 3);
        assert_eq!(s.total, 0, "no link was refused");
        assert_eq!(s.denied_recent.len(), 2);
        let b1 = &s.denied_recent[1];
        assert_eq!(
            (b1.zid.as_str(), b1.key.as_str(), b1.count),
            ("4f2a9c", "cell1/obs/b0/0", 2)
        );
        assert_eq!(b1.user(), Some("b1"));
        assert_eq!(
            b1.words(),
            "a peer signed in as b1 (Zenoh ID 4f2a9c) published on cell1/obs/b0/0, which its credentials do not allow: dropped by the access control"
        );
        assert_eq!(s.denied_recent[0].user(), Some("b2"), "newest first");
        let notice = log.take_notice(t0).unwrap();
        assert!(notice.contains("a peer signed in as b2"), "{notice}");
        assert!(
            notice.contains("3 publications dropped since the last such line"),
            "{notice}"
        );
        // A sender seen only in per-message events (its declaration before the layer was
        // there) has no name to give.
        feed("Using cached result: 99 is unauthorized to Put (ingress) on k");
        let newest = log.snapshot().denied_recent[0].clone();
        assert_eq!(newest.subject, None);
        assert!(
            newest
                .words()
                .starts_with("a peer with Zenoh ID 99 published on k,"),
            "{}",
            newest.words()
        );
    }

    #[test]
    fn the_pending_table_is_bounded() {
        let log = PeerRefusals::default();
        let t0 = Instant::now();
        // Distinct handshake keys: the ids of tokio tasks, as Zenoh's handshakes have.
        let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
        let keys: Vec<HandshakeKey> = rt.block_on(async {
            let mut v = Vec::new();
            for _ in 0..MAX_PENDING + 100 {
                v.push(tokio::spawn(async { HandshakeKey::current() }).await.unwrap());
            }
            v
        });
        assert!(keys.iter().all(|k| matches!(k, HandshakeKey::Task(_))));
        for (i, k) in keys.iter().enumerate() {
            log.observe(
                k.clone(),
                ZenohEvent::HandshakeFrom(format!("10.0.{}.{}:1", i / 256, i % 256)),
                t0,
            );
        }
        assert_eq!(
            log.state.lock().unwrap().pending.len(),
            MAX_PENDING,
            "full, not growing"
        );
        // Once full, entries older than the TTL make room.
        let later = t0 + PENDING_TTL * 2;
        log.observe(
            keys[0].clone(),
            ZenohEvent::HandshakeFrom("10.1.0.0:1".into()),
            later,
        );
        assert_eq!(log.state.lock().unwrap().pending.len(), 1);
    }
}
