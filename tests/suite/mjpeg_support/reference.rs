//! The MJPEG part parser as it was before scanning became resumable: it
//! rescans the whole unconsumed buffer on every call. Kept, for the tests only,
//! as the reference the resumable parser must agree with event for event.
#![allow(dead_code, missing_docs)]

use shotpilot::video::mjpeg::{ParseEvent, Part};

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    /// Looking for a boundary line (or a bare JPEG).
    Seek,
    /// After a boundary line: headers or a bare JPEG.
    Headers,
    /// In a body with a known length.
    Body { len: usize, timestamp: Option<f64> },
    /// In a body without a length: up to the next boundary, or the JPEG's
    /// end marker when it starts with one.
    OpenBody { timestamp: Option<f64> },
}

/// Incremental multipart/MJPEG parser: [`push`](Self::push) bytes, then call
/// [`next_part`](Self::next_part) until it returns `None`.
#[derive(Debug, Clone)]
pub struct RefParser {
    boundary: Option<Vec<u8>>,
    buf: Vec<u8>,
    pos: usize,
    state: State,
    max_part: usize,
}

/// Index of `needle` in `hay` (naive search with a first-byte skip; the
/// needle is short and the haystack is scanned once per part).
fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    if needle.is_empty() || hay.len() < needle.len() {
        return None;
    }
    let first = needle[0];
    let last_start = hay.len() - needle.len();
    let mut i = 0;
    while i <= last_start {
        match hay[i..=last_start].iter().position(|&b| b == first) {
            None => return None,
            Some(off) => {
                let j = i + off;
                if &hay[j..j + needle.len()] == needle {
                    return Some(j);
                }
                i = j + 1;
            }
        }
    }
    None
}

/// End (exclusive) of the JPEG starting at `buf[0]` (which must be an SOI),
/// found by walking the marker segments up to the scan and then scanning
/// the entropy-coded data for the EOI (FF D9; FF is byte-stuffed there, so
/// an embedded thumbnail's EOI in an APP segment is never mistaken for it).
/// `None` when the data is incomplete, or when a new SOI comes before the
/// end (a truncated JPEG followed by the next one).
pub fn jpeg_end(buf: &[u8]) -> Option<usize> {
    jpeg_scan(buf).ok()
}

/// [`jpeg_end`]'s walk: `Ok(end)`, or `Err(from)` when the data is
/// incomplete, where `from` is the first byte that is not inside a marker
/// segment (an SOI found there starts a new JPEG, so this one was cut
/// short; one inside a segment is data, e.g. an EXIF thumbnail).
fn jpeg_scan(buf: &[u8]) -> Result<usize, usize> {
    if buf.len() < 2 || buf[0] != 0xFF || buf[1] != 0xD8 {
        return Err(buf.len());
    }
    let mut i = 2;
    // Marker segments before the (first) scan.
    loop {
        // Skip fill bytes.
        while i < buf.len() && buf[i] == 0xFF && buf.get(i + 1) == Some(&0xFF) {
            i += 1;
        }
        if i + 1 >= buf.len() {
            return Err(i);
        }
        if buf[i] != 0xFF {
            // Not a marker where one must be: fall back to a plain search.
            return find(&buf[i..], &[0xFF, 0xD9]).map(|k| i + k + 2).ok_or(i);
        }
        let m = buf[i + 1];
        match m {
            0xD9 => return Ok(i + 2),
            // A new SOI where a marker must be: this JPEG has no end.
            0xD8 => return Err(i),
            0x01 | 0xD0..=0xD7 => {
                i += 2;
                continue;
            }
            _ => {}
        }
        if i + 3 >= buf.len() {
            return Err(i);
        }
        let len = u16::from_be_bytes([buf[i + 2], buf[i + 3]]) as usize;
        if len < 2 {
            return find(&buf[i..], &[0xFF, 0xD9]).map(|k| i + k + 2).ok_or(i);
        }
        let seg_end = i + 2 + len;
        if seg_end > buf.len() {
            // Inside a segment that has not fully arrived.
            return Err(buf.len());
        }
        if m == 0xDA {
            i = seg_end;
            break;
        }
        i = seg_end;
    }
    // Entropy-coded data (and possibly further scans): the first FF D9 that
    // is a marker.
    let scan = i;
    while i + 1 < buf.len() {
        match buf[i..].iter().position(|&b| b == 0xFF) {
            None => return Err(scan),
            Some(off) => {
                let j = i + off;
                match buf.get(j + 1) {
                    None => return Err(scan),
                    Some(0xD9) => return Ok(j + 2),
                    // An SOI cannot be in entropy-coded data: a new JPEG
                    // begins there and this one has no end.
                    Some(0xD8) => return Err(scan),
                    Some(_) => i = j + 1,
                }
            }
        }
    }
    Err(scan)
}

