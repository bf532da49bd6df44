//! Simulated cameras: the simulator's renderer running live at a chosen frame rate.
//!
//! Frame `k` is due at `epoch + k / fps` on CLOCK_MONOTONIC; the source sleeps until then,
//! renders every camera into the caller's buffers and stamps the frames with that capture
//! instant. By default the simulated cameras are hardware-synchronized (the pairing error is
//! zero); with `[source.sim.timing]` each camera's frame is its own exposure nearest to that
//! instant, stamped with what that camera would report (capture instant + its offset from the
//! nominal grid: phase, drift, timestamp offset, jitter), and the pairing error is their spread. When the consumer falls behind by more than one
//! period the source skips to the current frame and counts the skipped sets as dropped, as a
//! real camera overwriting its buffers would. The set index is the scenario frame number, so
//! `Scenario::truth(index)` is the ground truth of every published position.

use nalgebra::Vector3;
use serde::Deserialize;

use irtrack_core::params::RigParams;
use irtrack_robot::cell::CellFeed;
use irtrack_sim::wand::{WandConfig, WandWave};
use irtrack_sim::{BitDepth, FrameInfo, RigPreset, Scenario, SimConfig, Trajectory};

use super::{
    CameraControl, CameraControls, ControlValue, Frame, FrameSet, FrameSource, Pixels, SourceError,
    SourceStats,
};
use crate::clock;
use crate::error::{FirmwareError, Result};

/// Most loose single LEDs `[source.sim] loose_leds` renders.
pub const MAX_SIM_LOOSE_LEDS: usize = 4;

/// Rig geometry of the simulated source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum SimRig {
    /// Two cameras whose axes cross at `distance_mm` at `angle_deg` (90° by default).
    #[default]
    Convergent,
    /// Two parallel cameras `baseline_mm` apart.
    Parallel,
    /// `ring_cameras` cameras on a circle of radius `distance_mm` around the workspace centre,
    /// all looking at it (multi-board rigs, docs/cluster.md).
    Ring,
}

/// `[source.sim]`
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimSourceConfig {
    /// Camera arrangement.
    #[serde(default)]
    pub rig: SimRig,
    /// Working distance: axis crossing (convergent) or depth of the trajectory (parallel), mm.
    #[serde(default = "d_distance")]
    pub distance_mm: f64,
    /// Convergent rig: angle between the two cameras' optical axes, degrees.
    #[serde(default = "d_angle")]
    pub angle_deg: f64,
    /// Parallel rig: distance between the two cameras' centres, mm.
    #[serde(default = "d_baseline")]
    pub baseline_mm: f64,
    /// The marker circles the workspace centre with this radius, mm.
    #[serde(default = "d_radius")]
    pub radius_mm: f64,
    /// Time for one circle, s.
    #[serde(default = "d_period")]
    pub period_s: f64,
    /// Frame rate of the simulated cameras, Hz.
    #[serde(default = "d_fps")]
    pub fps: f64,
    /// `false`: deliver frames as fast as the loop takes them (tests, benchmarks).
    #[serde(default = "d_true")]
    pub paced: bool,
    /// 8 or 10.
    #[serde(default = "d_bits")]
    pub bit_depth: u8,
    /// Seed of the random generators (noise, drops), so a run can be repeated exactly.
    #[serde(default = "d_seed")]
    pub seed: u64,
    /// Probability that a camera drops a frame.
    #[serde(default)]
    pub drop_rate: f64,
    /// Add a lamp and a specular streak to camera 1.
    #[serde(default)]
    pub glare: bool,
    /// End the stream after this many frames (tests); endless by default.
    #[serde(default)]
    pub frames: Option<u64>,
    /// Render a built-in multi-LED tool (`probe4`, `tri3`) instead of the single marker; its
    /// definition is part of the simulator's parameter set, so irtrackd tracks it in 6-DOF.
    #[serde(default)]
    pub tool: Option<String>,
    /// With `tool`: more built-in tools rendered at once, each on its own circle crossing the
    /// first tool's path (several tools tracked together, docs/six-dof.md). Also part of the
    /// simulator's parameter set, after `tool`.
    #[serde(default)]
    pub extra_tools: Vec<String>,
    /// With `tool`: this many loose single LEDs (LEDs of no tool, 0..=4) rendered besides the
    /// tools, each going back and forth on its own line through the work volume, across the
    /// tools' paths. irtrackd reports them with stable ids (docs/stream-protocol.md); they are
    /// not part of the parameter set. Scenario bodies: after the tools, in order.
    #[serde(default)]
    pub loose_leds: usize,
    /// With `tool`: amplitude (deg) of the tool's turning about its own axes; 0 = fixed.
    #[serde(default = "d_tool_rotation")]
    pub tool_rotation_deg: f64,
    /// Render a wand wave instead of the marker: collinear LEDs at these distances (mm) from
    /// one end, waved and turned through the work volume, with occlusions and reflections — what
    /// `host-tools capture --wand` records for `wand-calibrate`.
    #[serde(default)]
    pub wand_mm: Option<Vec<f64>>,
    /// With `wand_mm`: frames in one wave (it repeats).
    #[serde(default = "d_wand_frames")]
    pub wand_frames: u64,
    /// With `rig = "ring"`: number of cameras (2..=8).
    #[serde(default = "d_ring_cameras")]
    pub ring_cameras: usize,
    /// With `rig = "ring"`: the cameras stand on this arc of the circle, degrees. 360 (the
    /// default): evenly all around (camera `i` at `i·360°/n`); less: from 0° to this angle
    /// (camera `i` at `i·arc/(n−1)`), e.g. four cameras on a 90° arc that all see one
    /// checkerboard.
    #[serde(default = "d_ring_arc")]
    pub ring_arc_deg: f64,
    /// Render a printed checkerboard instead of the marker (`[source.sim.checkerboard]`): held
    /// in a sequence of poses on the frame clock, what `host-tools capture` records for
    /// `host-tools calibrate` (docs/irtrackd.md).
    #[serde(default)]
    pub checkerboard: Option<Box<SimCheckerboardConfig>>,
    /// The rig's cameras this source renders (a camera board's share of a multi-board rig);
    /// all by default. The simulator's parameter set is then that share, re-based on the first.
    #[serde(default)]
    pub cameras: Option<Vec<usize>>,
    /// Frame `k` is captured at CLOCK_REALTIME `k / fps` and numbered `k`, so that sources in
    /// separate processes (simulated camera boards) render the same instants.
    #[serde(default)]
    pub wall_clock: bool,
    /// The simulated robot cell: the LED is carried by `host-tools robot-sim`'s flange and is
    /// rendered where robot-sim says the robot really put it (docs/simulator.md). With `tool`,
    /// the tool is mounted on the flange instead and rendered at the pose robot-sim gives it.
    #[serde(default)]
    pub cell: Option<SimCellConfig>,
    /// What real IR cameras see behind the marker (`[source.sim.backdrop]`): a background
    /// level with noise and vignetting, a textured floor with reflections, a lamp. Absent: a
    /// dark background (docs/simulator.md).
    #[serde(default)]
    pub backdrop: Option<SimBackdropConfig>,
    /// Per-camera clocks and shutters (`[source.sim.timing]`): free-running phases, drift,
    /// timestamp jitter, exposure and rolling shutter. Absent: every camera exposes at the
    /// frame instant with a global shutter and stamps it exactly.
    #[serde(default)]
    pub timing: Option<SimTimingConfig>,
}

