//! The refusal counter against real Zenoh sessions on loopback (docs/cluster.md, "Refused
//! peers"): a solver with a dictionary and, each from an address of its own (`#bind=` on the
//! connect endpoint), a peer without credentials, one claiming board b1 with b0's password,
//! one with a user name the dictionary does not list, a genuine board, and a TCP connection
//! that never speaks. The layer must count each refusal with the address it came from, the
//! genuine board not at all. This is what fails when a Zenoh upgrade changes the events the
//! layer recognises (refusals.rs): counting zero would pass silently otherwise.
#![cfg(feature = "zenoh")]

mod common;

use std::time::{Duration, Instant};

use irtrack_cluster::credentials::{BoardCredential, dictionary_text};
use irtrack_cluster::refusals::{
    self, CredentialProblem, RefusalReason, RefusalSnapshot, ZENOH_TRANSPORT_VERSION, ZENOH_VERSION,
};
use irtrack_cluster::transport::{Auth, ObsPublisher, ObsSubscriber, Session, TransportConfig, realtime_ns};
use irtrack_core::observation::ObsHeader;
use tracing_subscriber::layer::SubscriberExt;

const PW0: &str = "b0-secret-4Kq9zT2wXn7Lp3Rv";
const PW1: &str = "b1-secret-8Hd5sY6cMa1Qe0Uf";

/// A free TCP port on `ip` (any loopback address works on Linux).
fn free_port_on(ip: &str) -> u16 {
    std::net::TcpListener::bind((ip, 0))
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Opens a peer connecting to the solver from `from` (`ip:port`); a refused peer may fail to
/// open or open without a link, which is the same here.
fn peer(port: u16, from: &str, auth: Auth) -> Option<Session> {
    Session::open(&TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}#bind={from}")],
        auth,
        ..TransportConfig::default()
    })
    .ok()
}

fn board(name: &str, password: &str) -> Auth {
    Auth::Board {
        board: name.into(),
        password: password.into(),
    }
}

fn refused<'a>(s: &'a RefusalSnapshot, addr: &str) -> Option<&'a refusals::RefusedPeer> {
    s.recent.iter().find(|p| p.address.as_deref() == Some(addr))
}

#[test]
fn the_lock_file_pins_the_zenoh_transport_whose_events_are_recognised() {
    let lock = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../Cargo.lock")).unwrap();
    let locked = |name: &str| {
        lock.split("[[package]]")
            .find(|p| p.contains(&format!("name = \"{name}\"\n")))
            .and_then(|p| p.lines().find_map(|l| l.strip_prefix("version = ")))
            .map(|v| v.trim_matches('"').to_string())
    };
    assert_eq!(
        locked("zenoh").as_deref(),
        Some(ZENOH_VERSION),
        "cluster/src/refusals.rs recognises zenoh {ZENOH_VERSION}'s access-control events: read the new version's net/routing/interceptor/access_control.rs, update classify() and ZENOH_VERSION"
    );
    let version = locked("zenoh-transport");
    assert_eq!(
        version.as_deref(),
        Some(ZENOH_TRANSPORT_VERSION),
        "cluster/src/refusals.rs recognises zenoh-transport {ZENOH_TRANSPORT_VERSION}'s accept events: read the new version's unicast/establishment/accept.rs, unicast/manager.rs and ext/auth/usrpwd.rs, update classify() and ZENOH_TRANSPORT_VERSION"
    );
}

