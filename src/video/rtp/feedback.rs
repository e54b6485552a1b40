//! Asking the sender for what the link lost: RTCP feedback (RFC 4585's
//! generic NACK and picture loss indication, sent in RFC 3550 compound
//! packets) and RTP retransmission (RFC 4588: the lost packet again, on its
//! own payload type and SSRC, its original sequence number in the first two
//! bytes of the payload).
//!
//! The [`Resequencer`] stands between the socket and the depacketiser. With
//! no loss it passes every packet straight through. After a gap it holds
//! the packets behind it, names the missing ones for a NACK, and releases
//! them in order as soon as the retransmissions fill the gap, or gives the
//! gap up as lost after [`NackParams::wait`] (the depacketiser then sees
//! the gap, as without feedback). A sender that never retransmits is
//! noticed after [`NackParams::unanswered_limit`] requests: gaps are then
//! given up at once (no added latency), and one gap in
//! [`NackParams::probe_every`] is still asked for, so a sender that starts
//! answering is used again.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use super::{RtpPacket, rtcp_packets};

/// An RTP packet with its payload owned, as the resequencer holds it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OwnedRtp {
    /// Marker bit.
    pub marker: bool,
    /// Payload type.
    pub payload_type: u8,
    /// Sequence number (the original one for a retransmission).
    pub sequence: u16,
    /// RTP timestamp.
    pub timestamp: u32,
    /// Synchronisation source (the original stream's for a retransmission).
    pub ssrc: u32,
    /// The payload.
    pub payload: Vec<u8>,
}

impl OwnedRtp {
    /// Copy a parsed packet.
    pub fn of(p: &RtpPacket<'_>) -> Self {
        Self {
            marker: p.marker,
            payload_type: p.payload_type,
            sequence: p.sequence,
            timestamp: p.timestamp,
            ssrc: p.ssrc,
            payload: p.payload.to_vec(),
        }
    }

    /// The original packet a retransmission (RFC 4588 §4) carries: its
    /// sequence number from the payload's first two bytes, the original
    /// stream's payload type and SSRC. `None` when the payload is shorter
    /// than the sequence number.
    pub fn from_retransmission(p: &RtpPacket<'_>, payload_type: u8, ssrc: u32) -> Option<Self> {
        Some(Self {
            marker: p.marker,
            payload_type,
            sequence: retransmitted_sequence(p)?,
            timestamp: p.timestamp,
            ssrc,
            payload: p.payload[2..].to_vec(),
        })
    }

    /// Borrow as a parsed packet.
    pub fn as_packet(&self) -> RtpPacket<'_> {
        RtpPacket {
            marker: self.marker,
            payload_type: self.payload_type,
            sequence: self.sequence,
            timestamp: self.timestamp,
            ssrc: self.ssrc,
            payload: &self.payload,
        }
    }
}

/// The original sequence number a retransmission names (its payload's
/// first two bytes), `None` for a payload too short to carry one.
pub fn retransmitted_sequence(p: &RtpPacket<'_>) -> Option<u16> {
    p.payload.get(..2).map(|b| u16::from_be_bytes([b[0], b[1]]))
}

/// The resequencer's tunables (`[video] nack_wait_ms`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NackParams {
    /// How long the packets behind a gap are held for its retransmission
    /// before the gap is given up as lost. Zero: no NACK and no holding.
    pub wait: Duration,
    /// NACKs per missing packet: the first at once, the others spread
    /// evenly over the wait (a retransmission can be lost too).
    pub tries: u32,
    /// A gap longer than this many packets (an outage, or a sender that
    /// restarted its numbering) is not asked for: it is given up at once.
    pub max_gap: u16,
    /// Packets held at most; beyond, the oldest gap is given up.
    pub max_held: usize,
    /// Packets asked for without one retransmission arriving, after which
    /// the sender is taken not to retransmit.
    pub unanswered_limit: u32,
    /// While the sender is taken not to retransmit, one gap this often is
    /// still held and asked for.
    pub probe_every: Duration,
}

impl Default for NackParams {
    fn default() -> Self {
        Self {
            wait: Duration::from_millis(150),
            tries: 3,
            max_gap: 256,
            max_held: 2048,
            unanswered_limit: 16,
            probe_every: Duration::from_secs(10),
        }
    }
}

