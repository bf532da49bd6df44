//! PNG figures of a calibration: corner coverage per camera and per-view errors.

use std::path::Path;

use anyhow::{Result, anyhow, bail};
use opencv::core::{CV_8UC3, Mat, Point, Point2f, Rect, Scalar, Vector};
use opencv::imgcodecs;
use opencv::imgproc;

/// Colour (BGR) of series `i`: well-separated hues.
fn palette(i: usize) -> Scalar {
    const P: [(f64, f64, f64); 8] = [
        (180.0, 119.0, 31.0),
        (14.0, 127.0, 255.0),
        (44.0, 160.0, 44.0),
        (189.0, 103.0, 148.0),
        (75.0, 86.0, 140.0),
        (194.0, 119.0, 227.0),
        (34.0, 189.0, 188.0),
        (207.0, 190.0, 23.0),
    ];
    let (b, g, r) = P[i % P.len()];
    Scalar::new(b, g, r, 0.0)
}

const RED: (f64, f64, f64) = (40.0, 40.0, 220.0);

fn scalar(c: (f64, f64, f64)) -> Scalar {
    Scalar::new(c.0, c.1, c.2, 0.0)
}

fn write_png(path: &Path, img: &Mat) -> Result<()> {
    let name = path
        .to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8", path.display()))?;
    if !imgcodecs::imwrite_def(name, img)? {
        bail!("{}: OpenCV could not write the PNG", path.display());
    }
    Ok(())
}

fn text(img: &mut Mat, s: &str, x: i32, y: i32, scale: f64, colour: Scalar) -> Result<()> {
    imgproc::put_text(
        img,
        s,
        Point::new(x, y),
        imgproc::FONT_HERSHEY_SIMPLEX,
        scale,
        colour,
        1,
        imgproc::LINE_AA,
        false,
    )?;
    Ok(())
}

/// One view's corners on a camera's image plane.
pub struct CoverageView<'a> {
    pub corners: &'a [Point2f],
    pub rejected: bool,
}

