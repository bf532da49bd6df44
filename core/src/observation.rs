//! Camera observations: what a camera board sends the solver for one frame of one camera
//! (spec: docs/observation-protocol.md). A compact, versioned little-endian message with a
//! CRC-32 trailer; the transport (Zenoh, `irtrack-cluster`) carries it as an opaque payload.
//!
//! Encoding writes into a caller-owned buffer and decoding borrows the received bytes, so
//! neither side allocates per frame. [`ObservationGate`] adds the checks that need the rig's
//! layout and history: unknown rig or camera, a sequence seen before, a timestamp far from the
//! receiver's clock.

use core::fmt;

use crate::blob::Blob;
use crate::crc::Crc32;
use crate::params::MAX_CAMERAS;
use crate::{Error, Result};

/// First bytes of every observation.
pub const OBS_MAGIC: [u8; 2] = *b"IO";
/// The one version this build writes and reads.
pub const OBS_VERSION: u8 = 1;
/// Fixed part before the optional trigger counter and the ids.
pub const OBS_FIXED_LEN: usize = 36;
/// Bytes of one blob record.
pub const OBS_BLOB_LEN: usize = 16;
/// CRC-32 trailer.
pub const OBS_CRC_LEN: usize = 4;
/// Most blobs one observation carries (the board sends its best ones, largest first).
pub const MAX_OBS_BLOBS: usize = 32;
/// Longest rig or board id, bytes.
pub const MAX_OBS_ID_LEN: usize = 32;
/// Largest observation: fixed part, trigger counter, two ids, count byte, blobs, CRC.
pub const MAX_OBS_LEN: usize =
    OBS_FIXED_LEN + 8 + 2 * MAX_OBS_ID_LEN + 1 + MAX_OBS_BLOBS * OBS_BLOB_LEN + OBS_CRC_LEN;

const FLAG_TRIGGER: u8 = 0x01;
const KNOWN_FLAGS: u8 = FLAG_TRIGGER;
const BLOB_EDGE: u8 = 0x01;
const BLOB_ROI_EDGE: u8 = 0x02;
const BLOB_SATURATED: u8 = 0x04;
const KNOWN_BLOB_FLAGS: u8 = BLOB_EDGE | BLOB_ROI_EDGE | BLOB_SATURATED;

/// The clock a capture timestamp is read on. Pairing across boards needs a clock the boards
/// share (`Realtime` or `Tai`, disciplined by PTP or chrony; docs/cluster.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum ObsClock {
    /// CLOCK_REALTIME (UTC, ns since the Unix epoch), synchronised between boards.
    Realtime,
    /// CLOCK_TAI, synchronised between boards (PTP's own time scale).
    Tai,
    /// CLOCK_MONOTONIC of the sending board: comparable only with itself.
    Monotonic,
}

impl ObsClock {
    /// The clock's code on the wire.
    pub fn as_u8(self) -> u8 {
        match self {
            ObsClock::Realtime => 1,
            ObsClock::Tai => 2,
            ObsClock::Monotonic => 3,
        }
    }

    /// The clock of a wire code; `None` for a code this build does not know.
    pub fn from_u8(code: u8) -> Option<ObsClock> {
        match code {
            1 => Some(ObsClock::Realtime),
            2 => Some(ObsClock::Tai),
            3 => Some(ObsClock::Monotonic),
            _ => None,
        }
    }

    /// Lower-case name (config values, status reports).
    pub fn as_str(self) -> &'static str {
        match self {
            ObsClock::Realtime => "realtime",
            ObsClock::Tai => "tai",
            ObsClock::Monotonic => "monotonic",
        }
    }
}

