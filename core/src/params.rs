//! Rig parameters and their on-wire/on-disk blob format (see docs/param-blob.md).

use alloc::boxed::Box;
use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::camera::{CameraModel, RigidTransform};
use crate::crc::Crc32;
use crate::timing::CameraTiming;
use crate::{Error, Result};

/// One camera of the rig: model plus pose relative to camera 0
/// (`x_cam = R x_cam0 + t`, OpenCV stereoCalibrate's R, T). Camera 0 has the identity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraParams {
    /// Intrinsics, distortion and image size.
    pub model: CameraModel,
    /// Pose of this camera relative to camera 0 (`x_cam = R · x_cam0 + T`).
    pub cam_from_cam0: RigidTransform,
}

/// A rigid tool carrying several LEDs (6-DOF tracking); LED positions in the tool frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolDefinition {
    /// Name the tool is reported under.
    pub name: String,
    /// LED positions in the tool frame (mm).
    pub leds_mm: Vec<[f64; 3]>,
    /// The tool's tip in the tool frame (mm), from a pivot calibration (`host-tools pivot`).
    /// A tool with a tip is reported at its tip; without one, at its origin. Only blob format
    /// version 2 carries it (docs/param-blob.md).
    pub tip_mm: Option<[f64; 3]>,
}

/// Version-1 body (no tool tips), encoded from borrowed fields so writing needs no copy.
/// postcard encodes `&str`/`String`, `&[T]`/`Vec<T>` and `&Option<T>`/`Option<T>` alike.
#[derive(Serialize)]
struct RigV1Ref<'a> {
    rig_id: &'a str,
    created_unix_s: u64,
    cameras: &'a [CameraParams],
    world_from_cam0: &'a Option<RigidTransform>,
    tools: Vec<ToolV1Ref<'a>>,
}

#[derive(Serialize)]
struct ToolV1Ref<'a> {
    name: &'a str,
    leds_mm: &'a [[f64; 3]],
}

/// Version-1 body as read.
#[derive(Deserialize)]
struct RigV1 {
    rig_id: String,
    created_unix_s: u64,
    cameras: Vec<CameraParams>,
    world_from_cam0: Option<RigidTransform>,
    tools: Vec<ToolV1>,
}

#[derive(Deserialize)]
struct ToolV1 {
    name: String,
    leds_mm: Vec<[f64; 3]>,
}

/// Version-2 body (tools with tips, no calibration record), borrowed for writing.
#[derive(Serialize)]
struct RigV2Ref<'a> {
    rig_id: &'a str,
    created_unix_s: u64,
    cameras: &'a [CameraParams],
    world_from_cam0: &'a Option<RigidTransform>,
    tools: &'a [ToolDefinition],
}

/// Version-2 body as read.
#[derive(Deserialize)]
struct RigV2 {
    rig_id: String,
    created_unix_s: u64,
    cameras: Vec<CameraParams>,
    world_from_cam0: Option<RigidTransform>,
    tools: Vec<ToolDefinition>,
}

impl From<RigV2> for RigParams {
    fn from(v: RigV2) -> Self {
        RigParams {
            rig_id: v.rig_id,
            created_unix_s: v.created_unix_s,
            cameras: v.cameras,
            world_from_cam0: v.world_from_cam0,
            tools: v.tools,
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }
}

/// Version-3 body (a calibration record, no camera placement), borrowed for writing.
#[derive(Serialize)]
struct RigV3Ref<'a> {
    rig_id: &'a str,
    created_unix_s: u64,
    cameras: &'a [CameraParams],
    world_from_cam0: &'a Option<RigidTransform>,
    tools: &'a [ToolDefinition],
    calibration: &'a Option<Box<CalibrationInfo>>,
}

/// Version-3 body as read.
#[derive(Deserialize)]
struct RigV3 {
    rig_id: String,
    created_unix_s: u64,
    cameras: Vec<CameraParams>,
    world_from_cam0: Option<RigidTransform>,
    tools: Vec<ToolDefinition>,
    calibration: Option<Box<CalibrationInfo>>,
}

impl From<RigV3> for RigParams {
    fn from(v: RigV3) -> Self {
        RigParams {
            rig_id: v.rig_id,
            created_unix_s: v.created_unix_s,
            cameras: v.cameras,
            world_from_cam0: v.world_from_cam0,
            tools: v.tools,
            calibration: v.calibration,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }
}

/// Version-4 body (a camera placement, no timing or serial), borrowed for writing.
#[derive(Serialize)]
struct RigV4Ref<'a> {
    rig_id: &'a str,
    created_unix_s: u64,
    cameras: &'a [CameraParams],
    world_from_cam0: &'a Option<RigidTransform>,
    tools: &'a [ToolDefinition],
    calibration: &'a Option<Box<CalibrationInfo>>,
    placement: &'a [CameraPlace],
}

/// Version-4 body as read.
#[derive(Deserialize)]
struct RigV4 {
    rig_id: String,
    created_unix_s: u64,
    cameras: Vec<CameraParams>,
    world_from_cam0: Option<RigidTransform>,
    tools: Vec<ToolDefinition>,
    calibration: Option<Box<CalibrationInfo>>,
    placement: Vec<CameraPlace>,
}

impl From<RigV4> for RigParams {
    fn from(v: RigV4) -> Self {
        RigParams {
            rig_id: v.rig_id,
            created_unix_s: v.created_unix_s,
            cameras: v.cameras,
            world_from_cam0: v.world_from_cam0,
            tools: v.tools,
            calibration: v.calibration,
            placement: v.placement,
            timing: Vec::new(),
            serial: 0,
        }
    }
}

/// Version-5 body (per-camera timing and the set's serial), borrowed for writing. The timing
/// list is empty when every camera has the default timing ([`RigParams::has_timing`]).
#[derive(Serialize)]
struct RigV5Ref<'a> {
    rig_id: &'a str,
    created_unix_s: u64,
    cameras: &'a [CameraParams],
    world_from_cam0: &'a Option<RigidTransform>,
    tools: &'a [ToolDefinition],
    calibration: &'a Option<Box<CalibrationInfo>>,
    placement: &'a [CameraPlace],
    timing: &'a [CameraTiming],
    serial: u64,
}

