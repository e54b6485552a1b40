//! The robust Sim(3) from the SLAM map frame to local NED, fitted to
//! keyframe camera centres (map) paired with camera positions from
//! telemetry (NED).
//!
//! [`Georeference`] collects pairs as keyframes arrive (a keyframe moved by
//! bundle adjustment is simply added again under its id) and
//! [`Georeference::fit`] runs, in order:
//!
//! 1. refusals: too few pairs; NED positions whose covariance shows too
//!    little motion (largest eigenvalue) or motion too close to a line
//!    (second eigenvalue, absolutely and relative to the first), since the
//!    rotation about that line is then not fixed;
//! 2. seeded RANSAC with Umeyama ([`crate::geometry::umeyama`]) on minimal
//!    samples of 3 pairs (samples whose NED triangle is nearly degenerate are
//!    skipped), scored by MSAC (truncated squared residuals), the previous
//!    fit tried first so that an update usually converges at once, with the
//!    adaptive iteration count `log(1-p)/log(1-w³)`;
//! 3. a least-squares Umeyama refit on the inliers, repeated until the inlier
//!    set is stable;
//! 4. when pairs carry velocities, the time offset between capture times and
//!    telemetry (`p(t + e) ≈ p(t) + v·e`, alternated with Umeyama) and a
//!    refit on the corrected positions;
//! 5. optionally, when pairs carry orientations (`ned ← cam` from telemetry,
//!    `map ← cam` from SLAM), a Levenberg-Marquardt refinement of the Sim(3)
//!    over position and rotation residuals of the inliers together.
//!
//! The fit's quality reports the residual RMS, the pairs used, the inliers
//! and the spread of the positions (eigenvalues of their covariance).

use nalgebra::{Isometry3, Matrix3, Point3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::GeoError;
use super::mount::{MountOffset, MountParams};
use crate::geometry::{Sim3, umeyama};
use crate::optimize::lm::{LmParams, levenberg_marquardt};

mod attitude;
mod drift;
mod newest;

use attitude::Refinement;
pub use drift::{DriftFit, GnssDrift, fit_with_drift, fit_with_drift_readmitting};

/// Tunables of the alignment.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AlignParams {
    /// RANSAC seed.
    pub seed: u64,
    /// Fewest pairs to try a fit.
    pub min_pairs: usize,
    /// A pair is an inlier when its residual is below this, metres (NED).
    pub inlier_threshold_m: f64,
    /// Fewest inliers, as a fraction of the pairs.
    pub min_inlier_ratio: f64,
    /// RANSAC confidence for the adaptive iteration count.
    pub confidence: f64,
    /// Most RANSAC iterations.
    pub max_iterations: usize,
    /// Most refit rounds on the inliers.
    pub refit_rounds: usize,
    /// Minimal samples whose NED triangle has `|ab × ac| / (|ab|·|ac|)`
    /// below this (the sine of its smallest angle at a) are skipped.
    pub min_sample_sine: f64,
    /// Refuse while the standard deviation of the NED positions along their
    /// main direction (square root of the largest covariance eigenvalue) is
    /// below this, metres.
    pub min_extent_m: f64,
    /// Refuse while the standard deviation across the main direction
    /// (square root of the second eigenvalue) is below this, metres.
    pub min_lateral_m: f64,
    /// Refuse while the ratio of the second to the first standard deviation
    /// is below this.
    pub min_lateral_ratio: f64,
    /// Refine with orientations when pairs carry them.
    pub refine_with_orientations: bool,
    /// Standard deviation of a NED camera position, metres (weights the
    /// refinement).
    pub position_sigma_m: f64,
    /// Standard deviation of a camera orientation, degrees (weights the
    /// refinement).
    pub orientation_sigma_deg: f64,
    /// Learn the mount's heading and pitch offsets in the refinement with
    /// orientations: the camera's attitude in the georeferenced map against
    /// the attitude and gimbal angles the vehicle reports
    /// ([`GeoAlignment::mount_offset`], used by every target converted with
    /// the alignment).
    pub estimate_mount: bool,
    /// Prior standard deviation of each learned offset, degrees (keeps them
    /// small on thin evidence).
    pub mount_offset_sigma_deg: f64,
    /// LM settings of the refinement (not configurable from files).
    #[serde(skip)]
    pub lm: LmParams,
    /// Estimate the offset between capture times and the telemetry clock
    /// from pairs carrying a velocity (see [`Pair::v_ned`]).
    pub estimate_time_offset: bool,
    /// Largest offset estimated, seconds.
    pub max_time_offset_s: f64,
    /// The first offset estimate uses the pairs within this multiple of the
    /// inlier threshold of the RANSAC model.
    pub time_offset_search_factor: f64,
    /// Estimate the offset only when the pairs' velocities vary by at least
    /// this much (standard deviation about their mean), m/s.
    pub min_velocity_spread_m_s: f64,
    /// The receiver's drifting bias, estimated in the fit (one state per
    /// window, [`fit_with_drift`]) so the fit maps into the NED the
    /// receiver reads at the newest pair (`None`: a plain Sim(3), the bias
    /// averaged over the pairs).
    pub drift: Option<GnssDrift>,
}

