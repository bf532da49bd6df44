//! Hostile clients against the real `irtrackd` (issue 25; threat table in docs/security.md).
//!
//! Each probe starts irtrackd as a child process (simulated cameras at 60 sets/s, operator
//! password, robot control on, a robot link to a closed port so stop requests have a link to
//! act on), attacks it over loopback with real sockets — bounded in count and time — and
//! checks while the attack lasts:
//! - the processing loop's sets/s stays at ≥ 85 % of its rate before the attack (the
//!   simulator paces 60 sets/s; the margin is for this shared test machine);
//! - `/status` answers a fresh client (a loopback address of its own) within 100 ms
//!   (median of three tries, again for the shared machine);
//! - the active parameter set is unchanged (rig id and swap count);
//! - irtrackd's RSS stays within the bound the probe states.
//!
//! Attackers use addresses of 127.0.2.0/24 .. 127.0.8.0/24 and 127.0.10.0/24 (Linux answers
//! all of 127/8 on loopback), fresh clients 127.0.9.0/24, so the per-address caps and throttles act as they
//! would on a network. Needs the irtrackd binary (`cargo build -p irtrack-firmware`).

mod common;

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::{Duration, Instant};

use common::*;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

const SETS_PER_S: f64 = 60.0;
const RATE_KEPT: f64 = 0.85;
const FRESH_STATUS_MAX: Duration = Duration::from_millis(100);

/// A running irtrackd child.
struct Board {
    _irtrackd: Irtrackd,
    pid: u32,
    status: SocketAddr,
    params: SocketAddr,
    ndjson: SocketAddr,
    binary: SocketAddr,
    stderr: PathBuf,
    _dir: TempDir,
}

/// `[robot]` pointing at a closed port: the link exists (stop requests act on it) and never
/// connects.
const ROBOT: &str = r#"
[robot]
address = "127.0.0.1:9"
[robot.safety]
workspace_min_mm = [-1000.0, -1000.0, 100.0]
workspace_max_mm = [1000.0, 1000.0, 3000.0]
max_step_mm = 40.0
max_speed_mm_s = 400.0
max_gap_mm = 2.0
max_age_ms = 200
[robot.deadman]
kind = "flag"
"#;

