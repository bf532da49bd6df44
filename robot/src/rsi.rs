//! KUKA RobotSensorInterface (RSI) over Ethernet: the controller sends a `<Rob>` XML datagram
//! every interpolation cycle (4 ms on KR C4, 12 ms on KR C2) carrying its timestamp `IPOC` and
//! the actual Cartesian TCP `RIst`; irtrackd answers with a `<Sen>` datagram that echoes `IPOC`
//! and carries the Cartesian correction `RKorr`:
//!
//! - absolute mode: `RKorr` is the offset of the wanted TCP from where the session started;
//! - relative mode: `RKorr` is this cycle's increment (the controller's POSCORR object sums).
//!
//! Parsing is strict where it matters (root element, one `RIst` with finite X/Y/Z, one integer
//! `IPOC`, well-formed XML) and ignores the other elements a controller is configured to send.

use std::io::Write;

use quick_xml::Reader;
use quick_xml::events::{BytesStart, Event};

use crate::udp::{Command, RobotPacket, RsiMode, StreamConfig, StreamProto};
use crate::{LinkKind, RobotError};

/// Largest RSI datagram accepted (the controller's default receive buffer is 1024 bytes; a
/// verbose `<Rob>` with many tags stays well below this).
pub const MAX_PACKET_BYTES: usize = 4096;

fn bad(len: usize, reason: impl Into<String>) -> RobotError {
    RobotError::Packet {
        protocol: "RSI",
        len,
        reason: reason.into(),
    }
}

/// What a `<Rob>` datagram says.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RobFrame {
    /// The cycle's IPOC time stamp, echoed in the answer.
    pub ipoc: u64,
    /// `RIst` X, Y, Z (mm).
    pub pos_mm: [f64; 3],
    /// `RIst` A, B, C (degrees), when present.
    pub abc_deg: Option<[f64; 3]>,
    /// `RSol` X, Y, Z (mm): the setpoint including the corrections applied so far, when sent.
    pub setpoint_mm: Option<[f64; 3]>,
}

/// X, Y, Z and A, B, C attributes of a pose element, each present or not.
type PoseAttrs = ([Option<f64>; 3], [Option<f64>; 3]);

fn xyzabc(len: usize, e: &BytesStart<'_>) -> Result<PoseAttrs, RobotError> {
    let mut xyz = [None; 3];
    let mut abc = [None; 3];
    for a in e.attributes() {
        let a = a.map_err(|e| bad(len, format!("RIst attribute: {e}")))?;
        let slot = match a.key.as_ref() {
            "X" => &mut xyz[0],
            "Y" => &mut xyz[1],
            "Z" => &mut xyz[2],
            "A" => &mut abc[0],
            "B" => &mut abc[1],
            "C" => &mut abc[2],
            _ => continue,
        };
        let text: &str = &a.value;
        let v: f64 = text
            .trim()
            .parse()
            .map_err(|_| bad(len, format!("RIst value {text:?} is not a number")))?;
        if !v.is_finite() {
            return Err(bad(len, format!("RIst value {text:?} is not finite")));
        }
        if slot.replace(v).is_some() {
            return Err(bad(len, "RIst repeats an attribute"));
        }
    }
    Ok((xyz, abc))
}

