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
    /// Extract ORB features from every frame of a dataset and report the
    /// time per frame.
    ///
    /// All frames are decoded first; then each is timed alone (after 3
    /// untimed warm-up extractions), reporting the median and 95th
    /// percentile milliseconds per frame and the mean number of keypoints.
    Features(FeaturesArgs),
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
    let _config = load_config(cli.config.as_deref())?;
    match cli.command {
        Command::Eval(args) => cmd_eval(args),
        Command::Features(args) => cmd_features(args),
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
