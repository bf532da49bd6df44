//! Connection caps shared by every listener: at most `max_total` connections at once per
//! listener and `max_per_peer` from one client address. A connection over a cap is closed at
//! once after `accept` (the descriptor is freed immediately) and counted; the counts are in
//! `/metrics` as `irtrackd_connections_refused_total{listener, reason}`.
//!
//! The caps are what keeps a flood of idle or slow connections from taking every file
//! descriptor: their sum over the listeners, plus what the service itself holds, must stay
//! under `RLIMIT_NOFILE` ([`check_fd_limit`] warns at start when it does not).
//!
//! The status listener must also stay reachable while the cap is full: with
//! [`ConnLimiter::admit_evicting`] a connection over the listener cap (but within its own
//! address's cap) closes the oldest unanswered HTTP exchange of the address that holds the
//! most slots, instead of being refused. Enough addresses could otherwise hold every slot for
//! a whole head timeout, each within its per-address cap. Long-lived sessions (WebSockets)
//! are never closed this way; they may hold at most `max_long_lived` slots, so the rest stay
//! open to exchanges.

use std::collections::{BTreeMap, HashMap};
use std::net::IpAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;

/// Caps of one listener.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnLimits {
    /// Connections open at once on the listener.
    pub max_total: usize,
    /// Connections open at once from one client address.
    pub max_per_peer: usize,
    /// Of `max_total`, how many long-lived sessions (WebSockets) may hold at once.
    pub max_long_lived: usize,
}

/// Defaults (docs/security.md): the status port serves browsers (a page uses a WebSocket and
/// a few fetches) and scripts; the parameter port one push at a time with a little slack.
pub const STATUS_LIMITS: ConnLimits = ConnLimits {
    max_total: 256,
    max_per_peer: 32,
    // 64 slots stay for plain HTTP exchanges (`/status`, sign-in, stop requests).
    max_long_lived: 192,
};
/// Parameter port caps (one push at a time with a little slack).
pub const PARAMS_LIMITS: ConnLimits = ConnLimits {
    max_total: 8,
    max_per_peer: 2,
    max_long_lived: 8,
};
/// Per stream port; the clients of both ports together are also capped by
/// `listen.max_stream_clients`.
pub const STREAM_LIMITS: ConnLimits = ConnLimits {
    max_total: 64,
    max_per_peer: 16,
    max_long_lived: 64,
};

/// Descriptors the service needs besides its connections (cameras, LED lines, state files,
/// listeners, the robot link, runtime internals), with room to spare.
pub const FDS_BESIDES_CONNECTIONS: u64 = 128;

/// Kept by the connection and by a WebSocket session made from it, so a WebSocket counts
/// against the caps for as long as it lives.
#[derive(Clone, Default)]
pub struct ConnSlot(pub Option<Arc<ConnPermit>>);

impl ConnSlot {
    /// Turns the slot into a long-lived session's (a WebSocket after its upgrade): never
    /// closed for a fresh client, and within the listener's `max_long_lived`. `false` when
    /// that many are held already (the upgrade should be refused). A slot without a
    /// connection (in-process requests) always may.
    pub fn hold_long(&self) -> bool {
        self.0.as_ref().is_none_or(|p| p.hold_long())
    }
}

/// Counters of one listener, exported in `/metrics`.
#[derive(Debug, Default)]
pub struct ListenerCounters {
    /// Connections open now.
    pub open: AtomicU64,
    /// Connections accepted in total.
    pub accepted: AtomicU64,
    /// Closed at once: the listener's cap was reached.
    pub refused_listener_cap: AtomicU64,
    /// Closed at once: that client address's cap was reached.
    pub refused_peer_cap: AtomicU64,
    /// Connections ended by a timeout (slow head, body, answer, or a silent WebSocket).
    pub timeouts: AtomicU64,
    /// Unanswered exchanges closed to make room for a new connection at the listener's cap.
    pub evicted: AtomicU64,
}