impl Default for AlignParams {
    fn default() -> Self {
        Self {
            seed: 0x6e0_5eed,
            min_pairs: 6,
            inlier_threshold_m: 0.5,
            min_inlier_ratio: 0.5,
            confidence: 0.999,
            max_iterations: 500,
            refit_rounds: 5,
            min_sample_sine: 0.1,
            min_extent_m: 2.0,
            min_lateral_m: 0.5,
            min_lateral_ratio: 0.1,
            refine_with_orientations: true,
            position_sigma_m: 0.1,
            orientation_sigma_deg: 1.0,
            estimate_mount: true,
            mount_offset_sigma_deg: 3.0,
            lm: LmParams {
                max_iterations: 20,
                ..LmParams::default()
            },
            estimate_time_offset: true,
            max_time_offset_s: 0.5,
            time_offset_search_factor: 4.0,
            min_velocity_spread_m_s: 1.0,
            drift: None,
        }
    }
}

/// One keyframe's pair.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pair {
    /// Keyframe id.
    pub kf_id: u64,
    /// Camera centre in the SLAM map frame.
    pub p_map: Point3<f64>,
    /// Camera position in local NED, metres.
    pub p_ned: Point3<f64>,
    /// Capture time, seconds.
    pub time: f64,
    /// Orientations `(map ← cam, ned ← cam)` when known.
    pub orientations: Option<(UnitQuaternion<f64>, UnitQuaternion<f64>)>,
    /// The camera's NED velocity at `time` (m/s) when known: lets the fit
    /// estimate a time offset.
    pub v_ned: Option<Vector3<f64>>,
}

/// The spread of a set of positions: eigenvalues of their covariance,
/// largest first (m²).
pub fn spread(points: impl Iterator<Item = Point3<f64>>) -> [f64; 3] {
    let mut n = 0usize;
    let mut sum = Vector3::zeros();
    let mut sq = Matrix3::zeros();
    for p in points {
        n += 1;
        sum += p.coords;
        sq += p.coords * p.coords.transpose();
    }
    if n == 0 {
        return [0.0; 3];
    }
    let mean = sum / n as f64;
    let cov = sq / n as f64 - mean * mean.transpose();
    let mut e: Vec<f64> = cov
        .symmetric_eigenvalues()
        .iter()
        .map(|v| v.max(0.0))
        .collect();
    e.sort_by(|a, b| b.total_cmp(a));
    [e[0], e[1], e[2]]
}

