//! Local mapping: for each new keyframe, update its connections, cull the
//! recently created points that are rarely found, triangulate new points
//! with the covisible keyframes (epipolar search, parallax, reprojection and
//! scale checks), fuse duplicates with the neighbours, run local bundle
//! adjustment (the solve outside the map lock, so tracking never waits for
//! it), and cull keyframes whose points are seen by enough others.
//!
//! With telemetry priors ([`Priors`]), each keyframe first tries to put a
//! vision-only map in local NED ([`Priors::try_georeference`]); once it is,
//! local BA carries the GNSS and altitude priors of its free keyframes.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use nalgebra::{Point2, Vector3};

use crate::bow::Vocabulary;
use crate::geometry;
use crate::optimize::{self, BaParams};

use super::bundle::{apply_ba_result, build_ba_problem};
use super::map::{KeyFrameId, Map, PointId, lock};
use super::matcher::{self, MatcherParams};
use super::params::bound_history;
use super::priors::{Georeferenced, Priors};
use crate::matching::Bounds;

/// Tunable numbers of local mapping.
#[derive(Debug, Clone, PartialEq)]
pub struct MappingParams {
    /// Covisible keyframes used for triangulation.
    pub triangulation_neighbours: usize,
    /// Covisible keyframes used for fusion (first ring).
    pub fuse_neighbours: usize,
    /// Second-ring neighbours per first-ring one for fusion.
    pub fuse_second_neighbours: usize,
    /// Search radius of fusion, pixels at level 0.
    pub fuse_radius: f64,
    /// Skip a neighbour whose baseline is below this share of its median depth.
    pub min_baseline_ratio: f64,
    /// Rays more parallel than this cosine are not triangulated.
    pub max_parallax_cos: f64,
    /// Chi-square bound (2 DoF) of the reprojection error of a new point.
    pub reprojection_chi2: f64,
    /// Allowed ratio between the distance ratio and the octave ratio.
    pub scale_consistency: f64,
    /// A recent point found in fewer than this share of the frames that saw it is culled.
    pub min_found_ratio: f64,
    /// A recent point with at most this many observations two keyframes after its creation is culled.
    pub min_recent_observations: usize,
    /// A keyframe is redundant when this share of its points is seen by enough others.
    pub redundant_ratio: f64,
    /// Local bundle adjustment.
    pub local_ba: BaParams,
    /// Descriptor matching.
    pub matcher: MatcherParams,
}

impl Default for MappingParams {
    fn default() -> Self {
        MappingParams {
            triangulation_neighbours: 20,
            fuse_neighbours: 20,
            fuse_second_neighbours: 5,
            fuse_radius: 3.0,
            min_baseline_ratio: 0.01,
            max_parallax_cos: 0.9998,
            reprojection_chi2: 5.991,
            scale_consistency: 1.5,
            min_found_ratio: 0.25,
            min_recent_observations: 2,
            redundant_ratio: 0.9,
            local_ba: BaParams::default(),
            matcher: MatcherParams::default(),
        }
    }
}

/// Timing and counts of one keyframe's mapping.
#[derive(Debug, Clone, Copy, Default)]
pub struct MappingReport {
    /// Points created by triangulation.
    pub new_points: usize,
    /// Points fused.
    pub fused: usize,
    /// Recent points culled.
    pub culled_points: usize,
    /// Keyframes culled.
    pub culled_keyframes: usize,
    /// Whole keyframe, ms.
    pub total_ms: f64,
    /// Local bundle adjustment, ms.
    pub ba_ms: f64,
    /// Reprojection RMSE after local BA, pixels.
    pub ba_rmse_px: f64,
}

/// The local mapper (runs on its own thread, or inline in sequential mode).
pub struct LocalMapper {
    params: MappingParams,
    bounds: Bounds,
    vocabulary: Arc<Vocabulary>,
    bow_level: u32,
    recent: Vec<(PointId, KeyFrameId)>,
    priors: Option<Priors>,
    /// Reports of the processed keyframes (every one unless
    /// [`LocalMapper::set_history`] bounds them).
    pub reports: Vec<MappingReport>,
    keep_reports: Option<usize>,
    /// When the map was put in NED by telemetry: the keyframe and the fit.
    pub georeferenced: Option<(KeyFrameId, Georeferenced)>,
}

impl LocalMapper {
    /// A mapper for images bounded by `bounds`; it indexes new keyframes
    /// in the keyframe database with `vocabulary` (direct index at
    /// `bow_level`), off the tracking thread as ORB-SLAM does.
    pub fn new(
        params: MappingParams,
        bounds: Bounds,
        vocabulary: Arc<Vocabulary>,
        bow_level: u32,
    ) -> Self {
        LocalMapper {
            params,
            bounds,
            vocabulary,
            bow_level,
            recent: Vec::new(),
            priors: None,
            reports: Vec::new(),
            keep_reports: None,
            georeferenced: None,
        }
    }

