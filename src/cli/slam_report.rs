//! `shotpilot slam`'s report: the run's figures against the ground truth
//! and the telemetry (ATE overall, per pose source and in local NED, each
//! loop's and merge's effect, refused candidates, the revisit drift), the
//! frame-time and memory reports, the output files, printed as text or as
//! one JSON object.

use std::collections::{BTreeMap, HashSet};

use anyhow::{Context, Result};
use serde_json::json;

use shotpilot::eval::{self, Trajectory};
use shotpilot::geo::align::{Pair, fit_pairs};
use shotpilot::lie::Sim3;
use shotpilot::slam::priors::{PriorParams, TelemetryLog};
use shotpilot::slam::{self, MapMode, SlamRun};
use shotpilot::stats;

use super::slam_args::SlamArgs;
use super::slam_memory::{self, MemorySample, rss_mib};
use super::slam_timing;

/// What the tracking thread measured over the run, for the report.
pub(super) struct FrameStats {
    /// Frames processed (every lap's).
    pub(super) frames: usize,
    /// Wall time of the run, seconds.
    pub(super) wall_s: f64,
    /// Per frame: extraction and tracking (with extraction) wall time, ms.
    pub(super) extract_ms: Vec<f64>,
    pub(super) track_ms: Vec<f64>,
    /// Per frame: the tracking thread's CPU time for extraction, tracking
    /// with extraction, and tracking without it, ms (empty where the
    /// platform does not tell).
    pub(super) extract_cpu: Vec<f64>,
    pub(super) track_cpu: Vec<f64>,
    pub(super) track_only_cpu: Vec<f64>,
    /// The indices of the frames tracked when they came (every lap's
    /// frame has its own).
    pub(super) tracked_frames: HashSet<u64>,
    /// Frames per pose source.
    pub(super) by_source: BTreeMap<&'static str, usize>,
    /// Frames lost.
    pub(super) lost_frames: usize,
    /// Each frame's span on the tracking thread.
    pub(super) spans: Vec<slam_timing::FrameSpan>,
    /// The memory samples taken.
    pub(super) memory: Vec<MemorySample>,
    /// The rolling-shutter readout the run modelled, seconds (0: a global
    /// shutter).
    pub(super) readout_s: f64,
    /// The readout estimated from the final map (`--estimate-readout`).
    pub(super) readout_estimate: Option<shotpilot::slam::shutter::ReadoutEstimate>,
}

/// Median and 95th percentile of each per-frame and per-keyframe time, ms.
struct Times {
    extract: (f64, f64),
    track: (f64, f64),
    /// CPU times: extraction, tracking with and without extraction; None
    /// without CPU times.
    cpu: Option<[(f64, f64); 3]>,
    mapping: (f64, f64),
    local_ba: (f64, f64),
}