/// A value for every camera, or one per camera (`phase_ms = 3.1` or `[0, 3.1, -2.4]`).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(untagged)]
pub enum PerCamera {
    /// The same value for every camera.
    All(f64),
    /// One value per camera of the whole rig (camera order).
    Each(Vec<f64>),
}

impl Default for PerCamera {
    fn default() -> Self {
        PerCamera::Each(Vec::new())
    }
}

impl PerCamera {
    fn scaled(&self, scale: f64) -> Vec<f64> {
        match self {
            PerCamera::All(v) => vec![v * scale],
            PerCamera::Each(v) => v.iter().map(|x| x * scale).collect(),
        }
    }
}

/// `[source.sim.timing]`: how each simulated camera's clock and shutter behave
/// (docs/simulator.md "Camera timing"). Every key takes one value or one per camera.
#[derive(Debug, Clone, PartialEq, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct SimTimingConfig {
    /// `"free_running"`: phases spread over the whole frame period, ±50 ppm (seeded), 200 µs
    /// jitter; the keys below override it. Absent: all zero.
    #[serde(default)]
    pub preset: Option<String>,
    /// Middle of row 0's exposure against the nominal frame grid, ms.
    #[serde(default)]
    pub phase_ms: PerCamera,
    /// Clock rate error, ppm (period = nominal × (1 + ppm·1e-6)).
    #[serde(default)]
    pub ppm: PerCamera,
    /// Timestamp jitter, standard deviation in µs (clipped at ±3σ); timestamps only.
    #[serde(default)]
    pub ts_jitter_us: PerCamera,
    /// Exposure time, µs (motion blur over at least 8 sub-samples); 0 = none.
    #[serde(default)]
    pub exposure_us: PerCamera,
    /// Rolling shutter line time, µs per row; 0 = global shutter.
    #[serde(default)]
    pub line_time_us: PerCamera,
    /// Reported timestamp minus the middle of row 0's exposure, µs.
    #[serde(default)]
    pub ts_offset_us: PerCamera,
}

impl SimTimingConfig {
    /// The per-camera timings for a rig of `cameras` cameras; the error names the key.
    pub fn build(
        &self,
        cameras: usize,
        fps: f64,
        seed: u64,
    ) -> std::result::Result<Vec<irtrack_sim::SimCameraTiming>, String> {
        let lists = irtrack_sim::TimingLists {
            phase_ns: self.phase_ms.scaled(1e6),
            rate_ppm: self.ppm.scaled(1.0),
            ts_jitter_ns: self.ts_jitter_us.scaled(1e3),
            exposure_ns: self.exposure_us.scaled(1e3),
            line_time_ns: self.line_time_us.scaled(1e3),
            ts_offset_ns: self.ts_offset_us.scaled(1e3),
        };
        let lists = match self.preset.as_deref() {
            None => lists,
            Some("free_running") => lists.free_running(cameras, fps, seed),
            Some(other) => {
                return Err(format!(
                    "source.sim.timing.preset = {other:?}: the only preset is \"free_running\""
                ));
            }
        };
        lists
            .build(cameras)
            .map_err(|e| format!("source.sim.timing: {e}"))
    }
}

/// `[source.sim.checkerboard]`: a chessboard held still in one pose after another, each pose
/// for `hold_frames` frames, the sequence repeating. The view shown in frame `k` is
/// `(k / hold_frames) mod (views + single_views · cameras seen)`, so sources in separate
/// processes on the wall clock (`wall_clock = true`) show the same pose at the same instant.
/// The poses are the simulator's calibration views ([`irtrack_sim::checkerboard`]): first
/// `views` poses that every camera of `seen_by` sees whole, then `single_views` poses per camera
/// of `seen_by` that fill that camera's image (for its intrinsics; the others see them partly
/// or not at all). Every view is rendered once when the source starts (anti-aliased, with
/// lens distortion and 2 DN noise); a frame is a copy of its view.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimCheckerboardConfig {
    /// Inner corners along a row (`host-tools capture/calibrate --board-cols`).
    #[serde(default = "d_board_cols")]
    pub inner_cols: u32,
    /// Inner corners along a column (`--board-rows`).
    #[serde(default = "d_board_rows")]
    pub inner_rows: u32,
    /// Side of a square, mm (`--square-mm`).
    #[serde(default = "d_square")]
    pub square_mm: f64,
    /// Poses every camera of `seen_by` sees.
    #[serde(default = "d_board_views")]
    pub views: usize,
    /// Poses per camera of `seen_by` that only that camera sees whole.
    #[serde(default = "d_single_views")]
    pub single_views: usize,
    /// Frames each pose is held.
    #[serde(default = "d_hold_frames")]
    pub hold_frames: u64,
    /// The rig's cameras the poses are chosen for (indices in the whole rig); all by default.
    /// Give the same list on every camera board of one rig, so that they show the same poses.
    #[serde(default)]
    pub seen_by: Option<Vec<usize>>,
    /// Seed of the pose draw and the image noise.
    #[serde(default = "d_board_seed")]
    pub seed: u64,
}

impl Default for SimCheckerboardConfig {
    fn default() -> Self {
        Self {
            inner_cols: d_board_cols(),
            inner_rows: d_board_rows(),
            square_mm: d_square(),
            views: d_board_views(),
            single_views: d_single_views(),
            hold_frames: d_hold_frames(),
            seen_by: None,
            seed: d_board_seed(),
        }
    }
}

fn d_board_cols() -> u32 {
    9
}
fn d_board_rows() -> u32 {
    6
}
fn d_square() -> f64 {
    25.0
}
fn d_board_views() -> usize {
    14
}
fn d_single_views() -> usize {
    4
}
fn d_hold_frames() -> u64 {
    15
}
fn d_board_seed() -> u64 {
    5
}
fn d_ring_arc() -> f64 {
    360.0
}

/// `[source.sim.backdrop]`: every key defaults to the realistic scene
/// ([`irtrack_sim::Backdrop::realistic`]), so an empty table gives it whole.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimBackdropConfig {
    /// Background at the frame's centre, 8-bit DN.
    pub level_dn: f64,
    /// Extra per-pixel noise (standard deviation), 8-bit DN.
    pub noise_dn: f64,
    /// Fraction of the level lost in the corners.
    pub vignetting: f64,
    /// Textured floor with specular reflections in the lower third.
    pub floor: bool,
    /// A saturated lamp cut by the top edge.
    pub lamp: bool,
}

impl Default for SimBackdropConfig {
    fn default() -> Self {
        let b = irtrack_sim::Backdrop::realistic();
        Self {
            level_dn: b.level_dn,
            noise_dn: b.noise_dn,
            vignetting: b.vignetting,
            floor: b.floor,
            lamp: b.lamp,
        }
    }
}

