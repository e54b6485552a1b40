//! The vocabulary tree in flat arrays, and the transform of descriptors into
//! BoW and feature vectors.

use super::vector::{BowVector, FeatureVector, NodeId, WordId};
use super::{BowError, Descriptor, hamming};

/// How word values enter a BoW vector (DBoW2's `WeightingType`, same codes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weighting {
    /// Term frequency times inverse document frequency (code 0): each
    /// occurrence adds the word's idf weight. ORB-SLAM's vocabulary uses it.
    TfIdf,
    /// Term frequency (code 1): each occurrence adds the word's weight (1).
    Tf,
    /// Inverse document frequency (code 2): the word's weight, once.
    Idf,
    /// Binary (code 3): the word's weight (1), once.
    Binary,
}

impl Weighting {
    /// DBoW2's numeric code.
    pub fn code(self) -> u32 {
        match self {
            Weighting::TfIdf => 0,
            Weighting::Tf => 1,
            Weighting::Idf => 2,
            Weighting::Binary => 3,
        }
    }

    /// From DBoW2's numeric code.
    pub fn from_code(code: u32) -> Result<Self, BowError> {
        match code {
            0 => Ok(Weighting::TfIdf),
            1 => Ok(Weighting::Tf),
            2 => Ok(Weighting::Idf),
            3 => Ok(Weighting::Binary),
            _ => Err(BowError::Unsupported {
                what: "weighting",
                code,
                supported: "0 (tf-idf), 1 (tf), 2 (idf), 3 (binary)",
            }),
        }
    }

    /// Whether repeated occurrences of a word add up.
    fn accumulates(self) -> bool {
        matches!(self, Weighting::TfIdf | Weighting::Tf)
    }
}

/// How two BoW vectors compare (DBoW2's `ScoringType`). Only the L1 score
/// (code 0), the one ORB-SLAM uses, is implemented.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scoring {
    /// `1 - 0.5 |v1 - v2|_1` over L1-normalised vectors (code 0).
    L1,
}

impl Scoring {
    /// DBoW2's numeric code.
    pub fn code(self) -> u32 {
        0
    }

    /// From DBoW2's numeric code.
    pub fn from_code(code: u32) -> Result<Self, BowError> {
        match code {
            0 => Ok(Scoring::L1),
            _ => Err(BowError::Unsupported {
                what: "scoring",
                code,
                supported: "0 (L1-norm)",
            }),
        }
    }
}

/// Largest word weight accepted (idf weights are `ln(N / n)`, below 25 for
/// any realistic training set): keeps sums of weights far from overflow.
pub(crate) const MAX_WORD_WEIGHT: f32 = 1e6;

/// The bytes of the default vocabulary (see [`Vocabulary::builtin`]).
const BUILTIN_VOCABULARY: &[u8] = include_bytes!("default_k10_L4.bowvoc");

/// Descriptors walked down the tree together by the batch transform.
const LANES: usize = 4;

/// Marks a node that is not a leaf in `node_word`.
pub(crate) const NO_WORD: u32 = u32::MAX;

/// The flat arrays of a vocabulary, before validation.
pub(crate) struct Parts {
    pub k: u32,
    pub levels: u32,
    pub weighting: Weighting,
    pub scoring: Scoring,
    pub descriptors: Vec<Descriptor>,
    pub first_child: Vec<u32>,
    pub child_count: Vec<u8>,
    pub word_node: Vec<u32>,
    pub word_weight: Vec<f32>,
}

/// A vocabulary tree. Node 0 is the root; the children of node `n` are the
/// contiguous nodes `first_child[n] .. first_child[n] + child_count[n]`, and
/// every child has a larger id than its parent (so descent always ends).
/// Leaves (no children) are the words.
#[derive(Clone, PartialEq)]
pub struct Vocabulary {
    pub(crate) k: u32,
    pub(crate) levels: u32,
    pub(crate) weighting: Weighting,
    pub(crate) scoring: Scoring,
    /// Per node: its centroid (the root's is unused and zero).
    pub(crate) descriptors: Vec<Descriptor>,
    /// Per node: id of its first child (0 for a leaf).
    pub(crate) first_child: Vec<u32>,
    /// Per node: number of children (0 for a leaf).
    pub(crate) child_count: Vec<u8>,
    /// Per node: its word id, or [`NO_WORD`] for inner nodes.
    pub(crate) node_word: Vec<u32>,
    /// Per word: its node.
    pub(crate) word_node: Vec<u32>,
    /// Per word: its weight (idf for TF-IDF).
    pub(crate) word_weight: Vec<f32>,
}

