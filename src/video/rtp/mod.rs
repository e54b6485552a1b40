//! RTP for raw H.264 over UDP (RFC 3550, RFC 6184 packetisation mode 1):
//! the packet parser, the depacketiser that assembles access units and
//! counts lost packets, the RTP-clock-to-capture-time mapping, and
//! [`sdp`] for the session descriptions of such streams.
//!
//! RTSP streams are depacketised by `retina` instead (see
//! [`crate::video::rtsp`]); both hand Annex B access units to
//! [`crate::video::h264`].

pub mod feedback;
pub mod sdp;

use std::collections::VecDeque;

use crate::video::h264::push_annexb;

/// Errors of the RTP layer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RtpError {
    /// Shorter than its headers say.
    #[error("RTP packet of {len} bytes is shorter than its {needed}-byte header")]
    TooShort {
        /// The packet's length.
        len: usize,
        /// The header length it declares.
        needed: usize,
    },
    /// Not RTP version 2.
    #[error("RTP version {version} (expected 2)")]
    BadVersion {
        /// The version field.
        version: u8,
    },
    /// The padding count exceeds the payload.
    #[error("RTP padding of {padding} bytes exceeds the {payload}-byte payload")]
    BadPadding {
        /// Declared padding.
        padding: usize,
        /// Payload before removing it.
        payload: usize,
    },
    /// A payload this depacketiser does not handle.
    #[error("unsupported H.264 RTP payload: NAL unit type {nal_type}")]
    UnsupportedPayload {
        /// The payload's NAL unit type (25 STAP-B, 26/27 MTAP, 29 FU-B).
        nal_type: u8,
    },
    /// A malformed aggregation or fragmentation unit.
    #[error("malformed H.264 RTP payload: {reason}")]
    Malformed {
        /// What is wrong.
        reason: &'static str,
    },
}

/// One RTP packet, borrowed from its datagram.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RtpPacket<'a> {
    /// Marker bit (last packet of an access unit for H.264).
    pub marker: bool,
    /// Payload type.
    pub payload_type: u8,
    /// Sequence number.
    pub sequence: u16,
    /// RTP timestamp (90 kHz for video).
    pub timestamp: u32,
    /// Synchronisation source.
    pub ssrc: u32,
    /// The payload without padding.
    pub payload: &'a [u8],
}

/// Parse an RTP packet (header, CSRCs, extension and padding).
pub fn parse_rtp(buf: &[u8]) -> Result<RtpPacket<'_>, RtpError> {
    if buf.len() < 12 {
        return Err(RtpError::TooShort {
            len: buf.len(),
            needed: 12,
        });
    }
    let version = buf[0] >> 6;
    if version != 2 {
        return Err(RtpError::BadVersion { version });
    }
    let padding = buf[0] & 0x20 != 0;
    let extension = buf[0] & 0x10 != 0;
    let csrcs = usize::from(buf[0] & 0x0f);
    let mut off = 12 + 4 * csrcs;
    if extension {
        if buf.len() < off + 4 {
            return Err(RtpError::TooShort {
                len: buf.len(),
                needed: off + 4,
            });
        }
        let words = usize::from(u16::from_be_bytes([buf[off + 2], buf[off + 3]]));
        off += 4 + 4 * words;
    }
    if buf.len() < off {
        return Err(RtpError::TooShort {
            len: buf.len(),
            needed: off,
        });
    }
    let mut end = buf.len();
    if padding {
        let pad = usize::from(buf[end - 1]);
        if pad == 0 || pad > end - off {
            return Err(RtpError::BadPadding {
                padding: pad,
                payload: end - off,
            });
        }
        end -= pad;
    }
    Ok(RtpPacket {
        marker: buf[1] & 0x80 != 0,
        payload_type: buf[1] & 0x7f,
        sequence: u16::from_be_bytes([buf[2], buf[3]]),
        timestamp: u32::from_be_bytes([buf[4], buf[5], buf[6], buf[7]]),
        ssrc: u32::from_be_bytes([buf[8], buf[9], buf[10], buf[11]]),
        payload: &buf[off..end],
    })
}

