//! LED-wand calibration (behind `host-tools wand-calibrate`): input, LED identification.
//!
//! A wand carries K ≥ 3 collinear LEDs at known, unequal distances from one end. In every
//! camera's frame the LEDs are found as blobs (irtrack-core's detector), undistorted with the
//! camera's intrinsics, and identified: K blobs on one straight line (in undistorted
//! coordinates, where lines stay straight) whose spacing fits the wand's under perspective tells
//! which LED is which, and which end is end 0. A frame is rejected for a camera when LEDs are
//! missing, when the blobs fit no wand, when more than one set of blobs fits (a reflection on the
//! wand's line), or when the wand is seen too nearly end-on. [`wand_solve`] turns the identified
//! LEDs into camera poses; [`wand_report`] writes the results.
//!
//! [`wand_solve`]: super::wand_solve
//! [`wand_report`]: super::wand_report

use std::collections::BTreeSet;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, anyhow, bail, ensure};
use indicatif::{ProgressBar, ProgressStyle};
use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits};
use irtrack_core::camera::{CameraModel, Distortion, ImageSize, Intrinsics};
use irtrack_core::image::GrayImage;
use irtrack_core::params::{RigParams, looks_like_blob};
use irtrack_core::pgm::{self, PgmPixels};
use nalgebra::Vector2;
use opencv::core::{
    CV_64F, FileNode, FileNodeTraitConst, FileStorage, FileStorage_Mode, FileStorageTraitConst, Mat,
    MatTraitConst,
};

/// Largest ratio of the depths of the wand's two ends in one camera that identification
/// accepts: a wand of length L at least 2 L from the camera (a 300 mm wand at ≥ 600 mm).
pub const MAX_END_DEPTH_RATIO: f64 = 1.5;
/// An LED must lie this close to the line through the wand's ends (undistorted image, px).
pub const COLLINEAR_TOL_PX: f64 = 1.5;
/// Shorter wand images (end to end, px) are too foreshortened to identify reliably.
pub const MIN_WAND_IMAGE_PX: f64 = 40.0;
/// Blob detection threshold for 8-bit frames (scaled for deeper ones), as `track` uses.
pub const THRESHOLD_DN_8BIT: u32 = 40;

/// The wand: LED distances from end 0, increasing, mm.
#[derive(Debug, Clone, PartialEq)]
pub struct Wand {
    /// Each LED's distance from end 0 along the wand (mm), increasing, as given by `--wand-mm`.
    pub leds_mm: Vec<f64>,
}

impl Wand {
    /// Parses `0,120,300`. Needs ≥ 3 distinct distances with unequal spacing.
    pub fn parse(text: &str) -> Result<Wand> {
        let mut leds_mm = text
            .split(',')
            .map(|s| {
                s.trim().parse::<f64>().map_err(|_| {
                    anyhow!(
                        "--wand-mm: `{}` is not a number (expected e.g. 0,120,300)",
                        s.trim()
                    )
                })
            })
            .collect::<Result<Vec<f64>>>()?;
        ensure!(
            leds_mm.len() >= 3,
            "--wand-mm: need at least 3 LED distances (e.g. 0,120,300), got {}",
            leds_mm.len()
        );
        ensure!(
            leds_mm.iter().all(|v| v.is_finite()),
            "--wand-mm: distances must be finite"
        );
        leds_mm.sort_by(f64::total_cmp);
        ensure!(
            leds_mm.windows(2).all(|w| w[1] - w[0] >= 10.0),
            "--wand-mm: LEDs must be at least 10 mm apart, got {leds_mm:?}"
        );
        let w = Wand { leds_mm };
        let r = w.ratios();
        let mirrored = r.iter().rev().map(|v| 1.0 - v).collect::<Vec<_>>();
        ensure!(
            r.iter().zip(&mirrored).any(|(a, b)| (a - b).abs() > 0.05),
            "--wand-mm: {:?} is symmetric, so its ends cannot be told apart; use unequal spacing (e.g. 0,120,300)",
            w.leds_mm
        );
        Ok(w)
    }

