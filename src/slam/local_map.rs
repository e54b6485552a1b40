//! Tracking the local map (ORB-SLAM's `TrackLocalMap`, stella_vslam's
//! local map updater): the local keyframes are those sharing points with
//! the frame, their best covisible neighbours, parents and children; their
//! points that project into the frame are matched by projection, and the
//! frame's pose is optimised on all its matches. Points count as visible
//! and found here, which local mapping's culling reads.

use nalgebra::Isometry3;

use super::frame::{Context, Frame, Marks, PoseFit};
use super::map::{KeyFrameId, Map};
use super::matcher::{self, Projected};

/// What tracking the local map gave.
pub(super) struct LocalMapResult {
    /// The local keyframe sharing most points with the frame (the new
    /// reference keyframe), when any shares one.
    pub reference: Option<KeyFrameId>,
    /// The frame's pose on all its matches; `None` when the optimisation
    /// failed.
    pub fit: Option<PoseFit>,
}

/// Local-map tracking with its scratch space (reused from frame to frame:
/// no allocation per frame).
#[derive(Default)]
pub(super) struct LocalMapTracker {
    projected: Vec<Projected>,
}

impl LocalMapTracker {
    /// Track the local map from `cam_from_world` (the pose the motion
    /// model, the reference keyframe, relocalisation or the telemetry
    /// gave), searching within `radius` pixels (at level 0). A frame that
    /// shares no point with the map yet (posed by the telemetry) takes the
    /// local keyframes around `seed`.
    #[allow(clippy::too_many_arguments)]
    pub fn track(
        &mut self,
        ctx: &Context,
        marks: &mut Marks,
        map: &mut Map,
        frame: &mut Frame,
        cam_from_world: Isometry3<f64>,
        radius: f64,
        seed: Option<KeyFrameId>,
    ) -> LocalMapResult {
        let LocalKeyframes {
            reference,
            keyframes: local_kfs,
        } = local_keyframes(ctx, marks, map, frame, seed);
        let center = cam_from_world.inverse().translation.vector;
        marks.next_pass();
        for pid in frame.points.iter().flatten() {
            marks.mark_point(*pid);
        }
        let projected = &mut self.projected;
        projected.clear();
        for kf in &local_kfs {
            let Some(k) = map.keyframe(*kf) else { continue };
            for pid in k.points.iter().flatten() {
                if !marks.mark_point(*pid) {
                    continue;
                }
                if let Some(pr) = matcher::project_point(
                    map,
                    *pid,
                    &cam_from_world,
                    &center,
                    &ctx.bounds,
                    matcher::MIN_VIEW_COS,
                ) {
                    projected.push(pr);
                }
            }
        }
        // Points already matched count as visible too.
        for pid in frame.points.iter().flatten() {
            if let Some(mp) = map.point_mut(*pid) {
                mp.visible += 1;
            }
        }
        for pr in projected.iter() {
            if let Some(mp) = map.point_mut(pr.id) {
                mp.visible += 1;
            }
        }
        let found = matcher::search_local_points(
            &frame.search_target(),
            projected,
            map,
            &ctx.scale,
            radius,
            &ctx.params.matcher,
        );
        frame.add_matches(found);
        let fit = ctx.optimize_frame_pose(map, frame, cam_from_world);
        if fit.is_some() {
            for pid in frame.points.iter().flatten() {
                if let Some(mp) = map.point_mut(*pid) {
                    mp.found += 1;
                }
            }
        }
        LocalMapResult { reference, fit }
    }
}

/// The local keyframes of a frame.
struct LocalKeyframes {
    /// The keyframe sharing most points with the frame.
    reference: Option<KeyFrameId>,
    /// The keyframes sharing points with the frame (most shared first),
    /// then their best covisible neighbours, children and parents.
    keyframes: Vec<KeyFrameId>,
}

/// The keyframes sharing points with the frame (else `seed`), their best
/// covisible neighbours, parents and children; with the one sharing most.
fn local_keyframes(
    ctx: &Context,
    marks: &mut Marks,
    map: &Map,
    frame: &Frame,
    seed: Option<KeyFrameId>,
) -> LocalKeyframes {
    marks.next_pass();
    let mut list: Vec<(KeyFrameId, u32)> = Vec::new();
    for pid in frame.points.iter().flatten() {
        if let Some(mp) = map.point(*pid) {
            for (kf, _) in &mp.observations {
                if marks.mark_keyframe(*kf) {
                    list.push((*kf, 0));
                }
                marks.count[kf.0 as usize] += 1;
            }
        }
    }
    for e in &mut list {
        e.1 = marks.count[e.0.0 as usize];
    }
    if list.is_empty()
        && let Some(kf) = seed.filter(|k| map.keyframe(*k).is_some())
    {
        marks.mark_keyframe(kf);
        list.push((kf, 0));
    }
    list.sort_unstable_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let best = list.first().map(|e| e.0);
    let max = ctx.params.max_local_keyframes;
    let mut local: Vec<KeyFrameId> = list.iter().map(|e| e.0).collect();
    let direct = local.len();
    for d in 0..direct {
        if local.len() >= max {
            break;
        }
        let Some(k) = map.keyframe(local[d]) else {
            continue;
        };
        let extra = k
            .best_covisible(10)
            .chain(k.children.iter().copied())
            .chain(k.parent);
        for e in extra {
            if marks.mark_keyframe(e) {
                local.push(e);
                if local.len() >= max {
                    break;
                }
            }
        }
    }
    LocalKeyframes {
        reference: best,
        keyframes: local,
    }
}