/// Starts irtrackd with `extra` config lines; `nofile`: soft RLIMIT_NOFILE of the child.
fn start_board(name: &str, extra_service: &str, extra: &str, nofile: Option<u64>) -> Board {
    let dir = temp_dir(&format!("hostile-{name}"));
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            "[service]\nparams_from_simulator = true\ncontrol = true\n{}\n{extra_service}\n\
             [source.sim]\nfps = {SETS_PER_S:?}\n[leds]\nbackend = \"none\"\n{extra}\n{ROBOT}",
            operator_hash_line()
        ),
    )
    .unwrap();
    let stderr = dir.join("stderr.log");
    let mut cmd = Irtrackd::command(&bin("irtrackd"), &config, &dir.join("state"));
    cmd.env("RUST_LOG", "warn")
        .stderr(std::fs::File::create(&stderr).unwrap());
    if let Some(n) = nofile {
        use std::os::unix::process::CommandExt;
        // SAFETY: only setrlimit (async-signal-safe) runs between fork and exec.
        unsafe {
            cmd.pre_exec(move || {
                let mut r = libc::rlimit {
                    rlim_cur: 0,
                    rlim_max: 0,
                };
                if libc::getrlimit(libc::RLIMIT_NOFILE, &mut r) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                r.rlim_cur = n as libc::rlim_t;
                if libc::setrlimit(libc::RLIMIT_NOFILE, &r) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    }
    let irtrackd = Irtrackd::spawn(&mut cmd, Duration::from_secs(20)).unwrap_or_else(|e| panic!("{e}"));
    let line = irtrackd.ready().line.clone();
    Board {
        pid: irtrackd.pid(),
        _irtrackd: irtrackd,
        status: addr_field(&line, "status="),
        params: addr_field(&line, "params="),
        ndjson: addr_field(&line, "stream="),
        binary: addr_field(&line, "binary="),
        stderr,
        _dir: dir,
    }
}

/// The attackers' addresses: `n` of them in 127.0.`net`.0/24.
fn attackers(net: u8, n: u8) -> Vec<IpAddr> {
    (1..=n)
        .map(|i| IpAddr::V4(Ipv4Addr::new(127, 0, net, i)))
        .collect()
}

/// A loopback address no other client of this test binary used.
fn fresh_addr() -> IpAddr {
    static NEXT: AtomicU8 = AtomicU8::new(1);
    IpAddr::V4(Ipv4Addr::new(127, 0, 9, NEXT.fetch_add(1, Ordering::Relaxed)))
}

async fn connect_from(src: IpAddr, dst: SocketAddr) -> std::io::Result<TcpStream> {
    let s = TcpSocket::new_v4()?;
    s.bind(SocketAddr::new(src, 0))?;
    tokio::time::timeout(Duration::from_secs(3), s.connect(dst))
        .await
        .map_err(|_| std::io::Error::new(std::io::ErrorKind::TimedOut, "connect"))?
}

/// One raw HTTP/1.1 request from `src`; (status code, head, body). The board closes after
/// every answer.
async fn http_from(src: IpAddr, dst: SocketAddr, request: &str) -> (u16, String, String) {
    let mut s = connect_from(src, dst).await.unwrap();
    s.write_all(request.as_bytes()).await.unwrap();
    let mut resp = Vec::new();
    tokio::time::timeout(Duration::from_secs(15), s.read_to_end(&mut resp))
        .await
        .expect("no answer within 15 s")
        .unwrap();
    let resp = String::from_utf8_lossy(&resp).to_string();
    let (head, body) = resp.split_once("\r\n\r\n").unwrap_or((&resp, ""));
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (code, head.to_string(), body.to_string())
}

fn req(method: &str, path: &str, host: SocketAddr, headers: &str, body: &str) -> String {
    format!(
        "{method} {path} HTTP/1.1\r\nHost: {host}\r\n{headers}Content-Length: {}\r\n\r\n{body}",
        body.len()
    )
}

/// `GET /status` from a fresh address: (time to the whole answer, JSON).
async fn fresh_status(b: &Board) -> (Duration, serde_json::Value) {
    let t0 = Instant::now();
    let (code, _, body) = http_from(fresh_addr(), b.status, &req("GET", "/status", b.status, "", "")).await;
    let dt = t0.elapsed();
    assert_eq!(code, 200, "{body}");
    (dt, serde_json::from_str(&body).unwrap())
}

fn rss_kib(pid: u32) -> u64 {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    s.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap()
}

/// A counter or gauge from `/metrics` (first line starting with `name`).
async fn metric(b: &Board, name: &str) -> f64 {
    let (_, _, body) = http_from(fresh_addr(), b.status, &req("GET", "/metrics", b.status, "", "")).await;
    body.lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("{name} not in /metrics"))
}

async fn sets_per_s(b: &Board) -> f64 {
    let (_, a) = fresh_status(b).await;
    let t0 = Instant::now();
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let (_, z) = fresh_status(b).await;
    let n = |v: &serde_json::Value| v["processing"]["sets_processed"].as_u64().unwrap();
    (n(&z) - n(&a)) as f64 / t0.elapsed().as_secs_f64()
}

/// What the invariants compare against.
struct Baseline {
    sets_per_s: f64,
    rig: (String, u64),
    rss_kib: u64,
}

fn rig(v: &serde_json::Value) -> (String, u64) {
    (
        v["params"]["rig_id"].as_str().unwrap_or("").to_string(),
        v["params"]["swaps"].as_u64().unwrap(),
    )
}

async fn baseline(b: &Board) -> Baseline {
    // Let the loop and the first status answers settle.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (_, v) = fresh_status(b).await;
    let base = Baseline {
        sets_per_s: sets_per_s(b).await,
        rig: rig(&v),
        rss_kib: rss_kib(b.pid),
    };
    assert!(!base.rig.0.is_empty(), "no active parameter set");
    assert!(
        base.sets_per_s > 0.8 * SETS_PER_S,
        "loop runs at {:.1} sets/s before any attack",
        base.sets_per_s
    );
    base
}

/// The four invariants, during an attack.
async fn invariants(b: &Board, base: &Baseline, rss_bound_kib: u64, what: &str) {
    let mut times = Vec::new();
    let mut last = serde_json::Value::Null;
    for _ in 0..3 {
        let (dt, v) = fresh_status(b).await;
        times.push(dt);
        last = v;
    }
    times.sort();
    assert!(
        times[1] < FRESH_STATUS_MAX,
        "{what}: /status took {times:?} for a fresh client"
    );
    assert_eq!(rig(&last), base.rig, "{what}: the active parameter set changed");
    let rate = sets_per_s(b).await;
    assert!(
        rate >= RATE_KEPT * base.sets_per_s,
        "{what}: loop at {rate:.1} sets/s, was {:.1}",
        base.sets_per_s
    );
    let rss = rss_kib(b.pid);
    assert!(
        rss <= base.rss_kib + rss_bound_kib,
        "{what}: RSS {rss} KiB, idle {} KiB, bound +{rss_bound_kib} KiB",
        base.rss_kib
    );
    eprintln!(
        "{what}: fresh /status {times:?}, {rate:.1} sets/s (before {:.1}), RSS {} -> {rss} KiB",
        base.sets_per_s, base.rss_kib
    );
}

/// Whether the server closed `s` (EOF or reset) within `within`.
async fn closed_within(s: &mut TcpStream, within: Duration) -> bool {
    let mut buf = [0u8; 4096];
    let deadline = Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match tokio::time::timeout(left, s.read(&mut buf)).await {
            Err(_) => return false,
            Ok(Ok(0)) | Ok(Err(_)) => return true,
            Ok(Ok(_)) => continue,
        }
    }
}

