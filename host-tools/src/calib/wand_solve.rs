//! Camera poses from identified wand LEDs: initial poses from essential matrices (OpenCV), scale
//! from the wand's length, then one bundle adjustment of every camera pose (optionally every
//! camera's intrinsics) and every wand pose with a Huber loss, solved by the
//! `levenberg-marquardt` crate.
//!
//! Bundle adjustment by variable projection: a wand pose (end 0 plus direction, 5 DOF) touches
//! one frame only, so for given camera parameters every wand pose is solved on its own (a tiny
//! Levenberg–Marquardt problem per frame), and the outer Levenberg–Marquardt sees only the camera
//! parameters, with residuals at the optimal wand poses and the Jacobian projected onto the
//! complement of each frame's wand-pose Jacobian (`J_c − J_w (J_wᵀ J_w)⁻¹ J_wᵀ J_c`). Its normal
//! equations are exactly the Schur complement of the joint problem's, so every outer step is the
//! joint Gauss–Newton/LM step for the cameras with the wand poses following: one adjustment of
//! all parameters, at the cost of a dense problem with only the cameras' columns (6 per camera,
//! +9 with intrinsics) instead of thousands.

use std::cell::RefCell;

use anyhow::{Result, anyhow, bail, ensure};
use irtrack_core::camera::{CameraModel, Distortion, Intrinsics, RigidTransform};
use irtrack_core::params::CameraParams;
use irtrack_core::triangulate::{Ray, least_squares_rays, midpoint};
use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
use nalgebra::storage::Owned;
use nalgebra::{DMatrix, DVector, Dyn, Matrix3, Rotation3, SymmetricEigen, Vector2, Vector3};
use opencv::calib3d;
use opencv::core::{CV_64F, Mat, MatExprTraitConst, MatTraitConst, Point2d, Vector};

use super::wand::{LedPixels, Rejection, Wand, WandObservations};
use super::wand_boards::{BoardPose, BoardView, initial_board_pose};

/// Fewest frames seen by two or more cameras a calibration accepts.
pub const MIN_FRAMES: usize = 20;
/// Fewest frames two cameras must share to get an initial relative pose.
pub const MIN_PAIR_FRAMES: usize = 8;
/// Reprojection errors above this never count as outliers (px).
pub const OUTLIER_FLOOR_PX: f64 = 1.5;
/// A camera view whose RMS exceeds this many times the overall RMS is an outlier.
pub const OUTLIER_FACTOR: f64 = 5.0;
/// Rounds of bundle adjustment with outlier rejection in between.
const MAX_ROUNDS: usize = 3;

/// Bundle adjustment options.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveOptions {
    /// Also refine each camera's intrinsics and distortion (9 parameters per camera, 8 with
    /// `fix_k3`), in the rounds after the poses have converged without outliers.
    pub refine_intrinsics: bool,
    /// With `refine_intrinsics`: keep each camera's k3 at its input value.
    pub fix_k3: bool,
    /// Huber loss threshold (px): errors beyond it count linearly.
    pub huber_px: f64,
}

/// The wand at one frame: end 0 and unit direction, camera 0 frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WandPose {
    /// The wand's end 0 (where [`Wand::leds_mm`] distances start) in camera 0's frame (mm).
    pub end0_mm: Vector3<f64>,
    /// Unit vector from end 0 towards the other end, camera 0's frame.
    pub dir: Vector3<f64>,
}

impl WandPose {
    fn led(&self, s_mm: f64) -> Vector3<f64> {
        self.end0_mm + self.dir * s_mm
    }

    /// The pose moved by `[dx, dy, dz, a, b]`: end 0 shifted, direction tilted by (a, b) rad
    /// along two axes perpendicular to it.
    fn perturbed(&self, p: &[f64]) -> WandPose {
        let (e1, e2) = perpendicular_basis(&self.dir);
        WandPose {
            end0_mm: self.end0_mm + Vector3::new(p[0], p[1], p[2]),
            dir: (self.dir + e1 * p[3] + e2 * p[4]).normalize(),
        }
    }
}

fn perpendicular_basis(d: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let a = if d.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let e1 = (a - d * a.dot(d)).normalize();
    (e1, d.cross(&e1))
}

/// How one camera's initial pose was found.
#[derive(Debug, Clone, PartialEq)]
pub struct PairInit {
    /// The camera already placed that this one was paired with.
    pub reference: usize,
    /// The camera this pairing placed.
    pub camera: usize,
    /// Frames identified in both cameras.
    pub shared_frames: usize,
    /// LED correspondences the essential matrix explains (RANSAC inliers).
    pub inliers: usize,
    /// LED correspondences given to the essential-matrix fit (shared frames × LEDs).
    pub correspondences: usize,
    /// Scale factor applied to the unit-length essential-matrix translation (mm).
    pub scale_mm: f64,
}

/// One round of bundle adjustment.
#[derive(Debug, Clone, PartialEq)]
pub struct Round {
    /// Camera views (one camera's LEDs in one frame) in the adjustment.
    pub views: usize,
    /// RMS reprojection error of those views' LEDs (px).
    pub rms_px: f64,
    /// Checkerboard views in this round (0 while the intrinsics are held).
    pub board_views: usize,
    /// RMS reprojection error of those board views' corners (px; NaN without boards).
    pub board_rms_px: f64,
    /// Cost-function evaluations the Levenberg–Marquardt solver used.
    pub evaluations: usize,
    /// Why the solver stopped (its termination reason as text).
    pub termination: String,
    /// Camera and board views rejected as outliers after this round (0 ends the rounds once the
    /// intrinsics, if asked for, are refined).
    pub rejected: usize,
}

/// Result of the wand calibration.
#[derive(Debug, Clone)]
pub struct WandSolution {
    /// Calibrated cameras, camera 0 first (camera 0 at the identity pose).
    pub cameras: Vec<CameraParams>,
    /// Each camera's initial pose from the essential matrices (cam_from_cam0), before adjustment.
    pub initial: Vec<RigidTransform>,
    /// How each camera after camera 0 got its initial pose, in placement order.
    pub init_pairs: Vec<PairInit>,
    /// Per frame: the wand's pose, if the frame was used.
    pub poses: Vec<Option<WandPose>>,
    /// `views[frame][camera]` after outlier rejection (`Err` = not used, with the reason).
    pub views: Vec<Vec<std::result::Result<LedPixels, Rejection>>>,
    /// One entry per bundle adjustment round, in order.
    pub rounds: Vec<Round>,
    /// RMS reprojection error per camera over its used views in the final solution (px; NaN without
    /// views).
    pub per_camera_rms_px: Vec<f64>,
    /// Used views per camera in the final solution.
    pub per_camera_views: Vec<usize>,
    /// Every checkerboard view given, in input order, with its fit.
    pub boards: Vec<BoardFit>,
}

