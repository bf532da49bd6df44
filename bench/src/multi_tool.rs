//! Several tools at once (issue 29): per-set cost of irtrackd's 6-DOF path with 1, 3 and 8
//! built-in tools in the simulator's 90° pair, VGA and 720p, side by side: full-frame blob
//! detection in both cameras plus `MultiTracker::process`, the tracker alone, per tool, and
//! heap allocations per set.
//!
//! The tools stand still at spread-out poses (rendered once, processed again and again: the
//! hot case; the tracker keeps its references, as in a running loop), and the scene is
//! checked first: every tool must be tracked within 1 mm / 0.5° of the simulator's truth.

use std::hint::black_box;

use anyhow::{Context, Result, bail};
use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits};
use irtrack_core::camera::{Distortion, ImageSize};
use irtrack_core::image::GrayImage;
use irtrack_core::params::ToolDefinition;
use irtrack_core::pose6d::{MultiTracker, PoseConfig, PoseStatus, quaternion_angle_rad};
use irtrack_sim::rig::CameraSpec;
use irtrack_sim::tools::{BUILTIN_TOOLS, builtin_tool};
use irtrack_sim::{Orientation, RigPreset, Scenario, SimConfig, Trajectory};
use nalgebra::{UnitQuaternion, Vector3};

use crate::{fmt_us, time_ns};

/// Tool counts of the table.
pub const TOOL_COUNTS: [usize; 3] = [1, 3, 8];

/// Where tool `i` of 8 stands: a 4 × 2 grid in the plane both cameras of the 90° pair see
/// edge-on least (along (1, 0, 1) and y through the crossing point), so the tools' images are
/// spread in both cameras.
fn placement(i: usize) -> (Vector3<f64>, UnitQuaternion<f64>) {
    let along = [-300.0, -100.0, 100.0, 300.0][i % 4];
    let up = if i / 4 == 0 { -110.0 } else { 110.0 };
    let d = Vector3::new(1.0, 0.0, 1.0).normalize();
    let centre = Vector3::new(0.0, 0.0, 1000.0) + d * along + Vector3::new(0.0, up, 0.0);
    // Each tool faces between the two cameras, turned a little differently.
    let k = i as f64;
    let q = UnitQuaternion::from_euler_angles(0.35 + 0.11 * k, -0.6 + 0.07 * k, 0.25 - 0.13 * k);
    (centre, q)
}

struct MultiScene {
    name: String,
    tools: Vec<ToolDefinition>,
    frames: [Vec<u8>; 2],
    width_px: u32,
    height_px: u32,
    sim: Scenario,
}

fn scene(n: usize, width_px: u32, height_px: u32, focal_px: f64) -> Result<MultiScene> {
    let tools: Vec<ToolDefinition> = BUILTIN_TOOLS[..n]
        .iter()
        .map(|t| builtin_tool(t).context("built-in tool"))
        .collect::<Result<_>>()?;
    let mut cfg = SimConfig::preset(
        RigPreset::Convergent {
            distance_mm: 1000.0,
            angle_deg: 90.0,
        },
        1000.0,
        50.0,
    );
    cfg.camera = CameraSpec {
        focal_px,
        image_size: ImageSize { width_px, height_px },
        distortion: Distortion {
            k1: -0.08,
            k2: 0.02,
            p1: 0.0004,
            p2: -0.0003,
            k3: 0.0,
        },
    };
    cfg.seed = 29;
    for (i, t) in tools.iter().enumerate() {
        let (p, q) = placement(i);
        if i == 0 {
            cfg.trajectory = Trajectory::Fixed(p);
            cfg.set_tool(&t.leds_mm, Orientation::Fixed(q));
        } else {
            cfg.add_tool(&t.leds_mm, Trajectory::Fixed(p), Orientation::Fixed(q));
        }
    }
    let mut sim = Scenario::new(cfg)?;
    let (w, h) = sim.image_size();
    let mut frames = [vec![0u8; (w * h) as usize], vec![0u8; (w * h) as usize]];
    for (c, f) in frames.iter_mut().enumerate() {
        sim.render_u8(0, c, f)?;
    }
    Ok(MultiScene {
        name: format!("{w}x{h}"),
        tools,
        frames,
        width_px: w,
        height_px: h,
        sim,
    })
}

/// irtrackd's per-set work for tools: full-frame detection in both cameras, then the tracker.
struct Pipeline {
    detectors: [BlobDetector; 2],
    blob_cfg: BlobConfig,
    tracker: MultiTracker,
}

impl Pipeline {
    fn new(s: &MultiScene) -> Result<Self> {
        let tracker = MultiTracker::new(s.sim.rig(), &s.tools, PoseConfig::default())?;
        // As irtrackd does: the detector keeps as many blobs as the tracker takes.
        let mut limits = BlobLimits::for_frame(s.width_px, s.height_px);
        limits.max_blobs = limits.max_blobs.max(tracker.config().max_blobs_per_camera);
        Ok(Pipeline {
            detectors: [BlobDetector::new(limits)?, BlobDetector::new(limits)?],
            blob_cfg: BlobConfig::default(),
            tracker,
        })
    }

    fn detect(&mut self, s: &MultiScene) -> Result<()> {
        for (c, d) in self.detectors.iter_mut().enumerate() {
            let img = GrayImage::new(&s.frames[c], s.width_px, s.height_px, s.width_px)?;
            d.detect(&img, None, &self.blob_cfg)?;
        }
        Ok(())
    }

    fn track(&mut self) -> Result<()> {
        let lists = [self.detectors[0].blobs(), self.detectors[1].blobs()];
        self.tracker.process(&lists)?;
        Ok(())
    }
}

/// One cell of the table (ns per set; allocations per set).
struct Cell {
    set_ns: f64,
    track_ns: f64,
    allocs_per_set: f64,
}