/// Opens up to `n` connections from each of `srcs` to `dst`, sending `first` on each; keeps
/// the ones that stayed open (the board closes those over a cap at once).
async fn hold(srcs: &[IpAddr], dst: SocketAddr, n: usize, first: &[u8]) -> Vec<TcpStream> {
    let mut held = Vec::new();
    for src in srcs {
        for _ in 0..n {
            if let Ok(mut s) = connect_from(*src, dst).await {
                let _ = s.write_all(first).await;
                held.push(s);
            }
        }
    }
    held
}

/// Probe: request heads that never finish, and bodies that never come.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_heads_and_slow_bodies_are_timed_out() {
    let b = start_board("slow", "", "", None);
    let base = baseline(&b).await;
    let t0 = Instant::now();
    let mut heads = hold(&attackers(2, 3), b.status, 40, b"GET /status HTTP/1.1\r\nHo").await;
    let body_req = req(
        "POST",
        "/api/login",
        b.status,
        "Content-Type: application/json\r\n",
        "",
    )
    .replace("Content-Length: 0", "Content-Length: 1000");
    let mut bodies = hold(&attackers(3, 3), b.status, 40, body_req.as_bytes()).await;
    invariants(&b, &base, 20 * 1024, "slow heads and bodies").await;
    // A change request is refused before its body is read: the answer comes though the body
    // never does.
    let mut s = connect_from(fresh_addr(), b.status).await.unwrap();
    s.write_all(
        req("POST", "/api/tuning", b.status, "", "")
            .replace("Content-Length: 0", "Content-Length: 1000")
            .as_bytes(),
    )
    .await
    .unwrap();
    let mut answer = vec![0u8; 1024];
    let n = tokio::time::timeout(Duration::from_secs(2), s.read(&mut answer))
        .await
        .expect("credentials are checked before the body")
        .unwrap();
    assert!(
        String::from_utf8_lossy(&answer[..n]).starts_with("HTTP/1.1 401"),
        "{}",
        String::from_utf8_lossy(&answer[..n])
    );
    // Heads: 5 s; bodies: 5 s without a byte. Everything is closed well within 12 s.
    for s in heads.iter_mut().chain(bodies.iter_mut()) {
        let left = Duration::from_secs(12).saturating_sub(t0.elapsed());
        assert!(
            closed_within(s, left).await,
            "a slow connection was still open after 12 s"
        );
    }
    assert!(metric(&b, "irtrackd_connection_timeouts_total{listener=\"status\"}").await >= 1.0);
    eprintln!(
        "{} slow heads and {} slow bodies held, all closed after {:?}",
        heads.len(),
        bodies.len(),
        t0.elapsed()
    );
}

