//! `host-tools simulate`: renders a simulated scenario to a directory (layout in
//! docs/simulator.md): frames per camera as PGM, the rig as OpenCV YAML and as a parameter
//! blob, ground truth and per-frame timestamps. With `--tool`, a rigid multi-LED tool turning
//! about its own axes; its definition is added to the parameters (`RigParams.tools`) and the
//! truth gives the tool's pose (origin and quaternion).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use irtrack_core::params::ToolDefinition;
use irtrack_core::pgm;
use irtrack_sim::rig::{TABLE_I_BASELINE_MM, TABLE_I_FOCAL_PX};
use irtrack_sim::{
    BitDepth, MarkerSpec, RigPreset, Scenario, SimCameraTiming, SimConfig, TimingLists, Trajectory,
};
use nalgebra::Vector3;

/// Preset rig.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum RigArg {
    /// Two cameras side by side, optical axes parallel (`--baseline-mm` apart).
    Parallel,
    /// Two cameras whose optical axes cross at `--distance-mm` with `--angle-deg` between them.
    Convergent,
}

/// Arguments.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Output directory (created; existing frames are overwritten).
    #[arg(long)]
    pub out: PathBuf,
    /// Rig preset.
    #[arg(long, value_enum, default_value = "convergent")]
    pub rig: RigArg,
    /// Working distance (mm): where the convergent rig's axes cross and the path's centre.
    #[arg(long, default_value_t = 800.0)]
    pub distance_mm: f64,
    /// Parallel rig baseline (mm).
    #[arg(long, default_value_t = TABLE_I_BASELINE_MM)]
    pub baseline_mm: f64,
    /// Angle between the convergent rig's optical axes (deg).
    #[arg(long, default_value_t = 90.0)]
    pub angle_deg: f64,
    /// Focal length (px) of the VGA cameras.
    #[arg(long, default_value_t = TABLE_I_FOCAL_PX)]
    pub focal_px: f64,
    /// circle | line | figure8 | csv:FILE (t_s,x_mm,y_mm,z_mm in camera 0's frame).
    #[arg(long, default_value = "circle")]
    pub trajectory: String,
    /// Size of the parametric path (circle radius, line half-length, figure-eight half-width).
    #[arg(long, default_value_t = 100.0)]
    pub radius_mm: f64,
    /// Period of the parametric path (s).
    #[arg(long, default_value_t = 2.0)]
    pub period_s: f64,
    /// Number of frames.
    #[arg(long, default_value_t = 240)]
    pub frames: u64,
    /// Frame rate.
    #[arg(long, default_value_t = 120.0)]
    pub fps: f64,
    /// Add a ceiling lamp and a reflection seen by camera 1 only.
    #[arg(long)]
    pub glare: bool,
    /// Bit depth of the written frames: 8 (maxval 255) or 10 (16-bit PGM, maxval 1023).
    #[arg(long, default_value_t = 8)]
    pub bits: u8,
    /// Noise and drop seed.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Probability that a camera drops a frame.
    #[arg(long, default_value_t = 0.0)]
    pub drop_rate: f64,
    /// Sub-exposures for motion blur (1 = off).
    #[arg(long, default_value_t = 1)]
    pub motion_blur: u32,
    /// Exposure time (ms).
    #[arg(long, default_value_t = 2.0)]
    pub exposure_ms: f64,
    /// Number of markers (extra ones ride 30 mm apart on a rigid tool).
    #[arg(long, default_value_t = 1)]
    pub markers: usize,
    /// Peak of the marker's spot as a fraction of full scale at the working distance
    /// (auto-exposure stand-in); brightness still falls with distance along the path.
    #[arg(long, default_value_t = 0.6)]
    pub peak_fraction: f64,
    /// Render a rigid multi-LED tool instead of `--markers`: `probe4` (4 LEDs, asymmetric,
    /// non-planar, docs/six-dof.md) or `tri3` (3 LEDs, scalene triangle). The trajectory moves
    /// the tool's origin (LED 0).
    #[arg(long)]
    pub tool: Option<String>,
    /// With `--tool`: amplitude of the tool's turning about each of its axes (deg); 0 = the
    /// tool keeps one orientation (e.g. to measure its layout with `measure-tool`).
    #[arg(long, default_value_t = 30.0)]
    pub tool_rotation_deg: f64,
    /// Camera timing preset: `sync` (default: every camera exposes at the frame instant with
    /// a global shutter and stamps it exactly) or `free-running` (phases spread evenly over the
    /// whole frame period, clock rates drawn in ±50 ppm from the seed, 200 µs timestamp
    /// jitter). The per-camera options below override the preset's values.
    #[arg(long, default_value = "sync")]
    pub timing: String,
    /// Per-camera phase (ms): the middle of row 0's exposure against the nominal frame grid,
    /// e.g. `0,3.1,-2.4`; one value applies to every camera.
    #[arg(long, allow_hyphen_values = true)]
    pub phase_ms: Option<String>,
    /// Per-camera clock rate error (ppm): the camera's period is nominal × (1 + ppm·1e-6).
    #[arg(long, allow_hyphen_values = true)]
    pub ppm: Option<String>,
    /// Per-camera timestamp jitter, standard deviation (µs, clipped at ±3σ); only the reported
    /// timestamps move, not the exposures.
    #[arg(long)]
    pub ts_jitter_us: Option<String>,
    /// Per-camera exposure time (µs): motion blur as the average of at least 8 sub-samples
    /// across it (overrides `--exposure-ms`/`--motion-blur` for those cameras).
    #[arg(long)]
    pub exposure_us: Option<String>,
    /// Per-camera rolling-shutter line time (µs per row); 0 = global shutter.
    #[arg(long)]
    pub line_time_us: Option<String>,
    /// Per-camera timestamp offset (µs): reported timestamp minus the middle of row 0's
    /// exposure (e.g. a camera stamping the end of readout has a positive offset).
    #[arg(long, allow_hyphen_values = true)]
    pub ts_offset_us: Option<String>,
    /// Lens without distortion.
    #[arg(long)]
    pub no_distortion: bool,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

