//! Time alignment: interpolation of the telemetry history and its refusals.

use nalgebra::{UnitQuaternion, Vector3};
use shotpilot::geo::{
    GeoError, Geodetic, GimbalAngles, HistoryParams, LocalFrame, TelemetryHistory, capture_time,
};

fn filled(params: HistoryParams) -> TelemetryHistory {
    let mut h = TelemetryHistory::new(params);
    // 5 Hz positions of a straight constant-velocity flight, 10 Hz attitude
    // turning at a constant 20 deg/s with a fixed 5 deg roll, 5 Hz gimbal
    // yaw sweeping across +-180.
    for i in 0..=50 {
        let t = i as f64 * 0.2;
        h.push_position_ned(t, Vector3::new(3.0 * t, -t, -10.0 - 0.5 * t))
            .unwrap();
        h.push_gimbal(
            t,
            GimbalAngles {
                pitch: -0.5 + 0.02 * t,
                yaw: (170.0 + 10.0 * t).to_radians(),
            },
        )
        .unwrap();
    }
    for i in 0..=100 {
        let t = i as f64 * 0.1;
        h.push_attitude(t, attitude(t)).unwrap();
    }
    h
}

fn attitude(t: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(0.0, 0.0, (20.0 * t).to_radians())
        * UnitQuaternion::from_euler_angles(5f64.to_radians(), 0.0, 0.0)
}

#[test]
fn interpolates_position_linearly_attitude_by_slerp_and_angles_the_short_way() {
    let h = filled(HistoryParams::default());
    for t in [0.0, 0.05, 0.33, 1.0, 4.71, 9.99, 10.0] {
        let s = h.lookup(t).unwrap();
        let p = Vector3::new(3.0 * t, -t, -10.0 - 0.5 * t);
        assert!((s.p_ned - p).norm() < 1e-12, "t={t}");
        // Constant-rate rotation about a fixed axis: slerp is exact.
        assert!(s.ned_from_body.angle_to(&attitude(t)) < 1e-9, "t={t}");
        assert!((s.gimbal.pitch - (-0.5 + 0.02 * t)).abs() < 1e-12);
        let want = (170.0 + 10.0 * t).to_radians();
        let d = (s.gimbal.yaw - want).rem_euclid(std::f64::consts::TAU);
        assert!(
            d.min(std::f64::consts::TAU - d) < 1e-9,
            "t={t} yaw {}",
            s.gimbal.yaw
        );
        assert!(s.gimbal.yaw.abs() <= std::f64::consts::PI);
        let dh = (s.heading() - (20.0 * t).to_radians()).rem_euclid(std::f64::consts::TAU);
        assert!(dh.min(std::f64::consts::TAU - dh) < 1e-9, "t={t}");
    }
}

#[test]
fn refuses_outside_the_history_and_across_gaps() {
    let mut h = filled(HistoryParams {
        max_gap_s: 0.3,
        ..HistoryParams::default()
    });
    assert!(matches!(h.lookup(-0.01), Err(GeoError::TooOld { .. })));
    assert!(
        matches!(h.lookup(10.01), Err(GeoError::NotYet { stream: _, newest, .. }) if newest == 10.0)
    );
    // A 1 s hole in the attitude stream.
    for i in 0..=20 {
        let t = 11.0 + i as f64 * 0.1;
        h.push_position_ned(t, Vector3::zeros()).unwrap();
        h.push_gimbal(
            t,
            GimbalAngles {
                pitch: 0.0,
                yaw: 0.0,
            },
        )
        .unwrap();
    }
    h.push_attitude(11.0, attitude(11.0)).unwrap();
    h.push_attitude(13.0, attitude(13.0)).unwrap();
    match h.lookup(12.0) {
        Err(GeoError::Gap {
            stream,
            before,
            after,
            ..
        }) => {
            assert_eq!((stream, before, after), ("attitude", 11.0, 13.0))
        }
        other => panic!("expected a gap, got {other:?}"),
    }
    assert!(h.lookup(f64::NAN).is_err());
    let empty = TelemetryHistory::new(HistoryParams::default());
    assert!(matches!(
        empty.lookup(0.0),
        Err(GeoError::EmptyHistory { .. })
    ));
}

#[test]
fn bounded_history_forgets_the_oldest() {
    let mut h = TelemetryHistory::new(HistoryParams {
        max_age_s: 0.95, // 10 samples at 10 Hz
        ..HistoryParams::default()
    });
    for i in 0..100 {
        let t = i as f64 * 0.1;
        h.push_position_ned(t, Vector3::new(t, 0.0, 0.0)).unwrap();
        h.push_attitude(t, UnitQuaternion::identity()).unwrap();
        h.push_gimbal(
            t,
            GimbalAngles {
                pitch: 0.0,
                yaw: 0.0,
            },
        )
        .unwrap();
    }
    assert_eq!(h.len(), (10, 10, 10));
    assert!(matches!(h.lookup(5.0), Err(GeoError::TooOld { .. })));
    assert!((h.lookup(9.55).unwrap().p_ned.x - 9.55).abs() < 1e-12);
}

#[test]
fn geodetic_positions_and_capture_time() {
    let frame = LocalFrame::new(Geodetic {
        lat_deg: -33.9,
        lon_deg: 151.2,
        alt_m: 30.0,
    });
    let mut h = TelemetryHistory::new(HistoryParams::default());
    let a = frame.ned_to_geodetic(&Vector3::new(10.0, 20.0, -5.0));
    let b = frame.ned_to_geodetic(&Vector3::new(12.0, 24.0, -7.0));
    h.push_position_geodetic(1.0, &a, &frame).unwrap();
    h.push_position_geodetic(1.2, &b, &frame).unwrap();
    h.push_attitude(1.0, UnitQuaternion::identity()).unwrap();
    h.push_attitude(1.2, UnitQuaternion::identity()).unwrap();
    h.push_gimbal(
        1.0,
        GimbalAngles {
            pitch: 0.0,
            yaw: 0.0,
        },
    )
    .unwrap();
    h.push_gimbal(
        1.2,
        GimbalAngles {
            pitch: 0.0,
            yaw: 0.0,
        },
    )
    .unwrap();
    let s = h.lookup(1.1).unwrap();
    assert!((s.p_ned - Vector3::new(11.0, 22.0, -6.0)).norm() < 1e-6);
    let bad = Geodetic {
        lat_deg: f64::NAN,
        ..a
    };
    assert!(h.push_position_geodetic(1.3, &bad, &frame).is_err());

    let p = HistoryParams {
        video_latency_s: 0.12,
        ..HistoryParams::default()
    };
    assert_eq!(capture_time(10.0, Some(9.95), &p), 9.95);
    assert!((capture_time(10.0, None, &p) - 9.88).abs() < 1e-12);
    assert!((capture_time(10.0, Some(f64::NAN), &p) - 9.88).abs() < 1e-12);
}
