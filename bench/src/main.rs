//! `irtrack-bench`: the tracking hot path against OpenCV's equivalent pipeline and against
//! the memory floor, on the same frames, in one run (ratios, not timed asserts).
//!
//! Every case is timed twice: **hot** (one frame set, processed again and again, so it stays
//! in the CPU caches) and **cold** (a ring of at least 16 frame sets, together at least twice
//! the last-level cache, cycled through in order, like a V4L2 buffer queue that the camera
//! fills by DMA: every set is read from DRAM). The reference passes (a plain read of every
//! pixel, a sum of every pixel, OpenCV) run on the same ring.
//!
//! Usage:
//!   irtrack-bench [--quick]                 timing tables (synthetic VGA/720p, 8- and 10-bit,
//!                                            and simulator frames: 4-LED tool, lamp + reflection;
//!                                            then 1, 3 and 8 tools at once, VGA and 720p)
//!   irtrack-bench --run CASE --iterations N  run one case N times, print nothing else
//!                                            (for instruction counting under callgrind)
//!   irtrack-bench --idle SECONDS             sleep (baseline process for memory figures)
//! CASE is `<ours-full|ours-roi|windows-simd|windows-portable|opencv|sum|max>-<vga|720p>`
//! (`windows-*`: blob detection alone in the tracker's two windows with one kernel); `opencv` needs the default
//! feature `opencv`. Without it (`--no-default-features`) the OpenCV columns are left out
//! and the benchmark cross-builds for aarch64.

use std::hint::black_box;

use anyhow::{Context, Result, bail};
use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits, Kernel};
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::image::{GrayImage, Pixel, Roi};
use irtrack_core::params::{CameraParams, RigParams, ToolDefinition};
use irtrack_core::pipeline::{Measurement, TrackStatus, Tracker, TrackerConfig};
use irtrack_core::pose6d::{PoseConfig, PoseStatus, PoseTracker};
use irtrack_core::triangulate::{Ray, midpoint};
use irtrack_sim::{BitDepth, Orientation, RigPreset, Scenario, SimConfig, Trajectory};
use nalgebra::{Matrix3, UnitQuaternion, Vector3};

mod multi_tool;
#[cfg(feature = "opencv")]
mod opencv_pipeline;
mod timing;
#[cfg(feature = "opencv")]
use opencv_pipeline::OpenCv;

/// Counts heap allocations made through Rust's allocator on the benchmark thread (ours;
/// OpenCV's C++ heap is not seen, so only our pipeline's figure is reported).
#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

/// Threshold of the 8-bit synthetic frames; 10-bit frames use 4× (same scene, 4× the codes).
const THRESHOLD_DN: u8 = 30;

/// Fewest frame sets in the cold ring (a typical V4L2 queue depth and then some).
const MIN_RING_SETS: usize = 16;

