//! The simulated camera's H.264 stream: its render encoded with OpenH264
//! and sent as RTP over UDP, the way OpenIPC / wfb-ng links and many gimbal
//! cameras send it (no RTSP: the receiver listens on a port).
//!
//! - **Encoding** ([`H264Encoder`]): the grey render as the luma plane of
//!   an I420 picture (neutral chroma), OpenH264's bitrate rate control,
//!   an IDR picture every [`RtpOutParams::idr_interval_s`] with SPS and PPS
//!   in-band before it (a receiver can join at any IDR).
//! - **Packetisation** ([`Packetizer`], RFC 6184 packetisation mode 1): a
//!   NAL unit that fits in [`RtpOutParams::mtu`] goes in one packet (single
//!   NAL unit packet), a larger one in FU-A fragments; the marker bit is set
//!   on the last packet of each access unit. This is the simulator's own
//!   code, independent of the daemon's depacketiser, so each checks the
//!   other.
//! - **Clock**: the 90 kHz RTP timestamp of a picture is its capture time
//!   (the same unix time the MJPEG stream sends in `X-Timestamp`) on a
//!   clock starting at a random offset; RTCP sender reports (RFC 3550
//!   section 6.4.1, with an SDES CNAME) go to the RTP port + 1 every
//!   [`RtpOutParams::sr_interval_s`], mapping that clock to the wall clock,
//!   so a receiver recovers each picture's capture time exactly.
//! - **Threading** ([`RtpSender`]): encoding and sending run on their own
//!   thread behind a two-picture queue; [`RtpSender::offer`] never blocks
//!   (a picture arriving while the queue is full is dropped and counted).
//! - **Session description** ([`sdp`]): what a receiver needs (`m=video`
//!   port, `c=` address, `rtpmap` H264/90000, `sprop-parameter-sets`).

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::time::{Duration, Instant};

use image::GrayImage;

use crate::clock::unix_now;
use crate::video::VideoError;

/// The RTP clock rate of video, Hz (RFC 6184).
pub const CLOCK_RATE: u32 = 90_000;

/// Seconds between the NTP epoch (1900) and the unix epoch (1970).
const NTP_UNIX_OFFSET_S: f64 = 2_208_988_800.0;

/// The H.264 RTP output's settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RtpOutParams {
    /// Where RTP goes (RTCP goes to the next port).
    pub dest: SocketAddr,
    /// Target bitrate, bits per second. 1.5 Mbit/s: what a SIYI A8 mini
    /// sends at 1280x720, here spent on a 640x480 picture (generous: a
    /// SIYI's bits per pixel at 30 fps would give ~0.25 Mbit/s at 640x480
    /// and 15 fps).
    pub bitrate_bps: u32,
    /// Seconds between IDR pictures (a receiver joins, or recovers from a
    /// loss, at the next one). 1 s: a camera-to-ground link's usual GOP.
    pub idr_interval_s: f64,
    /// Largest RTP packet, bytes (header included); 1200 leaves room for
    /// IP, UDP and a tunnel inside a 1500-byte Ethernet MTU.
    pub mtu: usize,
    /// RTP payload type (dynamic, 96-127).
    pub payload_type: u8,
    /// Seconds between RTCP sender reports.
    pub sr_interval_s: f64,
}

impl Default for RtpOutParams {
    fn default() -> Self {
        Self {
            dest: SocketAddr::from(([127, 0, 0, 1], 5600)),
            bitrate_bps: 1_500_000,
            idr_interval_s: 1.0,
            mtu: 1200,
            payload_type: 96,
            sr_interval_s: 1.0,
        }
    }
}

impl RtpOutParams {
    /// The URI a camera announces for this stream in
    /// VIDEO_STREAM_INFORMATION (`udp://HOST:PORT`: where the ground
    /// station listens).
    pub fn uri(&self) -> String {
        format!("udp://{}", self.dest)
    }

