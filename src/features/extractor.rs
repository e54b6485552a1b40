//! [`OrbExtractor`]: ORB-SLAM's extractor, level by level.

use image::GrayImage;
use nalgebra::Point2;

use super::brief::{BlurScratch, Steerer, gaussian_blur};
use super::fast::{Corner, FastScratch, Rect, detect};
use super::noise::estimate_noise_sigma_masked;
use super::orientation::Disc;
use super::pyramid::{ResizeScratch, level_size, level_to_level0, resize_bilinear};
use super::quadtree::{QuadScratch, distribute};
use super::{Descriptor, FeatureError, Features, KeyPoint, Params};
use crate::camera::Camera;

/// Buffers of one pyramid level, reused from frame to frame.
#[derive(Debug, Default, Clone)]
struct Level {
    w: usize,
    h: usize,
    image: Vec<u8>,
    blur: Vec<u8>,
    blur_scratch: BlurScratch,
    fast: FastScratch,
    corners: Vec<Corner>,
    cell_counts: Vec<u32>,
    quad: QuadScratch,
    selected: Vec<u32>,
    selected2: Vec<u32>,
    keypoints: Vec<KeyPoint>,
    descriptors: Vec<Descriptor>,
}

/// What every level's work reads.
struct Shared<'a> {
    params: &'a Params,
    disc: &'a Disc,
    steerer: &'a Steerer,
    w0: usize,
    h0: usize,
    camera: Option<&'a Camera>,
    mask: Option<&'a [u8]>,
    /// Fallback FAST threshold for this image.
    low_threshold: u8,
}

/// ORB extractor with ORB-SLAM's detection, distribution and description.
///
/// Holds every buffer between frames: after the first frame of a given size,
/// extraction allocates only the returned [`Features`] (none with
/// [`OrbExtractor::extract_into`]).
#[derive(Debug, Clone)]
pub struct OrbExtractor {
    params: Params,
    scale_factors: Vec<f32>,
    inv_scale_factors: Vec<f32>,
    level_sigma2: Vec<f32>,
    inv_level_sigma2: Vec<f32>,
    features_per_level: Vec<usize>,
    disc: Disc,
    steerer: Steerer,
    levels: Vec<Level>,
    resize: ResizeScratch,
}

