//! OpenCV's equivalent of our pipeline (host only: feature `opencv`).

use anyhow::{Result, bail};
use nalgebra::Vector3;
use opencv::core::{self as cv, Mat, MatTraitConst, Point2d, Rect, Scalar, Vector};
use opencv::{calib3d, imgproc};

use irtrack_core::params::RigParams;

use crate::{Set, THRESHOLD_DN};

/// The same job with OpenCV: threshold, connectedComponentsWithStats, intensity moments of
/// the largest component (pixels minus threshold inside its mask), undistortPoints,
/// triangulatePoints. Buffers are kept across frames so OpenCV can reuse them.
pub struct OpenCv {
    k: [Mat; 2],
    d: [Mat; 2],
    p: [Mat; 2],
    bin: Mat,
    labels: Mat,
    stats: Mat,
    centroids: Mat,
    mask: Mat,
    shifted: Mat,
    weighted: Mat,
    points4: Mat,
}

impl OpenCv {
    pub fn new(rig: &RigParams) -> Result<Self> {
        // One thread, like our pipeline (and the board).
        cv::set_num_threads(1)?;
        let mut k = [Mat::default(), Mat::default()];
        let mut d = [Mat::default(), Mat::default()];
        let mut p = [Mat::default(), Mat::default()];
        for c in 0..2 {
            let cam = &rig.cameras[c];
            let i = &cam.model.intrinsics;
            k[c] = Mat::from_slice_2d(&[[i.fx_px, 0.0, i.cx_px], [0.0, i.fy_px, i.cy_px], [0.0, 0.0, 1.0]])?;
            d[c] = Mat::from_slice_2d(&[cam.model.distortion.as_array()])?;
            let r = cam.cam_from_cam0.r_row_major;
            let t = cam.cam_from_cam0.t_mm;
            p[c] = Mat::from_slice_2d(&[
                [r[0], r[1], r[2], t[0]],
                [r[3], r[4], r[5], t[1]],
                [r[6], r[7], r[8], t[2]],
            ])?;
        }
        Ok(OpenCv {
            k,
            d,
            p,
            bin: Mat::default(),
            labels: Mat::default(),
            stats: Mat::default(),
            centroids: Mat::default(),
            mask: Mat::default(),
            shifted: Mat::default(),
            weighted: Mat::default(),
            points4: Mat::default(),
        })
    }

    /// Centroid of the largest component, pixels.
    fn centroid(&mut self, name: &str, frame: &[u8], w: u32, h: u32, c: usize) -> Result<(f64, f64)> {
        let src = Mat::new_rows_cols_with_data(h as i32, w as i32, frame)?;
        imgproc::threshold(
            &src,
            &mut self.bin,
            THRESHOLD_DN as f64,
            255.0,
            imgproc::THRESH_BINARY,
        )?;
        let n = imgproc::connected_components_with_stats(
            &self.bin,
            &mut self.labels,
            &mut self.stats,
            &mut self.centroids,
            8,
            cv::CV_32S,
        )?;
        let mut best = (0, 0);
        for label in 1..n {
            let area = *self.stats.at_2d::<i32>(label, imgproc::CC_STAT_AREA)?;
            if area > best.1 {
                best = (label, area);
            }
        }
        if best.0 == 0 {
            bail!("{name}: OpenCV found no component in camera {c}");
        }
        let st = |k: i32| -> Result<i32> { Ok(*self.stats.at_2d::<i32>(best.0, k)?) };
        let rect = Rect::new(
            st(imgproc::CC_STAT_LEFT)?,
            st(imgproc::CC_STAT_TOP)?,
            st(imgproc::CC_STAT_WIDTH)?,
            st(imgproc::CC_STAT_HEIGHT)?,
        );
        let labels_roi = Mat::roi(&self.labels, rect)?;
        let src_roi = Mat::roi(&src, rect)?;
        cv::compare(
            &labels_roi,
            &Scalar::all(best.0 as f64),
            &mut self.mask,
            cv::CMP_EQ,
        )?;
        // Weight = value − threshold (saturating at 0), kept only inside the component.
        cv::subtract(
            &src_roi,
            &Scalar::all(THRESHOLD_DN as f64),
            &mut self.shifted,
            &cv::no_array(),
            -1,
        )?;
        cv::min(&self.shifted, &self.mask, &mut self.weighted)?;
        let m = imgproc::moments(&self.weighted, false)?;
        if m.m00 <= 0.0 {
            bail!("{name}: OpenCV component without weight in camera {c}");
        }
        Ok((rect.x as f64 + m.m10 / m.m00, rect.y as f64 + m.m01 / m.m00))
    }

    /// The 3-D point (camera-0 frame, mm) from one 8-bit stereo set of `w` × `h` frames.
    pub fn run(&mut self, name: &str, frames: &Set<u8>, w: u32, h: u32) -> Result<Vector3<f64>> {
        let mut normalized = [[0.0f64; 2]; 2];
        for (c, n) in normalized.iter_mut().enumerate() {
            let (x, y) = self.centroid(name, &frames[c], w, h, c)?;
            let src = Vector::<Point2d>::from_slice(&[Point2d::new(x, y)]);
            let mut dst = Vector::<Point2d>::new();
            calib3d::undistort_points(
                &src,
                &mut dst,
                &self.k[c],
                &self.d[c],
                &cv::no_array(),
                &cv::no_array(),
            )?;
            let q = dst.get(0)?;
            *n = [q.x, q.y];
        }
        let a = Mat::from_slice_2d(&[[normalized[0][0]], [normalized[0][1]]])?;
        let b = Mat::from_slice_2d(&[[normalized[1][0]], [normalized[1][1]]])?;
        calib3d::triangulate_points(&self.p[0], &self.p[1], &a, &b, &mut self.points4)?;
        let h = |r: i32| -> Result<f64> {
            Ok(if self.points4.typ() == cv::CV_64F {
                *self.points4.at_2d::<f64>(r, 0)?
            } else {
                *self.points4.at_2d::<f32>(r, 0)? as f64
            })
        };
        let w = h(3)?;
        Ok(Vector3::new(h(0)? / w, h(1)? / w, h(2)? / w))
    }
}
