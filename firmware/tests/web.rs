//! The status listener's set-up view API over real sockets on 127.0.0.1 (docs/http-api.md):
//! page and assets, sign-in for changes, live tuning reaching the loop, the live WebSocket,
//! a slow viewer not slowing the loop, frame-set capture, and saving the tuning.

mod common;

use std::net::SocketAddr;
use std::sync::atomic::Ordering::Relaxed;
use std::time::{Duration, Instant};

use common::*;
use futures_util::{SinkExt, StreamExt};
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::config::Config;
use irtrack_firmware::net::auth::{basic_header, hash_password};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;

const PASSWORD: &str = "correct horse";

/// A full HTTP answer.
struct Answer {
    code: u16,
    head: String,
    body: Vec<u8>,
}

impl Answer {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
    fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("{e}: {}", self.text()))
    }
    fn header(&self, name: &str) -> Option<String> {
        self.head.lines().find_map(|l| {
            let (k, v) = l.split_once(':')?;
            k.trim().eq_ignore_ascii_case(name).then(|| v.trim().to_string())
        })
    }
}

/// One request over a raw socket (HTTP/1.1, `Connection: close`).
async fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, String)],
    body: &str,
) -> Answer {
    let mut s = TcpStream::connect(addr).await.unwrap();
    let mut req = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    req.push_str(body);
    s.write_all(req.as_bytes()).await.unwrap();
    let mut raw = Vec::new();
    tokio::time::timeout(Duration::from_secs(10), s.read_to_end(&mut raw))
        .await
        .expect("answer within 10 s")
        .unwrap();
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a complete answer head");
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let code = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    let mut body = raw[split + 4..].to_vec();
    // Chunked bodies (streamed answers): undo the framing.
    if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let eol = rest.windows(2).position(|w| w == b"\r\n").unwrap();
            let n = usize::from_str_radix(std::str::from_utf8(&rest[..eol]).unwrap().trim(), 16).unwrap();
            if n == 0 {
                break;
            }
            out.extend_from_slice(&rest[eol + 2..eol + 2 + n]);
            rest = &rest[eol + 2 + n + 2..];
        }
        body = out;
    }
    Answer { code, head, body }
}

async fn get(addr: SocketAddr, path: &str) -> Answer {
    request(addr, "GET", path, &[], "").await
}

fn config(dir: &TempDir, password: Option<&str>) -> Config {
    let mut cfg = test_config(dir.path());
    cfg.service.params_from_simulator = true;
    cfg.service.operator_password_hash = password.map(|p| hash_password(p).unwrap());
    cfg
}

