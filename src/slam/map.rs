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

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};

use image::GrayImage;
use nalgebra::{Isometry3, Point3, Vector3};

use crate::camera::Camera;
use crate::features::{Descriptor, KeyPoint, hamming};

use crate::bow::{self, BowVector, FeatureVector, KeyFrameDatabase};
use crate::lie::{Sim3, renormalized};
use crate::matching::FeatureGrid;

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

/// A broken invariant of the map (see the module doc).
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

/// Id of a keyframe, unique for the life of a map (never reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct KeyFrameId(pub u32);

/// Id of a map point, unique for the life of a map (never reused).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct PointId(pub u32);

/// Id of one map of the atlas ([`Map`] holds every map: the active one,
/// which tracking extends, and the inactive ones left after a tracking
/// loss). Never reused; a merge moves one map's keyframes into another.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Default)]
pub struct MapId(pub u32);

/// One map merged into another ([`Map::merge_maps`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MergeRecord {
    /// The map that was moved (it no longer exists).
    pub from: MapId,
    /// The map it joined.
    pub into: MapId,
    /// The similarity applied to it (`into` world ← `from` world).
    pub sim3: Sim3,
    /// Every keyframe id it held, live or culled (frames placed relative to
    /// them scale their translations by `sim3.scale`).
    pub keyframes: Vec<KeyFrameId>,
}

/// Scale information of the extractor that the map needs.
#[derive(Debug, Clone, PartialEq)]
pub struct ScaleInfo {
    /// Scale factor between levels.
    pub scale_factor: f64,
    /// Per level: `scale_factor^level`.
    pub scale_factors: Vec<f64>,
    /// Per level: `1 / sigma^2` of a keypoint's position (level 0: 1 px).
    pub inv_level_sigma2: Vec<f64>,
}

impl ScaleInfo {
    /// Scale factors for `n_levels` levels of `scale_factor`.
    pub fn new(scale_factor: f64, n_levels: usize) -> Self {
        let scale_factors: Vec<f64> = (0..n_levels.max(1))
            .map(|l| scale_factor.powi(l as i32))
            .collect();
        let inv_level_sigma2 = scale_factors.iter().map(|s| 1.0 / (s * s)).collect();
        ScaleInfo {
            scale_factor,
            scale_factors,
            inv_level_sigma2,
        }
    }

    /// Number of levels.
    pub fn n_levels(&self) -> usize {
        self.scale_factors.len()
    }

    /// The level at which a point at `dist` whose scale range ends at
    /// `max_distance` should appear (ORB-SLAM's PredictScale).
    pub fn predict_level(&self, max_distance: f64, dist: f64) -> usize {
        let ratio = max_distance / dist.max(1e-9);
        let level = (ratio.ln() / self.scale_factor.ln()).ceil();
        if level.is_finite() {
            (level.max(0.0) as usize).min(self.n_levels() - 1)
        } else {
            0
        }
    }
}

/// A keyframe: a frame kept in the map, with its features and pose.
#[derive(Debug, Clone)]
pub struct KeyFrame {
    /// Its id.
    pub id: KeyFrameId,
    /// Index of the source frame in the input stream.
    pub frame_index: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// Pose: world to camera.
    pub cam_from_world: Isometry3<f64>,
    /// Keypoints (level-0 pixels, distorted and undistorted).
    pub keypoints: Vec<KeyPoint>,
    /// Descriptors, one per keypoint.
    pub descriptors: Vec<Descriptor>,
    /// Per keypoint: the map point it observes.
    pub points: Vec<Option<PointId>>,
    /// Keypoints by image cell (undistorted coordinates).
    pub grid: FeatureGrid,
    /// Covisible keyframes with the number of shared points (weight >= the
    /// connection threshold), sorted by weight, largest first.
    pub covisible: Vec<(KeyFrameId, u32)>,
    /// Parent in the spanning tree (none for the first keyframe).
    pub parent: Option<KeyFrameId>,
    /// Children in the spanning tree.
    pub children: Vec<KeyFrameId>,
    /// The grayscale image (for the map file, the API and the desired shot).
    pub image: Option<Arc<GrayImage>>,
}

impl KeyFrame {
    /// The camera centre in world coordinates.
    pub fn center(&self) -> Vector3<f64> {
        self.cam_from_world.inverse().translation.vector
    }

    /// The pose as world_from_cam.
    pub fn world_from_cam(&self) -> Isometry3<f64> {
        self.cam_from_world.inverse()
    }

    /// Number of map points observed by at least `min_obs` keyframes.
    pub fn tracked_points(&self, map: &Map, min_obs: usize) -> usize {
        self.points
            .iter()
            .flatten()
            .filter(|p| {
                map.point(**p)
                    .is_some_and(|mp| mp.observations.len() >= min_obs)
            })
            .count()
    }

    /// The best `n` covisible keyframes.
    pub fn best_covisible(&self, n: usize) -> impl Iterator<Item = KeyFrameId> + '_ {
        self.covisible.iter().take(n).map(|c| c.0)
    }

    /// Weight of the edge to `other` (0 when not connected).
    pub fn weight(&self, other: KeyFrameId) -> u32 {
        self.covisible
            .iter()
            .find(|c| c.0 == other)
            .map_or(0, |c| c.1)
    }
}

/// A 3D point of the map with the keyframes that observe it.
#[derive(Debug, Clone)]
pub struct MapPoint {
    /// Its id.
    pub id: PointId,
    /// Position in the world.
    pub position: Point3<f64>,
    /// Observations: (keyframe, keypoint index in it).
    pub observations: Vec<(KeyFrameId, u32)>,
    /// The representative descriptor: the observation with the least median
    /// distance to the others.
    pub descriptor: Descriptor,
    /// Mean viewing direction (unit, world frame), from the point to the cameras.
    pub normal: Vector3<f64>,
    /// Closest distance at which the point keeps its scale (scale invariance).
    pub min_distance: f64,
    /// Farthest distance at which the point keeps its scale.
    pub max_distance: f64,
    /// The keyframe that created it.
    pub first_kf: KeyFrameId,
    /// The keyframe used as reference for the scale range.
    pub ref_kf: KeyFrameId,
    /// Frames in whose view frustum it was.
    pub visible: u32,
    /// Frames in which it was matched.
    pub found: u32,
}

impl MapPoint {
    /// Share of the frames that saw it in view that also matched it.
    pub fn found_ratio(&self) -> f64 {
        self.found as f64 / self.visible.max(1) as f64
    }

