//! A simulated scenario: rig, trajectory, markers, sensor and clutter, rendered frame by frame.
//!
//! Rendering model (per camera, per frame):
//! - every marker is a Gaussian spot whose variance is the lens PSF's plus that of the LED's
//!   emitting disk as imaged (a disk of radius R has variance R²/4 per axis). Its centre is the
//!   marker projected through [`CameraModel::project`] (with lens distortion). The spot is
//!   integrated exactly over each pixel's area with `erf`, so sub-pixel positions are honest;
//! - motion blur sums `motion_blur_steps` such spots along the trajectory across the exposure;
//! - brightness falls with the square of the marker's distance from the camera;
//! - the signal in electrons gets shot noise (Gaussian with variance = mean) and read noise,
//!   is scaled so that the full well maps to the top code, rounded and clipped (saturation);
//! - fixed clutter (a lamp, a reflection) is added in the cameras it is declared for only.
//!
//! Pixels far from any source only see background; they are drawn from a precomputed table of
//! the background's code distribution, one 16-bit random index per pixel.
//!
//! [`CameraModel::project`]: irtrack_core::camera::CameraModel::project

use irtrack_core::camera::RigidTransform;
use irtrack_core::params::RigParams;
use nalgebra::{UnitQuaternion, Vector3};

use crate::SimError;
use crate::backdrop::Backdrop;
use crate::noise::{PixelRng, hash_words, normal_table, unit_from_hash};
use crate::rig::{CameraSpec, RigPreset, build_rig};
use crate::timing::{EXPOSURE_SUBSAMPLES, FrameTime, ROLLING_ITERATIONS, SimCameraTiming};
use crate::trajectory::{Orientation, Trajectory};

/// Most markers a scenario may carry (ground truth uses fixed-size storage): eight tools of
/// four LEDs plus loose LEDs.
pub const MAX_MARKERS: usize = 40;
/// Most cameras a scenario may have (visibility is a bit mask).
pub const MAX_CAMERAS: usize = 32;
/// Side of the largest window rendered around one marker or clutter source (px).
pub const MAX_WINDOW_PX: usize = 256;
/// A spot is rendered out to this many standard deviations.
const SPOT_EXTENT_SIGMA: f64 = 4.5;

/// Output pixel depth.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BitDepth {
    /// 8-bit samples (`u8`, 0..=255).
    Eight,
    /// 10-bit samples (`u16`, 0..=1023).
    Ten,
}

impl BitDepth {
    /// Largest code.
    pub fn max_code(self) -> u16 {
        match self {
            BitDepth::Eight => 255,
            BitDepth::Ten => 1023,
        }
    }
    /// Bits per pixel.
    pub fn bits(self) -> u8 {
        match self {
            BitDepth::Eight => 8,
            BitDepth::Ten => 10,
        }
    }
}

/// Sensor behind an IR-pass filter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorSpec {
    /// Electrons that map to the top code (saturation).
    pub full_well_e: f64,
    /// Read noise, electrons RMS.
    pub read_noise_e: f64,
    /// Ambient IR plus dark signal per pixel per exposure, electrons.
    pub background_e: f64,
    /// Exposure time; motion blur integrates over it.
    pub exposure_s: f64,
}

impl Default for SensorSpec {
    fn default() -> Self {
        SensorSpec {
            full_well_e: 10_000.0,
            read_noise_e: 12.0,
            background_e: 250.0,
            exposure_s: 0.002,
        }
    }
}

/// One IR LED.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerSpec {
    /// Offset from the trajectory point, mm: in camera 0's frame without an orientation
    /// trajectory (markers translate together), in the tool frame with one (the LED's position
    /// in the tool's definition; the tool turns about the trajectory point).
    pub offset_mm: Vector3<f64>,
    /// Radius of the emitting area (mm).
    pub radius_mm: f64,
    /// Lens point-spread function, standard deviation (px).
    pub psf_sigma_px: f64,
    /// Electrons collected over the whole spot at 1 m from the camera, per exposure.
    pub flux_e_at_1m: f64,
    /// The body the marker is on: 0 = the scenario's own trajectory and orientation,
    /// k ≥ 1 = `SimConfig::bodies[k − 1]` (several tools and loose LEDs in one scene).
    pub body: usize,
}

impl Default for MarkerSpec {
    fn default() -> Self {
        MarkerSpec {
            body: 0,
            offset_mm: Vector3::zeros(),
            radius_mm: 1.5,
            psf_sigma_px: 0.9,
            flux_e_at_1m: 50_000.0,
        }
    }
}

impl MarkerSpec {
    /// Flux that puts the spot's peak at `fraction` of the full well when the marker is at
    /// `distance_mm` from a camera of focal length `focal_px` (an auto-exposure stand-in).
    pub fn flux_for_peak(&self, fraction: f64, full_well_e: f64, distance_mm: f64, focal_px: f64) -> f64 {
        let sigma = self.sigma_px(distance_mm, focal_px);
        // Peak of a pixel-integrated Gaussian ≈ flux / (2πσ²) for σ ≳ 0.8 px.
        let peak_per_flux = 1.0 / (2.0 * core::f64::consts::PI * sigma * sigma);
        fraction * full_well_e / peak_per_flux * (distance_mm / 1000.0).powi(2)
    }

    /// Spot standard deviation at a distance (px).
    pub fn sigma_px(&self, distance_mm: f64, focal_px: f64) -> f64 {
        let disk_px = focal_px * self.radius_mm / distance_mm;
        (self.psf_sigma_px * self.psf_sigma_px + 0.25 * disk_px * disk_px).sqrt()
    }
}

/// A fixed ambient IR source seen by one camera only (lamp, specular reflection).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clutter {
    /// Camera that sees it.
    pub camera: usize,
    /// Centre column (px).
    pub u_px: f64,
    /// Centre row (px).
    pub v_px: f64,
    /// Gaussian width along x (px).
    pub sigma_x_px: f64,
    /// Gaussian width along y (px).
    pub sigma_y_px: f64,
    /// Electrons over the whole source per exposure.
    pub flux_e: f64,
}

/// A further rigid body moving on its own (another tool, a loose LED): markers with
/// `body = k` follow `bodies[k − 1]` the way body 0 follows the scenario's trajectory.
#[derive(Debug, Clone, PartialEq)]
pub struct Body {
    /// Path of the body's origin.
    pub trajectory: Trajectory,
    /// Its orientation; `None`: the markers only translate (a loose LED).
    pub orientation: Option<Orientation>,
}

/// Everything a scenario is made of.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Camera arrangement.
    pub rig: RigPreset,
    /// Focal length and image size of every camera.
    pub camera: CameraSpec,
    /// Path of the tool (its origin) over time.
    pub trajectory: Trajectory,
    /// Orientation of the rigid tool the markers belong to; `None`: the markers only translate.
    pub orientation: Option<Orientation>,
    /// The LEDs, positions on the tool.
    pub markers: Vec<MarkerSpec>,
    /// Further bodies (see [`Body`], [`SimConfig::add_tool`]); empty for one tool.
    pub bodies: Vec<Body>,
    /// Sensor: exposure, noise, saturation, bit depth.
    pub sensor: SensorSpec,
    /// Ambient bright spots that are not markers.
    pub clutter: Vec<Clutter>,
    /// Frames per second.
    pub fps: f64,
    /// Sub-exposures summed for motion blur; 1 disables it.
    pub motion_blur_steps: u32,
    /// Probability that a camera drops a frame.
    pub drop_rate: f64,
    /// Seed of every random draw (noise, drops).
    pub seed: u64,
    /// Depth the scenario is meant to be written at (both renderers work regardless).
    pub bit_depth: BitDepth,
    /// Realistic scene behind the markers (background level, floor, lamp); off by default.
    pub backdrop: Backdrop,
    /// Per-camera clock, shutter and timestamping ([`crate::timing`]): empty = every camera
    /// synchronous with a global shutter (the default), else one entry per camera.
    pub timing: Vec<SimCameraTiming>,
}