impl SimBackdropConfig {
    /// The renderer's backdrop with these settings.
    pub fn backdrop(&self) -> irtrack_sim::Backdrop {
        irtrack_sim::Backdrop {
            level_dn: self.level_dn,
            noise_dn: self.noise_dn,
            vignetting: self.vignetting,
            floor: self.floor,
            lamp: self.lamp,
        }
    }
}

/// `[source.sim.cell]`: simulator-only settings of the robot cell. The transform below is the
/// cell's truth; the tracker never sees it (the survey measures it).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimCellConfig {
    /// robot-sim's cell feed (`host-tools robot-sim --cell-feed`), UDP `ip:port`.
    pub robot: String,
    /// Rotation of `x_cam0 = R x_base + t` as a rotation vector (axis × angle), degrees.
    #[serde(default)]
    pub cam0_from_base_rotation_deg: [f64; 3],
    /// Translation `t` of the same transform, mm.
    pub cam0_from_base_translation_mm: [f64; 3],
    /// How long a frame waits for robot-sim's answer; without one the LED is dark.
    #[serde(default = "d_cell_timeout")]
    pub timeout_ms: u64,
}

impl SimCellConfig {
    /// `x_cam0 = R x_base + t`.
    pub fn cam0_from_base(&self) -> nalgebra::Isometry3<f64> {
        let r = Vector3::from(self.cam0_from_base_rotation_deg).map(f64::to_radians);
        nalgebra::Isometry3::from_parts(
            nalgebra::Translation3::from(Vector3::from(self.cam0_from_base_translation_mm)),
            nalgebra::UnitQuaternion::from_scaled_axis(r),
        )
    }
}

fn d_cell_timeout() -> u64 {
    20
}

fn d_ring_cameras() -> usize {
    4
}

fn d_wand_frames() -> u64 {
    900
}

fn d_distance() -> f64 {
    600.0
}
fn d_angle() -> f64 {
    90.0
}
fn d_baseline() -> f64 {
    irtrack_sim::rig::TABLE_I_BASELINE_MM
}
fn d_radius() -> f64 {
    40.0
}
fn d_period() -> f64 {
    4.0
}
fn d_fps() -> f64 {
    60.0
}
fn d_true() -> bool {
    true
}
fn d_tool_rotation() -> f64 {
    30.0
}
fn d_bits() -> u8 {
    8
}
fn d_seed() -> u64 {
    1
}

impl Default for SimSourceConfig {
    fn default() -> Self {
        Self {
            rig: SimRig::default(),
            distance_mm: d_distance(),
            angle_deg: d_angle(),
            baseline_mm: d_baseline(),
            radius_mm: d_radius(),
            period_s: d_period(),
            fps: d_fps(),
            paced: true,
            bit_depth: d_bits(),
            seed: d_seed(),
            drop_rate: 0.0,
            glare: false,
            frames: None,
            tool: None,
            extra_tools: Vec::new(),
            loose_leds: 0,
            tool_rotation_deg: d_tool_rotation(),
            wand_mm: None,
            wand_frames: d_wand_frames(),
            ring_cameras: d_ring_cameras(),
            ring_arc_deg: d_ring_arc(),
            checkerboard: None,
            cameras: None,
            wall_clock: false,
            cell: None,
            backdrop: None,
            timing: None,
        }
    }
}

