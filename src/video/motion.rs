//! How far the picture's content moved up or down between two decoded
//! pictures: the range of vertical block motion, for following damage
//! through the reference chain (`crate::video::damage`).
//!
//! A predicted picture copies blocks from its reference wherever its motion
//! vectors point; an encoder's motion search follows the content, so damage
//! in a reference travels with the content's motion. Without parsing the
//! motion vectors (CAVLC/CABAC decoding of every macroblock) the content's
//! motion is measured on the decoded pictures instead: both are reduced to
//! about [`MotionParams::work_width`] pixels wide, and blocks on a grid are
//! matched by the sum of absolute differences over a window of
//! ±[`MotionParams::search`] reduced pixels, then the vertical displacement
//! of each is refined to the pixel on the full pictures. Only blocks with
//! texture and a vertical displacement that stands out are counted, and
//! none whose rows or search window touch damaged rows (concealed content
//! matches nothing).

use std::sync::Arc;

use image::GrayImage;

/// Tunables of the vertical motion measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionParams {
    /// Width the pictures are reduced to before matching, pixels (the
    /// reduction factor is the picture's width over this, at least 1).
    pub work_width: u32,
    /// Block side in reduced pixels.
    pub block: u32,
    /// Search window, ± reduced pixels in both directions.
    pub search: u32,
    /// Blocks with a smaller standard deviation of intensity carry too
    /// little texture to be matched (grey levels).
    pub min_std: f64,
    /// A block's best vertical displacement must beat every displacement
    /// two or more reduced rows away by this factor of its cost.
    pub distinct: f64,
    /// Fewer accepted blocks than this: no measurement.
    pub min_blocks: usize,
}

impl Default for MotionParams {
    fn default() -> Self {
        Self {
            work_width: 160,
            block: 16,
            search: 8,
            min_std: 4.0,
            distinct: 1.15,
            min_blocks: 6,
        }
    }
}

/// The vertical motion of the content from one picture to the next, full
/// resolution pixels (down positive): every accepted block moved between
/// `lo` and `hi`, each measured to within `step` pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct VerticalMotion {
    /// Smallest block displacement.
    pub lo: i32,
    /// Largest block displacement.
    pub hi: i32,
    /// Resolution of the measurement (the reduction factor).
    pub step: u32,
    /// Blocks that were measured.
    pub blocks: usize,
}

impl VerticalMotion {
    /// The range covering both (for a motion that changes between pictures).
    pub fn union(self, other: VerticalMotion) -> VerticalMotion {
        VerticalMotion {
            lo: self.lo.min(other.lo),
            hi: self.hi.max(other.hi),
            step: self.step.max(other.step),
            blocks: self.blocks.min(other.blocks),
        }
    }

    /// Scaled by `f` (motion measured on a decimated picture, in the coded
    /// picture's pixels).
    pub fn scaled(self, f: u32) -> VerticalMotion {
        let f = f.max(1);
        VerticalMotion {
            lo: self.lo * f as i32,
            hi: self.hi * f as i32,
            step: self.step * f,
            blocks: self.blocks,
        }
    }
}

/// A picture reduced for matching, with the rows that may not be used.
#[derive(Debug, Clone)]
pub struct Reduced {
    full: Arc<GrayImage>,
    w: usize,
    h: usize,
    factor: u32,
    px: Vec<u16>,
    /// Reduced rows holding a damaged source row.
    bad: Vec<bool>,
}

impl Reduced {
    /// `img` box-filtered by the factor that makes it about
    /// `params.work_width` wide; `damage` (one flag per row of `img`,
    /// `true` where damaged) marks the rows not to match.
    pub fn new(img: &Arc<GrayImage>, damage: Option<&[bool]>, params: &MotionParams) -> Self {
        let factor = (img.width() / params.work_width.max(1)).max(1);
        let f = factor as usize;
        let (w, h) = (img.width() as usize / f, img.height() as usize / f);
        let src = img.as_raw();
        let sw = img.width() as usize;
        let mut px = vec![0u16; w * h];
        // Column sums over the factor's rows, then sums of the factor's
        // columns: two passes the compiler vectorises.
        let mut cols = vec![0u32; sw];
        for y in 0..h {
            cols.fill(0);
            for row in src[y * f * sw..(y * f + f) * sw].chunks_exact(sw) {
                for (c, &v) in cols.iter_mut().zip(row) {
                    *c += u32::from(v);
                }
            }
            for (out, group) in px[y * w..(y + 1) * w].iter_mut().zip(cols.chunks_exact(f)) {
                let s: u32 = group.iter().sum();
                // Averages kept in 4 fractional bits.
                *out = ((s * 16) / (f * f) as u32) as u16;
            }
        }
        let rows = damage;
        let bad = (0..h)
            .map(|y| {
                rows.is_some_and(|r| (0..f).any(|k| r.get(y * f + k).copied().unwrap_or(true)))
            })
            .collect();
        Self {
            full: img.clone(),
            w,
            h,
            factor,
            px,
            bad,
        }
    }

