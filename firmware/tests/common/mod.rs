//! Helpers shared by the firmware integration tests.
#![allow(dead_code)]

use std::future::Future;
use std::io::BufRead as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use irtrack_core::param_wire::{Verdict, encode_push};
use irtrack_core::stream::{BINARY_FRAME_LEN, PositionRecord};
use irtrack_firmware::app::{self, Overrides};
use irtrack_firmware::config::Config;
use irtrack_firmware::source::sim::SimSourceConfig;
use irtrack_sim::Scenario;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;

/// A fresh, empty directory under the system temp dir (removed on drop).
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(name: &str) -> Self {
        let p = std::env::temp_dir().join(format!("irtrackd-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Simulated source at a test-friendly rate (the convergent VGA rig of the defaults).
pub fn sim_cfg() -> SimSourceConfig {
    SimSourceConfig {
        fps: 100.0,
        ..SimSourceConfig::default()
    }
}

/// Config with every listener on 127.0.0.1:0, the given state dir and the simulated source.
pub fn test_config(state_dir: &Path) -> Config {
    let mut cfg = Config::default();
    cfg.service.state_dir = state_dir.to_path_buf();
    for a in [
        &mut cfg.listen.params,
        &mut cfg.listen.stream_ndjson,
        &mut cfg.listen.stream_binary,
        &mut cfg.listen.status,
    ] {
        *a = "127.0.0.1:0".into();
    }
    cfg.source.sim = Some(sim_cfg());
    // These tests push unsigned blobs; the signed path has its own tests (tests/signing.rs).
    cfg.params.allow_unsigned = true;
    cfg
}

/// The simulator scenario a config's sim source runs (same seed, so same truth).
pub fn scenario(cfg: &SimSourceConfig) -> Scenario {
    Scenario::new(cfg.scenario_config()).unwrap()
}

/// Pushes a blob and returns the server's verdict line.
pub async fn push(addr: SocketAddr, blob: &[u8]) -> String {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(&encode_push(blob)).await.unwrap();
    let mut line = String::new();
    s.read_to_string(&mut line).await.unwrap();
    line
}

pub async fn push_verdict(addr: SocketAddr, blob: &[u8]) -> Verdict {
    Verdict::parse_line(&push(addr, blob).await).unwrap()
}

/// An NDJSON stream client.
pub struct NdjsonClient {
    lines: tokio::io::Lines<BufReader<TcpStream>>,
}

impl NdjsonClient {
    pub async fn connect(addr: SocketAddr) -> Self {
        let s = TcpStream::connect(addr).await.unwrap();
        Self {
            lines: BufReader::new(s).lines(),
        }
    }

    /// Next record, failing the test after `timeout`.
    pub async fn next(&mut self) -> PositionRecord {
        let line = tokio::time::timeout(Duration::from_secs(10), self.lines.next_line())
            .await
            .expect("no record within 10 s")
            .unwrap()
            .expect("stream closed");
        PositionRecord::from_ndjson_line(&line).unwrap()
    }

    /// Reads until `pred` holds, at most `max` records.
    pub async fn until(&mut self, max: usize, pred: impl Fn(&PositionRecord) -> bool) -> PositionRecord {
        for _ in 0..max {
            let r = self.next().await;
            if pred(&r) {
                return r;
            }
        }
        panic!("no matching record within {max} records");
    }
}

/// Reads one binary record.
pub async fn read_binary(s: &mut TcpStream) -> PositionRecord {
    let mut buf = [0u8; BINARY_FRAME_LEN];
    tokio::time::timeout(Duration::from_secs(10), s.read_exact(&mut buf))
        .await
        .unwrap()
        .unwrap();
    PositionRecord::decode_binary(&buf).unwrap()
}

/// GET `path` from the status endpoint; returns (status code, body).
pub async fn http_get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .await
        .unwrap();
    let mut resp = String::new();
    s.read_to_string(&mut resp).await.unwrap();
    let code = resp.split_whitespace().nth(1).unwrap().parse().unwrap();
    let body = resp
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (code, body)
}

pub async fn status_json(addr: SocketAddr) -> serde_json::Value {
    let (code, body) = http_get(addr, "/status").await;
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Distance between two points, mm.
pub fn dist_mm(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Set in the re-run test inside its network namespace.
const INSIDE: &str = "IRTRACK_TEST_NETNS";

/// Outside the namespace: runs `test` of this binary again inside a fresh one and checks it
/// passed; returns false (the caller returns). Inside: sets up loopback multicast and returns
/// true (the caller runs the test body).
pub fn in_own_netns(test: &str) -> bool {
    if std::env::var_os(INSIDE).is_some() {
        for args in [
            &["link", "set", "lo", "up", "multicast", "on"][..],
            &["route", "add", "239.0.0.0/8", "dev", "lo"][..],
        ] {
            let st = std::process::Command::new("ip")
                .args(args)
                .status()
                .expect("ip runs");
            assert!(st.success(), "ip {args:?} failed in the test's network namespace");
        }
        return true;
    }
    let exe = std::env::current_exe().unwrap();
    // Cross-built runs (aarch64 under QEMU) set IRTRACK_TEST_RUNNER: a foreign binary is
    // started through it.
    let runner = std::env::var("IRTRACK_TEST_RUNNER").unwrap_or_default();
    let out = std::process::Command::new("unshare")
        .arg("-rn")
        .args(runner.split_whitespace())
        .arg(exe)
        .args([test, "--exact", "--nocapture", "--test-threads=1"])
        .env(INSIDE, "1")
        .output()
        .expect("unshare (util-linux) runs");
    print!("{}", String::from_utf8_lossy(&out.stdout));
    eprint!("{}", String::from_utf8_lossy(&out.stderr));
    assert!(
        out.status.success(),
        "{test} inside `unshare -rn` failed ({})",
        out.status
    );
    assert!(
        String::from_utf8_lossy(&out.stdout).contains("1 passed"),
        "{test} did not run inside the namespace"
    );
    false
}

/// Runs `body` on a 2-worker tokio runtime inside a network namespace of the test's own (see
/// [`in_own_netns`]; outside it, runs the test again in there and checks it passed).
pub fn run_in_own_netns<F: Future<Output = ()>>(test: &str, body: impl FnOnce() -> F) {
    if !in_own_netns(test) {
        return;
    }
    runtime().block_on(body());
}

/// The 2-worker tokio runtime the multi-threaded service tests run on.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a 2-worker tokio runtime")
}

/// irtrackd in this process on the simulated cameras (`sim_toml`: `[source.sim]` keys), its
/// parameters from the simulator, no status LEDs, every listener on 127.0.0.1:0, plus
/// `extra_toml` (the output under test, e.g. an `[outputs.natnet]` table).
pub async fn start_with(dir: &TempDir, sim_toml: &str, extra_toml: &str) -> app::Running {
    let toml = format!("[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n{extra_toml}");
    let mut cfg = Config::from_toml(&toml, "test.toml").unwrap();
    let base = test_config(dir.path());
    cfg.service.state_dir = base.service.state_dir;
    cfg.listen = base.listen;
    cfg.source.sim = Some(toml::from_str(sim_toml).unwrap());
    app::start(cfg, Overrides::default()).await.unwrap()
}

/// irtrackd's own NDJSON stream, read in the background: what an output is compared with.
pub struct NdjsonCollector {
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<Vec<PositionRecord>>,
}

impl NdjsonCollector {
    /// Connects and returns once the first record arrived (so a client started next sees
    /// nothing the collector missed).
    pub async fn start(addr: SocketAddr) -> Self {
        let mut client = NdjsonClient::connect(addr).await;
        let first = client.next().await;
        let (stop, mut stopped) = tokio::sync::oneshot::channel();
        let task = tokio::spawn(async move {
            let mut all = vec![first];
            loop {
                tokio::select! {
                    _ = &mut stopped => break,
                    r = client.lines.next_line() => match r {
                        Ok(Some(line)) => all.push(PositionRecord::from_ndjson_line(&line).unwrap()),
                        _ => break,
                    },
                }
            }
            all
        });
        Self { stop, task }
    }

    /// Every record so far; waits a moment first for records already on their way.
    pub async fn finish(self) -> Vec<PositionRecord> {
        tokio::time::sleep(Duration::from_millis(300)).await;
        let _ = self.stop.send(());
        self.task.await.unwrap()
    }
}

/// One of the Python interop clients (firmware/tests/py/), a separate process printing one
/// JSON document per line, read by a thread. Killed on drop.
pub struct JsonLinesChild {
    pub child: std::process::Child,
    lines: mpsc::Receiver<serde_json::Value>,
}

impl JsonLinesChild {
    /// `python3 firmware/tests/py/<script> <args...>`.
    pub fn spawn(script: &str, args: &[&str]) -> Self {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/py")
            .join(script);
        let mut child = Command::new("python3")
            .arg(&path)
            .args(args)
            .stdout(Stdio::piped())
            .spawn()
            .expect("python3 runs");
        let stdout = child.stdout.take().unwrap();
        let (tx, lines) = mpsc::channel();
        let script = script.to_string();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str(&line) {
                    Ok(v) => {
                        if tx.send(v).is_err() {
                            break;
                        }
                    }
                    Err(_) => eprintln!("{script}: {line}"),
                }
            }
        });
        Self { child, lines }
    }

    /// The next document, or `None` after `timeout` or at the end of the output.
    pub fn next(&self, timeout: Duration) -> Option<serde_json::Value> {
        self.lines.recv_timeout(timeout).ok()
    }

    /// Every document until one with the key `end` (returned separately; `Null` if none came
    /// within `timeout`).
    pub fn until(&self, end: &str, timeout: Duration) -> (Vec<serde_json::Value>, serde_json::Value) {
        let deadline = Instant::now() + timeout;
        let mut got = Vec::new();
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            match self.next(left) {
                Some(v) if v.get(end).is_some() => return (got, v),
                Some(v) => got.push(v),
                None => break,
            }
        }
        (got, serde_json::Value::Null)
    }
}

