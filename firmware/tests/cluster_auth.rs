//! Peers are who they say (issue 40, docs/cluster.md "Credentials"): a solver irtrackd with a
//! credentials file, two camera boards with their passwords, and two forgers over real Zenoh
//! sessions on 127.0.0.1 — one without credentials, one with board b1's genuine password
//! publishing under board b0's key expressions. The forgers send a point 300 mm off with
//! sequence numbers above the boards' (the attack of issue 40); the solver's positions stay
//! on the real point with all three cameras, nothing of the forgers is even seen, and the
//! simulated robot that follows the solver never leaves the real point.
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
    connect_from(port, None, auth)
}

/// A peer connecting to the solver, from the source address `from` (`ip:port`) when given.
fn connect_from(port: u16, from: Option<&str>, auth: Auth) -> Option<Session> {
    let bind = from.map_or(String::new(), |a| format!("#bind={a}"));
    Session::open(&TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}{bind}")],
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
/// `forged_sent` counts the forgers' puts that Zenoh accepted locally. `outsiders`: the peers
/// (source address if bound, credentials) that forge besides b1's own session.
fn publish(
    port: u16,
    r: RigParams,
    p: Vector3<f64>,
    forged: Vector3<f64>,
    stop: Arc<AtomicBool>,
    forged_sent: Arc<AtomicU64>,
    outsiders: Vec<(Option<String>, Auth)>,
) {
    let s0 = connect(port, board_auth("b0", PW0)).expect("board b0 opens");
    let s1 = connect(port, board_auth("b1", PW1)).expect("board b1 opens");
    let mut c00 = ObsPublisher::new(&s0, RIG, "b0", 0).unwrap();
    let mut c01 = ObsPublisher::new(&s0, RIG, "b0", 1).unwrap();
    let mut c10 = ObsPublisher::new(&s1, RIG, "b1", 0).unwrap();
    // The outsiders (e.g. one without credentials), and b1's own session publishing as b0.
    let outsiders: Vec<Session> = outsiders
        .into_iter()
        .filter_map(|(from, auth)| connect_from(port, from.as_deref(), auth))
        .collect();
    let mut forgers: Vec<ObsPublisher> = Vec::new();
    for s in outsiders.iter().chain([&s1]) {
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
    for s in outsiders.iter().chain([&s0, &s1]) {
        s.close();
    }
}

/// 3 s of records while forgers publish: every position on the real point `p`, from all three
/// cameras, and at least two thirds of the frames with one; returns how many.
async fn positions_stay_on(client: &mut NdjsonClient, p: Vector3<f64>) -> usize {
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
    n
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
    let p = Vector3::new(20.0, -10.0, 580.0);
    let forged = Vector3::new(320.0, -10.0, 580.0);
    // The robot of issue 40's attack: it was driven to the forged point (876 targets).
    let (robot, robot_cfg) = sim_robot([p.x, p.y, p.z]).await;
    cfg.robot = Some(robot_cfg);
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let forged_sent = Arc::new(AtomicU64::new(0));
    let publisher = {
        let (r, stop, sent) = (r.clone(), stop.clone(), forged_sent.clone());
        std::thread::spawn(move || publish(port, r, p, forged, stop, sent, vec![(None, Auth::None)]))
    };

    let mut client = NdjsonClient::connect(running.addrs.stream_ndjson).await;
    let first = client
        .until(10 * FPS as usize, |rec| {
            rec.status == TrackStatus::Ok && rec.cameras_used == 3
        })
        .await;
    assert!(dist_mm(first.position_mm.unwrap(), [p.x, p.y, p.z]) < 0.05);
    robot_following(&running, &robot).await;
    let n = positions_stay_on(&mut client, p).await;
    let (targets, worst) = assert_robot_stayed_on(&robot, [p.x, p.y, p.z], 0.1, (2.0 * FPS) as usize);
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
    eprintln!(
        "{n} positions in 3 s, all on the real point; forgers sent {sent}, none arrived; the \
         robot got {targets} targets, the worst {worst:.4} mm off, and never left the point"
    );
    running.shutdown().await;
}

/// irtrackd as a child process, as a unit runs it; killed when dropped.
struct Irtrackd {
    child: std::process::Child,
    params: std::net::SocketAddr,
    stream: std::net::SocketAddr,
    status: std::net::SocketAddr,
}

impl Drop for Irtrackd {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts irtrackd `name` with `config` (`dir/<name>.toml`), state in `dir/<name>-state`, log
/// in `dir/<name>.log` (appended across restarts).
fn spawn_irtrackd(dir: &std::path::Path, name: &str, config: &str) -> Irtrackd {
    use std::io::BufRead;
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, config).unwrap();
    let state = dir.join(format!("{name}-state"));
    std::fs::create_dir_all(&state).unwrap();
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(dir.join(format!("{name}.log")))
        .unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_irtrackd"))
        .arg("-c")
        .arg(&cfg)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(&state)
        .env("RUST_LOG", "info")
        .stdout(std::process::Stdio::piped())
        .stderr(log)
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    assert!(line.starts_with("irtrackd ready"), "{line}");
    std::thread::spawn(move || std::io::copy(&mut stdout, &mut std::io::sink()));
    let addr = |key: &str| -> std::net::SocketAddr {
        line.split_whitespace()
            .find_map(|f| f.strip_prefix(key))
            .unwrap_or_else(|| panic!("{key} in {line}"))
            .parse()
            .unwrap()
    };
    Irtrackd {
        params: addr("params="),
        stream: addr("stream="),
        status: addr("status="),
        child,
    }
}

/// A free port on a loopback address of its own, as `ip:port`: a forger's source address.
fn own_address(ip: &str) -> String {
    let port = std::net::TcpListener::bind((ip, 0))
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    format!("{ip}:{port}")
}

/// Issue 40, item 4: "an unauthenticated peer is refused and counted". The solver is a real
/// irtrackd process; a forger without credentials (from 127.0.0.66) and one that claims board
/// b1 with b0's password (from 127.0.0.67) try to publish. Both are counted with their
/// address in `/status`, `/metrics` and a plain-words fault; the positions stay on the real
/// point from all three cameras.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refused_peers_are_counted_with_their_address() {
    let dir = TempDir::new("cluster-auth-refused");
    let r = placed_ring(RIG, &[("b0", 0), ("b0", 1), ("b1", 0)]);
    let dict = dir.path().join("solver.credentials");
    std::fs::write(&dict, format!("b0:{PW0}\nb1:{PW1}\n")).unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&dict, std::fs::Permissions::from_mode(0o600)).unwrap();
    let port = free_tcp_port();
    let sizes: Vec<String> = r
        .cameras
        .iter()
        .map(|c| {
            format!(
                "[{}, {}]",
                c.model.image_size.width_px, c.model.image_size.height_px
            )
        })
        .collect();
    let solver = spawn_irtrackd(
        dir.path(),
        "solver",
        &format!(
            "[params]\nallow_unsigned = true\n[leds]\nbackend = \"none\"\n[cluster]\nrole = \"solver\"\nrig = \"{RIG}\"\n\
             listen = [\"tcp/127.0.0.1:{port}\"]\nfps = {FPS:.1}\nboard_timeout_ms = 300.0\nimage_sizes_px = [{}]\ncredentials_file = {:?}\n",
            sizes.join(", "),
            dict.display().to_string()
        ),
    );
    let verdict = push(solver.params, &r.to_blob().unwrap()).await;
    assert!(verdict.starts_with("OK"), "{verdict}");

    let anon = own_address("127.0.0.66");
    let wrong = own_address("127.0.0.67");
    let p = Vector3::new(20.0, -10.0, 580.0);
    let forged = Vector3::new(320.0, -10.0, 580.0);
    let stop = Arc::new(AtomicBool::new(false));
    let forged_sent = Arc::new(AtomicU64::new(0));
    let publisher = {
        let (r, stop, sent) = (r.clone(), stop.clone(), forged_sent.clone());
        let more = vec![
            (Some(anon.clone()), Auth::None),
            (Some(wrong.clone()), board_auth("b1", PW0)),
        ];
        std::thread::spawn(move || publish(port, r, p, forged, stop, sent, more))
    };

    let mut client = NdjsonClient::connect(solver.stream).await;
    client
        .until(10 * FPS as usize, |rec| {
            rec.status == TrackStatus::Ok && rec.cameras_used == 3
        })
        .await;
    let n = positions_stay_on(&mut client, p).await;

    // Both forgers are counted with the address they came from (Zenoh retries a refused
    // link, so each may be counted more than once).
    let find = |st: &serde_json::Value, addr: &str| -> Option<serde_json::Value> {
        st["cluster"]["refused_peers"]["recent"]
            .as_array()?
            .iter()
            .find(|e| e["address"].as_str() == Some(addr))
            .cloned()
    };
    let t0 = Instant::now();
    let st = loop {
        let st = status_json(solver.status).await;
        if (find(&st, &anon).is_some() && find(&st, &wrong).is_some())
            || t0.elapsed() > Duration::from_secs(10)
        {
            break st;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let refused = &st["cluster"]["refused_peers"];
    eprintln!("refused_peers: {refused:#}");
    assert_eq!(refused["counting"], true, "{refused}");
    for (addr, problem) in [(&anon, "missing"), (&wrong, "wrong_password")] {
        let e = find(&st, addr).unwrap_or_else(|| panic!("{addr} not counted: {refused:#}"));
        assert_eq!(e["reason"], "credentials", "{e}");
        assert_eq!(e["problem"], problem, "{e}");
        assert!(e["count"].as_u64().unwrap() >= 1, "{e}");
        let words = e["words"].as_str().unwrap();
        assert!(
            words.starts_with(&format!(
                "a peer at {addr} was refused: wrong or missing credentials"
            )),
            "{words}"
        );
    }
    let credentials = refused["by_reason"]["credentials"].as_u64().unwrap();
    assert!(credentials >= 2, "{refused}");
    assert!(
        refused["recent"]
            .as_array()
            .unwrap()
            .iter()
            .all(|e| e["address"].as_str().is_none_or(|a| a == anon || a == wrong)),
        "only the forgers are refused, never the boards: {refused:#}"
    );
    let faults = &st["fault_texts"];
    let fault = faults
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["code"] == "peer_refused")
        .unwrap_or_else(|| panic!("no peer_refused fault: {faults:#}"));
    let text = fault["message"].as_str().unwrap();
    assert!(
        [&anon, &wrong].iter().any(|a| text.starts_with(&format!(
            "a peer at {a} was refused: wrong or missing credentials"
        ))),
        "{text}"
    );
    // Nothing the forgers sent reached the pairing.
    assert!(
        st["cluster"]["refused"].as_object().is_none_or(|m| m.is_empty()),
        "{}",
        st["cluster"]["refused"]
    );
    let metrics = scrape_metrics(solver.status).await;
    let counted = metrics
        .value(
            "irtrackd_cluster_peers_refused_total",
            &[("reason", "credentials")],
        )
        .unwrap_or_else(|| panic!("no irtrackd_cluster_peers_refused_total: {}", metrics.0));
    assert!(counted >= 2.0, "{counted}");
    assert_eq!(
        metrics.family_type("irtrackd_cluster_peers_refused"),
        Some("counter")
    );
    // Board b1's own session publishing as b0 (the `publish` helper's last forgers) is let in;
    // each of its puts is dropped by the access control and counted under its user name.
    let denied = refused["denied_publications"].as_u64().unwrap();
    assert!(denied >= 10, "{refused:#}");
    let recent = refused["denied_recent"].as_array().unwrap();
    assert!(
        recent
            .iter()
            .any(|d| d["key"] == format!("irtrack/{RIG}/b0/cam/0/obs") && d["user"] == "b1"),
        "{refused:#}"
    );
    assert!(
        recent.iter().all(|d| d["user"] == "b1"
            && d["key"]
                .as_str()
                .is_some_and(|k| k.starts_with(&format!("irtrack/{RIG}/b0/cam/")))),
        "only b1's puts under b0's name, never the boards' own: {refused:#}"
    );
    let fault = faults
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["code"] == "publication_denied")
        .unwrap_or_else(|| panic!("no publication_denied fault: {faults:#}"));
    let text = fault["message"].as_str().unwrap();
    assert!(
        text.contains("which its credentials do not allow: dropped by the access control")
            && text.contains("a board publishes under another board's name"),
        "{text}"
    );
    let counted = metrics
        .value("irtrackd_cluster_publications_denied_total", &[])
        .unwrap_or_else(|| panic!("no irtrackd_cluster_publications_denied_total: {}", metrics.0));
    assert!(counted >= 10.0, "{counted}");
    stop.store(true, Ordering::Relaxed);
    publisher.join().unwrap();
    let log = std::fs::read_to_string(dir.path().join("solver.log")).unwrap();
    assert!(
        log.lines()
            .any(|l| l.contains("WARN") && l.contains("was refused: wrong or missing credentials")),
        "no log line about the refusals:\n{log}"
    );
    eprintln!(
        "{n} positions in 3 s, all on the real point; {credentials} credential refusals counted; forgers sent {}",
        forged_sent.load(Ordering::Relaxed)
    );
}

