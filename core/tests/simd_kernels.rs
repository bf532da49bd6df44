//! The blob detector's explicit SIMD kernels (SSE2 on x86_64, NEON on aarch64; see
//! `irtrack_core::simd`) against its portable path: bit-identical blobs, rejected blobs and
//! statistics on random frames and windows. Runs on the host and, in `cargo xtask test
//! --only aarch64-tests`, under qemu-aarch64 (the NEON kernels).

use irtrack_core::blob::{BlobConfig, BlobDetector, BlobLimits, Kernel};
use irtrack_core::image::{GrayImage, Roi};
use irtrack_core::simd;
use proptest::prelude::*;

/// SplitMix64: frame contents from one seed, so a failing case is reproduced by its seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
}

/// A frame of `stride` × `h` bytes: background near `thr`, plus (by `style`) Gaussian-ish
/// spots, random blotches, dense salt-and-pepper or saturated bars, so rows hold 0, 1 or
/// many runs, runs touch the window's first and last column, and values sit at thr ± 1.
fn frame(rng: &mut Rng, stride: usize, h: usize, thr: u8, style: u8) -> Vec<u8> {
    let bg = thr.saturating_sub(1 + rng.below(12) as u8);
    let mut img: Vec<u8> = (0..stride * h)
        .map(|_| bg.saturating_add(rng.below(2) as u8))
        .collect();
    let put = |img: &mut Vec<u8>, x: usize, y: usize, v: u8| {
        if x < stride && y < h {
            img[y * stride + x] = v;
        }
    };
    match style % 4 {
        0 => {
            // LED-like spots.
            for _ in 0..1 + rng.below(4) {
                let (cx, cy) = (rng.below(stride as u64) as f64, rng.below(h as u64) as f64);
                let s = 0.7 + rng.below(30) as f64 / 10.0;
                let peak = 40.0 + rng.below(400) as f64;
                let r = (4.0 * s) as i64 + 1;
                for dy in -r..=r {
                    for dx in -r..=r {
                        let (x, y) = (cx as i64 + dx, cy as i64 + dy);
                        if x < 0 || y < 0 {
                            continue;
                        }
                        let v = bg as f64 + peak * (-((dx * dx + dy * dy) as f64) / (2.0 * s * s)).exp();
                        put(&mut img, x as usize, y as usize, v.min(255.0) as u8);
                    }
                }
            }
        }
        1 => {
            // Blotches with holes (many runs per row, U shapes, diagonal contacts).
            for _ in 0..rng.below(8) {
                let (cx, cy) = (rng.below(stride as u64) as usize, rng.below(h as u64) as usize);
                let (rx, ry) = (1 + rng.below(20) as usize, 1 + rng.below(10) as usize);
                for y in cy.saturating_sub(ry)..cy + ry + 1 {
                    for x in cx.saturating_sub(rx)..cx + rx + 1 {
                        if rng.below(10) < 7 {
                            let v = thr.saturating_add(1 + rng.below(255) as u8);
                            put(&mut img, x, y, v);
                        }
                    }
                }
            }
        }
        2 => {
            // Dense noise straddling the threshold.
            let p = 1 + rng.below(9);
            for v in img.iter_mut() {
                if rng.below(10) < p {
                    *v = thr.saturating_add(rng.below(3) as u8);
                }
            }
        }
        _ => {
            // Saturated horizontal bars (long runs, whole window rows).
            for _ in 0..1 + rng.below(3) {
                let y0 = rng.below(h as u64) as usize;
                let x0 = rng.below(stride as u64) as usize;
                let len = 1 + rng.below(stride as u64) as usize;
                for y in y0..y0 + 1 + rng.below(4) as usize {
                    for x in x0..x0 + len {
                        put(&mut img, x, y, 255);
                    }
                }
            }
        }
    }
    img
}

/// One detection with a given kernel: blobs, rejected blobs, stats.
fn detect(
    det: &mut BlobDetector,
    kernel: Kernel,
    img: &GrayImage<'_, u8>,
    roi: Option<Roi>,
    cfg: &BlobConfig,
) -> (
    Vec<irtrack_core::blob::Blob>,
    Vec<irtrack_core::blob::Blob>,
    irtrack_core::blob::DetectStats,
) {
    det.set_kernel(kernel);
    let blobs = det.detect(img, roi, cfg).expect("valid frame").to_vec();
    (blobs, det.rejected_by_area().to_vec(), det.stats())
}

