//! Explicit SIMD kernels of the blob detector for 8-bit tracking windows (16..=64 pixels
//! wide): 16-byte vectors of the `wide` crate, which lowers each operation to `core::arch`
//! per target — SSE2 on x86_64, NEON on aarch64 (both baselines, so no run-time detection;
//! with `-C target-feature=+avx2` the same code compiles to VEX forms) — and to plain arrays
//! elsewhere. `wide` is no_std and already in irtrack-core's dependency tree (nalgebra →
//! simba); using it keeps this crate free of `unsafe` (`#![forbid(unsafe_code)]`): every
//! `core::arch` intrinsic is an `unsafe fn` to a crate that cannot mark its functions with
//! `#[target_feature]` safely.
//!
//! Why by hand: in a 49-pixel window the generic code spends most of its instructions on
//! per-row bookkeeping, not pixels, and LLVM does not derive a compare-to-bit-mask
//! (`pmovmskb`) from the generic pixel code. With a row's "above threshold" bits in one
//! `u64`, runs are found with `trailing_zeros` instead of chunk tests and a pixel walk.
//!
//! A function returns `None` when the request is outside what it handles (width out of
//! range, rows outside the slice); the caller then takes the portable path. Results equal
//! the portable path's exactly (maxima and bit masks are exact); `tests/simd_kernels.rs`
//! compares the two paths on random frames, on the host and under qemu-aarch64.

use wide::u8x16;

/// Narrowest row the kernels take (one 16-byte vector).
pub const MIN_W: usize = 16;
/// Widest row the kernels take (the mask is a `u64`).
pub const MAX_W: usize = 64;

/// Whether this build's vectors are real SIMD registers (else the kernels still give the
/// right answer, as arrays, but the portable path is as good).
pub const AVAILABLE: bool = cfg!(any(
    all(target_arch = "x86_64", target_feature = "sse2"),
    all(target_arch = "aarch64", target_feature = "neon")
));

/// Name of the instruction set the kernels use in this build.
pub const NAME: &str = if cfg!(all(target_arch = "x86_64", target_feature = "avx2")) {
    "SSE2/AVX2 (x86_64)"
} else if cfg!(all(target_arch = "x86_64", target_feature = "sse2")) {
    "SSE2 (x86_64)"
} else if cfg!(all(target_arch = "aarch64", target_feature = "neon")) {
    "NEON (aarch64)"
} else {
    "none (portable)"
};

/// A threshold broadcast to every lane (made once per window).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Threshold(u8x16);

impl Threshold {
    #[inline(always)]
    pub(crate) fn new(thr: u8) -> Self {
        Threshold(u8x16::splat(thr))
    }
}

/// Bits of the lanes above the threshold: v > thr ⇔ (v −sat thr) ≠ 0, and the compare with
/// zero marks the dark lanes.
#[inline(always)]
fn above(v: u8x16, t: Threshold) -> u64 {
    let dark = v.saturating_sub(t.0).cmp_eq(u8x16::ZERO).move_mask() as u32;
    (!dark & 0xffff) as u64
}

/// Number `K` of 16-byte blocks taken from the left of a `w`-pixel row (16 ≤ w ≤ 64); one
/// more is taken flush with the row's end (they may overlap, which is harmless for a maximum
/// and for a bit mask). The window scan is compiled once per `K`, so every row is a fixed,
/// unrolled sequence of loads.
#[inline(always)]
pub(crate) fn left_blocks(w: usize) -> usize {
    w.saturating_sub(1) / 16
}

/// Whether `w` is a width the kernels for `K` take. Stated as plain bounds (16·K < w,
/// 16 ≤ w ≤ 16·K + 16) so the compiler sees that every block load is inside the row.
#[inline(always)]
fn fits<const K: usize>(w: usize) -> bool {
    w > 16 * K && w >= MIN_W && w <= 16 * K + 16 && w <= MAX_W
}

/// The block of `row` starting at `o` (`None` past the end; the callers' width checks make
/// the compiler drop these checks).
#[inline(always)]
fn block(row: &[u8], o: usize) -> Option<u8x16> {
    Some(u8x16::new(*row.get(o..)?.first_chunk::<16>()?))
}

#[inline(always)]
fn tail(row: &[u8]) -> Option<u8x16> {
    Some(u8x16::new(*row.last_chunk::<16>()?))
}

/// Lane-wise maximum of a row that `fits::<K>`.
#[inline(always)]
fn row_max<const K: usize>(row: &[u8]) -> Option<u8x16> {
    let mut m = tail(row)?;
    for k in 0..K {
        m = m.max(block(row, 16 * k)?);
    }
    Some(m)
}

