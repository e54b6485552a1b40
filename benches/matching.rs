//! Matching hot paths: brute force 1000 x 1000 with ratio test and
//! cross-check, Hamming distance pair by pair, grid search by projection,
//! rotation histogram.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use rand::{Rng, SeedableRng, rngs::StdRng};
use shotpilot::features::{Descriptor, KeyPoint};
use shotpilot::matching::{self, Bounds, FeatureGrid, Match, Params, RotationHistogram};

fn descriptors(n: usize, rng: &mut StdRng) -> Vec<Descriptor> {
    (0..n)
        .map(|_| [rng.random(), rng.random(), rng.random(), rng.random()])
        .collect()
}

fn bench_matching(c: &mut Criterion) {
    let mut rng = StdRng::seed_from_u64(1);
    let train = descriptors(1000, &mut rng);
    // Queries: half are noisy copies of train descriptors.
    let mut query = descriptors(1000, &mut rng);
    for (k, q) in query.iter_mut().enumerate().take(500) {
        *q = train[2 * k];
        q[0] ^= rng.random::<u64>() & rng.random::<u64>() & rng.random::<u64>();
    }
    let p = Params {
        cross_check: true,
        ..Params::default()
    };
    let (mut rev, mut out) = (Vec::new(), Vec::new());
    c.bench_function("brute_force_1000x1000_ratio_crosscheck", |b| {
        b.iter(|| {
            let _ = matching::match_brute_force_into(
                black_box(&query),
                black_box(&train),
                &p,
                &mut rev,
                &mut out,
            );
            black_box(out.len())
        })
    });

    // Pair by pair, as the SLAM's searches by projection call it: the
    // runtime-dispatched `hamming` (POPCNT when the CPU has it) against the
    // portable `count_ones`, which the default x86-64 target compiles
    // without POPCNT.
    c.bench_function("hamming_pairs_1000x100_dispatched", |b| {
        b.iter(|| {
            let mut sum = 0u32;
            for q in &query {
                for t in &train[..100] {
                    sum = sum.wrapping_add(shotpilot::features::hamming(black_box(q), t));
                }
            }
            black_box(sum)
        })
    });
    c.bench_function("hamming_pairs_1000x100_portable", |b| {
        b.iter(|| {
            let mut sum = 0u32;
            for q in &query {
                for t in &train[..100] {
                    sum = sum.wrapping_add(shotpilot::features::hamming_portable(black_box(q), t));
                }
            }
            black_box(sum)
        })
    });

    let kps: Vec<KeyPoint> = (0..2000)
        .map(|_| {
            let (x, y) = (
                rng.random_range(0.0..640.0f32),
                rng.random_range(0.0..480.0f32),
            );
            KeyPoint {
                x,
                y,
                ux: x,
                uy: y,
                octave: rng.random_range(0..8),
                angle: rng.random_range(0.0..360.0),
                ..KeyPoint::default()
            }
        })
        .collect();
    let bounds = Bounds {
        min_x: 0.0,
        max_x: 640.0,
        min_y: 0.0,
        max_y: 480.0,
    };
    let mut grid = FeatureGrid::default();
    c.bench_function("feature_grid_build_2000", |b| {
        b.iter(|| {
            grid.rebuild(black_box(&kps), bounds);
            black_box(grid.len())
        })
    });
    let mut found = Vec::new();
    c.bench_function("feature_grid_1000_queries_r15", |b| {
        b.iter(|| {
            let mut total = 0;
            for k in kps.iter().take(1000) {
                grid.features_in_area(
                    &kps,
                    k.ux as f64 + 3.0,
                    k.uy as f64 - 2.0,
                    15.0,
                    0,
                    7,
                    &mut found,
                );
                total += found.len();
            }
            black_box(total)
        })
    });
    let matches: Vec<Match> = (0..1000)
        .map(|i| Match {
            query: i,
            train: (i * 7) % 2000,
            distance: 30,
        })
        .collect();
    c.bench_function("rotation_filter_1000", |b| {
        b.iter(|| {
            let mut m = matches.clone();
            matching::filter_by_rotation(&mut m, &kps, &kps, 30);
            black_box(m.len())
        })
    });
    let mut h = RotationHistogram::new(30);
    c.bench_function("rotation_histogram_add_1000", |b| {
        b.iter(|| {
            h.clear();
            for (i, k) in kps.iter().take(1000).enumerate() {
                h.add(k.angle, 10.0, i);
            }
            black_box(h.top_bins())
        })
    });
}

criterion_group!(benches, bench_matching);
criterion_main!(benches);
