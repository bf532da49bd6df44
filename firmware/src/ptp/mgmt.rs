//! IEEE 1588 management messages to ptp4l over its Unix datagram socket: the GET requests
//! irtrackd sends and the replies it parses (docs/cluster.md, "PTP management messages").
//!
//! Only what `/status` needs: CURRENT_DATA_SET (offset from the master, mean path delay,
//! steps removed), PORT_DATA_SET (the port's state) and linuxptp's TIME_STATUS_NP (whether a
//! grandmaster is present, and which). Every length in a reply is checked against the
//! datagram before a field is read; anything else is a named [`PtpError`], never a panic.

use std::fmt;

/// PTP header (IEEE 1588-2008 §13.3) in bytes.
pub const HEADER_LEN: usize = 34;
/// Header plus the management message's own fields (§15.4.1): target port identity (10),
/// starting boundary hops, boundary hops, action, reserved.
pub const MANAGEMENT_LEN: usize = 48;
/// A GET request: the management message plus an empty management TLV (type, length, id).
pub const GET_LEN: usize = MANAGEMENT_LEN + 6;
/// Largest datagram read (ptp4l's message buffer is 1500 bytes).
pub const MAX_REPLY_LEN: usize = 1500;

const MESSAGE_TYPE_MANAGEMENT: u8 = 0x0D;
const PTP_MAJOR_VERSION: u8 = 2;
const CONTROL_MANAGEMENT: u8 = 0x04;
const ACTION_GET: u8 = 0;
const ACTION_RESPONSE: u8 = 2;
const TLV_MANAGEMENT: u16 = 0x0001;
const TLV_MANAGEMENT_ERROR_STATUS: u16 = 0x0002;

/// The management ids irtrackd asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ManagementId {
    /// currentDS: stepsRemoved, offsetFromMaster, meanPathDelay (18 bytes).
    CurrentDataSet,
    /// portDS: portIdentity, portState, … (26 bytes).
    PortDataSet,
    /// linuxptp's TIME_STATUS_NP: master offset, grandmaster present and identity (50 bytes).
    TimeStatusNp,
}

impl ManagementId {
    /// The id on the wire.
    pub fn code(self) -> u16 {
        match self {
            ManagementId::CurrentDataSet => 0x2001,
            ManagementId::PortDataSet => 0x2004,
            ManagementId::TimeStatusNp => 0xC000,
        }
    }

    /// Length of the data set in a RESPONSE (the TLV's length field minus the id's 2 bytes).
    pub fn data_len(self) -> usize {
        match self {
            ManagementId::CurrentDataSet => 18,
            ManagementId::PortDataSet => 26,
            ManagementId::TimeStatusNp => 50,
        }
    }

    /// pmc's name for it.
    pub fn name(self) -> &'static str {
        match self {
            ManagementId::CurrentDataSet => "CURRENT_DATA_SET",
            ManagementId::PortDataSet => "PORT_DATA_SET",
            ManagementId::TimeStatusNp => "TIME_STATUS_NP",
        }
    }
}

/// A port identity: clock identity and port number.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PortIdentity {
    /// EUI-64 clock identity.
    pub clock: [u8; 8],
    /// Port number.
    pub port: u16,
}

impl PortIdentity {
    /// irtrackd's identity as a management client: like linuxptp's own `pmc` on a Unix socket,
    /// a zero clock identity and the process id as the port number.
    pub fn local_client(port: u16) -> Self {
        PortIdentity { clock: [0; 8], port }
    }
}

