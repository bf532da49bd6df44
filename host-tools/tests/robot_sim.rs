//! `host-tools robot-sim` as a process: protocol replies, speed limit, injected rejects and
//! disconnects, and the CSV log.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use irtrack_core::robot_proto::{HoldReason, RobotMsg, TrackerMsg, reject};

struct Sim {
    child: Child,
    addr: String,
}

impl Drop for Sim {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start(extra: &[&str]) -> Sim {
    let mut child = Command::new(env!("CARGO_BIN_EXE_host-tools"))
        .args(["robot-sim", "--listen", "127.0.0.1:0"])
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let addr = line.trim().rsplit(' ').next().unwrap().to_string();
    Sim { child, addr }
}

struct Conn {
    w: TcpStream,
    r: BufReader<TcpStream>,
}

impl Conn {
    fn open(addr: &str) -> Conn {
        let w = TcpStream::connect(addr).unwrap();
        w.set_read_timeout(Some(Duration::from_secs(3))).unwrap();
        let r = BufReader::new(w.try_clone().unwrap());
        Conn { w, r }
    }
    fn send(&mut self, m: TrackerMsg) {
        self.w.write_all(m.encode().unwrap().as_bytes()).unwrap();
    }
    /// Next non-heartbeat message.
    fn recv(&mut self) -> RobotMsg {
        loop {
            let mut l = String::new();
            assert!(self.r.read_line(&mut l).unwrap() > 0, "connection closed");
            assert!(l.len() <= 80);
            let m = RobotMsg::parse(&l).unwrap();
            if !matches!(m, RobotMsg::Beat { .. }) {
                return m;
            }
        }
    }
}

#[test]
fn robot_sim_follows_targets_at_its_speed_and_logs() {
    let dir = std::env::temp_dir().join(format!("irtrack-robot-sim-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("sim.csv");
    let sim = start(&[
        "--speed-mm-s",
        "200",
        "--home",
        "10,20,30",
        "--log",
        log.to_str().unwrap(),
        "--max-connections",
        "1",
        "--reject-every",
        "3",
    ]);
    let mut c = Conn::open(&sim.addr);
    assert_eq!(
        c.recv(),
        RobotMsg::Hello {
            version: 1,
            name: "robot-sim".into()
        }
    );
    assert_eq!(
        c.recv(),
        RobotMsg::Credit {
            ack_seq: 0,
            window: 1,
            pos_mm: [10.0, 20.0, 30.0]
        }
    );
    c.send(TrackerMsg::Hello {
        version: 1,
        name: "test".into(),
    });
    // 40 mm at 200 mm/s: about 0.2 s.
    let t0 = Instant::now();
    c.send(TrackerMsg::Target {
        seq: 1,
        pos_mm: [50.0, 20.0, 30.0],
    });
    assert_eq!(
        c.recv(),
        RobotMsg::Credit {
            ack_seq: 1,
            window: 1,
            pos_mm: [50.0, 20.0, 30.0]
        }
    );
    let dt = t0.elapsed().as_secs_f64();
    assert!((0.19..0.35).contains(&dt), "40 mm took {dt} s at 200 mm/s");
    // Without credit: rejected.
    c.send(TrackerMsg::Target {
        seq: 2,
        pos_mm: [60.0, 20.0, 30.0],
    });
    c.send(TrackerMsg::Target {
        seq: 3,
        pos_mm: [70.0, 20.0, 30.0],
    });
    let mut got = vec![c.recv(), c.recv()];
    got.sort_by_key(|m| matches!(m, RobotMsg::Credit { .. }));
    assert!(
        matches!(
            got[0],
            RobotMsg::Reject {
                seq: 3,
                code: reject::NO_CREDIT,
                ..
            }
        ),
        "{got:?}"
    );
    assert!(matches!(got[1], RobotMsg::Credit { ack_seq: 2, .. }));
    // Third accepted target is rejected by injection, and still consumed.
    c.send(TrackerMsg::Target {
        seq: 3,
        pos_mm: [70.0, 20.0, 30.0],
    });
    assert!(matches!(
        c.recv(),
        RobotMsg::Reject {
            seq: 3,
            code: reject::INJECTED,
            ..
        }
    ));
    assert!(matches!(c.recv(), RobotMsg::Credit { ack_seq: 3, .. }));
    // HOLD stops a move half way.
    c.send(TrackerMsg::Target {
        seq: 4,
        pos_mm: [460.0, 20.0, 30.0],
    });
    std::thread::sleep(Duration::from_millis(100));
    c.send(TrackerMsg::Hold {
        reason: HoldReason::Deadman,
    });
    let RobotMsg::Credit {
        ack_seq: 4, pos_mm, ..
    } = c.recv()
    else {
        panic!("no credit after HOLD")
    };
    assert!(pos_mm[0] > 62.0 && pos_mm[0] < 150.0, "stopped at {pos_mm:?}");
    c.w.write_all(b"T garbage\n").unwrap();
    assert!(matches!(
        c.recv(),
        RobotMsg::Reject {
            code: reject::MALFORMED,
            ..
        }
    ));
    c.send(TrackerMsg::Bye);
    assert_eq!(c.recv(), RobotMsg::Bye);
    drop(c);
    let mut sim = sim;
    let status = sim.child.wait().unwrap();
    assert!(status.success());
    let csv = std::fs::read_to_string(&log).unwrap();
    let mut lines = csv.lines();
    assert!(
        lines
            .next()
            .unwrap()
            .starts_with("t_s,conn,event,seq,target_x_mm")
    );
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert!(rows.iter().all(|r| r.len() == 11));
    let targets: Vec<_> = rows.iter().filter(|r| r[2] == "target").collect();
    assert_eq!(targets.len(), 3, "{csv}");
    assert_eq!(targets[0][4], "50.000");
    assert!(rows.iter().any(|r| r[2] == "hold" && r[10] == "DEADMAN"));
    assert!(rows.iter().any(|r| r[2] == "rejected" && r[10] == "02"));
    assert!(rows.iter().filter(|r| r[2] == "pos").count() > 5);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn robot_sim_injects_disconnects_and_delays() {
    let sim = start(&[
        "--speed-mm-s",
        "1000",
        "--disconnect-after",
        "2",
        "--inject-delay-ms",
        "100",
        "--max-connections",
        "2",
    ]);
    for _ in 0..2 {
        let mut c = Conn::open(&sim.addr);
        assert!(matches!(c.recv(), RobotMsg::Hello { .. }));
        assert!(matches!(c.recv(), RobotMsg::Credit { ack_seq: 0, .. }));
        let t0 = Instant::now();
        c.send(TrackerMsg::Target {
            seq: 1,
            pos_mm: [1.0, 0.0, 0.0],
        });
        assert!(matches!(c.recv(), RobotMsg::Credit { ack_seq: 1, .. }));
        assert!(t0.elapsed() >= Duration::from_millis(100), "reply not delayed");
        c.send(TrackerMsg::Target {
            seq: 2,
            pos_mm: [2.0, 0.0, 0.0],
        });
        // Dropped after the second target: the stream ends.
        let mut rest = String::new();
        let mut r = c.r;
        let end = loop {
            rest.clear();
            match r.read_line(&mut rest) {
                Ok(0) => break true,
                Ok(_) => continue,
                Err(_) => break false,
            }
        };
        assert!(end, "robot-sim did not disconnect");
    }
}

/// The robot answers a reached target at its next tick: 1 mm steps at 1000 mm/s (1 ms of
/// motion) come back within the move plus one 4 ms tick. A socket read timeout as the tick
/// (SO_RCVTIMEO, kernel ticks of 4 ms at HZ=250) made that 8-12 ms.
#[test]
fn robot_sim_answers_a_reached_target_within_one_tick() {
    let sim = start(&["--speed-mm-s", "1000", "--home", "0,0,0", "--tick-ms", "4"]);
    let mut c = Conn::open(&sim.addr);
    assert!(matches!(c.recv(), RobotMsg::Hello { .. }));
    assert!(matches!(c.recv(), RobotMsg::Credit { .. }));
    c.send(TrackerMsg::Hello {
        version: 1,
        name: "test".into(),
    });
    let mut delays_ms = Vec::new();
    for seq in 1..=60u32 {
        let t0 = Instant::now();
        c.send(TrackerMsg::Target {
            seq,
            pos_mm: [f64::from(seq), 0.0, 0.0],
        });
        assert!(matches!(c.recv(), RobotMsg::Credit { ack_seq, .. } if ack_seq == seq));
        delays_ms.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    delays_ms.sort_by(f64::total_cmp);
    let q = |p: f64| delays_ms[((delays_ms.len() - 1) as f64 * p) as usize];
    println!(
        "target → credit, 1 mm at 1000 mm/s, 4 ms tick: p50 {:.2} ms, p75 {:.2} ms, max {:.2} ms",
        q(0.5),
        q(0.75),
        q(1.0)
    );
    // 1 ms of motion + one 4 ms tick, with 1 ms to spare for a busy machine.
    assert!(q(0.75) <= 6.0, "p75 {:.2} ms", q(0.75));
}
