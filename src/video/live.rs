//! Live frames: the latest-value slot, the decoded [`Frame`], the ingest
//! counters and the decode thread.
//!
//! The network reader puts each whole JPEG part into a raw [`Latest`] slot;
//! a decode thread takes the newest part, decodes it to grey and puts the
//! frame into the frame slot, which SLAM takes from. Every slot keeps only the
//! newest value, so a slow decoder or a slow SLAM never stalls the reader:
//! the values they did not take are counted as dropped.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use image::GrayImage;
use serde::Serialize;
use tokio::sync::watch;

use crate::video::damage::RowDamage;

/// The slot was closed: no value will come any more.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the frame slot is closed")]
pub struct Closed;

#[derive(Debug)]
struct LatestState<T> {
    value: Option<T>,
    fresh: bool,
    closed: bool,
}

/// A slot holding only the newest value. `put` never blocks on the
/// consumer; `take_fresh` waits for a value not taken before.
#[derive(Debug)]
pub struct Latest<T> {
    state: Mutex<LatestState<T>>,
    cv: Condvar,
}

impl<T: Clone> Default for Latest<T> {
    fn default() -> Self {
        Self::new()
    }
}

impl<T: Clone> Latest<T> {
    /// An empty, open slot.
    pub fn new() -> Self {
        Self {
            state: Mutex::new(LatestState {
                value: None,
                fresh: false,
                closed: false,
            }),
            cv: Condvar::new(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, LatestState<T>> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Store `value` as the newest. Returns true when it replaced a value
    /// nobody had taken (that value is dropped).
    pub fn put(&self, value: T) -> bool {
        let mut s = self.lock();
        let replaced_unseen = s.fresh;
        s.value = Some(value);
        s.fresh = true;
        drop(s);
        self.cv.notify_all();
        replaced_unseen
    }

    /// Wait up to `timeout` for a value not taken before and take it.
    /// `Ok(None)` on timeout, `Err(Closed)` once the slot is closed.
    pub fn take_fresh(&self, timeout: Duration) -> Result<Option<T>, Closed> {
        let deadline = Instant::now() + timeout;
        let mut s = self.lock();
        loop {
            if s.fresh {
                s.fresh = false;
                return Ok(s.value.clone());
            }
            if s.closed {
                return Err(Closed);
            }
            let now = Instant::now();
            if now >= deadline {
                return Ok(None);
            }
            s = self
                .cv
                .wait_timeout(s, deadline - now)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// The newest value, taken or not, without marking it taken.
    pub fn peek(&self) -> Option<T> {
        self.lock().value.clone()
    }

    /// Close the slot: waiting consumers return `Err(Closed)` once the
    /// fresh value (if any) is taken.
    pub fn close(&self) {
        self.lock().closed = true;
        self.cv.notify_all();
    }

    /// Whether the slot was closed.
    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }
}

/// One whole JPEG as read from the network, not yet decoded.
#[derive(Debug, Clone)]
pub struct RawPart {
    /// The JPEG bytes.
    pub jpeg: Arc<Vec<u8>>,
    /// Capture time from the `X-Timestamp` header, unix seconds.
    pub capture_time: Option<f64>,
    /// When the last byte arrived.
    pub received: Instant,
    /// The same instant as unix seconds.
    pub received_unix: f64,
}

/// A decoded video frame.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Ingest sequence number (counts decoded frames from 0).
    pub seq: u64,
    /// Capture time (`X-Timestamp`), unix seconds, when the source sent it.
    pub capture_time: Option<f64>,
    /// When the JPEG was completely received.
    pub received: Instant,
    /// The same instant as unix seconds.
    pub received_unix: f64,
    /// The grey image.
    pub image: Arc<GrayImage>,
    /// Rows a lost packet may have reached (concealed by the decoder, or
    /// predicted from concealed rows): SLAM takes no feature from them.
    /// `None`: every row is as the camera encoded it.
    pub damage: Option<Arc<RowDamage>>,
    /// The JPEG the API re-serves: as received for MJPEG, encoded from the
    /// grey image on first use for H.264.
    jpeg: OnceLock<Arc<Vec<u8>>>,
    /// Whether `jpeg` holds the bytes as received (MJPEG), not an encoding.
    jpeg_received: bool,
}

impl Frame {
    /// A frame decoded from a source that sends no JPEG (H.264): the JPEG
    /// is encoded from `image` when somebody asks for it.
    pub fn from_image(
        seq: u64,
        capture_time: Option<f64>,
        received: Instant,
        received_unix: f64,
        image: Arc<GrayImage>,
    ) -> Self {
        Self {
            seq,
            capture_time,
            received,
            received_unix,
            image,
            damage: None,
            jpeg: OnceLock::new(),
            jpeg_received: false,
        }
    }

    /// The frame with its damaged rows (`rows` as many as the image's;
    /// kept only when some row is damaged).
    pub fn with_damage(mut self, rows: RowDamage) -> Self {
        self.damage = rows.any().then(|| Arc::new(rows));
        self
    }

    /// Share of the rows that are damaged (0 for an intact frame).
    pub fn masked_share(&self) -> f64 {
        match &self.damage {
            Some(d) if !d.rows().is_empty() => d.count() as f64 / d.rows().len() as f64,
            _ => 0.0,
        }
    }

    /// A pixel mask for feature extraction: 255 where the image can be
    /// trusted, 0 on damaged rows; `None` for an intact frame.
    pub fn reliable_mask(&self) -> Option<GrayImage> {
        let d = self.damage.as_ref()?;
        let (w, h) = self.image.dimensions();
        Some(GrayImage::from_fn(w, h, |_, y| {
            let bad = d.rows().get(y as usize).copied().unwrap_or(true);
            image::Luma([if bad { 0 } else { 255 }])
        }))
    }

    /// The JPEG bytes exactly as the source sent them (MJPEG, snapshot);
    /// `None` for frames decoded from a stream that sends no JPEG (H.264),
    /// whose only lossless form is `image` itself.
    pub fn received_jpeg(&self) -> Option<Arc<Vec<u8>>> {
        if self.jpeg_received {
            self.jpeg.get().cloned()
        } else {
            None
        }
    }

    /// The best timestamp: the capture time, else the receive time.
    pub fn timestamp(&self) -> f64 {
        self.capture_time.unwrap_or(self.received_unix)
    }

    /// The frame as a JPEG: the bytes received for MJPEG sources (no
    /// re-encoding), else the grey image encoded once (quality 85) and
    /// kept for every later caller.
    pub fn jpeg(&self) -> Arc<Vec<u8>> {
        self.jpeg
            .get_or_init(|| {
                let mut out = Vec::new();
                if let Err(e) = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 85)
                    .encode_image(self.image.as_ref())
                {
                    tracing::warn!("cannot encode frame {} as JPEG: {e}", self.seq);
                }
                Arc::new(out)
            })
            .clone()
    }
}

/// The current time as unix seconds, on the runtime's clock
/// ([`crate::clock::unix_now`]).
pub use crate::clock::unix_now;

/// Counters of the ingest, shared by the reader, the decoder and readers of
/// the status.
#[derive(Debug, Default)]
pub struct Counters {
    /// Whole parts (JPEG candidates) read from the network.
    pub received: AtomicU64,
    /// Parts decoded into frames.
    pub decoded: AtomicU64,
    /// Parts replaced in the raw slot before the decoder took them.
    pub dropped_undecoded: AtomicU64,
    /// Frames replaced in the frame slot before the consumer took them.
    pub dropped_unconsumed: AtomicU64,
    /// Frames the consumer took.
    pub consumed: AtomicU64,
    /// Bad data: malformed parts, truncated or undecodable JPEGs.
    pub bad: AtomicU64,
    /// Connections (re)opened.
    pub connects: AtomicU64,
    /// Connection or request failures.
    pub errors: AtomicU64,
    /// Bytes read from the network.
    pub bytes: AtomicU64,
    /// H.264 access units not decoded: before the stream's first IDR
    /// picture or recovery point, after a queue overflow, or (with
    /// `[video] conceal = false`) after a lost packet, until the next sync
    /// point; and access units the decoder could not decode at all.
    pub skipped: AtomicU64,
    /// H.264 frames decoded with damaged rows (a lost packet's slices, or
    /// rows predicted from them): given to SLAM with those rows masked.
    pub damaged: AtomicU64,
    /// Of those, frames whose every row is damaged.
    pub fully_damaged: AtomicU64,
    /// Damaged rows summed over the decoded H.264 frames.
    pub masked_rows: AtomicU64,
    /// Rows summed over the decoded H.264 frames.
    pub rows: AtomicU64,
    /// RTP packets lost (sequence-number gaps, after retransmissions).
    pub lost_packets: AtomicU64,
    /// RTP packets asked for again by NACK (RTP over UDP).
    pub retransmit_asked: AtomicU64,
    /// Of those, packets whose retransmission arrived in time.
    pub retransmit_recovered: AtomicU64,
    /// Time from noticing a gap to its retransmission's arrival, summed
    /// over the recovered packets, microseconds.
    pub retransmit_wait_us: AtomicU64,
    /// Key frames asked for (PLI) after a packet was lost for good.
    pub key_frame_requests: AtomicU64,
    /// H.264 access units dropped because the decoder fell behind the
    /// stream (the decoder then resumes at the next sync point).
    pub late: AtomicU64,
    /// Frames refused (a resolution other than the stream's first).
    pub refused: AtomicU64,
    /// RTCP sender reports taken: capture times then follow the sender's
    /// own clock instead of arrival times.
    pub sender_reports: AtomicU64,
}

/// A copy of the counters at one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct CountersSnapshot {
    /// See [`Counters::received`].
    pub received: u64,
    /// See [`Counters::decoded`].
    pub decoded: u64,
    /// Parts and frames dropped because a newer one arrived first.
    pub dropped: u64,
    /// See [`Counters::dropped_undecoded`].
    pub dropped_undecoded: u64,
    /// See [`Counters::dropped_unconsumed`].
    pub dropped_unconsumed: u64,
    /// See [`Counters::consumed`].
    pub consumed: u64,
    /// See [`Counters::bad`].
    pub bad: u64,
    /// See [`Counters::connects`].
    pub connects: u64,
    /// See [`Counters::errors`].
    pub errors: u64,
    /// See [`Counters::bytes`].
    pub bytes: u64,
    /// See [`Counters::skipped`].
    pub skipped: u64,
    /// See [`Counters::damaged`].
    pub damaged: u64,
    /// See [`Counters::fully_damaged`].
    pub fully_damaged: u64,
    /// Share of the decoded H.264 rows that were damaged (masked for SLAM),
    /// 0 to 1.
    pub masked_share: f64,
    /// See [`Counters::lost_packets`].
    pub lost_packets: u64,
    /// See [`Counters::retransmit_asked`].
    pub retransmit_asked: u64,
    /// See [`Counters::retransmit_recovered`].
    pub retransmit_recovered: u64,
    /// Mean time from noticing a gap to its retransmission, ms (0 when
    /// none was recovered).
    pub retransmit_wait_ms: f64,
    /// See [`Counters::key_frame_requests`].
    pub key_frame_requests: u64,
    /// See [`Counters::late`].
    pub late: u64,
    /// See [`Counters::refused`].
    pub refused: u64,
    /// See [`Counters::sender_reports`].
    pub sender_reports: u64,
}

impl Counters {
    /// Read all counters.
    pub fn snapshot(&self) -> CountersSnapshot {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let du = l(&self.dropped_undecoded);
        let dc = l(&self.dropped_unconsumed);
        CountersSnapshot {
            received: l(&self.received),
            decoded: l(&self.decoded),
            dropped: du + dc,
            dropped_undecoded: du,
            dropped_unconsumed: dc,
            consumed: l(&self.consumed),
            bad: l(&self.bad),
            connects: l(&self.connects),
            errors: l(&self.errors),
            bytes: l(&self.bytes),
            skipped: l(&self.skipped),
            damaged: l(&self.damaged),
            fully_damaged: l(&self.fully_damaged),
            masked_share: match l(&self.rows) {
                0 => 0.0,
                rows => l(&self.masked_rows) as f64 / rows as f64,
            },
            lost_packets: l(&self.lost_packets),
            retransmit_asked: l(&self.retransmit_asked),
            retransmit_recovered: l(&self.retransmit_recovered),
            retransmit_wait_ms: match l(&self.retransmit_recovered) {
                0 => 0.0,
                n => l(&self.retransmit_wait_us) as f64 / n as f64 / 1000.0,
            },
            key_frame_requests: l(&self.key_frame_requests),
            late: l(&self.late),
            refused: l(&self.refused),
            sender_reports: l(&self.sender_reports),
        }
    }