    /// Number of LEDs on the wand.
    pub fn len(&self) -> usize {
        self.leds_mm.len()
    }

    /// True when the wand has no LEDs (never, for a parsed wand).
    pub fn is_empty(&self) -> bool {
        self.leds_mm.is_empty()
    }

    /// Distance from the first to the last LED (mm).
    pub fn length_mm(&self) -> f64 {
        self.leds_mm[self.leds_mm.len() - 1] - self.leds_mm[0]
    }

    /// Position of each LED as a fraction of the end-to-end length.
    pub fn ratios(&self) -> Vec<f64> {
        let l = self.length_mm();
        self.leds_mm.iter().map(|s| (s - self.leds_mm[0]) / l).collect()
    }
}

/// Why one camera's view of one frame was not used.
#[derive(Debug, Clone, PartialEq)]
pub enum Rejection {
    /// Fewer blobs than LEDs (occluded, outside the image or merged).
    MissingLeds {
        /// Blobs found.
        found: usize,
        /// LEDs on the wand.
        needed: usize,
    },
    /// No set of blobs lies on a line with the wand's spacing.
    NoWandPattern {
        /// Blobs found.
        blobs: usize,
    },
    /// Several sets of blobs fit the wand (a reflection on its line).
    Ambiguous {
        /// Sets of blobs that fit.
        candidates: usize,
    },
    /// The wand is seen nearly end-on.
    Foreshortened {
        /// End-to-end length of the wand's image (undistorted px), below [`MIN_WAND_IMAGE_PX`].
        length_px: f64,
    },
    /// The frame was identified in this camera only: nothing to pair it with.
    SingleCamera,
    /// Exposed too far from camera 0's instant and without neighbouring frames to move the
    /// LEDs along their tracks to it (docs/calibration.md, "Time offsets").
    Unbridged,
    /// Identified, but far off the bundle adjustment's solution.
    ReprojectionOutlier {
        /// The view's RMS reprojection error (px).
        error_px: f64,
        /// The round's outlier limit it exceeded (px).
        limit_px: f64,
    },
}

impl Rejection {
    /// Short category for counting.
    pub fn kind(&self) -> &'static str {
        match self {
            Rejection::MissingLeds { .. } => "missing LEDs",
            Rejection::NoWandPattern { .. } => "no wand pattern (not collinear / wrong spacing)",
            Rejection::Ambiguous { .. } => "ambiguous (reflection on the wand's line)",
            Rejection::Foreshortened { .. } => "wand seen end-on",
            Rejection::SingleCamera => "seen by one camera only",
            Rejection::Unbridged => "not movable to camera 0's instant",
            Rejection::ReprojectionOutlier { .. } => "reprojection outlier",
        }
    }
}

impl std::fmt::Display for Rejection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Rejection::MissingLeds { found, needed } => {
                write!(f, "missing LEDs: {found} blobs, need {needed}")
            }
            Rejection::NoWandPattern { blobs } => {
                write!(
                    f,
                    "no wand pattern among {blobs} blobs (not collinear or wrong spacing)"
                )
            }
            Rejection::Ambiguous { candidates } => write!(
                f,
                "ambiguous: {candidates} sets of blobs fit the wand (a reflection on its line)"
            ),
            Rejection::Foreshortened { length_px } => {
                write!(
                    f,
                    "wand seen end-on: {length_px:.1} px long, need {MIN_WAND_IMAGE_PX} px"
                )
            }
            Rejection::SingleCamera => write!(f, "identified in this camera only"),
            Rejection::Unbridged => write!(
                f,
                "exposed away from camera 0's instant, with no neighbouring frame to move the LEDs to it"
            ),
            Rejection::ReprojectionOutlier { error_px, limit_px } => {
                write!(f, "reprojection outlier: {error_px:.2} px > {limit_px:.2} px")
            }
        }
    }
}

/// One camera's identified LEDs in one frame: distorted pixel centroids in wand order.
pub type LedPixels = Vec<Vector2<f64>>;