/// The run's figures, computed once for either form of the report.
struct Figures {
    timing: slam_timing::TimingReport,
    rss: Option<(f64, f64)>,
    /// Frames with a pose in the trajectory, keyframes in it.
    posed: usize,
    keyframes_posed: usize,
    initialized: bool,
    mode: MapMode,
    /// The map in local NED and what put it there.
    ned_from_map: Option<(Sim3, &'static str)>,
    /// In NED: without alignment, and with a Sim(3) to the ground truth.
    ned_eval: Option<(eval::Evaluation, eval::Evaluation)>,
    ate: Option<eval::Evaluation>,
    ate_kf: Option<eval::Evaluation>,
    ate_by_source: BTreeMap<&'static str, (f64, usize)>,
    loops: Vec<serde_json::Value>,
    merges: Vec<serde_json::Value>,
    map_starts: Vec<serde_json::Value>,
    maps_at_end: Vec<serde_json::Value>,
    /// Refused candidates by reason: (count, farther than 10 m in the
    /// ground truth).
    refusals: BTreeMap<String, (usize, usize)>,
    merge_refusals: BTreeMap<String, (usize, usize)>,
    revisit: Option<(f64, f64, f64)>,
    times: Times,
    /// Why the run never initialised.
    reason: Option<String>,
    /// The ground truth's path length; None without a ground truth.
    gt_path_length: Option<f64>,
}

/// Evaluates the run (`gt`: the ground truth; `telemetry`: the dataset's,
/// for the after-the-fact georeference of a vision-only map), writes the
/// output files and the map, and prints the report.
pub(super) fn report(
    args: &SlamArgs,
    gt: Option<&Trajectory>,
    telemetry: Option<&TelemetryLog>,
    prior_params: &PriorParams,
    run: &SlamRun,
    stats: &FrameStats,
) -> Result<()> {
    let mut windows: Vec<slam_timing::Window> = Vec::new();
    for l in &run.loops {
        let kf = l.summary.current.0;
        for (kind, w) in [
            ("loop", l.correction_window),
            ("global_ba", l.global_ba_window),
        ] {
            if let Some((from, to)) = w {
                windows.push(slam_timing::Window { kind, kf, from, to });
            }
        }
    }
    windows.extend(
        run.loop_holds
            .iter()
            .filter(|h| h.kind == shotpilot::slam::HoldKind::Merge)
            .map(|h| slam_timing::Window {
                kind: "merge",
                kf: h.kf.0,
                from: h.from,
                to: h.to,
            }),
    );
    let timing = slam_timing::report(&stats.spans, &run.loop_holds, &windows, args.after_frames);
    let rss = rss_mib();
    let traj = run.trajectory();
    let kf_traj = run.keyframe_trajectory();
    let initialized = run.initialized_at.is_some();
    let mode = run.map.mode();
    // The map in local NED: as it stands when gps-aided; for a vision-only
    // map, moved by a Sim(3) fitted to the telemetry's fixes after the fact.
    let ned_from_map: Option<(Sim3, &'static str)> = match (mode, telemetry) {
        (MapMode::GpsAided, _) => Some((shotpilot::lie::Sim3::identity(), "map")),
        (MapMode::VisionOnly, Some(log)) if initialized => {
            let pairs: Vec<Pair> = run
                .map
                .keyframes()
                .filter_map(|k| {
                    let s = log
                        .at(k.timestamp, prior_params.max_dt_s)
                        .filter(|s| s.fix)?;
                    Some(Pair {
                        kf_id: k.id.0 as u64,
                        p_map: nalgebra::Point3::from(k.center()),
                        p_ned: nalgebra::Point3::from(s.gps_ned),
                        time: k.timestamp,
                        orientations: None,
                        v_ned: None,
                    })
                })
                .collect();
            match fit_pairs(&pairs, &prior_params.align, None, prior_params.align.seed) {
                Ok(f) => Some((f.ned_from_map, "after_the_fact")),
                Err(e) => {
                    tracing::warn!(error = %e, "no after-the-fact georeference");
                    None
                }
            }
        }
        _ => None,
    };
    let ned_traj = ned_from_map.map(|(s, _)| transformed(&traj, &s));

    if let Some(dir) = &args.out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        traj.write_tum(&dir.join("trajectory.txt"))?;
        if let Some(t) = &ned_traj {
            t.write_tum(&dir.join("trajectory_ned.txt"))?;
        }
        kf_traj.write_tum(&dir.join("keyframes.txt"))?;
        for (n, l) in run.loops.iter().enumerate() {
            l.keyframes_before
                .write_tum(&dir.join(format!("loop{n}_keyframes_before.txt")))?;
            l.keyframes_after
                .write_tum(&dir.join(format!("loop{n}_keyframes_after.txt")))?;
        }
    }
    if let Some(path) = &args.save_map {
        if initialized {
            slam::mapfile::save(&run.map, path)?;
            tracing::info!(path = %path.display(), keyframes = run.map.keyframe_count(), "map saved");
        } else {
            tracing::warn!("no map to save: not initialised");
        }
    }
    let eval_params = eval::Params {
        max_dt: args.max_dt,
        ..Default::default()
    };
    // In NED: the error a user sees (no alignment) and the scale the
    // ground truth still finds (Sim(3) alignment of the NED trajectory).
    let ned_eval = match (gt, &ned_traj) {
        (Some(gt), Some(t)) => {
            let none = eval::evaluate(
                gt,
                t,
                &eval::Params {
                    align: eval::AlignMode::None,
                    ..eval_params
                },
            )
            .ok();
            let sim3 = eval::evaluate(gt, t, &eval_params).ok();
            none.zip(sim3)
        }
        _ => None,
    };
    let (ate, ate_kf) = match (gt, initialized) {
        (Some(gt), true) => (
            eval::evaluate(gt, &traj, &eval_params).ok(),
            eval::evaluate(gt, &kf_traj, &eval_params).ok(),
        ),
        _ => (None, None),
    };
    // The ATE of each pose source's frames, under the alignment of all.
    let ate_by_source = ate
        .as_ref()
        .map(|a| ate_by_source(a, &run.records, args.max_dt))
        .unwrap_or_default();
    // Each loop: the keyframes' ATE just before and just after its
    // correction, and the ground-truth distance between its two keyframes
    // (a loop between places far apart is a false loop).
    let gt_at = |t: f64| -> Option<nalgebra::Vector3<f64>> {
        let g = gt.as_ref()?;
        g.poses
            .iter()
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
            .filter(|p| (p.t - t).abs() <= args.max_dt)
            .map(|p| p.position())
    };
    // The ground-truth distance of the frames at two times.
    let gt_gap = |a: f64, b: f64| Some((gt_at(a)? - gt_at(b)?).norm());
    // A trajectory's ATE against the ground truth.
    let ate_of = |t: &Trajectory| {
        gt.as_ref()
            .and_then(|g| eval::evaluate(g, t, &eval_params).ok())
            .map(|e| e.ate.rmse)
    };
    let loops: Vec<serde_json::Value> = run
        .loops
        .iter()
        .map(|l| {
            let s = &l.summary;
            let gap = gt_gap(s.current_t, s.loop_t);
            json!({
                "current_kf": s.current.0,
                "loop_kf": s.loop_kf.0,
                "current_t": s.current_t,
                "loop_t": s.loop_t,
                "inliers": s.inliers,
                "projection_matches": s.projection_matches,
                "scale": s.scale,
                "rotation_deg": s.rotation_deg,
                "translation": s.translation,
                "fused": s.fused,
                "graph_edges": l.graph_edges,
                "correction_ms": s.correction_ms,
                "global_ba_ms": s.global_ba_ms,
                "global_ba_rmse_px": l.global_ba_rmse_px,
                "keyframes_ate_before_m": ate_of(&l.keyframes_before),
                "keyframes_ate_after_m": ate_of(&l.keyframes_after),
                "gt_distance_m": gap,
            })
        })
        .collect();
    // Each merge: the old map's and the new map's keyframes' ATE before
    // it (each aligned on its own), the merged map's after, and the
    // ground-truth distance of the two keyframes it joined.
    let merges: Vec<serde_json::Value> = run
        .merges
        .iter()
        .map(|m| {
            let s = &m.summary;
            let gap = gt_gap(s.current_t, s.merge_t);
            json!({
                "current_kf": s.current.0,
                "merge_kf": s.merge_kf.0,
                "current_t": s.current_t,
                "merge_t": s.merge_t,
                "from_map": s.from_map.0,
                "into_map": s.into_map.0,
                "inliers": s.inliers,
                "projection_matches": s.projection_matches,
                "scale": s.scale,
                "keyframes_moved": s.keyframes_moved,
                "fused": s.fused,
                "graph_edges": m.graph_edges,
                "correction_ms": s.correction_ms,
                "old_map_keyframes_ate_before_m": ate_of(&m.old_map_before),
                "new_map_keyframes_ate_before_m": ate_of(&m.new_map_before),
                "keyframes_ate_after_m": ate_of(&m.keyframes_after),
                "gt_distance_m": gap,
            })
        })
        .collect();
    let map_starts: Vec<serde_json::Value> = run
        .map_starts
        .iter()
        .map(|m| {
            json!({
                "map": m.map.0,
                "lost_at_frame": m.lost_at,
                "started_at_frame": m.started_at,
                "initialized_at_frame": m.initialized_at,
                "relocalized_at_frame": m.relocalized_at,
            })
        })
        .collect();
    let maps_at_end: Vec<serde_json::Value> = run
        .map
        .maps()
        .iter()
        .map(|(id, n)| json!({"map": id.0, "keyframes": n, "frames": run.trajectory_in(*id).len()}))
        .collect();
    // Refused consistent candidates by the check they failed, and how many
    // of them the ground truth puts more than 10 m from the keyframe that
    // proposed them (look-alike places: false loops or merges that were
    // stopped).
    let by_reason = |list: &[slam::LoopRefusal]| {
        let mut out: BTreeMap<String, (usize, usize)> = BTreeMap::new();
        for r in list {
            let far = gt_gap(r.current_t, r.candidate_t).is_some_and(|d| d > 10.0);
            let e = out.entry(format!("{:?}", r.reason)).or_default();
            e.0 += 1;
            e.1 += usize::from(far);
        }
        out
    };
    let merge_refusals = by_reason(&run.merge_refusals);
    let refusals = by_reason(&run.loop_refusals);
    let revisit = ate.as_ref().and_then(|e| revisit_drift(e, 10.0));
    let cpu = (!stats.track_cpu.is_empty()).then(|| {
        [
            med_p95(&stats.extract_cpu),
            med_p95(&stats.track_cpu),
            med_p95(&stats.track_only_cpu),
        ]
    });
    let map_ms: Vec<f64> = run.mapping.iter().map(|r| r.total_ms).collect();
    let ba_ms: Vec<f64> = run
        .mapping
        .iter()
        .map(|r| r.ba_ms)
        .filter(|v| *v > 0.0)
        .collect();
    let times = Times {
        extract: med_p95(&stats.extract_ms),
        track: med_p95(&stats.track_ms),
        cpu,
        mapping: med_p95(&map_ms),
        local_ba: med_p95(&ba_ms),
    };
    let reason = if initialized {
        None
    } else {
        run.last_reason.as_ref().map(ToString::to_string)
    };
    let fig = Figures {
        timing,
        rss,
        posed: traj.len(),
        keyframes_posed: kf_traj.len(),
        initialized,
        mode,
        ned_from_map,
        ned_eval,
        ate,
        ate_kf,
        ate_by_source,
        loops,
        merges,
        map_starts,
        maps_at_end,
        refusals,
        merge_refusals,
        revisit,
        times,
        reason,
        gt_path_length: gt.map(|g| g.path_length()),
    };
    if args.json {
        print_json(args, run, stats, &fig);
    } else {
        print_text(args, run, stats, &fig);
    }
    Ok(())
}