/// An access unit as the depacketiser assembled it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DepacketizedAu {
    /// Annex B NAL units.
    pub data: Vec<u8>,
    /// The RTP timestamp of its packets.
    pub timestamp: u32,
    /// Packets lost since the previous access unit or within this one.
    pub lost: u32,
    /// Where among the access unit's NAL units packets went missing: `k`
    /// before unit `k`, the unit count at the end (a slice hit by the loss
    /// is left out whole). See [`crate::video::damage`].
    pub gaps: Vec<u32>,
}

/// Counters of the depacketiser.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct DepacketizerStats {
    /// Packets taken.
    pub packets: u64,
    /// Packets lost (sequence gaps).
    pub lost: u64,
    /// Packets arriving after a later one (reordered or duplicated): dropped.
    pub late: u64,
    /// Malformed or unsupported payloads.
    pub malformed: u64,
}

/// Assembles RFC 6184 packets (single NAL unit, STAP-A, FU-A) into Annex B
/// access units, ended by the marker bit or a new timestamp. A lost packet
/// marks the access unit it falls into (and, when between units, the next
/// one) as damaged; the decoder then waits for a sync point.
#[derive(Debug, Default)]
pub struct H264Depacketizer {
    cur: Vec<u8>,
    cur_ts: Option<u32>,
    cur_lost: u32,
    /// NAL units in `cur`.
    cur_nals: u32,
    /// Loss positions among them.
    cur_gaps: Vec<u32>,
    fu: Option<Vec<u8>>,
    last_seq: Option<u16>,
    ssrc: Option<u32>,
    /// Parameter sets (from the SDP) put before an IDR unit that lacks them.
    param_sets: Vec<Vec<u8>>,
    max_au_bytes: usize,
    stats: DepacketizerStats,
}

/// The largest access unit accepted, bytes (a 4K intra picture is well under).
pub const MAX_AU_BYTES: usize = 8 << 20;

impl H264Depacketizer {
    /// A depacketiser; `param_sets` (SPS, PPS from an SDP's
    /// `sprop-parameter-sets`) are inserted before IDR pictures sent without
    /// them.
    pub fn new(param_sets: Vec<Vec<u8>>) -> Self {
        Self {
            param_sets,
            max_au_bytes: MAX_AU_BYTES,
            ..Default::default()
        }
    }

    /// Counters so far.
    pub fn stats(&self) -> DepacketizerStats {
        self.stats
    }

    /// Count `n` lost packets at the current position of the unit.
    fn lose(&mut self, n: u32) {
        self.cur_lost += n;
        if self.cur_gaps.last() != Some(&self.cur_nals) {
            self.cur_gaps.push(self.cur_nals);
        }
    }

    fn finish(&mut self) -> Option<DepacketizedAu> {
        let ts = self.cur_ts.take()?;
        if self.fu.take().is_some() {
            // An unfinished fragment: its end was lost.
            self.lose(1);
        }
        let data = std::mem::take(&mut self.cur);
        let lost = std::mem::take(&mut self.cur_lost);
        let mut gaps = std::mem::take(&mut self.cur_gaps);
        self.cur_nals = 0;
        if data.is_empty() && lost == 0 {
            return None;
        }
        let (data, inserted) = self.with_param_sets(data);
        for g in &mut gaps {
            *g += inserted;
        }
        Some(DepacketizedAu {
            data,
            timestamp: ts,
            lost,
            gaps,
        })
    }

    /// The unit with the SDP's parameter sets put first when it is an IDR
    /// picture sent without them, and how many units were put.
    fn with_param_sets(&self, data: Vec<u8>) -> (Vec<u8>, u32) {
        if self.param_sets.is_empty() {
            return (data, 0);
        }
        let kind = crate::video::h264::AuKind::of(&data);
        if !kind.idr || (kind.sps && kind.pps) {
            return (data, 0);
        }
        let mut out = Vec::with_capacity(data.len() + 64);
        for ps in &self.param_sets {
            push_annexb(&mut out, ps);
        }
        out.extend_from_slice(&data);
        (out, self.param_sets.len() as u32)
    }

