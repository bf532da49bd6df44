//! The NatNet command socket under abuse (issue 41; docs/outputs.md, "Spoofed requests and
//! floods"): requests whose source address is someone else's get that address no more bytes
//! than they carried, one address cannot take every unicast slot, and replies are rate limited;
//! each refusal is counted on `/status` and `/metrics`.
//!
//! A spoofed source is played by a socket of the test's own on another loopback address
//! (Linux routes all of 127.0.0.0/8 to `lo`): irtrackd cannot tell it from a forged packet, and
//! the test can count every byte that arrives there — what a victim would receive.

mod common;

use std::collections::BTreeMap;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::Ordering::Relaxed as R;
use std::time::{Duration, Instant};

use common::{TempDir, http_get, run_in_own_netns, runtime, start_with, status_json};
use irtrack_firmware::app;

const SIM: &str = "fps = 120.0\n";
const SERVERINFO: u16 = 1;
const MODELDEF: u16 = 5;
const FRAMEOFDATA: u16 = 7;

async fn start(dir: &TempDir, natnet_toml: &str) -> app::Running {
    let table = format!("[outputs.natnet]\nenabled = true\n{natnet_toml}");
    start_with(dir, SIM, &table).await
}

/// `u16 id, u16 payload bytes, payload`.
fn request(id: u16, payload: &[u8]) -> Vec<u8> {
    let mut p = id.to_le_bytes().to_vec();
    p.extend_from_slice(&(payload.len() as u16).to_le_bytes());
    p.extend_from_slice(payload);
    p
}

/// What arrived at a socket: bytes and datagrams per message id.
#[derive(Debug, Default)]
struct Received {
    bytes: usize,
    by_id: BTreeMap<u16, usize>,
}

impl Received {
    fn count(&self, id: u16) -> usize {
        self.by_id.get(&id).copied().unwrap_or(0)
    }
}

/// Reads everything that arrives at `s` for `window`.
fn drain(s: &UdpSocket, window: Duration, into: &mut Received) {
    let end = Instant::now() + window;
    let mut buf = vec![0u8; 65536];
    while let Some(left) = end.checked_duration_since(Instant::now()) {
        s.set_read_timeout(Some(left.max(Duration::from_millis(1))))
            .unwrap();
        match s.recv(&mut buf) {
            Ok(n) => {
                into.bytes += n;
                if n >= 2 {
                    *into
                        .by_id
                        .entry(u16::from_le_bytes([buf[0], buf[1]]))
                        .or_default() += 1;
                }
            }
            Err(_) => break,
        }
    }
}

fn socket_on(ip: &str) -> UdpSocket {
    UdpSocket::bind((ip, 0)).unwrap_or_else(|e| panic!("bind {ip}: {e}"))
}

/// Every kind of request, as an attacker would send it with a victim's source address:
/// connects of 4 bytes (empty), 9 bytes (PyPI `natnet`'s "Ping") and 268 bytes (the NatNet
/// SDK's sender block), model definitions, a frame, keep-alive, a string command, an unknown
/// id and a malformed datagram.
fn probe_requests() -> Vec<Vec<u8>> {
    let mut sdk_connect = vec![0u8; 264];
    sdk_connect[..8].copy_from_slice(b"NatNetLi");
    vec![
        request(0, &[]),
        request(0, b"Ping\0"),
        request(0, &sdk_connect),
        request(4, &[]),
        request(6, &[]),
        request(10, &[]),
        request(2, b"TimelinePlay\0"),
        request(77, &[]),
        vec![1, 0],
    ]
}

/// Sends the probe `rounds` times from `victim` (20 ms apart), then listens 1 s longer (a
/// client slot would keep frames coming); returns (bytes sent, what arrived).
fn spoof(victim: &UdpSocket, server: SocketAddr, rounds: usize) -> (usize, Received) {
    let mut sent = 0;
    let mut got = Received::default();
    for _ in 0..rounds {
        for r in probe_requests() {
            sent += victim.send_to(&r, server).unwrap();
        }
        drain(victim, Duration::from_millis(20), &mut got);
    }
    drain(victim, Duration::from_secs(1), &mut got);
    (sent, got)
}

