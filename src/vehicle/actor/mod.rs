//! The link actor: one task owns the connection and everything that talks on it.
//!
//! This file spawns it ([`spawn`]) and runs its loop: timers first
//! (heartbeats, the link-lost watch, protocol timeouts, resends), the
//! operator's commands, the connection's events, the mission gate kept in
//! step. The files below it (each pointing only further down) hold the rest:
//! `telemetry` what the vehicle sends (telemetry, heartbeats, message rates);
//! `commands` the operator's commands (mission transfers started and
//! delivered, COMMAND_LONG and its ACK, the stop, gimbal control); `state`
//! the actor's state and what every part uses (header, flush, peers; the
//! clock is [`crate::clock`], tokio's, so tests run the timers paused); `transfer` a mission transfer in flight and its outcome;
//! `pending` a command waiting for its ACK; `io` the connection task;
//! `camera` the camera protocol's messages read into the handle's types.

mod camera;
mod commands;
mod guided;
mod io;
mod pending;
mod state;
mod telemetry;
mod transfer;

pub use guided::{GUIDED_PERIOD, guided_setpoint_message};

use std::net::UdpSocket;
use std::sync::Arc;
use std::time::{Duration, Instant};

use mavlink::MavlinkVersion;
use mavlink::dialects::common::{
    HEARTBEAT_DATA, MavAutopilot, MavMessage, MavModeFlag, MavState, MavType,
};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use self::io::{IoEvent, IoTask};
use self::pending::retry_late;
use self::state::Actor;
use self::transfer::Transfer;
use super::command::Command;
use super::error::LinkError;
use super::handle::LinkHandle;
use super::params::Params;
use super::router::{self, Router};
use super::telemetry::{GimbalControl, Telemetry, VehicleState};
use super::transport::LinkUrl;
use crate::clock;
use crate::mission::upload::{self};

const CMD_QUEUE: usize = 32;
const IO_QUEUE: usize = 256;

/// Starts the link actor. Fails at once on a bad URL or signing key; the
/// connection itself (for `udpin:`, binding the socket) is (re)tried in the
/// background. Once a `udpin:` socket is bound, [`LinkHandle::bound_addr`]
/// gives its address (the port the kernel chose for port 0).
pub fn spawn(
    params: Params,
    transfer: upload::Params,
    cancel: CancellationToken,
) -> Result<(LinkHandle, JoinHandle<()>), LinkError> {
    spawn_inner(params, transfer, cancel, None)
}

/// [`spawn`] on a UDP socket the caller has already bound: the link listens
/// on it as on a `udpin:` URL (replies go to the last sender), whatever
/// `params.url` says, and never rebinds. For callers (tests, a supervisor)
/// that hold a port before the peer needs to know it.
pub fn spawn_with_socket(
    params: Params,
    transfer: upload::Params,
    cancel: CancellationToken,
    socket: UdpSocket,
) -> Result<(LinkHandle, JoinHandle<()>), LinkError> {
    spawn_inner(params, transfer, cancel, Some(socket))
}