    fn add_nal(&mut self, nal: &[u8]) {
        if self.cur.len() + nal.len() + 4 > self.max_au_bytes {
            self.lose(1);
            self.stats.malformed += 1;
            return;
        }
        push_annexb(&mut self.cur, nal);
        self.cur_nals += 1;
    }

    /// Take one packet; returns the access units it completed (at most two:
    /// the previous one on a timestamp change, and this one on its marker).
    pub fn push(&mut self, pkt: &RtpPacket<'_>) -> Vec<DepacketizedAu> {
        let mut out = Vec::new();
        if self.ssrc != Some(pkt.ssrc) {
            // A new source (sender restarted): its numbering starts afresh.
            if self.ssrc.is_some() {
                out.extend(self.finish());
                self.lose(1);
            }
            self.ssrc = Some(pkt.ssrc);
            self.last_seq = None;
        }
        if let Some(last) = self.last_seq {
            let d = pkt.sequence.wrapping_sub(last);
            if d == 0 || d >= 0x8000 {
                self.stats.late += 1;
                return out;
            }
            if d > 1 {
                let lost = u32::from(d - 1);
                self.stats.lost += u64::from(lost);
                // The loss belongs to this unit if its timestamp continues,
                // else to both the unfinished one and the next.
                if self.cur_ts.is_some() && self.cur_ts != Some(pkt.timestamp) {
                    self.lose(lost);
                    out.extend(self.finish());
                }
                self.lose(lost);
                self.fu = None;
            }
        }
        if self.last_seq.is_none() && !starts_access_unit(pkt.payload) {
            // Joined mid-unit (or its first packets were lost): what came
            // before cannot be known, so the unit counts as damaged.
            self.lose(1);
        }
        self.last_seq = Some(pkt.sequence);
        self.stats.packets += 1;
        if self.cur_ts.is_some() && self.cur_ts != Some(pkt.timestamp) {
            out.extend(self.finish());
        }
        self.cur_ts = Some(pkt.timestamp);
        if let Err(e) = self.payload(pkt.payload) {
            tracing::debug!("RTP seq {}: {e}", pkt.sequence);
            self.stats.malformed += 1;
            self.lose(1);
            self.fu = None;
        }
        if pkt.marker {
            out.extend(self.finish());
        }
        out
    }

    fn payload(&mut self, p: &[u8]) -> Result<(), RtpError> {
        let Some(&hdr) = p.first() else {
            return Err(RtpError::Malformed {
                reason: "empty payload",
            });
        };
        if hdr & 0x80 != 0 {
            return Err(RtpError::Malformed {
                reason: "forbidden_zero_bit set",
            });
        }
        match hdr & 0x1f {
            1..=23 => {
                if self.fu.is_some() {
                    // A fragment was cut short.
                    self.fu = None;
                    self.lose(1);
                }
                self.add_nal(p);
                Ok(())
            }
            24 => {
                let mut rest = &p[1..];
                while !rest.is_empty() {
                    if rest.len() < 2 {
                        return Err(RtpError::Malformed {
                            reason: "STAP-A size truncated",
                        });
                    }
                    let n = usize::from(u16::from_be_bytes([rest[0], rest[1]]));
                    if n == 0 || rest.len() < 2 + n {
                        return Err(RtpError::Malformed {
                            reason: "STAP-A unit overruns the packet",
                        });
                    }
                    self.add_nal(&rest[2..2 + n]);
                    rest = &rest[2 + n..];
                }
                Ok(())
            }
            28 => {
                if p.len() < 2 {
                    return Err(RtpError::Malformed {
                        reason: "FU-A without its header",
                    });
                }
                let fh = p[1];
                let (start, end) = (fh & 0x80 != 0, fh & 0x40 != 0);
                if start && end {
                    return Err(RtpError::Malformed {
                        reason: "FU-A with both start and end bits",
                    });
                }
                if start {
                    if self.fu.is_some() {
                        self.lose(1);
                    }
                    let mut nal = Vec::with_capacity(p.len() * 4);
                    nal.push((hdr & 0xe0) | (fh & 0x1f));
                    nal.extend_from_slice(&p[2..]);
                    self.fu = Some(nal);
                } else if let Some(nal) = self.fu.as_mut() {
                    if nal.len() + p.len() > self.max_au_bytes {
                        self.fu = None;
                        return Err(RtpError::Malformed {
                            reason: "FU-A larger than the access-unit limit",
                        });
                    }
                    nal.extend_from_slice(&p[2..]);
                } else {
                    // A fragment without its start: the start was lost.
                    self.lose(1);
                    return Ok(());
                }
                if end && let Some(nal) = self.fu.take() {
                    self.add_nal(&nal);
                }
                Ok(())
            }
            t @ (25 | 26 | 27 | 29) => Err(RtpError::UnsupportedPayload { nal_type: t }),
            _ => Err(RtpError::Malformed {
                reason: "reserved NAL unit type",
            }),
        }
    }
}

