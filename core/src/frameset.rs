//! Frame sets: the body of irtrackd's `GET /api/frameset`, one JSON header line followed by each
//! camera's frame as a binary PGM ([`crate::pgm`]). irtrackd writes it ([`encode`]),
//! `host-tools capture` reads it ([`FrameSet::parse`]). Spec: docs/frameset.md.

use alloc::format;
use alloc::string::String;
use alloc::vec::Vec;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::pgm;

/// HTTP `Content-Type` of a frame-set body.
pub const CONTENT_TYPE: &str = "application/x-irtrack-frameset";

fn bad(reason: String) -> Error {
    Error::FrameSet { reason }
}

/// One camera's entry in the header line.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CameraHeader {
    /// Camera index; entries come in camera order 0, 1, ...
    pub camera: u32,
    /// Frame columns.
    pub width_px: u32,
    /// Frame rows.
    pub height_px: u32,
    /// Significant bits per sample; the PGM's maxval is `2^bit_depth - 1`.
    pub bit_depth: u8,
    /// Capture time of the frame (the board's monotonic clock).
    pub timestamp_ns: u64,
    /// The camera's frame counter.
    #[serde(default)]
    pub sequence: u64,
    /// Length of this camera's PGM file in the body.
    pub pgm_bytes: usize,
}

/// The JSON line in front of the frames.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameSetHeader {
    /// The processing loop's set counter.
    pub set_index: u64,
    /// Largest timestamp difference between the set's frames.
    pub pairing_error_ns: u64,
    /// One entry per camera, in camera order.
    pub cameras: Vec<CameraHeader>,
    /// The board's CLOCK_REALTIME − CLOCK_MONOTONIC when it served the set: added to a
    /// `timestamp_ns` it gives the capture time on the realtime clock PTP or chrony keeps the
    /// boards agreeing on (the clock the cluster pairs by). Absent from older irtrackd.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub realtime_minus_monotonic_ns: Option<i64>,
}

impl FrameSetHeader {
    /// Camera `i`'s capture time on CLOCK_REALTIME, if the board said its clock difference.
    pub fn realtime_ns(&self, i: usize) -> Option<i128> {
        let d = self.realtime_minus_monotonic_ns?;
        let cam = self.cameras.get(i)?;
        Some(i128::from(cam.timestamp_ns) + i128::from(d))
    }
}

/// One camera's frame to put into a set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CameraFrame<'a> {
    /// The pixels.
    pub image: pgm::Image<'a>,
    /// Capture time (the board's monotonic clock).
    pub timestamp_ns: u64,
    /// The camera's frame counter.
    pub sequence: u64,
}

