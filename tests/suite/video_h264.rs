//! The H.264 path without outside peers: OpenH264-encoded renders of the
//! simulator, packetised as RFC 6184 RTP, through the depacketiser, the
//! skip-to-sync decode loop and the RTP clock. The lossy runs check that no
//! damaged picture reaches SLAM: every frame that comes out must be
//! bit-identical to the same picture decoded from the clean stream.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use image::GrayImage;
use rand::{Rng, SeedableRng};
use shotpilot::video::decode_loop::{DecodeLoop, DecodeParams, Decoded};
use shotpilot::video::h264::{AccessUnit, AuKind, AuQueue, GrayEncoder, annexb_units};
use shotpilot::video::rtp::{
    H264Depacketizer, RtpClock, looks_like_h265, packetize_h264, parse_rtp, parse_sender_report,
};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

/// `n` renders of the explore flight at 15 fps with a `w`x`h` camera.
fn renders(w: u32, h: u32, n: usize) -> Vec<GrayImage> {
    let world = Arc::new(World::generate_with(3, &WorldParams::small()).unwrap());
    let path = CameraPath::explore(&world, PathParams::default());
    let cam = SimCamera::with_size(w, h);
    let r = Renderer::new(world, cam, RenderParams::default());
    (0..n)
        .map(|i| r.render(&path.world_from_cam(path.start() + i as f64 / 15.0)))
        .collect()
}

struct Stream {
    aus: Vec<Vec<u8>>,
    frames: Vec<GrayImage>,
}

fn stream(w: u32, h: u32, n: usize, idr_period: u32) -> Stream {
    let frames = renders(w, h, n);
    let mut enc = GrayEncoder::new(w, h, 15.0, 400_000, idr_period).unwrap();
    let aus = frames.iter().map(|f| enc.encode(f).unwrap()).collect();
    Stream { aus, frames }
}

fn au(data: Vec<u8>, t: f64, lost: u32) -> AccessUnit {
    AccessUnit {
        data,
        capture_time: Some(t),
        received: Instant::now(),
        received_unix: t,
        lost,
        gaps: Vec::new(),
    }
}

fn mean_abs_diff(a: &GrayImage, b: &GrayImage) -> f64 {
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
        .sum::<f64>()
        / a.as_raw().len() as f64
}

/// Decode a stream cleanly: picture index -> image.
fn clean_decode(aus: &[Vec<u8>]) -> Vec<GrayImage> {
    let mut dl = DecodeLoop::new(DecodeParams::default()).unwrap();
    aus.iter()
        .enumerate()
        .map(|(i, a)| match dl.step(&au(a.clone(), i as f64, 0), false) {
            Decoded::Frame(f) => f.image.as_ref().clone(),
            other => panic!("clean picture {i}: {other:?}"),
        })
        .collect()
}

#[test]
fn decoder_gives_the_encoded_luma() {
    let s = stream(320, 240, 20, 10);
    assert!(AuKind::of(&s.aus[0]).idr && AuKind::of(&s.aus[0]).sps);
    assert!(!AuKind::of(&s.aus[1]).is_sync_point());
    assert!(AuKind::of(&s.aus[10]).idr, "IDR period 10");
    let out = clean_decode(&s.aus);
    assert_eq!(out.len(), 20);
    for (i, (o, f)) in out.iter().zip(&s.frames).enumerate() {
        assert_eq!(o.dimensions(), (320, 240));
        // 400 kbit/s at 320x240: a faithful picture, not a grey field.
        let d = mean_abs_diff(o, f);
        assert!(d < 6.0, "picture {i}: mean abs error {d:.2}");
    }
}

#[test]
fn rtp_roundtrip_gives_the_access_units_back() {
    let s = stream(320, 240, 12, 6);
    let mut seq = 65_530u16; // wraps inside the stream
    let mut depack = H264Depacketizer::new(vec![]);
    let mut got = Vec::new();
    let mut kinds = HashMap::new();
    for (i, a) in s.aus.iter().enumerate() {
        let ts = 4_294_960_000u32.wrapping_add(6000 * i as u32); // wraps too
        for p in packetize_h264(a, 400, 96, 0x1234_5678, &mut seq, ts) {
            assert!(p.len() <= 400);
            let pkt = parse_rtp(&p).unwrap();
            *kinds.entry(pkt.payload[0] & 0x1f).or_insert(0) += 1;
            got.extend(depack.push(&pkt));
        }
    }
    assert!(
        kinds.contains_key(&28),
        "large slices go as FU-A: {kinds:?}"
    );
    assert!(kinds.contains_key(&24), "SPS+PPS go as STAP-A: {kinds:?}");
    assert_eq!(got.len(), s.aus.len());
    for (g, a) in got.iter().zip(&s.aus) {
        assert_eq!(g.lost, 0);
        assert_eq!(annexb_units(&g.data), annexb_units(a));
    }
    assert_eq!(depack.stats().lost, 0);
    assert_eq!(depack.stats().late, 0);
}

