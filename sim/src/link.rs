//! The autopilot's MAVLink link: byte transports from a URL, a MAVLink 1/2
//! frame parser over the byte stream, and a seeded "bad radio" between the
//! bytes and the parser.
//!
//! URLs (`--mavlink`):
//! - `udpin:ADDR:PORT`: listen on ADDR:PORT, reply to the last sender.
//! - `udpout:HOST:PORT`: send to HOST:PORT from an ephemeral port and read
//!   the replies there (what PX4 SITL does towards a GCS on 14550).
//! - `tcpin:ADDR:PORT`: accept one client at a time.
//! - `tcpout:HOST:PORT`: connect, reconnecting every second if refused.
//! - `serial:/dev/xxx:BAUD`: a serial port (a `socat` pty pair works).
//!
//! The bad radio ([`RadioParams`]) acts per direction on whole frames:
//! a frame is dropped with a probability, each byte is corrupted (XOR with
//! a random non-zero byte) with a rate, delivery is delayed by a latency,
//! and a bandwidth cap in baud (8N1: 10 bits per byte, so 57600 baud is
//! 5760 bytes/s) serialises frames on the air; frames that would wait more
//! than `max_queue_bytes` of backlog are dropped, as a radio's buffer
//! overflows. Uplink is ground -> vehicle, downlink vehicle -> ground; each
//! direction has its own cap (a full-duplex model). Incoming bytes are
//! framed (so whole frames can be dropped), passed through the radio, and
//! parsed again from the byte stream, so corruption is caught by the CRC
//! exactly as on a real link.

use std::collections::VecDeque;
use std::fmt;
use std::net::SocketAddr;
use std::str::FromStr;
use std::time::Duration;

use mavlink::dialects::common::MavMessage;
use mavlink::{MAVLinkV2MessageRaw, MavHeader, MavlinkVersion, Message, calculate_crc};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// Errors of the link.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The `--mavlink` URL could not be understood.
    #[error("bad MAVLink URL {url:?}: {reason}")]
    BadUrl {
        /// The URL given.
        url: String,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// A socket or device could not be opened.
    #[error("cannot open {what}: {source}")]
    Open {
        /// The endpoint.
        what: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A frame could not be decoded.
    #[error("undecodable frame (message id {msg_id}): {reason}")]
    Decode {
        /// The message id in the frame header.
        msg_id: u32,
        /// The parser's complaint.
        reason: String,
    },
}

/// Where the link's bytes go.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Endpoint {
    /// Listen on a UDP address; reply to the last sender.
    UdpIn(String),
    /// Send to a UDP address.
    UdpOut(String),
    /// Accept TCP connections on an address.
    TcpIn(String),
    /// Connect to a TCP address.
    TcpOut(String),
    /// A serial device and baud rate.
    Serial {
        /// Device path.
        path: String,
        /// Baud rate.
        baud: u32,
    },
}

impl fmt::Display for Endpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Endpoint::UdpIn(a) => write!(f, "udpin:{a}"),
            Endpoint::UdpOut(a) => write!(f, "udpout:{a}"),
            Endpoint::TcpIn(a) => write!(f, "tcpin:{a}"),
            Endpoint::TcpOut(a) => write!(f, "tcpout:{a}"),
            Endpoint::Serial { path, baud } => write!(f, "serial:{path}:{baud}"),
        }
    }
}

impl FromStr for Endpoint {
    type Err = LinkError;
    fn from_str(url: &str) -> Result<Self, LinkError> {
        let bad = |reason| LinkError::BadUrl {
            url: url.to_string(),
            reason,
        };
        let (scheme, rest) = url
            .split_once(':')
            .ok_or_else(|| bad("expected SCHEME:..."))?;
        let host_port = |rest: &str| -> Result<String, LinkError> {
            let (host, port) = rest
                .rsplit_once(':')
                .ok_or_else(|| bad("expected HOST:PORT"))?;
            if host.is_empty() {
                return Err(bad("empty host"));
            }
            port.parse::<u16>()
                .map_err(|_| bad("port is not a number 0-65535"))?;
            Ok(rest.to_string())
        };
        match scheme {
            "udpin" | "udp" => Ok(Endpoint::UdpIn(host_port(rest)?)),
            "udpout" => Ok(Endpoint::UdpOut(host_port(rest)?)),
            "tcpin" => Ok(Endpoint::TcpIn(host_port(rest)?)),
            "tcpout" | "tcp" => Ok(Endpoint::TcpOut(host_port(rest)?)),
            "serial" => {
                let (path, baud) = rest
                    .rsplit_once(':')
                    .ok_or_else(|| bad("expected serial:PATH:BAUD"))?;
                if path.is_empty() {
                    return Err(bad("empty device path"));
                }
                let baud = baud
                    .parse::<u32>()
                    .map_err(|_| bad("baud is not a number"))?;
                Ok(Endpoint::Serial {
                    path: path.to_string(),
                    baud,
                })
            }
            _ => Err(bad("scheme must be udpin, udpout, tcpin, tcpout or serial")),
        }
    }
}

/// One direction of the bad radio.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RadioDirParams {
    /// Probability of dropping a whole frame.
    pub drop: f64,
    /// Probability of corrupting each byte.
    pub corrupt: f64,
    /// Added one-way latency, s.
    pub latency_s: f64,
    /// Bandwidth cap in baud (8N1), None = unlimited.
    pub baud: Option<u32>,
    /// Largest backlog before frames are dropped, bytes (with a cap only).
    pub max_queue_bytes: usize,
}

