//! The `shotpilot` command line.
//!
//! Every subcommand that reports figures takes `--json` and then prints
//! exactly one JSON object on stdout; logs go to stderr.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use serde_json::json;

use shotpilot::config::Config;
use shotpilot::eval::{self, AlignMode, Trajectory};

mod vocab_cli;

/// shotpilot: a ground-control-station daemon for camera drones.
///
/// It builds a map of the scene with monocular visual SLAM from the drone's
/// video, finds where the camera must stand to take the photograph an
/// operator describes, and sends the drone there as a MAVLink mission.
#[derive(Parser, Debug)]
#[command(name = "shotpilot", version, about, long_about)]
struct Cli {
    /// Configuration file (TOML). Default: ./config.toml when it exists,
    /// else the built-in defaults (which run against the bundled simulator).
    #[arg(long, global = true, value_name = "PATH")]
    config: Option<PathBuf>,

    /// Log filter for stderr, e.g. `info`, `debug`, `shotpilot=trace`.
    /// Overridden by the RUST_LOG environment variable.
    #[arg(long, global = true, default_value = "info", value_name = "FILTER")]
    log: String,

    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Compare an estimated camera trajectory with the ground truth.
    ///
    /// Both files are in the TUM format (`timestamp tx ty tz qx qy qz qw`,
    /// world_from_cam). Poses are paired by nearest timestamp within
    /// `--max-dt`, the estimate is aligned (Umeyama; Sim(3) by default, as
    /// monocular SLAM has no scale), and the absolute trajectory error of the
    /// positions and the relative pose error are reported. The figures agree
    /// with `evo_ape tum GT EST -as`.
    Eval(EvalArgs),

    /// Run monocular SLAM on a recorded sequence.
    ///
    /// DATASET is a folder in the TUM layout (rgb.txt, calib.txt, optional
    /// groundtruth.txt; also what `shotpilot-sim render` writes) or the
    /// EuRoC ASL layout (mav0/cam0). Prints per-stage timing, counts and,
    /// when ground truth is at hand, the ATE after Sim(3) alignment (as
    /// `eval` does). With `--out`, writes DIR/trajectory.txt (every tracked
    /// frame, placed relative to its reference keyframe after the final
    /// optimisation) and DIR/keyframes.txt, both in the TUM format.
    Slam(SlamArgs),

    /// The desired shot and the camera pose that takes it.
    ///
    /// Either four anchors on a keyframe of the map (where the frame's
    /// corners (0,0), (w-1,0), (w-1,h-1), (0,h-1) should go; the keyframe is
    /// warped by the perspective transform they define) or a photo taken
    /// with the map's camera. The shot is localised in the map (ORB,
    /// candidate keyframes, PnP RANSAC, motion-only refinement, reliability
    /// gate) and the pose printed as world_from_cam in map coordinates.
    /// Maps are made with `shotpilot slam DATASET --sequential --save-map FILE`.
    Shot(ShotArgs),

    /// Bag-of-words vocabularies: train one from images, import ORB-SLAM's
    /// ORBvoc.txt, describe one.
    Vocab(vocab_cli::VocabArgs),
    /// Plan, upload, download and start missions (the MAVLink link to the drone).
    #[command(subcommand)]
    Mission(MissionCommand),
    /// Run the daemon: live video -> SLAM, the MAVLink link, the HTTP API
    /// and the operator's page. With the default configuration it starts
    /// the bundled simulator in-process and prints the page's address.
    /// Ctrl-C or SIGTERM stops it cleanly (the map and shots are saved).
    Run(RunArgs),
    /// Extract ORB features from every frame of a dataset and report the
    /// time per frame.
    ///
    /// All frames are decoded first; then each is timed alone (after 3
    /// untimed warm-up extractions), reporting the median and 95th
    /// percentile milliseconds per frame and the mean number of keypoints.
    Features(FeaturesArgs),
    /// The closed loop in the simulator: explore, then per trial a desired
    /// shot from a hidden pose is localised, uploaded, flown and refined
    /// until the live view matches it; reports first and final shot errors.
    Scenario(cli::scenario::ScenarioArgs),
}

