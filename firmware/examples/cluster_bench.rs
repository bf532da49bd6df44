//! Cluster benchmark (docs/cluster.md, docs/performance.md), printed by `cargo xtask bench
//! --cluster` (and at the end of `cargo xtask bench` and `bench-links`):
//!
//! 1. observation hop over Zenoh on 127.0.0.1 (TCP, explicit endpoints): board publish →
//!    solver receive, p50/p99 and observations received of sent, for 2 and 4 boards of 2
//!    cameras at 120 fps each, Zenoh's default and low-latency transports side by side with
//!    the same traffic over plain TCP; with `--fifo PRIO` every row also with every thread of
//!    the process SCHED_FIFO (rows alternate, so both see the same load);
//! 2. bytes per observation (one blob, the message alone; Zenoh adds its framing);
//! 3. the solver's CPU per set at 8 cameras (thread CPU time): decode, gate, pair, set the
//!    blobs, triangulate; and the allocations per set in that loop (counting allocator);
//! 4. capture → published position (the loop's `end_to_end` histogram, what `/status` reports
//!    as `processing.latency_us.end_to_end`) side by side: an in-process solver (`app::start`,
//!    role `solver`) fed at 120 fps by 2 and 4 boards that this program simulates (each
//!    observation stamped at its frame's instant on a fixed schedule, as a camera's exposure
//!    is: the boards' publishing delay, the hop, the pairing wait and the solve; a real board
//!    adds its own capture → publish, the standalone row's `driver` and `detect`), and one
//!    standalone board (`app::start`, simulated source) with the same four-camera ring rig at
//!    120 fps; then where the solver's sets went in the same windows: frames sent, sets
//!    published, complete/incomplete, late, conflicting, clock-refused, queue overflow.
//!
//! 5. the hop in the product: 2, then 4 irtrackd camera boards (`--boards N`: N only) → an
//!    irtrackd solver as separate processes (the binary beside this example's directory, or
//!    `--irtrackd PATH`), the solver's `/status` → `cluster.hop_us`, without `[cluster]
//!    transport_fifo_priority`, with it at the loops' 50 (`--fifo PRIO`) and 10 above,
//!    alternating, `--rounds N` rounds
//!    (default 3); `--processes-only` runs only these rows.
//!
//! `cargo run --release -p irtrack-firmware --features cluster --example cluster_bench
//! [-- --secs S] [--quick] [--low-latency | --default-transport] [--fifo PRIO]
//! [--stamp-at-publish] [--processes-only] [--rounds N] [--boards N] [--irtrackd PATH]`.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
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

/// The transport of one row: Zenoh's default, or its low-latency unicast transport
/// (`[cluster] low_latency = true`).
fn transport(low_latency: bool, listen: Option<u16>, connect: Option<u16>) -> TransportConfig {
    let ep = |p: Option<u16>| p.map(|p| format!("tcp/127.0.0.1:{p}")).into_iter().collect();
    TransportConfig {
        listen: ep(listen),
        connect: ep(connect),
        low_latency,
        ..TransportConfig::default()
    }
}

/// One hop row: observations received of those sent, p50 and p99 in µs.
struct Hop {
    received: usize,
    sent: u64,
    p50_us: f64,
    p99_us: f64,
}

impl std::fmt::Display for Hop {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:.0} / {:.0} ({} of {})",
            self.p50_us, self.p99_us, self.received, self.sent
        )
    }
}

/// Credentials and the solver's TLS identity for boards b0..b3 of rig `bench` (the secured
/// row: user/password inside the TLS tunnels, docs/cluster.md "TLS").
struct Secure {
    dictionary: std::path::PathBuf,
    certificate: std::path::PathBuf,
    key: std::path::PathBuf,
    passwords: Vec<String>,
}

