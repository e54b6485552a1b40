//! Telemetry-aided tracking (issue 35, point 2): when vision cannot pose a
//! frame on its own (ground with little texture: grass, water), the
//! telemetry predicts it from the last frame vision posed, the *anchor*:
//!
//! - the turn from the camera's reported attitude, relative between the
//!   anchor and the frame (`ned_from_cam` of both), so the attitude's slow
//!   error (a heading off by degrees) cancels and only its change over the
//!   gap counts;
//! - the move from the GNSS displacement between the two when the map is in
//!   local NED ([`MapMode::GpsAided`]), again relative (the receiver's bias
//!   is common to both), else from the camera's velocity over the last
//!   vision frames.
//!
//! The local map is then searched around that prediction, and the pose
//! optimised on what vision found with the prediction as a prior
//! ([`crate::optimize::PosePrior`], its sigmas growing with the gap).
//! With enough inliers the frame is posed by *vision + telemetry*, else by
//! *telemetry* alone (the prediction). Keyframes are only made from frames
//! vision supports ([`super::TrackingParams::min_tracked_inliers`]), and a
//! gap longer than [`AidParams::max_gap_s`] is a loss as before. Each frame
//! says which it was ([`PoseSource`]).
//!
//! The same relative motion decides what vision alone cannot over flat
//! ground: which of a planar pair's two reconstructions is the real one
//! ([`RelativeMotion`], [`super::planar::telemetry_choice`]).

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

use crate::optimize::PosePrior;

use super::frame::FrameRecord;
pub use super::frame::PoseSource;
use super::map::{Map, MapMode};
use super::priors::{TelemetryFeed, TelemetrySample};

/// Tunables of telemetry-aided tracking.
#[derive(Debug, Clone, PartialEq)]
pub struct AidParams {
    /// A frame takes the telemetry sample nearest its time within this, s.
    pub max_dt_s: f64,
    /// Else the two samples around it when at most this far apart, s
    /// (telemetry slower than the video).
    pub interpolate_gap_s: Option<f64>,
    /// Longest time since the anchor the telemetry may pose frames for, s;
    /// beyond it tracking is lost as without the aid.
    pub max_gap_s: f64,
    /// Standard deviation of the reported attitude's change between two
    /// samples close in time, degrees (its noise).
    pub rotation_sigma_deg: f64,
    /// Growth of that deviation with the time since the anchor, degrees
    /// per square root of a second (the slow error's walk).
    pub rotation_walk_deg_per_sqrt_s: f64,
    /// Standard deviation of the reported attitude itself, degrees (the
    /// heading's, mostly): the direction of travel in the camera's axes
    /// carries it.
    pub attitude_sigma_deg: f64,
    /// Standard deviation of the GNSS displacement between two fixes close
    /// in time, m (the receiver's noise).
    pub position_sigma_m: f64,
    /// Its growth with the time since the anchor, m per square root of a
    /// second, at least (the bias's walk): a receiver reporting an
    /// accuracy `h_acc` walks `h_acc * sqrt(2 / gnss_bias_tau_s)` (a
    /// Gauss-Markov bias of that sigma), when that is more.
    pub position_walk_m_per_sqrt_s: f64,
    /// Correlation time of the receiver's bias, s.
    pub gnss_bias_tau_s: f64,
    /// Longest the telemetry may pose frames without the GNSS (a map not in
    /// local NED, or no fix), s: the camera's velocity then carries the
    /// move, and its error grows with the square of the gap.
    pub max_gap_without_gnss_s: f64,
    /// A new map started after vision was lost is put into the old one at
    /// once by the telemetry (the map in local NED) when the old map's last
    /// vision pose is at most this old, s.
    pub max_place_gap_s: f64,
    /// A new map is put into the old one only over a GNSS baseline (between
    /// its two initialisation frames) of this many of the displacement's
    /// sigmas: the scale's error is about one over it.
    pub min_place_baseline_sigmas: f64,
    /// A placed map's scale and place are refit once its keyframes with a
    /// fix span this GNSS baseline, m ([`refit_placement`]).
    pub refit_baseline_m: f64,
    /// A relocalisation in a map in local NED is refused when it puts the
    /// camera further from its GNSS position than this many of the
    /// receiver's reported accuracies (at least
    /// [`AidParams::min_reloc_distance_m`]).
    pub max_reloc_gnss_sigmas: f64,
    /// The least of that distance, m.
    pub min_reloc_distance_m: f64,
    /// Vision inliers a frame needs to be posed by vision + telemetry
    /// rather than by the telemetry alone.
    pub min_inliers: usize,
    /// Search radius of the local map's points around the prediction,
    /// pixels at level 0.
    pub search_radius: f64,
}

