//! The processing loop does not allocate per frame set once warmed up: a counting global
//! allocator counts allocations made by this test's thread while it runs `Engine::step`.

use std::sync::Arc;
use std::time::Duration;

use irtrack_core::pipeline::TrackerConfig;
use irtrack_core::stream::TrackStatus;
use irtrack_firmware::engine::{ActiveParams, Engine, ParamsHandle, StepOutcome};
use irtrack_firmware::source::FrameSource;
use irtrack_firmware::source::sim::{SimSource, SimSourceConfig};
use irtrack_firmware::status::SharedStatus;

#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

use irtrack_testkit::allocations as allocs;

fn engine(
    with_params: bool,
    bit_depth: u8,
) -> (
    Engine,
    tokio::sync::watch::Receiver<Option<irtrack_core::stream::PositionRecord>>,
) {
    engine_with(with_params, bit_depth, None, &[], 0)
}

/// `tool`: render this built-in multi-LED tool; the set then runs the loop in 6-DOF mode.
/// `loose_leds`: single LEDs of no tool rendered besides the tools.
fn engine_with(
    with_params: bool,
    bit_depth: u8,
    tool: Option<&str>,
    extra_tools: &[&str],
    loose_leds: usize,
) -> (
    Engine,
    tokio::sync::watch::Receiver<Option<irtrack_core::stream::PositionRecord>>,
) {
    let cfg = SimSourceConfig {
        paced: false,
        fps: 100.0,
        bit_depth,
        tool: tool.map(str::to_string),
        extra_tools: extra_tools.iter().map(|t| t.to_string()).collect(),
        loose_leds,
        distance_mm: if tool.is_some() { 1000.0 } else { 600.0 },
        tool_rotation_deg: 20.0,
        ..SimSourceConfig::default()
    };
    let source = SimSource::new(&cfg).unwrap();
    let handle = Arc::new(ParamsHandle::new());
    if with_params {
        let mut rig = source.scenario().rig().clone();
        rig.tools.extend(cfg.tool_definitions());
        handle.install(ActiveParams { rig, crc: 1 });
    }
    let status = Arc::new(SharedStatus::new(
        source.camera_count(),
        source.describe(),
        "none".into(),
    ));
    let (tx, rx) = tokio::sync::watch::channel(None);
    let mut tracker = TrackerConfig::default();
    if bit_depth == 10 {
        // 10-bit frames: threshold in 10-bit DN.
        tracker.threshold_dn = 120;
    }
    (
        Engine::new(
            Box::new(source),
            tracker,
            handle,
            tx,
            status,
            Duration::from_millis(10),
        ),
        rx,
    )
}

fn measure(engine: &mut Engine, warmup: usize, steps: usize) -> (u64, usize) {
    for _ in 0..warmup {
        engine.step().unwrap();
    }
    let before = allocs();
    let mut ok = 0;
    for _ in 0..steps {
        if let StepOutcome::Published(r) = engine.step().unwrap()
            && r.status == TrackStatus::Ok
        {
            ok += 1;
        }
    }
    (allocs() - before, ok)
}

#[test]
fn steady_state_processing_does_not_allocate() {
    for bits in [8u8, 10] {
        let (mut e, rx) = engine(true, bits);
        let (n, ok) = measure(&mut e, 10, 60);
        assert!(
            ok >= 55,
            "{bits}-bit: only {ok} of 60 sets tracked; the measured path must be the tracking path"
        );
        assert_eq!(n, 0, "{bits}-bit: {n} allocations in 60 frame sets");
        assert!(rx.borrow().is_some());
    }
    // The allocator really counts on this thread.
    let before = allocs();
    let v: Vec<u8> = Vec::with_capacity(16);
    drop(v);
    assert_eq!(allocs() - before, 1);
}

#[test]
fn six_dof_processing_does_not_allocate() {
    let (mut e, rx) = engine_with(true, 8, Some("probe4"), &[], 0);
    let (n, ok) = measure(&mut e, 10, 60);
    assert!(
        e.tracks_pose(),
        "the tool's set must switch the loop to 6-DOF mode"
    );
    assert!(ok >= 55, "only {ok} of 60 sets tracked in 6-DOF");
    assert_eq!(n, 0, "{n} allocations in 60 6-DOF frame sets");
    assert!(rx.borrow().unwrap().orientation_wxyz.is_some());
}

