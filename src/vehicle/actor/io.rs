//! The link actor's connection task: connects from the URL, reads frames (each forwarded
//! to the other ground stations first), reconnects with exponential backoff.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::time::Duration;

use mavlink::dialects::common::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{AsyncMavConnection, MavHeader, MavlinkVersion};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

use crate::clock;
use crate::vehicle::router::Router;
use crate::vehicle::transport::{self, Connection, LinkUrl};

pub(super) enum IoEvent {
    Connected(Arc<Connection>),
    Frame(MavHeader, Box<MavMessage>),
    Lost(String),
    ConnectFailed(String),
}

/// Connects, reads, and reconnects with exponential backoff.
pub(super) struct IoTask {
    pub(super) url: LinkUrl,
    /// The `udpin:` socket once bound (kept across reconnections).
    pub(super) udp_in: Option<UdpSocket>,
    /// Its address, for [`LinkHandle::bound_addr`].
    pub(super) bound: watch::Sender<Option<SocketAddr>>,
    pub(super) version: MavlinkVersion,
    pub(super) signing: Option<transport::Signing>,
    pub(super) backoff_min: Duration,
    pub(super) backoff_max: Duration,
    pub(super) tx: mpsc::Sender<IoEvent>,
    pub(super) cancel: CancellationToken,
    /// Forwards the vehicle's frames to the other ground stations.
    pub(super) router: Arc<Router>,
}

impl IoTask {
    /// Binds the `udpin:` socket if it is not yet bound.
    async fn bind(&mut self) -> std::io::Result<()> {
        if self.udp_in.is_none()
            && let Some(socket) = transport::bind_udp_in(&self.url).await?
        {
            let addr = socket.local_addr()?;
            info!(%addr, "link listening");
            self.bound.send_replace(Some(addr));
            self.udp_in = Some(socket);
        }
        Ok(())
    }

    async fn open(&mut self) -> std::io::Result<Connection> {
        self.bind().await?;
        transport::connect(
            &self.url,
            self.udp_in.as_ref(),
            self.version,
            self.signing.as_ref(),
        )
        .await
    }

    pub(super) async fn run(mut self) {
        let mut backoff = self.backoff_min;
        loop {
            let cancel = self.cancel.clone();
            let attempt = tokio::select! {
                _ = cancel.cancelled() => return,
                r = self.open() => r,
            };
            match attempt {
                Ok(conn) => {
                    backoff = self.backoff_min;
                    let conn = Arc::new(conn);
                    self.router.set_vehicle(Some(conn.clone()));
                    if self
                        .tx
                        .send(IoEvent::Connected(conn.clone()))
                        .await
                        .is_err()
                    {
                        return;
                    }
                    loop {
                        let r = tokio::select! {
                            _ = self.cancel.cancelled() => return,
                            r = conn.recv_raw() => r,
                        };
                        match r {
                            Ok(raw) => {
                                // Forwarded first (the other stations wait on
                                // nothing of ours), then handled here.
                                let Some((h, m)) = self.router.on_vehicle_frame(&raw, clock::now())
                                else {
                                    debug!(id = raw.message_id(), "undecodable frame");
                                    continue;
                                };
                                if self.tx.send(IoEvent::Frame(h, Box::new(m))).await.is_err() {
                                    return;
                                }
                            }
                            // A frame with a valid CRC that does not decode (unknown id, bad enum): skip.
                            Err(MessageReadError::Parse(e)) => {
                                debug!(error = %e, "undecodable frame")
                            }
                            Err(MessageReadError::Io(e)) => {
                                self.router.set_vehicle(None);
                                let _ = self.tx.send(IoEvent::Lost(e.to_string())).await;
                                break;
                            }
                        }
                    }
                }
                Err(e) => {
                    if self
                        .tx
                        .send(IoEvent::ConnectFailed(e.to_string()))
                        .await
                        .is_err()
                    {
                        return;
                    }
                }
            }
            tokio::select! {
                _ = self.cancel.cancelled() => return,
                _ = tokio::time::sleep(backoff) => {}
            }
            backoff = (backoff * 2).min(self.backoff_max);
        }
    }
}
