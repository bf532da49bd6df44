//! `host-tools calibrate`: calibrate a rig of N ≥ 2 cameras from chessboard images with OpenCV.
//!
//! Non-interactive: no prompts; the progress bar is drawn only when stderr is a terminal.
//! Writes rig.irp (blob), rig.yaml (OpenCV FileStorage), report.md, coverage_cam<i>.png and
//! view_errors.png into `--out-dir`. See docs/calibration.md.

use std::path::PathBuf;

use anyhow::{Result, bail};

use crate::calib::{self, Options, board_quality, detect::Board, input, report};

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Directory with the images: subdirectories cam0/, cam1/, ... (views paired by file name),
    /// or a flat directory together with --pattern.
    #[arg(long)]
    pub images: PathBuf,
    /// Comma-separated file-name patterns, one per camera in camera order, e.g.
    /// 'left*.png,right*.png'; views pair by the text matched by the wildcards.
    #[arg(long)]
    pub pattern: Option<String>,
    /// Inner corners per board row (squares per row minus one).
    #[arg(long)]
    pub board_cols: u32,
    /// Inner corners per board column (squares per column minus one).
    #[arg(long)]
    pub board_rows: u32,
    /// Side of one printed square, mm (measure the print).
    #[arg(long)]
    pub square_mm: f64,
    /// Output directory (created).
    #[arg(long)]
    pub out_dir: PathBuf,
    /// Reject views whose per-view RMS is an outlier, then recalibrate.
    #[arg(long)]
    pub reject_outliers: bool,
    /// Outlier factor k in median + k·1.4826·MAD.
    #[arg(long, default_value_t = 3.0)]
    pub outlier_k: f64,
    /// After the fixed-intrinsics stereo calibration, refine intrinsics and poses jointly.
    #[arg(long)]
    pub joint_refine: bool,
    /// Keep k3 at 0 (recommended for ordinary lenses with few views).
    #[arg(long)]
    pub fix_k3: bool,
    /// Rig id written into the parameters (default: calib-<unix time>).
    #[arg(long)]
    pub rig_id: Option<String>,
    /// The distance between camera 0 and camera 1 as measured on the rig (mm): the calibrated
    /// baseline must agree within 1 % (a wrong --square-mm scales every length).
    #[arg(long)]
    pub expect_baseline_mm: Option<f64>,
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
    if args.board_cols < 2 || args.board_rows < 2 {
        bail!(
            "board of {}x{} inner corners is too small; --board-cols/--board-rows count inner corners (at least 2)",
            args.board_cols,
            args.board_rows
        );
    }
    if args.board_cols == args.board_rows {
        eprintln!(
            "warning: a square pattern ({0}x{0}) has a 90° ambiguous corner order; a board with different \
             column and row counts (one odd, one even) is safer for multi-camera calibration",
            args.board_cols
        );
    }
    if !(args.square_mm > 0.0 && args.square_mm.is_finite()) {
        bail!("--square-mm must be a positive length, got {}", args.square_mm);
    }
    if let Some(b) = args.expect_baseline_mm
        && !(b > 0.0 && b.is_finite())
    {
        bail!("--expect-baseline-mm must be a positive length, got {b}");
    }
    if !(args.outlier_k > 0.0 && args.outlier_k.is_finite()) {
        bail!("--outlier-k must be positive, got {}", args.outlier_k);
    }
    let board = Board {
        cols: args.board_cols,
        rows: args.board_rows,
        square_mm: args.square_mm,
    };
    let set = input::discover(&args.images, args.pattern.as_deref())?;
    // A wrong placement is said before the calibration, not after it.
    crate::placement::precheck(&args.images, args.placement.as_deref(), set.cameras.len())?;
    eprintln!(
        "{} cameras, {} complete views ({} incomplete)",
        set.cameras.len(),
        set.complete_views.len(),
        set.incomplete_views.len()
    );
    let det = calib::detect::detect_all(&set, &board)?;
    for (ci, d) in det.iter().enumerate() {
        eprintln!(
            "cam{ci} ({}): board found in {} of {} images",
            set.cameras[ci].label,
            d.found.len(),
            d.found.len() + d.not_found.len()
        );
    }
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let rig_id = args.rig_id.clone().unwrap_or_else(|| format!("calib-{now}"));
    let options = Options {
        reject_outliers: args.reject_outliers,
        outlier_k: args.outlier_k,
        joint_refine: args.joint_refine,
        fix_k3: args.fix_k3,
    };
    let mut cal = calib::calibrate(&set, det, board, options, &rig_id, now)?;
    for (v, why) in &cal.skipped {
        eprintln!("skipped view {v}: {why}");
    }
    for r in &cal.rejected {
        eprintln!("rejected view {} (round {}): {}", r.view, r.round, r.why);
    }
    println!(
        "overall RMS {:.4} px over {} views",
        report::overall_rms_px(&cal),
        cal.stereo_views.len()
    );
    for (ci, f) in cal.intrinsics.iter().enumerate() {
        let k = &cal.rig.cameras[ci].model.intrinsics;
        println!(
            "cam{ci}: RMS {:.4} px, fx {:.3} fy {:.3} cx {:.3} cy {:.3}",
            f.rms_px, k.fx_px, k.fy_px, k.cx_px, k.cy_px
        );
    }
    for i in 1..cal.rig.cameras.len() {
        println!(
            "cam{i}: baseline {:.3} mm, optical axes {:.3}° apart",
            cal.rig.baseline_mm(i)?,
            cal.rig.optical_axis_angle_deg(i)?
        );
    }
    let gate = board_quality::judge(&cal, args.expect_baseline_mm)?;
    gate.enforce(args.accept_poor)?;
    cal.rig.calibration = Some(Box::new(gate.record(now)));
    // A new set: its serial is the time it was made (docs/param-blob.md, "Serial").
    cal.rig.serial = irtrack_core::params::RigParams::next_serial(0, now);
    crate::placement::for_calibration(&mut cal.rig, &args.images, args.placement.as_deref())?;
    cal.rig
        .validate()
        .map_err(|e| anyhow::anyhow!("calibration record: {e}"))?;
    let written = report::write_outputs(&cal, &args.out_dir, &args.images)?;
    for p in written {
        println!("wrote {}", p.display());
    }
    Ok(())
}
