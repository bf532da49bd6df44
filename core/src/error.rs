//! The crate's one error type. Variants carry the context needed to act on them.

use thiserror::Error;

/// Errors of irtrack-core.
#[derive(Debug, Clone, PartialEq, Error)]
#[non_exhaustive]
pub enum Error {
    /// A 3-D point lies on or behind a camera's image plane.
    #[error("point is behind camera {camera} (z = {z_mm} mm)")]
    BehindCamera { camera: usize, z_mm: f64 },
    /// Two rays are (nearly) parallel; the intersection is undefined.
    #[error("rays are parallel within {angle_rad:e} rad; cannot triangulate")]
    ParallelRays { angle_rad: f64 },
    /// Fewer observations than the method needs.
    #[error("need at least {needed} views, got {got}")]
    TooFewViews { needed: usize, got: usize },
    /// A numerical routine did not produce a finite result.
    #[error("degenerate geometry in {what}")]
    Degenerate { what: &'static str },
    /// A caller-provided buffer is too small for the request.
    #[error("buffer `{what}` too small: need {needed}, have {have}")]
    BufferTooSmall {
        what: &'static str,
        needed: usize,
        have: usize,
    },
    /// Frame dimensions disagree with the data or the configuration.
    #[error("bad frame geometry: {what}")]
    BadFrame { what: &'static str },
    /// Region of interest outside the frame.
    #[error("region of interest {x},{y} {w}x{h} outside frame {frame_w}x{frame_h}")]
    BadRoi {
        x: u32,
        y: u32,
        w: u32,
        h: u32,
        frame_w: u32,
        frame_h: u32,
    },
    /// Parameter blob shorter than its header or declared body.
    #[error("parameter blob truncated: need {needed} bytes, got {got}")]
    BlobTruncated { needed: usize, got: usize },
    /// Parameter blob does not start with the magic bytes.
    #[error("not an irtrack parameter blob (magic {found:02x?})")]
    BlobBadMagic { found: [u8; 4] },
    /// Parameter blob format version this build does not read.
    #[error("parameter blob format version {found} unsupported (this build reads versions 1 to {supported})")]
    BlobUnsupportedVersion { found: u16, supported: u16 },
    /// CRC mismatch: the blob was corrupted.
    #[error("parameter blob corrupted: CRC-32 {found:08x}, computed {computed:08x}")]
    BlobBadCrc { found: u32, computed: u32 },
    /// Trailing bytes after the declared body.
    #[error("parameter blob has {extra} trailing bytes after the declared body")]
    BlobTrailingBytes { extra: usize },
    /// Header flags this build does not understand (e.g. a signature trailer).
    #[error("parameter blob flags {flags:#06x} unsupported (known: {known:#06x})")]
    BlobUnsupportedFlags { flags: u16, known: u16 },
    /// Body did not decode.
    #[error("parameter blob body does not decode: {reason}")]
    BlobBody { reason: &'static str },
    /// An unsigned parameter blob where the policy requires a signature.
    #[error("parameter blob is not signed, and signed parameters are required (sign it with a trusted key)")]
    BlobUnsigned,
    /// A signed parameter blob whose key id matches none of the trusted keys.
    #[error("parameter blob is signed by key {key_id}, which is not one of the {trusted} trusted keys")]
    BlobUnknownKey {
        key_id: crate::signing::KeyId,
        trusted: usize,
    },
    /// The signature does not verify with the trusted key of that id: altered or forged.
    #[error("parameter blob signature by key {key_id} does not verify: altered after signing or forged")]
    BlobBadSignature { key_id: crate::signing::KeyId },
    /// A signing or verifying key (file) is malformed.
    #[error("bad {what}: {reason}")]
    BadKey {
        what: &'static str,
        reason: alloc::string::String,
    },
    /// Parameters are structurally valid but not usable.
    #[error("invalid parameters: {reason}")]
    InvalidParams { reason: alloc::string::String },
    /// A camera index past the rig's camera count.
    #[error("no camera {index}: the rig has {count} cameras")]
    NoSuchCamera { index: usize, count: usize },
    /// A protocol message announces more bytes than the protocol allows.
    #[error("{protocol} message of {size} bytes exceeds the limit of {max} bytes")]
    MessageTooLarge {
        protocol: &'static str,
        size: usize,
        max: usize,
    },
    /// A protocol message is malformed.
    #[error("malformed {protocol} message: {reason}")]
    Protocol {
        protocol: &'static str,
        reason: alloc::string::String,
    },
    /// A binary PGM file is malformed or does not fit the buffer (docs/frameset.md).
    #[error("not a usable binary PGM: {reason}")]
    Pgm { reason: alloc::string::String },
    /// A frame-set body does not match its header line (docs/frameset.md).
    #[error("bad frame set: {reason}")]
    FrameSet { reason: alloc::string::String },
}

/// Result alias for irtrack-core.
pub type Result<T> = core::result::Result<T, Error>;
