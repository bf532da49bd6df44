//! The crate's one error type. Variants carry the context needed to act on them.

use thiserror::Error;

/// Errors of irtrack-core.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum Error {
    /// A 3-D point lies on or behind a camera's image plane.
    #[error("point is behind camera {camera} (z = {z_mm} mm)")]
    BehindCamera {
        /// Camera index.
        camera: usize,
        /// Depth of the point in that camera's frame (mm).
        z_mm: f64,
    },
    /// Two rays are (nearly) parallel; the intersection is undefined.
    #[error("rays are parallel within {angle_rad:e} rad; cannot triangulate")]
    ParallelRays {
        /// Angle between the rays.
        angle_rad: f64,
    },
    /// Fewer observations than the method needs.
    #[error("need at least {needed} views, got {got}")]
    TooFewViews {
        /// How many are needed.
        needed: usize,
        /// How many there are.
        got: usize,
    },
    /// A numerical routine did not produce a finite result.
    #[error("degenerate geometry in {what}")]
    Degenerate {
        /// What it concerns.
        what: &'static str,
    },
    /// A caller-provided buffer is too small for the request.
    #[error("buffer `{what}` too small: need {needed}, have {have}")]
    BufferTooSmall {
        /// What it concerns.
        what: &'static str,
        /// How many are needed.
        needed: usize,
        /// How many there are.
        have: usize,
    },
    /// Frame dimensions disagree with the data or the configuration.
    #[error("bad frame geometry: {what}")]
    BadFrame {
        /// What it concerns.
        what: &'static str,
    },
    /// Region of interest outside the frame.
    #[error("region of interest {x},{y} {w}x{h} outside frame {frame_w}x{frame_h}")]
    BadRoi {
        /// Left column of the region (px).
        x: u32,
        /// Top row of the region (px).
        y: u32,
        /// Width of the region (px).
        w: u32,
        /// Height of the region (px).
        h: u32,
        /// Frame width (px).
        frame_w: u32,
        /// Frame height (px).
        frame_h: u32,
    },
    /// Parameter blob shorter than its header or declared body.
    #[error("parameter blob truncated: need {needed} bytes, got {got}")]
    BlobTruncated {
        /// How many are needed.
        needed: usize,
        /// How many there are.
        got: usize,
    },
    /// Parameter blob does not start with the magic bytes.
    #[error("not an irtrack parameter blob (magic {found:02x?})")]
    BlobBadMagic {
        /// The value found in the blob.
        found: [u8; 4],
    },
    /// Parameter blob format version this build does not read.
    #[error("parameter blob format version {found} unsupported (this build reads versions 1 to {supported})")]
    BlobUnsupportedVersion {
        /// The value found in the blob.
        found: u16,
        /// Newest version this build reads.
        supported: u16,
    },
    /// CRC mismatch: the blob was corrupted.
    #[error("parameter blob corrupted: CRC-32 {found:08x}, computed {computed:08x}")]
    BlobBadCrc {
        /// The value found in the blob.
        found: u32,
        /// The value computed over the blob.
        computed: u32,
    },
    /// Trailing bytes after the declared body.
    #[error("parameter blob has {extra} trailing bytes after the declared body")]
    BlobTrailingBytes {
        /// Number of trailing bytes.
        extra: usize,
    },
    /// Header flags this build does not understand (e.g. a signature trailer).
    #[error("parameter blob flags {flags:#06x} unsupported (known: {known:#06x})")]
    BlobUnsupportedFlags {
        /// The blob's flags.
        flags: u16,
        /// Flags this build understands.
        known: u16,
    },
    /// Body did not decode.
    #[error("parameter blob body does not decode: {reason}")]
    BlobBody {
        /// Why.
        reason: &'static str,
    },
    /// An unsigned parameter blob where the policy requires a signature.
    #[error("parameter blob is not signed, and signed parameters are required (sign it with a trusted key)")]
    BlobUnsigned,
    /// A signed parameter blob whose key id matches none of the trusted keys.
    #[error("parameter blob is signed by key {key_id}, which is not one of the {trusted} trusted keys")]
    BlobUnknownKey {
        /// Id of the signing key.
        key_id: crate::signing::KeyId,
        /// Number of trusted keys.
        trusted: usize,
    },
    /// The signature does not verify with the trusted key of that id: altered or forged.
    #[error("parameter blob signature by key {key_id} does not verify: altered after signing or forged")]
    BlobBadSignature {
        /// Id of the signing key.
        key_id: crate::signing::KeyId,
    },
    /// A signing or verifying key (file) is malformed.
    #[error("bad {what}: {reason}")]
    BadKey {
        /// What it concerns.
        what: &'static str,
        /// Why.
        reason: alloc::string::String,
    },
    /// Parameters are structurally valid but not usable.
    #[error("invalid parameters: {reason}")]
    InvalidParams {
        /// Why.
        reason: alloc::string::String,
    },
    /// A camera index past the rig's camera count.
    #[error("no camera {index}: the rig has {count} cameras")]
    NoSuchCamera {
        /// Camera index asked for.
        index: usize,
        /// Cameras of the rig.
        count: usize,
    },
    /// A protocol message announces more bytes than the protocol allows.
    #[error("{protocol} message of {size} bytes exceeds the limit of {max} bytes")]
    MessageTooLarge {
        /// The protocol.
        protocol: &'static str,
        /// Announced size (bytes).
        size: usize,
        /// The limit (bytes).
        max: usize,
    },
    /// A camera observation was refused (docs/observation-protocol.md).
    #[error("observation refused: {problem}")]
    Observation {
        /// What was wrong with it.
        problem: crate::observation::ObservationProblem,
    },
    /// A protocol message is malformed.
    #[error("malformed {protocol} message: {reason}")]
    Protocol {
        /// The protocol.
        protocol: &'static str,
        /// Why.
        reason: alloc::string::String,
    },
    /// A binary PGM file is malformed or does not fit the buffer (docs/frameset.md).
    #[error("not a usable binary PGM: {reason}")]
    Pgm {
        /// Why.
        reason: alloc::string::String,
    },
    /// A frame-set body does not match its header line (docs/frameset.md).
    #[error("bad frame set: {reason}")]
    FrameSet {
        /// Why.
        reason: alloc::string::String,
    },
}

/// Result alias for irtrack-core.
pub type Result<T> = core::result::Result<T, Error>;