/// Probe: 2,000 idle connections over all four listeners with the soft open-file limit at 1024.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_thousand_idle_connections_under_a_1024_file_limit() {
    // This process needs its own 2,000 descriptors; the child gets 1024.
    // SAFETY: plain get/setrlimit on this process.
    unsafe {
        let mut r = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        assert_eq!(libc::getrlimit(libc::RLIMIT_NOFILE, &mut r), 0);
        assert!(
            r.rlim_max >= 4096,
            "hard file limit {} too low for this test",
            r.rlim_max
        );
        r.rlim_cur = r.rlim_max.min(65536);
        assert_eq!(libc::setrlimit(libc::RLIMIT_NOFILE, &r), 0);
    }
    let b = start_board("idle", "", "", Some(1024));
    let base = baseline(&b).await;
    let srcs = attackers(4, 4);
    let mut held = Vec::new();
    held.extend(hold(&srcs, b.status, 250, b"").await);
    held.extend(hold(&srcs, b.params, 125, b"").await);
    held.extend(hold(&srcs, b.ndjson, 63, b"").await);
    held.extend(hold(&srcs, b.binary, 62, b"").await);
    assert!(held.len() >= 1900, "only {} connections were made", held.len());
    invariants(&b, &base, 30 * 1024, "2,000 idle connections").await;
    let refused = metric(
        &b,
        "irtrackd_connections_refused_total{listener=\"status\",reason=\"peer\"}",
    )
    .await;
    assert!(refused >= 500.0, "status refusals counted: {refused}");
    let log = std::fs::read_to_string(&b.stderr).unwrap();
    assert!(
        !log.contains("Too many open files"),
        "irtrackd ran out of descriptors:\n{log}"
    );
    eprintln!("held {} of 2,000 connections on the client side", held.len());
}

/// Probe: slow request heads from ten addresses, 32 each (the per-address cap): together more
/// than the status port's 256 slots, held for the whole 5 s head timeout. A fresh client is
/// still answered at once: at the cap the board closes the oldest unanswered exchange of the
/// address that holds the most.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slot_flood_from_ten_addresses_leaves_status_answering() {
    let b = start_board("slotflood", "", "", None);
    let base = baseline(&b).await;
    let t0 = Instant::now();
    let held = hold(&attackers(10, 10), b.status, 32, b"GET /status HTTP/1.1\r\nHo").await;
    assert!(held.len() >= 256, "only {} connections were made", held.len());
    invariants(&b, &base, 20 * 1024, "256 status slots held by 10 addresses").await;
    assert!(
        t0.elapsed() < Duration::from_secs(5),
        "the probe outlived the head timeout ({:?}); it proves nothing",
        t0.elapsed()
    );
    let evicted = metric(
        &b,
        "irtrackd_connections_refused_total{listener=\"status\",reason=\"evicted\"}",
    )
    .await;
    assert!(
        evicted >= 1.0,
        "no unanswered exchange was closed for a fresh client"
    );
    eprintln!(
        "{} slow heads held, {evicted} closed for fresh clients",
        held.len()
    );
}