    /// Use telemetry priors (`None`: vision only).
    pub fn set_priors(&mut self, priors: Option<Priors>) {
        self.priors = priors;
    }

    /// Keep at least the newest `keep` reports and at most twice as many
    /// (`None`: all).
    pub fn set_history(&mut self, keep: Option<usize>) {
        self.keep_reports = keep;
        bound_history(&mut self.reports, keep);
    }

    /// Process one new keyframe. `more_waiting` skips the expensive steps
    /// (fusion, BA) when keyframes are queued behind this one.
    pub fn process_keyframe(
        &mut self,
        map: &Mutex<Map>,
        kf: KeyFrameId,
        more_waiting: bool,
    ) -> MappingReport {
        let t0 = Instant::now();
        let mut report = MappingReport::default();
        self.index_keyframe(map, kf);
        {
            let mut m = lock(map);
            let pids: Vec<PointId> = m
                .keyframe(kf)
                .map(|k| k.points.iter().flatten().copied().collect())
                .unwrap_or_default();
            for p in pids {
                m.update_point_normal_and_depth(p);
                m.update_point_descriptor(p);
            }
            m.update_connections(kf);
            report.culled_points = self.cull_recent_points(&mut m, kf);
            report.new_points = self.create_new_points(&mut m, kf);
            if !more_waiting {
                report.fused = self.fuse_neighbours(&mut m, kf);
            }
        }
        if let Some(p) = &self.priors {
            let mut m = lock(map);
            if let Some(g) = p.try_georeference(&mut m) {
                tracing::info!(
                    kf = kf.0,
                    scale = g.ned_from_map.scale,
                    pairs = g.pairs,
                    inliers = g.inliers,
                    rms_m = g.rms_m,
                    "map put in local NED by telemetry (gps-aided)"
                );
                self.georeferenced = Some((kf, g));
            } else if let Some(g) = p.try_realign(&mut m) {
                tracing::info!(
                    kf = kf.0,
                    scale = g.ned_from_map.scale,
                    inliers = g.inliers,
                    rms_m = g.rms_m,
                    "map refit to the telemetry's fixes"
                );
            }
        }
        if !more_waiting {
            let t_ba = Instant::now();
            if let Some(rmse) = self.local_bundle_adjustment(map, kf) {
                report.ba_rmse_px = rmse;
            }
            report.ba_ms = t_ba.elapsed().as_secs_f64() * 1e3;
            let mut m = lock(map);
            report.culled_keyframes = self.cull_keyframes(&mut m, kf);
        }
        report.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        tracing::debug!(
            kf = kf.0,
            new_points = report.new_points,
            fused = report.fused,
            culled_points = report.culled_points,
            culled_kfs = report.culled_keyframes,
            ms = report.total_ms,
            ba_ms = report.ba_ms,
            "keyframe mapped"
        );
        self.reports.push(report);
        bound_history(&mut self.reports, self.keep_reports);
        report
    }

    /// The keyframe's BoW vector and direct index into the keyframe
    /// database (computed outside the map lock), unless tracking already
    /// indexed it.
    fn index_keyframe(&self, map: &Mutex<Map>, kf: KeyFrameId) {
        let descriptors = {
            let m = lock(map);
            if m.is_indexed(kf) {
                return;
            }
            match m.keyframe(kf) {
                Some(k) => k.descriptors.clone(),
                None => return,
            }
        };
        let (bow, fv) = self
            .vocabulary
            .transform_with_features(&descriptors, self.bow_level);
        let mut m = lock(map);
        if !m.is_indexed(kf) {
            m.index_keyframe(kf, bow, fv, self.vocabulary.word_count());
        }
    }

    fn cull_recent_points(&mut self, map: &mut Map, current: KeyFrameId) -> usize {
        let mut culled = 0;
        let p = &self.params;
        self.recent.retain(|&(pid, created)| {
            let Some(mp) = map.point(pid) else {
                return false;
            };
            let age = current.0.saturating_sub(created.0);
            if mp.found_ratio() < p.min_found_ratio
                || (age >= 2 && mp.observations.len() <= p.min_recent_observations)
            {
                map.erase_point(pid);
                culled += 1;
                false
            } else {
                age < 3
            }
        });
        culled
    }