impl SimSourceConfig {
    /// Checks the values serde cannot (frame rate, bit depth, tool rotation, ...); the error names
    /// the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |reason: String| Err(FirmwareError::Config { reason });
        if !(self.fps.is_finite() && self.fps > 0.0) {
            return bad(format!("source.sim.fps must be > 0, got {}", self.fps));
        }
        if let Some(t) = &self.timing {
            if self.wand_mm.is_some() || self.checkerboard.is_some() {
                return bad("source.sim.timing is rendered by the marker and tool scenes; the wand wave and the checkerboard are rendered synchronously, so remove [source.sim.timing] with wand_mm or checkerboard".into());
            }
            t.build(self.rig_camera_count(), self.fps, self.seed)
                .map_err(|reason| FirmwareError::Config { reason })?;
        }
        if !matches!(self.bit_depth, 8 | 10) {
            return bad(format!(
                "source.sim.bit_depth must be 8 or 10, got {}",
                self.bit_depth
            ));
        }
        if let Some(name) = &self.tool
            && irtrack_sim::tools::builtin_tool(name).is_none()
        {
            return bad(format!(
                "source.sim.tool = {name:?} is not a built-in tool (use {})",
                irtrack_sim::tools::BUILTIN_TOOLS.join(" or ")
            ));
        }
        for (i, name) in self.extra_tools.iter().enumerate() {
            if self.tool.is_none() {
                return bad("source.sim.extra_tools needs source.sim.tool (the first tool)".into());
            }
            if irtrack_sim::tools::builtin_tool(name).is_none() {
                return bad(format!(
                    "source.sim.extra_tools: {name:?} is not a built-in tool (use {})",
                    irtrack_sim::tools::BUILTIN_TOOLS.join(" or ")
                ));
            }
            if self.tool.as_ref() == Some(name) || self.extra_tools[..i].contains(name) {
                return bad(format!("source.sim.extra_tools: tool {name:?} is listed twice"));
            }
        }
        if self.loose_leds > 0 && self.tool.is_none() {
            // Only the 6-DOF loop (a set with tools) reports loose LEDs; the single-marker
            // loop would take them for its marker.
            return bad(
                "source.sim.loose_leds needs source.sim.tool (loose LEDs are reported beside tools)".into(),
            );
        }
        if self.loose_leds > MAX_SIM_LOOSE_LEDS {
            return bad(format!(
                "source.sim.loose_leds must be in 0..={MAX_SIM_LOOSE_LEDS}, got {}",
                self.loose_leds
            ));
        }
        if !(self.tool_rotation_deg.is_finite() && (0.0..=90.0).contains(&self.tool_rotation_deg)) {
            return bad(format!(
                "source.sim.tool_rotation_deg must be in 0..=90, got {}",
                self.tool_rotation_deg
            ));
        }
        if let Some(leds) = &self.wand_mm {
            if self.tool.is_some() {
                return bad("source.sim.wand_mm and source.sim.tool exclude each other: the simulator renders either a wand or a tool".into());
            }
            // Finite first, so that `<=` below sees no NaN.
            if leds.len() < 3 || leds.iter().any(|v| !v.is_finite()) || leds.windows(2).any(|w| w[1] <= w[0])
            {
                return bad(format!(
                    "source.sim.wand_mm = {leds:?}: need 3 or more increasing distances in mm (e.g. [0, 120, 300])"
                ));
            }
            if self.wand_frames < 10 {
                return bad(format!(
                    "source.sim.wand_frames must be at least 10, got {}",
                    self.wand_frames
                ));
            }
        }
        if !(self.ring_arc_deg.is_finite() && self.ring_arc_deg > 0.0 && self.ring_arc_deg <= 360.0) {
            return bad(format!(
                "source.sim.ring_arc_deg must be in (0, 360], got {}",
                self.ring_arc_deg
            ));
        }
        if let Some(b) = &self.checkerboard {
            if self.wand_mm.is_some() || self.tool.is_some() || self.cell.is_some() {
                return bad("source.sim.checkerboard renders a board only; it excludes source.sim.wand_mm, source.sim.tool and source.sim.cell".into());
            }
            if b.inner_cols < 2 || b.inner_rows < 2 {
                return bad(format!(
                    "source.sim.checkerboard: {}x{} inner corners; need at least 2x2",
                    b.inner_cols, b.inner_rows
                ));
            }
            if !(b.square_mm.is_finite() && b.square_mm > 0.0) {
                return bad(format!(
                    "source.sim.checkerboard.square_mm must be > 0, got {}",
                    b.square_mm
                ));
            }
            if b.views < 1 || b.views + b.single_views > 1000 {
                return bad(format!(
                    "source.sim.checkerboard: views = {} (at least 1) and single_views = {}: 1000 poses at most",
                    b.views, b.single_views
                ));
            }
            if b.hold_frames < 1 {
                return bad("source.sim.checkerboard.hold_frames must be at least 1".into());
            }
            let total = self.rig_camera_count();
            if let Some(seen) = &b.seen_by
                && (seen.len() < 2
                    || seen.iter().any(|&c| c >= total)
                    || (1..seen.len()).any(|i| seen[..i].contains(&seen[i])))
            {
                return bad(format!(
                    "source.sim.checkerboard.seen_by = {seen:?}: two or more distinct indices below the rig's {total} cameras"
                ));
            }
        }
        if let Some(cell) = &self.cell {
            if !self.extra_tools.is_empty() || self.wand_mm.is_some() || self.loose_leds > 0 {
                return bad("source.sim.cell renders the robot's single LED or its one tool (source.sim.tool); it excludes source.sim.extra_tools, source.sim.loose_leds and source.sim.wand_mm".into());
            }
            if cell.robot.parse::<std::net::SocketAddr>().is_err() {
                return bad(format!(
                    "source.sim.cell.robot = {:?} is not an ip:port (robot-sim's --cell-feed address)",
                    cell.robot
                ));
            }
            let finite = cell
                .cam0_from_base_rotation_deg
                .iter()
                .chain(&cell.cam0_from_base_translation_mm)
                .all(|v| v.is_finite());
            if !finite {
                return bad("source.sim.cell: the cam0_from_base transform must be finite".into());
            }
            if !(1..=1000).contains(&cell.timeout_ms) {
                return bad(format!(
                    "source.sim.cell.timeout_ms must be in 1..=1000, got {}",
                    cell.timeout_ms
                ));
            }
        }
        if let Some(b) = &self.backdrop
            && let Err(e) = b.backdrop().validate()
        {
            return bad(format!("source.sim.backdrop: {e}"));
        }
        if self.rig == SimRig::Ring && !(2..=irtrack_core::params::MAX_CAMERAS).contains(&self.ring_cameras) {
            return bad(format!(
                "source.sim.ring_cameras must be in 2..={}, got {}",
                irtrack_core::params::MAX_CAMERAS,
                self.ring_cameras
            ));
        }
        if let Some(cams) = &self.cameras {
            let total = self.rig_camera_count();
            if cams.is_empty()
                || cams.iter().any(|&c| c >= total)
                || (1..cams.len()).any(|i| cams[..i].contains(&cams[i]))
            {
                return bad(format!(
                    "source.sim.cameras = {cams:?}: distinct indices below the rig's {total} cameras"
                ));
            }
        }
        if !(0.0..1.0).contains(&self.drop_rate) {
            return bad(format!(
                "source.sim.drop_rate must be in [0, 1), got {}",
                self.drop_rate
            ));
        }
        for (key, v) in [
            ("distance_mm", self.distance_mm),
            ("angle_deg", self.angle_deg),
            ("baseline_mm", self.baseline_mm),
            ("period_s", self.period_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!("source.sim.{key} must be > 0, got {v}"));
            }
        }
        if !(self.radius_mm.is_finite() && self.radius_mm >= 0.0) {
            return bad(format!(
                "source.sim.radius_mm must be >= 0, got {}",
                self.radius_mm
            ));
        }
        Ok(())
    }

    /// Cameras of the whole rig (`ring_cameras` for the ring, else 2).
    pub fn rig_camera_count(&self) -> usize {
        if self.rig == SimRig::Ring {
            self.ring_cameras
        } else {
            2
        }
    }

    /// The checkerboard's poses (`cam0_from_board`, camera 0 of the whole rig) in the order
    /// the source shows them: `views` poses every camera of `seen_by` sees, then `single_views`
    /// per camera of `seen_by`. `full` is the whole rig (the scenario's). Deterministic.
    pub fn checkerboard_poses(
        &self,
        full: &RigParams,
    ) -> std::result::Result<Vec<irtrack_core::camera::RigidTransform>, String> {
        use irtrack_sim::checkerboard::{
            BoardSpec, PoseConfig, generate_poses, generate_single_camera_poses,
        };
        let Some(b) = &self.checkerboard else {
            return Ok(Vec::new());
        };
        let board = BoardSpec::new(b.inner_cols, b.inner_rows, b.square_mm)
            .map_err(|e| format!("source.sim.checkerboard: {e}"))?;
        let seen: Vec<usize> = b
            .seen_by
            .clone()
            .unwrap_or_else(|| (0..full.cameras.len()).collect());
        // The cameras that must see the board, kept in camera 0's frame (not re-based): the
        // poses are the same whichever share of the rig a board renders.
        let mut sub = full.clone();
        sub.cameras = seen
            .iter()
            .filter_map(|&c| full.cameras.get(c).cloned())
            .collect();
        let cfg = |count, seed| PoseConfig {
            count,
            seed,
            ..Default::default()
        };
        let why = |e: irtrack_sim::SimError| {
            format!(
                "source.sim.checkerboard: {e} (cameras {seen:?} of the rig must all see the board; \
                 choose them with seen_by, or a rig whose cameras face one way, e.g. ring_arc_deg = 90)"
            )
        };
        let mut poses = generate_poses(&sub, &board, &cfg(b.views, b.seed)).map_err(why)?;
        if b.single_views > 0 {
            for j in 0..sub.cameras.len() {
                poses.extend(
                    generate_single_camera_poses(
                        &sub,
                        &board,
                        j,
                        &cfg(b.single_views, b.seed + 1 + j as u64),
                    )
                    .map_err(why)?,
                );
            }
        }
        Ok(poses)
    }

    /// The timing constants of each of the whole rig's cameras (irtrack-core's model: shutter,
    /// line time, exposure, offset) that the tracker must be given for `[source.sim.timing]`;
    /// synchronous without the table.
    pub fn camera_timings(&self) -> Vec<irtrack_core::timing::CameraTiming> {
        let n = self.rig_camera_count();
        let timings = self
            .timing
            .as_ref()
            .and_then(|t| t.build(n, self.fps, self.seed).ok())
            .unwrap_or_default();
        (0..n)
            .map(|c| {
                timings
                    .get(c)
                    .map_or(irtrack_core::timing::CameraTiming::SYNCHRONOUS, |t| {
                        t.core_timing()
                    })
            })
            .collect()
    }

    /// The simulator configuration this section describes.
    pub fn scenario_config(&self) -> SimConfig {
        let preset = match self.rig {
            SimRig::Convergent => RigPreset::Convergent {
                distance_mm: self.distance_mm,
                angle_deg: self.angle_deg,
            },
            SimRig::Parallel => RigPreset::Parallel {
                baseline_mm: self.baseline_mm,
            },
            SimRig::Ring => RigPreset::Custom(ring_rig_arc(
                self.ring_cameras,
                self.distance_mm,
                self.ring_arc_deg,
            )),
        };
        let mut cfg = SimConfig::preset(preset, self.distance_mm, self.radius_mm);
        if let Trajectory::Circle {
            centre_mm,
            radius_mm,
            normal,
            ..
        } = cfg.trajectory
        {
            cfg.trajectory = Trajectory::Circle {
                centre_mm,
                radius_mm,
                normal,
                period_s: self.period_s,
            };
        } else {
            let centre = cfg.rig.workspace_centre_mm(self.distance_mm);
            cfg.trajectory = Trajectory::Circle {
                centre_mm: centre,
                radius_mm: self.radius_mm,
                normal: Vector3::new(0.3, 1.0, 0.4),
                period_s: self.period_s,
            };
        }
        cfg.fps = self.fps;
        cfg.seed = self.seed;
        cfg.drop_rate = self.drop_rate;
        cfg.bit_depth = if self.bit_depth == 10 {
            BitDepth::Ten
        } else {
            BitDepth::Eight
        };
        if self.glare {
            cfg.add_glare();
        }
        if let Some(b) = &self.backdrop {
            cfg.backdrop = b.backdrop();
        }
        if let Some(t) = &self.timing {
            // Checked by `validate`; an invalid table renders synchronous cameras.
            cfg.timing = t
                .build(self.rig_camera_count(), self.fps, self.seed)
                .unwrap_or_default();
        }
        if let Some(tool) = self.tool_definition() {
            cfg.set_tool(
                &tool.leds_mm,
                irtrack_sim::tools::turning(self.tool_rotation_deg, self.period_s),
            );
            let centre = cfg.rig.workspace_centre_mm(self.distance_mm);
            for (i, t) in self.tool_definitions().iter().enumerate().skip(1) {
                // Each on its own tilted circle through the work volume, slower than the
                // first: the paths cross, the tools do not collide every lap.
                let k = i as f64;
                cfg.add_tool(
                    &t.leds_mm,
                    Trajectory::Circle {
                        centre_mm: centre + Vector3::new(20.0 * k, -15.0 * k, -10.0 * k),
                        radius_mm: self.radius_mm.max(1.0) * (1.0 + 0.3 * k),
                        normal: Vector3::new(-0.2 * k, 1.0, 0.3 * k),
                        period_s: self.period_s * (1.0 + 0.45 * k),
                    },
                    irtrack_sim::Orientation::Wobble {
                        base: nalgebra::UnitQuaternion::from_euler_angles(0.5 * k, -0.3 * k, 0.9 * k),
                        amplitude_deg: Vector3::repeat(self.tool_rotation_deg * 0.8),
                        period_s: Vector3::new(5.0, 6.5, 8.0) * (1.0 + 0.2 * k),
                        phase_rad: Vector3::new(0.5 * k, 0.0, 1.5),
                    },
                );
            }
            for i in 0..self.loose_leds {
                cfg.add_loose_led(self.loose_led_path(i, centre));
            }
        }
        cfg
    }

    /// Path of loose LED `i` around the workspace centre: back and forth on a line through the
    /// middle of the tools' circles (so it crosses their paths), each LED on its own line and
    /// at its own pace.
    pub fn loose_led_path(&self, i: usize, centre_mm: Vector3<f64>) -> Trajectory {
        let k = i as f64;
        let r = self.radius_mm.max(1.0);
        Trajectory::Line {
            from_mm: centre_mm + Vector3::new(-1.5 * r, 0.4 * r - 20.0 * k, -0.5 * r + 15.0 * k),
            to_mm: centre_mm + Vector3::new(1.5 * r, -0.5 * r - 20.0 * k, 0.6 * r - 15.0 * k),
            period_s: self.period_s * (1.15 + 0.35 * k),
        }
    }

    /// The parameter set of the cameras this source renders: the whole rig, or with
    /// `cameras` that share re-based on its first camera.
    pub fn rendered_rig(&self, full: &RigParams) -> RigParams {
        let Some(cams) = &self.cameras else {
            return full.clone();
        };
        let base = &full.cameras[cams[0]].cam_from_cam0;
        let rb = nalgebra::Matrix3::from_row_slice(&base.r_row_major);
        let tb = Vector3::from(base.t_mm);
        let mut rig = full.clone();
        rig.rig_id = format!(
            "{}-cams{}",
            full.rig_id,
            cams.iter().map(|c| c.to_string()).collect::<Vec<_>>().join("-")
        );
        rig.cameras = cams
            .iter()
            .map(|&c| {
                let p = &full.cameras[c];
                let r = nalgebra::Matrix3::from_row_slice(&p.cam_from_cam0.r_row_major) * rb.transpose();
                let t = Vector3::from(p.cam_from_cam0.t_mm) - r * tb;
                irtrack_core::params::CameraParams {
                    model: p.model,
                    cam_from_cam0: irtrack_core::camera::RigidTransform::from_parts(&r, &t),
                }
            })
            .collect();
        rig.world_from_cam0 = None;
        rig
    }

    /// The multi-LED tool this source renders, if any.
    pub fn tool_definition(&self) -> Option<irtrack_core::params::ToolDefinition> {
        self.tool.as_deref().and_then(irtrack_sim::tools::builtin_tool)
    }

    /// Every tool this source renders: `tool`, then `extra_tools` (empty without `tool`).
    pub fn tool_definitions(&self) -> Vec<irtrack_core::params::ToolDefinition> {
        let Some(first) = self.tool_definition() else {
            return Vec::new();
        };
        let mut all = vec![first];
        all.extend(
            self.extra_tools
                .iter()
                .filter_map(|n| irtrack_sim::tools::builtin_tool(n)),
        );
        all
    }
}

