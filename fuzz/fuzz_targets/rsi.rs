//! KUKA RSI (firmware/src/robot/rsi.rs): the `<Rob>` parser never panics; an accepted packet
//! written back as XML parses to the same values, and the sensor's `<Sen>` answer parses and
//! echoes its IPOC.
#![no_main]

use irtrack_robot::rsi;
use irtrack_robot::udp::{Command, StreamConfig, StreamProto};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(f) = rsi::parse_rob(data) else {
        return;
    };
    // `{}` prints the shortest text that parses back to the same f64.
    let [x, y, z] = f.pos_mm;
    let abc = f
        .abc_deg
        .map(|[a, b, c]| format!(" A=\"{a}\" B=\"{b}\" C=\"{c}\""))
        .unwrap_or_default();
    let rsol = f
        .setpoint_mm
        .map(|[a, b, c]| format!("<RSol X=\"{a}\" Y=\"{b}\" Z=\"{c}\"/>"))
        .unwrap_or_default();
    let text = format!(
        "<Rob Type=\"KUKA\"><RIst X=\"{x}\" Y=\"{y}\" Z=\"{z}\"{abc}/>{rsol}<IPOC>{}</IPOC></Rob>",
        f.ipoc
    );
    assert_eq!(rsi::parse_rob(text.as_bytes()).expect("rewritten <Rob> parses"), f);

    let mut link = rsi::Rsi::new(&StreamConfig::default());
    let pkt = link.decode(data).expect("decodes as in parse_rob");
    link.on_session(&pkt);
    let mut out = Vec::new();
    let cmd = Command {
        pos_mm: pkt.pos_mm,
        quat_wxyz: [1.0, 0.0, 0.0, 0.0],
    };
    link.encode(&pkt, &cmd, &mut out).expect("the answer encodes");
    let sen = rsi::parse_sen(&out).expect("the answer parses");
    assert_eq!(sen.ipoc, f.ipoc);
    assert_eq!(sen.korr_mm, [0.0; 3], "holding at the start pose is a zero correction");
});
