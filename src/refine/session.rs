//! One shot's refinement loop as a state machine the daemon (or the
//! scenario) drives: it is told the vehicle has arrived with a steady view
//! and given the live frame; it measures the shot error, decides, localises
//! the live frame and returns the corrected target to upload, or stops.
//! Its rounds are the record the API shows.

use std::collections::BTreeMap;

use image::GrayImage;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use super::measure::{LiveFrame, robust_mean};
use super::{ControllerParams, Correction, Decision, Params, Reachable, decide, shot_error};
use crate::angle::wrap180;
use crate::camera::Camera;
use crate::geo::{
    GeoAlignment, GeoTarget, Geodetic, GimbalAngles, LocalFrame, MountParams, VehicleState,
    convert_target, ned_from_cam,
};
use crate::mission::plan::{Fence, Home, Target};
use crate::shot::{Localization, LocalizeParams, localize};
use crate::slam::Map;
use crate::stats::finite_median;

/// What the loop needs from the rest of the daemon at an arrival.
#[derive(Debug, Clone, Copy)]
pub struct Context<'a> {
    /// The SLAM map (a snapshot).
    pub map: &'a Map,
    /// The map → NED alignment.
    pub alignment: &'a GeoAlignment,
    /// The local tangent plane at home.
    pub frame: &'a LocalFrame,
    /// The camera's mounting.
    pub mount: &'a MountParams,
    /// Home.
    pub home: &'a Home,
    /// The geofence every target must lie in.
    pub fence: &'a Fence,
    /// Localisation of the live frame.
    pub localize: &'a LocalizeParams,
}

/// A [`Context`]'s contents owned, for a driver that keeps them across
/// frames (a map snapshot copies the map, so one is taken per servo, not
/// per frame); [`World::ctx`] lends them.
#[derive(Debug, Clone)]
pub struct World {
    /// The SLAM map (a snapshot).
    pub map: Map,
    /// The map → NED alignment.
    pub alignment: GeoAlignment,
    /// The local tangent plane at home.
    pub frame: LocalFrame,
    /// The camera's mounting.
    pub mount: MountParams,
    /// Home.
    pub home: Home,
    /// The geofence every target must lie in.
    pub fence: Fence,
    /// Localisation of the live frame.
    pub localize: LocalizeParams,
}

impl World {
    /// The context borrowing this world.
    pub fn ctx(&self) -> Context<'_> {
        Context {
            map: &self.map,
            alignment: &self.alignment,
            frame: &self.frame,
            mount: &self.mount,
            home: &self.home,
            fence: &self.fence,
            localize: &self.localize,
        }
    }
}

/// One arrival: what was measured and what was done.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RoundRecord {
    /// 0 for the first flight, then one per correction.
    pub round: usize,
    /// The target flown.
    pub target: Target,
    /// Shot error, % of the image diagonal (None: no homography).
    pub shot_error_pct: Option<f64>,
    /// Shot error, pixels.
    pub shot_error_px: Option<f64>,
    /// Homography inliers (median over the frames).
    pub inliers: Option<usize>,
    /// Live frames measured.
    pub frames: usize,
    /// Frames with a shot error (the shot error is their median).
    pub frames_with_error: usize,
    /// Spread of one frame's shot error around the median (1.4826 MAD),
    /// % of the diagonal, when more than one frame had one.
    pub shot_error_spread_pct: Option<f64>,
    /// The shot error a camera exactly at the shot's pose would measure,
    /// % of the diagonal, when known ([`Session::with_reachable`]).
    pub floor_pct: Option<f64>,
    /// How much the framing would still change if the camera moved from
    /// the live frame's localised pose to the shot's pose (corner error,
    /// % of the diagonal, over the shot's map points): what the loop can
    /// still remove. Computed for shots whose floor is above the threshold.
    pub pose_framing_pct: Option<f64>,
    /// The decision.
    pub decision: Decision,
    /// The live frame's pose in the map, when it was localised.
    pub live_map_position: Option<[f64; 3]>,
    /// The live offset measured and filtered, when the loop corrected.
    pub offset: Option<OffsetRecord>,
    /// The correction uploaded next.
    pub correction: Option<Correction>,
    /// Why the loop could not go on, or why the shot error is missing.
    pub note: Option<String>,
    /// What the driver saw besides the frame (telemetry, timing), when it
    /// told ([`Session::observe`]).
    pub observed: Option<Observation>,
}

/// The live camera's offset at one arrival, per axis (north, east, down
/// in metres: the vehicle position the live camera implies through the
/// georeference minus the reported one; heading and gimbal pitch in
/// degrees: the live ones minus the commanded).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OffsetRecord {
    /// Frames localised (and converted) for it.
    pub frames_localised: usize,
    /// Robust mean over the frames.
    pub measured: [f64; 5],
    /// Its standard deviation (the measurement's noise).
    pub sigma: [f64; 5],
    /// The share of the new measurement taken (1 on the first round
    /// with the default gain).
    pub gain: [f64; 5],
    /// The filtered offset the correction compensates.
    pub estimate: [f64; 5],
    /// Axes whose change was within `gate_sigmas` of the noise and left as
    /// they were.
    pub gated: [bool; 5],
}

/// The filtered offset between rounds.
#[derive(Debug, Clone, Copy, PartialEq)]
struct OffsetEstimate {
    value: [f64; 5],
    var: [f64; 5],
    t_s: f64,
    /// The desired vehicle state (north, east, down, heading, gimbal
    /// pitch) through that round's alignment: the offset is measured
    /// through the alignment, so when a refit moves it, the estimate moves
    /// with it by the change at the desired pose.
    desired: [f64; 5],
}

/// What the driver of the loop saw at an arrival besides the live frame:
/// the vehicle's own report and the frame's timing, for the record (the
/// session does not use it).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Observation {
    /// The measured frame's capture time, unix seconds, when the source
    /// sent it.
    pub frame_capture_unix: Option<f64>,
    /// The measured frame's capture time minus the arrival time, seconds
    /// (negative: captured before the view was judged steady).
    pub capture_after_arrival_s: Option<f64>,
    /// The measured frame's receipt minus its capture, seconds.
    pub frame_latency_s: Option<f64>,
    /// The reported vehicle position minus the target's, local NED metres.
    pub vehicle_offset_ned_m: Option<[f64; 3]>,
    /// The reported heading minus the target's, degrees.
    pub yaw_error_deg: Option<f64>,
    /// The reported gimbal pitch minus the target's, degrees.
    pub gimbal_pitch_error_deg: Option<f64>,
    /// The reported 3-D speed, m/s.
    pub speed_m_s: Option<f64>,
    /// Age of the position report when the frame was taken, seconds.
    pub position_age_s: Option<f64>,
}

