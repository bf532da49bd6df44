//! A wand wave: a rod carrying collinear IR LEDs moved and turned through the work volume,
//! rendered for any rig, with lens distortion, sensor noise, LEDs hidden from single cameras
//! (occlusion) and spurious bright spots (reflections), plus the ground truth.
//!
//! Used to test `host-tools wand-calibrate`. The rendering is the scenario's model reduced to
//! what a wand needs: each visible LED is a Gaussian spot (lens PSF plus the imaged disk),
//! integrated exactly over every pixel with `erf`, brightness falling with the square of the
//! distance; background and noise are drawn per pixel from a quantile table. Reflections come in
//! two kinds: a ghost of the wand on the wand's own image line beyond one end (which makes the
//! LEDs' identification ambiguous and must be rejected) and a stray spot elsewhere in the image
//! (which a robust identification simply ignores).
//!
//! Files written by [`write_wave`]: `DIR/cam<i>/<frame:06>.pgm` (8-bit), `DIR/wand_truth.csv`
//! (one row per frame and camera), `DIR/timestamps.csv` (`frame,camera,timestamp_ns,dropped`:
//! the timestamp each camera gives) and `DIR/truth_rig.irp` (the true rig as a parameter blob).
//!
//! Camera timing ([`WandConfig::timing`], docs/simulator.md "Camera timing"): each camera sees
//! the wand at its own exposure instant (phase, drift) and, with a rolling shutter, each LED at
//! the instant its row was exposed; the frame rate `fps` turns those instants into wave time.
//! Exposure blur is not rendered for the wand.

use std::io::Write;
use std::path::{Path, PathBuf};

use irtrack_core::camera::RigidTransform;
use irtrack_core::params::RigParams;
use nalgebra::{Matrix3, Vector2, Vector3};

use crate::SimError;
use crate::noise::{PixelRng, hash_words, normal_table, unit_from_hash};
use crate::timing::{ROLLING_ITERATIONS, SimCameraTiming};
use irtrack_core::pgm;

/// A spot is rendered out to this many standard deviations.
const SPOT_EXTENT_SIGMA: f64 = 4.5;

/// Everything a wand wave is made of.
#[derive(Debug, Clone, PartialEq)]
pub struct WandConfig {
    /// The true rig (camera 0 is the reference frame).
    pub rig: RigParams,
    /// LED positions along the wand from its end 0, mm, increasing (e.g. 0, 120, 300).
    pub leds_mm: Vec<f64>,
    /// Number of frames of the wave.
    pub frames: usize,
    /// Centre of the wand's middle over the wave (camera 0 frame, mm).
    pub centre_mm: Vector3<f64>,
    /// The wand's middle sweeps ± this far along camera 0's axes (mm).
    pub sweep_mm: Vector3<f64>,
    /// Largest angle of the wand from the plane perpendicular to `up` (degrees); the wand turns
    /// fully about `up`.
    pub max_elevation_deg: f64,
    /// Full turns of the wand about `up` over the wave (0: it keeps its heading).
    pub turns: f64,
    /// "Up" direction in camera 0's frame (the wand turns about it).
    pub up: Vector3<f64>,
    /// A wand that is not straight: each LED sits `bend_mm · 4u(1 − u)` off the line through
    /// the end LEDs (u: its fraction of the way from end 0), sideways to the wand (along
    /// `dir × up`, so the bend turns with the wand). 0: straight (the default).
    pub bend_mm: f64,
    /// Radius of an LED's emitting disk (mm).
    pub led_radius_mm: f64,
    /// Lens point-spread function, standard deviation (px).
    pub psf_sigma_px: f64,
    /// Peak grey level of an LED spot at 1 m (before saturation at 255).
    pub peak_dn_at_1m: f64,
    /// Background grey level.
    pub background_dn: f64,
    /// Read noise, grey levels RMS; shot noise adds `sqrt(signal · shot_gain_dn)`.
    pub noise_dn: f64,
    /// Grey levels per photo-electron for the shot noise.
    pub shot_gain_dn: f64,
    /// Probability that one LED is hidden from one camera in one frame.
    pub occlusion_rate: f64,
    /// Probability of a ghost on the wand's image line beyond an end in one camera's frame.
    pub ghost_rate: f64,
    /// Probability of a stray bright spot somewhere in one camera's frame.
    pub stray_rate: f64,
    /// Seed of every random draw.
    pub seed: u64,
    /// Frame rate (converts camera timing into wave time; the wave itself is in frames).
    pub fps: f64,
    /// Per-camera timing; empty: synchronous global-shutter cameras.
    pub timing: Vec<SimCameraTiming>,
}

