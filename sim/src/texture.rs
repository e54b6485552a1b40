//! Procedural texture painting and mip-mapped texture sampling.
//!
//! Textures are square, power-of-two sized and wrap around (tile
//! seamlessly), so shapes painted across an edge continue on the other side
//! and the value-noise lattice has a period that divides the texture. The
//! world never lets one tile repeat inside a view that could alias: large
//! textures cover the whole scene and the small close-up detail layers are
//! combined at incommensurate scales and angles (see `world.rs`).
//!
//! Sampling is trilinear: the level of detail comes from the caller's
//! per-pixel footprint (how many level-0 texels one image pixel covers), so
//! minified textures are pre-filtered instead of aliasing.

/// A floating-point canvas used while generating a texture.
#[derive(Debug, Clone)]
pub struct Canvas {
    size: usize,
    data: Vec<f32>,
}

/// Fast floor for the f32 range used here (|x| < 2^31).
#[inline(always)]
pub(crate) fn fast_floor(x: f32) -> i32 {
    let i = x as i32;
    i - ((x < i as f32) as i32)
}

/// Integer part and fraction of `x` for bilinear weights, without the
/// saturating float-to-int cast: `x = i + f` with `f` in [0, 1] (a tie may
/// give `f = 1`, which bilinear interpolation tolerates). Exact for
/// |x| < 2^22; larger values give a wrong but harmless index.
#[inline(always)]
pub(crate) fn split_floor(x: f32) -> (i32, f32) {
    const MAGIC: f32 = 12_582_912.0; // 1.5 * 2^23: adding it rounds to an integer
    let t = (x - 0.5) + MAGIC;
    let i = (t.to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32);
    (i, x - (t - MAGIC))
}

/// Rounds to the nearest grey level in 0..=255 without a saturating cast
/// (NaN gives 0).
#[inline(always)]
pub(crate) fn round_u8(x: f32) -> u8 {
    const MAGIC: f32 = 12_582_912.0;
    let c = if x > 0.0 { x.min(255.0) } else { 0.0 };
    ((c + MAGIC).to_bits().wrapping_sub(MAGIC.to_bits()) & 0xff) as u8
}

/// Piecewise-linear approximation of log2 for positive finite `x`
/// (absolute error below 0.09), good enough to pick a mip level.
#[inline(always)]
pub(crate) fn fast_log2(x: f32) -> f32 {
    (x.to_bits() as f32) * (1.0 / 8_388_608.0) - 127.0
}

