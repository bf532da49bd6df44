//! Several tools at once through irtrackd (issue 29): the simulated source renders `probe4`,
//! `tri3` and `wing4` on crossing paths and a loose single LED crossing them; the loop tracks
//! all of them each set. Clients that send `tools\n` get a record per tool (NDJSON and binary)
//! with its id and name, and a record per loose LED with its stable id, checked against the
//! simulator's truth; clients that send nothing get the main records only, as before. The
//! main record follows `[robot] tool`; an unknown robot tool is refused at start and at push,
//! naming it and the set's tools.

mod common;

use std::time::Duration;

use common::*;
use irtrack_core::params::{RigParams, ToolDefinition};
use irtrack_core::pose6d::quaternion_angle_rad;
use irtrack_core::stream::{
    BINARY_FRAME_LEN, BINARY_MAGIC, LOOSE_BINARY_FRAME_LEN, LOOSE_BINARY_MAGIC, LooseRecord, PositionRecord,
    TOOL_BINARY_FRAME_LEN, TOOL_BINARY_MAGIC, ToolRecord, TrackStatus,
};
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::source::sim::SimSourceConfig;
use nalgebra::{UnitQuaternion, Vector3};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

const FRAMES: u64 = 480;
const NAMES: [&str; 3] = ["probe4", "tri3", "wing4"];
/// Scenario body of the loose LED (after the three tools).
const LOOSE_BODY: usize = 3;

fn sim(frames: u64) -> SimSourceConfig {
    toml::from_str(&format!(
        r#"
rig = "convergent"
distance_mm = 1000.0
radius_mm = 60.0
period_s = 6.0
fps = 120.0
seed = 29
tool = "probe4"
extra_tools = ["tri3", "wing4"]
loose_leds = 1
tool_rotation_deg = 20.0
frames = {frames}
"#
    ))
    .unwrap()
}

fn config(
    dir: &std::path::Path,
    sim_cfg: &SimSourceConfig,
    robot_tool: Option<&str>,
    from_sim: bool,
) -> irtrack_firmware::config::Config {
    let tool_line = robot_tool.map_or(String::new(), |t| format!("tool = \"{t}\""));
    let toml = format!(
        r#"
[service]
params_from_simulator = {from_sim}
[leds]
backend = "none"
[robot]
address = "127.0.0.1:9"
{tool_line}
[robot.safety]
workspace_min_mm = [-2000, -2000, -2000]
workspace_max_mm = [2000, 2000, 3000]
max_step_mm = 20.0
max_speed_mm_s = 1000.0
max_gap_mm = 1.5
max_age_ms = 200
require_world_frame = false
[robot.deadman]
kind = "none"
"#
    );
    let mut cfg = irtrack_firmware::config::Config::from_toml(&toml, "multitool.toml").unwrap();
    let base = test_config(dir);
    cfg.service.state_dir = base.service.state_dir;
    cfg.listen = base.listen;
    cfg.params.allow_unsigned = true;
    cfg.source.sim = Some(sim_cfg.clone());
    cfg
}

/// Error of a tracked tool record against body `body`'s truth: (position mm, orientation °).
fn error_of(truth: &irtrack_sim::Scenario, body: usize, r: &PositionRecord) -> (f64, f64) {
    let t_s = truth.truth(r.frame).t_s;
    let (p, q): (Vector3<f64>, UnitQuaternion<f64>) = truth.config().body_pose(body, t_s).unwrap();
    let e_pos = (Vector3::from(r.position_mm.unwrap()) - p).norm();
    let e_rot = quaternion_angle_rad(&r.orientation_wxyz.unwrap(), &[q.w, q.i, q.j, q.k]).to_degrees();
    (e_pos, e_rot)
}

