//! Camera boards and a solver as separate irtrackd processes on simulated cameras (docs/
//! cluster.md): their configurations, the solver's parameter set with the placement, the
//! processes with their position streams, and the errors against the simulator's truth.
//! Shared by `tests/cluster_e2e.rs` and the `cluster_demo` example (`cargo xtask demo`).

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use irtrack_core::params::{CameraPlace, RigParams};
use irtrack_firmware::source::sim::{SimRig, SimSourceConfig, ring_rig};
use irtrack_sim::Scenario;

use super::{Proc, addr_field, bin, http};

pub const FPS: f64 = 30.0;
pub const DISTANCE_MM: f64 = 600.0;
pub const RIG: &str = "cell1";

pub fn sim_cfg() -> SimSourceConfig {
    SimSourceConfig {
        rig: SimRig::Ring,
        ring_cameras: 4,
        distance_mm: DISTANCE_MM,
        fps: FPS,
        wall_clock: true,
        ..Default::default()
    }
}

/// `[source.sim]` of the four-camera ring rig; `cameras`: the share this process renders.
pub fn sim_section(cameras: Option<&[usize]>) -> String {
    format!(
        "[source.sim]\nrig = \"ring\"\nring_cameras = 4\ndistance_mm = {DISTANCE_MM}\nfps = {FPS}\nwall_clock = true\n{}",
        cameras.map_or(String::new(), |c| format!("cameras = {c:?}\n"))
    )
}

/// A camera board rendering `cameras` of the ring rig (one or two).
pub fn board_config(board: &str, cameras: impl AsRef<[usize]>, solver: &str, extra: &str) -> String {
    format!(
        "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n{}\n[cluster]\nrole = \"camera\"\nrig = \"{RIG}\"\nboard = \"{board}\"\nconnect = [\"{solver}\"]\nfps = {FPS}\n{extra}\n",
        sim_section(Some(cameras.as_ref()))
    )
}

pub fn solver_config(listen: &str) -> String {
    format!(
        "[params]\nallow_unsigned = true\n[leds]\nbackend = \"none\"\n[cluster]\nrole = \"solver\"\nrig = \"{RIG}\"\nlisten = [\"{listen}\"]\nfps = {FPS}\nboard_timeout_ms = 300\nimage_sizes_px = [[640, 480], [640, 480], [640, 480], [640, 480]]\n"
    )
}

/// A solver that also renders `own` cameras of the ring rig itself, as board `board`.
pub fn solver_config_own(listen: &str, board: &str, own: &[usize]) -> String {
    format!(
        "{}\n{}board = \"{board}\"\nown_cameras = true\n",
        sim_section(Some(own)),
        solver_config(listen)
    )
}

/// The solver's parameter set: the ring rig, cameras 0 and 1 on board b0, 2 and 3 on b1.
pub fn solver_params(state: &Path) {
    solver_params_placed(state, &[("b0", 0), ("b0", 1), ("b1", 0), ("b1", 1)]);
}

/// The solver's parameter set with the ring rig's cameras placed on (board, local index).
pub fn solver_params_placed(state: &Path, placement: &[(&str, u8)]) {
    let mut rig: RigParams = ring_rig(4, DISTANCE_MM);
    rig.rig_id = RIG.into();
    rig.placement = placement
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
pub struct Node {
    _proc: Proc,
    pub status: SocketAddr,
    records: Arc<Mutex<Vec<serde_json::Value>>>,
}

pub fn spawn(dir: &Path, name: &str, config: &str, netns: Option<&str>, host_ip: &str) -> Node {
    let cmd = match netns {
        Some(ns) => {
            // `ip netns exec` execs irtrackd: the child's pid is irtrackd's (killed on drop).
            let mut c = Command::new("ip");
            c.args(["netns", "exec", ns]).arg(bin("irtrackd"));
            c
        }
        None => Command::new(bin("irtrackd")),
    };
    spawn_with(dir, name, config, cmd, host_ip)
}

/// Like [`spawn`], with the command that starts irtrackd given (e.g. an aarch64 irtrackd
/// under `qemu-aarch64`); its config, state and endpoint arguments are appended.
pub fn spawn_with(dir: &Path, name: &str, config: &str, mut cmd: Command, host_ip: &str) -> Node {
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, config).unwrap();
    let state = dir.join(format!("{name}-state"));
    std::fs::create_dir_all(&state).unwrap();
    cmd.arg("-c")
        .arg(&cfg)
        .args(["--ephemeral-ports", host_ip, "--state-dir"])
        .arg(&state)
        .stderr(std::fs::File::create(dir.join(format!("{name}.log"))).unwrap());
    let mut child = super::spawn(&mut cmd, name);
    let line = child
        .wait_line("irtrackd ready", Duration::from_secs(30))
        .unwrap_or_else(|e| panic!("{name}: {e}"));
    let status = addr_field(&line, "status=");
    let stream = addr_field(&line, "stream=");
    let records = Arc::new(Mutex::new(Vec::new()));
    let r2 = records.clone();
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
    });
    Node {
        _proc: child,
        status,
        records,
    }
}

