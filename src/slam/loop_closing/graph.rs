//! The essential graph of a correction in Sim(3) ([`EssentialGraph`], the
//! adapter between the map and [`crate::optimize::optimize_pose_graph`]):
//! spanning tree, loop edges, covisibility edges of weight at least
//! `essential_min_weight` and the correction's new links, the anchored
//! keyframes fixed; built under the map lock, solved on its own copy of the
//! poses (a loop's without the lock), written back under the lock (a
//! keyframe added meanwhile keeps its pose relative to the keyframe it
//! follows, every point follows a keyframe). A merge builds, solves and
//! applies it at once ([`optimize_essential_graph`]).

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use crate::lie::Sim3;
use crate::optimize::{PoseGraph, PoseGraphParams, Sim3Edge, optimize_pose_graph};
use crate::slam::map::{KeyFrameId, Map, PointId};

use super::params::LoopParams;
use super::sim3::sim3_to_isometry;

/// The essential graph in Sim(3) over the keyframes `graph_kfs` (one
/// map's), those in `anchored` fixed (a loop: the loop keyframe; a merge:
/// the old map's keyframes); keyframe poses and the points of those
/// keyframes updated. Returns the number of edges.
#[allow(clippy::too_many_arguments)]
pub(super) fn optimize_essential_graph(
    map: &mut Map,
    graph_kfs: Vec<KeyFrameId>,
    anchored: &HashSet<KeyFrameId>,
    loop_kf: KeyFrameId,
    current: KeyFrameId,
    corrected: &HashMap<KeyFrameId, Sim3>,
    uncorrected: &HashMap<KeyFrameId, Sim3>,
    corrected_by: HashMap<PointId, KeyFrameId>,
    loop_links: &[(KeyFrameId, KeyFrameId)],
    p: &LoopParams,
) -> usize {
    let mut eg = EssentialGraph::build(
        map,
        graph_kfs,
        anchored,
        loop_kf,
        current,
        corrected,
        uncorrected,
        corrected_by,
        loop_links,
        p,
        Instant::now(),
    );
    if eg.solve(&p.pose_graph) {
        eg.apply(map);
    }
    eg.edges
}

/// The essential graph of a correction: built from the map (under its
/// lock), solved on its own copy of the poses (a loop's without the lock:
/// tracking goes on meanwhile), then written back (under the lock again).
pub(super) struct EssentialGraph {
    /// The keyframes of the graph, in vertex order.
    ids: Vec<KeyFrameId>,
    /// Vertex of each keyframe.
    index: HashMap<KeyFrameId, usize>,
    /// The largest id in it (keyframes added later follow a vertex).
    max_id: KeyFrameId,
    /// The keyframe that closed the loop (or made the merge).
    current: KeyFrameId,
    graph: PoseGraph,
    /// The poses before the solve (corrected where the loop corrected them).
    initial: Vec<Sim3>,
    /// Points corrected with a keyframe of the loop's neighbourhood: they
    /// follow that keyframe.
    corrected_by: HashMap<PointId, KeyFrameId>,
    /// Its edges.
    pub(super) edges: usize,
    /// When the correction it belongs to started.
    pub(super) started: Instant,
}

