//! The closed loop end to end, in CI time: `shotpilot scenario --quick`
//! (a short survey over the simulator's world, then a few trials with the
//! simulator's disturbances: GPS bias drift, gimbal pitch and camera
//! heading calibration errors) through the real binary and its JSON.
//!
//! The judges are the simulator's hidden camera poses and the images: the
//! loop must bring the median shot error under the 1 % threshold from first
//! flights that miss by more, every trial under 3 % of the diagonal, and a
//! trial left above the threshold only after it used all its rounds; never
//! leaving the geofence. (The "90 % of trials <= 2 %" is a figure of
//! the full 20-trial scenario over the whole survey, measured in the notes;
//! the quick survey's map and georeference are rougher, and on 4 trials one
//! trial over 2 % is already a p90 over 2 %.)

use std::process::Command;

use serde_json::Value;

fn f(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing or not a number in {v}"))
}

#[test]
fn a_short_scenario_converges_under_one_percent() {
    let out = Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args([
            "--log",
            "warn",
            "scenario",
            "--quick",
            "--trials",
            "4",
            "--seed",
            "3",
            "--anchor-every",
            "2",
            "--json",
        ])
        .output()
        .expect("run shotpilot");
    assert!(
        out.status.success(),
        "scenario failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: Value = serde_json::from_slice(&out.stdout).expect("one JSON object on stdout");
    let trials = r["trial_reports"].as_array().expect("trial_reports");
    for t in trials {
        println!(
            "trial {} {}: first {:.2} % -> final {:.2} % after {} corrections; position {:.3} m -> {:.3} m; yaw {:.2} deg, pitch {:.2} deg",
            t["trial"],
            t["kind"],
            f(t, "first_shot_error_pct"),
            f(t, "final_shot_error_pct"),
            t["rounds"],
            f(t, "first_position_error_m"),
            f(t, "position_error_m"),
            f(t, "yaw_error_deg"),
            f(t, "pitch_error_deg"),
        );
    }
    let e = &r["explore"];
    println!(
        "explore: {} frames, {} keyframes, georeference rms {:.3} m; median shot error first {:.2} % final {:.2} %, p90 final {:.2} %; median position {:.3} m",
        e["frames"],
        e["keyframes"],
        f(e, "geo_rms_m"),
        f(&r, "median_first_shot_error_pct"),
        f(&r, "median_final_shot_error_pct"),
        f(&r, "p90_final_shot_error_pct"),
        f(&r, "median_position_error_m"),
    );
    assert_eq!(trials.len(), 4);
    assert_eq!(r["flown"], 4, "every desired shot localised and flown");
    assert!(
        trials.iter().any(|t| t["kind"] == "anchors")
            && trials.iter().any(|t| t["kind"] == "render")
    );
    assert_eq!(r["fence_violations"], 0);
    // The loop's figures.
    assert!(f(&r, "median_final_shot_error_pct") <= 1.0);
    for t in trials {
        assert!(f(t, "final_shot_error_pct") <= 3.0, "{t}");
        if f(t, "final_shot_error_pct") >= 1.0 {
            assert_eq!(
                t["stop"], "max_rounds",
                "stopped above the threshold early: {t}"
            );
        }
        assert!(t["inside_fence"].as_bool().unwrap_or(false));
        // Each measurement and correction is recorded.
        let rounds = t["round_reports"].as_array().expect("round_reports");
        assert_eq!(rounds.len() as u64, t["rounds"].as_u64().unwrap_or(0) + 1);
        // The judge agrees with the image measure: a matched framing is a
        // camera within a metre and a degree of the hidden pose.
        assert!(f(t, "position_error_m") < 1.0, "{t}");
        assert!(f(t, "yaw_error_deg").abs() < 1.0 && f(t, "pitch_error_deg").abs() < 1.0);
    }
    // The disturbances make the first flights miss: refinement did the work.
    assert!(f(&r, "median_first_shot_error_pct") > 2.0 * f(&r, "median_final_shot_error_pct"));
    assert!(f(&r, "median_first_position_error_m") > f(&r, "median_position_error_m"));
    assert!(f(&r, "p90_first_shot_error_pct") >= f(&r, "median_first_shot_error_pct"));
}
