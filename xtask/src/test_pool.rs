//! Runs the test binaries of one `cargo test --no-run` build side by side, one per core.
//!
//! `cargo test` runs its test binaries one after another. Many of ours spend most of their time
//! waiting on wall-clock work (a simulated cell at 60 fps, a robot link's timeouts, a browser),
//! so on CI's 2-core machine one core sat idle for much of the host-tests phase. Here every
//! binary is run exactly as `cargo test` would run it (the package directory as working
//! directory, cargo's variables set), `workers` at a time, the longest known ones first.
//! Binaries that share a resource another could disturb (DDS discovery and NatNet multicast on
//! the host's interfaces, network namespaces and veth pairs) are put in a group, and no two of
//! a group run at once. Each binary's output is printed as one block when it ends.

use std::collections::VecDeque;
use std::ffi::OsString;
use std::path::PathBuf;
use std::process::Command;
use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

use crate::util::{self, RunOpts};

/// One test executable built by `cargo test --no-run`.
#[derive(Debug, Clone, PartialEq)]
pub struct TestBinary {
    pub package: String,
    /// The target's name (`cluster_e2e`, `irtrack_core`, ...).
    pub target: String,
    /// Source path relative to the package (`tests/cluster_e2e.rs`), as cargo prints it.
    pub src: String,
    pub path: PathBuf,
    pub package_dir: PathBuf,
    pub version: String,
}

/// The test binaries (harness targets) among cargo's `--message-format=json` lines.
pub fn test_binaries(json_lines: &str) -> Vec<TestBinary> {
    let mut found = Vec::new();
    for line in json_lines.lines() {
        let Ok(v) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        if v["reason"] != "compiler-artifact" || v["profile"]["test"] != true {
            continue;
        }
        let (Some(exe), Some(manifest), Some(target), Some(src)) = (
            v["executable"].as_str(),
            v["manifest_path"].as_str(),
            v["target"]["name"].as_str(),
            v["target"]["src_path"].as_str(),
        ) else {
            continue;
        };
        let package_dir = PathBuf::from(manifest)
            .parent()
            .map(PathBuf::from)
            .unwrap_or_default();
        let src = PathBuf::from(src)
            .strip_prefix(&package_dir)
            .map(|p| p.display().to_string())
            .unwrap_or_else(|_| src.to_string());
        // `package_id` is `path+file:///dir#name@version` (or `...#version` when the directory
        // is named like the package).
        let id = v["package_id"].as_str().unwrap_or("");
        let tail = id.rsplit('#').next().unwrap_or("");
        let (name, version) = match tail.split_once('@') {
            Some((n, ver)) => (n.to_string(), ver.to_string()),
            None => (
                package_dir
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                tail.to_string(),
            ),
        };
        found.push(TestBinary {
            package: name,
            target: target.to_string(),
            src,
            path: PathBuf::from(exe),
            package_dir,
            version,
        });
    }
    found
}

/// Binaries that must not run beside another of the same group.
fn group(b: &TestBinary) -> Option<&'static str> {
    let t = b.target.as_str();
    // DDS discovery (fixed multicast group, ports from the domain id) and NatNet multicast.
    if t.contains("ros2") || t.contains("dds") || t.contains("natnet") {
        return Some("multicast");
    }
    // Network namespaces, veth pairs and their addresses.
    if matches!(
        t,
        "cluster_e2e" | "cluster_checkerboard_e2e" | "ptp_status" | "ptp_sandbox"
    ) {
        return Some("netns");
    }
    None
}

/// Binaries that run with nothing beside them: their wall-clock figures are what they test.
/// `cluster_e2e`'s free-running cameras across boards (simulated boards at 60 fps in real
/// time, the solver's clock models judged to 0.5 mm) failed once beside `wand_cli`'s
/// calibrations (worst 1.27 mm, 197 of 240 positions; 2026-11-28) and passed alone.
const ALONE: &[&str] = &["cluster_e2e"];

fn alone(b: &TestBinary) -> bool {
    ALONE.contains(&b.target.as_str())
}

/// The slowest binaries of a CI run (seconds, docs/development.md), started first so the
/// workers finish together instead of one of them starting a minute-long binary last.
const KNOWN_LONG: &[&str] = &[
    "cluster_checkerboard_e2e",
    "wand_cli",
    "cluster_e2e",
    "hostile_clients",
    "survey_e2e",
    "browser_setup_view",
    "browser_update",
    "multibody_sim",
    "cluster_agreement",
    "calibrate_cli",
    "update_cli",
    "web",
    "calibrate_push_e2e",
];

/// Run order: those that run alone, then the known long ones (in [`KNOWN_LONG`]'s order), then
/// cargo's order.
pub fn schedule(mut bins: Vec<TestBinary>) -> Vec<TestBinary> {
    let rank = |b: &TestBinary| {
        let long = KNOWN_LONG
            .iter()
            .position(|k| *k == b.target)
            .unwrap_or(KNOWN_LONG.len());
        (!alone(b), long)
    };
    bins.sort_by_key(rank); // stable: cargo's order among the rest
    bins
}

