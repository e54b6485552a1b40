//! Raw RTP H.264 over UDP (OpenIPC / wfb-ng links, GStreamer or ffmpeg
//! `udpsink`): listen on `udp://HOST:PORT` (a multicast `HOST` is joined),
//! read RTCP sender reports on `PORT + 1` when the sender sends them,
//! depacketise into access units and queue them for the decoder.
//!
//! There is no connection: the source counts as connected while packets
//! arrive, and a silence longer than the read timeout, or a new SSRC (the
//! sender restarted), makes the decoder wait for the next sync point.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use tokio::net::UdpSocket;
use tokio_util::sync::CancellationToken;

use crate::video::h264::{AccessUnit, H264Error};
use crate::video::live::{Counters, unix_now};
use crate::video::rtp::sdp::SdpVideo;
use crate::video::rtp::{
    H264Depacketizer, RtpClock, looks_like_h265, parse_rtp, parse_sender_report,
};
use crate::video::stream::{H264Params, H264Sink, SourceError};

async fn bind(addr: SocketAddr) -> Result<UdpSocket, SourceError> {
    let err = |e: std::io::Error| SourceError::Bind {
        addr,
        reason: e.to_string(),
    };
    if addr.ip().is_multicast() {
        let any = match addr {
            SocketAddr::V4(_) => {
                SocketAddr::new(std::net::Ipv4Addr::UNSPECIFIED.into(), addr.port())
            }
            SocketAddr::V6(_) => {
                SocketAddr::new(std::net::Ipv6Addr::UNSPECIFIED.into(), addr.port())
            }
        };
        let s = UdpSocket::bind(any).await.map_err(err)?;
        match addr.ip() {
            std::net::IpAddr::V4(g) => s
                .join_multicast_v4(g, std::net::Ipv4Addr::UNSPECIFIED)
                .map_err(err)?,
            std::net::IpAddr::V6(g) => s.join_multicast_v6(&g, 0).map_err(err)?,
        }
        Ok(s)
    } else {
        UdpSocket::bind(addr).await.map_err(err)
    }
}

/// How many ports 0 are tried for an RTP port whose next one is free too.
const PAIR_TRIES: usize = 64;

/// An RTP socket and, beside it (port + 1), its RTCP socket, bound before
/// the sender is told where to send: with both held, no other process can
/// take either port.
#[derive(Debug)]
pub struct RtpSockets {
    /// The RTP socket.
    pub rtp: std::net::UdpSocket,
    /// The RTCP socket on the next port (None: not bound; a raw camera link
    /// sends no RTCP).
    pub rtcp: Option<std::net::UdpSocket>,
}

impl RtpSockets {
    /// Binds a free RTP port on `ip` whose next port is free too (the
    /// kernel picks the RTP port; the pair is kept when the next one binds,
    /// else another is tried).
    pub fn bind_pair(ip: std::net::IpAddr) -> std::io::Result<Self> {
        let mut last = None;
        for _ in 0..PAIR_TRIES {
            let rtp = std::net::UdpSocket::bind(SocketAddr::new(ip, 0))?;
            let port = rtp.local_addr()?.port();
            let Some(next) = port.checked_add(1) else {
                continue;
            };
            match std::net::UdpSocket::bind(SocketAddr::new(ip, next)) {
                Ok(rtcp) => {
                    return Ok(Self {
                        rtp,
                        rtcp: Some(rtcp),
                    });
                }
                Err(e) => last = Some(e),
            }
        }
        Err(last.unwrap_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::AddrNotAvailable,
                "no RTP port with a free RTCP port beside it",
            )
        }))
    }

    /// The RTP socket's address.
    pub fn rtp_addr(&self) -> std::io::Result<SocketAddr> {
        self.rtp.local_addr()
    }
}

fn to_tokio(s: std::net::UdpSocket) -> std::io::Result<UdpSocket> {
    s.set_nonblocking(true)?;
    UdpSocket::from_std(s)
}

/// Receive RTP H.264 on `addr` until `cancel` fires. `sdp` (from an SDP
/// file) gives the payload type and parameter sets; without it any dynamic
/// payload type is taken as H.264 and an H.265 stream is recognised by its
/// NAL headers and refused. Port 0 (unicast): an RTP port the kernel picks
/// with a free RTCP port beside it ([`RtpSockets::bind_pair`]); the source's
/// URL then shows the port.
pub async fn run(
    addr: SocketAddr,
    sdp: Option<SdpVideo>,
    params: &H264Params,
    sink: &H264Sink,
    cancel: &CancellationToken,
) -> Result<(), SourceError> {
    let err = |e: std::io::Error| SourceError::Bind {
        addr,
        reason: e.to_string(),
    };
    if addr.port() == 0 && !addr.ip().is_multicast() {
        let pair = RtpSockets::bind_pair(addr.ip()).map_err(err)?;
        return run_on(pair, sdp, params, sink, cancel).await;
    }
    let sock = bind(addr).await?;
    let local = sock.local_addr().map_err(err)?;
    // RTCP beside it, when that port is free (raw camera links send none).
    let rtcp_addr = SocketAddr::new(local.ip(), local.port().wrapping_add(1));
    let rtcp = match UdpSocket::bind(rtcp_addr).await {
        Ok(s) => Some(s),
        Err(e) => {
            tracing::debug!("video: no RTCP listener on {rtcp_addr}: {e}");
            None
        }
    };
    receive(sock, rtcp, sdp, params, sink, cancel).await
}

