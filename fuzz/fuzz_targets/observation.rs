//! Observation decoder (core/src/observation.rs, docs/observation-protocol.md): never panics,
//! and whatever decodes re-encodes to the same bytes; the solver's gate never panics either.
//!
//! Modes (first byte): 0 raw bytes; 1 the CRC is fixed up first, so that the checks behind it
//! (ids, blob count, blobs) are reached.
#![no_main]

use irtrack_core::crc::crc32;
use irtrack_core::observation::{CameraPlace, MAX_OBS_LEN, ObsClock, ObservationGate, decode, encode};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let mut bytes = rest.to_vec();
    if mode & 1 == 1 && bytes.len() >= 4 {
        let n = bytes.len() - 4;
        let crc = crc32(&bytes[..n]);
        bytes[n..].copy_from_slice(&crc.to_le_bytes());
    }
    let Ok(obs) = decode(&bytes) else {
        return;
    };
    let blobs: Vec<_> = obs.blobs().collect();
    assert_eq!(blobs.len(), obs.blob_count());
    let mut out = [0u8; MAX_OBS_LEN];
    let n = encode(&obs.header, &blobs, &mut out).expect("a decoded observation re-encodes");
    assert_eq!(&out[..n], &bytes[..], "re-encoding differs");
    let places = [CameraPlace {
        board: obs.header.board.into(),
        local_index: obs.header.camera,
    }];
    let mut gate = ObservationGate::new(obs.header.rig, &places, ObsClock::Realtime, 1_000_000_000).unwrap();
    let _ = gate.check(&obs, obs.header.capture_ts_ns);
});