/// The identification of every frame in every camera.
#[derive(Debug, Clone)]
pub struct WandObservations {
    /// Frame file names (paired across cameras), sorted.
    pub frames: Vec<String>,
    /// `views[frame][camera]`.
    pub views: Vec<Vec<std::result::Result<LedPixels, Rejection>>>,
    /// `blobs[frame][camera]`: the spots found (not touching the frame's edge), distorted
    /// pixels; the quality gate identifies the wand in them with other cameras' intrinsics.
    pub blobs: Vec<Vec<Vec<Vector2<f64>>>>,
}

/// Camera directories and their paired frames.
#[derive(Debug, Clone)]
pub struct Recording {
    /// One directory per camera (`cam0`, `cam1`, …), camera 0 first.
    pub dirs: Vec<PathBuf>,
    /// Frame file names found in every camera directory, sorted.
    pub frames: Vec<String>,
}

/// Finds `dir/cam0 .. cam<n-1>`, checks that no further cam directory exists and that every
/// camera has the same frame file names (`.pgm`).
pub fn discover(dir: &Path, n_cameras: usize, intrinsics: &Path) -> Result<Recording> {
    ensure!(dir.is_dir(), "--frames {}: no such directory", dir.display());
    let mut dirs = Vec::new();
    let mut found_cams = Vec::new();
    for i in 0..64 {
        let d = dir.join(format!("cam{i}"));
        if d.is_dir() {
            found_cams.push(i);
        }
    }
    ensure!(
        !found_cams.is_empty(),
        "{}: no camera directories (expected cam0/, cam1/, ... with PGM frames paired by file name)",
        dir.display()
    );
    for i in 0..n_cameras {
        let d = dir.join(format!("cam{i}"));
        ensure!(
            d.is_dir(),
            "{} is missing: {} describes {n_cameras} cameras but {} holds {}",
            d.display(),
            intrinsics.display(),
            dir.display(),
            list_cams(&found_cams)
        );
        dirs.push(d);
    }
    if let Some(extra) = found_cams.iter().find(|c| **c >= n_cameras) {
        bail!(
            "{} has cam{extra}/ but {} has intrinsics for only {n_cameras} camera(s) (K1..K{n_cameras}): \
             missing `K{}`/`D{}` for camera {extra}",
            dir.display(),
            intrinsics.display(),
            extra + 1,
            extra + 1
        );
    }
    let mut names: Vec<BTreeSet<String>> = Vec::with_capacity(n_cameras);
    for d in &dirs {
        let mut set = BTreeSet::new();
        for e in std::fs::read_dir(d).with_context(|| format!("listing {}", d.display()))? {
            let name = e?.file_name().to_string_lossy().into_owned();
            if name.to_ascii_lowercase().ends_with(".pgm") {
                set.insert(name);
            }
        }
        names.push(set);
    }
    for (i, set) in names.iter().enumerate() {
        ensure!(!set.is_empty(), "{}: no .pgm frames", dirs[i].display());
    }
    for i in 1..n_cameras {
        if names[i] != names[0] {
            let missing_here = names[0].difference(&names[i]).next();
            let missing_in_0 = names[i].difference(&names[0]).next();
            let example = match (missing_here, missing_in_0) {
                (Some(n), _) => format!("{n} is in cam0 but not in cam{i}"),
                (None, Some(n)) => format!("{n} is in cam{i} but not in cam0"),
                (None, None) => String::new(),
            };
            bail!(
                "frame counts differ: cam0 has {} frames, cam{i} has {} ({example}); frames pair by file name",
                names[0].len(),
                names[i].len()
            );
        }
    }
    Ok(Recording {
        dirs,
        frames: names[0].iter().cloned().collect(),
    })
}

fn list_cams(c: &[usize]) -> String {
    let v: Vec<String> = c.iter().map(|i| format!("cam{i}/")).collect();
    v.join(", ")
}

fn fs_node(fs: &FileStorage, key: &str) -> Result<Option<FileNode>> {
    let n = fs.get(key)?;
    Ok(if n.empty()? || n.is_none()? { None } else { Some(n) })
}

