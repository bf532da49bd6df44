//! NatNet 3.1 packets (docs/outputs.md, "NatNet"): written from the protocol's public
//! description. Every packet is `u16 message id, u16 payload bytes, payload`, little-endian;
//! strings are NUL-terminated unless a fixed length is stated.

use std::net::Ipv4Addr;

use crate::error::{FirmwareError, Result};
use crate::outputs::scene::{Models, SceneFrame};

/// Client → server: connect (and ping); answered with `NAT_SERVERINFO`.
pub const NAT_CONNECT: u16 = 0;
/// Server → client: the server's name, versions and data port ([`ServerInfo`]).
pub const NAT_SERVERINFO: u16 = 1;
/// Client → server: a command string.
pub const NAT_REQUEST: u16 = 2;
/// Server → client: the answer to a `NAT_REQUEST`.
pub const NAT_RESPONSE: u16 = 3;
/// Client → server: ask for the model definitions.
pub const NAT_REQUEST_MODELDEF: u16 = 4;
/// Server → client: the model definitions (marker sets, rigid bodies).
pub const NAT_MODELDEF: u16 = 5;
/// Client → server: ask for the latest frame.
pub const NAT_REQUEST_FRAMEOFDATA: u16 = 6;
/// Server → client: one frame of tracking data.
pub const NAT_FRAMEOFDATA: u16 = 7;
/// Either way: a free-text message.
pub const NAT_MESSAGESTRING: u16 = 8;
/// Client → server: the client leaves (unicast: stop sending to it).
pub const NAT_DISCONNECT: u16 = 9;
/// Client → server: still here (unicast clients not heard from time out).
pub const NAT_KEEPALIVE: u16 = 10;
/// Server → client: the request's message id is not one the server answers.
pub const NAT_UNRECOGNIZED_REQUEST: u16 = 100;

/// The protocol version irtrackd speaks (the frame layout below depends on it).
pub const NATNET_VERSION: [u8; 4] = [3, 1, 0, 0];
/// Largest UDP payload a NatNet packet may have.
pub const MAX_PACKET: usize = 65503;
/// High-resolution timestamps are nanoseconds of the tracker's monotonic clock.
pub const CLOCK_HZ: u64 = 1_000_000_000;

/// Data description types (model definitions).
const DESC_MARKERSET: u32 = 0;
const DESC_RIGIDBODY: u32 = 1;

/// Labelled-marker parameter bits.
pub const MARKER_POINT_CLOUD_SOLVED: u16 = 0x02;
/// The marker's position comes from a solved model (a tool's pose).
pub const MARKER_MODEL_SOLVED: u16 = 0x04;
/// The marker belongs to a model (a tool's LED).
pub const MARKER_HAS_MODEL: u16 = 0x08;
/// The marker belongs to no model.
pub const MARKER_UNLABELED: u16 = 0x10;

/// Diameter reported for every marker (the LEDs' size is not measured), metres.
pub const MARKER_SIZE_M: f32 = 0.005;

/// A request from a client.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Request<'a> {
    /// Message id (`NAT_CONNECT`, `NAT_REQUEST`, ...).
    pub id: u16,
    /// Payload bytes (for `NAT_REQUEST`, a command string).
    pub payload: &'a [u8],
}

/// Splits a datagram into message id and payload; refuses short or inconsistent packets.
pub fn parse_request(datagram: &[u8]) -> Result<Request<'_>> {
    let bad = |reason: String| FirmwareError::Output {
        what: "NatNet request",
        reason,
    };
    if datagram.len() < 4 {
        return Err(bad(format!(
            "{} bytes, shorter than the 4-byte header",
            datagram.len()
        )));
    }
    let id = u16::from_le_bytes([datagram[0], datagram[1]]);
    let size = usize::from(u16::from_le_bytes([datagram[2], datagram[3]]));
    let payload = &datagram[4..];
    if size > payload.len() {
        return Err(bad(format!(
            "message {id} announces {size} payload bytes, has {}",
            payload.len()
        )));
    }
    Ok(Request {
        id,
        payload: &payload[..size],
    })
}

/// The command string of a `NAT_REQUEST` payload (up to the first NUL).
pub fn command_text(payload: &[u8]) -> String {
    let end = payload.iter().position(|&b| b == 0).unwrap_or(payload.len());
    String::from_utf8_lossy(&payload[..end]).into_owned()
}

/// Writes little-endian values into a reused buffer.
struct Writer<'a>(&'a mut Vec<u8>);

