//! irtrackd's ROS 2 output (`[outputs.ros2]`, ros2-client on rustdds) against an independent
//! DDS: Cyclone DDS (PyPI `cyclonedds`, the DDS of ROS 2's rmw_cyclonedds) in a separate
//! Python process subscribes to `rt/<topic>` with ROS 2's type names; PyPI `rosbags` decodes the
//! CDR (firmware/tests/py/ros2_subscriber.py). What it decodes must equal irtrackd's own NDJSON
//! stream.
//!
//! DDS discovery is multicast: each test runs itself again inside a network namespace of its
//! own (`unshare -rn`, loopback only, multicast on, a route for 239.0.0.0/8), so nothing leaves
//! the machine and parallel tests do not see each other. Needs the `ros2` feature (workspace
//! builds enable it through irtrack-tests).
#![cfg(feature = "ros2")]

mod common;

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use common::*;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_firmware::app::{self, Overrides};
use serde_json::Value;

/// The Cyclone DDS subscriber (firmware/tests/py/ros2_subscriber.py), started; returns once it
/// says it is ready.
fn subscriber(args: &[&str]) -> JsonLinesChild {
    let sub = JsonLinesChild::spawn("ros2_subscriber.py", args);
    let ready = sub
        .next(Duration::from_secs(20))
        .expect("subscriber ready (are PyPI's cyclonedds and rosbags installed? cargo xtask setup)");
    assert!(ready.get("ready").is_some(), "{ready}");
    sub
}

/// irtrackd with `[outputs.ros2]` enabled and `ros2_toml` in that table.
async fn start(dir: &TempDir, sim_toml: &str, ros2_toml: &str) -> app::Running {
    start_with(
        dir,
        sim_toml,
        &format!("[outputs.ros2]\nenabled = true\n{ros2_toml}"),
    )
    .await
}

