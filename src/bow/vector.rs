//! BoW vectors (word -> weight) and feature vectors (node -> feature indices).

/// Index of a word (a leaf of the vocabulary tree), `0 .. word_count`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct WordId(pub u32);

/// Index of a node of the vocabulary tree; the root is node 0.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct NodeId(pub u32);

/// A sparse bag-of-words vector: `(word, value)` pairs sorted by word id with
/// no duplicates; the values of a vector made by
/// [`Vocabulary::transform`](super::Vocabulary::transform) are positive and
/// sum to 1 (L1-normalised).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BowVector {
    pub(crate) entries: Vec<(WordId, f32)>,
}

impl BowVector {
    /// An empty vector.
    pub fn new() -> Self {
        Self::default()
    }

    /// Build a vector from `(word, value)` pairs in any order: values of
    /// repeated words add up; values count by magnitude; zero and non-finite
    /// values are dropped; the result is L1-normalised (an all-zero input
    /// gives an empty vector).
    pub fn from_weights(pairs: impl IntoIterator<Item = (WordId, f32)>) -> Self {
        let mut v = Self {
            entries: pairs
                .into_iter()
                .filter(|(_, x)| x.is_finite() && *x != 0.0)
                .map(|(w, x)| (w, x.abs()))
                .collect(),
        };
        v.sort_merge(true);
        v.normalize_l1();
        v
    }

    /// Number of distinct words.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// True when no word is present.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The `(word, value)` pairs, sorted by word.
    pub fn entries(&self) -> &[(WordId, f32)] {
        &self.entries
    }

    /// The value of `word`, 0 when absent.
    pub fn get(&self, word: WordId) -> f32 {
        self.entries
            .binary_search_by_key(&word, |e| e.0)
            .map_or(0.0, |i| self.entries[i].1)
    }

    /// Remove all words, keeping the allocation.
    pub fn clear(&mut self) {
        self.entries.clear();
    }

    /// DBoW2's L1 score of two L1-normalised vectors,
    /// `1 - 0.5 * |a - b|_1`, in `[0, 1]`.
    ///
    /// For non-negative normalised vectors this equals the sum over the
    /// common words of `min(a_w, b_w)`, which is what the merge computes.
    pub fn l1_score(&self, other: &BowVector) -> f32 {
        let (a, b) = (&self.entries, &other.entries);
        let (mut i, mut j) = (0, 0);
        let mut score = 0.0f64;
        while i < a.len() && j < b.len() {
            let (wa, va) = a[i];
            let (wb, vb) = b[j];
            match wa.cmp(&wb) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    score += f64::from(va.min(vb));
                    i += 1;
                    j += 1;
                }
            }
        }
        score as f32
    }

    /// Sort by word and merge repeated words: add their values when
    /// `accumulate`, else keep the first value.
    pub(crate) fn sort_merge(&mut self, accumulate: bool) {
        let e = &mut self.entries;
        e.sort_unstable_by_key(|p| p.0);
        let mut out = 0usize;
        for i in 0..e.len() {
            if out > 0 && e[out - 1].0 == e[i].0 {
                if accumulate {
                    e[out - 1].1 += e[i].1;
                }
            } else {
                e[out] = e[i];
                out += 1;
            }
        }
        e.truncate(out);
    }

    /// Divide by the sum of the values (no change when it is 0).
    pub(crate) fn normalize_l1(&mut self) {
        let sum: f64 = self.entries.iter().map(|e| f64::from(e.1.abs())).sum();
        if sum > 0.0 {
            for e in &mut self.entries {
                e.1 = (f64::from(e.1) / sum) as f32;
            }
        }
    }
}

/// The direct index of one image: for each vocabulary node at a chosen level,
/// the indices (into the image's descriptor slice) of the features whose path
/// down the tree went through that node. Stored flat as `(node, feature)`
/// pairs sorted by node, then feature.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FeatureVector {
    pub(crate) pairs: Vec<(NodeId, u32)>,
}

impl FeatureVector {
    /// An empty feature vector.
    pub fn new() -> Self {
        Self::default()
    }

    /// Total number of features indexed.
    pub fn feature_count(&self) -> usize {
        self.pairs.len()
    }

    /// True when no feature is indexed.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// Remove everything, keeping the allocation.
    pub fn clear(&mut self) {
        self.pairs.clear();
    }

