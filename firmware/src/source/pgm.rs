//! Binary PGM (P5) reading and writing, 8 or 16 bit (16-bit samples are big-endian per Netpbm).

use super::{Frame, Pixels, SourceError};

/// Parsed P5 header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PgmHeader {
    pub width_px: u32,
    pub height_px: u32,
    pub maxval: u16,
    /// Byte offset of the first sample.
    pub data_offset: usize,
}

impl PgmHeader {
    pub fn bytes_per_sample(&self) -> usize {
        if self.maxval < 256 { 1 } else { 2 }
    }

    /// Significant bits implied by maxval (255 → 8, 1023 → 10, 65535 → 16).
    pub fn bit_depth(&self) -> u8 {
        (16 - self.maxval.leading_zeros()) as u8
    }
}

fn bad(path: &str, reason: &str) -> SourceError {
    SourceError::Config(format!("{path}: not a usable binary PGM: {reason}"))
}

/// Parses the header of a P5 file held in `data` (`path` only names it in errors).
pub fn parse_header(data: &[u8], path: &str) -> Result<PgmHeader, SourceError> {
    if data.len() < 2 || &data[..2] != b"P5" {
        return Err(bad(path, "missing P5 magic"));
    }
    let mut pos = 2;
    let mut fields = [0u32; 3];
    for field in &mut fields {
        // Skip whitespace and comments between header fields.
        loop {
            match data.get(pos) {
                Some(b) if b.is_ascii_whitespace() => pos += 1,
                Some(b'#') => {
                    while data.get(pos).is_some_and(|&b| b != b'\n') {
                        pos += 1;
                    }
                }
                Some(_) => break,
                None => return Err(bad(path, "header truncated")),
            }
        }
        let start = pos;
        while data.get(pos).is_some_and(u8::is_ascii_digit) {
            pos += 1;
        }
        let digits = std::str::from_utf8(&data[start..pos]).map_err(|_| bad(path, "header not ASCII"))?;
        *field = digits
            .parse()
            .map_err(|_| bad(path, "header field is not a number"))?;
    }
    // Exactly one whitespace byte separates maxval from the samples.
    if !data.get(pos).is_some_and(u8::is_ascii_whitespace) {
        return Err(bad(path, "no whitespace after maxval"));
    }
    let [w, h, maxval] = fields;
    if w == 0 || h == 0 || maxval == 0 || maxval > 65535 {
        return Err(bad(path, "zero size or maxval outside 1..=65535"));
    }
    let header = PgmHeader {
        width_px: w,
        height_px: h,
        maxval: maxval as u16,
        data_offset: pos + 1,
    };
    let needed = header.data_offset + w as usize * h as usize * header.bytes_per_sample();
    if data.len() < needed {
        return Err(bad(path, &format!("{} bytes, header needs {needed}", data.len())));
    }
    Ok(header)
}

/// Copies the samples of a P5 file into `frame` (which must already have the file's size and
/// sample width; no allocation).
pub fn decode_into(data: &[u8], path: &str, frame: &mut Frame) -> Result<(), SourceError> {
    let h = parse_header(data, path)?;
    if h.width_px != frame.width_px || h.height_px != frame.height_px {
        return Err(bad(
            path,
            &format!(
                "size {}x{} differs from {}x{}",
                h.width_px, h.height_px, frame.width_px, frame.height_px
            ),
        ));
    }
    let (w, rows, stride) = (
        frame.width_px as usize,
        frame.height_px as usize,
        frame.stride_px as usize,
    );
    let body = &data[h.data_offset..];
    match (&mut frame.pixels, h.bytes_per_sample()) {
        (Pixels::U8(px), 1) => {
            for (dst, src) in px.chunks_mut(stride).zip(body.chunks(w)).take(rows) {
                dst[..w].copy_from_slice(src);
            }
        }
        (Pixels::U16(px), 2) => {
            for (dst, src) in px.chunks_mut(stride).zip(body.chunks(2 * w)).take(rows) {
                for (d, s) in dst[..w].iter_mut().zip(src.chunks_exact(2)) {
                    *d = u16::from_be_bytes([s[0], s[1]]);
                }
            }
        }
        _ => return Err(bad(path, "sample width changed between frames")),
    }
    frame.bit_depth = h.bit_depth();
    Ok(())
}

/// An empty frame shaped like the P5 file described by `h`.
pub fn frame_for(h: &PgmHeader) -> Frame {
    let n = h.width_px as usize * h.height_px as usize;
    Frame {
        width_px: h.width_px,
        height_px: h.height_px,
        stride_px: h.width_px,
        bit_depth: h.bit_depth(),
        pixels: if h.bytes_per_sample() == 1 {
            Pixels::U8(vec![0; n])
        } else {
            Pixels::U16(vec![0; n])
        },
        timestamp_ns: 0,
        sequence: 0,
    }
}

/// Encodes a frame as P5 (used by tests and recording tools).
pub fn encode(frame: &Frame) -> Vec<u8> {
    let (w, h, stride) = (
        frame.width_px as usize,
        frame.height_px as usize,
        frame.stride_px as usize,
    );
    let maxval: u32 = (1u32 << frame.bit_depth.clamp(1, 16)) - 1;
    let mut out = format!("P5\n{w} {h}\n{maxval}\n").into_bytes();
    match &frame.pixels {
        Pixels::U8(px) => px
            .chunks(stride)
            .take(h)
            .for_each(|r| out.extend_from_slice(&r[..w])),
        Pixels::U16(px) => px.chunks(stride).take(h).for_each(|r| {
            r[..w]
                .iter()
                .for_each(|v| out.extend_from_slice(&v.to_be_bytes()))
        }),
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roundtrip_8_and_16_bit_with_comments() {
        for (depth, pixels) in [
            (8u8, Pixels::U8((0..12).collect())),
            (10, Pixels::U16((0..12).map(|v| v * 80).collect())),
        ] {
            let f = Frame {
                width_px: 4,
                height_px: 3,
                stride_px: 4,
                bit_depth: depth,
                pixels,
                timestamp_ns: 0,
                sequence: 0,
            };
            let mut bytes = encode(&f);
            // Insert a comment after the magic, as GIMP/ImageMagick do.
            bytes.splice(2..2, b"\n# made by a test".iter().copied());
            let h = parse_header(&bytes, "t.pgm").unwrap();
            assert_eq!((h.width_px, h.height_px, h.bit_depth()), (4, 3, depth));
            let mut g = frame_for(&h);
            decode_into(&bytes, "t.pgm", &mut g).unwrap();
            assert_eq!(g.pixels, f.pixels);
        }
    }

    #[test]
    fn truncated_and_wrong_magic_are_named() {
        let err = parse_header(b"P2\n1 1\n255\n0", "a.pgm").unwrap_err().to_string();
        assert!(err.contains("a.pgm") && err.contains("P5"), "{err}");
        let err = parse_header(b"P5\n4 4\n255\n0123", "b.pgm")
            .unwrap_err()
            .to_string();
        assert!(err.contains("bytes, header needs 27"), "{err}");
    }
}