/// How good a fit is.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct AlignQuality {
    /// RMS of the inliers' position residuals, metres (NED).
    pub rms_m: f64,
    /// Largest inlier residual, metres.
    pub max_residual_m: f64,
    /// RMS of the inliers' rotation residuals, degrees (when orientations
    /// were used).
    pub rotation_rms_deg: Option<f64>,
    /// Estimated offset of the capture times on the telemetry clock,
    /// seconds (positive: the given capture times are late), when estimated.
    pub time_offset_s: Option<f64>,
    /// Pairs held.
    pub pairs: usize,
    /// Inliers used by the final fit.
    pub inliers: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
    /// Eigenvalues of the covariance of the inliers' NED positions, largest
    /// first, m².
    pub spread_m2: [f64; 3],
    /// Older pairs left out of the fit because the pairs as a whole did not
    /// agree and the newest ones did (see [`Georeference::fit`]); 0 for a
    /// fit of every pair.
    pub set_aside: usize,
    /// With [`AlignParams::drift`]: the GNSS bias estimated at the newest
    /// pair, NED, m (already in the fit's translation); the residuals are
    /// then those after each pair's own window's bias.
    pub gnss_bias_m: Option<[f64; 3]>,
}

/// A fitted map → NED similarity and its quality.
#[derive(Debug, Clone, PartialEq)]
pub struct GeoAlignment {
    /// `ned ← map`: `p_ned = s·R·p_map + t`.
    pub ned_from_map: Sim3,
    /// Its quality.
    pub quality: AlignQuality,
    /// Ids of the inlier keyframes.
    pub inlier_ids: Vec<u64>,
    /// The mount's calibration as the fit learned it
    /// ([`AlignParams::estimate_mount`]), to add to the configured mount
    /// ([`GeoAlignment::mount`]).
    pub mount_offset: Option<MountOffset>,
}

impl GeoAlignment {
    /// An alignment known rather than fitted (the simulator's truth, a
    /// test's chosen transform): `ned_from_map` with a zero-residual,
    /// zero-pair quality and no inlier keyframes.
    pub fn given(ned_from_map: Sim3) -> Self {
        Self {
            ned_from_map,
            quality: AlignQuality {
                rms_m: 0.0,
                max_residual_m: 0.0,
                rotation_rms_deg: None,
                time_offset_s: None,
                pairs: 0,
                inliers: 0,
                iterations: 0,
                spread_m2: [0.0; 3],
                set_aside: 0,
                gnss_bias_m: None,
            },
            inlier_ids: Vec::new(),
            mount_offset: None,
        }
    }

    /// The configured mount with the offsets this fit learned: what turns
    /// a camera pose through this alignment into vehicle commands and back.
    pub fn mount(&self, configured: &MountParams) -> MountParams {
        match &self.mount_offset {
            Some(o) => configured.corrected(o),
            None => configured.clone(),
        }
    }

    /// The georeference of a map already in local NED (gps-aided by
    /// telemetry priors): the identity, not fitted (`iterations` 0), with
    /// its residuals against the keyframe `pairs`, and the mount's offsets
    /// learned from their orientations when `params` asks.
    pub fn of_map_in_ned(pairs: &[Pair], params: &AlignParams) -> Self {
        let mut a = Self::given(Sim3::identity());
        let r: Vec<f64> = pairs.iter().map(|p| (p.p_ned - p.p_map).norm()).collect();
        if !r.is_empty() {
            (a.quality.rms_m, a.quality.max_residual_m) = rms_max(&r);
            a.quality.spread_m2 = spread(pairs.iter().map(|p| p.p_ned));
        }
        a.quality.pairs = pairs.len();
        a.quality.inliers = pairs.len();
        a.inlier_ids = pairs.iter().map(|p| p.kf_id).collect();
        let oriented = pairs.iter().filter(|p| p.orientations.is_some()).count();
        if params.estimate_mount && oriented >= 3 {
            let refs: Vec<&Pair> = pairs.iter().collect();
            let mut problem = Refinement::new(&refs, Sim3::identity(), params);
            problem.free_sim = false;
            levenberg_marquardt(&mut problem, &params.lm);
            a.quality.rotation_rms_deg = Some(problem.rotation_rms().to_degrees());
            a.mount_offset = problem.mount_offset();
        }
        a
    }