/// How one checkerboard view (one camera's image of the board) fitted.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardFit {
    /// Index of the camera that saw the board.
    pub camera: usize,
    /// View name (file stem or the pattern's wildcard text).
    pub view: String,
    /// RMS reprojection error of its corners in the last round it took part in (px; NaN if
    /// never fitted).
    pub rms_px: f64,
    /// Why it was not used in the final adjustment, if it was not.
    pub rejected: Option<String>,
}

/// Camera parameters in the outer problem's layout: 6 pose parameters per camera i ≥ 1, then
/// (when refined) `n_intr` intrinsic parameters per camera: fx, fy, cx, cy, k1, k2, p1, p2 and,
/// unless k3 is held, k3.
#[derive(Debug, Clone)]
struct Layout {
    n_cam: usize,
    /// 0 (intrinsics held), 8 (k3 held) or 9.
    n_intr: usize,
}

impl Layout {
    fn new(n_cam: usize, options: &SolveOptions) -> Self {
        let n_intr = match (options.refine_intrinsics, options.fix_k3) {
            (false, _) => 0,
            (true, true) => 8,
            (true, false) => 9,
        };
        Layout { n_cam, n_intr }
    }
    fn len(&self) -> usize {
        6 * (self.n_cam - 1) + self.n_intr * self.n_cam
    }
    fn intr_base(&self, c: usize) -> usize {
        6 * (self.n_cam - 1) + self.n_intr * c
    }
    /// Parameter indices camera `c` depends on.
    fn columns(&self, c: usize) -> Vec<usize> {
        let mut v = Vec::new();
        if c > 0 {
            v.extend(6 * (c - 1)..6 * c);
        }
        let base = self.intr_base(c);
        v.extend(base..base + self.n_intr);
        v
    }
    fn pack(&self, cams: &[CameraParams]) -> DVector<f64> {
        let mut x = DVector::zeros(self.len());
        for (c, cam) in cams.iter().enumerate().skip(1) {
            let r = Rotation3::from_matrix_unchecked(cam.cam_from_cam0.rotation()).scaled_axis();
            let t = cam.cam_from_cam0.translation_mm();
            for k in 0..3 {
                x[6 * (c - 1) + k] = r[k];
                x[6 * (c - 1) + 3 + k] = t[k];
            }
        }
        for (c, cam) in cams.iter().enumerate() {
            let base = self.intr_base(c);
            let k = &cam.model.intrinsics;
            let d = cam.model.distortion.as_array();
            let vals = [k.fx_px, k.fy_px, k.cx_px, k.cy_px, d[0], d[1], d[2], d[3], d[4]];
            for (j, v) in vals.iter().take(self.n_intr).enumerate() {
                x[base + j] = *v;
            }
        }
        x
    }
    /// Camera `c` from the parameter vector (`base` supplies what is not refined).
    fn camera(&self, x: &[f64], c: usize, base: &CameraModel) -> Cam {
        let (r, t) = if c == 0 {
            (Matrix3::identity(), Vector3::zeros())
        } else {
            let o = 6 * (c - 1);
            (
                Rotation3::from_scaled_axis(Vector3::new(x[o], x[o + 1], x[o + 2])).into_inner(),
                Vector3::new(x[o + 3], x[o + 4], x[o + 5]),
            )
        };
        let model = if self.n_intr > 0 {
            let b = self.intr_base(c);
            CameraModel {
                intrinsics: Intrinsics {
                    fx_px: x[b],
                    fy_px: x[b + 1],
                    cx_px: x[b + 2],
                    cy_px: x[b + 3],
                },
                distortion: Distortion {
                    k1: x[b + 4],
                    k2: x[b + 5],
                    p1: x[b + 6],
                    p2: x[b + 7],
                    k3: if self.n_intr == 9 {
                        x[b + 8]
                    } else {
                        base.distortion.k3
                    },
                },
                image_size: base.image_size,
            }
        } else {
            *base
        };
        Cam { r, t, model }
    }
    /// Finite-difference step per parameter.
    fn step(&self, j: usize) -> f64 {
        let pose_len = 6 * (self.n_cam - 1);
        if j < pose_len {
            if j % 6 < 3 { 1e-6 } else { 1e-4 }
        } else {
            match (j - pose_len) % self.n_intr {
                0..=3 => 1e-3,
                _ => 1e-6,
            }
        }
    }
}

/// One camera for evaluation.
#[derive(Debug, Clone, Copy)]
struct Cam {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    model: CameraModel,
}

impl Cam {
    fn project(&self, p: &Vector3<f64>) -> Vector2<f64> {
        let q = self.r * p + self.t;
        // Behind the camera only during wild trial steps: keep the residual finite and large.
        let z = q.z.max(1.0);
        self.model.normalized_to_pixel(q.x / z, q.y / z)
    }
}

/// Huber-weighted residual: r·sqrt(2ρ(|r|))/|r|, so that Σ|r̃|² = Σ 2ρ(|r|).
fn robust(e: Vector2<f64>, huber_px: f64) -> Vector2<f64> {
    let n = e.norm();
    if n <= huber_px {
        e
    } else {
        e * ((2.0 * huber_px * n - huber_px * huber_px).sqrt() / n)
    }
}

/// The used views of one frame: (camera, LED pixels).
type FrameViews = Vec<(usize, LedPixels)>;

fn frame_residuals(
    cams: &[Cam],
    views: &FrameViews,
    wand: &Wand,
    pose: &WandPose,
    huber_px: f64,
    out: &mut Vec<f64>,
) {
    out.clear();
    for (c, px) in views {
        for (s, obs) in wand.leds_mm.iter().zip(px) {
            let e = robust(cams[*c].project(&pose.led(*s)) - obs, huber_px);
            out.push(e.x);
            out.push(e.y);
        }
    }
}

const WAND_STEPS: [f64; 5] = [1e-4, 1e-4, 1e-4, 1e-7, 1e-7];

