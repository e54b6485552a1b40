//! The map's typed ids: keyframes ([`KeyFrameId`]), points ([`PointId`])
//! and the maps of the atlas ([`MapId`]). None is ever reused.

/// Id of a keyframe, unique for the life of a map (never reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyFrameId(pub u32);

/// Id of a map point, unique for the life of a map (never reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PointId(pub u32);

/// Id of one map of the atlas ([`super::Map`] holds every map: the active one,
/// which tracking extends, and the inactive ones left after a tracking
/// loss). Never reused; a merge moves one map's keyframes into another.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct MapId(pub u32);