/// For both transports: an address outside `client_networks` (127.0.0.9, not in the
/// configured 127.0.0.1/32) gets at most as many bytes as it sent, never server info, model
/// definitions or frames; the vouched-for address is served as before. Multicast runs in a
/// network namespace of the test's own (its group route on `lo`).
#[test]
fn natnet_spoofed_source_gets_no_amplification() {
    run_in_own_netns("natnet_spoofed_source_gets_no_amplification", || async {
        for transport in ["unicast", "multicast"] {
            let dir = TempDir::new(&format!("natnet-spoof-{transport}"));
            let running = start(
                &dir,
                &format!(
                    "command = \"127.0.0.1:0\"\ntransport = \"{transport}\"\nmulticast_interface = \"127.0.0.1\"\nclient_networks = [\"127.0.0.1/32\"]\n"
                ),
            )
            .await;
            let server = running.addrs.natnet.unwrap();
            let stats = running.outputs.natnet.clone();
            let victim = socket_on("127.0.0.9");
            let (sent, got) = tokio::task::spawn_blocking(move || spoof(&victim, server, 50))
                .await
                .unwrap();
            let factor = got.bytes as f64 / sent as f64;
            eprintln!(
                "{transport}: spoofed source sent {sent} B in {} requests, received {} B ({:?}): amplification {factor:.3}",
                50 * probe_requests().len(),
                got.bytes,
                got.by_id
            );
            assert!(
                got.bytes <= sent,
                "{transport}: amplification {factor:.3} > 1: {got:?}"
            );
            for id in [SERVERINFO, MODELDEF, FRAMEOFDATA] {
                assert_eq!(
                    got.count(id),
                    0,
                    "{transport}: message {id} reached the spoofed source: {got:?}"
                );
            }
            // Small answers (no larger than their request) still go out: the unknown id's
            // 4-byte NAT_UNRECOGNIZED_REQUEST, the string command's 8-byte response.
            assert!(got.count(100) > 0 && got.count(3) > 0, "{got:?}");
            assert_eq!(
                stats.clients.load(R),
                0,
                "{transport}: the spoofed source became a client"
            );
            let withheld = stats.withheld.load(R);
            assert!(withheld >= 50 * 4, "{transport}: withheld {withheld}");

            // The address the operator vouched for is served: server info, then frames.
            let client = socket_on("127.0.0.1");
            let got = tokio::task::spawn_blocking(move || {
                client.send_to(&request(0, b"Ping\0"), server).unwrap();
                let mut got = Received::default();
                drain(&client, Duration::from_millis(500), &mut got);
                got
            })
            .await
            .unwrap();
            assert_eq!(got.count(SERVERINFO), 1, "{transport}: {got:?}");
            if transport == "unicast" {
                assert!(got.count(FRAMEOFDATA) >= 10, "{transport}: {got:?}");
            }

            let st = status_json(running.addrs.status).await;
            assert_eq!(
                st["outputs"]["natnet"]["withheld"].as_u64(),
                Some(stats.withheld.load(R)),
                "{st}"
            );
            let (code, metrics) = http_get(running.addrs.status, "/metrics").await;
            assert_eq!(code, 200);
            let line = format!(
                "irtrackd_output_withheld_total{{output=\"natnet\"}} {}",
                stats.withheld.load(R)
            );
            assert!(metrics.contains(&line), "{line} not in /metrics");
            running.shutdown().await;
        }
    });
}

