//! The link actor: one task owns the connection and everything that talks on it.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mavlink::dialects::common::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MavAutopilot, MavCmd, MavMessage, MavMissionType,
    MavModeFlag, MavResult, MavState, MavType,
};
use mavlink::error::MessageReadError;
use mavlink::{AsyncMavConnection, MavHeader, MavlinkVersion, Message};
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{Span, debug, info, info_span, warn};

use super::router::{self, Router};
use super::transport::{self, Connection, LinkUrl};
use super::{
    Attitude, Command, FlightMode, GimbalAttitude, GimbalControl, GimbalManagerStatus,
    GlobalPosition, GpsRaw, HoldAck, HomePosition, LinkError, LinkHandle, LocalPosition,
    MissionProgress, Params, Stamped, Telemetry, VehicleState, ardupilot_mode_name, mode_params,
    px4_mode_name, quat_to_euler_deg,
};
use crate::mission::upload::{self, Downloader, MissionError, Peers, Uploader, same_mission};
use crate::mission::{Download, Flavour, MissionItem, UploadReport};

/// The actor's clock: tokio's, so that tests drive the protocol timers in
/// paused time (it is the system's monotonic clock otherwise). The
/// protocol machines and the telemetry stamps take it as a std `Instant`.
fn clock_now() -> Instant {
    tokio::time::Instant::now().into_std()
}

const CMD_QUEUE: usize = 32;
const IO_QUEUE: usize = 256;
/// How often missing telemetry streams are asked for again.
const RATE_RECHECK: Duration = Duration::from_secs(5);
/// How many times, after the vehicle appears.
const RATE_ROUNDS: u32 = 5;

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
    let now = clock_now();
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

enum IoEvent {
    Connected(Arc<Connection>),
    Frame(MavHeader, Box<MavMessage>),
    Lost(String),
    ConnectFailed(String),
}

/// Connects, reads, and reconnects with exponential backoff.
struct IoTask {
    url: LinkUrl,
    /// The `udpin:` socket once bound (kept across reconnections).
    udp_in: Option<UdpSocket>,
    /// Its address, for [`LinkHandle::bound_addr`].
    bound: watch::Sender<Option<SocketAddr>>,
    version: MavlinkVersion,
    signing: Option<transport::Signing>,
    backoff_min: Duration,
    backoff_max: Duration,
    tx: mpsc::Sender<IoEvent>,
    cancel: CancellationToken,
    /// Forwards the vehicle's frames to the other ground stations.
    router: Arc<Router>,
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