impl Writer<'_> {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u16(&mut self, v: u16) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn i16(&mut self, v: i16) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn i32(&mut self, v: i32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f64(&mut self, v: f64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn vec3(&mut self, v: &[f64; 3]) {
        for c in v {
            self.f32(*c as f32);
        }
    }
    fn count(&mut self, n: usize) {
        self.i32(i32::try_from(n).unwrap_or(i32::MAX));
    }
    /// NUL-terminated; an interior NUL ends the string early (names never contain one).
    fn string(&mut self, s: &str) {
        self.0.extend(s.bytes().take_while(|&b| b != 0));
        self.0.push(0);
    }
    /// Exactly `len` bytes: the string, cut to leave room for a NUL, then zeros.
    fn fixed_string(&mut self, s: &str, len: usize) {
        let bytes: Vec<u8> = s.bytes().take_while(|&b| b != 0).take(len - 1).collect();
        self.0.extend_from_slice(&bytes);
        self.0.resize(self.0.len() + len - bytes.len(), 0);
    }
}

/// Starts a packet in `out` (cleared); [`finish`] fills in the payload size.
fn begin(out: &mut Vec<u8>, id: u16) -> Writer<'_> {
    out.clear();
    let mut w = Writer(out);
    w.u16(id);
    w.u16(0);
    w
}

fn finish(out: &mut [u8]) -> Result<()> {
    let payload = out.len() - 4;
    if out.len() > MAX_PACKET {
        return Err(FirmwareError::Output {
            what: "NatNet packet",
            reason: format!("{} bytes exceed NatNet's {MAX_PACKET}-byte limit", out.len()),
        });
    }
    out[2..4].copy_from_slice(&(payload as u16).to_le_bytes());
    Ok(())
}

/// What the server says about itself in `NAT_SERVERINFO`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServerInfo {
    /// Application name shown by clients (`irtrackd`).
    pub app_name: String,
    /// Application version, four bytes (major, minor, build, revision).
    pub app_version: [u8; 4],
    /// UDP port of the frame data (`[outputs.natnet] data_port`).
    pub data_port: u16,
    /// The multicast group frames go to; `None` when frames go to each client (unicast).
    pub multicast: Option<Ipv4Addr>,
}

/// `NAT_SERVERINFO`: name (256 bytes), app version, NatNet version, then the connection info
/// of NatNet 3: clock frequency u64, data port u16, multicast flag u8, group address.
pub fn encode_server_info(info: &ServerInfo, out: &mut Vec<u8>) -> Result<()> {
    let mut w = begin(out, NAT_SERVERINFO);
    w.fixed_string(&info.app_name, 256);
    w.0.extend_from_slice(&info.app_version);
    w.0.extend_from_slice(&NATNET_VERSION);
    w.u64(CLOCK_HZ);
    w.u16(info.data_port);
    w.u8(u8::from(info.multicast.is_some()));
    w.0.extend_from_slice(&info.multicast.unwrap_or(Ipv4Addr::UNSPECIFIED).octets());
    finish(out)
}

/// `NAT_MODELDEF`: one marker set per model (its markers named `<model>_<n>`), then one rigid
/// body description per rigid-body model (name, id, parent −1, zero offset, marker positions
/// relative to the body, marker labels 0).
pub fn encode_model_def(models: &Models, out: &mut Vec<u8>) -> Result<()> {
    let mut w = begin(out, NAT_MODELDEF);
    w.count(models.list.len() + models.rigid_bodies().count());
    for m in &models.list {
        w.u32(DESC_MARKERSET);
        w.string(&m.name);
        w.count(m.markers_m.len());
        for i in 0..m.markers_m.len() {
            w.string(&format!("{}_{}", m.name, i + 1));
        }
    }
    for m in models.rigid_bodies() {
        w.u32(DESC_RIGIDBODY);
        w.string(&m.name);
        w.u32(m.id);
        w.i32(-1);
        w.vec3(&[0.0; 3]);
        w.count(m.markers_m.len());
        for p in &m.markers_m {
            w.vec3(p);
        }
        for _ in &m.markers_m {
            w.i32(0);
        }
    }
    finish(out)
}

/// Stamps of one frame besides the scene's capture time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameStamps {
    /// When the server sends the frame (tracker monotonic clock, ns).
    pub transmit_ns: u64,
    /// The model list changed since the last frame: clients should ask for definitions again.
    pub models_changed: bool,
}