fn fs_matrix(fs: &FileStorage, key: &str) -> Result<Option<Vec<f64>>> {
    let Some(n) = fs_node(fs, key)? else {
        return Ok(None);
    };
    let m = n
        .mat()
        .with_context(|| format!("`{key}` is not an !!opencv-matrix"))?;
    let mut m64 = Mat::default();
    m.convert_to(&mut m64, CV_64F, 1.0, 0.0)?;
    let mut out = Vec::new();
    for r in 0..m64.rows() {
        for c in 0..m64.cols() {
            out.push(*m64.at_2d::<f64>(r, c)?);
        }
    }
    Ok(Some(out))
}

fn fs_int(fs: &FileStorage, key: &str) -> Result<Option<u32>> {
    let Some(n) = fs_node(fs, key)? else {
        return Ok(None);
    };
    let v = n.real()?;
    ensure!(
        v >= 1.0 && v.fract() == 0.0 && v < 1e6,
        "`{key}` = {v} is not an image size"
    );
    Ok(Some(v as u32))
}

/// Reads each camera's intrinsics: an OpenCV FileStorage file with `K<n>` (or `M<n>`), `D<n>`
/// and `image_width[_<n>]`/`image_height[_<n>]` (n from 1; poses, if present, are ignored), or a
/// parameter blob.
pub fn read_intrinsics(path: &Path) -> Result<Vec<CameraModel>> {
    ensure!(path.is_file(), "--intrinsics {}: no such file", path.display());
    let bytes = std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
    if looks_like_blob(&bytes) {
        let rig = RigParams::from_blob(&bytes)
            .with_context(|| format!("{}: bad parameter blob", path.display()))?;
        return Ok(rig.cameras.iter().map(|c| c.model).collect());
    }
    let name = path
        .to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8", path.display()))?;
    let fs = FileStorage::new(name, FileStorage_Mode::READ as i32, "")
        .map_err(|e| anyhow!("{}: OpenCV cannot parse it: {}", path.display(), e.message))?;
    ensure!(fs.is_opened()?, "{}: OpenCV cannot open it", path.display());
    let mut models = Vec::new();
    for n in 1..=16 {
        let k = match fs_matrix(&fs, &format!("K{n}"))? {
            Some(k) => k,
            None => match fs_matrix(&fs, &format!("M{n}"))? {
                Some(k) => k,
                None => break,
            },
        };
        ensure!(
            k.len() == 9 && k[1] == 0.0 && k[3] == 0.0 && k[6] == 0.0 && k[7] == 0.0,
            "{}: `K{n}` is not a 3×3 camera matrix without skew",
            path.display()
        );
        let d = fs_matrix(&fs, &format!("D{n}"))?
            .ok_or_else(|| anyhow!("{}: `K{n}` has no `D{n}` (camera {n} distortion)", path.display()))?;
        let distortion =
            Distortion::from_slice(&d).map_err(|e| anyhow!("{}: `D{n}`: {e}", path.display()))?;
        let dim = |specific: String, general: &str| -> Result<u32> {
            match fs_int(&fs, &specific)? {
                Some(v) => Ok(v),
                None => fs_int(&fs, general)?.ok_or_else(|| {
                    anyhow!(
                        "{}: missing `{specific}` and `{general}` (camera {n} image size)",
                        path.display()
                    )
                }),
            }
        };
        let image_size = ImageSize {
            width_px: dim(format!("image_width_{n}"), "image_width")?,
            height_px: dim(format!("image_height_{n}"), "image_height")?,
        };
        models.push(CameraModel {
            intrinsics: Intrinsics {
                fx_px: k[0],
                fy_px: k[4],
                cx_px: k[2],
                cy_px: k[5],
            },
            distortion,
            image_size,
        });
    }
    ensure!(
        !models.is_empty(),
        "{}: no camera intrinsics (expected `K1`, `D1`, `K2`, `D2`, ... and image size)",
        path.display()
    );
    Ok(models)
}

