//! Binary PGM (Netpbm `P5`), 8 and 16 bit: irtrack's one encoder and decoder of grey frames.
//!
//! Used for recorded directories (`camN/NNNNNN.pgm`: simulator output, replay, `capture`), for
//! the frames of `GET /api/frameset` ([`crate::frameset`]) and by every host tool that reads
//! them. Spec: docs/frameset.md.
//!
//! **The maxval rule** (one for every writer): a frame with `bit_depth` significant bits is
//! written with maxval `2^bit_depth - 1` (8 → 255, 10 → 1023, 16 → 65535). As Netpbm defines,
//! samples are one byte when maxval < 256 and two bytes big-endian otherwise. A reader takes the
//! bit depth back from maxval ([`PgmHeader::bit_depth`]).

use alloc::format;
use alloc::string::String;
use alloc::vec;
use alloc::vec::Vec;

use crate::error::{Error, Result};

fn bad(reason: String) -> Error {
    Error::Pgm { reason }
}

/// maxval of a frame with `bit_depth` significant bits (1..=16): `2^bit_depth - 1`.
pub fn maxval_for_bit_depth(bit_depth: u8) -> Result<u16> {
    if !(1..=16).contains(&bit_depth) {
        return Err(bad(format!("bit depth {bit_depth} outside 1..=16")));
    }
    Ok(((1u32 << bit_depth) - 1) as u16)
}

/// Significant bits implied by a maxval (255 → 8, 1023 → 10, 65535 → 16).
pub fn bit_depth_of_maxval(maxval: u16) -> u8 {
    (16 - maxval.leading_zeros()) as u8
}

/// Bytes per sample for a maxval: 1 below 256, else 2 (big-endian).
pub fn bytes_per_sample(maxval: u16) -> usize {
    if maxval < 256 { 1 } else { 2 }
}

/// Borrowed samples of a frame, row-major, rows `stride_px` samples apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Samples<'a> {
    /// One byte per sample (bit depth 1..=8).
    U8(&'a [u8]),
    /// Two bytes per sample in memory (bit depth 9..=16).
    U16(&'a [u16]),
}

/// Mutable samples to decode into, row-major, rows `stride_px` samples apart.
#[derive(Debug, PartialEq, Eq)]
pub enum SamplesMut<'a> {
    /// For files with maxval < 256.
    U8(&'a mut [u8]),
    /// For files with maxval >= 256.
    U16(&'a mut [u16]),
}

/// A view of one grey frame to encode.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Image<'a> {
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
    /// Samples from one row to the next (>= `width_px`).
    pub stride_px: u32,
    /// Significant bits per sample; decides maxval (module docs).
    pub bit_depth: u8,
    /// The samples.
    pub samples: Samples<'a>,
}

impl Image<'_> {
    /// Checks size, stride, buffer length and that the bit depth fits the sample type.
    fn check(&self) -> Result<u16> {
        let maxval = maxval_for_bit_depth(self.bit_depth)?;
        let (w, h, stride) = (
            self.width_px as usize,
            self.height_px as usize,
            self.stride_px as usize,
        );
        if w == 0 || h == 0 || stride < w {
            return Err(bad(format!(
                "{w}x{h} image with stride {stride}: size must be non-zero and stride >= width"
            )));
        }
        let (len, wide) = match self.samples {
            Samples::U8(s) => (s.len(), false),
            Samples::U16(s) => (s.len(), true),
        };
        let needed = stride * (h - 1) + w;
        if len < needed {
            return Err(bad(format!(
                "{w}x{h} image with stride {stride} needs {needed} samples, got {len}"
            )));
        }
        if wide != (bytes_per_sample(maxval) == 2) {
            return Err(bad(format!(
                "bit depth {} needs {} samples",
                self.bit_depth,
                if wide { "8-bit" } else { "16-bit" }
            )));
        }
        Ok(maxval)
    }

    /// Length of the encoded file in bytes (0 if the image is invalid).
    pub fn encoded_len(&self) -> usize {
        let Ok(maxval) = self.check() else { return 0 };
        header_text_len(self.width_px, self.height_px, maxval)
            + self.width_px as usize * self.height_px as usize * bytes_per_sample(maxval)
    }
}

fn decimal_len(mut v: u32) -> usize {
    let mut n = 1;
    while v >= 10 {
        v /= 10;
        n += 1;
    }
    n
}

