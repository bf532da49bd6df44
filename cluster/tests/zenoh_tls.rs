//! TLS between camera boards and the solver over real Zenoh sessions on 127.0.0.1
//! (docs/cluster.md, "TLS"): a board talks only to the solver that proves itself with the
//! pinned certificate, the bytes on the wire are encrypted, a peer without TLS is refused and
//! counted with its address, and a flood of failing handshakes does not keep a board out.
#![cfg(feature = "zenoh")]

mod common;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::{blob, free_port, header};
use irtrack_cluster::credentials::{BoardCredential, dictionary_text};
use irtrack_cluster::refusals::{RefusalReason, global};
use irtrack_cluster::tls::{SOLVER_NAME, TlsRole, board_log};
use irtrack_cluster::transport::{
    Auth, ObsPublisher, ObsSubscriber, Received, Session, TransportConfig, realtime_ns,
};
use irtrack_core::observation::decode;

const PW0: &str = "b0-secret-4Kq9zT2wXn7Lp3Rv";

/// The tests that read the board-side log (one per process) one at a time.
static BOARD_LOG: Mutex<()> = Mutex::new(());

fn temp_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("irtrack-ztls-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A self-signed certificate for the solver's name, as `cluster-keys --tls` makes one:
/// (certificate file, key file).
fn identity(dir: &Path, name: &str) -> (PathBuf, PathBuf) {
    let key = rcgen::KeyPair::generate().unwrap();
    let params = rcgen::CertificateParams::new(vec![SOLVER_NAME.to_string()]).unwrap();
    let cert = params.self_signed(&key).unwrap();
    let (c, k) = (dir.join(format!("{name}.crt")), dir.join(format!("{name}.key")));
    std::fs::write(&c, cert.pem()).unwrap();
    std::fs::write(&k, key.serialize_pem()).unwrap();
    (c, k)
}

fn dictionary(dir: &Path) -> PathBuf {
    let dict = dir.join("solver.dict");
    let text = dictionary_text(&[BoardCredential {
        board: "b0".into(),
        password: PW0.into(),
    }]);
    std::fs::write(&dict, text).unwrap();
    dict
}

/// A solver with TLS (`cert`, `key`) on `port`, subscribed to rig cell1.
fn solver(dir: &Path, port: u16, cert: &Path, key: &Path) -> (Session, ObsSubscriber, Receiver<Received>) {
    let (auth, _) = Auth::solver_from_file("cell1", &dictionary(dir)).unwrap();
    let s = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        auth,
        tls: Some(TlsRole::Solver {
            certificate_file: cert.to_path_buf(),
            key_file: key.to_path_buf(),
        }),
        ..TransportConfig::default()
    })
    .unwrap();
    let (sub, rx) = ObsSubscriber::new(&s, "cell1", 4096, realtime_ns).unwrap();
    (s, sub, rx)
}

fn b0_auth() -> Auth {
    Auth::Board {
        board: "b0".into(),
        password: PW0.into(),
    }
}

/// Board b0 connecting to `port`, pinning `pinned` (no TLS when `None`).
fn board(port: u16, pinned: Option<&Path>) -> Session {
    Session::open(&TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        auth: b0_auth(),
        tls: pinned.map(|p| TlsRole::Board {
            solver_certificate_file: p.to_path_buf(),
        }),
        ..TransportConfig::default()
    })
    .unwrap()
}

/// Publishes from `board` every 2 ms, sequences from `base` on, until `want` of them arrived
/// or `limit` passed; returns how many arrived, and when the first did (from the start).
/// Others still on their way (an earlier sender's) are not counted.
fn deliver(
    board: &Session,
    rx: &Receiver<Received>,
    base: u64,
    want: usize,
    limit: Duration,
) -> (usize, Option<Duration>) {
    let mut p = ObsPublisher::new(board, "cell1", "b0", 0).unwrap();
    let start = Instant::now();
    let (mut got, mut first) = (0usize, None);
    let mut seq = base;
    while got < want && start.elapsed() < limit {
        seq += 1;
        p.publish(&header("cell1", "b0", 0, seq), &[blob()]).unwrap();
        std::thread::sleep(Duration::from_millis(2));
        while let Ok(m) = rx.try_recv() {
            let obs = decode(m.payload()).unwrap();
            assert_eq!(obs.header.board, "b0");
            if (base..base + 1_000_000).contains(&obs.header.sequence) {
                got += 1;
                first.get_or_insert(start.elapsed());
            }
        }
    }
    (got, first)
}