fn measure(
    n: usize,
    width_px: u32,
    height_px: u32,
    focal_px: f64,
    batches: usize,
    iters: usize,
) -> Result<(String, Cell)> {
    let s = scene(n, width_px, height_px, focal_px)?;
    let mut p = Pipeline::new(&s)?;
    // Correctness first: every tool tracked at its true pose (a few sets, so references exist).
    for _ in 0..3 {
        p.detect(&s)?;
        p.track()?;
    }
    let cfg = s.sim.config();
    for (b, t) in s.tools.iter().enumerate() {
        let pose = p.tracker.pose(b).context("tool index")?;
        if pose.status != PoseStatus::Tracked {
            let blobs = [p.detectors[0].blobs().len(), p.detectors[1].blobs().len()];
            bail!(
                "{n} tools, {}: {} not tracked: {:?} (blobs per camera {blobs:?}, {} candidate points)",
                s.name,
                t.name,
                pose.status,
                p.tracker.points().len()
            );
        }
        let (tp, tq) = cfg.body_pose(b, 0.0).context("body pose")?;
        let e_pos = (Vector3::from(pose.position_mm) - tp).norm();
        let e_rot = quaternion_angle_rad(&pose.quaternion_wxyz, &[tq.w, tq.i, tq.j, tq.k]).to_degrees();
        if e_pos > 1.0 || e_rot > 0.5 {
            bail!(
                "{n} tools, {}: {} is {e_pos:.3} mm / {e_rot:.3}° off the truth",
                s.name,
                t.name
            );
        }
    }
    let set_ns = time_ns(batches, iters, || {
        p.detect(&s)?;
        p.track()?;
        black_box(p.tracker.pose(0));
        Ok(())
    })?;
    p.detect(&s)?;
    let track_ns = time_ns(batches, iters * 4, || {
        p.track()?;
        black_box(p.tracker.pose(0));
        Ok(())
    })?;
    let a0 = irtrack_testkit::allocations();
    let runs = 100;
    for _ in 0..runs {
        p.detect(&s)?;
        p.track()?;
    }
    let allocs_per_set = (irtrack_testkit::allocations() - a0) as f64 / runs as f64;
    Ok((
        s.name,
        Cell {
            set_ns,
            track_ns,
            allocs_per_set,
        },
    ))
}

/// Prints the table: one row per tool count, VGA and 720p side by side.
pub fn table(quick: bool) -> Result<()> {
    let (batches, scale) = if quick { (3, 1) } else { (11, 6) };
    let resolutions = [(640u32, 480u32, 681.0f64), (1280, 720, 900.0)];
    let mut rows = Vec::new();
    let mut names = Vec::new();
    for &n in &TOOL_COUNTS {
        let mut cells = Vec::new();
        for &(w, h, f) in &resolutions {
            let iters = scale * if w > 640 { 8 } else { 20 };
            let (name, cell) = measure(n, w, h, f, batches, iters)?;
            if names.len() < resolutions.len() {
                names.push(name);
            }
            cells.push(cell);
        }
        rows.push((n, cells));
    }
    println!();
    println!(
        "Several tools at once (simulator's 90° pair, built-in tools standing still, hot; thread CPU time per stereo set, median of {batches} batches): \
         full-frame blob detection in both cameras + MultiTracker::process | the tracker alone | tracker per tool | allocations per set"
    );
    println!();
    let mut head = String::from("| tools |");
    let mut rule = String::from("|---|");
    for n in &names {
        head += &format!(" {n} set | {n} tracker | {n} tracker/tool | {n} allocs/set |");
        rule += "---|---|---|---|";
    }
    println!("{head}");
    println!("{rule}");
    for (n, cells) in &rows {
        let mut line = format!("| {n} |");
        for c in cells {
            line += &format!(
                " {} | {} | {} | {} |",
                fmt_us(c.set_ns),
                fmt_us(c.track_ns),
                fmt_us(c.track_ns / *n as f64),
                c.allocs_per_set
            );
        }
        println!("{line}");
    }
    println!();
    println!(
        "Goal: 0 allocations per set with any number of tools; every tool checked against the truth first."
    );
    let worst = rows
        .iter()
        .flat_map(|(_, c)| c.iter())
        .map(|c| c.allocs_per_set)
        .fold(0.0f64, f64::max);
    if worst > 0.0 {
        bail!("the multi-tool path allocated ({worst} per set)");
    }
    accuracy(quick)
}

/// Issue 29's accuracy runs (irtrack_sim::multibody): three tools and a loose LED for 60 s
/// (10 s in the quick CI run, which has a 10-minute limit for everything; a 60 s run takes
/// about a minute in release on a loaded machine) in the 90° pair and in the 4-camera rig,
/// against the truth. Prints the figures and every target missed; does not fail on a missed
/// target (a benchmark; the host tests assert what holds on the 10 s run).
fn accuracy(quick: bool) -> Result<()> {
    use irtrack_sim::multibody::{FPS, four_camera_rig, missed_targets, ninety_degree_pair, report, run};
    let seconds = if quick { 10.0 } else { 60.0 };
    println!();
    println!(
        "Several tools against the truth (issue 29): probe4, tri3, wing4 and a loose LED crossing, {seconds} s at {FPS} fps"
    );
    for (what, rig) in [
        ("90° pair", ninety_degree_pair()),
        ("4-camera rig", four_camera_rig()?),
    ] {
        let r = run(rig, (seconds * FPS) as u64, PoseConfig::default())?;
        print!("{}", report(what, &r));
        let missed = missed_targets(what, &r);
        if missed.is_empty() {
            println!("  all of issue 29's targets met");
        }
        for m in missed {
            println!("  target missed: {m}");
        }
    }
    Ok(())
}
