//! Checkerboard calibration views: poses that every camera of a rig sees, rendered images
//! that OpenCV's `findChessboardCorners` accepts, and the ground-truth corner pixels.
//!
//! Board frame: origin at the first inner corner, x along a row of inner corners (`inner_cols`
//! of them), y along a column, z into the board (away from the cameras). Inner corner (c, r) sits
//! at (c·s, r·s, 0); corners are listed row by row, as OpenCV lists detected corners. The square
//! touching the top-left outer corner is black, a white margin surrounds the squares.
//!
//! Rendering maps every pixel back onto the board instead of drawing the board forward: the
//! undistorted normalized coordinates of the pixel corners (computed once per camera) go
//! through the homography from normalized image to board plane. A pixel whose four corners
//! fall in the same square is uniform; any other pixel is supersampled (n × n sub-pixels with
//! normalized coordinates interpolated inside the pixel, far below 1e-4 px error for real
//! lenses), which gives honest anti-aliased edges and corner positions.

use std::path::{Path, PathBuf};

use irtrack_core::camera::{CameraModel, RigidTransform};
use irtrack_core::params::RigParams;
use irtrack_core::triangulate::{Ray, least_squares_rays};
use nalgebra::{Matrix3, Rotation3, Unit, Vector2, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

use crate::SimError;
use irtrack_core::pgm;

/// A printed chessboard.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BoardSpec {
    /// Inner corners along a row (OpenCV's pattern width).
    pub inner_cols: u32,
    /// Inner corners along a column (OpenCV's pattern height).
    pub inner_rows: u32,
    /// Side of one square (mm).
    pub square_mm: f64,
    /// White paper around the squares, in squares (OpenCV's detector needs at least ~1).
    pub margin_squares: f64,
}

impl BoardSpec {
    /// A board with the default 1.5-square white margin.
    pub fn new(inner_cols: u32, inner_rows: u32, square_mm: f64) -> Result<Self, SimError> {
        let b = BoardSpec {
            inner_cols,
            inner_rows,
            square_mm,
            margin_squares: 1.5,
        };
        b.validate()?;
        Ok(b)
    }

    /// Checks the geometry.
    pub fn validate(&self) -> Result<(), SimError> {
        if self.inner_cols < 2 || self.inner_rows < 2 {
            return Err(SimError::Config {
                field: "board",
                reason: format!(
                    "{}x{} inner corners; need at least 2x2",
                    self.inner_cols, self.inner_rows
                ),
            });
        }
        if !(self.square_mm > 0.0 && self.square_mm.is_finite()) {
            return Err(SimError::Config {
                field: "square_mm",
                reason: format!("{} must be > 0", self.square_mm),
            });
        }
        if !(self.margin_squares >= 0.0 && self.margin_squares.is_finite()) {
            return Err(SimError::Config {
                field: "margin_squares",
                reason: format!("{} must be >= 0", self.margin_squares),
            });
        }
        Ok(())
    }

    /// Number of inner corners.
    pub fn corner_count(&self) -> usize {
        self.inner_cols as usize * self.inner_rows as usize
    }

    /// Inner corners in the board frame (mm), row by row.
    pub fn object_points_mm(&self) -> Vec<Vector3<f64>> {
        let s = self.square_mm;
        (0..self.inner_rows)
            .flat_map(|r| (0..self.inner_cols).map(move |c| Vector3::new(c as f64 * s, r as f64 * s, 0.0)))
            .collect()
    }

    /// Centre of the inner-corner grid in the board frame.
    pub fn centre_mm(&self) -> Vector3<f64> {
        let s = self.square_mm;
        Vector3::new(
            (self.inner_cols - 1) as f64 * s / 2.0,
            (self.inner_rows - 1) as f64 * s / 2.0,
            0.0,
        )
    }

    /// Rectangle [x0, x1] × [y0, y1] (board frame, mm) covering the squares plus `margin` squares.
    fn rect_mm(&self, margin_squares: f64) -> [f64; 4] {
        let s = self.square_mm;
        let m = (1.0 + margin_squares) * s;
        [
            -m,
            (self.inner_cols - 1) as f64 * s + m,
            -m,
            (self.inner_rows - 1) as f64 * s + m,
        ]
    }

