//! The shared harness (`irtrack_testkit::harness`, used by these tests and by xtask's demo,
//! soak and image system test) against a real `irtrackd` on simulated cameras: a config from
//! the builder, start up to the ready line on ephemeral ports, `GET /status` and the set-up
//! page over HTTP, the live WebSocket's first message, the operator sign-in (a change refused
//! with a wrong password, accepted with the right one) and a graceful shutdown.
//!
//! The binary belongs to another package: run `cargo build -p irtrack-firmware --bin irtrackd`
//! first.

mod common;

use std::time::Duration;

use common::*;
use irtrack_testkit::harness::{LiveSocket, json};

#[test]
fn harness_starts_talks_to_and_stops_irtrackd() {
    let dir = temp_dir("harness");
    let irtrackd = bin("irtrackd");
    let phc = irtrack_testkit::harness::operator_hash(&irtrackd, OPERATOR_PASSWORD).unwrap();
    let config = dir.join("irtrackd.toml");
    IrtrackdConfig::simulated()
        .comment("harness_e2e")
        .set("source.sim.fps", 30.0)
        .operator_hash(&phc)
        .write(&config)
        .unwrap();
    let d = Irtrackd::start(&irtrackd, &config, &dir.join("state"), Duration::from_secs(20)).unwrap();
    let ready = d.ready().clone();
    assert!(ready.line.starts_with("irtrackd ready"), "{}", ready.line);
    assert_eq!(ready.status.ip().to_string(), "127.0.0.1");

    let http = Http::new(Duration::from_secs(30));
    let (code, body) = http.get(ready.status, "/status").unwrap();
    assert_eq!(code, 200, "{body}");
    let status = json::parse(&body).unwrap();
    assert!(
        json::str_at(&status, "source.description").is_some_and(|d| !d.is_empty()),
        "{body}"
    );
    assert_eq!(
        json::at(&status, "source.cameras")
            .and_then(|c| c.as_array())
            .map(Vec::len),
        Some(2),
        "{body}"
    );
    let (code, page) = http.get(ready.status, "/").unwrap();
    assert!(code == 200 && page.contains("<html"), "{code}: {page:.200}");
    let (code, _) = http.get(ready.status, "/no-such-page").unwrap();
    assert_eq!(code, 404);

    // The live WebSocket speaks first: a JSON message with a type.
    let mut ws = LiveSocket::connect(ready.status, "/api/live", Duration::from_secs(20)).unwrap();
    let first = json::parse(&ws.next_text().unwrap()).unwrap();
    assert!(json::str_at(&first, "type").is_some(), "{first}");
    ws.close();

    // Reading is open; a change needs the operator.
    let change = Some(r#"{"threshold_dn": 41}"#);
    let (code, body) = http
        .clone()
        .signed_in("not-the-password")
        .post(ready.status, "/api/tuning", change)
        .unwrap();
    assert_eq!(code, 401, "{body}");
    let (code, body) = http
        .clone()
        .signed_in(OPERATOR_PASSWORD)
        .post(ready.status, "/api/tuning", change)
        .unwrap();
    assert_eq!(code, 200, "{body}");
    assert_eq!(
        json::f64_at(&json::parse(&body).unwrap(), "threshold_dn"),
        Some(41.0),
        "{body}"
    );

    let how = d.shutdown(Duration::from_secs(10)).unwrap();
    assert!(how.starts_with("exited after SIGTERM"), "{how}");
}