    /// A camera pose in the map (`map ← cam`) as a camera pose in NED.
    pub fn ned_from_cam(&self, map_from_cam: &Isometry3<f64>) -> Isometry3<f64> {
        let s = &self.ned_from_map;
        Isometry3::from_parts(
            s.transform_point(&Point3::from(map_from_cam.translation.vector))
                .coords
                .into(),
            s.rotation * map_from_cam.rotation,
        )
    }

    /// A point in the map as a point in NED.
    pub fn ned_from_map_point(&self, p_map: &Point3<f64>) -> Point3<f64> {
        self.ned_from_map.transform_point(p_map)
    }
}

/// Collects keyframe pairs and fits the map → NED similarity.
///
/// A refit refused for too little evidence (too few pairs, too little or
/// too straight motion: the map culled the keyframes that made the
/// baseline, not new evidence against the fit) keeps the last successful
/// alignment while the pairs still held agree with it (within the inlier
/// threshold, in the share a fit needs): the operator's georeference does
/// not vanish mid-mission because a redundant keyframe was culled.
/// [`Georeference::held`] says when that is the case and why.
#[derive(Debug, Clone)]
pub struct Georeference {
    params: AlignParams,
    pairs: Vec<Pair>,
    last: Option<GeoAlignment>,
    held: Option<GeoError>,
    changed: bool,
    fits: u64,
}

