//! H.264: NAL-unit helpers, the OpenH264 decoder giving the luma plane, and
//! the decode thread.
//!
//! The network reader (RTSP or raw RTP) assembles whole access units and
//! hands them to a short [`AuQueue`]; it never waits on the decoder. The
//! decode thread decodes every access unit in order (an H.264 picture needs
//! the pictures before it), copies the decoded luma plane into a grey image
//! (no RGB conversion) and publishes it to the ingest's newest-frame slot,
//! which SLAM takes from.
//!
//! After a lost packet, a broken slice, or a queue overflow (the decoder
//! fell behind), the decoder skips access units until the next IDR picture
//! or SEI recovery point: the pictures in between would be predicted from
//! a damaged reference and reach SLAM smeared. OpenH264's error concealment
//! stays off for the same reason.

use std::collections::VecDeque;
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use image::GrayImage;

use crate::video::live::{Counters, Frame, Ingest};

/// Errors of the H.264 path.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum H264Error {
    /// The stream is in a codec this build cannot decode.
    #[error(
        "the camera sends {codec} video, which shotpilot cannot decode: set the camera's stream to H.264 (AVC)"
    )]
    UnsupportedCodec {
        /// The codec's name as the source gave it.
        codec: String,
    },
    /// The decoder could not be created.
    #[error("cannot start the H.264 decoder: {reason}")]
    DecoderInit {
        /// OpenH264's message.
        reason: String,
    },
    /// An access unit could not be decoded.
    #[error("broken H.264 access unit: {reason}")]
    Broken {
        /// OpenH264's message.
        reason: String,
    },
    /// The decoded picture's planes do not match its size.
    #[error("decoded picture {width}x{height} has a luma plane of {len} bytes (stride {stride})")]
    BadPicture {
        /// Width, pixels.
        width: usize,
        /// Height, pixels.
        height: usize,
        /// Row stride, bytes.
        stride: usize,
        /// Luma plane length, bytes.
        len: usize,
    },
}

/// NAL unit type: coded slice of a non-IDR picture.
pub const NAL_SLICE: u8 = 1;
/// NAL unit type: coded slice of an IDR picture.
pub const NAL_IDR: u8 = 5;
/// NAL unit type: supplemental enhancement information.
pub const NAL_SEI: u8 = 6;
/// NAL unit type: sequence parameter set.
pub const NAL_SPS: u8 = 7;
/// NAL unit type: picture parameter set.
pub const NAL_PPS: u8 = 8;
/// SEI payload type of a recovery point.
const SEI_RECOVERY_POINT: u32 = 6;

/// The type of a NAL unit (its first byte's low five bits); 0 for an empty
/// unit.
pub fn nal_type(nal: &[u8]) -> u8 {
    nal.first().map_or(0, |b| b & 0x1f)
}

