//! Two camera boards and a solver as separate `irtrackd` processes over Zenoh (docs/cluster.md),
//! four simulated cameras of one ring rig, compared with one board carrying the same four
//! cameras and with the simulator's truth. Then: a board killed and restarted, 5 % loss and
//! 3 ms jitter injected in a board's sender, and a board whose clock is off by more than the
//! tolerance (fault, never a wrong pairing).
//!
//! Network: explicit `tcp/` endpoints, no multicast. With root and `ip netns`, each camera
//! board runs in its own network namespace joined to the test's namespace by a veth link
//! (10.231.<k>.0/30; the solver, in the test's namespace, listens on every interface and each
//! board connects to its link's far end: no forwarding needed); otherwise everything runs on
//! 127.0.0.1 (the plain-loopback variant; `IRTRACK_CLUSTER_LOOPBACK=1` forces it). Build the
//! binaries first: `cargo build -p irtrack-firmware`.

#![cfg(feature = "cluster")]

mod common;

use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use common::*;
use irtrack_core::params::{CameraPlace, RigParams};
use irtrack_firmware::source::sim::{SimRig, SimSourceConfig, ring_rig};
use irtrack_sim::Scenario;

const FPS: f64 = 30.0;
const DISTANCE_MM: f64 = 600.0;
const RIG: &str = "cell1";

fn sim_cfg() -> SimSourceConfig {
    SimSourceConfig {
        rig: SimRig::Ring,
        ring_cameras: 4,
        distance_mm: DISTANCE_MM,
        fps: FPS,
        wall_clock: true,
        ..Default::default()
    }
}

fn sim_section(cameras: Option<[usize; 2]>) -> String {
    format!(
        "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ndistance_mm = {DISTANCE_MM}\nfps = {FPS}\nwall_clock = true\n{}",
        cameras.map_or(String::new(), |c| format!("cameras = [{}, {}]\n", c[0], c[1]))
    )
}

fn board_config(board: &str, cameras: [usize; 2], solver: &str, extra: &str) -> String {
    format!(
        "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n{}\n[cluster]\nrole = \"camera\"\nrig = \"{RIG}\"\nboard = \"{board}\"\nconnect = [\"{solver}\"]\nfps = {FPS}\n{extra}\n",
        sim_section(Some(cameras))
    )
}

fn solver_config(listen: &str) -> String {
    format!(
        "[params]\nallow_unsigned = true\n[leds]\nbackend = \"none\"\n[cluster]\nrole = \"solver\"\nrig = \"{RIG}\"\nlisten = [\"{listen}\"]\nfps = {FPS}\nboard_timeout_ms = 300\nimage_sizes_px = [[640, 480], [640, 480], [640, 480], [640, 480]]\n"
    )
}

/// The solver's parameter set: the ring rig, cameras 0 and 1 on board b0, 2 and 3 on b1.
fn solver_params(state: &Path) {
    let mut rig: RigParams = ring_rig(4, DISTANCE_MM);
    rig.rig_id = RIG.into();
    rig.placement = [("b0", 0), ("b0", 1), ("b1", 0), ("b1", 1)]
        .iter()
        .map(|(b, i)| CameraPlace {
            board: (*b).into(),
            local_index: *i,
        })
        .collect();
    rig.validate().unwrap();
    std::fs::create_dir_all(state).unwrap();
    std::fs::write(state.join("params.irp"), rig.to_blob().unwrap()).unwrap();
}

/// A running irtrackd, optionally inside a network namespace.
struct Node {
    _proc: Proc,
    status: SocketAddr,
    records: Arc<Mutex<Vec<serde_json::Value>>>,
    netns: Option<String>,
}

