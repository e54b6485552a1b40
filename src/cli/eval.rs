//! `shotpilot eval`: a trajectory against the ground truth.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use serde_json::json;

use shotpilot::eval::{self, AlignMode, Trajectory};

/// Arguments of `shotpilot eval`.
#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Ground-truth trajectory (TUM format).
    #[arg(long, value_name = "FILE")]
    pub gt: PathBuf,
    /// Estimated trajectory (TUM format).
    #[arg(long, value_name = "FILE")]
    pub est: PathBuf,
    /// Alignment of the estimate before measuring.
    #[arg(long, value_enum, default_value = "sim3")]
    pub align: AlignMode,
    /// Largest timestamp difference for a pair, seconds.
    #[arg(long, default_value_t = 0.02, value_name = "S")]
    pub max_dt: f64,
    /// Frame distance for the relative pose error.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub rpe_delta: usize,
    /// Draw both trajectories (top view) and the error over time to a PNG.
    #[arg(long, value_name = "FILE.png")]
    pub plot: Option<PathBuf>,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Reads both trajectories, aligns, and prints the errors.
pub fn run(args: EvalArgs) -> Result<()> {
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
