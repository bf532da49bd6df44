//! TCP client of the robot protocol: connects to the robot controller (the server), reconnects
//! with exponential backoff, sends the newest safe position as the next target whenever the robot
//! grants credit, holds on every safety condition, and exchanges heartbeats.
//!
//! Every (re)connection starts held: sequence state resets and motion resumes only after an
//! explicit [`RobotLink::enable`] issued after the connection came up.

use std::sync::Arc;
use std::time::Duration;

use irtrack_core::robot_proto::{self, HoldReason, PROTOCOL_VERSION, RobotMsg, TrackerMsg};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use tokio::net::tcp::OwnedWriteHalf;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::{Instant, timeout};

use crate::deadman::Deadman;
use crate::gate::Gate;
use crate::link::{LinkHandle, LinkState, LinkStatus};
use crate::safety::Verdict;
use crate::{Clock, LinkKind, PositionFeed, RobotConfig, RobotError};

/// The socket protocol's client task behind a [`LinkHandle`].
impl LinkHandle {
    /// Validates the config and starts the socket-protocol client task on the current tokio
    /// runtime (use [`crate::spawn_link`] to start whatever `cfg.kind` names).
    pub fn spawn_socket<F: PositionFeed, C: Clock>(
        cfg: RobotConfig,
        feed: F,
        clock: C,
        deadman: Arc<dyn Deadman>,
    ) -> Result<Self, RobotError> {
        cfg.validate()?;
        if cfg.kind != LinkKind::Socket {
            return Err(RobotError::Config {
                reason: format!("robot.kind = \"{}\" is not the socket protocol", cfg.kind.name()),
            });
        }
        Ok(Self::start(|ctl_rx, status_tx| {
            let mut client = Client {
                gate: Gate::new(&cfg, feed, clock, deadman, ctl_rx),
                cfg,
                status: status_tx,
            };
            async move { client.run().await }
        }))
    }
}

struct Client<F, C> {
    cfg: RobotConfig,
    gate: Gate<F, C>,
    status: watch::Sender<LinkStatus>,
}

/// Per-connection protocol state (reset on every connect).
struct Session {
    wr: OwnedWriteHalf,
    ack_seq: u32,
    window: u8,
    last_sent_seq: u32,
    last_sent_ts_ns: Option<u64>,
    holding: Option<HoldReason>,
    last_rx: Instant,
    last_tx: Instant,
    beat: u32,
}

enum End {
    Stop,
    Lost(RobotError),
}

impl<F: PositionFeed, C: Clock> Client<F, C> {
    fn addr(&self) -> String {
        self.cfg.address.clone()
    }

    async fn run(&mut self) {
        self.run_sessions().await;
        self.gate.log_latency("socket");
    }

    async fn run_sessions(&mut self) {
        let mut backoff_ms = self.cfg.backoff_min_ms;
        loop {
            if self.gate.ctl.borrow().stop {
                return;
            }
            self.status.send_modify(|s| s.state = LinkState::Connecting);
            let connect = timeout(
                Duration::from_millis(self.cfg.connect_timeout_ms),
                TcpStream::connect(self.cfg.address.as_str()),
            )
            .await;
            let err = match connect {
                Ok(Ok(stream)) => match self.session(stream).await {
                    (End::Stop, _) => {
                        self.status.send_modify(|s| s.state = LinkState::Disconnected);
                        return;
                    }
                    (End::Lost(e), handshake_done) => {
                        if handshake_done {
                            backoff_ms = self.cfg.backoff_min_ms;
                        }
                        e
                    }
                },
                Ok(Err(e)) => RobotError::Io {
                    addr: self.addr(),
                    what: "connect",
                    source: e,
                },
                Err(_) => RobotError::Timeout {
                    addr: self.addr(),
                    ms: self.cfg.connect_timeout_ms,
                },
            };
            tracing::warn!("{err}; reconnecting in {backoff_ms} ms");
            self.status.send_modify(|s| {
                s.state = LinkState::Disconnected;
                s.last_error = Some(err.to_string());
            });
            let sleep = tokio::time::sleep(Duration::from_millis(backoff_ms));
            tokio::pin!(sleep);
            loop {
                tokio::select! {
                    _ = &mut sleep => break,
                    r = self.gate.ctl.changed() => if r.is_err() || self.gate.ctl.borrow_and_update().stop { return },
                }
            }
            backoff_ms = (backoff_ms * 2).min(self.cfg.backoff_max_ms);
        }
    }

