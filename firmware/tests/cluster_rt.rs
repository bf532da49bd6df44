//! `[cluster] transport_fifo_priority` on real processes: an irtrackd camera board and an
//! irtrackd solver on loopback; each thread's scheduling policy and priority are read from
//! `/proc/<pid>/task/<tid>/stat` (fields 40 `rt_priority` and 41 `policy`, 1 = SCHED_FIFO).
//! Configured, the camera board's Zenoh transmit threads (`tx-*`) and the solver's receive
//! threads (`rx-*`) run SCHED_FIFO at the priority, and nothing else does (the HTTP/stream
//! tokio workers `irtrackd-io`, the main thread, the loop, Zenoh's other runtimes). Not configured, no thread of
//! either process is raised. Needs the permission to set SCHED_FIFO (root or CAP_SYS_NICE /
//! RLIMIT_RTPRIO); without it the test checks that `/status` names the refusal instead.
//!
//! `cargo test -p irtrack-firmware --features cluster --test cluster_rt` (a few seconds).

#![cfg(feature = "cluster")]

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Both tests start two irtrackd processes: one test at a time.
static SERIAL: Mutex<()> = Mutex::new(());

const PRIORITY: u32 = 42;

struct Proc {
    child: Child,
    status: SocketAddr,
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn spawn(dir: &std::path::Path, name: &str, config: &str) -> Proc {
    let cfg = dir.join(format!("{name}.toml"));
    std::fs::write(&cfg, config).unwrap();
    let state = dir.join(format!("{name}-state"));
    std::fs::create_dir_all(&state).unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_irtrackd"))
        .arg("-c")
        .arg(&cfg)
        .args(["--ephemeral-ports", "127.0.0.1", "--state-dir"])
        .arg(&state)
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.join(format!("{name}.log"))).unwrap())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut line = String::new();
    stdout.read_line(&mut line).unwrap();
    assert!(line.starts_with("irtrackd ready"), "{name}: {line}");
    // Keep reading so the child never blocks on a full pipe.
    std::thread::spawn(move || std::io::copy(&mut stdout, &mut std::io::sink()));
    let status = line
        .split_whitespace()
        .find_map(|f| f.strip_prefix("status="))
        .unwrap()
        .parse()
        .unwrap();
    Proc { child, status }
}

fn status(addr: SocketAddr) -> serde_json::Value {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET /status HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut body = String::new();
    s.read_to_string(&mut body).unwrap();
    let json = &body[body.find("\r\n\r\n").unwrap() + 4..];
    serde_json::from_str(json).unwrap_or_else(|e| panic!("{e}: {body}"))
}

/// One thread: its name, policy (0 = SCHED_OTHER, 1 = SCHED_FIFO) and real-time priority.
#[derive(Debug)]
struct Task {
    name: String,
    policy: u32,
    rt_priority: u32,
}

fn tasks(pid: u32) -> Vec<Task> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(format!("/proc/{pid}/task")).unwrap().flatten() {
        let Ok(stat) = std::fs::read_to_string(e.path().join("stat")) else {
            continue;
        };
        // "tid (comm) state ...": the name may hold spaces or parentheses; the fields after
        // the last ')' start at field 3.
        let open = stat.find('(').unwrap();
        let close = stat.rfind(')').unwrap();
        let name = stat[open + 1..close].to_string();
        let f: Vec<&str> = stat[close + 2..].split_whitespace().collect();
        out.push(Task {
            name,
            rt_priority: f[40 - 3].parse().unwrap(),
            policy: f[41 - 3].parse().unwrap(),
        });
    }
    out
}

/// The camera board and the solver, connected, with `extra` in both `[cluster]` sections.
fn pair(dir: &std::path::Path, extra: &str) -> (Proc, Proc) {
    let port = free_port();
    let solver = spawn(
        dir,
        "solver",
        &format!(
            "[params]\nallow_unsigned = true\n[leds]\nbackend = \"none\"\n[cluster]\nrole = \"solver\"\nrig = \"rt\"\n\
             listen = [\"tcp/127.0.0.1:{port}\"]\nfps = 30.0\nimage_sizes_px = [[640, 480], [640, 480]]\n{extra}\n"
        ),
    );
    let board = spawn(
        dir,
        "board",
        &format!(
            "[service]\nparams_from_simulator = true\n[leds]\nbackend = \"none\"\n\
             [source.sim]\nfps = 30.0\nwall_clock = true\n\
             [cluster]\nrole = \"camera\"\nrig = \"rt\"\nboard = \"b0\"\nconnect = [\"tcp/127.0.0.1:{port}\"]\nfps = 30.0\n{extra}\n"
        ),
    );
    (board, solver)
}

