//! Operator sign-in for the status listener's change requests (tuning, save, robot control).
//!
//! The board stores only an Argon2id PHC string (`[service] operator_password_hash`, made by
//! `irtrackd --hash-password`). A browser signs in once (`POST /api/login`) and gets a random
//! session token in an HttpOnly, SameSite=Strict cookie; scripts may send HTTP Basic
//! credentials with every change instead. Viewing needs no sign-in (docs/security.md).

use std::collections::{HashMap, VecDeque};
use std::net::IpAddr;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use argon2::password_hash::{PasswordHash, PasswordHasher, SaltString};
use argon2::{Algorithm, Argon2};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::Response;
use base64::Engine as _;
use rand::RngCore;

use super::http::text;
use crate::error::{FirmwareError, Result};

/// Name of the session cookie.
pub const SESSION_COOKIE: &str = "irtrack_session";
/// User name expected in HTTP Basic credentials.
pub const BASIC_USER: &str = "operator";
/// How long a session stays valid after sign-in.
pub const SESSION_TTL: Duration = Duration::from_secs(12 * 3600);
/// Sessions kept at once; signing in beyond this forgets the oldest.
const MAX_SESSIONS: usize = 32;
/// Wrong passwords in a row from one address before its password checks pause.
pub const FAILURES_BEFORE_PAUSE: u32 = 5;
/// First pause; each further wrong password after a pause doubles it, up to [`MAX_PAUSE`].
const FIRST_PAUSE: Duration = Duration::from_secs(10);
const MAX_PAUSE: Duration = Duration::from_secs(300);
/// Global ceiling: wrong passwords from all addresses together within [`GLOBAL_WINDOW`]. Once
/// reached, addresses that already sent a wrong password wait until the window frees up;
/// an address without a wrong password, and loopback, are still checked, so the ceiling can
/// never lock every address out (docs/security.md, "Sign-in throttle").
pub const GLOBAL_WRONG_MAX: usize = 30;
/// The sliding window [`GLOBAL_WRONG_MAX`] counts over.
pub const GLOBAL_WINDOW: Duration = Duration::from_secs(60);
/// Addresses whose wrong passwords are remembered at once (oldest forgotten first).
const MAX_TRACKED_ADDRESSES: usize = 4096;

/// Hashes `password` as an Argon2id PHC string (random salt).
pub fn hash_password(password: &str) -> Result<String> {
    if password.is_empty() {
        return Err(FirmwareError::Config {
            reason: "the operator password must not be empty".into(),
        });
    }
    let mut salt = [0u8; 16];
    rand::rngs::OsRng.fill_bytes(&mut salt);
    let salt = SaltString::encode_b64(&salt).map_err(|e| FirmwareError::Config {
        reason: format!("password salt: {e}"),
    })?;
    Argon2::default()
        .hash_password(password.as_bytes(), &salt)
        .map(|h| h.to_string())
        .map_err(|e| FirmwareError::Config {
            reason: format!("hashing the operator password: {e}"),
        })
}

/// Checks that `phc` is an Argon2id PHC string (config validation).
pub fn check_hash(phc: &str) -> Result<()> {
    let bad = |why: String| FirmwareError::Config {
        reason: format!("service.operator_password_hash: {why}; make one with `irtrackd --hash-password`"),
    };
    let h = PasswordHash::new(phc).map_err(|e| bad(format!("not a PHC string ({e})")))?;
    if h.algorithm != Algorithm::Argon2id.ident() {
        return Err(bad(format!("algorithm {} is not argon2id", h.algorithm)));
    }
    Ok(())
}

/// Why a change request was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// No password hash in the config: nobody may change anything.
    NotConfigured,
    /// No (valid) session or credentials.
    NotSignedIn,
    /// Credentials were sent but are wrong.
    BadCredentials,
    /// Too many wrong passwords in a row: no password is checked for this many seconds.
    Paused {
        /// Seconds until a password is checked again (the `Retry-After` value).
        retry_after_s: u64,
    },
}