impl SimConfig {
    /// A preset rig looking at a circle of `radius_mm` around its workspace centre at
    /// `distance_mm`, one marker, default sensor, 120 fps, no clutter, no drops.
    pub fn preset(rig: RigPreset, distance_mm: f64, radius_mm: f64) -> Self {
        let centre = rig.workspace_centre_mm(distance_mm);
        SimConfig {
            trajectory: Trajectory::Circle {
                centre_mm: centre,
                radius_mm,
                normal: Vector3::new(0.3, 1.0, 0.4),
                period_s: 2.0,
            },
            rig,
            camera: CameraSpec::default(),
            orientation: None,
            markers: vec![MarkerSpec::default()],
            bodies: Vec::new(),
            sensor: SensorSpec::default(),
            clutter: Vec::new(),
            fps: 120.0,
            motion_blur_steps: 1,
            drop_rate: 0.0,
            seed: 1,
            bit_depth: BitDepth::Eight,
            backdrop: Backdrop::default(),
            timing: Vec::new(),
        }
    }

    /// Turns the scenario into a rigid multi-LED tool: one marker per LED of `leds_mm` (tool
    /// frame, mm; marker optics copied from the first marker) and the tool's orientation over
    /// time. The trajectory then moves the tool frame's origin.
    pub fn set_tool(&mut self, leds_mm: &[[f64; 3]], orientation: Orientation) {
        let template = self.markers.first().copied().unwrap_or_default();
        self.markers = leds_mm
            .iter()
            .map(|p| MarkerSpec {
                offset_mm: Vector3::from(*p),
                ..template
            })
            .collect();
        self.orientation = Some(orientation);
    }

    /// Adds a further rigid tool moving on its own: one marker per LED (optics copied from
    /// the first marker). Returns its body number (for [`SimConfig::body_pose`]).
    pub fn add_tool(
        &mut self,
        leds_mm: &[[f64; 3]],
        trajectory: Trajectory,
        orientation: Orientation,
    ) -> usize {
        self.add_body(leds_mm, trajectory, Some(orientation))
    }

    /// Adds a single LED on its own path; returns its body number.
    pub fn add_loose_led(&mut self, trajectory: Trajectory) -> usize {
        self.add_body(&[[0.0; 3]], trajectory, None)
    }

    fn add_body(
        &mut self,
        leds_mm: &[[f64; 3]],
        trajectory: Trajectory,
        orientation: Option<Orientation>,
    ) -> usize {
        let template = self.markers.first().copied().unwrap_or_default();
        self.bodies.push(Body {
            trajectory,
            orientation,
        });
        let body = self.bodies.len();
        self.markers.extend(leds_mm.iter().map(|p| MarkerSpec {
            offset_mm: Vector3::from(*p),
            body,
            ..template
        }));
        body
    }

    /// Pose of the tool frame at `t_s`: origin and rotation (tool to camera 0).
    pub fn tool_pose(&self, t_s: f64) -> (Vector3<f64>, UnitQuaternion<f64>) {
        let q = self
            .orientation
            .as_ref()
            .map_or_else(UnitQuaternion::identity, |o| o.rotation(t_s));
        (self.trajectory.position(t_s), q)
    }

    /// Pose of body `body` at `t_s` (0: [`SimConfig::tool_pose`]); `None` for an unknown body.
    pub fn body_pose(&self, body: usize, t_s: f64) -> Option<(Vector3<f64>, UnitQuaternion<f64>)> {
        if body == 0 {
            return Some(self.tool_pose(t_s));
        }
        let b = self.bodies.get(body - 1)?;
        let q = b
            .orientation
            .as_ref()
            .map_or_else(UnitQuaternion::identity, |o| o.rotation(t_s));
        Some((b.trajectory.position(t_s), q))
    }

    /// Position of `marker` (camera 0 frame) at `t_s`.
    pub fn marker_position(&self, marker: &MarkerSpec, t_s: f64) -> Vector3<f64> {
        if marker.body > 0
            && let Some((origin, q)) = self.body_pose(marker.body, t_s)
        {
            return origin + q * marker.offset_mm;
        }
        let origin = self.trajectory.position(t_s);
        match &self.orientation {
            // Without a tool the offset is already in camera 0's frame (kept bit-exact).
            None => origin + marker.offset_mm,
            Some(o) => origin + o.rotation(t_s) * marker.offset_mm,
        }
    }

    /// A ceiling lamp in camera 1 only: a large saturated spot near the top-left corner plus
    /// an elongated specular streak, both well off the rows a centred trajectory uses.
    pub fn add_glare(&mut self) {
        let w = self.camera.image_size.width_px as f64;
        let h = self.camera.image_size.height_px as f64;
        self.clutter.push(Clutter {
            camera: 1,
            u_px: 0.18 * w,
            v_px: 0.12 * h,
            sigma_x_px: 5.0,
            sigma_y_px: 5.0,
            flux_e: 3.0e6,
        });
        self.clutter.push(Clutter {
            camera: 1,
            u_px: 0.8 * w,
            v_px: 0.9 * h,
            sigma_x_px: 9.0,
            sigma_y_px: 2.0,
            flux_e: 6.0e5,
        });
    }
}

/// Where one marker is at one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarkerTruth {
    /// Position in camera 0's frame (mm).
    pub p_cam0_mm: Vector3<f64>,
    /// Bit `i` set when the marker's centre projects inside camera `i`'s image.
    pub visible_mask: u32,
}

/// Ground truth for one frame (fixed-size, no allocation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTruth {
    /// Frame number.
    pub index: u64,
    /// Mid-exposure time.
    pub t_s: f64,
    /// Valid entries of `markers`.
    pub marker_count: usize,
    /// Each marker's truth (the first `marker_count`).
    pub markers: [MarkerTruth; MAX_MARKERS],
    /// Tool frame origin (the trajectory point) in camera 0's frame, mm.
    pub tool_position_mm: Vector3<f64>,
    /// Tool orientation (tool to camera 0); identity without an orientation trajectory.
    pub tool_orientation: UnitQuaternion<f64>,
}

impl FrameTruth {
    /// The markers present in the scenario.
    pub fn markers(&self) -> &[MarkerTruth] {
        &self.markers[..self.marker_count]
    }

    /// Tool orientation as (w, x, y, z) with w ≥ 0 (the tracker's and RAPID's convention).
    pub fn tool_quaternion_wxyz(&self) -> [f64; 4] {
        let q = self.tool_orientation.quaternion();
        let s = if q.w < 0.0 { -1.0 } else { 1.0 };
        [s * q.w, s * q.i, s * q.j, s * q.k]
    }
}