    /// Region key of a board point: square cell indices, or `None` off the paper. Cells are
    /// convex, so a pixel whose corners share a key lies entirely inside one colour.
    #[inline]
    fn region(&self, x_mm: f64, y_mm: f64) -> Option<(i64, i64)> {
        let [x0, x1, y0, y1] = self.rect_mm(self.margin_squares);
        if !(x_mm >= x0 && x_mm < x1 && y_mm >= y0 && y_mm < y1) {
            return None;
        }
        let s = self.square_mm;
        Some(((x_mm / s).floor() as i64, (y_mm / s).floor() as i64))
    }

    /// Reflectance of a region: 0 black, 1 white paper.
    #[inline]
    fn is_black(&self, cell: (i64, i64)) -> bool {
        let (ix, iy) = cell;
        let inside = ix >= -1 && ix < self.inner_cols as i64 && iy >= -1 && iy < self.inner_rows as i64;
        inside && (ix + iy).rem_euclid(2) == 0
    }
}

/// Fractional part of the golden ratio, for the sub-pixel sample lattice.
const GOLDEN_FRAC: f64 = 0.618_033_988_749_894_8;

/// Grey levels and noise of rendered views.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RenderSettings {
    /// Grey level of the black squares.
    pub black_level: f64,
    /// Grey level of the white squares.
    pub white_level: f64,
    /// Everything off the paper.
    pub background_level: f64,
    /// The board's back, for cameras behind it.
    pub backing_level: f64,
    /// Gaussian sensor noise, grey levels RMS.
    pub noise_sigma: f64,
    /// Pixels crossed by an edge get `supersample²` samples.
    pub supersample: u32,
    /// Seed of the sensor noise.
    pub seed: u64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            black_level: 35.0,
            white_level: 215.0,
            background_level: 110.0,
            backing_level: 150.0,
            noise_sigma: 2.0,
            supersample: 8,
            seed: 1,
        }
    }
}

/// How to choose board poses.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseConfig {
    /// Number of board poses (views).
    pub count: usize,
    /// Seed of the pose draw.
    pub seed: u64,
    /// Largest tilt of the board away from facing the rig (degrees).
    pub max_tilt_deg: f64,
    /// Largest angle between the board normal and the direction to any camera (degrees);
    /// beyond ~60° the detector struggles.
    pub max_obliquity_deg: f64,
    /// Largest in-plane rotation (degrees). Kept small so corner ordering stays unambiguous.
    pub max_roll_deg: f64,
    /// Distance from the rig's common target to the board centre; `None`: the crossing point of
    /// the optical axes for a convergent rig, or a distance where the board fills about half the
    /// image for a parallel one.
    pub distance_mm: Option<f64>,
    /// The board's squares plus this many squares of margin must stay this far inside every image.
    pub border_px: f64,
}

impl Default for PoseConfig {
    fn default() -> Self {
        PoseConfig {
            count: 15,
            seed: 7,
            max_tilt_deg: 35.0,
            max_obliquity_deg: 62.0,
            max_roll_deg: 15.0,
            distance_mm: None,
            border_px: 4.0,
        }
    }
}

/// Ground-truth corner pixels of board corners seen by `cam` at pose `cam_from_board`,
/// in [`BoardSpec::object_points_mm`] order.
pub fn corner_pixels(
    cam: &CameraModel,
    cam_from_board: &RigidTransform,
    board: &BoardSpec,
) -> Result<Vec<Vector2<f64>>, SimError> {
    board
        .object_points_mm()
        .iter()
        .map(|p| cam.project(&cam_from_board.apply(p)).map_err(SimError::from))
        .collect()
}

/// Pose of the board in camera `i`'s frame.
pub fn cam_from_board(
    rig: &RigParams,
    camera: usize,
    cam0_from_board: &RigidTransform,
) -> Result<RigidTransform, SimError> {
    let cam = rig.cameras.get(camera).ok_or(SimError::NoSuchCamera {
        camera,
        count: rig.cameras.len(),
    })?;
    Ok(cam.cam_from_cam0.compose(cam0_from_board))
}

