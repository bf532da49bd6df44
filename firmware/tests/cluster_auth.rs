//! Peers are who they say (issue 40, docs/cluster.md "Credentials"): a solver irtrackd with a
//! credentials file, two camera boards with their passwords, and two forgers over real Zenoh
//! sessions on 127.0.0.1 — one without credentials, one with board b1's genuine password
//! publishing under board b0's key expressions. The forgers send a point 300 mm off with
//! sequence numbers above the boards' (the attack of issue 40); the solver's positions stay
//! on the real point with all three cameras and nothing of the forgers is even seen.
#![cfg(feature = "cluster")]

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use common::*;
use irtrack_cluster::transport::{Auth, ObsPublisher, Session, TransportConfig, realtime_ns};
use irtrack_core::params::RigParams;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::cluster::{ClusterConfig, UNAUTHENTICATED};
use irtrack_firmware::config::Config;
use nalgebra::Vector3;

const RIG: &str = "cellauth";
const FPS: f64 = 30.0;
const PW0: &str = "b0-pw-7Tq2Lm9Xz4Kc8Vn1Rb5W";
const PW1: &str = "b1-pw-3Hs6Jd0Fy2Gp7Qa9Ue4N";

fn connect(port: u16, auth: Auth) -> Option<Session> {
    Session::open(&TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        auth,
        ..TransportConfig::default()
    })
    .ok()
}

fn board_auth(board: &str, password: &str) -> Auth {
    Auth::Board {
        board: board.into(),
        password: password.into(),
    }
}

