//! The robust map → NED Sim(3): recovery through noise and outliers,
//! incremental updates, orientation refinement, the mount's offsets learned,
//! refusals.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::geo::{
    AlignParams, GeoError, Geodetic, Georeference, LocalFrame, MountOffset, MountParams,
    VehicleState, convert_target, ned_from_cam,
};
use shotpilot::geometry::Sim3;

fn gauss(rng: &mut SmallRng) -> f64 {
    // Box-Muller.
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

fn truth() -> Sim3 {
    // ned <- map: a monocular map about 1/12 of the world's size.
    Sim3::new(
        UnitQuaternion::from_euler_angles(0.4, -0.7, 2.6),
        Vector3::new(12.0, -30.0, -25.0),
        12.3,
    )
}

/// A lawn-mower flight at two altitudes: NED camera positions.
fn flight(n: usize) -> Vec<Point3<f64>> {
    (0..n)
        .map(|i| {
            let u = i as f64 / n as f64;
            let lane = (u * 6.0).floor();
            let along = (u * 6.0).fract() * 60.0;
            let x = if lane as i64 % 2 == 0 {
                along
            } else {
                60.0 - along
            };
            Point3::new(
                x - 30.0,
                lane * 8.0 - 20.0,
                if u < 0.5 { -15.0 } else { -25.0 },
            )
        })
        .collect()
}

#[test]
fn recovers_a_known_sim3_through_noise_and_20_percent_outliers() {
    let mut rng = SmallRng::seed_from_u64(11);
    let t = truth();
    let inv = t.inverse();
    let noise = 0.05;
    let mut geo = Georeference::new(AlignParams {
        refine_with_orientations: false,
        ..AlignParams::default()
    });
    let ned = flight(200);
    let mut outliers = 0;
    for (i, p) in ned.iter().enumerate() {
        let mut p_map = inv.transform_point(p);
        if i % 5 == 2 {
            // 20% gross errors: a keyframe misplaced by 3 to 20 m (NED).
            let dir = Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)).normalize();
            p_map += inv.transform_vector(&(dir * rng.random_range(3.0..20.0)));
            outliers += 1;
        }
        let p_noisy = p + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * noise;
        geo.add_pair(i as u64, p_map, p_noisy, i as f64 * 0.5)
            .unwrap();
    }
    let fit = geo.fit().unwrap();
    let s = fit.ned_from_map;
    let scale_err = (s.scale / t.scale - 1.0).abs();
    let rot_err = s.rotation.angle_to(&t.rotation).to_degrees();
    let q = fit.quality;
    println!(
        "scale rel err {scale_err:.2e}, rotation err {rot_err:.4} deg, rms {:.4} m, inliers {}/{} ({} outliers planted), iterations {}, spread {:?}",
        q.rms_m, q.inliers, q.pairs, outliers, q.iterations, q.spread_m2
    );
    assert!(scale_err < 1e-3, "scale error {scale_err}");
    assert!(rot_err < 0.05, "rotation error {rot_err} deg");
    assert_eq!(q.inliers, 160, "every clean pair and no outlier");
    assert!(fit.inlier_ids.iter().all(|id| id % 5 != 2));
    // The residual is the noise: E|n| for 3D Gaussian is sqrt(3)*sigma.
    assert!(
        q.rms_m > 0.7 * 3f64.sqrt() * noise && q.rms_m < 1.3 * 3f64.sqrt() * noise,
        "rms {}",
        q.rms_m
    );
    // The map origin lands where the truth puts it.
    let o = Point3::new(0.3, -0.2, 0.5);
    assert!((s.transform_point(&o) - t.transform_point(&o)).norm() < 0.05);
}

#[test]
fn updates_incrementally_and_repeats_with_its_seed() {
    let t = truth();
    let inv = t.inverse();
    let mut rng = SmallRng::seed_from_u64(5);
    let ned = flight(120);
    let mut geo = Georeference::new(AlignParams::default());
    let mut first_ok = None;
    for (i, p) in ned.iter().enumerate() {
        let p_noisy = p + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.03;
        geo.add_pair(i as u64, inv.transform_point(p), p_noisy, i as f64)
            .unwrap();
        if let Ok(fit) = geo.fit() {
            first_ok.get_or_insert(i);
            assert!(
                (fit.ned_from_map.scale / t.scale - 1.0).abs() < 0.02,
                "at {i}"
            );
        }
    }
    let first_ok = first_ok.expect("a fit at some point");
    assert!(
        first_ok > 5 && first_ok < 40,
        "first fit after {first_ok} keyframes"
    );
    let a = geo.fit().unwrap();
    // Unchanged: the same fit, no work.
    assert_eq!(geo.fit().unwrap(), a);
    // A re-added keyframe (moved by bundle adjustment) replaces its pair.
    geo.add_pair(3, inv.transform_point(&ned[3]), ned[3], 3.0)
        .unwrap();
    assert_eq!(geo.pairs().len(), 120);
    assert!(geo.remove(4) && !geo.remove(4));
    let b = geo.fit().unwrap();
    assert!((b.ned_from_map.scale - a.ned_from_map.scale).abs() < 1e-3 * a.ned_from_map.scale);
    // The warm start converges at once.
    assert!(
        b.quality.iterations < 20,
        "{} iterations",
        b.quality.iterations
    );
}