/// Errors of the management client. Each names what was wrong with which reply.
#[derive(Debug, thiserror::Error)]
pub enum PtpError {
    /// A reply shorter than its fixed part.
    #[error("{what}: {len} bytes, need at least {need}")]
    Truncated {
        /// The message or field.
        what: &'static str,
        /// Bytes received.
        len: usize,
        /// Bytes the fixed part takes.
        need: usize,
    },
    /// A length field that disagrees with the bytes received.
    #[error("{what}: length field says {declared} bytes, {actual} present")]
    Length {
        /// The length field (`messageLength`, `management TLV`, …).
        what: &'static str,
        /// What the field says.
        declared: usize,
        /// What the datagram holds (or the data set's size).
        actual: usize,
    },
    /// Not a PTP version 2 management message.
    #[error("not a PTPv2 management message (messageType {message_type:#x}, versionPTP {version})")]
    NotManagement {
        /// The header's message type nibble.
        message_type: u8,
        /// The header's major version nibble.
        version: u8,
    },
    /// A management message whose action is not RESPONSE.
    #[error("management action {action} where a RESPONSE (2) was expected")]
    Action {
        /// The action field.
        action: u8,
    },
    /// A TLV other than MANAGEMENT or MANAGEMENT_ERROR_STATUS.
    #[error("unexpected TLV type {tlv_type:#06x} in a management reply")]
    Tlv {
        /// The TLV's type.
        tlv_type: u16,
    },
    /// The reply answers another management id.
    #[error("reply for management id {got:#06x}, asked for {asked} ({asked_code:#06x})")]
    WrongId {
        /// The id asked for, by name.
        asked: &'static str,
        /// Its code.
        asked_code: u16,
        /// The id in the reply.
        got: u16,
    },
    /// ptp4l answered with MANAGEMENT_ERROR_STATUS.
    #[error("ptp4l refused GET {asked}: {error} ({code:#06x})")]
    Refused {
        /// The id asked for.
        asked: &'static str,
        /// The error's name (IEEE 1588 Table 72).
        error: &'static str,
        /// The managementErrorId.
        code: u16,
    },
    /// A field value outside its range.
    #[error("{what}: value {value} is out of range")]
    Value {
        /// The field.
        what: &'static str,
        /// The value read.
        value: u64,
    },
    /// A reply to an older request (its sequenceId is not the one sent).
    #[error("reply with sequenceId {got}, expected {expected}")]
    Stale {
        /// The sequence id of the request.
        expected: u16,
        /// The one in the reply.
        got: u16,
    },
    /// The socket could not be opened, sent on or read.
    #[error("{what} {path}: {source}")]
    Io {
        /// The step (`binding the client socket`, `sending to ptp4l at`, …).
        what: &'static str,
        /// The path concerned.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// No reply in time.
    #[error("ptp4l at {path} did not answer GET {asked} within {timeout_ms} ms")]
    Timeout {
        /// The server socket.
        path: String,
        /// The id asked for.
        asked: &'static str,
        /// The wait, ms.
        timeout_ms: u64,
    },
}

/// Writes a GET request for `id` into `out` (exactly [`GET_LEN`] bytes): boundary hops 0
/// (answered by the local ptp4l only, never forwarded onto the network), all ports targeted,
/// an empty TLV body (linuxptp accepts zero-length GETs; `pmc -z` sends them too).
pub fn encode_get(
    out: &mut [u8; GET_LEN],
    id: ManagementId,
    sequence: u16,
    domain: u8,
    source: PortIdentity,
) {
    *out = [0; GET_LEN];
    out[0] = MESSAGE_TYPE_MANAGEMENT; // transportSpecific 0
    out[1] = PTP_MAJOR_VERSION; // minor version 0: linuxptp 3.1 compares the whole byte
    out[2..4].copy_from_slice(&(GET_LEN as u16).to_be_bytes());
    out[4] = domain;
    // 5: reserved, 6..8 flags, 8..16 correction, 16..20 reserved: zero.
    out[20..28].copy_from_slice(&source.clock);
    out[28..30].copy_from_slice(&source.port.to_be_bytes());
    out[30..32].copy_from_slice(&sequence.to_be_bytes());
    out[32] = CONTROL_MANAGEMENT;
    out[33] = 0x7F; // logMessageInterval: none for management
    // targetPortIdentity: all clocks, all ports.
    out[34..44].fill(0xFF);
    // 44: startingBoundaryHops 0, 45: boundaryHops 0.
    out[46] = ACTION_GET;
    // 47: reserved.
    out[48..50].copy_from_slice(&TLV_MANAGEMENT.to_be_bytes());
    out[50..52].copy_from_slice(&2u16.to_be_bytes());
    out[52..54].copy_from_slice(&id.code().to_be_bytes());
}

/// The state of a PTP port (IEEE 1588 Table 8; 10 is linuxptp's GRAND_MASTER).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PortState {
    /// 1
    Initializing,
    /// 2
    Faulty,
    /// 3
    Disabled,
    /// 4
    Listening,
    /// 5
    PreMaster,
    /// 6
    Master,
    /// 7
    Passive,
    /// 8: a master chosen, the clock not yet steered to it.
    Uncalibrated,
    /// 9
    Slave,
    /// 10
    GrandMaster,
}