/// `/status` of irtrackd at `addr` (blocking).
fn status_now(addr: std::net::SocketAddr) -> serde_json::Value {
    common::runtime().block_on(status_json(addr))
}

/// Pushes `bytes` to a parameter port and returns the verdict line (blocking).
fn push_now(addr: std::net::SocketAddr, bytes: &[u8]) -> String {
    common::runtime().block_on(push(addr, bytes))
}

/// A solver s0 and a camera board b0 of rig `rt` that start without credentials and trust
/// the PC key for pushes, b0's password and the dictionary made on the PC, and each board's
/// public key for sealing (the push tests).
struct PushCell {
    dir: TempDir,
    port: u16,
    pc: irtrack_core::signing::SigningKey,
    solver_cfg: String,
    board_cfg: String,
    solver_key: [u8; 32],
    board_key: [u8; 32],
    password: Vec<u8>,
    dictionary: Vec<u8>,
}

impl PushCell {
    /// Starts both (returned: solver, board) and reads their keys.
    fn start(name: &str) -> (PushCell, Irtrackd, Irtrackd) {
        let dir = TempDir::new(name);
        let pc = irtrack_core::signing::SigningKey::from_bytes(&[0x42; 32]);
        let pub_file = dir.path().join("pc.pub");
        std::fs::write(
            &pub_file,
            irtrack_core::signing::public_key_file(&pc.verifying_key()),
        )
        .unwrap();
        let port = free_tcp_port();
        let solver_cfg = format!(
            "[params]\nallow_unsigned = true\ntrusted_keys = [{pub_file:?}]\n[leds]\nbackend = \"none\"\n[cluster]\nrole = \"solver\"\nrig = \"rt\"\nboard = \"s0\"\n\
             listen = [\"tcp/127.0.0.1:{port}\"]\nfps = 30.0\nimage_sizes_px = [[640, 480], [640, 480]]\n"
        );
        let board_cfg = format!(
            "[params]\ntrusted_keys = [{pub_file:?}]\n[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n\
             [source.sim]\nfps = 30.0\nwall_clock = true\n\
             [cluster]\nrole = \"camera\"\nrig = \"rt\"\nboard = \"b0\"\nconnect = [\"tcp/127.0.0.1:{port}\"]\nfps = 30.0\n"
        );
        let keys = dir.path().join("keys");
        irtrack_cluster::credentials::write_new_credentials(&keys, &["b0"], false).unwrap();
        let password = std::fs::read(irtrack_cluster::credentials::password_path(&keys, "b0")).unwrap();
        let dictionary = std::fs::read(irtrack_cluster::credentials::dictionary_path(&keys)).unwrap();
        let mut cell = PushCell {
            dir,
            port,
            pc,
            solver_cfg,
            board_cfg,
            solver_key: [0; 32],
            board_key: [0; 32],
            password,
            dictionary,
        };
        let (solver, board) = cell.spawn();
        let key_of = |st: &serde_json::Value| {
            irtrack_cluster::envelope::parse_key_hex(
                st["cluster"]["box_public_key"]
                    .as_str()
                    .unwrap_or_else(|| panic!("{st}")),
            )
            .unwrap()
        };
        cell.solver_key = key_of(&status_now(solver.status));
        cell.board_key = key_of(&status_now(board.status));
        (cell, solver, board)
    }

