//! Monocular initialisation (ORB-SLAM's, as stella_vslam's `initializer`
//! module): the first frame of an attempt is kept, later frames are matched
//! with it in a window that follows each keypoint, and when enough matches
//! hold, the two-view solver chooses between the fundamental matrix and the
//! homography and triangulates. A planar pair whose two reconstructions
//! both hold is decided with the frames seen in between
//! ([`super::planar`]). The initial map is the two keyframes and their
//! points after a bundle adjustment with the first fixed, scaled to a
//! median scene depth of 1.

use std::sync::Mutex;

use nalgebra::{Isometry3, Point2};

use crate::features::KeyPoint;
use crate::geometry::{self, GeometryError};
use crate::lie::renormalized;

use super::bundle::run_bundle_adjustment;
use super::frame::{Context, Frame};
use super::map::{KeyFrameId, Map, PointId, lock};
use super::matcher;
use super::planar::{self, PlanarFailure};

/// Why the map is not initialised yet.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InitFailure {
    /// The frame has too few keypoints to start an attempt with.
    #[error(
        "frame has {found} keypoints, too few to start initialisation (need more than {needed})"
    )]
    TooFewKeypoints {
        /// Keypoints of the frame.
        found: usize,
        /// The minimum (exclusive).
        needed: usize,
    },
    /// Too few matches with the attempt's first frame: the attempt starts
    /// over from this frame.
    #[error(
        "only {found} matches with the initialisation frame (need {needed}); starting over from this frame"
    )]
    NotEnoughMatches {
        /// Matches found.
        found: usize,
        /// Matches needed.
        needed: usize,
    },
    /// The two-view solver refused the pair.
    #[error("two-view initialisation refused ({matches} matches): {source}")]
    TwoView {
        /// Matches between the two frames.
        matches: usize,
        /// The solver's reason.
        source: GeometryError,
    },
    /// The pair is planar and ambiguous, and the frames in between did not
    /// decide it.
    #[error("two-view initialisation refused ({matches} matches): {ambiguity}; {planar}")]
    Planar {
        /// Matches between the two frames.
        matches: usize,
        /// The solver's ambiguity.
        ambiguity: GeometryError,
        /// Why the third views did not decide.
        planar: PlanarFailure,
    },
    /// The bundle adjustment of the two views left no point.
    #[error("initial map has no points")]
    EmptyMap,
    /// The initial map has too few points or a non-positive depth.
    #[error(
        "initial map rejected: median depth {median_depth:.3}, {points} points (need {needed})"
    )]
    MapRejected {
        /// Median scene depth of the first keyframe.
        median_depth: f64,
        /// Points the second keyframe tracks.
        points: usize,
        /// Points needed.
        needed: usize,
    },
    /// The second keyframe was gone right after it was made.
    #[error("initial keyframe vanished")]
    KeyFrameVanished,
    /// The reconstruction's motion disagrees with the telemetry's (its
    /// reported attitudes and GNSS displacement between the two frames).
    #[error(
        "two-view initialisation refused ({matches} matches): the motion is {sigmas:.1} sigmas from the telemetry's"
    )]
    RefutedByTelemetry {
        /// Matches between the two frames.
        matches: usize,
        /// The distance, in the telemetry's sigmas.
        sigmas: f64,
    },
    /// A new map the telemetry must put into the old one waits for a GNSS
    /// baseline that fixes its scale.
    #[error(
        "waiting for a GNSS baseline of {needed_m:.2} m to put the new map into the old one (have {baseline_m:.2} m)"
    )]
    ShortGnssBaseline {
        /// The GNSS displacement between the two frames, m.
        baseline_m: f64,
        /// The displacement needed, m.
        needed_m: f64,
    },
}

/// One frame of the initial map.
#[derive(Debug, Clone, Copy)]
pub(super) struct InitFrameRef {
    /// Frame index.
    pub index: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// Its keyframe.
    pub keyframe: KeyFrameId,
}

/// A new initial map.
#[derive(Debug, Clone)]
pub(super) struct InitialMap {
    /// The attempt's first frame (at the world origin).
    pub first: InitFrameRef,
    /// The frame that completed it.
    pub second: InitFrameRef,
    /// The second frame's pose.
    pub cam_from_world: Isometry3<f64>,
    /// The second frame's keypoints.
    pub keypoints: Vec<KeyPoint>,
    /// The second frame's (keypoint, point) matches.
    pub matches: Vec<(usize, PointId)>,
}

/// The first frame of an initialisation attempt.
struct InitFrame {
    frame: Frame,
    /// Where each of its keypoints was last matched (window centre).
    prev: Vec<Point2<f64>>,
    /// Later frames matched with it, to tell planar reconstructions apart.
    third_views: Vec<planar::ThirdView>,
}

impl InitFrame {
    fn new(frame: Frame) -> Self {
        InitFrame {
            prev: frame.pixels(),
            frame,
            third_views: Vec::new(),
        }
    }
}