impl Drop for JsonLinesChild {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `/metrics` of `addr` as parsed by prometheus_client's OpenMetrics parser in a separate
/// Python process (firmware/tests/py/scrape_metrics.py). Panics if the text does not parse.
pub async fn scrape_metrics(addr: SocketAddr) -> Metrics {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/scrape_metrics.py");
    let url = format!("http://{addr}/metrics");
    let out = tokio::task::spawn_blocking(move || Command::new("python3").arg(&script).arg(&url).output())
        .await
        .expect("the scrape thread")
        .expect("python3 runs");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "scrape_metrics.py failed: {}\n{text}",
        String::from_utf8_lossy(&out.stderr)
    );
    let doc: serde_json::Value = serde_json::from_str(text.trim()).expect("one JSON document");
    assert!(
        doc["error"].is_null(),
        "/metrics does not parse as OpenMetrics: {}",
        doc["error"]
    );
    Metrics(doc)
}

/// A parsed scrape (see [`scrape_metrics`]).
pub struct Metrics(pub serde_json::Value);

impl Metrics {
    /// The value of sample `name` whose labels include every pair of `labels`.
    pub fn value(&self, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
        self.0["samples"].as_array()?.iter().find_map(|s| {
            let matches =
                s["name"] == name && labels.iter().all(|(k, v)| s["labels"][*k].as_str() == Some(*v));
            if matches { s["value"].as_f64() } else { None }
        })
    }

