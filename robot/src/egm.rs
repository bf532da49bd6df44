//! ABB Externally Guided Motion (EGM), position guidance: irtrackd is the EGM *sensor*. The
//! controller sends an `EgmRobot` datagram every cycle (4 ms); irtrackd answers each with an
//! `EgmSensor` whose `planned.cartesian` pose is the next position to go to.
//!
//! The messages are protobuf (proto2) as documented in ABB's application manual *Externally
//! Guided Motion* and its `egm.proto`. They are declared here by hand with `prost` derives (no
//! protoc at build time), with the field numbers of that file (docs/robot-streaming.md lists
//! them). Only the fields irtrackd reads or writes are declared: protobuf decoders skip
//! undeclared fields, so the joint arrays a controller also sends are passed over without
//! being stored (decoding a packet allocates nothing).

use crate::udp::{Command, RobotPacket, StreamConfig, StreamProto};
use crate::{LinkKind, RobotError};
use prost::Message;

/// `EgmHeader.MessageType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum MessageType {
    /// Not set.
    Undefined = 0,
    /// Reserved by ABB.
    Command = 1,
    /// Sent by the robot controller.
    Data = 2,
    /// Sent by the sensor for position guidance.
    Correction = 3,
    /// Sent by the sensor for path correction.
    PathCorrection = 4,
}

/// `EgmHeader`: 1 seqno, 2 tm (controller time stamp, ms), 3 mtype.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmHeader {
    /// Sequence number of the message.
    #[prost(uint32, optional, tag = "1")]
    pub seqno: Option<u32>,
    /// Controller time stamp (ms).
    #[prost(uint32, optional, tag = "2")]
    pub tm: Option<u32>,
    /// A [`MessageType`].
    #[prost(enumeration = "MessageType", optional, tag = "3")]
    pub mtype: Option<i32>,
}

/// `EgmCartesian` (mm): 1 x, 2 y, 3 z, all required.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmCartesian {
    /// X (mm).
    #[prost(double, required, tag = "1")]
    pub x: f64,
    /// Y (mm).
    #[prost(double, required, tag = "2")]
    pub y: f64,
    /// Z (mm).
    #[prost(double, required, tag = "3")]
    pub z: f64,
}

/// `EgmQuaternion`: 1 u0 (scalar part), 2 u1, 3 u2, 4 u3, all required.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmQuaternion {
    #[prost(double, required, tag = "1")]
    /// Scalar part (w).
    pub u0: f64,
    /// x part.
    #[prost(double, required, tag = "2")]
    pub u1: f64,
    /// y part.
    #[prost(double, required, tag = "3")]
    pub u2: f64,
    /// z part.
    #[prost(double, required, tag = "4")]
    pub u3: f64,
}

/// `EgmEuler` (degrees): 1 x, 2 y, 3 z. When a pose carries both, the controller uses Euler.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmEuler {
    /// Rotation about x (degrees).
    #[prost(double, required, tag = "1")]
    pub x: f64,
    /// Rotation about y (degrees).
    #[prost(double, required, tag = "2")]
    pub y: f64,
    /// Rotation about z (degrees).
    #[prost(double, required, tag = "3")]
    pub z: f64,
}

/// `EgmPose`: 1 pos, 2 orient (quaternion), 3 euler.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmPose {
    /// Position.
    #[prost(message, optional, tag = "1")]
    pub pos: Option<EgmCartesian>,
    /// Orientation as a quaternion.
    #[prost(message, optional, tag = "2")]
    pub orient: Option<EgmQuaternion>,
    /// Orientation as Euler angles.
    #[prost(message, optional, tag = "3")]
    pub euler: Option<EgmEuler>,
}

/// `EgmClock`: 1 sec, 2 usec.
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmClock {
    #[prost(uint64, required, tag = "1")]
    /// Seconds.
    pub sec: u64,
    /// Microseconds within the second.
    #[prost(uint64, required, tag = "2")]
    pub usec: u64,
}