impl WandConfig {
    /// A wave around `centre_mm` for `rig` with a 0/120/300 mm wand, moderate noise,
    /// 3 % occlusion per LED, 2 % ghosts and 5 % stray spots per camera and frame.
    pub fn new(rig: RigParams, centre_mm: Vector3<f64>, frames: usize) -> Self {
        WandConfig {
            rig,
            leds_mm: vec![0.0, 120.0, 300.0],
            frames,
            centre_mm,
            sweep_mm: Vector3::new(220.0, 130.0, 220.0),
            max_elevation_deg: 50.0,
            turns: 4.0,
            up: Vector3::new(0.0, -1.0, 0.0),
            bend_mm: 0.0,
            led_radius_mm: 1.5,
            psf_sigma_px: 0.9,
            peak_dn_at_1m: 230.0,
            background_dn: 10.0,
            noise_dn: 1.5,
            shot_gain_dn: 0.05,
            occlusion_rate: 0.03,
            ghost_rate: 0.02,
            stray_rate: 0.05,
            seed: 1,
            fps: 120.0,
            timing: Vec::new(),
        }
    }

    fn validate(&self) -> Result<(), SimError> {
        let bad = |field, reason: String| Err(SimError::Config { field, reason });
        if self.rig.cameras.len() < 2 {
            return bad(
                "rig",
                format!("need at least 2 cameras, got {}", self.rig.cameras.len()),
            );
        }
        if self.leds_mm.len() < 3
            || self
                .leds_mm
                .windows(2)
                .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
        {
            return bad(
                "leds_mm",
                format!("{:?}: need 3 or more increasing distances", self.leds_mm),
            );
        }
        if self.frames == 0 {
            return bad("frames", "must be > 0".into());
        }
        for (field, p) in [
            ("occlusion_rate", self.occlusion_rate),
            ("ghost_rate", self.ghost_rate),
            ("stray_rate", self.stray_rate),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(field, format!("{p} must be in [0, 1]"));
            }
        }
        if !(self.fps > 0.0 && self.fps.is_finite()) {
            return bad("fps", format!("{} must be > 0", self.fps));
        }
        if !self.timing.is_empty() && self.timing.len() != self.rig.cameras.len() {
            return bad(
                "timing",
                format!(
                    "{} entries for {} cameras (none, or one per camera)",
                    self.timing.len(),
                    self.rig.cameras.len()
                ),
            );
        }
        for (c, t) in self.timing.iter().enumerate() {
            t.validate(c)?;
        }
        if !self.bend_mm.is_finite() {
            return bad("bend_mm", format!("{} must be finite", self.bend_mm));
        }
        if !(self.psf_sigma_px > 0.05 && self.up.norm() > 0.0) {
            return bad("psf_sigma_px/up", "PSF must be > 0.05 px and up non-zero".into());
        }
        Ok(())
    }
}

/// The wand at one frame: end 0 and the unit direction toward the other LEDs (camera 0 frame).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WandPose {
    /// Position of end 0 (mm).
    pub end0_mm: Vector3<f64>,
    /// Unit vector from end 0 toward the other LEDs.
    pub dir: Vector3<f64>,
}

impl WandPose {
    /// Position of the LED at `s_mm` along the wand.
    pub fn led(&self, s_mm: f64) -> Vector3<f64> {
        self.end0_mm + self.dir * s_mm
    }
}

