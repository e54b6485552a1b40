//! MJPEG over HTTP (`multipart/x-mixed-replace`) and snapshot polling.
//!
//! [`source`] is the client: a GET with hyper's HTTP/1.1 client (chunked
//! or close-delimited bodies), the bytes fed to [`parser`]'s incremental,
//! allocation-light, tolerant [`PartParser`]. A bad part is counted and
//! skipped; a dropped connection is reopened with exponential backoff. The
//! reader never waits for the decoder: whole JPEGs go into the ingest's
//! latest-value slot ([`super::live::Ingest`]).

pub mod parser;
pub mod source;

pub use parser::{ParseEvent, Part, PartParser, boundary_from_content_type, jpeg_end};
pub use source::{HttpUrl, backoff, fetch_snapshot, run_mjpeg, run_snapshots};

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
            reconnect_max_ms: 2000,
            max_part_bytes: 16 << 20,
            max_header_bytes: 16 << 10,
        }
    }
}