/// The genuine boards (b0 cameras 0 and 1, b1 camera 0) observing `p`, and the forgers
/// observing `forged` under b0's keys with sequence numbers 1000 ahead; until `stop`.
/// `forged_sent` counts the forgers' puts that Zenoh accepted locally.
fn publish(
    port: u16,
    r: RigParams,
    p: Vector3<f64>,
    forged: Vector3<f64>,
    stop: Arc<AtomicBool>,
    forged_sent: Arc<AtomicU64>,
) {
    let s0 = connect(port, board_auth("b0", PW0)).expect("board b0 opens");
    let s1 = connect(port, board_auth("b1", PW1)).expect("board b1 opens");
    let mut c00 = ObsPublisher::new(&s0, RIG, "b0", 0).unwrap();
    let mut c01 = ObsPublisher::new(&s0, RIG, "b0", 1).unwrap();
    let mut c10 = ObsPublisher::new(&s1, RIG, "b1", 0).unwrap();
    // Forger 1: no credentials. Forger 2: b1's own session, publishing as b0.
    let anon = connect(port, Auth::None);
    let mut forgers: Vec<ObsPublisher> = Vec::new();
    for s in anon.iter().chain([&s1]) {
        forgers.push(ObsPublisher::new(s, RIG, "b0", 0).unwrap());
        forgers.push(ObsPublisher::new(s, RIG, "b0", 1).unwrap());
    }
    let good = [obs_blob(&r, 0, &p), obs_blob(&r, 1, &p), obs_blob(&r, 2, &p)];
    let bad = [obs_blob(&r, 0, &forged), obs_blob(&r, 1, &forged)];
    let period_ns = (1e9 / FPS) as u64;
    let start = Instant::now();
    let mut seq = 0u64;
    while !stop.load(Ordering::Relaxed) && start.elapsed() < Duration::from_secs(60) {
        seq += 1;
        let ts = realtime_ns();
        c00.publish(&obs_header(RIG, "b0", 0, seq, ts), &good[..1])
            .unwrap();
        c01.publish(&obs_header(RIG, "b0", 1, seq, ts), &good[1..2])
            .unwrap();
        c10.publish(&obs_header(RIG, "b1", 0, seq, ts), &good[2..])
            .unwrap();
        for (i, f) in forgers.iter_mut().enumerate() {
            let cam = i % 2;
            if f.publish(
                &obs_header(RIG, "b0", cam as u8, seq + 1000, ts),
                &bad[cam..cam + 1],
            )
            .is_ok()
            {
                forged_sent.fetch_add(1, Ordering::Relaxed);
            }
        }
        let next = start + Duration::from_nanos(seq * period_ns);
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
    for s in anon.iter().chain([&s0, &s1]) {
        s.close();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_peers_never_move_the_solver() {
    let dir = TempDir::new("cluster-auth");
    let r = placed_ring(RIG, &[("b0", 0), ("b0", 1), ("b1", 0)]);
    std::fs::write(dir.path().join("params.irp"), r.to_blob().unwrap()).unwrap();
    let dict = dir.path().join("solver.credentials");
    std::fs::write(&dict, format!("b0:{PW0}\nb1:{PW1}\n")).unwrap();
    let port = free_tcp_port();
    let mut cfg = test_config(dir.path());
    cfg.cluster = ClusterConfig {
        credentials_file: Some(dict),
        ..solver_cluster(&r, RIG, port, FPS)
    };
    cfg.cluster.validate().unwrap();
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let p = Vector3::new(20.0, -10.0, 580.0);
    let forged = Vector3::new(320.0, -10.0, 580.0);
    let stop = Arc::new(AtomicBool::new(false));
    let forged_sent = Arc::new(AtomicU64::new(0));
    let publisher = {
        let (r, stop, sent) = (r.clone(), stop.clone(), forged_sent.clone());
        std::thread::spawn(move || publish(port, r, p, forged, stop, sent))
    };

    let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    let first = client
        .until(10 * FPS as usize, |rec| {
            rec.status == TrackStatus::Ok && rec.cameras_used == 3
        })
        .await;
    assert!(dist_mm(first.position_mm.unwrap(), [p.x, p.y, p.z]) < 0.05);
    // 3 s of records: every position on the real point, all three cameras.
    let mut n = 0;
    let until = Instant::now() + Duration::from_secs(3);
    while Instant::now() < until {
        let rec = client.next().await;
        if let Some(pos) = rec.position_mm {
            let e = dist_mm(pos, [p.x, p.y, p.z]);
            assert!(e < 0.05, "a forged position got through: {pos:?} ({e} mm)");
            assert_eq!(rec.cameras_used, 3, "{rec:?}");
            n += 1;
        }
    }
    assert!(n as f64 >= 2.0 * FPS, "only {n} positions in 3 s");
    // Nothing of the forgers reached the solver: not even as refused duplicates (in issue 40
    // the real boards' observations were the ones refused, as `duplicate_sequence`).
    let st = status_json(running.addrs.status).await;
    let refused = &st["cluster"]["refused"];
    assert!(
        refused.as_object().is_none_or(|m| m.is_empty()),
        "observations refused: {refused}"
    );
    let boards = st["cluster"]["boards"].as_array().unwrap();
    assert_eq!(boards.len(), 2, "{boards:?}");
    stop.store(true, Ordering::Relaxed);
    publisher.join().unwrap();
    let sent = forged_sent.load(Ordering::Relaxed);
    assert!(sent > 100, "the forgers sent only {sent} observations");
    eprintln!("{n} positions in 3 s, all on the real point; forgers sent {sent}, none arrived");
    running.shutdown().await;
}

#[test]
fn credentials_config_is_checked_and_unauthenticated_is_said() {
    let dir = TempDir::new("cluster-auth-config");
    let pw = dir.path().join("b0.password");
    std::fs::write(&pw, format!("{PW0}\n")).unwrap();
    let camera = |extra: &str| {
        format!(
            "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ncameras = [2]\n[cluster]\nrole = \"camera\"\nboard = \"b0\"\n{extra}"
        )
    };
    let err = |toml: &str| Config::from_toml(toml, "test.toml").unwrap_err().to_string();

    // Without credentials: valid, and said to be unauthenticated.
    let c = Config::from_toml(&camera("connect = [\"tcp/127.0.0.1:7447\"]\n"), "t").unwrap();
    assert_eq!(c.cluster.auth_summary().as_deref(), Some(UNAUTHENTICATED));
    assert!(UNAUTHENTICATED.contains("UNAUTHENTICATED"));
    // With a password file: authenticated as its board.
    let with_pw = format!("connect = [\"tcp/127.0.0.1:7447\"]\npassword_file = {:?}\n", pw);
    let c = Config::from_toml(&camera(&with_pw), "t").unwrap();
    let line = c.cluster.auth_summary().unwrap();
    assert!(line.contains("authenticated as board \"b0\""), "{line}");
    assert!(!line.contains(PW0));
    // A board with credentials that listens would refuse the solver: refused, said why.
    let e = err(&camera(&format!(
        "listen = [\"tcp/127.0.0.1:7447\"]\npassword_file = {pw:?}\n"
    )));
    assert!(e.contains("camera boards connect to the solver"), "{e}");
    // The solver's key on a board, a bad password file: named.
    let e = err(&camera(&format!(
        "connect = [\"tcp/127.0.0.1:7447\"]\ncredentials_file = {pw:?}\n"
    )));
    assert!(e.contains("a camera board takes its own password_file"), "{e}");
    std::fs::write(&pw, "short\n").unwrap();
    let e = err(&camera(&with_pw));
    assert!(e.contains("16..=128") && e.contains("b0.password"), "{e}");

    // The solver: listens; its dictionary must not list its own cameras' board.
    let dict = dir.path().join("solver.credentials");
    std::fs::write(&dict, format!("b0:{PW0}\ns0:{PW1}\n")).unwrap();
    let solver = format!(
        "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ncameras = [2]\n[cluster]\nrole = \"solver\"\nboard = \"s0\"\nown_cameras = true\n\
         listen = [\"tcp/127.0.0.1:7447\"]\nimage_sizes_px = [[640, 480], [640, 480]]\ncredentials_file = {dict:?}\n"
    );
    let e = err(&solver);
    assert!(e.contains("the solver's own board name"), "{e}");
    std::fs::write(&dict, format!("b0:{PW0}\nb1:{PW1}\n")).unwrap();
    let c = Config::from_toml(&solver, "t").unwrap();
    let line = c.cluster.auth_summary().unwrap();
    assert!(line.contains("only the boards in"), "{line}");
    let e = err(&solver.replace("listen = ", "connect = "));
    assert!(e.contains("the solver listens"), "{e}");
}
