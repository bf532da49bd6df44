//! `host-tools plan`: analytic resolution of a rig along each axis, at given distances and over
//! a workspace cube, next to the paper's Table I.
//!
//! Resolution = the displacement that moves some camera's image of the marker, or some camera
//! pair's disparity, by one pixel (see `irtrack_sim::resolution`). Cameras are ideal pinholes.

use std::fmt::Write as _;

use anyhow::bail;
use irtrack_sim::resolution::{
    AxisResolution, TABLE_I, convergent_closed_form, ideal_camera, ideal_convergent, ideal_parallel,
    parallel_closed_form, resolution_at,
};
use irtrack_sim::rig::{TABLE_I_BASELINE_MM, TABLE_I_FOCAL_PX};
use nalgebra::Vector3;

/// Which rig(s) to plan.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RigKind {
    /// Two cameras side by side with parallel optical axes.
    Parallel,
    /// Two cameras whose optical axes cross at the working distance.
    Convergent,
    /// Both rigs, one row each.
    Both,
}

/// Arguments.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Rig type.
    #[arg(long, value_enum, default_value = "both")]
    pub rig: RigKind,
    /// Working distance(s) in mm (comma-separated). Convergent rigs are planned with their
    /// axes crossing at each distance. Default: Table I's distances.
    #[arg(long, value_delimiter = ',', default_values_t = [659.84, 2309.44])]
    pub distance_mm: Vec<f64>,
    /// Focal length (px).
    #[arg(long, default_value_t = TABLE_I_FOCAL_PX)]
    pub focal_px: f64,
    /// Parallel baseline (mm).
    #[arg(long, default_value_t = TABLE_I_BASELINE_MM)]
    pub baseline_mm: f64,
    /// Angle between the convergent rig's optical axes (deg).
    #[arg(long, default_value_t = 90.0)]
    pub angle_deg: f64,
    /// Sensor width (px).
    #[arg(long, default_value_t = 640)]
    pub width_px: u32,
    /// Sensor height (px).
    #[arg(long, default_value_t = 480)]
    pub height_px: u32,
    /// Side of the workspace cube around the working point over which the worst resolution is
    /// reported (mm; 0 = the working point only).
    #[arg(long, default_value_t = 200.0)]
    pub workspace_mm: f64,
    /// Grid points per cube edge.
    #[arg(long, default_value_t = 5)]
    pub grid: usize,
}

/// One line of the plan.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanRow {
    /// Rig layout: `convergent` or `parallel`.
    pub rig: &'static str,
    /// Working distance of this row (mm).
    pub distance_mm: f64,
    /// Closed-form resolution at the working point.
    pub closed_form: AxisResolution,
    /// Exact-projection resolution at the working point.
    pub at_point: AxisResolution,
    /// Worst exact resolution per axis over the workspace cube (points seen by both cameras).
    pub workspace_worst: AxisResolution,
    /// Table I's figures (x=y, z) when the distance is one of the table's.
    pub table_i: Option<(f64, f64)>,
}