/// Central-difference Jacobian of a frame's residuals with respect to its wand pose.
fn wand_jacobian(
    cams: &[Cam],
    views: &FrameViews,
    wand: &Wand,
    pose: &WandPose,
    huber_px: f64,
) -> DMatrix<f64> {
    let m = views.len() * wand.len() * 2;
    let mut j = DMatrix::zeros(m, 5);
    let (mut plus, mut minus) = (Vec::new(), Vec::new());
    for k in 0..5 {
        let mut p = [0.0; 5];
        p[k] = WAND_STEPS[k];
        frame_residuals(cams, views, wand, &pose.perturbed(&p), huber_px, &mut plus);
        p[k] = -WAND_STEPS[k];
        frame_residuals(cams, views, wand, &pose.perturbed(&p), huber_px, &mut minus);
        for i in 0..m {
            j[(i, k)] = (plus[i] - minus[i]) / (2.0 * WAND_STEPS[k]);
        }
    }
    j
}

/// The per-frame wand problem for the `levenberg-marquardt` crate: parameters are a
/// perturbation of `anchor`.
struct WandProblem<'a> {
    cams: &'a [Cam],
    views: &'a FrameViews,
    wand: &'a Wand,
    anchor: WandPose,
    p: DVector<f64>,
    huber_px: f64,
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for WandProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.p.copy_from(x);
    }
    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        let mut r = Vec::new();
        frame_residuals(
            self.cams,
            self.views,
            self.wand,
            &self.anchor.perturbed(self.p.as_slice()),
            self.huber_px,
            &mut r,
        );
        Some(DVector::from_vec(r))
    }
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        // The perturbation is re-based at the current point, which has the same local
        // derivatives up to the basis change at p ≠ 0; tolerances make p tiny at convergence.
        Some(wand_jacobian(
            self.cams,
            self.views,
            self.wand,
            &self.anchor.perturbed(self.p.as_slice()),
            self.huber_px,
        ))
    }
}

fn solve_wand(cams: &[Cam], views: &FrameViews, wand: &Wand, start: WandPose, huber_px: f64) -> WandPose {
    let mut pose = start;
    // Re-anchoring keeps the parameterisation's Jacobian exact at the solution.
    for _ in 0..3 {
        let problem = WandProblem {
            cams,
            views,
            wand,
            anchor: pose,
            p: DVector::zeros(5),
            huber_px,
        };
        let (problem, _report) = LevenbergMarquardt::new()
            .with_xtol(1e-13)
            .with_ftol(1e-14)
            .minimize(problem);
        let step = problem.p.norm();
        pose = problem.anchor.perturbed(problem.p.as_slice());
        if step < 1e-9 {
            break;
        }
    }
    pose
}

fn board_residuals(
    model: &CameraModel,
    view: &BoardView,
    pose: &BoardPose,
    huber_px: f64,
    out: &mut Vec<f64>,
) {
    out.clear();
    let cam = Cam {
        r: pose.r,
        t: pose.t_mm,
        model: *model,
    };
    for (p, obs) in view.object_mm.iter().zip(&view.corners_px) {
        let e = robust(cam.project(p) - obs, huber_px);
        out.push(e.x);
        out.push(e.y);
    }
}

const BOARD_STEPS: [f64; 6] = [1e-7, 1e-7, 1e-7, 1e-4, 1e-4, 1e-4];

/// Central-difference Jacobian of a board view's residuals with respect to its pose.
fn board_jacobian(model: &CameraModel, view: &BoardView, pose: &BoardPose, huber_px: f64) -> DMatrix<f64> {
    let m = view.corners_px.len() * 2;
    let mut j = DMatrix::zeros(m, 6);
    let (mut plus, mut minus) = (Vec::new(), Vec::new());
    for k in 0..6 {
        let mut p = [0.0; 6];
        p[k] = BOARD_STEPS[k];
        board_residuals(model, view, &pose.perturbed(&p), huber_px, &mut plus);
        p[k] = -BOARD_STEPS[k];
        board_residuals(model, view, &pose.perturbed(&p), huber_px, &mut minus);
        for i in 0..m {
            j[(i, k)] = (plus[i] - minus[i]) / (2.0 * BOARD_STEPS[k]);
        }
    }
    j
}

/// The per-view board problem for the `levenberg-marquardt` crate: parameters are a
/// perturbation of `anchor`.
struct BoardProblem<'a> {
    model: &'a CameraModel,
    view: &'a BoardView,
    anchor: BoardPose,
    p: DVector<f64>,
    huber_px: f64,
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for BoardProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.p.copy_from(x);
    }
    fn params(&self) -> DVector<f64> {
        self.p.clone()
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        let mut r = Vec::new();
        board_residuals(
            self.model,
            self.view,
            &self.anchor.perturbed(self.p.as_slice()),
            self.huber_px,
            &mut r,
        );
        Some(DVector::from_vec(r))
    }
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        Some(board_jacobian(
            self.model,
            self.view,
            &self.anchor.perturbed(self.p.as_slice()),
            self.huber_px,
        ))
    }
}

fn solve_board(model: &CameraModel, view: &BoardView, start: BoardPose, huber_px: f64) -> BoardPose {
    let mut pose = start;
    for _ in 0..3 {
        let problem = BoardProblem {
            model,
            view,
            anchor: pose,
            p: DVector::zeros(6),
            huber_px,
        };
        let (problem, _report) = LevenbergMarquardt::new()
            .with_xtol(1e-13)
            .with_ftol(1e-14)
            .minimize(problem);
        let step = problem.p.norm();
        pose = problem.anchor.perturbed(problem.p.as_slice());
        if step < 1e-9 {
            break;
        }
    }
    pose
}

/// Reprojection error (px, not robustified) of one board view.
fn board_rms(model: &CameraModel, view: &BoardView, pose: &BoardPose) -> f64 {
    let cam = Cam {
        r: pose.r,
        t: pose.t_mm,
        model: *model,
    };
    let s: f64 = view
        .object_mm
        .iter()
        .zip(&view.corners_px)
        .map(|(p, o)| (cam.project(p) - o).norm_squared())
        .sum();
    (s / view.corners_px.len().max(1) as f64).sqrt()
}