    /// The family's type (`counter`, `gauge`, …) as the parser read it.
    pub fn family_type(&self, family: &str) -> Option<&str> {
        self.0["types"][family].as_str()
    }
}

/// A TCP port free on 127.0.0.1 a moment ago (for listeners that cannot report theirs, like
/// Zenoh's).
pub fn free_tcp_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// `[cluster]` of a solver for `rig` listening on `tcp/127.0.0.1:<port>`, boards declared
/// down after 300 ms, image sizes from the rig.
pub fn solver_cluster(
    rig: &irtrack_core::params::RigParams,
    rig_name: &str,
    port: u16,
    fps: f64,
) -> irtrack_firmware::cluster::ClusterConfig {
    irtrack_firmware::cluster::ClusterConfig {
        role: irtrack_firmware::cluster::Role::Solver,
        rig: rig_name.into(),
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        fps,
        board_timeout_ms: 300.0,
        image_sizes_px: rig
            .cameras
            .iter()
            .map(|c| [c.model.image_size.width_px, c.model.image_size.height_px])
            .collect(),
        ..irtrack_firmware::cluster::ClusterConfig::default()
    }
}

/// The ring rig of one camera per `placement` entry (board, index on it) at 600 mm, named
/// `rig_id`; validated. The cluster tests' rig.
pub fn placed_ring(rig_id: &str, placement: &[(&str, u8)]) -> irtrack_core::params::RigParams {
    let mut r = irtrack_firmware::source::sim::ring_rig(placement.len(), 600.0);
    r.rig_id = rig_id.into();
    r.placement = placement
        .iter()
        .map(|&(b, i)| irtrack_core::params::CameraPlace {
            board: b.into(),
            local_index: i,
        })
        .collect();
    r.validate().unwrap();
    r
}

/// Camera `cam` of `r` seeing a marker at `p_cam0_mm`: the observation blob a board sends.
pub fn obs_blob(
    r: &irtrack_core::params::RigParams,
    cam: usize,
    p_cam0_mm: &nalgebra::Vector3<f64>,
) -> irtrack_core::observation::ObsBlob {
    let c = &r.cameras[cam];
    let px = c.model.project(&c.cam_from_cam0.apply(p_cam0_mm)).unwrap();
    irtrack_core::observation::ObsBlob {
        x_px: px.x as f32,
        y_px: px.y as f32,
        area_px: 9,
        peak_dn: 200,
        roundness: 1.0,
        ..irtrack_core::observation::ObsBlob::default()
    }
}

