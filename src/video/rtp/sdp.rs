//! The parts of an SDP session description (RFC 8866) a raw RTP video
//! receiver needs: the video port, payload type, codec, clock rate and the
//! H.264 parameter sets (`sprop-parameter-sets`, RFC 6184).

/// Errors reading an SDP.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SdpError {
    /// No `m=video` line.
    #[error("the SDP has no m=video line")]
    NoVideo,
    /// A line that must be well formed is not.
    #[error("SDP line {line}: {reason}")]
    BadLine {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
}

/// A video stream described by an SDP.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SdpVideo {
    /// The UDP port RTP arrives on.
    pub port: u16,
    /// The connection address (`c=`), when given.
    pub address: Option<String>,
    /// The RTP payload type.
    pub payload_type: u8,
    /// The codec (`rtpmap` encoding name, upper case), e.g. `H264`.
    pub codec: String,
    /// The RTP clock rate, Hz.
    pub clock_rate: u32,
    /// Decoded `sprop-parameter-sets` (SPS, PPS).
    pub param_sets: Vec<Vec<u8>>,
    /// The payload type of the stream's retransmissions (RFC 4588: an
    /// `rtx` rtpmap whose `apt` names the video's payload type), when the
    /// sender offers them.
    pub rtx_payload_type: Option<u8>,
}

/// Decode standard base64 (padding optional, as SDP writers differ);
/// `None` on a bad character.
pub fn base64_decode(s: &str) -> Option<Vec<u8>> {
    use base64::Engine as _;
    use base64::engine::{DecodePaddingMode, GeneralPurpose, GeneralPurposeConfig};
    const LENIENT: GeneralPurpose = GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        GeneralPurposeConfig::new()
            .with_decode_padding_mode(DecodePaddingMode::Indifferent)
            .with_decode_allow_trailing_bits(true),
    );
    LENIENT.decode(s).ok()
}