fn spawn_inner(
    mut params: Params,
    transfer: upload::Params,
    cancel: CancellationToken,
    socket: Option<UdpSocket>,
) -> Result<(LinkHandle, JoinHandle<()>), LinkError> {
    let bound_now = match &socket {
        Some(s) => Some(s.local_addr().map_err(|e| LinkError::BadUrl {
            url: params.url.clone(),
            reason: format!("the given UDP socket has no local address: {e}"),
        })?),
        None => None,
    };
    if let Some(a) = bound_now {
        params.url = format!("udpin:{a}");
    }
    let url: LinkUrl = params.url.parse()?;
    if let Some(s) = &params.signing {
        s.key()?;
    }
    let forward = router::parse_forward(&params.forward, &params.url)?;
    let router = Arc::new(Router::new(
        (params.system_id, params.component_id),
        &forward,
    ));
    let bound = watch::channel(bound_now);
    let (cmd_tx, cmd_rx) = mpsc::channel(CMD_QUEUE);
    let (io_tx, io_rx) = mpsc::channel(IO_QUEUE);
    let vehicle = watch::channel(VehicleState {
        link_lost: true,
        ..VehicleState::default()
    });
    let gp = watch::channel(None);
    let lp = watch::channel(None);
    let gps_raw = watch::channel(None);
    let att = watch::channel(None);
    let home = watch::channel(None);
    let gimbal = watch::channel(None);
    let progress = watch::channel(None);
    let video_streams = watch::channel(Vec::new());
    let cameras = watch::channel(Vec::new());
    let captures = watch::channel(Vec::new());
    let gimbal_manager = watch::channel(None);
    let gimbal_control = watch::channel(GimbalControl::default());
    let gimbal_tx = Arc::new(gimbal_control.0);
    let handle = LinkHandle {
        tx: cmd_tx,
        gimbal: gimbal_tx.clone(),
        own: (params.system_id, params.component_id),
        command_timeout: Duration::from_millis(params.command_timeout_ms.max(1)),
        bound: bound.1,
        router: router.clone(),
        telemetry: Telemetry {
            vehicle: vehicle.1,
            global_position: gp.1,
            local_position: lp.1,
            gps_raw: gps_raw.1,
            attitude: att.1,
            home: home.1,
            gimbal: gimbal.1,
            progress: progress.1,
            video_streams: video_streams.1,
            cameras: cameras.1,
            captures: captures.1,
            gimbal_manager: gimbal_manager.1,
            gimbal_control: gimbal_control.1,
            mission_changes: router.mission_changes(),
        },
    };
    let version = if params.mavlink1 {
        MavlinkVersion::V1
    } else {
        MavlinkVersion::V2
    };
    let io_cancel = cancel.child_token();
    let io = IoTask {
        url,
        udp_in: socket,
        bound: bound.0,
        version,
        signing: params.signing.clone(),
        backoff_min: Duration::from_millis(params.reconnect_min_ms.max(1)),
        backoff_max: Duration::from_millis(
            params.reconnect_max_ms.max(params.reconnect_min_ms).max(1),
        ),
        tx: io_tx,
        cancel: io_cancel.clone(),
        router: router.clone(),
    };
    let now = clock::now();
    let actor = Actor {
        transfer_params: transfer,
        conn: None,
        vehicle: vehicle.0,
        gp: gp.0,
        lp: lp.0,
        gps_raw: gps_raw.0,
        att: att.0,
        home: home.0,
        gimbal: gimbal.0,
        progress: progress.0,
        video_streams: video_streams.0,
        cameras: cameras.0,
        captures: captures.0,
        camera_asked: Vec::new(),
        gimbal_manager: gimbal_manager.0,
        gimbal_control: gimbal_tx,
        transfer: None,
        command: None,
        stop: None,
        next_heartbeat: now,
        rates_requested: None,
        rate_rounds: 0,
        connect_failure_logged: false,
        out: Vec::new(),
        params,
        router: router.clone(),
        deferred: Vec::new(),
        guided: None,
    };
    let endpoints = router::spawn_endpoints(&router, forward, &io_cancel);
    let task = tokio::spawn(async move {
        let io_task = tokio::spawn(io.run());
        actor.run(cmd_rx, io_rx, cancel).await;
        io_cancel.cancel();
        let _ = io_task.await;
        for e in endpoints {
            let _ = e.await;
        }
    });
    Ok((handle, task))
}

impl Actor {
    async fn run(
        mut self,
        mut cmd_rx: mpsc::Receiver<Command>,
        mut io_rx: mpsc::Receiver<IoEvent>,
        cancel: CancellationToken,
    ) {
        info!(url = %self.params.url, "link actor started");
        loop {
            let wake = self.next_wake();
            tokio::select! {
                // Timers first: a busy link must not starve heartbeats and
                // protocol timeouts.
                biased;
                _ = cancel.cancelled() => break,
                _ = tokio::time::sleep_until(tokio::time::Instant::from_std(wake)) => self.on_wake().await,
                cmd = cmd_rx.recv() => match cmd {
                    Some(c) => self.on_command(c).await,
                    None => break,
                },
                ev = io_rx.recv() => match ev {
                    Some(ev) => self.on_io(ev).await,
                    None => break,
                },
            }
            self.sync_gate().await;
        }
        for cmd in self.deferred.drain(..) {
            match cmd {
                Command::UploadMission { reply, .. } => {
                    let _ = reply.send(Err(LinkError::ActorGone));
                }
                Command::DownloadMission { reply } => {
                    let _ = reply.send(Err(LinkError::ActorGone));
                }
                _ => {}
            }
        }
        if let Some(mut t) = self.transfer.take() {
            t.cancel(clock::now(), &mut self.out);
            self.flush().await;
            t.deliver(clock::now(), false);
        }
        info!("link actor stopped");
    }

