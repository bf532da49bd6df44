//! Chessboard detection with sub-pixel refinement (OpenCV), with a progress bar.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

use anyhow::{Result, anyhow, bail};
use indicatif::{ProgressBar, ProgressStyle};
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Size, TermCriteria, TermCriteria_Type, Vector};
use opencv::imgcodecs;
use opencv::imgproc;
use opencv::prelude::*;

use super::input::ImageSet;

/// Board geometry as the user gives it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Board {
    /// Inner corners per row.
    pub cols: u32,
    /// Inner corners per column.
    pub rows: u32,
    /// Side of one printed square (mm); sets the scale of every pose and baseline.
    pub square_mm: f64,
}

impl Board {
    /// Inner corners in the board frame, row by row (OpenCV's detection order).
    pub fn object_points(&self) -> Vector<opencv::core::Point3f> {
        let s = self.square_mm as f32;
        (0..self.rows)
            .flat_map(|r| {
                (0..self.cols).map(move |c| opencv::core::Point3f::new(c as f32 * s, r as f32 * s, 0.0))
            })
            .collect()
    }

    /// Inner corners on the board (`cols × rows`), what a full detection must find.
    pub fn corner_count(&self) -> usize {
        self.cols as usize * self.rows as usize
    }
}

/// Detections of one camera.
#[derive(Debug, Clone)]
pub struct CameraDetections {
    /// Size of this camera's images (width, height, px); its intrinsics are fitted for it.
    pub image_size: (u32, u32),
    /// Refined corners per view where the board was found.
    pub found: BTreeMap<String, Vec<Point2f>>,
    /// Views whose image did not show the whole board.
    pub not_found: Vec<String>,
    /// View name → image file.
    pub files: BTreeMap<String, PathBuf>,
}

/// Reads an image as 8-bit grey (OpenCV converts colour and deeper images).
pub fn load_grey(path: &Path) -> Result<Mat> {
    let name = path
        .to_str()
        .ok_or_else(|| anyhow!("{}: path is not UTF-8 (OpenCV needs UTF-8)", path.display()))?;
    let img = imgcodecs::imread(name, imgcodecs::IMREAD_GRAYSCALE)
        .map_err(|e| anyhow!("{}: cannot read image: {}", path.display(), e.message))?;
    if img.empty() {
        bail!(
            "{}: cannot read image (missing, truncated or not an image format OpenCV knows)",
            path.display()
        );
    }
    Ok(img)
}

/// Finds the board in one grey image and refines the corners; `None` when not found.
pub fn find_corners(img: &Mat, board: &Board) -> Result<Option<Vec<Point2f>>> {
    let pattern = Size::new(board.cols as i32, board.rows as i32);
    let mut corners: Vector<Point2f> = Vector::new();
    let flags =
        calib3d::CALIB_CB_ADAPTIVE_THRESH | calib3d::CALIB_CB_NORMALIZE_IMAGE | calib3d::CALIB_CB_FAST_CHECK;
    if !calib3d::find_chessboard_corners(img, pattern, &mut corners, flags)? {
        return Ok(None);
    }
    // Refinement window: as large as possible (up to 11 px half-width) while staying inside
    // one square, so that no neighbouring corner enters it.
    let cols = board.cols as usize;
    let pts = corners.to_vec();
    let mut min_spacing = f32::INFINITY;
    for (i, p) in pts.iter().enumerate() {
        if (i + 1) % cols != 0 {
            let q = pts[i + 1];
            min_spacing = min_spacing.min(((q.x - p.x).powi(2) + (q.y - p.y).powi(2)).sqrt());
        }
        if i + cols < pts.len() {
            let q = pts[i + cols];
            min_spacing = min_spacing.min(((q.x - p.x).powi(2) + (q.y - p.y).powi(2)).sqrt());
        }
    }
    let half = ((min_spacing * 0.5).floor() as i32 - 1).clamp(2, 11);
    let criteria = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 | TermCriteria_Type::EPS as i32,
        100,
        1e-4,
    )?;
    imgproc::corner_sub_pix(
        img,
        &mut corners,
        Size::new(half, half),
        Size::new(-1, -1),
        criteria,
    )?;
    Ok(Some(corners.to_vec()))
}