/// The shape only: a vocabulary has up to millions of nodes.
impl std::fmt::Debug for Vocabulary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Vocabulary")
            .field("k", &self.k)
            .field("levels", &self.levels)
            .field("weighting", &self.weighting)
            .field("scoring", &self.scoring)
            .field("nodes", &self.node_count())
            .field("words", &self.word_count())
            .finish()
    }
}

impl Vocabulary {
    /// Assemble and validate a vocabulary from its flat arrays (used by
    /// training and loading). `node_word` is derived from `word_node`.
    pub(crate) fn from_parts(parts: Parts) -> Result<Self, BowError> {
        let Parts {
            k,
            levels,
            weighting,
            scoring,
            descriptors,
            first_child,
            child_count,
            word_node,
            word_weight,
        } = parts;
        let n = descriptors.len();
        let bad = |node: usize, reason: &'static str| BowError::InvalidStructure {
            node: node as u32,
            reason,
        };
        if n == 0 || n > u32::MAX as usize - 1 {
            return Err(bad(0, "node count must be between 1 and 2^32 - 2"));
        }
        if first_child.len() != n || child_count.len() != n {
            return Err(bad(0, "per-node arrays differ in length"));
        }
        if word_node.len() != word_weight.len() {
            return Err(bad(0, "per-word arrays differ in length"));
        }
        if !(2..=255).contains(&k) {
            return Err(bad(0, "branching factor k must be in 2..=255"));
        }
        // Every node but the root must have exactly one parent, with children
        // after their parent; the depth must not exceed `levels`.
        let mut has_parent = vec![false; n];
        let mut depth = vec![0u32; n];
        for node in 0..n {
            let c = child_count[node] as usize;
            if c == 0 {
                continue;
            }
            if c > k as usize {
                return Err(bad(node, "more children than the branching factor"));
            }
            let f = first_child[node] as usize;
            if f <= node || f + c > n {
                return Err(bad(node, "children out of range or not after their parent"));
            }
            if depth[node] >= levels {
                return Err(bad(node, "tree deeper than its level count"));
            }
            for child in f..f + c {
                if has_parent[child] {
                    return Err(bad(child, "node has two parents"));
                }
                has_parent[child] = true;
                depth[child] = depth[node] + 1;
            }
        }
        if let Some(orphan) = (1..n).find(|&i| !has_parent[i]) {
            return Err(bad(orphan, "node has no parent"));
        }
        let mut node_word = vec![NO_WORD; n];
        for (w, &node) in word_node.iter().enumerate() {
            let node = node as usize;
            if node >= n {
                return Err(bad(0, "word refers to a node out of range"));
            }
            if child_count[node] != 0 {
                return Err(bad(
                    node as u32 as usize,
                    "word on a node that has children",
                ));
            }
            if node_word[node] != NO_WORD {
                return Err(bad(node, "leaf holds two words"));
            }
            node_word[node] = w as u32;
        }
        for node in 0..n {
            if child_count[node] == 0 && node_word[node] == NO_WORD {
                return Err(bad(node, "leaf without a word"));
            }
        }
        if let Some(w) = word_weight
            .iter()
            .position(|x| !(0.0..=MAX_WORD_WEIGHT).contains(x))
        {
            return Err(bad(
                word_node[w] as usize,
                "word weight outside 0 ..= 1e6 (or not a number)",
            ));
        }
        Ok(Self {
            k,
            levels,
            weighting,
            scoring,
            descriptors,
            first_child,
            child_count,
            node_word,
            word_node,
            word_weight,
        })
    }

    /// The vocabulary shipped with shotpilot, embedded in the library.
    ///
    #[doc = include_str!("default_vocabulary.md")]
    pub fn builtin() -> Result<Vocabulary, BowError> {
        Vocabulary::from_bytes(BUILTIN_VOCABULARY)
    }

    /// Branching factor `k`.
    pub fn branching(&self) -> u32 {
        self.k
    }

    /// Depth `L` (levels below the root).
    pub fn levels(&self) -> u32 {
        self.levels
    }

    /// Weighting of word values.
    pub fn weighting(&self) -> Weighting {
        self.weighting
    }

    /// Scoring of vector pairs.
    pub fn scoring(&self) -> Scoring {
        self.scoring
    }

    /// Number of nodes, root included.
    pub fn node_count(&self) -> usize {
        self.descriptors.len()
    }

    /// Number of words (leaves).
    pub fn word_count(&self) -> usize {
        self.word_node.len()
    }

    /// Weight of a word, `None` when out of range.
    pub fn word_weight(&self, word: WordId) -> Option<f32> {
        self.word_weight.get(word.0 as usize).copied()
    }

    /// The node of a word, `None` when out of range.
    pub fn word_node(&self, word: WordId) -> Option<NodeId> {
        self.word_node.get(word.0 as usize).map(|&n| NodeId(n))
    }

    /// The word of a node, `None` for inner nodes or out of range.
    pub fn node_word(&self, node: NodeId) -> Option<WordId> {
        match self.node_word.get(node.0 as usize) {
            Some(&w) if w != NO_WORD => Some(WordId(w)),
            _ => None,
        }
    }

    /// The centroid of a node, `None` when out of range.
    pub fn node_descriptor(&self, node: NodeId) -> Option<&[u64; 4]> {
        self.descriptors.get(node.0 as usize)
    }

    /// The children of a node (empty for a leaf or out of range).
    pub fn children(
        &self,
        node: NodeId,
    ) -> impl DoubleEndedIterator<Item = NodeId> + ExactSizeIterator + use<> {
        let n = node.0 as usize;
        let (f, c) = match (self.first_child.get(n), self.child_count.get(n)) {
            (Some(&f), Some(&c)) => (f, u32::from(c)),
            _ => (0, 0),
        };
        (f..f + c).map(NodeId)
    }

    /// Walk one descriptor down the tree: its word, the word's weight, and the
    /// node it passed at `level` (the leaf itself when the leaf is shallower).
    #[inline(always)]
    fn descend(&self, d: &Descriptor, level: u32) -> (u32, u32) {
        let mut node = 0usize;
        let mut depth = 0u32;
        let mut at_level = 0u32;
        loop {
            let count = self.child_count[node] as usize;
            if count == 0 {
                break;
            }
            let first = self.first_child[node] as usize;
            let children = &self.descriptors[first..first + count];
            let mut best = 0usize;
            let mut best_dist = u32::MAX;
            for (i, c) in children.iter().enumerate() {
                let dist = hamming(d, c);
                if dist < best_dist {
                    best_dist = dist;
                    best = i;
                }
            }
            node = first + best;
            depth += 1;
            if depth <= level {
                at_level = node as u32;
            }
        }
        (self.node_word[node], at_level)
    }

    /// The word a descriptor falls into, with its weight.
    pub fn word_of(&self, descriptor: &[u64; 4]) -> (WordId, f32) {
        let (w, _) = self.descend(descriptor, 0);
        (WordId(w), self.word_weight[w as usize])
    }

    /// Turn a descriptor set into its BoW vector.
    pub fn transform(&self, descriptors: &[[u64; 4]]) -> BowVector {
        let mut bow = BowVector::new();
        self.transform_into(descriptors, None, &mut bow);
        bow
    }

    /// Turn a descriptor set into its BoW vector and its feature vector (the
    /// direct index at `level`, counted from the root: ORB-SLAM uses `L - 4`).
    pub fn transform_with_features(
        &self,
        descriptors: &[[u64; 4]],
        level: u32,
    ) -> (BowVector, FeatureVector) {
        let mut bow = BowVector::new();
        let mut fv = FeatureVector::new();
        self.transform_into(descriptors, Some((level, &mut fv)), &mut bow);
        (bow, fv)
    }

    /// The allocation-free form of [`Vocabulary::transform_with_features`]:
    /// clears and fills `bow` and, when given, the feature vector (at its
    /// level). Features whose word has weight 0 (a word seen in every
    /// training image) are left out of both, as DBoW2 does.
    pub fn transform_into(
        &self,
        descriptors: &[[u64; 4]],
        features: Option<(u32, &mut FeatureVector)>,
        bow: &mut BowVector,
    ) {
        bow.entries.clear();
        bow.entries.reserve(descriptors.len());
        match features {
            Some((level, fv)) => {
                fv.pairs.clear();
                fv.pairs.reserve(descriptors.len());
                self.descend_batch(descriptors, level, &mut bow.entries, Some(&mut fv.pairs));
                fv.sort();
            }
            None => self.descend_batch(descriptors, 0, &mut bow.entries, None),
        }
        bow.sort_merge(self.weighting.accumulates());
        bow.normalize_l1();
    }

    /// Walk every descriptor down the tree, appending `(word, weight)` and,
    /// when asked, `(node at level, feature index)` for words of non-zero
    /// weight. Uses the CPU's popcount instruction when it has one.
    pub(crate) fn descend_batch(
        &self,
        descriptors: &[Descriptor],
        level: u32,
        words: &mut Vec<(WordId, f32)>,
        nodes: Option<&mut Vec<(NodeId, u32)>>,
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU supports the `popcnt` feature the callee is
            // compiled for (checked on the line above).
            unsafe { self.descend_batch_popcnt(descriptors, level, words, nodes) };
            return;
        }
        self.descend_batch_body(descriptors, level, words, nodes);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "popcnt")]
    fn descend_batch_popcnt(
        &self,
        descriptors: &[Descriptor],
        level: u32,
        words: &mut Vec<(WordId, f32)>,
        nodes: Option<&mut Vec<(NodeId, u32)>>,
    ) {
        self.descend_batch_body(descriptors, level, words, nodes);
    }

    #[inline(always)]
    fn descend_batch_body(
        &self,
        descriptors: &[Descriptor],
        level: u32,
        words: &mut Vec<(WordId, f32)>,
        mut nodes: Option<&mut Vec<(NodeId, u32)>>,
    ) {
        let mut emit = |i: usize, w: u32, node: u32| {
            let weight = self.word_weight[w as usize];
            if weight > 0.0 {
                words.push((WordId(w), weight));
                if let Some(nodes) = nodes.as_deref_mut() {
                    nodes.push((NodeId(node), i as u32));
                }
            }
        };
        // Groups of LANES descriptors descend together, level by level: their
        // memory accesses are independent, so a large tree's cache misses
        // overlap instead of queueing.
        let mut chunks = descriptors.chunks_exact(LANES);
        let mut base = 0usize;
        for chunk in &mut chunks {
            let mut node = [0usize; LANES];
            let mut at_level = [0u32; LANES];
            let mut depth = 0u32;
            loop {
                let mut moved = false;
                for lane in 0..LANES {
                    let count = self.child_count[node[lane]] as usize;
                    if count == 0 {
                        continue;
                    }
                    moved = true;
                    let first = self.first_child[node[lane]] as usize;
                    let children = &self.descriptors[first..first + count];
                    let d = &chunk[lane];
                    let mut best = 0usize;
                    let mut best_dist = u32::MAX;
                    for (c, child) in children.iter().enumerate() {
                        let dist = hamming(d, child);
                        if dist < best_dist {
                            best_dist = dist;
                            best = c;
                        }
                    }
                    node[lane] = first + best;
                    if depth < level {
                        at_level[lane] = node[lane] as u32;
                    }
                }
                if !moved {
                    break;
                }
                depth += 1;
            }
            for lane in 0..LANES {
                emit(base + lane, self.node_word[node[lane]], at_level[lane]);
            }
            base += LANES;
        }
        for (k, d) in chunks.remainder().iter().enumerate() {
            let (w, node) = self.descend(d, level);
            emit(base + k, w, node);
        }
    }

    /// Score two BoW vectors with the vocabulary's scoring.
    pub fn score(&self, a: &BowVector, b: &BowVector) -> f32 {
        match self.scoring {
            Scoring::L1 => a.l1_score(b),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hand-made k = 2, L = 2 tree:
    /// root -> A (all zeros), B (all ones); A -> A0 (0), A1 (low 8 bits set);
    /// B is a leaf at level 1.
    fn tiny() -> Vocabulary {
        let z = [0u64; 4];
        let ones = [u64::MAX; 4];
        let a1 = [0xff, 0, 0, 0];
        Vocabulary::from_parts(Parts {
            k: 2,
            levels: 2,
            weighting: Weighting::TfIdf,
            scoring: Scoring::L1,
            descriptors: vec![z, z, ones, z, a1],
            first_child: vec![1, 3, 0, 0, 0],
            child_count: vec![2, 2, 0, 0, 0],
            word_node: vec![2, 3, 4],
            word_weight: vec![1.0, 2.0, 0.0],
        })
        .expect("valid tree")
    }

    #[test]
    fn descend_picks_nearest_children() {
        let v = tiny();
        assert_eq!(v.word_of(&[0x1, 0, 0, 0]).0, WordId(1)); // A0 node 3
        assert_eq!(v.word_of(&[0x7f, 0, 0, 0]).0, WordId(2)); // A1 node 4
        assert_eq!(v.word_of(&[u64::MAX, 0xffff, 0, 0]).0, WordId(2)); // 80 ones: A side, then A1 (72 < 80)
        assert_eq!(v.word_of(&[u64::MAX, u64::MAX, u64::MAX, 1]).0, WordId(0)); // B leaf
    }

    #[test]
    fn transform_weights_normalises_and_indexes() {
        let v = tiny();
        let descs = [
            [0x1, 0, 0, 0],                           // word 1 (w=2), level-1 node 1
            [u64::MAX, u64::MAX, u64::MAX, u64::MAX], // word 0 (w=1), node 2
            [0x3, 0, 0, 0],                           // word 1 again
            [0xfe, 0, 0, 0],                          // word 2, weight 0: dropped
        ];
        let (bow, fv) = v.transform_with_features(&descs, 1);
        assert_eq!(bow.entries(), &[(WordId(0), 0.2), (WordId(1), 0.8)]);
        assert_eq!(
            fv.pairs(),
            &[(NodeId(1), 0), (NodeId(1), 2), (NodeId(2), 1)]
        );
        // Level 2: the leaves themselves (B is a leaf at level 1).
        let (_, fv2) = v.transform_with_features(&descs, 2);
        assert_eq!(
            fv2.pairs(),
            &[(NodeId(2), 1), (NodeId(3), 0), (NodeId(3), 2)]
        );
        assert!(v.transform(&[]).is_empty());
    }

    #[test]
    fn batch_descent_agrees_with_single_descent() {
        use rand::rngs::SmallRng;
        use rand::{Rng, SeedableRng};
        let mut rng = SmallRng::seed_from_u64(4);
        let images: Vec<Vec<Descriptor>> = (0..3)
            .map(|_| (0..400).map(|_| rng.random()).collect())
            .collect();
        let params = crate::bow::TrainParams {
            k: 5,
            levels: 4,
            seed: 1,
            max_iterations: 10,
        };
        let v = Vocabulary::train(&images, &params, &mut |_| {}).expect("train");
        // 103 descriptors: 25 groups of 4 and a remainder of 3.
        let probe: Vec<Descriptor> = (0..103).map(|_| rng.random()).collect();
        let mut words = Vec::new();
        let mut nodes = Vec::new();
        v.descend_batch(&probe, 2, &mut words, Some(&mut nodes));
        let single: Vec<(u32, u32)> = probe
            .iter()
            .map(|d| v.descend(d, 2))
            .filter(|&(w, _)| v.word_weight[w as usize] > 0.0)
            .collect();
        let batch: Vec<(u32, u32)> = words
            .iter()
            .zip(&nodes)
            .map(|(w, n)| (w.0.0, n.0.0))
            .collect();
        assert!(single.len() > 50);
        assert_eq!(batch, single);
    }

    #[test]
    fn builtin_vocabulary_loads() {
        let v = Vocabulary::builtin().expect("embedded vocabulary");
        assert_eq!((v.branching(), v.levels()), (10, 4));
        assert_eq!((v.node_count(), v.word_count()), (11_111, 10_000));
        assert_eq!(v.weighting(), Weighting::TfIdf);
        assert!(v.word_weight.iter().all(|&w| w > 0.0 && w < 10.0));
    }

    #[test]
    fn from_parts_rejects_broken_trees() {
        let z = [0u64; 4];
        // a leaf without a word
        let e = Vocabulary::from_parts(Parts {
            k: 2,
            levels: 2,
            weighting: Weighting::TfIdf,
            scoring: Scoring::L1,
            descriptors: vec![z, z, z],
            first_child: vec![1, 0, 0],
            child_count: vec![2, 0, 0],
            word_node: vec![1],
            word_weight: vec![1.0],
        });
        assert!(matches!(e, Err(BowError::InvalidStructure { node: 2, .. })));
        let e = Vocabulary::from_parts(Parts {
            k: 2,
            levels: 1,
            weighting: Weighting::TfIdf,
            scoring: Scoring::L1,
            descriptors: vec![z, z, z],
            first_child: vec![1, 0, 0],
            child_count: vec![2, 0, 0],
            word_node: vec![1, 2],
            word_weight: vec![1.0, f32::NAN],
        });
        assert!(matches!(e, Err(BowError::InvalidStructure { node: 2, .. })));
    }
}