    /// One connection; returns how it ended and whether the handshake completed.
    async fn session(&mut self, stream: TcpStream) -> (End, bool) {
        let addr = self.addr();
        let _ = stream.set_nodelay(true);
        let (rd, wr) = stream.into_split();
        // Reading in its own task keeps partial lines safe across `select!` cancellation.
        let (tx, mut rx) = mpsc::channel::<Result<RobotMsg, RobotError>>(64);
        let reader = tokio::spawn(read_lines(BufReader::new(rd), addr.clone(), tx));
        let _abort = AbortOnDrop(reader);
        let now = Instant::now();
        let mut s = Session {
            wr,
            ack_seq: 0,
            window: 1,
            last_sent_seq: 0,
            last_sent_ts_ns: None,
            holding: None,
            last_rx: now,
            last_tx: now,
            beat: 0,
        };
        let hello = TrackerMsg::Hello {
            version: PROTOCOL_VERSION,
            name: self.cfg.name.clone(),
        };
        if let Err(e) = self.send(&mut s, &hello).await {
            return (End::Lost(e), false);
        }
        let robot_pos_mm = match self.handshake(&mut s, &mut rx).await {
            Ok(p) => p,
            Err(e) => return (End::Lost(e), false),
        };
        // A fresh connection never moves on an enable given before it.
        self.gate.on_connect(robot_pos_mm);
        self.status.send_modify(|st| st.connects += 1);
        tracing::info!("robot link {addr}: connected; holding until enabled");
        let period = self
            .cfg
            .heartbeat_ms
            .min(self.cfg.safety.max_age_ms / 2)
            .clamp(5, 1000);
        let mut tick = tokio::time::interval(Duration::from_millis(period));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let end = loop {
            let r: Result<(), End> = tokio::select! {
                m = rx.recv() => match m {
                    None => Err(End::Lost(RobotError::Closed { addr: addr.clone() })),
                    Some(Err(e)) => Err(End::Lost(e)),
                    Some(Ok(msg)) => self.on_robot(&mut s, msg),
                },
                open = self.gate.feed.changed(), if self.gate.feed_open => {
                    self.gate.feed_open = open;
                    self.gate.refresh();
                    Ok(())
                }
                r = self.gate.ctl.changed() => {
                    if r.is_err() || self.gate.apply_control() {
                        Err(End::Stop)
                    } else {
                        Ok(())
                    }
                }
                _ = tick.tick() => self.on_tick(&mut s).await,
            };
            let r = match r {
                Ok(()) => self.evaluate(&mut s).await,
                Err(e) => Err(e),
            };
            if let Err(e) = r {
                break e;
            }
        };
        if matches!(end, End::Stop) {
            let _ = self
                .send(
                    &mut s,
                    &TrackerMsg::Hold {
                        reason: HoldReason::Stop,
                    },
                )
                .await;
            let _ = self.send(&mut s, &TrackerMsg::Bye).await;
        }
        self.status.send_modify(|st| st.robot_pos_mm = None);
        (end, true)
    }

