//! Keyframe database: an inverted index word -> (keyframe, weight), queried
//! for similar keyframes and for ORB-SLAM's covisibility-grouped candidates.

use std::collections::HashMap;

use super::BowError;
use super::vector::BowVector;

/// A keyframe id chosen by the caller; the database treats it as opaque.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct KeyFrameId(pub u64);

/// One answer of [`KeyFrameDatabase::query`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct QueryResult {
    /// The keyframe.
    pub id: KeyFrameId,
    /// L1 score against the query, in `[0, 1]`.
    pub score: f32,
}

/// One answer of [`KeyFrameDatabase::detect_candidates`]: the best keyframe
/// of a covisibility group.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    /// The best-scoring keyframe of the group.
    pub id: KeyFrameId,
    /// Its own L1 score against the query.
    pub score: f32,
    /// The group's accumulated score (the keyframe the group was built
    /// around plus its covisible neighbours that are candidates themselves).
    pub group_score: f32,
}

/// Parameters of the covisibility-grouped candidate search (ORB-SLAM's
/// `DetectRelocalizationCandidates` / `DetectLoopCandidates`).
#[derive(Debug, Clone, PartialEq)]
pub struct CandidateParams {
    /// A keyframe is scored only when it shares more than this fraction of
    /// the largest number of words any keyframe shares with the query (0.8).
    pub min_common_words_ratio: f32,
    /// How many of the best covisible neighbours of a keyframe form its
    /// group (10).
    pub covisible_neighbours: usize,
    /// Groups are kept when their accumulated score exceeds this fraction of
    /// the best group's (0.75).
    pub min_group_score_ratio: f32,
    /// Keyframes scoring below this are not candidates (0 for
    /// relocalisation; loop detection uses the lowest score between the
    /// query keyframe and its covisible neighbours).
    pub min_score: f32,
}

impl Default for CandidateParams {
    fn default() -> Self {
        Self {
            min_common_words_ratio: 0.8,
            covisible_neighbours: 10,
            min_group_score_ratio: 0.75,
            min_score: 0.0,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Posting {
    slot: u32,
    weight: f32,
}

#[derive(Debug, Clone)]
struct Entry {
    id: KeyFrameId,
    bow: BowVector,
}

/// Per-query accumulator of one slot: partial L1 score and words in common.
#[derive(Debug, Clone, Copy, Default)]
struct Acc {
    score: f32,
    common: u32,
}

/// Inverted index over the BoW vectors of a set of keyframes.
///
/// Keyframes live in slots; a removed keyframe's slot is reused. Queries
/// accumulate the L1 score `sum_w min(q_w, v_w)` word by word through the
/// inverted lists, so they only touch keyframes that share a word with the
/// query.
#[derive(Clone)]
pub struct KeyFrameDatabase {
    inverted: Vec<Vec<Posting>>,
    slots: Vec<Option<Entry>>,
    free: Vec<u32>,
    by_id: HashMap<KeyFrameId, u32>,
}

/// The sizes only: the index holds a posting per keyframe word.
impl std::fmt::Debug for KeyFrameDatabase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KeyFrameDatabase")
            .field("keyframes", &self.len())
            .field("words", &self.inverted.len())
            .field(
                "postings",
                &self.inverted.iter().map(Vec::len).sum::<usize>(),
            )
            .finish()
    }
}

impl KeyFrameDatabase {
    /// An empty database for a vocabulary of `word_count` words.
    pub fn new(word_count: usize) -> Self {
        Self {
            inverted: vec![Vec::new(); word_count],
            slots: Vec::new(),
            free: Vec::new(),
            by_id: HashMap::new(),
        }
    }