    pub(crate) fn inc(a: &AtomicU64) {
        a.fetch_add(1, Ordering::Relaxed);
    }

    pub(crate) fn add(a: &AtomicU64, n: u64) {
        a.fetch_add(n, Ordering::Relaxed);
    }
}

/// What the video source is, for the status and the log.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SourceInfo {
    /// `mjpeg`, `snapshot`, `rtsp` or `rtp`.
    pub kind: String,
    /// The URL with any password removed.
    pub url: String,
    /// `jpeg` or `h264` once known.
    pub codec: Option<String>,
    /// RTSP transport (`tcp` or `udp`).
    pub transport: Option<String>,
    /// The stream's resolution once a frame was decoded.
    pub width: Option<u32>,
    /// See `width`.
    pub height: Option<u32>,
    /// Whether the source is connected (RTSP playing, UDP packets arriving,
    /// HTTP stream open).
    pub connected: bool,
    /// The last error, as the operator should read it.
    pub last_error: Option<String>,
}

/// Bytes per second over a sliding window.
#[derive(Debug)]
pub struct ByteRate {
    window: Duration,
    samples: Mutex<VecDeque<(Instant, u64)>>,
}

impl ByteRate {
    /// A meter over `window`.
    pub fn new(window: Duration) -> Self {
        Self {
            window,
            samples: Mutex::new(VecDeque::new()),
        }
    }