#[derive(Args, Debug)]
struct RunArgs {
    /// Listen address of the API, overriding `[server] bind`.
    #[arg(long, value_name = "ADDR:PORT")]
    bind: Option<String>,
    /// Do not start the simulator (overrides `[sim] enabled`).
    #[arg(long)]
    no_sim: bool,
    /// Print the final summary as one JSON object on stdout.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct ShotArgs {
    /// Map file (from `shotpilot slam --save-map`).
    #[arg(long, value_name = "FILE")]
    map: PathBuf,
    /// Keyframe whose image the anchors are placed on.
    #[arg(
        long,
        value_name = "ID",
        requires = "anchors",
        conflicts_with = "photo"
    )]
    keyframe: Option<u32>,
    /// The four anchors, pixels of the keyframe: where the frame's top-left,
    /// top-right, bottom-right and bottom-left corners should go.
    #[arg(
        long,
        value_name = "x1,y1,x2,y2,x3,y3,x4,y4",
        requires = "keyframe",
        allow_hyphen_values = true
    )]
    anchors: Option<String>,
    /// A photo of the desired shot: taken with the map's camera, or (at
    /// another size, same aspect ratio) a resized copy of one, unless
    /// --photo-intrinsics says otherwise.
    #[arg(long, value_name = "FILE")]
    photo: Option<PathBuf>,
    /// The photo's camera when it is not the map's: `fx,fy,cx,cy` or
    /// `fx,fy,cx,cy,k1,k2,p1,p2,k3` (pixels of the photo, OpenCV order).
    #[arg(long, value_name = "fx,fy,cx,cy[,k1,k2,p1,p2,k3]", requires = "photo")]
    photo_intrinsics: Option<String>,
    /// Folder for desired_shot.png (and desired_shot_mask.png).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Candidate keyframes tried.
    #[arg(long, default_value_t = 5, value_name = "K")]
    top_k: usize,
    /// Choose the candidates by a bag-of-words query with the built-in
    /// vocabulary instead of descriptor matching against every keyframe.
    #[arg(long)]
    bow: bool,
    /// Seed of the RANSAC.
    #[arg(long, default_value_t = 1, value_name = "N")]
    seed: u64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct SlamArgs {
    /// Dataset folder (TUM or EuRoC layout).
    dataset: PathBuf,
    /// Folder for trajectory.txt and keyframes.txt (created if missing).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Ground truth (TUM format); default: the dataset's own, if any.
    #[arg(long, value_name = "FILE")]
    gt: Option<PathBuf>,
    /// Run local mapping after each keyframe on the same thread, so runs
    /// repeat exactly (and frames are not paced).
    #[arg(long)]
    sequential: bool,
    /// Replay speed relative to the frame timestamps (two-thread mode);
    /// 0 feeds frames as fast as tracking takes them.
    #[arg(long, default_value_t = 1.0, value_name = "X")]
    speed: f64,
    /// Save the map to this file at the end.
    #[arg(long, value_name = "FILE")]
    save_map: Option<PathBuf>,
    /// ORB features per frame.
    #[arg(long, default_value_t = 1000, value_name = "N")]
    features: usize,
    /// Use only the first N frames.
    #[arg(long, value_name = "N")]
    max_frames: Option<usize>,
    /// Seed of the randomised steps (RANSAC).
    #[arg(long, default_value_t = 1, value_name = "N")]
    seed: u64,
    /// Largest timestamp difference when pairing with the ground truth, seconds.
    #[arg(long, default_value_t = 0.02, value_name = "S")]
    max_dt: f64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand, Debug)]
enum MissionCommand {
    /// Plan the mission that takes the camera to a target, upload it, and
    /// read it back to verify. Never arms, changes mode or starts the mission.
    Upload(UploadArgs),
    /// Download the vehicle's mission.
    Download(LinkArgs),
    /// Plan a mission offline and export it as a QGroundControl `.plan` file.
    Plan(PlanArgs),
    /// Operator action: (optionally arm, then) start the uploaded mission.
    Start(StartArgs),
}