/// Version-5 body as read.
#[derive(Deserialize)]
struct RigV5 {
    rig_id: String,
    created_unix_s: u64,
    cameras: Vec<CameraParams>,
    world_from_cam0: Option<RigidTransform>,
    tools: Vec<ToolDefinition>,
    calibration: Option<Box<CalibrationInfo>>,
    placement: Vec<CameraPlace>,
    timing: Vec<CameraTiming>,
    serial: u64,
}

impl From<RigV5> for RigParams {
    fn from(v: RigV5) -> Self {
        RigParams {
            rig_id: v.rig_id,
            created_unix_s: v.created_unix_s,
            cameras: v.cameras,
            world_from_cam0: v.world_from_cam0,
            tools: v.tools,
            calibration: v.calibration,
            placement: v.placement,
            timing: v.timing,
            serial: v.serial,
        }
    }
}

/// A camera's board and its index on that board: where the rig's camera `i` is captured when
/// the cameras sit on several boards (cluster solver, docs/cluster.md).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraPlace {
    /// The camera board's name (as in its observations and its `[cluster] board`).
    pub board: String,
    /// The camera's index on that board.
    pub local_index: u8,
}

/// Longest board name in a placement, bytes (it travels in observations and key expressions).
pub const MAX_BOARD_NAME_LEN: usize = 32;
/// Longest tool name (bytes): per-tool stream records carry it in a fixed field
/// (docs/stream-protocol.md).
pub const MAX_TOOL_NAME_LEN: usize = 32;

/// The judgement of a calibration against its quality limits (docs/calibration.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Verdict {
    /// Every limit held.
    Good,
    /// A limit failed and the result was written anyway (`--accept-poor`).
    Poor,
}

impl Verdict {
    /// `good` or `poor`, as status pages and reports print it.
    pub fn as_str(self) -> &'static str {
        match self {
            Verdict::Good => "good",
            Verdict::Poor => "poor",
        }
    }
}

/// One named figure of a calibration, e.g. `wand_length_rms_mm` or `board_rms_px`
/// (names carry their unit; docs/param-blob.md lists those the tools write).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Figure {
    /// Its name, with the unit as suffix.
    pub name: String,
    /// Its value, in that unit.
    pub value: f64,
}

/// Provenance and quality of a parameter set: how it was calibrated, when, by which tool, how
/// well the data fitted and the verdict (blob format version 3, docs/param-blob.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationInfo {
    /// `wand`, `checkerboard`, `wand+checkerboard`, ... (what `host-tools` ran).
    pub method: String,
    /// When the calibration was computed, Unix seconds.
    pub calibrated_unix_s: u64,
    /// The tool that computed it, e.g. `host-tools 0.1.0`.
    pub tool_version: String,
    /// Whether the calibration met its limits.
    pub verdict: Verdict,
    /// The verdict in plain words with the most likely cause of a failed limit (empty when
    /// every limit held).
    pub summary: String,
    /// Reprojection RMS per camera (px), in camera order (empty if the method has none).
    pub rms_px: Vec<f64>,
    /// Further figures: wand length error, board corners RMS, pivot fit, ...
    pub figures: Vec<Figure>,
}

impl CalibrationInfo {
    /// The figure called `name`, if present.
    pub fn figure(&self, name: &str) -> Option<f64> {
        self.figures.iter().find(|f| f.name == name).map(|f| f.value)
    }
}

/// Longest method and tool-version text a calibration record may carry (bytes).
pub const MAX_CALIBRATION_LABEL_LEN: usize = 64;
/// Longest calibration summary (bytes).
pub const MAX_CALIBRATION_SUMMARY_LEN: usize = 1024;
/// Most figures one calibration record may carry.
pub const MAX_CALIBRATION_FIGURES: usize = 64;

impl From<RigV1> for RigParams {
    fn from(v: RigV1) -> Self {
        RigParams {
            rig_id: v.rig_id,
            created_unix_s: v.created_unix_s,
            cameras: v.cameras,
            world_from_cam0: v.world_from_cam0,
            tools: v
                .tools
                .into_iter()
                .map(|t| ToolDefinition {
                    name: t.name,
                    leds_mm: t.leds_mm,
                    tip_mm: None,
                })
                .collect(),
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }
}

/// Everything the tracker needs to turn pixels into millimetres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RigParams {
    /// Identifies the parameter set (shown in status, logged on swap).
    pub rig_id: String,
    /// Creation time, Unix seconds.
    pub created_unix_s: u64,
    /// N ≥ 2 cameras; index 0 is the reference frame.
    pub cameras: Vec<CameraParams>,
    /// Optional registration: robot/world frame from camera-0 frame.
    pub world_from_cam0: Option<RigidTransform>,
    /// Rigid multi-LED tools for 6-DOF tracking.
    pub tools: Vec<ToolDefinition>,
    /// How the set was calibrated and how good it is; only blob format version 3 carries it,
    /// sets without it are written as before (docs/param-blob.md). Boxed: most code never
    /// looks at it, and the set stays small to move and clone.
    pub calibration: Option<Box<CalibrationInfo>>,
    /// Where each camera is when the cameras sit on several boards (docs/cluster.md):
    /// `placement[i]` is camera `i`'s board and its index there. Empty for a single board.
    /// Only blob format version 4 carries it; sets without it are written as before.
    pub placement: Vec<CameraPlace>,
    /// Each camera's timing (shutter, line time, exposure, offset; docs/timing.md): empty
    /// (every camera has the default: global shutter, timestamps are exposure instants) or one
    /// per camera. Read it through [`Self::camera_timing`]. Only blob format version 5 carries
    /// it; a list whose entries are all default is written as none.
    #[serde(default)]
    pub timing: Vec<CameraTiming>,
    /// The set's serial, set by the PC tool that wrote it: larger for a later set of the same
    /// site, so that irtrackd can refuse a rollback to an older one (docs/param-protocol.md).
    /// 0: none (sets written before version 5; they compare by `created_unix_s`).
    #[serde(default)]
    pub serial: u64,
}