/// An observation header of `board`'s camera `camera`, frame `seq`, captured at `ts` on the
/// shared realtime clock.
pub fn obs_header<'a>(
    rig: &'a str,
    board: &'a str,
    camera: u8,
    seq: u64,
    ts: u64,
) -> irtrack_core::observation::ObsHeader<'a> {
    irtrack_core::observation::ObsHeader {
        rig,
        board,
        camera,
        sequence: seq,
        trigger_count: None,
        capture_ts_ns: ts,
        clock: irtrack_core::observation::ObsClock::Realtime,
        exposure_us: 0,
        dropped: 0,
        send_delay_us: 0,
    }
}

/// A simulated robot controller (the reference socket protocol) homed at `home_mm`: quick
/// (2 m/s), a window of 4 targets, a heartbeat every 50 ms.
pub async fn sim_robot_server(home_mm: [f64; 3]) -> irtrack_robot::sim::SimRobotServer {
    use irtrack_robot::sim::{SimRobotServer, SimServerConfig};
    use irtrack_robot::sim_robot::SimRobotConfig;
    SimRobotServer::start(SimServerConfig {
        robot: SimRobotConfig {
            speed_mm_s: 2000.0,
            window: 4,
            home_mm,
            beat_period_s: 0.05,
            ..Default::default()
        },
        ..Default::default()
    })
    .await
    .unwrap()
}

/// [`sim_robot_server`], and the
/// `[robot]` section that has irtrackd stream the tracked point to it: deadman `none`, so
/// the link moves once enabled (`RobotLink::enable` on `app::Running::robot()`).
pub async fn sim_robot(
    home_mm: [f64; 3],
) -> (irtrack_robot::sim::SimRobotServer, irtrack_robot::RobotConfig) {
    let robot = sim_robot_server(home_mm).await;
    let section = format!(
        "address = \"{}\"\n[safety]\nworkspace_min_mm = [-2000.0, -2000.0, -2000.0]\n\
         workspace_max_mm = [2000.0, 2000.0, 2000.0]\nmax_step_mm = 50.0\nmax_speed_mm_s = 2000.0\n\
         max_gap_mm = 2.0\nmax_age_ms = 200\nrequire_world_frame = false\n[deadman]\nkind = \"none\"\n",
        robot.addr
    );
    let cfg: irtrack_robot::RobotConfig = toml::from_str(&section).unwrap();
    (robot, cfg)
}

/// Enables irtrackd's robot link and waits until the simulated robot has its first targets.
pub async fn robot_following(running: &app::Running, robot: &irtrack_robot::sim::SimRobotServer) {
    use irtrack_robot::RobotLink;
    let link = running.robot().expect("the robot link runs");
    let t0 = std::time::Instant::now();
    loop {
        link.enable();
        if robot.received().len() >= 3 {
            return;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "the robot got no targets: {:?}",
            link.status()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The robot's path is unchanged by an attack: every target it was sent, and every position
/// it was at since its first target, within `tol_mm` of the still point `p_mm`; at least
/// `min_targets` targets. Returns (targets, the worst distance of a target, mm).
pub fn assert_robot_stayed_on(
    robot: &irtrack_robot::sim::SimRobotServer,
    p_mm: [f64; 3],
    tol_mm: f64,
    min_targets: usize,
) -> (usize, f64) {
    let targets = robot.received();
    assert!(
        targets.len() >= min_targets,
        "the robot got {} targets (want {min_targets})",
        targets.len()
    );
    let worst = targets
        .iter()
        .map(|t| dist_mm(t.pos_mm, p_mm))
        .fold(0.0f64, f64::max);
    assert!(
        worst <= tol_mm,
        "a target {worst:.3} mm off the real point reached the robot"
    );
    let t_first = targets[0].t_s;
    let path: Vec<[f64; 3]> = robot
        .trace()
        .into_iter()
        .filter(|(t, _)| *t >= t_first + 0.5)
        .map(|(_, p)| p)
        .collect();
    let off = path.iter().map(|q| dist_mm(*q, p_mm)).fold(0.0f64, f64::max);
    assert!(!path.is_empty(), "no robot positions recorded");
    assert!(off <= tol_mm, "the robot moved {off:.3} mm off the real point");
    (targets.len(), worst)
}