    /// Record `n` bytes arriving now.
    pub fn add(&self, n: u64) {
        let now = Instant::now();
        let mut s = self.samples.lock().unwrap_or_else(|e| e.into_inner());
        s.push_back((now, n));
        while s
            .front()
            .is_some_and(|f| now.duration_since(f.0) > self.window)
        {
            s.pop_front();
        }
    }

    /// Bits per second over the window (0 with fewer than two samples).
    pub fn bits_per_second(&self) -> f64 {
        let now = Instant::now();
        let mut s = self.samples.lock().unwrap_or_else(|e| e.into_inner());
        while s
            .front()
            .is_some_and(|f| now.duration_since(f.0) > self.window)
        {
            s.pop_front();
        }
        match (s.front(), s.back()) {
            (Some(a), Some(b)) if s.len() >= 2 => {
                let span = b.0.duration_since(a.0).as_secs_f64();
                // The first sample's bytes arrived before the span began.
                let bytes: u64 = s.iter().skip(1).map(|x| x.1).sum();
                if span > 0.0 {
                    bytes as f64 * 8.0 / span
                } else {
                    0.0
                }
            }
            _ => 0.0,
        }
    }
}

/// Frames per second over a sliding window.
#[derive(Debug)]
pub struct RateMeter {
    window: Duration,
    times: Mutex<VecDeque<Instant>>,
}