/// What a lossy run gave.
#[derive(Debug, Default)]
struct LossyRun {
    /// Pictures sent.
    sent: usize,
    /// Packets sent and lost.
    packets: usize,
    lost: u64,
    /// Frames decoded (handed to SLAM).
    decoded: usize,
    /// Of those, frames with damaged rows, and with every row damaged.
    damaged: usize,
    fully_damaged: usize,
    /// Damaged rows over all decoded rows.
    masked_share: f64,
    skipped: usize,
    /// Frames whose unmasked rows were checked against the clean decode.
    compared: usize,
}

/// Encode `n` renders (IDR every `idr_period`; slices of at most
/// `slice_bytes`), send them as RTP packets of at most 1400 bytes, drop the
/// packets `drop` says (packet number -> dropped), and decode what comes
/// through with `params`. Every frame that comes out must equal the clean
/// decode of its picture, pixel for pixel, on every row it does not mark
/// damaged (with concealment off: on every row).
fn lossy_run_with(
    s: &Stream,
    params: DecodeParams,
    mut drop: impl FnMut(usize) -> bool,
    mut each: impl FnMut(usize, &shotpilot::video::live::Frame, &GrayImage),
) -> LossyRun {
    let clean = clean_decode(&s.aus);
    let mut seq = 0u16;
    let mut depack = H264Depacketizer::new(vec![]);
    let mut dl = DecodeLoop::new(params).unwrap();
    let mut run = LossyRun {
        sent: s.aus.len(),
        ..Default::default()
    };
    let (mut rows, mut masked_rows) = (0usize, 0usize);
    for (i, a) in s.aus.iter().enumerate() {
        let ts = 6000 * i as u32;
        for p in packetize_h264(a, 1400, 96, 7, &mut seq, ts) {
            run.packets += 1;
            if drop(run.packets - 1) {
                continue;
            }
            for done in depack.push(&parse_rtp(&p).unwrap()) {
                let idx = (done.timestamp / 6000) as usize;
                let mut unit = au(done.data, idx as f64, done.lost);
                unit.gaps = done.gaps;
                let out = dl.step(&unit, false);
                match out {
                    Decoded::Frame(f) => {
                        run.decoded += 1;
                        let h = f.image.height() as usize;
                        let bad = f.damage.as_ref().map_or(0, |d| d.count());
                        rows += h;
                        masked_rows += bad;
                        if bad > 0 {
                            run.damaged += 1;
                        }
                        if bad == h {
                            run.fully_damaged += 1;
                            continue;
                        }
                        run.compared += 1;
                        let w = f.image.width() as usize;
                        for y in 0..h {
                            if f.damage.as_ref().is_some_and(|d| d.rows()[y]) {
                                continue;
                            }
                            let got = &f.image.as_raw()[y * w..(y + 1) * w];
                            let want = &clean[idx].as_raw()[y * w..(y + 1) * w];
                            assert_eq!(
                                got, want,
                                "picture {idx}: row {y} is not marked damaged but differs from the clean decode"
                            );
                        }
                        each(idx, &f, &clean[idx]);
                    }
                    Decoded::Skipped | Decoded::Broken(_) => run.skipped += 1,
                    Decoded::NoPicture => {}
                    Decoded::Refused { .. } => panic!("no size change here"),
                }
            }
        }
    }
    run.lost = depack.stats().lost;
    run.masked_share = masked_rows as f64 / rows.max(1) as f64;
    run
}

fn sliced_stream(n: usize, idr_period: u32, slice_bytes: Option<u32>) -> Stream {
    let frames = renders(320, 240, n);
    let mut enc =
        GrayEncoder::with_slices(320, 240, 15.0, 400_000, idr_period, slice_bytes).unwrap();
    let aus = frames.iter().map(|f| enc.encode(f).unwrap()).collect();
    Stream { aus, frames }
}

fn random_loss(loss: f64, seed: u64) -> impl FnMut(usize) -> bool {
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    move |_| rng.random::<f64>() < loss
}