/// Identifies the wand among one camera's blob centroids (distorted pixels).
pub fn identify(
    model: &CameraModel,
    wand: &Wand,
    blobs_px: &[Vector2<f64>],
) -> std::result::Result<LedPixels, Rejection> {
    let k = wand.len();
    if blobs_px.len() < k {
        return Err(Rejection::MissingLeds {
            found: blobs_px.len(),
            needed: k,
        });
    }
    let f = model.intrinsics.fx_px;
    // Undistorted coordinates scaled to pixels, where the wand's image is a straight line.
    let und: Vec<Vector2<f64>> = blobs_px
        .iter()
        .map(|p| model.undistort_point(p.x, p.y) * f)
        .collect();
    let ratios = wand.ratios();
    let mut candidates: Vec<(Vec<usize>, f64)> = Vec::new();
    for a in 0..und.len() {
        for b in 0..und.len() {
            if a == b {
                continue;
            }
            // Ordered ends: a is end 0, b the far end.
            let ab = und[b] - und[a];
            let len = ab.norm();
            if len < 1e-9 {
                continue;
            }
            let dir = ab / len;
            let mut inner: Vec<(f64, usize)> = Vec::new();
            for (i, p) in und.iter().enumerate() {
                if i == a || i == b {
                    continue;
                }
                let ap = p - und[a];
                let t = ap.dot(&dir) / len;
                let off = (ap.x * dir.y - ap.y * dir.x).abs();
                if t > 0.0 && t < 1.0 && off <= COLLINEAR_TOL_PX {
                    inner.push((t, i));
                }
            }
            if inner.len() != k - 2 {
                continue;
            }
            inner.sort_by(|x, y| x.0.total_cmp(&y.0));
            // The first inner LED gives the depth ratio of the ends (perspective on a line:
            // t' = t·q / (1 − t + t·q), q = depth of end 0 / depth of the far end); the rest must
            // follow it.
            let (t_img, r) = (inner[0].0, ratios[1]);
            let q = t_img * (1.0 - r) / (r * (1.0 - t_img));
            if !(1.0 / MAX_END_DEPTH_RATIO..=MAX_END_DEPTH_RATIO).contains(&q) {
                continue;
            }
            let consistent = inner.iter().zip(&ratios[1..k - 1]).all(|((t, _), r)| {
                let predicted = r * q / (1.0 - r + r * q);
                ((t - predicted) * len).abs() <= 2.0 * COLLINEAR_TOL_PX
            });
            if !consistent {
                continue;
            }
            let mut order = vec![a];
            order.extend(inner.iter().map(|(_, i)| *i));
            order.push(b);
            candidates.push((order, len));
        }
    }
    match candidates.len() {
        0 => Err(Rejection::NoWandPattern {
            blobs: blobs_px.len(),
        }),
        1 => {
            let (order, len) = &candidates[0];
            if *len < MIN_WAND_IMAGE_PX {
                return Err(Rejection::Foreshortened { length_px: *len });
            }
            Ok(order.iter().map(|i| blobs_px[*i]).collect())
        }
        n => Err(Rejection::Ambiguous { candidates: n }),
    }
}

/// The spots of one frame (blob centroids not touching the frame's edge, distorted pixels).
fn spots(
    detector: &mut BlobDetector,
    pgm: &pgm::Pgm,
    path: &Path,
    out: &mut Vec<Vector2<f64>>,
) -> Result<()> {
    let threshold_dn = (THRESHOLD_DN_8BIT as f64 * (pgm.maxval as f64 + 1.0) / 256.0).round() as u32;
    let cfg = BlobConfig {
        threshold_dn,
        saturation_dn: Some(pgm.maxval as u32),
        ..BlobConfig::default()
    };
    let (w, h) = (pgm.width_px, pgm.height_px);
    let blobs = match &pgm.pixels {
        PgmPixels::U8(d) => detector.detect(&GrayImage::new(d, w, h, w)?, None, &cfg),
        PgmPixels::U16(d) => detector.detect(&GrayImage::new(d, w, h, w)?, None, &cfg),
    }
    .map_err(|e| anyhow!("{}: blob detection: {e}", path.display()))?;
    out.clear();
    out.extend(
        blobs
            .iter()
            .filter(|b| !b.touches_frame_edge)
            .map(|b| Vector2::new(b.x_px, b.y_px)),
    );
    Ok(())
}