fn secure_files() -> Secure {
    let dir = std::env::temp_dir().join(format!("irtrack-bench-tls-{}", std::process::id()));
    let names = ["b0", "b1", "b2", "b3"];
    let creds = irtrack_cluster::credentials::write_new_credentials(&dir, &names, true).unwrap();
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec![irtrack_cluster::names::SOLVER_TLS_NAME.to_string()])
        .unwrap()
        .self_signed(&key)
        .unwrap();
    let (certificate, key_file) = (dir.join("solver.tls.crt"), dir.join("solver.tls.key"));
    std::fs::write(&certificate, cert.pem()).unwrap();
    irtrack_cluster::credentials::write_private(&key_file, &key.serialize_pem()).unwrap();
    Secure {
        dictionary: irtrack_cluster::credentials::dictionary_path(&dir),
        certificate,
        key: key_file,
        passwords: creds.into_iter().map(|c| c.password).collect(),
    }
}

/// The transport of the solver (`board` None) or of board `b<i>`, secured when `secure`.
fn node(low_latency: bool, port: u16, board: Option<usize>, secure: Option<&Secure>) -> TransportConfig {
    use irtrack_cluster::tls::TlsRole;
    use irtrack_cluster::transport::Auth;
    let mut t = match board {
        None => transport(low_latency, Some(port), None),
        Some(_) => transport(low_latency, None, Some(port)),
    };
    if let Some(s) = secure {
        match board {
            None => {
                t.auth = Auth::solver_from_file("bench", &s.dictionary).unwrap().0;
                t.tls = Some(TlsRole::Solver {
                    certificate_file: s.certificate.clone(),
                    key_file: s.key.clone(),
                });
            }
            Some(i) => {
                t.auth = Auth::Board {
                    board: format!("b{i}"),
                    password: s.passwords[i].clone(),
                };
                t.tls = Some(TlsRole::Board {
                    solver_certificate_file: s.certificate.clone(),
                });
            }
        }
    }
    t
}

/// Hop latency with `boards` boards of 2 cameras each at 120 fps for `secs` s.
fn hop(boards: usize, secs: f64, low_latency: bool, secure: Option<&Secure>) -> Hop {
    let port = free_port();
    let solver = Session::open(&node(low_latency, port, None, secure)).unwrap();
    let (_sub, rx) = ObsSubscriber::new(&solver, "bench", 4096, realtime_ns).unwrap();
    let sessions: Vec<Session> = (0..boards)
        .map(|b| Session::open(&node(low_latency, port, Some(b), secure)).unwrap())
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
    let sent0: u64 = pubs.iter().map(|(_, p)| p.sent()).sum();
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
    let sent = pubs.iter().map(|(_, p)| p.sent()).sum::<u64>() - sent0;
    let received = hops.len();
    let (p50, p99) = (pct(&mut hops, 0.5), pct(&mut hops, 0.99));
    for s in &sessions {
        s.close();
    }
    solver.close();
    Hop {
        received,
        sent,
        p50_us: p50 / 1e3,
        p99_us: p99 / 1e3,
    }
}

/// The same traffic over one plain TCP connection (TCP_NODELAY, a blocking reader thread
/// stamping on arrival): what the machine itself gives, to tell Zenoh's tail from the load's.
fn tcp_hop(streams: usize, secs: f64) -> Hop {
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
    Hop {
        received: hops.len(),
        sent: (frames * streams) as u64,
        p50_us: pct(&mut hops, 0.5) / 1e3,
        p99_us: pct(&mut hops, 0.99) / 1e3,
    }
}