impl MarkerTruth {
    /// Whether the marker is inside every one of `camera_count` images.
    pub fn visible_in_all(&self, camera_count: usize) -> bool {
        let all = if camera_count >= 32 {
            u32::MAX
        } else {
            (1u32 << camera_count) - 1
        };
        self.visible_mask & all == all
    }
}

/// What happened to one rendered frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameInfo {
    /// Frame number.
    pub index: u64,
    /// Camera index.
    pub camera: usize,
    /// Mid-exposure time in ns since the scenario's start.
    pub timestamp_ns: u64,
    /// The camera dropped this frame; the output buffer was left untouched.
    pub dropped: bool,
}

/// Integer pixel window, half-open.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Window {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
}

impl Window {
    fn around(u: f64, v: f64, rx: f64, ry: f64, w: usize, h: usize) -> Option<Window> {
        let x0 = (u - rx).floor().max(0.0);
        let y0 = (v - ry).floor().max(0.0);
        let x1 = ((u + rx).ceil() + 1.0).min(w as f64);
        let y1 = ((v + ry).ceil() + 1.0).min(h as f64);
        if !(x1 > x0 && y1 > y0) {
            return None;
        }
        Some(Window {
            x0: x0 as usize,
            y0: y0 as usize,
            x1: x1 as usize,
            y1: y1 as usize,
        })
    }
    fn union(&self, o: &Window) -> Window {
        Window {
            x0: self.x0.min(o.x0),
            y0: self.y0.min(o.y0),
            x1: self.x1.max(o.x1),
            y1: self.y1.max(o.y1),
        }
    }
    fn intersect(&self, o: &Window) -> Option<Window> {
        let w = Window {
            x0: self.x0.max(o.x0),
            y0: self.y0.max(o.y0),
            x1: self.x1.min(o.x1),
            y1: self.y1.min(o.y1),
        };
        (w.x1 > w.x0 && w.y1 > w.y0).then_some(w)
    }
}

/// One Gaussian light source in one camera's image for the frame being rendered.
#[derive(Debug, Clone, Copy)]
struct Spot {
    u: f64,
    v: f64,
    sx: f64,
    sy: f64,
    flux_e: f64,
    window: Window,
}

/// Per-depth lookup of background codes.
#[derive(Debug)]
struct CodeTables {
    u8_codes: Vec<u8>,
    u16_codes: Vec<u16>,
}

/// Scratch reused by every render call (sized once in [`Scenario::new`]).
#[derive(Debug)]
struct Scratch {
    spots: Vec<Spot>,
    windows: Vec<Window>,
    mean_e: Vec<f32>,
    gx: Vec<f64>,
    gy: Vec<f64>,
}

/// Output pixel types.
trait Code: Copy {
    fn from_code(c: u16) -> Self;
    fn code(self) -> u16;
}
impl Code for u8 {
    #[inline]
    fn from_code(c: u16) -> Self {
        c as u8
    }
    #[inline]
    fn code(self) -> u16 {
        u16::from(self)
    }
}
impl Code for u16 {
    #[inline]
    fn from_code(c: u16) -> Self {
        c
    }
    #[inline]
    fn code(self) -> u16 {
        self
    }
}

/// A ready-to-render scenario.
#[derive(Debug)]
pub struct Scenario {
    cfg: SimConfig,
    rig: RigParams,
    poses: Vec<RigidTransform>,
    normal: Vec<f32>,
    tables: CodeTables,
    scratch: Scratch,
    /// Per camera: the backdrop's static scene in 8-bit DN (empty without a backdrop).
    backdrop_dn: Vec<Vec<f32>>,
}

impl Scenario {
    /// Validates the configuration and precomputes rig, noise tables and scratch buffers.
    pub fn new(cfg: SimConfig) -> Result<Self, SimError> {
        let bad = |field, reason: String| Err(SimError::Config { field, reason });
        if !(cfg.fps > 0.0 && cfg.fps.is_finite()) {
            return bad("fps", format!("{} must be > 0", cfg.fps));
        }
        if !(0.0..1.0).contains(&cfg.drop_rate) {
            return bad("drop_rate", format!("{} must be in [0, 1)", cfg.drop_rate));
        }
        if cfg.motion_blur_steps == 0 || cfg.motion_blur_steps > 64 {
            return bad(
                "motion_blur_steps",
                format!("{} must be in 1..=64", cfg.motion_blur_steps),
            );
        }
        if cfg.markers.is_empty() || cfg.markers.len() > MAX_MARKERS {
            return bad(
                "markers",
                format!("{} markers; need 1..={MAX_MARKERS}", cfg.markers.len()),
            );
        }
        let s = &cfg.sensor;
        if !(s.full_well_e > 0.0 && s.read_noise_e >= 0.0 && s.background_e >= 0.0 && s.exposure_s >= 0.0) {
            return bad("sensor", format!("{s:?}: full well must be > 0, the rest >= 0"));
        }
        for m in &cfg.markers {
            if !(m.psf_sigma_px > 0.05 && m.radius_mm >= 0.0 && m.flux_e_at_1m >= 0.0) {
                return bad(
                    "markers",
                    format!("{m:?}: psf sigma must be > 0.05 px, radius and flux >= 0"),
                );
            }
        }
        cfg.trajectory.validate()?;
        if let Some(o) = &cfg.orientation {
            o.validate()?;
        }
        for b in &cfg.bodies {
            b.trajectory.validate()?;
            if let Some(o) = &b.orientation {
                o.validate()?;
            }
        }
        if let Some(m) = cfg.markers.iter().find(|m| m.body > cfg.bodies.len()) {
            return bad(
                "markers",
                format!(
                    "marker on body {} but only {} further bodies",
                    m.body,
                    cfg.bodies.len()
                ),
            );
        }
        let rig = build_rig(&cfg.rig, &cfg.camera)?;
        if rig.cameras.len() > MAX_CAMERAS {
            return bad(
                "rig",
                format!("{} cameras; at most {MAX_CAMERAS}", rig.cameras.len()),
            );
        }
        let size = rig.cameras[0].model.image_size;
        if rig.cameras.iter().any(|c| c.model.image_size != size) {
            return bad("rig", "all cameras must have the same image size".into());
        }
        if size.width_px == 0 || size.height_px == 0 {
            return bad("rig", "image size must be non-zero".into());
        }
        for c in &cfg.clutter {
            if c.camera >= rig.cameras.len() {
                return Err(SimError::NoSuchCamera {
                    camera: c.camera,
                    count: rig.cameras.len(),
                });
            }
            if !(c.sigma_x_px > 0.05 && c.sigma_y_px > 0.05 && c.flux_e >= 0.0) {
                return bad("clutter", format!("{c:?}: sigmas must be > 0.05 px, flux >= 0"));
            }
        }
        if !cfg.timing.is_empty() && cfg.timing.len() != rig.cameras.len() {
            return bad(
                "timing",
                format!(
                    "{} entries for {} cameras (none, or one per camera)",
                    cfg.timing.len(),
                    rig.cameras.len()
                ),
            );
        }
        for (c, t) in cfg.timing.iter().enumerate() {
            t.validate(c)?;
        }
        cfg.backdrop.validate()?;
        let backdrop_dn = if cfg.backdrop.is_active() {
            (0..rig.cameras.len())
                .map(|c| {
                    cfg.backdrop
                        .scene_dn(size.width_px as usize, size.height_px as usize, c, cfg.seed)
                })
                .collect()
        } else {
            Vec::new()
        };
        let poses = rig.cameras.iter().map(|c| c.cam_from_cam0).collect();
        let normal = normal_table();
        let tables = CodeTables {
            u8_codes: background_codes(&normal, s, BitDepth::Eight)
                .iter()
                .map(|c| *c as u8)
                .collect(),
            u16_codes: background_codes(&normal, s, BitDepth::Ten),
        };
        let max_steps = cfg
            .timing
            .iter()
            .map(|t| blur_steps(cfg.motion_blur_steps, t))
            .fold(cfg.motion_blur_steps, u32::max);
        let spots_cap = cfg.markers.len() * max_steps as usize + cfg.clutter.len();
        let scratch = Scratch {
            spots: Vec::with_capacity(spots_cap),
            windows: Vec::with_capacity(cfg.markers.len() + cfg.clutter.len()),
            mean_e: vec![0.0; MAX_WINDOW_PX * MAX_WINDOW_PX],
            gx: vec![0.0; MAX_WINDOW_PX + 1],
            gy: vec![0.0; MAX_WINDOW_PX + 1],
        };
        Ok(Scenario {
            cfg,
            rig,
            poses,
            normal,
            tables,
            scratch,
            backdrop_dn,
        })
    }

