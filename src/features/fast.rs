//! FAST-9 corner detection (Rosten and Drummond) with a score and 3x3
//! non-maximum suppression, as OpenCV's `FAST(.., nonmaxSuppression = true)`.
//!
//! A pixel `c` is a corner for threshold `t` when 9 contiguous pixels of the
//! 16-pixel Bresenham circle of radius 3 are all brighter than `c + t` or all
//! darker than `c - t`. Its score is the largest `t` for which it stays a
//! corner. A corner survives suppression when its score is strictly above the
//! scores of its 8 neighbours (non-corners score 0).
//!
//! The test runs on 32 pixels at once with fixed-size arrays the compiler turns
//! into SIMD: a compass pre-test (any 9-arc holds one pixel of each opposite
//! pair 0/8 and 4/12) skips flat runs, then 16-bit "brighter" and "darker"
//! masks per pixel are searched for a run of 9 set bits by rotate-and-AND.

/// A FAST corner on one pyramid level.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Corner {
    /// Column, level pixels.
    pub x: u32,
    /// Row, level pixels.
    pub y: u32,
    /// FAST score (>= the detection threshold).
    pub score: u8,
}

/// A rectangle of pixels `[x0, x1) x [y0, y1)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
}

impl Rect {
    /// True when the rectangle holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.x1 <= self.x0 || self.y1 <= self.y0
    }
}

