//! HTTP pieces shared by the status listener's modules (`status`, `live`, `auth`, `server`):
//! plain-text and JSON answers, the security headers of every answer, and the Host and Origin
//! rules (docs/security.md). A leaf module: it uses none of the others, so they import it and
//! not each other.

use std::net::{IpAddr, SocketAddr};

use axum::http::{HeaderMap, HeaderName, HeaderValue, Method, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

/// A plain-text answer (every error is a sentence ending in a newline). Texts are fixed
/// sentences: they never repeat what the request sent (no reflected input).
pub(crate) fn text(code: StatusCode, body: impl Into<String>) -> Response {
    (
        code,
        [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
        body.into(),
    )
        .into_response()
}

/// A JSON answer; `body` carries its own trailing newline.
pub(crate) fn json_text(code: StatusCode, body: String) -> Response {
    (code, [(header::CONTENT_TYPE, "application/json")], body).into_response()
}

/// `v` as one JSON line.
pub(crate) fn json_line<T: Serialize>(v: &T) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "null".into()) + "\n"
}

/// Largest request body (tuning and login JSON are a few hundred bytes).
pub const MAX_REQUEST_BODY_BYTES: usize = 64 * 1024;

/// Content-Security-Policy of every answer: the set-up page loads its scripts, styles and
/// images only from the board (`blob:`/`data:` images for the previews the page decodes
/// itself) and talks only to the board; no other page may frame it. `inline_script_hashes`:
/// base64 SHA-256 of each inline script the page has (its import map), allowed by hash.
pub fn content_security_policy(inline_script_hashes: &[String]) -> String {
    let inline: String = inline_script_hashes
        .iter()
        .map(|h| format!(" 'sha256-{h}'"))
        .collect();
    format!(
        "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; style-src 'self'; \
         script-src 'self'{inline}; object-src 'none'; base-uri 'none'; form-action 'self'; \
         frame-ancestors 'none'"
    )
}

/// Base64 SHA-256 of every inline `<script>` (one without `src`) in `html`, as CSP wants them.
pub fn inline_script_hashes(html: &str) -> Vec<String> {
    use base64::Engine as _;
    use sha2::Digest as _;
    let mut out = Vec::new();
    let mut rest = html;
    while let Some(start) = rest.find("<script") {
        let after = &rest[start..];
        let Some(open_end) = after.find('>') else { break };
        let tag = &after[..open_end];
        let body_and_more = &after[open_end + 1..];
        let Some(close) = body_and_more.find("</script>") else {
            break;
        };
        if !tag.contains("src=") {
            let digest = sha2::Sha256::digest(&body_and_more.as_bytes()[..close]);
            out.push(base64::engine::general_purpose::STANDARD.encode(digest));
        }
        rest = &body_and_more[close..];
    }
    out
}

/// Headers added to every answer of the status listener (if the handler did not set them);
/// `csp` from [`content_security_policy`].
pub fn security_headers(csp: &str) -> Vec<(HeaderName, HeaderValue)> {
    let mut h = vec![
        (
            header::X_CONTENT_TYPE_OPTIONS,
            HeaderValue::from_static("nosniff"),
        ),
        (header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY")),
        (header::REFERRER_POLICY, HeaderValue::from_static("no-referrer")),
        (
            HeaderName::from_static("cross-origin-resource-policy"),
            HeaderValue::from_static("same-origin"),
        ),
    ];
    if let Ok(v) = HeaderValue::from_str(csp) {
        h.push((header::CONTENT_SECURITY_POLICY, v));
    }
    h
}

/// The two ends of one accepted connection (a request extension set by the accept loop).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnInfo {
    /// The client's address.
    pub peer: SocketAddr,
    /// Our address the client connected to.
    pub local: SocketAddr,
}

/// Which `Host` names the board answers to (docs/security.md, "Host and Origin").
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct HostPolicy {
    /// Names from `[status] allowed_hosts` and the machine's own host name (lower case).
    names: Vec<String>,
}

impl HostPolicy {
    /// `configured`: extra names (DNS names or addresses) the board is reached by.
    pub fn new(configured: &[String]) -> Self {
        let mut names: Vec<String> = configured.iter().map(|n| n.trim().to_ascii_lowercase()).collect();
        if let Some(h) = own_host_name() {
            names.push(format!("{h}.local"));
            names.push(h);
        }
        names.retain(|n| !n.is_empty());
        names.sort();
        names.dedup();
        Self { names }
    }

