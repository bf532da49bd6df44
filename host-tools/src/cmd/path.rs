//! `host-tools path`: turns a recorded path (from `host-tools record`) into a robot program.
//!
//! Pipeline: valid samples → One-Euro filter (restarted after tracking gaps) → 3-D
//! Ramer-Douglas-Peucker simplification (`--rdp-tol-mm`) → arc-length resampling
//! (`--resample-mm`) → speed per segment (constant `--speed-mm-s`, or the recorded hand speed
//! clamped to `--min-speed-mm-s`..`--max-speed-mm-s`) → export as a RAPID module, CSV or JSON.
//! With `--waypoints-only` only the samples marked in point-teach mode are used.
//!
//! Orientation: when every usable sample carries a quaternion (`qw,qx,qy,qz` columns, recorded
//! from a 6-DOF tool), each point keeps the orientation of its sample (slerp between the two
//! kept samples when resampling; signs made continuous so interpolation takes the short way)
//! and it becomes the robtarget's `orient`, and the CSV/JSON exports carry `qw,qx,qy,qz`. The
//! RAPID tooldata must then define the TCP frame as the tracked tool's frame. Otherwise every
//! robtarget gets `--orient`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use irtrack_core::filter::{OneEuro3, OneEuroConfig, dist_mm, rdp_indices, resample};
use nalgebra::{Quaternion, UnitQuaternion};

/// Export format.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq)]
pub enum Export {
    /// An ABB RAPID module with one `MoveL` per point.
    Rapid,
    /// CSV, one row per point (`index,x_mm,y_mm,z_mm,speed_mm_s,t_s`, plus `qw,qx,qy,qz` with
    /// orientation).
    Csv,
    /// JSON: the source name and the points with their speeds.
    Json,
}

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Recorded path CSV (`host-tools record` output).
    pub input: PathBuf,
    /// Apply the One-Euro filter.
    #[arg(long)]
    pub one_euro: bool,
    /// One-Euro cut-off at rest.
    #[arg(long, default_value_t = 1.0)]
    pub min_cutoff_hz: f64,
    /// One-Euro speed coefficient (per mm/s).
    #[arg(long, default_value_t = 0.01)]
    pub beta: f64,
    /// One-Euro cut-off of the speed estimate.
    #[arg(long, default_value_t = 1.0)]
    pub d_cutoff_hz: f64,
    /// RDP tolerance; 0 keeps every point.
    #[arg(long, default_value_t = 0.0)]
    pub rdp_tol_mm: f64,
    /// Resample at this spacing after simplification; 0 = no resampling.
    #[arg(long, default_value_t = 0.0)]
    pub resample_mm: f64,
    /// Constant programmed speed; without it the recorded speed is used.
    #[arg(long)]
    pub speed_mm_s: Option<f64>,
    /// Lowest programmed speed; the recorded speed is clamped to it, and it is the first point's
    /// speed.
    #[arg(long, default_value_t = 5.0)]
    pub min_speed_mm_s: f64,
    /// Highest programmed speed; the recorded speed is clamped to it.
    #[arg(long, default_value_t = 500.0)]
    pub max_speed_mm_s: f64,
    /// Use only the waypoints marked while recording.
    #[arg(long)]
    pub waypoints_only: bool,
    /// A gap longer than this between valid samples restarts the filter.
    #[arg(long, default_value_t = 0.2)]
    pub gap_s: f64,
    /// Output format.
    #[arg(long, value_enum, default_value_t = Export::Rapid)]
    pub export: Export,
    /// Output file (the RAPID module, CSV or JSON).
    #[arg(long)]
    pub out: PathBuf,
    /// RAPID module name.
    #[arg(long, default_value = "IrPath")]
    pub module: String,
    /// RAPID tool and work object (must exist on the controller).
    #[arg(long, default_value = "tool0")]
    pub tool: String,
    /// RAPID work object the robtargets are in.
    #[arg(long, default_value = "wobj0")]
    pub wobj: String,
    /// RAPID zone for intermediate points (the last point is always `fine`).
    #[arg(long, default_value = "z1")]
    pub zone: String,
    /// Tool orientation for every robtarget, `q1,q2,q3,q4` (default: tool z pointing down).
    #[arg(long, default_value = "0,0,1,0")]
    pub orient: String,
}

