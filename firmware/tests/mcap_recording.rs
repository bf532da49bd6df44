//! irtrackd's `[outputs.mcap]` recording read back by PyPI's `mcap` + `mcap-ros2-support`
//! (`irtrack_testkit::mcap_check`, a separate process): every message decodes with its
//! ROS 2 schema, log times are monotonic, the counts equal what irtrackd recorded, and the
//! positions equal irtrackd's own NDJSON stream. Needs the `mcap` feature (host-tools enables
//! it in workspace builds).
#![cfg(feature = "mcap")]

mod common;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::*;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn irtrackd_records_tool_poses_into_mcap_readable_by_python() {
    let dir = TempDir::new("mcap-rec");
    let toml = "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n[outputs.mcap]\nenabled = true\npath = \"rec.mcap\"\n";
    let mut cfg = irtrack_firmware::config::Config::from_toml(toml, "mcap.toml").unwrap();
    let base = test_config(dir.path());
    cfg.service.state_dir = base.service.state_dir;
    cfg.listen = base.listen;
    cfg.source.sim = Some(
        toml::from_str(
            "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\nframes = 240\n",
        )
        .unwrap(),
    );
    let mut running = app::start(cfg, Overrides::default()).await.unwrap();
    let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    let mut by_frame = HashMap::new();
    while let Ok(r) = tokio::time::timeout(Duration::from_secs(1), client.next()).await {
        by_frame.insert(r.frame, r);
    }
    let _ = running.take_loop_result().unwrap().await;
    let stats = running.outputs.mcap.clone();
    let published = running.status.published.load(Ordering::Relaxed);
    running.shutdown().await;

    // The configured name is numbered: the first recording in an empty directory is -0001.
    let file = dir.path().join("rec-0001.mcap");
    // PyPI's reader in a separate process; it checks the ros2 profile and monotonic log times.
    let got = irtrack_testkit::mcap_check::read_mcap_with_python(&file).unwrap();
    let written = stats.frames_sent.load(Ordering::Relaxed);
    let (skips, drops) = (
        stats.slot_skips.load(Ordering::Relaxed),
        stats.send_drops.load(Ordering::Relaxed),
    );
    println!(
        "irtrackd MCAP: {written} records written of {published} published, {skips} skipped, {drops} dropped; counts {}",
        got["counts"]
    );
    assert_eq!(got["counts"]["/diagnostics"], written);
    assert_eq!(written + skips + drops, published);
    // Skips grow with the machine's load (a loaded 2-core run: 151 of 194 written).
    assert!(written >= 100, "{written}");
    // Every recorded record: status message; tracked ones: position, pose and tf, equal to
    // the NDJSON stream's record of the same frame (metres).
    let status = got["status"].as_array().unwrap();
    let frames: Vec<u64> = status
        .iter()
        .map(|s| s[2]["frame"].as_str().unwrap().parse().unwrap())
        .collect();
    let tracked: Vec<u64> = status
        .iter()
        .zip(&frames)
        .filter(|(s, _)| s[1] == "ok")
        .map(|(_, f)| *f)
        .collect();
    // The live ROS 2 output's topics and /tf frame names.
    assert_eq!(got["counts"]["/irtrack/probe4/pose"], tracked.len());
    assert_eq!(got["counts"]["/tf"], tracked.len());
    assert!(
        got["counts"].get("/irtrack/led/point").is_none(),
        "{}",
        got["counts"]
    );
    for (topic, qos) in got["qos"].as_object().unwrap() {
        assert!(
            qos.as_str().is_some_and(|q| q.contains("history:")),
            "{topic} has no offered_qos_profiles: {qos}"
        );
    }
    // The recorder's counts for the file: written and skipped equal /status's.
    let meta = got["metadata"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "irtrack_recorder")
        .unwrap_or_else(|| panic!("no irtrack_recorder metadata: {}", got["metadata"]));
    assert_eq!(meta["metadata"]["records_written"], written.to_string());
    assert_eq!(meta["metadata"]["records_skipped"], skips.to_string());
    // /diagnostics carries the running skip count too (readable without the summary).
    let last = status.last().unwrap();
    assert!(
        last[2]["records_skipped"]
            .as_str()
            .unwrap()
            .parse::<u64>()
            .unwrap()
            <= skips
    );
    let (mut compared, mut worst) = (0usize, 0.0f64);
    for (p, f) in got["poses"].as_array().unwrap().iter().zip(&tracked) {
        let Some(r) = by_frame.get(f) else { continue };
        assert_eq!(r.status, TrackStatus::Ok);
        let want = r.position_mm.unwrap();
        let q = r.orientation_wxyz.unwrap();
        for i in 0..3 {
            worst = worst.max((p[i].as_f64().unwrap() - want[i] / 1e3).abs());
        }
        for (i, c) in [q[1], q[2], q[3], q[0]].iter().enumerate() {
            worst = worst.max((p[3 + i].as_f64().unwrap() - c).abs());
        }
        compared += 1;
    }
    println!("MCAP poses vs NDJSON: {compared} compared, largest difference {worst:.1e}");
    assert!(compared >= 100, "{compared}");
    assert!(worst < 1e-12, "{worst}");
    assert_eq!(got["tf"][0][1], "irtrack_probe4");
}

