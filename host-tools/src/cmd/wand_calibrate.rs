//! `host-tools wand-calibrate`: camera poses (and optionally intrinsics) of an N-camera rig from
//! a wave of a collinear LED wand. See docs/calibration.md, "Wand calibration".
//!
//! Non-interactive; the progress bar is drawn only when stderr is a terminal.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use irtrack_core::params::RigParams;

use crate::calib::detect::Board;
use crate::calib::quality::now_unix_s;
use crate::calib::wand::{self, Wand};
use crate::calib::wand_quality::{self, WandRun};
use crate::calib::{wand_boards, wand_report, wand_solve, wand_time};
use crate::cmd::convert_params::parse_timing;
use irtrack_core::timing::{CameraTiming, Shutter};

/// Rounds of (estimate the offsets, adjust again with the retimed LEDs) at most.
const TIME_ROUNDS: usize = 3;
/// The adjustment is run again only when an offset moved by more than this (ns).
const RESOLVE_ABOVE_NS: f64 = 5_000.0;

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Recording with cam0/, cam1/, ... holding PGM frames paired by file name.
    #[arg(long)]
    pub frames: PathBuf,
    /// Each camera's intrinsics: OpenCV YAML with K<n>, D<n> and the image size (as
    /// `calibrate` writes), or a parameter blob.
    #[arg(long)]
    pub intrinsics: PathBuf,
    /// LED distances from one end of the wand, mm, e.g. 0,120,300 (unequal spacing).
    #[arg(long)]
    pub wand_mm: String,
    /// Output directory (created).
    #[arg(long)]
    pub out_dir: PathBuf,
    /// Also refine every camera's intrinsics and distortion in the bundle adjustment.
    #[arg(long)]
    pub refine_intrinsics: bool,
    /// Checkerboard views of every camera (cam0/, cam1/, ... as `calibrate --images` reads them,
    /// e.g. the views the intrinsics came from): their corners join the adjustment and pin each
    /// camera's intrinsics, which are then refined (implies --refine-intrinsics). Needs
    /// --board-cols, --board-rows and --square-mm.
    #[arg(long, requires_all = ["board_cols", "board_rows", "square_mm"])]
    pub boards: Option<PathBuf>,
    /// With --boards: comma-separated file-name patterns, one per camera (as `calibrate
    /// --pattern`), for a flat board directory.
    #[arg(long, requires = "boards")]
    pub board_pattern: Option<String>,
    /// With --boards: inner corners per board row.
    #[arg(long, requires = "boards")]
    pub board_cols: Option<u32>,
    /// With --boards: inner corners per board column.
    #[arg(long, requires = "boards")]
    pub board_rows: Option<u32>,
    /// With --boards: side of one printed square, mm.
    #[arg(long, requires = "boards")]
    pub square_mm: Option<f64>,
    /// When intrinsics are refined: keep each camera's k3 as the intrinsics file gives it (as
    /// `calibrate --fix-k3` does; recommended for ordinary lenses).
    #[arg(long)]
    pub fix_k3: bool,
    /// Huber loss threshold, px.
    #[arg(long, default_value_t = 1.0)]
    pub huber_px: f64,
    /// Rig id written into the parameters (default: wand-<unix time>).
    #[arg(long)]
    pub rig_id: Option<String>,
    /// Write the result even when it fails a quality limit (docs/calibration.md, "Quality
    /// gates"); it is marked poor in the parameters, and push-params then refuses it unless told
    /// --accept-poor too.
    #[arg(long)]
    pub accept_poor: bool,
    /// Where each camera sits when the cameras are on several boards, camera 0 first:
    /// BOARD:INDEX,… (the board's `[cluster] board` name and the camera's index there, e.g.
    /// b0:0,b0:1,b1:0,b1:1). Default: the capture folder's cameras.csv when its boards reported
    /// names (`host-tools capture --from A --from B`); none for one board (docs/cluster.md).
    #[arg(long, value_name = "BOARD:INDEX,…")]
    pub placement: Option<String>,
    /// A camera's known timing, as `convert-params --timing`: CAM:SHUTTER[:KEY=VALUE]… with keys
    /// line_time_us, exposure_us, offset_us (e.g. 1:rolling:line_time_us=15.2). Repeat per
    /// camera. With the recording's timestamps.csv, camera 0's offset is the reference and the
    /// other cameras' offsets are estimated from the wave (docs/calibration.md, "Time offsets").
    #[arg(long, value_name = "CAM:SHUTTER[:KEY=VALUE]…")]
    pub timing: Vec<String>,
    /// Also estimate the line time of every camera ≠ 0 declared rolling with `--timing` (its
    /// given line time is the starting point; searched over 0…2× it) jointly with its offset.
    #[arg(long)]
    pub estimate_line_time: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    let start = Instant::now();
    let wand = Wand::parse(&args.wand_mm)?;
    if !(args.huber_px > 0.0 && args.huber_px.is_finite()) {
        bail!("--huber-px must be positive, got {}", args.huber_px);
    }
    let models = wand::read_intrinsics(&args.intrinsics)?;
    if models.len() < 2 {
        bail!(
            "{}: intrinsics for {} camera(s); a rig needs at least 2",
            args.intrinsics.display(),
            models.len()
        );
    }
    let refine_intrinsics = args.refine_intrinsics || args.boards.is_some();
    // A wrong placement is said before the calibration, not after it.
    crate::placement::precheck(&args.frames, args.placement.as_deref(), models.len())?;
    if args.fix_k3 && !refine_intrinsics {
        bail!("--fix-k3 applies to refined intrinsics: add --refine-intrinsics or --boards");
    }
    let boards = match &args.boards {
        Some(dir) => {
            let board = Board {
                cols: args.board_cols.unwrap_or(0),
                rows: args.board_rows.unwrap_or(0),
                square_mm: args.square_mm.unwrap_or(f64::NAN),
            };
            if board.cols < 2 || board.rows < 2 {
                bail!(
                    "board of {}x{} inner corners is too small; --board-cols/--board-rows count inner corners",
                    board.cols,
                    board.rows
                );
            }
            if !(board.square_mm > 0.0 && board.square_mm.is_finite()) {
                bail!("--square-mm must be a positive length, got {}", board.square_mm);
            }
            let b = wand_boards::read_board_views(dir, args.board_pattern.as_deref(), &board, &models)?;
            for (c, n) in b.per_camera(models.len()).iter().enumerate() {
                let missed = b.not_found.iter().filter(|(nc, _)| *nc == c).count();
                eprintln!("cam{c}: board found in {n} of {} images", n + missed);
            }
            b.views
        }
        None => Vec::new(),
    };
    let rec = wand::discover(&args.frames, models.len(), &args.intrinsics)?;
    eprintln!("{} cameras, {} frames", models.len(), rec.frames.len());
    let raw_obs = wand::observe(&rec, &models, &wand)?;
    for c in 0..models.len() {
        let ok = raw_obs.views.iter().filter(|r| r[c].is_ok()).count();
        eprintln!(
            "cam{c}: wand identified in {ok} of {} frames",
            raw_obs.frames.len()
        );
    }
    let options = wand_solve::SolveOptions {
        refine_intrinsics,
        fix_k3: args.fix_k3,
        huber_px: args.huber_px,
    };
    let mut timing = vec![CameraTiming::default(); models.len()];
    let mut time_skipped = String::from(
        "not estimated: the recording has no timestamps.csv, so the cameras are taken as exposing together",
    );
    for spec in &args.timing {
        let (c, t) = parse_timing(spec, models.len())?;
        timing[c] = t;
    }
    let clock = match wand_time::read_clock(&args.frames, models.len(), &raw_obs.frames)? {
        Some(c) if c.not_continuous.is_some() => {
            time_skipped = format!(
                "not estimated: {} — the cameras are taken as exposing together",
                c.not_continuous.as_deref().unwrap_or_default()
            );
            None
        }
        Some(c) => Some(c),
        None => None,
    };
    // With timestamps each frame's LEDs are moved to camera 0's instant before the adjustment;
    // the offsets are then estimated with the solved geometry and the adjustment run again.
    let mut obs = match &clock {
        Some(clock) => wand_time::retime_observations(&raw_obs, clock, &timing),
        None => raw_obs.clone(),
    };
    let solve =
        |obs: &wand::WandObservations| match wand_solve::solve(&models, obs, &wand, &boards, options, |m| {
            eprintln!("{m}")
        }) {
            Ok(sol) => Ok(sol),
            Err(e) => {
                // Say what the spots alone tell about the intrinsics, if anything.
                let causes = wand_quality::intrinsics_causes(&models, obs);
                if causes.is_empty() {
                    return Err(e);
                }
                Err(e.context(format!("Likely cause: {}", causes.join(". Also: "))))
            }
        };
    let mut sol = solve(&obs)?;
    let mut time_result = None;
    if let Some(clock) = &clock {
        for round in 1..=TIME_ROUNDS {
            // The views the adjustment kept (outliers and misidentified views left out), as seen.
            let mut kept = raw_obs.clone();
            for (row, solved) in kept.views.iter_mut().zip(&sol.views) {
                for (v, s) in row.iter_mut().zip(solved) {
                    if let Err(e) = s {
                        *v = Err(e.clone());
                    }
                }
            }
            let r = wand_time::estimate(
                &sol.cameras,
                &kept,
                clock,
                &timing,
                args.huber_px,
                args.estimate_line_time,
            );
            let mut moved_ns: f64 = 0.0;
            for e in &r.offsets {
                if let Some(d) = e.offset_vs_cam0_ns {
                    let new = timing[0].offset_ns + d.round() as i64;
                    moved_ns = moved_ns.max((new - timing[e.camera].offset_ns).abs() as f64);
                    timing[e.camera].offset_ns = new;
                }
                if let Some(l) = e.line_time_ns {
                    let old = f64::from(timing[e.camera].line_time_ns);
                    // A line time change moves the bottom row's instant by rows × the change.
                    let rows = f64::from(models[e.camera].image_size.height_px);
                    moved_ns = moved_ns.max((l - old).abs() * rows);
                    timing[e.camera].line_time_ns = l.round() as u32;
                }
            }
            eprintln!(
                "time offsets, round {round}: {} (changed by up to {:.0} µs)",
                offsets_line(&r),
                moved_ns * 1e-3
            );
            time_result = Some(r);
            if moved_ns < RESOLVE_ABOVE_NS {
                break;
            }
            obs = wand_time::retime_observations(&raw_obs, clock, &timing);
            sol = solve(&obs)?;
        }
    } else {
        eprintln!("time offsets {time_skipped}");
    }
    let now = now_unix_s();
    let mut rig = RigParams {
        rig_id: args.rig_id.clone().unwrap_or_else(|| format!("wand-{now}")),
        created_unix_s: now,
        cameras: sol.cameras.clone(),
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        // Written only when some camera's timing differs from the default.
        timing: if timing.iter().any(|t| *t != CameraTiming::default()) {
            timing.clone()
        } else {
            Vec::new()
        },
        // A new set: its serial is the time it was made (docs/param-blob.md, "Serial").
        serial: RigParams::next_serial(0, now),
    };
    rig.validate()
        .context("wand calibration produced unusable parameters")?;
    let fig = wand_report::figures(&sol, &rig, &wand);
    let gate = wand_quality::judge(&WandRun {
        models: &models,
        obs: &obs,
        wand: &wand,
        boards: &boards,
        options,
        sol: &sol,
        fig: &fig,
    });
    print_figures(&rig, &sol, &fig)?;
    let time_text = time_report(time_result.as_ref(), &timing, &time_skipped);
    print!("{time_text}");
    gate.enforce(args.accept_poor)?;
    rig.calibration = Some(Box::new(gate.record(now)));
    crate::placement::for_calibration(&mut rig, &args.frames, args.placement.as_deref())?;
    rig.validate()
        .context("wand calibration produced unusable parameters")?;
    let (mut written, _) = wand_report::write_outputs(&args.out_dir, &sol, &rig, &wand, &obs.frames)?;
    // The time offsets join the report and get a machine-readable file of their own.
    let report = args.out_dir.join("report.md");
    let mut md =
        std::fs::read_to_string(&report).with_context(|| format!("{}: cannot read", report.display()))?;
    md.push_str("\n## Time offsets\n\n");
    md.push_str(&time_text);
    std::fs::write(&report, md).with_context(|| format!("{}: cannot write", report.display()))?;
    let p = args.out_dir.join("time_offsets.json");
    std::fs::write(&p, time_json(time_result.as_ref(), &timing)?)
        .with_context(|| format!("{}: cannot write", p.display()))?;
    written.push(p);
    println!("done in {:.1} s", start.elapsed().as_secs_f64());
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}

