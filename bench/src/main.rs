//! `irtrack-bench`: the tracking hot path against OpenCV's equivalent pipeline and against
//! the memory floor, on the same rendered frames, in one run (ratios, not timed asserts).
//!
//! Usage:
//!   irtrack-bench [--quick]                 timing table (VGA and 1280x720 stereo pairs)
//!   irtrack-bench --run CASE --iterations N  run one case N times, print nothing else
//!                                            (for instruction counting under callgrind)
//!   irtrack-bench --idle SECONDS             sleep (baseline process for memory figures)
//! CASE is `<ours-full|ours-roi|opencv|sum|max>-<vga|720p>`; `opencv` needs the default
//! feature `opencv`. Without it (`--no-default-features`) the OpenCV columns are left out
//! and the benchmark cross-builds for aarch64.

use std::hint::black_box;

use anyhow::{Context, Result, bail};
use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits};
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
use irtrack_core::image::{GrayImage, Roi};
use irtrack_core::params::{CameraParams, RigParams};
use irtrack_core::pipeline::{TrackStatus, Tracker, TrackerConfig};
use irtrack_core::triangulate::{Ray, midpoint};
use nalgebra::{Matrix3, Vector3};

#[cfg(feature = "opencv")]
mod opencv_pipeline;
#[cfg(feature = "opencv")]
use opencv_pipeline::OpenCv;

/// Counts heap allocations made through Rust's allocator on the benchmark thread (ours;
/// OpenCV's C++ heap is not seen, so only our pipeline's figure is reported).
#[global_allocator]
static GLOBAL: irtrack_testkit::CountingAlloc = irtrack_testkit::CountingAlloc;

const THRESHOLD_DN: u8 = 30;