#[test]
fn orientations_refine_the_rotation() {
    let t = truth();
    let inv = t.inverse();
    let mut rng = SmallRng::seed_from_u64(9);
    // A short, nearly planar flight: positions alone fix the rotation about
    // the plane's normal poorly at 0.15 m noise.
    let ned: Vec<Point3<f64>> = (0..40)
        .map(|i| {
            let a = i as f64 * 0.15;
            Point3::new(6.0 * a.cos(), 4.0 * a.sin(), -20.0 + 0.2 * (i % 3) as f64)
        })
        .collect();
    let mut with = Georeference::new(AlignParams {
        position_sigma_m: 0.15,
        orientation_sigma_deg: 0.5,
        min_extent_m: 1.0,
        min_lateral_m: 0.5,
        ..AlignParams::default()
    });
    let mut without = Georeference::new(AlignParams {
        refine_with_orientations: false,
        min_extent_m: 1.0,
        min_lateral_m: 0.5,
        ..AlignParams::default()
    });
    for (i, p) in ned.iter().enumerate() {
        let ned_from_cam_rot =
            UnitQuaternion::from_euler_angles(0.1 * i as f64, -0.5, 0.3 * i as f64);
        let ned_noise = UnitQuaternion::from_scaled_axis(
            Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.5f64.to_radians(),
        );
        let ned_from_cam = Isometry3::from_parts(
            Translation3::from(
                p.coords + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.15,
            ),
            ned_noise * ned_from_cam_rot,
        );
        let map_from_cam = Isometry3::from_parts(
            Translation3::from(inv.transform_point(p).coords),
            inv.rotation * ned_from_cam_rot,
        );
        with.add_keyframe(i as u64, &map_from_cam, &ned_from_cam, None, i as f64)
            .unwrap();
        without
            .add_pair(
                i as u64,
                map_from_cam.translation.vector.into(),
                ned_from_cam.translation.vector.into(),
                i as f64,
            )
            .unwrap();
    }
    let a = with.fit().unwrap();
    let b = without.fit().unwrap();
    let ea = a.ned_from_map.rotation.angle_to(&t.rotation).to_degrees();
    let eb = b.ned_from_map.rotation.angle_to(&t.rotation).to_degrees();
    println!(
        "rotation error with orientations {ea:.3} deg (rotation rms {:.3} deg), positions only {eb:.3} deg",
        a.quality.rotation_rms_deg.unwrap_or(f64::NAN)
    );
    assert!(ea < 0.3, "{ea}");
    assert!(ea < eb, "{ea} vs {eb}");
    let rr = a
        .quality
        .rotation_rms_deg
        .expect("rotation residual reported");
    assert!(
        rr > 0.3 && rr < 1.3,
        "rotation rms {rr} deg at 0.5 deg per axis noise"
    );
}

#[test]
fn refuses_too_little_motion_and_collinear_motion() {
    let t = truth();
    let inv = t.inverse();
    let params = AlignParams::default();
    // Hovering within 1 m.
    let mut geo = Georeference::new(params.clone());
    for i in 0..30 {
        let a = i as f64 * 0.7;
        let p = Point3::new(0.8 * a.cos(), 0.8 * a.sin(), -10.0 + 0.3 * a.sin());
        geo.add_pair(i, inv.transform_point(&p), p, i as f64)
            .unwrap();
    }
    match geo.fit() {
        Err(GeoError::TooLittleMotion { extent_m, needed_m }) => {
            assert!(extent_m < 1.0 && needed_m == params.min_extent_m)
        }
        other => panic!("expected TooLittleMotion, got {other:?}"),
    }
    // A straight 50 m line with 10 cm of wobble.
    let mut geo = Georeference::new(params.clone());
    let mut rng = SmallRng::seed_from_u64(3);
    for i in 0..30 {
        let s = i as f64 * 50.0 / 29.0;
        let p = Point3::new(0.6 * s, 0.8 * s, -10.0)
            + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.1;
        geo.add_pair(i, inv.transform_point(&p), p, i as f64)
            .unwrap();
    }
    match geo.fit() {
        Err(GeoError::Collinear {
            lateral_m, ratio, ..
        }) => {
            assert!(lateral_m < 0.2 && ratio < 0.02, "{lateral_m} {ratio}")
        }
        other => panic!("expected Collinear, got {other:?}"),
    }
    // Too few pairs.
    let mut geo = Georeference::new(params);
    for i in 0..3 {
        let p = Point3::new(i as f64 * 10.0, (i * i) as f64 * 5.0, -10.0);
        geo.add_pair(i, inv.transform_point(&p), p, 0.0).unwrap();
    }
    assert!(matches!(
        geo.fit(),
        Err(GeoError::NotEnoughPairs {
            found: 3,
            needed: 6
        })
    ));
    assert!(
        geo.add_pair(9, Point3::new(f64::NAN, 0.0, 0.0), Point3::origin(), 0.0)
            .is_err()
    );
}