/// The report as one JSON object on stdout.
fn print_json(args: &SlamArgs, run: &SlamRun, stats: &FrameStats, fig: &Figures) {
    let Figures {
        timing,
        rss,
        posed,
        initialized,
        mode,
        ned_from_map,
        ned_eval,
        ate,
        ate_kf,
        ate_by_source,
        loops,
        merges,
        map_starts,
        maps_at_end,
        refusals,
        merge_refusals,
        revisit,
        times,
        reason,
        gt_path_length,
        ..
    } = fig;
    let FrameStats {
        frames: n,
        wall_s,
        by_source,
        lost_frames,
        memory,
        ..
    } = stats;
    let mut out = json!({
        "dataset": args.dataset.display().to_string(),
        "frames": n,
        "initialized": initialized,
        "initialized_at_frame": run.initialized_at,
        "reason": reason,
        "tracked_frames": posed,
        "lost_frames": lost_frames,
        "keyframes": run.map.keyframe_count(),
        "map_points": run.map.point_count(),
        "median_extract_ms": times.extract.0,
        "p95_extract_ms": times.extract.1,
        "median_track_ms": times.track.0,
        "p95_track_ms": times.track.1,
        "median_extract_cpu_ms": times.cpu.map(|c| c[0].0),
        "p95_extract_cpu_ms": times.cpu.map(|c| c[0].1),
        "median_track_cpu_ms": times.cpu.map(|c| c[1].0),
        "p95_track_cpu_ms": times.cpu.map(|c| c[1].1),
        "median_track_only_cpu_ms": times.cpu.map(|c| c[2].0),
        "p95_track_only_cpu_ms": times.cpu.map(|c| c[2].1),
        "median_mapping_ms": times.mapping.0,
        "p95_mapping_ms": times.mapping.1,
        "median_local_ba_ms": times.local_ba.0,
        "p95_local_ba_ms": times.local_ba.1,
        "wall_s": wall_s,
        "ate_rmse_m": ate.as_ref().map(|e| e.ate.rmse),
        "ate_max_m": ate.as_ref().map(|e| e.ate.max),
        "ate_matched": ate.as_ref().map(|e| e.matched),
        "ate_scale": ate.as_ref().map(|e| e.alignment.scale),
        "ate_keyframes_rmse_m": ate_kf.as_ref().map(|e| e.ate.rmse),
        "posed_by": by_source,
        "ate_by_source_rmse_m": ate_by_source.iter().map(|(k, v)| (*k, v.0)).collect::<std::collections::BTreeMap<_, _>>(),
        "gt_path_length_m": gt_path_length,
        "sequential": args.sequential,
        "loop_closing": !args.no_loop_closing,

        "loops": loops,
        "loop_refusals": refusals.iter().map(|(r, (n, far))| json!({"reason": r, "count": n, "gt_farther_than_10m": gt_path_length.is_some().then_some(far)})).collect::<Vec<_>>(),
        "revisit_t": revisit.map(|r| r.0),
        "revisit_gt_gap_m": revisit.map(|r| r.1),
        "revisit_drift_m": revisit.map(|r| r.2),
    });
    // The map's frame and its figures in local NED (a second object:
    // one json! of every field overflows the macro's recursion limit).
    let ned = json!({
        "map_mode": mode,
        "georeferenced_at_kf": run.georeferenced.map(|g| g.0.0),
        "georeference_fit_scale": run.georeferenced.map(|g| g.1.ned_from_map.scale),
        "georeference_fit_rms_m": run.georeferenced.map(|g| g.1.rms_m),
        "ned_frame": ned_from_map.map(|n| n.1),
        "ned_ate_rmse_m": ned_eval.as_ref().map(|e| e.0.ate.rmse),
        "ned_ate_max_m": ned_eval.as_ref().map(|e| e.0.ate.max),
        "ned_scale_error": ned_eval.as_ref().map(|e| e.1.alignment.scale - 1.0),
    });
    if let (Some(o), serde_json::Value::Object(n)) = (out.as_object_mut(), ned) {
        o.extend(n);
    }
    let atlas = json!({
        "blackout": args.blackout,
        "new_maps": !args.no_new_maps,
        "merging": !args.no_merging && !args.no_loop_closing,
        "map_starts": map_starts,
        "merges": merges,
        "merge_refusals": merge_refusals.iter().map(|(r, (n, far))| json!({"reason": r, "count": n, "gt_farther_than_10m": gt_path_length.is_some().then_some(far)})).collect::<Vec<_>>(),
        "maps_at_end": maps_at_end,
    });
    if let (Some(o), serde_json::Value::Object(n)) = (out.as_object_mut(), atlas) {
        o.extend(n);
    }
    let shutter = json!({
        "readout_ms": 1000.0 * stats.readout_s,
        "readout_estimate": stats.readout_estimate.as_ref().map(|e| json!({
            "readout_ms": 1000.0 * e.readout_s,
            "trials": e.trials.iter().map(|t| json!({
                "readout_ms": 1000.0 * t.readout_s,
                "cost": t.cost,
                "rmse_px": t.rmse_px,
            })).collect::<Vec<_>>(),
        })),
    });
    if let (Some(o), serde_json::Value::Object(n)) = (out.as_object_mut(), shutter) {
        o.extend(n);
    }
    let perf = json!({
        "frame_time": timing,
        "rss_mib": rss.map(|r| r.0),
        "rss_peak_mib": rss.map(|r| r.1),
        "memory": memory,
    });
    if let (Some(o), serde_json::Value::Object(n)) = (out.as_object_mut(), perf) {
        o.extend(n);
    }
    println!("{out}");
}

