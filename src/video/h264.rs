//! H.264: NAL-unit helpers, the access units the reader hands over and their
//! short queue, the OpenH264 decoder giving the luma plane, and a grey-picture
//! encoder for benches and tests.
//!
//! The network reader (RTSP or raw RTP) assembles whole access units and
//! hands them to a short [`AuQueue`]; it never waits on the decoder. The
//! decode thread ([`crate::video::decode_loop`]) decodes every access unit
//! in order (an H.264 picture needs the pictures before it), copies the
//! decoded luma plane into a grey image (no RGB conversion) and publishes it
//! to the ingest's newest-frame slot, which SLAM takes from.
//!
//! After a lost packet the decoder goes on with OpenH264's error
//! concealment, and [`crate::video::damage`] works out which rows of each
//! picture the loss reached (the lost slices' rows, and through the
//! reference chain the rows predicted from them): the frame reaches SLAM
//! with those rows marked ([`crate::video::live::Frame::damage`]), and SLAM
//! takes no feature from them. With
//! [`DecodeParams::conceal`](crate::video::decode_loop::DecodeParams::conceal)
//! off (and after a queue overflow: the decoder fell behind), the decoder
//! instead skips access units until the next IDR picture or SEI recovery
//! point.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

use image::GrayImage;

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
/// NAL unit type: access unit delimiter.
pub const NAL_AUD: u8 = 9;
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
    // Emulation prevention bytes removed first.
    let rbsp = crate::video::damage::rbsp(nal);
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
    /// Where among the NAL units packets went missing (see
    /// [`crate::video::rtp::DepacketizedAu::gaps`]); empty with `lost > 0`
    /// when the reader cannot tell (the whole picture counts as damaged).
    pub gaps: Vec<u32>,
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
    conceal: bool,
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
        Ok(Self {
            dec,
            conceal: false,
        })
    }

    /// A decoder with OpenH264's error concealment on (lost macroblocks
    /// copied from the previous picture, slice by slice): a damaged access
    /// unit still gives a picture. Which rows of it to trust is
    /// [`crate::video::damage`]'s answer, not the decoder's.
    pub fn concealing() -> Result<Self, H264Error> {
        let mut d = Self::new()?;
        let mut idc: openh264_sys2::ERROR_CON_IDC = openh264_sys2::ERROR_CON_SLICE_COPY_CROSS_IDR;
        // SAFETY: the decoder is initialised; SetOption reads one int
        // through the pointer, which lives across the call.
        let rc = unsafe {
            d.dec.raw_api().set_option(
                openh264_sys2::DECODER_OPTION_ERROR_CON_IDC,
                std::ptr::addr_of_mut!(idc).cast(),
            )
        };
        if rc != 0 {
            return Err(H264Error::DecoderInit {
                reason: format!("OpenH264 refused error concealment (code {rc})"),
            });
        }
        d.conceal = true;
        Ok(d)
    }

    /// Decode through OpenH264's raw call: a concealed picture comes with a
    /// non-zero state (`dsDataErrorConcealed`, `dsRefLost`, ...), which
    /// is not an error here when a picture came out.
    fn decode_concealing(&mut self, annexb: &[u8]) -> Result<Option<GrayImage>, H264Error> {
        Ok(self.decode_tagged(annexb, 0)?.pop().map(|p| p.0))
    }

    /// Decode one Annex B access unit tagged `tag`; the pictures that come
    /// out (usually one) carry the tag of the access unit each was coded
    /// in. Concealing decoders only; a plain one gives back `tag` with its
    /// picture.
    ///
    /// This is OpenH264's `DecodeFrameNoDelay` made by hand (the unit, then
    /// an empty call that ends it), keeping a picture the first call gave:
    /// the second call clears the output of the first, which loses the
    /// concealed picture an access unit delimiter ends (see
    /// [`DecodeLoop::step`]).
    pub fn decode_tagged(
        &mut self,
        annexb: &[u8],
        tag: u64,
    ) -> Result<Vec<(GrayImage, u64)>, H264Error> {
        if !self.conceal {
            return Ok(self
                .decode(annexb)?
                .map(|img| (img, tag))
                .into_iter()
                .collect());
        }
        let len = i32::try_from(annexb.len()).map_err(|_| H264Error::Broken {
            reason: format!("access unit of {} bytes", annexb.len()),
        })?;
        let mut out = Vec::new();
        let mut state = 0;
        for last in [false, true] {
            let mut dst = [std::ptr::null_mut::<u8>(); 3];
            let mut info = openh264_sys2::SBufferInfo {
                uiInBsTimeStamp: tag,
                ..Default::default()
            };
            let (src, n) = if last {
                (std::ptr::null(), 0)
            } else {
                (annexb.as_ptr(), len)
            };
            // SAFETY: `src` is valid for `n` bytes during the call (or
            // null with 0: the end of the unit); `dst` and `info` are the
            // out-parameters OpenH264 fills.
            state |= unsafe {
                self.dec
                    .raw_api()
                    .decode_frame2(src, n, dst.as_mut_ptr(), &raw mut info)
            };
            if last && info.iBufferStatus == 0 && out.is_empty() {
                // A picture held back (reordering): flush it as the safe
                // wrapper does after each unit.
                let mut remaining: i32 = 0;
                // SAFETY: GetOption writes one int through the pointer.
                let rc = unsafe {
                    self.dec.raw_api().get_option(
                        openh264_sys2::DECODER_OPTION_NUM_OF_FRAMES_REMAINING_IN_BUFFER,
                        std::ptr::addr_of_mut!(remaining).cast(),
                    )
                };
                if rc == 0 && remaining > 0 {
                    info = openh264_sys2::SBufferInfo::default();
                    dst = [std::ptr::null_mut::<u8>(); 3];
                    // SAFETY: out-parameters as above.
                    state |= unsafe {
                        self.dec
                            .raw_api()
                            .flush_frame(dst.as_mut_ptr(), &raw mut info)
                    };
                }
            }
            if info.iBufferStatus == 1 && !dst[0].is_null() {
                // Copied at once: the next call reuses the buffers.
                out.push((Self::copy_luma(&dst, &info)?, info.uiOutYuvTimeStamp));
            }
        }
        if out.is_empty() && state != 0 {
            return Err(H264Error::Broken {
                reason: format!("OpenH264 decoding state {state:#x}, no picture"),
            });
        }
        Ok(out)
    }

    /// The luma plane of a picture OpenH264 returned, as a grey image.
    fn copy_luma(
        dst: &[*mut u8; 3],
        info: &openh264_sys2::SBufferInfo,
    ) -> Result<GrayImage, H264Error> {
        // SAFETY: OpenH264 filled the system buffer's description for the
        // picture it returned.
        let sb = unsafe { info.UsrData.sSystemBuffer };
        let bad = || H264Error::BadPicture {
            width: sb.iWidth.max(0) as usize,
            height: sb.iHeight.max(0) as usize,
            stride: sb.iStride[0].max(0) as usize,
            len: 0,
        };
        let (w, h, stride) = (
            usize::try_from(sb.iWidth).map_err(|_| bad())?,
            usize::try_from(sb.iHeight).map_err(|_| bad())?,
            usize::try_from(sb.iStride[0]).map_err(|_| bad())?,
        );
        if w == 0 || h == 0 || stride < w || dst[0].is_null() {
            return Err(bad());
        }
        // SAFETY: the luma plane of the returned picture holds `h` rows of
        // `stride` bytes, valid until the next call into the decoder.
        let y = unsafe { std::slice::from_raw_parts(dst[0], stride * (h - 1) + w) };
        let mut luma = Vec::with_capacity(w * h);
        for row in 0..h {
            luma.extend_from_slice(&y[row * stride..row * stride + w]);
        }
        let (wu, hu) = (
            u32::try_from(w).map_err(|_| bad())?,
            u32::try_from(h).map_err(|_| bad())?,
        );
        GrayImage::from_raw(wu, hu, luma).ok_or_else(bad)
    }

    /// Decode one Annex B access unit; `Ok(None)` when it held no picture
    /// (parameter sets only).
    pub fn decode(&mut self, annexb: &[u8]) -> Result<Option<GrayImage>, H264Error> {
        use openh264::formats::YUVSource;
        if self.conceal {
            return self.decode_concealing(annexb);
        }

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
        Self::with_slices(width, height, fps, bitrate_bps, idr_period, None)
    }

    /// [`GrayEncoder::new`] with slices of at most `max_slice_bytes` bytes
    /// (`None`: one slice per picture), as senders for lossy links cut
    /// them to fit one packet each.
    pub fn with_slices(
        width: u32,
        height: u32,
        fps: f32,
        bitrate_bps: u32,
        idr_period: u32,
        max_slice_bytes: Option<u32>,
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
        let cfg = match max_slice_bytes {
            Some(n) => cfg.max_slice_len(n),
            None => cfg,
        };
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
