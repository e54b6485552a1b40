//! Properties: the L1 score against its dense definition, and loading never
//! panics on damaged files, even when the damage carries a valid checksum.

use proptest::prelude::*;
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use shotpilot::bow::{BowVector, TrainParams, Vocabulary, WordId, checksum};

fn bow_strategy() -> impl Strategy<Value = BowVector> {
    prop::collection::vec((0u32..40, 0.01f32..5.0), 0..30)
        .prop_map(|p| BowVector::from_weights(p.into_iter().map(|(w, x)| (WordId(w), x))))
}

fn dense(v: &BowVector) -> Vec<f64> {
    let mut d = vec![0.0; 40];
    for &(w, x) in v.entries() {
        d[w.0 as usize] = f64::from(x);
    }
    d
}

proptest! {
    #[test]
    fn l1_score_is_one_minus_half_l1_distance(a in bow_strategy(), b in bow_strategy()) {
        let s = a.l1_score(&b);
        let (da, db) = (dense(&a), dense(&b));
        let dist: f64 = da.iter().zip(&db).map(|(x, y)| (x - y).abs()).sum();
        if !a.is_empty() && !b.is_empty() {
            prop_assert!((f64::from(s) - (1.0 - 0.5 * dist)).abs() < 1e-5, "{s} vs {dist}");
        } else {
            prop_assert_eq!(s, 0.0);
        }
        prop_assert!((a.l1_score(&b) - b.l1_score(&a)).abs() < 1e-7);
        prop_assert!((-1e-6..=1.0 + 1e-6).contains(&s));
    }
}

fn small_vocabulary_bytes() -> Vec<u8> {
    let mut rng = SmallRng::seed_from_u64(1);
    let images: Vec<Vec<[u64; 4]>> = (0..4)
        .map(|_| (0..150).map(|_| rng.random()).collect())
        .collect();
    let params = TrainParams {
        k: 3,
        levels: 3,
        seed: 2,
        max_iterations: 5,
    };
    Vocabulary::train(&images, &params, &mut |_| {})
        .unwrap()
        .to_bytes()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(400))]
    #[test]
    fn damaged_files_with_valid_checksums_load_or_fail_cleanly(
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..6),
        probe in any::<[u64; 4]>(),
    ) {
        let mut bytes = small_vocabulary_bytes();
        let body = bytes.len() - 8;
        // Damage the header's counts and the tree arrays, then re-seal.
        for (at, value) in edits {
            let i = 8 + at.index(body - 8);
            bytes[i] = value;
        }
        let sum = checksum(&bytes[..body]);
        bytes[body..].copy_from_slice(&sum.to_le_bytes());
        if let Ok(v) = Vocabulary::from_bytes(&bytes) {
            // A tree that passed validation must transform without panicking.
            let bow = v.transform(&[probe, [0; 4], [u64::MAX; 4]]);
            prop_assert!(bow.entries().iter().all(|e| e.1.is_finite()));
        }
    }
}