    /// Checks the settings (a reason for the first bad one).
    pub fn check(&self) -> Result<(), (&'static str, &'static str)> {
        if self.dest.port() == 0 || self.dest.port() == u16::MAX {
            return Err(("dest", "port must be in 1-65534 (RTCP uses the next)"));
        }
        if !(50_000..=50_000_000).contains(&self.bitrate_bps) {
            return Err(("bitrate_bps", "must be in 50 kbit/s - 50 Mbit/s"));
        }
        if !(self.idr_interval_s > 0.0 && self.idr_interval_s <= 60.0) {
            return Err(("idr_interval_s", "must be in (0, 60]"));
        }
        if !(100..=65_000).contains(&self.mtu) {
            return Err(("mtu", "must be in 100-65000 bytes"));
        }
        if !(96..=127).contains(&self.payload_type) {
            return Err(("payload_type", "must be dynamic (96-127)"));
        }
        if !(self.sr_interval_s > 0.0 && self.sr_interval_s <= 60.0) {
            return Err(("sr_interval_s", "must be in (0, 60]"));
        }
        Ok(())
    }
}

fn h264_err(what: &str, e: impl std::fmt::Display) -> VideoError {
    VideoError::H264 {
        reason: format!("{what}: {e}"),
    }
}

/// One encoded picture.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EncodedPicture {
    /// Its NAL units, without start codes, in decoding order.
    pub nals: Vec<Vec<u8>>,
    /// Whether it is an IDR picture.
    pub idr: bool,
}

impl EncodedPicture {
    /// The picture as an Annex B byte stream (4-byte start codes).
    pub fn annexb(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.nals.iter().map(|n| n.len() + 4).sum());
        for n in &self.nals {
            out.extend_from_slice(&[0, 0, 0, 1]);
            out.extend_from_slice(n);
        }
        out
    }

    /// Encoded size, bytes (NAL units without start codes).
    pub fn bytes(&self) -> usize {
        self.nals.iter().map(Vec::len).sum()
    }
}

/// Strips an Annex B start code (`00 00 01` or `00 00 00 01`) from the
/// front of a NAL unit as OpenH264 hands it out.
fn strip_start_code(nal: &[u8]) -> &[u8] {
    let zeros = nal.iter().take_while(|&&b| b == 0).count();
    if zeros >= 2 && nal.get(zeros) == Some(&1) {
        &nal[zeros + 1..]
    } else {
        nal
    }
}

/// Grey pictures encoded as H.264 by OpenH264 (the luma plane of an I420
/// picture with neutral chroma).
pub struct H264Encoder {
    enc: openh264::encoder::Encoder,
    width: u32,
    height: u32,
    chroma: Vec<u8>,
}

impl std::fmt::Debug for H264Encoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "H264Encoder({}x{})", self.width, self.height)
    }
}

impl H264Encoder {
    /// An encoder for `width`x`height` pictures (both even) at `fps`,
    /// aiming at `bitrate_bps` with bitrate rate control (no skipped
    /// pictures), an IDR picture every `idr_period` pictures, SPS and PPS
    /// before each.
    pub fn new(
        width: u32,
        height: u32,
        fps: f64,
        bitrate_bps: u32,
        idr_period: u32,
    ) -> Result<Self, VideoError> {
        use openh264::encoder::{
            BitRate, EncoderConfig, FrameRate, IntraFramePeriod, RateControlMode, SpsPpsStrategy,
        };
        if width == 0 || height == 0 || width % 2 == 1 || height % 2 == 1 {
            return Err(VideoError::H264 {
                reason: format!("{width}x{height}: H.264 4:2:0 needs even, non-zero sides"),
            });
        }
        let cfg = EncoderConfig::new()
            .bitrate(BitRate::from_bps(bitrate_bps))
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .rate_control_mode(RateControlMode::Bitrate)
            .skip_frames(false)
            .scene_change_detect(false)
            .sps_pps_strategy(SpsPpsStrategy::ConstantId)
            .num_threads(1)
            .intra_frame_period(IntraFramePeriod::from_num_frames(idr_period.max(1)));
        let enc =
            openh264::encoder::Encoder::with_api_config(openh264::OpenH264API::from_source(), cfg)
                .map_err(|e| h264_err("starting the OpenH264 encoder", e))?;
        let chroma = vec![128u8; (width as usize / 2) * (height as usize / 2)];
        Ok(Self {
            enc,
            width,
            height,
            chroma,
        })
    }

