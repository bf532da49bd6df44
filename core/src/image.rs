//! Borrowed grey images (8- and 16-bit) and regions of interest.
//!
//! Images are views into caller-owned buffers (V4L2 mmap buffers, simulator frames), so the
//! per-frame path never copies or allocates. Pixel (0,0) is the top-left pixel; its centre is
//! at coordinate (0.0, 0.0), as in OpenCV.

use crate::{Error, Result};

/// A pixel type the blob detector can read: unsigned, with a known full-scale value.
pub trait Pixel: Copy + Ord + Default + Send + Sync + 'static {
    /// Full-scale value (the saturation level unless configured otherwise).
    const MAX_DN: u32;
    /// The value as an integer in digital numbers.
    fn dn(self) -> u32;
    /// `v` as a pixel, clamped to full scale.
    fn from_dn_saturating(v: u32) -> Self;
    /// The pixels as bytes when the type is `u8` (the blob detector's SIMD kernels are for
    /// 8-bit frames); `None` for wider types.
    #[inline(always)]
    fn as_u8(pixels: &[Self]) -> Option<&[u8]> {
        let _ = pixels;
        None
    }
}

impl Pixel for u8 {
    const MAX_DN: u32 = u8::MAX as u32;
    #[inline(always)]
    fn dn(self) -> u32 {
        self as u32
    }
    #[inline(always)]
    fn from_dn_saturating(v: u32) -> Self {
        v.min(Self::MAX_DN) as u8
    }
    #[inline(always)]
    fn as_u8(pixels: &[u8]) -> Option<&[u8]> {
        Some(pixels)
    }
}

impl Pixel for u16 {
    const MAX_DN: u32 = u16::MAX as u32;
    #[inline(always)]
    fn dn(self) -> u32 {
        self as u32
    }
    #[inline(always)]
    fn from_dn_saturating(v: u32) -> Self {
        v.min(Self::MAX_DN) as u16
    }
}

/// A grey image borrowed from a caller's buffer. Rows are `stride_px` pixels apart
/// (stride ≥ width, for padded V4L2 buffers).
#[derive(Debug, Clone, Copy)]
pub struct GrayImage<'a, P> {
    /// The pixels, row-major, rows `stride_px` apart.
    pub data: &'a [P],
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
    /// Pixels from one row to the next (>= `width_px`).
    pub stride_px: u32,
}

impl<'a, P> GrayImage<'a, P> {
    /// A checked view: non-zero size, stride ≥ width, and `data` long enough for every row.
    pub fn new(data: &'a [P], width_px: u32, height_px: u32, stride_px: u32) -> Result<Self> {
        let img = GrayImage {
            data,
            width_px,
            height_px,
            stride_px,
        };
        img.validate()?;
        Ok(img)
    }

    /// Re-checks the invariants of [`GrayImage::new`] (the fields are public, so a view
    /// built literally is checked again before pixel loops index into it).
    pub fn validate(&self) -> Result<()> {
        if self.width_px == 0 || self.height_px == 0 {
            return Err(Error::BadFrame {
                what: "zero width or height",
            });
        }
        if self.stride_px < self.width_px {
            return Err(Error::BadFrame {
                what: "stride smaller than width",
            });
        }
        let needed = (self.stride_px as usize)
            .checked_mul(self.height_px as usize - 1)
            .and_then(|n| n.checked_add(self.width_px as usize))
            .ok_or(Error::BadFrame {
                what: "frame size overflows usize",
            })?;
        if self.data.len() < needed {
            return Err(Error::BufferTooSmall {
                what: "image data",
                needed,
                have: self.data.len(),
            });
        }
        Ok(())
    }

    /// Row `y` (exactly `width_px` pixels); empty if out of range or the view is invalid.
    #[inline]
    pub fn row(&self, y: u32) -> &'a [P] {
        let start = y as usize * self.stride_px as usize;
        self.data
            .get(start..start + self.width_px as usize)
            .unwrap_or(&[])
    }

    /// The whole frame as a region of interest.
    pub fn full_roi(&self) -> Roi {
        Roi {
            x_px: 0,
            y_px: 0,
            width_px: self.width_px,
            height_px: self.height_px,
        }
    }
}