#[test]
fn without_concealment_a_loss_skips_to_the_next_idr_and_never_smears() {
    let s = stream(320, 240, 90, 15);
    let params = DecodeParams {
        conceal: false,
        ..Default::default()
    };
    let r = lossy_run_with(&s, params, random_loss(0.01, 11), |_, f, _| {
        assert!(f.damage.is_none(), "skipping mode marks nothing")
    });
    eprintln!("1% loss, skipping: {r:?}");
    assert!(r.lost > 0, "the run must lose packets");
    assert!(r.skipped > 0);
    // One IDR per second: most of the stream survives 1 % loss.
    assert!(r.decoded >= 45, "{r:?}");
}

/// Concealment off on a stream cut into slices (what the simulator's
/// encoder and most cameras send): after a loss the loop skips to the next
/// IDR picture and decodes from there on, also when the lost packet was
/// an IDR picture's own. OpenH264 with concealment off drops its
/// parameter sets when a damaged picture fails, so the loop must give
/// them again with the next IDR.
#[test]
fn without_concealment_a_sliced_stream_resumes_at_each_idr() {
    let s = sliced_stream(90, 15, Some(1200));
    // Where each picture's packets start.
    let mut first_packet = Vec::new();
    let mut seq = 0u16;
    let mut n = 0;
    for a in &s.aus {
        first_packet.push(n);
        n += packetize_h264(a, 1400, 96, 7, &mut seq, 0).len();
    }
    // The last packet of IDR picture 15, a packet of picture 47 (in the
    // fourth group of pictures) and the first of IDR picture 75.
    let drops = [first_packet[16] - 1, first_packet[47], first_packet[75]];
    let params = DecodeParams {
        conceal: false,
        ..Default::default()
    };
    let r = lossy_run_with(
        &s,
        params,
        |k| drops.contains(&k),
        |_, f, _| assert!(f.damage.is_none(), "skipping mode marks nothing"),
    );
    eprintln!("sliced, skipping, packets {drops:?} lost: {r:?}");
    assert_eq!(r.lost, 3, "{r:?}");
    // Pictures 0-14, 30-46 and 60-74 decode; 15-29 (from the damaged
    // IDR), 47-59 and 75-89 are skipped.
    assert_eq!(r.decoded, 15 + 17 + 15, "{r:?}");
}

/// A stream whose parameter sets come once, with its first picture (as
/// from a camera that sends them only in the SDP): after a loss the fresh
/// decoder at the next IDR picture is given the ones seen before.
#[test]
fn without_concealment_parameter_sets_sent_once_are_given_again() {
    let mut s = sliced_stream(60, 15, Some(1200));
    for a in s.aus.iter_mut().skip(1) {
        let mut kept = Vec::new();
        for nal in annexb_units(a) {
            if !matches!(nal[0] & 0x1f, 7 | 8) {
                shotpilot::video::h264::push_annexb(&mut kept, nal);
            }
        }
        *a = kept;
    }
    assert!(s.aus[15..].iter().all(|a| {
        let k = AuKind::of(a);
        !k.sps && !k.pps
    }));
    let mut first_packet = Vec::new();
    let (mut seq, mut n) = (0u16, 0);
    for a in &s.aus {
        first_packet.push(n);
        n += packetize_h264(a, 1400, 96, 7, &mut seq, 0).len();
    }
    let drop = first_packet[20];
    let params = DecodeParams {
        conceal: false,
        ..Default::default()
    };
    let r = lossy_run_with(&s, params, |k| k == drop, |_, _, _| {});
    eprintln!("parameter sets once, packet {drop} lost: {r:?}");
    assert_eq!(r.lost, 1, "{r:?}");
    // 0-19 and 30-59 decode; 20-29 are skipped.
    assert_eq!(r.decoded, 20 + 30, "{r:?}");
}

/// Concealment on, a stream cut into slices of one packet each: every
/// frame reaches SLAM, and its unmasked rows are the clean decode's.
fn concealed_run(loss: f64, seed: u64, slice_bytes: Option<u32>) -> LossyRun {
    let s = sliced_stream(90, 15, slice_bytes);
    let r = lossy_run_with(
        &s,
        DecodeParams::default(),
        random_loss(loss, seed),
        |_, _, _| {},
    );
    eprintln!(
        "{:.0} % loss, slices {slice_bytes:?}: {} packets, {} lost; {} of {} pictures decoded, \
         {} damaged ({} fully), {:.1} % of rows masked, {} skipped",
        loss * 100.0,
        r.packets,
        r.lost,
        r.decoded,
        r.sent,
        r.damaged,
        r.fully_damaged,
        r.masked_share * 100.0,
        r.skipped
    );
    r
}