/// Culling can leave a georeference's pairs too thin to refit (one
/// straight lane): the last fit is kept while those pairs agree with it,
/// and dropped when they contradict it.
#[test]
fn keeps_the_last_fit_when_culling_leaves_too_little_motion() {
    let t = truth();
    let inv = t.inverse();
    let mut geo = Georeference::new(AlignParams {
        refine_with_orientations: false,
        ..AlignParams::default()
    });
    // One straight lane only: refused, nothing to hold yet.
    let ned = flight(120);
    let lane: Vec<u64> = (0..20).collect();
    for &i in &lane {
        let p = ned[i as usize];
        geo.add_pair(i, inv.transform_point(&p), p, i as f64)
            .unwrap();
    }
    assert!(matches!(geo.fit(), Err(GeoError::Collinear { .. })));
    assert!(geo.held().is_none());
    // The whole flight: fitted.
    for (i, p) in ned.iter().enumerate().skip(20) {
        geo.add_pair(i as u64, inv.transform_point(p), *p, i as f64)
            .unwrap();
    }
    let fitted = geo.fit().unwrap();
    assert!(geo.held().is_none());
    assert!((fitted.ned_from_map.scale / t.scale - 1.0).abs() < 1e-6);
    // Culled down to the first lane: the refit is refused, the last fit
    // is kept and says why.
    for i in 20..120 {
        assert!(geo.remove(i));
    }
    let held = geo.fit().unwrap();
    assert_eq!(held.ned_from_map.scale, fitted.ned_from_map.scale);
    assert!(
        matches!(geo.held(), Some(GeoError::Collinear { .. })),
        "{:?}",
        geo.held()
    );
    // The lane's NED side moved 5 m (the map was rebuilt under it, or a
    // GPS glitch): the pairs contradict the last fit, which is not kept.
    for &i in &lane {
        let p = ned[i as usize] + Vector3::new(5.0, 0.0, 0.0);
        geo.add_pair(i, inv.transform_point(&ned[i as usize]), p, i as f64)
            .unwrap();
    }
    assert!(matches!(geo.fit(), Err(GeoError::Collinear { .. })));
    assert!(geo.held().is_none());
}

#[test]
fn refuses_when_the_pairs_do_not_agree() {
    let mut rng = SmallRng::seed_from_u64(2);
    let mut geo = Georeference::new(AlignParams::default());
    for i in 0..40 {
        let p = Point3::new(
            rng.random_range(-30.0..30.0),
            rng.random_range(-30.0..30.0),
            rng.random_range(-30.0..-5.0),
        );
        let q = Point3::new(
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
            rng.random_range(-3.0..3.0),
        );
        geo.add_pair(i, q, p, 0.0).unwrap();
    }
    assert!(matches!(geo.fit(), Err(GeoError::TooFewInliers { .. })));
}