    /// Keypoint index of this point in keyframe `kf`.
    pub fn index_in(&self, kf: KeyFrameId) -> Option<u32> {
        self.observations.iter().find(|o| o.0 == kf).map(|o| o.1)
    }
}

/// A keyframe removed from the map, kept so frames that referred to it can
/// still be placed: their pose goes through its parent.
#[derive(Debug, Clone, Copy)]
pub struct CulledKeyFrame {
    /// Its parent when it was removed.
    pub parent: KeyFrameId,
    /// Its pose relative to the parent: cam_from_parent_cam.
    pub cam_from_parent: Isometry3<f64>,
}

/// What frame the map is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MapMode {
    /// Monocular vision only: an arbitrary frame and scale.
    #[default]
    VisionOnly,
    /// Re-expressed in local NED (metres) by GNSS fixes, held there by
    /// position and altitude priors in bundle adjustment.
    GpsAided,
}

impl MapMode {
    /// The name the output and the API use.
    pub fn name(self) -> &'static str {
        match self {
            MapMode::VisionOnly => "vision_only",
            MapMode::GpsAided => "gps_aided",
        }
    }
}

impl std::fmt::Display for MapMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

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

/// Keyframes, points and the graphs between them.
#[derive(Debug, Clone)]
pub struct Map {
    /// The camera of every keyframe.
    pub camera: Camera,
    /// Extractor scale levels.
    pub scale: ScaleInfo,
    /// By id; boxed, so the slot of an id no longer live (a culled
    /// keyframe, an erased point: ids are never reused) costs a pointer,
    /// not a whole object: over a long flight mapping creates and culls
    /// hundreds of points a second, and the dead slots stay.
    keyframes: Vec<Option<Box<KeyFrame>>>,
    /// By id; boxed (see `keyframes`).
    points: Vec<Option<Box<MapPoint>>>,
    n_keyframes: usize,
    n_points: usize,
    /// Removed keyframes, for placing frames referring to them.
    pub culled: HashMap<KeyFrameId, CulledKeyFrame>,
    /// Keyframes with fewer shared points are not covisibility neighbours.
    pub covisibility_threshold: u32,
    places: Option<Places>,
    /// Loop edges of the essential graph (keyframes joined by a loop
    /// closure); their keyframes are never culled.
    loop_edges: Vec<(KeyFrameId, KeyFrameId)>,
    /// Keyframes the operator drew a shot on: never culled, so the shot
    /// can be asked again on them (not saved: the daemon pins its shots'
    /// keyframes again when it loads a map).
    pinned: std::collections::HashSet<KeyFrameId>,
    /// Loop corrections applied (tracking re-places its last frame when
    /// this changes).
    corrections: u64,
    /// The frame the map is in (in the map file since version 5).
    mode: MapMode,
    /// Product of the scales of the similarities applied to the whole map
    /// ([`Map::apply_sim3`]; tracking rescales its relative poses when this
    /// changes).
    scale_applied: f64,
    /// The map of every keyframe id ever given (live or culled), by id.
    kf_maps: Vec<MapId>,
    /// The map new keyframes go to.
    active_map: MapId,
    /// The next map id [`Map::start_map`] gives.
    next_map: u32,
    /// Each map's first keyframe (the root of its spanning tree, never
    /// culled and never given a parent by [`Map::update_connections`]).
    roots: HashMap<MapId, KeyFrameId>,
    /// The merges so far, in order (tracking rescales the relative poses
    /// of its frames placed on a merged map's keyframes).
    merges: Vec<MergeRecord>,
    /// Keyframes of new maps whose initialisation did not hold
    /// ([`Map::discard_map`]): erased, neither live nor culled.
    discarded: Vec<KeyFrameId>,
}

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

impl Map {
    /// An empty map.
    pub fn new(camera: Camera, scale: ScaleInfo) -> Self {
        Map {
            camera,
            scale,
            keyframes: Vec::new(),
            points: Vec::new(),
            n_keyframes: 0,
            n_points: 0,
            culled: HashMap::new(),
            covisibility_threshold: 15,
            places: None,
            loop_edges: Vec::new(),
            pinned: std::collections::HashSet::new(),
            corrections: 0,
            mode: MapMode::VisionOnly,
            scale_applied: 1.0,
            kf_maps: Vec::new(),
            active_map: MapId(0),
            next_map: 1,
            roots: HashMap::new(),
            merges: Vec::new(),
            discarded: Vec::new(),
        }
    }

    /// The map new keyframes go to (the one tracking extends).
    pub fn active_map(&self) -> MapId {
        self.active_map
    }

    /// Start a new, empty map and make it the active one (after a tracking
    /// loss: the initializer builds it while the others are kept).
    pub fn start_map(&mut self) -> MapId {
        let id = MapId(self.next_map);
        self.next_map += 1;
        self.active_map = id;
        id
    }

    /// Make `id` the active map (tracking relocalised into it).
    pub fn set_active_map(&mut self, id: MapId) {
        self.active_map = id;
        self.next_map = self.next_map.max(id.0 + 1);
    }

    /// The map of a keyframe, live or culled.
    pub fn map_of(&self, kf: KeyFrameId) -> Option<MapId> {
        self.kf_maps.get(kf.0 as usize).copied()
    }

    /// The map of a point (its observers', else its first keyframe's).
    pub fn map_of_point(&self, p: PointId) -> Option<MapId> {
        let mp = self.point(p)?;
        let kf = mp.observations.first().map_or(mp.first_kf, |o| o.0);
        self.map_of(kf)
    }

    /// The maps holding live keyframes, with their keyframe counts, by id.
    pub fn maps(&self) -> Vec<(MapId, usize)> {
        let mut counts: std::collections::BTreeMap<MapId, usize> = Default::default();
        for k in self.keyframes() {
            if let Some(m) = self.map_of(k.id) {
                *counts.entry(m).or_insert(0) += 1;
            }
        }
        counts.into_iter().collect()
    }

    /// The live keyframes of map `id`, by id.
    pub fn keyframes_in(&self, id: MapId) -> impl Iterator<Item = &KeyFrame> {
        self.keyframes()
            .filter(move |k| self.map_of(k.id) == Some(id))
    }

    /// The first keyframe of map `id` (the root of its spanning tree).
    pub fn root_of(&self, id: MapId) -> Option<KeyFrameId> {
        self.roots.get(&id).copied()
    }