/// One recorded sample.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    /// Time since the recording's first record (s, from the board's capture times).
    pub t_s: f64,
    /// Position as recorded (mm; the robot's frame when the tracker applied a registration).
    pub pos_mm: [f64; 3],
    /// Marked as a waypoint while recording.
    pub waypoint: bool,
    /// Tool orientation (w, x, y, z) when recorded from a 6-DOF tool.
    pub quat_wxyz: Option<[f64; 4]>,
}

/// One output point with the speed to reach it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PathPoint {
    /// Target position (mm), in the recording's frame.
    pub pos_mm: [f64; 3],
    /// Time of the sample it came from (s; interpolated when resampled).
    pub t_s: f64,
    /// Programmed speed to reach this point (mm/s), within `--min-speed-mm-s`..`--max-speed-mm-s`.
    pub speed_mm_s: f64,
    /// Orientation (w, x, y, z, unit) when every sample of the path had one.
    pub quat_wxyz: Option<[f64; 4]>,
}

/// Reads valid samples (status ok, position present) from a record CSV.
pub fn read_record(path: &Path) -> anyhow::Result<Vec<Sample>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty() && !l.starts_with('#'));
    let Some((_, header)) = lines.next() else {
        bail!("{}: empty file", path.display())
    };
    let names: Vec<&str> = header.split(',').map(str::trim).collect();
    let col = |c: &str| {
        names
            .iter()
            .position(|n| *n == c)
            .with_context(|| format!("{}: no column {c}", path.display()))
    };
    let (it, ix, iy, iz) = (col("t_s")?, col("x_mm")?, col("y_mm")?, col("z_mm")?);
    let istatus = names.iter().position(|n| *n == "status");
    let iway = names.iter().position(|n| *n == "waypoint");
    let iquat = ["qw", "qx", "qy", "qz"].map(|c| names.iter().position(|n| *n == c));
    let mut out = Vec::new();
    for (lineno, line) in lines {
        let c: Vec<&str> = line.split(',').map(str::trim).collect();
        if istatus.is_some_and(|i| c.get(i).is_some_and(|s| *s != "ok")) {
            continue;
        }
        let num = |i: usize, what: &str| -> anyhow::Result<Option<f64>> {
            match c.get(i).copied() {
                None | Some("") => Ok(None),
                Some(s) => s.parse::<f64>().map(Some).with_context(|| {
                    format!(
                        "{}:{}: {what} = {s:?} is not a number",
                        path.display(),
                        lineno + 1
                    )
                }),
            }
        };
        let (Some(t), Some(x), Some(y), Some(z)) = (
            num(it, "t_s")?,
            num(ix, "x_mm")?,
            num(iy, "y_mm")?,
            num(iz, "z_mm")?,
        ) else {
            continue;
        };
        let waypoint = iway.is_some_and(|i| c.get(i).is_some_and(|s| *s == "1"));
        let mut q = [0.0; 4];
        let mut have_q = true;
        for (k, (i, name)) in iquat.iter().zip(["qw", "qx", "qy", "qz"]).enumerate() {
            match i.map(|i| num(i, name)).transpose()?.flatten() {
                Some(v) => q[k] = v,
                None => have_q = false,
            }
        }
        let quat_wxyz = if have_q {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            ensure!(
                (n - 1.0).abs() < 1e-3,
                "{}:{}: quaternion {q:?} is not unit (norm {n})",
                path.display(),
                lineno + 1
            );
            Some(q.map(|v| v / n))
        } else {
            None
        };
        out.push(Sample {
            t_s: t,
            pos_mm: [x, y, z],
            waypoint,
            quat_wxyz,
        });
    }
    Ok(out)
}