#[derive(Args, Debug)]
struct LinkArgs {
    /// Link URL (serial:/dev/ttyUSB0:57600, udpin:0.0.0.0:14550,
    /// udpout:HOST:PORT, tcpout:HOST:PORT). Default: `[link] url` of the config.
    #[arg(long, value_name = "URL")]
    link: Option<String>,
    /// How long to wait for the vehicle's heartbeat, seconds.
    #[arg(long, default_value_t = 10.0, value_name = "S")]
    wait: f64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

/// Autopilot flavour on the command line.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum FlavourArg {
    /// From the vehicle's heartbeat.
    Auto,
    /// PX4.
    Px4,
    /// ArduPilot.
    Ardupilot,
}

#[derive(Args, Debug)]
struct TargetArgs {
    /// The camera target: latitude and longitude (degrees), altitude above
    /// home (m), heading (degrees from north), gimbal pitch (degrees, negative down).
    #[arg(
        long,
        value_name = "LAT,LON,ALT,YAW_DEG,PITCH_DEG",
        allow_hyphen_values = true
    )]
    target: String,
    /// Take a photo on arrival.
    #[arg(long)]
    photo: bool,
    /// Home (latitude, longitude, altitude AMSL) for the geofence. Default:
    /// the vehicle's HOME_POSITION (required for `mission plan`).
    #[arg(long, value_name = "LAT,LON,ALT_AMSL", allow_hyphen_values = true)]
    home: Option<String>,
}

#[derive(Args, Debug)]
struct UploadArgs {
    #[command(flatten)]
    link: LinkArgs,
    #[command(flatten)]
    target: TargetArgs,
    /// Which autopilot's items to plan.
    #[arg(long, value_enum, default_value = "auto")]
    flavour: FlavourArg,
    /// Skip reading the mission back after the upload.
    #[arg(long)]
    no_verify: bool,
}

