//! Hamming matching of ORB descriptors.
//!
//! - [`match_brute_force`]: every query against every train descriptor, with
//!   a distance bound, Lowe's ratio test and an optional cross-check, in one
//!   pass over the distance matrix (the reverse best is tracked on the way).
//! - [`FeatureGrid`]: keypoints binned in ORB-SLAM's 64 x 48 cells over the
//!   undistorted image [`Bounds`], for search by projection (the SLAM's
//!   tracking, mapping and relocalisation, the shot's localisation):
//!   [`FeatureGrid::features_in_area`].
//! - [`RotationHistogram`]: ORB-SLAM's rotation-consistency filter: the
//!   angle differences of the matches go into 30 bins and only the matches of
//!   the (up to) 3 fullest bins are kept.
//!
//! Matching by vocabulary node lives with the vocabulary.

use nalgebra::Point2;

use crate::camera::Camera;
pub use crate::features::{Descriptor, KeyPoint, hamming};

/// Errors of the matching helpers.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MatchingError {
    /// A parameter is out of its range.
    #[error("invalid parameter {name} = {value}: {reason}")]
    InvalidParams {
        /// The parameter.
        name: &'static str,
        /// Its value, printed.
        value: String,
        /// The allowed range.
        reason: &'static str,
    },
}

/// One correspondence between a query and a train descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Match {
    /// Index into the query set.
    pub query: usize,
    /// Index into the train set.
    pub train: usize,
    /// Hamming distance.
    pub distance: u32,
}

/// Every tunable number of brute-force matching.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Largest accepted Hamming distance (ORB-SLAM: 100 loose, 50 strict).
    pub max_distance: u32,
    /// Lowe's ratio: keep when `best < ratio * second_best`; 1.0 disables.
    pub ratio: f32,
    /// Keep only pairs that are each other's best match.
    pub cross_check: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            max_distance: 64,
            ratio: 0.8,
            cross_check: false,
        }
    }
}

impl Params {
    /// Check the numbers.
    pub fn validate(&self) -> Result<(), MatchingError> {
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(MatchingError::InvalidParams {
                name: "ratio",
                value: self.ratio.to_string(),
                reason: "must be in (0, 1]",
            });
        }
        if self.max_distance > 256 {
            return Err(MatchingError::InvalidParams {
                name: "max_distance",
                value: self.max_distance.to_string(),
                reason: "must be at most 256",
            });
        }
        Ok(())
    }
}

/// Match every query descriptor against every train descriptor; see
/// [`match_brute_force_into`].
pub fn match_brute_force(
    query: &[Descriptor],
    train: &[Descriptor],
    params: &Params,
) -> Result<Vec<Match>, MatchingError> {
    let mut out = Vec::new();
    match_brute_force_into(query, train, params, &mut Vec::new(), &mut out)?;
    Ok(out)
}

/// Brute-force matching into `out` (cleared first), in query order. A query
/// keeps its nearest train descriptor when the distance is at most
/// `max_distance`, passes the ratio test against the second nearest (when
/// there is one) and, with `cross_check`, when the query is also the train
/// descriptor's nearest (the lowest query index wins ties). `reverse` is
/// scratch space reused between calls.
pub fn match_brute_force_into(
    query: &[Descriptor],
    train: &[Descriptor],
    params: &Params,
    reverse: &mut Vec<(u32, u32)>,
    out: &mut Vec<Match>,
) -> Result<(), MatchingError> {
    params.validate()?;
    out.clear();
    if query.is_empty() || train.is_empty() {
        return Ok(());
    }
    reverse.clear();
    reverse.resize(train.len(), (u32::MAX, u32::MAX));
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("popcnt")
            && std::arch::is_x86_feature_detected!("avx2")
        {
            // SAFETY: the CPU has POPCNT and AVX2, checked just above.
            unsafe { scan_fast(query, train, params, reverse, out) };
            return finish(params, reverse, out);
        }
    }
    scan(query, train, params, reverse, out);
    finish(params, reverse, out)
}

