//! The System panel's update upload in a real browser: Debian's headless Chromium over WebDriver
//! (helpers in `common/chromium.rs`) against the real `irtrackd` with the simulated system
//! updater (`[update] backend = "simulated"`, docs/updates.md), which checks bundles as a board
//! does (layout, `openssl cms -verify` against the CA, board, version). Bundles and keys are
//! real: made with the host's `openssl` and `rauc` (`irtrack_testkit::update_bundles`).
//!
//! Checks, as an operator would see them: without an operator password on the board, and then
//! without sign-in, the file chooser and the button are disabled and the panel says why and
//! what to do; signed in, a good bundle chosen through the file input (WebDriver's send-keys
//! of its path) uploads with the progress bar to 100 %, installs, and the panel shows the other
//! slot with the new version and "reboot to start it"; a bundle signed by a key the board does
//! not trust and a truncated bundle are refused with the reason in words. At 1400 px the Health
//! panel's camera rows and clock rows stay on one or two lines. Screenshots (looked at) under
//! `target/browser-test/`: `system-no-password.png`, `system-signed-out.png`,
//! `system-installed.png`, `system-refused-signature.png`, `system-refused-truncated.png`,
//! `health-1400.png`, `setup-view-update.png`.
//!
//! Needs `chromium`, `chromium-driver`, `openssl` and `rauc` (`cargo xtask setup`) and the
//! irtrackd binary (`cargo build -p irtrack-firmware --bin irtrackd`).

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::chromium::*;
use common::*;
use fantoccini::{Client, Locator};
use irtrack_testkit::update_bundles::{make_bundle, make_update_keys};
use serde_json::{Value, json};

const PASSWORD: &str = "browser-update-password";
/// The board type the simulated updater accepts (the CI image's).
const COMPATIBLE: &str = "irtrack-qemu-arm64";
/// The laptop width at which the Health table's clock column used to wrap to six lines.
const LAPTOP: (u32, u32) = (1400, 1700);

/// `len` bytes of noise (xorshift), standing in for a root file system image that does not
/// compress away, so the upload takes a while.
fn noise(len: usize, seed: u32) -> Vec<u8> {
    let mut x = seed | 1;
    (0..len)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            x as u8
        })
        .collect()
}

fn utf8(p: &Path) -> &str {
    p.to_str().expect("temporary paths are UTF-8")
}

/// irtrackd on four simulated free-running cameras (so every clock cell has figures) with the
/// simulated system updater trusting `ca`, and the operator password when `operator` is set.
fn config(dir: &Path, ca: &Path, operator: Option<&str>) -> PathBuf {
    let mut cfg = IrtrackdConfig::simulated()
        .set("service.params_from_simulator", true)
        .set("source.sim.rig", "ring")
        .set("source.sim.ring_cameras", 4)
        .set("source.sim.fps", 30.0)
        .set("source.sim.timing.preset", "free_running")
        .set("update.backend", "simulated")
        .set("update.ca_cert", utf8(ca))
        .set("update.compatible", COMPATIBLE)
        .set("update.sim_dir", utf8(&dir.join("system")))
        .set("update.running_version", "1.1.0");
    if let Some(pw) = operator {
        cfg = cfg.operator_hash(&password_hash(pw));
    }
    let path = dir.join(if operator.is_some() {
        "irtrackd.toml"
    } else {
        "irtrackd-no-password.toml"
    });
    cfg.write(&path).unwrap();
    path
}

/// The value of the System panel's row `name` ("running", "other slot", …).
fn row<'a>(p: &'a Value, name: &str) -> &'a str {
    p["rows"]
        .as_array()
        .and_then(|rows| rows.iter().find(|r| r[0] == name))
        .and_then(|r| r[1].as_str())
        .unwrap_or_else(|| panic!("no row {name:?} in the System panel: {p}"))
}

/// Chooses `bundle` in the page's file input (WebDriver types the path into it, as a person
/// picking the file would) and presses "Upload and install".
async fn upload(c: &Client, bundle: &Path) {
    let input = c.find(Locator::Id("update-file")).await.unwrap();
    // A single-file input: clearing first so the new path replaces the old one.
    input.clear().await.unwrap();
    input.send_keys(utf8(bundle)).await.unwrap();
    wait_for(
        c,
        "the upload button enabled with a file chosen",
        10,
        "window.__irtrack.update()",
        |v| v["button_enabled"] == true,
    )
    .await;
    click(c, "update-btn").await;
}

/// Uploads `bundle` and waits up to `secs` until the panel's message says how it ended.
async fn upload_until(
    c: &Client,
    bundle: &Path,
    what: &str,
    secs: u64,
    ended: impl Fn(&str) -> bool,
) -> Value {
    upload(c, bundle).await;
    wait_for(c, what, secs, "window.__irtrack.update()", |v| {
        v["message"].as_str().is_some_and(&ended)
    })
    .await
}