impl Default for RadioDirParams {
    fn default() -> Self {
        Self {
            drop: 0.0,
            corrupt: 0.0,
            latency_s: 0.0,
            baud: None,
            max_queue_bytes: 4096,
        }
    }
}

/// The bad radio: uplink (ground -> vehicle) and downlink, and a seed.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RadioParams {
    /// Ground -> vehicle.
    pub up: RadioDirParams,
    /// Vehicle -> ground.
    pub down: RadioDirParams,
    /// Seed of the radio's randomness.
    pub seed: u64,
}

impl RadioParams {
    /// True when the radio changes nothing.
    pub fn is_perfect(&self) -> bool {
        self.up == RadioDirParams::default() && self.down == RadioDirParams::default()
    }
}

/// Counters of one radio direction.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RadioStats {
    /// Frames offered.
    pub frames_in: u64,
    /// Frames dropped at random.
    pub dropped: u64,
    /// Frames dropped because the backlog was full.
    pub overflowed: u64,
    /// Frames with at least one corrupted byte.
    pub corrupted: u64,
    /// Bytes delivered.
    pub bytes_out: u64,
}

/// One direction of the simulated radio, driven by a clock (seconds).
#[derive(Debug, Clone)]
pub struct RadioDir {
    p: RadioDirParams,
    rng: SmallRng,
    busy_until: f64,
    queue: VecDeque<(f64, Vec<u8>)>,
    stats: RadioStats,
}

impl RadioDir {
    /// A radio direction with its own seed.
    pub fn new(p: RadioDirParams, seed: u64) -> Self {
        Self {
            p,
            rng: SmallRng::seed_from_u64(seed),
            busy_until: 0.0,
            queue: VecDeque::new(),
            stats: RadioStats::default(),
        }
    }

    /// Offer one frame at time `now`.
    pub fn push(&mut self, now: f64, mut frame: Vec<u8>) {
        self.stats.frames_in += 1;
        if self.p.drop > 0.0 && self.rng.random::<f64>() < self.p.drop {
            self.stats.dropped += 1;
            return;
        }
        let start = self.busy_until.max(now);
        let airtime = match self.p.baud {
            Some(b) if b > 0 => frame.len() as f64 * 10.0 / f64::from(b),
            _ => 0.0,
        };
        if let Some(b) = self.p.baud
            && b > 0
        {
            let backlog_bytes = (start - now) * f64::from(b) / 10.0;
            if backlog_bytes + frame.len() as f64 > self.p.max_queue_bytes as f64 {
                self.stats.overflowed += 1;
                return;
            }
        }
        if self.p.corrupt > 0.0 {
            let mut hit = false;
            for b in frame.iter_mut() {
                if self.rng.random::<f64>() < self.p.corrupt {
                    *b ^= self.rng.random_range(1..=255u8);
                    hit = true;
                }
            }
            if hit {
                self.stats.corrupted += 1;
            }
        }
        self.busy_until = start + airtime;
        let deliver = self.busy_until + self.p.latency_s;
        self.queue.push_back((deliver, frame));
    }

    /// The next frame due by `now`.
    pub fn pop_ready(&mut self, now: f64) -> Option<Vec<u8>> {
        if self.queue.front().is_some_and(|(t, _)| *t <= now) {
            let (_, f) = self.queue.pop_front()?;
            self.stats.bytes_out += f.len() as u64;
            return Some(f);
        }
        None
    }

    /// When the next frame is due.
    pub fn next_due(&self) -> Option<f64> {
        self.queue.front().map(|(t, _)| *t)
    }

    /// Counters.
    pub fn stats(&self) -> RadioStats {
        self.stats
    }
}

/// Counters of a frame parser.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ParserStats {
    /// Frames found.
    pub frames: u64,
    /// Candidate frames rejected by their CRC.
    pub crc_errors: u64,
    /// Bytes skipped while looking for a frame start.
    pub skipped_bytes: u64,
}

/// Splits a byte stream into MAVLink 1 and 2 frames, checking each CRC with
/// the common dialect's CRC_EXTRA (frames of messages outside the common
/// dialect cannot be checked and are skipped).
#[derive(Debug, Default, Clone)]
pub struct FrameParser {
    buf: Vec<u8>,
    start: usize,
    stats: ParserStats,
}

const STX_V1: u8 = 0xFE;
const STX_V2: u8 = 0xFD;

impl FrameParser {
    /// An empty parser.
    pub fn new() -> Self {
        Self::default()
    }

    /// Counters.
    pub fn stats(&self) -> ParserStats {
        self.stats
    }

    /// Append received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.start > 0 && self.start * 2 > self.buf.len() {
            self.buf.drain(..self.start);
            self.start = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// The next complete, CRC-valid frame, if any (byte-stream mode: an
    /// incomplete candidate waits for more bytes).
    pub fn next_frame(&mut self) -> Option<Vec<u8>> {
        self.next(false)
    }

    /// Like [`FrameParser::next_frame`], but the buffer holds everything
    /// there will be (a UDP datagram, a radio delivery): an incomplete
    /// candidate is a false start and is skipped, so it cannot hide the
    /// frames behind it.
    pub fn next_frame_complete(&mut self) -> Option<Vec<u8>> {
        self.next(true)
    }

