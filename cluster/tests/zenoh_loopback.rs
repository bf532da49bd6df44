//! Observations over real Zenoh sessions on 127.0.0.1 with explicit TCP endpoints (no
//! multicast scouting): to the crate's own subscriber, and to PyPI's `eclipse-zenoh` as an
//! independent subscriber that decodes the spec itself (tests/python/obs_subscriber.py).
#![cfg(feature = "zenoh")]

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use irtrack_cluster::transport::{
    ObsPublisher, ObsSubscriber, Session, TransportConfig, observation_key, realtime_ns,
};
use irtrack_core::observation::{ObsBlob, ObsClock, ObsHeader, decode};

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

fn board_and_peer(port: u16) -> (Session, TransportConfig) {
    board_and_peer_with(port, false)
}

fn board_and_peer_with(port: u16, low_latency: bool) -> (Session, TransportConfig) {
    let board = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        low_latency,
        ..TransportConfig::default()
    })
    .unwrap();
    let peer = TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        low_latency,
        ..TransportConfig::default()
    };
    (board, peer)
}

fn header(seq: u64, camera: u8) -> ObsHeader<'static> {
    ObsHeader {
        rig: "cell1",
        board: "b0",
        camera,
        sequence: seq,
        trigger_count: seq.is_multiple_of(2).then_some(seq * 10),
        capture_ts_ns: realtime_ns(),
        clock: ObsClock::Realtime,
        exposure_us: 250,
        dropped: 1,
        send_delay_us: 700,
    }
}

fn blob(seq: u64) -> ObsBlob {
    ObsBlob {
        x_px: 100.25 + seq as f32,
        y_px: 200.5,
        area_px: 9,
        peak_dn: 240,
        roundness: 1.0,
        touches_frame_edge: false,
        touches_roi_edge: true,
        saturated: seq.is_multiple_of(3),
    }
}

#[test]
fn observations_reach_the_solver_subscriber() {
    burst_reaches_the_subscriber(false);
}

/// The same with Zenoh's low-latency transport (`[cluster] low_latency = true`), which a
/// loaded CI run once failed; run by hand (`-- --ignored`) to check it under load
/// (docs/cluster.md, "Low-latency transport").
#[test]
#[ignore = "by hand: the low-latency transport under load (docs/cluster.md)"]
fn observations_reach_the_solver_subscriber_low_latency() {
    burst_reaches_the_subscriber(true);
}

fn burst_reaches_the_subscriber(low_latency: bool) {
    let port = free_port();
    let (board, peer) = board_and_peer_with(port, low_latency);
    let solver = Session::open(&peer).unwrap();
    let (_sub, rx) = ObsSubscriber::new(&solver, "cell1", 256, realtime_ns).unwrap();
    let mut publisher = ObsPublisher::new(&board, "cell1", "b0", 1).unwrap();

    // Routes take a moment to establish: publish until the first one arrives.
    let start = Instant::now();
    let mut seq = 0;
    let first = loop {
        seq += 1;
        publisher.publish(&header(seq, 1), &[blob(seq)]).unwrap();
        if let Ok(m) = rx.recv_timeout(Duration::from_millis(50)) {
            break m;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "no observation within 10 s"
        );
    };
    assert!(decode(first.payload()).is_ok());
    while rx.try_recv().is_ok() {}

    // Paced at one observation per millisecond: four times what a two-camera board sends at
    // 120 fps. Observations are published with congestion control Drop (a board's loop never
    // waits on the network), so an unpaced burst on a starved machine loses its tail by
    // design once Zenoh's real-time queue (16 batches) is full; that loss is counted by the
    // solver as missing cameras, and is not what this test checks (docs/cluster.md).
    let base = seq + 1;
    for s in base..base + 100 {
        publisher.publish(&header(s, 1), &[blob(s), blob(s + 1)]).unwrap();
        std::thread::sleep(Duration::from_millis(1));
    }
    let mut got = Vec::new();
    while got.len() < 100 {
        let Ok(m) = rx.recv_timeout(Duration::from_secs(5)) else {
            // Say which ones are missing: the first, the last, or a hole.
            let seqs: Vec<u64> = got.iter().map(|(s, _)| *s).collect();
            panic!(
                "{} of 100 observations within 5 s (low_latency {low_latency}); received sequences {seqs:?}, sent {base}..{}",
                got.len(),
                base + 100
            );
        };
        let obs = decode(m.payload()).unwrap();
        assert!(m.received_ns >= obs.header.capture_ts_ns);
        got.push((obs.header.sequence, obs.blobs().collect::<Vec<_>>()));
    }
    // In order, complete, and the blobs as sent.
    for (i, (s, blobs)) in got.iter().enumerate() {
        assert_eq!(*s, base + i as u64);
        assert_eq!(blobs, &vec![blob(*s), blob(*s + 1)]);
    }
    assert_eq!(publisher.sent(), seq + 100);
    solver.close();
    board.close();
}