/// The report as text on stdout.
fn print_text(args: &SlamArgs, run: &SlamRun, stats: &FrameStats, fig: &Figures) {
    let Figures {
        timing,
        rss,
        posed,
        keyframes_posed,
        initialized,
        mode,
        ned_from_map,
        ned_eval,
        ate,
        ate_kf,
        ate_by_source,
        loops,
        merges,
        maps_at_end,
        refusals,
        merge_refusals,
        revisit,
        times,
        reason,
        gt_path_length,
        ..
    } = fig;
    let FrameStats {
        frames: n,
        wall_s,
        tracked_frames,
        by_source,
        lost_frames,
        memory,
        ..
    } = stats;
    let has_gt = gt_path_length.is_some();
    let tracked = tracked_frames.len();
    if !initialized {
        println!(
            "not initialised after {n} frames: {}",
            reason.as_deref().unwrap_or("no reason recorded")
        );
        return;
    }
    // The counts of the first line and of the ATE line are the same
    // numbers: frames with a pose in the trajectory of the first map
    // (tracked as they came, plus the first frame of the initialisation,
    // posed after the fact, minus frames tracked in the maps started
    // after a loss, and frames whose reference keyframe is gone) and the
    // keyframes of the map.
    // Posed at an initialisation: the first frame of an initialisation
    // pair, not tracked when it came.
    let at_init = run
        .records
        .iter()
        .filter(|r| !tracked_frames.contains(&r.index))
        .count();
    // Tracked when they came but without a pose now: the two frames of
    // a map the telemetry put into the old one were posed by the
    // telemetry first, then by the map (one record each).
    let tracked_unrecorded = {
        let recorded: std::collections::HashSet<u64> =
            run.records.iter().map(|r| r.index).collect();
        tracked_frames
            .iter()
            .filter(|i| !recorded.contains(i))
            .count()
    };
    let first_map = run.first_map();
    let live = |r: &&slam::FrameRecord| run.map.keyframe_pose(r.reference).is_some();
    let in_later_maps = run
        .records
        .iter()
        .filter(live)
        .filter(
            |r| matches!((run.map.map_of(r.reference), first_map), (Some(m), Some(f)) if m != f),
        )
        .count();
    let unposed = run.records.iter().filter(|r| !live(r)).count();
    let mut why = vec![format!("{tracked} tracked")];
    if at_init > 0 {
        why.push(format!("+ {at_init} posed at initialisation"));
    }
    if in_later_maps > 0 {
        why.push(format!(
            "- {in_later_maps} in maps started after a loss (not in the ATE below)"
        ));
    }
    if unposed > 0 {
        why.push(format!("- {unposed} whose reference keyframe is gone"));
    }
    if tracked_unrecorded > 0 {
        why.push(format!(
            "- {tracked_unrecorded} not recorded (tracked frames whose record gave way)"
        ));
    }
    let other = *posed as i64 - (tracked + at_init) as i64
        + (unposed + in_later_maps + tracked_unrecorded) as i64;
    if other != 0 {
        why.push(format!("{other:+} other"));
    }
    println!(
        "{n} frames: initialised at frame {}, {posed} frames posed ({}), {lost_frames} lost, {} keyframes, {} map points, {wall_s:.2} s",
        run.initialized_at.unwrap_or(0),
        why.join(" "),
        run.map.keyframe_count(),
        run.map.point_count()
    );
    let ((med_ex, p95_ex), (med_tr, p95_tr)) = (times.extract, times.track);
    println!(
        "per frame   extraction median {med_ex:.2} ms p95 {p95_ex:.2} ms | tracking (with extraction) median {med_tr:.2} ms p95 {p95_tr:.2} ms"
    );
    if let Some(
        [
            (med_ex_cpu, p95_ex_cpu),
            (med_tr_cpu, p95_tr_cpu),
            (med_tro_cpu, p95_tro_cpu),
        ],
    ) = times.cpu
    {
        println!(
            "per frame, CPU time of the tracking thread: extraction median {med_ex_cpu:.2} ms p95 {p95_ex_cpu:.2} ms | tracking with extraction median {med_tr_cpu:.2} ms p95 {p95_tr_cpu:.2} ms | without median {med_tro_cpu:.2} ms p95 {p95_tro_cpu:.2} ms"
        );
    }
    let ((med_map, p95_map), (med_ba, p95_ba)) = (times.mapping, times.local_ba);
    println!(
        "per keyframe mapping median {med_map:.2} ms p95 {p95_map:.2} ms | local BA median {med_ba:.2} ms p95 {p95_ba:.2} ms"
    );
    print_timing(timing);
    print_shutter(stats);
    if let Some(last) = memory.last() {
        slam_memory::print_memory(memory, last, *rss);
    }
    match (&ate, &ate_kf) {
        (Some(a), Some(k)) => println!(
            "ATE (Sim(3)) all frames rmse {:.4} m max {:.4} m ({} of the {posed} posed frames matched the ground truth within {} s) | keyframes rmse {:.4} m ({} of the {} keyframes matched)",
            a.ate.rmse, a.ate.max, a.matched, args.max_dt, k.ate.rmse, k.matched, keyframes_posed
        ),
        _ if has_gt => println!("ATE: too few poses matched the ground truth"),
        _ => {}
    }
    if by_source.keys().any(|k| *k != "vision") {
        let line: Vec<String> = by_source
            .iter()
            .map(|(k, n)| match ate_by_source.get(k) {
                Some((rmse, m)) => format!("{k} {n} (ATE rmse {rmse:.4} m over {m})"),
                None => format!("{k} {n}"),
            })
            .collect();
        println!("posed by {}", line.join(", "));
    }
    match &run.georeferenced {
        Some((kf, g)) => println!(
            "map mode {mode}: put in local NED by telemetry at keyframe {} (Sim(3) scale {:.4}, {} of {} keyframes with a fix inliers, rms {:.3} m)",
            kf.0, g.ned_from_map.scale, g.inliers, g.pairs, g.rms_m
        ),
        None => println!("map mode {mode}"),
    }
    if let (Some((_, frame)), Some((none, sim3))) = (&ned_from_map, &ned_eval) {
        println!(
            "in local NED ({}): ATE rmse {:.4} m max {:.4} m without alignment; scale error {:+.4} % (Sim(3) to the ground truth)",
            if *frame == "map" {
                "the map's own frame"
            } else {
                "vision-only map, Sim(3) fitted to the GNSS fixes after the fact"
            },
            none.ate.rmse,
            none.ate.max,
            (sim3.alignment.scale - 1.0) * 100.0
        );
    }
    if let Some((t, gap, drift)) = revisit {
        println!(
            "revisit of the start at t = {t:.2} s ({gap:.2} m from it): drift {drift:.4} m (aligned estimate's displacement against the ground truth's)"
        );
    }
    let rejects: Vec<String> = refusals
        .iter()
        .map(|(r, (n, far))| {
            if has_gt {
                format!("{r} {n} ({far} more than 10 m apart in the ground truth)")
            } else {
                format!("{r} {n}")
            }
        })
        .collect();
    println!(
        "loop closing {}: {} loops closed{}",
        if args.no_loop_closing { "off" } else { "on" },
        run.loops.len(),
        if rejects.is_empty() {
            String::new()
        } else {
            format!(" (consistent candidates refused: {})", rejects.join(", "))
        }
    );
    for l in loops {
        let f = |k: &str| l[k].as_f64().map_or("-".to_string(), |v| format!("{v:.4}"));
        println!(
            "  loop keyframe {} (t {:.2} s) -> {} (t {:.2} s): {} Sim(3) inliers, {} matches by projection, scale {:.4}, rotation {:.3} deg, move {:.3}, {} fused, {} graph edges, {:.1} ms; keyframes ATE before {} m after {} m; ground-truth distance of the two keyframes {} m",
            l["current_kf"],
            l["current_t"].as_f64().unwrap_or(0.0),
            l["loop_kf"],
            l["loop_t"].as_f64().unwrap_or(0.0),
            l["inliers"],
            l["projection_matches"],
            l["scale"].as_f64().unwrap_or(0.0),
            l["rotation_deg"].as_f64().unwrap_or(0.0),
            l["translation"].as_f64().unwrap_or(0.0),
            l["fused"],
            l["graph_edges"],
            l["correction_ms"].as_f64().unwrap_or(0.0),
            f("keyframes_ate_before_m"),
            f("keyframes_ate_after_m"),
            f("gt_distance_m"),
        );
    }
    for m in &run.map_starts {
        let opt = |v: Option<u64>| v.map_or("-".to_string(), |v| v.to_string());
        println!(
            "new map {} after a loss at frame {}: initialising from frame {}, initialised at frame {}{}",
            m.map.0,
            m.lost_at,
            m.started_at,
            opt(m.initialized_at),
            m.relocalized_at.map_or(String::new(), |r| format!(
                ", abandoned: relocalised at frame {r}"
            ))
        );
    }
    let mrejects: Vec<String> = merge_refusals
        .iter()
        .map(|(r, (n, far))| format!("{r} {n} ({far} more than 10 m apart)"))
        .collect();
    println!(
        "{} maps started, {} merges{}; maps at the end: {}",
        run.map_starts.len(),
        run.merges.len(),
        if mrejects.is_empty() {
            String::new()
        } else {
            format!(
                " (consistent merge candidates refused: {})",
                mrejects.join(", ")
            )
        },
        maps_at_end
            .iter()
            .map(|m| format!(
                "map {} ({} keyframes, {} frames)",
                m["map"], m["keyframes"], m["frames"]
            ))
            .collect::<Vec<_>>()
            .join(", ")
    );
    for m in merges {
        let f = |k: &str| m[k].as_f64().map_or("-".to_string(), |v| format!("{v:.4}"));
        println!(
            "  merge map {} -> {}: keyframe {} (t {:.2} s) -> {} (t {:.2} s): {} Sim(3) inliers, {} matches by projection, scale {:.4}, {} keyframes moved, {} fused, {} graph edges, {:.1} ms; keyframes ATE before: old map {} m, new map {} m (each aligned alone), merged after {} m; ground-truth distance of the two keyframes {} m",
            m["from_map"],
            m["into_map"],
            m["current_kf"],
            m["current_t"].as_f64().unwrap_or(0.0),
            m["merge_kf"],
            m["merge_t"].as_f64().unwrap_or(0.0),
            m["inliers"],
            m["projection_matches"],
            m["scale"].as_f64().unwrap_or(0.0),
            m["keyframes_moved"],
            m["fused"],
            m["graph_edges"],
            m["correction_ms"].as_f64().unwrap_or(0.0),
            f("old_map_keyframes_ate_before_m"),
            f("new_map_keyframes_ate_before_m"),
            f("keyframes_ate_after_m"),
            f("gt_distance_m"),
        );
    }
}
/// The trajectory moved by a similarity.
fn transformed(t: &Trajectory, s: &shotpilot::lie::Sim3) -> Trajectory {
    Trajectory {
        poses: t
            .poses
            .iter()
            .map(|p| eval::StampedPose {
                t: p.t,
                world_from_cam: s.transform_pose(&p.world_from_cam),
            })
            .collect(),
    }
}