    fn next(&mut self, complete: bool) -> Option<Vec<u8>> {
        loop {
            let data = &self.buf[self.start..];
            let pos = data.iter().position(|&b| b == STX_V1 || b == STX_V2);
            let Some(pos) = pos else {
                self.stats.skipped_bytes += data.len() as u64;
                self.start = self.buf.len();
                return None;
            };
            self.stats.skipped_bytes += pos as u64;
            self.start += pos;
            let data = &self.buf[self.start..];
            let incomplete = |me: &mut Self| {
                if complete {
                    me.skip_one();
                    true
                } else {
                    false
                }
            };
            let (total, header_len, msg_id) = if data[0] == STX_V1 {
                if data.len() < 6 {
                    if incomplete(self) {
                        continue;
                    }
                    return None;
                }
                (6 + usize::from(data[1]) + 2, 6, u32::from(data[5]))
            } else {
                if data.len() < 3 {
                    if incomplete(self) {
                        continue;
                    }
                    return None;
                }
                let flags = data[2];
                if flags & !0x03 != 0 {
                    self.skip_one();
                    continue;
                }
                let hdr = if flags & 0x02 != 0 { 13 } else { 10 };
                if data.len() < hdr {
                    if incomplete(self) {
                        continue;
                    }
                    return None;
                }
                let sig = if flags & 0x01 != 0 { 13 } else { 0 };
                let id = u32::from_le_bytes([data[hdr - 3], data[hdr - 2], data[hdr - 1], 0]);
                (hdr + usize::from(data[1]) + 2 + sig, hdr, id)
            };
            // A message we do not know cannot be checked: treat it as a
            // false start (we could not decode it anyway).
            let Some(extra) = known_extra_crc(msg_id) else {
                self.skip_one();
                continue;
            };
            if data.len() < total {
                if incomplete(self) {
                    continue;
                }
                return None;
            }
            let payload_end = header_len + usize::from(data[1]);
            let crc = calculate_crc(&data[1..payload_end], extra);
            let ok = crc == u16::from_le_bytes([data[payload_end], data[payload_end + 1]]);
            if !ok {
                self.stats.crc_errors += 1;
                self.skip_one();
                continue;
            }
            let frame = data[..total].to_vec();
            self.start += total;
            self.stats.frames += 1;
            return Some(frame);
        }
    }

    fn skip_one(&mut self) {
        self.start += 1;
        self.stats.skipped_bytes += 1;
    }
}

fn known_extra_crc(msg_id: u32) -> Option<u8> {
    MavMessage::default_message_from_id(msg_id).map(|_| MavMessage::extra_crc(msg_id))
}

/// Decode one CRC-checked frame from [`FrameParser`].
pub fn decode_frame(frame: &[u8]) -> Result<(MavHeader, MavMessage, MavlinkVersion), LinkError> {
    let too_short = || LinkError::Decode {
        msg_id: 0,
        reason: "frame too short".into(),
    };
    if frame.first() == Some(&STX_V1) {
        if frame.len() < 8 {
            return Err(too_short());
        }
        let len = usize::from(frame[1]);
        let id = u32::from(frame[5]);
        let payload = frame.get(6..6 + len).ok_or_else(too_short)?;
        let msg = parse_payload(MavlinkVersion::V1, id, payload)?;
        let header = MavHeader {
            system_id: u32::from(frame[3]),
            component_id: frame[4],
            sequence: frame[2],
        };
        Ok((header, msg, MavlinkVersion::V1))
    } else {
        if frame.len() < 12 {
            return Err(too_short());
        }
        let len = usize::from(frame[1]);
        let sysid32 = frame[2] & 0x02 != 0;
        let hdr = if sysid32 { 13 } else { 10 };
        let id = u32::from_le_bytes([frame[hdr - 3], frame[hdr - 2], frame[hdr - 1], 0]);
        let system_id = if sysid32 {
            u32::from_le_bytes([frame[4], frame[5], frame[6], frame[7]])
        } else {
            u32::from(frame[5])
        };
        let component_id = frame[hdr - 4];
        let payload = frame.get(hdr..hdr + len).ok_or_else(too_short)?;
        let msg = parse_payload(MavlinkVersion::V2, id, payload)?;
        Ok((
            MavHeader {
                system_id,
                component_id,
                sequence: frame[4],
            },
            msg,
            MavlinkVersion::V2,
        ))
    }
}

/// Placeholder for a mission item's command the dialect does not know: a
/// reserved user command, which the autopilot refuses with
/// MAV_MISSION_UNSUPPORTED.
pub const UNKNOWN_COMMAND_PLACEHOLDER: u16 = 31014; // MAV_CMD_USER_5
/// Placeholder for a mission item's frame the dialect does not know: a
/// reserved frame, refused with MAV_MISSION_UNSUPPORTED_FRAME.
pub const UNKNOWN_FRAME_PLACEHOLDER: u8 = 19; // MAV_FRAME_RESERVED_19