/// Probes: a lock-out attempt on the operator sign-in, and stop requests during a throttle.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn signin_lockout_fails_and_stop_requests_pass_the_throttle() {
    let b = start_board("lockout", "", "", None);
    let base = baseline(&b).await;
    let login = |password: &str| {
        req(
            "POST",
            "/api/login",
            b.status,
            "Content-Type: application/json\r\n",
            &format!("{{\"password\":\"{password}\"}}"),
        )
    };
    // Six addresses guess six times each: every one ends paused, the global ceiling is hit.
    let mut codes = Vec::new();
    for src in attackers(5, 6) {
        for _ in 0..6 {
            codes.push(http_from(src, b.status, &login("guess")).await.0);
        }
    }
    assert!(codes.contains(&429), "no throttle: {codes:?}");
    // Cross-site sign-in attempts (a page posting text/plain) do not even reach the check.
    let cross = login("guess").replace(
        "Content-Type: application/json\r\n",
        "Content-Type: text/plain\r\nOrigin: http://evil.example\r\n",
    );
    assert_eq!(http_from(attackers(5, 1)[0], b.status, &cross).await.0, 403);
    // The operator, from an address without wrong guesses, signs in at once.
    let (code, head, body) = http_from(fresh_addr(), b.status, &login(OPERATOR_PASSWORD)).await;
    assert_eq!(code, 200, "{body}");
    assert!(head.contains("irtrack_session="));
    invariants(&b, &base, 30 * 1024, "sign-in lock-out").await;

    // Disable during a throttle: this address is paused (even the right password waits) ...
    let op = fresh_addr();
    for _ in 0..5 {
        http_from(op, b.status, &login("typo")).await;
    }
    let basic = format!(
        "Authorization: {}\r\n",
        irtrack_firmware::net::auth::basic_header(OPERATOR_PASSWORD)
    );
    let (code, _, _) = http_from(op, b.status, &req("POST", "/robot/enable", b.status, &basic, "")).await;
    assert_eq!(code, 429, "enable is throttled like any sign-in");
    // ... but every request that makes the robot safer is answered, without credentials.
    for path in ["/robot/disable", "/robot/hold", "/robot/deadman?pressed=0"] {
        let (code, _, body) = http_from(op, b.status, &req("POST", path, b.status, "", "")).await;
        assert_eq!(code, 200, "{path}: {body}");
    }
    let press = req("POST", "/robot/deadman?pressed=1", b.status, &basic, "");
    let (code, _, _) = http_from(op, b.status, &press).await;
    assert_eq!(code, 429, "pressing the deadman is not a safe-direction request");
    assert!(metric(&b, "irtrackd_signin_throttled_total").await >= 1.0);
}

/// Probe: 100 password checks leave RSS within 10 MB of idle.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_hundred_password_checks_return_their_memory() {
    let b = start_board("argon2", "", "", None);
    let base = baseline(&b).await;
    let src = fresh_addr();
    let login = req(
        "POST",
        "/api/login",
        b.status,
        "Content-Type: application/json\r\n",
        &format!("{{\"password\":\"{OPERATOR_PASSWORD}\"}}"),
    );
    let t0 = Instant::now();
    for _ in 0..100 {
        assert_eq!(http_from(src, b.status, &login).await.0, 200);
    }
    eprintln!("100 password checks in {:?}", t0.elapsed());
    invariants(&b, &base, 10 * 1000, "100 password checks").await;
}