/// The initializer: the current attempt and how many were made (each
/// attempt's randomness has its own seed).
#[derive(Default)]
pub(super) struct Initializer {
    init: Option<InitFrame>,
    attempt: u64,
    /// The telemetry, to tell a planar pair's reconstructions apart.
    aid: Option<super::aided::TelemetryAid>,
    /// The map must be put into an old one by the telemetry: wait for a
    /// GNSS baseline that fixes its scale.
    need_gnss_baseline: bool,
}

impl Initializer {
    /// Use the telemetry's relative motion between the two frames to tell
    /// a planar pair's reconstructions apart (`None`: the third views only).
    pub fn set_aid(&mut self, aid: Option<super::aided::TelemetryAid>) {
        self.aid = aid;
    }

    /// Whether the next map must wait for a GNSS baseline between its two
    /// frames (a new map the telemetry puts into the old one,
    /// [`super::aided::place_new_map`]).
    pub fn set_need_gnss_baseline(&mut self, need: bool) {
        self.need_gnss_baseline = need;
    }

    /// Drop the current attempt.
    pub fn reset(&mut self) {
        self.init = None;
    }

    /// One step with `frame`: `Ok(Some)` when the map was initialised
    /// (into `map`'s active map, which must be empty; the other maps of
    /// the atlas are left as they are), `Ok(None)` when the frame became
    /// the first frame of a new attempt, `Err` while not initialised.
    pub fn step(
        &mut self,
        ctx: &Context,
        map: &Mutex<Map>,
        frame: Frame,
    ) -> Result<Option<InitialMap>, InitFailure> {
        let p = &ctx.params;
        let Some(init) = self.init.take() else {
            if frame.keypoints.len() > p.init_min_matches {
                self.init = Some(InitFrame::new(frame));
                return Ok(None);
            }
            return Err(InitFailure::TooFewKeypoints {
                found: frame.keypoints.len(),
                needed: p.init_min_matches,
            });
        };
        let m12 = matcher::search_for_initialization(
            &init.frame.keypoints,
            &init.frame.descriptors,
            &frame.keypoints,
            &frame.descriptors,
            &frame.grid,
            &init.prev,
            p.init_window,
            p.init_max_octave,
            &p.matcher,
            |_, _| true,
        );
        let matches: Vec<(usize, usize)> = m12
            .iter()
            .enumerate()
            .filter_map(|(i, m)| m.map(|j| (i, j)))
            .collect();
        if matches.len() < p.init_min_matches {
            let failure = InitFailure::NotEnoughMatches {
                found: matches.len(),
                needed: p.init_min_matches,
            };
            // Start a new attempt from this frame.
            if frame.keypoints.len() > p.init_min_matches {
                self.init = Some(InitFrame::new(frame));
            }
            return Err(failure);
        }
        let mut init = init;
        for &(i, j) in &matches {
            let k = &frame.keypoints[j];
            init.prev[i] = Point2::new(k.ux as f64, k.uy as f64);
        }
        let kp1 = init.frame.pixels();
        let kp2 = frame.pixels();
        let motion = self
            .aid
            .as_ref()
            .and_then(|a| a.relative_motion(init.frame.timestamp, frame.timestamp));
        if self.need_gnss_baseline
            && let Some(aid) = &self.aid
        {
            let needed_m = aid.place_baseline_m(init.frame.timestamp, frame.timestamp);
            let baseline_m = aid
                .gnss_displacement(init.frame.timestamp, frame.timestamp)
                .unwrap_or(0.0);
            if baseline_m < needed_m {
                // Keep the attempt: a later frame gives the baseline.
                self.init = Some(init);
                return Err(InitFailure::ShortGnssBaseline {
                    baseline_m,
                    needed_m,
                });
            }
        }
        self.attempt += 1;
        let tv = geometry::initialize_two_view(
            &ctx.camera.k(),
            &kp1,
            &kp2,
            &matches,
            &p.two_view,
            p.seed.wrapping_add(self.attempt),
        );
        let tv = match tv {
            Ok(tv) => Ok(tv),
            Err(ambiguity @ GeometryError::Ambiguous { .. }) => planar::choose_reconstruction(
                &ctx.camera,
                p,
                &kp1,
                &kp2,
                &matches,
                init.frame.index,
                &init.third_views,
                self.attempt,
                motion.as_ref(),
            )
            .map_err(|planar| InitFailure::Planar {
                matches: matches.len(),
                ambiguity,
                planar,
            }),
            Err(source) => Err(InitFailure::TwoView {
                matches: matches.len(),
                source,
            }),
        };
        init.third_views.push(planar::ThirdView {
            index: frame.index,
            seen: matches.iter().map(|&(i, j)| (i, kp2[j])).collect(),
        });
        if init.third_views.len() > 64 {
            // Keep them spread over the attempt: drop every other one.
            let mut n = 0;
            init.third_views.retain(|_| {
                n += 1;
                n % 2 == 1
            });
        }
        let tv = match tv {
            Ok(tv) => tv,
            Err(failure) => {
                self.init = Some(init);
                return Err(failure);
            }
        };
        if let Some(m) = &motion {
            let sigmas = planar::telemetry_distance(&tv.cam2_from_cam1, m);
            if sigmas > planar::TELEMETRY_REFUTE_SIGMAS {
                // A wrong reconstruction (too little parallax, matches on
                // something that moves): a later frame may do.
                self.init = Some(init);
                return Err(InitFailure::RefutedByTelemetry {
                    matches: matches.len(),
                    sigmas,
                });
            }
        }
        match create_initial_map(ctx, map, &init.frame, &frame, &matches, &tv) {
            Ok(r) => Ok(Some(r)),
            Err(failure) => {
                // The reconstruction did not hold; try again from this frame.
                self.init = Some(InitFrame::new(frame));
                Err(failure)
            }
        }
    }
}