impl EssentialGraph {
    /// The graph of the keyframes `graph_kfs` (the live ones): spanning
    /// tree, loop edges, strong covisibility, the new links of the loop
    /// (measured with the corrected poses), and `anchored` held fixed (the
    /// first vertex when none is).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn build(
        map: &Map,
        graph_kfs: Vec<KeyFrameId>,
        anchored: &HashSet<KeyFrameId>,
        loop_kf: KeyFrameId,
        current: KeyFrameId,
        corrected: &HashMap<KeyFrameId, Sim3>,
        uncorrected: &HashMap<KeyFrameId, Sim3>,
        corrected_by: HashMap<PointId, KeyFrameId>,
        loop_links: &[(KeyFrameId, KeyFrameId)],
        p: &LoopParams,
        started: Instant,
    ) -> Self {
        let ids: Vec<KeyFrameId> = graph_kfs
            .into_iter()
            .filter(|id| map.keyframe(*id).is_some())
            .collect();
        let index: HashMap<KeyFrameId, usize> =
            ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
        let mut poses = Vec::with_capacity(ids.len());
        let mut plain = Vec::with_capacity(ids.len());
        for id in &ids {
            let Some(k) = map.keyframe(*id) else { continue };
            let s = corrected
                .get(id)
                .copied()
                .unwrap_or_else(|| Sim3::from_isometry(&k.cam_from_world));
            poses.push(s);
            plain.push(uncorrected.get(id).copied().unwrap_or(s));
        }
        let mut fixed: Vec<bool> = ids.iter().map(|id| anchored.contains(id)).collect();
        if !fixed.iter().any(|f| *f)
            && let Some(f) = fixed.first_mut()
        {
            *f = true;
        }
        let mut edges: Vec<Sim3Edge> = Vec::new();
        let mut have: HashSet<(usize, usize)> = HashSet::new();
        let mut push = |i: usize, j: usize, s_ji: Sim3, edges: &mut Vec<Sim3Edge>| {
            let key = (i.min(j), i.max(j));
            if i != j && have.insert(key) {
                edges.push(Sim3Edge {
                    i,
                    j,
                    s_ji,
                    weight: 1.0,
                });
            }
        };
        // New loop links, measured with the corrected poses.
        for (a, b) in loop_links {
            let (Some(&i), Some(&j)) = (index.get(a), index.get(b)) else {
                continue;
            };
            let w = map.keyframe(*a).map_or(0, |k| k.weight(*b));
            let is_loop = (*a == current && *b == loop_kf) || (*b == current && *a == loop_kf);
            if !is_loop && w < p.essential_min_weight {
                continue;
            }
            push(i, j, poses[j].compose(&poses[i].inverse()), &mut edges);
        }
        // The closing edge itself, measured with the corrected poses.
        if let (Some(&i), Some(&j)) = (index.get(&current), index.get(&loop_kf)) {
            push(i, j, poses[j].compose(&poses[i].inverse()), &mut edges);
        }
        for (i, id) in ids.iter().enumerate() {
            let Some(k) = map.keyframe(*id) else { continue };
            let s_wi = plain[i].inverse();
            if let Some(parent) = k.parent
                && let Some(&j) = index.get(&parent)
            {
                push(i, j, plain[j].compose(&s_wi), &mut edges);
            }
            for (a, b) in map.loop_edges() {
                let other = if *a == *id {
                    *b
                } else if *b == *id {
                    *a
                } else {
                    continue;
                };
                if let Some(&j) = index.get(&other) {
                    push(i, j, plain[j].compose(&s_wi), &mut edges);
                }
            }
            for (o, w) in &k.covisible {
                if *w < p.essential_min_weight {
                    break;
                }
                if let Some(&j) = index.get(o) {
                    push(i, j, plain[j].compose(&s_wi), &mut edges);
                }
            }
        }
        let n_edges = edges.len();
        EssentialGraph {
            max_id: ids.iter().copied().max().unwrap_or(current),
            ids,
            index,
            current,
            initial: poses.clone(),
            graph: PoseGraph {
                poses,
                fixed,
                edges,
            },
            corrected_by,
            edges: n_edges,
            started,
        }
    }

    /// Optimise the poses (the map is not touched); false when the
    /// optimisation failed (logged; nothing to apply).
    pub(super) fn solve(&mut self, params: &PoseGraphParams) -> bool {
        match optimize_pose_graph(&mut self.graph, params) {
            Ok(summary) => {
                tracing::debug!(?summary, edges = self.edges, "essential graph optimised");
                true
            }
            Err(e) => {
                tracing::warn!("essential graph not optimised: {e}");
                false
            }
        }
    }

    /// The similarity that moves what vertex `i` carries (world_new ←
    /// world_old).
    fn point_move(&self, i: usize) -> Sim3 {
        self.graph.poses[i].inverse().compose(&self.initial[i])
    }

    /// Write the optimised poses back: the graph's keyframes take theirs;
    /// keyframes of the same map added since the graph was built keep
    /// their pose relative to their parent's vertex (the current
    /// keyframe's when their parent is not in the graph); every point
    /// moves with the keyframe it was corrected by, else its reference
    /// keyframe, else any observer in the graph.
    pub(super) fn apply(&self, map: &mut Map) {
        let my_map = map.map_of(self.current);
        let added: Vec<(KeyFrameId, usize)> = map
            .keyframes()
            .filter(|k| k.id > self.max_id && map.map_of(k.id) == my_map)
            .filter_map(|k| {
                let follow = k
                    .parent
                    .and_then(|p| self.index.get(&p))
                    .or_else(|| self.index.get(&self.current))?;
                Some((k.id, *follow))
            })
            .collect();
        for (id, i) in added {
            if let Some(k) = map.keyframe_mut(id) {
                let s = Sim3::from_isometry(&k.cam_from_world)
                    .compose(&self.initial[i].inverse())
                    .compose(&self.graph.poses[i]);
                k.cam_from_world = sim3_to_isometry(&s);
            }
        }
        for (i, id) in self.ids.iter().enumerate() {
            if let Some(k) = map.keyframe_mut(*id) {
                k.cam_from_world = sim3_to_isometry(&self.graph.poses[i]);
            }
        }
        let pids: Vec<PointId> = map.points().map(|mp| mp.id).collect();
        for pid in pids {
            let Some(mp) = map.point(pid) else { continue };
            let r = self
                .corrected_by
                .get(&pid)
                .copied()
                .filter(|r| self.index.contains_key(r))
                .or_else(|| Some(mp.ref_kf).filter(|r| self.index.contains_key(r)))
                .or_else(|| {
                    mp.observations
                        .iter()
                        .map(|o| o.0)
                        .find(|r| self.index.contains_key(r))
                });
            let Some(r) = r else { continue };
            let s_move = self.point_move(self.index[&r]);
            if let Some(mp) = map.point_mut(pid) {
                mp.position = s_move.transform_point(&mp.position);
            }
            map.update_point_normal_and_depth(pid);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::features::KeyPoint;
    use crate::matching::FeatureGrid;
    use crate::slam::map::KeyFrame;
    use nalgebra::{Isometry3, Point3};

    /// Keypoint slots of each keyframe.
    const SLOTS: usize = 60;

    fn keyframe(x: f64) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: x,
            cam_from_world: Isometry3::translation(-x, 0.0, 0.0),
            keypoints: vec![KeyPoint::default(); SLOTS],
            descriptors: vec![[0; 4]; SLOTS],
            points: vec![None; SLOTS],
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        }
    }

    /// Four keyframes along x in a chain: each shares points with the one
    /// before it (30, 25, 20: fewer further on, so each one's strongest
    /// neighbour, its parent, is the one before).
    fn chain() -> Map {
        let cam = Camera::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            Distortion::default(),
        )
        .unwrap();
        let mut m = Map::new(cam, crate::slam::ScaleInfo::new(1.2, 8));
        let ids: Vec<KeyFrameId> = (0..4).map(|i| m.add_keyframe(keyframe(i as f64))).collect();
        let mut next_slot = [0u32; 4];
        for b in 1..4 {
            for j in 0..(35 - 5 * b) {
                let p = m.add_point(
                    Point3::new(b as f64 + j as f64 * 0.02, 0.0, 5.0),
                    [j as u64; 4],
                    ids[b - 1],
                );
                for k in [b - 1, b] {
                    assert!(m.add_observation(p, ids[k], next_slot[k]));
                    next_slot[k] += 1;
                }
            }
        }
        for &k in &ids {
            m.update_connections(k);
        }
        for k in 1..4 {
            assert_eq!(m.keyframe(ids[k]).unwrap().parent, Some(ids[k - 1]));
        }
        m
    }

    /// The loop's graph is solved without the map lock, so tracking may
    /// add a keyframe meanwhile: written back, the graph moves it with
    /// the keyframe that closed the loop (its pose relative to it kept,
    /// the translation scaled as the graph scaled that keyframe's
    /// surroundings), and the loop keyframe stays where it was.
    #[test]
    fn a_keyframe_added_while_the_graph_is_solved_follows_the_current_keyframe() {
        let mut m = chain();
        let (first, current) = (KeyFrameId(0), KeyFrameId(3));
        let plain = Sim3::from_isometry(&m.keyframe(current).unwrap().cam_from_world);
        // The loop puts the current keyframe half a unit further along x
        // (the drift it corrects), as the correction's first step does.
        let fixed_pose = Isometry3::translation(-3.5, 0.0, 0.0);
        m.keyframe_mut(current).unwrap().cam_from_world = fixed_pose;
        let corrected = HashMap::from([(current, Sim3::from_isometry(&fixed_pose))]);
        let uncorrected = HashMap::from([(current, plain)]);
        let ids: Vec<KeyFrameId> = m.keyframes().map(|k| k.id).collect();
        let p = LoopParams::default();
        let mut graph = EssentialGraph::build(
            &m,
            ids,
            &HashSet::from([first]),
            first,
            current,
            &corrected,
            &uncorrected,
            HashMap::new(),
            &[(current, first)],
            &p,
            Instant::now(),
        );
        assert!(graph.edges >= 4, "{} edges", graph.edges);
        // Tracking adds a keyframe just past the current one meanwhile.
        let added = m.add_keyframe(keyframe(3.7));
        let before = m.keyframe(added).unwrap().cam_from_world
            * m.keyframe(current).unwrap().cam_from_world.inverse();
        let first_before = m.keyframe(first).unwrap().cam_from_world;
        let middle_before = m.keyframe(KeyFrameId(2)).unwrap().cam_from_world;
        assert!(graph.solve(&p.pose_graph));
        graph.apply(&mut m);
        let i = graph.index[&current];
        let scale = graph.graph.poses[i].scale / graph.initial[i].scale;
        let after = m.keyframe(added).unwrap().cam_from_world
            * m.keyframe(current).unwrap().cam_from_world.inverse();
        assert!(
            (after.translation.vector * scale - before.translation.vector).norm() < 1e-9,
            "{after:?} {before:?} scale {scale}"
        );
        assert!(after.rotation.angle_to(&before.rotation) < 1e-9);
        assert_eq!(m.keyframe(first).unwrap().cam_from_world, first_before);
        // The correction spread along the chain: the keyframe before the
        // current one moved too.
        let moved = (m
            .keyframe(KeyFrameId(2))
            .unwrap()
            .cam_from_world
            .translation
            .vector
            - middle_before.translation.vector)
            .norm();
        assert!(moved > 0.05, "moved {moved}");
        m.check_invariants().unwrap();
    }
}