impl PortState {
    fn from_u8(v: u8) -> Option<Self> {
        Some(match v {
            1 => PortState::Initializing,
            2 => PortState::Faulty,
            3 => PortState::Disabled,
            4 => PortState::Listening,
            5 => PortState::PreMaster,
            6 => PortState::Master,
            7 => PortState::Passive,
            8 => PortState::Uncalibrated,
            9 => PortState::Slave,
            10 => PortState::GrandMaster,
            _ => return None,
        })
    }

    /// The name pmc and ptp4l's log use.
    pub fn name(self) -> &'static str {
        match self {
            PortState::Initializing => "INITIALIZING",
            PortState::Faulty => "FAULTY",
            PortState::Disabled => "DISABLED",
            PortState::Listening => "LISTENING",
            PortState::PreMaster => "PRE_MASTER",
            PortState::Master => "MASTER",
            PortState::Passive => "PASSIVE",
            PortState::Uncalibrated => "UNCALIBRATED",
            PortState::Slave => "SLAVE",
            PortState::GrandMaster => "GRAND_MASTER",
        }
    }
}

impl fmt::Display for PortState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// currentDS.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurrentDataSet {
    /// Boundary clocks between this clock and the grandmaster (0 on the grandmaster).
    pub steps_removed: u16,
    /// Offset from the master, ns (TimeInterval: ns × 2¹⁶ on the wire).
    pub offset_from_master_ns: f64,
    /// Mean path delay to the master, ns.
    pub mean_path_delay_ns: f64,
}

/// The parts of portDS that `/status` shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PortDataSet {
    /// The port answering.
    pub port: PortIdentity,
    /// Its state.
    pub state: PortState,
}

/// The parts of TIME_STATUS_NP that `/status` shows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TimeStatus {
    /// Offset from the master, integer ns.
    pub master_offset_ns: i64,
    /// A grandmaster is known (ptp4l's gmPresent).
    pub gm_present: bool,
    /// The grandmaster's clock identity.
    pub gm_identity: [u8; 8],
}

/// A parsed RESPONSE.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Reply {
    /// To GET CURRENT_DATA_SET.
    Current(CurrentDataSet),
    /// To GET PORT_DATA_SET.
    Port(PortDataSet),
    /// To GET TIME_STATUS_NP.
    TimeStatus(TimeStatus),
}

fn be16(b: &[u8], at: usize) -> u16 {
    u16::from_be_bytes([b[at], b[at + 1]])
}

fn be64(b: &[u8], at: usize) -> i64 {
    let mut a = [0u8; 8];
    a.copy_from_slice(&b[at..at + 8]);
    i64::from_be_bytes(a)
}

fn port_identity(b: &[u8], at: usize) -> PortIdentity {
    let mut clock = [0u8; 8];
    clock.copy_from_slice(&b[at..at + 8]);
    PortIdentity {
        clock,
        port: be16(b, at + 8),
    }
}

/// managementErrorId names (IEEE 1588-2008 Table 72).
fn error_name(code: u16) -> &'static str {
    match code {
        0x0001 => "RESPONSE_TOO_BIG",
        0x0002 => "NO_SUCH_ID",
        0x0003 => "WRONG_LENGTH",
        0x0004 => "WRONG_VALUE",
        0x0005 => "NOT_SETABLE",
        0x0006 => "NOT_SUPPORTED",
        0xFFFE => "GENERAL_ERROR",
        _ => "unknown error",
    }
}