    fn create_new_points(&mut self, map: &mut Map, kf: KeyFrameId) -> usize {
        let Some(k1) = map.keyframe(kf) else {
            return 0;
        };
        let neighbours: Vec<KeyFrameId> = k1
            .best_covisible(self.params.triangulation_neighbours)
            .collect();
        let t1 = k1.cam_from_world;
        let c1 = k1.center();
        let r1wc = t1.rotation.inverse();
        let cam = map.camera;
        let k_inv = cam.k_inv();
        let mut created = 0;
        for n in neighbours {
            let Some(k2) = map.keyframe(n) else { continue };
            let t2 = k2.cam_from_world;
            let c2 = k2.center();
            let baseline = (c2 - c1).norm();
            let Some(median2) = map.median_depth(n) else {
                continue;
            };
            if baseline / median2 < self.params.min_baseline_ratio {
                continue;
            }
            let f12 = matcher::fundamental_12(&cam, &t1, &t2);
            let matches = matcher::search_for_triangulation(map, kf, n, &f12, &self.params.matcher);
            let r2wc = t2.rotation.inverse();
            let mut new_points = Vec::new();
            {
                let (Some(k1), Some(k2)) = (map.keyframe(kf), map.keyframe(n)) else {
                    continue;
                };
                for (i1, i2) in matches {
                    let kp1 = &k1.keypoints[i1];
                    let kp2 = &k2.keypoints[i2];
                    let xn1 = k_inv * Vector3::new(kp1.ux as f64, kp1.uy as f64, 1.0);
                    let xn2 = k_inv * Vector3::new(kp2.ux as f64, kp2.uy as f64, 1.0);
                    let ray1 = r1wc * xn1;
                    let ray2 = r2wc * xn2;
                    let cos_par = ray1.dot(&ray2) / (ray1.norm() * ray2.norm());
                    if !(cos_par > 0.0 && cos_par < self.params.max_parallax_cos) {
                        continue;
                    }
                    let Some(x) = geometry::triangulate(
                        &t1,
                        &t2,
                        &Point2::new(xn1.x, xn1.y),
                        &Point2::new(xn2.x, xn2.y),
                    ) else {
                        continue;
                    };
                    let p1 = t1 * x;
                    let p2 = t2 * x;
                    if p1.z <= 0.0 || p2.z <= 0.0 {
                        continue;
                    }
                    let chi = |p: &nalgebra::Point3<f64>, kp: &crate::features::KeyPoint| {
                        let u = cam.fx * p.x / p.z + cam.cx;
                        let v = cam.fy * p.y / p.z + cam.cy;
                        let (ex, ey) = (u - kp.ux as f64, v - kp.uy as f64);
                        (ex * ex + ey * ey) * map.scale.inv_level_sigma2[kp.octave as usize]
                    };
                    if chi(&p1, kp1) > self.params.reprojection_chi2
                        || chi(&p2, kp2) > self.params.reprojection_chi2
                    {
                        continue;
                    }
                    let d1 = (x.coords - c1).norm();
                    let d2 = (x.coords - c2).norm();
                    if d1 == 0.0 || d2 == 0.0 {
                        continue;
                    }
                    let ratio_dist = d2 / d1;
                    let ratio_octave = map.scale.scale_factors[kp1.octave as usize]
                        / map.scale.scale_factors[kp2.octave as usize];
                    let f = self.params.scale_consistency;
                    if ratio_dist * f < ratio_octave || ratio_dist > ratio_octave * f {
                        continue;
                    }
                    new_points.push((x, i1, i2, k1.descriptors[i1]));
                }
            }
            for (x, i1, i2, desc) in new_points {
                // The slot may have been taken by an earlier point of this loop.
                if map.keyframe(kf).and_then(|k| k.points[i1]).is_some()
                    || map.keyframe(n).and_then(|k| k.points[i2]).is_some()
                {
                    continue;
                }
                let pid = map.add_point(x, desc, kf);
                map.add_observation(pid, kf, i1 as u32);
                map.add_observation(pid, n, i2 as u32);
                map.update_point_descriptor(pid);
                map.update_point_normal_and_depth(pid);
                self.recent.push((pid, kf));
                created += 1;
            }
        }
        created
    }

