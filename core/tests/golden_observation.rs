//! Observation message (docs/observation-protocol.md): golden bytes, named errors for bad
//! input, the solver's gate, round trips.

use irtrack_core::Error;
use irtrack_core::observation::{
    CameraPlace, MAX_OBS_BLOBS, MAX_OBS_LEN, ObsBlob, ObsClock, ObsHeader, ObservationGate,
    ObservationProblem, decode, encode, encoded_len,
};
use proptest::prelude::*;

fn hex(parts: &[&str]) -> Vec<u8> {
    let s: String = parts.concat();
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

fn golden_header() -> ObsHeader<'static> {
    ObsHeader {
        rig: "cell1",
        board: "b1",
        camera: 1,
        sequence: 7,
        trigger_count: None,
        capture_ts_ns: 1_000_000_000,
        clock: ObsClock::Realtime,
        exposure_us: 500,
        dropped: 2,
        send_delay_us: 1500,
    }
}

fn golden_blob() -> ObsBlob {
    ObsBlob {
        x_px: 320.5,
        y_px: 240.25,
        area_px: 12,
        peak_dn: 250,
        roundness: 1.0,
        touches_frame_edge: false,
        touches_roi_edge: false,
        saturated: false,
    }
}

/// Bytes checked independently with Python's `struct` and `zlib.crc32`.
fn golden_bytes() -> Vec<u8> {
    hex(&[
        "494f",             // magic "IO"
        "01",               // version 1
        "00",               // flags: no trigger counter
        "01",               // clock 1 = realtime
        "01",               // camera 1 of its board
        "05",               // rig id length
        "02",               // board id length
        "0700000000000000", // sequence 7
        "00ca9a3b00000000", // capture 1 000 000 000 ns
        "f4010000",         // exposure 500 µs
        "02000000",         // 2 frames dropped
        "dc050000",         // capture to send 1500 µs
        "63656c6c31",       // "cell1"
        "6231",             // "b1"
        "01",               // one blob
        "0040a043",         // x 320.5 (f32)
        "00407043",         // y 240.25
        "0c00",             // area 12 px
        "fa00",             // peak 250 DN
        "ffff",             // roundness 1.0
        "00",               // blob flags
        "00",               // reserved
        "7ac91bb1",         // CRC-32 of all bytes before
    ])
}

/// The same with a trigger counter (42) and no blobs.
fn golden_triggered_bytes() -> Vec<u8> {
    hex(&[
        "494f01",
        "01",
        "01",
        "00",
        "05",
        "02",
        "0800000000000000", // sequence 8
        "206ba23b00000000", // 1 000 500 000 ns
        "f4010000",
        "00000000",
        "dc050000",
        "2a00000000000000", // trigger counter 42
        "63656c6c31",
        "6231",
        "00",       // no blobs
        "c35d2756", // CRC-32
    ])
}

#[test]
fn golden_observation_encodes_and_decodes() {
    let mut buf = [0u8; MAX_OBS_LEN];
    let n = encode(&golden_header(), &[golden_blob()], &mut buf).unwrap();
    assert_eq!(buf[..n], golden_bytes()[..]);
    assert_eq!(n, 64);
    assert_eq!(encoded_len(&golden_header(), 1), 64);
    let bytes = golden_bytes();
    let obs = decode(&bytes).unwrap();
    assert_eq!(obs.header, golden_header());
    assert_eq!(obs.blobs().collect::<Vec<_>>(), vec![golden_blob()]);
}

#[test]
fn golden_triggered_observation() {
    let h = ObsHeader {
        camera: 0,
        sequence: 8,
        trigger_count: Some(42),
        capture_ts_ns: 1_000_500_000,
        dropped: 0,
        ..golden_header()
    };
    let mut buf = [0u8; MAX_OBS_LEN];
    let n = encode(&h, &[], &mut buf).unwrap();
    assert_eq!(buf[..n], golden_triggered_bytes()[..]);
    let obs = decode(&buf[..n]).unwrap();
    assert_eq!(obs.header, h);
    assert_eq!(obs.blob_count(), 0);
}

