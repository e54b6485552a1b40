//! The MJPEG reader against real local TCP servers: a normal stream,
//! boundary variants (and chunked transfer), a server that drops the
//! connection mid-frame and sends truncated JPEGs, a stalled consumer, and
//! snapshots. The servers send in lockstep with the consumer (the next
//! frame once the last one was taken), so every assertion is about order
//! and counts, never about how long something took.

use std::sync::Arc;
use std::time::Duration;

use image::{GrayImage, Luma};
use shotpilot::video::live::{Closed, Ingest};
use shotpilot::video::mjpeg::{self, MjpegError, Params};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// A 96x64 JPEG whose mean brightness encodes `i` (i * 2 grey levels).
fn jpeg(i: u32) -> Vec<u8> {
    let img = GrayImage::from_fn(96, 64, |x, y| {
        Luma([((i * 2) as u8).wrapping_add(((x ^ y) & 3) as u8)])
    });
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95)
        .encode_image(&img)
        .unwrap();
    out
}

fn mean(img: &GrayImage) -> f64 {
    img.pixels().map(|p| p.0[0] as f64).sum::<f64>() / (img.width() * img.height()) as f64
}

async fn read_request(s: &mut TcpStream) {
    let mut buf = vec![0u8; 4096];
    let mut got = Vec::new();
    while !got.windows(4).any(|w| w == b"\r\n\r\n") {
        let n = s.read(&mut buf).await.unwrap();
        if n == 0 {
            return;
        }
        got.extend_from_slice(&buf[..n]);
    }
}

fn part(boundary_line: &str, eol: &str, j: &[u8], ts: f64) -> Vec<u8> {
    let mut v = format!(
        "{boundary_line}{eol}Content-Type: image/jpeg{eol}Content-Length: {}{eol}X-Timestamp: {ts:.6}{eol}{eol}",
        j.len()
    )
    .into_bytes();
    v.extend_from_slice(j);
    v.extend_from_slice(eol.as_bytes());
    v
}

/// Start the reader and its decoder on `url`.
fn start(url: String) -> (Arc<Ingest>, CancellationToken, tokio::task::JoinHandle<()>) {
    let ingest = Arc::new(Ingest::new());
    ingest.spawn_decoder().unwrap();
    let cancel = CancellationToken::new();
    let params = Params {
        reconnect_min_ms: 20,
        reconnect_max_ms: 200,
        ..Params::default()
    };
    let (i2, c2) = (ingest.clone(), cancel.clone());
    let h = tokio::spawn(async move {
        mjpeg::run_mjpeg(&url, &params, i2, c2).await.unwrap();
    });
    (ingest, cancel, h)
}

/// The frames the consumer took, as it takes them (by image).
struct Taken(mpsc::UnboundedReceiver<u32>);

impl Taken {
    /// Wait until the consumer took `jpeg(i)` (the server sends the next
    /// frame only then, so no frame is ever replaced before it is taken).
    /// Panics on any other frame: the lockstep makes the order exact.
    async fn taken(&mut self, i: u32) {
        match self.0.recv().await {
            Some(got) => assert_eq!(got, i, "the consumer took frame {got}, expected {i}"),
            None => panic!("the consumer stopped before frame {i}"),
        }
    }
}

/// Which `jpeg(i)` a decoded image is (its mean is `2 i + 1.5`).
fn which(img: &GrayImage) -> u32 {
    let m = mean(img);
    let i = ((m - 1.5) / 2.0).round();
    assert!(
        i >= 0.0 && (m - (2.0 * i + 1.5)).abs() < 0.5,
        "not one of the test's images: mean {m}"
    );
    i as u32
}

/// A consumer (as SLAM is) on its own thread: takes every frame it can,
/// reports which image each is to the server, returns them with their
/// capture times once the ingest is closed.
type Consumer = tokio::task::JoinHandle<Vec<(u32, Option<f64>)>>;