    /// The ground-truth rig.
    pub fn rig(&self) -> &RigParams {
        &self.rig
    }

    /// The configuration the scenario was built from.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Replaces the marker trajectory (the simulated robot cell moves the LED where the robot
    /// really put it, frame by frame). Everything else stays as built.
    pub fn set_trajectory(&mut self, trajectory: Trajectory) -> Result<(), SimError> {
        trajectory.validate()?;
        self.cfg.trajectory = trajectory;
        Ok(())
    }

    /// Replaces the tool's orientation (the simulated robot cell turns the tool as the robot
    /// really turned its flange, frame by frame); the scenario must render a tool
    /// ([`SimConfig::set_tool`]).
    pub fn set_tool_orientation(&mut self, orientation: Orientation) -> Result<(), SimError> {
        orientation.validate()?;
        if self.cfg.orientation.is_none() {
            return Err(SimError::Config {
                field: "orientation",
                reason: "the scenario renders no tool".into(),
            });
        }
        self.cfg.orientation = Some(orientation);
        Ok(())
    }

    /// Number of cameras of the rig.
    pub fn camera_count(&self) -> usize {
        self.rig.cameras.len()
    }

    /// (width, height) in pixels, the same for every camera.
    pub fn image_size(&self) -> (u32, u32) {
        let s = self.rig.cameras[0].model.image_size;
        (s.width_px, s.height_px)
    }

    /// Mid-exposure time of a frame.
    pub fn time_s(&self, index: u64) -> f64 {
        index as f64 / self.cfg.fps
    }

    /// Timestamp of a frame in ns since start.
    pub fn timestamp_ns(&self, index: u64) -> u64 {
        (index as f64 * 1e9 / self.cfg.fps).round() as u64
    }

    /// Camera `camera`'s timing (the synchronous default when the scenario has none).
    pub fn camera_timing(&self, camera: usize) -> SimCameraTiming {
        self.cfg.timing.get(camera).copied().unwrap_or_default()
    }

    /// When `camera` exposed its frame of slot `index` (middle of row 0's exposure) and the
    /// timestamp it reports (docs/simulator.md "Camera timing").
    pub fn frame_time(&self, index: u64, camera: usize) -> FrameTime {
        crate::timing::frame_time(
            &self.camera_timing(camera),
            self.cfg.fps,
            self.cfg.seed,
            index,
            camera,
        )
    }

    /// Ground truth at any instant `t_ns` of the scenario's clock (the clock the reported
    /// timestamps are on): what a tracker's "position at reference instant t" is compared
    /// with. `index` of the result is the nearest slot (0 before the start).
    pub fn truth_at(&self, t_ns: f64) -> FrameTruth {
        let index = (t_ns * self.cfg.fps / 1e9).round().max(0.0) as u64;
        self.truth_at_s(t_ns * 1e-9, index)
    }

    /// Whether `camera` drops frame `index` (deterministic in the seed).
    pub fn is_dropped(&self, index: u64, camera: usize) -> bool {
        self.cfg.drop_rate > 0.0
            && unit_from_hash(hash_words(&[self.cfg.seed, index, camera as u64, 0x4452_4f50]))
                < self.cfg.drop_rate
    }

    /// Marker positions (camera 0 frame) and visibility at frame `index`.
    pub fn truth(&self, index: u64) -> FrameTruth {
        self.truth_at_s(self.time_s(index), index)
    }

    fn truth_at_s(&self, t_s: f64, index: u64) -> FrameTruth {
        let (tool_position_mm, tool_orientation) = self.cfg.tool_pose(t_s);
        let empty = MarkerTruth {
            p_cam0_mm: Vector3::zeros(),
            visible_mask: 0,
        };
        let mut out = FrameTruth {
            index,
            t_s,
            marker_count: self.cfg.markers.len(),
            markers: [empty; MAX_MARKERS],
            tool_position_mm,
            tool_orientation,
        };
        for (m, spec) in self.cfg.markers.iter().enumerate() {
            let p = self.cfg.marker_position(spec, t_s);
            let mut mask = 0u32;
            for (i, cam) in self.rig.cameras.iter().enumerate() {
                let pc = self.poses[i].apply(&p);
                if let Ok(px) = cam.model.project(&pc)
                    && cam.model.contains_px(&px)
                {
                    mask |= 1 << i;
                }
            }
            out.markers[m] = MarkerTruth {
                p_cam0_mm: p,
                visible_mask: mask,
            };
        }
        out
    }

    /// Renders an 8-bit frame into `out` (width × height, row-major, no padding).
    pub fn render_u8(&mut self, index: u64, camera: usize, out: &mut [u8]) -> Result<FrameInfo, SimError> {
        let max = BitDepth::Eight.max_code();
        self.render_into(index, camera, out, max, Which::Eight)
    }

    /// Renders a 10-bit frame (codes 0..=1023) into `out`.
    pub fn render_u16(&mut self, index: u64, camera: usize, out: &mut [u16]) -> Result<FrameInfo, SimError> {
        let max = BitDepth::Ten.max_code();
        self.render_into(index, camera, out, max, Which::Ten)
    }