impl OrbExtractor {
    /// An extractor for `params` (checked with [`Params::validate`]).
    pub fn new(params: Params) -> Result<Self, FeatureError> {
        params.validate()?;
        let n = params.n_levels;
        let s = params.scale_factor;
        let scale_factors: Vec<f32> = (0..n).map(|l| s.powi(l as i32)).collect();
        let inv_scale_factors = scale_factors.iter().map(|v| 1.0 / v).collect();
        let level_sigma2: Vec<f32> = scale_factors.iter().map(|v| v * v).collect();
        let inv_level_sigma2 = level_sigma2.iter().map(|v| 1.0 / v).collect();
        Ok(OrbExtractor {
            features_per_level: features_per_level(
                params.n_features,
                n,
                s,
                params.level_weight_exponent,
            ),
            params,
            scale_factors,
            inv_scale_factors,
            level_sigma2,
            inv_level_sigma2,
            disc: Disc::new(params.patch_size / 2),
            steerer: Steerer::default(),
            levels: vec![Level::default(); n],
            resize: ResizeScratch::default(),
        })
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Number of pyramid levels.
    pub fn n_levels(&self) -> usize {
        self.params.n_levels
    }

    /// `scale_factor^level` for every level.
    pub fn scale_factors(&self) -> &[f32] {
        &self.scale_factors
    }

    /// `1 / scale_factor^level` for every level.
    pub fn inv_scale_factors(&self) -> &[f32] {
        &self.inv_scale_factors
    }

    /// Variance factor of a keypoint's position per level, `scale^(2 level)`.
    pub fn level_sigma2(&self) -> &[f32] {
        &self.level_sigma2
    }

    /// Inverse of [`OrbExtractor::level_sigma2`].
    pub fn inv_level_sigma2(&self) -> &[f32] {
        &self.inv_level_sigma2
    }

    /// Features wanted on each level.
    pub fn features_per_level(&self) -> &[usize] {
        &self.features_per_level
    }

    /// Extract keypoints and descriptors from `img`. With a camera, `ux, uy`
    /// are the undistorted positions. Images too small for the border margins
    /// give no features.
    pub fn extract(&mut self, img: &GrayImage, camera: Option<&Camera>) -> Features {
        let mut out = Features::default();
        self.run(img, None, camera, &mut out);
        out
    }

    /// [`OrbExtractor::extract`] ignoring every pixel whose `mask` value is 0:
    /// no keypoint is kept whose patch (in level-0 pixels) reaches a masked
    /// pixel, so black fill around a warped image never yields a feature.
    pub fn extract_masked(
        &mut self,
        img: &GrayImage,
        mask: &GrayImage,
        camera: Option<&Camera>,
    ) -> Result<Features, FeatureError> {
        let mut out = Features::default();
        self.extract_into(img, Some(mask), camera, &mut out)?;
        Ok(out)
    }

    /// Extract into `out` (cleared first), reusing its storage.
    pub fn extract_into(
        &mut self,
        img: &GrayImage,
        mask: Option<&GrayImage>,
        camera: Option<&Camera>,
        out: &mut Features,
    ) -> Result<(), FeatureError> {
        if let Some(m) = mask
            && m.dimensions() != img.dimensions()
        {
            return Err(FeatureError::MaskSize {
                width: img.width(),
                height: img.height(),
                mask_width: m.width(),
                mask_height: m.height(),
            });
        }
        self.run(img, mask.map(|m| m.as_raw().as_slice()), camera, out);
        Ok(())
    }

    fn run(
        &mut self,
        img: &GrayImage,
        mask: Option<&[u8]>,
        camera: Option<&Camera>,
        out: &mut Features,
    ) {
        out.keypoints.clear();
        out.descriptors.clear();
        let (w0, h0) = (img.width() as usize, img.height() as usize);
        self.build_pyramid(img.as_raw(), w0, h0);
        let low_threshold = if self.params.noise_threshold_factor > 0.0 {
            let sigma = estimate_noise_sigma_masked(img.as_raw(), mask, w0, h0, 3, 6);
            let t = (self.params.noise_threshold_factor * sigma).round();
            (t.clamp(0.0, 255.0) as u8).clamp(self.params.min_th_fast, self.params.ini_th_fast)
        } else {
            self.params.min_th_fast
        };
        let shared = Shared {
            low_threshold,
            params: &self.params,
            disc: &self.disc,
            steerer: &self.steerer,
            w0,
            h0,
            camera,
            mask,
        };
        let quotas = &self.features_per_level;
        if self.params.threads >= 2 && self.levels.len() > 1 {
            // Longest-processing-time split of the levels by area.
            let mut load = [0usize; 2];
            let mut groups: [Vec<(usize, &mut Level)>; 2] = [Vec::new(), Vec::new()];
            for (l, level) in self.levels.iter_mut().enumerate() {
                let g = if load[0] <= load[1] { 0 } else { 1 };
                load[g] += level.w * level.h;
                groups[g].push((l, level));
            }
            let [mut a, mut b] = groups;
            std::thread::scope(|scope| {
                let shared = &shared;
                scope.spawn(move || {
                    for (l, level) in b.iter_mut() {
                        process_level(level, *l, quotas[*l], shared);
                    }
                });
                for (l, level) in a.iter_mut() {
                    process_level(level, *l, quotas[*l], shared);
                }
            });
        } else {
            for (l, level) in self.levels.iter_mut().enumerate() {
                process_level(level, l, quotas[l], &shared);
            }
        }
        let total: usize = self.levels.iter().map(|l| l.keypoints.len()).sum();
        out.keypoints.reserve(total);
        out.descriptors.reserve(total);
        for level in &self.levels {
            out.keypoints.extend_from_slice(&level.keypoints);
            out.descriptors.extend_from_slice(&level.descriptors);
        }
    }

    fn build_pyramid(&mut self, raw: &[u8], w0: usize, h0: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2, checked just above.
                unsafe { self.build_pyramid_avx2(raw, w0, h0) };
                return;
            }
        }
        self.build_pyramid_impl(raw, w0, h0)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn build_pyramid_avx2(&mut self, raw: &[u8], w0: usize, h0: usize) {
        self.build_pyramid_impl(raw, w0, h0)
    }

    #[inline(always)]
    fn build_pyramid_impl(&mut self, raw: &[u8], w0: usize, h0: usize) {
        let s = self.params.scale_factor;
        for l in 0..self.levels.len() {
            let (w, h) = level_size(w0, h0, s, l);
            if l == 0 {
                let level = &mut self.levels[0];
                level.w = w0;
                level.h = h0;
                level.image.clear();
                level
                    .image
                    .extend_from_slice(&raw[..(w0 * h0).min(raw.len())]);
                level.image.resize(w0 * h0, 0);
                continue;
            }
            let (prev, rest) = self.levels.split_at_mut(l);
            let src = &prev[l - 1];
            let dst = &mut rest[0];
            dst.w = w;
            dst.h = h;
            resize_bilinear(
                &src.image,
                src.w,
                src.h,
                &mut dst.image,
                w,
                h,
                &mut self.resize,
            );
        }
    }
}

