//! Contrast normalisation of a shot before ORB ([`LocalizeParams::query_contrast`]):
//! contrast-limited adaptive histogram equalisation (CLAHE, Zuiderveld
//! 1994, as OpenCV's `createCLAHE`). A photo taken under another sun has
//! the same corners at other contrasts (a face in shadow is dimmer and
//! flatter); FAST's fixed thresholds then find them in some places and
//! not in others. CLAHE equalises each tile's grey levels (its histogram
//! clipped, so noise in flat tiles is not stretched into corners) and
//! blends the tiles' mappings bilinearly. The mapping is monotonic at
//! every pixel, so ORB's binary tests (grey-level comparisons within a
//! patch) keep their outcome wherever the mapping varies little across
//! the patch.
//!
//! Written here rather than taken from a crate: the pure-Rust CLAHE crates
//! found are colour-only or panic on some tile sizes, and this is the
//! textbook algorithm in a page.
//!
//! [`LocalizeParams::query_contrast`]: super::LocalizeParams::query_contrast

use image::GrayImage;

/// CLAHE settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Clahe {
    /// Tiles along each side of the image (the grid is `tiles` x `tiles`).
    pub tiles: u32,
    /// Clip limit: the largest histogram bin, as a multiple of the tile's
    /// mean bin count (OpenCV's `clipLimit`); the excess is spread evenly
    /// over all bins.
    pub clip_limit: f64,
}

impl Default for Clahe {
    fn default() -> Self {
        Clahe {
            tiles: 8,
            clip_limit: 2.0,
        }
    }
}

/// `img` equalised by CLAHE. A blank image, or `tiles` 0, is returned as it
/// is.
pub fn clahe(img: &GrayImage, p: &Clahe) -> GrayImage {
    let (w, h) = img.dimensions();
    if w == 0 || h == 0 || p.tiles == 0 || !p.clip_limit.is_finite() {
        return img.clone();
    }
    let (w, h) = (w as usize, h as usize);
    let nx = (p.tiles as usize).min(w);
    let ny = (p.tiles as usize).min(h);
    let src = img.as_raw();
    // Each tile's mapping of the 256 grey levels.
    let mut luts = vec![[0u8; 256]; nx * ny];
    for ty in 0..ny {
        let (y0, y1) = (ty * h / ny, (ty + 1) * h / ny);
        for tx in 0..nx {
            let (x0, x1) = (tx * w / nx, (tx + 1) * w / nx);
            let mut hist = [0u32; 256];
            for y in y0..y1 {
                for &v in &src[y * w + x0..y * w + x1] {
                    hist[v as usize] += 1;
                }
            }
            let n = ((x1 - x0) * (y1 - y0)) as u32;
            if n == 0 {
                continue;
            }
            let limit = ((p.clip_limit * f64::from(n) / 256.0) as u32).max(1);
            let mut excess = 0u32;
            for b in hist.iter_mut() {
                if *b > limit {
                    excess += *b - limit;
                    *b = limit;
                }
            }
            let (add, rest) = (excess / 256, (excess % 256) as usize);
            let lut = &mut luts[ty * nx + tx];
            let mut cum = 0u32;
            for (i, b) in hist.iter().enumerate() {
                cum += b + add + u32::from(i < rest);
                lut[i] = ((f64::from(cum) * 255.0 / f64::from(n)).round()).min(255.0) as u8;
            }
        }
    }
    // Bilinear blend of the four nearest tiles' mappings (tile centres at
    // the tiles' middles; clamped at the borders).
    let cell = |i: usize, n: usize, len: usize| -> (usize, usize, f32) {
        let f = ((i as f32 + 0.5) * n as f32 / len as f32 - 0.5).max(0.0);
        let a = (f.floor() as usize).min(n - 1);
        let b = (a + 1).min(n - 1);
        (a, b, (f - a as f32).clamp(0.0, 1.0))
    };
    let cols: Vec<(usize, usize, f32)> = (0..w).map(|x| cell(x, nx, w)).collect();
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        let (ya, yb, wy) = cell(y, ny, h);
        for (x, &(xa, xb, wx)) in cols.iter().enumerate() {
            let v = src[y * w + x] as usize;
            let m = |ty: usize, tx: usize| f32::from(luts[ty * nx + tx][v]);
            let top = m(ya, xa) * (1.0 - wx) + m(ya, xb) * wx;
            let bottom = m(yb, xa) * (1.0 - wx) + m(yb, xb) * wx;
            out[y * w + x] = (top * (1.0 - wy) + bottom * wy).round().clamp(0.0, 255.0) as u8;
        }
    }
    GrayImage::from_raw(w as u32, h as u32, out).unwrap_or_else(|| img.clone())
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Luma;

    #[test]
    fn a_dim_half_gets_the_contrast_of_the_bright_half_and_the_order_of_grey_levels_is_kept() {
        // Left half: a pattern of amplitude 8 around 40 (a face in shadow);
        // right half: the same pattern with amplitude 64 around 128.
        let img = GrayImage::from_fn(256, 128, |x, y| {
            let t = ((x * 7 + y * 13) % 17) as f64 / 16.0 - 0.5;
            Luma([if x < 128 {
                (40.0 + 16.0 * t).round() as u8
            } else {
                (128.0 + 128.0 * t).round() as u8
            }])
        });
        let eq = clahe(
            &img,
            &Clahe {
                tiles: 4,
                clip_limit: 8.0,
            },
        );
        let spread = |im: &GrayImage, x0: u32, x1: u32| {
            let v: Vec<u8> = (0..128)
                .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                .map(|(x, y)| im.get_pixel(x, y)[0])
                .collect();
            f64::from(*v.iter().max().unwrap_or(&0)) - f64::from(*v.iter().min().unwrap_or(&0))
        };
        // Away from the blend zone between the halves.
        let (dim_before, dim_after) = (spread(&img, 0, 48), spread(&eq, 0, 48));
        let bright_after = spread(&eq, 208, 256);
        assert!(dim_before <= 16.0, "{dim_before}");
        assert!(
            dim_after >= 0.6 * bright_after && dim_after >= 4.0 * dim_before,
            "dim half {dim_before} -> {dim_after}, bright half {bright_after}"
        );
        // Monotonic: where one tile's mapping alone applies (the corner
        // up to its tile's centre), a brighter source pixel never maps
        // darker than a dimmer one.
        let corner: Vec<(u8, u8)> = (0..16)
            .flat_map(|y| (0..32).map(move |x| (x, y)))
            .map(|(x, y)| (img.get_pixel(x, y)[0], eq.get_pixel(x, y)[0]))
            .collect();
        for &(a, ea) in &corner {
            for &(b, eb) in &corner {
                assert!(a >= b || ea <= eb, "{a}->{ea} but {b}->{eb}");
            }
        }
    }

    #[test]
    fn odd_sizes_blank_and_flat_images_never_panic() {
        for (w, h) in [(1, 1), (3, 200), (641, 479), (7, 5)] {
            let img = GrayImage::from_fn(w, h, |x, y| Luma([((x * 31 + y * 7) % 256) as u8]));
            let eq = clahe(&img, &Clahe::default());
            assert_eq!(eq.dimensions(), (w, h));
        }
        let flat = GrayImage::from_pixel(64, 64, Luma([90]));
        let eq = clahe(&flat, &Clahe::default());
        // One grey level stays one grey level.
        let v0 = eq.get_pixel(0, 0)[0];
        assert!(eq.pixels().all(|p| p[0] == v0));
        assert_eq!(
            clahe(&GrayImage::new(0, 0), &Clahe::default()).dimensions(),
            (0, 0)
        );
    }
}