fn problem(r: Result<impl std::fmt::Debug, Error>) -> ObservationProblem {
    match r {
        Err(Error::Observation { problem }) => problem,
        other => panic!("expected an observation error, got {other:?}"),
    }
}

/// Re-seals `bytes` with a correct CRC after an edit, so that the check after the CRC is hit.
fn reseal(mut bytes: Vec<u8>) -> Vec<u8> {
    let n = bytes.len() - 4;
    let crc = irtrack_core::crc::crc32(&bytes[..n]);
    bytes[n..].copy_from_slice(&crc.to_le_bytes());
    bytes
}

#[test]
fn bad_input_names_the_problem() {
    let g = golden_bytes();
    assert_eq!(
        problem(decode(&g[..20])),
        ObservationProblem::Truncated { needed: 36, got: 20 }
    );
    assert_eq!(
        problem(decode(&g[..50])),
        ObservationProblem::Truncated { needed: 64, got: 50 }
    );
    let mut v = g.clone();
    v[2] = 2;
    assert_eq!(
        problem(decode(&v)),
        ObservationProblem::UnsupportedVersion {
            found: 2,
            supported: 1
        }
    );
    let mut v = g.clone();
    v[0] = b'X';
    assert!(matches!(problem(decode(&v)), ObservationProblem::BadMagic { .. }));
    let mut v = g.clone();
    v[3] = 0x80;
    assert_eq!(
        problem(decode(&v)),
        ObservationProblem::UnknownFlags { flags: 0x80 }
    );
    let mut v = g.clone();
    v[4] = 9;
    assert_eq!(problem(decode(&v)), ObservationProblem::UnknownClock { code: 9 });
    let mut v = g.clone();
    v[44] ^= 1; // a bit of the first blob's x
    assert!(matches!(problem(decode(&v)), ObservationProblem::BadCrc { .. }));
    let mut v = g.clone();
    v.push(0);
    assert_eq!(
        problem(decode(&v)),
        ObservationProblem::TrailingBytes { extra: 1 }
    );
    let mut v = g.clone();
    v[36] = 0xff; // rig id no longer UTF-8
    assert_eq!(
        problem(decode(&reseal(v))),
        ObservationProblem::BadId { what: "rig", len: 5 }
    );
    let mut v = g.clone();
    v[48..52].copy_from_slice(&f32::NAN.to_le_bytes()); // y of blob 0
    assert_eq!(
        problem(decode(&reseal(v))),
        ObservationProblem::BadBlob { index: 0 }
    );
    let blobs = vec![golden_blob(); MAX_OBS_BLOBS + 1];
    let mut buf = vec![0u8; 2 * MAX_OBS_LEN];
    assert_eq!(
        problem(encode(&golden_header(), &blobs, &mut buf)),
        ObservationProblem::TooManyBlobs { count: 33, max: 32 }
    );
    let mut small = [0u8; 63];
    assert_eq!(
        problem(encode(&golden_header(), &[golden_blob()], &mut small)),
        ObservationProblem::BufferTooSmall { needed: 64, have: 63 }
    );
    // The message names the problem in words.
    let msg = decode(&g[..20]).unwrap_err().to_string();
    assert!(msg.contains("truncated") && msg.contains("36"), "{msg}");
}

fn gate() -> ObservationGate {
    let places = [
        CameraPlace {
            board: "b0".into(),
            local_index: 0,
        },
        CameraPlace {
            board: "b0".into(),
            local_index: 1,
        },
        CameraPlace {
            board: "b1".into(),
            local_index: 0,
        },
        CameraPlace {
            board: "b1".into(),
            local_index: 1,
        },
    ];
    ObservationGate::new("cell1", &places, ObsClock::Realtime, 50_000_000).unwrap()
}