/// What the resequencer did, for the status and the log.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ResequencerStats {
    /// Packets asked for by NACK (each counted once however often asked).
    pub asked: u64,
    /// Missing packets a retransmission filled in time.
    pub recovered: u64,
    /// Missing packets given up as lost (the depacketiser sees these).
    pub given_up: u64,
    /// Packets that came after their place was passed (duplicates, late
    /// retransmissions, reordered beyond the wait): dropped.
    pub late: u64,
    /// Packets that arrived out of order and were put back in order.
    pub reordered: u64,
    /// Summed time from a gap's detection to its retransmission's arrival,
    /// over the recovered packets, microseconds.
    pub recovery_us_total: u64,
    /// The longest of those, microseconds.
    pub recovery_us_max: u64,
}

#[derive(Debug, Clone, Copy)]
struct Missing {
    since: Instant,
    /// Held and asked for (false: given up when its turn comes).
    hold: bool,
    sent: u32,
    last_sent: Option<Instant>,
}

/// Puts RTP packets back in order, holding the ones behind a gap while the
/// gap may still be filled by a retransmission (see the module's text).
#[derive(Debug, Clone)]
pub struct Resequencer {
    params: NackParams,
    /// The next extended sequence number to release.
    next: Option<u64>,
    /// The highest extended sequence number seen.
    highest: u64,
    held: BTreeMap<u64, OwnedRtp>,
    missing: BTreeMap<u64, Missing>,
    stats: ResequencerStats,
    unanswered: u32,
    last_probe: Option<Instant>,
    /// The RTP timestamp of the last packet released.
    last_released_ts: Option<u32>,
}

impl Resequencer {
    /// An empty resequencer.
    pub fn new(params: NackParams) -> Self {
        Self {
            params,
            next: None,
            highest: 0,
            held: BTreeMap::new(),
            missing: BTreeMap::new(),
            stats: ResequencerStats::default(),
            unanswered: 0,
            last_probe: None,
            last_released_ts: None,
        }
    }

    /// Forget the stream (a new SSRC): the next packet starts it again.
    /// Held packets are dropped; the statistics are kept.
    pub fn reset(&mut self) {
        self.next = None;
        self.held.clear();
        self.missing.clear();
    }

    /// What it has done so far.
    pub fn stats(&self) -> ResequencerStats {
        self.stats
    }

    /// Whether retransmissions are waited for: NACK on, and the sender has
    /// answered (or not yet been asked often enough to tell).
    pub fn sender_answers(&self) -> bool {
        self.unanswered < self.params.unanswered_limit
    }

    /// Whether `seq` is missing and still waited for, and `timestamp` fits
    /// its place: not before the packet before it, not after the packet
    /// after it (a video stream's timestamps do not go back in sequence
    /// order). Without a payload type saying which stream retransmits,
    /// this tells a retransmission from another stream whose first two
    /// bytes happen to name a missing packet.
    pub fn wants_at(&self, seq: u16, timestamp: u32) -> bool {
        if self.next.is_none() {
            return false;
        }
        let ext = self.extend(seq);
        if !self.missing.contains_key(&ext) {
            return false;
        }
        // `b` is not before `a` (RTP timestamps wrap).
        let not_before = |a: u32, b: u32| b.wrapping_sub(a) as i32 >= 0;
        let before = self
            .held
            .range(..ext)
            .next_back()
            .map(|(_, p)| p.timestamp)
            .or(self.last_released_ts);
        let after = self.held.range(ext + 1..).next().map(|(_, p)| p.timestamp);
        before.is_none_or(|b| not_before(b, timestamp))
            && after.is_none_or(|a| not_before(timestamp, a))
    }

    /// The extended sequence number of `seq`: the one nearest the highest
    /// seen.
    fn extend(&self, seq: u16) -> u64 {
        let base = self.highest & !0xffff;
        let cand = base | u64::from(seq);
        let best = [cand.wrapping_sub(1 << 16), cand, cand + (1 << 16)]
            .into_iter()
            .filter(|&c| c <= self.highest + (1 << 16))
            .min_by_key(|&c| c.abs_diff(self.highest))
            .unwrap_or(cand);
        // Keep the numbers away from zero so a wrap backwards never
        // underflows.
        best.max(1)
    }