fn print_figures(rig: &RigParams, sol: &wand_solve::WandSolution, fig: &wand_report::Figures) -> Result<()> {
    for c in 0..rig.cameras.len() {
        let extra = if c == 0 {
            String::new()
        } else {
            format!(
                ", baseline {:.3} mm, optical axes {:.3}° apart",
                rig.baseline_mm(c)?,
                rig.optical_axis_angle_deg(c)?
            )
        };
        println!(
            "cam{c}: reprojection RMS {:.4} px over {} views, coverage {:.0} %{extra}",
            fig.per_camera_rms_px[c],
            sol.per_camera_views[c],
            fig.coverage[c] * 100.0
        );
    }
    if !sol.boards.is_empty() {
        for c in 0..rig.cameras.len() {
            let fits: Vec<_> = sol
                .boards
                .iter()
                .filter(|b| b.camera == c && b.rejected.is_none())
                .collect();
            let rms =
                (fits.iter().map(|b| b.rms_px * b.rms_px).sum::<f64>() / fits.len().max(1) as f64).sqrt();
            println!(
                "cam{c}: board corners RMS {rms:.4} px over {} board views",
                fits.len()
            );
        }
    }
    println!(
        "wand length error over {} frames: mean {:+.4} mm, std {:.4} mm, max {:.4} mm",
        fig.frames_used, fig.length_mean_mm, fig.length_std_mm, fig.length_max_abs_mm
    );
    Ok(())
}

