//! The video source chosen by `[video] url`: `http://` MJPEG or snapshots
//! ([`crate::video::mjpeg`]), `rtsp://` H.264 ([`crate::video::rtsp`]),
//! `udp://HOST:PORT` raw RTP H.264 or an SDP file describing it
//! ([`crate::video::udp`]), or `auto`: the URL the vehicle's camera
//! announces in `VIDEO_STREAM_INFORMATION`.
//!
//! [`run_h264`] runs an H.264 source: the network reader (RTSP or UDP)
//! assembles access units into a short queue, a dedicated thread decodes
//! them ([`crate::video::h264`]) into the ingest's newest-frame slot.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use crate::video::decode_loop;
use crate::video::h264::{AuQueue, H264Error};
use crate::video::live::Ingest;
pub use crate::video::stream::{
    H264Params, H264Sink, RtspTransport, SourceError, backoff, codec_name,
};

/// How video frames are fetched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VideoSource {
    /// `multipart/x-mixed-replace` stream.
    Mjpeg,
    /// Poll a JPEG snapshot URL.
    Snapshot,
}

/// `[video]` of `config.toml`: the live video source.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VideoConfig {
    /// For `http://` URLs: `mjpeg` or `snapshot`.
    pub source: VideoSource,
    /// Where the video comes from: `rtsp://[user:pass@]host[:port]/path`
    /// (H.264), `udp://HOST:PORT` (raw RTP H.264, e.g. `udp://0.0.0.0:5600`),
    /// a path to an `.sdp` file, `http://` (MJPEG stream or JPEG
    /// snapshots, per `source`), or `auto` (the URL the vehicle's camera
    /// announces over MAVLink in VIDEO_STREAM_INFORMATION).
    pub url: String,
    /// RTSP transport for RTP: `tcp` (interleaved, default) or `udp`.
    pub transport: RtspTransport,
    /// RTSP user name, when the URL carries none.
    pub username: Option<String>,
    /// RTSP password, when the URL carries none.
    pub password: Option<String>,
    /// `auto`: the MAVLink component asked for VIDEO_STREAM_INFORMATION
    /// (100: MAV_COMP_ID_CAMERA).
    pub camera_component: u8,
    /// `auto`: how long to wait for the vehicle and its camera's answer, s
    /// (asking again each second).
    pub auto_timeout_s: f64,
    /// H.264: access units queued ahead of the decoder before the oldest
    /// are dropped and decoding resumes at the next key frame.
    pub decode_queue: usize,
    /// H.264: after a lost packet, decode on with error concealment and
    /// hand SLAM each frame with its damaged rows masked (true), or skip
    /// every picture up to the next key frame (false).
    pub conceal: bool,
    /// H.264: the bound on vertical motion between a picture and its
    /// references, pixels: damage spreads this far per predicted picture
    /// (see `video::damage`).
    pub damage_mv_px: u32,
    /// H.264: follow damage with the content's vertical motion measured on
    /// the decoded pictures (true), or spread it by `damage_mv_px` per
    /// predicted picture always (false).
    pub damage_follow_motion: bool,
    /// H.264, following motion: how far damage reaches beyond the measured
    /// motion range per predicted picture, pixels.
    pub damage_motion_margin_px: u32,
    /// RTP over UDP: after a lost packet, hold the packets behind it this
    /// long while a NACK asks the sender to retransmit it (RFC 4585/4588;
    /// a sender that never answers is noticed and costs no more waiting),
    /// ms; 0: no NACK.
    pub nack_wait_ms: u64,
    /// RTP over UDP: after a packet is lost for good, ask the sender for a
    /// key frame (RTCP PLI) at most this often, ms; 0: never.
    pub key_frame_request_ms: u64,
    /// Decimate the picture by this integer factor before SLAM (1: full
    /// resolution; any source); the camera intrinsics are scaled to match.
    pub downscale: u32,
    /// Snapshot polling rate, Hz.
    pub snapshot_hz: f64,
    /// Connect timeout, ms.
    pub connect_timeout_ms: u64,
    /// A connection silent this long is reopened, ms.
    pub read_timeout_ms: u64,
    /// First reconnect delay, ms (doubles per failure).
    pub reconnect_min_ms: u64,
    /// Largest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// Largest accepted JPEG, bytes.
    pub max_frame_bytes: usize,
}

