//! `shotpilot slam`'s arguments.

use std::path::PathBuf;

use clap::Args;

/// Arguments of `shotpilot slam`.
#[derive(Args, Debug)]
pub struct SlamArgs {
    /// Dataset folder (TUM or EuRoC layout).
    pub dataset: PathBuf,
    /// Folder for trajectory.txt, keyframes.txt and, per loop closed, the
    /// keyframes just before and after its correction
    /// (loopN_keyframes_before.txt, loopN_keyframes_after.txt); created if
    /// missing.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Ground truth (TUM format); default: the dataset's own, if any.
    #[arg(long, value_name = "FILE")]
    pub gt: Option<PathBuf>,
    /// Run local mapping after each keyframe on the same thread, so runs
    /// repeat exactly (and frames are not paced).
    #[arg(long)]
    pub sequential: bool,
    /// Replay speed relative to the frame timestamps (two-thread mode);
    /// 0 feeds frames as fast as tracking takes them.
    #[arg(long, default_value_t = 1.0, value_name = "X")]
    pub speed: f64,
    /// Save the map to this file at the end.
    #[arg(long, value_name = "FILE")]
    pub save_map: Option<PathBuf>,
    /// ORB features per frame.
    #[arg(long, default_value_t = 1000, value_name = "N")]
    pub features: usize,
    /// Other FAST thresholds than the defaults.
    #[command(flatten)]
    pub fast: super::features::FastThresholds,
    /// The camera's rolling-shutter readout, ms (first row to last; 0: a
    /// global shutter). Tracking and bundle adjustment then see each row
    /// from its own pose, moved by the camera's velocity. Default: the
    /// dataset's `exposures.txt` (the simulator's render writes it), else 0.
    #[arg(long, value_name = "MS")]
    pub readout_ms: Option<f64>,
    /// After the run, estimate the rolling-shutter readout from the final
    /// map: its whole bundle adjustment run again under readouts of 0 to
    /// 50 ms in 5 ms steps; the best fit, refined between its neighbours,
    /// is reported (text and JSON) with every readout's reprojection RMSE.
    /// Takes one whole-map adjustment per readout (seconds on a few hundred
    /// keyframes).
    #[arg(long)]
    pub estimate_readout: bool,
    /// Use only the first N frames.
    #[arg(long, value_name = "N")]
    pub max_frames: Option<usize>,
    /// Seed of the randomised steps (RANSAC).
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub seed: u64,
    /// Largest timestamp difference when pairing with the ground truth, seconds.
    #[arg(long, default_value_t = 0.02, value_name = "S")]
    pub max_dt: f64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Run without loop closing.
    #[arg(long)]
    pub no_loop_closing: bool,
    /// Loop closing: fit the loop's Sim(3) again on the matches found by
    /// projection (experimental, off by default).
    #[arg(long)]
    pub loop_refit: bool,
    /// Loop closing: a bundle adjustment over the whole map after each
    /// loop's essential graph (experimental, off by default).
    #[arg(long)]
    pub loop_global_ba: bool,
    /// Telemetry priors from the dataset's telemetry.txt (GNSS fixes with
    /// their reported accuracy, barometric altitude): the map is put in
    /// local NED once the fixes span a baseline, and bundle adjustment keeps
    /// it there. Without the file the run is vision-only.
    #[arg(long)]
    pub priors: bool,
    /// Telemetry-aided tracking from the dataset's telemetry.txt: a frame
    /// vision cannot pose is predicted from the last one it did by the
    /// reported attitude (and the GNSS once the map is in local NED), and
    /// the local map searched around that; the summary says how many
    /// frames each way posed and the ATE of each. Needs the attitude
    /// columns; without them the run is vision-only.
    #[arg(long)]
    pub aid: bool,
    /// Replace COUNT frames from frame START on by black frames (a forced
    /// tracking loss); may be given more than once.
    #[arg(long, value_name = "START:COUNT", value_parser = parse_blackout)]
    pub blackout: Vec<(usize, usize)>,
    /// After a tracking loss, only relocalise (no new map).
    #[arg(long)]
    pub no_new_maps: bool,
    /// Start new maps after a loss but never merge them.
    #[arg(long)]
    pub no_merging: bool,
    /// Every N frames, sample the process's resident memory and the map's
    /// stores (`Map::footprint`) and report them (0: only at the end).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub memory_every: usize,
    /// Fly the frames this many times, every other lap backwards (a patrol
    /// over the same ground: the motion stays continuous, the map should
    /// stop growing after the first lap); frame indices and timestamps go
    /// on increasing. The ground truth matches the first lap only.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub laps: usize,
    /// Frames counted as "after" a loop's correction or a global BA in the
    /// frame-time report.
    #[arg(long, default_value_t = 30, value_name = "N")]
    pub after_frames: usize,
}

/// `START:COUNT` of `--blackout`.
fn parse_blackout(s: &str) -> std::result::Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(':')
        .ok_or_else(|| format!("{s:?}: expected START:COUNT"))?;
    let start = a.trim().parse().map_err(|e| format!("{a:?}: {e}"))?;
    let count = b.trim().parse().map_err(|e| format!("{b:?}: {e}"))?;
    Ok((start, count))
}