fn offsets_line(r: &wand_time::TimingResult) -> String {
    let v: Vec<String> = r
        .offsets
        .iter()
        .map(|e| match e.offset_vs_cam0_ns {
            Some(d) => format!(
                "cam{} {:+.1} µs ± {:.1} µs",
                e.camera,
                d * 1e-3,
                e.sigma_ns * 1e-3
            ),
            None => format!("cam{} not observable", e.camera),
        })
        .collect();
    v.join(", ")
}

/// The time-offset part of the report (stdout and report.md).
fn time_report(r: Option<&wand_time::TimingResult>, timing: &[CameraTiming], skipped: &str) -> String {
    use std::fmt::Write as _;
    let mut s = String::new();
    let Some(r) = r else {
        let _ = writeln!(s, "time offsets {skipped}");
        return s;
    };
    for (c, t) in timing.iter().enumerate() {
        let e = r.offsets.iter().find(|e| e.camera == c);
        let shutter = match (
            t.shutter,
            e.and_then(|e| e.line_time_ns.zip(e.line_time_sigma_ns)),
        ) {
            (Shutter::Global, _) => "global shutter".to_string(),
            (Shutter::Rolling, Some((_, sigma))) => format!(
                "rolling shutter, line time {:.3} µs ± {:.3} µs (estimated)",
                f64::from(t.line_time_ns) * 1e-3,
                sigma * 1e-3
            ),
            (Shutter::Rolling, None) => match e.and_then(|e| e.line_time_sigma_ns) {
                Some(sigma) => format!(
                    "rolling shutter, line time {:.3} µs (as given; the wave cannot tell it: ± {:.3} µs)",
                    f64::from(t.line_time_ns) * 1e-3,
                    sigma * 1e-3
                ),
                None => format!(
                    "rolling shutter, line time {:.3} µs (as given)",
                    f64::from(t.line_time_ns) * 1e-3
                ),
            },
        };
        let clock = format!(
            "frame period {:.3} ms, timestamp jitter {:.0} µs RMS",
            r.period_ns[c] * 1e-6,
            r.jitter_rms_ns[c] * 1e-3
        );
        let line = if c == 0 {
            format!(
                "cam0: time offset {:+.1} µs (the reference, as given); {shutter}; {clock}",
                t.offset_ns as f64 * 1e-3
            )
        } else {
            match e {
                Some(e) => match (e.offset_vs_cam0_ns, &e.not_observable) {
                    (Some(d), _) => format!(
                        "cam{c}: time offset {:+.1} µs ± {:.1} µs against camera 0 ({} frames, halves {}, \
                         two-view RMS {:.3} px, wand {:.2} px/ms); {shutter}; {clock}",
                        d * 1e-3,
                        e.sigma_ns * 1e-3,
                        e.shared_frames,
                        e.halves_ns.map_or("-".into(), |(a, b)| format!(
                            "{:+.1}/{:+.1} µs",
                            a * 1e-3,
                            b * 1e-3
                        )),
                        e.rms_px,
                        e.image_speed_px_per_ms
                    ),
                    (None, why) => format!(
                        "cam{c}: time offset NOT OBSERVABLE: {}; kept at {:+.1} µs; {shutter}; {clock}",
                        why.as_deref().unwrap_or("no estimate"),
                        t.offset_ns as f64 * 1e-3
                    ),
                },
                None => format!("cam{c}: no estimate"),
            }
        };
        let _ = writeln!(s, "{line}");
    }
    s
}

