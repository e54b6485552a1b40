//! `shotpilot scenario`: the closed-loop experiment in the simulator
//! ([`shotpilot::simulator::scenario`]): explore, then per trial a desired shot
//! from a hidden pose, localised, planned, uploaded, flown and refined.

use anyhow::{Context, Result};
use clap::Args;

use shotpilot::simulator::scenario::{self, ScenarioParams, TrialReport};

/// Arguments of `shotpilot scenario`.
#[derive(Args, Debug)]
pub struct ScenarioArgs {
    /// Trials after the explore flight.
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    /// Seed of the world, the sensor noise and the hidden poses.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The short survey and small textures of the CI test instead of the
    /// full `explore` flight.
    #[arg(long)]
    pub quick: bool,
    /// Shot error under which the loop stops, % of the image diagonal.
    #[arg(long, default_value_t = 1.0)]
    pub threshold_pct: f64,
    /// Corrections at most per trial.
    #[arg(long, default_value_t = 4)]
    pub max_rounds: usize,
    /// Every N-th trial makes its desired shot from anchors on a keyframe
    /// (0: never).
    #[arg(long, default_value_t = 4)]
    pub anchor_every: usize,
    /// Draw the anchor trials as an operator drags the four corners: a
    /// zoom of 1.0-1.6x, a pan of up to 20 % of the frame and a rotation of
    /// up to 15 deg (instead of a small pan and tilt of the keyframe's
    /// camera); the truth is the camera that takes the drawn picture best
    /// in the true world.
    #[arg(long)]
    pub drags: bool,
    /// Localise the anchor trials' shots as photos are (their warped
    /// picture matched against the map), as before an anchors shot's camera
    /// came from its keyframe's geometry: for comparison.
    #[arg(long)]
    pub anchors_by_matching: bool,
    /// Save the explored map to its file format and load it back before
    /// the trials, as a daemon restart does: the shots are localised on
    /// the reloaded map.
    #[arg(long)]
    pub restart: bool,
    /// Fly without the disturbances (GPS bias drift, gimbal pitch and camera
    /// heading calibration errors): the vehicle is exactly where telemetry
    /// says and the camera exactly as mounted.
    #[arg(long)]
    pub no_disturbances: bool,
    /// Telemetry priors in the explore flight's SLAM (the daemon's `[slam]
    /// priors`): the map is put in local NED by the GNSS fixes and kept
    /// there by position priors in bundle adjustment, and the georeference
    /// is the map itself instead of a Sim(3) fitted after the flight.
    #[arg(long)]
    pub priors: bool,
    /// Fly every trial with the georeference fitted after the explore
    /// flight, the GNSS bias averaged over it (as before the georeference
    /// followed the drift): for comparison. By default the georeference is
    /// kept, given live frames paired in a short hover before each
    /// departure, and refitted with a GNSS bias state per window.
    #[arg(long)]
    pub fixed_georeference: bool,
    /// Realism of the simulator: `ideal` (the clean world), `field` (a
    /// calm day, a SIYI-class camera) or `harsh` (gusty evening), then any
    /// `-EFFECT` (off) or `+EFFECT[@PRESET]` (on), e.g. `field-blur`; see
    /// `shotpilot-sim --help`.
    #[arg(long, default_value = "ideal", value_name = "PRESET")]
    pub realism: String,
    /// Servo at the shot: after the first arrival (and after a mission leg
    /// for a correction longer than 3 m), every processed frame (5 a
    /// second, 0.15 s from capture to setpoint) corrects the position,
    /// heading and gimbal through the autopilot's guided control (PX4
    /// OFFBOARD / ArduPilot GUIDED), and the photo is taken at the first
    /// frame whose shot error is under `--servo-threshold-pct` (after 20 s,
    /// at one within the best quarter measured; after 30 s, where it is).
    /// Without it: rounds of mission legs only.
    #[arg(long)]
    pub servo: bool,
    /// The servo's photo threshold, % of the image diagonal.
    #[arg(long, default_value_t = shotpilot::refine::ServoParams::default().threshold_pct, requires = "servo")]
    pub servo_threshold_pct: f64,
    /// How long the servo's shot error must stay under its threshold
    /// before the photo, seconds (0: the first frame under it).
    #[arg(long, default_value_t = 0.0, requires = "servo")]
    pub servo_settle_s: f64,
    /// Fly each leg to the target converted when it started, never
    /// re-targeting on the approach (for comparison). By default the target
    /// is converted again each second with the georeference refitted from
    /// frames paired in flight, and the moved target flown when it moved
    /// beyond a fit's noise (the daemon's `[refine.approach]`).
    #[arg(long)]
    pub no_retarget: bool,
    /// Re-targets per leg at most (`[refine.approach] max_per_leg`).
    #[arg(long, default_value_t = shotpilot::refine::ApproachParams::default().max_per_leg)]
    pub retarget_max: usize,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".into(), |x| format!("{x:.digits$}"))
}