    fn at(&self, x: usize, y: usize) -> i32 {
        i32::from(self.px[y * self.w + x])
    }
}

/// The vertical motion of the content from `prev` to `cur` (both reduced
/// with the same parameters from pictures of one size), or `None` when too
/// few blocks could be measured.
pub fn vertical_motion(
    prev: &Reduced,
    cur: &Reduced,
    params: &MotionParams,
) -> Option<VerticalMotion> {
    if prev.w != cur.w || prev.h != cur.h || prev.factor != cur.factor {
        return None;
    }
    let (b, s) = (params.block as usize, params.search as usize);
    if cur.w < b + 2 * s || cur.h < b + 2 * s {
        return None;
    }
    let n = (2 * s + 1) * (2 * s + 1);
    let mut costs = vec![0u32; n];
    let (mut lo, mut hi, mut blocks) = (i32::MAX, i32::MIN, 0usize);
    let min_var = (params.min_std * 16.0).powi(2);
    let mut y0 = s;
    while y0 + b + s <= cur.h {
        let mut x0 = s;
        while x0 + b + s <= cur.w {
            let usable = !cur.bad[y0..y0 + b].iter().any(|&d| d)
                && !prev.bad[y0 - s..y0 + b + s].iter().any(|&d| d);
            if usable
                && let Some((dx, dy)) =
                    block_dy(prev, cur, x0, y0, b, s, min_var, params, &mut costs)
            {
                let dy = refine_dy(prev, cur, x0, y0, b, dx, dy);
                lo = lo.min(dy);
                hi = hi.max(dy);
                blocks += 1;
            }
            x0 += b;
        }
        y0 += b;
    }
    (blocks >= params.min_blocks).then_some(VerticalMotion {
        lo,
        hi,
        step: 1,
        blocks,
    })
}

/// The block's vertical displacement on the full pictures, pixels: the
/// reduced match (`dx`, `dy`, reduced pixels) refined over ± one reduction
/// factor, the horizontal one held (every other row and column compared).
fn refine_dy(
    prev: &Reduced,
    cur: &Reduced,
    x0: usize,
    y0: usize,
    b: usize,
    dx: i32,
    dy: i32,
) -> i32 {
    let f = cur.factor as i32;
    let (pw, ph) = (prev.full.width() as i32, prev.full.height() as i32);
    let (cw, ch) = (cur.full.width() as i32, cur.full.height() as i32);
    let (bx, by, side) = (x0 as i32 * f, y0 as i32 * f, b as i32 * f);
    if f == 1 || pw != cw || ph != ch {
        return dy * f;
    }
    let (p, c) = (prev.full.as_raw(), cur.full.as_raw());
    let mut best = (u64::MAX, dy * f);
    for cand in dy * f - f..=dy * f + f {
        // Content at prev (x - dx, y - cand) is at cur (x, y).
        let (sx, sy) = (bx - dx * f, by - cand);
        if sx < 0 || sy < 0 || sx + side > pw || sy + side > ph {
            continue;
        }
        let mut sad = 0u64;
        for y in (0..side).step_by(2) {
            let pr = &p[((sy + y) * pw + sx) as usize..][..side as usize];
            let cr = &c[((by + y) * cw + bx) as usize..][..side as usize];
            sad += pr
                .iter()
                .step_by(2)
                .zip(cr.iter().step_by(2))
                .map(|(&a, &b)| u64::from(a.abs_diff(b)))
                .sum::<u64>();
        }
        if sad < best.0 {
            best = (sad, cand);
        }
    }
    best.1
}