/// First bytes of every parameter blob.
pub const BLOB_MAGIC: [u8; 4] = *b"IRPB";
/// The newest blob format version this build reads and writes (5: per-camera timing and a
/// serial; 4: cameras placed on boards; 3: a calibration record; 2: tools may carry a tip). A
/// set is written in the oldest version that carries it, so a set without tool tips and
/// without a calibration record is version 1 and older readers take it.
pub const BLOB_FORMAT_VERSION: u16 = 5;
/// The version that added the camera placement (and no timing or serial).
pub const BLOB_PLACEMENT_VERSION: u16 = 4;
/// The version that added the calibration record (and no camera placement).
pub const BLOB_CALIBRATION_VERSION: u16 = 3;
/// The version whose tools may carry a tip (and no calibration record).
pub const BLOB_TIPS_VERSION: u16 = 2;
/// The oldest blob format version this build reads (1: tools without tips).
pub const BLOB_OLDEST_VERSION: u16 = 1;
/// Header size in bytes (magic, version, flags, body length, CRC-32).
pub const BLOB_HEADER_LEN: usize = 16;
/// Flag bit: an Ed25519 signature trailer follows the body (docs/param-blob.md, `crate::signing`).
pub const BLOB_FLAG_SIGNED: u16 = 0x0001;
/// Flags [`RigParams::from_blob`] and [`BlobHeader::parse`] accept: none. A signed blob is read
/// only through [`crate::signing`], so that a signature can never be silently ignored.
pub const BLOB_KNOWN_FLAGS: u16 = 0;
/// Every flag this build understands ([`BlobHeader::parse_allow_signed`]).
pub const BLOB_ALL_FLAGS: u16 = BLOB_FLAG_SIGNED;
/// Size of the signature trailer of a signed blob: 8-byte key id + 64-byte Ed25519 signature.
pub const BLOB_SIGNATURE_TRAILER_LEN: usize = 72;
/// Maximum number of cameras a rig may have: the one limit of the whole system. The tracker's
/// per-frame arrays are sized by it (`pipeline::MAX_CAMERAS` is this constant), so a set that
/// [`RigParams::validate`] accepts is one every tracker can load.
pub const MAX_CAMERAS: usize = 8;
/// Maximum length of a rig id in bytes.
pub const MAX_RIG_ID_LEN: usize = 64;
/// Largest accepted image dimension in pixels.
pub const MAX_IMAGE_DIM_PX: u32 = 16_384;
/// Tolerance for orthonormality / determinant of rotation matrices.
pub const ROTATION_TOL: f64 = 1e-6;

/// The fixed-size header in front of a blob body.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlobHeader {
    /// Format version of the body.
    pub version: u16,
    /// Flags (e.g. a signature trailer follows).
    pub flags: u16,
    /// Length of the body in bytes.
    pub body_len: u32,
    /// CRC-32 (IEEE) over header bytes 0..12 followed by the body.
    pub crc32: u32,
}

impl BlobHeader {
    /// Parses and checks magic, version and flags from the start of `bytes`
    /// (the body is not looked at). Used by services to reject early. Refuses signed blobs
    /// (`BlobUnsupportedFlags`); see [`Self::parse_allow_signed`].
    pub fn parse(bytes: &[u8]) -> Result<BlobHeader> {
        Self::parse_with_flags(bytes, BLOB_KNOWN_FLAGS)
    }

    /// Like [`Self::parse`], but also accepts the signature flag. For code that then checks
    /// the signature (or says clearly that it did not, like `show-params`).
    pub fn parse_allow_signed(bytes: &[u8]) -> Result<BlobHeader> {
        Self::parse_with_flags(bytes, BLOB_ALL_FLAGS)
    }

    fn parse_with_flags(bytes: &[u8], known: u16) -> Result<BlobHeader> {
        if bytes.len() < 4 {
            return Err(Error::BlobTruncated {
                needed: BLOB_HEADER_LEN,
                got: bytes.len(),
            });
        }
        let magic = [bytes[0], bytes[1], bytes[2], bytes[3]];
        if magic != BLOB_MAGIC {
            return Err(Error::BlobBadMagic { found: magic });
        }
        if bytes.len() < BLOB_HEADER_LEN {
            return Err(Error::BlobTruncated {
                needed: BLOB_HEADER_LEN,
                got: bytes.len(),
            });
        }
        let version = u16::from_le_bytes([bytes[4], bytes[5]]);
        if !(BLOB_OLDEST_VERSION..=BLOB_FORMAT_VERSION).contains(&version) {
            return Err(Error::BlobUnsupportedVersion {
                found: version,
                supported: BLOB_FORMAT_VERSION,
            });
        }
        let flags = u16::from_le_bytes([bytes[6], bytes[7]]);
        if flags & !known != 0 {
            return Err(Error::BlobUnsupportedFlags { flags, known });
        }
        let body_len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]);
        let crc32 = u32::from_le_bytes([bytes[12], bytes[13], bytes[14], bytes[15]]);
        Ok(BlobHeader {
            version,
            flags,
            body_len,
            crc32,
        })
    }

    /// Whether the signature flag is set (a trailer follows the body).
    pub fn is_signed(&self) -> bool {
        self.flags & BLOB_FLAG_SIGNED != 0
    }

    /// Length of the authenticated part: header + body (the CRC covers the same bytes).
    pub fn signed_part_len(&self) -> usize {
        BLOB_HEADER_LEN + self.body_len as usize
    }

    /// Total blob length the header declares, signature trailer included.
    pub fn blob_len(&self) -> usize {
        self.signed_part_len()
            + if self.is_signed() {
                BLOB_SIGNATURE_TRAILER_LEN
            } else {
                0
            }
    }

    /// Checks the length of `bytes` against the header and the CRC; returns the body.
    /// `bytes` must be the whole blob the header came from.
    pub(crate) fn check_frame<'a>(&self, bytes: &'a [u8]) -> Result<&'a [u8]> {
        let needed = self.blob_len();
        if bytes.len() < needed {
            return Err(Error::BlobTruncated {
                needed,
                got: bytes.len(),
            });
        }
        if bytes.len() > needed {
            return Err(Error::BlobTrailingBytes {
                extra: bytes.len() - needed,
            });
        }
        let body = &bytes[BLOB_HEADER_LEN..self.signed_part_len()];
        let computed = blob_crc(&bytes[..12], body);
        if computed != self.crc32 {
            return Err(Error::BlobBadCrc {
                found: self.crc32,
                computed,
            });
        }
        Ok(body)
    }
}