/// One benchmark resolution: rig and a rendered stereo frame pair.
struct Scene {
    name: &'static str,
    rig: RigParams,
    frames: [Vec<u8>; 2],
    width_px: u32,
    height_px: u32,
    truth_mm: Vector3<f64>,
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

/// IR camera frame: background 10 ± 2 DN, a Gaussian LED (σ 1.5 px, peak 190 DN).
fn render(w: u32, h: u32, led_px: (f64, f64), seed: u32) -> Vec<u8> {
    let mut noise = Noise(seed | 1);
    let mut img: Vec<u8> = (0..w * h)
        .map(|_| (10.0 + noise.dn()).round().clamp(0.0, 255.0) as u8)
        .collect();
    let (cx, cy) = led_px;
    let (x0, y0) = ((cx - 8.0).max(0.0) as u32, (cy - 8.0).max(0.0) as u32);
    for y in y0..((cy + 9.0) as u32).min(h) {
        for x in x0..((cx + 9.0) as u32).min(w) {
            let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
            let v = img[(y * w + x) as usize] as f64 + 190.0 * (-r2 / (2.0 * 1.5 * 1.5)).exp();
            img[(y * w + x) as usize] = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    img
}

fn scene(name: &'static str, w: u32, h: u32, f_px: f64) -> Result<Scene> {
    let model = camera(w, h, f_px);
    let t1 = RigidTransform::from_parts(&Matrix3::identity(), &Vector3::new(-150.0, 0.0, 0.0));
    let rig = RigParams {
        rig_id: format!("bench-{name}"),
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
    };
    let truth_mm = Vector3::new(40.0, -25.0, 800.0);
    let mut frames: [Vec<u8>; 2] = [vec![], vec![]];
    for (c, f) in frames.iter_mut().enumerate() {
        let cam = &rig.cameras[c];
        let px = cam.model.project(&cam.cam_from_cam0.apply(&truth_mm))?;
        *f = render(w, h, (px.x, px.y), 0x9E37_79B9 ^ (c as u32 + w));
    }
    Ok(Scene {
        name,
        rig,
        frames,
        width_px: w,
        height_px: h,
        truth_mm,
    })
}

fn views(s: &Scene) -> Result<[GrayImage<'_, u8>; 2]> {
    let v = |c: usize| GrayImage::new(&s.frames[c], s.width_px, s.height_px, s.width_px);
    Ok([v(0)?, v(1)?])
}

/// Our pipeline; `roi` = tracking windows on (after a warm-up frame) or full frame only.
struct Ours {
    tracker: Tracker,
}

impl Ours {
    fn new(s: &Scene, roi: bool) -> Result<Self> {
        let cfg = TrackerConfig {
            threshold_dn: THRESHOLD_DN as u32,
            roi_half_px: if roi {
                TrackerConfig::default().roi_half_px
            } else {
                0
            },
            ..TrackerConfig::default()
        };
        let mut o = Ours {
            tracker: Tracker::new(&s.rig, cfg)?,
        };
        // Warm-up: establishes the tracking windows.
        let p = o.run(s)?;
        if (p - s.truth_mm).norm() > 2.0 {
            bail!(
                "{}: our point {p:?} is far from the truth {:?}",
                s.name,
                s.truth_mm
            );
        }
        Ok(o)
    }

    fn run(&mut self, s: &Scene) -> Result<Vector3<f64>> {
        let m = self.tracker.process_u8(&views(s)?)?;
        match (m.status, m.point_cam0_mm) {
            (TrackStatus::Tracked, Some(p)) => Ok(p),
            _ => bail!("{}: our pipeline did not track: {:?}", s.name, m.status),
        }
    }
}

/// The memory floor: one pass summing every pixel of both frames.
fn sum_pixels(s: &Scene) -> u64 {
    let mut total = 0u64;
    for f in &s.frames {
        // u32 partial sums over chunks that cannot overflow (65536 × 255 < 2^32) vectorise.
        for chunk in black_box(f).chunks(65536) {
            total += chunk.iter().map(|&v| v as u32).sum::<u32>() as u64;
        }
    }
    total
}

/// The cheapest full read: the maximum of every pixel of both frames (byte-wide SIMD max,
/// no widening), i.e. what a threshold test must at least cost.
fn max_pixels(s: &Scene) -> u8 {
    let mut m = 0u8;
    for f in &s.frames {
        m = m.max(black_box(f).iter().fold(0u8, |a, &v| a.max(v)));
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
    } else {
        format!("{:.1} µs", ns / 1000.0)
    }
}

fn scenes() -> Result<Vec<Scene>> {
    Ok(vec![
        scene("VGA 640x480", 640, 480, 600.0)?,
        scene("HD 1280x720", 1280, 720, 900.0)?,
    ])
}

/// Timings of one scene (ns per stereo pair).
struct Row {
    full: f64,
    roi: f64,
    sum: f64,
    max: f64,
    allocs_per_pair: f64,
    /// The ROI path split up: blob detection in the two windows, and the geometry every
    /// tracked pair needs whatever the image work (2 undistortions + 1 triangulation).
    roi_windows: f64,
    geometry: f64,
}

fn measure(s: &Scene, batches: usize, iters: usize) -> Result<Row> {
    let mut full = Ours::new(s, false)?;
    let mut roi = Ours::new(s, true)?;
    let t_full = time_ns(batches, iters, || {
        full.run(s).map(|p| {
            black_box(p);
        })
    })?;
    let t_roi = time_ns(batches, iters * 20, || {
        roi.run(s).map(|p| {
            black_box(p);
        })
    })?;
    let m = *roi.tracker.measurement();
    if !m.used_roi {
        bail!("{}: ROI case did not use the tracking windows", s.name);
    }
    // Allocations, counted over plain loops (no timing harness inside the window).
    let a0 = irtrack_testkit::allocations();
    for _ in 0..100 {
        black_box(full.run(s)?);
        black_box(roi.run(s)?);
    }
    let allocs_per_pair = (irtrack_testkit::allocations() - a0) as f64 / 200.0;
    let t_sum = time_ns(batches, iters * 4, || {
        black_box(sum_pixels(s));
        Ok(())
    })?;
    let t_max = time_ns(batches, iters * 4, || {
        black_box(max_pixels(s));
        Ok(())
    })?;

    // ROI breakdown with the public building blocks, on the tracker's own windows.
    let cfg = *roi.tracker.config();
    let mut centroids = [(0.0, 0.0); 2];
    for (c, xy) in centroids.iter_mut().enumerate() {
        let b = m.cameras[c].marker.context("ROI case: camera without marker")?;
        *xy = (b.x_px, b.y_px);
    }
    let windows = centroids.map(|(x, y)| Roi::around(x, y, cfg.roi_half_px, s.width_px, s.height_px));
    let mut det = BlobDetector::new(BlobLimits::for_frame(s.width_px, s.height_px))?;
    let blob_cfg = BlobConfig {
        threshold_dn: cfg.threshold_dn,
        ..BlobConfig::default()
    };
    let v = views(s)?;
    let t_windows = time_ns(batches, iters * 40, || {
        for c in 0..2 {
            black_box(det.detect(&v[c], Some(windows[c]), &blob_cfg)?.len());
        }
        Ok(())
    })?;
    let cams = [&s.rig.cameras[0], &s.rig.cameras[1]];
    let t_geometry = time_ns(batches, iters * 40, || {
        let r = [0, 1].map(|c| {
            let (x, y) = black_box(centroids[c]);
            Ray::from_pixel(&cams[c].model, &cams[c].cam_from_cam0, x, y)
        });
        black_box(midpoint(&r[0], &r[1])?);
        Ok(())
    })?;
    Ok(Row {
        full: t_full,
        roi: t_roi,
        sum: t_sum,
        max: t_max,
        allocs_per_pair,
        roi_windows: t_windows,
        geometry: t_geometry,
    })
}

fn table(quick: bool) -> Result<()> {
    let (batches, scale) = if quick { (3, 1) } else { (11, 8) };
    println!(
        "irtrack-bench: per stereo frame pair, thread CPU time, median of {batches} batches, one thread"
    );
    println!();
    let mut rows = Vec::new();
    #[cfg(feature = "opencv")]
    {
        println!(
            "| frames | ours full | OpenCV | OpenCV/ours | sum pass | ours/sum | max pass | ours/max | ours ROI | ROI/full | allocs/pair | ours−OpenCV |"
        );
        println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    }
    #[cfg(not(feature = "opencv"))]
    {
        println!(
            "| frames | ours full | sum pass | ours/sum | max pass | ours/max | ours ROI | ROI/full | allocs/pair |"
        );
        println!("|---|---|---|---|---|---|---|---|---|");
    }
    for s in scenes()? {
        let iters = scale * if s.width_px > 640 { 10 } else { 25 };
        let r = measure(&s, batches, iters)?;
        let (full, sum, max) = (fmt_us(r.full), fmt_us(r.sum), fmt_us(r.max));
        let (ours_sum, ours_max) = (r.full / r.sum, r.full / r.max);
        let (roi, roi_pct) = (fmt_us(r.roi), 100.0 * r.roi / r.full);
        #[cfg(feature = "opencv")]
        {
            let mut ocv = OpenCv::new(&s)?;
            let p_ours = Ours::new(&s, false)?.run(&s)?;
            let diff_mm = (p_ours - ocv.run(&s)?).norm();
            let t_cv = time_ns(batches, iters, || {
                ocv.run(&s).map(|p| {
                    black_box(p);
                })
            })?;
            println!(
                "| {} | {full} | {} | {:.1}x | {sum} | {ours_sum:.2}x | {max} | {ours_max:.2}x | {roi} | {roi_pct:.2} % | {} | {diff_mm:.4} mm |",
                s.name,
                fmt_us(t_cv),
                t_cv / r.full,
                r.allocs_per_pair,
            );
        }
        #[cfg(not(feature = "opencv"))]
        println!(
            "| {} | {full} | {sum} | {ours_sum:.2}x | {max} | {ours_max:.2}x | {roi} | {roi_pct:.2} % | {} |",
            s.name, r.allocs_per_pair,
        );
        rows.push((s.name, r));
    }
    println!();
    println!("ROI tracking split up (same windows, public building blocks):");
    println!();
    println!(
        "| frames | ours ROI | blob detection in 2 windows | undistort ×2 + triangulate (floor) | rest | floor/full |"
    );
    println!("|---|---|---|---|---|---|");
    for (name, r) in &rows {
        println!(
            "| {name} | {} | {} | {} | {} | {:.2} % |",
            fmt_us(r.roi),
            fmt_us(r.roi_windows),
            fmt_us(r.geometry),
            fmt_us((r.roi - r.roi_windows - r.geometry).max(0.0)),
            100.0 * r.geometry / r.full,
        );
    }
    println!();
    #[cfg(feature = "opencv")]
    println!("Goals: OpenCV/ours ≥ 20x, ours/sum ≤ 3x, ROI/full ≤ 5 %, 0 allocations per pair.");
    #[cfg(feature = "opencv")]
    println!("ours−OpenCV: distance between the two pipelines' 3-D points on the same frames.");
    #[cfg(not(feature = "opencv"))]
    println!("Goals: ours/sum ≤ 3x, ROI/full ≤ 5 %, 0 allocations per pair (built without OpenCV).");
    println!("floor/full: the per-pair geometry any tracked frame needs, as a share of the full frame.");
    Ok(())
}

/// Runs one case `iters` times after setup and one warm-up, printing nothing but a checksum
/// (so the work cannot be optimised away); `cargo xtask bench` runs this under callgrind
/// with two iteration counts and reports the difference per iteration.
fn run_case(case: &str, iters: usize) -> Result<()> {
    let (what, res) = case.rsplit_once('-').context("case must be <what>-<vga|720p>")?;
    let s = match res {
        "vga" => scene("VGA", 640, 480, 600.0)?,
        "720p" => scene("720p", 1280, 720, 900.0)?,
        other => bail!("unknown resolution `{other}` (vga or 720p)"),
    };
    let mut check = 0.0f64;
    match what {
        "ours-full" | "ours-roi" => {
            let mut o = Ours::new(&s, what == "ours-roi")?;
            for _ in 0..iters {
                check += o.run(&s)?.z;
            }
        }
        #[cfg(feature = "opencv")]
        "opencv" => {
            let mut o = OpenCv::new(&s)?;
            o.run(&s)?;
            for _ in 0..iters {
                check += o.run(&s)?.z;
            }
        }
        "sum" => {
            for _ in 0..iters {
                check += sum_pixels(&s) as f64;
            }
        }
        "max" => {
            for _ in 0..iters {
                check += max_pixels(&s) as f64;
            }
        }
        other => bail!("unknown case `{other}` (ours-full, ours-roi, opencv, sum, max)"),
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
                    "usage: irtrack-bench [--quick] | --run <ours-full|ours-roi|opencv|sum|max>-<vga|720p> --iterations N | --idle SECONDS"
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
