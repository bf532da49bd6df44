//! CLOCK_MONOTONIC in nanoseconds: the clock V4L2 stamps frames with, so simulated, replayed
//! and real frames share one time base and end-to-end latency can be computed.

/// Current CLOCK_MONOTONIC time in ns (one definition, shared with the robot links).
pub use irtrack_robot::monotonic_ns;

/// Sleeps until CLOCK_MONOTONIC reaches `deadline_ns` (returns at once if it already has).
pub fn sleep_until_ns(deadline_ns: u64) {
    let now = monotonic_ns();
    if deadline_ns > now {
        std::thread::sleep(std::time::Duration::from_nanos(deadline_ns - now));
    }
}
