//! Streaming links (ABB EGM, KUKA RSI): the controller sends a packet every interpolation cycle
//! and irtrackd answers each one at once with the position to go to. The protocol specifics
//! (decode, encode) are a [`StreamProto`]; the session handling, sequence checks, hold logic and
//! the safety gate are shared here, so both kinds behave identically.
//!
//! Hold rule: whenever the gate says hold, the reply commands the robot's own position as
//! reported in the packet where the hold began, and keeps commanding that point until motion
//! resumes: the robot stops where it is and never receives an older (stale) target.
//!
//! Packet checks (issue 41), in this order, before a packet can touch the session, the gate or
//! a reply: the source (the configured controller, or the one whose session runs), the decoding,
//! the sequence number (newer than the last accepted one, and at most a time-bounded window
//! ahead of it) and the reported position (no further from the last accepted one than the robot
//! can move in between). A packet failing any check is counted and not answered, and nothing in
//! it is used: not its sequence number, not its position (so never a hold point), not its
//! `RSol`. A hold therefore holds where the robot was as the accepted packets said.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;

use irtrack_core::robot_proto::HoldReason;
use serde::Deserialize;
use tokio::net::UdpSocket;
use tokio::sync::watch;
use tokio::time::Instant;

use crate::deadman::Deadman;
use crate::gate::Gate;
use crate::link::{LinkHandle, LinkState, LinkStatus, Refusal, RefusedPacket};
use crate::safety::{Sample, Verdict};
use crate::{Clock, LinkKind, PositionFeed, RobotConfig, RobotError};

/// RSI correction mode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RsiMode {
    /// `RKorr` is the whole offset from the pose the session started at.
    #[default]
    Absolute,
    /// `RKorr` is this cycle's increment (the controller sums them).
    Relative,
}

fn default_max_predict_mm() -> f64 {
    5.0
}
fn default_session_timeout_ms() -> u64 {
    500
}
fn default_rsi_sen_type() -> String {
    "ImFree".into()
}

/// `[robot.stream]`: options of the EGM and RSI links.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StreamConfig {
    /// Latency compensation: extrapolate the sample along the marker's velocity by its age at
    /// send time plus `predict_lead_ms`. Off by default.
    #[serde(default)]
    pub predict: bool,
    /// Extra lead beyond the sample's age (e.g. the controller's servo delay), ms.
    #[serde(default)]
    pub predict_lead_ms: f64,
    /// The extrapolation never moves the point further than this from the measured one.
    #[serde(default = "default_max_predict_mm")]
    pub max_predict_mm: f64,
    /// The session ends (and a new one starts held) when the controller is silent this long.
    #[serde(default = "default_session_timeout_ms")]
    pub session_timeout_ms: u64,
    /// RSI: absolute or relative (`RKorr` increments) corrections.
    #[serde(default)]
    pub rsi_mode: RsiMode,
    /// RSI: the `Type` attribute of `<Sen>`; must equal the controller's configured one.
    #[serde(default = "default_rsi_sen_type")]
    pub rsi_sen_type: String,
    /// The controller's address, `"ip"` (any source port) or `"ip:port"`: packets from
    /// anywhere else are refused from the start. Absent: the controller whose packet starts a
    /// session is pinned (address and port) for the session's life.
    #[serde(default)]
    pub controller: Option<String>,
    /// The fastest the TCP reported by the controller may move between two accepted packets
    /// (mm/s; a packet reporting more is refused). Absent: twice `robot.safety.max_speed_mm_s`.
    /// Raise it for RSI programs that move the robot themselves while correcting.
    #[serde(default)]
    pub max_robot_speed_mm_s: Option<f64>,
}

impl Default for StreamConfig {
    fn default() -> Self {
        Self {
            predict: false,
            predict_lead_ms: 0.0,
            max_predict_mm: default_max_predict_mm(),
            session_timeout_ms: default_session_timeout_ms(),
            rsi_mode: RsiMode::default(),
            rsi_sen_type: default_rsi_sen_type(),
            controller: None,
            max_robot_speed_mm_s: None,
        }
    }
}