impl Refusal {
    /// The answer body: what was refused and what to do about it.
    pub fn message(self) -> String {
        match self {
            Refusal::NotConfigured => "no operator password is configured, so changes are refused: run \
                 `irtrackd --hash-password` and put the result in [service] \
                 operator_password_hash (docs/security.md)\n"
                .into(),
            Refusal::NotSignedIn => "sign in first: POST /api/login with {\"password\": ...}, or send HTTP \
                 Basic credentials for user \"operator\"\n"
                .into(),
            Refusal::BadCredentials => "wrong operator password\n".into(),
            Refusal::Paused { retry_after_s } => format!(
                "too many wrong operator passwords in a row: password checks are paused, try again \
                 in {retry_after_s} s (sessions already signed in keep working)\n"
            ),
        }
    }

    /// 401 with the message; 429 with `Retry-After` while password checks are paused.
    pub fn response(self) -> Response {
        match self {
            Refusal::Paused { retry_after_s } => {
                let mut r = text(StatusCode::TOO_MANY_REQUESTS, self.message());
                r.headers_mut()
                    .insert(header::RETRY_AFTER, axum::http::HeaderValue::from(retry_after_s));
                r
            }
            _ => text(StatusCode::UNAUTHORIZED, self.message()),
        }
    }
}

/// Wrong-password bookkeeping of one client address: guessing is slowed to a few tries per
/// pause.
#[derive(Debug, Clone, Copy)]
struct Failures {
    in_a_row: u32,
    pause: Duration,
    paused_until: Option<tokio::time::Instant>,
    last_wrong: tokio::time::Instant,
}

/// Per-address records and the times of the recent wrong passwords from anyone.
#[derive(Debug, Default)]
struct Throttle {
    by_address: HashMap<IpAddr, Failures>,
    recent_wrong: VecDeque<tokio::time::Instant>,
}

impl Throttle {
    /// `Err(Paused)` while `peer` must wait.
    fn check(&mut self, peer: IpAddr, now: tokio::time::Instant) -> std::result::Result<(), Refusal> {
        let secs = |d: Duration| d.as_secs_f64().ceil().max(1.0) as u64;
        let record = self.by_address.get(&peer).copied();
        if let Some(until) = record.and_then(|f| f.paused_until)
            && until > now
        {
            return Err(Refusal::Paused {
                retry_after_s: secs(until - now),
            });
        }
        while self
            .recent_wrong
            .front()
            .is_some_and(|t| now.duration_since(*t) >= GLOBAL_WINDOW)
        {
            self.recent_wrong.pop_front();
        }
        if self.recent_wrong.len() >= GLOBAL_WRONG_MAX
            && record.is_some_and(|f| f.in_a_row > 0)
            && !peer.is_loopback()
            && let Some(oldest) = self.recent_wrong.front()
        {
            return Err(Refusal::Paused {
                retry_after_s: secs(GLOBAL_WINDOW.saturating_sub(now.duration_since(*oldest))),
            });
        }
        Ok(())
    }

    fn wrong(&mut self, peer: IpAddr, now: tokio::time::Instant) {
        if !self.by_address.contains_key(&peer) && self.by_address.len() >= MAX_TRACKED_ADDRESSES {
            // Forget the address whose last wrong password is oldest.
            if let Some(old) = self
                .by_address
                .iter()
                .min_by_key(|(_, f)| f.last_wrong)
                .map(|(a, _)| *a)
            {
                self.by_address.remove(&old);
            }
        }
        let f = self.by_address.entry(peer).or_insert(Failures {
            in_a_row: 0,
            pause: Duration::ZERO,
            paused_until: None,
            last_wrong: now,
        });
        f.in_a_row += 1;
        f.last_wrong = now;
        if f.in_a_row >= FAILURES_BEFORE_PAUSE {
            f.pause = if f.pause.is_zero() {
                FIRST_PAUSE
            } else {
                (f.pause * 2).min(MAX_PAUSE)
            };
            f.paused_until = Some(now + f.pause);
            tracing::warn!(
                %peer,
                wrong_in_a_row = f.in_a_row,
                pause_s = f.pause.as_secs(),
                "operator password checks paused for this address after repeated wrong passwords"
            );
        }
        self.recent_wrong.push_back(now);
        if self.recent_wrong.len() > GLOBAL_WRONG_MAX {
            self.recent_wrong.pop_front();
        }
    }
}

