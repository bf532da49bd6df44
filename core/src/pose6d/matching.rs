//! Step 1, correspondence: blobs of two or more cameras whose rays meet become candidate 3-D
//! points ([`PointMatcher`]); ghosts and reflections stay in the set for step 2 to weed out.

use alloc::format;
use alloc::vec::Vec;

use nalgebra::Vector3;

use super::config::{MAX_CAMERAS, NO_BLOB, PoseConfig};
use crate::blob::Blob;
use crate::camera::RigidTransform;
use crate::params::RigParams;
use crate::triangulate::{Ray, least_squares_rays, midpoint};
use crate::{Error, Result};

/// A candidate 3-D point: blobs of two or more cameras whose rays meet.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulatedPoint {
    /// Camera-0 frame (mm).
    pub point_mm: Vector3<f64>,
    /// Two views: the ray gap; more: RMS distance of the rays from the point (mm).
    pub gap_mm: f64,
    /// Blob index (into the slice given for that camera) per camera, [`NO_BLOB`] if unused.
    pub blobs: [u8; MAX_CAMERAS],
    /// Number of cameras contributing.
    pub cameras: u8,
}

impl TriangulatedPoint {
    /// Whether `self` and `other` use the same blob of some camera.
    pub(super) fn shares_blob(&self, other: &TriangulatedPoint) -> bool {
        self.blobs
            .iter()
            .zip(&other.blobs)
            .any(|(a, b)| *a != NO_BLOB && a == b)
    }

    /// Whether every blob of `self` is also used by `other`.
    fn is_subset_of(&self, other: &TriangulatedPoint) -> bool {
        self.blobs
            .iter()
            .zip(&other.blobs)
            .all(|(a, b)| *a == NO_BLOB || a == b)
    }
}

#[derive(Debug, Clone, Copy)]
struct BlobRay {
    blob: u8,
    ray: Ray,
    /// The blob's centroid (px).
    px: [f64; 2],
}

/// One camera of the rig with this frame's usable blob rays.
#[derive(Debug, Clone)]
pub(super) struct CameraSlot {
    pub(super) model: crate::camera::CameraModel,
    pub(super) cam_from_cam0: RigidTransform,
    rays: Vec<BlobRay>,
}

/// Multi-camera correspondence of many blobs by the epipolar constraint (ray gap).
#[derive(Debug, Clone)]
pub struct PointMatcher {
    config: PoseConfig,
    pub(super) cams: Vec<CameraSlot>,
    points: Vec<TriangulatedPoint>,
    scratch_rays: Vec<Ray>,
    dropped: u32,
}

impl PointMatcher {
    /// Allocates every buffer for `rig` (2..=[`MAX_CAMERAS`] cameras).
    pub fn new(rig: &RigParams, config: &PoseConfig) -> Result<Self> {
        config.validate()?;
        let n = rig.cameras.len();
        if !(2..=MAX_CAMERAS).contains(&n) {
            return Err(Error::InvalidParams {
                reason: format!("rig has {n} cameras; 6-DOF tracking needs 2..={MAX_CAMERAS}"),
            });
        }
        let cams = rig
            .cameras
            .iter()
            .map(|c| CameraSlot {
                model: c.model,
                cam_from_cam0: c.cam_from_cam0,
                rays: Vec::with_capacity(config.max_blobs_per_camera),
            })
            .collect();
        Ok(PointMatcher {
            config: *config,
            cams,
            points: Vec::with_capacity(config.max_candidates),
            scratch_rays: Vec::with_capacity(n),
            dropped: 0,
        })
    }

    /// Number of cameras.
    pub fn camera_count(&self) -> usize {
        self.cams.len()
    }

    /// Candidate points of the last [`PointMatcher::solve`].
    pub fn points(&self) -> &[TriangulatedPoint] {
        &self.points
    }

    /// Candidates dropped in the last frame because `max_candidates` was reached.
    pub fn dropped(&self) -> u32 {
        self.dropped
    }

