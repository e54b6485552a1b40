//! Candidate keyframes of a shot: its ORB features, the bag-of-words
//! index of the map's keyframes, descriptor matching against each
//! candidate's map points; and the nearest keyframes of a shot that was not
//! localised.

use std::collections::HashSet;

use image::GrayImage;
use nalgebra::Point3;

use super::outcome::NotLocalizedReason;
use super::params::LocalizeParams;
use crate::bow::{self, BowVector, KeyFrameDatabase, Vocabulary};
use crate::camera::Camera;
use crate::features::{self, Descriptor, OrbExtractor, hamming};
use crate::shot::ShotError;
use crate::slam::matcher::rotation_outliers;
use crate::slam::{KeyFrameId, Map, PointId};

/// A bag-of-words index of a map's keyframes: the vocabulary and a database
/// holding every keyframe's BoW vector.
pub struct BowIndex<'v> {
    vocabulary: &'v Vocabulary,
    database: KeyFrameDatabase,
}

impl<'v> BowIndex<'v> {
    /// Indexes every keyframe of `map` (its descriptors through `vocabulary`).
    pub fn build(map: &Map, vocabulary: &'v Vocabulary) -> Self {
        let mut database = KeyFrameDatabase::new(vocabulary.word_count());
        for kf in map.keyframes() {
            let v: BowVector = vocabulary.transform(&kf.descriptors);
            // Ids are unique in a map, so adding cannot collide.
            let _ = database.add(bow::KeyFrameId(kf.id.0 as u64), v);
        }
        BowIndex {
            vocabulary,
            database,
        }
    }

    /// Keyframes indexed.
    pub fn len(&self) -> usize {
        self.database.len()
    }

    /// True when no keyframe is indexed.
    pub fn is_empty(&self) -> bool {
        self.database.is_empty()
    }
}

/// For every shot descriptor, its best match among `cand` (point, descriptor)
/// under `max_d` and the ratio test; one-to-one on points (the closest wins).
fn match_descriptors(
    shot: &[Descriptor],
    cand: &[(PointId, Descriptor)],
    max_d: u32,
    ratio: f32,
) -> Vec<(usize, PointId)> {
    let mut m: Vec<(u32, usize, PointId)> = Vec::new();
    for (i, d) in shot.iter().enumerate() {
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for (j, (_, c)) in cand.iter().enumerate() {
            let h = hamming(d, c);
            if h < b1 {
                b2 = b1;
                b1 = h;
                bi = j;
            } else if h < b2 {
                b2 = h;
            }
        }
        if b1 <= max_d && (b2 == u32::MAX || (b1 as f32) < ratio * b2 as f32) {
            m.push((b1, i, cand[bi].0));
        }
    }
    m.sort_unstable_by_key(|x| x.0);
    let mut used = HashSet::new();
    m.into_iter()
        .filter(|(_, _, p)| used.insert(*p))
        .map(|(_, i, p)| (i, p))
        .collect()
}

/// ORB on the shot with the map's pyramid (scale factor and levels),
/// after checking that the shot and the mask have `camera`'s size.
pub(super) fn extract_shot_features(
    map: &Map,
    camera: &Camera,
    shot: &GrayImage,
    mask: Option<&GrayImage>,
    params: &LocalizeParams,
) -> Result<features::Features, ShotError> {
    let cam = camera;
    for img in std::iter::once(shot).chain(mask) {
        if img.dimensions() != (cam.width, cam.height) {
            return Err(ShotError::ImageSize {
                width: img.width(),
                height: img.height(),
                expected_width: cam.width,
                expected_height: cam.height,
            });
        }
    }
    let mut fparams = params.features;
    fparams.scale_factor = map.scale.scale_factor as f32;
    fparams.n_levels = map.scale.n_levels();
    let mut extractor = OrbExtractor::new(fparams).map_err(|e| ShotError::Features {
        message: e.to_string(),
    })?;
    let feats = match mask {
        Some(m) => {
            extractor
                .extract_masked(shot, m, Some(cam))
                .map_err(|e| ShotError::Features {
                    message: e.to_string(),
                })?
        }
        None => extractor.extract(shot, Some(cam)),
    };
    Ok(feats)
}

/// A keyframe a shot resembles: for a shot that was not localised, where
/// the drone could fly to see what the shot shows ("fly towards here").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NearKeyframe {
    /// The keyframe.
    pub keyframe_id: KeyFrameId,
    /// Its bag-of-words similarity to the shot (L1 score, 0 to 1).
    pub score: f64,
    /// Its camera centre, map coordinates.
    pub position: Point3<f64>,
}