/// Decodes a postcard value that must use all of `body`.
fn take_all<'de, T: Deserialize<'de>>(body: &'de [u8]) -> Result<T> {
    let (value, rest) = postcard::take_from_bytes::<T>(body).map_err(|e| Error::BlobBody {
        reason: postcard_reason(&e),
    })?;
    if !rest.is_empty() {
        return Err(Error::BlobBody {
            reason: "unused bytes at the end of the body",
        });
    }
    Ok(value)
}

/// Decodes the body of a blob of format `version` (checked by [`BlobHeader::parse`]).
pub(crate) fn decode_body(version: u16, body: &[u8]) -> Result<RigParams> {
    let rig = match version {
        BLOB_OLDEST_VERSION => RigParams::from(take_all::<RigV1>(body)?),
        BLOB_TIPS_VERSION => RigParams::from(take_all::<RigV2>(body)?),
        BLOB_CALIBRATION_VERSION => RigParams::from(take_all::<RigV3>(body)?),
        BLOB_PLACEMENT_VERSION => RigParams::from(take_all::<RigV4>(body)?),
        _ => RigParams::from(take_all::<RigV5>(body)?),
    };
    // postcard accepts over-long varints; refuse any body that is not the canonical encoding
    // so that one parameter set has exactly one byte form (and one CRC, its identity). That
    // includes the version: a set without tool tips is written as version 1.
    let (canonical_version, canonical) = rig.encode_body()?;
    if canonical_version != version {
        return Err(Error::BlobBody {
            reason: match version {
                BLOB_TIPS_VERSION => "version-2 body without a tool tip (such a set is written as version 1)",
                BLOB_CALIBRATION_VERSION => {
                    "version-3 body without a calibration record (such a set is written as version 1 or 2)"
                }
                BLOB_PLACEMENT_VERSION => {
                    "version-4 body without a camera placement (such a set is written as version 1, 2 or 3)"
                }
                _ => {
                    "version-5 body without camera timing or serial (such a set is written as version 1 to 4)"
                }
            },
        });
    }
    if !rig.timing.is_empty() && !rig.has_timing() {
        return Err(Error::BlobBody {
            reason: "version-5 body whose cameras all have the default timing (such a list is written empty)",
        });
    }
    if canonical != body {
        return Err(Error::BlobBody {
            reason: "body is not in canonical encoding (over-long integer)",
        });
    }
    Ok(rig)
}

/// `YYYY-MM-DD HH:MM UTC` of Unix seconds (proleptic Gregorian calendar); times past the
/// year 9999 are printed as seconds.
pub fn utc_minute(unix_s: u64) -> String {
    const LAST_S: u64 = 253_402_300_799; // 9999-12-31 23:59:59
    if unix_s > LAST_S {
        return format!("{unix_s} s after 1970");
    }
    let mut days = unix_s / 86_400;
    let minute_of_day = (unix_s % 86_400) / 60;
    // Whole 400-year cycles (146 097 days each) first, then years one by one (≤ 400 steps).
    let mut year = 1970 + 400 * (days / 146_097);
    days %= 146_097;
    let leap = |y: u64| (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
    loop {
        let len = if leap(year) { 366 } else { 365 };
        if days < len {
            break;
        }
        days -= len;
        year += 1;
    }
    let feb = if leap(year) { 29 } else { 28 };
    let mut month = 1;
    for len in [31, feb, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31] {
        if days < len {
            break;
        }
        days -= len;
        month += 1;
    }
    format!(
        "{year:04}-{month:02}-{:02} {:02}:{:02} UTC",
        days + 1,
        minute_of_day / 60,
        minute_of_day % 60
    )
}

/// Whether `bytes` starts like a parameter blob (for sniffing file types).
pub fn looks_like_blob(bytes: &[u8]) -> bool {
    bytes.len() >= 4 && bytes[..4] == BLOB_MAGIC
}

fn blob_crc(header_prefix: &[u8], body: &[u8]) -> u32 {
    let mut c = Crc32::new();
    c.update(header_prefix);
    c.update(body);
    c.finish()
}

fn postcard_reason(e: &postcard::Error) -> &'static str {
    match e {
        postcard::Error::DeserializeUnexpectedEnd => "body ends early",
        postcard::Error::DeserializeBadVarint => "bad varint",
        postcard::Error::DeserializeBadBool => "bad bool",
        postcard::Error::DeserializeBadUtf8 => "string is not UTF-8",
        postcard::Error::DeserializeBadOption => "bad option tag",
        postcard::Error::DeserializeBadEnum => "bad enum tag",
        postcard::Error::DeserializeBadEncoding => "bad encoding",
        _ => "postcard error",
    }
}

fn invalid(reason: String) -> Error {
    Error::InvalidParams { reason }
}

fn check_transform(what: &str, t: &RigidTransform) -> Result<()> {
    if !t.r_row_major.iter().chain(t.t_mm.iter()).all(|v| v.is_finite()) {
        return Err(invalid(format!("{what}: non-finite rotation or translation")));
    }
    if !t.is_proper_rotation(ROTATION_TOL) {
        return Err(invalid(format!(
            "{what}: rotation is not a proper rotation (orthonormal, det +1) within {ROTATION_TOL:e}"
        )));
    }
    Ok(())
}

/// A placement is empty (one board) or names every camera's board, each (board, index) once.
fn check_placement(placement: &[CameraPlace], n_cameras: usize) -> Result<()> {
    if !placement.is_empty() && placement.len() != n_cameras {
        return Err(invalid(format!(
            "placement lists {} cameras, the rig has {n_cameras}",
            placement.len()
        )));
    }
    for (i, p) in placement.iter().enumerate() {
        let name_ok = !p.board.is_empty()
            && p.board.len() <= MAX_BOARD_NAME_LEN
            && p.board
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
        if !name_ok {
            return Err(invalid(format!(
                "camera {i}: board name {:?} must be 1..={MAX_BOARD_NAME_LEN} characters of A-Z a-z 0-9 _ -",
                p.board
            )));
        }
        if placement[..i].contains(p) {
            return Err(invalid(format!(
                "camera {i}: board {:?} camera {} is placed twice",
                p.board, p.local_index
            )));
        }
    }
    Ok(())
}