/// Both kernels on one window: (portable, SIMD) results with the "which path" flag taken out
/// of the stats, and whether the SIMD path really ran.
#[allow(clippy::type_complexity)]
fn both(
    det: &mut BlobDetector,
    img: &GrayImage<'_, u8>,
    roi: Roi,
    cfg: &BlobConfig,
) -> (
    (
        Vec<irtrack_core::blob::Blob>,
        Vec<irtrack_core::blob::Blob>,
        irtrack_core::blob::DetectStats,
    ),
    (
        Vec<irtrack_core::blob::Blob>,
        Vec<irtrack_core::blob::Blob>,
        irtrack_core::blob::DetectStats,
    ),
    bool,
) {
    let portable = detect(det, Kernel::Portable, img, Some(roi), cfg);
    let mut vector = detect(det, Kernel::Simd, img, Some(roi), cfg);
    assert!(!portable.2.simd_kernel, "the portable kernel must not use SIMD");
    let ran = vector.2.simd_kernel;
    vector.2.simd_kernel = false;
    (portable, vector, ran)
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 400,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// Random 8-bit frames and windows (every width 1..=80 around the kernels' 16..=64, every
    /// position incl. the frame's edges, padded strides, any threshold, saturation level and
    /// label budget): both kernels report exactly the same.
    #[test]
    fn simd_and_portable_kernels_give_identical_blobs(
        seed in any::<u64>(),
        width in 1u32..=80,
        style in 0u8..4,
        thr in 0u8..=254,
        pad in 0u32..6,
        sat in proptest::option::of(0u32..300),
        tight_labels in any::<bool>(),
    ) {
        let mut rng = Rng(seed);
        let (w, h) = (96u32, 40u32);
        let stride = w + pad;
        let img = frame(&mut rng, stride as usize, h as usize, thr, style);
        let g = GrayImage::new(&img, w, h, stride).expect("frame geometry");
        let rh = 1 + rng.below(h as u64) as u32;
        let roi = Roi {
            x_px: rng.below((w - width + 1) as u64) as u32,
            y_px: rng.below((h - rh + 1) as u64) as u32,
            width_px: width,
            height_px: rh,
        };
        let cfg = BlobConfig {
            threshold_dn: thr as u32,
            saturation_dn: sat,
            min_area_px: 1 + rng.below(4) as u32,
            max_area_px: 5 + rng.below(200) as u32,
        };
        let mut det = BlobDetector::new(BlobLimits {
            max_labels: if tight_labels { 1 + rng.below(12) as usize } else { 4096 },
            max_blobs: 1 + rng.below(20) as usize,
            ..BlobLimits::for_frame(w, h)
        })
        .expect("limits");
        let (portable, vector, ran) = both(&mut det, &g, roi, &cfg);
        prop_assert_eq!(ran, simd::AVAILABLE && (simd::MIN_W..=simd::MAX_W).contains(&(width as usize)));
        prop_assert_eq!(&portable, &vector, "window {:?}, {}", roi, simd::NAME);
    }
}

/// The property above only means something if the SIMD path ran and found things: count the
/// windows it handled that had blobs, and check that a tracking window (49 px) takes it where
/// the build has the kernels (x86_64, aarch64) and the portable path where not (armv7).
#[test]
fn simd_path_is_exercised() {
    assert_eq!(
        simd::AVAILABLE,
        cfg!(any(target_arch = "x86_64", target_arch = "aarch64")),
        "this build has no SIMD kernels ({})",
        simd::NAME
    );
    let mut rng = Rng(7);
    let (w, h) = (96u32, 40u32);
    let mut det = BlobDetector::new(BlobLimits::for_frame(w, h)).expect("limits");
    let mut with_blobs = 0;
    for round in 0..200u32 {
        let img = frame(&mut rng, w as usize, h as usize, 30, (round % 4) as u8);
        let g = GrayImage::new(&img, w, h, w).expect("frame");
        let roi = Roi {
            x_px: rng.below(48) as u32,
            y_px: 0,
            width_px: 49,
            height_px: h,
        };
        let cfg = BlobConfig {
            min_area_px: 1,
            ..BlobConfig::default()
        };
        let (a, b, ran) = both(&mut det, &g, roi, &cfg);
        // Where the build has no SIMD kernels (armv7: `wide` has no 32-bit ARM back end) the
        // window must fall back to the portable path, with the same result.
        assert_eq!(
            ran,
            simd::AVAILABLE,
            "a 49-pixel 8-bit window must take the SIMD kernels exactly where the build has them ({})",
            simd::NAME
        );
        assert_eq!(a, b, "round {round}");
        with_blobs += usize::from(!b.0.is_empty());
    }
    assert!(with_blobs > 100, "only {with_blobs} of 200 windows had blobs");
}
