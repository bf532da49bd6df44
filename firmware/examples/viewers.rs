//! Does watching disturb tracking? Loop latency with 0 and with 3 live viewers, side by side.
//!
//! Runs irtrackd's processing loop (simulated 90° rig, VGA, paced at `--fps`, default 100) with
//! its status listener on 127.0.0.1, measures per set the loop's processing time and the
//! capture → publish latency (`latency_us` of the records) for `--seconds` (default 10) with no
//! viewer, then the same with 3 WebSocket viewers asking for 30 fps full-width previews, 64 px
//! zooms and every set's blob lists, and prints percentiles (hdrhistogram) and the ratios.
//!
//! ```sh
//! cargo run --release -p irtrack-firmware --example viewers [-- --seconds 10 --fps 100]
//! ```

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use hdrhistogram::Histogram;
use irtrack_core::pipeline::TrackerConfig;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use irtrack_firmware::net::status::StatusService;
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_firmware::tuning::TuningHandle;
use irtrack_firmware::viewer::ViewerTap;

/// Per-phase histograms, µs.
struct Phase {
    process_us: Histogram<u64>,
    latency_us: Histogram<u64>,
}

impl Phase {
    fn new() -> anyhow::Result<Self> {
        Ok(Self {
            process_us: Histogram::new_with_bounds(1, 10_000_000, 3)?,
            latency_us: Histogram::new_with_bounds(1, 10_000_000, 3)?,
        })
    }
}

fn arg(name: &str, default: f64) -> f64 {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() -> anyhow::Result<()> {
    let seconds = arg("--seconds", 10.0);
    let fps = arg("--fps", 100.0);
    let cfg = SimSourceConfig {
        fps,
        ..SimSourceConfig::default()
    };
    let source = SimSource::new(&cfg)?;
    let handle = Arc::new(ParamsHandle::new());
    handle.install(ActiveParams {
        rig: source.scenario().rig().clone(),
        crc: 1,
    });
    let status = Arc::new(SharedStatus::new(
        source.camera_count(),
        source.describe(),
        "none".into(),
    ));
    let tracking = TrackerConfig::default();
    let tap = Arc::new(ViewerTap::new());
    let tuning = Arc::new(TuningHandle::new(tracking, &[], &std::env::temp_dir(), false));
    let (tx, rx) = tokio::sync::watch::channel(None);
    let mut engine = Engine::new(
        Box::new(source),
        tracking,
        handle.clone(),
        tx,
        status.clone(),
        Duration::from_secs_f64(1.0 / fps),
    )
    .with_viewer_tap(tap.clone())
    .with_tuning(tuning.clone());

    // Phase switch: the loop thread records into phase 0 or 1.
    let phase = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let (phase2, stop2, status2) = (phase.clone(), stop.clone(), status.clone());
    let loop_thread = std::thread::spawn(move || -> anyhow::Result<[Phase; 2]> {
        let mut phases = [Phase::new()?, Phase::new()?];
        let (mut last_count, mut last_sum_us) = (0u64, 0u64);
        while !stop2.load(Ordering::Relaxed) {
            let outcome = engine.step()?;
            let p = phase2.load(Ordering::Relaxed) as usize;
            if let (StepOutcome::Published(rec), Some(h)) = (outcome, phases.get_mut(p)) {
                h.latency_us.record(u64::from(rec.latency_us).max(1))?;
            }
            // The loop's own processing time of this set (detect → publish, viewer copy
            // included): the step of its `process` stage histogram's running sum.
            let snap = status2.stages.process.snapshot();
            let count = snap.count();
            if let Some(h) = phases.get_mut(p)
                && count == last_count + 1
            {
                h.process_us.record((snap.sum_us - last_sum_us).max(1))?;
            }
            (last_count, last_sum_us) = (count, snap.sum_us);
        }
        Ok(phases)
    });

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    rt.block_on(async {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let service = StatusService::new(status.clone()).with_live(tap.clone(), tuning, rx, handle);
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(service.serve(listener, async move {
            let _ = stop_rx.await;
        }));
        tokio::time::sleep(Duration::from_secs(1)).await; // warm up
        phase.store(0, Ordering::Relaxed);
        tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
        let viewers: Vec<_> = (0..3).map(|_| tokio::spawn(viewer(addr))).collect();
        tokio::time::sleep(Duration::from_millis(500)).await;
        phase.store(1, Ordering::Relaxed);
        let copies0 = tap.copies();
        tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
        phase.store(2, Ordering::Relaxed);
        let copies = tap.copies() - copies0;
        let mut received = 0u64;
        for v in viewers {
            v.abort();
            if let Ok(n) = v.await {
                received += n.unwrap_or(0);
            }
        }
        let _ = stop_tx.send(());
        let _ = server.await;
        println!(
            "viewer phase: the loop made {copies} copies for the viewers; {} busy skips",
            tap.busy_skips()
        );
        let _ = received;
        anyhow::Ok(())
    })?;
    stop.store(true, Ordering::Relaxed);
    let phases = loop_thread
        .join()
        .map_err(|_| anyhow::anyhow!("loop thread panicked"))??;

    println!(
        "processing loop, simulated 2 × 640x480 at {fps} fps, {seconds} s per phase (cargo run --release -p irtrack-firmware --example viewers)"
    );
    println!(
        "{:<34} {:>8} {:>8} {:>8} {:>8} {:>8}",
        "", "sets", "p50 µs", "p90 µs", "p99 µs", "max µs"
    );
    let row = |name: &str, h: &Histogram<u64>| {
        println!(
            "{:<34} {:>8} {:>8} {:>8} {:>8} {:>8}",
            name,
            h.len(),
            h.value_at_quantile(0.5),
            h.value_at_quantile(0.9),
            h.value_at_quantile(0.99),
            h.max()
        );
    };
    row("process time, 0 viewers", &phases[0].process_us);
    row("process time, 3 viewers", &phases[1].process_us);
    row("capture→publish, 0 viewers", &phases[0].latency_us);
    row("capture→publish, 3 viewers", &phases[1].latency_us);
    let ratio = |q: f64, a: &Histogram<u64>, b: &Histogram<u64>| {
        b.value_at_quantile(q) as f64 / a.value_at_quantile(q).max(1) as f64
    };
    println!(
        "ratio 3 viewers / 0 viewers: process p50 {:.2}, p99 {:.2}; capture→publish p50 {:.2}, p99 {:.2}",
        ratio(0.5, &phases[0].process_us, &phases[1].process_us),
        ratio(0.99, &phases[0].process_us, &phases[1].process_us),
        ratio(0.5, &phases[0].latency_us, &phases[1].latency_us),
        ratio(0.99, &phases[0].latency_us, &phases[1].latency_us),
    );
    println!(
        "deadline misses: {} in total",
        status.deadline_misses.load(Ordering::Relaxed)
    );
    Ok(())
}

/// A viewer asking for everything; reads (and discards) what it gets. Returns bytes received.
async fn viewer(addr: SocketAddr) -> anyhow::Result<u64> {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/api/live")).await?;
    ws.send(tokio_tungstenite::tungstenite::Message::Text(
        r#"{"type":"subscribe","preview_fps":30,"preview_max_width_px":640,"zoom_px":64,"blobs":true}"#
            .into(),
    ))
    .await?;
    let mut bytes = 0u64;
    let t0 = Instant::now();
    while let Some(msg) = ws.next().await {
        bytes += msg?.len() as u64;
        if t0.elapsed() > Duration::from_secs(3600) {
            break;
        }
    }
    Ok(bytes)
}
