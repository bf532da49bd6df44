//! Several tools and loose single LEDs in one frame set ([`MultiTracker`]).
//!
//! One correspondence step ([`PointMatcher`]) serves every tool. The tools are then identified
//! one after the other on the candidate points still free: tools with a recent pose first
//! (their predicted pose makes them the most reliable), then the others, in definition order.
//! A tracked tool claims the blobs of its LEDs in every camera, so ghosts made of its blobs and
//! another tool's (the 90° rig pairs any two LEDs at about the same image row) vanish from the
//! set the next tools see. Identities need no bookkeeping across frames: a tool is whatever
//! matches its own layout, and [`check_tool_set`] refuses sets in which any LEDs of one tool
//! could pass for another (the cross-tool identification margin). Candidates left over become
//! loose LEDs, associated frame to frame with a constant-velocity predictor to keep their ids.
//!
//! Fixed capacity: every buffer is allocated by [`MultiTracker::new`]; `process` allocates
//! nothing.

use alloc::format;
use alloc::vec::Vec;

use nalgebra::Vector3;

use super::config::{MAX_CAMERAS, MAX_TOOL_LEDS, NO_BLOB, PoseConfig};
use super::identify::{self, Hypothesis, NO_LED, ToolModel};
use super::matching::{PointMatcher, TriangulatedPoint};
use super::{Decide, Pose6d, PoseStatus, Reference, layout_centroid};
use crate::blob::Blob;
use crate::params::{RigParams, ToolDefinition};
use crate::{Error, Result};

/// Most tools tracked at once.
pub const MAX_TOOLS: usize = 8;
/// Most loose single LEDs reported per frame set.
pub const MAX_LOOSE_LEDS: usize = 16;
/// [`MultiTracker::blob_owner`]: the blob went to no tool and no loose LED.
pub const NO_TOOL: u8 = u8::MAX;
/// [`MultiTracker::blob_owner`]: the blob belongs to a loose LED.
pub const LOOSE_LED: u8 = u8::MAX - 1;

/// A loose LED lost after being tracked this many frame sets in a row is still looked for in
/// the merge audit (its spot may be hidden in a tool LED's blob); shorter tracks are often
/// ghosts or another tool's LEDs and would block good poses.
const ESTABLISHED_LOOSE_FRAMES: u32 = 10;

/// Merge audit: a loose LED or another tool's LED estimate within this distance (mm, 3-D) of
/// a tool's measured LED is that LED itself, not a second spot merged into its blob.
const SAME_POINT_MM: f64 = 5.0;

/// A new point one of whose blobs has its centroid this close (px) to where a tool's LED
/// projects is made with that LED's image, not a loose LED. A tracked LED's blob lies within a
/// few tenths of a pixel of its projection; a real loose LED's spot merged with a tool LED's
/// shifts the centroid by half their separation, so it is taken for the LED only when the two
/// spots are within about 4 px (such a point is biased anyway). Tried 2, 3, 4 and 6 px in the
/// simulator's 90° pair: 6 px delayed the loose LED's reacquisitions (61 fewer frames).
const TOOL_LED_IMAGE_PX: f64 = 2.0;

/// Blob indices a camera can have in the matcher (the configuration caps
/// `max_blobs_per_camera` at 64): claims are one bit per blob.
const MAX_BLOBS: usize = 64;

/// A single LED that belongs to no tool, with an id kept while it is tracked.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LooseLed {
    /// Stable id: the same LED keeps it from frame to frame (new LEDs get new ids).
    pub id: u32,
    /// Camera-0 frame (mm).
    pub position_mm: [f64; 3],
    /// Ray gap (two views) or RMS ray distance (more views), mm.
    pub gap_mm: f64,
    /// Cameras contributing.
    pub cameras: u8,
    /// Consecutive frame sets it has been tracked in (1 = new).
    pub frames_tracked: u32,
}

#[derive(Debug, Clone, Copy)]
struct LooseTrack {
    led: LooseLed,
    velocity_mm: Vector3<f64>,
    frames_ago: u32,
    /// Frame sets it had been tracked in a row when it was last lost (0 while tracked).
    run_before_loss: u32,
    /// [`NO_TOOL`]: a loose LED; else the tool whose candidate LED this is (not reported, no
    /// id: see `MultiTracker::track_loose`).
    tool: u8,
}

#[derive(Debug, Clone)]
struct ToolSlot {
    model: ToolModel,
    centroid_mm: Vector3<f64>,
    reference: Option<Reference>,
    pose: Pose6d,
    /// Frame sets since this tool was last tracked (0: tracked in the last one).
    frames_since_tracked: u32,
    /// The candidate point each LED of the current pose came from (the merge audit re-solves
    /// an LED without a camera where its blob is shared).
    led_points: [Option<TriangulatedPoint>; MAX_TOOL_LEDS],
}

/// Checks a set of tools against each other (each must already be a valid [`ToolModel`]):
/// no LEDs of one tool may reproduce another tool's distances within `min_margin_mm`, or
/// the tracker of the second could identify the first as it. The error names both tools.
pub fn check_tool_set(tools: &[ToolModel], config: &PoseConfig) -> Result<()> {
    if tools.len() > MAX_TOOLS {
        return Err(Error::InvalidParams {
            reason: format!(
                "{} tools defined; at most {MAX_TOOLS} are tracked at once",
                tools.len()
            ),
        });
    }
    for (i, a) in tools.iter().enumerate() {
        for (j, b) in tools.iter().enumerate() {
            if i == j {
                continue;
            }
            let margin = a.cross_margin_mm(b);
            if margin < config.min_margin_mm {
                return Err(Error::InvalidParams {
                    reason: format!(
                        "tools {:?} and {:?} are confusable: {} of {:?}'s LEDs reproduce {:?}'s \
                         distances within {margin:.2} mm (need a cross-tool margin ≥ {} mm); \
                         change one of the layouts",
                        a.name(),
                        b.name(),
                        a.min_leds(),
                        b.name(),
                        a.name(),
                        config.min_margin_mm
                    ),
                });
            }
        }
    }
    Ok(())
}