impl Default for AidParams {
    fn default() -> Self {
        AidParams {
            max_dt_s: 0.05,
            interpolate_gap_s: Some(0.5),
            max_gap_s: 10.0,
            max_gap_without_gnss_s: 1.0,
            max_place_gap_s: 60.0,
            min_place_baseline_sigmas: 10.0,
            refit_baseline_m: 20.0,
            max_reloc_gnss_sigmas: 5.0,
            min_reloc_distance_m: 5.0,
            rotation_sigma_deg: 0.1,
            rotation_walk_deg_per_sqrt_s: 0.3,
            attitude_sigma_deg: 2.0,
            position_sigma_m: 0.05,
            position_walk_m_per_sqrt_s: 0.1,
            gnss_bias_tau_s: 120.0,
            min_inliers: 12,
            search_radius: 15.0,
        }
    }
}

impl AidParams {
    /// The GNSS displacement's walk, m per square root of a second, for a
    /// receiver reporting `h_acc` (see
    /// [`AidParams::position_walk_m_per_sqrt_s`]).
    pub fn walk(&self, h_acc: f64) -> f64 {
        let from_receiver = if h_acc.is_finite() && self.gnss_bias_tau_s > 0.0 {
            h_acc * (2.0 / self.gnss_bias_tau_s).sqrt()
        } else {
            0.0
        };
        self.position_walk_m_per_sqrt_s.max(from_receiver)
    }

    /// Checks the numbers; the error names the first bad one.
    pub fn check(&self) -> Result<(), String> {
        let positive = [
            ("max_dt_s", self.max_dt_s),
            ("max_gap_s", self.max_gap_s),
            ("gnss_bias_tau_s", self.gnss_bias_tau_s),
            ("max_gap_without_gnss_s", self.max_gap_without_gnss_s),
            ("max_place_gap_s", self.max_place_gap_s),
            ("min_place_baseline_sigmas", self.min_place_baseline_sigmas),
            ("refit_baseline_m", self.refit_baseline_m),
            ("max_reloc_gnss_sigmas", self.max_reloc_gnss_sigmas),
            ("min_reloc_distance_m", self.min_reloc_distance_m),
            ("search_radius", self.search_radius),
        ];
        for (name, v) in positive {
            if !(v > 0.0 && v.is_finite()) {
                return Err(format!("{name} must be positive, not {v}"));
            }
        }
        let non_negative = [
            ("rotation_sigma_deg", self.rotation_sigma_deg),
            (
                "rotation_walk_deg_per_sqrt_s",
                self.rotation_walk_deg_per_sqrt_s,
            ),
            ("attitude_sigma_deg", self.attitude_sigma_deg),
            ("position_sigma_m", self.position_sigma_m),
            (
                "position_walk_m_per_sqrt_s",
                self.position_walk_m_per_sqrt_s,
            ),
        ];
        for (name, v) in non_negative {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(format!("{name} must be zero or more, not {v}"));
            }
        }
        if let Some(g) = self.interpolate_gap_s
            && !(g > 0.0 && g.is_finite())
        {
            return Err(format!("interpolate_gap_s must be positive, not {g}"));
        }
        if self.min_inliers < 3 {
            return Err(format!(
                "min_inliers must be at least 3, not {}",
                self.min_inliers
            ));
        }
        Ok(())
    }
}

/// The telemetry tracking is aided by, and its tunables.
#[derive(Debug, Clone, PartialEq)]
pub struct TelemetryAid {
    /// Tunables.
    pub params: AidParams,
    /// The telemetry (a dataset's log, or the daemon's live feed).
    pub feed: TelemetryFeed,
}

impl TelemetryAid {
    /// Aid from `feed` with the default tunables.
    pub fn new(feed: TelemetryFeed) -> Self {
        TelemetryAid {
            params: AidParams::default(),
            feed,
        }
    }

    /// The sample at `t` with an attitude, if any.
    pub(super) fn sample(&self, t: f64) -> Option<TelemetrySample> {
        self.feed
            .sample_at(t, self.params.max_dt_s, self.params.interpolate_gap_s)
            .filter(|s| s.ned_from_cam.is_some())
    }
}

/// The motion between two frames as the telemetry reports it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RelativeMotion {
    /// `cam2 ← cam1` from the two reported attitudes.
    pub rotation: UnitQuaternion<f64>,
    /// Its standard deviation, radians.
    pub rotation_sigma: f64,
    /// The direction of camera 2's centre in camera 1's axes, from the
    /// GNSS displacement (`None`: no fix at one of them, or a displacement
    /// within the receiver's noise).
    pub direction: Option<Vector3<f64>>,
    /// Standard deviation of the direction, radians.
    pub direction_sigma: f64,
}

impl TelemetryAid {
    /// Standard deviation of the GNSS displacement over `dt` seconds, m.
    fn displacement_sigma(&self, dt: f64, h_acc: f64) -> f64 {
        let p = &self.params;
        (2.0 * p.position_sigma_m.powi(2) + p.walk(h_acc).powi(2) * dt.abs()).sqrt()
    }

