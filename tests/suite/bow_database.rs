//! Place recognition on a synthetic trajectory: a camera moves along a strip
//! of "world" descriptors; image `i` sees 500 consecutive world points from
//! `40 i` on, each with 16 of its 256 bits flipped (a new observation). Two
//! images are covisible when they see common points (`|i - j| < 12.5`).

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use shotpilot::bow::{CandidateParams, KeyFrameDatabase, KeyFrameId, TrainParams, Vocabulary};

type Descriptor = [u64; 4];

const STEP: usize = 40;
const PER_IMAGE: usize = 500;

struct World {
    points: Vec<Descriptor>,
    rng: SmallRng,
}

impl World {
    fn new(seed: u64, n: usize) -> Self {
        let mut rng = SmallRng::seed_from_u64(seed);
        let points = (0..n).map(|_| rng.random()).collect();
        Self { points, rng }
    }

    fn image(&mut self, i: usize) -> Vec<Descriptor> {
        (0..PER_IMAGE)
            .map(|j| {
                let mut d = self.points[(i * STEP + j) % self.points.len()];
                for _ in 0..16 {
                    let b = self.rng.random_range(0..256u32);
                    d[(b / 64) as usize] ^= 1 << (b % 64);
                }
                d
            })
            .collect()
    }
}

fn covisible(i: usize, j: usize) -> bool {
    i.abs_diff(j) * STEP < PER_IMAGE
}

#[test]
fn non_keyframes_retrieve_covisible_keyframes() {
    // 400 frames; the vocabulary is trained on every 8th frame.
    let mut world = World::new(5, 400 * STEP + PER_IMAGE);
    let train: Vec<Vec<Descriptor>> = (0..400).step_by(8).map(|i| world.image(i)).collect();
    let params = TrainParams {
        k: 10,
        levels: 4,
        seed: 3,
        max_iterations: 15,
    };
    let voc = Vocabulary::train(&train, &params, &mut |_| {}).unwrap();

    // Keyframes every 5th frame.
    let mut db = KeyFrameDatabase::new(voc.word_count());
    for i in (0..400).step_by(5) {
        let img = world.image(i);
        db.add(KeyFrameId(i as u64), voc.transform(&img)).unwrap();
    }
    let mut hits = 0;
    let mut nearest = 0;
    let mut queries = 0;
    let mut cand_hits = 0;
    for i in (0..400).filter(|i| i % 5 != 0) {
        let q = voc.transform(&world.image(i));
        let top = db.query(&q, 5);
        queries += 1;
        if top.first().is_some_and(|r| covisible(i, r.id.0 as usize)) {
            hits += 1;
        }
        // The keyframes bracketing frame i are within 4 frames of it.
        if top
            .first()
            .is_some_and(|r| (r.id.0 as usize).abs_diff(i) < 5)
        {
            nearest += 1;
        }
        let cands = db.detect_candidates(
            &q,
            &CandidateParams::default(),
            |_| false,
            |id, out| {
                let k = id.0 as i64;
                for d in [5i64, -5, 10, -10, 15, -15, 20, -20, 25, -25] {
                    if (0..400).contains(&(k + d)) {
                        out.push(KeyFrameId((k + d) as u64));
                    }
                }
            },
        );
        if cands.first().is_some_and(|c| covisible(i, c.id.0 as usize)) {
            cand_hits += 1;
        }
    }
    let rate = hits as f64 / queries as f64;
    let cand_rate = cand_hits as f64 / queries as f64;
    eprintln!(
        "top-1 covisible: {hits}/{queries}; top-1 bracketing: {nearest}/{queries}; \
         best candidate covisible: {cand_hits}/{queries}"
    );
    assert!(
        nearest as f64 >= 0.9 * queries as f64,
        "top-1 bracketing {nearest}/{queries}"
    );
    assert!(rate >= 0.95, "top-1 covisible rate {rate}");
    assert!(cand_rate >= 0.95, "candidate covisible rate {cand_rate}");

    // A removed keyframe is never returned again.
    let q = voc.transform(&world.image(101));
    let best = db.query(&q, 1)[0].id;
    db.remove(best).unwrap();
    assert!(db.query(&q, 100).iter().all(|r| r.id != best));
    assert_eq!(db.len(), 79);
}