    async fn handshake(
        &mut self,
        s: &mut Session,
        rx: &mut mpsc::Receiver<Result<RobotMsg, RobotError>>,
    ) -> Result<[f64; 3], RobotError> {
        let addr = self.addr();
        let wait = Duration::from_millis(self.cfg.peer_timeout_ms);
        let timeout_err = || RobotError::Timeout {
            addr: addr.clone(),
            ms: self.cfg.peer_timeout_ms,
        };
        let closed = || RobotError::Closed { addr: addr.clone() };
        let proto = |reason: String| RobotError::Protocol {
            addr: addr.clone(),
            source: irtrack_core::Error::Protocol {
                protocol: "robot",
                reason,
            },
        };
        let first = timeout(wait, rx.recv())
            .await
            .map_err(|_| timeout_err())?
            .ok_or_else(closed)??;
        let RobotMsg::Hello { version, name } = first else {
            return Err(proto(format!("expected HELLO first, got {first:?}")));
        };
        if version != PROTOCOL_VERSION {
            return Err(RobotError::Version {
                addr: addr.clone(),
                found: version,
                supported: PROTOCOL_VERSION,
            });
        }
        loop {
            match timeout(wait, rx.recv())
                .await
                .map_err(|_| timeout_err())?
                .ok_or_else(closed)??
            {
                RobotMsg::Credit {
                    ack_seq,
                    window,
                    pos_mm,
                } => {
                    s.ack_seq = ack_seq;
                    s.last_sent_seq = ack_seq;
                    s.window = window;
                    s.last_rx = Instant::now();
                    self.status.send_modify(|st| {
                        st.robot_name = Some(name.clone());
                        st.robot_pos_mm = Some(pos_mm);
                    });
                    return Ok(pos_mm);
                }
                RobotMsg::Beat { .. } => {}
                other => {
                    return Err(proto(format!(
                        "expected the ready credit after HELLO, got {other:?}"
                    )));
                }
            }
        }
    }

    fn on_robot(&mut self, s: &mut Session, msg: RobotMsg) -> Result<(), End> {
        s.last_rx = Instant::now();
        match msg {
            RobotMsg::Credit {
                ack_seq,
                window,
                pos_mm,
            } => {
                // An ack beyond what was sent means the robot and tracker disagree: reconnect.
                if robot_proto::seq_distance(ack_seq, s.last_sent_seq)
                    > robot_proto::seq_distance(s.ack_seq, s.last_sent_seq)
                {
                    return Err(End::Lost(RobotError::Protocol {
                        addr: self.addr(),
                        source: irtrack_core::Error::Protocol {
                            protocol: "robot",
                            reason: format!("credit acknowledges {ack_seq}, last sent {}", s.last_sent_seq),
                        },
                    }));
                }
                s.ack_seq = ack_seq;
                s.window = window;
                self.gate.sup.on_robot_position(pos_mm);
                self.status.send_modify(|st| st.robot_pos_mm = Some(pos_mm));
            }
            RobotMsg::Reject { seq, code, reason } => {
                tracing::warn!("robot rejected target {seq}: {code:02} {reason}");
                self.status.send_modify(|st| st.rejects += 1);
            }
            RobotMsg::Beat { .. } => {}
            // irtrackd never sends `POSE` (only `host-tools survey` does); an unasked answer
            // carries nothing the link needs.
            RobotMsg::Actual { .. } => tracing::debug!("unrequested pose answer from the robot"),
            RobotMsg::Bye => return Err(End::Lost(RobotError::Closed { addr: self.addr() })),
            RobotMsg::Hello { .. } => {
                return Err(End::Lost(RobotError::Protocol {
                    addr: self.addr(),
                    source: irtrack_core::Error::Protocol {
                        protocol: "robot",
                        reason: "HELLO in session".into(),
                    },
                }));
            }
        }
        Ok(())
    }

    async fn on_tick(&mut self, s: &mut Session) -> Result<(), End> {
        let silent = s.last_rx.elapsed();
        if silent > Duration::from_millis(self.cfg.peer_timeout_ms) {
            return Err(End::Lost(RobotError::Timeout {
                addr: self.addr(),
                ms: silent.as_millis() as u64,
            }));
        }
        if s.last_tx.elapsed() >= Duration::from_millis(self.cfg.heartbeat_ms) {
            s.beat = robot_proto::seq_next(s.beat);
            self.send(s, &TrackerMsg::Beat { counter: s.beat })
                .await
                .map_err(End::Lost)?;
        }
        Ok(())
    }