impl Default for VideoConfig {
    fn default() -> Self {
        let p = crate::video::mjpeg::Params::default();
        Self {
            source: VideoSource::Mjpeg,
            url: "http://127.0.0.1:8554/video.mjpg".into(),
            transport: Default::default(),
            username: None,
            password: None,
            camera_component: 100,
            auto_timeout_s: 30.0,
            decode_queue: 8,
            conceal: true,
            damage_mv_px: crate::video::damage::DamageParams::default().mv_px,
            damage_follow_motion: crate::video::damage::DamageParams::default().follow_motion,
            damage_motion_margin_px: crate::video::damage::DamageParams::default().motion_margin_px,
            nack_wait_ms: crate::video::rtp::feedback::NackParams::default()
                .wait
                .as_millis() as u64,
            key_frame_request_ms: 1000,
            downscale: 1,
            snapshot_hz: 5.0,
            connect_timeout_ms: p.connect_timeout_ms,
            read_timeout_ms: p.read_timeout_ms,
            reconnect_min_ms: p.reconnect_min_ms,
            reconnect_max_ms: p.reconnect_max_ms,
            max_frame_bytes: p.max_part_bytes,
        }
    }
}

impl VideoConfig {
    /// The client tunables.
    pub fn params(&self) -> crate::video::mjpeg::Params {
        crate::video::mjpeg::Params {
            connect_timeout_ms: self.connect_timeout_ms,
            read_timeout_ms: self.read_timeout_ms,
            reconnect_min_ms: self.reconnect_min_ms,
            reconnect_max_ms: self.reconnect_max_ms,
            max_part_bytes: self.max_frame_bytes,
            ..Default::default()
        }
    }

    /// The H.264 sources' tunables.
    pub fn h264_params(&self) -> H264Params {
        H264Params {
            transport: self.transport,
            username: self.username.clone(),
            password: self.password.clone(),
            connect_timeout_ms: self.connect_timeout_ms,
            read_timeout_ms: self.read_timeout_ms,
            reconnect_min_ms: self.reconnect_min_ms,
            reconnect_max_ms: self.reconnect_max_ms,
            decode: crate::video::decode_loop::DecodeParams {
                queue: self.decode_queue,
                downscale: self.downscale,
                conceal: self.conceal,
                damage: crate::video::damage::DamageParams {
                    mv_px: self.damage_mv_px,
                    follow_motion: self.damage_follow_motion,
                    motion_margin_px: self.damage_motion_margin_px,
                    ..Default::default()
                },
                ..Default::default()
            },
            feedback: crate::video::stream::FeedbackParams {
                nack: crate::video::rtp::feedback::NackParams {
                    wait: std::time::Duration::from_millis(self.nack_wait_ms),
                    ..Default::default()
                },
                key_frame_interval: (self.key_frame_request_ms > 0)
                    .then(|| std::time::Duration::from_millis(self.key_frame_request_ms)),
            },
        }
    }
}

/// A parsed `[video] url`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum VideoUrl {
    /// `http://`: MJPEG stream or JPEG snapshots (per `[video] source`).
    Http(String),
    /// `rtsp://` (credentials removed from the URL and kept apart).
    Rtsp {
        /// The URL without user information.
        url: String,
        /// User name from the URL.
        username: Option<String>,
        /// Password from the URL.
        password: Option<String>,
    },
    /// `udp://HOST:PORT`: raw RTP H.264 arriving on this local address
    /// (`HOST` may be a multicast group, or empty for all interfaces).
    Udp {
        /// Where to listen.
        bind: SocketAddr,
    },
    /// An SDP file describing a raw RTP stream (`file:///x.sdp` or a path
    /// ending in `.sdp`).
    Sdp {
        /// The file.
        path: PathBuf,
    },
    /// Ask the vehicle's camera over MAVLink.
    Auto,
}

fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%'
            && i + 2 < b.len()
            && let Ok(v) =
                u8::from_str_radix(std::str::from_utf8(&b[i + 1..i + 3]).unwrap_or("zz"), 16)
        {
            out.push(v);
            i += 3;
            continue;
        }
        out.push(b[i]);
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

impl VideoUrl {
    /// Parse `[video] url`.
    pub fn parse(raw: &str) -> Result<Self, SourceError> {
        let s = raw.trim();
        let bad = |reason: &str| SourceError::BadUrl {
            url: redact(s),
            reason: reason.to_owned(),
        };
        let lower = s.to_ascii_lowercase();
        if lower == "auto" {
            return Ok(Self::Auto);
        }
        if lower.starts_with("http://") {
            return Ok(Self::Http(s.to_owned()));
        }
        if lower.starts_with("https://") {
            return Err(bad(
                "https is not supported; cameras serve MJPEG over plain http://",
            ));
        }
        if lower.starts_with("rtsps://") {
            return Err(bad("rtsps (RTSP over TLS) is not supported; use rtsp://"));
        }
        if lower.starts_with("rtsp://") {
            let rest = &s[7..];
            let (authority, path) = match rest.find('/') {
                Some(i) => (&rest[..i], &rest[i..]),
                None => (rest, "/"),
            };
            let (userinfo, host) = match authority.rfind('@') {
                Some(i) => (Some(&authority[..i]), &authority[i + 1..]),
                None => (None, authority),
            };
            if host.is_empty() {
                return Err(bad("no host"));
            }
            let url = format!("rtsp://{host}{path}");
            url::Url::parse(&url).map_err(|e| bad(&e.to_string()))?;
            let (username, password) = match userinfo {
                None => (None, None),
                Some(u) => match u.split_once(':') {
                    Some((n, p)) => (Some(percent_decode(n)), Some(percent_decode(p))),
                    None => (Some(percent_decode(u)), None),
                },
            };
            return Ok(Self::Rtsp {
                url,
                username,
                password,
            });
        }
        if lower.starts_with("udp://") {
            let hostport = s[6..].trim_end_matches('/');
            let hostport = hostport.strip_prefix('@').unwrap_or(hostport);
            let (host, port) = hostport
                .rsplit_once(':')
                .ok_or_else(|| bad("udp:// needs HOST:PORT (e.g. udp://0.0.0.0:5600)"))?;
            let host = host.trim_start_matches('[').trim_end_matches(']');
            let host = if host.is_empty() { "0.0.0.0" } else { host };
            let port: u16 = port.parse().map_err(|_| bad("bad port"))?;
            let ip: std::net::IpAddr = host
                .parse()
                .map_err(|_| bad("udp:// needs a numeric local or multicast address"))?;
            return Ok(Self::Udp {
                bind: SocketAddr::new(ip, port),
            });
        }
        if let Some(p) = s.strip_prefix("file://") {
            return Ok(Self::Sdp {
                path: PathBuf::from(p),
            });
        }
        if lower.ends_with(".sdp") {
            return Ok(Self::Sdp {
                path: PathBuf::from(s),
            });
        }
        Err(bad(
            "expected rtsp://, udp://HOST:PORT, an .sdp file, http:// (MJPEG or snapshots) or auto",
        ))
    }

    /// The URL as logged and shown (password removed).
    pub fn display(&self) -> String {
        match self {
            Self::Http(u) => redact(u),
            Self::Rtsp { url, username, .. } => match username {
                Some(u) => url.replacen("rtsp://", &format!("rtsp://{u}@"), 1),
                None => url.clone(),
            },
            Self::Udp { bind } => format!("udp://{bind}"),
            Self::Sdp { path } => path.display().to_string(),
            Self::Auto => "auto".into(),
        }
    }
}

