//! The keyframes in the map's graphs: a keyframe inserted, pinned (never
//! culled) or culled (its pose kept relative to its parent, its children
//! moved to its parent), a culled keyframe's pose, and the covisibility
//! edges with the spanning tree kept up to date
//! ([`Map::update_connections`]).

use std::collections::HashMap;

use nalgebra::Isometry3;

use super::ids::{KeyFrameId, PointId};
use super::keyframe::{CulledKeyFrame, KeyFrame};
use super::places::Places;
use super::store::Map;

impl Map {
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
}
