//! Per-tool stream records (docs/stream-protocol.md, "Per-tool records"): golden bytes and
//! text, round trips, refusals.

mod common;

use common::{assert_corruption_refused, assert_golden_frame, golden_position};
use irtrack_core::stream::{PositionRecord, TOOL_BINARY_FRAME_LEN, ToolRecord};

fn wing4() -> ToolRecord {
    ToolRecord::new(2, 3, "wing4", golden_position(Some([1.0, 0.0, 0.0, 0.0]))).unwrap()
}

/// The golden frame, hex by field as laid out in the spec.
const GOLDEN_HEX: &[&str] = &[
    "4952544c",         // magic "IRTL"
    "01",               // version 1
    "07",               // flags: position, orientation, world
    "8000",             // payload length 128
    "2a00000000000000", // frame 42
    "15cd853dfe9c9717", // capture_ts_ns
    "0000000000002940",
    "0000000000000ac0",
    "0000000000709740", // position 12.5, -3.25, 1500
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",                                                 // w x y z
    "000000000000c03f",                                                 // gap_mm 0.125
    "00",                                                               // status ok
    "02",                                                               // cameras_used
    "0000",                                                             // reserved
    "e1100000",                                                         // latency_us 4321
    "efbeadde",                                                         // params_crc
    "02",                                                               // tool_id
    "03",                                                               // tool_count
    "05",                                                               // name length
    "00",                                                               // reserved
    "77696e6734000000000000000000000000000000000000000000000000000000", // "wing4", zero padded to 32
];

#[test]
fn tool_record_binary_golden_bytes() {
    let b = wing4().to_binary();
    assert_eq!(b.len(), TOOL_BINARY_FRAME_LEN);
    assert_eq!(TOOL_BINARY_FRAME_LEN, 140);
    // CRC-32/IEEE over bytes 0..136, little-endian.
    assert_golden_frame(&b, GOLDEN_HEX, "7324283a");
    assert_eq!(ToolRecord::decode_binary(&b).unwrap(), wing4());
}

#[test]
fn tool_record_ndjson_golden_text() {
    let line = wing4().to_ndjson_line();
    assert_eq!(
        line,
        "{\"tool_id\":2,\"tool\":\"wing4\",\"tool_count\":3,\"frame\":42,\
         \"capture_ts_ns\":1700000000123456789,\"position_mm\":[12.5,-3.25,1500],\
         \"orientation_wxyz\":[1,0,0,0],\"gap_mm\":0.125,\"status\":\"ok\",\"cameras_used\":2,\
         \"world_frame\":true,\"latency_us\":4321,\"params_crc\":3735928559}\n"
    );
    let back = ToolRecord::from_ndjson_line(line.trim_end()).unwrap();
    assert_eq!(back, wing4());
    assert_eq!(back.name(), "wing4");
    // A reader of plain position records still reads the line (unknown keys are ignored).
    assert_eq!(PositionRecord::from_ndjson_line(&line).unwrap(), wing4().record);
}

#[test]
fn tool_record_refusals_name_the_problem() {
    let r = wing4().record;
    for bad in ["", "has\"quote", "back\\slash", "tab\there", "ä", &"x".repeat(33)] {
        assert!(ToolRecord::new(0, 1, bad, r).is_err(), "{bad:?} accepted");
    }
    assert!(ToolRecord::new(0, 1, &"x".repeat(32), r).is_ok());
    let plain = r.to_ndjson_line();
    let err = ToolRecord::from_ndjson_line(&plain).unwrap_err().to_string();
    assert!(err.contains("tool"), "{err}");
    // Every corrupted byte, and version 2, refused.
    assert_corruption_refused(&wing4().to_binary(), ToolRecord::decode_binary);
    // A main-record frame is not a tool frame.
    assert!(ToolRecord::decode_binary(&r.to_binary()).is_err());
}
