//! A DBoW2 text vocabulary (ORB-SLAM's `ORBvoc.txt` format) written here from
//! a trained vocabulary imports to the same tree and scores identically.

use std::fmt::Write as _;

use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use shotpilot::bow::{NodeId, TrainParams, Vocabulary, WordId};

type Descriptor = [u64; 4];

fn images(seed: u64, n: usize) -> Vec<Vec<Descriptor>> {
    let mut rng = SmallRng::seed_from_u64(seed);
    let world: Vec<Descriptor> = (0..3000).map(|_| rng.random()).collect();
    (0..n)
        .map(|i| {
            (0..400)
                .map(|j| {
                    let mut d = world[(i * 150 + j) % world.len()];
                    for _ in 0..12 {
                        let b = rng.random_range(0..256u32);
                        d[(b / 64) as usize] ^= 1 << (b % 64);
                    }
                    d
                })
                .collect()
        })
        .collect()
}

/// Write `voc` as DBoW2 text, numbering nodes depth first (unlike the
/// native breadth-first layout). Returns the text and, for each native word,
/// the word id DBoW2 gives it (leaves numbered in file order).
fn to_dbow2_text(voc: &Vocabulary) -> (String, Vec<u32>) {
    let mut text = format!("{} {} 0 0\n", voc.branching(), voc.levels());
    let mut dbow_word = vec![u32::MAX; voc.word_count()];
    let mut next_word = 0u32;
    let mut next_id = 1u32;
    // Stack of (native node, DBoW2 id of its parent); children pushed in
    // reverse so they come out in order.
    let mut stack: Vec<(NodeId, u32)> = voc.children(NodeId(0)).rev().map(|c| (c, 0)).collect();
    while let Some((node, parent)) = stack.pop() {
        let id = next_id;
        next_id += 1;
        let word = voc.node_word(node);
        write!(text, "{} {}", parent, u8::from(word.is_some())).unwrap();
        let d = voc.node_descriptor(node).unwrap();
        for j in 0..32 {
            write!(text, " {}", (d[j / 8] >> (8 * (j % 8))) & 0xff).unwrap();
        }
        match word {
            Some(w) => {
                writeln!(text, " {}", voc.word_weight(w).unwrap()).unwrap();
                dbow_word[w.0 as usize] = next_word;
                next_word += 1;
            }
            None => text.push_str(" 0\n"),
        }
        for c in voc.children(node).rev() {
            stack.push((c, id));
        }
    }
    (text, dbow_word)
}

#[test]
fn dbow2_text_imports_and_scores_like_native() {
    let train = images(1, 40);
    let params = TrainParams {
        k: 6,
        levels: 4,
        seed: 17,
        max_iterations: 15,
    };
    let native = Vocabulary::train(&train, &params, &mut |_| {}).unwrap();
    assert!(native.word_count() > 500, "{} words", native.word_count());
    let (text, dbow_word) = to_dbow2_text(&native);
    let imported = Vocabulary::from_dbow2_text(text.as_bytes()).unwrap();

    // Same shape; breadth-first renumbering of a depth-first file gives the
    // native node layout back.
    assert_eq!(imported.node_count(), native.node_count());
    assert_eq!(imported.word_count(), native.word_count());
    assert_eq!((imported.branching(), imported.levels()), (6, 4));
    for n in 0..native.node_count() as u32 {
        let n = NodeId(n);
        assert_eq!(imported.node_descriptor(n), native.node_descriptor(n));
        assert!(imported.children(n).eq(native.children(n)));
    }
    // Word ids follow DBoW2's file order; the weights carry over exactly.
    for w in 0..native.word_count() as u32 {
        let iw = WordId(dbow_word[w as usize]);
        assert_eq!(imported.word_node(iw), native.word_node(WordId(w)));
        assert_eq!(imported.word_weight(iw), native.word_weight(WordId(w)));
    }

    // Fresh images (other noise): identical BoW vectors up to the word
    // renumbering, identical feature vectors, identical scores.
    let test = images(2, 12);
    let nat: Vec<_> = test
        .iter()
        .map(|d| native.transform_with_features(d, 2))
        .collect();
    let imp: Vec<_> = test
        .iter()
        .map(|d| imported.transform_with_features(d, 2))
        .collect();
    for ((nb, nf), (ib, if_)) in nat.iter().zip(&imp) {
        assert!(!nb.is_empty());
        assert_eq!(nf, if_);
        let mut mapped: Vec<(WordId, f32)> = nb
            .entries()
            .iter()
            .map(|&(w, x)| (WordId(dbow_word[w.0 as usize]), x))
            .collect();
        mapped.sort_by_key(|e| e.0);
        assert_eq!(mapped.len(), ib.len());
        for (a, b) in mapped.iter().zip(ib.entries()) {
            assert_eq!(a.0, b.0);
            assert!((a.1 - b.1).abs() < 1e-6);
        }
    }
    let mut max_score = 0.0f32;
    for i in 0..test.len() {
        for j in 0..test.len() {
            let sn = native.score(&nat[i].0, &nat[j].0);
            let si = imported.score(&imp[i].0, &imp[j].0);
            assert!((sn - si).abs() < 1e-5, "pair {i},{j}: {sn} vs {si}");
            if i != j {
                max_score = max_score.max(sn);
            }
        }
    }
    // Neighbouring images overlap, so scores are not trivially zero.
    assert!(max_score > 0.05, "max cross score {max_score}");

    // And the imported vocabulary survives the native file format.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("imported.bowvoc");
    imported.save(&path).unwrap();
    assert_eq!(Vocabulary::load(&path).unwrap(), imported);
}