/// How the loop ended.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(rename_all = "snake_case", tag = "stop", content = "reason")]
pub enum Stop {
    /// The shot error is under the threshold.
    Converged,
    /// The round budget is spent.
    MaxRounds,
    /// The shot error cannot go lower: it is the shot's own floor (above
    /// the threshold) and the live view is within the threshold of the
    /// best framing a camera can reach.
    AtFloor,
    /// The shot error is above the threshold but the correction is within
    /// the measurement's own noise on every axis: the loop cannot tell a
    /// better pose.
    WithinNoise,
    /// The live frame could not be localised.
    LiveNotLocalised(String),
    /// The correction failed its checks (geofence, altitude, gimbal) or
    /// the georeference refused it.
    CorrectionRefused(String),
}

impl Stop {
    /// A short name (`converged`, `max_rounds`, `at_floor`,
    /// `within_noise`, `live_not_localised`, `correction_refused`).
    pub fn name(&self) -> &'static str {
        match self {
            Stop::Converged => "converged",
            Stop::MaxRounds => "max_rounds",
            Stop::AtFloor => "at_floor",
            Stop::WithinNoise => "within_noise",
            Stop::LiveNotLocalised(_) => "live_not_localised",
            Stop::CorrectionRefused(_) => "correction_refused",
        }
    }
}

/// A flight back to an earlier round's view.
struct Back {
    /// The round.
    round: usize,
    /// Its live camera pose (map frame).
    view: Isometry3<f64>,
    /// Why the loop flies back.
    note: String,
    /// How the loop ends there.
    stop: Stop,
}

/// The decision recorded with a loop ending `stop` after a return.
fn stop_decision(stop: &Stop) -> Decision {
    if *stop == Stop::MaxRounds {
        Decision::MaxRounds
    } else {
        Decision::AtFloor
    }
}

/// The loop stalled near its floor ([`Session::stalled_near_floor`]).
enum Stalled {
    /// This view is the best measured: stop here (the note says why).
    Here(String),
    /// An earlier round (its number and live camera pose) measured
    /// better: fly back to that view.
    BackTo(usize, Isometry3<f64>, String),
}

/// What to do after an arrival.
#[derive(Debug, Clone, PartialEq)]
pub enum Step {
    /// Plan and upload this target, fly, and call [`Session::on_arrival`] again.
    Upload(Target),
    /// The loop is over.
    Done(Stop),
}

/// One shot's loop.
#[derive(Debug, Clone)]
pub struct Session {
    desired: GrayImage,
    mask: Option<GrayImage>,
    map_from_desired: Isometry3<f64>,
    target: Target,
    rounds: Vec<RoundRecord>,
    stop: Option<Stop>,
    params: Params,
    reachable: Option<Reachable>,
    offset: Option<OffsetEstimate>,
    /// Flying back to the best round's view (its round number) and how
    /// the next arrival ends the loop there: `at_floor` (stalled near the
    /// floor) or `max_rounds` (the budget spent on a view worse than the
    /// best).
    returning: Option<(usize, Stop)>,
    /// Each round's live camera pose (map frame), where its frames were
    /// localised: the view a return to that round flies back to.
    views: BTreeMap<usize, Isometry3<f64>>,
    /// Re-targets flown on the approaches so far ([`Session::retarget`]).
    retargets: Vec<super::Shift>,
}

impl Session {
    /// A loop for the desired shot (image, mask of its valid pixels, pose
    /// in the map) whose first target is being flown.
    pub fn new(
        desired: GrayImage,
        mask: Option<GrayImage>,
        map_from_desired: Isometry3<f64>,
        first_target: Target,
        params: Params,
    ) -> Self {
        Self {
            desired,
            mask,
            map_from_desired,
            target: first_target,
            rounds: Vec::new(),
            stop: None,
            params,
            reachable: None,
            offset: None,
            returning: None,
            views: BTreeMap::new(),
            retargets: Vec::new(),
        }
    }

    /// The same loop knowing the shot's reachable framing: it stops
    /// (`at_floor`) when the shot error is the shot's own floor, above the
    /// threshold, and the live view is within the threshold of the best
    /// framing a camera can reach.
    pub fn with_reachable(mut self, reachable: Reachable) -> Self {
        self.reachable = Some(reachable);
        self
    }

    /// The shot's reachable framing, when known.
    pub fn reachable(&self) -> Option<&Reachable> {
        self.reachable.as_ref()
    }

    /// The desired picture the live view is compared with.
    pub fn desired_picture(&self) -> &GrayImage {
        &self.desired
    }

    /// The desired picture's mask of valid pixels, when it has one.
    pub fn desired_mask(&self) -> Option<&GrayImage> {
        self.mask.as_ref()
    }

    /// This loop's parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// A servo toward this loop's shot from the setpoint being held
    /// (its desired picture, mask, pose and floor; this loop's parameters).
    pub fn servo(&self, holding: Target, params: super::ServoParams) -> super::Servo {
        super::Servo::new(
            self.desired.clone(),
            self.mask.clone(),
            self.map_from_desired,
            self.reachable.as_ref().map(|r| r.floor_pct),
            holding,
            self.params.clone(),
            params,
        )
    }

    /// The desired shot's camera pose in the map.
    pub fn map_from_desired(&self) -> &Isometry3<f64> {
        &self.map_from_desired
    }

    /// The target being flown.
    pub fn target(&self) -> &Target {
        &self.target
    }

    /// The target flown from now on, converted again on the approach with
    /// a refitted georeference ([`super::approach`]); `shift` is its move
    /// from the one flown until now. The next arrival's correction is
    /// measured from it.
    pub fn retarget(&mut self, target: Target, shift: super::Shift) {
        self.target = target;
        self.retargets.push(shift);
    }

    /// The re-targets flown on the approaches so far, in order.
    pub fn retargets(&self) -> &[super::Shift] {
        &self.retargets
    }

    /// The rounds so far.
    pub fn rounds(&self) -> &[RoundRecord] {
        &self.rounds
    }

    /// How the loop ended, once it has.
    pub fn stop(&self) -> Option<&Stop> {
        self.stop.as_ref()
    }