/// ORB-SLAM's share of features per level: geometric with ratio
/// `scale^-exponent`, the last level taking what is left.
fn features_per_level(n: usize, levels: usize, scale: f32, exponent: f32) -> Vec<usize> {
    let factor = (1.0 / scale as f64).powf(exponent as f64);
    let mut per = if (1.0 - factor).abs() < 1e-9 {
        n as f64 / levels as f64
    } else {
        n as f64 * (1.0 - factor) / (1.0 - factor.powi(levels as i32))
    };
    let mut out = Vec::with_capacity(levels);
    let mut sum = 0usize;
    for _ in 0..levels.saturating_sub(1) {
        let k = per.round() as usize;
        out.push(k);
        sum += k;
        per *= factor;
    }
    out.push(n.saturating_sub(sum));
    out
}

/// True when no mask pixel under the patch of a corner at level-0 position
/// `(x, y)` with radius `r` (level-0 pixels) is 0: every pixel of the
/// patch's vertical and horizontal diameters (a band of masked rows or
/// columns anywhere under the patch is seen; the damage of a lost video
/// packet is whole rows) and 8 points on its circle.
fn patch_unmasked(mask: &[u8], w0: usize, h0: usize, x: f32, y: f32, r: f32) -> bool {
    let at = |px: f32, py: f32| unmasked_at(mask, w0, h0, px, py);
    let steps = r.ceil() as i32;
    let diameters = (-steps..=steps).all(|k| {
        let d = (k as f32).clamp(-r, r);
        at(x, y + d) && at(x + d, y)
    });
    diameters && circle_unmasked(mask, w0, h0, x, y, r)
}

/// The centre and 8 points on the circle of radius `r` about `(x, y)`
/// unmasked (and inside the image).
fn circle_unmasked(mask: &[u8], w0: usize, h0: usize, x: f32, y: f32, r: f32) -> bool {
    const D: f32 = std::f32::consts::FRAC_1_SQRT_2;
    const DIRS: [(f32, f32); 9] = [
        (0.0, 0.0),
        (1.0, 0.0),
        (D, D),
        (0.0, 1.0),
        (-D, D),
        (-1.0, 0.0),
        (-D, -D),
        (0.0, -1.0),
        (D, -D),
    ];
    DIRS.iter()
        .all(|&(dx, dy)| unmasked_at(mask, w0, h0, x + dx * r, y + dy * r))
}

/// The mask's pixel nearest `(px, py)` is inside the image and not 0.
fn unmasked_at(mask: &[u8], w0: usize, h0: usize, px: f32, py: f32) -> bool {
    let (px, py) = (px.round(), py.round());
    px >= 0.0
        && py >= 0.0
        && px < w0 as f32
        && py < h0 as f32
        && mask
            .get(py as usize * w0 + px as usize)
            .is_some_and(|&m| m != 0)
}

/// How far, in level-0 pixels, a pixel of the level at `scale` reaches back
/// through the pyramid's bilinear resizes (each by `factor`): one source
/// pixel of each level below it, `1 + factor + ... + factor^(l-1)` for
/// `scale = factor^l` (0 at level 0).
fn resample_reach(scale: f32, factor: f32) -> f32 {
    if scale <= 1.0 || factor <= 1.0 {
        return 0.0;
    }
    (scale - 1.0) / (factor - 1.0)
}

/// The detection cells of a level.
struct CellGrid {
    area: Rect,
    n_cols: usize,
    n_rows: usize,
    cw: usize,
    ch: usize,
}