    async fn run(mut self) {
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
                                let Some((h, m)) = self.router.on_vehicle_frame(&raw, clock_now())
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

/// Why a download runs.
enum DownPurpose {
    /// The operator asked for the mission.
    Reply(oneshot::Sender<Result<Download, LinkError>>),
    /// An upload's final ACK was lost: the read-back decides.
    Verify {
        items: Vec<MissionItem>,
        skip_home: bool,
        report: UploadReport,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
    },
}

enum Transfer {
    Up {
        machine: Uploader,
        items: Vec<MissionItem>,
        skip_home: bool,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
        span: Span,
    },
    Down {
        machine: Downloader,
        purpose: DownPurpose,
        span: Span,
    },
}

/// What finishing a transfer leads to.
enum Next {
    Nothing,
    /// Read the mission back to confirm an upload whose final ACK was lost.
    Verify {
        items: Vec<MissionItem>,
        skip_home: bool,
        report: UploadReport,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
        span: Span,
    },
}

fn log_upload(span: &Span, outcome: &Result<UploadReport, MissionError>) {
    span.in_scope(|| match outcome {
        Ok(r) => info!(
            items = r.items,
            retries = r.retries,
            repeats = r.repeats,
            seconds = r.seconds,
            verified_by_download = r.verified_by_download,
            "mission uploaded"
        ),
        Err(e) => warn!(error = %e, "mission upload failed"),
    });
}

impl Transfer {
    fn on_message(
        &mut self,
        h: &MavHeader,
        m: &MavMessage,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        match self {
            Self::Up { machine, span, .. } => span.in_scope(|| machine.on_message(h, m, now, out)),
            Self::Down { machine, span, .. } => {
                span.in_scope(|| machine.on_message(h, m, now, out))
            }
        }
    }

    fn on_timeout(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        match self {
            Self::Up { machine, .. } => machine.on_timeout(now, out),
            Self::Down { machine, .. } => machine.on_timeout(now, out),
        }
    }

    fn cancel(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        match self {
            Self::Up { machine, .. } => machine.cancel(now, out),
            Self::Down { machine, .. } => machine.cancel(now, out),
        }
    }

    fn deadline(&self) -> Option<Instant> {
        match self {
            Self::Up { machine, .. } => machine.deadline(),
            Self::Down { machine, .. } => machine.deadline(),
        }
    }

    fn is_done(&self) -> bool {
        match self {
            Self::Up { machine, .. } => machine.is_done(),
            Self::Down { machine, .. } => machine.is_done(),
        }
    }

    /// Sends the outcome of a finished transfer to whoever waits for it, or
    /// asks for a read-back when an upload's final ACK is missing and
    /// `may_verify`.
    fn deliver(self, now: Instant, may_verify: bool) -> Next {
        match self {
            Self::Up {
                mut machine,
                items,
                skip_home,
                reply,
                span,
            } => match machine.take_outcome() {
                Some(Err(MissionError::NoFinalAck { .. })) if may_verify => {
                    span.in_scope(|| warn!("final MISSION_ACK missing; reading the mission back"));
                    Next::Verify {
                        items,
                        skip_home,
                        report: machine.report_at(now),
                        reply,
                        span,
                    }
                }
                Some(outcome) => {
                    log_upload(&span, &outcome);
                    let _ = reply.send(outcome.map_err(LinkError::from));
                    Next::Nothing
                }
                None => Next::Nothing,
            },
            Self::Down {
                mut machine,
                purpose,
                span,
            } => {
                let Some(outcome) = machine.take_outcome() else {
                    return Next::Nothing;
                };
                match purpose {
                    DownPurpose::Reply(reply) => {
                        span.in_scope(|| match &outcome {
                            Ok(d) => info!(
                                items = d.items.len(),
                                retries = d.retries,
                                seconds = d.seconds,
                                "mission downloaded"
                            ),
                            Err(e) => warn!(error = %e, "mission download failed"),
                        });
                        let _ = reply.send(outcome.map_err(LinkError::from));
                    }
                    DownPurpose::Verify {
                        items,
                        skip_home,
                        report,
                        reply,
                    } => {
                        let result = match outcome {
                            Ok(d) if same_mission(&items, &d.items, skip_home) => {
                                Ok(UploadReport {
                                    seconds: report.seconds + d.seconds,
                                    retries: report.retries + d.retries,
                                    verified_by_download: true,
                                    ..report
                                })
                            }
                            Ok(d) => Err(MissionError::ReadBackDiffers {
                                uploaded: report.items,
                                downloaded: d.items.len(),
                            }),
                            Err(MissionError::Cancelled) => Err(MissionError::Cancelled),
                            Err(_) => Err(MissionError::NoFinalAck {
                                count: report.items,
                                retries: report.retries,
                            }),
                        };
                        log_upload(&span, &result);
                        let _ = reply.send(result.map_err(LinkError::from));
                    }
                }
                Next::Nothing
            }
        }
    }
}

struct PendingCommand {
    data: COMMAND_LONG_DATA,
    attempts: u32,
    deadline: Instant,
    reply: Reply,
}

/// Who waits for a command's COMMAND_ACK.
enum Reply {
    /// `Ok(())` on ACCEPTED.
    Done(oneshot::Sender<Result<(), LinkError>>),
    /// The operator's stop: the ACK itself, with the mode asked for.
    Hold {
        mode: String,
        reply: oneshot::Sender<Result<HoldAck, LinkError>>,
    },
}

impl Reply {
    fn accepted(self, result: MavResult) {
        match self {
            Self::Done(r) => {
                let _ = r.send(Ok(()));
            }
            Self::Hold { mode, reply } => {
                let _ = reply.send(Ok(HoldAck {
                    command: "MAV_CMD_DO_SET_MODE",
                    mode,
                    result: format!("{result:?}"),
                }));
            }
        }
    }

    fn fail(self, e: LinkError) {
        match self {
            Self::Done(r) => {
                let _ = r.send(Err(e));
            }
            Self::Hold { reply, .. } => {
                let _ = reply.send(Err(e));
            }
        }
    }
}

/// Resends a command whose ACK is late, or gives up after the link's
/// attempts (the waiter gets [`LinkError::CommandTimeout`]).
fn retry_late(
    slot: &mut Option<PendingCommand>,
    params: &Params,
    now: Instant,
    out: &mut Vec<MavMessage>,
) {
    if slot.as_ref().is_some_and(|c| c.deadline <= now)
        && let Some(mut c) = slot.take()
    {
        if c.attempts >= params.command_attempts.max(1) {
            c.reply.fail(LinkError::CommandTimeout {
                command: cmd_number(c.data.command),
                attempts: c.attempts,
            });
        } else {
            c.attempts += 1;
            c.data.confirmation = c.data.confirmation.saturating_add(1);
            c.deadline = now + Duration::from_millis(params.command_timeout_ms);
            out.push(MavMessage::COMMAND_LONG(c.data.clone()));
            *slot = Some(c);
        }
    }
}

struct Actor {
    params: Params,
    transfer_params: upload::Params,
    conn: Option<Arc<Connection>>,
    vehicle: watch::Sender<VehicleState>,
    gp: watch::Sender<Option<Stamped<GlobalPosition>>>,
    lp: watch::Sender<Option<Stamped<LocalPosition>>>,
    gps_raw: watch::Sender<Option<Stamped<GpsRaw>>>,
    att: watch::Sender<Option<Stamped<Attitude>>>,
    home: watch::Sender<Option<Stamped<HomePosition>>>,
    gimbal: watch::Sender<Option<Stamped<GimbalAttitude>>>,
    progress: watch::Sender<Option<Stamped<MissionProgress>>>,
    video_streams: watch::Sender<Vec<super::VideoStreamInfo>>,
    cameras: watch::Sender<Vec<super::CameraInfo>>,
    captures: watch::Sender<Vec<super::ImageCaptured>>,
    /// Camera components asked for CAMERA_INFORMATION, and when.
    camera_asked: Vec<(u8, Instant)>,
    gimbal_manager: watch::Sender<Option<Stamped<GimbalManagerStatus>>>,
    gimbal_control: Arc<watch::Sender<GimbalControl>>,
    transfer: Option<Transfer>,
    command: Option<PendingCommand>,
    /// The operator's stop, beside any other command in flight.
    stop: Option<PendingCommand>,
    next_heartbeat: Instant,
    rates_requested: Option<Instant>,
    rate_rounds: u32,
    connect_failure_logged: bool,
    out: Vec<MavMessage>,
    /// The forward endpoints' router and its mission gate.
    router: Arc<Router>,
    /// Mission transfers waiting for another station's to end.
    deferred: Vec<Command>,
}

/// Message ids for SET_MESSAGE_INTERVAL.
mod msg_id {
    pub const ATTITUDE: u32 = 30;
    pub const LOCAL_POSITION_NED: u32 = 32;
    pub const GLOBAL_POSITION_INT: u32 = 33;
    pub const MISSION_CURRENT: u32 = 42;
    pub const HOME_POSITION: u32 = 242;
    pub const GIMBAL_DEVICE_ATTITUDE_STATUS: u32 = 285;
}

fn cmd_number(c: MavCmd) -> u16 {
    c as u32 as u16
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
            t.cancel(clock_now(), &mut self.out);
            self.flush().await;
            t.deliver(clock_now(), false);
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
        wake
    }

    /// Keeps the mission gate in step with our transfer: when ours has
    /// ended, the frames another station sent meanwhile go to the vehicle;
    /// when another station's has ended, the transfers that waited start.
    async fn sync_gate(&mut self) {
        let now = clock_now();
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

    /// Starts our transfer in the gate; false (and the command kept for
    /// later) while another station's runs.
    fn gate_or_defer(&mut self, now: Instant, cmd: Command) -> Option<Command> {
        if self.router.begin_own(now) {
            return Some(cmd);
        }
        info!("another station's mission transfer is running; ours waits for it to end");
        self.deferred.push(cmd);
        None
    }

    fn header(&self) -> MavHeader {
        MavHeader {
            system_id: u32::from(self.params.system_id),
            component_id: self.params.component_id,
            sequence: 0,
        }
    }

    /// Sends everything queued in `out`. Without a connection the messages
    /// are dropped: the protocol machines resend on their own timeouts.
    async fn flush(&mut self) {
        if self.out.is_empty() {
            return;
        }
        let header = self.header();
        if let Some(conn) = &self.conn {
            for m in self.out.drain(..) {
                // MAVLink 1 has 8-bit message ids (and the crate panics on
                // larger ones): such messages cannot go out on a v1 link.
                if self.params.mavlink1 && m.message_id() > 255 {
                    warn!(
                        id = m.message_id(),
                        "message id does not fit MAVLink 1; not sent"
                    );
                    continue;
                }
                if let Err(e) = conn.send(&header, &m).await {
                    debug!(error = %e, "send failed");
                }
            }
        } else {
            self.out.clear();
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
                self.next_heartbeat = clock_now();
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

    async fn on_frame(&mut self, h: MavHeader, m: MavMessage) {
        let now = clock_now();
        if let MavMessage::HEARTBEAT(hb) = &m {
            self.on_heartbeat(&h, hb, now).await;
            return;
        }
        let tracked = self.vehicle.borrow().system_id;
        if tracked.map(u32::from) != Some(h.system_id) {
            return;
        }
        match &m {
            MavMessage::GLOBAL_POSITION_INT(d) => {
                let value = GlobalPosition {
                    time_boot_ms: d.time_boot_ms,
                    lat_deg: f64::from(d.lat) / 1e7,
                    lon_deg: f64::from(d.lon) / 1e7,
                    alt_amsl_m: f64::from(d.alt) / 1e3,
                    rel_alt_m: f64::from(d.relative_alt) / 1e3,
                    vel_ned_m_s: [
                        f32::from(d.vx) / 100.0,
                        f32::from(d.vy) / 100.0,
                        f32::from(d.vz) / 100.0,
                    ],
                    heading_deg: (d.hdg != u16::MAX).then(|| f32::from(d.hdg) / 100.0),
                };
                self.gp.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::GPS_RAW_INT(d) => {
                let value = GpsRaw::from_message(d);
                self.gps_raw.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::LOCAL_POSITION_NED(d) => {
                let value = LocalPosition {
                    time_boot_ms: d.time_boot_ms,
                    pos_ned_m: [d.x, d.y, d.z],
                    vel_ned_m_s: [d.vx, d.vy, d.vz],
                };
                self.lp.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::ATTITUDE(d) => {
                let value = Attitude {
                    time_boot_ms: d.time_boot_ms,
                    roll_rad: d.roll,
                    pitch_rad: d.pitch,
                    yaw_rad: d.yaw,
                };
                self.att.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::HOME_POSITION(d) => {
                let value = HomePosition {
                    lat_deg: f64::from(d.latitude) / 1e7,
                    lon_deg: f64::from(d.longitude) / 1e7,
                    alt_amsl_m: f64::from(d.altitude) / 1e3,
                };
                self.home.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(d) => {
                use mavlink::dialects::common::GimbalDeviceFlags as F;
                let (roll_deg, pitch_deg, yaw_deg) = quat_to_euler_deg(d.q);
                let yaw_absolute = d.flags.contains(F::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME)
                    || (!d
                        .flags
                        .contains(F::GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME)
                        && d.flags.contains(F::GIMBAL_DEVICE_FLAGS_YAW_LOCK));
                let value = GimbalAttitude {
                    roll_deg,
                    pitch_deg,
                    yaw_deg,
                    yaw_absolute,
                    time_boot_ms: Some(d.time_boot_ms),
                };
                self.gimbal.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            // ArduPilot's legacy mounts still send it.
            #[allow(deprecated)]
            MavMessage::MOUNT_ORIENTATION(d) => {
                let value = GimbalAttitude {
                    roll_deg: d.roll,
                    pitch_deg: d.pitch,
                    yaw_deg: d.yaw,
                    yaw_absolute: false,
                    time_boot_ms: Some(d.time_boot_ms),
                };
                self.gimbal.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::MISSION_CURRENT(d) => {
                let mut p = self.progress.borrow().map(|s| s.value).unwrap_or_default();
                p.current_seq = Some(d.seq);
                p.total = (d.total != u16::MAX && d.total != 0).then_some(d.total);
                p.state = Some(d.mission_state as u8);
                self.progress.send_replace(Some(Stamped {
                    value: p,
                    received: now,
                }));
                self.gimbal_after_mission(d.mission_state as u8);
            }
            MavMessage::GIMBAL_MANAGER_STATUS(d) => {
                let value = GimbalManagerStatus {
                    manager_component: h.component_id,
                    gimbal_device_id: d.gimbal_device_id,
                    primary: (d.primary_control_sysid, d.primary_control_compid),
                    secondary: (d.secondary_control_sysid, d.secondary_control_compid),
                    flags: d.flags.bits(),
                };
                let before = self.gimbal_manager.borrow().map(|s| s.value.primary);
                if before.is_some_and(|b| b != value.primary) {
                    info!(
                        from = ?before,
                        to = ?value.primary,
                        "gimbal primary control changed"
                    );
                }
                // The status first, then the control it changes: a reader
                // that sees control passed finds who has it.
                self.gimbal_manager.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
                let own = (self.params.system_id, self.params.component_id);
                if self.gimbal_control.borrow().held && value.primary != own {
                    // Someone (a PX4 mission's own configure item, another
                    // ground station) took control: we no longer hold it and
                    // have nothing to give back.
                    let (s, c) = value.primary;
                    info!("gimbal control passed from us to {s}/{c}");
                    self.gimbal_control.send_modify(|g| {
                        g.held = false;
                        g.for_mission = false;
                        g.last_event = Some(format!("gimbal control passed to {s}/{c}"));
                    });
                }
            }
            MavMessage::MISSION_ITEM_REACHED(d) => {
                let mut p = self.progress.borrow().map(|s| s.value).unwrap_or_default();
                p.last_reached = Some(d.seq);
                self.progress.send_replace(Some(Stamped {
                    value: p,
                    received: now,
                }));
            }
            MavMessage::COMMAND_ACK(a) => {
                self.on_command_ack(a.command, a.result, a.target_system, now)
            }
            MavMessage::CAMERA_INFORMATION(d) => {
                let info = camera_info(h.component_id, d);
                info!(
                    component = info.component_id,
                    vendor = %info.vendor,
                    model = %info.model,
                    captures_images = info.captures_images,
                    "camera described"
                );
                self.cameras.send_modify(|v| {
                    v.retain(|c| c.component_id != info.component_id);
                    v.push(info);
                    v.sort_by_key(|c| c.component_id);
                });
            }
            MavMessage::CAMERA_IMAGE_CAPTURED(d) => {
                let c = image_captured(h.component_id, d);
                debug!(
                    component = c.component_id,
                    index = c.index,
                    "CAMERA_IMAGE_CAPTURED"
                );
                self.captures.send_modify(|v| {
                    if !v
                        .iter()
                        .any(|x| (x.component_id, x.index) == (c.component_id, c.index))
                    {
                        v.push(c);
                        if v.len() > super::CAPTURES_KEPT {
                            v.remove(0);
                        }
                    }
                });
            }
            MavMessage::VIDEO_STREAM_INFORMATION(d) => {
                let info = video_stream_info(h.component_id, d);
                self.video_streams.send_modify(|v| {
                    v.retain(|x| {
                        (x.component_id, x.stream_id) != (info.component_id, info.stream_id)
                    });
                    v.push(info);
                });
            }
            _ => {}
        }
        if let Some(t) = &mut self.transfer {
            t.on_message(&h, &m, now, &mut self.out);
            self.flush().await;
            self.deliver_if_done();
        }
        self.flush().await;
    }

    /// A camera component of the vehicle's system is heard: ask it for its
    /// CAMERA_INFORMATION until it answers (every 5 s).
    async fn on_camera_heartbeat(&mut self, h: &MavHeader, now: Instant) {
        let Some(sys) = self.vehicle.borrow().system_id else {
            return;
        };
        if h.system_id != u32::from(sys) {
            return;
        }
        let comp = h.component_id;
        if self.cameras.borrow().iter().any(|c| c.component_id == comp) {
            return;
        }
        if self
            .camera_asked
            .iter()
            .any(|(c, t)| *c == comp && now.saturating_duration_since(*t) < CAMERA_ASK_EVERY)
        {
            return;
        }
        self.camera_asked.retain(|(c, _)| *c != comp);
        self.camera_asked.push((comp, now));
        info!(
            component = comp,
            "camera heard: asking for CAMERA_INFORMATION"
        );
        self.out.push(MavMessage::COMMAND_LONG(command_long(
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [CAMERA_INFORMATION_ID as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            sys,
            comp,
        )));
        self.flush().await;
    }

    async fn on_heartbeat(&mut self, h: &MavHeader, hb: &HEARTBEAT_DATA, now: Instant) {
        if hb.mavtype == MavType::MAV_TYPE_CAMERA {
            self.on_camera_heartbeat(h, now).await;
            return;
        }
        let is_vehicle = hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
            && !matches!(
                hb.mavtype,
                MavType::MAV_TYPE_GCS
                    | MavType::MAV_TYPE_GIMBAL
                    | MavType::MAV_TYPE_CAMERA
                    | MavType::MAV_TYPE_ONBOARD_CONTROLLER
            );
        let Ok(sys) = u8::try_from(h.system_id) else {
            return;
        };
        if !is_vehicle || sys == self.params.system_id {
            return;
        }
        let wanted = self.params.vehicle_system_id;
        let tracked = self.vehicle.borrow().system_id;
        if (wanted != 0 && sys != wanted) || tracked.is_some_and(|t| t != sys) {
            return;
        }
        let flavour = match hb.autopilot {
            MavAutopilot::MAV_AUTOPILOT_PX4 => Some(Flavour::Px4),
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Some(Flavour::ArduPilot),
            _ => None,
        };
        let mode = match flavour {
            Some(Flavour::Px4) => px4_mode_name(hb.custom_mode),
            Some(Flavour::ArduPilot) => ardupilot_mode_name(hb.custom_mode),
            None => format!("{}", hb.custom_mode),
        };
        let mut appeared = false;
        self.vehicle.send_modify(|v| {
            appeared = v.system_id.is_none() || v.link_lost;
            v.system_id = Some(sys);
            v.component_id = h.component_id;
            v.flavour = flavour;
            v.autopilot = hb.autopilot as u8;
            v.mav_type = hb.mavtype as u8;
            v.base_mode = hb.base_mode.bits();
            v.custom_mode = hb.custom_mode;
            v.mode = mode;
            v.armed = hb
                .base_mode
                .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
            v.link_lost = false;
            v.last_heartbeat = Some(now);
        });
        if appeared {
            info!(
                system = sys,
                component = h.component_id,
                ?flavour,
                "vehicle heard"
            );
            self.rate_rounds = 0;
            self.request_rates(sys, h.component_id, now, false);
            self.flush().await;
        } else if self.rate_rounds < RATE_ROUNDS
            && self
                .rates_requested
                .is_some_and(|t| now.saturating_duration_since(t) >= RATE_RECHECK)
        {
            // A request lost on a bad radio leaves a stream at the vehicle's
            // default rate: ask again for the streams that are not arriving.
            self.rate_rounds += 1;
            self.request_rates(sys, h.component_id, now, true);
            self.flush().await;
        }
    }

    /// When each requested stream last arrived.
    fn last_received(&self, id: u32) -> Option<Instant> {
        match id {
            msg_id::GLOBAL_POSITION_INT => self.gp.borrow().map(|s| s.received),
            msg_id::LOCAL_POSITION_NED => self.lp.borrow().map(|s| s.received),
            msg_id::ATTITUDE => self.att.borrow().map(|s| s.received),
            msg_id::HOME_POSITION => self.home.borrow().map(|s| s.received),
            msg_id::GIMBAL_DEVICE_ATTITUDE_STATUS => self.gimbal.borrow().map(|s| s.received),
            msg_id::MISSION_CURRENT => self.progress.borrow().map(|s| s.received),
            _ => None,
        }
    }

    /// Sends SET_MESSAGE_INTERVAL for every configured stream, or with
    /// `only_stale` for those not received within three periods (at least 3 s).
    fn request_rates(&mut self, sys: u8, comp: u8, now: Instant, only_stale: bool) {
        self.rates_requested = Some(now);
        let r = self.params.rates;
        for (id, hz) in [
            (msg_id::GLOBAL_POSITION_INT, r.global_position_hz),
            (msg_id::LOCAL_POSITION_NED, r.local_position_hz),
            (msg_id::ATTITUDE, r.attitude_hz),
            (msg_id::HOME_POSITION, r.home_position_hz),
            (msg_id::GIMBAL_DEVICE_ATTITUDE_STATUS, r.gimbal_hz),
            (msg_id::MISSION_CURRENT, r.mission_current_hz),
        ] {
            if !(hz > 0.0 && hz.is_finite()) {
                continue;
            }
            if only_stale {
                let window = Duration::from_secs_f32((3.0 / hz).max(3.0));
                if self
                    .last_received(id)
                    .is_some_and(|t| now.saturating_duration_since(t) < window)
                {
                    continue;
                }
            }
            // param7 0: the response target is the requester
            self.out.push(MavMessage::COMMAND_LONG(command_long(
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                [id as f32, (1e6 / hz).round(), 0.0, 0.0, 0.0, 0.0, 0.0],
                sys,
                comp,
            )));
        }
    }

    fn deliver_if_done(&mut self) {
        if !self.transfer.as_ref().is_some_and(Transfer::is_done) {
            return;
        }
        let Some(t) = self.transfer.take() else {
            return;
        };
        let now = clock_now();
        let peers = self.peers().map(|(p, _)| p);
        if let Next::Verify {
            items,
            skip_home,
            report,
            reply,
            span,
        } = t.deliver(now, peers.is_some())
            && let Some(peers) = peers
        {
            let machine = Downloader::new(
                peers,
                MavMissionType::MAV_MISSION_TYPE_MISSION,
                self.transfer_params,
                now,
                &mut self.out,
            );
            self.transfer = Some(Transfer::Down {
                machine,
                purpose: DownPurpose::Verify {
                    items,
                    skip_home,
                    report,
                    reply,
                },
                span,
            });
        }
    }

    fn on_command_ack(
        &mut self,
        command: MavCmd,
        result: MavResult,
        target_system: u8,
        now: Instant,
    ) {
        if target_system != 0 && target_system != self.params.system_id {
            return;
        }
        let timeout = Duration::from_millis(self.params.command_timeout_ms);
        // The stop and the other command never share a command id (a
        // DO_SET_MODE in flight gives way to a stop), so the ACK is theirs.
        for slot in [&mut self.stop, &mut self.command] {
            let Some(pending) = slot else {
                continue;
            };
            if pending.data.command != command {
                continue;
            }
            if result == MavResult::MAV_RESULT_IN_PROGRESS {
                pending.deadline = now + timeout;
                return;
            }
            if let Some(p) = slot.take() {
                let ok = result == MavResult::MAV_RESULT_ACCEPTED;
                info!(command = cmd_number(command), ok, "command acknowledged");
                if ok {
                    p.reply.accepted(result);
                } else {
                    p.reply.fail(LinkError::CommandRejected {
                        command: cmd_number(command),
                        result: format!("{result:?}"),
                    });
                }
            }
            return;
        }
    }

    async fn on_wake(&mut self) {
        let now = clock_now();
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
        self.flush().await;
    }

    /// The vehicle's peers for a transfer, if one is heard.
    fn peers(&self) -> Option<(Peers, VehicleState)> {
        let v = self.vehicle.borrow().clone();
        let sys = v.system_id?;
        if v.link_lost {
            return None;
        }
        Some((
            Peers {
                own_system: self.params.system_id,
                own_component: self.params.component_id,
                target_system: sys,
                target_component: v.component_id,
            },
            v,
        ))
    }

    async fn on_command(&mut self, cmd: Command) {
        let now = clock_now();
        match cmd {
            Command::UploadMission { items, reply } => {
                if self.transfer.is_some() {
                    let _ = reply.send(Err(LinkError::Busy {
                        what: "mission transfer",
                    }));
                    return;
                }
                let Some(Command::UploadMission { items, reply }) =
                    self.gate_or_defer(now, Command::UploadMission { items, reply })
                else {
                    return;
                };
                let Some((peers, vehicle)) = self.peers() else {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                    return;
                };
                let flavour = vehicle.flavour;
                let span = info_span!(
                    "mission_upload",
                    items = items.len(),
                    vehicle = peers.target_system
                );
                let made = Uploader::new(
                    &items,
                    peers,
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    self.transfer_params,
                    now,
                    &mut self.out,
                );
                match made {
                    Ok(machine) => {
                        span.in_scope(|| info!("MISSION_COUNT sent"));
                        self.transfer = Some(Transfer::Up {
                            machine,
                            items,
                            skip_home: flavour == Some(Flavour::ArduPilot),
                            reply,
                            span,
                        });
                    }
                    Err(e) => {
                        let _ = reply.send(Err(e.into()));
                    }
                }
            }
            Command::DownloadMission { reply } => {
                if self.transfer.is_some() {
                    let _ = reply.send(Err(LinkError::Busy {
                        what: "mission transfer",
                    }));
                    return;
                }
                let Some(Command::DownloadMission { reply }) =
                    self.gate_or_defer(now, Command::DownloadMission { reply })
                else {
                    return;
                };
                let Some((peers, _)) = self.peers() else {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                    return;
                };
                let span = info_span!("mission_download", vehicle = peers.target_system);
                let machine = Downloader::new(
                    peers,
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    self.transfer_params,
                    now,
                    &mut self.out,
                );
                self.transfer = Some(Transfer::Down {
                    machine,
                    purpose: DownPurpose::Reply(reply),
                    span,
                });
            }
            Command::CancelTransfer { reply } => {
                let running = match self.transfer.take() {
                    Some(mut t) => {
                        t.cancel(now, &mut self.out);
                        t.deliver(now, false);
                        true
                    }
                    None => false,
                };
                let _ = reply.send(Ok(running));
            }
            Command::Arm { arm, reply } => {
                info!(arm, "operator: arm/disarm");
                self.start_command(
                    MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                    [if arm { 1.0 } else { 0.0 }, 0.0, 0.0],
                    Reply::Done(reply),
                    now,
                );
            }
            Command::SetMode { mode, reply } => {
                info!(?mode, "operator: set mode");
                let flavour = self.vehicle.borrow().flavour;
                match flavour {
                    Some(f) => {
                        let (base, main, sub) = mode_params(f, mode);
                        self.start_command(
                            MavCmd::MAV_CMD_DO_SET_MODE,
                            [base, main, sub],
                            Reply::Done(reply),
                            now,
                        );
                    }
                    None => {
                        let autopilot = self.vehicle.borrow().autopilot;
                        let _ = reply.send(Err(if self.vehicle.borrow().system_id.is_none() {
                            LinkError::NoVehicle
                        } else {
                            LinkError::UnsupportedMode { mode, autopilot }
                        }));
                    }
                }
            }
            Command::Hold { reply } => self.start_stop(reply, now),
            Command::StartMission { reply } => {
                info!("operator: start mission");
                self.start_command(
                    MavCmd::MAV_CMD_MISSION_START,
                    [0.0, 0.0, 0.0],
                    Reply::Done(reply),
                    now,
                );
            }
            Command::Long {
                command,
                params,
                target_component,
                reply,
            } => {
                info!(command = cmd_number(command), ?params, "command");
                self.start_command7(command, params, target_component, Reply::Done(reply), now);
            }
            Command::RequestMessage {
                message_id,
                target_component,
                reply,
            } => match self.peers() {
                Some((peers, _)) => {
                    self.out.push(MavMessage::COMMAND_LONG(command_long(
                        MavCmd::MAV_CMD_REQUEST_MESSAGE,
                        [message_id as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                        peers.target_system,
                        target_component,
                    )));
                    let _ = reply.send(Ok(()));
                }
                None => {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                }
            },
        }
        self.flush().await;
    }

    /// Gimbal control taken for a mission goes back once the vehicle
    /// reports that mission complete (MISSION_CURRENT.mission_state 5 after
    /// 3, active). Sent once, without waiting for the ACK.
    fn gimbal_after_mission(&mut self, state: u8) {
        const ACTIVE: u8 = 3;
        const COMPLETE: u8 = 5;
        let g = self.gimbal_control.borrow().clone();
        if !(g.held && g.for_mission) {
            return;
        }
        if state == ACTIVE && !g.mission_seen_active {
            self.gimbal_control
                .send_modify(|g| g.mission_seen_active = true);
        } else if state == COMPLETE && g.mission_seen_active {
            let Some((peers, _)) = self.peers() else {
                return;
            };
            let target = self
                .gimbal_manager
                .borrow()
                .map_or(peers.target_component, |s| s.value.manager_component);
            let p = super::release_params(g.device_id);
            self.out.push(MavMessage::COMMAND_LONG(command_long(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                p,
                peers.target_system,
                target,
            )));
            info!("mission complete: gimbal control released");
            self.gimbal_control.send_modify(|g| {
                g.held = false;
                g.for_mission = false;
                g.mission_seen_active = false;
                g.last_event = Some("mission complete: released gimbal control".into());
            });
        }
    }

    fn start_command(&mut self, command: MavCmd, p: [f32; 3], reply: Reply, now: Instant) {
        self.start_command7(
            command,
            [p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0],
            None,
            reply,
            now,
        );
    }

    fn start_command7(
        &mut self,
        command: MavCmd,
        p: [f32; 7],
        target_component: Option<u8>,
        reply: Reply,
        now: Instant,
    ) {
        if self.command.is_some() {
            reply.fail(LinkError::Busy { what: "command" });
            return;
        }
        // Its ACK could not be told from the stop's.
        if self
            .stop
            .as_ref()
            .is_some_and(|s| s.data.command == command)
        {
            reply.fail(LinkError::Busy { what: "stop" });
            return;
        }
        let Some((peers, _)) = self.peers() else {
            reply.fail(LinkError::NoVehicle);
            return;
        };
        let data = command_long(
            command,
            p,
            peers.target_system,
            target_component.unwrap_or(peers.target_component),
        );
        self.out.push(MavMessage::COMMAND_LONG(data.clone()));
        self.command = Some(PendingCommand {
            data,
            attempts: 1,
            deadline: now + Duration::from_millis(self.params.command_timeout_ms),
            reply,
        });
    }

    /// The operator's stop: DO_SET_MODE to the hold mode, sent now whatever
    /// else waits for an ACK. A DO_SET_MODE in flight gives way (its waiter
    /// gets [`LinkError::Superseded`]): the two ACKs could not be told apart.
    fn start_stop(&mut self, reply: oneshot::Sender<Result<HoldAck, LinkError>>, now: Instant) {
        info!("operator: stop (hold)");
        if self.stop.is_some() {
            let _ = reply.send(Err(LinkError::Busy { what: "stop" }));
            return;
        }
        let flavour = self.vehicle.borrow().flavour;
        let (Some(flavour), Some((peers, _))) = (flavour, self.peers()) else {
            let _ = reply.send(Err(LinkError::NoVehicle));
            return;
        };
        if self
            .command
            .as_ref()
            .is_some_and(|c| c.data.command == MavCmd::MAV_CMD_DO_SET_MODE)
            && let Some(c) = self.command.take()
        {
            warn!("a mode change in flight gives way to the stop");
            c.reply.fail(LinkError::Superseded {
                command: cmd_number(MavCmd::MAV_CMD_DO_SET_MODE),
            });
        }
        let (base, main, sub) = mode_params(flavour, FlightMode::Hold);
        let mode = match flavour {
            Flavour::Px4 => px4_mode_name(((sub as u32) << 24) | ((main as u32) << 16)),
            Flavour::ArduPilot => ardupilot_mode_name(main as u32),
        };
        let data = command_long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [base, main, sub, 0.0, 0.0, 0.0, 0.0],
            peers.target_system,
            peers.target_component,
        );
        self.out.push(MavMessage::COMMAND_LONG(data.clone()));
        self.stop = Some(PendingCommand {
            data,
            attempts: 1,
            deadline: now + Duration::from_millis(self.params.command_timeout_ms),
            reply: Reply::Hold { mode, reply },
        });
    }
}

/// A COMMAND_LONG with its seven params in order (first transmission).
fn command_long(
    command: MavCmd,
    p: [f32; 7],
    target_system: u8,
    target_component: u8,
) -> COMMAND_LONG_DATA {
    COMMAND_LONG_DATA {
        param1: p[0],
        param2: p[1],
        param3: p[2],
        param4: p[3],
        param5: p[4],
        param6: p[5],
        param7: p[6],
        command,
        target_system,
        target_component,
        confirmation: 0,
    }
}

/// MAVLink message id of CAMERA_INFORMATION.
const CAMERA_INFORMATION_ID: u32 = 259;
/// How often a silent camera is asked again for CAMERA_INFORMATION.
const CAMERA_ASK_EVERY: Duration = Duration::from_secs(5);

fn c_string(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|b| *b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

fn camera_info(
    component_id: u8,
    d: &mavlink::dialects::common::CAMERA_INFORMATION_DATA,
) -> super::CameraInfo {
    use mavlink::dialects::common::CameraCapFlags;
    super::CameraInfo {
        component_id,
        vendor: c_string(&d.vendor_name),
        model: c_string(&d.model_name),
        focal_length_mm: d.focal_length,
        sensor_size_mm: [d.sensor_size_h, d.sensor_size_v],
        resolution: [d.resolution_h, d.resolution_v],
        captures_images: d
            .flags
            .contains(CameraCapFlags::CAMERA_CAP_FLAGS_CAPTURE_IMAGE),
    }
}

fn image_captured(
    component_id: u8,
    d: &mavlink::dialects::common::CAMERA_IMAGE_CAPTURED_DATA,
) -> super::ImageCaptured {
    super::ImageCaptured {
        component_id,
        index: d.image_index,
        time_utc_us: d.time_utc,
        lat_deg: f64::from(d.lat) / 1e7,
        lon_deg: f64::from(d.lon) / 1e7,
        alt_amsl_m: f64::from(d.alt) / 1e3,
        relative_alt_m: f64::from(d.relative_alt) / 1e3,
        q: d.q,
        ok: d.capture_result == mavlink::dialects::common::MavBool::MAV_BOOL_TRUE,
        file_url: d.file_url.to_str().unwrap_or("").to_string(),
    }
}

fn video_stream_info(
    component_id: u8,
    d: &mavlink::dialects::common::VIDEO_STREAM_INFORMATION_DATA,
) -> super::VideoStreamInfo {
    use mavlink::dialects::common::{VideoStreamEncoding as E, VideoStreamType as T};
    let text = |b: &[u8]| {
        let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
        String::from_utf8_lossy(&b[..end]).trim().to_owned()
    };
    super::VideoStreamInfo {
        component_id,
        stream_id: d.stream_id,
        count: d.count,
        kind: match d.mavtype {
            T::VIDEO_STREAM_TYPE_RTSP => "rtsp",
            T::VIDEO_STREAM_TYPE_RTPUDP => "rtpudp",
            T::VIDEO_STREAM_TYPE_TCP_MPEG => "tcp_mpeg",
            T::VIDEO_STREAM_TYPE_MPEG_TS => "mpeg_ts",
            T::VIDEO_STREAM_TYPE_WHEP => "whep",
        }
        .into(),
        encoding: match d.encoding {
            E::VIDEO_STREAM_ENCODING_H264 => "h264",
            E::VIDEO_STREAM_ENCODING_H265 => "h265",
            E::VIDEO_STREAM_ENCODING_UNKNOWN => "unknown",
        }
        .into(),
        name: text(&d.name[..]),
        uri: text(&d.uri[..]),
        framerate: d.framerate,
        width: d.resolution_h,
        height: d.resolution_v,
        bitrate: d.bitrate,
    }
}
