//! The vehicle and telemetry effects of realism, each measured: the wind's
//! position-hold error, the gimbal's pointing error, GNSS noise and fix
//! losses, barometric drift, and the autopilot's telemetry at PX4's rates
//! with the fix losses visible in GPS_RAW_INT and GLOBAL_POSITION_INT, and
//! the reported attitude's error.

use mavlink::Message;
use mavlink::dialects::common::{GpsFixType, MavMessage};
use nalgebra::Vector3;
use shotpilot_sim::autopilot::{Autopilot, AutopilotParams};
use shotpilot_sim::realism::{BaroDrift, GpsDropouts, Realism};
use shotpilot_sim::vehicle::{SensorErrors, Setpoint, Vehicle, VehicleDisturbances, VehicleParams};

const DT: f64 = 0.02;

fn hovering(d: VehicleDisturbances) -> Vehicle {
    let mut v = Vehicle::new(VehicleParams {
        disturbances: d,
        ..VehicleParams::default()
    });
    v.teleport(Vector3::new(0.0, 0.0, -30.0), 0.0);
    v.set_setpoint(Setpoint::Position {
        p_ned: Vector3::new(0.0, 0.0, -30.0),
        yaw: Some(0.0),
        max_speed: None,
    });
    v
}

fn rms(xs: &[f64]) -> f64 {
    (xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64).sqrt()
}

/// Rms horizontal distance of the true position from the setpoint while
/// hovering 300 s in `realism`'s wind (other effects off), over 4 seeds.
fn hold_error_m(realism: &Realism) -> f64 {
    let mut errs = Vec::new();
    for seed in 0..4 {
        let d = VehicleDisturbances {
            wind: realism.vehicle.wind,
            seed,
            ..VehicleDisturbances::default()
        };
        let mut v = hovering(d);
        for k in 0..(300.0 / DT) as usize {
            v.step(DT);
            if k as f64 * DT > 20.0 {
                errs.push(v.true_p_ned().xy().norm());
            }
        }
    }
    rms(&errs)
}

#[test]
fn wind_gives_a_decimetre_hold_error_and_the_vehicle_leans_into_it() {
    let harsh = hold_error_m(&Realism::harsh());
    let field = hold_error_m(&Realism::field());
    eprintln!("hold error rms: field {field:.3} m, harsh {harsh:.3} m");
    // Multicopters hold position to decimetres in wind (PX4 flight logs:
    // 0.1-0.5 m in a breeze, more in strong wind).
    assert!((0.1..1.0).contains(&harsh), "harsh {harsh}");
    assert!((0.02..0.3).contains(&field), "field {field}");
    assert!(harsh > 2.0 * field);
    // Leaning into a 9 m/s wind from 250 degrees: the thrust tilts
    // towards it (west-south-west), about atan(drag / g).
    let mut v = hovering(VehicleDisturbances {
        wind: Realism::harsh().vehicle.wind,
        seed: 1,
        ..VehicleDisturbances::default()
    });
    let (mut roll, mut pitch, mut n) = (0.0, 0.0, 0.0);
    for k in 0..(120.0 / DT) as usize {
        v.step(DT);
        if k as f64 * DT > 20.0 {
            let (r, p) = v.roll_pitch();
            roll += r;
            pitch += p;
            n += 1.0;
        }
    }
    let (roll, pitch) = (roll / n, pitch / n);
    // Yaw north: positive pitch tilts the nose up (thrust backwards,
    // south); negative roll tilts left (west).
    assert!(pitch > 0.0 && roll < 0.0, "roll {roll} pitch {pitch}");
    let tilt = roll.hypot(pitch).to_degrees();
    let expected = (0.03f64 * 81.0 / 9.806_65).atan().to_degrees();
    assert!(
        (tilt / expected - 1.0).abs() < 0.25,
        "tilt {tilt} vs {expected}"
    );
}

#[test]
fn gimbal_error_turns_the_true_camera_by_its_rms() {
    let g = Realism::harsh().vehicle.gimbal.unwrap();
    let mut v = hovering(VehicleDisturbances {
        gimbal: Some(g),
        seed: 3,
        ..VehicleDisturbances::default()
    });
    let mut angles = Vec::new();
    for _ in 0..(200.0 / 0.013) as usize {
        v.step(0.013);
        let nominal = v.world_from_cam();
        let truth = v.true_world_from_cam();
        assert!((nominal.translation.vector - truth.translation.vector).norm() < 1e-12);
        angles.push(nominal.rotation.angle_to(&truth.rotation));
    }
    // Three axes, each of deviation sqrt(stab^2 + jitter^2).
    let per_axis = (g.stabilisation_deg.powi(2) + g.jitter_deg.powi(2)).sqrt();
    let total = rms(&angles).to_degrees();
    let expected = per_axis * 3f64.sqrt();
    assert!(
        (total / expected - 1.0).abs() < 0.15,
        "{total} vs {expected}"
    );
}

