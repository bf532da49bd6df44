//! Parameter blob format (docs/param-blob.md): golden bytes, specific errors, round trips.

use irtrack_core::Error;
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::params::{
    BLOB_FORMAT_VERSION, BLOB_HEADER_LEN, BlobHeader, CalibrationInfo, CameraParams, CameraPlace, Figure,
    RigParams, ToolDefinition, Verdict,
};
use irtrack_core::timing::{CameraTiming, Shutter};
use proptest::prelude::*;

/// The golden rig: two VGA cameras, the second 100 mm to the right (OpenCV T = (-100, 0, 0)).
fn golden_rig() -> RigParams {
    let vga = ImageSize {
        width_px: 640,
        height_px: 480,
    };
    RigParams {
        rig_id: "golden1".into(),
        created_unix_s: 1_700_000_000,
        cameras: vec![
            CameraParams {
                model: CameraModel {
                    intrinsics: Intrinsics {
                        fx_px: 500.0,
                        fy_px: 500.0,
                        cx_px: 319.5,
                        cy_px: 239.5,
                    },
                    distortion: Distortion::NONE,
                    image_size: vga,
                },
                cam_from_cam0: RigidTransform::IDENTITY,
            },
            CameraParams {
                model: CameraModel {
                    intrinsics: Intrinsics {
                        fx_px: 510.0,
                        fy_px: 505.0,
                        cx_px: 320.0,
                        cy_px: 240.0,
                    },
                    distortion: Distortion {
                        k1: -0.25,
                        k2: 0.125,
                        p1: 0.0,
                        p2: 0.0,
                        k3: 0.0,
                    },
                    image_size: vga,
                },
                cam_from_cam0: RigidTransform {
                    t_mm: [-100.0, 0.0, 0.0],
                    ..RigidTransform::IDENTITY
                },
            },
        ],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Independently assembled (Python: struct.pack + zlib.crc32) from the spec, one field per line.
const GOLDEN_HEX: &[&str] = &[
    "49525042",         // magic "IRPB"
    "0100",             // format version 1
    "0000",             // flags
    "68010000",         // body length 360
    "5a3073ee",         // CRC-32 0xee73305a over bytes 0..12 + body
    "07676f6c64656e31", // rig_id: varint 7, "golden1"
    "80e2cfaa06",       // created_unix_s 1700000000 (varint)
    "02",               // 2 cameras
    // camera 0: fx fy cx cy, k1 k2 p1 p2 k3, width 640 height 480 (varints), R (9), t (3)
    "0000000000407f40",
    "0000000000407f40",
    "0000000000f87340",
    "0000000000f06d40",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "8005",
    "e003",
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    // camera 1
    "0000000000e07f40",
    "0000000000907f40",
    "0000000000007440",
    "0000000000006e40",
    "000000000000d0bf",
    "000000000000c03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "8005",
    "e003",
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "000000000000f03f",
    "0000000000000000",
    "0000000000000000",
    "0000000000000000",
    "000000000000f03f",
    "00000000000059c0", // t_x = -100 mm
    "0000000000000000",
    "0000000000000000",
    "00", // world_from_cam0: None
    "00", // no tools
];

fn from_hex(hex: &str) -> Vec<u8> {
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect()
}

/// The version-1 golden blob: written by this build for a set without tool tips, and the
/// form every blob made before tool tips existed has (old blobs still load).
fn golden_bytes() -> Vec<u8> {
    from_hex(&GOLDEN_HEX.concat())
}

/// The version-2 golden rig: the version-1 rig plus a pivot-calibrated tool with a tip.
fn golden_rig_v2() -> RigParams {
    RigParams {
        rig_id: "golden2".into(),
        tools: vec![ToolDefinition {
            name: "pen".into(),
            leds_mm: vec![[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [10.0, 45.0, 5.0]],
            tip_mm: Some([1.5, -2.25, 150.0]),
        }],
        ..golden_rig()
    }
}

/// Independently assembled (Python: struct.pack + zlib.crc32) from docs/param-blob.md; the
/// camera bytes are those of [`GOLDEN_HEX`] (between the camera count and the trailing
/// `None`/no-tools bytes).
const GOLDEN_V2_HEAD: &[&str] = &[
    "49525042",         // magic "IRPB"
    "0200",             // format version 2 (a tool has a tip)
    "0000",             // flags
    "ce010000",         // body length 462
    "cd12d002",         // CRC-32 0x02d012cd over bytes 0..12 + body
    "07676f6c64656e32", // rig_id: varint 7, "golden2"
    "80e2cfaa06",       // created_unix_s 1700000000 (varint)
    "02",               // 2 cameras
];
const GOLDEN_V2_TAIL: &[&str] = &[
    "00",                                               // world_from_cam0: None
    "01",                                               // 1 tool
    "0370656e",                                         // name: varint 3, "pen"
    "03",                                               // 3 LEDs
    "000000000000000000000000000000000000000000000000", // LED (0, 0, 0)
    "0000000000004e4000000000000000000000000000000000", // LED (60, 0, 0)
    "000000000000244000000000008046400000000000001440", // LED (10, 45, 5)
    "01",                                               // tip_mm: Some
    "000000000000f83f00000000000002c00000000000c06240", // tip (1.5, -2.25, 150) mm
];

fn golden_v2_bytes() -> Vec<u8> {
    with_golden_cameras(GOLDEN_V2_HEAD, GOLDEN_V2_TAIL)
}

#[test]
fn golden_v2_encode_decode() {
    let rig = golden_rig_v2();
    assert_eq!(rig.blob_version(), 2);
    assert_eq!(rig.to_blob().unwrap(), golden_v2_bytes());
    let back = RigParams::from_blob(&golden_v2_bytes()).unwrap();
    assert_eq!(back, rig);
    back.validate().unwrap();
    assert_eq!(back.params_crc().unwrap(), 0x02d0_12cd);
    let h = BlobHeader::parse(&golden_v2_bytes()).unwrap();
    assert_eq!((h.version, h.body_len, h.blob_len()), (2, 462, 478));
}

#[test]
fn old_blob_still_loads_and_sets_without_tips_stay_version_1() {
    // The version-1 golden blob decodes to tools-without-tips parameters ...
    let rig = RigParams::from_blob(&golden_bytes()).unwrap();
    assert_eq!(rig.blob_version(), 1);
    // ... and a set with tools but no tip is still written as version 1 (old readers take it).
    let mut with_tool = golden_rig_v2();
    with_tool.tools[0].tip_mm = None;
    let blob = with_tool.to_blob().unwrap();
    assert_eq!(BlobHeader::parse(&blob).unwrap().version, 1);
    assert_eq!(RigParams::from_blob(&blob).unwrap(), with_tool);
    // A version-1 tool record has no tip byte: name, LEDs, nothing else.
    assert_eq!(&blob[blob.len() - 4 - 1 - 72..blob.len() - 72][..4], b"\x03pen");
}

#[test]
fn version_2_body_without_a_tip_is_not_canonical() {
    // The version-1 golden blob relabelled as version 2 (CRC fixed): without tools its body is
    // also a valid version-2 encoding, of a set that must be written as version 1.
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(2, &[])),
        Err(Error::BlobBody {
            reason: "version-2 body without a tool tip (such a set is written as version 1)"
        })
    );
}

#[test]
fn every_single_byte_corruption_of_the_v2_blob_is_detected() {
    assert_every_single_byte_corruption_is_detected(&golden_v2_bytes());
}

/// The version-3 golden rig: the version-1 cameras with a calibration record (a wand
/// calibration written anyway, marked poor).
fn golden_rig_v3() -> RigParams {
    RigParams {
        rig_id: "golden3".into(),
        calibration: Some(Box::new(CalibrationInfo {
            method: "wand".into(),
            calibrated_unix_s: 1_700_000_100,
            tool_version: "host-tools 0.1.0".into(),
            verdict: Verdict::Poor,
            summary: "cam1 RMS 3.75 px > 1 px".into(),
            rms_px: vec![0.5, 3.75],
            figures: vec![Figure {
                name: "wand_length_rms_mm".into(),
                value: 0.25,
            }],
        })),
        ..golden_rig()
    }
}

/// Independently assembled (Python: struct.pack + zlib.crc32) from docs/param-blob.md; the
/// camera bytes are those of [`GOLDEN_HEX`].
const GOLDEN_V3_HEAD: &[&str] = &[
    "49525042",         // magic "IRPB"
    "0300",             // format version 3 (a calibration record)
    "0000",             // flags
    "ca010000",         // body length 458
    "25bed752",         // CRC-32 0x52d7be25 over bytes 0..12 + body
    "07676f6c64656e33", // rig_id: varint 7, "golden3"
    "80e2cfaa06",       // created_unix_s 1700000000 (varint)
    "02",               // 2 cameras
];
const GOLDEN_V3_TAIL: &[&str] = &[
    "00",                                               // world_from_cam0: None
    "00",                                               // no tools
    "01",                                               // calibration: Some
    "0477616e64",                                       // method: varint 4, "wand"
    "e4e2cfaa06",                                       // calibrated_unix_s 1700000100
    "10686f73742d746f6f6c7320302e312e30",               // tool_version "host-tools 0.1.0"
    "01",                                               // verdict: 1 = poor
    "1763616d3120524d5320332e3735207078203e2031207078", // summary "cam1 RMS 3.75 px > 1 px"
    "02",                                               // rms_px: 2 cameras
    "000000000000e03f",                                 // 0.5 px
    "0000000000000e40",                                 // 3.75 px
    "01",                                               // 1 figure
    "1277616e645f6c656e6774685f726d735f6d6d",           // name "wand_length_rms_mm"
    "000000000000d03f",                                 // value 0.25
];

fn golden_v3_bytes() -> Vec<u8> {
    with_golden_cameras(GOLDEN_V3_HEAD, GOLDEN_V3_TAIL)
}

#[test]
fn golden_v3_encode_decode() {
    let rig = golden_rig_v3();
    assert_eq!(rig.blob_version(), 3);
    assert_eq!(rig.to_blob().unwrap(), golden_v3_bytes());
    let back = RigParams::from_blob(&golden_v3_bytes()).unwrap();
    assert_eq!(back, rig);
    back.validate().unwrap();
    let c = back.calibration.as_ref().unwrap();
    assert_eq!(
        (c.verdict, c.figure("wand_length_rms_mm")),
        (Verdict::Poor, Some(0.25))
    );
    let h = BlobHeader::parse(&golden_v3_bytes()).unwrap();
    assert_eq!(
        (h.version, h.body_len, h.blob_len(), h.crc32),
        (3, 458, 474, 0x52d7_be25)
    );
    // The same set without its record is the version-1 golden blob's cameras again.
    let plain = RigParams {
        calibration: None,
        placement: Vec::new(),
        ..rig
    };
    assert_eq!(plain.blob_version(), 1);
}

#[test]
fn version_3_body_without_a_record_is_not_canonical() {
    // The version-1 golden body + a `None` record byte, relabelled as version 3.
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(3, &[0])),
        Err(Error::BlobBody {
            reason: "version-3 body without a calibration record (such a set is written as version 1 or 2)"
        })
    );
}

