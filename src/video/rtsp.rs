//! RTSP H.264 client on `retina`: DESCRIBE (with digest or basic
//! credentials), SETUP of the video stream over TCP-interleaved or UDP RTP,
//! PLAY, then whole access units (Annex B, parameter sets before each key
//! frame) into the decode queue. RTCP sender reports map the RTP clock to
//! capture times. Connection failures, server restarts and silent streams
//! reconnect with backoff; a codec other than H.264 stops with a reason.

use std::time::Duration;

use futures_util::StreamExt;
use retina::client::{
    Credentials, PlayOptions, Session, SessionGroup, SessionOptions, SetupOptions,
    TcpTransportOptions, Transport, UdpTransportOptions,
};
use retina::codec::{CodecItem, FrameFormat};
use tokio_util::sync::CancellationToken;

use crate::video::h264::{AccessUnit, H264Error};
use crate::video::live::unix_now;
use crate::video::rtp::RtpClock;
use crate::video::stream::{H264Params, H264Sink, RtspTransport, SourceError, backoff, codec_name};

/// Errors of one RTSP session.
#[derive(Debug, thiserror::Error)]
pub enum RtspError {
    /// The server answered 401: the credentials are missing or wrong.
    #[error(
        "the RTSP server refused the credentials (401 Unauthorized): check the user name and password in [video] url or [video] username/password"
    )]
    Unauthorized,
    /// The server answered 404.
    #[error(
        "the RTSP server has no stream at this path (404 Not Found): check the path in [video] url"
    )]
    NotFound,
    /// Any other failure of the RTSP exchange or the connection.
    #[error("RTSP: {0}")]
    Protocol(String),
    /// The presentation has no video stream.
    #[error("the RTSP presentation has no video stream")]
    NoVideo,
    /// The stream's codec cannot be decoded.
    #[error(transparent)]
    Codec(#[from] H264Error),
    /// No data within the read timeout.
    #[error("no video data for {seconds:.1} s")]
    Silent {
        /// The timeout.
        seconds: f64,
    },
    /// Connecting took longer than the connect timeout.
    #[error("no RTSP answer within {seconds:.1} s")]
    ConnectTimeout {
        /// The timeout.
        seconds: f64,
    },
    /// The server ended the stream.
    #[error("the RTSP server ended the stream")]
    Ended,
}

impl From<retina::Error> for RtspError {
    fn from(e: retina::Error) -> Self {
        match e.status_code() {
            Some(401) => Self::Unauthorized,
            Some(404) => Self::NotFound,
            _ => Self::Protocol(first_line(&e.to_string())),
        }
    }
}

fn first_line(s: &str) -> String {
    s.lines().next().unwrap_or("").to_owned()
}

/// Run the RTSP client until `cancel` fires: reconnect with backoff after
/// each failure; return only for a codec that cannot be decoded.
pub async fn run(
    url: &str,
    creds: Option<(String, String)>,
    params: &H264Params,
    sink: &H264Sink,
    cancel: &CancellationToken,
) -> Result<(), SourceError> {
    let parsed = url::Url::parse(url).map_err(|e| SourceError::BadUrl {
        url: url.to_owned(),
        reason: e.to_string(),
    })?;
    let creds = creds.map(|(username, password)| Credentials { username, password });
    let group = std::sync::Arc::new(SessionGroup::default());
    let mut failures = 0u32;
    tracing::info!(url, transport = ?params.transport, "video: RTSP source");
    loop {
        let r = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = session(&parsed, creds.clone(), params, sink, &group, cancel, &mut failures) => r,
        };
        match r {
            Ok(()) => return Ok(()),
            Err(RtspError::Codec(e)) => {
                tracing::error!("video: {e}");
                return Err(SourceError::Codec(e));
            }
            Err(e) => sink.error(e.to_string()),
        }
        let wait = backoff(params.reconnect_min_ms, params.reconnect_max_ms, failures);
        failures = failures.saturating_add(1);
        tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            _ = tokio::time::sleep(wait) => {}
        }
    }
}

