//! Shots on the aliasing world: a grid of identical buildings and cars
//! around a car park, built to fool place recognition. Issue 34, part 4: a
//! candidate keyframe that disagrees with the best but has far fewer
//! inliers is left out instead of vetoing
//! ([`shot::GateParams::drop_disagreeing_below`]); this is where that rule
//! could let a wrong place through, so every picture is localised with
//! and without it.
//!
//! What it found (a known gap, printed by the test): a picture of a place
//! the map never saw, whose building is identical to a mapped one, is put
//! at the mapped look-alike, 33-152 m away, with or without the rule
//! (12 of 57 pictures here, 30-71 inliers, up to 4 agreeing candidates:
//! the look-alike's neighbours agree with it). Nothing in one picture
//! tells the two places apart where the map holds only one of them; the
//! share of the local map in view that the pose explains (0-0.11 wrong,
//! 0.03-0.23 for right real photos 10-30 deg off the flown views) and the
//! share of the picture the inliers cover (0.15-0.32 wrong, from 0.18 for
//! right simulator photos) were measured and separate neither. Where both
//! places are mapped the candidates disagree and the shot is refused.
//!
//! The count was 10 with the gate's sigma bound at 2 % / 1 deg; with the
//! bound at 5 % / 2.5 deg (half the error of a wrong shot) and the map's
//! error grown beyond the flown views, 12: the sigma bound refused two
//! look-alikes by chance, not by telling the places apart, while it
//! refused real photos of the right place (teddy_100, 10-30 deg beyond the
//! views: 33 -> 50 of 57 accepted, 0 wrong). With a photo's GPS tag
//! (5 m, every picture localised a third time with one) all 12 are
//! refused, and the candidates near the tag tried beyond the first five
//! (those far from it left out when a pose near it remains) find 3 right
//! places more: 22 right passes with tags, 19 without, 0 wrong.

use std::sync::Arc;

use rand::SeedableRng;

use anyhow::Context;
use nalgebra::Point3;
use shotpilot::eval::{StampedPose, Trajectory, associate};
use shotpilot::geometry::umeyama;
use shotpilot::shot::{self, Localization};
use shotpilot::slam::{self, Slam};
use shotpilot::video::dataset::Dataset;
use shotpilot_sim::world::WorldKind;

use crate::sim_support::render_lap;

/// The sigma of the simulated GPS tags, metres per axis.
const TAG_SIGMA_M: f64 = 5.0;

/// A localisation this far off the truth is a wrong pass: position, % of
/// the distance to what the picture sees (the inliers' median depth).
const WRONG_POSITION_PCT: f64 = 10.0;
/// The same for the orientation, degrees.
const WRONG_ROTATION_DEG: f64 = 5.0;