/// `time_offsets.json`: per camera the offset written, and the estimate behind it.
fn time_json(r: Option<&wand_time::TimingResult>, timing: &[CameraTiming]) -> Result<String> {
    let cams: Vec<serde_json::Value> = timing
        .iter()
        .enumerate()
        .map(|(c, t)| {
            let e = r.and_then(|r| r.offsets.iter().find(|e| e.camera == c));
            serde_json::json!({
                "camera": c,
                "shutter": t.shutter.as_str(),
                "line_time_ns": t.line_time_ns,
                "offset_ns": t.offset_ns,
                "estimated": e.is_some_and(|e| e.offset_vs_cam0_ns.is_some()),
                "offset_vs_cam0_ns": e.and_then(|e| e.offset_vs_cam0_ns),
                "sigma_ns": e.and_then(|e| e.sigma_ns.is_finite().then_some(e.sigma_ns)),
                "halves_ns": e.and_then(|e| e.halves_ns.map(|(a, b)| [a, b])),
                "shared_frames": e.map(|e| e.shared_frames),
                "image_speed_px_per_ms": e.map(|e| e.image_speed_px_per_ms),
                "not_observable": e.and_then(|e| e.not_observable.clone()),
                "line_time_estimated": e.is_some_and(|e| e.line_time_ns.is_some()),
                "line_time_sigma_ns": e.and_then(|e| e.line_time_sigma_ns.filter(|s| s.is_finite())),
                "period_ns": r.map(|r| r.period_ns[c]),
                "jitter_rms_ns": r.map(|r| r.jitter_rms_ns[c]),
            })
        })
        .collect();
    Ok(serde_json::to_string_pretty(&serde_json::json!({
        "timestamps": r.is_some(),
        "cameras": cams,
    }))?)
}