/// Parse a payload. A MISSION_ITEM(_INT) whose command or frame is not in
/// the dialect (the crate cannot represent it) has the field replaced by a
/// reserved placeholder, so the autopilot can refuse the item with the
/// right MISSION_ACK code instead of never hearing of it.
fn parse_payload(
    version: MavlinkVersion,
    id: u32,
    payload: &[u8],
) -> Result<MavMessage, LinkError> {
    use mavlink::error::ParserError;
    const MISSION_ITEM: u32 = 39;
    const MISSION_ITEM_INT: u32 = 73;
    // Both layouts put the command at bytes 30-31 and the frame at 34.
    const COMMAND_OFFSET: usize = 30;
    const FRAME_OFFSET: usize = 34;
    let err = |e: ParserError| LinkError::Decode {
        msg_id: id,
        reason: e.to_string(),
    };
    match MavMessage::parse(version, id, payload) {
        Ok(m) => Ok(m),
        Err(ParserError::InvalidEnum { .. }) if id == MISSION_ITEM || id == MISSION_ITEM_INT => {
            let mut buf = [0u8; 40];
            let n = payload.len().min(buf.len()).max(FRAME_OFFSET + 1);
            let k = payload.len().min(buf.len());
            buf[..k].copy_from_slice(&payload[..k]);
            for _ in 0..3 {
                match MavMessage::parse(version, id, &buf[..n]) {
                    Ok(m) => return Ok(m),
                    Err(ParserError::InvalidEnum { enum_type, value }) => match enum_type {
                        "MavCmd" => buf[COMMAND_OFFSET..COMMAND_OFFSET + 2]
                            .copy_from_slice(&UNKNOWN_COMMAND_PLACEHOLDER.to_le_bytes()),
                        "MavFrame" => buf[FRAME_OFFSET] = UNKNOWN_FRAME_PLACEHOLDER,
                        _ => return Err(err(ParserError::InvalidEnum { enum_type, value })),
                    },
                    Err(e) => return Err(err(e)),
                }
            }
            Err(LinkError::Decode {
                msg_id: id,
                reason: "enum fields could not be repaired".into(),
            })
        }
        Err(e) => Err(err(e)),
    }
}

/// Encode a message as a MAVLink 2 frame.
pub fn encode_v2(header: MavHeader, msg: &MavMessage) -> Vec<u8> {
    let mut raw = MAVLinkV2MessageRaw::new();
    raw.serialize_message(header, msg);
    raw.raw_bytes().to_vec()
}

/// Everything the link needs.
#[derive(Debug, Clone)]
pub struct LinkParams {
    /// Where the bytes go.
    pub endpoint: Endpoint,
    /// The bad radio.
    pub radio: RadioParams,
    /// Our system id (outgoing headers).
    pub system_id: u8,
    /// Our component id (outgoing headers).
    pub component_id: u8,
}

/// Counters of a running link.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Uplink radio.
    pub up: RadioStats,
    /// Downlink radio.
    pub down: RadioStats,
    /// Parser after the uplink radio (CRC errors are corrupted frames).
    pub parser: ParserStats,
    /// Messages decoded and handed to the autopilot.
    pub received: u64,
    /// Messages handed to the link by the autopilot.
    pub sent: u64,
}

/// The app's handle on a running link.
#[derive(Debug)]
pub struct LinkHandle {
    /// Messages to send (the link fills in the header: the autopilot's
    /// component unless [`Outgoing::component`] says another).
    pub to_link: mpsc::Sender<Outgoing>,
    /// Messages received (after the radio and the parser).
    pub from_link: mpsc::Receiver<(MavHeader, MavMessage)>,
    /// Latest counters.
    pub stats: tokio::sync::watch::Receiver<LinkStats>,
    /// The bound address of a listening endpoint (`udpin:`, `tcpin:`; port
    /// 0 picks a free one), None for the others.
    pub local_addr: Option<SocketAddr>,
}

/// A message for the link to send.
#[derive(Debug, Clone)]
pub struct Outgoing {
    /// The sending component of the vehicle's system (None: the
    /// autopilot's, `LinkParams::component_id`).
    pub component: Option<u8>,
    /// The message.
    pub msg: MavMessage,
}

impl From<MavMessage> for Outgoing {
    fn from(msg: MavMessage) -> Self {
        Self {
            component: None,
            msg,
        }
    }
}

/// Raw transport: chunks in, chunks out.
struct Transport {
    rx: mpsc::Receiver<Vec<u8>>,
    tx: mpsc::Sender<Vec<u8>>,
    local: Option<SocketAddr>,
}