/// Build the initial map from the two frames and their reconstruction.
fn create_initial_map(
    ctx: &Context,
    map_lock: &Mutex<Map>,
    f1: &Frame,
    f2: &Frame,
    matches: &[(usize, usize)],
    tv: &geometry::TwoViewResult,
) -> Result<InitialMap, InitFailure> {
    let mut map = lock(map_lock);
    let mut kf1 = f1.to_keyframe(Isometry3::identity());
    let mut kf2 = f2.to_keyframe(renormalized(tv.cam2_from_cam1));
    kf1.points.iter_mut().for_each(|p| *p = None);
    kf2.points.iter_mut().for_each(|p| *p = None);
    let level = ctx.params.bow.direct_index_level;
    let mut bows = [f1, f2].map(|f| {
        ctx.vocabulary
            .transform_with_features(&f.descriptors, level)
    });
    let id1 = map.add_keyframe(kf1);
    let id2 = map.add_keyframe(kf2);
    let mut new_points: Vec<PointId> = Vec::with_capacity(matches.len());
    let words = ctx.vocabulary.word_count();
    for (id, (bow, fv)) in [id1, id2].into_iter().zip(bows.iter_mut()) {
        map.index_keyframe(id, std::mem::take(bow), std::mem::take(fv), words);
    }
    for (m, &(i, j)) in matches.iter().enumerate() {
        let Some(p) = tv.points.get(m).copied().flatten() else {
            continue;
        };
        let pid = map.add_point(p, f1.descriptors[i], id1);
        new_points.push(pid);
        map.add_observation(pid, id1, i as u32);
        map.add_observation(pid, id2, j as u32);
        map.update_point_descriptor(pid);
        map.update_point_normal_and_depth(pid);
    }
    map.update_connections(id1);
    map.update_connections(id2);
    // Bundle adjustment of the two views, the first fixed.
    run_bundle_adjustment(&mut map, &[id1, id2], &[id1], &ctx.params.init_ba);
    let Some(median) = map.median_depth(id1) else {
        reset_map(&mut map);
        return Err(InitFailure::EmptyMap);
    };
    let n_tracked = map.keyframe(id2).map_or(0, |k| k.tracked_points(&map, 1));
    if median <= 0.0 || n_tracked < ctx.params.init_min_points {
        reset_map(&mut map);
        return Err(InitFailure::MapRejected {
            median_depth: median,
            points: n_tracked,
            needed: ctx.params.init_min_points,
        });
    }
    // Scale so the median scene depth is 1.
    let s = 1.0 / median;
    if let Some(k) = map.keyframe_mut(id2) {
        k.cam_from_world.translation.vector *= s;
    }
    // Only this map's points (the BA may have erased some).
    let pids: Vec<PointId> = new_points
        .into_iter()
        .filter(|p| map.point(*p).is_some())
        .collect();
    for pid in &pids {
        if let Some(mp) = map.point_mut(*pid) {
            mp.position.coords *= s;
        }
    }
    for pid in &pids {
        map.update_point_normal_and_depth(*pid);
    }
    let Some(kf2) = map.keyframe(id2) else {
        return Err(InitFailure::KeyFrameVanished);
    };
    let cam2_from_world = kf2.cam_from_world;
    let matched: Vec<(usize, PointId)> = kf2
        .points
        .iter()
        .enumerate()
        .filter_map(|(i, p)| p.map(|p| (i, p)))
        .collect();
    tracing::info!(
        frame = f2.index,
        first_frame = f1.index,
        points = matched.len(),
        model = ?tv.model,
        parallax_deg = tv.parallax_deg,
        "map initialised"
    );
    Ok(InitialMap {
        first: InitFrameRef {
            index: f1.index,
            timestamp: f1.timestamp,
            keyframe: id1,
        },
        second: InitFrameRef {
            index: f2.index,
            timestamp: f2.timestamp,
            keyframe: id2,
        },
        cam_from_world: cam2_from_world,
        keypoints: f2.keypoints.clone(),
        matches: matched,
    })
}

/// Undo a failed initialisation: the whole map emptied when it was the
/// only one, else only the new (active) map erased, the others kept.
fn reset_map(map: &mut Map) {
    let active = map.active_map();
    if map.keyframes().all(|k| map.map_of(k.id) == Some(active)) {
        *map = Map::new(map.camera, map.scale.clone());
    } else {
        map.discard_map(active);
    }
}