    /// A packet of the stream as it arrived; what can be released in order
    /// is appended to `out`.
    pub fn push(&mut self, pkt: OwnedRtp, now: Instant, out: &mut Vec<OwnedRtp>) {
        let Some(next) = self.next else {
            // The first packet: numbering starts well above zero so that
            // packets slightly before it still extend below it.
            let ext = (1u64 << 32) | u64::from(pkt.sequence);
            self.next = Some(ext + 1);
            self.highest = ext;
            self.last_released_ts = Some(pkt.timestamp);
            out.push(pkt);
            return;
        };
        let ext = self.extend(pkt.sequence);
        if ext < next {
            self.stats.late += 1;
            return;
        }
        if ext > self.highest {
            let gap = ext - self.highest - 1;
            if gap > u64::from(self.params.max_gap) || self.params.wait.is_zero() {
                // Not asked for: everything before it goes out as it is.
                self.flush(out);
                self.stats.given_up += gap;
                self.next = Some(ext + 1);
                self.highest = ext;
                self.last_released_ts = Some(pkt.timestamp);
                out.push(pkt);
                return;
            }
            if gap > 0 {
                let hold = self.sender_answers()
                    || self.last_probe.is_none_or(|t| {
                        now.saturating_duration_since(t) >= self.params.probe_every
                    });
                if hold && !self.sender_answers() {
                    self.last_probe = Some(now);
                }
                for s in self.highest + 1..ext {
                    self.missing.insert(
                        s,
                        Missing {
                            since: now,
                            hold,
                            sent: 0,
                            last_sent: None,
                        },
                    );
                }
            }
            self.highest = ext;
        } else if self.missing.remove(&ext).is_some() {
            self.stats.reordered += 1;
        } else {
            // Already held: a duplicate.
            self.stats.late += 1;
            return;
        }
        self.held.insert(ext, pkt);
        self.release(now, out);
    }

    /// A retransmitted packet (already turned back into its original by
    /// [`OwnedRtp::from_retransmission`]): used when its gap is still
    /// waited for, else counted late. Either way the sender answers.
    pub fn retransmitted(&mut self, pkt: OwnedRtp, now: Instant, out: &mut Vec<OwnedRtp>) {
        self.unanswered = 0;
        if self.next.is_none() {
            self.stats.late += 1;
            return;
        }
        let ext = self.extend(pkt.sequence);
        match self.missing.remove(&ext) {
            Some(m) => {
                let us = now.saturating_duration_since(m.since).as_micros() as u64;
                self.stats.recovered += 1;
                self.stats.recovery_us_total += us;
                self.stats.recovery_us_max = self.stats.recovery_us_max.max(us);
                self.held.insert(ext, pkt);
                self.release(now, out);
            }
            None => self.stats.late += 1,
        }
    }

    /// Give up the gaps whose wait has passed and release what follows
    /// them; call at [`Self::deadline`].
    pub fn poll(&mut self, now: Instant, out: &mut Vec<OwnedRtp>) {
        self.release(now, out);
    }

    /// NACKs per missing packet, and the time between them.
    fn tries_and_spacing(&self) -> (u32, Duration) {
        let tries = self.params.tries.max(1);
        (tries, self.params.wait / tries)
    }

    /// The sequence numbers to NACK now (first requests and the repeats
    /// that are due), in order.
    pub fn due_nacks(&mut self, now: Instant) -> Vec<u16> {
        let (tries, spacing) = self.tries_and_spacing();
        let mut due = Vec::new();
        for (&ext, m) in self.missing.iter_mut() {
            if !m.hold || m.sent >= tries {
                continue;
            }
            let ready = m
                .last_sent
                .is_none_or(|t| now.saturating_duration_since(t) >= spacing);
            if ready {
                if m.sent == 0 {
                    self.stats.asked += 1;
                    self.unanswered = self.unanswered.saturating_add(1);
                }
                m.sent += 1;
                m.last_sent = Some(now);
                due.push(ext as u16);
            }
        }
        due
    }

    /// When [`Self::poll`] or [`Self::due_nacks`] next has something to do.
    pub fn deadline(&self) -> Option<Instant> {
        let (tries, spacing) = self.tries_and_spacing();
        self.missing
            .values()
            .filter(|m| m.hold)
            .map(|m| {
                let give_up = m.since + self.params.wait;
                match m.last_sent {
                    Some(t) if m.sent < tries => give_up.min(t + spacing),
                    None => m.since,
                    _ => give_up,
                }
            })
            .min()
    }