/// Checks that every camera sees the whole board (squares plus half a square of margin) at least
/// `border_px` inside its image, from the front and not too obliquely. Returns the worst
/// obliquity in degrees, or `None` when some camera fails.
pub fn view_is_usable(
    rig: &RigParams,
    board: &BoardSpec,
    cam0_from_board: &RigidTransform,
    max_obliquity_deg: f64,
    border_px: f64,
) -> Option<f64> {
    let [x0, x1, y0, y1] = board.rect_mm(0.5_f64.min(board.margin_squares));
    // The outline is sampled densely because distortion bends straight edges.
    const STEPS: usize = 12;
    let mut outline = Vec::with_capacity(4 * STEPS);
    for k in 0..STEPS {
        let f = k as f64 / STEPS as f64;
        outline.push(Vector3::new(x0 + (x1 - x0) * f, y0, 0.0));
        outline.push(Vector3::new(x1, y0 + (y1 - y0) * f, 0.0));
        outline.push(Vector3::new(x1 - (x1 - x0) * f, y1, 0.0));
        outline.push(Vector3::new(x0, y1 - (y1 - y0) * f, 0.0));
    }
    let mut worst_deg: f64 = 0.0;
    for cam in &rig.cameras {
        let pose = cam.cam_from_cam0.compose(cam0_from_board);
        let model = &cam.model;
        let w = model.image_size.width_px as f64;
        let h = model.image_size.height_px as f64;
        for p in &outline {
            let q = pose.apply(p);
            // Stay well inside the field of view so the distortion polynomial is still monotonic.
            if q.z <= 0.0 || (q.x / q.z).hypot(q.y / q.z) > 1.2 {
                return None;
            }
            let px = model.project(&q).ok()?;
            if px.x < border_px
                || px.y < border_px
                || px.x > w - 1.0 - border_px
                || px.y > h - 1.0 - border_px
            {
                return None;
            }
        }
        // Board z points away from the cameras; its front normal is -z.
        let centre = pose.apply(&board.centre_mm());
        let normal = -(pose.rotation() * Vector3::z());
        let to_cam = -centre.normalize();
        let cos = normal.dot(&to_cam);
        if cos <= 0.0 {
            return None;
        }
        let deg = cos.clamp(-1.0, 1.0).acos().to_degrees();
        if deg > max_obliquity_deg {
            return None;
        }
        // Squares must stay large enough for the detector.
        let c = corner_pixels(model, &pose, board).ok()?;
        let cols = board.inner_cols as usize;
        let min_step = (0..c.len())
            .filter(|i| (i + 1) % cols != 0)
            .map(|i| (c[i + 1] - c[i]).norm())
            .fold(f64::INFINITY, f64::min);
        if min_step < 8.0 {
            return None;
        }
        worst_deg = worst_deg.max(deg);
    }
    Some(worst_deg)
}

/// Common target of the rig (cam0 frame) and the unit direction from it toward the cameras.
fn rig_target(
    rig: &RigParams,
    board: &BoardSpec,
    distance_mm: Option<f64>,
) -> Result<(Vector3<f64>, Vector3<f64>), SimError> {
    if rig.cameras.len() < 2 {
        return Err(SimError::Config {
            field: "rig",
            reason: format!("need at least 2 cameras, got {}", rig.cameras.len()),
        });
    }
    let axes: Vec<Ray> = rig
        .cameras
        .iter()
        .map(|c| Ray::from_normalized(&c.cam_from_cam0, &Vector2::new(0.0, 0.0)))
        .collect();
    let n = axes.len() as f64;
    let mean_origin = axes.iter().map(|r| r.origin_mm).sum::<Vector3<f64>>() / n;
    let mean_dir = axes.iter().map(|r| r.dir).sum::<Vector3<f64>>().normalize();
    // Distance at which the squares span about half the narrower image side of camera 0.
    let m0 = &rig.cameras[0].model;
    let extent_mm = (board.inner_cols.max(board.inner_rows) + 1) as f64 * board.square_mm;
    let short_px = m0.image_size.width_px.min(m0.image_size.height_px) as f64;
    let fill_distance_mm = m0.intrinsics.fx_px * extent_mm / (0.6 * short_px);
    let target = match (least_squares_rays(&axes), distance_mm) {
        // Convergent rig: the axes meet (nearly) in front of every camera.
        (Ok((p, _)), None) => p,
        (Ok((p, _)), Some(d)) => {
            let dir = (p - mean_origin).normalize();
            mean_origin + dir * d
        }
        (Err(_), d) => mean_origin + mean_dir * d.unwrap_or(fill_distance_mm),
    };
    let toward = rig
        .cameras
        .iter()
        .map(|c| (c.cam_from_cam0.inverse().translation_mm() - target).normalize())
        .sum::<Vector3<f64>>();
    if toward.norm() <= 1e-6 || !toward.norm().is_finite() || !target.iter().all(|v| v.is_finite()) {
        return Err(SimError::Config {
            field: "rig",
            reason: "cameras have no common viewing direction".into(),
        });
    }
    Ok((target, toward.normalize()))
}