/// Which tools are "seen" in `frame`: 3 or more of their LEDs each image inside 2 or more
/// cameras at least 8 px from every other LED's image (as tests/tests/multibody_sim.rs counts).
fn seen_tools(truth: &irtrack_sim::Scenario, frame: u64) -> [bool; 3] {
    let cfg = truth.config();
    let rig = truth.rig();
    let t_s = truth.truth(frame).t_s;
    let px: Vec<Vec<Option<nalgebra::Vector2<f64>>>> = rig
        .cameras
        .iter()
        .map(|cam| {
            cfg.markers
                .iter()
                .map(|m| {
                    let p = cfg.marker_position(m, t_s);
                    cam.model
                        .project(&cam.cam_from_cam0.apply(&p))
                        .ok()
                        .filter(|q| cam.model.contains_px(q))
                })
                .collect()
        })
        .collect();
    let mut out = [false; 3];
    for (b, seen) in out.iter_mut().enumerate() {
        let leds = (0..cfg.markers.len())
            .filter(|&m| cfg.markers[m].body == b)
            .filter(|&m| {
                px.iter()
                    .filter(|cam| {
                        cam[m].is_some_and(|q| {
                            cam.iter()
                                .enumerate()
                                .all(|(o, r)| o == m || r.is_none_or(|r| (r - q).norm() >= 8.0))
                        })
                    })
                    .count()
                    >= 2
            })
            .count();
        *seen = leds >= 3;
    }
    out
}