/// A built-in tool definition by name (irtrack-sim's list).
pub fn builtin_tool(name: &str) -> anyhow::Result<ToolDefinition> {
    irtrack_sim::tools::builtin_tool(name).ok_or_else(|| {
        anyhow::anyhow!(
            "unknown tool `{name}`: use {}",
            irtrack_sim::tools::BUILTIN_TOOLS.join(" or ")
        )
    })
}

/// The tool the arguments ask for, if any.
pub fn tool_from_args(a: &Args) -> anyhow::Result<Option<ToolDefinition>> {
    a.tool.as_deref().map(builtin_tool).transpose()
}

/// Parses `1.5` or `0,3.1,-2.4` into values scaled by `scale` (e.g. ms → ns).
fn parse_list(option: &str, text: Option<&str>, scale: f64) -> anyhow::Result<Vec<f64>> {
    let Some(text) = text else {
        return Ok(Vec::new());
    };
    text.split(',')
        .map(|v| {
            let x: f64 = v
                .trim()
                .parse()
                .with_context(|| format!("--{option} {text}: `{v}` is not a number"))?;
            if !x.is_finite() {
                bail!("--{option} {text}: `{v}` is not finite");
            }
            Ok(x * scale)
        })
        .collect()
}

/// Per-camera timing from `--timing` and the per-camera options, for `cameras` cameras.
pub fn timing_from_args(a: &Args, cameras: usize, fps: f64, seed: u64) -> anyhow::Result<Vec<SimCameraTiming>> {
    let lists = TimingLists {
        phase_ns: parse_list("phase-ms", a.phase_ms.as_deref(), 1e6)?,
        rate_ppm: parse_list("ppm", a.ppm.as_deref(), 1.0)?,
        ts_jitter_ns: parse_list("ts-jitter-us", a.ts_jitter_us.as_deref(), 1e3)?,
        exposure_ns: parse_list("exposure-us", a.exposure_us.as_deref(), 1e3)?,
        line_time_ns: parse_list("line-time-us", a.line_time_us.as_deref(), 1e3)?,
        ts_offset_ns: parse_list("ts-offset-us", a.ts_offset_us.as_deref(), 1e3)?,
    };
    let lists = match a.timing.as_str() {
        "sync" => lists,
        "free-running" => lists.free_running(cameras, fps, seed),
        other => bail!("--timing {other}: use sync or free-running"),
    };
    let v = lists.build(cameras).context("camera timing")?;
    // All zero is the synchronous default: keep the configuration (and scenario.txt) as before.
    Ok(if v.iter().all(SimCameraTiming::is_synchronous) {
        Vec::new()
    } else {
        v
    })
}

