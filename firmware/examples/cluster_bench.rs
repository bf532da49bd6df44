//! Cluster benchmark (docs/cluster.md), printed by `cargo xtask bench-links`:
//!
//! 1. observation hop over Zenoh on 127.0.0.1 (TCP, explicit endpoints): board publish →
//!    solver receive, p50/p99, for 2 and 4 boards of 2 cameras at 120 fps each;
//! 2. bytes per observation (one blob, the message alone; Zenoh adds its framing);
//! 3. the solver's CPU per set at 8 cameras (thread CPU time): decode, gate, pair, set the
//!    blobs, triangulate; and the allocations per set in that loop (counting allocator);
//! 4. capture → published position (the loop's `end_to_end` histogram, what `/status` reports
//!    as `processing.latency_us.end_to_end`) side by side: an in-process solver (`app::start`,
//!    role `solver`) fed at 120 fps by 2 and 4 boards that this program simulates (each
//!    observation's capture time is its publish instant: the hop, the pairing wait and the
//!    solve; a real board adds its own capture → publish, the standalone row's `driver` and
//!    `detect`), and one standalone board (`app::start`, simulated source) with the same
//!    four-camera ring rig at 120 fps.
//!
//! `cargo run --release -p irtrack-firmware --features cluster --example cluster_bench
//! [-- --secs S] [--quick]`; `cargo xtask bench` runs it (docs/performance.md).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use irtrack_cluster::pairing::{Pairer, PairingConfig};
use irtrack_cluster::transport::{ObsPublisher, ObsSubscriber, Session, TransportConfig, realtime_ns};
use irtrack_core::blob::Blob;
use irtrack_core::observation::{
    CameraPlace, MAX_OBS_LEN, ObsBlob, ObsClock, ObsHeader, ObservationGate, decode, encode,
};
use irtrack_core::params::RigParams;
use irtrack_core::pipeline::{Tracker, TrackerConfig};
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::config::Config;
use irtrack_firmware::metrics::HistogramSnapshot;
use nalgebra::Vector3;

#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

const FPS: f64 = 120.0;

fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: valid out-pointer; CLOCK_THREAD_CPUTIME_ID exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn pct(v: &mut [u64], p: f64) -> f64 {
    v.sort_unstable();
    v[((v.len() - 1) as f64 * p).round() as usize] as f64
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn blob_at(x: f64, y: f64) -> ObsBlob {
    ObsBlob {
        x_px: x as f32,
        y_px: y as f32,
        area_px: 12,
        peak_dn: 230,
        roundness: 0.95,
        ..ObsBlob::default()
    }
}

/// Hop latency with `boards` boards of 2 cameras each at 120 fps for `secs` s.
fn hop(boards: usize, secs: f64) -> (usize, f64, f64) {
    let port = free_port();
    let solver = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    })
    .unwrap();
    let (_sub, rx) = ObsSubscriber::new(&solver, "bench", 4096, realtime_ns).unwrap();
    let sessions: Vec<Session> = (0..boards)
        .map(|_| {
            Session::open(&TransportConfig {
                connect: vec![format!("tcp/127.0.0.1:{port}")],
                ..TransportConfig::default()
            })
            .unwrap()
        })
        .collect();
    let names: Vec<String> = (0..boards).map(|b| format!("b{b}")).collect();
    let mut pubs: Vec<(usize, ObsPublisher)> = sessions
        .iter()
        .enumerate()
        .flat_map(|(b, s)| (0..2).map(move |c| (b, c, s)))
        .map(|(b, c, s)| (b, ObsPublisher::new(s, "bench", &names[b], c).unwrap()))
        .collect();
    // Wait for the routes.
    let start = Instant::now();
    'warm: loop {
        for (b, p) in pubs.iter_mut() {
            let h = header(&names[*b], 0, 0);
            p.publish(&h, &[blob_at(1.0, 1.0)]).unwrap();
        }
        while let Ok(_m) = rx.recv_timeout(Duration::from_millis(20)) {
            if start.elapsed() > Duration::from_millis(500) {
                break 'warm;
            }
        }
        assert!(start.elapsed() < Duration::from_secs(10), "no route");
    }
    while rx.try_recv().is_ok() {}
    let period = Duration::from_secs_f64(1.0 / FPS);
    let frames = (secs * FPS) as u64;
    let mut hops = Vec::with_capacity((frames as usize) * pubs.len());
    let t0 = Instant::now();
    for k in 1..=frames {
        let due = t0 + period * k as u32;
        while Instant::now() < due {
            while let Ok(m) = rx.try_recv() {
                let o = decode(m.payload()).unwrap();
                hops.push(m.received_ns.saturating_sub(o.header.capture_ts_ns));
            }
            std::thread::sleep(Duration::from_micros(200));
        }
        for (b, p) in pubs.iter_mut() {
            // The capture timestamp is the publish instant: the hop alone.
            let h = header(&names[*b], k, realtime_ns());
            p.publish(&h, &[blob_at(320.0, 240.0)]).unwrap();
        }
    }
    let end = Instant::now() + Duration::from_millis(200);
    while Instant::now() < end {
        if let Ok(m) = rx.recv_timeout(Duration::from_millis(10)) {
            let o = decode(m.payload()).unwrap();
            hops.push(m.received_ns.saturating_sub(o.header.capture_ts_ns));
        }
    }
    let n = hops.len();
    let (p50, p99) = (pct(&mut hops, 0.5), pct(&mut hops, 0.99));
    for s in &sessions {
        s.close();
    }
    solver.close();
    (n, p50 / 1e3, p99 / 1e3)
}