#[test]
fn every_single_byte_corruption_of_the_v3_blob_is_detected() {
    assert_every_single_byte_corruption_is_detected(&golden_v3_bytes());
}

#[test]
fn calibration_records_are_validated() {
    let mut rig = golden_rig_v3();
    rig.validate().unwrap();
    let c = rig.calibration.as_mut().unwrap();
    c.rms_px.push(1.0);
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("RMS for 3 cameras, the rig has 2"), "{e}");
    let c = rig.calibration.as_mut().unwrap();
    c.rms_px.pop();
    c.figures[0].value = f64::NAN;
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("wand_length_rms_mm"), "{e}");
    let c = rig.calibration.as_mut().unwrap();
    c.figures[0].value = 1.0;
    c.method.clear();
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("calibration method"), "{e}");
}

/// The version-4 golden rig: the version-1 cameras placed on two camera boards (a cluster
/// solver's set, docs/cluster.md), without a calibration record.
fn golden_rig_v4() -> RigParams {
    RigParams {
        rig_id: "golden4".into(),
        placement: vec![
            CameraPlace {
                board: "b0".into(),
                local_index: 0,
            },
            CameraPlace {
                board: "b1".into(),
                local_index: 2,
            },
        ],
        ..golden_rig()
    }
}

/// Independently assembled (Python: struct.pack + zlib.crc32) from docs/param-blob.md; the
/// camera bytes are those of [`GOLDEN_HEX`].
const GOLDEN_V4_HEAD: &[&str] = &[
    "49525042",         // magic "IRPB"
    "0400",             // format version 4 (a camera placement)
    "0000",             // flags
    "72010000",         // body length 370
    "338ca674",         // CRC-32 0x74a68c33 over bytes 0..12 + body
    "07676f6c64656e34", // rig_id: varint 7, "golden4"
    "80e2cfaa06",       // created_unix_s 1700000000 (varint)
    "02",               // 2 cameras
];
const GOLDEN_V4_TAIL: &[&str] = &[
    "00",     // world_from_cam0: None
    "00",     // no tools
    "00",     // calibration: None
    "02",     // placement: 2 cameras
    "026230", // board: varint 2, "b0"
    "00",     // local_index 0 (u8, one byte)
    "026231", // board "b1"
    "02",     // local_index 2
];

