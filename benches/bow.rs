//! Bag-of-words hot paths: descriptor -> BoW transform, vocabulary loading,
//! DBoW2 text import, keyframe database queries.
//!
//! Synthetic data: a "world" of random 256-bit prototype descriptors; an image
//! at trajectory position `i` observes 1000 consecutive prototypes starting at
//! `50 i`, each with 16 random bits flipped (ORB descriptors of one point seen
//! twice typically differ by a few tens of bits). Two vocabularies:
//! - `trained`: k = 10, L = 6, trained on 60 such images (60 000 descriptors);
//! - `full`: a complete random k = 10, L = 6 tree (1 111 111 nodes, 10^6
//!   words), the shape of ORB-SLAM's `ORBvoc.txt`, built through the DBoW2
//!   text importer; every descriptor walks the full 6 levels, DBoW2's case.

use std::hint::black_box;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use shotpilot::bow::{CandidateParams, KeyFrameDatabase, KeyFrameId, TrainParams, Vocabulary};

type Descriptor = [u64; 4];

const WORLD: usize = 60_000;
const PER_IMAGE: usize = 1000;
const STEP: usize = 50;
const NOISE_BITS: u32 = 16;

fn world(seed: u64) -> Vec<Descriptor> {
    let mut rng = SmallRng::seed_from_u64(seed);
    (0..WORLD).map(|_| rng.random()).collect()
}

fn image(world: &[Descriptor], pos: usize, rng: &mut SmallRng) -> Vec<Descriptor> {
    (0..PER_IMAGE)
        .map(|j| {
            let mut d = world[(pos * STEP + j) % world.len()];
            for _ in 0..NOISE_BITS {
                let bit = rng.random_range(0..256u32);
                d[(bit / 64) as usize] ^= 1u64 << (bit % 64);
            }
            d
        })
        .collect()
}

fn trained_vocabulary(world: &[Descriptor], levels: u32) -> Vocabulary {
    let mut rng = SmallRng::seed_from_u64(2);
    let images: Vec<Vec<Descriptor>> = (0..60).map(|i| image(world, i * 19, &mut rng)).collect();
    let t = Instant::now();
    let params = TrainParams {
        levels,
        ..TrainParams::default()
    };
    let voc = Vocabulary::train(&images, &params, &mut |_| {}).expect("training on synthetic data");
    eprintln!(
        "trained k=10 L={levels} on 60 x 1000 descriptors in {:.2} s: {} nodes, {} words, {} bytes",
        t.elapsed().as_secs_f64(),
        voc.node_count(),
        voc.word_count(),
        voc.to_bytes().len()
    );
    voc
}

/// A complete k = 10, L = 6 tree with random centroids, as DBoW2 text.
fn full_tree_text() -> Vec<u8> {
    use std::io::Write;
    let mut rng = SmallRng::seed_from_u64(7);
    let mut out = Vec::with_capacity(130 << 20);
    writeln!(out, "10 6 0 0").expect("vec write");
    // Breadth first: level l has 10^l nodes; parents of level l + 1 are the
    // nodes of level l in order.
    let mut level_start = 0u64; // id of the first node of the current level
    let mut level_len = 1u64;
    let mut next_id = 1u64;
    for level in 1..=6u32 {
        for p in 0..level_len {
            for _ in 0..10 {
                let parent = level_start + p;
                write!(out, "{} {}", parent, u8::from(level == 6)).expect("vec write");
                for _ in 0..32 {
                    write!(out, " {}", rng.random::<u8>()).expect("vec write");
                }
                let w = if level == 6 {
                    rng.random_range(0.1..8.0)
                } else {
                    0.0
                };
                writeln!(out, " {w:.6}").expect("vec write");
                next_id += 1;
            }
        }
        level_start = next_id - level_len * 10;
        level_len *= 10;
    }
    out
}