    fn next_wake(&self) -> Instant {
        let mut wake = self.next_heartbeat;
        let v = self.vehicle.borrow();
        if let (Some(last), false) = (v.last_heartbeat, v.link_lost) {
            wake = wake.min(last + Duration::from_millis(self.params.link_lost_after_ms));
        }
        if let Some(d) = self.transfer.as_ref().and_then(Transfer::deadline) {
            wake = wake.min(d);
        }
        for c in [&self.command, &self.stop].into_iter().flatten() {
            wake = wake.min(c.deadline);
        }
        if let Some(d) = self.router.foreign_deadline() {
            wake = wake.min(d);
        }
        if let Some(g) = &self.guided {
            wake = wake.min(g.next);
        }
        wake
    }

    /// Keeps the mission gate in step with our transfer: when ours has
    /// ended, the frames another station sent meanwhile go to the vehicle;
    /// when another station's has ended, the transfers that waited start.
    async fn sync_gate(&mut self) {
        let now = clock::now();
        self.router.expire(now);
        if self.transfer.is_none() && self.router.own_busy() {
            self.router.end_own(now).await;
        }
        if !self.deferred.is_empty() && self.transfer.is_none() && !self.router.foreign_busy(now) {
            let waiting = std::mem::take(&mut self.deferred);
            info!(
                transfers = waiting.len(),
                "the other station's mission transfer ended; ours starts"
            );
            for cmd in waiting {
                Box::pin(self.on_command(cmd)).await;
            }
        }
    }

    async fn on_io(&mut self, ev: IoEvent) {
        match ev {
            IoEvent::Connected(conn) => {
                self.conn = Some(conn);
                self.connect_failure_logged = false;
                self.vehicle.send_modify(|v| {
                    v.connected = true;
                    v.connections += 1;
                });
                info!(url = %self.params.url, "link connected");
                self.next_heartbeat = clock::now();
            }
            IoEvent::Lost(reason) => {
                self.conn = None;
                self.vehicle.send_modify(|v| v.connected = false);
                warn!(%reason, "link lost; reconnecting");
            }
            IoEvent::ConnectFailed(reason) => {
                // Say it once per outage; the retries go on with backoff.
                if !self.connect_failure_logged {
                    warn!(url = %self.params.url, %reason, "cannot open the link; retrying with backoff");
                    self.connect_failure_logged = true;
                } else {
                    debug!(%reason, "connect failed");
                }
            }
            IoEvent::Frame(h, m) => self.on_frame(h, *m).await,
        }
    }

    async fn on_wake(&mut self) {
        let now = clock::now();
        if now >= self.next_heartbeat {
            self.out.push(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_GCS,
                autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
                base_mode: MavModeFlag::empty(),
                system_status: MavState::MAV_STATE_ACTIVE,
                mavlink_version: 3,
            }));
            let period = Duration::from_millis(self.params.heartbeat_period_ms.max(10));
            self.next_heartbeat += period;
            if self.next_heartbeat <= now {
                self.next_heartbeat = now + period;
            }
        }
        let lost_after = Duration::from_millis(self.params.link_lost_after_ms);
        let lost = {
            let v = self.vehicle.borrow();
            !v.link_lost
                && v.last_heartbeat
                    .is_some_and(|t| now.saturating_duration_since(t) >= lost_after)
        };
        if lost {
            self.vehicle.send_modify(|v| v.link_lost = true);
            warn!(
                after_ms = self.params.link_lost_after_ms,
                "vehicle link lost: no heartbeat"
            );
        }
        if let Some(t) = &mut self.transfer
            && t.deadline().is_some_and(|d| d <= now)
        {
            t.on_timeout(now, &mut self.out);
            self.deliver_if_done();
        }
        retry_late(&mut self.stop, &self.params, now, &mut self.out);
        retry_late(&mut self.command, &self.params, now, &mut self.out);
        self.stream_guided(now);
        self.flush().await;
    }
}
