//! A stalled consumer never slows the processing loop: for NatNet (irtrackd with unicast
//! clients that connect and never read, their receive buffers full) and the MCAP recorder (a
//! sink whose writes block, behind a stand-in loop publishing into the slot as the engine
//! does), the loop's sets/s while the consumer is stalled equal its rate before, and the output
//! counts what it could not deliver. (The DDS case is
//! `ros2_dds.rs::ros2_stalled_subscriber_does_not_slow_the_loop`, inside a network namespace.)

mod common;

use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::Duration;

use common::*;
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::status::SharedStatus;

const R: Ordering = Ordering::Relaxed;

/// The loop's sets per second over `secs`.
async fn sets_per_s(status: &SharedStatus, secs: f64) -> f64 {
    let (n0, t0) = (status.sets_processed.load(R), std::time::Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    (status.sets_processed.load(R) - n0) as f64 / t0.elapsed().as_secs_f64()
}

async fn start(dir: &TempDir, outputs_toml: &str) -> app::Running {
    let toml = format!("[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n{outputs_toml}");
    let mut cfg = irtrack_firmware::config::Config::from_toml(&toml, "stalled.toml").unwrap();
    let base = test_config(dir.path());
    cfg.service.state_dir = base.service.state_dir;
    cfg.listen = base.listen;
    cfg.source.sim = Some(
        toml::from_str(
            "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\nframes = 100000\n",
        )
        .unwrap(),
    );
    app::start(cfg, Overrides::default()).await.unwrap()
}

/// One machine-readable line for `cargo xtask bench --latency`'s output rows (µs).
fn latency_line(label: &str, stats: &irtrack_firmware::outputs::OutputStats) {
    let s = stats.latency.snapshot().summary();
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
    println!(
        "OUTPUT-LATENCY|{label}|{}|{}|{}|{}|{}",
        s.count,
        f(s.p50_us),
        f(s.p90_us),
        f(s.p99_us),
        f(s.max_us)
    );
}

fn report(name: &str, before: f64, during: f64, status: &Arc<irtrack_firmware::outputs::OutputStats>) {
    latency_line(name, status);
    println!(
        "{name} stalled: loop {before:.1} → {during:.1} sets/s; sent {}, dropped {}, skipped {}, clients {}, capture→sent p50 {:?} µs",
        status.frames_sent.load(R),
        status.send_drops.load(R),
        status.slot_skips.load(R),
        status.clients.load(R),
        status.latency.snapshot().summary().p50_us,
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn natnet_clients_that_never_read_do_not_slow_the_loop() {
    let dir = TempDir::new("stalled-natnet");
    let running = start(
        &dir,
        "[outputs.natnet]\nenabled = true\ncommand = \"127.0.0.1:0\"\ntransport = \"unicast\"\n",
    )
    .await;
    let natnet = running.addrs.natnet.unwrap();
    let before = sets_per_s(&running.status, 1.5).await;
    // Eight clients connect (NAT_CONNECT: id 0, no payload) and never read again: their
    // receive buffers fill and the kernel drops what arrives. Eight hosts (127.0.0.10..17, all
    // in the default client_networks): one address may hold only 4 slots.
    let clients: Vec<std::net::UdpSocket> = (0..8)
        .map(|i| {
            let s = std::net::UdpSocket::bind(format!("127.0.0.{}:0", 10 + i)).unwrap();
            s.send_to(&[0, 0, 0, 0], natnet).unwrap();
            s
        })
        .collect();
    tokio::time::sleep(Duration::from_millis(200)).await;
    let stats = running.outputs.natnet.clone();
    assert_eq!(stats.clients.load(R), 8);
    let sent0 = stats.frames_sent.load(R);
    let during = sets_per_s(&running.status, 3.0).await;
    report(
        "NatNet, unicast, 8 clients (never reading)",
        before,
        during,
        &stats,
    );
    // Every frame still went to all eight (the kernel takes it; the full buffers drop it).
    assert!(
        stats.frames_sent.load(R) - sent0 >= 8 * 300,
        "{}",
        stats.frames_sent.load(R)
    );
    assert!(
        during >= 0.95 * before,
        "loop slowed: {before:.1} → {during:.1} sets/s"
    );
    // The same counters on /status and /metrics.
    let st = status_json(running.addrs.status).await;
    let nat = &st["outputs"]["natnet"];
    assert_eq!(nat["enabled"], true, "{st}");
    assert_eq!(nat["clients"], 8);
    assert!(nat["sent"].as_u64().unwrap() >= 8 * 300, "{nat}");
    assert!(nat["capture_to_sent"]["p50_us"].as_f64().unwrap() > 0.0, "{nat}");
    assert_eq!(st["outputs"]["ros2"]["enabled"], false);
    let (code, metrics) = http_get(running.addrs.status, "/metrics").await;
    assert_eq!(code, 200);
    for line in [
        "irtrackd_output_clients{output=\"natnet\"} 8",
        "irtrackd_output_sent_total{output=\"natnet\"} ",
        "irtrackd_output_dropped_total{output=\"natnet\"} 0",
        "irtrackd_output_latency_seconds{output=\"natnet\",quantile=\"0.99\"} ",
    ] {
        assert!(metrics.contains(line), "{line} not in /metrics:\n{metrics}");
    }
    assert!(
        !metrics.contains("output=\"ros2\""),
        "disabled outputs are not exported"
    );
    drop(clients);
    running.shutdown().await;
}

/// An in-memory recording file whose writes block while `stall` is set: a disk that stops.
#[cfg(feature = "mcap")]
struct StallingSink {
    data: Vec<u8>,
    stall: Arc<std::sync::atomic::AtomicBool>,
}

#[cfg(feature = "mcap")]
impl irtrack_firmware::outputs::recording::RecordingFile for StallingSink {
    fn write_all_at_offset(&mut self, offset_bytes: u64, buf: &[u8]) -> std::io::Result<()> {
        while self.stall.load(R) {
            std::thread::sleep(Duration::from_millis(5));
        }
        let at = offset_bytes as usize;
        self.data.resize(self.data.len().max(at + buf.len()), 0);
        self.data[at..at + buf.len()].copy_from_slice(buf);
        Ok(())
    }
    fn truncate_to(&mut self, len_bytes: u64) -> std::io::Result<()> {
        self.data.truncate(len_bytes as usize);
        Ok(())
    }
}

/// irtrackd's recorder on a sink that blocks: a stand-in loop publishes 120 records/s into
/// the latest-value slot (as the engine does: `send_replace`, never waiting); its rate stays
/// 120/s while the writer thread is stuck, and the recorder drops and counts what its queue
/// cannot take.
#[cfg(feature = "mcap")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mcap_recording_into_a_blocked_sink_drops_and_counts_without_slowing_the_loop() {
    use irtrack_core::stream::{PositionRecord, TrackStatus};
    use irtrack_firmware::outputs::recording::Recorder;
    let stall = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sink = StallingSink {
        data: Vec::new(),
        stall: stall.clone(),
    };
    let rec = Recorder::with_sink("stalling sink".into(), Box::new(sink), 16).unwrap();
    let status = Arc::new(SharedStatus::new(2, "test".into(), "none".into()));
    let stats = Arc::new(irtrack_firmware::outputs::OutputStats::default());
    let (tx, rx) = tokio::sync::watch::channel(None);
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(rec.run(rx, status.clone(), stats.clone(), async {
        let _ = stop_rx.await;
    }));
    // The stand-in loop: paced at 120 Hz, publishing like the engine.
    let running = Arc::new(std::sync::atomic::AtomicBool::new(true));
    let loop_thread = {
        let (status, running) = (status.clone(), running.clone());
        std::thread::spawn(move || {
            let period = Duration::from_secs_f64(1.0 / 120.0);
            let mut next = std::time::Instant::now();
            let mut frame = 0u64;
            while running.load(R) {
                frame += 1;
                tx.send_replace(Some(PositionRecord {
                    frame,
                    capture_ts_ns: irtrack_firmware::clock::monotonic_ns(),
                    position_mm: Some([1.0, 2.0, 1000.0]),
                    orientation_wxyz: Some([1.0, 0.0, 0.0, 0.0]),
                    gap_mm: 0.1,
                    status: TrackStatus::Ok,
                    cameras_used: 2,
                    world_frame: false,
                    latency_us: 50,
                    params_crc: 0,
                }));
                status.published.fetch_add(1, R);
                status.sets_processed.fetch_add(1, R);
                next += period;
                if let Some(d) = next.checked_duration_since(std::time::Instant::now()) {
                    std::thread::sleep(d);
                }
            }
        })
    };
    let before = sets_per_s(&status, 1.5).await;
    // `sent` counts records on file: a chunk is written at least every second.
    let written0 = stats.frames_sent.load(R);
    assert!(written0 > 50, "{written0}");
    stall.store(true, R);
    let during = sets_per_s(&status, 3.0).await;
    report(
        "MCAP recording, queue 16 (sink blocked half way)",
        before,
        during,
        &stats,
    );
    let dropped = stats.send_drops.load(R);
    // The writer is stuck in a chunk's write: at most that chunk (a second of records) and
    // the queue go through; the rest is dropped and counted.
    assert!(
        stats.frames_sent.load(R) - written0 <= 121 + 17,
        "{}",
        stats.frames_sent.load(R)
    );
    assert!(dropped > 150, "{dropped}");
    assert!(
        during >= 0.95 * before,
        "loop slowed: {before:.1} → {during:.1} sets/s"
    );
    // The disk comes back: the queue drains, the file is finished at shutdown.
    stall.store(false, R);
    running.store(false, R);
    loop_thread.join().unwrap();
    let _ = stop_tx.send(());
    tokio::time::timeout(Duration::from_secs(10), task)
        .await
        .expect("recorder finishes")
        .unwrap();
}