    /// Finds candidate points from one blob list per camera (camera order). Blobs with
    /// non-finite centroids, low roundness or (optionally) touching the border are skipped.
    /// Errors when the number of blob lists differs from the rig's camera count.
    pub fn solve(&mut self, blobs: &[&[Blob]]) -> Result<&[TriangulatedPoint]> {
        if blobs.len() != self.cams.len() {
            return Err(Error::BadFrame {
                what: "6-DOF: number of blob lists differs from the rig's camera count",
            });
        }
        let cfg = self.config;
        for (cam, list) in self.cams.iter_mut().zip(blobs) {
            cam.rays.clear();
            for (i, b) in list
                .iter()
                .enumerate()
                .take(cfg.max_blobs_per_camera.min(NO_BLOB as usize))
            {
                let usable = b.x_px.is_finite()
                    && b.y_px.is_finite()
                    && b.roundness >= cfg.min_roundness
                    && !(cfg.reject_edge_blobs && b.touches_frame_edge);
                if usable {
                    let ray = Ray::from_pixel(&cam.model, &cam.cam_from_cam0, b.x_px, b.y_px);
                    if ray.dir.iter().all(|v| v.is_finite()) {
                        cam.rays.push(BlobRay {
                            blob: i as u8,
                            ray,
                            px: [b.x_px, b.y_px],
                        });
                    }
                }
            }
        }
        self.points.clear();
        self.dropped = 0;
        let n = self.cams.len();
        for ca in 0..n {
            for cb in ca + 1..n {
                for ra in &self.cams[ca].rays {
                    for rb in &self.cams[cb].rays {
                        let Ok(m) = midpoint(&ra.ray, &rb.ray) else {
                            continue;
                        };
                        let in_range = m
                            .range_mm
                            .iter()
                            .all(|r| (cfg.min_range_mm..=cfg.max_range_mm).contains(r));
                        if !(m.gap_mm <= cfg.max_gap_mm && in_range) {
                            continue;
                        }
                        let mut p = TriangulatedPoint {
                            point_mm: m.point_mm,
                            gap_mm: m.gap_mm,
                            blobs: [NO_BLOB; MAX_CAMERAS],
                            cameras: 2,
                        };
                        p.blobs[ca] = ra.blob;
                        p.blobs[cb] = rb.blob;
                        if n > 2 {
                            extend_with_other_cameras(&self.cams, &cfg, &mut p, &mut self.scratch_rays);
                        }
                        insert_candidate(&mut self.points, &mut self.dropped, p);
                    }
                }
            }
        }
        Ok(&self.points)
    }
}

impl PointMatcher {
    /// Centroid (px) of blob `blob` of camera `camera` in the last [`PointMatcher::solve`]
    /// (`None` if it was not usable).
    pub(super) fn blob_px(&self, camera: usize, blob: u8) -> Option<[f64; 2]> {
        self.cams
            .get(camera)?
            .rays
            .iter()
            .find(|r| r.blob == blob)
            .map(|r| r.px)
    }

    /// `p` without the cameras in `drop_mask` (bit per camera), re-solved from the rays of
    /// the cameras left (least squares; two views: the midpoint and its gap). `None` when
    /// fewer than two cameras remain or the rays do not give a point. Used when one camera's
    /// blob is another LED's too (claimed by another tool, or two spots merged into one).
    pub(super) fn without_cameras(
        &mut self,
        p: &TriangulatedPoint,
        drop_mask: u32,
    ) -> Option<TriangulatedPoint> {
        let mut q = *p;
        q.cameras = 0;
        self.scratch_rays.clear();
        for (c, cam) in self.cams.iter().enumerate() {
            if q.blobs[c] == NO_BLOB {
                continue;
            }
            if drop_mask & (1 << c) != 0 {
                q.blobs[c] = NO_BLOB;
                continue;
            }
            let br = cam.rays.iter().find(|r| r.blob == q.blobs[c])?;
            self.scratch_rays.push(br.ray);
            q.cameras += 1;
        }
        match self.scratch_rays.as_slice() {
            [a, b] => {
                let m = midpoint(a, b).ok()?;
                q.point_mm = m.point_mm;
                q.gap_mm = m.gap_mm;
            }
            rays if rays.len() > 2 => {
                let (pt, rms) = least_squares_rays(rays).ok()?;
                q.point_mm = pt;
                q.gap_mm = rms;
            }
            _ => return None,
        }
        Some(q)
    }
}

/// Adds the closest consistent ray of every camera not yet in `p` and re-solves the point.
fn extend_with_other_cameras(
    cams: &[CameraSlot],
    cfg: &PoseConfig,
    p: &mut TriangulatedPoint,
    rays: &mut Vec<Ray>,
) {
    for (c, cam) in cams.iter().enumerate() {
        if p.blobs[c] != NO_BLOB {
            continue;
        }
        let mut best: Option<(f64, u8)> = None;
        for br in &cam.rays {
            let v = p.point_mm - br.ray.origin_mm;
            let along = v.dot(&br.ray.dir);
            if along.is_nan() || along <= 0.0 {
                continue;
            }
            let d = (v - br.ray.dir * along).norm();
            if d <= cfg.max_gap_mm && best.is_none_or(|(bd, _)| d < bd) {
                best = Some((d, br.blob));
            }
        }
        if let Some((_, b)) = best {
            p.blobs[c] = b;
            p.cameras += 1;
        }
    }
    if p.cameras > 2 {
        rays.clear();
        for (c, cam) in cams.iter().enumerate() {
            if let Some(br) = cam.rays.iter().find(|r| r.blob == p.blobs[c]) {
                rays.push(br.ray);
            }
        }
        if let Ok((q, rms)) = least_squares_rays(rays) {
            p.point_mm = q;
            p.gap_mm = rms;
        }
    }
}