    /// Whether a `Host` value (`name[:port]`) names this board on a connection to `local`.
    ///
    /// An address literal is always accepted: DNS rebinding needs a name the attacker
    /// controls, and a browser that reached the board by its address has the board's own
    /// origin (this also covers NAT and port forwarding, where the address differs from the
    /// listener's). `localhost` only on a loopback listener. Names: the configured list and
    /// the host name.
    pub fn host_allowed(&self, host: &str, local: IpAddr) -> bool {
        let Some(name) = host_name_of(host) else {
            return false;
        };
        if name.parse::<IpAddr>().is_ok() {
            return true;
        }
        if name == "localhost" || name.ends_with(".localhost") {
            return local.is_loopback();
        }
        self.names.contains(&name)
    }
}

/// The host part of a `Host` or Origin authority (`name`, `name:port`, `[v6]:port`), lower
/// case, without brackets. `None` when malformed.
fn host_name_of(authority: &str) -> Option<String> {
    let a = authority.trim();
    if a.is_empty() || a.contains(['/', '@', ' ']) {
        return None;
    }
    let host = if let Some(rest) = a.strip_prefix('[') {
        let (v6, _) = rest.split_once(']')?;
        v6
    } else {
        match a.rsplit_once(':') {
            Some((h, port)) if port.chars().all(|c| c.is_ascii_digit()) => h,
            Some(_) => return None,
            None => a,
        }
    };
    (!host.is_empty()).then(|| host.trim_end_matches('.').to_ascii_lowercase())
}

/// The authority (`host[:port]`) of an Origin value `scheme://authority`, lower case.
fn origin_authority(origin: &str) -> Option<String> {
    let (scheme, rest) = origin.trim().split_once("://")?;
    if !matches!(scheme, "http" | "https") || rest.contains('/') {
        return None;
    }
    let rest = rest.to_ascii_lowercase();
    // A default port may be written or not; compare without it.
    let default_port = if scheme == "https" { ":443" } else { ":80" };
    Some(
        rest.strip_suffix(default_port)
            .map(str::to_string)
            .unwrap_or(rest),
    )
}

/// Why a request was refused by [`check_request`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// `Host` names something this board is not (DNS rebinding).
    ForeignHost,
    /// A change or WebSocket upgrade from another site's page.
    ForeignOrigin,
}

impl Refused {
    /// 421 for a foreign Host, 403 for a foreign Origin; fixed texts (nothing echoed).
    pub fn response(self) -> Response {
        match self {
            Refused::ForeignHost => text(
                StatusCode::MISDIRECTED_REQUEST,
                "this board does not answer to that host name: use its address, or add the name \
                 to [status] allowed_hosts (docs/security.md)\n",
            ),
            Refused::ForeignOrigin => text(
                StatusCode::FORBIDDEN,
                "changes and live connections are accepted only from the board's own page \
                 (the request's Origin is another site; docs/security.md)\n",
            ),
        }
    }
}

/// Whether a request changes something or opens a WebSocket (what the Origin rule covers).
pub fn needs_origin_check(method: &Method, headers: &HeaderMap) -> bool {
    let upgrade = headers
        .get(header::UPGRADE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.eq_ignore_ascii_case("websocket"));
    upgrade || !matches!(*method, Method::GET | Method::HEAD | Method::OPTIONS)
}

/// The Host and Origin rules for one request on a connection to `local`:
/// - a `Host` naming something else is refused (a request without `Host` comes from a
///   program, not a browser, and passes);
/// - a change or WebSocket upgrade whose `Origin` is not the page's own origin (same
///   authority as `Host`, and `Host` allowed) is refused; `Origin: null` too. Requests without
///   `Origin` are not from a browser page (browsers send it on every POST and upgrade).
pub fn check_request(
    policy: &HostPolicy,
    method: &Method,
    headers: &HeaderMap,
    local: IpAddr,
) -> Result<(), Refused> {
    let host = headers.get(header::HOST).map(|v| v.to_str().unwrap_or(""));
    if let Some(h) = host
        && !policy.host_allowed(h, local)
    {
        return Err(Refused::ForeignHost);
    }
    if !needs_origin_check(method, headers) {
        return Ok(());
    }
    let Some(origin) = headers.get(header::ORIGIN) else {
        return Ok(());
    };
    let origin = origin.to_str().ok().and_then(origin_authority);
    let same = match (origin, host) {
        (Some(o), Some(h)) => {
            let h = h.trim().to_ascii_lowercase();
            let h = h.strip_suffix(":80").map(str::to_string).unwrap_or(h);
            o == h
        }
        // A browser always sends Host; an Origin without it is nobody we know.
        _ => false,
    };
    if same { Ok(()) } else { Err(Refused::ForeignOrigin) }
}

