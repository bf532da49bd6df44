//! Simulated streaming controllers (ABB EGM, KUKA RSI) for `host-tools robot-sim --egm/--rsi`,
//! the end-to-end tests and the latency benchmark.
//!
//! Like the real controllers, the simulation sends a packet every cycle (EGM 4 ms; RSI 4 ms on
//! KR C4 or 12 ms on KR C2) to the sensor, waits for the answer until the next cycle, and moves
//! its TCP toward the commanded position through a servo model: a first-order lag, then a
//! speed and an acceleration limit. A cycle without its answer counts as missed (an answer that
//! arrives in a later cycle is counted late and not used); after `max_missed` missed cycles in a
//! row the session stops, as EGM's communication timeout and RSI's late-packet limit do.

use std::io::Write;
use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use prost::Message;

use crate::RobotError;
use crate::egm::{self, EgmCartesian, EgmHeader, EgmPlanned, EgmPose, EgmQuaternion, EgmRobot, MessageType};
use crate::rsi;
use crate::udp::RsiMode;

/// Which controller is simulated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CtrlKind {
    /// An ABB controller speaking EGM.
    Egm,
    /// A KUKA controller speaking RSI, with its correction mode.
    Rsi(RsiMode),
}

/// Settings of a simulated controller.
#[derive(Debug, Clone)]
pub struct CtrlConfig {
    /// Which controller.
    pub kind: CtrlKind,
    /// irtrackd's UDP address.
    pub sensor: SocketAddr,
    /// Local address to send from (port 0 picks one).
    pub bind: SocketAddr,
    /// Interpolation cycle (4 ms = 250 Hz; KR C2's RSI: 12 ms ≈ 83 Hz).
    pub cycle_ms: f64,
    /// TCP at start.
    pub home_mm: [f64; 3],
    /// Time constant of the servo's first-order lag.
    pub servo_lag_ms: f64,
    /// Speed limit of the TCP (mm/s).
    pub max_speed_mm_s: f64,
    /// Acceleration limit of the TCP (mm/s²).
    pub max_accel_mm_s2: f64,
    /// Missed cycles in a row that stop the session (0 = never stop).
    pub max_missed: u32,
    /// Stop after this long (None = until stopped).
    pub duration_s: Option<f64>,
    /// Keep every cycle in [`CtrlRecord::path`] (tests; the CLI logs to CSV instead).
    pub keep_path: bool,
    /// Bind with `SO_REUSEPORT` and connect to the sensor, so a test's spoofer can send from
    /// this controller's very address and port ([`bind_shared_udp`]) while the replies still
    /// reach the controller (Linux gives a connected socket precedence). IPv4 only.
    pub share_port: bool,
}

impl CtrlConfig {
    /// Defaults close to a mid-size arm: 4 ms, 12 ms lag, 1 m/s, 5 m/s².
    pub fn new(kind: CtrlKind, sensor: SocketAddr) -> Self {
        Self {
            kind,
            sensor,
            bind: SocketAddr::from(([127, 0, 0, 1], 0)),
            cycle_ms: 4.0,
            home_mm: [0.0; 3],
            servo_lag_ms: 12.0,
            max_speed_mm_s: 1000.0,
            max_accel_mm_s2: 5000.0,
            max_missed: 25,
            duration_s: None,
            keep_path: false,
            share_port: false,
        }
    }
}

/// One cycle of the simulated controller.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CtrlCycle {
    /// CLOCK_MONOTONIC when the cycle's packet was sent (the clock irtrackd stamps frames with).
    pub t_ns: u64,
    /// The packet's number: EGM's `seqno` (from 1) or RSI's IPOC (ms-based).
    pub id: u64,
    /// Actual TCP.
    pub pos_mm: [f64; 3],
    /// Commanded TCP (the last answer's).
    pub cmd_mm: [f64; 3],
    /// The answer to this cycle arrived within it.
    pub answered: bool,
    /// CLOCK_MONOTONIC when that answer arrived (0 = none): at most a loopback hop after
    /// irtrackd sent it, so the marker's true position then is what the command should be.
    pub answer_ns: u64,
}