fn consume(ingest: &Arc<Ingest>) -> (Taken, Consumer) {
    let (tx, rx) = mpsc::unbounded_channel();
    let ing = ingest.clone();
    let h = tokio::task::spawn_blocking(move || {
        let mut got = Vec::new();
        loop {
            match ing.take_frame(Duration::from_millis(100)) {
                Ok(Some(f)) => {
                    assert_eq!(f.image.dimensions(), (96, 64));
                    let i = which(&f.image);
                    got.push((i, f.capture_time));
                    let _ = tx.send(i);
                }
                Ok(None) => {}
                Err(Closed) => return got,
            }
        }
    });
    (Taken(rx), h)
}

/// `(i, Some(base + i))` for `i` in `range`: the frames a test expects.
fn stamped(range: std::ops::Range<u32>, base: f64) -> Vec<(u32, Option<f64>)> {
    range.map(|i| (i, Some(base + f64::from(i)))).collect()
}

/// A test must not hang when the reader misbehaves: this bounds a whole
/// scenario (a failure, not a measurement).
const HANG_GUARD: Duration = Duration::from_secs(60);

/// Run `server` (it returns what must stay open until the reader is
/// cancelled), then stop the reader, the decoder and the consumer.
async fn finish<T>(
    server: tokio::task::JoinHandle<T>,
    ingest: &Ingest,
    cancel: CancellationToken,
    reader: tokio::task::JoinHandle<()>,
    consumer: Consumer,
) -> Vec<(u32, Option<f64>)> {
    let kept = tokio::time::timeout(HANG_GUARD, server)
        .await
        .expect("the scenario hung")
        .expect("the server failed");
    cancel.cancel();
    reader.await.unwrap();
    drop(kept);
    ingest.close();
    consumer.await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn normal_stream_delivers_every_frame_with_timestamps() {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let (ingest, cancel, reader) = start(format!("http://{addr}/video.mjpg"));
    let (mut taken, consumer) = consume(&ingest);
    let server = tokio::spawn(async move {
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\nConnection: close\r\n\r\n").await.unwrap();
        for i in 0..20u32 {
            let t = 1000.0 + i as f64;
            s.write_all(&part("--frame", "\r\n", &jpeg(i), t))
                .await
                .unwrap();
            taken.taken(i).await;
        }
        s
    });
    let seen = finish(server, &ingest, cancel, reader, consumer).await;
    let c = ingest.counters.snapshot();
    assert_eq!(seen, stamped(0..20, 1000.0));
    assert_eq!(c.received, 20, "{c:?}");
    assert_eq!(c.decoded, 20, "{c:?}");
    assert_eq!(c.consumed, 20, "{c:?}");
    assert_eq!(
        (c.bad, c.dropped, c.errors, c.connects),
        (0, 0, 0, 1),
        "{c:?}"
    );
}

/// Serve one connection with the given head and body framing; returns the
/// counters and the stamps the consumer took.
async fn serve_variant(
    head: &'static str,
    boundary_line: &'static str,
    eol: &'static str,
    chunked: bool,
) -> (
    shotpilot::video::live::CountersSnapshot,
    Vec<(u32, Option<f64>)>,
) {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let (ingest, cancel, reader) = start(format!("http://{addr}/"));
    let (mut taken, consumer) = consume(&ingest);
    let server = tokio::spawn(async move {
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head.as_bytes()).await.unwrap();
        for i in 0..6u32 {
            let p = part(boundary_line, eol, &jpeg(i), i as f64);
            if chunked {
                // Split each part into two chunks at an odd place.
                let k = p.len() / 3;
                for c in [&p[..k], &p[k..]] {
                    s.write_all(format!("{:x}\r\n", c.len()).as_bytes())
                        .await
                        .unwrap();
                    s.write_all(c).await.unwrap();
                    s.write_all(b"\r\n").await.unwrap();
                }
            } else {
                s.write_all(&p).await.unwrap();
            }
            taken.taken(i).await;
        }
        s
    });
    let seen = finish(server, &ingest, cancel, reader, consumer).await;
    (ingest.counters.snapshot(), seen)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn boundary_variants_and_chunked_transfer() {
    let cases: [(&str, &str, &str, bool); 6] = [
        (
            "HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=\"frame\"\r\n\r\n",
            "--frame",
            "\r\n",
            false,
        ),
        (
            "HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=--frame\r\n\r\n",
            "--frame",
            "\r\n",
            false,
        ),
        (
            "HTTP/1.0 200 OK\nContent-Type: multipart/x-mixed-replace; boundary=frame\n\n",
            "--frame",
            "\n",
            false,
        ),
        (
            "HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n",
            "frame",
            "\r\n",
            false,
        ),
        (
            "HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\nTransfer-Encoding: chunked\r\n\r\n",
            "--frame",
            "\r\n",
            true,
        ),
        // No boundary in the header: JPEG markers delimit the frames.
        (
            "HTTP/1.1 200 OK\r\nContent-Type: video/x-motion-jpeg\r\n\r\n",
            "--whatever",
            "\r\n",
            false,
        ),
    ];
    for (head, line, eol, chunked) in cases {
        let (c, seen) = serve_variant(head, line, eol, chunked).await;
        if head.contains("boundary") {
            assert_eq!(seen, stamped(0..6, 0.0), "{head:?}");
        } else {
            // Without parts there are no part headers, so no timestamps.
            let frames: Vec<u32> = seen.iter().map(|f| f.0).collect();
            assert_eq!(frames, [0, 1, 2, 3, 4, 5], "{head:?}");
        }
        assert_eq!(c.decoded, 6, "{head:?}: {c:?}");
        assert_eq!(c.bad, 0, "{head:?}: {c:?}");
        assert_eq!(c.errors, 0, "{head:?}: {c:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn survives_dropped_connections_and_truncated_jpegs() {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let (ingest, cancel, reader) = start(format!("http://{addr}/video.mjpg"));
    let (mut taken, consumer) = consume(&ingest);
    let server = tokio::spawn(async move {
        let head =
            b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n";
        // Connection 1: 3 good, a truncated JPEG with an honest length, a
        // part whose length is a lie, a good one, then a drop in the
        // middle of a frame.
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head).await.unwrap();
        for i in 0..3u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), i as f64))
                .await
                .unwrap();
            taken.taken(i).await;
        }
        let j = jpeg(50);
        s.write_all(&part("--frame", "\r\n", &j[..j.len() / 2], 50.0))
            .await
            .unwrap();
        let mut lie = format!("--frame\r\nContent-Length: {}\r\n\r\n", j.len() + 500).into_bytes();
        lie.extend_from_slice(&j[..j.len() / 3]);
        lie.extend_from_slice(b"\r\n");
        s.write_all(&lie).await.unwrap();
        s.write_all(&part("--frame", "\r\n", &jpeg(3), 3.0))
            .await
            .unwrap();
        taken.taken(3).await;
        let p = part("--frame", "\r\n", &jpeg(51), 51.0);
        s.write_all(&p[..p.len() / 2]).await.unwrap();
        drop(s);
        // Connection 2: garbage, then 5 good frames, then drop.
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head).await.unwrap();
        s.write_all(b"\x00\x01garbage\r\n").await.unwrap();
        for i in 4..9u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), i as f64))
                .await
                .unwrap();
            taken.taken(i).await;
        }
        drop(s);
        // Connection 3: refuse by closing at once; connection 4: 3 frames,
        // kept open until the reader is cancelled.
        let (s, _) = l.accept().await.unwrap();
        drop(s);
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head).await.unwrap();
        for i in 9..12u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), i as f64))
                .await
                .unwrap();
            taken.taken(i).await;
        }
        (l, s)
    });
    let stamps = finish(server, &ingest, cancel, reader, consumer).await;
    let c = ingest.counters.snapshot();
    eprintln!("counters after faults: {c:?}");
    // Every good frame arrives, in order; none of the broken ones does.
    assert_eq!(stamps, stamped(0..12, 0.0));
    assert_eq!(c.decoded, 12, "{c:?}");
    assert_eq!(c.received, 12, "{c:?}");
    assert_eq!(c.bad, 3, "truncated, lying length, cut by drop: {c:?}");
    // Four connections, three of them ended by the server.
    assert_eq!((c.connects, c.errors), (4, 3), "{c:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_consumer_gets_the_newest_and_never_stalls_the_reader() {
    const N: u32 = 120;
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let frames: Vec<Vec<u8>> = (0..N).map(jpeg).collect();
    // The server sends all frames back to back, and nobody consumes.
    let server = tokio::spawn(async move {
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(
            b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n",
        )
        .await
        .unwrap();
        for (i, j) in frames.iter().enumerate() {
            s.write_all(&part("--frame", "\r\n", j, i as f64))
                .await
                .unwrap();
        }
        s
    });
    let (ingest, cancel, reader) = start(format!("http://{addr}/"));
    let mut decoded = ingest.subscribe();
    let last = (N - 1) as f64;
    // The reader reads the whole stream and the decoder reaches its last
    // frame while the consumer takes nothing.
    tokio::time::timeout(
        HANG_GUARD,
        decoded.wait_for(|f| f.as_ref().and_then(|f| f.capture_time) == Some(last)),
    )
    .await
    .expect("the last frame was never decoded")
    .unwrap();
    let before = ingest.counters.snapshot();
    // The consumer, waking up, gets the newest frame, and only that one.
    let ing = ingest.clone();
    let (first, second) = tokio::task::spawn_blocking(move || {
        (
            ing.take_frame(Duration::from_millis(100)),
            ing.take_frame(Duration::ZERO),
        )
    })
    .await
    .unwrap();
    let s = tokio::time::timeout(HANG_GUARD, server)
        .await
        .unwrap()
        .unwrap();
    cancel.cancel();
    reader.await.unwrap();
    drop(s);
    ingest.close();
    let c = ingest.counters.snapshot();
    eprintln!("stalled consumer: {N} frames sent, counters {c:?}");
    assert_eq!(before.received, N as u64, "{before:?}");
    assert_eq!(before.consumed, 0, "{before:?}");
    // Each part was decoded or replaced by a newer one before decoding;
    // each decoded frame but the newest was replaced before anyone took it.
    assert_eq!(c.decoded + c.dropped_undecoded, N as u64, "{c:?}");
    assert_eq!(c.dropped_unconsumed, c.decoded - 1, "{c:?}");
    assert_eq!(
        first.unwrap().and_then(|f| f.capture_time),
        Some(last),
        "the consumer must get the newest frame"
    );
    assert!(second.unwrap().is_none(), "a frame was handed out twice");
    assert_eq!((c.consumed, c.bad, c.errors), (1, 0, 0), "{c:?}");
}