/// The displacement (reduced pixels, content moving right and down
/// positive) of the block at (`x0`, `y0`) of `cur` from `prev`, when it has
/// texture and one vertical displacement stands out.
#[allow(clippy::too_many_arguments)]
fn block_dy(
    prev: &Reduced,
    cur: &Reduced,
    x0: usize,
    y0: usize,
    b: usize,
    s: usize,
    min_var: f64,
    params: &MotionParams,
    costs: &mut [u32],
) -> Option<(i32, i32)> {
    let (mut sum, mut sq) = (0f64, 0f64);
    for y in y0..y0 + b {
        for x in x0..x0 + b {
            let v = f64::from(cur.at(x, y));
            sum += v;
            sq += v * v;
        }
    }
    let m = (b * b) as f64;
    if sq / m - (sum / m).powi(2) < min_var {
        return None;
    }
    let side = 2 * s + 1;
    for (k, c) in costs.iter_mut().enumerate() {
        let (oy, ox) = (k / side, k % side);
        let mut sad = 0u32;
        for y in 0..b {
            let pr = &prev.px[(y0 + y + oy - s) * prev.w + x0 + ox - s..][..b];
            let cr = &cur.px[(y0 + y) * cur.w + x0..][..b];
            sad += pr
                .iter()
                .zip(cr)
                .map(|(&p, &c)| u32::from(p.abs_diff(c)))
                .sum::<u32>();
        }
        *c = sad;
    }
    let (best, &best_cost) = costs.iter().enumerate().min_by_key(|(_, c)| **c)?;
    let (best_oy, best_ox) = ((best / side) as i32, (best % side) as i32);
    // Content at prev row y + oy - s is at cur row y: it moved by s - oy.
    let others = costs
        .iter()
        .enumerate()
        .filter(|(k, _)| ((*k / side) as i32 - best_oy).abs() >= 2)
        .map(|(_, c)| *c)
        .min()?;
    (f64::from(others) > params.distinct * f64::from(best_cost) + m)
        .then_some((s as i32 - best_ox, s as i32 - best_oy))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured picture (smooth noise) shifted by (`dx`, `dy`).
    fn picture(w: u32, h: u32, dx: i32, dy: i32) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| {
            let (u, v) = (x as i32 - dx, y as i32 - dy);
            let t = ((u as f64 * 0.21).sin() * (v as f64 * 0.17).cos()
                + (u as f64 * 0.05 + v as f64 * 0.07).sin()
                + ((u * 7919 + v * 104_729) % 97) as f64 / 200.0)
                * 60.0
                + 128.0;
            image::Luma([t.clamp(0.0, 255.0) as u8])
        })
    }

    #[test]
    fn a_shift_is_measured_within_its_step() {
        let p = MotionParams::default();
        for (dx, dy) in [(0, 0), (5, 12), (-9, -20), (3, 28)] {
            let a = Reduced::new(&Arc::new(picture(640, 480, 0, 0)), None, &p);
            let b = Reduced::new(&Arc::new(picture(640, 480, dx, dy)), None, &p);
            let m = vertical_motion(&a, &b, &p).expect("a measurement");
            assert_eq!(m.step, 1);
            assert!(m.blocks >= 20, "{m:?}");
            assert!(m.lo >= dy - 1 && m.hi <= dy + 1, "({dx}, {dy}): {m:?}");
        }
    }

    #[test]
    fn flat_pictures_and_damaged_rows_give_no_measurement() {
        let p = MotionParams::default();
        let flat = Arc::new(GrayImage::from_pixel(640, 480, image::Luma([90])));
        let a = Reduced::new(&flat, None, &p);
        assert_eq!(vertical_motion(&a, &a, &p), None);
        let all = vec![true; 480];
        let t = Arc::new(picture(640, 480, 0, 0));
        let d = Reduced::new(&t, Some(&all), &p);
        let c = Reduced::new(&t, None, &p);
        assert_eq!(vertical_motion(&d, &c, &p), None);
        // Other sizes are not compared.
        let small = Reduced::new(&Arc::new(picture(320, 240, 0, 0)), None, &p);
        assert_eq!(vertical_motion(&c, &small, &p), None);
    }
}
