//! A long flight: the daemon with the in-process simulator flying its
//! `patrol` script (the survey lap after lap over the same town, so the
//! map keeps meeting places it has mapped) for `SOAK_MINUTES` minutes
//! (default 30). Every 30 s it samples the process's resident memory and
//! the SLAM's status (frames, tracked, keyframes, points, the frame
//! processing time's 95th percentile, loops) and prints one row; at the
//! end it checks that what a long flight must keep holds: tracking, a
//! bounded map and bounded memory once the patrol repeats itself.
//!
//! Measured (2 cores, 30 min, 26 578 frames, 99.6 % tracked): RSS 479 MiB
//! at 5 min, 581 at 10 (the first lap done), 618 at 25, 643 at 30;
//! keyframes 294 / 353 / 363 / 365; the frame time's p95 (over the last
//! 100 frames) averaged 18.3 ms over the samples of minutes 0.5-7.5 and
//! 15.9 ms over 22.5-30 (15 frames/s: 66 ms a frame). No loop closed:
//! tracking never lost the mapped town, so the revisits were tracked in
//! the local map.
//!
//! With the point and keyframe arenas boxed and the histories bounded
//! (SOAK_MINUTES=12, 2 cores shared with other builds): RSS 418 MiB at
//! 5 min, 594 at 10, 600 at 12; keyframes 308 / 382 / 383. From 10.5 to
//! 12 min RSS still rose 4.3 MiB with the map flat: the per-frame and
//! per-keyframe stores `shotpilot slam --memory-every` counts no longer
//! grow that fast (a dead point id costs 8 bytes, not 144), so the rest of
//! the creep is elsewhere in the daemon (not found yet).
//!
//! The rest of the creep was freed memory the allocator kept: a 12-minute
//! run under heaptrack, with the allocator's view beside RSS (the `heap`
//! and `free` columns), had the heap in use level at 258 MiB after the
//! first lap while the threads' arenas held 345 MiB freed but not given
//! back, RSS 601.8 -> 608.3 MiB from 7.5 to 11 min. With the daemon's
//! trim every 30 s (`shotpilot::daemon::memory`), 30 min, 26 967 frames,
//! 99.6 % tracked: RSS 330 MiB at 5 min, 432 at 10, 445 at 30 (358-480
//! from 10 min on, the trims' sawtooth); heap in use 226 / 253 / 265 MiB;
//! keyframes 309 / 373 / 389.
//!
//! `cargo test --release --test suite soak:: -- --ignored --nocapture`

use crate::daemon_support;

use daemon_support::get_json;

use std::path::Path;
use std::time::{Duration, Instant};

/// The process's resident set, MiB (Linux `/proc/self/status`).
fn rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: f64 = s
        .lines()
        .find(|l| l.starts_with("VmRSS:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()?;
    Some(kb / 1024.0)
}

/// The allocator's view: the heap the program holds and the memory freed
/// but kept by the allocator, MiB (NaN where the allocator does not say).
/// RSS growing while the first stays flat is freed memory not given back,
/// not a store that grows.
fn heap_mib() -> (f64, f64) {
    let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
    shotpilot::daemon::memory::heap_use()
        .map_or((f64::NAN, f64::NAN), |h| (mib(h.in_use), mib(h.free)))
}

/// One sample of the run.
#[derive(Debug, Clone, Copy)]
struct Row {
    min: f64,
    rss: f64,
    heap: f64,
    heap_free: f64,
    frames: u64,
    tracked: u64,
    keyframes: u64,
    points: u64,
    frame_p95: f64,
    latency_p95: f64,
    loops: u64,
}

#[test]
#[ignore = "a 30-minute soak run: cargo test --release --test suite soak:: -- --ignored --nocapture (SOAK_MINUTES sets its length)"]
fn a_long_patrol_keeps_tracking_and_memory_bounded() {
    let minutes: f64 = std::env::var("SOAK_MINUTES")
        .ok()
        .and_then(|m| m.parse().ok())
        .unwrap_or(30.0);
    let dir = tempfile::tempdir().unwrap();
    let (mut cfg, sockets) = daemon_support::sim_config();
    cfg.sim.script = "patrol".into();
    cfg.validate(Path::new("test")).unwrap();
    let daemon = daemon_support::start(cfg, sockets, dir.path());
    let addr = daemon.addr;
    let t0 = Instant::now();
    let mut rows: Vec<Row> = Vec::new();
    eprintln!(
        "  min   RSS MiB  heap MiB  free MiB   frames  tracked  keyframes  points  frame p95 ms  latency p95 ms  loops"
    );
    let mut next = 0.0;
    while t0.elapsed().as_secs_f64() < minutes * 60.0 + 1.0 {
        let now = t0.elapsed().as_secs_f64();
        if now < next {
            std::thread::sleep(Duration::from_secs_f64((next - now).min(1.0)));
            continue;
        }
        next += 30.0;
        let st = get_json(addr, "/api/v1/status");
        let s = &st["slam"];
        let u = |k: &str| s[k].as_u64().unwrap_or(0);
        let f = |k: &str| s[k].as_f64().unwrap_or(f64::NAN);
        let (heap, heap_free) = heap_mib();
        let row = Row {
            min: now / 60.0,
            rss: rss_mib().unwrap_or(f64::NAN),
            heap,
            heap_free,
            frames: u("frames"),
            tracked: u("tracked"),
            keyframes: u("keyframes"),
            points: u("points"),
            frame_p95: f("frame_ms_p95"),
            latency_p95: f("latency_ms_p95"),
            loops: u("loops_closed"),
        };
        eprintln!(
            "{:5.1} {:9.1} {:9.1} {:9.1} {:8} {:8} {:10} {:7} {:13.1} {:15.1} {:6}",
            row.min,
            row.rss,
            row.heap,
            row.heap_free,
            row.frames,
            row.tracked,
            row.keyframes,
            row.points,
            row.frame_p95,
            row.latency_p95,
            row.loops
        );
        rows.push(row);
    }
    daemon.stop(Duration::from_secs(60));
    let at = |m: f64| {
        rows.iter()
            .min_by(|a, b| (a.min - m).abs().total_cmp(&(b.min - m).abs()))
            .copied()
            .expect("samples")
    };
    let (first, last) = (at(5.0), at(minutes));
    eprintln!("at 5 min: {first:?}\nat {minutes} min: {last:?}");
    // Tracking holds over the whole flight.
    let share = last.tracked as f64 / last.frames.max(1) as f64;
    assert!(share > 0.9, "tracked {share:.3} of the frames");
    assert!(
        last.frames as f64 > minutes * 60.0 * 10.0,
        "frames {}",
        last.frames
    );
    // The first lap (about 7.5 min) maps the town; the later ones fly over
    // it again and must track in the map they have, not map it anew: a
    // second copy of the map would add as many keyframes and as much
    // memory as the first lap did (about 350 keyframes and 450 MiB).
    if minutes >= 20.0 {
        let lap = at(10.0);
        assert!(
            last.keyframes as f64 <= 1.15 * lap.keyframes as f64,
            "keyframes {} at 10 min, {} at the end",
            lap.keyframes,
            last.keyframes
        );
        assert!(
            last.rss <= 1.2 * lap.rss,
            "RSS {:.0} MiB at 10 min, {:.0} MiB at the end",
            lap.rss,
            last.rss
        );
    }
}
