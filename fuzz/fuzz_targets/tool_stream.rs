//! Per-tool and loose-LED stream records (core/src/stream.rs, `ToolRecord`, `LooseRecord`):
//! `IRTL`/`IRLL` binary frames and their NDJSON lines never panic, and whatever decodes
//! re-encodes stably (encode, decode, encode gives the same bytes/text), in both framings.
//!
//! Modes (first byte, mod 6): 0 tool NDJSON text; 1 a raw `IRTL` frame; 2 an `IRTL` frame whose
//! CRC is fixed up first, so that the fields behind the CRC check (flags, status, tool name) are
//! reached; 3, 4, 5 the same for loose-LED records (`IRLL`).
#![no_main]

use irtrack_core::crc::Crc32;
use irtrack_core::stream::{
    LOOSE_BINARY_FRAME_LEN, LooseRecord, MAX_NDJSON_LINE, TOOL_BINARY_FRAME_LEN, ToolRecord,
};
use libfuzzer_sys::fuzz_target;

fn check_binary(frame: &[u8]) {
    let Ok(rec) = ToolRecord::decode_binary(frame) else {
        return;
    };
    let enc = rec.to_binary();
    let again = ToolRecord::decode_binary(&enc).expect("re-encoded frame must decode");
    assert_eq!(again.to_binary(), enc);
    check_ndjson_record(&rec);
}

fn check_ndjson_record(rec: &ToolRecord) {
    let line = rec.to_ndjson_line();
    assert!(
        line.len() <= MAX_NDJSON_LINE,
        "encoder wrote a {}-byte line, over MAX_NDJSON_LINE: {line}",
        line.len()
    );
    let again = ToolRecord::from_ndjson_line(&line).expect("encoded line must parse");
    assert_eq!(again.to_ndjson_line(), line);
    assert_eq!((again.tool_id, again.tool_count, again.name()), (rec.tool_id, rec.tool_count, rec.name()));
}

fn check_loose_binary(frame: &[u8]) {
    let Ok(rec) = LooseRecord::decode_binary(frame) else {
        return;
    };
    assert!(rec.record.orientation_wxyz.is_none(), "a loose frame decoded with an orientation");
    let enc = rec.to_binary();
    let again = LooseRecord::decode_binary(&enc).expect("re-encoded loose frame must decode");
    assert_eq!(again.to_binary(), enc);
    check_loose_ndjson_record(&rec);
}

fn check_loose_ndjson_record(rec: &LooseRecord) {
    let line = rec.to_ndjson_line();
    assert!(
        line.len() <= MAX_NDJSON_LINE,
        "encoder wrote a {}-byte loose line, over MAX_NDJSON_LINE: {line}",
        line.len()
    );
    let again = LooseRecord::from_ndjson_line(&line).expect("encoded loose line must parse");
    assert_eq!(again.to_ndjson_line(), line);
    assert_eq!(
        (again.loose_id, again.loose_count, again.frames_tracked),
        (rec.loose_id, rec.loose_count, rec.frames_tracked)
    );
    // The text form carries the binary form's fields: both encode the same record.
    let frame = rec.to_binary();
    assert_eq!(LooseRecord::decode_binary(&frame).expect("encoded loose frame must decode").to_ndjson_line(), line);
}

/// `rest` copied into a frame of `N` bytes whose CRC is then fixed up.
fn crc_fixed<const N: usize>(rest: &[u8]) -> [u8; N] {
    let mut frame = [0u8; N];
    let n = rest.len().min(N);
    frame[..n].copy_from_slice(&rest[..n]);
    let end = N - 4;
    let mut c = Crc32::new();
    c.update(&frame[..end]);
    frame[end..].copy_from_slice(&c.finish().to_le_bytes());
    frame
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    match mode % 6 {
        0 => {
            let Ok(text) = std::str::from_utf8(rest) else {
                return;
            };
            if let Ok(rec) = ToolRecord::from_ndjson_line(text) {
                check_ndjson_record(&rec);
            }
        }
        1 => check_binary(rest),
        2 => check_binary(&crc_fixed::<TOOL_BINARY_FRAME_LEN>(rest)),
        3 => {
            let Ok(text) = std::str::from_utf8(rest) else {
                return;
            };
            if let Ok(rec) = LooseRecord::from_ndjson_line(text) {
                check_loose_ndjson_record(&rec);
            }
        }
        4 => check_loose_binary(rest),
        _ => check_loose_binary(&crc_fixed::<LOOSE_BINARY_FRAME_LEN>(rest)),
    }
});