#[test]
fn a_drifting_gnss_bias_is_fitted_on_the_newest_pairs() {
    // A 400 s flight whose GNSS height bias drifts 5 m (a Gauss-Markov
    // bias of 2 m over 300 s moves about that much): the pairs do not
    // agree as a whole, each stretch of the flight does. The vehicle flies
    // by its GNSS as it reads now, so the fit must agree with the newest.
    let mut rng = SmallRng::seed_from_u64(23);
    let t = truth();
    let inv = t.inverse();
    let ned = flight(200);
    let mut geo = Georeference::new(AlignParams {
        refine_with_orientations: false,
        ..AlignParams::default()
    });
    let mut pairs = Vec::new();
    for (i, p) in ned.iter().enumerate() {
        let time = i as f64 * 2.0;
        let bias = Vector3::new(0.0, 0.0, -5.0 * time / 400.0);
        let read =
            p + bias + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.05;
        let p_map = inv.transform_point(p);
        geo.add_pair(i as u64, p_map, read, time).unwrap();
        pairs.push((p_map, read));
    }
    // Every pair at once: refused, they disagree.
    let all = shotpilot::geo::align::fit_pairs(geo.pairs(), geo.params(), None, 1);
    assert!(
        matches!(all, Err(GeoError::TooFewInliers { .. })),
        "{all:?}"
    );
    let fit = geo.fit().expect("the newest pairs agree");
    let q = fit.quality;
    // The newest 20 keyframes are where the GNSS now says they are.
    let worst = pairs[180..]
        .iter()
        .map(|(m, read)| (fit.ned_from_map.transform_point(m) - read).norm())
        .fold(0.0, f64::max);
    println!(
        "fitted on the newest {} pairs ({} set aside), {} inliers, rms {:.3} m; newest 20 within {worst:.3} m of the GNSS",
        q.pairs, q.set_aside, q.inliers, q.rms_m
    );
    assert!(q.set_aside > 0 && q.pairs + q.set_aside == 200, "{q:?}");
    // Inliers of the fit, within its 0.5 m threshold of the GNSS now.
    assert!(
        (180..200).all(|id| fit.inlier_ids.contains(&id)),
        "{:?}",
        fit.inlier_ids
    );
    assert!(
        worst < 0.5,
        "the newest keyframes are {worst} m off the GNSS"
    );
}

#[test]
fn estimates_a_time_offset_from_keyframe_velocities() {
    let t = truth();
    let inv = t.inverse();
    let mut rng = SmallRng::seed_from_u64(17);
    // Lanes flown back and forth at 4 m/s; the NED positions were looked up
    // 0.12 s late: p(t + 0.12) = p(t) + v·0.12.
    let offset = 0.12;
    let mut geo = Georeference::new(AlignParams::default());
    let mut plain = Georeference::new(AlignParams {
        estimate_time_offset: false,
        ..AlignParams::default()
    });
    let ned = flight(150);
    for (i, p) in ned.iter().enumerate() {
        let u = i as f64 / 150.0;
        let lane = (u * 6.0).floor() as i64;
        let v = Vector3::new(if lane % 2 == 0 { 4.0 } else { -4.0 }, 0.0, 0.0);
        let looked_up =
            p + v * offset + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.02;
        let map_from_cam = Isometry3::from_parts(
            Translation3::from(inv.transform_point(p).coords),
            UnitQuaternion::identity(),
        );
        let ned_from_cam = Isometry3::from_parts(Translation3::from(looked_up.coords), t.rotation);
        geo.add_keyframe(i as u64, &map_from_cam, &ned_from_cam, Some(v), i as f64)
            .unwrap();
        plain
            .add_pair(i as u64, inv.transform_point(p), looked_up, i as f64)
            .unwrap();
    }
    let a = geo.fit().unwrap();
    let b = plain.fit().unwrap();
    let e = a.quality.time_offset_s.expect("estimated");
    println!(
        "time offset {e:.4} s (truth {offset}): rms {:.3} m, {} / {} inliers; without: rms {:.3} m, {} inliers",
        a.quality.rms_m, a.quality.inliers, a.quality.pairs, b.quality.rms_m, b.quality.inliers
    );
    assert!((e - offset).abs() < 0.005, "{e}");
    assert!(a.quality.rms_m < 0.06, "{}", a.quality.rms_m);
    assert_eq!(a.quality.inliers, 150);
    // Without the estimate the lanes flown one way disagree with the others
    // by 2·|v|·e = 0.96 m: about half of them are lost.
    assert!(b.quality.inliers < 110, "{}", b.quality.inliers);
    assert!((a.ned_from_map.scale / t.scale - 1.0).abs() < 1e-3);
}

fn hover(p: &Point3<f64>, heading_deg: f64, pitch_deg: f64) -> VehicleState {
    crate::geo_conventions::state(p.coords, heading_deg, pitch_deg)
}

