//! Raw RTP H.264 over UDP (OpenIPC / wfb-ng links, GStreamer or ffmpeg
//! `udpsink`): listen on `udp://HOST:PORT` (a multicast `HOST` is joined),
//! read RTCP sender reports on `PORT + 1` when the sender sends them,
//! depacketise into access units and queue them for the decoder.
//!
//! After a lost packet the packets behind it are held for a short wait
//! while a NACK asks the sender to retransmit it (RFC 4585/4588, see
//! [`crate::video::rtp::feedback`]); a gap that is not filled in time is
//! given up, and a key frame is asked for (PLI) so the damage it leaves
//! ends at the sender's next IDR picture instead of its regular one.
//! Feedback goes from the RTCP socket to where the sender's RTCP comes
//! from (else to the RTP source's next port); senders that ignore it cost
//! nothing after a few requests.
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
use crate::video::rtp::feedback::{
    OwnedRtp, Resequencer, ResequencerStats, nack_packet, pli_packet, retransmitted_sequence,
};
use crate::video::rtp::sdp::SdpVideo;
use crate::video::rtp::{
    H264Depacketizer, RtpClock, RtpPacket, looks_like_h265, parse_rtp, parse_sender_report,
};
use crate::video::stream::{FeedbackParams, H264Params, H264Sink, SourceError};

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

/// Where the receive loop is with its feedback to the sender.
struct Feedback {
    reseq: Resequencer,
    /// Our RTCP SSRC and CNAME.
    own_ssrc: u32,
    cname: String,
    /// Where the sender's RTCP comes from (feedback goes back there), else
    /// the RTP source's next port.
    rtcp_from: Option<SocketAddr>,
    rtp_from: Option<SocketAddr>,
    /// The stream's payload type (the SDP's, else its first packet's).
    media_pt: Option<u8>,
    /// The retransmissions' payload type from the SDP.
    rtx_pt: Option<u8>,
    key_frame_interval: Option<Duration>,
    last_key_frame_request: Option<Instant>,
    /// A key frame request went to the guessed destination (the RTP
    /// source's next port) before the sender's RTCP showed where it
    /// listens: it is sent again there once known.
    key_frame_request_unconfirmed: bool,
    /// The resequencer's statistics as last added to the counters.
    sent: ResequencerStats,
    out: Vec<OwnedRtp>,
}

impl Feedback {
    fn new(params: &FeedbackParams, sdp: Option<&SdpVideo>, local: SocketAddr) -> Self {
        use std::hash::BuildHasher as _;
        let own_ssrc = std::collections::hash_map::RandomState::new().hash_one(local) as u32;
        Self {
            reseq: Resequencer::new(params.nack),
            own_ssrc,
            cname: format!("shotpilot@{}", local.ip()),
            rtcp_from: None,
            rtp_from: None,
            media_pt: sdp.map(|s| s.payload_type),
            rtx_pt: sdp.and_then(|s| s.rtx_payload_type),
            key_frame_interval: params.key_frame_interval,
            last_key_frame_request: None,
            key_frame_request_unconfirmed: false,
            sent: ResequencerStats::default(),
            out: Vec::new(),
        }
    }

    /// Where feedback goes: the sender's RTCP source, else the RTP
    /// source's next port (RFC 3550's convention).
    fn destination(&self) -> Option<SocketAddr> {
        self.rtcp_from.or_else(|| {
            self.rtp_from
                .map(|a| SocketAddr::new(a.ip(), a.port().wrapping_add(1)))
        })
    }

