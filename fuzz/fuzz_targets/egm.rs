//! ABB EGM (firmware/src/robot/egm.rs): the `EgmRobot` decoder never panics; an accepted packet
//! re-encodes to bytes that decode to the same packet, and the sensor's answer to it is a valid
//! `EgmSensor` echoing its seqno with a finite pose.
#![no_main]

use irtrack_robot::egm::{self, EgmSensor};
use irtrack_robot::udp::{Command, StreamConfig, StreamProto};
use libfuzzer_sys::fuzz_target;
use prost::Message;

fuzz_target!(|data: &[u8]| {
    let Ok((msg, pkt)) = egm::decode_robot(data) else {
        return;
    };
    let again = msg.encode_to_vec();
    let (msg2, pkt2) = egm::decode_robot(&again).expect("a decoded EgmRobot re-encodes");
    // Compared as bytes: fields the link does not use (e.g. the planned pose) may hold NaN,
    // which is never equal to itself.
    assert_eq!(msg2.encode_to_vec(), again);
    assert_eq!(pkt2, pkt);
    let mut link = egm::Egm::new(&StreamConfig::default());
    let cmd = Command {
        pos_mm: pkt.pos_mm,
        quat_wxyz: pkt.quat_wxyz.unwrap_or([1.0, 0.0, 0.0, 0.0]),
    };
    let mut out = Vec::new();
    link.encode(&pkt, &cmd, &mut out).expect("the answer encodes");
    let answer = EgmSensor::decode(&out[..]).expect("the answer decodes");
    assert_eq!(answer.header.and_then(|h| h.seqno), Some(pkt.id as u32));
    let p = answer
        .planned
        .and_then(|p| p.cartesian)
        .and_then(|c| c.pos)
        .expect("the answer has a position");
    assert_eq!([p.x, p.y, p.z], pkt.pos_mm);
});
