//! Who gets how much from the NatNet command socket (docs/outputs.md, "Spoofed requests and
//! floods"). NatNet runs over UDP without any handshake, so a request's source address is
//! only a claim: answering it with more bytes than it carried would let anyone reflect and
//! amplify traffic onto a victim whose address they write into their packets. The protocol has
//! no cookie a client would echo, so no client can prove it receives what is sent to it;
//! addresses in `client_networks` are the ones the operator vouches for.
//!
//! - A reply larger than its request goes only to an address in `client_networks`; elsewhere
//!   it is withheld (counted). So before an address is vouched for, every reply it triggers is
//!   at most as large as the request that triggered it (amplification ≤ 1).
//! - Only addresses in `client_networks` become unicast clients (frames flow to clients without
//!   any request); at most `max_clients_per_address` of them per IP address.
//! - Replies are rate limited per address and in total (token buckets with one second's
//!   burst), counted when dropped.

use std::collections::HashMap;
use std::fmt;
use std::net::IpAddr;
use std::time::Instant;

/// An IPv4 or IPv6 network, `address/prefix` (a bare address is a single host).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Network {
    addr: IpAddr,
    prefix: u8,
}

impl Network {
    /// Parses `10.0.0.0/8`, `192.168.1.7`, `fd00::/8`; the reason names what is wrong.
    pub fn parse(text: &str) -> std::result::Result<Self, String> {
        let (addr_text, prefix_text) = match text.split_once('/') {
            Some((a, p)) => (a, Some(p)),
            None => (text, None),
        };
        let addr: IpAddr = addr_text
            .trim()
            .parse()
            .map_err(|_| format!("{text:?} is not a network `address/prefix`"))?;
        let max = if addr.is_ipv4() { 32 } else { 128 };
        let prefix = match prefix_text {
            None => max,
            Some(p) => p
                .trim()
                .parse::<u8>()
                .ok()
                .filter(|p| *p <= max)
                .ok_or_else(|| format!("{text:?}: prefix {p:?} is not 0..={max}"))?,
        };
        let net = Self { addr, prefix };
        if net.masked(addr) != addr {
            return Err(format!(
                "{text:?} has host bits set (the network is {})",
                Self {
                    addr: net.masked(addr),
                    prefix
                }
            ));
        }
        Ok(net)
    }

    /// `ip` with the host bits cleared to this network's prefix.
    fn masked(&self, ip: IpAddr) -> IpAddr {
        match ip {
            IpAddr::V4(v4) => {
                let bits = u32::from(v4);
                let mask = u32::MAX.checked_shl(32 - u32::from(self.prefix)).unwrap_or(0);
                IpAddr::V4((bits & mask).into())
            }
            IpAddr::V6(v6) => {
                let bits = u128::from(v6);
                let mask = u128::MAX.checked_shl(128 - u32::from(self.prefix)).unwrap_or(0);
                IpAddr::V6((bits & mask).into())
            }
        }
    }

    /// Whether `ip` is in this network (an IPv4-mapped IPv6 address counts as IPv4).
    pub fn contains(&self, ip: IpAddr) -> bool {
        let ip = ip.to_canonical();
        ip.is_ipv4() == self.addr.is_ipv4() && self.masked(ip) == self.addr
    }
}

impl fmt::Display for Network {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.addr, self.prefix)
    }
}

/// `rate` tokens per second, at most `rate` stored (a burst of one second's worth).
#[derive(Debug, Clone, Copy)]
struct Bucket {
    tokens: f64,
    last: Instant,
}

impl Bucket {
    fn full(rate: f64, now: Instant) -> Self {
        Self {
            tokens: rate,
            last: now,
        }
    }

    fn refill(&mut self, rate: f64, now: Instant) {
        let dt = now.saturating_duration_since(self.last).as_secs_f64();
        self.tokens = (self.tokens + dt * rate).min(rate);
        self.last = now;
    }
}

