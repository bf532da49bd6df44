//! Loose-LED stream records (docs/stream-protocol.md, "Loose LEDs"): golden bytes and text,
//! round trips, refusals.

mod common;

use common::{assert_corruption_refused, assert_golden_frame, golden_position};
use irtrack_core::camera::RigidTransform;
use irtrack_core::pose6d::LooseLed;
use irtrack_core::stream::{LOOSE_BINARY_FRAME_LEN, LooseRecord, ToolRecord, TrackStatus};

fn led7() -> LooseRecord {
    LooseRecord {
        loose_id: 7,
        loose_count: 2,
        frames_tracked: 120,
        record: golden_position(None),
    }
}

/// The golden frame, hex by field as laid out in the spec.
const GOLDEN_HEX: &[&str] = &[
    "49524c4c",         // magic "IRLL"
    "01",               // version 1
    "05",               // flags: position, world (no orientation)
    "6800",             // payload length 104
    "2a00000000000000", // frame 42
    "15cd853dfe9c9717", // capture_ts_ns
    "0000000000002940",
    "0000000000000ac0",
    "0000000000709740", // position 12.5, -3.25, 1500
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000", // orientation: always zero
    "000000000000c03f", // gap_mm 0.125
    "00",               // status ok
    "02",               // cameras_used
    "0000",             // reserved
    "e1100000",         // latency_us 4321
    "efbeadde",         // params_crc
    "07000000",         // loose_id 7
    "02",               // loose_count
    "000000",           // reserved
    "78000000",         // frames_tracked 120
];

#[test]
fn loose_record_binary_golden_bytes() {
    let b = led7().to_binary();
    assert_eq!(b.len(), LOOSE_BINARY_FRAME_LEN);
    assert_eq!(LOOSE_BINARY_FRAME_LEN, 116);
    // CRC-32/IEEE over bytes 0..112, little-endian; the constant was computed independently
    // with Python's zlib.crc32 over the golden bytes above.
    assert_golden_frame(&b, GOLDEN_HEX, "00b34cac");
    assert_eq!(LooseRecord::decode_binary(&b).unwrap(), led7());
}

#[test]
fn loose_record_ndjson_golden_text() {
    let line = led7().to_ndjson_line();
    assert_eq!(
        line,
        "{\"loose_id\":7,\"loose_count\":2,\"frames_tracked\":120,\"frame\":42,\
         \"capture_ts_ns\":1700000000123456789,\"position_mm\":[12.5,-3.25,1500],\
         \"orientation_wxyz\":null,\"gap_mm\":0.125,\"status\":\"ok\",\"cameras_used\":2,\
         \"world_frame\":true,\"latency_us\":4321,\"params_crc\":3735928559}\n"
    );
    assert_eq!(LooseRecord::from_ndjson_line(line.trim_end()).unwrap(), led7());
    // Not a tool record: a reader that tells records apart by key refuses it as one.
    let err = ToolRecord::from_ndjson_line(&line).unwrap_err().to_string();
    assert!(err.contains("tool"), "{err}");
}

#[test]
fn orientation_is_never_sent_and_refused_when_received() {
    let mut r = led7();
    r.record.orientation_wxyz = Some([1.0, 0.0, 0.0, 0.0]);
    // Encoders drop it.
    assert_eq!(r.to_binary(), led7().to_binary());
    assert_eq!(r.to_ndjson_line(), led7().to_ndjson_line());
    // Decoders refuse it.
    let line = led7()
        .to_ndjson_line()
        .replace("\"orientation_wxyz\":null", "\"orientation_wxyz\":[1,0,0,0]");
    let err = LooseRecord::from_ndjson_line(&line).unwrap_err().to_string();
    assert!(err.contains("orientation"), "{err}");
    let mut b = led7().to_binary();
    b[5] |= 0x02;
    let crc = irtrack_core::crc::crc32(&b[..112]);
    b[112..].copy_from_slice(&crc.to_le_bytes());
    let err = LooseRecord::decode_binary(&b).unwrap_err().to_string();
    assert!(err.contains("orientation"), "{err}");
}

#[test]
fn loose_record_refusals_name_the_problem() {
    // Each required key missing.
    let line = led7().to_ndjson_line();
    for key in ["loose_id", "loose_count", "frames_tracked"] {
        let start = line.find(&format!("\"{key}\"")).unwrap();
        let end = start + line[start..].find(',').unwrap() + 1;
        let cut = format!("{}{}", &line[..start], &line[end..]);
        let err = LooseRecord::from_ndjson_line(&cut).unwrap_err().to_string();
        assert!(err.contains(key), "{key}: {err}");
    }
    // A tool line or a main line is not a loose record.
    assert!(LooseRecord::from_ndjson_line(&led7().record.to_ndjson_line()).is_err());
    let b = led7().to_binary();
    // Every corrupted byte, and version 2, refused.
    assert_corruption_refused(&b, LooseRecord::decode_binary);
    // Neither of the other frames is a loose frame.
    assert!(LooseRecord::decode_binary(&led7().record.to_binary()).is_err());
    let tool = ToolRecord::new(0, 1, "probe4", led7().record).unwrap();
    assert!(LooseRecord::decode_binary(&tool.to_binary()).is_err());
    assert!(LooseRecord::decode_binary(&b[..115]).is_err());
    // Reserved bytes must be zero (CRC fixed so that the check behind it is reached).
    let mut r = b;
    r[106] = 1;
    let crc = irtrack_core::crc::crc32(&r[..112]);
    r[112..].copy_from_slice(&crc.to_le_bytes());
    let err = LooseRecord::decode_binary(&r).unwrap_err().to_string();
    assert!(err.contains("reserved"), "{err}");
}

#[test]
fn from_loose_led_moves_into_the_world_frame() {
    let led = LooseLed {
        id: 3,
        position_mm: [10.0, 20.0, 1000.0],
        gap_mm: 0.05,
        cameras: 2,
        frames_tracked: 9,
    };
    let r = LooseRecord::from_loose_led(5, 77, &led, None, 1);
    assert_eq!((r.loose_id, r.loose_count, r.frames_tracked), (3, 1, 9));
    assert_eq!(r.record.position_mm, Some([10.0, 20.0, 1000.0]));
    assert_eq!(
        (
            r.record.status,
            r.record.gap_mm,
            r.record.cameras_used,
            r.record.world_frame
        ),
        (TrackStatus::Ok, 0.05, 2, false)
    );
    assert_eq!(r.record.orientation_wxyz, None);
    // World = camera 0 turned 90° about x and shifted.
    let world = RigidTransform {
        r_row_major: [1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0],
        t_mm: [100.0, 0.0, 50.0],
    };
    let r = LooseRecord::from_loose_led(5, 77, &led, Some(&world), 1);
    let p = r.record.position_mm.unwrap();
    for (a, b) in p.iter().zip([110.0, -1000.0, 70.0]) {
        assert!((a - b).abs() < 1e-9, "{p:?}");
    }
    assert!(r.record.world_frame);
    assert_eq!(LooseRecord::decode_binary(&r.to_binary()).unwrap(), r);
}
