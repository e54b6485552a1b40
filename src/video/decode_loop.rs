//! The H.264 decode thread: [`DecodeLoop`], its state machine (decode every
//! access unit in order, match each picture to the unit it was coded in,
//! mark the rows a lost packet damaged, skip to a sync point when told to,
//! refuse a changed resolution), its [`DecodeParams`], and
//! [`spawn_decoder`], the thread that runs it between the reader's
//! [`AuQueue`] and the ingest's newest-frame slot.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use image::GrayImage;

use crate::video::damage::{DamageParams, DamageTracker, Losses, RowDamage};
use crate::video::h264::{
    AccessUnit, AuKind, AuQueue, H264Error, LumaDecoder, NAL_AUD, NAL_PPS, NAL_SPS, annexb_units,
    nal_type, push_annexb,
};
use crate::video::live::{Counters, Frame, Ingest};
use crate::video::motion::{MotionParams, Reduced, VerticalMotion, vertical_motion};

/// Tunables of the decode thread.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodeParams {
    /// Access units the reader may queue ahead of the decoder.
    pub queue: usize,
    /// Decimate the decoded luma by this integer factor (1: full
    /// resolution) before SLAM sees it.
    pub downscale: u32,
    /// After a lost packet, decode on with error concealment and mark the
    /// damaged rows (true), or skip to the next sync point (false).
    pub conceal: bool,
    /// How damage is followed through the pictures.
    pub damage: DamageParams,
    /// How the content's motion is measured for following the damage.
    pub motion: MotionParams,
}

impl Default for DecodeParams {
    fn default() -> Self {
        Self {
            queue: 8,
            downscale: 1,
            conceal: true,
            damage: DamageParams::default(),
            motion: MotionParams::default(),
        }
    }
}

/// The decode thread's state machine, apart from the thread so tests can
/// drive it: decode in order, skip to a sync point after damage, refuse a
/// changed resolution.
#[derive(Debug)]
pub struct DecodeLoop {
    decoder: LumaDecoder,
    damage: DamageTracker,
    params: DecodeParams,
    waiting_for_sync: bool,
    /// Without concealment: the decoder may hold a damaged picture or a
    /// failed state (OpenH264 then refuses every later IDR picture, "no
    /// parameter sets"), so decoding resumes at the next sync point with a
    /// fresh decoder.
    stale_decoder: bool,
    /// The stream's latest parameter sets (SPS and PPS NAL units, by type
    /// and id), given to a fresh decoder at a sync point that lacks them
    /// (a stream whose parameter sets came once, from the SDP or the
    /// first IDR picture).
    param_sets: Vec<(u8, u32, Vec<u8>)>,
    size: Option<(u32, u32)>,
    seq: u64,
    /// The decoder's tag of the next access unit.
    tag: u64,
    /// Access units given to the decoder whose picture has not come out
    /// yet: tag, damage, and the unit's times.
    pending: VecDeque<Pending>,
    /// The last picture handed out, reduced for motion measurement, and
    /// its tag.
    last: Option<(u64, Reduced)>,
    /// The content's last measured vertical motion (coded rows), and how
    /// many pictures ago it was measured.
    last_motion: Option<(VerticalMotion, u32)>,
}

/// An access unit whose picture the decoder has not handed out yet.
#[derive(Debug)]
struct Pending {
    tag: u64,
    damage: Option<crate::video::damage::PictureDamage>,
    lost: u32,
    capture_time: Option<f64>,
    received: Instant,
    received_unix: f64,
}

/// Pictures a motion measurement stands for when the next ones cannot be
/// measured (see `DecodeLoop::follow_motion`).
const MOTION_HOLD: u32 = 8;

/// Pictures the decoder may hold back before the oldest counts as lost.
const MAX_PENDING: usize = 16;

/// What one access unit became.
#[derive(Debug, Clone)]
pub enum Decoded {
    /// A picture for SLAM (with its damaged rows, if any).
    Frame(Arc<Frame>),
    /// Skipped: damaged, or predicted from a damaged picture.
    Skipped,
    /// Parameter sets only, no picture.
    NoPicture,
    /// The slice could not be decoded (then skipped to the next sync point).
    Broken(H264Error),
    /// The picture has another resolution than the stream's first.
    Refused {
        /// The stream's first resolution.
        first: (u32, u32),
        /// This picture's.
        now: (u32, u32),
    },
}

