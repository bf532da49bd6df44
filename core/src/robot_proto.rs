//! Robot link protocol v1 (see docs/robot-protocol.md): short ASCII lines with fixed-width fields.
//!
//! The tracker is the TCP client, the robot controller the server. Every line, including its
//! `'\n'`, is at most [`MAX_LINE_BYTES`] bytes because RAPID's `SocketReceive \Str` returns at most
//! 80 characters. Fields sit at fixed columns so the RAPID side can cut them with `StrPart` and
//! convert them with `StrToVal`; the `*_COL` constants below are the 1-based columns RAPID uses and
//! `rapid/IrTrack.mod` declares the same values (a test compares them).
//!
//! Encoding writes into a fixed [`LineBuf`] (no allocation); parsing is strict: any deviation from
//! the fixed layout is an [`Error::Protocol`] naming the problem.
//!
//! The robot side as a state machine (`SimRobot`, used by `host-tools robot-sim` and the tests)
//! lives in the `irtrack-robot` crate.

use alloc::string::{String, ToString};
use core::fmt::{self, Write};

use crate::error::{Error, Result};

/// Protocol version carried in `HELLO`.
pub const PROTOCOL_VERSION: u8 = 1;
/// Longest line on the wire, newline included (RAPID string limit).
pub const MAX_LINE_BYTES: usize = 80;
/// Sequence numbers are six decimal digits and wrap modulo this value.
pub const SEQ_MODULUS: u32 = 1_000_000;
/// Largest coordinate magnitude representable in `±dddd.dd`.
pub const MAX_COORD_MM: f64 = 9999.99;
/// Longest name in `HELLO` and longest reason text in `X`.
pub const MAX_NAME_CHARS: usize = 24;
/// Largest credit window the robot may grant.
pub const MAX_WINDOW: u8 = 99;

/// 1-based columns of the fixed-width fields (what RAPID's `StrPart` uses).
pub const SEQ_COL: usize = 3;
/// Length of a sequence field.
pub const SEQ_LEN: usize = 6;
/// Length of a coordinate field `±dddd.dd`.
pub const COORD_LEN: usize = 8;
/// Length of a quaternion component field `±d.dddddd`.
pub const QUAT_LEN: usize = 9;
/// `T`/`Q`: columns of x, y, z.
pub const T_X_COL: usize = 10;
/// `T`/`Q`: column of y.
pub const T_Y_COL: usize = 19;
/// `T`/`Q`: column of z.
pub const T_Z_COL: usize = 28;
/// `Q`: column of the first quaternion component (q1 = w); the others follow every 10 columns.
pub const Q_Q1_COL: usize = 37;
/// `C`: column of the window field and of x, y, z.
pub const C_WIN_COL: usize = 10;
/// `C`: column of x (y and z follow every 9 columns, as in `T`).
pub const C_X_COL: usize = 13;
/// `HOLD`: column of the reason code.
pub const HOLD_CODE_COL: usize = 6;
/// `BEAT`: column of the counter.
pub const BEAT_COL: usize = 6;
/// `POSE`: column of the request counter (same place as `BEAT`'s).
pub const POSE_COL: usize = 6;
/// `A`: columns of x, y, z and q1 (same layout as `Q`).
pub const A_X_COL: usize = T_X_COL;
/// `A`: column of q1 (as `Q`).
pub const A_Q1_COL: usize = Q_Q1_COL;

const PROTO: &str = "robot";

fn err(reason: impl Into<String>) -> Error {
    Error::Protocol {
        protocol: PROTO,
        reason: reason.into(),
    }
}

/// One encoded line (newline included) in a fixed buffer.
#[derive(Clone, Copy)]
pub struct LineBuf {
    bytes: [u8; MAX_LINE_BYTES],
    len: usize,
    overflow: bool,
}

impl LineBuf {
    /// An empty line buffer.
    pub const fn new() -> Self {
        Self {
            bytes: [0; MAX_LINE_BYTES],
            len: 0,
            overflow: false,
        }
    }
    /// The encoded bytes, newline included.
    pub fn as_bytes(&self) -> &[u8] {
        &self.bytes[..self.len]
    }
    /// The encoded line as text (always ASCII).
    pub fn as_str(&self) -> &str {
        core::str::from_utf8(self.as_bytes()).unwrap_or("")
    }
    /// Length in bytes, newline included.
    pub fn len(&self) -> usize {
        self.len
    }
    /// True when nothing was written.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
}

impl Default for LineBuf {
    fn default() -> Self {
        Self::new()
    }
}

