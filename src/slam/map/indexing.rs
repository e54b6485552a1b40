//! Indexing the map's keyframes for place recognition: a keyframe's BoW and
//! feature vectors into the [`Places`] of the [`Map`], and every keyframe
//! of a loaded map (the map file does not store the vectors).

use std::collections::HashMap;

use crate::bow::{self, BowVector, FeatureVector, KeyFrameDatabase};

use super::ids::KeyFrameId;
use super::places::Places;
use super::store::Map;

impl Map {
    /// The bag-of-words index of the keyframes, once one was indexed.
    pub fn places(&self) -> Option<&Places> {
        self.places.as_ref()
    }

    /// Index a live keyframe for place recognition (its BoW vector and
    /// feature vector, from a vocabulary of `word_count` words). Returns
    /// false when the keyframe is not live or the vector does not fit the
    /// database.
    pub fn index_keyframe(
        &mut self,
        id: KeyFrameId,
        bow: BowVector,
        features: FeatureVector,
        word_count: usize,
    ) -> bool {
        if self.keyframe(id).is_none() {
            return false;
        }
        let places = self.places.get_or_insert_with(|| Places {
            database: KeyFrameDatabase::new(word_count),
            features: HashMap::new(),
        });
        places.database.remove(Places::db_id(id));
        if places.database.add(Places::db_id(id), bow).is_err() {
            places.features.remove(&id);
            return false;
        }
        places.features.insert(id, features);
        true
    }

    /// Whether a keyframe is in the keyframe database.
    pub fn is_indexed(&self, id: KeyFrameId) -> bool {
        self.places
            .as_ref()
            .is_some_and(|p| p.features.contains_key(&id))
    }

    /// Index every live keyframe that is not indexed yet, from its stored
    /// descriptors with `vocabulary` (direct index at `level`): the map file
    /// does not store the BoW vectors, so a loaded map needs this before it
    /// can relocalise. Returns the number of keyframes indexed.
    pub fn index_keyframes(&mut self, vocabulary: &bow::Vocabulary, level: u32) -> usize {
        let todo: Vec<KeyFrameId> = self
            .keyframes()
            .filter(|k| {
                self.places
                    .as_ref()
                    .is_none_or(|p| !p.features.contains_key(&k.id))
            })
            .map(|k| k.id)
            .collect();
        let words = vocabulary.word_count();
        let mut n = 0;
        for id in todo {
            let Some(k) = self.keyframe(id) else { continue };
            let (bow, fv) = vocabulary.transform_with_features(&k.descriptors, level);
            if self.index_keyframe(id, bow, fv, words) {
                n += 1;
            }
        }
        n
    }
}