/// `model` for the same camera at another resolution: focal lengths and principal point
/// scaled by `s` (pixel centres kept), distortion unchanged (it acts on normalised
/// coordinates), as binning or a scaled sensor mode gives.
pub fn scaled_model(model: &CameraModel, s: f64, size: ImageSize) -> CameraModel {
    let k = &model.intrinsics;
    CameraModel {
        intrinsics: Intrinsics {
            fx_px: k.fx_px * s,
            fy_px: k.fy_px * s,
            cx_px: (k.cx_px + 0.5) * s - 0.5,
            cy_px: (k.cy_px + 0.5) * s - 0.5,
        },
        distortion: model.distortion,
        image_size: size,
    }
}

/// Frames of one camera the size diagnosis looks at (spread over the recording).
const SIZE_PROBE_FRAMES: usize = 300;
/// The size diagnosis judges straightness on views whose end LEDs lie within this share of
/// the image height in rows (a rolling shutter leaves those straight).
const LEVEL_ROWS: f64 = 0.03;
/// Level spots lying within this of a straight line (upper quartile, px) fit the intrinsics:
/// simulated, 0.05 px with the right ones, 0.12–0.16 px with another lens's.
const LEVEL_BEND_PX: f64 = 0.1;

/// The size of camera `c`'s first frame, if it can be read.
fn frame_size(rec: &Recording, c: usize) -> Option<ImageSize> {
    let name = rec.frames.first()?;
    let bytes = std::fs::read(rec.dirs.get(c)?.join(name)).ok()?;
    let pgm = pgm::decode(&bytes).ok()?;
    Some(ImageSize {
        width_px: pgm.width_px,
        height_px: pgm.height_px,
    })
}

/// How one set of intrinsics fits a camera's frames: the share of frames showing the wand in
/// which it is identified, and how straight its spots lie.
struct SizeTest {
    share: f64,
    bend_px: Option<f64>,
}

impl SizeTest {
    fn fits(&self) -> bool {
        self.share >= 0.5 && self.bend_px.is_some_and(|b| b <= LEVEL_BEND_PX)
    }

    fn text(&self) -> String {
        format!(
            "the wand identified in {:.0} % of the frames showing it, its level spots {} off a straight line",
            self.share * 100.0,
            self.bend_px
                .map_or("too few to judge".to_string(), |b| format!("{b:.2} px"))
        )
    }
}