    fn fuse_neighbours(&mut self, map: &mut Map, kf: KeyFrameId) -> usize {
        let Some(k) = map.keyframe(kf) else {
            return 0;
        };
        let mut targets: Vec<KeyFrameId> = Vec::new();
        let mut seen: HashSet<KeyFrameId> = HashSet::from([kf]);
        for n in k
            .best_covisible(self.params.fuse_neighbours)
            .collect::<Vec<_>>()
        {
            if seen.insert(n) {
                targets.push(n);
            }
            if let Some(nk) = map.keyframe(n) {
                for n2 in nk.best_covisible(self.params.fuse_second_neighbours) {
                    if seen.insert(n2) {
                        targets.push(n2);
                    }
                }
            }
        }
        let mut fused = 0;
        let own: Vec<PointId> = k.points.iter().flatten().copied().collect();
        for &t in &targets {
            fused += matcher::fuse(
                map,
                t,
                &own,
                self.params.fuse_radius,
                &self.bounds,
                &self.params.matcher,
            );
        }
        let mut others: Vec<PointId> = Vec::new();
        let mut seen_p: HashSet<PointId> = HashSet::new();
        for &t in &targets {
            if let Some(tk) = map.keyframe(t) {
                for p in tk.points.iter().flatten() {
                    if seen_p.insert(*p) {
                        others.push(*p);
                    }
                }
            }
        }
        fused += matcher::fuse(
            map,
            kf,
            &others,
            self.params.fuse_radius,
            &self.bounds,
            &self.params.matcher,
        );
        let pids: Vec<PointId> = map
            .keyframe(kf)
            .map(|k| k.points.iter().flatten().copied().collect())
            .unwrap_or_default();
        for p in pids {
            map.update_point_descriptor(p);
            map.update_point_normal_and_depth(p);
        }
        map.update_connections(kf);
        fused
    }

    /// Local BA: the keyframe and its covisible keyframes free (the first
    /// keyframe of the keyframe's map fixed), other observers fixed. The solve runs without
    /// the map lock. Returns the final reprojection RMSE.
    fn local_bundle_adjustment(&mut self, map: &Mutex<Map>, kf: KeyFrameId) -> Option<f64> {
        let (corrections, mut setup) = {
            let m = lock(map);
            let corrections = m.corrections();
            let k = m.keyframe(kf)?;
            let mut local: Vec<KeyFrameId> = vec![kf];
            local.extend(k.covisible.iter().map(|c| c.0));
            // The root of the keyframe's map (the gauge of a monocular map).
            let first = m.map_of(kf).and_then(|id| m.root_of(id));
            let fixed: Vec<KeyFrameId> = first.into_iter().collect();
            let mut setup = build_ba_problem(&m, &local, &fixed)?;
            if let Some(p) = &self.priors {
                setup.problem.priors = p.priors_for(&m, &setup);
            }
            (corrections, setup)
        };
        if !setup.problem.poses.iter().any(|p| !p.fixed) {
            return None;
        }
        let report =
            optimize::local_bundle_adjustment(&mut setup.problem, &self.params.local_ba).ok()?;
        tracing::trace!(kf = kf.0, before = report.initial_rmse_px, after = report.final_rmse_px, outliers = report.n_outliers, first = ?report.first_pass, second = ?report.second_pass, "local BA");
        let mut m = lock(map);
        // The loop closer (on its own thread) corrected the map while this
        // was solved: the result would put back poses from before the
        // correction. The next keyframe's local BA starts from the
        // corrected map.
        if m.corrections() != corrections {
            tracing::debug!(
                kf = kf.0,
                "local BA result dropped: the map was corrected while it was solved"
            );
            return None;
        }
        apply_ba_result(&mut m, &setup, &report.outliers);
        Some(report.final_rmse_px)
    }

    fn cull_keyframes(&mut self, map: &mut Map, kf: KeyFrameId) -> usize {
        let Some(k) = map.keyframe(kf) else {
            return 0;
        };
        let candidates: Vec<KeyFrameId> = k.covisible.iter().map(|c| c.0).collect();
        let mut culled = 0;
        for c in candidates {
            let Some(ck) = map.keyframe(c) else { continue };
            if ck.parent.is_none() {
                continue;
            }
            let mut n_points = 0;
            let mut redundant = 0;
            for (i, p) in ck.points.iter().enumerate() {
                let Some(pid) = p else { continue };
                let Some(mp) = map.point(*pid) else { continue };
                n_points += 1;
                if mp.observations.len() <= 3 {
                    continue;
                }
                let octave = ck.keypoints[i].octave;
                let mut others = 0;
                for (okf, oi) in &mp.observations {
                    if *okf == c {
                        continue;
                    }
                    let Some(ok) = map.keyframe(*okf) else {
                        continue;
                    };
                    if ok
                        .keypoints
                        .get(*oi as usize)
                        .is_some_and(|kp| kp.octave <= octave + 1)
                    {
                        others += 1;
                        if others >= 3 {
                            break;
                        }
                    }
                }
                if others >= 3 {
                    redundant += 1;
                }
            }
            if n_points > 0
                && redundant as f64 > self.params.redundant_ratio * n_points as f64
                && map.erase_keyframe(c)
            {
                culled += 1;
            }
        }
        culled
    }
}