    /// Heap bytes of the index (capacities; a hash map entry counted as
    /// the pair and one control byte): inverted lists, slots with their
    /// BoW vectors, the free list and the id table.
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        self.inverted.capacity() * size_of::<Vec<Posting>>()
            + self
                .inverted
                .iter()
                .map(|l| l.capacity() * size_of::<Posting>())
                .sum::<usize>()
            + self.slots.capacity() * size_of::<Option<Entry>>()
            + self
                .slots
                .iter()
                .flatten()
                .map(|e| e.bow.entries.capacity() * size_of::<(crate::bow::WordId, f32)>())
                .sum::<usize>()
            + self.free.capacity() * size_of::<u32>()
            + self.by_id.capacity() * (size_of::<(KeyFrameId, u32)>() + 1)
    }

    /// Postings in the inverted lists (one per keyframe word).
    pub fn postings(&self) -> usize {
        self.inverted.iter().map(Vec::len).sum()
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.by_id.len()
    }

    /// True when there is no keyframe.
    pub fn is_empty(&self) -> bool {
        self.by_id.is_empty()
    }

    /// Whether `id` is in the database.
    pub fn contains(&self, id: KeyFrameId) -> bool {
        self.by_id.contains_key(&id)
    }

    /// The BoW vector stored for `id`.
    pub fn bow(&self, id: KeyFrameId) -> Option<&BowVector> {
        let slot = *self.by_id.get(&id)?;
        self.slots[slot as usize].as_ref().map(|e| &e.bow)
    }

    /// Add a keyframe with its BoW vector.
    pub fn add(&mut self, id: KeyFrameId, bow: BowVector) -> Result<(), BowError> {
        if self.by_id.contains_key(&id) {
            return Err(BowError::DuplicateKeyFrame { id });
        }
        let words = self.inverted.len() as u32;
        if let Some(&(w, _)) = bow.entries.iter().find(|(w, _)| w.0 >= words) {
            return Err(BowError::WordOutOfRange { word: w.0, words });
        }
        let slot = match self.free.pop() {
            Some(s) => s,
            None => {
                self.slots.push(None);
                (self.slots.len() - 1) as u32
            }
        };
        for &(w, weight) in &bow.entries {
            self.inverted[w.0 as usize].push(Posting { slot, weight });
        }
        self.slots[slot as usize] = Some(Entry { id, bow });
        self.by_id.insert(id, slot);
        Ok(())
    }

    /// Remove a keyframe; returns its BoW vector, `None` when it was absent.
    pub fn remove(&mut self, id: KeyFrameId) -> Option<BowVector> {
        let slot = self.by_id.remove(&id)?;
        let entry = self.slots[slot as usize].take()?;
        for &(w, _) in &entry.bow.entries {
            let list = &mut self.inverted[w.0 as usize];
            if let Some(i) = list.iter().position(|p| p.slot == slot) {
                list.swap_remove(i);
            }
        }
        self.free.push(slot);
        Some(entry.bow)
    }

    /// Remove every keyframe.
    pub fn clear(&mut self) {
        for list in &mut self.inverted {
            list.clear();
        }
        self.slots.clear();
        self.free.clear();
        self.by_id.clear();
    }

    /// Walk the inverted lists of the query's words, accumulating per slot
    /// the L1 score `sum min(q_w, v_w)` and the number of common words.
    fn accumulate(&self, query: &BowVector) -> Vec<Acc> {
        let mut acc = vec![Acc::default(); self.slots.len()];
        for &(w, q) in &query.entries {
            let Some(list) = self.inverted.get(w.0 as usize) else {
                continue;
            };
            for p in list {
                // Slots in postings always index `slots` (kept by add/remove).
                if let Some(a) = acc.get_mut(p.slot as usize) {
                    a.common += 1;
                    a.score += q.min(p.weight);
                }
            }
        }
        acc
    }