/// Why an observation was refused. `Copy` and without strings, so that counting it allocates
/// nothing; [`ObservationProblem::code`] names it in status reports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ObservationProblem {
    /// Fewer bytes than the header or the declared contents need.
    Truncated {
        /// Bytes needed.
        needed: usize,
        /// Bytes there are.
        got: usize,
    },
    /// Not an observation.
    BadMagic {
        /// The first two bytes received.
        found: [u8; 2],
    },
    /// A version this build does not read.
    UnsupportedVersion {
        /// The message's version.
        found: u8,
        /// The newest version this build reads.
        supported: u8,
    },
    /// Header flags this build does not know.
    UnknownFlags {
        /// The header's flags.
        flags: u8,
    },
    /// Clock code this build does not know.
    UnknownClock {
        /// The clock code received.
        code: u8,
    },
    /// Rig or board id empty, too long or not UTF-8.
    BadId {
        /// Which id (`rig` or `board`).
        what: &'static str,
        /// Its length in bytes.
        len: usize,
    },
    /// More blobs than [`MAX_OBS_BLOBS`].
    TooManyBlobs {
        /// Blobs in the message.
        count: usize,
        /// The most a message may carry.
        max: usize,
    },
    /// A blob with a non-finite centroid, unknown flags or a nonzero reserved byte.
    BadBlob {
        /// Position of the blob in the message.
        index: usize,
    },
    /// CRC mismatch: corrupted on the way.
    BadCrc {
        /// The CRC in the message.
        found: u32,
        /// The CRC computed over the received bytes.
        computed: u32,
    },
    /// Bytes after the CRC.
    TrailingBytes {
        /// How many bytes follow the CRC.
        extra: usize,
    },
    /// The buffer given to the encoder is too small.
    BufferTooSmall {
        /// Bytes the message needs.
        needed: usize,
        /// Bytes the buffer has.
        have: usize,
    },
    /// From another rig than the receiver's.
    UnknownRig,
    /// A board/camera pair the rig's parameters do not list.
    UnknownCamera {
        /// The camera's index on its board.
        local_index: u8,
    },
    /// The sequence number is not newer than the last one of that camera.
    DuplicateSequence {
        /// The rig's camera index.
        camera: usize,
        /// The sequence number received.
        sequence: u64,
        /// The newest sequence number seen of that camera.
        last: u64,
    },
    /// A different clock than the receiver pairs on.
    WrongClock {
        /// The message's clock.
        found: ObsClock,
        /// The clock the receiver pairs on.
        expected: ObsClock,
    },
    /// The timestamp is further from the receiver's clock than allowed.
    TimestampOff {
        /// The rig's camera index.
        camera: usize,
        /// Capture time minus the receiver's clock, ns.
        offset_ns: i64,
        /// The largest distance allowed, ns.
        limit_ns: u64,
    },
}

impl ObservationProblem {
    /// Every code [`Self::code`] returns, for counters indexed by [`Self::index`].
    pub const CODES: [&'static str; 16] = [
        "truncated",
        "bad_magic",
        "unsupported_version",
        "unknown_flags",
        "unknown_clock",
        "bad_id",
        "too_many_blobs",
        "bad_blob",
        "bad_crc",
        "trailing_bytes",
        "buffer_too_small",
        "unknown_rig",
        "unknown_camera",
        "duplicate_sequence",
        "wrong_clock",
        "timestamp_off",
    ];

    /// Position of [`Self::code`] in [`Self::CODES`].
    pub fn index(&self) -> usize {
        match self {
            ObservationProblem::Truncated { .. } => 0,
            ObservationProblem::BadMagic { .. } => 1,
            ObservationProblem::UnsupportedVersion { .. } => 2,
            ObservationProblem::UnknownFlags { .. } => 3,
            ObservationProblem::UnknownClock { .. } => 4,
            ObservationProblem::BadId { .. } => 5,
            ObservationProblem::TooManyBlobs { .. } => 6,
            ObservationProblem::BadBlob { .. } => 7,
            ObservationProblem::BadCrc { .. } => 8,
            ObservationProblem::TrailingBytes { .. } => 9,
            ObservationProblem::BufferTooSmall { .. } => 10,
            ObservationProblem::UnknownRig => 11,
            ObservationProblem::UnknownCamera { .. } => 12,
            ObservationProblem::DuplicateSequence { .. } => 13,
            ObservationProblem::WrongClock { .. } => 14,
            ObservationProblem::TimestampOff { .. } => 15,
        }
    }

