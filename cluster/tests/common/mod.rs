//! What the Zenoh tests share: a free port, an observation's header and blob.
// Each test file uses a part of it.
#![allow(dead_code)]

use irtrack_cluster::transport::realtime_ns;
use irtrack_core::observation::{ObsBlob, ObsClock, ObsHeader};

/// A free TCP port on 127.0.0.1 (taken and let go).
pub fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

/// A header of `board`'s camera `camera` in `rig`, sequence `seq`, captured now.
pub fn header<'a>(rig: &'a str, board: &'a str, camera: u8, seq: u64) -> ObsHeader<'a> {
    ObsHeader {
        rig,
        board,
        camera,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: realtime_ns(),
        clock: ObsClock::Realtime,
        exposure_us: 250,
        dropped: 0,
        send_delay_us: 100,
    }
}

/// One round blob near the image centre.
pub fn blob() -> ObsBlob {
    ObsBlob {
        x_px: 320.5,
        y_px: 240.25,
        area_px: 9,
        peak_dn: 240,
        roundness: 1.0,
        touches_frame_edge: false,
        touches_roi_edge: false,
        saturated: false,
    }
}