    fn render_into<P: Code>(
        &mut self,
        index: u64,
        camera: usize,
        out: &mut [P],
        max_code: u16,
        which: Which,
    ) -> Result<FrameInfo, SimError> {
        let count = self.camera_count();
        if camera >= count {
            return Err(SimError::NoSuchCamera { camera, count });
        }
        let (w, h) = self.image_size();
        let (w, h) = (w as usize, h as usize);
        if out.len() != w * h {
            return Err(SimError::BufferSize {
                needed: w * h,
                have: out.len(),
            });
        }
        // Today's nominal stamp for a synchronous camera; else the camera's own (a stamp
        // before the scenario's start saturates at 0: see `frame_time` for the signed one).
        let timestamp_ns = if self.camera_timing(camera).is_synchronous() {
            self.timestamp_ns(index)
        } else {
            self.frame_time(index, camera).reported_ns.max(0) as u64
        };
        let info = FrameInfo {
            index,
            camera,
            timestamp_ns,
            dropped: false,
        };
        if self.is_dropped(index, camera) {
            return Ok(FrameInfo {
                dropped: true,
                ..info
            });
        }
        self.collect_spots(index, camera, w, h)?;

        let mut rng = PixelRng::new(self.cfg.seed, index, camera as u64);
        // Background everywhere, from the precomputed code distribution.
        match which {
            Which::Eight => fill_background(out, &self.tables.u8_codes, &mut rng, |c: u8| c as u16),
            Which::Ten => fill_background(out, &self.tables.u16_codes, &mut rng, |c: u16| c),
        }
        let gain = max_code as f64 / self.cfg.sensor.full_well_e;
        let read_var = (self.cfg.sensor.read_noise_e * self.cfg.sensor.read_noise_e) as f32;
        let bg = self.cfg.sensor.background_e as f32;
        let sc = &mut self.scratch;
        for wi in 0..sc.windows.len() {
            let win = sc.windows[wi];
            let ww = win.x1 - win.x0;
            let wh = win.y1 - win.y0;
            let mean = &mut sc.mean_e[..ww * wh];
            mean.fill(bg);
            for spot in &sc.spots {
                let Some(iw) = win.intersect(&spot.window) else {
                    continue;
                };
                pixel_integrals(&mut sc.gx, iw.x0, iw.x1, spot.u, spot.sx);
                pixel_integrals(&mut sc.gy, iw.y0, iw.y1, spot.v, spot.sy);
                for y in iw.y0..iw.y1 {
                    let fy = spot.flux_e * sc.gy[y - iw.y0];
                    let row = &mut mean[(y - win.y0) * ww..(y - win.y0 + 1) * ww];
                    for x in iw.x0..iw.x1 {
                        row[x - win.x0] += (fy * sc.gx[x - iw.x0]) as f32;
                    }
                }
            }
            for y in win.y0..win.y1 {
                let src = &mean[(y - win.y0) * ww..(y - win.y0 + 1) * ww];
                let dst = &mut out[y * w + win.x0..y * w + win.x1];
                for (d, m) in dst.iter_mut().zip(src) {
                    let z = self.normal[rng.next_u16() as usize];
                    let e = m + (m + read_var).sqrt() * z;
                    let c = (e as f64 * gain).round().clamp(0.0, max_code as f64);
                    *d = P::from_code(c as u16);
                }
            }
        }
        if let Some(scene) = self.backdrop_dn.get(camera) {
            let scale = f32::from(max_code) / 255.0;
            let noise = self.cfg.backdrop.noise_dn as f32 * scale;
            let max = f32::from(max_code);
            for (d, s) in out.iter_mut().zip(scene) {
                let z = self.normal[rng.next_u16() as usize];
                let v = (f32::from(d.code()) + s * scale + noise * z)
                    .round()
                    .clamp(0.0, max);
                *d = P::from_code(v as u16);
            }
        }
        Ok(info)
    }

    /// Fills `scratch.spots` and `scratch.windows` for one camera and frame.
    fn collect_spots(&mut self, index: u64, camera: usize, w: usize, h: usize) -> Result<(), SimError> {
        let timing = self.camera_timing(camera);
        // Middle of row 0's exposure (exactly `index / fps` for a synchronous camera).
        let t_mid = if timing.is_synchronous() {
            self.time_s(index)
        } else {
            self.frame_time(index, camera).exposure_s
        };
        let line_time_s = timing.line_time_ns * 1e-9;
        let sc = &mut self.scratch;
        sc.spots.clear();
        sc.windows.clear();
        let model = &self.rig.cameras[camera].model;
        let pose = &self.poses[camera];
        let steps = blur_steps(self.cfg.motion_blur_steps, &timing) as usize;
        let exp = if timing.exposure_ns > 0.0 {
            timing.exposure_ns * 1e-9
        } else {
            self.cfg.sensor.exposure_s
        };
        for spec in &self.cfg.markers {
            let mut win: Option<Window> = None;
            for k in 0..steps {
                let t = if steps == 1 {
                    t_mid
                } else {
                    t_mid + exp * ((k as f64 + 0.5) / steps as f64 - 0.5)
                };
                let mut p_cam = pose.apply(&self.cfg.marker_position(spec, t));
                let Ok(mut c) = model.project(&p_cam) else {
                    continue;
                };
                if line_time_s > 0.0 {
                    // Rolling shutter: the spot is where the LED was when its row was exposed;
                    // the row depends on that position, so iterate (converges in 2–3 steps).
                    for _ in 0..ROLLING_ITERATIONS {
                        let t_row = t + c.y.max(0.0) * line_time_s;
                        p_cam = pose.apply(&self.cfg.marker_position(spec, t_row));
                        match model.project(&p_cam) {
                            Ok(next) => c = next,
                            Err(_) => break,
                        }
                    }
                }
                let dist_mm = p_cam.norm();
                let sigma = spec.sigma_px(p_cam.z, model.intrinsics.fx_px);
                let r = SPOT_EXTENT_SIGMA * sigma + 1.0;
                let Some(sw) = Window::around(c.x, c.y, r, r, w, h) else {
                    continue;
                };
                let flux = spec.flux_e_at_1m * (1000.0 / dist_mm).powi(2) / steps as f64;
                sc.spots.push(Spot {
                    u: c.x,
                    v: c.y,
                    sx: sigma,
                    sy: sigma,
                    flux_e: flux,
                    window: sw,
                });
                win = Some(win.map_or(sw, |a| a.union(&sw)));
            }
            if let Some(win) = win {
                sc.windows.push(win);
            }
        }
        for c in self.cfg.clutter.iter().filter(|c| c.camera == camera) {
            let rx = SPOT_EXTENT_SIGMA * c.sigma_x_px + 1.0;
            let ry = SPOT_EXTENT_SIGMA * c.sigma_y_px + 1.0;
            if let Some(sw) = Window::around(c.u_px, c.v_px, rx, ry, w, h) {
                sc.spots.push(Spot {
                    u: c.u_px,
                    v: c.v_px,
                    sx: c.sigma_x_px,
                    sy: c.sigma_y_px,
                    flux_e: c.flux_e,
                    window: sw,
                });
                sc.windows.push(sw);
            }
        }
        for win in &sc.windows {
            let (ww, wh) = (win.x1 - win.x0, win.y1 - win.y0);
            if ww > MAX_WINDOW_PX || wh > MAX_WINDOW_PX {
                return Err(SimError::WindowTooLarge {
                    width_px: ww,
                    height_px: wh,
                    max_px: MAX_WINDOW_PX,
                });
            }
        }
        Ok(())
    }
}

/// Sub-exposures rendered for a camera: its own exposure time asks for at least
/// [`EXPOSURE_SUBSAMPLES`].
fn blur_steps(configured: u32, timing: &SimCameraTiming) -> u32 {
    if timing.exposure_ns > 0.0 {
        configured.max(EXPOSURE_SUBSAMPLES)
    } else {
        configured
    }
}