/// Whether a payload can only open an access unit: an access unit
/// delimiter, a sequence parameter set, or an aggregation opening with one.
fn starts_access_unit(payload: &[u8]) -> bool {
    match payload.first().map(|b| b & 0x1f) {
        Some(7 | 9) => true,
        Some(24) => payload.get(3).is_some_and(|b| matches!(b & 0x1f, 7 | 9)),
        _ => false,
    }
}

/// Whether an RTP payload looks like H.265 (RFC 7798) rather than H.264:
/// H.265's two-byte NAL header has layer 0 / temporal id 1 (`xx 01`) and
/// types that read as invalid or data-partition types in H.264.
pub fn looks_like_h265(payload: &[u8]) -> bool {
    if payload.len() < 3 || payload[1] != 0x01 {
        return false;
    }
    let h265_type = (payload[0] >> 1) & 0x3f;
    let h264_type = payload[0] & 0x1f;
    // VPS, SPS, PPS, aggregation and fragmentation units of H.265 read as
    // H.264 types 0, 2, 4 (never sent by H.264 cameras).
    matches!(h265_type, 32..=34 | 48 | 49) && matches!(h264_type, 0 | 2 | 4)
}

/// Maps RTP timestamps to capture times (unix seconds): through the latest
/// RTCP sender report when there is one, else onto arrival times by the
/// smallest arrival-minus-RTP offset over a window (the least-delayed
/// packet bounds the capture time from above without the network jitter).
#[derive(Debug)]
pub struct RtpClock {
    clock_rate: f64,
    ext: Option<i64>,
    /// (extended RTP timestamp, unix seconds) from the latest sender report.
    sr: Option<(i64, f64)>,
    /// (arrival unix seconds, arrival - rtp seconds).
    offsets: VecDeque<(f64, f64)>,
    window_s: f64,
    /// The SSRC of the RTP stream being timed, once its first packet came.
    ssrc: Option<u32>,
    /// A sender report (ssrc, rtp, ntp) from a sender whose RTP has not
    /// come yet: RTCP and RTP arrive on two sockets read in either order,
    /// and a sender sends its first report right after its first picture.
    early: Option<(u32, u32, u64)>,
}

/// Seconds between the NTP epoch (1900) and the unix epoch (1970).
pub const NTP_UNIX_OFFSET_S: f64 = 2_208_988_800.0;

/// An NTP timestamp (32.32 fixed point since 1900) as unix seconds.
pub fn ntp_to_unix(ntp: u64) -> f64 {
    (ntp >> 32) as f64 + (ntp & 0xffff_ffff) as f64 / 4_294_967_296.0 - NTP_UNIX_OFFSET_S
}