    /// Short snake_case name (status counters, logs).
    pub fn code(&self) -> &'static str {
        Self::CODES[self.index()]
    }
}

impl fmt::Display for ObservationProblem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ObservationProblem::Truncated { needed, got } => {
                write!(f, "truncated: need {needed} bytes, got {got}")
            }
            ObservationProblem::BadMagic { found } => {
                write!(f, "not an observation (magic {found:02x?})")
            }
            ObservationProblem::UnsupportedVersion { found, supported } => write!(
                f,
                "version {found} unsupported (this build reads version {supported})"
            ),
            ObservationProblem::UnknownFlags { flags } => write!(f, "unknown header flags {flags:#04x}"),
            ObservationProblem::UnknownClock { code } => write!(f, "unknown clock code {code}"),
            ObservationProblem::BadId { what, len } => write!(
                f,
                "{what} id of {len} bytes is empty, longer than {MAX_OBS_ID_LEN} or not UTF-8"
            ),
            ObservationProblem::TooManyBlobs { count, max } => {
                write!(f, "{count} blobs, at most {max} allowed")
            }
            ObservationProblem::BadBlob { index } => write!(
                f,
                "blob {index} has a non-finite centroid, unknown flags or a nonzero reserved byte"
            ),
            ObservationProblem::BadCrc { found, computed } => {
                write!(f, "corrupted: CRC-32 {found:08x}, computed {computed:08x}")
            }
            ObservationProblem::TrailingBytes { extra } => {
                write!(f, "{extra} trailing bytes after the CRC")
            }
            ObservationProblem::BufferTooSmall { needed, have } => {
                write!(f, "encode buffer too small: need {needed} bytes, have {have}")
            }
            ObservationProblem::UnknownRig => write!(f, "from another rig"),
            ObservationProblem::UnknownCamera { local_index } => write!(
                f,
                "camera {local_index} of its board is not in the rig's parameters"
            ),
            ObservationProblem::DuplicateSequence {
                camera,
                sequence,
                last,
            } => write!(
                f,
                "camera {camera}: sequence {sequence} is not newer than the last one ({last})"
            ),
            ObservationProblem::WrongClock { found, expected } => write!(
                f,
                "timestamp on the {} clock, the solver pairs on {}",
                found.as_str(),
                expected.as_str()
            ),
            ObservationProblem::TimestampOff {
                camera,
                offset_ns,
                limit_ns,
            } => write!(
                f,
                "camera {camera}: timestamp {:.3} ms from the solver's clock (limit {:.3} ms)",
                *offset_ns as f64 / 1e6,
                *limit_ns as f64 / 1e6
            ),
        }
    }
}

fn err(problem: ObservationProblem) -> Error {
    Error::Observation { problem }
}

/// One blob as sent: the distorted centroid and what the solver's quality gate needs.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ObsBlob {
    /// Intensity-weighted centroid in the distorted image, px (pixel centres at integers).
    pub x_px: f32,
    /// Centroid row, px (see `x_px`).
    pub y_px: f32,
    /// Pixels above threshold (saturates at 65 535).
    pub area_px: u16,
    /// Brightest pixel value, DN (saturates at 65 535).
    pub peak_dn: u16,
    /// Quality: `sigma_minor / sigma_major` in [0, 1], sent in 1/65 535 steps.
    pub roundness: f32,
    /// The blob touches the frame's border (its centroid may be cut off).
    pub touches_frame_edge: bool,
    /// The blob touches the border of the region the detector searched.
    pub touches_roi_edge: bool,
    /// Some pixels reached the saturation level.
    pub saturated: bool,
}

impl ObsBlob {
    /// The wire fields of a detected blob. The centroid is rounded to `f32` (about 6e-5 px
    /// at VGA size, far below centroid noise).
    pub fn from_blob(b: &Blob) -> ObsBlob {
        ObsBlob {
            x_px: b.x_px as f32,
            y_px: b.y_px as f32,
            area_px: b.area_px.min(u32::from(u16::MAX)) as u16,
            peak_dn: b.peak_dn.min(u32::from(u16::MAX)) as u16,
            roundness: quantize_roundness(b.roundness),
            touches_frame_edge: b.touches_frame_edge,
            touches_roi_edge: b.touches_roi_edge,
            saturated: b.saturated_px > 0,
        }
    }

