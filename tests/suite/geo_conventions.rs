//! Frame conventions of `geo`: a known NED pose gives the known latitude,
//! longitude, altitude, yaw and pitch; map → NED → WGS84 → NED round trips.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use shotpilot::geo::{
    GeoAlignment, GeoError, Geodetic, GimbalAngles, LocalFrame, MountParams, VehicleState,
    convert_target, ned_from_cam, target_from_ned,
};
use shotpilot::geometry::Sim3;

const HOME: Geodetic = Geodetic {
    lat_deg: 47.397_742,
    lon_deg: 8.545_594,
    alt_m: 488.0,
};

/// WGS84 radii of curvature at a latitude, computed here from the textbook
/// formulas (meridian M, prime vertical N).
fn radii(lat_deg: f64) -> (f64, f64) {
    let a = 6_378_137.0;
    let f = 1.0 / 298.257_223_563;
    let e2 = f * (2.0 - f);
    let s2 = lat_deg.to_radians().sin().powi(2);
    (
        a * (1.0 - e2) / (1.0 - e2 * s2).powf(1.5),
        a / (1.0 - e2 * s2).sqrt(),
    )
}

/// A level vehicle at `p` with heading and gimbal pitch in degrees.
pub(crate) fn state(p: Vector3<f64>, heading_deg: f64, pitch_deg: f64) -> VehicleState {
    VehicleState {
        time: 0.0,
        p_ned: p,
        v_ned: Vector3::zeros(),
        ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, heading_deg.to_radians()),
        gimbal: GimbalAngles {
            pitch: pitch_deg.to_radians(),
            yaw: 0.0,
        },
    }
}

#[test]
fn a_known_ned_pose_gives_the_known_lat_lon_alt_yaw_pitch() {
    let frame = LocalFrame::new(HOME);
    let mount = MountParams::default();
    let (m, n) = radii(HOME.lat_deg);
    let p = Vector3::new(100.0, 50.0, -30.0);
    let s = state(p, 90.0, -30.0);
    let cam = ned_from_cam(&s, &mount);
    // Heading east, pitched 30 deg down: optical axis (0, cos 30, sin 30),
    // image right = south, image down = (0, -sin 30... ) below the axis.
    let r = cam.rotation;
    let (s30, c30) = 30f64.to_radians().sin_cos();
    assert!((r * Vector3::z() - Vector3::new(0.0, c30, s30)).norm() < 1e-12);
    assert!((r * Vector3::x() - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-12);
    assert!((r * Vector3::y() - Vector3::new(0.0, -s30, c30)).norm() < 1e-12);
    // Lever arm (0.10 forward, 0.08 down) turned east.
    assert!((cam.translation.vector - (p + Vector3::new(0.0, 0.10, 0.08))).norm() < 1e-12);

    let t = target_from_ned(&cam, &frame, &mount).unwrap();
    let dlat = (100.0 / (m + HOME.alt_m)).to_degrees();
    let dlon = (50.0 / ((n + HOME.alt_m) * HOME.lat_deg.to_radians().cos())).to_degrees();
    // Arc vs tangent-plane differences at 112 m are below 1e-4 m.
    let lat_m = (t.lat_deg - HOME.lat_deg - dlat).to_radians() * m;
    let lon_m =
        (t.lon_deg - HOME.lon_deg - dlon).to_radians() * n * HOME.lat_deg.to_radians().cos();
    assert!(lat_m.abs() < 2e-3, "latitude off by {lat_m} m");
    assert!(lon_m.abs() < 2e-3, "longitude off by {lon_m} m");
    // 30 m up plus the plane's rise d^2/(2R) (1 mm at 112 m).
    let rise = (100.0f64 * 100.0 + 50.0 * 50.0) / (2.0 * 6_371_000.0);
    assert!(
        (t.alt_above_home_m - (30.0 + rise)).abs() < 2e-4,
        "{}",
        t.alt_above_home_m
    );
    assert!((t.yaw_deg - 90.0).abs() < 1e-9);
    assert!((t.gimbal_pitch_deg + 30.0).abs() < 1e-9);
    assert!(t.residual_roll_deg.abs() < 1e-9);
    assert!((t.p_ned_vehicle - p).norm() < 1e-12);
    let mission = t.to_mission_target(true);
    assert_eq!(mission.yaw_deg, t.yaw_deg);
    assert_eq!(mission.alt_m, t.alt_above_home_m);

    // Heading north-west (315 deg) straight down: the image's top points
    // north-west.
    let s = state(Vector3::new(-20.0, 10.0, -50.0), -45.0, -90.0);
    let cam = ned_from_cam(&s, &mount);
    let up = cam.rotation * -Vector3::y();
    assert!((up - Vector3::new(1.0, -1.0, 0.0).normalize()).norm() < 1e-12);
    let t = target_from_ned(&cam, &frame, &mount).unwrap();
    assert!((t.yaw_deg - 315.0).abs() < 1e-9, "{}", t.yaw_deg);
    assert!((t.gimbal_pitch_deg + 90.0).abs() < 1e-9);
}

#[test]
fn roll_the_gimbal_cannot_make_is_reported_and_pitch_range_is_enforced() {
    let frame = LocalFrame::new(HOME);
    let mount = MountParams::default();
    let base = ned_from_cam(&state(Vector3::new(5.0, 5.0, -10.0), 30.0, -20.0), &mount);
    // Roll the target by +12 deg about its optical axis.
    let rolled = Isometry3::from_parts(
        base.translation,
        base.rotation * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 12f64.to_radians()),
    );
    let t = target_from_ned(&rolled, &frame, &mount).unwrap();
    assert!(
        (t.residual_roll_deg - 12.0).abs() < 1e-9,
        "{}",
        t.residual_roll_deg
    );
    assert!((t.yaw_deg - 30.0).abs() < 1e-9 && (t.gimbal_pitch_deg + 20.0).abs() < 1e-9);

    // Looking 45 deg up is beyond the default +30 deg.
    let up = ned_from_cam(&state(Vector3::new(0.0, 0.0, -10.0), 0.0, 45.0), &mount);
    match target_from_ned(&up, &frame, &mount) {
        Err(GeoError::PitchOutOfRange {
            pitch_deg, max_deg, ..
        }) => {
            assert!((pitch_deg - 45.0).abs() < 1e-9 && max_deg == 30.0)
        }
        other => panic!("expected a pitch refusal, got {other:?}"),
    }
    // A narrower gimbal refuses -80.
    let narrow = MountParams {
        pitch_min_deg: -60.0,
        ..MountParams::default()
    };
    let down = ned_from_cam(&state(Vector3::new(0.0, 0.0, -10.0), 0.0, -80.0), &mount);
    assert!(matches!(
        target_from_ned(&down, &frame, &narrow),
        Err(GeoError::PitchOutOfRange { .. })
    ));
}