#[test]
fn one_percent_loss_conceals_and_masks_only_the_damaged_rows() {
    let r = concealed_run(0.01, 11, Some(1200));
    assert!(
        r.lost > 0 && r.damaged > 0,
        "the run must damage pictures: {r:?}"
    );
    assert_eq!(r.decoded, r.sent, "every picture reaches SLAM: {r:?}");
    assert!(r.compared > r.fully_damaged, "{r:?}");
}

#[test]
fn five_percent_loss_conceals_and_masks_only_the_damaged_rows() {
    let r = concealed_run(0.05, 12, Some(1200));
    assert!(r.lost > 5, "{r:?}");
    assert!(
        r.decoded + 2 >= r.sent,
        "every picture but a lost IDR's reaches SLAM: {r:?}"
    );
    assert!(r.compared > 0, "{r:?}");
}

#[test]
fn single_slice_pictures_lose_the_whole_picture_to_a_loss() {
    let r = concealed_run(0.02, 13, None);
    assert!(r.lost > 0, "{r:?}");
    assert!(
        r.fully_damaged > 0,
        "one slice per picture: a loss masks it all: {r:?}"
    );
}

#[test]
fn a_lost_slice_masks_its_rows_and_the_features_there_are_the_clean_ones() {
    use shotpilot::features::{OrbExtractor, Params as OrbParams};
    let s = sliced_stream(30, 30, Some(600));
    // The packets of picture 5 (a P picture cut into several slices).
    let mut seq = 0u16;
    let mut first_of = Vec::new();
    let mut count = 0;
    for (i, a) in s.aus.iter().enumerate() {
        first_of.push(count);
        count += packetize_h264(a, 1400, 96, 7, &mut seq, 6000 * i as u32).len();
    }
    let (p5, p6) = (first_of[5], first_of[6]);
    assert!(p6 - p5 >= 3, "picture 5 has {} packets", p6 - p5);
    let victim = p5 + (p6 - p5) / 2;
    let mut ext = OrbExtractor::new(OrbParams::default()).unwrap();
    let mut masks = Vec::new();
    let mut features_checked = 0;
    let r = lossy_run_with(
        &s,
        DecodeParams::default(),
        |k| k == victim,
        |idx, f, clean| {
            masks.push((idx, f.masked_share()));
            let Some(mask) = f.reliable_mask() else {
                return;
            };
            // What SLAM extracts from the damaged frame is what it would
            // extract, under the same mask, from the clean picture.
            let got = ext.extract_masked(&f.image, &mask, None).unwrap();
            let want = ext.extract_masked(clean, &mask, None).unwrap();
            assert_eq!(got.keypoints.len(), want.keypoints.len(), "picture {idx}");
            for (a, b) in got.keypoints.iter().zip(&want.keypoints) {
                assert_eq!((a.x, a.y), (b.x, b.y), "picture {idx}");
                let row = a.y.round() as usize;
                assert!(!f.damage.as_ref().unwrap().rows()[row.min(f.image.height() as usize - 1)]);
            }
            assert_eq!(got.descriptors, want.descriptors, "picture {idx}");
            features_checked += got.keypoints.len();
        },
    );
    eprintln!("one packet of picture 5 lost: {r:?}; masked share per picture {masks:?}");
    assert_eq!(r.lost, 1);
    assert_eq!(r.decoded, 30);
    let share = |i: usize| masks.iter().find(|m| m.0 == i).map_or(-1.0, |m| m.1);
    assert_eq!(share(4), 0.0, "before the loss");
    assert!(
        share(5) > 0.0 && share(5) < 1.0,
        "part of picture 5: {}",
        share(5)
    );
    assert!(share(6) >= share(5), "picture 6 predicts from it");
    assert!(features_checked > 100, "{features_checked}");
}

#[test]
fn a_stream_joined_mid_gop_waits_for_the_idr() {
    let s = stream(160, 120, 16, 8);
    let mut dl = DecodeLoop::new(DecodeParams::default()).unwrap();
    let mut out = Vec::new();
    for (i, a) in s.aus.iter().enumerate().skip(3) {
        out.push(match dl.step(&au(a.clone(), i as f64, 0), false) {
            Decoded::Frame(_) => 'F',
            Decoded::Skipped => 'S',
            other => panic!("{other:?}"),
        });
    }
    let out: String = out.into_iter().collect();
    assert_eq!(out, "SSSSSFFFFFFFF", "pictures 3..16 with an IDR at 8");
}

