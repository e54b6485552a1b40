//! The explore flight: the simulator's `explore` script flown while the
//! SLAM maps the frames and the georeference takes the telemetry; what it
//! built (the map, its georeference, each keyframe's truth) and its report.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Isometry3, Vector3};

use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::script::{Script, ScriptKind};

use crate::camera::Camera;
use crate::geo::{self, GeoAlignment, Geodetic, LocalFrame};
use crate::slam::priors::{PriorParams, Priors, TelemetryFeed};
use crate::slam::{Map, MapMode, Slam};

use super::error::ScenarioError;
use super::params::ScenarioParams;
use super::report::ExploreReport;
use super::sim::{PriorTap, Sim};

fn camera_of(c: &SimCamera) -> Result<Camera, crate::camera::CameraError> {
    crate::simulator::camera_from_sim(c)
}

/// The truth of one explore frame: the vehicle position (NED), heading and
/// gimbal pitch (radians) as reported, and the camera pose it really had.
type FrameTruth = ((Vector3<f64>, f64, f64), Isometry3<f64>);

/// The explore flight and what it built.
pub(super) struct Explored {
    pub(super) map: Map,
    pub(super) alignment: GeoAlignment,
    pub(super) frame: LocalFrame,
    /// Truth per keyframe id: (vehicle position NED, heading rad, gimbal
    /// pitch rad) as reported, and the true camera pose.
    pub(super) kf_truth: BTreeMap<u32, FrameTruth>,
    pub(super) report: ExploreReport,
}

pub(super) fn explore(sim: &mut Sim, params: &ScenarioParams) -> Result<Explored, ScenarioError> {
    let wall = Instant::now();
    let mut camera = camera_of(sim.renderer.camera())?;
    // The realistic camera's rolling shutter, which the SLAM models.
    camera.readout_s = sim
        .imager
        .as_ref()
        .and_then(|i| i.camera().rolling_shutter)
        .map_or(0.0, |r| r.readout_s);
    let mut slam_params = params.slam.clone();
    if params.priors {
        let feed = TelemetryFeed::live(params.geo.history.max_age_s);
        slam_params.priors = Some(Priors::with_feed(feed.clone(), PriorParams::default()));
        sim.priors = Some(PriorTap {
            feed,
            mount: params.geo.mount.clone(),
            attitude: None,
            gps: None,
        });
    }
    let mut slam = Slam::new(camera, slam_params)?;
    let home = sim.ap.params().vehicle.home;
    let mut g = geo::Geo::new(params.geo.clone());
    g.set_home(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_m,
    })?;
    let world = sim.renderer.world().clone();
    let mut script = Script::new(
        ScriptKind::Explore,
        params.script.clone(),
        &move |x, y, r| world.max_height_near(x, y, r),
    );
    let every = ((params.step_hz / params.slam_fps).round() as u64).max(1);
    let limit_s = 3.0 * script.length_m() / params.script.speed.max(0.1) + 120.0;
    let mut truth_by_frame: BTreeMap<u64, FrameTruth> = BTreeMap::new();
    let (mut frames, mut tracked) = (0u64, 0u64);
    while !script.finished() {
        if sim.t > limit_s {
            return Err(ScenarioError::ExploreTimeout { seconds: limit_s });
        }
        script.step(&mut sim.ap, sim.t + sim.dt);
        sim.step(Some(&mut g));
        if sim.k.is_multiple_of(every) && !sim.ap.vehicle().landed() {
            let image = Arc::new(sim.render());
            let v = sim.ap.vehicle();
            truth_by_frame.insert(
                frames,
                ((v.p_ned(), v.yaw(), v.gimbal_angles().0), sim.true_camera()),
            );
            let outcome = slam.process(frames, sim.t, image);
            frames += 1;
            if outcome.cam_from_world.is_some() {
                tracked += 1;
            }
        }
    }
    // A little more telemetry so the last keyframes are covered.
    for _ in 0..50 {
        sim.step(Some(&mut g));
    }
    let run = slam.finish();
    let map = run.map;
    let mut kf_truth = BTreeMap::new();
    for kf in map.keyframes() {
        // As the daemon does: a keyframe the georeference refuses (its
        // time in a telemetry gap) is left out, the rest go on.
        if let Err(e) = g.add_keyframe(u64::from(kf.id.0), &kf.world_from_cam(), kf.timestamp) {
            tracing::debug!(kf = kf.id.0, "geo: keyframe refused: {e}");
            continue;
        }
        if let Some(t) = truth_by_frame.get(&kf.frame_index) {
            kf_truth.insert(kf.id.0, *t);
        }
    }
    g.retry_pending();
    let keyframes = map.keyframes().count();
    if keyframes < 5 {
        return Err(ScenarioError::NoMap { keyframes });
    }
    // A map the priors put in local NED is georeferenced by itself (the
    // daemon's `source: map`); else the Sim(3) fitted after the flight.
    let map_mode = map.mode();
    let alignment = if map_mode == MapMode::GpsAided {
        GeoAlignment::of_map_in_ned(g.georeference().pairs(), g.georeference().params())
    } else {
        g.fit()?
    };
    sim.priors = None;
    let frame = *g.frame().ok_or(crate::geo::GeoError::NoHome)?;
    if params.geo.align.drift.is_some() {
        // The georeference follows the drift through the trials (a map in
        // local NED too: its pairs fitted with the bias states give the
        // identity moved to where the receiver reads now).
        sim.geo = Some(g);
    }
    let report = ExploreReport {
        sim_s: sim.t,
        frames,
        tracked,
        keyframes,
        points: map.points().count(),
        geo_pairs: alignment.quality.pairs,
        geo_inliers: alignment.quality.inliers,
        geo_rms_m: alignment.quality.rms_m,
        mount_offset: alignment.mount_offset,
        geo_scale: alignment.ned_from_map.scale,
        map_mode: map_mode.name(),
        wall_s: wall.elapsed().as_secs_f64(),
    };
    Ok(Explored {
        map,
        alignment,
        frame,
        kf_truth,
        report,
    })
}