/// What one camera saw of one frame, as rendered.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraFrameTruth {
    /// True pixel of each LED (`None`: hidden, behind the camera or outside the image).
    pub leds_px: Vec<Option<Vector2<f64>>>,
    /// Bit k: LED k was hidden on purpose (occlusion).
    pub hidden_mask: u32,
    /// Where a ghost on the wand's image line was drawn, if one was.
    pub ghost_px: Option<Vector2<f64>>,
    /// Where a stray spot elsewhere was drawn, if one was.
    pub stray_px: Option<Vector2<f64>>,
}

impl CameraFrameTruth {
    /// Distance (px) from the nearest spurious spot to the nearest visible LED: a spot this close
    /// merges with the LED's blob and no identification can tell.
    pub fn spurious_clearance_px(&self) -> f64 {
        let mut best = f64::INFINITY;
        for s in self.ghost_px.iter().chain(self.stray_px.iter()) {
            for l in self.leds_px.iter().flatten() {
                best = best.min((s - l).norm());
            }
        }
        best
    }
}

/// Pose of a camera at `centre_cam0_mm` looking at `target_cam0_mm` with image "up" toward
/// `up_cam0` (all in camera 0's frame), as `x_cam = R x_cam0 + t`.
pub fn look_at(
    centre_cam0_mm: Vector3<f64>,
    target_cam0_mm: Vector3<f64>,
    up_cam0: Vector3<f64>,
) -> Result<RigidTransform, SimError> {
    let z = (target_cam0_mm - centre_cam0_mm)
        .try_normalize(1e-9)
        .ok_or_else(|| SimError::Config {
            field: "look_at",
            reason: "camera centre equals its target".into(),
        })?;
    // Image y points down, so the image's "down" is -up projected off the viewing axis.
    let y = (-up_cam0 + z * up_cam0.dot(&z))
        .try_normalize(1e-9)
        .ok_or_else(|| SimError::Config {
            field: "look_at",
            reason: "up is parallel to the viewing direction".into(),
        })?;
    let x = y.cross(&z);
    let cam0_from_cam = Matrix3::from_columns(&[x, y, z]);
    let r = cam0_from_cam.transpose();
    Ok(RigidTransform::from_parts(&r, &(-(r * centre_cam0_mm))))
}

/// Renders wand waves frame by frame.
#[derive(Debug)]
pub struct WandWave {
    cfg: WandConfig,
    normal: Vec<f32>,
    bg_codes: Vec<u8>,
    mean: Vec<f32>,
    gx: Vec<f64>,
    gy: Vec<f64>,
}

fn u01(seed: u64, words: &[u64]) -> f64 {
    let mut w = vec![seed];
    w.extend_from_slice(words);
    unit_from_hash(hash_words(&w))
}

impl WandWave {
    /// Validates the configuration and precomputes the noise tables.
    pub fn new(cfg: WandConfig) -> Result<Self, SimError> {
        cfg.validate()?;
        let normal = normal_table();
        let bg_codes = normal
            .iter()
            .map(|z| {
                (cfg.background_dn + cfg.noise_dn * *z as f64)
                    .round()
                    .clamp(0.0, 255.0) as u8
            })
            .collect();
        Ok(WandWave {
            cfg,
            normal,
            bg_codes,
            mean: Vec::new(),
            gx: Vec::new(),
            gy: Vec::new(),
        })
    }

    /// The wave's configuration.
    pub fn config(&self) -> &WandConfig {
        &self.cfg
    }

    /// The wand's true pose at `frame`: its middle follows a Lissajous curve through the sweep
    /// box, its direction turns fully about `up` and tilts up to `max_elevation_deg`.
    pub fn pose(&self, frame: usize) -> WandPose {
        self.pose_at(frame as f64)
    }

