//! Asking a real sender for what a lossy link lost: GStreamer's `rtpbin`
//! with `rtprtxsend` (`tests/peers/rtp_rtx_sender.py`: x264, 640x480,
//! 15 fps, 1.5 Mbit/s, slices capped at 1200 bytes, an IDR picture every
//! 2 s) sends RTP through a UDP proxy bound here to two of the daemon's
//! `udp://` sources: one behind a lossy link (RTP and retransmissions
//! dropped on the way in, feedback on the way back, by a seeded drop
//! model), one lossless (the reference its frames are compared with, row
//! by row, matched by capture time). The lossy source NACKs what it misses
//! and asks for a key frame when a packet is lost for good; the same
//! stream from a sender without feedback (`--no-feedback`: plain RTCP)
//! shows what that buys. Each case prints a FIGURES row.
//!
//! Needs Debian's GStreamer (tools, plugins base/good/bad/ugly) and
//! python3-gi; `.ci/run` installs them.

use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use shotpilot::config::VideoConfig;
use shotpilot::video::live::{CountersSnapshot, Frame, LinkQuality};
use shotpilot::video::udp::RtpSockets;

use crate::video_support::{Flight, LiveSource, Loss, against_clean, explore_flight, row_hashes};

/// What the proxy counted for the lossy destination.
#[derive(Debug, Default)]
struct ProxyCounts {
    /// RTP packets (media and retransmissions) forwarded and dropped.
    forwarded: AtomicU64,
    dropped: AtomicU64,
    /// Retransmissions (payload type 97) that reached the proxy.
    retransmissions: AtomicU64,
    /// Feedback packets from the lossy source forwarded to the sender, and
    /// dropped on the way.
    feedback: AtomicU64,
    feedback_dropped: AtomicU64,
    /// With `SHOTPILOT_FEEDBACK_TRACE` set: what passed, by time since the
    /// proxy started (drops, NACKs, PLIs, retransmissions, IDR pictures).
    trace: Mutex<Vec<(f64, String)>>,
}

impl ProxyCounts {
    fn note(&self, t0: Instant, what: impl FnOnce() -> String) {
        if std::env::var_os("SHOTPILOT_FEEDBACK_TRACE").is_some() {
            self.trace
                .lock()
                .unwrap()
                .push((t0.elapsed().as_secs_f64(), what()));
        }
    }
}

/// A proxy on an RTP socket and its RTCP socket beside it. RTP from the
/// sender goes on to the lossy destination (dropped as `loss` says) and to
/// the clean one, from the RTP socket; the sender's RTCP goes to both
/// destinations' RTCP ports, from the RTCP socket; RTCP from the lossy
/// destination (its feedback) goes back to where the sender's RTCP came
/// from (dropped as `loss` says too); the clean destination's is dropped.
struct Proxy {
    rtp_port: u16,
    stop: Arc<AtomicBool>,
    counts: Arc<ProxyCounts>,
    threads: Vec<std::thread::JoinHandle<()>>,
}