/// Pixel types the benchmark runs: the tracker's entry point per type.
trait Px: Pixel {
    const BITS: &'static str;
    fn process<'t>(t: &'t mut Tracker, f: &[GrayImage<'_, Self>]) -> irtrack_core::Result<&'t Measurement>;
    fn detect(t: &mut Tracker, camera: usize, f: &GrayImage<'_, Self>) -> irtrack_core::Result<usize>;
    /// The simulator's renderer for this pixel type (8-bit or 10-bit codes).
    fn render_sim(sc: &mut Scenario, index: u64, camera: usize, out: &mut [Self]) -> Result<()>;
}

impl Px for u8 {
    const BITS: &'static str = "8-bit";
    fn process<'t>(t: &'t mut Tracker, f: &[GrayImage<'_, u8>]) -> irtrack_core::Result<&'t Measurement> {
        t.process_u8(f)
    }
    fn detect(t: &mut Tracker, camera: usize, f: &GrayImage<'_, u8>) -> irtrack_core::Result<usize> {
        t.detect_u8(camera, f)
    }
    fn render_sim(sc: &mut Scenario, index: u64, camera: usize, out: &mut [u8]) -> Result<()> {
        sc.render_u8(index, camera, out)?;
        Ok(())
    }
}

impl Px for u16 {
    const BITS: &'static str = "10-bit";
    fn process<'t>(t: &'t mut Tracker, f: &[GrayImage<'_, u16>]) -> irtrack_core::Result<&'t Measurement> {
        t.process_u16(f)
    }
    fn detect(t: &mut Tracker, camera: usize, f: &GrayImage<'_, u16>) -> irtrack_core::Result<usize> {
        t.detect_u16(camera, f)
    }
    fn render_sim(sc: &mut Scenario, index: u64, camera: usize, out: &mut [u16]) -> Result<()> {
        sc.render_u16(index, camera, out)?;
        Ok(())
    }
}

/// A stereo frame set.
type Set<P> = [Vec<P>; 2];

/// What the pipeline must find in a scene.
#[derive(Clone)]
enum Target {
    /// One LED: the single-marker tracker (ROI tracking applies).
    Point { truth_mm: Vector3<f64> },
    /// A rigid multi-LED tool: full-frame detection in both cameras, then the 6-DOF
    /// tracker, as irtrackd does with a tool configured (no tracking windows).
    Tool {
        tool: ToolDefinition,
        origin_truth_mm: Vector3<f64>,
    },
}

/// One benchmark scene: rig, a rendered stereo frame set and what it shows.
struct Scene<P> {
    name: String,
    rig: RigParams,
    frames: Set<P>,
    width_px: u32,
    height_px: u32,
    threshold_dn: u32,
    target: Target,
    /// OpenCV's single-component pipeline is comparable (one LED, no clutter, 8-bit).
    #[cfg_attr(not(feature = "opencv"), allow(dead_code))]
    opencv: bool,
}

impl<P> Scene<P> {
    fn set_bytes(&self) -> usize {
        2 * self.frames[0].len() * std::mem::size_of::<P>()
    }
}

fn camera(w: u32, h: u32, f_px: f64) -> CameraModel {
    CameraModel {
        intrinsics: Intrinsics {
            fx_px: f_px,
            fy_px: f_px,
            cx_px: w as f64 / 2.0,
            cy_px: h as f64 / 2.0,
        },
        distortion: Distortion {
            k1: -0.2,
            k2: 0.05,
            p1: 0.001,
            p2: -0.0005,
            k3: 0.0,
        },
        image_size: ImageSize {
            width_px: w,
            height_px: h,
        },
    }
}

/// Cheap deterministic noise (xorshift32), so rendering stays fast even under callgrind.
struct Noise(u32);

impl Noise {
    fn next(&mut self) -> u32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        self.0
    }
    /// Approximately normal, sd ≈ 2 DN (sum of four uniforms on ±3.46).
    fn dn(&mut self) -> f64 {
        let r = self.next();
        let u = |s: u32| ((r >> s) & 0xff) as f64 / 255.0 - 0.5;
        (u(0) + u(8) + u(16) + u(24)) * 6.93
    }
}

/// IR camera frame: background 10 ± 2 DN, a Gaussian LED (σ 1.5 px, peak 190 DN), in 8-bit
/// codes times `scale` (1 for 8-bit, 4 for 10-bit), clamped to `max_code`.
fn render<P: Pixel>(w: u32, h: u32, led_px: (f64, f64), seed: u32, scale: f64, max_code: f64) -> Vec<P> {
    let mut noise = Noise(seed | 1);
    let code = |v: f64| P::from_dn_saturating(v.round().clamp(0.0, max_code) as u32);
    let mut img: Vec<P> = (0..w * h).map(|_| code((10.0 + noise.dn()) * scale)).collect();
    let (cx, cy) = led_px;
    let (x0, y0) = ((cx - 8.0).max(0.0) as u32, (cy - 8.0).max(0.0) as u32);
    for y in y0..((cy + 9.0) as u32).min(h) {
        for x in x0..((cx + 9.0) as u32).min(w) {
            let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
            let i = (y * w + x) as usize;
            let v = img[i].dn() as f64 + 190.0 * scale * (-r2 / (2.0 * 1.5 * 1.5)).exp();
            img[i] = code(v);
        }
    }
    img
}

/// The synthetic scene: parallel rig, one LED at (40, −25, 800) mm. `scale` 1 = 8-bit
/// codes, 4 = 10-bit codes of the same scene.
fn synthetic<P: Px>(label: &str, w: u32, h: u32, f_px: f64, scale: u32) -> Result<Scene<P>> {
    let model = camera(w, h, f_px);
    let t1 = RigidTransform::from_parts(&Matrix3::identity(), &Vector3::new(-150.0, 0.0, 0.0));
    let rig = RigParams {
        rig_id: format!("bench-{label}"),
        created_unix_s: 0,
        cameras: vec![
            CameraParams {
                model,
                cam_from_cam0: RigidTransform::IDENTITY,
            },
            CameraParams {
                model,
                cam_from_cam0: t1,
            },
        ],
        world_from_cam0: None,
        tools: vec![],
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    };
    let truth_mm = Vector3::new(40.0, -25.0, 800.0);
    let max_code = (255 * scale).min(P::MAX_DN) as f64;
    let mut frames: Set<P> = [vec![], vec![]];
    for (c, f) in frames.iter_mut().enumerate() {
        let cam = &rig.cameras[c];
        let px = cam.model.project(&cam.cam_from_cam0.apply(&truth_mm))?;
        *f = render(
            w,
            h,
            (px.x, px.y),
            0x9E37_79B9 ^ (c as u32 + w),
            scale as f64,
            max_code,
        );
    }
    Ok(Scene {
        name: format!("{label} {}", P::BITS),
        rig,
        frames,
        width_px: w,
        height_px: h,
        threshold_dn: THRESHOLD_DN as u32 * scale,
        target: Target::Point { truth_mm },
        opencv: scale == 1 && std::mem::size_of::<P>() == 1,
    })
}

/// Simulator frames (irtrack-sim, 90° rig, VGA, sensor noise, lens distortion): the 4-LED
/// `probe4` tool turned and tilted at 1 m, and/or a ceiling lamp (large saturated spot) and a
/// specular streak in camera 1 next to the LED(s).
fn simulated<P: Px>(tool: bool, glare: bool) -> Result<Scene<P>> {
    let depth = if std::mem::size_of::<P>() == 1 {
        BitDepth::Eight
    } else {
        BitDepth::Ten
    };
    let mut cfg = SimConfig::preset(
        RigPreset::Convergent {
            distance_mm: 1000.0,
            angle_deg: 90.0,
        },
        1000.0,
        50.0,
    );
    cfg.trajectory = Trajectory::Circle {
        centre_mm: Vector3::new(-40.0, -30.0, 1000.0),
        radius_mm: 50.0,
        normal: Vector3::new(0.3, 1.0, 0.4),
        period_s: 6.0,
    };
    let tool_def = irtrack_sim::tools::builtin_tool("probe4").context("built-in tool probe4")?;
    if tool {
        cfg.set_tool(
            &tool_def.leds_mm,
            Orientation::Wobble {
                base: UnitQuaternion::from_euler_angles(0.2, -0.3, 0.4),
                amplitude_deg: Vector3::new(35.0, 30.0, 45.0),
                period_s: Vector3::new(4.0, 5.0, 6.5),
                phase_rad: Vector3::new(0.0, 1.0, 2.0),
            },
        );
    }
    if glare {
        cfg.add_glare();
    }
    cfg.bit_depth = depth;
    cfg.seed = 6;
    let mut sc = Scenario::new(cfg)?;
    let (w, h) = sc.image_size();
    let index = 30;
    let mut frames: Set<P> = [
        vec![P::default(); (w * h) as usize],
        vec![P::default(); (w * h) as usize],
    ];
    for (c, f) in frames.iter_mut().enumerate() {
        P::render_sim(&mut sc, index, c, f)?;
    }
    let truth = sc.truth(index);
    let target = if tool {
        Target::Tool {
            tool: tool_def,
            origin_truth_mm: truth.tool_position_mm,
        }
    } else {
        Target::Point {
            truth_mm: truth.markers[0].p_cam0_mm,
        }
    };
    let what = match (tool, glare) {
        (true, true) => "sim 4-LED tool + lamp + reflection",
        (true, false) => "sim 4-LED tool",
        (false, true) => "sim LED + lamp + reflection",
        (false, false) => "sim LED",
    };
    Ok(Scene {
        name: format!("{what}, VGA {}", P::BITS),
        rig: sc.rig().clone(),
        frames,
        width_px: w,
        height_px: h,
        // 30 DN of 255, in the frame's own codes.
        threshold_dn: (30 * depth.max_code() as u32).div_ceil(255),
        target,
        opencv: false,
    })
}

/// Frame sets in a buffer queue: `sets.len() == 1` is the hot case.
struct Ring<P> {
    sets: Vec<Set<P>>,
    next: usize,
}

impl<P: Clone> Ring<P> {
    fn hot(frames: &Set<P>) -> Self {
        Ring {
            sets: vec![frames.clone()],
            next: 0,
        }
    }

    /// At least [`MIN_RING_SETS`] copies of `frames` and at least `min_bytes` in all.
    fn cold(frames: &Set<P>, min_bytes: usize) -> Self {
        let set_bytes = 2 * frames[0].len() * std::mem::size_of::<P>();
        let n = MIN_RING_SETS.max(min_bytes.div_ceil(set_bytes.max(1)));
        Ring {
            sets: (0..n).map(|_| frames.clone()).collect(),
            next: 0,
        }
    }

    /// The next set in queue order.
    fn advance(&mut self) -> &Set<P> {
        let i = self.next;
        self.next = (i + 1) % self.sets.len();
        &self.sets[i]
    }
}

/// Size (bytes) and description of the last-level cache, from Linux's sysfs; 32 MiB (larger
/// than most) if it cannot be read.
fn last_level_cache() -> (usize, String) {
    let mut best: Option<(u32, usize)> = None;
    for idx in 0..16 {
        let dir = format!("/sys/devices/system/cpu/cpu0/cache/index{idx}");
        let read = |f: &str| std::fs::read_to_string(format!("{dir}/{f}")).map(|s| s.trim().to_string());
        let (Ok(level), Ok(kind), Ok(size)) = (read("level"), read("type"), read("size")) else {
            continue;
        };
        if kind == "Instruction" {
            continue;
        }
        let (Ok(level), Some(bytes)) = (level.parse::<u32>(), parse_size(&size)) else {
            continue;
        };
        if best.is_none_or(|(l, _)| level > l) {
            best = Some((level, bytes));
        }
    }
    match best {
        Some((level, bytes)) => (bytes, format!("L{level} {} KiB (sysfs)", bytes / 1024)),
        None => (
            32 << 20,
            "unknown (no /sys/devices/system/cpu/cpu0/cache), assumed 32 MiB".to_string(),
        ),
    }
}

/// "8192K", "32M", "512" → bytes.
fn parse_size(s: &str) -> Option<usize> {
    let (num, mult) = match s.chars().last()? {
        'K' => (&s[..s.len() - 1], 1 << 10),
        'M' => (&s[..s.len() - 1], 1 << 20),
        'G' => (&s[..s.len() - 1], 1 << 30),
        _ => (s, 1),
    };
    num.parse::<usize>().ok().map(|n| n * mult)
}

fn views<'a, P: Px>(s: &Scene<P>, f: &'a Set<P>) -> Result<[GrayImage<'a, P>; 2]> {
    let v = |c: usize| GrayImage::new(&f[c], s.width_px, s.height_px, s.width_px);
    Ok([v(0)?, v(1)?])
}

/// Our pipeline for a scene; `roi` = tracking windows on (after a warm-up frame).
struct Ours {
    tracker: Tracker,
    pose: Option<PoseTracker>,
}

impl Ours {
    fn new<P: Px>(s: &Scene<P>, roi: bool) -> Result<Self> {
        let cfg = TrackerConfig {
            threshold_dn: s.threshold_dn,
            roi_half_px: if roi {
                TrackerConfig::default().roi_half_px
            } else {
                0
            },
            ..TrackerConfig::default()
        };
        let pose = match &s.target {
            Target::Tool { tool, .. } => Some(PoseTracker::new(&s.rig, tool, PoseConfig::default())?),
            Target::Point { .. } => None,
        };
        let mut o = Ours {
            tracker: Tracker::new(&s.rig, cfg)?,
            pose,
        };
        // Warm-up (establishes the tracking windows) and the correctness check.
        let p = o.run(s, &s.frames)?;
        let truth = match &s.target {
            Target::Point { truth_mm } => truth_mm,
            Target::Tool { origin_truth_mm, .. } => origin_truth_mm,
        };
        if (p - truth).norm() > 2.0 {
            bail!("{}: our point {p:?} is far from the truth {truth:?}", s.name);
        }
        Ok(o)
    }

    fn run<P: Px>(&mut self, s: &Scene<P>, f: &Set<P>) -> Result<Vector3<f64>> {
        let v = views(s, f)?;
        match &mut self.pose {
            None => {
                let m = P::process(&mut self.tracker, &v)?;
                match (m.status, m.point_cam0_mm) {
                    (TrackStatus::Tracked, Some(p)) => Ok(p),
                    _ => bail!("{}: our pipeline did not track: {:?}", s.name, m.status),
                }
            }
            Some(pose) => {
                for (c, img) in v.iter().enumerate() {
                    P::detect(&mut self.tracker, c, img)?;
                }
                let lists = [self.tracker.blobs(0), self.tracker.blobs(1)];
                let p = pose.process(&lists)?;
                if p.status != PoseStatus::Tracked {
                    bail!("{}: no 6-DOF pose: {:?}", s.name, p.status);
                }
                Ok(Vector3::from(p.position_mm))
            }
        }
    }
}

/// The memory floor with arithmetic: one pass summing every pixel of both frames.
fn sum_pixels<P: Pixel>(f: &Set<P>) -> u64 {
    let mut total = 0u64;
    for frame in f {
        // u32 partial sums over chunks that cannot overflow (65536 × 65535 < 2^32) vectorise.
        for chunk in black_box(frame).chunks(65536) {
            total += chunk.iter().map(|v| v.dn()).sum::<u32>() as u64;
        }
    }
    total
}

/// A plain read of every pixel: the maximum of both frames (pixel-wide SIMD max, no
/// widening), i.e. the cheapest pass that must look at every byte.
fn max_pixels<P: Pixel>(f: &Set<P>) -> P {
    let mut m = P::default();
    for frame in f {
        m = m.max(black_box(frame).iter().fold(P::default(), |a, &v| a.max(v)));
    }
    m
}

/// CPU time of the calling thread (ns). The machine may be shared, so wall time would
/// charge one side of a comparison for time spent preempted; thread CPU time does not.
fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec; the clock id is a constant.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return 0;
    }
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Median thread-CPU time per iteration (ns) over `batches` batches of `iters` iterations.
fn time_ns(batches: usize, iters: usize, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    let mut per = Vec::with_capacity(batches);
    for _ in 0..batches {
        let t = thread_cpu_ns();
        for _ in 0..iters {
            f()?;
        }
        per.push((thread_cpu_ns() - t) as f64 / iters as f64);
    }
    per.sort_by(|a, b| a.total_cmp(b));
    Ok(per[per.len() / 2])
}

fn fmt_us(ns: f64) -> String {
    // Two decimals for the sub-10 µs figures (ROI, its parts), where .1 hides the changes.
    if ns < 10_000.0 {
        format!("{:.2} µs", ns / 1000.0)
    } else if ns < 1_000_000.0 {
        format!("{:.1} µs", ns / 1000.0)
    } else {
        format!("{:.0} µs", ns / 1000.0)
    }
}

/// A hot and a cold figure (ns).
#[derive(Clone, Copy, Default)]
struct HotCold {
    hot: f64,
    cold: f64,
}

impl HotCold {
    fn us(self) -> String {
        format!("{} / {}", fmt_us(self.hot), fmt_us(self.cold))
    }
    fn ratio(self, base: HotCold) -> String {
        format!("{:.2}x / {:.2}x", self.hot / base.hot, self.cold / base.cold)
    }
}

/// Timings of one scene (ns per stereo set).
struct Row {
    name: String,
    ring_sets: usize,
    full: HotCold,
    read: HotCold,
    sum: HotCold,
    roi: Option<HotCold>,
    opencv: Option<(HotCold, f64)>,
    allocs_per_set: f64,
    /// The ROI path split up (hot): blob detection in the two windows, and the geometry every
    /// tracked pair needs whatever the image work (2 undistortions + 1 triangulation).
    roi_split: Option<RoiSplit>,
}

/// Times `f` on the hot set and on the cold ring (`iters` per batch each).
fn hot_cold<P: Clone>(
    hot: &mut Ring<P>,
    cold: &mut Ring<P>,
    batches: usize,
    iters: usize,
    mut f: impl FnMut(&Set<P>) -> Result<()>,
) -> Result<HotCold> {
    Ok(HotCold {
        hot: time_ns(batches, iters, || f(hot.advance()))?,
        cold: time_ns(batches, iters, || f(cold.advance()))?,
    })
}

fn measure<P: Px>(s: &Scene<P>, batches: usize, iters: usize, llc_bytes: usize) -> Result<Row> {
    let mut hot = Ring::hot(&s.frames);
    let mut cold = Ring::cold(&s.frames, 2 * llc_bytes);
    let ring_sets = cold.sets.len();
    let mut full = Ours::new(s, false)?;
    let t_full = hot_cold(&mut hot, &mut cold, batches, iters, |f| {
        black_box(full.run(s, f)?);
        Ok(())
    })?;
    let roi_applies = matches!(s.target, Target::Point { .. });
    let mut roi = if roi_applies {
        Some(Ours::new(s, true)?)
    } else {
        None
    };
    let t_roi = match roi.as_mut() {
        Some(r) => {
            let t = hot_cold(&mut hot, &mut cold, batches, iters * 20, |f| {
                black_box(r.run(s, f)?);
                Ok(())
            })?;
            if !r.tracker.measurement().used_roi {
                bail!("{}: ROI case did not use the tracking windows", s.name);
            }
            Some(t)
        }
        None => None,
    };
    // Allocations, counted over plain loops (no timing harness inside the window).
    let a0 = irtrack_testkit::allocations();
    let mut runs = 0;
    for _ in 0..100 {
        black_box(full.run(s, &s.frames)?);
        runs += 1;
        if let Some(r) = roi.as_mut() {
            black_box(r.run(s, &s.frames)?);
            runs += 1;
        }
    }
    let allocs_per_set = (irtrack_testkit::allocations() - a0) as f64 / runs as f64;
    let t_sum = hot_cold(&mut hot, &mut cold, batches, iters * 4, |f| {
        black_box(sum_pixels(f));
        Ok(())
    })?;
    let t_read = hot_cold(&mut hot, &mut cold, batches, iters * 4, |f| {
        black_box(max_pixels(f));
        Ok(())
    })?;
    let roi_split = match roi.as_ref() {
        Some(r) => Some(roi_split(s, r, batches, iters)?),
        None => None,
    };
    Ok(Row {
        name: s.name.clone(),
        ring_sets,
        full: t_full,
        read: t_read,
        sum: t_sum,
        roi: t_roi,
        opencv: None,
        allocs_per_set,
        roi_split,
    })
}

/// The ROI path split up (hot, ns per set).
#[derive(Clone, Copy)]
struct RoiSplit {
    /// Blob detection in the two tracking windows, default kernel (SIMD where the build has
    /// it, see `irtrack_core::simd`) and portable kernel.
    windows: f64,
    windows_portable: f64,
    /// Two undistortions and a triangulation: what every tracked set needs.
    geometry: f64,
}

/// The tracker's two tracking windows, the centroids they are centred on (px) and its blob
/// settings, after a tracked set.
type Windows = ([Roi; 2], [(f64, f64); 2], BlobConfig);

fn tracking_windows<P: Px>(s: &Scene<P>, roi: &Ours) -> Result<Windows> {
    let m = *roi.tracker.measurement();
    let cfg = *roi.tracker.config();
    let mut centroids = [(0.0, 0.0); 2];
    for (c, xy) in centroids.iter_mut().enumerate() {
        let b = m.cameras[c].marker.context("ROI case: camera without marker")?;
        *xy = (b.x_px, b.y_px);
    }
    let windows = centroids.map(|(x, y)| Roi::around(x, y, cfg.roi_half_px, s.width_px, s.height_px));
    let blob_cfg = BlobConfig {
        threshold_dn: cfg.threshold_dn,
        ..BlobConfig::default()
    };
    Ok((windows, centroids, blob_cfg))
}

/// ROI breakdown with the public building blocks, on the tracker's own windows (hot).
fn roi_split<P: Px>(s: &Scene<P>, roi: &Ours, batches: usize, iters: usize) -> Result<RoiSplit> {
    let (windows, centroids, blob_cfg) = tracking_windows(s, roi)?;
    let mut det = BlobDetector::new(BlobLimits::for_frame(s.width_px, s.height_px))?;
    let v = views(s, &s.frames)?;
    let mut t_windows = [0.0; 2];
    for (t, kernel) in t_windows.iter_mut().zip([Kernel::Simd, Kernel::Portable]) {
        det.set_kernel(kernel);
        *t = time_ns(batches, iters * 40, || {
            for c in 0..2 {
                black_box(det.detect(&v[c], Some(windows[c]), &blob_cfg)?.len());
            }
            Ok(())
        })?;
    }
    let cams = [&s.rig.cameras[0], &s.rig.cameras[1]];
    let t_geometry = time_ns(batches, iters * 40, || {
        let r = [0, 1].map(|c| {
            let (x, y) = black_box(centroids[c]);
            Ray::from_pixel(&cams[c].model, &cams[c].cam_from_cam0, x, y)
        });
        black_box(midpoint(&r[0], &r[1])?);
        Ok(())
    })?;
    Ok(RoiSplit {
        windows: t_windows[0],
        windows_portable: t_windows[1],
        geometry: t_geometry,
    })
}

/// OpenCV on the same hot set and cold ring; also the distance between the two points.
#[cfg(feature = "opencv")]
fn measure_opencv(s: &Scene<u8>, batches: usize, iters: usize, llc_bytes: usize) -> Result<(HotCold, f64)> {
    let mut hot = Ring::hot(&s.frames);
    let mut cold = Ring::cold(&s.frames, 2 * llc_bytes);
    let mut ocv = OpenCv::new(&s.rig)?;
    let p_ours = Ours::new(s, false)?.run(s, &s.frames)?;
    let diff_mm = (p_ours - ocv.run(&s.name, &s.frames, s.width_px, s.height_px)?).norm();
    let t = hot_cold(&mut hot, &mut cold, batches, iters, |f| {
        black_box(ocv.run(&s.name, f, s.width_px, s.height_px)?);
        Ok(())
    })?;
    Ok((t, diff_mm))
}

/// Every scene of the table: the synthetic one (VGA and 720p, 8- and 10-bit) and the
/// simulator's realistic ones.
enum AnyScene {
    U8(Scene<u8>),
    U16(Scene<u16>),
}

fn scenes() -> Result<Vec<AnyScene>> {
    Ok(vec![
        AnyScene::U8(synthetic("VGA 640x480", 640, 480, 600.0, 1)?),
        AnyScene::U8(synthetic("HD 1280x720", 1280, 720, 900.0, 1)?),
        AnyScene::U16(synthetic("VGA 640x480", 640, 480, 600.0, 4)?),
        AnyScene::U16(synthetic("HD 1280x720", 1280, 720, 900.0, 4)?),
        AnyScene::U8(simulated(true, false)?),
        AnyScene::U8(simulated(false, true)?),
        AnyScene::U16(simulated(true, true)?),
    ])
}

fn table(quick: bool) -> Result<()> {
    let (batches, scale) = if quick { (3, 1) } else { (11, 8) };
    let (llc_bytes, llc_what) = last_level_cache();
    println!("irtrack-bench: per stereo frame set, thread CPU time, median of {batches} batches, one thread");
    println!(
        "hot = one frame set processed again and again (stays in cache); cold = a ring of ≥ {MIN_RING_SETS} frame sets, ≥ 2 × the last-level cache ({llc_what}), cycled in order like a V4L2 buffer queue"
    );
    println!();
    let mut rows = Vec::new();
    for sc in scenes()? {
        let pixels = match &sc {
            AnyScene::U8(s) => s.frames[0].len(),
            AnyScene::U16(s) => s.frames[0].len(),
        };
        let iters = scale * if pixels > 640 * 480 { 10 } else { 25 };
        let row = match &sc {
            AnyScene::U8(s) => {
                #[allow(unused_mut)]
                let mut r = measure(s, batches, iters, llc_bytes)?;
                #[cfg(feature = "opencv")]
                if s.opencv {
                    r.opencv = Some(measure_opencv(s, batches, iters, llc_bytes)?);
                }
                (r, s.set_bytes())
            }
            AnyScene::U16(s) => (measure(s, batches, iters, llc_bytes)?, s.set_bytes()),
        };
        rows.push(row);
    }

    println!(
        "| frames | cold ring | ours full | read pass | ours/read | sum pass | ours/sum | OpenCV | OpenCV/ours | ours ROI | ROI/full | allocs/set |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (r, set_bytes) in &rows {
        let (ocv, ocv_ratio) = match r.opencv {
            Some((t, _)) => (
                t.us(),
                format!("{:.0}x / {:.0}x", t.hot / r.full.hot, t.cold / r.full.cold),
            ),
            None => ("–".to_string(), "–".to_string()),
        };
        let (roi, roi_pct) = match r.roi {
            Some(t) => (
                t.us(),
                format!(
                    "{:.2} % / {:.2} %",
                    100.0 * t.hot / r.full.hot,
                    100.0 * t.cold / r.full.cold
                ),
            ),
            None => ("– (6-DOF: full frames)".to_string(), "–".to_string()),
        };
        println!(
            "| {} | {} × {:.2} MB | {} | {} | {} | {} | {} | {ocv} | {ocv_ratio} | {roi} | {roi_pct} | {} |",
            r.name,
            r.ring_sets,
            *set_bytes as f64 / 1e6,
            r.full.us(),
            r.read.us(),
            r.full.ratio(r.read),
            r.sum.us(),
            r.full.ratio(r.sum),
            r.allocs_per_set,
        );
    }
    println!();
    println!("Each cell: hot / cold.");
    #[cfg(feature = "opencv")]
    {
        println!("ours−OpenCV: distance between the two pipelines' 3-D points on the same frames:");
        for (r, _) in &rows {
            if let Some((_, d)) = r.opencv {
                println!("  {}: {d:.4} mm", r.name);
            }
        }
    }
    println!();
    println!("ROI tracking split up (hot, same windows, public building blocks):");
    println!();
    println!(
        "| frames | ours ROI | blob detection in 2 windows ({}) | same, portable kernel | undistort ×2 + triangulate (floor) | rest | floor/full |",
        irtrack_core::simd::NAME
    );
    println!("|---|---|---|---|---|---|---|");
    for (r, _) in &rows {
        let (Some(roi), Some(split)) = (r.roi, r.roi_split) else {
            continue;
        };
        println!(
            "| {} | {} | {} | {} | {} | {} | {:.2} % |",
            r.name,
            fmt_us(roi.hot),
            fmt_us(split.windows),
            fmt_us(split.windows_portable),
            fmt_us(split.geometry),
            fmt_us((roi.hot - split.windows - split.geometry).max(0.0)),
            100.0 * split.geometry / r.full.hot,
        );
    }
    println!();
    #[cfg(feature = "opencv")]
    println!(
        "Goals: ours full ≤ 1.5x a cold read (ours/read, cold), OpenCV/ours ≥ 20x, ROI/full ≤ 5 % (VGA) and ≤ 4 % (720p), 0 allocations per set."
    );
    #[cfg(not(feature = "opencv"))]
    println!(
        "Goals: ours full ≤ 1.5x a cold read (ours/read, cold), ROI/full ≤ 5 % (VGA) and ≤ 4 % (720p), 0 allocations per set (built without OpenCV)."
    );
    println!("floor/full: the per-set geometry any tracked frame needs, as a share of the full frame.");
    multi_tool::table(quick)?;
    println!();
    timing::table(quick)
}

/// Runs one case `iters` times after setup and one warm-up, printing nothing but a checksum
/// (so the work cannot be optimised away); `cargo xtask bench` runs this under callgrind
/// with two iteration counts and reports the difference per iteration.
fn run_case(case: &str, iters: usize) -> Result<()> {
    let (what, res) = case.rsplit_once('-').context("case must be <what>-<vga|720p>")?;
    let s: Scene<u8> = match res {
        "vga" => synthetic("VGA", 640, 480, 600.0, 1)?,
        "720p" => synthetic("720p", 1280, 720, 900.0, 1)?,
        other => bail!("unknown resolution `{other}` (vga or 720p)"),
    };
    let mut check = 0.0f64;
    match what {
        "ours-full" | "ours-roi" => {
            let mut o = Ours::new(&s, what == "ours-roi")?;
            for _ in 0..iters {
                check += o.run(&s, &s.frames)?.z;
            }
        }
        #[cfg(feature = "opencv")]
        "opencv" => {
            let mut o = OpenCv::new(&s.rig)?;
            o.run(&s.name, &s.frames, s.width_px, s.height_px)?;
            for _ in 0..iters {
                check += o.run(&s.name, &s.frames, s.width_px, s.height_px)?.z;
            }
        }
        "windows-simd" | "windows-portable" => {
            // Blob detection alone in the tracker's two windows, one kernel.
            let o = Ours::new(&s, true)?;
            let (windows, _, blob_cfg) = tracking_windows(&s, &o)?;
            let mut det = BlobDetector::new(BlobLimits::for_frame(s.width_px, s.height_px))?;
            det.set_kernel(if what == "windows-simd" {
                Kernel::Simd
            } else {
                Kernel::Portable
            });
            let v = views(&s, &s.frames)?;
            for _ in 0..iters {
                for c in 0..2 {
                    check += det.detect(&v[c], Some(windows[c]), &blob_cfg)?.len() as f64;
                }
            }
        }
        "sum" => {
            for _ in 0..iters {
                check += sum_pixels(&s.frames) as f64;
            }
        }
        "max" => {
            for _ in 0..iters {
                check += max_pixels(&s.frames) as f64;
            }
        }
        other => bail!(
            "unknown case `{other}` (ours-full, ours-roi, windows-simd, windows-portable, opencv, sum, max)"
        ),
    }
    println!("checksum {check}");
    Ok(())
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let mut quick = false;
    let mut case = None;
    let mut iters = 10usize;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        match a.as_str() {
            "--quick" => quick = true,
            "--multi-tool" => return multi_tool::table(quick),
            "--timing" => return timing::table(quick),
            "--run" => case = Some(it.next().context("--run needs a case")?.clone()),
            "--iterations" => iters = it.next().context("--iterations needs a number")?.parse()?,
            "--idle" => {
                // Baseline process for memory figures (`cargo xtask bench --aarch64`): the
                // runtime alone, doing nothing.
                let s: u64 = it.next().context("--idle needs seconds")?.parse()?;
                std::thread::sleep(std::time::Duration::from_secs(s));
                return Ok(());
            }
            "-h" | "--help" => {
                println!(
                    "usage: irtrack-bench [--quick] [--multi-tool (only the several-tools tables)] [--timing (only the time-true table)] | --run <ours-full|ours-roi|windows-simd|windows-portable|opencv|sum|max>-<vga|720p> --iterations N | --idle SECONDS"
                );
                return Ok(());
            }
            other => bail!("unknown argument `{other}`"),
        }
    }
    match case {
        Some(c) => run_case(&c, iters),
        None => table(quick),
    }
}