impl StreamConfig {
    /// Checks the values; messages name the key.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.predict_lead_ms.is_finite() && (0.0..=100.0).contains(&self.predict_lead_ms)) {
            return Err(format!(
                "robot.stream.predict_lead_ms = {} must be in 0..=100",
                self.predict_lead_ms
            ));
        }
        if !(self.max_predict_mm.is_finite() && self.max_predict_mm >= 0.0) {
            return Err(format!(
                "robot.stream.max_predict_mm = {} must be >= 0",
                self.max_predict_mm
            ));
        }
        if self.session_timeout_ms == 0 {
            return Err("robot.stream.session_timeout_ms must be > 0".into());
        }
        let t = &self.rsi_sen_type;
        if t.is_empty() || t.len() > 32 || !t.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
            return Err(format!(
                "robot.stream.rsi_sen_type = {t:?} must be 1..=32 of [A-Za-z0-9_]"
            ));
        }
        if let Some(c) = &self.controller {
            ControllerAddr::parse(c)?;
        }
        if let Some(v) = self.max_robot_speed_mm_s
            && !(v.is_finite() && v > 0.0)
        {
            return Err(format!("robot.stream.max_robot_speed_mm_s = {v} must be > 0"));
        }
        Ok(())
    }
}

/// `[robot.stream] controller`: the address packets must come from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ControllerAddr {
    /// This address, any source port.
    Ip(IpAddr),
    /// This address and port.
    Exact(SocketAddr),
}

impl ControllerAddr {
    /// Parses `"ip"` or `"ip:port"` (`"[v6]:port"`); the message names the key.
    pub fn parse(text: &str) -> Result<Self, String> {
        if let Ok(a) = text.parse::<SocketAddr>() {
            if a.port() == 0 {
                return Err(format!(
                    "robot.stream.controller = {text:?}: port 0 is no controller's port (give \"ip\" for any port)"
                ));
            }
            return Ok(Self::Exact(a));
        }
        text.parse::<IpAddr>().map(Self::Ip).map_err(|_| {
            format!("robot.stream.controller = {text:?} must be \"ip\" or \"ip:port\" (numeric)")
        })
    }

    /// Whether a packet from `peer` comes from this controller (an IPv4 peer seen on an IPv6
    /// socket as `::ffff:a.b.c.d` counts as its IPv4 address).
    pub fn matches(&self, peer: SocketAddr) -> bool {
        let ip = peer.ip().to_canonical();
        match self {
            Self::Ip(a) => a.to_canonical() == ip,
            Self::Exact(a) => a.ip().to_canonical() == ip && a.port() == peer.port(),
        }
    }
}

impl std::fmt::Display for ControllerAddr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Ip(a) => write!(f, "{a} (any port)"),
            Self::Exact(a) => write!(f, "{a}"),
        }
    }
}

/// What irtrackd needs from one controller packet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobotPacket {
    /// EGM header seqno or RSI IPOC: increases every cycle.
    pub id: u64,
    /// The robot's actual TCP position (EGM feedback, RSI `RIst`), mm.
    pub pos_mm: [f64; 3],
    /// The robot's actual TCP orientation (w, x, y, z) when the packet carries one.
    pub quat_wxyz: Option<[f64; 4]>,
}

/// Position (and orientation) a reply commands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Command {
    /// Target position (mm).
    pub pos_mm: [f64; 3],
    /// Target orientation (w, x, y, z).
    pub quat_wxyz: [f64; 4],
}

/// One streaming protocol.
pub trait StreamProto: Send + 'static {
    /// The `[robot] kind` this protocol serves.
    const KIND: LinkKind;
    /// The protocol's state for one link.
    fn new(cfg: &StreamConfig) -> Self;
    /// Decodes a controller packet; a clear error for anything malformed.
    fn decode(&mut self, bytes: &[u8]) -> Result<RobotPacket, RobotError>;
    /// How many ids `id` is ahead of `last` (wrap-around aware where the protocol wraps);
    /// `None` when it is not newer (a duplicate or an older packet).
    fn ahead(id: u64, last: u64) -> Option<u64>;
    /// True when `id` comes after `last`.
    fn is_newer(id: u64, last: u64) -> bool {
        Self::ahead(id, last).is_some()
    }
    /// Sequence window: ids a packet may be ahead of the last accepted one, besides what
    /// [`Self::MAX_IDS_PER_S`] allows for the time since.
    const SEQ_SLACK_IDS: u64;
    /// The most ids a controller advances per second (its fastest cycle, with margin).
    const MAX_IDS_PER_S: u64;
    /// A session starts with this packet (the reference pose of relative protocols).
    fn on_session(&mut self, first: &RobotPacket);
    /// Writes the reply to `pkt` commanding `cmd` into `out` (cleared first).
    fn encode(&mut self, pkt: &RobotPacket, cmd: &Command, out: &mut Vec<u8>) -> Result<(), RobotError>;
}