/// The board sizes next to `board` (one more or one fewer inner corner per row and/or column,
/// and rows and columns exchanged), most likely first: counting squares instead of inner
/// corners gives one more of each.
fn neighbour_sizes(board: &Board) -> Vec<(u32, u32)> {
    let (c, r) = (board.cols as i64, board.rows as i64);
    let mut out: Vec<(u32, u32)> = Vec::new();
    for (dc, dr) in [
        (-1, -1),
        (1, 1),
        (-1, 0),
        (0, -1),
        (1, 0),
        (0, 1),
        (-1, 1),
        (1, -1),
    ] {
        let (nc, nr) = (c + dc, r + dr);
        if nc >= 2 && nr >= 2 {
            out.push((nc as u32, nr as u32));
        }
    }
    out
}

/// Which board size near the given one `img` shows, if any (see [`neighbour_sizes`]).
pub fn other_board_size(img: &Mat, board: &Board) -> Result<Option<(u32, u32)>> {
    for (cols, rows) in neighbour_sizes(board) {
        let b = Board { cols, rows, ..*board };
        if find_corners(img, &b)?.is_some() {
            return Ok(Some((cols, rows)));
        }
    }
    Ok(None)
}

/// Loads and searches every image of every camera. Errors on unreadable images and on images
/// of one camera with different sizes. The progress bar is drawn only on a terminal.
pub fn detect_all(set: &ImageSet, board: &Board) -> Result<Vec<CameraDetections>> {
    let total: usize = set.cameras.iter().map(|c| c.files.len()).sum();
    let bar = if std::io::stderr().is_terminal() {
        let bar = ProgressBar::new(total as u64);
        if let Ok(style) = ProgressStyle::with_template("detecting corners {bar:40} {pos}/{len} {msg}") {
            bar.set_style(style);
        }
        bar
    } else {
        ProgressBar::hidden()
    };
    let mut out = Vec::with_capacity(set.cameras.len());
    for (ci, cam) in set.cameras.iter().enumerate() {
        let mut size: Option<(u32, u32, &Path)> = None;
        let mut found = BTreeMap::new();
        let mut not_found = Vec::new();
        for (view, path) in &cam.files {
            bar.set_message(format!("cam{ci} {view}"));
            let img = load_grey(path)?;
            let (w, h) = (img.cols() as u32, img.rows() as u32);
            match size {
                None => size = Some((w, h, path)),
                Some((w0, h0, first)) if (w0, h0) != (w, h) => {
                    bar.finish_and_clear();
                    bail!(
                        "image sizes differ within camera {ci} ({}): {} is {w}x{h} but {} is {w0}x{h0}",
                        cam.label,
                        path.display(),
                        first.display()
                    );
                }
                Some(_) => {}
            }
            match find_corners(&img, board)? {
                Some(c) => {
                    found.insert(view.clone(), c);
                }
                None => not_found.push(view.clone()),
            }
            bar.inc(1);
        }
        let (w, h, _) = size.ok_or_else(|| anyhow!("camera {ci} ({}) has no images", cam.label))?;
        // Searching for a wrongly sized board is slow in OpenCV: stop at the first camera
        // where it was never found instead of searching the others too.
        if found.is_empty() {
            bar.finish_and_clear();
            let hint = match cam.files.values().next() {
                Some(first) => match other_board_size(&load_grey(first)?, board)? {
                    Some((cols, rows)) => format!(
                        ". Likely cause: the board size. {} shows a board of {cols}x{rows} inner corners: \
                         give --board-cols {cols} --board-rows {rows}",
                        first.display()
                    ),
                    None => String::new(),
                },
                None => String::new(),
            };
            bail!(
                "the {}x{} board (inner corners) was found in none of the {} images of camera {ci} ({}). \
                 Check --board-cols/--board-rows: they count inner corners (squares per row minus one), \
                 and the whole board with a white border must be in view{hint}",
                board.cols,
                board.rows,
                not_found.len(),
                cam.label
            );
        }
        out.push(CameraDetections {
            image_size: (w, h),
            found,
            not_found,
            files: cam.files.clone(),
        });
    }
    bar.finish_and_clear();
    Ok(out)
}
