//! Position stream decoders (core/src/stream.rs): NDJSON lines and binary frames never panic,
//! and whatever decodes re-encodes stably (encode, decode, encode gives the same text/bytes;
//! NaN gaps make direct record comparison meaningless, so encodings are compared).
//!
//! Modes (first byte): 0 NDJSON text; 1 a raw binary frame; 2 a binary frame whose CRC is
//! fixed up first, so that the fields behind the CRC check are reached.
#![no_main]

use irtrack_core::crc::Crc32;
use irtrack_core::stream::{BINARY_FRAME_LEN, MAX_NDJSON_LINE, PositionRecord};
use libfuzzer_sys::fuzz_target;

fn check_binary(frame: &[u8]) {
    let Ok(rec) = PositionRecord::decode_binary(frame) else {
        return;
    };
    let enc = rec.to_binary();
    let again = PositionRecord::decode_binary(&enc).expect("re-encoded frame must decode");
    assert_eq!(again.to_binary(), enc);
    // The same record must also survive the NDJSON framing.
    check_ndjson_record(&rec);
}

fn check_ndjson_record(rec: &PositionRecord) {
    let line = rec.to_ndjson_line();
    assert!(
        line.len() <= MAX_NDJSON_LINE,
        "encoder wrote a {}-byte line, over MAX_NDJSON_LINE: {line}",
        line.len()
    );
    let again = PositionRecord::from_ndjson_line(&line).expect("encoded line must parse");
    assert_eq!(again.to_ndjson_line(), line);
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    match mode % 3 {
        0 => {
            let Ok(text) = std::str::from_utf8(rest) else {
                return;
            };
            if let Ok(rec) = PositionRecord::from_ndjson_line(text) {
                check_ndjson_record(&rec);
            }
        }
        1 => check_binary(rest),
        _ => {
            let mut frame = [0u8; BINARY_FRAME_LEN];
            let n = rest.len().min(BINARY_FRAME_LEN);
            frame[..n].copy_from_slice(&rest[..n]);
            let mut c = Crc32::new();
            c.update(&frame[..100]);
            frame[100..104].copy_from_slice(&c.finish().to_le_bytes());
            check_binary(&frame);
        }
    }
});