/// Eight sockets of one address (127.0.0.1) connect: only `max_clients_per_address` (4)
/// become clients, the others are refused and counted, and a second address still gets a slot
/// and frames.
#[test]
fn natnet_one_address_cannot_take_every_unicast_slot() {
    runtime().block_on(async {
        let dir = TempDir::new("natnet-per-address");
        let running = start(&dir, "command = \"127.0.0.1:0\"\ntransport = \"unicast\"\n").await;
        let server = running.addrs.natnet.unwrap();
        let stats = running.outputs.natnet.clone();
        let got = tokio::task::spawn_blocking(move || {
            let mut sockets: Vec<UdpSocket> = (0..8).map(|_| socket_on("127.0.0.1")).collect();
            sockets.push(socket_on("127.0.0.2"));
            for s in &sockets {
                s.send_to(&request(0, &[]), server).unwrap();
            }
            std::thread::sleep(Duration::from_millis(300));
            // Frames per socket over 0.5 s (server info of the first connect included).
            sockets
                .iter()
                .map(|s| {
                    let mut got = Received::default();
                    drain(s, Duration::from_millis(60), &mut got);
                    let mut more = Received::default();
                    drain(s, Duration::from_millis(500), &mut more);
                    more.count(FRAMEOFDATA)
                })
                .collect::<Vec<usize>>()
        })
        .await
        .unwrap();
        eprintln!("frames per socket (8 on 127.0.0.1, then 127.0.0.2): {got:?}");
        let served_first = got[..8].iter().filter(|n| **n >= 10).count();
        assert_eq!(served_first, 4, "{got:?}");
        assert_eq!(got[..8].iter().filter(|n| **n == 0).count(), 4, "{got:?}");
        assert!(got[8] >= 10, "the second address got no frames: {got:?}");
        assert_eq!(stats.clients.load(R), 5);
        assert_eq!(stats.refused_per_address.load(R), 4);
        assert_eq!(stats.refused.load(R), 0);
        let st = status_json(running.addrs.status).await;
        assert_eq!(st["outputs"]["natnet"]["refused_per_address"], 4, "{st}");
        let (_, metrics) = http_get(running.addrs.status, "/metrics").await;
        let line = "irtrackd_output_refused_per_address_total{output=\"natnet\"} 4";
        assert!(metrics.contains(line), "{line} not in /metrics");
        running.shutdown().await;
    });
}

/// A burst of 60 model-definition requests from each of three addresses: each address gets
/// at most its per-address burst (10) plus what refills while the burst is answered, and all
/// together at most the total burst (25) plus refill; the rest is counted as rate limited.
#[test]
fn natnet_replies_are_rate_limited() {
    runtime().block_on(async {
        let dir = TempDir::new("natnet-rate");
        let running = start(
            &dir,
            "command = \"127.0.0.1:0\"\ntransport = \"unicast\"\nreplies_per_s_per_address = 10\nreplies_per_s = 25\n",
        )
        .await;
        let server = running.addrs.natnet.unwrap();
        let stats = running.outputs.natnet.clone();
        let (got, elapsed_s) = tokio::task::spawn_blocking(move || {
            let sockets: Vec<UdpSocket> = ["127.0.0.1", "127.0.0.2", "127.0.0.3"]
                .into_iter()
                .map(socket_on)
                .collect();
            let t0 = Instant::now();
            for s in &sockets {
                // 180 requests in all fit the server's receive buffer (none lost before counting).
                for _ in 0..60 {
                    s.send_to(&request(4, &[]), server).unwrap();
                }
            }
            std::thread::sleep(Duration::from_millis(300));
            let elapsed_s = t0.elapsed().as_secs_f64();
            let got: Vec<usize> = sockets
                .iter()
                .map(|s| {
                    let mut got = Received::default();
                    drain(s, Duration::from_millis(50), &mut got);
                    got.count(MODELDEF)
                })
                .collect();
            (got, elapsed_s)
        })
        .await
        .unwrap();
        eprintln!("model definitions answered per address over {elapsed_s:.2} s: {got:?}");
        let per_address_max = 10 + (10.0 * elapsed_s).ceil() as usize;
        let total_max = 25 + (25.0 * elapsed_s).ceil() as usize;
        assert!(got[0] >= 10 && got[0] <= per_address_max, "{got:?}");
        assert!(got.iter().all(|n| *n <= per_address_max), "{got:?}");
        let total: usize = got.iter().sum();
        assert!((25..=total_max).contains(&total), "{got:?}");
        let limited = stats.rate_limited.load(R) as usize;
        assert_eq!(limited, 180 - total, "every unanswered request is counted");
        let st = status_json(running.addrs.status).await;
        assert_eq!(st["outputs"]["natnet"]["rate_limited"].as_u64(), Some(limited as u64));
        running.shutdown().await;
    });
}