/// Identity orientation (w, x, y, z), used when neither the robot nor the marker gives one.
const IDENTITY_WXYZ: [f64; 4] = [1.0, 0.0, 0.0, 0.0];

/// Binds the UDP address and starts the streaming link for `P` on the current tokio runtime.
pub fn spawn<P: StreamProto, F: PositionFeed, C: Clock>(
    cfg: RobotConfig,
    feed: F,
    clock: C,
    deadman: Arc<dyn Deadman>,
) -> Result<LinkHandle, RobotError> {
    cfg.validate()?;
    let io = |what, source| RobotError::Io {
        addr: cfg.address.clone(),
        what,
        source,
    };
    let std_sock = std::net::UdpSocket::bind(cfg.address.as_str()).map_err(|e| io("bind", e))?;
    std_sock
        .set_nonblocking(true)
        .map_err(|e| io("set_nonblocking", e))?;
    let sock = UdpSocket::from_std(std_sock).map_err(|e| io("register", e))?;
    let controller = cfg
        .stream
        .controller
        .as_deref()
        .map(ControllerAddr::parse)
        .transpose()
        .map_err(|reason| RobotError::Config { reason })?;
    let max_robot_speed_mm_s = cfg
        .stream
        .max_robot_speed_mm_s
        .unwrap_or(2.0 * cfg.safety.max_speed_mm_s);
    Ok(LinkHandle::start(move |ctl, status| {
        let link = Streamer {
            controller,
            max_robot_speed_mm_s,
            refusal_log: RefusalLog::default(),
            proto: P::new(&cfg.stream),
            gate: Gate::new(&cfg, feed, clock, deadman, ctl),
            predictor: Predictor::default(),
            cfg,
            sock,
            status,
            session: None,
        };
        link.run()
    }))
}

struct Session {
    /// The controller pinned for this session: packets from anywhere else are refused.
    peer: SocketAddr,
    /// Sequence number of the newest accepted packet.
    last_id: u64,
    /// When the newest packet was accepted (refused ones do not keep a session alive).
    last_rx: Instant,
    /// The robot's TCP as the newest accepted packet reported it.
    robot_pos_mm: [f64; 3],
    /// Where the robot is held while a hold lasts (its own position when the hold began).
    hold: Option<(HoldReason, Command)>,
    /// Orientation commanded when the marker gives none: the robot's at session start.
    orient_wxyz: [f64; 4],
}

/// Velocity extrapolation from the last two distinct samples.
#[derive(Default)]
struct Predictor {
    prev: Option<([f64; 3], u64)>,
    last: Option<([f64; 3], u64)>,
}

impl Predictor {
    fn observe(&mut self, s: &Sample) {
        let Some(p) = s.position_mm else {
            // A gap in tracking: velocity across it would be meaningless.
            self.prev = None;
            self.last = None;
            return;
        };
        if self.last.is_some_and(|(_, t)| t == s.capture_ts_ns) {
            return;
        }
        self.prev = self.last;
        self.last = Some((p, s.capture_ts_ns));
    }

    /// `s` moved ahead by `lead_s` along the marker's velocity, at most `max_mm` from it.
    fn predict(&self, s: &Sample, lead_s: f64, max_mm: f64) -> Sample {
        let (Some(p), Some((p0, t0)), Some((p1, t1))) = (s.position_mm, self.prev, self.last) else {
            return *s;
        };
        if t1 <= t0 || t1 != s.capture_ts_ns {
            return *s;
        }
        let dt_s = (t1 - t0) as f64 * 1e-9;
        let mut d = [0.0; 3];
        for i in 0..3 {
            d[i] = (p1[i] - p0[i]) / dt_s * lead_s;
        }
        let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let k = if n > max_mm && n > 0.0 { max_mm / n } else { 1.0 };
        Sample {
            position_mm: Some([p[0] + d[0] * k, p[1] + d[1] * k, p[2] + d[2] * k]),
            ..*s
        }
    }
}