/// A TCP relay from a port of its own to `to`, keeping what the board side sent: a
/// listener on the wire between board and solver.
fn wire_tap(to: u16) -> (u16, Arc<Mutex<Vec<u8>>>) {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    let seen = Arc::new(Mutex::new(Vec::new()));
    let s2 = seen.clone();
    std::thread::spawn(move || {
        for c in l.incoming().take(16) {
            let Ok(mut down) = c else { continue };
            let Ok(mut up) = TcpStream::connect(("127.0.0.1", to)) else {
                continue;
            };
            let (mut down2, mut up2) = (down.try_clone().unwrap(), up.try_clone().unwrap());
            let seen = s2.clone();
            std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                while let Ok(n) = down.read(&mut buf) {
                    if n == 0 || up.write_all(&buf[..n]).is_err() {
                        break;
                    }
                    if let Ok(mut s) = seen.lock()
                        && s.len() < 1 << 20
                    {
                        s.extend_from_slice(&buf[..n]);
                    }
                }
            });
            std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                while let Ok(n) = up2.read(&mut buf) {
                    if n == 0 || down2.write_all(&buf[..n]).is_err() {
                        break;
                    }
                }
            });
        }
    });
    (port, seen)
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

#[test]
fn a_board_talks_only_to_the_solver_that_proves_itself_and_nothing_is_readable_on_the_wire() {
    let _one_at_a_time = BOARD_LOG.lock().unwrap_or_else(|e| e.into_inner());
    let dir = temp_dir("prove");
    let (cert, key) = identity(&dir, "solver");
    let (impostor_cert, impostor_key) = identity(&dir, "impostor");

    // The genuine solver, reached through a tap that keeps what the board sends.
    let port = free_port();
    let (solver_s, _sub, rx) = solver(&dir, port, &cert, &key);
    let (tap_port, seen) = wire_tap(port);
    let b0 = board(tap_port, Some(&cert));
    let (got, first) = deliver(&b0, &rx, 0, 50, Duration::from_secs(15));
    assert!(
        got >= 50,
        "the board pinning the solver's certificate delivered {got} of 50"
    );
    eprintln!("through TLS: first observation after {first:?}");
    let wire = seen.lock().unwrap().clone();
    assert!(wire.len() > 1000, "the tap saw {} bytes", wire.len());
    for plain in [&b"irtrack/cell1"[..], b"cell1", b"b0"] {
        assert!(
            !contains(&wire, plain),
            "{:?} readable on the wire through TLS",
            String::from_utf8_lossy(plain)
        );
    }
    b0.close();

    // The same check can fail: without TLS the tap reads the key expression.
    let plain_port = free_port();
    let (dict_auth, _) = Auth::solver_from_file("cell1", &dictionary(&dir)).unwrap();
    let plain_solver = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{plain_port}")],
        auth: dict_auth,
        ..TransportConfig::default()
    })
    .unwrap();
    let (_psub, prx) = ObsSubscriber::new(&plain_solver, "cell1", 4096, realtime_ns).unwrap();
    let (ptap, pseen) = wire_tap(plain_port);
    let pb0 = board(ptap, None);
    let (pgot, _) = deliver(&pb0, &prx, 1_000_000, 20, Duration::from_secs(15));
    assert!(pgot >= 20, "{pgot}");
    assert!(
        contains(&pseen.lock().unwrap(), b"cell1"),
        "without TLS the key expression is readable on the wire"
    );
    pb0.close();
    plain_solver.close();

    // An impostor at the solver's address, with its own certificate for the same name and
    // even the boards' dictionary: the board refuses it and sends it nothing.
    let before = board_log().snapshot();
    let iport = free_port();
    let (impostor, _isub, irx) = solver(&dir, iport, &impostor_cert, &impostor_key);
    let fooled = board(iport, Some(&cert));
    let (igot, _) = deliver(&fooled, &irx, 2_000_000, 1, Duration::from_secs(4));
    assert_eq!(igot, 0, "the impostor received observations");
    let after = board_log().snapshot();
    assert!(
        after.solver_refused > before.solver_refused,
        "the board did not count the impostor: {after:?}"
    );
    let (words, age) = after.last_problem.clone().unwrap();
    assert!(
        words.contains(&format!(
            "the peer at 127.0.0.1:{iport} did not prove itself as this cell's solver"
        )) && words.contains("invalid peer certificate"),
        "{words}"
    );
    assert!(age < 5.0, "{age}");
    fooled.close();
    impostor.close();

    // A peer without TLS at the solver's TLS port: refused before Zenoh, counted with its
    // address; and it delivers nothing.
    let before = global().snapshot().by_reason[3].1;
    let no_tls = board(port, None);
    let (ngot, _) = deliver(&no_tls, &rx, 3_000_000, 1, Duration::from_secs(3));
    assert_eq!(ngot, 0, "a peer without TLS reached the solver");
    let snap = global().snapshot();
    assert_eq!(snap.by_reason[3].0, RefusalReason::Tls);
    assert!(snap.by_reason[3].1 > before, "{snap:?}");
    let p = snap
        .recent
        .iter()
        .find(|p| p.reason == RefusalReason::Tls)
        .unwrap();
    assert!(
        p.address.as_deref().is_some_and(|a| a.starts_with("127.0.0.1:")),
        "{p:?}"
    );
    no_tls.close();
    solver_s.close();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Zenoh's own TLS listener pauses 100 ms after each failed handshake, so 10 a second shut
