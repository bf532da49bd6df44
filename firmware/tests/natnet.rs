//! irtrackd's NatNet output against an independent client: PyPI's pure-Python `natnet`
//! (firmware/tests/py/natnet_client.py) runs as a separate process, connects, reads the model
//! definitions and frames; what it decodes must equal irtrackd's own NDJSON stream.

mod common;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::time::Duration;

use common::*;
use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_firmware::app::{self, Overrides};
use serde_json::Value;

const CLIENT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/py/natnet_client.py");

/// Runs the Python client against `addr` until it has `frames` frames (or `timeout_s`).
async fn python_client(addr: SocketAddr, frames: usize, timeout_s: f64, extra: &[String]) -> Value {
    let mut cmd = std::process::Command::new("python3");
    cmd.arg(CLIENT)
        .arg(addr.ip().to_string())
        .arg(addr.port().to_string())
        .arg(frames.to_string())
        .arg(timeout_s.to_string())
        .args(extra);
    let out = tokio::task::spawn_blocking(move || cmd.output())
        .await
        .unwrap()
        .expect("python3 runs");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "NatNet client failed ({}); is PyPI's `natnet` installed (cargo xtask setup)?\n{stderr}",
        out.status
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("client output: {e}\n{stderr}"))
}

/// irtrackd's own stream from the collector's start until `finish`, by frame number.
async fn by_frame(ndjson: NdjsonCollector) -> HashMap<u32, PositionRecord> {
    ndjson
        .finish()
        .await
        .into_iter()
        .map(|r| (r.frame as u32, r))
        .collect()
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

fn vec3(v: &Value) -> [f64; 3] {
    [f(&v[0]), f(&v[1]), f(&v[2])]
}

/// irtrackd with `[outputs.natnet]` enabled, its command socket on 127.0.0.1:0, and
/// `natnet_toml` in that table.
async fn start(dir: &TempDir, sim_toml: &str, natnet_toml: &str) -> app::Running {
    let table = format!("[outputs.natnet]\nenabled = true\ncommand = \"127.0.0.1:0\"\n{natnet_toml}");
    start_with(dir, sim_toml, &table).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn natnet_client_reads_tool_rigid_bodies_equal_to_the_ndjson_stream() {
    let dir = TempDir::new("natnet-tool");
    let sim = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nperiod_s = 6.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\nframes = 900\n";
    let running = start(&dir, sim, "transport = \"unicast\"\n").await;
    let natnet = running.addrs.natnet.expect("NatNet enabled");
    assert!(running.addrs.ready_line().ends_with(&format!(" natnet={natnet}")));
    let ndjson = NdjsonCollector::start(running.addrs.stream_ndjson).await;

    let got = python_client(natnet, 150, 10.0, &[]).await;
    let by_frame = by_frame(ndjson).await;
    let stats = running.outputs.natnet.clone();
    running.shutdown().await;

    assert_eq!(got["server"]["name"], "irtrackd");
    assert_eq!(got["server"]["natnet"], "3.1.0.0");
    assert_eq!(got["complete"], true, "{got}");
    // Model definitions: the tool as a marker set and as rigid body 1 with its 4 LEDs.
    let models = &got["models"][0];
    assert_eq!(models["marker_sets"][0][0], "probe4");
    assert_eq!(models["marker_sets"][0][1].as_array().unwrap().len(), 4);
    let rb = &models["rigid_bodies"][0];
    assert_eq!(
        (rb["name"].as_str(), rb["id"].as_u64()),
        (Some("probe4"), Some(1))
    );
    let layout: Vec<[f64; 3]> = rb["markers"].as_array().unwrap().iter().map(vec3).collect();
    assert_eq!(layout.len(), 4);
    // probe4's LEDs are 99 mm apart (LED 0 to LED 1), in metres.
    let d01 = dist_mm(layout[0], layout[1]);
    assert!((d01 - 0.099).abs() < 1e-6, "{d01}");

    let frames = got["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 150);
    let (mut compared, mut worst_m, mut worst_q) = (0usize, 0.0f64, 0.0f64);
    let mut not_on_stream = 0usize;
    let mut last_frame = None;
    for fr in frames {
        let n = fr["frame"].as_u64().unwrap() as u32;
        if let Some(last) = last_frame {
            assert!(n > last, "frames out of order: {last} then {n}");
        }
        last_frame = Some(n);
        // The NDJSON stream drops records for a client that falls behind (a loaded machine):
        // such a frame has nothing to compare with and is counted, as in the two-tool test.
        let Some(rec) = by_frame.get(&n) else {
            not_on_stream += 1;
            continue;
        };
        assert_eq!(fr["stamp_mid_exposure"].as_u64(), Some(rec.capture_ts_ns));
        let body = &fr["rigid_bodies"][0];
        assert_eq!(body["id"], 1);
        let tracked = rec.status == TrackStatus::Ok;
        assert_eq!(body["valid"], tracked, "frame {n}");
        if !tracked {
            continue;
        }
        let p = rec.position_mm.unwrap();
        let q = rec.orientation_wxyz.unwrap();
        let pos = vec3(&body["pos"]);
        let rot = body["rot"].as_array().unwrap();
        for i in 0..3 {
            worst_m = worst_m.max((pos[i] - p[i] / 1e3).abs());
        }
        // NatNet: x y z w; the stream: w x y z (same sign convention, w ≥ 0).
        for (i, c) in [q[1], q[2], q[3], q[0]].iter().enumerate() {
            worst_q = worst_q.max((f(&rot[i]) - c).abs());
        }
        assert!((f(&body["error"]) - rec.gap_mm / 1e3).abs() < 1e-7);
        // Labelled markers: the 4 LEDs of rigid body 1, model-solved, keeping the layout.
        let labeled = fr["labeled"].as_array().unwrap();
        assert_eq!(labeled.len(), 4);
        for (i, m) in labeled.iter().enumerate() {
            assert_eq!(m["id"].as_u64(), Some((1 << 16) | (i as u64 + 1)));
            assert_eq!(m["param"], 0x0C);
        }
        let m0 = vec3(&labeled[0]["pos"]);
        let m1 = vec3(&labeled[1]["pos"]);
        assert!((dist_mm(m0, m1) - d01).abs() < 1e-5);
        assert_eq!(vec3(&fr["marker_sets"][0][1][1]), m1);
        compared += 1;
    }
    println!(
        "NatNet vs NDJSON: {compared} tracked frames, largest position difference {worst_m:.2e} m, quaternion {worst_q:.2e}; \
         {not_on_stream} frames not on the NDJSON stream"
    );
    assert!(compared >= 100, "only {compared} tracked frames compared");
    assert!(worst_m <= 1e-4, "{worst_m} m");
    assert!(worst_q <= 1e-4, "{worst_q}");
    let sent = stats.frames_sent.load(std::sync::atomic::Ordering::Relaxed);
    assert!(sent >= 150, "{sent}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn natnet_single_led_is_an_unlabelled_marker_in_y_up_axes() {
    let dir = TempDir::new("natnet-led");
    let sim = "fps = 200.0\nframes = 900\n";
    let running = start(&dir, sim, "transport = \"unicast\"\naxes = \"y_up\"\n").await;
    let natnet = running.addrs.natnet.unwrap();
    let ndjson = NdjsonCollector::start(running.addrs.stream_ndjson).await;
    let got = python_client(natnet, 150, 10.0, &[]).await;
    let by_frame = by_frame(ndjson).await;
    running.shutdown().await;

    let models = &got["models"][0];
    assert_eq!(models["marker_sets"][0][0], "led");
    assert!(models["rigid_bodies"].as_array().unwrap().is_empty());
    let (mut compared, mut worst) = (0usize, 0.0f64);
    for fr in got["frames"].as_array().unwrap() {
        let n = fr["frame"].as_u64().unwrap() as u32;
        // Both read the latest-value slot on their own: under load either may skip a record.
        let Some(rec) = by_frame.get(&n) else { continue };
        assert!(fr["rigid_bodies"].as_array().unwrap().is_empty());
        let Some(p) = rec.position_mm.filter(|_| rec.status == TrackStatus::Ok) else {
            assert!(fr["unlabeled"].as_array().unwrap().is_empty());
            continue;
        };
        assert!(!rec.world_frame);
        // Camera-0 frame → Y up: (x, −y, −z), metres.
        let want = [p[0] / 1e3, -p[1] / 1e3, -p[2] / 1e3];
        let u = vec3(&fr["unlabeled"][0]);
        let l = &fr["labeled"][0];
        assert_eq!((l["id"].as_u64(), l["param"].as_u64()), (Some(1), Some(0x12)));
        for i in 0..3 {
            worst = worst.max((u[i] - want[i]).abs());
        }
        assert_eq!(vec3(&l["pos"]), u);
        assert_eq!(vec3(&fr["marker_sets"][0][1][0]), u);
        compared += 1;
    }
    println!("NatNet single LED vs NDJSON: {compared} frames, largest difference {worst:.2e} m");
    assert!(compared >= 100, "{compared}");
    assert!(worst <= 1e-4, "{worst}");
}

#[tokio::test]
async fn natnet_configuration_errors_name_the_problem() {
    let dir = TempDir::new("natnet-config");
    // Port in use.
    let taken = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    let mut cfg = test_config(dir.path());
    cfg.outputs.natnet.enabled = true;
    cfg.outputs.natnet.command = taken.local_addr().unwrap().to_string();
    let e = app::start(cfg, Overrides::default())
        .await
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("cannot listen for NatNet command on 127.0.0.1:"),
        "{e}"
    );
    // Not a multicast group; unknown key; bad address.
    for (table, want) in [
        (
            "enabled = true\nmulticast_group = \"10.1.2.3\"",
            "outputs.natnet.multicast_group: 10.1.2.3 is not a multicast address",
        ),
        (
            "enabled = true\ncommand = \"nowhere\"",
            "outputs.natnet.command: \"nowhere\" is not an address",
        ),
        ("enabled = true\naxes = \"z_down\"", "unknown variant `z_down`"),
        ("enabled = true\nport = 1510", "unknown field `port`"),
        (
            "enabled = true\nclient_networks = [\"10.1.2.3/16\"]",
            "outputs.natnet.client_networks: \"10.1.2.3/16\" has host bits set (the network is 10.1.0.0/16)",
        ),
        (
            "enabled = true\nclient_networks = [\"lab\"]",
            "outputs.natnet.client_networks: \"lab\" is not a network",
        ),
        (
            "enabled = true\nmax_clients_per_address = 0",
            "outputs.natnet.max_clients_per_address: must be at least 1",
        ),
        (
            "enabled = true\nreplies_per_s = 0.5",
            "outputs.natnet.replies_per_s: 0.5 must be a number of replies per second >= 1",
        ),
    ] {
        let text = format!("[outputs.natnet]\n{table}\n");
        let e = irtrack_firmware::config::Config::from_toml(&text, "x.toml")
            .unwrap_err()
            .to_string();
        assert!(e.contains(want), "{table}: {e}");
    }
    // Disabled by default: nothing bound, no natnet= in the ready line.
    let cfg = test_config(dir.path());
    assert!(!cfg.outputs.natnet.enabled);
    let running = app::start(cfg, Overrides::default()).await.unwrap();
    assert!(running.addrs.natnet.is_none() && !running.addrs.ready_line().contains("natnet"));
    running.shutdown().await;
}

/// Multicast (NatNet's default transport): frames go to 239.255.42.99:1511 on loopback, the
/// Python client joins the group. Runs inside a network namespace of its own (multicast on its
/// `lo`), so nothing reaches the real network.
#[test]
fn natnet_multicast_frames_reach_a_client_that_joined_the_group() {
    run_in_own_netns(
        "natnet_multicast_frames_reach_a_client_that_joined_the_group",
        || async {
            let dir = TempDir::new("natnet-multicast");
            let sim = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nperiod_s = 6.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\ntool_rotation_deg = 20.0\nframes = 900\n";
            let running = start(
            &dir,
            sim,
            "transport = \"multicast\"\nmulticast_group = \"239.255.42.99\"\nmulticast_interface = \"127.0.0.1\"\ndata_port = 1511\n",
        )
        .await;
            let natnet = running.addrs.natnet.unwrap();
            let ndjson = NdjsonCollector::start(running.addrs.stream_ndjson).await;
            let extra = ["multicast".to_string(), "239.255.42.99".into(), "1511".into()];
            let got = python_client(natnet, 120, 10.0, &extra).await;
            let by_frame = by_frame(ndjson).await;
            let sent = running
                .outputs
                .natnet
                .frames_sent
                .load(std::sync::atomic::Ordering::Relaxed);
            running.shutdown().await;
            assert_eq!(got["complete"], true, "{got}");
            let (mut compared, mut worst_m) = (0usize, 0.0f64);
            for fr in got["frames"].as_array().unwrap() {
                let n = fr["frame"].as_u64().unwrap() as u32;
                let Some(rec) = by_frame.get(&n) else { continue };
                let Some(p) = rec.position_mm.filter(|_| rec.status == TrackStatus::Ok) else {
                    continue;
                };
                let pos = vec3(&fr["rigid_bodies"][0]["pos"]);
                for i in 0..3 {
                    worst_m = worst_m.max((pos[i] - p[i] / 1e3).abs());
                }
                compared += 1;
            }
            println!(
                "NatNet multicast: {compared} tracked frames compared, largest difference {worst_m:.2e} m; {sent} frames sent to the group"
            );
            assert!(compared >= 80, "{compared}");
            assert!(worst_m <= 1e-4, "{worst_m}");
        },
    );
}

/// Per-tool records by (frame, tool id) and loose LEDs by frame: (loose id, position mm, gap mm).
type Collected = (
    HashMap<(u32, u8), irtrack_core::stream::ToolRecord>,
    HashMap<u32, Vec<(u32, [f64; 3], f64)>>,
);

/// Collects every per-tool NDJSON record (the client asks with `tools\n`) by (frame, tool id),
/// and the loose LEDs' positions by frame, until the stream is quiet for 2 s; returns once the
/// first tool record arrived.
async fn collect_tool_records(addr: SocketAddr) -> tokio::task::JoinHandle<Collected> {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(b"tools\n").await.unwrap();
    let mut lines = tokio::io::BufReader::new(s).lines();
    let mut by_key = HashMap::new();
    loop {
        let line = tokio::time::timeout(Duration::from_secs(10), lines.next_line())
            .await
            .expect("no record within 10 s")
            .unwrap()
            .unwrap();
        if line.starts_with("{\"tool_id\"") {
            let t = irtrack_core::stream::ToolRecord::from_ndjson_line(&line).unwrap();
            by_key.insert((t.record.frame as u32, t.tool_id), t);
            break;
        }
    }
    tokio::spawn(async move {
        let mut loose: HashMap<u32, Vec<(u32, [f64; 3], f64)>> = HashMap::new();
        while let Ok(Ok(Some(line))) = tokio::time::timeout(Duration::from_secs(2), lines.next_line()).await {
            if line.starts_with("{\"tool_id\"") {
                let t = irtrack_core::stream::ToolRecord::from_ndjson_line(&line).unwrap();
                by_key.insert((t.record.frame as u32, t.tool_id), t);
            } else if line.starts_with("{\"loose_id\"") {
                let l = irtrack_core::stream::LooseRecord::from_ndjson_line(&line).unwrap();
                loose.entry(l.record.frame as u32).or_default().push((
                    l.loose_id,
                    l.record.position_mm.unwrap(),
                    l.record.gap_mm,
                ));
            }
        }
        (by_key, loose)
    })
}

/// `[source.sim]` of the two-tool test: `probe4` and `tri3` on circles of 50 mm radius (their
/// images cross often) and a loose LED, 900 frames at 120 fps.
const TWO_TOOLS_SIM: &str = "rig = \"convergent\"\ndistance_mm = 1000.0\nradius_mm = 50.0\nperiod_s = 6.0\nfps = 120.0\nseed = 6\ntool = \"probe4\"\nextra_tools = [\"tri3\"]\nloose_leds = 1\ntool_rotation_deg = 20.0\nframes = 900\n";

/// The two-tool test's scenario tracked straight from the simulator (`MultiTracker` with the
/// default settings, no daemon), frame by frame against the truth: `tri3` is untracked only
/// where fewer than 3 of its LEDs are seen on their own by 2 or more cameras, i.e. where its
/// spots merge with `probe4`'s or leave a camera's image (the simulator has no LED beam
/// angle). Prints the classification of every frame and the untracked stretches.
#[test]
fn two_tool_scenario_leaves_tri3_untracked_only_where_it_is_not_seen() {
    let sim: irtrack_firmware::source::sim::SimSourceConfig = toml::from_str(TWO_TOOLS_SIM).unwrap();
    let tools = sim.tool_definitions();
    let r = irtrack_sim::multibody::run_scene(
        sim.scenario_config(),
        &tools,
        sim.frames.unwrap_or(900),
        irtrack_core::pose6d::PoseConfig::default(),
        &|| 0,
    )
    .unwrap();
    print!(
        "{}",
        irtrack_sim::multibody::report("NatNet two-tool scenario", &r)
    );
    for (k, st) in r.tools.iter().enumerate() {
        let name = &tools[k].name;
        let count = |f: &dyn Fn(&irtrack_sim::multibody::ToolFrame) -> bool| {
            st.frames.iter().filter(|x| f(x)).count()
        };
        // Not seen: how many LEDs each camera pair lacks, and why (merged spots or outside).
        let by_leds_seen =
            |n: usize| count(&|x| !x.seen && !x.tracked && x.alone.iter().filter(|&&c| c >= 2).count() == n);
        println!(
            "{name}: {} frames; tracked and seen {}, tracked though not seen {}, seen but untracked {}, \
             untracked and not seen {} (LEDs seen on their own by 2+ cameras: 2 in {}, 1 in {}, 0 in {})",
            st.frames.len(),
            count(&|x| x.tracked && x.seen),
            count(&|x| x.tracked && !x.seen),
            count(&|x| !x.tracked && x.seen),
            count(&|x| !x.tracked && !x.seen),
            by_leds_seen(2),
            by_leds_seen(1),
            by_leds_seen(0),
        );
        // Untracked stretches: where, how long, and why the LEDs were not seen.
        let mut i = 0;
        while i < st.frames.len() {
            if st.frames[i].tracked {
                i += 1;
                continue;
            }
            let start = i;
            while i < st.frames.len() && !st.frames[i].tracked {
                i += 1;
            }
            let run = &st.frames[start..i];
            let leds = tools[k].leds_mm.len();
            let (mut merged, mut outside) = (0usize, 0usize);
            for x in run {
                merged += x.merged[..leds].iter().map(|&c| c as usize).sum::<usize>();
                outside += x.outside[..leds].iter().map(|&c| c as usize).sum::<usize>();
            }
            println!(
                "  untracked frames {start}..{i} ({}): seen in {}, causes {:?}; LED images per frame: \
                 {:.1} merged, {:.1} outside",
                i - start,
                run.iter().filter(|x| x.seen).count(),
                run.iter()
                    .filter_map(|x| x.cause)
                    .collect::<std::collections::BTreeSet<_>>(),
                merged as f64 / run.len() as f64,
                outside as f64 / run.len() as f64,
            );
        }
        assert!(
            st.tracked_share_pct() >= 99.0,
            "{name}: tracked in {:.2} % of the frames it is seen",
            st.tracked_share_pct()
        );
    }
}

/// Two tools and a loose LED at once: a rigid body per tool in the model definitions and in
/// every frame, each equal to that tool's per-tool record on the NDJSON stream; the loose LEDs
/// of each frame are its unlabelled markers (legacy list) and labelled markers of model 0 with
/// the unlabelled flag (what NatNet 3+ clients read), equal to the NDJSON stream's loose records.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn natnet_client_reads_a_rigid_body_per_tool() {
    let dir = TempDir::new("natnet-two-tools");
    let running = start(&dir, TWO_TOOLS_SIM, "transport = \"unicast\"\n").await;
    let natnet = running.addrs.natnet.expect("NatNet enabled");
    let tools = collect_tool_records(running.addrs.stream_ndjson).await;
    // 300 frames (2.5 s): tri3 cannot be seen in frames 15..119 of its 6 s path (one of its
    // three LEDs merges with a probe4 spot; see the test above), so a shorter window that
    // starts there (its start follows the daemon's start-up time) compares too few poses.
    let got = python_client(natnet, 300, 15.0, &[]).await;
    let (by_key, loose) = tools.await.unwrap();
    running.shutdown().await;

    assert_eq!(got["complete"], true, "{got}");
    let models = &got["models"][0];
    let names: Vec<(&str, u64, usize)> = models["rigid_bodies"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| {
            (
                b["name"].as_str().unwrap(),
                b["id"].as_u64().unwrap(),
                b["markers"].as_array().unwrap().len(),
            )
        })
        .collect();
    assert_eq!(names, [("probe4", 1, 4), ("tri3", 2, 3)]);
    assert_eq!(models["marker_sets"][1][0], "tri3");

    let (mut compared, mut worst_m, mut worst_q) = ([0usize; 2], 0.0f64, 0.0f64);
    let (mut loose_frames, mut worst_loose_m) = (0usize, 0.0f64);
    let (mut labelled_loose, mut worst_labelled_m) = (0usize, 0.0f64);
    let mut not_on_stream = 0usize;
    for fr in got["frames"].as_array().unwrap() {
        let n = fr["frame"].as_u64().unwrap() as u32;
        // Unlabelled markers: the frame's loose LEDs, in the stream's order (by id).
        let unlabelled = fr["unlabeled"].as_array().unwrap();
        let expected = loose.get(&n).map_or(&[][..], |v| &v[..]);
        if by_key.contains_key(&(n, 0)) {
            assert_eq!(
                unlabelled.len(),
                expected.len(),
                "frame {n}: {unlabelled:?} vs {expected:?}"
            );
            for (u, (_, p, _)) in unlabelled.iter().zip(expected) {
                let u = vec3(u);
                for i in 0..3 {
                    worst_loose_m = worst_loose_m.max((u[i] - p[i] / 1e3).abs());
                }
            }
            loose_frames += usize::from(!expected.is_empty());
            // NatNet 3+ clients read the labelled list: each loose LED is there as a marker of
            // model 0 (id = loose_id + 1) flagged unlabelled, not as a model's.
            let model0: Vec<&Value> = fr["labeled"]
                .as_array()
                .unwrap()
                .iter()
                .filter(|m| m["id"].as_u64().unwrap() >> 16 == 0)
                .collect();
            assert_eq!(
                model0.len(),
                expected.len(),
                "frame {n}: {model0:?} vs {expected:?}"
            );
            for (m, (id, p, gap)) in model0.iter().zip(expected) {
                assert_eq!(m["id"].as_u64(), Some(u64::from(*id) + 1), "frame {n}");
                let param = m["param"].as_u64().unwrap();
                assert_eq!(
                    param & 0x10,
                    0x10,
                    "frame {n}: unlabelled flag missing in {param:#x}"
                );
                assert_eq!(param & 0x0C, 0, "frame {n}: model flags in {param:#x}");
                let q = vec3(&m["pos"]);
                for i in 0..3 {
                    worst_labelled_m = worst_labelled_m.max((q[i] - p[i] / 1e3).abs());
                }
                assert!(
                    (f(&m["residual"]) - gap / 1e3).abs() < 1e-6,
                    "frame {n}: residual {m}"
                );
                labelled_loose += 1;
            }
        }
        let bodies = fr["rigid_bodies"].as_array().unwrap();
        assert_eq!(bodies.len(), 2, "frame {n}");
        for (k, body) in bodies.iter().enumerate() {
            assert_eq!(body["id"].as_u64(), Some(k as u64 + 1));
            // The NDJSON stream drops records for a client that falls behind (a loaded
            // machine); such frames have nothing to compare with and are counted.
            let Some(t) = by_key.get(&(n, k as u8)) else {
                not_on_stream += 1;
                continue;
            };
            let tracked = t.record.status == TrackStatus::Ok;
            assert_eq!(body["valid"], tracked, "frame {n} tool {k}");
            if !tracked {
                continue;
            }
            let p = t.record.position_mm.unwrap();
            let q = t.record.orientation_wxyz.unwrap();
            let pos = vec3(&body["pos"]);
            for i in 0..3 {
                worst_m = worst_m.max((pos[i] - p[i] / 1e3).abs());
            }
            let rot = body["rot"].as_array().unwrap();
            for (i, c) in [q[1], q[2], q[3], q[0]].iter().enumerate() {
                worst_q = worst_q.max((f(&rot[i]) - c).abs());
            }
            compared[k] += 1;
        }
    }
    println!(
        "NatNet, two tools: probe4 {} and tri3 {} tracked frames compared, largest difference {worst_m:.2e} m, \
         quaternion {worst_q:.2e}; {not_on_stream} tool frames not on the NDJSON stream",
        compared[0], compared[1]
    );
    println!(
        "NatNet, loose LEDs: {loose_frames} frames with unlabelled markers, largest difference {worst_loose_m:.2e} m"
    );
    assert!(compared[0] >= 100 && compared[1] >= 50, "{compared:?}");
    assert!(worst_m <= 1e-4 && worst_q <= 1e-4, "{worst_m} m {worst_q}");
    assert!(
        loose_frames >= 100,
        "unlabelled markers in only {loose_frames} frames"
    );
    assert!(worst_loose_m <= 1e-4, "{worst_loose_m} m");
    println!(
        "NatNet, loose LEDs as labelled markers of model 0: {labelled_loose} compared, largest difference \
         {worst_labelled_m:.2e} m"
    );
    assert!(labelled_loose >= 100, "{labelled_loose}");
    assert!(worst_labelled_m <= 1e-4, "{worst_labelled_m} m");
}

/// `irtrackd --ephemeral-ports 127.0.0.1` covers NatNet too: two processes with the same
/// config (NatNet on its default fixed ports, command 0.0.0.0:1510, multicast data port 1511)
/// start side by side; each has its command socket on 127.0.0.1 with a port of its own, and its
/// server info names a multicast data port of its own.
#[test]
fn ephemeral_ports_cover_natnet_command_and_data_ports() {
    use std::io::BufRead;
    use std::process::{Command, Stdio};
    let dir = TempDir::new("natnet-ephemeral");
    let cfg = dir.path().join("irtrackd.toml");
    std::fs::write(
        &cfg,
        "[leds]\nbackend = \"none\"\n[outputs.natnet]\nenabled = true\n",
    )
    .unwrap();
    let exe = env!("CARGO_BIN_EXE_irtrackd");
    let mut children = Vec::new();
    let mut ports = Vec::new();
    for n in 0..2 {
        let state = dir.path().join(format!("state{n}"));
        let mut cmd = match std::env::var("IRTRACK_TEST_RUNNER") {
            Ok(runner) if !runner.trim().is_empty() => {
                let mut parts = runner.split_whitespace();
                let mut c = Command::new(parts.next().unwrap());
                c.args(parts).arg(exe);
                c
            }
            _ => Command::new(exe),
        };
        cmd.arg("--config")
            .arg(&cfg)
            .args([
                "--ephemeral-ports",
                "127.0.0.1",
                "--params-from-simulator",
                "--sim-fps",
                "30",
            ])
            .arg("--state-dir")
            .arg(&state)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .stderr(Stdio::null());
        let mut child = cmd.spawn().unwrap();
        let mut line = String::new();
        std::io::BufReader::new(child.stdout.take().unwrap())
            .read_line(&mut line)
            .unwrap();
        children.push(child);
        let natnet: SocketAddr = line
            .split_whitespace()
            .find_map(|f| f.strip_prefix("natnet="))
            .unwrap_or_else(|| panic!("no natnet= in the ready line: {line}"))
            .parse()
            .unwrap();
        assert_eq!(natnet.ip().to_string(), "127.0.0.1", "{line}");
        assert_ne!(natnet.port(), 1510, "{line}");
        // NAT_CONNECT; the server info's data port follows the 256-byte name, two versions
        // and the clock frequency (payload offset 272), then the multicast flag.
        let s = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        s.send_to(&[0, 0, 0, 0], natnet).unwrap();
        let mut buf = [0u8; 1024];
        let (len, from) = s.recv_from(&mut buf).expect("server info within 5 s");
        assert_eq!((from, len, buf[0]), (natnet, 4 + 279, 1), "server info");
        let data_port = u16::from_le_bytes([buf[4 + 272], buf[4 + 273]]);
        assert_eq!(buf[4 + 274], 1, "multicast flag");
        assert!(data_port != 1511 && data_port != 0, "data port {data_port}");
        println!("instance {n}: NatNet command {natnet}, multicast data port {data_port}");
        ports.push((natnet.port(), data_port));
    }
    for mut c in children {
        c.kill().unwrap();
        c.wait().unwrap();
    }
    assert_ne!(ports[0].0, ports[1].0, "{ports:?}");
    assert_ne!(ports[0].1, ports[1].1, "{ports:?}");
}
