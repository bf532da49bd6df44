//! PNG figures of a calibration (corner coverage per camera over its first image, per-view
//! errors) and of the accuracy study, drawn with `plotters` into an RGB buffer and encoded with
//! `png`. Text uses DejaVu Sans embedded in the binary (`host-tools/assets/`, Bitstream Vera
//! licence), registered with plotters' `ab_glyph` font backend: no system fonts, no fontconfig.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, Result, anyhow};
use opencv::core::Point2f;
use plotters::coord::ReverseCoordTranslate;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

/// DejaVu Sans 2.37 (Debian's fonts-dejavu-core); licence in assets/DejaVuSans-LICENSE.txt.
static FONT_TTF: &[u8] = include_bytes!("../../assets/DejaVuSans.ttf");
/// The family name the embedded font is registered under.
pub const FONT: &str = "sans-serif";

/// Registers the embedded font once; every figure calls it before drawing text.
pub fn ensure_font() -> Result<()> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE.get_or_init(|| register_font(FONT, FontStyle::Normal, FONT_TTF).is_ok());
    if ok {
        Ok(())
    } else {
        Err(anyhow!("the embedded DejaVu Sans font does not load"))
    }
}

/// Series colours: well-separated hues (matplotlib's "tab10").
pub fn palette(i: usize) -> RGBColor {
    const P: [(u8, u8, u8); 8] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = P[i % P.len()];
    RGBColor(r, g, b)
}

/// Rejected views and the outlier threshold.
pub const ALERT: RGBColor = RGBColor(214, 39, 40);

/// Plotters' drawing errors carry the backend's error type; flatten them for anyhow.
pub fn draw_err<E: std::fmt::Debug>(e: E) -> anyhow::Error {
    anyhow!("drawing the figure failed: {e:?}")
}

/// Draws a chart's legend box (one style for every figure: translucent white, thin border).
pub fn draw_legend<'a, DB, CT>(
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
    font_px: u32,
) -> Result<()>
where
    DB: DrawingBackend + 'a,
    CT: plotters::coord::CoordTranslate,
{
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK.mix(0.3))
        .label_font((FONT, font_px))
        .draw()
        .map_err(draw_err)
}

/// Writes an RGB8 buffer as PNG.
pub fn write_rgb_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    let file = std::fs::File::create(path).with_context(|| format!("{}: cannot create", path.display()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc
        .write_header()
        .with_context(|| format!("{}: PNG header", path.display()))?;
    w.write_image_data(rgb)
        .with_context(|| format!("{}: PNG data", path.display()))?;
    Ok(())
}

/// An 8-bit grey image to draw under the coverage (a camera's first calibration image).
pub struct Background<'a> {
    /// Image width (px).
    pub width_px: u32,
    /// Image height (px).
    pub height_px: u32,
    /// Grey values, row-major, `width_px × height_px` bytes.
    pub pixels: &'a [u8],
}

/// One view's corners on a camera's image plane.
pub struct CoverageView<'a> {
    /// Detected corners (distorted pixels).
    pub corners: &'a [Point2f],
    /// The view was rejected as an outlier: drawn as red crosses.
    pub rejected: bool,
}

