//! The simulator's own vehicle and gimbal code (`shotpilot-sim`) as the
//! judge of `geo`: frame conventions, time alignment, the map → NED fit and
//! target conversion against its ground truth.
//!
//! The SLAM side is synthetic here: keyframe poses are the simulator's true
//! camera poses expressed in a map frame through a known similarity, with
//! noise; the NED side goes through this crate's telemetry history (the
//! simulator's message rates and quantisation) and camera mounting.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::geo::{
    AlignParams, Geo, Geodetic, GimbalAngles, HistoryParams, LeverArmFrame, LocalFrame,
    MountParams, Params, VehicleState, ned_from_cam,
};
use shotpilot::geometry::Sim3;
use shotpilot_sim::vehicle::{Setpoint, Vehicle, VehicleParams};

const DT: f64 = 0.01;

fn mount_for(p: &VehicleParams, frame: LeverArmFrame) -> MountParams {
    MountParams {
        lever_arm_body_m: p.camera_offset_body,
        lever_arm_frame: frame,
        stabilised: true,
        pitch_min_deg: p.gimbal.pitch_min_deg,
        pitch_max_deg: p.gimbal.pitch_max_deg,
        ..MountParams::default()
    }
}

fn exact_state(v: &Vehicle, t: f64) -> VehicleState {
    let (pitch, yaw) = v.gimbal_angles();
    VehicleState {
        time: t,
        p_ned: v.p_ned(),
        v_ned: v.v_ned(),
        ned_from_body: v.world_from_body_rotation(),
        gimbal: GimbalAngles { pitch, yaw },
    }
}