/// Draws every view's detected corners (one colour per view, rejected views as red crosses)
/// and the board outline on an image-sized canvas.
pub fn coverage_png(
    path: &Path,
    image_size: (u32, u32),
    board_cols: u32,
    views: &[CoverageView<'_>],
    title: &str,
) -> Result<()> {
    let mut img = Mat::new_rows_cols_with_default(
        image_size.1 as i32,
        image_size.0 as i32,
        CV_8UC3,
        Scalar::new(250.0, 250.0, 250.0, 0.0),
    )?;
    let cols = board_cols as usize;
    for (vi, v) in views.iter().enumerate() {
        let colour = if v.rejected { scalar(RED) } else { palette(vi) };
        let n = v.corners.len();
        if n >= cols && cols > 0 {
            let rows = n / cols;
            let pick = |i: usize| {
                let p = v.corners[i];
                Point::new(p.x.round() as i32, p.y.round() as i32)
            };
            let outline: Vector<Point> = [
                pick(0),
                pick(cols - 1),
                pick(rows * cols - 1),
                pick((rows - 1) * cols),
            ]
            .into_iter()
            .collect();
            let polys: Vector<Vector<Point>> = [outline].into_iter().collect();
            imgproc::polylines(&mut img, &polys, true, colour, 1, imgproc::LINE_AA, 0)?;
        }
        for p in v.corners {
            let c = Point::new(p.x.round() as i32, p.y.round() as i32);
            if v.rejected {
                imgproc::draw_marker(&mut img, c, colour, imgproc::MARKER_CROSS, 6, 1, imgproc::LINE_8)?;
            } else {
                imgproc::circle(&mut img, c, 2, colour, imgproc::FILLED, imgproc::LINE_AA, 0)?;
            }
        }
    }
    text(&mut img, title, 8, 18, 0.5, Scalar::new(20.0, 20.0, 20.0, 0.0))?;
    write_png(path, &img)
}

/// Bar chart of per-view RMS errors: one group per view, one bar per series (camera), a dashed
/// line at the outlier threshold and rejected views' labels in red.
pub fn view_errors_png(
    path: &Path,
    views: &[String],
    series: &[(String, Vec<Option<f64>>)],
    rejected: &[bool],
    threshold_px: Option<f64>,
) -> Result<()> {
    let n_series = series.len().max(1);
    let bar_w = 8;
    let group_w = (bar_w * n_series as i32 + 6).max(14);
    let (left, right, top, bottom) = (60, 20, 40, 70);
    let plot_w = group_w * views.len().max(1) as i32;
    let width = (left + plot_w + right).max(480);
    let height = 360;
    let plot_h = height - top - bottom;
    let mut img =
        Mat::new_rows_cols_with_default(height, width, CV_8UC3, Scalar::new(255.0, 255.0, 255.0, 0.0))?;
    let max_err = series
        .iter()
        .flat_map(|(_, v)| v.iter().flatten().copied())
        .chain(threshold_px)
        .fold(0.0f64, f64::max)
        .max(1e-3)
        * 1.1;
    let y_of = |e: f64| top + plot_h - ((e / max_err) * plot_h as f64).round() as i32;
    let black = Scalar::new(30.0, 30.0, 30.0, 0.0);
    let grey = Scalar::new(200.0, 200.0, 200.0, 0.0);
    // Axes and a few gridlines.
    for k in 0..=4 {
        let e = max_err * k as f64 / 4.0;
        let y = y_of(e);
        imgproc::line(
            &mut img,
            Point::new(left, y),
            Point::new(left + plot_w, y),
            grey,
            1,
            imgproc::LINE_8,
            0,
        )?;
        text(&mut img, &format!("{e:.3}"), 4, y + 4, 0.35, black)?;
    }
    imgproc::line(
        &mut img,
        Point::new(left, top),
        Point::new(left, top + plot_h),
        black,
        1,
        imgproc::LINE_8,
        0,
    )?;
    let prefix_len = views
        .iter()
        .skip(1)
        .fold(views.first().map_or(0, |v| v.chars().count()), |n, v| {
            views[0]
                .chars()
                .zip(v.chars())
                .take(n)
                .take_while(|(a, b)| a == b)
                .count()
        });
    // Keep at least one character of every name.
    let prefix_len = prefix_len.min(
        views
            .iter()
            .map(|v| v.chars().count().saturating_sub(1))
            .min()
            .unwrap_or(0),
    );
    for (vi, view) in views.iter().enumerate() {
        let gx = left + vi as i32 * group_w + 3;
        for (si, (_, vals)) in series.iter().enumerate() {
            if let Some(Some(e)) = vals.get(vi) {
                let y = y_of(*e);
                let rect = Rect::new(gx + si as i32 * bar_w, y, bar_w - 1, (top + plot_h - y).max(1));
                imgproc::rectangle(&mut img, rect, palette(si), imgproc::FILLED, imgproc::LINE_8, 0)?;
            }
        }
        let colour = if rejected.get(vi).copied().unwrap_or(false) {
            scalar(RED)
        } else {
            black
        };
        // View names without their common prefix, vertically under the group (OpenCV has no
        // rotated text; stack characters).
        let label: String = view.chars().skip(prefix_len).take(6).collect();
        for (k, ch) in label.chars().enumerate() {
            text(
                &mut img,
                &ch.to_string(),
                gx,
                top + plot_h + 12 + 10 * k as i32,
                0.3,
                colour,
            )?;
        }
    }
    if let Some(th) = threshold_px {
        let y = y_of(th);
        let mut x = left;
        while x < left + plot_w {
            imgproc::line(
                &mut img,
                Point::new(x, y),
                Point::new((x + 6).min(left + plot_w), y),
                scalar(RED),
                1,
                imgproc::LINE_8,
                0,
            )?;
            x += 10;
        }
        text(
            &mut img,
            &format!("outlier threshold {th:.3} px"),
            left + 4,
            y - 4,
            0.35,
            scalar(RED),
        )?;
    }
    text(
        &mut img,
        "per-view RMS reprojection error (px)",
        left,
        16,
        0.45,
        black,
    )?;
    let mut lx = left;
    for (si, (name, _)) in series.iter().enumerate() {
        imgproc::rectangle(
            &mut img,
            Rect::new(lx, 24, 10, 8),
            palette(si),
            imgproc::FILLED,
            imgproc::LINE_8,
            0,
        )?;
        text(&mut img, name, lx + 14, 32, 0.35, black)?;
        lx += 14 + 8 * name.len() as i32 + 12;
    }
    write_png(path, &img)
}