#[derive(Args, Debug)]
struct PlanArgs {
    #[command(flatten)]
    target: TargetArgs,
    /// Which autopilot's items to plan (`auto` means PX4 offline).
    #[arg(long, value_enum, default_value = "px4")]
    flavour: FlavourArg,
    /// Write the QGroundControl plan here.
    #[arg(long, value_name = "FILE")]
    qgc_plan: PathBuf,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct StartArgs {
    #[command(flatten)]
    link: LinkArgs,
    /// Arm the vehicle before starting (an explicit operator decision).
    #[arg(long)]
    arm: bool,
}

#[derive(Args, Debug)]
struct FeaturesArgs {
    /// Dataset folder (TUM or EuRoC layout).
    #[arg(value_name = "DATASET")]
    dataset: PathBuf,
    /// Features wanted per frame.
    #[arg(long = "features", default_value_t = 1000, value_name = "N")]
    n_features: usize,
    /// Threads per frame (1 or 2; the pyramid levels are split among them).
    #[arg(long, default_value_t = 1, value_name = "N")]
    threads: usize,
    /// Passes over the dataset; the figures are over all timed frames.
    #[arg(long, default_value_t = 1, value_name = "N")]
    repeat: usize,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

#[derive(Args, Debug)]
struct EvalArgs {
    /// Ground-truth trajectory (TUM format).
    #[arg(long, value_name = "FILE")]
    gt: PathBuf,
    /// Estimated trajectory (TUM format).
    #[arg(long, value_name = "FILE")]
    est: PathBuf,
    /// Alignment of the estimate before measuring.
    #[arg(long, value_enum, default_value = "sim3")]
    align: AlignMode,
    /// Largest timestamp difference for a pair, seconds.
    #[arg(long, default_value_t = 0.02, value_name = "S")]
    max_dt: f64,
    /// Frame distance for the relative pose error.
    #[arg(long, default_value_t = 1, value_name = "N")]
    rpe_delta: usize,
    /// Draw both trajectories (top view) and the error over time to a PNG.
    #[arg(long, value_name = "FILE.png")]
    plot: Option<PathBuf>,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    json: bool,
}

mod cli;

fn init_logging(filter: &str) {
    let env = tracing_subscriber::EnvFilter::try_from_default_env()
        .or_else(|_| tracing_subscriber::EnvFilter::try_new(filter))
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    tracing_subscriber::fmt()
        .with_env_filter(env)
        .with_writer(std::io::stderr)
        .init();
}

/// The configuration: `--config PATH`, else ./config.toml if present, else defaults.
fn load_config(path: Option<&Path>) -> Result<Config> {
    match path {
        Some(p) => Ok(Config::load(p)?),
        None => {
            let default = Path::new("config.toml");
            if default.is_file() {
                Ok(Config::load(default)?)
            } else {
                Ok(Config::default())
            }
        }
    }
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    init_logging(&cli.log);
    match run(cli) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let config = load_config(cli.config.as_deref())?;
    match cli.command {
        Command::Eval(args) => cmd_eval(args),
        Command::Slam(args) => cli::slam::run(args),
        Command::Shot(args) => cli::shot::run(args),
        Command::Vocab(args) => vocab_cli::run(args),
        Command::Mission(cmd) => mission_cli::run(cmd, &config),
        Command::Run(args) => cmd_run(args, config, cli.config.as_deref()),
        Command::Features(args) => cmd_features(args),
        Command::Scenario(args) => cli::scenario::run(args),
    }
}

fn cmd_run(args: RunArgs, mut config: Config, path: Option<&Path>) -> Result<()> {
    if let Some(b) = args.bind {
        config.server.bind = b;
    }
    if args.no_sim {
        config.sim.enabled = false;
    }
    config.validate(path.unwrap_or(Path::new("config.toml")))?;
    let base_dir = path
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let summary = rt.block_on(async move {
        let cancel = tokio_util::sync::CancellationToken::new();
        let c = cancel.clone();
        tokio::spawn(async move {
            wait_for_signal().await;
            tracing::info!("signal received, stopping");
            c.cancel();
        });
        let (tx, rx) = tokio::sync::oneshot::channel();
        tokio::spawn(async move {
            if let Ok(s) = rx.await {
                let s: shotpilot::daemon::Started = s;
                eprintln!("shotpilot: operator page at http://{}/", s.api_addr);
            }
        });
        shotpilot::daemon::run(config, &base_dir, cancel, Some(tx)).await
    })?;
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        eprintln!(
            "shotpilot: stopped after {:.1} s; video received {} decoded {} dropped {} bad {}; SLAM frames {} keyframes {}; {} shots",
            summary.run_s,
            summary.video.received,
            summary.video.decoded,
            summary.video.dropped,
            summary.video.bad,
            summary.slam.frames,
            summary.slam.keyframes,
            summary.shots
        );
    }
    Ok(())
}

/// Ctrl-C, or SIGTERM on Unix.
async fn wait_for_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

fn cmd_eval(args: EvalArgs) -> Result<()> {
    let gt = Trajectory::read_tum(&args.gt)?;
    let est = Trajectory::read_tum(&args.est)?;
    let params = eval::Params {
        max_dt: args.max_dt,
        align: args.align,
        rpe_delta: args.rpe_delta,
    };
    let ev = eval::evaluate(&gt, &est, &params).with_context(|| {
        format!(
            "evaluating {} against {}",
            args.est.display(),
            args.gt.display()
        )
    })?;
    if let Some(plot) = &args.plot {
        let title = args
            .est
            .file_name()
            .and_then(|s| s.to_str())
            .unwrap_or("estimate");
        eval::plot::plot_evaluation(&ev, plot, title)?;
        tracing::info!(path = %plot.display(), "plot written");
    }
    let q = ev.alignment.rotation.coords;
    if args.json {
        let out = json!({
            "gt_poses": gt.len(),
            "est_poses": est.len(),
            "matched": ev.matched,
            "align": args.align,
            "scale": ev.alignment.scale,
            "rotation_xyzw": [q.x, q.y, q.z, q.w],
            "translation": [ev.alignment.translation.x, ev.alignment.translation.y, ev.alignment.translation.z],
            "ate_rmse_m": ev.ate.rmse,
            "ate_mean_m": ev.ate.mean,
            "ate_median_m": ev.ate.median,
            "ate_max_m": ev.ate.max,
            "ate_std_m": ev.ate.std,
            "rpe_trans_rmse_m": ev.rpe_trans.rmse,
            "rpe_rot_rmse_deg": ev.rpe_rot_deg.rmse,
            "rpe_delta": args.rpe_delta,
            "gt_path_length_m": gt.path_length(),
        });
        println!("{out}");
    } else {
        println!(
            "matched {} of {} estimated poses ({} ground truth), align {:?}, scale {:.6}",
            ev.matched,
            est.len(),
            gt.len(),
            args.align,
            ev.alignment.scale
        );
        println!(
            "ATE  rmse {:.6} m  mean {:.6} m  median {:.6} m  max {:.6} m",
            ev.ate.rmse, ev.ate.mean, ev.ate.median, ev.ate.max
        );
        println!(
            "RPE (delta {})  translation rmse {:.6} m  rotation rmse {:.4} deg",
            args.rpe_delta, ev.rpe_trans.rmse, ev.rpe_rot_deg.rmse
        );
    }
    Ok(())
}

/// `shotpilot mission ...`.
mod mission_cli {
    use std::time::Duration;