/// The map: SLAM over the first 55 % of one lap of the aliasing world (the
/// lap goes round the grid and comes back over its start; the map stops
/// before it comes back). The pictures: every 6th frame of the rest, most
/// of them of places the map never saw, among buildings identical to
/// mapped ones, and at the end the return over the mapped start. Each is
/// localised with the default gate, with the disagreeing candidate
/// always vetoing (`drop_disagreeing_below` 0, the rule before issue 34),
/// and with a simulated GPS tag of [`TAG_SIGMA_M`].
/// Asserted: the rule adds no wrong pass (every picture it accepts that
/// the veto refused is right), the pictures of the mapped start are all
/// right, and at most the 12 look-alike passes measured at this commit
/// happen (the known gap above, so that more would fail here); with the
/// tag, no look-alike passes and no right place is lost. About 2 minutes
/// in `--release` (the render and the map).
#[test]
fn the_disagreement_rule_adds_no_wrong_shot_on_the_aliasing_world() -> anyhow::Result<()> {
    let dir = render_lap(WorldKind::Aliasing, "shot_aliasing");
    let ds = Dataset::open(dir.path())?;
    let gt = ds
        .groundtruth
        .clone()
        .context("the render has ground truth")?;
    let n_map = ds.len() * 55 / 100;
    let mut system = Slam::new(
        ds.camera,
        slam::Params {
            sequential: true,
            ..slam::Params::default()
        },
    )?;
    for i in 0..n_map {
        let f = ds.frame(i)?;
        system.process(i as u64, f.timestamp, Arc::new(f.image));
    }
    let map = system.finish().map;
    anyhow::ensure!(
        map.keyframes().count() >= 10,
        "the map has {} keyframes",
        map.keyframes().count()
    );
    // The map in the true world: a Sim(3) on the keyframes' centres.
    let mut kf_traj = Trajectory {
        poses: map
            .keyframes()
            .map(|k| StampedPose {
                t: k.timestamp,
                world_from_cam: k.world_from_cam(),
            })
            .collect(),
    };
    kf_traj.poses.sort_by(|a, b| a.t.total_cmp(&b.t));
    let pairs = associate(&kf_traj, &gt, 0.02);
    let src: Vec<Point3<f64>> = pairs
        .iter()
        .map(|(a, _)| Point3::from(kf_traj.poses[*a].world_from_cam.translation.vector))
        .collect();
    let dst: Vec<Point3<f64>> = pairs
        .iter()
        .map(|(_, b)| Point3::from(gt.poses[*b].world_from_cam.translation.vector))
        .collect();
    let sim = umeyama(&src, &dst, true)?;
    let kf_rmse = (src
        .iter()
        .zip(&dst)
        .map(|(s, d)| (sim.transform_point(s) - d).norm_squared())
        .sum::<f64>()
        / src.len().max(1) as f64)
        .sqrt();
    println!(
        "aliasing map: frames 0-{n_map} of {}, {} keyframes, {} points; keyframe centres vs truth after Sim(3) (scale {:.3}): RMSE {kf_rmse:.3} m",
        ds.len(),
        map.keyframes().count(),
        map.points().count(),
        sim.scale
    );

    let with_rule = shot::LocalizeParams {
        gate: crate::sim_support::gate_from_env()?,
        pnp: crate::sim_support::pnp_from_env()?,
        ..shot::LocalizeParams::default()
    };
    let mut without_rule = with_rule.clone();
    without_rule.gate.drop_disagreeing_below = 0.0;
    // Each picture is also localised with a position prior, as a photo's
    // GPS tag through the georeference gives one: its true camera centre
    // moved by a seeded Gaussian error of TAG_SIGMA_M per axis, into the
    // map's frame.
    let mut tag_rng = rand::rngs::StdRng::seed_from_u64(34);
    let mut wrong = Vec::new();
    let (mut added_by_rule, mut wrong_at_mapped, mut wrong_with_rule) = (Vec::new(), Vec::new(), 0);
    // The lap is about 520 m round and then 60 m over its start again:
    // from nine tenths on, it flies over mapped ground.
    let return_from = ds.len() * 9 / 10;
    let (mut n, mut accepted, mut accepted_old, mut only_with_rule) = (0, 0, 0, 0);
    let (mut right_with_tag, mut right_without_tag, mut wrong_with_tag) = (0, 0, 0);
    let mut refusals: std::collections::BTreeMap<String, usize> = Default::default();
    for i in (n_map..ds.len()).step_by(6) {
        let f = ds.frame(i)?;
        let Some(truth) = gt
            .poses
            .iter()
            .min_by(|a, b| {
                (a.t - f.timestamp)
                    .abs()
                    .total_cmp(&(b.t - f.timestamp).abs())
            })
            .filter(|p| (p.t - f.timestamp).abs() < 0.02)
        else {
            continue;
        };
        n += 1;
        // (localised, wrong) with the rule and with the veto.
        let mut outcomes: Vec<(bool, bool)> = Vec::new();
        let tagged = shot::LocalizeParams {
            position_prior: Some(crate::sim_support::simulated_tag(
                &truth.world_from_cam.translation.vector,
                &sim,
                TAG_SIGMA_M,
                &mut tag_rng,
            )),
            ..with_rule.clone()
        };
        for (label, params) in [
            ("default", &with_rule),
            ("always veto", &without_rule),
            ("gps tag", &tagged),
        ] {
            let outcome = shot::localize(&map, &f.image, None, None, params)?;
            let mut is_wrong = false;
            match &outcome {
                Localization::Localized(p) => {
                    let est = sim.transform_pose(&p.world_from_cam);
                    let pos_m =
                        (est.translation.vector - truth.world_from_cam.translation.vector).norm();
                    let dist_m = p.median_depth * sim.scale;
                    let pos_pct = 100.0 * pos_m / dist_m.max(1e-9);
                    let rot_deg = est
                        .rotation
                        .angle_to(&truth.world_from_cam.rotation)
                        .to_degrees();
                    println!(
                        "frame {i:3} [{label:11}]: localised on keyframe {} ({} inliers, {} agreeing), {pos_m:.2} m ({pos_pct:.1} % of {dist_m:.0} m), {rot_deg:.2} deg off",
                        p.keyframe_id.0, p.inliers, p.agreeing_candidates
                    );
                    if pos_pct > WRONG_POSITION_PCT || rot_deg > WRONG_ROTATION_DEG {
                        is_wrong = true;
                        wrong.push(format!(
                            "frame {i} [{label}]: {pos_m:.2} m ({pos_pct:.1} %), {rot_deg:.2} deg off"
                        ));
                    }
                }
                Localization::NotLocalized { reason } => {
                    println!("frame {i:3} [{label:11}]: refused: {reason}");
                    if label == "default" {
                        let kind = reason.to_string();
                        let kind = kind
                            .split([':', '('])
                            .next()
                            .unwrap_or("")
                            .trim()
                            .to_owned();
                        *refusals.entry(kind).or_default() += 1;
                    }
                }
            }
            outcomes.push((matches!(outcome, Localization::Localized(_)), is_wrong));
        }
        let ((rule_loc, rule_wrong), (veto_loc, veto_wrong)) = (outcomes[0], outcomes[1]);
        let (tag_loc, tag_wrong) = outcomes[2];
        right_with_tag += usize::from(tag_loc && !tag_wrong);
        right_without_tag += usize::from(rule_loc && !rule_wrong);
        wrong_with_tag += usize::from(tag_wrong);
        accepted += usize::from(rule_loc);
        accepted_old += usize::from(veto_loc);
        only_with_rule += usize::from(rule_loc && !veto_loc);
        if rule_wrong && !veto_wrong {
            added_by_rule.push(i);
        }
        // The lap's return over the mapped start: a mapped place.
        if i >= return_from && rule_wrong {
            wrong_at_mapped.push(i);
        }
        wrong_with_rule += usize::from(rule_wrong);
    }
    println!(
        "aliasing pictures: {n}; localised {accepted} (always veto: {accepted_old}; only with the rule: {only_with_rule}); refusals {refusals:?}; wrong passes with the rule {wrong_with_rule}, added by the rule {}",
        added_by_rule.len()
    );
    println!(
        "with a {TAG_SIGMA_M} m GPS tag: {right_with_tag} right passes (without: {right_without_tag}), {wrong_with_tag} wrong"
    );
    println!("wrong passes (with the rule, with the veto and with a tag): {wrong:#?}");
    assert!(n >= 40, "{n} pictures with ground truth");
    assert!(
        added_by_rule.is_empty(),
        "the rule let wrong places through: frames {added_by_rule:?}"
    );
    assert!(
        wrong_at_mapped.is_empty(),
        "pictures of the mapped start put elsewhere: frames {wrong_at_mapped:?}"
    );
    assert!(
        wrong_with_rule <= 12,
        "{wrong_with_rule} look-alike passes (12 at the commit that measured it)"
    );
    // A tag refuses every look-alike, and costs no right place: the
    // candidates near the tag are tried and those far from it left out.
    assert_eq!(wrong_with_tag, 0, "look-alike passes with a GPS tag");
    assert!(
        right_with_tag >= right_without_tag,
        "a tag lost right places: {right_with_tag} right with it, {right_without_tag} without"
    );
    Ok(())
}