/// `NAT_FRAMEOFDATA` for NatNet 3.1 (layout in docs/outputs.md). `names` are the marker set
/// names in the order of `frame.marker_sets`. Allocation-free once `out` has grown.
pub fn encode_frame(
    frame: &SceneFrame,
    names: &[String],
    stamps: FrameStamps,
    out: &mut Vec<u8>,
) -> Result<()> {
    let mut w = begin(out, NAT_FRAMEOFDATA);
    w.u32(frame.frame as u32);
    w.count(frame.marker_sets.len());
    for (set, name) in frame.marker_sets.iter().zip(names) {
        w.string(name);
        w.count(set.len());
        for p in set {
            w.vec3(p);
        }
    }
    w.count(frame.unlabelled_m.len());
    for p in &frame.unlabelled_m {
        w.vec3(p);
    }
    w.count(frame.bodies.len());
    for b in &frame.bodies {
        w.u32(b.id);
        w.vec3(&b.position_m);
        for c in b.orientation_xyzw {
            w.f32(c as f32);
        }
        w.f32(b.mean_error_m as f32);
        w.i16(i16::from(b.tracked));
    }
    w.count(0); // skeletons
    w.count(frame.markers.len());
    for m in &frame.markers {
        w.u32(m.id);
        w.vec3(&m.position_m);
        w.f32(MARKER_SIZE_M);
        let params = if m.model_solved {
            MARKER_MODEL_SOLVED | MARKER_HAS_MODEL
        } else {
            MARKER_POINT_CLOUD_SOLVED | MARKER_UNLABELED
        };
        w.u16(params);
        w.f32(m.residual_m as f32);
    }
    w.count(0); // force plates
    w.count(0); // devices
    w.u32(0); // SMPTE timecode
    w.u32(0); // timecode sub-frame
    w.f64(frame.capture_ts_ns as f64 / 1e9);
    w.u64(frame.capture_ts_ns); // mid-exposure
    w.u64(frame.capture_ts_ns.saturating_add(frame.latency_ns)); // data received (published)
    w.u64(stamps.transmit_ns);
    w.i16(if stamps.models_changed { 0x02 } else { 0 });
    w.i32(0); // end of data
    finish(out)
}

/// `NAT_RESPONSE` with a 4-byte result code (0: done; irtrackd answers 1 to every command it
/// does not carry out).
pub fn encode_response_code(code: i32, out: &mut Vec<u8>) -> Result<()> {
    let mut w = begin(out, NAT_RESPONSE);
    w.i32(code);
    finish(out)
}

/// An empty packet with just a message id (`NAT_UNRECOGNIZED_REQUEST`, keep-alive echo).
pub fn encode_empty(id: u16, out: &mut Vec<u8>) -> Result<()> {
    begin(out, id);
    finish(out)
}

#[cfg(test)]
mod tests {
    //! Golden packets from firmware/tests/data/natnet_golden.py (Python's struct module,
    //! written from docs/outputs.md, independent of this encoder).
    use super::*;
    use crate::outputs::scene::{BodySample, MarkerSample, ModelDef};

    const SERVER_INFO: &str = "010017016972747261636b640000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000000100000301000000ca9a3b00000000e6050000000000";
    const MODEL_DEF: &str = "05006400020000000000000070726f6265000200000070726f62655f310070726f62655f32000100000070726f62650001000000ffffffff0000000000000000000000000200000000000000000000000ad7a33ccdcccc3d000000000ad7a33c0000000000000000";
    const FRAME: &str = "0700ca002a0000000100000070726f62650002000000cdcccc3dcdcc4c3e5c8f823fcdcc4c3ecdcc4c3e5c8f823f000000000100000001000000cdcccc3dcdcc4c3e0000803f0000000000000000000000000000803f6f12033a0100000000000200000001000100cdcccc3dcdcc4c3e5c8f823f0ad7a33b0c000000000002000100cdcc4c3ecdcc4c3e5c8f823f0ad7a33b0c000000000000000000000000000000000000000000000000000000f03f00ca9a3b00000000804eb93b00000000a0efc03b00000000000000000000";

    const FRAME_LOOSE: &str = "0700f0002a0000000100000070726f62650002000000cdcccc3dcdcc4c3e5c8f823fcdcc4c3ecdcc4c3e5c8f823f010000009a99993ecdccccbd6666663f0100000001000000cdcccc3dcdcc4c3e0000803f0000000000000000000000000000803f6f12033a0100000000000300000001000100cdcccc3dcdcc4c3e5c8f823f0ad7a33b0c000000000002000100cdcc4c3ecdcc4c3e5c8f823f0ad7a33b0c0000000000050000009a99993ecdccccbd6666663f0ad7a33b12006f12833900000000000000000000000000000000000000000000f03f00ca9a3b00000000804eb93b00000000a0efc03b00000000000000000000";

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    fn probe() -> Models {
        Models {
            list: vec![ModelDef {
                id: 1,
                name: "probe".into(),
                markers_m: vec![[0.0, 0.0, 0.02], [0.1, 0.0, 0.02]],
                rigid_body: true,
            }],
        }
    }

