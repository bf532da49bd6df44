//! Driving the set-up page in Debian's headless Chromium over WebDriver (chromedriver, started
//! on a free port) with `fantoccini`: the helpers the browser tests share (starting the driver
//! and a session, opening the page, evaluating and polling page expressions, screenshots).

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::{Client, ClientBuilder, Locator, key::Key};
use serde_json::{Value, json};

use super::{Proc, bin, spawn};

pub const CHROMIUM: &str = "/usr/bin/chromium";
pub const CHROMEDRIVER: &str = "/usr/bin/chromedriver";
pub const WINDOW: (u32, u32) = (1600, 1300);

/// Fails (never skips) without the browser, naming the fix.
pub fn require_browser() {
    for p in [CHROMIUM, CHROMEDRIVER] {
        assert!(
            Path::new(p).is_file(),
            "{p} is missing: the set-up page test needs Debian's chromium and chromium-driver; \
             run `cargo xtask setup` (or `apt-get install chromium chromium-driver`)"
        );
    }
}

/// target/browser-test, next to the test binary's profile directory.
pub fn out_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let target = exe.ancestors().nth(3).unwrap().to_path_buf();
    let d = target.join("browser-test");
    std::fs::create_dir_all(&d).unwrap();
    d
}

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// An Argon2id hash of `password` made by irtrackd itself (`--hash-password` reads stdin).
pub fn password_hash(password: &str) -> String {
    irtrack_testkit::harness::irtrackd::operator_hash(&bin("irtrackd"), password)
        .unwrap_or_else(|e| panic!("{e}"))
}

/// Starts chromedriver on a free port; returns its guard and URL once it answers.
pub fn start_chromedriver(dir: &Path) -> (Proc, String) {
    let port = free_port();
    let guard = spawn(
        Command::new(CHROMEDRIVER)
            .arg(format!("--port={port}"))
            .arg(format!("--log-path={}", dir.join("chromedriver.log").display()))
            .stderr(Stdio::null()),
        "chromedriver",
    );
    let addr: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let end = Instant::now() + Duration::from_secs(15);
    loop {
        if chromedriver_ready(addr) {
            break;
        }
        assert!(
            Instant::now() < end,
            "chromedriver did not come up on {addr} within 15 s"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    (guard, format!("http://{addr}"))
}

/// chromedriver's `/status` says ready. (It refuses HTTP/1.0, and checks that the Host is the loopback
/// address it listens on, so this cannot use the common helper with its made-up Host.)
pub fn chromedriver_ready(addr: SocketAddr) -> bool {
    use std::io::{Read, Write};
    let Ok(mut s) = std::net::TcpStream::connect(addr) else {
        return false;
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(2)));
    if write!(
        s,
        "GET /status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .is_err()
    {
        return false;
    }
    let mut resp = String::new();
    let _ = s.read_to_string(&mut resp);
    resp.starts_with("HTTP/1.") && resp.contains("\"ready\":true")
}

pub async fn browser(driver_url: &str, profile: &Path, downloads: &Path) -> Client {
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": CHROMIUM,
            "args": [
                "--headless",
                // As root (CI) Chromium refuses to start with its sandbox.
                "--no-sandbox",
                "--disable-dev-shm-usage",
                // WebGL for three.js on a machine without a GPU: SwiftShader.
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                format!("--window-size={},{}", WINDOW.0, WINDOW.1),
                format!("--user-data-dir={}", profile.display()),
            ],
            // "Save frame set" downloads one file per camera: no prompt, several allowed.
            "prefs": {
                "download.default_directory": downloads.display().to_string(),
                "download.prompt_for_download": false,
                "profile.default_content_setting_values.automatic_downloads": 1,
            },
        }),
    );
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(driver_url)
        .await
        .unwrap_or_else(|e| panic!("WebDriver session with {CHROMIUM} failed: {e}"))
}

/// Starts chromedriver and a headless Chromium session whose downloads land in
/// `dir/downloads`; the driver process lives as long as the returned handle.
pub async fn open_browser(dir: &Path) -> (Proc, Client, PathBuf) {
    let (driver, driver_url) = start_chromedriver(dir);
    let downloads = dir.join("downloads");
    std::fs::create_dir_all(&downloads).unwrap();
    let c = browser(&driver_url, &dir.join("profile"), &downloads).await;
    (driver, c, downloads)
}

/// Opens the set-up page at `url` and waits until its script reports ready.
pub async fn open_page(c: &Client, url: &str) {
    c.goto(url).await.unwrap();
    wait_for(
        c,
        "page ready",
        20,
        "window.__irtrack && window.__irtrack.ready",
        |v| v == true,
    )
    .await;
}