/// Timing is empty (every camera default) or one sane entry per camera.
fn check_timing(timing: &[CameraTiming], n_cameras: usize) -> Result<()> {
    if !timing.is_empty() && timing.len() != n_cameras {
        return Err(invalid(format!(
            "timing lists {} cameras, the rig has {n_cameras}",
            timing.len()
        )));
    }
    for (i, t) in timing.iter().enumerate() {
        t.validate()
            .map_err(|reason| invalid(format!("camera {i} timing: {reason}")))?;
    }
    Ok(())
}

fn check_calibration(c: &CalibrationInfo, n_cameras: usize) -> Result<()> {
    for (what, text) in [("method", &c.method), ("tool version", &c.tool_version)] {
        if text.is_empty() || text.len() > MAX_CALIBRATION_LABEL_LEN {
            return Err(invalid(format!(
                "calibration {what} must be 1..={MAX_CALIBRATION_LABEL_LEN} bytes, got {}",
                text.len()
            )));
        }
    }
    if c.summary.len() > MAX_CALIBRATION_SUMMARY_LEN {
        return Err(invalid(format!(
            "calibration summary is {} bytes, at most {MAX_CALIBRATION_SUMMARY_LEN}",
            c.summary.len()
        )));
    }
    if !c.rms_px.is_empty() && c.rms_px.len() != n_cameras {
        return Err(invalid(format!(
            "calibration gives an RMS for {} cameras, the rig has {n_cameras}",
            c.rms_px.len()
        )));
    }
    if !c.rms_px.iter().all(|v| v.is_finite() && *v >= 0.0) {
        return Err(invalid("calibration RMS must be finite and ≥ 0".into()));
    }
    if c.figures.len() > MAX_CALIBRATION_FIGURES {
        return Err(invalid(format!(
            "calibration has {} figures, at most {MAX_CALIBRATION_FIGURES}",
            c.figures.len()
        )));
    }
    for f in &c.figures {
        if f.name.is_empty() || f.name.len() > MAX_CALIBRATION_LABEL_LEN || !f.value.is_finite() {
            return Err(invalid(format!(
                "calibration figure {:?} = {} needs a name of 1..={MAX_CALIBRATION_LABEL_LEN} bytes and a finite value",
                f.name, f.value
            )));
        }
    }
    Ok(())
}

fn check_camera(i: usize, cam: &CameraModel) -> Result<()> {
    let size = cam.image_size;
    if size.width_px == 0 || size.height_px == 0 {
        return Err(invalid(format!(
            "camera {i}: image size {}x{} is empty",
            size.width_px, size.height_px
        )));
    }
    if size.width_px > MAX_IMAGE_DIM_PX || size.height_px > MAX_IMAGE_DIM_PX {
        return Err(invalid(format!(
            "camera {i}: image size {}x{} exceeds {MAX_IMAGE_DIM_PX} px",
            size.width_px, size.height_px
        )));
    }
    let k = &cam.intrinsics;
    if ![k.fx_px, k.fy_px, k.cx_px, k.cy_px].iter().all(|v| v.is_finite()) {
        return Err(invalid(format!("camera {i}: non-finite intrinsics")));
    }
    if k.fx_px <= 0.0 || k.fy_px <= 0.0 {
        return Err(invalid(format!(
            "camera {i}: focal length fx={} fy={} px must be > 0",
            k.fx_px, k.fy_px
        )));
    }
    // Pixel centres are at integer coordinates, so the image spans [-0.5, size - 0.5].
    let (w, h) = (f64::from(size.width_px), f64::from(size.height_px));
    if !(-0.5..=w - 0.5).contains(&k.cx_px) || !(-0.5..=h - 0.5).contains(&k.cy_px) {
        return Err(invalid(format!(
            "camera {i}: principal point ({}, {}) px outside the {}x{} image",
            k.cx_px, k.cy_px, size.width_px, size.height_px
        )));
    }
    if !cam.distortion.as_array().iter().all(|v| v.is_finite()) {
        return Err(invalid(format!("camera {i}: non-finite distortion coefficients")));
    }
    Ok(())
}

impl RigParams {
    /// Encodes header + postcard body (docs/param-blob.md). Does not validate, so that
    /// tests and tools can also produce blobs a service must refuse; call [`Self::validate`].
    pub fn to_blob(&self) -> Result<Vec<u8>> {
        self.encode_blob(0, 0)
    }

    /// The format version this set is written in: the oldest that carries it (5 with camera
    /// timing or a serial, else 4 with a camera placement, else 3 with a calibration record,
    /// else 2 if a tool has a tip, else 1), so that readers that only know older versions
    /// still take every set that needs nothing newer.
    pub fn blob_version(&self) -> u16 {
        if self.has_timing() || self.serial != 0 {
            BLOB_FORMAT_VERSION
        } else if !self.placement.is_empty() {
            BLOB_PLACEMENT_VERSION
        } else if self.calibration.is_some() {
            BLOB_CALIBRATION_VERSION
        } else if self.tools.iter().any(|t| t.tip_mm.is_some()) {
            BLOB_TIPS_VERSION
        } else {
            BLOB_OLDEST_VERSION
        }
    }

    /// Whether some camera's timing differs from the default (global shutter, no offset): only
    /// then does the set carry a timing list in its blob.
    pub fn has_timing(&self) -> bool {
        self.timing.iter().any(|t| *t != CameraTiming::default())
    }

    /// Camera `index`'s timing: its entry in [`Self::timing`], or the default (global shutter,
    /// timestamps are exposure instants) when the set carries none.
    pub fn camera_timing(&self, index: usize) -> CameraTiming {
        self.timing.get(index).copied().unwrap_or_default()
    }

