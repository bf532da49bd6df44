//! Simulated robot controller on tokio: the same [`SimRobot`] state machine `host-tools robot-sim`
//! runs, behind a TCP listener, with fault injection (reply delay, disconnect after N targets).
//! Used by the robot link's end-to-end tests and usable by integration tests of irtrackd.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use irtrack_core::robot_proto::{RobotMsg, TrackerMsg};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinHandle;
use tokio::time::Instant;

use crate::sim_robot::{SimEvent, SimRobot, SimRobotConfig};

/// Server-side options around the robot model.
#[derive(Debug, Clone)]
pub struct SimServerConfig {
    /// The robot model.
    pub robot: SimRobotConfig,
    /// Motion update period.
    pub tick_ms: u64,
    /// Delay before every credit reply (a slow controller).
    pub inject_delay_ms: u64,
    /// Drop the connection after this many targets on it; 0 = never.
    pub disconnect_after: u32,
    /// Stop answering (no heartbeats, no credits) after this many targets; 0 = never.
    pub silent_after: u32,
    /// After this many targets on a connection, answer with garbage (binary bytes, an
    /// over-long line, an unknown command) instead of the protocol; 0 = never.
    pub garbage_after: u32,
}

impl Default for SimServerConfig {
    fn default() -> Self {
        Self {
            robot: SimRobotConfig::default(),
            tick_ms: 5,
            inject_delay_ms: 0,
            disconnect_after: 0,
            silent_after: 0,
            garbage_after: 0,
        }
    }
}

/// One log entry.
#[derive(Debug, Clone, PartialEq)]
pub enum SimLog {
    /// A tracker connected.
    Connected,
    /// The tracker's connection ended.
    Disconnected,
    /// The server sent garbage (`garbage_after`).
    GarbageSent,
    /// The robot model did something.
    Event(SimEvent),
}

/// Shared record of what the simulated robot saw and did.
#[derive(Debug, Default)]
pub struct SimRecord {
    /// (seconds since start, connection number, entry, robot TCP at that time).
    pub log: Vec<(f64, u32, SimLog, [f64; 3])>,
    /// (seconds since start, robot TCP), every tick while connected.
    pub trace: Vec<(f64, [f64; 3])>,
    /// Every well-formed `T`/`Q` target line as received, before the robot model judges it.
    pub received: Vec<ReceivedTarget>,
}

/// One target line as it arrived on the wire.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReceivedTarget {
    /// Seconds since the server started.
    pub t_s: f64,
    /// Connection number (from 1).
    pub conn: u32,
    /// The target's sequence number.
    pub seq: u32,
    /// The target position (mm).
    pub pos_mm: [f64; 3],
    /// Orientation of a 6-DOF `Q` target (w, x, y, z); `None` for a position-only `T`.
    pub quat_wxyz: Option<[f64; 4]>,
}

/// A running simulated robot server.
pub struct SimRobotServer {
    /// The address it listens on.
    pub addr: SocketAddr,
    /// What it saw and did so far.
    pub record: Arc<Mutex<SimRecord>>,
    task: JoinHandle<()>,
}

impl Drop for SimRobotServer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl SimRobotServer {
    /// Binds 127.0.0.1 on an ephemeral port and serves one connection at a time.
    pub async fn start(cfg: SimServerConfig) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        let record = Arc::new(Mutex::new(SimRecord::default()));
        let rec = record.clone();
        let task = tokio::spawn(async move {
            let mut robot = SimRobot::new(cfg.robot.clone());
            let t0 = Instant::now();
            let mut conn = 0;
            while let Ok((stream, _)) = listener.accept().await {
                conn += 1;
                serve(&cfg, &mut robot, stream, &rec, t0, conn).await;
                robot.disconnect();
                push(&rec, t0, conn, SimLog::Disconnected, robot.pos_mm());
            }
        });
        Ok(Self { addr, record, task })
    }

    /// Snapshot of the log.
    pub fn log(&self) -> Vec<(f64, u32, SimLog, [f64; 3])> {
        self.record.lock().map(|r| r.log.clone()).unwrap_or_default()
    }

    /// Snapshot of the targets received so far.
    pub fn received(&self) -> Vec<ReceivedTarget> {
        self.record.lock().map(|r| r.received.clone()).unwrap_or_default()
    }

    /// Snapshot of the position trace.
    pub fn trace(&self) -> Vec<(f64, [f64; 3])> {
        self.record.lock().map(|r| r.trace.clone()).unwrap_or_default()
    }
}

