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

/// CLOCK_REALTIME minus CLOCK_MONOTONIC, ns, to put monotonic stamps on the shared clock.
/// The realtime clock is read between two monotonic reads: a thread preempted between two
/// plain reads would move every stamp by the time it was away (milliseconds on a loaded
/// machine). The tightest of a few tries is kept. Read at each use, so a step of the realtime
/// clock (NTP, PTP) is followed.
pub fn realtime_minus_mono_ns() -> i128 {
    let mut best: Option<(u64, i128)> = None;
    for _ in 0..4 {
        let before = monotonic_ns();
        let rt = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let after = monotonic_ns();
        let span_ns = after.saturating_sub(before);
        let diff = i128::try_from(rt).unwrap_or(i128::MAX) - i128::from(before / 2 + after / 2);
        if best.is_none_or(|(s, _)| span_ns < s) {
            best = Some((span_ns, diff));
        }
        // Under 20 µs is as close as the reads themselves allow on a busy board.
        if span_ns < 20_000 {
            break;
        }
    }
    best.map_or(0, |(_, d)| d)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The difference is the same however often it is read (the clocks run at one rate here),
    /// within the bracket's width, and a monotonic stamp put on it lands on the realtime clock.
    #[test]
    fn realtime_minus_mono_is_steady_and_maps_now_to_now() {
        let first = realtime_minus_mono_ns();
        let mut widest = 0i128;
        for _ in 0..1000 {
            widest = widest.max((realtime_minus_mono_ns() - first).abs());
        }
        assert!(widest < 1_000_000, "moved by {widest} ns between reads");
        let rt_now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as i128)
            .unwrap_or(0);
        let mapped = i128::from(monotonic_ns()) + realtime_minus_mono_ns();
        assert!((mapped - rt_now).abs() < 5_000_000, "{mapped} vs {rt_now}");
    }
}