fn spawn(dir: &Path, name: &str, config: &str, netns: Option<&str>, host_ip: &str) -> Node {
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, config).unwrap();
    let state = dir.join(format!("{name}-state"));
    std::fs::create_dir_all(&state).unwrap();
    let mut cmd = match netns {
        Some(ns) => {
            // `ip netns exec` execs irtrackd: the child's pid is irtrackd's (killed on drop).
            let mut c = Command::new("ip");
            c.args(["netns", "exec", ns]).arg(bin("irtrackd"));
            c
        }
        None => Command::new(bin("irtrackd")),
    };
    cmd.arg("-c")
        .arg(&cfg)
        .args(["--ephemeral-ports", host_ip, "--state-dir"])
        .arg(&state)
        .stderr(std::fs::File::create(dir.join(format!("{name}.log"))).unwrap());
    let mut child = common::spawn(&mut cmd, name);
    let line = child
        .wait_line("irtrackd ready", Duration::from_secs(30))
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let status = addr_field(&line, "status=");
    let stream = addr_field(&line, "stream=");
    let records = Arc::new(Mutex::new(Vec::new()));
    let r2 = records.clone();
    let ns = netns.map(str::to_string);
    std::thread::spawn(move || {
        // The stream port is reached from the host's namespace through the node's veth
        // address, or on loopback.
        let Ok(s) = TcpStream::connect(stream) else { return };
        for line in BufReader::new(s).lines().map_while(Result::ok) {
            if let Ok(v) = serde_json::from_str::<serde_json::Value>(&line)
                && let Ok(mut g) = r2.lock()
            {
                g.push(v);
            }
        }
        let _ = ns;
    });
    Node {
        _proc: child,
        status,
        records,
        netns: netns.map(str::to_string),
    }
}

impl Node {
    fn take_records(&self) -> Vec<serde_json::Value> {
        std::mem::take(&mut *self.records.lock().unwrap())
    }

    fn status(&self) -> serde_json::Value {
        let (code, body) = http(self.status, "GET", "/status");
        assert_eq!(code, 200, "{body}");
        serde_json::from_str(&body).unwrap()
    }

    fn kill(self) {
        drop(self);
    }
}

/// Errors (mm) of the tracked records against the simulator's truth, and the cameras used.
fn errors(records: &[serde_json::Value], scenario: &Scenario) -> (Vec<f64>, Vec<u64>) {
    let mut err = Vec::new();
    let mut used = Vec::new();
    for r in records {
        if r["status"] != "ok" {
            continue;
        }
        let p = r["position_mm"].as_array().unwrap();
        let p = nalgebra::Vector3::new(
            p[0].as_f64().unwrap(),
            p[1].as_f64().unwrap(),
            p[2].as_f64().unwrap(),
        );
        let frame = r["frame"].as_u64().unwrap();
        let truth = scenario.truth(frame).markers[0].p_cam0_mm;
        err.push((p - truth).norm());
        used.push(r["cameras_used"].as_u64().unwrap());
    }
    (err, used)
}

fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|e| e * e).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(start.elapsed() < timeout, "{what}: not within {timeout:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn has_fault(st: &serde_json::Value, code: &str) -> bool {
    st["fault_texts"]
        .as_array()
        .is_some_and(|f| f.iter().any(|t| t["code"] == code))
}

fn board(st: &serde_json::Value, name: &str) -> serde_json::Value {
    st["cluster"]["boards"]
        .as_array()
        .and_then(|b| b.iter().find(|b| b["name"] == name).cloned())
        .unwrap_or(serde_json::Value::Null)
}

/// Network namespaces of this test (deleted on drop), when `ip netns` works here.
struct Netns {
    names: Vec<String>,
}

impl Netns {
    /// A namespace per node and a veth link from each to the test's namespace, on
    /// 10.231.<k>.0/30: the node is .2, the test's side .1.
    fn try_new(nodes: &[&str]) -> Option<Netns> {
        let pid = std::process::id() % 10_000;
        let mut n = Netns { names: Vec::new() };
        for (k, node) in nodes.iter().enumerate() {
            let ns = format!("irt{pid}{node}");
            let host_if = format!("irh{pid}{k}");
            let ok = [
                vec!["netns", "add", &ns],
                vec![
                    "link", "add", &host_if, "type", "veth", "peer", "name", "eth0", "netns", &ns,
                ],
            ]
            .iter()
            .all(|args| {
                Command::new("ip")
                    .args(args)
                    .stderr(Stdio::null())
                    .status()
                    .is_ok_and(|s| s.success())
            });
            n.names.push(ns.clone());
            if !ok {
                return None;
            }
            let host_ip = format!("10.231.{k}.1/30");
            let node_ip = format!("10.231.{k}.2/30");
            let cmds: Vec<Vec<&str>> = vec![
                vec!["addr", "add", &host_ip, "dev", &host_if],
                vec!["link", "set", &host_if, "up"],
                vec!["netns", "exec", &ns, "ip", "addr", "add", &node_ip, "dev", "eth0"],
                vec!["netns", "exec", &ns, "ip", "link", "set", "eth0", "up"],
                vec!["netns", "exec", &ns, "ip", "link", "set", "lo", "up"],
            ];
            for args in cmds {
                if !Command::new("ip")
                    .args(&args)
                    .stderr(Stdio::null())
                    .status()
                    .is_ok_and(|s| s.success())
                {
                    return None;
                }
            }
        }
        Some(n)
    }