/// The four listeners' counters (part of `SharedStatus`).
#[derive(Debug, Default)]
pub struct NetCounters {
    /// Parameter port.
    pub params: Arc<ListenerCounters>,
    /// NDJSON stream port.
    pub stream_ndjson: Arc<ListenerCounters>,
    /// Binary stream port.
    pub stream_binary: Arc<ListenerCounters>,
    /// Status port (HTTP and the live WebSocket).
    pub status: Arc<ListenerCounters>,
    /// Sign-in attempts refused by the throttle (per address or the global ceiling).
    pub signin_throttled: AtomicU64,
    /// Live WebSocket sessions ended because a send was not taken within the send timeout
    /// (the viewer stopped reading).
    pub ws_send_timeouts: AtomicU64,
    /// Live WebSocket sessions ended because nothing (pong or message) came back in time.
    pub ws_silence_timeouts: AtomicU64,
}

impl NetCounters {
    /// `(listener label, counters)` for the metrics export.
    pub fn listeners(&self) -> [(&'static str, &ListenerCounters); 4] {
        [
            ("params", &self.params),
            ("stream_ndjson", &self.stream_ndjson),
            ("stream_binary", &self.stream_binary),
            ("status", &self.status),
        ]
    }
}

/// Why a connection was closed at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Over {
    /// The listener's `max_total`.
    Listener,
    /// The client address's `max_per_peer`.
    Peer,
}

/// The caps of one listener and who holds a slot now.
#[derive(Debug)]
pub struct ConnLimiter {
    limits: ConnLimits,
    counters: Arc<ListenerCounters>,
    table: Mutex<Table>,
}

/// Who holds the slots.
#[derive(Debug, Default)]
struct Table {
    per_peer: HashMap<IpAddr, PeerSlots>,
    long_lived: usize,
    next_id: u64,
}

/// One client address's slots.
#[derive(Debug, Default)]
struct PeerSlots {
    held: usize,
    /// Exchanges that may be closed for a fresh client, oldest first (by admission order).
    evictable: BTreeMap<u64, Arc<Notify>>,
}

/// A held slot; dropping it frees the slot.
#[derive(Debug)]
pub struct ConnPermit {
    limiter: Arc<ConnLimiter>,
    peer: IpAddr,
    id: u64,
    long_lived: AtomicBool,
}

impl ConnLimiter {
    /// A limiter with `limits` (each at least 1) counting into `counters`.
    pub fn new(limits: ConnLimits, counters: Arc<ListenerCounters>) -> Arc<Self> {
        Arc::new(Self {
            limits: ConnLimits {
                max_total: limits.max_total.max(1),
                max_per_peer: limits.max_per_peer.max(1),
                max_long_lived: limits.max_long_lived.clamp(1, limits.max_total.max(1)),
            },
            counters,
            table: Mutex::new(Table::default()),
        })
    }

    /// The caps in force.
    pub fn limits(&self) -> ConnLimits {
        self.limits
    }

    /// The listener's counters.
    pub fn counters(&self) -> &ListenerCounters {
        &self.counters
    }

    /// A slot for a connection from `peer`, or which cap refused it (counted).
    pub fn admit(self: &Arc<Self>, peer: IpAddr) -> Result<ConnPermit, Over> {
        let Ok(mut t) = self.table.lock() else {
            return Err(Over::Listener);
        };
        if self.counters.open.load(Ordering::Relaxed) as usize >= self.limits.max_total {
            self.counters.refused_listener_cap.fetch_add(1, Ordering::Relaxed);
            return Err(Over::Listener);
        }
        self.take(&mut t, peer, None)
    }

    /// Like [`admit`](Self::admit), but at the listener cap the oldest evictable exchange of
    /// the address holding the most slots is told to close (its `Notify` fires; counted as
    /// `evicted`) and the new connection is admitted. The new connection is itself evictable
    /// until [`ConnPermit::hold_long`]; its close signal is returned with the permit.
    pub fn admit_evicting(self: &Arc<Self>, peer: IpAddr) -> Result<(ConnPermit, Arc<Notify>), Over> {
        let Ok(mut t) = self.table.lock() else {
            return Err(Over::Listener);
        };
        if self.counters.open.load(Ordering::Relaxed) as usize >= self.limits.max_total {
            let held = |p: &IpAddr| t.per_peer.get(p).map_or(0, |s| s.held);
            if held(&peer) >= self.limits.max_per_peer {
                self.counters.refused_peer_cap.fetch_add(1, Ordering::Relaxed);
                return Err(Over::Peer);
            }
            let victim = t
                .per_peer
                .iter_mut()
                .filter(|(_, s)| !s.evictable.is_empty())
                .max_by_key(|(_, s)| s.held)
                .and_then(|(_, s)| s.evictable.pop_first());
            let Some((_, close)) = victim else {
                self.counters.refused_listener_cap.fetch_add(1, Ordering::Relaxed);
                return Err(Over::Listener);
            };
            close.notify_one();
            self.counters.evicted.fetch_add(1, Ordering::Relaxed);
        }
        let close = Arc::new(Notify::new());
        let permit = self.take(&mut t, peer, Some(close.clone()))?;
        Ok((permit, close))
    }