fn golden_v4_bytes() -> Vec<u8> {
    with_golden_cameras(GOLDEN_V4_HEAD, GOLDEN_V4_TAIL)
}

#[test]
fn golden_v4_encode_decode() {
    let rig = golden_rig_v4();
    assert_eq!(rig.blob_version(), 4);
    assert_eq!(rig.to_blob().unwrap(), golden_v4_bytes());
    let back = RigParams::from_blob(&golden_v4_bytes()).unwrap();
    assert_eq!(back, rig);
    back.validate().unwrap();
    let h = BlobHeader::parse(&golden_v4_bytes()).unwrap();
    assert_eq!(
        (h.version, h.body_len, h.blob_len(), h.crc32),
        (4, 370, 386, 0x74a6_8c33)
    );
    // With a calibration record too it stays version 4; without the placement it is what it
    // was before version 4 existed.
    let both = RigParams {
        calibration: golden_rig_v3().calibration,
        ..rig.clone()
    };
    assert_eq!(both.blob_version(), 4);
    assert_eq!(RigParams::from_blob(&both.to_blob().unwrap()).unwrap(), both);
    let without = RigParams {
        placement: Vec::new(),
        ..both
    };
    assert_eq!(without.blob_version(), 3);
    assert_eq!(
        without.to_blob().unwrap(),
        RigParams {
            rig_id: "golden4".into(),
            ..golden_rig_v3()
        }
        .to_blob()
        .unwrap()
    );
}

