//! The simulated source on the wall clock (`[source.sim] wall_clock`, used by simulated camera
//! boards in separate processes): frame k is captured at CLOCK_REALTIME k / fps, so every
//! process renders the same instants under the same numbers.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use irtrack_firmware::clock;
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};

fn realtime_ns() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).unwrap().as_nanos() as u64
}

#[test]
fn wall_clock_frames_come_at_their_realtime_instants() {
    // 30 fps: 1e9 / 30 is not a whole number of ns, the case where an integer period drifted
    // from the frame times by seconds at today's frame numbers.
    let fps = 30.0;
    let cfg = SimSourceConfig {
        fps,
        wall_clock: true,
        ..SimSourceConfig::default()
    };
    let mut sim = SimSource::new(&cfg).unwrap();
    let mut set = sim.allocate_set();
    let start = Instant::now();
    for _ in 0..5 {
        sim.next_set(&mut set).unwrap();
        let rt = realtime_ns();
        let mono = clock::monotonic_ns();
        // The frame's number is the wall clock's frame now (or the one just before).
        let now_index = (rt as f64 * fps / 1e9).floor() as u64;
        assert!(
            set.index + 1 >= now_index && set.index <= now_index,
            "frame {} delivered during frame {now_index}",
            set.index
        );
        // Its capture time, on CLOCK_MONOTONIC, is close to now.
        let age_ms = mono.abs_diff(set.frames[0].timestamp_ns) as f64 / 1e6;
        assert!(age_ms < 40.0, "frame {} captured {age_ms} ms from now", set.index);
    }
    assert!(
        start.elapsed() < Duration::from_secs(2),
        "5 frames at 30 fps took {:?}",
        start.elapsed()
    );
}