#[test]
fn gate_maps_cameras_and_refuses_bad_ones() {
    let mut g = gate();
    let bytes = golden_bytes();
    let obs = decode(&bytes).unwrap();
    // b1 camera 1 is the rig's camera 3.
    assert_eq!(g.check(&obs, 1_010_000_000).unwrap(), 3);
    assert_eq!(
        problem(g.check(&obs, 1_010_000_000)),
        ObservationProblem::DuplicateSequence {
            camera: 3,
            sequence: 7,
            last: 7
        }
    );
    g.reset_camera(3);
    assert_eq!(g.check(&obs, 1_010_000_000).unwrap(), 3);

    let mut buf = [0u8; MAX_OBS_LEN];
    let other_rig = ObsHeader {
        rig: "cell2",
        sequence: 9,
        ..golden_header()
    };
    let n = encode(&other_rig, &[], &mut buf).unwrap();
    assert_eq!(
        problem(g.check(&decode(&buf[..n]).unwrap(), 1_000_000_000)),
        ObservationProblem::UnknownRig
    );

    let unknown = ObsHeader {
        board: "b9",
        sequence: 9,
        ..golden_header()
    };
    let n = encode(&unknown, &[], &mut buf).unwrap();
    assert_eq!(
        problem(g.check(&decode(&buf[..n]).unwrap(), 1_000_000_000)),
        ObservationProblem::UnknownCamera { local_index: 1 }
    );

    let late = ObsHeader {
        sequence: 10,
        ..golden_header()
    };
    let n = encode(&late, &[], &mut buf).unwrap();
    // One second after capture: far beyond 50 ms.
    assert_eq!(
        problem(g.check(&decode(&buf[..n]).unwrap(), 2_000_000_000)),
        ObservationProblem::TimestampOff {
            camera: 3,
            offset_ns: -1_000_000_000,
            limit_ns: 50_000_000
        }
    );
    // The refused observation did not advance the sequence: the same one, in time, passes.
    assert_eq!(g.check(&decode(&buf[..n]).unwrap(), 1_000_000_000).unwrap(), 3);

    let mono = ObsHeader {
        sequence: 11,
        clock: ObsClock::Monotonic,
        ..golden_header()
    };
    let n = encode(&mono, &[], &mut buf).unwrap();
    assert_eq!(
        problem(g.check(&decode(&buf[..n]).unwrap(), 1_000_000_000)),
        ObservationProblem::WrongClock {
            found: ObsClock::Monotonic,
            expected: ObsClock::Realtime
        }
    );
}

#[test]
fn problem_codes_are_distinct() {
    let mut codes = ObservationProblem::CODES.to_vec();
    codes.sort();
    codes.dedup();
    assert_eq!(codes.len(), ObservationProblem::CODES.len());
    assert_eq!(ObservationProblem::UnknownRig.code(), "unknown_rig");
}

proptest! {
    #[test]
    fn round_trip(
        seq in any::<u64>(), ts in any::<u64>(), trig in proptest::option::of(any::<u64>()),
        cam in any::<u8>(), exp in any::<u32>(), drop in any::<u32>(),
        blobs in proptest::collection::vec(
            (-1e4f32..1e4, -1e4f32..1e4, any::<u16>(), any::<u16>(), 0u16..=65535, 0u8..8), 0..=MAX_OBS_BLOBS),
    ) {
        let h = ObsHeader { rig: "r", board: "board-x", camera: cam, sequence: seq, trigger_count: trig,
            capture_ts_ns: ts, clock: ObsClock::Tai, exposure_us: exp, dropped: drop, send_delay_us: exp / 3 };
        let blobs: Vec<ObsBlob> = blobs.into_iter().map(|(x, y, a, p, q, f)| ObsBlob {
            x_px: x, y_px: y, area_px: a, peak_dn: p, roundness: f32::from(q) / 65_535.0,
            touches_frame_edge: f & 1 != 0, touches_roi_edge: f & 2 != 0, saturated: f & 4 != 0,
        }).collect();
        let mut buf = [0u8; MAX_OBS_LEN];
        let n = encode(&h, &blobs, &mut buf).unwrap();
        let obs = decode(&buf[..n]).unwrap();
        prop_assert_eq!(obs.header, h);
        prop_assert_eq!(obs.blobs().collect::<Vec<_>>(), blobs);
    }

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
        let _ = decode(&bytes);
    }
}