/// Generates `cfg.count` board poses (`cam0_from_board`) that every camera sees entirely,
/// spread over the common field of view (sunflower pattern of board centres) with random tilts,
/// distances and small in-plane rotations. Deterministic for a given seed.
pub fn generate_poses(
    rig: &RigParams,
    board: &BoardSpec,
    cfg: &PoseConfig,
) -> Result<Vec<RigidTransform>, SimError> {
    board.validate()?;
    let (target, toward) = rig_target(rig, board, cfg.distance_mm)?;
    let distance = (rig.cameras[0].cam_from_cam0.inverse().translation_mm() - target).norm();
    sample_poses(rig, board, cfg, target, toward, distance)
}

/// Board poses around `target` facing `toward` (unit, from the board to the cameras) that every
/// camera of `rig` sees; the lateral spread follows the first camera's field of view.
fn sample_poses(
    rig: &RigParams,
    board: &BoardSpec,
    cfg: &PoseConfig,
    target: Vector3<f64>,
    toward: Vector3<f64>,
    distance: f64,
) -> Result<Vec<RigidTransform>, SimError> {
    let first = rig.cameras.first().ok_or(SimError::Config {
        field: "rig",
        reason: "no cameras".into(),
    })?;
    // Base orientation: board facing the cameras, its x along the first camera's x where possible.
    let z_b = -toward;
    let x0 = first.cam_from_cam0.rotation().transpose() * Vector3::x();
    let x_b = (x0 - z_b * x0.dot(&z_b))
        .try_normalize(1e-9)
        .unwrap_or_else(Vector3::y);
    let y_b = z_b.cross(&x_b);
    let base = Matrix3::from_columns(&[x_b, y_b, z_b]);
    // Lateral reach of board centres: the half field of view of the first camera at the target.
    let m0 = &first.model;
    let half_w_mm = distance * m0.image_size.width_px as f64 / (2.0 * m0.intrinsics.fx_px);
    let half_h_mm = distance * m0.image_size.height_px as f64 / (2.0 * m0.intrinsics.fy_px);

    let mut rng = StdRng::seed_from_u64(cfg.seed);
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut poses = Vec::with_capacity(cfg.count);
    for k in 0..cfg.count {
        let phi = k as f64 * golden;
        let mut reach = ((k as f64 + 0.5) / cfg.count as f64).sqrt();
        let mut found = None;
        'shrink: for _ in 0..30 {
            for _ in 0..60 {
                let lateral = x_b * (reach * half_w_mm * phi.cos()) + y_b * (reach * half_h_mm * phi.sin());
                let depth = distance * rng.gen_range(-0.15..0.25);
                let centre = target + lateral - toward * depth;
                let tilt_axis_angle: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
                let axis = Unit::new_normalize(x_b * tilt_axis_angle.cos() + y_b * tilt_axis_angle.sin());
                // Tilted views pin down the focal length: keep every view at least a third of the
                // largest tilt away from facing the rig.
                let tilt_deg = rng.gen_range(cfg.max_tilt_deg / 3.0..=cfg.max_tilt_deg);
                let tilt = if rng.gen_bool(0.5) { tilt_deg } else { -tilt_deg }.to_radians();
                let roll = rng.gen_range(-cfg.max_roll_deg..=cfg.max_roll_deg).to_radians();
                let r = Rotation3::from_axis_angle(&axis, tilt).into_inner()
                    * base
                    * Rotation3::from_axis_angle(&Vector3::z_axis(), roll).into_inner();
                let t = centre - r * board.centre_mm();
                let pose = RigidTransform::from_parts(&r, &t);
                if view_is_usable(rig, board, &pose, cfg.max_obliquity_deg, cfg.border_px).is_some() {
                    found = Some(pose);
                    break 'shrink;
                }
            }
            reach *= 0.9;
        }
        match found {
            Some(p) => poses.push(p),
            None => {
                return Err(SimError::Config {
                    field: "board",
                    reason: format!(
                        "no pose for view {k} shows the {}x{} board ({} mm squares) to every camera; \
                         use a smaller board or another distance",
                        board.inner_cols, board.inner_rows, board.square_mm
                    ),
                });
            }
        }
    }
    Ok(poses)
}