/// A camera mounted 1 deg lower and 0.7 deg to the right of what the
/// gimbal reports (the scenario's calibration errors): the fit learns both
/// offsets from the keyframes' attitudes, keeps its rotation where the
/// positions put it, and a target converted through it is flown with the
/// camera looking where the target asks.
#[test]
fn the_mount_offsets_are_learned_and_the_target_corrected() {
    let t = truth();
    let inv = t.inverse();
    let rng = SmallRng::seed_from_u64(21);
    let reported = MountParams::default();
    let true_offset = MountOffset {
        pitch_deg: -1.0,
        yaw_deg: 0.7,
        ..Default::default()
    };
    let real = reported.corrected(&true_offset);
    let ned = flight(150);
    let fit = |estimate_mount: bool| {
        let mut geo = Georeference::new(AlignParams {
            estimate_mount,
            ..AlignParams::default()
        });
        let mut rng = rng.clone();
        for (i, p) in ned.iter().enumerate() {
            // Headings round the compass, the gimbal between -20 and -90.
            let heading = (i as f64 * 37.0) % 360.0 - 180.0;
            let pitch = -20.0 - (i as f64 * 13.0) % 70.0;
            let state = hover(p, heading, pitch);
            let camera = ned_from_cam(&state, &real);
            let slam_noise = UnitQuaternion::from_scaled_axis(
                Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng))
                    * 0.3f64.to_radians(),
            );
            let map_from_cam = Isometry3::from_parts(
                Translation3::from(
                    inv.transform_point(&Point3::from(camera.translation.vector))
                        .coords,
                ),
                inv.rotation * slam_noise * camera.rotation,
            );
            let mut telemetry = ned_from_cam(&state, &reported);
            telemetry.translation.vector +=
                Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * 0.1;
            geo.add_keyframe(i as u64, &map_from_cam, &telemetry, None, i as f64)
                .unwrap();
        }
        geo.fit().unwrap()
    };
    let learned = fit(true);
    let plain = fit(false);
    let o = learned.mount_offset.expect("offsets learned");
    let rot_learned = learned
        .ned_from_map
        .rotation
        .angle_to(&t.rotation)
        .to_degrees();
    let rot_plain = plain
        .ned_from_map
        .rotation
        .angle_to(&t.rotation)
        .to_degrees();
    println!(
        "learned pitch {:.3} deg, yaw {:.3} deg from {} pairs; rotation error {rot_learned:.3} deg \
         (without learning {rot_plain:.3} deg), rotation rms {:.3} vs {:.3} deg",
        o.pitch_deg,
        o.yaw_deg,
        o.pairs,
        learned.quality.rotation_rms_deg.unwrap_or(f64::NAN),
        plain.quality.rotation_rms_deg.unwrap_or(f64::NAN),
    );
    assert!(plain.mount_offset.is_none());
    assert_eq!(o.pairs, 150);
    assert!((o.pitch_deg - true_offset.pitch_deg).abs() < 0.1, "{o:?}");
    assert!((o.yaw_deg - true_offset.yaw_deg).abs() < 0.1, "{o:?}");
    // The rotation stays where the positions put it, and the attitudes
    // agree with the map to their noise (0.3 deg per axis: 0.52 deg RMS).
    assert!(rot_learned < 0.1, "{rot_learned}");
    let rms = |a: &shotpilot::geo::GeoAlignment| a.quality.rotation_rms_deg.unwrap_or(f64::NAN);
    assert!(rms(&learned) < 0.65, "{}", rms(&learned));
    assert!(rms(&plain) > 1.0, "{}", rms(&plain));

    // A shot in the map: the camera the vehicle really flies, at the
    // commanded yaw and pitch, looks within 0.1 deg of it; without the
    // offsets learned it misses by the calibration error.
    let frame = LocalFrame::new(Geodetic {
        lat_deg: 47.397_742,
        lon_deg: 8.545_594,
        alt_m: 488.0,
    });
    let wanted = ned_from_cam(&hover(&Point3::new(5.0, 3.0, -18.0), 63.0, -47.0), &real);
    let map_pose = Isometry3::from_parts(
        Translation3::from(
            inv.transform_point(&Point3::from(wanted.translation.vector))
                .coords,
        ),
        inv.rotation * wanted.rotation,
    );
    let miss = |alignment: &shotpilot::geo::GeoAlignment| {
        let target = convert_target(alignment, &map_pose, &frame, &reported).unwrap();
        let flown = ned_from_cam(
            &hover(
                &Point3::from(target.p_ned_vehicle),
                target.yaw_deg,
                target.gimbal_pitch_deg,
            ),
            &real,
        );
        (flown.rotation * Vector3::z())
            .angle(&(wanted.rotation * Vector3::z()))
            .to_degrees()
    };
    let (m_learned, m_plain) = (miss(&learned), miss(&plain));
    println!(
        "optical axis off by {m_learned:.3} deg with the offsets learned, {m_plain:.3} without"
    );
    assert!(m_learned < 0.1, "{m_learned}");
    assert!(m_plain > 0.8, "{m_plain}");
}
