//! Regression tests for what the cargo-fuzz targets in fuzz/ found (docs/fuzzing.md), plus a
//! replay of the committed seed corpora so the decoders' contracts are checked on every
//! `cargo test`, not only when someone fuzzes.

use std::path::{Path, PathBuf};

use irtrack_core::Error;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::crc::Crc32;
use irtrack_core::param_wire::{RejectCode, Verdict};
use irtrack_core::params::{BLOB_HEADER_LEN, CameraParams, RigParams};
use irtrack_core::robot_proto::{RobotMsg, TrackerMsg};
use irtrack_core::stream::{MAX_NDJSON_LINE, PositionRecord, TrackStatus};

fn seeds(target: &str) -> Vec<(PathBuf, Vec<u8>)> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/seeds")
        .join(target);
    let mut out: Vec<_> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| {
            let p = e.unwrap().path();
            let bytes = std::fs::read(&p).unwrap();
            (p, bytes)
        })
        .collect();
    out.sort();
    assert!(!out.is_empty(), "no seeds in {}", dir.display());
    out
}

fn record(position_mm: [f64; 3], gap_mm: f64) -> PositionRecord {
    PositionRecord {
        frame: 42,
        capture_ts_ns: 4_433_230_883_192_818_965,
        position_mm: Some(position_mm),
        orientation_wxyz: Some([f64::MIN_POSITIVE, -5e-324, 1e-7, -0.5]),
        gap_mm,
        status: TrackStatus::Ok,
        cameras_used: 0,
        world_frame: false,
        latency_us: 512,
        params_crc: 4321,
    }
}

/// Fuzz finding F2 (stream target): values like 1.9e-300 were written as ~330 plain digits,
/// so a record decoded from a valid binary frame produced an NDJSON line over
/// MAX_NDJSON_LINE that every reader refuses.
#[test]
fn ndjson_line_of_extreme_magnitudes_stays_short_and_exact() {
    let rec = record([1.955_571_58e-300, -f64::MAX, 1e16], f64::MIN_POSITIVE);
    let line = rec.to_ndjson_line();
    assert!(line.len() <= MAX_NDJSON_LINE, "{} bytes: {line}", line.len());
    let back = PositionRecord::from_ndjson_line(&line).unwrap();
    // Exact bits, not approximately: the exponent form is still the shortest exact decimal.
    let bits = |r: &PositionRecord| {
        let p = r.position_mm.unwrap();
        let q = r.orientation_wxyz.unwrap();
        [p[0], p[1], p[2], q[0], q[1], q[2], q[3], r.gap_mm].map(f64::to_bits)
    };
    assert_eq!(bits(&back), bits(&rec));
    assert_eq!(back.to_ndjson_line(), line);
}

#[test]
fn ndjson_ordinary_values_keep_plain_decimals() {
    let mut rec = record([12.5, -3.25, 1500.0], 0.125);
    rec.orientation_wxyz = Some([1e-6, 9.5e15, -0.0, 1.0]);
    let line = rec.to_ndjson_line();
    assert!(line.contains("\"position_mm\":[12.5,-3.25,1500]"), "{line}");
    assert!(line.contains("\"gap_mm\":0.125"), "{line}");
    // Plain decimals inside [1e-6, 1e16), exponent form outside.
    assert!(line.contains("[0.000001,9500000000000000,-0,1]"), "{line}");
    rec.gap_mm = 1e-7;
    assert!(rec.to_ndjson_line().contains("\"gap_mm\":1e-7"));
}

/// Fuzz finding F3 (param_wire target): an unknown code is written back as `ERR UNKNOWN <raw>
/// ...`; reading that line took `UNKNOWN` for yet another unknown code, so every relay
/// prepended one more `UNKNOWN`.
#[test]
fn unknown_verdict_code_survives_relaying() {
    let v1 = Verdict::parse_line("ERR SOMETHING new code\n").unwrap();
    let line1 = v1.to_line();
    assert_eq!(line1, "ERR UNKNOWN SOMETHING new code\n");
    let v2 = Verdict::parse_line(&line1).unwrap();
    assert_eq!(v2, v1);
    assert_eq!(
        v2,
        Verdict::Rejected {
            code: RejectCode::Unknown,
            message: "SOMETHING new code".into()
        }
    );
}

/// Fuzz finding F4 (param_wire target): `OK` with a control character inside the rig id was
/// accepted, but `to_line` turns control characters into spaces, so the verdict could not be
/// written back as a parseable line.
#[test]
fn ok_verdict_with_control_character_in_rig_id_is_refused() {
    for line in ["OK g1J@OKIRPPxR\u{1f}x0\n", "OK rig\u{7f}1\n", "OK a\u{85}b\n"] {
        assert!(
            matches!(Verdict::parse_line(line), Err(Error::Protocol { .. })),
            "{line:?} accepted"
        );
    }
    assert_eq!(
        Verdict::parse_line("OK rig-1\n").unwrap(),
        Verdict::Accepted {
            rig_id: "rig-1".into()
        }
    );
}

