//! Ports for the servers that tests start, chosen below the kernel's
//! ephemeral range (Linux: 32768-60999).
//!
//! Binding port 0, reading the port and dropping the socket leaves a window
//! in which any client that binds an ephemeral port (a `udpout:` link, a
//! Python peer, an HTTP client) can be handed that same port by the kernel;
//! CI saw "Address already in use" from exactly that. A port below the
//! ephemeral range is never handed out for port 0, so only another explicit
//! bind can take it, and successive calls in one process never repeat a
//! port (a counter walks the range with a step coprime to its length,
//! from a per-process start).
#![allow(dead_code)] // each test binary uses its own subset

use std::net::{TcpListener, UdpSocket};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

const LOW: u32 = 20_000;
const SPAN: u32 = 12_000;
/// Coprime with `SPAN` (a prime that does not divide it).
const STEP: u32 = 7_919;

static CALLS: AtomicU32 = AtomicU32::new(0);

fn candidates() -> impl Iterator<Item = u16> {
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.subsec_nanos())
        .unwrap_or(0);
    let start = std::process::id()
        .wrapping_mul(2_654_435_761)
        .wrapping_add(nanos)
        % SPAN;
    (0..SPAN).map(move |_| {
        let k = CALLS.fetch_add(1, Ordering::Relaxed);
        let offset = (u64::from(start) + u64::from(k) * u64::from(STEP)) % u64::from(SPAN);
        (LOW + offset as u32) as u16
    })
}

/// A UDP port on 127.0.0.1 that was free at the time of the call and that
/// no ephemeral bind can take.
pub fn free_udp_port() -> u16 {
    candidates()
        .find(|&p| UdpSocket::bind(("127.0.0.1", p)).is_ok())
        .expect("a free UDP port in 20000-31999")
}

/// A TCP port on 127.0.0.1 that was free at the time of the call and that
/// no ephemeral bind can take.
pub fn free_tcp_port() -> u16 {
    candidates()
        .find(|&p| TcpListener::bind(("127.0.0.1", p)).is_ok())
        .expect("a free TCP port in 20000-31999")
}