#[test]
fn older_blobs_still_load_next_to_version_4() {
    for (bytes, version) in [
        (golden_bytes(), 1),
        (golden_v2_bytes(), 2),
        (golden_v3_bytes(), 3),
    ] {
        let rig = RigParams::from_blob(&bytes).unwrap();
        assert!(rig.placement.is_empty());
        assert_eq!(rig.blob_version(), version);
        assert_eq!(
            rig.to_blob().unwrap(),
            bytes,
            "version {version} re-encodes unchanged"
        );
    }
}

#[test]
fn version_4_body_without_a_placement_is_not_canonical() {
    // The version-1 golden body + `None` record + empty placement, relabelled as version 4.
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(4, &[0, 0])),
        Err(Error::BlobBody {
            reason: "version-4 body without a camera placement (such a set is written as version 1, 2 or 3)"
        })
    );
}

#[test]
fn every_single_byte_corruption_of_the_v4_blob_is_detected() {
    assert_every_single_byte_corruption_is_detected(&golden_v4_bytes());
}

#[test]
fn placements_are_validated() {
    let mut rig = golden_rig_v4();
    rig.validate().unwrap();
    rig.placement.pop();
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("placement lists 1 cameras, the rig has 2"), "{e}");
    rig.placement.push(rig.placement[0].clone());
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("placed twice"), "{e}");
    rig.placement[1] = CameraPlace {
        board: "b 1".into(),
        local_index: 0,
    };
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("board name"), "{e}");
}

/// The version-5 golden rig: the version-1 cameras as rig `golden5`, camera 0 with the default
/// timing and camera 1 a rolling shutter (15.2 µs per row, 1 ms exposure, −120 µs offset),
/// serial 1700000500; no record, no placement.
fn golden_rig_v5() -> RigParams {
    RigParams {
        rig_id: "golden5".into(),
        timing: vec![
            CameraTiming::default(),
            CameraTiming {
                shutter: Shutter::Rolling,
                line_time_ns: 15_200,
                exposure_ns: 1_000_000,
                offset_ns: -120_000,
            },
        ],
        serial: 1_700_000_500,
        ..golden_rig()
    }
}

/// Independently assembled (Python: struct.pack, zlib.crc32 and a 7-bit varint / zigzag
/// routine written from docs/param-blob.md); the camera bytes are those of [`GOLDEN_HEX`].
const GOLDEN_V5_HEAD: &[&str] = &[
    "49525042",         // magic "IRPB"
    "0500",             // format version 5 (timing, serial)
    "0000",             // flags
    "7d010000",         // body length 381
    "afd7aeee",         // CRC-32 0xeeaed7af over bytes 0..12 + body
    "07676f6c64656e35", // rig_id: varint 7, "golden5"
    "80e2cfaa06",       // created_unix_s 1700000000 (varint)
    "02",               // 2 cameras
];
const GOLDEN_V5_TAIL: &[&str] = &[
    "00",         // world_from_cam0: None
    "00",         // no tools
    "00",         // calibration: None
    "00",         // placement: empty
    "02",         // timing: 2 cameras
    "00",         // camera 0: shutter global (varint 0)
    "00",         // line_time_ns 0
    "00",         // exposure_ns 0
    "00",         // offset_ns 0 (zigzag varint)
    "01",         // camera 1: shutter rolling (varint 1)
    "e076",       // line_time_ns 15200
    "c0843d",     // exposure_ns 1000000
    "ffd20e",     // offset_ns -120000: zigzag 239999
    "f4e5cfaa06", // serial 1700000500 (varint)
];