    /// Picture width, pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Picture height, pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Encodes one picture (its size must be the encoder's); `time_ms` is
    /// its time on the stream's clock.
    pub fn encode(&mut self, img: &GrayImage, time_ms: u64) -> Result<EncodedPicture, VideoError> {
        if img.dimensions() != (self.width, self.height) {
            return Err(VideoError::H264 {
                reason: format!(
                    "a {}x{} picture for a {}x{} encoder",
                    img.width(),
                    img.height(),
                    self.width,
                    self.height
                ),
            });
        }
        let (w, h) = (self.width as usize, self.height as usize);
        let yuv = openh264::formats::YUVSlices::new(
            (img.as_raw(), &self.chroma, &self.chroma),
            (w, h),
            (w, w / 2, w / 2),
        );
        let bs = self
            .enc
            .encode_at(&yuv, openh264::Timestamp::from_millis(time_ms))
            .map_err(|e| h264_err("encoding", e))?;
        let idr = bs.frame_type() == openh264::encoder::FrameType::IDR;
        let mut nals = Vec::new();
        for l in 0..bs.num_layers() {
            let Some(layer) = bs.layer(l) else { continue };
            for n in 0..layer.nal_count() {
                if let Some(nal) = layer.nal_unit(n) {
                    let nal = strip_start_code(nal);
                    if !nal.is_empty() {
                        nals.push(nal.to_vec());
                    }
                }
            }
        }
        Ok(EncodedPicture { nals, idr })
    }

    /// The next picture is an IDR picture.
    pub fn force_idr(&mut self) {
        self.enc.force_intra_frame();
    }

    /// The SPS and PPS this encoder's settings give (from a grey picture
    /// encoded by a throwaway encoder of the same settings), for an SDP's
    /// `sprop-parameter-sets`.
    pub fn parameter_sets(
        width: u32,
        height: u32,
        fps: f64,
        bitrate_bps: u32,
    ) -> Result<Vec<Vec<u8>>, VideoError> {
        let mut enc = H264Encoder::new(width, height, fps, bitrate_bps, 1)?;
        let pic = enc.encode(&GrayImage::from_pixel(width, height, image::Luma([128])), 0)?;
        Ok(pic
            .nals
            .into_iter()
            .filter(|n| matches!(n.first().map(|b| b & 0x1f), Some(7 | 8)))
            .collect())
    }
}

/// RFC 6184 packetisation mode 1 (single NAL unit packets and FU-A) of
/// one stream: its SSRC, payload type and sequence numbers.
#[derive(Debug, Clone)]
pub struct Packetizer {
    /// Synchronisation source of the stream.
    pub ssrc: u32,
    /// RTP payload type.
    pub payload_type: u8,
    /// Sequence number of the next packet.
    pub seq: u16,
    /// Largest packet, bytes (12-byte RTP header included).
    pub mtu: usize,
}

impl Packetizer {
    /// The RTP packets of one access unit (`nals` without start codes)
    /// stamped `timestamp`: a NAL unit that fits whole in one packet, a
    /// larger one as FU-A fragments; the marker bit on the last packet.
    /// Empty NAL units are skipped.
    pub fn packetize(&mut self, nals: &[Vec<u8>], timestamp: u32) -> Vec<Vec<u8>> {
        // At least one payload byte per fragment beside the FU indicator
        // and header.
        let max_payload = self.mtu.max(12 + 3) - 12;
        let mut payloads: Vec<Vec<u8>> = Vec::new();
        for nal in nals.iter().filter(|n| !n.is_empty()) {
            if nal.len() <= max_payload {
                payloads.push(nal.clone());
                continue;
            }
            let (hdr, body) = (nal[0], &nal[1..]);
            let indicator = (hdr & 0xe0) | 28;
            let chunk = max_payload - 2;
            let count = body.len().div_ceil(chunk);
            for (k, part) in body.chunks(chunk).enumerate() {
                let mut fu_header = hdr & 0x1f;
                if k == 0 {
                    fu_header |= 0x80;
                }
                if k + 1 == count {
                    fu_header |= 0x40;
                }
                let mut p = Vec::with_capacity(2 + part.len());
                p.push(indicator);
                p.push(fu_header);
                p.extend_from_slice(part);
                payloads.push(p);
            }
        }
        let last = payloads.len().saturating_sub(1);
        payloads
            .into_iter()
            .enumerate()
            .map(|(k, p)| {
                let mut pkt = Vec::with_capacity(12 + p.len());
                pkt.push(0x80); // V=2, no padding, no extension, no CSRC
                let marker = if k == last { 0x80 } else { 0 };
                pkt.push(marker | (self.payload_type & 0x7f));
                pkt.extend_from_slice(&self.seq.to_be_bytes());
                pkt.extend_from_slice(&timestamp.to_be_bytes());
                pkt.extend_from_slice(&self.ssrc.to_be_bytes());
                pkt.extend_from_slice(&p);
                self.seq = self.seq.wrapping_add(1);
                pkt
            })
            .collect()
    }
}