/// A tmpfs of the test's own (a small filesystem that fills), unmounted on drop.
struct SmallFs {
    dir: PathBuf,
}

impl SmallFs {
    /// Mounts `size_kib` of tmpfs on a fresh directory; `Err` says why not (not root).
    fn mount(name: &str, size_kib: u64) -> Result<Self, String> {
        let dir = std::env::temp_dir().join(format!("irtrackd-{name}-{}", std::process::id()));
        let _ = Command::new("umount").arg(&dir).output();
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let out = Command::new("mount")
            .args([
                "-t",
                "tmpfs",
                "-o",
                &format!("size={size_kib}k,mode=0700"),
                "tmpfs",
            ])
            .arg(&dir)
            .output()
            .map_err(|e| format!("mount: {e}"))?;
        if !out.status.success() {
            let _ = std::fs::remove_dir(&dir);
            return Err(String::from_utf8_lossy(&out.stderr).trim().to_string());
        }
        Ok(Self { dir })
    }
}

impl Drop for SmallFs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.dir).output();
        let _ = std::fs::remove_dir(&self.dir);
    }
}

/// Polls `/status` until `pred` holds for `outputs.mcap` (or the whole document), at most
/// `secs`.
async fn wait_status(
    addr: std::net::SocketAddr,
    secs: u64,
    what: &str,
    pred: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let until = Instant::now() + Duration::from_secs(secs);
    loop {
        let st = status_json(addr).await;
        if pred(&st) {
            return st;
        }
        assert!(
            Instant::now() < until,
            "{what} not within {secs} s: {}",
            st["outputs"]["mcap"]
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn mcap_toml(dir: &Path) -> String {
    format!(
        "[outputs.mcap]\nenabled = true\npath = \"{}\"\n",
        dir.join("rec.mcap").display()
    )
}

const TOOL_SIM: &str = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\n";

/// issue 41.4: irtrackd records onto a filesystem that fills. The write failure is a fault in
/// plain words on `/status` and counted there and on `/metrics`; the file keeps every whole
/// chunk and reads with PyPI's `mcap` (no summary); once space is freed the recording goes on
/// in a new file; a restart starts a third file and leaves both earlier ones byte for byte.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_stops_the_file_readably_shows_a_fault_and_recording_resumes_in_a_new_file() {
    let fs = match SmallFs::mount("mcap-full", 1024) {
        Ok(fs) => fs,
        Err(why) => {
            eprintln!("SKIPPED: cannot mount a tmpfs of the test's own (root needed): {why}");
            return;
        }
    };
    // Leave about 200 kB free: irtrackd's ~80 kB/s of records fill it in a few seconds.
    let filler = fs.dir.join("filler");
    std::fs::write(&filler, vec![0u8; 800 * 1024]).unwrap();
    let state = TempDir::new("mcap-full-state");
    let running = start_with(&state, TOOL_SIM, &mcap_toml(&fs.dir)).await;
    let addr = running.addrs.status;
    let st = wait_status(addr, 30, "the recording failing", |st| {
        st["outputs"]["mcap"]["write_errors"].as_u64() >= Some(1)
    })
    .await;
    let mcap = &st["outputs"]["mcap"];
    println!("after the disk filled: {mcap}");
    assert!(mcap["file"].is_null(), "{mcap}");
    assert_eq!(mcap["files"], 1);
    let fault = st["fault_texts"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["code"] == "recording_failed")
        .unwrap_or_else(|| panic!("no recording_failed fault: {}", st["fault_texts"]))
        .clone();
    let text = fault["message"].as_str().unwrap();
    println!("fault: {text}");
    for words in [
        "rec-0001.mcap stopped",
        "No space left on device",
        "stay readable",
        "free space in",
    ] {
        assert!(text.contains(words), "{words:?} not in {text:?}");
    }
    // While nothing can be written, records are counted as dropped and sent stays.
    let sent_then = mcap["sent"].as_u64().unwrap();
    let dropped_then = mcap["dropped"].as_u64().unwrap();
    tokio::time::sleep(Duration::from_millis(700)).await;
    let st = status_json(addr).await;
    let mcap = &st["outputs"]["mcap"];
    if mcap["files"] == 1 {
        assert_eq!(mcap["sent"].as_u64().unwrap(), sent_then, "{mcap}");
        assert!(mcap["dropped"].as_u64().unwrap() > dropped_then + 30, "{mcap}");
    }
    let (code, metrics) = http_get(addr, "/metrics").await;
    assert_eq!(code, 200);
    assert!(
        metrics.contains("irtrackd_output_fault{output=\"mcap\"} 1"),
        "{metrics}"
    );
    let errors_line = metrics
        .lines()
        .find(|l| l.starts_with("irtrackd_output_write_errors_total{output=\"mcap\"}"))
        .unwrap_or_else(|| panic!("no write error counter in /metrics:\n{metrics}"));
    assert!(!errors_line.ends_with(" 0"), "{errors_line}");

    // Space comes back: the next try (at most a few seconds away) starts rec-0002.
    std::fs::remove_file(&filler).unwrap();
    let st = wait_status(addr, 20, "the recording resuming", |st| {
        st["outputs"]["mcap"]["files"] == 2 && st["outputs"]["mcap"]["fault"].is_null()
    })
    .await;
    let mcap = &st["outputs"]["mcap"];
    assert!(
        mcap["file"].as_str().unwrap().ends_with("rec-0002.mcap"),
        "{mcap}"
    );
    assert!(
        !st["fault_texts"]
            .as_array()
            .unwrap()
            .iter()
            .any(|f| f["code"] == "recording_failed"),
        "{}",
        st["fault_texts"]
    );
    // About a second into the new file, then shut down (rec-0002 gets its summary).
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let stats = running.outputs.mcap.clone();
    let published_before = running.status.published.load(Ordering::Relaxed);
    running.shutdown().await;
    let (sent, dropped, skipped) = (
        stats.frames_sent.load(Ordering::Relaxed),
        stats.send_drops.load(Ordering::Relaxed),
        stats.slot_skips.load(Ordering::Relaxed),
    );
    println!("sent {sent}, dropped {dropped}, skipped {skipped}, published {published_before}+");

    let first = fs.dir.join("rec-0001.mcap");
    let second = fs.dir.join("rec-0002.mcap");
    let one = irtrack_testkit::mcap_check::read_mcap_with_python(&first).unwrap();
    let two = irtrack_testkit::mcap_check::read_mcap_with_python(&second).unwrap();
    let n1 = one["counts"]["/diagnostics"].as_u64().unwrap_or(0);
    let n2 = two["counts"]["/diagnostics"].as_u64().unwrap_or(0);
    println!(
        "rec-0001: {n1} records, {} bytes, summary {}; rec-0002: {n2} records, summary {}",
        std::fs::metadata(&first).unwrap().len(),
        one["summary"],
        two["summary"]
    );
    // The stopped file: every whole chunk, no summary; its records in frame order.
    assert!(n1 >= 100, "{n1} records kept before the disk filled");
    assert!(one["summary"].is_null(), "{}", one["summary"]);
    let frames = |doc: &serde_json::Value| -> Vec<u64> {
        doc["status"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s[2]["frame"].as_str().unwrap().parse().unwrap())
            .collect()
    };
    let f1 = frames(&one);
    assert!(f1.windows(2).all(|w| w[0] < w[1]), "rec-0001 frames out of order");
    // The new file is finished: its summary counts every message.
    assert!(n2 >= 60, "{n2} records in the resumed file");
    let total2: u64 = two["counts"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(two["summary"]["messages"].as_u64(), Some(total2));
    assert!(frames(&two)[0] > *f1.last().unwrap());
    // `sent` counts exactly the records on file.
    assert_eq!(sent, n1 + n2);
    assert!(dropped > 0);

    // A restart records into rec-0003 and leaves the earlier files as they were.
    let before: Vec<Vec<u8>> = [&first, &second]
        .iter()
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    let again = start_with(&state, TOOL_SIM, &mcap_toml(&fs.dir)).await;
    wait_status(again.addrs.status, 20, "the restarted recording", |st| {
        st["outputs"]["mcap"]["sent"].as_u64() >= Some(60)
    })
    .await;
    again.shutdown().await;
    let after: Vec<Vec<u8>> = [&first, &second]
        .iter()
        .map(|p| std::fs::read(p).unwrap())
        .collect();
    assert!(before == after, "a restart changed an earlier recording");
    let three = irtrack_testkit::mcap_check::read_mcap_with_python(&fs.dir.join("rec-0003.mcap")).unwrap();
    assert!(
        three["counts"]["/diagnostics"].as_u64() >= Some(60),
        "{}",
        three["counts"]
    );
}

/// issue 42.2: with three tools and a loose LED, the recording carries every tool on its own
/// topic (`/irtrack/<tool>/pose`), every tool's `/tf` frame (`irtrack_<tool>`) and the loose
/// LEDs' cloud, as the live ROS 2 output; each tool's poses equal its own per-tool NDJSON
/// records of the same frame (read with PyPI `mcap` + `mcap-ros2-support`).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn irtrackd_records_every_tool_and_the_loose_leds_on_the_live_ros2_topics() {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
    let dir = TempDir::new("mcap-tools");
    let sim = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\nextra_tools = [\"tri3\", \"wing4\"]\nloose_leds = 1\nframes = 360\n";
    let mut running = start_with(&dir, sim, "[outputs.mcap]\nenabled = true\npath = \"rec.mcap\"\n").await;
    // Every tool's record: a `tools\n` client of the NDJSON stream.
    let mut s = tokio::net::TcpStream::connect(running.addrs.stream_ndjson)
        .await
        .unwrap();
    s.write_all(b"tools\n").await.unwrap();
    let mut lines = tokio::io::BufReader::new(s).lines();
    let mut per_tool: HashMap<(String, u64), serde_json::Value> = HashMap::new();
    let mut loose: HashMap<u64, Vec<u64>> = HashMap::new();
    while let Ok(Ok(Some(line))) = tokio::time::timeout(Duration::from_secs(1), lines.next_line()).await {
        let v: serde_json::Value = serde_json::from_str(&line).unwrap();
        let frame = v["frame"].as_u64().unwrap();
        if let Some(tool) = v["tool"].as_str() {
            per_tool.insert((tool.to_string(), frame), v);
        } else if let Some(id) = v["loose_id"].as_u64() {
            loose.entry(frame).or_default().push(id);
        }
    }
    let _ = running.take_loop_result().unwrap().await;
    running.shutdown().await;
    let got = irtrack_testkit::mcap_check::read_mcap_with_python(&dir.path().join("rec-0001.mcap")).unwrap();
    println!("counts {}", got["counts"]);
    for tool in ["probe4", "tri3", "wing4"] {
        let topic = format!("/irtrack/{tool}/pose");
        assert!(
            got["counts"][&topic].as_u64() >= Some(20),
            "{topic}: {}",
            got["counts"]
        );
    }
    // Poses equal each tool's own record of the frame with the same stamp (frame from
    // /diagnostics of the same stamp).
    let mut frame_of_stamp = HashMap::new();
    for s in got["status"].as_array().unwrap() {
        let frame: u64 = s[2]["frame"].as_str().unwrap().parse().unwrap();
        frame_of_stamp.insert((s[4].as_i64().unwrap(), s[5].as_i64().unwrap()), frame);
    }
    let (mut compared, mut worst) = (0usize, 0.0f64);
    for p in got["poses"].as_array().unwrap() {
        let tool = p[7]
            .as_str()
            .unwrap()
            .trim_start_matches("/irtrack/")
            .trim_end_matches("/pose");
        let frame = frame_of_stamp[&(p[9].as_i64().unwrap(), p[10].as_i64().unwrap())];
        let Some(r) = per_tool.get(&(tool.to_string(), frame)) else {
            continue;
        };
        let want = r["position_mm"].as_array().unwrap();
        for i in 0..3 {
            worst = worst.max((p[i].as_f64().unwrap() - want[i].as_f64().unwrap() / 1e3).abs());
        }
        compared += 1;
    }
    println!(
        "MCAP per-tool poses vs NDJSON tool records: {compared} compared, largest difference {worst:.1e}"
    );
    assert!(compared >= 100, "{compared}");
    assert!(worst < 1e-12, "{worst}");
    // /tf names every tool's frame as live ROS 2 does.
    let mut children: Vec<String> = got["tf_children"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|c| {
            c.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_str().unwrap().to_string())
        })
        .collect();
    children.sort();
    children.dedup();
    assert_eq!(children, ["irtrack_probe4", "irtrack_tri3", "irtrack_wing4"]);
    // The loose LED's cloud: ids equal the NDJSON loose records of the same frame.
    let clouds = got["clouds"].as_array().unwrap();
    assert!(!clouds.is_empty(), "no loose-LED clouds");
    let (mut matched, mut points) = (0usize, 0usize);
    for c in clouds {
        let frame = frame_of_stamp[&(c[0].as_i64().unwrap(), c[1].as_i64().unwrap())];
        let mut ids: Vec<u64> = c[2]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p[0].as_u64().unwrap())
            .collect();
        points += ids.len();
        if let Some(want) = loose.get(&frame) {
            let mut want = want.clone();
            want.sort();
            ids.sort();
            assert_eq!(ids, want, "frame {frame}");
            matched += 1;
        }
    }
    println!(
        "loose clouds: {} ({matched} with NDJSON loose records, {points} points)",
        clouds.len()
    );
    assert!(points > 0 && matched > 0);
}