/// What happens to one reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Send it.
    Send,
    /// Larger than its request, to an address outside `client_networks`: not sent.
    Withheld,
    /// Over the per-address or the total reply rate: not sent.
    RateLimited,
}

/// Addresses whose reply buckets are kept; beyond it new addresses are rate limited until the
/// once-a-second sweep forgets idle ones (a flood from spoofed addresses cannot grow the table).
pub const MAX_TRACKED_ADDRESSES: usize = 4096;

/// The reply policy of one NatNet server (see the module docs).
#[derive(Debug)]
pub struct Gate {
    networks: Vec<Network>,
    per_address_rate: f64,
    total_rate: f64,
    total: Bucket,
    per_address: HashMap<IpAddr, Bucket>,
}

impl Gate {
    /// `per_address_rate`, `total_rate`: replies per second (also the burst).
    pub fn new(networks: Vec<Network>, per_address_rate: f64, total_rate: f64, now: Instant) -> Self {
        Self {
            networks,
            per_address_rate,
            total_rate,
            total: Bucket::full(total_rate, now),
            per_address: HashMap::new(),
        }
    }

    /// Whether `ip` is in `client_networks`: it may get replies larger than its requests and
    /// become a unicast client.
    pub fn vouched_for(&self, ip: IpAddr) -> bool {
        self.networks.iter().any(|n| n.contains(ip))
    }

    /// Decides on a reply of `reply_len` bytes to a request of `request_len` bytes from `ip`;
    /// a reply that may be sent takes a token from both buckets.
    pub fn reply(&mut self, ip: IpAddr, request_len: usize, reply_len: usize, now: Instant) -> Verdict {
        if reply_len > request_len && !self.vouched_for(ip) {
            return Verdict::Withheld;
        }
        let ip = ip.to_canonical();
        self.total.refill(self.total_rate, now);
        if !self.per_address.contains_key(&ip) && self.per_address.len() >= MAX_TRACKED_ADDRESSES {
            return Verdict::RateLimited;
        }
        let rate = self.per_address_rate;
        let bucket = self
            .per_address
            .entry(ip)
            .or_insert_with(|| Bucket::full(rate, now));
        bucket.refill(rate, now);
        if bucket.tokens < 1.0 || self.total.tokens < 1.0 {
            return Verdict::RateLimited;
        }
        bucket.tokens -= 1.0;
        self.total.tokens -= 1.0;
        Verdict::Send
    }

    /// Forgets addresses whose bucket has refilled (they are as if never seen).
    pub fn sweep(&mut self, now: Instant) {
        let rate = self.per_address_rate;
        self.per_address.retain(|_, b| {
            b.refill(rate, now);
            b.tokens < rate
        });
    }