/// `EgmPlanned` / `EgmFeedBack` share the layout: 1 joints, 2 cartesian, 3 externalJoints,
/// 4 time. The joint arrays (1, 3) are not declared (position guidance in Cartesian space).
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmPlanned {
    /// The Cartesian pose.
    #[prost(message, optional, tag = "2")]
    pub cartesian: Option<EgmPose>,
    /// When the pose holds.
    #[prost(message, optional, tag = "4")]
    pub time: Option<EgmClock>,
}

/// Same wire layout as [`EgmPlanned`].
pub type EgmFeedBack = EgmPlanned;

/// `EgmMotorState.MotorStateType`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum MotorState {
    /// Not set.
    Undefined = 0,
    /// Motors on.
    On = 1,
    /// Motors off.
    Off = 2,
}

/// `EgmMotorState`: 1 state (required).
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmMotorState {
    /// A [`MotorState`].
    #[prost(enumeration = "MotorState", required, tag = "1")]
    pub state: i32,
}

/// `EgmMCIState.MCIStateType` (the motion control interface of the EGM instruction).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, prost::Enumeration)]
#[repr(i32)]
pub enum MciState {
    /// Not set.
    Undefined = 0,
    /// The EGM instruction failed.
    Error = 1,
    /// Not guiding.
    Stopped = 2,
    /// Guiding: the sensor's answers move the robot.
    Running = 3,
}

/// `EgmMCIState`: 1 state (required).
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmMciState {
    /// A [`MciState`].
    #[prost(enumeration = "MciState", required, tag = "1")]
    pub state: i32,
}

/// `EgmRobot`, controller → sensor: 1 header, 2 feedBack, 3 planned, 4 motorState, 5 mciState,
/// 6 mciConvergenceMet, 10 utilizationRate (7 testSignals, 8 rapidExecState and 9 measuredForce
/// are not declared).
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmRobot {
    /// Sequence number, time stamp, message type.
    #[prost(message, optional, tag = "1")]
    pub header: Option<EgmHeader>,
    #[prost(message, optional, tag = "2")]
    /// Where the robot is.
    pub feed_back: Option<EgmFeedBack>,
    /// Where the controller plans to be.
    #[prost(message, optional, tag = "3")]
    pub planned: Option<EgmPlanned>,
    /// Motors on or off.
    #[prost(message, optional, tag = "4")]
    pub motor_state: Option<EgmMotorState>,
    /// State of the EGM instruction.
    #[prost(message, optional, tag = "5")]
    pub mci_state: Option<EgmMciState>,
    /// The robot reached the guided position within the convergence criteria.
    #[prost(bool, optional, tag = "6")]
    pub mci_convergence_met: Option<bool>,
    /// Utilisation rate as the controller reports it.
    #[prost(double, optional, tag = "10")]
    pub utilization_rate: Option<f64>,
}

/// `EgmSensor`, sensor → controller: 1 header, 2 planned (3 speedRef is not declared).
#[derive(Clone, Copy, PartialEq, Message)]
pub struct EgmSensor {
    /// Sequence number, time stamp, message type.
    #[prost(message, optional, tag = "1")]
    pub header: Option<EgmHeader>,
    /// The pose to go to next.
    #[prost(message, optional, tag = "2")]
    pub planned: Option<EgmPlanned>,
}

/// Largest EGM datagram accepted (a controller's EgmRobot is a few hundred bytes).
pub const MAX_PACKET_BYTES: usize = 1400;

fn bad(len: usize, reason: impl Into<String>) -> RobotError {
    RobotError::Packet {
        protocol: "EGM",
        len,
        reason: reason.into(),
    }
}

