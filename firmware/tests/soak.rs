//! Short soak of the real processing loop (unpaced simulated source): counters agree with
//! each other and resident memory stays flat. Timing is measured by `examples/soak.rs`, not
//! asserted here.

use irtrack_firmware::soak::{self, SoakConfig};

#[test]
fn short_soak_counters_consistent_and_memory_flat() {
    let r = soak::run(
        SoakConfig {
            frames: 1500,
            fps: 120.0,
            paced: false,
        },
        |_, _| {},
    )
    .unwrap();
    assert_eq!(r.sets_published, 1500);
    assert_eq!(r.consistency_errors(), Vec::<String>::new());
    assert_eq!(r.tracked, 1500, "simulated marker tracked in every set");
    let [start, _, end] = r.rss_bytes;
    assert!(start > 0 && end > 0, "RSS not readable: {:?}", r.rss_bytes);
    // Steady state allocates nothing per set; allow 1 MiB of allocator/page-cache noise.
    assert!(
        end.saturating_sub(start) < 1 << 20,
        "RSS grew from {start} to {end} bytes"
    );
}