    /// Addresses currently tracked (tests).
    pub fn tracked(&self) -> usize {
        self.per_address.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[test]
    fn networks_parse_and_contain() {
        let n = Network::parse("10.1.0.0/16").unwrap();
        assert!(n.contains(ip("10.1.255.7")));
        assert!(!n.contains(ip("10.2.0.1")));
        assert!(n.contains(ip("::ffff:10.1.2.3")), "IPv4-mapped");
        assert!(!n.contains(ip("fd00::1")));
        assert_eq!(n.to_string(), "10.1.0.0/16");
        let host = Network::parse("192.168.3.9").unwrap();
        assert!(host.contains(ip("192.168.3.9")) && !host.contains(ip("192.168.3.8")));
        let all = Network::parse("0.0.0.0/0").unwrap();
        assert!(all.contains(ip("203.0.113.5")));
        let v6 = Network::parse("fd00::/8").unwrap();
        assert!(v6.contains(ip("fd12::1")) && !v6.contains(ip("fe80::1")));
        assert!(Network::parse("::/0").unwrap().contains(ip("2001:db8::1")));
        for (bad, says) in [
            ("10.1.2.3/16", "host bits set (the network is 10.1.0.0/16)"),
            ("10.0.0.0/33", "prefix \"33\" is not 0..=32"),
            ("fd00::/129", "is not 0..=128"),
            ("10.0.0.0/x", "prefix \"x\""),
            ("lab", "not a network"),
            ("", "not a network"),
        ] {
            let e = Network::parse(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn a_reply_larger_than_its_request_goes_only_to_vouched_for_addresses() {
        let t0 = Instant::now();
        let nets = vec![Network::parse("127.0.0.1/32").unwrap()];
        let mut g = Gate::new(nets, 100.0, 1000.0, t0);
        assert_eq!(g.reply(ip("127.0.0.9"), 4, 283, t0), Verdict::Withheld);
        assert_eq!(g.reply(ip("127.0.0.9"), 9, 10, t0), Verdict::Withheld);
        // Not larger than the request: sent even to an unknown address.
        assert_eq!(g.reply(ip("127.0.0.9"), 8, 8, t0), Verdict::Send);
        assert_eq!(g.reply(ip("127.0.0.9"), 300, 283, t0), Verdict::Send);
        assert_eq!(g.reply(ip("127.0.0.1"), 4, 283, t0), Verdict::Send);
        assert!(g.vouched_for(ip("127.0.0.1")) && !g.vouched_for(ip("127.0.0.9")));
    }

    #[test]
    fn replies_are_rate_limited_per_address_and_in_total() {
        let t0 = Instant::now();
        let nets = vec![Network::parse("0.0.0.0/0").unwrap()];
        let mut g = Gate::new(nets, 5.0, 8.0, t0);
        let sent = |g: &mut Gate, who: &str, n: usize, at: Instant| {
            (0..n)
                .filter(|_| g.reply(ip(who), 4, 100, at) == Verdict::Send)
                .count()
        };
        // A burst of one second's worth per address ...
        assert_eq!(sent(&mut g, "10.0.0.1", 20, t0), 5);
        // ... and the total bucket (8) leaves 3 for the next address.
        assert_eq!(sent(&mut g, "10.0.0.2", 20, t0), 3);
        assert_eq!(sent(&mut g, "10.0.0.3", 20, t0), 0);
        // Refilled at the rate: 0.4 s later 2 more for the first address (5/s), 3.2 in total.
        let t1 = t0 + Duration::from_millis(400);
        assert_eq!(sent(&mut g, "10.0.0.1", 20, t1), 2);
        assert_eq!(sent(&mut g, "10.0.0.3", 20, t1), 1);
        // Over 10 s at 1 request per 10 ms from one address: 5 per second and the burst.
        let mut n = 0;
        let start = t0 + Duration::from_secs(5);
        for i in 0..1000 {
            n += sent(&mut g, "10.0.0.4", 1, start + Duration::from_millis(10 * i));
        }
        assert!((50..=56).contains(&n), "{n}");
    }

    #[test]
    fn the_address_table_is_bounded_and_swept() {
        let t0 = Instant::now();
        let nets = vec![Network::parse("0.0.0.0/0").unwrap()];
        let mut g = Gate::new(nets, 2.0, 1e9, t0);
        for i in 0..MAX_TRACKED_ADDRESSES as u32 {
            let a = IpAddr::V4((0x0a00_0000 + i).into());
            assert_eq!(g.reply(a, 4, 4, t0), Verdict::Send);
        }
        assert_eq!(g.tracked(), MAX_TRACKED_ADDRESSES);
        // A new address while the table is full: limited, not tracked.
        assert_eq!(g.reply(ip("11.0.0.1"), 4, 4, t0), Verdict::RateLimited);
        assert_eq!(g.tracked(), MAX_TRACKED_ADDRESSES);
        // Nothing is idle yet; a second later every bucket is full again and forgotten.
        g.sweep(t0);
        assert_eq!(g.tracked(), MAX_TRACKED_ADDRESSES);
        g.sweep(t0 + Duration::from_secs(1));
        assert_eq!(g.tracked(), 0);
        assert_eq!(
            g.reply(ip("11.0.0.1"), 4, 4, t0 + Duration::from_secs(1)),
            Verdict::Send
        );
    }
}