fn named<'a>(ts: &'a [Task], prefix: &str) -> Vec<&'a Task> {
    ts.iter().filter(|t| t.name.starts_with(prefix)).collect()
}

/// Waits until `pid` has threads named `prefix*` and every one of them is SCHED_FIFO at
/// `PRIORITY`; returns the process's threads then (or panics with them).
fn wait_raised(pid: u32, prefix: &str) -> Vec<Task> {
    let t0 = Instant::now();
    loop {
        let ts = tasks(pid);
        let n = named(&ts, prefix);
        if !n.is_empty() && n.iter().all(|t| t.policy == 1 && t.rt_priority == PRIORITY) {
            return ts;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "{prefix}* threads of {pid} not SCHED_FIFO {PRIORITY} after 10 s: {ts:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn may_set_fifo() -> bool {
    let p = libc::sched_param { sched_priority: 1 };
    // SAFETY: a throw-away thread tries SCHED_FIFO on itself and ends.
    std::thread::spawn(move || unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &p) } == 0)
        .join()
        .unwrap()
}

fn realtime_lines(st: &serde_json::Value) -> String {
    st["processing"]["realtime"].to_string()
}

#[test]
fn transport_threads_run_fifo_and_nothing_else_does() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-rt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (board, solver) = pair(&dir, &format!("transport_fifo_priority = {PRIORITY}"));
    if !may_set_fifo() {
        // No permission here: both keep running and say so.
        std::thread::sleep(Duration::from_secs(2));
        for p in [&board, &solver] {
            let lines = realtime_lines(&status(p.status));
            assert!(lines.contains("not permitted"), "{lines}");
            assert!(tasks(p.child.id()).iter().all(|t| t.policy == 0));
        }
        eprintln!("SKIPPED the raised-thread checks: SCHED_FIFO is not permitted here");
        return;
    }
    for (p, raised, other) in [(&board, "tx-", "rx-"), (&solver, "rx-", "tx-")] {
        let ts = wait_raised(p.child.id(), raised);
        let fifo: Vec<&Task> = ts.iter().filter(|t| t.policy != 0).collect();
        assert!(
            fifo.iter().all(|t| t.name.starts_with(raised)),
            "only {raised}* threads may be raised: {fifo:?}"
        );
        // The HTTP/stream services' tokio workers (`irtrackd-io`) and Zenoh's other runtimes
        // stay normal.
        let workers = named(&ts, "irtrackd-io");
        assert!(!workers.is_empty(), "no tokio worker found: {ts:?}");
        assert!(workers.iter().all(|t| t.policy == 0), "{workers:?}");
        assert!(named(&ts, other).iter().all(|t| t.policy == 0), "{ts:?}");
        assert!(named(&ts, "irtrackd").iter().all(|t| t.policy == 0), "{ts:?}");
        let lines = realtime_lines(&status(p.status));
        assert!(
            lines.contains(&format!("({raised}*) SCHED_FIFO priority {PRIORITY}: applied to")),
            "{lines}"
        );
    }
    drop((board, solver));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn without_the_setting_no_thread_is_raised() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = std::env::temp_dir().join(format!("irtrack-cluster-rt0-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (board, solver) = pair(&dir, "");
    // Wait for the link: the runtimes that carry it exist from then on.
    let t0 = Instant::now();
    while named(&tasks(solver.child.id()), "rx-").is_empty()
        || named(&tasks(board.child.id()), "tx-").is_empty()
    {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "no Zenoh link threads after 10 s"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    // Longer than the watcher's rescan interval, had one been started.
    std::thread::sleep(Duration::from_millis(1200));
    for p in [&board, &solver] {
        let ts = tasks(p.child.id());
        assert!(ts.iter().all(|t| t.policy == 0 && t.rt_priority == 0), "{ts:?}");
        let lines = realtime_lines(&status(p.status));
        assert!(!lines.contains("Zenoh"), "{lines}");
    }
    drop((board, solver));
    let _ = std::fs::remove_dir_all(&dir);
}