/// Why camera `ci`'s frames (of size `frame`) do not match its intrinsics' size, each
/// hypothesis tested on the camera's frames: another resolution of the same camera (the same
/// aspect: its intrinsics scaled), or the cameras listed in another order (only when swapping
/// two cameras' intrinsics fits both cameras' frame sizes). Says so when it cannot tell.
fn size_cause(rec: &Recording, models: &[CameraModel], wand: &Wand, ci: usize, frame: ImageSize) -> String {
    let given = &models[ci].image_size;
    let (sx, sy) = (
        f64::from(frame.width_px) / f64::from(given.width_px),
        f64::from(frame.height_px) / f64::from(given.height_px),
    );
    let scaled = ((sx - sy).abs() <= 0.002 * sx).then(|| scaled_model(&models[ci], sx, frame));
    let swap = (0..models.len()).find(|m| {
        *m != ci && models[*m].image_size == frame && frame_size(rec, *m) == Some(models[ci].image_size)
    });
    if scaled.is_none() && swap.is_none() {
        return format!(
            "intrinsics of another camera, or of another resolution or sensor window; cannot tell which from \
             the frames: the sizes differ in aspect, so no scaling fits, and no other order of the cameras \
             fits every camera's frame size; calibrate cam{ci}'s intrinsics at {}x{} px",
            frame.width_px, frame.height_px
        );
    }
    // Spots of up to SIZE_PROBE_FRAMES frames showing at least as many spots as LEDs.
    let step = (rec.frames.len() / SIZE_PROBE_FRAMES).max(1);
    let mut frames_spots = Vec::new();
    if let Ok(mut detector) = BlobDetector::new(BlobLimits::for_frame(frame.width_px, frame.height_px)) {
        let mut buf = Vec::new();
        for name in rec.frames.iter().step_by(step) {
            let path = rec.dirs[ci].join(name);
            let Ok(bytes) = std::fs::read(&path) else { continue };
            let Ok(pgm) = pgm::decode(&bytes) else { continue };
            if (pgm.width_px, pgm.height_px) == (frame.width_px, frame.height_px)
                && spots(&mut detector, &pgm, &path, &mut buf).is_ok()
                && buf.len() >= wand.len()
            {
                frames_spots.push(buf.clone());
            }
        }
    }
    let test = |model: &CameraModel| {
        let views: Vec<LedPixels> = frames_spots
            .iter()
            .filter_map(|b| identify(model, wand, b).ok())
            .collect();
        // Raw spots: a rolling shutter bends a turning wand's image through its rows' delays,
        // except where its ends lie on nearly the same rows; lens distortion bends those too.
        let level = views
            .iter()
            .filter(|v| (v[v.len() - 1].y - v[0].y).abs() <= LEVEL_ROWS * f64::from(frame.height_px));
        SizeTest {
            share: views.len() as f64 / frames_spots.len().max(1) as f64,
            bend_px: super::wand_quality::bend_px(level, model),
        }
    };
    let scaled_test = scaled.as_ref().map(&test);
    let swap_test = swap.map(|m| (m, test(&models[m])));
    let resolution = |t: &SizeTest| {
        format!(
            "intrinsics of the same camera at another resolution (binning or a scaled mode): scaled by {sx:.3} \
             they fit its frames ({}); calibrate the intrinsics at the resolution the camera runs at, or scale \
             fx, fy, cx, cy by {sx:.3}",
            t.text()
        )
    };
    let order = |m: usize, t: &SizeTest| {
        format!(
            "cameras in another order: the intrinsics given for cam{m} are for this size and fit its frames ({}), \
             and cam{m}'s frames have the size of cam{ci}'s intrinsics: --intrinsics lists the cameras in another \
             order than the cam directories of --frames",
            t.text()
        )
    };
    match (&scaled_test, &swap_test) {
        (Some(s), Some((m, o))) if s.fits() && o.fits() => {
            format!("cannot tell which: {}; or {}", resolution(s), order(*m, o))
        }
        (Some(s), _) if s.fits() => resolution(s),
        (_, Some((m, o))) if o.fits() => order(*m, o),
        _ => {
            let mut tried = Vec::new();
            if let Some(s) = &scaled_test {
                tried.push(format!("its own scaled by {sx:.3} ({})", s.text()));
            }
            if let Some((m, o)) = &swap_test {
                tried.push(format!("cam{m}'s ({})", o.text()));
            }
            format!(
                "intrinsics of another camera: neither {} fit its frames; calibrate cam{ci}'s intrinsics at {}x{} px",
                tried.join(" nor "),
                frame.width_px,
                frame.height_px
            )
        }
    }
}