/// Detected corners of every view (one colour per view; rejected views as red crosses) and
/// each board's outline, in image pixel coordinates over `background` (dimmed, so the marks
/// stay visible) or a blank image-sized plane.
pub fn coverage_png(
    path: &Path,
    image_size: (u32, u32),
    board_cols: u32,
    views: &[CoverageView<'_>],
    title: &str,
    background: Option<&Background<'_>>,
) -> Result<()> {
    ensure_font()?;
    let (w, h) = image_size;
    let (width, height) = (w + 90, h + 90);
    let mut rgb = vec![255u8; (width * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        // y grows downwards in images; the chart's y is the negated row so it reads the same.
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 16))
            .margin(10)
            .x_label_area_size(34)
            .y_label_area_size(46)
            .build_cartesian_2d(-0.5..f64::from(w) - 0.5, -(f64::from(h) - 0.5)..0.5)
            .map_err(draw_err)?;
        if let Some(bg) = background.filter(|b| (b.width_px, b.height_px) == image_size) {
            let area = chart.plotting_area();
            let (xs, ys) = area.get_pixel_range();
            let coords = area.as_coord_spec();
            for py in ys {
                for px in xs.clone() {
                    let Some((x, y)) = coords.reverse_translate((px, py)) else {
                        continue;
                    };
                    let (ix, iy) = (x.round(), (-y).round());
                    if ix < 0.0 || iy < 0.0 || ix >= f64::from(w) || iy >= f64::from(h) {
                        continue;
                    }
                    let v = bg.pixels[iy as usize * w as usize + ix as usize];
                    // Dimmed towards light grey: the image stays readable under the marks.
                    let g = (110 + u16::from(v) * 145 / 255) as u8;
                    root.draw_pixel((px, py), &RGBColor(g, g, g)).map_err(draw_err)?;
                }
            }
        }
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc("x (px)")
            .y_desc("y (px)")
            .y_label_formatter(&|v| format!("{:.0}", -v))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .label_style((FONT, 12))
            .draw()
            .map_err(draw_err)?;
        let cols = board_cols as usize;
        for (vi, v) in views.iter().enumerate() {
            let colour = if v.rejected { ALERT } else { palette(vi) };
            let pt = |i: usize| (f64::from(v.corners[i].x), -f64::from(v.corners[i].y));
            let n = v.corners.len();
            if cols > 0 && n >= cols {
                let rows = n / cols;
                let outline = vec![
                    pt(0),
                    pt(cols - 1),
                    pt(rows * cols - 1),
                    pt((rows - 1) * cols),
                    pt(0),
                ];
                chart
                    .draw_series(std::iter::once(PathElement::new(outline, colour.stroke_width(1))))
                    .map_err(draw_err)?;
            }
            if v.rejected {
                chart
                    .draw_series((0..n).map(|i| Cross::new(pt(i), 4, colour.stroke_width(1))))
                    .map_err(draw_err)?;
            } else {
                chart
                    .draw_series((0..n).map(|i| Circle::new(pt(i), 2, colour.filled())))
                    .map_err(draw_err)?;
            }
        }
        root.present().map_err(draw_err)?;
    }
    write_rgb_png(path, width, height, &rgb)
}

/// Grouped bar chart of per-view RMS errors: one group per view, one bar per series (camera),
/// a dashed line at the outlier threshold and rejected views marked in red under the axis.
pub fn view_errors_png(
    path: &Path,
    views: &[String],
    series: &[(String, Vec<Option<f64>>)],
    rejected: &[bool],
    threshold_px: Option<f64>,
) -> Result<()> {
    ensure_font()?;
    let n_views = views.len().max(1);
    let width = (120 + 22 * n_views as u32).clamp(560, 2400);
    let height = 420;
    let max_err = series
        .iter()
        .flat_map(|(_, v)| v.iter().flatten().copied())
        .chain(threshold_px)
        .fold(0.0f64, f64::max)
        .max(1e-3)
        * 1.15;
    let labels = short_labels(views);
    let mut rgb = vec![255u8; (width * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (width, height)).into_drawing_area();
        let mut chart = ChartBuilder::on(&root)
            .caption("per-view RMS reprojection error (px)", (FONT, 16))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .build_cartesian_2d(0.0..n_views as f64, 0.0..max_err)
            .map_err(draw_err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(0)
            .y_desc("RMS (px)")
            .x_desc("view")
            .y_label_formatter(&|v| format!("{v:.3}"))
            .label_style((FONT, 12))
            .draw()
            .map_err(draw_err)?;
        let n_series = series.len().max(1) as f64;
        let bar_w = 0.8 / n_series;
        for (si, (name, vals)) in series.iter().enumerate() {
            let colour = palette(si);
            chart
                .draw_series(vals.iter().enumerate().filter_map(|(vi, e)| {
                    let e = (*e)?;
                    let x0 = vi as f64 + 0.1 + si as f64 * bar_w;
                    Some(Rectangle::new(
                        [(x0, 0.0), (x0 + bar_w * 0.9, e)],
                        colour.filled(),
                    ))
                }))
                .map_err(draw_err)?
                .label(name.as_str())
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], colour.filled()));
        }
        // View names (without their common prefix) under each group; rejected ones in red.
        let area = chart.plotting_area();
        let (_, ys) = area.get_pixel_range();
        for (vi, label) in labels.iter().enumerate() {
            let colour = if rejected.get(vi).copied().unwrap_or(false) {
                ALERT
            } else {
                BLACK
            };
            let (px, _) = area.map_coordinate(&(vi as f64 + 0.5, 0.0));
            let style = TextStyle::from((FONT, 11).into_font())
                .color(&colour)
                .transform(FontTransform::Rotate90);
            root.draw_text(label, &style, (px + 5, ys.end + 4))
                .map_err(draw_err)?;
        }
        if let Some(th) = threshold_px {
            chart
                .draw_series(DashedLineSeries::new(
                    [(0.0, th), (n_views as f64, th)],
                    6,
                    4,
                    ALERT.stroke_width(1),
                ))
                .map_err(draw_err)?
                .label(format!("outlier threshold {th:.3} px"))
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 14, y)], ALERT.stroke_width(1)));
        }
        draw_legend(&mut chart, SeriesLabelPosition::UpperRight, 12)?;
        root.present().map_err(draw_err)?;
    }
    write_rgb_png(path, width, height, &rgb)
}