/// The NAL units of an Annex B byte stream (start codes `00 00 01` or
/// `00 00 00 01`), without their start codes. Bytes before the first start
/// code are ignored; trailing zero bytes of a unit are trimmed.
pub fn annexb_units(stream: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= stream.len() {
        if stream[i] == 0 && stream[i + 1] == 0 && stream[i + 2] == 1 {
            starts.push(i + 3);
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut out = Vec::with_capacity(starts.len());
    for (k, &s) in starts.iter().enumerate() {
        let mut end = match starts.get(k + 1) {
            Some(&next) => next - 3,
            None => stream.len(),
        };
        while end > s && stream[end - 1] == 0 {
            end -= 1;
        }
        if end > s {
            out.push(&stream[s..end]);
        }
    }
    out
}

/// Append `nal` to `out` as Annex B (4-byte start code).
pub fn push_annexb(out: &mut Vec<u8>, nal: &[u8]) {
    out.extend_from_slice(&[0, 0, 0, 1]);
    out.extend_from_slice(nal);
}

/// Whether the SEI NAL unit carries a recovery point message.
fn sei_has_recovery_point(nal: &[u8]) -> bool {
    // Remove emulation prevention bytes from the RBSP first.
    let mut rbsp = Vec::with_capacity(nal.len());
    let mut zeros = 0;
    for &b in nal.iter().skip(1) {
        if zeros >= 2 && b == 3 {
            zeros = 0;
            continue;
        }
        zeros = if b == 0 { zeros + 1 } else { 0 };
        rbsp.push(b);
    }
    let mut i = 0;
    while i < rbsp.len() && rbsp[i] != 0x80 {
        let mut ty = 0u32;
        while i < rbsp.len() && rbsp[i] == 0xff {
            ty += 255;
            i += 1;
        }
        let Some(&b) = rbsp.get(i) else { return false };
        ty += u32::from(b);
        i += 1;
        let mut size = 0usize;
        while i < rbsp.len() && rbsp[i] == 0xff {
            size += 255;
            i += 1;
        }
        let Some(&b) = rbsp.get(i) else { return false };
        size += usize::from(b);
        i += 1;
        if ty == SEI_RECOVERY_POINT {
            return true;
        }
        i = i.saturating_add(size);
    }
    false
}

/// What an access unit holds, for the skip-to-sync decisions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct AuKind {
    /// It has an IDR slice.
    pub idr: bool,
    /// It has an SEI recovery point.
    pub recovery_point: bool,
    /// It has a sequence parameter set.
    pub sps: bool,
    /// It has a picture parameter set.
    pub pps: bool,
    /// It has a slice of any picture.
    pub slice: bool,
}

impl AuKind {
    /// Classify an Annex B access unit.
    pub fn of(annexb: &[u8]) -> Self {
        let mut k = AuKind::default();
        for nal in annexb_units(annexb) {
            match nal_type(nal) {
                NAL_IDR => {
                    k.idr = true;
                    k.slice = true;
                }
                NAL_SLICE..=4 => k.slice = true,
                NAL_SEI => k.recovery_point |= sei_has_recovery_point(nal),
                NAL_SPS => k.sps = true,
                NAL_PPS => k.pps = true,
                _ => {}
            }
        }
        k
    }

    /// Whether decoding may restart here after a loss.
    pub fn is_sync_point(&self) -> bool {
        self.idr || self.recovery_point
    }
}

/// One whole access unit (one picture's NAL units), Annex B framed.
#[derive(Debug, Clone)]
pub struct AccessUnit {
    /// The NAL units with start codes.
    pub data: Vec<u8>,
    /// Capture time, unix seconds (from RTCP sender reports, else the RTP
    /// clock mapped onto arrival times).
    pub capture_time: Option<f64>,
    /// When its last packet arrived.
    pub received: Instant,
    /// The same instant as unix seconds.
    pub received_unix: f64,
    /// Packets lost since the previous access unit or inside this one: the
    /// picture (or one it is predicted from) is damaged.
    pub lost: u32,
}

#[derive(Debug, Default)]
struct QueueState {
    units: VecDeque<AccessUnit>,
    /// Access units were thrown away since the last one taken.
    gap: bool,
    closed: bool,
}

/// A short queue of access units from the reader to the decode thread.
/// `push` never blocks: when the decoder is `capacity` units behind, the
/// queued units are dropped (counted as late) and the decoder resumes at
/// the next sync point.
#[derive(Debug)]
pub struct AuQueue {
    capacity: usize,
    state: Mutex<QueueState>,
    cv: Condvar,
}

impl AuQueue {
    /// A queue holding at most `capacity` units (at least 1).
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.max(1),
            state: Mutex::new(QueueState::default()),
            cv: Condvar::new(),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, QueueState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Queue `au`; returns how many queued units were dropped to make room.
    pub fn push(&self, au: AccessUnit) -> usize {
        let mut s = self.lock();
        let mut dropped = 0;
        if s.units.len() >= self.capacity {
            dropped = s.units.len();
            s.units.clear();
            s.gap = true;
        }
        s.units.push_back(au);
        drop(s);
        self.cv.notify_one();
        dropped
    }

    /// Wait up to `timeout` for the next unit. The flag tells whether units
    /// were dropped before it. `Err(())` once closed and empty.
    #[allow(clippy::result_unit_err)]
    pub fn pop(&self, timeout: Duration) -> Result<Option<(AccessUnit, bool)>, ()> {
        let deadline = Instant::now() + timeout;
        let mut s = self.lock();
        loop {
            if let Some(au) = s.units.pop_front() {
                let gap = std::mem::take(&mut s.gap);
                return Ok(Some((au, gap)));
            }
            if s.closed {
                return Err(());
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

    /// Close the queue: the decode thread ends once it is empty.
    pub fn close(&self) {
        self.lock().closed = true;
        self.cv.notify_all();
    }
}

/// OpenH264 wrapped to give grey images.
pub struct LumaDecoder {
    dec: openh264::decoder::Decoder,
}

impl std::fmt::Debug for LumaDecoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LumaDecoder")
    }
}

impl LumaDecoder {
    /// A decoder (error concealment off: a damaged picture is an error,
    /// never a smeared image).
    pub fn new() -> Result<Self, H264Error> {
        let dec = openh264::decoder::Decoder::new().map_err(|e| H264Error::DecoderInit {
            reason: e.to_string(),
        })?;
        Ok(Self { dec })
    }

    /// Decode one Annex B access unit; `Ok(None)` when it held no picture
    /// (parameter sets only).
    pub fn decode(&mut self, annexb: &[u8]) -> Result<Option<GrayImage>, H264Error> {
        use openh264::formats::YUVSource;
        let yuv = self.dec.decode(annexb).map_err(|e| H264Error::Broken {
            reason: e.to_string(),
        })?;
        let Some(yuv) = yuv else { return Ok(None) };
        let (w, h) = yuv.dimensions();
        let stride = yuv.strides().0;
        let y = yuv.y();
        if w == 0 || h == 0 || stride < w || y.len() < stride * (h - 1) + w {
            return Err(H264Error::BadPicture {
                width: w,
                height: h,
                stride,
                len: y.len(),
            });
        }
        let mut luma = Vec::with_capacity(w * h);
        for row in 0..h {
            luma.extend_from_slice(&y[row * stride..row * stride + w]);
        }
        let bad = || H264Error::BadPicture {
            width: w,
            height: h,
            stride,
            len: y.len(),
        };
        let (wu, hu) = (
            u32::try_from(w).map_err(|_| bad())?,
            u32::try_from(h).map_err(|_| bad())?,
        );
        GrayImage::from_raw(wu, hu, luma).map(Some).ok_or_else(bad)
    }
}

/// Tunables of the decode thread.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodeParams {
    /// Access units the reader may queue ahead of the decoder.
    pub queue: usize,
    /// Decimate the decoded luma by this integer factor (1: full
    /// resolution) before SLAM sees it.
    pub downscale: u32,
}

impl Default for DecodeParams {
    fn default() -> Self {
        Self {
            queue: 8,
            downscale: 1,
        }
    }
}

/// The decode thread's state machine, apart from the thread so tests can
/// drive it: decode in order, skip to a sync point after damage, refuse a
/// changed resolution.
#[derive(Debug)]
pub struct DecodeLoop {
    decoder: LumaDecoder,
    params: DecodeParams,
    waiting_for_sync: bool,
    size: Option<(u32, u32)>,
    seq: u64,
}

/// What one access unit became.
#[derive(Debug, Clone)]
pub enum Decoded {
    /// A picture for SLAM.
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
        Ok(Self {
            decoder: LumaDecoder::new()?,
            params,
            waiting_for_sync: true,
            size: None,
            seq: 0,
        })
    }

    /// Forget the stream (a new connection): wait for a sync point and take
    /// the next resolution as the stream's.
    pub fn reset(&mut self) {
        self.waiting_for_sync = true;
        self.size = None;
    }

    /// Process one access unit; `gap` tells that units were dropped before it.
    pub fn step(&mut self, au: &AccessUnit, gap: bool) -> Decoded {
        let kind = AuKind::of(&au.data);
        if au.lost > 0 || gap {
            self.waiting_for_sync = true;
        }
        if self.waiting_for_sync {
            if !kind.is_sync_point() {
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
        }
        match self.decoder.decode(&au.data) {
            Ok(Some(img)) => {
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
                let frame = Frame::from_image(
                    self.seq,
                    au.capture_time,
                    au.received,
                    au.received_unix,
                    Arc::new(img),
                );
                self.seq += 1;
                Decoded::Frame(Arc::new(frame))
            }
            Ok(None) => Decoded::NoPicture,
            Err(e) => {
                self.waiting_for_sync = true;
                Decoded::Broken(e)
            }
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
                        ingest.update_source(|s| {
                            s.width = Some(w);
                            s.height = Some(h);
                        });
                        ingest.publish(f);
                    }
                    Decoded::Skipped => Counters::inc(&c.skipped),
                    Decoded::NoPicture => {}
                    Decoded::Broken(e) => {
                        Counters::inc(&c.bad);
                        Counters::inc(&c.skipped);
                        broken_logged += 1;
                        if broken_logged.is_power_of_two() {
                            tracing::warn!(
                                "video: {e}; skipping to the next IDR picture ({broken_logged} so far)"
                            );
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

/// Grey pictures encoded as H.264 by OpenH264 (neutral chroma): what the
/// decode benchmark and the tests of the depacketiser and the decoder feed
/// through the same path a camera's stream takes.
pub struct GrayEncoder {
    enc: openh264::encoder::Encoder,
    width: u32,
    height: u32,
    yuv: Vec<u8>,
}

impl std::fmt::Debug for GrayEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GrayEncoder({}x{})", self.width, self.height)
    }
}

impl GrayEncoder {
    /// An encoder for `width`x`height` (even) pictures at `fps`, aiming at
    /// `bitrate_bps`, with an IDR picture every `idr_period` pictures.
    pub fn new(
        width: u32,
        height: u32,
        fps: f32,
        bitrate_bps: u32,
        idr_period: u32,
    ) -> Result<Self, H264Error> {
        use openh264::encoder::{
            BitRate, EncoderConfig, FrameRate, IntraFramePeriod, RateControlMode, SpsPpsStrategy,
        };
        let cfg = EncoderConfig::new()
            .bitrate(BitRate::from_bps(bitrate_bps))
            .max_frame_rate(FrameRate::from_hz(fps))
            .rate_control_mode(RateControlMode::Bitrate)
            .skip_frames(false)
            .scene_change_detect(false)
            .sps_pps_strategy(SpsPpsStrategy::ConstantId)
            .intra_frame_period(IntraFramePeriod::from_num_frames(idr_period));
        let enc =
            openh264::encoder::Encoder::with_api_config(openh264::OpenH264API::from_source(), cfg)
                .map_err(|e| H264Error::DecoderInit {
                    reason: e.to_string(),
                })?;
        let (w, h) = (width as usize, height as usize);
        let mut yuv = vec![128u8; w * h + 2 * (w / 2) * (h / 2)];
        yuv[..w * h].fill(0);
        Ok(Self {
            enc,
            width,
            height,
            yuv,
        })
    }

    /// Encode one picture (its size must be the encoder's) into an Annex B
    /// access unit (with SPS and PPS before each IDR picture).
    pub fn encode(&mut self, img: &GrayImage) -> Result<Vec<u8>, H264Error> {
        if (img.width(), img.height()) != (self.width, self.height) {
            return Err(H264Error::BadPicture {
                width: img.width() as usize,
                height: img.height() as usize,
                stride: img.width() as usize,
                len: img.as_raw().len(),
            });
        }
        let n = img.as_raw().len();
        self.yuv[..n].copy_from_slice(img.as_raw());
        let buf = openh264::formats::YUVBuffer::from_vec(
            self.yuv.clone(),
            self.width as usize,
            self.height as usize,
        );
        let bs = self.enc.encode(&buf).map_err(|e| H264Error::Broken {
            reason: e.to_string(),
        })?;
        Ok(bs.to_vec())
    }

    /// The next picture is an IDR picture.
    pub fn force_idr(&mut self) {
        self.enc.force_intra_frame();
    }
}
