//! `host-tools accuracy`: simulate both rigs at Table I's distances (and some in between),
//! track with the firmware's pipeline, and report RMS / p95 3-D error next to Table I's
//! pixel-resolution figures as a markdown table and a PNG plot.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use irtrack_core::image::GrayImage;
use irtrack_core::pipeline::{Tracker, TrackerConfig};
use irtrack_sim::resolution::{TABLE_I, convergent_closed_form, parallel_closed_form};
use irtrack_sim::rig::{TABLE_I_BASELINE_MM, TABLE_I_FOCAL_PX};
use irtrack_sim::{MarkerSpec, RigPreset, Scenario, SimConfig, Trajectory};

use super::track::{ErrorStats, error_stats};

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Output directory for accuracy.md, accuracy.csv and accuracy.png.
    #[arg(long)]
    pub out: PathBuf,
    /// Distances (mm), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [659.84, 1000.0, 1500.0, 2000.0, 2309.44])]
    pub distance_mm: Vec<f64>,
    /// Frames per rig and distance (120 fps; the default covers the circle once).
    #[arg(long, default_value_t = 240)]
    pub frames: u64,
    /// Noise seed.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
}

/// Result for one rig at one distance.
#[derive(Debug, Clone, PartialEq)]
pub struct StudyRow {
    pub rig: &'static str,
    pub distance_mm: f64,
    /// Table I's figure for the rig's worst axis, or the same analytic model between its rows.
    pub reference_mm: f64,
    /// Whether `reference_mm` is printed in Table I (otherwise it is the model's value).
    pub in_table_i: bool,
    pub frames: u64,
    pub tracked: u64,
    pub stats: Option<ErrorStats>,
}

impl StudyRow {
    /// Goal: p95 3-D error at most a tenth of the reference.
    pub fn goal_met(&self) -> bool {
        self.stats.is_some_and(|s| s.p95_mm <= self.reference_mm / 10.0)
            && self.tracked * 10 >= self.frames * 9
    }
}

/// The scenario used for one rig at one distance: a circle of 8 % of the distance around the
/// working point, auto-exposed to 60 % of full scale there, 4-step motion blur over 2 ms.
pub fn study_config(convergent: bool, distance_mm: f64, seed: u64) -> SimConfig {
    let rig = if convergent {
        RigPreset::Convergent {
            distance_mm,
            angle_deg: 90.0,
        }
    } else {
        RigPreset::Parallel {
            baseline_mm: TABLE_I_BASELINE_MM,
        }
    };
    let mut cfg = SimConfig::preset(rig, distance_mm, 0.08 * distance_mm);
    if let Trajectory::Circle { period_s, .. } = &mut cfg.trajectory {
        *period_s = 2.0;
    }
    let m = MarkerSpec::default();
    let flux = m.flux_for_peak(0.6, cfg.sensor.full_well_e, distance_mm, cfg.camera.focal_px);
    cfg.markers = vec![MarkerSpec {
        flux_e_at_1m: flux,
        ..m
    }];
    cfg.motion_blur_steps = 4;
    cfg.seed = seed ^ distance_mm.to_bits() ^ (convergent as u64);
    cfg
}

/// Simulates and tracks one configuration in memory; returns (tracked, 3-D errors).
pub fn run_one(cfg: SimConfig, frames: u64) -> anyhow::Result<(u64, Vec<f64>)> {
    let mut sc = Scenario::new(cfg)?;
    let (w, h) = sc.image_size();
    let n = sc.camera_count();
    let mut bufs = vec![vec![0u8; (w * h) as usize]; n];
    let mut tracker = Tracker::new(sc.rig(), TrackerConfig::default())?;
    let mut errors = Vec::with_capacity(frames as usize);
    let mut tracked = 0;
    for index in 0..frames {
        let mut dropped = false;
        for (c, b) in bufs.iter_mut().enumerate() {
            dropped |= sc.render_u8(index, c, b)?.dropped;
        }
        if dropped {
            continue;
        }
        let imgs: Vec<GrayImage<'_, u8>> = bufs
            .iter()
            .map(|b| GrayImage::new(b, w, h, w))
            .collect::<Result<_, _>>()?;
        let m = tracker.process_u8(&imgs)?;
        if let Some(p) = m.point_cam0_mm {
            tracked += 1;
            errors.push((p - sc.truth(index).markers()[0].p_cam0_mm).norm());
        }
    }
    Ok((tracked, errors))
}