/// Builds the simulator configuration the arguments describe.
pub fn config_from_args(a: &Args) -> anyhow::Result<SimConfig> {
    let rig = match a.rig {
        RigArg::Parallel => RigPreset::Parallel {
            baseline_mm: a.baseline_mm,
        },
        RigArg::Convergent => RigPreset::Convergent {
            distance_mm: a.distance_mm,
            angle_deg: a.angle_deg,
        },
    };
    let mut cfg = SimConfig::preset(rig, a.distance_mm, a.radius_mm);
    cfg.camera.focal_px = a.focal_px;
    if a.no_distortion {
        cfg.camera.distortion = irtrack_core::camera::Distortion::NONE;
    }
    let centre = cfg.rig.workspace_centre_mm(a.distance_mm);
    let r = a.radius_mm;
    let normal = Vector3::new(0.3, 1.0, 0.4);
    cfg.trajectory = match a.trajectory.as_str() {
        "circle" => Trajectory::Circle {
            centre_mm: centre,
            radius_mm: r,
            normal,
            period_s: a.period_s,
        },
        "figure8" => Trajectory::Figure8 {
            centre_mm: centre,
            size_mm: r,
            normal,
            period_s: a.period_s,
        },
        "line" => Trajectory::Line {
            from_mm: centre - Vector3::new(r, 0.4 * r, 0.6 * r),
            to_mm: centre + Vector3::new(r, 0.4 * r, 0.6 * r),
            period_s: a.period_s,
        },
        other => match other.strip_prefix("csv:") {
            Some(file) => {
                let text =
                    std::fs::read_to_string(file).with_context(|| format!("reading trajectory {file}"))?;
                Trajectory::from_csv(&text).with_context(|| format!("trajectory {file}"))?
            }
            None => bail!("unknown trajectory `{other}`: use circle, line, figure8 or csv:FILE"),
        },
    };
    cfg.fps = a.fps;
    cfg.seed = a.seed;
    cfg.drop_rate = a.drop_rate;
    cfg.motion_blur_steps = a.motion_blur;
    cfg.sensor.exposure_s = a.exposure_ms * 1e-3;
    cfg.bit_depth = match a.bits {
        8 => BitDepth::Eight,
        10 => BitDepth::Ten,
        other => bail!("--bits {other}: use 8 or 10"),
    };
    if a.markers == 0 || a.markers > irtrack_sim::scenario::MAX_MARKERS {
        bail!("--markers must be 1..={}", irtrack_sim::scenario::MAX_MARKERS);
    }
    let base = MarkerSpec::default();
    let flux = base.flux_for_peak(a.peak_fraction, cfg.sensor.full_well_e, a.distance_mm, a.focal_px);
    cfg.markers = (0..a.markers)
        .map(|i| MarkerSpec {
            offset_mm: Vector3::new(30.0 * (i % 2) as f64, -30.0 * (i / 2) as f64, 0.0),
            flux_e_at_1m: flux,
            ..base
        })
        .collect();
    if let Some(tool) = tool_from_args(a)? {
        if a.markers != 1 {
            bail!("--tool and --markers exclude each other");
        }
        if !(a.tool_rotation_deg.is_finite() && (0.0..=90.0).contains(&a.tool_rotation_deg)) {
            bail!("--tool-rotation-deg {} must be in 0..=90", a.tool_rotation_deg);
        }
        cfg.set_tool(
            &tool.leds_mm,
            irtrack_sim::tools::turning(a.tool_rotation_deg, a.period_s),
        );
    }
    if a.glare {
        cfg.add_glare();
    }
    let cameras = irtrack_sim::rig::build_rig(&cfg.rig, &cfg.camera)
        .context("rig")?
        .cameras
        .len();
    cfg.timing = timing_from_args(a, cameras, cfg.fps, cfg.seed)?;
    Ok(cfg)
}

/// What was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteSummary {
    /// Frames rendered (each one image per camera).
    pub frames: u64,
    /// Images written as PGM files.
    pub images: u64,
    /// Images the simulated camera dropped (not written; marked in timestamps.csv).
    pub dropped: u64,
}