/// `n` cameras evenly on a circle of radius `distance_mm` around (0, 0, `distance_mm`) in
/// camera 0's frame, all looking at that centre (camera `i` turned by `i·360°/n` about y).
pub fn ring_rig(n: usize, distance_mm: f64) -> RigParams {
    ring_rig_arc(n, distance_mm, 360.0)
}

/// [`ring_rig`] with the cameras on an arc of `arc_deg` (`[source.sim] ring_arc_deg`): 360°
/// is the full ring; less puts camera `i` at `i·arc_deg/(n−1)`, both ends occupied.
pub fn ring_rig_arc(n: usize, distance_mm: f64, arc_deg: f64) -> RigParams {
    let spec = irtrack_sim::CameraSpec::default();
    let full = arc_deg >= 360.0;
    let step_deg = if full {
        360.0 / n as f64
    } else {
        arc_deg / (n.max(2) - 1) as f64
    };
    RigParams {
        rig_id: if full {
            format!("sim-ring{n}-d{distance_mm}")
        } else {
            format!("sim-ring{n}-a{arc_deg}-d{distance_mm}")
        },
        created_unix_s: 0,
        cameras: (0..n)
            .map(|i| irtrack_core::params::CameraParams {
                model: spec.model(i),
                cam_from_cam0: if i == 0 {
                    irtrack_core::camera::RigidTransform::IDENTITY
                } else {
                    irtrack_sim::rig::convergent_pose(distance_mm, step_deg * i as f64)
                },
            })
            .collect(),
        world_from_cam0: None,
        tools: Vec::new(),
        calibration: None,
        placement: Vec::new(),
        timing: Vec::new(),
        serial: 0,
    }
}

