//! Fuzz the MJPEG multipart parser (`shotpilot::video::mjpeg`).
//!
//! Two modes, chosen by the first input byte:
//! - raw: arbitrary bytes, split into arbitrary chunks, go through a
//!   [`PartParser`] whose boundary comes from an arbitrary `Content-Type`
//!   value. Checked: no panic, the parser always makes progress (a bounded
//!   number of events per push), it never hands out more bytes than it was
//!   given, and a part delimited by JPEG markers alone is a whole JPEG by
//!   [`jpeg_end`].
//! - round trip: a well-formed stream is built from the input (boundary
//!   token, line ends, with or without part headers and `Content-Length`,
//!   JPEG-shaped bodies with arbitrary segment and entropy bytes), fed in
//!   arbitrary chunks; every body and timestamp must come back, in order.
#![no_main]

use libfuzzer_sys::arbitrary::{Result as AResult, Unstructured};
use libfuzzer_sys::fuzz_target;
use shotpilot::video::mjpeg::{ParseEvent, Part, PartParser, boundary_from_content_type, jpeg_end};

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

/// Chunk lengths: cycle through the given bytes (0 means "all the rest").
fn chunks<'a>(stream: &'a [u8], sizes: &[u8]) -> Vec<&'a [u8]> {
    let mut out = Vec::new();
    let mut rest = stream;
    let mut k = 0;
    while !rest.is_empty() {
        let s = sizes.get(k % sizes.len().max(1)).copied().unwrap_or(0) as usize;
        let n = if s == 0 {
            rest.len()
        } else {
            s.min(rest.len())
        };
        out.push(&rest[..n]);
        rest = &rest[n..];
        k += 1;
    }
    out
}

/// Push every chunk, drain the parser after each, check the invariants;
/// returns the parts.
fn feed(p: &mut PartParser, pieces: &[&[u8]]) -> Vec<Part> {
    let mut parts = Vec::new();
    let mut pushed = 0usize;
    let mut handed = 0usize;
    for piece in pieces {
        p.push(piece);
        pushed += piece.len();
        let before = p.buffered();
        let mut events = 0usize;
        while let Some(ev) = p.next_part() {
            events += 1;
            // Every event but a zero-byte skip or an empty part consumes
            // input, and those two are followed by one that does.
            assert!(
                events <= 2 * before + 4,
                "no progress: {events} events from {before} buffered bytes"
            );
            match ev {
                ParseEvent::Part(part) => {
                    handed += part.body.len();
                    if !part.had_headers {
                        assert_eq!(
                            jpeg_end(&part.body),
                            Some(part.body.len()),
                            "a marker-delimited part is not a whole JPEG"
                        );
                    }
                    if let Some(t) = part.timestamp {
                        assert!(t.is_finite());
                    }
                    parts.push(part);
                }
                ParseEvent::Skipped { bytes, reason } => {
                    assert!(!reason.is_empty());
                    handed += bytes;
                }
            }
            assert!(
                handed + p.buffered() <= pushed,
                "handed out {handed} + buffered {} > pushed {pushed}",
                p.buffered()
            );
        }
    }
    parts
}

fn raw(u: &mut Unstructured<'_>) -> AResult<()> {
    let ct_len = u.int_in_range(0..=48)?;
    let ct = String::from_utf8_lossy(u.bytes(ct_len)?).into_owned();
    let boundary = boundary_from_content_type(&ct);
    if let Some(b) = &boundary {
        // Unquoted, one leading "--" dropped (a value may itself begin
        // with dashes), never empty.
        assert!(
            !b.is_empty() && ct.contains(b.as_str()),
            "{b:?} from {ct:?}"
        );
    }
    let max_part = u.int_in_range(0..=4096usize)?;
    let n_sizes = u.int_in_range(1..=8)?;
    let sizes = u.bytes(n_sizes)?.to_vec();
    let stream = u.bytes(u.len())?;
    if let Some(e) = jpeg_end(stream) {
        assert!(e >= 4 && e <= stream.len() && stream[e - 2..e] == [0xFF, 0xD9]);
    }
    let mut p = PartParser::new(boundary.as_deref(), max_part);
    feed(&mut p, &chunks(stream, &sizes));
    // A reset forgets everything and the parser starts over.
    p.reset();
    assert_eq!(p.buffered(), 0);
    feed(&mut p, &chunks(stream, &[0]));
    Ok(())
}