/// Renders `frames` frames of `sc` into `dir` with the layout of docs/simulator.md.
pub fn write_scenario(
    sc: &mut Scenario,
    dir: &Path,
    frames: u64,
    tool: Option<&ToolDefinition>,
    show_progress: bool,
) -> anyhow::Result<WriteSummary> {
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let n_cam = sc.camera_count();
    for c in 0..n_cam {
        let d = dir.join(format!("cam{c}"));
        std::fs::create_dir_all(&d).with_context(|| format!("creating {}", d.display()))?;
        // Stale frames from an earlier, longer run would be read as part of this one.
        for e in std::fs::read_dir(&d)? {
            let p = e?.path();
            if p.extension().is_some_and(|x| x == "pgm") {
                std::fs::remove_file(&p).with_context(|| format!("removing stale {}", p.display()))?;
            }
        }
    }
    let mut rig = sc.rig().clone();
    rig.tools.extend(tool.cloned());
    rig.validate().context("tool definition")?;
    crate::opencv_yaml::write_rig_yaml(&dir.join("rig.yaml"), &rig)?;
    std::fs::write(dir.join("rig.irp"), rig.to_blob()?).context("writing rig.irp")?;
    std::fs::write(dir.join("scenario.txt"), format!("{:#?}\n", sc.config()))
        .context("writing scenario.txt")?;

    let (w, h) = sc.image_size();
    let depth = sc.config().bit_depth;
    let mut f8 = vec![0u8; (w * h) as usize];
    let mut f16 = vec![0u16; (w * h) as usize];
    // With a tool, the truth is the tool's pose (origin = the trajectory point).
    let mut truth = String::from(if tool.is_some() {
        "frame,t_s,x_mm,y_mm,z_mm,visible,qw,qx,qy,qz\n"
    } else {
        "frame,t_s,x_mm,y_mm,z_mm,visible\n"
    });
    let multi = sc.config().markers.len() > 1;
    let mut markers = String::from("frame,marker,x_mm,y_mm,z_mm,visible\n");
    let mut stamps = String::from("frame,camera,timestamp_ns,dropped\n");
    let bar = if show_progress {
        indicatif::ProgressBar::new(frames)
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut sum = WriteSummary {
        frames,
        images: 0,
        dropped: 0,
    };
    for index in 0..frames {
        let t = sc.truth(index);
        for (m, mt) in t.markers().iter().enumerate() {
            let p = mt.p_cam0_mm;
            let vis = mt.visible_in_all(n_cam) as u8;
            if m == 0 && tool.is_some() {
                let o = t.tool_position_mm;
                let all = t.markers().iter().all(|m| m.visible_in_all(n_cam)) as u8;
                let q = t.tool_quaternion_wxyz();
                let _ = writeln!(
                    truth,
                    "{index},{:.9},{:.6},{:.6},{:.6},{all},{:.9},{:.9},{:.9},{:.9}",
                    t.t_s, o.x, o.y, o.z, q[0], q[1], q[2], q[3]
                );
            } else if m == 0 {
                let _ = writeln!(
                    truth,
                    "{index},{:.9},{:.6},{:.6},{:.6},{vis}",
                    t.t_s, p.x, p.y, p.z
                );
            }
            if multi {
                let _ = writeln!(markers, "{index},{m},{:.6},{:.6},{:.6},{vis}", p.x, p.y, p.z);
            }
        }
        for c in 0..n_cam {
            let path = dir.join(format!("cam{c}/{index:06}.pgm"));
            // An exposure stamped before the scenario's start (a negative phase or offset in
            // slot 0) is before the recording began: written as dropped.
            if sc.frame_time(index, c).reported_ns < 0 {
                let _ = writeln!(stamps, "{index},{c},0,1");
                sum.dropped += 1;
                continue;
            }
            let info = match depth {
                BitDepth::Eight => sc.render_u8(index, c, &mut f8)?,
                BitDepth::Ten => sc.render_u16(index, c, &mut f16)?,
            };
            let _ = writeln!(stamps, "{index},{c},{},{}", info.timestamp_ns, info.dropped as u8);
            if info.dropped {
                sum.dropped += 1;
                continue;
            }
            let file = match depth {
                BitDepth::Eight => pgm::encode_u8(w, h, &f8)?,
                BitDepth::Ten => pgm::encode_u16(w, h, 10, &f16)?,
            };
            std::fs::write(&path, file).with_context(|| format!("writing {}", path.display()))?;
            sum.images += 1;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    std::fs::write(dir.join("truth.csv"), truth).context("writing truth.csv")?;
    std::fs::write(dir.join("timestamps.csv"), stamps).context("writing timestamps.csv")?;
    if multi {
        std::fs::write(dir.join("markers.csv"), markers).context("writing markers.csv")?;
    }
    write_timing_files(sc, dir, frames)?;
    Ok(sum)
}

/// Name of the per-camera timing constants file.
pub const CAMERA_TIMING_FILE: &str = "camera_timing.csv";
/// Name of the densely sampled truth (timed scenarios only).
pub const TRUTH_DENSE_FILE: &str = "truth_dense.csv";
/// Spacing of `truth_dense.csv` (ns): 0.1 ms, where linear interpolation of a hand's motion
/// is off by nanometres.
pub const TRUTH_DENSE_STEP_NS: i64 = 100_000;

/// `camera_timing.csv` (every scenario): per camera the constants a tracker is given
/// (irtrack-core's `CameraTiming`: shutter, line time, exposure, `offset_ns` = middle of row 0's
/// exposure − timestamp) and the simulated clock's own phase, rate error and jitter. A timed
/// scenario also gets `truth_dense.csv` (`t_ns,x_mm,y_mm,z_mm`, marker 0 every 0.1 ms on the
/// timestamps' clock, from one period before frame 0 to one after the last), so that truth
/// can be evaluated at any instant.
fn write_timing_files(sc: &Scenario, dir: &Path, frames: u64) -> anyhow::Result<()> {
    let mut csv =
        String::from("camera,shutter,line_time_ns,exposure_ns,offset_ns,phase_ns,rate_ppm,ts_jitter_ns\n");
    let mut timed = false;
    for c in 0..sc.camera_count() {
        let t = sc.camera_timing(c);
        timed |= !t.is_synchronous();
        let k = t.core_timing();
        let _ = writeln!(
            csv,
            "{c},{},{},{},{},{:.1},{:.3},{:.1}",
            k.shutter.as_str(),
            k.line_time_ns,
            k.exposure_ns,
            k.offset_ns,
            t.phase_ns,
            t.rate_ppm,
            t.ts_jitter_ns
        );
    }
    std::fs::write(dir.join(CAMERA_TIMING_FILE), csv).context("writing camera_timing.csv")?;
    let dense = dir.join(TRUTH_DENSE_FILE);
    if !timed {
        // A synchronous scenario's truth.csv rows are at the frame instants already; a dense
        // file from an earlier timed run would describe another scene.
        if dense.is_file() {
            std::fs::remove_file(&dense).with_context(|| format!("removing stale {}", dense.display()))?;
        }
        return Ok(());
    }
    let period_ns = 1e9 / sc.config().fps;
    let first = (-period_ns / TRUTH_DENSE_STEP_NS as f64).floor() as i64;
    let last = ((frames as f64 + 1.0) * period_ns / TRUTH_DENSE_STEP_NS as f64).ceil() as i64;
    let mut out = String::with_capacity(((last - first + 1) * 40) as usize);
    out.push_str("t_ns,x_mm,y_mm,z_mm\n");
    for i in first..=last {
        let t_ns = i * TRUTH_DENSE_STEP_NS;
        let p = sc.truth_at(t_ns as f64).markers()[0].p_cam0_mm;
        let _ = writeln!(out, "{t_ns},{:.6},{:.6},{:.6}", p.x, p.y, p.z);
    }
    std::fs::write(&dense, out).context("writing truth_dense.csv")?;
    Ok(())
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    let cfg = config_from_args(&args)?;
    let tool = tool_from_args(&args)?;
    let mut sc = Scenario::new(cfg)?;
    let s = write_scenario(&mut sc, &args.out, args.frames, tool.as_ref(), !args.quiet)?;
    println!(
        "wrote {} frames x {} cameras ({} images, {} dropped) to {}",
        s.frames,
        sc.camera_count(),
        s.images,
        s.dropped,
        args.out.display()
    );
    Ok(())
}
