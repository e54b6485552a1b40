//! Bilinear downscaling for the image pyramid.
//!
//! Pixel centres are aligned (OpenCV's `INTER_LINEAR` convention): destination
//! pixel `x` samples the source at `(x + 0.5) * sw / dw - 0.5`. Chaining levels
//! therefore keeps the simple relation `x0 = (xl + 0.5) * w0 / wl - 0.5`
//! between level `l` and level 0, which [`level_to_level0`] applies.
//!
//! The vertical pass runs first on whole rows (contiguous, vectorised), then a
//! horizontal gather with precomputed offsets and 8-bit weights.

/// Size of level `level` for a level-0 image of `w` x `h`: ORB-SLAM's
/// `round(w / s^level)`.
pub fn level_size(w: usize, h: usize, scale_factor: f32, level: usize) -> (usize, usize) {
    let s = (scale_factor as f64).powi(level as i32);
    (
        (w as f64 / s).round() as usize,
        (h as f64 / s).round() as usize,
    )
}

/// Map a level pixel coordinate to level 0, given the level-0 and level
/// extents along that axis (pixel-centre aligned).
#[inline]
pub fn level_to_level0(v: f32, extent0: usize, extent_level: usize) -> f32 {
    if extent_level == 0 {
        return v;
    }
    (v + 0.5) * (extent0 as f32 / extent_level as f32) - 0.5
}

/// Interpolation weights are fixed point with this unit (7 bits), so that a
/// vertically blended value (`<= 255 * 128`) fits a signed 16-bit lane.
const WEIGHT_ONE: u16 = 128;

/// Reusable tables and row buffer of [`resize_bilinear`].
#[derive(Debug, Default, Clone)]
pub struct ResizeScratch {
    xofs: Vec<i32>,
    /// Weight pairs `(1 - w) | w << 16` per destination column.
    xw: Vec<u32>,
    row: Vec<u16>,
}

fn source_pos(d: usize, ratio: f64, src_extent: usize) -> (usize, u16) {
    let f = (d as f64 + 0.5) * ratio - 0.5;
    if f <= 0.0 || src_extent < 2 {
        return (0, 0);
    }
    let i = f.floor() as usize;
    if i >= src_extent - 1 {
        return (src_extent - 2, WEIGHT_ONE);
    }
    let w = ((f - i as f64) * WEIGHT_ONE as f64).round() as u16;
    (i, w)
}

/// Resize `src` (`sw` x `sh`, row-major, no padding) into `dst` (`dw` x `dh`)
/// by bilinear interpolation. `dst` is resized to `dw * dh`. Sizes of zero give
/// an empty destination; a source of one pixel in either direction is
/// replicated.
#[inline(always)]
pub fn resize_bilinear(
    src: &[u8],
    sw: usize,
    sh: usize,
    dst: &mut Vec<u8>,
    dw: usize,
    dh: usize,
    scratch: &mut ResizeScratch,
) {
    if dst.len() != dw * dh {
        dst.clear();
        dst.resize(dw * dh, 0);
    }
    if sw == 0 || sh == 0 || dw == 0 || dh == 0 || src.len() < sw * sh {
        dst.fill(0);
        return;
    }
    let rx = sw as f64 / dw as f64;
    let ry = sh as f64 / dh as f64;
    scratch.xofs.clear();
    scratch.xw.clear();
    for x in 0..dw {
        let (i, w) = source_pos(x, rx, sw);
        scratch.xofs.push(i as i32);
        scratch.xw.push((WEIGHT_ONE - w) as u32 | (w as u32) << 16);
    }
    scratch.row.clear();
    scratch.row.resize(sw + 1, 0);
    // Every pair `row[i], row[i + 1]` read by the gather lies inside `row`.
    let tables_ok = scratch.xofs.iter().all(|&i| i >= 0 && (i as usize) < sw);
    let row = &mut scratch.row;
    let last = sw - 1;
    for (y, out) in dst.chunks_exact_mut(dw).enumerate() {
        let (sy, wy) = source_pos(y, ry, sh);
        let r0 = &src[sy * sw..sy * sw + sw];
        let r1 = if sh > 1 {
            &src[(sy + 1) * sw..(sy + 1) * sw + sw]
        } else {
            r0
        };
        let wy1 = wy;
        let wy0 = WEIGHT_ONE - wy;
        // Vertical blend of two whole rows: value * 128 fits i16.
        for ((o, &a), &b) in row[..sw].iter_mut().zip(r0).zip(r1) {
            *o = a as u16 * wy0 + b as u16 * wy1;
        }
        row[sw] = row[last];
        // Horizontal gather.
        let done = if tables_ok {
            hgather(row, &scratch.xofs, &scratch.xw, out)
        } else {
            0
        };
        for ((o, &ofs), &wp) in out[done..]
            .iter_mut()
            .zip(&scratch.xofs[done..])
            .zip(&scratch.xw[done..])
        {
            let i = ofs as usize;
            let (a, b) = (row[i] as u32, row[i + 1] as u32);
            let v = a * (wp & 0xffff) + b * (wp >> 16);
            *o = ((v + (1 << 13)) >> 14) as u8;
        }
    }
}