fn gauss(rng: &mut SmallRng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn to_geo(g: &shotpilot_sim::geodesy::Geodetic) -> Geodetic {
    Geodetic {
        lat_deg: g.lat_deg,
        lon_deg: g.lon_deg,
        alt_m: g.alt_m,
    }
}

#[test]
fn the_simulators_camera_pose_is_ours_for_every_state() {
    let params = VehicleParams::default();
    let mount = mount_for(&params, LeverArmFrame::Heading);
    let mut v = Vehicle::new(params);
    v.teleport(Vector3::new(0.0, 0.0, -10.0), 0.0);
    let mut worst_m: f64 = 0.0;
    let mut worst_rad: f64 = 0.0;
    let mut rng = SmallRng::seed_from_u64(1);
    for leg in 0..20 {
        v.set_setpoint(Setpoint::Position {
            p_ned: Vector3::new(
                rng.random_range(-40.0..40.0),
                rng.random_range(-40.0..40.0),
                rng.random_range(-30.0..-5.0),
            ),
            yaw: Some(rng.random_range(-3.1..3.1)),
            max_speed: None,
        });
        v.set_gimbal_target(rng.random_range(-90.0..30.0), rng.random_range(-60.0..60.0));
        for i in 0..300 {
            v.step(DT);
            let ours = ned_from_cam(&exact_state(&v, 0.0), &mount);
            let theirs = v.world_from_cam();
            worst_m = worst_m.max((ours.translation.vector - theirs.translation.vector).norm());
            worst_rad = worst_rad.max(ours.rotation.angle_to(&theirs.rotation));
            if i == 150 && leg % 5 == 0 {
                // WGS84: our tangent plane agrees with the simulator's.
                let ours = LocalFrame::new(to_geo(&v.frame().home())).ned_to_geodetic(&v.p_ned());
                let theirs = v.geodetic();
                assert!((ours.lat_deg - theirs.lat_deg).abs() < 1e-10);
                assert!((ours.lon_deg - theirs.lon_deg).abs() < 1e-10);
                assert!((ours.alt_m - theirs.alt_m).abs() < 1e-6);
            }
        }
    }
    println!(
        "sim vs geo camera pose: {worst_m:.2e} m, {:.2e} deg",
        worst_rad.to_degrees()
    );
    assert!(worst_m < 1e-9 && worst_rad < 1e-9);
}

/// Telemetry clock errors of a run.
#[derive(Clone, Copy)]
struct Clocks {
    /// Telemetry samples are stamped this late...
    telemetry_delay_s: f64,
    /// ...plus a uniform jitter in [-j/2, j/2].
    telemetry_jitter_s: f64,
    /// Capture times are estimated this late (mis-set video latency).
    latency_error_s: f64,
}

struct Figures {
    cam_pos_rms_m: f64,
    cam_rot_rms_deg: f64,
    scale_err: f64,
    align_rms_m: f64,
    time_offset_s: Option<f64>,
    inliers: usize,
    pairs: usize,
    target_pos_max_m: f64,
    target_alt_max_m: f64,
    target_yaw_max_deg: f64,
    target_pitch_max_deg: f64,
}

/// An explore-like flight: lanes at two altitudes, facing the direction of
/// travel, the gimbal alternating between -30 and -60 deg.
fn waypoints() -> Vec<(Vector3<f64>, f64, f64)> {
    let mut w = Vec::new();
    for (level, z) in [-12.0, -20.0].into_iter().enumerate() {
        for lane in 0..4 {
            let y = -24.0 + lane as f64 * 16.0;
            let (x0, x1) = if (lane + level) % 2 == 0 {
                (-30.0, 30.0)
            } else {
                (30.0, -30.0)
            };
            let yaw = if x1 > x0 { 0.0 } else { std::f64::consts::PI };
            let pitch = if lane % 2 == 0 { -30.0 } else { -60.0 };
            w.push((Vector3::new(x0, y, z), yaw, pitch));
            w.push((Vector3::new(x1, y, z), yaw, pitch));
        }
    }
    w
}

fn run(clocks: Clocks, estimate_offset: bool, seed: u64) -> Figures {
    let params = VehicleParams::default();
    let frame = LocalFrame::new(to_geo(&params.home));
    let mount = mount_for(&params, LeverArmFrame::Heading);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut v = Vehicle::new(params);
    v.teleport(Vector3::new(-30.0, -24.0, -12.0), 0.0);
    v.snap_gimbal(-30.0, 0.0);
    let mut geo = Geo::new(Params {
        history: HistoryParams::default(),
        mount: mount.clone(),
        align: AlignParams {
            estimate_time_offset: estimate_offset,
            ..AlignParams::default()
        },
        ..Params::default()
    });
    geo.set_home(to_geo(&params.home)).unwrap();
    // The true map <- ned (a monocular map of arbitrary scale and frame).
    let ned_from_map = Sim3::new(
        UnitQuaternion::from_euler_angles(1.2, -0.4, -2.0),
        Vector3::new(-5.0, 17.0, -8.0),
        9.5,
    );
    let map_from_ned = ned_from_map.inverse();
    let jitter = |rng: &mut SmallRng| {
        clocks.telemetry_delay_s + (rng.random_range(0.0..1.0) - 0.5) * clocks.telemetry_jitter_s
    };
    // Frames (15 Hz) wait until telemetry covers them: (true time, truth pose).
    let mut pending: Vec<(f64, Isometry3<f64>)> = Vec::new();
    let mut cam_err2 = (0.0, 0.0, 0usize);
    let mut kf_id = 0u64;
    // The first keyframe comes after the first telemetry (t >= 1.5 s).
    let mut last_kf = 0.5;
    let mut t = 0.0;
    let mut step_i = 0u64;
    for (p, yaw, pitch) in waypoints() {
        v.set_setpoint(Setpoint::Position {
            p_ned: p,
            yaw: Some(yaw),
            max_speed: None,
        });
        v.set_gimbal_target(pitch, 0.0);
        let start = t;
        while (v.p_ned() - p).norm() > 0.3 && t - start < 60.0 {
            v.step(DT);
            step_i += 1;
            t = step_i as f64 * DT;
            // Telemetry at the simulator's rates and quantisation.
            if step_i.is_multiple_of(10) {
                let (roll, pitch) = v.roll_pitch();
                geo.history_mut()
                    .push_attitude_euler(
                        t + jitter(&mut rng),
                        roll as f32 as f64,
                        pitch as f32 as f64,
                        v.yaw() as f32 as f64,
                    )
                    .unwrap();
            }
            if step_i.is_multiple_of(20) {
                let g = v.geodetic();
                let q = Geodetic {
                    lat_deg: (g.lat_deg * 1e7).round() / 1e7,
                    lon_deg: (g.lon_deg * 1e7).round() / 1e7,
                    alt_m: (g.alt_m * 1e3).round() / 1e3,
                };
                geo.push_position_geodetic(t + jitter(&mut rng), &q)
                    .unwrap();
                let (gp, gy) = v.gimbal_angles();
                geo.history_mut()
                    .push_gimbal(
                        t + jitter(&mut rng),
                        GimbalAngles {
                            pitch: gp as f32 as f64,
                            yaw: gy as f32 as f64,
                        },
                    )
                    .unwrap();
            }
            if step_i.is_multiple_of(10) {
                geo.retry_pending();
            }
            if step_i.is_multiple_of(7) {
                let truth = v.world_from_cam();
                pending.push((t, truth));
                if t - last_kf >= 1.0 {
                    last_kf = t;
                    // A keyframe: its map pose is the truth through
                    // map <- ned with SLAM-like noise (3 cm, 0.3 deg in
                    // world units), its capture time the estimate.
                    let c = truth.translation.vector
                        + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.03;
                    let rn = UnitQuaternion::from_scaled_axis(
                        Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng))
                            * 0.3f64.to_radians(),
                    );
                    let map_from_cam = Isometry3::from_parts(
                        Translation3::from(map_from_ned.transform_point(&Point3::from(c)).coords),
                        map_from_ned.rotation * rn * truth.rotation,
                    );
                    geo.add_keyframe(kf_id, &map_from_cam, t + clocks.latency_error_s)
                        .unwrap();
                    kf_id += 1;
                }
            }
            // Process frames whose (estimated) capture time telemetry covers.
            pending.retain(|(t_true, truth)| {
                let t_est = t_true + clocks.latency_error_s;
                let Ok(state) = geo.history().lookup(t_est) else {
                    return t - t_true < 2.0; // keep waiting, drop when stale
                };
                let ours = ned_from_cam(&state, &mount);
                let e = (ours.translation.vector - truth.translation.vector).norm();
                let r = ours.rotation.angle_to(&truth.rotation);
                cam_err2.0 += e * e;
                cam_err2.1 += r * r;
                cam_err2.2 += 1;
                false
            });
        }
    }
    geo.retry_pending();
    assert_eq!(geo.dropped(), 0);
    assert!(
        geo.pending() <= 1,
        "{} keyframes still waiting",
        geo.pending()
    );
    let fit = geo.fit().expect("the explore flight fixes the alignment");
    let scale_err = (fit.ned_from_map.scale / ned_from_map.scale - 1.0).abs();

    // 20 target shots: the simulator's vehicle hovering with a yaw and a
    // gimbal pitch; the target camera pose is given in the map.
    let mut fig = Figures {
        cam_pos_rms_m: (cam_err2.0 / cam_err2.2 as f64).sqrt(),
        cam_rot_rms_deg: (cam_err2.1 / cam_err2.2 as f64).sqrt().to_degrees(),
        scale_err,
        align_rms_m: fit.quality.rms_m,
        time_offset_s: fit.quality.time_offset_s,
        inliers: fit.quality.inliers,
        pairs: fit.quality.pairs,
        target_pos_max_m: 0.0,
        target_alt_max_m: 0.0,
        target_yaw_max_deg: 0.0,
        target_pitch_max_deg: 0.0,
    };
    let mut shot = Vehicle::new(params);
    for i in 0..20 {
        let p = Vector3::new(
            rng.random_range(-35.0..35.0),
            rng.random_range(-30.0..30.0),
            rng.random_range(-25.0..-8.0),
        );
        let yaw = rng.random_range(-3.1..3.1);
        let pitch = rng.random_range(-90.0..10.0);
        shot.teleport(p, yaw);
        shot.set_setpoint(Setpoint::Position {
            p_ned: p,
            yaw: Some(yaw),
            max_speed: None,
        });
        shot.snap_gimbal(pitch, 0.0);
        shot.step(DT);
        let truth_cam = shot.world_from_cam();
        let map_from_cam = Isometry3::from_parts(
            Translation3::from(
                map_from_ned
                    .transform_point(&Point3::from(truth_cam.translation.vector))
                    .coords,
            ),
            map_from_ned.rotation * truth_cam.rotation,
        );
        let target = geo
            .target(&map_from_cam)
            .unwrap_or_else(|e| panic!("target {i}: {e}"));
        let g = shot.geodetic();
        let back = frame.geodetic_to_ned(&Geodetic {
            lat_deg: target.lat_deg,
            lon_deg: target.lon_deg,
            alt_m: g.alt_m,
        });
        let horiz = (back - frame.geodetic_to_ned(&to_geo(&g))).norm();
        fig.target_pos_max_m = fig.target_pos_max_m.max(horiz);
        fig.target_alt_max_m = fig
            .target_alt_max_m
            .max((target.alt_above_home_m - (g.alt_m - params.home.alt_m)).abs());
        let dyaw = (target.yaw_deg - shot.yaw().to_degrees()).rem_euclid(360.0);
        let dyaw = dyaw.min(360.0 - dyaw);
        // Straight down, the heading is set by the image's right axis.
        fig.target_yaw_max_deg = fig.target_yaw_max_deg.max(dyaw);
        fig.target_pitch_max_deg = fig
            .target_pitch_max_deg
            .max((target.gimbal_pitch_deg - shot.gimbal_angles().0.to_degrees()).abs());
    }
    println!(
        "camera pose from telemetry: {:.3} m, {:.3} deg rms; scale error {:.3}%, alignment rms {:.3} m ({} / {} inliers), time offset {:?} s; \
         20 targets max: horizontal {:.3} m, altitude {:.3} m, yaw {:.3} deg, pitch {:.3} deg",
        fig.cam_pos_rms_m,
        fig.cam_rot_rms_deg,
        fig.scale_err * 100.0,
        fig.align_rms_m,
        fig.inliers,
        fig.pairs,
        fig.time_offset_s,
        fig.target_pos_max_m,
        fig.target_alt_max_m,
        fig.target_yaw_max_deg,
        fig.target_pitch_max_deg
    );
    fig
}

