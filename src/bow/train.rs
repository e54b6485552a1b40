//! Vocabulary training: hierarchical k-majority clustering with k-means++
//! seeding, then TF-IDF word weights from the training images.

use std::collections::VecDeque;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::vocabulary::{Parts, Scoring, Vocabulary, Weighting};
use super::{BowError, Descriptor, hamming};

/// Training parameters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrainParams {
    /// Branching factor `k` (children per node), 2..=255. DBoW2/ORB-SLAM: 10.
    pub k: u32,
    /// Depth `L` (levels below the root), 1..=16. ORB-SLAM: 6.
    pub levels: u32,
    /// Seed of the k-means++ seeding.
    pub seed: u64,
    /// Most assignment/update rounds of k-majority per node; the clustering
    /// stops earlier when no assignment changes.
    pub max_iterations: u32,
}

impl Default for TrainParams {
    fn default() -> Self {
        Self {
            k: 10,
            levels: 6,
            seed: 0,
            max_iterations: 25,
        }
    }
}

/// The phases of a training run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrainPhase {
    /// Building the tree; units are descriptor-levels.
    Clustering,
    /// Counting the images each word occurs in; units are images.
    Weighting,
}

impl TrainPhase {
    /// A short lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            TrainPhase::Clustering => "clustering",
            TrainPhase::Weighting => "weighting",
        }
    }
}

/// Progress of a training run, reported through the caller's callback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrainProgress {
    /// The phase running.
    pub phase: TrainPhase,
    /// Units done.
    pub done: u64,
    /// Units in the phase (for clustering an upper bound, `descriptors * L`,
    /// reached at the end of the phase).
    pub total: u64,
}

impl Vocabulary {
    /// Train a vocabulary on the descriptors of a set of images.
    ///
    /// Each node's descriptors are split into up to `k` clusters by k-majority
    /// (k-means with Hamming distance and bitwise-majority centroids, seeded by
    /// k-means++); a node with at most `k` distinct descriptors gets one child
    /// per distinct descriptor. Clusters become leaves at depth `L` or when
    /// all their descriptors are equal. Word weights are the inverse document
    /// frequencies `ln(N / n_w)` over the `N` images (`n_w` images contain
    /// word `w`); a word in every image gets weight 0 and is ignored by
    /// [`Vocabulary::transform`]. The same inputs and seed give the same
    /// vocabulary.
    pub fn train<I: AsRef<[[u64; 4]]>>(
        images: &[I],
        params: &TrainParams,
        progress: &mut dyn FnMut(TrainProgress),
    ) -> Result<Vocabulary, BowError> {
        if !(2..=255).contains(&params.k) {
            return Err(BowError::InvalidParam {
                name: "k",
                value: params.k.to_string(),
                reason: "must be in 2..=255",
            });
        }
        if !(1..=16).contains(&params.levels) {
            return Err(BowError::InvalidParam {
                name: "levels",
                value: params.levels.to_string(),
                reason: "must be in 1..=16",
            });
        }
        if images.len() < 2 {
            return Err(BowError::NotEnoughTrainingData {
                what: "images",
                found: images.len(),
                needed: 2,
            });
        }
        let total: usize = images.iter().map(|i| i.as_ref().len()).sum();
        if total < params.k as usize {
            return Err(BowError::NotEnoughTrainingData {
                what: "descriptors",
                found: total,
                needed: params.k as usize,
            });
        }
        if total >= u32::MAX as usize {
            return Err(BowError::InvalidParam {
                name: "descriptors",
                value: total.to_string(),
                reason: "at most 2^32 - 2 training descriptors",
            });
        }
        let mut all: Vec<Descriptor> = Vec::with_capacity(total);
        for img in images {
            all.extend_from_slice(img.as_ref());
        }

        let k = params.k as usize;
        let mut rng = StdRng::seed_from_u64(params.seed);
        let mut clusterer = Clusterer::new(k, params.max_iterations);
        let mut descriptors: Vec<Descriptor> = vec![[0; 4]];
        let mut first_child: Vec<u32> = vec![0];
        let mut child_count: Vec<u8> = vec![0];
        let clustering_total = total as u64 * u64::from(params.levels);
        let mut done = 0u64;
        progress(TrainProgress {
            phase: TrainPhase::Clustering,
            done,
            total: clustering_total,
        });

        // Breadth first, so node ids grow level by level and the children of a
        // node are created together (contiguous ids).
        let mut queue: VecDeque<(usize, u32, Vec<u32>)> = VecDeque::new();
        queue.push_back((0, 0, (0..total as u32).collect()));
        while let Some((node, depth, members)) = queue.pop_front() {
            let clusters = clusterer.cluster(&all, &members, &mut rng);
            done += members.len() as u64;
            drop(members);
            let first = descriptors.len();
            first_child[node] = first as u32;
            child_count[node] = clusters.len() as u8;
            for (i, (center, m)) in clusters.into_iter().enumerate() {
                descriptors.push(center);
                first_child.push(0);
                child_count.push(0);
                if depth + 1 < params.levels && !all_equal(&all, &m) {
                    queue.push_back((first + i, depth + 1, m));
                } else {
                    // A leaf: its descriptors are done for the deeper levels too.
                    done += m.len() as u64 * u64::from(params.levels - depth - 1);
                }
            }
            progress(TrainProgress {
                phase: TrainPhase::Clustering,
                done,
                total: clustering_total,
            });
        }

        let word_node: Vec<u32> = (0..descriptors.len() as u32)
            .filter(|&n| child_count[n as usize] == 0)
            .collect();
        let word_weight = vec![1.0f32; word_node.len()];
        let mut voc = Vocabulary::from_parts(Parts {
            k: params.k,
            levels: params.levels,
            weighting: Weighting::TfIdf,
            scoring: Scoring::L1,
            descriptors,
            first_child,
            child_count,
            word_node,
            word_weight,
        })?;

        // Inverse document frequencies.
        let n_images = images.len();
        let mut images_with_word = vec![0u32; voc.word_count()];
        let mut last_image = vec![u32::MAX; voc.word_count()];
        let mut words = Vec::new();
        for (i, img) in images.iter().enumerate() {
            words.clear();
            // All weights are 1 here, so every descriptor yields its word.
            voc.descend_batch(img.as_ref(), 0, &mut words, None);
            for &(w, _) in &words {
                let w = w.0 as usize;
                if last_image[w] != i as u32 {
                    last_image[w] = i as u32;
                    images_with_word[w] += 1;
                }
            }
            progress(TrainProgress {
                phase: TrainPhase::Weighting,
                done: i as u64 + 1,
                total: n_images as u64,
            });
        }
        for (weight, &n) in voc.word_weight.iter_mut().zip(&images_with_word) {
            *weight = if n > 0 {
                (n_images as f64 / f64::from(n)).ln() as f32
            } else {
                0.0
            };
        }
        Ok(voc)
    }
}