/// Probes: foreign Host and Origin over HTTP and WebSocket; security headers; no echo.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn foreign_hosts_and_origins_are_refused() {
    let b = start_board("origin", "", "", None);
    let base = baseline(&b).await;
    let src = fresh_addr();
    let login = req(
        "POST",
        "/api/login",
        b.status,
        "Content-Type: application/json\r\n",
        &format!("{{\"password\":\"{OPERATOR_PASSWORD}\"}}"),
    );
    let (_, head, _) = http_from(src, b.status, &login).await;
    let cookie = head
        .lines()
        .find_map(|l| {
            l.strip_prefix("set-cookie: ")
                .or_else(|| l.strip_prefix("Set-Cookie: "))
        })
        .and_then(|c| c.split(';').next())
        .unwrap()
        .to_string();
    let own = format!("Origin: http://{}\r\nCookie: {cookie}\r\n", b.status);
    let evil = format!("Origin: http://evil.example\r\nCookie: {cookie}\r\n");
    let tuning = "{\"threshold_dn\": 120}";
    // Changes with a valid cookie: from the board's own page yes, from another site no.
    let own_h = format!("{own}Content-Type: application/json\r\n");
    let evil_h = format!("{evil}Content-Type: application/json\r\n");
    assert_eq!(
        http_from(
            src,
            b.status,
            &req("POST", "/api/tuning", b.status, &own_h, tuning)
        )
        .await
        .0,
        200
    );
    assert_eq!(
        http_from(
            src,
            b.status,
            &req("POST", "/api/tuning", b.status, &evil_h, tuning)
        )
        .await
        .0,
        403
    );
    assert_eq!(
        http_from(
            src,
            b.status,
            &req("POST", "/robot/deadman?pressed=0", b.status, &evil, "")
        )
        .await
        .0,
        403
    );
    // DNS rebinding: a foreign Host gets nothing, frames included.
    for path in ["/", "/status", "/api/frameset"] {
        let r = format!(
            "GET {path} HTTP/1.1\r\nHost: evil.example:{}\r\n\r\n",
            b.status.port()
        );
        let (code, _, body) = http_from(src, b.status, &r).await;
        assert_eq!(code, 421, "{path}: {body}");
        assert!(!body.contains("evil"), "the refusal repeats the request: {body}");
    }
    // WebSocket upgrades: own origin streams, foreign origin and foreign host do not.
    let own_ws = ws_upgrade(
        src,
        b.status,
        &b.status.to_string(),
        Some(&format!("http://{}", b.status)),
        None,
    )
    .await;
    assert_eq!(own_ws.0, 101);
    assert!(own_ws.1, "no message on the board's own WebSocket");
    let evil_ws = ws_upgrade(
        src,
        b.status,
        &b.status.to_string(),
        Some("http://evil.example"),
        None,
    )
    .await;
    assert_eq!(evil_ws.0, 403);
    let rebound = ws_upgrade(src, b.status, "evil.example", None, None).await;
    assert_eq!(rebound.0, 421);
    // Security headers on pages, errors and refusals; error texts do not echo input.
    for path in ["/", "/status", "/no/such/%3Cscript%3E", "/web/%3Cscript%3E.js"] {
        let (code, head, body) = http_from(src, b.status, &req("GET", path, b.status, "", "")).await;
        let head = head.to_ascii_lowercase();
        for h in [
            "x-content-type-options: nosniff",
            "x-frame-options: deny",
            "content-security-policy: default-src 'self'",
        ] {
            assert!(head.contains(h), "{path} ({code}) lacks {h}:\n{head}");
        }
        if code != 200 {
            assert!(!body.contains("script"), "{path} echoes input: {body}");
        }
    }
    invariants(&b, &base, 30 * 1024, "foreign Host/Origin").await;

    // [status] public_view = false: live data only after sign-in.
    let p = start_board("private", "", "[status]\npublic_view = false\n", None);
    let origin = format!("http://{}", p.status);
    let anon = ws_upgrade(src, p.status, &p.status.to_string(), Some(&origin), None).await;
    assert_eq!(anon.0, 401);
    let r = req("GET", "/api/frameset", p.status, "", "");
    assert_eq!(http_from(src, p.status, &r).await.0, 401);
    let login = login.replace(&b.status.to_string(), &p.status.to_string());
    let (_, head, _) = http_from(src, p.status, &login).await;
    let cookie = head
        .lines()
        .find_map(|l| {
            l.strip_prefix("set-cookie: ")
                .or_else(|| l.strip_prefix("Set-Cookie: "))
        })
        .and_then(|c| c.split(';').next())
        .unwrap()
        .to_string();
    let signed = ws_upgrade(src, p.status, &p.status.to_string(), Some(&origin), Some(&cookie)).await;
    assert_eq!(signed.0, 101);
}

/// A WebSocket handshake by hand: (status code, whether a first server frame arrived).
async fn ws_upgrade(
    src: IpAddr,
    dst: SocketAddr,
    host: &str,
    origin: Option<&str>,
    cookie: Option<&str>,
) -> (u16, bool) {
    let mut s = connect_from(src, dst).await.unwrap();
    let (code, rest) = ws_handshake(&mut s, host, origin, cookie).await;
    if code != 101 {
        return (code, false);
    }
    let mut got = rest;
    let mut buf = [0u8; 4096];
    let deadline = Instant::now() + Duration::from_secs(3);
    while got.is_empty() && Instant::now() < deadline {
        match tokio::time::timeout(Duration::from_secs(3), s.read(&mut buf)).await {
            Ok(Ok(n)) if n > 0 => got.extend_from_slice(&buf[..n]),
            _ => break,
        }
    }
    (code, got.first() == Some(&0x81))
}

