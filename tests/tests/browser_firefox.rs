//! The set-up page in Firefox (Debian's firefox-esr), against the real `irtrackd` on the
//! simulated cameras, at a laptop size and at a tablet size. Firefox runs on a virtual X display
//! (Xvfb): its headless mode offers no WebGL without a GPU, while on X it renders WebGL with
//! Mesa's llvmpipe, so the 3-D view is tested too.
//!
//! Firefox is driven over Marionette, its own remote protocol (what geckodriver translates
//! WebDriver into): length-prefixed JSON messages on a local TCP port, simple enough to speak
//! here, so no geckodriver (not packaged by Debian) is needed. Checks what an operator would
//! see: the page loads without a script error, the previews of both cameras update with one
//! kept blob each, the threshold view tints pixels, the 3-D view runs, and at tablet width
//! nothing sticks out sideways. Screenshots: `target/browser-test/setup-view-firefox.png` and
//! `setup-view-tablet.png`.
//!
//! Needs `firefox-esr` and `xvfb` (installed by `cargo xtask setup`) and the irtrackd binary
//! (`cargo test --workspace` builds it).

mod common;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use common::*;
use serde_json::{Value, json};

const FIREFOX: &str = "/usr/bin/firefox-esr";
const XVFB: &str = "/usr/bin/Xvfb";

/// Starts Xvfb on a display number it picks itself (`-displayfd`); returns it and the display.
fn start_xvfb() -> (Proc, String) {
    let mut xvfb = spawn(
        Command::new(XVFB)
            .args([
                "-displayfd",
                "1",
                "-screen",
                "0",
                "1600x1300x24",
                "-nolisten",
                "tcp",
            ])
            .stderr(Stdio::null()),
        "Xvfb",
    );
    // `-displayfd 1`: the display number is its first output line.
    let line = xvfb.wait_line("", Duration::from_secs(20)).unwrap();
    let n: u32 = line
        .trim()
        .parse()
        .unwrap_or_else(|_| panic!("Xvfb printed no display number: {line:?}"));
    (xvfb, format!(":{n}"))
}

/// A Marionette session (protocol 3): commands `[0, id, name, params]`, answers
/// `[1, id, error, result]`, each message framed as `<length>:<json>`.
struct Marionette {
    reader: BufReader<TcpStream>,
    writer: TcpStream,
    next_id: u64,
}

impl Marionette {
    fn connect(port: u16) -> Self {
        let writer = TcpStream::connect(("127.0.0.1", port)).unwrap();
        writer.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
        let mut m = Marionette {
            reader: BufReader::new(writer.try_clone().unwrap()),
            writer,
            next_id: 0,
        };
        let hello = m.read();
        assert_eq!(hello["applicationType"], "gecko", "not Firefox: {hello}");
        m
    }

    fn read(&mut self) -> Value {
        let mut len = Vec::new();
        self.reader.read_until(b':', &mut len).unwrap();
        len.pop();
        let n: usize = String::from_utf8(len).unwrap().trim().parse().unwrap();
        let mut body = vec![0; n];
        self.reader.read_exact(&mut body).unwrap();
        serde_json::from_slice(&body).unwrap()
    }

    fn cmd(&mut self, name: &str, params: Value) -> Result<Value, String> {
        self.next_id += 1;
        let id = self.next_id;
        let msg = json!([0, id, name, params]).to_string();
        write!(self.writer, "{}:{msg}", msg.len()).unwrap();
        loop {
            let a = self.read();
            if a[0] == 1 && a[1] == id {
                if !a[2].is_null() {
                    return Err(format!("{name}: {}", a[2]["message"]));
                }
                return Ok(a[3].clone());
            }
        }
    }

    /// Evaluates `expr` in the page.
    fn js(&mut self, expr: &str) -> Value {
        let r = self
            .cmd(
                "WebDriver:ExecuteScript",
                json!({"script": format!("return ({expr});"), "args": []}),
            )
            .unwrap();
        r["value"].clone()
    }