/// 6-DOF tracking of up to [`MAX_TOOLS`] tools plus loose single LEDs (see the module docs).
#[derive(Debug, Clone)]
pub struct MultiTracker {
    config: PoseConfig,
    matcher: PointMatcher,
    tools: Vec<ToolSlot>,
    hypotheses: Vec<Hypothesis>,
    /// This tool's view of the candidates: those sharing no blob with a claimed one.
    free: Vec<TriangulatedPoint>,
    /// Claimed blobs per camera (bit per blob index).
    claimed: [u64; MAX_CAMERAS],
    owner: [[u8; MAX_BLOBS]; MAX_CAMERAS],
    /// Loose LEDs and tools' candidate LEDs (points of a tool not tracked in the set).
    loose_tracks: Vec<LooseTrack>,
    loose: Vec<LooseLed>,
    next_loose_id: u32,
}

impl MultiTracker {
    /// Validates every tool (alone and against each other) and allocates every buffer.
    ///
    /// The matcher's per-camera blob and candidate limits are raised to what the tools' LEDs
    /// need (`max_blobs_per_camera` ≥ all LEDs + 8, `max_candidates` ≥ 4 × all LEDs + 16,
    /// within the configuration's caps); [`MultiTracker::config`] reports the values in use.
    pub fn new(rig: &RigParams, tools: &[ToolDefinition], config: PoseConfig) -> Result<Self> {
        config.validate()?;
        let models = tools
            .iter()
            .map(|t| ToolModel::new(t, &config))
            .collect::<Result<Vec<_>>>()?;
        check_tool_set(&models, &config)?;
        let leds: usize = models.iter().map(ToolModel::led_count).sum();
        let mut config = config;
        config.max_blobs_per_camera = config.max_blobs_per_camera.max((leds + 8).min(MAX_BLOBS));
        config.max_candidates = config.max_candidates.max((4 * leds + 16).min(NO_LED as usize));
        let matcher = PointMatcher::new(rig, &config)?;
        let tools = models
            .into_iter()
            .map(|model| ToolSlot {
                centroid_mm: model.centroid_mm(),
                pose: Pose6d::empty(PoseStatus::TooFewLeds {
                    points: 0,
                    needed: model.min_leds() as u32,
                }),
                model,
                reference: None,
                frames_since_tracked: u32::MAX,
                led_points: [None; MAX_TOOL_LEDS],
            })
            .collect();
        Ok(MultiTracker {
            config,
            matcher,
            tools,
            hypotheses: Vec::with_capacity(config.max_hypotheses),
            free: Vec::with_capacity(config.max_candidates),
            claimed: [0; MAX_CAMERAS],
            owner: [[NO_TOOL; MAX_BLOBS]; MAX_CAMERAS],
            loose_tracks: Vec::with_capacity(MAX_LOOSE_LEDS + leds),
            loose: Vec::with_capacity(MAX_LOOSE_LEDS),
            next_loose_id: 0,
        })
    }

    /// The configuration in use (with the raised matcher limits).
    pub fn config(&self) -> &PoseConfig {
        &self.config
    }

    /// Number of tools.
    pub fn tool_count(&self) -> usize {
        self.tools.len()
    }

    /// Tool `i` (definition order).
    pub fn tool(&self, i: usize) -> Option<&ToolModel> {
        self.tools.get(i).map(|t| &t.model)
    }

    /// Index of the tool called `name`.
    pub fn tool_index(&self, name: &str) -> Option<usize> {
        self.tools.iter().position(|t| t.model.name() == name)
    }

    /// The last pose of tool `i`.
    pub fn pose(&self, i: usize) -> Option<&Pose6d> {
        self.tools.get(i).map(|t| &t.pose)
    }

    /// Frame sets since tool `i` was last tracked (0: in the last one; `u32::MAX`: never).
    pub fn frames_since_tracked(&self, i: usize) -> u32 {
        self.tools.get(i).map_or(u32::MAX, |t| t.frames_since_tracked)
    }

    /// Loose LEDs of the last frame set.
    pub fn loose_leds(&self) -> &[LooseLed] {
        &self.loose
    }

    /// Candidate 3-D points of the last frame set.
    pub fn points(&self) -> &[TriangulatedPoint] {
        self.matcher.points()
    }

    /// Who got blob `blob` of camera `camera` in the last frame set: a tool index,
    /// [`LOOSE_LED`] or [`NO_TOOL`].
    pub fn blob_owner(&self, camera: usize, blob: usize) -> u8 {
        self.owner
            .get(camera)
            .and_then(|o| o.get(blob))
            .copied()
            .unwrap_or(NO_TOOL)
    }

    /// Forget every previous pose and loose LED (after a parameter swap or a long gap).
    pub fn reset(&mut self) {
        for t in &mut self.tools {
            t.reference = None;
            t.frames_since_tracked = u32::MAX;
        }
        self.loose_tracks.clear();
    }

    /// Processes one frame set: one blob list per camera, in camera order.
    pub fn process(&mut self, blobs: &[&[Blob]]) -> Result<()> {
        self.matcher.solve(blobs)?;
        self.claimed = [0; MAX_CAMERAS];
        for o in &mut self.owner {
            o.fill(NO_TOOL);
        }
        let cfg = self.config;
        for t in &mut self.tools {
            t.frames_since_tracked = t.frames_since_tracked.saturating_add(1);
            if let Some(r) = &mut t.reference
                && !r.age(cfg.max_coast_frames)
            {
                t.reference = None;
            }
        }
        // Tools with a (recent) reference first, most recently tracked first; then the rest.
        let mut order = [0u8; MAX_TOOLS];
        let n = self.tools.len();
        for (i, o) in order.iter_mut().enumerate().take(n) {
            *o = i as u8;
        }
        let key = |t: &ToolSlot| t.reference.map_or(u32::MAX, |r| r.frames_ago);
        order[..n].sort_unstable_by_key(|&i| (key(&self.tools[i as usize]), i));
        for &ti in &order[..n] {
            self.track_tool(ti as usize);
        }
        self.track_loose();
        for ti in 0..n {
            self.audit_merges(ti);
            let slot = &mut self.tools[ti];
            if slot.pose.status == PoseStatus::Tracked {
                slot.reference = Some(Reference::after(
                    slot.reference.as_ref(),
                    slot.pose.quaternion_wxyz,
                    layout_centroid(&slot.pose, &slot.centroid_mm),
                ));
                slot.frames_since_tracked = 0;
            }
        }
        Ok(())
    }