    /// The map of the oldest live keyframe: the one the first frames were
    /// tracked in, with every map merged into it (what the daemon shows and
    /// georeferences while a newer map is not merged yet).
    pub fn first_map(&self) -> Option<MapId> {
        self.keyframes().next().and_then(|k| self.map_of(k.id))
    }

    /// This map with every map but `id` erased (a snapshot of one map).
    pub fn only(&self, id: MapId) -> Map {
        let mut m = self.clone();
        for (other, _) in self.maps() {
            if other != id {
                m.discard_map(other);
            }
        }
        m
    }

    /// The merges so far, in order.
    pub fn merges(&self) -> &[MergeRecord] {
        &self.merges
    }

    /// Keyframes erased with a new map whose initialisation did not hold.
    pub fn discarded(&self) -> &[KeyFrameId] {
        &self.discarded
    }

    /// The map of every live and culled keyframe, by id (the map file).
    pub fn keyframe_maps(&self) -> Vec<(KeyFrameId, MapId)> {
        self.kf_maps
            .iter()
            .enumerate()
            .map(|(i, m)| (KeyFrameId(i as u32), *m))
            .filter(|(id, _)| self.keyframe(*id).is_some() || self.culled.contains_key(id))
            .collect()
    }

    /// Whether keyframe `id` is the root of its map's spanning tree.
    fn is_root(&self, id: KeyFrameId) -> bool {
        self.map_of(id)
            .and_then(|m| self.roots.get(&m))
            .is_some_and(|r| *r == id)
    }

    /// Move map `from` into map `into`: every keyframe, culled keyframe and
    /// point of `from` is carried by the similarity `s` (`into` world ←
    /// `from` world; monocular maps differ in scale), its keyframes become
    /// `into`'s, and its spanning tree hangs from `into`'s keyframe
    /// `anchor` through `current` (the path from `current` to `from`'s root
    /// is reversed, so the tree stays a tree). `into` becomes the active map
    /// when `from` was. Counts as a correction. Returns false (and changes
    /// nothing) when `current` is not a live keyframe of `from` or `anchor`
    /// not one of `into`.
    pub fn merge_maps(
        &mut self,
        from: MapId,
        into: MapId,
        s: &Sim3,
        current: KeyFrameId,
        anchor: KeyFrameId,
    ) -> bool {
        if from == into
            || self.keyframe(current).is_none()
            || self.keyframe(anchor).is_none()
            || self.map_of(current) != Some(from)
            || self.map_of(anchor) != Some(into)
        {
            return false;
        }
        let ids: Vec<KeyFrameId> = (0..self.kf_maps.len())
            .filter(|&i| self.kf_maps[i] == from)
            .map(|i| KeyFrameId(i as u32))
            .collect();
        let pids: Vec<PointId> = self
            .points()
            .filter(|p| self.map_of_point(p.id) == Some(from))
            .map(|p| p.id)
            .collect();
        for id in &ids {
            if let Some(kf) = self.keyframe_mut(*id) {
                let world_from_cam = s.transform_pose(&kf.cam_from_world.inverse());
                kf.cam_from_world = renormalized(world_from_cam.inverse());
            } else if let Some(c) = self.culled.get_mut(id) {
                c.cam_from_parent.translation.vector *= s.scale;
            }
        }
        for pid in &pids {
            if let Some(p) = self.point_mut(*pid) {
                p.position = s.transform_point(&p.position);
            }
        }
        for id in &ids {
            self.kf_maps[id.0 as usize] = into;
        }
        for pid in pids {
            self.update_point_normal_and_depth(pid);
        }
        // The spanning tree: reverse the path current -> root, then hang
        // current from the anchor.
        let mut path = vec![current];
        let mut at = current;
        while let Some(p) = self.keyframe(at).and_then(|k| k.parent) {
            if path.len() > self.keyframes.len() {
                break;
            }
            path.push(p);
            at = p;
        }
        for w in path.windows(2) {
            let (c, p) = (w[0], w[1]);
            if let Some(pk) = self.keyframe_mut(p) {
                pk.children.retain(|x| *x != c);
                pk.parent = Some(c);
            }
            if let Some(ck) = self.keyframe_mut(c) {
                ck.children.push(p);
            }
        }
        if let Some(ck) = self.keyframe_mut(current) {
            ck.parent = Some(anchor);
        }
        if let Some(ak) = self.keyframe_mut(anchor) {
            ak.children.push(current);
        }
        self.roots.remove(&from);
        if self.active_map == from {
            self.active_map = into;
        }
        self.merges.push(MergeRecord {
            from,
            into,
            sim3: *s,
            keyframes: ids,
        });
        self.note_correction();
        true
    }

    /// Erase map `id` whole: its keyframes (taken out of the place index),
    /// their points and culled keyframes (a new map whose initialisation
    /// did not hold). The other maps are untouched.
    pub fn discard_map(&mut self, id: MapId) {
        let ids: Vec<KeyFrameId> = (0..self.kf_maps.len())
            .filter(|&i| self.kf_maps[i] == id)
            .map(|i| KeyFrameId(i as u32))
            .collect();
        for kf in &ids {
            let pids: Vec<PointId> = self
                .keyframe(*kf)
                .map(|k| k.points.iter().flatten().copied().collect())
                .unwrap_or_default();
            for p in pids {
                self.erase_point(p);
            }
        }
        for kf in &ids {
            self.culled.remove(kf);
            if let Some(slot) = self.keyframes.get_mut(kf.0 as usize)
                && slot.take().is_some()
            {
                self.n_keyframes -= 1;
            }
            if let Some(places) = &mut self.places {
                places.database.remove(Places::db_id(*kf));
                places.features.remove(kf);
            }
            self.pinned.remove(kf);
        }
        self.loop_edges
            .retain(|(a, b)| !ids.contains(a) && !ids.contains(b));
        self.roots.remove(&id);
        self.discarded.extend(ids);
    }

    /// Give the keyframes their maps (the map file): `maps` names the map
    /// of every keyframe id, live or culled; `active` is the active map.
    /// Each map's root is its first live keyframe without a parent.
    pub fn set_keyframe_maps(&mut self, maps: &[(KeyFrameId, MapId)], active: MapId) {
        for (kf, m) in maps {
            if let Some(slot) = self.kf_maps.get_mut(kf.0 as usize) {
                *slot = *m;
            }
        }
        self.active_map = active;
        self.next_map = self
            .kf_maps
            .iter()
            .map(|m| m.0 + 1)
            .chain([active.0 + 1])
            .max()
            .unwrap_or(1);
        self.recompute_roots();
    }