impl RateMeter {
    /// A meter over `window`.
    pub fn new(window: Duration) -> Self {
        Self {
            window,
            times: Mutex::new(VecDeque::new()),
        }
    }

    /// Record one event now.
    pub fn tick(&self) {
        let now = Instant::now();
        let mut t = self.times.lock().unwrap_or_else(|e| e.into_inner());
        t.push_back(now);
        while t
            .front()
            .is_some_and(|f| now.duration_since(*f) > self.window)
        {
            t.pop_front();
        }
    }

    /// Events per second over the window (0 with fewer than two events).
    pub fn rate(&self) -> f64 {
        let now = Instant::now();
        let mut t = self.times.lock().unwrap_or_else(|e| e.into_inner());
        while t
            .front()
            .is_some_and(|f| now.duration_since(*f) > self.window)
        {
            t.pop_front();
        }
        match (t.front(), t.back()) {
            (Some(a), Some(b)) if t.len() >= 2 => {
                let span = b.duration_since(*a).as_secs_f64();
                if span > 0.0 {
                    (t.len() - 1) as f64 / span
                } else {
                    0.0
                }
            }
            _ => 0.0,
        }
    }
}

/// What the link's loss leaves SLAM over a sliding window: the frames
/// given to it, with the share of each one's rows masked, against the
/// frames lost to it (not decoded: waiting for a sync point after a lost
/// packet, or undecodable). Frames dropped because a newer one arrived
/// first are not the link's doing and are not counted.
#[derive(Debug)]
pub struct LinkWindow {
    window: Duration,
    /// (when, masked share of a frame given; None for a frame lost).
    events: Mutex<VecDeque<(Instant, Option<f64>)>>,
}