/// Decodes an `EgmRobot` datagram and takes what the link needs: seqno and the feedback pose.
pub fn decode_robot(bytes: &[u8]) -> Result<(EgmRobot, RobotPacket), RobotError> {
    let len = bytes.len();
    if len > MAX_PACKET_BYTES {
        return Err(bad(len, format!("longer than {MAX_PACKET_BYTES} bytes")));
    }
    let msg = EgmRobot::decode(bytes).map_err(|e| bad(len, format!("not an EgmRobot: {e}")))?;
    let header = msg.header.ok_or_else(|| bad(len, "no header"))?;
    let seqno = header.seqno.ok_or_else(|| bad(len, "header without seqno"))?;
    if let Some(t) = header.mtype
        && t != MessageType::Data as i32
    {
        return Err(bad(len, format!("header.mtype {t} is not MSGTYPE_DATA (2)")));
    }
    let pose = msg
        .feed_back
        .and_then(|f| f.cartesian)
        .ok_or_else(|| bad(len, "no feedBack.cartesian pose"))?;
    let p = pose
        .pos
        .ok_or_else(|| bad(len, "feedBack.cartesian without pos"))?;
    let pos_mm = [p.x, p.y, p.z];
    if !pos_mm.iter().all(|v| v.is_finite()) {
        return Err(bad(len, "feedBack position is not finite"));
    }
    let quat_wxyz = pose.orient.map(|q| [q.u0, q.u1, q.u2, q.u3]).filter(|q| {
        q.iter().all(|v| v.is_finite()) && (q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-2
    });
    Ok((
        msg,
        RobotPacket {
            id: u64::from(seqno),
            pos_mm,
            quat_wxyz,
        },
    ))
}

/// The `EgmSensor` answering the packet with sequence number `seqno`, commanding `cmd`.
pub fn sensor_message(seqno: u32, tm_ms: u32, cmd: &Command) -> EgmSensor {
    let [w, x, y, z] = cmd.quat_wxyz;
    EgmSensor {
        header: Some(EgmHeader {
            seqno: Some(seqno),
            tm: Some(tm_ms),
            mtype: Some(MessageType::Correction as i32),
        }),
        planned: Some(EgmPlanned {
            cartesian: Some(EgmPose {
                pos: Some(EgmCartesian {
                    x: cmd.pos_mm[0],
                    y: cmd.pos_mm[1],
                    z: cmd.pos_mm[2],
                }),
                orient: Some(EgmQuaternion {
                    u0: w,
                    u1: x,
                    u2: y,
                    u3: z,
                }),
                euler: None,
            }),
            time: None,
        }),
    }
}

/// The EGM side of a streaming link.
pub struct Egm {
    t0: std::time::Instant,
}

impl StreamProto for Egm {
    const KIND: LinkKind = LinkKind::Egm;

    fn new(_cfg: &StreamConfig) -> Self {
        Self {
            t0: std::time::Instant::now(),
        }
    }

    fn decode(&mut self, bytes: &[u8]) -> Result<RobotPacket, RobotError> {
        decode_robot(bytes).map(|(_, p)| p)
    }

    fn ahead(id: u64, last: u64) -> Option<u64> {
        // seqno is a u32 that wraps: newer means less than half the range ahead.
        let d = (id as u32).wrapping_sub(last as u32);
        (d != 0 && d < 1 << 31).then_some(u64::from(d))
    }

    /// 100 packets (0.4 s at EGM's 4 ms) lost in a row, besides the time-based allowance.
    const SEQ_SLACK_IDS: u64 = 100;
    /// One packet per ms: four times EGM's fastest cycle (4 ms).
    const MAX_IDS_PER_S: u64 = 1000;

    fn on_session(&mut self, _first: &RobotPacket) {}

    fn encode(&mut self, pkt: &RobotPacket, cmd: &Command, out: &mut Vec<u8>) -> Result<(), RobotError> {
        let tm_ms = self.t0.elapsed().as_millis() as u32;
        out.clear();
        // The reply carries the seqno it answers: the controller uses the newest message either
        // way, and the echo lets a simulated controller (and a capture) pair replies with cycles.
        sensor_message(pkt.id as u32, tm_ms, cmd)
            .encode(out)
            .map_err(|e| bad(0, format!("encode EgmSensor: {e}")))
    }
}
