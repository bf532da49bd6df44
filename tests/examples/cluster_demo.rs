//! Two camera boards and a solver with a camera of its own, on simulated cameras, for `cargo xtask demo` (step "more
//! cameras than one board") and for trying the cluster by hand:
//!
//! ```text
//! cargo build -p irtrack-firmware -p irtrack-tests --features irtrack-tests/cluster \
//!     --bin irtrackd --example cluster_demo
//! target/debug/examples/cluster_demo OUT_DIR
//! ```
//!
//! Board b0 carries cameras 0 and 1 of a four-camera ring rig, board b1 camera 2 alone (one
//! camera per board, the usual case at 120 fps VGA; it needs no parameter set), and the solver
//! camera 3 itself; the boards publish their blobs over Zenoh (loopback, explicit endpoints) and
//! the solver pairs them with its own camera's and triangulates all four. The solver's positions
//! are printed against the simulator's truth, then b1 is stopped and the solver goes on with
//! b0's two cameras and its own. Exits non-zero when the positions are not
//! within 0.1 mm RMS of the truth. Configurations and logs stay in OUT_DIR.

#[path = "../tests/common/mod.rs"]
mod common;

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use common::cluster::{
    FPS, Node, board, board_config, errors, errs as errs_mm, latency_ms, rms, sim_cfg, solver_config_own,
    solver_params_placed, spawn, wait_for,
};
use irtrack_sim::Scenario;

/// Largest RMS error accepted against the truth (the test measures about 0.008 mm).
const MAX_RMS_MM: f64 = 0.1;

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [out] = args.as_slice() else {
        eprintln!("usage: cluster_demo OUT_DIR");
        return ExitCode::from(2);
    };
    let out = PathBuf::from(out);
    let _ = std::fs::remove_dir_all(&out);
    if let Err(e) = std::fs::create_dir_all(&out) {
        eprintln!("creating {}: {e}", out.display());
        return ExitCode::FAILURE;
    }
    match run(&out) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("cluster demo: {e} (logs in {})", out.display());
            ExitCode::FAILURE
        }
    }
}

fn run(out: &std::path::Path) -> Result<(), String> {
    let scenario = Scenario::new(sim_cfg().scenario_config()).map_err(|e| e.to_string())?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map_err(|e| e.to_string())?
        .port();
    let ep = format!("tcp/127.0.0.1:{port}");
    solver_params_placed(
        &out.join("solver-state"),
        &[("b0", 0), ("b0", 1), ("b1", 0), ("s0", 0)],
    );
    println!(
        "solver s0: listens on {ep}, owns camera 3 itself; parameter set places cameras 0, 1 on \
         b0, 2 on b1 and 3 on s0"
    );
    let solver = spawn(
        out,
        "solver",
        &solver_config_own(&ep, "s0", &[3]),
        None,
        "127.0.0.1",
    );
    println!(
        "board b0: cameras 0 and 1; board b1: camera 2 only (no parameter set of its own: it \
         detects and publishes); each connects to the solver"
    );
    let b0 = spawn(out, "b0", &board_config("b0", [0, 1], &ep, ""), None, "127.0.0.1");
    let b1 = spawn(out, "b1", &board_config("b1", [2], &ep, ""), None, "127.0.0.1");
    wait_for(
        "the solver tracking with 4 cameras",
        Duration::from_secs(30),
        || {
            solver
                .take_records()
                .iter()
                .any(|r| r["status"] == "ok" && r["cameras_used"] == 4)
        },
    );

    let four = watch(&solver, &scenario, "all four cameras", 4.0);
    let st = solver.status();
    for b in ["b0", "b1", "s0"] {
        let r = board(&st, b);
        println!(
            "board {b}: cameras {}, clock offset measured by the solver {:.3} ms, down {}",
            r["cameras"],
            r["clock_offset_ms"].as_f64().unwrap_or(f64::NAN),
            r["down"]
        );
    }

    println!("stopping board b1 ...");
    b1.kill();
    wait_for("board b1 reported down", Duration::from_secs(5), || {
        board(&solver.status(), "b1")["down"] == true
    });
    let faults: Vec<String> = solver.status()["fault_texts"]
        .as_array()
        .map(|f| {
            f.iter()
                .map(|t| t["message"].as_str().unwrap_or("").to_string())
                .collect()
        })
        .unwrap_or_default();
    println!("solver faults: {faults:?}");
    solver.take_records();
    let three = watch(&solver, &scenario, "b0's two cameras and the solver's own", 2.0);
    drop(b0);
    for (what, (n, rms_mm)) in [("4 cameras", four), ("3 cameras", three)] {
        if n < 10 || rms_mm > MAX_RMS_MM {
            return Err(format!(
                "{what}: {n} positions, RMS {rms_mm:.4} mm against the truth (limit {MAX_RMS_MM} mm)"
            ));
        }
    }
    Ok(())
}

/// Prints the solver's positions against the truth for `secs`; returns (count, RMS mm).
fn watch(solver: &Node, scenario: &Scenario, what: &str, secs: f64) -> (usize, f64) {
    solver.take_records();
    std::thread::sleep(Duration::from_secs_f64(secs));
    let records = solver.take_records();
    let errs = errors(&records, scenario);
    for r in records
        .iter()
        .filter(|r| r["status"] == "ok")
        .step_by(FPS as usize / 2)
    {
        let frame = r["frame"].as_u64().unwrap_or(0);
        let p: Vec<f64> = r["position_mm"]
            .as_array()
            .map(|a| a.iter().filter_map(|v| v.as_f64()).collect())
            .unwrap_or_default();
        let t = scenario.truth(frame).markers[0].p_cam0_mm;
        if let (Some((e, used)), [x, y, z]) = (errs.get(&frame), p.as_slice()) {
            println!(
                "frame {frame}: solver ({x:8.3}, {y:8.3}, {z:8.3}) mm  truth ({:8.3}, {:8.3}, \
                 {:8.3}) mm  error {e:.4} mm  cameras {used}",
                t.x, t.y, t.z
            );
        }
    }
    let rms_mm = rms(&errs_mm(&errs));
    let (p50, p99) = latency_ms(&records);
    println!(
        "{what}: {} positions in {secs} s ({} records), RMS error against the truth {rms_mm:.4} mm, \
         capture → published position p50 {p50:.2} ms, p99 {p99:.2} ms",
        errs.len(),
        records.len()
    );
    (errs.len(), rms_mm)
}