/// A JPEG-shaped body: SOI, an APP segment with arbitrary bytes (which may
/// hold a fake EOI), SOS, entropy-coded bytes with every FF stuffed, EOI.
fn jpeg_body(app: &[u8], entropy: &[u8]) -> Vec<u8> {
    let mut v = vec![0xFF, 0xD8, 0xFF, 0xE0];
    v.extend_from_slice(&((app.len() + 2) as u16).to_be_bytes());
    v.extend_from_slice(app);
    v.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x04, 0x01, 0x02]);
    for &b in entropy {
        v.push(b);
        if b == 0xFF {
            v.push(0x00);
        }
    }
    v.extend_from_slice(&[0xFF, 0xD9]);
    v
}

fn find(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

fn round_trip(u: &mut Unstructured<'_>) -> AResult<()> {
    const ALNUM: &[u8] = b"abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789";
    let tok_len = u.int_in_range(1..=16)?;
    let mut token = String::new();
    for _ in 0..tok_len {
        token.push(ALNUM[u.int_in_range(0..=ALNUM.len() - 1)?] as char);
    }
    let flags: u8 = u.arbitrary()?;
    let crlf = flags & 1 != 0;
    let headers = flags & 2 != 0;
    let length = headers && flags & 4 != 0;
    // The boundary line: "--token" (RFC 2046), bare "token", or "----token";
    // the Content-Type value quoted or not, with or without the dashes.
    let line = match (flags >> 3) & 3 {
        0 | 3 => format!("--{token}"),
        1 => token.clone(),
        _ => format!("----{token}"),
    };
    let ct = if flags & 32 != 0 {
        format!("multipart/x-mixed-replace;boundary=\"--{token}\"")
    } else {
        format!("multipart/x-mixed-replace; boundary={token}")
    };
    let boundary = boundary_from_content_type(&ct);
    assert_eq!(boundary.as_deref(), Some(token.as_str()), "{ct}");
    let eol = if crlf { "\r\n" } else { "\n" };
    let n = u.int_in_range(1..=6)?;
    let mut bodies = Vec::new();
    for _ in 0..n {
        let a = u.int_in_range(0..=200)?;
        let app = u.bytes(a)?.to_vec();
        let e = u.int_in_range(0..=400)?;
        let entropy = u.bytes(e)?.to_vec();
        let body = jpeg_body(&app, &entropy);
        // A body holding the boundary token is ambiguous without a length
        // (RFC 2046 forbids it): not a case to hold the parser to.
        if find(&body, token.as_bytes()) {
            return Ok(());
        }
        bodies.push(body);
    }
    let mut stream = Vec::new();
    for (i, body) in bodies.iter().enumerate() {
        stream.extend_from_slice(format!("{line}{eol}").as_bytes());
        if headers {
            stream.extend_from_slice(format!("Content-Type: image/jpeg{eol}").as_bytes());
            if length {
                stream.extend_from_slice(format!("Content-Length: {}{eol}", body.len()).as_bytes());
            }
            stream.extend_from_slice(format!("X-Timestamp: {i}.25{eol}{eol}").as_bytes());
        }
        stream.extend_from_slice(body);
        stream.extend_from_slice(eol.as_bytes());
    }
    let n_sizes = u.int_in_range(1..=8)?;
    let sizes = u.bytes(n_sizes)?.to_vec();
    let mut p = PartParser::new(boundary.as_deref(), 1 << 20);
    let parts = feed(&mut p, &chunks(&stream, &sizes));
    assert_eq!(
        parts.len(),
        bodies.len(),
        "token {token:?} flags {flags:#x}"
    );
    for (i, (part, body)) in parts.iter().zip(&bodies).enumerate() {
        assert_eq!(
            &part.body, body,
            "part {i}, token {token:?} flags {flags:#x}"
        );
        if headers {
            assert_eq!(part.timestamp, Some(i as f64 + 0.25));
        }
    }
    Ok(())
}