/// Unix seconds as an NTP timestamp (32.32 fixed point since 1900).
pub fn unix_to_ntp(unix_s: f64) -> u64 {
    let ntp = unix_s + NTP_UNIX_OFFSET_S;
    if !(ntp.is_finite() && ntp > 0.0) {
        return 0;
    }
    let secs = ntp.floor();
    let frac = ((ntp - secs) * 4_294_967_296.0)
        .floor()
        .min(4_294_967_295.0);
    ((secs as u64) << 32) | frac as u64
}

/// An RTCP compound packet: a sender report (RFC 3550 section 6.4.1, no
/// reception blocks) saying the RTP clock read `rtp` at wall time `ntp`,
/// then an SDES with the stream's CNAME.
pub fn sender_report(
    ssrc: u32,
    ntp: u64,
    rtp: u32,
    packets: u32,
    octets: u32,
    cname: &str,
) -> Vec<u8> {
    let mut out = Vec::with_capacity(64);
    out.extend_from_slice(&[0x80, 200, 0, 6]); // 7 words: length 6
    out.extend_from_slice(&ssrc.to_be_bytes());
    out.extend_from_slice(&ntp.to_be_bytes());
    out.extend_from_slice(&rtp.to_be_bytes());
    out.extend_from_slice(&packets.to_be_bytes());
    out.extend_from_slice(&octets.to_be_bytes());
    // SDES: one chunk, CNAME then END, padded to a word.
    let name = &cname.as_bytes()[..cname.len().min(255)];
    let mut chunk = Vec::with_capacity(8 + name.len());
    chunk.extend_from_slice(&ssrc.to_be_bytes());
    chunk.push(1); // CNAME
    chunk.push(name.len() as u8);
    chunk.extend_from_slice(name);
    chunk.push(0); // END
    while chunk.len() % 4 != 0 {
        chunk.push(0);
    }
    let words = (4 + chunk.len()) / 4 - 1;
    out.extend_from_slice(&[0x81, 202]);
    out.extend_from_slice(&(words as u16).to_be_bytes());
    out.extend_from_slice(&chunk);
    out
}

/// Standard base64 with padding (for `sprop-parameter-sets`).
pub fn base64(data: &[u8]) -> String {
    use base64::Engine as _;
    base64::engine::general_purpose::STANDARD.encode(data)
}

/// The session description of the stream (RFC 8866, RFC 6184): a receiver
/// given it listens on `params.dest`'s port. `param_sets` (SPS, PPS) go in
/// `sprop-parameter-sets` and the SPS's profile and level in
/// `profile-level-id`, when given.
pub fn sdp(params: &RtpOutParams, fps: f64, param_sets: &[Vec<u8>]) -> String {
    let ip = params.dest.ip();
    let family = if ip.is_ipv4() { "IP4" } else { "IP6" };
    let pt = params.payload_type;
    let mut fmtp = format!("a=fmtp:{pt} packetization-mode=1");
    if let Some(sps) = param_sets
        .iter()
        .find(|n| n.first().map(|b| b & 0x1f) == Some(7))
        && sps.len() >= 4
    {
        fmtp.push_str(&format!(
            ";profile-level-id={:02X}{:02X}{:02X}",
            sps[1], sps[2], sps[3]
        ));
    }
    if !param_sets.is_empty() {
        let sets: Vec<String> = param_sets.iter().map(|p| base64(p)).collect();
        fmtp.push_str(&format!(";sprop-parameter-sets={}", sets.join(",")));
    }
    format!(
        "v=0\r\n\
         o=- 0 0 IN {family} {ip}\r\n\
         s=shotpilot-sim camera\r\n\
         c=IN {family} {ip}\r\n\
         t=0 0\r\n\
         m=video {port} RTP/AVP {pt}\r\n\
         a=rtpmap:{pt} H264/{CLOCK_RATE}\r\n\
         {fmtp}\r\n\
         a=framerate:{fps}\r\n\
         a=recvonly\r\n",
        port = params.dest.port(),
    )
}