/// Reads every frame, detects blobs and identifies the wand per camera. Shows a progress bar on
/// a terminal.
pub fn observe(rec: &Recording, models: &[CameraModel], wand: &Wand) -> Result<WandObservations> {
    let n_cam = rec.dirs.len();
    let total = (rec.frames.len() * n_cam) as u64;
    let bar = if std::io::stderr().is_terminal() {
        let bar = ProgressBar::new(total);
        if let Ok(style) = ProgressStyle::with_template("finding the wand {bar:40} {pos}/{len}") {
            bar.set_style(style);
        }
        bar
    } else {
        ProgressBar::hidden()
    };
    let mut detectors: Vec<BlobDetector> = models
        .iter()
        .map(|m| {
            BlobDetector::new(BlobLimits::for_frame(
                m.image_size.width_px,
                m.image_size.height_px,
            ))
        })
        .collect::<std::result::Result<_, _>>()
        .map_err(|e| anyhow!("blob detector: {e}"))?;
    let mut views = Vec::with_capacity(rec.frames.len());
    let mut all_blobs = Vec::with_capacity(rec.frames.len());
    let mut blobs_px: Vec<Vector2<f64>> = Vec::with_capacity(16);
    for name in &rec.frames {
        let mut row = Vec::with_capacity(n_cam);
        let mut blob_row = Vec::with_capacity(n_cam);
        for (ci, dir) in rec.dirs.iter().enumerate() {
            let path = dir.join(name);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let pgm = pgm::decode(&bytes).with_context(|| format!("decoding {}", path.display()))?;
            let size = models[ci].image_size;
            if (pgm.width_px, pgm.height_px) != (size.width_px, size.height_px) {
                let frame = ImageSize {
                    width_px: pgm.width_px,
                    height_px: pgm.height_px,
                };
                bail!(
                    "{}: {}x{} px, but the intrinsics of camera {ci} are for {}x{} px ({})",
                    path.display(),
                    pgm.width_px,
                    pgm.height_px,
                    size.width_px,
                    size.height_px,
                    size_cause(rec, models, wand, ci, frame)
                );
            }
            spots(&mut detectors[ci], &pgm, &path, &mut blobs_px)?;
            row.push(identify(&models[ci], wand, &blobs_px));
            blob_row.push(blobs_px.clone());
            bar.inc(1);
        }
        views.push(row);
        all_blobs.push(blob_row);
    }
    bar.finish_and_clear();
    Ok(WandObservations {
        frames: rec.frames.clone(),
        views,
        blobs: all_blobs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> CameraModel {
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: 700.0,
                fy_px: 700.0,
                cx_px: 376.0,
                cy_px: 240.0,
            },
            distortion: Distortion {
                k1: -0.3,
                k2: 0.1,
                ..Distortion::NONE
            },
            image_size: ImageSize {
                width_px: 752,
                height_px: 480,
            },
        }
    }

    fn project(m: &CameraModel, p: [f64; 3]) -> Vector2<f64> {
        m.project(&nalgebra::Vector3::from(p)).unwrap()
    }

    #[test]
    fn identifies_the_ends_under_perspective_and_rejects_ambiguity() {
        let m = model();
        let wand = Wand::parse("0,120,300").unwrap();
        // End 0 nearer than the far end, tilted in depth.
        let e0 = nalgebra::Vector3::new(-120.0, 40.0, 1000.0);
        let d = nalgebra::Vector3::new(0.8, -0.2, 0.4).normalize();
        let leds: Vec<Vector2<f64>> = wand
            .leds_mm
            .iter()
            .map(|s| project(&m, (e0 + d * *s).into()))
            .collect();
        // Shuffled order, plus a stray spot off the line.
        let blobs = vec![leds[2], Vector2::new(600.0, 400.0), leds[0], leds[1]];
        let got = identify(&m, &wand, &blobs).unwrap();
        assert_eq!(got, leds);
        // A ghost on the line beyond the far end makes a second fitting set.
        let ghost_3d = e0 + d * 420.0;
        let blobs = vec![leds[0], leds[1], leds[2], project(&m, ghost_3d.into())];
        assert_eq!(
            identify(&m, &wand, &blobs),
            Err(Rejection::Ambiguous { candidates: 2 })
        );
        // Missing LED.
        assert_eq!(
            identify(&m, &wand, &leds[..2]),
            Err(Rejection::MissingLeds { found: 2, needed: 3 })
        );
        // Middle LED pushed off the line.
        let bent = vec![leds[0], leds[1] + Vector2::new(0.0, 8.0), leds[2]];
        assert!(matches!(
            identify(&m, &wand, &bent),
            Err(Rejection::NoWandPattern { .. })
        ));
    }

    #[test]
    fn wand_spec_errors_are_clear() {
        assert!(
            Wand::parse("0,150,300")
                .unwrap_err()
                .to_string()
                .contains("symmetric")
        );
        assert!(
            Wand::parse("0,120")
                .unwrap_err()
                .to_string()
                .contains("at least 3")
        );
        assert!(Wand::parse("0,x,300").unwrap_err().to_string().contains("`x`"));
        assert_eq!(
            Wand::parse("300, 0,120").unwrap().leds_mm,
            vec![0.0, 120.0, 300.0]
        );
    }
}