    /// Starts (again) both irtrackd processes: solver, board.
    fn spawn(&self) -> (Irtrackd, Irtrackd) {
        (
            spawn_irtrackd(self.dir.path(), "solver", &self.solver_cfg),
            spawn_irtrackd(self.dir.path(), "board", &self.board_cfg),
        )
    }

    /// An envelope of `kind` for `board`, sealed to `recipient`, signed by `signer`.
    fn seal_by(
        kind: irtrack_cluster::envelope::SecretKind,
        board: &str,
        serial: u64,
        recipient: [u8; 32],
        plaintext: &[u8],
        signer: &irtrack_core::signing::SigningKey,
    ) -> Vec<u8> {
        irtrack_cluster::envelope::seal(
            &irtrack_cluster::envelope::Sealing {
                kind,
                board,
                serial,
                created_unix_s: 1_795_000_000,
                recipient,
                plaintext,
            },
            signer,
        )
        .unwrap()
    }

    /// The same, signed by the PC key both trust.
    fn seal(
        &self,
        kind: irtrack_cluster::envelope::SecretKind,
        board: &str,
        serial: u64,
        recipient: [u8; 32],
        plaintext: &[u8],
    ) -> Vec<u8> {
        Self::seal_by(kind, board, serial, recipient, plaintext, &self.pc)
    }
}