/// Poses (`cam0_from_board`) for intrinsics-only views of one camera: the board fills that
/// camera's image from varied directions, whether or not the other cameras see it. Needed for
/// convergent rigs, where the views all cameras share are all tilted the same way and leave the
/// principal point poorly determined. Other cameras see such boards partly, edge-on or from
/// behind (rendered as plain backing), so a detector does not find them there.
pub fn generate_single_camera_poses(
    rig: &RigParams,
    board: &BoardSpec,
    camera: usize,
    cfg: &PoseConfig,
) -> Result<Vec<RigidTransform>, SimError> {
    let cam = rig.cameras.get(camera).ok_or(SimError::NoSuchCamera {
        camera,
        count: rig.cameras.len(),
    })?;
    // A one-camera rig: its pose stays relative to camera 0, so the poses come out in cam0's frame.
    let single = RigParams {
        cameras: vec![cam.clone()],
        ..rig.clone()
    };
    let (centre, axis) = {
        let ray = Ray::from_normalized(&cam.cam_from_cam0, &Vector2::new(0.0, 0.0));
        (ray.origin_mm, ray.dir)
    };
    let m = &cam.model;
    let extent_mm = (board.inner_cols.max(board.inner_rows) + 1) as f64 * board.square_mm;
    let short_px = m.image_size.width_px.min(m.image_size.height_px) as f64;
    let distance = cfg
        .distance_mm
        .unwrap_or(m.intrinsics.fx_px * extent_mm / (0.6 * short_px));
    let target = centre + axis * distance;
    sample_poses(&single, board, cfg, target, -axis, distance)
}

/// Renders views of one camera; holds the undistorted pixel-corner grid so it is computed once.
#[derive(Debug, Clone)]
pub struct CameraRenderer {
    model: CameraModel,
    /// Normalized coordinates of pixel corners, (width+1) × (height+1), row-major.
    corners: Vec<Vector2<f64>>,
}

impl CameraRenderer {
    /// A renderer for the camera `model`.
    pub fn new(model: CameraModel) -> Self {
        let w = model.image_size.width_px as usize;
        let h = model.image_size.height_px as usize;
        let mut corners = Vec::with_capacity((w + 1) * (h + 1));
        for j in 0..=h {
            for i in 0..=w {
                corners.push(model.undistort_point(i as f64 - 0.5, j as f64 - 0.5));
            }
        }
        CameraRenderer { model, corners }
    }

    /// The camera model it renders with.
    pub fn model(&self) -> &CameraModel {
        &self.model
    }