async fn click(c: &Client, id: &str) {
    c.find(Locator::Id(id)).await.unwrap().click().await.unwrap();
}

/// The board's own `/status` → `system`.
fn board_system(status: SocketAddr) -> Value {
    let (code, body) = http(status, "GET", "/status");
    assert_eq!(code, 200, "{body}");
    serde_json::from_str::<Value>(&body).unwrap()["system"].clone()
}

/// Per table row, the lines each of its cells takes (text line boxes, by Range rects).
const LINES_JS: &str = "(sel) => Array.from(document.querySelectorAll(sel + ' tbody tr')).map((tr) => \
    Array.from(tr.cells).map((td) => { const r = document.createRange(); \
    r.selectNodeContents(td); return r.getClientRects().length; }))";

/// Line counts of `LINES_JS`: (most lines of any cell but the last, lines of the last).
fn lines(v: &Value) -> Vec<(u64, u64)> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|row| {
            let n: Vec<u64> = row
                .as_array()
                .unwrap()
                .iter()
                .map(|n| n.as_u64().unwrap())
                .collect();
            let (last, rest) = n.split_last().unwrap();
            (rest.iter().copied().max().unwrap_or(0), *last)
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn update_upload_from_the_system_panel_in_headless_chromium() {
    require_browser();
    let t0 = Instant::now();
    let dir = temp_dir("browser-update");
    let out = out_dir();

    let (keys, foreign) = (dir.join("keys"), dir.join("foreign"));
    let ca = make_update_keys(&keys, "page").unwrap();
    make_update_keys(&foreign, "stranger").unwrap();
    let good = make_bundle(&keys, &dir, "good", COMPATIBLE, "1.2.0", &noise(24 << 20, 7)).unwrap();
    let untrusted = make_bundle(
        &foreign,
        &dir,
        "untrusted",
        COMPATIBLE,
        "1.3.0",
        &noise(1 << 20, 11),
    )
    .unwrap();
    let bytes = std::fs::read(&good).unwrap();
    let truncated = dir.join("truncated.raucb");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    println!(
        "bundles made in {:.1} s: good {:.1} MiB",
        t0.elapsed().as_secs_f64(),
        bytes.len() as f64 / 1048576.0
    );

    let (_driver, c, _) = open_browser(&dir).await;
    c.set_window_size(LAPTOP.0, LAPTOP.1).await.unwrap();
    let result = tokio::time::timeout(Duration::from_secs(180), async {
        // 1. A board without an operator password: no upload, and the panel says how to set one.
        {
            let cfg = config(&dir, &ca, None);
            let (_irtrackd, ready) = start_irtrackd(&cfg, &dir.join("state-no-password"));
            let status = addr_field(&ready, "status=");
            open_page(&c, &format!("http://{status}/")).await;
            let p = wait_for(
                &c,
                "the System panel of a board without an operator password",
                20,
                "window.__irtrack.update()",
                |v| v["why"].as_str().is_some_and(|s| !s.is_empty()),
            )
            .await;
            println!("no operator password: {}", p["why"]);
            assert_eq!(p["file_enabled"], false, "{p}");
            assert_eq!(p["button_enabled"], false, "{p}");
            let why = p["why"].as_str().unwrap();
            assert!(
                why.contains("no operator password is set")
                    && why.contains("irtrackd --hash-password")
                    && why.contains("operator_password_hash"),
                "{why}"
            );
            assert!(row(&p, "running").contains("1.1.0"), "{p}");
            element_screenshot(&c, ".system-panel", &out.join("system-no-password.png")).await;
        }

        // 2. The same board with a password, not signed in.
        let cfg = config(&dir, &ca, Some(PASSWORD));
        let (_irtrackd, ready) = start_irtrackd(&cfg, &dir.join("state"));
        let status = addr_field(&ready, "status=");
        open_page(&c, &format!("http://{status}/")).await;
        let p = wait_for(
            &c,
            "the System panel before sign-in",
            20,
            "window.__irtrack.update()",
            |v| v["why"].as_str().is_some_and(|s| s.contains("sign in")),
        )
        .await;
        println!("not signed in: {}", p["why"]);
        assert_eq!(p["file_enabled"], false, "{p}");
        assert_eq!(p["button_enabled"], false, "{p}");
        assert!(row(&p, "running").starts_with("A · 1.1.0"), "{p}");
        assert!(row(&p, "other slot").contains("empty"), "{p}");
        // The board agrees: no upload without sign-in.
        let (code, _) = http(status, "POST", "/api/update");
        assert_eq!(code, 401, "POST /api/update without sign-in answered {code}");
        element_screenshot(&c, ".system-panel", &out.join("system-signed-out.png")).await;

        // 3. The Health panel at laptop width: camera rows and clock rows readable.
        let clocks = wait_for(
            &c,
            "figures in every camera's clock row",
            30,
            "window.__irtrack.clocks()",
            |v| {
                v.as_array().is_some_and(|rows| {
                    rows.len() == 4 && rows.iter().all(|r| r["cells"][2] != "—" && r["cells"][3] != "—")
                })
            },
        )
        .await;
        for r in clocks.as_array().unwrap() {
            println!("clock row {} — tooltip: {}", r["cells"], r["title"]);
            let title = r["title"].as_str().unwrap();
            assert!(title.contains("fps") && title.contains("jitter"), "{r}");
        }
        assert_eq!(clocks[0]["cells"][2], "reference", "{clocks}");
        // Figures on one line; only the events may take a second.
        let clock_lines = lines(&js(&c, &format!("({LINES_JS})('#camera-clocks')")).await);
        println!(
            "lines per clock row (figures, events) at {} px: {clock_lines:?}",
            LAPTOP.0
        );
        assert!(
            clock_lines
                .iter()
                .all(|&(figures, events)| figures == 1 && events <= 2),
            "a clock row wraps at {} px: {clock_lines:?}",
            LAPTOP.0
        );
        let camera_lines = lines(&js(&c, &format!("({LINES_JS})('#camera-health')")).await);
        assert!(
            camera_lines.iter().all(|&(a, b)| a == 1 && b == 1),
            "a camera row of the health table wraps at {} px: {camera_lines:?}",
            LAPTOP.0
        );
        // Nothing sticks out sideways.
        let wide = js(
            &c,
            "document.documentElement.scrollWidth - document.documentElement.clientWidth",
        )
        .await;
        assert_eq!(wide, 0, "the page scrolls sideways at {} px", LAPTOP.0);
        element_screenshot(&c, ".health-grid", &out.join("health-1400.png")).await;

        // 4. Sign in: the chooser opens, the button waits for a file.
        js(&c, "(window.scrollTo(0, 0), true)").await;
        c.find(Locator::Id("password"))
            .await
            .unwrap()
            .send_keys(PASSWORD)
            .await
            .unwrap();
        c.find(Locator::Id("signin-btn"))
            .await
            .unwrap()
            .click()
            .await
            .unwrap();
        let p = wait_for(
            &c,
            "the file chooser after sign-in",
            10,
            "window.__irtrack.update()",
            |v| v["file_enabled"] == true,
        )
        .await;
        assert_eq!(p["button_enabled"], false, "enabled without a file: {p}");
        assert!(
            p["why"].as_str().unwrap().contains("Choose a signed bundle"),
            "{p}"
        );

        // 5. The good bundle, with "reboot into it when installed" ticked: upload progress to
        // 100 %, installed into slot B, and the reboot asked for (`?reboot=1`).
        click(&c, "update-reboot").await;
        let p = upload_until(
            &c,
            &good,
            "the good bundle installed and the reboot asked for",
            60,
            |s| s.contains("rebooting into it") || s.starts_with("Refused"),
        )
        .await;
        assert_eq!(p["reboot_checked"], true, "{p}");
        println!(
            "good bundle: {}; upload progress shown {}; install states shown {}",
            p["message"], p["seen"]["upload"], p["seen"]["install"]
        );
        assert_eq!(
            p["message"], "Installed 1.2.0 into slot B; rebooting into it.",
            "{p}"
        );
        assert_eq!(p["message_class"], "msg ok", "{p}");
        let shown: Vec<u64> = p["seen"]["upload"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(Value::as_u64)
            .collect();
        assert_eq!(shown.last(), Some(&100), "upload progress shown: {shown:?}");
        assert!(
            shown.windows(2).all(|w| w[0] <= w[1]),
            "upload progress went back: {shown:?}"
        );
        assert_eq!(p["upload_bar"], 100, "{p}");
        assert_eq!(p["upload_label"], "upload 100%", "{p}");
        assert_eq!(p["install_bar"], 100, "{p}");
        assert!(
            p["seen"]["install"]
                .as_array()
                .unwrap()
                .iter()
                .any(|s| s == "installed"),
            "{p}"
        );
        // The slot rows follow with the next status reports.
        let p = wait_for(
            &c,
            "slot B carrying 1.2.0",
            10,
            "window.__irtrack.update()",
            |v| {
                v["rows"].as_array().is_some_and(|rows| {
                    rows.iter().any(|r| {
                        r[0] == "other slot" && r[1].as_str().is_some_and(|s| s.starts_with("B · 1.2.0"))
                    })
                })
            },
        )
        .await;
        assert_eq!(row(&p, "boots next"), "B", "{p}");
        assert!(row(&p, "running").starts_with("A · 1.1.0"), "{p}");
        assert!(
            row(&p, "last update").starts_with("installed 1.2.0 → slot B"),
            "{p}"
        );
        let sys = board_system(status);
        assert_eq!(sys["other"]["version"], "1.2.0", "{sys}");
        assert_eq!(sys["boot_next"], "B", "{sys}");
        // The reboot: asked for by the page, recorded by the simulated system (whose restart
        // stands for it), and shown in the panel.
        assert_eq!(sys["reboot"]["state"], "pending", "{sys}");
        assert_eq!(sys["reboot"]["slot"], "B", "{sys}");
        assert!(
            dir.join("system/reboot-requested").is_file(),
            "the simulated system recorded no reboot request"
        );
        let p = wait_for(&c, "the reboot row", 10, "window.__irtrack.update()", |v| {
            v["rows"].as_array().is_some_and(|rows| {
                rows.iter().any(|r| {
                    r[0] == "reboot"
                        && r[1]
                            .as_str()
                            .is_some_and(|s| s.starts_with("rebooting into slot B (1.2.0)"))
                })
            })
        })
        .await;
        println!("reboot row: {}", row(&p, "reboot"));
        // The slot holds the bundle's signed image: all but the signature and its 8-byte size.
        let sig_len = u64::from_be_bytes(bytes[bytes.len() - 8..].try_into().unwrap()) as usize;
        let image = &bytes[..bytes.len() - 8 - sig_len];
        let slot = std::fs::read(dir.join("system/slot-B.img")).unwrap();
        assert!(
            slot == image,
            "slot B ({} bytes) is not the bundle's image ({} bytes)",
            slot.len(),
            image.len()
        );
        element_screenshot(&c, ".system-panel", &out.join("system-installed.png")).await;
        // The refusals below are uploaded without a reboot.
        click(&c, "update-reboot").await;

        // 6. Signed by a key the board does not trust: refused, said in words; slot B unchanged.
        let p = upload_until(&c, &untrusted, "the untrusted bundle refused", 30, |s| {
            s.starts_with("Refused") || s.starts_with("Installed")
        })
        .await;
        println!("untrusted bundle: {}", p["message"]);
        let msg = p["message"].as_str().unwrap();
        assert!(
            msg.starts_with("Refused: wrong signature: the bundle is not signed by a key this board trusts"),
            "{p}"
        );
        assert_eq!(p["message_class"], "msg error", "{p}");
        assert_eq!(
            p["install_bar"],
            Value::Null,
            "install bar left up after a refusal: {p}"
        );
        let p = wait_for(
            &c,
            "the refusal in the last-update row",
            10,
            "window.__irtrack.update()",
            |v| {
                v["rows"].as_array().is_some_and(|rows| {
                    rows.iter().any(|r| {
                        r[0] == "last update" && r[1].as_str().is_some_and(|s| s.contains("wrong signature"))
                    })
                })
            },
        )
        .await;
        assert!(row(&p, "other slot").starts_with("B · 1.2.0"), "{p}");
        let sys = board_system(status);
        assert_eq!(sys["install"]["refusal"]["kind"], "signature", "{sys}");
        element_screenshot(&c, ".system-panel", &out.join("system-refused-signature.png")).await;

        // 7. Truncated: refused at once (422) with the reason; slot B unchanged.
        upload(&c, &truncated).await;
        let p = wait_for(
            &c,
            "the truncated bundle refused",
            30,
            "window.__irtrack.update()",
            |v| {
                v["message"]
                    .as_str()
                    .is_some_and(|s| s.starts_with("Refused") && s.contains("truncated"))
                    && v["uploading"] == false
            },
        )
        .await;
        println!("truncated bundle: {}", p["message"]);
        assert!(
            p["message"]
                .as_str()
                .unwrap()
                .starts_with("Refused: the bundle is truncated or corrupted"),
            "{p}"
        );
        assert!(
            p["message"]
                .as_str()
                .unwrap()
                .contains("copy or download it again"),
            "{p}"
        );
        assert_eq!(
            p["upload_bar"],
            Value::Null,
            "upload bar left up after a refusal: {p}"
        );
        let sys = board_system(status);
        assert_eq!(sys["install"]["refusal"]["kind"], "truncated", "{sys}");
        assert_eq!(sys["other"]["version"], "1.2.0", "{sys}");
        element_screenshot(&c, ".system-panel", &out.join("system-refused-truncated.png")).await;
        screenshot(&c, &out.join("setup-view-update.png")).await;

        let errors = js(&c, "window.__irtrackErrors").await;
        assert_eq!(errors, json!([]), "the page logged errors");
    })
    .await;
    let _ = c.close().await;
    result.expect("update browser test took longer than 180 s");
    println!("update browser test took {:.1} s", t0.elapsed().as_secs_f64());
}