/// [`LinkWindow`]'s sliding window.
pub const LINK_WINDOW: Duration = Duration::from_secs(10);

/// A frame with more than this share of its rows masked cannot become a
/// keyframe (SLAM's `max_masked_share` default): it is not counted usable.
pub const LINK_MAX_MASKED_SHARE: f64 = 0.25;

/// Below this share of usable frames the link makes shots unreliable: the
/// video-loss goal is 70 % of the frames reaching SLAM at 5 % packet loss,
/// with tracking holding.
pub const LINK_MIN_USABLE_SHARE: f64 = 0.7;

/// Fewest frames in the window for a verdict (a stream just started, or
/// stalled, says nothing about its loss).
pub const LINK_MIN_FRAMES: u64 = 10;

/// The link's effect on SLAM over the last [`LINK_WINDOW`]
/// ([`LinkWindow::report`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LinkQuality {
    /// The window, seconds.
    pub window_s: f64,
    /// Frames in it: given to SLAM or lost to it.
    pub frames: u64,
    /// Share of them given to SLAM with at most [`LINK_MAX_MASKED_SHARE`]
    /// of their rows masked (1 with no frames).
    pub usable_share: f64,
    /// Mean share of masked rows over the frames given to SLAM (0 to 1).
    pub masked_share: f64,
    /// True when the window holds [`LINK_MIN_FRAMES`] or more and fewer
    /// than [`LINK_MIN_USABLE_SHARE`] of them are usable: the map cannot
    /// grow or hold on such a link, and shots localised or refined over it
    /// are unreliable.
    pub unreliable: bool,
}

impl LinkWindow {
    /// A window of `window`.
    pub fn new(window: Duration) -> Self {
        Self {
            window,
            events: Mutex::new(VecDeque::new()),
        }
    }

    /// A frame given to SLAM with `masked_share` of its rows masked.
    pub fn given(&self, masked_share: f64) {
        self.record(Instant::now(), Some(masked_share));
    }

    /// A frame lost to SLAM.
    pub fn lost(&self) {
        self.record(Instant::now(), None);
    }

    /// The window's figures now.
    pub fn report(&self) -> LinkQuality {
        self.report_at(Instant::now())
    }

    fn record(&self, at: Instant, event: Option<f64>) {
        let mut e = self.events.lock().unwrap_or_else(|e| e.into_inner());
        e.push_back((at, event));
        Self::expire(&mut e, at, self.window);
    }

    fn expire(e: &mut VecDeque<(Instant, Option<f64>)>, now: Instant, window: Duration) {
        while e
            .front()
            .is_some_and(|(t, _)| now.saturating_duration_since(*t) > window)
        {
            e.pop_front();
        }
    }