/// The same traffic over one plain TCP connection (TCP_NODELAY, a blocking reader thread
/// stamping on arrival): what the machine itself gives, to tell Zenoh's tail from the load's.
fn tcp_hop(streams: usize, secs: f64) -> (usize, f64, f64) {
    use std::io::{Read, Write};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let mut tx = std::net::TcpStream::connect(addr).unwrap();
    tx.set_nodelay(true).unwrap();
    let (mut rx, _) = listener.accept().unwrap();
    let frames = (secs * FPS) as usize;
    let reader = std::thread::spawn(move || {
        let mut hops = Vec::with_capacity(frames * streams);
        let mut msg = [0u8; 64];
        while rx.read_exact(&mut msg).is_ok() {
            let sent = u64::from_le_bytes(msg[..8].try_into().unwrap());
            hops.push(realtime_ns().saturating_sub(sent));
        }
        hops
    });
    let period = Duration::from_secs_f64(1.0 / FPS);
    let t0 = Instant::now();
    for k in 1..=frames {
        std::thread::sleep((t0 + period.mul_f64(k as f64)).saturating_duration_since(Instant::now()));
        for _ in 0..streams {
            let mut msg = [0u8; 64];
            msg[..8].copy_from_slice(&realtime_ns().to_le_bytes());
            tx.write_all(&msg).unwrap();
        }
    }
    drop(tx);
    let mut hops = reader.join().unwrap();
    let n = hops.len();
    (n, pct(&mut hops, 0.5) / 1e3, pct(&mut hops, 0.99) / 1e3)
}

fn header(board: &str, seq: u64, ts: u64) -> ObsHeader<'_> {
    ObsHeader {
        rig: "bench",
        board,
        camera: 0,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: ts,
        clock: ObsClock::Realtime,
        exposure_us: 500,
        dropped: 0,
        send_delay_us: 800,
    }
}