/// Refusals are logged at most once a second per reason and source (a flood must not flood the
/// log); the lines in between are counted and reported with the next one.
#[derive(Default)]
struct RefusalLog {
    last: Option<(Refusal, SocketAddr, Instant)>,
    suppressed: u64,
}

impl RefusalLog {
    /// `Some(suppressed)` when this refusal is to be logged now.
    fn due(&mut self, reason: Refusal, from: SocketAddr, now: Instant) -> Option<u64> {
        let quiet = self.last.is_some_and(|(r, f, t)| {
            r == reason && f == from && now.duration_since(t) < Duration::from_secs(1)
        });
        if quiet {
            self.suppressed += 1;
            return None;
        }
        self.last = Some((reason, from, now));
        Some(std::mem::take(&mut self.suppressed))
    }
}

fn dist_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

struct Streamer<P, F, C> {
    cfg: RobotConfig,
    /// `[robot.stream] controller`, parsed.
    controller: Option<ControllerAddr>,
    /// Bound of the reported TCP's speed between accepted packets (mm/s).
    max_robot_speed_mm_s: f64,
    refusal_log: RefusalLog,
    proto: P,
    gate: Gate<F, C>,
    predictor: Predictor,
    sock: UdpSocket,
    status: watch::Sender<LinkStatus>,
    session: Option<Session>,
}

