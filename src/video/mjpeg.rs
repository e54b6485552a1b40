//! MJPEG over HTTP (`multipart/x-mixed-replace`) and snapshot polling.
//!
//! The client is a plain HTTP/1.1 GET over a TCP stream (chunked or
//! close-delimited bodies) feeding an incremental, allocation-light
//! multipart parser ([`PartParser`]). The parser is tolerant: the boundary
//! may be quoted, sent with or without its leading `--`, lines may end in
//! CRLF or LF, parts may lack headers or `Content-Length` (then the JPEG's
//! own start/end markers delimit it), and garbage between parts is skipped.
//! A bad part is counted and skipped; a dropped connection is reopened
//! with exponential backoff. The reader never waits for the decoder: whole
//! JPEGs go into the ingest's latest-value slot ([`super::live::Ingest`]).

use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_util::sync::CancellationToken;

use super::live::{Counters, Ingest, RawPart, unix_now};

/// Errors of the HTTP video client.
#[derive(Debug, thiserror::Error)]
pub enum MjpegError {
    /// The URL is not `http://host[:port]/path`.
    #[error("bad video URL {url:?}: {reason}")]
    BadUrl {
        /// The URL.
        url: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// Connecting, writing or reading failed.
    #[error("video {url}: {source}")]
    Io {
        /// The URL.
        url: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// Nothing arrived within the timeout.
    #[error("video {url}: no data for {ms} ms")]
    Timeout {
        /// The URL.
        url: String,
        /// The timeout, ms.
        ms: u64,
    },
    /// The server's response is not usable.
    #[error("video {url}: bad response: {reason}")]
    BadResponse {
        /// The URL.
        url: String,
        /// What is wrong.
        reason: String,
    },
    /// The server closed the stream.
    #[error("video {url}: the server closed the stream")]
    Closed {
        /// The URL.
        url: String,
    },
}

/// Tunables of the HTTP video client.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Connect timeout, ms.
    pub connect_timeout_ms: u64,
    /// A connection that delivers no byte for this long is reopened, ms.
    pub read_timeout_ms: u64,
    /// First reconnect delay, ms (doubles per failure).
    pub reconnect_min_ms: u64,
    /// Largest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// Largest accepted part (JPEG), bytes; longer data is discarded.
    pub max_part_bytes: usize,
    /// Largest response header block, bytes.
    pub max_header_bytes: usize,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            connect_timeout_ms: 3000,
            read_timeout_ms: 5000,
            reconnect_min_ms: 100,
            reconnect_max_ms: 5000,
            max_part_bytes: 16 << 20,
            max_header_bytes: 16 << 10,
        }
    }
}

/// One part cut out of the stream.
#[derive(Debug, Clone, PartialEq)]
pub struct Part {
    /// The body bytes (a JPEG when the part is good).
    pub body: Vec<u8>,
    /// `X-Timestamp`, unix seconds.
    pub timestamp: Option<f64>,
    /// Whether the body was delimited by headers (false: by JPEG markers).
    pub had_headers: bool,
}

/// What [`PartParser::next_part`] produces.
#[derive(Debug, Clone, PartialEq)]
pub enum ParseEvent {
    /// A whole part.
    Part(Part),
    /// Data that was skipped as unusable (bytes, reason).
    Skipped {
        /// How many bytes.
        bytes: usize,
        /// Why.
        reason: &'static str,
    },
}

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
///
/// Scanning resumes where it stopped: each search remembers, in stream
/// offsets, the range in which it found no match, and the JPEG walk keeps
/// its place, so bytes that arrive in many small pieces are looked at a
/// bounded number of times each (the work is linear in the bytes received;
/// [`bytes_examined`](Self::bytes_examined) counts it).
#[derive(Debug, Clone)]
pub struct PartParser {
    boundary: Option<Vec<u8>>,
    buf: Vec<u8>,
    pos: usize,
    state: State,
    max_part: usize,
    /// Stream offset of `buf[0]` (bytes dropped by compaction before it).
    base: u64,
    /// Resumable searches: the boundary, a JPEG start (FF D8 FF), and the
    /// two header-block ends.
    bnd_scan: Scan,
    soi_scan: Scan,
    crlf2_scan: Scan,
    lf2_scan: Scan,
    /// The walk through the JPEG at the current position.
    walk: Option<JpegWalk>,
    examined: u64,
}

/// Index of `needle` in `hay` (naive search with a first-byte skip; the
/// needle is short).
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

/// A resumable search for one needle in a growing buffer. Offsets are
/// stream offsets (`base` + index), so they survive the buffer's
/// compaction: no match starts in `clear_from..clear_to`, and a later
/// search that starts inside that range goes on from its end instead of
/// looking at those bytes again.
#[derive(Debug, Clone, Copy, Default)]
struct Scan {
    clear_from: u64,
    clear_to: u64,
}

impl Scan {
    /// The first match of `needle` that starts at or after `buf[from]` and
    /// ends by `buf[limit]`, as an index into `buf` (whose first byte is at
    /// stream offset `base`). Adds the bytes looked at to `examined`.
    fn find(
        &mut self,
        buf: &[u8],
        base: u64,
        needle: &[u8],
        from: usize,
        limit: usize,
        examined: &mut u64,
    ) -> Option<usize> {
        let limit = limit.min(buf.len());
        let n = needle.len();
        let abs_from = base + from as u64;
        let mut start = from;
        if self.clear_from <= abs_from && abs_from < self.clear_to {
            start = usize::try_from(self.clear_to - base).unwrap_or(usize::MAX);
        }
        if n == 0 || start >= limit || limit - start < n {
            return None;
        }
        let hay = &buf[start..limit];
        let (found, clear_to) = match find(hay, needle) {
            Some(k) => {
                *examined += (k + n) as u64;
                (Some(start + k), base + (start + k) as u64)
            }
            None => {
                *examined += hay.len() as u64;
                (None, base + (limit - n + 1) as u64)
            }
        };
        // `abs_from..clear_to` is clear now (searched, or partly known
        // clear before); merge it with the old range when they touch.
        if abs_from <= self.clear_to && clear_to >= self.clear_from {
            self.clear_from = self.clear_from.min(abs_from);
            self.clear_to = self.clear_to.max(clear_to);
        } else {
            self.clear_from = abs_from;
            self.clear_to = clear_to;
        }
        found
    }
}