impl Node {
    pub fn take_records(&self) -> Vec<serde_json::Value> {
        std::mem::take(&mut *self.records.lock().unwrap())
    }

    pub fn status(&self) -> serde_json::Value {
        let (code, body) = http(self.status, "GET", "/status");
        assert_eq!(code, 200, "{body}");
        serde_json::from_str(&body).unwrap()
    }

    pub fn kill(self) {
        drop(self);
    }
}

/// Error (mm) against the simulator's truth and cameras used, per tracked record's frame.
pub fn errors(records: &[serde_json::Value], scenario: &Scenario) -> BTreeMap<u64, (f64, u64)> {
    let mut out = BTreeMap::new();
    for r in records {
        if r["status"] != "ok" {
            continue;
        }
        let p = r["position_mm"].as_array().expect("position_mm");
        let p = nalgebra::Vector3::new(
            p[0].as_f64().unwrap(),
            p[1].as_f64().unwrap(),
            p[2].as_f64().unwrap(),
        );
        let frame = r["frame"].as_u64().expect("frame");
        let truth = scenario.truth(frame).markers[0].p_cam0_mm;
        out.insert(
            frame,
            (
                (p - truth).norm(),
                r["cameras_used"].as_u64().expect("cameras_used"),
            ),
        );
    }
    out
}

pub fn errs(m: &BTreeMap<u64, (f64, u64)>) -> Vec<f64> {
    m.values().map(|v| v.0).collect()
}

pub fn used(m: &BTreeMap<u64, (f64, u64)>) -> Vec<u64> {
    m.values().map(|v| v.1).collect()
}

/// RMS errors of `a` and `b` over the frames both tracked (the same instants), and how many.
pub fn matched_rms(a: &BTreeMap<u64, (f64, u64)>, b: &BTreeMap<u64, (f64, u64)>) -> (f64, f64, usize) {
    let common: Vec<(f64, f64)> = a
        .iter()
        .filter_map(|(f, x)| b.get(f).map(|y| (x.0, y.0)))
        .collect();
    let ea: Vec<f64> = common.iter().map(|c| c.0).collect();
    let eb: Vec<f64> = common.iter().map(|c| c.1).collect();
    (rms(&ea), rms(&eb), common.len())
}

/// Three seconds of a cell at [`FPS`] gave at least 60 % of its frames as positions, and at
/// least 90 % of them came from all four cameras (`used`: cameras per position).
pub fn assert_three_seconds_from_four_cameras(positions: usize, used: &[u64]) {
    assert!(positions as f64 >= 0.6 * 3.0 * FPS, "{positions} positions");
    assert!(
        used.iter().filter(|&&c| c == 4).count() as f64 >= 0.9 * used.len() as f64,
        "cameras used: {used:?}"
    );
}

/// No tracked record anywhere near a wrong pairing or a stale position.
pub fn assert_no_wrong_position(phase: &str, m: &BTreeMap<u64, (f64, u64)>) {
    let worst = m.values().map(|v| v.0).fold(0.0, f64::max);
    assert!(worst < 1.0, "{phase}: a position {worst:.3} mm from the truth");
}

/// p50 and p99 of the records' capture → publication latency (`latency_us`), ms.
pub fn latency_ms(records: &[serde_json::Value]) -> (f64, f64) {
    let mut v: Vec<f64> = records.iter().filter_map(|r| r["latency_us"].as_f64()).collect();
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    v.sort_by(f64::total_cmp);
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize] / 1e3;
    (q(0.5), q(0.99))
}