    /// Takes a slot for `peer` within its address cap; `close`: evictable with that signal.
    fn take(
        self: &Arc<Self>,
        t: &mut Table,
        peer: IpAddr,
        close: Option<Arc<Notify>>,
    ) -> Result<ConnPermit, Over> {
        let id = t.next_id;
        let slots = t.per_peer.entry(peer).or_default();
        if slots.held >= self.limits.max_per_peer {
            if slots.held == 0 {
                t.per_peer.remove(&peer);
            }
            self.counters.refused_peer_cap.fetch_add(1, Ordering::Relaxed);
            return Err(Over::Peer);
        }
        slots.held += 1;
        if let Some(close) = close {
            slots.evictable.insert(id, close);
        }
        t.next_id += 1;
        self.counters.open.fetch_add(1, Ordering::Relaxed);
        self.counters.accepted.fetch_add(1, Ordering::Relaxed);
        Ok(ConnPermit {
            limiter: self.clone(),
            peer,
            id,
            long_lived: AtomicBool::new(false),
        })
    }

    /// Logs a refusal now and then (a flood must not flood the log too).
    pub fn log_refusal(&self, listener: &'static str, over: Over) {
        let c = &self.counters;
        let n = c.refused_listener_cap.load(Ordering::Relaxed) + c.refused_peer_cap.load(Ordering::Relaxed);
        if n == 1 || n.is_multiple_of(1000) {
            tracing::warn!(
                listener,
                ?over,
                refused_so_far = n,
                max_total = self.limits.max_total,
                max_per_peer = self.limits.max_per_peer,
                "connection cap reached; connection closed"
            );
        }
    }
}

impl ConnPermit {
    /// See [`ConnSlot::hold_long`].
    pub fn hold_long(&self) -> bool {
        let limiter = &self.limiter;
        let Ok(mut t) = limiter.table.lock() else {
            return false;
        };
        if self.long_lived.load(Ordering::Relaxed) {
            return true;
        }
        if t.long_lived >= limiter.limits.max_long_lived {
            return false;
        }
        t.long_lived += 1;
        self.long_lived.store(true, Ordering::Relaxed);
        if let Some(s) = t.per_peer.get_mut(&self.peer) {
            s.evictable.remove(&self.id);
        }
        true
    }
}

impl Drop for ConnPermit {
    fn drop(&mut self) {
        if let Ok(mut t) = self.limiter.table.lock() {
            if self.long_lived.load(Ordering::Relaxed) {
                t.long_lived = t.long_lived.saturating_sub(1);
            }
            if let Some(s) = t.per_peer.get_mut(&self.peer) {
                s.held = s.held.saturating_sub(1);
                s.evictable.remove(&self.id);
                if s.held == 0 {
                    t.per_peer.remove(&self.peer);
                }
            }
        }
        self.limiter.counters.open.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Descriptors the caps can take at once, plus [`FDS_BESIDES_CONNECTIONS`].
pub fn fds_needed(max_stream_clients: u64) -> u64 {
    let stream = (2 * STREAM_LIMITS.max_total as u64).max(max_stream_clients);
    STATUS_LIMITS.max_total as u64 + PARAMS_LIMITS.max_total as u64 + stream + FDS_BESIDES_CONNECTIONS
}

/// The soft and hard `RLIMIT_NOFILE`.
pub fn fd_limit() -> Option<(u64, u64)> {
    let mut r = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: getrlimit writes one rlimit struct we own.
    let rc = unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut r) };
    // `rlim_t` is not u64 on every target (32-bit ones).
    #[allow(clippy::unnecessary_cast)]
    (rc == 0).then_some((r.rlim_cur as u64, r.rlim_max as u64))
}