impl fmt::Debug for LineBuf {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.as_str())
    }
}

impl Write for LineBuf {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        let b = s.as_bytes();
        if self.len + b.len() > MAX_LINE_BYTES {
            self.overflow = true;
            return Err(fmt::Error);
        }
        self.bytes[self.len..self.len + b.len()].copy_from_slice(b);
        self.len += b.len();
        Ok(())
    }
}

/// Why the tracker holds the robot (`HOLD nn TEXT`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HoldReason {
    /// Operator has not enabled motion (after start or reconnect).
    NotEnabled,
    /// Deadman / enabling input released.
    Deadman,
    /// No marker position.
    MarkerLost,
    /// Ray gap or blob quality beyond the limit.
    PoorQuality,
    /// Newest position is older than the allowed age.
    Stale,
    /// Target outside the workspace box.
    Workspace,
    /// Step from the previous target too large.
    StepTooLarge,
    /// Implied speed above the limit.
    TooFast,
    /// Tracker shutting down or operator stop.
    Stop,
}

impl HoldReason {
    /// All reasons, for exhaustive tests.
    pub const ALL: [HoldReason; 9] = [
        HoldReason::NotEnabled,
        HoldReason::Deadman,
        HoldReason::MarkerLost,
        HoldReason::PoorQuality,
        HoldReason::Stale,
        HoldReason::Workspace,
        HoldReason::StepTooLarge,
        HoldReason::TooFast,
        HoldReason::Stop,
    ];
    /// Two-digit wire code.
    pub fn code(self) -> u8 {
        match self {
            HoldReason::NotEnabled => 1,
            HoldReason::Deadman => 2,
            HoldReason::MarkerLost => 3,
            HoldReason::PoorQuality => 4,
            HoldReason::Stale => 5,
            HoldReason::Workspace => 6,
            HoldReason::StepTooLarge => 7,
            HoldReason::TooFast => 8,
            HoldReason::Stop => 9,
        }
    }
    /// Upper-case wire text (informative; RAPID logs it).
    pub fn text(self) -> &'static str {
        match self {
            HoldReason::NotEnabled => "NOT_ENABLED",
            HoldReason::Deadman => "DEADMAN",
            HoldReason::MarkerLost => "MARKER_LOST",
            HoldReason::PoorQuality => "POOR_QUALITY",
            HoldReason::Stale => "STALE",
            HoldReason::Workspace => "WORKSPACE",
            HoldReason::StepTooLarge => "STEP_TOO_LARGE",
            HoldReason::TooFast => "TOO_FAST",
            HoldReason::Stop => "STOP",
        }
    }
    /// Reason from its wire code.
    pub fn from_code(code: u8) -> Result<Self> {
        Self::ALL
            .iter()
            .copied()
            .find(|r| r.code() == code)
            .ok_or_else(|| err(alloc::format!("unknown HOLD reason code {code:02}")))
    }
}

/// Lines the tracker (client) sends.
#[derive(Debug, Clone, PartialEq)]
pub enum TrackerMsg {
    /// `HELLO 01 TRACKER name`
    Hello {
        /// Protocol version the tracker speaks.
        version: u8,
        /// The tracker's name (one word).
        name: String,
    },
    /// `T ssssss ±xxxx.xx ±yyyy.yy ±zzzz.zz` — position target in the robot base frame.
    Target {
        /// Target sequence number.
        seq: u32,
        /// Target position, robot base frame, mm.
        pos_mm: [f64; 3],
    },
    /// `Q ssssss x y z q1 q2 q3 q4` — 6-DOF target; quaternion w, x, y, z as in RAPID's `orient`.
    Pose {
        /// Target sequence number.
        seq: u32,
        /// Target position, robot base frame, mm.
        pos_mm: [f64; 3],
        /// Target orientation, unit quaternion w, x, y, z.
        quat_wxyz: [f64; 4],
    },
    /// `HOLD nn TEXT` — stop, drop queued targets, wait.
    Hold {
        /// Why the robot must hold.
        reason: HoldReason,
    },
    /// `BEAT nnnnnn`
    Beat {
        /// Heartbeat counter.
        counter: u32,
    },
    /// `POSE nnnnnn` — ask for the robot's actual TCP pose (answered with `A nnnnnn …`, the same
    /// counter). Used by `host-tools survey`; no credit needed, the robot answers at standstill.
    PoseRequest {
        /// Request counter, repeated in the answer.
        counter: u32,
    },
    /// `BYE`
    Bye,
}