/// Solver CPU and allocations per set at 8 cameras (4 boards × 2).
fn solver_cpu(sets: u64) -> (f64, f64, f64) {
    let rig = irtrack_firmware::source::sim::ring_rig(8, 600.0);
    let mut tracker = Tracker::new(&rig, TrackerConfig::default()).unwrap();
    let boards = ["b0", "b1", "b2", "b3"];
    let places: Vec<CameraPlace> = (0..8)
        .map(|c| CameraPlace {
            board: boards[c / 2].into(),
            local_index: (c % 2) as u8,
        })
        .collect();
    let mut gate = ObservationGate::new("bench", &places, ObsClock::Realtime, u64::MAX / 4).unwrap();
    let mut pairer = Pairer::new(PairingConfig::for_fps((0..8).map(|c| c / 2).collect(), FPS)).unwrap();
    // Pre-encoded observations of a marker on a circle, as the boards would send them.
    let period_ns = (1e9 / FPS) as u64;
    let t_base = 1_000_000_000_000u64;
    let mut msgs: Vec<Vec<([u8; MAX_OBS_LEN], usize)>> = Vec::new();
    for k in 0..sets {
        let a = k as f64 * 0.05;
        let p = Vector3::new(40.0 * a.cos(), 20.0 * a.sin(), 600.0 + 30.0 * a.sin());
        let mut set = Vec::new();
        for (c, cam) in rig.cameras.iter().enumerate() {
            let pc = cam.cam_from_cam0.apply(&p);
            let px = cam.model.project(&pc).unwrap();
            let h = ObsHeader {
                rig: "bench",
                board: boards[c / 2],
                camera: (c % 2) as u8,
                sequence: k + 1,
                trigger_count: None,
                capture_ts_ns: t_base + k * period_ns,
                clock: ObsClock::Realtime,
                exposure_us: 500,
                dropped: 0,
                send_delay_us: 0,
            };
            let mut buf = [0u8; MAX_OBS_LEN];
            let n = encode(&h, &[blob_at(px.x, px.y)], &mut buf).unwrap();
            set.push((buf, n));
        }
        msgs.push(set);
    }
    let mut blobs: Vec<Blob> = Vec::with_capacity(32);
    let mut tracked = 0u64;
    let mut run = |k: usize, tracker: &mut Tracker, blobs: &mut Vec<Blob>| {
        let now = t_base + k as u64 * period_ns + 1_000_000;
        for (buf, n) in &msgs[k] {
            let obs = decode(&buf[..*n]).unwrap();
            let c = gate.check(&obs, now).unwrap();
            pairer.push(c, &obs, now);
        }
        let set = pairer.poll(now).expect("complete set");
        for (c, e) in set.cameras[..8].iter().enumerate() {
            blobs.clear();
            blobs.extend(e.blobs().iter().map(|b| b.to_blob()));
            tracker.set_blobs(c, blobs.iter().copied()).unwrap();
        }
        tracker.solve().point_cam0_mm.is_some()
    };
    // Warm up (first sets may grow buffers), then measure.
    let warm = 20usize;
    for k in 0..warm {
        run(k, &mut tracker, &mut blobs);
    }
    let a0 = irtrack_testkit::allocations();
    let c0 = thread_cpu_ns();
    for k in warm..sets as usize {
        tracked += u64::from(run(k, &mut tracker, &mut blobs));
    }
    let cpu = (thread_cpu_ns() - c0) as f64 / (sets as usize - warm) as f64;
    let allocs = (irtrack_testkit::allocations() - a0) as f64 / (sets as usize - warm) as f64;
    let share = tracked as f64 / (sets as usize - warm) as f64;
    (cpu / 1e3, allocs, share)
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let secs: f64 = std::env::args()
        .skip_while(|a| a != "--secs")
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(if quick { 1.0 } else { 3.0 });
    let mut buf = [0u8; MAX_OBS_LEN];
    let one = encode(&header("b1", 7, 1), &[blob_at(1.0, 2.0)], &mut buf).unwrap();
    println!(
        "cluster benchmark (Zenoh on 127.0.0.1, TCP, explicit endpoints; {FPS} fps per camera, {secs} s)"
    );
    println!("| measure | value |");
    println!("|---|---|");
    for boards in [2usize, 4] {
        let (n, p50, p99) = hop(boards, secs);
        println!(
            "| hop board publish → solver receive, {boards} boards × 2 cameras ({n} observations) | p50 {p50:.0} µs, p99 {p99:.0} µs |"
        );
        let (n, p50, p99) = tcp_hop(2 * boards, secs);
        println!(
            "| the same traffic over plain TCP (baseline of this machine now), {boards} boards ({n} messages) | p50 {p50:.0} µs, p99 {p99:.0} µs |"
        );
    }
    println!(
        "| bytes per observation (1 blob, board name of 2 characters, rig `bench`) | {one} (+16 per further blob; Zenoh framing not included) |"
    );
    let (cpu_us, allocs, share) = solver_cpu(if quick { 500 } else { 2000 });
    let budget_us = 1e6 / FPS;
    println!(
        "| solver CPU per set, 8 cameras (decode, gate, pair, triangulate; {:.0} % tracked) | {cpu_us:.1} µs = {:.1} % of one core at 120 sets/s |",
        share * 100.0,
        100.0 * cpu_us / budget_us
    );
    println!("| allocations per set in the solver's loop | {allocs:.2} |");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    println!();
    println!(
        "capture → published position, {FPS} fps, the loop's end_to_end histogram after a 1 s warm-up ({secs} s each; µs)"
    );
    println!("| irtrackd | sets | p50 | p90 | p99 | max | of which |");
    println!("|---|---|---|---|---|---|---|");
    let one = rt.block_on(standalone_latency(secs));
    println!(
        "| standalone board, 4 cameras (simulated, VGA) | {} | {:.0} | {:.0} | {:.0} | {:.0} | driver (capture → dequeued) p50 {:.0}, detect p50 {:.0}, ours (dequeued → published) p50 {:.0} |",
        one.end_to_end.count(),
        q(&one.end_to_end, 0.5),
        q(&one.end_to_end, 0.9),
        q(&one.end_to_end, 0.99),
        one.end_to_end.max_ns as f64 / 1e3,
        q(&one.driver, 0.5),
        q(&one.detect, 0.5),
        q(&one.ours, 0.5),
    );
    for boards in [2usize, 4] {
        let s = rt.block_on(solver_latency(boards, secs));
        println!(
            "| solver, {boards} boards × 2 cameras (board publish → published) | {} | {:.0} | {:.0} | {:.0} | {:.0} | hop + set closing (driver) p50 {:.0}, ours p50 {:.0}; {:.0} % of sets tracked |",
            s.end_to_end.count(),
            q(&s.end_to_end, 0.5),
            q(&s.end_to_end, 0.9),
            q(&s.end_to_end, 0.99),
            s.end_to_end.max_ns as f64 / 1e3,
            q(&s.driver, 0.5),
            q(&s.ours, 0.5),
            100.0 * s.tracked,
        );
    }
}