    /// The wand's true pose at a fractional frame (wave time; frame `k` is at `k / fps` s).
    pub fn pose_at(&self, frame: f64) -> WandPose {
        let c = &self.cfg;
        let t = frame / c.frames as f64;
        let tau = std::f64::consts::TAU;
        let off = Vector3::new(
            c.sweep_mm.x * (tau * 3.0 * t + 0.3).sin(),
            c.sweep_mm.y * (tau * 5.0 * t + 1.1).sin(),
            c.sweep_mm.z * (tau * 2.0 * t + 2.0).sin(),
        );
        let up = c.up.normalize();
        // Any two axes perpendicular to up.
        let a = if up.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let e1 = (a - up * a.dot(&up)).normalize();
        let e2 = up.cross(&e1);
        let az = tau * c.turns * t + 0.4;
        let el = c.max_elevation_deg.to_radians() * (tau * 7.0 * t + 0.7).sin();
        let dir = (e1 * az.cos() + e2 * az.sin()) * el.cos() + up * el.sin();
        let half = c.leds_mm[c.leds_mm.len() - 1] / 2.0;
        let middle = c.centre_mm + off;
        WandPose {
            end0_mm: middle - dir * (half + c.leds_mm[0]),
            dir,
        }
    }

    /// Where LED `s_mm` is at wave frame `at` (camera 0 frame): on the wand's line, plus the
    /// sideways bow of a wand that is not straight ([`WandConfig::bend_mm`]).
    pub fn led_at(&self, at: f64, s_mm: f64) -> Vector3<f64> {
        let c = &self.cfg;
        let pose = self.pose_at(at);
        let p = pose.led(s_mm);
        if c.bend_mm == 0.0 {
            return p;
        }
        let (first, last) = (c.leds_mm[0], c.leds_mm[c.leds_mm.len() - 1]);
        let u = (s_mm - first) / (last - first);
        let side = pose.dir.cross(&c.up);
        // A wand along `up` has no sideways direction from it; any perpendicular will do.
        let side = if side.norm() > 1e-9 {
            side.normalize()
        } else {
            pose.dir.cross(&Vector3::x()).normalize()
        };
        p + side * (c.bend_mm * 4.0 * u * (1.0 - u))
    }

    /// Camera `camera`'s exposure of `frame` (middle of row 0) in wave frames, and the
    /// timestamp it reports (ns, signed; see [`crate::timing`]).
    pub fn frame_time(&self, frame: usize, camera: usize) -> (f64, i64) {
        let c = &self.cfg;
        match c.timing.get(camera) {
            Some(t) if !t.is_synchronous() => {
                let ft = crate::timing::frame_time(t, c.fps, c.seed, frame as u64, camera);
                (ft.exposure_s * c.fps, ft.reported_ns)
            }
            _ => (frame as f64, (frame as f64 * 1e9 / c.fps).round() as i64),
        }
    }

    /// Where LED `s_mm` is seen by `camera` exposing at wave frame `at`: its position (camera
    /// 0 frame), at the instant its row was exposed with a rolling shutter.
    fn led_seen(&self, camera: usize, at: f64, s_mm: f64) -> Vector3<f64> {
        let c = &self.cfg;
        let mut p = self.led_at(at, s_mm);
        let line_frames = c
            .timing
            .get(camera)
            .map_or(0.0, |t| t.line_time_ns * 1e-9 * c.fps);
        if line_frames > 0.0 {
            let cam = &c.rig.cameras[camera];
            for _ in 0..ROLLING_ITERATIONS {
                let Ok(px) = cam.model.project(&cam.cam_from_cam0.apply(&p)) else {
                    break;
                };
                p = self.led_at(at + px.y.max(0.0) * line_frames, s_mm);
            }
        }
        p
    }