    /// The GNSS baseline a new map needs between frames at `t1` and `t2`
    /// to be put into the old one, m
    /// ([`AidParams::min_place_baseline_sigmas`] of the displacement's
    /// sigma with the receiver's reported accuracy then).
    pub fn place_baseline_m(&self, t1: f64, t2: f64) -> f64 {
        let h_acc = [t1, t2]
            .iter()
            .filter_map(|t| self.sample(*t))
            .map(|s| s.h_acc)
            .fold(0.0, f64::max);
        self.params.min_place_baseline_sigmas * self.displacement_sigma(t2 - t1, h_acc)
    }

    /// The GNSS displacement between times `t1` and `t2`, m (`None`: no
    /// fix at one of them).
    pub fn gnss_displacement(&self, t1: f64, t2: f64) -> Option<f64> {
        let (a, b) = (self.sample(t1)?, self.sample(t2)?);
        (a.fix && b.fix).then(|| (b.gps_ned - a.gps_ned).norm())
    }

    /// The reported motion from time `t1` to `t2`, when both have an
    /// attitude.
    pub fn relative_motion(&self, t1: f64, t2: f64) -> Option<RelativeMotion> {
        let (a, b) = (self.sample(t1)?, self.sample(t2)?);
        let (qa, qb) = (a.ned_from_cam?, b.ned_from_cam?);
        let p = &self.params;
        let dt = (t2 - t1).abs();
        let rotation_sigma = (p.rotation_sigma_deg.powi(2)
            + p.rotation_walk_deg_per_sqrt_s.powi(2) * dt)
            .sqrt()
            .to_radians();
        let pos_sigma = self.displacement_sigma(dt, a.h_acc.max(b.h_acc));
        let d = b.gps_ned - a.gps_ned;
        let known = a.fix && b.fix && d.norm() > DIRECTION_MIN_SIGMAS * pos_sigma;
        Some(RelativeMotion {
            rotation: qb.inverse() * qa,
            rotation_sigma,
            direction: known.then(|| (qa.inverse() * d).normalize()),
            direction_sigma: (pos_sigma / d.norm().max(1e-9))
                .atan()
                .hypot(p.attitude_sigma_deg.to_radians()),
        })
    }
}

/// A GNSS displacement gives a direction once it is this many of its
/// sigmas long.
const DIRECTION_MIN_SIGMAS: f64 = 4.0;

/// The last frame vision posed, which predictions start from.
#[derive(Debug, Clone, Copy)]
pub(super) struct Anchor {
    /// Its record (the pose relative to its reference keyframe, so it
    /// follows what mapping and loop closing do to the keyframe).
    pub record: FrameRecord,
    /// Its telemetry sample (with an attitude).
    pub sample: TelemetrySample,
    /// The camera's velocity over the last vision frames, in the anchor's
    /// camera axes, map units per second (`None`: not known yet).
    pub velocity_cam: Option<Vector3<f64>>,
}

impl Anchor {
    /// Scale what is in map units by `k` (the map was scaled).
    pub fn scale(&mut self, k: f64) {
        self.record.cam_from_ref.translation.vector *= k;
        if let Some(v) = &mut self.velocity_cam {
            *v *= k;
        }
    }

    /// The anchor's `cam_from_world` in the map as it stands.
    pub fn cam_from_world(&self, map: &Map) -> Option<Isometry3<f64>> {
        map.keyframe_pose(self.record.reference)
            .map(|ref_pose| self.record.cam_from_ref * ref_pose)
    }
}

/// A frame's pose as the telemetry predicts it.
#[derive(Debug, Clone, Copy)]
pub(super) struct Prediction {
    /// The predicted `cam_from_world` with its uncertainty.
    pub prior: PosePrior,
    /// Whether the move came from the GNSS (else from the velocity).
    pub from_gnss: bool,
}

