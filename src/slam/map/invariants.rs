//! The map's invariants checked ([`Map::check_invariants`]; the first
//! violation as a [`Violation`]):
//! - a point lists keyframe `k` at keypoint `i` exactly when keyframe `k`'s
//!   slot `i` holds that point;
//! - no live object refers to an erased id;
//! - covisibility weights are symmetric;
//! - the place index (BoW database) holds exactly the indexed live keyframes;
//! - no covisibility edge, parent link or point joins two maps.

use super::error::{MapError, Violation};
use super::places::Places;
use super::store::Map;

impl Map {
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
