//! `shotpilot features`: ORB extraction time per frame on a dataset, and
//! with `--pairs` where the matches between consecutive frames are lost
//! (too few corners, descriptors that do not match, the ratio test, the
//! rotation check), checked against the ground truth's motion.

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
    /// Other FAST thresholds than the SLAM's.
    #[command(flatten)]
    pub fast: FastThresholds,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
    /// Instead of timing: match every frame with the next as the SLAM's
    /// initialisation does (a window of `init_window` pixels, levels up to
    /// `init_max_octave`) and count, per pair, the keypoints, the nearest
    /// descriptors within `th_low`, those the ratio test keeps and those
    /// the rotation check keeps after it; with ground truth, how many of
    /// each agree with the true motion (within 2 pixels, times the level's
    /// scale, of the epipolar line; exact on the simulator's renders, only
    /// as good as the ground truth is the camera's pose elsewhere).
    #[arg(long)]
    pub pairs: bool,
    /// With `--pairs`: also print one line per pair.
    #[arg(long, requires = "pairs")]
    pub per_pair: bool,
    /// With `--pairs` and ground truth: search only the candidates within
    /// this many pixels (times the level's scale) of the epipolar line of
    /// the true motion, as a search from the telemetry's predicted motion
    /// would (this is its best case: the prediction without its error).
    #[arg(long, requires = "pairs", value_name = "PX")]
    pub guided_band: Option<f64>,
    /// With `--pairs`: the largest descriptor distance of a match, bits
    /// (default: the SLAM's `th_low`, 50).
    #[arg(long, requires = "pairs", value_name = "BITS")]
    pub th_low: Option<u32>,
}

/// The extractor's FAST thresholds, for trying others than the SLAM's
/// defaults on footage (`features`, `slam`).
#[derive(Args, Debug, Clone, Copy, Default)]
pub struct FastThresholds {
    /// FAST threshold tried first in every cell (the extractor's
    /// `ini_th_fast`; default: the SLAM's).
    #[arg(long, value_name = "T")]
    pub ini_th_fast: Option<u8>,
    /// FAST threshold in cells where the first finds nothing, at the least
    /// (`min_th_fast`; default: the SLAM's).
    #[arg(long, value_name = "T")]
    pub min_th_fast: Option<u8>,
    /// That fallback threshold as this many times the image's noise
    /// deviation, when larger (`noise_threshold_factor`; 0: off; default:
    /// the SLAM's).
    #[arg(long, value_name = "K")]
    pub noise_factor: Option<f32>,
}

impl FastThresholds {
    /// `params` with the thresholds given here.
    pub fn apply(&self, params: &mut shotpilot::features::Params) {
        if let Some(t) = self.ini_th_fast {
            params.ini_th_fast = t;
        }
        if let Some(t) = self.min_th_fast {
            params.min_th_fast = t;
        }
        if let Some(k) = self.noise_factor {
            params.noise_threshold_factor = k;
        }
    }
}

