//! `shotpilot features`: ORB extraction time per frame on a dataset.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use serde_json::json;

/// Arguments of `shotpilot features`.
#[derive(Args, Debug)]
pub struct FeaturesArgs {
    /// Dataset folder (TUM or EuRoC layout).
    #[arg(value_name = "DATASET")]
    pub dataset: PathBuf,
    /// Features wanted per frame.
    #[arg(long = "features", default_value_t = 1000, value_name = "N")]
    pub n_features: usize,
    /// Threads per frame (1 or 2; the pyramid levels are split among them).
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub threads: usize,
    /// Passes over the dataset; the figures are over all timed frames.
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub repeat: usize,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Times the extraction on every frame and prints the summary.
pub fn run(args: FeaturesArgs) -> Result<()> {
    use shotpilot::features::{OrbExtractor, Params};
    use shotpilot::features_eval as feval;
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
