//! The map's errors ([`MapError`]): a map rebuilt from parts that do not
//! fit, or a broken invariant ([`Violation`]; the invariants are listed in
//! the `slam::map` module doc and checked by `invariants.rs`).

use super::ids::{KeyFrameId, PointId};

/// Errors of the map: a map rebuilt from parts that do not fit, or a
/// broken invariant.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MapError {
    /// Ids too large to be a real map's.
    #[error("ids out of range: {keyframes} keyframe slots, {points} point slots")]
    IdsOutOfRange {
        /// Keyframe slots the ids need.
        keyframes: usize,
        /// Point slots the ids need.
        points: usize,
    },
    /// Two keyframes with one id.
    #[error("keyframe id {} twice", id.0)]
    DuplicateKeyFrame {
        /// The id.
        id: KeyFrameId,
    },
    /// Two points with one id.
    #[error("point id {} twice", id.0)]
    DuplicatePoint {
        /// The id.
        id: PointId,
    },
    /// An invariant does not hold.
    #[error("map invariant broken: {0}")]
    Invariant(Violation),
}

/// A broken invariant of the map (listed in the `slam::map` module doc).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Violation {
    /// The place index holds an erased keyframe.
    #[error("place index holds erased keyframe {keyframe:?}")]
    IndexedErased {
        /// The keyframe.
        keyframe: KeyFrameId,
    },
    /// A keyframe has feature vectors but no BoW entry.
    #[error("keyframe {keyframe:?} has features but no BoW entry")]
    NotInDatabase {
        /// The keyframe.
        keyframe: KeyFrameId,
    },
    /// The keyframe database and the feature vectors differ in size.
    #[error("keyframe database holds {database} keyframes, feature vectors {features}")]
    DatabaseSize {
        /// Entries of the database.
        database: usize,
        /// Feature vectors.
        features: usize,
    },
    /// A keyframe's keypoints, descriptors and point slots differ in count.
    #[error("keyframe {keyframe:?}: slot counts differ")]
    SlotCounts {
        /// The keyframe.
        keyframe: KeyFrameId,
    },
    /// A keyframe slot holds an erased point.
    #[error("keyframe {keyframe:?} slot {slot}: dangling point {point:?}")]
    DanglingPoint {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The slot.
        slot: usize,
        /// The point.
        point: PointId,
    },
    /// A keyframe slot holds a point that does not list the keyframe there.
    #[error("keyframe {keyframe:?} slot {slot}: point {point:?} does not list it")]
    PointMissesKeyFrame {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The slot.
        slot: usize,
        /// The point.
        point: PointId,
    },
    /// A covisibility edge to an erased keyframe.
    #[error("keyframe {keyframe:?}: dangling covisible {covisible:?}")]
    DanglingCovisible {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The erased neighbour.
        covisible: KeyFrameId,
    },
    /// A covisibility weight differs between its two ends.
    #[error("covisibility {a:?}-{b:?} asymmetric: {a_to_b} vs {b_to_a}")]
    AsymmetricCovisibility {
        /// One end.
        a: KeyFrameId,
        /// The other end.
        b: KeyFrameId,
        /// The weight `a` holds.
        a_to_b: u32,
        /// The weight `b` holds.
        b_to_a: u32,
    },
    /// A spanning-tree parent that was erased.
    #[error("keyframe {keyframe:?}: dangling parent {parent:?}")]
    DanglingParent {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The parent.
        parent: KeyFrameId,
    },
    /// A parent that does not list the keyframe as its child.
    #[error("keyframe {keyframe:?}: parent {parent:?} does not list it")]
    ParentMissesChild {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The parent.
        parent: KeyFrameId,
    },
    /// A child whose parent is another keyframe.
    #[error("keyframe {keyframe:?}: child {child:?} has another parent")]
    ChildHasOtherParent {
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The child.
        child: KeyFrameId,
    },
    /// The live keyframes and the count differ.
    #[error("keyframe count {live} != {counted}")]
    KeyFrameCount {
        /// Live keyframes.
        live: usize,
        /// The map's count.
        counted: usize,
    },
    /// A point observed by an erased keyframe.
    #[error("point {point:?}: dangling keyframe {keyframe:?}")]
    DanglingObserver {
        /// The point.
        point: PointId,
        /// The erased keyframe.
        keyframe: KeyFrameId,
    },
    /// A point observation whose keyframe slot holds something else.
    #[error("point {point:?}: keyframe {keyframe:?} slot {slot} does not hold it")]
    SlotMissesPoint {
        /// The point.
        point: PointId,
        /// The keyframe.
        keyframe: KeyFrameId,
        /// The slot.
        slot: u32,
    },
    /// Two keyframes of different maps joined by a covisibility edge, a
    /// parent link or a shared point.
    #[error("keyframes {a:?} and {b:?} are linked across maps")]
    CrossMap {
        /// One keyframe.
        a: KeyFrameId,
        /// The other.
        b: KeyFrameId,
    },
    /// The live points and the count differ.
    #[error("point count {live} != {counted}")]
    PointCount {
        /// Live points.
        live: usize,
        /// The map's count.
        counted: usize,
    },
}