impl<P: StreamProto, F: PositionFeed, C: Clock> Streamer<P, F, C> {
    async fn run(mut self) {
        let local = self.sock.local_addr().ok();
        self.status.send_modify(|s| {
            s.kind = P::KIND;
            s.local_addr = local;
            s.state = LinkState::Connecting;
        });
        tracing::info!(
            "robot link ({}) listening on {:?}; holding until enabled",
            P::KIND.name(),
            local
        );
        let mut rx = vec![0u8; 4096];
        let mut tx = Vec::with_capacity(1024);
        let session_timeout = Duration::from_millis(self.cfg.stream.session_timeout_ms);
        let mut tick = tokio::time::interval(session_timeout / 4);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                r = self.sock.recv_from(&mut rx) => match r {
                    Ok((n, peer)) => {
                        if self.on_packet(&rx[..n], peer, &mut tx).await {
                            break;
                        }
                    }
                    Err(e) => {
                        // ICMP errors of an earlier send_to surface here on Linux; keep serving.
                        tracing::debug!("robot link ({}): receive: {e}", P::KIND.name());
                    }
                },
                r = self.gate.ctl.changed() => {
                    // Takes effect with the next packet; a session that starts later still
                    // begins held (`Gate::on_connect`).
                    if r.is_err() || self.gate.apply_control() {
                        break;
                    }
                }
                _ = tick.tick() => {
                    if self.session.as_ref().is_some_and(|s| s.last_rx.elapsed() > session_timeout) {
                        self.end_session("controller silent");
                    }
                }
            }
        }
        self.status.send_modify(|s| s.state = LinkState::Disconnected);
        self.gate.log_latency(P::KIND.name());
    }

    fn end_session(&mut self, why: &str) {
        if let Some(s) = self.session.take() {
            tracing::warn!("robot link ({}) {}: session ended: {why}", P::KIND.name(), s.peer);
            let msg = format!("{}: session ended: {why}", s.peer);
            self.status.send_modify(|st| {
                st.state = LinkState::Connecting;
                st.robot_pos_mm = None;
                st.controller = None;
                st.last_error = Some(msg);
            });
        }
    }

    /// Counts a refused packet, remembers it in words and logs it (rate-limited).
    fn refuse(&mut self, reason: Refusal, from: SocketAddr, now: Instant, words: String) {
        if let Some(suppressed) = self.refusal_log.due(reason, from, now) {
            if suppressed > 0 {
                tracing::warn!(
                    "robot link ({}) refused {words} ({suppressed} more refusals in the last second)",
                    P::KIND.name()
                );
            } else {
                tracing::warn!("robot link ({}) refused {words}", P::KIND.name());
            }
        }
        let at = now.into_std();
        self.status.send_if_modified(|st| {
            match reason {
                Refusal::Source => st.refused_source += 1,
                Refusal::Sequence => st.refused_sequence += 1,
                Refusal::Implausible => st.refused_implausible += 1,
                Refusal::Malformed => st.bad_packets += 1,
            }
            // Where the link reports its other errors, too (`/status` robot.last_error).
            st.last_error = Some(format!("refused {words}"));
            st.last_refused = Some(RefusedPacket {
                reason,
                from,
                words,
                at,
            });
            // Counters change with every packet; subscribers (LEDs) wake for state changes.
            false
        });
    }

    /// The checks of one datagram (module documentation): `Some(packet)` when it is accepted,
    /// `None` when it was refused or is older than the last accepted one (counted either way).
    fn check(&mut self, bytes: &[u8], peer: SocketAddr, now: Instant) -> Option<RobotPacket> {
        let timeout = Duration::from_millis(self.cfg.stream.session_timeout_ms);
        let live = self
            .session
            .as_ref()
            .filter(|s| now.duration_since(s.last_rx) <= timeout)
            .map(|s| (s.peer, s.last_id, s.last_rx, s.robot_pos_mm));
        if let Some(c) = self.controller
            && !c.matches(peer)
        {
            let words = format!("a packet from {peer}: the configured controller is {c}");
            self.refuse(Refusal::Source, peer, now, words);
            return None;
        }
        if let Some((pinned, ..)) = live
            && pinned != peer
        {
            let words = format!(
                "a packet from {peer}: the session with the controller {pinned} is running (a second controller or a spoofed sender)"
            );
            self.refuse(Refusal::Source, peer, now, words);
            return None;
        }
        // The RSI side keeps each decoded packet's RSol; a refused packet's is never used,
        // because every accepted packet's own decode replaces it right before its encode.
        let pkt = match self.proto.decode(bytes) {
            Ok(p) => p,
            Err(e) => {
                // Without a decodable packet there is no sequence number to answer to.
                self.refuse(
                    Refusal::Malformed,
                    peer,
                    now,
                    format!("a packet from {peer}: {e}"),
                );
                return None;
            }
        };
        let Some((_, last_id, last_rx, last_pos_mm)) = live else {
            return Some(pkt);
        };
        let Some(ahead) = P::ahead(pkt.id, last_id) else {
            // Duplicated or overtaken packet: the newer one was answered already.
            self.status.send_if_modified(|st| {
                st.out_of_order += 1;
                false
            });
            return None;
        };
        let since = now.duration_since(last_rx);
        let window = P::SEQ_SLACK_IDS + P::MAX_IDS_PER_S.saturating_mul(since.as_millis() as u64) / 1000;
        if ahead > window {
            let words = format!(
                "a packet from {peer}: sequence number {} is {ahead} ahead of the last accepted {last_id}, at most {window} allowed {} ms later",
                pkt.id,
                since.as_millis()
            );
            self.refuse(Refusal::Sequence, peer, now, words);
            return None;
        }
        let moved_mm = dist_mm(pkt.pos_mm, last_pos_mm);
        let limit_mm = self.cfg.safety.max_step_mm + self.max_robot_speed_mm_s * since.as_secs_f64();
        if moved_mm.is_nan() || moved_mm > limit_mm {
            let words = format!(
                "a packet from {peer}: it reports the robot {moved_mm:.1} mm from where it was {} ms earlier, at most {limit_mm:.1} mm possible",
                since.as_millis()
            );
            self.refuse(Refusal::Implausible, peer, now, words);
            return None;
        }
        Some(pkt)
    }

    /// Handles one datagram; true when the link must stop.
    async fn on_packet(&mut self, bytes: &[u8], peer: SocketAddr, tx: &mut Vec<u8>) -> bool {
        let now = Instant::now();
        let Some(pkt) = self.check(bytes, peer, now) else {
            return false;
        };
        let timeout = Duration::from_millis(self.cfg.stream.session_timeout_ms);
        let live = self
            .session
            .as_ref()
            .is_some_and(|s| now.duration_since(s.last_rx) <= timeout);
        if !live {
            if self.session.is_some() {
                self.end_session("controller silent (no packet accepted within session_timeout_ms)");
            }
            self.start_session(&pkt, peer, now);
        }
        if self.gate.poll_control() {
            return true;
        }
        self.gate.sup.on_robot_position(pkt.pos_mm);
        self.gate.refresh();
        let cur = self.gate.cur;
        if let Some(c) = &cur {
            self.predictor.observe(c);
        }
        let judged = match (&cur, self.cfg.stream.predict) {
            (Some(c), true) => {
                let age_s = self.gate.now_ns().saturating_sub(c.capture_ts_ns) as f64 * 1e-9;
                let lead_s = age_s + self.cfg.stream.predict_lead_ms * 1e-3;
                Some(self.predictor.predict(c, lead_s, self.cfg.stream.max_predict_mm))
            }
            (c, _) => *c,
        };
        let verdict = self.gate.verdict(judged.as_ref());
        let Some(session) = self.session.as_mut() else {
            return false;
        };
        session.last_id = pkt.id;
        session.last_rx = now;
        session.robot_pos_mm = pkt.pos_mm;
        let (cmd, sent_ts, new_hold) = match verdict {
            Verdict::Send { pos_mm, quat_wxyz } => {
                session.hold = None;
                let cmd = Command {
                    pos_mm,
                    quat_wxyz: quat_wxyz.unwrap_or(session.orient_wxyz),
                };
                (cmd, judged.map(|s| s.capture_ts_ns), None)
            }
            Verdict::Hold(reason) => match session.hold {
                Some((_, cmd)) => {
                    session.hold = Some((reason, cmd));
                    (cmd, None, None)
                }
                None => {
                    // This packet passed every check: its position is the robot's as the
                    // accepted packets know it.
                    let cmd = Command {
                        pos_mm: pkt.pos_mm,
                        quat_wxyz: pkt.quat_wxyz.unwrap_or(session.orient_wxyz),
                    };
                    session.hold = Some((reason, cmd));
                    (cmd, None, Some(reason))
                }
            },
        };
        if let Err(e) = self.proto.encode(&pkt, &cmd, tx) {
            tracing::warn!("robot link ({}): {e}", P::KIND.name());
            self.status.send_if_modified(|st| {
                st.last_error = Some(e.to_string());
                false
            });
            return false;
        }
        if let Err(e) = self.sock.send_to(tx, peer).await {
            tracing::warn!("robot link ({}) {peer}: send: {e}", P::KIND.name());
            return false;
        }
        if let Some(ts) = sent_ts {
            self.gate.record_sent(ts);
            if let Verdict::Send { pos_mm, quat_wxyz } = verdict {
                self.gate.sup.committed(pos_mm, quat_wxyz, ts);
            }
        }
        if let Some(reason) = new_hold {
            tracing::info!("robot hold ({}): {}", P::KIND.name(), reason.text());
        }
        let state = match verdict {
            Verdict::Send { .. } => LinkState::Moving,
            Verdict::Hold(r) => LinkState::Holding(r),
        };
        let latency = self.gate.latency_summary_due();
        // Counters change every cycle; subscribers (LEDs) are woken only by state changes.
        self.status.send_if_modified(|st| {
            st.packets_answered += 1;
            if latency.is_some() {
                st.latency = latency;
            }
            st.robot_pos_mm = Some(pkt.pos_mm);
            match verdict {
                Verdict::Send { .. } => st.targets_sent += 1,
                Verdict::Hold(_) if new_hold.is_some() => st.holds_sent += 1,
                Verdict::Hold(_) => {}
            }
            let changed = st.state != state;
            st.state = state;
            changed
        });
        false
    }

    fn start_session(&mut self, pkt: &RobotPacket, peer: SocketAddr, now: Instant) {
        self.proto.on_session(pkt);
        self.gate.on_connect(pkt.pos_mm);
        self.predictor = Predictor::default();
        let orient_wxyz = pkt.quat_wxyz.unwrap_or(IDENTITY_WXYZ);
        self.session = Some(Session {
            peer,
            // The first packet is answered; anything older than it afterwards is not.
            last_id: pkt.id,
            last_rx: now,
            robot_pos_mm: pkt.pos_mm,
            hold: None,
            orient_wxyz,
        });
        tracing::info!(
            "robot link ({}) {peer}: session started (packets from elsewhere are refused while it runs); holding until enabled",
            P::KIND.name()
        );
        let name = format!("{} controller {peer}", P::KIND.name());
        self.status.send_modify(|st| {
            st.connects += 1;
            st.controller = Some(peer);
            st.robot_name = Some(name);
            st.state = LinkState::Holding(HoldReason::NotEnabled);
        });
    }
}