/// Serve each of `responses` to one connection, in order; each is written
/// whole and the connection closed. The task ends (and the listener
/// closes) after the last one.
async fn serve_responses(
    responses: Vec<Vec<u8>>,
) -> (std::net::SocketAddr, tokio::task::JoinHandle<()>) {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let h = tokio::spawn(async move {
        for r in responses {
            let (mut s, _) = l.accept().await.unwrap();
            read_request(&mut s).await;
            s.write_all(&r).await.unwrap();
            s.shutdown().await.unwrap();
        }
    });
    (addr, h)
}

fn response(head: &str, body: &[u8]) -> Vec<u8> {
    let mut v = head.as_bytes().to_vec();
    v.extend_from_slice(body);
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn snapshots_keep_their_timestamp_and_bad_ones_are_refused() {
    let j = jpeg(7);
    let mut chunked = Vec::new();
    for c in [&j[..j.len() / 2], &j[j.len() / 2..]] {
        chunked.extend_from_slice(format!("{:x}\r\n", c.len()).as_bytes());
        chunked.extend_from_slice(c);
        chunked.extend_from_slice(b"\r\n");
    }
    chunked.extend_from_slice(b"0\r\n\r\n");
    let (addr, server) = serve_responses(vec![
        // With a length and a timestamp.
        response(
            &format!(
                "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nX-Timestamp: 1234.5\r\n\r\n",
                j.len()
            ),
            &j,
        ),
        // Chunked, no timestamp.
        response(
            "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nTransfer-Encoding: chunked\r\n\r\n",
            &chunked,
        ),
        // Delimited by the close.
        response("HTTP/1.0 200 OK\r\nContent-Type: image/jpeg\r\n\r\n", &j),
        // Cut short of its length.
        response(
            &format!(
                "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\n\r\n",
                j.len()
            ),
            &j[..j.len() / 2],
        ),
        // Not found.
        response("HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n", b""),
    ])
    .await;
    let url = format!("http://{addr}/snapshot.jpg");
    let params = Params::default();
    let counters = shotpilot::video::live::Counters::default();
    let get = || mjpeg::fetch_snapshot(&url, &params, &counters);
    assert_eq!(get().await.unwrap(), (j.clone(), Some(1234.5)));
    assert_eq!(get().await.unwrap(), (j.clone(), None));
    assert_eq!(get().await.unwrap(), (j.clone(), None));
    match get().await {
        Err(MjpegError::BadResponse { reason, .. }) => {
            assert!(reason.contains("truncated"), "{reason}")
        }
        other => panic!("a cut snapshot must be refused: {other:?}"),
    }
    match get().await {
        Err(MjpegError::BadResponse { reason, .. }) => assert!(reason.contains("404"), "{reason}"),
        other => panic!("a 404 must be refused: {other:?}"),
    }
    // Nobody listens any more: a clear I/O error, no panic.
    server.await.unwrap();
    assert!(matches!(get().await, Err(MjpegError::Io { .. })));
    assert!(matches!(
        mjpeg::fetch_snapshot("https://cam/x.jpg", &params, &counters).await,
        Err(MjpegError::BadUrl { .. })
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn snapshot_polling_feeds_the_ingest_with_capture_times() {
    // Three snapshots, then a server error: the poller pushes the three,
    // counts the error and keeps polling.
    let mut responses: Vec<Vec<u8>> = (0..3u32)
        .map(|i| {
            let j = jpeg(i);
            response(
                &format!(
                    "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nX-Timestamp: {}\r\n\r\n",
                    j.len(),
                    100 + i
                ),
                &j,
            )
        })
        .collect();
    responses.push(response(
        "HTTP/1.1 500 Internal Server Error\r\nContent-Length: 0\r\n\r\n",
        b"",
    ));
    let j = jpeg(3);
    responses.push(response(
        &format!(
            "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nX-Timestamp: 103\r\n\r\n",
            j.len()
        ),
        &j,
    ));
    let (addr, _server) = serve_responses(responses).await;
    let ingest = Arc::new(Ingest::new());
    ingest.spawn_decoder().unwrap();
    let mut decoded = ingest.subscribe();
    let cancel = CancellationToken::new();
    let params = Params {
        reconnect_min_ms: 10,
        ..Params::default()
    };
    let (i2, c2) = (ingest.clone(), cancel.clone());
    let url = format!("http://{addr}/snap.jpg");
    let poller = tokio::spawn(async move {
        mjpeg::run_snapshots(&url, 50.0, &params, i2, c2)
            .await
            .unwrap();
    });
    let mut stamps = Vec::new();
    tokio::time::timeout(HANG_GUARD, async {
        while stamps.last() != Some(&103.0) {
            decoded.changed().await.unwrap();
            let f = decoded.borrow_and_update().clone();
            if let Some(t) = f.and_then(|f| f.capture_time) {
                stamps.push(t);
            }
        }
    })
    .await
    .expect("the snapshots never arrived");
    cancel.cancel();
    poller.await.unwrap();
    ingest.close();
    let c = ingest.counters.snapshot();
    // The watch keeps only the newest, so some may be skipped, never
    // reordered; the last one always arrives.
    assert!(stamps.windows(2).all(|w| w[0] < w[1]), "{stamps:?}");
    assert_eq!(c.received, 4, "{c:?}");
    assert!(c.errors >= 1, "the 500 is an error: {c:?}");
    assert_eq!(c.bad, 0, "{c:?}");
}