/// A frame-set body: the header line, then each frame's PGM in camera order.
pub fn encode(set_index: u64, pairing_error_ns: u64, frames: &[CameraFrame<'_>]) -> Result<Vec<u8>> {
    encode_with_clock(set_index, pairing_error_ns, None, frames)
}

/// [`encode`] with the board's CLOCK_REALTIME − CLOCK_MONOTONIC in the header
/// ([`FrameSetHeader::realtime_minus_monotonic_ns`]), so frame sets of several boards can be
/// paired on the shared realtime clock.
pub fn encode_with_clock(
    set_index: u64,
    pairing_error_ns: u64,
    realtime_minus_monotonic_ns: Option<i64>,
    frames: &[CameraFrame<'_>],
) -> Result<Vec<u8>> {
    let mut pgms = Vec::with_capacity(frames.len());
    for (i, f) in frames.iter().enumerate() {
        pgms.push(pgm::encode(&f.image).map_err(|e| bad(format!("camera {i}: {e}")))?);
    }
    let header = FrameSetHeader {
        set_index,
        pairing_error_ns,
        cameras: frames
            .iter()
            .zip(&pgms)
            .enumerate()
            .map(|(i, (f, p))| CameraHeader {
                camera: i as u32,
                width_px: f.image.width_px,
                height_px: f.image.height_px,
                bit_depth: f.image.bit_depth,
                timestamp_ns: f.timestamp_ns,
                sequence: f.sequence,
                pgm_bytes: p.len(),
            })
            .collect(),
        realtime_minus_monotonic_ns,
    };
    let mut body = serde_json::to_vec(&header).map_err(|e| bad(format!("header: {e}")))?;
    body.push(b'\n');
    for p in pgms {
        body.extend_from_slice(&p);
    }
    Ok(body)
}

/// A parsed frame set: the header and each camera's PGM file bytes, in camera order.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameSet {
    /// The header line.
    pub header: FrameSetHeader,
    /// Each camera's PGM file, exactly as served.
    pub pgms: Vec<Vec<u8>>,
}

impl FrameSet {
    /// Parses a body, checking that every frame is a PGM of the size and depth its header
    /// entry announces, that it fills its `pgm_bytes` exactly and that nothing is left over.
    ///
    /// A frame deeper than 8 bits with maxval 65535 is also accepted: irtrackd before the one
    /// maxval rule (docs/frameset.md) wrote every 16-bit frame that way.
    pub fn parse(body: &[u8]) -> Result<FrameSet> {
        let nl = body
            .iter()
            .position(|b| *b == b'\n')
            .ok_or_else(|| bad(format!("no header line (no newline in {} bytes)", body.len())))?;
        let header: FrameSetHeader = serde_json::from_slice(&body[..nl]).map_err(|e| {
            bad(format!(
                "header is not the documented JSON ({e}): {:?}",
                String::from_utf8_lossy(&body[..nl.min(200)])
            ))
        })?;
        if header.cameras.is_empty() {
            return Err(bad(String::from("no cameras")));
        }
        let mut rest = &body[nl + 1..];
        let mut pgms = Vec::with_capacity(header.cameras.len());
        for (i, cam) in header.cameras.iter().enumerate() {
            if cam.camera as usize != i {
                return Err(bad(format!(
                    "header lists camera {} at position {i}; cameras must come in order",
                    cam.camera
                )));
            }
            if rest.len() < cam.pgm_bytes {
                return Err(bad(format!(
                    "camera {i}: header announces {} PGM bytes, only {} left in the body",
                    cam.pgm_bytes,
                    rest.len()
                )));
            }
            let (file, tail) = rest.split_at(cam.pgm_bytes);
            let h = pgm::parse_header(file).map_err(|e| bad(format!("camera {i}: {e}")))?;
            if (h.width_px, h.height_px) != (cam.width_px, cam.height_px) {
                return Err(bad(format!(
                    "camera {i}: PGM is {}x{}, header says {}x{}",
                    h.width_px, h.height_px, cam.width_px, cam.height_px
                )));
            }
            let expected =
                pgm::maxval_for_bit_depth(cam.bit_depth).map_err(|e| bad(format!("camera {i}: {e}")))?;
            let legacy = cam.bit_depth > 8 && h.maxval == u16::MAX;
            if h.maxval != expected && !legacy {
                return Err(bad(format!(
                    "camera {i}: PGM maxval {} does not match bit depth {} (maxval {expected})",
                    h.maxval, cam.bit_depth
                )));
            }
            if h.file_len() != file.len() {
                return Err(bad(format!(
                    "camera {i}: PGM of {} bytes in {} announced bytes",
                    h.file_len(),
                    file.len()
                )));
            }
            pgms.push(file.to_vec());
            rest = tail;
        }
        if !rest.is_empty() {
            return Err(bad(format!("{} bytes after the last camera's frame", rest.len())));
        }
        Ok(FrameSet { header, pgms })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use alloc::string::ToString;
    use alloc::vec;

    /// Golden body: camera 0 is 3x2 8-bit, camera 1 is 2x1 10-bit (docs/frameset.md).
    const GOLDEN: &[u8] = b"{\"set_index\":7,\"pairing_error_ns\":250,\"cameras\":[\
{\"camera\":0,\"width_px\":3,\"height_px\":2,\"bit_depth\":8,\"timestamp_ns\":1000,\"sequence\":41,\"pgm_bytes\":17},\
{\"camera\":1,\"width_px\":2,\"height_px\":1,\"bit_depth\":10,\"timestamp_ns\":1250,\"sequence\":42,\"pgm_bytes\":16}]}\n\
P5\n3 2\n255\n\x00\x01\x02\x03\x04\xff\
P5\n2 1\n1023\n\x03\xff\x00\x10";

    fn frames<'a>(px8: &'a [u8], px16: &'a [u16]) -> [CameraFrame<'a>; 2] {
        [
            CameraFrame {
                image: pgm::Image {
                    width_px: 3,
                    height_px: 2,
                    stride_px: 3,
                    bit_depth: 8,
                    samples: pgm::Samples::U8(px8),
                },
                timestamp_ns: 1000,
                sequence: 41,
            },
            CameraFrame {
                image: pgm::Image {
                    width_px: 2,
                    height_px: 1,
                    stride_px: 2,
                    bit_depth: 10,
                    samples: pgm::Samples::U16(px16),
                },
                timestamp_ns: 1250,
                sequence: 42,
            },
        ]
    }

    /// The clock difference is one more header field (docs/frameset.md), absent when `None`.
    #[test]
    fn realtime_clock_difference_encodes_and_parses() {
        let px8 = [0u8, 1, 2, 3, 4, 255];
        let px16 = [1023u16, 16];
        let body = encode_with_clock(7, 250, Some(1_700_000_000_000_000_000), &frames(&px8, &px16)).unwrap();
        let golden = String::from_utf8_lossy(GOLDEN).replacen(
            "]}\n",
            "],\"realtime_minus_monotonic_ns\":1700000000000000000}\n",
            1,
        );
        assert_eq!(String::from_utf8_lossy(&body), golden);
        let set = FrameSet::parse(&body).unwrap();
        assert_eq!(
            set.header.realtime_minus_monotonic_ns,
            Some(1_700_000_000_000_000_000)
        );
        assert_eq!(set.header.realtime_ns(1), Some(1_700_000_000_000_001_250));
        let old = FrameSet::parse(GOLDEN).unwrap();
        assert_eq!(old.header.realtime_minus_monotonic_ns, None);
        assert_eq!(old.header.realtime_ns(0), None);
    }

    #[test]
    fn golden_body_encodes_and_parses() {
        let px8 = [0u8, 1, 2, 3, 4, 255];
        let px16 = [1023u16, 16];
        let body = encode(7, 250, &frames(&px8, &px16)).unwrap();
        assert_eq!(body, GOLDEN, "{}", String::from_utf8_lossy(&body));
        let set = FrameSet::parse(GOLDEN).unwrap();
        assert_eq!(set.header.set_index, 7);
        assert_eq!(set.header.pairing_error_ns, 250);
        assert_eq!(set.header.cameras[1].bit_depth, 10);
        assert_eq!(set.header.cameras[1].sequence, 42);
        assert_eq!(set.pgms.len(), 2);
        assert_eq!(
            pgm::decode(&set.pgms[1]).unwrap().pixels,
            pgm::PgmPixels::U16(vec![1023, 16])
        );
        assert_eq!(
            pgm::decode(&set.pgms[0]).unwrap().pixels,
            pgm::PgmPixels::U8(px8.to_vec())
        );
    }

    #[test]
    fn bodies_that_do_not_match_their_header_are_refused() {
        let e = |b: &[u8]| FrameSet::parse(b).unwrap_err().to_string();
        assert!(e(&GOLDEN[..GOLDEN.len() - 1]).contains("left in the body"));
        let mut extra = GOLDEN.to_vec();
        extra.push(0);
        assert!(e(&extra).contains("after the last camera"));
        assert!(e(b"{\"set_index\":1}").contains("no header line"));
        assert!(e(b"<html>404</html>\n").contains("not the documented JSON"));
        // The header line with one field changed, the frames as they are.
        let nl = GOLDEN.iter().position(|b| *b == b'\n').unwrap();
        let frames = &GOLDEN[nl..];
        let edit = |from: &str, to: &str, frames: &[u8]| {
            let line = core::str::from_utf8(&GOLDEN[..nl]).unwrap().replacen(from, to, 1);
            [line.as_bytes(), frames].concat()
        };
        assert!(e(&edit("\"width_px\":3", "\"width_px\":4", frames)).contains("PGM is 3x2, header says 4x2"));
        assert!(e(&edit("\"camera\":0", "\"camera\":1", frames)).contains("in order"));
        assert!(
            e(&edit("\"bit_depth\":10", "\"bit_depth\":12", frames))
                .contains("maxval 1023 does not match bit depth 12")
        );
        // An older board's 16-bit frame (maxval 65535 for 10-bit data) is still read.
        let old_frames = [&frames[..frames.len() - 16], b"P5\n2 1\n65535\n\x03\xff\x00\x10"].concat();
        let old = edit("\"pgm_bytes\":16", "\"pgm_bytes\":17", &old_frames);
        assert!(FrameSet::parse(&old).is_ok(), "{}", e(&old));
    }
}
