//! Gaussian smoothing and steered BRIEF descriptors.
//!
//! The level is smoothed with a 7x7 Gaussian of sigma 2 (separable, 8-bit
//! fixed-point taps `[18, 34, 49, 54, 49, 34, 18] / 256`, borders reflected
//! without repeating the edge pixel). The 256 tests of the learned pattern are
//! rotated by the keypoint angle, rounded to whole pixels and compared: bit `i`
//! is 1 when the first point of pair `i` is darker than the second.

use super::Descriptor;
use super::pattern::ORB_PATTERN;

const TAPS: [u16; 7] = [18, 34, 49, 54, 49, 34, 18];

/// Largest distance (pixels, per axis) a rotated pattern point can reach from
/// the keypoint.
pub const PATTERN_REACH: usize = 18;

#[inline]
fn reflect101(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let mut i = i;
    while i < 0 || i >= n {
        if i < 0 {
            i = -i;
        }
        if i >= n {
            i = 2 * (n - 1) - i;
        }
    }
    i as usize
}

/// Reusable row buffer of [`gaussian_blur`].
#[derive(Debug, Default, Clone)]
pub struct BlurScratch {
    row: Vec<u8>,
}

/// Smooth `src` (`w` x `h`) into `dst` with the 7x7 Gaussian (sigma 2):
/// per output row, a vertical pass over 7 source rows into one row buffer,
/// then the horizontal pass, each one fused loop over symmetric tap pairs.
#[inline(always)]
pub fn gaussian_blur(src: &[u8], w: usize, h: usize, dst: &mut Vec<u8>, scratch: &mut BlurScratch) {
    if dst.len() != w * h {
        dst.clear();
        dst.resize(w * h, 0);
    }
    if w == 0 || h == 0 || src.len() < w * h {
        dst.fill(0);
        return;
    }
    let vrow = &mut scratch.row;
    vrow.clear();
    vrow.resize(w, 0);
    let [t0, t1, t2, t3, ..] = TAPS;
    for (y, drow) in dst.chunks_exact_mut(w).enumerate() {
        let r: [&[u8]; 7] = std::array::from_fn(|k| {
            let sy = reflect101(y as isize + k as isize - 3, h);
            &src[sy * w..sy * w + w]
        });
        let (r0, r1, r2, r3, r4, r5, r6) = (r[0], r[1], r[2], r[3], r[4], r[5], r[6]);
        let vrow = &mut vrow[..w];
        for i in 0..w {
            let v = 128
                + t0 * (r0[i] as u16 + r6[i] as u16)
                + t1 * (r1[i] as u16 + r5[i] as u16)
                + t2 * (r2[i] as u16 + r4[i] as u16)
                + t3 * r3[i] as u16;
            vrow[i] = (v >> 8) as u8;
        }
        if w >= 7 {
            let n = w - 6;
            let s: [&[u8]; 7] = std::array::from_fn(|k| &vrow[k..k + n]);
            let (s0, s1, s2, s3, s4, s5, s6) = (s[0], s[1], s[2], s[3], s[4], s[5], s[6]);
            let out = &mut drow[3..3 + n];
            for i in 0..n {
                let v = 128
                    + t0 * (s0[i] as u16 + s6[i] as u16)
                    + t1 * (s1[i] as u16 + s5[i] as u16)
                    + t2 * (s2[i] as u16 + s4[i] as u16)
                    + t3 * s3[i] as u16;
                out[i] = (v >> 8) as u8;
            }
            for x in (0..3).chain(w - 3..w) {
                drow[x] = ((128 + border_tap(vrow, x as isize, w)) >> 8) as u8;
            }
        } else {
            for x in 0..w {
                drow[x] = ((128 + border_tap(vrow, x as isize, w)) >> 8) as u8;
            }
        }
    }
}

fn border_tap(row: &[u8], x: isize, w: usize) -> u16 {
    TAPS.iter()
        .enumerate()
        .map(|(k, &tap)| tap * row[reflect101(x + k as isize - 3, w)] as u16)
        .sum()
}

/// The pattern as point lists, ready to rotate.
#[derive(Debug, Clone)]
pub struct Steerer {
    px: [i32; 512],
    py: [i32; 512],
}

impl Default for Steerer {
    fn default() -> Self {
        let mut px = [0i32; 512];
        let mut py = [0i32; 512];
        for (i, p) in ORB_PATTERN.iter().enumerate() {
            px[2 * i] = p[0] as i32;
            py[2 * i] = p[1] as i32;
            px[2 * i + 1] = p[2] as i32;
            py[2 * i + 1] = p[3] as i32;
        }
        Steerer { px, py }
    }
}