/// Runs the study.
pub fn study(args: &Args) -> anyhow::Result<Vec<StudyRow>> {
    let mut rows = Vec::new();
    for &d in &args.distance_mm {
        if !(d > 0.0 && d.is_finite()) {
            anyhow::bail!("distance {d} mm must be > 0");
        }
        let table = TABLE_I.iter().find(|t| (t.0 - d).abs() < 1e-6);
        for convergent in [true, false] {
            let (name, reference) = if convergent {
                (
                    "convergent",
                    table
                        .map(|t| t.1)
                        .unwrap_or(convergent_closed_form(TABLE_I_FOCAL_PX, d, 90.0).z_mm),
                )
            } else {
                (
                    "parallel",
                    table
                        .map(|t| t.3)
                        .unwrap_or(parallel_closed_form(TABLE_I_FOCAL_PX, TABLE_I_BASELINE_MM, d).z_mm),
                )
            };
            let (tracked, errors) = run_one(study_config(convergent, d, args.seed), args.frames)
                .with_context(|| format!("{name} rig at {d} mm"))?;
            rows.push(StudyRow {
                rig: name,
                distance_mm: d,
                reference_mm: reference,
                in_table_i: table.is_some(),
                frames: args.frames,
                tracked,
                stats: error_stats(&errors),
            });
        }
    }
    Ok(rows)
}

/// Markdown table of the study.
pub fn markdown(rows: &[StudyRow]) -> String {
    let mut s = String::from(
        "| rig | distance mm | Table I resolution mm | goal (1/10) mm | RMS 3-D error mm | p95 mm | max mm | tracked | goal met |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|:---:|\n",
    );
    for r in rows {
        let (rms, p95, max) = r
            .stats
            .map(|e| {
                (
                    format!("{:.3}", e.rms_mm),
                    format!("{:.3}", e.p95_mm),
                    format!("{:.3}", e.max_mm),
                )
            })
            .unwrap_or(("-".into(), "-".into(), "-".into()));
        let _ = writeln!(
            s,
            "| {} | {:.2} | {:.2}{} | {:.3} | {rms} | {p95} | {max} | {}/{} | {} |",
            r.rig,
            r.distance_mm,
            r.reference_mm,
            if r.in_table_i { "" } else { " (model)" },
            r.reference_mm / 10.0,
            r.tracked,
            r.frames,
            if r.goal_met() { "yes" } else { "no" }
        );
    }
    s
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let rows = study(&args)?;
    let md = markdown(&rows);
    let header = format!(
        "# Accuracy study\n\nTable I reference: convergent rig x=y=z, parallel rig z (its worst axis); \
         rows marked (model) use Table I's formulas (f = {TABLE_I_FOCAL_PX} px, b = {TABLE_I_BASELINE_MM} mm). \
         {} frames per row at 120 fps, circle of radius 8 % of the distance, 8-bit VGA, seed {}.\n\n",
        args.frames, args.seed
    );
    std::fs::write(args.out.join("accuracy.md"), format!("{header}{md}")).context("writing accuracy.md")?;
    let mut csv = String::from("rig,distance_mm,reference_mm,rms_mm,p95_mm,max_mm,tracked,frames\n");
    for r in &rows {
        let (a, b, c) =
            r.stats
                .map(|e| (e.rms_mm, e.p95_mm, e.max_mm))
                .unwrap_or((f64::NAN, f64::NAN, f64::NAN));
        let _ = writeln!(
            csv,
            "{},{},{},{a},{b},{c},{},{}",
            r.rig, r.distance_mm, r.reference_mm, r.tracked, r.frames
        );
    }
    std::fs::write(args.out.join("accuracy.csv"), csv).context("writing accuracy.csv")?;
    plot::write_plot(&args.out.join("accuracy.png"), &rows)?;
    print!("{md}");
    println!(
        "written {}/accuracy.md, accuracy.csv, accuracy.png",
        args.out.display()
    );
    Ok(())
}

