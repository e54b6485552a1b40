//! The resumable MJPEG part parser against the rescanning reference
//! parser it replaced (`mjpeg_support/reference.rs`): the same events on
//! random camera-like streams with faults and on marker soup, fed in random
//! pieces, and scanning work linear in the bytes received.

use crate::mjpeg_support;

use mjpeg_support::reference::RefParser;
use shotpilot::video::mjpeg::{ParseEvent, Part, PartParser};

/// A tiny JPEG-shaped byte string: SOI, an APP0 segment holding a fake
/// EOI, SOS, entropy data with a stuffed FF and an RST, EOI.
fn fake_jpeg(tag: u8) -> Vec<u8> {
    let mut v = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x06, 0xFF, 0xD9, tag, 0x00];
    v.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x04, 0x01, 0x02]);
    v.extend_from_slice(&[0x11, 0xFF, 0x00, 0x22, 0xFF, 0xD0, tag, 0x33]);
    v.extend_from_slice(&[0xFF, 0xD9]);
    v
}

fn parts(p: &mut PartParser) -> (Vec<Part>, usize) {
    let mut out = Vec::new();
    let mut skipped = 0;
    while let Some(ev) = p.next_part() {
        match ev {
            ParseEvent::Part(x) => out.push(x),
            ParseEvent::Skipped { .. } => skipped += 1,
        }
    }
    (out, skipped)
}

/// A JPEG-shaped byte string of about `size` bytes, as a camera sends
/// it: APP0, sometimes an APP1 holding a whole thumbnail JPEG (so SOI
/// and EOI bytes inside a segment), a table segment, SOS, entropy-coded
/// data with stuffed FF 00 and restart markers, EOI.
fn camera_jpeg(rng: &mut rand::rngs::StdRng, size: usize) -> Vec<u8> {
    use rand::Rng;
    let mut v = vec![0xFF, 0xD8, 0xFF, 0xE0, 0x00, 0x10];
    v.extend_from_slice(b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0");
    if rng.random_bool(0.3) {
        let thumb = fake_jpeg(rng.random());
        v.extend_from_slice(&[0xFF, 0xE1]);
        v.extend_from_slice(&((thumb.len() + 8) as u16).to_be_bytes());
        v.extend_from_slice(b"Exif\0\0");
        v.extend_from_slice(&thumb);
    }
    v.extend_from_slice(&[0xFF, 0xDB, 0x00, 0x43, 0x00]);
    v.extend((0..64).map(|_| rng.random_range(1..=255u8)));
    v.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x08, 0x01, 0x01, 0x00, 0x00, 0x3F, 0x00]);
    let mut rst = 0u8;
    while v.len() + 2 < size {
        let b: u8 = rng.random();
        v.push(b);
        if b == 0xFF {
            if rng.random_bool(0.05) {
                v.push(0xD0 + rst);
                rst = (rst + 1) % 8;
            } else {
                v.push(0x00);
            }
        }
    }
    v.extend_from_slice(&[0xFF, 0xD9]);
    v
}

/// A stream of `n` parts framed one of several ways, with the ways
/// servers get it wrong mixed in when `faults`.
fn random_stream(
    rng: &mut rand::rngs::StdRng,
    n: usize,
    size: std::ops::Range<usize>,
    faults: bool,
) -> (Option<&'static str>, Vec<u8>) {
    use rand::Rng;
    let boundary = [Some("frame"), Some("--myboundary"), None][rng.random_range(0..3)];
    let eol: &[u8] = if rng.random_bool(0.5) { b"\r\n" } else { b"\n" };
    let (headers, length) = (rng.random_bool(0.8), rng.random_bool(0.6));
    let mut s = Vec::new();
    for i in 0..n {
        let sz = rng.random_range(size.clone());
        let mut j = camera_jpeg(rng, sz);
        let mut claimed = j.len();
        if faults && rng.random_bool(0.15) {
            let cut = rng.random_range(1..j.len());
            j.truncate(cut);
        }
        if faults && rng.random_bool(0.1) {
            claimed = (claimed as i64 + rng.random_range(-40..40i64)).max(0) as usize;
        }
        if faults && rng.random_bool(0.1) {
            let k = rng.random_range(0..j.len());
            j[k] = rng.random();
        }
        if faults && rng.random_bool(0.1) {
            s.extend((0..rng.random_range(1..50)).map(|_| rng.random::<u8>()));
        }
        if let Some(b) = boundary {
            s.extend_from_slice(b"--");
            s.extend_from_slice(b.as_bytes());
            s.extend_from_slice(eol);
            if headers {
                s.extend_from_slice(b"Content-Type: image/jpeg");
                s.extend_from_slice(eol);
                if length {
                    s.extend_from_slice(format!("Content-Length: {claimed}").as_bytes());
                    s.extend_from_slice(eol);
                }
                s.extend_from_slice(format!("X-Timestamp: {i}.25").as_bytes());
                s.extend_from_slice(eol);
                s.extend_from_slice(eol);
            }
        }
        s.extend_from_slice(&j);
        s.extend_from_slice(eol);
    }
    (boundary.map(|b| b.trim_start_matches('-')), s)
}

