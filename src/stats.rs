//! Order statistics of samples: the median and nearest-rank quantiles, used
//! by the SLAM (scene median depth), the evaluation reports and the tests.
//!
//! Every function ignores NaN values (they have no rank) and keeps the
//! infinities (an infinite error is a failure that must show in a
//! percentile), except the `finite_` ones, which drop the infinities too. Each works on a copy and runs in linear time
//! (`select_nth_unstable_by`); the input is never reordered. An input with
//! no value left gives `None`.

/// The median: the middle value of the sorted sample, or the mean of the two
/// middle values when their number is even (the textbook definition).
/// `None` when no value is left after dropping NaN.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut v = without_nan(values);
    let n = v.len();
    if n == 0 {
        return None;
    }
    let (low, upper, _) = v.select_nth_unstable_by(n / 2, f64::total_cmp);
    let upper = *upper;
    if n % 2 == 1 {
        return Some(upper);
    }
    // `low` holds the n / 2 values at or below the upper middle one; its
    // largest is the lower middle value.
    let lower = low.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(0.5 * (lower + upper))
}

/// The nearest-rank quantile `q` in `[0, 1]`: the smallest value such that at
/// least a fraction `q` of the sample lies at or below it (rank
/// `ceil(q n)`, at least 1). `quantile(v, 0.5)` is the lower median
/// (ORB-SLAM's scene median depth), `quantile(v, 1.0)` the maximum and
/// `quantile(v, 0.0)` the minimum. `None` when no value is left after
/// dropping NaN, or when `q` is outside `[0, 1]` or NaN.
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    if !(0.0..=1.0).contains(&q) {
        return None;
    }
    let mut v = without_nan(values);
    let n = v.len();
    if n == 0 {
        return None;
    }
    // The product can land just above an integer it stands for (0.07 * 100
    // is 7.000000000000001): a tolerance far below 1 / n keeps that rank.
    let rank = ((q * n as f64 - 1e-9).ceil() as usize).clamp(1, n);
    let (_, value, _) = v.select_nth_unstable_by(rank - 1, f64::total_cmp);
    Some(*value)
}

/// The median and the maximum, as the tests report a distribution of
/// errors. `None` when no value is left after dropping NaN.
pub fn median_max(values: &[f64]) -> Option<(f64, f64)> {
    Some((median(values)?, quantile(values, 1.0)?))
}

/// [`median`] of the finite values only: the infinities are dropped too (a
/// frame or a trial without a figure has no rank), for the refinement
/// loop's averages over frames. `None` when no value is finite.
pub fn finite_median(values: &[f64]) -> Option<f64> {
    median(&finite(values))
}

/// [`quantile`] of the finite values only (the infinities dropped too, as
/// in [`finite_median`]). `None` when no value is finite or `q` is outside
/// `[0, 1]`.
pub fn finite_quantile(values: &[f64], q: f64) -> Option<f64> {
    quantile(&finite(values), q)
}

fn finite(values: &[f64]) -> Vec<f64> {
    values.iter().copied().filter(|x| x.is_finite()).collect()
}