/// every board out; the tunnel never pauses. A host opening idle connections and sending
/// garbage handshakes as fast as it can (four threads), starting a second before board b0:
/// b0 is in within seconds.
#[test]
fn a_flood_of_failing_handshakes_does_not_keep_a_board_out() {
    let dir = temp_dir("flood");
    let (cert, key) = identity(&dir, "solver");
    let port = free_port();
    let (solver_s, _sub, rx) = solver(&dir, port, &cert, &key);
    let stop = Arc::new(AtomicBool::new(false));
    let mut flooders = Vec::new();
    let sent = Arc::new(std::sync::atomic::AtomicU64::new(0));
    for _ in 0..4 {
        let (stop, sent) = (stop.clone(), sent.clone());
        flooders.push(std::thread::spawn(move || {
            let mut idle = Vec::new();
            let t0 = Instant::now();
            // Bounded: at most 20 s and 20,000 connections per thread.
            for i in 0..20_000u32 {
                if stop.load(Ordering::Relaxed) || t0.elapsed() > Duration::from_secs(20) {
                    break;
                }
                let Ok(mut c) = TcpStream::connect(("127.0.0.1", port)) else {
                    continue;
                };
                if i % 2 == 0 {
                    // Not a TLS record: the handshake fails at once.
                    let _ = c.write_all(b"GET / HTTP/1.0\r\n\r\n");
                    sent.fetch_add(1, Ordering::Relaxed);
                } else {
                    // Silent: holds a handshake slot until the timeout.
                    idle.push(c);
                    if idle.len() > 100 {
                        idle.remove(0);
                    }
                }
            }
        }));
    }
    std::thread::sleep(Duration::from_millis(1000));
    let before_board = sent.load(Ordering::Relaxed);
    let start = Instant::now();
    let b0 = board(port, Some(&cert));
    let opened = start.elapsed();
    let (got, first) = deliver(&b0, &rx, 0, 10, Duration::from_secs(15));
    let first = first.map(|f| f + opened);
    let took = start.elapsed();
    stop.store(true, Ordering::Relaxed);
    for f in flooders {
        f.join().unwrap();
    }
    let tls_refused = global().snapshot().by_reason[3].1;
    eprintln!(
        "during the flood ({before_board} garbage handshakes in the second before the board started, {} in all, {tls_refused} counted): first observation {first:?} after the board's start, 10 in {took:?}",
        sent.load(Ordering::Relaxed)
    );
    assert!(got >= 10, "the board delivered {got} of 10 during the flood");
    // At least three times what stops Zenoh's own TLS listener (10 failures a second). The
    // debug build's tunnel accepts a few hundred a second here; beyond that the kernel's
    // accept queue drops connections and the flooders wait on their SYN retries.
    assert!(
        before_board >= 30,
        "the flood sent only {before_board} bad handshakes in its first second"
    );
    assert!(
        first.is_some_and(|f| f < Duration::from_secs(3)),
        "the board's first observation came {first:?} after its start"
    );
    assert!(tls_refused >= 100, "only {tls_refused} failed handshakes counted");
    b0.close();
    solver_s.close();
    let _ = std::fs::remove_dir_all(&dir);
}