/// What one binary did.
pub struct BinRun {
    pub bin: TestBinary,
    pub out: util::Output,
    pub elapsed: Duration,
}

struct Queue {
    waiting: VecDeque<TestBinary>,
    busy_groups: Vec<&'static str>,
    running: usize,
    alone_running: bool,
}

/// Runs `bins` (in order) on `workers` threads, each with `env` set and what is left of
/// `deadline` as its time limit. Returns every run, in the order they ended.
pub fn run_all(
    bins: Vec<TestBinary>,
    workers: usize,
    env: &[(OsString, OsString)],
    cargo: &OsString,
    deadline: Option<Instant>,
) -> Vec<BinRun> {
    let queue = Mutex::new(Queue {
        waiting: bins.into(),
        busy_groups: Vec::new(),
        running: 0,
        alone_running: false,
    });
    let changed = Condvar::new();
    let done = Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..workers.max(1) {
            scope.spawn(|| {
                while let Some(bin) = take_next(&queue, &changed) {
                    let run = run_one(&bin, env, cargo, deadline);
                    print_block(&run);
                    if let Ok(mut q) = queue.lock() {
                        if let Some(g) = group(&bin) {
                            q.busy_groups.retain(|b| *b != g);
                        }
                        q.running -= 1;
                        q.alone_running &= !alone(&bin);
                    }
                    changed.notify_all();
                    if let Ok(mut d) = done.lock() {
                        d.push(run);
                    }
                }
            });
        }
    });
    done.into_inner().unwrap_or_default()
}

/// The first waiting binary whose group is free (marking the group busy); waits while every
/// waiting binary's group is busy, while one that runs alone runs, and, when the first free
/// one must run alone, until nothing else runs; `None` when nothing is left.
fn take_next(queue: &Mutex<Queue>, changed: &Condvar) -> Option<TestBinary> {
    let mut q = queue.lock().ok()?;
    loop {
        if q.waiting.is_empty() {
            return None;
        }
        let free = q
            .waiting
            .iter()
            .position(|b| group(b).is_none_or(|g| !q.busy_groups.contains(&g)));
        if let Some(i) = free
            && !q.alone_running
            && (q.running == 0 || !alone(&q.waiting[i]))
        {
            let bin = q.waiting.remove(i)?;
            if let Some(g) = group(&bin) {
                q.busy_groups.push(g);
            }
            q.running += 1;
            q.alone_running = alone(&bin);
            return Some(bin);
        }
        q = changed.wait(q).ok()?;
    }
}

fn run_one(
    bin: &TestBinary,
    env: &[(OsString, OsString)],
    cargo: &OsString,
    deadline: Option<Instant>,
) -> BinRun {
    let mut cmd = Command::new(&bin.path);
    cmd.current_dir(&bin.package_dir);
    // What `cargo test` gives a test binary at run time.
    cmd.env("CARGO", cargo)
        .env("CARGO_MANIFEST_DIR", &bin.package_dir)
        .env("CARGO_PKG_NAME", &bin.package)
        .env("CARGO_PKG_VERSION", &bin.version);
    for (k, v) in env {
        cmd.env(k, v);
    }
    let t0 = Instant::now();
    let timeout = deadline.map(|d| d.saturating_duration_since(t0));
    let out = util::run(
        &mut cmd,
        RunOpts {
            capture_stdout: true,
            capture_stderr: true,
            quiet_stdout: true,
            quiet_stderr: true,
            timeout,
        },
    )
    .unwrap_or_else(|e| util::Output {
        status: None,
        timed_out: false,
        stdout: String::new(),
        stderr: format!("xtask: {e:#}\n"),
    });
    BinRun {
        bin: bin.clone(),
        out,
        elapsed: t0.elapsed(),
    }
}