/// An axis-aligned region of interest in pixels (top-left corner and size).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Roi {
    /// Left column.
    pub x_px: u32,
    /// Top row.
    pub y_px: u32,
    /// Columns.
    pub width_px: u32,
    /// Rows.
    pub height_px: u32,
}

impl Roi {
    /// A window of `2 * half_px + 1` pixels per side centred on the pixel nearest
    /// (`x_px`, `y_px`), clipped to a `frame_w` × `frame_h` frame. A centre outside the frame
    /// (or NaN) is clamped to the nearest border pixel.
    pub fn around(x_px: f64, y_px: f64, half_px: u32, frame_w: u32, frame_h: u32) -> Roi {
        let clamp = |v: f64, n: u32| -> i64 {
            let max = n.saturating_sub(1) as f64;
            // `max`/`min` on a NaN pick the other operand, so NaN lands on 0.
            libm::round(v.max(0.0).min(max)) as i64
        };
        let (cx, cy, h) = (clamp(x_px, frame_w), clamp(y_px, frame_h), half_px as i64);
        let x0 = (cx - h).max(0);
        let y0 = (cy - h).max(0);
        let x1 = (cx + h + 1).min(frame_w as i64);
        let y1 = (cy + h + 1).min(frame_h as i64);
        Roi {
            x_px: x0 as u32,
            y_px: y0 as u32,
            width_px: (x1 - x0).max(0) as u32,
            height_px: (y1 - y0).max(0) as u32,
        }
    }

    /// Errors unless the region is non-empty and inside a `frame_w` × `frame_h` frame.
    pub fn check(&self, frame_w: u32, frame_h: u32) -> Result<()> {
        let inside = self.width_px > 0
            && self.height_px > 0
            && (self.x_px as u64 + self.width_px as u64) <= frame_w as u64
            && (self.y_px as u64 + self.height_px as u64) <= frame_h as u64;
        if inside {
            Ok(())
        } else {
            Err(Error::BadRoi {
                x: self.x_px,
                y: self.y_px,
                w: self.width_px,
                h: self.height_px,
                frame_w,
                frame_h,
            })
        }
    }

    /// Number of pixels in the region.
    pub fn area_px(&self) -> u64 {
        self.width_px as u64 * self.height_px as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn new_checks_geometry() {
        let buf = [0u8; 100];
        assert!(GrayImage::new(&buf, 10, 10, 10).is_ok());
        // Padded stride: last row needs only `width` pixels.
        assert!(GrayImage::new(&buf, 8, 10, 10).is_ok());
        assert!(matches!(
            GrayImage::new(&buf, 10, 11, 10),
            Err(Error::BufferTooSmall { .. })
        ));
        assert!(matches!(
            GrayImage::new(&buf, 11, 9, 10),
            Err(Error::BadFrame { .. })
        ));
        assert!(matches!(
            GrayImage::new(&buf, 0, 9, 10),
            Err(Error::BadFrame { .. })
        ));
        let literal = GrayImage {
            data: &buf[..50],
            width_px: 10,
            height_px: 10,
            stride_px: 10,
        };
        assert!(literal.validate().is_err());
        assert!(literal.row(7).is_empty());
    }

    #[test]
    fn roi_around_clips_to_frame() {
        let r = Roi::around(2.4, 478.6, 5, 640, 480);
        assert_eq!(
            r,
            Roi {
                x_px: 0,
                y_px: 474,
                width_px: 8,
                height_px: 6
            }
        );
        assert!(r.check(640, 480).is_ok());
        let r = Roi::around(320.0, 240.0, 5, 640, 480);
        assert_eq!(
            r,
            Roi {
                x_px: 315,
                y_px: 235,
                width_px: 11,
                height_px: 11
            }
        );
        let r = Roi::around(f64::NAN, 1e9, 3, 640, 480);
        assert_eq!(
            r,
            Roi {
                x_px: 0,
                y_px: 476,
                width_px: 4,
                height_px: 4
            }
        );
        assert!(
            Roi {
                x_px: 630,
                y_px: 0,
                width_px: 11,
                height_px: 1
            }
            .check(640, 480)
            .is_err()
        );
        assert!(
            Roi {
                x_px: 0,
                y_px: 0,
                width_px: 0,
                height_px: 1
            }
            .check(640, 480)
            .is_err()
        );
    }
}