    #[test]
    fn server_info_matches_golden_bytes() {
        let mut out = Vec::new();
        let info = ServerInfo {
            app_name: "irtrackd".into(),
            app_version: [0, 1, 0, 0],
            data_port: 1510,
            multicast: None,
        };
        encode_server_info(&info, &mut out).unwrap();
        assert_eq!(out, hex(SERVER_INFO));
    }

    #[test]
    fn model_definitions_match_golden_bytes() {
        let mut out = Vec::new();
        encode_model_def(&probe(), &mut out).unwrap();
        assert_eq!(out, hex(MODEL_DEF));
    }

    #[test]
    fn frame_of_data_matches_golden_bytes() {
        let p = [0.1, 0.2, 1.0];
        let m: Vec<[f64; 3]> = probe().list[0]
            .markers_m
            .iter()
            .map(|l| [p[0] + l[0], p[1] + l[1], p[2] + l[2]])
            .collect();
        let scene = SceneFrame {
            frame: 42,
            capture_ts_ns: 1_000_000_000,
            latency_ns: 2_000_000,
            world_frame: false,
            marker_sets: vec![m.clone()],
            bodies: vec![BodySample {
                id: 1,
                position_m: p,
                orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
                mean_error_m: 0.0005,
                tracked: true,
            }],
            markers: m
                .iter()
                .enumerate()
                .map(|(i, q)| MarkerSample {
                    id: (1 << 16) | (i as u32 + 1),
                    position_m: *q,
                    residual_m: 0.0,
                    model_solved: true,
                })
                .collect(),
            unlabelled_m: vec![],
            loose: vec![],
            per_tool: false,
        };
        let mut out = Vec::new();
        let stamps = FrameStamps {
            transmit_ns: 1_002_500_000,
            models_changed: false,
        };
        encode_frame(&scene, &["probe".to_string()], stamps, &mut out).unwrap();
        assert_eq!(out, hex(FRAME));
        // The buffer is reused: a second frame encodes without growing it.
        let cap = out.capacity();
        encode_frame(&scene, &["probe".to_string()], stamps, &mut out).unwrap();
        assert_eq!(out.capacity(), cap);
    }

    /// A loose LED goes out twice: in the legacy unlabelled list (NatNet 2 clients) and as a
    /// labelled marker of model 0 flagged unlabelled (NatNet 3+ clients skip the legacy list).
    #[test]
    fn frame_with_a_loose_led_matches_golden_bytes() {
        let p = [0.1, 0.2, 1.0];
        let u = [0.3, -0.1, 0.9];
        let m: Vec<[f64; 3]> = probe().list[0]
            .markers_m
            .iter()
            .map(|l| [p[0] + l[0], p[1] + l[1], p[2] + l[2]])
            .collect();
        let mut markers: Vec<MarkerSample> = m
            .iter()
            .enumerate()
            .map(|(i, q)| MarkerSample {
                id: (1 << 16) | (i as u32 + 1),
                position_m: *q,
                residual_m: 0.0,
                model_solved: true,
            })
            .collect();
        markers.push(MarkerSample {
            id: crate::outputs::scene::loose_marker_id(4),
            position_m: u,
            residual_m: 0.00025,
            model_solved: false,
        });
        let scene = SceneFrame {
            frame: 42,
            capture_ts_ns: 1_000_000_000,
            latency_ns: 2_000_000,
            world_frame: false,
            marker_sets: vec![m.clone()],
            bodies: vec![BodySample {
                id: 1,
                position_m: p,
                orientation_xyzw: [0.0, 0.0, 0.0, 1.0],
                mean_error_m: 0.0005,
                tracked: true,
            }],
            markers,
            unlabelled_m: vec![u],
            loose: vec![],
            per_tool: true,
        };
        let mut out = Vec::new();
        let stamps = FrameStamps {
            transmit_ns: 1_002_500_000,
            models_changed: false,
        };
        encode_frame(&scene, &["probe".to_string()], stamps, &mut out).unwrap();
        assert_eq!(out, hex(FRAME_LOOSE));
    }

    #[test]
    fn requests_are_split_and_short_ones_refused() {
        let r = parse_request(&[2, 0, 5, 0, b'P', b'i', b'n', b'g', 0]).unwrap();
        assert_eq!((r.id, command_text(r.payload).as_str()), (NAT_REQUEST, "Ping"));
        assert_eq!(parse_request(&[10, 0, 0, 0]).unwrap().id, NAT_KEEPALIVE);
        let e = parse_request(&[0, 0]).unwrap_err().to_string();
        assert!(e.contains("shorter than the 4-byte header"), "{e}");
        let e = parse_request(&[0, 0, 9, 0, 1]).unwrap_err().to_string();
        assert!(e.contains("announces 9 payload bytes, has 1"), "{e}");
    }
}