/// Detect with the fallback threshold in the cells where the first found
/// nothing (`level.cell_counts`), appending to `level.corners`. Horizontal
/// runs of empty cells are scanned as one rectangle: the same corners, fewer
/// partial SIMD chunks and row set-ups.
#[inline(always)]
fn detect_fallback(level: &mut Level, g: &CellGrid, threshold: u8) {
    let (w, h) = (level.w, level.h);
    for j in 0..g.n_rows {
        let mut i = 0;
        while i < g.n_cols {
            if level.cell_counts[j * g.n_cols + i] != 0 {
                i += 1;
                continue;
            }
            let first = i;
            while i < g.n_cols && level.cell_counts[j * g.n_cols + i] == 0 {
                i += 1;
            }
            let run = Rect {
                x0: g.area.x0 + first * g.cw,
                y0: g.area.y0 + j * g.ch,
                x1: (g.area.x0 + i * g.cw).min(g.area.x1),
                y1: (g.area.y0 + (j + 1) * g.ch).min(g.area.y1),
            };
            detect(
                &level.image,
                w,
                h,
                run,
                threshold,
                &mut level.fast,
                &mut level.corners,
            );
        }
    }
}

/// Drop the corners from index `from` on whose patch reaches a masked
/// pixel: radius in level-0 pixels, half the patch plus 3 (the blur before
/// the descriptor) times the level's `scale`, plus what the pyramid's
/// bilinear resizes reach ([`resample_reach`]).
#[inline(always)]
fn mask_filter(level: &mut Level, from: usize, scale: f32, sh: &Shared) {
    let Some(mask) = sh.mask else {
        return;
    };
    let r = (sh.params.patch_size / 2 + 3) as f32 * scale
        + resample_reach(scale, sh.params.scale_factor);
    let (w0, h0, w, h) = (sh.w0, sh.h0, level.w, level.h);
    let mut i = 0;
    level.corners.retain(|c| {
        i += 1;
        if i <= from {
            return true;
        }
        let x = level_to_level0(c.x as f32, w0, w);
        let y = level_to_level0(c.y as f32, h0, h);
        patch_unmasked(mask, w0, h0, x, y, r)
    });
}

/// Work of one level: detection, distribution, orientation, description.
/// Runs the AVX2 build of the same code when the CPU has it.
fn process_level(level: &mut Level, l: usize, quota: usize, sh: &Shared) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { process_level_avx2(level, l, quota, sh) };
            return;
        }
    }
    process_level_impl(level, l, quota, sh)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,bmi1,bmi2,popcnt")]
fn process_level_avx2(level: &mut Level, l: usize, quota: usize, sh: &Shared) {
    process_level_impl(level, l, quota, sh)
}