/// `url` with the password of its user information replaced by `***`.
pub fn redact(url: &str) -> String {
    let Some(scheme_end) = url.find("://") else {
        return url.to_owned();
    };
    let rest = &url[scheme_end + 3..];
    let auth_end = rest.find('/').unwrap_or(rest.len());
    let authority = &rest[..auth_end];
    match authority.rfind('@') {
        Some(at) => {
            let user = authority[..at].split(':').next().unwrap_or("");
            format!("{}{}:***@{}", &url[..scheme_end + 3], user, &rest[at + 1..])
        }
        None => url.to_owned(),
    }
}

/// Run an H.264 source (`rtsp://`, `udp://` or SDP) until `cancel` fires.
/// Errors that retrying cannot fix (a bad SDP file, an unbindable port)
/// return; network errors are retried with backoff.
pub async fn run_h264(
    url: VideoUrl,
    params: H264Params,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
) -> Result<(), SourceError> {
    run_h264_on(url, params, ingest, cancel, None).await
}

/// [`run_h264`]; a `udp://` source receives on `rtp` when given (sockets
/// the caller bound, whatever port the URL names).
async fn run_h264_on(
    url: VideoUrl,
    params: H264Params,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
    rtp: Option<crate::video::udp::RtpSockets>,
) -> Result<(), SourceError> {
    let queue = Arc::new(AuQueue::new(params.decode.queue));
    let resets = Arc::new(AtomicU64::new(0));
    let decoder = decode_loop::spawn_decoder(
        ingest.clone(),
        queue.clone(),
        params.decode.clone(),
        resets.clone(),
    )
    .map_err(|e| SourceError::Thread(e.to_string()))?;
    let sink = H264Sink {
        ingest: ingest.clone(),
        queue: queue.clone(),
        resets,
    };
    ingest.update_source(|s| {
        s.url = url.display();
        s.codec = Some("h264".into());
    });
    let r = match url {
        VideoUrl::Rtsp {
            url,
            username,
            password,
        } => {
            let creds = match (
                username.or(params.username.clone()),
                password.or(params.password.clone()),
            ) {
                (Some(u), p) => Some((u, p.unwrap_or_default())),
                (None, _) => None,
            };
            ingest.update_source(|s| {
                s.kind = "rtsp".into();
                s.transport = Some(
                    match params.transport {
                        RtspTransport::Tcp => "tcp",
                        RtspTransport::Udp => "udp",
                    }
                    .into(),
                );
            });
            crate::video::rtsp::run(&url, creds, &params, &sink, &cancel).await
        }
        VideoUrl::Udp { bind } => {
            ingest.update_source(|s| s.kind = "rtp".into());
            match rtp {
                Some(sockets) => {
                    crate::video::udp::run_on(sockets, None, &params, &sink, &cancel).await
                }
                None => crate::video::udp::run(bind, None, &params, &sink, &cancel).await,
            }
        }
        VideoUrl::Sdp { path } => {
            ingest.update_source(|s| s.kind = "rtp".into());
            let text = std::fs::read_to_string(&path).map_err(|e| SourceError::ReadSdp {
                path: path.clone(),
                reason: e.to_string(),
            })?;
            let sdp = crate::video::rtp::sdp::parse(&text).map_err(|source| SourceError::Sdp {
                path: path.clone(),
                source,
            })?;
            if sdp.codec != "H264" {
                Err(SourceError::Codec(H264Error::UnsupportedCodec {
                    codec: codec_name(&sdp.codec),
                }))
            } else {
                let ip = sdp
                    .address
                    .as_deref()
                    .and_then(|a| a.parse::<std::net::IpAddr>().ok())
                    .filter(|ip| ip.is_multicast())
                    .unwrap_or(std::net::IpAddr::V4(std::net::Ipv4Addr::UNSPECIFIED));
                crate::video::udp::run(
                    SocketAddr::new(ip, sdp.port),
                    Some(sdp),
                    &params,
                    &sink,
                    &cancel,
                )
                .await
            }
        }
        VideoUrl::Http(_) | VideoUrl::Auto => Err(SourceError::BadUrl {
            url: url.display(),
            reason: "not an H.264 source".into(),
        }),
    };
    if let Err(e) = &r {
        ingest.update_source(|s| {
            s.connected = false;
            s.last_error = Some(e.to_string());
        });
    }
    queue.close();
    let _ = tokio::task::spawn_blocking(move || decoder.join()).await;
    r
}