/// Filter, simplify, resample and assign speeds.
pub fn process(samples: &[Sample], args: &Args) -> anyhow::Result<Vec<PathPoint>> {
    let mut pts: Vec<Sample> = if args.waypoints_only {
        samples.iter().copied().filter(|s| s.waypoint).collect()
    } else {
        samples.to_vec()
    };
    ensure!(
        pts.len() >= 2,
        "need at least 2 usable samples, have {}",
        pts.len()
    );
    ensure!(
        pts.windows(2).all(|w| w[1].t_s >= w[0].t_s),
        "timestamps must not decrease"
    );
    if args.one_euro && !args.waypoints_only {
        let mut f = OneEuro3::new(OneEuroConfig {
            min_cutoff_hz: args.min_cutoff_hz,
            beta: args.beta,
            d_cutoff_hz: args.d_cutoff_hz,
        })?;
        let mut last_t = f64::NEG_INFINITY;
        for s in &mut pts {
            if s.t_s - last_t > args.gap_s {
                f.reset();
            }
            last_t = s.t_s;
            s.pos_mm = f.filter(s.t_s, s.pos_mm);
        }
    }
    // Orientation only when every sample has one: a path half with, half without is ambiguous.
    let oriented = pts.iter().all(|s| s.quat_wxyz.is_some());
    let mut quats: Vec<UnitQuaternion<f64>> = Vec::with_capacity(pts.len());
    if oriented {
        for s in &pts {
            let q = s.quat_wxyz.unwrap_or([1.0, 0.0, 0.0, 0.0]);
            let mut q = UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]));
            // q and −q are the same rotation; keep neighbours in one hemisphere.
            if let Some(prev) = quats.last()
                && prev.coords.dot(&q.coords) < 0.0
            {
                q = UnitQuaternion::new_unchecked(-q.into_inner());
            }
            quats.push(q);
        }
    }
    let quat_at = |i: usize| oriented.then(|| quats[i]);
    let positions: Vec<[f64; 3]> = pts.iter().map(|s| s.pos_mm).collect();
    let keep = rdp_indices(&positions, args.rdp_tol_mm)?;
    let mut kept: Vec<(f64, [f64; 3], Option<UnitQuaternion<f64>>)> = keep
        .iter()
        .map(|&i| (pts[i].t_s, pts[i].pos_mm, quat_at(i)))
        .collect();
    if args.resample_mm > 0.0 {
        let poly: Vec<[f64; 3]> = kept.iter().map(|k| k.1).collect();
        let res = resample(&poly, args.resample_mm)?;
        // Times by arc length along the kept polyline, so recorded speeds survive resampling.
        let mut cum = vec![0.0];
        for w in poly.windows(2) {
            cum.push(cum[cum.len() - 1] + dist_mm(w[0], w[1]));
        }
        let mut seg = 0;
        let mut s_along = 0.0;
        let mut out = Vec::with_capacity(res.len());
        for (i, p) in res.iter().enumerate() {
            if i > 0 {
                s_along += dist_mm(res[i - 1], *p);
            }
            while seg + 1 < cum.len() - 1 && cum[seg + 1] < s_along {
                seg += 1;
            }
            let len = cum[seg + 1] - cum[seg];
            let f = if len > 0.0 {
                ((s_along - cum[seg]) / len).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let q = match (kept[seg].2, kept[seg + 1].2) {
                (Some(a), Some(b)) => Some(a.slerp(&b, f)),
                _ => None,
            };
            out.push((kept[seg].0 + f * (kept[seg + 1].0 - kept[seg].0), *p, q));
        }
        kept = out;
    }
    let mut path = Vec::with_capacity(kept.len());
    for (i, &(t, p, q)) in kept.iter().enumerate() {
        let speed = match args.speed_mm_s {
            Some(v) => v,
            None if i == 0 => args.min_speed_mm_s,
            None => {
                let (t0, p0, _) = kept[i - 1];
                let dt = t - t0;
                if dt > 0.0 {
                    dist_mm(p, p0) / dt
                } else {
                    args.max_speed_mm_s
                }
            }
        };
        path.push(PathPoint {
            pos_mm: p,
            t_s: t,
            speed_mm_s: speed.clamp(args.min_speed_mm_s, args.max_speed_mm_s),
            quat_wxyz: q.map(|q| [q.w, q.i, q.j, q.k]),
        });
    }
    Ok(path)
}

fn parse_orient(s: &str) -> anyhow::Result<[f64; 4]> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .context("--orient")?;
    let q: [f64; 4] = v
        .try_into()
        .map_err(|_| anyhow::anyhow!("--orient needs 4 numbers q1,q2,q3,q4"))?;
    let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
    ensure!(n > 1e-9, "--orient must not be all zero");
    Ok(q.map(|x| x / n))
}

fn rapid_ident(s: &str, what: &str) -> anyhow::Result<()> {
    let ok = s.chars().next().is_some_and(|c| c.is_ascii_alphabetic())
        && s.len() <= 32
        && s.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    ensure!(
        ok,
        "{what} {s:?} is not a RAPID identifier (letter, then letters/digits/_, at most 32)"
    );
    Ok(())
}