/// [`run`] on sockets the caller has already bound.
pub async fn run_on(
    sockets: RtpSockets,
    sdp: Option<SdpVideo>,
    params: &H264Params,
    sink: &H264Sink,
    cancel: &CancellationToken,
) -> Result<(), SourceError> {
    let addr = sockets
        .rtp
        .local_addr()
        .unwrap_or_else(|_| SocketAddr::from(([0, 0, 0, 0], 0)));
    let err = |e: std::io::Error| SourceError::Bind {
        addr,
        reason: e.to_string(),
    };
    let sock = to_tokio(sockets.rtp).map_err(err)?;
    let rtcp = match sockets.rtcp {
        Some(s) => Some(to_tokio(s).map_err(err)?),
        None => None,
    };
    receive(sock, rtcp, sdp, params, sink, cancel).await
}

async fn receive(
    sock: UdpSocket,
    rtcp: Option<UdpSocket>,
    sdp: Option<SdpVideo>,
    params: &H264Params,
    sink: &H264Sink,
    cancel: &CancellationToken,
) -> Result<(), SourceError> {
    let local = sock.local_addr().map_err(|e| SourceError::Bind {
        addr: SocketAddr::from(([0, 0, 0, 0], 0)),
        reason: e.to_string(),
    })?;
    tracing::info!(%local, "video: listening for RTP H.264");
    sink.ingest
        .update_source(|s| s.url = format!("udp://{local}"));
    let payload_type = sdp.as_ref().map(|s| s.payload_type);
    let clock_rate = sdp.as_ref().map_or(90_000, |s| s.clock_rate);
    let mut depack = H264Depacketizer::new(sdp.map(|s| s.param_sets).unwrap_or_default());
    let mut clock = RtpClock::new(clock_rate);
    let read = Duration::from_millis(params.read_timeout_ms.max(1));
    let mut buf = vec![0u8; 65_536];
    let mut rbuf = vec![0u8; 2048];
    let mut last_packet: Option<Instant> = None;
    let mut last_lost = 0u64;
    let mut h265_votes = 0u32;
    let mut wrong_pt_logged = false;
    loop {
        let rtcp_recv = async {
            match &rtcp {
                Some(s) => s.recv_from(&mut rbuf).await.map(|(n, _)| n),
                None => std::future::pending().await,
            }
        };
        let n = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = tokio::time::timeout(read, sock.recv_from(&mut buf)) => match r {
                Err(_) => {
                    if last_packet.take().is_some() {
                        sink.error(format!("no RTP packets on {local} for {:.1} s", read.as_secs_f64()));
                    }
                    continue;
                }
                Ok(Err(e)) => {
                    sink.error(format!("UDP receive on {local}: {e}"));
                    tokio::time::sleep(Duration::from_millis(params.reconnect_min_ms.max(1))).await;
                    continue;
                }
                Ok(Ok((n, _))) => n,
            },
            r = rtcp_recv => {
                if let Ok(n) = r
                    && let Some((s, ntp, rtp)) = parse_sender_report(&rbuf[..n])
                    && clock.sender_report_from(s, rtp, ntp)
                {
                    Counters::inc(&sink.ingest.counters.sender_reports);
                }
                continue;
            }
        };
        let received = crate::clock::now();
        let received_unix = unix_now();
        let pkt = match parse_rtp(&buf[..n]) {
            Ok(p) => p,
            Err(e) => {
                Counters::inc(&sink.ingest.counters.bad);
                tracing::debug!("video: {e}");
                continue;
            }
        };
        if let Some(pt) = payload_type {
            if pkt.payload_type != pt {
                if !wrong_pt_logged {
                    wrong_pt_logged = true;
                    tracing::warn!(
                        "video: RTP payload type {} on {local}, the SDP says {pt}: ignored",
                        pkt.payload_type
                    );
                }
                continue;
            }
        } else if pkt.payload_type < 96 {
            Counters::inc(&sink.ingest.counters.bad);
            continue;
        } else if looks_like_h265(pkt.payload) {
            h265_votes += 1;
            if h265_votes >= 3 {
                return Err(SourceError::Codec(H264Error::UnsupportedCodec {
                    codec: "H.265 (HEVC)".into(),
                }));
            }
        }
        let ssrc = clock.ssrc();
        if last_packet.is_none() || ssrc != Some(pkt.ssrc) {
            if ssrc.is_some_and(|s| s != pkt.ssrc) {
                tracing::info!(
                    "video: RTP sender on {local} restarted (new SSRC {:08x})",
                    pkt.ssrc
                );
            }
            if clock.stream_from(pkt.ssrc) {
                Counters::inc(&sink.ingest.counters.sender_reports);
            }
            sink.new_connection();
            sink.ingest.update_source(|s| {
                s.connected = true;
                s.last_error = None;
            });
        }
        last_packet = Some(received);
        for au in depack.push(&pkt) {
            let capture = clock.capture_time(au.timestamp, received_unix);
            sink.push(AccessUnit {
                data: au.data,
                capture_time: Some(capture),
                received,
                received_unix,
                lost: au.lost,
                gaps: au.gaps,
            });
        }
        let lost = depack.stats().lost;
        if lost > last_lost {
            Counters::add(&sink.ingest.counters.lost_packets, lost - last_lost);
            last_lost = lost;
        }
    }
}