#[test]
fn map_to_ned_to_wgs84_to_ned_round_trips() {
    let frame = LocalFrame::new(HOME);
    let mount = MountParams::default();
    let ned_from_map = Sim3::new(
        UnitQuaternion::from_euler_angles(0.3, -0.2, 2.1),
        Vector3::new(40.0, -25.0, -12.0),
        7.5,
    );
    let alignment = GeoAlignment::given(ned_from_map);
    let mut worst_m: f64 = 0.0;
    let mut worst_deg: f64 = 0.0;
    for i in 0..50 {
        let a = i as f64 * 0.37;
        // A camera pose built from a 2-axis-gimbal NED pose, expressed in the
        // map through the inverse similarity.
        let truth = ned_from_cam(
            &state(
                Vector3::new(80.0 * a.cos(), 60.0 * a.sin(), -15.0 - 2.0 * i as f64),
                (a * 57.0) % 360.0 - 180.0,
                -5.0 - (i as f64 * 1.7) % 85.0,
            ),
            &mount,
        );
        let inv = ned_from_map.inverse();
        let map_from_cam = Isometry3::from_parts(
            Translation3::from(
                inv.transform_point(&Point3::from(truth.translation.vector))
                    .coords,
            ),
            inv.rotation * truth.rotation,
        );
        let t = convert_target(&alignment, &map_from_cam, &frame, &mount).unwrap();
        let back = frame.geodetic_to_ned(&Geodetic {
            lat_deg: t.lat_deg,
            lon_deg: t.lon_deg,
            alt_m: t.alt_m,
        });
        let cam_back = back
            + UnitQuaternion::from_euler_angles(0.0, 0.0, t.yaw_deg.to_radians())
                * Vector3::from(mount.lever_arm_body_m);
        worst_m = worst_m.max((cam_back - truth.translation.vector).norm());
        let rebuilt = ned_from_cam(
            &VehicleState {
                time: 0.0,
                p_ned: back,
                v_ned: Vector3::zeros(),
                ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, t.yaw_deg.to_radians()),
                gimbal: GimbalAngles {
                    pitch: t.gimbal_pitch_deg.to_radians(),
                    yaw: 0.0,
                },
            },
            &mount,
        );
        worst_deg = worst_deg.max(rebuilt.rotation.angle_to(&truth.rotation).to_degrees());
        assert!(t.residual_roll_deg.abs() < 1e-6);
    }
    assert!(worst_m < 1e-6, "position round trip {worst_m} m");
    assert!(worst_deg < 1e-6, "orientation round trip {worst_deg} deg");
}

#[test]
fn params_read_from_toml_with_defaults_for_the_rest() {
    let p: shotpilot::geo::Params = toml::from_str(
        r#"
        [history]
        video_latency_s = 0.18
        [mount]
        lever_arm_body_m = [0.12, 0.0, 0.05]
        lever_arm_frame = "heading"
        pitch_min_deg = -100.0
        [align]
        inlier_threshold_m = 0.8
        "#,
    )
    .unwrap();
    assert_eq!(p.history.video_latency_s, 0.18);
    assert_eq!(
        p.history.max_gap_s,
        shotpilot::geo::HistoryParams::default().max_gap_s
    );
    assert_eq!(p.mount.lever_arm_body_m, [0.12, 0.0, 0.05]);
    assert_eq!(
        p.mount.lever_arm_frame,
        shotpilot::geo::LeverArmFrame::Heading
    );
    assert_eq!(p.align.inlier_threshold_m, 0.8);
    assert!(toml::from_str::<shotpilot::geo::Params>("[align]\nbogus = 1").is_err());
}
