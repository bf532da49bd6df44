//! An aarch64 `irtrackd` built with `cluster` (Zenoh), run under QEMU user mode as a camera
//! board, feeding a host-native solver over Zenoh on 127.0.0.1 (docs/cluster.md). It shows
//! that the board's Zenoh build works on the board's architecture and speaks to an x86_64
//! solver: the solver hears the board, pairs its two cameras' observations and tracks.
//!
//! Ignored in the host test run: it needs the aarch64 build, which `cargo xtask test --only
//! cluster-qemu-user` makes (44 minutes cold on the loaded 2-core machine, so not a CI phase) and
//! passes in `IRTRACK_AARCH64_CLUSTER_IRTRACKD`. By hand:
//! `cargo xtask cross --cluster`, then `IRTRACK_AARCH64_CLUSTER_IRTRACKD=<path>
//! cargo test -p irtrack-tests --features cluster --test cluster_qemu_user -- --ignored`.
//! `IRTRACK_QEMU_USER` overrides the emulator command (default `qemu-aarch64 -L /`).

#![cfg(feature = "cluster")]

mod common;

use std::process::Command;
use std::time::{Duration, Instant};

use common::cluster::*;
use common::temp_dir;
use irtrack_sim::Scenario;

#[test]
#[ignore = "needs an aarch64 irtrackd with `cluster`: cargo xtask test --only cluster-qemu-user"]
fn aarch64_camera_board_under_qemu_feeds_host_solver() {
    let board_bin = std::env::var_os("IRTRACK_AARCH64_CLUSTER_IRTRACKD").expect(
        "IRTRACK_AARCH64_CLUSTER_IRTRACKD must name an aarch64 irtrackd built with `cluster` \
         (cargo xtask test --only cluster-qemu-user builds it)",
    );
    let qemu = std::env::var("IRTRACK_QEMU_USER").unwrap_or_else(|_| "qemu-aarch64 -L /".into());
    let mut qemu_words = qemu.split_whitespace();
    let mut board_cmd = Command::new(qemu_words.next().expect("IRTRACK_QEMU_USER is empty"));
    board_cmd.args(qemu_words).arg(&board_bin);

    let t0 = Instant::now();
    let dir = temp_dir("cluster-qemu-user");
    let scenario = Scenario::new(sim_cfg().scenario_config()).unwrap();
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let endpoint = format!("tcp/127.0.0.1:{port}");
    // The solver's parameter set places cameras 0 and 1 on b0 and 2 and 3 on b1; only b0 runs
    // (under QEMU), so every set closes with two cameras and b1 shows as never heard from.
    solver_params(&dir.join("solver-state"));
    let solver = spawn(&dir, "solver", &solver_config(&endpoint), None, "127.0.0.1");
    let b0 = spawn_with(
        &dir,
        "b0",
        &board_config("b0", [0, 1], &endpoint, ""),
        board_cmd,
        "127.0.0.1",
    );
    eprintln!(
        "solver and aarch64 board ready after {:.1} s",
        t0.elapsed().as_secs_f64()
    );

    // The board, emulated on a loaded machine, may not keep 30 fps: wait for positions, then
    // collect a few seconds of them.
    wait_for(
        "solver tracks from the aarch64 board's cameras",
        Duration::from_secs(60),
        || {
            solver
                .take_records()
                .iter()
                .any(|r| r["status"] == "ok" && r["cameras_used"] == 2)
        },
    );
    std::thread::sleep(Duration::from_secs(3));
    let records = solver.take_records();
    let tracked = errors(&records, &scenario);
    assert!(
        tracked.len() >= 10,
        "only {} tracked frames in 3 s ({} records)",
        tracked.len(),
        records.len()
    );
    assert!(
        used(&tracked).iter().all(|&n| n == 2),
        "cameras used: {:?}",
        used(&tracked)
    );
    assert_no_wrong_position("aarch64 board", &tracked);

    let st = solver.status();
    assert_eq!(st["cluster"]["role"], "solver");
    let b = board(&st, "b0");
    assert!(b["last_seen_ms"].as_f64().is_some(), "b0 never heard from: {b}");
    assert_eq!(b["down"], false, "{b}");
    assert_eq!(b["clock_fault"], false, "{b}");
    assert!(
        board(&st, "b1")["last_seen_ms"].is_null(),
        "b1 does not run: {}",
        board(&st, "b1")
    );
    let received = st["cluster"]["received"].as_u64().unwrap_or(0);
    assert!(received > 0, "solver received nothing: {}", st["cluster"]);

    let bst = b0.status();
    assert_eq!(bst["cluster"]["role"], "camera");
    let published = bst["cluster"]["published"].as_u64().unwrap_or(0);
    assert!(published > 0, "board published nothing: {}", bst["cluster"]);
    assert_eq!(bst["cluster"]["publish_errors"], 0, "{}", bst["cluster"]);

    let e = errs(&tracked);
    eprintln!(
        "aarch64 board under QEMU → host solver: {} tracked frames in 3 s, rms {:.3} mm, \
         board published {published}, solver received {received}, {:.1} s in all",
        tracked.len(),
        rms(&e),
        t0.elapsed().as_secs_f64()
    );
}