/// Counters of an [`RtpSender`].
#[derive(Debug, Default)]
pub struct RtpStats {
    /// Pictures encoded and sent.
    pub pictures: AtomicU64,
    /// IDR pictures among them.
    pub idr: AtomicU64,
    /// Pictures dropped because the encoder was still busy.
    pub dropped: AtomicU64,
    /// RTP packets sent.
    pub packets: AtomicU64,
    /// RTP payload bytes sent.
    pub payload_bytes: AtomicU64,
    /// RTCP sender reports sent.
    pub sender_reports: AtomicU64,
    /// Sends the OS refused (e.g. nobody listening yet on loopback).
    pub send_errors: AtomicU64,
    /// Pictures the encoder failed on.
    pub encode_errors: AtomicU64,
}

/// A snapshot of [`RtpStats`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RtpStatsSnapshot {
    /// Pictures encoded and sent.
    pub pictures: u64,
    /// IDR pictures among them.
    pub idr: u64,
    /// Pictures dropped because the encoder was still busy.
    pub dropped: u64,
    /// RTP packets sent.
    pub packets: u64,
    /// RTP payload bytes sent.
    pub payload_bytes: u64,
    /// RTCP sender reports sent.
    pub sender_reports: u64,
    /// Sends the OS refused.
    pub send_errors: u64,
    /// Pictures the encoder failed on.
    pub encode_errors: u64,
}

impl RtpStats {
    /// The counters now.
    pub fn snapshot(&self) -> RtpStatsSnapshot {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        RtpStatsSnapshot {
            pictures: g(&self.pictures),
            idr: g(&self.idr),
            dropped: g(&self.dropped),
            packets: g(&self.packets),
            payload_bytes: g(&self.payload_bytes),
            sender_reports: g(&self.sender_reports),
            send_errors: g(&self.send_errors),
            encode_errors: g(&self.encode_errors),
        }
    }
}

/// A picture waiting for the encoder.
struct Job {
    image: Arc<GrayImage>,
    capture_unix_s: f64,
}

/// The stream's clock: RTP time = `rtp_base` + 90 kHz x (unix time -
/// `unix_base`).
#[derive(Debug, Clone, Copy)]
struct StreamClock {
    unix_base: f64,
    rtp_base: u32,
}

impl StreamClock {
    fn rtp_at(&self, unix_s: f64) -> u32 {
        let ticks = ((unix_s - self.unix_base) * f64::from(CLOCK_RATE)).round() as i64;
        self.rtp_base.wrapping_add(ticks as u32)
    }
}

/// The H.264 RTP sender: an encoding thread fed by [`RtpSender::offer`]
/// (see the module documentation). Dropping it stops the thread.
pub struct RtpSender {
    tx: Option<SyncSender<Job>>,
    stats: Arc<RtpStats>,
    thread: Option<std::thread::JoinHandle<()>>,
    params: RtpOutParams,
}

impl std::fmt::Debug for RtpSender {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RtpSender")
            .field("params", &self.params)
            .field("stats", &self.stats.snapshot())
            .finish()
    }
}