/// Parses a `<Rob>` datagram.
pub fn parse_rob(bytes: &[u8]) -> Result<RobFrame, RobotError> {
    let len = bytes.len();
    if len > MAX_PACKET_BYTES {
        return Err(bad(len, format!("longer than {MAX_PACKET_BYTES} bytes")));
    }
    let mut r = Reader::from_reader(bytes);
    r.config_mut().trim_text(true);
    let mut depth = 0usize;
    let mut root_done = false;
    let mut in_ipoc = false;
    let mut ipoc: Option<u64> = None;
    let mut rist: Option<([f64; 3], Option<[f64; 3]>)> = None;
    let mut rsol: Option<[f64; 3]> = None;
    loop {
        let ev = r
            .read_event()
            .map_err(|e| bad(len, format!("XML at byte {}: {e}", r.buffer_position())))?;
        match ev {
            Event::Eof => break,
            Event::Decl(_) | Event::Comment(_) | Event::PI(_) => {}
            Event::DocType(_) => return Err(bad(len, "DOCTYPE is not allowed")),
            _ if root_done => return Err(bad(len, "content after </Rob>")),
            Event::Empty(_) if depth == 0 => return Err(bad(len, "empty root element")),
            Event::Start(e) if depth == 0 => {
                if e.name().as_ref() != "Rob" {
                    let name = e.name().as_ref().to_owned();
                    return Err(bad(len, format!("root element <{name}> is not <Rob>")));
                }
                depth = 1;
            }
            Event::Start(e) => {
                if depth == 1 && e.name().as_ref() == "IPOC" {
                    in_ipoc = true;
                }
                if depth == 1 && e.name().as_ref() == "RIst" {
                    return Err(bad(len, "RIst must be an empty element with attributes"));
                }
                depth += 1;
            }
            Event::Empty(e) => {
                if depth == 1 && e.name().as_ref() == "RIst" {
                    let (xyz, abc) = xyzabc(len, &e)?;
                    let [Some(x), Some(y), Some(z)] = xyz else {
                        return Err(bad(len, "RIst without X, Y and Z"));
                    };
                    let abc = match abc {
                        [Some(a), Some(b), Some(c)] => Some([a, b, c]),
                        _ => None,
                    };
                    if rist.replace(([x, y, z], abc)).is_some() {
                        return Err(bad(len, "more than one RIst"));
                    }
                } else if depth == 1 && e.name().as_ref() == "RSol" {
                    let (xyz, _) = xyzabc(len, &e)?;
                    let [Some(x), Some(y), Some(z)] = xyz else {
                        return Err(bad(len, "RSol without X, Y and Z"));
                    };
                    if rsol.replace([x, y, z]).is_some() {
                        return Err(bad(len, "more than one RSol"));
                    }
                } else if depth == 1 && e.name().as_ref() == "IPOC" {
                    return Err(bad(len, "empty IPOC"));
                }
            }
            Event::Text(t) if in_ipoc => {
                let text: &str = &t;
                let v: u64 = text
                    .trim()
                    .parse()
                    .map_err(|_| bad(len, format!("IPOC {text:?} is not an unsigned integer")))?;
                if ipoc.replace(v).is_some() {
                    return Err(bad(len, "more than one IPOC"));
                }
            }
            Event::Text(_) | Event::CData(_) | Event::GeneralRef(_) => {}
            Event::End(_) => {
                in_ipoc = false;
                depth = depth.saturating_sub(1);
                if depth == 0 {
                    root_done = true;
                }
            }
        }
    }
    if !root_done {
        return Err(bad(len, "no complete <Rob> element"));
    }
    let ipoc = ipoc.ok_or_else(|| bad(len, "no IPOC"))?;
    let (pos_mm, abc_deg) = rist.ok_or_else(|| bad(len, "no RIst"))?;
    Ok(RobFrame {
        ipoc,
        pos_mm,
        abc_deg,
        setpoint_mm: rsol,
    })
}

/// Writes the `<Sen>` answer: `Type` attribute, `RKorr` (mm, degrees) and the echoed `IPOC`.
pub fn write_sen(out: &mut Vec<u8>, sen_type: &str, korr_mm: [f64; 3], korr_deg: [f64; 3], ipoc: u64) {
    out.clear();
    // Writing into a Vec cannot fail.
    let _ = write!(
        out,
        "<Sen Type=\"{sen_type}\"><EStr>irtrack</EStr><RKorr X=\"{:.4}\" Y=\"{:.4}\" Z=\"{:.4}\" A=\"{:.4}\" B=\"{:.4}\" C=\"{:.4}\"/><IPOC>{ipoc}</IPOC></Sen>",
        korr_mm[0], korr_mm[1], korr_mm[2], korr_deg[0], korr_deg[1], korr_deg[2]
    );
}

/// What a `<Sen>` datagram says (the simulated controller's side).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SenFrame {
    /// The IPOC of the `<Rob>` answered.
    pub ipoc: u64,
    /// `RKorr` X, Y, Z (mm).
    pub korr_mm: [f64; 3],
    /// `RKorr` A, B, C (degrees).
    pub korr_deg: [f64; 3],
}

