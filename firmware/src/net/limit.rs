//! Connection caps shared by every listener: at most `max_total` connections at once per
//! listener and `max_per_peer` from one client address. A connection over a cap is closed at
//! once after `accept` (the descriptor is freed immediately) and counted; the counts are in
//! `/metrics` as `irtrackd_connections_refused_total{listener, reason}`.
//!
//! The caps are what keeps a flood of idle or slow connections from taking every file
//! descriptor: their sum over the listeners, plus what the service itself holds, must stay
//! under `RLIMIT_NOFILE` ([`check_fd_limit`] warns at start when it does not).

use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Caps of one listener.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnLimits {
    pub max_total: usize,
    pub max_per_peer: usize,
}

/// Defaults (docs/security.md): the status port serves browsers (a page uses a WebSocket and
/// a few fetches) and scripts; the parameter port one push at a time with a little slack.
pub const STATUS_LIMITS: ConnLimits = ConnLimits {
    max_total: 256,
    max_per_peer: 32,
};
pub const PARAMS_LIMITS: ConnLimits = ConnLimits {
    max_total: 8,
    max_per_peer: 2,
};
/// Per stream port; the clients of both ports together are also capped by
/// `listen.max_stream_clients`.
pub const STREAM_LIMITS: ConnLimits = ConnLimits {
    max_total: 64,
    max_per_peer: 16,
};

/// Descriptors the service needs besides its connections (cameras, LED lines, state files,
/// listeners, the robot link, runtime internals), with room to spare.
pub const FDS_BESIDES_CONNECTIONS: u64 = 128;

/// Kept by the connection and by a WebSocket session made from it, so a WebSocket counts
/// against the caps for as long as it lives.
#[derive(Clone, Default)]
pub struct ConnSlot(pub Option<Arc<ConnPermit>>);

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
}

/// The four listeners' counters (part of `SharedStatus`).
#[derive(Debug, Default)]
pub struct NetCounters {
    pub params: Arc<ListenerCounters>,
    pub stream_ndjson: Arc<ListenerCounters>,
    pub stream_binary: Arc<ListenerCounters>,
    pub status: Arc<ListenerCounters>,
    /// Sign-in attempts refused by the throttle (per address or the global ceiling).
    pub signin_throttled: AtomicU64,
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
    Listener,
    Peer,
}

/// The caps of one listener and who holds a slot now.
#[derive(Debug)]
pub struct ConnLimiter {
    limits: ConnLimits,
    counters: Arc<ListenerCounters>,
    per_peer: Mutex<HashMap<IpAddr, usize>>,
}

/// A held slot; dropping it frees the slot.
#[derive(Debug)]
pub struct ConnPermit {
    limiter: Arc<ConnLimiter>,
    peer: IpAddr,
}

impl ConnLimiter {
    pub fn new(limits: ConnLimits, counters: Arc<ListenerCounters>) -> Arc<Self> {
        Arc::new(Self {
            limits: ConnLimits {
                max_total: limits.max_total.max(1),
                max_per_peer: limits.max_per_peer.max(1),
            },
            counters,
            per_peer: Mutex::new(HashMap::new()),
        })
    }

    pub fn limits(&self) -> ConnLimits {
        self.limits
    }

    pub fn counters(&self) -> &ListenerCounters {
        &self.counters
    }

    /// A slot for a connection from `peer`, or which cap refused it (counted).
    pub fn admit(self: &Arc<Self>, peer: IpAddr) -> Result<ConnPermit, Over> {
        let Ok(mut map) = self.per_peer.lock() else {
            return Err(Over::Listener);
        };
        let total: usize = self.counters.open.load(Ordering::Relaxed) as usize;
        if total >= self.limits.max_total {
            self.counters.refused_listener_cap.fetch_add(1, Ordering::Relaxed);
            return Err(Over::Listener);
        }
        let n = map.entry(peer).or_insert(0);
        if *n >= self.limits.max_per_peer {
            self.counters.refused_peer_cap.fetch_add(1, Ordering::Relaxed);
            return Err(Over::Peer);
        }
        *n += 1;
        self.counters.open.fetch_add(1, Ordering::Relaxed);
        self.counters.accepted.fetch_add(1, Ordering::Relaxed);
        Ok(ConnPermit {
            limiter: self.clone(),
            peer,
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

impl Drop for ConnPermit {
    fn drop(&mut self) {
        if let Ok(mut map) = self.limiter.per_peer.lock()
            && let Some(n) = map.get_mut(&self.peer)
        {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.peer);
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
    fn fd_budget_fits_the_unit_file_limit() {
        // systemd/irtrackd.service sets LimitNOFILE=4096.
        assert!(fds_needed(32) < 4096);
        // ... and the caps also fit a plain shell's 1024.
        assert!(fds_needed(32) < 1024, "{}", fds_needed(32));
    }
}