/// Warns (and says what to set) when the soft file limit is below what the caps can take.
/// Returns whether the limit suffices.
pub fn check_fd_limit(needed: u64) -> bool {
    match fd_limit() {
        Some((soft, _)) if soft < needed => {
            tracing::warn!(
                soft_limit = soft,
                needed,
                "the open-file limit is below what the connection caps can take; a flood of \
                 connections could starve the service: raise it (LimitNOFILE= in the systemd \
                 unit, or `ulimit -n`)"
            );
            false
        }
        Some((soft, _)) => {
            tracing::debug!(soft_limit = soft, needed, "open-file limit suffices");
            true
        }
        None => true,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_per_listener_and_per_peer_count_refusals_and_free_slots() {
        let counters = Arc::new(ListenerCounters::default());
        let l = ConnLimiter::new(
            ConnLimits {
                max_total: 3,
                max_per_peer: 2,
                max_long_lived: 3,
            },
            counters.clone(),
        );
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let c: IpAddr = "10.0.0.3".parse().unwrap();
        let a1 = l.admit(a).unwrap();
        let _a2 = l.admit(a).unwrap();
        assert_eq!(l.admit(a).unwrap_err(), Over::Peer);
        let _b1 = l.admit(b).unwrap();
        assert_eq!(l.admit(c).unwrap_err(), Over::Listener);
        assert_eq!(counters.open.load(Ordering::Relaxed), 3);
        drop(a1);
        assert_eq!(counters.open.load(Ordering::Relaxed), 2);
        let _c1 = l.admit(c).unwrap();
        assert_eq!(counters.refused_peer_cap.load(Ordering::Relaxed), 1);
        assert_eq!(counters.refused_listener_cap.load(Ordering::Relaxed), 1);
        assert_eq!(counters.accepted.load(Ordering::Relaxed), 4);
    }

    #[test]
    fn at_the_cap_the_oldest_exchange_of_the_biggest_holder_is_closed() {
        let counters = Arc::new(ListenerCounters::default());
        let l = ConnLimiter::new(
            ConnLimits {
                max_total: 4,
                max_per_peer: 3,
                max_long_lived: 2,
            },
            counters.clone(),
        );
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let c: IpAddr = "10.0.0.3".parse().unwrap();
        let (a1, a1_close) = l.admit_evicting(a).unwrap();
        let (_a2, a2_close) = l.admit_evicting(a).unwrap();
        let (_a3, _) = l.admit_evicting(a).unwrap();
        let (b1, b1_close) = l.admit_evicting(b).unwrap();
        // a WebSocket is never closed for a fresh client ...
        assert!(a1.hold_long());
        // ... so a full listener closes a's oldest exchange (a holds the most), not b's.
        let (_c1, _) = l.admit_evicting(c).unwrap();
        assert_eq!(counters.evicted.load(Ordering::Relaxed), 1);
        let fired = |n: &Arc<Notify>| {
            let f = n.notified();
            tokio::pin!(f);
            f.as_mut().enable()
        };
        assert!(fired(&a2_close));
        assert!(!fired(&a1_close));
        assert!(!fired(&b1_close));
        // An address at its own cap evicts nobody.
        assert_eq!(l.admit_evicting(a).unwrap_err(), Over::Peer);
        // Long-lived sessions stay within their own cap.
        assert!(b1.hold_long());
        let (c2, _) = l.admit_evicting(c).unwrap();
        assert!(
            !c2.hold_long(),
            "a third long-lived session over max_long_lived = 2"
        );
        drop(a1);
        assert!(c2.hold_long());
        assert_eq!(counters.evicted.load(Ordering::Relaxed), 2);
    }

    #[test]
    fn fd_budget_fits_the_unit_file_limit() {
        // systemd/irtrackd.service sets LimitNOFILE=4096.
        assert!(fds_needed(32) < 4096);
        // ... and the caps also fit a plain shell's 1024.
        assert!(fds_needed(32) < 1024, "{}", fds_needed(32));
    }
}