/// Sends the upgrade request and reads the answer head; returns the code and any bytes read
/// past the head.
async fn ws_handshake(
    s: &mut TcpStream,
    host: &str,
    origin: Option<&str>,
    cookie: Option<&str>,
) -> (u16, Vec<u8>) {
    let mut r = format!(
        "GET /api/live HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: aXJ0cmFjay1ob3N0aWxlIQ==\r\nSec-WebSocket-Version: 13\r\n"
    );
    if let Some(o) = origin {
        r.push_str(&format!("Origin: {o}\r\n"));
    }
    if let Some(c) = cookie {
        r.push_str(&format!("Cookie: {c}\r\n"));
    }
    r.push_str("\r\n");
    s.write_all(r.as_bytes()).await.unwrap();
    let mut got = Vec::new();
    let mut buf = [0u8; 4096];
    loop {
        if let Some(end) = got.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&got[..end]).to_string();
            let code = head
                .split_whitespace()
                .nth(1)
                .and_then(|c| c.parse().ok())
                .unwrap_or(0);
            return (code, got[end + 4..].to_vec());
        }
        match tokio::time::timeout(Duration::from_secs(5), s.read(&mut buf)).await {
            Ok(Ok(n)) if n > 0 => got.extend_from_slice(&buf[..n]),
            _ => return (0, Vec::new()),
        }
    }
}

/// A client frame; `mask`: masked as RFC 6455 requires of clients.
fn ws_frame(opcode: u8, payload: &[u8], mask: bool) -> Vec<u8> {
    let mut f = vec![0x80 | opcode];
    let m = if mask { 0x80 } else { 0 };
    match payload.len() {
        n if n < 126 => f.push(m | n as u8),
        n if n <= 0xffff => {
            f.push(m | 126);
            f.extend_from_slice(&(n as u16).to_be_bytes());
        }
        n => {
            f.push(m | 127);
            f.extend_from_slice(&(n as u64).to_be_bytes());
        }
    }
    if mask {
        let key = [0x1b, 0x2c, 0x3d, 0x4e];
        f.extend_from_slice(&key);
        f.extend(payload.iter().enumerate().map(|(i, b)| b ^ key[i % 4]));
    } else {
        f.extend_from_slice(payload);
    }
    f
}