    /// Where tool `ti`'s LED `led` is this frame: from its pose if tracked, else predicted
    /// from its reference; `None` when unknown.
    fn led_estimate_mm(&self, ti: usize, led: usize) -> Option<Vector3<f64>> {
        let slot = &self.tools[ti];
        let l = slot.model.leds_mm().get(led)?;
        if slot.pose.status == PoseStatus::Tracked {
            let r = nalgebra::Matrix3::from_row_slice(&slot.pose.r_row_major);
            return Some(r * l + Vector3::from(slot.pose.position_mm));
        }
        let (q, c) = slot.reference.as_ref()?.predicted();
        let q = super::unit_quaternion(&q);
        Some(q * (l - slot.centroid_mm) + c)
    }

    /// LEDs of tracked tool `ti` whose image in some camera lies within `merge_radius_px` of
    /// another tool's LED or a loose LED: their blob is probably two spots merged, with a
    /// biased centroid. The pose is refitted without them when 3 or more LEDs remain, else
    /// the frame is `LedsMerged` for this tool.
    fn audit_merges(&mut self, ti: usize) {
        let pose = self.tools[ti].pose;
        if pose.status != PoseStatus::Tracked {
            return;
        }
        let radius = self.config.merge_radius_px;
        let mut suspect = 0u32;
        let mut suspect_cams = [0u32; MAX_TOOL_LEDS];
        let mut first: Option<(u32, u32)> = None;
        for led in (0..MAX_TOOL_LEDS).filter(|l| pose.led_mask & (1 << l) != 0) {
            let p = self
                .led_estimate_mm(ti, led)
                .unwrap_or_else(|| Vector3::from(pose.leds_mm[led]));
            let used = self.tools[ti].led_points[led].map(|q| q.blobs);
            let measured = Vector3::from(pose.leds_mm[led]);
            for (c, cam) in self.matcher.cams.iter().enumerate() {
                // A camera whose blob the LED's point does not use cannot bias it.
                if used.is_some_and(|b| b[c] == NO_BLOB) {
                    continue;
                }
                let Ok(px) = cam.model.project(&cam.cam_from_cam0.apply(&p)) else {
                    continue;
                };
                // Something at this LED's own place in 3-D is this LED (a loose track of it
                // from frames where the tool was lost), not a second spot in its blob.
                let near = |q: &Vector3<f64>| {
                    (q - measured).norm() > SAME_POINT_MM
                        && cam
                            .model
                            .project(&cam.cam_from_cam0.apply(q))
                            .is_ok_and(|qx| (qx - px).norm() < radius)
                };
                // Loose LEDs and other tools' candidate LEDs found this frame.
                let mut hit = self
                    .loose_tracks
                    .iter()
                    .any(|t| t.frames_ago == 0 && near(&Vector3::from(t.led.position_mm)));
                // A loose LED not found this frame may be hidden in this very blob: where its
                // track predicts it.
                hit |= self
                    .loose_tracks
                    .iter()
                    .filter(|t| t.frames_ago > 0 && t.run_before_loss >= ESTABLISHED_LOOSE_FRAMES)
                    .any(|t| {
                        near(&(Vector3::from(t.led.position_mm) + t.velocity_mm * f64::from(t.frames_ago)))
                    });
                for other in (0..self.tools.len()).filter(|&o| o != ti) {
                    for ol in 0..self.tools[other].model.led_count() {
                        hit |= self.led_estimate_mm(other, ol).is_some_and(|q| near(&q));
                    }
                }
                if hit {
                    suspect |= 1 << led;
                    suspect_cams[led] |= 1 << c;
                    first.get_or_insert((led as u32, c as u32));
                }
            }
        }
        // Three or more cameras: a suspect LED seen on its own by two or more other cameras is
        // re-solved from those instead of dropped.
        let mut leds_mm = pose.leds_mm;
        let mut resolved = 0u32;
        for led in (0..MAX_TOOL_LEDS).filter(|l| suspect & (1 << l) != 0) {
            let Some(p) = self.tools[ti].led_points[led] else {
                continue;
            };
            if let Some(q) = self.matcher.without_cameras(&p, suspect_cams[led]) {
                leds_mm[led] = q.point_mm.into();
                resolved |= 1 << led;
            }
        }
        let suspect = suspect & !resolved;
        let slot = &mut self.tools[ti];
        let cfg = &self.config;
        let fit_of = |mask: u32| {
            let mut model = [Vector3::zeros(); MAX_TOOL_LEDS];
            let mut measured = [Vector3::zeros(); MAX_TOOL_LEDS];
            let mut k = 0;
            for led in (0..MAX_TOOL_LEDS).filter(|l| mask & (1 << l) != 0) {
                model[k] = slot.model.leds_mm()[led];
                measured[k] = Vector3::from(leds_mm[led]);
                k += 1;
            }
            (k >= 3)
                .then(|| super::fit::fit_rigid_horn(&model[..k], &measured[..k]))
                .flatten()
        };
        let mut keep = pose.led_mask & !suspect;
        if suspect == 0 && resolved == 0 {
            // No known neighbour, but a residual far above the noise from 4+ LEDs: one LED is
            // probably biased (a spot merged with something the tracker does not know).
            if pose.residual_rms_mm <= cfg.outlier_residual_mm {
                return;
            }
            if pose.leds_used < 4 {
                // Three LEDs cannot tell which one is biased: no pose rather than a skewed one.
                slot.pose.status = PoseStatus::ResidualTooLarge;
                return;
            }
            let best = (0..MAX_TOOL_LEDS)
                .filter(|l| pose.led_mask & (1 << l) != 0)
                .filter_map(|l| fit_of(pose.led_mask & !(1 << l)).map(|f| (l, f.rms_mm)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            match best {
                Some((l, rms)) if rms <= cfg.outlier_residual_mm => keep = pose.led_mask & !(1 << l),
                _ => return,
            }
        }
        let fit = fit_of(keep).filter(|f| f.rms_mm <= cfg.max_residual_mm);
        let Some(f) = fit else {
            let (led, camera) = first.unwrap_or((0, 0));
            slot.pose.status = PoseStatus::LedsMerged { led, camera };
            return;
        };
        let k = keep.count_ones();
        let p = &mut slot.pose;
        p.position_mm = f.translation_mm.into();
        p.tip_mm = (f.rotation * slot.model.tip_mm + f.translation_mm).into();
        p.quaternion_wxyz = f.quaternion_wxyz;
        for i in 0..3 {
            for j in 0..3 {
                p.r_row_major[i * 3 + j] = f.rotation[(i, j)];
            }
        }
        p.residual_rms_mm = f.rms_mm;
        p.residual_max_mm = f.max_mm;
        p.led_mask = keep;
        p.leds_used = k;
        p.leds_mm = leds_mm;
    }

    /// The candidates the next tool (or the loose LEDs) may use: those sharing no blob with a
    /// claimed one, and, with three or more cameras, those that do, re-solved without the
    /// claimed cameras when two or more cameras remain (a blob merged with another tool's LED
    /// in one camera no longer hides the LED from the cameras that see it on its own).
    fn fill_free(&mut self) {
        self.free.clear();
        // Blobs used by two or more unclaimed candidates confirmed by three or more cameras:
        // possibly two LEDs whose spots merged in that camera.
        let mut uses = [[0u8; MAX_BLOBS]; MAX_CAMERAS];
        let multi = self.matcher.camera_count() > 2;
        if multi {
            for p in self.matcher.points() {
                if p.cameras < 3 || self.claimed_cameras(p) != 0 {
                    continue;
                }
                for (c, &b) in p.blobs.iter().enumerate() {
                    if b != NO_BLOB && (b as usize) < MAX_BLOBS {
                        uses[c][b as usize] = uses[c][b as usize].saturating_add(1);
                    }
                }
            }
        }
        for i in 0..self.matcher.points().len() {
            if self.free.len() == self.free.capacity() {
                break;
            }
            let p = self.matcher.points()[i];
            let mut claimed = self.claimed_cameras(&p);
            if multi && p.cameras >= 3 && claimed == 0 {
                claimed = self.merged_cameras(i, &uses);
            }
            if claimed == 0 {
                // A two-view candidate whose blobs all belong to candidates confirmed by three
                // or more cameras is a ghost made of their rays: with 3+ cameras a real LED seen
                // on its own by two cameras gets no third view only where it is hidden, so
                // this costs no LED but takes the near-duplicates of true LEDs (a few mm off)
                // that make a tool ambiguous.
                let explained = multi
                    && p.cameras == 2
                    && p.blobs
                        .iter()
                        .enumerate()
                        .all(|(c, &b)| b == NO_BLOB || ((b as usize) < MAX_BLOBS && uses[c][b as usize] > 0));
                if !explained {
                    self.free.push(p);
                }
                continue;
            }
            match self.matcher.without_cameras(&p, claimed) {
                Some(q) => {
                    // Re-solved points are two-view candidates again: keep them only if no
                    // candidate already covers the same blobs.
                    let dup = self.free.iter().any(|f| f.blobs == q.blobs);
                    if !dup && q.gap_mm <= self.config.max_gap_mm {
                        self.free.push(q);
                    }
                }
                // Shared (not claimed) blobs in all but one camera: the point is more likely
                // the LED itself than a set of merges; it stays as it is.
                None if self.claimed_cameras(&p) == 0 => self.free.push(p),
                None => {}
            }
        }
    }

    /// Cameras (bit per camera) in which unclaimed candidate `i` (three or more cameras)
    /// shares its blob with exactly one other such candidate's, the two sharing no other
    /// blob: two LEDs whose spots merged in that camera (both are re-solved without it). Two
    /// candidates sharing blobs in two or more cameras are one LED and a ghost made of its
    /// rays (a third view confirms ghosts often enough in a 4-camera rig): that is no merge,
    /// and taking those cameras away would leave the true LED too few views.
    fn merged_cameras(&self, i: usize, uses: &[[u8; MAX_BLOBS]; MAX_CAMERAS]) -> u32 {
        let points = self.matcher.points();
        let p = &points[i];
        let mut mask = 0u32;
        for (c, &b) in p.blobs.iter().enumerate() {
            if b == NO_BLOB || (b as usize) >= MAX_BLOBS || uses[c][b as usize] < 2 {
                continue;
            }
            let merge = points.iter().enumerate().any(|(j, q)| {
                j != i
                    && q.cameras >= 3
                    && q.blobs[c] == b
                    && self.claimed_cameras(q) == 0
                    && p.blobs
                        .iter()
                        .zip(&q.blobs)
                        .filter(|(x, y)| **x != NO_BLOB && x == y)
                        .count()
                        == 1
            });
            if merge {
                mask |= 1 << c;
            }
        }
        mask
    }

    /// Cameras (bit per camera) in which `p`'s blob is claimed.
    fn claimed_cameras(&self, p: &TriangulatedPoint) -> u32 {
        let mut mask = 0;
        for (c, (&b, &cl)) in p.blobs.iter().zip(&self.claimed).enumerate() {
            if b != NO_BLOB && (b as usize) < MAX_BLOBS && cl & (1u64 << b) != 0 {
                mask |= 1 << c;
            }
        }
        mask
    }

    fn track_tool(&mut self, ti: usize) {
        let cfg = self.config;
        self.fill_free();
        let slot = &self.tools[ti];
        let overflow =
            identify::find_assignments(&slot.model, &self.free, cfg.distance_tol_mm, &mut self.hypotheses);
        let (pose, chosen) = Decide {
            cfg: &cfg,
            tool: &slot.model,
            tool_centroid_mm: slot.centroid_mm,
            points: &self.free,
            hypotheses: &self.hypotheses,
            overflow,
            reference: slot.reference.as_ref(),
            cams: &self.matcher.cams,
        }
        .run();
        self.tools[ti].led_points = [None; MAX_TOOL_LEDS];
        if let Some(assign) = chosen {
            for (led, &c) in assign.iter().take(MAX_TOOL_LEDS).enumerate() {
                if let Some(p) = self.free.get(c as usize) {
                    let p = *p;
                    self.claim(&p, ti as u8);
                    self.tools[ti].led_points[led] = Some(p);
                }
            }
        }
        // The reference is updated after the merge audit (in `process`).
        self.tools[ti].pose = pose;
    }

    fn is_claimed(&self, p: &TriangulatedPoint) -> bool {
        p.blobs
            .iter()
            .zip(&self.claimed)
            .any(|(&b, &c)| b != NO_BLOB && (b as usize) < MAX_BLOBS && c & (1u64 << b) != 0)
    }

    fn claim(&mut self, p: &TriangulatedPoint, owner: u8) {
        for (c, &b) in p.blobs.iter().enumerate() {
            if b != NO_BLOB && (b as usize) < MAX_BLOBS {
                self.claimed[c] |= 1u64 << b;
                self.owner[c][b as usize] = owner;
            }
        }
    }

    /// Loose LEDs: the free candidates, each known point first taking the closest one to its
    /// predicted position (within `loose_gate_mm`, also after a gap), then new ones by
    /// increasing ray gap (a ghost shares a blob with two true points and has the larger gap).
    ///
    /// A tool's LEDs are not loose LEDs: a new point within `loose_gate_mm` of an LED of a
    /// tool — where its pose puts it, or where its predictor does during a gap of up to
    /// `max_coast_frames` — is that tool's candidate LED. It is followed like a loose LED
    /// (so it stays the tool's while the tool is lost, however long) but gets no id and is
    /// not reported; its blobs go to the tool ([`MultiTracker::blob_owner`]). Once the tool is
    /// tracked again its candidates end (its LEDs are claimed by its pose).
    fn track_loose(&mut self) {
        let cfg = self.config;
        self.fill_free();
        self.loose.clear();
        let tools = &self.tools;
        self.loose_tracks.retain(|t| {
            t.tool == NO_TOOL
                || tools
                    .get(t.tool as usize)
                    .is_some_and(|s| s.pose.status != PoseStatus::Tracked)
        });
        // Longest-tracked points choose first.
        self.loose_tracks
            .sort_unstable_by_key(|t| core::cmp::Reverse(t.led.frames_tracked));
        for k in 0..self.loose_tracks.len() {
            let tr = self.loose_tracks[k];
            let ahead = f64::from(tr.frames_ago + 1);
            let predicted = Vector3::from(tr.led.position_mm) + tr.velocity_mm * ahead;
            let mut best: Option<(f64, usize)> = None;
            for (i, p) in self.free.iter().enumerate() {
                if self.is_claimed(p) {
                    continue;
                }
                let d = (p.point_mm - predicted).norm();
                if d <= cfg.loose_gate_mm && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, i));
                }
            }
            let t = &mut self.loose_tracks[k];
            match best {
                Some((_, i)) => {
                    let p = self.free[i];
                    let prev = Vector3::from(t.led.position_mm);
                    t.velocity_mm = (p.point_mm - prev) / ahead;
                    t.frames_ago = 0;
                    t.run_before_loss = 0;
                    t.led.position_mm = p.point_mm.into();
                    t.led.gap_mm = p.gap_mm;
                    t.led.cameras = p.cameras;
                    t.led.frames_tracked = t.led.frames_tracked.saturating_add(1);
                    let (led, tool) = (t.led, t.tool);
                    if tool == NO_TOOL {
                        self.claim(&p, LOOSE_LED);
                        self.loose.push(led);
                    } else {
                        self.claim(&p, tool);
                    }
                }
                None => {
                    if t.frames_ago == 0 {
                        t.run_before_loss = t.led.frames_tracked;
                    }
                    t.frames_ago += 1;
                    t.led.frames_tracked = 0;
                }
            }
        }
        let max_coast = cfg.max_coast_frames;
        self.loose_tracks.retain(|t| t.frames_ago <= max_coast);
        self.free.sort_unstable_by(|a, b| a.gap_mm.total_cmp(&b.gap_mm));
        for i in 0..self.free.len() {
            let p = self.free[i];
            if self.is_claimed(&p) || self.loose_tracks.len() == self.loose_tracks.capacity() {
                continue;
            }
            let tool = self.tool_led_near(&p.point_mm, cfg.loose_gate_mm);
            let loose = self.loose_tracks.iter().filter(|t| t.tool == NO_TOOL).count();
            if tool.is_none() && (loose >= MAX_LOOSE_LEDS || self.uses_tool_led_image(&p)) {
                continue;
            }
            let led = LooseLed {
                id: if tool.is_none() {
                    self.next_loose_id
                } else {
                    u32::MAX
                },
                position_mm: p.point_mm.into(),
                gap_mm: p.gap_mm,
                cameras: p.cameras,
                frames_tracked: 1,
            };
            self.loose_tracks.push(LooseTrack {
                led,
                velocity_mm: Vector3::zeros(),
                frames_ago: 0,
                run_before_loss: 0,
                tool: tool.map_or(NO_TOOL, |t| t as u8),
            });
            match tool {
                Some(t) => self.claim(&p, t as u8),
                None => {
                    self.next_loose_id = self.next_loose_id.wrapping_add(1);
                    self.claim(&p, LOOSE_LED);
                    if self.loose.len() < self.loose.capacity() {
                        self.loose.push(led);
                    }
                }
            }
        }
    }

    /// Whether one of `p`'s blobs lies within [`TOOL_LED_IMAGE_PX`] of the image of a tool's LED
    /// (tracked, predicted, or a candidate LED found this set) that is not `p` itself: `p` is
    /// then a ghost made with that LED's ray (its blob in that camera went unclaimed when the
    /// LED's point did not use it) or a spot merged with the LED, a biased point either way.
    fn uses_tool_led_image(&self, p: &TriangulatedPoint) -> bool {
        let gate = self.config.loose_gate_mm;
        for (c, cam) in self.matcher.cams.iter().enumerate() {
            let b = p.blobs.get(c).copied().unwrap_or(NO_BLOB);
            let Some(bpx) = (b != NO_BLOB).then(|| self.matcher.blob_px(c, b)).flatten() else {
                continue;
            };
            let hit = |q: &Vector3<f64>| {
                (q - p.point_mm).norm() > gate
                    && cam.model.project(&cam.cam_from_cam0.apply(q)).is_ok_and(|qx| {
                        (qx - nalgebra::Vector2::new(bpx[0], bpx[1])).norm() < TOOL_LED_IMAGE_PX
                    })
            };
            for ti in 0..self.tools.len() {
                for led in 0..self.tools[ti].model.led_count() {
                    match self.led_estimate_mm(ti, led) {
                        Some(q) if hit(&q) => return true,
                        Some(_) => {}
                        None => break,
                    }
                }
            }
            let candidate = self
                .loose_tracks
                .iter()
                .filter(|t| t.tool != NO_TOOL && t.frames_ago == 0)
                .any(|t| hit(&Vector3::from(t.led.position_mm)));
            if candidate {
                return true;
            }
        }
        false
    }

    /// The tool one of whose LEDs is within `gate_mm` of `p` (its pose's LED if tracked, else
    /// its predicted LED during a gap), the nearest such LED's tool.
    fn tool_led_near(&self, p: &Vector3<f64>, gate_mm: f64) -> Option<usize> {
        let mut best: Option<(f64, usize)> = None;
        for ti in 0..self.tools.len() {
            for led in 0..self.tools[ti].model.led_count() {
                let Some(q) = self.led_estimate_mm(ti, led) else {
                    break;
                };
                let d = (q - p).norm();
                if d <= gate_mm && best.is_none_or(|(bd, _)| d < bd) {
                    best = Some((d, ti));
                }
            }
        }
        best.map(|(_, ti)| ti)
    }
}