/// Every sample the subscriber prints until its `done` line (20 s at most), and that line;
/// the subscriber is stopped after.
async fn read_samples(sub: JsonLinesChild) -> (Vec<Value>, Value) {
    tokio::task::spawn_blocking(move || sub.until("done", Duration::from_secs(20)))
        .await
        .unwrap()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

fn stamp_ns(header: &Value) -> i128 {
    i128::from(header["stamp"]["sec"].as_i64().unwrap()) * 1_000_000_000
        + i128::from(header["stamp"]["nanosec"].as_i64().unwrap())
}

const TOOL_SIM: &str = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nperiod_s = 6.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\nframes = 2400\n";

#[test]
fn ros2_tool_poses_and_tf_reach_cyclone_dds_equal_to_the_ndjson_stream() {
    run_in_own_netns(
        "ros2_tool_poses_and_tf_reach_cyclone_dds_equal_to_the_ndjson_stream",
        || async {
            let dir = TempDir::new("ros2-tool");
            let sub = subscriber(&[
                "--domain",
                "7",
                "--count",
                "300",
                "--seconds",
                "15",
                "/irtrack/probe4/pose=geometry_msgs/msg/PoseStamped",
                "/tf=tf2_msgs/msg/TFMessage",
            ]);
            let running = start(&dir, TOOL_SIM, "domain_id = 7\n").await;
            let ndjson = NdjsonCollector::start(running.addrs.stream_ndjson).await;
            let (samples, done) = read_samples(sub).await;
            let records = ndjson.finish().await;
            let stats = running.outputs.ros2.clone();
            let published = running.status.published.load(Ordering::Relaxed);
            running.shutdown().await;
            println!(
                "ROS 2: subscriber {done}; irtrackd sent {} messages, {} dropped, {} records skipped of {published}",
                stats.frames_sent.load(Ordering::Relaxed),
                stats.send_drops.load(Ordering::Relaxed),
                stats.slot_skips.load(Ordering::Relaxed),
            );
            assert!(samples.len() >= 300, "only {} samples: {done}", samples.len());

            // Stamps are capture times on the wall clock: one constant offset for every record.
            let tracked: Vec<&PositionRecord> = records
                .iter()
                .filter(|r| r.status == TrackStatus::Ok && r.orientation_wxyz.is_some())
                .collect();
            let by_capture: HashMap<u64, &PositionRecord> =
                tracked.iter().map(|r| (r.capture_ts_ns, *r)).collect();
            let poses: Vec<&Value> = samples
                .iter()
                .filter(|s| s["topic"] == "/irtrack/probe4/pose")
                .map(|s| &s["msg"])
                .collect();
            let tfs: Vec<&Value> = samples
                .iter()
                .filter(|s| s["topic"] == "/tf")
                .map(|s| &s["msg"])
                .collect();
            assert!(
                poses.len() >= 100 && tfs.len() >= 100,
                "{} poses, {} tf",
                poses.len(),
                tfs.len()
            );
            // The offset from the first pose whose position equals a tracked record's exactly.
            let first = poses[0];
            let p0 = &first["pose"]["position"];
            let anchor = tracked
                .iter()
                .find(|r| {
                    let p = r.position_mm.unwrap();
                    (f(&p0["x"]) - p[0] / 1e3).abs() < 1e-12
                        && (f(&p0["y"]) - p[1] / 1e3).abs() < 1e-12
                        && (f(&p0["z"]) - p[2] / 1e3).abs() < 1e-12
                })
                .expect("the first pose equals a record of the NDJSON stream");
            let offset = stamp_ns(&first["header"]) - i128::from(anchor.capture_ts_ns);
            let (mut worst_m, mut worst_q) = (0.0f64, 0.0f64);
            // A record the NDJSON client missed (a slow test client is dropped records, counted by
            // irtrackd) cannot be compared; every pose that has its record must equal it.
            let (mut compared, mut missing) = (0usize, 0usize);
            for m in &poses {
                assert_eq!(m["header"]["frame_id"], "irtrack_camera0_optical");
                let capture = u64::try_from(stamp_ns(&m["header"]) - offset).unwrap();
                let Some(rec) = by_capture.get(&capture) else {
                    missing += 1;
                    continue;
                };
                compared += 1;
                let p = rec.position_mm.unwrap();
                let q = rec.orientation_wxyz.unwrap();
                let pos = &m["pose"]["position"];
                let ori = &m["pose"]["orientation"];
                for (k, want) in ["x", "y", "z"].iter().zip(p) {
                    worst_m = worst_m.max((f(&pos[k]) - want / 1e3).abs());
                }
                for (k, want) in ["x", "y", "z", "w"].iter().zip([q[1], q[2], q[3], q[0]]) {
                    worst_q = worst_q.max((f(&ori[k]) - want).abs());
                }
            }
            for m in &tfs {
                let t = &m["transforms"][0];
                assert_eq!(t["header"]["frame_id"], "irtrack_camera0_optical");
                assert_eq!(t["child_frame_id"], "irtrack_probe4");
                let capture = u64::try_from(stamp_ns(&t["header"]) - offset).unwrap();
                let Some(rec) = by_capture.get(&capture) else {
                    continue;
                };
                let p = rec.position_mm.unwrap();
                let tr = &t["transform"]["translation"];
                for (k, want) in ["x", "y", "z"].iter().zip(p) {
                    worst_m = worst_m.max((f(&tr[k]) - want / 1e3).abs());
                }
            }
            println!(
                "ROS 2 vs NDJSON: {compared} of {} poses compared ({missing} without their NDJSON record), {} tf; largest difference {worst_m:.1e} m, quaternion {worst_q:.1e}",
                poses.len(),
                tfs.len()
            );
            assert!(
                compared >= 100 && missing * 10 <= poses.len(),
                "{compared} compared, {missing} missing"
            );
            assert!(worst_m < 1e-9, "{worst_m}");
            assert!(worst_q < 1e-9, "{worst_q}");
        },
    );
}

#[test]
fn ros2_single_led_is_a_point_stamped_reliable() {
    run_in_own_netns("ros2_single_led_is_a_point_stamped_reliable", || async {
        let dir = TempDir::new("ros2-led");
        let sub = subscriber(&[
            "--domain",
            "3",
            "--reliable",
            "--count",
            "100",
            "--seconds",
            "15",
            "/cell/irtrack/led/point=geometry_msgs/msg/PointStamped",
        ]);
        let sim = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nfps = 120.0\nseed = 3\nframes = 2400\n";
        let running = start(
            &dir,
            sim,
            "domain_id = 3\nnamespace = \"/cell/irtrack\"\nqos = \"reliable\"\n",
        )
        .await;
        let ndjson = NdjsonCollector::start(running.addrs.stream_ndjson).await;
        let (samples, done) = read_samples(sub).await;
        let records = ndjson.finish().await;
        let clients = running.outputs.ros2.clients.load(Ordering::Relaxed);
        running.shutdown().await;
        assert_eq!(samples.len(), 100, "{done}");
        let tracked: Vec<[f64; 3]> = records
            .iter()
            .filter(|r| r.status == TrackStatus::Ok)
            .filter_map(|r| r.position_mm)
            .collect();
        // Every point equals (in metres) a tracked record's position, in its order. The NDJSON
        // stream drops records for a client that falls behind (a loaded machine), which shows
        // as gaps in its frame numbers: at most that many points may have nothing to equal.
        let dropped: u64 = records
            .windows(2)
            .map(|w| w[1].frame.saturating_sub(w[0].frame).saturating_sub(1))
            .sum();
        let (mut next, mut unmatched) = (0usize, 0u64);
        for s in &samples {
            let m = &s["msg"];
            assert_eq!(m["header"]["frame_id"], "irtrack_camera0_optical");
            let p = [f(&m["point"]["x"]), f(&m["point"]["y"]), f(&m["point"]["z"])];
            match tracked[next..]
                .iter()
                .position(|t| (0..3).all(|i| (p[i] - t[i] / 1e3).abs() < 1e-12))
            {
                Some(at) => next += at + 1,
                None => unmatched += 1,
            }
        }
        println!(
            "ROS 2 single LED: {} of {} points equal the NDJSON stream, which dropped {dropped} frames; \
             {clients} subscription(s) matched",
            samples.len() as u64 - unmatched,
            samples.len()
        );
        assert!(
            unmatched <= dropped,
            "{unmatched} points are not on the NDJSON stream, which dropped only {dropped} frames"
        );
        assert!(
            samples.len() as u64 - unmatched >= 90,
            "{unmatched} of 100 points unmatched"
        );
    });
}

#[test]
fn ros2_configuration_errors_name_the_problem() {
    // The unknown-tool case joins a DDS domain before the tools are checked: kept in a
    // namespace too.
    run_in_own_netns("ros2_configuration_errors_name_the_problem", bad_configs);
}

async fn bad_configs() {
    let dir = TempDir::new("ros2-bad");
    let sim = "rig = \"convergent\"\nfps = 120.0\ntool = \"probe4\"\nframes = 10\n";
    for (ros2, want) in [
        (
            "domain_id = 300\n",
            "outputs.ros2.domain_id: 300 is not a DDS domain id",
        ),
        ("namespace = \"irtrack\"\n", "outputs.ros2.namespace"),
        (
            "tools = [\"wand\"]\n",
            "outputs.ros2.tools: unknown tool \"wand\"; the parameter set has probe4",
        ),
    ] {
        let toml = format!(
            "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n[outputs.ros2]\nenabled = true\n{ros2}"
        );
        let err = match irtrack_firmware::config::Config::from_toml(&toml, "ros2.toml") {
            Err(e) => e.to_string(),
            Ok(mut cfg) => {
                let base = test_config(dir.path());
                cfg.service.state_dir = base.service.state_dir;
                cfg.listen = base.listen;
                cfg.source.sim = Some(toml::from_str(sim).unwrap());
                match app::start(cfg, Overrides::default()).await {
                    Ok(r) => {
                        r.shutdown().await;
                        panic!("{ros2} was accepted")
                    }
                    Err(e) => e.to_string(),
                }
            }
        };
        assert!(err.contains(want), "{ros2}: {err}");
    }
}

/// The loop's sets per second over `secs`.
async fn sets_per_s(status: &irtrack_firmware::status::SharedStatus, secs: f64) -> f64 {
    let (n0, t0) = (status.sets_processed.load(Ordering::Relaxed), Instant::now());
    tokio::time::sleep(Duration::from_secs_f64(secs)).await;
    (status.sets_processed.load(Ordering::Relaxed) - n0) as f64 / t0.elapsed().as_secs_f64()
}

#[test]
fn ros2_stalled_subscriber_does_not_slow_the_loop() {
    run_in_own_netns("ros2_stalled_subscriber_does_not_slow_the_loop", || async {
        let dir = TempDir::new("ros2-stalled");
        // A reliable subscriber: once it stops (SIGSTOP) it acknowledges nothing, so the
        // reliable writer's window fills.
        let sub = subscriber(&[
            "--domain",
            "5",
            "--reliable",
            "--count",
            "100000",
            "--seconds",
            "60",
            "/irtrack/probe4/pose=geometry_msgs/msg/PoseStamped",
        ]);
        let sim = TOOL_SIM.replace("frames = 2400", "frames = 100000");
        let running = start(&dir, &sim, "domain_id = 5\nqos = \"reliable\"\n").await;
        let stats = running.outputs.ros2.clone();
        // It receives, then stops dead.
        for _ in 0..20 {
            let v = sub.next(Duration::from_secs(15)).expect("samples arrive");
            assert!(v.get("topic").is_some(), "{v}");
        }
        let before = sets_per_s(&running.status, 1.5).await;
        // SAFETY: kill(2) on our own child's pid.
        assert_eq!(unsafe { libc::kill(sub.child.id() as i32, libc::SIGSTOP) }, 0);
        let sent0 = stats.frames_sent.load(Ordering::Relaxed);
        let during = sets_per_s(&running.status, 3.0).await;
        let (sent, dropped, skipped, clients) = (
            stats.frames_sent.load(Ordering::Relaxed),
            stats.send_drops.load(Ordering::Relaxed),
            stats.slot_skips.load(Ordering::Relaxed),
            stats.clients.load(Ordering::Relaxed),
        );
        println!(
            "DDS subscriber stalled (SIGSTOP, reliable QoS): loop {before:.1} → {during:.1} sets/s; sent {sent} (+{} while stalled), dropped {dropped}, skipped {skipped}, matched subscriptions {clients}, capture→published p50 {:?} µs",
            sent - sent0,
            stats.latency.snapshot().summary().p50_us,
        );
        let l = stats.latency.snapshot().summary();
        let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1}"));
        // For `cargo xtask bench --latency`'s output rows (µs).
        println!(
            "OUTPUT-LATENCY|ROS 2 over DDS, reliable, 1 subscriber (stopped half way)|{}|{}|{}|{}|{}",
            l.count,
            f(l.p50_us),
            f(l.p90_us),
            f(l.p99_us),
            f(l.max_us)
        );
        drop(sub);
        running.shutdown().await;
        assert!(
            during >= 0.95 * before,
            "loop slowed: {before:.1} → {during:.1} sets/s"
        );
        // The publisher kept going while the reader was stopped (published or dropped).
        assert!(sent - sent0 + dropped >= 300, "{sent} {sent0} {dropped}");
    });
}

