//! The mount's offsets learned on real maps (`../shared/data`, skipped with
//! a message when absent): keyframes of the SLAM's own map of a real
//! sequence, paired with the sequence's ground-truth camera poses standing
//! in for telemetry. With the true attitude reported, the georeference must
//! learn no offset the map's own rotation errors invent (a wrong pass would
//! turn every shot); with a camera mounted 1 deg lower and 0.7 deg to the
//! right of what is reported, it must learn those; and either way the
//! standard deviations it states must cover its error.

use std::sync::Arc;

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, UnitQuaternion, Vector3};
use shotpilot::eval::associate;
use shotpilot::geo::{AlignParams, Georeference, MountOffset};
use shotpilot::slam::{self, Slam};
use shotpilot::video::dataset::Dataset;

use crate::data_support;

/// The sequences' world frame (x right, y down, z forward at the first
/// camera) as NED (north forward, east right, down down).
fn ned_from_world() -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::new(
        0.0, 0.0, 1.0, //
        1.0, 0.0, 0.0, //
        0.0, 1.0, 0.0,
    )))
}

/// The offsets the georeference learns from `name`'s map with telemetry
/// reporting the true camera turned back by `planted`.
fn learned(name: &str, params: AlignParams, planted: &[MountOffset]) -> Option<Vec<MountOffset>> {
    let dir = data_support::shared_data(name)?;
    let ds = Dataset::open(&dir).expect("the sequence opens");
    let mut p = slam::Params {
        sequential: true,
        ..Default::default()
    };
    p.tracking.seed = 1;
    let mut s = Slam::new(ds.camera, p).expect("a SLAM");
    for f in ds.frames() {
        let f = f.expect("a frame");
        s.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    let run = s.finish();
    let kfs = run.keyframe_trajectory();
    let gt = ds.groundtruth.as_ref().expect("ground truth");
    let matches = associate(gt, &kfs, 0.02);
    let r = ned_from_world();
    let out = planted
        .iter()
        .map(|o| {
            let mut geo = Georeference::new(params.clone());
            for (i, &(g, k)) in matches.iter().enumerate() {
                let truth = gt.poses[g].world_from_cam;
                let turn_back = |q: UnitQuaternion<f64>| {
                    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -o.yaw_deg.to_radians())
                        * q
                        * UnitQuaternion::from_axis_angle(
                            &Vector3::x_axis(),
                            -o.pitch_deg.to_radians(),
                        )
                };
                let telemetry = Isometry3::from_parts(
                    (r * Point3::from(truth.translation.vector)).coords.into(),
                    turn_back(r * truth.rotation),
                );
                geo.add_keyframe(i as u64, &kfs.poses[k].world_from_cam, &telemetry, None, kfs.poses[k].t)
                    .expect("a pair");
            }
            let fit = geo.fit().expect("the georeference fits");
            let m = fit.mount_offset.expect("offsets learned");
            println!(
                "{name}: planted pitch {:+.2} yaw {:+.2} deg -> learned {:+.3} ± {:.3} / {:+.3} ± {:.3} deg from {} keyframes; rms {:.3} m, rotation rms {:.3} deg, inliers {}/{}",
                o.pitch_deg,
                o.yaw_deg,
                m.pitch_deg,
                m.pitch_sigma_deg,
                m.yaw_deg,
                m.yaw_sigma_deg,
                m.pairs,
                fit.quality.rms_m,
                fit.quality.rotation_rms_deg.unwrap_or(f64::NAN),
                fit.quality.inliers,
                fit.quality.pairs,
            );
            m
        })
        .collect();
    Some(out)
}

/// Learns with no offset and with one planted; every learned offset must
/// lie within three of its stated standard deviations of the truth, and
/// within `tolerance_deg` when given.
fn check(name: &str, params: AlignParams, tolerance_deg: Option<f64>) {
    let planted = [
        MountOffset::default(),
        MountOffset {
            pitch_deg: -1.0,
            yaw_deg: 0.7,
            ..Default::default()
        },
    ];
    let Some(got) = learned(name, params, &planted) else {
        return;
    };
    for (p, g) in planted.iter().zip(&got) {
        let (ep, ey) = (
            (g.pitch_deg - p.pitch_deg).abs(),
            (g.yaw_deg - p.yaw_deg).abs(),
        );
        assert!(
            ep <= 3.0 * g.pitch_sigma_deg && ey <= 3.0 * g.yaw_sigma_deg,
            "{name}: planted {p:?}, learned {g:?}: outside 3 sigma"
        );
        if let Some(t) = tolerance_deg {
            assert!(ep < t && ey < t, "{name}: planted {p:?}, learned {g:?}");
        }
    }
}

/// KITTI 07: a car's forward camera, ~98 m with a left turn, RTK/INS truth.
#[test]
fn kitti_learns_the_planted_mount_offsets_and_none_of_its_own() {
    check(
        "kitti07_first160",
        AlignParams {
            inlier_threshold_m: 2.0,
            position_sigma_m: 0.3,
            // A street: 2.8 m across 28 m along.
            min_lateral_ratio: 0.05,
            ..AlignParams::default()
        },
        Some(0.3),
    );
}

/// TUM teddy: a hand-held camera round an object, motion-capture truth. A
/// 36 cm arc fixes the offsets to about half a degree: they must say so.
#[test]
fn teddy_learns_the_planted_mount_offsets_and_none_of_its_own() {
    check(
        "tum_fr3_teddy_100",
        AlignParams {
            inlier_threshold_m: 0.05,
            position_sigma_m: 0.01,
            min_extent_m: 0.1,
            // An arc of the orbit: 1 cm across 36 cm along.
            min_lateral_m: 0.005,
            min_lateral_ratio: 0.02,
            ..AlignParams::default()
        },
        None,
    );
}