/// Lines the robot (server) sends.
#[derive(Debug, Clone, PartialEq)]
pub enum RobotMsg {
    /// `HELLO 01 ROBOT name`
    Hello {
        /// Protocol version the robot speaks.
        version: u8,
        /// The robot's name (one word).
        name: String,
    },
    /// `C ssssss ww ±x ±y ±z` — everything up to `ack_seq` is done; the tracker may have `window`
    /// targets outstanding beyond it; the robot's current TCP position. `C 000000 ..` right after
    /// `HELLO` is the "ready" signal.
    Credit {
        /// Every target up to this sequence number is done.
        ack_seq: u32,
        /// Targets the tracker may have outstanding beyond `ack_seq`.
        window: u8,
        /// The robot's current TCP position, base frame, mm.
        pos_mm: [f64; 3],
    },
    /// `X ssssss nn TEXT` — target `seq` rejected (it still counts as consumed).
    Reject {
        /// The rejected target's sequence number.
        seq: u32,
        /// Reason code (docs/robot-protocol.md).
        code: u8,
        /// The reason in words.
        reason: String,
    },
    /// `A nnnnnn ±x ±y ±z q1 q2 q3 q4` — answer to `POSE nnnnnn`: the robot's actual TCP pose as
    /// the controller knows it (RAPID `CRobT`), position in the base frame and orientation
    /// w, x, y, z (RAPID `orient`). Same columns as `Q`.
    Actual {
        /// The counter of the `POSE` request answered.
        counter: u32,
        /// TCP position, base frame, mm.
        pos_mm: [f64; 3],
        /// TCP orientation, unit quaternion w, x, y, z.
        quat_wxyz: [f64; 4],
    },
    /// `BEAT nnnnnn`
    Beat {
        /// Heartbeat counter.
        counter: u32,
    },
    /// `BYE`
    Bye,
}

/// Reject codes the robot side uses.
pub mod reject {
    /// Target outside the robot's reach or joint limits.
    pub const UNREACHABLE: u8 = 1;
    /// Rejected by the simulator's fault injection.
    pub const INJECTED: u8 = 2;
    /// Target sent without credit.
    pub const NO_CREDIT: u8 = 98;
    /// Line did not parse.
    pub const MALFORMED: u8 = 99;
}

fn check_seq(seq: u32) -> Result<()> {
    if seq >= SEQ_MODULUS {
        return Err(err(alloc::format!("sequence {seq} exceeds 6 digits")));
    }
    Ok(())
}

fn check_name(name: &str, what: &str) -> Result<()> {
    if name.is_empty() || name.len() > MAX_NAME_CHARS {
        return Err(err(alloc::format!(
            "{what} must be 1..={MAX_NAME_CHARS} characters"
        )));
    }
    if !name
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b"-_.".contains(&b))
    {
        return Err(err(alloc::format!(
            "{what} {name:?} has characters outside [A-Za-z0-9._-]"
        )));
    }
    Ok(())
}

fn write_coord(buf: &mut LineBuf, v_mm: f64) -> Result<()> {
    let r = libm::round(v_mm * 100.0) / 100.0;
    if !r.is_finite() || libm::fabs(r) > MAX_COORD_MM {
        return Err(err(alloc::format!(
            "coordinate {v_mm} mm outside ±{MAX_COORD_MM}"
        )));
    }
    // `+ 0.0` turns -0.0 into +0.0 so the sign column is stable.
    write!(buf, " {:+08.2}", r + 0.0).map_err(|_| err("line too long"))
}

fn write_quat(buf: &mut LineBuf, q: f64) -> Result<()> {
    let r = libm::round(q * 1e6) / 1e6;
    if !r.is_finite() || libm::fabs(r) > 1.0 {
        return Err(err(alloc::format!("quaternion component {q} outside ±1")));
    }
    write!(buf, " {:+09.6}", r + 0.0).map_err(|_| err("line too long"))
}

fn check_unit_quat(q: &[f64; 4]) -> Result<()> {
    let n = libm::sqrt(q.iter().map(|c| c * c).sum::<f64>());
    if !(n > 0.99 && n < 1.01) {
        return Err(err(alloc::format!("quaternion norm {n} is not 1")));
    }
    Ok(())
}

fn finish(mut buf: LineBuf) -> Result<LineBuf> {
    buf.write_str("\n")
        .map_err(|_| err("line longer than 80 bytes"))?;
    Ok(buf)
}

