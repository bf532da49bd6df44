//! Demo: the set-up page (docs/setup-view.md). [`screenshot`] runs irtrackd on simulated
//! cameras and saves headless Chromium's picture of the page; [`view`] (`cargo xtask demo
//! --view`) keeps irtrackd running until Ctrl-C so a person can open the page.

use std::net::{SocketAddr, TcpListener};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use crate::util::{Proc, addr_field, http, json};

/// Operator password of the demo's irtrackd (bound to 127.0.0.1 only).
pub const DEMO_PASSWORD: &str = "demo";
const CHROMIUM: &str = "/usr/bin/chromium";
/// The status listener's usual port, used by `--view` when it is free.
const VIEW_PORT: u16 = 7704;

fn config(status_listen: &str, hash: &str) -> String {
    format!(
        r#"# Written by `cargo xtask demo` (set-up view).
[service]
params_from_simulator = true
operator_password_hash = "{hash}"
[listen]
params = "127.0.0.1:0"
stream_ndjson = "127.0.0.1:0"
stream_binary = "127.0.0.1:0"
status = "{status_listen}"
[source.sim]
fps = 30.0
[leds]
backend = "sim"
"#
    )
}

/// Starts irtrackd (simulated cameras, parameters from the simulator) in `dir`.
fn start(bin_dir: &Path, dir: &Path, status_listen: &str) -> Result<(Proc, SocketAddr)> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let irtrackd = bin_dir.join("irtrackd");
    let cfg = dir.join("irtrackd.toml");
    let hash = irtrack_testkit::harness::operator_hash(&irtrackd, DEMO_PASSWORD)?;
    std::fs::write(&cfg, config(status_listen, &hash))?;
    let state = dir.join("state");
    // A fresh state directory: values saved by an earlier run would be loaded at start.
    if state.exists() {
        std::fs::remove_dir_all(&state).with_context(|| format!("removing {}", state.display()))?;
    }
    // Its own [listen] addresses (the usual status port for --view), not --ephemeral-ports.
    let mut irtrackd = Proc::spawn(
        Command::new(&irtrackd)
            .arg("-c")
            .arg(&cfg)
            .arg("--state-dir")
            .arg(&state)
            .stderr(Stdio::null()),
        "irtrackd",
    )?;
    let ready = irtrackd.wait_line("irtrackd ready", Duration::from_secs(30))?;
    Ok((irtrackd, addr_field(&ready, "status=")?))
}

/// Waits until irtrackd has processed frame sets (so the page has something to show).
fn wait_running(status: SocketAddr) -> Result<()> {
    let end = Instant::now() + Duration::from_secs(20);
    loop {
        let (code, body) = http(status, "GET", "/status")?;
        let tracked = json::parse(&body)
            .ok()
            .and_then(|v| json::f64_at(&v, "processing.tracked"));
        if code == 200 && tracked.is_some_and(|n| n > 0.0) {
            return Ok(());
        }
        if Instant::now() > end {
            bail!("irtrackd tracked nothing within 20 s");
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// Saves `out/setup-view.png`: headless Chromium's picture of the page served by a running
/// irtrackd.
pub fn screenshot(bin_dir: &Path, out: &Path) -> Result<()> {
    if !Path::new(CHROMIUM).is_file() {
        bail!("{CHROMIUM} is missing: run `cargo xtask setup` (installs chromium)");
    }
    let dir = out.join("view");
    let (_irtrackd, status) = start(bin_dir, &dir, "127.0.0.1:0")?;
    wait_running(status)?;
    let url = format!("http://{status}/");
    println!("irtrackd serves the set-up page at {url}");
    let png = out.join("setup-view.png");
    let _ = std::fs::remove_file(&png);
    let profile = dir.join("chromium-profile");
    let _ = std::fs::remove_dir_all(&profile);
    // The virtual-time budget lets the page run ~8 s (previews, status, 3-D) before the picture.
    let output = Command::new(CHROMIUM)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-dev-shm-usage",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--hide-scrollbars",
            "--window-size=1600,1300",
            "--virtual-time-budget=8000",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(format!("--screenshot={}", png.display()))
        .arg(&url)
        .output()
        .context("running chromium")?;
    let len = std::fs::metadata(&png).map(|m| m.len()).unwrap_or(0);
    if len == 0 {
        bail!(
            "chromium did not save {} ({}): {}",
            png.display(),
            output.status,
            String::from_utf8_lossy(&output.stderr).trim()
        );
    }
    println!("saved a screenshot of the page: {} ({len} bytes)", png.display());
    println!("to keep the page open in your browser: cargo xtask demo --view");
    Ok(())
}

/// `cargo xtask demo --view`: irtrackd on simulated cameras until Ctrl-C.
pub fn view(bin_dir: &Path, out: &Path) -> Result<()> {
    let listen = if TcpListener::bind(("127.0.0.1", VIEW_PORT)).is_ok() {
        format!("127.0.0.1:{VIEW_PORT}")
    } else {
        println!("port {VIEW_PORT} is taken; using a free one");
        "127.0.0.1:0".to_string()
    };
    let (irtrackd, status) = start(bin_dir, &out.join("view"), &listen)?;
    println!("\nirtrackd runs on simulated cameras. Open the set-up page:\n\n    http://{status}/\n");
    println!("Sign in with the password `{DEMO_PASSWORD}` to change threshold, exposure and gain.");
    println!("Press Ctrl-C to stop.");
    let code = irtrackd.wait()?;
    println!("irtrackd stopped ({code})");
    Ok(())
}