/// The drift at the revisit of a trajectory that comes back to its start:
/// the frame after the first half of the run whose ground-truth position
/// is closest to the first matched frame's, and the error of the aligned
/// estimate's displacement between the two, metres. Returns (time of the
/// revisit, ground-truth distance of the two frames, drift), or `None`
/// when nothing comes within `max_gap` metres of the start.
fn revisit_drift(e: &eval::Evaluation, max_gap: f64) -> Option<(f64, f64, f64)> {
    let n = e.errors.len();
    if n < 4 {
        return None;
    }
    let g0 = e.gt_positions[0];
    let x0 = e.est_positions[0];
    let t_mid = 0.5 * (e.errors[0].0 + e.errors[n - 1].0);
    let (j, gap) = (0..n)
        .filter(|&j| e.errors[j].0 > t_mid)
        .map(|j| (j, (e.gt_positions[j] - g0).norm()))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    if gap > max_gap {
        return None;
    }
    let drift = ((e.est_positions[j] - x0) - (e.gt_positions[j] - g0)).norm();
    Some((e.errors[j].0, gap, drift))
}

/// Lower median and 95th percentile (nearest rank) of a list of
/// milliseconds; zeros when empty.
fn med_p95(v: &[f64]) -> (f64, f64) {
    (
        stats::quantile(v, 0.5).unwrap_or(0.0),
        stats::quantile(v, 0.95).unwrap_or(0.0),
    )
}