    /// Renders the board at `cam_from_board` into `out` (8-bit, row-major, width × height).
    pub fn render(
        &self,
        cam_from_board: &RigidTransform,
        board: &BoardSpec,
        settings: &RenderSettings,
        noise_seed: u64,
        out: &mut [u8],
    ) -> Result<(), SimError> {
        board.validate()?;
        let w = self.model.image_size.width_px as usize;
        let h = self.model.image_size.height_px as usize;
        if out.len() != w * h {
            return Err(SimError::BufferSize {
                needed: w * h,
                have: out.len(),
            });
        }
        let n_sub = settings.supersample.max(1) as usize;
        let n_samples = n_sub * n_sub;
        // Normalized image → board plane: the ray s·(x, y, 1) meets X r1 + Y r2 + t, so
        // (X, Y, 1) ∝ M⁻¹ (x, y, 1) with M = [r1 r2 t]; the third component must be > 0.
        let r = cam_from_board.rotation();
        let t = cam_from_board.translation_mm();
        let m = Matrix3::from_columns(&[r.column(0).into_owned(), r.column(1).into_owned(), t]);
        let m_inv = m.try_inverse().ok_or(SimError::Config {
            field: "pose",
            reason: "board plane passes through the camera centre".into(),
        })?;
        let to_board = |n: &Vector2<f64>| -> Option<(f64, f64)> {
            let q = m_inv * Vector3::new(n.x, n.y, 1.0);
            (q.z > 1e-12).then(|| (q.x / q.z, q.y / q.z))
        };
        let region_of = |n: &Vector2<f64>| to_board(n).and_then(|(x, y)| board.region(x, y));
        // Seen from behind (camera on the board's +z side) the board shows its plain backing:
        // the pattern must never appear mirrored, which would give a detector wrong corners.
        let from_behind = cam_from_board.inverse().t_mm[2] > 0.0;
        let level = |reg: Option<(i64, i64)>| match reg {
            None => settings.background_level,
            Some(_) if from_behind => settings.backing_level,
            Some(c) if board.is_black(c) => settings.black_level,
            Some(_) => settings.white_level,
        };
        let noise = Normal::new(0.0, settings.noise_sigma.max(0.0)).map_err(|e| SimError::Config {
            field: "noise_sigma",
            reason: e.to_string(),
        })?;
        let mut rng = StdRng::seed_from_u64(noise_seed ^ settings.seed.rotate_left(32));
        let mut prev_row: Vec<Option<(i64, i64)>> = (0..=w).map(|i| region_of(&self.corners[i])).collect();
        let mut row: Vec<Option<(i64, i64)>> = vec![None; w + 1];
        for j in 0..h {
            for (i, reg) in row.iter_mut().enumerate() {
                *reg = region_of(&self.corners[(j + 1) * (w + 1) + i]);
            }
            for i in 0..w {
                let a = prev_row[i];
                let value = if a == prev_row[i + 1] && a == row[i] && a == row[i + 1] {
                    level(a)
                } else {
                    let c00 = self.corners[j * (w + 1) + i];
                    let c10 = self.corners[j * (w + 1) + i + 1];
                    let c01 = self.corners[(j + 1) * (w + 1) + i];
                    let c11 = self.corners[(j + 1) * (w + 1) + i + 1];
                    let mut sum = 0.0;
                    for k in 0..n_samples {
                        // Rank-1 lattice: n² distinct x and y offsets, so an edge along either
                        // image axis is resolved to 1/n² px instead of a square grid's 1/n.
                        let fx = (k as f64 + 0.5) / n_samples as f64;
                        let fy = ((k as f64 + 0.5) * GOLDEN_FRAC).fract();
                        let n = c00 * ((1.0 - fx) * (1.0 - fy))
                            + c10 * (fx * (1.0 - fy))
                            + c01 * ((1.0 - fx) * fy)
                            + c11 * (fx * fy);
                        sum += level(region_of(&n));
                    }
                    sum / n_samples as f64
                };
                let noisy = if settings.noise_sigma > 0.0 {
                    value + noise.sample(&mut rng)
                } else {
                    value
                };
                out[j * w + i] = noisy.round().clamp(0.0, 255.0) as u8;
            }
            std::mem::swap(&mut prev_row, &mut row);
        }
        Ok(())
    }
}

/// Files and ground truth of a rendered calibration set.
#[derive(Debug, Clone)]
pub struct CheckerboardSet {
    /// The board that was rendered.
    pub board: BoardSpec,
    /// `cam0_from_board` for every view.
    pub poses: Vec<RigidTransform>,
    /// `files[camera][view]`.
    pub files: Vec<Vec<PathBuf>>,
    /// `corners_px[camera][view]`: ground-truth corner pixels, object-point order.
    pub corners_px: Vec<Vec<Vec<Vector2<f64>>>>,
}