    /// Polls `expr` until `pred` holds; fails with the page's errors and the last value.
    fn wait_for(&mut self, what: &str, secs: u64, expr: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let v = self.js(expr);
            if pred(&v) {
                return v;
            }
            if Instant::now() > deadline {
                let errors = self.js("window.__irtrackErrors");
                panic!("Firefox: {what} not seen within {secs} s; last value {v}; page errors {errors}");
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn screenshot(&mut self, path: &Path) {
        let r = self
            .cmd("WebDriver:TakeScreenshot", json!({"full": false}))
            .unwrap();
        let png = base64::engine::general_purpose::STANDARD
            .decode(r["value"].as_str().unwrap())
            .unwrap();
        assert!(png.starts_with(b"\x89PNG"), "screenshot is not a PNG");
        std::fs::write(path, &png).unwrap();
        println!("screenshot: {} ({} bytes)", path.display(), png.len());
    }
}

fn out_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let d = exe.ancestors().nth(3).unwrap().join("browser-test");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Starts Firefox on `display` with Marionette on a port it picks; returns the process and port.
fn start_firefox(profile: &Path, display: &str) -> (Proc, u16) {
    std::fs::create_dir_all(profile).unwrap();
    // Port 0: Firefox picks a free one and writes it to MarionetteActivePort. The rest keeps a
    // fresh profile from calling home or showing first-run pages.
    std::fs::write(
        profile.join("user.js"),
        "user_pref(\"marionette.port\", 0);\n\
         user_pref(\"browser.shell.checkDefaultBrowser\", false);\n\
         user_pref(\"browser.startup.homepage_override.mstone\", \"ignore\");\n\
         user_pref(\"datareporting.policy.dataSubmissionEnabled\", false);\n\
         user_pref(\"toolkit.telemetry.reportingpolicy.firstRun\", false);\n\
         user_pref(\"app.update.disabledForTesting\", true);\n\
",
    )
    .unwrap();
    let guard = spawn(
        Command::new(FIREFOX)
            .args(["--marionette", "--no-remote", "--profile"])
            .arg(profile)
            .env("DISPLAY", display)
            .env_remove("WAYLAND_DISPLAY")
            .stderr(Stdio::null()),
        "firefox",
    );
    let port_file = profile.join("MarionetteActivePort");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if let Some(port) = std::fs::read_to_string(&port_file)
            .ok()
            .and_then(|s| s.trim().parse::<u16>().ok())
        {
            return (guard, port);
        }
        assert!(
            Instant::now() < deadline,
            "Firefox wrote no Marionette port within 60 s"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn cams(v: &Value) -> Vec<Value> {
    v.as_array().cloned().unwrap_or_default()
}

const TINTED_JS: &str = "Array.from(document.querySelectorAll('canvas.preview')).map((cv) => { \
    const d = cv.getContext('2d').getImageData(0, 0, cv.width, cv.height).data; let n = 0; \
    for (let i = 0; i < d.length; i += 4) if (d[i] === 255 && d[i + 1] === 61 && d[i + 2] === 242) n++; \
    return n; })";

#[test]
fn setup_page_in_firefox_at_laptop_and_tablet_size() {
    for p in [FIREFOX, XVFB] {
        assert!(
            Path::new(p).is_file(),
            "{p} is missing: the Firefox test of the set-up page needs Debian's firefox-esr and \
             xvfb; run `cargo xtask setup` (or `apt-get install firefox-esr xvfb`)"
        );
    }
    let t0 = Instant::now();
    let dir = temp_dir("firefox");
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        "[service]\nparams_from_simulator = true\n[source.sim]\nfps = 30.0\n[leds]\nbackend = \"sim\"\n",
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");
    let (_xvfb, display) = start_xvfb();
    let (_firefox, port) = start_firefox(&dir.join("profile"), &display);
    let mut m = Marionette::connect(port);
    let caps = m
        .cmd("WebDriver:NewSession", json!({"capabilities": {}}))
        .unwrap();
    println!("Firefox {} (Marionette)", caps["capabilities"]["browserVersion"]);
    m.cmd("WebDriver:SetWindowRect", json!({"width": 1600, "height": 1300}))
        .unwrap();
    m.cmd("WebDriver:Navigate", json!({"url": format!("http://{status}/")}))
        .unwrap();
    m.wait_for(
        "page ready",
        20,
        "window.__irtrack && window.__irtrack.ready",
        |v| v == true,
    );

    let first = m.wait_for(
        "a preview of every camera",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).len() == 2 && cams(v).iter().all(|c| c["shown"].as_u64() >= Some(1)),
    );
    m.wait_for("previews updating", 20, "window.__irtrack.cameras()", |v| {
        cams(v)
            .iter()
            .zip(cams(&first))
            .all(|(now, then)| now["shown"].as_u64() >= then["shown"].as_u64().map(|n| n + 3))
    });
    let cameras = m.wait_for(
        "one kept blob per camera",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).iter().all(|c| c["kept"] == 1),
    );
    println!("previews live, one kept blob per camera: {cameras}");

    m.js("document.getElementById('threshold-view').click()");
    let tinted = m.wait_for("tinted pixels in both previews", 10, TINTED_JS, |v| {
        v.as_array()
            .is_some_and(|a| a.len() == 2 && a.iter().all(|n| n.as_u64() > Some(0)))
    });
    println!("threshold view: tinted pixels per camera {tinted}");

    let scene = m.wait_for("3-D view with positions", 15, "window.__irtrack.scene()", |v| {
        v["webgl"] == true && v["records"].as_u64() > Some(5)
    });
    println!("3-D view: {scene}");
    let errors = m.js("window.__irtrackErrors");
    assert_eq!(errors, json!([]), "script errors in Firefox");
    m.screenshot(&out_dir().join("setup-view-firefox.png"));

    // A tablet held upright: the page is one column and nothing is wider than the screen.
    m.cmd("WebDriver:SetWindowRect", json!({"width": 820, "height": 1180}))
        .unwrap();
    let fits = m.wait_for(
        "tablet layout without sideways scrolling",
        10,
        "[window.innerWidth, document.documentElement.scrollWidth]",
        |v| {
            let (w, sw) = (v[0].as_u64().unwrap_or(0), v[1].as_u64().unwrap_or(u64::MAX));
            w > 0 && w <= 820 && sw <= w
        },
    );
    println!("tablet: viewport and page width {fits}");
    // One column, the cameras on top (what an operator aims with comes first).
    let order = m.js(
        "Array.from(document.querySelectorAll('.panel')).map((p) => [p.className, Math.round(p.getBoundingClientRect().top)]).sort((a, b) => a[1] - b[1]).map((p) => p[0])",
    );
    println!("tablet: panels from the top {order}");
    assert!(
        order[0].as_str().is_some_and(|c| c.contains("cameras-panel")),
        "the cameras are not the first panel at tablet width: {order}"
    );
    m.wait_for(
        "previews still updating at tablet size",
        10,
        "window.__irtrack.cameras()",
        |v| {
            cams(v)
                .iter()
                .zip(cams(&cameras))
                .all(|(now, then)| now["shown"].as_u64() >= then["shown"].as_u64().map(|n| n + 2))
        },
    );
    assert_eq!(
        m.js("window.__irtrackErrors"),
        json!([]),
        "script errors in Firefox"
    );
    m.screenshot(&out_dir().join("setup-view-tablet.png"));
    let _ = m.cmd("WebDriver:DeleteSession", json!({}));
    println!("Firefox test took {:.1} s", t0.elapsed().as_secs_f64());
}