/// Predict the frame at `now` from `anchor` (see the module
/// documentation); `None` when the gap is too long, the anchor's keyframe
/// is gone, or neither the GNSS nor a velocity gives the move.
pub(super) fn predict(
    params: &AidParams,
    map: &Map,
    anchor: &Anchor,
    now: &TelemetrySample,
) -> Option<Prediction> {
    let dt = now.t - anchor.sample.t;
    if !(dt >= 0.0 && dt <= params.max_gap_s) {
        return None;
    }
    let anchor_pose = anchor.cam_from_world(map)?;
    let (q_now, q_anchor) = (now.ned_from_cam?, anchor.sample.ned_from_cam?);
    // cam_now ← cam_anchor from the two reported attitudes.
    let turn = q_now.inverse() * q_anchor;
    let rotation = turn * anchor_pose.rotation;
    let world_from_anchor = anchor_pose.inverse();
    let centre_anchor = world_from_anchor.translation.vector;
    let in_ned = map.mode() == MapMode::GpsAided;
    let (centre, from_gnss) = if in_ned && now.fix && anchor.sample.fix {
        (centre_anchor + (now.gps_ned - anchor.sample.gps_ned), true)
    } else if dt <= params.max_gap_without_gnss_s {
        let v = anchor.velocity_cam?;
        (centre_anchor + world_from_anchor.rotation * (v * dt), false)
    } else {
        return None;
    };
    let cam_from_world = Isometry3::from_parts(Translation3::from(-(rotation * centre)), rotation);
    let rot_sigma = (params.rotation_sigma_deg.powi(2)
        + params.rotation_walk_deg_per_sqrt_s.powi(2) * dt)
        .sqrt()
        .to_radians();
    // A position prior only in metres: in a vision-only map the velocity's
    // scale is the map's own and its error unknown.
    let pos_sigma = in_ned.then(|| {
        let walk = params.walk(now.h_acc.max(anchor.sample.h_acc));
        (params.position_sigma_m.powi(2) + walk.powi(2) * dt).sqrt()
    });
    Some(Prediction {
        prior: PosePrior::isotropic(cam_from_world, pos_sigma, rot_sigma),
        from_gnss,
    })
}

/// A new map put into an old one by the telemetry ([`place_new_map`]):
/// its scale came from the short GNSS baseline of its two initialisation
/// frames, so it is refit once its keyframes span a long one
/// ([`refit_placement`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Placement {
    /// The new map's first keyframe: it and every later keyframe of the
    /// map are the placed part (ids grow with time).
    pub first_kf: super::map::KeyFrameId,
}

/// Refit a placed part's scale about its first keyframe (its place and
/// rotation kept: the telemetry's placement fixed them, and a straight
/// flight would leave a rotation about its line free) to the GNSS
/// displacements of its keyframes from the first, once those with a fix
/// span
/// [`AidParams::refit_baseline_m`]: the part's keyframes and the points
/// only they observe move by the fitted similarity (counts as a
/// correction). `Ok(None)`: not yet (too short a baseline); `Err`: the
/// part cannot be refit (its reason; the placement is then left as it is).
pub(super) fn refit_placement(
    aid: &TelemetryAid,
    map: &mut Map,
    placement: &Placement,
) -> Result<Option<crate::lie::Sim3>, &'static str> {
    let into = map
        .map_of(placement.first_kf)
        .ok_or("the placed map's first keyframe is gone")?;
    let part: Vec<super::map::KeyFrameId> = map
        .keyframes()
        .filter(|k| k.id >= placement.first_kf && map.map_of(k.id) == Some(into))
        .map(|k| k.id)
        .collect();
    // (centre in the map, GNSS position) of the part's keyframes with a
    // fix; the first is the placed first keyframe's.
    let mut pairs: Vec<(Vector3<f64>, Vector3<f64>)> = Vec::new();
    for id in &part {
        let Some(k) = map.keyframe(*id) else { continue };
        let Some(s) = aid.sample(k.timestamp).filter(|s| s.fix) else {
            if *id == placement.first_kf {
                return Err("no GNSS fix at the placed map's first keyframe");
            }
            continue;
        };
        pairs.push((k.cam_from_world.inverse().translation.vector, s.gps_ned));
    }
    let spread = pairs
        .iter()
        .flat_map(|a| pairs.iter().map(move |b| (a.1 - b.1).norm()))
        .fold(0.0, f64::max);
    if pairs.len() < 4 || spread < aid.params.refit_baseline_m {
        return Ok(None);
    }
    // The scale about the first keyframe (where the placement put it):
    // the GNSS displacements from it against the map's.
    let (c0, g0) = pairs[0];
    let (num, den) = pairs.iter().fold((0.0, 0.0), |(num, den), (c, g)| {
        let d = c - c0;
        (num + d.dot(&(g - g0)), den + d.norm_squared())
    });
    if den <= 0.0 {
        return Err("the placed keyframes do not move");
    }
    let scale = num / den;
    if !(0.5..=2.0).contains(&scale) {
        return Err("the fitted scale is off by more than a factor of two");
    }
    let sim = crate::lie::Sim3::new(UnitQuaternion::identity(), c0 - c0 * scale, scale);
    let in_part: std::collections::HashSet<super::map::KeyFrameId> = part.iter().copied().collect();
    let (mut points, mut shared) = (Vec::new(), 0usize);
    for p in map.points() {
        let seen_in_part = p.observations.iter().any(|(k, _)| in_part.contains(k));
        if !seen_in_part {
            continue;
        }
        if p.observations.iter().all(|(k, _)| in_part.contains(k)) {
            points.push(p.id);
        } else {
            shared += 1;
        }
    }
    // Vision joined the part to the old map again (points seen from
    // both): it holds the two together better than the GNSS would.
    if shared * 10 > points.len() + shared {
        return Err("the placed keyframes see the old map's points again");
    }
    for id in &part {
        if let Some(k) = map.keyframe_mut(*id) {
            let world_from_cam = sim.transform_pose(&k.cam_from_world.inverse());
            k.cam_from_world = crate::lie::renormalized(world_from_cam.inverse());
        }
    }
    for pid in &points {
        if let Some(p) = map.point_mut(*pid) {
            p.position = sim.transform_point(&p.position);
        }
    }
    for pid in points {
        map.update_point_normal_and_depth(pid);
    }
    map.note_correction();
    Ok(Some(sim))
}