fn golden_v5_bytes() -> Vec<u8> {
    with_golden_cameras(GOLDEN_V5_HEAD, GOLDEN_V5_TAIL)
}

#[test]
fn golden_v5_encode_decode() {
    let rig = golden_rig_v5();
    rig.validate().unwrap();
    assert_eq!(rig.blob_version(), 5);
    assert_eq!(rig.to_blob().unwrap(), golden_v5_bytes());
    let back = RigParams::from_blob(&golden_v5_bytes()).unwrap();
    assert_eq!(back, rig);
    assert_eq!(back.camera_timing(1).line_time_ns, 15_200);
    assert_eq!(back.camera_timing(0), CameraTiming::default());
    let h = BlobHeader::parse(&golden_v5_bytes()).unwrap();
    assert_eq!(
        (h.version, h.body_len, h.blob_len(), h.crc32),
        (5, 381, 397, 0xeeae_d7af)
    );
    // Everything together (record, placement, timing, serial) round-trips in version 5.
    let all = RigParams {
        calibration: golden_rig_v3().calibration,
        placement: golden_rig_v4().placement,
        ..rig.clone()
    };
    all.validate().unwrap();
    assert_eq!(all.blob_version(), 5);
    assert_eq!(RigParams::from_blob(&all.to_blob().unwrap()).unwrap(), all);
}

#[test]
fn serial_or_timing_alone_make_version_5_and_neither_keeps_the_old_bytes() {
    let only_serial = RigParams {
        serial: 7,
        ..golden_rig()
    };
    assert_eq!(only_serial.blob_version(), 5);
    let back = RigParams::from_blob(&only_serial.to_blob().unwrap()).unwrap();
    assert_eq!(back, only_serial);
    let only_timing = RigParams {
        serial: 0,
        ..golden_rig_v5()
    };
    assert_eq!(only_timing.blob_version(), 5);
    assert_eq!(
        RigParams::from_blob(&only_timing.to_blob().unwrap()).unwrap(),
        only_timing
    );
    // Default timing for every camera is no timing: the set keeps its version-1 bytes.
    let defaults = RigParams {
        timing: vec![CameraTiming::default(); 2],
        serial: 0,
        ..golden_rig()
    };
    assert!(!defaults.has_timing());
    assert_eq!(defaults.blob_version(), 1);
    assert_eq!(defaults.to_blob().unwrap(), golden_bytes());
    // With a serial it is version 5 with an empty timing list, read back as empty.
    let defaults_serial = RigParams {
        serial: 9,
        ..defaults
    };
    let back = RigParams::from_blob(&defaults_serial.to_blob().unwrap()).unwrap();
    assert!(back.timing.is_empty());
    assert_eq!(back.camera_timing(1), CameraTiming::default());
}

#[test]
fn older_blobs_load_with_default_timing_and_no_serial() {
    for (bytes, version) in [
        (golden_bytes(), 1),
        (golden_v2_bytes(), 2),
        (golden_v3_bytes(), 3),
        (golden_v4_bytes(), 4),
    ] {
        let rig = RigParams::from_blob(&bytes).unwrap();
        assert!(rig.timing.is_empty(), "version {version}");
        assert_eq!(rig.serial, 0);
        for i in 0..rig.camera_count() {
            assert_eq!(rig.camera_timing(i), CameraTiming::default());
            assert_eq!(rig.camera_timing(i).shutter, Shutter::Global);
            assert_eq!(rig.camera_timing(i).offset_ns, 0);
        }
        assert_eq!(rig.blob_version(), version);
        assert_eq!(
            rig.to_blob().unwrap(),
            bytes,
            "version {version} re-encodes unchanged"
        );
    }
}