#[test]
fn explore_like_flight_then_20_targets_within_30_cm_and_1_degree() {
    let f = run(
        Clocks {
            telemetry_delay_s: 0.0,
            telemetry_jitter_s: 0.0,
            latency_error_s: 0.0,
        },
        true,
        21,
    );
    let e = f.time_offset_s.expect("offset estimated");
    assert!(e.abs() < 0.01, "time offset {e} s with exact clocks");
    assert!(
        f.cam_pos_rms_m < 0.05,
        "camera position from telemetry {} m",
        f.cam_pos_rms_m
    );
    assert!(
        f.cam_rot_rms_deg < 0.5,
        "camera rotation from telemetry {} deg",
        f.cam_rot_rms_deg
    );
    assert!(f.scale_err < 0.01);
    assert!(f.align_rms_m < 0.2);
    assert!(f.inliers as f64 > 0.95 * f.pairs as f64);
    assert!(f.target_pos_max_m < 0.3 && f.target_alt_max_m < 0.3);
    assert!(f.target_yaw_max_deg < 1.0 && f.target_pitch_max_deg < 1.0);
}

#[test]
fn delayed_jittered_telemetry_and_mis_set_latency_stay_within_twice() {
    let clocks = Clocks {
        telemetry_delay_s: 0.1,
        telemetry_jitter_s: 0.1,
        latency_error_s: 0.05,
    };
    // Without the offset estimate: the figures the issue bounds at twice
    // the nominal ones.
    let raw = run(clocks, false, 22);
    assert!(raw.scale_err < 0.02);
    assert!(raw.align_rms_m < 0.4);
    assert!(raw.target_pos_max_m < 0.6 && raw.target_alt_max_m < 0.6);
    assert!(raw.target_yaw_max_deg < 2.0 && raw.target_pitch_max_deg < 2.0);
    // With it: frames looked up 0.05 s late against telemetry stamped 0.1 s
    // late see the state of 0.05 s earlier, an offset of -0.05 s.
    let f = run(clocks, true, 22);
    let e = f.time_offset_s.expect("offset estimated");
    assert!(
        (e + 0.05).abs() < 0.015,
        "time offset {e} s, expected -0.05"
    );
    assert!(
        f.align_rms_m < 0.6 * raw.align_rms_m,
        "{} vs {}",
        f.align_rms_m,
        raw.align_rms_m
    );
    assert!(f.scale_err < 0.02);
    assert!(f.align_rms_m < 0.4);
    assert!(f.target_pos_max_m < 0.6 && f.target_alt_max_m < 0.6);
    assert!(f.target_yaw_max_deg < 2.0 && f.target_pitch_max_deg < 2.0);
}