impl DecodeLoop {
    /// A fresh loop waiting for its first sync point.
    pub fn new(params: DecodeParams) -> Result<Self, H264Error> {
        let decoder = if params.conceal {
            LumaDecoder::concealing()?
        } else {
            LumaDecoder::new()?
        };
        Ok(Self {
            decoder,
            damage: DamageTracker::new(params.damage.clone()),
            params,
            waiting_for_sync: true,
            stale_decoder: false,
            param_sets: Vec::new(),
            size: None,
            seq: 0,
            tag: 0,
            pending: VecDeque::new(),
            last: None,
            last_motion: None,
        })
    }

    /// Forget the stream (a new connection): wait for a sync point and take
    /// the next resolution as the stream's.
    pub fn reset(&mut self) {
        self.waiting_for_sync = true;
        self.stale_decoder = !self.params.conceal;
        self.param_sets.clear();
        self.size = None;
        self.damage.reset();
        self.pending.clear();
        self.last = None;
        self.last_motion = None;
    }

    /// Measures the content's motion from the last picture handed out to
    /// `img` (tag `tag`, damaged `rows`) while there is damage to follow,
    /// and tells the damage tracker what to expect of the next picture: the
    /// range of the last two motions (a motion that changes), or the one
    /// measured widened by a pixel each way. A picture that could not be
    /// measured (damage over most of it, no texture) keeps the last
    /// measurement for up to [`MOTION_HOLD`] pictures, widened by a pixel
    /// each way per picture; after that, nothing is expected and the
    /// tracker falls back to its motion bound. Without damage only the
    /// reduced picture is kept (the matching is most of the cost).
    fn follow_motion(&mut self, tag: u64, img: &Arc<GrayImage>, rows: &RowDamage) {
        if !(self.params.conceal && self.params.damage.follow_motion) {
            return;
        }
        let cur = Reduced::new(img, Some(rows.rows()), &self.params.motion);
        if !self.damage.has_damage() {
            self.damage.set_motion(None);
            self.last_motion = None;
            self.last = Some((tag, cur));
            return;
        }
        let now = match &self.last {
            Some((t, prev)) if *t + 1 == tag => vertical_motion(prev, &cur, &self.params.motion)
                .map(|m| m.scaled(self.params.downscale)),
            _ => None,
        };
        let (expect, kept) = match (now, self.last_motion) {
            (Some(a), Some((b, age))) if age < MOTION_HOLD => (Some(a.union(b)), Some((a, 0))),
            (Some(a), _) => {
                let wide = VerticalMotion {
                    lo: a.lo - 1,
                    hi: a.hi + 1,
                    ..a
                };
                (Some(wide), Some((a, 0)))
            }
            (None, Some((b, age))) if age < MOTION_HOLD => {
                let w = age as i32 + 1;
                let wide = VerticalMotion {
                    lo: b.lo - w,
                    hi: b.hi + w,
                    ..b
                };
                (Some(wide), Some((b, age + 1)))
            }
            (None, _) => (None, None),
        };
        self.damage.set_motion(expect);
        self.last_motion = kept;
        self.last = Some((tag, cur));
    }

    /// Keep the parameter sets of an intact unit (the newest of each type
    /// and id).
    fn learn_param_sets(&mut self, annexb: &[u8]) {
        for nal in annexb_units(annexb) {
            let t = nal_type(nal);
            let id = match t {
                NAL_SPS => crate::video::damage::parse_sps(nal).map(|s| s.id),
                NAL_PPS => crate::video::damage::parse_pps(nal).map(|p| p.0),
                _ => continue,
            };
            let Some(id) = id else { continue };
            self.param_sets
                .retain(|(pt, pid, _)| !(*pt == t && *pid == id));
            self.param_sets.push((t, id, nal.to_vec()));
        }
    }

    /// The unit with the known parameter sets it lacks put first (for a
    /// fresh decoder).
    fn with_param_sets(&self, annexb: &[u8], kind: AuKind) -> Vec<u8> {
        let mut out = Vec::with_capacity(annexb.len() + 64);
        for (t, _, nal) in &self.param_sets {
            if (*t == NAL_SPS && !kind.sps) || (*t == NAL_PPS && !kind.pps) {
                push_annexb(&mut out, nal);
            }
        }
        out.extend_from_slice(annexb);
        out
    }