    /// The serial a PC tool gives a set it writes (docs/param-blob.md, "Serial"): one more than
    /// the serial of the set it modifies (`previous`, 0 for a new set), and never less than the
    /// current Unix time in seconds, so that sets written later on any of a site's PCs (with
    /// sane clocks) have larger serials, also when they start from scratch.
    pub fn next_serial(previous: u64, now_unix_s: u64) -> u64 {
        previous.saturating_add(1).max(now_unix_s)
    }

    /// The body in the format of [`Self::blob_version`], with that version.
    fn encode_body(&self) -> Result<(u16, Vec<u8>)> {
        let version = self.blob_version();
        let encoded = match version {
            BLOB_OLDEST_VERSION => postcard::to_allocvec(&RigV1Ref {
                rig_id: &self.rig_id,
                created_unix_s: self.created_unix_s,
                cameras: &self.cameras,
                world_from_cam0: &self.world_from_cam0,
                tools: self
                    .tools
                    .iter()
                    .map(|t| ToolV1Ref {
                        name: &t.name,
                        leds_mm: &t.leds_mm,
                    })
                    .collect(),
            }),
            BLOB_TIPS_VERSION => postcard::to_allocvec(&RigV2Ref {
                rig_id: &self.rig_id,
                created_unix_s: self.created_unix_s,
                cameras: &self.cameras,
                world_from_cam0: &self.world_from_cam0,
                tools: &self.tools,
            }),
            BLOB_CALIBRATION_VERSION => postcard::to_allocvec(&RigV3Ref {
                rig_id: &self.rig_id,
                created_unix_s: self.created_unix_s,
                cameras: &self.cameras,
                world_from_cam0: &self.world_from_cam0,
                tools: &self.tools,
                calibration: &self.calibration,
            }),
            BLOB_PLACEMENT_VERSION => postcard::to_allocvec(&RigV4Ref {
                rig_id: &self.rig_id,
                created_unix_s: self.created_unix_s,
                cameras: &self.cameras,
                world_from_cam0: &self.world_from_cam0,
                tools: &self.tools,
                calibration: &self.calibration,
                placement: &self.placement,
            }),
            _ => postcard::to_allocvec(&RigV5Ref {
                rig_id: &self.rig_id,
                created_unix_s: self.created_unix_s,
                cameras: &self.cameras,
                world_from_cam0: &self.world_from_cam0,
                tools: &self.tools,
                calibration: &self.calibration,
                placement: &self.placement,
                // All default is written as none: one set, one byte form.
                timing: if self.has_timing() { &self.timing } else { &[] },
                serial: self.serial,
            }),
        };
        let body = encoded.map_err(|_| Error::BlobBody {
            reason: "body does not encode",
        })?;
        Ok((version, body))
    }

    /// Header + body with `flags`, reserving `extra_capacity` bytes (for a signature trailer).
    pub(crate) fn encode_blob(&self, flags: u16, extra_capacity: usize) -> Result<Vec<u8>> {
        let (version, body) = self.encode_body()?;
        let body_len = u32::try_from(body.len()).map_err(|_| Error::BlobBody {
            reason: "body longer than 4 GiB",
        })?;
        let mut out = Vec::with_capacity(BLOB_HEADER_LEN + body.len() + extra_capacity);
        out.extend_from_slice(&BLOB_MAGIC);
        out.extend_from_slice(&version.to_le_bytes());
        out.extend_from_slice(&flags.to_le_bytes());
        out.extend_from_slice(&body_len.to_le_bytes());
        let crc = blob_crc(&out[..12], &body);
        out.extend_from_slice(&crc.to_le_bytes());
        out.extend_from_slice(&body);
        Ok(out)
    }

    /// Decodes an unsigned blob, checking (in this order) magic, length, version, flags,
    /// declared body length, CRC and body. Does not validate the contents; call
    /// [`Self::validate`]. A signed blob is refused (`BlobUnsupportedFlags`): read it with
    /// [`crate::signing::verify_blob`], which checks the signature.
    pub fn from_blob(bytes: &[u8]) -> Result<RigParams> {
        let header = BlobHeader::parse(bytes)?;
        decode_body(header.version, header.check_frame(bytes)?)
    }

