//! Does watching disturb tracking? Loop latency with 0 and with 3 live viewers, side by side.
//!
//! Runs irtrackd's processing loop (simulated 90° rig, VGA, paced at `--fps`, default 100) with
//! its status listener on 127.0.0.1, records per set the timestamps of its path
//! (`Engine::last_times`: rendering, driver = capture → dequeued, ours = dequeued → published,
//! the whole processing time incl. the viewers' copy, capture → published) for `--seconds`
//! (default 10) with no viewer and `--seconds` with 3 WebSocket viewers asking for 30 fps
//! full-width previews, 64 px zooms and every set's blob lists — side by side in one run:
//! the two conditions alternate in `--rounds` (default 4) slices, so a change in the machine's
//! load (other builds on a shared machine) hits both alike — and prints percentiles (the
//! product's own log-linear histogram) and the ratios. `--fifo-priority N` runs the loop thread
//! SCHED_FIFO (as irtrackd's `[realtime] fifo_priority`) where permitted; the output says
//! whether it was.
//!
//! ```sh
//! cargo run --release -p irtrack-firmware --example viewers [-- --seconds 10 --fps 100 --fifo-priority 50]
//! ```
//!
//! `--timing-compare` (no viewers) measures instead what time-true tracking costs the loop:
//! two loops side by side in alternating slices, one on cameras exposing together, one on
//! free-running cameras (phases over the period, ±50 ppm, 200 µs timestamp jitter) with a
//! 15 µs/row rolling shutter, whose sets the clock models and the retiming carry to one instant.

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use futures_util::{SinkExt, StreamExt};
use irtrack_core::pipeline::TrackerConfig;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, SetTimes, StepOutcome};
use irtrack_firmware::metrics::LatencyHistogram;
use irtrack_firmware::net::status::StatusService;
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;
use irtrack_firmware::tuning::TuningHandle;
use irtrack_firmware::viewer::ViewerTap;

/// Per-phase histograms of the set timestamps ([`SetTimes`]), recorded with the product's own
/// log-linear histogram.
#[derive(Default)]
struct Phase {
    render: LatencyHistogram,
    driver: LatencyHistogram,
    ours: LatencyHistogram,
    process: LatencyHistogram,
    end_to_end: LatencyHistogram,
}

