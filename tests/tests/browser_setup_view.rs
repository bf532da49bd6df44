//! The set-up page in a real browser: Debian's headless Chromium, driven over WebDriver
//! (chromedriver, started here on a free port) with `fantoccini`, against the real `irtrackd`
//! binary on the simulated cameras. Checks what an operator would: the page loads without
//! script errors, previews update, the overlay shows one kept blob per camera, a change without
//! sign-in is refused with a clear message, and after sign-in raising the threshold above the
//! LED's peak gives 0 blobs and a plain-words fault. Saves screenshots under
//! `target/browser-test/` (paths printed).
//!
//! Needs `chromium` and `chromium-driver` (installed by `cargo xtask setup`) and the irtrackd
//! binary: run `cargo build -p irtrack-firmware` first (same target dir and profile). The
//! WebDriver helpers are shared with `browser_update` (`common/chromium.rs`).

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::chromium::*;
use common::*;
use fantoccini::{Client, Locator};
use serde_json::{Value, json};

const PASSWORD: &str = "browser-test-password";

/// Pixels of each preview canvas in the threshold view's tint colour.
const TINTED_JS: &str = "Array.from(document.querySelectorAll('canvas.preview')).map((cv) => { \
    const d = cv.getContext('2d').getImageData(0, 0, cv.width, cv.height).data; let n = 0; \
    for (let i = 0; i < d.length; i += 4) if (d[i] === 255 && d[i + 1] === 61 && d[i + 2] === 242) n++; \
    return n; })";

fn cams(v: &Value) -> &Vec<Value> {
    v.as_array().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn setup_page_in_headless_chromium_against_irtrackd() {
    require_browser();
    let t0 = Instant::now();
    let dir = temp_dir("browser");
    let out = out_dir();

    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            r#"
[service]
params_from_simulator = true
operator_password_hash = "{}"
[source.sim]
fps = 30.0
[leds]
backend = "sim"
"#,
            password_hash(PASSWORD)
        ),
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");
    let (_driver, c, downloads) = open_browser(&dir).await;
    let result = tokio::time::timeout(Duration::from_secs(90), run(&c, status, &out, &downloads)).await;
    let _ = c.close().await;
    result.expect("browser test took longer than 90 s");
    println!("browser test took {:.1} s", t0.elapsed().as_secs_f64());
}

