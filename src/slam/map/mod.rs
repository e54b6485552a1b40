//! The map: keyframes and map points in arenas with typed ids, observations
//! kept both ways, the covisibility graph with weights and its spanning tree.
//!
//! It is an atlas: every keyframe belongs to one map ([`MapId`]; a point to
//! its observers' map). Tracking extends the active map; after a tracking
//! loss a new map is started beside the old ones ([`Map::start_map`]), and
//! loop closing merges it into an old one ([`Map::merge_maps`]) when it sees
//! a common place. Each map has its own root keyframe (the first, never
//! culled, the gauge of its bundle adjustments).
//!
//! Invariants (checked by [`Map::check_invariants`]):
//! - a point lists keyframe `k` at keypoint `i` exactly when keyframe `k`'s
//!   slot `i` holds that point;
//! - no live object refers to an erased id;
//! - covisibility weights are symmetric;
//! - the place index (BoW database) holds exactly the indexed live keyframes;
//! - no covisibility edge, parent link or point joins two maps.
//!
//! # Layout (each file points down to the ones below it)
//!
//! | file | what it holds |
//! |---|---|
//! | `invariants.rs` | [`Map::check_invariants`] |
//! | `footprint.rs` | [`Footprint`]: what the stores hold, their bytes |
//! | `indexing.rs` | keyframes indexed for place recognition |
//! | `observations.rs` | points and observations both ways, a point's descriptor, normal and scale range, the map's reprojection noise |
//! | `graph.rs` | keyframes inserted, pinned, culled; covisibility and the spanning tree |
//! | `atlas.rs` | the maps of the atlas: started, merged, discarded; the whole map moved |
//! | `store.rs` | [`Map`]'s stores and reading them, [`MergeRecord`], [`MapMode`], [`Map::from_parts`] |
//! | `error.rs` | [`MapError`], [`Violation`] |
//! | `places.rs` | [`Places`]: the keyframe database and feature vectors |
//! | `keyframe.rs`, `point.rs` | [`KeyFrame`], [`CulledKeyFrame`]; [`MapPoint`] |
//! | `scale.rs`, `ids.rs` | [`ScaleInfo`]; [`KeyFrameId`], [`PointId`], [`MapId`] |

mod atlas;
mod error;
mod footprint;
mod graph;
mod ids;
mod indexing;
mod invariants;
mod keyframe;
mod observations;
mod places;
mod point;
mod scale;
mod store;
#[cfg(test)]
pub(crate) mod testing;

use std::sync::{Mutex, MutexGuard};

pub use self::error::{MapError, Violation};
pub use self::footprint::Footprint;
pub use self::ids::{KeyFrameId, MapId, PointId};
pub use self::keyframe::{CulledKeyFrame, KeyFrame};
pub use self::places::Places;
pub use self::point::MapPoint;
pub use self::scale::ScaleInfo;
pub use self::store::{Map, MapMode, MergeRecord};

/// The map behind its lock. A panic in another thread while holding the
/// lock leaves the map as it was between two whole operations: keep going
/// with it.
pub fn lock(map: &Mutex<Map>) -> MutexGuard<'_, Map> {
    map.lock().unwrap_or_else(|e| e.into_inner())
}

/// [`lock`], adding the time spent waiting for the lock (held by another
/// thread) to `waited_ms`; an uncontended lock costs no clock reading.
pub fn lock_timed<'a>(map: &'a Mutex<Map>, waited_ms: &mut f64) -> MutexGuard<'a, Map> {
    match map.try_lock() {
        Ok(g) => g,
        Err(std::sync::TryLockError::Poisoned(e)) => e.into_inner(),
        Err(std::sync::TryLockError::WouldBlock) => {
            let t = std::time::Instant::now();
            let g = lock(map);
            *waited_ms += t.elapsed().as_secs_f64() * 1e3;
            g
        }
    }
}