pub fn rms(v: &[f64]) -> f64 {
    (v.iter().map(|e| e * e).sum::<f64>() / v.len().max(1) as f64).sqrt()
}

pub fn wait_for(what: &str, timeout: Duration, mut f: impl FnMut() -> bool) {
    let start = Instant::now();
    while !f() {
        assert!(start.elapsed() < timeout, "{what}: not within {timeout:?}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

pub fn has_fault(st: &serde_json::Value, code: &str) -> bool {
    st["fault_texts"]
        .as_array()
        .is_some_and(|f| f.iter().any(|t| t["code"] == code))
}

pub fn board(st: &serde_json::Value, name: &str) -> serde_json::Value {
    st["cluster"]["boards"]
        .as_array()
        .and_then(|b| b.iter().find(|b| b["name"] == name).cloned())
        .unwrap_or(serde_json::Value::Null)
}

/// Two camera boards for calibration across boards: b0 renders rig cameras 0 and 1 and listens,
/// b1 renders 2 and 3 and connects to it (no solver: a new cell's solver has no parameters
/// yet). `board_config(board, cameras, zenoh_line)` gives each board's irtrackd.toml. The port
/// is below Linux's ephemeral range (32768–60999): a port the kernel hands out for `:0` could
/// be given again to one of irtrackd's own ephemeral listeners before Zenoh binds it (seen
/// once: "Address already in use"); `salt` keeps two tests of one process apart.
pub fn two_calibration_boards(
    dir: &Path,
    salt: u16,
    board_config: impl Fn(&str, [usize; 2], &str) -> String,
) -> (Node, Node) {
    let port = (0..2000u16)
        .map(|i| 20_000 + (std::process::id() as u16 % 8000 + salt + i) % 10_000)
        .find(|p| std::net::TcpListener::bind(("127.0.0.1", *p)).is_ok())
        .expect("a free port in 20000..30000");
    let ep = format!("tcp/127.0.0.1:{port}");
    let b0 = spawn(
        dir,
        "b0",
        &board_config("b0", [0, 1], &format!("listen = [\"{ep}\"]")),
        None,
        "127.0.0.1",
    );
    let b1 = spawn(
        dir,
        "b1",
        &board_config("b1", [2, 3], &format!("connect = [\"{ep}\"]")),
        None,
        "127.0.0.1",
    );
    for (name, b) in [("b0", &b0), ("b1", &b1)] {
        let st = b.status();
        assert_eq!(st["cluster"]["role"], "camera", "{name}: {st}");
    }
    (b0, b1)
}

/// `host-tools capture --from <b0> --from <b1> <args> --out <out>`: asserts success and
/// returns (stdout, stderr, seconds taken).
pub fn capture_from(b0: &Node, b1: &Node, args: &[&str], out: &Path) -> (String, String, f64) {
    let (a, b) = (b0.status.to_string(), b1.status.to_string());
    let started = Instant::now();
    let o = Command::new(bin("host-tools"))
        .arg("capture")
        .args(["--from", &a, "--from", &b])
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .expect("host-tools runs");
    let secs = started.elapsed().as_secs_f64();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    );
    assert!(o.status.success(), "capture failed:\n{stdout}\n{stderr}");
    (stdout, stderr, secs)
}

/// The calibrated set `got` carries the placement the two calibration boards reported (b0's
/// cameras 0 and 1, then b1's), taken from `capture`'s `cameras.csv` in `captured` — the line
/// the calibration prints and the blob's placement itself.
pub fn assert_placed_by_capture(stdout: &str, captured: &Path, got: &RigParams) {
    assert!(
        stdout.contains(&format!(
            "placement from {}: cam0 = b0/0, cam1 = b0/1, cam2 = b1/0, cam3 = b1/1",
            captured.join("cameras.csv").display()
        )),
        "{stdout}"
    );
    let placed: Vec<(&str, u8)> = got
        .placement
        .iter()
        .map(|p| (p.board.as_str(), p.local_index))
        .collect();
    assert_eq!(placed, [("b0", 0), ("b0", 1), ("b1", 0), ("b1", 1)]);
}