impl RtpClock {
    /// A clock for `clock_rate` Hz (90 000 for video).
    pub fn new(clock_rate: u32) -> Self {
        Self {
            clock_rate: f64::from(clock_rate.max(1)),
            ext: None,
            sr: None,
            offsets: VecDeque::new(),
            window_s: 10.0,
            ssrc: None,
            early: None,
        }
    }

    /// Forget everything (a new stream).
    pub fn reset(&mut self) {
        self.ext = None;
        self.sr = None;
        self.offsets.clear();
        self.ssrc = None;
        self.early = None;
    }

    /// The RTP stream's packets come from `ssrc`. A sender other than the
    /// one timed so far (a restarted camera) starts the clock afresh; a
    /// sender report it sent before its first packet is taken now. Returns
    /// whether a report was taken.
    pub fn stream_from(&mut self, ssrc: u32) -> bool {
        if self.ssrc == Some(ssrc) {
            return false;
        }
        if self.ssrc.is_some() {
            let early = self.early.take();
            self.reset();
            self.early = early;
        }
        self.ssrc = Some(ssrc);
        match self.early.take() {
            Some((s, rtp, ntp)) if s == ssrc => {
                self.sender_report(rtp, ntp);
                true
            }
            _ => false,
        }
    }

    /// The SSRC of the RTP stream being timed, once its first packet came.
    pub fn ssrc(&self) -> Option<u32> {
        self.ssrc
    }

    /// Take an RTCP sender report from `ssrc`: at once when it is the
    /// stream's sender, kept for later when no RTP has come from it yet
    /// (see [`RtpClock::stream_from`]). Returns whether it was taken now.
    pub fn sender_report_from(&mut self, ssrc: u32, rtp: u32, ntp: u64) -> bool {
        if self.ssrc == Some(ssrc) {
            self.sender_report(rtp, ntp);
            true
        } else {
            self.early = Some((ssrc, rtp, ntp));
            false
        }
    }

    /// Extend a 32-bit timestamp to 64 bits near the previous one.
    fn extend(&mut self, ts: u32) -> i64 {
        let e = match self.ext {
            None => i64::from(ts),
            Some(prev) => {
                let d = i64::from(ts.wrapping_sub(prev as u32) as i32);
                prev + d
            }
        };
        self.ext = Some(e);
        e
    }

    fn extend_near(&self, ts: u32) -> i64 {
        match self.ext {
            None => i64::from(ts),
            Some(prev) => prev + i64::from(ts.wrapping_sub(prev as u32) as i32),
        }
    }

    /// Take an RTCP sender report: `rtp` was the RTP clock at wall time
    /// `ntp` (NTP format).
    pub fn sender_report(&mut self, rtp: u32, ntp: u64) {
        let e = self.extend_near(rtp);
        self.sr = Some((e, ntp_to_unix(ntp)));
    }

    /// Whether a sender report was seen.
    pub fn has_sender_report(&self) -> bool {
        self.sr.is_some()
    }

    /// The capture time of a picture with RTP timestamp `ts` whose last
    /// packet arrived at `arrival_unix`.
    pub fn capture_time(&mut self, ts: u32, arrival_unix: f64) -> f64 {
        let e = self.extend(ts);
        let rtp_s = e as f64 / self.clock_rate;
        let off = arrival_unix - rtp_s;
        self.offsets.push_back((arrival_unix, off));
        while self
            .offsets
            .front()
            .is_some_and(|f| arrival_unix - f.0 > self.window_s)
        {
            self.offsets.pop_front();
        }
        if let Some((sr_e, sr_unix)) = self.sr {
            return sr_unix + (e - sr_e) as f64 / self.clock_rate;
        }
        let best = self
            .offsets
            .iter()
            .map(|x| x.1)
            .fold(f64::INFINITY, f64::min);
        rtp_s + best
    }
}