/// Parses a `<Sen>` datagram (used by the simulated controller and the tests).
pub fn parse_sen(bytes: &[u8]) -> Result<SenFrame, RobotError> {
    let len = bytes.len();
    let mut r = Reader::from_reader(bytes);
    r.config_mut().trim_text(true);
    let mut in_ipoc = false;
    let mut ipoc = None;
    let mut korr = None;
    let mut root = false;
    loop {
        match r.read_event().map_err(|e| bad(len, format!("XML: {e}")))? {
            Event::Eof => break,
            Event::Start(e) if !root => {
                if e.name().as_ref() != "Sen" {
                    return Err(bad(len, "root element is not <Sen>"));
                }
                root = true;
            }
            Event::Start(e) => in_ipoc = e.name().as_ref() == "IPOC",
            Event::Empty(e) if e.name().as_ref() == "RKorr" => {
                let (xyz, abc) = xyzabc(len, &e)?;
                korr = Some((xyz.map(|v| v.unwrap_or(0.0)), abc.map(|v| v.unwrap_or(0.0))));
            }
            Event::Text(t) if in_ipoc => {
                let text: &str = &t;
                ipoc = Some(
                    text.trim()
                        .parse::<u64>()
                        .map_err(|_| bad(len, format!("IPOC {text:?}")))?,
                );
            }
            Event::End(_) => in_ipoc = false,
            _ => {}
        }
    }
    let (korr_mm, korr_deg) = korr.ok_or_else(|| bad(len, "no RKorr"))?;
    Ok(SenFrame {
        ipoc: ipoc.ok_or_else(|| bad(len, "no IPOC"))?,
        korr_mm,
        korr_deg,
    })
}

/// The RSI side of a streaming link.
pub struct Rsi {
    mode: RsiMode,
    sen_type: String,
    /// `RIst` when the session started: the reference of absolute corrections.
    start_mm: [f64; 3],
    /// Position commanded so far (start + the sum of relative increments).
    commanded_mm: [f64; 3],
    /// The current packet's `RSol`, when the controller sends it.
    setpoint_mm: Option<[f64; 3]>,
}

impl StreamProto for Rsi {
    const KIND: LinkKind = LinkKind::Rsi;

    fn new(cfg: &StreamConfig) -> Self {
        Self {
            mode: cfg.rsi_mode,
            sen_type: cfg.rsi_sen_type.clone(),
            start_mm: [0.0; 3],
            commanded_mm: [0.0; 3],
            setpoint_mm: None,
        }
    }

    fn decode(&mut self, bytes: &[u8]) -> Result<RobotPacket, RobotError> {
        let f = parse_rob(bytes)?;
        self.setpoint_mm = f.setpoint_mm;
        Ok(RobotPacket {
            id: f.ipoc,
            pos_mm: f.pos_mm,
            quat_wxyz: None,
        })
    }

    fn ahead(id: u64, last: u64) -> Option<u64> {
        id.checked_sub(last).filter(|d| *d > 0)
    }

    /// IPOC counts milliseconds: 0.4 s of lost packets, besides the time-based allowance.
    const SEQ_SLACK_IDS: u64 = 400;
    /// Twice the IPOC's millisecond rate (margin for a controller clock that runs fast).
    const MAX_IDS_PER_S: u64 = 2000;

    fn on_session(&mut self, first: &RobotPacket) {
        self.start_mm = first.pos_mm;
        self.commanded_mm = first.pos_mm;
    }

    fn encode(&mut self, pkt: &RobotPacket, cmd: &Command, out: &mut Vec<u8>) -> Result<(), RobotError> {
        let reference = match self.mode {
            RsiMode::Absolute => self.start_mm,
            // The controller's setpoint already holds every increment it applied: a reply it
            // dropped as late is then not counted twice (the running sum would drift).
            RsiMode::Relative => self.setpoint_mm.unwrap_or(self.commanded_mm),
        };
        // Rounded to what goes on the wire, so relative increments sum without drift.
        let round = |v: f64| (v * 1e4).round() / 1e4;
        let korr = [
            round(cmd.pos_mm[0] - reference[0]),
            round(cmd.pos_mm[1] - reference[1]),
            round(cmd.pos_mm[2] - reference[2]),
        ];
        self.commanded_mm = [
            reference[0] + korr[0],
            reference[1] + korr[1],
            reference[2] + korr[2],
        ];
        // Orientation is held (zero rotation correction): RSI here guides the position only.
        write_sen(out, &self.sen_type, korr, [0.0; 3], pkt.id);
        Ok(())
    }
}