/// Sets every thread of this process (Zenoh's runtime threads, the tokio workers, ours) to
/// SCHED_FIFO at `priority`, or back to normal scheduling with `None`; threads started later
/// inherit the policy of the thread that starts them. What an appliance would do with
/// `[realtime] fifo_priority` for the whole daemon. Returns an error text if refused.
fn schedule_all(priority: Option<i32>) -> Result<(), String> {
    let (policy, prio) = match priority {
        Some(p) => (libc::SCHED_FIFO, p),
        None => (libc::SCHED_OTHER, 0),
    };
    let tasks = std::fs::read_dir("/proc/self/task").map_err(|e| e.to_string())?;
    for t in tasks.flatten() {
        let Some(tid) = t.file_name().to_str().and_then(|s| s.parse::<libc::pid_t>().ok()) else {
            continue;
        };
        let param = libc::sched_param { sched_priority: prio };
        // SAFETY: `tid` is a thread of this process (it may have ended: ESRCH is ignored);
        // `param` is a valid sched_param.
        if unsafe { libc::sched_setscheduler(tid, policy, &param) } != 0 {
            let e = std::io::Error::last_os_error();
            if e.raw_os_error() != Some(libc::ESRCH) {
                return Err(format!("SCHED_FIFO {prio} refused: {e}"));
            }
        }
    }
    Ok(())
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

/// Command line: `--secs S`, `--quick`, `--low-latency` (only Zenoh's low-latency transport)
/// or `--default-transport` (only the default; neither: both side by side), `--fifo PRIO`
/// (hop rows also with every thread SCHED_FIFO), `--stamp-at-publish` (the simulated boards
/// stamp observations when they publish, as before 2026-11-26, beside the frame-instant rows).
struct Opts {
    quick: bool,
    secs: f64,
    transports: Vec<bool>,
    fifo: Option<i32>,
    stamps: Vec<Stamp>,
}

fn opts() -> Opts {
    let args: Vec<String> = std::env::args().collect();
    let has = |f: &str| args.iter().any(|a| a == f);
    let value = |f: &str| {
        args.iter()
            .skip_while(|a| *a != f)
            .nth(1)
            .and_then(|s| s.parse::<f64>().ok())
    };
    let quick = has("--quick");
    let transports = match (has("--low-latency"), has("--default-transport")) {
        (true, false) => vec![true],
        (false, true) => vec![false],
        _ => vec![false, true],
    };
    let mut stamps = vec![Stamp::FrameInstant];
    if has("--stamp-at-publish") {
        stamps.insert(0, Stamp::Publish);
    }
    Opts {
        quick,
        secs: value("--secs").unwrap_or(if quick { 1.0 } else { 3.0 }),
        transports,
        fifo: value("--fifo").map(|p| p as i32),
        stamps,
    }
}

fn transport_name(low_latency: bool) -> &'static str {
    if low_latency { "low-latency" } else { "default" }
}