/// Where [`JpegWalk`] is.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Walking the marker segments before the first scan.
    Segments,
    /// In the entropy-coded data, which starts at `scan`.
    Entropy { scan: usize },
    /// A marker was missing where one must be: a plain search for FF D9
    /// from `from`.
    Plain { from: usize },
}

/// [`jpeg_scan`]'s walk through one JPEG, resumable as more of it arrives.
#[derive(Debug, Clone, Copy)]
struct JpegWalk {
    /// Stream offset of the JPEG's SOI.
    start: u64,
    /// Next index (from the SOI) to look at.
    i: usize,
    phase: Phase,
    /// The FF D9 search of [`Phase::Plain`].
    eoi: Scan,
}

impl JpegWalk {
    fn new(start: u64) -> Self {
        Self {
            start,
            i: 2,
            phase: Phase::Segments,
            eoi: Scan::default(),
        }
    }

    /// The walk over `buf`, the JPEG's bytes so far (`buf[0]` is its SOI,
    /// and `buf` only ever grows between calls): as [`jpeg_scan`].
    fn advance(&mut self, buf: &[u8], examined: &mut u64) -> Result<usize, usize> {
        if buf.len() < 2 || buf[0] != 0xFF || buf[1] != 0xD8 {
            return Err(buf.len());
        }
        loop {
            match self.phase {
                Phase::Plain { from } => {
                    return self
                        .eoi
                        .find(buf, self.start, &[0xFF, 0xD9], from, buf.len(), examined)
                        .map(|k| k + 2)
                        .ok_or(from);
                }
                Phase::Segments => {
                    let mut i = self.i;
                    // Skip fill bytes.
                    while i < buf.len() && buf[i] == 0xFF && buf.get(i + 1) == Some(&0xFF) {
                        i += 1;
                    }
                    *examined += (i - self.i) as u64;
                    self.i = i;
                    if i + 1 >= buf.len() {
                        return Err(i);
                    }
                    if buf[i] != 0xFF {
                        // Not a marker where one must be: a plain search.
                        self.phase = Phase::Plain { from: i };
                        continue;
                    }
                    let m = buf[i + 1];
                    match m {
                        0xD9 => return Ok(i + 2),
                        // A new SOI where a marker must be: no end.
                        0xD8 => return Err(i),
                        0x01 | 0xD0..=0xD7 => {
                            *examined += 2;
                            self.i = i + 2;
                            continue;
                        }
                        _ => {}
                    }
                    if i + 3 >= buf.len() {
                        return Err(i);
                    }
                    let len = u16::from_be_bytes([buf[i + 2], buf[i + 3]]) as usize;
                    if len < 2 {
                        self.phase = Phase::Plain { from: i };
                        continue;
                    }
                    let seg_end = i + 2 + len;
                    if seg_end > buf.len() {
                        // Inside a segment that has not fully arrived.
                        return Err(buf.len());
                    }
                    *examined += 4;
                    self.i = seg_end;
                    if m == 0xDA {
                        self.phase = Phase::Entropy { scan: seg_end };
                    }
                }
                Phase::Entropy { scan } => {
                    // The first FF D9 that is a marker (FF is byte-stuffed).
                    let mut i = self.i;
                    while i + 1 < buf.len() {
                        let Some(off) = buf[i..].iter().position(|&b| b == 0xFF) else {
                            *examined += (buf.len() - i) as u64;
                            self.i = buf.len();
                            return Err(scan);
                        };
                        *examined += off as u64 + 1;
                        let j = i + off;
                        match buf.get(j + 1) {
                            None => {
                                self.i = j;
                                return Err(scan);
                            }
                            Some(0xD9) => {
                                self.i = j;
                                return Ok(j + 2);
                            }
                            // An SOI cannot be in entropy-coded data: a new
                            // JPEG begins there and this one has no end.
                            Some(0xD8) => {
                                self.i = j;
                                return Err(scan);
                            }
                            Some(_) => i = j + 1,
                        }
                    }
                    self.i = i;
                    return Err(scan);
                }
            }
        }
    }
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
    JpegWalk::new(0).advance(buf, &mut 0)
}

/// The boundary from a `Content-Type` header value, unquoted and without a
/// leading `--`.
pub fn boundary_from_content_type(ct: &str) -> Option<String> {
    for param in ct.split(';').skip(1) {
        let (k, v) = match param.split_once('=') {
            Some(kv) => kv,
            None => continue,
        };
        if k.trim().eq_ignore_ascii_case("boundary") {
            let v = v.trim().trim_matches('"');
            let v = v.strip_prefix("--").unwrap_or(v);
            if !v.is_empty() {
                return Some(v.to_owned());
            }
        }
    }
    None
}

impl PartParser {
    /// A parser for parts separated by `boundary` (given without `--`; None:
    /// delimit by JPEG markers alone). `max_part` caps a part's size, bytes.
    pub fn new(boundary: Option<&str>, max_part: usize) -> Self {
        Self {
            boundary: boundary.map(|b| b.as_bytes().to_vec()),
            buf: Vec::with_capacity(1 << 16),
            pos: 0,
            state: State::Seek,
            max_part: max_part.max(64),
            base: 0,
            bnd_scan: Scan::default(),
            soi_scan: Scan::default(),
            crlf2_scan: Scan::default(),
            lf2_scan: Scan::default(),
            walk: None,
            examined: 0,
        }
    }

