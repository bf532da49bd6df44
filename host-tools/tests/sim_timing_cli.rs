//! `host-tools simulate` with per-camera timing (free-running phases, drift, jitter, rolling
//! shutter; issue 39) and `host-tools track` reading what it writes.

mod common;

use common::scratch;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_host-tools"))
}

fn run_ok(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{cmd:?} failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    stdout
}

fn simulate(dir: &Path, extra: &[&str]) {
    let mut c = bin();
    c.args(["simulate", "--quiet", "--rig", "convergent", "--out"])
        .arg(dir)
        .args(extra);
    run_ok(&mut c);
}

fn track(dir: &Path) -> (String, PathBuf) {
    let out = dir.join("positions.csv");
    let mut c = bin();
    c.args(["track", "--frames"])
        .arg(dir)
        .arg("--params")
        .arg(dir.join("rig.irp"))
        .arg("--out")
        .arg(&out);
    (run_ok(&mut c), out)
}

/// (frame, camera) → (timestamp_ns, dropped)
fn read_stamps(dir: &Path) -> BTreeMap<(u64, usize), (u64, bool)> {
    let text = std::fs::read_to_string(dir.join("timestamps.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next().unwrap(), "frame,camera,timestamp_ns,dropped");
    lines
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (
                (f[0].parse().unwrap(), f[1].parse().unwrap()),
                (f[2].parse().unwrap(), f[3] == "1"),
            )
        })
        .collect()
}

fn read_dense(dir: &Path) -> Vec<(f64, [f64; 3])> {
    let text = std::fs::read_to_string(dir.join("truth_dense.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next().unwrap(), "t_ns,x_mm,y_mm,z_mm");
    lines
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            (v[0], [v[1], v[2], v[3]])
        })
        .collect()
}

#[test]
fn timed_simulation_writes_each_cameras_timestamps_and_dense_truth_and_track_uses_them() {
    let dir = scratch("timed");
    let period_ns = 1e9 / 120.0;
    simulate(
        &dir,
        &[
            "--frames",
            "60",
            "--phase-ms",
            "0,3.1",
            "--ppm",
            "0,40",
            "--ts-jitter-us",
            "50",
            "--line-time-us",
            "15",
            "--ts-offset-us",
            "200,500",
            "--exposure-us",
            "1000",
        ],
    );
    // The constants a tracker is given: offset_ns = −ts offset, rolling shutter, exposure.
    let timing = std::fs::read_to_string(dir.join("camera_timing.csv")).unwrap();
    let rows: Vec<&str> = timing.lines().collect();
    assert_eq!(
        rows[0],
        "camera,shutter,line_time_ns,exposure_ns,offset_ns,phase_ns,rate_ppm,ts_jitter_ns"
    );
    assert!(
        rows[1].starts_with("0,rolling,15000,1000000,-200000,0.0,0.000,50000.0"),
        "{}",
        rows[1]
    );
    assert!(
        rows[2].starts_with("1,rolling,15000,1000000,-500000,3100000.0,40.000,50000.0"),
        "{}",
        rows[2]
    );

    // Each camera's own timestamps: camera 0 0.2 ms after the grid, camera 1 3.1 ms + 0.5 ms
    // after it and drifting 40 ppm, both within 3σ = 150 µs of jitter (so none before 0).
    let stamps = read_stamps(&dir);
    assert_eq!(stamps.len(), 120);
    for k in 0..60u64 {
        let (t0, d0) = stamps[&(k, 0)];
        let (t1, d1) = stamps[&(k, 1)];
        assert!(!d0 && !d1);
        let nominal = k as f64 * period_ns + 200_000.0;
        assert!((t0 as f64 - nominal).abs() <= 150_001.0, "frame {k}: {t0}");
        let expect1 = 3_100_000.0 + k as f64 * period_ns * (1.0 + 40e-6) + 500_000.0;
        assert!(
            (t1 as f64 - expect1).abs() <= 150_001.0,
            "frame {k}: {t1} vs {expect1}"
        );
    }
    // Not one timestamp per set any more: the jitter makes camera 0's deviate from the grid.
    assert!((0..60u64).any(|k| stamps[&(k, 0)].0 != (k as f64 * period_ns + 2e5).round() as u64));

    // Dense truth from a period before frame 0 to a period after the last, every 0.1 ms,
    // agreeing with truth.csv at the frame instants.
    let dense = read_dense(&dir);
    assert!(dense[0].0 <= -period_ns && dense.last().unwrap().0 >= 60.0 * period_ns);
    assert!(dense.windows(2).all(|w| w[1].0 - w[0].0 == 100_000.0));
    let truth = std::fs::read_to_string(dir.join("truth.csv")).unwrap();
    for line in truth.lines().skip(1).step_by(12) {
        let f: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        let t_ns = f[1] * 1e9;
        if let Some(d) = dense.iter().find(|(t, _)| (t - t_ns).abs() < 1.0) {
            for a in 0..3 {
                assert!((d.1[a] - f[2 + a]).abs() < 1e-5, "{line} vs {d:?}");
            }
        }
    }

    // track pairs by timestamp, writes the instant each position is compared at, and its
    // summary is the error against the dense truth at that instant.
    let (summary, out) = track(&dir);
    assert!(summary.contains("missing frames 0"), "{summary}");
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "frame,x_mm,y_mm,z_mm,gap_mm,status,cameras_used,quality,used_roi,instant_ns"
    );
    let mut sq = 0.0;
    let mut n = 0;
    for l in lines {
        let f: Vec<&str> = l.split(',').collect();
        let k: u64 = f[0].parse().unwrap();
        if f[1].is_empty() {
            // The tracker's first set has no track history yet.
            continue;
        }
        let instant: f64 = f[9].parse().unwrap();
        // No offset on camera 0: the instant is its timestamp (until the tracker states its
        // own reference instant, which must lie within a frame of it).
        assert!((instant - stamps[&(k, 0)].0 as f64).abs() < period_ns, "{l}");
        let p: Vec<f64> = (1..4).map(|i| f[i].parse().unwrap()).collect();
        let i = dense.partition_point(|(t, _)| *t <= instant);
        let ((ta, a), (tb, b)) = (dense[i - 1], dense[i]);
        let w = (instant - ta) / (tb - ta);
        let e2: f64 = (0..3).map(|j| (p[j] - (a[j] + (b[j] - a[j]) * w)).powi(2)).sum();
        sq += e2;
        n += 1;
    }
    assert!(n >= 58, "only {n} tracked");
    let rms = (sq / n as f64).sqrt();
    let reported: f64 = summary
        .split("RMS ")
        .nth(1)
        .and_then(|s| s.split(' ').next())
        .unwrap()
        .parse()
        .unwrap();
    assert!(
        (rms - reported).abs() < 1e-3,
        "recomputed RMS {rms} vs summary {reported}: {summary}"
    );
    assert!(rms < 5.0, "{summary}");
}