    fn recompute_roots(&mut self) {
        self.roots.clear();
        let roots: Vec<(MapId, KeyFrameId)> = self
            .keyframes()
            .filter(|k| k.parent.is_none())
            .filter_map(|k| self.map_of(k.id).map(|m| (m, k.id)))
            .collect();
        for (m, k) in roots {
            self.roots.entry(m).or_insert(k);
        }
    }

    /// The frame the map is in.
    pub fn mode(&self) -> MapMode {
        self.mode
    }

    /// Say which frame the map is in.
    pub fn set_mode(&mut self, mode: MapMode) {
        self.mode = mode;
    }

    /// Product of the scales of the similarities applied so far (1 when
    /// none).
    pub fn scale_applied(&self) -> f64 {
        self.scale_applied
    }

    /// Move the whole map by the similarity `s` (new world ← old world):
    /// every keyframe pose, every point, the culled keyframes' relative
    /// poses (their translations scale); counts as a correction, so
    /// tracking re-places its last frame.
    pub fn apply_sim3(&mut self, s: &Sim3) {
        for kf in self.keyframes.iter_mut().flatten() {
            let world_from_cam = s.transform_pose(&kf.cam_from_world.inverse());
            kf.cam_from_world = renormalized(world_from_cam.inverse());
        }
        for p in self.points.iter_mut().flatten() {
            p.position = s.transform_point(&p.position);
        }
        for c in self.culled.values_mut() {
            c.cam_from_parent.translation.vector *= s.scale;
        }
        let ids: Vec<PointId> = self.points().map(|p| p.id).collect();
        for id in ids {
            self.update_point_normal_and_depth(id);
        }
        self.scale_applied *= s.scale;
        self.note_correction();
    }

    /// The loop edges (keyframe pairs joined by a loop closure).
    pub fn loop_edges(&self) -> &[(KeyFrameId, KeyFrameId)] {
        &self.loop_edges
    }

    /// Record a loop edge between two live keyframes (false when one is
    /// not live).
    pub fn add_loop_edge(&mut self, a: KeyFrameId, b: KeyFrameId) -> bool {
        if a == b || self.keyframe(a).is_none() || self.keyframe(b).is_none() {
            return false;
        }
        if !self.loop_edges.contains(&(a, b)) && !self.loop_edges.contains(&(b, a)) {
            self.loop_edges.push((a, b));
        }
        true
    }

    /// Count a loop correction (poses moved by more than local mapping).
    pub fn note_correction(&mut self) {
        self.corrections += 1;
    }

    /// Loop corrections applied so far.
    pub fn corrections(&self) -> u64 {
        self.corrections
    }

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

    /// Rebuild a map from its parts (the map file): objects are placed at
    /// their ids; ids must be unique and every reference must resolve.
    pub fn from_parts(
        camera: Camera,
        scale: ScaleInfo,
        covisibility_threshold: u32,
        keyframes: Vec<KeyFrame>,
        points: Vec<MapPoint>,
        culled: Vec<(KeyFrameId, CulledKeyFrame)>,
    ) -> Result<Map, MapError> {
        let mut map = Map::new(camera, scale);
        map.covisibility_threshold = covisibility_threshold;
        let max_kf = keyframes
            .iter()
            .map(|k| k.id.0 as usize + 1)
            .chain(culled.iter().map(|c| c.0.0 as usize + 1))
            .max()
            .unwrap_or(0);
        let max_p = points
            .iter()
            .map(|p| p.id.0 as usize + 1)
            .max()
            .unwrap_or(0);
        if max_kf > 10_000_000 || max_p > 100_000_000 {
            return Err(MapError::IdsOutOfRange {
                keyframes: max_kf,
                points: max_p,
            });
        }
        map.keyframes = vec![None; max_kf];
        map.points = vec![None; max_p];
        for kf in keyframes {
            let slot = &mut map.keyframes[kf.id.0 as usize];
            if slot.is_some() {
                return Err(MapError::DuplicateKeyFrame { id: kf.id });
            }
            *slot = Some(Box::new(kf));
            map.n_keyframes += 1;
        }
        for p in points {
            let slot = &mut map.points[p.id.0 as usize];
            if slot.is_some() {
                return Err(MapError::DuplicatePoint { id: p.id });
            }
            *slot = Some(Box::new(p));
            map.n_points += 1;
        }
        for (id, c) in culled {
            map.culled.insert(id, c);
        }
        map.kf_maps = vec![MapId(0); max_kf];
        map.recompute_roots();
        Ok(map)
    }

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

    /// Number of live keyframes.
    pub fn keyframe_count(&self) -> usize {
        self.n_keyframes
    }

    /// Number of live points.
    pub fn point_count(&self) -> usize {
        self.n_points
    }

    /// A live keyframe.
    pub fn keyframe(&self, id: KeyFrameId) -> Option<&KeyFrame> {
        self.keyframes.get(id.0 as usize).and_then(Option::as_deref)
    }

    /// A live keyframe, mutable.
    pub fn keyframe_mut(&mut self, id: KeyFrameId) -> Option<&mut KeyFrame> {
        self.keyframes
            .get_mut(id.0 as usize)
            .and_then(Option::as_deref_mut)
    }

    /// A live point.
    pub fn point(&self, id: PointId) -> Option<&MapPoint> {
        self.points.get(id.0 as usize).and_then(Option::as_deref)
    }

    /// A live point, mutable.
    pub fn point_mut(&mut self, id: PointId) -> Option<&mut MapPoint> {
        self.points
            .get_mut(id.0 as usize)
            .and_then(Option::as_deref_mut)
    }

    /// All live keyframes, by id.
    pub fn keyframes(&self) -> impl Iterator<Item = &KeyFrame> {
        self.keyframes.iter().flatten().map(|k| &**k)
    }

    /// All live points, by id.
    pub fn points(&self) -> impl Iterator<Item = &MapPoint> {
        self.points.iter().flatten().map(|p| &**p)
    }

    /// The id the next keyframe will get.
    pub fn next_keyframe_id(&self) -> KeyFrameId {
        KeyFrameId(self.keyframes.len() as u32)
    }