/// Issue 40, item 4: "keys pushed like parameter sets". A solver and a camera board start
/// without credentials (each makes its key pair); the test seals b0's password to b0's key
/// and the dictionary to the solver's key, signs both with the PC key they trust, and pushes
/// them through their parameter ports. Refused over the same sockets: a replay, an envelope
/// for the other board, one signed by an untrusted key. After a restart both use the pushed
/// credentials: the board is heard by the solver, and a peer without credentials is refused.
#[test]
fn pushed_credentials_let_the_board_in_after_a_restart() {
    use irtrack_cluster::envelope::SecretKind;
    let (cell, solver, board) = PushCell::start("cluster-auth-push");
    let (solver_key, board_key, port) = (cell.solver_key, cell.board_key, cell.port);
    let (password, dictionary) = (cell.password.clone(), cell.dictionary.clone());
    assert_ne!(solver_key, board_key);
    let to_board = cell.seal(SecretKind::BoardPassword, "b0", 5, board_key, &password);
    let to_solver = cell.seal(SecretKind::SolverDictionary, "s0", 5, solver_key, &dictionary);
    // Refused before anything is stored: signed by a key neither trusts; b0's envelope at
    // the solver (sealed to b0's key).
    let stranger = irtrack_core::signing::SigningKey::from_bytes(&[0x43; 32]);
    let forged = PushCell::seal_by(
        SecretKind::BoardPassword,
        "b0",
        6,
        board_key,
        &password,
        &stranger,
    );
    let v = push_now(board.params, &forged);
    assert!(
        v.starts_with("ERR UNAUTHORIZED") && v.contains("does not trust"),
        "{v}"
    );
    let v = push_now(solver.params, &to_board);
    assert!(
        v.starts_with("ERR RIG_MISMATCH") && v.contains("sealed to key"),
        "{v}"
    );
    // Accepted, then the same envelope again is a replay.
    assert_eq!(push_now(board.params, &to_board).trim(), "OK credentials-b0-5");
    assert_eq!(push_now(solver.params, &to_solver).trim(), "OK credentials-s0-5");
    let v = push_now(board.params, &to_board);
    assert!(
        v.starts_with("ERR ROLLBACK") && v.contains("replayed or older"),
        "{v}"
    );
    let st = status_now(board.status);
    let pushed = &st["cluster"]["pushed_credentials"];
    assert_eq!(pushed["serial"], 5, "{pushed}");
    assert_eq!(pushed["in_use"], false, "{pushed}");
    assert!(
        pushed["words"]
            .as_str()
            .unwrap()
            .contains("takes effect at the next start"),
        "{pushed}"
    );
    // The secret is stored mode 0600, and the envelope never carried it in clear.
    use std::os::unix::fs::PermissionsExt;
    let stored = cell
        .dir
        .path()
        .join("board-state/cluster-credentials/board.password");
    assert_eq!(
        std::fs::metadata(&stored).unwrap().permissions().mode() & 0o777,
        0o600
    );
    assert_eq!(std::fs::read(&stored).unwrap(), password);
    assert!(!to_board.windows(16).any(|w| w == &password[..16]));

    // Restart both: they take the pushed credentials; the board is heard by the solver.
    drop(board);
    drop(solver);
    let (solver, board) = cell.spawn();
    let outsider = own_address("127.0.0.66");
    let _anon = connect_from(port, Some(outsider.as_str()), Auth::None);
    let t0 = Instant::now();
    let (mut received, mut refused) = (0, false);
    while t0.elapsed() < Duration::from_secs(10) && (received < 30 || !refused) {
        std::thread::sleep(Duration::from_millis(200));
        let st = status_now(solver.status);
        received = st["cluster"]["received"].as_u64().unwrap_or(0);
        refused = st["cluster"]["refused_peers"]["recent"]
            .as_array()
            .is_some_and(|a| a.iter().any(|e| e["address"].as_str() == Some(outsider.as_str())));
    }
    let st = status_now(solver.status);
    assert!(
        received >= 30,
        "the board was not heard with its pushed password: {}",
        st["cluster"]
    );
    assert!(
        refused,
        "a peer without credentials was not refused: {}",
        st["cluster"]["refused_peers"]
    );
    assert_eq!(
        st["cluster"]["pushed_credentials"]["in_use"], true,
        "{}",
        st["cluster"]
    );
    let bst = status_now(board.status);
    assert_eq!(
        bst["cluster"]["pushed_credentials"]["in_use"], true,
        "{}",
        bst["cluster"]
    );
    eprintln!(
        "after the restart the solver received {received} observations from b0 with its pushed password"
    );
}

