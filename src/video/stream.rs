//! What every H.264 network source (RTSP, raw RTP over UDP) shares: its
//! tunables, the sink that hands access units to the decode thread, the
//! errors, the reconnection backoff. [`crate::video::source`] chooses and
//! runs a source; [`crate::video::rtsp`] and [`crate::video::udp`] read one.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicU64;
use std::time::Duration;

use crate::video::decode_loop::DecodeParams;
use crate::video::h264::{self, AuQueue, H264Error};
use crate::video::live::Ingest;
use crate::video::rtp::sdp::SdpError;

/// Errors choosing or running a video source.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The URL names no source shotpilot can read.
    #[error("video url {url:?}: {reason}")]
    BadUrl {
        /// The URL (password removed).
        url: String,
        /// What is wrong.
        reason: String,
    },
    /// The SDP file could not be read.
    #[error("cannot read the SDP file {path}: {reason}")]
    ReadSdp {
        /// The file.
        path: PathBuf,
        /// The OS error.
        reason: String,
    },
    /// The SDP file is malformed.
    #[error("SDP file {path}: {source}")]
    Sdp {
        /// The file.
        path: PathBuf,
        /// The parse error.
        #[source]
        source: SdpError,
    },
    /// The stream's codec cannot be decoded.
    #[error(transparent)]
    Codec(#[from] H264Error),
    /// The UDP port could not be bound.
    #[error("cannot listen for RTP on {addr}: {reason}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The OS error.
        reason: String,
    },
    /// A thread could not be started.
    #[error("cannot start the H.264 decode thread: {0}")]
    Thread(String),
    /// `auto` found no stream.
    #[error("auto: {reason}")]
    Auto {
        /// What happened.
        reason: String,
    },
}

/// RTSP's RTP transport.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RtspTransport {
    /// RTP interleaved in the RTSP TCP connection (works through NAT and
    /// firewalls; the default).
    #[default]
    Tcp,
    /// RTP over separate UDP ports (lower latency on a clean LAN).
    Udp,
}

/// Tunables of the H.264 sources.
#[derive(Debug, Clone, PartialEq)]
pub struct H264Params {
    /// RTSP transport.
    pub transport: RtspTransport,
    /// RTSP user name when the URL has none.
    pub username: Option<String>,
    /// RTSP password when the URL has none.
    pub password: Option<String>,
    /// Connect (and RTSP setup) timeout, ms.
    pub connect_timeout_ms: u64,
    /// A stream silent this long is reopened, ms.
    pub read_timeout_ms: u64,
    /// First reconnect delay, ms (doubles per failure).
    pub reconnect_min_ms: u64,
    /// Largest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// The decode thread's tunables.
    pub decode: DecodeParams,
    /// RTP over UDP: what is asked of the sender after a loss.
    pub feedback: FeedbackParams,
}

/// RTP over UDP: NACK for retransmissions and key frame requests
/// (`[video] nack_wait_ms`, `key_frame_request_ms`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FeedbackParams {
    /// The resequencer's tunables (a zero wait: no NACK).
    pub nack: crate::video::rtp::feedback::NackParams,
    /// After a lost packet is given up, ask for a key frame (PLI), at most
    /// this often; `None`: never.
    pub key_frame_interval: Option<Duration>,
}

impl Default for H264Params {
    fn default() -> Self {
        Self {
            transport: RtspTransport::Tcp,
            username: None,
            password: None,
            connect_timeout_ms: 5_000,
            read_timeout_ms: 5_000,
            reconnect_min_ms: 250,
            reconnect_max_ms: 2_000,
            decode: DecodeParams::default(),
            feedback: FeedbackParams {
                key_frame_interval: Some(Duration::from_millis(1000)),
                ..Default::default()
            },
        }
    }
}

/// Reconnect delay after `failures` consecutive failures (exponential
/// from `min`, capped at `max`).
pub fn backoff(min_ms: u64, max_ms: u64, failures: u32) -> Duration {
    let ms = min_ms
        .saturating_mul(1u64 << failures.min(20))
        .min(max_ms.max(min_ms));
    Duration::from_millis(ms)
}

/// The shared parts every H.264 reader hands access units through.
#[derive(Debug, Clone)]
pub struct H264Sink {
    /// The ingest (counters, source info, frame slot).
    pub ingest: Arc<Ingest>,
    /// The queue to the decode thread.
    pub queue: Arc<AuQueue>,
    /// Bumped on each new connection (the decoder waits for a sync point).
    pub resets: Arc<AtomicU64>,
}

impl H264Sink {
    /// Queue one access unit (never waits on the decoder).
    pub fn push(&self, au: h264::AccessUnit) {
        use crate::video::live::Counters;
        let c = &self.ingest.counters;
        Counters::inc(&c.received);
        Counters::add(&c.bytes, au.data.len() as u64);
        self.ingest.received_rate.tick();
        self.ingest.byte_rate.add(au.data.len() as u64);
        let dropped = self.queue.push(au);
        if dropped > 0 {
            Counters::add(&c.late, dropped as u64);
            Counters::add(&c.dropped_undecoded, dropped as u64);
        }
    }

    /// A new connection starts.
    pub fn new_connection(&self) {
        use crate::video::live::Counters;
        self.resets
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        Counters::inc(&self.ingest.counters.connects);
    }

    /// Note an error for the status and the log (the log only when it
    /// differs from the previous one, so a dead camera does not flood it).
    pub fn error(&self, msg: String) {
        use crate::video::live::Counters;
        Counters::inc(&self.ingest.counters.errors);
        let mut changed = false;
        self.ingest.update_source(|s| {
            s.connected = false;
            if s.last_error.as_deref() != Some(msg.as_str()) {
                changed = true;
                s.last_error = Some(msg.clone());
            }
        });
        if changed {
            tracing::warn!("video: {msg}");
        } else {
            tracing::debug!("video: {msg}");
        }
    }
}

/// The operator's name for a codec as SDP or RTSP spell it.
pub fn codec_name(encoding: &str) -> String {
    match encoding.to_ascii_uppercase().as_str() {
        "H265" | "HEVC" => "H.265 (HEVC)".into(),
        "JPEG" => "Motion JPEG over RTP".into(),
        "MP2T" => "MPEG-TS".into(),
        other => other.to_owned(),
    }
}