/// Whether any pixel of `rows` rows of `w` pixels (`fits::<K>(w)`), the first at
/// `data[start]`, `stride` apart, is above the threshold. `None` if a row is not inside
/// `data` or `w` does not fit `K`.
#[inline(always)]
pub(crate) fn group_has_bright<const K: usize>(
    data: &[u8],
    start: usize,
    stride: usize,
    rows: usize,
    w: usize,
    t: Threshold,
) -> Option<bool> {
    if !fits::<K>(w) || rows == 0 || stride < w {
        return None;
    }
    let mut m = u8x16::ZERO;
    // Whole strides when the data has them (every group but one at the very end of a tight
    // buffer): `chunks_exact` lets the compiler hoist the row-length check out of the loop.
    if let Some(region) = rows.checked_mul(stride).and_then(|n| data.get(start..)?.get(..n)) {
        for row in region.chunks_exact(stride) {
            m = m.max(row_max::<K>(row.get(..w)?)?);
        }
    } else {
        let len = (rows - 1).checked_mul(stride)?.checked_add(w)?;
        for row in data.get(start..)?.get(..len)?.chunks(stride) {
            m = m.max(row_max::<K>(row.get(..w)?)?);
        }
    }
    Some(above(m, t) != 0)
}

/// Bit `i` set ⇔ `row[i]` is above the threshold, for `fits::<K>(row.len())`; else `None`.
#[inline(always)]
pub(crate) fn bright_mask<const K: usize>(row: &[u8], t: Threshold) -> Option<u64> {
    let w = row.len();
    if !fits::<K>(w) {
        return None;
    }
    let mut m = above(tail(row)?, t) << (w - 16);
    for k in 0..K {
        m |= above(block(row, 16 * k)?, t) << (16 * k);
    }
    Some(m)
}

/// [`group_has_bright`] for any width (dispatches on `K`; tests and one-off callers).
pub fn group_has_bright_u8(
    data: &[u8],
    start: usize,
    stride: usize,
    rows: usize,
    w: usize,
    thr: u8,
) -> Option<bool> {
    let t = Threshold::new(thr);
    match left_blocks(w) {
        0 => group_has_bright::<0>(data, start, stride, rows, w, t),
        1 => group_has_bright::<1>(data, start, stride, rows, w, t),
        2 => group_has_bright::<2>(data, start, stride, rows, w, t),
        3 => group_has_bright::<3>(data, start, stride, rows, w, t),
        _ => None,
    }
}

/// [`bright_mask`] for any width.
pub fn bright_mask_u8(row: &[u8], thr: u8) -> Option<u64> {
    let t = Threshold::new(thr);
    match left_blocks(row.len()) {
        0 => bright_mask::<0>(row, t),
        1 => bright_mask::<1>(row, t),
        2 => bright_mask::<2>(row, t),
        3 => bright_mask::<3>(row, t),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Kernels against the obvious scalar definitions, every width, random bytes.
    #[test]
    fn kernels_match_scalar_definitions() {
        let mut s = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        let mut data = [0u8; 70 * 12];
        for _ in 0..200 {
            for b in data.iter_mut() {
                // Mostly dark, some bright, some at the threshold ± 1.
                let r = next();
                *b = match r % 8 {
                    0 => (r >> 8) as u8,
                    1 => 29 + (r >> 8) as u8 % 3,
                    _ => (r >> 8) as u8 % 20,
                };
            }
            for w in MIN_W..=MAX_W {
                let thr = 30u8;
                for y in 0..12 {
                    let row = &data[y * 70..y * 70 + w];
                    let want = row
                        .iter()
                        .enumerate()
                        .fold(0u64, |m, (i, &v)| m | (((v > thr) as u64) << i));
                    assert_eq!(bright_mask_u8(row, thr), Some(want), "w {w} row {y}");
                }
                let rows = 1 + (next() % 8) as usize;
                let start = (next() % 4) as usize;
                let max = (0..rows)
                    .flat_map(|r| data[start + r * 70..start + r * 70 + w].iter().copied())
                    .max();
                for t in [0u8, 29, 30, 31, 200, 254, 255] {
                    let want = max.map(|m| m > t);
                    assert_eq!(
                        group_has_bright_u8(&data, start, 70, rows, w, t),
                        want,
                        "w {w} thr {t}"
                    );
                }
            }
        }
        // Out of range: refused, never read out of bounds.
        assert_eq!(bright_mask_u8(&data[..15], 3), None);
        assert_eq!(bright_mask_u8(&data[..65], 3), None);
        assert_eq!(group_has_bright_u8(&data[..100], 0, 70, 2, 40, 3), None);
        assert_eq!(group_has_bright_u8(&data, 0, 70, 0, 40, 3), None);
        assert_eq!(group_has_bright_u8(&data, 0, 70, 2, 65, 3), None);
    }
}
