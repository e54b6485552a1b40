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

/// Reusable tables and row buffer of [`resize_bilinear`].
#[derive(Debug, Default, Clone)]
pub struct ResizeScratch {
    xofs: Vec<u32>,
    xw: Vec<u16>,
    row: Vec<u16>,
}

fn source_pos(d: usize, ratio: f64, src_extent: usize) -> (usize, u16) {
    let f = (d as f64 + 0.5) * ratio - 0.5;
    if f <= 0.0 || src_extent < 2 {
        return (0, 0);
    }
    let i = f.floor() as usize;
    if i >= src_extent - 1 {
        return (src_extent - 2, 256);
    }
    let w = ((f - i as f64) * 256.0).round() as u16;
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
        scratch.xofs.push(i as u32);
        scratch.xw.push(w);
    }
    scratch.row.clear();
    scratch.row.resize(sw + 1, 0);
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
        let wy0 = 256 - wy;
        // Vertical blend of two whole rows: value * 256 fits u16.
        for ((o, &a), &b) in row[..sw].iter_mut().zip(r0).zip(r1) {
            *o = a as u16 * wy0 + b as u16 * wy1;
        }
        row[sw] = row[last];
        // Horizontal gather.
        for ((o, &ofs), &wx) in out.iter_mut().zip(&scratch.xofs).zip(&scratch.xw) {
            let i = ofs as usize;
            debug_assert!(i < sw);
            // SAFETY: `source_pos` returns offsets below `sw - 1` (or 0 when
            // `sw < 2`), and `row` holds `sw + 1` values.
            let (a, b) = unsafe { (*row.get_unchecked(i) as u32, *row.get_unchecked(i + 1) as u32) };
            let v = a * (256 - wx as u32) + b * wx as u32;
            *o = ((v + (1 << 15)) >> 16) as u8;
        }
    }
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