/// The multi-tool simulator of firmware/tests/multitool_service.rs: `probe4`, `tri3` and
/// `wing4` on crossing paths and one loose single LED crossing them.
const MULTI_SIM: &str = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 60.0\nperiod_s = 6.0\nfps = 120.0\nseed = 29\ntool = \"probe4\"\nextra_tools = [\"tri3\", \"wing4\"]\nloose_leds = 1\ntool_rotation_deg = 20.0\nframes = 2400\n";
const MULTI_NAMES: [&str; 3] = ["probe4", "tri3", "wing4"];

/// irtrackd's NDJSON stream with per-tool and loose-LED records (`tools\n`), read in the
/// background: per capture time, every tool's record and the loose LEDs' records.
struct ToolCollector {
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<ToolStream>,
}

#[derive(Default)]
struct ToolStream {
    /// (tool name, capture ns) → record.
    tools: HashMap<(String, u64), PositionRecord>,
    /// capture ns → the set's loose LEDs (id, position mm).
    loose: HashMap<u64, Vec<(u32, [f64; 3])>>,
    /// Capture times of the main records after the first tool records.
    sets: Vec<u64>,
}

impl ToolCollector {
    async fn start(addr: std::net::SocketAddr) -> Self {
        use irtrack_core::stream::{LooseRecord, ToolRecord};
        use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(b"tools\n").await.unwrap();
        let mut lines = BufReader::new(s).lines();
        // Wait for the first tool record, so a subscriber started next misses nothing.
        let first = loop {
            let line = lines.next_line().await.unwrap().expect("stream open");
            if line.starts_with("{\"tool_id\"") {
                break ToolRecord::from_ndjson_line(&line).unwrap();
            }
        };
        let (stop, mut stopped) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(async move {
            let mut out = ToolStream::default();
            let add_tool = |out: &mut ToolStream, t: ToolRecord| {
                out.tools
                    .insert((t.name().to_string(), t.record.capture_ts_ns), t.record);
            };
            add_tool(&mut out, first);
            loop {
                tokio::select! {
                    _ = &mut stopped => break,
                    r = lines.next_line() => match r {
                        Ok(Some(line)) if line.starts_with("{\"tool_id\"") => {
                            add_tool(&mut out, ToolRecord::from_ndjson_line(&line).unwrap());
                        }
                        Ok(Some(line)) if line.starts_with("{\"loose_id\"") => {
                            let l = LooseRecord::from_ndjson_line(&line).unwrap();
                            out.loose
                                .entry(l.record.capture_ts_ns)
                                .or_default()
                                .push((l.loose_id, l.record.position_mm.unwrap()));
                        }
                        Ok(Some(line)) => {
                            out.sets.push(PositionRecord::from_ndjson_line(&line).unwrap().capture_ts_ns);
                        }
                        _ => break,
                    },
                }
            }
            out
        });
        Self { stop, task }
    }