/// A small hand-drawn log-scale plot (no plotting dependency).
pub mod plot {
    use super::*;

    const W: usize = 960;
    const H: usize = 600;
    const LEFT: usize = 100;
    const RIGHT: usize = 330;
    const TOP: usize = 50;
    const BOTTOM: usize = 80;

    /// 5×7 glyphs, one byte per row, low 5 bits used.
    fn glyph(c: char) -> [u8; 7] {
        match c.to_ascii_uppercase() {
            'A' => [14, 17, 17, 31, 17, 17, 17],
            'B' => [30, 17, 17, 30, 17, 17, 30],
            'C' => [14, 17, 16, 16, 16, 17, 14],
            'D' => [30, 17, 17, 17, 17, 17, 30],
            'E' => [31, 16, 16, 30, 16, 16, 31],
            'F' => [31, 16, 16, 30, 16, 16, 16],
            'G' => [14, 17, 16, 23, 17, 17, 15],
            'H' => [17, 17, 17, 31, 17, 17, 17],
            'I' => [14, 4, 4, 4, 4, 4, 14],
            'J' => [7, 2, 2, 2, 2, 18, 12],
            'K' => [17, 18, 20, 24, 20, 18, 17],
            'L' => [16, 16, 16, 16, 16, 16, 31],
            'M' => [17, 27, 21, 21, 17, 17, 17],
            'N' => [17, 17, 25, 21, 19, 17, 17],
            'O' => [14, 17, 17, 17, 17, 17, 14],
            'P' => [30, 17, 17, 30, 16, 16, 16],
            'Q' => [14, 17, 17, 17, 21, 18, 13],
            'R' => [30, 17, 17, 30, 20, 18, 17],
            'S' => [15, 16, 16, 14, 1, 1, 30],
            'T' => [31, 4, 4, 4, 4, 4, 4],
            'U' => [17, 17, 17, 17, 17, 17, 14],
            'V' => [17, 17, 17, 17, 17, 10, 4],
            'W' => [17, 17, 17, 21, 21, 21, 10],
            'X' => [17, 17, 10, 4, 10, 17, 17],
            'Y' => [17, 17, 10, 4, 4, 4, 4],
            'Z' => [31, 1, 2, 4, 8, 16, 31],
            '0' => [14, 17, 19, 21, 25, 17, 14],
            '1' => [4, 12, 4, 4, 4, 4, 14],
            '2' => [14, 17, 1, 2, 4, 8, 31],
            '3' => [31, 2, 4, 2, 1, 17, 14],
            '4' => [2, 6, 10, 18, 31, 2, 2],
            '5' => [31, 16, 30, 1, 1, 17, 14],
            '6' => [6, 8, 16, 30, 17, 17, 14],
            '7' => [31, 1, 2, 4, 8, 8, 8],
            '8' => [14, 17, 17, 14, 17, 17, 14],
            '9' => [14, 17, 17, 15, 1, 2, 12],
            '.' => [0, 0, 0, 0, 0, 12, 12],
            '-' => [0, 0, 0, 31, 0, 0, 0],
            '/' => [1, 2, 2, 4, 8, 8, 16],
            '(' => [2, 4, 8, 8, 8, 4, 2],
            ')' => [8, 4, 2, 2, 2, 4, 8],
            '=' => [0, 0, 31, 0, 31, 0, 0],
            ',' => [0, 0, 0, 0, 12, 4, 8],
            '%' => [24, 25, 2, 4, 8, 19, 3],
            _ => [0; 7],
        }
    }

    struct Canvas {
        rgb: Vec<u8>,
    }