/// Operator credential and the open sessions.
#[derive(Debug)]
pub struct OperatorAuth {
    hash: Option<String>,
    sessions: Mutex<HashMap<String, Instant>>,
    /// One Argon2 check at a time: each takes ~19 MiB and a core for a while, and a flood of
    /// requests must not take the board's memory or the processing loop's CPU.
    checking: tokio::sync::Semaphore,
    throttle: Mutex<Throttle>,
}

impl Default for OperatorAuth {
    /// No password: every change refused.
    fn default() -> Self {
        Self {
            hash: None,
            sessions: Mutex::new(HashMap::new()),
            checking: tokio::sync::Semaphore::new(1),
            throttle: Mutex::new(Throttle::default()),
        }
    }
}

impl OperatorAuth {
    /// `hash`: the configured PHC string (checked), or `None` (every change refused).
    pub fn new(hash: Option<String>) -> Result<Self> {
        if let Some(h) = &hash {
            check_hash(h)?;
        }
        Ok(Self {
            hash,
            ..Self::default()
        })
    }

    /// Whether a password from `peer` would be checked now: configured, and `peer` not
    /// waiting out a pause. Called before a sign-in body is read.
    pub fn precheck(&self, peer: IpAddr) -> std::result::Result<(), Refusal> {
        if !self.configured() {
            return Err(Refusal::NotConfigured);
        }
        self.paused(peer)
    }

    /// Checks a password from a request sent by `peer`: one check at a time, off the async
    /// threads, and refused without checking while `peer` waits out a pause after repeated
    /// wrong passwords (a right password then waits too, or the pause would not slow
    /// guessing). Pauses are per address, with a global ceiling that spares addresses without
    /// wrong passwords (see [`GLOBAL_WRONG_MAX`]).
    pub async fn check_password(
        self: &std::sync::Arc<Self>,
        password: String,
        peer: IpAddr,
    ) -> std::result::Result<(), Refusal> {
        self.precheck(peer)?;
        let Ok(_permit) = self.checking.acquire().await else {
            return Err(Refusal::BadCredentials);
        };
        // A check that waited for the permit may find a pause started meanwhile.
        self.paused(peer)?;
        let me = self.clone();
        let ok = tokio::task::spawn_blocking(move || me.verify(&password))
            .await
            .unwrap_or(false);
        let Ok(mut t) = self.throttle.lock() else {
            return Err(Refusal::BadCredentials);
        };
        if ok {
            t.by_address.remove(&peer);
            return Ok(());
        }
        t.wrong(peer, tokio::time::Instant::now());
        Err(Refusal::BadCredentials)
    }

    /// `Err(Paused)` while `peer` must wait.
    fn paused(&self, peer: IpAddr) -> std::result::Result<(), Refusal> {
        let now = tokio::time::Instant::now();
        match self.throttle.lock() {
            Ok(mut t) => t.check(peer, now),
            Err(_) => Err(Refusal::BadCredentials),
        }
    }

    /// An operator password hash is configured; without one every change is refused.
    pub fn configured(&self) -> bool {
        self.hash.is_some()
    }

    /// Verifies a password (slow on purpose: Argon2; call from a blocking context).
    ///
    /// Argon2's working memory (~19 MiB with the default parameters) is mapped for this one
    /// check and unmapped after it, so it goes back to the system at once: through the
    /// allocator, glibc kept each check's blocks in its per-thread arenas (RSS grew by ~19 MiB
    /// per check; issue 25).
    pub fn verify(&self, password: &str) -> bool {
        let Some(phc) = &self.hash else { return false };
        verify_phc(phc, password).unwrap_or(false)
    }

    /// Opens a session; returns its token.
    pub fn open_session(&self) -> String {
        let mut raw = [0u8; 32];
        rand::rngs::OsRng.fill_bytes(&mut raw);
        let token: String = raw.iter().map(|b| format!("{b:02x}")).collect();
        let now = Instant::now();
        if let Ok(mut s) = self.sessions.lock() {
            s.retain(|_, expiry| *expiry > now);
            if s.len() >= MAX_SESSIONS
                && let Some(oldest) = s.iter().min_by_key(|(_, e)| **e).map(|(k, _)| k.clone())
            {
                s.remove(&oldest);
            }
            s.insert(token.clone(), now + SESSION_TTL);
        }
        token
    }