fn main() {
    let o = opts();
    let secs = o.secs;
    let args: Vec<String> = std::env::args().collect();
    let rounds = args
        .iter()
        .skip_while(|a| *a != "--rounds")
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(if o.quick { 1 } else { 3 });
    // `--boards N` runs the process rows with N camera boards only (default: 2, then 4).
    let board_counts: Vec<usize> = match args
        .iter()
        .skip_while(|a| *a != "--boards")
        .nth(1)
        .and_then(|s| s.parse().ok())
    {
        Some(n) => vec![n],
        None => vec![2, 4],
    };
    let procs = |prio: Option<i32>| match irtrackd_exe() {
        Some(exe) => {
            for &boards in &board_counts {
                process_rows(&exe, boards, secs, rounds, &o.transports, prio.unwrap_or(50));
            }
        }
        None => println!(
            "\nProcess rows skipped: no irtrackd binary beside this example (build it with `--features cluster --bin irtrackd`, or give --irtrackd PATH)"
        ),
    };
    if args.iter().any(|a| a == "--processes-only") {
        procs(o.fifo);
        return;
    }
    let mut buf = [0u8; MAX_OBS_LEN];
    let one = encode(&header("b1", 7, 1), &[blob_at(1.0, 2.0)], &mut buf).unwrap();
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "cluster benchmark (Zenoh on 127.0.0.1, TCP, explicit endpoints; {FPS} fps per camera, {secs} s per row; load average at start {})",
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
    );
    println!();
    println!(
        "Observation hop, board publish → solver receive (µs p50 / p99, observations received of sent), transports side by side:"
    );
    print!("| boards × 2 cameras | scheduling |");
    for &ll in &o.transports {
        print!(" Zenoh {} transport |", transport_name(ll));
    }
    // The secured cell: passwords inside TLS tunnels, on the first transport.
    let secure = secure_files();
    print!(" {} + passwords + TLS tunnels |", transport_name(o.transports[0]));
    println!(" plain TCP, same traffic (this machine's baseline) |");
    println!("|---|---|{}---|---|", "---|".repeat(o.transports.len()));
    let scheds: Vec<Option<i32>> = std::iter::once(None).chain(o.fifo.map(Some)).collect();
    for boards in [2usize, 4] {
        for &prio in &scheds {
            // Rows with and without real-time priority alternate, so both see the same load.
            let sched = match prio {
                None => "normal".to_string(),
                Some(p) => match schedule_all(Some(p)) {
                    Ok(()) => format!("every thread SCHED_FIFO {p}"),
                    Err(e) => {
                        println!("| {boards} | {e} |");
                        continue;
                    }
                },
            };
            print!("| {boards} | {sched} |");
            for &ll in &o.transports {
                print!(" {} |", hop(boards, secs, ll, None));
            }
            print!(" {} |", hop(boards, secs, o.transports[0], Some(&secure)));
            println!(" {} |", tcp_hop(2 * boards, secs));
            if prio.is_some() {
                schedule_all(None).expect("back to normal scheduling");
            }
        }
    }
    println!();
    println!("| measure | value |");
    println!("|---|---|");
    println!(
        "| bytes per observation (1 blob, board name of 2 characters, rig `bench`) | {one} (+16 per further blob; Zenoh framing not included) |"
    );
    let (cpu_us, allocs, share) = solver_cpu(if o.quick { 500 } else { 2000 });
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
    let mut accounts = Vec::new();
    for boards in [2usize, 4] {
        for &ll in &o.transports {
            for &stamp in &o.stamps {
                let (s, a) = rt.block_on(solver_latency(boards, secs, ll, stamp));
                println!(
                    "| solver, {boards} boards × 2 cameras, {} transport{} (capture → published) | {} | {:.0} | {:.0} | {:.0} | {:.0} | capture → set delivered (driver) p50 {:.0}, ours p50 {:.0}; {:.0} % of sets tracked |",
                    transport_name(ll),
                    stamp.note(),
                    s.end_to_end.count(),
                    q(&s.end_to_end, 0.5),
                    q(&s.end_to_end, 0.9),
                    q(&s.end_to_end, 0.99),
                    s.end_to_end.max_ns as f64 / 1e3,
                    q(&s.driver, 0.5),
                    q(&s.ours, 0.5),
                    100.0 * s.tracked,
                );
                accounts.push((boards, ll, stamp, a));
            }
        }
    }
    println!();
    println!(
        "Where the solver's sets went in the same windows (frames the boards sent → sets published; the pairing counters come from the solver's report, refreshed every 200 ms, so they may lag a set or two):"
    );
    println!(
        "| solver | frames sent | boards' thread: publishing one frame, mean µs | sets published | complete | incomplete | observations: late | conflicting | refused (clock) | queue overflow | whole run: received of sent | sets dropped as not newer | skewed |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (boards, ll, stamp, a) in accounts {
        println!(
            "| {boards} boards, {}{} | {} | {:.0} | {} | {} | {} | {} | {} | {} | {} | {} of {} | {} | {} |",
            transport_name(ll),
            stamp.note(),
            a.frames,
            a.publish_ns as f64 / 1e3 / a.frames.max(1) as f64,
            a.published,
            a.complete,
            a.incomplete,
            a.late,
            a.conflicting,
            a.refused_clock,
            a.overflow,
            a.received,
            a.sent,
            a.stale,
            a.skewed,
        );
    }
    procs(o.fifo);
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

/// Warm-up, then `secs` of the running service's stage histograms; `mark` runs when the
/// window opens and when it closes (for counters taken over the same window).
async fn measure(running: &app::Running, secs: f64, mut mark: impl FnMut()) -> Stages {
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
    mark();
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    let b = snap();
    mark();
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
    let s = measure(&running, secs, || ()).await;
    running.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
    s
}

