//! Detection, steps 1 and 2 of the module doc: BoW candidates from the
//! keyframe database (a loop's in the keyframe's own map, outside its
//! covisible neighbourhood and above their lowest score; a merge's in the
//! other maps, by normalised score alone), then consistency: a candidate's
//! group (it and its covisible keyframes) must overlap a group of the
//! previous keyframe's, `consistency` keyframes in a row.

use std::collections::HashSet;

use crate::bow::CandidateParams;
use crate::slam::map::{KeyFrameId, Map, Places};

use super::params::LoopParams;

/// Steps 1 and 2: the candidates consistent over enough keyframes;
/// loop candidates in `kf`'s own map, merge candidates (`merge`) in
/// the other maps. `groups` are the previous keyframe's candidate
/// groups of that kind.
pub(super) fn detect(
    p: &LoopParams,
    last_loop: Option<KeyFrameId>,
    groups: &mut Vec<(HashSet<KeyFrameId>, usize)>,
    map: &Map,
    kf: KeyFrameId,
    merge: bool,
) -> Vec<KeyFrameId> {
    let Some(k) = map.keyframe(kf) else {
        return Vec::new();
    };
    let Some(places) = map.places() else {
        return Vec::new();
    };
    let Some(bow) = places.database.bow(Places::db_id(kf)) else {
        return Vec::new();
    };
    let my_map = map.map_of(kf);
    let in_my_map = my_map.map_or(0, |id| map.keyframes_in(id).count());
    let too_early = if merge {
        in_my_map < p.merge_min_keyframes || map.maps().len() < 2
    } else {
        in_my_map < p.min_keyframes
            || last_loop.is_some_and(|l| (kf.0 as usize) < l.0 as usize + p.min_keyframes)
    };
    if too_early {
        groups.clear();
        return Vec::new();
    }
    let connected: HashSet<KeyFrameId> = k.covisible.iter().map(|c| c.0).collect();
    let mut min_score = f32::INFINITY;
    for c in &connected {
        if let Some(b) = places.database.bow(Places::db_id(*c)) {
            min_score = min_score.min(bow.l1_score(b));
        }
    }
    if !min_score.is_finite() {
        groups.clear();
        return Vec::new();
    }
    // A merge looks into other maps: a young map's few keyframes
    // resemble each other far more than any view of another map does,
    // so the loop's score floor would hide every candidate (ORB-SLAM3
    // takes the best groups for merges, without the floor). Nor are
    // keyframes pre-filtered by words in common: the old map's two
    // initialisation keyframes (twice the features) share the most
    // words with anything and would be the only ones scored; the
    // normalised score does not favour them.
    let cp = if merge {
        CandidateParams {
            min_score: 0.0,
            min_common_words_ratio: 0.0,
            ..CandidateParams::default()
        }
    } else {
        CandidateParams {
            min_score,
            ..CandidateParams::default()
        }
    };
    let neighbours = cp.covisible_neighbours;
    let candidates = places.database.detect_candidates(
        bow,
        &cp,
        |id| {
            Places::map_id(id).is_none_or(|id| {
                let same = map.map_of(id) == my_map;
                id == kf || connected.contains(&id) || same == merge
            })
        },
        |id, out| {
            if let Some(k) = Places::map_id(id).and_then(|id| map.keyframe(id)) {
                out.extend(k.best_covisible(neighbours).map(Places::db_id));
            }
        },
    );
    // Consistency with the previous keyframe's groups.
    let mut current_groups: Vec<(HashSet<KeyFrameId>, usize)> = Vec::new();
    let mut extended = vec![false; groups.len()];
    let mut consistent = Vec::new();
    for c in candidates {
        let Some(cid) = Places::map_id(c.id) else {
            continue;
        };
        let Some(ck) = map.keyframe(cid) else {
            continue;
        };
        let group: HashSet<KeyFrameId> = std::iter::once(cid)
            .chain(ck.best_covisible(p.group_neighbours))
            .collect();
        let mut enough = false;
        let mut consistent_for_some = false;
        for (g, (prev, n)) in groups.iter().enumerate() {
            if prev.is_disjoint(&group) {
                continue;
            }
            consistent_for_some = true;
            let count = n + 1;
            if !extended[g] {
                current_groups.push((group.clone(), count));
                extended[g] = true;
            }
            if count >= p.consistency && !enough {
                consistent.push(cid);
                enough = true;
            }
        }
        if !consistent_for_some {
            current_groups.push((group, 0));
        }
    }
    *groups = current_groups;
    consistent
}