    /// The `(node, feature)` pairs, sorted.
    pub fn pairs(&self) -> &[(NodeId, u32)] {
        &self.pairs
    }

    /// The nodes with their features, in increasing node order.
    pub fn nodes(&self) -> impl Iterator<Item = (NodeId, FeatureIndices<'_>)> + '_ {
        self.pairs
            .chunk_by(|a, b| a.0 == b.0)
            .map(|g| (g[0].0, FeatureIndices(g)))
    }

    /// The nodes present in both feature vectors with the features of each
    /// side, in increasing node order: the candidate pairs of BoW-guided
    /// matching.
    pub fn common_nodes<'a>(
        &'a self,
        other: &'a FeatureVector,
    ) -> impl Iterator<Item = (NodeId, FeatureIndices<'a>, FeatureIndices<'a>)> + 'a {
        let mut a = self.nodes().peekable();
        let mut b = other.nodes().peekable();
        std::iter::from_fn(move || {
            loop {
                let (na, nb) = (a.peek()?.0, b.peek()?.0);
                match na.cmp(&nb) {
                    std::cmp::Ordering::Less => {
                        a.next();
                    }
                    std::cmp::Ordering::Greater => {
                        b.next();
                    }
                    std::cmp::Ordering::Equal => {
                        let (_, fa) = a.next()?;
                        let (_, fb) = b.next()?;
                        return Some((na, fa, fb));
                    }
                }
            }
        })
    }

    pub(crate) fn sort(&mut self) {
        self.pairs.sort_unstable();
    }
}

/// The feature indices stored under one node of a [`FeatureVector`].
#[derive(Debug, Clone, Copy)]
pub struct FeatureIndices<'a>(&'a [(NodeId, u32)]);

impl<'a> FeatureIndices<'a> {
    /// Number of features.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// True when there is none (never for indices yielded by a feature vector).
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The feature indices, increasing.
    pub fn iter(&self) -> impl ExactSizeIterator<Item = u32> + 'a {
        self.0.iter().map(|p| p.1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bow(p: &[(u32, f32)]) -> BowVector {
        BowVector::from_weights(p.iter().map(|&(w, x)| (WordId(w), x)))
    }

    #[test]
    fn from_weights_merges_sorts_and_normalises() {
        let v = bow(&[(5, 1.0), (2, 2.0), (5, 1.0), (9, 0.0)]);
        assert_eq!(v.entries(), &[(WordId(2), 0.5), (WordId(5), 0.5)]);
        assert_eq!(v.get(WordId(9)), 0.0);
        assert!(bow(&[(1, 0.0)]).is_empty());
    }

    #[test]
    fn l1_score_matches_definition() {
        let a = bow(&[(1, 0.2), (3, 0.3), (7, 0.5)]);
        let b = bow(&[(3, 0.6), (7, 0.1), (8, 0.3)]);
        // |a-b|_1 = 0.2 + 0.3 + 0.4 + 0.3 = 1.2 -> 1 - 0.6 = 0.4
        assert!((a.l1_score(&b) - 0.4).abs() < 1e-6);
        assert!((a.l1_score(&a) - 1.0).abs() < 1e-6);
        assert_eq!(a.l1_score(&BowVector::new()), 0.0);
        let c = bow(&[(2, 1.0)]);
        assert_eq!(a.l1_score(&c), 0.0);
    }

    #[test]
    fn common_nodes_walks_the_intersection() {
        let a = FeatureVector {
            pairs: vec![
                (NodeId(1), 0),
                (NodeId(1), 4),
                (NodeId(3), 1),
                (NodeId(9), 2),
            ],
        };
        let b = FeatureVector {
            pairs: vec![
                (NodeId(2), 0),
                (NodeId(3), 5),
                (NodeId(3), 6),
                (NodeId(9), 1),
            ],
        };
        let got: Vec<(u32, Vec<u32>, Vec<u32>)> = a
            .common_nodes(&b)
            .map(|(n, fa, fb)| (n.0, fa.iter().collect(), fb.iter().collect()))
            .collect();
        assert_eq!(got, vec![(3, vec![1], vec![5, 6]), (9, vec![2], vec![1])]);
        assert_eq!(a.nodes().count(), 3);
    }
}