#[test]
fn gnss_error_has_its_bias_and_noise_and_the_fix_is_lost_as_often_as_set() {
    let f = Realism::field().vehicle.gps.unwrap();
    // Bias and noise: the deviation of the true-minus-reported position
    // over long runs and several seeds (the bias starts at zero, its
    // correlation time is 120 s: skip the first 600 s).
    let mut xs = Vec::new();
    let mut fast = Vec::new();
    for seed in 0..6 {
        let mut v = hovering(VehicleDisturbances {
            gps: Some(f),
            seed,
            ..VehicleDisturbances::default()
        });
        let mut prev = v.position_error();
        for k in 0..(3000.0 / 0.1) as usize {
            v.step(0.1);
            let e = v.position_error();
            if k as f64 * 0.1 > 600.0 {
                xs.push(e.x);
                fast.push(e.x - prev.x);
            }
            prev = e;
        }
    }
    let sd = rms(&xs);
    let expected = (f.bias_sigma_xy_m.powi(2) + f.noise_sigma_m.powi(2)).sqrt();
    assert!((sd / expected - 1.0).abs() < 0.3, "{sd} vs {expected}");
    // Step-to-step changes are dominated by the fast noise: for a
    // Gauss-Markov of sigma s and tau T, Var(dx) = 2 s^2 dt / T. The bias
    // reaches the vehicle through the estimator's second-order low-pass
    // (natural frequency w = 1 / fusion_tau, damping z = 1 / sqrt 2), whose
    // output is smooth: its rate has the variance of the bias's
    // high-frequency PSD 2 s^2 / (T w^2) through the filter's noise
    // bandwidth w / (4 z), s^2 w / (2 z T), and a step of dt moves it by
    // the rate times dt (the raw bias would move 2.5 times as far).
    let step_sd = rms(&fast);
    let w = 1.0 / f.fusion_tau_s;
    let bias_rate_var = f.bias_sigma_xy_m.powi(2) * w / (std::f64::consts::SQRT_2 * f.bias_tau_s);
    let expect_step =
        (2.0 * 0.1 * f.noise_sigma_m.powi(2) / f.noise_tau_s + bias_rate_var * 0.1 * 0.1).sqrt();
    assert!(
        (step_sd / expect_step - 1.0).abs() < 0.15,
        "{step_sd} vs {expect_step}"
    );

    // Fix losses: a loss every 60 s on average lasting 5 s: lost about
    // 5/65 of the time, and the estimate drifts while lost.
    let drop = GpsDropouts {
        mean_interval_s: 60.0,
        mean_duration_s: 5.0,
        drift_m_per_sqrt_s: 0.5,
    };
    let (mut lost, mut total, mut losses) = (0usize, 0usize, 0usize);
    let mut drift_at_end = Vec::new();
    for seed in 0..4 {
        let mut v = hovering(VehicleDisturbances {
            gps_dropouts: Some(drop),
            seed,
            ..VehicleDisturbances::default()
        });
        let mut was = true;
        let mut last_err = Vector3::zeros();
        for _ in 0..(3000.0 / DT) as usize {
            v.step(DT);
            let fix = v.gps_fix();
            if !fix {
                lost += 1;
                last_err = v.position_error();
            }
            if was && !fix {
                losses += 1;
            }
            if !was && fix {
                drift_at_end.push(last_err.xy().norm());
                // The estimator resets onto the fix.
                assert!(v.position_error().norm() < 1e-9);
            }
            was = fix;
            total += 1;
        }
    }
    let frac = lost as f64 / total as f64;
    assert!((frac / (5.0 / 65.0) - 1.0).abs() < 0.35, "lost {frac}");
    let rate = losses as f64 / (4.0 * 3000.0);
    assert!((rate * 65.0 - 1.0).abs() < 0.3, "losses per s {rate}");
    // A random walk of 0.5 m/sqrt(s) over ~5 s: about 1.6 m (2 axes).
    let mean_drift = drift_at_end.iter().sum::<f64>() / drift_at_end.len() as f64;
    assert!((0.5..3.0).contains(&mean_drift), "drift {mean_drift}");
}

#[test]
fn barometer_drifts_at_its_rate() {
    let rate = 0.2;
    let mut ends = Vec::new();
    for seed in 0..40 {
        let mut v = hovering(VehicleDisturbances {
            baro: Some(BaroDrift {
                rate_m_per_min: rate,
            }),
            seed,
            ..VehicleDisturbances::default()
        });
        for _ in 0..(600.0 / 0.1) as usize {
            v.step(0.1);
        }
        let e = v.position_error();
        assert_eq!((e.x, e.y), (0.0, 0.0));
        ends.push(e.z);
    }
    // After 10 minutes: deviation rate * sqrt(10).
    let sd = rms(&ends);
    let expected = rate * 10f64.sqrt();
    assert!((sd / expected - 1.0).abs() < 0.3, "{sd} vs {expected}");
}

