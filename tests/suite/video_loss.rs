//! A real encoder through a lossy link: Debian's ffmpeg encodes its
//! `testsrc2` pattern with x264 (baseline, 640x480, 15 fps, 1.5 Mbit/s, an
//! IDR picture every 2 s) and sends it as RTP (RFC 6184) to a UDP proxy
//! this test binds on port 0, which sends every packet on to several of the
//! daemon's `udp://` sources, dropping packets for each with a seeded random
//! generator (independent losses, or Gilbert-Elliott bursts) or none (the
//! lossless copy, which the others' frames are compared with, row by row,
//! matched by capture time). Each run prints a FIGURES row:
//! pictures received, frames decoded and given to SLAM, damaged and fully
//! damaged frames, the masked share of the rows, skipped units.
//!
//! Two stream shapes: x264's one slice per picture (a lost packet damages
//! the whole picture), and slices capped at one packet (`slice-max-size`,
//! what senders for lossy links do: a lost packet damages its slice's rows).
//!
//! Needs Debian's `ffmpeg` (with libx264); `.ci/run` installs it.

use std::net::{SocketAddr, UdpSocket};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use shotpilot::config::VideoConfig;
use shotpilot::video::live::{CountersSnapshot, LinkQuality};
use shotpilot::video::udp::RtpSockets;

use crate::video_support::{
    LiveSource, Loss, RowHashes, against_clean, explore_flight, row_hashes,
};