fn q(h: &HistogramSnapshot, p: f64) -> f64 {
    h.quantile_us(p).unwrap_or(f64::NAN)
}

/// Histograms of one run, warm-up subtracted.
struct Stages {
    end_to_end: HistogramSnapshot,
    driver: HistogramSnapshot,
    detect: HistogramSnapshot,
    ours: HistogramSnapshot,
    /// Share of published sets with a position (solver runs).
    tracked: f64,
}

/// `b − a` of two snapshots of one histogram (min/max are `b`'s: a bound, not exact).
fn since(a: &HistogramSnapshot, b: &HistogramSnapshot) -> HistogramSnapshot {
    HistogramSnapshot {
        counts: b.counts.iter().zip(&a.counts).map(|(x, y)| x - y).collect(),
        sum_ns: b.sum_ns - a.sum_ns,
        min_ns: b.min_ns,
        max_ns: b.max_ns,
    }
}

/// Warm-up, then `secs` of the running service's stage histograms.
async fn measure(running: &app::Running, secs: f64) -> Stages {
    let st = &running.status.stages;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let snap = || {
        [
            st.end_to_end.snapshot(),
            st.driver.snapshot(),
            st.detect.snapshot(),
            st.ours.snapshot(),
        ]
    };
    let a = snap();
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    let b = snap();
    Stages {
        end_to_end: since(&a[0], &b[0]),
        driver: since(&a[1], &b[1]),
        detect: since(&a[2], &b[2]),
        ours: since(&a[3], &b[3]),
        tracked: f64::NAN,
    }
}

fn service_config(state: &std::path::Path, extra: &str) -> Config {
    let text = format!(
        "[service]\nstate_dir = {state:?}\n[listen]\nparams = \"127.0.0.1:0\"\nstream_ndjson = \"127.0.0.1:0\"\n\
         stream_binary = \"127.0.0.1:0\"\nstatus = \"127.0.0.1:0\"\n[params]\nallow_unsigned = true\n\
         [leds]\nbackend = \"none\"\n{extra}"
    );
    Config::from_toml(&text, "cluster_bench").unwrap()
}

