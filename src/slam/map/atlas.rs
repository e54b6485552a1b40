//! The atlas: every keyframe belongs to one map of the [`Map`] ([`MapId`];
//! a point to its observers' map). Tracking extends the active map; after a
//! tracking loss a new map is started beside the old ones
//! ([`Map::start_map`]), and loop closing merges it into an old one
//! ([`Map::merge_maps`]: moved by a similarity, its spanning tree hung from
//! the old map, a [`MergeRecord`] kept) when it sees a common place; a new
//! map whose initialisation did not hold is discarded ([`Map::discard_map`]).
//! Each map has its own root keyframe (the first, never culled, the gauge
//! of its bundle adjustments). Also the whole map moved by a similarity
//! ([`Map::apply_sim3`]: telemetry priors put it in local NED).

use crate::lie::{Sim3, renormalized};

use super::ids::{KeyFrameId, MapId, PointId};
use super::keyframe::KeyFrame;
use super::places::Places;
use super::store::{Map, MergeRecord};

impl Map {
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
    pub(super) fn is_root(&self, id: KeyFrameId) -> bool {
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

    pub(super) fn recompute_roots(&mut self) {
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
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Point3, Vector3};

    use super::*;
    use crate::slam::map::testing::{kf, map_with};

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
}