/// A proxy on two sockets bound here (RTP and RTCP beside it) sending each
/// packet on to every destination (and RTCP to its next port), dropping RTP
/// packets per destination as its `Loss` says: the copies carry the same
/// RTP timestamps and sender reports, so their frames match by capture time.
struct Proxy {
    rtp_port: u16,
    stop: Arc<AtomicBool>,
    /// Per destination: packets forwarded, dropped.
    counts: Arc<Vec<(AtomicU64, AtomicU64)>>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Proxy {
    fn start(dests: &[(SocketAddr, Loss)], seed: u64) -> Proxy {
        let pair = RtpSockets::bind_pair("127.0.0.1".parse().unwrap()).unwrap();
        let rtp_port = pair.rtp_addr().unwrap().port();
        let stop = Arc::new(AtomicBool::new(false));
        let counts: Arc<Vec<(AtomicU64, AtomicU64)>> = Arc::new(
            dests
                .iter()
                .map(|_| (AtomicU64::new(0), AtomicU64::new(0)))
                .collect(),
        );
        let mut threads = Vec::new();
        let sockets = [
            (pair.rtp, true),
            (pair.rtcp.expect("an RTCP socket"), false),
        ];
        for (sock, rtp) in sockets {
            let (stop, counts) = (stop.clone(), counts.clone());
            let mut outs: Vec<(SocketAddr, Box<dyn FnMut() -> bool + Send>)> = dests
                .iter()
                .enumerate()
                .map(|(k, &(to, loss))| {
                    let dest = if rtp {
                        to
                    } else {
                        SocketAddr::new(to.ip(), to.port() + 1)
                    };
                    let d: Box<dyn FnMut() -> bool + Send> = if rtp {
                        Box::new(loss.dropper(seed + k as u64))
                    } else {
                        Box::new(|| false)
                    };
                    (dest, d)
                })
                .collect();
            threads.push(std::thread::spawn(move || {
                sock.set_read_timeout(Some(Duration::from_millis(100)))
                    .unwrap();
                let out = UdpSocket::bind("127.0.0.1:0").unwrap();
                let mut buf = vec![0u8; 65_536];
                while !stop.load(Ordering::Relaxed) {
                    let Ok(n) = sock.recv(&mut buf) else { continue };
                    for (k, (dest, drop_now)) in outs.iter_mut().enumerate() {
                        if drop_now() {
                            counts[k].1.fetch_add(1, Ordering::Relaxed);
                            continue;
                        }
                        if rtp {
                            counts[k].0.fetch_add(1, Ordering::Relaxed);
                        }
                        let _ = out.send_to(&buf[..n], *dest);
                    }
                }
            }));
        }
        Proxy {
            rtp_port,
            stop,
            counts,
            threads,
        }
    }

    fn finish(self) -> Vec<(u64, u64)> {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads {
            t.join().unwrap();
        }
        self.counts
            .iter()
            .map(|c| (c.0.load(Ordering::Relaxed), c.1.load(Ordering::Relaxed)))
            .collect()
    }
}

/// One run: ffmpeg -> proxy -> the daemon's udp:// source, for `secs`.
struct Case {
    loss: Loss,
    /// `slice-max-size` bytes (None: one slice per picture).
    slice_bytes: Option<u32>,
    /// Pictures between IDR pictures.
    gop: u32,
    /// `[video] damage_mv_px` (None: the default).
    mv_px: Option<u32>,
    /// `[video] damage_follow_motion = false`: the motion bound always.
    bound: bool,
}

#[derive(Debug)]
struct Outcome {
    counters: CountersSnapshot,
    /// What the link left SLAM over the stream's last 10 s (the status's
    /// `video.link`), read as the sender finished.
    link: LinkQuality,
    forwarded: u64,
    dropped: u64,
    /// Per frame given to SLAM: its capture time (from the sender's RTCP
    /// reports, the same in every copy of the stream), a hash of each row,
    /// and which rows it marks damaged.
    frames: Vec<RowHashes>,
}

/// Each group of cases with one stream shape: one ffmpeg, one proxy, one
/// daemon `udp://` source per case.
fn run_cases(rt: &tokio::runtime::Runtime, cases: &[Case], secs: u32) -> Vec<Outcome> {
    let mut shapes: Vec<(Option<u32>, u32)> = Vec::new();
    for c in cases {
        if !shapes.contains(&(c.slice_bytes, c.gop)) {
            shapes.push((c.slice_bytes, c.gop));
        }
    }
    struct Running {
        case: usize,
        source: LiveSource<RowHashes>,
    }
    let mut groups = Vec::new();
    for (g, &(slice_bytes, gop)) in shapes.iter().enumerate() {
        let mut running = Vec::new();
        let mut dests = Vec::new();
        for (k, c) in cases.iter().enumerate() {
            if (c.slice_bytes, c.gop) != (slice_bytes, gop) {
                continue;
            }
            let mut cfg = VideoConfig::default();
            if let Some(px) = c.mv_px {
                cfg.damage_mv_px = px;
            }
            cfg.damage_follow_motion = !c.bound;
            // Every frame published, as it comes.
            let (to, source) = LiveSource::start(rt, cfg, row_hashes);
            dests.push((to, c.loss));
            running.push(Running { case: k, source });
        }
        let proxy = Proxy::start(&dests, 1000 + 100 * g as u64);
        let mut x264 = format!("keyint={gop}:min-keyint={gop}:scenecut=0");
        if let Some(n) = slice_bytes {
            x264.push_str(&format!(":slice-max-size={n}"));
        } else {
            x264.push_str(":slices=1:sliced-threads=0");
        }
        let child = Command::new("ffmpeg")
            .args([
                "-hide_banner",
                "-loglevel",
                "error",
                "-re",
                "-f",
                "lavfi",
                "-i",
            ])
            .arg(format!("testsrc2=size=640x480:rate=15:duration={secs}"))
            .args([
                "-c:v",
                "libx264",
                "-profile:v",
                "baseline",
                "-preset",
                "veryfast",
                "-b:v",
                "1500k",
                "-maxrate",
                "1500k",
                "-bufsize",
                "1000k",
                "-x264-params",
                &x264,
                "-f",
                "rtp",
                "-payload_type",
                "96",
            ])
            .arg(format!("rtp://127.0.0.1:{}?pkt_size=1400", proxy.rtp_port))
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("ffmpeg (Debian's ffmpeg with libx264)");
        groups.push((child, proxy, running));
    }
    let mut out: Vec<Option<Outcome>> = cases.iter().map(|_| None).collect();
    for (mut child, proxy, running) in groups {
        let status = child.wait().unwrap();
        assert!(status.success(), "ffmpeg failed: {status}");
        let links: Vec<LinkQuality> = running
            .iter()
            .map(|r| r.source.ingest.link.report())
            .collect();
        // The decoders drain what is queued (a bound, not a figure).
        let t = Instant::now();
        let snap = |r: &Vec<Running>| -> Vec<_> {
            r.iter()
                .map(|x| x.source.ingest.counters.snapshot())
                .collect()
        };
        let mut last = snap(&running);
        loop {
            std::thread::sleep(Duration::from_millis(200));
            let now = snap(&running);
            if now == last || t.elapsed() > Duration::from_secs(10) {
                break;
            }
            last = now;
        }
        let counts = proxy.finish();
        for ((r, (forwarded, dropped)), link) in running.into_iter().zip(counts).zip(links) {
            let (counters, frames) = r.source.stop(rt);
            out[r.case] = Some(Outcome {
                counters,
                link,
                forwarded,
                dropped,
                frames,
            });
        }
    }
    out.into_iter()
        .map(|o| o.expect("every case ran"))
        .collect()
}

fn figures(cases: &[Case], outcomes: &[Outcome]) {
    eprintln!(
        "FIGURES loss | slices | gop | damage model | packets sent/dropped | pictures received | decoded (given to SLAM) | damaged | fully damaged | masked rows | skipped | rows really differing | differing unmasked | usable, last 10 s (status) | unreliable"
    );
    for (c, o) in cases.iter().zip(outcomes) {
        let k = &o.counters;
        let clean = cases
            .iter()
            .zip(outcomes)
            .find(|(d, _)| d.loss.rate() == 0.0 && d.slice_bytes == c.slice_bytes && d.gop == c.gop)
            .map(|(_, o)| o);
        let (rows, _, differ, unmarked) =
            clean.map_or((0, 0, 0, 0), |cl| against_clean(&o.frames, &cl.frames));
        eprintln!(
            "FIGURES {} | {} | {} | {} | {}/{} | {} | {} ({:.1} %) | {} | {} | {:.1} % | {} | {:.1} % | {} | {:.1} % of {} | {}",
            c.loss.name(),
            c.slice_bytes
                .map_or("one per picture".to_string(), |n| format!("<= {n} B")),
            c.gop,
            match (c.bound, c.mv_px) {
                (false, _) => "motion followed".to_string(),
                (true, None) => "motion bound".to_string(),
                (true, Some(p)) => format!("motion bound {p} px"),
            },
            o.forwarded + o.dropped,
            o.dropped,
            k.received,
            k.decoded,
            100.0 * k.decoded as f64 / k.received.max(1) as f64,
            k.damaged,
            k.fully_damaged,
            k.masked_share * 100.0,
            k.skipped,
            100.0 * differ as f64 / rows.max(1) as f64,
            unmarked,
            o.link.usable_share * 100.0,
            o.link.frames,
            o.link.unreliable,
        );
    }
}

#[test]
#[ignore = "needs ffmpeg (Debian's ffmpeg with libx264)"]
fn x264_through_a_lossy_link_reaches_slam_with_its_damage_masked() {
    let rt = crate::video_support::runtime();
    let mut cases = Vec::new();
    for slice_bytes in [None, Some(1200)] {
        for loss in [0.0, 0.01, 0.02, 0.05, 0.10] {
            cases.push(Case {
                loss: Loss::Random(loss),
                slice_bytes,
                gop: 30,
                mv_px: None,
                bound: false,
            });
        }
        cases.push(Case {
            loss: Loss::Bursts {
                rate: 0.05,
                burst: 5.0,
            },
            slice_bytes,
            gop: 30,
            mv_px: None,
            bound: false,
        });
    }
    // The motion bound instead of the measured motion: nothing may differ
    // unmarked.
    for loss in [0.01, 0.05] {
        cases.push(Case {
            loss: Loss::Random(loss),
            slice_bytes: Some(1200),
            gop: 30,
            mv_px: None,
            bound: true,
        });
    }
    // A tighter motion bound than the default: its figures only (the
    // bound is an assumption about the stream; these rows show what a
    // smaller one would keep, and whether it would let damage through).
    for (loss, px) in [(0.01, 4), (0.05, 4), (0.01, 0)] {
        cases.push(Case {
            loss: Loss::Random(loss),
            slice_bytes: Some(1200),
            gop: 30,
            mv_px: Some(px),
            bound: true,
        });
    }
    let outcomes = run_cases(&rt, &cases, 20);
    figures(&cases, &outcomes);
    for (c, o) in cases.iter().zip(&outcomes) {
        let k = &o.counters;
        let name = format!("{} (slices {:?})", c.loss.name(), c.slice_bytes);
        assert!(k.received >= 250, "{name}: {k:?}");
        if c.loss.rate() == 0.0 {
            assert_eq!(k.damaged, 0, "no loss, no damage: {k:?}");
            assert_eq!(o.dropped, 0);
            // Every picture decoded, but for those dropped because the
            // decoder fell behind on a loaded machine (late) and skipped to
            // the next key frame after them.
            assert_eq!(k.decoded + k.late + k.skipped, k.received, "{name}: {k:?}");
            assert!(k.late + k.skipped <= k.received / 10, "{name}: {k:?}");
            // A clean link: every frame of the last 10 s usable.
            assert!(
                o.link.frames >= 100 && o.link.usable_share > 0.95 && !o.link.unreliable,
                "{name}: {:?}",
                o.link
            );
            continue;
        }
        assert!(o.dropped > 0 && k.damaged > 0, "{name}: {k:?}");
        // The status's verdict on the link: at 5 % loss and more, sliced or
        // not, under 70 % of the frames keep three quarters of their rows
        // (measured: 2.6-9.7 % usable), and the operator is told. (At 1-2 %
        // too, today: 11-27 % usable with 1200-byte slices, 13-14 % with
        // one slice per picture; the status says so, this does not assert
        // it, as better masking should change it.)
        if matches!(c.loss, Loss::Random(r) if r >= 0.05) {
            assert!(o.link.unreliable, "{name}: {:?}", o.link);
        }
        // It never counts more usable than reached SLAM.
        assert!(
            o.link.usable_share <= k.decoded as f64 / k.received.max(1) as f64 + 0.1,
            "{name}: {:?} against {k:?}",
            o.link
        );
        // Nothing SLAM may use differs from the lossless copy.
        let clean = cases
            .iter()
            .zip(&outcomes)
            .find(|(d, _)| d.loss.rate() == 0.0 && (d.slice_bytes, d.gop) == (c.slice_bytes, c.gop))
            .map(|(_, o)| o)
            .unwrap();
        let (rows, _, _, unmarked) = against_clean(&o.frames, &clean.frames);
        assert!(rows > 50 * 480, "{name}: {rows} rows compared");
        // Rows that differ from the lossless copy (by any grey level; the
        // SLAM test below counts the visible ones) without a mark: the bound
        // let none through in most runs and 30 of 144,000 in one (5 %);
        // the measured motion is an estimate, 27 at 1 % and 371 at 10 %
        // loss in one run.
        let allowed = if c.bound { 0.0005 } else { 0.005 };
        if c.mv_px.is_none() {
            assert!(
                unmarked as f64 <= allowed * rows as f64,
                "{name}: {unmarked} of {rows} rows differ from the lossless copy without a mark"
            );
        }
        // Every picture with a slice that arrived reaches SLAM (skipping to
        // the next IDR picture gave 18 % at 1 % loss); only pictures whose
        // every slice was lost do not, or units before the first parameter
        // sets that arrived.
        if c.loss.rate() <= 0.02 {
            assert!(k.decoded as f64 >= 0.8 * k.received as f64, "{name}: {k:?}");
        }
    }
    // Slices of one packet: at 1 % loss, most frames keep usable rows.
    let k = &outcomes[7].counters;
    assert_eq!(cases[7].slice_bytes, Some(1200));
    assert!(
        (k.decoded - k.fully_damaged) as f64 >= 0.5 * k.received as f64,
        "{k:?}"
    );
}

/// SLAM on the simulator's explore flight (640x480, 15 fps, 30 s), encoded
/// by OpenH264 with one-packet slices (IDR every 2 s), sent as RTP with
/// packets dropped at random, decoded with the damage masked (or skipping
/// to the next IDR picture, as before): frames given to SLAM, tracked
/// share, ATE against the lossless run's, and each frame's rows against
/// the lossless decode of the same picture.
struct SlamRun {
    given: usize,
    usable: usize,
    tracked: usize,
    masked_share: f64,
    ate_m: f64,
    /// Rows compared with the lossless decode, rows that differ, rows that
    /// differ without being masked, and of those the rows where a pixel
    /// differs by more than [`VISIBLE`] grey levels.
    rows: usize,
    differ: usize,
    unmasked_differ: usize,
    unmasked_visible: usize,
}

/// A difference an eye (or a FAST corner test, threshold 20 and 7) notices.
const VISIBLE: u8 = 8;

/// Every picture of `aus` decoded without loss, by index.
fn lossless_pictures(aus: &[Vec<u8>]) -> Vec<Option<image::GrayImage>> {
    use shotpilot::video::decode_loop::{DecodeLoop, DecodeParams, Decoded};
    use shotpilot::video::h264::AccessUnit;
    let mut dl = DecodeLoop::new(DecodeParams::default()).unwrap();
    aus.iter()
        .map(|a| {
            let unit = AccessUnit {
                data: a.clone(),
                capture_time: None,
                received: Instant::now(),
                received_unix: 0.0,
                lost: 0,
                gaps: vec![],
            };
            match dl.step(&unit, false) {
                Decoded::Frame(f) => Some((*f.image).clone()),
                _ => None,
            }
        })
        .collect()
}

fn slam_through_loss(
    aus: &[Vec<u8>],
    clean: &[Option<image::GrayImage>],
    gt: &[(f64, nalgebra::Isometry3<f64>)],
    cam: &shotpilot::camera::Camera,
    loss: f64,
    params: shotpilot::video::decode_loop::DecodeParams,
) -> SlamRun {
    use shotpilot::video::decode_loop::{DecodeLoop, Decoded};
    use shotpilot::video::h264::AccessUnit;
    use shotpilot::video::rtp::{H264Depacketizer, packetize_h264, parse_rtp};
    let mut rng = rand::rngs::StdRng::seed_from_u64(77);
    let mut dl = DecodeLoop::new(params).unwrap();
    let mut depack = H264Depacketizer::new(vec![]);
    let mut slam = shotpilot::slam::Slam::new(
        *cam,
        shotpilot::slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    let (mut given, mut usable, mut rows, mut masked) = (0, 0, 0, 0);
    let (mut skipped, mut broken) = (0, 0);
    let (mut compared, mut differ, mut unmasked_differ, mut unmasked_visible) = (0, 0, 0, 0);
    let mut seq = 0u16;
    for (i, a) in aus.iter().enumerate() {
        for p in packetize_h264(a, 1400, 96, 5, &mut seq, 6000 * i as u32) {
            if rng.random::<f64>() < loss {
                continue;
            }
            for done in depack.push(&parse_rtp(&p).unwrap()) {
                let idx = (done.timestamp / 6000) as usize;
                let t = gt[idx].0;
                let unit = AccessUnit {
                    data: done.data,
                    capture_time: Some(t),
                    received: Instant::now(),
                    received_unix: t,
                    lost: done.lost,
                    gaps: done.gaps,
                };
                let out = dl.step(&unit, false);
                match &out {
                    Decoded::Skipped => skipped += 1,
                    Decoded::Broken(e) => {
                        broken += 1;
                        if broken == 1 {
                            eprintln!("picture {idx}: {e}");
                        }
                    }
                    _ => {}
                }
                if let Decoded::Frame(f) = out {
                    // The picture this frame is (its capture time).
                    let k = gt
                        .iter()
                        .position(|g| (g.0 - f.timestamp()).abs() < 1e-6)
                        .unwrap();
                    given += 1;
                    let share = f.masked_share();
                    usable += usize::from(share < 1.0);
                    rows += f.image.height() as usize;
                    masked += f.damage.as_ref().map_or(0, |d| d.count());
                    if let Some(c) = &clean[k] {
                        let w = c.width() as usize;
                        let marks = f.damage.as_ref().map(|d| d.rows().to_vec());
                        for (y, (a, b)) in f
                            .image
                            .as_raw()
                            .chunks(w)
                            .zip(c.as_raw().chunks(w))
                            .enumerate()
                        {
                            compared += 1;
                            let worst = a
                                .iter()
                                .zip(b)
                                .map(|(p, q)| p.abs_diff(*q))
                                .max()
                                .unwrap_or(0);
                            let marked = marks.as_ref().is_some_and(|m| m[y]);
                            differ += usize::from(worst > 0);
                            unmasked_differ += usize::from(worst > 0 && !marked);
                            unmasked_visible += usize::from(worst > VISIBLE && !marked);
                        }
                    }
                    let mask = f.reliable_mask();
                    slam.process_masked(k as u64, f.timestamp(), f.image.clone(), mask.as_ref());
                }
            }
        }
    }
    eprintln!(
        "loss {loss}: {skipped} skipped, {broken} broken, {} lost",
        depack.stats().lost
    );
    let r = slam.finish();
    let gt_traj = shotpilot::eval::Trajectory {
        poses: gt
            .iter()
            .map(|(t, p)| shotpilot::eval::StampedPose {
                t: *t,
                world_from_cam: *p,
            })
            .collect(),
    };
    let ate = shotpilot::eval::evaluate(
        &gt_traj,
        &r.trajectory(),
        &shotpilot::eval::Params::default(),
    )
    .map_or(f64::NAN, |e| e.ate.rmse);
    SlamRun {
        given,
        usable,
        tracked: r.records.len(),
        masked_share: masked as f64 / rows.max(1) as f64,
        ate_m: ate,
        rows: compared,
        differ,
        unmasked_differ,
        unmasked_visible,
    }
}

#[test]
#[ignore = "slow: renders, encodes and runs SLAM on 450 frames nine times (about two minutes)"]
fn slam_keeps_tracking_through_a_lossy_link() {
    use shotpilot::video::decode_loop::DecodeParams;
    use shotpilot::video::h264::GrayEncoder;
    let n = 450;
    let flight = explore_flight(n);
    let (sim, gt, cam) = (flight.sim, flight.gt, flight.cam);
    let mut enc =
        GrayEncoder::with_slices(sim.width, sim.height, 15.0, 1_500_000, 30, Some(1200)).unwrap();
    let aus: Vec<Vec<u8>> = flight
        .pictures
        .iter()
        .map(|p| enc.encode(p).unwrap())
        .collect();
    let clean = lossless_pictures(&aus);
    let skip = DecodeParams {
        conceal: false,
        ..Default::default()
    };
    let bound = DecodeParams::default();
    let followed = DecodeParams {
        damage: shotpilot::video::damage::DamageParams {
            follow_motion: true,
            ..Default::default()
        },
        ..Default::default()
    };
    // Other margins beyond the measured motion: their figures only.
    let margin = |px: u32| DecodeParams {
        damage: shotpilot::video::damage::DamageParams {
            motion_margin_px: px,
            follow_motion: true,
            ..Default::default()
        },
        ..Default::default()
    };
    let lossless = slam_through_loss(&aus, &clean, &gt, &cam, 0.0, DecodeParams::default());
    eprintln!(
        "FIGURES SLAM {}x{} | loss | decoding | given to SLAM | usable | masked rows | rows differing | differing unmasked (by > {VISIBLE}) | tracked | ATE m (lossless {:.3})",
        sim.width, sim.height, lossless.ate_m
    );
    let mut results = Vec::new();
    for (loss, name, params) in [
        (0.0, "masked, motion followed", followed.clone()),
        (0.01, "masked, motion followed", followed.clone()),
        (0.01, "masked, motion bound", bound.clone()),
        (0.01, "masked, motion followed, margin 0", margin(0)),
        (0.01, "masked, motion followed, margin 1", margin(1)),
        (0.01, "skip to IDR", skip.clone()),
        (0.02, "masked, motion followed", followed.clone()),
        (0.05, "masked, motion followed", followed.clone()),
        (0.05, "masked, motion bound", bound.clone()),
        (0.05, "skip to IDR", skip.clone()),
        (0.10, "masked, motion followed", followed.clone()),
    ] {
        let r = if loss == 0.0 {
            SlamRun { ..lossless }
        } else {
            slam_through_loss(&aus, &clean, &gt, &cam, loss, params)
        };
        eprintln!(
            "FIGURES SLAM | {:.0} % | {name} | {} / {n} | {} | {:.1} % | {:.1} % | {} ({}) of {} | {} ({:.1} %) | {:.3} ({:.2}x)",
            loss * 100.0,
            r.given,
            r.usable,
            r.masked_share * 100.0,
            100.0 * r.differ as f64 / r.rows.max(1) as f64,
            r.unmasked_differ,
            r.unmasked_visible,
            r.rows,
            r.tracked,
            100.0 * r.tracked as f64 / n as f64,
            r.ate_m,
            r.ate_m / lossless.ate_m
        );
        results.push(r);
    }
    assert!(
        lossless.tracked as f64 >= 0.8 * n as f64,
        "{}",
        lossless.tracked
    );
    assert_eq!(lossless.differ, 0, "the lossless run is the reference");
    // The measured motion keeps more of the picture than the bound, and
    // more frames tracked, with at most one visibly wrong row unmasked in
    // ten thousand (the bound: none).
    let (followed, bound) = (&results[1], &results[2]);
    assert!(
        followed.masked_share < bound.masked_share - 0.05,
        "{} vs {}",
        followed.masked_share,
        bound.masked_share
    );
    assert!(
        followed.tracked > bound.tracked,
        "{} vs {}",
        followed.tracked,
        bound.tracked
    );
    assert_eq!(bound.unmasked_visible, 0);
    assert!(
        followed.unmasked_visible as f64 <= 1e-4 * followed.rows as f64,
        "{}",
        followed.unmasked_visible
    );
    // 1 % loss, masked: every frame reaches SLAM.
    assert!(
        results[1].given as f64 >= 0.95 * n as f64,
        "{}",
        results[1].given
    );
}