/// Parse the first video stream of an SDP.
pub fn parse(text: &str) -> Result<SdpVideo, SdpError> {
    let mut video: Option<SdpVideo> = None;
    let mut session_addr: Option<String> = None;
    let mut in_video = false;
    // The video section's `rtx` payload types and the `apt` each names.
    let mut rtx: Vec<u8> = Vec::new();
    let mut apt: Vec<(u8, u8)> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        let bad = |reason: &str| SdpError::BadLine {
            line: i + 1,
            reason: reason.to_owned(),
        };
        if let Some(m) = line.strip_prefix("m=") {
            if video.is_some() {
                // Only the first video stream.
                in_video = false;
                continue;
            }
            let f: Vec<&str> = m.split_whitespace().collect();
            in_video = f.first() == Some(&"video");
            if in_video {
                let port = f
                    .get(1)
                    .and_then(|p| p.split('/').next())
                    .and_then(|p| p.parse().ok())
                    .ok_or_else(|| bad("m=video without a port"))?;
                let payload_type = f
                    .get(3)
                    .and_then(|p| p.parse().ok())
                    .ok_or_else(|| bad("m=video without a payload type"))?;
                video = Some(SdpVideo {
                    port,
                    address: None,
                    payload_type,
                    codec: String::new(),
                    clock_rate: 90_000,
                    param_sets: Vec::new(),
                    rtx_payload_type: None,
                });
            }
            continue;
        }
        if let Some(c) = line.strip_prefix("c=") {
            let addr = c
                .split_whitespace()
                .nth(2)
                .map(|a| a.split('/').next().unwrap_or(a).to_owned());
            match (&mut video, in_video) {
                (Some(v), true) => v.address = addr,
                (None, _) => session_addr = addr,
                _ => {}
            }
            continue;
        }
        let Some(v) = video.as_mut().filter(|_| in_video) else {
            continue;
        };
        if let Some(rest) = line.strip_prefix("a=rtpmap:") {
            let mut it = rest.splitn(2, ' ');
            let pt: Option<u8> = it.next().and_then(|p| p.parse().ok());
            if let Some(p) = pt
                && it
                    .clone()
                    .next()
                    .is_some_and(|e| e.trim().to_ascii_lowercase().starts_with("rtx/"))
            {
                rtx.push(p);
                continue;
            }
            if pt != Some(v.payload_type) {
                continue;
            }
            let enc = it.next().ok_or_else(|| bad("rtpmap without an encoding"))?;
            let mut parts = enc.trim().split('/');
            v.codec = parts.next().unwrap_or("").to_ascii_uppercase();
            if let Some(rate) = parts.next() {
                v.clock_rate = rate.parse().map_err(|_| bad("bad clock rate"))?;
            }
        } else if let Some(rest) = line.strip_prefix("a=fmtp:") {
            let mut it = rest.splitn(2, ' ');
            let pt: Option<u8> = it.next().and_then(|p| p.parse().ok());
            if pt != Some(v.payload_type) {
                if let Some(p) = pt {
                    for kv in it.next().unwrap_or("").split(';') {
                        let mut kv = kv.trim().splitn(2, '=');
                        if kv.next().map(str::trim) == Some("apt")
                            && let Some(a) = kv.next().and_then(|a| a.trim().parse().ok())
                        {
                            apt.push((p, a));
                        }
                    }
                }
                continue;
            }
            for kv in it.next().unwrap_or("").split(';') {
                let mut kv = kv.trim().splitn(2, '=');
                if kv.next().map(str::trim) == Some("sprop-parameter-sets") {
                    for ps in kv.next().unwrap_or("").split(',') {
                        let ps = base64_decode(ps.trim())
                            .ok_or_else(|| bad("sprop-parameter-sets is not base64"))?;
                        if !ps.is_empty() {
                            v.param_sets.push(ps);
                        }
                    }
                }
            }
        }
    }
    let mut v = video.ok_or(SdpError::NoVideo)?;
    v.rtx_payload_type = rtx
        .into_iter()
        .find(|p| apt.contains(&(*p, v.payload_type)));
    if v.address.is_none() {
        v.address = session_addr;
    }
    if v.codec.is_empty() {
        // Static payload types carry no rtpmap; none of them is H.264.
        v.codec = format!("payload type {}", v.payload_type);
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_roundtrip_known() {
        assert_eq!(
            base64_decode("aM4xsg==").unwrap(),
            vec![0x68, 0xce, 0x31, 0xb2]
        );
        assert_eq!(base64_decode("Zm9vYg").unwrap(), b"foob");
        assert!(base64_decode("a$b").is_none());
    }

    #[test]
    fn parses_a_gstreamer_style_sdp() {
        let sdp = "v=0\r\no=- 0 0 IN IP4 127.0.0.1\r\ns=cam\r\nc=IN IP4 127.0.0.1\r\nt=0 0\r\n\
                   m=audio 5602 RTP/AVP 0\r\n\
                   m=video 5600 RTP/AVP 96\r\na=rtpmap:96 H264/90000\r\n\
                   a=fmtp:96 packetization-mode=1;profile-level-id=42C01E;sprop-parameter-sets=Z0LAHtkDxWhAAAADAEAAAAwDxYuS,aMuMsg==\r\n";
        let v = parse(sdp).unwrap();
        assert_eq!(v.port, 5600);
        assert_eq!(v.payload_type, 96);
        assert_eq!(v.codec, "H264");
        assert_eq!(v.clock_rate, 90_000);
        assert_eq!(v.address.as_deref(), Some("127.0.0.1"));
        assert_eq!(v.param_sets.len(), 2);
        assert_eq!(v.param_sets[0][0] & 0x1f, 7);
        assert_eq!(v.param_sets[1][0] & 0x1f, 8);
        assert_eq!(v.rtx_payload_type, None);
    }

    #[test]
    fn finds_the_retransmission_payload_type() {
        let sdp = "m=video 5600 RTP/AVPF 96 97 99
a=rtpmap:96 H264/90000
                   a=rtpmap:99 rtx/90000
a=fmtp:99 apt=100
                   a=rtpmap:97 rtx/90000
a=fmtp:97 apt=96;rtx-time=500
";
        let v = parse(sdp).unwrap();
        assert_eq!((v.payload_type, v.codec.as_str()), (96, "H264"));
        assert_eq!(v.rtx_payload_type, Some(97), "the rtx whose apt is 96");
    }

    #[test]
    fn h265_and_missing_video_are_reported() {
        let v = parse("m=video 5600 RTP/AVP 97\na=rtpmap:97 H265/90000\n").unwrap();
        assert_eq!(v.codec, "H265");
        assert_eq!(parse("v=0\nm=audio 1 RTP/AVP 0\n"), Err(SdpError::NoVideo));
        assert!(matches!(
            parse("m=video x RTP/AVP 96\n"),
            Err(SdpError::BadLine { line: 1, .. })
        ));
    }
}