/// The outer (camera) problem.
struct RigProblem<'a> {
    layout: Layout,
    base: &'a [CameraModel],
    frames: &'a [FrameViews],
    wand: &'a Wand,
    huber_px: f64,
    x: DVector<f64>,
    /// Wand poses at the last accepted point (start of every inner solve).
    anchors: RefCell<Vec<WandPose>>,
    /// Wand poses solved for `x`.
    poses: Vec<WandPose>,
    /// Checkerboard views (only while intrinsics are refined: they constrain nothing else).
    boards: &'a [&'a BoardView],
    /// Board poses at the last accepted point, and solved for `x`.
    board_anchors: RefCell<Vec<BoardPose>>,
    board_poses: Vec<BoardPose>,
    evaluations: RefCell<usize>,
}

impl RigProblem<'_> {
    fn cams(&self, x: &[f64]) -> Vec<Cam> {
        (0..self.layout.n_cam)
            .map(|c| self.layout.camera(x, c, &self.base[c]))
            .collect()
    }
}

impl LeastSquaresProblem<f64, Dyn, Dyn> for RigProblem<'_> {
    type ResidualStorage = Owned<f64, Dyn>;
    type JacobianStorage = Owned<f64, Dyn, Dyn>;
    type ParameterStorage = Owned<f64, Dyn>;

    fn set_params(&mut self, x: &DVector<f64>) {
        self.x.copy_from(x);
        let cams = self.cams(x.as_slice());
        let anchors = self.anchors.borrow();
        self.poses = self
            .frames
            .iter()
            .zip(anchors.iter())
            .map(|(v, a)| solve_wand(&cams, v, self.wand, *a, self.huber_px))
            .collect();
        let board_anchors = self.board_anchors.borrow();
        self.board_poses = self
            .boards
            .iter()
            .zip(board_anchors.iter())
            .map(|(b, a)| solve_board(&cams[b.camera].model, b, *a, self.huber_px))
            .collect();
        *self.evaluations.borrow_mut() += 1;
    }
    fn params(&self) -> DVector<f64> {
        self.x.clone()
    }
    fn residuals(&self) -> Option<DVector<f64>> {
        let cams = self.cams(self.x.as_slice());
        let mut all = Vec::new();
        let mut r = Vec::new();
        for (v, p) in self.frames.iter().zip(&self.poses) {
            frame_residuals(&cams, v, self.wand, p, self.huber_px, &mut r);
            all.extend_from_slice(&r);
        }
        for (b, p) in self.boards.iter().zip(&self.board_poses) {
            board_residuals(&cams[b.camera].model, b, p, self.huber_px, &mut r);
            all.extend_from_slice(&r);
        }
        all.iter().all(|v| v.is_finite()).then(|| DVector::from_vec(all))
    }
    fn jacobian(&self) -> Option<DMatrix<f64>> {
        // Only accepted points get a Jacobian: their wand poses seed the next inner solves.
        self.anchors.borrow_mut().clone_from(&self.poses);
        self.board_anchors.borrow_mut().clone_from(&self.board_poses);
        let x = self.x.as_slice();
        let cams = self.cams(x);
        let n = self.layout.len();
        let k = self.wand.len();
        let rows: usize = self.frames.iter().map(|v| v.len() * k * 2).sum::<usize>()
            + self.boards.iter().map(|b| b.corners_px.len() * 2).sum::<usize>();
        let mut jac = DMatrix::zeros(rows, n);
        let mut row0 = 0;
        let mut xp = x.to_vec();
        for (v, pose) in self.frames.iter().zip(&self.poses) {
            let m = v.len() * k * 2;
            let jw = wand_jacobian(&cams, v, self.wand, pose, self.huber_px);
            let mut jc = DMatrix::zeros(m, n);
            for (vi, (c, px)) in v.iter().enumerate() {
                let single: FrameViews = vec![(*c, px.clone())];
                for col in self.layout.columns(*c) {
                    let h = self.layout.step(col);
                    let orig = xp[col];
                    let eval = |delta: f64, xp: &mut Vec<f64>| {
                        xp[col] = orig + delta;
                        let mut cs = cams.clone();
                        cs[*c] = self.layout.camera(xp, *c, &self.base[*c]);
                        let mut r = Vec::new();
                        frame_residuals(&cs, &single, self.wand, pose, self.huber_px, &mut r);
                        r
                    };
                    let plus = eval(h, &mut xp);
                    let minus = eval(-h, &mut xp);
                    xp[col] = orig;
                    for i in 0..2 * k {
                        jc[(vi * 2 * k + i, col)] = (plus[i] - minus[i]) / (2.0 * h);
                    }
                }
            }
            // Project out the wand pose's directions (variable projection / Schur complement).
            let jtj = jw.transpose() * &jw;
            let reduced = match jtj.cholesky() {
                Some(ch) => {
                    let coef = ch.solve(&(jw.transpose() * &jc));
                    &jc - &jw * coef
                }
                None => jc,
            };
            jac.view_mut((row0, 0), (m, n)).copy_from(&reduced);
            row0 += m;
        }
        // Board views: only their camera's intrinsics; the board pose is projected out as the
        // wand pose is.
        for (b, pose) in self.boards.iter().zip(&self.board_poses) {
            let c = b.camera;
            let m = b.corners_px.len() * 2;
            let jb = board_jacobian(&cams[c].model, b, pose, self.huber_px);
            let mut jc = DMatrix::zeros(m, n);
            let base = self.layout.intr_base(c);
            for col in base..base + self.layout.n_intr {
                let h = self.layout.step(col);
                let orig = xp[col];
                let mut eval = |delta: f64| {
                    xp[col] = orig + delta;
                    let model = self.layout.camera(&xp, c, &self.base[c]).model;
                    let mut r = Vec::new();
                    board_residuals(&model, b, pose, self.huber_px, &mut r);
                    r
                };
                let plus = eval(h);
                let minus = eval(-h);
                xp[col] = orig;
                for i in 0..m {
                    jc[(i, col)] = (plus[i] - minus[i]) / (2.0 * h);
                }
            }
            let jtj = jb.transpose() * &jb;
            let reduced = match jtj.cholesky() {
                Some(ch) => {
                    let coef = ch.solve(&(jb.transpose() * &jc));
                    &jc - &jb * coef
                }
                None => jc,
            };
            jac.view_mut((row0, 0), (m, n)).copy_from(&reduced);
            row0 += m;
        }
        Some(jac)
    }
}

