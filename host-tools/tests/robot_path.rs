//! `host-tools path`: a noisy recorded square becomes a RAPID module with the square's corners,
//! valid structure and the requested speed; CSV and JSON exports carry the same points.

use std::collections::HashSet;
use std::path::PathBuf;

use irtrack_core::filter::{dist_mm, point_segment_dist_mm};
use irtrack_host_tools::cmd::path::{self, Export};

const CORNERS: [[f64; 3]; 5] = [
    [500.0, -100.0, 300.0],
    [700.0, -100.0, 300.0],
    [700.0, 100.0, 320.0],
    [500.0, 100.0, 320.0],
    [500.0, -100.0, 300.0],
];

struct Lcg(u64);
impl Lcg {
    fn noise(&mut self, amp: f64) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        amp * (2.0 * ((self.0 >> 11) as f64 / (1u64 << 53) as f64) - 1.0)
    }
}

/// Writes a record CSV: the square at 50 mm/s, 100 Hz, ±0.3 mm noise, with a lost stretch.
fn write_record(dir: &std::path::Path) -> PathBuf {
    let mut rng = Lcg(3);
    let mut s = String::from("t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint\n");
    let mut t = 0.0;
    let mut frame = 0;
    for w in CORNERS.windows(2) {
        let len = dist_mm(w[0], w[1]);
        let n = (len / 0.5) as usize; // 50 mm/s at 100 Hz
        for i in 0..n {
            let f = i as f64 / n as f64;
            let p: Vec<f64> = (0..3)
                .map(|k| w[0][k] + f * (w[1][k] - w[0][k]) + rng.noise(0.3))
                .collect();
            frame += 1;
            if frame % 97 < 3 && i != 0 {
                s.push_str(&format!("{t:.4},{frame},{},,,,,lost,0\n", (t * 1e9) as u64));
            } else {
                let wp = u8::from(i == 0);
                s.push_str(&format!(
                    "{t:.4},{frame},{},{},{},{},0.2,ok,{wp}\n",
                    (t * 1e9) as u64,
                    p[0],
                    p[1],
                    p[2]
                ));
            }
            t += 0.01;
        }
    }
    let e = CORNERS[4];
    s.push_str(&format!(
        "{t:.4},{},{},{},{},{},0.2,ok,1\n",
        frame + 1,
        (t * 1e9) as u64,
        e[0],
        e[1],
        e[2]
    ));
    let p = dir.join("rec.csv");
    std::fs::write(&p, s).unwrap();
    p
}

fn args(input: PathBuf, out: PathBuf, export: Export) -> path::Args {
    path::Args {
        input,
        one_euro: true,
        min_cutoff_hz: 1.0,
        beta: 0.05,
        d_cutoff_hz: 1.0,
        rdp_tol_mm: 2.0,
        resample_mm: 0.0,
        speed_mm_s: Some(120.0),
        min_speed_mm_s: 5.0,
        max_speed_mm_s: 500.0,
        waypoints_only: false,
        gap_s: 0.2,
        export,
        out,
        module: "IrPath".into(),
        tool: "tPen".into(),
        wobj: "wobj0".into(),
        zone: "z1".into(),
        orient: "0,0,1,0".into(),
    }
}