fn header_text_len(w: u32, h: u32, maxval: u16) -> usize {
    // "P5\n{w} {h}\n{maxval}\n"
    3 + decimal_len(w) + 1 + decimal_len(h) + 1 + decimal_len(maxval.into()) + 1
}

/// Appends `img` as a P5 file to `out` (header `P5\n<w> <h>\n<maxval>\n`, no comments).
pub fn encode_into(img: &Image<'_>, out: &mut Vec<u8>) -> Result<()> {
    let maxval = img.check()?;
    let (w, h, stride) = (
        img.width_px as usize,
        img.height_px as usize,
        img.stride_px as usize,
    );
    out.reserve(img.encoded_len());
    out.extend_from_slice(format!("P5\n{w} {h}\n{maxval}\n").as_bytes());
    match img.samples {
        Samples::U8(px) => px
            .chunks(stride)
            .take(h)
            .for_each(|row| out.extend_from_slice(&row[..w])),
        Samples::U16(px) => px.chunks(stride).take(h).for_each(|row| {
            row[..w]
                .iter()
                .for_each(|v| out.extend_from_slice(&v.to_be_bytes()))
        }),
    }
    Ok(())
}

/// `img` as a P5 file.
pub fn encode(img: &Image<'_>) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    encode_into(img, &mut out)?;
    Ok(out)
}

/// An 8-bit P5 file of tightly packed samples (maxval 255).
pub fn encode_u8(width_px: u32, height_px: u32, data: &[u8]) -> Result<Vec<u8>> {
    check_packed(width_px, height_px, data.len())?;
    encode(&Image {
        width_px,
        height_px,
        stride_px: width_px,
        bit_depth: 8,
        samples: Samples::U8(data),
    })
}

/// A 16-bit P5 file of tightly packed samples with `bit_depth` 9..=16 (10 → maxval 1023).
pub fn encode_u16(width_px: u32, height_px: u32, bit_depth: u8, data: &[u16]) -> Result<Vec<u8>> {
    check_packed(width_px, height_px, data.len())?;
    encode(&Image {
        width_px,
        height_px,
        stride_px: width_px,
        bit_depth,
        samples: Samples::U16(data),
    })
}

fn check_packed(width_px: u32, height_px: u32, len: usize) -> Result<()> {
    let needed = width_px as usize * height_px as usize;
    if needed != len || needed == 0 {
        return Err(bad(format!(
            "{width_px}x{height_px} image needs {needed} samples, got {len}"
        )));
    }
    Ok(())
}

/// A parsed P5 header.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PgmHeader {
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
    /// Largest sample value, 1..=65535.
    pub maxval: u16,
    /// Byte offset of the first sample.
    pub data_offset: usize,
}

impl PgmHeader {
    /// 1 below maxval 256, else 2.
    pub fn bytes_per_sample(&self) -> usize {
        bytes_per_sample(self.maxval)
    }

    /// Significant bits implied by maxval (255 → 8, 1023 → 10, 65535 → 16).
    pub fn bit_depth(&self) -> u8 {
        bit_depth_of_maxval(self.maxval)
    }

    /// Bytes of header and samples: where the file ends (later bytes are not part of it).
    pub fn file_len(&self) -> usize {
        self.data_offset + self.width_px as usize * self.height_px as usize * self.bytes_per_sample()
    }
}

/// Parses the header of the P5 file at the start of `data` and checks that `data` holds all
/// its samples (bytes after them are ignored).
pub fn parse_header(data: &[u8]) -> Result<PgmHeader> {
    if data.len() < 2 || &data[..2] != b"P5" {
        return Err(bad(String::from("missing P5 magic (binary greymap expected)")));
    }
    let mut pos = 2;
    let mut fields = [0u32; 3];
    for (field, name) in fields.iter_mut().zip(["width", "height", "maxval"]) {
        // Whitespace and `#` comments may separate the fields.
        loop {
            match data.get(pos) {
                Some(b) if b.is_ascii_whitespace() => pos += 1,
                Some(b'#') => {
                    while data.get(pos).is_some_and(|&b| b != b'\n') {
                        pos += 1;
                    }
                }
                Some(_) => break,
                None => return Err(bad(String::from("header truncated"))),
            }
        }
        let start = pos;
        while data.get(pos).is_some_and(|b| !b.is_ascii_whitespace()) {
            pos += 1;
        }
        let token = &data[start..pos];
        *field = core::str::from_utf8(token)
            .ok()
            .filter(|t| t.bytes().all(|b| b.is_ascii_digit()))
            .and_then(|t| t.parse().ok())
            .ok_or_else(|| {
                bad(format!(
                    "{name} `{}` is not a number",
                    String::from_utf8_lossy(&token[..token.len().min(20)])
                ))
            })?;
    }
    // Exactly one whitespace byte separates maxval from the samples.
    if !data.get(pos).is_some_and(u8::is_ascii_whitespace) {
        return Err(bad(String::from("header truncated after maxval")));
    }
    let [w, h, maxval] = fields;
    if w == 0 || h == 0 || maxval == 0 || maxval > 65535 {
        return Err(bad(format!(
            "header {w}x{h} maxval {maxval}: zero size or maxval outside 1..=65535"
        )));
    }
    let header = PgmHeader {
        width_px: w,
        height_px: h,
        maxval: maxval as u16,
        data_offset: pos + 1,
    };
    let needed = header.file_len();
    if data.len() < needed {
        return Err(bad(format!("{} bytes, header needs {needed}", data.len())));
    }
    Ok(header)
}

