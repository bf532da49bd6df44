//! Parameter push protocol (core/src/param_wire.rs): the 8-byte push header and the server's
//! verdict line never panic the parser. Verdicts normalise in one step: parse, write, parse
//! again gives a verdict whose line is stable from then on.
#![no_main]

use irtrack_core::param_wire::{MAX_BLOB_BYTES, PUSH_HEADER_LEN, Verdict, encode_push, parse_push_header};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if data.len() >= PUSH_HEADER_LEN {
        let mut hdr = [0u8; PUSH_HEADER_LEN];
        hdr.copy_from_slice(&data[..PUSH_HEADER_LEN]);
        if let Ok(len) = parse_push_header(&hdr) {
            assert!((1..=MAX_BLOB_BYTES).contains(&len));
        }
    }
    // A request built by the client always has a header the server accepts (for sane sizes).
    let body = &data[..data.len().min(4096)];
    if !body.is_empty() {
        let req = encode_push(body);
        let mut hdr = [0u8; PUSH_HEADER_LEN];
        hdr.copy_from_slice(&req[..PUSH_HEADER_LEN]);
        assert_eq!(parse_push_header(&hdr).expect("client header"), body.len());
    }
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(v1) = Verdict::parse_line(text) {
        let line1 = v1.to_line();
        let v2 = Verdict::parse_line(&line1).expect("a written verdict must parse");
        let line2 = v2.to_line();
        let v3 = Verdict::parse_line(&line2).expect("a written verdict must parse");
        assert_eq!(
            v3, v2,
            "verdict not stable after one normalisation: {line1:?} -> {line2:?}"
        );
        assert_eq!(v1.is_accepted(), v3.is_accepted());
    }
});