    /// The vehicle reached the target and the view is steady: measure the
    /// shot error over the live `frames` (taken a little apart after the
    /// arrival; their median decides), and when going on, localise each,
    /// combine the offsets of the live camera from where the vehicle
    /// reported itself (robust mean; the frames' spread is the
    /// measurement's noise), weigh them against what the earlier rounds
    /// measured and the drift since (`t_s`: the measurement's time,
    /// seconds on any steady clock), and correct the target. `camera`
    /// undistorts the shot-error keypoints.
    pub fn on_arrival(
        &mut self,
        frames: &[LiveFrame<'_>],
        t_s: f64,
        camera: Option<&Camera>,
        ctx: &Context<'_>,
    ) -> Step {
        if let Some(s) = &self.stop {
            return Step::Done(s.clone());
        }
        let round = self.rounds.len();
        let mut errors = Vec::new();
        let mut first_error = None;
        for f in frames {
            match shot_error(
                f.image,
                &self.desired,
                self.mask.as_ref(),
                camera,
                &self.params.error,
            ) {
                Ok(e) => errors.push(e),
                Err(e) => {
                    first_error.get_or_insert(e);
                }
            }
        }
        let pcts: Vec<f64> = errors.iter().map(|e| e.corner_error_pct).collect();
        let pct = finite_median(&pcts);
        let spread = finite_median(
            &pcts
                .iter()
                .map(|x| (x - pct.unwrap_or(0.0)).abs())
                .collect::<Vec<_>>(),
        )
        .filter(|_| pcts.len() > 1)
        .map(|m| 1.4826 * m);
        let threshold = self.params.controller.threshold_pct;
        let decision = decide(pct, round, &self.params.controller);
        let mut rec = RoundRecord {
            round,
            target: self.target,
            shot_error_pct: pct,
            shot_error_px: finite_median(
                &errors.iter().map(|e| e.corner_error_px).collect::<Vec<_>>(),
            ),
            inliers: finite_median(&errors.iter().map(|e| e.inliers as f64).collect::<Vec<_>>())
                .map(|x| x.round() as usize),
            frames: frames.len(),
            frames_with_error: errors.len(),
            shot_error_spread_pct: spread,
            floor_pct: self.reachable.as_ref().map(|r| r.floor_pct),
            pose_framing_pct: None,
            decision,
            live_map_position: None,
            offset: None,
            correction: None,
            note: match (&first_error, errors.is_empty()) {
                (Some(e), true) => Some(format!("shot error: {e}")),
                (None, true) => Some("no live frame".into()),
                _ => None,
            },
            observed: None,
        };
        if decision == Decision::Converged {
            return self.end(rec, Stop::Converged);
        }
        // A shot whose floor is above the threshold can stop short of it:
        // when the live camera stands where the vehicle can reproduce the
        // shot's pose (what the remaining pose error would still change in
        // the framing is under the threshold) and the shot error is the
        // floor there (within the threshold), no correction can lower it.
        let reachable_pose = self
            .reachable
            .as_ref()
            .and_then(|_| reproducible_pose(ctx, &self.map_from_desired));
        if let (Some(r), Some(pose)) = (self.reachable.as_mut(), reachable_pose.as_ref())
            && let Some((px, pct)) = r.floor_at(pose, &ctx.map.camera)
        {
            r.floor_px = px;
            r.floor_pct = pct;
            rec.floor_pct = Some(pct);
        }
        // Within a few tenths of the floor (or of the measurement's own
        // noise), a correction can gain no more than the measurement can
        // tell: the loop stops there, once the live frames are localised so
        // that the record says how far the camera stands from the shot's
        // pose. Under the floor it stops too: the floor is what a camera
        // at the shot's pose measures, so the view is already better than
        // the pose gives (50 field drags flying on from under the floor
        // toward the pose: 14 of 24 ended worse, 5 better, 39 rounds
        // against 27).
        let near_floor = match (self.reachable.as_ref(), pct) {
            (Some(r), Some(e)) => {
                let noise = median_noise_pct(spread, pcts.len());
                let margin = self.params.controller.at_floor_margin_pct.max(noise);
                (e - r.floor_pct <= margin).then(|| {
                    format!(
                        "{e:.2} % is within {margin:.2} % of the shot's floor {:.2} %: no correction can gain more than the measurement tells",
                        r.floor_pct
                    )
                })
            }
            _ => None,
        };
        let floor = self
            .reachable
            .as_ref()
            .filter(|r| r.floor_pct >= threshold)
            .zip(reachable_pose);
        // Every frame localised (those that are), with what the vehicle
        // reported when it was taken.
        let mut localised: Vec<(Isometry3<f64>, Option<Vector3<f64>>)> = Vec::new();
        let mut why_not: Option<String> = None;
        if floor.is_some()
            || near_floor.is_some()
            || matches!(decision, Decision::Correct | Decision::MaxRounds)
        {
            for f in frames {
                match localize(ctx.map, f.image, None, None, ctx.localize) {
                    Ok(Localization::Localized(p)) => {
                        localised.push((p.world_from_cam, f.reported_ned_m));
                    }
                    Ok(Localization::NotLocalized { reason }) => {
                        why_not.get_or_insert(reason.to_string());
                    }
                    Err(e) => {
                        why_not.get_or_insert(e.to_string());
                    }
                }
            }
        }
        // The frame nearest the frames' median position stands for them
        // where one pose is needed (the floor, the record).
        let central = central_pose(&localised);
        if let Some(c) = &central {
            rec.live_map_position = Some(c.translation.vector.into());
        }
        if let (Some((r, pose)), Some(live)) = (floor, &central) {
            let framing = r.framing_change_pct(live, &pose, &ctx.map.camera);
            rec.pose_framing_pct = framing;
            if framing.is_some_and(|f| f < threshold)
                && pct.is_some_and(|e| e <= r.floor_pct + threshold)
            {
                rec.decision = Decision::AtFloor;
                return self.end(rec, Stop::AtFloor);
            }
        }
        if let Some(note) = near_floor {
            rec.decision = Decision::AtFloor;
            rec.note = Some(note);
            return self.end(rec, Stop::AtFloor);
        }
        if let Some((best, stop)) = self.returning.take() {
            let why = if stop == Stop::MaxRounds {
                "with the rounds spent"
            } else {
                "near the floor"
            };
            rec.decision = stop_decision(&stop);
            rec.note = Some(format!(
                "back at round {best}'s view, the best measured {why}"
            ));
            return self.end(rec, stop);
        }
        if let Some(stall) = self.stalled_near_floor(pct) {
            match stall {
                Stalled::Here(note) => {
                    rec.decision = Decision::AtFloor;
                    rec.note = Some(note);
                    return self.end(rec, Stop::AtFloor);
                }
                Stalled::BackTo(best, goal, note) => {
                    let back = Back {
                        round: best,
                        view: goal,
                        note,
                        stop: Stop::AtFloor,
                    };
                    return self.back_to(rec, back, &localised, t_s, round, ctx);
                }
            }
        }
        if let Some(c) = central {
            self.views.insert(round, c);
        }
        if decision == Decision::MaxRounds {
            // The budget is spent: the loop ends on the best view it
            // measured, not on a last one that measured worse (a field
            // drag flew 14.8, 14.7, 16.8, 17.5 and ended at 19.5 %).
            let noise = median_noise_pct(spread, pcts.len());
            let margin = self.params.controller.at_floor_margin_pct.max(noise);
            if let Some((best, view, note)) = self.worse_than_best(pct, margin) {
                let back = Back {
                    round: best,
                    view,
                    note,
                    stop: Stop::MaxRounds,
                };
                return self.back_to(rec, back, &localised, t_s, round, ctx);
            }
            return self.end(rec, Stop::MaxRounds);
        }
        if localised.is_empty() {
            let why = why_not.unwrap_or_else(|| "no live frame".to_string());
            rec.note = Some(format!("live frame not localised: {why}"));
            return self.end(rec, Stop::LiveNotLocalised(why));
        }
        match self.correct_from(&localised, t_s, round, ctx) {
            Ok((c, offset)) => {
                let gated = offset.gated.iter().all(|&g| g);
                rec.offset = Some(offset);
                if gated {
                    rec.decision = Decision::WithinNoise;
                    rec.note = Some(
                        "the correction is within the measurement's noise on every axis".into(),
                    );
                    return self.end(rec, Stop::WithinNoise);
                }
                self.target = c.target;
                rec.correction = Some(c);
                self.rounds.push(rec);
                Step::Upload(self.target)
            }
            Err(e) => {
                rec.note = Some(format!("correction refused: {e}"));
                self.end(rec, Stop::CorrectionRefused(e.to_string()))
            }
        }
    }

    /// The correction from the localised live frames: per axis (north,
    /// east, down, heading, gimbal pitch) the offset of the live vehicle
    /// state (through the georeference) from the reported position (or the
    /// target flown) and the commanded angles, robustly averaged, filtered
    /// against the earlier rounds', and the target that puts the camera at
    /// the desired pose given that offset, with the axes whose change is
    /// within the measurement's noise left as they are.
    fn correct_from(
        &mut self,
        localised: &[(Isometry3<f64>, Option<Vector3<f64>>)],
        t_s: f64,
        round: usize,
        ctx: &Context<'_>,
    ) -> Result<(Correction, OffsetRecord), super::RefineError> {
        let goal = self.map_from_desired;
        self.correct_toward(&goal, localised, t_s, round, ctx)
    }

    /// [`Self::correct_from`] toward the camera pose `goal` (map frame)
    /// instead of the shot's.
    fn correct_toward(
        &mut self,
        goal: &Isometry3<f64>,
        localised: &[(Isometry3<f64>, Option<Vector3<f64>>)],
        t_s: f64,
        round: usize,
        ctx: &Context<'_>,
    ) -> Result<(Correction, OffsetRecord), super::RefineError> {
        let ctrl = &self.params.controller;
        let m = &self.params.measure;
        let desired = convert_target(ctx.alignment, goal, ctx.frame, ctx.mount)
            .map_err(super::RefineError::Geo)?;
        let current = self.target;
        let current_ned = ctx.frame.geodetic_to_ned(&Geodetic {
            lat_deg: current.lat_deg,
            lon_deg: current.lon_deg,
            alt_m: ctx.home.alt_amsl_m + current.alt_m,
        });
        let mut per_axis: [Vec<f64>; 5] = Default::default();
        let mut last_err = None;
        for (pose, reported) in localised {
            let live = match convert_target(ctx.alignment, pose, ctx.frame, ctx.mount) {
                Ok(l) => l,
                Err(e) => {
                    last_err = Some(e);
                    continue;
                }
            };
            let base = reported
                .filter(|r| r.iter().all(|x| x.is_finite()))
                .unwrap_or(current_ned);
            let d = live.p_ned_vehicle - base;
            per_axis[0].push(d.x);
            per_axis[1].push(d.y);
            per_axis[2].push(d.z);
            per_axis[3].push(wrap180(live.yaw_deg - current.yaw_deg));
            per_axis[4].push(live.gimbal_pitch_deg - current.gimbal_pitch_deg);
        }
        let mut measured = [0.0; 5];
        let mut sigma = [0.0; 5];
        for (i, v) in per_axis.iter().enumerate() {
            let floor = if i < 3 {
                m.min_position_sigma_m
            } else {
                m.min_angle_sigma_deg
            };
            let Some(r) = robust_mean(v, m.outlier_sigmas, floor) else {
                return Err(match last_err {
                    Some(e) => super::RefineError::Geo(e),
                    None => super::RefineError::NonFinite {
                        what: "live offset",
                    },
                });
            };
            measured[i] = r.mean;
            sigma[i] = r.sigma;
        }
        // Filter: the first correction takes `gain` of the measured offset
        // (the first error is mostly systematic); later ones weigh the new
        // measurement against the estimate, whose variance grew with the
        // drift since the last measurement.
        let desired_state = [
            desired.p_ned_vehicle.x,
            desired.p_ned_vehicle.y,
            desired.p_ned_vehicle.z,
            desired.yaw_deg,
            desired.gimbal_pitch_deg,
        ];
        let mut gain = [ctrl.gain; 5];
        let (estimate, variance) = match (&self.offset, round) {
            (Some(o), r) if r > 0 => {
                let dt = (t_s - o.t_s).max(0.0);
                let dt = if dt.is_finite() { dt } else { 0.0 };
                let mut est = o.value;
                let mut var = o.var;
                // A refit of the georeference between the rounds moves
                // every converted state, the live ones measured now as
                // well as the desired: the last estimate is carried into
                // the new alignment by the change it makes at the desired
                // pose (zero when the alignment stayed). Without it, the
                // share of the old estimate the filter keeps would be an
                // error of that share of the refit's change.
                for i in 0..5 {
                    let moved = desired_state[i] - o.desired[i];
                    est[i] += if i == 3 { wrap180(moved) } else { moved };
                }
                for i in 0..5 {
                    let q = if i < 3 {
                        ctrl.position_drift_m2_per_s
                    } else {
                        ctrl.angle_drift_deg2_per_s
                    };
                    let p = var[i] + q.max(0.0) * dt;
                    let r = sigma[i] * sigma[i];
                    let k = if p + r > 0.0 { p / (p + r) } else { 1.0 };
                    gain[i] = k.min(ctrl.later_gain);
                    est[i] += gain[i] * (measured[i] - est[i]);
                    var[i] = (1.0 - gain[i]).powi(2) * p + gain[i].powi(2) * r;
                }
                (est, var)
            }
            _ => {
                let mut est = [0.0; 5];
                let mut var = [0.0; 5];
                for i in 0..5 {
                    est[i] = gain[i] * measured[i];
                    var[i] = (sigma[i] * sigma[i]).max(((1.0 - gain[i]) * measured[i]).powi(2));
                }
                (est, var)
            }
        };
        // The command: the desired vehicle state minus the offset; an axis
        // whose change is within the measurement's noise stays.
        let mut step = [
            desired.p_ned_vehicle.x - estimate[0] - current_ned.x,
            desired.p_ned_vehicle.y - estimate[1] - current_ned.y,
            desired.p_ned_vehicle.z - estimate[2] - current_ned.z,
            wrap180(desired.yaw_deg - estimate[3] - current.yaw_deg),
            desired.gimbal_pitch_deg - estimate[4] - current.gimbal_pitch_deg,
        ];
        let mut gated = [false; 5];
        for i in 0..5 {
            if step[i].abs() < ctrl.gate_sigmas * sigma[i] {
                step[i] = 0.0;
                gated[i] = true;
            }
        }
        // As a live state whose difference from the desired is the step:
        // the controller's limits and checks apply as to every correction.
        let live = GeoTarget {
            p_ned_vehicle: desired.p_ned_vehicle - Vector3::new(step[0], step[1], step[2]),
            yaw_deg: desired.yaw_deg - step[3],
            gimbal_pitch_deg: desired.gimbal_pitch_deg - step[4],
            ..desired
        };
        let unit = ControllerParams { gain: 1.0, ..*ctrl };
        let c = super::correct_targets(
            &desired, &live, &current, ctx.home, ctx.fence, ctx.mount, &unit,
        )?;
        self.offset = Some(OffsetEstimate {
            value: estimate,
            var: variance,
            t_s,
            desired: desired_state,
        });
        Ok((
            c,
            OffsetRecord {
                frames_localised: per_axis[0].len(),
                measured,
                sigma,
                gain,
                estimate,
                gated,
            },
        ))
    }

    /// Attaches what the driver saw at the last arrival to its round.
    pub fn observe(&mut self, observed: Observation) {
        if let Some(r) = self.rounds.last_mut() {
            r.observed = Some(observed);
        }
    }

    /// Adds `note` to the last round's note (after what the round itself
    /// noted): what the driver did differently in that round.
    pub fn annotate(&mut self, note: &str) {
        if let Some(r) = self.rounds.last_mut() {
            r.note = Some(match r.note.take() {
                Some(n) if !n.is_empty() => format!("{n}; {note}"),
                _ => note.to_owned(),
            });
        }
    }

    /// Whether the loop ends near its floor after a correction: the error
    /// `pct` within [`ControllerParams::stall_band_pct`] of the floor, for
    /// a shot whose floor is not more than the margin under the threshold
    /// (one that can converge flies on).
    /// Stop here when the correction gained, or when this view is within
    /// [`ControllerParams::at_floor_margin_pct`] of the best measured;
    /// else fly back to the best round's view.
    fn stalled_near_floor(&self, pct: Option<f64>) -> Option<Stalled> {
        let ctrl = &self.params.controller;
        let e = pct?;
        let floor = self.reachable.as_ref()?.floor_pct;
        // Only for a shot that cannot converge: one whose floor lies more
        // than the margin under the threshold flies on toward it.
        if e - floor > ctrl.stall_band_pct || floor + ctrl.at_floor_margin_pct < ctrl.threshold_pct
        {
            return None;
        }
        let (round, best_pct) = self
            .rounds
            .iter()
            .filter_map(|r| r.shot_error_pct.map(|b| (r.round, b)))
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        let margin = ctrl.at_floor_margin_pct;
        let over = e - floor;
        if e < best_pct - margin {
            // A correction that gained and landed near the floor: the
            // floor estimate sits a few tenths under what the vehicle
            // reaches, and the GNSS drift between two looks moves the view
            // by as much, so a further round gambles the gain (a browser
            // run flew on from 3.13 % and ended at 4.17 %).
            return Some(Stalled::Here(format!(
                "{e:.2} %, {over:.2} % over the floor {floor:.2} %, gained {:.2} % on round {round}'s {best_pct:.2} %: near the floor a further round would chase the drift between looks",
                best_pct - e
            )));
        }
        match self.views.get(&round) {
            Some(pose) if e > best_pct + margin => Some(Stalled::BackTo(
                round,
                *pose,
                format!(
                    "{e:.2} %, {over:.2} % over the floor {floor:.2} %, is worse than round {round}'s {best_pct:.2} %: back to that round's view"
                ),
            )),
            _ => Some(Stalled::Here(format!(
                "{e:.2} %, {over:.2} % over the floor {floor:.2} %, gained less than {margin:.2} % on round {round}'s {best_pct:.2} %: the loop is at what the measurement can tell"
            ))),
        }
    }

    /// Fly back to `back`'s round's view: its view, not its target (the
    /// GNSS bias has drifted since, so the same target puts the camera
    /// elsewhere), through the offset measured now; the loop ends
    /// `back.stop` on arriving there. Without a way back (the live frames
    /// not localised, or the way within the measurement's noise) it ends
    /// `back.stop` here and says why.
    fn back_to(
        &mut self,
        mut rec: RoundRecord,
        back: Back,
        localised: &[(Isometry3<f64>, Option<Vector3<f64>>)],
        t_s: f64,
        round: usize,
        ctx: &Context<'_>,
    ) -> Step {
        match self.correct_toward(&back.view, localised, t_s, round, ctx) {
            Ok((c, offset)) if !offset.gated.iter().all(|&g| g) => {
                rec.decision = Decision::ReturnToBest;
                rec.note = Some(back.note);
                rec.offset = Some(offset);
                self.target = c.target;
                rec.correction = Some(c);
                self.rounds.push(rec);
                self.returning = Some((back.round, back.stop));
                Step::Upload(self.target)
            }
            other => {
                let why = match other {
                    Ok(_) => "the way back is within the measurement's noise".to_string(),
                    Err(e) => format!("no way back: {e}"),
                };
                rec.decision = stop_decision(&back.stop);
                rec.note = Some(format!("{}; {why}: stopped here", back.note));
                self.end(rec, back.stop)
            }
        }
    }

    /// The best measured round whose view is known, with that view and a
    /// note, when `pct` measures worse than it by more than `margin`.
    fn worse_than_best(
        &self,
        pct: Option<f64>,
        margin: f64,
    ) -> Option<(usize, Isometry3<f64>, String)> {
        let e = pct?;
        let (round, best_pct, view) = self
            .rounds
            .iter()
            .filter_map(|r| {
                let v = self.views.get(&r.round)?;
                r.shot_error_pct.map(|b| (r.round, b, *v))
            })
            .min_by(|a, b| a.1.total_cmp(&b.1))?;
        (e > best_pct + margin).then(|| {
            (
                round,
                view,
                format!(
                    "{e:.2} % with the rounds spent is worse than round {round}'s {best_pct:.2} %: back to that round's view"
                ),
            )
        })
    }

    fn end(&mut self, rec: RoundRecord, stop: Stop) -> Step {
        self.rounds.push(rec);
        self.stop = Some(stop.clone());
        Step::Done(stop)
    }
}

/// The camera pose (map frame) a vehicle reproducing `map_from_desired`
/// takes: the target the georeference makes of it (position, heading,
/// gimbal pitch; a 2-axis gimbal drops the roll), flown exactly.
fn reproducible_pose(
    ctx: &Context<'_>,
    map_from_desired: &Isometry3<f64>,
) -> Option<Isometry3<f64>> {
    let t = convert_target(ctx.alignment, map_from_desired, ctx.frame, ctx.mount).ok()?;
    let state = VehicleState {
        time: 0.0,
        p_ned: t.p_ned_vehicle,
        v_ned: Vector3::zeros(),
        ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, t.yaw_deg.to_radians()),
        gimbal: GimbalAngles {
            pitch: t.gimbal_pitch_deg.to_radians(),
            yaw: 0.0,
        },
    };
    let ned = ned_from_cam(&state, &ctx.alignment.mount(ctx.mount));
    let map_from_ned = ctx.alignment.ned_from_map.inverse();
    Some(Isometry3::from_parts(
        Translation3::from(
            map_from_ned
                .transform_point(&Point3::from(ned.translation.vector))
                .coords,
        ),
        map_from_ned.rotation * ned.rotation,
    ))
}