impl RtpSender {
    /// Opens the socket and starts the encoding thread for pictures at
    /// `fps`; `seed` picks the SSRC, first sequence number and RTP clock
    /// offset (RFC 3550 wants them random; seeded, a run is repeatable).
    pub fn start(params: RtpOutParams, fps: f64, seed: u64) -> Result<RtpSender, VideoError> {
        params.check().map_err(|(field, reason)| VideoError::H264 {
            reason: format!("RTP output {field}: {reason}"),
        })?;
        let bind: SocketAddr = if params.dest.is_ipv4() {
            SocketAddr::from(([0, 0, 0, 0], 0))
        } else {
            SocketAddr::from((std::net::Ipv6Addr::UNSPECIFIED, 0))
        };
        let sock = UdpSocket::bind(bind).map_err(|e| h264_err("binding the RTP socket", e))?;
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::SmallRng::seed_from_u64(seed ^ 0x0052_5450);
        let packetizer = Packetizer {
            ssrc: rng.random(),
            payload_type: params.payload_type,
            seq: rng.random(),
            mtu: params.mtu,
        };
        let clock = StreamClock {
            unix_base: unix_now(),
            rtp_base: rng.random(),
        };
        let (tx, rx) = std::sync::mpsc::sync_channel::<Job>(2);
        let stats = Arc::new(RtpStats::default());
        let st = stats.clone();
        let thread = std::thread::Builder::new()
            .name("sim-rtp".into())
            .spawn(move || send_loop(rx, sock, params, fps, packetizer, clock, &st))
            .map_err(|e| h264_err("starting the RTP thread", e))?;
        tracing::info!(
            "RTP H.264 to {} ({:.2} Mbit/s, IDR every {} s, RTCP to port {})",
            params.dest,
            f64::from(params.bitrate_bps) / 1e6,
            params.idr_interval_s,
            params.dest.port() + 1
        );
        Ok(RtpSender {
            tx: Some(tx),
            stats,
            thread: Some(thread),
            params,
        })
    }

    /// Queues a picture captured at `capture_unix_s` (unix seconds;
    /// increasing from picture to picture) for encoding; false (and
    /// counted) when the encoder is still busy with two, or has stopped.
    pub fn offer(&self, image: Arc<GrayImage>, capture_unix_s: f64) -> bool {
        let Some(tx) = &self.tx else { return false };
        match tx.try_send(Job {
            image,
            capture_unix_s,
        }) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.stats.dropped.fetch_add(1, Ordering::Relaxed);
                false
            }
        }
    }

    /// The counters.
    pub fn stats(&self) -> RtpStatsSnapshot {
        self.stats.snapshot()
    }

    /// The settings.
    pub fn params(&self) -> &RtpOutParams {
        &self.params
    }
}

