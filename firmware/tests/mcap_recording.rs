//! irtrackd's `[outputs.mcap]` recording read back by PyPI's `mcap` + `mcap-ros2-support`
//! (`irtrack_testkit::mcap_check`, a separate process): every message decodes with its
//! ROS 2 schema, log times are monotonic, the counts equal what irtrackd recorded, and the
//! positions equal irtrackd's own NDJSON stream. Needs the `mcap` feature (host-tools enables
//! it in workspace builds).
#![cfg(feature = "mcap")]

mod common;

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::time::Duration;

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

    let file = dir.path().join("rec.mcap");
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
    assert_eq!(got["counts"]["/irtrack/status"], written);
    assert_eq!(written + skips + drops, published);
    assert!(written >= 200, "{written}");
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
    assert_eq!(got["counts"]["/irtrack/position"], tracked.len());
    assert_eq!(got["counts"]["/irtrack/pose"], tracked.len());
    assert_eq!(got["counts"]["/tf"], tracked.len());
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
    assert_eq!(got["tf"][0][1], "irtrack_tool");
}