/// A 64-bit integer mix (splitmix64 finaliser).
#[inline(always)]
pub(crate) fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Hash of a lattice point to a value in [-1, 1].
#[inline(always)]
fn lattice(ix: u32, iy: u32, salt: u64) -> f32 {
    let h = mix64(salt ^ ((ix as u64) << 32 | iy as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    ((h >> 40) as f32) * (2.0 / 16_777_216.0) - 1.0
}

#[inline(always)]
fn fade(t: f32) -> f32 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

impl Canvas {
    /// A canvas of `size`² texels (rounded up to a power of two, at least 1) filled with `value`.
    pub fn new(size: usize, value: f32) -> Self {
        let size = size.max(1).next_power_of_two();
        Self {
            size,
            data: vec![value; size * size],
        }
    }

    /// Side length in texels.
    pub fn size(&self) -> usize {
        self.size
    }

    /// The texel values, row-major.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Mutable texel values, row-major.
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    /// Adds multi-octave value noise that tiles with the canvas.
    ///
    /// `cells` is the number of lattice cells across the canvas at the
    /// first octave; each further octave doubles it and multiplies the
    /// amplitude by `gain`. Octaves whose cells would be smaller than two
    /// texels are skipped.
    pub fn add_fbm(&mut self, cells: u32, octaves: u32, amplitude: f32, gain: f32, seed: u64) {
        let n = self.size;
        let mut amp = amplitude;
        let mut cells = cells.max(1) as usize;
        // Per column: lattice index and fade weight (the same on every row).
        let mut col_ix = vec![0usize; n];
        let mut col_t = vec![0.0f32; n];
        let mut top = Vec::new();
        let mut bottom = Vec::new();
        let mut row_vals = Vec::new();
        for octave in 0..octaves {
            if cells * 2 > n {
                break;
            }
            let salt = mix64(seed ^ (0x5bd1_e995u64.wrapping_mul(octave as u64 + 1)));
            let scale = cells as f32 / n as f32;
            for x in 0..n {
                let fx = (x as f32 + 0.5) * scale;
                let ix = (fx as usize).min(cells - 1);
                col_ix[x] = ix;
                col_t[x] = fade(fx - ix as f32);
            }
            let mut last_iy = usize::MAX;
            for y in 0..n {
                let fy = (y as f32 + 0.5) * scale;
                let iy = (fy as usize).min(cells - 1);
                let ty = fade(fy - iy as f32);
                if iy != last_iy {
                    // Lattice rows iy and iy+1, with the wrap column appended.
                    top.clear();
                    bottom.clear();
                    for ix in 0..=cells {
                        top.push(lattice((ix % cells) as u32, iy as u32, salt));
                        bottom.push(lattice(
                            (ix % cells) as u32,
                            ((iy + 1) % cells) as u32,
                            salt,
                        ));
                    }
                    last_iy = iy;
                }
                row_vals.clear();
                row_vals.extend(top.iter().zip(&bottom).map(|(a, b)| a + (b - a) * ty));
                let dst = &mut self.data[y * n..(y + 1) * n];
                for ((d, &ix), &tx) in dst.iter_mut().zip(&col_ix).zip(&col_t) {
                    let a = row_vals[ix];
                    let b = row_vals[ix + 1];
                    *d += amp * (a + (b - a) * tx);
                }
            }
            amp *= gain;
            cells *= 2;
        }
    }

    /// Multiplies every texel by `1 + amount * noise`, a grime/lighting
    /// variation that tiles with the canvas.
    pub fn modulate_fbm(&mut self, cells: u32, octaves: u32, amount: f32, seed: u64) {
        let mut noise = Canvas::new(self.size, 0.0);
        noise.add_fbm(cells, octaves, 1.0, 0.5, seed);
        for (d, m) in self.data.iter_mut().zip(&noise.data) {
            *d *= 1.0 + amount * m;
        }
    }

    /// Blends `value` into the texels covered by a shape whose support
    /// lies within `half_extent` (x, y) of `centre`; `coverage(dx, dy)`
    /// (texel-centre offsets from `centre`, unwrapped) returns the covered
    /// fraction in [0, 1].
    fn paint<F: Fn(f32, f32) -> f32>(
        &mut self,
        centre: (f32, f32),
        half_extent: (f32, f32),
        value: f32,
        alpha: f32,
        coverage: F,
    ) {
        let n = self.size as i32;
        let mask = n - 1;
        let x0 = fast_floor(centre.0 - half_extent.0 - 1.0);
        let x1 = fast_floor(centre.0 + half_extent.0 + 1.0) + 1;
        let y0 = fast_floor(centre.1 - half_extent.1 - 1.0);
        let y1 = fast_floor(centre.1 + half_extent.1 + 1.0) + 1;
        // Shapes larger than the canvas are clipped to one period.
        let x1 = x1.min(x0 + n);
        let y1 = y1.min(y0 + n);
        for y in y0..y1 {
            let row = ((y & mask) * n) as usize;
            let dy = y as f32 + 0.5 - centre.1;
            for x in x0..x1 {
                let dx = x as f32 + 0.5 - centre.0;
                let c = coverage(dx, dy);
                if c > 0.0 {
                    let d = &mut self.data[row + (x & mask) as usize];
                    *d += (value - *d) * (c * alpha);
                }
            }
        }
    }

    /// Paints a rotated rectangle (texel units) with a one-texel anti-aliased edge.
    pub fn rect(
        &mut self,
        centre: (f32, f32),
        half: (f32, f32),
        angle: f32,
        value: f32,
        alpha: f32,
    ) {
        let (s, c) = angle.sin_cos();
        let ext = (
            (c * half.0).abs() + (s * half.1).abs(),
            (s * half.0).abs() + (c * half.1).abs(),
        );
        self.paint(centre, ext, value, alpha, |dx, dy| {
            let lx = (c * dx + s * dy).abs();
            let ly = (-s * dx + c * dy).abs();
            let cx = (0.5 + half.0 - lx).clamp(0.0, 1.0);
            let cy = (0.5 + half.1 - ly).clamp(0.0, 1.0);
            cx * cy
        });
    }

    /// Paints a disc (texel units) with an anti-aliased edge.
    pub fn disc(&mut self, centre: (f32, f32), radius: f32, value: f32, alpha: f32) {
        self.paint(centre, (radius, radius), value, alpha, |dx, dy| {
            (0.5 + radius - (dx * dx + dy * dy).sqrt()).clamp(0.0, 1.0)
        });
    }

    /// Paints a ring (texel units): a disc outline of width `width`.
    pub fn ring(&mut self, centre: (f32, f32), radius: f32, width: f32, value: f32, alpha: f32) {
        let r = radius + width;
        self.paint(centre, (r, r), value, alpha, |dx, dy| {
            let d = ((dx * dx + dy * dy).sqrt() - radius).abs();
            (0.5 + 0.5 * width - d).clamp(0.0, 1.0)
        });
    }

    /// Paints a line segment of width `width` (texel units) with round caps.
    pub fn line(&mut self, a: (f32, f32), b: (f32, f32), width: f32, value: f32, alpha: f32) {
        let centre = ((a.0 + b.0) * 0.5, (a.1 + b.1) * 0.5);
        let (hx, hy) = ((b.0 - a.0) * 0.5, (b.1 - a.1) * 0.5);
        let len2 = (hx * hx + hy * hy).max(1e-12);
        let ext = (hx.abs() + width, hy.abs() + width);
        self.paint(centre, ext, value, alpha, |dx, dy| {
            let t = ((dx * hx + dy * hy) / len2).clamp(-1.0, 1.0);
            let ex = dx - t * hx;
            let ey = dy - t * hy;
            (0.5 + 0.5 * width - (ex * ex + ey * ey).sqrt()).clamp(0.0, 1.0)
        });
    }

    /// Builds the mip chain of this canvas, clamping values to 0..=255.
    pub fn into_mip(self) -> MipTexture {
        MipTexture::from_canvas(&self)
    }
}

/// One level of a mip chain, row-major.
#[derive(Debug, Clone)]
struct Level {
    size: usize,
    mask: i32,
    /// log2 of `size`.
    shift: u32,
    data: Vec<u8>,
}

impl Level {
    fn from_linear(size: usize, linear: &[f32]) -> Level {
        Level {
            size,
            mask: size as i32 - 1,
            shift: size.trailing_zeros(),
            data: linear.iter().map(|v| (v + 0.5) as u8).collect(),
        }
    }

    #[inline(always)]
    fn addr(&self, x: usize, y: usize) -> usize {
        (y << self.shift) | x
    }
}

/// A square, wrapping, mip-mapped 8-bit texture.
#[derive(Debug, Clone)]
pub struct MipTexture {
    levels: Vec<Level>,
    mean: f32,
}

impl MipTexture {
    /// Builds the mip chain (2x2 box filter) of a canvas.
    pub fn from_canvas(canvas: &Canvas) -> Self {
        let mut size = canvas.size;
        let mut current: Vec<f32> = canvas.data.iter().map(|v| v.clamp(0.0, 255.0)).collect();
        let mut levels = Vec::new();
        loop {
            levels.push(Level::from_linear(size, &current));
            if size == 1 {
                break;
            }
            let half = size / 2;
            let mut next = vec![0.0f32; half * half];
            for y in 0..half {
                for x in 0..half {
                    let i = 2 * y * size + 2 * x;
                    next[y * half + x] = 0.25
                        * (current[i] + current[i + 1] + current[i + size] + current[i + size + 1]);
                }
            }
            current = next;
            size = half;
        }
        let mean = current.first().copied().unwrap_or(0.0);
        Self { levels, mean }
    }

    /// Side length of level 0 in texels.
    pub fn size(&self) -> usize {
        self.levels.first().map_or(0, |l| l.size)
    }

    /// The mean value (the 1x1 level, before 8-bit rounding).
    pub fn mean(&self) -> f32 {
        self.mean
    }

    /// Number of mip levels.
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Level 0 texel at integer coordinates (wrapping).
    pub fn texel(&self, x: i32, y: i32) -> u8 {
        match self.levels.first() {
            Some(l) => l.data[l.addr((x & l.mask) as usize, (y & l.mask) as usize)],
            None => 0,
        }
    }

    #[inline(always)]
    fn bilinear(level: &Level, u: f32, v: f32) -> f32 {
        let (x0, fx) = split_floor(u - 0.5);
        let (y0, fy) = split_floor(v - 0.5);
        let m = level.mask;
        let xa = (x0 & m) as usize;
        let xb = ((x0 + 1) & m) as usize;
        let ya = ((y0 & m) as usize) << level.shift;
        let yb = (((y0 + 1) & m) as usize) << level.shift;
        let d = &level.data;
        let a = d[ya | xa] as f32;
        let b = d[ya | xb] as f32;
        let c = d[yb | xa] as f32;
        let e = d[yb | xb] as f32;
        let top = a + (b - a) * fx;
        let bottom = c + (e - c) * fx;
        top + (bottom - top) * fy
    }

    /// Clamps a level of detail (log2 of the footprint in level-0 texels)
    /// to the chain; `None` when only the mean remains.
    #[inline(always)]
    pub fn lod_from(&self, lod: f32) -> Option<f32> {
        let lod = if lod > 0.0 { lod } else { 0.0 };
        if lod >= (self.levels.len() - 1) as f32 {
            None
        } else {
            Some(lod)
        }
    }

    /// Level 0 as a float canvas, to paint on and rebuild the chain.
    pub fn level0_canvas(&self) -> Canvas {
        match self.levels.first() {
            Some(l) => Canvas {
                size: l.size,
                data: (0..l.size * l.size)
                    .map(|i| l.data[l.addr(i % l.size, i / l.size)] as f32)
                    .collect(),
            },
            None => Canvas::new(1, self.mean),
        }
    }

    /// The level of detail (fractional mip level) for a footprint of
    /// `footprint` level-0 texels per pixel; `None` when it is so coarse
    /// that only the mean remains.
    #[inline(always)]
    pub fn lod(&self, footprint: f32) -> Option<f32> {
        let lod = if footprint > 1.0 {
            fast_log2(footprint)
        } else {
            0.0
        };
        if lod >= (self.levels.len() - 1) as f32 {
            None
        } else {
            Some(lod)
        }
    }

    /// Trilinear sample at level-0 texel coordinates `(u, v)` (texel `i`
    /// covers `[i, i+1)`) for a footprint of `footprint` level-0 texels.
    #[inline(always)]
    pub fn sample(&self, u: f32, v: f32, footprint: f32) -> f32 {
        match self.lod(footprint) {
            None => self.mean,
            Some(lod) => self.sample_lod(u, v, lod),
        }
    }

    /// Trilinear sample at an explicit level of detail (see [`Self::lod`]),
    /// with a narrowed blend band ("brilinear"): within [`BLEND_MARGIN`] of
    /// a level only that level is read, in between the two levels are
    /// blended with a weight that still runs continuously from 0 to 1, so
    /// there is no popping and about half the pixels need one bilinear
    /// lookup instead of two.
    #[inline(always)]
    pub fn sample_lod(&self, u: f32, v: f32, lod: f32) -> f32 {
        // A negative level (only for lod < 0, which callers clamp away)
        // becomes a huge index and reads as the mean.
        let (l, f) = split_floor(lod);
        let l = l as usize;
        let (Some(a), Some(b)) = (self.levels.get(l), self.levels.get(l + 1)) else {
            return self.mean;
        };
        // 2^-l, exactly, without a division.
        let sa = f32::from_bits((127 - (l as u32 & 63)) << 23);
        if f <= BLEND_MARGIN {
            return Self::bilinear(a, u * sa, v * sa);
        }
        if f >= 1.0 - BLEND_MARGIN {
            return Self::bilinear(b, u * sa * 0.5, v * sa * 0.5);
        }
        let w = (f - BLEND_MARGIN) * (1.0 / (1.0 - 2.0 * BLEND_MARGIN));
        let va = Self::bilinear(a, u * sa, v * sa);
        let vb = Self::bilinear(b, u * sa * 0.5, v * sa * 0.5);
        va + (vb - va) * w
    }
}

/// Fraction of a mip level at each end where [`MipTexture::sample_lod`]
/// reads a single level.
pub const BLEND_MARGIN: f32 = 0.25;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_u8_rounds_and_clamps() {
        assert_eq!(round_u8(-3.0), 0);
        assert_eq!(round_u8(f32::NAN), 0);
        assert_eq!(round_u8(0.4), 0);
        assert_eq!(round_u8(0.6), 1);
        assert_eq!(round_u8(127.49), 127);
        assert_eq!(round_u8(254.7), 255);
        assert_eq!(round_u8(1e9), 255);
        for i in 0..=255u8 {
            assert_eq!(round_u8(i as f32 + 0.3), i);
        }
    }

    #[test]
    fn split_floor_splits() {
        for &x in &[
            -3.7f32,
            -1.0,
            -0.2,
            0.0,
            0.3,
            1.0,
            2.5,
            5.999,
            1234.5,
            -100_000.25,
            4_000_000.5,
        ] {
            let (i, f) = split_floor(x);
            assert!((0.0..=1.0).contains(&f), "{x}: {f}");
            assert!(
                (i as f64 + f as f64 - x as f64).abs() < 1e-3,
                "{x}: {i} {f}"
            );
        }
    }

    #[test]
    fn fast_math_is_close() {
        for &x in &[-3.7f32, -1.0, -0.2, 0.0, 0.3, 1.0, 5.999, 1234.5] {
            assert_eq!(fast_floor(x), x.floor() as i32, "{x}");
        }
        for &x in &[1.0f32, 1.5, 2.0, 3.0, 10.0, 1000.0, 0.25] {
            assert!((fast_log2(x) - x.log2()).abs() < 0.09, "{x}");
        }
    }

    #[test]
    fn mip_chain_preserves_the_mean_and_sampling_interpolates() {
        let mut c = Canvas::new(64, 100.0);
        c.add_fbm(4, 4, 40.0, 0.5, 7);
        let expected: f32 =
            c.data().iter().map(|v| v.clamp(0.0, 255.0)).sum::<f32>() / (64.0 * 64.0);
        let t = c.into_mip();
        assert_eq!(t.level_count(), 7);
        assert!((t.mean() - expected).abs() < 0.01);
        // At a texel centre with a sub-texel footprint, sampling returns the texel.
        let v = t.sample(10.5, 20.5, 0.5);
        assert!((v - t.texel(10, 20) as f32).abs() < 1e-3);
        // Half way between two texels, the average.
        let mid = t.sample(11.0, 20.5, 0.5);
        let avg = 0.5 * (t.texel(10, 20) as f32 + t.texel(11, 20) as f32);
        assert!((mid - avg).abs() < 1e-3);
        // Wrapping: one period away is the same value.
        assert!((t.sample(10.5 + 64.0, 20.5 - 128.0, 0.5) - v).abs() < 1e-3);
        // A huge footprint gives the mean.
        assert_eq!(t.sample(3.0, 3.0, 1e6), t.mean());
    }

    #[test]
    fn minification_filters_a_checkerboard_to_its_mean() {
        let mut c = Canvas::new(256, 0.0);
        for y in 0..256 {
            for x in 0..256 {
                c.data_mut()[y * 256 + x] = if (x + y) % 2 == 0 { 255.0 } else { 0.0 };
            }
        }
        let t = c.into_mip();
        // With a 4-texel footprint the one-texel checkerboard is averaged away.
        for i in 0..20 {
            let v = t.sample(17.3 + i as f32 * 3.1, 40.7 + i as f32 * 1.7, 4.0);
            assert!((v - 127.5).abs() < 1.0, "{v}");
        }
    }

    #[test]
    fn fbm_tiles_seamlessly() {
        let mut c = Canvas::new(128, 0.0);
        c.add_fbm(8, 3, 50.0, 0.5, 3);
        let n = 128;
        // The jump across the wrap edge is like the jump between neighbours inside.
        let edge: f32 = (0..n)
            .map(|y| (c.data()[y * n] - c.data()[y * n + n - 1]).abs())
            .sum::<f32>()
            / n as f32;
        let inner: f32 = (0..n)
            .map(|y| (c.data()[y * n + 60] - c.data()[y * n + 61]).abs())
            .sum::<f32>()
            / n as f32;
        assert!(edge < 3.0 * inner + 0.5, "edge {edge} inner {inner}");
    }

    #[test]
    fn shapes_paint_with_coverage() {
        let mut c = Canvas::new(64, 0.0);
        c.rect((32.0, 32.0), (10.0, 5.0), 0.0, 200.0, 1.0);
        assert_eq!(c.data()[32 * 64 + 32], 200.0);
        assert_eq!(c.data()[32 * 64 + 50], 0.0);
        c.disc((10.0, 10.0), 4.0, 100.0, 0.5);
        assert!((c.data()[10 * 64 + 10] - 50.0).abs() < 1e-4);
        c.line((0.0, 60.0), (63.0, 60.0), 2.0, 80.0, 1.0);
        assert!((c.data()[59 * 64 + 30] - 80.0).abs() < 1e-4);
    }
}
