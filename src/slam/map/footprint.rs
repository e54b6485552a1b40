//! What the [`Map`]'s stores hold and an estimate of their heap bytes
//! ([`Footprint`], [`Map::footprint`]): memory accounting over long runs.

use crate::bow::{self, FeatureVector};
use crate::features::{Descriptor, KeyPoint};

use super::ids::{KeyFrameId, MapId, PointId};
use super::keyframe::{CulledKeyFrame, KeyFrame};
use super::point::MapPoint;
use super::store::Map;

/// What a [`Map`]'s stores hold, and estimates of their heap bytes
/// ([`Map::footprint`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Footprint {
    /// Keyframe ids given (live, culled and discarded: the arena's slots).
    pub keyframe_ids: usize,
    /// Live keyframes.
    pub keyframes: usize,
    /// Point ids given (the arena's slots).
    pub point_ids: usize,
    /// Live points.
    pub points: usize,
    /// Culled keyframes kept for placing frames ([`Map::culled`]).
    pub culled: usize,
    /// Observations of the live points.
    pub observations: usize,
    /// Keyframes in the place index (BoW database).
    pub places: usize,
    /// Postings of its inverted lists (one per word of an indexed
    /// keyframe).
    pub postings: usize,
    /// Live keyframes holding their image.
    pub images: usize,
    /// The keyframe arena and the live keyframes' vectors (images apart).
    pub keyframe_bytes: usize,
    /// The live keyframes' images.
    pub image_bytes: usize,
    /// The point arena and the live points' observation lists.
    pub point_bytes: usize,
    /// The culled keyframes' table.
    pub culled_bytes: usize,
    /// The place index: inverted lists, BoW and feature vectors.
    pub places_bytes: usize,
    /// The rest: keyframes' maps, loop edges, merges, discarded ids.
    pub other_bytes: usize,
}

impl Footprint {
    /// The estimated bytes of every store together.
    pub fn total_bytes(&self) -> usize {
        self.keyframe_bytes
            + self.image_bytes
            + self.point_bytes
            + self.culled_bytes
            + self.places_bytes
            + self.other_bytes
    }
}

impl Map {
    /// What the map's stores hold and an estimate of their heap bytes
    /// (capacities times element sizes; allocator overhead not counted):
    /// memory accounting over long runs.
    pub fn footprint(&self) -> Footprint {
        use std::mem::size_of;
        let vec_bytes = |cap: usize, elem: usize| cap * elem;
        let mut keyframe_bytes = vec_bytes(
            self.keyframes.capacity(),
            size_of::<Option<Box<KeyFrame>>>(),
        );
        let mut image_bytes = 0;
        let mut images = 0;
        for k in self.keyframes() {
            keyframe_bytes += size_of::<KeyFrame>()
                + vec_bytes(k.keypoints.capacity(), size_of::<KeyPoint>())
                + vec_bytes(k.descriptors.capacity(), size_of::<Descriptor>())
                + vec_bytes(k.points.capacity(), size_of::<Option<PointId>>())
                + vec_bytes(k.covisible.capacity(), size_of::<(KeyFrameId, u32)>())
                + vec_bytes(k.children.capacity(), size_of::<KeyFrameId>())
                + k.grid.heap_bytes();
            if let Some(img) = &k.image {
                images += 1;
                image_bytes += img.as_raw().capacity();
            }
        }
        let mut point_bytes = vec_bytes(self.points.capacity(), size_of::<Option<Box<MapPoint>>>());
        let mut observations = 0;
        for p in self.points() {
            observations += p.observations.len();
            point_bytes += size_of::<MapPoint>()
                + vec_bytes(p.observations.capacity(), size_of::<(KeyFrameId, u32)>());
        }
        // A hash map entry: the pair and one control byte, at the table's
        // capacity.
        let culled_bytes = self.culled.capacity() * (size_of::<(KeyFrameId, CulledKeyFrame)>() + 1);
        let (places, postings, places_bytes) = self.places.as_ref().map_or((0, 0, 0), |p| {
            let features: usize = p
                .features
                .values()
                .map(|f| f.pairs.capacity() * size_of::<(bow::NodeId, u32)>())
                .sum::<usize>()
                + p.features.capacity() * (size_of::<(KeyFrameId, FeatureVector)>() + 1);
            (
                p.database.len(),
                p.database.postings(),
                p.database.heap_bytes() + features,
            )
        });
        let other_bytes = vec_bytes(self.kf_maps.capacity(), size_of::<MapId>())
            + vec_bytes(
                self.loop_edges.capacity(),
                size_of::<(KeyFrameId, KeyFrameId)>(),
            )
            + self
                .merges
                .iter()
                .map(|m| m.keyframes.capacity() * size_of::<KeyFrameId>())
                .sum::<usize>()
            + vec_bytes(self.discarded.capacity(), size_of::<KeyFrameId>());
        Footprint {
            keyframe_ids: self.keyframes.len(),
            keyframes: self.n_keyframes,
            point_ids: self.points.len(),
            points: self.n_points,
            culled: self.culled.len(),
            observations,
            places,
            postings,
            images,
            keyframe_bytes,
            image_bytes,
            point_bytes,
            culled_bytes,
            places_bytes,
            other_bytes,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bow::BowVector;
    use crate::slam::map::testing::map_with;

    #[test]
    fn culled_keyframes_and_erased_points_leave_only_their_ids() {
        use std::mem::size_of;
        let mut m = map_with(5, 40);
        for k in 0..5u32 {
            let bow = BowVector::from_weights((0..8).map(|w| (bow::WordId(w + k), 1.0)));
            assert!(m.index_keyframe(KeyFrameId(k), bow, FeatureVector::new(), 64));
        }
        let before = m.footprint();
        assert_eq!((before.keyframe_ids, before.keyframes), (5, 5));
        assert_eq!((before.places, before.postings), (5, 40));
        assert_eq!(before.observations, 5 * 40);
        // A culled keyframe: its observations, its place-index entry and its
        // postings go; its id stays (a pose kept relative to its parent).
        assert!(m.erase_keyframe(KeyFrameId(3)));
        let culled = m.footprint();
        assert_eq!(
            (culled.keyframe_ids, culled.keyframes, culled.culled),
            (5, 4, 1)
        );
        assert_eq!((culled.places, culled.postings), (4, 32));
        assert_eq!(culled.observations, 4 * 40);
        let per_keyframe = size_of::<KeyFrame>()
            + 40 * (size_of::<KeyPoint>() + size_of::<Descriptor>() + size_of::<Option<PointId>>());
        assert!(before.keyframe_bytes - culled.keyframe_bytes >= per_keyframe);
        // Erased points leave a pointer-sized slot each.
        for j in 0..30 {
            m.erase_point(PointId(j));
        }
        let erased = m.footprint();
        assert_eq!((erased.point_ids, erased.points), (40, 10));
        assert_eq!(erased.observations, 4 * 10);
        assert!(culled.point_bytes - erased.point_bytes >= 30 * size_of::<MapPoint>());
        // The arena's slots (a pointer each) and the ten live points.
        assert!(
            erased.point_bytes
                <= m.points.capacity() * size_of::<Option<Box<MapPoint>>>()
                    + 10 * (size_of::<MapPoint>() + 8 * size_of::<(KeyFrameId, u32)>())
        );
        m.check_invariants().unwrap();
    }
}