impl TrackerMsg {
    /// Encodes into one line (newline included); values that do not fit the fixed layout are errors.
    pub fn encode(&self) -> Result<LineBuf> {
        let mut b = LineBuf::new();
        let w = |r: fmt::Result| r.map_err(|_| err("line longer than 80 bytes"));
        match self {
            TrackerMsg::Hello { version, name } => {
                check_name(name, "tracker name")?;
                w(write!(b, "HELLO {version:02} TRACKER {name}"))?;
            }
            TrackerMsg::Target { seq, pos_mm } => {
                check_seq(*seq)?;
                w(write!(b, "T {seq:06}"))?;
                for v in pos_mm {
                    write_coord(&mut b, *v)?;
                }
            }
            TrackerMsg::Pose {
                seq,
                pos_mm,
                quat_wxyz,
            } => {
                check_seq(*seq)?;
                check_unit_quat(quat_wxyz)?;
                w(write!(b, "Q {seq:06}"))?;
                for v in pos_mm {
                    write_coord(&mut b, *v)?;
                }
                for q in quat_wxyz {
                    write_quat(&mut b, *q)?;
                }
            }
            TrackerMsg::Hold { reason } => w(write!(b, "HOLD {:02} {}", reason.code(), reason.text()))?,
            TrackerMsg::Beat { counter } => {
                check_seq(*counter)?;
                w(write!(b, "BEAT {counter:06}"))?;
            }
            TrackerMsg::PoseRequest { counter } => {
                check_seq(*counter)?;
                w(write!(b, "POSE {counter:06}"))?;
            }
            TrackerMsg::Bye => w(b.write_str("BYE"))?,
        }
        finish(b)
    }

    /// Parses one line (with or without its trailing `'\n'`).
    pub fn parse(line: &str) -> Result<Self> {
        let l = Fields::new(line)?;
        match l.tag() {
            "HELLO" => {
                let (version, name) = l.hello("TRACKER")?;
                Ok(TrackerMsg::Hello { version, name })
            }
            "T" => {
                l.expect_len(T_Z_COL - 1 + COORD_LEN)?;
                Ok(TrackerMsg::Target {
                    seq: l.seq()?,
                    pos_mm: l.xyz(T_X_COL)?,
                })
            }
            "Q" => {
                let (pos_mm, quat_wxyz) = l.pose()?;
                Ok(TrackerMsg::Pose {
                    seq: l.seq()?,
                    pos_mm,
                    quat_wxyz,
                })
            }
            "HOLD" => {
                let code = l.uint(HOLD_CODE_COL, 2)? as u8;
                let reason = HoldReason::from_code(code)?;
                l.sep(HOLD_CODE_COL + 2)?;
                let text = l.rest(HOLD_CODE_COL + 3);
                if text != reason.text() {
                    return Err(err(alloc::format!("HOLD code {code:02} with text {text:?}")));
                }
                Ok(TrackerMsg::Hold { reason })
            }
            "BEAT" => Ok(TrackerMsg::Beat { counter: l.beat()? }),
            "POSE" => Ok(TrackerMsg::PoseRequest { counter: l.beat()? }),
            "BYE" => {
                l.expect_len(3)?;
                Ok(TrackerMsg::Bye)
            }
            other => Err(err(alloc::format!("unknown tracker message tag {other:?}"))),
        }
    }
}

impl RobotMsg {
    /// Encodes into one line (newline included).
    pub fn encode(&self) -> Result<LineBuf> {
        let mut b = LineBuf::new();
        let w = |r: fmt::Result| r.map_err(|_| err("line longer than 80 bytes"));
        match self {
            RobotMsg::Hello { version, name } => {
                check_name(name, "robot name")?;
                w(write!(b, "HELLO {version:02} ROBOT {name}"))?;
            }
            RobotMsg::Credit {
                ack_seq,
                window,
                pos_mm,
            } => {
                check_seq(*ack_seq)?;
                if *window > MAX_WINDOW {
                    return Err(err(alloc::format!("credit window {window} > {MAX_WINDOW}")));
                }
                w(write!(b, "C {ack_seq:06} {window:02}"))?;
                for v in pos_mm {
                    write_coord(&mut b, *v)?;
                }
            }
            RobotMsg::Reject { seq, code, reason } => {
                check_seq(*seq)?;
                check_name(reason, "reject reason")?;
                w(write!(b, "X {seq:06} {code:02} {reason}"))?;
            }
            RobotMsg::Actual {
                counter,
                pos_mm,
                quat_wxyz,
            } => {
                check_seq(*counter)?;
                check_unit_quat(quat_wxyz)?;
                w(write!(b, "A {counter:06}"))?;
                for v in pos_mm {
                    write_coord(&mut b, *v)?;
                }
                for q in quat_wxyz {
                    write_quat(&mut b, *q)?;
                }
            }
            RobotMsg::Beat { counter } => {
                check_seq(*counter)?;
                w(write!(b, "BEAT {counter:06}"))?;
            }
            RobotMsg::Bye => w(b.write_str("BYE"))?,
        }
        finish(b)
    }