fn push(rec: &Mutex<SimRecord>, t0: Instant, conn: u32, e: SimLog, pos: [f64; 3]) {
    if let Ok(mut r) = rec.lock() {
        r.log.push((t0.elapsed().as_secs_f64(), conn, e, pos));
    }
}

fn record_target(rec: &Mutex<SimRecord>, t0: Instant, conn: u32, line: &str) {
    let (seq, pos_mm, quat_wxyz) = match TrackerMsg::parse(line) {
        Ok(TrackerMsg::Target { seq, pos_mm }) => (seq, pos_mm, None),
        Ok(TrackerMsg::Pose {
            seq,
            pos_mm,
            quat_wxyz,
        }) => (seq, pos_mm, Some(quat_wxyz)),
        _ => return,
    };
    if let Ok(mut r) = rec.lock() {
        r.received.push(ReceivedTarget {
            t_s: t0.elapsed().as_secs_f64(),
            conn,
            seq,
            pos_mm,
            quat_wxyz,
        });
    }
}

async fn send_all(w: &mut tokio::net::tcp::OwnedWriteHalf, msgs: &[RobotMsg]) -> bool {
    for m in msgs {
        let Ok(line) = m.encode() else { return false };
        if w.write_all(line.as_bytes()).await.is_err() {
            return false;
        }
    }
    true
}

async fn serve(
    cfg: &SimServerConfig,
    robot: &mut SimRobot,
    stream: TcpStream,
    rec: &Mutex<SimRecord>,
    t0: Instant,
    conn: u32,
) {
    let _ = stream.set_nodelay(true);
    let (rd, mut wr) = stream.into_split();
    let mut lines = BufReader::new(rd).lines();
    push(rec, t0, conn, SimLog::Connected, robot.pos_mm());
    if !send_all(&mut wr, &robot.connect()).await {
        return;
    }
    let mut targets = 0u32;
    let mut tick = tokio::time::interval(Duration::from_millis(cfg.tick_ms));
    let mut last = Instant::now();
    let mut silent = false;
    loop {
        let replies = tokio::select! {
            line = lines.next_line() => match line {
                Ok(Some(l)) => {
                    record_target(rec, t0, conn, &l);
                    robot.on_line(&l)
                }
                _ => return,
            },
            _ = tick.tick() => {
                let dt = last.elapsed().as_secs_f64();
                last = Instant::now();
                let out = robot.advance(dt);
                if let Ok(mut r) = rec.lock() {
                    r.trace.push((t0.elapsed().as_secs_f64(), robot.pos_mm()));
                }
                out
            }
        };
        for e in robot.take_events() {
            if matches!(e, SimEvent::Target { .. }) {
                targets += 1;
            }
            push(rec, t0, conn, SimLog::Event(e), robot.pos_mm());
        }
        if cfg.silent_after > 0 && targets >= cfg.silent_after {
            silent = true;
        }
        if cfg.garbage_after > 0 && targets >= cfg.garbage_after {
            // A confused controller: the session must end here without another target.
            let junk: &[&[u8]] = &[b"\x00\xff\xfe garbage\n", &[b'A'; 200], b"\nMOVE NOW 1 2 3\n"];
            for j in junk {
                if wr.write_all(j).await.is_err() {
                    return;
                }
            }
            push(rec, t0, conn, SimLog::GarbageSent, robot.pos_mm());
            // Keep reading (and recording targets) until the tracker hangs up.
            while let Ok(Some(l)) = lines.next_line().await {
                record_target(rec, t0, conn, &l);
            }
            return;
        }
        if silent {
            continue;
        }
        if cfg.inject_delay_ms > 0 && replies.iter().any(|m| matches!(m, RobotMsg::Credit { .. })) {
            tokio::time::sleep(Duration::from_millis(cfg.inject_delay_ms)).await;
        }
        if !send_all(&mut wr, &replies).await || replies.contains(&RobotMsg::Bye) {
            return;
        }
        if cfg.disconnect_after > 0 && targets >= cfg.disconnect_after {
            return;
        }
    }
}