fn small_rig() -> RigParams {
    let cam = |t_x_mm: f64| CameraParams {
        model: CameraModel {
            intrinsics: Intrinsics {
                fx_px: 500.0,
                fy_px: 500.0,
                cx_px: 319.5,
                cy_px: 239.5,
            },
            distortion: Distortion::NONE,
            image_size: ImageSize {
                width_px: 640,
                height_px: 480,
            },
        },
        cam_from_cam0: RigidTransform {
            t_mm: [t_x_mm, 0.0, 0.0],
            ..RigidTransform::IDENTITY
        },
    };
    RigParams {
        rig_id: "golden1".into(),
        created_unix_s: 1_700_000_000,
        cameras: vec![cam(0.0), cam(-100.0)],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Header + body with a correct length and CRC (what the fuzz target's body mode builds).
fn wrap(body: &[u8]) -> Vec<u8> {
    let mut out = b"IRPB\x01\x00\x00\x00".to_vec();
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    let mut c = Crc32::new();
    c.update(&out);
    c.update(body);
    out.extend_from_slice(&c.finish().to_le_bytes());
    out.extend_from_slice(body);
    out
}

/// The blob body with the rig id's length varint (first body byte, 7) written over-long as
/// `0x87 0x00`, the kind of input the param_blob target found (finding F1).
fn overlong_blob() -> Vec<u8> {
    let canonical = small_rig().to_blob().unwrap();
    let body = &canonical[BLOB_HEADER_LEN..];
    assert_eq!(body[0], 7);
    let mut overlong = vec![0x87, 0x00];
    overlong.extend_from_slice(&body[1..]);
    wrap(&overlong)
}

/// Finding F1: whatever an over-long varint does, it must never be read as a different value.
#[test]
fn overlong_varint_blob_never_decodes_to_a_different_rig() {
    match RigParams::from_blob(&overlong_blob()) {
        Ok(rig) => assert_eq!(rig, small_rig()),
        Err(e) => assert!(matches!(e, Error::BlobBody { .. }), "{e:?}"),
    }
}

/// Finding F1 (fixed): the blob format promises one encoding per parameter set (its CRC is
/// reported as `params_crc`), but postcard accepts over-long varints, so byte-different blobs
/// with different CRCs would decode to the same rig; `from_blob` refuses them.
#[test]
fn overlong_varint_blob_is_refused() {
    assert!(matches!(
        RigParams::from_blob(&overlong_blob()),
        Err(Error::BlobBody { .. })
    ));
}

/// The committed param_blob seeds: the golden blob decodes in both modes, and every accepted
/// seed re-encodes to a fixed point (the fuzz target's invariant).
#[test]
fn param_blob_seeds_replay() {
    let mut accepted = 0;
    for (path, data) in seeds("param_blob") {
        let (mode, rest) = data.split_first().unwrap();
        let blob = if mode & 1 == 0 { rest.to_vec() } else { wrap(rest) };
        if let Ok(rig) = RigParams::from_blob(&blob) {
            let enc = rig.to_blob().unwrap();
            assert_eq!(enc, blob, "{}", path.display());
            accepted += 1;
        }
    }
    assert!(accepted >= 3, "only {accepted} seeds decode");
}

/// The committed robot_proto seeds (mode 0): each is a valid line of one direction and
/// round-trips through encode.
#[test]
fn robot_proto_seeds_replay() {
    for (path, data) in seeds("robot_proto") {
        if data[0] & 1 != 0 {
            continue;
        }
        let text = std::str::from_utf8(&data[1..]).unwrap();
        let tracker = TrackerMsg::parse(text).ok();
        let robot = RobotMsg::parse(text).ok();
        assert!(
            tracker.is_some() || robot.is_some(),
            "{}: {text:?}",
            path.display()
        );
        if let Some(m) = tracker {
            assert_eq!(m.encode().unwrap().as_str(), text);
        }
        if let Some(m) = robot {
            assert_eq!(m.encode().unwrap().as_str(), text);
        }
    }
}

/// The committed stream seeds: NDJSON and binary examples decode and round-trip.
#[test]
fn stream_seeds_replay() {
    for (path, data) in seeds("stream") {
        let (mode, rest) = data.split_first().unwrap();
        let rec = match mode % 3 {
            0 => PositionRecord::from_ndjson_line(std::str::from_utf8(rest).unwrap()),
            1 => PositionRecord::decode_binary(rest),
            _ => continue,
        };
        let rec = rec.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let line = rec.to_ndjson_line();
        assert_eq!(
            PositionRecord::from_ndjson_line(&line).unwrap().to_ndjson_line(),
            line
        );
        let frame = rec.to_binary();
        assert_eq!(PositionRecord::decode_binary(&frame).unwrap().to_binary(), frame);
    }
}

/// The committed per-tool and loose-LED stream seeds (`IRTL`/`IRLL` frames and their NDJSON):
/// each decodes (the CRC-fixed ones after their CRC is fixed, as the fuzz target does) and
/// round-trips in both framings.
#[test]
fn tool_stream_seeds_replay() {
    use irtrack_core::stream::{LOOSE_BINARY_FRAME_LEN, LooseRecord, TOOL_BINARY_FRAME_LEN, ToolRecord};
    fn crc_fixed<const N: usize>(rest: &[u8]) -> [u8; N] {
        let mut frame = [0u8; N];
        let n = rest.len().min(N);
        frame[..n].copy_from_slice(&rest[..n]);
        let end = N - 4;
        let crc = irtrack_core::crc::crc32(&frame[..end]);
        frame[end..].copy_from_slice(&crc.to_le_bytes());
        frame
    }
    let mut modes = [0usize; 6];
    for (path, data) in seeds("tool_stream") {
        let (mode, rest) = data.split_first().unwrap();
        let mode = usize::from(mode % 6);
        modes[mode] += 1;
        if mode < 3 {
            let rec = match mode {
                0 => ToolRecord::from_ndjson_line(std::str::from_utf8(rest).unwrap()),
                1 => ToolRecord::decode_binary(rest),
                _ => ToolRecord::decode_binary(&crc_fixed::<TOOL_BINARY_FRAME_LEN>(rest)),
            };
            let rec = rec.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            let line = rec.to_ndjson_line();
            assert!(line.len() <= MAX_NDJSON_LINE, "{}", path.display());
            assert_eq!(
                ToolRecord::from_ndjson_line(&line).unwrap().to_ndjson_line(),
                line
            );
            let frame = rec.to_binary();
            assert_eq!(ToolRecord::decode_binary(&frame).unwrap().to_binary(), frame);
            assert_eq!(rec.name(), "wing4", "{}", path.display());
        } else {
            let rec = match mode {
                3 => LooseRecord::from_ndjson_line(std::str::from_utf8(rest).unwrap()),
                4 => LooseRecord::decode_binary(rest),
                _ => LooseRecord::decode_binary(&crc_fixed::<LOOSE_BINARY_FRAME_LEN>(rest)),
            };
            let rec = rec.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            let line = rec.to_ndjson_line();
            assert!(line.len() <= MAX_NDJSON_LINE, "{}", path.display());
            assert_eq!(
                LooseRecord::from_ndjson_line(&line).unwrap().to_ndjson_line(),
                line
            );
            let frame = rec.to_binary();
            assert_eq!(LooseRecord::decode_binary(&frame).unwrap().to_binary(), frame);
            assert!(rec.record.orientation_wxyz.is_none(), "{}", path.display());
        }
    }
    assert!(modes.iter().all(|&n| n > 0), "a seed per mode: {modes:?}");
}

/// The committed observation seeds: the raw golden messages (mode 0) decode and re-encode to the
/// same bytes; the CRC-fixed one with a blob count its payload does not hold is refused.
#[test]
fn observation_seeds_replay() {
    use irtrack_core::observation::{MAX_OBS_LEN, ObservationProblem, decode, encode};
    let mut decoded = 0;
    for (path, data) in seeds("observation") {
        let (mode, rest) = data.split_first().unwrap();
        if mode & 1 == 1 {
            // As the fuzz target does: the CRC is fixed up, so the count check is what refuses.
            let mut fixed = rest.to_vec();
            let n = fixed.len() - 4;
            let crc = irtrack_core::crc::crc32(&fixed[..n]);
            fixed[n..].copy_from_slice(&crc.to_le_bytes());
            let e = decode(&fixed).map(|_| ()).unwrap_err();
            assert!(
                matches!(
                    e,
                    Error::Observation {
                        problem: ObservationProblem::Truncated { .. }
                    }
                ),
                "{}: {e}",
                path.display()
            );
            continue;
        }
        let obs = decode(rest).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let blobs: Vec<_> = obs.blobs().collect();
        let mut out = [0u8; MAX_OBS_LEN];
        let n = encode(&obs.header, &blobs, &mut out).unwrap();
        assert_eq!(&out[..n], rest, "{}", path.display());
        decoded += 1;
    }
    assert_eq!(decoded, 2);
}