#[test]
fn recorded_square_exports_valid_rapid_with_its_corners() {
    let dir = std::env::temp_dir().join(format!("irtrack-path-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = write_record(&dir);
    let out = dir.join("IrPath.mod");
    path::run(args(rec.clone(), out.clone(), Export::Rapid)).unwrap();
    let src = std::fs::read_to_string(&out).unwrap();
    let lines: Vec<&str> = src.lines().map(str::trim).collect();
    assert_eq!(lines.first(), Some(&"MODULE IrPath"));
    assert_eq!(lines.last(), Some(&"ENDMODULE"));
    assert_eq!(lines.iter().filter(|l| l.starts_with("PROC ")).count(), 1);
    assert_eq!(lines.iter().filter(|l| **l == "ENDPROC").count(), 1);
    // Every robtarget declared once, used by exactly one MoveL, in order.
    let mut declared = Vec::new();
    let mut coords = Vec::new();
    for l in &lines {
        if let Some(rest) = l.strip_prefix("CONST robtarget ") {
            let (name, val) = rest.split_once(" := ").unwrap();
            assert!(val.starts_with("[[") && val.ends_with("]];"), "{l}");
            assert!(val.contains("[0, 0, 0, 0], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]"));
            let xyz: Vec<f64> = val[2..]
                .split(']')
                .next()
                .unwrap()
                .split(", ")
                .map(|v| v.parse().unwrap())
                .collect();
            declared.push(name.to_string());
            coords.push([xyz[0], xyz[1], xyz[2]]);
        }
    }
    let speeds: HashSet<&str> = lines
        .iter()
        .filter_map(|l| l.strip_prefix("CONST speeddata "))
        .map(|r| r.split(' ').next().unwrap())
        .collect();
    assert_eq!(speeds, HashSet::from(["vIr120"]));
    let moves: Vec<&str> = lines
        .iter()
        .filter(|l| l.starts_with("MoveL "))
        .copied()
        .collect();
    assert_eq!(moves.len(), declared.len());
    for (m, name) in moves.iter().zip(&declared) {
        assert!(m.starts_with(&format!("MoveL {name}, vIr120, ")), "{m}");
        assert!(m.ends_with(", tPen \\WObj:=wobj0;"), "{m}");
    }
    assert!(moves.last().unwrap().contains(", fine, "));
    assert!(moves[1].contains(", z1, "));
    for l in &lines {
        let block = ["MODULE", "ENDMODULE", "PROC", "ENDPROC", "!"]
            .iter()
            .any(|k| l.starts_with(k));
        assert!(l.is_empty() || block || l.ends_with(';'), "{l}");
    }
    // RDP at 2 mm reduces the noisy square to (about) its corners.
    assert!((5..=9).contains(&coords.len()), "{} points", coords.len());
    for c in &CORNERS {
        let nearest = coords.iter().map(|p| dist_mm(*p, *c)).fold(f64::MAX, f64::min);
        assert!(nearest < 3.0, "corner {c:?} missed by {nearest} mm");
    }
    // Every output point lies near the true square.
    for p in &coords {
        let d = CORNERS
            .windows(2)
            .map(|w| point_segment_dist_mm(*p, w[0], w[1]))
            .fold(f64::MAX, f64::min);
        assert!(d < 2.0, "{p:?} is {d} mm off the path");
    }

    // CSV with resampling: even spacing; JSON carries the same points.
    let mut a = args(rec.clone(), dir.join("p.csv"), Export::Csv);
    a.resample_mm = 10.0;
    a.speed_mm_s = None;
    path::run(a.clone()).unwrap();
    let csv = std::fs::read_to_string(dir.join("p.csv")).unwrap();
    let pts: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    // Arc-length spacing is 10 mm; straight-line chords are 10 mm except across a corner.
    let spacing: Vec<f64> = pts
        .windows(2)
        .map(|w| dist_mm([w[0][1], w[0][2], w[0][3]], [w[1][1], w[1][2], w[1][3]]))
        .collect();
    assert!(spacing.iter().all(|d| *d <= 10.0 + 2e-3), "{spacing:?}"); // CSV keeps 3 decimals
    let exact = spacing.iter().filter(|d| (**d - 10.0).abs() < 2e-3).count();
    assert!(
        exact + 5 >= spacing.len(),
        "{exact} of {} spacings are 10 mm",
        spacing.len()
    );
    // Recorded speed (50 mm/s) survives resampling.
    let mid: Vec<f64> = pts[5..pts.len() - 5].iter().map(|p| p[4]).collect();
    let mean = mid.iter().sum::<f64>() / mid.len() as f64;
    assert!((mean - 50.0).abs() < 5.0, "mean recorded speed {mean}");
    a.export = Export::Json;
    a.out = dir.join("p.json");
    path::run(a).unwrap();
    let json = std::fs::read_to_string(dir.join("p.json")).unwrap();
    assert!(json.starts_with("{\"source\":"));
    assert_eq!(json.matches("\"x_mm\"").count(), pts.len());

    // Point-teach waypoints only: the five marked corners.
    let mut w = args(rec, dir.join("w.mod"), Export::Rapid);
    w.waypoints_only = true;
    w.rdp_tol_mm = 0.0;
    let samples = path::read_record(&w.input).unwrap();
    let wp = path::process(&samples, &w).unwrap();
    assert_eq!(wp.len(), 5);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn path_refuses_bad_input_and_names() {
    let dir = std::env::temp_dir().join(format!("irtrack-path-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rec = write_record(&dir);
    let mut a = args(rec, dir.join("x.mod"), Export::Rapid);
    a.module = "9bad".into();
    assert!(
        path::run(a.clone())
            .unwrap_err()
            .to_string()
            .contains("RAPID identifier")
    );
    let bad = dir.join("bad.csv");
    std::fs::write(&bad, "t_s,x_mm,y_mm,z_mm,status\n0,1,2,abc,ok\n").unwrap();
    a.input = bad;
    a.module = "Ok".into();
    let e = path::run(a).unwrap_err().to_string();
    assert!(e.contains("z_mm") && e.contains("abc"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