    /// Insert a keyframe (its `id` is set here); its `points` slots are
    /// taken as given and their observations are added to the points.
    pub fn add_keyframe(&mut self, mut kf: KeyFrame) -> KeyFrameId {
        let id = self.next_keyframe_id();
        kf.id = id;
        let slots: Vec<(u32, PointId)> = kf
            .points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i as u32, p)))
            .collect();
        kf.points.iter_mut().for_each(|p| *p = None);
        self.keyframes.push(Some(Box::new(kf)));
        self.kf_maps.push(self.active_map);
        self.roots.entry(self.active_map).or_insert(id);
        self.n_keyframes += 1;
        for (i, p) in slots {
            self.add_observation(p, id, i);
        }
        id
    }

    /// Insert a point with no observations yet.
    pub fn add_point(
        &mut self,
        position: Point3<f64>,
        descriptor: Descriptor,
        first_kf: KeyFrameId,
    ) -> PointId {
        let id = PointId(self.points.len() as u32);
        self.points.push(Some(Box::new(MapPoint {
            id,
            position,
            observations: Vec::with_capacity(4),
            descriptor,
            normal: Vector3::zeros(),
            min_distance: 0.0,
            max_distance: f64::INFINITY,
            first_kf,
            ref_kf: first_kf,
            visible: 1,
            found: 1,
        })));
        self.n_points += 1;
        id
    }

    /// Record that keyframe `kf` sees point `p` at keypoint `idx` (both ways).
    /// A slot already holding another point keeps it (returns false).
    pub fn add_observation(&mut self, p: PointId, kf: KeyFrameId, idx: u32) -> bool {
        let Some(mp) = self.point(p) else {
            return false;
        };
        let existing = mp.index_in(kf);
        let Some(k) = self.keyframe_mut(kf) else {
            return false;
        };
        match k.points.get(idx as usize) {
            None => return false,
            Some(Some(q)) => return *q == p,
            Some(None) => {}
        }
        k.points[idx as usize] = Some(p);
        if let Some(old) = existing {
            // Seen by this keyframe at another keypoint: one observation per
            // keyframe, the newer wins.
            if let Some(s) = k.points.get_mut(old as usize) {
                *s = None;
            }
            if let Some(mp) = self.point_mut(p)
                && let Some(o) = mp.observations.iter_mut().find(|o| o.0 == kf)
            {
                o.1 = idx;
            }
        } else if let Some(mp) = self.point_mut(p) {
            mp.observations.push((kf, idx));
        }
        true
    }

    /// Remove the observation of `p` by `kf` (both ways). A point left with
    /// fewer than 2 observations is erased. Returns true when it was erased.
    pub fn erase_observation(&mut self, p: PointId, kf: KeyFrameId) -> bool {
        let Some(mp) = self.point_mut(p) else {
            return false;
        };
        let Some(pos) = mp.observations.iter().position(|o| o.0 == kf) else {
            return false;
        };
        let (_, idx) = mp.observations.swap_remove(pos);
        let remaining = mp.observations.len();
        let ref_gone = mp.ref_kf == kf;
        if ref_gone && let Some(first) = mp.observations.first() {
            mp.ref_kf = first.0;
        }
        if let Some(k) = self.keyframe_mut(kf)
            && let Some(s) = k.points.get_mut(idx as usize)
            && *s == Some(p)
        {
            *s = None;
        }
        if remaining < 2 {
            self.erase_point(p);
            return true;
        }
        false
    }

    /// Erase a point and every reference to it.
    pub fn erase_point(&mut self, p: PointId) {
        let Some(slot) = self.points.get_mut(p.0 as usize) else {
            return;
        };
        let Some(mp) = slot.take() else {
            return;
        };
        self.n_points -= 1;
        for (kf, idx) in mp.observations {
            if let Some(k) = self.keyframe_mut(kf)
                && let Some(s) = k.points.get_mut(idx as usize)
                && *s == Some(p)
            {
                *s = None;
            }
        }
    }

    /// Replace point `old` by `new` everywhere (fusion of duplicates): the
    /// observations of `old` move to `new` where the keyframe does not
    /// already see `new`; `old` is erased.
    pub fn replace_point(&mut self, old: PointId, new: PointId) {
        if old == new || self.point(new).is_none() {
            return;
        }
        let Some(mp_old) = self.points.get_mut(old.0 as usize).and_then(Option::take) else {
            return;
        };
        self.n_points -= 1;
        let (visible, found) = (mp_old.visible, mp_old.found);
        for (kf, idx) in mp_old.observations {
            let already = self.point(new).is_some_and(|m| m.index_in(kf).is_some());
            if let Some(k) = self.keyframe_mut(kf)
                && let Some(s) = k.points.get_mut(idx as usize)
            {
                *s = None;
            }
            if !already {
                self.add_observation(new, kf, idx);
            }
        }
        if let Some(mp) = self.point_mut(new) {
            mp.visible += visible;
            mp.found += found;
        }
        self.update_point_descriptor(new);
        self.update_point_normal_and_depth(new);
    }

    /// Keeps keyframe `id` from culling (an operator's shot is drawn on
    /// it); false when no such keyframe lives in the map.
    pub fn pin_keyframe(&mut self, id: KeyFrameId) -> bool {
        if self.keyframe(id).is_none() {
            return false;
        }
        self.pinned.insert(id);
        true
    }

    /// Erase a keyframe: its observations are removed (points left with
    /// fewer than 2 are erased), its children move to its parent, its
    /// covisibility edges go, and its pose relative to its parent is kept in
    /// [`Map::culled`]. The first keyframe (no parent), the keyframes of
    /// loop edges and pinned keyframes ([`Map::pin_keyframe`]) are never
    /// erased.
    pub fn erase_keyframe(&mut self, id: KeyFrameId) -> bool {
        let Some(kf) = self.keyframe(id) else {
            return false;
        };
        let Some(parent) = kf.parent else {
            return false;
        };
        if self.loop_edges.iter().any(|e| e.0 == id || e.1 == id) || self.pinned.contains(&id) {
            return false;
        }
        let Some(parent_kf) = self.keyframe(parent) else {
            return false;
        };
        let cam_from_parent = kf.cam_from_world * parent_kf.cam_from_world.inverse();
        let children = kf.children.clone();
        let covis: Vec<KeyFrameId> = kf.covisible.iter().map(|c| c.0).collect();
        let observed: Vec<PointId> = kf.points.iter().flatten().copied().collect();
        for p in observed {
            self.erase_observation(p, id);
        }
        for c in covis {
            if let Some(k) = self.keyframe_mut(c) {
                k.covisible.retain(|e| e.0 != id);
            }
        }
        // Children: re-parent to the erased keyframe's parent.
        for c in &children {
            if let Some(k) = self.keyframe_mut(*c) {
                k.parent = Some(parent);
            }
        }
        if let Some(p) = self.keyframe_mut(parent) {
            p.children.retain(|c| *c != id);
            p.children.extend(children.iter().copied());
        }
        self.culled.insert(
            id,
            CulledKeyFrame {
                parent,
                cam_from_parent,
            },
        );
        self.keyframes[id.0 as usize] = None;
        self.n_keyframes -= 1;
        if let Some(places) = &mut self.places {
            places.database.remove(Places::db_id(id));
            places.features.remove(&id);
        }
        true
    }

    /// The pose (cam_from_world) of a keyframe, live or culled.
    pub fn keyframe_pose(&self, id: KeyFrameId) -> Option<Isometry3<f64>> {
        let mut id = id;
        let mut chain = Isometry3::identity();
        for _ in 0..100_000 {
            if let Some(kf) = self.keyframe(id) {
                return Some(chain * kf.cam_from_world);
            }
            let c = self.culled.get(&id)?;
            chain *= c.cam_from_parent;
            id = c.parent;
        }
        None
    }

    /// Recompute the covisibility edges of `id` from shared points, on both
    /// ends, and give it a parent (its strongest neighbour) if it has none
    /// and is not the first keyframe.
    pub fn update_connections(&mut self, id: KeyFrameId) {
        let Some(kf) = self.keyframe(id) else {
            return;
        };
        let mut counts: HashMap<KeyFrameId, u32> = HashMap::new();
        for p in kf.points.iter().flatten() {
            if let Some(mp) = self.point(*p) {
                for (other, _) in &mp.observations {
                    if *other != id {
                        *counts.entry(*other).or_insert(0) += 1;
                    }
                }
            }
        }
        let root = self.is_root(id);
        let had_parent = kf.parent.is_some();
        if counts.is_empty() {
            return;
        }
        let th = self.covisibility_threshold;
        let (best_id, best_w) = counts
            .iter()
            .max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0)))
            .map(|(k, w)| (*k, *w))
            .unwrap_or((id, 0));
        let mut edges: Vec<(KeyFrameId, u32)> = counts
            .iter()
            .filter(|e| *e.1 >= th)
            .map(|(k, w)| (*k, *w))
            .collect();
        if edges.is_empty() {
            edges.push((best_id, best_w));
        }
        edges.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        // Symmetric update on the other ends.
        for (other, w) in counts {
            let keep = w >= th || other == best_id;
            if let Some(k) = self.keyframe_mut(other) {
                k.covisible.retain(|e| e.0 != id);
                if keep {
                    let pos = k
                        .covisible
                        .partition_point(|e| e.1 > w || (e.1 == w && e.0 < id));
                    k.covisible.insert(pos, (id, w));
                }
            }
        }
        if let Some(k) = self.keyframe_mut(id) {
            // Edges that vanished on this side vanish on the other too.
            let old: Vec<KeyFrameId> = k.covisible.iter().map(|e| e.0).collect();
            k.covisible = edges.clone();
            for o in old {
                if !edges.iter().any(|e| e.0 == o)
                    && let Some(ok) = self.keyframe_mut(o)
                {
                    ok.covisible.retain(|e| e.0 != id);
                }
            }
        }
        if !had_parent && !root && best_id != id {
            if let Some(k) = self.keyframe_mut(id) {
                k.parent = Some(best_id);
            }
            if let Some(p) = self.keyframe_mut(best_id) {
                p.children.push(id);
            }
        }
    }

    /// Choose the representative descriptor of a point: the one with the
    /// least median Hamming distance to the point's other descriptors.
    pub fn update_point_descriptor(&mut self, p: PointId) {
        let Some(mp) = self.point(p) else {
            return;
        };
        let descs: Vec<Descriptor> = mp
            .observations
            .iter()
            .filter_map(|(kf, idx)| {
                self.keyframe(*kf)
                    .and_then(|k| k.descriptors.get(*idx as usize))
                    .copied()
            })
            .collect();
        if descs.is_empty() {
            return;
        }
        let n = descs.len();
        let mut best = (u32::MAX, 0usize);
        let mut row = vec![0u32; n];
        for i in 0..n {
            for j in 0..n {
                row[j] = hamming(&descs[i], &descs[j]);
            }
            row.sort_unstable();
            let median = row[(n - 1) / 2];
            if median < best.0 {
                best = (median, i);
            }
        }
        let d = descs[best.1];
        if let Some(mp) = self.point_mut(p) {
            mp.descriptor = d;
        }
    }

    /// Recompute a point's mean viewing direction and scale-invariance range.
    pub fn update_point_normal_and_depth(&mut self, p: PointId) {
        let Some(mp) = self.point(p) else {
            return;
        };
        let pos = mp.position.coords;
        let mut normal = Vector3::zeros();
        let mut n = 0;
        for (kf, _) in &mp.observations {
            if let Some(k) = self.keyframe(*kf) {
                let v = pos - k.center();
                let norm = v.norm();
                if norm > 0.0 {
                    normal += v / norm;
                    n += 1;
                }
            }
        }
        let ref_kf = if self.keyframe(mp.ref_kf).is_some() {
            mp.ref_kf
        } else {
            match mp.observations.first() {
                Some(o) => o.0,
                None => return,
            }
        };
        let Some(rk) = self.keyframe(ref_kf) else {
            return;
        };
        let Some(idx) = mp.index_in(ref_kf) else {
            return;
        };
        let dist = (pos - rk.center()).norm();
        let octave = rk
            .keypoints
            .get(idx as usize)
            .map_or(0, |k| k.octave as usize);
        let level_scale = self.scale.scale_factors.get(octave).copied().unwrap_or(1.0);
        let top = self.scale.scale_factors.last().copied().unwrap_or(1.0);
        let max_distance = dist * level_scale;
        let min_distance = max_distance / top;
        if let Some(mp) = self.point_mut(p) {
            if n > 0 {
                mp.normal = (normal / n as f64).normalize();
            }
            mp.ref_kf = ref_kf;
            mp.max_distance = max_distance;
            mp.min_distance = min_distance;
        }
    }

    /// Median depth of the keyframe's points in its camera: the lower median
    /// (nearest-rank 50 % quantile, ORB-SLAM's scene median depth); None
    /// without points.
    pub fn median_depth(&self, id: KeyFrameId) -> Option<f64> {
        let kf = self.keyframe(id)?;
        let depths: Vec<f64> = kf
            .points
            .iter()
            .flatten()
            .filter_map(|p| self.point(*p))
            .map(|mp| (kf.cam_from_world * mp.position).z)
            .collect();
        crate::stats::quantile(&depths, 0.5)
    }

    /// Check the map's invariants; the first violation.
    pub fn check_invariants(&self) -> Result<(), MapError> {
        use MapError::Invariant as Broken;
        use Violation as V;
        if let Some(places) = &self.places {
            for id in places.features.keys() {
                if self.keyframe(*id).is_none() {
                    return Err(Broken(V::IndexedErased { keyframe: *id }));
                }
                if !places.database.contains(Places::db_id(*id)) {
                    return Err(Broken(V::NotInDatabase { keyframe: *id }));
                }
            }
            if places.database.len() != places.features.len() {
                return Err(Broken(V::DatabaseSize {
                    database: places.database.len(),
                    features: places.features.len(),
                }));
            }
        }
        let mut n_kf = 0;
        for kf in self.keyframes() {
            n_kf += 1;
            if kf.points.len() != kf.keypoints.len() || kf.descriptors.len() != kf.keypoints.len() {
                return Err(Broken(V::SlotCounts { keyframe: kf.id }));
            }
            for (i, p) in kf.points.iter().enumerate() {
                if let Some(p) = p {
                    let Some(mp) = self.point(*p) else {
                        return Err(Broken(V::DanglingPoint {
                            keyframe: kf.id,
                            slot: i,
                            point: *p,
                        }));
                    };
                    if mp.index_in(kf.id) != Some(i as u32) {
                        return Err(Broken(V::PointMissesKeyFrame {
                            keyframe: kf.id,
                            slot: i,
                            point: *p,
                        }));
                    }
                }
            }
            for (o, w) in &kf.covisible {
                let Some(other) = self.keyframe(*o) else {
                    return Err(Broken(V::DanglingCovisible {
                        keyframe: kf.id,
                        covisible: *o,
                    }));
                };
                if self.map_of(*o) != self.map_of(kf.id) {
                    return Err(Broken(V::CrossMap { a: kf.id, b: *o }));
                }
                if other.weight(kf.id) != *w {
                    return Err(Broken(V::AsymmetricCovisibility {
                        a: kf.id,
                        b: *o,
                        a_to_b: *w,
                        b_to_a: other.weight(kf.id),
                    }));
                }
            }
            if let Some(p) = kf.parent {
                let Some(pk) = self.keyframe(p) else {
                    return Err(Broken(V::DanglingParent {
                        keyframe: kf.id,
                        parent: p,
                    }));
                };
                if self.map_of(p) != self.map_of(kf.id) {
                    return Err(Broken(V::CrossMap { a: kf.id, b: p }));
                }
                if !pk.children.contains(&kf.id) {
                    return Err(Broken(V::ParentMissesChild {
                        keyframe: kf.id,
                        parent: p,
                    }));
                }
            }
            for c in &kf.children {
                if self.keyframe(*c).and_then(|k| k.parent) != Some(kf.id) {
                    return Err(Broken(V::ChildHasOtherParent {
                        keyframe: kf.id,
                        child: *c,
                    }));
                }
            }
        }
        if n_kf != self.n_keyframes {
            return Err(Broken(V::KeyFrameCount {
                live: n_kf,
                counted: self.n_keyframes,
            }));
        }
        let mut n_p = 0;
        for mp in self.points() {
            n_p += 1;
            for (kf, idx) in &mp.observations {
                let Some(k) = self.keyframe(*kf) else {
                    return Err(Broken(V::DanglingObserver {
                        point: mp.id,
                        keyframe: *kf,
                    }));
                };
                if let Some((first, _)) = mp.observations.first()
                    && self.map_of(*kf) != self.map_of(*first)
                {
                    return Err(Broken(V::CrossMap { a: *kf, b: *first }));
                }
                if k.points.get(*idx as usize).copied().flatten() != Some(mp.id) {
                    return Err(Broken(V::SlotMissesPoint {
                        point: mp.id,
                        keyframe: *kf,
                        slot: *idx,
                    }));
                }
            }
        }
        if n_p != self.n_points {
            return Err(Broken(V::PointCount {
                live: n_p,
                counted: self.n_points,
            }));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use nalgebra::Translation3;

    fn kf(n: usize, x: f64) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: x,
            cam_from_world: Isometry3::from_parts(
                Translation3::new(-x, 0.0, 0.0),
                Default::default(),
            ),
            keypoints: vec![KeyPoint::default(); n],
            descriptors: vec![[0; 4]; n],
            points: vec![None; n],
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        }
    }

    fn map_with(n_kf: usize, n_pts: usize) -> Map {
        let cam = Camera::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            Distortion::default(),
        )
        .unwrap();
        let mut m = Map::new(cam, ScaleInfo::new(1.2, 8));
        m.covisibility_threshold = 2;
        let ids: Vec<KeyFrameId> = (0..n_kf)
            .map(|i| m.add_keyframe(kf(n_pts, i as f64 * 0.1)))
            .collect();
        for j in 0..n_pts {
            let p = m.add_point(
                Point3::new(j as f64 * 0.01, 0.0, 2.0),
                [j as u64; 4],
                ids[0],
            );
            for &k in &ids {
                assert!(m.add_observation(p, k, j as u32));
            }
            m.update_point_normal_and_depth(p);
        }
        for &k in &ids {
            m.update_connections(k);
        }
        m
    }

    #[test]
    fn observations_stay_two_way_through_edits() {
        let mut m = map_with(4, 10);
        m.check_invariants().unwrap();
        assert_eq!(m.keyframe(KeyFrameId(0)).unwrap().covisible.len(), 3);
        assert_eq!(m.keyframe(KeyFrameId(2)).unwrap().weight(KeyFrameId(1)), 10);
        // A slot already holding another point is not overwritten.
        assert!(!m.add_observation(PointId(1), KeyFrameId(0), 0));
        // Erasing observations down to one erases the point.
        for k in 0..3 {
            m.erase_observation(PointId(3), KeyFrameId(k));
        }
        assert!(m.point(PointId(3)).is_none());
        m.check_invariants().unwrap();
        // Fusion: point 4's observations move to point 5 where possible.
        m.erase_observation(PointId(5), KeyFrameId(3));
        m.replace_point(PointId(4), PointId(5));
        assert!(m.point(PointId(4)).is_none());
        assert_eq!(m.point(PointId(5)).unwrap().observations.len(), 4);
        m.check_invariants().unwrap();
        // Erasing a keyframe re-parents its children and leaves no dangling id.
        let child_of_1: Vec<KeyFrameId> = m.keyframe(KeyFrameId(1)).unwrap().children.clone();
        let pose_before = m.keyframe(KeyFrameId(1)).unwrap().cam_from_world;
        // A keyframe a shot is drawn on is kept; a missing one cannot be pinned.
        assert!(m.pin_keyframe(KeyFrameId(2)));
        assert!(!m.erase_keyframe(KeyFrameId(2)));
        assert!(!m.pin_keyframe(KeyFrameId(99)));
        assert!(m.erase_keyframe(KeyFrameId(1)));
        m.check_invariants().unwrap();
        for c in child_of_1 {
            assert_ne!(m.keyframe(c).unwrap().parent, Some(KeyFrameId(1)));
        }
        // Its pose can still be recovered through its parent.
        let pose_after = m.keyframe_pose(KeyFrameId(1)).unwrap();
        assert!((pose_after.translation.vector - pose_before.translation.vector).norm() < 1e-12);
        // The first keyframe is never erased.
        assert!(!m.erase_keyframe(KeyFrameId(0)));
        assert_eq!(m.keyframe_count(), 3);
    }

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

    #[test]
    fn a_similarity_moves_every_pose_point_and_culled_keyframe() {
        let mut m = map_with(4, 10);
        assert!(m.erase_keyframe(KeyFrameId(2)));
        let ids = [0, 1, 2, 3].map(KeyFrameId);
        let before: Vec<Isometry3<f64>> = ids
            .iter()
            .map(|&k| m.keyframe_pose(k).unwrap().inverse())
            .collect();
        let p_before = m.point(PointId(4)).unwrap().position;
        let s = Sim3::new(
            nalgebra::UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
            Vector3::new(5.0, -2.0, -30.0),
            12.5,
        );
        m.apply_sim3(&s);
        assert_eq!(m.scale_applied(), 12.5);
        assert_eq!(m.corrections(), 1);
        for (k, b) in ids.iter().zip(&before) {
            let after = m.keyframe_pose(*k).unwrap().inverse();
            let want = s.transform_pose(b);
            assert!((after.translation.vector - want.translation.vector).norm() < 1e-9);
            assert!(after.rotation.angle_to(&want.rotation) < 1e-9);
        }
        let p = m.point(PointId(4)).unwrap();
        assert!((p.position - s.transform_point(&p_before)).norm() < 1e-9);
        m.check_invariants().unwrap();
    }

    /// A second map beside `map_with`'s, merged into it by a similarity:
    /// the keyframes move, the tree stays a tree, one map is left.
    #[test]
    fn a_second_map_is_kept_apart_then_merged() {
        let mut m = map_with(3, 10);
        assert_eq!(m.first_map(), Some(MapId(0)));
        let b = m.start_map();
        assert_eq!(b, MapId(1));
        let ids: Vec<KeyFrameId> = (0..3)
            .map(|i| m.add_keyframe(kf(10, 5.0 + i as f64)))
            .collect();
        for j in 0..10 {
            let p = m.add_point(
                Point3::new(j as f64 * 0.01, 1.0, 2.0),
                [j as u64; 4],
                ids[0],
            );
            for &k in &ids {
                assert!(m.add_observation(p, k, j as u32));
            }
            m.update_point_normal_and_depth(p);
        }
        for &k in &ids {
            m.update_connections(k);
        }
        m.check_invariants().unwrap();
        assert_eq!(m.maps(), vec![(MapId(0), 3), (MapId(1), 3)]);
        assert_eq!(m.root_of(b), Some(ids[0]));
        assert_eq!(m.keyframe(ids[0]).unwrap().parent, None, "a new map's root");
        assert_eq!(m.only(MapId(0)).keyframe_count(), 3);
        // Merge: the new map moved by s into map 0, hung from keyframe 2
        // through its keyframe ids[2].
        let s = Sim3::new(
            nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0),
            Vector3::new(1.0, 0.0, 0.0),
            2.0,
        );
        let before = m.keyframe(ids[1]).unwrap().world_from_cam();
        assert!(
            !m.merge_maps(b, MapId(0), &s, KeyFrameId(2), ids[2]),
            "wrong sides"
        );
        assert!(m.merge_maps(b, MapId(0), &s, ids[2], KeyFrameId(2)));
        m.check_invariants().unwrap();
        assert_eq!(m.maps(), vec![(MapId(0), 6)]);
        assert_eq!(m.active_map(), MapId(0));
        let after = m.keyframe(ids[1]).unwrap().world_from_cam();
        let want = s.transform_pose(&before);
        assert!((after.translation.vector - want.translation.vector).norm() < 1e-9);
        assert_eq!(m.keyframe(ids[2]).unwrap().parent, Some(KeyFrameId(2)));
        assert!(
            m.keyframe(ids[0]).unwrap().parent.is_some(),
            "the old root hangs below"
        );
        assert_eq!(m.merges().len(), 1);
        assert_eq!(m.merges()[0].keyframes, ids);
        // A new map whose initialisation failed is erased, the rest kept.
        let c = m.start_map();
        let k = m.add_keyframe(kf(10, 9.0));
        m.discard_map(c);
        assert!(m.keyframe(k).is_none());
        assert_eq!(m.discarded(), &[k]);
        m.check_invariants().unwrap();
    }

    #[test]
    fn scale_prediction_matches_orb_slam() {
        let s = ScaleInfo::new(1.2, 8);
        assert_eq!(s.predict_level(10.0, 10.0), 0);
        assert_eq!(s.predict_level(10.0, 10.0 / 1.2 / 1.2 * 1.01), 2);
        assert_eq!(s.predict_level(10.0, 0.001), 7);
        assert_eq!(s.predict_level(10.0, 20.0), 0);
    }
}