impl Steerer {
    /// Descriptor of the keypoint at `(x, y)` of the smoothed level `blur`
    /// (`w` wide), pattern rotated by `angle_deg`. The caller keeps the
    /// keypoint [`PATTERN_REACH`] pixels inside the level; tests that fall
    /// outside read 0.
    #[inline(always)]
    pub fn describe(
        &self,
        blur: &[u8],
        w: usize,
        x: usize,
        y: usize,
        angle_deg: f32,
    ) -> Descriptor {
        let (sin, cos) = angle_deg.to_radians().sin_cos();
        // Rotation in 16.16 fixed point; rounding half up, clamped to the reach
        // so every read below stays inside the window checked here.
        let ca = (cos * 65536.0).round() as i32;
        let sa = (sin * 65536.0).round() as i32;
        let reach = PATTERN_REACH as i32;
        let wi = w as i32;
        let mut offs = [0i32; 512];
        for i in 0..512 {
            let (px, py) = (self.px[i], self.py[i]);
            let u = ((px * ca - py * sa + 32768) >> 16).clamp(-reach, reach);
            let v = ((px * sa + py * ca + 32768) >> 16).clamp(-reach, reach);
            offs[i] = v * wi + u;
        }
        let mut vals = [0u8; 512];
        let r = PATTERN_REACH;
        if x >= r && y >= r && x + r < w && (y + r) * w + x + r < blur.len() {
            let centre = (y * w + x) as isize;
            for (v, &o) in vals.iter_mut().zip(&offs) {
                let idx = (centre + o as isize) as usize;
                // SAFETY: |u|, |v| <= r, so idx lies in
                // [(y - r) w + x - r, (y + r) w + x + r], inside `blur` (checked).
                *v = unsafe { *blur.get_unchecked(idx) };
            }
        } else {
            let centre = (y * w + x) as isize;
            for (v, &o) in vals.iter_mut().zip(&offs) {
                let idx = centre + o as isize;
                *v = usize::try_from(idx)
                    .ok()
                    .and_then(|i| blur.get(i))
                    .copied()
                    .unwrap_or(0);
            }
        }
        let mut d: Descriptor = [0; 4];
        for (word, chunk) in d.iter_mut().zip(vals.chunks_exact(128)) {
            let mut bits = 0u64;
            for (j, pair) in chunk.chunks_exact(2).enumerate() {
                bits |= ((pair[0] < pair[1]) as u64) << j;
            }
            *word = bits;
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blur_keeps_constants_and_mass() {
        let (w, h) = (23, 17);
        let src = vec![200u8; w * h];
        let (mut dst, mut tmp) = (Vec::new(), BlurScratch::default());
        gaussian_blur(&src, w, h, &mut dst, &mut tmp);
        assert!(dst.iter().all(|&v| v == 200));
        // An impulse spreads into the Gaussian's shape.
        let mut src = vec![0u8; w * h];
        src[8 * w + 11] = 255;
        gaussian_blur(&src, w, h, &mut dst, &mut tmp);
        let c = dst[8 * w + 11] as f32;
        let expect_c = 255.0 * (54.0 / 256.0f32).powi(2);
        assert!((c - expect_c).abs() <= 1.5, "{c} vs {expect_c}");
        assert!(dst[8 * w + 14] < dst[8 * w + 12]);
        assert_eq!(dst[8 * w + 15], 0);
        // Tiny images do not panic.
        gaussian_blur(&[1, 2, 3], 3, 1, &mut dst, &mut tmp);
        assert_eq!(dst.len(), 3);
    }

    #[test]
    fn reflect_indices() {
        assert_eq!(reflect101(-1, 5), 1);
        assert_eq!(reflect101(-3, 5), 3);
        assert_eq!(reflect101(5, 5), 3);
        assert_eq!(reflect101(7, 5), 1);
        assert_eq!(reflect101(-3, 2), 1);
    }

    #[test]
    fn pattern_reach_bounds_rotated_points() {
        let s = Steerer::default();
        for deg in 0..360 {
            let (b, a) = (deg as f32).to_radians().sin_cos();
            for i in 0..512 {
                let (px, py) = (s.px[i] as f32, s.py[i] as f32);
                let u = (px * a - py * b).round().abs();
                let v = (px * b + py * a).round().abs();
                assert!(u <= PATTERN_REACH as f32 && v <= PATTERN_REACH as f32);
            }
        }
    }
}