    /// A [`Blob`] for the solver's tracker: the fields the wire carries, the rest zero.
    pub fn to_blob(&self) -> Blob {
        Blob {
            x_px: f64::from(self.x_px),
            y_px: f64::from(self.y_px),
            area_px: u32::from(self.area_px),
            peak_dn: u32::from(self.peak_dn),
            saturated_px: u32::from(self.saturated),
            roundness: f64::from(self.roundness),
            sigma_major_px: 1.0,
            sigma_minor_px: f64::from(self.roundness),
            touches_frame_edge: self.touches_frame_edge,
            touches_roi_edge: self.touches_roi_edge,
            ..Blob::default()
        }
    }

    fn write(&self, out: &mut [u8]) {
        out[0..4].copy_from_slice(&self.x_px.to_le_bytes());
        out[4..8].copy_from_slice(&self.y_px.to_le_bytes());
        out[8..10].copy_from_slice(&self.area_px.to_le_bytes());
        out[10..12].copy_from_slice(&self.peak_dn.to_le_bytes());
        out[12..14].copy_from_slice(&roundness_q(self.roundness).to_le_bytes());
        let mut flags = 0;
        if self.touches_frame_edge {
            flags |= BLOB_EDGE;
        }
        if self.touches_roi_edge {
            flags |= BLOB_ROI_EDGE;
        }
        if self.saturated {
            flags |= BLOB_SATURATED;
        }
        out[14] = flags;
        out[15] = 0;
    }

    fn read(b: &[u8], index: usize) -> Result<ObsBlob> {
        let x_px = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let y_px = f32::from_le_bytes([b[4], b[5], b[6], b[7]]);
        let flags = b[14];
        if !x_px.is_finite() || !y_px.is_finite() || flags & !KNOWN_BLOB_FLAGS != 0 || b[15] != 0 {
            return Err(err(ObservationProblem::BadBlob { index }));
        }
        Ok(ObsBlob {
            x_px,
            y_px,
            area_px: u16::from_le_bytes([b[8], b[9]]),
            peak_dn: u16::from_le_bytes([b[10], b[11]]),
            roundness: f32::from(u16::from_le_bytes([b[12], b[13]])) / 65_535.0,
            touches_frame_edge: flags & BLOB_EDGE != 0,
            touches_roi_edge: flags & BLOB_ROI_EDGE != 0,
            saturated: flags & BLOB_SATURATED != 0,
        })
    }
}

fn roundness_q(r: f32) -> u16 {
    if r.is_nan() {
        return 0;
    }
    (r.clamp(0.0, 1.0) * 65_535.0 + 0.5) as u16
}

fn quantize_roundness(r: f64) -> f32 {
    f32::from(roundness_q(r as f32)) / 65_535.0
}

/// The header fields of an observation (everything but the blobs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ObsHeader<'a> {
    /// The rig (parameter set's rig id) this board belongs to.
    pub rig: &'a str,
    /// The sending board's name.
    pub board: &'a str,
    /// The camera's index on its board.
    pub camera: u8,
    /// The camera's frame counter on its board (increasing; gaps are drops).
    pub sequence: u64,
    /// Hardware trigger's frame counter, when the cameras are triggered.
    pub trigger_count: Option<u64>,
    /// Start of exposure, ns on `clock`.
    pub capture_ts_ns: u64,
    /// The clock `capture_ts_ns` is read on.
    pub clock: ObsClock,
    /// Exposure time, µs.
    pub exposure_us: u32,
    /// Frames of this camera dropped on the board since it started.
    pub dropped: u32,
    /// Capture to sending, µs (the board's processing time). The receiver subtracts it to
    /// estimate the sender's clock offset: `receive − capture − send_delay` is the one-way
    /// transit plus the clock offset.
    pub send_delay_us: u32,
}