    /// Parses one line (with or without its trailing `'\n'`).
    pub fn parse(line: &str) -> Result<Self> {
        let l = Fields::new(line)?;
        match l.tag() {
            "HELLO" => {
                let (version, name) = l.hello("ROBOT")?;
                Ok(RobotMsg::Hello { version, name })
            }
            "C" => {
                l.expect_len(C_X_COL - 1 + 3 * (COORD_LEN + 1) - 1)?;
                let window = l.uint(C_WIN_COL, 2)? as u8;
                l.sep(C_WIN_COL - 1)?;
                Ok(RobotMsg::Credit {
                    ack_seq: l.seq()?,
                    window,
                    pos_mm: l.xyz(C_X_COL)?,
                })
            }
            "X" => {
                let seq = l.seq()?;
                l.sep(SEQ_COL + SEQ_LEN)?;
                let code = l.uint(SEQ_COL + SEQ_LEN + 1, 2)? as u8;
                l.sep(SEQ_COL + SEQ_LEN + 3)?;
                let reason = l.rest(SEQ_COL + SEQ_LEN + 4).to_string();
                check_name(&reason, "reject reason")?;
                Ok(RobotMsg::Reject { seq, code, reason })
            }
            "A" => {
                let (pos_mm, quat_wxyz) = l.pose()?;
                Ok(RobotMsg::Actual {
                    counter: l.seq()?,
                    pos_mm,
                    quat_wxyz,
                })
            }
            "BEAT" => Ok(RobotMsg::Beat { counter: l.beat()? }),
            "BYE" => {
                l.expect_len(3)?;
                Ok(RobotMsg::Bye)
            }
            other => Err(err(alloc::format!("unknown robot message tag {other:?}"))),
        }
    }
}

/// A validated line split into fixed columns.
struct Fields<'a> {
    s: &'a str,
}