/// Inserts `p` unless an equal or better-confirmed candidate already covers its blobs;
/// removes candidates it covers. When full, the largest gap gives way.
fn insert_candidate(points: &mut Vec<TriangulatedPoint>, dropped: &mut u32, p: TriangulatedPoint) {
    if points.iter().any(|q| p.is_subset_of(q)) {
        return;
    }
    points.retain(|q| !q.is_subset_of(&p));
    if points.len() < points.capacity() {
        points.push(p);
        return;
    }
    *dropped += 1;
    let worst = points
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.gap_mm.total_cmp(&b.1.gap_mm))
        .map(|(i, q)| (i, q.gap_mm));
    if let Some((i, g)) = worst
        && p.gap_mm < g
    {
        points[i] = p;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{CameraModel, Distortion, ImageSize, Intrinsics};
    use crate::params::CameraParams;

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

    /// Two parallel cameras, camera 1 200 mm along camera 0's x axis.
    fn rig() -> RigParams {
        let shifted = RigidTransform {
            t_mm: [-200.0, 0.0, 0.0],
            ..RigidTransform::IDENTITY
        };
        RigParams {
            rig_id: "parallel".into(),
            created_unix_s: 0,
            cameras: alloc::vec![
                CameraParams {
                    model: camera(),
                    cam_from_cam0: RigidTransform::IDENTITY,
                },
                CameraParams {
                    model: camera(),
                    cam_from_cam0: shifted,
                },
            ],
            world_from_cam0: None,
            tools: Vec::new(),
            calibration: None,
            placement: Vec::new(),
            timing: Vec::new(),
            serial: 0,
        }
    }

    fn blobs(rig: &RigParams, points: &[Vector3<f64>]) -> Vec<Vec<Blob>> {
        rig.cameras
            .iter()
            .map(|c| {
                points
                    .iter()
                    .map(|p| {
                        let px = c.model.project(&c.cam_from_cam0.apply(p)).unwrap();
                        Blob {
                            x_px: px.x,
                            y_px: px.y,
                            area_px: 9,
                            roundness: 1.0,
                            ..Blob::default()
                        }
                    })
                    .collect()
            })
            .collect()
    }

    fn near(points: &[TriangulatedPoint], want: Vector3<f64>) -> bool {
        points.iter().any(|p| (p.point_mm - want).norm() < 1e-6)
    }

    #[test]
    fn points_on_different_epipolar_planes_triangulate_exactly() {
        let rig = rig();
        let truth = [Vector3::new(0.0, 0.0, 1000.0), Vector3::new(50.0, 80.0, 1200.0)];
        let b = blobs(&rig, &truth);
        let lists: Vec<&[Blob]> = b.iter().map(|v| v.as_slice()).collect();
        let mut m = PointMatcher::new(&rig, &PoseConfig::default()).unwrap();
        let points = m.solve(&lists).unwrap();
        assert_eq!(points.len(), 2, "{points:?}");
        for (i, t) in truth.iter().enumerate() {
            let p = points.iter().find(|p| p.blobs[0] == i as u8).unwrap();
            assert!((p.point_mm - t).norm() < 1e-6, "{} vs {t}", p.point_mm);
            assert!(p.gap_mm < 1e-6);
            assert_eq!((p.blobs[1], p.cameras), (i as u8, 2));
        }
    }

    #[test]
    fn ghosts_on_one_epipolar_plane_are_kept_at_their_predicted_places() {
        // Both LEDs on the plane y = 0: each ray of camera 0 meets each ray of camera 1.
        // Ray 0→P0 (the z axis) meets camera 1's ray to P1 where 200 − 100 s = 0: z = 2000;
        // ray 0→P1 meets camera 1's ray to P0 at s = 2/3 of P1.
        let rig = rig();
        let p0 = Vector3::new(0.0, 0.0, 1000.0);
        let p1 = Vector3::new(100.0, 0.0, 1000.0);
        let b = blobs(&rig, &[p0, p1]);
        let lists: Vec<&[Blob]> = b.iter().map(|v| v.as_slice()).collect();
        let mut m = PointMatcher::new(&rig, &PoseConfig::default()).unwrap();
        let points = m.solve(&lists).unwrap();
        assert_eq!(points.len(), 4, "{points:?}");
        assert!(near(points, p0) && near(points, p1));
        assert!(near(points, Vector3::new(0.0, 0.0, 2000.0)));
        assert!(near(points, p1 * (2.0 / 3.0)));
        assert_eq!(m.dropped(), 0);
    }

    #[test]
    fn unusable_blobs_and_wrong_inputs_are_refused() {
        let rig = rig();
        let mut b = blobs(&rig, &[Vector3::new(0.0, 0.0, 1000.0)]);
        let mut m = PointMatcher::new(&rig, &PoseConfig::default()).unwrap();
        // A streak (low roundness) in one camera leaves no pair.
        b[1][0].roundness = 0.1;
        let lists: Vec<&[Blob]> = b.iter().map(|v| v.as_slice()).collect();
        assert!(m.solve(&lists).unwrap().is_empty());
        assert!(m.solve(&lists[..1]).is_err());
        let mut one = rig.clone();
        one.cameras.truncate(1);
        assert!(PointMatcher::new(&one, &PoseConfig::default()).is_err());
    }
}