    use anyhow::{Context, Result, anyhow, bail};
    use serde_json::json;
    use tokio_util::sync::CancellationToken;

    use super::{
        FlavourArg, LinkArgs, MissionCommand, PlanArgs, StartArgs, TargetArgs, UploadArgs,
    };
    use shotpilot::config::Config;
    use shotpilot::mission::plan::{self, Flavour, Home, Target};
    use shotpilot::mission::upload::same_mission;
    use shotpilot::vehicle::{self, FlightMode, LinkHandle};

    pub fn run(cmd: MissionCommand, config: &Config) -> Result<()> {
        match cmd {
            MissionCommand::Plan(args) => cmd_plan(args, config),
            MissionCommand::Upload(args) => block_on(cmd_upload(args, config)),
            MissionCommand::Download(args) => block_on(cmd_download(args, config)),
            MissionCommand::Start(args) => block_on(cmd_start(args, config)),
        }
    }

    fn block_on<F: std::future::Future<Output = Result<()>>>(f: F) -> Result<()> {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()?
            .block_on(f)
    }

    fn numbers(text: &str, n: usize, what: &str) -> Result<Vec<f64>> {
        let v: Vec<f64> = text
            .split(',')
            .map(|s| s.trim().parse::<f64>())
            .collect::<std::result::Result<_, _>>()
            .with_context(|| format!("{what} `{text}`: not numbers"))?;
        if v.len() != n {
            bail!(
                "{what} `{text}`: expected {n} comma-separated numbers, got {}",
                v.len()
            );
        }
        Ok(v)
    }

    fn target(args: &TargetArgs) -> Result<Target> {
        let v = numbers(&args.target, 5, "--target")?;
        Ok(Target {
            lat_deg: v[0],
            lon_deg: v[1],
            alt_m: v[2],
            yaw_deg: v[3],
            gimbal_pitch_deg: v[4],
            photo: args.photo,
        })
    }

    fn home_arg(args: &TargetArgs) -> Result<Option<Home>> {
        args.home
            .as_deref()
            .map(|h| {
                let v = numbers(h, 3, "--home")?;
                Ok(Home {
                    lat_deg: v[0],
                    lon_deg: v[1],
                    alt_amsl_m: v[2],
                })
            })
            .transpose()
    }