async fn open_transport(
    ep: &Endpoint,
    socket: Option<std::net::UdpSocket>,
    cancel: CancellationToken,
) -> Result<Transport, LinkError> {
    let (in_tx, in_rx) = mpsc::channel::<Vec<u8>>(256);
    let (out_tx, mut out_rx) = mpsc::channel::<Vec<u8>>(256);
    let open_err = |source| LinkError::Open {
        what: ep.to_string(),
        source,
    };
    let mut local = None;
    if socket.is_some() && !matches!(ep, Endpoint::UdpIn(_) | Endpoint::UdpOut(_)) {
        return Err(open_err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "a bound UDP socket needs a udpin: or udpout: endpoint",
        )));
    }
    match ep {
        Endpoint::UdpIn(addr) | Endpoint::UdpOut(addr) => {
            let listen = matches!(ep, Endpoint::UdpIn(_));
            let sock = match socket {
                Some(s) => {
                    s.set_nonblocking(true).map_err(open_err)?;
                    tokio::net::UdpSocket::from_std(s).map_err(open_err)?
                }
                None if listen => tokio::net::UdpSocket::bind(addr).await.map_err(open_err)?,
                None => tokio::net::UdpSocket::bind("0.0.0.0:0")
                    .await
                    .map_err(open_err)?,
            };
            if listen {
                local = sock.local_addr().ok();
            }
            let mut peer: Option<SocketAddr> = if listen {
                None
            } else {
                Some(
                    tokio::net::lookup_host(addr)
                        .await
                        .map_err(open_err)?
                        .next()
                        .ok_or_else(|| open_err(std::io::Error::other("no address")))?,
                )
            };
            tokio::spawn(async move {
                let mut buf = vec![0u8; 65536];
                loop {
                    tokio::select! {
                        _ = cancel.cancelled() => break,
                        r = sock.recv_from(&mut buf) => match r {
                            Ok((n, from)) => {
                                if listen { peer = Some(from); }
                                if in_tx.send(buf[..n].to_vec()).await.is_err() { break; }
                            }
                            Err(e) => {
                                // ICMP port unreachable shows up here on Linux: ignore.
                                tracing::debug!("udp recv: {e}");
                            }
                        },
                        out = out_rx.recv() => match out {
                            Some(bytes) => if let Some(p) = peer
                                && let Err(e) = sock.send_to(&bytes, p).await
                            {
                                tracing::debug!("udp send to {p}: {e}");
                            },
                            None => break,
                        },
                    }
                }
            });
        }
        Endpoint::TcpIn(addr) => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .map_err(open_err)?;
            local = listener.local_addr().ok();
            tokio::spawn(async move {
                loop {
                    let stream = tokio::select! {
                        _ = cancel.cancelled() => return,
                        r = listener.accept() => match r {
                            Ok((s, from)) => { tracing::info!("tcp client {from}"); s }
                            Err(e) => { tracing::warn!("accept: {e}"); continue; }
                        },
                        // Drain outgoing while nobody listens.
                        out = out_rx.recv() => { if out.is_none() { return; } continue; }
                    };
                    if !pump_stream(stream, &in_tx, &mut out_rx, &cancel).await {
                        return;
                    }
                }
            });
        }
        Endpoint::TcpOut(addr) => {
            let addr = addr.clone();
            tokio::spawn(async move {
                loop {
                    let stream = tokio::select! {
                        _ = cancel.cancelled() => return,
                        r = tokio::net::TcpStream::connect(&addr) => r,
                    };
                    match stream {
                        Ok(s) => {
                            if !pump_stream(s, &in_tx, &mut out_rx, &cancel).await {
                                return;
                            }
                        }
                        Err(e) => tracing::debug!("connect {addr}: {e}"),
                    }
                    tokio::select! {
                        _ = cancel.cancelled() => return,
                        _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                    }
                }
            });
        }
        Endpoint::Serial { path, baud } => {
            let port = serialport::new(path.as_str(), *baud)
                .timeout(Duration::from_millis(100))
                .open()
                .map_err(|e| open_err(std::io::Error::other(e.to_string())))?;
            let mut reader = port
                .try_clone()
                .map_err(|e| open_err(std::io::Error::other(e.to_string())))?;
            let mut writer = port;
            let c2 = cancel.clone();
            std::thread::spawn(move || {
                let mut buf = [0u8; 4096];
                while !c2.is_cancelled() {
                    match reader.read(&mut buf) {
                        Ok(0) => std::thread::sleep(Duration::from_millis(5)),
                        Ok(n) => {
                            if in_tx.blocking_send(buf[..n].to_vec()).is_err() {
                                break;
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                        Err(e) => {
                            tracing::warn!("serial read: {e}");
                            std::thread::sleep(Duration::from_millis(100));
                        }
                    }
                }
            });
            std::thread::spawn(move || {
                while let Some(bytes) = out_rx.blocking_recv() {
                    if let Err(e) = std::io::Write::write_all(&mut writer, &bytes) {
                        tracing::warn!("serial write: {e}");
                    }
                }
            });
        }
    }
    Ok(Transport {
        rx: in_rx,
        tx: out_tx,
        local,
    })
}

use std::io::Read as _;

/// Copy between a TCP stream and the channels until it closes. Returns
/// false when the link is shutting down.
async fn pump_stream(
    stream: tokio::net::TcpStream,
    in_tx: &mpsc::Sender<Vec<u8>>,
    out_rx: &mut mpsc::Receiver<Vec<u8>>,
    cancel: &CancellationToken,
) -> bool {
    let _ = stream.set_nodelay(true);
    let (mut r, mut w) = stream.into_split();
    let mut buf = vec![0u8; 8192];
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return false,
            n = r.read(&mut buf) => match n {
                Ok(0) | Err(_) => return true,
                Ok(n) => if in_tx.send(buf[..n].to_vec()).await.is_err() { return false; },
            },
            out = out_rx.recv() => match out {
                Some(bytes) => if w.write_all(&bytes).await.is_err() { return true; },
                None => return false,
            },
        }
    }
}

/// Open the endpoint and run the link (transport, radio, parser) as a task.
pub async fn spawn_link(
    params: LinkParams,
    cancel: CancellationToken,
) -> Result<LinkHandle, LinkError> {
    spawn_link_on(params, None, cancel).await
}