/// Python's `ssl` module (OpenSSL), run as a separate process (tests/python/tls_peer.py), on
/// each side of the tunnels: as a board it completes TLS 1.3 with the solver's tunnel when it
/// trusts the solver's certificate and fails when it trusts another; as a solver with the
/// solver's own certificate and key it gets the board's Zenoh bytes, decrypted, and as an
/// impostor with its own certificate it gets no handshake from the board.
#[test]
fn an_independent_tls_stack_meets_the_tunnels() {
    let _one_at_a_time = BOARD_LOG.lock().unwrap_or_else(|e| e.into_inner());
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/tls_peer.py");
    let dir = temp_dir("openssl");
    let (cert, key) = identity(&dir, "solver");
    let (impostor_cert, impostor_key) = identity(&dir, "impostor");
    let port = free_port();
    let (solver_s, _sub, _rx) = solver(&dir, port, &cert, &key);
    let client = |trusted: &Path| {
        let o = std::process::Command::new("python3")
            .args([script, "client", &port.to_string(), trusted.to_str().unwrap()])
            .output()
            .expect("python3");
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    let ok = client(&cert);
    assert!(ok.contains("\"ok\": true") && ok.contains("TLSv1.3"), "{ok}");
    let refused = client(&impostor_cert);
    assert!(
        refused.contains("\"ok\": false") && refused.contains("CERTIFICATE_VERIFY_FAILED"),
        "{refused}"
    );
    eprintln!(
        "OpenSSL as a board: {}; trusting another certificate: {}",
        ok.trim(),
        refused.trim()
    );

    for (c, k, genuine) in [(&cert, &key, true), (&impostor_cert, &impostor_key, false)] {
        use std::io::BufRead;
        let sport = free_port();
        let mut child = std::process::Command::new("python3")
            .args([
                script,
                "server",
                &sport.to_string(),
                c.to_str().unwrap(),
                k.to_str().unwrap(),
                "3",
            ])
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("python3");
        let mut lines = std::io::BufReader::new(child.stdout.take().unwrap()).lines();
        assert_eq!(lines.next().unwrap().unwrap(), "listening");
        let before = board_log().snapshot();
        let b0 = board(sport, Some(&cert));
        let report = lines.next().unwrap().unwrap();
        child.wait().unwrap();
        let after = board_log().snapshot();
        b0.close();
        let v: serde_json::Value = serde_json::from_str(&report).unwrap();
        eprintln!(
            "OpenSSL as the solver ({}): {report}",
            if genuine {
                "its certificate"
            } else {
                "an impostor's"
            }
        );
        if genuine {
            assert!(
                v["handshakes"].as_u64() >= Some(1) && v["bytes"].as_u64() > Some(0),
                "{report}"
            );
            assert!(after.carried > before.carried, "{after:?}");
        } else {
            assert_eq!(v["handshakes"], 0, "{report}");
            assert!(v["failed"].as_u64() >= Some(1), "{report}");
            assert!(after.solver_refused > before.solver_refused, "{after:?}");
        }
    }
    solver_s.close();
    let _ = std::fs::remove_dir_all(&dir);
}