/// TLS pushed like the passwords: the board gets the solver's certificate to pin, the solver
/// its certificate and key; after a restart the board reaches the solver only through TLS,
/// both say so on `/status`, and a peer without TLS is refused with its address.
#[test]
fn pushed_tls_files_make_the_solver_prove_itself_after_a_restart() {
    use irtrack_cluster::envelope::SecretKind;
    let (cell, solver, board) = PushCell::start("cluster-auth-tls");
    let (solver_key, board_key, port) = (cell.solver_key, cell.board_key, cell.port);
    let (password, dictionary) = (cell.password.clone(), cell.dictionary.clone());
    // The solver's identity as `cluster-keys --tls` makes it.
    let tls_key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec![irtrack_cluster::names::SOLVER_TLS_NAME.to_string()])
        .unwrap()
        .self_signed(&tls_key)
        .unwrap()
        .pem();
    let identity = format!("{cert}{}", tls_key.serialize_pem());
    let seal = |kind, board: &str, serial, recipient, plaintext: &[u8]| {
        cell.seal(kind, board, serial, recipient, plaintext)
    };
    // The solver's key never goes to a board: not as the solver's identity (the wrong kind
    // for a camera board), nor inside the certificate to pin.
    let v = push_now(
        board.params,
        &seal(SecretKind::SolverTls, "b0", 4, board_key, identity.as_bytes()),
    );
    assert!(
        v.starts_with("ERR RIG_MISMATCH") && v.contains("takes board password or"),
        "{v}"
    );
    let v = push_now(
        board.params,
        &seal(
            SecretKind::PinnedSolverCertificate,
            "b0",
            4,
            board_key,
            identity.as_bytes(),
        ),
    );
    assert!(
        v.starts_with("ERR INVALID_PARAMS") && v.contains("holds a private key"),
        "{v}"
    );
    for (to, name, key, kind, serial, text) in [
        (
            board.params,
            "b0",
            board_key,
            SecretKind::BoardPassword,
            5,
            password.as_slice(),
        ),
        (
            board.params,
            "b0",
            board_key,
            SecretKind::PinnedSolverCertificate,
            6,
            cert.as_bytes(),
        ),
        (
            solver.params,
            "s0",
            solver_key,
            SecretKind::SolverDictionary,
            5,
            dictionary.as_slice(),
        ),
        (
            solver.params,
            "s0",
            solver_key,
            SecretKind::SolverTls,
            6,
            identity.as_bytes(),
        ),
    ] {
        assert_eq!(
            push_now(to, &seal(kind, name, serial, key, text)).trim(),
            format!("OK credentials-{name}-{serial}"),
            "{}",
            kind.words()
        );
    }

    drop(board);
    drop(solver);
    let (solver, board) = cell.spawn();
    // A peer with b0's own password but no TLS, from an address of its own.
    let outsider = own_address("127.0.0.67");
    let b0_password = String::from_utf8(password.clone()).unwrap();
    let _plain = connect_from(
        port,
        Some(outsider.as_str()),
        board_auth("b0", b0_password.trim()),
    );
    let t0 = Instant::now();
    let (mut received, mut refused) = (0, None);
    while t0.elapsed() < Duration::from_secs(10) && (received < 30 || refused.is_none()) {
        std::thread::sleep(Duration::from_millis(200));
        let st = status_now(solver.status);
        received = st["cluster"]["received"].as_u64().unwrap_or(0);
        refused = st["cluster"]["refused_peers"]["recent"].as_array().and_then(|a| {
            a.iter()
                .find(|e| e["address"].as_str() == Some(outsider.as_str()))
                .cloned()
        });
    }
    let st = status_now(solver.status);
    assert!(
        received >= 30,
        "the board was not heard through TLS: {}",
        st["cluster"]
    );
    let refused = refused.unwrap_or_else(|| {
        panic!(
            "the peer without TLS was not refused: {}",
            st["cluster"]["refused_peers"]
        )
    });
    assert_eq!(refused["reason"], "tls", "{refused}");
    assert_eq!(st["cluster"]["tls"]["side"], "solver", "{}", st["cluster"]);
    assert_eq!(
        st["cluster"]["refused_peers"]["by_reason"]["tls"]
            .as_u64()
            .map(|n| n >= 1),
        Some(true),
        "{}",
        st["cluster"]["refused_peers"]
    );
    let bst = status_now(board.status);
    let tls = &bst["cluster"]["tls"];
    assert_eq!(tls["side"], "board", "{}", bst["cluster"]);
    assert!(tls["carried"].as_u64().is_some_and(|n| n >= 1), "{tls}");
    assert_eq!(tls["solver_refused"], 0, "{tls}");
    assert!(
        tls["certificate_file"]
            .as_str()
            .is_some_and(|f| f.ends_with("cluster-credentials/solver.tls.crt")),
        "{tls}"
    );
    eprintln!("through pushed TLS: the solver received {received}; refused without TLS: {refused}");
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

    // TLS: the files load, the keys fit the role, and they come with credentials.
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["irtrack-solver".to_string()])
        .unwrap()
        .self_signed(&key)
        .unwrap();
    let (crt, kf) = (
        dir.path().join("solver.tls.crt"),
        dir.path().join("solver.tls.key"),
    );
    std::fs::write(&crt, cert.pem()).unwrap();
    std::fs::write(&kf, key.serialize_pem()).unwrap();
    let tls_solver = format!("{solver}tls_certificate_file = {crt:?}\ntls_key_file = {kf:?}\n");
    let c = Config::from_toml(&tls_solver, "t").unwrap();
    let line = c.cluster.auth_summary().unwrap();
    assert!(
        line.contains("TLS: proves itself with") && line.contains("solver.tls.crt"),
        "{line}"
    );
    let e = err(&format!("{solver}tls_certificate_file = {crt:?}\n"));
    assert!(
        e.contains("tls_certificate_file and tls_key_file go together"),
        "{e}"
    );
    let e = err(&tls_solver.replace(&format!("credentials_file = {dict:?}\n"), ""));
    assert!(e.contains("TLS needs credentials too"), "{e}");
    // A key that is not the certificate's; a certificate file that is not PEM: named.
    let other = rcgen::KeyPair::generate().unwrap();
    let other_file = dir.path().join("other.key");
    std::fs::write(&other_file, other.serialize_pem()).unwrap();
    let e = err(&format!(
        "{solver}tls_certificate_file = {crt:?}\ntls_key_file = {other_file:?}\n"
    ));
    assert!(e.contains("other.key") && e.contains("does not go with"), "{e}");
    let e = err(&format!(
        "{solver}tls_certificate_file = {pw:?}\ntls_key_file = {kf:?}\n"
    ));
    assert!(e.contains("b0.password") && e.contains("no certificate"), "{e}");
    // A board pins the certificate; the solver's keys are not a board's.
    std::fs::write(&pw, format!("{PW0}\n")).unwrap();
    let c = Config::from_toml(
        &camera(&format!("{with_pw}tls_solver_certificate_file = {crt:?}\n")),
        "t",
    )
    .unwrap();
    let line = c.cluster.auth_summary().unwrap();
    assert!(
        line.contains("talks only to the solver that proves itself with"),
        "{line}"
    );
    let e = err(&camera(&format!(
        "{with_pw}tls_certificate_file = {crt:?}\ntls_key_file = {kf:?}\n"
    )));
    assert!(
        e.contains("a camera board takes tls_solver_certificate_file"),
        "{e}"
    );
    let e = err(&camera(&format!(
        "connect = [\"tcp/127.0.0.1:7447\"]\ntls_solver_certificate_file = {crt:?}\n"
    )));
    assert!(e.contains("TLS needs credentials too"), "{e}");
    let e = err(&camera(&format!(
        "{with_pw}tls_solver_certificate_file = {pw:?}\n"
    )));
    assert!(e.contains("no certificate"), "{e}");
}