fn finish(
    params: &Params,
    reverse: &[(u32, u32)],
    out: &mut Vec<Match>,
) -> Result<(), MatchingError> {
    if params.cross_check {
        out.retain(|m| reverse[m.train].1 as usize == m.query);
    }
    Ok(())
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt,avx2")]
fn scan_fast(
    query: &[Descriptor],
    train: &[Descriptor],
    params: &Params,
    reverse: &mut [(u32, u32)],
    out: &mut Vec<Match>,
) {
    scan(query, train, params, reverse, out)
}

/// The distance scan: best and second best per query, best query per train.
#[inline(always)]
fn scan(
    query: &[Descriptor],
    train: &[Descriptor],
    params: &Params,
    reverse: &mut [(u32, u32)],
    out: &mut Vec<Match>,
) {
    for (qi, q) in query.iter().enumerate() {
        let (mut best, mut second, mut best_t) = (u32::MAX, u32::MAX, 0usize);
        for (ti, (t, rev)) in train.iter().zip(reverse.iter_mut()).enumerate() {
            let d = crate::features::hamming_portable(q, t);
            if d < best {
                second = best;
                best = d;
                best_t = ti;
            } else if d < second {
                second = d;
            }
            if d < rev.0 {
                *rev = (d, qi as u32);
            }
        }
        if best > params.max_distance {
            continue;
        }
        if second != u32::MAX && params.ratio < 1.0 && best as f32 >= params.ratio * second as f32 {
            continue;
        }
        out.push(Match {
            query: qi,
            train: best_t,
            distance: best,
        });
    }
}

/// Columns of the [`FeatureGrid`] (ORB-SLAM's 64).
pub const GRID_COLS: usize = 64;
/// Rows of the [`FeatureGrid`] (ORB-SLAM's 48).
pub const GRID_ROWS: usize = 48;

/// The undistorted image bounds of a camera: where undistorted keypoints can
/// lie, the region a [`FeatureGrid`] covers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bounds {
    /// Smallest x.
    pub min_x: f64,
    /// Largest x.
    pub max_x: f64,
    /// Smallest y.
    pub min_y: f64,
    /// Largest y.
    pub max_y: f64,
}

impl Bounds {
    /// The bounding box of the undistorted image border.
    pub fn of(camera: &Camera) -> Bounds {
        let (w, h) = (camera.width as f64 - 1.0, camera.height as f64 - 1.0);
        let mut b = Bounds {
            min_x: f64::INFINITY,
            max_x: f64::NEG_INFINITY,
            min_y: f64::INFINITY,
            max_y: f64::NEG_INFINITY,
        };
        let n = 16;
        for i in 0..=n {
            let t = i as f64 / n as f64;
            for p in [
                Point2::new(t * w, 0.0),
                Point2::new(t * w, h),
                Point2::new(0.0, t * h),
                Point2::new(w, t * h),
            ] {
                let u = camera.undistort_pixel(p);
                b.min_x = b.min_x.min(u.x);
                b.max_x = b.max_x.max(u.x);
                b.min_y = b.min_y.min(u.y);
                b.max_y = b.max_y.max(u.y);
            }
        }
        b
    }

    /// True when a point lies inside.
    #[inline]
    pub fn contains(&self, x: f64, y: f64) -> bool {
        x >= self.min_x && x <= self.max_x && y >= self.min_y && y <= self.max_y
    }

    /// True when the bounds are finite and enclose some area.
    pub fn is_valid(&self) -> bool {
        [self.min_x, self.max_x, self.min_y, self.max_y]
            .iter()
            .all(|v| v.is_finite())
            && self.max_x > self.min_x
            && self.max_y > self.min_y
    }
}

/// Keypoints binned in [`GRID_COLS`] x [`GRID_ROWS`] cells over the
/// undistorted image [`Bounds`], for search by projection
/// ([`FeatureGrid::features_in_area`]). Uses the undistorted positions
/// `ux, uy`; keypoints outside `[min_x, max_x) x [min_y, max_y)` are not
/// indexed. Flat storage (cell offsets + entries in cell order), built once
/// per frame; [`FeatureGrid::rebuild`] reuses it.
#[derive(Debug, Clone, Default)]
pub struct FeatureGrid {
    /// `None` for an empty grid (default, or built over invalid bounds).
    bounds: Option<Bounds>,
    inv_cell_w: f64,
    inv_cell_h: f64,
    /// `cell_start[c]..cell_start[c + 1]` indexes `entries` for cell `c`.
    cell_start: Vec<u32>,
    /// The keypoints in cell order, with what the search tests (read in
    /// sequence rather than gathered from the keypoint list).
    entries: Vec<Entry>,
}