/// Renders every view for every camera into `dir/cam<i>/view<k>.pgm` (directories created).
pub fn write_set(
    dir: &Path,
    rig: &RigParams,
    board: &BoardSpec,
    poses: &[RigidTransform],
    settings: &RenderSettings,
) -> Result<CheckerboardSet, SimError> {
    let mut files = Vec::with_capacity(rig.cameras.len());
    let mut corners_px = Vec::with_capacity(rig.cameras.len());
    for (ci, cam) in rig.cameras.iter().enumerate() {
        let renderer = CameraRenderer::new(cam.model);
        let cam_dir = dir.join(format!("cam{ci}"));
        std::fs::create_dir_all(&cam_dir)?;
        let size = cam.model.image_size;
        let mut buf = vec![0u8; size.width_px as usize * size.height_px as usize];
        let mut cam_files = Vec::with_capacity(poses.len());
        let mut cam_corners = Vec::with_capacity(poses.len());
        for (vi, pose) in poses.iter().enumerate() {
            let cam_pose = cam.cam_from_cam0.compose(pose);
            renderer.render(
                &cam_pose,
                board,
                settings,
                ((ci as u64) << 32) | vi as u64,
                &mut buf,
            )?;
            let path = cam_dir.join(format!("view{vi:03}.pgm"));
            std::fs::write(&path, pgm::encode_u8(size.width_px, size.height_px, &buf)?)?;
            cam_files.push(path);
            cam_corners.push(corner_pixels(&cam.model, &cam_pose, board)?);
        }
        files.push(cam_files);
        corners_px.push(cam_corners);
    }
    Ok(CheckerboardSet {
        board: *board,
        poses: poses.to_vec(),
        files,
        corners_px,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{CameraSpec, RigPreset, build_rig};

    fn rigs() -> Vec<RigParams> {
        let spec = CameraSpec::default();
        vec![
            build_rig(&RigPreset::Parallel { baseline_mm: 120.0 }, &spec).unwrap(),
            build_rig(
                &RigPreset::Convergent {
                    distance_mm: 700.0,
                    angle_deg: 90.0,
                },
                &spec,
            )
            .unwrap(),
        ]
    }

    #[test]
    fn poses_are_seen_by_every_camera_for_both_rigs() {
        let board = BoardSpec::new(9, 6, 25.0).unwrap();
        for rig in rigs() {
            let poses = generate_poses(
                &rig,
                &board,
                &PoseConfig {
                    count: 12,
                    ..Default::default()
                },
            )
            .unwrap();
            assert_eq!(poses.len(), 12);
            for pose in &poses {
                assert!(pose.is_proper_rotation(1e-9));
                assert!(view_is_usable(&rig, &board, pose, 62.0, 4.0).is_some());
                for ci in 0..rig.cameras.len() {
                    let c = corner_pixels(
                        &rig.cameras[ci].model,
                        &cam_from_board(&rig, ci, pose).unwrap(),
                        &board,
                    )
                    .unwrap();
                    assert!(c.iter().all(|p| rig.cameras[ci].model.contains_px(p)));
                }
            }
            // Board centres spread over camera 0's image: spans of at least a third of each side.
            let m0 = &rig.cameras[0].model;
            let centres: Vec<_> = poses
                .iter()
                .map(|p| m0.project(&p.apply(&board.centre_mm())).unwrap())
                .collect();
            let span = |f: fn(&Vector2<f64>) -> f64| {
                centres.iter().map(f).fold(f64::MIN, f64::max)
                    - centres.iter().map(f).fold(f64::MAX, f64::min)
            };
            assert!(span(|p| p.x) > 640.0 / 3.0, "x span {}", span(|p| p.x));
            assert!(span(|p| p.y) > 480.0 / 3.0, "y span {}", span(|p| p.y));
        }
    }

    #[test]
    fn convergent_rig_board_faces_between_the_cameras() {
        let board = BoardSpec::new(7, 5, 25.0).unwrap();
        let rig = &rigs()[1];
        let poses = generate_poses(
            rig,
            &board,
            &PoseConfig {
                count: 6,
                ..Default::default()
            },
        )
        .unwrap();
        for p in &poses {
            // Board normal (toward the cameras) is roughly 45° from camera 0's axis.
            let n = -(p.rotation() * Vector3::z());
            let ang = n.dot(&-Vector3::z()).acos().to_degrees();
            assert!((10.0..80.0).contains(&ang), "normal at {ang}°");
        }
    }

    #[test]
    fn too_large_board_is_an_error() {
        let board = BoardSpec::new(9, 6, 200.0).unwrap();
        let rig = &rigs()[1];
        let e = generate_poses(
            rig,
            &board,
            &PoseConfig {
                count: 3,
                ..Default::default()
            },
        )
        .unwrap_err();
        assert!(e.to_string().contains("9x6"), "{e}");
        assert!(BoardSpec::new(1, 6, 20.0).is_err());
        assert!(BoardSpec::new(5, 6, 0.0).is_err());
    }

    /// Rendering is faithful: a pixel fully inside a square has exactly its colour, and the
    /// intensity centroid of the anti-aliased image puts edges where the geometry says.
    #[test]
    fn rendered_squares_and_edges_are_where_geometry_puts_them() {
        let rig = &rigs()[0];
        let model = rig.cameras[0].model;
        let board = BoardSpec::new(5, 4, 30.0).unwrap();
        // Board facing camera 0 squarely at 800 mm, centred on the principal point.
        let r = Matrix3::identity();
        let t = Vector3::new(0.0, 0.0, 800.0) - board.centre_mm();
        let pose = RigidTransform::from_parts(&r, &t);
        let settings = RenderSettings {
            noise_sigma: 0.0,
            ..Default::default()
        };
        let renderer = CameraRenderer::new(model);
        let mut img = vec![0u8; 640 * 480];
        renderer.render(&pose, &board, &settings, 0, &mut img).unwrap();
        let corners = corner_pixels(&model, &pose, &board).unwrap();
        let px = |u: f64, v: f64| img[v.round() as usize * 640 + u.round() as usize];
        // Cell (0,0), right-below corner 0, has even parity: black.
        let c0 = corners[0];
        let c6 = corners[6]; // corner (1,1)
        let mid = (c0 + c6) / 2.0;
        assert_eq!(px(mid.x, mid.y), 35, "cell (0,0) is black");
        let c1 = corners[1];
        let c7 = corners[7];
        let mid = (c1 + c7) / 2.0;
        assert_eq!(px(mid.x, mid.y), 215, "cell (1,0) is white");
        // Far outside the paper: background.
        assert_eq!(img[2 * 640 + 2], 110);
        // A vertical edge between cells (0,0) and (1,0) at the row through their middle:
        // the sub-pixel edge from the grey profile matches the projected edge.
        let v = ((c0.y + c6.y) / 2.0).round();
        let u_edge_true = {
            let a = corners[1];
            let b = corners[6];
            // Edge x = 30 mm, between corner (1,0) and (1,1): interpolate at row v.
            let f = (v - a.y) / (b.y - a.y);
            a.x + f * (b.x - a.x)
        };
        let u0 = u_edge_true.floor() as usize - 3;
        // Black→white step: the edge sits where the accumulated whiteness equals the white span.
        let mut white_px = 0.0;
        for u in u0..u0 + 7 {
            white_px += (img[v as usize * 640 + u] as f64 - 35.0) / 180.0;
        }
        let u_edge_img = (u0 + 7) as f64 - 0.5 - white_px;
        assert!(
            (u_edge_img - u_edge_true).abs() < 0.02,
            "edge {u_edge_img} vs {u_edge_true}"
        );
    }

    #[test]
    fn single_camera_poses_fill_that_camera_and_backs_are_plain() {
        let rig = &rigs()[1];
        let board = BoardSpec::new(9, 6, 25.0).unwrap();
        let cfg = PoseConfig {
            count: 4,
            ..Default::default()
        };
        for cam in 0..2 {
            let poses = generate_single_camera_poses(rig, &board, cam, &cfg).unwrap();
            let single = RigParams {
                cameras: vec![rig.cameras[cam].clone()],
                ..rig.clone()
            };
            assert!(
                poses
                    .iter()
                    .all(|p| view_is_usable(&single, &board, p, 62.0, 4.0).is_some())
            );
        }
        // Camera 0 looking at the board's back: no pattern, only backing and background.
        let r = Rotation3::from_axis_angle(&Vector3::y_axis(), std::f64::consts::PI).into_inner();
        let pose = RigidTransform::from_parts(&r, &(Vector3::new(0.0, 0.0, 800.0) - r * board.centre_mm()));
        let settings = RenderSettings {
            noise_sigma: 0.0,
            ..Default::default()
        };
        let mut img = vec![0u8; 640 * 480];
        CameraRenderer::new(rig.cameras[0].model)
            .render(&pose, &board, &settings, 0, &mut img)
            .unwrap();
        assert!(img.iter().all(|v| *v >= 110), "pattern visible from behind");
        assert!(img.contains(&150));
    }

    #[test]
    fn write_set_creates_files_and_truth() {
        let dir = std::env::temp_dir().join(format!("irtrack-cb-{}", std::process::id()));
        let rig = &rigs()[0];
        let board = BoardSpec::new(6, 4, 30.0).unwrap();
        let poses = generate_poses(
            rig,
            &board,
            &PoseConfig {
                count: 2,
                ..Default::default()
            },
        )
        .unwrap();
        let set = write_set(&dir, rig, &board, &poses, &RenderSettings::default()).unwrap();
        assert_eq!(set.files.len(), 2);
        assert_eq!(set.corners_px[1][1].len(), 24);
        let bytes = std::fs::read(&set.files[1][0]).unwrap();
        let pgm = pgm::decode(&bytes).unwrap();
        assert_eq!((pgm.width_px, pgm.height_px), (640, 480));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