/// A decoded observation borrowing the received bytes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation<'a> {
    /// Everything but the blobs.
    pub header: ObsHeader<'a>,
    blob_bytes: &'a [u8],
}

impl<'a> Observation<'a> {
    /// Number of blobs carried.
    pub fn blob_count(&self) -> usize {
        self.blob_bytes.len() / OBS_BLOB_LEN
    }

    /// The blobs, in the sender's order (validated by [`decode`]).
    pub fn blobs(&self) -> impl Iterator<Item = ObsBlob> + 'a {
        self.blob_bytes
            .chunks_exact(OBS_BLOB_LEN)
            .enumerate()
            .filter_map(|(i, c)| ObsBlob::read(c, i).ok())
    }
}

fn check_id(what: &'static str, id: &str) -> Result<()> {
    if id.is_empty() || id.len() > MAX_OBS_ID_LEN {
        return Err(err(ObservationProblem::BadId { what, len: id.len() }));
    }
    Ok(())
}

/// Size of the encoded observation.
pub fn encoded_len(header: &ObsHeader<'_>, blob_count: usize) -> usize {
    OBS_FIXED_LEN
        + if header.trigger_count.is_some() { 8 } else { 0 }
        + header.rig.len()
        + header.board.len()
        + 1
        + blob_count * OBS_BLOB_LEN
        + OBS_CRC_LEN
}

/// Writes one observation into `out`; returns its length. Errors: an empty or too long id,
/// more than [`MAX_OBS_BLOBS`] blobs, `out` too small.
pub fn encode(header: &ObsHeader<'_>, blobs: &[ObsBlob], out: &mut [u8]) -> Result<usize> {
    check_id("rig", header.rig)?;
    check_id("board", header.board)?;
    if blobs.len() > MAX_OBS_BLOBS {
        return Err(err(ObservationProblem::TooManyBlobs {
            count: blobs.len(),
            max: MAX_OBS_BLOBS,
        }));
    }
    let len = encoded_len(header, blobs.len());
    if out.len() < len {
        return Err(err(ObservationProblem::BufferTooSmall {
            needed: len,
            have: out.len(),
        }));
    }
    out[0..2].copy_from_slice(&OBS_MAGIC);
    out[2] = OBS_VERSION;
    out[3] = if header.trigger_count.is_some() {
        FLAG_TRIGGER
    } else {
        0
    };
    out[4] = header.clock.as_u8();
    out[5] = header.camera;
    out[6] = header.rig.len() as u8;
    out[7] = header.board.len() as u8;
    out[8..16].copy_from_slice(&header.sequence.to_le_bytes());
    out[16..24].copy_from_slice(&header.capture_ts_ns.to_le_bytes());
    out[24..28].copy_from_slice(&header.exposure_us.to_le_bytes());
    out[28..32].copy_from_slice(&header.dropped.to_le_bytes());
    out[32..36].copy_from_slice(&header.send_delay_us.to_le_bytes());
    let mut at = OBS_FIXED_LEN;
    if let Some(t) = header.trigger_count {
        out[at..at + 8].copy_from_slice(&t.to_le_bytes());
        at += 8;
    }
    for id in [header.rig, header.board] {
        out[at..at + id.len()].copy_from_slice(id.as_bytes());
        at += id.len();
    }
    out[at] = blobs.len() as u8;
    at += 1;
    for b in blobs {
        b.write(&mut out[at..at + OBS_BLOB_LEN]);
        at += OBS_BLOB_LEN;
    }
    let crc = crc_of(&out[..at]);
    out[at..at + OBS_CRC_LEN].copy_from_slice(&crc.to_le_bytes());
    Ok(at + OBS_CRC_LEN)
}

fn crc_of(bytes: &[u8]) -> u32 {
    let mut c = Crc32::new();
    c.update(bytes);
    c.finish()
}

fn need(bytes: &[u8], needed: usize) -> Result<()> {
    if bytes.len() < needed {
        return Err(err(ObservationProblem::Truncated {
            needed,
            got: bytes.len(),
        }));
    }
    Ok(())
}