    fn node_ip(k: usize) -> String {
        format!("10.231.{k}.2")
    }

    fn host_ip(k: usize) -> String {
        format!("10.231.{k}.1")
    }
}

impl Drop for Netns {
    fn drop(&mut self) {
        for ns in &self.names {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

#[test]
fn two_camera_boards_and_a_solver_track_like_one_board() {
    let t0 = Instant::now();
    let dir = temp_dir("cluster");
    let scenario = Scenario::new(sim_cfg().scenario_config()).unwrap();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    // Namespaces when available (root, iproute2, forwarding on); else loopback.
    let netns = if std::env::var_os("IRTRACK_CLUSTER_LOOPBACK").is_none() {
        Netns::try_new(&["b0", "b1"])
    } else {
        None
    };
    // Per board: its namespace, its own address, and the solver's endpoint as it sees it.
    let (ns, ips, solver_eps): ([Option<String>; 3], [String; 3], [String; 3]) = match &netns {
        Some(n) => (
            [None, Some(n.names[0].clone()), Some(n.names[1].clone())],
            ["127.0.0.1".into(), Netns::node_ip(0), Netns::node_ip(1)],
            [
                format!("tcp/0.0.0.0:{port}"),
                format!("tcp/{}:{port}", Netns::host_ip(0)),
                format!("tcp/{}:{port}", Netns::host_ip(1)),
            ],
        ),
        None => (
            [None, None, None],
            ["127.0.0.1".into(), "127.0.0.1".into(), "127.0.0.1".into()],
            [
                format!("tcp/127.0.0.1:{port}"),
                format!("tcp/127.0.0.1:{port}"),
                format!("tcp/127.0.0.1:{port}"),
            ],
        ),
    };
    eprintln!(
        "cluster test: {}",
        if netns.is_some() {
            "boards in network namespaces over veth"
        } else {
            "plain loopback"
        }
    );

    solver_params(&dir.join("solver-state"));
    let solver = spawn(&dir, "solver", &solver_config(&solver_eps[0]), None, &ips[0]);
    let b0 = spawn(
        &dir,
        "b0",
        &board_config("b0", [0, 1], &solver_eps[1], ""),
        ns[1].as_deref(),
        &ips[1],
    );
    let b1 = spawn(
        &dir,
        "b1",
        &board_config("b1", [2, 3], &solver_eps[2], ""),
        ns[2].as_deref(),
        &ips[2],
    );
    let single_cfg = format!(
        "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n{}",
        sim_section(None)
    );
    let single = spawn(&dir, "single", &single_cfg, None, "127.0.0.1");

    // 1. Accuracy: all four cameras through the solver vs one board with the same cameras.
    wait_for("solver tracks with 4 cameras", Duration::from_secs(20), || {
        solver
            .take_records()
            .iter()
            .any(|r| r["status"] == "ok" && r["cameras_used"] == 4)
    });
    single.take_records();
    std::thread::sleep(Duration::from_secs(3));
    let (e_cluster, used) = errors(&solver.take_records(), &scenario);
    let (e_single, _) = errors(&single.take_records(), &scenario);
    let (rms_c, rms_s) = (rms(&e_cluster), rms(&e_single));
    eprintln!(
        "cluster: {} positions, RMS {rms_c:.4} mm; one board: {} positions, RMS {rms_s:.4} mm",
        e_cluster.len(),
        e_single.len()
    );
    assert!(
        e_cluster.len() as f64 >= 0.6 * 3.0 * FPS,
        "only {} positions in 3 s",
        e_cluster.len()
    );
    assert!(e_single.len() as f64 >= 0.6 * 3.0 * FPS);
    assert!(used.iter().filter(|&&u| u == 4).count() as f64 >= 0.9 * used.len() as f64);
    assert!(
        rms_c <= 1.1 * rms_s + 0.01,
        "cluster RMS {rms_c} mm vs one board {rms_s} mm"
    );
    let st = solver.status();
    assert_eq!(st["cluster"]["role"], "solver");
    assert!(board(&st, "b0")["clock_offset_ms"].as_f64().unwrap().abs() < 5.0);
    drop(single);

    // 2. Board b1 stops: the solver goes on with b0's two cameras and says so.
    b1.kill();
    wait_for("board b1 reported down", Duration::from_secs(5), || {
        board(&solver.status(), "b1")["down"] == true
    });
    let st = solver.status();
    assert!(has_fault(&st, "board_down"), "{}", st["fault_texts"]);
    solver.take_records();
    std::thread::sleep(Duration::from_secs(1));
    let (e, used) = errors(&solver.take_records(), &scenario);
    assert!(
        e.len() as f64 >= 0.5 * FPS,
        "{} positions in 1 s with one board",
        e.len()
    );
    assert!(used.iter().all(|&u| u == 2), "{used:?}");
    assert!(rms(&e) < 1.0, "RMS {} mm with two cameras", rms(&e));

    // 3. Restarted, with 5 % loss and 3 ms jitter injected in its sender.
    let b1 = spawn(
        &dir,
        "b1",
        &board_config(
            "b1",
            [2, 3],
            &solver_eps[2],
            "inject_loss = 0.05\ninject_jitter_ms = 3.0",
        ),
        ns[2].as_deref(),
        &ips[2],
    );
    wait_for("board b1 back", Duration::from_secs(20), || {
        solver.take_records().iter().any(|r| r["cameras_used"] == 4)
    });
    std::thread::sleep(Duration::from_secs(3));
    let (e, used) = errors(&solver.take_records(), &scenario);
    let four = used.iter().filter(|&&u| u == 4).count();
    eprintln!(
        "loss/jitter: {} positions, {four} with 4 cameras, RMS {:.4} mm",
        e.len(),
        rms(&e)
    );
    assert!(e.len() as f64 >= 0.6 * 3.0 * FPS);
    assert!(four as f64 >= 0.7 * e.len() as f64, "{four} of {}", e.len());
    assert!(
        rms(&e) <= 1.1 * rms_s + 0.05,
        "RMS {} mm under loss and jitter",
        rms(&e)
    );
    let st = solver.status();
    assert!(
        st["cluster"]["sets_incomplete"].as_u64().unwrap() > 0,
        "loss shows as incomplete sets"
    );
    assert!(!board(&st, "b1")["clock_fault"].as_bool().unwrap());
    b1.kill();

    // 4. b1's clock 50 ms off (more than the 16.7 ms tolerance at 30 fps): fault, and no set
    //    ever mixes its observations with b0's (no wrong pairing).
    let b1 = spawn(
        &dir,
        "b1",
        &board_config("b1", [2, 3], &solver_eps[2], "clock_offset_ms = 50.0"),
        ns[2].as_deref(),
        &ips[2],
    );
    wait_for("clock fault of b1", Duration::from_secs(20), || {
        board(&solver.status(), "b1")["clock_fault"] == true
    });
    solver.take_records();
    std::thread::sleep(Duration::from_secs(2));
    let (e, used) = errors(&solver.take_records(), &scenario);
    assert!(
        used.iter().all(|&u| u == 2),
        "a set used the offset board: {used:?}"
    );
    assert!(
        e.iter().all(|&x| x < 2.0),
        "a wrong position: {:?}",
        e.iter().cloned().fold(0.0, f64::max)
    );
    let st = solver.status();
    let off = board(&st, "b1")["clock_offset_ms"].as_f64().unwrap();
    assert!((off - 50.0).abs() < 10.0, "measured offset {off} ms");
    assert!(has_fault(&st, "clock_offset"), "{}", st["fault_texts"]);
    drop(b1);
    drop(b0);
    eprintln!("cluster test took {:.1} s", t0.elapsed().as_secs_f64());
    let _ = solver.netns;
}