    /// What camera `camera` sees at `frame` (without rendering).
    pub fn camera_truth(&self, frame: usize, camera: usize) -> Result<CameraFrameTruth, SimError> {
        let c = &self.cfg;
        let cam = c.rig.cameras.get(camera).ok_or(SimError::NoSuchCamera {
            camera,
            count: c.rig.cameras.len(),
        })?;
        let (at, _) = self.frame_time(frame, camera);
        let pose = self.pose_at(at);
        let (f, k) = (frame as u64, camera as u64);
        let mut hidden_mask = 0u32;
        let mut leds_px = Vec::with_capacity(c.leds_mm.len());
        for (li, s) in c.leds_mm.iter().enumerate() {
            if u01(c.seed, &[f, k, li as u64, 1]) < c.occlusion_rate {
                hidden_mask |= 1 << li;
                leds_px.push(None);
                continue;
            }
            let p = cam.cam_from_cam0.apply(&self.led_seen(camera, at, *s));
            leds_px.push(
                cam.model
                    .project(&p)
                    .ok()
                    .filter(|px| in_view(&cam.model, &p, px)),
            );
        }
        let mut ghost_px = None;
        if u01(c.seed, &[f, k, 2]) < c.ghost_rate {
            // A reflection of the wand in a shiny surface along its own line: beyond one end by
            // 20–60 % of the wand's image length.
            let pa = cam
                .model
                .project(&cam.cam_from_cam0.apply(&pose.led(c.leds_mm[0])));
            let pb = cam
                .model
                .project(&cam.cam_from_cam0.apply(&pose.led(c.leds_mm[c.leds_mm.len() - 1])));
            if let (Ok(pa), Ok(pb)) = (pa, pb) {
                let beyond = 0.2 + 0.4 * u01(c.seed, &[f, k, 4]);
                let (from, to) = if u01(c.seed, &[f, k, 5]) < 0.5 {
                    (pa, pb)
                } else {
                    (pb, pa)
                };
                ghost_px = Some(to + (to - from) * beyond);
            }
        }
        let (w, h) = (
            cam.model.image_size.width_px as f64,
            cam.model.image_size.height_px as f64,
        );
        let stray_px = (u01(c.seed, &[f, k, 3]) < c.stray_rate).then(|| {
            Vector2::new(
                u01(c.seed, &[f, k, 6]) * (w - 20.0) + 10.0,
                u01(c.seed, &[f, k, 7]) * (h - 20.0) + 10.0,
            )
        });
        Ok(CameraFrameTruth {
            leds_px,
            hidden_mask,
            ghost_px,
            stray_px,
        })
    }

    /// Renders one camera's frame into `out` (row-major, width × height); returns its truth.
    pub fn render(
        &mut self,
        frame: usize,
        camera: usize,
        out: &mut [u8],
    ) -> Result<CameraFrameTruth, SimError> {
        let truth = self.camera_truth(frame, camera)?;
        let c = &self.cfg;
        let cam = &c.rig.cameras[camera];
        let (w, h) = (
            cam.model.image_size.width_px as usize,
            cam.model.image_size.height_px as usize,
        );
        if out.len() != w * h {
            return Err(SimError::BufferSize {
                needed: w * h,
                have: out.len(),
            });
        }
        let mut rng = PixelRng::new(c.seed, frame as u64, camera as u64);
        for px in out.iter_mut() {
            *px = self.bg_codes[rng.next_u16() as usize];
        }
        let (at, _) = self.frame_time(frame, camera);
        let focal = cam.model.intrinsics.fx_px;
        let mut spots: Vec<(Vector2<f64>, f64, f64)> = Vec::with_capacity(c.leds_mm.len() + 2);
        let mut sigma_ref = c.psf_sigma_px;
        let mut peak_ref = c.peak_dn_at_1m;
        for (li, s) in c.leds_mm.iter().enumerate() {
            let Some(px) = truth.leds_px[li] else { continue };
            let p = cam.cam_from_cam0.apply(&self.led_seen(camera, at, *s));
            let disk_px = focal * c.led_radius_mm / p.z;
            let sigma = (c.psf_sigma_px.powi(2) + 0.25 * disk_px * disk_px).sqrt();
            let peak = c.peak_dn_at_1m * (1000.0 / p.norm()).powi(2);
            spots.push((px, sigma, peak));
            sigma_ref = sigma;
            peak_ref = peak;
        }
        if let Some(g) = truth.ghost_px {
            spots.push((g, sigma_ref, peak_ref));
        }
        if let Some(g) = truth.stray_px {
            spots.push((g, 1.6, 200.0));
        }
        for (px, sigma, peak) in spots {
            self.add_spot(out, w, h, px, sigma, peak, &mut rng);
        }
        Ok(truth)
    }

