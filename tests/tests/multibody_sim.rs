//! Several tools at once against the simulator's truth (issue 29): three tools (`probe4`,
//! `tri3`, `wing4`) and one loose LED moving through each other, rendered by the simulator,
//! blobs by `BlobDetector`, tracked by `MultiTracker` — the scene, the run and the figures are
//! `irtrack_sim::multibody` (shared with `cargo xtask bench`, which runs the 60 s cases in
//! release; the 60 s 4-camera run is a host test here too). Figures: `cargo test -p irtrack-tests --test multibody_sim -- --nocapture`.

use irtrack_core::pose6d::PoseConfig;
use irtrack_sim::multibody::{
    FPS, RunStats, four_camera_rig, missed_targets, ninety_degree_pair, report, run, run_counting,
};

// Counts this thread's allocations: the 4-camera run checks that `MultiTracker::process`
// makes none (merges, ghosts and re-solved points included).
#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;
use nalgebra::Rotation3;

const SECONDS: f64 = 60.0;

/// What holds in every run: no swaps, every tool seen in most frames and mostly tracked, the
/// loose LED followed.
fn check_basics(what: &str, r: &RunStats) {
    for (i, st) in r.tools.iter().enumerate() {
        assert_eq!(st.swaps, 0, "{what} tool {i}: identity swaps");
        assert!(
            st.seen as u64 > r.frames / 2,
            "{what} tool {i}: seen in only {} frames",
            st.seen
        );
        assert!(
            st.tracked_share_pct() >= 85.0,
            "{what} tool {i}: tracked in {:.2} % of the frames it was seen",
            st.tracked_share_pct()
        );
        assert!(
            st.rot_rms_deg() <= 0.2 && st.pos_rms_mm() <= 0.2,
            "{what} tool {i}: {}° {} mm",
            st.rot_rms_deg(),
            st.pos_rms_mm()
        );
    }
    assert!(
        r.loose_frames as u64 >= r.frames * 8 / 10,
        "{what}: loose LED in {} frames",
        r.loose_frames
    );
    // Its id may change after a gap (a new id on reacquisition), but it never takes an id that
    // a tool's LED had.
    assert_eq!(r.loose_id_swaps, 0, "{what}: loose LED under a tool LED's id");
}

/// 10 s in the 90° pair: what holds today (run in CI).
#[test]
fn three_tools_and_a_loose_led_cross_without_swaps() {
    let r = run(ninety_degree_pair(), (10.0 * FPS) as u64, PoseConfig::default()).unwrap();
    print!("{}", report("90° pair, 10 s", &r));
    check_basics("90° pair, 10 s", &r);
    // A tool's LEDs are not loose LEDs while the tool is briefly lost (its candidates). Left:
    // LEDs reappearing while their tool has been lost longer than `max_coast_frames` (tri3
    // out of one camera's reach for up to a second). Before: 575 reports under 44 ids, 51
    // ids in all; after: 172 under 11, 18 in all.
    assert!(
        r.loose_on_tool_leds <= 250 && r.loose_ids_reported <= 25,
        "90° pair, 10 s: {} loose reports on tool LEDs, {} loose ids",
        r.loose_on_tool_leds,
        r.loose_ids_reported
    );
}

#[test]
#[ignore = "60 s (meets issue 29's targets); run in release by `cargo xtask bench` (CI's quick bench runs 10 s) or here with --ignored"]
fn three_tools_and_a_loose_led_in_the_90_degree_pair() {
    let r = run(
        ninety_degree_pair(),
        (SECONDS * FPS) as u64,
        PoseConfig::default(),
    )
    .unwrap();
    print!("{}", report("90° pair", &r));
    let missed = missed_targets("90° pair", &r);
    assert!(missed.is_empty(), "{missed:#?}");
}

/// Issue 29's targets in the 4-camera rig, 60 s (about 15 s here): ≥ 99 % tracked when seen
/// for every tool, 0 swaps, orientation RMS ≤ 0.05°, position RMS ≤ 0.05 mm (`missed_targets`).
/// Run in CI: the 4-camera association (ghosts confirmed by a third view, blobs shared by
/// two LEDs) is where the tracker lost frames.
#[test]
fn three_tools_and_a_loose_led_in_a_four_camera_rig() {
    let r = run_counting(
        four_camera_rig().unwrap(),
        (SECONDS * FPS) as u64,
        PoseConfig::default(),
        &irtrack_testkit::allocations,
    )
    .unwrap();
    print!("{}", report("4-camera rig", &r));
    let missed = missed_targets("4-camera rig", &r);
    assert!(missed.is_empty(), "{missed:#?}");
    assert_eq!(r.track_allocs, 0, "MultiTracker::process allocated");
    // Loose LEDs are the loose LED only: one id throughout, no tool LED and no ghost made with
    // a tool LED's image reported as a loose LED (before: 153 ids, 188 reports on tool LEDs,
    // 430 elsewhere; after: 1 id, 0, 1 — that one under the loose LED's own id, its spot
    // merged with a tool LED's so its point lies 5+ mm off).
    assert_eq!(r.loose_ids, 1, "4-camera rig: the loose LED changed id");
    assert_eq!(r.loose_ids_reported, 1, "4-camera rig: loose ids issued");
    assert_eq!(
        r.loose_on_tool_leds, 0,
        "4-camera rig: loose reports on tool LEDs"
    );
    assert!(
        r.loose_elsewhere <= 2,
        "4-camera rig: {} loose reports elsewhere",
        r.loose_elsewhere
    );
}

#[test]
fn wing4_rotation_is_proper() {
    // The rig helper builds proper rotations (det +1): a reflection would mirror the scene.
    if let irtrack_sim::RigPreset::Custom(rig) = four_camera_rig().unwrap() {
        for c in &rig.cameras {
            let r = Rotation3::from_matrix_unchecked(c.cam_from_cam0.rotation());
            assert!((r.matrix().determinant() - 1.0).abs() < 1e-9);
        }
    }
}