/// Random chunk sizes: mostly small, sometimes large.
fn chunks(rng: &mut rand::rngs::StdRng, total: usize) -> Vec<usize> {
    use rand::Rng;
    let mut v = Vec::new();
    let mut left = total;
    while left > 0 {
        let c = match rng.random_range(0..4) {
            0 => 1,
            1 => rng.random_range(1..16),
            2 => rng.random_range(1..400),
            _ => rng.random_range(1..5000),
        }
        .min(left);
        v.push(c);
        left -= c;
    }
    v
}

#[test]
fn resumable_scanning_gives_the_same_events_as_rescanning() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    let (mut events, mut parts_seen, mut skips) = (0usize, 0usize, 0usize);
    for trial in 0..400 {
        let faults = trial % 4 != 0;
        let n = rng.random_range(1..12);
        let (boundary, data) = random_stream(&mut rng, n, 60..3000, faults);
        let max_part = if rng.random_bool(0.2) { 1500 } else { 1 << 20 };
        let mut new = PartParser::new(boundary, max_part);
        let mut old = RefParser::new(boundary, max_part);
        let mut at = 0;
        for c in chunks(&mut rng, data.len()) {
            new.push(&data[at..at + c]);
            old.push(&data[at..at + c]);
            at += c;
            loop {
                let (a, b) = (new.next_part(), old.next_part());
                assert_eq!(a, b, "trial {trial}, {at} bytes in, boundary {boundary:?}");
                match a {
                    None => break,
                    Some(ParseEvent::Part(_)) => parts_seen += 1,
                    Some(ParseEvent::Skipped { .. }) => skips += 1,
                }
                events += 1;
            }
            assert_eq!(new.buffered(), old.buffered());
            if rng.random_bool(0.002) {
                assert_eq!(new.reset(), old.reset());
            }
        }
    }
    // The streams exercised both the good path and the faults.
    assert!(
        parts_seen > 1500 && skips > 200,
        "{events} {parts_seen} {skips}"
    );
}

#[test]
fn resumable_scanning_agrees_on_marker_soup() {
    // Bytes drawn from markers, boundary pieces and line ends: fill
    // bytes, segments with odd lengths, missing markers (the plain
    // search), SOIs everywhere.
    use rand::{Rng, SeedableRng};
    let alphabet: &[u8] = b"\xFF\xFF\xFF\xD8\xD9\xDA\xE0\x00\x02\x10--fr\r\n\n";
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let (mut parts_seen, mut skips) = (0usize, 0usize);
    for trial in 0..600 {
        let n = rng.random_range(1..3000);
        let data: Vec<u8> = (0..n)
            .map(|_| alphabet[rng.random_range(0..alphabet.len())])
            .collect();
        let boundary = [Some("fr"), Some("-fr"), None][trial % 3];
        let max_part = [64, 500, 1 << 20][rng.random_range(0..3)];
        let mut new = PartParser::new(boundary, max_part);
        let mut old = RefParser::new(boundary, max_part);
        let mut at = 0;
        for c in chunks(&mut rng, data.len()) {
            new.push(&data[at..at + c]);
            old.push(&data[at..at + c]);
            at += c;
            loop {
                let (a, b) = (new.next_part(), old.next_part());
                assert_eq!(a, b, "trial {trial}, {at} bytes in");
                match a {
                    None => break,
                    Some(ParseEvent::Part(_)) => parts_seen += 1,
                    Some(ParseEvent::Skipped { .. }) => skips += 1,
                }
            }
        }
    }
    eprintln!("marker soup: {parts_seen} parts, {skips} skips");
    assert!(parts_seen > 500 && skips > 500, "{parts_seen} {skips}");
}

