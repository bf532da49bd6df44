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
use crate::calib::{wand_boards, wand_report, wand_solve};

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
    let obs = wand::observe(&rec, &models, &wand)?;
    for c in 0..models.len() {
        let ok = obs.views.iter().filter(|r| r[c].is_ok()).count();
        eprintln!("cam{c}: wand identified in {ok} of {} frames", obs.frames.len());
    }
    let options = wand_solve::SolveOptions {
        refine_intrinsics,
        fix_k3: args.fix_k3,
        huber_px: args.huber_px,
    };
    let sol = match wand_solve::solve(&models, &obs, &wand, &boards, options, |m| eprintln!("{m}")) {
        Ok(sol) => sol,
        Err(e) => {
            // Say what the spots alone tell about the intrinsics, if anything.
            let (causes, _) = wand_quality::intrinsics_causes(&models, &obs, &wand);
            if causes.is_empty() {
                return Err(e);
            }
            return Err(e.context(format!("Likely cause: {}", causes.join(". Also: "))));
        }
    };
    let now = now_unix_s();
    let mut rig = RigParams {
        rig_id: args.rig_id.clone().unwrap_or_else(|| format!("wand-{now}")),
        created_unix_s: now,
        cameras: sol.cameras.clone(),
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
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
    gate.enforce(args.accept_poor)?;
    rig.calibration = Some(Box::new(gate.record(now)));
    crate::placement::for_calibration(&mut rig, &args.frames, args.placement.as_deref())?;
    rig.validate()
        .context("wand calibration produced unusable parameters")?;
    let (written, _) = wand_report::write_outputs(&args.out_dir, &sol, &rig, &wand, &obs.frames)?;
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