/// Probes: oversized and unmasked WebSocket frames, and viewers that stop reading.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_frames_and_stalled_readers_end_their_sessions() {
    let b = start_board("ws", "", "", None);
    let base = baseline(&b).await;
    let origin = format!("http://{}", b.status);
    let host = b.status.to_string();
    let open = |src: IpAddr| {
        let (host, origin) = (host.clone(), origin.clone());
        async move {
            let mut s = connect_from(src, b.status).await.unwrap();
            let (code, _) = ws_handshake(&mut s, &host, Some(&origin), None).await;
            assert_eq!(code, 101);
            s
        }
    };
    // A frame announcing 1 MiB (over the 64 KiB limit), sent in part; and an unmasked frame.
    let mut big = open(fresh_addr()).await;
    let mut frame = ws_frame(0x1, &vec![b'x'; 1024 * 1024], true);
    frame.truncate(70_000);
    let _ = big.write_all(&frame).await;
    let mut unmasked = open(fresh_addr()).await;
    let _ = unmasked
        .write_all(&ws_frame(0x1, br#"{"type":"subscribe"}"#, false))
        .await;
    assert!(
        closed_within(&mut big, Duration::from_secs(3)).await,
        "oversized frame not refused"
    );
    assert!(
        closed_within(&mut unmasked, Duration::from_secs(3)).await,
        "unmasked frame not refused"
    );
    // A deaf viewer reads everything but never answers a ping: it is closed once 25 s pass
    // without a frame back (at the third ping, 30 s in). Opened first; checked last.
    let mut deaf = open(fresh_addr()).await;
    let deaf_opened = Instant::now();
    let deaf_closed = tokio::spawn(async move { closed_within(&mut deaf, Duration::from_secs(40)).await });
    // Twenty viewers ask for previews, zooms, blobs and positions, then never read again.
    let subscribe = br#"{"type":"subscribe","preview_fps":10,"zoom_px":64,"blobs":true,"positions":true}"#;
    let mut stalled = Vec::new();
    for src in attackers(6, 2) {
        for _ in 0..10 {
            let mut s = open(src).await;
            s.write_all(&ws_frame(0x1, subscribe, true)).await.unwrap();
            stalled.push(s);
        }
    }
    let t0 = Instant::now();
    invariants(&b, &base, 60 * 1024, "stalled WebSocket readers").await;
    // Each session ends once a send blocks for 5 s (their kernel buffers fill first).
    loop {
        let (_, v) = fresh_status(&b).await;
        let live = v["viewers"]["live"].as_u64().unwrap();
        if live == 0 {
            break;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(30),
            "{live} stalled viewers still served after 30 s"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    eprintln!("20 stalled viewers dropped after {:?}", t0.elapsed());
    invariants(&b, &base, 60 * 1024, "after the stalled readers").await;
    let send_timeouts = metric(&b, "irtrackd_websocket_timeouts_total{reason=\"send\"}").await;
    assert!(send_timeouts >= 20.0, "stalled readers counted: {send_timeouts}");
    assert!(
        deaf_closed.await.unwrap(),
        "a viewer that never answers pings was kept for 40 s"
    );
    eprintln!("deaf viewer closed after {:?}", deaf_opened.elapsed());
    assert!(deaf_opened.elapsed() >= Duration::from_secs(25));
    let silence = metric(&b, "irtrackd_websocket_timeouts_total{reason=\"silence\"}").await;
    assert!(silence >= 1.0, "deaf viewer not counted: {silence}");
}

/// Probe: 300 concurrent pushes announcing 1 MiB each, some over the limit.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_oversize_parameter_pushes() {
    // Unsigned blobs allowed (development mode), so a bad blob reaches the decoder's verdict.
    let b = start_board("push", "", "[params]\nallow_unsigned = true", None);
    let base = baseline(&b).await;
    let mut header = b"IRPP".to_vec();
    header.extend_from_slice(&(1024u32 * 1024).to_le_bytes());
    header.extend_from_slice(&[0x55; 60_000]);
    let held = hold(&attackers(7, 10), b.params, 30, &header).await;
    invariants(&b, &base, 20 * 1024, "300 pushes of 1 MiB").await;
    let refused = metric(
        &b,
        "irtrackd_connections_refused_total{listener=\"params\",reason=\"listener\"}",
    )
    .await
        + metric(
            &b,
            "irtrackd_connections_refused_total{listener=\"params\",reason=\"peer\"}",
        )
        .await;
    assert!(refused >= 250.0, "parameter connections refused: {refused}");
    // The attackers leave; their slots free up as the board sees them go.
    drop(held);
    tokio::time::sleep(Duration::from_millis(500)).await;
    // Over the blob limit: the verdict arrives although the client keeps sending (the board
    // drains the rest instead of resetting the connection).
    let mut s = connect_from(fresh_addr(), b.params).await.unwrap();
    let mut too_large = b"IRPP".to_vec();
    too_large.extend_from_slice(&(8u32 * 1024 * 1024).to_le_bytes());
    s.write_all(&too_large).await.unwrap();
    let _ = s.write_all(&[0u8; 256 * 1024]).await;
    let mut verdict = String::new();
    tokio::time::timeout(Duration::from_secs(5), s.read_to_string(&mut verdict))
        .await
        .expect("no verdict")
        .unwrap();
    assert!(verdict.starts_with("ERR TOO_LARGE"), "{verdict:?}");
    // A blob that is markup with a line break and a forged verdict: the answer is one line
    // naming the problem, with the 4 magic bytes it found as hex, and none of the input.
    let forged = b"<sc\nript>alert(1)</script>\r\nOK forged-rig\n".repeat(4);
    let mut push = b"IRPP".to_vec();
    push.extend_from_slice(&(forged.len() as u32).to_le_bytes());
    push.extend_from_slice(&forged);
    let mut s = connect_from(fresh_addr(), b.params).await.unwrap();
    s.write_all(&push).await.unwrap();
    let mut verdict = String::new();
    tokio::time::timeout(Duration::from_secs(5), s.read_to_string(&mut verdict))
        .await
        .expect("no verdict")
        .unwrap();
    assert!(verdict.starts_with("ERR BAD_BLOB "), "{verdict:?}");
    assert!(verdict.contains("[3c, 73, 63, 0a]"), "{verdict:?}");
    assert_eq!(verdict.matches('\n').count(), 1, "{verdict:?}");
    assert!(verdict.ends_with('\n'), "{verdict:?}");
    for echoed in ["<sc", "script", "forged", "OK "] {
        assert!(
            !verdict.contains(echoed),
            "the verdict echoes the push: {verdict:?}"
        );
    }
    let (_, v) = fresh_status(&b).await;
    assert_eq!(rig(&v), base.rig);
}