    /// Whether `pkt`, on another SSRC and payload type than the stream's
    /// (a retransmission stream, RFC 4588 SSRC multiplexing), is a
    /// retransmission: the SDP's rtx payload type, or without one a
    /// dynamic payload type naming a packet still waited for, with a
    /// timestamp between its neighbours' (so a FEC or other stream whose
    /// first bytes happen to match is not taken for one).
    fn is_retransmission(&self, pkt: &RtpPacket<'_>) -> bool {
        match self.rtx_pt {
            Some(pt) => pkt.payload_type == pt,
            None => {
                pkt.payload_type >= 96
                    && retransmitted_sequence(pkt)
                        .is_some_and(|s| self.reseq.wants_at(s, pkt.timestamp))
            }
        }
    }
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
    let mut fb = Feedback::new(&params.feedback, sdp.as_ref(), local);
    let mut depack = H264Depacketizer::new(sdp.map(|s| s.param_sets).unwrap_or_default());
    let mut clock = RtpClock::new(clock_rate);
    let read = Duration::from_millis(params.read_timeout_ms.max(1));
    let mut buf = vec![0u8; 65_536];
    let mut rbuf = vec![0u8; 2048];
    let mut last_packet: Option<Instant> = None;
    let mut last_lost = 0u64;
    let mut h265_votes = 0u32;
    let mut wrong_pt_logged = false;
    let mut other_stream_logged = false;
    loop {
        let rtcp_recv = async {
            match &rtcp {
                Some(s) => s.recv_from(&mut rbuf).await,
                None => std::future::pending().await,
            }
        };
        let deadline = fb.reseq.deadline();
        let wake = async {
            match deadline {
                Some(d) => tokio::time::sleep_until(tokio::time::Instant::from_std(d)).await,
                None => std::future::pending().await,
            }
        };
        let (n, from) = tokio::select! {
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
                Ok(Ok(r)) => r,
            },
            r = rtcp_recv => {
                if let Ok((n, from)) = r
                    && let Some((s, ntp, rtp)) = parse_sender_report(&rbuf[..n])
                {
                    if clock.ssrc().is_none_or(|c| c == s) {
                        let first = fb.rtcp_from.is_none();
                        fb.rtcp_from = Some(from);
                        if first {
                            tracing::debug!("video: the sender's RTCP comes from {from}: feedback goes there");
                            if std::mem::take(&mut fb.key_frame_request_unconfirmed)
                                && let Some(media) = clock.ssrc()
                            {
                                request_key_frame(&mut fb, &sock, rtcp.as_ref(), media, sink, from, crate::clock::now()).await;
                            }
                        }
                    }
                    if clock.sender_report_from(s, rtp, ntp) {
                        Counters::inc(&sink.ingest.counters.sender_reports);
                    }
                }
                continue;
            }
            _ = wake => {
                let now = crate::clock::now();
                fb.out.clear();
                fb.reseq.poll(now, &mut fb.out);
                deliver(&mut fb, &mut depack, &mut clock, sink, now, unix_now());
                send_feedback(&mut fb, &sock, rtcp.as_ref(), clock.ssrc(), sink, now).await;
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
        let stream = clock.ssrc();
        // A second stream beside the live one, on its own SSRC and payload
        // type: retransmissions (used when asked for), else not ours.
        let (owned, retransmission) = if let (Some(ssrc), Some(media_pt)) = (stream, fb.media_pt)
            && last_packet.is_some()
            && pkt.ssrc != ssrc
            && pkt.payload_type != media_pt
        {
            let orig = fb
                .is_retransmission(&pkt)
                .then(|| OwnedRtp::from_retransmission(&pkt, media_pt, ssrc))
                .flatten();
            match orig {
                Some(o) => (o, true),
                None => {
                    if !other_stream_logged && !fb.is_retransmission(&pkt) {
                        other_stream_logged = true;
                        tracing::info!(
                            "video: a second RTP stream on {local} (SSRC {:08x}, payload type {}) beside the video's: ignored",
                            pkt.ssrc,
                            pkt.payload_type
                        );
                    }
                    continue;
                }
            }
        } else {
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
            if last_packet.is_none() || stream != Some(pkt.ssrc) {
                if stream.is_some_and(|s| s != pkt.ssrc) {
                    tracing::info!(
                        "video: RTP sender on {local} restarted (new SSRC {:08x})",
                        pkt.ssrc
                    );
                }
                if clock.stream_from(pkt.ssrc) {
                    Counters::inc(&sink.ingest.counters.sender_reports);
                }
                fb.reseq.reset();
                fb.media_pt = Some(pkt.payload_type);
                sink.new_connection();
                sink.ingest.update_source(|s| {
                    s.connected = true;
                    s.last_error = None;
                });
            }
            last_packet = Some(received);
            fb.rtp_from = Some(from);
            (OwnedRtp::of(&pkt), false)
        };
        fb.out.clear();
        if retransmission {
            fb.reseq.retransmitted(owned, received, &mut fb.out);
        } else {
            fb.reseq.push(owned, received, &mut fb.out);
        }
        deliver(
            &mut fb,
            &mut depack,
            &mut clock,
            sink,
            received,
            received_unix,
        );
        let media = clock.ssrc();
        send_feedback(&mut fb, &sock, rtcp.as_ref(), media, sink, received).await;
        let lost = depack.stats().lost;
        if lost > last_lost {
            Counters::add(&sink.ingest.counters.lost_packets, lost - last_lost);
            last_lost = lost;
        }
    }
}

/// Depacketise what the resequencer released and queue the access units.
fn deliver(
    fb: &mut Feedback,
    depack: &mut H264Depacketizer,
    clock: &mut RtpClock,
    sink: &H264Sink,
    received: Instant,
    received_unix: f64,
) {
    for p in fb.out.drain(..) {
        for au in depack.push(&p.as_packet()) {
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
    }
}

/// Send the NACKs that are due, and a key frame request after a gap was
/// given up (at most one per `key_frame_interval`); count them.
async fn send_feedback(
    fb: &mut Feedback,
    sock: &UdpSocket,
    rtcp: Option<&UdpSocket>,
    stream: Option<u32>,
    sink: &H264Sink,
    now: Instant,
) {
    // Due NACKs are taken even when they cannot be sent, so that their
    // deadline moves on.
    let nacks = fb.reseq.due_nacks(now);
    let Some(media) = stream else { return };
    let stats = fb.reseq.stats();
    // Most packets change nothing: no request, no counter.
    if nacks.is_empty() && stats == fb.sent {
        return;
    }
    let pli = stats.given_up > fb.sent.given_up
        && fb.key_frame_interval.is_some_and(|every| {
            fb.last_key_frame_request
                .is_none_or(|t| now.saturating_duration_since(t) >= every)
        });
    let counters = &sink.ingest.counters;
    Counters::add(&counters.retransmit_asked, stats.asked - fb.sent.asked);
    Counters::add(
        &counters.retransmit_recovered,
        stats.recovered - fb.sent.recovered,
    );
    Counters::add(
        &counters.retransmit_wait_us,
        stats.recovery_us_total - fb.sent.recovery_us_total,
    );
    fb.sent = stats;
    if nacks.is_empty() && !pli {
        return;
    }
    let Some(to) = fb.destination() else { return };
    // From the RTCP socket, so a sender with symmetric RTCP knows us.
    let via = rtcp.unwrap_or(sock);
    if !nacks.is_empty() {
        let packet = nack_packet(fb.own_ssrc, media, &fb.cname, &nacks);
        if let Err(e) = via.send_to(&packet, to).await {
            tracing::debug!("video: NACK to {to}: {e}");
        }
    }
    if pli {
        tracing::debug!(
            "video: a lost packet was not retransmitted: key frame requested from {to}"
        );
        fb.key_frame_request_unconfirmed = fb.rtcp_from.is_none();
        request_key_frame(fb, sock, rtcp, media, sink, to, now).await;
    }
}

/// Ask `to` for a key frame of `media` (RTCP PLI) and count it.
async fn request_key_frame(
    fb: &mut Feedback,
    sock: &UdpSocket,
    rtcp: Option<&UdpSocket>,
    media: u32,
    sink: &H264Sink,
    to: SocketAddr,
    now: Instant,
) {
    fb.last_key_frame_request = Some(now);
    Counters::inc(&sink.ingest.counters.key_frame_requests);
    let packet = pli_packet(fb.own_ssrc, media, &fb.cname);
    if let Err(e) = rtcp.unwrap_or(sock).send_to(&packet, to).await {
        tracing::debug!("video: PLI to {to}: {e}");
    }
}