/// How the simulated boards stamp an observation's capture time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stamp {
    /// At the frame's instant on a fixed 120 fps schedule, as a camera's exposure is,
    /// however late the board's thread gets to publish it (the send delay says how late).
    FrameInstant,
    /// When the board's thread publishes (the benchmark before 2026-11-26): a thread that
    /// wakes late publishes two frames back to back with nearly the same time stamp.
    Publish,
}

impl Stamp {
    fn note(self) -> &'static str {
        match self {
            Stamp::FrameInstant => "",
            Stamp::Publish => ", boards stamp at publish",
        }
    }
}

/// Counts over one measured window of a solver run (see the table printed after the rows).
#[derive(Debug, Default)]
struct Account {
    frames: u64,
    publish_ns: u64,
    sent: u64,
    received: u64,
    published: u64,
    complete: u64,
    incomplete: u64,
    late: u64,
    conflicting: u64,
    refused_clock: u64,
    overflow: u64,
    stale: u64,
    skewed: u64,
}

/// Counters of the running solver and its simulated boards at one instant.
fn account(running: &app::Running, feed: &FeedCounters) -> Account {
    let st = &running.status;
    let r = st.cluster_report().unwrap_or_default();
    Account {
        frames: feed.frames.load(Ordering::Relaxed),
        publish_ns: feed.publish_ns.load(Ordering::Relaxed),
        sent: feed.sent.load(Ordering::Relaxed),
        received: r.received,
        published: st.published.load(Ordering::Relaxed),
        complete: r.sets_complete,
        incomplete: r.sets_incomplete,
        late: r.late,
        conflicting: r.conflicting,
        refused_clock: r.refused_clock,
        overflow: r.queue_overflow,
        stale: st.stale_sets.load(Ordering::Relaxed),
        skewed: st.skewed_sets.load(Ordering::Relaxed),
    }
}

impl std::ops::Sub for Account {
    type Output = Account;
    fn sub(self, a: Account) -> Account {
        Account {
            frames: self.frames - a.frames,
            publish_ns: self.publish_ns - a.publish_ns,
            sent: self.sent - a.sent,
            received: self.received - a.received,
            published: self.published - a.published,
            complete: self.complete - a.complete,
            incomplete: self.incomplete - a.incomplete,
            late: self.late - a.late,
            conflicting: self.conflicting - a.conflicting,
            refused_clock: self.refused_clock - a.refused_clock,
            overflow: self.overflow - a.overflow,
            stale: self.stale - a.stale,
            skewed: self.skewed - a.skewed,
        }
    }
}

/// What the simulated boards have done so far.
#[derive(Debug, Default)]
struct FeedCounters {
    stop: AtomicBool,
    /// Frames (instants) published, all cameras.
    frames: AtomicU64,
    /// Observations published.
    sent: AtomicU64,
    /// Time the boards' thread spent publishing frames' observations, summed, ns.
    publish_ns: AtomicU64,
}