async fn eventually(secs: u64, mut f: impl AsyncFnMut() -> bool) -> bool {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while Instant::now() < deadline {
        if f().await {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    false
}

fn basic() -> (&'static str, String) {
    ("Authorization", basic_header(PASSWORD))
}

/// `POST /api/login` with `password`.
async fn login(addr: SocketAddr, password: &str) -> Answer {
    let body = serde_json::json!({ "password": password }).to_string();
    request(addr, "POST", "/api/login", &[], &body).await
}

/// The `Cookie` header that sends back the session a sign-in answer set.
fn session_cookie(signed_in: &Answer) -> (&'static str, String) {
    let set = signed_in.header("set-cookie").expect("a session cookie");
    ("Cookie", set.split(';').next().unwrap_or_default().to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn page_assets_status_and_limits_on_the_new_server() {
    let dir = TempDir::new("web-page");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let a = get(addr, "/").await;
    assert_eq!(a.code, 200);
    assert!(
        a.header("content-type").unwrap().starts_with("text/html"),
        "{}",
        a.head
    );
    assert!(a.text().contains("<html"), "{}", a.text());
    let a = get(addr, "/web/index.html").await;
    assert_eq!(a.code, 200);
    let a = get(addr, "/web/no-such-file.js").await;
    assert_eq!(a.code, 404);
    // A fixed sentence: error texts never repeat the request (issue 25).
    assert!(a.text().contains("no such file"), "{}", a.text());
    assert!(!a.text().contains("no-such-file.js"), "{}", a.text());
    assert_eq!(a.header("x-content-type-options").as_deref(), Some("nosniff"));
    let a = get(addr, "/status").await;
    assert_eq!(a.code, 200);
    let st = a.json();
    assert_eq!(st["service"], "irtrackd");
    assert!(st["fault_texts"].is_array());
    let a = get(addr, "/metrics").await;
    assert!(a.text().contains("irtrackd_sets_processed_total"), "{}", a.text());
    // Unknown methods and paths: as before.
    assert_eq!(request(addr, "DELETE", "/status", &[], "").await.code, 405);
    assert_eq!(get(addr, "/nope").await.code, 404);
    // A request head over the limit is refused, not buffered.
    let huge = "x".repeat(16 * 1024);
    let a = request(addr, "GET", "/status", &[("X-Big", huge)], "").await;
    assert!(a.code >= 400, "oversized head answered {}", a.code);
    // A client that never finishes its head is cut off after the read timeout.
    let mut idle = TcpStream::connect(addr).await.unwrap();
    idle.write_all(b"GET /status HTTP/1.1\r\n").await.unwrap();
    let mut buf = Vec::new();
    let r = tokio::time::timeout(Duration::from_secs(10), idle.read_to_end(&mut buf)).await;
    assert!(r.is_ok(), "idle connection not closed within 10 s");
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_change_needs_an_operator_sign_in() {
    // No password configured: changes refused with a message saying how to set one.
    let dir = TempDir::new("web-nopw");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let a = request(addr, "POST", "/api/tuning", &[], r#"{"threshold_dn": 40}"#).await;
    assert_eq!(a.code, 401, "{}", a.text());
    assert!(a.text().contains("--hash-password"), "{}", a.text());
    let a = request(addr, "POST", "/api/login", &[], r#"{"password": "x"}"#).await;
    assert_eq!(a.code, 503, "{}", a.text());
    let s = get(addr, "/api/session").await.json();
    assert_eq!(s["operator_configured"], false);
    running.shutdown().await;

    // Password configured, control on (no robot): sign-in decides.
    let dir = TempDir::new("web-pw");
    let mut cfg = config(&dir, Some(PASSWORD));
    cfg.service.control = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let addr = running.addrs.status;
    let change = r#"{"threshold_dn": 41}"#;
    let a = request(addr, "POST", "/api/tuning", &[], change).await;
    assert_eq!(a.code, 401);
    assert!(a.text().contains("sign in"), "{}", a.text());
    for path in ["/robot/enable", "/robot", "/api/tuning/save"] {
        let a = request(addr, "POST", path, &[], "").await;
        assert_eq!(a.code, 401, "{path}: {}", a.text());
    }
    let wrong = ("Authorization", basic_header("wrong"));
    let a = request(addr, "POST", "/api/tuning", &[wrong], change).await;
    assert_eq!(a.code, 401);
    assert!(a.text().contains("wrong operator password"), "{}", a.text());
    // Scripts: HTTP Basic.
    let a = request(addr, "POST", "/api/tuning", &[basic()], change).await;
    assert_eq!(a.code, 200, "{}", a.text());
    assert_eq!(a.json()["threshold_dn"], 41);
    let a = request(addr, "POST", "/robot/enable", &[basic()], "").await;
    assert_eq!(a.code, 409, "signed in, but no [robot]: {}", a.text());
    // Browsers: login → cookie.
    let a = request(addr, "POST", "/api/login", &[], r#"{"password": "nope"}"#).await;
    assert_eq!(a.code, 401);
    let a = login(addr, PASSWORD).await;
    assert_eq!(a.code, 200, "{}", a.text());
    let cookie = a.header("set-cookie").expect("a session cookie");
    assert!(
        cookie.contains("HttpOnly") && cookie.contains("SameSite=Strict"),
        "{cookie}"
    );
    let c = session_cookie(&a);
    assert_eq!(get(addr, "/api/session").await.json()["signed_in"], false);
    let s = request(addr, "GET", "/api/session", std::slice::from_ref(&c), "")
        .await
        .json();
    assert_eq!(s["signed_in"], true);
    assert_eq!(s["control_allowed"], true);
    let a = request(
        addr,
        "POST",
        "/api/tuning",
        std::slice::from_ref(&c),
        r#"{"threshold_dn": 42}"#,
    )
    .await;
    assert_eq!(a.code, 200, "{}", a.text());
    // Bad values: 400 and nothing changes.
    let a = request(
        addr,
        "POST",
        "/api/tuning",
        std::slice::from_ref(&c),
        r#"{"threshold_dn": 5000}"#,
    )
    .await;
    assert_eq!(a.code, 400);
    assert!(a.text().contains("threshold_dn 5000"), "{}", a.text());
    let a = request(
        addr,
        "POST",
        "/api/tuning",
        std::slice::from_ref(&c),
        r#"{"min_area_px": 50, "max_area_px": 10}"#,
    )
    .await;
    assert_eq!(a.code, 400, "{}", a.text());
    assert_eq!(get(addr, "/api/tuning").await.json()["threshold_dn"], 42);
    // Logout ends the session.
    assert_eq!(
        request(addr, "POST", "/api/logout", std::slice::from_ref(&c), "")
            .await
            .code,
        200
    );
    let a = request(addr, "POST", "/api/tuning", &[c], r#"{"threshold_dn": 43}"#).await;
    assert_eq!(a.code, 401);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn repeated_wrong_passwords_pause_checks_but_not_open_sessions() {
    let dir = TempDir::new("web-guess");
    let running = app::start(config(&dir, Some(PASSWORD)), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let a = login(addr, PASSWORD).await;
    assert_eq!(a.code, 200, "{}", a.text());
    let cookie = session_cookie(&a);
    // Someone guesses, by Basic and by the sign-in form.
    for i in 0..5 {
        let a = if i % 2 == 0 {
            let wrong = ("Authorization", basic_header(&format!("guess{i}")));
            request(addr, "POST", "/api/tuning", &[wrong], r#"{"threshold_dn": 41}"#).await
        } else {
            login(addr, &format!("guess{i}")).await
        };
        assert_eq!(a.code, 401, "guess {i}: {}", a.text());
    }
    // Now even the right password waits, with a clear answer and Retry-After.
    for a in [
        request(addr, "POST", "/api/tuning", &[basic()], r#"{"threshold_dn": 41}"#).await,
        login(addr, PASSWORD).await,
    ] {
        assert_eq!(a.code, 429, "{}", a.text());
        assert!(
            a.text().contains("too many wrong operator passwords"),
            "{}",
            a.text()
        );
        let retry: u64 = a.header("retry-after").expect("Retry-After").parse().unwrap();
        assert!((1..=10).contains(&retry), "Retry-After {retry}");
    }
    // The operator already signed in keeps working.
    let a = request(addr, "POST", "/api/tuning", &[cookie], r#"{"threshold_dn": 42}"#).await;
    assert_eq!(a.code, 200, "{}", a.text());
    assert_eq!(a.json()["threshold_dn"], 42);
    running.shutdown().await;
}

fn camera_blobs(st: &serde_json::Value) -> Vec<u64> {
    st["source"]["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["blobs_last"].as_u64().unwrap())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn threshold_change_reaches_the_loop_and_faults_say_why() {
    let dir = TempDir::new("web-thr");
    let running = app::start(config(&dir, Some(PASSWORD)), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let tracked = running.status.clone();
    assert!(eventually(10, async || tracked.tracked.load(Relaxed) > 20).await);
    let st = status_json(addr).await;
    assert!(
        camera_blobs(&st).iter().all(|&n| n == 1),
        "{:?}",
        camera_blobs(&st)
    );
    // Dim the simulated cameras (exposure) so the LED peak is well below full scale, then
    // put the threshold above that peak.
    let tuning = get(addr, "/api/tuning").await.json();
    assert_eq!(tuning["cameras"].as_array().unwrap().len(), 2);
    assert_eq!(tuning["cameras"][0]["supported"], true);
    let dim = r#"{"cameras": [{"camera": 0, "exposure": 40}, {"camera": 1, "exposure": 40}]}"#;
    let a = request(addr, "POST", "/api/tuning", &[basic()], dim).await;
    assert_eq!(a.code, 200, "{}", a.text());
    assert!(
        eventually(5, async || {
            let st = status_json(addr).await;
            st["source"]["cameras"].as_array().unwrap().iter().all(|c| {
                let p = c["peak_dn"].as_u64().unwrap();
                p > 30 && p < 200
            })
        })
        .await,
        "the dimmed LED peak never showed in /status: {}",
        status_json(addr).await["source"]["cameras"]
    );
    let st = status_json(addr).await;
    let peak = st["source"]["cameras"][0]["peak_dn"].as_u64().unwrap();
    let thr = (peak + 20).min(250);
    let a = request(
        addr,
        "POST",
        "/api/tuning",
        &[basic()],
        &format!(r#"{{"threshold_dn": {thr}}}"#),
    )
    .await;
    assert_eq!(a.code, 200, "{}", a.text());
    assert!(
        eventually(5, async || camera_blobs(&status_json(addr).await)
            .iter()
            .all(|&n| n == 0))
        .await,
        "blob count did not drop to 0 with the threshold {thr} above the peak {peak}"
    );
    let st = status_json(addr).await;
    let texts: Vec<String> = st["fault_texts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["message"].as_str().unwrap().to_string())
        .collect();
    println!("faults: {texts:#?}");
    assert!(
        texts.iter().any(
            |t| t.contains(&format!("threshold {thr} DN is above the brightest pixel"))
                && t.contains("lower the threshold")
        ),
        "{texts:?}"
    );
    // Back to normal: tracking resumes.
    let restore = r#"{"threshold_dn": 30, "cameras": [{"camera": 0, "exposure": 100}, {"camera": 1, "exposure": 100}]}"#;
    assert_eq!(
        request(addr, "POST", "/api/tuning", &[basic()], restore)
            .await
            .code,
        200
    );
    let before = tracked.tracked.load(Relaxed);
    assert!(eventually(5, async || tracked.tracked.load(Relaxed) > before + 10).await);
    running.shutdown().await;
}

type Ws = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<TcpStream>>;

async fn connect_live(addr: SocketAddr, subscribe: &str) -> Ws {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/api/live"))
        .await
        .unwrap();
    ws.send(Message::Text(subscribe.into())).await.unwrap();
    ws
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn live_websocket_sends_status_previews_zoom_blobs_and_positions() {
    let dir = TempDir::new("web-live");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.tracked.load(Relaxed) > 10).await);
    let mut ws = connect_live(
        addr,
        r#"{"type": "subscribe", "preview_fps": 10, "preview_max_width_px": 320, "zoom_px": 32, "blobs": true}"#,
    )
    .await;
    let mut seen_status = false;
    let mut previews = [0usize; 2];
    let mut zooms = [0usize; 2];
    let mut blob_sets = 0usize;
    let mut positions = 0usize;
    let mut pending: Option<serde_json::Value> = None;
    let deadline = Instant::now() + Duration::from_secs(10);
    while Instant::now() < deadline
        && !(seen_status
            && previews.iter().all(|&n| n >= 2)
            && zooms.iter().all(|&n| n >= 1)
            && blob_sets >= 5
            && positions >= 5)
    {
        let msg = tokio::time::timeout(Duration::from_secs(5), ws.next())
            .await
            .expect("a live message within 5 s")
            .unwrap()
            .unwrap();
        match msg {
            Message::Text(t) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                match v["type"].as_str().unwrap() {
                    "status" => {
                        assert_eq!(v["service"], "irtrackd");
                        seen_status = true;
                    }
                    "preview" | "zoom" => pending = Some(v),
                    "blobs" => {
                        let cams = v["cameras"].as_array().unwrap();
                        assert_eq!(cams.len(), 2);
                        assert_eq!(v["timestamps_ns"].as_array().unwrap().len(), 2);
                        assert!(v["dropped"].is_u64());
                        blob_sets += 1;
                    }
                    "position" => {
                        assert!(v["record"]["frame"].is_u64(), "{v}");
                        positions += 1;
                    }
                    other => panic!("unexpected message type {other}: {v}"),
                }
            }
            Message::Binary(b) => {
                let meta = pending.take().expect("a binary message follows its description");
                let cam = meta["camera"].as_u64().unwrap() as usize;
                if meta["type"] == "preview" {
                    let mut dec = jpeg_decoder::Decoder::new(&b[..]);
                    let px = dec.decode().unwrap();
                    let info = dec.info().unwrap();
                    assert_eq!(u64::from(info.width), meta["width_px"].as_u64().unwrap());
                    assert_eq!(u64::from(info.height), meta["height_px"].as_u64().unwrap());
                    assert_eq!(
                        (info.width, info.height),
                        (320, 240),
                        "VGA downscaled to 320 px wide"
                    );
                    assert_eq!(px.len(), 320 * 240);
                    let blobs = meta["blobs"].as_array().unwrap();
                    let kept: Vec<_> = blobs.iter().filter(|b| b["kept"] == true).collect();
                    assert_eq!(
                        kept.len(),
                        1,
                        "one kept blob per camera on the sim source: {meta}"
                    );
                    let x = kept[0]["x_px"].as_f64().unwrap();
                    assert!((0.0..640.0).contains(&x), "full-resolution coordinates: {x}");
                    assert!(meta["peak_dn"].as_u64().unwrap() > 30);
                    previews[cam] += 1;
                } else {
                    let dec = png::Decoder::new(std::io::Cursor::new(&b[..]));
                    let reader = dec.read_info().unwrap();
                    assert_eq!(reader.info().width, 32);
                    assert_eq!(reader.info().height, 32);
                    zooms[cam] += 1;
                }
            }
            _ => {}
        }
    }
    println!(
        "live: status {seen_status}, previews {previews:?}, zooms {zooms:?}, blob sets {blob_sets}, positions {positions}"
    );
    assert!(seen_status, "no status message");
    assert!(previews.iter().all(|&n| n >= 2), "previews {previews:?}");
    assert!(zooms.iter().all(|&n| n >= 1), "zooms {zooms:?}");
    assert!(blob_sets >= 5, "blob sets {blob_sets}");
    assert!(positions >= 5, "positions {positions}");
    // A bad message gets an error answer, the session stays.
    ws.send(Message::Text(r#"{"type": "bogus"}"#.into()))
        .await
        .unwrap();
    let mut got_error = false;
    for _ in 0..200 {
        if let Some(Ok(Message::Text(t))) = ws.next().await
            && t.as_str().contains("\"error\"")
        {
            got_error = true;
            break;
        }
    }
    assert!(got_error);
    drop(ws);
    running.shutdown().await;
}

/// The next `blobs` message on a live session: per camera, the listed blobs.
async fn next_blob_lists(ws: &mut Ws) -> Vec<Vec<serde_json::Value>> {
    loop {
        let msg = tokio::time::timeout(Duration::from_secs(5), ws.next())
            .await
            .expect("a live message within 5 s")
            .unwrap()
            .unwrap();
        if let Message::Text(t) = msg {
            let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
            if v["type"] == "blobs" {
                return v["cameras"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|c| c.as_array().unwrap().clone())
                    .collect();
            }
        }
    }
}

fn reasons(list: &[serde_json::Value]) -> Vec<String> {
    list.iter()
        .map(|b| b["reason"].as_str().unwrap_or("kept").to_string())
        .collect()
}

/// While the marker is tracked the loop only looks inside its tracking window; the lamp and
/// the streak the simulator puts into camera 1 (`glare`) must still be drawn, with why they
/// are not used. Before any parameter set exists (cameras being aimed, not yet calibrated)
/// the loop tracks nothing, and the view still shows each camera's LED as a kept spot.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stray_lights_outside_the_window_and_spots_before_calibration_are_listed() {
    let subscribe = r#"{"type": "subscribe", "preview_fps": 10, "preview_max_width_px": 160, "blobs": true}"#;
    // Tracking, with glare in camera 1.
    let dir = TempDir::new("web-glare");
    let mut cfg = config(&dir, None);
    cfg.source.sim.as_mut().unwrap().glare = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let st = running.status.clone();
    assert!(eventually(10, async || st.tracked.load(Relaxed) > 10).await);
    let mut ws = connect_live(running.addrs.status, subscribe).await;
    let mut seen = None;
    for _ in 0..20 {
        let lists = next_blob_lists(&mut ws).await;
        let (r0, r1) = (reasons(&lists[0]), reasons(&lists[1]));
        if r0 == ["kept"] && r1.iter().filter(|r| *r == "kept").count() == 1 && r1.len() >= 3 {
            seen = Some(r1);
            break;
        }
    }
    let r1 = seen.expect("camera 1 lists its LED kept plus the lamp and the streak");
    println!("tracking, camera 1 with glare: {r1:?}");
    assert!(
        r1.iter().any(|r| r == "window" || r == "area"),
        "the round lamp outside the window is listed: {r1:?}"
    );
    assert!(
        r1.iter().any(|r| r == "roundness"),
        "the streak is listed as not round: {r1:?}"
    );
    drop(ws);
    running.shutdown().await;

    // No parameter set: nothing is tracked, the spots are still shown.
    let dir = TempDir::new("web-uncalibrated");
    let mut cfg = config(&dir, None);
    cfg.service.params_from_simulator = false;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let mut ws = connect_live(running.addrs.status, subscribe).await;
    let lists = next_blob_lists(&mut ws).await;
    println!(
        "no parameter set: {:?}",
        lists.iter().map(|l| reasons(l)).collect::<Vec<_>>()
    );
    assert_eq!(running.status.tracked.load(Relaxed), 0);
    for (camera, list) in lists.iter().enumerate() {
        assert_eq!(
            reasons(list),
            ["kept"],
            "camera {camera}: the LED as the one kept spot"
        );
        let peak = list[0]["peak_dn"].as_u64().unwrap();
        assert!(peak > 30, "camera {camera}: peak {peak}");
    }
    drop(ws);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_viewers_never_slow_the_loop() {
    let dir = TempDir::new("web-slow");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.tracked.load(Relaxed) > 10).await);
    let rate = async |secs: u64| {
        let (p0, t0) = (st.sets_processed.load(Relaxed), Instant::now());
        tokio::time::sleep(Duration::from_secs(secs)).await;
        (st.sets_processed.load(Relaxed) - p0) as f64 / t0.elapsed().as_secs_f64()
    };
    let base = rate(2).await;
    // Three viewers asking for everything at the highest rates, then never reading.
    let mut stalled = Vec::new();
    for _ in 0..3 {
        stalled.push(
            connect_live(
                addr,
                r#"{"type": "subscribe", "preview_fps": 30, "preview_max_width_px": 640, "zoom_px": 64, "blobs": true}"#,
            )
            .await,
        );
    }
    // Until their socket buffers are full the sessions still encode (real CPU load on a
    // 2-core board); after that they block on sending and cost nothing.
    tokio::time::sleep(Duration::from_secs(6)).await;
    let misses0 = st.deadline_misses.load(Relaxed);
    let with = rate(3).await;
    let misses = st.deadline_misses.load(Relaxed) - misses0;
    let viewers = status_json(addr).await["viewers"].clone();
    println!(
        "loop rate: {base:.1} sets/s without viewers, {with:.1} with 3 stalled viewers (ratio {:.3}); {misses} deadline misses; viewers {viewers}",
        with / base
    );
    assert!(
        with >= 0.9 * base,
        "loop slowed from {base:.1} to {with:.1} sets/s"
    );
    assert!(viewers["copies"].as_u64().unwrap() > 0);
    // A fresh client is still served while the stalled ones hang.
    assert_eq!(get(addr, "/status").await.code, 200);
    drop(stalled);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewers_with_the_same_settings_share_one_encode() {
    let dir = TempDir::new("web-share");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.tracked.load(Relaxed) > 10).await);
    let sub = r#"{"type": "subscribe", "preview_fps": 10, "preview_max_width_px": 320}"#;
    let mut viewers = Vec::new();
    for _ in 0..3 {
        viewers.push(connect_live(addr, sub).await);
    }
    // Every viewer reads its previews (JPEG frames) for 3 s.
    let deadline = Instant::now() + Duration::from_secs(3);
    let mut received = [0u64; 3];
    let mut tasks = Vec::new();
    for mut ws in viewers {
        tasks.push(tokio::spawn(async move {
            let mut jpegs = 0u64;
            while Instant::now() < deadline {
                match tokio::time::timeout(Duration::from_millis(500), ws.next()).await {
                    Ok(Some(Ok(Message::Binary(b)))) => {
                        assert_eq!(&b[..2], &[0xFF, 0xD8], "not a JPEG");
                        jpegs += 1;
                    }
                    Ok(Some(Ok(_))) | Err(_) => {}
                    Ok(_) => break,
                }
            }
            jpegs
        }));
    }
    for (i, t) in tasks.into_iter().enumerate() {
        received[i] = t.await.unwrap();
    }
    let v = status_json(addr).await["viewers"].clone();
    let (encoded, shared) = (
        v["previews_encoded"].as_u64().unwrap(),
        v["previews_shared"].as_u64().unwrap(),
    );
    println!("JPEGs received per viewer {received:?}; preview sets encoded {encoded}, shared {shared}");
    // Two cameras: two JPEGs per preview set. Everybody was served (10 fps asked; at least a
    // few sets even on a slow machine).
    assert!(received.iter().all(|&n| n >= 2 * 3), "{received:?}");
    let sets_served = received.iter().sum::<u64>() / 2;
    assert!(shared > 0, "no viewer reused another's encode: {v}");
    assert!(
        encoded < sets_served,
        "{encoded} encodes for {sets_served} preview sets served: nothing was shared"
    );
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn frameset_returns_every_camera_with_plausible_timestamps() {
    let dir = TempDir::new("web-frameset");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.sets_processed.load(Relaxed) > 5).await);
    for _ in 0..3 {
        let before_ns = irtrack_firmware::clock::monotonic_ns();
        let a = get(addr, "/api/frameset").await;
        assert_eq!(a.code, 200, "{}", a.text());
        assert_eq!(
            a.header("content-type").as_deref(),
            Some("application/x-irtrack-frameset")
        );
        let nl = a.body.iter().position(|&b| b == b'\n').unwrap();
        let head: serde_json::Value = serde_json::from_slice(&a.body[..nl]).unwrap();
        let cams = head["cameras"].as_array().unwrap();
        assert_eq!(cams.len(), 2);
        let mut rest = &a.body[nl + 1..];
        let stamps: Vec<u64> = cams.iter().map(|c| c["timestamp_ns"].as_u64().unwrap()).collect();
        for (i, c) in cams.iter().enumerate() {
            assert_eq!(c["camera"], i);
            let n = c["pgm_bytes"].as_u64().unwrap() as usize;
            let (pgm, tail) = rest.split_at(n);
            rest = tail;
            let header = format!("P5\n{} {}\n255\n", c["width_px"], c["height_px"]);
            assert!(pgm.starts_with(header.as_bytes()), "camera {i} PGM header");
            assert_eq!(pgm.len(), header.len() + 640 * 480);
        }
        assert!(rest.is_empty(), "no bytes after the last PGM");
        let spread = stamps.iter().max().unwrap() - stamps.iter().min().unwrap();
        assert!(
            spread <= head["pairing_error_ns"].as_u64().unwrap() + 1_000_000,
            "{stamps:?}"
        );
        // Captured within the last second (a set newer than the request, or just before it).
        let now_ns = irtrack_firmware::clock::monotonic_ns();
        assert!(
            stamps
                .iter()
                .all(|&t| t + 1_000_000_000 > before_ns && t <= now_ns),
            "{stamps:?} vs {before_ns}..{now_ns}"
        );
    }
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn saving_to_an_unwritable_place_errors_and_keeps_the_live_values() {
    let dir = TempDir::new("web-save");
    let state = dir.path().join("state");
    std::fs::create_dir_all(&state).unwrap();
    let mut cfg = config(&dir, Some(PASSWORD));
    cfg.service.state_dir = state.clone();
    let running = app::start(cfg.clone(), Overrides::default()).await.unwrap();
    let addr = running.addrs.status;
    let a = request(
        addr,
        "POST",
        "/api/tuning",
        &[basic()],
        r#"{"threshold_dn": 44, "min_area_px": 4}"#,
    )
    .await;
    assert_eq!(a.code, 200, "{}", a.text());
    // The file cannot be written: a directory stands where it goes (also refused as root).
    let blocker = state.join("tuning.toml");
    std::fs::create_dir_all(blocker.join("x")).unwrap();
    let a = request(addr, "POST", "/api/tuning/save", &[basic()], "").await;
    assert_eq!(a.code, 500, "{}", a.text());
    assert!(
        a.text().contains(&blocker.display().to_string()),
        "names the path: {}",
        a.text()
    );
    assert!(a.text().contains("live values stay applied"), "{}", a.text());
    let t = get(addr, "/api/tuning").await.json();
    assert_eq!(t["threshold_dn"], 44);
    assert_eq!(t["unsaved_changes"], true);
    // Once writable, saving works and the next start applies the file.
    std::fs::remove_dir_all(&blocker).unwrap();
    let a = request(addr, "POST", "/api/tuning/save", &[basic()], "").await;
    assert_eq!(a.code, 200, "{}", a.text());
    assert_eq!(a.json()["unsaved_changes"], false);
    running.shutdown().await;
    let text = std::fs::read_to_string(&blocker).unwrap();
    assert!(text.contains("threshold_dn = 44"), "{text}");
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let t = get(running.addrs.status, "/api/tuning").await.json();
    assert_eq!(t["threshold_dn"], 44);
    assert_eq!(t["min_area_px"], 4);
    assert_eq!(t["loaded_from_file"], true);
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scene_has_camera_poses_and_the_workspace_box() {
    let dir = TempDir::new("web-scene");
    let running = app::start(config(&dir, None), Overrides::default())
        .await
        .unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.params_loaded.load(Relaxed)).await);
    let s = get(addr, "/api/scene").await.json();
    let cams = s["cameras"].as_array().unwrap();
    assert_eq!(cams.len(), 2);
    assert_eq!(cams[0]["width_px"], 640);
    assert!(cams[1]["fx_px"].as_f64().unwrap() > 100.0);
    assert_eq!(cams[0]["t_cam_from_cam0_mm"], serde_json::json!([0.0, 0.0, 0.0]));
    assert!(s["workspace_mm"].is_null(), "no [robot] configured");
    running.shutdown().await;
}

/// The value of an unlabelled metric in `/metrics` text.
fn metric(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .and_then(|v| v.trim().parse().ok())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn viewer_drops_and_copies_are_on_metrics() {
    let dir = TempDir::new("web-viewer-metrics");
    let mut cfg = config(&dir, None);
    // Sets every 2.5 ms against the viewer's 5 ms poll: a blob viewer cannot send them all.
    if let Some(sim) = cfg.source.sim.as_mut() {
        sim.fps = 400.0;
    }
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let addr = running.addrs.status;
    let st = running.status.clone();
    assert!(eventually(10, async || st.tracked.load(Relaxed) > 10).await);
    let mut ws = connect_live(addr, r#"{"type": "subscribe", "blobs": true}"#).await;
    let (mut blob_sets, mut dropped) = (0u64, 0u64);
    let end = Instant::now() + Duration::from_millis(1500);
    while Instant::now() < end {
        let Ok(Some(Ok(Message::Text(t)))) = tokio::time::timeout(Duration::from_secs(5), ws.next()).await
        else {
            continue;
        };
        let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
        if v["type"] == "blobs" {
            blob_sets += 1;
            dropped = v["dropped"].as_u64().unwrap();
        }
    }
    let (code, text) = http_get(addr, "/metrics").await;
    assert_eq!(code, 200);
    let status = status_json(addr).await;
    running.shutdown().await;
    let m = |name: &str| metric(&text, name).unwrap_or_else(|| panic!("no {name} in /metrics:\n{text}"));
    let on_metrics = m("irtrackd_viewer_sets_dropped_total");
    println!(
        "blob viewer: {blob_sets} sets sent, {dropped} dropped (its own count); /metrics: dropped {on_metrics}, blob copies {}, live viewers {}",
        m("irtrackd_viewer_blob_copies_total"),
        m("irtrackd_live_viewers")
    );
    assert!(
        blob_sets > 10 && dropped > 0,
        "{blob_sets} sent, {dropped} dropped"
    );
    // /metrics was read after the viewer's last message and before /status.
    assert!(on_metrics >= dropped as f64, "{on_metrics} < {dropped}");
    assert!(status["viewers"]["blob_sets_dropped"].as_f64().unwrap() >= on_metrics);
    assert_eq!(m("irtrackd_live_viewers"), 1.0);
    assert!(m("irtrackd_viewer_blob_copies_total") >= blob_sets as f64);
    for name in [
        "irtrackd_viewer_frame_copies_total",
        "irtrackd_viewer_frame_copy_skips_total",
        "irtrackd_viewer_blob_copy_skips_total",
    ] {
        m(name);
    }
}