/// Whether the loose LED images inside two or more cameras in `frame`.
fn loose_in_view_of_two(truth: &irtrack_sim::Scenario, frame: u64) -> bool {
    let t = truth.truth(frame);
    let cfg = truth.config();
    let m = (0..cfg.markers.len())
        .find(|&m| cfg.markers[m].body == LOOSE_BODY)
        .expect("the loose LED's marker");
    t.markers()[m].visible_mask.count_ones() >= 2
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_tool_and_loose_led_is_streamed_and_the_main_record_follows_the_robot_tool() {
    let dir = TempDir::new("multitool-service");
    let sim_cfg = sim(FRAMES);
    let truth = scenario(&sim_cfg);
    let running = app::start(
        config(dir.path(), &sim_cfg, Some("tri3"), true),
        Overrides::default(),
    )
    .await
    .unwrap();
    // Three clients: NDJSON and binary asking for tools, NDJSON asking for nothing (an
    // existing reader).
    let mut nd = TcpStream::connect(running.addrs.stream_ndjson).await.unwrap();
    nd.write_all(b"tools\n").await.unwrap();
    let mut bin = TcpStream::connect(running.addrs.stream_binary).await.unwrap();
    bin.write_all(b"tools\n").await.unwrap();
    let plain = TcpStream::connect(running.addrs.stream_ndjson).await.unwrap();
    let mut nd = BufReader::new(nd).lines();
    let mut plain = BufReader::new(plain).lines();

    // --- NDJSON with tools: per frame, the tool lines come before the main line.
    let mut pending: Vec<ToolRecord> = Vec::new();
    let mut mains = 0usize;
    let mut tracked = [0usize; 3];
    let (mut seen_count, mut tracked_when_seen) = ([0usize; 3], [0usize; 3]);
    let mut seen_sets = 0usize;
    let (mut pos_max, mut rot_max) = (0.0f64, 0.0f64);
    let mut swaps = 0usize;
    // The loose LED: records within 2 mm of its truth are its own; others are LEDs of a tool
    // that went untracked (reported loose) or ghosts.
    let mut pending_loose: Vec<LooseRecord> = Vec::new();
    let (mut loose_in_view, mut loose_found_in_view) = (0usize, 0usize);
    let (mut loose_ids, mut loose_err) = (Vec::<u32>::new(), Vec::<f64>::new());
    let mut foreign_loose = Vec::<u32>::new();
    // Of those, how many lie within 1 mm of an LED of a tool.
    let mut foreign_on_tool_leds = 0usize;
    loop {
        let line = tokio::time::timeout(Duration::from_secs(10), nd.next_line())
            .await
            .expect("no line within 10 s")
            .unwrap()
            .expect("stream closed");
        if line.starts_with("{\"tool_id\"") {
            assert!(
                pending_loose.is_empty(),
                "tool records come before the loose ones"
            );
            pending.push(ToolRecord::from_ndjson_line(&line).unwrap());
            continue;
        }
        if line.starts_with("{\"loose_id\"") {
            pending_loose.push(LooseRecord::from_ndjson_line(&line).unwrap());
            continue;
        }
        let main = PositionRecord::from_ndjson_line(&line).unwrap();
        mains += 1;
        if main.status != TrackStatus::NoParams && !pending.is_empty() {
            assert_eq!(pending.len(), 3, "one record per tool: {pending:?}");
            seen_sets += 1;
            let seen = seen_tools(&truth, main.frame);
            for (i, t) in pending.iter().enumerate() {
                seen_count[i] += usize::from(seen[i]);
                tracked_when_seen[i] += usize::from(seen[i] && t.record.status == TrackStatus::Ok);
                assert_eq!((t.tool_id as usize, t.tool_count, t.name()), (i, 3, NAMES[i]));
                assert_eq!(t.record.frame, main.frame);
                if t.record.status == TrackStatus::Ok {
                    tracked[i] += 1;
                    let (e_pos, e_rot) = error_of(&truth, i, &t.record);
                    // A swap shows as centimetres or degrees off.
                    swaps += usize::from(e_pos > 5.0 || e_rot > 2.0);
                    pos_max = pos_max.max(e_pos);
                    rot_max = rot_max.max(e_rot);
                }
            }
            let t_s = truth.truth(main.frame).t_s;
            let (p_loose, _) = truth.config().body_pose(LOOSE_BODY, t_s).unwrap();
            let in_view = loose_in_view_of_two(&truth, main.frame);
            loose_in_view += usize::from(in_view);
            let mut found = false;
            for l in &pending_loose {
                assert_eq!(l.record.frame, main.frame);
                assert_eq!(usize::from(l.loose_count), pending_loose.len());
                assert_eq!(l.record.status, TrackStatus::Ok);
                assert!(l.record.orientation_wxyz.is_none());
                let e = (Vector3::from(l.record.position_mm.unwrap()) - p_loose).norm();
                if e < 2.0 {
                    found = true;
                    loose_err.push(e);
                    if loose_ids.last() != Some(&l.loose_id) {
                        loose_ids.push(l.loose_id);
                    }
                } else {
                    foreign_loose.push(l.loose_id);
                    let p = Vector3::from(l.record.position_mm.unwrap());
                    let cfg = truth.config();
                    foreign_on_tool_leds += usize::from(
                        cfg.markers
                            .iter()
                            .filter(|m| m.body != LOOSE_BODY)
                            .any(|m| (cfg.marker_position(m, t_s) - p).norm() < 1.0),
                    );
                }
            }
            assert!(
                pending_loose.windows(2).all(|w| w[0].loose_id < w[1].loose_id),
                "loose records by increasing id: {pending_loose:?}"
            );
            loose_found_in_view += usize::from(in_view && found);
            // `[robot] tool = "tri3"`: the main record is tri3's.
            assert_eq!(main.position_mm, pending[1].record.position_mm);
            assert_eq!(main.orientation_wxyz, pending[1].record.orientation_wxyz);
            assert_eq!(main.status, pending[1].record.status);
        }
        pending.clear();
        pending_loose.clear();
        if main.frame + 1 >= FRAMES {
            break;
        }
    }
    println!(
        "irtrackd, 3 tools, {seen_sets} sets with tool records of {mains}; largest error {pos_max:.3} mm / \
         {rot_max:.3}°; {swaps} swaps"
    );
    for i in 0..3 {
        println!(
            "  {}: tracked in {} sets, seen in {}, tracked in {} of those",
            NAMES[i], tracked[i], seen_count[i], tracked_when_seen[i]
        );
    }
    assert!(
        seen_sets * 10 >= mains * 9,
        "tool records in {seen_sets} of {mains} sets"
    );
    for i in 0..3 {
        assert!(
            seen_count[i] * 4 >= seen_sets,
            "{} seen in only {} sets",
            NAMES[i],
            seen_count[i]
        );
        assert!(
            tracked_when_seen[i] * 100 >= seen_count[i] * 95,
            "{} tracked in {} of {} sets where it was seen",
            NAMES[i],
            tracked_when_seen[i],
            seen_count[i]
        );
    }
    assert_eq!(swaps, 0);
    assert!(pos_max < 1.0 && rot_max < 1.0, "{pos_max} mm {rot_max}°");

    // The loose LED: found in (nearly) every set it is in view of two cameras, under one id,
    // an id never given to anything else, within 0.1 mm of the truth.
    let n = loose_err.len().max(1) as f64;
    let rms = (loose_err.iter().map(|e| e * e).sum::<f64>() / n).sqrt();
    let max = loose_err.iter().copied().fold(0.0, f64::max);
    println!(
        "loose LED: in view of 2 cameras in {loose_in_view} sets, found in {loose_found_in_view} of those \
         ({} records), ids {loose_ids:?}; error RMS {rms:.4} mm, max {max:.4} mm; {} other loose records \
         ({foreign_on_tool_leds} within 1 mm of a tool's LED; ids {:?})",
        loose_err.len(),
        foreign_loose.len(),
        {
            let mut ids = foreign_loose.clone();
            ids.sort_unstable();
            ids.dedup();
            ids
        }
    );
    assert!(
        loose_in_view * 10 >= seen_sets * 9,
        "loose LED in view in only {loose_in_view} of {seen_sets} sets"
    );
    assert!(
        loose_found_in_view * 100 >= loose_in_view * 95,
        "loose LED found in {loose_found_in_view} of {loose_in_view} sets in view"
    );
    assert_eq!(loose_ids.len(), 1, "the loose LED changed id: {loose_ids:?}");
    assert!(
        !foreign_loose.contains(&loose_ids[0]),
        "the loose LED's id was also given to another point"
    );
    assert!(max < 0.1, "loose LED {max} mm from the truth");

    // --- Binary with tools: IRTL frames (140 bytes), then IRLL frames (116 bytes), before each
    // IRPS frame (104 bytes).
    let mut tool_frames = 0usize;
    let (mut loose_frames, mut loose_frames_of_led) = (0usize, 0usize);
    let mut main_frames = 0usize;
    while main_frames < 50 {
        let mut magic = [0u8; 4];
        tokio::time::timeout(Duration::from_secs(10), bin.read_exact(&mut magic))
            .await
            .unwrap()
            .unwrap();
        if magic == TOOL_BINARY_MAGIC {
            let mut f = [0u8; TOOL_BINARY_FRAME_LEN];
            f[..4].copy_from_slice(&magic);
            bin.read_exact(&mut f[4..]).await.unwrap();
            let t = ToolRecord::decode_binary(&f).unwrap();
            assert_eq!(t.name(), NAMES[t.tool_id as usize]);
            tool_frames += 1;
        } else if magic == LOOSE_BINARY_MAGIC {
            let mut f = [0u8; LOOSE_BINARY_FRAME_LEN];
            f[..4].copy_from_slice(&magic);
            bin.read_exact(&mut f[4..]).await.unwrap();
            let l = LooseRecord::decode_binary(&f).unwrap();
            loose_frames += 1;
            let t_s = truth.truth(l.record.frame).t_s;
            let (p, _) = truth.config().body_pose(LOOSE_BODY, t_s).unwrap();
            if (Vector3::from(l.record.position_mm.unwrap()) - p).norm() < 0.1 {
                assert_eq!(l.loose_id, loose_ids[0], "binary and NDJSON carry the same id");
                loose_frames_of_led += 1;
            }
        } else {
            assert_eq!(magic, BINARY_MAGIC);
            let mut f = [0u8; BINARY_FRAME_LEN];
            f[..4].copy_from_slice(&magic);
            bin.read_exact(&mut f[4..]).await.unwrap();
            PositionRecord::decode_binary(&f).unwrap();
            main_frames += 1;
        }
    }
    println!(
        "binary: {tool_frames} tool frames, {loose_frames} loose frames ({loose_frames_of_led} of the loose LED) \
         with {main_frames} main frames"
    );
    assert!(tool_frames >= 3 * (main_frames - 2), "{tool_frames} tool frames");
    assert!(
        loose_frames_of_led * 10 >= main_frames * 8,
        "{loose_frames_of_led} loose frames of the LED"
    );

    // --- The client that asked for nothing got main records only.
    for _ in 0..100 {
        let line = plain.next_line().await.unwrap().unwrap();
        assert!(!line.contains("tool_id") && !line.contains("loose_id"), "{line}");
        PositionRecord::from_ndjson_line(&line).unwrap();
    }
    running.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_robot_tool_is_refused_at_start_and_at_push() {
    let dir = TempDir::new("multitool-unknown");
    let sim_cfg = sim(100_000);
    // At start: the simulator's set (probe4, tri3, wing4) lacks "pointer".
    let err = app::start(
        config(dir.path(), &sim_cfg, Some("pointer"), true),
        Overrides::default(),
    )
    .await
    .err()
    .expect("start with an unknown robot tool must fail")
    .to_string();
    println!("start refused: {err}");
    for word in ["\"pointer\"", "\"probe4\"", "\"tri3\"", "\"wing4\""] {
        assert!(err.contains(word), "{word} missing in: {err}");
    }

    // At push: irtrackd runs without parameters; a set without the robot tool is refused,
    // one with it is accepted.
    let dir = TempDir::new("multitool-unknown-push");
    let running = app::start(
        config(dir.path(), &sim_cfg, Some("tri3"), false),
        Overrides::default(),
    )
    .await
    .unwrap();
    let mut rig: RigParams = scenario(&sim_cfg).rig().clone();
    rig.tools = vec![irtrack_sim::tools::builtin_tool("probe4").unwrap()];
    let line = push(running.addrs.params, &rig.to_blob().unwrap()).await;
    println!("push refused: {}", line.trim_end());
    assert!(line.contains("\"tri3\"") && line.contains("\"probe4\""), "{line}");
    assert!(!line.starts_with("OK"), "{line}");
    rig.tools.push(ToolDefinition {
        name: "tri3".into(),
        ..irtrack_sim::tools::builtin_tool("tri3").unwrap()
    });
    let line = push(running.addrs.params, &rig.to_blob().unwrap()).await;
    assert!(line.starts_with("OK"), "{line}");
    running.shutdown().await;
}

/// `[source.sim] loose_leds`: needs a tool, at most `MAX_SIM_LOOSE_LEDS`, not with the cell;
/// each loose LED is one marker of its own body after the tools.
#[test]
fn loose_leds_in_the_sim_config_are_checked() {
    use irtrack_firmware::source::sim::MAX_SIM_LOOSE_LEDS;
    let err = |cfg: &SimSourceConfig| cfg.validate().unwrap_err().to_string();
    let none = SimSourceConfig {
        loose_leds: 1,
        ..SimSourceConfig::default()
    };
    let e = err(&none);
    assert!(e.contains("loose_leds needs source.sim.tool"), "{e}");
    let many = SimSourceConfig {
        loose_leds: MAX_SIM_LOOSE_LEDS + 1,
        ..sim(10)
    };
    let e = err(&many);
    assert!(e.contains("source.sim.loose_leds must be in 0..=4, got 5"), "{e}");
    let cell: SimSourceConfig = toml::from_str(
        "tool = \"probe4\"\nloose_leds = 1\n[cell]\nrobot = \"127.0.0.1:7750\"\ncam0_from_base_translation_mm = [0, 0, 0]\n",
    )
    .unwrap();
    let e = err(&cell);
    assert!(e.contains("excludes") && e.contains("loose_leds"), "{e}");
    let two = SimSourceConfig {
        loose_leds: 2,
        ..sim(10)
    };
    two.validate().unwrap();
    let cfg = two.scenario_config();
    for body in [3, 4] {
        assert_eq!(
            cfg.markers.iter().filter(|m| m.body == body).count(),
            1,
            "body {body}"
        );
    }
    assert_eq!(
        cfg.markers.len(),
        4 + 3 + 4 + 2,
        "probe4, tri3, wing4 and two loose LEDs"
    );
}
