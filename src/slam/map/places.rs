//! The place index's store ([`Places`]): the keyframe database (inverted
//! index) and each keyframe's feature vector, with the conversions between
//! the map's keyframe ids and the database's. Keyframes are indexed by
//! `indexing.rs`.

use std::collections::HashMap;

use crate::bow::{self, FeatureVector, KeyFrameDatabase};

use super::ids::KeyFrameId;

/// The bag-of-words index of the live keyframes: the keyframe database
/// (inverted index) and each keyframe's feature vector (direct index) for
/// BoW-guided matching.
#[derive(Debug, Clone)]
pub struct Places {
    /// Inverted index word -> keyframes (ids are the map's, widened).
    pub database: KeyFrameDatabase,
    /// Direct index of each indexed keyframe.
    pub features: HashMap<KeyFrameId, FeatureVector>,
}

impl Places {
    /// The database id of a keyframe.
    pub fn db_id(id: KeyFrameId) -> bow::KeyFrameId {
        bow::KeyFrameId(id.0 as u64)
    }

    /// The map id of a database id.
    pub fn map_id(id: bow::KeyFrameId) -> Option<KeyFrameId> {
        u32::try_from(id.0).ok().map(KeyFrameId)
    }
}