    /// Process one access unit; `gap` tells that units were dropped before it.
    pub fn step(&mut self, au: &AccessUnit, gap: bool) -> Decoded {
        let kind = AuKind::of(&au.data);
        // A queue overflow skips to a sync point either way: the decoder is
        // behind, and the pictures dropped were references.
        if gap || (au.lost > 0 && !self.params.conceal) {
            self.waiting_for_sync = true;
            self.stale_decoder = !self.params.conceal;
        }
        if !self.params.conceal {
            if au.lost > 0 {
                // Without concealment a damaged unit is never decoded, not
                // even an IDR picture: the decoder would hold it unfinished
                // or fail on it.
                return if kind.slice {
                    Decoded::Skipped
                } else {
                    Decoded::NoPicture
                };
            }
            self.learn_param_sets(&au.data);
        }
        let mut fresh: Option<Vec<u8>> = None;
        if self.waiting_for_sync {
            if kind.is_sync_point() && self.stale_decoder {
                match LumaDecoder::new() {
                    Ok(d) => self.decoder = d,
                    Err(e) => return Decoded::Broken(e),
                }
                self.stale_decoder = false;
                fresh = Some(self.with_param_sets(&au.data, kind));
            } else if !kind.is_sync_point() {
                return if kind.slice {
                    Decoded::Skipped
                } else {
                    // Parameter sets alone still go to the decoder.
                    match self.decoder.decode(&au.data) {
                        Ok(_) => Decoded::NoPicture,
                        Err(e) => Decoded::Broken(e),
                    }
                };
            }
            self.waiting_for_sync = false;
            self.damage.reset();
        }
        let damage = if self.params.conceal {
            let nals = annexb_units(&au.data);
            self.damage.picture(
                &nals,
                Losses {
                    lost: au.lost,
                    gaps: &au.gaps,
                },
            )
        } else {
            None
        };
        let tag = self.tag;
        self.tag += 1;
        if kind.slice {
            self.pending.push_back(Pending {
                tag,
                damage,
                lost: au.lost,
                capture_time: au.capture_time,
                received: au.received,
                received_unix: au.received_unix,
            });
            if self.pending.len() > MAX_PENDING {
                self.pending.pop_front();
                self.damage.picture_lost();
            }
        }
        // A picture missing slices is held by OpenH264 until the next
        // access unit starts, which then overwrites its output: an access
        // unit delimiter after a damaged unit ends the picture now, and its
        // concealed picture comes out with its own unit.
        let data: std::borrow::Cow<'_, [u8]> = if let Some(d) = fresh {
            d.into()
        } else if self.params.conceal && au.lost > 0 {
            let mut d = au.data.clone();
            push_annexb(&mut d, &[NAL_AUD, 0xf0]);
            d.into()
        } else {
            au.data.as_slice().into()
        };
        let mut pictures = match self.decoder.decode_tagged(&data, tag) {
            Ok(p) => p,
            Err(e) => {
                if self.params.conceal {
                    self.pending.retain(|p| p.tag != tag);
                    self.damage.picture_lost();
                } else {
                    self.waiting_for_sync = true;
                    self.stale_decoder = true;
                }
                return Decoded::Broken(e);
            }
        };
        let last = pictures.pop();
        // Rarely two pictures come out of one unit: the earlier one was
        // shown late, not lost; SLAM takes the newest.
        for (_, t) in pictures {
            self.pending.retain(|p| p.tag > t);
        }
        match last {
            Some((img, out_tag)) => {
                let now = (img.width(), img.height());
                match self.size {
                    None => self.size = Some(now),
                    Some(first) if first != now => {
                        return Decoded::Refused { first, now };
                    }
                    Some(_) => {}
                }
                let img = if self.params.downscale > 1 {
                    crate::video::live::downscale(&img, self.params.downscale)
                } else {
                    img
                };
                // The access unit this picture was coded in; the units
                // before it whose pictures never came out are lost, and so
                // is what was predicted from them.
                let mut skipped_before = false;
                while self.pending.front().is_some_and(|p| p.tag < out_tag) {
                    self.pending.pop_front();
                    skipped_before = true;
                }
                let unit = match self.pending.front() {
                    Some(p) if p.tag == out_tag => self.pending.pop_front(),
                    _ => None,
                };
                if skipped_before && self.params.conceal {
                    self.damage.picture_lost();
                }
                let h = img.height();
                let rows = match &unit {
                    _ if !self.params.conceal => RowDamage::clean(h as usize),
                    Some(p) if !skipped_before => match &p.damage {
                        Some(d) => d.rows_of(h, self.params.downscale),
                        // A picture the tracker could not place (parameter
                        // sets it could not read) is trusted only without
                        // a loss.
                        None if p.lost > 0 => RowDamage::full(h as usize),
                        None => RowDamage::clean(h as usize),
                    },
                    _ => RowDamage::full(h as usize),
                };
                let (capture_time, received, received_unix) = match &unit {
                    Some(p) => (p.capture_time, p.received, p.received_unix),
                    None => (au.capture_time, au.received, au.received_unix),
                };
                if skipped_before {
                    self.last = None;
                }
                let img = Arc::new(img);
                self.follow_motion(out_tag, &img, &rows);
                let frame = Frame::from_image(self.seq, capture_time, received, received_unix, img)
                    .with_damage(rows);
                self.seq += 1;
                Decoded::Frame(Arc::new(frame))
            }
            // No picture yet: a concealing decoder may hand it out with the
            // next access unit (it stays pending).
            None => Decoded::NoPicture,
        }
    }
}