/// A keypoint as the grid holds it.
#[derive(Debug, Clone, Copy, Default)]
struct Entry {
    x: f32,
    y: f32,
    octave: i32,
    index: u32,
}

impl FeatureGrid {
    /// Heap bytes of its storage (capacities).
    pub fn heap_bytes(&self) -> usize {
        self.cell_start.capacity() * std::mem::size_of::<u32>()
            + self.entries.capacity() * std::mem::size_of::<Entry>()
    }

    /// Index `keypoints` (their undistorted positions) within `bounds`. Over
    /// bounds that are not finite or enclose no area the grid is empty.
    pub fn new(keypoints: &[KeyPoint], bounds: Bounds) -> Self {
        let mut grid = FeatureGrid::default();
        grid.rebuild(keypoints, bounds);
        grid
    }

    /// [`FeatureGrid::new`] in place, reusing the storage.
    pub fn rebuild(&mut self, keypoints: &[KeyPoint], bounds: Bounds) {
        self.cell_start.clear();
        self.entries.clear();
        if !bounds.is_valid() || keypoints.len() > u32::MAX as usize {
            self.bounds = None;
            return;
        }
        self.bounds = Some(bounds);
        self.inv_cell_w = GRID_COLS as f64 / (bounds.max_x - bounds.min_x);
        self.inv_cell_h = GRID_ROWS as f64 / (bounds.max_y - bounds.min_y);
        const CELLS: usize = GRID_COLS * GRID_ROWS;
        self.cell_start.resize(CELLS + 1, 0);
        // Count per cell (shifted by one), then prefix sums: cell_start[c]
        // is where cell c begins.
        for k in keypoints {
            if let Some(c) = self.cell_of(k.ux as f64, k.uy as f64) {
                self.cell_start[c + 1] += 1;
            }
        }
        for i in 0..CELLS {
            self.cell_start[i + 1] += self.cell_start[i];
        }
        self.entries
            .resize(self.cell_start[CELLS] as usize, Entry::default());
        // Fill in keypoint order, advancing each cell's start; afterwards
        // every start sits at the next cell's beginning, so shift back.
        for (i, k) in keypoints.iter().enumerate() {
            if let Some(c) = self.cell_of(k.ux as f64, k.uy as f64) {
                let at = self.cell_start[c] as usize;
                self.entries[at] = Entry {
                    x: k.ux,
                    y: k.uy,
                    octave: k.octave as i32,
                    index: i as u32,
                };
                self.cell_start[c] += 1;
            }
        }
        self.cell_start.copy_within(0..CELLS, 1);
        self.cell_start[0] = 0;
    }

    /// Number of indexed keypoints.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when no keypoint is indexed.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The cell (row-major index) holding `(x, y)`, if inside.
    #[inline]
    fn cell_of(&self, x: f64, y: f64) -> Option<usize> {
        let b = self.bounds?;
        let cx = ((x - b.min_x) * self.inv_cell_w).floor();
        let cy = ((y - b.min_y) * self.inv_cell_h).floor();
        // Written so that NaN fails every test.
        if cx >= 0.0 && cy >= 0.0 && cx < GRID_COLS as f64 && cy < GRID_ROWS as f64 {
            Some(cy as usize * GRID_COLS + cx as usize)
        } else {
            None
        }
    }