fn own_host_name() -> Option<String> {
    let mut buf = [0u8; 256];
    // SAFETY: the buffer is valid for its length; gethostname NUL-terminates within it or
    // truncates, and we stop at the first NUL.
    let rc = unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) };
    if rc != 0 {
        return None;
    }
    let end = buf.iter().position(|b| *b == 0).unwrap_or(buf.len());
    let name = std::str::from_utf8(&buf[..end]).ok()?.trim().to_ascii_lowercase();
    (!name.is_empty() && name != "localhost").then_some(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(HeaderName::from_bytes(k.as_bytes()).unwrap(), v.parse().unwrap());
        }
        h
    }

    const LO: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);
    const LAN: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 5));

    #[test]
    fn inline_scripts_are_hashed_for_the_policy() {
        let html = "<script src=\"/a.js\"></script>\n<script type=\"importmap\">\n{}\n</script>";
        let hashes = inline_script_hashes(html);
        // sha256("\n{}\n"), base64
        assert_eq!(hashes, ["mStsuk6tXQZUQnBANrxib2jrZTl4uAW3mHJbbb97898="]);
        let csp = content_security_policy(&hashes);
        assert!(csp.contains("script-src 'self' 'sha256-mStsuk6tXQZUQnBANrxib2jrZTl4uAW3mHJbbb97898=';"));
        assert!(csp.contains("frame-ancestors 'none'"));
    }

    #[test]
    fn host_rule() {
        let p = HostPolicy::new(&["Board.example".into()]);
        assert!(p.host_allowed("127.0.0.1:7704", LO));
        assert!(p.host_allowed("10.0.0.5", LAN));
        assert!(p.host_allowed("[::1]:7704", LO));
        assert!(p.host_allowed("board.example:7704", LAN));
        assert!(p.host_allowed("BOARD.EXAMPLE.", LAN));
        assert!(p.host_allowed("localhost:7704", LO));
        assert!(!p.host_allowed("localhost:7704", LAN));
        assert!(!p.host_allowed("evil.example", LAN));
        assert!(!p.host_allowed("evil.example:7704", LO));
        assert!(!p.host_allowed("board.example.evil.example", LAN));
        assert!(!p.host_allowed("", LAN));
        assert!(!p.host_allowed("a/b", LAN));
        assert!(!p.host_allowed("x:y", LAN));
    }

    #[test]
    fn origin_rule() {
        let p = HostPolicy::new(&[]);
        let post = Method::POST;
        let ok = |h: &[(&str, &str)]| check_request(&p, &post, &headers(h), LO);
        assert_eq!(ok(&[("host", "127.0.0.1:7704")]), Ok(()));
        assert_eq!(
            ok(&[("host", "127.0.0.1:7704"), ("origin", "http://127.0.0.1:7704")]),
            Ok(())
        );
        assert_eq!(
            ok(&[("host", "127.0.0.1:7704"), ("origin", "http://evil.example")]),
            Err(Refused::ForeignOrigin)
        );
        assert_eq!(
            ok(&[("host", "127.0.0.1:7704"), ("origin", "http://127.0.0.1:7705")]),
            Err(Refused::ForeignOrigin)
        );
        assert_eq!(
            ok(&[("host", "127.0.0.1:7704"), ("origin", "null")]),
            Err(Refused::ForeignOrigin)
        );
        assert_eq!(
            ok(&[("host", "127.0.0.1"), ("origin", "http://127.0.0.1:80")]),
            Ok(())
        );
        assert_eq!(ok(&[("host", "evil.example")]), Err(Refused::ForeignHost));
        // Reads are not checked for Origin (the browser keeps other sites from reading them).
        let get = Method::GET;
        let h = headers(&[("host", "127.0.0.1:7704"), ("origin", "http://evil.example")]);
        assert_eq!(check_request(&p, &get, &h, LO), Ok(()));
        // ... but a WebSocket upgrade is.
        let h = headers(&[
            ("host", "127.0.0.1:7704"),
            ("origin", "http://evil.example"),
            ("upgrade", "websocket"),
        ]);
        assert_eq!(check_request(&p, &get, &h, LO), Err(Refused::ForeignOrigin));
    }
}