/// Renders a RAPID module: one robtarget per point, speed data per distinct speed, MoveL each.
pub fn to_rapid(path: &[PathPoint], args: &Args, source: &str) -> anyhow::Result<String> {
    rapid_ident(&args.module, "--module")?;
    rapid_ident(&args.tool, "--tool")?;
    rapid_ident(&args.wobj, "--wobj")?;
    rapid_ident(&args.zone, "--zone")?;
    ensure!(
        path.len() <= 9999,
        "{} points exceed 9999 robtargets: raise --rdp-tol-mm or --resample-mm",
        path.len()
    );
    let fixed_q = parse_orient(&args.orient)?;
    let mut speeds: Vec<i64> = path
        .iter()
        .map(|p| p.speed_mm_s.round().max(1.0) as i64)
        .collect();
    speeds.sort_unstable();
    speeds.dedup();
    let mut s = String::new();
    writeln!(s, "MODULE {}", args.module)?;
    writeln!(
        s,
        "    ! Generated by irtrack host-tools path from {}",
        source.replace(['\n', '"'], " ")
    )?;
    writeln!(
        s,
        "    ! {} points, tool {}, work object {}, orientation {}",
        path.len(),
        args.tool,
        args.wobj,
        if path.iter().all(|p| p.quat_wxyz.is_some()) {
            "recorded (6-DOF tool)"
        } else {
            "fixed (--orient)"
        }
    )?;
    for v in &speeds {
        writeln!(s, "    CONST speeddata vIr{v} := [{v}, 500, 5000, 1000];")?;
    }
    for (i, p) in path.iter().enumerate() {
        let q = p.quat_wxyz.unwrap_or(fixed_q);
        writeln!(
            s,
            "    CONST robtarget pIr{:04} := [[{:.2}, {:.2}, {:.2}], [{:.6}, {:.6}, {:.6}, {:.6}], [0, 0, 0, 0], [9E9, 9E9, 9E9, 9E9, 9E9, 9E9]];",
            i + 1,
            p.pos_mm[0],
            p.pos_mm[1],
            p.pos_mm[2],
            q[0],
            q[1],
            q[2],
            q[3]
        )?;
    }
    writeln!(s)?;
    writeln!(s, "    PROC {}Run()", args.module)?;
    writeln!(s, "        ConfL\\Off;")?;
    for (i, p) in path.iter().enumerate() {
        let zone = if i + 1 == path.len() || i == 0 {
            "fine"
        } else {
            args.zone.as_str()
        };
        let v = p.speed_mm_s.round().max(1.0) as i64;
        writeln!(
            s,
            "        MoveL pIr{:04}, vIr{v}, {zone}, {} \\WObj:={};",
            i + 1,
            args.tool,
            args.wobj
        )?;
    }
    writeln!(s, "    ENDPROC")?;
    writeln!(s, "ENDMODULE")?;
    Ok(s)
}

/// CSV export.
pub fn to_csv(path: &[PathPoint]) -> String {
    // Orientation columns only for an oriented path, so every field stays a number.
    let oriented = !path.is_empty() && path.iter().all(|p| p.quat_wxyz.is_some());
    let mut s = String::from(if oriented {
        "index,x_mm,y_mm,z_mm,speed_mm_s,t_s,qw,qx,qy,qz\n"
    } else {
        "index,x_mm,y_mm,z_mm,speed_mm_s,t_s\n"
    });
    for (i, p) in path.iter().enumerate() {
        let _ = write!(
            s,
            "{i},{:.3},{:.3},{:.3},{:.2},{:.4}",
            p.pos_mm[0], p.pos_mm[1], p.pos_mm[2], p.speed_mm_s, p.t_s
        );
        if let Some(q) = p.quat_wxyz.filter(|_| oriented) {
            let _ = write!(s, ",{:.6},{:.6},{:.6},{:.6}", q[0], q[1], q[2], q[3]);
        }
        s.push('\n');
    }
    s
}