/// Evaluates `expr` in the page.
pub async fn js(c: &Client, expr: &str) -> Value {
    c.execute(&format!("return ({expr});"), vec![])
        .await
        .unwrap_or_else(|e| panic!("evaluating `{expr}` failed: {e}"))
}

/// Polls `expr` until `pred` holds; fails with `what`, the last value and the page's errors.
pub async fn wait_for(c: &Client, what: &str, secs: u64, expr: &str, pred: impl Fn(&Value) -> bool) -> Value {
    let end = Instant::now() + Duration::from_secs(secs);
    loop {
        let v = js(c, expr).await;
        if pred(&v) {
            return v;
        }
        if Instant::now() > end {
            let errors = js(c, "window.__irtrackErrors || []").await;
            let faults = js(c, "window.__irtrack ? window.__irtrack.faults() : null").await;
            panic!(
                "{what}: not reached within {secs} s; last value {v}; page errors {errors}; faults on the page {faults}"
            );
        }
        tokio::time::sleep(Duration::from_millis(150)).await;
    }
}

pub async fn screenshot(c: &Client, path: &Path) {
    let png = c.screenshot().await.unwrap();
    std::fs::write(path, &png).unwrap();
    println!("screenshot: {} ({} bytes)", path.display(), png.len());
}

/// Types `value` into the number field `id` and leaves it (fires `change`, as a person would).
pub async fn type_number(c: &Client, id: &str, value: &str) {
    // Select what is there and type over it, keeping the focus in the field: WebDriver's
    // `clear` blurs the field, and the page then shows the board's value in it again.
    let field = c.find(Locator::Id(id)).await.unwrap();
    field.click().await.unwrap();
    field
        .send_keys(&format!(
            "{}a{}{value}{}",
            char::from(Key::Control),
            char::from(Key::Null),
            char::from(Key::Tab)
        ))
        .await
        .unwrap();
}

/// A screenshot of the element `css` alone, saved to `path`: the element is scrolled into view,
/// the viewport shot and cut to the element's box. (chromedriver's own element screenshot
/// sometimes cut a box further down the page here, after the page scrolled.) Taken again
/// while the box moves (images arriving above it shift the layout).
pub async fn element_screenshot(c: &Client, css: &str, path: &Path) {
    let css_js = serde_json::to_string(css).unwrap();
    js(
        c,
        &format!("(document.querySelector({css_js}).scrollIntoView({{block: 'center'}}), true)"),
    )
    .await;
    let rect_js = format!(
        "(() => {{ const r = document.querySelector({css_js}).getBoundingClientRect(); \
         return [r.left, r.top, r.width, r.height, window.devicePixelRatio]; }})()"
    );
    let mut tries = 0;
    let (png, rect) = loop {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let before = js(c, &rect_js).await;
        let png = c.screenshot().await.unwrap();
        let after = js(c, &rect_js).await;
        tries += 1;
        if before == after || tries == 10 {
            break (png, after);
        }
    };
    let f = |i: usize| rect[i].as_f64().unwrap_or_else(|| panic!("{css}: no box {rect}"));
    let dpr = f(4);
    let cut = [f(0), f(1), f(2), f(3)].map(|v| (v * dpr).round().max(0.0) as u32);
    let out = crop_png(&png, cut).unwrap_or_else(|e| panic!("{css}: cutting the screenshot: {e}"));
    std::fs::write(path, &out).unwrap();
    println!("screenshot: {} ({} bytes, {css})", path.display(), out.len());
}

/// The part `[x, y, w, h]` (pixels, clamped to the picture) of a PNG, as a PNG.
fn crop_png(png: &[u8], [x, y, w, h]: [u32; 4]) -> Result<Vec<u8>, String> {
    let mut reader = png::Decoder::new(png).read_info().map_err(|e| e.to_string())?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(|e| e.to_string())?;
    if info.bit_depth != png::BitDepth::Eight {
        return Err(format!("{:?} bits per sample", info.bit_depth));
    }
    let px = info.color_type.samples();
    let (x, y) = (x.min(info.width), y.min(info.height));
    let (w, h) = (w.min(info.width - x), h.min(info.height - y));
    if w == 0 || h == 0 {
        return Err(format!(
            "the box {x},{y} {w}×{h} is outside the {}×{} picture",
            info.width, info.height
        ));
    }
    let mut data = Vec::with_capacity((w * h) as usize * px);
    for row in y..y + h {
        let start = row as usize * info.line_size + x as usize * px;
        data.extend_from_slice(&buf[start..start + w as usize * px]);
    }
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(info.color_type);
    enc.set_depth(info.bit_depth);
    let mut writer = enc.write_header().map_err(|e| e.to_string())?;
    writer.write_image_data(&data).map_err(|e| e.to_string())?;
    writer.finish().map_err(|e| e.to_string())?;
    Ok(out)
}
