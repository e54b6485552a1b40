//! The HTTP side: a GET with hyper's HTTP/1.1 client over a tokio TCP
//! stream (status line, headers, chunked or close-delimited bodies are
//! hyper's), the stream's bytes fed to the [`PartParser`], whole JPEGs
//! pushed into the ingest; reconnects with exponential backoff; snapshot
//! polling.

use std::future::poll_fn;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use hyper::body::{Body as _, Incoming};
use hyper::header::{ACCEPT, CONNECTION, CONTENT_LENGTH, CONTENT_TYPE, HOST, USER_AGENT};
use hyper::{Request, Uri};
use hyper_util::rt::TokioIo;
use tokio::net::TcpStream;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use super::parser::{ParseEvent, PartParser, boundary_from_content_type, jpeg_end};
use super::{MjpegError, Params};
use crate::video::live::{Counters, Ingest, RawPart, unix_now};

/// A parsed `http://host[:port]/path` URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpUrl {
    /// `host:port` to connect to.
    pub authority: String,
    /// The request's Host header.
    pub host: String,
    /// Path and query, starting with `/`.
    pub path: String,
}

impl HttpUrl {
    /// Parse a plain-HTTP URL (with the `http` crate's URI parser).
    pub fn parse(url: &str) -> Result<Self, MjpegError> {
        let bad = |reason| MjpegError::BadUrl {
            url: url.to_owned(),
            reason,
        };
        if !url.starts_with("http://") {
            return Err(bad(
                "only http:// is supported (use a bridge for RTSP/HTTPS)",
            ));
        }
        let uri: Uri = url.parse().map_err(|_| bad("not a valid URL"))?;
        let auth = uri.authority().ok_or_else(|| bad("no host"))?;
        if auth.as_str().contains('@') {
            return Err(bad("credentials in the URL are not supported"));
        }
        if auth.host().is_empty() {
            return Err(bad("no host"));
        }
        let host = auth.host();
        // `Authority::port` hides a port that does not parse (`:99999`):
        // read what follows the host ourselves.
        let port = match auth.as_str().get(host.len()..).unwrap_or("") {
            "" => 80,
            rest => rest
                .strip_prefix(':')
                .and_then(|p| p.parse::<u16>().ok())
                .ok_or_else(|| bad("bad port"))?,
        };
        Ok(Self {
            authority: format!("{host}:{port}"),
            host: auth.as_str().to_owned(),
            path: uri
                .path_and_query()
                .map_or_else(|| "/".to_owned(), |p| p.as_str().to_owned()),
        })
    }
}

/// A response head.
#[derive(Debug)]
struct Head {
    content_type: Option<String>,
    timestamp: Option<f64>,
    content_length: Option<usize>,
}

/// The connection task, aborted when the response is dropped.
struct Connection(JoinHandle<()>);

impl Drop for Connection {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// An open response body.
struct Body {
    incoming: Incoming,
    url: String,
    read_timeout: Duration,
    _connection: Connection,
}

/// A hyper error as the client's error: a connection that ended early
/// (before the head, or inside a body of known length or a chunk) is
/// [`MjpegError::Closed`], one that failed is [`MjpegError::Io`], anything
/// else a bad response.
fn from_hyper(url: &str, e: hyper::Error) -> MjpegError {
    let io = std::error::Error::source(&e).and_then(|s| s.downcast_ref::<std::io::Error>());
    let cut = io.is_some_and(|io| io.kind() == std::io::ErrorKind::UnexpectedEof);
    if e.is_incomplete_message() || e.is_closed() || e.is_canceled() || cut {
        return MjpegError::Closed {
            url: url.to_owned(),
        };
    }
    if let Some(io) = io {
        return MjpegError::Io {
            url: url.to_owned(),
            source: std::io::Error::new(io.kind(), io.to_string()),
        };
    }
    MjpegError::BadResponse {
        url: url.to_owned(),
        reason: e.to_string(),
    }
}

impl Body {
    /// The next body bytes; `Ok(None)` at the end of the body.
    async fn next(
        &mut self,
        counters: &Counters,
    ) -> Result<Option<hyper::body::Bytes>, MjpegError> {
        loop {
            let frame = poll_fn(|cx| Pin::new(&mut self.incoming).poll_frame(cx));
            let frame = tokio::time::timeout(self.read_timeout, frame)
                .await
                .map_err(|_| MjpegError::Timeout {
                    url: self.url.clone(),
                    ms: self.read_timeout.as_millis() as u64,
                })?;
            match frame {
                None => return Ok(None),
                Some(Err(e)) => return Err(from_hyper(&self.url, e)),
                Some(Ok(f)) => {
                    // Trailers carry no image bytes.
                    if let Ok(data) = f.into_data()
                        && !data.is_empty()
                    {
                        counters
                            .bytes
                            .fetch_add(data.len() as u64, std::sync::atomic::Ordering::Relaxed);
                        return Ok(Some(data));
                    }
                }
            }
        }
    }
}

/// GET `url`; returns the response head and its body.
async fn open(url: &HttpUrl, raw_url: &str, params: &Params) -> Result<(Head, Body), MjpegError> {
    let io = |source| MjpegError::Io {
        url: raw_url.to_owned(),
        source,
    };
    let connect = TcpStream::connect(url.authority.as_str());
    let stream = tokio::time::timeout(Duration::from_millis(params.connect_timeout_ms), connect)
        .await
        .map_err(|_| MjpegError::Timeout {
            url: raw_url.to_owned(),
            ms: params.connect_timeout_ms,
        })?
        .map_err(io)?;
    stream.set_nodelay(true).map_err(io)?;
    let read_timeout = Duration::from_millis(params.read_timeout_ms);
    let timed_out = || MjpegError::Timeout {
        url: raw_url.to_owned(),
        ms: params.read_timeout_ms,
    };
    let (mut sender, conn) = hyper::client::conn::http1::Builder::new()
        // The read buffer bounds the response head (hyper needs 8 KiB).
        .max_buf_size(params.max_header_bytes.max(8192))
        .handshake::<_, String>(TokioIo::new(stream))
        .await
        .map_err(|e| from_hyper(raw_url, e))?;
    let log_url = raw_url.to_owned();
    let connection = Connection(tokio::spawn(async move {
        if let Err(e) = conn.await {
            tracing::debug!(url = log_url, "video connection: {e}");
        }
    }));
    let request = Request::get(url.path.as_str())
        .header(HOST, url.host.as_str())
        .header(USER_AGENT, "shotpilot")
        .header(ACCEPT, "multipart/x-mixed-replace, image/jpeg, */*")
        .header(CONNECTION, "close")
        .body(String::new())
        .map_err(|e| MjpegError::BadUrl {
            url: raw_url.to_owned(),
            reason: if e.is::<hyper::http::uri::InvalidUri>() {
                "bad path"
            } else {
                "not a valid request"
            },
        })?;
    let response = tokio::time::timeout(read_timeout, sender.send_request(request))
        .await
        .map_err(|_| timed_out())?
        .map_err(|e| from_hyper(raw_url, e))?;
    let status = response.status();
    if !status.is_success() {
        return Err(MjpegError::BadResponse {
            url: raw_url.to_owned(),
            reason: format!("HTTP status {}", status.as_u16()),
        });
    }
    let headers = response.headers();
    let text = |name: &str| {
        headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::trim)
    };
    let head = Head {
        content_type: text(CONTENT_TYPE.as_str()).map(str::to_owned),
        timestamp: text("x-timestamp")
            .and_then(|v| v.parse().ok())
            .filter(|t: &f64| t.is_finite()),
        content_length: text(CONTENT_LENGTH.as_str()).and_then(|v| v.parse().ok()),
    };
    let body = Body {
        incoming: response.into_body(),
        url: raw_url.to_owned(),
        read_timeout,
        _connection: connection,
    };
    Ok((head, body))
}