#[cfg(test)]
mod tests {
    use alloc::string::ToString;
    use alloc::vec;

    use nalgebra::{UnitQuaternion, Vector3};

    use super::*;
    use crate::camera::{CameraModel, Distortion, ImageSize, Intrinsics, RigidTransform};
    use crate::params::CameraParams;
    use crate::pose6d::quaternion_angle_rad;

    fn camera() -> CameraModel {
        CameraModel {
            intrinsics: Intrinsics {
                fx_px: 1000.0,
                fy_px: 1000.0,
                cx_px: 999.5,
                cy_px: 999.5,
            },
            distortion: Distortion::NONE,
            image_size: ImageSize {
                width_px: 2000,
                height_px: 2000,
            },
        }
    }

    /// Parallel cameras: camera 1 300 mm along x (its epipolar lines are image rows, so any two
    /// LEDs at one height make ghosts), camera 2 (if asked) 300 mm along y.
    fn rig(cameras: usize) -> RigParams {
        let shifted = |t: [f64; 3]| CameraParams {
            model: camera(),
            cam_from_cam0: RigidTransform {
                t_mm: t,
                ..RigidTransform::IDENTITY
            },
        };
        let all = [
            shifted([0.0; 3]),
            shifted([-300.0, 0.0, 0.0]),
            shifted([0.0, -300.0, 0.0]),
        ];
        RigParams {
            rig_id: "multi".into(),
            created_unix_s: 0,
            cameras: all[..cameras].to_vec(),
            world_from_cam0: None,
            tools: Vec::new(),
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }

    fn tool(name: &str, leds_mm: &[[f64; 3]]) -> ToolDefinition {
        ToolDefinition {
            name: name.into(),
            leds_mm: leds_mm.to_vec(),
            tip_mm: None,
        }
    }

    fn tools() -> Vec<ToolDefinition> {
        vec![
            tool(
                "probe4",
                &[
                    [0.0, 0.0, 0.0],
                    [99.0, 0.0, 0.0],
                    [3.0, 85.0, 0.0],
                    [62.0, 11.0, 32.0],
                ],
            ),
            tool("tri3", &[[0.0, 0.0, 0.0], [110.0, 0.0, 0.0], [81.8, 60.0, 0.0]]),
            tool(
                "wing4",
                &[
                    [0.0, 0.0, 0.0],
                    [166.0, 66.0, 27.0],
                    [15.0, -75.0, 24.0],
                    [122.0, 20.0, 1.0],
                ],
            ),
        ]
    }

    /// Ground truth of one frame: pose per tool, the loose LED.
    struct Scene {
        poses: Vec<(UnitQuaternion<f64>, Vector3<f64>)>,
        loose: Vector3<f64>,
    }

    /// Tools on straight paths through a common region (they cross at frame ~30), turning.
    fn scene(frame: usize) -> Scene {
        let f = frame as f64;
        let poses = vec![
            (
                UnitQuaternion::from_euler_angles(0.3 + 0.01 * f, -0.2, 0.1),
                Vector3::new(-150.0 + 5.0 * f, -40.0, 1000.0),
            ),
            (
                UnitQuaternion::from_euler_angles(-0.4, 0.2 + 0.012 * f, 0.7),
                Vector3::new(150.0 - 5.0 * f, 10.0, 1030.0),
            ),
            (
                UnitQuaternion::from_euler_angles(0.1, 0.5, -0.3 + 0.008 * f),
                Vector3::new(-20.0, -170.0 + 5.5 * f, 980.0),
            ),
        ];
        Scene {
            poses,
            loose: Vector3::new(60.0 - 2.0 * f, 120.0, 1010.0 + f),
        }
    }

    /// Every LED projected into every camera, blobs in a scrambled order; `hide(camera, tool)`
    /// drops a tool's blobs from a camera (`tool` = 3: the loose LED).
    fn blobs(
        rig: &RigParams,
        defs: &[ToolDefinition],
        s: &Scene,
        hide: impl Fn(usize, usize) -> bool,
    ) -> Vec<Vec<Blob>> {
        blobs_of_leds(rig, defs, s, |c, k, _| hide(c, k))
    }

    /// [`blobs`], `hide(camera, tool, led)` dropping single LEDs.
    fn blobs_of_leds(
        rig: &RigParams,
        defs: &[ToolDefinition],
        s: &Scene,
        hide: impl Fn(usize, usize, usize) -> bool,
    ) -> Vec<Vec<Blob>> {
        let mut pts: Vec<(usize, usize, Vector3<f64>)> = Vec::new();
        for (k, (d, (q, t))) in defs.iter().zip(&s.poses).enumerate() {
            for (i, l) in d.leds_mm.iter().enumerate() {
                pts.push((k, i, q * Vector3::from(*l) + t));
            }
        }
        pts.push((3, 0, s.loose));
        rig.cameras
            .iter()
            .enumerate()
            .map(|(c, cam)| {
                let mut v: Vec<Blob> = pts
                    .iter()
                    .filter(|(k, i, _)| !hide(c, *k, *i))
                    .map(|(_, _, p)| {
                        let px = cam.model.project(&cam.cam_from_cam0.apply(p)).unwrap();
                        Blob {
                            x_px: px.x,
                            y_px: px.y,
                            area_px: 9,
                            roundness: 1.0,
                            ..Blob::default()
                        }
                    })
                    .collect();
                v.reverse();
                let n = v.len();
                v.rotate_left((c * 3) % n.max(1));
                v
            })
            .collect()
    }

    fn run(tracker: &mut MultiTracker, b: &[Vec<Blob>]) {
        let lists: Vec<&[Blob]> = b.iter().map(|v| v.as_slice()).collect();
        tracker.process(&lists).unwrap();
    }

    /// Tracked poses must be the truth (exact projections): anything else is a swap.
    fn check_poses(tracker: &MultiTracker, s: &Scene, frame: usize) -> usize {
        let mut tracked = 0;
        for (k, (q, t)) in s.poses.iter().enumerate() {
            let p = tracker.pose(k).unwrap();
            if p.status != PoseStatus::Tracked {
                continue;
            }
            tracked += 1;
            let qt = [q.w, q.i, q.j, q.k];
            let e_rot = quaternion_angle_rad(&p.quaternion_wxyz, &qt).to_degrees();
            let e_pos = (Vector3::from(p.position_mm) - t).norm();
            assert!(
                e_rot < 1e-4 && e_pos < 1e-6,
                "frame {frame} tool {k}: {e_rot}° {e_pos} mm"
            );
        }
        tracked
    }

    #[test]
    fn three_tools_and_a_loose_led_cross_without_swaps_and_keep_ids() {
        for cameras in [2, 3] {
            let rig = rig(cameras);
            let defs = tools();
            let mut tracker = MultiTracker::new(&rig, &defs, PoseConfig::default()).unwrap();
            let (mut tracked, mut loose_id, mut loose_frames) = (0, None, 0);
            for frame in 0..60 {
                let s = scene(frame);
                run(&mut tracker, &blobs(&rig, &defs, &s, |_, _| false));
                tracked += check_poses(&tracker, &s, frame);
                for l in tracker.loose_leds() {
                    if (Vector3::from(l.position_mm) - s.loose).norm() < 1e-6 {
                        assert!(loose_id.is_none_or(|id| id == l.id), "loose LED changed id");
                        loose_id = Some(l.id);
                        loose_frames += 1;
                    }
                }
            }
            // Exact projections: where two LEDs are not at one image position, everything is
            // tracked; the crossing costs at most a few frames.
            assert!(
                tracked >= 3 * 60 - 12,
                "{cameras} cameras: {tracked} of 180 poses"
            );
            assert!(
                loose_frames >= 55,
                "{cameras} cameras: loose LED in {loose_frames} of 60"
            );
        }
    }

    #[test]
    fn a_loose_led_reappearing_beyond_the_gate_gets_a_new_id() {
        let rig = rig(2);
        let defs = tools();
        let mut tracker = MultiTracker::new(&rig, &defs, PoseConfig::default()).unwrap();
        let ids = |t: &MultiTracker, at: Vector3<f64>| {
            t.loose_leds()
                .iter()
                .find(|l| (Vector3::from(l.position_mm) - at).norm() < 1e-6)
                .map(|l| l.id)
        };
        // Moving 2 mm per frame: frames 0..10 tracked, 10..12 hidden, then back on its path
        // (same id), hidden again, then 25 mm off its predicted path (a new id).
        let path = |f: usize| Vector3::new(60.0 - 2.0 * f as f64, 120.0, 1010.0);
        let mut first = None;
        for frame in 0..24 {
            let mut s = scene(0);
            let hidden = (10..12).contains(&frame) || (18..20).contains(&frame);
            s.loose = if frame >= 20 {
                path(frame) + Vector3::new(0.0, 25.0, 0.0)
            } else {
                path(frame)
            };
            run(&mut tracker, &blobs(&rig, &defs, &s, |_, k| hidden && k == 3));
            if hidden {
                assert_eq!(ids(&tracker, s.loose), None);
                continue;
            }
            let id =
                ids(&tracker, s.loose).unwrap_or_else(|| panic!("frame {frame}: loose LED not reported"));
            let first = *first.get_or_insert(id);
            if frame < 20 {
                assert_eq!(
                    id, first,
                    "frame {frame}: the same LED keeps its id across a short gap"
                );
            } else {
                assert_ne!(id, first, "frame {frame}: 25 mm beyond the gate is a new LED");
            }
        }
    }

    #[test]
    fn an_untracked_tools_leds_are_its_candidates_not_loose_leds() {
        let rig = rig(2);
        let defs = tools();
        let mut tracker = MultiTracker::new(&rig, &defs, PoseConfig::default()).unwrap();
        // tri3 (tool 1) loses LED 0 in camera 1 for frames 10..30 (longer than the coast):
        // it is not tracked, its LEDs 1 and 2 are still seen by both cameras.
        let gap = 10..30;
        let mut loose_ids = Vec::new();
        for frame in 0..35 {
            let s = scene(frame);
            let hidden = gap.contains(&frame);
            let b = blobs_of_leds(&rig, &defs, &s, |c, k, i| hidden && c == 1 && k == 1 && i == 0);
            run(&mut tracker, &b);
            let tri3 = tracker.pose(1).unwrap().status;
            if frame < 30 {
                assert_eq!(
                    tri3 == PoseStatus::Tracked,
                    !hidden,
                    "frame {frame}: tri3 {tri3:?}"
                );
            }
            let (q, t) = s.poses[1];
            let tri3_leds: Vec<Vector3<f64>> = defs[1]
                .leds_mm
                .iter()
                .map(|l| q * Vector3::from(*l) + t)
                .collect();
            let mut loose_seen = false;
            for l in tracker.loose_leds() {
                let at = Vector3::from(l.position_mm);
                assert!(
                    tri3_leds.iter().all(|p| (p - at).norm() > 5.0),
                    "frame {frame}: tri3's LED reported as loose LED {}",
                    l.id
                );
                loose_seen |= (at - s.loose).norm() < 1e-6;
                if !loose_ids.contains(&l.id) {
                    loose_ids.push(l.id);
                }
            }
            assert!(loose_seen, "frame {frame}: the loose LED is reported");
            if hidden {
                // tri3's LEDs 1 and 2 are its candidates: their blobs go to it in both cameras.
                for (c, cam) in rig.cameras.iter().enumerate() {
                    for p in &tri3_leds[1..] {
                        let px = cam.model.project(&cam.cam_from_cam0.apply(p)).unwrap();
                        let i = b[c]
                            .iter()
                            .position(|bl| (bl.x_px - px.x).hypot(bl.y_px - px.y) < 1e-6)
                            .unwrap();
                        assert_eq!(tracker.blob_owner(c, i), 1, "frame {frame} camera {c}");
                    }
                }
            }
        }
        assert_eq!(loose_ids.len(), 1, "loose ids issued: {loose_ids:?}");
    }

    #[test]
    fn blobs_are_attributed_to_their_tools() {
        let rig = rig(3);
        let defs = tools();
        let mut tracker = MultiTracker::new(&rig, &defs, PoseConfig::default()).unwrap();
        let s = scene(0);
        let b = blobs(&rig, &defs, &s, |_, _| false);
        run(&mut tracker, &b);
        for (c, list) in b.iter().enumerate() {
            for (i, blob) in list.iter().enumerate() {
                // Which tool drew this blob: nearest projected LED.
                let mut best = (f64::INFINITY, NO_TOOL);
                for (k, (d, (q, t))) in defs.iter().zip(&s.poses).enumerate() {
                    for l in &d.leds_mm {
                        let cam = &rig.cameras[c];
                        let px = cam
                            .model
                            .project(&cam.cam_from_cam0.apply(&(q * Vector3::from(*l) + t)))
                            .unwrap();
                        let e = (px.x - blob.x_px).hypot(px.y - blob.y_px);
                        if e < best.0 {
                            best = (e, k as u8);
                        }
                    }
                }
                let want = if best.0 < 1e-6 { best.1 } else { LOOSE_LED };
                assert_eq!(tracker.blob_owner(c, i), want, "camera {c} blob {i}");
            }
        }
    }

    #[test]
    fn a_camera_losing_a_tool_keeps_it_tracked_by_the_others() {
        let rig = rig(3);
        let defs = tools();
        let mut tracker = MultiTracker::new(&rig, &defs, PoseConfig::default()).unwrap();
        for frame in 0..10 {
            let s = scene(frame);
            // Camera 2 loses tri3 entirely; camera 0 loses wing4 for frames 3..6.
            let hide =
                |c: usize, k: usize| (c == 2 && k == 1) || (c == 0 && k == 2 && (3..6).contains(&frame));
            run(&mut tracker, &blobs(&rig, &defs, &s, hide));
            assert_eq!(check_poses(&tracker, &s, frame), 3, "frame {frame}");
        }
    }

    #[test]
    fn predictor_bridges_a_gap_longer_than_the_step_limit() {
        let rig = rig(2);
        let defs = &tools()[..1];
        // 4 mm per frame, a 10 mm step limit, a 6-frame gap: the tool reappears 28 mm from
        // where it was last seen, but within a millimetre of where it was heading.
        let cfg = PoseConfig {
            max_step_mm: 10.0,
            ..PoseConfig::default()
        };
        let at = |f: usize| Scene {
            poses: vec![(
                UnitQuaternion::from_euler_angles(0.3, -0.2, 0.1 + 0.004 * f as f64),
                Vector3::new(-100.0 + 4.0 * f as f64, 0.0, 1000.0),
            )],
            loose: Vector3::new(0.0, 300.0, 1000.0),
        };
        let mut tracker = MultiTracker::new(&rig, defs, cfg).unwrap();
        for frame in 0..20 {
            let s = at(frame);
            let gap = (8..14).contains(&frame);
            run(&mut tracker, &blobs(&rig, defs, &s, |_, k| gap && k == 0));
            let status = tracker.pose(0).unwrap().status;
            if gap {
                assert_ne!(status, PoseStatus::Tracked);
                assert_eq!(tracker.frames_since_tracked(0), (frame - 7) as u32);
            } else {
                assert_eq!(status, PoseStatus::Tracked, "frame {frame}");
                check_poses(&tracker, &s, frame);
            }
        }
        // The same gap without motion knowledge (a fresh reference 28 mm away) is a jump.
        let mut cold = MultiTracker::new(&rig, defs, cfg).unwrap();
        run(&mut cold, &blobs(&rig, defs, &at(7), |_, _| false));
        run(&mut cold, &blobs(&rig, defs, &at(14), |_, _| false));
        assert_eq!(cold.pose(0).unwrap().status, PoseStatus::StepTooLarge);
    }

    #[test]
    fn confusable_tools_are_refused_naming_both() {
        let rig = rig(2);
        let mut defs = tools();
        // Three of probe4's LEDs, moved: the tri3-like tool could be found inside probe4.
        defs.push(tool(
            "part-of-probe",
            &[[10.0, 10.0, 10.0], [109.0, 10.0, 10.0], [72.0, 21.0, 42.0]],
        ));
        let e = MultiTracker::new(&rig, &defs, PoseConfig::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("\"part-of-probe\"") && e.contains("\"probe4\""), "{e}");
        assert!(e.contains("cross-tool margin"), "{e}");
        let nine: Vec<ToolDefinition> = (0..9)
            .map(|i| {
                tool(
                    &alloc::format!("t{i}"),
                    &[[0.0; 3], [100.0, 0.0, 0.0], [0.0, 60.0 + i as f64, 0.0]],
                )
            })
            .collect();
        let e = MultiTracker::new(&rig, &nine, PoseConfig::default()).unwrap_err();
        assert!(e.to_string().contains("at most 8"), "{e}");
        // The built-in pair and wing4 pass.
        MultiTracker::new(&rig, &tools(), PoseConfig::default()).unwrap();
    }
}