/// Computes the plan.
pub fn plan(args: &Args) -> anyhow::Result<Vec<PlanRow>> {
    if !(args.focal_px > 0.0 && args.baseline_mm > 0.0 && args.angle_deg > 0.0 && args.angle_deg < 180.0) {
        bail!("focal length and baseline must be > 0 and the angle in (0, 180) deg");
    }
    if args.width_px == 0 || args.height_px == 0 || args.grid == 0 {
        bail!("sensor size and grid must be non-zero");
    }
    let cam = ideal_camera(args.focal_px, args.width_px, args.height_px);
    let mut rows = Vec::new();
    for &d in &args.distance_mm {
        if !(d > 0.0 && d.is_finite()) {
            bail!("distance {d} mm must be > 0");
        }
        let table = TABLE_I.iter().find(|t| (t.0 - d).abs() < 1e-6);
        let kinds: &[RigKind] = match args.rig {
            RigKind::Both => &[RigKind::Convergent, RigKind::Parallel],
            RigKind::Parallel => &[RigKind::Parallel],
            RigKind::Convergent => &[RigKind::Convergent],
        };
        for kind in kinds {
            let (name, rig, point, closed, tab) = match kind {
                RigKind::Parallel => (
                    "parallel",
                    ideal_parallel(cam, args.baseline_mm),
                    // Table I's reference: on camera 0's optical axis.
                    Vector3::new(0.0, 0.0, d),
                    parallel_closed_form(args.focal_px, args.baseline_mm, d),
                    table.map(|t| (t.2, t.3)),
                ),
                _ => (
                    "convergent",
                    ideal_convergent(cam, d, args.angle_deg),
                    Vector3::new(0.0, 0.0, d),
                    convergent_closed_form(args.focal_px, d, args.angle_deg),
                    table.map(|t| (t.1, t.1)),
                ),
            };
            let at_point = resolution_at(&rig, &point)?;
            let mut worst = at_point;
            let n = args.grid;
            for i in 0..n {
                for j in 0..n {
                    for k in 0..n {
                        let f = |a: usize| {
                            if n == 1 {
                                0.0
                            } else {
                                (a as f64 / (n - 1) as f64 - 0.5) * args.workspace_mm
                            }
                        };
                        let p = point + Vector3::new(f(i), f(j), f(k));
                        let visible = rig.cameras.iter().all(|c| {
                            c.model
                                .project(&c.cam_from_cam0.apply(&p))
                                .is_ok_and(|q| c.model.contains_px(&q))
                        });
                        if !visible {
                            continue;
                        }
                        let r = resolution_at(&rig, &p)?;
                        worst.x_mm = worst.x_mm.max(r.x_mm);
                        worst.y_mm = worst.y_mm.max(r.y_mm);
                        worst.z_mm = worst.z_mm.max(r.z_mm);
                    }
                }
            }
            rows.push(PlanRow {
                rig: name,
                distance_mm: d,
                closed_form: closed,
                at_point,
                workspace_worst: worst,
                table_i: if args.focal_px == TABLE_I_FOCAL_PX
                    && args.baseline_mm == TABLE_I_BASELINE_MM
                    && args.angle_deg == 90.0
                    && args.width_px == 640
                {
                    tab
                } else {
                    None
                },
            });
        }
    }
    Ok(rows)
}

/// Formats the plan as a text table.
pub fn format_plan(args: &Args, rows: &[PlanRow]) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "resolution = displacement moving some camera's image (or a pair's disparity) by 1 px\n\
         cameras: {}x{} px, f = {} px; parallel baseline {} mm; convergent axes at {} deg\n",
        args.width_px, args.height_px, args.focal_px, args.baseline_mm, args.angle_deg
    );
    let _ = writeln!(
        s,
        "{:<11} {:>9} | {:>8} {:>8} {:>8} | {:>8} {:>8} {:>8} | worst over {} mm cube: {:>7} {:>7} {:>7} | Table I x/y, z",
        "rig",
        "dist_mm",
        "x_mm",
        "y_mm",
        "z_mm",
        "exact_x",
        "exact_y",
        "exact_z",
        args.workspace_mm,
        "x",
        "y",
        "z"
    );
    for r in rows {
        let t = r
            .table_i
            .map(|(a, b)| format!("{a:.2}, {b:.2}"))
            .unwrap_or_else(|| "-".into());
        let _ = writeln!(
            s,
            "{:<11} {:>9.2} | {:>8.2} {:>8.2} {:>8.2} | {:>8.3} {:>8.3} {:>8.3} | {:>27} {:>7.2} {:>7.2} {:>7.2} | {t}",
            r.rig,
            r.distance_mm,
            r.closed_form.x_mm,
            r.closed_form.y_mm,
            r.closed_form.z_mm,
            r.at_point.x_mm,
            r.at_point.y_mm,
            r.at_point.z_mm,
            "",
            r.workspace_worst.x_mm,
            r.workspace_worst.y_mm,
            r.workspace_worst.z_mm,
        );
    }
    s
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let rows = plan(&args)?;
    print!("{}", format_plan(&args, &rows));
    Ok(())
}