/// JSON export (numbers only, no strings needing escapes besides the source name).
pub fn to_json(path: &[PathPoint], source: &str) -> String {
    let esc: String = source
        .chars()
        .filter(|c| !c.is_control())
        .collect::<String>()
        .replace('\\', "\\\\")
        .replace('"', "\\\"");
    let mut s = format!("{{\"source\":\"{esc}\",\"points\":[");
    for (i, p) in path.iter().enumerate() {
        if i > 0 {
            s.push(',');
        }
        let _ = write!(
            s,
            "{{\"x_mm\":{:.3},\"y_mm\":{:.3},\"z_mm\":{:.3},\"speed_mm_s\":{:.2},\"t_s\":{:.4}",
            p.pos_mm[0], p.pos_mm[1], p.pos_mm[2], p.speed_mm_s, p.t_s
        );
        if let Some(q) = p.quat_wxyz {
            let _ = write!(
                s,
                ",\"qw\":{:.6},\"qx\":{:.6},\"qy\":{:.6},\"qz\":{:.6}",
                q[0], q[1], q[2], q[3]
            );
        }
        s.push('}');
    }
    s.push_str("]}\n");
    s
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if let Some(v) = args.speed_mm_s {
        ensure!(v.is_finite() && v > 0.0, "--speed-mm-s must be > 0");
    }
    ensure!(
        args.min_speed_mm_s > 0.0 && args.max_speed_mm_s >= args.min_speed_mm_s,
        "--min-speed-mm-s must be > 0 and <= --max-speed-mm-s"
    );
    let samples = read_record(&args.input)?;
    let path = process(&samples, &args)?;
    let source = args.input.display().to_string();
    let text = match args.export {
        Export::Rapid => to_rapid(&path, &args, &source)?,
        Export::Csv => to_csv(&path),
        Export::Json => to_json(&path, &source),
    };
    std::fs::write(&args.out, text).with_context(|| format!("{}: cannot write", args.out.display()))?;
    let len: f64 = path.windows(2).map(|w| dist_mm(w[0].pos_mm, w[1].pos_mm)).sum();
    println!(
        "{} samples -> {} points, {:.1} mm of path, written to {}",
        samples.len(),
        path.len(),
        len,
        args.out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        path: Args,
    }

    #[test]
    fn recorded_orientation_reaches_robtargets_csv_and_json() {
        let dir = std::env::temp_dir().join(format!("irtrack-path-orient-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let rec = dir.join("rec.csv");
        // 0..90° about z along a 100 mm line, stored with alternating quaternion signs.
        let mut text =
            String::from("t_s,frame,capture_ts_ns,x_mm,y_mm,z_mm,gap_mm,status,waypoint,qw,qx,qy,qz\n");
        for i in 0..=10 {
            let a = (9.0 * i as f64).to_radians() / 2.0;
            let s = if i % 2 == 0 { 1.0 } else { -1.0 };
            text += &format!(
                "{},{i},0,{},0,500,0.05,ok,0,{},0,0,{}\n",
                0.1 * i as f64,
                10.0 * i as f64,
                s * a.cos(),
                s * a.sin()
            );
        }
        std::fs::write(&rec, text).unwrap();
        let samples = read_record(&rec).unwrap();
        assert!(samples.iter().all(|s| s.quat_wxyz.is_some()));
        let out = dir.join("p.mod");
        let mut args = Cli::parse_from(["x", rec.to_str().unwrap(), "--out", out.to_str().unwrap()]).path;
        args.resample_mm = 25.0;
        let path = process(&samples, &args).unwrap();
        // Resampled at 25 mm: the point at 25 mm is a quarter of the way through 90°.
        let q = path[1].quat_wxyz.unwrap();
        let deg = 2.0 * q[3].atan2(q[0]).to_degrees();
        assert!((deg - 22.5).abs() < 1e-6, "{q:?} is {deg}°");
        let rapid = to_rapid(&path, &args, "rec.csv").unwrap();
        assert!(rapid.contains("orientation recorded"), "{rapid}");
        let last = path.last().unwrap().quat_wxyz.unwrap();
        assert!(rapid.contains(&format!(
            "[{:.6}, {:.6}, {:.6}, {:.6}]",
            last[0], last[1], last[2], last[3]
        )));
        let csv = to_csv(&path);
        assert!(csv.starts_with("index,x_mm,y_mm,z_mm,speed_mm_s,t_s,qw,qx,qy,qz\n"));
        assert!(csv.lines().skip(1).all(|l| l.split(',').count() == 10));
        assert_eq!(to_json(&path, "r").matches("\"qw\"").count(), path.len());
        // A non-unit quaternion is an error naming the line.
        std::fs::write(
            &rec,
            "t_s,x_mm,y_mm,z_mm,status,qw,qx,qy,qz\n0,1,2,3,ok,0.5,0,0,0\n",
        )
        .unwrap();
        let e = read_record(&rec).unwrap_err().to_string();
        assert!(e.contains(":2:") && e.contains("not unit"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
