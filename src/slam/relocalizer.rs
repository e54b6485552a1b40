//! Relocalisation of a lost frame (ORB-SLAM's, as stella_vslam's
//! `relocalizer` module): candidate keyframes from the keyframe database
//! (words in common, scores accumulated over covisibility groups),
//! BoW-guided matching with each, PnP RANSAC, motion-only bundle
//! adjustment, and, when the inliers fall short, search by projection of
//! the candidate's covisible points and a second optimisation.

use nalgebra::{Isometry3, Point2};

use crate::geometry;
use crate::lie::renormalized;

use super::frame::{Context, Frame, Marks, PoseFit};
use super::map::{self, KeyFrameId, Map};
use super::matcher;

/// Relocalise `frame` in `map`: its pose and matches when a candidate
/// keyframe gives `min_inliers_after_reloc` inliers; `None` (and no
/// matches) otherwise.
pub(super) fn relocalize(
    ctx: &Context,
    marks: &mut Marks,
    map: &Map,
    frame: &mut Frame,
) -> Option<PoseFit> {
    let p = &ctx.params;
    let places = map.places()?;
    let (bow, fv) = ctx.frame_bow(frame).clone();
    let neighbours = p.bow.candidates.covisible_neighbours;
    let mut candidates = places.database.detect_candidates(
        &bow,
        &p.bow.candidates,
        |_| false,
        |id, out| {
            if let Some(k) = map::Places::map_id(id).and_then(|id| map.keyframe(id)) {
                out.extend(k.best_covisible(neighbours).map(map::Places::db_id));
            }
        },
    );
    candidates.truncate(p.reloc_max_candidates);
    let needed = p.min_inliers_after_reloc;
    for (ci, cand) in candidates.iter().enumerate() {
        let Some(kf) = map::Places::map_id(cand.id) else {
            continue;
        };
        let Some(kf_fv) = places.features.get(&kf) else {
            continue;
        };
        let matches = matcher::search_by_bow(
            map,
            kf,
            kf_fv,
            &frame.descriptors,
            &frame.keypoints,
            &fv,
            &p.matcher,
            p.reloc_ratio,
        );
        if matches.len() < p.reloc_min_bow_matches {
            continue;
        }
        let mut pts = Vec::with_capacity(matches.len());
        let mut obs = Vec::with_capacity(matches.len());
        let mut used = Vec::with_capacity(matches.len());
        for &(i, pid) in &matches {
            let Some(mp) = map.point(pid) else { continue };
            let k = &frame.keypoints[i];
            pts.push(mp.position);
            obs.push(Point2::new(
                (k.ux as f64 - ctx.camera.cx) / ctx.camera.fx,
                (k.uy as f64 - ctx.camera.cy) / ctx.camera.fy,
            ));
            used.push((i, pid));
        }
        let Ok(r) = geometry::solve_pnp_ransac(
            &pts,
            &obs,
            ctx.camera.fx,
            &p.pnp,
            p.seed.wrapping_add(frame.index * 31 + ci as u64),
        ) else {
            continue;
        };
        frame.clear_matches();
        frame.set_matches(
            used.iter()
                .zip(&r.inliers)
                .filter(|(_, ok)| **ok)
                .map(|(m, _)| *m),
        );
        let Some(mut fit) = ctx.optimize_frame_pose(map, frame, renormalized(r.cam_from_world))
        else {
            continue;
        };
        if fit.inliers < 10 {
            continue;
        }
        // Search by projection for more matches: first wide, then
        // narrow after a second optimisation (ORB-SLAM's 10 then 3 px).
        for th in [3.0, 1.0] {
            if fit.inliers >= needed {
                break;
            }
            search_candidate_points(ctx, marks, map, frame, kf, &fit.cam_from_world, th);
            match ctx.optimize_frame_pose(map, frame, fit.cam_from_world) {
                Some(better) => fit = better,
                None => break,
            }
        }
        if fit.inliers >= needed {
            tracing::info!(
                frame = frame.index,
                keyframe = kf.0,
                candidates = candidates.len(),
                inliers = fit.inliers,
                "relocalised"
            );
            return Some(fit);
        }
    }
    frame.clear_matches();
    None
}

/// Project the points of keyframe `kf` and its best covisible neighbours
/// that the frame has not matched, and match them by projection (radius
/// factor `th`).
fn search_candidate_points(
    ctx: &Context,
    marks: &mut Marks,
    map: &Map,
    frame: &mut Frame,
    kf: KeyFrameId,
    cam_from_world: &Isometry3<f64>,
    th: f64,
) {
    let Some(k) = map.keyframe(kf) else { return };
    let center = cam_from_world.inverse().translation.vector;
    marks.next_pass();
    for pid in frame.points.iter().flatten() {
        marks.mark_point(*pid);
    }
    let mut projected = Vec::new();
    let kfs: Vec<KeyFrameId> = std::iter::once(kf).chain(k.best_covisible(10)).collect();
    for id in kfs {
        let Some(k) = map.keyframe(id) else { continue };
        for pid in k.points.iter().flatten() {
            if !marks.mark_point(*pid) {
                continue;
            }
            if let Some(pr) = matcher::project_point(
                map,
                *pid,
                cam_from_world,
                &center,
                &ctx.bounds,
                matcher::MIN_VIEW_COS,
            ) {
                projected.push(pr);
            }
        }
    }
    let found = matcher::search_local_points(
        &frame.search_target(),
        &projected,
        map,
        &ctx.scale,
        th,
        &ctx.params.matcher,
    );
    frame.add_matches(found);
}