#[test]
fn queue_overflow_drops_the_backlog_and_resumes_at_a_sync_point() {
    let s = stream(160, 120, 12, 6);
    let q = AuQueue::new(3);
    let mut dropped = 0;
    for (i, a) in s.aus.iter().enumerate().take(5) {
        dropped += q.push(au(a.clone(), i as f64, 0));
    }
    assert_eq!(
        dropped, 3,
        "the fourth push found 3 queued and dropped them"
    );
    let mut dl = DecodeLoop::new(DecodeParams::default()).unwrap();
    let (first, gap) = q
        .pop(std::time::Duration::ZERO)
        .unwrap()
        .expect("picture 3");
    assert!(gap);
    assert!(matches!(dl.step(&first, gap), Decoded::Skipped));
}

#[test]
fn a_resolution_change_is_refused_with_both_sizes() {
    let a = stream(160, 120, 2, 1);
    let b = stream(320, 240, 2, 1);
    let mut dl = DecodeLoop::new(DecodeParams::default()).unwrap();
    assert!(matches!(
        dl.step(&au(a.aus[0].clone(), 0.0, 0), false),
        Decoded::Frame(_)
    ));
    match dl.step(&au(b.aus[0].clone(), 1.0, 0), false) {
        Decoded::Refused { first, now } => {
            assert_eq!(first, (160, 120));
            assert_eq!(now, (320, 240));
        }
        other => panic!("{other:?}"),
    }
    // A new connection may bring a new size.
    dl.reset();
    assert!(matches!(
        dl.step(&au(b.aus[0].clone(), 2.0, 0), false),
        Decoded::Frame(_)
    ));
}

#[test]
fn downscaled_frames_average_the_blocks() {
    let s = stream(320, 240, 1, 1);
    let mut dl = DecodeLoop::new(DecodeParams {
        downscale: 2,
        ..Default::default()
    })
    .unwrap();
    let Decoded::Frame(f) = dl.step(&au(s.aus[0].clone(), 0.0, 0), false) else {
        panic!()
    };
    assert_eq!(f.image.dimensions(), (160, 120));
    let full = clean_decode(&s.aus);
    let p = |x: u32, y: u32| u32::from(full[0].get_pixel(x, y).0[0]);
    let want = (p(20, 30) + p(21, 30) + p(20, 31) + p(21, 31) + 2) / 4;
    assert_eq!(u32::from(f.image.get_pixel(10, 15).0[0]), want);
}

#[test]
fn rtp_clock_uses_sender_reports_else_the_least_delayed_arrival() {
    let mut c = RtpClock::new(90_000);
    // Arrivals with jitter of 0..40 ms over a true capture at 1000 + k/30.
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let mut last = 0.0;
    for k in 0..300u32 {
        let ts = 3000u32.wrapping_mul(k).wrapping_add(u32::MAX - 30_000); // wraps
        let truth = 1000.0 + f64::from(k) / 30.0;
        let arrival = truth + 0.010 + rng.random::<f64>() * 0.040;
        last = c.capture_time(ts, arrival) - truth;
    }
    // The minimum delay (10 ms plus the smallest jitter) remains; no jitter.
    assert!((0.009..0.013).contains(&last), "{last}");
    // A sender report pins RTP time to the sender's clock exactly.
    let ntp_of = |unix: f64| {
        let s = unix + shotpilot::video::rtp::NTP_UNIX_OFFSET_S;
        ((s.floor() as u64) << 32) | ((s.fract() * 4_294_967_296.0) as u64)
    };
    let ts300 = 3000u32.wrapping_mul(300).wrapping_add(u32::MAX - 30_000);
    c.sender_report(ts300, ntp_of(1010.0));
    let t = c.capture_time(ts300.wrapping_add(9000), 1010.2);
    assert!((t - 1010.1).abs() < 1e-4, "{t}");
    assert!(c.has_sender_report());
    // The RTCP parser finds the report in a compound packet (RR first).
    let mut rr = vec![0x80, 201, 0, 1, 0, 0, 0, 9];
    let mut sr = vec![0x80, 200, 0, 6, 0, 0, 0, 7];
    sr.extend_from_slice(&ntp_of(1010.0).to_be_bytes());
    sr.extend_from_slice(&ts300.to_be_bytes());
    sr.extend_from_slice(&[0; 8]);
    rr.extend_from_slice(&sr);
    let (ssrc, ntp, rtp) = parse_sender_report(&rr).unwrap();
    assert_eq!((ssrc, ntp, rtp), (7, ntp_of(1010.0), ts300));
}