fn id_at<'a>(bytes: &'a [u8], what: &'static str) -> Result<&'a str> {
    if bytes.is_empty() || bytes.len() > MAX_OBS_ID_LEN {
        return Err(err(ObservationProblem::BadId {
            what,
            len: bytes.len(),
        }));
    }
    core::str::from_utf8(bytes).map_err(|_| {
        err(ObservationProblem::BadId {
            what,
            len: bytes.len(),
        })
    })
}

/// Decodes one observation, checking in this order: magic, version, length, flags, clock,
/// CRC, trailing bytes, ids, blob count, blobs. Never panics on any input.
pub fn decode(bytes: &[u8]) -> Result<Observation<'_>> {
    need(bytes, 3)?;
    if bytes[0..2] != OBS_MAGIC {
        return Err(err(ObservationProblem::BadMagic {
            found: [bytes[0], bytes[1]],
        }));
    }
    if bytes[2] != OBS_VERSION {
        return Err(err(ObservationProblem::UnsupportedVersion {
            found: bytes[2],
            supported: OBS_VERSION,
        }));
    }
    need(bytes, OBS_FIXED_LEN)?;
    let flags = bytes[3];
    if flags & !KNOWN_FLAGS != 0 {
        return Err(err(ObservationProblem::UnknownFlags { flags }));
    }
    let clock =
        ObsClock::from_u8(bytes[4]).ok_or(err(ObservationProblem::UnknownClock { code: bytes[4] }))?;
    let (rig_len, board_len) = (usize::from(bytes[6]), usize::from(bytes[7]));
    let trigger_len = if flags & FLAG_TRIGGER != 0 { 8 } else { 0 };
    let count_at = OBS_FIXED_LEN + trigger_len + rig_len + board_len;
    need(bytes, count_at + 1)?;
    let count = usize::from(bytes[count_at]);
    let end = count_at + 1 + count * OBS_BLOB_LEN;
    need(bytes, end + OBS_CRC_LEN)?;
    let found = u32::from_le_bytes([bytes[end], bytes[end + 1], bytes[end + 2], bytes[end + 3]]);
    let computed = crc_of(&bytes[..end]);
    if found != computed {
        return Err(err(ObservationProblem::BadCrc { found, computed }));
    }
    if bytes.len() > end + OBS_CRC_LEN {
        return Err(err(ObservationProblem::TrailingBytes {
            extra: bytes.len() - end - OBS_CRC_LEN,
        }));
    }
    let u64_at = |at: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[at..at + 8]);
        u64::from_le_bytes(b)
    };
    let u32_at = |at: usize| u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]]);
    let ids_at = OBS_FIXED_LEN + trigger_len;
    let rig = id_at(&bytes[ids_at..ids_at + rig_len], "rig")?;
    let board = id_at(&bytes[ids_at + rig_len..count_at], "board")?;
    if count > MAX_OBS_BLOBS {
        return Err(err(ObservationProblem::TooManyBlobs {
            count,
            max: MAX_OBS_BLOBS,
        }));
    }
    let blob_bytes = &bytes[count_at + 1..end];
    for (i, c) in blob_bytes.chunks_exact(OBS_BLOB_LEN).enumerate() {
        ObsBlob::read(c, i)?;
    }
    Ok(Observation {
        header: ObsHeader {
            rig,
            board,
            camera: bytes[5],
            sequence: u64_at(8),
            trigger_count: (trigger_len > 0).then(|| u64_at(OBS_FIXED_LEN)),
            capture_ts_ns: u64_at(16),
            clock,
            exposure_us: u32_at(24),
            dropped: u32_at(28),
            send_delay_us: u32_at(32),
        },
        blob_bytes,
    })
}

pub use crate::params::CameraPlace;

/// The solver's checks of decoded observations against the rig's layout and history:
/// maps (board, local index) to the rig's camera index and refuses another rig, an unknown
/// camera, a sequence not newer than the last, a different clock and a timestamp further
/// than `max_offset_ns` from the receiver's clock. Allocates only in [`Self::new`].
#[derive(Debug, Clone)]
pub struct ObservationGate {
    rig: alloc::string::String,
    places: alloc::vec::Vec<CameraPlace>,
    clock: ObsClock,
    max_offset_ns: u64,
    last_sequence: [Option<u64>; MAX_CAMERAS],
}