    /// Adds a Gaussian spot (peak grey level `peak`) with shot and read noise inside its window.
    #[allow(clippy::too_many_arguments)]
    fn add_spot(
        &mut self,
        out: &mut [u8],
        w: usize,
        h: usize,
        c: Vector2<f64>,
        sigma: f64,
        peak: f64,
        rng: &mut PixelRng,
    ) {
        let r = SPOT_EXTENT_SIGMA * sigma + 1.0;
        let x0 = (c.x - r).floor().max(0.0) as usize;
        let y0 = (c.y - r).floor().max(0.0) as usize;
        let x1 = ((c.x + r).ceil() + 1.0).min(w as f64).max(0.0) as usize;
        let y1 = ((c.y + r).ceil() + 1.0).min(h as f64).max(0.0) as usize;
        if x1 <= x0 || y1 <= y0 {
            return;
        }
        let flux = peak * 2.0 * std::f64::consts::PI * sigma * sigma;
        self.gx.resize(x1 - x0, 0.0);
        self.gy.resize(y1 - y0, 0.0);
        pixel_integrals(&mut self.gx, x0, c.x, sigma);
        pixel_integrals(&mut self.gy, y0, c.y, sigma);
        self.mean.clear();
        self.mean.resize((x1 - x0) * (y1 - y0), 0.0);
        let cfg = &self.cfg;
        for y in y0..y1 {
            for x in x0..x1 {
                let m = flux * self.gy[y - y0] * self.gx[x - x0];
                let z = self.normal[rng.next_u16() as usize] as f64;
                let sd = (m * cfg.shot_gain_dn).sqrt();
                let v = out[y * w + x] as f64 + m + sd * z;
                out[y * w + x] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }

    /// Renders every frame of every camera into `dir` and writes the truth files; returns the
    /// per-frame, per-camera truth.
    pub fn write_wave(&mut self, dir: &Path) -> Result<Vec<Vec<CameraFrameTruth>>, SimError> {
        let n_cam = self.cfg.rig.cameras.len();
        let mut dirs: Vec<PathBuf> = Vec::with_capacity(n_cam);
        for ci in 0..n_cam {
            let d = dir.join(format!("cam{ci}"));
            std::fs::create_dir_all(&d)?;
            dirs.push(d);
        }
        let mut csv = String::from(
            "frame,camera,end0_x_mm,end0_y_mm,end0_z_mm,dir_x,dir_y,dir_z,visible_leds,hidden_mask,ghost,stray\n",
        );
        let mut all = Vec::with_capacity(self.cfg.frames);
        let mut buf = Vec::new();
        let mut stamps = String::from("frame,camera,timestamp_ns,dropped\n");
        for frame in 0..self.cfg.frames {
            let mut per_cam = Vec::with_capacity(n_cam);
            for (ci, d) in dirs.iter().enumerate() {
                // The pose this camera saw (at its own exposure; the same for all when synchronous).
                let (at, reported_ns) = self.frame_time(frame, ci);
                let pose = self.pose_at(at);
                // Stamped before the start: written as dropped, as `simulate` does.
                stamps.push_str(&format!(
                    "{frame},{ci},{},{}\n",
                    reported_ns.max(0),
                    u8::from(reported_ns < 0)
                ));
                let size = self.cfg.rig.cameras[ci].model.image_size;
                buf.resize(size.width_px as usize * size.height_px as usize, 0u8);
                let t = self.render(frame, ci, &mut buf)?;
                let file = pgm::encode_u8(size.width_px, size.height_px, &buf)?;
                std::fs::write(d.join(format!("{frame:06}.pgm")), file)?;
                csv.push_str(&format!(
                    "{frame},{ci},{:.6},{:.6},{:.6},{:.9},{:.9},{:.9},{},{},{},{}\n",
                    pose.end0_mm.x,
                    pose.end0_mm.y,
                    pose.end0_mm.z,
                    pose.dir.x,
                    pose.dir.y,
                    pose.dir.z,
                    t.leds_px.iter().filter(|p| p.is_some()).count(),
                    t.hidden_mask,
                    u8::from(t.ghost_px.is_some()),
                    u8::from(t.stray_px.is_some())
                ));
                per_cam.push(t);
            }
            all.push(per_cam);
        }
        std::fs::File::create(dir.join("wand_truth.csv"))?.write_all(csv.as_bytes())?;
        std::fs::write(dir.join("timestamps.csv"), stamps)?;
        let blob = self.cfg.rig.to_blob()?;
        std::fs::write(dir.join("truth_rig.irp"), blob)?;
        Ok(all)
    }
}

/// Inside the image, in front of the camera and well inside the field of view (where the
/// distortion polynomial is still monotonic).
fn in_view(model: &irtrack_core::camera::CameraModel, p: &Vector3<f64>, px: &Vector2<f64>) -> bool {
    p.z > 0.0 && (p.x / p.z).hypot(p.y / p.z) < 1.2 && px.x >= 3.0 && px.y >= 3.0 && {
        let s = model.image_size;
        px.x <= s.width_px as f64 - 4.0 && px.y <= s.height_px as f64 - 4.0
    }
}

/// Fraction of a unit 1-D Gaussian (centre `c`, sd `s`) in each pixel `i0..i0+out.len()`.
fn pixel_integrals(out: &mut [f64], i0: usize, c: f64, s: f64) {
    let k = 1.0 / (s * std::f64::consts::SQRT_2);
    let mut prev = libm::erf((i0 as f64 - 0.5 - c) * k);
    for (j, o) in out.iter_mut().enumerate() {
        let next = libm::erf(((i0 + j) as f64 + 0.5 - c) * k);
        *o = 0.5 * (next - prev);
        prev = next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{CameraSpec, RigPreset, build_rig};

    fn wave() -> WandWave {
        let rig = build_rig(
            &RigPreset::Convergent {
                distance_mm: 1200.0,
                angle_deg: 90.0,
            },
            &CameraSpec::default(),
        )
        .unwrap();
        WandWave::new(WandConfig::new(rig, Vector3::new(0.0, 0.0, 1200.0), 200)).unwrap()
    }

    #[test]
    fn leds_are_rendered_where_projected_and_the_wand_keeps_its_length() {
        let mut w = wave();
        let mut img = vec![0u8; 640 * 480];
        let mut seen = 0;
        for frame in (0..200).step_by(17) {
            let p = w.pose(frame);
            assert!((p.dir.norm() - 1.0).abs() < 1e-12);
            assert!(((p.led(300.0) - p.led(0.0)).norm() - 300.0).abs() < 1e-9);
            for cam in 0..2 {
                let t = w.render(frame, cam, &mut img).unwrap();
                for px in t.leds_px.iter().flatten() {
                    let at = px.y.round() as usize * 640 + px.x.round() as usize;
                    assert!(img[at] > 60, "frame {frame} cam {cam}: {} at {px:?}", img[at]);
                    seen += 1;
                }
            }
        }
        assert!(seen > 50, "{seen}");
    }

    #[test]
    fn occlusions_ghosts_and_strays_occur_near_their_rates() {
        let w = wave();
        let (mut hidden, mut ghosts, mut strays) = (0, 0, 0);
        for frame in 0..200 {
            for cam in 0..2 {
                let t = w.camera_truth(frame, cam).unwrap();
                hidden += t.hidden_mask.count_ones();
                ghosts += usize::from(t.ghost_px.is_some());
                strays += usize::from(t.stray_px.is_some());
            }
        }
        // 1200 LED-views at 3 %, 400 camera frames at 2 % and 5 %.
        assert!((15..60).contains(&hidden), "{hidden}");
        assert!((2..20).contains(&ghosts), "{ghosts}");
        assert!((8..40).contains(&strays), "{strays}");
    }

    #[test]
    fn look_at_points_the_optical_axis_at_the_target() {
        let pose = look_at(
            Vector3::new(300.0, -500.0, 200.0),
            Vector3::new(0.0, 0.0, 1200.0),
            Vector3::new(0.0, -1.0, 0.0),
        )
        .unwrap();
        assert!(pose.is_proper_rotation(1e-12));
        let t = pose.apply(&Vector3::new(0.0, 0.0, 1200.0));
        assert!(t.x.abs() < 1e-9 && t.y.abs() < 1e-9 && t.z > 0.0);
        // A point above the target appears above the image centre (negative image y).
        let above = pose.apply(&Vector3::new(0.0, -100.0, 1200.0));
        assert!(above.y < 0.0);
        assert!(look_at(Vector3::zeros(), Vector3::zeros(), Vector3::y()).is_err());
    }

    #[test]
    fn timed_cameras_see_the_wand_at_their_own_instants_and_rows() {
        let sync = wave();
        let mut cfg = sync.config().clone();
        cfg.timing = vec![
            SimCameraTiming::default(),
            SimCameraTiming {
                phase_ns: 2_500_000.0,
                line_time_ns: 15_000.0,
                ts_offset_ns: 100_000.0,
                ..SimCameraTiming::default()
            },
        ];
        let timed = WandWave::new(cfg).unwrap();
        let cam = &timed.config().rig.cameras[1];
        let project = |p: Vector3<f64>| cam.model.project(&cam.cam_from_cam0.apply(&p)).unwrap();
        let mut moved = 0.0f64;
        for frame in (10..190).step_by(9) {
            // Camera 0 is synchronous: the same view as before.
            assert_eq!(
                timed.camera_truth(frame, 0).unwrap(),
                sync.camera_truth(frame, 0).unwrap()
            );
            let (at, reported) = timed.frame_time(frame, 1);
            assert!((at - (frame as f64 + 2.5e-3 * 120.0)).abs() < 1e-9);
            assert_eq!(
                reported,
                (frame as f64 * 1e9 / 120.0 + 2_600_000.0).round() as i64
            );
            let t = timed.camera_truth(frame, 1).unwrap();
            for (li, s) in timed.config().leds_mm.iter().enumerate() {
                let Some(px) = t.leds_px[li] else { continue };
                // Independently: the fixed point row → instant → row, iterated to convergence.
                let mut q = project(timed.pose_at(at).led(*s));
                for _ in 0..20 {
                    q = project(timed.pose_at(at + q.y * 15e-6 * 120.0).led(*s));
                }
                // Far below a centroid's noise (~0.02 px).
                assert!((px - q).norm() < 2e-3, "frame {frame} LED {li}: {px:?} vs {q:?}");
                moved = moved.max((px - project(sync.pose(frame).led(*s))).norm());
            }
        }
        assert!(moved > 1.0, "timing moved the LEDs by at most {moved} px");
    }

    #[test]
    fn a_bent_wand_bows_its_middle_leds_sideways() {
        let mut cfg = wave().config().clone();
        cfg.bend_mm = 4.0;
        let bent = WandWave::new(cfg).unwrap();
        let straight = wave();
        for frame in (0..200).step_by(13) {
            let at = frame as f64;
            let (a, b) = (bent.led_at(at, 0.0), bent.led_at(at, 300.0));
            // The ends stay where the straight wand has them.
            assert!((a - straight.led_at(at, 0.0)).norm() < 1e-9);
            assert!((b - straight.led_at(at, 300.0)).norm() < 1e-9);
            let m = bent.led_at(at, 120.0);
            let axis = (b - a).normalize();
            let off = (m - a) - axis * (m - a).dot(&axis);
            // 4 · 0.4 · 0.6 · 4 mm, perpendicular to the wand.
            assert!((off.norm() - 3.84).abs() < 1e-9, "frame {frame}: {}", off.norm());
            assert!(((m - a).dot(&axis) - 120.0).abs() < 1e-9);
        }
    }

    #[test]
    fn bad_config_is_an_error() {
        let mut cfg = wave().config().clone();
        cfg.leds_mm = vec![0.0, 300.0, 120.0];
        assert!(WandWave::new(cfg).is_err());
        let mut cfg = wave().config().clone();
        cfg.occlusion_rate = 2.0;
        assert!(WandWave::new(cfg).is_err());
    }
}