#[test]
fn version_5_bodies_that_are_not_canonical_are_refused() {
    // The version-1 golden body + no record + no placement + no timing + serial 0.
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(5, &[0, 0, 0, 0])),
        Err(Error::BlobBody {
            reason: "version-5 body without camera timing or serial (such a set is written as version 1 to 4)"
        })
    );
    // Two cameras of default timing (written as none), serial 1.
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(5, &[0, 0, 2, 0, 0, 0, 0, 0, 0, 0, 0, 1])),
        Err(Error::BlobBody {
            reason: "version-5 body whose cameras all have the default timing (such a list is written empty)"
        })
    );
    // An over-long serial varint (1 written as 0x81 0x00).
    assert_eq!(
        RigParams::from_blob(&relabelled_golden(5, &[0, 0, 0, 0x81, 0x00])),
        Err(Error::BlobBody {
            reason: "body is not in canonical encoding (over-long integer)"
        })
    );
    // Shutter tag 2 does not exist.
    assert!(matches!(
        RigParams::from_blob(&relabelled_golden(5, &[0, 0, 1, 2, 0, 0, 0, 1])),
        Err(Error::BlobBody { .. })
    ));
}

#[test]
fn every_single_byte_corruption_of_the_v5_blob_is_detected() {
    assert_every_single_byte_corruption_is_detected(&golden_v5_bytes());
}

#[test]
fn timing_is_validated() {
    let mut rig = golden_rig_v5();
    rig.timing.pop();
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("timing lists 1 cameras, the rig has 2"), "{e}");
    let mut rig = golden_rig_v5();
    rig.timing[1].line_time_ns = 0;
    let e = rig.validate().unwrap_err().to_string();
    assert!(
        e.contains("camera 1 timing: a rolling shutter needs line_time_ns > 0"),
        "{e}"
    );
    let mut rig = golden_rig_v5();
    rig.timing[0].offset_ns = 5_000_000_000;
    let e = rig.validate().unwrap_err().to_string();
    assert!(e.contains("camera 0 timing") && e.contains("unit"), "{e}");
}

#[test]
fn next_serial_is_monotonic() {
    // A new set takes the time; a modified one one more than its predecessor, never less
    // than the time.
    assert_eq!(RigParams::next_serial(0, 1_800_000_000), 1_800_000_000);
    assert_eq!(
        RigParams::next_serial(1_800_000_000, 1_800_000_000),
        1_800_000_001
    );
    assert_eq!(
        RigParams::next_serial(1_900_000_000, 1_800_000_000),
        1_900_000_001
    );
    assert_eq!(RigParams::next_serial(u64::MAX, 0), u64::MAX);
}

#[test]
fn golden_encode() {
    assert_eq!(golden_rig().to_blob().unwrap(), golden_bytes());
}

#[test]
fn golden_decode() {
    let rig = RigParams::from_blob(&golden_bytes()).unwrap();
    assert_eq!(rig, golden_rig());
    rig.validate().unwrap();
    assert!((rig.baseline_mm(1).unwrap() - 100.0).abs() < 1e-12);
    assert_eq!(rig.optical_axis_angle_deg(1).unwrap(), 0.0);
    assert_eq!(rig.params_crc().unwrap(), 0xee73_305a);
}

#[test]
fn header_parses() {
    let h = BlobHeader::parse(&golden_bytes()).unwrap();
    assert_eq!(
        h,
        BlobHeader {
            version: 1,
            flags: 0,
            body_len: 360,
            crc32: 0xee73_305a
        }
    );
    assert_eq!(h.blob_len(), 376);
}

#[test]
fn truncated_blobs() {
    let b = golden_bytes();
    for len in [0, 3] {
        assert_eq!(
            RigParams::from_blob(&b[..len]),
            Err(Error::BlobTruncated { needed: 16, got: len })
        );
    }
    assert_eq!(
        RigParams::from_blob(&b[..15]),
        Err(Error::BlobTruncated { needed: 16, got: 15 })
    );
    for len in [16, 200, b.len() - 1] {
        assert_eq!(
            RigParams::from_blob(&b[..len]),
            Err(Error::BlobTruncated {
                needed: 376,
                got: len
            })
        );
    }
}

#[test]
fn wrong_magic() {
    let mut b = golden_bytes();
    b[0] = b'X';
    assert_eq!(
        RigParams::from_blob(&b),
        Err(Error::BlobBadMagic { found: *b"XRPB" })
    );
    // A YAML file is recognised as "not a blob", not as truncated.
    assert_eq!(
        RigParams::from_blob(b"%YAML:1.0\n"),
        Err(Error::BlobBadMagic { found: *b"%YAM" })
    );
}

#[test]
fn wrong_version() {
    let mut b = golden_bytes();
    b[4] = 6;
    assert_eq!(
        RigParams::from_blob(&b),
        Err(Error::BlobUnsupportedVersion {
            found: 6,
            supported: BLOB_FORMAT_VERSION
        })
    );
}

#[test]
fn signed_flag_refused_until_verification_exists() {
    let mut b = golden_bytes();
    b[6] = 0x01;
    assert_eq!(
        RigParams::from_blob(&b),
        Err(Error::BlobUnsupportedFlags { flags: 1, known: 0 })
    );
}