impl ObservationGate {
    /// `places[i]` is where the rig's camera `i` is (at most [`MAX_CAMERAS`]).
    pub fn new(
        rig: &str,
        places: &[CameraPlace],
        clock: ObsClock,
        max_offset_ns: u64,
    ) -> Result<ObservationGate> {
        if places.len() > MAX_CAMERAS {
            return Err(Error::NoSuchCamera {
                index: places.len() - 1,
                count: MAX_CAMERAS,
            });
        }
        Ok(ObservationGate {
            rig: rig.into(),
            places: places.to_vec(),
            clock,
            max_offset_ns,
            last_sequence: [None; MAX_CAMERAS],
        })
    }

    /// The rig's camera index of (board, local index), if listed.
    pub fn camera_of(&self, board: &str, local_index: u8) -> Option<usize> {
        self.places
            .iter()
            .position(|p| p.board == board && p.local_index == local_index)
    }

    /// Cameras the rig lists.
    pub fn camera_count(&self) -> usize {
        self.places.len()
    }

    /// Forgets the last sequence of `camera` (its board restarted and counts from 0 again).
    pub fn reset_camera(&mut self, camera: usize) {
        if let Some(s) = self.last_sequence.get_mut(camera) {
            *s = None;
        }
    }

    /// Checks `obs` received at `now_ns` (on the gate's clock); returns the rig's camera
    /// index. A sequence is remembered only when every check passed.
    pub fn check(&mut self, obs: &Observation<'_>, now_ns: u64) -> Result<usize> {
        let h = &obs.header;
        if h.rig != self.rig {
            return Err(err(ObservationProblem::UnknownRig));
        }
        let camera = self
            .camera_of(h.board, h.camera)
            .ok_or(err(ObservationProblem::UnknownCamera {
                local_index: h.camera,
            }))?;
        if h.clock != self.clock {
            return Err(err(ObservationProblem::WrongClock {
                found: h.clock,
                expected: self.clock,
            }));
        }
        let offset_ns = (i128::from(h.capture_ts_ns) - i128::from(now_ns))
            .clamp(i128::from(i64::MIN), i128::from(i64::MAX)) as i64;
        if offset_ns.unsigned_abs() > self.max_offset_ns {
            return Err(err(ObservationProblem::TimestampOff {
                camera,
                offset_ns,
                limit_ns: self.max_offset_ns,
            }));
        }
        if let Some(last) = self.last_sequence[camera]
            && h.sequence <= last
        {
            return Err(err(ObservationProblem::DuplicateSequence {
                camera,
                sequence: h.sequence,
                last,
            }));
        }
        self.last_sequence[camera] = Some(h.sequence);
        Ok(camera)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> ObsHeader<'static> {
        ObsHeader {
            rig: "cell1",
            board: "b1",
            camera: 1,
            sequence: 7,
            trigger_count: None,
            capture_ts_ns: 1_000_000,
            clock: ObsClock::Realtime,
            exposure_us: 500,
            dropped: 0,
            send_delay_us: 0,
        }
    }

    #[test]
    fn every_prefix_is_truncated_not_a_panic() {
        let mut buf = [0u8; MAX_OBS_LEN];
        let blobs = [ObsBlob {
            x_px: 1.5,
            y_px: 2.5,
            area_px: 9,
            peak_dn: 200,
            roundness: 1.0,
            ..ObsBlob::default()
        }];
        let n = encode(&header(), &blobs, &mut buf).unwrap();
        for cut in 0..n {
            match decode(&buf[..cut]) {
                Err(Error::Observation {
                    problem: ObservationProblem::Truncated { .. },
                }) => {}
                other => panic!("prefix of {cut} bytes: {other:?}"),
            }
        }
        assert!(decode(&buf[..n]).is_ok());
    }
}