#[test]
fn names_in_key_expressions_are_checked() {
    assert_eq!(observation_key("cell1", "b0", 2), "irtrack/cell1/b0/cam/2/obs");
    let port = free_port();
    let (board, _) = board_and_peer(port);
    let e = ObsPublisher::new(&board, "cell/1", "b0", 0).unwrap_err();
    assert!(e.to_string().contains("rig name"), "{e}");
    let e = Session::open(&TransportConfig {
        connect: vec!["127.0.0.1:7447".into()],
        ..TransportConfig::default()
    })
    .unwrap_err();
    assert!(e.to_string().contains("tcp/<ip>:<port>"), "{e}");
    board.close();
}

/// PyPI's eclipse-zenoh subscribes through its own Zenoh stack and decodes the observations
/// with `struct` from docs/observation-protocol.md.
#[test]
fn python_eclipse_zenoh_decodes_observations() {
    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/python/obs_subscriber.py");
    let port = free_port();
    let (board, _) = board_and_peer(port);
    let mut publisher = ObsPublisher::new(&board, "cell1", "b0", 3).unwrap();
    let mut child = Command::new("python3")
        .arg(script)
        .arg(format!("tcp/127.0.0.1:{port}"))
        .arg("irtrack/cell1/*/cam/*/obs")
        .arg("20")
        .arg("20")
        .stdout(Stdio::piped())
        .spawn()
        .expect("python3");
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let ready = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("the Python subscriber did not start (is PyPI's eclipse-zenoh installed? cargo xtask setup)");
    assert!(ready.contains("ready"), "{ready}");
    let mut sent = std::collections::HashMap::new();
    let mut lines = Vec::new();
    let start = Instant::now();
    let mut seq = 0u64;
    while lines.len() < 20 {
        seq += 1;
        let h = header(seq, 3);
        publisher.publish(&h, &[blob(seq)]).unwrap();
        sent.insert(seq, h);
        while let Ok(l) = rx.recv_timeout(Duration::from_millis(20)) {
            lines.push(l);
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "Python got {} observations",
            lines.len()
        );
    }
    assert!(child.wait().unwrap().success());
    for l in &lines[..20] {
        let v: serde_json::Value = serde_json::from_str(l).unwrap();
        assert!(v.get("error").is_none(), "Python could not decode: {l}");
        let s = v["sequence"].as_u64().unwrap();
        let h = &sent[&s];
        assert_eq!(v["key"], "irtrack/cell1/b0/cam/3/obs");
        assert_eq!(v["rig"], "cell1");
        assert_eq!(v["board"], "b0");
        assert_eq!(v["camera"], 3);
        assert_eq!(v["capture_ts_ns"].as_u64().unwrap(), h.capture_ts_ns);
        assert_eq!(v["clock"], 1);
        assert_eq!(v["exposure_us"], 250);
        assert_eq!(v["send_delay_us"], 700);
        assert_eq!(v["trigger"].as_u64(), h.trigger_count);
        let b = &v["blobs"][0];
        assert_eq!(b["x_px"].as_f64().unwrap(), f64::from(blob(s).x_px));
        assert_eq!(b["area_px"], 9);
        assert_eq!(
            b["flags"].as_u64().unwrap(),
            2 | if s.is_multiple_of(3) { 4 } else { 0 }
        );
    }
    board.close();
}