/// Counters and (optionally) the path.
#[derive(Debug, Clone, Default)]
pub struct CtrlRecord {
    /// Cycles sent.
    pub cycles: u64,
    /// Cycles answered within the cycle.
    pub answered: u64,
    /// Cycles without their answer.
    pub missed: u64,
    /// Answers that came in a later cycle than their own.
    pub late: u64,
    /// Answers that could not be decoded.
    pub malformed: u64,
    /// Longest run of missed cycles.
    pub max_missed_run: u32,
    /// Why the session stopped on its own (missed limit), if it did.
    pub stopped: Option<String>,
    /// Every cycle, when the path is kept.
    pub path: Vec<CtrlCycle>,
    /// Latest cycle (also when the path is not kept).
    pub last: Option<CtrlCycle>,
}

/// Servo model: first-order lag toward the command, then speed and acceleration limits.
#[derive(Debug, Clone, Copy)]
pub struct Servo {
    /// Actual TCP (mm).
    pub pos_mm: [f64; 3],
    /// Actual TCP velocity (mm/s).
    pub vel_mm_s: [f64; 3],
    /// Commanded TCP (mm).
    pub cmd_mm: [f64; 3],
    lag_s: f64,
    max_speed: f64,
    max_accel: f64,
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}

impl Servo {
    /// A servo at rest at `home_mm` commanded to stay there; `lag_ms` is the lag's time
    /// constant, `max_speed` (mm/s) and `max_accel` (mm/s²) its limits.
    pub fn new(home_mm: [f64; 3], lag_ms: f64, max_speed: f64, max_accel: f64) -> Self {
        Self {
            pos_mm: home_mm,
            vel_mm_s: [0.0; 3],
            cmd_mm: home_mm,
            lag_s: (lag_ms * 1e-3).max(1e-4),
            max_speed,
            max_accel,
        }
    }

    /// Advances `dt_s`.
    pub fn step(&mut self, dt_s: f64) {
        let mut want = [0.0; 3];
        for (i, w) in want.iter_mut().enumerate() {
            *w = (self.cmd_mm[i] - self.pos_mm[i]) / self.lag_s;
        }
        let s = norm(want);
        if s > self.max_speed {
            want = want.map(|v| v * self.max_speed / s);
        }
        let mut dv = [0.0; 3];
        for (i, d) in dv.iter_mut().enumerate() {
            *d = want[i] - self.vel_mm_s[i];
        }
        let a = norm(dv) / dt_s;
        if a > self.max_accel {
            dv = dv.map(|v| v * self.max_accel / a);
        }
        for ((v, p), d) in self.vel_mm_s.iter_mut().zip(&mut self.pos_mm).zip(dv) {
            *v += d;
            *p += *v * dt_s;
        }
    }
}

