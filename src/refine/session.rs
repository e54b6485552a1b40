//! One shot's refinement loop as a state machine the daemon (or the
//! scenario) drives: it is told the vehicle has arrived with a steady view
//! and given the live frame; it measures the shot error, decides, localises
//! the live frame and returns the corrected target to upload, or stops.
//! Its rounds are the record the API shows.

use image::GrayImage;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use super::{Correction, Decision, Params, Reachable, correct, decide, shot_error};
use crate::camera::Camera;
use crate::geo::{
    GeoAlignment, GimbalAngles, LocalFrame, MountParams, VehicleState, convert_target, ned_from_cam,
};
use crate::mission::plan::{Fence, Home, Target};
use crate::shot::{Localization, LocalizeParams, localize};
use crate::slam::Map;

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
    /// Homography inliers.
    pub inliers: Option<usize>,
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
    /// The correction uploaded next.
    pub correction: Option<Correction>,
    /// Why the loop could not go on, or why the shot error is missing.
    pub note: Option<String>,
    /// What the driver saw besides the frame (telemetry, timing), when it
    /// told ([`Session::observe`]).
    pub observed: Option<Observation>,
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
    /// The live frame could not be localised.
    LiveNotLocalised(String),
    /// The correction failed its checks (geofence, altitude, gimbal) or
    /// the georeference refused it.
    CorrectionRefused(String),
}

impl Stop {
    /// A short name (`converged`, `max_rounds`, `at_floor`,
    /// `live_not_localised`, `correction_refused`).
    pub fn name(&self) -> &'static str {
        match self {
            Stop::Converged => "converged",
            Stop::MaxRounds => "max_rounds",
            Stop::AtFloor => "at_floor",
            Stop::LiveNotLocalised(_) => "live_not_localised",
            Stop::CorrectionRefused(_) => "correction_refused",
        }
    }
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

    /// The target being flown.
    pub fn target(&self) -> &Target {
        &self.target
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
    /// shot error of `live`, decide, and when going on, localise `live` and
    /// correct the target. `camera` undistorts the shot-error keypoints.
    pub fn on_arrival(
        &mut self,
        live: &GrayImage,
        camera: Option<&Camera>,
        ctx: &Context<'_>,
    ) -> Step {
        if let Some(s) = &self.stop {
            return Step::Done(s.clone());
        }
        let round = self.rounds.len();
        let err = shot_error(
            live,
            &self.desired,
            self.mask.as_ref(),
            camera,
            &self.params.error,
        );
        let pct = err.as_ref().ok().map(|e| e.corner_error_pct);
        let threshold = self.params.controller.threshold_pct;
        let decision = decide(pct, round, &self.params.controller);
        let mut rec = RoundRecord {
            round,
            target: self.target,
            shot_error_pct: pct,
            shot_error_px: err.as_ref().ok().map(|e| e.corner_error_px),
            inliers: err.as_ref().ok().map(|e| e.inliers),
            floor_pct: self.reachable.as_ref().map(|r| r.floor_pct),
            pose_framing_pct: None,
            decision,
            live_map_position: None,
            correction: None,
            note: err.as_ref().err().map(|e| format!("shot error: {e}")),
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
        let floor = self
            .reachable
            .as_ref()
            .filter(|r| r.floor_pct >= threshold)
            .zip(reachable_pose);
        let localised = if floor.is_some() || decision == Decision::Correct {
            Some(localize(ctx.map, live, None, None, ctx.localize))
        } else {
            None
        };
        if let (Some((r, pose)), Some(Ok(Localization::Localized(p)))) = (floor, &localised) {
            rec.live_map_position = Some(p.world_from_cam.translation.vector.into());
            let framing = r.framing_change_pct(&p.world_from_cam, &pose, &ctx.map.camera);
            rec.pose_framing_pct = framing;
            if framing.is_some_and(|f| f < threshold)
                && pct.is_some_and(|e| e <= r.floor_pct + threshold)
            {
                rec.decision = Decision::AtFloor;
                return self.end(rec, Stop::AtFloor);
            }
        }
        if decision == Decision::MaxRounds {
            return self.end(rec, Stop::MaxRounds);
        }
        let live_map = match localised {
            Some(Ok(Localization::Localized(p))) => p.world_from_cam,
            Some(Ok(Localization::NotLocalized { reason })) => {
                let why = reason.to_string();
                rec.note = Some(format!("live frame not localised: {why}"));
                return self.end(rec, Stop::LiveNotLocalised(why));
            }
            Some(Err(e)) => {
                rec.note = Some(format!("live frame not localised: {e}"));
                return self.end(rec, Stop::LiveNotLocalised(e.to_string()));
            }
            None => {
                let why = "the live frame was not localised".to_string();
                rec.note = Some(why.clone());
                return self.end(rec, Stop::LiveNotLocalised(why));
            }
        };
        rec.live_map_position = Some(live_map.translation.vector.into());
        // The first correction takes the whole (mostly systematic) error,
        // the later ones a fraction, so the live localisation noise averages.
        let mut ctrl = self.params.controller;
        if round >= 1 {
            ctrl.gain = ctrl.later_gain;
        }
        match correct(
            ctx.alignment,
            ctx.frame,
            ctx.mount,
            &self.map_from_desired,
            &live_map,
            &self.target,
            ctx.home,
            ctx.fence,
            &ctrl,
        ) {
            Ok(c) => {
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

    /// Attaches what the driver saw at the last arrival to its round.
    pub fn observe(&mut self, observed: Observation) {
        if let Some(r) = self.rounds.last_mut() {
            r.observed = Some(observed);
        }
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
    let ned = ned_from_cam(&state, ctx.mount);
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

    fn run(f: &Fixture, live: &GrayImage, max_rounds: usize) -> (Step, Session) {
        let params = Params {
            controller: ControllerParams {
                max_rounds,
                ..ControllerParams::default()
            },
            ..Params::default()
        };
        let mut s = Session::new(
            f.desired.clone(),
            None,
            Isometry3::identity(),
            f.target,
            params,
        );
        let ctx = Context {
            map: &f.map,
            alignment: &f.alignment,
            frame: &f.frame,
            mount: &MountParams::default(),
            home: &f.home,
            fence: &Fence::default(),
            localize: &LocalizeParams::default(),
        };
        let step = s.on_arrival(live, None, &ctx);
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
            s.on_arrival(&f.desired, None, &ctx),
            Step::Done(Stop::LiveNotLocalised(_))
        ));
        assert_eq!(s.rounds().len(), 1);
    }
}