/// The camera model SLAM must use when the decoded picture is decimated by
/// `f` (block averaging): focal lengths over `f`, principal point at
/// `(c + 0.5) / f - 0.5`, size `floor(size / f)`; the distortion acts on
/// normalised coordinates and is unchanged.
pub fn decimated_camera(c: &crate::camera::Camera, f: u32) -> crate::camera::Camera {
    if f <= 1 {
        return *c;
    }
    let s = f64::from(f);
    let mut d = *c;
    d.width = c.width / f;
    d.height = c.height / f;
    d.fx = c.fx / s;
    d.fy = c.fy / s;
    d.cx = (c.cx + 0.5) / s - 0.5;
    d.cy = (c.cy + 0.5) / s - 0.5;
    d
}

/// The `[video] url` a camera's VIDEO_STREAM_INFORMATION stands for.
pub fn url_from_stream_info(
    info: &crate::vehicle::VideoStreamInfo,
) -> Result<VideoUrl, SourceError> {
    let bad = |reason: String| SourceError::Auto { reason };
    if info.encoding == "h265" {
        return Err(SourceError::Codec(H264Error::UnsupportedCodec {
            codec: "H.265 (HEVC)".into(),
        }));
    }
    let uri = info.uri.trim();
    match info.kind.as_str() {
        "rtpudp" => {
            // QGroundControl's convention: a bare port or udp://HOST:PORT.
            if let Ok(port) = uri.parse::<u16>() {
                return Ok(VideoUrl::Udp {
                    bind: SocketAddr::new(std::net::Ipv4Addr::UNSPECIFIED.into(), port),
                });
            }
            if uri.is_empty() {
                return Ok(VideoUrl::Udp {
                    bind: SocketAddr::new(std::net::Ipv4Addr::UNSPECIFIED.into(), 5600),
                });
            }
            VideoUrl::parse(uri)
        }
        "rtsp" => match VideoUrl::parse(uri)? {
            u @ VideoUrl::Rtsp { .. } => Ok(u),
            _ => Err(bad(format!(
                "stream {:?} is RTSP but its URI is {uri:?}",
                info.name
            ))),
        },
        _ => match VideoUrl::parse(uri) {
            Ok(u @ (VideoUrl::Http(_) | VideoUrl::Rtsp { .. } | VideoUrl::Udp { .. })) => Ok(u),
            _ => Err(bad(format!(
                "stream {:?} is {} at {uri:?}, which shotpilot cannot read (it reads RTSP, RTP/UDP H.264 and MJPEG over HTTP)",
                info.name, info.kind
            ))),
        },
    }
}