    async fn finish(self) -> ToolStream {
        tokio::time::sleep(Duration::from_millis(300)).await;
        let _ = self.stop.send(());
        self.task.await.unwrap()
    }
}

/// The loose LEDs of a `PointCloud2` sample: (loose_id, x y z metres).
fn cloud_points(m: &Value) -> Vec<(u32, [f64; 3])> {
    let fields: Vec<(&str, u64, u64)> = m["fields"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["name"].as_str().unwrap(),
                f["offset"].as_u64().unwrap(),
                f["datatype"].as_u64().unwrap(),
            )
        })
        .collect();
    // x y z float32 (7), loose_id uint32 (6), 16 bytes a point, little-endian.
    assert_eq!(
        fields,
        vec![("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("loose_id", 12, 6)]
    );
    assert_eq!(
        (m["point_step"].as_u64(), m["height"].as_u64()),
        (Some(16), Some(1))
    );
    assert_eq!(m["is_bigendian"], false);
    let data: Vec<u8> = m["data"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b.as_u64().unwrap() as u8)
        .collect();
    let width = m["width"].as_u64().unwrap() as usize;
    assert_eq!(data.len(), 16 * width);
    assert_eq!(m["row_step"].as_u64(), Some(16 * width as u64));
    data.chunks_exact(16)
        .map(|p| {
            let f = |i: usize| f64::from(f32::from_le_bytes(p[i..i + 4].try_into().unwrap()));
            (
                u32::from_le_bytes(p[12..16].try_into().unwrap()),
                [f(0), f(4), f(8)],
            )
        })
        .collect()
}

#[test]
fn ros2_three_tools_and_the_loose_led_equal_the_ndjson_records_of_their_frames() {
    run_in_own_netns(
        "ros2_three_tools_and_the_loose_led_equal_the_ndjson_records_of_their_frames",
        || async {
            let dir = TempDir::new("ros2-multi");
            let pose_topics: Vec<String> = MULTI_NAMES
                .iter()
                .map(|n| format!("/irtrack/{n}/pose=geometry_msgs/msg/PoseStamped"))
                .collect();
            let mut args = vec!["--domain", "9", "--count", "1200", "--seconds", "15"];
            args.extend(pose_topics.iter().map(String::as_str));
            args.push("/irtrack/loose/points=sensor_msgs/msg/PointCloud2");
            args.push("/tf=tf2_msgs/msg/TFMessage");
            let sub = subscriber(&args);
            let running = start(&dir, MULTI_SIM, "domain_id = 9\n").await;
            let ndjson = ToolCollector::start(running.addrs.stream_ndjson).await;
            let (samples, done) = read_samples(sub).await;
            let stream = ndjson.finish().await;
            running.shutdown().await;
            println!(
                "ROS 2, 3 tools + loose LED: subscriber {done}; NDJSON {} sets",
                stream.sets.len()
            );

            // The stamp offset (wall clock − capture clock) from the first pose that equals a
            // tool record of the same tool exactly.
            let poses: Vec<(&str, &Value)> = samples
                .iter()
                .filter_map(|s| {
                    let t = s["topic"].as_str()?;
                    let name = t.strip_prefix("/irtrack/")?.strip_suffix("/pose")?;
                    Some((name, &s["msg"]))
                })
                .collect();
            let (name0, first) = poses[0];
            let p0 = &first["pose"]["position"];
            let anchor = stream
                .tools
                .iter()
                .filter(|((n, _), r)| n == name0 && r.status == TrackStatus::Ok)
                .find(|(_, r)| {
                    let p = r.position_mm.unwrap();
                    (f(&p0["x"]) - p[0] / 1e3).abs() < 1e-12
                        && (f(&p0["y"]) - p[1] / 1e3).abs() < 1e-12
                        && (f(&p0["z"]) - p[2] / 1e3).abs() < 1e-12
                })
                .map(|((_, c), _)| *c)
                .expect("the first pose equals a tool record of the NDJSON stream");
            let offset = stamp_ns(&first["header"]) - i128::from(anchor);
            let capture = |h: &Value| u64::try_from(stamp_ns(h) - offset).unwrap();

            // Every tool is published on its own topic; each pose equals its tool's record of
            // that frame (position and orientation).
            let (mut worst_m, mut worst_q) = (0.0f64, 0.0f64);
            let mut compared = [0usize; 3];
            for (name, m) in &poses {
                let i = MULTI_NAMES.iter().position(|n| n == name).unwrap();
                assert_eq!(m["header"]["frame_id"], "irtrack_camera0_optical");
                let Some(rec) = stream.tools.get(&(name.to_string(), capture(&m["header"]))) else {
                    continue;
                };
                assert_eq!(
                    rec.status,
                    TrackStatus::Ok,
                    "{name}: a pose for an untracked record"
                );
                compared[i] += 1;
                let p = rec.position_mm.unwrap();
                let q = rec.orientation_wxyz.unwrap();
                let (pos, ori) = (&m["pose"]["position"], &m["pose"]["orientation"]);
                for (k, want) in ["x", "y", "z"].iter().zip(p) {
                    worst_m = worst_m.max((f(&pos[k]) - want / 1e3).abs());
                }
                for (k, want) in ["x", "y", "z", "w"].iter().zip([q[1], q[2], q[3], q[0]]) {
                    worst_q = worst_q.max((f(&ori[k]) - want).abs());
                }
            }
            // /tf: every tool's child frame by name, at its record's position.
            let mut tf_frames: HashMap<String, usize> = HashMap::new();
            for s in samples.iter().filter(|s| s["topic"] == "/tf") {
                for t in s["msg"]["transforms"].as_array().unwrap() {
                    let child = t["child_frame_id"].as_str().unwrap().to_string();
                    *tf_frames.entry(child.clone()).or_default() += 1;
                    let name = child.strip_prefix("irtrack_").unwrap().to_string();
                    if let Some(rec) = stream.tools.get(&(name, capture(&t["header"]))) {
                        let p = rec.position_mm.unwrap();
                        let tr = &t["transform"]["translation"];
                        for (k, want) in ["x", "y", "z"].iter().zip(p) {
                            worst_m = worst_m.max((f(&tr[k]) - want / 1e3).abs());
                        }
                    }
                }
            }
            // The loose LED: each cloud holds exactly the loose records of its frame.
            let (mut clouds, mut clouds_compared, mut points) = (0usize, 0usize, 0usize);
            let mut worst_loose_m = 0.0f64;
            for s in samples.iter().filter(|s| s["topic"] == "/irtrack/loose/points") {
                let m = &s["msg"];
                assert_eq!(m["header"]["frame_id"], "irtrack_camera0_optical");
                clouds += 1;
                let got = cloud_points(m);
                let c = capture(&m["header"]);
                if !stream.sets.contains(&c) {
                    continue;
                }
                clouds_compared += 1;
                let want = stream.loose.get(&c).cloned().unwrap_or_default();
                assert_eq!(
                    got.iter().map(|g| g.0).collect::<Vec<_>>(),
                    want.iter().map(|w| w.0).collect::<Vec<_>>(),
                    "loose ids of the frame"
                );
                for ((_, g), (_, w)) in got.iter().zip(&want) {
                    points += 1;
                    for k in 0..3 {
                        worst_loose_m = worst_loose_m.max((g[k] - w[k] / 1e3).abs());
                    }
                }
            }
            println!(
                "ROS 2 vs NDJSON: poses compared per tool {compared:?}; /tf child frames {tf_frames:?}; largest difference {worst_m:.1e} m, quaternion {worst_q:.1e}; {clouds} loose clouds ({clouds_compared} compared, {points} points), largest loose difference {worst_loose_m:.1e} m (float32)"
            );
            for (i, n) in MULTI_NAMES.iter().enumerate() {
                assert!(compared[i] >= 50, "{n}: only {} poses compared", compared[i]);
                assert!(
                    tf_frames.get(&format!("irtrack_{n}")).is_some_and(|&c| c >= 50),
                    "{n} in /tf: {tf_frames:?}"
                );
            }
            assert!(worst_m < 1e-9, "{worst_m}");
            assert!(worst_q < 1e-9, "{worst_q}");
            assert!(
                clouds_compared >= 50 && points >= 40,
                "{clouds_compared} clouds, {points} points"
            );
            // float32 metres: half an ulp at ~1 m is 3e-8 m.
            assert!(worst_loose_m < 1e-6, "{worst_loose_m}");
        },
    );
}
