//! Per-tool stream records (core/src/stream.rs, `ToolRecord`): `IRTL` binary frames and
//! per-tool NDJSON lines never panic, and whatever decodes re-encodes stably (encode, decode,
//! encode gives the same bytes/text), in both framings.
//!
//! Modes (first byte): 0 NDJSON text; 1 a raw `IRTL` frame; 2 an `IRTL` frame whose CRC is
//! fixed up first, so that the fields behind the CRC check (flags, status, tool name) are
//! reached.
#![no_main]

use irtrack_core::crc::Crc32;
use irtrack_core::stream::{MAX_NDJSON_LINE, TOOL_BINARY_FRAME_LEN, ToolRecord};
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

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    match mode % 3 {
        0 => {
            let Ok(text) = std::str::from_utf8(rest) else {
                return;
            };
            if let Ok(rec) = ToolRecord::from_ndjson_line(text) {
                check_ndjson_record(&rec);
            }
        }
        1 => check_binary(rest),
        _ => {
            let mut frame = [0u8; TOOL_BINARY_FRAME_LEN];
            let n = rest.len().min(TOOL_BINARY_FRAME_LEN);
            frame[..n].copy_from_slice(&rest[..n]);
            let end = TOOL_BINARY_FRAME_LEN - 4;
            let mut c = Crc32::new();
            c.update(&frame[..end]);
            frame[end..].copy_from_slice(&c.finish().to_le_bytes());
            check_binary(&frame);
        }
    }
});