fn without_nan(values: &[f64]) -> Vec<f64> {
    values.iter().copied().filter(|x| !x.is_nan()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    /// The definitions written out on a sorted copy, to compare with.
    fn sorted(values: &[f64]) -> Vec<f64> {
        let mut s = without_nan(values);
        s.sort_by(f64::total_cmp);
        s
    }

    #[test]
    fn median_of_odd_and_even_samples() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&[7.0]), Some(7.0));
        assert_eq!(median(&[-1.0, 5.0]), Some(2.0));
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[f64::NAN, f64::NAN]), None);
        // NaN is dropped, not ranked: the median of {1, 2, 9}.
        assert_eq!(median(&[9.0, f64::NAN, 1.0, 2.0]), Some(2.0));
        // Infinities count.
        assert_eq!(
            median(&[1.0, f64::INFINITY, f64::INFINITY]),
            Some(f64::INFINITY)
        );
        // Repeated values.
        assert_eq!(median(&[2.0, 2.0, 2.0, 5.0]), Some(2.0));
    }

    #[test]
    fn finite_ones_drop_the_infinities() {
        let v = [f64::INFINITY, 3.0, f64::NAN, 1.0, f64::NEG_INFINITY, 2.0];
        assert_eq!(finite_median(&v), Some(2.0));
        // Two failures among four: the median is infinite, the finite one
        // the middle of what was measured.
        let w = [f64::INFINITY, 1.0, f64::INFINITY, 2.0, f64::NAN];
        assert_eq!(median(&w), Some(f64::INFINITY));
        assert_eq!(finite_median(&w), Some(1.5));
        assert_eq!(finite_median(&[4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(finite_median(&[f64::INFINITY, f64::NAN]), None);
        assert_eq!(finite_median(&[]), None);
        assert_eq!(finite_quantile(&v, 1.0), Some(3.0));
        assert_eq!(quantile(&v, 1.0), Some(f64::INFINITY));
        assert_eq!(finite_quantile(&v, 0.0), Some(1.0));
        assert_eq!(finite_quantile(&[f64::INFINITY], 0.5), None);
        assert_eq!(finite_quantile(&v, 1.5), None);
    }

    #[test]
    fn nearest_rank_quantiles() {
        let v: Vec<f64> = (1..=10).rev().map(f64::from).collect();
        assert_eq!(quantile(&v, 0.0), Some(1.0));
        assert_eq!(quantile(&v, 0.1), Some(1.0));
        assert_eq!(quantile(&v, 0.11), Some(2.0));
        assert_eq!(quantile(&v, 0.5), Some(5.0), "lower median");
        assert_eq!(quantile(&v, 0.9), Some(9.0));
        assert_eq!(quantile(&v, 0.95), Some(10.0));
        assert_eq!(quantile(&v, 1.0), Some(10.0));
        assert_eq!(quantile(&[4.0, 8.0, 6.0], 0.5), Some(6.0));
        // 0.07 * 100 is 7.000000000000001 in floating point; the rank is 7.
        let hundred: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(quantile(&hundred, 0.07), Some(7.0));
        assert_eq!(quantile(&v, 1.5), None);
        assert_eq!(quantile(&v, -0.1), None);
        assert_eq!(quantile(&v, f64::NAN), None);
        assert_eq!(quantile(&[], 0.5), None);
        assert_eq!(quantile(&[f64::NAN, 3.0], 0.0), Some(3.0));
        assert_eq!(median_max(&[3.0, 1.0, 2.0, 10.0]), Some((2.5, 10.0)));
        assert_eq!(median_max(&[f64::NAN]), None);
    }

    #[test]
    fn agrees_with_the_sorted_definitions_and_leaves_the_input_alone() {
        let mut rng = StdRng::seed_from_u64(3);
        for n in 1..60usize {
            // Few distinct values, so ties are common.
            let v: Vec<f64> = (0..n)
                .map(|_| {
                    if rng.random_range(0..10) == 0 {
                        f64::NAN
                    } else {
                        f64::from(rng.random_range(-5..6i32)) * 0.5
                    }
                })
                .collect();
            let before: Vec<u64> = v.iter().map(|x| x.to_bits()).collect();
            let s = sorted(&v);
            let m = s.len();
            let want_median = match m {
                0 => None,
                _ if m % 2 == 1 => Some(s[m / 2]),
                _ => Some(0.5 * (s[m / 2 - 1] + s[m / 2])),
            };
            assert_eq!(median(&v), want_median, "{v:?}");
            for pct in [0usize, 5, 7, 25, 50, 70, 75, 90, 95, 100] {
                // Nearest rank: the smallest value with at least q m values
                // at or below it (in integers: 100 count >= pct m).
                let want = s
                    .iter()
                    .copied()
                    .find(|&x| 100 * s.iter().filter(|&&y| y <= x).count() >= pct * m);
                let q = pct as f64 / 100.0;
                assert_eq!(quantile(&v, q), want, "q {q} of {v:?}");
            }
            let after: Vec<u64> = v.iter().map(|x| x.to_bits()).collect();
            assert_eq!(before, after, "input untouched");
        }
    }
}