/// Read one MJPEG connection to its end, pushing whole parts into `ingest`.
/// Counts the parts it delivered in `delivered`.
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
    loop {
        let chunk = tokio::select! {
            _ = cancel.cancelled() => return Ok(()),
            r = body.next(&ingest.counters) => r,
        };
        let chunk = match chunk {
            Ok(Some(c)) => c,
            Ok(None) | Err(MjpegError::Closed { .. }) => {
                // A part cut off by the end of the stream is bad data.
                if parser.buffered() > 64 {
                    Counters::inc(&ingest.counters.bad);
                }
                return Err(MjpegError::Closed {
                    url: raw_url.to_owned(),
                });
            }
            Err(e) => {
                if parser.buffered() > 0 {
                    Counters::inc(&ingest.counters.bad);
                }
                return Err(e);
            }
        };
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
                    ingest.push_raw(RawPart {
                        jpeg: Arc::new(p.body),
                        capture_time: p.timestamp,
                        received: crate::clock::now(),
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
    let truncated = |got: usize| {
        head.content_length
            .filter(|&n| got < n)
            .map(|n| MjpegError::BadResponse {
                url: url.to_owned(),
                reason: format!("snapshot truncated at {got} of {n} bytes"),
            })
    };
    loop {
        match body.next(counters).await {
            Ok(Some(chunk)) => {
                all.extend_from_slice(&chunk);
                if all.len() > params.max_part_bytes {
                    return Err(MjpegError::BadResponse {
                        url: url.to_owned(),
                        reason: "snapshot larger than the limit".into(),
                    });
                }
            }
            Ok(None) => break,
            Err(MjpegError::Closed { .. }) if truncated(all.len()).is_some() => {
                return Err(truncated(all.len()).unwrap_or(MjpegError::Closed {
                    url: url.to_owned(),
                }));
            }
            Err(e) => return Err(e),
        }
    }
    if let Some(e) = truncated(all.len()) {
        return Err(e);
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
                    received: crate::clock::now(),
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
mod tests {
    use super::*;

    #[test]
    fn urls_parse() {
        let u = HttpUrl::parse("http://127.0.0.1:8554/video.mjpg").unwrap();
        assert_eq!(u.authority, "127.0.0.1:8554");
        assert_eq!(u.path, "/video.mjpg");
        let u = HttpUrl::parse("http://cam").unwrap();
        assert_eq!((u.authority.as_str(), u.path.as_str()), ("cam:80", "/"));
        assert!(HttpUrl::parse("rtsp://cam/x").is_err());
        assert!(HttpUrl::parse("http://cam:99999/").is_err());
        assert!(HttpUrl::parse("http://cam:/").is_err());
        assert!(HttpUrl::parse("http://user:pw@cam/").is_err());
        assert!(HttpUrl::parse("http:///x").is_err());
        let u = HttpUrl::parse("http://[::1]:8080/snap?q=1").unwrap();
        assert_eq!(u.authority, "[::1]:8080");
        assert_eq!(u.path, "/snap?q=1");
    }

    #[test]
    fn backoff_doubles_to_the_cap() {
        let p = Params::default();
        assert_eq!(backoff(&p, 0), Duration::from_millis(100));
        assert_eq!(backoff(&p, 3), Duration::from_millis(800));
        assert_eq!(backoff(&p, 30), Duration::from_millis(2000));
    }
}