#[test]
fn telemetry_runs_at_px4_rates_and_reports_fix_losses() {
    let mut realism = Realism::field();
    realism.vehicle.gps_dropouts = Some(GpsDropouts {
        mean_interval_s: 20.0,
        mean_duration_s: 4.0,
        drift_m_per_sqrt_s: 0.3,
    });
    let params = AutopilotParams {
        stream_intervals: realism.vehicle.telemetry.clone().unwrap().stream_intervals,
        vehicle: VehicleParams {
            disturbances: VehicleDisturbances::from_realism(&realism, 9),
            ..VehicleParams::default()
        },
        ..AutopilotParams::default()
    };
    let mut ap = Autopilot::new(params, 1.7e9);
    let mut msgs = Vec::new();
    let mut fix = Vec::new();
    let mut t = 0.0;
    for _ in 0..(120.0 / DT) as usize {
        t += DT;
        let out = ap.step(t, DT);
        fix.push(ap.vehicle().gps_fix());
        msgs.extend(out.into_iter().map(|m| (t, m, ap.vehicle().gps_fix())));
    }
    let count = |id: u32| msgs.iter().filter(|(_, m, _)| m.message_id() == id).count();
    // PX4 MAVLINK_MODE_NORMAL: ATTITUDE 15 Hz, LOCAL_POSITION_NED 1 Hz,
    // GIMBAL_DEVICE_ATTITUDE_STATUS 1 Hz (the defaults were 10, 5, 5).
    let attitude = count(30) as f64 / 120.0;
    assert!((attitude - 15.0).abs() < 0.5, "attitude {attitude} Hz");
    assert!((count(32) as f64 / 120.0 - 1.0).abs() < 0.05);
    assert!((count(285) as f64 / 120.0 - 1.0).abs() < 0.05);
    // GLOBAL_POSITION_INT at 5 Hz while the fix holds, none while lost.
    let lost_s = fix.iter().filter(|f| !**f).count() as f64 * DT;
    assert!(lost_s > 5.0, "the fix was lost for {lost_s} s only");
    assert!(msgs.iter().all(|(_, m, f)| *f || m.message_id() != 33));
    let gpi = count(33) as f64 / (120.0 - lost_s);
    assert!((gpi - 5.0).abs() < 0.3, "gpi {gpi} Hz");
    // GPS_RAW_INT says so.
    for (_, m, f) in &msgs {
        if let MavMessage::GPS_RAW_INT(d) = m {
            let expected = if *f {
                GpsFixType::GPS_FIX_TYPE_3D_FIX
            } else {
                GpsFixType::GPS_FIX_TYPE_NO_FIX
            };
            assert_eq!(d.fix_type, expected);
        }
    }
}

/// The reported attitude's error (`ahrs`): none in `ideal`; in `field` a
/// slow heading error of about its 1.5 degrees and a tilt error of about
/// its 0.3 over ten minutes, moving under 0.1 degrees between two frames (what the
/// SLAM's telemetry aid relies on: the turn between frames is reported far
/// better than the attitude itself).
#[test]
fn the_reported_attitude_errs_slowly_by_its_sigmas() {
    let ideal = SensorErrors::new(&VehicleDisturbances::from_realism(
        &Realism::parse("ideal").unwrap(),
        7,
    ));
    assert_eq!(ideal.attitude_error_deg(), Vector3::zeros());
    let field = Realism::parse("field").unwrap();
    let mut yaw = Vec::new();
    let mut tilt = Vec::new();
    let mut step_yaw = Vec::new();
    for seed in 0..4 {
        let mut s = SensorErrors::new(&VehicleDisturbances::from_realism(&field, seed));
        let dt = 1.0 / 15.0;
        let mut last = s.attitude_error_deg();
        for k in 1..=(600.0 / dt) as usize {
            s.step(k as f64 * dt, dt);
            let e = s.attitude_error_deg();
            if k as f64 * dt > 120.0 {
                yaw.push(e.z);
                tilt.push(e.x);
                tilt.push(e.y);
                step_yaw.push(e.z - last.z);
            }
            last = e;
        }
    }
    let (y, t, d) = (rms(&yaw), rms(&tilt), rms(&step_yaw));
    println!("heading error rms {y:.2} deg, tilt {t:.2} deg, frame to frame {d:.3} deg");
    assert!((0.8..2.4).contains(&y), "heading {y}");
    assert!((0.15..0.5).contains(&t), "tilt {t}");
    // The slow error walks 1.5 * sqrt(2 dt / 60 s) = 0.07 degrees a frame.
    assert!(d < 0.1, "frame to frame {d}");
}