impl Georeference {
    /// An empty georeference.
    pub fn new(params: AlignParams) -> Self {
        Self {
            params,
            pairs: Vec::new(),
            last: None,
            held: None,
            changed: false,
            fits: 0,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &AlignParams {
        &self.params
    }

    /// The pairs held.
    pub fn pairs(&self) -> &[Pair] {
        &self.pairs
    }

    /// The last successful fit.
    pub fn last(&self) -> Option<&GeoAlignment> {
        self.last.as_ref()
    }

    /// Why the last fit is held instead of refitted: the refit's refusal
    /// (too little evidence left), while the pairs held still agree with
    /// the last fit. `None` when the last fit is current.
    pub fn held(&self) -> Option<&GeoError> {
        self.held.as_ref()
    }

    /// Adds (or, for a known id, replaces) a keyframe's camera centre in the
    /// map and its camera position in NED.
    pub fn add_pair(
        &mut self,
        kf_id: u64,
        p_map: Point3<f64>,
        p_ned: Point3<f64>,
        time: f64,
    ) -> Result<(), GeoError> {
        self.insert(Pair {
            kf_id,
            p_map,
            p_ned,
            time,
            orientations: None,
            v_ned: None,
        })
    }

    /// Adds (or replaces) a keyframe with its full camera poses in the map
    /// and in NED, so the fit can be refined with orientations, and the
    /// camera's NED velocity when known ([`crate::geo::VehicleState::v_ned`]),
    /// so it can estimate the time offset.
    pub fn add_keyframe(
        &mut self,
        kf_id: u64,
        map_from_cam: &Isometry3<f64>,
        ned_from_cam: &Isometry3<f64>,
        v_ned: Option<Vector3<f64>>,
        time: f64,
    ) -> Result<(), GeoError> {
        if !(map_from_cam.rotation.coords.iter().all(|v| v.is_finite())
            && ned_from_cam.rotation.coords.iter().all(|v| v.is_finite())
            && v_ned.is_none_or(|v| v.iter().all(|x| x.is_finite())))
        {
            return Err(GeoError::NonFinite {
                what: "keyframe orientation",
            });
        }
        self.insert(Pair {
            kf_id,
            p_map: map_from_cam.translation.vector.into(),
            p_ned: ned_from_cam.translation.vector.into(),
            time,
            orientations: Some((map_from_cam.rotation, ned_from_cam.rotation)),
            v_ned,
        })
    }

    /// Moves a held keyframe's map side (bundle adjustment moved it),
    /// keeping its NED side. Returns whether it was held.
    pub fn update_map_pose(
        &mut self,
        kf_id: u64,
        map_from_cam: &Isometry3<f64>,
    ) -> Result<bool, GeoError> {
        if !(map_from_cam
            .translation
            .vector
            .iter()
            .all(|v| v.is_finite())
            && map_from_cam.rotation.coords.iter().all(|v| v.is_finite()))
        {
            return Err(GeoError::NonFinite {
                what: "keyframe pose",
            });
        }
        let Some(p) = self.pairs.iter_mut().find(|p| p.kf_id == kf_id) else {
            return Ok(false);
        };
        p.p_map = map_from_cam.translation.vector.into();
        if let Some((map_rot, _)) = &mut p.orientations {
            *map_rot = map_from_cam.rotation;
        }
        self.changed = true;
        Ok(true)
    }

    /// Whether a keyframe's pair is held.
    pub fn contains(&self, kf_id: u64) -> bool {
        self.pairs.iter().any(|p| p.kf_id == kf_id)
    }

    /// Forgets a keyframe (culled by the map). Returns whether it was held.
    pub fn remove(&mut self, kf_id: u64) -> bool {
        let before = self.pairs.len();
        self.pairs.retain(|p| p.kf_id != kf_id);
        let removed = self.pairs.len() != before;
        self.changed |= removed;
        removed
    }

    fn insert(&mut self, pair: Pair) -> Result<(), GeoError> {
        if !(pair.p_map.iter().all(|v| v.is_finite())
            && pair.p_ned.iter().all(|v| v.is_finite())
            && pair.time.is_finite())
        {
            return Err(GeoError::NonFinite { what: "pair" });
        }
        match self.pairs.iter_mut().find(|p| p.kf_id == pair.kf_id) {
            Some(p) => *p = pair,
            None => self.pairs.push(pair),
        }
        self.changed = true;
        Ok(())
    }

    /// Fits (or, when nothing changed since the last success, returns) the
    /// map → NED similarity. When the pairs disagree as a whole (too few
    /// inliers), the newest pairs that agree among themselves are fitted
    /// and the older ones set aside ([`AlignQuality::set_aside`]).
    pub fn fit(&mut self) -> Result<GeoAlignment, GeoError> {
        if !self.changed
            && let Some(last) = &self.last
        {
            return Ok(last.clone());
        }
        let previous = self.last.as_ref().map(|a| a.ned_from_map);
        let seed = self.params.seed.wrapping_add(self.fits);
        let result = match fit_pairs(&self.pairs, &self.params, previous.as_ref(), seed) {
            Err(e @ GeoError::TooFewInliers { .. }) => {
                self.fit_newest(previous.as_ref(), seed).ok_or(e)
            }
            r => r,
        };
        self.fits += 1;
        match result {
            Ok(a) => {
                self.last = Some(a.clone());
                self.held = None;
                self.changed = false;
                Ok(a)
            }
            Err(e) => match self.hold(&e) {
                Some(a) => {
                    self.held = Some(e);
                    Ok(a)
                }
                None => {
                    self.held = None;
                    Err(e)
                }
            },
        }
    }

    /// The last fit, when `refusal` only says the evidence is too thin
    /// now and the pairs held still agree with it.
    fn hold(&self, refusal: &GeoError) -> Option<GeoAlignment> {
        let thin = matches!(
            refusal,
            GeoError::NotEnoughPairs { .. }
                | GeoError::TooLittleMotion { .. }
                | GeoError::Collinear { .. }
        );
        let last = self.last.as_ref().filter(|_| thin)?;
        let th = self.params.inlier_threshold_m;
        let agree = self
            .pairs
            .iter()
            .filter(|p| residual(&last.ned_from_map, p) < th)
            .count();
        let needed = inliers_needed(&self.params, self.pairs.len());
        (agree >= needed).then(|| last.clone())
    }
}

/// Refuses NED positions without enough motion, or too close to a line.
pub fn check_motion(spread_m2: [f64; 3], params: &AlignParams) -> Result<(), GeoError> {
    let main = spread_m2[0].sqrt();
    let lateral = spread_m2[1].sqrt();
    if main < params.min_extent_m {
        return Err(GeoError::TooLittleMotion {
            extent_m: main,
            needed_m: params.min_extent_m,
        });
    }
    let ratio = lateral / main;
    if lateral < params.min_lateral_m || ratio < params.min_lateral_ratio {
        return Err(GeoError::Collinear {
            lateral_m: lateral,
            needed_m: params.min_lateral_m,
            ratio,
            needed_ratio: params.min_lateral_ratio,
        });
    }
    Ok(())
}

/// RMS and largest of residuals, metres ((0, 0) for none).
fn rms_max(r: &[f64]) -> (f64, f64) {
    if r.is_empty() {
        return (0.0, 0.0);
    }
    let rms = (r.iter().map(|x| x * x).sum::<f64>() / r.len() as f64).sqrt();
    (rms, r.iter().copied().fold(0.0, f64::max))
}

/// Inliers a fit of `n` pairs needs: `min_inlier_ratio` of them.
fn inliers_needed(params: &AlignParams, n: usize) -> usize {
    (params.min_inlier_ratio * n as f64).ceil() as usize
}

fn residual(s: &Sim3, p: &Pair) -> f64 {
    (s.transform_point(&p.p_map) - p.p_ned).norm()
}

/// The fit on a fixed set of pairs (see the module documentation).
pub fn fit_pairs(
    pairs: &[Pair],
    params: &AlignParams,
    previous: Option<&Sim3>,
    seed: u64,
) -> Result<GeoAlignment, GeoError> {
    let n = pairs.len();
    let needed = params.min_pairs.max(3);
    if n < needed {
        return Err(GeoError::NotEnoughPairs { found: n, needed });
    }
    check_motion(spread(pairs.iter().map(|p| p.p_ned)), params)?;

    let th = params.inlier_threshold_m;
    let th2 = th * th;
    let msac = |s: &Sim3| -> (f64, usize) {
        let mut cost = 0.0;
        let mut inl = 0;
        for p in pairs {
            let r2 = (s.transform_point(&p.p_map) - p.p_ned).norm_squared();
            if r2 < th2 {
                inl += 1;
                cost += r2;
            } else {
                cost += th2;
            }
        }
        (cost, inl)
    };
    let mut best: Option<(Sim3, f64, usize)> = None;
    let consider = |s: Sim3, best: &mut Option<(Sim3, f64, usize)>| {
        if !(s.scale.is_finite() && s.scale > 0.0) {
            return;
        }
        let (cost, inl) = msac(&s);
        if best.as_ref().is_none_or(|b| cost < b.1) {
            *best = Some((s, cost, inl));
        }
    };
    if let Some(prev) = previous {
        consider(*prev, &mut best);
    }
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut iterations = 0usize;
    let mut needed_iterations = params.max_iterations;
    let mut src = [Point3::origin(); 3];
    let mut dst = [Point3::origin(); 3];
    while iterations < needed_iterations.min(params.max_iterations) {
        iterations += 1;
        let i = rng.random_range(0..n);
        let mut j = rng.random_range(0..n - 1);
        if j >= i {
            j += 1;
        }
        let mut k = rng.random_range(0..n - 2);
        let (lo, hi) = (i.min(j), i.max(j));
        if k >= lo {
            k += 1;
        }
        if k >= hi {
            k += 1;
        }
        let (a, b, c) = (pairs[i].p_ned, pairs[j].p_ned, pairs[k].p_ned);
        let (ab, ac) = (b - a, c - a);
        let denom = ab.norm() * ac.norm();
        if denom <= 0.0 || ab.cross(&ac).norm() / denom < params.min_sample_sine {
            continue;
        }
        for (slot, idx) in [i, j, k].into_iter().enumerate() {
            src[slot] = pairs[idx].p_map;
            dst[slot] = pairs[idx].p_ned;
        }
        let Ok(s) = umeyama(&src, &dst, true) else {
            continue;
        };
        consider(s, &mut best);
        if let Some((_, _, inl)) = &best {
            let w = *inl as f64 / n as f64;
            let denom = (1.0 - w * w * w).max(1e-12).ln();
            if denom < 0.0 {
                let k = ((1.0 - params.confidence).ln() / denom).ceil();
                if k.is_finite() && k >= 0.0 {
                    needed_iterations = (k as usize).max(1);
                }
            }
        }
    }
    let min_inliers = inliers_needed(params, n).max(3);
    let Some((mut model, _, _)) = best else {
        return Err(GeoError::TooFewInliers {
            found: 0,
            needed: min_inliers,
            pairs: n,
        });
    };

    // Time offset between the capture times and the telemetry clock: a
    // first estimate on the pairs within a loose threshold of the RANSAC
    // model (an offset moves pairs by |v|·e, possibly beyond the inlier
    // threshold), a refit on the corrected positions, then a second estimate
    // on the strict inliers and a last refit.
    let mut time_offset_s = None;
    let mut corrected: Vec<Pair> = Vec::new();
    if params.estimate_time_offset {
        let loose = th * params.time_offset_search_factor.max(1.0);
        let mask: Vec<bool> = pairs.iter().map(|p| residual(&model, p) < loose).collect();
        let mut trial = model;
        if let Some(e1) = estimate_time_offset(pairs, &mask, &mut trial, params) {
            let shifted = shift_pairs(pairs, e1);
            if let Ok(mask) = refit(&shifted, &mut trial, th, min_inliers, params.refit_rounds)
                && let Some(e2) = estimate_time_offset(pairs, &mask, &mut trial, params)
            {
                time_offset_s = Some(e2);
                corrected = shift_pairs(pairs, e2);
                model = trial;
            }
        }
    }
    let pairs: &[Pair] = if time_offset_s.is_some() {
        &corrected
    } else {
        pairs
    };
    let mask = refit(pairs, &mut model, th, min_inliers, params.refit_rounds)?;
    let inliers: Vec<&Pair> = pairs
        .iter()
        .zip(&mask)
        .filter(|(_, m)| **m)
        .map(|(p, _)| p)
        .collect();
    let spread_m2 = spread(inliers.iter().map(|p| p.p_ned));
    check_motion(spread_m2, params)?;

    let mut rotation_rms_deg = None;
    let mut mount_offset = None;
    let oriented = inliers.iter().filter(|p| p.orientations.is_some()).count();
    if params.refine_with_orientations && oriented >= 3 {
        // Every inlier's position, and the orientations of those that have
        // one.
        let mut problem = Refinement::new(&inliers, model, params);
        levenberg_marquardt(&mut problem, &params.lm);
        if problem.sim.scale.is_finite() && problem.sim.scale > 0.0 {
            model = problem.sim;
        }
        rotation_rms_deg = Some(problem.rotation_rms().to_degrees());
        mount_offset = problem.mount_offset();
    }
    let mut gnss_bias_m = None;
    let mut r: Vec<f64> = inliers.iter().map(|p| residual(&model, p)).collect();
    let mut inliers = inliers;
    if let Some(drift) = &params.drift {
        let others: Vec<&Pair> = pairs
            .iter()
            .zip(&mask)
            .filter(|(_, m)| !**m)
            .map(|(p, _)| p)
            .collect();
        if let Some((fit, used)) = fit_with_drift_readmitting(
            inliers.clone(),
            others,
            model,
            drift,
            rotation_rms_deg.is_some(),
            th,
        ) {
            model = fit.ned_from_map;
            gnss_bias_m = Some(fit.newest_bias.into());
            r = fit.residuals;
            inliers = used;
        }
    }
    let (rms_m, max_residual_m) = rms_max(&r);
    Ok(GeoAlignment {
        ned_from_map: model,
        quality: AlignQuality {
            rms_m,
            max_residual_m,
            rotation_rms_deg,
            time_offset_s,
            pairs: n,
            inliers: inliers.len(),
            iterations,
            spread_m2,
            set_aside: 0,
            gnss_bias_m,
        },
        inlier_ids: inliers.iter().map(|p| p.kf_id).collect(),
        mount_offset,
    })
}

/// The pairs with their NED positions moved back by `v·e`.
fn shift_pairs(pairs: &[Pair], e: f64) -> Vec<Pair> {
    pairs
        .iter()
        .map(|p| Pair {
            p_ned: p.p_ned - p.v_ned.unwrap_or_else(Vector3::zeros) * e,
            ..*p
        })
        .collect()
}

/// Least-squares refits on the inliers until the inlier set is stable;
/// returns the final inlier mask.
fn refit(
    pairs: &[Pair],
    model: &mut Sim3,
    th: f64,
    min_inliers: usize,
    rounds: usize,
) -> Result<Vec<bool>, GeoError> {
    let n = pairs.len();
    let mut mask: Vec<bool> = pairs.iter().map(|p| residual(model, p) < th).collect();
    for _ in 0..rounds.max(1) {
        let count = mask.iter().filter(|m| **m).count();
        if count < min_inliers {
            return Err(GeoError::TooFewInliers {
                found: count,
                needed: min_inliers,
                pairs: n,
            });
        }
        let (src, dst): (Vec<_>, Vec<_>) = pairs
            .iter()
            .zip(&mask)
            .filter(|(_, m)| **m)
            .map(|(p, _)| (p.p_map, p.p_ned))
            .unzip();
        *model = umeyama(&src, &dst, true)?;
        let next: Vec<bool> = pairs.iter().map(|p| residual(model, p) < th).collect();
        if next == mask {
            break;
        }
        mask = next;
    }
    let count = mask.iter().filter(|m| **m).count();
    if count < min_inliers {
        return Err(GeoError::TooFewInliers {
            found: count,
            needed: min_inliers,
            pairs: n,
        });
    }
    Ok(mask)
}

/// Estimates the offset `e` (seconds) by which the capture times are late
/// on the telemetry clock, from the inliers carrying a velocity: the NED
/// position looked up at a late time is `p(t + e) ≈ p(t) + v·e`, so `e` and
/// the Sim(3) minimise `Σ|S(m_i) - (p_i - v_i·e)|²`. Alternates the
/// closed-form `e` for a fixed rotation and scale (velocities and residuals
/// centred, since the translation absorbs a common shift) with Umeyama on
/// the corrected positions. `None` when too few inliers carry a velocity or
/// the velocities vary too little to separate `e` from the translation.
fn estimate_time_offset(
    pairs: &[Pair],
    mask: &[bool],
    model: &mut Sim3,
    params: &AlignParams,
) -> Option<f64> {
    let used: Vec<(&Pair, Vector3<f64>)> = pairs
        .iter()
        .zip(mask)
        .filter(|(_, m)| **m)
        .filter_map(|(p, _)| p.v_ned.map(|v| (p, v)))
        .collect();
    if used.len() < params.min_pairs.max(3) {
        return None;
    }
    let inv_n = 1.0 / used.len() as f64;
    let v_mean = used.iter().map(|(_, v)| *v).sum::<Vector3<f64>>() * inv_n;
    let v_var = used
        .iter()
        .map(|(_, v)| (v - v_mean).norm_squared())
        .sum::<f64>()
        * inv_n;
    if v_var.sqrt() < params.min_velocity_spread_m_s {
        return None;
    }
    let limit = params.max_time_offset_s.abs();
    let mut e = 0.0;
    let mut trial = *model;
    for _ in 0..20 {
        let q: Vec<Vector3<f64>> = used
            .iter()
            .map(|(p, _)| trial.transform_point(&p.p_map) - p.p_ned)
            .collect();
        let q_mean = q.iter().sum::<Vector3<f64>>() * inv_n;
        let num: f64 = used
            .iter()
            .zip(&q)
            .map(|((_, v), q)| (v - v_mean).dot(&(q - q_mean)))
            .sum();
        let next = (-num / (v_var * used.len() as f64)).clamp(-limit, limit);
        let (src, dst): (Vec<_>, Vec<_>) = used
            .iter()
            .map(|(p, v)| (p.p_map, p.p_ned - v * next))
            .unzip();
        trial = umeyama(&src, &dst, true).ok()?;
        let done = (next - e).abs() < 1e-6;
        e = next;
        if done {
            break;
        }
    }
    *model = trial;
    Some(e)
}