impl<'a> Fields<'a> {
    fn new(line: &'a str) -> Result<Self> {
        let s = line.strip_suffix('\n').unwrap_or(line);
        if s.len() + 1 > MAX_LINE_BYTES {
            return Err(err(alloc::format!(
                "line of {} bytes exceeds {MAX_LINE_BYTES}",
                s.len() + 1
            )));
        }
        if s.is_empty() {
            return Err(err("empty line"));
        }
        if let Some(b) = s.bytes().find(|b| !(0x20..0x7f).contains(b)) {
            return Err(err(alloc::format!("non-printable byte 0x{b:02x}")));
        }
        Ok(Self { s })
    }
    fn tag(&self) -> &'a str {
        self.s.split(' ').next().unwrap_or("")
    }
    fn expect_len(&self, n: usize) -> Result<()> {
        if self.s.len() != n {
            return Err(err(alloc::format!(
                "{} line has {} characters, expected {n}",
                self.tag(),
                self.s.len()
            )));
        }
        Ok(())
    }
    /// Field at 1-based column `col` with `len` characters.
    fn field(&self, col: usize, len: usize) -> Result<&'a str> {
        self.s
            .get(col - 1..col - 1 + len)
            .ok_or_else(|| err(alloc::format!("line too short for column {col}")))
    }
    fn sep(&self, col: usize) -> Result<()> {
        if self.field(col, 1)? != " " {
            return Err(err(alloc::format!("expected a space at column {col}")));
        }
        Ok(())
    }
    fn rest(&self, col: usize) -> &'a str {
        self.s.get(col - 1..).unwrap_or("")
    }
    fn uint(&self, col: usize, len: usize) -> Result<u32> {
        let f = self.field(col, len)?;
        if !f.bytes().all(|b| b.is_ascii_digit()) {
            return Err(err(alloc::format!("{f:?} at column {col} is not {len} digits")));
        }
        Ok(f.bytes().fold(0u32, |a, b| a * 10 + u32::from(b - b'0')))
    }
    fn seq(&self) -> Result<u32> {
        self.sep(SEQ_COL - 1)?;
        self.uint(SEQ_COL, SEQ_LEN)
    }
    fn beat(&self) -> Result<u32> {
        self.expect_len(BEAT_COL - 1 + SEQ_LEN)?;
        self.sep(BEAT_COL - 1)?;
        self.uint(BEAT_COL, SEQ_LEN)
    }
    /// Signed fixed-point field `±` + `int_digits` + `.` + `frac_digits`, preceded by a space.
    fn fixed(&self, col: usize, int_digits: usize, frac_digits: usize) -> Result<f64> {
        self.sep(col - 1)?;
        let len = 1 + int_digits + 1 + frac_digits;
        let f = self.field(col, len)?;
        let b = f.as_bytes();
        let sign = match b[0] {
            b'+' => 1.0,
            b'-' => -1.0,
            _ => return Err(err(alloc::format!("{f:?} at column {col} lacks a sign"))),
        };
        if b[1 + int_digits] != b'.' {
            return Err(err(alloc::format!(
                "{f:?} at column {col} lacks the decimal point"
            )));
        }
        let mut v: u64 = 0;
        for (i, &c) in b[1..].iter().enumerate() {
            if i == int_digits {
                continue;
            }
            if !c.is_ascii_digit() {
                return Err(err(alloc::format!("{f:?} at column {col} has a non-digit")));
            }
            v = v * 10 + u64::from(c - b'0');
        }
        Ok(sign * v as f64 / libm::pow(10.0, frac_digits as f64))
    }
    fn xyz(&self, col: usize) -> Result<[f64; 3]> {
        let step = COORD_LEN + 1;
        Ok([
            self.fixed(col, 4, 2)?,
            self.fixed(col + step, 4, 2)?,
            self.fixed(col + 2 * step, 4, 2)?,
        ])
    }
    /// `Q`/`A` layout: x, y, z at [`T_X_COL`] and four quaternion components from [`Q_Q1_COL`].
    fn pose(&self) -> Result<([f64; 3], [f64; 4])> {
        self.expect_len(Q_Q1_COL - 1 + 4 * (QUAT_LEN + 1) - 1)?;
        let mut q = [0.0; 4];
        for (i, qi) in q.iter_mut().enumerate() {
            *qi = self.fixed(Q_Q1_COL + i * (QUAT_LEN + 1), 1, 6)?;
        }
        Ok((self.xyz(T_X_COL)?, q))
    }
    fn hello(&self, side: &str) -> Result<(u8, String)> {
        self.sep(6)?;
        let version = self.uint(7, 2)? as u8;
        self.sep(9)?;
        let who = self.field(10, side.len())?;
        if who != side {
            return Err(err(alloc::format!("HELLO from {who:?}, expected {side}")));
        }
        self.sep(10 + side.len())?;
        let name = self.rest(11 + side.len()).to_string();
        check_name(&name, "peer name")?;
        Ok((version, name))
    }
}

/// Next sequence number after `seq` (wraps modulo [`SEQ_MODULUS`]).
pub fn seq_next(seq: u32) -> u32 {
    (seq + 1) % SEQ_MODULUS
}