/// The `k` keyframes of `map` most similar to the shot by bag-of-words
/// score, best first, with where they are. ORB on the shot as in
/// [`localize_with_camera`].
///
/// Errors: as [`localize_with_camera`]'s.
pub fn nearest_keyframes(
    map: &Map,
    camera: &Camera,
    shot: &GrayImage,
    mask: Option<&GrayImage>,
    index: &BowIndex<'_>,
    params: &LocalizeParams,
    k: usize,
) -> Result<Vec<NearKeyframe>, ShotError> {
    let feats = extract_shot_features(map, camera, shot, mask, params)?;
    if feats.is_empty() || k == 0 {
        return Ok(Vec::new());
    }
    let q = index.vocabulary.transform(&feats.descriptors);
    Ok(index
        .database
        .query(&q, k)
        .into_iter()
        .filter_map(|r| {
            let id = KeyFrameId(u32::try_from(r.id.0).ok()?);
            let kf = map.keyframe(id)?;
            Some(NearKeyframe {
                keyframe_id: id,
                score: f64::from(r.score),
                position: Point3::from(kf.center()),
            })
        })
        .collect())
}

/// A candidate keyframe and the shot's descriptor matches to its map points
/// (keypoint, point).
pub(super) type Candidate = (KeyFrameId, Vec<(usize, PointId)>);

/// The candidate keyframes of a shot, most descriptor matches first (at
/// most [`LocalizeParams::top_k`]): with a [`BowIndex`] the first
/// [`LocalizeParams::bow_candidates`] of a bag-of-words query, else every
/// keyframe, each matched by descriptor against its map points; and
/// apart, with a position prior, the best [`LocalizeParams::top_k`] of
/// the keyframes near it ([`near_prior_keyframes`]) not among the first
/// (empty without a prior). The reason when there is none, or when the
/// best has too few matches.
pub(super) fn rank_candidates(
    map: &Map,
    feats: &features::Features,
    bow_index: Option<&BowIndex<'_>>,
    params: &LocalizeParams,
) -> Result<(Vec<Candidate>, Vec<Candidate>), NotLocalizedReason> {
    let mut ranked: Vec<Candidate> = Vec::new();
    let mut pts: Vec<(PointId, Descriptor)> = Vec::new();
    let candidates: Vec<KeyFrameId> = match bow_index {
        Some(index) => {
            let q = index.vocabulary.transform(&feats.descriptors);
            index
                .database
                .query(&q, params.bow_candidates.max(params.top_k).max(1))
                .into_iter()
                .filter_map(|r| u32::try_from(r.id.0).ok().map(KeyFrameId))
                .collect()
        }
        None => map.keyframes().map(|k| k.id).collect(),
    };
    // With a position prior, the keyframes that could see what a camera
    // there sees are candidates too (after the retrieved ones), and the
    // best of them by matches are tried beyond the first `top_k`: a
    // look-alike place that outranks the right one by its descriptors
    // does not keep the right one from being tried.
    let near_prior = near_prior_keyframes(map, params);
    let mut candidates = candidates;
    if bow_index.is_some() {
        let retrieved: HashSet<KeyFrameId> = candidates.iter().copied().collect();
        candidates.extend(near_prior.iter().filter(|k| !retrieved.contains(k)));
    }
    for kf in candidates.iter().filter_map(|id| map.keyframe(*id)) {
        pts.clear();
        for p in kf.points.iter().flatten() {
            if let Some(mp) = map.point(*p) {
                pts.push((*p, mp.descriptor));
            }
        }
        if pts.is_empty() {
            continue;
        }
        let m = match_descriptors(&feats.descriptors, &pts, params.max_hamming, params.ratio);
        ranked.push((kf.id, m));
    }
    if ranked.is_empty() {
        return Err(NotLocalizedReason::NoCandidate);
    }
    ranked.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(&b.0)));
    let top_k = params.top_k.max(1);
    let near: HashSet<KeyFrameId> = near_prior.into_iter().collect();
    let extra: Vec<Candidate> = ranked
        .iter()
        .skip(top_k)
        .filter(|(kf, m)| near.contains(kf) && m.len() >= params.min_candidate_matches)
        .take(top_k)
        .cloned()
        .collect();
    ranked.truncate(top_k);
    let best_count = ranked[0].1.len();
    if best_count < params.min_candidate_matches {
        return Err(NotLocalizedReason::TooFewMatches {
            found: best_count,
            needed: params.min_candidate_matches,
        });
    }
    Ok((ranked, extra))
}