/// A solver fed by `boards` simulated boards of two cameras each at 120 fps.
async fn solver_latency(boards: usize, secs: f64, low_latency: bool, stamp: Stamp) -> (Stages, Account) {
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
            "[cluster]\nrole = \"solver\"\nrig = \"bench\"\nlisten = [\"tcp/127.0.0.1:{port}\"]\nfps = {FPS}\nlow_latency = {low_latency}\nimage_sizes_px = [{}]\n",
            sizes.join(", ")
        ),
    );
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let counters = Arc::new(FeedCounters::default());
    let feeder = {
        let (c, rig, names) = (counters.clone(), rig.clone(), names.clone());
        std::thread::spawn(move || feed(port, &rig, &names, low_latency, stamp, &c))
    };
    // The window must not open before the boards are up: opening four Zenoh sessions took
    // more than the 1 s warm-up on the loaded machine, and the sets they had not sent yet
    // were once read as sets the solver lost.
    let up = Instant::now();
    while counters.frames.load(Ordering::Relaxed) == 0 {
        assert!(
            up.elapsed() < Duration::from_secs(30),
            "the simulated boards did not start"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let mut marks = Vec::new();
    let mut s = measure(&running, secs, || {
        marks.push((account(&running, &counters), tracked_published(&running)))
    })
    .await;
    let [(a0, (tr0, pub0)), (a1, (tr1, pub1))]: [_; 2] = marks.try_into().expect("two marks");
    s.tracked = (tr1 - tr0) as f64 / (pub1 - pub0).max(1) as f64;
    counters.stop.store(true, Ordering::Relaxed);
    tokio::task::spawn_blocking(move || feeder.join().unwrap())
        .await
        .unwrap();
    // Whole run, after the solver's report caught up: observations received of sent.
    tokio::time::sleep(Duration::from_millis(400)).await;
    let mut a = a1 - a0;
    a.sent = counters.sent.load(Ordering::Relaxed);
    a.received = running.status.cluster_report().map_or(0, |r| r.received);
    assert!(
        counters.sent.load(Ordering::Relaxed) > 0,
        "the simulated boards sent nothing"
    );
    running.shutdown().await;
    let _ = std::fs::remove_dir_all(&dir);
    (s, a)
}

/// Tracked and published sets so far.
fn tracked_published(running: &app::Running) -> (u64, u64) {
    let st = &running.status;
    (
        st.tracked.load(Ordering::Relaxed),
        st.published.load(Ordering::Relaxed),
    )
}

/// The simulated boards: every camera's blob of a point moving on a circle at 120 fps until
/// `c.stop`, stamped as `stamp` says; counts frames and observations in `c`.
fn feed(port: u16, rig: &RigParams, names: &[String], low_latency: bool, stamp: Stamp, c: &FeedCounters) {
    let tc = transport(low_latency, None, Some(port));
    let sessions: Vec<Session> = names.iter().map(|_| Session::open(&tc).unwrap()).collect();
    let mut pubs: Vec<ObsPublisher> = (0..rig.cameras.len())
        .map(|c| ObsPublisher::new(&sessions[c / 2], "bench", &names[c / 2], c % 2).unwrap())
        .collect();
    let period = Duration::from_secs_f64(1.0 / FPS);
    let (t0, t0_ns) = (Instant::now(), realtime_ns());
    let mut k = 0u64;
    while !c.stop.load(Ordering::Relaxed) {
        k += 1;
        let a = k as f64 * 0.05;
        let p = Vector3::new(40.0 * a.cos(), 20.0 * a.sin(), 600.0 + 30.0 * a.sin());
        let now_ns = realtime_ns();
        let ts = match stamp {
            // Frame k's exposure instant; the publishing thread is behind it by the send delay.
            Stamp::FrameInstant => t0_ns + (period.as_nanos() as u64 * (k - 1)),
            Stamp::Publish => now_ns,
        };
        let send_delay_us = (now_ns.saturating_sub(ts) / 1000) as u32;
        let started = Instant::now();
        for (i, publisher) in pubs.iter_mut().enumerate() {
            let cam = &rig.cameras[i];
            let Ok(px) = cam.model.project(&cam.cam_from_cam0.apply(&p)) else {
                continue;
            };
            let mut h = header(&names[i / 2], k, ts);
            h.camera = (i % 2) as u8;
            h.send_delay_us = send_delay_us;
            publisher.publish(&h, &[blob_at(px.x, px.y)]).unwrap();
            c.sent.fetch_add(1, Ordering::Relaxed);
        }
        let took = started.elapsed().as_nanos() as u64;
        c.publish_ns.fetch_add(took, Ordering::Relaxed);
        c.frames.fetch_add(1, Ordering::Relaxed);
        let due = t0 + period.mul_f64(k as f64);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
    }
    for s in &sessions {
        s.close();
    }
}

/// One irtrackd process of a process row, killed on drop.
struct IrtrackdProc {
    child: std::process::Child,
    status: std::net::SocketAddr,
}

impl Drop for IrtrackdProc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn spawn_irtrackd(
    exe: &std::path::Path,
    dir: &std::path::Path,
    name: &str,
    config: &str,
) -> Result<IrtrackdProc, String> {
    use std::io::BufRead;
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, config).map_err(|e| e.to_string())?;
    let state = dir.join(format!("{name}-state"));
    std::fs::create_dir_all(&state).map_err(|e| e.to_string())?;
    let mut child = std::process::Command::new(exe)
        .arg("-c")
        .arg(&cfg)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(&state)
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(dir.join(format!("{name}.log"))).map_err(|e| e.to_string())?)
        .spawn()
        .map_err(|e| format!("{}: {e}", exe.display()))?;
    let mut out = std::io::BufReader::new(child.stdout.take().ok_or("no stdout")?);
    let mut line = String::new();
    let _ = out.read_line(&mut line);
    std::thread::spawn(move || std::io::copy(&mut out, &mut std::io::sink()));
    let status = line
        .split_whitespace()
        .find_map(|f| f.strip_prefix("status="))
        .and_then(|a| a.parse().ok());
    let mut p = IrtrackdProc {
        child,
        status: "127.0.0.1:0".parse().map_err(|_| "addr")?,
    };
    match status {
        Some(s) => p.status = s,
        None => {
            return Err(format!(
                "{name} did not start (see {}/{name}.log): {line}",
                dir.display()
            ));
        }
    }
    Ok(p)
}