    /// Slots sharing at least one word, with their live entry.
    fn touched<'a>(&'a self, acc: &'a [Acc]) -> impl Iterator<Item = (u32, &'a Entry, Acc)> + 'a {
        acc.iter()
            .zip(&self.slots)
            .enumerate()
            .filter_map(|(s, (a, e))| match e {
                Some(e) if a.common > 0 => Some((s as u32, e, *a)),
                _ => None,
            })
    }

    /// The `max_results` keyframes most similar to `query` (L1 score), best
    /// first; keyframes sharing no word with the query are not returned.
    /// Ties are broken by increasing keyframe id.
    pub fn query(&self, query: &BowVector, max_results: usize) -> Vec<QueryResult> {
        let acc = self.accumulate(query);
        let mut results: Vec<QueryResult> = self
            .touched(&acc)
            .map(|(_, e, a)| QueryResult {
                id: e.id,
                score: a.score,
            })
            .collect();
        let order =
            |a: &QueryResult, b: &QueryResult| b.score.total_cmp(&a.score).then(a.id.cmp(&b.id));
        if results.len() > max_results {
            if max_results == 0 {
                return Vec::new();
            }
            results.select_nth_unstable_by(max_results - 1, order);
            results.truncate(max_results);
        }
        results.sort_unstable_by(order);
        results
    }

    /// ORB-SLAM's covisibility-grouped candidate search for relocalisation
    /// and loop closing.
    ///
    /// 1. Keyframes sharing words with `query` (and not `excluded`) are
    ///    found through the inverted index; those sharing more than
    ///    `min_common_words_ratio` times the most words shared by any of them,
    ///    and scoring at least `min_score`, are the scored candidates.
    /// 2. Each scored candidate forms a group with its best covisible
    ///    neighbours, which `covisible(id, &mut out)` appends to `out` best
    ///    first (only the first `covisible_neighbours` are used); the group's
    ///    score accumulates the scores of its members that are scored
    ///    candidates themselves, and the group is represented by its
    ///    best-scoring member.
    /// 3. Groups scoring more than `min_group_score_ratio` times the best
    ///    group are returned, one entry per representative keyframe, by
    ///    decreasing group score.
    ///
    /// The covisibility graph stays with the caller (the map), so the
    /// database does not depend on it.
    pub fn detect_candidates(
        &self,
        query: &BowVector,
        params: &CandidateParams,
        mut excluded: impl FnMut(KeyFrameId) -> bool,
        mut covisible: impl FnMut(KeyFrameId, &mut Vec<KeyFrameId>),
    ) -> Vec<Candidate> {
        let acc = self.accumulate(query);
        // Step 1: words in common, then scores.
        let mut sharing: Vec<(u32, Acc)> = Vec::new();
        let mut max_common = 0u32;
        for (s, e, a) in self.touched(&acc) {
            if excluded(e.id) {
                continue;
            }
            max_common = max_common.max(a.common);
            sharing.push((s, a));
        }
        if sharing.is_empty() {
            return Vec::new();
        }
        let min_common = params.min_common_words_ratio * max_common as f32;
        // Score of each scored candidate slot, negative when not a candidate.
        let mut cand_score = vec![-1.0f32; self.slots.len()];
        let mut scored: Vec<u32> = Vec::new();
        for &(s, a) in &sharing {
            if a.common as f32 > min_common && a.score >= params.min_score {
                cand_score[s as usize] = a.score;
                scored.push(s);
            }
        }
        // Step 2: accumulate over covisibility groups.
        let mut neighbours = Vec::new();
        let mut groups: Vec<(f32, u32, f32)> = Vec::with_capacity(scored.len());
        let mut best_group = 0.0f32;
        for &s in &scored {
            let Some(e) = self.slots[s as usize].as_ref() else {
                continue;
            };
            let mut best_slot = s;
            let mut best_score = cand_score[s as usize];
            let mut group = best_score;
            neighbours.clear();
            covisible(e.id, &mut neighbours);
            neighbours.truncate(params.covisible_neighbours);
            for (j, nb) in neighbours.iter().enumerate() {
                let Some(&ns) = self.by_id.get(nb) else {
                    continue;
                };
                // The keyframe itself, or a neighbour listed twice, counts once.
                if ns == s || neighbours[..j].contains(nb) {
                    continue;
                }
                let score = cand_score[ns as usize];
                if score < 0.0 {
                    continue;
                }
                group += score;
                if score > best_score {
                    best_score = score;
                    best_slot = ns;
                }
            }
            best_group = best_group.max(group);
            groups.push((group, best_slot, best_score));
        }
        // Step 3: keep the strong groups, one entry per representative.
        let threshold = params.min_group_score_ratio * best_group;
        groups.retain(|g| g.0 > threshold);
        groups.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut seen = vec![false; self.slots.len()];
        let mut out = Vec::with_capacity(groups.len());
        for (group_score, slot, score) in groups {
            if std::mem::replace(&mut seen[slot as usize], true) {
                continue;
            }
            if let Some(e) = self.slots[slot as usize].as_ref() {
                out.push(Candidate {
                    id: e.id,
                    score,
                    group_score,
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bow::WordId;

    fn bow(p: &[(u32, f32)]) -> BowVector {
        BowVector::from_weights(p.iter().map(|&(w, x)| (WordId(w), x)))
    }

    #[test]
    fn query_scores_equal_direct_l1() {
        let mut db = KeyFrameDatabase::new(20);
        let kfs = [
            bow(&[(1, 1.0), (2, 1.0), (3, 2.0)]),
            bow(&[(2, 1.0), (3, 1.0), (9, 1.0)]),
            bow(&[(10, 1.0), (11, 1.0)]),
            bow(&[(1, 3.0), (3, 1.0)]),
        ];
        for (i, b) in kfs.iter().enumerate() {
            db.add(KeyFrameId(100 + i as u64), b.clone()).expect("add");
        }
        let q = bow(&[(1, 1.0), (3, 1.0), (9, 0.5)]);
        let res = db.query(&q, 10);
        assert_eq!(res.len(), 3, "kf 102 shares nothing");
        for r in &res {
            let direct = q.l1_score(&kfs[(r.id.0 - 100) as usize]);
            assert!((r.score - direct).abs() < 1e-6);
        }
        assert!(res.windows(2).all(|w| w[0].score >= w[1].score));
        let top1 = db.query(&q, 1);
        assert_eq!(top1, res[..1].to_vec());
        assert!(db.query(&q, 0).is_empty());
    }

    #[test]
    fn add_remove_and_reuse() {
        let mut db = KeyFrameDatabase::new(8);
        db.add(KeyFrameId(1), bow(&[(1, 1.0)])).expect("add");
        assert!(matches!(
            db.add(KeyFrameId(1), bow(&[(2, 1.0)])),
            Err(BowError::DuplicateKeyFrame { .. })
        ));
        assert!(matches!(
            db.add(KeyFrameId(2), bow(&[(8, 1.0)])),
            Err(BowError::WordOutOfRange { word: 8, words: 8 })
        ));
        db.add(KeyFrameId(2), bow(&[(1, 1.0), (2, 1.0)]))
            .expect("add");
        assert_eq!(db.remove(KeyFrameId(1)), Some(bow(&[(1, 1.0)])));
        assert_eq!(db.remove(KeyFrameId(1)), None);
        let res = db.query(&bow(&[(1, 1.0)]), 5);
        assert_eq!(
            res,
            vec![QueryResult {
                id: KeyFrameId(2),
                score: 0.5
            }]
        );
        db.add(KeyFrameId(3), bow(&[(1, 1.0)]))
            .expect("add reuses slot");
        assert_eq!(db.len(), 2);
        let res = db.query(&bow(&[(1, 1.0)]), 5);
        assert_eq!(res[0].id, KeyFrameId(3));
        db.clear();
        assert!(db.query(&bow(&[(1, 1.0)]), 5).is_empty());
    }

    #[test]
    fn candidates_are_grouped_by_covisibility() {
        // Query words 0..10. Group A = {1, 2, 3} (covisible chain), each
        // sharing 9 words with moderate scores; lone keyframe 4 shares all
        // 10 words with a higher single score; keyframe 5 shares only 5
        // words (below 0.8 * 10) and must not count.
        let q = bow(&(0..10).map(|w| (w, 1.0)).collect::<Vec<_>>());
        let mut db = KeyFrameDatabase::new(64);
        let nine = |extra: u32| -> BowVector {
            let mut p: Vec<(u32, f32)> = (0..9).map(|w| (w, 1.0)).collect();
            p.push((20 + extra, 9.0)); // dilutes the score
            bow(&p)
        };
        db.add(KeyFrameId(1), nine(1)).expect("add");
        db.add(KeyFrameId(2), nine(2)).expect("add");
        db.add(KeyFrameId(3), nine(3)).expect("add");
        db.add(
            KeyFrameId(4),
            bow(&(0..10).map(|w| (w, 1.0)).collect::<Vec<_>>()),
        )
        .expect("add");
        db.add(
            KeyFrameId(5),
            bow(&(0..5).map(|w| (w, 1.0)).collect::<Vec<_>>()),
        )
        .expect("add");
        let graph = |id: KeyFrameId, out: &mut Vec<KeyFrameId>| match id.0 {
            1 => out.extend([KeyFrameId(2), KeyFrameId(5)]),
            2 => out.extend([KeyFrameId(1), KeyFrameId(3)]),
            3 => out.extend([KeyFrameId(2)]),
            _ => {}
        };
        // A neighbour list naming a keyframe twice (or the keyframe itself)
        // does not inflate the group.
        let c = db.detect_candidates(
            &q,
            &CandidateParams::default(),
            |_| false,
            |id, out| {
                if id.0 == 2 {
                    out.extend([KeyFrameId(2), KeyFrameId(1), KeyFrameId(1), KeyFrameId(3)]);
                }
            },
        );
        assert!((c[0].group_score - 1.5).abs() < 1e-5, "{c:?}");
        let s_nine = q.l1_score(&nine(1)); // 9 * min(0.1, 1/18) = 0.5
        assert!((s_nine - 0.5).abs() < 1e-6);
        let params = CandidateParams::default();
        let c = db.detect_candidates(&q, &params, |_| false, graph);
        // Group of 2 accumulates 1.5 (best), groups of 1 and 3 accumulate
        // 1.0, lone 4 scores 1.0: threshold 0.75 * 1.5 = 1.125 keeps only the
        // group of 2, represented by keyframe 2 (ties keep the centre).
        assert_eq!(c.len(), 1, "{c:?}");
        assert_eq!(c[0].id, KeyFrameId(2));
        assert!((c[0].group_score - 1.5).abs() < 1e-5);
        assert!((c[0].score - 0.5).abs() < 1e-5);
        // With a looser group threshold the lone, better keyframe 4 also
        // comes back, and keyframe 5 never does.
        let loose = CandidateParams {
            min_group_score_ratio: 0.5,
            ..params.clone()
        };
        let c = db.detect_candidates(&q, &loose, |_| false, graph);
        let ids: Vec<u64> = c.iter().map(|x| x.id.0).collect();
        assert!(
            ids.contains(&4) && ids.contains(&2) && !ids.contains(&5),
            "{ids:?}"
        );
        // Excluding keyframe 4 (e.g. connected to the query keyframe): then
        // 9 shared words is the maximum and the same group wins.
        let c = db.detect_candidates(&q, &loose, |id| id.0 == 4, graph);
        assert!(c.iter().all(|x| x.id.0 != 4));
        // A minimum score above 0.5 removes the diluted keyframes.
        let strict = CandidateParams {
            min_score: 0.6,
            ..params
        };
        let c = db.detect_candidates(&q, &strict, |_| false, graph);
        assert_eq!(c.iter().map(|x| x.id.0).collect::<Vec<_>>(), vec![4]);
    }
}
