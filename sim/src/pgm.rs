//! Binary PGM (P5) frames: 8-bit (maxval 255) and 16-bit big-endian (e.g. maxval 1023).

use std::io::Write;

use crate::SimError;

/// Pixels of a decoded PGM.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PgmPixels {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

/// A decoded PGM image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pgm {
    pub width_px: u32,
    pub height_px: u32,
    pub maxval: u16,
    pub pixels: PgmPixels,
}

/// Writes an 8-bit PGM.
pub fn write_pgm_u8(mut w: impl Write, width_px: u32, height_px: u32, data: &[u8]) -> Result<(), SimError> {
    check_len(width_px, height_px, data.len())?;
    write!(w, "P5\n{width_px} {height_px}\n255\n")?;
    w.write_all(data)?;
    Ok(())
}

/// Writes a 16-bit PGM with the given maxval (1023 for 10-bit data), samples big-endian.
pub fn write_pgm_u16(
    mut w: impl Write,
    width_px: u32,
    height_px: u32,
    maxval: u16,
    data: &[u16],
) -> Result<(), SimError> {
    check_len(width_px, height_px, data.len())?;
    if maxval < 256 {
        return Err(SimError::Pgm {
            reason: format!("16-bit PGM needs maxval >= 256, got {maxval}"),
        });
    }
    write!(w, "P5\n{width_px} {height_px}\n{maxval}\n")?;
    let mut bytes = Vec::with_capacity(data.len() * 2);
    for v in data {
        bytes.extend_from_slice(&v.to_be_bytes());
    }
    w.write_all(&bytes)?;
    Ok(())
}

fn check_len(width_px: u32, height_px: u32, len: usize) -> Result<(), SimError> {
    let needed = width_px as usize * height_px as usize;
    if needed != len || needed == 0 {
        return Err(SimError::Pgm {
            reason: format!("{width_px}x{height_px} image needs {needed} samples, got {len}"),
        });
    }
    Ok(())
}

/// Decodes a binary PGM.
pub fn read_pgm(bytes: &[u8]) -> Result<Pgm, SimError> {
    let bad = |reason: String| SimError::Pgm { reason };
    let mut pos = 0usize;
    let token = |pos: &mut usize| -> Result<String, SimError> {
        // Skip whitespace and comments.
        loop {
            match bytes.get(*pos) {
                Some(b) if b.is_ascii_whitespace() => *pos += 1,
                Some(b'#') => {
                    while bytes.get(*pos).is_some_and(|b| *b != b'\n') {
                        *pos += 1;
                    }
                }
                Some(_) => break,
                None => return Err(bad("header truncated".into())),
            }
        }
        let start = *pos;
        while bytes.get(*pos).is_some_and(|b| !b.is_ascii_whitespace()) {
            *pos += 1;
        }
        Ok(String::from_utf8_lossy(&bytes[start..*pos]).into_owned())
    };
    let magic = token(&mut pos)?;
    if magic != "P5" {
        return Err(bad(format!("magic `{magic}`, expected P5 (binary greymap)")));
    }
    let num = |what: &str, pos: &mut usize| -> Result<u32, SimError> {
        let t = token(pos)?;
        t.parse::<u32>()
            .map_err(|_| bad(format!("{what} `{t}` is not a number")))
    };
    let width_px = num("width", &mut pos)?;
    let height_px = num("height", &mut pos)?;
    let maxval = num("maxval", &mut pos)?;
    if width_px == 0 || height_px == 0 || maxval == 0 || maxval > 65535 {
        return Err(bad(format!("bad header {width_px}x{height_px} maxval {maxval}")));
    }
    // Exactly one whitespace byte separates the header from the samples.
    pos += 1;
    let n = width_px as usize * height_px as usize;
    let body = bytes.get(pos..).unwrap_or(&[]);
    let pixels = if maxval < 256 {
        if body.len() < n {
            return Err(bad(format!("{} sample bytes, need {n}", body.len())));
        }
        PgmPixels::U8(body[..n].to_vec())
    } else {
        if body.len() < 2 * n {
            return Err(bad(format!("{} sample bytes, need {}", body.len(), 2 * n)));
        }
        PgmPixels::U16(
            body[..2 * n]
                .chunks_exact(2)
                .map(|c| u16::from_be_bytes([c[0], c[1]]))
                .collect(),
        )
    };
    Ok(Pgm {
        width_px,
        height_px,
        maxval: maxval as u16,
        pixels,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_8_and_16_bit() {
        let d8: Vec<u8> = (0..12).map(|i| i * 20).collect();
        let mut buf = Vec::new();
        write_pgm_u8(&mut buf, 4, 3, &d8).unwrap();
        let p = read_pgm(&buf).unwrap();
        assert_eq!((p.width_px, p.height_px, p.maxval), (4, 3, 255));
        assert_eq!(p.pixels, PgmPixels::U8(d8));
        let d16: Vec<u16> = (0..6).map(|i| i * 200 + 3).collect();
        let mut buf = Vec::new();
        write_pgm_u16(&mut buf, 3, 2, 1023, &d16).unwrap();
        assert!(buf.starts_with(b"P5\n3 2\n1023\n"));
        assert_eq!(read_pgm(&buf).unwrap().pixels, PgmPixels::U16(d16));
    }

    #[test]
    fn malformed_files_are_named_errors() {
        assert!(
            read_pgm(b"P2\n1 1\n255\n0")
                .unwrap_err()
                .to_string()
                .contains("P5")
        );
        assert!(
            read_pgm(b"P5\n2 2\n255\n\x01\x02")
                .unwrap_err()
                .to_string()
                .contains("need 4")
        );
        assert!(
            read_pgm(b"P5\n2 x\n255\n")
                .unwrap_err()
                .to_string()
                .contains("height")
        );
        assert!(read_pgm(b"P5\n# c\n1 1\n255\n\x09").is_ok());
        assert!(write_pgm_u8(Vec::new(), 2, 2, &[0; 3]).is_err());
    }
}