/// Number of sequence steps from `from` to `to` (modular).
pub fn seq_distance(from: u32, to: u32) -> u32 {
    (to + SEQ_MODULUS - from % SEQ_MODULUS) % SEQ_MODULUS
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn golden_tracker_lines() {
        let t = TrackerMsg::Target {
            seq: 123,
            pos_mm: [123.45, -456.78, 789.01],
        };
        assert_eq!(
            t.encode().unwrap().as_str(),
            "T 000123 +0123.45 -0456.78 +0789.01\n"
        );
        let h = TrackerMsg::Hello {
            version: 1,
            name: "irtrackd-0.1".into(),
        };
        assert_eq!(h.encode().unwrap().as_str(), "HELLO 01 TRACKER irtrackd-0.1\n");
        let hold = TrackerMsg::Hold {
            reason: HoldReason::MarkerLost,
        };
        assert_eq!(hold.encode().unwrap().as_str(), "HOLD 03 MARKER_LOST\n");
        assert_eq!(
            TrackerMsg::Beat { counter: 7 }.encode().unwrap().as_str(),
            "BEAT 000007\n"
        );
        let q = TrackerMsg::Pose {
            seq: 5,
            pos_mm: [0.0, -0.004, 1.0],
            quat_wxyz: [
                core::f64::consts::FRAC_1_SQRT_2,
                0.0,
                -core::f64::consts::FRAC_1_SQRT_2,
                0.0,
            ],
        };
        assert_eq!(
            q.encode().unwrap().as_str(),
            "Q 000005 +0000.00 +0000.00 +0001.00 +0.707107 +0.000000 -0.707107 +0.000000\n"
        );
        for m in [t, h, hold, q, TrackerMsg::Bye] {
            let line = m.encode().unwrap();
            assert_eq!(
                TrackerMsg::parse(line.as_str()).unwrap(),
                round_trip_expect_tracker(&m)
            );
        }
    }

    // The codec rounds to the wire resolution; compare against the rounded message.
    fn round_trip_expect_tracker(m: &TrackerMsg) -> TrackerMsg {
        let r2 = |v: f64| libm::round(v * 100.0) / 100.0 + 0.0;
        let r6 = |v: f64| libm::round(v * 1e6) / 1e6 + 0.0;
        match m.clone() {
            TrackerMsg::Target { seq, pos_mm } => TrackerMsg::Target {
                seq,
                pos_mm: pos_mm.map(r2),
            },
            TrackerMsg::Pose {
                seq,
                pos_mm,
                quat_wxyz,
            } => TrackerMsg::Pose {
                seq,
                pos_mm: pos_mm.map(r2),
                quat_wxyz: quat_wxyz.map(r6),
            },
            other => other,
        }
    }

    #[test]
    fn golden_robot_lines() {
        let c = RobotMsg::Credit {
            ack_seq: 0,
            window: 1,
            pos_mm: [500.0, 0.0, -12.5],
        };
        assert_eq!(
            c.encode().unwrap().as_str(),
            "C 000000 01 +0500.00 +0000.00 -0012.50\n"
        );
        let x = RobotMsg::Reject {
            seq: 42,
            code: 1,
            reason: "UNREACHABLE".into(),
        };
        assert_eq!(x.encode().unwrap().as_str(), "X 000042 01 UNREACHABLE\n");
        let h = RobotMsg::Hello {
            version: 1,
            name: "IRB1200".into(),
        };
        assert_eq!(h.encode().unwrap().as_str(), "HELLO 01 ROBOT IRB1200\n");
        let a = RobotMsg::Actual {
            counter: 17,
            pos_mm: [612.5, -140.0, 220.04],
            quat_wxyz: [0.0, 0.0, 1.0, 0.0],
        };
        assert_eq!(
            a.encode().unwrap().as_str(),
            "A 000017 +0612.50 -0140.00 +0220.04 +0.000000 +0.000000 +1.000000 +0.000000\n"
        );
        for m in [c, x, h, a, RobotMsg::Beat { counter: 999_999 }, RobotMsg::Bye] {
            assert_eq!(RobotMsg::parse(m.encode().unwrap().as_str()).unwrap(), m);
        }
    }

    #[test]
    fn golden_pose_request_and_answer() {
        let p = TrackerMsg::PoseRequest { counter: 17 };
        assert_eq!(p.encode().unwrap().as_str(), "POSE 000017\n");
        assert_eq!(TrackerMsg::parse("POSE 000017\n").unwrap(), p);
        assert!(TrackerMsg::parse("POSE 17").is_err());
        // The answer has the Q layout: 75 characters, 76 with the newline.
        let line = "A 999999 -9999.99 +9999.99 +0000.00 -0.500000 +0.500000 -0.500000 +0.500000";
        assert_eq!(line.len() + 1, 76);
        assert_eq!(
            RobotMsg::parse(line).unwrap(),
            RobotMsg::Actual {
                counter: 999_999,
                pos_mm: [-9999.99, 9999.99, 0.0],
                quat_wxyz: [-0.5, 0.5, -0.5, 0.5],
            }
        );
        assert!(RobotMsg::parse("A 000001 +0000.00 +0000.00 +0000.00").is_err());
        let bad = RobotMsg::Actual {
            counter: 1,
            pos_mm: [0.0; 3],
            quat_wxyz: [0.5, 0.0, 0.0, 0.0],
        };
        assert!(bad.encode().is_err(), "non-unit quaternion refused");
    }

    #[test]
    fn every_client_message_fits_rapid_limits_at_extremes() {
        let name = "N".repeat(MAX_NAME_CHARS);
        let mut msgs = alloc::vec![
            TrackerMsg::Hello { version: 99, name },
            TrackerMsg::Bye,
            TrackerMsg::Beat {
                counter: SEQ_MODULUS - 1
            },
        ];
        for reason in HoldReason::ALL {
            msgs.push(TrackerMsg::Hold { reason });
        }
        for v in [-MAX_COORD_MM, MAX_COORD_MM, 0.0, -0.001, 9999.994] {
            msgs.push(TrackerMsg::Target {
                seq: SEQ_MODULUS - 1,
                pos_mm: [v; 3],
            });
            msgs.push(TrackerMsg::Pose {
                seq: SEQ_MODULUS - 1,
                pos_mm: [v; 3],
                quat_wxyz: [-0.5; 4],
            });
            msgs.push(TrackerMsg::Pose {
                seq: 0,
                pos_mm: [v; 3],
                quat_wxyz: [1.0, 0.0, 0.0, -0.0],
            });
        }
        for m in &msgs {
            let line = m.encode().unwrap();
            assert!(line.len() <= MAX_LINE_BYTES, "{line:?}");
            assert!(line.as_str().ends_with('\n'));
            assert!(
                line.as_bytes()[..line.len() - 1]
                    .iter()
                    .all(|b| (0x20..0x7f).contains(b))
            );
            // The fixed columns RAPID cuts must hold what they claim.
            let s = line.as_str();
            if s.starts_with("T ") || s.starts_with("Q ") {
                for col in [T_X_COL, T_Y_COL, T_Z_COL] {
                    let f = &s[col - 1..col - 1 + COORD_LEN];
                    assert!(f.starts_with(['+', '-']) && &f[5..6] == ".", "{s:?} col {col}");
                }
                assert!(
                    s[SEQ_COL - 1..SEQ_COL - 1 + SEQ_LEN]
                        .bytes()
                        .all(|b| b.is_ascii_digit())
                );
            }
            if s.starts_with("Q ") {
                for i in 0..4 {
                    let c = Q_Q1_COL + i * (QUAT_LEN + 1);
                    let f = &s[c - 1..c - 1 + QUAT_LEN];
                    assert!(f.starts_with(['+', '-']) && &f[2..3] == ".", "{s:?}");
                }
            }
            assert_eq!(TrackerMsg::parse(s).unwrap(), round_trip_expect_tracker(m));
        }
    }

    #[test]
    fn out_of_range_values_refused_at_encode() {
        for v in [10_000.0, -9999.996, f64::NAN, f64::INFINITY] {
            let e = TrackerMsg::Target {
                seq: 1,
                pos_mm: [0.0, v, 0.0],
            }
            .encode()
            .unwrap_err();
            assert!(matches!(e, Error::Protocol { .. }), "{e}");
        }
        assert!(
            TrackerMsg::Target {
                seq: SEQ_MODULUS,
                pos_mm: [0.0; 3]
            }
            .encode()
            .is_err()
        );
        assert!(
            TrackerMsg::Hello {
                version: 1,
                name: "a b".into()
            }
            .encode()
            .is_err()
        );
        assert!(
            TrackerMsg::Hello {
                version: 1,
                name: "x".repeat(25)
            }
            .encode()
            .is_err()
        );
        let bad_q = TrackerMsg::Pose {
            seq: 1,
            pos_mm: [0.0; 3],
            quat_wxyz: [1.0, 1.0, 0.0, 0.0],
        };
        assert!(bad_q.encode().is_err());
    }

    #[test]
    fn malformed_lines_name_the_problem() {
        let cases: [(&str, &str); 12] = [
            ("", "empty"),
            ("T 000123 +0123.45 -0456.78", "characters"),
            ("T 00012a +0123.45 -0456.78 +0789.01", "digits"),
            ("T 000123 0+123.45 -0456.78 +0789.01", "sign"),
            ("T 000123 +0123,45 -0456.78 +0789.01", "decimal point"),
            ("T 000123 +0123.45 -0456.78  0789.01", "sign"),
            ("T 000123 +0123.45 -0456.78 +0789.01 ", "characters"),
            ("Z 000123", "unknown"),
            ("HOLD 42 WHATEVER", "reason code"),
            ("HOLD 03 DEADMAN", "text"),
            ("HELLO 01 ROBOT x", "expected TRACKER"),
            ("T 000123 +0123.45 -0456.78 +0789.01\r", "non-printable"),
        ];
        for (line, want) in cases {
            match TrackerMsg::parse(line) {
                Err(Error::Protocol { reason, .. }) => assert!(reason.contains(want), "{line:?}: {reason}"),
                other => panic!("{line:?} gave {other:?}"),
            }
        }
        let long = "X 000001 01 ".to_string() + &"A".repeat(80);
        assert!(RobotMsg::parse(&long).is_err());
        assert!(RobotMsg::parse("C 000001 1 +0000.00 +0000.00 +0000.00").is_err());
        assert!(RobotMsg::parse("HELLO 01 TRACKER x").is_err());
    }

    #[test]
    fn seq_arithmetic_wraps() {
        assert_eq!(seq_next(SEQ_MODULUS - 1), 0);
        assert_eq!(seq_distance(SEQ_MODULUS - 1, 1), 2);
        assert_eq!(seq_distance(5, 5), 0);
    }
}