#[test]
fn an_exposure_before_the_start_is_dropped_and_that_set_is_missing() {
    let dir = scratch("negative_phase");
    simulate(&dir, &["--frames", "6", "--phase-ms", "0,-2.4"]);
    let stamps = read_stamps(&dir);
    assert_eq!(stamps[&(0, 1)], (0, true));
    assert!(!dir.join("cam1/000000.pgm").exists());
    let (t1, _) = stamps[&(1, 1)];
    assert_eq!(t1, (1e9 / 120.0 - 2.4e6_f64).round() as u64);
    let (summary, out) = track(&dir);
    // Set 0 lacks camera 1; set 1 starts camera 1's track (no history to retime with yet).
    assert!(
        summary.contains("missing frames 1") && !summary.contains("tracked 0,"),
        "{summary}"
    );
    let text = std::fs::read_to_string(out).unwrap();
    assert!(
        text.lines().nth(1).unwrap().starts_with("0,,,,,missing_frame"),
        "{text}"
    );
}

#[test]
fn zero_timing_options_write_todays_frames_and_no_dense_truth() {
    let plain = scratch("plain");
    let zeros = scratch("zeros");
    simulate(&plain, &["--frames", "4"]);
    simulate(
        &zeros,
        &[
            "--frames",
            "4",
            "--phase-ms",
            "0,0",
            "--ppm",
            "0",
            "--line-time-us",
            "0",
        ],
    );
    for f in [
        "cam0/000000.pgm",
        "cam1/000003.pgm",
        "timestamps.csv",
        "truth.csv",
        "scenario.txt",
    ] {
        assert_eq!(
            std::fs::read(plain.join(f)).unwrap(),
            std::fs::read(zeros.join(f)).unwrap(),
            "{f} differs"
        );
    }
    assert!(!plain.join("truth_dense.csv").exists());
    let timing = std::fs::read_to_string(plain.join("camera_timing.csv")).unwrap();
    assert!(timing.lines().nth(1).unwrap().starts_with("0,global,0,0,0,"));
}

#[test]
fn free_running_preset_and_bad_lists_are_explained() {
    let dir = scratch("free");
    simulate(&dir, &["--frames", "3", "--timing", "free-running"]);
    let timing = std::fs::read_to_string(dir.join("camera_timing.csv")).unwrap();
    // Two cameras: half a period apart, 200 µs jitter.
    assert!(timing.contains(",4166666.7,"), "{timing}");
    assert!(
        timing.lines().skip(1).all(|l| l.ends_with(",200000.0")),
        "{timing}"
    );
    let out = bin()
        .args(["simulate", "--quiet", "--frames", "1", "--out"])
        .arg(dir.join("bad"))
        .args(["--phase-ms", "0,1,2"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("phase") && err.contains("3 values for 2 cameras"),
        "{err}"
    );
}
