//! `shotpilot features --pairs` as a user runs it on the simulator's
//! footage: the match funnel between consecutive frames, checked against
//! the true motion, and a wrong truth that the check does not agree with.

use std::sync::Arc;

use crate::cli_support::{run_ok, shotpilot};
use crate::sim_support;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, PathSpec};
use shotpilot_sim::world::{World, WorldKind, WorldParams};

/// 45 frames (3 s at 15 frames a second) of the explore flight over a
/// world of `kind`, 10 s after its start.
fn render(kind: WorldKind, prefix: &str) -> tempfile::TempDir {
    let dir = sim_support::render_dir(prefix);
    let world = Arc::new(
        World::generate_with(
            sim_support::SEED,
            &WorldParams {
                kind,
                ..WorldParams::default()
            },
        )
        .unwrap(),
    );
    let explore = CameraPath::explore(&world, PathParams::default());
    let t0 = explore.start() + 10.0;
    let samples = (0..45)
        .map(|i| {
            let t = t0 + f64::from(i) / 15.0;
            (t, explore.world_from_cam(t))
        })
        .collect();
    let path = CameraPath::from_samples(samples).unwrap();
    sim_support::render(world, &path, &PathSpec::Explore, 45, dir.path());
    dir
}

fn pairs(dir: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let out = run_ok(
        shotpilot()
            .args(["--log", "warn", "features", "--pairs", "--json"])
            .args(extra)
            .arg(dir),
    );
    let text = String::from_utf8(out.stdout).unwrap();
    assert_eq!(text.trim().lines().count(), 1, "{text}");
    serde_json::from_str(&text).unwrap()
}

fn f(v: &serde_json::Value, key: &str, i: usize) -> f64 {
    v[key][i].as_f64().unwrap_or(f64::NAN)
}

#[test]
fn the_match_funnel_follows_the_true_motion_and_shows_where_grass_loses_its_matches() {
    let town_dir = render(WorldKind::Town, "features-town");
    let town = pairs(town_dir.path(), &[]);
    eprintln!("town: {town}");
    assert_eq!(town["pairs"], 44);
    assert_eq!(town["pairs_with_truth"], 44);
    // On textured ground nearly every match the checks keep is on its
    // epipolar line, and the checks remove few of those.
    assert!(f(&town, "agreeing_share", 2) > 0.9, "{town}");
    assert!(
        town["agreeing_lost_to_ratio"].as_f64().unwrap() < 0.2,
        "{town}"
    );

    // Grass: far fewer matches than the town (measured: 60 against 248 a
    // pair, from 273 keypoints against 1007), and not because the checks
    // remove them.
    let grass_dir = render(WorldKind::Grass, "features-grass");
    let grass = pairs(grass_dir.path(), &[]);
    eprintln!("grass: {grass}");
    assert!(
        f(&grass, "median_matches", 2) < 0.5 * f(&town, "median_matches", 2),
        "{grass}"
    );
    assert!(
        grass["agreeing_lost_to_ratio"].as_f64().unwrap() < 0.2,
        "{grass}"
    );

    // A search guided by the motion (the candidates within 4 px of its
    // epipolar line) takes descriptors up to 70 bits instead of 50: more
    // matches, and no smaller a share on the line (measured here: 60 -> 72
    // a pair, 99.7 -> 98.4 % agreeing; on 600 field frames 83 -> 130,
    // 91.6 -> 93.1 %). Unguided, the looser descriptors' share falls.
    let guided = pairs(grass_dir.path(), &["--guided-band", "4", "--th-low", "70"]);
    eprintln!("grass, guided: {guided}");
    assert_eq!(guided["th_low"], 70, "{guided}");
    assert_eq!(guided["guided_band_px"], 4.0, "{guided}");
    assert!(
        f(&guided, "median_matches", 2) >= 1.1 * f(&grass, "median_matches", 2),
        "{guided}"
    );
    assert!(
        f(&guided, "agreeing_share", 2) >= f(&grass, "agreeing_share", 2) - 0.02,
        "{guided}"
    );
    let unguided = pairs(grass_dir.path(), &["--th-low", "70"]);
    assert!(
        f(&unguided, "agreeing_share", 0) < f(&guided, "agreeing_share", 0),
        "{unguided}"
    );

    // A wrong truth: the flight mirrored (north and east swapped, the
    // camera's attitudes kept), so the motion between two frames points
    // elsewhere: far fewer matches agree with it (measured: 55 % against
    // 99 % with the true one; small motions keep many near their line).
    let gt = town_dir.path().join("groundtruth.txt");
    let text = std::fs::read_to_string(&gt).unwrap();
    let shifted: Vec<String> = text
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let mut w: Vec<&str> = l.split_whitespace().collect();
            w.swap(1, 2);
            w.join(" ")
        })
        .collect();
    std::fs::write(&gt, shifted.join("\n") + "\n").unwrap();
    let wrong = pairs(town_dir.path(), &[]);
    assert_eq!(wrong["pairs_with_truth"], 44);
    assert!(f(&wrong, "agreeing_share", 2) < 0.75, "{wrong}");
}