fn state_dir(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("irtrack-cluster-bench-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// One standalone board: the simulated four-camera ring at 120 fps.
async fn standalone_latency(secs: f64) -> Stages {
    let dir = state_dir("standalone");
    let mut cfg = service_config(
        &dir,
        &format!("[source.sim]\nrig = \"ring\"\nring_cameras = 4\ndistance_mm = 600\nfps = {FPS}\n"),
    );
    cfg.service.params_from_simulator = true;
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let s = measure(&running, secs).await;
    running.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
    s
}

/// A solver fed by `boards` simulated boards of two cameras each at 120 fps.
async fn solver_latency(boards: usize, secs: f64) -> Stages {
    let dir = state_dir(&format!("solver{boards}"));
    let cameras = 2 * boards;
    let mut rig = irtrack_firmware::source::sim::ring_rig(cameras, 600.0);
    rig.rig_id = "bench".into();
    let names: Vec<String> = (0..boards).map(|b| format!("b{b}")).collect();
    rig.placement = (0..cameras)
        .map(|c| CameraPlace {
            board: names[c / 2].clone(),
            local_index: (c % 2) as u8,
        })
        .collect();
    std::fs::write(dir.join("params.irp"), rig.to_blob().unwrap()).unwrap();
    let port = free_port();
    let sizes: Vec<String> = rig
        .cameras
        .iter()
        .map(|c| {
            format!(
                "[{}, {}]",
                c.model.image_size.width_px, c.model.image_size.height_px
            )
        })
        .collect();
    let cfg = service_config(
        &dir,
        &format!(
            "[cluster]\nrole = \"solver\"\nrig = \"bench\"\nlisten = [\"tcp/127.0.0.1:{port}\"]\nfps = {FPS}\nimage_sizes_px = [{}]\n",
            sizes.join(", ")
        ),
    );
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let feeder = {
        let (stop, rig, names) = (stop.clone(), rig.clone(), names.clone());
        std::thread::spawn(move || feed(port, &rig, &names, &stop))
    };
    let (tr0, pub0) = counters(&running);
    let mut s = measure(&running, secs).await;
    let (tr1, pub1) = counters(&running);
    s.tracked = (tr1 - tr0) as f64 / (pub1 - pub0).max(1) as f64;
    stop.store(true, Ordering::Relaxed);
    let sent = tokio::task::spawn_blocking(move || feeder.join().unwrap())
        .await
        .unwrap();
    assert!(sent > 0, "the simulated boards sent nothing");
    running.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
    s
}

/// Tracked and published sets so far.
fn counters(running: &app::Running) -> (u64, u64) {
    let st = &running.status;
    (
        st.tracked.load(Ordering::Relaxed),
        st.published.load(Ordering::Relaxed),
    )
}

/// The simulated boards: every camera's blob of a point moving on a circle, stamped with the
/// publish instant, at 120 fps until `stop`; returns the observations sent.
fn feed(port: u16, rig: &RigParams, names: &[String], stop: &AtomicBool) -> u64 {
    let tc = TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    };
    let sessions: Vec<Session> = names.iter().map(|_| Session::open(&tc).unwrap()).collect();
    let mut pubs: Vec<ObsPublisher> = (0..rig.cameras.len())
        .map(|c| ObsPublisher::new(&sessions[c / 2], "bench", &names[c / 2], c % 2).unwrap())
        .collect();
    let period = Duration::from_secs_f64(1.0 / FPS);
    let t0 = Instant::now();
    let mut k = 0u64;
    while !stop.load(Ordering::Relaxed) {
        k += 1;
        let a = k as f64 * 0.05;
        let p = Vector3::new(40.0 * a.cos(), 20.0 * a.sin(), 600.0 + 30.0 * a.sin());
        let ts = realtime_ns();
        for (c, publisher) in pubs.iter_mut().enumerate() {
            let cam = &rig.cameras[c];
            let Ok(px) = cam.model.project(&cam.cam_from_cam0.apply(&p)) else {
                continue;
            };
            let mut h = header(&names[c / 2], k, ts);
            h.camera = (c % 2) as u8;
            h.send_delay_us = 0;
            publisher.publish(&h, &[blob_at(px.x, px.y)]).unwrap();
        }
        let due = t0 + period.mul_f64(k as f64);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
    }
    let sent = pubs.iter().map(|p| p.sent()).sum();
    for s in &sessions {
        s.close();
    }
    sent
}