#[test]
fn trailing_bytes() {
    let mut b = golden_bytes();
    b.extend_from_slice(&[0, 0, 0]);
    assert_eq!(
        RigParams::from_blob(&b),
        Err(Error::BlobTrailingBytes { extra: 3 })
    );
}

#[test]
fn corrupted_body_and_crc() {
    let mut b = golden_bytes();
    b[100] ^= 0x10;
    assert!(matches!(
        RigParams::from_blob(&b),
        Err(Error::BlobBadCrc {
            found: 0xee73_305a,
            ..
        })
    ));
    let mut b = golden_bytes();
    b[12] ^= 0x01;
    assert_eq!(
        RigParams::from_blob(&b),
        Err(Error::BlobBadCrc {
            found: 0xee73_305b,
            computed: 0xee73_305a
        })
    );
}

/// Rewrites the CRC so that a damaged body reaches the body decoder.
fn reseal(mut b: Vec<u8>) -> Vec<u8> {
    let mut covered = b[..12].to_vec();
    covered.extend_from_slice(&b[BLOB_HEADER_LEN..]);
    let crc = irtrack_core::crc::crc32(&covered);
    b[12..16].copy_from_slice(&crc.to_le_bytes());
    b
}

/// A later version's golden blob: its own head and tail (header and the fields before and
/// after the cameras) around the cameras of [`GOLDEN_HEX`] (without its trailing `None` and
/// no-tools bytes).
fn with_golden_cameras(head: &[&str], tail: &[&str]) -> Vec<u8> {
    let cameras = &GOLDEN_HEX[8..GOLDEN_HEX.len() - 2];
    from_hex(&[head, cameras, tail].concat().concat())
}

/// The version-1 golden blob relabelled as `version`, with `extra` body bytes appended and
/// the length and CRC made consistent: a body the decoder must judge on its content.
fn relabelled_golden(version: u8, extra: &[u8]) -> Vec<u8> {
    let mut b = golden_bytes();
    b[4] = version;
    b.extend_from_slice(extra);
    let len = (b.len() - BLOB_HEADER_LEN) as u32;
    b[8..12].copy_from_slice(&len.to_le_bytes());
    reseal(b)
}

/// Every change of a single byte of `good` (each of the 255 xor values) makes the blob fail.
fn assert_every_single_byte_corruption_is_detected(good: &[u8]) {
    for i in 0..good.len() {
        for x in 1..=255u8 {
            let mut b = good.to_vec();
            b[i] ^= x;
            assert!(
                RigParams::from_blob(&b).is_err(),
                "byte {i} xor {x:#04x} undetected"
            );
        }
    }
}

#[test]
fn bad_body_with_valid_crc() {
    // Body cut short, length field and CRC made consistent.
    let mut b = golden_bytes();
    b.truncate(b.len() - 10);
    let body_len = (b.len() - BLOB_HEADER_LEN) as u32;
    b[8..12].copy_from_slice(&body_len.to_le_bytes());
    assert!(matches!(
        RigParams::from_blob(&reseal(b)),
        Err(Error::BlobBody { .. })
    ));
    // Option tag 7 for world_from_cam0.
    let mut b = golden_bytes();
    let n = b.len();
    b[n - 2] = 7;
    assert!(matches!(
        RigParams::from_blob(&reseal(b)),
        Err(Error::BlobBody { .. })
    ));
    // One extra byte inside the declared body.
    let mut b = golden_bytes();
    b.push(0);
    b[8..12].copy_from_slice(&361u32.to_le_bytes());
    assert_eq!(
        RigParams::from_blob(&reseal(b)),
        Err(Error::BlobBody {
            reason: "unused bytes at the end of the body"
        })
    );
}

#[test]
fn every_single_byte_corruption_is_detected() {
    let good = golden_bytes();
    let mut undetected = Vec::new();
    for i in 0..good.len() {
        for x in 1..=255u8 {
            let mut b = good.clone();
            b[i] ^= x;
            if RigParams::from_blob(&b).is_ok() {
                undetected.push((i, x));
            }
        }
    }
    assert!(
        undetected.is_empty(),
        "undetected corruptions (byte, xor): {undetected:?}"
    );
}

fn finite() -> impl Strategy<Value = f64> {
    -1e6..1e6f64
}

fn transform() -> impl Strategy<Value = RigidTransform> {
    (prop::array::uniform9(finite()), prop::array::uniform3(finite()))
        .prop_map(|(r_row_major, t_mm)| RigidTransform { r_row_major, t_mm })
}

