//! Image noise level, estimated robustly (Immerkaer's Laplacian-difference
//! mask, with the median absolute response instead of the mean so that edges
//! and texture, a minority of pixels, do not inflate it).
//!
//! The mask `[1 -2 1; -2 4 -2; 1 -2 1]` cancels planes and ramps; on white
//! noise of deviation `s` its response has deviation `6 s`, so
//! `s = 1.4826 median(|r|) / 6`.

/// Estimate the noise standard deviation (gray levels) of the `w` x `h`
/// image from every `step_y`-th row and `step_x`-th column. 0 for images
/// smaller than 3 x 3.
pub fn estimate_noise_sigma(img: &[u8], w: usize, h: usize, step_x: usize, step_y: usize) -> f32 {
    estimate_noise_sigma_masked(img, None, w, h, step_x, step_y)
}

/// [`estimate_noise_sigma`] over the pixels whose 3x3 neighbourhood is
/// unmasked (`mask` 0 = ignore).
pub fn estimate_noise_sigma_masked(
    img: &[u8],
    mask: Option<&[u8]>,
    w: usize,
    h: usize,
    step_x: usize,
    step_y: usize,
) -> f32 {
    if w < 3 || h < 3 || img.len() < w * h || mask.is_some_and(|m| m.len() < w * h) {
        return 0.0;
    }
    let (sx, sy) = (step_x.max(1), step_y.max(1));
    let mut hist = [0u32; 256];
    let mut n = 0u32;
    for y in (1..h - 1).step_by(sy) {
        let up = &img[(y - 1) * w..y * w];
        let mid = &img[y * w..(y + 1) * w];
        let down = &img[(y + 1) * w..(y + 2) * w];
        for x in (1..w - 1).step_by(sx) {
            if let Some(m) = mask {
                let ok = [y - 1, y, y + 1].iter().all(|&yy| {
                    m[yy * w + x - 1] != 0 && m[yy * w + x] != 0 && m[yy * w + x + 1] != 0
                });
                if !ok {
                    continue;
                }
            }
            let corners =
                up[x - 1] as i32 + up[x + 1] as i32 + down[x - 1] as i32 + down[x + 1] as i32;
            let edges = up[x] as i32 + down[x] as i32 + mid[x - 1] as i32 + mid[x + 1] as i32;
            let r = (corners - 2 * edges + 4 * mid[x] as i32)
                .unsigned_abs()
                .min(255);
            hist[r as usize] += 1;
            n += 1;
        }
    }
    if n == 0 {
        return 0.0;
    }
    let half = n.div_ceil(2);
    let mut acc = 0;
    for (v, &c) in hist.iter().enumerate() {
        acc += c;
        if acc >= half {
            return 1.4826 * v as f32 / 6.0;
        }
    }
    0.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    #[test]
    fn recovers_added_noise_on_a_ramp() {
        let (w, h) = (200, 150);
        let mut rng = StdRng::seed_from_u64(1);
        for sigma in [2.0f32, 5.0, 10.0] {
            let img: Vec<u8> = (0..w * h)
                .map(|i| {
                    let base = 60.0 + 0.3 * (i % w) as f32 + 0.2 * (i / w) as f32;
                    let u1: f32 = rng.random_range(1e-7..1.0);
                    let u2: f32 = rng.random();
                    let n = (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos();
                    (base + sigma * n).round().clamp(0.0, 255.0) as u8
                })
                .collect();
            let est = estimate_noise_sigma(&img, w, h, 1, 1);
            assert!(
                (est - sigma).abs() < 0.25 * sigma + 0.3,
                "sigma {sigma}: {est}"
            );
        }
        assert_eq!(estimate_noise_sigma(&vec![9u8; w * h], w, h, 2, 2), 0.0);
        assert_eq!(estimate_noise_sigma(&[1, 2], 2, 1, 1, 1), 0.0);
    }
}