async fn run(c: &Client, status: SocketAddr, out: &Path, downloads: &Path) {
    let url = format!("http://{status}/");
    open_page(c, &url).await;

    // Previews of both cameras arrive and keep updating.
    let first = wait_for(
        c,
        "a preview of every camera",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).len() == 2 && cams(v).iter().all(|c| c["shown"].as_u64() >= Some(1)),
    )
    .await;
    wait_for(c, "previews updating", 20, "window.__irtrack.cameras()", |v| {
        cams(v)
            .iter()
            .zip(cams(&first))
            .all(|(now, then)| now["shown"].as_u64() >= then["shown"].as_u64().map(|n| n + 3))
    })
    .await;

    // One kept blob per camera (the simulated rig has one LED and no stray light).
    let tracked = wait_for(
        c,
        "one kept blob per camera",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).iter().all(|c| c["kept"] == 1),
    )
    .await;
    for cam in 0..2 {
        let kept = js(c, &format!("document.getElementById('cam-{cam}').dataset.kept")).await;
        assert_eq!(kept, "1", "camera {cam}'s card shows {kept} kept blobs");
    }
    let peak = cams(&tracked)
        .iter()
        .map(|c| c["peak_dn"].as_u64().unwrap())
        .max()
        .unwrap();
    println!("previews live, one kept blob per camera, LED peak {peak} DN");

    // The parameter panel says what is known of the active set's calibration (the simulator's
    // set carries no quality record).
    wait_for(
        c,
        "the calibration row of the parameter panel",
        10,
        "document.getElementById('params').textContent",
        |v| v.as_str().is_some_and(|t| t.contains("no quality record")),
    )
    .await;

    // Threshold view: pixels above the threshold are tinted in the browser, around the LED.
    c.find(Locator::Id("threshold-view"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let tinted = wait_for(c, "tinted pixels in both previews", 10, TINTED_JS, |v| {
        v.as_array()
            .is_some_and(|a| a.len() == 2 && a.iter().all(|n| n.as_u64() > Some(0)))
    })
    .await;
    println!("threshold view: tinted pixels per camera {tinted}");

    // The 3-D view runs on WebGL and receives positions.
    wait_for(
        c,
        "3-D view with positions",
        15,
        "window.__irtrack.scene()",
        |v| v["webgl"] == true && v["records"].as_u64() > Some(5),
    )
    .await;

    // Health shows live numbers: per-camera fps in the table.
    let fps = wait_for(
        c,
        "camera fps in the health table",
        10,
        "document.querySelector('#camera-health tbody tr td:nth-child(2)')?.textContent",
        |v| {
            v.as_str()
                .and_then(|s| s.parse::<f64>().ok())
                .is_some_and(|f| f > 10.0)
        },
    )
    .await;
    println!("health: camera 0 at {fps} fps");

    // "Save frame set" (no sign-in needed: it only reads) saves one full-resolution PGM per
    // camera through the browser's downloads.
    c.find(Locator::Id("capture-btn"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let msg = wait_for(
        c,
        "frame set saved",
        10,
        "window.__irtrack.captureMessage()",
        |v| {
            v.as_str()
                .is_some_and(|s| s.starts_with("Saved set") || s.starts_with("Frame set not saved"))
        },
    )
    .await;
    let msg = msg.as_str().unwrap().to_owned();
    assert!(msg.starts_with("Saved set") && msg.contains("640×480"), "{msg}");
    let deadline = Instant::now() + Duration::from_secs(10);
    let saved = loop {
        let mut pgms: Vec<PathBuf> = std::fs::read_dir(downloads)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|x| x == "pgm"))
            .collect();
        pgms.sort();
        if pgms.len() == 2 || Instant::now() > deadline {
            break pgms;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert_eq!(saved.len(), 2, "downloaded PGMs: {saved:?} ({msg})");
    for (i, p) in saved.iter().enumerate() {
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(name.starts_with(&format!("cam{i}_")), "{name}");
        let bytes = std::fs::read(p).unwrap();
        assert!(
            bytes.starts_with(b"P5\n640 480\n255\n"),
            "{name}: not an 8-bit 640x480 PGM"
        );
        assert_eq!(bytes.len(), "P5\n640 480\n255\n".len() + 640 * 480, "{name}");
    }
    // With the frames, timestamps.csv for a replay: a header and one row per camera.
    let csv = std::fs::read_to_string(downloads.join("timestamps.csv")).unwrap_or_default();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.first(), Some(&"frame,camera,timestamp_ns,dropped"), "{csv}");
    assert_eq!(rows.len(), 3, "{csv}");
    println!("capture: {msg}");
    screenshot(c, &out.join("setup-view.png")).await;

    // A change without sign-in is refused and the page says so; the board keeps its value.
    let (_, before) = http(status, "GET", "/api/tuning");
    let before: Value = serde_json::from_str(&before).unwrap();
    let threshold_before = before["threshold_dn"].as_u64().unwrap();
    type_number(c, "threshold_dn", "200").await;
    let msg = wait_for(
        c,
        "refusal message",
        10,
        "window.__irtrack.tuningMessage()",
        |v| v.as_str().is_some_and(|s| s.starts_with("Not applied")),
    )
    .await;
    assert!(
        msg.as_str().unwrap().contains("Sign in to change settings"),
        "the page should tell to sign in: {msg}"
    );
    let (_, after) = http(status, "GET", "/api/tuning");
    let after: Value = serde_json::from_str(&after).unwrap();
    assert_eq!(
        after["threshold_dn"].as_u64(),
        Some(threshold_before),
        "refused change applied"
    );
    wait_for(
        c,
        "threshold field back at the board's value",
        5,
        "document.getElementById('threshold_dn').value",
        |v| v.as_str() == Some(threshold_before.to_string().as_str()),
    )
    .await;
    println!("unsigned change refused: {msg}");

    // Sign in, then raise the threshold above the LED's peak through the page.
    let pw = c.find(Locator::Id("password")).await.unwrap();
    pw.send_keys(PASSWORD).await.unwrap();
    c.find(Locator::Id("signin-btn"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    wait_for(c, "signed in", 10, "window.__irtrack.session()", |v| {
        v["signed_in"] == true
    })
    .await;
    // The simulated LED saturates (255 DN) at the nominal exposure, and no threshold of an
    // 8-bit frame is above that: first halve each camera's exposure through the page (the
    // exposure control reaching the source), then put the threshold above the new peak.
    let mut peak = peak;
    if peak >= 250 {
        let tuning: Value = serde_json::from_str(&http(status, "GET", "/api/tuning").1).unwrap();
        for cam in tuning["cameras"].as_array().unwrap() {
            let i = cam["camera"].as_u64().unwrap();
            let half = cam["exposure"].as_i64().unwrap() / 2;
            type_number(c, &format!("cam{i}-exposure"), &half.to_string()).await;
            let end = Instant::now() + Duration::from_secs(10);
            loop {
                let t: Value = serde_json::from_str(&http(status, "GET", "/api/tuning").1).unwrap();
                if t["cameras"][i as usize]["exposure"].as_i64() == Some(half) {
                    break;
                }
                assert!(
                    Instant::now() < end,
                    "camera {i}: exposure {half} from the page not applied: {t}"
                );
                tokio::time::sleep(Duration::from_millis(150)).await;
            }
        }
        let dimmed = wait_for(
            c,
            "LED below saturation after halving the exposure",
            15,
            "window.__irtrack.cameras()",
            |v| {
                cams(v)
                    .iter()
                    .all(|c| c["kept"] == 1 && c["peak_dn"].as_u64().is_some_and(|p| p < 240))
            },
        )
        .await;
        peak = cams(&dimmed)
            .iter()
            .map(|c| c["peak_dn"].as_u64().unwrap())
            .max()
            .unwrap();
        println!("exposure halved through the page: LED peak now {peak} DN");
    }
    let above = (peak + 10).min(254);
    type_number(c, "threshold_dn", &above.to_string()).await;
    let applied = format!("Applied: threshold dn {above}.");
    wait_for(c, "change applied", 10, "window.__irtrack.tuningMessage()", |v| {
        v.as_str().is_some_and(|s| s.starts_with(&applied))
    })
    .await;
    let (_, now) = http(status, "GET", "/api/tuning");
    let now: Value = serde_json::from_str(&now).unwrap();
    assert_eq!(
        now["threshold_dn"].as_u64(),
        Some(above),
        "the board did not take the page's threshold"
    );

    let dark = wait_for(
        c,
        "0 blobs in every camera",
        20,
        "window.__irtrack.cameras()",
        |v| {
            cams(v)
                .iter()
                .all(|c| c["threshold_dn"].as_u64() == Some(above) && c["kept"] == 0 && c["rejected"] == 0)
        },
    )
    .await;
    // The board reports it in plain words (`fault_texts`, code no_led) and the banner shows it.
    let faults = wait_for(
        c,
        "a plain-words fault per camera on the page",
        10,
        "window.__irtrack.faults()",
        |v| {
            (0..2).all(|i| {
                v.as_array().unwrap().iter().any(|f| {
                    f.as_str().is_some_and(|s| {
                        let s = s.to_lowercase();
                        s.contains(&format!("camera {i}")) && s.contains("threshold")
                    })
                })
            })
        },
    )
    .await;
    // The page may show its own diagnosis before the next status report (every 0.5 s) carries
    // the board's: wait for the board's too.
    wait_for(
        c,
        "the board's fault for each camera in its status",
        10,
        "window.__irtrack.serverFaults()",
        |v| (0..2).all(|i| v.as_array().is_some_and(|a| a.iter().any(|f| f["camera"] == i))),
    )
    .await;
    let banner_visible = js(c, "!document.getElementById('faults').hidden").await;
    assert_eq!(banner_visible, true, "the fault banner is hidden");
    println!("threshold {above} > peak {peak}: {dark}; faults shown: {faults}");
    screenshot(c, &out.join("setup-view-no-marker.png")).await;

    // Back to the old threshold: the marker is found again.
    type_number(c, "threshold_dn", &threshold_before.to_string()).await;
    wait_for(
        c,
        "one kept blob per camera again",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).iter().all(|c| c["kept"] == 1),
    )
    .await;

    // No script error, failed module load or console.error in the whole session.
    let errors = js(c, "window.__irtrackErrors").await;
    assert_eq!(errors, json!([]), "the page logged errors");
}

/// Per camera, what each part of the page says: the health table row (board's status), the
/// camera card (preview of a set), and the fault banner.
const PARTS_JS: &str = "(() => { \
    const rows = Array.from(document.querySelectorAll('#camera-health tbody tr')).map((tr) => ({...tr.dataset})); \
    return { health: rows, cards: window.__irtrack.cameras(), server: window.__irtrack.serverFaults(), \
             banner: window.__irtrack.faults(), headers: Array.from(document.querySelectorAll('.cam .stats')).map((e) => e.textContent) }; })()";

/// Whether the health table, the camera cards and the fault list tell the same story for
/// every camera: the same advice code (or none), the same kept count, background within 2 DN
/// (they may show sets a moment apart) and the same peak; the banner carries the advice of
/// each camera that has one and no other camera-specific fault.
fn parts_agree(v: &Value, cameras: usize) -> Result<(), String> {
    let health = v["health"].as_array().ok_or("no health rows")?;
    let cards = v["cards"].as_array().ok_or("no cards")?;
    let server = v["server"].as_array().ok_or("no server faults")?;
    let banner: Vec<&str> = v["banner"]
        .as_array()
        .ok_or("no banner")?
        .iter()
        .filter_map(Value::as_str)
        .collect();
    for i in 0..cameras {
        let h = health.get(i).ok_or(format!("no health row {i}"))?;
        let c = cards.get(i).ok_or(format!("no card {i}"))?;
        if h["kept"].is_null() {
            return Err(format!("camera {i}: the health table has no analysis"));
        }
        let num = |x: &Value| -> Option<i64> { x.as_str().and_then(|s| s.parse().ok()).or(x.as_i64()) };
        let card_code = c["advice"]["code"].as_str().unwrap_or("");
        let health_code = h["advice"].as_str().unwrap_or("");
        if card_code != health_code {
            return Err(format!(
                "camera {i}: card advice {card_code:?}, health table {health_code:?}"
            ));
        }
        if num(&h["kept"]) != c["kept"].as_i64() {
            return Err(format!(
                "camera {i}: kept {} in the table, {} on the card",
                h["kept"], c["kept"]
            ));
        }
        // (Region counts are not compared: the two may show sets a moment apart, and regions
        // near the threshold come and go with the noise.)
        if h["regions"].is_null() || c["regions"].is_null() {
            return Err(format!("camera {i}: no region count in the table or on the card"));
        }
        let (hb, cb) = (
            num(&h["background"]).unwrap_or(-99),
            c["background_dn"].as_i64().unwrap_or(99),
        );
        if (hb - cb).abs() > 2 {
            return Err(format!(
                "camera {i}: background {hb} DN in the table, {cb} DN on the card"
            ));
        }
        if num(&h["peak"]) != c["peak_dn"].as_i64() {
            return Err(format!(
                "camera {i}: peak {} in the table, {} on the card",
                h["peak"], c["peak_dn"]
            ));
        }
        let theirs: Vec<&Value> = server.iter().filter(|f| f["camera"] == i).collect();
        match (card_code, theirs.as_slice()) {
            ("", []) => {}
            ("", f) => return Err(format!("camera {i}: no advice on the card but faults {f:?}")),
            (_, [f]) => {
                let text = f["text"].as_str().unwrap_or("");
                if !banner.contains(&text) {
                    return Err(format!("camera {i}: fault {text:?} not in the banner {banner:?}"));
                }
            }
            (code, f) => return Err(format!("camera {i}: advice {code} but faults {f:?}")),
        }
    }
    Ok(())
}

/// Polls until the parts agree on three reads in a row; fails with the last disagreement.
async fn wait_parts_agree(c: &Client, what: &str, secs: u64) -> Value {
    let end = Instant::now() + Duration::from_secs(secs);
    let mut streak = 0;
    loop {
        let v = js(c, PARTS_JS).await;
        match parts_agree(&v, 2) {
            Ok(()) => {
                streak += 1;
                if streak >= 3 {
                    return v;
                }
            }
            Err(e) => {
                streak = 0;
                assert!(
                    Instant::now() < end,
                    "{what}: the page's parts disagree: {e}\n{v:#}"
                );
            }
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
}

/// Realistic frames (`[source.sim.backdrop]`: background 41 DN with noise and vignetting, a
/// floor with reflections, a lamp cut by the top edge) at the default threshold of 30 DN, with
/// and without a parameter set: the page says in words that the background is above the
/// threshold (never an area problem), the health table, camera headers and fault list agree,
/// the operator's "Suggest threshold" shows a value and its reasoning before applying, and
/// applying it leaves exactly the marker kept in every camera with the lamp and reflections
/// marked rejected. Saves docs/setup-view-realistic.png.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn realistic_frames_advice_and_suggested_threshold_in_headless_chromium() {
    require_browser();
    let t0 = Instant::now();
    let dir = temp_dir("browser-realistic");
    let out = out_dir();
    let hash = password_hash(PASSWORD);
    let config = |params: bool| {
        format!(
            r#"
[service]
params_from_simulator = {params}
operator_password_hash = "{hash}"
[source.sim]
fps = 30.0
[source.sim.backdrop]
[leds]
backend = "sim"
"#
        )
    };
    let (_driver, c, _) = open_browser(&dir).await;
    let result = tokio::time::timeout(Duration::from_secs(150), async {
        for params in [false, true] {
            let label = if params { "with-params" } else { "no-params" };
            let cfg_path = dir.join(format!("irtrackd-{label}.toml"));
            std::fs::write(&cfg_path, config(params)).unwrap();
            let (_irtrackd, ready) = start_irtrackd(&cfg_path, &dir.join(format!("state-{label}")));
            let status = addr_field(&ready, "status=");
            realistic_run(&c, status, params, &out).await;
        }
    })
    .await;
    let _ = c.close().await;
    result.expect("realistic-frames browser test took longer than 150 s");
    println!(
        "realistic-frames browser test took {:.1} s",
        t0.elapsed().as_secs_f64()
    );
}

async fn realistic_run(c: &Client, status: SocketAddr, params: bool, out: &Path) {
    let label = if params {
        "with a parameter set"
    } else {
        "without a parameter set"
    };
    open_page(c, &format!("http://{status}/")).await;
    wait_for(
        c,
        "a preview of every camera",
        20,
        "window.__irtrack.cameras()",
        |v| cams(v).len() == 2 && cams(v).iter().all(|c| c["shown"].as_u64() >= Some(1)),
    )
    .await;

    // 1. The default threshold is below the background: said in plain words with the measured
    //    background and a value, per camera, never as an area problem.
    let faults = wait_for(
        c,
        "background advice for every camera",
        20,
        "window.__irtrack.faults()",
        |v| {
            (0..2).all(|i| {
                v.as_array().unwrap().iter().any(|f| {
                    f.as_str().is_some_and(|s| {
                        s.contains(&format!("amera {i}: background "))
                            && s.contains("DN is above the threshold 30 DN — raise it to about ")
                    })
                })
            })
        },
    )
    .await;
    for f in faults.as_array().unwrap() {
        let f = f.as_str().unwrap();
        assert!(
            !f.contains("area limits"),
            "area advice for a bright background ({label}): {f}"
        );
    }
    println!("{label}: advice shown: {faults}");
    let agree = wait_parts_agree(c, "bright background", 15).await;
    println!("{label}: health, headers and faults agree: {}", agree["health"]);
    for row in agree["health"].as_array().unwrap() {
        assert_eq!(row["advice"], "background_above_threshold", "{row}");
        assert_ne!(row["regions"], "0", "health table shows no regions: {row}");
    }

    // 2. Without sign-in the suggestion is refused; signed in, it is shown before applying.
    let session = js(c, "window.__irtrack.session()").await;
    if session["signed_in"] != true {
        let disabled = js(c, "document.getElementById('suggest-btn').disabled").await;
        assert_eq!(disabled, true, "Suggest threshold is enabled without sign-in");
        let (code, _) = http(status, "POST", "/api/tuning/suggest");
        assert_eq!(
            code, 401,
            "the suggestion endpoint answered {code} without sign-in"
        );
        let pw = c.find(Locator::Id("password")).await.unwrap();
        pw.send_keys(PASSWORD).await.unwrap();
        c.find(Locator::Id("signin-btn"))
            .await
            .unwrap()
            .click()
            .await
            .unwrap();
        wait_for(c, "signed in", 10, "window.__irtrack.session()", |v| {
            v["signed_in"] == true
        })
        .await;
    }
    // A first-start suggestion may already be open; ask for a fresh one either way.
    js(c, "(document.getElementById('suggestion').hidden = true, true)").await;
    c.find(Locator::Id("suggest-btn"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let sug = wait_for(
        c,
        "a suggestion shown",
        30,
        "window.__irtrack.suggestion()",
        |v| {
            v["text"]
                .as_str()
                .is_some_and(|s| s.starts_with("Suggested: threshold"))
        },
    )
    .await;
    let suggested = sug["threshold_dn"].as_u64().unwrap();
    let why: Vec<&str> = sug["why"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_str)
        .collect();
    println!("{label}: {}\n  {}", sug["text"], why.join("\n  "));
    assert_eq!(sug["keeps_only_marker"], true, "{sug}");
    assert!(why.iter().any(|w| w.contains("background: median")), "{why:?}");
    assert!(
        why.iter().any(|w| w.contains("marker: the brightest round spot")),
        "{why:?}"
    );
    assert!(
        why.iter().filter(|w| w.starts_with("prediction: camera")).count() == 2,
        "{why:?}"
    );
    // Nothing applied yet.
    let t: Value = serde_json::from_str(&http(status, "GET", "/api/tuning").1).unwrap();
    assert_eq!(t["threshold_dn"], 30, "the suggestion was applied before Apply");

    // 3. Apply: exactly the marker kept in every camera, the lamp and reflections rejected.
    c.find(Locator::Id("suggest-apply"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    let applied = format!("Applied: threshold dn {suggested}.");
    wait_for(
        c,
        "suggestion applied",
        10,
        "window.__irtrack.tuningMessage()",
        |v| v.as_str().is_some_and(|s| s.starts_with(&applied)),
    )
    .await;
    let marked = wait_for(
        c,
        "exactly the marker kept in every camera",
        20,
        "window.__irtrack.cameras()",
        |v| {
            cams(v).iter().all(|c| {
                c["threshold_dn"].as_u64() == Some(suggested) && c["kept"] == 1 && c["advice"].is_null()
            })
        },
    )
    .await;
    let reasons: Vec<String> = cams(&marked)
        .iter()
        .flat_map(|c| {
            c["reasons"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_str().unwrap_or("").to_string())
        })
        .collect();
    assert!(
        reasons.iter().any(|r| r == "edge"),
        "no lamp marked as cut by the edge: {reasons:?}"
    );
    assert!(
        reasons.iter().any(|r| r == "roundness"),
        "no reflection marked for roundness: {reasons:?}"
    );
    let agree = wait_parts_agree(c, "suggested threshold", 15).await;
    for row in agree["health"].as_array().unwrap() {
        assert_eq!(row["kept"], "1", "{row}");
    }
    let banner = js(c, "window.__irtrack.faults()").await;
    for f in banner.as_array().unwrap() {
        let f = f.as_str().unwrap().to_lowercase();
        assert!(
            !(f.contains("camera 0") || f.contains("camera 1")),
            "camera fault left after the suggestion: {f}"
        );
    }
    println!("{label}: at {suggested} DN: {marked}; banner {banner}");
    if params {
        // The marker is tracked with the suggested threshold.
        wait_for(
            c,
            "positions in the 3-D view",
            15,
            "window.__irtrack.scene()",
            |v| v["records"].as_u64() > Some(5),
        )
        .await;
    }
    let name = if params {
        "setup-view-realistic-params.png"
    } else {
        "setup-view-realistic.png"
    };
    screenshot(c, &out.join(name)).await;
    if !params {
        // The picture in the docs: realistic frames after the suggestion (looked at by a person).
        let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/setup-view-realistic.png");
        std::fs::copy(out.join(name), &docs).unwrap();
        println!("screenshot copied to {}", docs.display());
    }
    let errors = js(c, "window.__irtrackErrors").await;
    assert_eq!(errors, json!([]), "the page logged errors ({label})");
}

/// The latency panel with a robot link sending targets (issue 30): the page shows the robot
/// link's protocol wait and the sample's age beside the loop's stages, and one line splitting
/// capture → robot packet into driver + ours + protocol wait — the split `cargo xtask bench
/// --latency` prints. irtrackd streams to a simulated EGM controller (4 ms cycle) that this
/// test runs over UDP on 127.0.0.1.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn latency_panel_splits_capture_to_robot_packet_in_headless_chromium() {
    use irtrack_robot::ctrl_sim::{CtrlConfig, CtrlKind, SimController};
    require_browser();
    let dir = temp_dir("browser-latency");
    let out = out_dir();
    let egm_port = std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        format!(
            r#"
[service]
params_from_simulator = true
control = true
{}
[source.sim]
fps = 60.0
[leds]
backend = "none"
[robot]
kind = "egm"
address = "{egm_port}"
[robot.safety]
workspace_min_mm = [-4000.0, -4000.0, -4000.0]
workspace_max_mm = [4000.0, 4000.0, 4000.0]
max_step_mm = 250.0
max_speed_mm_s = 1000.0
max_gap_mm = 2.0
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "flag"
"#,
            operator_hash_line()
        ),
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");
    // The controller starts where the marker is (one stream record), so the enable picks it up.
    let stream = std::net::TcpStream::connect(addr_field(&ready, "stream=")).unwrap();
    let mut line = String::new();
    let mut reader = std::io::BufReader::new(stream);
    let home = loop {
        line.clear();
        std::io::BufRead::read_line(&mut reader, &mut line).unwrap();
        let v: Value = serde_json::from_str(&line).unwrap();
        if let Some(p) = v["position_mm"].as_array() {
            break [0, 1, 2].map(|i| p[i].as_f64().unwrap());
        }
    };
    drop(reader);
    let ctrl = SimController::spawn(
        CtrlConfig {
            home_mm: home,
            max_missed: 0,
            ..CtrlConfig::new(CtrlKind::Egm, egm_port)
        },
        None,
    )
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let (code, body) = http_operator(status, "POST", "/robot");
        assert_eq!(code, 200, "{body}");
        if body.contains("\"state\":\"holding\"") {
            break;
        }
        assert!(Instant::now() < deadline, "the EGM link never came up: {body}");
        std::thread::sleep(Duration::from_millis(100));
    }
    for path in ["/robot/enable", "/robot/deadman?pressed=1"] {
        let (code, body) = http_operator(status, "POST", path);
        assert_eq!(code, 200, "{path}: {body}");
    }

    let (_driver, c, _) = open_browser(&dir).await;
    let result = tokio::time::timeout(Duration::from_secs(60), async {
        open_page(&c, &format!("http://{status}/")).await;
        let rows = wait_for(
            &c,
            "the robot link's rows in the latency table",
            20,
            "Array.from(document.querySelectorAll('#latency tbody tr.link-row')).map((tr) => \
             Array.from(tr.cells).map((td) => td.textContent))",
            |v| v.as_array().is_some_and(|a| a.len() == 2),
        )
        .await;
        println!("latency table, robot link rows: {rows}");
        let num = |s: &Value| -> f64 {
            s.as_str()
                .unwrap()
                .replace(',', "")
                .parse()
                .unwrap_or_else(|_| panic!("not a number: {s}"))
        };
        let (wait, age) = (&rows[0], &rows[1]);
        assert!(wait[0].as_str().unwrap().contains("protocol wait"), "{wait}");
        assert!(age[0].as_str().unwrap().contains("sample age"), "{age}");
        let (wait_p50, age_p50) = (num(&wait[1]), num(&age[1]));
        // EGM answers every 4 ms cycle with the newest sample, which is new every 1/60 s: a
        // target waits at most a frame period plus a cycle after its sample was published.
        assert!(
            wait_p50 > 0.0 && wait_p50 <= 1e6 / 60.0 + 4_000.0,
            "protocol wait p50 {wait_p50} µs"
        );
        assert!(age_p50 >= wait_p50, "age {age_p50} µs < wait {wait_p50} µs");
        let split = js(&c, "document.getElementById('latency-split').textContent").await;
        println!("latency split: {split}");
        let split = split.as_str().unwrap();
        for part in ["driver", "ours", "protocol wait", "age when it left"] {
            assert!(split.contains(part), "the split line lacks {part:?}: {split}");
        }
        js(
            &c,
            "document.getElementById('latency').scrollIntoView({block: 'center'})",
        )
        .await;
        screenshot(&c, &out.join("latency-panel.png")).await;
    })
    .await;
    let _ = c.close().await;
    let record = ctrl.stop();
    result.expect("latency panel test took longer than 60 s");
    assert!(record.answered > 100, "{record:?}");
}

/// Several tools at once (issue 29): irtrackd's simulator renders `probe4`, `tri3` and
/// `wing4`; the page's 3-D view shows each tool's axes and name, and each camera's blob list
/// says which blobs went to which tool. Screenshot `setup-view-tools.png`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn several_tools_in_the_3d_view_and_the_blob_lists_in_headless_chromium() {
    require_browser();
    let dir = temp_dir("browser-tools");
    let out = out_dir();
    let config = dir.join("irtrackd.toml");
    std::fs::write(
        &config,
        r#"
[service]
params_from_simulator = true
[source.sim]
fps = 30.0
distance_mm = 1000.0
radius_mm = 60.0
tool = "probe4"
extra_tools = ["tri3", "wing4"]
loose_leds = 1
tool_rotation_deg = 10.0
[leds]
backend = "sim"
"#,
    )
    .unwrap();
    let (_irtrackd, ready) = start_irtrackd(&config, &dir.join("state"));
    let status = addr_field(&ready, "status=");
    let (_driver, c, _) = open_browser(&dir).await;
    let run = async {
        open_page(&c, &format!("http://{status}/")).await;
        // Every tool is shown (tracked) in 3-D, with its name.
        let tools = wait_for(
            &c,
            "three tracked tools in 3-D",
            30,
            "window.__irtrack.scene().tools",
            |v| {
                v.as_array()
                    .is_some_and(|a| a.len() == 3 && a.iter().filter(|t| t["tracked"] == true).count() >= 2)
            },
        )
        .await;
        let names: Vec<&str> = tools
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t["name"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["probe4", "tri3", "wing4"]);
        // Per camera, the blobs carry the tool they went to, by name.
        let cams = wait_for(
            &c,
            "blobs assigned to tools in every camera",
            30,
            "window.__irtrack.cameras()",
            |v| {
                v.as_array().is_some_and(|a| {
                    a.len() == 2
                        && a.iter().all(|cam| {
                            let o = cam["owners"].as_array().cloned().unwrap_or_default();
                            o.iter().filter(|n| n == &"probe4").count() >= 3 && o.iter().any(|n| n == "wing4")
                        })
                })
            },
        )
        .await;
        println!(
            "3-D tools {tools}; blob owners per camera: {}",
            cams.as_array()
                .unwrap()
                .iter()
                .map(|c| c["owners"].to_string())
                .collect::<Vec<_>>()
                .join(" | ")
        );
        // The blob list's text names the tool too.
        let items = js(
            &c,
            "Array.from(document.querySelectorAll('.cam li')).map((li) => li.textContent)",
        )
        .await;
        assert!(
            items
                .as_array()
                .unwrap()
                .iter()
                .any(|t| t.as_str().unwrap().ends_with("· probe4")),
            "{items}"
        );
        let errors = js(&c, "window.__irtrackErrors || []").await;
        assert_eq!(errors, json!([]), "page errors");
        // Eleven LEDs per camera are what the tools need, not an overload: the detector's
        // limit follows the tools.
        let faults = js(&c, "window.__irtrack.faults()").await;
        assert!(!faults.to_string().contains("overloaded"), "{faults}");
        assert!(!faults.to_string().contains("one marker is expected"), "{faults}");
        // The loose single LED: a marker in 3-D labelled with its stable id (the stream's
        // loose_id), near the simulator's loose LED path (within the scene, 0.5-2 m away).
        let loose = wait_for(
            &c,
            "the loose LED drawn in 3-D with its id",
            30,
            "window.__irtrack.scene().loose",
            |v| v.as_array().is_some_and(|a| a.iter().any(|l| l["shown"] == true)),
        )
        .await;
        let shown = loose
            .as_array()
            .unwrap()
            .iter()
            .find(|l| l["shown"] == true)
            .unwrap();
        assert_eq!(
            shown["label"].as_str().unwrap(),
            format!("loose {}", shown["id"]),
            "{loose}"
        );
        let z = shown["position_mm"][2].as_f64().unwrap();
        assert!((500.0..2000.0).contains(&z), "loose LED at z = {z} mm");
        // Readable names: no two labels cover each other, in 3-D (tool names and loose ids)
        // and in each camera's overlay (one name per tool, blob reasons).
        let overlap = |boxes: &serde_json::Value, what: &str| {
            let b = boxes.as_array().unwrap();
            for (i, p) in b.iter().enumerate() {
                for q in &b[i + 1..] {
                    let f = |v: &serde_json::Value, k: &str| v[k].as_f64().unwrap();
                    let apart = f(p, "x") + f(p, "w") <= f(q, "x")
                        || f(q, "x") + f(q, "w") <= f(p, "x")
                        || f(p, "y") + f(p, "h") <= f(q, "y")
                        || f(q, "y") + f(q, "h") <= f(p, "y");
                    assert!(apart, "{what}: labels {p} and {q} overlap");
                }
            }
            b.len()
        };
        let labels_3d = wait_for(
            &c,
            "two or more name labels in 3-D",
            30,
            "window.__irtrack.scene().labels",
            |v| v.as_array().is_some_and(|a| a.len() >= 2),
        )
        .await;
        overlap(&labels_3d, "3-D view");
        let cams = js(&c, "window.__irtrack.cameras()").await;
        for cam in cams.as_array().unwrap() {
            let n = overlap(&cam["labels"], "camera overlay");
            let texts: Vec<&str> = cam["labels"]
                .as_array()
                .unwrap()
                .iter()
                .filter_map(|l| l["text"].as_str())
                .collect();
            // One name label per tool, not one per LED.
            assert!(texts.iter().filter(|t| **t == "probe4").count() <= 1, "{texts:?}");
            println!("camera {}: {n} labels {texts:?}", cam["camera"]);
        }
        println!("3-D labels: {labels_3d}; loose LEDs in 3-D: {loose}");
        screenshot(&c, &out.join("setup-view-tools.png")).await;
        // The 3-D view, fitted to what it shows.
        js(&c, "(document.querySelector('.scene-panel').scrollIntoView(), document.getElementById('scene-reset').click(), true)").await;
        tokio::time::sleep(Duration::from_millis(1000)).await;
        let labels_3d = js(&c, "window.__irtrack.scene().labels").await;
        overlap(&labels_3d, "3-D view after reset");
        screenshot(&c, &out.join("setup-view-tools-3d.png")).await;
    };
    let result = tokio::time::timeout(Duration::from_secs(90), run).await;
    let _ = c.close().await;
    result.expect("browser test took longer than 90 s");
}