/// `auto`: wait for the vehicle, ask its camera component for
/// VIDEO_STREAM_INFORMATION each second until one arrives or `timeout`
/// passes, log what it announced and return the first stream's URL.
pub async fn resolve_auto(
    link: &crate::vehicle::LinkHandle,
    camera_component: u8,
    timeout: Duration,
    cancel: &CancellationToken,
) -> Result<VideoUrl, SourceError> {
    let deadline = tokio::time::Instant::now() + timeout;
    let fail = |what: &str| SourceError::Auto {
        reason: format!(
            "{what} within {:.0} s; set [video] url to the camera's stream instead of auto",
            timeout.as_secs_f64()
        ),
    };
    tokio::select! {
        _ = cancel.cancelled() => return Err(SourceError::Auto { reason: "cancelled".into() }),
        r = link.wait_for_vehicle(timeout) => {
            r.map_err(|_| fail("no vehicle heartbeat"))?;
        }
    }
    let mut rx = link.telemetry.video_streams.clone();
    tracing::info!("video: auto: asking component {camera_component} for VIDEO_STREAM_INFORMATION");
    loop {
        if let Err(e) = link.request_message(269, camera_component).await {
            tracing::debug!("video: auto: request: {e}");
        }
        let wait = tokio::time::sleep(
            Duration::from_secs(1)
                .min(deadline.saturating_duration_since(tokio::time::Instant::now())),
        );
        tokio::select! {
            _ = cancel.cancelled() => return Err(SourceError::Auto { reason: "cancelled".into() }),
            _ = rx.changed() => {}
            _ = wait => {}
        }
        let streams = rx.borrow_and_update().clone();
        if let Some(first) = streams.iter().min_by_key(|s| s.stream_id) {
            for s in &streams {
                tracing::info!(
                    component = s.component_id,
                    stream = s.stream_id,
                    name = %s.name,
                    kind = %s.kind,
                    encoding = %s.encoding,
                    uri = %redact(&s.uri),
                    "video: auto: the camera announces {}x{} at {:.0} fps, {:.1} Mbit/s",
                    s.width,
                    s.height,
                    s.framerate,
                    f64::from(s.bitrate) / 1e6
                );
            }
            let url = url_from_stream_info(first)?;
            tracing::info!("video: auto: using {}", url.display());
            return Ok(url);
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(fail("no VIDEO_STREAM_INFORMATION from the camera"));
        }
    }
}

/// Run the source `[video]` names until `cancel` fires: MJPEG or
/// snapshots (`http://`), H.264 (`rtsp://`, `udp://`, SDP), or `auto` (the
/// link is awaited, the camera asked, then the URL it gave is run).
pub async fn run_configured(
    cfg: VideoConfig,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
    link: Option<tokio::sync::oneshot::Receiver<crate::vehicle::LinkHandle>>,
) -> Result<(), SourceError> {
    run_configured_on(cfg, ingest, cancel, link, None).await
}

/// [`run_configured`]; a `udp://` source receives on `rtp`, sockets the
/// caller bound (port 0, so it knew the port before the sender started).
pub async fn run_configured_on(
    cfg: VideoConfig,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
    link: Option<tokio::sync::oneshot::Receiver<crate::vehicle::LinkHandle>>,
    rtp: Option<crate::video::udp::RtpSockets>,
) -> Result<(), SourceError> {
    let mut url = VideoUrl::parse(&cfg.url)?;
    tokio::spawn(log_status(ingest.clone(), cancel.clone()));
    if url == VideoUrl::Auto {
        ingest.update_source(|s| {
            s.kind = "auto".into();
            s.url = "auto".into();
        });
        let Some(rx) = link else {
            return Err(SourceError::Auto {
                reason: "no MAVLink link to ask the camera".into(),
            });
        };
        let handle = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            h = rx => h.map_err(|_| SourceError::Auto { reason: "the MAVLink link did not start".into() })?,
        };
        let timeout = Duration::from_secs_f64(cfg.auto_timeout_s);
        url = match resolve_auto(&handle, cfg.camera_component, timeout, &cancel).await {
            Ok(u) => u,
            Err(e) => {
                ingest.update_source(|s| s.last_error = Some(e.to_string()));
                return Err(e);
            }
        };
    }
    match url {
        VideoUrl::Http(u) => {
            ingest.update_source(|s| {
                s.kind = match cfg.source {
                    VideoSource::Mjpeg => "mjpeg",
                    VideoSource::Snapshot => "snapshot",
                }
                .into();
                s.url = redact(&u);
                s.codec = Some("jpeg".into());
            });
            let p = cfg.params();
            let r = match cfg.source {
                VideoSource::Mjpeg => crate::video::mjpeg::run_mjpeg(&u, &p, ingest, cancel).await,
                VideoSource::Snapshot => {
                    crate::video::mjpeg::run_snapshots(&u, cfg.snapshot_hz, &p, ingest, cancel)
                        .await
                }
            };
            r.map_err(|e| SourceError::BadUrl {
                url: redact(&u),
                reason: e.to_string(),
            })
        }
        other => run_h264_on(other, cfg.h264_params(), ingest, cancel, rtp).await,
    }
}