async fn session(
    url: &url::Url,
    creds: Option<Credentials>,
    params: &H264Params,
    sink: &H264Sink,
    group: &std::sync::Arc<SessionGroup>,
    cancel: &CancellationToken,
    failures: &mut u32,
) -> Result<(), RtspError> {
    let connect = Duration::from_millis(params.connect_timeout_ms.max(1));
    let timed = |d: Duration| RtspError::ConnectTimeout {
        seconds: d.as_secs_f64(),
    };
    let opts = SessionOptions::default()
        .creds(creds)
        .user_agent(format!("shotpilot/{}", env!("CARGO_PKG_VERSION")))
        .session_group(group.clone());
    let mut described = tokio::time::timeout(connect, Session::describe(url.clone(), opts))
        .await
        .map_err(|_| timed(connect))??;
    let vi = described
        .streams()
        .iter()
        .position(|s| s.media() == "video")
        .ok_or(RtspError::NoVideo)?;
    let stream = &described.streams()[vi];
    let encoding = stream.encoding_name().to_owned();
    let clock_rate = stream.clock_rate_hz();
    if !encoding.eq_ignore_ascii_case("h264") {
        return Err(RtspError::Codec(H264Error::UnsupportedCodec {
            codec: codec_name(&encoding),
        }));
    }
    let transport = match params.transport {
        RtspTransport::Tcp => Transport::Tcp(TcpTransportOptions::default()),
        RtspTransport::Udp => Transport::Udp(UdpTransportOptions::default()),
    };
    tokio::time::timeout(
        connect,
        described.setup(
            vi,
            SetupOptions::default()
                .transport(transport)
                .frame_format(FrameFormat::SIMPLE),
        ),
    )
    .await
    .map_err(|_| timed(connect))??;
    let playing = tokio::time::timeout(
        connect,
        described.play(
            PlayOptions::default()
                .initial_timestamp(retina::client::InitialTimestampPolicy::Permissive)
                .unknown_rtcp_ssrc(retina::client::UnknownRtcpSsrcPolicy::DropPackets),
        ),
    )
    .await
    .map_err(|_| timed(connect))??;
    let mut demuxed = playing.demuxed()?;
    sink.new_connection();
    sink.ingest.update_source(|s| {
        s.connected = true;
        s.last_error = None;
    });
    tracing::info!(url = %url, "video: RTSP playing (H.264, clock {clock_rate} Hz)");
    let mut clock = RtpClock::new(clock_rate);
    let read = Duration::from_millis(params.read_timeout_ms.max(1));
    let mut got_frame = false;
    loop {
        let item = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = tokio::time::timeout(read, demuxed.next()) => r,
        };
        let item = match item {
            Err(_) => {
                return Err(RtspError::Silent {
                    seconds: read.as_secs_f64(),
                });
            }
            Ok(None) => return Err(RtspError::Ended),
            Ok(Some(Err(e))) => return Err(e.into()),
            Ok(Some(Ok(item))) => item,
        };
        match item {
            CodecItem::VideoFrame(f) => {
                if !got_frame {
                    got_frame = true;
                    *failures = 0;
                }
                let received = f.end_ctx().received();
                // retina stamps packets with the system's clock.
                let arrival = unix_now() - received.elapsed().as_secs_f64();
                let lost = u32::from(f.loss());
                if lost > 0 {
                    crate::video::live::Counters::add(
                        &sink.ingest.counters.lost_packets,
                        u64::from(lost),
                    );
                }
                let ts = f.timestamp().timestamp();
                let capture = clock.capture_time(ts as u32, arrival);
                sink.push(AccessUnit {
                    data: f.into_data(),
                    capture_time: Some(capture),
                    received,
                    received_unix: arrival,
                    lost,
                    // retina says how many packets a frame lost, not where:
                    // the whole picture counts as damaged.
                    gaps: Vec::new(),
                });
            }
            CodecItem::Rtcp(pkt) => {
                for p in pkt.pkts() {
                    if let Ok(Some(sr)) = p.as_sender_report() {
                        clock.sender_report(sr.rtp_timestamp(), sr.ntp_timestamp().0);
                        crate::video::live::Counters::inc(&sink.ingest.counters.sender_reports);
                    }
                }
            }
            _ => {}
        }
    }
}
