//! The MJPEG server against a real TCP client speaking raw HTTP/1.1.

use std::sync::Arc;
use std::time::Duration;

use image::GrayImage;
use shotpilot_sim::video::{BOUNDARY, VideoFrame, serve_video};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

fn frame(seq: u64) -> Arc<VideoFrame> {
    let mut img = GrayImage::new(80, 60);
    for (i, p) in img.pixels_mut().enumerate() {
        p.0[0] = ((i as u64 * 7 + seq * 31) % 256) as u8;
    }
    Arc::new(VideoFrame::encode(&img, 80, 1_700_000_000.0 + seq as f64 * 0.033_333, seq).unwrap())
}

/// Reads a response head: status line and headers (lower-cased names).
async fn read_head<R: AsyncBufReadExt + Unpin>(r: &mut R) -> (u16, Vec<(String, String)>) {
    let mut line = String::new();
    r.read_line(&mut line).await.unwrap();
    let status: u16 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    let mut headers = Vec::new();
    loop {
        line.clear();
        r.read_line(&mut line).await.unwrap();
        let l = line.trim_end();
        if l.is_empty() {
            break;
        }
        let (k, v) = l.split_once(':').unwrap();
        headers.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
    }
    (status, headers)
}

fn header<'a>(h: &'a [(String, String)], name: &str) -> Option<&'a str> {
    h.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
}

/// Decodes HTTP/1.1 chunked transfer encoding into `out` until it holds `want` bytes.
async fn read_chunks<R: AsyncBufReadExt + Unpin>(r: &mut R, out: &mut Vec<u8>, want: usize) {
    while out.len() < want {
        let mut line = String::new();
        r.read_line(&mut line).await.unwrap();
        let size = usize::from_str_radix(line.trim(), 16).unwrap();
        assert!(size > 0, "stream ended early");
        let mut chunk = vec![0u8; size + 2];
        r.read_exact(&mut chunk).await.unwrap();
        assert_eq!(&chunk[size..], b"\r\n");
        out.extend_from_slice(&chunk[..size]);
    }
}

struct Part {
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

/// Parses complete multipart parts from the front of `buf`, removing them.
fn take_parts(buf: &mut Vec<u8>) -> Vec<Part> {
    let mut parts = Vec::new();
    loop {
        let delim = format!("--{BOUNDARY}\r\n");
        if buf.len() < delim.len() {
            break;
        }
        assert_eq!(
            &buf[..delim.len()],
            delim.as_bytes(),
            "part does not start with the boundary"
        );
        let Some(head_end) = buf.windows(4).position(|w| w == b"\r\n\r\n") else {
            break;
        };
        let head = std::str::from_utf8(&buf[delim.len()..head_end]).unwrap();
        let headers: Vec<(String, String)> = head
            .split("\r\n")
            .map(|l| {
                let (k, v) = l.split_once(':').unwrap();
                (k.trim().to_ascii_lowercase(), v.trim().to_string())
            })
            .collect();
        let len: usize = header(&headers, "content-length").unwrap().parse().unwrap();
        let start = head_end + 4;
        if buf.len() < start + len + 2 {
            break;
        }
        let body = buf[start..start + len].to_vec();
        assert_eq!(&buf[start + len..start + len + 2], b"\r\n");
        buf.drain(..start + len + 2);
        parts.push(Part { headers, body });
    }
    parts
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mjpeg_stream_and_snapshot_over_real_tcp() {
    let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (tx, rx) = watch::channel(None);
    let cancel = CancellationToken::new();
    let server = tokio::spawn(serve_video(listener, rx, cancel.clone()));

    // Snapshot before any frame: 503.
    let mut s = BufReader::new(TcpStream::connect(addr).await.unwrap());
    s.get_mut()
        .write_all(b"GET /snapshot.jpg HTTP/1.1\r\nHost: sim\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let (status, _) = read_head(&mut s).await;
    assert_eq!(status, 503);

    tx.send_replace(Some(frame(0)));
    let mut s = BufReader::new(TcpStream::connect(addr).await.unwrap());
    s.get_mut()
        .write_all(b"GET /video.mjpg HTTP/1.1\r\nHost: sim\r\n\r\n")
        .await
        .unwrap();
    let (status, headers) = read_head(&mut s).await;
    assert_eq!(status, 200);
    assert_eq!(
        header(&headers, "content-type").unwrap(),
        format!("multipart/x-mixed-replace; boundary={BOUNDARY}")
    );
    assert_eq!(header(&headers, "transfer-encoding"), Some("chunked"));

    // A producer at ~50 frames/s.
    let producer = {
        let tx = tx.clone();
        tokio::spawn(async move {
            for seq in 1..=40u64 {
                tokio::time::sleep(Duration::from_millis(20)).await;
                tx.send_replace(Some(frame(seq)));
            }
        })
    };
    let mut buf = Vec::new();
    let mut parts = Vec::new();
    while parts.len() < 12 {
        let want = buf.len() + 1;
        tokio::time::timeout(Duration::from_secs(5), read_chunks(&mut s, &mut buf, want))
            .await
            .unwrap();
        parts.extend(take_parts(&mut buf));
    }
    let mut last_seq = None;
    for p in &parts {
        assert_eq!(header(&p.headers, "content-type"), Some("image/jpeg"));
        let seq: u64 = header(&p.headers, "x-sequence").unwrap().parse().unwrap();
        let ts: f64 = header(&p.headers, "x-timestamp").unwrap().parse().unwrap();
        // The capture time travels to the microsecond.
        assert!((ts - frame(seq).capture_time_unix_s).abs() < 1e-6, "{ts}");
        assert_eq!(p.body, frame(seq).jpeg, "part {seq} is not the frame sent");
        let img = image::load_from_memory(&p.body).unwrap();
        assert_eq!((img.width(), img.height()), (80, 60));
        // Each frame at most once, in order.
        if let Some(prev) = last_seq {
            assert!(seq > prev, "{seq} after {prev}");
        }
        last_seq = Some(seq);
    }
    assert_eq!(
        header(&parts[0].headers, "x-sequence"),
        Some("0"),
        "the current frame comes first"
    );
    producer.await.unwrap();

    // Snapshot now returns the latest frame.
    let mut s2 = BufReader::new(TcpStream::connect(addr).await.unwrap());
    s2.get_mut()
        .write_all(b"GET /snapshot.jpg HTTP/1.1\r\nHost: sim\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let (status, headers) = read_head(&mut s2).await;
    assert_eq!(status, 200);
    assert_eq!(header(&headers, "content-type"), Some("image/jpeg"));
    assert_eq!(header(&headers, "x-sequence"), Some("40"));
    let len: usize = header(&headers, "content-length").unwrap().parse().unwrap();
    let mut body = vec![0u8; len];
    s2.read_exact(&mut body).await.unwrap();
    assert_eq!(body, frame(40).jpeg);

    // Cancelling ends the open stream and the server.
    cancel.cancel();
    tokio::time::timeout(Duration::from_secs(5), server)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    let mut rest = Vec::new();
    let n = tokio::time::timeout(Duration::from_secs(5), s.read_to_end(&mut rest))
        .await
        .unwrap()
        .unwrap();
    // Whatever was still buffered ends with the terminating zero-size chunk.
    assert!(
        n == 0 || rest.ends_with(b"0\r\n\r\n"),
        "stream did not end cleanly"
    );
}