/// RTCP and RTP come on two sockets read in either order, and a sender
/// sends its first report right after its first picture: a report read
/// before the sender's first RTP packet must still time that sender's
/// pictures, and a report from another sender must not.
#[test]
fn a_sender_report_before_the_first_packet_is_kept_for_its_sender() {
    let ntp_of = |unix: f64| {
        let s = unix + shotpilot::video::rtp::NTP_UNIX_OFFSET_S;
        ((s.floor() as u64) << 32) | ((s.fract() * 4_294_967_296.0) as u64)
    };
    // The report comes first (RTP clock 90 000 at unix 2000.0).
    let mut c = RtpClock::new(90_000);
    assert!(!c.sender_report_from(7, 90_000, ntp_of(2000.0)));
    assert!(!c.has_sender_report());
    assert!(c.stream_from(7), "the early report is taken");
    assert_eq!(c.ssrc(), Some(7));
    assert!(!c.stream_from(7), "and only once");
    // A picture 1 s later on the RTP clock, arriving 0.3 s late.
    let t = c.capture_time(180_000, 2001.3);
    assert!((t - 2001.0).abs() < 1e-4, "{t}");
    // Later reports from the same sender are taken at once.
    assert!(c.sender_report_from(7, 270_000, ntp_of(2002.5)));
    let t = c.capture_time(270_000, 2002.9);
    assert!((t - 2002.5).abs() < 1e-4, "{t}");

    // A report from a sender that is not the stream's is not used, and a
    // restarted sender (new SSRC) starts the clock afresh.
    let mut c = RtpClock::new(90_000);
    assert!(!c.sender_report_from(8, 90_000, ntp_of(2000.0)));
    assert!(!c.stream_from(7));
    assert!(!c.has_sender_report());
    let t = c.capture_time(180_000, 2001.3);
    assert!((t - 2001.3).abs() < 1e-4, "arrival-mapped: {t}");
    assert!(c.sender_report_from(7, 180_000, ntp_of(2001.0)));
    assert!(
        !c.sender_report_from(9, 0, ntp_of(3000.0)),
        "kept for sender 9"
    );
    assert!(c.stream_from(9), "the restarted sender's early report");
    let t = c.capture_time(45_000, 3007.0);
    assert!((t - 3000.5).abs() < 1e-4, "{t}");
}

#[test]
fn h265_payloads_are_recognised() {
    // VPS, SPS, PPS, FU and a TRAIL_R-in-FU as rtph265pay sends them.
    for p in [
        [0x40u8, 0x01, 0x0c],
        [0x42, 0x01, 0x01],
        [0x44, 0x01, 0xc1],
        [0x62, 0x01, 0x93],
    ] {
        assert!(looks_like_h265(&p), "{p:02x?}");
    }
    // H.264: SPS, PPS, IDR, FU-A, STAP-A, SEI.
    for p in [
        [0x67u8, 0x42, 0xc0],
        [0x68, 0xce, 0x3c],
        [0x65, 0x88, 0x84],
        [0x7c, 0x85, 0x88],
        [0x78, 0x00, 0x0f],
        [0x06, 0x05, 0xff],
    ] {
        assert!(!looks_like_h265(&p), "{p:02x?}");
    }
}

#[test]
fn malformed_packets_are_errors_not_panics() {
    assert!(parse_rtp(&[0x80; 5]).is_err());
    assert!(parse_rtp(&[0x40; 20]).is_err(), "version 1");
    // Padding larger than the payload.
    let mut p = vec![0xa0, 96, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0x65, 0xff];
    assert!(parse_rtp(&p).is_err());
    p[0] = 0x80;
    let mut d = H264Depacketizer::new(vec![]);
    // A STAP-A whose unit overruns, then an FU-A continuation without start.
    for (k, payload) in [
        vec![24u8, 0, 9, 0x67],
        vec![28, 0x05, 1, 2, 3],
        vec![28, 0xc5],
        vec![],
    ]
    .into_iter()
    .enumerate()
    {
        let mut pkt = p[..12].to_vec();
        pkt[1] |= 0x80;
        pkt[3] = k as u8 + 1;
        pkt.extend_from_slice(&payload);
        if let Ok(r) = parse_rtp(&pkt) {
            let _ = d.push(&r);
        }
    }
    assert!(d.stats().malformed >= 2, "{:?}", d.stats());
}