/// The pose whose position is nearest the median position of `poses`.
fn central_pose(poses: &[(Isometry3<f64>, Option<Vector3<f64>>)]) -> Option<Isometry3<f64>> {
    let axis = |i: usize| {
        finite_median(
            &poses
                .iter()
                .map(|(p, _)| p.translation.vector[i])
                .collect::<Vec<_>>(),
        )
    };
    let m = Vector3::new(axis(0)?, axis(1)?, axis(2)?);
    poses
        .iter()
        .map(|(p, _)| p)
        .min_by(|a, b| {
            (a.translation.vector - m)
                .norm()
                .total_cmp(&(b.translation.vector - m).norm())
        })
        .copied()
}

/// The noise of a round's shot error (the median of `frames` frames'
/// errors whose spread is `spread`, % of the diagonal): twice the median's
/// standard error (1.25 sigma / sqrt(n)); 0 without a spread. A change
/// within it is one the measurement cannot tell.
pub fn median_noise_pct(spread: Option<f64>, frames: usize) -> f64 {
    spread.map_or(0.0, |s| 2.0 * 1.25 * s / (frames.max(1) as f64).sqrt())
}
#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use crate::geo::Geodetic;
    use crate::geometry::Sim3;
    use crate::refine::ControllerParams;
    use crate::slam::ScaleInfo;
    use nalgebra::Point3;
    use shotpilot_sim::camera::SimCamera;
    use shotpilot_sim::paths::camera_from_yaw_pitch;
    use shotpilot_sim::render::{RenderParams, Renderer};
    use shotpilot_sim::world::{World, WorldParams};
    use std::sync::Arc;

    struct Fixture {
        desired: GrayImage,
        turned: GrayImage,
        map: Map,
        alignment: GeoAlignment,
        frame: LocalFrame,
        home: Home,
        target: Target,
    }

    fn fixture() -> Fixture {
        let sc = SimCamera::default();
        let world = World::generate_with(3, &WorldParams::small()).unwrap();
        let r = Renderer::new(Arc::new(world), sc, RenderParams::default());
        let pose = camera_from_yaw_pitch(Point3::new(0.0, 0.0, -15.0), 0.2, 0.8);
        let turned = camera_from_yaw_pitch(Point3::new(0.0, 0.0, -15.0), 0.2 + 0.05, 0.8);
        let camera = Camera::new(
            sc.width,
            sc.height,
            [sc.fx, sc.fy, sc.cx, sc.cy],
            Distortion::default(),
        )
        .unwrap();
        let home = Home {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_amsl_m: 400.0,
        };
        Fixture {
            desired: r.render_noisy(&pose, 1),
            turned: r.render_noisy(&turned, 2),
            map: Map::new(camera, ScaleInfo::new(1.2, 8)),
            alignment: GeoAlignment::given(Sim3::identity()),
            frame: LocalFrame::new(Geodetic {
                lat_deg: home.lat_deg,
                lon_deg: home.lon_deg,
                alt_m: home.alt_amsl_m,
            }),
            home,
            target: Target {
                lat_deg: 47.0,
                lon_deg: 8.0,
                alt_m: 15.0,
                yaw_deg: 11.0,
                gimbal_pitch_deg: -45.0,
                photo: false,
            },
        }
    }

    impl Fixture {
        /// The flown target's position, local NED metres.
        fn target_ned(&self) -> Vector3<f64> {
            self.frame.geodetic_to_ned(&Geodetic {
                lat_deg: self.target.lat_deg,
                lon_deg: self.target.lon_deg,
                alt_m: self.home.alt_amsl_m + self.target.alt_m,
            })
        }
    }

    fn run(f: &Fixture, live: &GrayImage, max_rounds: usize) -> (Step, Session) {
        let params = Params {
            controller: ControllerParams {
                max_rounds,
                ..ControllerParams::default()
            },
            ..Params::default()
        };
        let mut s = new_session(f, params);
        let ctx = Context {
            map: &f.map,
            alignment: &f.alignment,
            frame: &f.frame,
            mount: &MountParams::default(),
            home: &f.home,
            fence: &Fence::default(),
            localize: &LocalizeParams::default(),
        };
        let step = s.on_arrival(
            &[LiveFrame {
                image: live,
                reported_ned_m: None,
            }],
            0.0,
            None,
            &ctx,
        );
        (step, s)
    }

    #[test]
    fn arrivals_end_the_loop_for_their_reasons() {
        let f = fixture();
        // The same view: converged at once.
        let (step, s) = run(&f, &f.desired, 4);
        assert_eq!(step, Step::Done(Stop::Converged));
        assert_eq!(s.rounds().len(), 1);
        assert!(s.rounds()[0].shot_error_pct.is_some_and(|e| e < 0.2));
        // A view turned by ~3 deg (about 4 % of the diagonal) with no round
        // left: the budget ends it, with the error recorded.
        let (step, s) = run(&f, &f.turned, 0);
        assert_eq!(step, Step::Done(Stop::MaxRounds));
        let e = s.rounds()[0].shot_error_pct.unwrap_or(0.0);
        assert!(e > 2.0, "{e}");
        // With rounds left, the live frame must be localised: an empty map
        // cannot, and the loop says so instead of guessing.
        let (step, s) = run(&f, &f.turned, 4);
        assert!(
            matches!(step, Step::Done(Stop::LiveNotLocalised(_))),
            "{step:?}"
        );
        assert_eq!(s.stop().map(Stop::name), Some("live_not_localised"));
        assert_eq!(s.rounds()[0].decision, Decision::Correct);
        assert!(s.rounds()[0].note.is_some());
        // A finished session stays finished.
        let mut s = s;
        let ctx = Context {
            map: &f.map,
            alignment: &f.alignment,
            frame: &f.frame,
            mount: &MountParams::default(),
            home: &f.home,
            fence: &Fence::default(),
            localize: &LocalizeParams::default(),
        };
        assert!(matches!(
            s.on_arrival(
                &[LiveFrame {
                    image: &f.desired,
                    reported_ned_m: None,
                }],
                0.0,
                None,
                &ctx
            ),
            Step::Done(Stop::LiveNotLocalised(_))
        ));
        assert_eq!(s.rounds().len(), 1);
    }

    /// A note the driver adds goes after the round's own (joined), or is
    /// the note when the round had none; without a round it changes nothing.
    #[test]
    fn the_driver_annotates_the_last_round() {
        let f = fixture();
        let (_, mut s) = run(&f, &f.desired, 4);
        assert_eq!(s.rounds()[0].note, None);
        s.annotate("kept the last alignment");
        assert_eq!(
            s.rounds()[0].note.as_deref(),
            Some("kept the last alignment")
        );
        let (_, mut s) = run(&f, &f.turned, 4);
        let own = s.rounds()[0].note.clone().unwrap();
        s.annotate("kept the last alignment");
        assert_eq!(
            s.rounds()[0].note.as_deref(),
            Some(format!("{own}; kept the last alignment").as_str())
        );
        let mut empty = new_session(&f, Params::default());
        empty.annotate("nothing to add it to");
        assert!(empty.rounds().is_empty());
    }

    /// The camera (map = NED here) of a vehicle at `p_ned` with the
    /// target's heading and gimbal pitch.
    fn camera_at(p_ned: Vector3<f64>, t: &Target, mount: &MountParams) -> Isometry3<f64> {
        ned_from_cam(
            &VehicleState {
                time: 0.0,
                p_ned,
                v_ned: Vector3::zeros(),
                ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, t.yaw_deg.to_radians()),
                gimbal: GimbalAngles {
                    pitch: t.gimbal_pitch_deg.to_radians(),
                    yaw: 0.0,
                },
            },
            mount,
        )
    }

    #[test]
    fn the_offset_is_measured_from_the_reported_position_and_noise_is_not_chased() {
        let f = fixture();
        let mount = MountParams::default();
        let ctx = Context {
            map: &f.map,
            alignment: &f.alignment,
            frame: &f.frame,
            mount: &mount,
            home: &f.home,
            fence: &Fence::default(),
            localize: &LocalizeParams::default(),
        };
        let flown = f.target;
        let t_ned = f.target_ned();
        // The desired camera: the vehicle exactly at the flown target. The
        // vehicle stands 5 cm off its target (wind) by its own report and
        // its GNSS bias puts it 0.6 m north, 0.4 m west, 0.2 m lower.
        let desired = camera_at(t_ned, &flown, &mount);
        let mut s = Session::new(f.desired.clone(), None, desired, flown, Params::default());
        let bias = Vector3::new(0.6, -0.4, 0.2);
        let reported = t_ned + Vector3::new(0.05, 0.0, 0.0);
        let mut frames: Vec<_> = [0.004, -0.003, 0.0, 0.002, -0.001]
            .iter()
            .map(|&n| {
                (
                    camera_at(reported + bias + Vector3::new(n, -n, n), &flown, &mount),
                    Some(reported),
                )
            })
            .collect();
        // One frame localised 2 m off: an outlier.
        frames[2].0.translation.vector.x += 2.0;
        let (c, o) = s.correct_from(&frames, 10.0, 0, &ctx).unwrap();
        assert_eq!(o.frames_localised, 5);
        for i in 0..3 {
            assert!((o.measured[i] - bias[i]).abs() < 0.01, "{o:?}");
            assert!(o.sigma[i] > 0.0 && o.sigma[i] < 0.05, "{o:?}");
        }
        assert!(
            o.measured[3].abs() < 0.01 && o.measured[4].abs() < 0.01,
            "{o:?}"
        );
        // The new target is where the vehicle must report itself for the
        // camera to stand at the desired pose: the target minus the bias,
        // whatever the vehicle's own holding error was.
        let step = Vector3::from(c.step_ned_m);
        assert!((step + bias).norm() < 0.01, "{step:?}");
        assert_eq!(o.gated, [false, false, false, true, true]);
        // Next round, 8 s later: the bias has not moved, so the camera
        // stands at the desired pose; the correction left is noise.
        s.target = c.target;
        let reported = t_ned - bias;
        let frames: Vec<_> = [0.003, -0.002, 0.0, 0.001, -0.004]
            .iter()
            .map(|&n| {
                (
                    camera_at(t_ned + Vector3::new(n, n, -n), &flown, &mount),
                    Some(reported),
                )
            })
            .collect();
        let (c, o) = s.correct_from(&frames, 18.0, 1, &ctx).unwrap();
        assert_eq!(o.gated, [true; 5], "{o:?}");
        assert!(Vector3::from(c.step_ned_m).norm() < 1e-9);
        // The filter weighs the new measurement against the estimate: 8 s
        // of drift make the old estimate worth less than a precise new
        // measurement (positions: 0.16 m² against 0.0005 m²; angles:
        // 0.016 deg² against 0.002 deg²).
        assert!(o.gain.iter().all(|&g| g > 0.85 && g <= 1.0), "{o:?}");
    }
    /// A refit of the georeference between two rounds (0.5 m and 2 deg of
    /// heading here) moves the live states and the desired one alike: the
    /// camera standing at the desired pose still needs no correction,
    /// whatever share of the last estimate the filter keeps.
    #[test]
    fn a_refit_between_rounds_is_not_taken_for_an_offset() {
        let f = fixture();
        let mount = MountParams::default();
        let refit = GeoAlignment::given(Sim3 {
            rotation: UnitQuaternion::from_euler_angles(0.0, 0.0, 2f64.to_radians()),
            translation: Vector3::new(0.5, -0.3, 0.1),
            scale: 1.0,
        });
        let (fence, localize) = (Fence::default(), LocalizeParams::default());
        let ctx_with = |alignment| Context {
            map: &f.map,
            alignment,
            frame: &f.frame,
            mount: &mount,
            home: &f.home,
            fence: &fence,
            localize: &localize,
        };
        let flown = f.target;
        let t_ned = f.target_ned();
        let desired = camera_at(t_ned, &flown, &mount);
        // Half of each new measurement: what is kept of the old estimate
        // is what a refit would leak into the correction.
        let mut params = Params::default();
        params.controller.later_gain = 0.5;
        let mut s = Session::new(f.desired.clone(), None, desired, flown, params);
        let bias = Vector3::new(0.6, -0.4, 0.2);
        let jitter = [0.003, -0.002, 0.0, 0.001, -0.004];
        let frames: Vec<_> = jitter
            .iter()
            .map(|&n| {
                (
                    camera_at(t_ned + bias + Vector3::new(n, -n, n), &flown, &mount),
                    Some(t_ned),
                )
            })
            .collect();
        let (c, _) = s
            .correct_from(&frames, 10.0, 0, &ctx_with(&f.alignment))
            .unwrap();
        s.target = c.target;
        // Next round: the camera stands at the desired pose (the vehicle
        // reports itself at the target minus the bias), and the map's
        // georeference has been refit.
        let frames: Vec<_> = jitter
            .iter()
            .map(|&n| {
                (
                    camera_at(t_ned + Vector3::new(n, n, -n), &flown, &mount),
                    Some(t_ned - bias),
                )
            })
            .collect();
        let (c, o) = s.correct_from(&frames, 18.0, 1, &ctx_with(&refit)).unwrap();
        assert!(o.gain.iter().all(|&g| g <= 0.5), "{o:?}");
        assert_eq!(o.gated, [true; 5], "{o:?}");
        assert!(Vector3::from(c.step_ned_m).norm() < 1e-9, "{c:?}");
        assert!(c.yaw_step_deg.abs() < 1e-9, "{c:?}");
    }

    fn ctx_of<'a>(
        f: &'a Fixture,
        mount: &'a MountParams,
        fence: &'a Fence,
        localize: &'a LocalizeParams,
    ) -> Context<'a> {
        Context {
            map: &f.map,
            alignment: &f.alignment,
            frame: &f.frame,
            mount,
            home: &f.home,
            fence,
            localize,
        }
    }

    fn reachable_with_floor(floor_pct: f64) -> Reachable {
        Reachable {
            ideal_from_desired: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            floor_px: floor_pct * 8.0,
            floor_pct,
            points: 100,
            inliers: 100,
            points_map: Vec::new(),
        }
    }

    /// The turned view's first round (its shot error over 2 %, asserted)
    /// and that view as one live frame.
    fn turned_view(f: &Fixture) -> (Session, f64, [LiveFrame<'_>; 1]) {
        let (_, measured) = run(f, &f.turned, 0);
        let e = measured.rounds()[0].shot_error_pct.unwrap_or(0.0);
        assert!(e > 2.0, "{e}");
        let live = [LiveFrame {
            image: &f.turned,
            reported_ned_m: None,
        }];
        (measured, e, live)
    }

    /// A fresh loop for the fixture's desired shot, its target being flown.
    fn new_session(f: &Fixture, params: Params) -> Session {
        Session::new(
            f.desired.clone(),
            None,
            Isometry3::identity(),
            f.target,
            params,
        )
    }

    /// A session whose round 0 measured `earlier` (the turned view's
    /// record, its live camera localised at the identity).
    fn after_round_0(f: &Fixture, measured: &Session, earlier: f64, params: Params) -> Session {
        let mut s = new_session(f, params);
        let mut r0 = measured.rounds()[0].clone();
        r0.round = 0;
        r0.shot_error_pct = Some(earlier);
        r0.decision = Decision::Correct;
        s.rounds.push(r0);
        s.views.insert(0, Isometry3::identity());
        s
    }

    /// The last round's note ("" without one).
    fn last_note(s: &Session) -> String {
        s.rounds()
            .last()
            .and_then(|r| r.note.clone())
            .unwrap_or_default()
    }

    /// Near its floor or under it the loop stops `at_floor` instead of
    /// flying a round that cannot gain more than the measurement tells;
    /// farther above it, it goes on.
    #[test]
    fn within_the_margin_of_the_floor_the_loop_stops_at_floor() {
        let f = fixture();
        let (mount, fence, localize) = (
            MountParams::default(),
            Fence::default(),
            LocalizeParams::default(),
        );
        let ctx = ctx_of(&f, &mount, &fence, &localize);
        let (_, e, live) = turned_view(&f);
        let near = new_session(&f, Params::default());
        let mut near = near.with_reachable(reachable_with_floor(e - 0.2));
        assert_eq!(
            near.on_arrival(&live, 0.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
        assert_eq!(near.rounds()[0].decision, Decision::AtFloor);
        assert!(
            near.rounds()[0]
                .note
                .as_deref()
                .is_some_and(|n| n.contains("floor"))
        );
        // 1 % above the floor: a correction can still gain, so the loop
        // goes on (and here, with an empty map, cannot localise the live
        // frame and says so).
        let far = new_session(&f, Params::default());
        let mut far = far.with_reachable(reachable_with_floor(e - 1.0));
        assert!(matches!(
            far.on_arrival(&live, 0.0, None, &ctx),
            Step::Done(Stop::LiveNotLocalised(_))
        ));
        // Under the floor, however far: the view is already better than a
        // camera at the shot's pose gives; it stops.
        let mut under =
            new_session(&f, Params::default()).with_reachable(reachable_with_floor(e + 1.0));
        assert_eq!(
            under.on_arrival(&live, 0.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
    }
    /// Near its floor, a correction that gains less than the margin over
    /// the best round ends the loop: here when this view is within the
    /// margin of the best measured, else after flying back to the best
    /// round's view (here, with an empty map, the live frame cannot be
    /// localised, so it says there is no way back and stops); one that
    /// gained stops too. One far above the floor goes on.
    #[test]
    fn a_loop_stalled_near_its_floor_ends_on_its_best_round() {
        let f = fixture();
        let (mount, fence, localize) = (
            MountParams::default(),
            Fence::default(),
            LocalizeParams::default(),
        );
        let ctx = ctx_of(&f, &mount, &fence, &localize);
        let (measured, e, live) = turned_view(&f);
        // A session whose round 0 measured `earlier` (its live camera
        // localised), now arriving with the error `e`.
        let after = |earlier: f64, floor: f64| {
            after_round_0(&f, &measured, earlier, Params::default())
                .with_reachable(reachable_with_floor(floor))
        };
        // 0.8 % over the floor, 0.1 % better than round 0: stop here.
        let mut here = after(e + 0.1, e - 0.8);
        assert_eq!(
            here.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
        assert!(
            last_note(&here).contains("gained less"),
            "{}",
            last_note(&here)
        );
        // 0.2 % worse than round 0, within the margin: stop here too.
        let mut level = after(e - 0.2, e - 0.8);
        assert_eq!(
            level.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
        assert!(
            last_note(&level).contains("gained less"),
            "{}",
            last_note(&level)
        );
        // 0.5 % worse: back to round 0's view, which needs the live
        // camera; unlocalised, the loop stops here and says why.
        let mut back = after(e - 0.5, e - 0.8);
        assert_eq!(
            back.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
        let n = last_note(&back);
        assert!(
            n.contains("back to that round's view") && n.contains("no way back"),
            "{n}"
        );
        // A correction that gained 0.5 % and landed near the floor: stop
        // here, a further round would gamble the gain.
        let mut gaining = after(e + 0.5, e - 0.8);
        assert_eq!(
            gaining.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::AtFloor)
        );
        assert!(
            last_note(&gaining).contains("gained 0.50"),
            "{}",
            last_note(&gaining)
        );
        // 1.5 % over the floor: not near it; the loop goes on.
        let mut far = after(e - 0.2, e - 1.5);
        assert!(matches!(
            far.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::LiveNotLocalised(_))
        ));
    }

    /// With the rounds spent, a last view that measured worse than an
    /// earlier round's (beyond the margin) is not where the loop ends: it
    /// flies back to that round's view (here, with an empty map, the live
    /// frame cannot be localised: it says there is no way back and stops);
    /// a last view that is the best ends the loop as it is.
    #[test]
    fn with_the_rounds_spent_the_loop_ends_on_its_best_view() {
        let f = fixture();
        let (mount, fence, localize) = (
            MountParams::default(),
            Fence::default(),
            LocalizeParams::default(),
        );
        let ctx = ctx_of(&f, &mount, &fence, &localize);
        let (measured, e, live) = turned_view(&f);
        let spent = |earlier: f64| {
            let params = Params {
                controller: ControllerParams {
                    max_rounds: 1,
                    ..ControllerParams::default()
                },
                ..Params::default()
            };
            after_round_0(&f, &measured, earlier, params)
        };
        let mut worse = spent(e - 1.0);
        assert_eq!(
            worse.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::MaxRounds)
        );
        let n = last_note(&worse);
        assert!(
            n.contains("worse than round 0") && n.contains("no way back"),
            "{n}"
        );
        let mut best = spent(e + 1.0);
        assert_eq!(
            best.on_arrival(&live, 1.0, None, &ctx),
            Step::Done(Stop::MaxRounds)
        );
        assert!(!last_note(&best).contains("back"), "{}", last_note(&best));
    }
}