fn get_status(addr: std::net::SocketAddr) -> Option<serde_json::Value> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        s,
        "GET /status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut body = String::new();
    s.read_to_string(&mut body).ok()?;
    serde_json::from_str(&body[body.find("\r\n\r\n")? + 4..]).ok()
}

/// What one process row measured: the solver's `/status` → `cluster.hop_us` and the transport
/// threads' real-time line.
struct ProcHop {
    p50_us: f64,
    p99_us: f64,
    count: u64,
    received: u64,
    realtime: String,
}

/// Real irtrackd processes: `boards` camera boards (2 simulated VGA cameras each of the ring
/// rig, 120 fps, wall clock) and a solver, every one with `[realtime] fifo_priority = 50` (its
/// loop; what an appliance sets) and `[cluster] low_latency`, with or without
/// `transport_fifo_priority`. After the solver's first hop samples (its 1 s warm-up), `secs`
/// of observations; the solver's hop summary (board publish → solver receive).
fn process_hop(
    exe: &std::path::Path,
    boards: usize,
    secs: f64,
    low_latency: bool,
    transport_prio: Option<i32>,
) -> Result<ProcHop, String> {
    let dir = state_dir(&format!(
        "procs{boards}{low_latency}{}",
        transport_prio.unwrap_or(0)
    ));
    let cameras = 2 * boards;
    let mut rig = irtrack_firmware::source::sim::ring_rig(cameras, 600.0);
    rig.rig_id = "bench".into();
    rig.placement = (0..cameras)
        .map(|c| CameraPlace {
            board: format!("b{}", c / 2),
            local_index: (c % 2) as u8,
        })
        .collect();
    std::fs::create_dir_all(dir.join("solver-state")).map_err(|e| e.to_string())?;
    std::fs::write(
        dir.join("solver-state/params.irp"),
        rig.to_blob().map_err(|e| e.to_string())?,
    )
    .map_err(|e| e.to_string())?;
    let port = free_port();
    let sizes = vec!["[640, 480]"; cameras].join(", ");
    let common = format!(
        "fps = {FPS}\nlow_latency = {low_latency}\n{}",
        transport_prio.map_or(String::new(), |p| format!("transport_fifo_priority = {p}\n"))
    );
    let solver = spawn_irtrackd(
        exe,
        &dir,
        "solver",
        &format!(
            "[params]\nallow_unsigned = true\n[leds]\nbackend = \"none\"\n[realtime]\nfifo_priority = 50\n\
             [cluster]\nrole = \"solver\"\nrig = \"bench\"\nlisten = [\"tcp/127.0.0.1:{port}\"]\n\
             image_sizes_px = [{sizes}]\n{common}"
        ),
    )?;
    let mut procs = Vec::new();
    for b in 0..boards {
        procs.push(spawn_irtrackd(
            exe,
            &dir,
            &format!("b{b}"),
            &format!(
                "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n\
                 [source.sim]\nrig = \"ring\"\nring_cameras = {cameras}\ndistance_mm = 600\nfps = {FPS}\n\
                 wall_clock = true\ncameras = [{}, {}]\n[realtime]\nfifo_priority = 50\n\
                 [cluster]\nrole = \"camera\"\nrig = \"bench\"\nboard = \"b{b}\"\n\
                 connect = [\"tcp/127.0.0.1:{port}\"]\n{common}",
                2 * b,
                2 * b + 1
            ),
        )?);
    }
    let hop = |st: &serde_json::Value| st["cluster"]["hop_us"].clone();
    let t0 = Instant::now();
    loop {
        if get_status(solver.status).is_some_and(|st| hop(&st)["count"].as_u64().unwrap_or(0) > 0) {
            break;
        }
        if t0.elapsed() > Duration::from_secs(20) {
            return Err(format!("no hop samples after 20 s (see {})", dir.display()));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_secs_f64(secs));
    let st = get_status(solver.status).ok_or("solver /status")?;
    let h = hop(&st);
    let out = ProcHop {
        p50_us: h["p50_us"].as_f64().unwrap_or(f64::NAN),
        p99_us: h["p99_us"].as_f64().unwrap_or(f64::NAN),
        count: h["count"].as_u64().unwrap_or(0),
        received: st["cluster"]["received"].as_u64().unwrap_or(0),
        realtime: st["processing"]["realtime"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|l| l.as_str())
            .filter(|l| l.starts_with("Zenoh"))
            .collect::<Vec<_>>()
            .join("; "),
    };
    drop(procs);
    drop(solver);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(out)
}

/// The irtrackd binary of the process rows: `--irtrackd PATH`, else the one beside this
/// example's directory (`target/<profile>/irtrackd`, which `cargo xtask bench --cluster`
/// builds with the `cluster` feature first).
fn irtrackd_exe() -> Option<std::path::PathBuf> {
    let args: Vec<String> = std::env::args().collect();
    if let Some(p) = args.iter().skip_while(|a| *a != "--irtrackd").nth(1) {
        return Some(p.into());
    }
    let exe = std::env::current_exe().ok()?;
    let p = exe.parent()?.parent()?.join("irtrackd");
    p.exists().then_some(p)
}

/// Process rows: real irtrackd camera boards → real irtrackd solver, without `[cluster]
/// transport_fifo_priority`, with it at the loops' priority and 10 above, for each transport, alternating within each round so
/// every variant sees the same load.
fn process_rows(
    exe: &std::path::Path,
    boards: usize,
    secs: f64,
    rounds: usize,
    transports: &[bool],
    prio: i32,
) {
    println!();
    println!(
        "Observation hop in the product: {boards} irtrackd camera boards (2 simulated cameras each, {FPS} fps) → an irtrackd solver, separate processes on 127.0.0.1, every loop `[realtime] fifo_priority = 50`; the solver's /status cluster.hop_us over {secs} s after its warm-up (µs); rows alternate within a round:"
    );
    println!(
        "| round | transport | transport_fifo_priority | p50 | p99 | samples | observations received | transport threads |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for round in 1..=rounds {
        for &ll in transports {
            // Unset, the loops' priority, and above the loops (a loop busy at the same
            // priority holds the transport thread back until it blocks).
            for tp in [None, Some(prio), Some((prio + 10).min(99))] {
                match process_hop(exe, boards, secs, ll, tp) {
                    Ok(h) => println!(
                        "| {round} | {} | {} | {:.0} | {:.0} | {} | {} | {} |",
                        transport_name(ll),
                        tp.map_or("unset".to_string(), |p| p.to_string()),
                        h.p50_us,
                        h.p99_us,
                        h.count,
                        h.received,
                        if h.realtime.is_empty() {
                            "normal"
                        } else {
                            &h.realtime
                        }
                    ),
                    Err(e) => println!("| {round} | {} | {tp:?} | failed: {e} |", transport_name(ll)),
                }
            }
        }
    }
}
