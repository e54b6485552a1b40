//! The [`Map`] itself: keyframes and points in arenas by id (boxed: an id
//! no longer live costs a pointer), the culled keyframes, the place index
//! ([`Places`]), loop edges, pins, the correction count, the frame the map
//! is in ([`MapMode`]) and the atlas's books (each keyframe's map, the
//! active map, each map's root, the merges as [`MergeRecord`]s). Here: an
//! empty map, a map rebuilt from its parts (the map file), and reading the
//! stores. What changes them is in the files beside it: `atlas.rs` (maps
//! and merges), `graph.rs` (keyframes), `observations.rs` (points),
//! `indexing.rs` (the place index).

use std::collections::HashMap;

use crate::camera::Camera;
use crate::lie::Sim3;

use super::error::MapError;
use super::ids::{KeyFrameId, MapId, PointId};
use super::keyframe::{CulledKeyFrame, KeyFrame};
use super::places::Places;
use super::point::MapPoint;
use super::scale::ScaleInfo;

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
    pub(super) keyframes: Vec<Option<Box<KeyFrame>>>,
    /// By id; boxed (see `keyframes`).
    pub(super) points: Vec<Option<Box<MapPoint>>>,
    pub(super) n_keyframes: usize,
    pub(super) n_points: usize,
    /// Removed keyframes, for placing frames referring to them.
    pub culled: HashMap<KeyFrameId, CulledKeyFrame>,
    /// Keyframes with fewer shared points are not covisibility neighbours.
    pub covisibility_threshold: u32,
    pub(super) places: Option<Places>,
    /// Loop edges of the essential graph (keyframes joined by a loop
    /// closure); their keyframes are never culled.
    pub(super) loop_edges: Vec<(KeyFrameId, KeyFrameId)>,
    /// Keyframes the operator drew a shot on: never culled, so the shot
    /// can be asked again on them (not saved: the daemon pins its shots'
    /// keyframes again when it loads a map).
    pub(super) pinned: std::collections::HashSet<KeyFrameId>,
    /// Loop corrections applied (tracking re-places its last frame when
    /// this changes).
    pub(super) corrections: u64,
    /// The frame the map is in (in the map file since version 5).
    pub(super) mode: MapMode,
    /// Product of the scales of the similarities applied to the whole map
    /// ([`Map::apply_sim3`]; tracking rescales its relative poses when this
    /// changes).
    pub(super) scale_applied: f64,
    /// The map of every keyframe id ever given (live or culled), by id.
    pub(super) kf_maps: Vec<MapId>,
    /// The map new keyframes go to.
    pub(super) active_map: MapId,
    /// The next map id [`Map::start_map`] gives.
    pub(super) next_map: u32,
    /// Each map's first keyframe (the root of its spanning tree, never
    /// culled and never given a parent by [`Map::update_connections`]).
    pub(super) roots: HashMap<MapId, KeyFrameId>,
    /// The merges so far, in order (tracking rescales the relative poses
    /// of its frames placed on a merged map's keyframes).
    pub(super) merges: Vec<MergeRecord>,
    /// Keyframes of new maps whose initialisation did not hold
    /// ([`Map::discard_map`]): erased, neither live nor culled.
    pub(super) discarded: Vec<KeyFrameId>,
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
}