#[derive(Debug, Clone, Copy)]
enum Which {
    Eight,
    Ten,
}

fn fill_background<P: Code, T: Copy>(
    out: &mut [P],
    table: &[T],
    rng: &mut PixelRng,
    to_code: impl Fn(T) -> u16,
) {
    for px in out.iter_mut() {
        *px = P::from_code(to_code(table[rng.next_u16() as usize]));
    }
}

/// Code distribution of a background pixel: one code per normal-table entry.
fn background_codes(normal: &[f32], s: &SensorSpec, depth: BitDepth) -> Vec<u16> {
    let max = depth.max_code() as f64;
    let gain = max / s.full_well_e;
    let sd = (s.background_e + s.read_noise_e * s.read_noise_e).sqrt();
    normal
        .iter()
        .map(|z| ((s.background_e + sd * *z as f64) * gain).round().clamp(0.0, max) as u16)
        .collect()
}

/// Fraction of a unit 1-D Gaussian (centre `c`, sd `s`) falling in each pixel `i0..i1`
/// (pixel `i` spans `[i - 0.5, i + 0.5]`), written to `out[0..i1-i0]`.
fn pixel_integrals(out: &mut [f64], i0: usize, i1: usize, c: f64, s: f64) {
    let k = 1.0 / (s * core::f64::consts::SQRT_2);
    let mut prev = libm::erf((i0 as f64 - 0.5 - c) * k);
    for (j, i) in (i0..i1).enumerate() {
        let next = libm::erf((i as f64 + 0.5 - c) * k);
        out[j] = 0.5 * (next - prev);
        prev = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn quiet_config() -> SimConfig {
        let mut cfg = SimConfig::preset(RigPreset::Parallel { baseline_mm: 50.0 }, 800.0, 60.0);
        cfg.seed = 42;
        cfg
    }

    /// Background-subtracted intensity-weighted centroid in a window around `(u, v)`.
    fn centroid(img: &[u16], w: usize, u: f64, v: f64, bg: f64) -> (f64, f64, f64) {
        let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
        for y in (v as usize - 8)..(v as usize + 9) {
            for x in (u as usize - 8)..(u as usize + 9) {
                let d = img[y * w + x] as f64 - bg;
                s += d;
                sx += d * x as f64;
                sy += d * y as f64;
            }
        }
        (sx / s, sy / s, s)
    }

    #[test]
    fn spot_centroid_is_sub_pixel_accurate_and_flux_is_conserved() {
        let mut sc = Scenario::new(quiet_config()).unwrap();
        let (w, h) = sc.image_size();
        let mut img = vec![0u16; (w * h) as usize];
        let gain = 1023.0 / sc.config().sensor.full_well_e;
        let bg = sc.config().sensor.background_e * gain;
        let (mut sum_sq, mut bias_x, mut bias_y, mut n) = (0.0, 0.0, 0.0, 0.0);
        for index in 0..40 {
            for cam in 0..2 {
                sc.render_u16(index, cam, &mut img).unwrap();
                let truth = sc.truth(index);
                let p = sc.rig().cameras[cam]
                    .cam_from_cam0
                    .apply(&truth.markers()[0].p_cam0_mm);
                let px = sc.rig().cameras[cam].model.project(&p).unwrap();
                let (cx, cy, sum) = centroid(&img, w as usize, px.x, px.y, bg);
                sum_sq += (cx - px.x).powi(2) + (cy - px.y).powi(2);
                bias_x += cx - px.x;
                bias_y += cy - px.y;
                n += 1.0;
                let expected = sc.config().markers[0].flux_e_at_1m * (1000.0 / p.norm()).powi(2) * gain;
                assert!((sum / expected - 1.0).abs() < 0.03, "flux {sum} vs {expected}");
            }
        }
        // The crude 17×17 centroid sums ~2 DN of background noise per pixel, ~0.02 px per axis.
        let rms = (sum_sq / n).sqrt();
        assert!(rms < 0.04, "centroid RMS error {rms} px");
        assert!(
            (bias_x / n).abs() < 0.01 && (bias_y / n).abs() < 0.01,
            "bias {} {}",
            bias_x / n,
            bias_y / n
        );
    }

    #[test]
    fn same_frame_regardless_of_order_and_seed_matters() {
        let mut a = Scenario::new(quiet_config()).unwrap();
        let mut b = Scenario::new(quiet_config()).unwrap();
        let (w, h) = a.image_size();
        let n = (w * h) as usize;
        let (mut fa, mut fb) = (vec![0u8; n], vec![0u8; n]);
        a.render_u8(5, 1, &mut fa).unwrap();
        b.render_u8(9, 0, &mut fb).unwrap();
        b.render_u8(5, 1, &mut fb).unwrap();
        assert_eq!(fa, fb);
        let mut cfg = quiet_config();
        cfg.seed = 43;
        let mut c = Scenario::new(cfg).unwrap();
        c.render_u8(5, 1, &mut fb).unwrap();
        assert_ne!(fa, fb);
    }

    #[test]
    fn saturation_clips_at_top_code() {
        let mut cfg = quiet_config();
        cfg.markers[0].flux_e_at_1m *= 50.0;
        let mut sc = Scenario::new(cfg).unwrap();
        let (w, h) = sc.image_size();
        let mut img = vec![0u8; (w * h) as usize];
        sc.render_u8(0, 0, &mut img).unwrap();
        let saturated = img.iter().filter(|v| **v == 255).count();
        assert!(saturated >= 9, "{saturated} saturated pixels");
    }

    #[test]
    fn glare_appears_in_camera_one_only() {
        let mut cfg = quiet_config();
        cfg.add_glare();
        let mut sc = Scenario::new(cfg).unwrap();
        let (w, h) = sc.image_size();
        let mut img = vec![0u8; (w * h) as usize];
        let lamp = sc.config().clutter[0];
        let at = (lamp.v_px.round() as usize) * w as usize + lamp.u_px.round() as usize;
        sc.render_u8(0, 1, &mut img).unwrap();
        assert_eq!(img[at], 255);
        sc.render_u8(0, 0, &mut img).unwrap();
        assert!(img[at] < 30, "{}", img[at]);
    }

    #[test]
    fn drops_are_deterministic_and_near_the_rate() {
        let mut cfg = quiet_config();
        cfg.drop_rate = 0.1;
        let mut sc = Scenario::new(cfg).unwrap();
        let dropped = (0..2000).filter(|i| sc.is_dropped(*i, 0)).count();
        assert!((150..250).contains(&dropped), "{dropped}");
        let (w, h) = sc.image_size();
        let mut img = vec![7u8; (w * h) as usize];
        let i = (0..2000).find(|i| sc.is_dropped(*i, 1)).unwrap();
        let info = sc.render_u8(i, 1, &mut img).unwrap();
        assert!(info.dropped);
        assert!(
            img.iter().all(|v| *v == 7),
            "dropped frame must leave the buffer untouched"
        );
    }

    #[test]
    fn motion_blur_stretches_the_spot_along_the_motion() {
        let mut cfg = quiet_config();
        // 1 m/s horizontally, 20 ms exposure: a 20 mm (~17 px) streak at 800 mm.
        cfg.trajectory = Trajectory::Line {
            from_mm: Vector3::new(-200.0, 0.0, 800.0),
            to_mm: Vector3::new(200.0, 0.0, 800.0),
            // Peak speed of the cosine-eased line is length·π/period.
            period_s: 400.0 * std::f64::consts::PI / 1000.0,
        };
        cfg.sensor.exposure_s = 0.02;
        cfg.motion_blur_steps = 16;
        let mut sc = Scenario::new(cfg).unwrap();
        let (w, h) = sc.image_size();
        let mut img = vec![0u8; (w * h) as usize];
        // Quarter period: the middle of the line, full speed.
        let idx = (sc.config().fps * 0.25 * 400.0 * std::f64::consts::PI / 1000.0).round() as u64;
        sc.render_u8(idx, 0, &mut img).unwrap();
        let row = |y: usize| {
            img[y * w as usize..(y + 1) * w as usize]
                .iter()
                .filter(|v| **v > 20)
                .count()
        };
        let wide = (0..h as usize).map(row).max().unwrap();
        assert!(wide >= 12, "streak only {wide} px wide");
    }

    #[test]
    fn bad_inputs_are_errors() {
        let mut sc = Scenario::new(quiet_config()).unwrap();
        let mut small = vec![0u8; 10];
        assert!(matches!(
            sc.render_u8(0, 0, &mut small),
            Err(SimError::BufferSize { .. })
        ));
        let mut ok = vec![0u8; 640 * 480];
        assert!(matches!(
            sc.render_u8(0, 2, &mut ok),
            Err(SimError::NoSuchCamera { camera: 2, count: 2 })
        ));
        let mut cfg = quiet_config();
        cfg.fps = 0.0;
        assert!(Scenario::new(cfg).is_err());
        let mut cfg = quiet_config();
        cfg.clutter.push(Clutter {
            camera: 5,
            u_px: 1.0,
            v_px: 1.0,
            sigma_x_px: 1.0,
            sigma_y_px: 1.0,
            flux_e: 1.0,
        });
        assert!(matches!(Scenario::new(cfg), Err(SimError::NoSuchCamera { .. })));
    }

    #[test]
    fn rotating_tool_truth_is_rigid_and_rendered_where_projected() {
        let mut cfg = SimConfig::preset(
            RigPreset::Convergent {
                distance_mm: 1000.0,
                angle_deg: 90.0,
            },
            1000.0,
            60.0,
        );
        let leds = [
            [0.0, 0.0, 0.0],
            [99.0, 0.0, 0.0],
            [3.0, 85.0, 0.0],
            [62.0, 11.0, 32.0],
        ];
        cfg.set_tool(
            &leds,
            Orientation::Wobble {
                base: UnitQuaternion::from_euler_angles(0.2, -0.5, 0.8),
                amplitude_deg: Vector3::new(40.0, 30.0, 50.0),
                period_s: Vector3::new(1.7, 2.3, 3.1),
                phase_rad: Vector3::new(0.0, 1.0, 2.0),
            },
        );
        let mut sc = Scenario::new(cfg).unwrap();
        let (w, h) = sc.image_size();
        let mut img = vec![0u8; (w * h) as usize];
        let mut turned_deg: f64 = 0.0;
        for index in (0..240).step_by(20) {
            let t = sc.truth(index);
            assert_eq!(t.marker_count, 4);
            turned_deg = turned_deg.max(
                t.tool_orientation
                    .angle_to(&sc.truth(0).tool_orientation)
                    .to_degrees(),
            );
            for (i, m) in t.markers().iter().enumerate() {
                let expect = t.tool_position_mm + t.tool_orientation * Vector3::from(leds[i]);
                assert!((m.p_cam0_mm - expect).norm() < 1e-9);
            }
            let q = t.tool_quaternion_wxyz();
            assert!(q[0] >= 0.0 && (q.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-12);
            for cam in 0..2 {
                sc.render_u8(index, cam, &mut img).unwrap();
                for m in t.markers() {
                    let pc = sc.rig().cameras[cam].cam_from_cam0.apply(&m.p_cam0_mm);
                    let px = sc.rig().cameras[cam].model.project(&pc).unwrap();
                    let at = px.y.round() as usize * w as usize + px.x.round() as usize;
                    assert!(img[at] > 60, "frame {index} cam {cam}: {} at {px:?}", img[at]);
                }
            }
        }
        assert!(turned_deg > 30.0, "tool turned only {turned_deg}°");
    }

    /// 1 m/s along +x at 800 mm (linear, so the speed is constant), LED at the image centre
    /// row at 0.5 s.
    fn moving_config() -> SimConfig {
        let mut cfg = quiet_config();
        cfg.trajectory = Trajectory::Samples(vec![
            (0.0, Vector3::new(-600.0, 0.0, 800.0)),
            (1.2, Vector3::new(600.0, 0.0, 800.0)),
        ]);
        cfg
    }

    fn project(sc: &Scenario, cam: usize, t_s: f64) -> nalgebra::Point2<f64> {
        let p = sc.config().marker_position(&sc.config().markers[0], t_s);
        let pc = sc.rig().cameras[cam].cam_from_cam0.apply(&p);
        let px = sc.rig().cameras[cam].model.project(&pc).unwrap();
        nalgebra::Point2::new(px.x, px.y)
    }

    fn render_centroid(sc: &mut Scenario, index: u64, cam: usize, near: nalgebra::Point2<f64>) -> (f64, f64) {
        let (w, h) = sc.image_size();
        let mut img = vec![0u16; (w * h) as usize];
        sc.render_u16(index, cam, &mut img).unwrap();
        let bg = sc.config().sensor.background_e * 1023.0 / sc.config().sensor.full_well_e;
        let (x, y, _) = centroid(&img, w as usize, near.x, near.y, bg);
        (x, y)
    }

    #[test]
    fn rolling_shutter_renders_the_led_where_it_was_when_its_row_was_exposed() {
        let line_time_ns = 15_000.0;
        let mut cfg = moving_config();
        cfg.timing = vec![
            SimCameraTiming {
                line_time_ns,
                ..SimCameraTiming::default()
            },
            SimCameraTiming::default(),
        ];
        let mut rolling = Scenario::new(cfg).unwrap();
        let mut global = Scenario::new(moving_config()).unwrap();
        let index = 60; // 0.5 s
        let t0 = index as f64 / 120.0;
        // The row instant solved independently: a fixed point iterated to convergence.
        let mut at = project(&rolling, 0, t0);
        for _ in 0..20 {
            at = project(&rolling, 0, t0 + at.y * line_time_ns * 1e-9);
        }
        let at_t0 = project(&rolling, 0, t0);
        let (rx, ry) = render_centroid(&mut rolling, index, 0, at);
        let (gx, gy) = render_centroid(&mut global, index, 0, at_t0);
        assert!(
            (rx - at.x).abs() < 0.05 && (ry - at.y).abs() < 0.05,
            "rolling centroid ({rx}, {ry}) vs row-instant projection {at:?}"
        );
        // The shift against the global shutter: speed in the image × row × line time.
        let speed_px_s = (project(&rolling, 0, t0 + 1e-3).x - project(&rolling, 0, t0 - 1e-3).x) / 2e-3;
        let expected_px = speed_px_s * at.y * line_time_ns * 1e-9;
        assert!(expected_px > 2.5, "test scene too slow: {expected_px} px");
        println!(
            "rolling: row {:.1}, shift {:.3} px expected, {:.3} px rendered, centroid error ({:.3}, {:.3}) px",
            at.y,
            expected_px,
            rx - gx,
            rx - at.x,
            ry - at.y
        );
        assert!(
            ((rx - gx) - expected_px).abs() < 0.08,
            "rolling − global = {} px, expected {expected_px} px",
            rx - gx
        );
        assert!((ry - gy).abs() < 0.05, "the row barely changes: {ry} vs {gy}");
        // Camera 1 stays global: the same frame as the synchronous scenario's.
        let (w, h) = rolling.image_size();
        let (mut a, mut b) = (vec![0u8; (w * h) as usize], vec![0u8; (w * h) as usize]);
        rolling.render_u8(index, 1, &mut a).unwrap();
        global.render_u8(index, 1, &mut b).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn phase_renders_the_led_at_the_cameras_own_instant_and_stamps_it() {
        let phase_ns = 3_100_000.0;
        let mut cfg = moving_config();
        cfg.timing = vec![
            SimCameraTiming::default(),
            SimCameraTiming {
                phase_ns,
                ts_offset_ns: 500_000.0,
                ..SimCameraTiming::default()
            },
        ];
        let mut sc = Scenario::new(cfg).unwrap();
        let index = 60;
        let ft = sc.frame_time(index, 1);
        assert!((ft.exposure_s - (0.5 + phase_ns * 1e-9)).abs() < 1e-12);
        let expect = project(&sc, 1, ft.exposure_s);
        let (x, y) = render_centroid(&mut sc, index, 1, expect);
        assert!((x - expect.x).abs() < 0.05 && (y - expect.y).abs() < 0.05);
        // 3.1 ms at ~850 px/s is ~2.6 px from where the nominal instant would put it.
        assert!((x - project(&sc, 1, 0.5).x).abs() > 2.0);
        let (w, h) = sc.image_size();
        let mut img = vec![0u8; (w * h) as usize];
        let info = sc.render_u8(index, 1, &mut img).unwrap();
        assert_eq!(info.timestamp_ns, 500_000_000 + 3_100_000 + 500_000);
        assert_eq!(
            sc.render_u8(index, 0, &mut img).unwrap().timestamp_ns,
            500_000_000
        );
        // Truth at any instant: the camera-1 exposure's truth is the trajectory there.
        let t = sc.truth_at(ft.exposure_s * 1e9);
        assert!((t.markers()[0].p_cam0_mm.x - (-600.0 + 1000.0 * ft.exposure_s)).abs() < 1e-6);
    }

    #[test]
    fn jitter_changes_timestamps_only_and_exposure_blurs() {
        let mut cfg = moving_config();
        cfg.timing = vec![
            SimCameraTiming {
                ts_jitter_ns: 200_000.0,
                ..SimCameraTiming::default()
            };
            2
        ];
        let mut jittery = Scenario::new(cfg.clone()).unwrap();
        let mut plain = Scenario::new(moving_config()).unwrap();
        let (w, h) = plain.image_size();
        let (mut a, mut b) = (vec![0u8; (w * h) as usize], vec![0u8; (w * h) as usize]);
        let mut moved = 0;
        for index in 0..20 {
            let ia = jittery.render_u8(index, 1, &mut a).unwrap();
            let ib = plain.render_u8(index, 1, &mut b).unwrap();
            assert_eq!(a, b, "jitter must not move the exposure");
            let d = ia.timestamp_ns as i64 - ib.timestamp_ns as i64;
            assert!(d.abs() <= 600_001, "{d}");
            moved += (d != 0) as usize;
        }
        assert!(moved >= 18);
        // A 20 ms exposure at 1 m/s: a ~17 px streak, centred on the exposure's middle.
        cfg.timing = vec![
            SimCameraTiming {
                exposure_ns: 20e6,
                ..SimCameraTiming::default()
            };
            2
        ];
        let mut blurred = Scenario::new(cfg).unwrap();
        blurred.render_u8(60, 0, &mut a).unwrap();
        let wide = (0..h as usize)
            .map(|y| {
                a[y * w as usize..(y + 1) * w as usize]
                    .iter()
                    .filter(|v| **v > 20)
                    .count()
            })
            .max()
            .unwrap();
        assert!(wide >= 12, "streak only {wide} px wide");
        let at = project(&blurred, 0, 0.5);
        let (x, _) = render_centroid(&mut blurred, 60, 0, at);
        // The 17×17 centroid window clips a little of a 17 px streak symmetrically.
        assert!((x - at.x).abs() < 0.1, "{x} vs {}", at.x);
    }

    #[test]
    fn explicit_zero_timing_is_todays_frames_bit_for_bit() {
        let mut cfg = quiet_config();
        cfg.motion_blur_steps = 4;
        cfg.add_glare();
        let mut today = Scenario::new(cfg.clone()).unwrap();
        cfg.timing = vec![SimCameraTiming::default(); 2];
        let mut zeros = Scenario::new(cfg).unwrap();
        let (w, h) = today.image_size();
        let (mut a, mut b) = (vec![0u16; (w * h) as usize], vec![0u16; (w * h) as usize]);
        for index in [0, 1, 17, 239] {
            for cam in 0..2 {
                let ia = today.render_u16(index, cam, &mut a).unwrap();
                let ib = zeros.render_u16(index, cam, &mut b).unwrap();
                assert_eq!((ia, &a), (ib, &b));
                assert_eq!(
                    zeros.frame_time(index, cam).reported_ns as u64,
                    today.timestamp_ns(index)
                );
            }
        }
        // Golden: FNV-1a of frame 5 of camera 1 (8-bit) as rendered before per-camera timing
        // existed (commit 7b4e7d7).
        let mut sc = Scenario::new(quiet_config()).unwrap();
        let mut img = vec![0u8; (w * h) as usize];
        sc.render_u8(5, 1, &mut img).unwrap();
        let fnv = img.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
            (h ^ u64::from(*v)).wrapping_mul(0x0100_0000_01b3)
        });
        assert_eq!(fnv, GOLDEN_FRAME_5_CAM_1_FNV);
    }

    const GOLDEN_FRAME_5_CAM_1_FNV: u64 = 0x3b04_3d77_eec8_7215;

    #[test]
    fn timing_of_the_wrong_length_is_refused() {
        let mut cfg = quiet_config();
        cfg.timing = vec![SimCameraTiming::default(); 3];
        let e = Scenario::new(cfg).unwrap_err().to_string();
        assert!(e.contains("timing") && e.contains("3 entries"), "{e}");
    }

    #[test]
    fn truth_reports_visibility_per_camera() {
        let mut cfg = quiet_config();
        // 20 mm inside camera 0's left image edge is 30 mm outside camera 1's (50 mm to the right).
        let model = CameraSpec::default().model(0);
        let z = 300.0;
        let x_edge0 = (-0.5 - model.intrinsics.cx_px) / model.intrinsics.fx_px * z;
        cfg.trajectory = Trajectory::Fixed(Vector3::new(x_edge0 + 20.0, 0.0, z));
        let sc = Scenario::new(cfg).unwrap();
        let t = sc.truth(0);
        assert_eq!(t.markers()[0].visible_mask, 0b01);
        assert!(!t.markers()[0].visible_in_all(2));
    }
}