fn bench_bow(c: &mut Criterion) {
    let w = world(1);
    let voc = trained_vocabulary(&w, 6);
    let mut rng = SmallRng::seed_from_u64(3);
    let query_img = image(&w, 517, &mut rng);

    let mut g = c.benchmark_group("bow");
    g.sample_size(30);
    g.measurement_time(std::time::Duration::from_secs(3));
    g.warm_up_time(std::time::Duration::from_millis(500));

    g.bench_function("transform_1000_trained_k10_L6", |b| {
        b.iter(|| black_box(voc.transform(black_box(&query_img))))
    });
    g.bench_function("transform_with_features_1000_trained_k10_L6", |b| {
        b.iter(|| black_box(voc.transform_with_features(black_box(&query_img), 2)))
    });

    // Native file load of the trained vocabulary.
    let bytes = voc.to_bytes();
    g.bench_function("load_bytes_trained_k10_L6", |b| {
        b.iter(|| black_box(Vocabulary::from_bytes(black_box(&bytes)).expect("load")))
    });

    // Full-size tree: DBoW2 text import (timed once), transform and load.
    let text = full_tree_text();
    let t = Instant::now();
    let full = Vocabulary::from_dbow2_text(&text).expect("import full tree");
    eprintln!(
        "imported full k=10 L=6 DBoW2 text ({} MB, {} nodes, {} words) in {:.2} s",
        text.len() >> 20,
        full.node_count(),
        full.word_count(),
        t.elapsed().as_secs_f64()
    );
    drop(text);
    g.bench_function("transform_1000_full_k10_L6", |b| {
        b.iter(|| black_box(full.transform(black_box(&query_img))))
    });
    let full_bytes = full.to_bytes();
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("full.bowvoc");
    full.save(&path).expect("save");
    eprintln!("full tree native file: {} bytes", full_bytes.len());
    drop(full_bytes);
    g.sample_size(10);
    g.bench_function("load_file_full_k10_L6", |b| {
        b.iter(|| black_box(Vocabulary::load(black_box(&path)).expect("load")))
    });
    drop(full);
    g.sample_size(30);

    // Keyframe database: 1000 keyframes along the trajectory; the query is
    // an image between two keyframes. With the L = 6 vocabulary (60 000
    // words) and with an L = 4 one (about 10 000 words: longer inverted
    // lists, the shipped default's shape).
    let voc4 = trained_vocabulary(&w, 4);
    for (name, v) in [("L6", &voc), ("L4", &voc4)] {
        let mut db = KeyFrameDatabase::new(v.word_count());
        for i in 0..1000u64 {
            let img = image(&w, i as usize, &mut rng);
            db.add(KeyFrameId(i), v.transform(&img)).expect("add");
        }
        let q = v.transform(&query_img);
        let top = db.query(&q, 10);
        eprintln!(
            "{name}: query top-3 of 1000 keyframes for position 517: {:?}",
            &top[..3.min(top.len())]
        );
        g.bench_function(format!("db_query_top10_1000kf_{name}"), |b| {
            b.iter(|| black_box(db.query(black_box(&q), 10)))
        });
        let params = CandidateParams::default();
        let covisible = |id: KeyFrameId, out: &mut Vec<KeyFrameId>| {
            // The ten nearest keyframes along the trajectory.
            let i = id.0 as i64;
            for d in [1i64, -1, 2, -2, 3, -3, 4, -4, 5, -5] {
                if (0..1000).contains(&(i + d)) {
                    out.push(KeyFrameId((i + d) as u64));
                }
            }
        };
        let cands = db.detect_candidates(&q, &params, |_| false, covisible);
        eprintln!("{name}: covisibility-grouped candidates: {cands:?}");
        g.bench_function(format!("db_detect_candidates_1000kf_{name}"), |b| {
            b.iter(|| black_box(db.detect_candidates(black_box(&q), &params, |_| false, covisible)))
        });
    }
    g.bench_function("transform_1000_trained_k10_L4", |b| {
        b.iter(|| black_box(voc4.transform(black_box(&query_img))))
    });

    // The built-in vocabulary (k = 10, L = 4, embedded): load time, and
    // the transform of a real frame (TUM fr3/teddy frame 52, 1000 ORB
    // features, when ../shared/data is present).
    let builtin = Vocabulary::builtin().expect("builtin");
    let builtin_bytes = builtin.to_bytes();
    g.bench_function("load_bytes_builtin_k10_L4", |b| {
        b.iter(|| black_box(Vocabulary::from_bytes(black_box(&builtin_bytes)).expect("load")))
    });
    if let Some(teddy) = ["../shared/data", "../../shared/data"]
        .iter()
        .map(|r| {
            std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join(r)
                .join("tum_fr3_teddy_100")
        })
        .find(|p| p.is_dir())
    {
        let ds = shotpilot::video::dataset::Dataset::open(&teddy).expect("teddy");
        let mut orb =
            shotpilot::features::OrbExtractor::new(shotpilot::features::Params::default())
                .expect("orb");
        let frame = orb
            .extract(&ds.frame(52).expect("frame").image, None)
            .descriptors;
        eprintln!("teddy frame 52: {} descriptors", frame.len());
        g.bench_function("transform_teddy_frame_builtin_k10_L4", |b| {
            b.iter(|| black_box(builtin.transform(black_box(&frame))))
        });
        g.bench_function("transform_with_features_teddy_frame_builtin_k10_L4", |b| {
            b.iter(|| black_box(builtin.transform_with_features(black_box(&frame), 2)))
        });
    }
    g.finish();
}

criterion_group!(benches, bench_bow);
criterion_main!(benches);