    /// Append received bytes.
    pub fn push(&mut self, data: &[u8]) {
        // Compact when the consumed prefix is large.
        if self.pos > 0 && (self.pos >= self.buf.len() / 2 || self.pos > 1 << 20) {
            self.buf.drain(..self.pos);
            self.base += self.pos as u64;
            self.pos = 0;
        }
        self.buf.extend_from_slice(data);
    }

    /// Bytes buffered and not yet consumed.
    pub fn buffered(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// Bytes the parser has looked at so far, over all its searches and
    /// JPEG walks (a byte looked at twice counts twice): the measure of its
    /// work, which grows linearly with the bytes pushed however they are
    /// split.
    pub fn bytes_examined(&self) -> u64 {
        self.examined
    }

    /// Forget the buffered bytes (after a reconnect); returns how many.
    pub fn reset(&mut self) -> usize {
        let n = self.buffered();
        self.base += self.buf.len() as u64;
        self.buf.clear();
        self.pos = 0;
        self.state = State::Seek;
        self.bnd_scan = Scan::default();
        self.soi_scan = Scan::default();
        self.crlf2_scan = Scan::default();
        self.lf2_scan = Scan::default();
        self.walk = None;
        n
    }

    fn skip(&mut self, n: usize, reason: &'static str) -> Option<ParseEvent> {
        self.pos += n;
        Some(ParseEvent::Skipped { bytes: n, reason })
    }

    /// The next match of the boundary at or after the current position and
    /// before `buf[limit]`, relative to the position.
    fn find_boundary(&mut self, limit: usize) -> Option<usize> {
        let b = self.boundary.as_deref()?;
        self.bnd_scan
            .find(&self.buf, self.base, b, self.pos, limit, &mut self.examined)
            .map(|q| q - self.pos)
    }

    /// The next JPEG start (FF D8 FF) at or after `from` bytes past the
    /// current position, relative to the position.
    fn find_soi(&mut self, from: usize) -> Option<usize> {
        let len = self.buf.len();
        self.soi_scan
            .find(
                &self.buf,
                self.base,
                &[0xFF, 0xD8, 0xFF],
                self.pos + from,
                len,
                &mut self.examined,
            )
            .map(|q| q - self.pos)
    }

    /// The next part or skipped run, or None when more bytes are needed.
    pub fn next_part(&mut self) -> Option<ParseEvent> {
        loop {
            let len = self.buf.len();
            match self.state {
                State::Seek => {
                    let soi = self.find_soi(0);
                    let bnd = self.find_boundary(len);
                    let data = &self.buf[self.pos..];
                    match (bnd, soi) {
                        (Some(b), s) if s.is_none_or(|s| b < s) => {
                            // The boundary line: the token, maybe "--", to LF.
                            let after = b + self.boundary.as_ref().map_or(0, Vec::len);
                            let lf = data[after..].iter().position(|&c| c == b'\n');
                            self.examined += lf.map_or(data.len() - after, |k| k + 1) as u64;
                            let Some(lf) = lf else {
                                if data.len() - after > 256 {
                                    return self.skip(after, "boundary line without end");
                                }
                                return None;
                            };
                            let junk = b > 2 && data[..b].iter().any(|c| !b"-\r\n".contains(c));
                            self.pos += after + lf + 1;
                            self.state = State::Headers;
                            if junk {
                                // Something other than "--" or CRLF before it.
                                return Some(ParseEvent::Skipped {
                                    bytes: b,
                                    reason: "data before the boundary",
                                });
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
                    let data = &self.buf[self.pos..];
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
                        let (pos, base) = (self.pos, self.base);
                        let crlf2 = self
                            .crlf2_scan
                            .find(&self.buf, base, b"\r\n\r\n", pos, len, &mut self.examined)
                            .map(|q| q - pos);
                        let lf2 = self
                            .lf2_scan
                            .find(&self.buf, base, b"\n\n", pos, len, &mut self.examined)
                            .map(|q| q - pos);
                        match (crlf2, lf2) {
                            (Some(a), Some(b)) if b + 1 < a => Some((b + 1, 1)),
                            (Some(a), _) => Some((a + 2, 2)),
                            (None, Some(b)) => Some((b + 1, 1)),
                            (None, None) => None,
                        }
                    };
                    let data = &self.buf[self.pos..];
                    let Some((hdr_end, sep)) = end else {
                        if data.len() > 8192 {
                            self.state = State::Seek;
                            return self.skip(data.len(), "part headers too long");
                        }
                        return None;
                    };
                    let mut length = None;
                    let mut timestamp = None;
                    self.examined += hdr_end as u64;
                    for line in data[..hdr_end].split(|&c| c == b'\n') {
                        let line = std::str::from_utf8(line).unwrap_or("").trim();
                        let Some((k, v)) = line.split_once(':') else {
                            continue;
                        };
                        let k = k.trim();
                        let v = v.trim();
                        if k.eq_ignore_ascii_case("content-length") {
                            length = v.parse::<usize>().ok();
                        } else if k.eq_ignore_ascii_case("x-timestamp") {
                            timestamp = v.parse::<f64>().ok().filter(|t| t.is_finite());
                        }
                    }
                    self.pos += hdr_end + sep;
                    self.state = match length {
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
                State::Body {
                    len: body_len,
                    timestamp,
                } => {
                    let have = len - self.pos;
                    if have < body_len {
                        // A length that is a lie: a boundary inside shows it.
                        let blen = self.boundary.as_ref().map_or(0, Vec::len);
                        if let Some(k) = self.find_boundary(len)
                            && k + blen + 2 < have
                        {
                            self.state = State::Seek;
                            return self.skip(k, "part shorter than its Content-Length");
                        }
                        return None;
                    }
                    // Stop at a boundary inside the claimed length.
                    let inside = self.find_boundary(self.pos + body_len);
                    let body = &self.buf[self.pos..self.pos + body_len];
                    if let Some(k) = inside {
                        self.examined += body_len as u64;
                        if !(body.starts_with(&[0xFF, 0xD8]) && jpeg_end(body) == Some(body_len)) {
                            self.state = State::Seek;
                            return self.skip(k, "part shorter than its Content-Length");
                        }
                    }
                    let part = Part {
                        body: body.to_vec(),
                        timestamp,
                        had_headers: true,
                    };
                    self.pos += body_len;
                    self.state = State::Seek;
                    return Some(ParseEvent::Part(part));
                }
                State::OpenBody { timestamp } => {
                    let bnd = self.find_boundary(len);
                    let pos = self.pos;
                    let data = &self.buf[pos..];
                    if data.starts_with(&[0xFF, 0xD8]) {
                        // Delimit by the JPEG's own markers, unless a
                        // boundary comes first (a truncated JPEG).
                        let abs = self.base + pos as u64;
                        let walk = match &mut self.walk {
                            Some(w) if w.start == abs => w,
                            slot => slot.insert(JpegWalk::new(abs)),
                        };
                        let scan = walk.advance(data, &mut self.examined);
                        match (scan.ok().filter(|&e| bnd.is_none_or(|b| e <= b)), bnd) {
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
                                let from = scan.err().unwrap_or(data.len()).max(2);
                                if let Some(k) = self.find_soi(from)
                                    && k > 2
                                {
                                    self.state = State::Seek;
                                    return self.skip(k, "truncated JPEG");
                                }
                                if len - pos > self.max_part {
                                    self.state = State::Seek;
                                    return self.skip(len - pos, "part longer than the limit");
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

/// A parsed `http://host[:port]/path` URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpUrl {
    /// `host:port` to connect to.
    pub authority: String,
    /// Host (for the Host header).
    pub host: String,
    /// Path and query, starting with `/`.
    pub path: String,
}

impl HttpUrl {
    /// Parse a plain-HTTP URL.
    pub fn parse(url: &str) -> Result<Self, MjpegError> {
        let bad = |reason| MjpegError::BadUrl {
            url: url.to_owned(),
            reason,
        };
        let rest = url
            .strip_prefix("http://")
            .ok_or_else(|| bad("only http:// is supported (use a bridge for RTSP/HTTPS)"))?;
        let (auth, path) = match rest.find('/') {
            Some(i) => (&rest[..i], &rest[i..]),
            None => (rest, "/"),
        };
        if auth.is_empty() {
            return Err(bad("no host"));
        }
        if auth.contains('@') {
            return Err(bad("credentials in the URL are not supported"));
        }
        let (host, authority) = if auth.starts_with('[') {
            match auth.rfind("]:") {
                Some(_) => (auth.to_owned(), auth.to_owned()),
                None => (auth.to_owned(), format!("{auth}:80")),
            }
        } else {
            match auth.rsplit_once(':') {
                Some((h, p)) => {
                    p.parse::<u16>().map_err(|_| bad("bad port"))?;
                    (h.to_owned(), auth.to_owned())
                }
                None => (auth.to_owned(), format!("{auth}:80")),
            }
        };
        Ok(Self {
            authority,
            host,
            path: path.to_owned(),
        })
    }
}

/// De-chunker for `Transfer-Encoding: chunked` bodies.
#[derive(Debug, Default)]
struct Dechunk {
    pending: Vec<u8>,
    remaining: usize,
    need_crlf: bool,
    done: bool,
}

impl Dechunk {
    /// Feed raw bytes; append decoded body bytes to `out`.
    fn feed(&mut self, data: &[u8], out: &mut Vec<u8>) -> Result<(), &'static str> {
        if self.done {
            return Ok(());
        }
        self.pending.extend_from_slice(data);
        let mut i = 0;
        let p = &self.pending;
        loop {
            if self.remaining > 0 {
                let n = self.remaining.min(p.len() - i);
                out.extend_from_slice(&p[i..i + n]);
                i += n;
                self.remaining -= n;
                if self.remaining > 0 {
                    break;
                }
                self.need_crlf = true;
            }
            if self.need_crlf {
                if p.len() - i < 1 {
                    break;
                }
                if p[i] == b'\r' {
                    if p.len() - i < 2 {
                        break;
                    }
                    i += 2;
                } else if p[i] == b'\n' {
                    i += 1;
                } else {
                    return Err("missing CRLF after a chunk");
                }
                self.need_crlf = false;
            }
            let Some(lf) = p[i..].iter().position(|&c| c == b'\n') else {
                if p.len() - i > 1024 {
                    return Err("chunk size line too long");
                }
                break;
            };
            let line = std::str::from_utf8(&p[i..i + lf]).map_err(|_| "bad chunk size")?;
            let size_str = line.trim().split(';').next().unwrap_or("").trim();
            let size = usize::from_str_radix(size_str, 16).map_err(|_| "bad chunk size")?;
            i += lf + 1;
            if size == 0 {
                self.done = true;
                break;
            }
            self.remaining = size;
        }
        self.pending.drain(..i);
        Ok(())
    }
}

/// The body framing of a response.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Framing {
    Chunked,
    Length(usize),
    Close,
}

/// A response head.
#[derive(Debug)]
struct Head {
    status: u16,
    content_type: Option<String>,
    timestamp: Option<f64>,
    framing: Framing,
}

fn parse_head(text: &str) -> Result<Head, String> {
    let mut lines = text.lines();
    let status_line = lines.next().ok_or("empty response")?;
    let mut it = status_line.split_whitespace();
    let proto = it.next().unwrap_or("");
    if !proto.starts_with("HTTP/") {
        return Err(format!("not HTTP: {status_line:?}"));
    }
    let status = it
        .next()
        .and_then(|s| s.parse::<u16>().ok())
        .ok_or_else(|| format!("bad status line {status_line:?}"))?;
    let mut head = Head {
        status,
        content_type: None,
        timestamp: None,
        framing: Framing::Close,
    };
    for line in lines {
        let Some((k, v)) = line.split_once(':') else {
            continue;
        };
        let (k, v) = (k.trim(), v.trim());
        if k.eq_ignore_ascii_case("content-type") {
            head.content_type = Some(v.to_owned());
        } else if k.eq_ignore_ascii_case("transfer-encoding")
            && v.to_ascii_lowercase().contains("chunked")
        {
            head.framing = Framing::Chunked;
        } else if k.eq_ignore_ascii_case("content-length") && head.framing != Framing::Chunked {
            if let Ok(n) = v.parse() {
                head.framing = Framing::Length(n);
            }
        } else if k.eq_ignore_ascii_case("x-timestamp") {
            head.timestamp = v.parse().ok().filter(|t: &f64| t.is_finite());
        }
    }
    Ok(head)
}

/// An open HTTP response body.
struct Body {
    stream: TcpStream,
    url: String,
    framing: Framing,
    dechunk: Dechunk,
    delivered: usize,
    read_timeout: Duration,
    scratch: Vec<u8>,
    /// Body bytes that arrived with the head, delivered first.
    prefix: Vec<u8>,
}

impl Body {
    /// Read the next body bytes into `out` (cleared first). `Ok(false)` at
    /// the end of the body.
    async fn read(&mut self, out: &mut Vec<u8>, counters: &Counters) -> Result<bool, MjpegError> {
        out.clear();
        if !self.prefix.is_empty() {
            std::mem::swap(out, &mut self.prefix);
            return Ok(true);
        }
        loop {
            if self.dechunk.done {
                return Ok(false);
            }
            if let Framing::Length(n) = self.framing
                && self.delivered >= n
            {
                return Ok(false);
            }
            let n =
                match tokio::time::timeout(self.read_timeout, self.stream.read(&mut self.scratch))
                    .await
                {
                    Err(_) => {
                        return Err(MjpegError::Timeout {
                            url: self.url.clone(),
                            ms: self.read_timeout.as_millis() as u64,
                        });
                    }
                    Ok(Err(source)) => {
                        return Err(MjpegError::Io {
                            url: self.url.clone(),
                            source,
                        });
                    }
                    Ok(Ok(n)) => n,
                };
            if n == 0 {
                return Ok(false);
            }
            counters
                .bytes
                .fetch_add(n as u64, std::sync::atomic::Ordering::Relaxed);
            let data = &self.scratch[..n];
            match self.framing {
                Framing::Chunked => {
                    self.dechunk
                        .feed(data, out)
                        .map_err(|r| MjpegError::BadResponse {
                            url: self.url.clone(),
                            reason: r.to_owned(),
                        })?;
                }
                Framing::Length(len) => {
                    let take = n.min(len - self.delivered);
                    out.extend_from_slice(&data[..take]);
                }
                Framing::Close => out.extend_from_slice(data),
            }
            self.delivered += out.len();
            if !out.is_empty() {
                return Ok(true);
            }
        }
    }
}

/// GET `url`; returns the response head and its body reader.
async fn open(url: &HttpUrl, raw_url: &str, params: &Params) -> Result<(Head, Body), MjpegError> {
    let io = |source| MjpegError::Io {
        url: raw_url.to_owned(),
        source,
    };
    let connect = TcpStream::connect(url.authority.as_str());
    let mut stream =
        tokio::time::timeout(Duration::from_millis(params.connect_timeout_ms), connect)
            .await
            .map_err(|_| MjpegError::Timeout {
                url: raw_url.to_owned(),
                ms: params.connect_timeout_ms,
            })?
            .map_err(io)?;
    stream.set_nodelay(true).map_err(io)?;
    let req = format!(
        "GET {} HTTP/1.1\r\nHost: {}\r\nUser-Agent: shotpilot\r\nAccept: multipart/x-mixed-replace, image/jpeg, */*\r\nConnection: close\r\n\r\n",
        url.path, url.host
    );
    stream.write_all(req.as_bytes()).await.map_err(io)?;
    let read_timeout = Duration::from_millis(params.read_timeout_ms);
    let mut head_buf = Vec::with_capacity(1024);
    let mut scratch = vec![0u8; 64 << 10];
    let (head_len, sep) = loop {
        let n = tokio::time::timeout(read_timeout, stream.read(&mut scratch))
            .await
            .map_err(|_| MjpegError::Timeout {
                url: raw_url.to_owned(),
                ms: params.read_timeout_ms,
            })?
            .map_err(io)?;
        if n == 0 {
            return Err(MjpegError::Closed {
                url: raw_url.to_owned(),
            });
        }
        head_buf.extend_from_slice(&scratch[..n]);
        if let Some(i) = find(&head_buf, b"\r\n\r\n") {
            break (i, 4);
        }
        if let Some(i) = find(&head_buf, b"\n\n") {
            break (i, 2);
        }
        if head_buf.len() > params.max_header_bytes {
            return Err(MjpegError::BadResponse {
                url: raw_url.to_owned(),
                reason: "response headers too long".into(),
            });
        }
    };
    let text = String::from_utf8_lossy(&head_buf[..head_len]).into_owned();
    let head = parse_head(&text).map_err(|reason| MjpegError::BadResponse {
        url: raw_url.to_owned(),
        reason,
    })?;
    if !(200..300).contains(&head.status) {
        return Err(MjpegError::BadResponse {
            url: raw_url.to_owned(),
            reason: format!("HTTP status {}", head.status),
        });
    }
    let mut body = Body {
        stream,
        url: raw_url.to_owned(),
        framing: head.framing,
        dechunk: Dechunk::default(),
        delivered: 0,
        read_timeout,
        scratch,
        prefix: Vec::new(),
    };
    // Body bytes that came with the head.
    let rest = head_buf[head_len + sep..].to_vec();
    let mut first = Vec::new();
    match body.framing {
        Framing::Chunked => {
            body.dechunk
                .feed(&rest, &mut first)
                .map_err(|r| MjpegError::BadResponse {
                    url: raw_url.to_owned(),
                    reason: r.to_owned(),
                })?;
        }
        Framing::Length(n) => first.extend_from_slice(&rest[..rest.len().min(n)]),
        Framing::Close => first = rest,
    }
    body.delivered = first.len();
    body.prefix = first;
    Ok((head, body))
}

/// Read one MJPEG connection to its end, pushing whole parts into `ingest`.
/// Returns how many parts it delivered.
async fn read_stream(
    url: &HttpUrl,
    raw_url: &str,
    params: &Params,
    ingest: &Ingest,
    cancel: &CancellationToken,
    delivered: &mut u64,
) -> Result<(), MjpegError> {
    let (head, mut body) = open(url, raw_url, params).await?;
    let ct = head.content_type.clone().unwrap_or_default();
    let boundary = boundary_from_content_type(&ct);
    if boundary.is_none() {
        tracing::warn!(url = raw_url, content_type = %ct, "no multipart boundary: delimiting frames by JPEG markers");
    }
    let mut parser = PartParser::new(boundary.as_deref(), params.max_part_bytes);
    let mut chunk = Vec::with_capacity(64 << 10);
    loop {
        let more = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = body.read(&mut chunk, &ingest.counters) => r,
        };
        let more = match more {
            Ok(m) => m,
            Err(e) => {
                if parser.buffered() > 0 {
                    Counters::inc(&ingest.counters.bad);
                }
                return Err(e);
            }
        };
        if !more {
            // A part cut off by the end of the stream is bad data.
            if parser.buffered() > 64 {
                Counters::inc(&ingest.counters.bad);
            }
            return Err(MjpegError::Closed {
                url: raw_url.to_owned(),
            });
        }
        parser.push(&chunk);
        while let Some(ev) = parser.next_part() {
            match ev {
                ParseEvent::Part(mut p) => {
                    // A JPEG without its end marker is truncated (decoders
                    // would fill the rest with grey): bad data.
                    match jpeg_end(&p.body) {
                        Some(end) => p.body.truncate(end),
                        None => {
                            Counters::inc(&ingest.counters.bad);
                            continue;
                        }
                    }
                    let now = Instant::now();
                    ingest.push_raw(RawPart {
                        jpeg: Arc::new(p.body),
                        capture_time: p.timestamp,
                        received: now,
                        received_unix: unix_now(),
                    });
                    *delivered += 1;
                }
                ParseEvent::Skipped { bytes, reason } => {
                    tracing::debug!(bytes, reason, "skipped MJPEG data");
                    // Text between parts is framing noise, not bad data.
                    if !reason.starts_with("data before") {
                        Counters::inc(&ingest.counters.bad);
                    }
                }
            }
        }
    }
}

/// The reconnect delay after `failures` consecutive failures.
pub fn backoff(params: &Params, failures: u32) -> Duration {
    let ms = params
        .reconnect_min_ms
        .saturating_mul(1u64 << failures.min(20))
        .min(params.reconnect_max_ms.max(params.reconnect_min_ms));
    Duration::from_millis(ms)
}

/// Read the MJPEG stream at `url` into `ingest` until `cancel` fires,
/// reconnecting with exponential backoff. Never returns early on bad data
/// or lost connections; fails at once only on a malformed URL.
pub async fn run_mjpeg(
    url: &str,
    params: &Params,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
) -> Result<(), MjpegError> {
    let parsed = HttpUrl::parse(url)?;
    let mut failures = 0u32;
    while !cancel.is_cancelled() {
        Counters::inc(&ingest.counters.connects);
        let mut delivered = 0;
        match read_stream(&parsed, url, params, &ingest, &cancel, &mut delivered).await {
            Ok(()) => break,
            Err(e) => {
                Counters::inc(&ingest.counters.errors);
                tracing::warn!(frames = delivered, "{e}");
            }
        }
        if delivered > 0 {
            failures = 0;
        }
        let delay = backoff(params, failures);
        failures = failures.saturating_add(1);
        tokio::select! {
            _ = cancel.cancelled() => break,
            _ = tokio::time::sleep(delay) => {}
        }
    }
    Ok(())
}

/// Fetch one snapshot: the whole body of a GET and its `X-Timestamp`.
pub async fn fetch_snapshot(
    url: &str,
    params: &Params,
    counters: &Counters,
) -> Result<(Vec<u8>, Option<f64>), MjpegError> {
    let parsed = HttpUrl::parse(url)?;
    let (head, mut body) = open(&parsed, url, params).await?;
    let mut all = Vec::new();
    let mut chunk = Vec::new();
    while body.read(&mut chunk, counters).await? {
        all.extend_from_slice(&chunk);
        if all.len() > params.max_part_bytes {
            return Err(MjpegError::BadResponse {
                url: url.to_owned(),
                reason: "snapshot larger than the limit".into(),
            });
        }
    }
    if let Framing::Length(n) = head.framing
        && all.len() < n
    {
        return Err(MjpegError::BadResponse {
            url: url.to_owned(),
            reason: format!("snapshot truncated at {} of {n} bytes", all.len()),
        });
    }
    Ok((all, head.timestamp))
}

/// Poll the snapshot URL at `rate_hz` into `ingest` until `cancel` fires.
/// Failures back off like the stream's reconnects.
pub async fn run_snapshots(
    url: &str,
    rate_hz: f64,
    params: &Params,
    ingest: Arc<Ingest>,
    cancel: CancellationToken,
) -> Result<(), MjpegError> {
    HttpUrl::parse(url)?;
    let period = Duration::from_secs_f64(1.0 / rate_hz.clamp(0.01, 200.0));
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut failures = 0u32;
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            _ = tick.tick() => {}
        }
        Counters::inc(&ingest.counters.connects);
        let r = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = fetch_snapshot(url, params, &ingest.counters) => r,
        };
        match r {
            Ok((jpeg, ts)) if jpeg_end(&jpeg).is_some() => {
                failures = 0;
                ingest.push_raw(RawPart {
                    jpeg: Arc::new(jpeg),
                    capture_time: ts,
                    received: Instant::now(),
                    received_unix: unix_now(),
                });
            }
            Ok(_) => Counters::inc(&ingest.counters.bad),
            Err(e) => {
                Counters::inc(&ingest.counters.errors);
                tracing::warn!("{e}");
                let delay = backoff(params, failures);
                failures = failures.saturating_add(1);
                tokio::select! {
                    _ = cancel.cancelled() => return Ok(()),
                    _ = tokio::time::sleep(delay) => {}
                }
            }
        }
    }
}

#[cfg(test)]
#[path = "mjpeg_reference.rs"]
mod reference;

#[cfg(test)]
mod tests {
    use super::*;

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

    #[test]
    fn jpeg_end_walks_segments_and_skips_stuffed_bytes() {
        let j = fake_jpeg(7);
        assert_eq!(jpeg_end(&j), Some(j.len()));
        for cut in 0..j.len() {
            assert_eq!(jpeg_end(&j[..cut]), None, "cut {cut}");
        }
    }

    #[test]
    fn boundary_variants_from_content_type() {
        let b = |s| boundary_from_content_type(s);
        assert_eq!(
            b("multipart/x-mixed-replace; boundary=frame").as_deref(),
            Some("frame")
        );
        assert_eq!(
            b("multipart/x-mixed-replace;boundary=\"--frame\"").as_deref(),
            Some("frame")
        );
        assert_eq!(
            b("multipart/x-mixed-replace; Boundary=--frame ; x=1").as_deref(),
            Some("frame")
        );
        assert_eq!(b("image/jpeg"), None);
    }

    fn stream(boundary_line: &str, eol: &str, headers: bool, length: bool, n: u8) -> Vec<u8> {
        let mut s = Vec::new();
        for i in 0..n {
            let j = fake_jpeg(i);
            s.extend_from_slice(format!("{boundary_line}{eol}").as_bytes());
            if headers {
                s.extend_from_slice(format!("Content-Type: image/jpeg{eol}").as_bytes());
                if length {
                    s.extend_from_slice(format!("Content-Length: {}{eol}", j.len()).as_bytes());
                }
                s.extend_from_slice(format!("X-Timestamp: {}.5{eol}", 100 + i as u32).as_bytes());
                s.extend_from_slice(eol.as_bytes());
            }
            s.extend_from_slice(&j);
            s.extend_from_slice(eol.as_bytes());
        }
        s
    }

    #[test]
    fn all_variants_yield_all_parts_fed_whole_and_byte_by_byte() {
        for (line, eol, headers, length) in [
            ("--frame", "\r\n", true, true),
            ("--frame", "\n", true, true),
            ("--frame", "\r\n", true, false),
            ("--frame", "\n", true, false),
            ("frame", "\r\n", true, true),
            ("----frame", "\r\n", true, true),
            ("--frame", "\r\n", false, false),
        ] {
            let data = stream(line, eol, headers, length, 5);
            for bytewise in [false, true] {
                let mut p = PartParser::new(Some("frame"), 1 << 20);
                let mut got = Vec::new();
                if bytewise {
                    for b in &data {
                        p.push(std::slice::from_ref(b));
                        got.extend(parts(&mut p).0);
                    }
                } else {
                    p.push(&data);
                    got = parts(&mut p).0;
                }
                assert_eq!(
                    got.len(),
                    5,
                    "{line:?} {eol:?} {headers} {length} {bytewise}"
                );
                for (i, part) in got.iter().enumerate() {
                    assert_eq!(
                        part.body,
                        fake_jpeg(i as u8),
                        "{line:?} {eol:?} {headers} {length}"
                    );
                    if headers {
                        assert_eq!(part.timestamp, Some(100.5 + i as f64));
                    }
                }
            }
        }
    }

    #[test]
    fn no_boundary_at_all_uses_jpeg_markers() {
        let mut data = b"garbage".to_vec();
        for i in 0..4 {
            data.extend_from_slice(&fake_jpeg(i));
            data.extend_from_slice(b"\r\n junk \r\n");
        }
        let mut p = PartParser::new(None, 1 << 20);
        p.push(&data);
        let (got, _) = parts(&mut p);
        assert_eq!(got.len(), 4);
        assert!(
            got.iter()
                .enumerate()
                .all(|(i, g)| g.body == fake_jpeg(i as u8))
        );
    }

    #[test]
    fn wrong_content_length_and_truncated_jpeg_resync() {
        let mut data = Vec::new();
        let j0 = fake_jpeg(0);
        // Length claims more than there is: the next boundary shows it.
        data.extend_from_slice(
            format!("--b\r\nContent-Length: {}\r\n\r\n", j0.len() + 40).as_bytes(),
        );
        data.extend_from_slice(&j0[..10]);
        data.extend_from_slice(b"\r\n");
        // A headerless truncated JPEG, then a good part.
        data.extend_from_slice(b"--b\r\n");
        data.extend_from_slice(&j0[..12]);
        data.extend_from_slice(b"\r\n");
        for i in 1..3 {
            let j = fake_jpeg(i);
            data.extend_from_slice(
                format!("--b\r\nContent-Length: {}\r\n\r\n", j.len()).as_bytes(),
            );
            data.extend_from_slice(&j);
            data.extend_from_slice(b"\r\n");
        }
        data.extend_from_slice(b"--b\r\n"); // so the length lie is visible
        let mut p = PartParser::new(Some("b"), 1 << 20);
        p.push(&data);
        let (got, skipped) = parts(&mut p);
        let good: Vec<_> = got
            .iter()
            .filter(|g| jpeg_end(&g.body) == Some(g.body.len()))
            .collect();
        assert_eq!(good.len(), 2, "{got:?}");
        assert_eq!(good[0].body, fake_jpeg(1));
        assert_eq!(good[1].body, fake_jpeg(2));
        assert!(skipped >= 2, "{skipped}");
    }

    /// A JPEG whose APP1 segment holds a whole thumbnail JPEG (as EXIF
    /// does), with a bigger entropy-coded part.
    fn jpeg_with_thumbnail(tag: u8) -> Vec<u8> {
        let thumb = fake_jpeg(tag.wrapping_add(100));
        let mut v = vec![0xFF, 0xD8, 0xFF, 0xE1];
        v.extend_from_slice(&((thumb.len() + 2 + 6) as u16).to_be_bytes());
        v.extend_from_slice(b"Exif\0\0");
        v.extend_from_slice(&thumb);
        v.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x04, 0x01, 0x02]);
        for k in 0..300u32 {
            v.push((k * 37 % 255) as u8);
        }
        v.extend_from_slice(&[tag, 0xFF, 0xD9]);
        v
    }

    // Found by the mjpeg_parser fuzz target: a JPEG carrying an embedded
    // JPEG in a marker segment, arriving in pieces without Content-Length,
    // was cut at the thumbnail's SOI as "truncated".
    #[test]
    fn thumbnail_in_a_segment_is_not_a_new_jpeg_when_fed_in_pieces() {
        for boundary in [Some("myboundary"), None] {
            let mut data = Vec::new();
            for i in 0..3 {
                if boundary.is_some() {
                    data.extend_from_slice(b"--myboundary\r\n\r\n");
                }
                data.extend_from_slice(&jpeg_with_thumbnail(i));
                data.extend_from_slice(b"\r\n");
            }
            for step in [1, 7, 64] {
                let mut p = PartParser::new(boundary, 1 << 20);
                let mut got = Vec::new();
                let mut skipped = 0;
                for piece in data.chunks(step) {
                    p.push(piece);
                    let (parts, s) = parts(&mut p);
                    got.extend(parts);
                    skipped += s;
                }
                assert_eq!(got.len(), 3, "{boundary:?} step {step}");
                assert_eq!(skipped, 0, "{boundary:?} step {step}");
                for (i, g) in got.iter().enumerate() {
                    assert_eq!(g.body, jpeg_with_thumbnail(i as u8));
                }
            }
        }
    }

    #[test]
    fn jpeg_cut_in_its_scan_is_skipped_when_the_next_one_starts() {
        let good = jpeg_with_thumbnail(1);
        let mut data = jpeg_with_thumbnail(0);
        data.truncate(data.len() - 120); // cut in the entropy-coded data
        data.extend_from_slice(&good);
        for step in [1, 13, data.len()] {
            let mut p = PartParser::new(None, 1 << 20);
            let mut got = Vec::new();
            let mut skipped = 0;
            for piece in data.chunks(step) {
                p.push(piece);
                let (parts, s) = parts(&mut p);
                got.extend(parts);
                skipped += s;
            }
            assert_eq!(got.len(), 1, "step {step}");
            assert_eq!(got[0].body, good);
            assert_eq!(skipped, 1, "step {step}");
        }
    }

    #[test]
    fn oversized_part_is_skipped_and_parser_recovers() {
        let mut data = b"--b\r\nContent-Length: 999999\r\n\r\n".to_vec();
        let j = fake_jpeg(3);
        data.extend_from_slice(format!("--b\r\nContent-Length: {}\r\n\r\n", j.len()).as_bytes());
        data.extend_from_slice(&j);
        let mut p = PartParser::new(Some("b"), 1000);
        p.push(&data);
        let (got, skipped) = parts(&mut p);
        assert_eq!(got.len(), 1);
        assert_eq!(got[0].body, j);
        assert!(skipped >= 1);
    }

    #[test]
    fn dechunk_decodes_split_chunks() {
        let enc = b"5\r\nhello\r\n6;ext=1\r\n world\r\n0\r\n\r\n";
        for split in 0..enc.len() {
            let mut d = Dechunk::default();
            let mut out = Vec::new();
            d.feed(&enc[..split], &mut out)
                .unwrap_or_else(|e| panic!("split {split} first: {e}"));
            d.feed(&enc[split..], &mut out)
                .unwrap_or_else(|e| panic!("split {split} second: {e}"));
            assert_eq!(out, b"hello world", "split {split}");
            assert!(d.done);
        }
    }

    #[test]
    fn urls_parse() {
        let u = HttpUrl::parse("http://127.0.0.1:8554/video.mjpg").unwrap();
        assert_eq!(u.authority, "127.0.0.1:8554");
        assert_eq!(u.path, "/video.mjpg");
        let u = HttpUrl::parse("http://cam").unwrap();
        assert_eq!((u.authority.as_str(), u.path.as_str()), ("cam:80", "/"));
        assert!(HttpUrl::parse("rtsp://cam/x").is_err());
        assert!(HttpUrl::parse("http://cam:99999/").is_err());
    }

    #[test]
    fn backoff_doubles_to_the_cap() {
        let p = Params::default();
        assert_eq!(backoff(&p, 0), Duration::from_millis(100));
        assert_eq!(backoff(&p, 3), Duration::from_millis(800));
        assert_eq!(backoff(&p, 30), Duration::from_millis(5000));
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
            let mut old = reference::RefParser::new(boundary, max_part);
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
            let mut old = reference::RefParser::new(boundary, max_part);
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
        let mut old = reference::RefParser::new(Some("frame"), 1 << 20);
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
}