/// View names without the prefix they all share (keeping at least one character of each),
/// at most 10 characters: axis labels stay short.
fn short_labels(views: &[String]) -> Vec<String> {
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
    let prefix_len = prefix_len.min(
        views
            .iter()
            .map(|v| v.chars().count().saturating_sub(1))
            .min()
            .unwrap_or(0),
    );
    views
        .iter()
        .map(|v| v.chars().skip(prefix_len).take(10).collect())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png_size(path: &Path) -> (u32, u32) {
        let dec = png::Decoder::new(std::fs::File::open(path).unwrap());
        let reader = dec.read_info().unwrap();
        let info = reader.info();
        (info.width, info.height)
    }

    #[test]
    fn labels_drop_the_common_prefix() {
        let v: Vec<String> = ["view_001", "view_002", "view_013"].map(String::from).to_vec();
        assert_eq!(short_labels(&v), ["01", "02", "13"]);
        let one = vec!["abc".to_string()];
        assert_eq!(short_labels(&one), ["c"]);
    }

    #[test]
    fn figures_draw_with_the_embedded_font_and_the_background() {
        let dir = std::env::temp_dir().join(format!("irtrack-plots-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (w, h) = (160u32, 120u32);
        let pixels: Vec<u8> = (0..w * h).map(|i| ((i % w) * 255 / w) as u8).collect();
        let corners: Vec<Point2f> = (0..6)
            .flat_map(|r| (0..9).map(move |c| Point2f::new(20.0 + 12.0 * c as f32, 20.0 + 12.0 * r as f32)))
            .collect();
        let views = [
            CoverageView {
                corners: &corners,
                rejected: false,
            },
            CoverageView {
                corners: &corners[..9],
                rejected: true,
            },
        ];
        let bg = Background {
            width_px: w,
            height_px: h,
            pixels: &pixels,
        };
        let p = dir.join("cov.png");
        coverage_png(&p, (w, h), 9, &views, "cam0: 2 views", Some(&bg)).unwrap();
        assert_eq!(png_size(&p), (w + 90, h + 90));
        let names: Vec<String> = (0..5).map(|i| format!("v{i:02}")).collect();
        let series = vec![
            (
                "cam0".to_string(),
                vec![Some(0.1), Some(0.2), None, Some(0.05), Some(0.3)],
            ),
            (
                "cam1".to_string(),
                vec![Some(0.12), None, Some(0.2), Some(0.06), Some(0.25)],
            ),
        ];
        let p = dir.join("err.png");
        view_errors_png(
            &p,
            &names,
            &series,
            &[false, true, false, false, false],
            Some(0.28),
        )
        .unwrap();
        assert_eq!(png_size(&p), (560, 420));
        // Text was rendered: the caption row holds dark pixels (anti-aliased glyphs).
        let dec = png::Decoder::new(std::fs::File::open(&p).unwrap());
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        reader.next_frame(&mut buf).unwrap();
        let dark = buf[..560 * 3 * 30]
            .chunks(3)
            .filter(|px| px.iter().all(|v| *v < 100))
            .count();
        assert!(dark > 50, "no caption text drawn ({dark} dark pixels)");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