/// The keyframes that could see what a camera at the photo's position
/// prior ([`LocalizeParams::position_prior`]) sees, nearest first, at most
/// [`LocalizeParams::bow_candidates`]: those whose centre lies within the
/// prior's reach ([`crate::shot::GateParams::max_prior_sigmas`] of its
/// sigma) plus twice the keyframe's median scene depth. None without a
/// prior.
fn near_prior_keyframes(map: &Map, params: &LocalizeParams) -> Vec<KeyFrameId> {
    let Some(prior) = &params.position_prior else {
        return Vec::new();
    };
    let reach = prior.sigma * params.gate.max_prior_sigmas;
    let mut near: Vec<(f64, KeyFrameId)> = map
        .keyframes()
        .filter_map(|k| {
            let (d, _) = prior.distance(&Point3::from(k.center()), 0.0);
            // The scene depth (a pass over the keyframe's points) only
            // where the reach alone does not decide.
            let near = d <= reach || d <= reach + 2.0 * map.median_depth(k.id).unwrap_or(0.0);
            near.then_some((d, k.id))
        })
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    near.truncate(params.bow_candidates.max(params.top_k).max(1));
    near.into_iter().map(|(_, k)| k).collect()
}

/// A candidate's matches for its PnP, matched again against the points of
/// its neighbourhood: the candidate and its best
/// [`LocalizeParams::candidate_covisible`] covisible keyframes. Each point
/// is compared through every observation's descriptor (the keypoint of
/// each keyframe that sees it, not only its representative one): a photo
/// 10-40 degrees round from the flown views looks most like the keyframe
/// nearest to it, whose descriptor of a point may be far from the
/// representative one. Nearest point under [`LocalizeParams::max_hamming`]
/// and the ratio test against the second-nearest other point, one-to-one
/// on points, then ORB-SLAM's rotation-consistency filter on the angle
/// between the photo's keypoint and the matched observation's.
pub(super) fn neighbourhood_matches(
    map: &Map,
    kf_id: KeyFrameId,
    feats: &features::Features,
    params: &LocalizeParams,
) -> Vec<(usize, PointId)> {
    let Some(kf) = map.keyframe(kf_id) else {
        return Vec::new();
    };
    // The neighbourhood's points (dense indices) and, per observation,
    // (point index, descriptor, keypoint angle of that observation).
    let mut points: Vec<PointId> = Vec::new();
    let mut cand: Vec<(usize, Descriptor, f32)> = Vec::new();
    let mut seen: HashSet<PointId> = HashSet::new();
    let kfs = std::iter::once(kf_id).chain(kf.best_covisible(params.candidate_covisible));
    for k in kfs.filter_map(|id| map.keyframe(id)) {
        for p in k.points.iter().flatten() {
            if !seen.insert(*p) {
                continue;
            }
            let Some(mp) = map.point(*p) else { continue };
            let pi = points.len();
            points.push(*p);
            for (ok, idx) in &mp.observations {
                if let Some(okf) = map.keyframe(*ok)
                    && let (Some(d), Some(kp)) = (
                        okf.descriptors.get(*idx as usize),
                        okf.keypoints.get(*idx as usize),
                    )
                {
                    cand.push((pi, *d, kp.angle));
                }
            }
        }
    }
    // Per shot keypoint: the nearest point (through any of its
    // descriptors); per point: the nearest shot keypoint.
    let mut m: Vec<(u32, usize, usize, f32)> = Vec::new();
    let mut point_best: Vec<(u32, usize)> = vec![(u32::MAX, usize::MAX); points.len()];
    for (i, d) in feats.descriptors.iter().enumerate() {
        let (mut b1, mut bj) = (u32::MAX, usize::MAX);
        for (j, (pi, c, _)) in cand.iter().enumerate() {
            let h = hamming(d, c);
            if h < b1 {
                b1 = h;
                bj = j;
            }
            let e = &mut point_best[*pi];
            if h < e.0 {
                *e = (h, i);
            }
        }
        if let Some((pi, _, a)) = cand.get(bj)
            && b1 <= params.max_hamming
        {
            m.push((b1, i, *pi, *a));
        }
    }
    // Mutual nearest neighbours (a cross check instead of the ratio test:
    // a point seen from far round has no distinctive nearest keypoint,
    // and the map's near-duplicate points would fail the ratio test).
    m.retain(|(_, i, pi, _)| point_best[*pi].1 == *i);
    m.sort_unstable_by_key(|x| x.0);
    let mut used = HashSet::new();
    let m: Vec<(usize, PointId, f32)> = m
        .into_iter()
        .filter(|(_, _, pi, _)| used.insert(*pi))
        .map(|(_, i, pi, a)| (i, points[pi], a))
        .collect();
    let rot: Vec<(usize, f32)> = m
        .iter()
        .enumerate()
        .map(|(k, (i, _, a))| (k, feats.keypoints[*i].angle - a))
        .collect();
    let drop: HashSet<usize> = rotation_outliers(&rot, params.matcher.histo_bins)
        .into_iter()
        .collect();
    m.into_iter()
        .enumerate()
        .filter(|(k, _)| !drop.contains(k))
        .map(|(_, (i, p, _))| (i, p))
        .collect()
}