    fn cmd_plan(args: PlanArgs, config: &Config) -> Result<()> {
        let t = target(&args.target)?;
        let home = home_arg(&args.target)?
            .ok_or_else(|| anyhow!("`mission plan` needs --home LAT,LON,ALT_AMSL"))?;
        let flavour = match args.flavour {
            FlavourArg::Ardupilot => Flavour::ArduPilot,
            FlavourArg::Px4 | FlavourArg::Auto => Flavour::Px4,
        };
        let p = &config.mission.plan;
        let items = plan::plan(&t, &home, flavour, p)?;
        let doc = plan::to_qgc_plan(&items, &home, flavour, p)?;
        std::fs::write(&args.qgc_plan, serde_json::to_string_pretty(&doc)? + "\n")
            .with_context(|| format!("writing {}", args.qgc_plan.display()))?;
        if args.json {
            println!(
                "{}",
                json!({ "items": items, "flavour": flavour, "qgc_plan": args.qgc_plan })
            );
        } else {
            println!(
                "{} items for {flavour:?} written to {}",
                items.len(),
                args.qgc_plan.display()
            );
        }
        Ok(())
    }

    async fn connect(
        args: &LinkArgs,
        config: &Config,
        cancel: &CancellationToken,
    ) -> Result<(LinkHandle, vehicle::VehicleState)> {
        let mut p = config.link.clone();
        if let Some(url) = &args.link {
            p.url = url.clone();
        }
        let (link, _task) = vehicle::spawn(p, config.mission.transfer, cancel.clone())?;
        let v = link
            .wait_for_vehicle(Duration::from_secs_f64(args.wait.max(0.0)))
            .await?;
        tracing::info!(system = ?v.system_id, flavour = ?v.flavour, mode = %v.mode, "vehicle");
        Ok((link, v))
    }

    async fn cmd_upload(args: UploadArgs, config: &Config) -> Result<()> {
        let cancel = CancellationToken::new();
        let t = target(&args.target)?;
        let (link, v) = connect(&args.link, config, &cancel).await?;
        let flavour = match args.flavour {
            FlavourArg::Px4 => Flavour::Px4,
            FlavourArg::Ardupilot => Flavour::ArduPilot,
            FlavourArg::Auto => v.flavour.ok_or_else(|| {
                anyhow!(
                    "autopilot {} is neither PX4 nor ArduPilot: pass --flavour",
                    v.autopilot
                )
            })?,
        };
        let home = match home_arg(&args.target)? {
            Some(h) => h,
            None => {
                let mut rx = link.telemetry.home.clone();
                let h = tokio::time::timeout(Duration::from_secs(5), rx.wait_for(|h| h.is_some()))
                    .await
                    .map_err(|_| {
                        anyhow!("no HOME_POSITION from the vehicle within 5 s: pass --home")
                    })??
                    .map(|s| s.value)
                    .ok_or_else(|| anyhow!("no home"))?;
                Home {
                    lat_deg: h.lat_deg,
                    lon_deg: h.lon_deg,
                    alt_amsl_m: h.alt_amsl_m,
                }
            }
        };
        let items = plan::plan(&t, &home, flavour, &config.mission.plan)?;
        let upload = tokio::select! {
            r = link.upload_mission(items.clone()) => r,
            _ = tokio::signal::ctrl_c() => {
                link.cancel_transfer().await.ok();
                bail!("cancelled by the operator");
            }
        };
        let report = match upload {
            Ok(r) => r,
            Err(e) => {
                if args.link.json {
                    println!(
                        "{}",
                        json!({ "result": "error", "error": e.to_string(), "items": items.len() })
                    );
                }
                cancel.cancel();
                return Err(e.into());
            }
        };
        let verified = if args.no_verify {
            None
        } else {
            let d = link.download_mission().await?;
            Some((
                same_mission(&items, &d.items, flavour == Flavour::ArduPilot),
                d.seconds,
            ))
        };
        cancel.cancel();
        if args.link.json {
            println!(
                "{}",
                json!({
                    "result": "accepted",
                    "items": report.items,
                    "seconds": report.seconds,
                    "retries": report.retries,
                    "repeats": report.repeats,
                    "ack_lost_verified_by_download": report.verified_by_download,
                    "flavour": flavour,
                    "vehicle_system_id": v.system_id,
                    "verified": verified.map(|v| v.0),
                    "download_seconds": verified.map(|v| v.1),
                })
            );
        } else {
            println!(
                "uploaded {} items to vehicle {:?} ({flavour:?}) in {:.2} s with {} retries{}",
                report.items,
                v.system_id,
                report.seconds,
                report.retries,
                match verified {
                    Some((true, s)) => format!("; read back identical in {s:.2} s"),
                    Some((false, _)) => "; READ BACK DIFFERENT".into(),
                    None => String::new(),
                }
            );
        }
        if verified.is_some_and(|v| !v.0) {
            bail!("the vehicle's mission differs from the one uploaded");
        }
        Ok(())
    }