    /// Release in order from `next`: held packets, and missing ones whose
    /// wait is over (or that are not held for, or when too much is held).
    fn release(&mut self, now: Instant, out: &mut Vec<OwnedRtp>) {
        let Some(mut next) = self.next else { return };
        while next <= self.highest {
            if let Some(p) = self.held.remove(&next) {
                self.last_released_ts = Some(p.timestamp);
                out.push(p);
                next += 1;
                continue;
            }
            match self.missing.get(&next) {
                Some(m) => {
                    let expired = !m.hold
                        || now.saturating_duration_since(m.since) >= self.params.wait
                        || self.held.len() > self.params.max_held;
                    if !expired {
                        break;
                    }
                    self.missing.remove(&next);
                    self.stats.given_up += 1;
                    next += 1;
                }
                // Neither held nor missing: cannot happen (every number up
                // to the highest is one or the other until released).
                None => next += 1,
            }
        }
        self.next = Some(next);
    }

    /// Release everything held, giving up every gap.
    fn flush(&mut self, out: &mut Vec<OwnedRtp>) {
        self.stats.given_up += self.missing.len() as u64;
        self.missing.clear();
        let held = std::mem::take(&mut self.held);
        if let Some(p) = held.values().next_back() {
            self.last_released_ts = Some(p.timestamp);
        }
        out.extend(held.into_values());
    }
}

/// RTCP payload types (RFC 3550, RFC 4585).
const RTCP_RR: u8 = 201;
const RTCP_SDES: u8 = 202;
const RTCP_RTPFB: u8 = 205;
const RTCP_PSFB: u8 = 206;
/// Feedback message types: generic NACK (RTPFB), PLI (PSFB).
const FMT_NACK: u8 = 1;
const FMT_PLI: u8 = 1;

/// Append an RTCP header whose packet holds `body_words` 32-bit words after
/// the header.
fn header(out: &mut Vec<u8>, count: u8, pt: u8, body_words: usize) {
    out.push(0x80 | (count & 0x1f));
    out.push(pt);
    out.extend_from_slice(&(body_words as u16).to_be_bytes());
}

/// The empty receiver report and the CNAME that open a compound RTCP
/// packet (RFC 3550 §6.1: every compound packet starts with a report and
/// carries a CNAME).
fn report_and_cname(own_ssrc: u32, cname: &str) -> Vec<u8> {
    let mut out = Vec::with_capacity(64);
    header(&mut out, 0, RTCP_RR, 1);
    out.extend_from_slice(&own_ssrc.to_be_bytes());
    let name = &cname.as_bytes()[..cname.len().min(255)];
    // SSRC, CNAME item (type, length, text), end of items, padding to 32
    // bits.
    let items = 4 + 2 + name.len() + 1;
    let words = items.div_ceil(4);
    header(&mut out, 1, RTCP_SDES, words);
    out.extend_from_slice(&own_ssrc.to_be_bytes());
    out.push(1);
    out.push(name.len() as u8);
    out.extend_from_slice(name);
    out.resize(out.len() + words * 4 - (items - 1), 0);
    out
}

/// A compound RTCP packet asking `media_ssrc`'s sender to retransmit
/// `lost` (generic NACK, RFC 4585 §6.2.1: each entry one sequence number
/// and a bitmask of the 16 after it).
pub fn nack_packet(own_ssrc: u32, media_ssrc: u32, cname: &str, lost: &[u16]) -> Vec<u8> {
    let mut seqs = lost.to_vec();
    seqs.sort_unstable();
    seqs.dedup();
    let mut fci: Vec<(u16, u16)> = Vec::new();
    for s in seqs {
        match fci.last_mut() {
            Some((pid, blp)) if s.wrapping_sub(*pid) >= 1 && s.wrapping_sub(*pid) <= 16 => {
                *blp |= 1 << (s.wrapping_sub(*pid) - 1);
            }
            _ => fci.push((s, 0)),
        }
    }
    let mut out = report_and_cname(own_ssrc, cname);
    header(&mut out, FMT_NACK, RTCP_RTPFB, 2 + fci.len());
    out.extend_from_slice(&own_ssrc.to_be_bytes());
    out.extend_from_slice(&media_ssrc.to_be_bytes());
    for (pid, blp) in fci {
        out.extend_from_slice(&pid.to_be_bytes());
        out.extend_from_slice(&blp.to_be_bytes());
    }
    out
}