#[test]
fn refused_peers_are_counted_with_their_address() {
    tracing::subscriber::set_global_default(tracing_subscriber::registry().with(refusals::refusal_layer()))
        .expect("the only subscriber of this test binary");
    let log = refusals::global();
    assert!(log.counting());

    let dir = std::env::temp_dir().join(format!("irtrack-zrefusals-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let dict = dir.join("solver.dict");
    std::fs::write(
        &dict,
        dictionary_text(&[
            BoardCredential {
                board: "b0".into(),
                password: PW0.into(),
            },
            BoardCredential {
                board: "b1".into(),
                password: PW1.into(),
            },
        ]),
    )
    .unwrap();
    let port = free_port_on("127.0.0.1");
    let (auth, _) = Auth::solver_from_file("cell1", &dict).unwrap();
    let solver = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        auth,
        ..TransportConfig::default()
    })
    .unwrap();
    let (_sub, rx) = ObsSubscriber::new(&solver, "cell1", 64, realtime_ns).unwrap();

    let anon = format!("127.0.0.66:{}", free_port_on("127.0.0.66"));
    let wrong = format!("127.0.0.67:{}", free_port_on("127.0.0.67"));
    let stranger = format!("127.0.0.68:{}", free_port_on("127.0.0.68"));
    let genuine = format!("127.0.0.69:{}", free_port_on("127.0.0.69"));
    let t0 = Instant::now();
    let p_anon = peer(port, &anon, Auth::None);
    let p_wrong = peer(port, &wrong, board("b1", PW0));
    let p_stranger = peer(port, &stranger, board("b9", PW1));
    let p_genuine = peer(port, &genuine, board("b0", PW0)).expect("the genuine board opens");
    // Board b1 with its own, valid credentials, publishing under b0's name: let in, and each
    // put dropped by the access control, counted as a denied publication.
    let impostor_addr = format!("127.0.0.71:{}", free_port_on("127.0.0.71"));
    let p_impostor = peer(port, &impostor_addr, board("b1", PW1)).expect("b1 opens with its own credentials");
    let mut impostor = ObsPublisher::new(&p_impostor, "cell1", "b0", 1).unwrap();
    // A connection that never speaks: refused when Zenoh's 1 s handshake time runs out.
    let silent = silent_connect("127.0.0.70", port);

    // The genuine board is heard: the solver's authentication works in this run.
    let mut publ = ObsPublisher::new(&p_genuine, "cell1", "b0", 0).unwrap();
    let header = |seq| common::header("cell1", "b0", 0, seq);
    let mut heard = false;
    let mut snap = log.snapshot();
    let deadline = t0 + Duration::from_secs(8);
    let done = |s: &RefusalSnapshot| {
        [&anon, &wrong, &stranger].iter().all(|a| refused(s, a).is_some())
            && s.by_reason[1].1 >= 1
            && s.denied_publications >= 10
    };
    let mut seq = 0;
    let mut forged = 0u64;
    let mut forged_heard = 0u64;
    while Instant::now() < deadline && !(heard && done(&snap)) {
        seq += 1;
        publ.publish(&header(seq), &[]).unwrap();
        impostor
            .publish(
                &ObsHeader {
                    camera: 1,
                    ..header(seq)
                },
                &[],
            )
            .unwrap();
        forged += 1;
        while let Ok(obs) = rx.try_recv() {
            heard = true;
            let camera = irtrack_core::observation::decode(obs.payload()).map(|o| o.header.camera);
            forged_heard += u64::from(camera.ok() == Some(1));
        }
        std::thread::sleep(Duration::from_millis(50));
        snap = log.snapshot();
    }
    drop(silent);
    eprintln!("after {:.1} s: {snap:#?}", t0.elapsed().as_secs_f64());
    assert!(heard, "the genuine board b0 was not heard");
    let check = |addr: &str, problem: CredentialProblem| {
        let p = refused(&snap, addr).unwrap_or_else(|| panic!("no refusal from {addr}: {snap:#?}"));
        assert_eq!(p.reason, RefusalReason::Credentials, "{p:?}");
        assert_eq!(p.problem, Some(problem), "{p:?}");
        assert!(p.count >= 1);
        let words = p.words();
        assert!(
            words.starts_with(&format!(
                "a peer at {addr} was refused: wrong or missing credentials"
            )),
            "{words}"
        );
    };
    check(&anon, CredentialProblem::Missing);
    check(&wrong, CredentialProblem::WrongPassword);
    check(&stranger, CredentialProblem::UnknownUser);
    assert!(
        refused(&snap, &genuine).is_none(),
        "the genuine board was counted: {snap:#?}"
    );
    let credentials = snap.by_reason[0];
    assert_eq!(credentials.0, RefusalReason::Credentials);
    assert!(credentials.1 >= 3, "{snap:#?}");
    assert!(
        snap.by_reason[1].1 >= 1,
        "the silent connection's timeout: {snap:#?}"
    );
    // The impostor's puts: none reached the subscriber, each was counted once, under b1's
    // name on b0's key; nothing of the genuine board (whose prefix declaration Zenoh also
    // decides "denied" for a put that never comes).
    assert_eq!(forged_heard, 0, "a forged observation reached the solver");
    assert!(
        snap.denied_publications >= 10 && snap.denied_publications <= forged,
        "{} denied of {forged} forged: {snap:#?}",
        snap.denied_publications
    );
    let denied = snap
        .denied_recent
        .iter()
        .find(|d| d.key == "irtrack/cell1/b0/cam/1/obs")
        .unwrap_or_else(|| panic!("no denial on b0's camera 1: {snap:#?}"));
    assert_eq!(denied.user(), Some("b1"), "{denied:?}");
    let words = denied.words();
    assert!(
        words.starts_with("a peer signed in as b1 (Zenoh ID ")
            && words.contains("published on irtrack/cell1/b0/cam/1/obs, which its credentials do not allow"),
        "{words}"
    );
    assert!(
        snap.denied_recent
            .iter()
            .all(|d| d.key == "irtrack/cell1/b0/cam/1/obs" && d.user() == Some("b1")),
        "only the impostor's puts: {snap:#?}"
    );

    // The clock probe: the impostor answers under b0's clock key as well. Each answer is
    // dropped by the access control and counted as a denied reply under b1's name; the
    // genuine board's answers on its own key, and the decisions Zenoh makes when either
    // declares its queryable, are not.
    use irtrack_cluster::refusals::DeniedAction;
    use irtrack_cluster::transport::{ClockProber, ClockResponder};
    use std::sync::atomic::Ordering;
    let own = ClockResponder::new(&p_genuine, "cell1", "b0", realtime_ns).unwrap();
    // b1's own answers bring the probe's query to b1's session, where the forger hears it.
    let b1_own = ClockResponder::new(&p_impostor, "cell1", "b1", realtime_ns).unwrap();
    let forger = ClockResponder::new(&p_impostor, "cell1", "b0", || realtime_ns() + 100_000_000).unwrap();
    let (prober, replies) =
        ClockProber::start(&solver, "cell1", Duration::from_millis(50), realtime_ns).unwrap();
    let until = Instant::now() + Duration::from_secs(8);
    let (mut genuine_answers, mut forged_answers) = (0u64, 0u64);
    let reply_denial = |s: &RefusalSnapshot| {
        s.denied_recent
            .iter()
            .find(|d| d.action == DeniedAction::Reply)
            .cloned()
    };
    loop {
        while let Ok(r) = replies.try_recv() {
            if r.sample.offset_ns() > 50_000_000 {
                forged_answers += 1;
            } else {
                genuine_answers += 1;
            }
        }
        let s = log.snapshot();
        if genuine_answers >= 10 && reply_denial(&s).is_some_and(|d| d.count >= 10) || Instant::now() > until
        {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let snap = log.snapshot();
    let answered = forger.answered.load(Ordering::Relaxed);
    eprintln!(
        "clock probe: genuine answers taken {genuine_answers}, forged taken {forged_answers}, forger answered {answered}, own answered {}; replies denied {:?}",
        own.answered.load(Ordering::Relaxed),
        reply_denial(&snap)
    );
    assert_eq!(forged_answers, 0, "a forged clock answer reached the prober");
    assert!(
        genuine_answers >= 10,
        "the genuine board's answers: {genuine_answers}"
    );
    let d = reply_denial(&snap).unwrap_or_else(|| panic!("no denied clock answer counted: {snap:#?}"));
    assert_eq!(
        (d.key.as_str(), d.user()),
        ("irtrack/cell1/b0/clock", Some("b1")),
        "{d:?}"
    );
    assert!(
        d.count >= 10 && d.count <= answered,
        "{} denied of {answered} answered",
        d.count
    );
    assert!(
        d.words()
            .contains("answered the clock probe on irtrack/cell1/b0/clock"),
        "{}",
        d.words()
    );
    assert!(
        snap.denied_recent.iter().all(|x| x.user() == Some("b1")),
        "nothing of the genuine board: {snap:#?}"
    );
    drop(prober);
    drop(own);
    drop(b1_own);
    drop(forger);
    for p in [p_anon, p_wrong, p_stranger].into_iter().flatten() {
        p.close();
    }
    p_genuine.close();
    p_impostor.close();
    solver.close();
    let _ = std::fs::remove_dir_all(&dir);
}

/// A plain TCP connection to `127.0.0.1:port` from `ip` (std cannot bind before connecting;
/// tokio's socket can), held open without a byte sent.
fn silent_connect(ip: &str, port: u16) -> std::net::TcpStream {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let ip: std::net::IpAddr = ip.parse().unwrap();
    let s = rt.block_on(async {
        let sock = tokio::net::TcpSocket::new_v4().unwrap();
        sock.bind((ip, 0).into()).unwrap();
        sock.connect(([127, 0, 0, 1], port).into()).await.unwrap()
    });
    s.into_std().unwrap()
}
