//! A connection flood on the solver's Zenoh port must not keep a camera board out (issue 40:
//! 150 idle connections renewed every 8 s kept a restarting board out for 39–40 s, because
//! Zenoh closes every new link while `accept_pending` links are in their handshake, each for
//! up to `accept_timeout`).
//!
//! A flooder holds `FLOOD` idle TCP connections to the port, replacing each as soon as Zenoh
//! closes it (a harder flood than the issue's), while a board that was connected before keeps
//! publishing, then restarts (a new session) and must be heard again within a few seconds.
#![cfg(feature = "zenoh")]

use std::time::{Duration, Instant};

use irtrack_cluster::transport::{
    ACCEPT_PENDING, ACCEPT_TIMEOUT_MS, ObsPublisher, ObsSubscriber, Session, TransportConfig, realtime_ns,
};
use irtrack_core::observation::{ObsBlob, ObsClock, ObsHeader, decode};
use irtrack_testkit::flood::Flood;

/// Idle connections the flooder keeps open: above Zenoh's default `accept_pending` (100).
const FLOOD: usize = 300;
/// A restarted board must be heard again within this.
const LIMIT: Duration = Duration::from_secs(4);

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

fn header(seq: u64) -> ObsHeader<'static> {
    ObsHeader {
        rig: "flood",
        board: "b0",
        camera: 0,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: realtime_ns(),
        clock: ObsClock::Realtime,
        exposure_us: 0,
        dropped: 0,
        send_delay_us: 0,
    }
}

/// Keeps `FLOOD` connections open until `stop`; counts the ones the peer closed (and that
/// were replaced).
/// Publishes from a new board session until the solver's subscriber has one of its
/// observations with a sequence from `first_seq` on; returns how long that took.
fn board_heard(
    port: u16,
    rx: &std::sync::mpsc::Receiver<irtrack_cluster::transport::Received>,
    first_seq: u64,
) -> (Session, Duration) {
    let start = Instant::now();
    let board = Session::open(&TransportConfig {
        connect: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    })
    .unwrap();
    let mut p = ObsPublisher::new(&board, "flood", "b0", 0).unwrap();
    let blob = ObsBlob {
        x_px: 10.0,
        y_px: 20.0,
        area_px: 9,
        peak_dn: 200,
        roundness: 1.0,
        ..ObsBlob::default()
    };
    let mut seq = first_seq;
    loop {
        p.publish(&header(seq), &[blob]).unwrap();
        seq += 1;
        if let Ok(m) = rx.recv_timeout(Duration::from_millis(10))
            && decode(m.payload()).unwrap().header.sequence >= first_seq
        {
            return (board, start.elapsed());
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the board was kept out for 30 s by the flood"
        );
    }
}

#[test]
fn a_connection_flood_keeps_no_board_out() {
    let port = free_port();
    let solver = Session::open(&TransportConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..TransportConfig::default()
    })
    .unwrap();
    let (_sub, rx) = ObsSubscriber::new(&solver, "flood", 4096, realtime_ns).unwrap();

    // The board before the flood.
    let (board, t0) = board_heard(port, &rx, 1);
    println!(
        "board heard {:.0} ms after its start, no flood",
        t0.as_secs_f64() * 1e3
    );

    let flood = Flood::start(port, FLOOD, Duration::from_secs(60));
    // Let the flood fill Zenoh's handshake slots and run through a few timeouts.
    std::thread::sleep(Duration::from_millis(2 * ACCEPT_TIMEOUT_MS + 500));
    assert!(
        flood.open() as usize >= FLOOD / 2,
        "the flooder holds only {} connections",
        flood.open()
    );

    // The board that was connected keeps reaching the solver during the flood.
    while rx.try_recv().is_ok() {}
    let t_connected = {
        let mut p = ObsPublisher::new(&board, "flood", "b0", 0).unwrap();
        let start = Instant::now();
        let mut seq = 1_000;
        loop {
            p.publish(&header(seq), &[]).unwrap();
            seq += 1;
            if rx.recv_timeout(Duration::from_millis(10)).is_ok() {
                break start.elapsed();
            }
            assert!(
                start.elapsed() < LIMIT,
                "the connected board was cut off by the flood"
            );
        }
    };
    // Restart: the old session closes, a new one opens while the flood goes on.
    board.close();
    std::thread::sleep(Duration::from_millis(100));
    while rx.try_recv().is_ok() {}
    let (board2, t_restart) = board_heard(port, &rx, 1_000_000);
    let closed = flood.stop();
    println!(
        "flood of {FLOOD} idle connections (accept_pending {ACCEPT_PENDING}, accept_timeout {ACCEPT_TIMEOUT_MS} ms): {} closed by Zenoh and replaced; connected board heard after {:.0} ms, restarted board after {:.0} ms",
        closed,
        t_connected.as_secs_f64() * 1e3,
        t_restart.as_secs_f64() * 1e3
    );
    assert!(
        t_restart < LIMIT,
        "the restarted board was heard only after {t_restart:?} (limit {LIMIT:?})"
    );
    // Zenoh closed the silent connections at its accept timeout.
    assert!(closed >= FLOOD as u64);
    board2.close();
    solver.close();
}