    /// Applies the supervisor to the newest sample: HOLD on a new hold condition, a target when
    /// allowed and credit is available.
    async fn evaluate(&mut self, s: &mut Session) -> Result<(), End> {
        let cur = self.gate.cur;
        let verdict = self.gate.verdict(cur.as_ref());
        match verdict {
            Verdict::Hold(reason) => {
                if s.holding.is_none() {
                    self.send(s, &TrackerMsg::Hold { reason })
                        .await
                        .map_err(End::Lost)?;
                    tracing::info!("robot hold: {}", reason.text());
                    self.status.send_modify(|st| st.holds_sent += 1);
                }
                s.holding = Some(reason);
                self.status.send_if_modified(|st| {
                    let changed = st.state != LinkState::Holding(reason);
                    st.state = LinkState::Holding(reason);
                    changed
                });
            }
            Verdict::Send { pos_mm, quat_wxyz } => {
                let Some(sample) = self.gate.cur else {
                    return Ok(());
                };
                if s.last_sent_ts_ns == Some(sample.capture_ts_ns) {
                    return Ok(());
                }
                let outstanding = robot_proto::seq_distance(s.ack_seq, s.last_sent_seq);
                if outstanding >= u32::from(s.window) {
                    return Ok(());
                }
                let seq = robot_proto::seq_next(s.last_sent_seq);
                let msg = match quat_wxyz {
                    Some(quat_wxyz) => TrackerMsg::Pose {
                        seq,
                        pos_mm,
                        quat_wxyz,
                    },
                    None => TrackerMsg::Target { seq, pos_mm },
                };
                self.send(s, &msg).await.map_err(End::Lost)?;
                self.gate.record_sent(sample.capture_ts_ns);
                self.gate.sup.committed(pos_mm, quat_wxyz, sample.capture_ts_ns);
                s.last_sent_seq = seq;
                s.last_sent_ts_ns = Some(sample.capture_ts_ns);
                s.holding = None;
                let latency = self.gate.latency_summary_due();
                self.status.send_modify(|st| {
                    st.targets_sent += 1;
                    st.state = LinkState::Moving;
                    if latency.is_some() {
                        st.latency = latency;
                    }
                });
            }
        }
        Ok(())
    }

    async fn send(&self, s: &mut Session, msg: &TrackerMsg) -> Result<(), RobotError> {
        send_line(s, msg, self.addr(), self.cfg.peer_timeout_ms).await
    }
}

/// Writes one line with a timeout (a robot that stops reading must not block the client).
async fn send_line(
    s: &mut Session,
    msg: &TrackerMsg,
    addr: String,
    timeout_ms: u64,
) -> Result<(), RobotError> {
    let line = msg.encode().map_err(|e| RobotError::Protocol {
        addr: addr.clone(),
        source: e,
    })?;
    match timeout(Duration::from_millis(timeout_ms), s.wr.write_all(line.as_bytes())).await {
        Ok(Ok(())) => {
            s.last_tx = Instant::now();
            Ok(())
        }
        Ok(Err(e)) => Err(RobotError::Io {
            addr,
            what: "write",
            source: e,
        }),
        Err(_) => Err(RobotError::Timeout { addr, ms: timeout_ms }),
    }
}

struct AbortOnDrop(JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Reads bounded lines (≤ 80 bytes) and parses them; stops at the first error.
async fn read_lines<R: tokio::io::AsyncRead + Unpin>(
    mut rd: BufReader<R>,
    addr: String,
    tx: mpsc::Sender<Result<RobotMsg, RobotError>>,
) {
    let mut buf = Vec::with_capacity(robot_proto::MAX_LINE_BYTES + 1);
    loop {
        buf.clear();
        let n = match (&mut rd)
            .take(robot_proto::MAX_LINE_BYTES as u64)
            .read_until(b'\n', &mut buf)
            .await
        {
            Ok(n) => n,
            Err(e) => {
                let _ = tx
                    .send(Err(RobotError::Io {
                        addr,
                        what: "read",
                        source: e,
                    }))
                    .await;
                return;
            }
        };
        if n == 0 {
            return; // closed: dropping `tx` tells the session
        }
        let msg = if buf.last() != Some(&b'\n') {
            Err(irtrack_core::Error::Protocol {
                protocol: "robot",
                reason: format!(
                    "line longer than {} bytes or cut off",
                    robot_proto::MAX_LINE_BYTES
                ),
            })
        } else {
            match std::str::from_utf8(&buf) {
                Ok(text) => RobotMsg::parse(text),
                Err(_) => Err(irtrack_core::Error::Protocol {
                    protocol: "robot",
                    reason: "non-ASCII bytes".into(),
                }),
            }
        };
        let item = msg.map_err(|source| RobotError::Protocol {
            addr: addr.clone(),
            source,
        });
        let stop = item.is_err();
        if tx.send(item).await.is_err() || stop {
            return;
        }
    }
}