/// [`spawn_link`] on a UDP socket the caller has already bound (a
/// `udpin:`/`udpout:` endpoint then reads and writes through it instead of
/// binding its address), so a caller that bound port 0 knows the port
/// before the simulator starts.
pub async fn spawn_link_on(
    params: LinkParams,
    socket: Option<std::net::UdpSocket>,
    cancel: CancellationToken,
) -> Result<LinkHandle, LinkError> {
    let mut transport = open_transport(&params.endpoint, socket, cancel.clone()).await?;
    let local_addr = transport.local;
    let (to_link, mut app_rx) = mpsc::channel::<Outgoing>(1024);
    let (app_tx, from_link) = mpsc::channel::<(MavHeader, MavMessage)>(1024);
    let (stats_tx, stats) = tokio::sync::watch::channel(LinkStats::default());
    let radio = params.radio;
    let datagrams = matches!(params.endpoint, Endpoint::UdpIn(_) | Endpoint::UdpOut(_));
    tokio::spawn(async move {
        let t0 = tokio::time::Instant::now();
        let now = || t0.elapsed().as_secs_f64();
        let mut framer = FrameParser::new();
        let mut parser = FrameParser::new();
        let mut up = RadioDir::new(radio.up, radio.seed ^ 0x5550);
        let mut down = RadioDir::new(radio.down, radio.seed ^ 0xD0D0);
        // MAVLink sequence numbers count per sending component.
        let mut seqs = [0u8; 256];
        let mut st = LinkStats::default();
        let mut last_stats = 0.0;
        loop {
            let due = [up.next_due(), down.next_due()]
                .into_iter()
                .flatten()
                .fold(f64::INFINITY, f64::min);
            let sleep_for = if due.is_finite() {
                Duration::from_secs_f64((due - now()).max(0.0))
            } else {
                Duration::from_secs(3600)
            };
            tokio::select! {
                _ = cancel.cancelled() => break,
                chunk = transport.rx.recv() => {
                    let Some(chunk) = chunk else { break };
                    framer.push(&chunk);
                    let t = now();
                    while let Some(f) = if datagrams { framer.next_frame_complete() } else { framer.next_frame() } {
                        up.push(t, f);
                    }
                }
                msg = app_rx.recv() => {
                    let Some(Outgoing { component, msg }) = msg else { break };
                    let component_id = component.unwrap_or(params.component_id);
                    let seq = &mut seqs[usize::from(component_id)];
                    let header = MavHeader { system_id: u32::from(params.system_id), component_id, sequence: *seq };
                    *seq = seq.wrapping_add(1);
                    st.sent += 1;
                    down.push(now(), encode_v2(header, &msg));
                }
                _ = tokio::time::sleep(sleep_for) => {}
            }
            let t = now();
            while let Some(bytes) = up.pop_ready(t) {
                parser.push(&bytes);
                while let Some(frame) = parser.next_frame_complete() {
                    match decode_frame(&frame) {
                        Ok((h, m, _)) => {
                            st.received += 1;
                            if app_tx.try_send((h, m)).is_err() {
                                tracing::warn!("autopilot inbox full: message dropped");
                            }
                        }
                        Err(e) => tracing::debug!("{e}"),
                    }
                }
            }
            while let Some(bytes) = down.pop_ready(t) {
                if transport.tx.send(bytes).await.is_err() {
                    return;
                }
            }
            if t - last_stats > 0.5 {
                last_stats = t;
                st.up = up.stats();
                st.down = down.stats();
                st.parser = parser.stats();
                let _ = stats_tx.send(st);
            }
        }
    });
    Ok(LinkHandle {
        local_addr,
        to_link,
        from_link,
        stats,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{HEARTBEAT_DATA, MISSION_COUNT_DATA};

    fn hb() -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA::default())
    }
    fn header(seq: u8) -> MavHeader {
        MavHeader {
            system_id: 1,
            component_id: 1,
            sequence: seq,
        }
    }

    #[test]
    fn urls_parse() {
        assert_eq!(
            "udpin:0.0.0.0:14550".parse::<Endpoint>().ok(),
            Some(Endpoint::UdpIn("0.0.0.0:14550".into()))
        );
        assert_eq!(
            "udpout:127.0.0.1:14550".parse::<Endpoint>().ok(),
            Some(Endpoint::UdpOut("127.0.0.1:14550".into()))
        );
        assert_eq!(
            "tcpin:127.0.0.1:5760".parse::<Endpoint>().ok(),
            Some(Endpoint::TcpIn("127.0.0.1:5760".into()))
        );
        assert_eq!(
            "serial:/dev/pts/3:57600".parse::<Endpoint>().ok(),
            Some(Endpoint::Serial {
                path: "/dev/pts/3".into(),
                baud: 57600
            })
        );
        for bad in [
            "udpin:14550",
            "foo:1.2.3.4:5",
            "serial:/dev/x",
            "udpout:h:99999",
            "nocolon",
        ] {
            assert!(bad.parse::<Endpoint>().is_err(), "{bad}");
        }
    }

    #[test]
    fn parser_finds_v1_and_v2_frames_in_noise_and_split_chunks() {
        let a = encode_v2(header(1), &hb());
        let mut v1 = mavlink::MAVLinkV1MessageRaw::new();
        v1.serialize_message(header(2), &hb());
        let b = v1.raw_bytes().to_vec();
        let c = encode_v2(
            header(3),
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 7,
                ..Default::default()
            }),
        );
        let mut stream = vec![0x00, 0xFD, 0x13, 0xFE];
        stream.extend(&a);
        stream.extend([1, 2, 3]);
        stream.extend(&b);
        stream.extend(&c);
        let mut p = FrameParser::new();
        let mut got = Vec::new();
        for chunk in stream.chunks(5) {
            p.push(chunk);
            while let Some(f) = p.next_frame() {
                got.push(decode_frame(&f).expect("decode"));
            }
        }
        // The false v1 start (0xFE, length 0xFD) waits for bytes that never
        // come in stream mode; as a complete buffer it is skipped.
        while let Some(f) = p.next_frame_complete() {
            got.push(decode_frame(&f).expect("decode"));
        }
        assert_eq!(got.len(), 3);
        assert_eq!(got[0].0.sequence, 1);
        assert_eq!(got[1].2, MavlinkVersion::V1);
        assert!(matches!(got[2].1, MavMessage::MISSION_COUNT(ref m) if m.count == 7));
    }

    #[test]
    fn corrupted_frames_fail_the_crc_and_the_parser_resyncs() {
        let a = encode_v2(header(1), &hb());
        let mut bad = a.clone();
        bad[12] ^= 0x40;
        let mut p = FrameParser::new();
        p.push(&bad);
        p.push(&a);
        let f = p.next_frame().expect("good frame after the bad one");
        assert_eq!(f, a);
        assert!(p.next_frame().is_none());
        assert_eq!(p.stats().crc_errors, 1);
    }

    #[test]
    fn radio_drop_rate_is_seeded_and_close_to_the_setting() {
        let p = RadioDirParams {
            drop: 0.3,
            ..Default::default()
        };
        let run = |seed| {
            let mut r = RadioDir::new(p, seed);
            let mut n = 0;
            for i in 0..10_000 {
                r.push(i as f64, vec![0; 20]);
                while r.pop_ready(i as f64).is_some() {
                    n += 1;
                }
            }
            n
        };
        let n = run(7);
        assert_eq!(n, run(7));
        assert!((6800..=7200).contains(&n), "{n}");
    }

    #[test]
    fn radio_bandwidth_cap_serialises_frames_at_the_baud_rate() {
        // 57600 baud -> 5760 bytes/s: 100 frames of 57.6 bytes take 1 s.
        let p = RadioDirParams {
            baud: Some(57600),
            max_queue_bytes: 1 << 20,
            ..Default::default()
        };
        let mut r = RadioDir::new(p, 1);
        for _ in 0..100 {
            r.push(0.0, vec![0; 576]);
        }
        // 100 * 576 bytes = 57600 bytes = 10 s of air time.
        let mut last = 0.0;
        while let Some(t) = r.next_due() {
            last = t;
            r.pop_ready(t);
        }
        assert!((last - 10.0).abs() < 1e-9, "{last}");
        // A small queue overflows.
        let p = RadioDirParams {
            baud: Some(57600),
            max_queue_bytes: 2000,
            ..Default::default()
        };
        let mut r = RadioDir::new(p, 1);
        for _ in 0..10 {
            r.push(0.0, vec![0; 576]);
        }
        assert_eq!(r.stats().overflowed, 7);
    }

    #[test]
    fn radio_latency_and_corruption() {
        let p = RadioDirParams {
            latency_s: 0.2,
            corrupt: 0.01,
            ..Default::default()
        };
        let mut r = RadioDir::new(p, 3);
        let frame = encode_v2(header(0), &hb());
        let mut parser = FrameParser::new();
        let mut ok = 0;
        for i in 0..2000 {
            r.push(i as f64 * 0.01, frame.clone());
        }
        assert!(r.pop_ready(0.19).is_none());
        while let Some(t) = r.next_due() {
            let b = r.pop_ready(t).expect("due");
            parser.push(&b);
            while parser.next_frame_complete().is_some() {
                ok += 1;
            }
        }
        // P(frame of 21 bytes intact) = 0.99^21 = 0.81.
        let frac = f64::from(ok) / 2000.0;
        assert!((0.77..0.85).contains(&frac), "{frac}");
        assert_eq!(r.stats().corrupted as usize + ok as usize, 2000);
    }

    #[tokio::test]
    async fn udpin_link_on_a_socket_the_caller_bound() {
        let cancel = CancellationToken::new();
        let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
        let addr = socket.local_addr().expect("addr");
        let mut link = spawn_link_on(
            LinkParams {
                // The address is the socket's: the URL's is not bound.
                endpoint: Endpoint::UdpIn("127.0.0.1:9".into()),
                radio: RadioParams::default(),
                system_id: 1,
                component_id: 1,
            },
            Some(socket),
            cancel.clone(),
        )
        .await
        .expect("link");
        assert_eq!(link.local_addr, Some(addr));
        let peer = tokio::net::UdpSocket::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let hello = encode_v2(header(4), &hb());
        peer.send_to(&hello, addr).await.expect("send");
        let (h, m) = tokio::time::timeout(Duration::from_secs(10), link.from_link.recv())
            .await
            .expect("the link hears the peer")
            .expect("msg");
        assert_eq!(h.sequence, 4);
        assert!(matches!(m, MavMessage::HEARTBEAT(_)));
        // Replies go to the peer it heard.
        link.to_link.send(hb().into()).await.expect("send");
        let mut buf = [0u8; 512];
        let (n, from) = tokio::time::timeout(Duration::from_secs(10), peer.recv_from(&mut buf))
            .await
            .expect("the peer hears the link")
            .expect("recv");
        assert_eq!(from, addr);
        let mut p = FrameParser::new();
        p.push(&buf[..n]);
        let (h, _, _) = decode_frame(&p.next_frame().expect("frame")).expect("decode");
        assert_eq!(h.system_id, 1);
        cancel.cancel();
    }

    #[tokio::test]
    async fn udp_link_round_trip_with_a_peer_socket() {
        let cancel = CancellationToken::new();
        let peer = tokio::net::UdpSocket::bind("127.0.0.1:0")
            .await
            .expect("bind");
        let addr = peer.local_addr().expect("addr");
        let mut link = spawn_link(
            LinkParams {
                endpoint: Endpoint::UdpOut(addr.to_string()),
                radio: RadioParams::default(),
                system_id: 1,
                component_id: 1,
            },
            cancel.clone(),
        )
        .await
        .expect("link");
        link.to_link.send(hb().into()).await.expect("send");
        let mut buf = [0u8; 512];
        let (n, from) = tokio::time::timeout(Duration::from_secs(2), peer.recv_from(&mut buf))
            .await
            .expect("timeout")
            .expect("recv");
        let mut p = FrameParser::new();
        p.push(&buf[..n]);
        let (h, m, _) = decode_frame(&p.next_frame().expect("frame")).expect("decode");
        assert_eq!(h.system_id, 1);
        assert!(matches!(m, MavMessage::HEARTBEAT(_)));
        let reply = encode_v2(
            MavHeader {
                system_id: 255,
                component_id: 190,
                sequence: 9,
            },
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 3,
                target_system: 1,
                ..Default::default()
            }),
        );
        peer.send_to(&reply, from).await.expect("send");
        let (h, m) = tokio::time::timeout(Duration::from_secs(2), link.from_link.recv())
            .await
            .expect("timeout")
            .expect("msg");
        assert_eq!(h.system_id, 255);
        assert!(matches!(m, MavMessage::MISSION_COUNT(ref c) if c.count == 3));
        cancel.cancel();
    }

    #[tokio::test]
    async fn tcpin_link_with_a_client_and_a_bandwidth_cap() {
        let cancel = CancellationToken::new();
        let link = spawn_link(
            LinkParams {
                endpoint: Endpoint::TcpIn("127.0.0.1:0".into()),
                radio: RadioParams {
                    down: RadioDirParams {
                        baud: Some(9600),
                        max_queue_bytes: 1 << 20,
                        ..Default::default()
                    },
                    ..Default::default()
                },
                system_id: 1,
                component_id: 1,
            },
            cancel.clone(),
        )
        .await
        .expect("link");
        let bound = link.local_addr.expect("tcpin reports its bound address");
        let mut client = tokio::net::TcpStream::connect(bound)
            .await
            .expect("connect");
        tokio::time::sleep(Duration::from_millis(100)).await;
        // 48 heartbeats of 21 bytes = 1008 bytes: 1.05 s at 960 bytes/s.
        let t0 = tokio::time::Instant::now();
        for _ in 0..48 {
            link.to_link.send(hb().into()).await.expect("send");
        }
        let mut p = FrameParser::new();
        let mut n = 0;
        let mut buf = [0u8; 1024];
        while n < 48 {
            let k = tokio::time::timeout(Duration::from_secs(3), client.read(&mut buf))
                .await
                .expect("timeout")
                .expect("read");
            assert!(k > 0, "closed");
            p.push(&buf[..k]);
            while p.next_frame().is_some() {
                n += 1;
            }
        }
        let secs = t0.elapsed().as_secs_f64();
        assert!(
            (0.95..1.6).contains(&secs),
            "{secs} s for 1008 bytes at 9600 baud"
        );
        cancel.cancel();
    }

    #[test]
    fn mission_item_with_an_unknown_command_or_frame_decodes_to_placeholders() {
        use mavlink::dialects::common::{MISSION_ITEM_INT_DATA, MavCmd, MavFrame};
        let item = MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
            seq: 4,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            z: 12.0,
            ..Default::default()
        });
        let mut f = encode_v2(header(0), &item);
        // Patch the command to 9999 and the frame to 99, then fix the CRC.
        let hdr = 10;
        f[hdr + 30..hdr + 32].copy_from_slice(&9999u16.to_le_bytes());
        f[hdr + 34] = 99;
        let end = hdr + usize::from(f[1]);
        let crc = calculate_crc(&f[1..end], MavMessage::extra_crc(73));
        f[end..end + 2].copy_from_slice(&crc.to_le_bytes());
        let (_, m, _) = decode_frame(&f).expect("decodes");
        let MavMessage::MISSION_ITEM_INT(m) = m else {
            panic!("{m:?}")
        };
        assert_eq!(m.command as u32, u32::from(UNKNOWN_COMMAND_PLACEHOLDER));
        assert_eq!(m.frame as u32, u32::from(UNKNOWN_FRAME_PLACEHOLDER));
        assert_eq!((m.seq, m.z), (4, 12.0));
    }
}