/// A binary's output as one block, headed like cargo's `Running` line plus its time.
fn print_block(run: &BinRun) {
    let mut block = format!(
        "     Running {} ({}) [{}, {}]\n",
        run.bin.src,
        run.bin.path.display(),
        run.bin.package,
        util::fmt_duration(run.elapsed)
    );
    block.push_str(&run.out.stdout);
    if !run.out.stderr.is_empty() {
        block.push_str("---- stderr ----\n");
        block.push_str(&run.out.stderr);
    }
    if !run.out.success() {
        block.push_str(&format!(
            "xtask: {} {}\n",
            run.bin.path.display(),
            run.out.describe()
        ));
    }
    let mut o = std::io::stdout().lock();
    let _ = std::io::Write::write_all(&mut o, block.as_bytes());
    let _ = std::io::Write::flush(&mut o);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bin(target: &str) -> TestBinary {
        TestBinary {
            package: "p".into(),
            target: target.into(),
            src: format!("tests/{target}.rs"),
            path: PathBuf::from(format!("/t/{target}")),
            package_dir: PathBuf::from("/p"),
            version: "0.1.0".into(),
        }
    }

    #[test]
    fn harness_executables_are_read_from_cargo_json() {
        let json = r#"{"reason":"compiler-artifact","package_id":"path+file:///w/tests#irtrack-tests@0.1.0","manifest_path":"/w/tests/Cargo.toml","target":{"kind":["test"],"crate_types":["bin"],"name":"cluster_e2e","src_path":"/w/tests/tests/cluster_e2e.rs","edition":"2024","doc":false,"doctest":false,"test":true},"profile":{"opt_level":"1","debuginfo":1,"debug_assertions":true,"overflow_checks":true,"test":true},"features":[],"filenames":["/w/target/debug/deps/cluster_e2e-0123"],"executable":"/w/target/debug/deps/cluster_e2e-0123","fresh":true}
{"reason":"compiler-artifact","package_id":"registry+https://github.com/rust-lang/crates.io-index#serde@1.0.0","manifest_path":"/r/serde/Cargo.toml","target":{"kind":["lib"],"name":"serde","src_path":"/r/serde/src/lib.rs"},"profile":{"test":false},"executable":null,"fresh":true}
{"reason":"compiler-artifact","package_id":"path+file:///w/core#0.1.0","manifest_path":"/w/core/Cargo.toml","target":{"kind":["lib"],"name":"irtrack_core","src_path":"/w/core/src/lib.rs"},"profile":{"test":true},"executable":"/w/target/debug/deps/irtrack_core-9","fresh":true}
{"reason":"compiler-artifact","package_id":"path+file:///w/firmware#irtrack-firmware@0.1.0","manifest_path":"/w/firmware/Cargo.toml","target":{"kind":["bin"],"name":"irtrackd","src_path":"/w/firmware/src/main.rs"},"profile":{"test":false},"executable":"/w/target/debug/irtrackd","fresh":true}
{"reason":"build-finished","success":true}
not json at all"#;
        let bins = test_binaries(json);
        assert_eq!(bins.len(), 2, "{bins:?}");
        assert_eq!(bins[0].package, "irtrack-tests");
        assert_eq!(bins[0].version, "0.1.0");
        assert_eq!(bins[0].target, "cluster_e2e");
        assert_eq!(bins[0].src, "tests/cluster_e2e.rs");
        assert_eq!(bins[0].package_dir, PathBuf::from("/w/tests"));
        assert_eq!(
            bins[0].path,
            PathBuf::from("/w/target/debug/deps/cluster_e2e-0123")
        );
        // A directory named like its package: cargo leaves the name out of the id.
        assert_eq!(bins[1].package, "core");
        assert_eq!(bins[1].src, "src/lib.rs");
    }

    #[test]
    fn known_long_binaries_start_first_and_the_rest_keep_cargos_order() {
        let order = schedule(vec![
            bin("a"),
            bin("web"),
            bin("b"),
            bin("cluster_checkerboard_e2e"),
        ]);
        let names: Vec<&str> = order.iter().map(|b| b.target.as_str()).collect();
        assert_eq!(names, ["cluster_checkerboard_e2e", "web", "a", "b"]);
    }

    /// Two binaries of one group never overlap; others run beside them; one that runs alone
    /// has the machine to itself. Real processes
    /// (`sh` scripts standing in for test binaries) record when they start and end.
    #[test]
    fn a_group_runs_one_at_a_time_and_others_run_beside_it() {
        let dir = std::env::temp_dir().join(format!("xtask-pool-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let log = dir.join("log");
        let mk = |target: &str| {
            let path = dir.join(target);
            std::fs::write(
                &path,
                format!(
                    "#!/bin/sh\necho start {target} >> {log}\nsleep 0.3\necho end {target} >> {log}\n\
                     echo 'test result: ok. 1 passed; 0 failed; 0 ignored; 0 measured; 0 filtered out; finished in 0.30s'\n",
                    log = log.display()
                ),
            )
            .unwrap();
            std::fs::set_permissions(&path, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
            TestBinary {
                path,
                package_dir: dir.clone(),
                ..bin(target)
            }
        };
        let bins = vec![mk("natnet"), mk("ros2_dds"), mk("plain_a"), mk("plain_b")];
        let t0 = Instant::now();
        let runs = run_all(bins, 2, &[], &OsString::from("cargo"), None);
        let wall = t0.elapsed();
        assert_eq!(runs.len(), 4);
        let alone_run = run_all(
            schedule(vec![mk("plain_c"), mk("cluster_e2e"), mk("plain_d")]),
            2,
            &[],
            &OsString::from("cargo"),
            None,
        );
        assert_eq!(alone_run.len(), 3);
        assert!(
            runs.iter()
                .all(|r| r.out.success() && r.out.stdout.contains("1 passed"))
        );
        let text = std::fs::read_to_string(&log).unwrap();
        let events: Vec<&str> = text.lines().collect();
        let at = |e: &str| events.iter().position(|l| *l == e).unwrap();
        // The two multicast binaries do not overlap ...
        assert!(
            at("end natnet") < at("start ros2_dds") || at("end ros2_dds") < at("start natnet"),
            "{events:?}"
        );
        // ... and two workers still beat one after another (4 x 0.3 s).
        assert!(wall < Duration::from_millis(1100), "{wall:?} {events:?}");
        // The one that runs alone ran first, and nothing started before it ended.
        assert_eq!(events[8], "start cluster_e2e", "{events:?}");
        assert_eq!(events[9], "end cluster_e2e", "{events:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