/// Parses ptp4l's answer to the GET `asked` with sequence id `sequence`. The datagram must be
/// exactly one management message carrying exactly one TLV of the data set's size.
pub fn parse_reply(msg: &[u8], asked: ManagementId, sequence: u16) -> Result<Reply, PtpError> {
    if msg.len() < MANAGEMENT_LEN + 4 {
        return Err(PtpError::Truncated {
            what: "management reply",
            len: msg.len(),
            need: MANAGEMENT_LEN + 4,
        });
    }
    let (message_type, version) = (msg[0] & 0x0F, msg[1] & 0x0F);
    if message_type != MESSAGE_TYPE_MANAGEMENT || version != PTP_MAJOR_VERSION {
        return Err(PtpError::NotManagement {
            message_type,
            version,
        });
    }
    let declared = usize::from(be16(msg, 2));
    if declared != msg.len() {
        return Err(PtpError::Length {
            what: "messageLength",
            declared,
            actual: msg.len(),
        });
    }
    let got_seq = be16(msg, 30);
    if got_seq != sequence {
        return Err(PtpError::Stale {
            expected: sequence,
            got: got_seq,
        });
    }
    let action = msg[46] & 0x0F;
    if action != ACTION_RESPONSE {
        return Err(PtpError::Action { action });
    }
    let tlv_type = be16(msg, MANAGEMENT_LEN);
    let tlv_len = usize::from(be16(msg, MANAGEMENT_LEN + 2));
    let body = &msg[MANAGEMENT_LEN + 4..];
    if tlv_len != body.len() {
        return Err(PtpError::Length {
            what: "management TLV",
            declared: tlv_len,
            actual: body.len(),
        });
    }
    match tlv_type {
        TLV_MANAGEMENT => {}
        TLV_MANAGEMENT_ERROR_STATUS => {
            // managementErrorId, managementId, 4 reserved bytes, optional displayData.
            if body.len() < 8 {
                return Err(PtpError::Truncated {
                    what: "MANAGEMENT_ERROR_STATUS TLV",
                    len: body.len(),
                    need: 8,
                });
            }
            let code = be16(body, 0);
            return Err(PtpError::Refused {
                asked: asked.name(),
                error: error_name(code),
                code,
            });
        }
        other => return Err(PtpError::Tlv { tlv_type: other }),
    }
    if body.len() < 2 {
        return Err(PtpError::Truncated {
            what: "management TLV",
            len: body.len(),
            need: 2,
        });
    }
    let got = be16(body, 0);
    if got != asked.code() {
        return Err(PtpError::WrongId {
            asked: asked.name(),
            asked_code: asked.code(),
            got,
        });
    }
    let data = &body[2..];
    if data.len() != asked.data_len() {
        return Err(PtpError::Length {
            what: asked.name(),
            declared: data.len(),
            actual: asked.data_len(),
        });
    }
    // TimeInterval: signed ns scaled by 2^16.
    let scaled = |at: usize| be64(data, at) as f64 / 65536.0;
    Ok(match asked {
        ManagementId::CurrentDataSet => Reply::Current(CurrentDataSet {
            steps_removed: be16(data, 0),
            offset_from_master_ns: scaled(2),
            mean_path_delay_ns: scaled(10),
        }),
        ManagementId::PortDataSet => {
            let state = PortState::from_u8(data[10]).ok_or(PtpError::Value {
                what: "portDS.portState",
                value: u64::from(data[10]),
            })?;
            Reply::Port(PortDataSet {
                port: port_identity(data, 0),
                state,
            })
        }
        ManagementId::TimeStatusNp => {
            let mut gm_identity = [0u8; 8];
            gm_identity.copy_from_slice(&data[42..50]);
            let gm_present = i32::from_be_bytes([data[38], data[39], data[40], data[41]]);
            Reply::TimeStatus(TimeStatus {
                master_offset_ns: be64(data, 0),
                gm_present: gm_present != 0,
                gm_identity,
            })
        }
    })
}