    /// Fill `out` (cleared first) with the indices of the keypoints within
    /// `r` pixels of `(x, y)` (the square window's cells, then the exact
    /// circle) whose octave is in `min_level..=max_level`, in grid order.
    /// `keypoints` are the ones the grid was built from (indices past their
    /// end are skipped, so a mismatched list cannot index out of bounds).
    #[allow(clippy::too_many_arguments)]
    pub fn features_in_area(
        &self,
        keypoints: &[KeyPoint],
        x: f64,
        y: f64,
        r: f64,
        min_level: i32,
        max_level: i32,
        out: &mut Vec<usize>,
    ) {
        out.clear();
        let Some(b) = self.bounds else {
            return;
        };
        // Cell range of the square window. `as usize` truncates towards
        // zero and saturates negatives (and NaN) at 0, which is the floor
        // clamped at 0 for the low ends; a high end below 0 (or NaN) means
        // the window misses the grid.
        let (hx, hy) = (
            (x + r - b.min_x) * self.inv_cell_w,
            (y + r - b.min_y) * self.inv_cell_h,
        );
        if !(hx >= 0.0 && hy >= 0.0) {
            return;
        }
        let c0 = ((x - r - b.min_x) * self.inv_cell_w) as usize;
        let r0 = ((y - r - b.min_y) * self.inv_cell_h) as usize;
        let c1 = (hx as usize).min(GRID_COLS - 1);
        let r1 = (hy as usize).min(GRID_ROWS - 1);
        if c0 > c1 || r0 > r1 {
            return;
        }
        let r2 = (r * r) as f32;
        let (xf, yf) = (x as f32, y as f32);
        let n = keypoints.len();
        for row in r0..=r1 {
            let start = self.cell_start[row * GRID_COLS + c0] as usize;
            let end = self.cell_start[row * GRID_COLS + c1 + 1] as usize;
            for e in &self.entries[start..end] {
                if e.octave < min_level || e.octave > max_level {
                    continue;
                }
                let (dx, dy) = (e.x - xf, e.y - yf);
                if dx * dx + dy * dy <= r2 && (e.index as usize) < n {
                    out.push(e.index as usize);
                }
            }
        }
    }
}

/// ORB-SLAM's rotation-consistency check: the angle change of every match
/// goes into one of `bins` bins of `360 / bins` degrees; matches outside the
/// three fullest bins are rejected (the second and third only count when
/// they hold at least a tenth of the fullest).
#[derive(Debug, Clone)]
pub struct RotationHistogram {
    bins: usize,
    counts: Vec<u32>,
    entries: Vec<(u32, usize)>,
}

impl Default for RotationHistogram {
    fn default() -> Self {
        RotationHistogram::new(30)
    }
}

impl RotationHistogram {
    /// A histogram of `bins` bins (ORB-SLAM: 30); at least 1.
    pub fn new(bins: usize) -> Self {
        let bins = bins.max(1);
        RotationHistogram {
            bins,
            counts: vec![0; bins],
            entries: Vec::new(),
        }
    }

    /// Forget every entry.
    pub fn clear(&mut self) {
        self.counts.fill(0);
        self.entries.clear();
    }

    /// Record match `index` whose keypoint angle went from `train_deg` to
    /// `query_deg`.
    pub fn add(&mut self, query_deg: f32, train_deg: f32, index: usize) {
        let mut rot = query_deg - train_deg;
        if !rot.is_finite() {
            rot = 0.0;
        }
        let rot = rot.rem_euclid(360.0);
        let bin = ((rot * self.bins as f32 / 360.0).round() as usize) % self.bins;
        self.counts[bin] += 1;
        self.entries.push((bin as u32, index));
    }

    /// The kept bins, fullest first (up to 3).
    pub fn top_bins(&self) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.bins).filter(|&b| self.counts[b] > 0).collect();
        order.sort_by(|&a, &b| self.counts[b].cmp(&self.counts[a]).then(a.cmp(&b)));
        order.truncate(3);
        if let Some(&first) = order.first() {
            let max1 = self.counts[first] as f32;
            if order.len() > 1 && (self.counts[order[1]] as f32) < 0.1 * max1 {
                order.truncate(1);
            } else if order.len() > 2 && (self.counts[order[2]] as f32) < 0.1 * max1 {
                order.truncate(2);
            }
        }
        order
    }

    /// Indices of the matches outside the kept bins, in insertion order.
    pub fn rejected(&self) -> Vec<usize> {
        let keep = self.top_bins();
        self.entries
            .iter()
            .filter(|(b, _)| !keep.contains(&(*b as usize)))
            .map(|&(_, i)| i)
            .collect()
    }
}