/// Simulated exposure (100 µs units, like V4L2's `exposure_absolute`) at which the renderer's
/// brightness is unchanged, and its range.
pub const SIM_EXPOSURE_NOMINAL: i64 = 100;
/// Smallest and largest simulated exposure, 100 µs units.
pub const SIM_EXPOSURE_RANGE: (i64, i64) = (1, 1000);
/// Simulated gain at which brightness and noise are the renderer's own, and its range.
pub const SIM_GAIN_NOMINAL: i64 = 16;
/// Smallest and largest simulated gain.
pub const SIM_GAIN_RANGE: (i64, i64) = (1, 255);

/// Exposure and gain of one simulated camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct SimControls {
    exposure: i64,
    gain: i64,
}

impl SimControls {
    const NOMINAL: Self = Self {
        exposure: SIM_EXPOSURE_NOMINAL,
        gain: SIM_GAIN_NOMINAL,
    };
}

/// A [`FrameSource`] rendering a [`Scenario`] live.
pub struct SimSource {
    cfg: SimSourceConfig,
    scenario: Scenario,
    period_ns: u64,
    epoch_ns: Option<u64>,
    next_index: u64,
    stats: SourceStats,
    controls: Vec<SimControls>,
    noise_state: u64,
    /// Wand mode: the wave and an 8-bit scratch frame for 10-bit output (allocated up front).
    wand: Option<(WandWave, Vec<u8>)>,
    /// Checkerboard mode: every view of every rendered camera, rendered up front.
    board: Option<BoardViews>,
    /// Cell mode: the feed from robot-sim and camera 0's pose in the robot base frame.
    cell: Option<(CellFeed, nalgebra::Isometry3<f64>)>,
    /// Paced mode renders this long before a frame's capture instant, so that the frame is
    /// handed over at that instant like a camera's (adapted to the recent rendering times).
    render_lead_ns: u64,
    /// The scenario's cameras this source renders, in frame order.
    /// Per slot: the camera's reported timestamp minus the set's nominal instant (ns), for
    /// `[source.sim.timing]` (kept here so a set costs no allocation).
    skew_ns: Vec<i64>,
    render_cams: Vec<usize>,
}

/// Checkerboard mode's images: each view rendered once at start, so a frame is a copy (no
/// allocation, no rendering cost per frame).
struct BoardViews {
    hold_frames: u64,
    views: usize,
    /// Pixels per image.
    pixels: usize,
    /// `images[(slot * views + view) * pixels ..][.. pixels]`, 8-bit.
    images: Vec<u8>,
}

impl BoardViews {
    fn render(
        cfg: &SimSourceConfig,
        b: &SimCheckerboardConfig,
        full: &RigParams,
        render_cams: &[usize],
    ) -> std::result::Result<Self, SourceError> {
        use irtrack_sim::checkerboard::{BoardSpec, CameraRenderer, RenderSettings};
        let poses = cfg.checkerboard_poses(full).map_err(SourceError::Config)?;
        let board = BoardSpec::new(b.inner_cols, b.inner_rows, b.square_mm)
            .map_err(|e| SourceError::Config(format!("source.sim.checkerboard: {e}")))?;
        let settings = RenderSettings {
            seed: b.seed,
            ..Default::default()
        };
        let mut pixels = 0;
        let mut images = Vec::new();
        for &camera in render_cams {
            let cam = full.cameras.get(camera).ok_or_else(|| {
                SourceError::Config(format!("source.sim.cameras: no camera {camera} in the rig"))
            })?;
            let size = cam.model.image_size;
            pixels = size.width_px as usize * size.height_px as usize;
            let renderer = CameraRenderer::new(cam.model);
            for (view, pose) in poses.iter().enumerate() {
                let start = images.len();
                images.resize(start + pixels, 0);
                renderer
                    .render(
                        &cam.cam_from_cam0.compose(pose),
                        &board,
                        &settings,
                        // The same noise for a camera and view in every process.
                        ((camera as u64) << 32) | view as u64,
                        &mut images[start..],
                    )
                    .map_err(|e| SourceError::CameraLost {
                        camera,
                        device: "simulator".into(),
                        reason: format!("rendering checkerboard view {view}: {e}"),
                    })?;
            }
        }
        Ok(Self {
            hold_frames: b.hold_frames,
            views: poses.len(),
            pixels,
            images,
        })
    }

    /// The image of rendered camera `slot` in frame `index`.
    fn image(&self, slot: usize, index: u64) -> &[u8] {
        let view = ((index / self.hold_frames) % self.views as u64) as usize;
        let start = (slot * self.views + view) * self.pixels;
        &self.images[start..start + self.pixels]
    }
}

/// Where a dark LED is put: so far away that its spot carries no light.
const DARK_MM: f64 = 1e9;

/// Applies exposure × gain to a rendered frame: brightness scales with both, and gain above
/// nominal adds read noise (σ = 2 DN per nominal gain step), so the set-up view's controls
/// visibly act. Nominal settings leave the renderer's frame untouched.
fn apply_sim_controls(px: &mut Pixels, c: SimControls, max_dn: f32, state: &mut u64) {
    if c == SimControls::NOMINAL {
        return;
    }
    let scale = (c.exposure as f32 / SIM_EXPOSURE_NOMINAL as f32) * (c.gain as f32 / SIM_GAIN_NOMINAL as f32);
    let sigma = 2.0 * ((c.gain - SIM_GAIN_NOMINAL).max(0) as f32 / SIM_GAIN_NOMINAL as f32);
    let mut noise = || {
        if sigma == 0.0 {
            return 0.0;
        }
        // xorshift64; the sum of two uniforms is a cheap, roughly bell-shaped noise.
        let mut next = || {
            *state ^= *state << 13;
            *state ^= *state >> 7;
            *state ^= *state << 17;
            (*state >> 40) as f32 / (1u64 << 24) as f32
        };
        (next() + next() - 1.0) * sigma * 2.45
    };
    match px {
        Pixels::U8(v) => {
            for p in v.iter_mut() {
                *p = (f32::from(*p) * scale + noise()).clamp(0.0, max_dn) as u8;
            }
        }
        Pixels::U16(v) => {
            for p in v.iter_mut() {
                *p = (f32::from(*p) * scale + noise()).clamp(0.0, max_dn) as u16;
            }
        }
    }
}