/// The frame-time report's lines.
/// The rolling shutter modelled, and the readout estimated from the map.
fn print_shutter(stats: &FrameStats) {
    if stats.readout_s > 0.0 {
        println!(
            "rolling shutter modelled: readout {:.1} ms",
            1000.0 * stats.readout_s
        );
    } else {
        println!("global shutter (readout 0; --readout-ms sets one)");
    }
    if let Some(e) = &stats.readout_estimate {
        let trials: Vec<String> = e
            .trials
            .iter()
            .map(|t| format!("{:.0} ms {:.4}", 1000.0 * t.readout_s, t.rmse_px))
            .collect();
        println!(
            "readout estimated from the map: {:.1} ms (least adjusted cost; reprojection RMSE px per readout: {})",
            1000.0 * e.readout_s,
            trials.join(", ")
        );
    }
}

fn print_timing(t: &slam_timing::TimingReport) {
    println!(
        "tracking thread per frame (wall): {} | waiting for the map lock: {}, {} frames waited",
        t.track_ms, t.lock_wait_ms, t.frames_waited
    );
    if t.search_holds_ms.n > 0 {
        println!(
            "loop closer holding the map lock: searches {} | at a loop (search, correction, graph built) {} | writing the essential graph back {} | global BA {}",
            t.search_holds_ms, t.loop_holds_ms, t.graph_holds_ms, t.global_ba_holds_ms
        );
    }
    for w in &t.windows {
        println!(
            "  {} at keyframe {} ({:.1} ms): frames during it {} (waiting {}); the {} frames after {}",
            w.kind, w.kf, w.ms, w.during, w.during_wait, t.after_frames, w.after
        );
    }
}

/// The RMS of `eval`'s position errors per pose source: each error goes
/// to the record nearest its time within `max_dt` (source name → (rmse,
/// count)).
fn ate_by_source(
    eval: &eval::Evaluation,
    records: &[slam::FrameRecord],
    max_dt: f64,
) -> std::collections::BTreeMap<&'static str, (f64, usize)> {
    let mut by_time: Vec<(f64, &'static str)> = records
        .iter()
        .map(|r| (r.timestamp, r.source.name()))
        .collect();
    by_time.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut sums: std::collections::BTreeMap<&'static str, (f64, usize)> = Default::default();
    for &(t, e) in &eval.errors {
        let i = by_time.partition_point(|r| r.0 < t);
        let nearest = [i.checked_sub(1), Some(i)]
            .into_iter()
            .flatten()
            .filter_map(|k| by_time.get(k))
            .filter(|r| (r.0 - t).abs() <= max_dt)
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()));
        if let Some(&(_, name)) = nearest {
            let s = sums.entry(name).or_default();
            s.0 += e * e;
            s.1 += 1;
        }
    }
    sums.into_iter()
        .map(|(k, (sq, n))| (k, ((sq / n as f64).sqrt(), n)))
        .collect()
}
