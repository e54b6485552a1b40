//! ORB extraction on teddy frames: 1000 and 2000 features, 1 and 2 threads.
//! Needs `../shared/data` (or `SHOTPILOT_DATA`); falls back to a synthetic
//! texture when absent. The OpenCV peer for the same frames is
//! `benches/peers/orb_opencv.py`.

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, criterion_group, criterion_main};
use image::GrayImage;
use shotpilot::features::{Features, OrbExtractor, Params};
use shotpilot::features_eval as eval;

fn frames() -> Vec<GrayImage> {
    let dir = std::env::var_os("SHOTPILOT_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"))
        .join("tum_fr3_teddy_100");
    match eval::load_dataset_gray(&dir) {
        Ok(f) => f.into_iter().step_by(10).collect(),
        Err(e) => {
            eprintln!("{e}: benchmarking a synthetic texture instead");
            let img = GrayImage::from_fn(640, 480, |x, y| {
                let v = ((x * 7919 + y * 104729) ^ (x * y)) % 251;
                image::Luma([v as u8])
            });
            vec![img]
        }
    }
}

fn bench_extract(c: &mut Criterion) {
    let frames = frames();
    let mut group = c.benchmark_group("orb_extract");
    for n in [1000usize, 2000] {
        for threads in [1usize, 2] {
            let mut ex = match OrbExtractor::new(Params {
                n_features: n,
                threads,
                ..Params::default()
            }) {
                Ok(ex) => ex,
                Err(e) => panic!("bench parameters: {e}"),
            };
            let mut out = Features::default();
            let mut i = 0;
            group.bench_function(format!("teddy_{n}f_{threads}t"), |b| {
                b.iter(|| {
                    let f = &frames[i % frames.len()];
                    i += 1;
                    let _ = ex.extract_into(black_box(f), None, None, &mut out);
                    black_box(out.len())
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_extract);
criterion_main!(benches);