    async fn cmd_download(args: LinkArgs, config: &Config) -> Result<()> {
        let cancel = CancellationToken::new();
        let (link, v) = connect(&args, config, &cancel).await?;
        let d = link.download_mission().await?;
        cancel.cancel();
        if args.json {
            println!(
                "{}",
                json!({ "items": d.items, "count": d.items.len(), "seconds": d.seconds, "retries": d.retries, "vehicle_system_id": v.system_id })
            );
        } else {
            println!(
                "{} items from vehicle {:?} in {:.2} s ({} retries)",
                d.items.len(),
                v.system_id,
                d.seconds,
                d.retries
            );
            for i in &d.items {
                println!(
                    "{:3} cmd {:5} frame {:2} params {:?} x {} y {} z {}",
                    i.seq, i.command, i.frame, i.params, i.x, i.y, i.z
                );
            }
        }
        Ok(())
    }

    async fn cmd_start(args: StartArgs, config: &Config) -> Result<()> {
        let cancel = CancellationToken::new();
        let (link, _v) = connect(&args.link, config, &cancel).await?;
        if args.arm {
            link.arm(true).await?;
        }
        link.set_mode(FlightMode::Mission).await?;
        link.start_mission().await?;
        cancel.cancel();
        if args.link.json {
            println!(
                "{}",
                json!({ "result": "started", "armed_by_us": args.arm })
            );
        } else {
            println!("mission started{}", if args.arm { " (armed)" } else { "" });
        }
        Ok(())
    }
}

fn cmd_features(args: FeaturesArgs) -> Result<()> {
    use shotpilot::features::{OrbExtractor, Params, eval as feval};
    let ds = shotpilot::video::dataset::Dataset::open(&args.dataset)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let frames = ds
        .frames()
        .map(|f| f.map(|f| f.image))
        .collect::<Result<Vec<_>, _>>()?;
    let params = Params {
        n_features: args.n_features,
        threads: args.threads,
        ..Params::default()
    };
    let mut ex = OrbExtractor::new(params)?;
    let mut all = Vec::with_capacity(frames.len() * args.repeat.max(1));
    for _ in 0..args.repeat.max(1) {
        all.extend(feval::time_frames(&mut ex, &frames, Some(&ds.camera), 3));
    }
    let r = feval::summarize(&all);
    if args.json {
        let out = json!({
            "dataset": args.dataset,
            "frames": frames.len(),
            "timed": r.frames,
            "features": args.n_features,
            "threads": args.threads,
            "median_ms": r.median_ms,
            "p95_ms": r.p95_ms,
            "mean_keypoints": r.mean_keypoints,
        });
        println!("{out}");
    } else {
        println!(
            "{} frames x {}: median {:.3} ms, p95 {:.3} ms per frame, {:.1} keypoints (features {}, threads {})",
            frames.len(),
            args.repeat.max(1),
            r.median_ms,
            r.p95_ms,
            r.mean_keypoints,
            args.n_features,
            args.threads
        );
    }
    Ok(())
}