/// A compound RTCP packet asking `media_ssrc`'s sender for a key frame
/// (picture loss indication, RFC 4585 §6.3.1).
pub fn pli_packet(own_ssrc: u32, media_ssrc: u32, cname: &str) -> Vec<u8> {
    let mut out = report_and_cname(own_ssrc, cname);
    header(&mut out, FMT_PLI, RTCP_PSFB, 2);
    out.extend_from_slice(&own_ssrc.to_be_bytes());
    out.extend_from_slice(&media_ssrc.to_be_bytes());
    out
}

/// A feedback message found in a compound RTCP packet.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Feedback {
    /// Generic NACK: the media SSRC and the sequence numbers asked for.
    Nack {
        /// The stream the request is about.
        media_ssrc: u32,
        /// The sequence numbers asked for, in the packet's order.
        lost: Vec<u16>,
    },
    /// Picture loss indication for the media SSRC.
    Pli {
        /// The stream the request is about.
        media_ssrc: u32,
    },
}

/// The feedback messages of a compound RTCP packet (other packets are
/// skipped; parsing stops at the first malformed one).
pub fn parse_feedback(buf: &[u8]) -> Vec<Feedback> {
    let mut found = Vec::new();
    for pkt in rtcp_packets(buf).filter(|p| p.len() >= 12) {
        let media_ssrc = u32::from_be_bytes([pkt[8], pkt[9], pkt[10], pkt[11]]);
        match (pkt[1], pkt[0] & 0x1f) {
            (RTCP_RTPFB, FMT_NACK) => {
                let mut lost = Vec::new();
                for e in pkt[12..].chunks_exact(4) {
                    let pid = u16::from_be_bytes([e[0], e[1]]);
                    let blp = u16::from_be_bytes([e[2], e[3]]);
                    lost.push(pid);
                    for i in 0..16u16 {
                        if blp & (1 << i) != 0 {
                            lost.push(pid.wrapping_add(i + 1));
                        }
                    }
                }
                found.push(Feedback::Nack { media_ssrc, lost });
            }
            (RTCP_PSFB, FMT_PLI) => found.push(Feedback::Pli { media_ssrc }),
            _ => {}
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pkt(seq: u16) -> OwnedRtp {
        OwnedRtp {
            marker: false,
            payload_type: 96,
            sequence: seq,
            timestamp: u32::from(seq) * 100,
            ssrc: 7,
            payload: vec![seq as u8],
        }
    }

    fn seqs(out: &[OwnedRtp]) -> Vec<u16> {
        out.iter().map(|p| p.sequence).collect()
    }

    /// A 120 ms wait with two tries: the repeat 60 ms after the first.
    fn params() -> NackParams {
        NackParams {
            wait: Duration::from_millis(120),
            tries: 2,
            ..Default::default()
        }
    }

    fn ms(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn without_loss_every_packet_passes_at_once() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        for s in 65_530..=65_535u16 {
            let mut out = Vec::new();
            r.push(pkt(s), t0, &mut out);
            assert_eq!(seqs(&out), vec![s]);
        }
        for s in 0..5u16 {
            let mut out = Vec::new();
            r.push(pkt(s), t0, &mut out);
            assert_eq!(seqs(&out), vec![s], "across the wrap");
        }
        assert_eq!(r.deadline(), None);
        assert_eq!(r.stats(), ResequencerStats::default());
    }

    #[test]
    fn a_gap_is_held_asked_for_and_filled_by_its_retransmission() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        let mut out = Vec::new();
        r.push(pkt(10), t0, &mut out);
        r.push(pkt(13), ms(t0, 1), &mut out);
        r.push(pkt(14), ms(t0, 2), &mut out);
        assert_eq!(seqs(&out), vec![10], "13 and 14 wait behind the gap");
        assert!(r.wants_at(11, 1100) && r.wants_at(12, 1200) && !r.wants_at(13, 1300));
        assert_eq!(
            r.deadline(),
            Some(ms(t0, 1)),
            "the first NACK is due at once"
        );
        assert_eq!(r.due_nacks(ms(t0, 2)), vec![11, 12]);
        assert_eq!(
            r.due_nacks(ms(t0, 3)),
            Vec::<u16>::new(),
            "not again so soon"
        );
        // The repeat is due half the wait later.
        assert_eq!(r.deadline(), Some(ms(t0, 2 + 60)));
        r.retransmitted(pkt(12), ms(t0, 20), &mut out);
        assert_eq!(seqs(&out), vec![10], "12 alone does not open the gap");
        assert_eq!(r.due_nacks(ms(t0, 62)), vec![11], "11 asked for again");
        r.retransmitted(pkt(11), ms(t0, 70), &mut out);
        assert_eq!(seqs(&out), vec![10, 11, 12, 13, 14]);
        let st = r.stats();
        assert_eq!((st.asked, st.recovered, st.given_up), (2, 2, 0));
        assert_eq!(st.recovery_us_max, 69_000);
        assert_eq!(r.deadline(), None);
        r.retransmitted(pkt(11), ms(t0, 80), &mut out);
        assert_eq!(r.stats().late, 1, "a second copy is late");
    }

    #[test]
    fn an_unfilled_gap_is_given_up_after_the_wait() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        let mut out = Vec::new();
        r.push(pkt(100), t0, &mut out);
        r.push(pkt(102), t0, &mut out);
        r.poll(ms(t0, 119), &mut out);
        assert_eq!(seqs(&out), vec![100]);
        assert_eq!(r.deadline(), Some(t0), "its NACK is due");
        r.due_nacks(t0);
        r.due_nacks(ms(t0, 60));
        assert_eq!(r.deadline(), Some(ms(t0, 120)));
        r.poll(ms(t0, 120), &mut out);
        assert_eq!(seqs(&out), vec![100, 102]);
        assert_eq!(r.stats().given_up, 1);
        r.retransmitted(pkt(101), ms(t0, 130), &mut out);
        assert_eq!(seqs(&out), vec![100, 102], "too late: not released");
        assert_eq!(r.stats().late, 1);
    }

    #[test]
    fn a_retransmission_must_fit_between_its_neighbours_timestamps() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        let mut out = Vec::new();
        // pkt(s) has timestamp 100 s: 1 -> 100, 3 -> 300.
        r.push(pkt(1), t0, &mut out);
        r.push(pkt(3), t0, &mut out);
        assert!(r.wants_at(2, 200) && r.wants_at(2, 100) && r.wants_at(2, 300));
        assert!(!r.wants_at(2, 301), "after the packet after it");
        assert!(!r.wants_at(2, 99), "before the packet before it");
        assert!(!r.wants_at(4, 400), "not missing");
        // Across the timestamp's wrap.
        let mut w = Resequencer::new(params());
        let at = |seq: u16, ts: u32| OwnedRtp {
            timestamp: ts,
            ..pkt(seq)
        };
        w.push(at(1, u32::MAX - 10), t0, &mut out);
        w.push(at(3, 20), t0, &mut out);
        assert!(w.wants_at(2, 5) && w.wants_at(2, u32::MAX));
        assert!(!w.wants_at(2, 100));
    }

    #[test]
    fn reordered_packets_are_put_back_in_order() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        let mut out = Vec::new();
        for s in [1u16, 3, 2, 4] {
            r.push(pkt(s), t0, &mut out);
        }
        assert_eq!(seqs(&out), vec![1, 2, 3, 4]);
        assert_eq!(r.stats().reordered, 1);
        r.push(pkt(3), t0, &mut out);
        assert_eq!(r.stats().late, 1);
    }

    #[test]
    fn a_long_gap_or_no_wait_is_not_asked_for() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(params());
        let mut out = Vec::new();
        r.push(pkt(1), t0, &mut out);
        r.push(pkt(3), t0, &mut out);
        r.push(pkt(1000), t0, &mut out);
        assert_eq!(seqs(&out), vec![1, 3, 1000], "3 flushed with the outage");
        assert_eq!(r.stats().given_up, 1 + 996);
        assert!(r.due_nacks(t0).is_empty());

        let mut off = Resequencer::new(NackParams {
            wait: Duration::ZERO,
            ..Default::default()
        });
        let mut out = Vec::new();
        for s in [5u16, 7, 8] {
            off.push(pkt(s), t0, &mut out);
        }
        assert_eq!(seqs(&out), vec![5, 7, 8]);
        assert!(off.due_nacks(t0).is_empty());
    }

    #[test]
    fn a_sender_that_never_answers_stops_costing_latency_but_is_probed() {
        let t0 = Instant::now();
        let p = params();
        let mut r = Resequencer::new(p);
        let mut out = Vec::new();
        let mut s = 0u16;
        let mut t = 0u64;
        r.push(pkt(s), ms(t0, t), &mut out);
        // Gaps of one packet, never filled.
        for _ in 0..p.unanswered_limit {
            s += 2;
            t += 200;
            r.push(pkt(s), ms(t0, t), &mut out);
            r.due_nacks(ms(t0, t));
            r.poll(ms(t0, t + 150), &mut out);
        }
        assert!(!r.sender_answers());
        // The first gap after that is a probe (held), the next one is not.
        s += 2;
        t += 200;
        out.clear();
        r.push(pkt(s), ms(t0, t), &mut out);
        assert!(out.is_empty(), "the probe is held");
        assert_eq!(r.due_nacks(ms(t0, t)).len(), 1);
        r.poll(ms(t0, t + 150), &mut out);
        s += 2;
        t += 200;
        out.clear();
        r.push(pkt(s), ms(t0, t), &mut out);
        assert_eq!(seqs(&out), vec![s], "not held: no latency");
        assert!(r.due_nacks(ms(t0, t)).is_empty());
        // A retransmission (even a late one) shows the sender answers.
        r.retransmitted(pkt(s - 1), ms(t0, t + 1), &mut out);
        assert!(r.sender_answers());
    }

    #[test]
    fn too_much_held_gives_the_oldest_gap_up() {
        let t0 = Instant::now();
        let mut r = Resequencer::new(NackParams {
            max_held: 4,
            ..params()
        });
        let mut out = Vec::new();
        r.push(pkt(0), t0, &mut out);
        for s in 2..=6u16 {
            r.push(pkt(s), t0, &mut out);
        }
        assert_eq!(seqs(&out), vec![0, 2, 3, 4, 5, 6]);
        assert_eq!(r.stats().given_up, 1);
    }

    #[test]
    fn nack_and_pli_packets_round_trip() {
        let lost = [65_534u16, 65_535, 0, 3, 17, 18, 40];
        let buf = nack_packet(0x1111, 0x2222, "shotpilot@test", &lost);
        assert_eq!(buf.len() % 4, 0);
        // RR, SDES, then the NACK.
        assert_eq!((buf[1], buf[0] & 0x1f), (201, 0));
        let fb = parse_feedback(&buf);
        let Some(Feedback::Nack {
            media_ssrc,
            lost: got,
        }) = fb.first()
        else {
            panic!("no NACK in {fb:?}");
        };
        assert_eq!(*media_ssrc, 0x2222);
        let mut got = got.clone();
        got.sort_unstable();
        let mut want = lost.to_vec();
        want.sort_unstable();
        assert_eq!(got, want);
        // Sorted: 0 (3 in its mask), 17 (18), 40, 65534 (65535): four
        // entries after the two SSRCs.
        let nack_words = usize::from(u16::from_be_bytes([
            buf[buf.len() - 4 * 6 - 2],
            buf[buf.len() - 4 * 6 - 1],
        ]));
        assert_eq!(nack_words, 2 + 4);
        let pli = pli_packet(0x1111, 0x2222, "x");
        assert_eq!(
            parse_feedback(&pli),
            vec![Feedback::Pli { media_ssrc: 0x2222 }]
        );
        // Each part's length field covers the whole buffer exactly.
        let mut off = 0;
        let mut parts = 0;
        while off < pli.len() {
            off += (usize::from(u16::from_be_bytes([pli[off + 2], pli[off + 3]])) + 1) * 4;
            parts += 1;
        }
        assert_eq!((off, parts), (pli.len(), 3));
    }

    #[test]
    fn a_retransmission_gives_back_its_original() {
        let payload = [0x01, 0x2c, 0x7c, 0x85, 0xaa];
        let rtx = RtpPacket {
            marker: true,
            payload_type: 97,
            sequence: 5,
            timestamp: 9000,
            ssrc: 0xbeef,
            payload: &payload,
        };
        let o = OwnedRtp::from_retransmission(&rtx, 96, 0xcafe).expect("has an OSN");
        assert_eq!(
            (o.sequence, o.payload_type, o.ssrc, o.timestamp, o.marker),
            (300, 96, 0xcafe, 9000, true)
        );
        assert_eq!(o.payload, vec![0x7c, 0x85, 0xaa]);
        let short = RtpPacket {
            payload: &payload[..1],
            ..rtx
        };
        assert!(OwnedRtp::from_retransmission(&short, 96, 1).is_none());
    }
}
