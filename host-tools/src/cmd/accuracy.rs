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
    /// Rig layout: `convergent` or `parallel`.
    pub rig: &'static str,
    /// Working distance of this row (mm).
    pub distance_mm: f64,
    /// Table I's figure for the rig's worst axis, or the same analytic model between its rows.
    pub reference_mm: f64,
    /// Whether `reference_mm` is printed in Table I (otherwise it is the model's value).
    pub in_table_i: bool,
    /// Frames simulated.
    pub frames: u64,
    /// Frames in which the tracker found a position.
    pub tracked: u64,
    /// 3-D error statistics of the tracked frames against truth; `None` when none was tracked.
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

/// The study's log-scale plot, drawn with plotters (shared font and PNG helpers of
/// `calib::plots`).
pub mod plot {
    use super::*;
    use crate::calib::plots::{FONT, draw_err, draw_legend, ensure_font, write_rgb_png};
    use plotters::prelude::*;

    const W: u32 = 960;
    const H: u32 = 600;

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
        ensure_font()?;
        let (dmin, dmax) = rows.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), r| {
            (a.min(r.distance_mm), b.max(r.distance_mm))
        });
        anyhow::ensure!(dmin.is_finite(), "no study rows to plot");
        let x_lo = ((dmin - 100.0) / 500.0).floor() * 500.0;
        let x_hi = ((dmax + 100.0) / 500.0).ceil() * 500.0;
        let metrics = [Metric::Reference, Metric::Goal, Metric::Rms, Metric::P95];
        let vals: Vec<f64> = rows
            .iter()
            .flat_map(|r| metrics.iter().filter_map(|m| m.value(r)))
            .filter(|v| *v > 0.0 && v.is_finite())
            .collect();
        let lo = 10f64.powf(vals.iter().cloned().fold(f64::INFINITY, f64::min).log10().floor());
        let hi = 10f64.powf(
            vals.iter()
                .cloned()
                .fold(f64::NEG_INFINITY, f64::max)
                .log10()
                .ceil(),
        );
        let hi = hi.max(lo * 10.0);
        let mut rgb = vec![255u8; (W * H * 3) as usize];
        {
            let root = BitMapBackend::with_buffer(&mut rgb, (W, H)).into_drawing_area();
            let mut chart = ChartBuilder::on(&root)
                .caption("accuracy vs Table I (log scale)", (FONT, 20))
                .margin(14)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d(x_lo..x_hi, (lo..hi).log_scale())
                .map_err(draw_err)?;
            chart
                .configure_mesh()
                .x_desc("distance (mm)")
                .y_desc("3-D error (mm)")
                .x_label_formatter(&|d| format!("{d:.0}"))
                .y_label_formatter(&|v| format!("{v}"))
                .label_style((FONT, 14))
                .draw()
                .map_err(draw_err)?;
            let dark = RGBColor(90, 90, 90);
            let series: [(&str, RGBColor, bool, Metric, &str); 7] = [
                (
                    "convergent",
                    dark,
                    false,
                    Metric::Reference,
                    "Table I, convergent x=y=z",
                ),
                (
                    "convergent",
                    RGBColor(0, 150, 60),
                    true,
                    Metric::Goal,
                    "goal = Table I / 10",
                ),
                (
                    "convergent",
                    RGBColor(20, 80, 220),
                    false,
                    Metric::Rms,
                    "convergent RMS",
                ),
                (
                    "convergent",
                    RGBColor(120, 170, 255),
                    true,
                    Metric::P95,
                    "convergent p95",
                ),
                (
                    "parallel",
                    RGBColor(150, 150, 150),
                    false,
                    Metric::Reference,
                    "Table I, parallel z",
                ),
                (
                    "parallel",
                    RGBColor(210, 30, 30),
                    false,
                    Metric::Rms,
                    "parallel RMS",
                ),
                (
                    "parallel",
                    RGBColor(255, 150, 150),
                    true,
                    Metric::P95,
                    "parallel p95",
                ),
            ];
            for (rig, colour, dashed, metric, label) in series {
                let pts: Vec<(f64, f64)> = rows
                    .iter()
                    .filter(|r| r.rig == rig)
                    .filter_map(|r| metric.value(r).filter(|v| *v > 0.0).map(|v| (r.distance_mm, v)))
                    .collect();
                let style = colour.stroke_width(3);
                let drawn = if dashed {
                    chart.draw_series(DashedLineSeries::new(pts.clone(), 10, 6, style))
                } else {
                    chart.draw_series(LineSeries::new(pts.clone(), style))
                };
                drawn.map_err(draw_err)?.label(label).legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 24, y)], colour.stroke_width(3))
                });
                chart
                    .draw_series(pts.iter().map(|p| Circle::new(*p, 4, colour.filled())))
                    .map_err(draw_err)?;
            }
            draw_legend(&mut chart, SeriesLabelPosition::LowerRight, 14)?;
            root.present().map_err(draw_err)?;
        }
        write_rgb_png(path, W, H, &rgb)
    }
}