/// Feeds `data` in `chunk`-byte pieces; (bytes examined, parts, pushes).
fn examine(boundary: Option<&str>, data: &[u8], chunk: usize) -> (u64, usize, usize) {
    let mut p = PartParser::new(boundary, 1 << 20);
    let (mut got, mut pushes) = (0, 0);
    for piece in data.chunks(chunk) {
        p.push(piece);
        pushes += 1;
        got += parts(&mut p).0.len();
    }
    (p.bytes_examined(), got, pushes)
}

#[test]
fn scanning_work_is_linear_in_the_bytes_received() {
    use rand::SeedableRng;
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    for variant in 0..3 {
        // Good streams of the three framings: boundary with
        // Content-Length, boundary without, JPEG markers alone.
        let (boundary, data, n) = loop {
            let (b, d) = random_stream(&mut rng, 8, 30_000..40_000, false);
            let has_length = d.windows(15).any(|w| w == b"Content-Length:");
            let kind = match (b, has_length) {
                (Some(_), true) => 0,
                (Some(_), false) => 1,
                (None, _) => 2,
            };
            if kind == variant {
                break (b, d, 8);
            }
        };
        let blen = boundary.map_or(0, str::len) as u64;
        for chunk in [1, 7, 100, 1460, data.len()] {
            let (examined, got, pushes) = examine(boundary, &data, chunk);
            assert_eq!(got, n, "variant {variant} chunk {chunk}");
            let per_byte = examined as f64 / data.len() as f64;
            eprintln!(
                "variant {variant} ({boundary:?}), {} bytes in {chunk}-byte pieces: {examined} bytes examined ({per_byte:.2} per byte)",
                data.len()
            );
            // Each byte is looked at by at most three searches (the
            // boundary, a JPEG start, the JPEG walk) and once more when
            // a part is cut out; a search that resumes looks again at
            // the few bytes a split needle may straddle (its length
            // minus one) per push.
            let bound = 4 * data.len() as u64 + (blen + 8) * pushes as u64;
            assert!(examined <= bound, "{examined} > {bound}");
        }
    }
    // The work per byte does not grow with the part size (a rescan of
    // the buffer per push would make it grow with the part): parts 8x
    // larger, fed byte by byte.
    let small: Vec<u8> = (0..6)
        .flat_map(|_| {
            let mut v = b"--frame\r\n\r\n".to_vec();
            v.extend(camera_jpeg(&mut rng, 5_000));
            v
        })
        .collect();
    let large: Vec<u8> = (0..6)
        .flat_map(|_| {
            let mut v = b"--frame\r\n\r\n".to_vec();
            v.extend(camera_jpeg(&mut rng, 40_000));
            v
        })
        .collect();
    let (es, ps, _) = examine(Some("frame"), &small, 1);
    let (el, pl, _) = examine(Some("frame"), &large, 1);
    assert_eq!((ps, pl), (6, 6));
    let (rs, rl) = (
        es as f64 / small.len() as f64,
        el as f64 / large.len() as f64,
    );
    eprintln!(
        "byte by byte: {rs:.2} bytes examined per byte with 5 kB parts, {rl:.2} with 40 kB parts"
    );
    assert!(rl < rs * 1.1, "{rl} vs {rs}");
    // For scale: the old parser searched the whole unconsumed buffer on
    // each call that waited for more data; the bytes it had in hand at
    // those calls, with 1460-byte pieces:
    let mut old = RefParser::new(Some("frame"), 1 << 20);
    let mut rescanned = 0u64;
    for piece in large.chunks(1460) {
        old.push(piece);
        loop {
            let before = old.buffered() as u64;
            if old.next_part().is_none() {
                rescanned += before;
                break;
            }
        }
    }
    let (enew, _, _) = examine(Some("frame"), &large, 1460);
    eprintln!(
        "1460-byte pieces of 40 kB parts: the old parser rescanned {:.1} bytes per byte received, the new one examines {:.2}",
        rescanned as f64 / large.len() as f64,
        enew as f64 / large.len() as f64
    );
    assert!(enew < rescanned);
}