impl Phase {
    fn record(&self, t: &SetTimes) {
        if t.render_ns > 0 {
            self.render.record_ns(t.render_ns);
        }
        self.driver.record_ns(t.driver_ns());
        self.ours.record_ns(t.ours_ns());
        self.process.record_ns(t.done_ns.saturating_sub(t.dequeued_ns));
        self.end_to_end
            .record_ns(t.published_ns.saturating_sub(t.capture_ns));
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
    // `--connect ADDR`: only the 3 viewers, against a running irtrackd's status port, for
    // `--seconds` (the viewer load of `cargo xtask bench --latency`'s robot link rows).
    let args: Vec<String> = std::env::args().collect();
    if let Some(addr) = args
        .iter()
        .position(|a| a == "--connect")
        .and_then(|i| args.get(i + 1))
    {
        let addr: SocketAddr = addr.parse()?;
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?;
        return rt.block_on(async {
            let bytes = Arc::new(AtomicU64::new(0));
            let viewers: Vec<_> = (0..3)
                .map(|_| tokio::spawn(viewer(addr, bytes.clone())))
                .collect();
            tokio::time::sleep(Duration::from_secs_f64(seconds)).await;
            for v in viewers {
                if v.is_finished() {
                    // A viewer that ended early failed: say why rather than measure without it.
                    v.await??;
                    anyhow::bail!("a viewer's connection closed early");
                }
                v.abort();
            }
            let bytes = bytes.load(Ordering::Relaxed);
            if bytes == 0 {
                anyhow::bail!("the viewers received nothing from {addr}");
            }
            println!("viewers done: 3 viewers, {seconds} s, {bytes} bytes received");
            anyhow::Ok(())
        });
    }
    let fps = arg("--fps", 100.0);
    if args.iter().any(|a| a == "--timing-compare") {
        return timing_compare(fps, seconds);
    }
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

    // Phase switch: the loop thread records into phase 0 (no viewer) or 1 (3 viewers); 2 =
    // not recorded (warm-up, viewers connecting or leaving).
    let phase = Arc::new(AtomicU64::new(2));
    let stop = Arc::new(AtomicBool::new(false));
    let (phase2, stop2) = (phase.clone(), stop.clone());
    let fifo = arg("--fifo-priority", 0.0) as i32;
    let (sched_tx, sched_rx) = std::sync::mpsc::channel();
    let loop_thread = std::thread::spawn(move || -> anyhow::Result<[Phase; 2]> {
        let sched = if fifo > 0 {
            irtrack_firmware::rt::apply(&irtrack_firmware::config::RealtimeConfig {
                fifo_priority: Some(fifo),
                ..Default::default()
            })
            .join("; ")
        } else {
            "normal scheduling (no --fifo-priority)".to_string()
        };
        let _ = sched_tx.send(sched);
        let phases = [Phase::default(), Phase::default()];
        while !stop2.load(Ordering::Relaxed) {
            let outcome = engine.step()?;
            let p = phase2.load(Ordering::Relaxed) as usize;
            if let (StepOutcome::Published(_), Some(h)) = (outcome, phases.get(p)) {
                h.record(&engine.last_times());
            }
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
        let rounds = arg("--rounds", 4.0).max(1.0) as u32;
        let slice = Duration::from_secs_f64(seconds / f64::from(rounds));
        let received = Arc::new(AtomicU64::new(0));
        let (mut copies, mut blob_copies) = (0, 0);
        for _ in 0..rounds {
            phase.store(0, Ordering::Relaxed);
            tokio::time::sleep(slice).await;
            phase.store(2, Ordering::Relaxed);
            let viewers: Vec<_> = (0..3)
                .map(|_| tokio::spawn(viewer(addr, received.clone())))
                .collect();
            tokio::time::sleep(Duration::from_millis(500)).await;
            let (c0, b0) = (tap.copies(), tap.blob_copies());
            phase.store(1, Ordering::Relaxed);
            tokio::time::sleep(slice).await;
            phase.store(2, Ordering::Relaxed);
            copies += tap.copies() - c0;
            blob_copies += tap.blob_copies() - b0;
            for v in viewers {
                v.abort();
            }
            // The sessions end and detach before the next no-viewer slice.
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
        let _ = stop_tx.send(());
        let _ = server.await;
        println!(
            "viewer phases: the loop made {copies} frame copies and {blob_copies} blob copies for the viewers; {} frame / {} blob copies skipped (slot busy); {} sets not sent by the blob viewers",
            tap.busy_skips(),
            tap.blob_busy_skips(),
            tap.viewer_dropped_sets(),
        );
        println!("viewers received {} bytes", received.load(Ordering::Relaxed));
        anyhow::Ok(())
    })?;
    stop.store(true, Ordering::Relaxed);
    let phases = loop_thread
        .join()
        .map_err(|_| anyhow::anyhow!("loop thread panicked"))??;

    println!(
        "processing loop, simulated 2 × 640x480 at {fps} fps, {seconds} s per condition in alternating slices (cargo run --release -p irtrack-firmware --example viewers)"
    );
    println!(
        "scheduling of the loop thread: {}",
        sched_rx.recv().unwrap_or_default()
    );
    println!(
        "{:<34} {:>8} {:>9} {:>9} {:>9} {:>9} {:>9}",
        "", "sets", "p50 µs", "p90 µs", "p99 µs", "p99.9 µs", "max µs"
    );
    let row = |name: &str, h: &LatencyHistogram| {
        let s = h.snapshot();
        let q = |q: f64| s.quantile_us(q).unwrap_or(f64::NAN);
        println!(
            "{:<34} {:>8} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
            name,
            s.count(),
            q(0.5),
            q(0.9),
            q(0.99),
            q(0.999),
            s.max_ns as f64 / 1e3
        );
    };
    for (i, p) in phases.iter().enumerate() {
        let v = if i == 0 { 0 } else { 3 };
        row(&format!("render (simulator), {v} viewers"), &p.render);
        row(&format!("driver, {v} viewers"), &p.driver);
        row(&format!("ours, {v} viewers"), &p.ours);
        row(&format!("process time, {v} viewers"), &p.process);
        row(&format!("capture→publish, {v} viewers"), &p.end_to_end);
    }
    let ratio = |q: f64, a: &LatencyHistogram, b: &LatencyHistogram| {
        let (a, b) = (a.snapshot(), b.snapshot());
        b.quantile_us(q).unwrap_or(f64::NAN) / a.quantile_us(q).unwrap_or(f64::NAN)
    };
    println!(
        "ratio 3 viewers / 0 viewers: ours p50 {:.2}, p99 {:.2}; capture→publish p50 {:.2}, p99 {:.2}",
        ratio(0.5, &phases[0].ours, &phases[1].ours),
        ratio(0.99, &phases[0].ours, &phases[1].ours),
        ratio(0.5, &phases[0].end_to_end, &phases[1].end_to_end),
        ratio(0.99, &phases[0].end_to_end, &phases[1].end_to_end),
    );
    println!(
        "deadline misses: {} in total",
        status.deadline_misses.load(Ordering::Relaxed)
    );
    Ok(())
}

/// A viewer asking for everything; reads (and discards) what it gets, counting the bytes.
async fn viewer(addr: SocketAddr, received: Arc<AtomicU64>) -> anyhow::Result<()> {
    let (mut ws, _) = tokio_tungstenite::connect_async(format!("ws://{addr}/api/live")).await?;
    ws.send(tokio_tungstenite::tungstenite::Message::Text(
        r#"{"type":"subscribe","preview_fps":30,"preview_max_width_px":640,"zoom_px":64,"blobs":true}"#
            .into(),
    ))
    .await?;
    let t0 = Instant::now();
    while let Some(msg) = ws.next().await {
        received.fetch_add(msg?.len() as u64, Ordering::Relaxed);
        if t0.elapsed() > Duration::from_secs(3600) {
            break;
        }
    }
    Ok(())
}

/// One loop of [`timing_compare`]: its engine runs only while `active`; after each resume the
/// first sets are not recorded (the paced source skips the frames it missed while paused).
fn spawn_paused_loop(
    mut engine: Engine,
    active: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<anyhow::Result<(Phase, u64)>> {
    std::thread::spawn(move || {
        let phase = Phase::default();
        let (mut was_active, mut since_resume, mut unbridged) = (false, 0u32, 0u64);
        while !stop.load(Ordering::Relaxed) {
            if !active.load(Ordering::Relaxed) {
                was_active = false;
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
            if !was_active {
                was_active = true;
                since_resume = 0;
            }
            if let StepOutcome::Published(r) = engine.step()? {
                since_resume += 1;
                if since_resume > 10 {
                    phase.record(&engine.last_times());
                    if r.position_mm.is_none() {
                        unbridged += 1;
                    }
                }
            }
        }
        Ok((phase, unbridged))
    })
}

/// `--timing-compare`: the loop on cameras exposing together and on free-running,
/// rolling-shutter cameras (time-true tracking at work), alternating in slices, no viewers.
fn timing_compare(fps: f64, seconds: f64) -> anyhow::Result<()> {
    let make = |free_running: bool| -> anyhow::Result<Engine> {
        let mut cfg = SimSourceConfig {
            fps,
            ..SimSourceConfig::default()
        };
        if free_running {
            cfg.timing = Some(toml::from_str(
                "preset = \"free_running\"\nline_time_us = 15.0\nexposure_us = 1000.0",
            )?);
        }
        cfg.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
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
        let (tx, _rx) = tokio::sync::watch::channel(None);
        Ok(Engine::new(
            Box::new(source),
            TrackerConfig::default(),
            handle,
            tx,
            status,
            Duration::from_secs_f64(1.0 / fps),
        )
        .with_nominal_fps(Some(fps))
        .with_camera_timing(cfg.camera_timings()))
    };
    let stop = Arc::new(AtomicBool::new(false));
    let actives = [Arc::new(AtomicBool::new(false)), Arc::new(AtomicBool::new(false))];
    let loops = [
        spawn_paused_loop(make(false)?, actives[0].clone(), stop.clone()),
        spawn_paused_loop(make(true)?, actives[1].clone(), stop.clone()),
    ];
    let rounds = arg("--rounds", 4.0).max(1.0) as u32;
    let slice = Duration::from_secs_f64(seconds / f64::from(rounds));
    // Warm-up: each loop locks its clock models and fills its tracks before measuring.
    for a in &actives {
        a.store(true, Ordering::Relaxed);
        std::thread::sleep(Duration::from_secs(1));
        a.store(false, Ordering::Relaxed);
    }
    for _ in 0..rounds {
        for a in &actives {
            a.store(true, Ordering::Relaxed);
            std::thread::sleep(slice);
            a.store(false, Ordering::Relaxed);
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    stop.store(true, Ordering::Relaxed);
    let mut phases = Vec::new();
    for l in loops {
        phases.push(l.join().map_err(|_| anyhow::anyhow!("loop thread panicked"))??);
    }
    println!(
        "processing loop, simulated 2 × 640x480 at {fps} fps, {seconds} s per condition in alternating slices, no viewers (cargo run --release -p irtrack-firmware --example viewers -- --timing-compare)"
    );
    println!(
        "{:<34} {:>8} {:>9} {:>9} {:>9} {:>9} {:>9}",
        "", "sets", "p50 µs", "p90 µs", "p99 µs", "p99.9 µs", "max µs"
    );
    for ((p, without), name) in phases.iter().zip(["together", "free-running"]) {
        for (what, h) in [("ours", &p.ours), ("capture→publish", &p.end_to_end)] {
            let s = h.snapshot();
            let q = |q: f64| s.quantile_us(q).unwrap_or(f64::NAN);
            println!(
                "{:<34} {:>8} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>9.1}",
                format!("{what}, {name}"),
                s.count(),
                q(0.5),
                q(0.9),
                q(0.99),
                q(0.999),
                s.max_ns as f64 / 1e3
            );
        }
        println!("sets without a position, {name}: {without}");
    }
    let (a, b) = (phases[0].0.ours.snapshot(), phases[1].0.ours.snapshot());
    println!(
        "ratio free-running / together: ours p50 {:.2}, p99 {:.2}",
        b.quantile_us(0.5).unwrap_or(f64::NAN) / a.quantile_us(0.5).unwrap_or(f64::NAN),
        b.quantile_us(0.99).unwrap_or(f64::NAN) / a.quantile_us(0.99).unwrap_or(f64::NAN),
    );
    Ok(())
}