impl SimSource {
    /// Builds the scenario `cfg` describes and a source that renders it.
    pub fn new(cfg: &SimSourceConfig) -> std::result::Result<Self, SourceError> {
        let scenario =
            Scenario::new(cfg.scenario_config()).map_err(|e| SourceError::Config(e.to_string()))?;
        let mut source = Self::from_scenario(scenario, cfg);
        if let Some(leds_mm) = &cfg.wand_mm {
            let sim_cfg = source.scenario.config();
            let centre_mm = sim_cfg.rig.workspace_centre_mm(cfg.distance_mm);
            let mut wand_cfg =
                WandConfig::new(source.scenario.rig().clone(), centre_mm, cfg.wand_frames as usize);
            wand_cfg.leds_mm = leds_mm.clone();
            wand_cfg.seed = cfg.seed;
            // The default sweep suits a 1.2 m working distance; keep the same share of the view.
            wand_cfg.sweep_mm *= cfg.distance_mm / 1200.0;
            let wave = WandWave::new(wand_cfg).map_err(|e| SourceError::Config(e.to_string()))?;
            let (w, h) = source.scenario.image_size();
            source.wand = Some((wave, vec![0; w as usize * h as usize]));
        }
        if let Some(b) = &cfg.checkerboard {
            source.board = Some(BoardViews::render(
                cfg,
                b,
                source.scenario.rig(),
                &source.render_cams,
            )?);
        }
        if let Some(cell) = &cfg.cell {
            let addr = cell
                .robot
                .parse()
                .map_err(|e| SourceError::Config(format!("source.sim.cell.robot {:?}: {e}", cell.robot)))?;
            let feed =
                CellFeed::connect(addr, std::time::Duration::from_millis(cell.timeout_ms)).map_err(|e| {
                    SourceError::Config(format!("source.sim.cell: cannot open the feed socket: {e}"))
                })?;
            source.cell = Some((feed, cell.cam0_from_base()));
        }
        Ok(source)
    }

    /// Runs an existing scenario (tests keep a copy of the same scenario for ground truth).
    pub fn from_scenario(scenario: Scenario, cfg: &SimSourceConfig) -> Self {
        let fps = scenario.config().fps;
        let render_cams = cfg
            .cameras
            .clone()
            .unwrap_or_else(|| (0..scenario.camera_count()).collect());
        Self {
            cfg: SimSourceConfig { fps, ..cfg.clone() },
            period_ns: (1e9 / fps).round() as u64,
            epoch_ns: None,
            next_index: 0,
            stats: SourceStats::default(),
            controls: vec![SimControls::NOMINAL; render_cams.len()],
            skew_ns: vec![0; render_cams.len()],
            render_cams,
            noise_state: 0x9E37_79B9_7F4A_7C15,
            render_lead_ns: ((1e9 / fps) as u64 / 2).min(3_000_000),
            scenario,
            wand: None,
            board: None,
            cell: None,
        }
    }

    /// The scenario being rendered (ground truth for tests).
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }
}

impl FrameSource for SimSource {
    fn camera_count(&self) -> usize {
        self.render_cams.len()
    }

    fn allocate_set(&self) -> FrameSet {
        let (w, h) = self.scenario.image_size();
        let n = w as usize * h as usize;
        let ten = self.cfg.bit_depth == 10;
        let frames = (0..self.camera_count())
            .map(|_| Frame {
                width_px: w,
                height_px: h,
                stride_px: w,
                bit_depth: if ten { 10 } else { 8 },
                pixels: if ten {
                    Pixels::U16(vec![0; n])
                } else {
                    Pixels::U8(vec![0; n])
                },
                timestamp_ns: 0,
                sequence: 0,
            })
            .collect();
        FrameSet {
            index: 0,
            frames,
            pairing_error_ns: 0,
            render_ns: 0,
        }
    }