impl Proxy {
    fn start(lossy: SocketAddr, clean: SocketAddr, loss: Loss, feedback: bool, seed: u64) -> Proxy {
        let pair = RtpSockets::bind_pair("127.0.0.1".parse().unwrap()).unwrap();
        let rtp_port = pair.rtp_addr().unwrap().port();
        let stop = Arc::new(AtomicBool::new(false));
        let counts = Arc::new(ProxyCounts::default());
        let rtcp_of = |a: SocketAddr| SocketAddr::new(a.ip(), a.port() + 1);
        let mut threads = Vec::new();
        {
            let (stop, counts) = (stop.clone(), counts.clone());
            let sock = pair.rtp;
            let mut drop_now = loss.dropper(seed);
            threads.push(std::thread::spawn(move || {
                sock.set_read_timeout(Some(Duration::from_millis(100)))
                    .unwrap();
                let mut buf = vec![0u8; 65_536];
                let t0 = Instant::now();
                while !stop.load(Ordering::Relaxed) {
                    let Ok(n) = sock.recv(&mut buf) else { continue };
                    let seq = || u16::from_be_bytes([buf[2], buf[3]]);
                    if n > 14 && buf[1] & 0x7f == 97 {
                        counts.retransmissions.fetch_add(1, Ordering::Relaxed);
                        counts.note(t0, || {
                            format!("rtx {}", u16::from_be_bytes([buf[12], buf[13]]))
                        });
                    } else if n > 13 {
                        let nal = buf[12] & 0x1f;
                        let idr_start = nal == 5 || (nal == 28 && buf[13] & 0x9f == 0x85);
                        if idr_start {
                            counts.note(t0, || format!("IDR starts at {}", seq()));
                        }
                    }
                    let _ = sock.send_to(&buf[..n], clean);
                    if drop_now() {
                        counts.note(t0, || format!("drop {}", seq()));
                        counts.dropped.fetch_add(1, Ordering::Relaxed);
                    } else {
                        counts.forwarded.fetch_add(1, Ordering::Relaxed);
                        let _ = sock.send_to(&buf[..n], lossy);
                    }
                }
            }));
        }
        {
            let (stop, counts) = (stop.clone(), counts.clone());
            let sock = pair.rtcp.expect("an RTCP socket");
            let mut drop_back = loss.dropper(seed + 7);
            let (lossy_rtcp, clean_rtcp) = (rtcp_of(lossy), rtcp_of(clean));
            threads.push(std::thread::spawn(move || {
                sock.set_read_timeout(Some(Duration::from_millis(100)))
                    .unwrap();
                let mut sender: Option<SocketAddr> = None;
                let mut buf = vec![0u8; 65_536];
                let t0 = Instant::now();
                while !stop.load(Ordering::Relaxed) {
                    let Ok((n, from)) = sock.recv_from(&mut buf) else {
                        continue;
                    };
                    if from == lossy_rtcp {
                        counts.note(t0, || {
                            format!(
                                "feedback {:?} (sender known: {})",
                                shotpilot::video::rtp::feedback::parse_feedback(&buf[..n]),
                                sender.is_some()
                            )
                        });
                        if !feedback || drop_back() {
                            counts.feedback_dropped.fetch_add(1, Ordering::Relaxed);
                        } else if let Some(to) = sender {
                            counts.feedback.fetch_add(1, Ordering::Relaxed);
                            let _ = sock.send_to(&buf[..n], to);
                        }
                    } else if from != clean_rtcp {
                        if sender.is_none() {
                            counts.note(t0, || "the sender's first RTCP".into());
                        }
                        sender = Some(from);
                        let _ = sock.send_to(&buf[..n], lossy_rtcp);
                        let _ = sock.send_to(&buf[..n], clean_rtcp);
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

    fn finish(self) -> Arc<ProxyCounts> {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads {
            t.join().unwrap();
        }
        self.counts
    }
}

/// What the sender does with the lossy source's feedback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Answer {
    /// Retransmits what a NACK asks for, makes a key frame for a PLI.
    NackPli,
    /// Makes a key frame for a PLI; NACKs go unanswered (no rtprtxsend).
    PliOnly,
    /// Hears nothing: the proxy drops the feedback (as a sender without
    /// RTCP, ffmpeg's RTP muxer, would ignore it).
    Nothing,
}

impl Answer {
    fn name(self) -> &'static str {
        match self {
            Answer::NackPli => "NACK + PLI",
            Answer::PliOnly => "PLI only",
            Answer::Nothing => "none",
        }
    }
}

/// How the sender's encoder makes the stream recoverable.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Shape {
    /// An IDR picture every this many pictures.
    Idr(u32),
    /// Periodic intra refresh over this many pictures (x264's moving intra
    /// column; a recovery point SEI starts each sweep), no IDR after the
    /// first picture.
    IntraRefresh(u32),
}

impl Shape {
    /// The default stream: an IDR picture every 2 s at 15 fps.
    const IDR_2S: Shape = Shape::Idr(30);

    fn name(self) -> String {
        match self {
            Shape::Idr(n) => format!("IDR every {:.0} s", f64::from(n) / 15.0),
            Shape::IntraRefresh(n) => format!("intra refresh over {:.0} s", f64::from(n) / 15.0),
        }
    }

    /// The sender's arguments for it.
    fn args(self) -> Vec<String> {
        match self {
            Shape::Idr(n) => vec!["--gop".into(), n.to_string()],
            Shape::IntraRefresh(n) => vec!["--gop".into(), n.to_string(), "--intra-refresh".into()],
        }
    }
}

/// One case: a sender, its proxy, a lossy and a clean source.
#[derive(Debug, Clone, Copy)]
struct Case {
    loss: Loss,
    answer: Answer,
    shape: Shape,
}

impl Case {
    fn name(&self) -> String {
        format!(
            "{}, {} (the sender answers {})",
            self.loss.name(),
            self.shape.name(),
            self.answer.name()
        )
    }
}

#[derive(Debug)]
struct Outcome {
    lossy: CountersSnapshot,
    clean: CountersSnapshot,
    link: LinkQuality,
    proxy: Arc<ProxyCounts>,
    /// Rows compared, marked, differing, differing unmarked (lossy against
    /// clean).
    rows: (usize, usize, usize, usize),
}

/// The GStreamer sender to the proxy at `rtp_port`: its test pattern for
/// `secs`, or the numbered PNG frames of `frames` (a printf pattern).
fn sender(
    rtp_port: u16,
    secs: u32,
    retransmits: bool,
    shape: Shape,
    frames: Option<&std::path::Path>,
) -> Child {
    let script =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/rtp_rtx_sender.py");
    let mut cmd = Command::new("/usr/bin/python3");
    cmd.arg(script)
        .args(["--rtp-port", &rtp_port.to_string()])
        .args(["--rtcp-port", &(rtp_port + 1).to_string()])
        .args(["--secs", &secs.to_string()])
        .args(shape.args());
    if !retransmits {
        cmd.arg("--no-retransmission");
    }
    if let Some(f) = frames {
        cmd.arg("--frames").arg(f);
    }
    cmd.stdout(Stdio::null())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("/usr/bin/python3 with gi (python3-gi) and GStreamer")
}

/// What one case's two sources published, and the proxy's counts.
struct Ran<T> {
    lossy: CountersSnapshot,
    clean: CountersSnapshot,
    link: LinkQuality,
    proxy: Arc<ProxyCounts>,
    lossy_frames: Vec<T>,
    clean_frames: Vec<T>,
}

/// At most this many cases run at once (a sender, two decoders each).
const AT_ONCE: usize = 7;

/// Run the cases, [`AT_ONCE`] at a time: the sender's test pattern for
/// `secs`, or the PNG frames of `frames`; `keep` takes what is kept of each
/// frame.
fn run_cases<T: Send + 'static>(
    rt: &tokio::runtime::Runtime,
    cases: &[Case],
    secs: u32,
    frames: Option<&std::path::Path>,
    keep: fn(&Frame) -> T,
) -> Vec<Ran<T>> {
    let mut out = Vec::new();
    for (b, batch) in cases.chunks(AT_ONCE).enumerate() {
        out.extend(run_batch(rt, batch, b * AT_ONCE, secs, frames, keep));
    }
    out
}

/// Run `cases` at once; `first` numbers the first (the drop models' seeds).
fn run_batch<T: Send + 'static>(
    rt: &tokio::runtime::Runtime,
    cases: &[Case],
    first: usize,
    secs: u32,
    frames: Option<&std::path::Path>,
    keep: fn(&Frame) -> T,
) -> Vec<Ran<T>> {
    let mut running = Vec::new();
    for (k, c) in cases.iter().enumerate() {
        let k = first + k;
        let (lossy_at, lossy) = LiveSource::start(rt, VideoConfig::default(), keep);
        let (clean_at, clean) = LiveSource::start(rt, VideoConfig::default(), keep);
        let proxy = Proxy::start(
            lossy_at,
            clean_at,
            c.loss,
            c.answer != Answer::Nothing,
            4000 + 10 * k as u64,
        );
        let child = sender(
            proxy.rtp_port,
            secs,
            c.answer == Answer::NackPli,
            c.shape,
            frames,
        );
        running.push((child, proxy, lossy, clean));
    }
    let mut out = Vec::new();
    for (mut child, proxy, lossy, clean) in running {
        let status = child.wait().unwrap();
        assert!(status.success(), "the GStreamer sender failed: {status}");
        let link = lossy.ingest.link.report();
        // The decoders drain what is queued (a bound, not a figure).
        let t = Instant::now();
        let mut last = lossy.ingest.counters.snapshot();
        loop {
            std::thread::sleep(Duration::from_millis(200));
            let now = lossy.ingest.counters.snapshot();
            if now == last || t.elapsed() > Duration::from_secs(10) {
                break;
            }
            last = now;
        }
        let counts = proxy.finish();
        let (lossy, lossy_frames) = lossy.stop(rt);
        let (clean, clean_frames) = clean.stop(rt);
        out.push(Ran {
            lossy,
            clean,
            link,
            proxy: counts,
            lossy_frames,
            clean_frames,
        });
    }
    out
}

/// The proxies' traces, with `SHOTPILOT_FEEDBACK_TRACE` set: their first
/// `SHOTPILOT_FEEDBACK_TRACE` seconds.
fn print_traces(cases: &[Case], proxies: &[&ProxyCounts]) {
    let Some(secs) = std::env::var("SHOTPILOT_FEEDBACK_TRACE")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
    else {
        return;
    };
    for (c, p) in cases.iter().zip(proxies) {
        for (t, what) in p.trace.lock().unwrap().iter().filter(|e| e.0 <= secs) {
            eprintln!("TRACE {}: {t:.3} s {what}", c.name());
        }
    }
}

fn figures(cases: &[Case], outcomes: &[Outcome]) {
    eprintln!(
        "FIGURES loss | stream | the sender answers | packets dropped/sent | pictures received | decoded | damaged | masked rows | usable, last 10 s | unreliable | asked (NACK) | recovered | mean wait ms | key frames asked | lost after retransmission | rows differing | differing unmasked | retransmissions sent | feedback packets back/dropped"
    );
    for (c, o) in cases.iter().zip(outcomes) {
        let k = &o.lossy;
        let p = &o.proxy;
        let dropped = p.dropped.load(Ordering::Relaxed);
        let (rows, _, differ, unmarked) = o.rows;
        eprintln!(
            "FIGURES {} | {} | {} | {}/{} | {} | {} | {} | {:.1} % | {:.1} % of {} | {} | {} | {} | {:.1} | {} | {} | {:.2} % | {} | {} | {}/{}",
            c.loss.name(),
            c.shape.name(),
            c.answer.name(),
            dropped,
            dropped + p.forwarded.load(Ordering::Relaxed),
            k.received,
            k.decoded,
            k.damaged,
            100.0 * k.masked_share,
            100.0 * o.link.usable_share,
            o.link.frames,
            o.link.unreliable,
            k.retransmit_asked,
            k.retransmit_recovered,
            k.retransmit_wait_ms,
            k.key_frame_requests,
            k.lost_packets,
            100.0 * differ as f64 / rows.max(1) as f64,
            unmarked,
            p.retransmissions.load(Ordering::Relaxed),
            p.feedback.load(Ordering::Relaxed),
            p.feedback_dropped.load(Ordering::Relaxed),
        );
    }
}

/// The cases on the sender's test pattern (20 s each), their figures and,
/// with `SHOTPILOT_FEEDBACK_TRACE` set, the proxies' traces.
fn pattern_outcomes(rt: &tokio::runtime::Runtime, cases: &[Case]) -> Vec<Outcome> {
    let outcomes: Vec<Outcome> = run_cases(rt, cases, 20, None, row_hashes)
        .into_iter()
        .map(|r| Outcome {
            rows: against_clean(&r.lossy_frames, &r.clean_frames),
            lossy: r.lossy,
            clean: r.clean,
            link: r.link,
            proxy: r.proxy,
        })
        .collect();
    outcomes
}

/// The checks of a table's cases, gathered rather than stopped at the
/// first: a failing run says every check that failed ahead of its table
/// (the first lines of a failure are what a CI log keeps).
#[derive(Default)]
struct Checks(Vec<String>);

impl Checks {
    /// Records `what` when `ok` is false.
    fn check(&mut self, ok: bool, what: impl FnOnce() -> String) {
        if !ok {
            self.0.push(what());
        }
    }

    /// The failed checks, then the table and the traces; fails the test
    /// when any check failed.
    fn report(self, cases: &[Case], outcomes: &[Outcome]) {
        if !self.0.is_empty() {
            eprintln!("{} checks failed:\n{}", self.0.len(), self.0.join("\n"));
        }
        figures(cases, outcomes);
        print_traces(
            cases,
            &outcomes.iter().map(|o| &*o.proxy).collect::<Vec<_>>(),
        );
        assert!(
            self.0.is_empty(),
            "{} checks failed:\n{}",
            self.0.len(),
            self.0.join("\n")
        );
    }
}

/// What holds on the test pattern whatever the case: the stream arrives,
/// the lossless copy is whole, and no row the lossy copy leaves unmarked
/// differs from the lossless one beyond the motion bound's allowance (as in
/// `video_loss`: 0.05 %; measured 0 in all 33 stream-shape cases): SLAM is
/// never given a damaged row as a good one.
fn check_pattern(checks: &mut Checks, c: &Case, o: &Outcome) {
    let name = c.name();
    let k = &o.lossy;
    checks.check(k.received >= 250, || format!("{name}: received {k:?}"));
    checks.check(o.clean.damaged == 0, || {
        format!("{name}: the clean copy damaged: {:?}", o.clean)
    });
    checks.check(
        (o.proxy.dropped.load(Ordering::Relaxed) > 0) == (c.loss.rate() > 0.0),
        || format!("{name}: the proxy's drops do not follow the loss rate"),
    );
    let (rows, _, _, unmarked) = o.rows;
    checks.check(rows > 200 * 480, || format!("{name}: {rows} rows compared"));
    checks.check(unmarked as f64 <= 0.0005 * rows as f64, || {
        format!("{name}: {unmarked} of {rows} rows differ without a mark")
    });
}

#[test]
#[ignore = "needs GStreamer (gst rtpbin, rtprtxsend, x264enc) and python3-gi"]
fn a_sender_that_retransmits_keeps_the_frames_whole_over_a_lossy_link() {
    let rt = crate::video_support::runtime();
    let mut cases = Vec::new();
    for loss in [
        Loss::Random(0.01),
        Loss::Random(0.05),
        Loss::Bursts {
            rate: 0.05,
            burst: 5.0,
        },
    ] {
        for answer in [Answer::NackPli, Answer::Nothing] {
            cases.push(Case {
                loss,
                answer,
                shape: Shape::IDR_2S,
            });
        }
    }
    cases.push(Case {
        loss: Loss::Random(0.01),
        answer: Answer::PliOnly,
        shape: Shape::IDR_2S,
    });
    let outcomes = pattern_outcomes(&rt, &cases);
    let mut checks = Checks::default();
    for (c, o) in cases.iter().zip(&outcomes) {
        check_pattern(&mut checks, c, o);
        let name = c.name();
        let k = &o.lossy;
        if c.answer == Answer::NackPli {
            checks.check(k.retransmit_asked > 0, || {
                format!("{name}: none asked: {k:?}")
            });
            // A request or its retransmission is lost at the link's rate
            // (twice over with two tries), and a burst can take both.
            let floor = match c.loss {
                Loss::Random(_) => 0.9,
                Loss::Bursts { .. } => 0.7,
            };
            checks.check(
                k.retransmit_recovered as f64 >= floor * k.retransmit_asked as f64,
                || format!("{name}: recovered under {floor} of those asked: {k:?}"),
            );
        } else {
            // A sender that does not retransmit is noticed: after the
            // first 16 requests only one gap in 10 s is asked for again.
            checks.check(k.retransmit_recovered == 0, || {
                format!("{name}: recovered from a silent sender: {k:?}")
            });
            checks.check(k.retransmit_asked <= 16 + 3 * 8, || {
                format!("{name}: a silent sender asked too often: {k:?}")
            });
        }
    }
    // What it buys: at each loss, the frames SLAM can use with feedback
    // against without.
    for (pair, cs) in outcomes[..6].chunks(2).zip(cases.chunks(2)) {
        let (with, without) = (&pair[0], &pair[1]);
        checks.check(
            with.lossy.masked_share < 0.5 * without.lossy.masked_share,
            || {
                format!(
                    "{}: masked share {:.3} with feedback against {:.3} without",
                    cs[0].name(),
                    with.lossy.masked_share,
                    without.lossy.masked_share
                )
            },
        );
    }
    // At 1 % random loss, the goal of issue 40: at least 90 % of the
    // frames reach SLAM usable.
    checks.check(
        outcomes[0].link.usable_share >= 0.9 && !outcomes[0].link.unreliable,
        || format!("{}: {:?}", cases[0].name(), outcomes[0].link),
    );
    checks.report(&cases, &outcomes);
}

/// Issue 40's table on a real encoder: the stream shapes a camera can be
/// set to (an IDR picture every 2 s or every 1 s, or periodic intra
/// refresh over 2 s) at 0, 1, 2, 5 and 10 % random loss and 5 % in bursts
/// of 5, from a sender that answers NACK and PLI and from one that answers
/// nothing. Every case: no damaged row passes unmarked. With a sender that
/// answers, up to 2 % random loss keeps at least 90 % of the frames
/// usable whatever the shape. `SHOTPILOT_FEEDBACK_ONLY=TEXT` runs only the
/// cases whose name contains TEXT.
#[test]
#[ignore = "needs GStreamer (gst rtpbin, rtprtxsend, x264enc) and python3-gi"]
fn every_stream_shape_at_every_loss_keeps_damage_out_of_slam() {
    let rt = crate::video_support::runtime();
    let only = std::env::var("SHOTPILOT_FEEDBACK_ONLY").ok();
    let mut cases = Vec::new();
    for shape in [Shape::IDR_2S, Shape::Idr(15), Shape::IntraRefresh(30)] {
        for loss in [
            Loss::Random(0.0),
            Loss::Random(0.01),
            Loss::Random(0.02),
            Loss::Random(0.05),
            Loss::Random(0.10),
            Loss::Bursts {
                rate: 0.05,
                burst: 5.0,
            },
        ] {
            for answer in [Answer::NackPli, Answer::Nothing] {
                if loss.rate() == 0.0 && answer == Answer::Nothing {
                    continue;
                }
                let c = Case {
                    loss,
                    answer,
                    shape,
                };
                if only.as_deref().is_none_or(|o| c.name().contains(o)) {
                    cases.push(c);
                }
            }
        }
    }
    let outcomes = pattern_outcomes(&rt, &cases);
    let mut checks = Checks::default();
    for (c, o) in cases.iter().zip(&outcomes) {
        check_pattern(&mut checks, c, o);
        let name = c.name();
        if c.loss.rate() == 0.0 {
            checks.check(o.lossy.damaged == 0, || {
                format!("{name}: damaged {:?}", o.lossy)
            });
            checks.check(o.link.usable_share >= 0.99, || {
                format!("{name}: usable {:?}", o.link)
            });
        } else if c.answer == Answer::NackPli && matches!(c.loss, Loss::Random(r) if r <= 0.02) {
            // A packet lost for good (its request or its retransmission
            // lost too, or late on a loaded machine) damages the stream
            // until it recovers: an IDR stream at the key frame its PLI
            // asks for (at the latest its next IDR), an intra-refresh
            // stream once the refresh has passed over it; up to the
            // stream's period of frames each (seen: intra refresh, 1 %, 2
            // packets lost for good, 82.5 % usable; 2 %, 4, 100 %).
            let k = &o.lossy;
            let period = match c.shape {
                Shape::IntraRefresh(n) | Shape::Idr(n) => f64::from(n),
            };
            let allowance = k.lost_packets as f64 * period / o.link.frames.max(1) as f64;
            // Recovered: 0.93-1.0 of those asked over these cases; a
            // sender that does not answer recovers none.
            checks.check(
                k.retransmit_recovered as f64 >= 0.85 * k.retransmit_asked as f64,
                || format!("{name}: recovered under 0.85 of those asked: {k:?}"),
            );
            checks.check(o.link.usable_share >= 0.9 - allowance, || {
                format!(
                    "{name}: usable under {:.3}: {:?} ({} packets lost for good)",
                    0.9 - allowance,
                    o.link,
                    k.lost_packets
                )
            });
        }
    }
    checks.report(&cases, &outcomes);
}

/// Which rendered picture a received frame is: the one in `window` whose
/// content its undamaged rows match best (mean absolute difference over a
/// grid of every 4th pixel), when that is clearly a match; else the best
/// candidate and its difference (`Err`), or `Err(None)` when too little
/// of the frame is undamaged to tell.
fn picture_index(
    f: &Frame,
    pictures: &[image::GrayImage],
    window: std::ops::Range<usize>,
) -> Result<usize, Option<(usize, f64)>> {
    let (w, h) = f.image.dimensions();
    let damaged = |y: u32| {
        f.damage
            .as_ref()
            .is_some_and(|d| d.rows().get(y as usize).copied().unwrap_or(true))
    };
    let mut best: Option<(usize, f64)> = None;
    for k in window {
        let Some(p) = pictures.get(k) else { break };
        let (mut sum, mut n) = (0u64, 0u64);
        for y in (0..h).step_by(4).filter(|&y| !damaged(y)) {
            for x in (0..w).step_by(4) {
                sum += u64::from(f.image.get_pixel(x, y)[0].abs_diff(p.get_pixel(x, y)[0]));
                n += 1;
            }
        }
        if n < 1000 {
            return Err(None);
        }
        let mad = sum as f64 / n as f64;
        if best.is_none_or(|b| mad < b.1) {
            best = Some((k, mad));
        }
    }
    // The encoder's error is a few grey levels; the flight's neighbouring
    // picture differs by more.
    match best {
        Some((k, mad)) if mad < 6.0 => Ok(k),
        other => Err(other),
    }
}

/// SLAM on the frames one source published, each put at its rendered
/// picture's time.
#[derive(Debug)]
struct SlamOutcome {
    /// Frames published; of those, frames too damaged to tell which
    /// picture they are (under 1,000 grid points unmasked), and frames
    /// unmasked enough that match no picture near where they should be.
    given: usize,
    unknown: usize,
    unmatched: usize,
    /// Frames with some row unmasked.
    usable: usize,
    /// Frames SLAM posed.
    tracked: usize,
    /// Mean masked share of the frames published.
    masked_share: f64,
    /// ATE against the truth, m.
    ate_m: f64,
}

fn slam_on(frames: &[Frame], flight: &Flight) -> SlamOutcome {
    let mut slam = shotpilot::slam::Slam::new(
        flight.cam,
        shotpilot::slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    let (mut next, mut unknown, mut unmatched, mut usable, mut masked) = (0usize, 0, 0, 0, 0.0);
    let mut misses = 0usize;
    for f in frames {
        // Search from the picture after the last one matched, further after
        // frames that were not (lost, or too damaged to tell).
        let window = next..(next + 10 + 10 * misses).min(flight.pictures.len());
        let k = match picture_index(f, &flight.pictures, window) {
            Ok(k) => k,
            Err(None) => {
                masked += f.masked_share();
                unknown += 1;
                misses += 1;
                continue;
            }
            Err(Some(best)) => {
                masked += f.masked_share();
                if unmatched < 3 {
                    eprintln!(
                        "frame {} (masked {:.2}): no picture from {next} matches (best {best:?})",
                        f.seq,
                        f.masked_share()
                    );
                }
                unmatched += 1;
                misses += 1;
                continue;
            }
        };
        misses = 0;
        next = k + 1;
        let share = f.masked_share();
        usable += usize::from(share < 1.0);
        masked += share;
        let mask = f.reliable_mask();
        slam.process_masked(k as u64, flight.gt[k].0, f.image.clone(), mask.as_ref());
    }
    let r = slam.finish();
    let gt = shotpilot::eval::Trajectory {
        poses: flight
            .gt
            .iter()
            .map(|(t, p)| shotpilot::eval::StampedPose {
                t: *t,
                world_from_cam: *p,
            })
            .collect(),
    };
    let ate = shotpilot::eval::evaluate(&gt, &r.trajectory(), &shotpilot::eval::Params::default())
        .map_or(f64::NAN, |e| e.ate.rmse);
    SlamOutcome {
        given: frames.len(),
        unknown,
        unmatched,
        usable,
        tracked: r.records.len(),
        masked_share: masked / frames.len().max(1) as f64,
        ate_m: ate,
    }
}

#[test]
#[ignore = "needs GStreamer (rtpbin, rtprtxsend, x264enc, pngdec) and python3-gi; renders 450 frames, runs SLAM eight times"]
fn slam_through_a_real_sender_over_a_lossy_link_with_and_without_feedback() {
    let rt = crate::video_support::runtime();
    let n = 450;
    let flight = explore_flight(n);
    let dir = tempfile::tempdir().unwrap();
    for (i, p) in flight.pictures.iter().enumerate() {
        p.save(dir.path().join(format!("{i:06}.png"))).unwrap();
    }
    // The stream shape: an IDR picture every 2 s, or for their figures
    // `SHOTPILOT_FEEDBACK_SHAPE=idr1` (every 1 s) or `intra` (intra
    // refresh over 2 s).
    let shape = match std::env::var("SHOTPILOT_FEEDBACK_SHAPE").as_deref() {
        Err(_) | Ok("idr2") => Shape::IDR_2S,
        Ok("idr1") => Shape::Idr(15),
        Ok("intra") => Shape::IntraRefresh(30),
        Ok(other) => panic!("SHOTPILOT_FEEDBACK_SHAPE={other}: idr2, idr1 or intra"),
    };
    let mut cases = Vec::new();
    for loss in [0.01, 0.05] {
        for answer in [Answer::NackPli, Answer::PliOnly, Answer::Nothing] {
            cases.push(Case {
                loss: Loss::Random(loss),
                answer,
                shape,
            });
        }
    }
    let ran = run_cases(
        &rt,
        &cases,
        0,
        Some(&dir.path().join("%06d.png")),
        Frame::clone,
    );
    print_traces(&cases, &ran.iter().map(|r| &*r.proxy).collect::<Vec<_>>());
    eprintln!(
        "FIGURES SLAM loss | stream | the sender answers | copy | published | too damaged to tell | usable | masked rows (mean) | usable, last 10 s | asked / recovered (NACK) | key frames asked | tracked | ATE m | ATE / lossless"
    );
    let mut results = Vec::new();
    for (c, r) in cases.iter().zip(&ran) {
        let lossy = slam_on(&r.lossy_frames, &flight);
        let clean = slam_on(&r.clean_frames, &flight);
        for (copy, o) in [("lossless", &clean), ("lossy", &lossy)] {
            eprintln!(
                "FIGURES SLAM {} | {} | {} | {copy} | {} | {} | {} | {:.1} % | {:.1} % | {} / {} | {} | {} ({:.1} %) | {:.3} | {:.2}x",
                c.loss.name(),
                c.shape.name(),
                c.answer.name(),
                o.given,
                o.unknown,
                o.usable,
                100.0 * o.masked_share,
                if copy == "lossy" {
                    100.0 * r.link.usable_share
                } else {
                    100.0
                },
                r.lossy.retransmit_asked,
                r.lossy.retransmit_recovered,
                r.lossy.key_frame_requests,
                o.tracked,
                100.0 * o.tracked as f64 / n as f64,
                o.ate_m,
                o.ate_m / clean.ate_m,
            );
        }
        results.push((lossy, clean));
    }
    for ((c, r), (lossy, clean)) in cases.iter().zip(&ran).zip(&results) {
        let name = c.name();
        // Every picture reaches both copies, but for a few a loaded machine's
        // decoder or watcher drops; each is the picture it is said to be.
        assert!(clean.given >= n * 9 / 10, "{name}: {clean:?}");
        assert!(clean.unmatched + clean.unknown <= 2, "{name}: {clean:?}");
        assert!(lossy.unmatched <= 2, "{name}: {lossy:?}");
        assert!(clean.tracked >= n * 8 / 10, "{name}: {clean:?}");
        // The other shapes' runs are for their figures (docs/FIGURES.md:
        // intra refresh tracks 85 % of the lossless copy's frames, an IDR
        // picture every 1 s measured 2.0x the ATE of its copy at 5 %).
        if c.answer == Answer::NackPli && c.shape == Shape::IDR_2S {
            // Issue 40's goals, with a sender that answers: at 1 % loss at
            // least 90 % of the frames reach SLAM usable (over the last
            // 10 s of the stream, past the first second, whose losses
            // come before the sender's first report says where to ask)
            // and the track holds; at 5 %, at least 70 % usable and the
            // track holds. The ATE: the lossless copies' own spreads
            // 0.034-0.073 m from run to run (each sender's key frames
            // differ), and the lossy one's ratio to it measured 0.80-1.29x
            // at 1 % and 0.52-1.45x at 5 % over five runs, and 2.31x at
            // 1 % in a sixth (0.087 against 0.038 m, in CI beside other
            // tests), so the goal's 1.2x is a figure, not a per-run bound;
            // what is asserted is that the map holds (a broken one is
            // 0.6 m off, 11x).
            let (usable, tracked) = match c.loss.rate() {
                r if r <= 0.01 => (0.9, 0.95),
                _ => (0.7, 0.8),
            };
            assert!(r.link.usable_share >= usable, "{name}: {:?}", r.link);
            assert!(
                lossy.tracked as f64 >= tracked * clean.tracked as f64,
                "{name}: {lossy:?} against {clean:?}"
            );
            assert!(
                lossy.ate_m <= (3.0 * clean.ate_m).max(clean.ate_m + 0.06),
                "{name}: {lossy:?} against {clean:?}"
            );
        }
    }
}

/// The daemon's `udp://` source against a sender scripted here (the plain
/// run's check of the feedback path; the GStreamer tests above are the
/// real peer): a lost packet is asked for by NACK and its RFC 4588
/// retransmission (another SSRC and payload type, the original sequence
/// number first) fills the gap without damage; then a sender that answers
/// nothing is asked 16 times and probed once, and the rest of its gaps
/// are given up at once.
#[test]
fn a_scripted_retransmission_fills_the_gap_and_a_silent_sender_stops_being_asked() {
    use shotpilot::video::h264::GrayEncoder;
    use shotpilot::video::rtp::feedback::{Feedback, parse_feedback};
    use shotpilot::video::rtp::packetize_h264;
    let rt = crate::video_support::runtime();
    let (to, source) = LiveSource::start(&rt, VideoConfig::default(), |f: &Frame| f.masked_share());
    let rtcp_to = SocketAddr::new(to.ip(), to.port() + 1);
    let sender = std::net::UdpSocket::bind("127.0.0.1:0").unwrap();
    sender
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let ssrc = 0x5eed_0001u32;
    let (w, h) = (320u32, 240u32);
    let mut enc = GrayEncoder::with_slices(w, h, 15.0, 300_000, 200, Some(600)).unwrap();
    let picture = |i: u32| {
        image::GrayImage::from_fn(w, h, |x, y| {
            image::Luma([(((x + 3 * i) / 8 + y / 8) % 2 * 160 + (x * 7 + y * 3 + i) % 40) as u8])
        })
    };
    let mut seq = 1000u16;
    let mut frames: Vec<Vec<Vec<u8>>> = Vec::new();
    for i in 0..60u32 {
        let au = enc.encode(&picture(i)).unwrap();
        frames.push(packetize_h264(
            &au,
            700,
            96,
            ssrc,
            &mut seq,
            90_000 + 6000 * i,
        ));
    }
    assert!(frames[5].len() >= 2 && frames[10..30].iter().all(|f| f.len() >= 2));
    // A sender report first, so the source knows where this sender's RTCP
    // comes from.
    let sr = shotpilot_sim::rtp::sender_report(ssrc, 1 << 40, 90_000, 0, 0, "scripted");
    sender.send_to(&sr, rtcp_to).unwrap();
    let counters = || source.ingest.counters.snapshot();
    let wait_for = |what: &str, done: &dyn Fn() -> bool| {
        let t = Instant::now();
        while !done() {
            assert!(
                t.elapsed() < Duration::from_secs(20),
                "{what}: {:?}",
                counters()
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    };
    // The frames go out at a camera's pace (50 fps), so that the source's
    // socket buffer never overflows: every loss is one made here.
    let pace = || std::thread::sleep(Duration::from_millis(20));
    // Frames 0-9: the second packet of frame 5 is lost, and retransmitted
    // when asked for (the gap shows when the next packet arrives).
    let lost = frames[5][1].clone();
    let lost_seq = u16::from_be_bytes([lost[2], lost[3]]);
    for (i, f) in frames[..10].iter().enumerate() {
        for (k, p) in f.iter().enumerate() {
            if (i, k) != (5, 1) {
                sender.send_to(p, to).unwrap();
            }
        }
        pace();
        if i == 6 {
            let mut buf = [0u8; 1500];
            let (n, _) = sender.recv_from(&mut buf).expect("a NACK");
            assert_eq!(
                parse_feedback(&buf[..n]),
                vec![Feedback::Nack {
                    media_ssrc: ssrc,
                    lost: vec![lost_seq]
                }]
            );
            // RFC 4588: another SSRC and payload type, its own sequence
            // number, the original's timestamp, and the original sequence
            // number before the original payload.
            let mut rtx = lost[..12].to_vec();
            rtx[1] = (lost[1] & 0x80) | 97;
            rtx[2..4].copy_from_slice(&7u16.to_be_bytes());
            rtx[8..12].copy_from_slice(&0x0bad_cafeu32.to_be_bytes());
            rtx.extend_from_slice(&lost_seq.to_be_bytes());
            rtx.extend_from_slice(&lost[12..]);
            sender.send_to(&rtx, to).unwrap();
        }
    }
    wait_for("frames 0-9 decoded", &|| counters().decoded >= 10);
    let k = counters();
    assert_eq!(
        (
            k.retransmit_asked,
            k.retransmit_recovered,
            k.lost_packets,
            k.damaged
        ),
        (1, 1, 0, 0),
        "{k:?}"
    );
    // Frames 10-59: one packet lost in each of 20 frames, never answered.
    for (i, f) in frames[10..].iter().enumerate() {
        for (k, p) in f.iter().enumerate() {
            if !(i < 20 && k == 1) {
                sender.send_to(p, to).unwrap();
            }
        }
        pace();
    }
    wait_for("all 20 gaps given up", &|| counters().lost_packets >= 20);
    wait_for("frames 10-59 decoded", &|| counters().decoded >= 60);
    let k = counters();
    // 16 asked before the sender counts as silent, then one probe.
    assert_eq!(
        (k.retransmit_asked, k.retransmit_recovered, k.lost_packets),
        (1 + 16 + 1, 1, 20),
        "{k:?}"
    );
    assert!(k.key_frame_requests >= 1, "{k:?}");
    let (_, kept) = source.stop(&rt);
    assert!(
        kept.iter().filter(|&&m| m > 0.0).count() >= 20,
        "frames after the losses are masked"
    );
}
