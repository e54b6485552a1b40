//! `shotpilot slam`: run the SLAM on a dataset and report.

use std::io::IsTerminal;
use std::sync::Arc;
use std::sync::mpsc::sync_channel;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};

use shotpilot::eval::Trajectory;
use shotpilot::optimize::BaParams;
use shotpilot::slam::priors::{PriorParams, Priors, TelemetryFeed, TelemetryLog};
use shotpilot::slam::{self, Slam, TrackState};

pub use super::slam_args::SlamArgs;
use super::slam_memory::{MemorySample, memory_sample};
use super::slam_report::{self, FrameStats};
use super::slam_timing;
use shotpilot::video::dataset::Dataset;

/// Runs the SLAM over the dataset and prints timing, counts and accuracy.
pub fn run(args: SlamArgs) -> Result<()> {
    let ds = Dataset::open(&args.dataset)?;
    let n = args.max_frames.map_or(ds.len(), |m| m.min(ds.len()));
    if n == 0 {
        bail!("{}: no frames to process", args.dataset.display());
    }
    if args.laps == 0 {
        bail!("--laps must be at least 1");
    }
    if !(args.speed >= 0.0 && args.speed.is_finite()) {
        bail!("--speed must be a non-negative number, got {}", args.speed);
    }
    let gt = match &args.gt {
        Some(p) => Some(Trajectory::read_tum(p)?),
        None => ds.groundtruth.clone(),
    };
    let mut params = slam::Params {
        sequential: args.sequential,
        ..Default::default()
    };
    params.tracking.features.n_features = args.features;
    args.fast.apply(&mut params.tracking.features);
    params.tracking.init_features = args.features * 2;
    params.tracking.seed = args.seed;
    if args.no_new_maps {
        params.tracking.new_map_after_lost_frames = None;
    }
    if args.no_loop_closing {
        params.loop_closing = None;
    } else if let Some(l) = &mut params.loop_closing {
        l.seed = args.seed;
        l.refit_on_projection = args.loop_refit;
        l.merging = !args.no_merging;
        if args.loop_global_ba {
            l.global_ba = Some(BaParams::default());
        }
    }
    // The dataset's telemetry: priors with --priors, and the after-the-fact
    // georeference of a vision-only map either way.
    let tel_path = args.dataset.join("telemetry.txt");
    let telemetry = if tel_path.exists() {
        Some(TelemetryLog::read(&tel_path)?)
    } else {
        None
    };
    let prior_params = PriorParams::default();
    if args.priors {
        match &telemetry {
            Some(log) => {
                params.priors = Some(Priors::with_feed(
                    TelemetryFeed::fixed(log.clone()),
                    prior_params.clone(),
                ))
            }
            None => tracing::warn!(
                path = %tel_path.display(),
                "--priors: no telemetry.txt, the map stays vision-only"
            ),
        }
    }
    if args.aid {
        match &telemetry {
            Some(log) if log.samples().iter().any(|s| s.ned_from_cam.is_some()) => {
                params.telemetry_aid =
                    Some(slam::TelemetryAid::new(TelemetryFeed::fixed(log.clone())))
            }
            _ => tracing::warn!(
                path = %tel_path.display(),
                "--aid: no telemetry.txt with the attitude columns, tracking is vision-only"
            ),
        }
    }
    let mut camera = ds.camera;
    if let Some(ms) = args.readout_ms {
        camera.readout_s = ms / 1000.0;
        camera
            .validate()
            .with_context(|| format!("--readout-ms {ms}"))?;
    }
    tracing::info!(
        readout_ms = camera.readout_s * 1000.0,
        "rolling shutter {}",
        if camera.readout_s > 0.0 {
            "modelled"
        } else {
            "off (a global shutter)"
        }
    );
    let mut system = Slam::new(camera, params).context("starting the SLAM")?;

    // Decode frames ahead on a reader thread (decoding is not tracking).
    // With --laps the dataset's n frames are flown again and again, every
    // other lap backwards: lap k's j-th frame is dataset frame j (k even)
    // or n-1-j (k odd), at a time that goes on from the lap before.
    let laps = args.laps;
    let t_first_frame = ds.timestamp(0).unwrap_or(0.0);
    let t_span = ds.timestamp(n - 1).unwrap_or(t_first_frame) - t_first_frame;
    let t_step = if n > 1 { t_span / (n - 1) as f64 } else { 0.0 };
    let frame_of = move |k: usize| -> (usize, f64) {
        let (lap, j) = (k / n, k % n);
        let i = if lap.is_multiple_of(2) { j } else { n - 1 - j };
        (i, lap as f64 * (t_span + t_step))
    };
    let n_single = n;
    let n = n * laps;
    let (tx, rx) = sync_channel(8);
    let reader_ds = ds.clone();
    let blackout = args.blackout.clone();
    let reader = std::thread::Builder::new()
        .name("frame-reader".into())
        .spawn(move || {
            for k in 0..n {
                let (i, offset) = frame_of(k);
                let mut f = reader_ds.frame(i).map(|mut fr| {
                    if k >= n_single {
                        let t = fr.timestamp - t_first_frame;
                        let t = if (k / n_single).is_multiple_of(2) {
                            t
                        } else {
                            t_span - t
                        };
                        fr.timestamp = t_first_frame + offset + t;
                        fr.index = k;
                    }
                    fr
                });
                let i = k;
                if blackout.iter().any(|&(a, c)| i >= a && i < a + c)
                    && let Ok(fr) = &mut f
                {
                    fr.image = image::GrayImage::new(fr.image.width(), fr.image.height());
                }
                let stop = f.is_err();
                if tx.send(f).is_err() || stop {
                    break;
                }
            }
        })
        .context("starting the frame reader")?;

    let bar = if std::io::stderr().is_terminal() && !args.json {
        let b = indicatif::ProgressBar::new(n as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} frames {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let mut extract_ms = Vec::with_capacity(n);
    let mut track_ms = Vec::with_capacity(n);
    // This thread's CPU time per frame (the machine may be busy with other
    // work, which wall time would count): extraction, tracking with
    // extraction, and tracking without it.
    let mut extract_cpu = Vec::with_capacity(n);
    let mut track_cpu = Vec::with_capacity(n);
    let mut track_only_cpu = Vec::with_capacity(n);
    let mut tracked_frames = std::collections::HashSet::new();
    let mut by_source: std::collections::BTreeMap<&'static str, usize> = Default::default();
    let mut lost_frames = 0usize;
    let mut spans: Vec<slam_timing::FrameSpan> = Vec::with_capacity(n);
    let mut memory: Vec<MemorySample> = Vec::new();
    let start = Instant::now();
    let mut t_first: Option<f64> = None;
    for i in 0..n {
        if args.memory_every > 0 && i % args.memory_every == 0 {
            memory.push(memory_sample(&system, i));
        }
        let frame = rx.recv().context("frame reader stopped")??;
        if !args.sequential && args.speed > 0.0 {
            let t0 = *t_first.get_or_insert(frame.timestamp);
            let due = Duration::from_secs_f64(((frame.timestamp - t0) / args.speed).max(0.0));
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        let from = Instant::now();
        let out = system.process(frame.index as u64, frame.timestamp, Arc::new(frame.image));
        spans.push(slam_timing::FrameSpan {
            from,
            to: Instant::now(),
            track_ms: out.track_ms,
            wait_ms: out.lock_wait_ms,
        });
        extract_ms.push(out.extract_ms);
        track_ms.push(out.track_ms);
        if let (Some(e), Some(t)) = (out.extract_cpu_ms, out.track_cpu_ms) {
            extract_cpu.push(e);
            track_cpu.push(t);
            track_only_cpu.push(t - e);
        }
        if let Some(s) = out.source {
            *by_source.entry(s.name()).or_default() += 1;
        }
        match out.state {
            TrackState::Tracking => {
                tracked_frames.insert(frame.index as u64);
            }
            TrackState::Lost => lost_frames += 1,
            TrackState::NotInitialized => {}
        }
        if let Some(r) = &out.reason {
            tracing::debug!(frame = frame.index, reason = %r, "frame not tracked");
        }
        bar.set_message(format!("{:?}", out.state));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let _ = reader.join();
    let wall_s = start.elapsed().as_secs_f64();
    memory.push(memory_sample(&system, n));
    let run = system.finish();
    let readout_estimate = if args.estimate_readout {
        let grid: Vec<f64> = (0..=10).map(|i| 0.005 * f64::from(i)).collect();
        let e = slam::shutter::estimate_readout(&run.map, &grid, &BaParams::default());
        if e.is_none() {
            tracing::warn!("--estimate-readout: the map has nothing to adjust");
        }
        e
    } else {
        None
    };
    slam_report::report(
        &args,
        gt.as_ref(),
        telemetry.as_ref(),
        &prior_params,
        &run,
        &FrameStats {
            frames: n,
            wall_s,
            extract_ms,
            track_ms,
            extract_cpu,
            track_cpu,
            track_only_cpu,
            tracked_frames,
            by_source,
            lost_frames,
            spans,
            memory,
            readout_s: camera.readout_s,
            readout_estimate,
        },
    )
}