    /// Ends the session `token` names (sign-out); unknown tokens are ignored.
    pub fn close_session(&self, token: &str) {
        if let Ok(mut s) = self.sessions.lock() {
            s.remove(token);
        }
    }

    /// Whether `token` names an open, unexpired session.
    pub fn session_valid(&self, token: &str) -> bool {
        self.sessions
            .lock()
            .map(|s| s.get(token).is_some_and(|e| *e > Instant::now()))
            .unwrap_or(false)
    }

    /// Whether the request carries a valid session cookie.
    pub fn signed_in(&self, headers: &HeaderMap) -> bool {
        session_token(headers).is_some_and(|t| self.session_valid(t))
    }

    /// Decides whether a change request may proceed: a valid session cookie, or HTTP Basic
    /// credentials with the right password (verified off the async threads).
    pub async fn authorize(
        self: &std::sync::Arc<Self>,
        headers: &HeaderMap,
        peer: IpAddr,
    ) -> std::result::Result<(), Refusal> {
        if !self.configured() {
            return Err(Refusal::NotConfigured);
        }
        if self.signed_in(headers) {
            return Ok(());
        }
        let Some(password) = basic_password(headers) else {
            return Err(Refusal::NotSignedIn);
        };
        self.check_password(password, peer).await
    }
}

/// `Some(matches)` for a well-formed Argon2id PHC string.
fn verify_phc(phc: &str, password: &str) -> Option<bool> {
    let h = PasswordHash::new(phc).ok()?;
    if h.algorithm != Algorithm::Argon2id.ident() {
        return None;
    }
    let expected = h.hash?;
    let params = argon2::Params::try_from(&h).ok()?;
    let version = match h.version {
        Some(v) => argon2::Version::try_from(v).ok()?,
        None => argon2::Version::default(),
    };
    let mut salt_buf = [0u8; 64];
    let salt = h.salt?.decode_b64(&mut salt_buf).ok()?;
    let mut out_buf = [0u8; 64];
    let out = out_buf.get_mut(..expected.len())?;
    let mut memory = BlockMemory::map(params.block_count())?;
    Argon2::new(Algorithm::Argon2id, version, params)
        .hash_password_into_with_memory(password.as_bytes(), salt, out, memory.blocks())
        .ok()?;
    // `Output`'s comparison takes the same time wherever the first difference is.
    Some(argon2::password_hash::Output::new(out).ok()? == expected)
}

/// Argon2 blocks in an anonymous mapping of their own, unmapped on drop.
struct BlockMemory {
    ptr: std::ptr::NonNull<argon2::Block>,
    blocks: usize,
}

impl BlockMemory {
    fn map(blocks: usize) -> Option<Self> {
        let bytes = blocks.checked_mul(std::mem::size_of::<argon2::Block>())?;
        if bytes == 0 {
            return None;
        }
        // SAFETY: an anonymous private read-write mapping; no file, no fixed address.
        let p = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                bytes,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
                -1,
                0,
            )
        };
        if p == libc::MAP_FAILED {
            return None;
        }
        Some(Self {
            ptr: std::ptr::NonNull::new(p.cast())?,
            blocks,
        })
    }

    fn blocks(&mut self) -> &mut [argon2::Block] {
        // SAFETY: the mapping is `blocks` blocks long, page-aligned (more than a Block's 64-byte
        // alignment), zero-filled (a valid Block: plain u64 words) and owned by `self`.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.as_ptr(), self.blocks) }
    }
}

impl Drop for BlockMemory {
    fn drop(&mut self) {
        // SAFETY: unmaps exactly the mapping made in `map`.
        unsafe {
            libc::munmap(
                self.ptr.as_ptr().cast(),
                self.blocks * std::mem::size_of::<argon2::Block>(),
            );
        }
    }
}

// SAFETY: the mapping is owned exclusively by this value.
unsafe impl Send for BlockMemory {}

