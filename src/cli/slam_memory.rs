//! `slam`'s memory report: the process's resident set, the map's stores
//! sampled every `--memory-every` frames, and the lines that print them.

use shotpilot::slam::Slam;

/// The process's resident set and its peak, MiB (Linux `/proc/self/status`;
/// `None` elsewhere).
pub(super) fn rss_mib() -> Option<(f64, f64)> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let field = |name: &str| -> Option<f64> {
        let kb: f64 = s
            .lines()
            .find(|l| l.starts_with(name))?
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()?;
        Some(kb / 1024.0)
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

/// One memory sample of the run.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub(super) struct MemorySample {
    /// Frames given so far.
    pub(super) frames: usize,
    /// Resident set, MiB.
    pub(super) rss_mib: Option<f64>,
    /// The map's stores.
    pub(super) map: shotpilot::slam::Footprint,
    /// Frame records the tracker holds.
    pub(super) records: usize,
}

pub(super) fn memory_sample(system: &Slam, frames: usize) -> MemorySample {
    let map = system.map();
    let fp = shotpilot::slam::map::lock(&map).footprint();
    MemorySample {
        frames,
        rss_mib: rss_mib().map(|r| r.0),
        map: fp,
        records: system.records_len(),
    }
}

/// The memory lines: resident set, the map's stores at the end, and the
/// samples taken with --memory-every.
pub(super) fn print_memory(samples: &[MemorySample], last: &MemorySample, rss: Option<(f64, f64)>) {
    let mib = |b: usize| b as f64 / (1024.0 * 1024.0);
    let f = &last.map;
    if let Some((now, peak)) = rss {
        println!("memory: resident {now:.1} MiB (peak {peak:.1} MiB)");
    }
    println!(
        "map stores: {} keyframe ids ({} live, {} culled, {} with images), {} point ids ({} live, {} observations), {} in the place index, {} frame records; estimated {:.1} MiB: keyframes {:.1}, images {:.1}, points {:.1}, culled {:.2}, places {:.1}, other {:.2}",
        f.keyframe_ids,
        f.keyframes,
        f.culled,
        f.images,
        f.point_ids,
        f.points,
        f.observations,
        f.places,
        last.records,
        mib(f.total_bytes()),
        mib(f.keyframe_bytes),
        mib(f.image_bytes),
        mib(f.point_bytes),
        mib(f.culled_bytes),
        mib(f.places_bytes),
        mib(f.other_bytes),
    );
    if samples.len() > 1 {
        println!("  frames  RSS MiB  map MiB  kf ids  live kfs  point ids  live points");
        for s in samples {
            println!(
                "  {:6}  {:7}  {:7.1}  {:6}  {:8}  {:9}  {:11}",
                s.frames,
                s.rss_mib.map_or("-".into(), |r| format!("{r:.1}")),
                mib(s.map.total_bytes()),
                s.map.keyframe_ids,
                s.map.keyframes,
                s.map.point_ids,
                s.map.points
            );
        }
    }
}