    fn report_at(&self, now: Instant) -> LinkQuality {
        let mut e = self.events.lock().unwrap_or_else(|e| e.into_inner());
        Self::expire(&mut e, now, self.window);
        let frames = e.len() as u64;
        let (mut given, mut usable, mut masked) = (0u64, 0u64, 0.0);
        for m in e.iter().filter_map(|(_, m)| *m) {
            given += 1;
            usable += u64::from(m <= LINK_MAX_MASKED_SHARE);
            masked += m;
        }
        let usable_share = if frames == 0 {
            1.0
        } else {
            usable as f64 / frames as f64
        };
        let masked_share = if given == 0 {
            0.0
        } else {
            masked / given as f64
        };
        LinkQuality {
            window_s: self.window.as_secs_f64(),
            frames,
            usable_share,
            masked_share,
            unreliable: frames >= LINK_MIN_FRAMES && usable_share < LINK_MIN_USABLE_SHARE,
        }
    }
}

/// The shared state of one ingest pipeline: reader -> raw slot -> decoder
/// -> frame slot (+ a watch for async observers such as the API).
#[derive(Debug)]
pub struct Ingest {
    /// The counters.
    pub counters: Counters,
    /// Whole JPEGs waiting for the decoder.
    pub raw: Latest<RawPart>,
    /// Decoded frames waiting for the consumer (SLAM).
    pub frames: Latest<Arc<Frame>>,
    /// Received parts per second.
    pub received_rate: RateMeter,
    /// Decoded frames per second.
    pub decoded_rate: RateMeter,
    /// Consumed frames per second.
    pub consumed_rate: RateMeter,
    /// Received video bytes per second.
    pub byte_rate: ByteRate,
    /// What the link's loss leaves SLAM, over the last [`LINK_WINDOW`].
    pub link: LinkWindow,
    /// What the source is (set by the reader).
    pub source: Mutex<SourceInfo>,
    /// Decimation of JPEG frames before SLAM (`[video] downscale`; 1: none).
    pub jpeg_downscale: std::sync::atomic::AtomicU32,
    observers: watch::Sender<Option<Arc<Frame>>>,
}

impl Default for Ingest {
    fn default() -> Self {
        Self::new()
    }
}

impl Ingest {
    /// A fresh pipeline state.
    pub fn new() -> Self {
        let w = Duration::from_secs(2);
        Self {
            counters: Counters::default(),
            raw: Latest::new(),
            frames: Latest::new(),
            received_rate: RateMeter::new(w),
            decoded_rate: RateMeter::new(w),
            consumed_rate: RateMeter::new(w),
            byte_rate: ByteRate::new(w),
            link: LinkWindow::new(LINK_WINDOW),
            source: Mutex::new(SourceInfo::default()),
            jpeg_downscale: std::sync::atomic::AtomicU32::new(1),
            observers: watch::channel(None).0,
        }
    }

    /// Hand a whole JPEG to the decoder (never blocks on it).
    pub fn push_raw(&self, part: RawPart) {
        Counters::inc(&self.counters.received);
        self.received_rate.tick();
        self.byte_rate.add(part.jpeg.len() as u64);
        if self.raw.put(part) {
            Counters::inc(&self.counters.dropped_undecoded);
        }
    }

    /// Take the newest decoded frame not taken before, waiting up to
    /// `timeout`. For the one consumer (SLAM).
    pub fn take_frame(&self, timeout: Duration) -> Result<Option<Arc<Frame>>, Closed> {
        let f = self.frames.take_fresh(timeout)?;
        if f.is_some() {
            Counters::inc(&self.counters.consumed);
            self.consumed_rate.tick();
        }
        Ok(f)
    }

    /// The newest decoded frame (for observers; does not consume it).
    pub fn latest(&self) -> Option<Arc<Frame>> {
        self.frames.peek()
    }

    /// A receiver that sees every new decoded frame (newest wins).
    pub fn subscribe(&self) -> watch::Receiver<Option<Arc<Frame>>> {
        self.observers.subscribe()
    }

    /// Change the source description.
    pub fn update_source(&self, f: impl FnOnce(&mut SourceInfo)) {
        f(&mut self.source.lock().unwrap_or_else(|e| e.into_inner()));
    }

