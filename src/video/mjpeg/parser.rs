//! The multipart/MJPEG part parser: the product's own, tolerant, fuzzed
//! (`fuzz/fuzz_targets/mjpeg_parser.rs`) and tested against the
//! rescanning reference parser (`tests/suite/mjpeg_parser.rs`).
//!
//! The boundary may be quoted, sent with or without its leading `--`,
//! lines may end in CRLF or LF, parts may lack headers or
//! `Content-Length` (then the JPEG's own start/end markers delimit it),
//! and garbage between parts is skipped. Scanning resumes where it
//! stopped, so the work is linear in the bytes received.

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
}