fn camera() -> impl Strategy<Value = CameraParams> {
    (
        prop::array::uniform4(finite()),
        prop::array::uniform5(-1.0..1.0f64),
        1..10_000u32,
        1..10_000u32,
        transform(),
    )
        .prop_map(|(k, d, w, h, pose)| CameraParams {
            model: CameraModel {
                intrinsics: Intrinsics {
                    fx_px: k[0],
                    fy_px: k[1],
                    cx_px: k[2],
                    cy_px: k[3],
                },
                distortion: Distortion {
                    k1: d[0],
                    k2: d[1],
                    p1: d[2],
                    p2: d[3],
                    k3: d[4],
                },
                image_size: ImageSize {
                    width_px: w,
                    height_px: h,
                },
            },
            cam_from_cam0: pose,
        })
}

fn tool() -> impl Strategy<Value = ToolDefinition> {
    (
        "\\PC{0,12}",
        prop::collection::vec(prop::array::uniform3(finite()), 0..6),
        prop::option::of(prop::array::uniform3(finite())),
    )
        .prop_map(|(name, leds_mm, tip_mm)| ToolDefinition {
            name,
            leds_mm,
            tip_mm,
        })
}

fn calibration() -> impl Strategy<Value = CalibrationInfo> {
    (
        "\\PC{0,12}",
        any::<u64>(),
        "\\PC{0,12}",
        any::<bool>(),
        "\\PC{0,30}",
        prop::collection::vec(finite(), 0..4),
        prop::collection::vec(("\\PC{0,12}", finite()), 0..4),
    )
        .prop_map(
            |(method, calibrated_unix_s, tool_version, poor, summary, rms_px, figures)| CalibrationInfo {
                method,
                calibrated_unix_s,
                tool_version,
                verdict: if poor { Verdict::Poor } else { Verdict::Good },
                summary,
                rms_px,
                figures: figures
                    .into_iter()
                    .map(|(name, value)| Figure { name, value })
                    .collect(),
            },
        )
}

fn rig() -> impl Strategy<Value = RigParams> {
    (
        "\\PC{0,40}",
        any::<u64>(),
        prop::collection::vec(camera(), 0..6),
        prop::option::of(transform()),
        prop::collection::vec(tool(), 0..3),
        prop::option::of(calibration()),
        prop::collection::vec(("[a-z0-9_-]{1,8}", any::<u8>()), 0..4),
        prop::collection::vec(timing(), 0..4),
        prop::option::of(1..u64::MAX),
    )
        .prop_map(
            |(
                rig_id,
                created_unix_s,
                cameras,
                world_from_cam0,
                tools,
                calibration,
                placement,
                timing,
                serial,
            )| RigParams {
                rig_id,
                created_unix_s,
                cameras,
                world_from_cam0,
                tools,
                calibration: calibration.map(Box::new),
                placement: placement
                    .into_iter()
                    .map(|(board, local_index)| CameraPlace { board, local_index })
                    .collect(),
                // A list whose cameras all have the default timing is written as none: the
                // set that comes back has an empty list (`normalised_timing`).
                timing,
                serial: serial.unwrap_or(0),
            },
        )
}

fn timing() -> impl Strategy<Value = CameraTiming> {
    (any::<bool>(), any::<u32>(), any::<u32>(), any::<i64>()).prop_map(
        |(rolling, line_time_ns, exposure_ns, offset_ns)| CameraTiming {
            shutter: if rolling {
                Shutter::Rolling
            } else {
                Shutter::Global
            },
            line_time_ns,
            exposure_ns,
            offset_ns,
        },
    )
}

/// The set as it reads back from its blob: a timing list of defaults only is written as none.
fn normalised_timing(mut rig: RigParams) -> RigParams {
    if !rig.has_timing() {
        rig.timing.clear();
    }
    rig
}

proptest! {
    #[test]
    fn random_rigs_round_trip(rig in rig()) {
        let blob = rig.to_blob().unwrap();
        let h = BlobHeader::parse(&blob).unwrap();
        prop_assert_eq!(h.blob_len(), blob.len());
        prop_assert_eq!(RigParams::from_blob(&blob).unwrap(), normalised_timing(rig));
    }

    #[test]
    fn random_single_byte_corruption_detected(rig in rig(), pos in any::<prop::sample::Index>(), x in 1..=255u8) {
        let mut blob = rig.to_blob().unwrap();
        let i = pos.index(blob.len());
        blob[i] ^= x;
        prop_assert!(RigParams::from_blob(&blob).is_err());
    }
}
