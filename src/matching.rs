//! Hamming matching of ORB descriptors.
//!
//! - [`match_brute_force`]: every query against every train descriptor, with
//!   a distance bound, Lowe's ratio test and an optional cross-check, in one
//!   pass over the distance matrix (the reverse best is tracked on the way).
//! - [`FeatureGrid`]: keypoints binned over the image (ORB-SLAM uses 64 x 48
//!   cells) for search by projection: [`FeatureGrid::features_in_area`].
//! - [`RotationHistogram`]: ORB-SLAM's rotation-consistency filter: the
//!   angle differences of the matches go into 30 bins and only the matches of
//!   the (up to) 3 fullest bins are kept.
//!
//! Matching by vocabulary node lives with the vocabulary.

use std::ops::RangeInclusive;

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
    for (qi, q) in query.iter().enumerate() {
        let (mut best, mut second, mut best_t) = (u32::MAX, u32::MAX, 0usize);
        for (ti, (t, rev)) in train.iter().zip(reverse.iter_mut()).enumerate() {
            let d = hamming(q, t);
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
    if params.cross_check {
        out.retain(|m| reverse[m.train].1 as usize == m.query);
    }
    Ok(())
}

/// Keypoints binned in a regular grid over an image region, for search by
/// projection. Uses the undistorted positions `ux, uy`; keypoints outside the
/// region are not indexed.
#[derive(Debug, Clone, Default)]
pub struct FeatureGrid {
    min_x: f32,
    min_y: f32,
    inv_cell_w: f32,
    inv_cell_h: f32,
    cols: usize,
    rows: usize,
    /// `starts[c]..starts[c + 1]` are the entries of cell `c`.
    starts: Vec<u32>,
    /// Keypoint index, x, y, octave per entry, grouped by cell.
    entries: Vec<(u32, f32, f32, u8)>,
}

impl FeatureGrid {
    /// Index `keypoints` in `cols` x `rows` cells over
    /// `[min_x, max_x) x [min_y, max_y)` (ORB-SLAM: 64 x 48 over the
    /// undistorted image bounds).
    pub fn new(
        keypoints: &[KeyPoint],
        (min_x, min_y, max_x, max_y): (f32, f32, f32, f32),
        cols: usize,
        rows: usize,
    ) -> Result<Self, MatchingError> {
        let mut g = FeatureGrid::default();
        g.rebuild(keypoints, (min_x, min_y, max_x, max_y), cols, rows)?;
        Ok(g)
    }

    /// Rebuild in place, reusing the storage.
    pub fn rebuild(
        &mut self,
        keypoints: &[KeyPoint],
        (min_x, min_y, max_x, max_y): (f32, f32, f32, f32),
        cols: usize,
        rows: usize,
    ) -> Result<(), MatchingError> {
        if cols == 0 || rows == 0 || cols * rows > 1 << 20 {
            return Err(MatchingError::InvalidParams {
                name: "cols x rows",
                value: format!("{cols} x {rows}"),
                reason: "must be between 1 and 2^20 cells",
            });
        }
        if !(max_x > min_x && max_y > min_y && min_x.is_finite() && max_x.is_finite())
            || !(min_y.is_finite() && max_y.is_finite())
        {
            return Err(MatchingError::InvalidParams {
                name: "bounds",
                value: format!("[{min_x}, {max_x}) x [{min_y}, {max_y})"),
                reason: "must be a finite, non-empty region",
            });
        }
        self.min_x = min_x;
        self.min_y = min_y;
        self.inv_cell_w = cols as f32 / (max_x - min_x);
        self.inv_cell_h = rows as f32 / (max_y - min_y);
        self.cols = cols;
        self.rows = rows;
        let cell_of = |kp: &KeyPoint| -> Option<usize> {
            let cx = ((kp.ux - min_x) * self.inv_cell_w).floor();
            let cy = ((kp.uy - min_y) * self.inv_cell_h).floor();
            if cx >= 0.0 && cy >= 0.0 && cx < cols as f32 && cy < rows as f32 {
                Some(cy as usize * cols + cx as usize)
            } else {
                None
            }
        };
        self.starts.clear();
        self.starts.resize(cols * rows + 1, 0);
        for kp in keypoints {
            if let Some(c) = cell_of(kp) {
                self.starts[c + 1] += 1;
            }
        }
        for c in 0..cols * rows {
            self.starts[c + 1] += self.starts[c];
        }
        let total = self.starts[cols * rows] as usize;
        self.entries.clear();
        self.entries.resize(total, (0, 0.0, 0.0, 0));
        let mut fill: Vec<u32> = self.starts[..cols * rows].to_vec();
        for (i, kp) in keypoints.iter().enumerate() {
            if let Some(c) = cell_of(kp) {
                self.entries[fill[c] as usize] = (i as u32, kp.ux, kp.uy, kp.octave);
                fill[c] += 1;
            }
        }
        Ok(())
    }

    /// Number of indexed keypoints.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when no keypoint is indexed.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Indices of the keypoints with `|ux - x| < r`, `|uy - y| < r` (ORB-SLAM's
    /// square window) and octave in `octaves`, appended to `out` (cleared
    /// first) in grid order.
    pub fn features_in_area(
        &self,
        x: f32,
        y: f32,
        r: f32,
        octaves: RangeInclusive<u8>,
        out: &mut Vec<usize>,
    ) {
        out.clear();
        if self.cols == 0 || !(r > 0.0) || !x.is_finite() || !y.is_finite() {
            return;
        }
        let c0 = ((x - r - self.min_x) * self.inv_cell_w).floor();
        let c1 = ((x + r - self.min_x) * self.inv_cell_w).floor();
        let r0 = ((y - r - self.min_y) * self.inv_cell_h).floor();
        let r1 = ((y + r - self.min_y) * self.inv_cell_h).floor();
        if c1 < 0.0 || r1 < 0.0 || c0 >= self.cols as f32 || r0 >= self.rows as f32 {
            return;
        }
        let c0 = c0.max(0.0) as usize;
        let r0 = r0.max(0.0) as usize;
        let c1 = (c1 as usize).min(self.cols - 1);
        let r1 = (r1 as usize).min(self.rows - 1);
        let (lo, hi) = (*octaves.start(), *octaves.end());
        for row in r0..=r1 {
            let a = self.starts[row * self.cols + c0] as usize;
            let b = self.starts[row * self.cols + c1 + 1] as usize;
            for &(i, kx, ky, oct) in &self.entries[a..b] {
                if oct >= lo && oct <= hi && (kx - x).abs() < r && (ky - y).abs() < r {
                    out.push(i as usize);
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
        let g = FeatureGrid::new(&kps, (0.0, 0.0, 640.0, 480.0), 64, 48).unwrap();
        let inside = kps
            .iter()
            .filter(|k| k.ux >= 0.0 && k.ux < 640.0 && k.uy >= 0.0 && k.uy < 480.0)
            .count();
        assert_eq!(g.len(), inside);
        let mut out = Vec::new();
        for _ in 0..200 {
            let (x, y) = (
                rng.random_range(-30.0..670.0),
                rng.random_range(-30.0..510.0),
            );
            let r = rng.random_range(1.0..60.0);
            let (lo, hi) = (rng.random_range(0..4u8), rng.random_range(3..8u8));
            g.features_in_area(x, y, r, lo..=hi, &mut out);
            out.sort_unstable();
            let want: Vec<usize> = kps
                .iter()
                .enumerate()
                .filter(|(_, k)| {
                    k.ux >= 0.0
                        && k.ux < 640.0
                        && k.uy >= 0.0
                        && k.uy < 480.0
                        && (k.ux - x).abs() < r
                        && (k.uy - y).abs() < r
                        && k.octave >= lo
                        && k.octave <= hi
                })
                .map(|(i, _)| i)
                .collect();
            assert_eq!(out, want);
        }
        assert!(FeatureGrid::new(&kps, (0.0, 0.0, 0.0, 480.0), 64, 48).is_err());
        assert!(FeatureGrid::new(&kps, (0.0, 0.0, 640.0, 480.0), 0, 48).is_err());
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
