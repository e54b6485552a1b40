//! Fuzz the RTP/H.264 depacketising path (`shotpilot::video::rtp`, the
//! NAL-unit helpers of `shotpilot::video::h264`, the SDP reader).
//!
//! Two modes, chosen by the first input byte:
//! - raw: arbitrary datagrams go through `parse_rtp` and the
//!   `H264Depacketizer`, and the access units through `AuKind::of` and
//!   `annexb_units`; an arbitrary text goes through the SDP reader.
//!   Checked: no panic, every access unit is Annex B framed and holds at
//!   most what was sent, the counters add up.
//! - round trip: access units built from the input (NAL units of arbitrary
//!   types and bodies, with emulation prevention as an encoder writes them)
//!   are packetised with an arbitrary MTU, an arbitrary subset of packets is
//!   dropped; every unit that comes back unmarked must equal the one sent,
//!   and every unit one of whose packets was dropped must come back marked
//!   lost or not at all (the first unit is never dropped from).
#![no_main]

use libfuzzer_sys::arbitrary::{Result as AResult, Unstructured};
use libfuzzer_sys::fuzz_target;
use shotpilot::video::h264::{AuKind, annexb_units, push_annexb};
use shotpilot::video::rtp::{H264Depacketizer, packetize_h264, parse_rtp, sdp};

fuzz_target!(|data: &[u8]| {
    let mut u = Unstructured::new(data);
    let Ok(mode) = u.arbitrary::<u8>() else {
        return;
    };
    if mode & 1 == 0 {
        let _ = raw(&mut u);
    } else {
        let _ = round_trip(&mut u);
    }
});

fn raw(u: &mut Unstructured<'_>) -> AResult<()> {
    let sdp_len = u.int_in_range(0..=512usize)?;
    if let Ok(text) = std::str::from_utf8(u.bytes(sdp_len.min(u.len()))?) {
        let _ = sdp::parse(text);
    }
    let mut d = H264Depacketizer::new(vec![]);
    let mut sent = 0usize;
    let mut taken = 0u64;
    while !u.is_empty() {
        let len = u.int_in_range(0..=1600usize)?;
        let pkt = u.bytes(len.min(u.len()))?;
        if let Ok(p) = parse_rtp(pkt) {
            sent += p.payload.len();
            taken += 1;
            for au in d.push(&p) {
                assert!(au.data.is_empty() || au.data.starts_with(&[0, 0, 0, 1]));
                // Start codes add at most 4 bytes per payload byte's unit.
                assert!(au.data.len() <= 5 * sent + 64);
                let _ = AuKind::of(&au.data);
                for n in annexb_units(&au.data) {
                    assert!(!n.is_empty());
                }
            }
        }
    }
    let s = d.stats();
    assert!(s.packets + s.late <= taken);
    Ok(())
}

/// Emulation prevention: no 00 00 0x (x <= 3) inside a NAL unit.
fn escape(body: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(body.len() + body.len() / 2);
    let mut zeros = 0;
    for &b in body {
        if zeros >= 2 && b <= 3 {
            out.push(3);
            zeros = 0;
        }
        zeros = if b == 0 { zeros + 1 } else { 0 };
        out.push(b);
    }
    if out.last() == Some(&0) {
        // A unit never ends in a zero byte (trailing bits).
        out.push(0x80);
    }
    out
}

fn round_trip(u: &mut Unstructured<'_>) -> AResult<()> {
    let mtu = u.int_in_range(32..=1500usize)?;
    let n_aus = u.int_in_range(1..=6usize)?;
    let mut aus = Vec::new();
    for _ in 0..n_aus {
        let mut au = Vec::new();
        for _ in 0..u.int_in_range(1..=4usize)? {
            let ty = u.int_in_range(1..=23u8)?;
            let nri = u.int_in_range(0..=3u8)? << 5;
            let len = u.int_in_range(1..=3000usize)?;
            let body = u.bytes(len.min(u.len()))?;
            let mut nal = vec![nri | ty];
            nal.extend(escape(body));
            push_annexb(&mut au, &nal);
        }
        aus.push(au);
    }
    let mut seq = u.arbitrary::<u16>()?;
    let ts0 = u.arbitrary::<u32>()?;
    let mut d = H264Depacketizer::new(vec![]);
    let mut out = Vec::new();
    let mut damaged = Vec::new();
    for (i, au) in aus.iter().enumerate() {
        let ts = ts0.wrapping_add(3000 * i as u32);
        let pkts = packetize_h264(au, mtu, 96, 0xfeed, &mut seq, ts);
        let mut dropped_any = false;
        for p in &pkts {
            assert!(p.len() <= mtu.max(16));
            // The first unit is kept whole: a receiver cannot tell a
            // stream that starts with it from one joined after its first
            // packets (it then trusts units opened by SPS/AUD only).
            if i > 0 && u.arbitrary::<u8>().unwrap_or(0) < 16 {
                dropped_any = true;
                continue;
            }
            out.extend(d.push(&parse_rtp(p).expect("our own packets parse")));
        }
        damaged.push(dropped_any);
    }
    for got in out {
        let i = got.timestamp.wrapping_sub(ts0) as usize / 3000;
        assert!(i < aus.len());
        if got.lost == 0 {
            assert!(!damaged[i], "access unit {i} lost packets but came back unmarked");
            assert_eq!(annexb_units(&got.data), annexb_units(&aus[i]), "access unit {i}");
        }
    }
    Ok(())
}