/// Copies the samples of the P5 file `data` (described by `header`, from [`parse_header`])
/// into `dst`, rows `stride_px` apart. No allocation: the per-frame path of replay.
pub fn decode_into(data: &[u8], header: &PgmHeader, dst: SamplesMut<'_>, stride_px: usize) -> Result<()> {
    let (w, h) = (header.width_px as usize, header.height_px as usize);
    let body = data.get(header.data_offset..header.file_len()).ok_or_else(|| {
        bad(format!(
            "{} bytes, header needs {}",
            data.len(),
            header.file_len()
        ))
    })?;
    let dst_len = match &dst {
        SamplesMut::U8(d) => d.len(),
        SamplesMut::U16(d) => d.len(),
    };
    if stride_px < w || dst_len < stride_px * (h - 1) + w {
        return Err(bad(format!(
            "{w}x{h} image does not fit a buffer of {dst_len} samples with stride {stride_px}"
        )));
    }
    match (dst, header.bytes_per_sample()) {
        (SamplesMut::U8(px), 1) => {
            for (d, s) in px.chunks_mut(stride_px).zip(body.chunks_exact(w)) {
                d[..w].copy_from_slice(s);
            }
        }
        (SamplesMut::U16(px), 2) => {
            for (d, s) in px.chunks_mut(stride_px).zip(body.chunks_exact(2 * w)) {
                for (v, b) in d[..w].iter_mut().zip(s.chunks_exact(2)) {
                    *v = u16::from_be_bytes([b[0], b[1]]);
                }
            }
        }
        (_, n) => {
            return Err(bad(format!(
                "file has {n}-byte samples (maxval {}), the buffer the other width",
                header.maxval
            )));
        }
    }
    Ok(())
}

/// Decoded samples, tightly packed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PgmPixels {
    /// maxval < 256.
    U8(Vec<u8>),
    /// maxval >= 256.
    U16(Vec<u16>),
}

/// A decoded PGM file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pgm {
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
    /// Largest sample value.
    pub maxval: u16,
    /// The samples, row-major without padding.
    pub pixels: PgmPixels,
}

impl Pgm {
    /// Significant bits implied by maxval.
    pub fn bit_depth(&self) -> u8 {
        bit_depth_of_maxval(self.maxval)
    }
}