#[inline(always)]
fn process_level_impl(level: &mut Level, l: usize, quota: usize, sh: &Shared) {
    level.keypoints.clear();
    level.descriptors.clear();
    level.corners.clear();
    let p = sh.params;
    let (w, h) = (level.w, level.h);
    let edge = p.edge_threshold;
    if quota == 0 || w <= 2 * edge + 1 || h <= 2 * edge + 1 || level.image.len() < w * h {
        return;
    }
    let area = Rect {
        x0: edge,
        y0: edge,
        x1: w - edge,
        y1: h - edge,
    };
    detect(
        &level.image,
        w,
        h,
        area,
        p.ini_th_fast,
        &mut level.fast,
        &mut level.corners,
    );

    // Masked corners go before anything counts them: a cell whose corners
    // all lie in the mask gets the second threshold like an empty one, so
    // what is kept depends on the unmasked pixels only.
    let scale = (sh.w0 as f32 / w as f32).max(sh.h0 as f32 / h as f32);
    mask_filter(level, 0, scale, sh);

    // Cells where the first threshold found nothing get the second.
    let (aw, ah) = (area.x1 - area.x0, area.y1 - area.y0);
    let n_cols = (aw / p.cell_size).max(1);
    let n_rows = (ah / p.cell_size).max(1);
    let (cw, ch) = (aw.div_ceil(n_cols), ah.div_ceil(n_rows));
    level.cell_counts.clear();
    level.cell_counts.resize(n_cols * n_rows, 0);
    for c in &level.corners {
        let i = ((c.x as usize - area.x0) / cw).min(n_cols - 1);
        let j = ((c.y as usize - area.y0) / ch).min(n_rows - 1);
        level.cell_counts[j * n_cols + i] += 1;
    }
    let grid = CellGrid {
        area,
        n_cols,
        n_rows,
        cw,
        ch,
    };
    let n_strong = level.corners.len();

    let region = (
        area.x0 as f32,
        area.y0 as f32,
        area.x1 as f32,
        area.y1 as f32,
    );
    let has_fallback = sh.low_threshold < p.ini_th_fast;
    if p.fallback_fills_only {
        // The quadtree spreads the first-threshold corners; fallback corners
        // (from cells where the first threshold found nothing) are detected
        // only when those cannot fill the level's quota, and get a quadtree
        // of their own over what is left of it.
        distribute(
            &level.corners,
            region,
            quota,
            &mut level.quad,
            &mut level.selected,
        );
        let missing = quota.saturating_sub(level.selected.len());
        if missing > 0 && has_fallback {
            detect_fallback(level, &grid, sh.low_threshold);
            mask_filter(level, n_strong, scale, sh);
            if level.corners.len() > n_strong {
                distribute(
                    &level.corners[n_strong..],
                    region,
                    missing,
                    &mut level.quad,
                    &mut level.selected2,
                );
                level
                    .selected
                    .extend(level.selected2.iter().map(|&i| i + n_strong as u32));
            }
        }
    } else {
        if has_fallback {
            detect_fallback(level, &grid, sh.low_threshold);
            mask_filter(level, n_strong, scale, sh);
        }
        distribute(
            &level.corners,
            region,
            quota,
            &mut level.quad,
            &mut level.selected,
        );
    }
    if level.selected.is_empty() {
        return;
    }
    gaussian_blur(&level.image, w, h, &mut level.blur, &mut level.blur_scratch);
    let size = p.patch_size as f32 * (p.scale_factor).powi(l as i32);
    for &i in &level.selected {
        let c = level.corners[i as usize];
        let (cx, cy) = (c.x as usize, c.y as usize);
        let angle = sh.disc.angle(&level.image, w, cx, cy);
        let d = sh.steerer.describe(&level.blur, w, cx, cy, angle);
        let x = level_to_level0(c.x as f32, sh.w0, w);
        let y = level_to_level0(c.y as f32, sh.h0, h);
        let (ux, uy) = match sh.camera {
            Some(cam) => {
                let u = cam.undistort_pixel(Point2::new(x as f64, y as f64));
                (u.x as f32, u.y as f32)
            }
            None => (x, y),
        };
        level.keypoints.push(KeyPoint {
            x,
            y,
            ux,
            uy,
            octave: l as u8,
            angle,
            size,
            response: c.score as f32,
        });
        level.descriptors.push(d);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_shares_are_geometric_and_sum_to_n() {
        let q = features_per_level(1000, 8, 1.2, 1.0);
        assert_eq!(q.iter().sum::<usize>(), 1000);
        assert_eq!(q[0], 217); // ORB-SLAM's first level for 1000 features
        for k in 1..7 {
            let r = q[k] as f32 / q[k - 1] as f32;
            assert!((r - 1.0 / 1.2).abs() < 0.02, "{q:?}");
        }
        let q = features_per_level(1000, 8, 1.2, 2.0);
        assert_eq!(q.iter().sum::<usize>(), 1000);
        assert!(
            (q[1] as f32 / q[0] as f32 - 1.0 / 1.44).abs() < 0.02,
            "{q:?}"
        );
        let q = features_per_level(100, 4, 1.2, 0.0);
        assert_eq!(q, vec![25, 25, 25, 25]);
    }

    #[test]
    fn mask_probe() {
        let (w, h) = (100, 80);
        let mut mask = vec![255u8; w * h];
        for y in 0..h {
            for x in 60..w {
                mask[y * w + x] = 0;
            }
        }
        assert!(patch_unmasked(&mask, w, h, 30.0, 40.0, 18.0));
        assert!(!patch_unmasked(&mask, w, h, 50.0, 40.0, 18.0));
        assert!(!patch_unmasked(&mask, w, h, 5.0, 40.0, 18.0));
        // A band of damaged rows under the patch but between the circle's
        // probes (rows 48-52 for a patch at row 40 of radius 18: the
        // diagonal probes sit at rows 27 and 53) is seen.
        let mut rows = vec![255u8; w * h];
        for y in 48..=52 {
            for x in 0..w {
                rows[y * w + x] = 0;
            }
        }
        assert!(circle_unmasked(&rows, w, h, 30.0, 40.0, 18.0));
        assert!(!patch_unmasked(&rows, w, h, 30.0, 40.0, 18.0));
        assert!(patch_unmasked(&rows, w, h, 30.0, 25.0, 18.0));
    }

    #[test]
    fn the_resample_reach_sums_the_levels_below() {
        assert_eq!(resample_reach(1.0, 1.2), 0.0);
        // Level 5 of a 1.2 pyramid: 1 + 1.2 + 1.44 + 1.728 + 2.0736.
        let got = resample_reach(1.2f32.powi(5), 1.2);
        assert!((got - 7.4416).abs() < 1e-3, "{got}");
    }
}