/// Runs the scenario and prints the report.
pub fn run(args: ScenarioArgs) -> Result<()> {
    let mut params = if args.quick {
        ScenarioParams::quick(args.trials, args.seed)
    } else {
        ScenarioParams {
            trials: args.trials,
            seed: args.seed,
            ..ScenarioParams::default()
        }
    };
    params.refine.controller.threshold_pct = args.threshold_pct;
    params.refine.controller.max_rounds = args.max_rounds;
    params.anchor_every = args.anchor_every;
    params.anchors_by_matching = args.anchors_by_matching;
    if args.drags {
        params.hidden.drags = Some(scenario::DragParams::default());
    }
    params.realism = args
        .realism
        .parse()
        .with_context(|| format!("--realism {:?}", args.realism))?;
    if args.no_disturbances {
        params.disturbances = scenario::Disturbances::none();
    }
    if args.servo {
        if !(args.servo_threshold_pct.is_finite() && args.servo_threshold_pct > 0.0) {
            anyhow::bail!(
                "--servo-threshold-pct must be a positive percentage, not {}",
                args.servo_threshold_pct
            );
        }
        if !(args.servo_settle_s.is_finite() && args.servo_settle_s >= 0.0) {
            anyhow::bail!(
                "--servo-settle-s must be zero or more seconds, not {}",
                args.servo_settle_s
            );
        }
        let mut d = scenario::ServoDriverParams::default();
        d.servo.threshold_pct = args.servo_threshold_pct;
        d.servo.settle_s = args.servo_settle_s;
        params.servo = Some(d);
    }
    params.priors = args.priors;
    params.restart = args.restart;
    if args.fixed_georeference {
        params.geo.align.drift = None;
    }
    params.refine.approach.enabled = !args.no_retarget;
    params.refine.approach.max_per_leg = args.retarget_max;
    let json = args.json;
    let mut progress = |t: &TrialReport| {
        if !json {
            println!(
                "trial {:2} {:7}: first {:>6} %  final {:>6} %  position {:>6} m  yaw {:>6}°  pitch {:>6}°  rounds {}  {}{}  ({:.0} s sim, {:.1} s wall)",
                t.trial,
                t.kind,
                fmt_opt(t.first_shot_error_pct, 2),
                fmt_opt(t.final_shot_error_pct, 2),
                fmt_opt(t.position_error_m, 3),
                fmt_opt(t.yaw_error_deg, 2),
                fmt_opt(t.pitch_error_deg, 2),
                t.rounds,
                t.stop,
                t.reason
                    .as_ref()
                    .map(|r| format!(" ({r})"))
                    .unwrap_or_default(),
                t.sim_s,
                t.wall_s
            );
        }
    };
    let report = scenario::run(&params, &mut progress)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    let e = &report.explore;
    println!(
        "explore: {:.0} s simulated, {} frames ({} tracked), {} keyframes, {} points; map {}; georeference {} / {} inliers, rms {:.3} m ({:.1} s wall)",
        e.sim_s,
        e.frames,
        e.tracked,
        e.keyframes,
        e.points,
        e.map_mode,
        e.geo_inliers,
        e.geo_pairs,
        e.geo_rms_m,
        e.wall_s
    );
    println!(
        "{} trials, {} flown, {} converged under {} %; fence violations: {}",
        report.trials,
        report.flown,
        report.converged,
        report.threshold_pct,
        report.fence_violations
    );
    if report.servo {
        println!(
            "servo: {} of {} flown settled; arrival to photo median {} s",
            report.servo_settled,
            report.flown,
            fmt_opt(report.median_arrival_to_photo_s, 1),
        );
    }
    println!(
        "shot error: first median {} % p90 {} %; final median {} % p90 {} %; final <= 2 %: {}",
        fmt_opt(report.median_first_shot_error_pct, 2),
        fmt_opt(report.p90_first_shot_error_pct, 2),
        fmt_opt(report.median_final_shot_error_pct, 2),
        fmt_opt(report.p90_final_shot_error_pct, 2),
        fmt_opt(report.fraction_final_within_2pct.map(|f| 100.0 * f), 0) + " %",
    );
    println!(
        "camera position error: first median {} m, final median {} m; final yaw {}°, pitch {}° (medians); {} corrections per trial on average; {:.1} s wall",
        fmt_opt(report.median_first_position_error_m, 3),
        fmt_opt(report.median_position_error_m, 3),
        fmt_opt(report.median_yaw_error_deg, 2),
        fmt_opt(report.median_pitch_error_deg, 2),
        fmt_opt(report.mean_rounds, 1),
        report.wall_s
    );
    Ok(())
}
