//! The `shotpilot` command line.
//!
//! Every subcommand that reports figures takes `--json` and then prints
//! exactly one JSON object on stdout; logs go to stderr.

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::{Parser, Subcommand};

use shotpilot::config::Config;

mod cli;

/// shotpilot: a ground-control-station daemon for camera drones.
///
/// It builds a map of the scene with monocular visual SLAM from the drone's
/// video, finds where the camera must stand to take the photograph an
/// operator describes, and sends the drone there as a MAVLink mission.
#[derive(Parser, Debug)]
#[command(name = "shotpilot", version, about, long_about)]
struct Cli {
    /// Configuration file (TOML). Default: ./config.toml when it exists,
    /// else the built-in defaults (which run against the bundled simulator;
    /// a build without it needs `[sim] enabled = false` or `run --no-sim`).
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
    Eval(cli::eval::EvalArgs),

    /// Run monocular SLAM on a recorded sequence.
    ///
    /// DATASET is a folder in the TUM layout (rgb.txt, calib.txt, optional
    /// groundtruth.txt; also what `shotpilot-sim render` writes) or the
    /// EuRoC ASL layout (mav0/cam0). Prints per-stage timing, counts and,
    /// when ground truth is at hand, the ATE after Sim(3) alignment (as
    /// `eval` does). With `--out`, writes DIR/trajectory.txt (every tracked
    /// frame, placed relative to its reference keyframe after the final
    /// optimisation) and DIR/keyframes.txt, both in the TUM format.
    Slam(cli::slam::SlamArgs),

    /// The desired shot and the camera pose that takes it.
    ///
    /// Either four anchors on a keyframe of the map (where the frame's
    /// corners (0,0), (w-1,0), (w-1,h-1), (0,h-1) should go; the keyframe is
    /// warped by the perspective transform they define) or a photo. An
    /// anchors shot's camera comes from the keyframe's own geometry (its
    /// observations moved through that transform, PnP; refused only when
    /// the drawn frame holds too few mapped points); a photo is localised
    /// in the map (ORB, candidate keyframes, PnP RANSAC, motion-only
    /// refinement, reliability gate). The pose is printed as world_from_cam
    /// in map coordinates.
    /// Maps are made with `shotpilot slam DATASET --sequential --save-map FILE`.
    Shot(cli::shot::ShotArgs),

    /// Bag-of-words vocabularies: train one from images, import ORB-SLAM's
    /// ORBvoc.txt, describe one.
    Vocab(cli::vocab::VocabArgs),
    /// Plan, upload, download and start missions (the MAVLink link to the drone).
    #[command(subcommand)]
    Mission(cli::mission::MissionCommand),
    /// Run the daemon: live video -> SLAM, the MAVLink link, the HTTP API
    /// and the operator's page. With the default configuration it starts
    /// the bundled simulator in-process and prints the page's address.
    /// Ctrl-C or SIGTERM stops it cleanly (the map and shots are saved).
    Run(cli::run::RunArgs),
    /// Extract ORB features from every frame of a dataset and report the
    /// time per frame.
    ///
    /// All frames are decoded first; then each is timed alone (after 3
    /// untimed warm-up extractions), reporting the median and 95th
    /// percentile milliseconds per frame and the mean number of keypoints.
    Features(cli::features::FeaturesArgs),
    /// The closed loop in the simulator: explore, then per trial a desired
    /// shot from a hidden pose is localised, uploaded, flown and refined
    /// until the live view matches it; reports first and final shot errors.
    /// (Only in a build with the `sim` feature, the default.)
    #[cfg(feature = "sim")]
    Scenario(cli::scenario::ScenarioArgs),
}

fn init_logging(filter: &str) {
    let env = tracing_subscriber::EnvFilter::try_from_default_env()
        .or_else(|_| tracing_subscriber::EnvFilter::try_new(filter))
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    // Colour only for a terminal and without NO_COLOR (https://no-color.org,
    // unset or empty): a log redirected to a file or a pipe carries no
    // escape codes. `shotpilot-sim` decides it alike for its stdout.
    let colour = std::io::IsTerminal::is_terminal(&std::io::stderr())
        && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty());
    tracing_subscriber::fmt()
        .with_env_filter(env)
        .with_ansi(colour)
        .with_writer(std::io::stderr)
        .init();
}

/// The error and its causes on one line, `outer: cause: ...`, each cause
/// once: a cause whose text the line already holds (an error that prints
/// its source in its own message, as many do) is not repeated.
fn error_chain(e: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if text.is_empty() || line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// A configuration file, with the `[sim]` keys only the simulator can
/// check (a build without the simulator parses `[sim]` and leaves them:
/// `run` refuses `[sim] enabled = true` there).
fn load_checked(path: &Path) -> Result<Config> {
    let cfg = Config::load(path)?;
    #[cfg(feature = "sim")]
    shotpilot::simulator::check(&cfg, path)?;
    Ok(cfg)
}

/// The configuration: `--config PATH`, else ./config.toml if present, else defaults.
fn load_config(path: Option<&Path>) -> Result<Config> {
    match path {
        Some(p) => load_checked(p),
        None => {
            let default = Path::new("config.toml");
            if default.is_file() {
                load_checked(default)
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
            eprintln!("error: {}", error_chain(&e));
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    let config = load_config(cli.config.as_deref())?;
    match cli.command {
        Command::Eval(args) => cli::eval::run(args),
        Command::Slam(args) => cli::slam::run(args),
        Command::Shot(args) => cli::shot::run(args),
        Command::Vocab(args) => cli::vocab::run(args),
        Command::Mission(cmd) => cli::mission::run(cmd, &config),
        Command::Run(args) => cli::run::run(args, config, cli.config.as_deref()),
        Command::Features(args) => cli::features::run(args),
        #[cfg(feature = "sim")]
        Command::Scenario(args) => cli::scenario::run(args),
    }
}

#[cfg(test)]
mod tests {
    use super::error_chain;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot read {path}: {source}")]
    struct Wraps {
        path: &'static str,
        source: std::io::Error,
    }

    #[test]
    fn each_cause_is_printed_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such folder");
        let e = anyhow::Error::new(Wraps {
            path: "/x",
            source: io,
        })
        .context("opening the dataset");
        assert_eq!(
            error_chain(&e),
            "opening the dataset: cannot read /x: no such folder"
        );
        let plain = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_chain(&plain), "outer: inner");
    }
}