/// Times the extraction on every frame and prints the summary.
pub fn run(args: FeaturesArgs) -> Result<()> {
    use shotpilot::features::{OrbExtractor, Params};
    use shotpilot::features_eval as feval;
    let ds = shotpilot::video::dataset::Dataset::open(&args.dataset)
        .with_context(|| format!("opening {}", args.dataset.display()))?;
    let (times, frames): (Vec<f64>, Vec<_>) = ds
        .frames()
        .map(|f| f.map(|f| (f.timestamp, f.image)))
        .collect::<Result<Vec<_>, _>>()?
        .into_iter()
        .unzip();
    let mut params = Params {
        n_features: args.n_features,
        threads: args.threads,
        ..Params::default()
    };
    args.fast.apply(&mut params);
    let mut ex = OrbExtractor::new(params)?;
    if args.pairs {
        return pairs::run(&args, &ds, &times, &frames, &mut ex);
    }
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

mod pairs {
    //! The match funnel between consecutive frames (`--pairs`).

    use anyhow::Result;
    use nalgebra::{Isometry3, Matrix3, Vector3};
    use serde_json::json;
    use shotpilot::camera::Camera;
    use shotpilot::eval::Trajectory;
    use shotpilot::features::{Features, OrbExtractor};
    use shotpilot::matching::{Bounds, FeatureGrid};
    use shotpilot::slam::TrackingParams;
    use shotpilot::slam::matcher::{MatcherParams, search_for_initialization};
    use shotpilot::video::dataset::Dataset;

    use super::FeaturesArgs;

    /// The stages of the funnel, in order.
    const STAGES: [&str; 3] = ["descriptor", "ratio", "rotation"];

    /// One pair's counts.
    struct Pair {
        index: usize,
        keypoints: (usize, usize),
        /// Matches after each of [`STAGES`].
        matches: [usize; 3],
        /// Of those, agreeing with the true motion (None: no usable truth).
        agree: Option<[usize; 3]>,
    }

    /// The ground truth's pose within 20 ms of `t` (the nearest).
    fn truth_at(gt: &Trajectory, t: f64) -> Option<Isometry3<f64>> {
        gt.poses
            .iter()
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
            .filter(|p| (p.t - t).abs() <= 0.02)
            .map(|p| p.world_from_cam)
    }

    /// The essential matrix from camera 1 to camera 2 (None: no baseline
    /// to speak of, where every match agrees with the epipolar geometry).
    fn essential(w1: &Isometry3<f64>, w2: &Isometry3<f64>) -> Option<Matrix3<f64>> {
        let c2_from_c1 = w2.inverse() * w1;
        let t = c2_from_c1.translation.vector;
        if t.norm() < 1e-6 {
            return None;
        }
        Some(t.cross_matrix() * c2_from_c1.rotation.to_rotation_matrix().into_inner())
    }

    /// The larger of the two point-to-epipolar-line distances, pixels.
    fn epipolar_px(e: &Matrix3<f64>, cam: &Camera, u1: (f32, f32), u2: (f32, f32)) -> f64 {
        let n = |u: (f32, f32)| {
            Vector3::new(
                (f64::from(u.0) - cam.cx) / cam.fx,
                (f64::from(u.1) - cam.cy) / cam.fy,
                1.0,
            )
        };
        let (x1, x2) = (n(u1), n(u2));
        let l2 = e * x1;
        let l1 = e.transpose() * x2;
        let d2 = x2.dot(&l2).abs() / l2.x.hypot(l2.y).max(1e-12);
        let d1 = x1.dot(&l1).abs() / l1.x.hypot(l1.y).max(1e-12);
        d1.max(d2) * cam.fx
    }

    #[allow(clippy::too_many_arguments)]
    fn funnel(
        a: &Features,
        b: &Features,
        grid: &FeatureGrid,
        tracking: &TrackingParams,
        e: Option<&Matrix3<f64>>,
        cam: &Camera,
        scale_factor: f64,
        guided_band: Option<f64>,
    ) -> ([usize; 3], Option<[usize; 3]>) {
        let base = tracking.matcher;
        let level_px = |px: f64, i: usize, j: usize| {
            px * scale_factor.powi(i32::from(a.keypoints[i].octave.max(b.keypoints[j].octave)))
        };
        // The guided search: candidates near the true motion's epipolar
        // line (all of them without truth or without a band).
        let accept = |i: usize, j: usize| match (guided_band, e) {
            (Some(band), Some(e)) => {
                let (k1, k2) = (&a.keypoints[i], &b.keypoints[j]);
                epipolar_px(e, cam, (k1.ux, k1.uy), (k2.ux, k2.uy)) <= level_px(band, i, j)
            }
            _ => true,
        };
        // The ratio test off (a tie still fails it) and one rotation bin
        // (nothing rejected), then the ratio on, then the rotation check.
        let settings = [
            MatcherParams {
                init_ratio: 1.0,
                histo_bins: 1,
                ..base
            },
            MatcherParams {
                histo_bins: 1,
                ..base
            },
            base,
        ];
        let prev: Vec<_> = a
            .keypoints
            .iter()
            .map(|k| nalgebra::Point2::new(f64::from(k.ux), f64::from(k.uy)))
            .collect();
        let mut matches = [0; 3];
        let mut agree = [0; 3];
        for (s, m) in settings.iter().enumerate() {
            let m12 = search_for_initialization(
                &a.keypoints,
                &a.descriptors,
                &b.keypoints,
                &b.descriptors,
                grid,
                &prev,
                tracking.init_window,
                tracking.init_max_octave,
                m,
                accept,
            );
            for (i, j) in m12.iter().enumerate() {
                let Some(j) = *j else { continue };
                matches[s] += 1;
                if let Some(e) = e {
                    let (k1, k2) = (&a.keypoints[i], &b.keypoints[j]);
                    if epipolar_px(e, cam, (k1.ux, k1.uy), (k2.ux, k2.uy)) <= level_px(2.0, i, j) {
                        agree[s] += 1;
                    }
                }
            }
        }
        (matches, e.map(|_| agree))
    }

    fn median(v: impl Iterator<Item = f64>) -> f64 {
        let v: Vec<f64> = v.collect();
        shotpilot::stats::median(&v).unwrap_or(f64::NAN)
    }

    /// The funnel over every consecutive pair of `frames`, printed.
    pub(super) fn run(
        args: &FeaturesArgs,
        ds: &Dataset,
        times: &[f64],
        frames: &[image::GrayImage],
        ex: &mut OrbExtractor,
    ) -> Result<()> {
        let mut tracking = TrackingParams::default();
        if let Some(t) = args.th_low {
            tracking.matcher.th_low = t;
        }
        if args.guided_band.is_some() && ds.groundtruth.is_none() {
            anyhow::bail!(
                "--guided-band needs the dataset's ground truth (its motion guides the search)"
            );
        }
        let cam = ds.camera;
        let bounds = Bounds::of(&cam);
        let scale_factor = f64::from(ex.params().scale_factor);
        let mut out = Vec::new();
        let mut prev: Option<Features> = None;
        for (k, img) in frames.iter().enumerate() {
            let f = ex.extract(img, Some(&cam));
            if let Some(a) = prev.take() {
                let grid = FeatureGrid::new(&f.keypoints, bounds);
                let e = ds.groundtruth.as_ref().and_then(|gt| {
                    let w1 = truth_at(gt, *times.get(k - 1)?)?;
                    let w2 = truth_at(gt, *times.get(k)?)?;
                    essential(&w1, &w2)
                });
                let (matches, agree) = funnel(
                    &a,
                    &f,
                    &grid,
                    &tracking,
                    e.as_ref(),
                    &cam,
                    scale_factor,
                    args.guided_band,
                );
                let p = Pair {
                    index: k - 1,
                    keypoints: (a.len(), f.len()),
                    matches,
                    agree,
                };
                if args.per_pair && !args.json {
                    println!(
                        "pair {}-{}: keypoints {} / {}, matches {:?}, agreeing with the truth {:?}",
                        p.index,
                        p.index + 1,
                        p.keypoints.0,
                        p.keypoints.1,
                        p.matches,
                        p.agree
                    );
                }
                out.push(p);
            }
            prev = Some(f);
        }
        let with_truth: Vec<&Pair> = out.iter().filter(|p| p.agree.is_some()).collect();
        let med_kp = median(out.iter().map(|p| p.keypoints.0 as f64));
        let med_m: Vec<f64> = (0..3)
            .map(|s| median(out.iter().map(|p| p.matches[s] as f64)))
            .collect();
        let med_a: Vec<f64> = (0..3)
            .map(|s| {
                median(
                    with_truth
                        .iter()
                        .filter_map(|p| p.agree.map(|a| a[s] as f64)),
                )
            })
            .collect();
        // Shares over all pairs with truth: agreeing of the matches at each
        // stage, and what each check removed of the agreeing ones.
        let sum = |f: &dyn Fn(&Pair) -> usize| with_truth.iter().map(|p| f(p)).sum::<usize>();
        let agree_share: Vec<f64> = (0..3)
            .map(|s| {
                sum(&|p| p.agree.map_or(0, |a| a[s])) as f64 / sum(&|p| p.matches[s]).max(1) as f64
            })
            .collect();
        let lost = |s: usize| {
            let before = sum(&|p| p.agree.map_or(0, |a| a[s - 1]));
            let after = sum(&|p| p.agree.map_or(0, |a| a[s]));
            before.saturating_sub(after) as f64 / before.max(1) as f64
        };
        let weak = out
            .iter()
            .filter(|p| p.matches[2] < tracking.init_min_matches)
            .count();
        if args.json {
            let per: Vec<_> = out
                .iter()
                .map(|p| {
                    json!({"pair": p.index, "keypoints": [p.keypoints.0, p.keypoints.1],
                           "matches": p.matches, "agree": p.agree})
                })
                .collect();
            let o = json!({
                "dataset": args.dataset,
                "pairs": out.len(),
                "pairs_with_truth": with_truth.len(),
                "stages": STAGES,
                "median_keypoints": med_kp,
                "median_matches": med_m,
                "median_agreeing": med_a,
                "agreeing_share": agree_share,
                "agreeing_lost_to_ratio": lost(1),
                "agreeing_lost_to_rotation": lost(2),
                "pairs_under_init_min_matches": weak,
                "init_min_matches": tracking.init_min_matches,
                "th_low": tracking.matcher.th_low,
                "guided_band_px": args.guided_band,
                "per_pair": if args.per_pair { serde_json::Value::from(per) } else { serde_json::Value::Null },
            });
            println!("{o}");
        } else {
            println!(
                "descriptors within {} bits{}",
                tracking.matcher.th_low,
                args.guided_band.map_or(String::new(), |b| format!(
                    ", candidates within {b} px of the true motion's epipolar line"
                ))
            );
            println!(
                "{} pairs ({} with ground truth): median keypoints {med_kp:.0}; median matches: descriptor {:.0}, after the ratio test {:.0}, after the rotation check {:.0}",
                out.len(),
                with_truth.len(),
                med_m[0],
                med_m[1],
                med_m[2]
            );
            if !with_truth.is_empty() {
                println!(
                    "agreeing with the true motion: median {:.0} / {:.0} / {:.0}, share {:.1} / {:.1} / {:.1} %; of the agreeing matches the ratio test removed {:.1} %, the rotation check {:.1} % of what was left",
                    med_a[0],
                    med_a[1],
                    med_a[2],
                    agree_share[0] * 100.0,
                    agree_share[1] * 100.0,
                    agree_share[2] * 100.0,
                    lost(1) * 100.0,
                    lost(2) * 100.0
                );
            }
            println!(
                "{weak} of {} pairs keep fewer than the {} matches the initialisation needs",
                out.len(),
                tracking.init_min_matches
            );
        }
        Ok(())
    }
}