impl RefParser {
    /// A parser for parts separated by `boundary` (given without `--`; None:
    /// delimit by JPEG markers alone). `max_part` caps a part's size, bytes.
    pub fn new(boundary: Option<&str>, max_part: usize) -> Self {
        Self {
            boundary: boundary.map(|b| b.as_bytes().to_vec()),
            buf: Vec::with_capacity(1 << 16),
            pos: 0,
            state: State::Seek,
            max_part: max_part.max(64),
        }
    }

    /// Append received bytes.
    pub fn push(&mut self, data: &[u8]) {
        // Compact when the consumed prefix is large.
        if self.pos > 0 && (self.pos >= self.buf.len() / 2 || self.pos > 1 << 20) {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        self.buf.extend_from_slice(data);
    }

    /// Bytes buffered and not yet consumed.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Forget the buffered bytes (after a reconnect); returns how many.
    pub fn reset(&mut self) -> usize {
        let n = self.buffered();
        self.buf.clear();
        self.pos = 0;
        self.state = State::Seek;
        n
    }

    fn skip(&mut self, n: usize, reason: &'static str) -> Option<ParseEvent> {
        self.pos += n;
        Some(ParseEvent::Skipped { bytes: n, reason })
    }

    /// The next part or skipped run, or None when more bytes are needed.
    pub fn next_part(&mut self) -> Option<ParseEvent> {
        loop {
            let data = &self.buf[self.pos..];
            match self.state {
                State::Seek => {
                    let soi = find(data, &[0xFF, 0xD8, 0xFF]);
                    let bnd = self.boundary.as_deref().and_then(|b| find(data, b));
                    match (bnd, soi) {
                        (Some(b), s) if s.is_none_or(|s| b < s) => {
                            // The boundary line: the token, maybe "--", to LF.
                            let after = b + self.boundary.as_ref().map_or(0, Vec::len);
                            let Some(lf) = data[after..].iter().position(|&c| c == b'\n') else {
                                if data.len() - after > 256 {
                                    return self.skip(after, "boundary line without end");
                                }
                                return None;
                            };
                            self.pos += after + lf + 1;
                            self.state = State::Headers;
                            if b > 2 {
                                // Something other than "--" or CRLF before it.
                                let junk = data[..b].iter().filter(|c| !b"-\r\n".contains(c));
                                if junk.count() > 0 {
                                    return Some(ParseEvent::Skipped {
                                        bytes: b,
                                        reason: "data before the boundary",
                                    });
                                }
                            }
                        }
                        (_, Some(s)) => {
                            if s > 0 {
                                let junk = data[..s].iter().any(|c| !b"-\r\n".contains(c));
                                self.pos += s;
                                self.state = State::OpenBody { timestamp: None };
                                if junk && self.boundary.is_none() {
                                    return Some(ParseEvent::Skipped {
                                        bytes: s,
                                        reason: "data before a JPEG",
                                    });
                                }
                            } else {
                                self.state = State::OpenBody { timestamp: None };
                            }
                        }
                        _ => {
                            // Keep a tail that may hold a split boundary/SOI.
                            let keep = self.boundary.as_ref().map_or(2, |b| b.len() + 2);
                            if data.len() > keep + 4096 {
                                return self.skip(data.len() - keep, "no boundary or JPEG");
                            }
                            return None;
                        }
                    }
                }
                State::Headers => {
                    if data.len() >= 2 && data[0] == 0xFF && data[1] == 0xD8 {
                        self.state = State::OpenBody { timestamp: None };
                        continue;
                    }
                    if data.len() < 2 {
                        return None;
                    }
                    // Header block ends at an empty line (CRLFCRLF or LFLF,
                    // or directly if the first line is empty).
                    let end = if data.starts_with(b"\r\n") {
                        Some((0, 2))
                    } else if data.starts_with(b"\n") {
                        Some((0, 1))
                    } else {
                        match (find(data, b"\r\n\r\n"), find(data, b"\n\n")) {
                            (Some(a), Some(b)) if b + 1 < a => Some((b + 1, 1)),
                            (Some(a), _) => Some((a + 2, 2)),
                            (None, Some(b)) => Some((b + 1, 1)),
                            (None, None) => None,
                        }
                    };
                    let Some((hdr_end, sep)) = end else {
                        if data.len() > 8192 {
                            self.state = State::Seek;
                            return self.skip(data.len(), "part headers too long");
                        }
                        return None;
                    };
                    let mut len = None;
                    let mut timestamp = None;
                    for line in data[..hdr_end].split(|&c| c == b'\n') {
                        let line = std::str::from_utf8(line).unwrap_or("").trim();
                        let Some((k, v)) = line.split_once(':') else {
                            continue;
                        };
                        let k = k.trim();
                        let v = v.trim();
                        if k.eq_ignore_ascii_case("content-length") {
                            len = v.parse::<usize>().ok();
                        } else if k.eq_ignore_ascii_case("x-timestamp") {
                            timestamp = v.parse::<f64>().ok().filter(|t| t.is_finite());
                        }
                    }
                    self.pos += hdr_end + sep;
                    self.state = match len {
                        Some(l) if l <= self.max_part => State::Body { len: l, timestamp },
                        Some(_) => {
                            self.state = State::Seek;
                            return Some(ParseEvent::Skipped {
                                bytes: 0,
                                reason: "part longer than the limit",
                            });
                        }
                        None => State::OpenBody { timestamp },
                    };
                }
                State::Body { len, timestamp } => {
                    if data.len() < len {
                        // A length that is a lie: a boundary inside shows it.
                        if let Some(b) = self.boundary.as_deref()
                            && let Some(k) = find(data, b)
                            && k + b.len() + 2 < data.len()
                        {
                            self.state = State::Seek;
                            return self.skip(k, "part shorter than its Content-Length");
                        }
                        return None;
                    }
                    let body = &data[..len];
                    // Stop at a boundary inside the claimed length.
                    if let Some(b) = self.boundary.as_deref()
                        && let Some(k) = find(body, b)
                        && !(body.starts_with(&[0xFF, 0xD8]) && jpeg_end(body) == Some(len))
                    {
                        self.state = State::Seek;
                        return self.skip(k, "part shorter than its Content-Length");
                    }
                    let part = Part {
                        body: body.to_vec(),
                        timestamp,
                        had_headers: true,
                    };
                    self.pos += len;
                    self.state = State::Seek;
                    return Some(ParseEvent::Part(part));
                }
                State::OpenBody { timestamp } => {
                    let bnd = self.boundary.as_deref().and_then(|b| find(data, b));
                    if data.starts_with(&[0xFF, 0xD8]) {
                        // Delimit by the JPEG's own markers, unless a
                        // boundary comes first (a truncated JPEG).
                        let end = jpeg_end(data);
                        match (end.filter(|&e| bnd.is_none_or(|b| e <= b)), bnd) {
                            (Some(e), _) => {
                                let part = Part {
                                    body: data[..e].to_vec(),
                                    timestamp,
                                    had_headers: timestamp.is_some() || self.boundary.is_some(),
                                };
                                self.pos += e;
                                self.state = State::Seek;
                                return Some(ParseEvent::Part(part));
                            }
                            (_, Some(b)) => {
                                self.state = State::Seek;
                                return self.skip(b, "truncated JPEG");
                            }
                            (None, None) => {
                                // A new SOI after the start, outside the
                                // marker segments (which may hold an EXIF
                                // thumbnail), means this one was cut short.
                                let from = jpeg_scan(data).err().unwrap_or(data.len()).max(2);
                                if let Some(k) = find(&data[from..], &[0xFF, 0xD8, 0xFF])
                                    && from + k > 2
                                {
                                    self.state = State::Seek;
                                    return self.skip(from + k, "truncated JPEG");
                                }
                                if data.len() > self.max_part {
                                    self.state = State::Seek;
                                    return self.skip(data.len(), "part longer than the limit");
                                }
                                return None;
                            }
                        }
                    }
                    match bnd {
                        Some(b) => {
                            let mut end = b;
                            // Trim the delimiter's "--" and line break.
                            while end > 0 && matches!(data[end - 1], b'-') {
                                end -= 1;
                            }
                            while end > 0 && matches!(data[end - 1], b'\r' | b'\n') {
                                end -= 1;
                            }
                            let part = Part {
                                body: data[..end].to_vec(),
                                timestamp,
                                had_headers: true,
                            };
                            self.pos += b;
                            self.state = State::Seek;
                            return Some(ParseEvent::Part(part));
                        }
                        None => {
                            if data.len() > self.max_part {
                                self.state = State::Seek;
                                return self.skip(data.len(), "part longer than the limit");
                            }
                            return None;
                        }
                    }
                }
            }
        }
    }
}