/// How far beyond the allowed distance a pose in a map in local NED puts
/// the camera from the GNSS position of `sample` (`None`: within it, or no
/// fix): [`AidParams::max_reloc_gnss_sigmas`] of the reported accuracy, at
/// least [`AidParams::min_reloc_distance_m`].
pub(super) fn gnss_disagreement(
    params: &AidParams,
    cam_from_world: &Isometry3<f64>,
    sample: &TelemetrySample,
) -> Option<f64> {
    if !sample.fix {
        return None;
    }
    let centre = cam_from_world.inverse().translation.vector;
    let off = (centre - sample.gps_ned).norm();
    let allowed = (params.max_reloc_gnss_sigmas * sample.h_acc.max(sample.v_acc))
        .max(params.min_reloc_distance_m);
    (off > allowed).then_some(off)
}

/// The similarity (old map's world ← new map's world) that puts a new map,
/// initialised from frames at `t1` (its first keyframe, pose `new1`) and
/// `t2` (`new2`), where the telemetry says those frames were relative to
/// the old map's `anchor`: the turn from the reported attitudes, the
/// moves and the scale from the GNSS displacements. Only for a map in
/// local NED (the GNSS displacement is then in map units), an anchor at
/// most [`AidParams::max_place_gap_s`] old, fixes at all three, and a
/// baseline between the two frames long enough for the scale
/// ([`DIRECTION_MIN_SIGMAS`] of its noise). The reason when not.
pub(super) fn place_new_map(
    aid: &TelemetryAid,
    map: &Map,
    anchor: &Anchor,
    (t1, new1): (f64, &Isometry3<f64>),
    (t2, new2): (f64, &Isometry3<f64>),
) -> Result<crate::lie::Sim3, &'static str> {
    let p = &aid.params;
    if map.mode() != MapMode::GpsAided {
        return Err("the map is not in local NED yet");
    }
    let age = t2 - anchor.sample.t;
    if !(age >= 0.0 && age <= p.max_place_gap_s) {
        return Err("the last vision pose of the old map is too old");
    }
    let old = anchor
        .cam_from_world(map)
        .ok_or("the anchor's keyframe is gone")?;
    let (s1, s2) = (
        aid.sample(t1).ok_or("no attitude at the first frame")?,
        aid.sample(t2).ok_or("no attitude at the second frame")?,
    );
    if !(s1.fix && s2.fix && anchor.sample.fix) {
        return Err("no GNSS fix");
    }
    let q_anchor = anchor
        .sample
        .ned_from_cam
        .ok_or("no attitude at the anchor")?;
    let centre_old = old.inverse().translation.vector;
    // Where the old map's world has each frame: turned and moved from the
    // anchor by the telemetry.
    let place = |s: &TelemetrySample| -> Option<(UnitQuaternion<f64>, Vector3<f64>)> {
        let turn = s.ned_from_cam?.inverse() * q_anchor;
        let cam_from_world = turn * old.rotation;
        Some((
            cam_from_world.inverse(),
            centre_old + (s.gps_ned - anchor.sample.gps_ned),
        ))
    };
    let ((w1, c1), (w2, c2)) = (
        place(&s1).ok_or("no attitude")?,
        place(&s2).ok_or("no attitude")?,
    );
    let baseline_old = (c2 - c1).norm();
    let (n1, n2) = (new1.inverse(), new2.inverse());
    let baseline_new = (n2.translation.vector - n1.translation.vector).norm();
    if baseline_old < aid.place_baseline_m(t1, t2) || baseline_new <= 0.0 {
        return Err("the GNSS baseline between the two frames is too short for the scale");
    }
    let scale = baseline_old / baseline_new;
    // old ← new rotation from each frame, halfway between the two.
    let r1 = w1 * new1.rotation;
    let r2 = w2 * new2.rotation;
    let rotation = r1.slerp(&r2, 0.5);
    let mid_new = (n1.translation.vector + n2.translation.vector) / 2.0;
    let mid_old = (c1 + c2) / 2.0;
    let translation = mid_old - rotation * (mid_new * scale);
    Ok(crate::lie::Sim3::new(rotation, translation, scale))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    use super::*;
    use crate::slam::map::testing::map_with;
    use crate::slam::map::{KeyFrameId, MapMode};
    use crate::slam::priors::{TelemetryFeed, TelemetryLog};

    /// `ned ← cam` looking down and ahead (pitch `pitch_deg`) on heading
    /// `yaw_deg`, at `centre`.
    fn camera(yaw_deg: f64, pitch_deg: f64, centre: Vector3<f64>) -> Isometry3<f64> {
        let q = TelemetrySample::camera_attitude(
            0.0,
            0.0,
            yaw_deg.to_radians(),
            pitch_deg.to_radians(),
            0.0,
        );
        Isometry3::from_parts(Translation3::from(centre), q)
    }

    /// The sample the telemetry reports for a camera at `ned_from_cam`,
    /// with a slow error common to every sample: 2 degrees of heading and
    /// a GNSS bias of 1.5 m.
    fn reported(t: f64, ned_from_cam: &Isometry3<f64>, fix: bool) -> TelemetrySample {
        let heading_error = UnitQuaternion::from_euler_angles(0.0, 0.0, 2f64.to_radians());
        TelemetrySample {
            t,
            fix,
            gps_ned: ned_from_cam.translation.vector + Vector3::new(1.5, -1.0, 0.5),
            h_acc: 1.3,
            v_acc: 0.8,
            baro_alt: None,
            ned_from_cam: Some(heading_error * ned_from_cam.rotation),
        }
    }

    fn aid(samples: Vec<TelemetrySample>) -> TelemetryAid {
        TelemetryAid::new(TelemetryFeed::fixed(TelemetryLog::new(samples)))
    }

    /// An anchor on keyframe 1 of a small map in local NED, the camera
    /// truly at `ned_from_cam`.
    fn anchor_at(map: &Map, ned_from_cam: &Isometry3<f64>, sample: TelemetrySample) -> Anchor {
        let kf_pose = map.keyframe_pose(KeyFrameId(1)).unwrap();
        Anchor {
            record: FrameRecord {
                index: 10,
                timestamp: sample.t,
                reference: KeyFrameId(1),
                cam_from_ref: ned_from_cam.inverse() * kf_pose.inverse(),
                source: PoseSource::Vision,
            },
            sample,
            velocity_cam: None,
        }
    }

    /// In a map in local NED the prediction is the camera's true pose: the
    /// heading error and the GNSS bias common to the anchor and the frame
    /// cancel; its prior's sigmas grow with the gap; beyond the longest gap
    /// there is none.
    #[test]
    fn the_telemetry_predicts_a_frame_from_its_anchor_whatever_its_slow_errors() {
        let mut map = map_with(2, 5);
        map.set_mode(MapMode::GpsAided);
        let at_anchor = camera(30.0, -60.0, Vector3::new(10.0, 5.0, -30.0));
        let now = camera(41.0, -57.0, Vector3::new(14.0, 9.0, -31.0));
        let anchor = anchor_at(&map, &at_anchor, reported(20.0, &at_anchor, true));
        let params = AidParams::default();
        let p = predict(&params, &map, &anchor, &reported(22.0, &now, true)).unwrap();
        assert!(p.from_gnss);
        let predicted = p.prior.cam_from_world.inverse();
        assert!((predicted.translation.vector - now.translation.vector).norm() < 1e-9);
        assert!(predicted.rotation.angle_to(&now.rotation) < 1e-9);
        // Sigmas 2 s after the anchor: sqrt(0.1² + 0.3²·2) degrees; the
        // receiver reports 1.3 m, so its bias walks 1.3·sqrt(2/120 s) per
        // root second: sqrt(0.05² + 1.3²·(2/120)·2) m.
        let w = p.prior.information;
        let rot_sigma = (1.0 / w[(3, 3)]).sqrt().to_degrees();
        assert!((rot_sigma - (0.01f64 + 0.09 * 2.0).sqrt()).abs() < 1e-9);
        let pos_sigma = (1.0 / w[(0, 0)]).sqrt();
        let expected = (0.0025f64 + 1.69 * (2.0 / 120.0) * 2.0).sqrt();
        assert!((pos_sigma - expected).abs() < 1e-9, "{pos_sigma}");
        // Past the longest gap: no prediction.
        assert!(predict(&params, &map, &anchor, &reported(30.5, &now, true)).is_none());
        // No fix: the velocity carries the move, and only briefly.
        let no_fix = reported(22.0, &now, false);
        assert!(
            predict(&params, &map, &anchor, &no_fix).is_none(),
            "no velocity yet"
        );
        let mut moving = anchor;
        // 2 m/s along the anchor camera's forward axis.
        moving.velocity_cam = Some(Vector3::new(0.0, 0.0, 2.0));
        let soon = reported(20.5, &now, false);
        let p = predict(&params, &map, &moving, &soon).unwrap();
        assert!(!p.from_gnss);
        let moved =
            p.prior.cam_from_world.inverse().translation.vector - at_anchor.translation.vector;
        let expected = at_anchor.rotation * Vector3::new(0.0, 0.0, 1.0);
        assert!((moved - expected).norm() < 1e-9, "{moved}");
        let late = reported(21.5, &now, false);
        assert!(predict(&params, &map, &moving, &late).is_none());
    }

    /// A map not in local NED gets no position prior (its scale is its
    /// own): only the turn is held.
    #[test]
    fn a_vision_only_map_gets_a_turn_prior_and_no_position_prior() {
        let map = map_with(2, 5);
        let at_anchor = camera(30.0, -60.0, Vector3::new(10.0, 5.0, -30.0));
        let now = camera(35.0, -60.0, Vector3::new(10.5, 5.3, -30.0));
        let mut anchor = anchor_at(&map, &at_anchor, reported(20.0, &at_anchor, true));
        anchor.velocity_cam = Some(Vector3::zeros());
        let p = predict(
            &AidParams::default(),
            &map,
            &anchor,
            &reported(20.2, &now, true),
        )
        .unwrap();
        assert!(!p.from_gnss);
        let w = p.prior.information;
        assert_eq!(w.fixed_view::<3, 3>(0, 0).norm(), 0.0);
        assert!(w[(3, 3)] > 0.0);
        let predicted = p.prior.cam_from_world.inverse();
        assert!(predicted.rotation.angle_to(&now.rotation) < 1e-9);
    }

    /// The reported motion between two frames: the turn exactly (the slow
    /// error cancels), the direction of travel in the first camera's axes
    /// once the displacement is beyond the receiver's noise.
    #[test]
    fn relative_motion_gives_the_turn_and_the_direction_beyond_the_noise() {
        let a = camera(10.0, -70.0, Vector3::new(0.0, 0.0, -30.0));
        let b = camera(13.0, -69.0, Vector3::new(2.0, 1.0, -30.0));
        let near = camera(13.0, -69.0, Vector3::new(0.1, 0.05, -30.0));
        let aid = aid(vec![
            reported(0.0, &a, true),
            reported(1.0, &b, true),
            reported(2.0, &near, true),
        ]);
        let m = aid.relative_motion(0.0, 1.0).unwrap();
        let truth = b.inverse() * a;
        assert!(m.rotation.angle_to(&truth.rotation) < 1e-9);
        // The direction is turned into the camera's axes by the reported
        // attitude: off by its heading error (2 degrees), within its sigma.
        let dir = m.direction.unwrap();
        let true_dir = (a.inverse() * b).translation.vector.normalize();
        let off = dir.angle(&true_dir);
        assert!(
            off.to_degrees() < 2.0 + 1e-9 && off < m.direction_sigma,
            "{off}"
        );
        assert!((aid.gnss_displacement(0.0, 1.0).unwrap() - 5f64.sqrt()).abs() < 1e-9);
        // 0.11 m in 2 s: within 4 sigmas of the displacement's noise.
        assert!(aid.relative_motion(0.0, 2.0).unwrap().direction.is_none());
    }

    /// A new map, in its own frame and scale, is put where the telemetry
    /// says its two frames were: the similarity recovered exactly with
    /// exact relative telemetry; refused before the map is in NED, over a
    /// short baseline, or long after the anchor.
    #[test]
    fn a_new_map_is_put_where_the_telemetry_says_its_frames_were() {
        let mut map = map_with(2, 5);
        map.set_mode(MapMode::GpsAided);
        let at_anchor = camera(30.0, -60.0, Vector3::new(10.0, 5.0, -30.0));
        let f1 = camera(50.0, -55.0, Vector3::new(30.0, 20.0, -32.0));
        let f2 = camera(52.0, -54.0, Vector3::new(33.5, 22.0, -32.2));
        let aid = aid(vec![
            reported(10.0, &at_anchor, true),
            reported(20.0, &f1, true),
            reported(20.6, &f2, true),
        ]);
        let anchor = anchor_at(&map, &at_anchor, aid.sample(10.0).unwrap());
        // The new map's frame: f1 at the origin, lengths in units of 7 m.
        let new_from_ned = |p: &Isometry3<f64>| {
            let rel = f1.inverse() * p;
            let mut r = rel;
            r.translation.vector /= 7.0;
            r.inverse()
        };
        let (n1, n2) = (new_from_ned(&f1), new_from_ned(&f2));
        let s = place_new_map(&aid, &map, &anchor, (20.0, &n1), (20.6, &n2)).unwrap();
        assert!((s.scale - 7.0).abs() < 1e-9, "{}", s.scale);
        for (truth, new) in [(&f1, &n1), (&f2, &n2)] {
            let placed = s.transform_pose(&new.inverse());
            assert!((placed.translation.vector - truth.translation.vector).norm() < 1e-9);
            assert!(placed.rotation.angle_to(&truth.rotation) < 1e-9);
        }
        // Refusals.
        let mut vision_only = map.clone();
        vision_only.set_mode(MapMode::VisionOnly);
        assert!(place_new_map(&aid, &vision_only, &anchor, (20.0, &n1), (20.6, &n2)).is_err());
        let short = aid.place_baseline_m(20.0, 20.6) * 0.9;
        let f2_short = camera(52.0, -54.0, Vector3::new(30.0 + short, 20.0, -32.0));
        let aid_short = super::tests::aid(vec![
            reported(10.0, &at_anchor, true),
            reported(20.0, &f1, true),
            reported(20.6, &f2_short, true),
        ]);
        let why = place_new_map(&aid_short, &map, &anchor, (20.0, &n1), (20.6, &n2)).unwrap_err();
        assert!(why.contains("baseline"), "{why}");
        let mut old = anchor;
        old.sample.t = 20.6 - 61.0;
        let why = place_new_map(&aid, &map, &old, (20.0, &n1), (20.6, &n2)).unwrap_err();
        assert!(why.contains("too old"), "{why}");
    }

    /// A placed part whose keyframes are 20 m apart where the GNSS says 22
    /// (a 10 % scale error from a short initial baseline) is scaled by 1.1
    /// about its first keyframe, its points with it; not before its
    /// keyframes span the baseline, and not when vision already joined it
    /// to the old map (points seen from both).
    #[test]
    fn a_placed_map_is_rescaled_to_the_gnss_over_a_long_baseline() {
        let mut map = map_with(6, 5);
        // Keyframes 20 m apart along north (timestamps 0, 0.1, ... 0.5).
        map.apply_sim3(&crate::lie::Sim3::new(
            UnitQuaternion::identity(),
            Vector3::zeros(),
            200.0,
        ));
        map.set_mode(MapMode::GpsAided);
        let samples = (0..6)
            .map(|i| {
                let at = camera(0.0, -90.0, Vector3::new(22.0 * i as f64, 0.0, -30.0));
                reported(i as f64 * 0.1, &at, true)
            })
            .collect();
        let aid = aid(samples);
        let point = map.points().next().unwrap().id;
        let before = map.point(point).unwrap().position;
        let whole = Placement {
            first_kf: KeyFrameId(0),
        };
        let long = TelemetryAid {
            params: AidParams {
                refit_baseline_m: 200.0,
                ..AidParams::default()
            },
            ..aid.clone()
        };
        assert_eq!(refit_placement(&long, &mut map.clone(), &whole), Ok(None));
        let shared = Placement {
            first_kf: KeyFrameId(2),
        };
        let why = refit_placement(&aid, &mut map.clone(), &shared).unwrap_err();
        assert!(why.contains("old map"), "{why}");
        let corrections = map.corrections();
        let sim = refit_placement(&aid, &mut map, &whole).unwrap().unwrap();
        assert!((sim.scale - 1.1).abs() < 1e-9, "{}", sim.scale);
        for (i, k) in map.keyframes().enumerate() {
            let c = k.center();
            assert!(
                (c - Vector3::new(22.0 * i as f64, 0.0, 0.0)).norm() < 1e-6,
                "{c}"
            );
        }
        let after = map.point(point).unwrap().position;
        assert!((after.coords - before.coords * 1.1).norm() < 1e-9);
        assert_eq!(map.corrections(), corrections + 1);
    }

    /// A pose 48 m from where the GNSS puts the camera (a look-alike place)
    /// disagrees; one within five reported sigmas does not.
    #[test]
    fn a_pose_far_from_the_gnss_disagrees() {
        let truth = camera(30.0, -60.0, Vector3::new(10.0, 5.0, -30.0));
        let s = reported(0.0, &truth, true);
        let params = AidParams::default();
        assert!(gnss_disagreement(&params, &truth.inverse(), &s).is_none());
        let far = camera(30.0, -60.0, Vector3::new(44.0, 39.0, -30.0));
        let off = gnss_disagreement(&params, &far.inverse(), &s).unwrap();
        let expected = Vector3::new(32.5f64, 35.0, -0.5).norm();
        assert!((off - expected).abs() < 1e-9, "{off}");
        let no_fix = reported(0.0, &truth, false);
        assert!(gnss_disagreement(&params, &far.inverse(), &no_fix).is_none());
    }

    #[test]
    fn aid_params_check_names_the_bad_number() {
        assert!(AidParams::default().check().is_ok());
        let bad = AidParams {
            max_gap_s: -1.0,
            ..AidParams::default()
        };
        assert!(bad.check().unwrap_err().contains("max_gap_s"));
        let bad = AidParams {
            min_inliers: 2,
            ..AidParams::default()
        };
        assert!(bad.check().unwrap_err().contains("min_inliers"));
    }
}