/// A clock identity the way linuxptp prints it (`001122.fffe.334455`).
pub fn clock_identity_text(id: &[u8; 8]) -> String {
    format!(
        "{:02x}{:02x}{:02x}.{:02x}{:02x}.{:02x}{:02x}{:02x}",
        id[0], id[1], id[2], id[3], id[4], id[5], id[6], id[7]
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const CLIENT: PortIdentity = PortIdentity {
        clock: [0; 8],
        port: 0x1234,
    };

    /// GET CURRENT_DATA_SET, sequence 7, domain 0, from port 0x1234: byte by byte.
    #[test]
    fn get_request_golden_bytes() {
        let mut out = [0u8; GET_LEN];
        encode_get(&mut out, ManagementId::CurrentDataSet, 7, 0, CLIENT);
        #[rustfmt::skip]
        let golden: [u8; GET_LEN] = [
            0x0d, 0x02, 0x00, 0x36, 0x00, 0x00, 0x00, 0x00, // type, version, length 54, domain, flags
            0, 0, 0, 0, 0, 0, 0, 0,                         // correction
            0, 0, 0, 0,                                     // reserved
            0, 0, 0, 0, 0, 0, 0, 0, 0x12, 0x34,             // sourcePortIdentity
            0x00, 0x07, 0x04, 0x7f,                         // sequenceId, control, logMessageInterval
            0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, // targetPortIdentity
            0x00, 0x00, 0x00, 0x00,                         // hops 0/0, action GET, reserved
            0x00, 0x01, 0x00, 0x02, 0x20, 0x01,             // TLV MANAGEMENT, length 2, id
        ];
        assert_eq!(out, golden);
        encode_get(&mut out, ManagementId::PortDataSet, 0xBEEF, 5, CLIENT);
        assert_eq!(out[4], 5);
        assert_eq!(&out[30..32], &[0xBE, 0xEF]);
        assert_eq!(&out[52..54], &[0x20, 0x04]);
        encode_get(&mut out, ManagementId::TimeStatusNp, 1, 0, CLIENT);
        assert_eq!(&out[52..54], &[0xC0, 0x00]);
    }

    /// A reply as ptp4l builds it: header (from its UDS port), target = the client, action
    /// RESPONSE, one TLV.
    fn reply(sequence: u16, tlv_type: u16, id: u16, data: &[u8]) -> Vec<u8> {
        let tlv_len = 2 + data.len();
        let len = MANAGEMENT_LEN + 4 + tlv_len;
        let mut m = vec![0u8; MANAGEMENT_LEN];
        m[0] = 0x0D;
        m[1] = 0x12; // linuxptp 4.x sends minor version 1
        m[2..4].copy_from_slice(&(len as u16).to_be_bytes());
        m[20..28].copy_from_slice(&[0x02, 0x11, 0x22, 0xff, 0xfe, 0x33, 0x44, 0x55]);
        m[30..32].copy_from_slice(&sequence.to_be_bytes());
        m[32] = 0x04;
        m[33] = 0x7f;
        m[34..44].copy_from_slice(&[0, 0, 0, 0, 0, 0, 0, 0, 0x12, 0x34]);
        m[46] = 2;
        m.extend_from_slice(&tlv_type.to_be_bytes());
        m.extend_from_slice(&(tlv_len as u16).to_be_bytes());
        m.extend_from_slice(&id.to_be_bytes());
        m.extend_from_slice(data);
        m
    }

    /// Golden reply to GET CURRENT_DATA_SET: stepsRemoved 1, offset −1234.5 ns, delay 4096.25 ns.
    #[rustfmt::skip]
    const CURRENT_REPLY: [u8; 72] = [
        0x0d, 0x12, 0x00, 0x48, 0x00, 0x00, 0x00, 0x00,
        0, 0, 0, 0, 0, 0, 0, 0,
        0, 0, 0, 0,
        0x02, 0x11, 0x22, 0xff, 0xfe, 0x33, 0x44, 0x55, 0x00, 0x00,
        0x00, 0x07, 0x04, 0x7f,
        0, 0, 0, 0, 0, 0, 0, 0, 0x12, 0x34,
        0x00, 0x00, 0x02, 0x00,
        0x00, 0x01, 0x00, 0x14, 0x20, 0x01,
        0x00, 0x01,                                     // stepsRemoved 1
        0xff, 0xff, 0xff, 0xff, 0xfb, 0x2d, 0x80, 0x00, // −1234.5 × 2^16
        0x00, 0x00, 0x00, 0x00, 0x10, 0x00, 0x40, 0x00, // 4096.25 × 2^16
    ];

    #[test]
    fn current_data_set_reply_golden_bytes() {
        let r = parse_reply(&CURRENT_REPLY, ManagementId::CurrentDataSet, 7).unwrap();
        assert_eq!(
            r,
            Reply::Current(CurrentDataSet {
                steps_removed: 1,
                offset_from_master_ns: -1234.5,
                mean_path_delay_ns: 4096.25,
            })
        );
        // The helper builds the same bytes.
        let mut data = vec![0x00, 0x01];
        data.extend_from_slice(&((-1234.5f64 * 65536.0) as i64).to_be_bytes());
        data.extend_from_slice(&((4096.25f64 * 65536.0) as i64).to_be_bytes());
        assert_eq!(reply(7, 1, 0x2001, &data), CURRENT_REPLY.to_vec());
    }

    #[test]
    fn port_and_time_status_replies_parse() {
        let mut pds = [0u8; 26];
        pds[..10].copy_from_slice(&[0x02, 0x11, 0x22, 0xff, 0xfe, 0x33, 0x44, 0x55, 0x00, 0x01]);
        pds[10] = 9;
        let r = parse_reply(&reply(3, 1, 0x2004, &pds), ManagementId::PortDataSet, 3).unwrap();
        let Reply::Port(p) = r else { panic!("{r:?}") };
        assert_eq!(p.state, PortState::Slave);
        assert_eq!(p.port.port, 1);
        assert_eq!(clock_identity_text(&p.port.clock), "021122.fffe.334455");
        pds[10] = 6;
        let r = parse_reply(&reply(3, 1, 0x2004, &pds), ManagementId::PortDataSet, 3).unwrap();
        assert!(matches!(
            r,
            Reply::Port(PortDataSet {
                state: PortState::Master,
                ..
            })
        ));

        let mut ts = [0u8; 50];
        ts[..8].copy_from_slice(&(-42i64).to_be_bytes());
        ts[38..42].copy_from_slice(&1i32.to_be_bytes());
        ts[42..50].copy_from_slice(&[1, 2, 3, 4, 5, 6, 7, 8]);
        let r = parse_reply(&reply(9, 1, 0xC000, &ts), ManagementId::TimeStatusNp, 9).unwrap();
        assert_eq!(
            r,
            Reply::TimeStatus(TimeStatus {
                master_offset_ns: -42,
                gm_present: true,
                gm_identity: [1, 2, 3, 4, 5, 6, 7, 8],
            })
        );
    }

    #[test]
    fn malformed_replies_are_named_errors() {
        let ok = CURRENT_REPLY.to_vec();
        let cur = ManagementId::CurrentDataSet;
        // Every truncation: an error, never a panic.
        for n in 0..ok.len() {
            let e = parse_reply(&ok[..n], cur, 7).unwrap_err();
            assert!(
                matches!(e, PtpError::Truncated { .. } | PtpError::Length { .. }),
                "{n}: {e}"
            );
        }
        // Trailing byte (messageLength then disagrees).
        let mut long = ok.clone();
        long.push(0);
        assert!(matches!(
            parse_reply(&long, cur, 7),
            Err(PtpError::Length {
                what: "messageLength",
                ..
            })
        ));
        // messageLength and TLV length patched to cover the extra byte: the data set's size is wrong.
        long[3] = 0x49;
        long[51] = 0x15;
        assert!(matches!(
            parse_reply(&long, cur, 7),
            Err(PtpError::Length {
                what: "CURRENT_DATA_SET",
                ..
            })
        ));
        // TLV length lying.
        let mut bad = ok.clone();
        bad[51] = 0x30;
        assert!(matches!(
            parse_reply(&bad, cur, 7),
            Err(PtpError::Length {
                what: "management TLV",
                ..
            })
        ));
        let mut bad = ok.clone();
        bad[0] = 0x0B; // an announce
        assert!(matches!(
            parse_reply(&bad, cur, 7),
            Err(PtpError::NotManagement { .. })
        ));
        let mut bad = ok.clone();
        bad[46] = 0; // a GET echoed back
        assert!(matches!(
            parse_reply(&bad, cur, 7),
            Err(PtpError::Action { action: 0 })
        ));
        assert!(matches!(
            parse_reply(&ok, cur, 8),
            Err(PtpError::Stale { expected: 8, got: 7 })
        ));
        let e = parse_reply(&ok, ManagementId::PortDataSet, 7).unwrap_err();
        assert!(e.to_string().contains("PORT_DATA_SET"), "{e}");
        let mut bad = ok.clone();
        bad[49] = 0x03;
        assert!(matches!(
            parse_reply(&bad, cur, 7),
            Err(PtpError::Tlv { tlv_type: 3 })
        ));
        // An error status: NOT_SUPPORTED (what ptp4l answers for an id it does not serve).
        let err_body = [0x00, 0x06, 0xC0, 0x00, 0, 0, 0, 0];
        let mut m = reply(2, 2, 0, &[]);
        m.truncate(MANAGEMENT_LEN);
        m.extend_from_slice(&[0x00, 0x02, 0x00, 0x08]);
        m.extend_from_slice(&err_body);
        let len = m.len() as u16;
        m[2..4].copy_from_slice(&len.to_be_bytes());
        let e = parse_reply(&m, ManagementId::TimeStatusNp, 2).unwrap_err();
        assert!(
            matches!(
                e,
                PtpError::Refused {
                    error: "NOT_SUPPORTED",
                    ..
                }
            ),
            "{e}"
        );
        assert!(e.to_string().contains("TIME_STATUS_NP"), "{e}");
        // A port state out of range.
        let mut pds = [0u8; 26];
        pds[10] = 42;
        let e = parse_reply(&reply(1, 1, 0x2004, &pds), ManagementId::PortDataSet, 1).unwrap_err();
        assert!(matches!(e, PtpError::Value { value: 42, .. }), "{e}");
    }
}