    fn next_set(&mut self, out: &mut FrameSet) -> std::result::Result<(), SourceError> {
        loop {
            let index = self.next_index;
            if self.cfg.frames.is_some_and(|n| index >= n) {
                return Err(SourceError::EndOfStream);
            }
            let capture_ns = if self.cfg.paced && self.cfg.wall_clock {
                // Frame k at CLOCK_REALTIME k / fps, expressed on CLOCK_MONOTONIC.
                let rt_now = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_nanos() as u64);
                let rt_minus_mono = u64::try_from(clock::realtime_minus_mono_ns()).unwrap_or(0);
                // The frame being captured now, by the scenario's own time base (frame k at
                // k * 1e9 / fps ns): an integer period would drift from it by seconds at
                // today's frame numbers (~5e10 at 30 fps).
                let current = (rt_now as f64 * self.cfg.fps / 1e9).floor() as u64;
                if index == 0 || current > index + 1 {
                    if index != 0 {
                        self.stats.sets_dropped += current - index;
                    }
                    self.next_index = current + 1;
                    continue;
                }
                let due = self.scenario.timestamp_ns(index).saturating_sub(rt_minus_mono);
                clock::sleep_until_ns(due.saturating_sub(self.render_lead_ns));
                Some(due)
            } else if self.cfg.paced {
                let epoch = *self.epoch_ns.get_or_insert_with(clock::monotonic_ns);
                let due = epoch + self.scenario.timestamp_ns(index);
                let now = clock::monotonic_ns();
                if now > due + self.period_ns {
                    // Behind by more than a frame: the camera has moved on; skip to its frame.
                    let current = (now - epoch) / self.period_ns;
                    self.stats.sets_dropped += current - index;
                    self.next_index = current;
                    continue;
                }
                // Render ahead of the capture instant (the scene is drawn as it is at `due`)
                // and hand the frames over at it: a camera's frame reaches the loop at its
                // timestamp too; rendering is reported as its own stage (`render_ns`).
                clock::sleep_until_ns(due.saturating_sub(self.render_lead_ns));
                Some(due)
            } else {
                None
            };
            let render_start_ns = clock::monotonic_ns();
            self.next_index = index + 1;
            if out.frames.len() != self.render_cams.len() {
                return Err(SourceError::Config(format!(
                    "frame set has {} frames, simulator has {} cameras",
                    out.frames.len(),
                    self.camera_count()
                )));
            }
            if let Some((feed, cam0_from_base)) = &mut self.cell {
                let config = |e: irtrack_sim::SimError| SourceError::Config(e.to_string());
                if self.cfg.tool.is_some() {
                    // The tool on the flange, turned as the robot really turned it.
                    let (p_cam0, q_cam0) = match feed.tool_pose() {
                        Ok(Some((p, q))) => (
                            *cam0_from_base * nalgebra::Point3::from(Vector3::from(p)),
                            cam0_from_base.rotation
                                * nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                                    q[0], q[1], q[2], q[3],
                                )),
                        ),
                        Ok(None) | Err(_) => (
                            nalgebra::Point3::new(0.0, 0.0, DARK_MM),
                            nalgebra::UnitQuaternion::identity(),
                        ),
                    };
                    self.scenario
                        .set_tool_orientation(irtrack_sim::Orientation::Fixed(q_cam0))
                        .map_err(config)?;
                    self.scenario
                        .set_trajectory(Trajectory::Fixed(p_cam0.coords))
                        .map_err(config)?;
                } else {
                    // No answer in time (robot-sim not running) or no LED: nothing to see.
                    let p_cam0 = match feed.led_mm() {
                        Ok(Some(p)) => *cam0_from_base * nalgebra::Point3::from(Vector3::from(p)),
                        Ok(None) | Err(_) => nalgebra::Point3::new(0.0, 0.0, DARK_MM),
                    };
                    self.scenario
                        .set_trajectory(Trajectory::Fixed(p_cam0.coords))
                        .map_err(config)?;
                }
            }
            let mut dropped = 0usize;
            let (mut min_ts, mut max_ts) = (i64::MAX, i64::MIN);
            let nominal_ns = self.scenario.timestamp_ns(index) as i64;
            for (slot, frame) in out.frames.iter_mut().enumerate() {
                let camera = self.render_cams[slot];
                let lost = |e: irtrack_sim::SimError| SourceError::CameraLost {
                    camera,
                    device: "simulator".into(),
                    reason: e.to_string(),
                };
                let info = if let Some(board) = &self.board {
                    let img = board.image(slot, index);
                    match &mut frame.pixels {
                        Pixels::U8(px) if px.len() == img.len() => px.copy_from_slice(img),
                        Pixels::U16(px) if px.len() == img.len() => {
                            // 8-bit rendering shifted into the 10-bit range.
                            for (d, s) in px.iter_mut().zip(img) {
                                *d = u16::from(*s) << 2;
                            }
                        }
                        _ => {
                            return Err(SourceError::Config(format!(
                                "camera {camera}: frame buffer is not {} pixels",
                                img.len()
                            )));
                        }
                    }
                    FrameInfo {
                        index,
                        camera,
                        dropped: false,
                        timestamp_ns: self.scenario.timestamp_ns(index),
                    }
                } else if let Some((wave, scratch)) = &mut self.wand {
                    let wave_frame = (index % self.cfg.wand_frames) as usize;
                    match &mut frame.pixels {
                        Pixels::U8(px) => {
                            wave.render(wave_frame, camera, px).map_err(lost)?;
                        }
                        Pixels::U16(px) => {
                            wave.render(wave_frame, camera, scratch).map_err(lost)?;
                            // 8-bit rendering shifted into the 10-bit range.
                            for (d, s) in px.iter_mut().zip(scratch.iter()) {
                                *d = u16::from(*s) << 2;
                            }
                        }
                    }
                    FrameInfo {
                        index,
                        camera,
                        dropped: false,
                        timestamp_ns: self.scenario.timestamp_ns(index),
                    }
                } else {
                    match &mut frame.pixels {
                        Pixels::U8(px) => self.scenario.render_u8(index, camera, px),
                        Pixels::U16(px) => self.scenario.render_u16(index, camera, px),
                    }
                    .map_err(lost)?
                };
                if info.dropped {
                    dropped += 1;
                }
                if let Some(&c) = self.controls.get(slot) {
                    let max_dn = if frame.bit_depth == 10 { 1023.0 } else { 255.0 };
                    apply_sim_controls(&mut frame.pixels, c, max_dn, &mut self.noise_state);
                }
                // Each camera's own timestamp against the set's nominal instant (0 for
                // synchronous cameras; `[source.sim.timing]` makes them differ).
                let time = self.scenario.frame_time(index, camera);
                let skew_ns = time.reported_ns - nominal_ns;
                self.skew_ns[slot] = skew_ns;
                min_ts = min_ts.min(skew_ns);
                max_ts = max_ts.max(skew_ns);
                // The camera's own frame counter, as a real camera's driver gives it: a
                // free-running camera that drifted a period against the set grid shows the
                // same exposure twice (same sequence and timestamp) or skips one, never a new
                // number on an old exposure. Synchronous cameras: the set index.
                frame.sequence = u64::try_from(time.exposure_index).unwrap_or(0);
            }
            let render_end_ns = clock::monotonic_ns();
            let render_ns = render_end_ns - render_start_ns;
            // Lead: 1.5 × this rendering + 0.2 ms, decaying slowly after a slow one; never
            // more than most of a period.
            let want_ns = render_ns + render_ns / 2 + 200_000;
            self.render_lead_ns = want_ns
                .max(self.render_lead_ns - self.render_lead_ns / 64)
                .min(self.period_ns * 3 / 4);
            // Unpaced: the frames are captured when they are handed over, now.
            let capture_ns = match capture_ns {
                Some(due) => {
                    // Not before the last camera's own timestamp: a free-running camera
                    // stamped after the set's nominal instant has not exposed its frame yet
                    // (handing it over early showed its board's clock as ahead, by up to half
                    // a period, to a cluster solver).
                    clock::sleep_until_ns(due.saturating_add(max_ts.max(0).unsigned_abs()));
                    due
                }
                None => render_end_ns,
            };
            for (frame, skew) in out.frames.iter_mut().zip(&self.skew_ns) {
                frame.timestamp_ns = capture_ns.saturating_add_signed(*skew);
            }
            if dropped > 0 {
                // An incomplete set cannot be triangulated; the other cameras' frames are unpaired.
                self.stats.sets_dropped += 1;
                self.stats.unpaired_dropped += (out.frames.len() - dropped) as u64;
                continue;
            }
            out.index = index;
            out.pairing_error_ns = max_ts.abs_diff(min_ts);
            out.render_ns = render_ns;
            self.stats.sets_delivered += 1;
            return Ok(());
        }
    }

    fn stats(&self) -> SourceStats {
        self.stats.clone()
    }

    fn controls(&self) -> Vec<CameraControls> {
        self.controls
            .iter()
            .map(|c| CameraControls {
                exposure: Some(ControlValue {
                    value: c.exposure,
                    min: SIM_EXPOSURE_RANGE.0,
                    max: SIM_EXPOSURE_RANGE.1,
                }),
                gain: Some(ControlValue {
                    value: c.gain,
                    min: SIM_GAIN_RANGE.0,
                    max: SIM_GAIN_RANGE.1,
                }),
            })
            .collect()
    }

    fn set_control(
        &mut self,
        camera: usize,
        control: CameraControl,
        value: i64,
    ) -> std::result::Result<(), SourceError> {
        let count = self.controls.len();
        let c = self.controls.get_mut(camera).ok_or_else(|| {
            SourceError::Config(format!(
                "camera {camera} does not exist (the simulator has {count})"
            ))
        })?;
        let ((lo, hi), slot) = match control {
            CameraControl::Exposure => (SIM_EXPOSURE_RANGE, &mut c.exposure),
            CameraControl::Gain => (SIM_GAIN_RANGE, &mut c.gain),
        };
        if !(lo..=hi).contains(&value) {
            return Err(SourceError::Config(format!(
                "camera {camera}: {control:?} {value} is outside {lo}..={hi}"
            )));
        }
        *slot = value;
        Ok(())
    }

    fn describe(&self) -> String {
        let (w, h) = self.scenario.image_size();
        format!(
            "simulated {:?} rig, {} cameras {}x{} {}-bit at {} fps{}",
            self.cfg.rig,
            self.camera_count(),
            w,
            h,
            self.cfg.bit_depth,
            self.cfg.fps,
            if self.cfg.paced { "" } else { " (unpaced)" }
        )
    }
}