fn all_equal(all: &[Descriptor], members: &[u32]) -> bool {
    match members.split_first() {
        None => true,
        Some((&first, rest)) => rest.iter().all(|&m| all[m as usize] == all[first as usize]),
    }
}

/// k-majority clustering of one node's descriptors, with reusable buffers.
struct Clusterer {
    k: usize,
    max_iterations: u32,
    dist2: Vec<u64>,
    assignment: Vec<u32>,
    counts: Vec<[u32; 256]>,
    sizes: Vec<u32>,
}

impl Clusterer {
    fn new(k: usize, max_iterations: u32) -> Self {
        Self {
            k,
            max_iterations,
            dist2: Vec::new(),
            assignment: Vec::new(),
            counts: vec![[0; 256]; k],
            sizes: vec![0; k],
        }
    }

    /// Split `members` (indices into `all`) into at most `k` non-empty
    /// clusters, returned with their centroids in seeding order. Uses the
    /// CPU's popcount instruction when it has one.
    fn cluster(
        &mut self,
        all: &[Descriptor],
        members: &[u32],
        rng: &mut StdRng,
    ) -> Vec<(Descriptor, Vec<u32>)> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU supports the `popcnt` feature the callee is
            // compiled for (checked on the line above).
            return unsafe { self.cluster_popcnt(all, members, rng) };
        }
        self.cluster_body(all, members, rng)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "popcnt")]
    fn cluster_popcnt(
        &mut self,
        all: &[Descriptor],
        members: &[u32],
        rng: &mut StdRng,
    ) -> Vec<(Descriptor, Vec<u32>)> {
        self.cluster_body(all, members, rng)
    }

    #[inline(always)]
    fn cluster_body(
        &mut self,
        all: &[Descriptor],
        members: &[u32],
        rng: &mut StdRng,
    ) -> Vec<(Descriptor, Vec<u32>)> {
        if members.len() <= self.k {
            // One child per distinct descriptor.
            let mut sorted: Vec<u32> = members.to_vec();
            sorted.sort_unstable_by_key(|&m| (all[m as usize], m));
            return sorted
                .chunk_by(|&a, &b| all[a as usize] == all[b as usize])
                .map(|g| (all[g[0] as usize], g.to_vec()))
                .collect();
        }
        let mut centers = self.seed_kmeanspp(all, members, rng);
        let n = members.len();
        self.assignment.clear();
        self.assignment.resize(n, u32::MAX);
        let mut iteration = 0u32;
        loop {
            // Assignment step (ties go to the lower center index).
            let mut changed = false;
            for (slot, &m) in self.assignment.iter_mut().zip(members) {
                let d = &all[m as usize];
                let mut best = 0u32;
                let mut best_dist = u32::MAX;
                for (j, c) in centers.iter().enumerate() {
                    let dist = hamming(d, c);
                    if dist < best_dist {
                        best_dist = dist;
                        best = j as u32;
                    }
                }
                if *slot != best {
                    *slot = best;
                    changed = true;
                }
            }
            if !changed || iteration >= self.max_iterations {
                break;
            }
            iteration += 1;
            // Update step: bitwise majority of each cluster.
            let kc = centers.len();
            for c in &mut self.counts[..kc] {
                c.fill(0);
            }
            self.sizes[..kc].fill(0);
            for (&a, &m) in self.assignment.iter().zip(members) {
                let counts = &mut self.counts[a as usize];
                self.sizes[a as usize] += 1;
                let d = &all[m as usize];
                for (w, &word) in d.iter().enumerate() {
                    let c = &mut counts[w * 64..w * 64 + 64];
                    for (b, cb) in c.iter_mut().enumerate() {
                        *cb += ((word >> b) & 1) as u32;
                    }
                }
            }
            for (j, center) in centers.iter_mut().enumerate() {
                let size = self.sizes[j];
                if size == 0 {
                    continue; // an empty cluster keeps its centroid
                }
                let counts = &self.counts[j];
                let mut out = [0u64; 4];
                for (w, word) in out.iter_mut().enumerate() {
                    for b in 0..64 {
                        if 2 * counts[w * 64 + b] > size {
                            *word |= 1 << b;
                        }
                    }
                }
                *center = out;
            }
        }
        let mut groups: Vec<Vec<u32>> = vec![Vec::new(); centers.len()];
        for (&a, &m) in self.assignment.iter().zip(members) {
            groups[a as usize].push(m);
        }
        centers
            .into_iter()
            .zip(groups)
            .filter(|(_, g)| !g.is_empty())
            .collect()
    }

    /// k-means++ seeding: the first center uniformly, each next one with
    /// probability proportional to the squared Hamming distance to the
    /// nearest center so far. Stops early when every descriptor coincides
    /// with a center.
    #[inline(always)]
    fn seed_kmeanspp(
        &mut self,
        all: &[Descriptor],
        members: &[u32],
        rng: &mut StdRng,
    ) -> Vec<Descriptor> {
        let mut centers = Vec::with_capacity(self.k);
        let first = all[members[rng.random_range(0..members.len())] as usize];
        centers.push(first);
        self.dist2.clear();
        self.dist2.extend(members.iter().map(|&m| {
            let d = u64::from(hamming(&all[m as usize], &first));
            d * d
        }));
        while centers.len() < self.k {
            let total: u64 = self.dist2.iter().sum();
            if total == 0 {
                break;
            }
            let r = rng.random_range(0..total);
            let mut acc = 0u64;
            let mut pick = members.len() - 1;
            for (i, &d2) in self.dist2.iter().enumerate() {
                acc += d2;
                if acc > r {
                    pick = i;
                    break;
                }
            }
            let c = all[members[pick] as usize];
            centers.push(c);
            for (d2, &m) in self.dist2.iter_mut().zip(members) {
                let d = u64::from(hamming(&all[m as usize], &c));
                *d2 = (*d2).min(d * d);
            }
        }
        centers
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::SmallRng;

    /// `n` descriptors around each of `protos`, each bit flipped with
    /// probability `p`.
    fn noisy(protos: &[Descriptor], n: usize, p: f64, rng: &mut SmallRng) -> Vec<Descriptor> {
        let mut out = Vec::new();
        for proto in protos {
            for _ in 0..n {
                let mut d = *proto;
                for w in d.iter_mut() {
                    for b in 0..64 {
                        if rng.random_bool(p) {
                            *w ^= 1 << b;
                        }
                    }
                }
                out.push(d);
            }
        }
        out
    }

    #[test]
    fn clustering_recovers_separated_prototypes() {
        let mut rng = SmallRng::seed_from_u64(3);
        let protos: Vec<Descriptor> = (0..4).map(|_| rng.random()).collect();
        // Four images, each holding noisy copies of all prototypes.
        let images: Vec<Vec<Descriptor>> =
            (0..4).map(|_| noisy(&protos, 50, 0.05, &mut rng)).collect();
        let params = TrainParams {
            k: 4,
            levels: 1,
            seed: 11,
            max_iterations: 25,
        };
        let voc = Vocabulary::train(&images, &params, &mut |_| {}).expect("train");
        assert_eq!(voc.word_count(), 4);
        // Each prototype lands in its own word, and the centroid is the
        // prototype itself (majority over 200 copies with 5% noise).
        let mut words: Vec<u32> = protos.iter().map(|p| voc.word_of(p).0.0).collect();
        for p in &protos {
            let (w, _) = voc.word_of(p);
            let node = voc.word_node(w).expect("node");
            let c = voc.node_descriptor(node).expect("descriptor");
            assert!(hamming(c, p) <= 2, "centroid {} bits off", hamming(c, p));
        }
        words.sort_unstable();
        words.dedup();
        assert_eq!(words.len(), 4);
        // Every word is in every image: idf = ln(4/4) = 0.
        assert!((0..4).all(|w| voc.word_weight(super::super::WordId(w)) == Some(0.0)));
    }

    #[test]
    fn training_is_seeded_and_idf_counts_images() {
        let mut rng = SmallRng::seed_from_u64(5);
        let protos: Vec<Descriptor> = (0..40).map(|_| rng.random()).collect();
        // Image i holds exact copies of prototypes i*10 .. i*10+20
        // (overlapping neighbours), so each prototype ends in a leaf of its own.
        let images: Vec<Vec<Descriptor>> = (0..3)
            .map(|i| noisy(&protos[i * 10..i * 10 + 20], 5, 0.0, &mut rng))
            .collect();
        let params = TrainParams {
            k: 5,
            levels: 4,
            seed: 1,
            max_iterations: 25,
        };
        let a = Vocabulary::train(&images, &params, &mut |_| {}).expect("train");
        let b = Vocabulary::train(&images, &params, &mut |_| {}).expect("train");
        assert_eq!(a, b);
        let c = Vocabulary::train(
            &images,
            &TrainParams {
                seed: 2,
                ..params.clone()
            },
            &mut |_| {},
        )
        .expect("train");
        assert_ne!(a, c);
        // Prototype 0 only appears in image 0 -> idf ln(3); prototype 15 in
        // images 0 and 1 -> ln(1.5).
        let (_, w0) = a.word_of(&protos[0]);
        let (_, w15) = a.word_of(&protos[15]);
        assert!((w0 - 3f32.ln()).abs() < 1e-6, "w0 {w0}");
        assert!((w15 - 1.5f32.ln()).abs() < 1e-6, "w15 {w15}");
    }

    #[test]
    fn training_rejects_bad_input() {
        let one = vec![vec![[0u64; 4]; 20]];
        let e = Vocabulary::train(&one, &TrainParams::default(), &mut |_| {});
        assert!(matches!(
            e,
            Err(BowError::NotEnoughTrainingData { what: "images", .. })
        ));
        let two = vec![vec![[0u64; 4]; 20]; 2];
        let e = Vocabulary::train(
            &two,
            &TrainParams {
                k: 1,
                ..TrainParams::default()
            },
            &mut |_| {},
        );
        assert!(matches!(e, Err(BowError::InvalidParam { name: "k", .. })));
        // All-equal descriptors: a single word.
        let v = Vocabulary::train(&two, &TrainParams::default(), &mut |_| {}).expect("train");
        assert_eq!(v.word_count(), 1);
    }
}