/// Start the H.264 decode thread: it takes access units from `queue`,
/// decodes them and publishes the frames to `ingest` until the queue is
/// closed. `resets` is bumped by the reader on each new connection.
pub fn spawn_decoder(
    ingest: Arc<Ingest>,
    queue: Arc<AuQueue>,
    params: DecodeParams,
    resets: Arc<std::sync::atomic::AtomicU64>,
) -> Result<std::thread::JoinHandle<()>, std::io::Error> {
    std::thread::Builder::new()
        .name("h264-decode".into())
        .spawn(move || {
            let mut dl = match DecodeLoop::new(params) {
                Ok(d) => d,
                Err(e) => {
                    tracing::error!("video: {e}");
                    ingest.update_source(|s| s.last_error = Some(e.to_string()));
                    return;
                }
            };
            let mut seen_resets = 0;
            let mut refused_logged = false;
            let mut broken_logged = 0u64;
            loop {
                let (au, gap) = match queue.pop(Duration::from_millis(500)) {
                    Ok(Some(x)) => x,
                    Ok(None) => continue,
                    Err(()) => break,
                };
                let r = resets.load(std::sync::atomic::Ordering::Relaxed);
                if r != seen_resets {
                    seen_resets = r;
                    dl.reset();
                    refused_logged = false;
                }
                let c = &ingest.counters;
                match dl.step(&au, gap) {
                    Decoded::Frame(f) => {
                        let (w, h) = (f.image.width(), f.image.height());
                        let masked = f.damage.as_ref().map_or(0, |d| d.count()) as u64;
                        Counters::add(&c.rows, u64::from(h));
                        if masked > 0 {
                            Counters::inc(&c.damaged);
                            Counters::add(&c.masked_rows, masked);
                            if masked >= u64::from(h) {
                                Counters::inc(&c.fully_damaged);
                            }
                        }
                        ingest.update_source(|s| {
                            s.width = Some(w);
                            s.height = Some(h);
                        });
                        ingest.publish(f);
                    }
                    Decoded::Skipped => {
                        Counters::inc(&c.skipped);
                        ingest.link.lost();
                    }
                    Decoded::NoPicture => {}
                    Decoded::Broken(e) => {
                        Counters::inc(&c.bad);
                        Counters::inc(&c.skipped);
                        ingest.link.lost();
                        broken_logged += 1;
                        if broken_logged.is_power_of_two() {
                            tracing::warn!("video: {e} ({broken_logged} so far)");
                        }
                    }
                    Decoded::Refused { first, now } => {
                        Counters::inc(&c.refused);
                        if !refused_logged {
                            refused_logged = true;
                            let msg = format!(
                                "the stream changed resolution from {}x{} to {}x{} mid-flight; \
                                 frames are refused because the SLAM map and the camera \
                                 calibration are for {}x{} (set the camera back, or restart \
                                 the daemon with a [camera] for the new size)",
                                first.0, first.1, now.0, now.1, first.0, first.1
                            );
                            tracing::error!("video: {msg}");
                            ingest.update_source(|s| s.last_error = Some(msg));
                        }
                    }
                }
            }
        })
}