/// Log the video's state every 30 s until `cancel` fires: source, codec,
/// resolution, rates and the counters an operator checks first.
async fn log_status(ingest: Arc<Ingest>, cancel: CancellationToken) {
    let mut tick = tokio::time::interval(Duration::from_secs(30));
    tick.tick().await;
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let s = ingest.source_info();
        let c = ingest.counters.snapshot();
        tracing::info!(
            source = %s.kind,
            url = %s.url,
            codec = s.codec.as_deref().unwrap_or("?"),
            connected = s.connected,
            "video: {}x{} at {:.1} fps, {:.0} kbit/s; decoded {}, dropped {}, late {}, skipped to key frame {}, lost packets {}, bad {}, reconnects {}{}",
            s.width.unwrap_or(0),
            s.height.unwrap_or(0),
            ingest.decoded_rate.rate(),
            ingest.byte_rate.bits_per_second() / 1e3,
            c.decoded,
            c.dropped,
            c.late,
            c.skipped,
            c.lost_packets,
            c.bad,
            c.connects.saturating_sub(1),
            s.last_error.map(|e| format!("; last error: {e}")).unwrap_or_default()
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse() {
        assert_eq!(VideoUrl::parse("auto").unwrap(), VideoUrl::Auto);
        assert_eq!(
            VideoUrl::parse("rtsp://admin:p%40ss@192.168.144.25:8554/main.264").unwrap(),
            VideoUrl::Rtsp {
                url: "rtsp://192.168.144.25:8554/main.264".into(),
                username: Some("admin".into()),
                password: Some("p@ss".into()),
            }
        );
        assert_eq!(
            VideoUrl::parse("udp://0.0.0.0:5600").unwrap(),
            VideoUrl::Udp {
                bind: "0.0.0.0:5600".parse().unwrap()
            }
        );
        assert_eq!(
            VideoUrl::parse("udp://@:5600").unwrap(),
            VideoUrl::Udp {
                bind: "0.0.0.0:5600".parse().unwrap()
            }
        );
        assert!(matches!(
            VideoUrl::parse("/etc/cam.sdp").unwrap(),
            VideoUrl::Sdp { .. }
        ));
        assert!(matches!(
            VideoUrl::parse("http://127.0.0.1:8554/video.mjpg").unwrap(),
            VideoUrl::Http(_)
        ));
        for bad in [
            "ftp://x",
            "udp://host",
            "udp://:99999",
            "rtsp://",
            "rtsps://x/y",
        ] {
            assert!(VideoUrl::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn passwords_never_shown() {
        let u = VideoUrl::parse("rtsp://admin:secret@cam/x").unwrap();
        assert_eq!(u.display(), "rtsp://admin@cam/x");
        assert_eq!(redact("rtsp://a:secret@h:1/p"), "rtsp://a:***@h:1/p");
        let e = VideoUrl::parse("rtsps://a:secret@h/p")
            .unwrap_err()
            .to_string();
        assert!(!e.contains("secret"), "{e}");
    }

    #[test]
    fn backoff_doubles_and_caps() {
        assert_eq!(backoff(250, 2000, 0), Duration::from_millis(250));
        assert_eq!(backoff(250, 2000, 2), Duration::from_millis(1000));
        assert_eq!(backoff(250, 2000, 30), Duration::from_millis(2000));
    }
}