/// Horizontal pass with AVX2 gathers, 8 columns at a time; returns how many
/// leading columns it wrote (0 without AVX2). The caller guarantees
/// `0 <= xofs[i] < row.len() - 1` for every `i`.
#[inline(always)]
fn hgather(row: &[u16], xofs: &[i32], xw: &[u32], out: &mut [u8]) -> usize {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present (checked just above); the offsets are
            // inside `row`, as this function's caller guarantees.
            return unsafe { hgather_avx2(row, xofs, xw, out) };
        }
    }
    let _ = (row, xofs, xw, out);
    0
}

/// # Safety
/// The CPU supports AVX2, and `0 <= xofs[i] < row.len() - 1` for every `i`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn hgather_avx2(row: &[u16], xofs: &[i32], xw: &[u32], out: &mut [u8]) -> usize {
    use std::arch::x86_64::*;
    let n = out.len().min(xofs.len()).min(xw.len()) / 8 * 8;
    let base = row.as_ptr() as *const i32;
    let round = _mm256_set1_epi32(1 << 13);
    let mut x = 0;
    while x < n {
        // SAFETY: `x + 8 <= n` bounds the loads and stores; the gathered
        // 4-byte reads at byte offsets `2 i` cover `row[i]` and `row[i + 1]`,
        // inside `row` (the caller's guarantee, checked in `resize_bilinear`).
        unsafe {
            let idx = _mm256_loadu_si256(xofs.as_ptr().add(x) as *const __m256i);
            let wts = _mm256_loadu_si256(xw.as_ptr().add(x) as *const __m256i);
            let pairs = _mm256_i32gather_epi32::<2>(base, idx);
            let v = _mm256_srai_epi32::<14>(_mm256_add_epi32(_mm256_madd_epi16(pairs, wts), round));
            let v16 = _mm256_packus_epi32(v, v);
            let v8 = _mm256_packus_epi16(v16, v16);
            let lo = _mm_cvtsi128_si32(_mm256_castsi256_si128(v8));
            let hi = _mm_cvtsi128_si32(_mm256_extracti128_si256::<1>(v8));
            let dst = out.as_mut_ptr().add(x);
            std::ptr::write_unaligned(dst as *mut i32, lo);
            std::ptr::write_unaligned(dst.add(4) as *mut i32, hi);
        }
        x += 8;
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_follow_orb_slam() {
        assert_eq!(level_size(640, 480, 1.2, 0), (640, 480));
        assert_eq!(level_size(640, 480, 1.2, 1), (533, 400));
        assert_eq!(level_size(640, 480, 1.2, 7), (179, 134));
    }

    #[test]
    fn resize_constant_and_ramp() {
        let (sw, sh) = (60, 40);
        let src = vec![77u8; sw * sh];
        let mut dst = Vec::new();
        let mut s = ResizeScratch::default();
        resize_bilinear(&src, sw, sh, &mut dst, 50, 33, &mut s);
        assert_eq!(dst.len(), 50 * 33);
        assert!(dst.iter().all(|&v| v == 77));

        // A horizontal ramp v = 2x is resampled at the aligned positions.
        let src: Vec<u8> = (0..sh)
            .flat_map(|_| (0..sw).map(|x| (2 * x) as u8))
            .collect();
        resize_bilinear(&src, sw, sh, &mut dst, 50, 33, &mut s);
        for x in 1..49 {
            let f = (x as f64 + 0.5) * 1.2 - 0.5;
            let want = 2.0 * f;
            let got = dst[10 * 50 + x] as f64;
            assert!((got - want).abs() <= 1.0, "x {x}: {got} vs {want}");
        }
    }

    #[test]
    fn degenerate_sizes_do_not_panic() {
        let mut dst = Vec::new();
        let mut s = ResizeScratch::default();
        resize_bilinear(&[5], 1, 1, &mut dst, 1, 1, &mut s);
        assert_eq!(dst, vec![5]);
        resize_bilinear(&[], 0, 0, &mut dst, 3, 3, &mut s);
        assert_eq!(dst, vec![0; 9]);
        resize_bilinear(&[1, 2, 3], 3, 1, &mut dst, 2, 1, &mut s);
        assert_eq!(dst.len(), 2);
    }
}