    /// Checks that the parameters are usable for tracking: 2..=[`MAX_CAMERAS`] cameras, camera 0 at the
    /// identity, proper rotations, finite numbers, positive focal lengths, principal points
    /// inside the images, non-empty image sizes, distinct camera centres, a printable rig id
    /// (it travels in one-line protocol replies), sane tool definitions, a placement and a
    /// timing list that are empty or name every camera, and timing each camera could have.
    pub fn validate(&self) -> Result<()> {
        if self.rig_id.is_empty() || self.rig_id.len() > MAX_RIG_ID_LEN {
            return Err(invalid(format!(
                "rig id must be 1..={MAX_RIG_ID_LEN} bytes, got {}",
                self.rig_id.len()
            )));
        }
        if !self.rig_id.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(invalid(format!(
                "rig id {:?} must be printable ASCII without spaces",
                self.rig_id
            )));
        }
        let n = self.cameras.len();
        if !(2..=MAX_CAMERAS).contains(&n) {
            return Err(invalid(format!("rig needs 2..={MAX_CAMERAS} cameras, has {n}")));
        }
        for (i, cam) in self.cameras.iter().enumerate() {
            check_camera(i, &cam.model)?;
            check_transform(&format!("camera {i} pose"), &cam.cam_from_cam0)?;
        }
        let cam0 = &self.cameras[0].cam_from_cam0;
        let id = RigidTransform::IDENTITY;
        let off = cam0
            .r_row_major
            .iter()
            .chain(cam0.t_mm.iter())
            .zip(id.r_row_major.iter().chain(id.t_mm.iter()))
            .any(|(a, b)| (a - b).abs() > 1e-9);
        if off {
            return Err(invalid(
                "camera 0 pose must be the identity (it is the reference frame)".into(),
            ));
        }
        for i in 0..n {
            for j in (i + 1)..n {
                let d = (self.camera_centre_cam0_mm(i)? - self.camera_centre_cam0_mm(j)?).norm();
                if d < 1e-3 {
                    return Err(invalid(format!(
                        "cameras {i} and {j} have the same centre (distance {d:e} mm); no baseline"
                    )));
                }
            }
        }
        if let Some(w) = &self.world_from_cam0 {
            check_transform("registration world_from_cam0", w)?;
        }
        for (ti, tool) in self.tools.iter().enumerate() {
            if tool.name.is_empty() {
                return Err(invalid(format!("tool {ti} has an empty name")));
            }
            // Printable ASCII without quote and backslash: the name goes verbatim into the
            // stream's per-tool records (NDJSON string, fixed binary field).
            if tool.name.len() > MAX_TOOL_NAME_LEN
                || !tool
                    .name
                    .bytes()
                    .all(|b| (0x20..0x7f).contains(&b) && b != b'"' && b != b'\\')
            {
                return Err(invalid(format!(
                    "tool name {:?} must be 1..={MAX_TOOL_NAME_LEN} printable ASCII characters without \" or \\",
                    tool.name
                )));
            }
            if self.tools[..ti].iter().any(|t| t.name == tool.name) {
                return Err(invalid(format!("tool name {:?} used twice", tool.name)));
            }
            if tool.leds_mm.len() < 3 {
                return Err(invalid(format!(
                    "tool {:?} has {} LEDs; 6-DOF needs at least 3",
                    tool.name,
                    tool.leds_mm.len()
                )));
            }
            if !tool.leds_mm.iter().flatten().all(|v| v.is_finite()) {
                return Err(invalid(format!(
                    "tool {:?} has non-finite LED positions",
                    tool.name
                )));
            }
            if tool.tip_mm.is_some_and(|t| !t.iter().all(|v| v.is_finite())) {
                return Err(invalid(format!("tool {:?} has a non-finite tip", tool.name)));
            }
        }
        if let Some(c) = &self.calibration {
            check_calibration(c, n)?;
        }
        check_placement(&self.placement, n)?;
        check_timing(&self.timing, n)
    }

    /// Number of cameras.
    pub fn camera_count(&self) -> usize {
        self.cameras.len()
    }

    /// Camera `index`, or [`Error::NoSuchCamera`].
    pub fn camera(&self, index: usize) -> Result<&CameraParams> {
        self.cameras.get(index).ok_or(Error::NoSuchCamera {
            index,
            count: self.cameras.len(),
        })
    }

    /// The model (intrinsics, distortion, image size) of camera `index`.
    pub fn camera_model(&self, index: usize) -> Result<&CameraModel> {
        Ok(&self.camera(index)?.model)
    }

    /// Pose of camera `index` relative to camera 0 (`x_cam = R x_cam0 + t`).
    pub fn cam_from_cam0(&self, index: usize) -> Result<&RigidTransform> {
        Ok(&self.camera(index)?.cam_from_cam0)
    }

    /// Optical centre of camera `index` in camera-0 coordinates (`-Rᵀ t`), mm.
    pub fn camera_centre_cam0_mm(&self, index: usize) -> Result<Vector3<f64>> {
        let t = self.cam_from_cam0(index)?;
        Ok(-(t.rotation().transpose() * t.translation_mm()))
    }

    /// Distance between the optical centres of camera 0 and camera `index`, mm.
    pub fn baseline_mm(&self, index: usize) -> Result<f64> {
        Ok(self.camera_centre_cam0_mm(index)?.norm())
    }

    /// Angle between the optical axes (z) of camera 0 and camera `index`, degrees
    /// (0 for a parallel rig, 90 for the orthogonal one).
    pub fn optical_axis_angle_deg(&self, index: usize) -> Result<f64> {
        // Camera i's z axis in cam0 coordinates is Rᵀ e_z, whose z component is R[2][2].
        let r22 = self.cam_from_cam0(index)?.r_row_major[8];
        Ok(libm::acos(r22.clamp(-1.0, 1.0)).to_degrees())
    }

    /// Whether this set is older than `active` (the rollback rule, docs/param-protocol.md): by
    /// serial when both sets have one, else by creation time. A set as new as the active one
    /// (the same set pushed again) is not older.
    pub fn is_older_than(&self, active: &RigParams) -> bool {
        if self.serial != 0 && active.serial != 0 {
            self.serial < active.serial
        } else {
            self.created_unix_s < active.created_unix_s
        }
    }

    /// The set's id, serial and creation date in words, e.g.
    /// `cell-v2 (serial 1790000000, created 2026-09-21 14:13 UTC)`: how rollback messages
    /// name a set.
    pub fn age_label(&self) -> String {
        let serial = if self.serial == 0 {
            String::from("no serial")
        } else {
            format!("serial {}", self.serial)
        };
        format!(
            "{} ({serial}, created {})",
            self.rig_id,
            utc_minute(self.created_unix_s)
        )
    }

    /// The CRC-32 of this parameter set's unsigned blob: a short id for logs and stream
    /// records. The same set pushed signed has another header CRC (its flags differ); this id
    /// does not depend on signing.
    pub fn params_crc(&self) -> Result<u32> {
        let blob = self.to_blob()?;
        Ok(BlobHeader::parse(&blob)?.crc32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Distortion, ImageSize, Intrinsics};
    use alloc::vec;
    use nalgebra::Matrix3;

    fn cam(t_mm: [f64; 3], r_row_major: [f64; 9]) -> CameraParams {
        CameraParams {
            model: CameraModel {
                intrinsics: Intrinsics {
                    fx_px: 800.0,
                    fy_px: 801.0,
                    cx_px: 640.0,
                    cy_px: 360.0,
                },
                distortion: Distortion {
                    k1: -0.1,
                    k2: 0.02,
                    p1: 0.0,
                    p2: 0.0,
                    k3: 0.0,
                },
                image_size: ImageSize {
                    width_px: 1280,
                    height_px: 720,
                },
            },
            cam_from_cam0: RigidTransform { r_row_major, t_mm },
        }
    }

    /// The paper's orthogonal (90° convergent) rig.
    fn orthogonal_rig() -> RigParams {
        // x1 = R x0 + t with R a +90° rotation about y; camera 1 sits at (500, 0, 500) in cam0.
        let r = [0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0];
        let c1 = Vector3::new(500.0, 0.0, 500.0);
        let t = -(Matrix3::from_row_slice(&r) * c1);
        RigParams {
            rig_id: "ortho-1".into(),
            created_unix_s: 1,
            cameras: vec![
                cam([0.0; 3], RigidTransform::IDENTITY.r_row_major),
                cam([t.x, t.y, t.z], r),
            ],
            world_from_cam0: None,
            tools: vec![],
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }

    fn reason(rig: &RigParams) -> String {
        match rig.validate() {
            Err(Error::InvalidParams { reason }) => reason,
            other => panic!("expected InvalidParams, got {other:?}"),
        }
    }

    #[test]
    fn utc_minutes() {
        assert_eq!(utc_minute(0), "1970-01-01 00:00 UTC");
        assert_eq!(utc_minute(1_700_000_000), "2023-11-14 22:13 UTC");
        assert_eq!(utc_minute(951_782_400), "2000-02-29 00:00 UTC");
        assert_eq!(utc_minute(4_107_542_400), "2100-03-01 00:00 UTC");
        assert_eq!(utc_minute(253_402_300_799), "9999-12-31 23:59 UTC");
        assert!(utc_minute(u64::MAX).contains("s after 1970"));
    }

    #[test]
    fn older_sets_by_serial_else_creation_time() {
        let v2 = RigParams {
            rig_id: "cell-v2".into(),
            created_unix_s: 1_790_000_000,
            ..orthogonal_rig()
        };
        let v1 = RigParams {
            rig_id: "cell-v1".into(),
            created_unix_s: 1_700_000_000,
            ..orthogonal_rig()
        };
        assert!(v1.is_older_than(&v2));
        assert!(!v2.is_older_than(&v1));
        assert!(!v2.is_older_than(&v2), "the same set again is not a rollback");
        // Serials decide when both have one, whatever the creation times say.
        let v1s = RigParams {
            serial: 20,
            ..v1.clone()
        };
        let v2s = RigParams {
            serial: 19,
            ..v2.clone()
        };
        assert!(v2s.is_older_than(&v1s));
        assert!(!v1s.is_older_than(&v2s));
        // One without a serial: creation times.
        assert!(v1s.is_older_than(&v2));
        assert_eq!(
            v1s.age_label(),
            "cell-v1 (serial 20, created 2023-11-14 22:13 UTC)"
        );
        assert!(v2.age_label().contains("no serial"));
    }

    #[test]
    fn geometry_helpers() {
        let rig = orthogonal_rig();
        rig.validate().unwrap();
        let c1 = rig.camera_centre_cam0_mm(1).unwrap();
        assert!((c1 - Vector3::new(500.0, 0.0, 500.0)).norm() < 1e-9);
        assert!((rig.baseline_mm(1).unwrap() - 500.0 * 2f64.sqrt()).abs() < 1e-9);
        assert!((rig.optical_axis_angle_deg(1).unwrap() - 90.0).abs() < 1e-9);
        assert_eq!(
            rig.camera_model(2),
            Err(Error::NoSuchCamera { index: 2, count: 2 })
        );
        assert_eq!(rig.camera_count(), 2);
    }

    #[test]
    fn validate_rejects_each_problem() {
        let mut r = orthogonal_rig();
        r.cameras.truncate(1);
        assert!(reason(&r).contains(&format!("2..={MAX_CAMERAS} cameras")));

        let mut r = orthogonal_rig();
        r.cameras[0].cam_from_cam0.t_mm[0] = 1.0;
        assert!(reason(&r).contains("camera 0 pose must be the identity"));

        let mut r = orthogonal_rig();
        r.cameras[1].cam_from_cam0.r_row_major[0] = 0.5;
        assert!(reason(&r).contains("camera 1 pose: rotation is not a proper rotation"));

        let mut r = orthogonal_rig();
        // A reflection (det -1) is orthonormal but not a rotation.
        r.cameras[1].cam_from_cam0.r_row_major = [-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        assert!(reason(&r).contains("not a proper rotation"));

        let mut r = orthogonal_rig();
        r.cameras[1].cam_from_cam0.t_mm[2] = f64::NAN;
        assert!(reason(&r).contains("non-finite"));

        let mut r = orthogonal_rig();
        r.cameras[1].model.intrinsics.fx_px = 0.0;
        assert!(reason(&r).contains("camera 1: focal length"));

        let mut r = orthogonal_rig();
        r.cameras[0].model.intrinsics.cy_px = 720.0;
        assert!(reason(&r).contains("camera 0: principal point"));

        let mut r = orthogonal_rig();
        r.cameras[1].model.image_size.height_px = 0;
        assert!(reason(&r).contains("is empty"));

        let mut r = orthogonal_rig();
        r.cameras[1].model.distortion.k3 = f64::INFINITY;
        assert!(reason(&r).contains("distortion"));

        let mut r = orthogonal_rig();
        r.cameras[1].cam_from_cam0 = RigidTransform::IDENTITY;
        assert!(reason(&r).contains("same centre"));

        let mut r = orthogonal_rig();
        r.rig_id = "two words".into();
        assert!(reason(&r).contains("printable ASCII"));
        r.rig_id.clear();
        assert!(reason(&r).contains("rig id"));

        let mut r = orthogonal_rig();
        r.world_from_cam0 = Some(RigidTransform {
            r_row_major: [0.0; 9],
            t_mm: [0.0; 3],
        });
        assert!(reason(&r).contains("registration"));

        let mut r = orthogonal_rig();
        r.tools = vec![ToolDefinition {
            name: "probe".into(),
            leds_mm: vec![[0.0; 3]; 2],
            tip_mm: None,
        }];
        assert!(reason(&r).contains("at least 3"));
        r.tools[0].leds_mm.push([1.0, 2.0, 3.0]);
        r.validate().unwrap();
        r.tools[0].tip_mm = Some([0.0, f64::NAN, 150.0]);
        assert!(reason(&r).contains("non-finite tip"));
        r.tools[0].tip_mm = Some([0.0, 0.0, 150.0]);
        r.validate().unwrap();
        r.tools.push(r.tools[0].clone());
        assert!(reason(&r).contains("used twice"));
    }
}