/// A simulated controller running on its own thread.
pub struct SimController {
    /// The address the controller sends from.
    pub local: SocketAddr,
    record: Arc<Mutex<CtrlRecord>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl SimController {
    /// Binds and starts sending; `log` (CSV) receives one row per cycle.
    pub fn spawn(cfg: CtrlConfig, log: Option<Box<dyn Write + Send>>) -> Result<Self, RobotError> {
        let bind = cfg.bind.to_string();
        let io = |what, source| RobotError::Io {
            addr: bind.clone(),
            what,
            source,
        };
        if !(cfg.cycle_ms.is_finite() && cfg.cycle_ms >= 1.0) {
            return Err(RobotError::Config {
                reason: format!("simulated controller cycle {} ms must be >= 1", cfg.cycle_ms),
            });
        }
        let sock = if cfg.share_port {
            let s = bind_shared_udp(cfg.bind).map_err(|e| io("bind", e))?;
            s.connect(cfg.sensor).map_err(|e| io("connect", e))?;
            s
        } else {
            UdpSocket::bind(cfg.bind).map_err(|e| io("bind", e))?
        };
        sock.set_nonblocking(true).map_err(|e| io("set_nonblocking", e))?;
        let local = sock.local_addr().map_err(|e| io("local_addr", e))?;
        let record = Arc::new(Mutex::new(CtrlRecord::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let (rec, st) = (record.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("ctrl-sim".into())
            .spawn(move || run(cfg, sock, rec, st, log))
            .map_err(|e| io("thread", e))?;
        Ok(Self {
            local,
            record,
            stop,
            thread: Some(thread),
        })
    }

    /// Snapshot of the counters and path.
    pub fn record(&self) -> CtrlRecord {
        self.record.lock().map(|r| r.clone()).unwrap_or_default()
    }

    /// The latest cycle.
    pub fn last(&self) -> Option<CtrlCycle> {
        self.record.lock().ok().and_then(|r| r.last)
    }

    /// True once the session ended (duration reached or missed limit).
    pub fn finished(&self) -> bool {
        self.thread.as_ref().is_none_or(|t| t.is_finished())
    }

    /// Stops and returns the record.
    pub fn stop(mut self) -> CtrlRecord {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        self.record()
    }
}

impl Drop for SimController {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A UDP socket bound to `addr` (IPv4) with `SO_REUSEPORT`, so that a second such socket can
/// bind the same address and port: how the tests send spoofed packets whose source is exactly
/// a controller's (what an attacker on the cell network can forge).
pub fn bind_shared_udp(addr: SocketAddr) -> std::io::Result<UdpSocket> {
    use std::os::fd::FromRawFd;
    let SocketAddr::V4(v4) = addr else {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{addr}: a shared port needs an IPv4 address"),
        ));
    };
    // SAFETY: plain socket(2); the descriptor is owned by the UdpSocket below or closed here.
    let fd = unsafe { libc::socket(libc::AF_INET, libc::SOCK_DGRAM | libc::SOCK_CLOEXEC, 0) };
    if fd < 0 {
        return Err(std::io::Error::last_os_error());
    }
    // SAFETY: `fd` is a socket we own; nothing else holds it.
    let sock = unsafe { UdpSocket::from_raw_fd(fd) };
    let one: libc::c_int = 1;
    // SAFETY: a valid socket and a c_int option value that outlives the call.
    let rc = unsafe {
        libc::setsockopt(
            fd,
            libc::SOL_SOCKET,
            libc::SO_REUSEPORT,
            (&one as *const libc::c_int).cast(),
            std::mem::size_of::<libc::c_int>() as libc::socklen_t,
        )
    };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    let sin = libc::sockaddr_in {
        sin_family: libc::AF_INET as libc::sa_family_t,
        sin_port: v4.port().to_be(),
        sin_addr: libc::in_addr {
            s_addr: u32::from(*v4.ip()).to_be(),
        },
        sin_zero: [0; 8],
    };
    // SAFETY: `sin` is a valid sockaddr_in of the size passed.
    let rc = unsafe {
        libc::bind(
            fd,
            (&sin as *const libc::sockaddr_in).cast(),
            std::mem::size_of::<libc::sockaddr_in>() as libc::socklen_t,
        )
    };
    if rc != 0 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(sock)
}

/// A controller packet as this simulation sends it, reporting the TCP at `pos_mm` (and
/// commanded there): what a spoofer in the tests forges.
pub fn encode_packet(kind: CtrlKind, id: u64, pos_mm: [f64; 3], out: &mut Vec<u8>) {
    robot_packet(kind, id, 0, &Servo::new(pos_mm, 12.0, 1000.0, 5000.0), out);
}

/// Encodes this cycle's controller packet.
fn robot_packet(kind: CtrlKind, id: u64, tm_ms: u32, s: &Servo, out: &mut Vec<u8>) {
    out.clear();
    match kind {
        CtrlKind::Egm => {
            let pose = |p: [f64; 3]| EgmPose {
                pos: Some(EgmCartesian {
                    x: p[0],
                    y: p[1],
                    z: p[2],
                }),
                orient: Some(EgmQuaternion {
                    u0: 1.0,
                    u1: 0.0,
                    u2: 0.0,
                    u3: 0.0,
                }),
                euler: None,
            };
            let msg = EgmRobot {
                header: Some(EgmHeader {
                    seqno: Some(id as u32),
                    tm: Some(tm_ms),
                    mtype: Some(MessageType::Data as i32),
                }),
                feed_back: Some(EgmPlanned {
                    cartesian: Some(pose(s.pos_mm)),
                    time: None,
                }),
                planned: Some(EgmPlanned {
                    cartesian: Some(pose(s.cmd_mm)),
                    time: None,
                }),
                motor_state: Some(egm::EgmMotorState {
                    state: egm::MotorState::On as i32,
                }),
                mci_state: Some(egm::EgmMciState {
                    state: egm::MciState::Running as i32,
                }),
                mci_convergence_met: Some(false),
                utilization_rate: None,
            };
            // Encoding into a Vec only fails for lack of capacity, which a Vec grows.
            let _ = msg.encode(out);
        }
        CtrlKind::Rsi(_) => {
            let p = s.pos_mm;
            let c = s.cmd_mm;
            let _ = write!(
                out,
                "<Rob Type=\"KUKA\"><RIst X=\"{:.4}\" Y=\"{:.4}\" Z=\"{:.4}\" A=\"180.0\" B=\"0.0\" C=\"180.0\"/><RSol X=\"{:.4}\" Y=\"{:.4}\" Z=\"{:.4}\" A=\"180.0\" B=\"0.0\" C=\"180.0\"/><Delay D=\"0\"/><IPOC>{id}</IPOC></Rob>",
                p[0], p[1], p[2], c[0], c[1], c[2]
            );
        }
    }
}

/// Decodes an answer: (cycle id it answers, commanded position).
fn answer(
    kind: CtrlKind,
    bytes: &[u8],
    start_mm: [f64; 3],
    cmd_mm: [f64; 3],
) -> Result<(u64, [f64; 3]), RobotError> {
    match kind {
        CtrlKind::Egm => {
            let bad = |reason: String| RobotError::Packet {
                protocol: "EGM",
                len: bytes.len(),
                reason,
            };
            let m = egm::EgmSensor::decode(bytes).map_err(|e| bad(format!("not an EgmSensor: {e}")))?;
            let seq = m
                .header
                .and_then(|h| h.seqno)
                .ok_or_else(|| bad("no header.seqno".into()))?;
            let p = m
                .planned
                .and_then(|p| p.cartesian)
                .and_then(|c| c.pos)
                .ok_or_else(|| bad("no planned.cartesian.pos".into()))?;
            Ok((u64::from(seq), [p.x, p.y, p.z]))
        }
        CtrlKind::Rsi(mode) => {
            let s = rsi::parse_sen(bytes)?;
            let base = match mode {
                RsiMode::Absolute => start_mm,
                RsiMode::Relative => cmd_mm,
            };
            Ok((
                s.ipoc,
                [
                    base[0] + s.korr_mm[0],
                    base[1] + s.korr_mm[1],
                    base[2] + s.korr_mm[2],
                ],
            ))
        }
    }
}

/// Waits until `sock` is readable (data, or a TCP peer that hung up) or `timeout` passes; true
/// when a read will not block. `ppoll` sleeps on a high-resolution timer; a socket read timeout
/// (`SO_RCVTIMEO`) is rounded up to scheduler ticks (4 ms at HZ=250, a whole EGM cycle; it woke
/// the socket robot-sim every 8-12 ms for its 4 ms tick). Also used by `host-tools robot-sim`.
pub fn wait_readable(sock: &impl std::os::fd::AsRawFd, timeout: Duration) -> bool {
    let mut fd = libc::pollfd {
        fd: sock.as_raw_fd(),
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: libc::c_long::from(timeout.subsec_nanos() as i32),
    };
    // SAFETY: one valid pollfd, a valid timespec, no signal mask; both outlive the call.
    let rc = unsafe { libc::ppoll(&mut fd, 1, &ts, std::ptr::null()) };
    rc > 0 && fd.revents & (libc::POLLIN | libc::POLLHUP) != 0
}

fn run(
    cfg: CtrlConfig,
    sock: UdpSocket,
    rec: Arc<Mutex<CtrlRecord>>,
    stop: Arc<AtomicBool>,
    mut log: Option<Box<dyn Write + Send>>,
) {
    let cycle = Duration::from_secs_f64(cfg.cycle_ms * 1e-3);
    let mut servo = Servo::new(
        cfg.home_mm,
        cfg.servo_lag_ms,
        cfg.max_speed_mm_s,
        cfg.max_accel_mm_s2,
    );
    let start_mm = cfg.home_mm;
    let t0 = Instant::now();
    // RSI's IPOC is a millisecond-based counter; EGM numbers packets from 1.
    let (mut id, id_step) = match cfg.kind {
        CtrlKind::Egm => (0u64, 1u64),
        CtrlKind::Rsi(_) => (1_000_000u64, cfg.cycle_ms.round().max(1.0) as u64),
    };
    let mut out = Vec::with_capacity(512);
    let mut buf = [0u8; 2048];
    let mut run = 0u32;
    if let Some(l) = log.as_mut() {
        let _ = writeln!(
            l,
            "t_s,mono_ns,id,x_mm,y_mm,z_mm,cmd_x_mm,cmd_y_mm,cmd_z_mm,answered"
        );
    }
    let mut next = Instant::now();
    while !stop.load(Ordering::SeqCst) {
        if cfg.duration_s.is_some_and(|d| t0.elapsed().as_secs_f64() >= d) {
            break;
        }
        id += id_step;
        let t_ns = crate::monotonic_ns();
        robot_packet(cfg.kind, id, t0.elapsed().as_millis() as u32, &servo, &mut out);
        if let Err(e) = sock.send_to(&out, cfg.sensor) {
            tracing::debug!("ctrl-sim: send: {e}");
        }
        let deadline = next + cycle;
        let mut answered = false;
        let mut answer_ns = 0;
        let (mut late, mut malformed) = (0, 0);
        loop {
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            if !wait_readable(&sock, deadline - now) {
                continue;
            }
            let n = match sock.recv(&mut buf) {
                Ok(n) => n,
                // WouldBlock after a spurious wake-up, or an ICMP error while the sensor is down.
                Err(_) => continue,
            };
            match answer(cfg.kind, &buf[..n], start_mm, servo.cmd_mm) {
                Ok((rid, cmd)) if rid == id => {
                    servo.cmd_mm = cmd;
                    answered = true;
                    answer_ns = crate::monotonic_ns();
                    // Keep waiting out the cycle: the controller's clock, not the answer, paces it.
                }
                Ok(_) => late += 1,
                Err(_) => malformed += 1,
            }
        }
        if let Some(wait) = deadline.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        next = deadline;
        // A loaded machine can fall behind: catch up rather than send bursts.
        if Instant::now() > next + cycle {
            next = Instant::now();
        }
        servo.step(cycle.as_secs_f64());
        let c = CtrlCycle {
            t_ns,
            id,
            pos_mm: servo.pos_mm,
            cmd_mm: servo.cmd_mm,
            answered,
            answer_ns,
        };
        if let Some(l) = log.as_mut() {
            let _ = writeln!(
                l,
                "{:.4},{t_ns},{id},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{}",
                t0.elapsed().as_secs_f64(),
                c.pos_mm[0],
                c.pos_mm[1],
                c.pos_mm[2],
                c.cmd_mm[0],
                c.cmd_mm[1],
                c.cmd_mm[2],
                u8::from(answered)
            );
        }
        run = if answered { 0 } else { run + 1 };
        let Ok(mut r) = rec.lock() else { return };
        r.cycles += 1;
        r.answered += u64::from(answered);
        r.missed += u64::from(!answered);
        r.late += late;
        r.malformed += malformed;
        r.max_missed_run = r.max_missed_run.max(run);
        r.last = Some(c);
        if cfg.keep_path {
            r.path.push(c);
        }
        if cfg.max_missed > 0 && run >= cfg.max_missed {
            r.stopped = Some(format!(
                "{run} cycles in a row without an answer (limit {})",
                cfg.max_missed
            ));
            break;
        }
    }
    if let Some(l) = log.as_mut() {
        let _ = l.flush();
    }
}