/// Three tools and a loose LED: every tool's record and the loose LED's record (with its id)
/// go to the tool slot each set, without allocating.
#[test]
fn three_tools_in_the_loop_do_not_allocate() {
    let (e, rx) = engine_with(true, 8, Some("probe4"), &["tri3", "wing4"], 1);
    let (tools_tx, tools_rx) = tokio::sync::watch::channel(irtrack_firmware::engine::ToolSet::EMPTY);
    let mut e = e.with_tool_slot(tools_tx);
    for _ in 0..10 {
        e.step().unwrap();
    }
    let before = allocs();
    let mut loose_sets = 0;
    for _ in 0..60 {
        e.step().unwrap();
        loose_sets += usize::from(tools_rx.borrow().loose_records().count() > 0);
    }
    let n = allocs() - before;
    assert_eq!(
        n, 0,
        "{n} allocations in 60 frame sets with three tools and a loose LED"
    );
    assert!(
        loose_sets >= 50,
        "a loose LED record in only {loose_sets} of 60 sets"
    );
    let set = *tools_rx.borrow();
    assert_eq!(set.count, 3);
    assert_eq!(set.frame, rx.borrow().unwrap().frame);
    let names: Vec<&str> = set.records().map(|r| r.name()).collect();
    assert_eq!(names, ["probe4", "tri3", "wing4"]);
    for l in set.loose_records() {
        assert_eq!(l.record.frame, set.frame);
        assert_eq!(usize::from(l.loose_count), set.loose_records().count());
        assert!(l.record.position_mm.is_some() && l.record.orientation_wxyz.is_none());
    }
}

#[test]
fn steady_state_with_a_viewer_attached_does_not_allocate() {
    use irtrack_firmware::viewer::ViewerTap;
    let (e, _rx) = engine(true, 8);
    let tap = Arc::new(ViewerTap::new());
    let mut e = e.with_viewer_tap(tap.clone());
    // The viewer arrives: its buffer is allocated here, on the viewer's side.
    let viewer = tap.attach();
    viewer.set_interval_ns(1); // a copy of every set
    let (n, ok) = measure(&mut e, 10, 60);
    assert!(ok >= 55, "only {ok} of 60 sets tracked with a viewer");
    assert_eq!(n, 0, "{n} allocations in 60 frame sets copied for a viewer");
    assert!(tap.copies() >= 60, "the loop copied only {} sets", tap.copies());
    // The copies really hold the tracked blobs: one kept blob per camera.
    let guard = tap.read().unwrap();
    let set = guard.as_deref().unwrap();
    for (camera, blobs) in set.blobs.iter().enumerate() {
        assert_eq!(
            blobs.iter().filter(|b| b.kept).count(),
            1,
            "camera {camera}: {blobs:?}"
        );
    }
    drop(guard);
    // A viewer holding the copy makes the loop skip, not wait.
    let held = tap.read().unwrap();
    let (n, _) = measure(&mut e, 0, 5);
    drop(held);
    assert_eq!(n, 0);
    assert!(tap.busy_skips() >= 5, "busy skips {}", tap.busy_skips());
    drop(viewer);
}

/// A viewer that asks for every set's blob lists but no previews gets a blob copy of every set
/// and makes the loop copy no frame at all; with a preview rate, frames are copied only at that
/// rate. Neither allocates in the loop.
#[test]
fn blob_viewers_get_every_set_without_frame_copies() {
    use irtrack_firmware::viewer::ViewerTap;
    let (e, _rx) = engine(true, 8);
    let tap = Arc::new(ViewerTap::new());
    let mut e = e.with_viewer_tap(tap.clone());
    let viewer = tap.attach();
    viewer.set_wants(0, true);
    let (n, ok) = measure(&mut e, 10, 60);
    assert!(ok >= 55, "only {ok} of 60 sets tracked with a blob viewer");
    assert_eq!(n, 0, "{n} allocations in 60 sets with a blob viewer");
    assert_eq!(tap.blob_copies(), 70, "a blob copy of every set");
    assert_eq!(tap.copies(), 0, "no frame copy for a blob-only viewer");
    let copy = tap.read_blobs().expect("a blob copy");
    assert!(copy.detected);
    for (camera, blobs) in copy.blobs.iter().enumerate() {
        assert_eq!(
            blobs.iter().filter(|b| b.kept).count(),
            1,
            "camera {camera}: {blobs:?}"
        );
    }
    assert_eq!(copy.timestamps_ns.len(), 2);
    assert!(copy.timestamps_ns.iter().all(|&t| t > 0));
    // Previews at 2 per second besides: the frames are copied on that grid only (the
    // unpaced source runs far faster than 2 sets/s).
    viewer.set_wants(500_000_000, true);
    let t0 = std::time::Instant::now();
    let (n, _) = measure(&mut e, 0, 60);
    let secs = t0.elapsed().as_secs_f64();
    assert_eq!(n, 0, "{n} allocations with a preview-rate viewer");
    assert_eq!(tap.blob_copies(), 130);
    let most = (secs * 2.0).ceil() as u64 + 1;
    assert!(
        (1..=most).contains(&tap.copies()),
        "{} frame copies in {secs:.3} s at 2 per second",
        tap.copies()
    );
    drop(viewer);
    assert!(!tap.wants_blobs(), "the last viewer left");
}

#[test]
fn no_params_path_does_not_allocate() {
    let (mut e, rx) = engine(false, 8);
    let (n, ok) = measure(&mut e, 5, 30);
    assert_eq!(ok, 0);
    assert_eq!(n, 0, "{n} allocations in 30 frame sets without parameters");
    assert_eq!(rx.borrow().unwrap().status, TrackStatus::NoParams);
}
