//! The MJPEG reader against real local TCP servers: a normal stream,
//! boundary variants (and chunked transfer), a server that drops the
//! connection mid-frame and sends truncated JPEGs, and a slow consumer.

use std::sync::Arc;
use std::time::{Duration, Instant};

use image::{GrayImage, Luma};
use shotpilot::video::live::Ingest;
use shotpilot::video::mjpeg::{self, Params};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
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

async fn wait_until(deadline_s: f64, mut f: impl FnMut() -> bool) -> bool {
    let t0 = Instant::now();
    while t0.elapsed().as_secs_f64() < deadline_s {
        if f() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    f()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn normal_stream_delivers_every_frame_with_timestamps() {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    tokio::spawn(async move {
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\nConnection: close\r\n\r\n").await.unwrap();
        for i in 0..20u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), 1000.0 + i as f64))
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        tokio::time::sleep(Duration::from_secs(10)).await;
    });
    let (ingest, cancel, h) = start(format!("http://{addr}/video.mjpg"));
    // Consume as fast as frames come: every frame is seen.
    let mut seen = Vec::new();
    let t0 = Instant::now();
    while seen.len() < 20 && t0.elapsed() < Duration::from_secs(10) {
        let ing = ingest.clone();
        if let Ok(Some(f)) =
            tokio::task::spawn_blocking(move || ing.take_frame(Duration::from_millis(100)))
                .await
                .unwrap()
        {
            seen.push(f);
        }
    }
    let c = ingest.counters.snapshot();
    cancel.cancel();
    h.await.unwrap();
    assert_eq!(c.received, 20, "{c:?}");
    assert_eq!(c.decoded, 20, "{c:?}");
    assert_eq!(c.bad, 0, "{c:?}");
    assert_eq!(seen.len(), 20);
    for (i, f) in seen.iter().enumerate() {
        assert_eq!(f.capture_time, Some(1000.0 + i as f64));
        assert!(
            (mean(&f.image) - (i as f64 * 2.0 + 1.5)).abs() < 1.5,
            "frame {i}: {}",
            mean(&f.image)
        );
        assert_eq!(f.image.dimensions(), (96, 64));
    }
}