    /// A copy of the source description.
    pub fn source_info(&self) -> SourceInfo {
        self.source
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Publish a decoded frame to SLAM and the observers.
    pub fn publish(&self, frame: Arc<Frame>) {
        Counters::inc(&self.counters.decoded);
        self.decoded_rate.tick();
        self.link.given(frame.masked_share());
        if self.frames.put(frame.clone()) {
            Counters::inc(&self.counters.dropped_unconsumed);
        }
        self.observers.send_replace(Some(frame));
    }

    /// Close both slots: the decoder and the consumer stop.
    pub fn close(&self) {
        self.raw.close();
        self.frames.close();
    }

    /// Decode one part and publish it. Returns false for bad data.
    pub fn decode_and_publish(&self, part: &RawPart, seq: u64) -> bool {
        match image::load_from_memory_with_format(&part.jpeg, image::ImageFormat::Jpeg) {
            Ok(img) => {
                let frame = Arc::new(Frame {
                    seq,
                    capture_time: part.capture_time,
                    received: part.received,
                    received_unix: part.received_unix,
                    damage: None,
                    image: Arc::new({
                        let grey = img.to_luma8();
                        match self.jpeg_downscale.load(Ordering::Relaxed) {
                            f if f > 1 => downscale(&grey, f),
                            _ => grey,
                        }
                    }),
                    jpeg: OnceLock::from(part.jpeg.clone()),
                    jpeg_received: true,
                });
                let (w, h) = (frame.image.width(), frame.image.height());
                self.update_source(|s| {
                    s.width = Some(w);
                    s.height = Some(h);
                    s.connected = true;
                });
                self.publish(frame);
                true
            }
            Err(e) => {
                tracing::debug!("undecodable JPEG ({} bytes): {e}", part.jpeg.len());
                Counters::inc(&self.counters.bad);
                self.link.lost();
                false
            }
        }
    }

    /// Start the decode thread: it decodes the newest raw part until the
    /// raw slot is closed.
    pub fn spawn_decoder(self: &Arc<Self>) -> std::io::Result<std::thread::JoinHandle<()>> {
        let me = Arc::clone(self);
        // The runtime's clock on this thread too (simulated when paused).
        let rt = tokio::runtime::Handle::try_current().ok();
        std::thread::Builder::new()
            .name("jpeg-decode".into())
            .spawn(move || {
                let _rt = rt.as_ref().map(|h| h.enter());
                let mut seq = 0u64;
                loop {
                    match me.raw.take_fresh(Duration::from_millis(500)) {
                        Ok(Some(part)) => {
                            if me.decode_and_publish(&part, seq) {
                                seq += 1;
                            }
                        }
                        Ok(None) => {}
                        Err(Closed) => break,
                    }
                }
            })
    }
}

/// Average `img` over `f`x`f` blocks (integer decimation; the intrinsics
/// scale by `1/f` with the principal point at `(c + 0.5) / f - 0.5`).
pub fn downscale(img: &GrayImage, f: u32) -> GrayImage {
    if f <= 1 {
        return img.clone();
    }
    let (w, h) = (img.width() / f, img.height() / f);
    let src = img.as_raw();
    let sw = img.width() as usize;
    let fu = f as usize;
    let area = (fu * fu) as u32;
    let mut out = Vec::with_capacity(w as usize * h as usize);
    for y in 0..h as usize {
        for x in 0..w as usize {
            let mut sum = 0u32;
            for dy in 0..fu {
                let row = (y * fu + dy) * sw + x * fu;
                for &p in &src[row..row + fu] {
                    sum += u32::from(p);
                }
            }
            out.push(((sum + area / 2) / area) as u8);
        }
    }
    GrayImage::from_raw(w, h, out).unwrap_or_else(|| GrayImage::new(w, h))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_link_window_counts_usable_frames_and_says_when_too_few() {
        let w = LinkWindow::new(Duration::from_secs(10));
        let t0 = Instant::now();
        // Nothing yet: no verdict.
        let q = w.report_at(t0);
        assert_eq!((q.frames, q.usable_share, q.unreliable), (0, 1.0, false));
        // 8 intact, 2 with a tenth masked, 2 half masked, 3 lost: 10 of
        // 15 usable (the half-masked ones cannot become keyframes).
        let at = |k: u64| t0 + Duration::from_millis(100 * k);
        let mut k = 0;
        for masked in [0.0; 8].into_iter().chain([0.1, 0.1, 0.5, 0.5]) {
            w.record(at(k), Some(masked));
            k += 1;
        }
        for _ in 0..3 {
            w.record(at(k), None);
            k += 1;
        }
        let q = w.report_at(at(k));
        assert_eq!(q.frames, 15);
        assert!((q.usable_share - 10.0 / 15.0).abs() < 1e-12, "{q:?}");
        assert!((q.masked_share - 1.2 / 12.0).abs() < 1e-12, "{q:?}");
        assert!(q.unreliable, "10 of 15 is under 70 %");
        // Ten seconds on, the window holds only what came since: 10
        // intact frames, a reliable link again.
        let later = at(k) + Duration::from_secs(11);
        for j in 0..10 {
            w.record(later + Duration::from_millis(j), Some(0.0));
        }
        let q = w.report_at(later + Duration::from_millis(10));
        assert_eq!((q.frames, q.usable_share, q.unreliable), (10, 1.0, false));
        // Under the fewest frames for a verdict: all lost says nothing.
        let w = LinkWindow::new(Duration::from_secs(10));
        for j in 0..(LINK_MIN_FRAMES - 1) {
            w.record(t0 + Duration::from_millis(j), None);
        }
        let q = w.report_at(t0 + Duration::from_millis(20));
        assert_eq!((q.usable_share, q.unreliable), (0.0, false));
        w.record(t0 + Duration::from_millis(21), None);
        assert!(w.report_at(t0 + Duration::from_millis(22)).unreliable);
    }

    #[test]
    fn latest_keeps_newest_and_counts_replaced() {
        let s = Latest::new();
        assert!(!s.put(1));
        assert!(s.put(2));
        assert_eq!(s.take_fresh(Duration::ZERO), Ok(Some(2)));
        assert_eq!(s.take_fresh(Duration::from_millis(10)), Ok(None));
        assert!(!s.put(3));
        s.close();
        assert_eq!(s.take_fresh(Duration::ZERO), Ok(Some(3)));
        assert_eq!(s.take_fresh(Duration::ZERO), Err(Closed));
        assert_eq!(s.peek(), Some(3));
    }

    #[test]
    fn take_fresh_wakes_on_put_from_another_thread() {
        let s = Arc::new(Latest::new());
        let s2 = s.clone();
        let t = std::thread::spawn(move || s2.put(7u32));
        // No deadline to hide behind: the wait ends only when the put wakes
        // it (or finds the value already there, if the other thread ran
        // first); a lost wake-up hangs here instead of passing late.
        assert_eq!(s.take_fresh(Duration::from_secs(86_400)), Ok(Some(7)));
        t.join().unwrap();
    }

    #[test]
    fn jpeg_frames_are_decimated_as_configured() {
        let img = GrayImage::from_fn(64, 48, |x, y| image::Luma([(x * 4 + y) as u8]));
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
            .encode_image(&img)
            .unwrap();
        let ing = Ingest::new();
        ing.jpeg_downscale.store(2, Ordering::Relaxed);
        let part = RawPart {
            jpeg: Arc::new(jpeg),
            capture_time: None,
            received: Instant::now(),
            received_unix: unix_now(),
        };
        assert!(ing.decode_and_publish(&part, 0));
        let f = ing.latest().unwrap();
        assert_eq!(f.image.dimensions(), (32, 24));
        // The re-served JPEG is the one received, at full size.
        assert_eq!(f.jpeg().len(), part.jpeg.len());
        let s = ing.source_info();
        assert_eq!((s.width, s.height), (Some(32), Some(24)));
    }

    #[test]
    fn rate_meter_measures_rate() {
        let m = RateMeter::new(Duration::from_secs(10));
        assert_eq!(m.rate(), 0.0);
        for _ in 0..11 {
            m.tick();
            std::thread::sleep(Duration::from_millis(10));
        }
        let r = m.rate();
        // 10 intervals of >= 10 ms: at most 100/s, and sleeping is not
        // slower than 4x on a loaded machine.
        assert!(r > 25.0 && r <= 100.5, "{r}");
    }
}