fn normalized(model: &CameraModel, px: &LedPixels) -> Vec<Vector2<f64>> {
    px.iter().map(|p| model.undistort_point(p.x, p.y)).collect()
}

/// Relative pose of camera b from camera a (`x_b = R x_a + t`, |t| = 1) from normalized
/// correspondences, by OpenCV's RANSAC essential matrix and cheirality check.
fn essential_pose(
    na: &[Vector2<f64>],
    nb: &[Vector2<f64>],
    threshold: f64,
) -> Result<(Matrix3<f64>, Vector3<f64>, usize)> {
    let pa: Vector<Point2d> = na.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let pb: Vector<Point2d> = nb.iter().map(|p| Point2d::new(p.x, p.y)).collect();
    let k = Mat::eye(3, 3, CV_64F)?.to_mat()?;
    let mut mask = Mat::default();
    let e = calib3d::find_essential_mat(&pa, &pb, &k, calib3d::RANSAC, 0.9999, threshold, 5000, &mut mask)?;
    ensure!(e.rows() == 3 && e.cols() == 3, "no essential matrix");
    let (mut r, mut t) = (Mat::default(), Mat::default());
    let inliers = calib3d::recover_pose_estimated(&e, &pa, &pb, &k, &mut r, &mut t, &mut mask)?;
    let mut rm = Matrix3::zeros();
    for i in 0..3 {
        for j in 0..3 {
            rm[(i, j)] = *r.at_2d::<f64>(i as i32, j as i32)?;
        }
    }
    let tv = Vector3::new(
        *t.at_2d::<f64>(0, 0)?,
        *t.at_2d::<f64>(1, 0)?,
        *t.at_2d::<f64>(2, 0)?,
    );
    Ok((rm, tv, inliers.max(0) as usize))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Initial camera poses: essential matrix per pair, camera 0 first, each further camera from the
/// already solved camera it shares the most frames with; scale from the wand's length.
fn initial_poses(
    models: &[CameraModel],
    obs: &WandObservations,
    wand: &Wand,
) -> Result<(Vec<RigidTransform>, Vec<PairInit>)> {
    let n_cam = models.len();
    let shared = |a: usize, b: usize| -> Vec<usize> {
        (0..obs.frames.len())
            .filter(|f| obs.views[*f][a].is_ok() && obs.views[*f][b].is_ok())
            .collect()
    };
    let mut poses: Vec<Option<RigidTransform>> = vec![None; n_cam];
    poses[0] = Some(RigidTransform::IDENTITY);
    let mut pairs = Vec::new();
    let last = wand.len() - 1;
    while poses.iter().any(Option::is_none) {
        let mut best: Option<(usize, usize, Vec<usize>)> = None;
        for a in (0..n_cam).filter(|a| poses[*a].is_some()) {
            for b in (0..n_cam).filter(|b| poses[*b].is_none()) {
                let s = shared(a, b);
                if best.as_ref().is_none_or(|(_, _, bs)| s.len() > bs.len()) {
                    best = Some((a, b, s));
                }
            }
        }
        let Some((a, b, frames)) = best else { break };
        if frames.len() < MIN_PAIR_FRAMES {
            bail!(
                "too few usable wand observations for camera {b}: it shares {} identified wand frames with the \
                 cameras already placed (best: camera {a}), need at least {MIN_PAIR_FRAMES}. Wave the wand where \
                 camera {b} and another camera both see it",
                frames.len()
            );
        }
        let (mut na, mut nb) = (Vec::new(), Vec::new());
        for f in &frames {
            if let (Ok(pa), Ok(pb)) = (&obs.views[*f][a], &obs.views[*f][b]) {
                na.extend(normalized(&models[a], pa));
                nb.extend(normalized(&models[b], pb));
            }
        }
        let threshold = 1.0 / models[a].intrinsics.fx_px.max(models[b].intrinsics.fx_px);
        let (r, t, inliers) = essential_pose(&na, &nb, threshold).map_err(|e| {
            anyhow!("degenerate motion: no relative pose between camera {a} and camera {b}: {e}")
        })?;
        if inliers * 2 < na.len() {
            bail!(
                "degenerate motion or wrong intrinsics: the essential matrix between camera {a} and camera {b} \
                 explains only {inliers} of {} LED correspondences",
                na.len()
            );
        }
        // Scale: the wand's end-to-end length triangulated with the unit baseline.
        let rel = RigidTransform::from_parts(&r, &t);
        let mut lengths = Vec::new();
        for f in &frames {
            if let (Ok(pa), Ok(pb)) = (&obs.views[*f][a], &obs.views[*f][b]) {
                let ends: Option<Vec<Vector3<f64>>> = [0, last]
                    .iter()
                    .map(|i| {
                        let ra = Ray::from_normalized(
                            &RigidTransform::IDENTITY,
                            &models[a].undistort_point(pa[*i].x, pa[*i].y),
                        );
                        let rb = Ray::from_normalized(&rel, &models[b].undistort_point(pb[*i].x, pb[*i].y));
                        midpoint(&ra, &rb).ok().map(|m| m.point_mm)
                    })
                    .collect();
                if let Some(e) = ends {
                    lengths.push((e[1] - e[0]).norm());
                }
            }
        }
        ensure!(
            !lengths.is_empty(),
            "degenerate motion: the wand could not be triangulated between camera {a} and camera {b}"
        );
        let scale = wand.length_mm() / median(&mut lengths);
        let rel = RigidTransform::from_parts(&r, &(t * scale));
        let a_pose = poses[a].ok_or_else(|| anyhow!("camera {a} unplaced"))?;
        poses[b] = Some(rel.compose(&a_pose));
        pairs.push(PairInit {
            reference: a,
            camera: b,
            shared_frames: frames.len(),
            inliers,
            correspondences: na.len(),
            scale_mm: scale,
        });
    }
    let poses = poses
        .into_iter()
        .enumerate()
        .map(|(i, p)| p.ok_or_else(|| anyhow!("camera {i} could not be placed")))
        .collect::<Result<Vec<_>>>()?;
    Ok((poses, pairs))
}

/// Wand pose from triangulated LEDs: least-squares line with the known spacing.
fn fit_wand(points: &[Vector3<f64>], wand: &Wand) -> Option<WandPose> {
    // Minimise Σ |e0 + s_k d − X_k|² over e0 and (unnormalised) d: 6 linear unknowns.
    let n = points.len() as f64;
    let s: Vec<f64> = wand.leds_mm.clone();
    let (ss, s2) = (s.iter().sum::<f64>(), s.iter().map(|v| v * v).sum::<f64>());
    let sx: Vector3<f64> = points.iter().sum();
    let sxs: Vector3<f64> = points.iter().zip(&s).map(|(p, v)| p * *v).sum();
    let det = n * s2 - ss * ss;
    if det.abs() < 1e-9 {
        return None;
    }
    let d = (sxs * n - sx * ss) / det;
    let e0 = (sx - d * ss) / n;
    let dir = d.try_normalize(1e-9)?;
    // Keep the known spacing: centre the wand on the fitted line.
    let mean_s = ss / n;
    let centre = e0 + d * mean_s;
    Some(WandPose {
        end0_mm: centre - dir * mean_s,
        dir,
    })
}

fn triangulate_pose(cams: &[CameraParams], views: &[(usize, LedPixels)], wand: &Wand) -> Option<WandPose> {
    let mut pts = Vec::with_capacity(wand.len());
    for k in 0..wand.len() {
        let rays: Vec<Ray> = views
            .iter()
            .map(|(c, px)| Ray::from_pixel(&cams[*c].model, &cams[*c].cam_from_cam0, px[k].x, px[k].y))
            .collect();
        pts.push(least_squares_rays(&rays).ok()?.0);
    }
    fit_wand(&pts, wand)
}

/// Frames usable for the adjustment: each with its identified views (two or more cameras).
fn usable(views: &[Vec<std::result::Result<LedPixels, Rejection>>]) -> Vec<(usize, FrameViews)> {
    views
        .iter()
        .enumerate()
        .filter_map(|(f, row)| {
            let v: FrameViews = row
                .iter()
                .enumerate()
                .filter_map(|(c, r)| r.as_ref().ok().map(|p| (c, p.clone())))
                .collect();
            (v.len() >= 2).then_some((f, v))
        })
        .collect()
}

/// Checks that the wand was moved and turned enough to determine the rig.
fn check_motion(poses: &[WandPose], wand: &Wand) -> Result<()> {
    let n = poses.len() as f64;
    let mut scatter = Matrix3::zeros();
    for p in poses {
        scatter += p.dir * p.dir.transpose();
    }
    let eig = SymmetricEigen::new(scatter / n).eigenvalues;
    let mut e: Vec<f64> = eig.iter().copied().collect();
    e.sort_by(f64::total_cmp);
    if e[1] < 0.02 {
        bail!(
            "degenerate motion: the wand kept nearly one direction (direction spread {:.3}, need ≥ 0.02); \
             turn it through different directions while waving",
            e[1]
        );
    }
    let mids: Vec<Vector3<f64>> = poses.iter().map(|p| p.led(wand.length_mm() / 2.0)).collect();
    let mean: Vector3<f64> = mids.iter().sum::<Vector3<f64>>() / n;
    let spread = (mids.iter().map(|m| (m - mean).norm_squared()).sum::<f64>() / n).sqrt();
    if spread < 0.2 * wand.length_mm() {
        bail!(
            "degenerate motion: the wand's middle stayed within {spread:.0} mm RMS of one point; \
             move it through the whole work volume"
        );
    }
    Ok(())
}

/// Reprojection error (px, not robustified) of one view.
fn view_rms(cam: &Cam, px: &LedPixels, pose: &WandPose, wand: &Wand) -> f64 {
    let s: f64 = wand
        .leds_mm
        .iter()
        .zip(px)
        .map(|(s, o)| (cam.project(&pose.led(*s)) - o).norm_squared())
        .sum();
    (s / px.len() as f64).sqrt()
}

/// Runs initialisation and the bundle adjustment with outlier rejection. `boards` (checkerboard
/// views, see [`super::wand_boards`]) join the adjustment in the rounds that refine the
/// intrinsics, which they require.
pub fn solve(
    models: &[CameraModel],
    obs: &WandObservations,
    wand: &Wand,
    boards: &[BoardView],
    options: SolveOptions,
    mut progress: impl FnMut(&str),
) -> Result<WandSolution> {
    let n_cam = models.len();
    ensure!(
        boards.is_empty() || options.refine_intrinsics,
        "checkerboard views constrain only the intrinsics: they need intrinsics refinement"
    );
    if let Some(b) = boards.iter().find(|b| b.camera >= n_cam) {
        bail!(
            "board view {} is for camera {}, but the rig has {n_cam} cameras",
            b.view,
            b.camera
        );
    }
    let frames = usable(&obs.views);
    if frames.len() < MIN_FRAMES {
        let mut counts = std::collections::BTreeMap::new();
        for row in &obs.views {
            for r in row.iter().filter_map(|r| r.as_ref().err()) {
                *counts.entry(r.kind()).or_insert(0usize) += 1;
            }
        }
        let why: Vec<String> = counts.iter().map(|(k, v)| format!("{v} {k}")).collect();
        bail!(
            "too few usable wand observations: {} of {} frames show the identified wand in two or more cameras, \
             need at least {MIN_FRAMES} (rejected camera views: {})",
            frames.len(),
            obs.frames.len(),
            if why.is_empty() {
                "none".into()
            } else {
                why.join(", ")
            }
        );
    }
    let (initial, init_pairs) = initial_poses(models, obs, wand)?;
    progress(&format!(
        "initial poses from {} essential matrices",
        init_pairs.len()
    ));
    let mut cameras: Vec<CameraParams> = models
        .iter()
        .zip(&initial)
        .map(|(m, p)| CameraParams {
            model: *m,
            cam_from_cam0: *p,
        })
        .collect();
    let mut views = obs.views.clone();
    // Frames identified in one camera only are of no use; say so.
    for row in views.iter_mut() {
        if row.iter().filter(|r| r.is_ok()).count() == 1 {
            for r in row.iter_mut().filter(|r| r.is_ok()) {
                *r = Err(Rejection::SingleCamera);
            }
        }
    }
    // Intrinsics are refined only once the poses have converged without outliers: refined
    // while gross outliers are still in (round 1 can be at pixels of RMS), they are dragged
    // into a different valley of this weakly conditioned problem and the later rounds stay
    // there (measured: 0.032° vs 0.001° with the intrinsics held, on the same wave).
    let held = Layout::new(
        n_cam,
        &SolveOptions {
            refine_intrinsics: false,
            ..options
        },
    );
    let refined = Layout::new(n_cam, &options);
    let mut layout = held.clone();
    let mut rounds = Vec::new();
    let mut poses_by_frame: Vec<Option<WandPose>> = vec![None; obs.frames.len()];
    let mut board_fits: Vec<BoardFit> = boards
        .iter()
        .map(|b| BoardFit {
            camera: b.camera,
            view: b.view.clone(),
            rms_px: f64::NAN,
            rejected: None,
        })
        .collect();
    let mut board_poses: Vec<Option<BoardPose>> = Vec::with_capacity(boards.len());
    for (b, fit) in boards.iter().zip(board_fits.iter_mut()) {
        match initial_board_pose(&models[b.camera], b) {
            Ok(p) => board_poses.push(Some(p)),
            Err(e) => {
                fit.rejected = Some(format!("{e:#}"));
                board_poses.push(None);
            }
        }
    }
    for round in 0..MAX_ROUNDS + usize::from(options.refine_intrinsics) {
        let frames = usable(&views);
        ensure!(
            frames.len() >= MIN_FRAMES,
            "too few usable wand observations after rejecting outliers: {} frames, need at least {MIN_FRAMES}",
            frames.len()
        );
        let mut start = Vec::with_capacity(frames.len());
        let mut kept = Vec::with_capacity(frames.len());
        for (f, v) in &frames {
            match poses_by_frame[*f].or_else(|| triangulate_pose(&cameras, v, wand)) {
                Some(p) => {
                    start.push(p);
                    kept.push((*f, v.clone()));
                }
                None => {
                    for (c, _) in v {
                        views[*f][*c] = Err(Rejection::ReprojectionOutlier {
                            error_px: f64::INFINITY,
                            limit_px: 0.0,
                        });
                    }
                }
            }
        }
        if round == 0 {
            check_motion(&start, wand)?;
        }
        let frame_views: Vec<FrameViews> = kept.iter().map(|(_, v)| v.clone()).collect();
        let n_views: usize = frame_views.iter().map(Vec::len).sum();
        // Board views take part only while the intrinsics are refined.
        let active: Vec<usize> = if layout.n_intr > 0 {
            (0..boards.len())
                .filter(|i| board_fits[*i].rejected.is_none() && board_poses[*i].is_some())
                .collect()
        } else {
            Vec::new()
        };
        let active_boards: Vec<&BoardView> = active.iter().map(|i| &boards[*i]).collect();
        let board_start: Vec<BoardPose> = active.iter().filter_map(|i| board_poses[*i]).collect();
        progress(&format!(
            "bundle adjustment round {}: {} frames, {n_views} camera views, {} board views, {} camera parameters",
            round + 1,
            kept.len(),
            active.len(),
            layout.len()
        ));
        let problem = RigProblem {
            layout: layout.clone(),
            base: models,
            frames: &frame_views,
            wand,
            huber_px: options.huber_px,
            x: layout.pack(&cameras),
            anchors: RefCell::new(start.clone()),
            poses: start,
            boards: &active_boards,
            board_anchors: RefCell::new(board_start.clone()),
            board_poses: board_start,
            evaluations: RefCell::new(0),
        };
        let x0 = problem.x.clone();
        let mut problem = problem;
        problem.set_params(&x0);
        let (problem, report) = LevenbergMarquardt::new()
            .with_xtol(1e-12)
            .with_ftol(1e-12)
            .with_patience(200)
            .minimize(problem);
        let x = problem.x.clone();
        let cams = problem.cams(x.as_slice());
        let poses = problem.poses.clone();
        let solved_boards = problem.board_poses.clone();
        let evaluations = *problem.evaluations.borrow();
        for (c, cam) in cameras.iter_mut().enumerate() {
            cam.model = cams[c].model;
            cam.cam_from_cam0 = RigidTransform::from_parts(&cams[c].r, &cams[c].t);
        }
        // Outliers: views far above the overall error.
        let mut errs = Vec::new();
        for ((f, v), p) in kept.iter().zip(&poses) {
            poses_by_frame[*f] = Some(*p);
            for (c, px) in v {
                errs.push((*f, *c, view_rms(&cams[*c], px, p, wand)));
            }
        }
        let rms = (errs.iter().map(|e| e.2 * e.2).sum::<f64>() / errs.len() as f64).sqrt();
        let mut sorted: Vec<f64> = errs.iter().map(|e| e.2).collect();
        let limit = (OUTLIER_FACTOR * median(&mut sorted)).max(OUTLIER_FLOOR_PX);
        let mut rejected = 0;
        for (f, c, e) in &errs {
            if *e > limit {
                views[*f][*c] = Err(Rejection::ReprojectionOutlier {
                    error_px: *e,
                    limit_px: limit,
                });
                rejected += 1;
            }
        }
        for row in views.iter_mut() {
            if row.iter().filter(|r| r.is_ok()).count() == 1 {
                for r in row.iter_mut().filter(|r| r.is_ok()) {
                    *r = Err(Rejection::SingleCamera);
                }
            }
        }
        // Board views far above the boards' own error level (blur, a bent or moving board).
        let mut board_errs = Vec::with_capacity(active.len());
        for (i, p) in active.iter().zip(&solved_boards) {
            board_poses[*i] = Some(*p);
            let e = board_rms(&cams[boards[*i].camera].model, &boards[*i], p);
            board_fits[*i].rms_px = e;
            board_errs.push((*i, e));
        }
        let mut board_rms_px = f64::NAN;
        if !board_errs.is_empty() {
            let n_corners: usize = active.iter().map(|i| boards[*i].corners_px.len()).sum();
            board_rms_px = (board_errs
                .iter()
                .map(|(i, e)| e * e * boards[*i].corners_px.len() as f64)
                .sum::<f64>()
                / n_corners as f64)
                .sqrt();
            let mut sorted: Vec<f64> = board_errs.iter().map(|e| e.1).collect();
            let limit = (OUTLIER_FACTOR * median(&mut sorted)).max(OUTLIER_FLOOR_PX);
            for (i, e) in &board_errs {
                if *e > limit {
                    board_fits[*i].rejected =
                        Some(format!("reprojection outlier: {e:.2} px > {limit:.2} px"));
                    rejected += 1;
                }
            }
        }
        progress(&format!(
            "round {}: RMS {rms:.4} px over {n_views} views, boards {board_rms_px:.4} px over {} views, \
             {evaluations} evaluations ({:?}); {rejected} outlier views",
            round + 1,
            board_errs.len(),
            report.termination
        ));
        rounds.push(Round {
            views: n_views,
            rms_px: rms,
            board_views: board_errs.len(),
            board_rms_px,
            evaluations,
            termination: format!("{:?}", report.termination),
            rejected,
        });
        if rejected == 0 {
            if layout.n_intr == refined.n_intr {
                break;
            }
            layout = refined.clone();
            continue;
        }
        // The next round starts from this round's poses; rejected frames drop out.
        for (f, row) in views.iter().enumerate() {
            if row.iter().filter(|r| r.is_ok()).count() < 2 {
                poses_by_frame[f] = None;
            }
        }
    }
    // Final statistics on the used views.
    let cams: Vec<Cam> = cameras
        .iter()
        .map(|c| Cam {
            r: c.cam_from_cam0.rotation(),
            t: c.cam_from_cam0.translation_mm(),
            model: c.model,
        })
        .collect();
    let mut sum2 = vec![0.0; n_cam];
    let mut count = vec![0usize; n_cam];
    for (f, row) in views.iter().enumerate() {
        let Some(p) = poses_by_frame[f] else { continue };
        for (c, r) in row.iter().enumerate() {
            if let Ok(px) = r {
                let e = view_rms(&cams[c], px, &p, wand);
                sum2[c] += e * e;
                count[c] += 1;
            }
        }
    }
    for (f, row) in views.iter().enumerate() {
        if row.iter().filter(|r| r.is_ok()).count() < 2 {
            poses_by_frame[f] = None;
        }
    }
    Ok(WandSolution {
        cameras,
        initial,
        init_pairs,
        poses: poses_by_frame,
        views,
        rounds,
        per_camera_rms_px: sum2
            .iter()
            .zip(&count)
            .map(|(s, n)| if *n > 0 { (s / *n as f64).sqrt() } else { f64::NAN })
            .collect(),
        per_camera_views: count,
        boards: board_fits,
    })
}

/// The wand's LEDs of one frame triangulated freely (no wand constraint) with the calibrated
/// rig from the frame's used views, in camera 0's frame (mm). `None` when fewer than two
/// cameras saw the frame or an LED's rays do not meet.
pub fn free_leds_mm(
    sol: &WandSolution,
    row: &[std::result::Result<LedPixels, Rejection>],
    led_count: usize,
) -> Option<Vec<Vector3<f64>>> {
    let v: Vec<(usize, &LedPixels)> = row
        .iter()
        .enumerate()
        .filter_map(|(c, r)| r.as_ref().ok().map(|p| (c, p)))
        .collect();
    if v.len() < 2 {
        return None;
    }
    (0..led_count)
        .map(|k| {
            let rays: Vec<Ray> = v
                .iter()
                .map(|(c, px)| {
                    let cam = &sol.cameras[*c];
                    Ray::from_pixel(&cam.model, &cam.cam_from_cam0, px[k].x, px[k].y)
                })
                .collect();
            least_squares_rays(&rays).ok().map(|r| r.0)
        })
        .collect()
}

/// Wand length error per used frame (mm): both ends triangulated freely (no wand constraint)
/// with the calibrated rig from the frame's used views, minus the true length.
pub fn length_errors_mm(sol: &WandSolution, wand: &Wand) -> Vec<f64> {
    let last = wand.len() - 1;
    sol.views
        .iter()
        .filter_map(|row| free_leds_mm(sol, row, wand.len()))
        .map(|pts| (pts[last] - pts[0]).norm() - wand.length_mm())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_wand_recovers_a_line_with_known_spacing() {
        let wand = Wand::parse("0,120,300").unwrap();
        let e0 = Vector3::new(10.0, -20.0, 900.0);
        let d = Vector3::new(0.3, 0.5, -0.2).normalize();
        let pts: Vec<Vector3<f64>> = wand.leds_mm.iter().map(|s| e0 + d * *s).collect();
        let p = fit_wand(&pts, &wand).unwrap();
        assert!((p.end0_mm - e0).norm() < 1e-9 && (p.dir - d).norm() < 1e-12);
    }

    #[test]
    fn board_pose_is_recovered_and_its_residuals_vanish() {
        let model = CameraModel {
            intrinsics: Intrinsics {
                fx_px: 700.0,
                fy_px: 700.0,
                cx_px: 376.0,
                cy_px: 240.0,
            },
            distortion: Distortion {
                k1: -0.3,
                k2: 0.11,
                ..Distortion::NONE
            },
            image_size: irtrack_core::camera::ImageSize {
                width_px: 752,
                height_px: 480,
            },
        };
        let truth = BoardPose {
            r: Rotation3::from_euler_angles(0.3, -0.4, 0.1).into_inner(),
            t_mm: Vector3::new(-100.0, -60.0, 900.0),
        };
        let object_mm: Vec<Vector3<f64>> = (0..6)
            .flat_map(|r| (0..9).map(move |c| Vector3::new(c as f64 * 30.0, r as f64 * 30.0, 0.0)))
            .collect();
        let corners_px = object_mm
            .iter()
            .map(|p| model.project(&(truth.r * p + truth.t_mm)).unwrap())
            .collect();
        let view = BoardView {
            camera: 0,
            view: "v".into(),
            object_mm,
            corners_px,
        };
        let start = initial_board_pose(&model, &view).unwrap();
        assert!((start.t_mm - truth.t_mm).norm() < 0.5, "{start:?}");
        let off = start.perturbed(&[0.01, -0.02, 0.01, 5.0, -3.0, 20.0]);
        let got = solve_board(&model, &view, off, 1.0);
        assert!((got.t_mm - truth.t_mm).norm() < 1e-4, "{got:?}");
        assert!((got.r - truth.r).norm() < 1e-8);
        assert!(board_rms(&model, &view, &got) < 1e-6);
    }

    #[test]
    fn huber_residual_matches_the_loss() {
        let e = Vector2::new(3.0, 4.0);
        let r = robust(e, 1.0);
        // 2ρ(5) = 2·1·5 − 1 = 9.
        assert!((r.norm_squared() - 9.0).abs() < 1e-12);
        assert_eq!(robust(Vector2::new(0.3, 0.4), 1.0), Vector2::new(0.3, 0.4));
    }
}
