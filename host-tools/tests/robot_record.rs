//! `host-tools record` against a fake irtrackd position stream (NDJSON and binary): continuous
//! recording with lost records, and point-teach through the mark file.

use std::io::Write;
use std::net::TcpListener;
use std::time::Duration;

use irtrack_core::stream::{PositionRecord, TrackStatus};
use irtrack_host_tools::cmd::record::{self, Format};

fn rec(frame: u64) -> PositionRecord {
    let lost = frame % 10 == 5;
    PositionRecord {
        frame,
        capture_ts_ns: 1_000_000_000 + frame * 10_000_000,
        position_mm: (!lost).then_some([frame as f64, 2.0 * frame as f64, 300.0]),
        // The last records carry a tool orientation (6-DOF), the others are a single LED.
        orientation_wxyz: (!lost && frame > 30).then_some([0.5, 0.5, -0.5, 0.5]),
        gap_mm: if lost { f64::NAN } else { 0.3 },
        status: if lost { TrackStatus::Lost } else { TrackStatus::Ok },
        cameras_used: if lost { 1 } else { 2 },
        world_frame: true,
        latency_us: 900,
        params_crc: 7,
    }
}

/// Serves `n` records at 100 Hz, then closes; creates `mark` after record `mark_at`.
fn serve(binary: bool, n: u64, mark: Option<(std::path::PathBuf, u64)>) -> String {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap().to_string();
    std::thread::spawn(move || {
        let (mut s, _) = l.accept().unwrap();
        for f in 1..=n {
            let r = rec(f);
            // The recorder may stop early (enough waypoints): a closed socket ends the server.
            let sent = if binary {
                s.write_all(&r.to_binary())
            } else {
                let line = r.to_ndjson_line();
                // Split lines across writes: the recorder must reassemble them.
                let (a, b) = line.as_bytes().split_at(line.len() / 2);
                s.write_all(a)
                    .and_then(|()| s.flush())
                    .and_then(|()| s.write_all(b))
            };
            if sent.is_err() {
                return;
            }
            if let Some((p, at)) = &mark
                && *at == f
            {
                std::fs::write(p, b"").unwrap();
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    });
    addr
}

fn base_args(from: String, out: std::path::PathBuf, format: Format) -> record::Args {
    record::Args {
        from,
        format,
        out: Some(out),
        mcap: None,
        duration_s: Some(10.0),
        points: false,
        max_points: None,
        mark_file: None,
        no_stdin: true,
    }
}

#[test]
fn records_continuous_stream_with_gaps() {
    let dir = std::env::temp_dir().join(format!("irtrack-record-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for (binary, format) in [(false, Format::Ndjson), (true, Format::Binary)] {
        let out = dir.join(format!("rec-{binary}.csv"));
        let addr = serve(binary, 40, None);
        let s = record::record(&base_args(addr, out.clone(), format)).unwrap();
        assert_eq!((s.records, s.lost, s.written_rows), (40, 4, 40), "{format:?}");
        let csv = std::fs::read_to_string(&out).unwrap();
        let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
        assert_eq!(rows.len(), 40);
        assert_eq!(rows[0][0], "0.000000");
        assert_eq!(rows[11][0], "0.110000");
        assert_eq!(&rows[2][3..6], &["3.0000", "6.0000", "300.0000"]);
        assert_eq!(&rows[4][3..8], &["", "", "", "", "lost"]);
        // The path tool reads it back, skipping lost rows.
        let samples = irtrack_host_tools::cmd::path::read_record(&out).unwrap();
        assert_eq!(samples.len(), 36);
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn point_teach_marks_waypoints_from_the_mark_file() {
    let dir = std::env::temp_dir().join(format!("irtrack-record-pts-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mark = dir.join("mark");
    let out = dir.join("points.csv");
    let addr = serve(false, 60, Some((mark.clone(), 20)));
    let mut a = base_args(addr, out.clone(), Format::Ndjson);
    a.points = true;
    a.mark_file = Some(mark.clone());
    a.max_points = Some(1);
    let s = record::record(&a).unwrap();
    assert_eq!(s.waypoints, 1);
    assert!(!mark.exists(), "mark file consumed");
    let csv = std::fs::read_to_string(&out).unwrap();
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 1);
    assert_eq!(rows[0][8], "1");
    // The waypoint is the newest valid position when the mark appeared (frame 20 or just after).
    let frame: u64 = rows[0][1].parse().unwrap();
    assert!((20..=24).contains(&frame), "waypoint frame {frame}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn mcap_recording_decodes_with_ros2_schemas_in_python() {
    let dir = std::env::temp_dir().join(format!("irtrack-record-mcap-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("rec.mcap");
    let addr = serve(false, 40, None);
    let mut a = base_args(addr, dir.join("unused.csv"), Format::Ndjson);
    a.out = None;
    a.mcap = Some(file.clone());
    let s = record::record(&a).unwrap();
    let streamed: Vec<PositionRecord> = (1..=40).map(rec).collect();
    let tracked = streamed.iter().filter(|r| r.status == TrackStatus::Ok).count();
    let with_pose = streamed
        .iter()
        .filter(|r| r.status == TrackStatus::Ok && r.orientation_wxyz.is_some())
        .count();
    let led = tracked - with_pose;
    let c = s.mcap.unwrap();
    assert_eq!(
        (c.status, c.position, c.tf, c.pose),
        (40, led as u64, tracked as u64, with_pose as u64)
    );

    // PyPI's reader in a separate process; it checks the ros2 profile and monotonic log times.
    let got = irtrack_testkit::mcap_check::read_mcap_with_python(&file).unwrap();
    // Counts equal what was streamed, on the live ROS 2 output's topics: every record's
    // status on /diagnostics, every tracked LED position and tool pose (the stream's main
    // records do not name the tool: `tool`), a /tf per tracked record.
    let counts = &got["counts"];
    assert_eq!(counts["/diagnostics"], 40);
    assert_eq!(counts["/irtrack/led/point"], led);
    assert_eq!(counts["/tf"], tracked);
    assert_eq!(counts["/irtrack/tool/pose"], with_pose);
    assert_eq!(
        got["schemas"]["/irtrack/tool/pose"][0],
        "geometry_msgs/msg/PoseStamped"
    );
    assert_eq!(got["schemas"]["/tf"][0], "tf2_msgs/msg/TFMessage");
    assert_eq!(
        got["schemas"]["/diagnostics"],
        serde_json::json!(["diagnostic_msgs/msg/DiagnosticArray", "ros2msg", "cdr"])
    );
    // Every channel carries the QoS a live publisher offers (the ros2 profile requires it).
    for (topic, qos) in got["qos"].as_object().unwrap() {
        assert!(
            qos.as_str().is_some_and(|q| q.contains("reliability:")),
            "{topic}: {qos}"
        );
    }
    // Decoded values equal the streamed records (metres), stamps keep the board's spacing.
    let positions = got["positions"].as_array().unwrap();
    let tracked_recs: Vec<&PositionRecord> = streamed
        .iter()
        .filter(|r| r.status == TrackStatus::Ok && r.orientation_wxyz.is_none())
        .collect();
    assert_eq!(positions.len(), tracked_recs.len());
    let stamp = |p: &serde_json::Value| {
        p[1].as_i64().unwrap() as i128 * 1_000_000_000 + p[2].as_i64().unwrap() as i128
    };
    for (p, r) in positions.iter().zip(&tracked_recs) {
        assert_eq!(p[0], "irtrack_world");
        let want = r.position_mm.unwrap();
        for i in 0..3 {
            assert!((p[3 + i].as_f64().unwrap() - want[i] / 1e3).abs() < 1e-12);
        }
        let dt = stamp(p) - stamp(&positions[0]);
        assert_eq!(dt, i128::from(r.capture_ts_ns - tracked_recs[0].capture_ts_ns));
    }
    let pose = &got["poses"][0];
    assert_eq!(
        pose.as_array().unwrap()[3..7],
        [0.5, -0.5, 0.5, 0.5].map(serde_json::Value::from)
    );
    // Without a registration world-frame records hang under the world frame in /tf.
    assert_eq!(got["tf"][0][0], "irtrack_world");
    assert_eq!(got["tf"][0][1], "irtrack_led");
    assert_eq!(got["tf"][tracked - 1][1], "irtrack_tool");
    let lost = &got["status"][4];
    assert_eq!((lost[0].as_u64(), lost[1].as_str()), (Some(1), Some("lost")));
    assert_eq!(lost[2]["frame"], "5");
    let _ = std::fs::remove_dir_all(&dir);
}