impl Drop for RtpSender {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn send_loop(
    rx: Receiver<Job>,
    sock: UdpSocket,
    params: RtpOutParams,
    fps: f64,
    mut packetizer: Packetizer,
    clock: StreamClock,
    stats: &RtpStats,
) {
    let rtcp_dest = SocketAddr::new(params.dest.ip(), params.dest.port().wrapping_add(1));
    let sr_every = Duration::from_secs_f64(params.sr_interval_s);
    let idr_period = (params.idr_interval_s * fps).round().max(1.0) as u32;
    let mut encoder: Option<H264Encoder> = None;
    let mut last_sr: Option<Instant> = None;
    let mut last_capture = f64::NEG_INFINITY;
    let (mut packets, mut octets) = (0u32, 0u32);
    let count_send = |r: std::io::Result<usize>| {
        if let Err(e) = r {
            stats.send_errors.fetch_add(1, Ordering::Relaxed);
            tracing::trace!("RTP send: {e}");
        }
    };
    loop {
        let job = match rx.recv_timeout(sr_every) {
            Ok(j) => Some(j),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        if let Some(job) = job
            && job.capture_unix_s > last_capture
        {
            last_capture = job.capture_unix_s;
            let (w, h) = job.image.dimensions();
            if encoder
                .as_ref()
                .is_none_or(|e| (e.width(), e.height()) != (w, h))
            {
                encoder = match H264Encoder::new(w, h, fps, params.bitrate_bps, idr_period) {
                    Ok(e) => Some(e),
                    Err(e) => {
                        stats.encode_errors.fetch_add(1, Ordering::Relaxed);
                        tracing::warn!("RTP output: {e}");
                        None
                    }
                };
            }
            let Some(enc) = encoder.as_mut() else {
                continue;
            };
            let ms = ((job.capture_unix_s - clock.unix_base).max(0.0) * 1000.0) as u64;
            match enc.encode(&job.image, ms) {
                Ok(pic) if !pic.nals.is_empty() => {
                    let ts = clock.rtp_at(job.capture_unix_s);
                    for pkt in packetizer.packetize(&pic.nals, ts) {
                        count_send(sock.send_to(&pkt, params.dest));
                        packets = packets.wrapping_add(1);
                        octets = octets.wrapping_add((pkt.len() - 12) as u32);
                        stats.packets.fetch_add(1, Ordering::Relaxed);
                        stats
                            .payload_bytes
                            .fetch_add((pkt.len() - 12) as u64, Ordering::Relaxed);
                    }
                    stats.pictures.fetch_add(1, Ordering::Relaxed);
                    if pic.idr {
                        stats.idr.fetch_add(1, Ordering::Relaxed);
                    }
                }
                Ok(_) => {}
                Err(e) => {
                    stats.encode_errors.fetch_add(1, Ordering::Relaxed);
                    tracing::warn!("RTP output: {e}");
                }
            }
        }
        // A sender report once the stream has started, then each interval.
        if packets > 0 && last_sr.is_none_or(|t| t.elapsed() >= sr_every) {
            let now = unix_now();
            let sr = sender_report(
                packetizer.ssrc,
                unix_to_ntp(now),
                clock.rtp_at(now),
                packets,
                octets,
                "shotpilot-sim@camera",
            );
            count_send(sock.send_to(&sr, rtcp_dest));
            stats.sender_reports.fetch_add(1, Ordering::Relaxed);
            last_sr = Some(Instant::now());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reassembler written from RFC 6184 for these tests: single NAL
    /// units and FU-A only.
    fn reassemble(pkts: &[Vec<u8>]) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        let mut fu: Option<Vec<u8>> = None;
        for p in pkts {
            let pl = &p[12..];
            if pl[0] & 0x1f == 28 {
                if pl[1] & 0x80 != 0 {
                    fu = Some(vec![(pl[0] & 0xe0) | (pl[1] & 0x1f)]);
                }
                fu.as_mut().unwrap().extend_from_slice(&pl[2..]);
                if pl[1] & 0x40 != 0 {
                    out.push(fu.take().unwrap());
                }
            } else {
                out.push(pl.to_vec());
            }
        }
        out
    }

    #[test]
    fn packets_fit_the_mtu_and_reassemble_to_the_nal_units() {
        let nals = vec![
            vec![0x67, 1, 2, 3],
            vec![0x68, 4],
            (0..5000u32)
                .map(|i| if i == 0 { 0x65 } else { (i % 253) as u8 + 1 })
                .collect(),
            (0..1188u32)
                .map(|i| if i == 0 { 0x41 } else { 7 })
                .collect(),
        ];
        let mut p = Packetizer {
            ssrc: 0xdead_beef,
            payload_type: 96,
            seq: 65534,
            mtu: 1200,
        };
        let pkts = p.packetize(&nals, 123_456);
        // SPS, PPS, 5 fragments of the IDR slice (4999 / 1186), one whole
        // 1188-byte slice (exactly fills 1200).
        assert_eq!(pkts.len(), 2 + 5 + 1);
        for (k, pkt) in pkts.iter().enumerate() {
            assert!(pkt.len() <= 1200);
            assert_eq!(pkt[0], 0x80);
            assert_eq!(pkt[1] & 0x7f, 96);
            assert_eq!(
                pkt[1] & 0x80 != 0,
                k + 1 == pkts.len(),
                "marker on the last"
            );
            let seq = u16::from_be_bytes([pkt[2], pkt[3]]);
            assert_eq!(seq, 65534u16.wrapping_add(k as u16), "wraps");
            assert_eq!(
                u32::from_be_bytes([pkt[4], pkt[5], pkt[6], pkt[7]]),
                123_456
            );
            assert_eq!(
                u32::from_be_bytes([pkt[8], pkt[9], pkt[10], pkt[11]]),
                0xdead_beef
            );
        }
        let fu: Vec<&Vec<u8>> = pkts.iter().filter(|p| p[12] & 0x1f == 28).collect();
        assert_eq!(fu.len(), 5);
        assert_eq!(fu[0][12], 0x60 | 28, "NRI of the IDR slice kept");
        assert_eq!(fu[0][13], 0x80 | 5);
        assert_eq!(fu[4][13], 0x40 | 5);
        assert_eq!(reassemble(&pkts), nals);
        assert_eq!(p.seq, 65534u16.wrapping_add(8));
    }

    #[test]
    fn sender_report_layout() {
        let ntp = unix_to_ntp(1_700_000_000.25);
        assert_eq!(ntp >> 32, 1_700_000_000 + 2_208_988_800);
        assert_eq!(ntp & 0xffff_ffff, 1 << 30);
        let sr = sender_report(7, ntp, 99, 3, 4000, "cam");
        assert_eq!(&sr[..4], &[0x80, 200, 0, 6]);
        assert_eq!(u64::from_be_bytes(sr[8..16].try_into().unwrap()), ntp);
        assert_eq!(u32::from_be_bytes(sr[16..20].try_into().unwrap()), 99);
        assert_eq!(u32::from_be_bytes(sr[24..28].try_into().unwrap()), 4000);
        let sdes = &sr[28..];
        assert_eq!(sdes[1], 202);
        let words = u16::from_be_bytes([sdes[2], sdes[3]]) as usize;
        assert_eq!(
            sdes.len(),
            (words + 1) * 4,
            "the compound packet ends on the SDES"
        );
        assert_eq!(&sdes[8..10], &[1, 3]);
        assert_eq!(&sdes[10..13], b"cam");
    }

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn encoder_sends_parameter_sets_before_each_idr_and_hits_its_bitrate() {
        let (w, h, fps) = (320u32, 240u32, 15.0);
        let mut enc = H264Encoder::new(w, h, fps, 400_000, 15).unwrap();
        let mut bytes = 0usize;
        let mut idr_at = Vec::new();
        for k in 0..60u32 {
            // A textured picture panning a pixel per frame.
            let img = GrayImage::from_fn(w, h, |x, y| {
                let v = (((x + k) * 37) ^ (y * 91)) % 251;
                image::Luma([v as u8])
            });
            let pic = enc.encode(&img, u64::from(k) * 66).unwrap();
            let types: Vec<u8> = pic.nals.iter().map(|n| n[0] & 0x1f).collect();
            if pic.idr {
                idr_at.push(k);
                assert_eq!(&types[..2], &[7, 8], "SPS, PPS first: {types:?}");
                assert!(types.contains(&5));
            } else {
                assert!(types.iter().all(|&t| t == 1), "{types:?}");
            }
            bytes += pic.bytes();
        }
        assert_eq!(idr_at, vec![0, 15, 30, 45]);
        let kbps = bytes as f64 * 8.0 / (60.0 / fps) / 1e3;
        // Rate control over 4 s: within a factor of two of the target.
        assert!((200.0..800.0).contains(&kbps), "{kbps} kbit/s");
        let ps = H264Encoder::parameter_sets(w, h, fps, 400_000).unwrap();
        assert_eq!(ps.len(), 2);
        let text = sdp(&RtpOutParams::default(), fps, &ps);
        assert!(text.contains("m=video 5600 RTP/AVP 96\r\n"), "{text}");
        assert!(text.contains("c=IN IP4 127.0.0.1\r\n"));
        assert!(text.contains("a=rtpmap:96 H264/90000\r\n"));
        assert!(text.contains(&format!("sprop-parameter-sets={},", base64(&ps[0]))));
        assert!(H264Encoder::new(321, 240, fps, 400_000, 15).is_err());
        assert!(enc.encode(&GrayImage::new(32, 24), 0).is_err());
    }

    #[test]
    fn stream_clock_is_the_capture_clock_at_90_khz() {
        let c = StreamClock {
            unix_base: 1000.0,
            rtp_base: u32::MAX - 10,
        };
        assert_eq!(c.rtp_at(1000.0), u32::MAX - 10);
        assert_eq!(c.rtp_at(1001.0), (u32::MAX - 10).wrapping_add(90_000));
        assert_eq!(c.rtp_at(999.9), (u32::MAX - 10).wrapping_sub(9000));
    }

    #[test]
    fn bad_settings_are_refused() {
        let ok = RtpOutParams::default();
        assert!(ok.check().is_ok());
        for bad in [
            RtpOutParams { mtu: 20, ..ok },
            RtpOutParams {
                payload_type: 33,
                ..ok
            },
            RtpOutParams {
                bitrate_bps: 0,
                ..ok
            },
            RtpOutParams {
                dest: "127.0.0.1:0".parse().unwrap(),
                ..ok
            },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
            assert!(RtpSender::start(bad, 15.0, 1).is_err());
        }
    }
}