/// Decodes a whole P5 file (allocating; for host tools and tests).
pub fn decode(data: &[u8]) -> Result<Pgm> {
    let header = parse_header(data)?;
    let n = header.width_px as usize * header.height_px as usize;
    let stride = header.width_px as usize;
    let pixels = if header.bytes_per_sample() == 1 {
        let mut px = vec![0u8; n];
        decode_into(data, &header, SamplesMut::U8(&mut px), stride)?;
        PgmPixels::U8(px)
    } else {
        let mut px = vec![0u16; n];
        decode_into(data, &header, SamplesMut::U16(&mut px), stride)?;
        PgmPixels::U16(px)
    };
    Ok(Pgm {
        width_px: header.width_px,
        height_px: header.height_px,
        maxval: header.maxval,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use alloc::string::ToString;

    #[test]
    fn maxval_rule() {
        assert_eq!(maxval_for_bit_depth(8).unwrap(), 255);
        assert_eq!(maxval_for_bit_depth(10).unwrap(), 1023);
        assert_eq!(maxval_for_bit_depth(16).unwrap(), 65535);
        assert_eq!(maxval_for_bit_depth(1).unwrap(), 1);
        assert!(maxval_for_bit_depth(0).is_err() && maxval_for_bit_depth(17).is_err());
        for d in 1..=16 {
            assert_eq!(bit_depth_of_maxval(maxval_for_bit_depth(d).unwrap()), d);
        }
    }

    /// Golden bytes: a 3x2 8-bit image with stride 4 and a 2x2 10-bit image.
    #[test]
    fn golden_bytes_8_and_16_bit() {
        let px8 = [1u8, 2, 3, 99, 4, 5, 6, 99];
        let img8 = Image {
            width_px: 3,
            height_px: 2,
            stride_px: 4,
            bit_depth: 8,
            samples: Samples::U8(&px8),
        };
        let golden8: &[u8] = b"P5\n3 2\n255\n\x01\x02\x03\x04\x05\x06";
        assert_eq!(encode(&img8).unwrap(), golden8);
        assert_eq!(img8.encoded_len(), golden8.len());
        let px16 = [0u16, 1023, 0x0102, 0x0300];
        let img16 = Image {
            width_px: 2,
            height_px: 2,
            stride_px: 2,
            bit_depth: 10,
            samples: Samples::U16(&px16),
        };
        let golden16: &[u8] = b"P5\n2 2\n1023\n\x00\x00\x03\xff\x01\x02\x03\x00";
        assert_eq!(encode(&img16).unwrap(), golden16);
        assert_eq!(img16.encoded_len(), golden16.len());
        let d = decode(golden16).unwrap();
        assert_eq!(
            (d.width_px, d.height_px, d.maxval, d.bit_depth()),
            (2, 2, 1023, 10)
        );
        assert_eq!(d.pixels, PgmPixels::U16(px16.to_vec()));
        let d = decode(golden8).unwrap();
        assert_eq!(d.pixels, PgmPixels::U8(vec![1, 2, 3, 4, 5, 6]));
    }

    #[test]
    fn round_trips_with_comments_and_stride() {
        let d8: Vec<u8> = (0..12).map(|i| i * 20).collect();
        let mut bytes = encode_u8(4, 3, &d8).unwrap();
        // A comment after the magic, as GIMP and ImageMagick write one.
        bytes.splice(2..2, b"\n# made by a test".iter().copied());
        let h = parse_header(&bytes).unwrap();
        assert_eq!((h.width_px, h.height_px, h.bit_depth()), (4, 3, 8));
        // Into a buffer with a wider stride: padding stays untouched.
        let mut dst = [7u8; 5 * 3];
        decode_into(&bytes, &h, SamplesMut::U8(&mut dst), 5).unwrap();
        assert_eq!(&dst[5..9], &d8[4..8]);
        assert_eq!(dst[4], 7);
        let d16: Vec<u16> = (0..6).map(|i| i * 200 + 3).collect();
        let bytes = encode_u16(3, 2, 10, &d16).unwrap();
        assert!(bytes.starts_with(b"P5\n3 2\n1023\n"));
        assert_eq!(decode(&bytes).unwrap().pixels, PgmPixels::U16(d16));
    }

    #[test]
    fn bad_input_is_named() {
        let e = |b: &[u8]| decode(b).unwrap_err().to_string();
        assert!(e(b"P2\n1 1\n255\n0").contains("P5"));
        assert!(e(b"P5\n2 2\n255\n\x01\x02").contains("13 bytes, header needs 15"));
        assert!(e(b"P5\n2 x\n255\n").contains("height `x`"));
        assert!(e(b"P5\n2 2\n70000\n").contains("maxval outside"));
        assert!(e(b"P5\n2 2\n255").contains("truncated"));
        assert!(decode(b"P5\n# c\n1 1\n255\n\x09").is_ok());
        assert!(encode_u8(2, 2, &[0; 3]).is_err());
        // A 16-bit file into an 8-bit buffer, and the sample type not matching the bit depth.
        let f = encode_u16(1, 1, 12, &[5]).unwrap();
        let h = parse_header(&f).unwrap();
        assert!(
            decode_into(&f, &h, SamplesMut::U8(&mut [0]), 1)
                .unwrap_err()
                .to_string()
                .contains("2-byte samples")
        );
        assert!(
            encode_u16(1, 1, 8, &[5])
                .unwrap_err()
                .to_string()
                .contains("8-bit samples")
        );
        assert!(encode_u8(1, 1, &[5]).is_ok());
    }
}