/// Parse an RTCP compound packet for a sender report: (ssrc, NTP
/// timestamp, RTP timestamp).
pub fn parse_sender_report(buf: &[u8]) -> Option<(u32, u64, u32)> {
    rtcp_packets(buf)
        .find(|p| p[1] == 200 && p.len() >= 28)
        .map(|p| {
            let ssrc = u32::from_be_bytes([p[4], p[5], p[6], p[7]]);
            let ntp = u64::from_be_bytes([p[8], p[9], p[10], p[11], p[12], p[13], p[14], p[15]]);
            let rtp = u32::from_be_bytes([p[16], p[17], p[18], p[19]]);
            (ssrc, ntp, rtp)
        })
}

/// The packets of a compound RTCP packet (RFC 3550 section 6.1), each
/// with its header, in order; the walk ends at the first one that is not
/// version 2 or runs past the buffer.
pub fn rtcp_packets(buf: &[u8]) -> impl Iterator<Item = &[u8]> {
    let mut rest = buf;
    std::iter::from_fn(move || {
        if rest.len() < 4 || rest[0] >> 6 != 2 {
            return None;
        }
        let len = (usize::from(u16::from_be_bytes([rest[2], rest[3]])) + 1) * 4;
        let p = rest.get(..len)?;
        rest = &rest[len..];
        Some(p)
    })
}

/// Packetise one Annex B access unit as RFC 6184 mode 1 RTP packets of at
/// most `mtu` bytes: parameter sets aggregated in one STAP-A, NAL units
/// that fit sent whole, larger ones as FU-A fragments; the marker bit on
/// the last packet. `seq` is advanced per packet.
pub fn packetize_h264(
    au: &[u8],
    mtu: usize,
    payload_type: u8,
    ssrc: u32,
    seq: &mut u16,
    timestamp: u32,
) -> Vec<Vec<u8>> {
    let mtu = mtu.max(12 + 3 + 1);
    let max_payload = mtu - 12;
    let nals = crate::video::h264::annexb_units(au);
    let mut payloads: Vec<Vec<u8>> = Vec::new();
    let mut i = 0;
    while i < nals.len() {
        // Aggregate a run of small parameter-set/SEI units.
        let mut agg: Vec<&[u8]> = Vec::new();
        let mut size = 1;
        while i + agg.len() < nals.len() {
            let n = nals[i + agg.len()];
            let t = n.first().map_or(0, |b| b & 0x1f);
            if !matches!(t, 6..=9) || size + 2 + n.len() > max_payload {
                break;
            }
            size += 2 + n.len();
            agg.push(n);
        }
        if agg.len() >= 2 {
            let nri = agg.iter().map(|n| n[0] & 0x60).max().unwrap_or(0);
            let mut p = vec![nri | 24];
            for n in &agg {
                p.extend_from_slice(&(n.len() as u16).to_be_bytes());
                p.extend_from_slice(n);
            }
            payloads.push(p);
            i += agg.len();
            continue;
        }
        let nal = nals[i];
        i += 1;
        if nal.len() <= max_payload {
            payloads.push(nal.to_vec());
            continue;
        }
        let (hdr, body) = (nal[0], &nal[1..]);
        let chunk = max_payload - 2;
        let count = body.len().div_ceil(chunk);
        for (k, part) in body.chunks(chunk).enumerate() {
            let mut fu = (hdr & 0x1f) & 0x1f;
            if k == 0 {
                fu |= 0x80;
            }
            if k + 1 == count {
                fu |= 0x40;
            }
            let mut p = vec![(hdr & 0xe0) | 28, fu];
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
            pkt.push(0x80);
            pkt.push(if k == last { 0x80 } else { 0 } | (payload_type & 0x7f));
            pkt.extend_from_slice(&seq.to_be_bytes());
            pkt.extend_from_slice(&timestamp.to_be_bytes());
            pkt.extend_from_slice(&ssrc.to_be_bytes());
            pkt.extend_from_slice(&p);
            *seq = seq.wrapping_add(1);
            pkt
        })
        .collect()
}
