//! Parameter blob decoder (`RigParams::from_blob`): never panics on any input; whatever it
//! accepts re-encodes, and the re-encoding decodes back to itself.
//!
//! The first input byte picks the mode. Raw mode hands the rest to the decoder unchanged, so
//! the header checks are fuzzed. Body mode wraps the rest in a valid header with the correct
//! length and CRC: a mutated body almost never has a matching CRC, so without this the
//! postcard body decoder behind the CRC check would hardly ever run.
#![no_main]

use irtrack_core::crc::Crc32;
use irtrack_core::params::{BLOB_FORMAT_VERSION, BLOB_HEADER_LEN, BLOB_MAGIC, RigParams};
use libfuzzer_sys::fuzz_target;

fn wrap_body(body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(BLOB_HEADER_LEN + body.len());
    out.extend_from_slice(&BLOB_MAGIC);
    out.extend_from_slice(&BLOB_FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out.extend_from_slice(&(body.len() as u32).to_le_bytes());
    let mut c = Crc32::new();
    c.update(&out[..12]);
    c.update(body);
    out.extend_from_slice(&c.finish().to_le_bytes());
    out.extend_from_slice(body);
    out
}

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let blob = if mode & 1 == 0 {
        rest.to_vec()
    } else {
        wrap_body(rest)
    };
    let Ok(rig) = RigParams::from_blob(&blob) else {
        return;
    };
    // Whatever was accepted encodes, and that encoding is a fixed point of decode + encode.
    // (Byte identity with the input does not hold: postcard accepts over-long varints, so
    // several byte strings decode to one rig; see docs/fuzzing.md, finding F1.)
    let encoded = rig.to_blob().expect("a decoded rig must encode");
    let again = RigParams::from_blob(&encoded).expect("re-encoded blob must decode");
    assert_eq!(again.to_blob().expect("encode"), encoded);
    if encoded.len() == blob.len() {
        // Same length means no over-long varint: then the bytes must be identical.
        assert_eq!(encoded, blob, "accepted blob differs from its re-encoding");
    }
    // Everything a service does with a freshly decoded set must be panic-free too.
    if rig.validate().is_ok() {
        let _ = rig.params_crc();
        for i in 0..rig.camera_count() {
            let _ = rig.baseline_mm(i);
            let _ = rig.optical_axis_angle_deg(i);
            let _ = rig.camera_centre_cam0_mm(i);
        }
    }
});
