//! Checks shared by the golden-record tests of the stream's extra record kinds (per-tool and
//! loose-LED records): they wrap the same position record and frame it the same way (magic,
//! version, body, CRC-32 trailer).
#![allow(dead_code)]

use irtrack_core::Error;
use irtrack_core::stream::{PositionRecord, TrackStatus};

/// The position record inside the golden frames (frame 42, position 12.5, −3.25, 1500 mm in the
/// world frame, …); `orientation_wxyz` differs between the record kinds.
pub fn golden_position(orientation_wxyz: Option<[f64; 4]>) -> PositionRecord {
    PositionRecord {
        frame: 42,
        capture_ts_ns: 1_700_000_000_123_456_789,
        position_mm: Some([12.5, -3.25, 1500.0]),
        orientation_wxyz,
        gap_mm: 0.125,
        status: TrackStatus::Ok,
        cameras_used: 2,
        world_frame: true,
        latency_us: 4321,
        params_crc: 0xDEAD_BEEF,
    }
}

/// Lower-case hex of `bytes`.
pub fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A frame is its golden body (`golden_hex`, by field) followed by CRC-32/IEEE of the body,
/// little-endian, equal to `crc_hex` (computed independently with Python's zlib.crc32).
pub fn assert_golden_frame(frame: &[u8], golden_hex: &[&str], crc_hex: &str) {
    let body_len = frame.len() - 4;
    assert_eq!(hex(&frame[..body_len]), golden_hex.concat());
    assert_eq!(
        frame[body_len..],
        irtrack_core::crc::crc32(&frame[..body_len]).to_le_bytes()
    );
    assert_eq!(
        hex(&frame[body_len..]),
        crc_hex,
        "CRC of the golden frame (zlib.crc32 agrees)"
    );
}

/// Flipping bit 6 of any one byte of `frame` makes `decode` fail with a protocol error; a
/// version byte (offset 4) of 2 is refused by name.
pub fn assert_corruption_refused<T: std::fmt::Debug>(
    frame: &[u8],
    decode: impl Fn(&[u8]) -> Result<T, Error>,
) {
    for i in 0..frame.len() {
        let mut c = frame.to_vec();
        c[i] ^= 0x40;
        assert!(
            matches!(decode(&c), Err(Error::Protocol { .. })),
            "byte {i} corruption undetected"
        );
    }
    let mut v = frame.to_vec();
    v[4] = 2;
    let err = decode(&v).unwrap_err().to_string();
    assert!(err.contains("version 2"), "{err}");
}