    impl Canvas {
        fn new() -> Self {
            Canvas {
                rgb: vec![255; W * H * 3],
            }
        }
        fn px(&mut self, x: i64, y: i64, c: [u8; 3]) {
            if x >= 0 && y >= 0 && (x as usize) < W && (y as usize) < H {
                let i = (y as usize * W + x as usize) * 3;
                self.rgb[i..i + 3].copy_from_slice(&c);
            }
        }
        fn dot(&mut self, x: i64, y: i64, r: i64, c: [u8; 3]) {
            for dy in -r..=r {
                for dx in -r..=r {
                    if dx * dx + dy * dy <= r * r {
                        self.px(x + dx, y + dy, c);
                    }
                }
            }
        }
        /// Line with thickness `t`; `dash` > 0 draws dashes of that length.
        fn line(&mut self, (x0, y0): (f64, f64), (x1, y1): (f64, f64), t: i64, dash: usize, c: [u8; 3]) {
            let n = ((x1 - x0).abs().max((y1 - y0).abs()).ceil() as usize).max(1);
            for i in 0..=n {
                if dash > 0 && (i / dash) % 2 == 1 {
                    continue;
                }
                let f = i as f64 / n as f64;
                let (x, y) = (x0 + (x1 - x0) * f, y0 + (y1 - y0) * f);
                for d in 0..t {
                    self.px(x.round() as i64, y.round() as i64 + d - t / 2, c);
                    self.px(x.round() as i64 + d - t / 2, y.round() as i64, c);
                }
            }
        }
        /// Text at scale 2 (10×14 px glyphs, 12 px advance); `vertical` rotates it upwards.
        fn text(&mut self, x: i64, y: i64, s: &str, c: [u8; 3], vertical: bool) {
            for (k, ch) in s.chars().enumerate() {
                let g = glyph(ch);
                for (row, bits) in g.iter().enumerate() {
                    for col in 0..5 {
                        if bits & (1 << (4 - col)) != 0 {
                            for (sx, sy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                                let (gx, gy) = (k as i64 * 12 + col * 2 + sx, row as i64 * 2 + sy);
                                if vertical {
                                    self.px(x + gy, y - gx, c);
                                } else {
                                    self.px(x + gx, y + gy, c);
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    /// What a plotted series shows.
    #[derive(Debug, Clone, Copy)]
    enum Metric {
        Reference,
        Goal,
        Rms,
        P95,
    }

    impl Metric {
        fn value(self, r: &StudyRow) -> Option<f64> {
            match self {
                Metric::Reference => Some(r.reference_mm),
                Metric::Goal => Some(r.reference_mm / 10.0),
                Metric::Rms => r.stats.map(|s| s.rms_mm),
                Metric::P95 => r.stats.map(|s| s.p95_mm),
            }
        }
    }

    /// Draws RMS/p95 per rig against distance with Table I's figures and the goal, log y.
    pub fn write_plot(path: &Path, rows: &[StudyRow]) -> anyhow::Result<()> {
        let mut cv = Canvas::new();
        let ds: Vec<f64> = rows.iter().map(|r| r.distance_mm).collect();
        let (dmin, dmax) = ds.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), d| {
            (a.min(*d), b.max(*d))
        });
        let x_lo = ((dmin - 100.0) / 500.0).floor() * 500.0;
        let x_hi = ((dmax + 100.0) / 500.0).ceil() * 500.0;
        let mut vals: Vec<f64> = rows.iter().map(|r| r.reference_mm / 10.0).collect();
        vals.extend(rows.iter().map(|r| r.reference_mm));
        vals.extend(rows.iter().filter_map(|r| r.stats.map(|s| s.rms_mm)));
        vals.extend(rows.iter().filter_map(|r| r.stats.map(|s| s.p95_mm)));
        let vals: Vec<f64> = vals.into_iter().filter(|v| *v > 0.0 && v.is_finite()).collect();
        let lo = vals.iter().cloned().fold(f64::INFINITY, f64::min).log10().floor();
        let hi = vals
            .iter()
            .cloned()
            .fold(f64::NEG_INFINITY, f64::max)
            .log10()
            .ceil()
            .max(lo + 1.0);
        let (pw, ph) = ((W - LEFT - RIGHT) as f64, (H - TOP - BOTTOM) as f64);
        let fx = |d: f64| LEFT as f64 + (d - x_lo) / (x_hi - x_lo) * pw;
        let fy = |v: f64| TOP as f64 + (hi - v.log10()) / (hi - lo) * ph;
        let grey = [200, 200, 200];
        let black = [0, 0, 0];
        // Grid and axes.
        let mut e = lo;
        while e <= hi + 1e-9 {
            let y = fy(10f64.powf(e));
            cv.line((LEFT as f64, y), (LEFT as f64 + pw, y), 1, 0, grey);
            let label = if e >= 0.0 {
                format!("{}", 10u64.pow(e as u32))
            } else {
                format!("0.{}1", "0".repeat((-e) as usize - 1))
            };
            cv.text(
                LEFT as i64 - 12 * label.len() as i64 - 8,
                y as i64 - 7,
                &label,
                black,
                false,
            );
            e += 1.0;
        }
        let mut d = x_lo;
        while d <= x_hi + 1e-9 {
            let x = fx(d);
            cv.line((x, TOP as f64), (x, TOP as f64 + ph), 1, 0, grey);
            let label = format!("{d}");
            cv.text(
                x as i64 - 6 * label.len() as i64,
                (TOP as f64 + ph) as i64 + 10,
                &label,
                black,
                false,
            );
            d += 500.0;
        }
        cv.line(
            (LEFT as f64, TOP as f64),
            (LEFT as f64, TOP as f64 + ph),
            2,
            0,
            black,
        );
        cv.line(
            (LEFT as f64, TOP as f64 + ph),
            (LEFT as f64 + pw, TOP as f64 + ph),
            2,
            0,
            black,
        );
        cv.text(
            LEFT as i64 + pw as i64 / 2 - 72,
            H as i64 - 34,
            "DISTANCE MM",
            black,
            false,
        );
        cv.text(20, TOP as i64 + ph as i64 / 2 + 80, "3-D ERROR MM", black, true);
        cv.text(LEFT as i64, 14, "ACCURACY VS TABLE I (LOG SCALE)", black, false);

        let blue = [20, 80, 220];
        let light_blue = [120, 170, 255];
        let red = [210, 30, 30];
        let light_red = [255, 150, 150];
        let dark = [90, 90, 90];
        let green = [0, 150, 60];
        let series: Vec<(&str, [u8; 3], usize, Metric, &str)> = vec![
            ("convergent", dark, 0, Metric::Reference, "TABLE I CONV X=Y=Z"),
            ("convergent", green, 8, Metric::Goal, "GOAL = TABLE I / 10"),
            ("convergent", blue, 0, Metric::Rms, "CONVERGENT RMS"),
            ("convergent", light_blue, 6, Metric::P95, "CONVERGENT P95"),
            (
                "parallel",
                [150, 150, 150],
                0,
                Metric::Reference,
                "TABLE I PARALLEL Z",
            ),
            ("parallel", red, 0, Metric::Rms, "PARALLEL RMS"),
            ("parallel", light_red, 6, Metric::P95, "PARALLEL P95"),
        ];
        for (k, (rig, color, dash, metric, label)) in series.iter().enumerate() {
            let pts: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| r.rig == *rig)
                .filter_map(|r| {
                    metric
                        .value(r)
                        .filter(|v| *v > 0.0)
                        .map(|v| (fx(r.distance_mm), fy(v)))
                })
                .collect();
            for w in pts.windows(2) {
                cv.line(w[0], w[1], 3, *dash, *color);
            }
            for p in &pts {
                cv.dot(p.0 as i64, p.1 as i64, 4, *color);
            }
            let ly = TOP as i64 + 10 + 28 * k as i64;
            let lx = (W - RIGHT) as i64 + 20;
            cv.line(
                (lx as f64, ly as f64 + 7.0),
                (lx as f64 + 30.0, ly as f64 + 7.0),
                3,
                *dash / 2,
                *color,
            );
            cv.dot(lx + 15, ly + 7, 4, *color);
            cv.text(lx + 40, ly, label, black, false);
        }
        let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), W as u32, H as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().context("PNG header")?;
        wr.write_image_data(&cv.rgb).context("PNG data")?;
        Ok(())
    }
}