/// Drop from `matches` those whose angle change is inconsistent with the
/// majority ([`RotationHistogram`] with `bins` bins).
pub fn filter_by_rotation(
    matches: &mut Vec<Match>,
    query_kps: &[KeyPoint],
    train_kps: &[KeyPoint],
    bins: usize,
) {
    let mut h = RotationHistogram::new(bins);
    for (i, m) in matches.iter().enumerate() {
        let (Some(q), Some(t)) = (query_kps.get(m.query), train_kps.get(m.train)) else {
            continue;
        };
        h.add(q.angle, t.angle, i);
    }
    let keep_bins = h.top_bins();
    let mut keep = vec![false; matches.len()];
    for &(b, i) in &h.entries {
        keep[i] = keep_bins.contains(&(b as usize));
    }
    let mut k = 0;
    matches.retain(|_| {
        let r = keep[k];
        k += 1;
        r
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    fn random_desc(rng: &mut StdRng) -> Descriptor {
        [rng.random(), rng.random(), rng.random(), rng.random()]
    }

    fn flip_bits(d: &Descriptor, n: usize, rng: &mut StdRng) -> Descriptor {
        let mut out = *d;
        let mut done = std::collections::HashSet::new();
        while done.len() < n {
            let b = rng.random_range(0..256usize);
            if done.insert(b) {
                out[b / 64] ^= 1 << (b % 64);
            }
        }
        out
    }

    #[test]
    fn brute_force_finds_perturbed_copies() {
        let mut rng = StdRng::seed_from_u64(7);
        let train: Vec<Descriptor> = (0..300).map(|_| random_desc(&mut rng)).collect();
        // Queries: noisy copies of train[3 k], plus unrelated ones.
        let mut query = Vec::new();
        for k in 0..100 {
            query.push(flip_bits(&train[3 * k], 20, &mut rng));
        }
        for _ in 0..50 {
            query.push(random_desc(&mut rng));
        }
        let p = Params {
            max_distance: 64,
            ratio: 0.8,
            cross_check: true,
        };
        let m = match_brute_force(&query, &train, &p).unwrap();
        assert_eq!(m.len(), 100, "only the copies match");
        for x in &m {
            assert_eq!(x.train, 3 * x.query);
            assert_eq!(x.distance, 20);
        }
    }

    #[test]
    fn ratio_and_cross_check_reject_ambiguity() {
        let mut rng = StdRng::seed_from_u64(8);
        let a = random_desc(&mut rng);
        let train = vec![flip_bits(&a, 10, &mut rng), flip_bits(&a, 11, &mut rng)];
        let query = vec![a];
        let loose = Params {
            ratio: 1.0,
            ..Params::default()
        };
        assert_eq!(match_brute_force(&query, &train, &loose).unwrap().len(), 1);
        // 10 vs 11 bits: ambiguous under the ratio test.
        assert!(
            match_brute_force(&query, &train, &Params::default())
                .unwrap()
                .is_empty()
        );
        // Two queries wanting the same train: cross-check keeps the closer.
        let t = random_desc(&mut rng);
        let query = vec![flip_bits(&t, 12, &mut rng), flip_bits(&t, 5, &mut rng)];
        let p = Params {
            ratio: 1.0,
            cross_check: true,
            ..Params::default()
        };
        let m = match_brute_force(&query, &[t], &p).unwrap();
        assert_eq!(
            m,
            vec![Match {
                query: 1,
                train: 0,
                distance: 5
            }]
        );
        assert!(match_brute_force(&[], &[t], &p).unwrap().is_empty());
        assert!(
            match_brute_force(&query, &[t], &Params { ratio: 0.0, ..p }).is_err(),
            "ratio 0 refused"
        );
    }

    fn kp(x: f32, y: f32, octave: u8) -> KeyPoint {
        KeyPoint {
            x,
            y,
            ux: x,
            uy: y,
            octave,
            ..KeyPoint::default()
        }
    }

    #[test]
    fn grid_search_equals_linear_scan() {
        let mut rng = StdRng::seed_from_u64(9);
        let kps: Vec<KeyPoint> = (0..2000)
            .map(|_| {
                kp(
                    rng.random_range(-20.0..660.0),
                    rng.random_range(-20.0..500.0),
                    rng.random_range(0..8),
                )
            })
            .collect();
        let b = Bounds {
            min_x: 0.0,
            max_x: 640.0,
            min_y: 0.0,
            max_y: 480.0,
        };
        let inside = |k: &KeyPoint| k.ux >= 0.0 && k.ux < 640.0 && k.uy >= 0.0 && k.uy < 480.0;
        let g = FeatureGrid::new(&kps, b);
        assert_eq!(g.len(), kps.iter().filter(|k| inside(k)).count());
        // Rebuilding storage that held other keypoints gives the same grid.
        let mut reused = FeatureGrid::new(&kps[..700], b);
        reused.rebuild(&kps, b);
        let (mut out, mut out2) = (Vec::new(), Vec::new());
        let mut total = 0;
        for i in 0..300 {
            let (x, y) = if i < 3 {
                // The corners and a point outside.
                [(0.0, 0.0), (639.0, 479.0), (700.0, -40.0)][i]
            } else {
                (
                    rng.random_range(-30.0..670.0),
                    rng.random_range(-30.0..510.0),
                )
            };
            let r = rng.random_range(1.0..60.0);
            let (lo, hi) = (rng.random_range(0..4), rng.random_range(3..8));
            g.features_in_area(&kps, x, y, r, lo, hi, &mut out);
            reused.features_in_area(&kps, x, y, r, lo, hi, &mut out2);
            assert_eq!(out, out2);
            out.sort_unstable();
            let want: Vec<usize> = kps
                .iter()
                .enumerate()
                .filter(|(_, k)| {
                    let d2 = (k.ux as f64 - x).powi(2) + (k.uy as f64 - y).powi(2);
                    inside(k) && d2 <= r * r && (k.octave as i32) >= lo && (k.octave as i32) <= hi
                })
                .map(|(i, _)| i)
                .collect();
            assert_eq!(out, want, "({x}, {y}) r {r} levels {lo}..={hi}");
            total += want.len();
        }
        assert!(total > 1000, "the queries find points: {total}");
        // A keypoint list shorter than the grid's: no index past its end.
        g.features_in_area(&kps[..10], 320.0, 240.0, 400.0, 0, 7, &mut out);
        assert!(!out.is_empty() && out.iter().all(|&i| i < 10));
        // Windows that miss, NaN, degenerate bounds, the empty grid.
        g.features_in_area(&kps, -100.0, 240.0, 30.0, 0, 7, &mut out);
        assert!(out.is_empty());
        g.features_in_area(&kps, f64::NAN, 240.0, 30.0, 0, 7, &mut out);
        assert!(out.is_empty());
        for bad in [
            Bounds { max_x: 0.0, ..b },
            Bounds {
                min_y: f64::NAN,
                ..b
            },
        ] {
            let e = FeatureGrid::new(&kps, bad);
            assert!(e.is_empty());
            e.features_in_area(&kps, 320.0, 240.0, 50.0, 0, 7, &mut out);
            assert!(out.is_empty());
        }
        FeatureGrid::default().features_in_area(&kps, 320.0, 240.0, 50.0, 0, 7, &mut out);
        assert!(out.is_empty());
    }

    #[test]
    fn rotation_histogram_keeps_the_consistent_majority() {
        let mut q = Vec::new();
        let mut t = Vec::new();
        let mut matches = Vec::new();
        // 60 matches rotated by ~36 degrees, 20 by ~264 (second mode), 10 random;
        // both modes sit on bin centres (12-degree bins).
        let mut rng = StdRng::seed_from_u64(10);
        for i in 0..90 {
            let a: f32 = rng.random_range(0.0..360.0);
            let rot = if i < 60 {
                36.0 + rng.random_range(-3.0..3.0)
            } else if i < 80 {
                264.0 + rng.random_range(-2.0..2.0)
            } else {
                rng.random_range(100.0..230.0)
            };
            t.push(KeyPoint {
                angle: a,
                ..KeyPoint::default()
            });
            q.push(KeyPoint {
                angle: (a + rot) % 360.0,
                ..KeyPoint::default()
            });
            matches.push(Match {
                query: i,
                train: i,
                distance: 0,
            });
        }
        let mut kept = matches.clone();
        filter_by_rotation(&mut kept, &q, &t, 30);
        let n_major = kept.iter().filter(|m| m.query < 60).count();
        let n_second = kept.iter().filter(|m| (60..80).contains(&m.query)).count();
        let n_noise = kept.iter().filter(|m| m.query >= 80).count();
        assert!(n_major >= 50, "{n_major}");
        assert!(n_second >= 15, "{n_second}");
        assert!(n_noise <= 3, "{n_noise}");
        let mut h = RotationHistogram::new(30);
        h.add(10.0, 350.0, 0); // wraps to +20 degrees
        assert_eq!(h.top_bins(), vec![2]);
        assert!(h.rejected().is_empty());
    }
}