/// Circle offsets `(dx, dy)`, clockwise from the top.
pub const CIRCLE: [(i32, i32); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

const L: usize = 32;

/// Reusable buffers of [`detect`].
#[derive(Debug, Default, Clone)]
pub struct FastScratch {
    scores: [Vec<u8>; 3],
    cands: [Vec<u32>; 3],
    pad: Vec<u8>,
}

#[inline(always)]
fn load(row: &[u8], x: usize) -> [u8; L] {
    let mut a = [0u8; L];
    a.copy_from_slice(&row[x..x + L]);
    a
}

/// Raise `best[i]` to the longest circular run of circle pixels brighter
/// than `bound[i]` (`brighter`) or darker than it, capped at 16 + 9.
#[inline(always)]
fn longest_run(rows: &[&[u8]; 7], xs: usize, bound: &[u8; L], brighter: bool, best: &mut [u8; L]) {
    let mut m = [[0u8; L]; 16];
    for (k, &(dx, dy)) in CIRCLE.iter().enumerate() {
        let p = load(rows[(dy + 3) as usize], (xs as i32 + dx) as usize);
        // 0xff where the pixel lies beyond the bound: a saturating
        // difference is non-zero exactly there.
        for i in 0..L {
            let d = if brighter {
                p[i].saturating_sub(bound[i])
            } else {
                bound[i].saturating_sub(p[i])
            };
            m[k][i] = if d == 0 { 0 } else { 0xff };
        }
    }
    let mut run = [0u8; L];
    for k in 0..25 {
        let mk = &m[k & 15];
        for i in 0..L {
            run[i] = run[i].wrapping_add(1) & mk[i];
            best[i] = best[i].max(run[i]);
        }
    }
}

/// Corner flags of the `L` pixels `xs..xs + L` of the middle row (`rows[3]`);
/// `rows[r]` is image row `y + r - 3`, each at least `xs + L + 3` long, and
/// `xs >= 3`. Byte `i` of the result is 1 when pixel `xs + i` is a corner
/// (read as four little-endian words by the caller).
///
/// Everything stays in 8-bit lanes: per circle pixel a 0x00/0xFF mask for
/// "brighter" and for "darker", then one walk of 25 steps around the circle
/// counts the current run of set masks and keeps its maximum; a run of 9 or
/// more makes a corner.
#[inline(always)]
fn chunk_corners(rows: &[&[u8]; 7], xs: usize, t: u8) -> [u64; L / 8] {
    let c = load(rows[3], xs);
    let mut hi = [0u8; L];
    let mut lo = [0u8; L];
    for i in 0..L {
        hi[i] = c[i].saturating_add(t);
        lo[i] = c[i].saturating_sub(t);
    }
    let p0 = load(rows[0], xs);
    let p4 = load(rows[3], xs + 3);
    let p8 = load(rows[6], xs);
    let p12 = load(rows[3], xs - 3);
    let mut any_b = 0u8;
    let mut any_d = 0u8;
    for i in 0..L {
        let b = ((p0[i] > hi[i]) | (p8[i] > hi[i])) & ((p4[i] > hi[i]) | (p12[i] > hi[i]));
        let d = ((p0[i] < lo[i]) | (p8[i] < lo[i])) & ((p4[i] < lo[i]) | (p12[i] < lo[i]));
        any_b |= b as u8;
        any_d |= d as u8;
    }
    if any_b | any_d == 0 {
        return [0; L / 8];
    }
    let mut best = [0u8; L];
    if any_b != 0 {
        longest_run(rows, xs, &hi, true, &mut best);
    }
    if any_d != 0 {
        longest_run(rows, xs, &lo, false, &mut best);
    }
    let mut hit = [0u8; L];
    for i in 0..L {
        hit[i] = (best[i] >= 9) as u8;
    }
    let mut out = [0u64; L / 8];
    for (o, b) in out.iter_mut().zip(hit.chunks_exact(8)) {
        let mut a = [0u8; 8];
        a.copy_from_slice(b);
        *o = u64::from_le_bytes(a);
    }
    out
}

/// FAST score of centre `c` with circle values `p`: the largest threshold at
/// which it is a corner (0 when it is not a corner even at threshold 0).
#[inline(always)]
pub fn corner_score(c: u8, p: &[u8; 16]) -> u8 {
    let mut d = [0i16; 16];
    for k in 0..16 {
        d[k] = p[k] as i16 - c as i16;
    }
    // Sliding min / max over 9 contiguous circle pixels by doubling windows.
    let mut mn = [0i16; 16];
    let mut mx = [0i16; 16];
    for i in 0..16 {
        mn[i] = d[i].min(d[(i + 1) & 15]);
        mx[i] = d[i].max(d[(i + 1) & 15]);
    }
    let (mut mn4, mut mx4) = ([0i16; 16], [0i16; 16]);
    for i in 0..16 {
        mn4[i] = mn[i].min(mn[(i + 2) & 15]);
        mx4[i] = mx[i].max(mx[(i + 2) & 15]);
    }
    let (mut mn8, mut mx8) = ([0i16; 16], [0i16; 16]);
    for i in 0..16 {
        mn8[i] = mn4[i].min(mn4[(i + 4) & 15]);
        mx8[i] = mx4[i].max(mx4[(i + 4) & 15]);
    }
    let mut bright = i16::MIN;
    let mut dark = i16::MIN;
    for i in 0..16 {
        bright = bright.max(mn8[i].min(d[(i + 8) & 15]));
        dark = dark.max(-(mx8[i].max(d[(i + 8) & 15])));
    }
    (bright.max(dark) - 1).clamp(0, 255) as u8
}

/// Circle values around `(x, y)`; the caller guarantees a 3-pixel margin.
#[inline(always)]
pub fn circle_values(img: &[u8], w: usize, x: usize, y: usize) -> [u8; 16] {
    let mut p = [0u8; 16];
    for (k, &(dx, dy)) in CIRCLE.iter().enumerate() {
        let xx = (x as i32 + dx) as usize;
        let yy = (y as i32 + dy) as usize;
        p[k] = img[yy * w + xx];
    }
    p
}

/// Detect FAST-9 corners with threshold `t` inside `rect` of the `w` x `h`
/// image `img` and append the ones surviving non-maximum suppression to `out`
/// (row by row, left to right). The rectangle is clipped to a 4-pixel margin
/// (3 for the circle, 1 for the suppression neighbourhood).
#[inline(always)]
pub fn detect(
    img: &[u8],
    w: usize,
    h: usize,
    rect: Rect,
    t: u8,
    scratch: &mut FastScratch,
    out: &mut Vec<Corner>,
) {
    if img.len() < w * h || w < 9 || h < 9 {
        return;
    }
    let r = Rect {
        x0: rect.x0.max(4),
        y0: rect.y0.max(4),
        x1: rect.x1.min(w - 4),
        y1: rect.y1.min(h - 4),
    };
    if r.is_empty() {
        return;
    }
    // Scores are computed on the rectangle grown by one pixel.
    let sx0 = r.x0 - 1;
    let sw = r.x1 - r.x0 + 2;
    for s in scratch.scores.iter_mut() {
        s.clear();
        s.resize(sw, 0);
    }
    for c in scratch.cands.iter_mut() {
        c.clear();
    }
    scratch.pad.clear();
    scratch.pad.resize(7 * (L + 6), 0);
    for y in r.y0 - 1..r.y1 + 1 {
        let slot = y % 3;
        scratch.scores[slot].fill(0);
        scratch.cands[slot].clear();
        let rows: [&[u8]; 7] = std::array::from_fn(|k| &img[(y + k - 3) * w..(y + k - 3) * w + w]);
        let mut xs = sx0;
        while xs < sx0 + sw {
            let words = if xs + L + 3 <= w {
                chunk_corners(&rows, xs, t)
            } else {
                // Tail: copy into zero-padded rows; lanes past the end are dropped.
                let n = w - (xs - 3);
                for (k, row) in rows.iter().enumerate() {
                    let dst = &mut scratch.pad[k * (L + 6)..(k + 1) * (L + 6)];
                    dst.fill(0);
                    dst[..n].copy_from_slice(&row[xs - 3..w]);
                }
                let pad = &scratch.pad;
                let prow: [&[u8]; 7] =
                    std::array::from_fn(|k| &pad[k * (L + 6)..(k + 1) * (L + 6)]);
                chunk_corners(&prow, 3, t)
            };
            let end = sx0 + sw;
            for (wi, &word) in words.iter().enumerate() {
                let mut bits = word;
                while bits != 0 {
                    let i = wi * 8 + (bits.trailing_zeros() / 8) as usize;
                    bits &= bits - 1;
                    let x = xs + i;
                    if x >= end {
                        break;
                    }
                    let score = corner_score(rows[3][x], &circle_values(img, w, x, y)).max(1);
                    scratch.scores[slot][x - sx0] = score;
                    scratch.cands[slot].push(x as u32);
                }
            }
            xs += L;
        }
        // Suppress on the previous row now that its neighbours are known.
        if y > r.y0 && y - 1 < r.y1 {
            let yc = y - 1;
            let (above, mid, below) = (
                &scratch.scores[(yc + 2) % 3],
                &scratch.scores[yc % 3],
                &scratch.scores[slot],
            );
            for &xc in &scratch.cands[yc % 3] {
                let x = xc as usize;
                if x < r.x0 || x >= r.x1 {
                    continue;
                }
                let j = x - sx0;
                let s = mid[j];
                if s > mid[j - 1]
                    && s > mid[j + 1]
                    && s > above[j - 1]
                    && s > above[j]
                    && s > above[j + 1]
                    && s > below[j - 1]
                    && s > below[j]
                    && s > below[j + 1]
                {
                    out.push(Corner {
                        x: xc,
                        y: yc as u32,
                        score: s,
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn naive_is_corner(img: &[u8], w: usize, x: usize, y: usize, t: u8) -> bool {
        let c = img[y * w + x] as i32;
        let p = circle_values(img, w, x, y);
        let t = t as i32;
        for start in 0..16 {
            if (0..9).all(|j| p[(start + j) % 16] as i32 > c + t)
                || (0..9).all(|j| (p[(start + j) % 16] as i32) < c - t)
            {
                return true;
            }
        }
        false
    }

    fn naive_score(img: &[u8], w: usize, x: usize, y: usize) -> u8 {
        let mut best = 0;
        for t in 0..=255u8 {
            if naive_is_corner(img, w, x, y, t) {
                best = t;
            } else {
                break;
            }
        }
        best
    }

    fn random_image(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut rng = StdRng::seed_from_u64(seed);
        // Blocky noise: corners at many thresholds.
        let cells: Vec<u8> = (0..(w / 3 + 1) * (h / 3 + 1))
            .map(|_| rng.random())
            .collect();
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let v = cells[(y / 3) * (w / 3 + 1) + x / 3] as i32 + rng.random_range(-6..=6);
                v.clamp(0, 255) as u8
            })
            .collect()
    }

    #[test]
    fn detect_equals_naive_fast_with_nonmax() {
        for (w, h, seed) in [(101, 67, 1u64), (40, 30, 2), (13, 13, 3), (200, 50, 4)] {
            let img = random_image(w, h, seed);
            for t in [7u8, 20, 40] {
                let rect = Rect {
                    x0: 0,
                    y0: 0,
                    x1: w,
                    y1: h,
                };
                let mut out = Vec::new();
                detect(&img, w, h, rect, t, &mut FastScratch::default(), &mut out);
                // Reference: score map over the 3-pixel margin, suppression in 4.
                let mut score = vec![0u8; w * h];
                for y in 3..h - 3 {
                    for x in 3..w - 3 {
                        if naive_is_corner(&img, w, x, y, t) {
                            score[y * w + x] = naive_score(&img, w, x, y).max(1);
                        }
                    }
                }
                let mut want = Vec::new();
                for y in 4..h - 4 {
                    for x in 4..w - 4 {
                        let s = score[y * w + x];
                        if s == 0 {
                            continue;
                        }
                        let mut ok = true;
                        for dy in -1i32..=1 {
                            for dx in -1i32..=1 {
                                if (dx, dy) != (0, 0) {
                                    let n = score
                                        [(y as i32 + dy) as usize * w + (x as i32 + dx) as usize];
                                    ok &= s > n;
                                }
                            }
                        }
                        if ok {
                            want.push(Corner {
                                x: x as u32,
                                y: y as u32,
                                score: s,
                            });
                        }
                    }
                }
                assert!(
                    !want.is_empty() || t == 40,
                    "{w}x{h} t{t}: no corners at all"
                );
                assert_eq!(out, want, "{w}x{h} t{t}");
            }
        }
    }

    #[test]
    fn score_is_threshold_boundary() {
        let img = random_image(64, 64, 9);
        let w = 64;
        let mut checked = 0;
        for y in 3..61 {
            for x in 3..61 {
                if naive_is_corner(&img, w, x, y, 10) {
                    let s = corner_score(img[y * w + x], &circle_values(&img, w, x, y));
                    assert!(naive_is_corner(&img, w, x, y, s));
                    assert!(s == 255 || !naive_is_corner(&img, w, x, y, s + 1));
                    checked += 1;
                }
            }
        }
        assert!(checked > 50);
    }

    #[test]
    fn flat_and_tiny_images_have_no_corners() {
        let mut out = Vec::new();
        let mut s = FastScratch::default();
        let all = Rect {
            x0: 0,
            y0: 0,
            x1: 100,
            y1: 100,
        };
        detect(&[0u8; 100 * 100], 100, 100, all, 7, &mut s, &mut out);
        detect(&[255u8; 100 * 100], 100, 100, all, 7, &mut s, &mut out);
        detect(&[9u8; 16], 4, 4, all, 7, &mut s, &mut out);
        detect(&[], 0, 0, all, 7, &mut s, &mut out);
        assert!(out.is_empty());
    }
}