/// Serve one connection with the given head and body writer behaviour.
async fn serve_variant(
    head: &'static str,
    boundary_line: &'static str,
    eol: &'static str,
    chunked: bool,
) -> Arc<Ingest> {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    tokio::spawn(async move {
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
            tokio::time::sleep(Duration::from_millis(15)).await;
        }
        tokio::time::sleep(Duration::from_secs(10)).await;
    });
    let (ingest, cancel, h) = start(format!("http://{addr}/"));
    let ing = ingest.clone();
    let ok = wait_until(5.0, || ing.counters.snapshot().decoded >= 6).await;
    cancel.cancel();
    h.await.unwrap();
    assert!(
        ok,
        "{head:?} {boundary_line:?}: {:?}",
        ingest.counters.snapshot()
    );
    ingest
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
        let ing = serve_variant(head, line, eol, chunked).await;
        let c = ing.counters.snapshot();
        assert_eq!(c.decoded, 6, "{head:?}: {c:?}");
        assert_eq!(c.bad, 0, "{head:?}: {c:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn survives_dropped_connections_and_truncated_jpegs() {
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    tokio::spawn(async move {
        let head =
            b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n";
        // Connection 1: 3 good, a truncated JPEG with an honest length, a
        // part whose length is a lie, then a drop in the middle of a frame.
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head).await.unwrap();
        let pause = || tokio::time::sleep(Duration::from_millis(10));
        for i in 0..3u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), i as f64))
                .await
                .unwrap();
            pause().await;
        }
        let j = jpeg(50);
        s.write_all(&part("--frame", "\r\n", &j[..j.len() / 2], 50.0))
            .await
            .unwrap();
        pause().await;
        let mut lie = format!("--frame\r\nContent-Length: {}\r\n\r\n", j.len() + 500).into_bytes();
        lie.extend_from_slice(&j[..j.len() / 3]);
        lie.extend_from_slice(b"\r\n");
        s.write_all(&lie).await.unwrap();
        pause().await;
        s.write_all(&part("--frame", "\r\n", &jpeg(3), 3.0))
            .await
            .unwrap();
        pause().await;
        let p = part("--frame", "\r\n", &jpeg(51), 51.0);
        s.write_all(&p[..p.len() / 2]).await.unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
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
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        drop(s);
        // Connection 3: refuse by closing at once; connection 4: 3 frames.
        let (s, _) = l.accept().await.unwrap();
        drop(s);
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(head).await.unwrap();
        for i in 9..12u32 {
            s.write_all(&part("--frame", "\r\n", &jpeg(i), i as f64))
                .await
                .unwrap();
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        tokio::time::sleep(Duration::from_secs(10)).await;
    });
    let (ingest, cancel, h) = start(format!("http://{addr}/video.mjpg"));
    let mut stamps = Vec::new();
    let t0 = Instant::now();
    while !stamps.contains(&11.0) && t0.elapsed() < Duration::from_secs(10) {
        let ing = ingest.clone();
        if let Ok(Some(f)) =
            tokio::task::spawn_blocking(move || ing.take_frame(Duration::from_millis(100)))
                .await
                .unwrap()
        {
            stamps.push(f.capture_time.unwrap());
        }
    }
    let c = ingest.counters.snapshot();
    cancel.cancel();
    h.await.unwrap();
    eprintln!("counters after faults: {c:?}");
    // Every good frame arrives (in order); none of the broken ones does.
    assert_eq!(c.decoded, 12, "{c:?}");
    assert_eq!(c.received, 12, "{c:?}");
    assert!(stamps.windows(2).all(|w| w[0] < w[1]), "{stamps:?}");
    assert_eq!(stamps.last(), Some(&11.0));
    assert!(!stamps.contains(&50.0) && !stamps.contains(&51.0));
    assert_eq!(c.bad, 3, "truncated, lying length, cut by drop: {c:?}");
    assert!(c.connects >= 4, "{c:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_consumer_gets_newest_and_reader_keeps_full_rate() {
    const N: u32 = 120;
    const PERIOD_MS: u64 = 10;
    let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = l.local_addr().unwrap();
    let frames: Vec<Vec<u8>> = (0..N).map(jpeg).collect();
    tokio::spawn(async move {
        let (mut s, _) = l.accept().await.unwrap();
        read_request(&mut s).await;
        s.write_all(
            b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n",
        )
        .await
        .unwrap();
        let mut tick = tokio::time::interval(Duration::from_millis(PERIOD_MS));
        for (i, j) in frames.iter().enumerate() {
            tick.tick().await;
            s.write_all(&part("--frame", "\r\n", j, i as f64))
                .await
                .unwrap();
        }
        tokio::time::sleep(Duration::from_secs(10)).await;
    });
    let (ingest, cancel, h) = start(format!("http://{addr}/"));
    // A consumer that takes 100 ms per frame (10x slower than the stream).
    let ing = ingest.clone();
    let consumer = tokio::task::spawn_blocking(move || {
        let mut taken = Vec::new();
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(8) {
            if let Ok(Some(f)) = ing.take_frame(Duration::from_millis(200)) {
                // How far behind the newest received part is this frame?
                let newest = ing.latest().map_or(0.0, |l| l.capture_time.unwrap_or(0.0));
                taken.push((f.capture_time.unwrap_or(-1.0), newest));
                if f.capture_time == Some((N - 1) as f64) {
                    break;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        }
        taken
    });
    let t0 = Instant::now();
    let ing = ingest.clone();
    assert!(wait_until(10.0, || ing.counters.snapshot().received >= N as u64).await);
    let read_time = t0.elapsed().as_secs_f64();
    let taken = consumer.await.unwrap();
    let c = ingest.counters.snapshot();
    cancel.cancel();
    h.await.unwrap();
    eprintln!(
        "slow consumer: {N} frames sent at {} fps, read in {read_time:.2} s ({:.1} fps), consumer took {}, counters {c:?}",
        1000 / PERIOD_MS,
        N as f64 / read_time,
        taken.len()
    );
    // The reader kept up: all parts read, in about the stream's duration.
    assert_eq!(c.received, N as u64);
    assert!(
        read_time < (N as f64 * PERIOD_MS as f64 / 1000.0) * 2.0 + 1.0,
        "{read_time}"
    );
    // The consumer saw few frames, each the newest at the time it was taken.
    assert!(taken.len() < 40, "{}", taken.len());
    assert!(c.dropped >= (N as u64) / 2, "{c:?}");
    for (got, newest) in &taken {
        assert!(
            newest - got <= 3.0,
            "took {got} while {newest} was available"
        );
    }
    assert_eq!(taken.last().map(|t| t.0), Some((N - 1) as f64));
}