/// The session token from the `Cookie` header(s).
pub fn session_token(headers: &HeaderMap) -> Option<&str> {
    headers
        .get_all(header::COOKIE)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(';'))
        .find_map(|kv| {
            let (k, v) = kv.trim().split_once('=')?;
            (k == SESSION_COOKIE).then_some(v)
        })
}

/// The password of HTTP Basic credentials for [`BASIC_USER`].
fn basic_password(headers: &HeaderMap) -> Option<String> {
    let v = headers.get(header::AUTHORIZATION)?.to_str().ok()?;
    let (scheme, b64) = v.split_once(' ')?;
    if !scheme.eq_ignore_ascii_case("basic") {
        return None;
    }
    let raw = base64::engine::general_purpose::STANDARD
        .decode(b64.trim())
        .ok()?;
    let text = String::from_utf8(raw).ok()?;
    let (user, password) = text.split_once(':')?;
    (user == BASIC_USER).then(|| password.to_string())
}

/// `Authorization` header value for scripts and tests.
pub fn basic_header(password: &str) -> String {
    format!(
        "Basic {}",
        base64::engine::general_purpose::STANDARD.encode(format!("{BASIC_USER}:{password}"))
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hash_verifies_and_rejects_wrong_password() {
        let h = hash_password("s3cret").unwrap();
        assert!(h.starts_with("$argon2id$"), "{h}");
        check_hash(&h).unwrap();
        let a = OperatorAuth::new(Some(h)).unwrap();
        assert!(a.verify("s3cret"));
        assert!(!a.verify("s3cret "));
        assert!(hash_password("").is_err());
        assert!(check_hash("plain").is_err());
    }

    #[tokio::test(start_paused = true)]
    async fn wrong_passwords_in_a_row_pause_checks_that_double_then_reset() {
        let a = std::sync::Arc::new(OperatorAuth::new(Some(hash_password("right").unwrap())).unwrap());
        let peer: IpAddr = "10.0.0.7".parse().unwrap();
        let check = |p: &str| {
            let a = a.clone();
            let p = p.to_string();
            async move { a.check_password(p, peer).await }
        };
        // Four wrong, then right: no pause, and the count starts again.
        for _ in 0..FAILURES_BEFORE_PAUSE - 1 {
            assert_eq!(check("wrong").await, Err(Refusal::BadCredentials));
        }
        assert_eq!(check("right").await, Ok(()));
        for _ in 0..FAILURES_BEFORE_PAUSE {
            assert_eq!(check("wrong").await, Err(Refusal::BadCredentials));
        }
        // Paused: even the right password is refused unchecked.
        assert_eq!(check("right").await, Err(Refusal::Paused { retry_after_s: 10 }));
        tokio::time::advance(Duration::from_secs(4)).await;
        assert_eq!(check("right").await, Err(Refusal::Paused { retry_after_s: 6 }));
        tokio::time::advance(Duration::from_secs(6)).await;
        // Another wrong one right after the pause doubles it.
        assert_eq!(check("wrong").await, Err(Refusal::BadCredentials));
        assert_eq!(check("right").await, Err(Refusal::Paused { retry_after_s: 20 }));
        tokio::time::advance(Duration::from_secs(20)).await;
        assert_eq!(check("right").await, Ok(()));
        // A success forgets the pauses: the next run of wrong ones starts at 10 s again.
        for _ in 0..FAILURES_BEFORE_PAUSE {
            assert_eq!(check("wrong").await, Err(Refusal::BadCredentials));
        }
        assert_eq!(check("right").await, Err(Refusal::Paused { retry_after_s: 10 }));
        // The cap.
        for _ in 0..8 {
            tokio::time::advance(MAX_PAUSE).await;
            assert_eq!(check("wrong").await, Err(Refusal::BadCredentials));
        }
        assert_eq!(
            check("right").await,
            Err(Refusal::Paused {
                retry_after_s: MAX_PAUSE.as_secs()
            })
        );
        let r = Refusal::Paused { retry_after_s: 7 }.response();
        assert_eq!(r.status(), StatusCode::TOO_MANY_REQUESTS);
        assert_eq!(r.headers()[header::RETRY_AFTER], "7");
        // Nothing configured: refused before any check.
        let none = std::sync::Arc::new(OperatorAuth::default());
        assert_eq!(
            none.check_password("x".into(), peer).await,
            Err(Refusal::NotConfigured)
        );
    }

    #[tokio::test(start_paused = true)]
    async fn pauses_are_per_address_and_the_global_ceiling_spares_clean_addresses() {
        let a = std::sync::Arc::new(OperatorAuth::new(Some(hash_password("right").unwrap())).unwrap());
        let addr = |i: u32| IpAddr::from(std::net::Ipv4Addr::from(0x0a00_0000 + i));
        // One address guessing does not pause another.
        for _ in 0..FAILURES_BEFORE_PAUSE {
            assert_eq!(
                a.check_password("wrong".into(), addr(1)).await,
                Err(Refusal::BadCredentials)
            );
        }
        assert!(matches!(a.precheck(addr(1)), Err(Refusal::Paused { .. })));
        assert_eq!(a.check_password("right".into(), addr(2)).await, Ok(()));
        // Many addresses guessing reach the global ceiling: those that guessed wrong wait ...
        for i in 10..10 + GLOBAL_WRONG_MAX as u32 {
            let _ = a.check_password("wrong".into(), addr(i)).await;
        }
        let r = a.check_password("right".into(), addr(10)).await;
        assert!(
            matches!(r, Err(Refusal::Paused { retry_after_s }) if retry_after_s <= 60),
            "{r:?}"
        );
        // ... but an address without a wrong password, and loopback, are still checked.
        assert_eq!(a.check_password("right".into(), addr(999)).await, Ok(()));
        let lo: IpAddr = "127.0.0.1".parse().unwrap();
        assert_eq!(
            a.check_password("wrong".into(), lo).await,
            Err(Refusal::BadCredentials)
        );
        assert_eq!(a.check_password("right".into(), lo).await, Ok(()));
        // The window passes: the ceiling lifts.
        tokio::time::advance(GLOBAL_WINDOW).await;
        assert_eq!(a.check_password("right".into(), addr(10)).await, Ok(()));
    }

    #[test]
    fn mapped_memory_verify_agrees_with_the_argon2_verifier() {
        use argon2::password_hash::PasswordVerifier;
        // Default parameters, and others (several lanes, another memory and time cost).
        let other = Argon2::new(
            Algorithm::Argon2id,
            argon2::Version::V0x13,
            argon2::Params::new(4096, 3, 2, Some(24)).unwrap(),
        );
        let salt = SaltString::encode_b64(b"0123456789abcdef").unwrap();
        let phcs = [
            hash_password("right").unwrap(),
            other.hash_password(b"right", &salt).unwrap().to_string(),
        ];
        for phc in &phcs {
            let parsed = PasswordHash::new(phc).unwrap();
            for pw in ["right", "wrong", "", "right "] {
                let reference = Argon2::default().verify_password(pw.as_bytes(), &parsed).is_ok();
                assert_eq!(verify_phc(phc, pw), Some(reference), "{phc} {pw:?}");
            }
        }
        // Not argon2id: refused as malformed.
        let argon2i = Argon2::new(
            Algorithm::Argon2i,
            argon2::Version::V0x13,
            argon2::Params::default(),
        );
        let phc = argon2i.hash_password(b"right", &salt).unwrap().to_string();
        assert_eq!(verify_phc(&phc, "right"), None);
    }

    #[test]
    fn sessions_and_basic_credentials_are_parsed() {
        let a = OperatorAuth::new(None).unwrap();
        let t = a.open_session();
        assert_eq!(t.len(), 64);
        let mut h = HeaderMap::new();
        h.insert(
            header::COOKIE,
            format!("x=1; {SESSION_COOKIE}={t}").parse().unwrap(),
        );
        assert!(a.signed_in(&h));
        a.close_session(&t);
        assert!(!a.signed_in(&h));
        let mut h = HeaderMap::new();
        h.insert(
            header::AUTHORIZATION,
            basic_header("pw:with:colons").parse().unwrap(),
        );
        assert_eq!(basic_password(&h).as_deref(), Some("pw:with:colons"));
    }
}
