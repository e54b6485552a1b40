//! Sharing the vehicle's link with other ground stations: `[link] forward`.
//!
//! shotpilot holds the radio; QGroundControl, Mission Planner or MAVProxy
//! connect to shotpilot's forward endpoints (`udpout:127.0.0.1:14550`,
//! where QGC listens by default; `udpin:`, `tcpin:` for several clients,
//! `tcpout:`), as they would to mavlink-router or `mavproxy --out`.
//!
//! **Routing** follows MAVLink's rules
//! (<https://mavlink.io/en/guide/routing.html>): every link remembers the
//! (system, component) pairs heard on it; a message without a target, or
//! with target system 0, goes to every link but the one it came from; a
//! targeted message goes to the links where its target was heard (where
//! only the system was heard, there), and nowhere when the target is
//! shotpilot itself. Frames are forwarded as they arrived, byte for byte:
//! their sequence numbers and MAVLink 2 signatures pass untouched (an
//! endpoint's frames are not checked against `[link.signing]`; the vehicle
//! checks them). Only messages of the common dialect are understood and
//! forwarded (the CRC of a frame cannot be checked without its dialect).
//! shotpilot's own traffic goes out under its own component id
//! (`[link] component_id`, 191 by default; QGC and Mission Planner use 190).
//!
//! **One mission transfer at a time** ([`MissionGate`]). The mission
//! protocol of the autopilots serves one partner at a time, so two ground
//! stations must not interleave on the wire. A transfer another station
//! starts (MISSION_COUNT, MISSION_REQUEST_LIST, MISSION_CLEAR_ALL through an
//! endpoint) is followed until the vehicle's or the station's MISSION_ACK
//! (or [`FOREIGN_IDLE`] of silence); shotpilot's own upload or download
//! waits for it to end. A transfer a station starts while shotpilot's own
//! runs is held back (its frames kept, newest per message) and passed to
//! the vehicle when shotpilot's ends, so the station's own timeouts see at
//! most a delay. When another station stores or clears a mission (the
//! vehicle ACCEPTED it), or its transfer went silent unfinished, the
//! count [`super::Telemetry::mission_changes`] goes up: the daemon reads
//! the vehicle's mission back and marks its shots `replaced` or `cleared`.

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use mavlink::dialects::common::{MavMessage, MavMissionResult, MavMissionType};
use mavlink::{AsyncMavConnection, MAVLinkMessageRaw, MavHeader, Message};
use serde::Serialize;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::transport::{self, Connection, LinkUrl};

/// A transfer by another station counts as over after this long without
/// one of its mission messages (the autopilots give up sooner).
pub const FOREIGN_IDLE: Duration = Duration::from_secs(3);
/// Frames queued for one endpoint before newer ones are dropped (a client
/// that stops reading must not hold the vehicle's traffic).
const OUTLET_QUEUE: usize = 512;
/// Reconnect delay of a `tcpout:` endpoint.
const ENDPOINT_RETRY: Duration = Duration::from_secs(1);

/// A link a frame came in on or goes out on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum LinkId {
    /// The vehicle's link (`[link] url`).
    Vehicle,
    /// A forward endpoint (one per `tcpin:` client), numbered from 1.
    Endpoint(u32),
}

/// Where each (system, component) was heard.
#[derive(Debug, Default)]
pub struct RouteTable {
    seen: HashMap<(u8, u8), HashSet<LinkId>>,
}

impl RouteTable {
    /// Notes that `(system, component)` speaks on `link` (system 0 is not
    /// an address and is not learned).
    pub fn learn(&mut self, link: LinkId, system: u8, component: u8) {
        if system != 0 {
            self.seen
                .entry((system, component))
                .or_default()
                .insert(link);
        }
    }

    /// Forgets a link (a `tcpin:` client that left).
    pub fn forget(&mut self, link: LinkId) {
        self.seen.retain(|_, links| {
            links.remove(&link);
            !links.is_empty()
        });
    }

    /// The links a message from `from` with `target` (system, component)
    /// goes to, among `links`. `own` is shotpilot: messages to it stop here.
    pub fn destinations(
        &self,
        from: LinkId,
        target: Option<(u8, u8)>,
        own: (u8, u8),
        links: &[LinkId],
    ) -> Vec<LinkId> {
        let others = links.iter().copied().filter(|l| *l != from);
        let (system, component) = match target {
            None | Some((0, _)) => return others.collect(),
            Some(t) => t,
        };
        if (system, component) == own {
            return Vec::new();
        }
        // Where the component was heard; else (broadcast to the system's
        // components, or a component not heard yet) where the system was.
        let wanted: HashSet<LinkId> = match self.seen.get(&(system, component)) {
            Some(l) if component != 0 => l.clone(),
            _ => self
                .seen
                .iter()
                .filter(|((s, _), _)| *s == system)
                .flat_map(|(_, l)| l.iter().copied())
                .collect(),
        };
        others.filter(|l| wanted.contains(l)).collect()
    }
}

/// The message's target (system, component), if it has one.
fn target_of(m: &MavMessage) -> Option<(u8, u8)> {
    let s = m.target_system_id()?;
    Some((s, m.target_component_id().unwrap_or(0)))
}

fn mission_types(t: MavMissionType) -> bool {
    matches!(
        t,
        MavMissionType::MAV_MISSION_TYPE_MISSION | MavMissionType::MAV_MISSION_TYPE_ALL
    )
}

/// What kind of transfer another station runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ForeignKind {
    /// It uploads a mission.
    Upload,
    /// It reads the mission.
    Download,
    /// It clears the mission.
    Clear,
}

/// The transfer a message starts, if it starts one.
fn starts_transfer(m: &MavMessage) -> Option<ForeignKind> {
    match m {
        MavMessage::MISSION_COUNT(c)
            if c.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
        {
            Some(if c.count == 0 {
                ForeignKind::Clear
            } else {
                ForeignKind::Upload
            })
        }
        MavMessage::MISSION_REQUEST_LIST(r)
            if r.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION =>
        {
            Some(ForeignKind::Download)
        }
        MavMessage::MISSION_CLEAR_ALL(c) if mission_types(c.mission_type) => {
            Some(ForeignKind::Clear)
        }
        _ => None,
    }
}

/// Whether a message belongs to the mission protocol (ArduPilot still
/// speaks the legacy MISSION_REQUEST / MISSION_ITEM).
#[allow(deprecated)]
fn is_mission(m: &MavMessage) -> bool {
    matches!(
        m,
        MavMessage::MISSION_COUNT(_)
            | MavMessage::MISSION_REQUEST_LIST(_)
            | MavMessage::MISSION_REQUEST(_)
            | MavMessage::MISSION_REQUEST_INT(_)
            | MavMessage::MISSION_ITEM(_)
            | MavMessage::MISSION_ITEM_INT(_)
            | MavMessage::MISSION_ACK(_)
            | MavMessage::MISSION_CLEAR_ALL(_)
    )
}

#[derive(Debug, Clone, Copy)]
struct Foreign {
    peer: (u8, u8),
    kind: ForeignKind,
    last: Instant,
}

/// A frame kept back while shotpilot's own transfer runs.
struct Held {
    key: ((u8, u8), u32),
    start: Option<ForeignKind>,
    raw: MAVLinkMessageRaw,
}

/// What to do with a frame from an endpoint to the vehicle.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// Send it on.
    Pass,
    /// Keep it until shotpilot's own transfer ends.
    Hold,
}

/// One mission transfer on the vehicle's link at a time (see the module
/// documentation). Pure state, driven by the router and the link actor.
#[derive(Default)]
pub struct MissionGate {
    own: bool,
    foreign: Option<Foreign>,
    held: Vec<Held>,
}

impl MissionGate {
    /// Whether another station's transfer runs at `now`.
    pub fn foreign_busy(&self, now: Instant) -> bool {
        self.foreign
            .is_some_and(|f| now.saturating_duration_since(f.last) < FOREIGN_IDLE)
    }

    /// When another station's transfer, silent from now on, counts as over.
    pub fn foreign_deadline(&self) -> Option<Instant> {
        self.foreign.map(|f| f.last + FOREIGN_IDLE)
    }

    /// Whether shotpilot's own transfer runs.
    pub fn own_busy(&self) -> bool {
        self.own
    }

    /// shotpilot starts a transfer: refused (the caller waits) while
    /// another station's runs.
    pub fn begin_own(&mut self, now: Instant) -> bool {
        if self.foreign_busy(now) {
            return false;
        }
        self.own = true;
        true
    }

    /// shotpilot's transfer ended: the frames held meanwhile, in order;
    /// the transfer the last of them starts is followed from `now`.
    fn end_own(&mut self, now: Instant) -> Vec<MAVLinkMessageRaw> {
        self.own = false;
        for h in &self.held {
            if let Some(kind) = h.start {
                self.foreign = Some(Foreign {
                    peer: h.key.0,
                    kind,
                    last: now,
                });
            }
        }
        self.held.drain(..).map(|h| h.raw).collect()
    }

    /// A silent foreign transfer is over; true when it may have changed
    /// the mission (an upload or clear that never saw its ACK).
    pub fn expire(&mut self, now: Instant) -> bool {
        match self.foreign {
            Some(f) if !self.foreign_busy(now) => {
                self.foreign = None;
                warn!(
                    system = f.peer.0,
                    component = f.peer.1,
                    kind = ?f.kind,
                    "another station's mission transfer went silent unfinished"
                );
                f.kind != ForeignKind::Download
            }
            _ => false,
        }
    }

    /// A message from station `src` to the vehicle.
    pub fn on_station_frame(&mut self, src: (u8, u8), m: &MavMessage, now: Instant) -> Verdict {
        if let Some(kind) = starts_transfer(m) {
            if self.own {
                return Verdict::Hold;
            }
            if self.foreign.is_none_or(|f| f.peer != src || f.kind != kind) {
                info!(
                    system = src.0,
                    component = src.1,
                    ?kind,
                    "another station starts a mission transfer"
                );
            }
            self.foreign = Some(Foreign {
                peer: src,
                kind,
                last: now,
            });
            return Verdict::Pass;
        }
        if let Some(f) = &mut self.foreign
            && f.peer == src
            && is_mission(m)
        {
            f.last = now;
            // A download ends with the station's ACK.
            if matches!(m, MavMessage::MISSION_ACK(_)) && f.kind == ForeignKind::Download {
                self.foreign = None;
            }
        }
        Verdict::Pass
    }

    /// A message from the vehicle; true when it says another station's
    /// upload or clear was accepted (the vehicle's mission changed).
    pub fn on_vehicle_frame(&mut self, m: &MavMessage, now: Instant) -> bool {
        let Some(f) = &mut self.foreign else {
            return false;
        };
        if !is_mission(m)
            || target_of(m).is_none_or(|(s, c)| (s, c) != f.peer && !(s == f.peer.0 && c == 0))
        {
            return false;
        }
        f.last = now;
        if let MavMessage::MISSION_ACK(a) = m
            && mission_types(a.mission_type)
        {
            let kind = f.kind;
            self.foreign = None;
            let changed = kind != ForeignKind::Download
                && a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED;
            info!(?kind, result = ?a.mavtype, "another station's mission transfer ended");
            return changed;
        }
        false
    }

    fn hold(&mut self, src: (u8, u8), m: &MavMessage, raw: MAVLinkMessageRaw) {
        let key = (src, m.message_id());
        self.held.retain(|h| h.key != key);
        self.held.push(Held {
            key,
            start: starts_transfer(m),
            raw,
        });
    }
}

fn copy_raw(r: &MAVLinkMessageRaw) -> MAVLinkMessageRaw {
    match r {
        MAVLinkMessageRaw::V1(m) => MAVLinkMessageRaw::V1(*m),
        MAVLinkMessageRaw::V2(m) => MAVLinkMessageRaw::V2(*m),
    }
}

/// Parses a raw frame of the common dialect.
pub fn parse_raw(raw: &MAVLinkMessageRaw) -> Option<(MavHeader, MavMessage)> {
    let m = MavMessage::parse(raw.version(), raw.message_id(), raw.payload()).ok()?;
    let h = MavHeader {
        system_id: raw.system_id(),
        component_id: raw.component_id(),
        sequence: raw.sequence(),
    };
    Some((h, m))
}

/// One forward endpoint as the status shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ForwardStatus {
    /// Its URL as configured.
    pub url: String,
    /// The local address it is bound to (`udpin:`, `tcpin:`), once bound.
    pub bound: Option<String>,
    /// Clients connected now (`tcpin:`; 1 for the other kinds once open).
    pub clients: u32,
    /// Frames received from it.
    pub frames_in: u64,
    /// Frames sent to it.
    pub frames_out: u64,
    /// Frames for it dropped because it did not keep up.
    pub dropped: u64,
    /// Frames from it held back while shotpilot's own mission transfer ran.
    pub held: u64,
}

#[derive(Debug, Default)]
struct Counters {
    frames_in: AtomicU64,
    frames_out: AtomicU64,
    dropped: AtomicU64,
    held: AtomicU64,
    clients: AtomicU64,
}

struct Outlet {
    id: LinkId,
    endpoint: usize,
    tx: mpsc::Sender<MAVLinkMessageRaw>,
}

struct Inner {
    /// Frames received from the vehicle, by message id (counted while
    /// there are endpoints).
    from_vehicle: HashMap<u32, u64>,
    table: RouteTable,
    outlets: Vec<Outlet>,
    gate: MissionGate,
    next_id: u32,
}

/// The router between the vehicle's link and the forward endpoints.
pub struct Router {
    own: (u8, u8),
    inner: Mutex<Inner>,
    vehicle: Mutex<Option<Arc<Connection>>>,
    changes: watch::Sender<u64>,
    endpoints: Vec<(String, Counters, Mutex<Option<SocketAddr>>)>,
}

impl std::fmt::Debug for Router {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Router")
            .field("own", &self.own)
            .field("endpoints", &self.status())
            .finish()
    }
}

impl Router {
    /// A router for shotpilot at `own` (system, component) with the given
    /// endpoint URLs (already parsed, see [`parse_forward`]).
    pub fn new(own: (u8, u8), endpoints: &[LinkUrl]) -> Self {
        Self {
            own,
            inner: Mutex::new(Inner {
                from_vehicle: HashMap::new(),
                table: RouteTable::default(),
                outlets: Vec::new(),
                gate: MissionGate::default(),
                next_id: 1,
            }),
            vehicle: Mutex::new(None),
            changes: watch::channel(0).0,
            endpoints: endpoints
                .iter()
                .map(|u| (u.to_string(), Counters::default(), Mutex::new(None)))
                .collect(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// How many missions other stations stored or cleared (see the module
    /// documentation).
    pub fn mission_changes(&self) -> watch::Receiver<u64> {
        self.changes.subscribe()
    }

    fn bump_changes(&self) {
        self.changes.send_modify(|n| *n += 1);
    }

    /// The vehicle's connection (None while it is down).
    pub(super) fn set_vehicle(&self, conn: Option<Arc<Connection>>) {
        *self.vehicle.lock().unwrap_or_else(|e| e.into_inner()) = conn;
    }

    fn vehicle_conn(&self) -> Option<Arc<Connection>> {
        self.vehicle
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The endpoints' state.
    pub fn status(&self) -> Vec<ForwardStatus> {
        self.endpoints
            .iter()
            .map(|(url, c, bound)| ForwardStatus {
                url: url.clone(),
                bound: bound
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .map(|a| a.to_string()),
                clients: c.clients.load(Ordering::Relaxed) as u32,
                frames_in: c.frames_in.load(Ordering::Relaxed),
                frames_out: c.frames_out.load(Ordering::Relaxed),
                dropped: c.dropped.load(Ordering::Relaxed),
                held: c.held.load(Ordering::Relaxed),
            })
            .collect()
    }

    /// Frames of message `id` received from the vehicle since start (counted
    /// only with forward endpoints configured: what a station connected
    /// directly would have received).
    pub fn frames_from_vehicle(&self, id: u32) -> u64 {
        self.lock().from_vehicle.get(&id).copied().unwrap_or(0)
    }

    /// The address endpoint `i` is bound to, once bound.
    pub fn bound(&self, i: usize) -> Option<SocketAddr> {
        self.endpoints
            .get(i)
            .and_then(|(_, _, b)| *b.lock().unwrap_or_else(|e| e.into_inner()))
    }

    /// shotpilot starts a mission transfer (false: another station's runs,
    /// wait until [`Router::foreign_deadline`]).
    pub fn begin_own(&self, now: Instant) -> bool {
        self.lock().gate.begin_own(now)
    }

    /// Whether another station's transfer runs.
    pub fn foreign_busy(&self, now: Instant) -> bool {
        self.lock().gate.foreign_busy(now)
    }

    /// When a silent foreign transfer counts as over.
    pub fn foreign_deadline(&self) -> Option<Instant> {
        self.lock().gate.foreign_deadline()
    }

    /// Whether shotpilot's own transfer is marked as running.
    pub fn own_busy(&self) -> bool {
        self.lock().gate.own_busy()
    }

    /// Ends a silent foreign transfer (counting a possible mission change).
    pub fn expire(&self, now: Instant) {
        if self.lock().gate.expire(now) {
            self.bump_changes();
        }
    }

    /// shotpilot's transfer ended: the frames held meanwhile go to the
    /// vehicle now.
    pub async fn end_own(&self, now: Instant) {
        let held = self.lock().gate.end_own(now);
        if held.is_empty() {
            return;
        }
        debug!(
            frames = held.len(),
            "passing held mission frames to the vehicle"
        );
        if let Some(conn) = self.vehicle_conn() {
            for raw in held {
                if let Err(e) = conn.send_raw(&raw).await {
                    debug!(error = %e, "routing to the vehicle failed");
                }
            }
        }
    }

    /// A frame from the vehicle: learned, forwarded to the endpoints its
    /// target says, and given back parsed for the link actor.
    pub fn on_vehicle_frame(
        &self,
        raw: &MAVLinkMessageRaw,
        now: Instant,
    ) -> Option<(MavHeader, MavMessage)> {
        let parsed = parse_raw(raw);
        if self.endpoints.is_empty() {
            return parsed;
        }
        let target = parsed.as_ref().and_then(|(_, m)| target_of(m));
        let src = (raw.system_id().min(255) as u8, raw.component_id());
        let mut changed = false;
        {
            let mut inner = self.lock();
            *inner.from_vehicle.entry(raw.message_id()).or_default() += 1;
            inner.table.learn(LinkId::Vehicle, src.0, src.1);
            if let Some((_, m)) = &parsed {
                changed = inner.gate.on_vehicle_frame(m, now);
            }
            self.send_to_outlets(&inner, LinkId::Vehicle, target, raw);
        }
        if changed {
            self.bump_changes();
        }
        parsed
    }

    fn send_to_outlets(
        &self,
        inner: &Inner,
        from: LinkId,
        target: Option<(u8, u8)>,
        raw: &MAVLinkMessageRaw,
    ) -> bool {
        let mut links: Vec<LinkId> = inner.outlets.iter().map(|o| o.id).collect();
        links.push(LinkId::Vehicle);
        let dests = inner.table.destinations(from, target, self.own, &links);
        for o in &inner.outlets {
            if !dests.contains(&o.id) {
                continue;
            }
            let c = &self.endpoints[o.endpoint].1;
            match o.tx.try_send(copy_raw(raw)) {
                Ok(()) => c.frames_out.fetch_add(1, Ordering::Relaxed),
                Err(_) => c.dropped.fetch_add(1, Ordering::Relaxed),
            };
        }
        dests.contains(&LinkId::Vehicle)
    }

    /// A frame from an endpoint's client.
    async fn on_endpoint_frame(
        &self,
        id: LinkId,
        endpoint: usize,
        raw: MAVLinkMessageRaw,
        now: Instant,
    ) {
        let c = &self.endpoints[endpoint].1;
        c.frames_in.fetch_add(1, Ordering::Relaxed);
        let parsed = parse_raw(&raw);
        let target = parsed.as_ref().and_then(|(_, m)| target_of(m));
        let src = (raw.system_id().min(255) as u8, raw.component_id());
        let to_vehicle = {
            let mut inner = self.lock();
            inner.table.learn(id, src.0, src.1);
            let to_vehicle = self.send_to_outlets(&inner, id, target, &raw);
            if to_vehicle && let Some((_, m)) = &parsed {
                match inner.gate.on_station_frame(src, m, now) {
                    Verdict::Pass => true,
                    Verdict::Hold => {
                        c.held.fetch_add(1, Ordering::Relaxed);
                        info!(
                            system = src.0,
                            component = src.1,
                            message = m.message_name(),
                            "held until shotpilot's own mission transfer ends"
                        );
                        inner.gate.hold(src, m, copy_raw(&raw));
                        false
                    }
                }
            } else {
                to_vehicle
            }
        };
        if to_vehicle
            && let Some(conn) = self.vehicle_conn()
            && let Err(e) = conn.send_raw(&raw).await
        {
            debug!(error = %e, "routing to the vehicle failed");
        }
    }

    fn add_outlet(&self, endpoint: usize) -> (LinkId, mpsc::Receiver<MAVLinkMessageRaw>) {
        let (tx, rx) = mpsc::channel(OUTLET_QUEUE);
        let mut inner = self.lock();
        let id = LinkId::Endpoint(inner.next_id);
        inner.next_id += 1;
        inner.outlets.push(Outlet { id, endpoint, tx });
        self.endpoints[endpoint]
            .1
            .clients
            .fetch_add(1, Ordering::Relaxed);
        (id, rx)
    }

    fn remove_outlet(&self, id: LinkId, endpoint: usize) {
        let mut inner = self.lock();
        inner.outlets.retain(|o| o.id != id);
        inner.table.forget(id);
        self.endpoints[endpoint]
            .1
            .clients
            .fetch_sub(1, Ordering::Relaxed);
    }

    fn set_bound(&self, endpoint: usize, addr: SocketAddr) {
        *self.endpoints[endpoint]
            .2
            .lock()
            .unwrap_or_else(|e| e.into_inner()) = Some(addr);
    }
}

/// Parses `[link] forward`, refusing an endpoint that is the vehicle's own
/// URL or a serial device (share a radio through one program only).
pub fn parse_forward(
    urls: &[String],
    vehicle: &str,
) -> Result<Vec<LinkUrl>, super::error::LinkError> {
    urls.iter()
        .map(|u| {
            let url: LinkUrl = u.parse()?;
            let bad = |reason: &str| super::error::LinkError::BadUrl {
                url: u.clone(),
                reason: reason.into(),
            };
            if u == vehicle {
                return Err(bad("a forward endpoint cannot be the vehicle's own link"));
            }
            if matches!(url, LinkUrl::Serial { .. }) {
                return Err(bad(
                    "forward endpoints are udpin, udpout, tcpin or tcpout (a serial port belongs to the vehicle link)",
                ));
            }
            Ok(url)
        })
        .collect()
}

/// Starts one task per endpoint; they end with `cancel`.
pub fn spawn_endpoints(
    router: &Arc<Router>,
    urls: Vec<LinkUrl>,
    cancel: &CancellationToken,
) -> Vec<JoinHandle<()>> {
    urls.into_iter()
        .enumerate()
        .map(|(i, url)| {
            let router = router.clone();
            let cancel = cancel.clone();
            tokio::spawn(async move { run_endpoint(router, i, url, cancel).await })
        })
        .collect()
}

async fn run_endpoint(router: Arc<Router>, i: usize, url: LinkUrl, cancel: CancellationToken) {
    match &url {
        LinkUrl::TcpIn { addr } => {
            let listener = match tokio::net::TcpListener::bind(addr.as_str()).await {
                Ok(l) => l,
                Err(e) => {
                    warn!(%url, error = %e, "forward endpoint cannot listen; it stays off");
                    return;
                }
            };
            if let Ok(a) = listener.local_addr() {
                router.set_bound(i, a);
                info!(%url, bound = %a, "forward endpoint listening");
            }
            loop {
                let accepted = tokio::select! {
                    _ = cancel.cancelled() => return,
                    a = listener.accept() => a,
                };
                let stream = match accepted.and_then(|(s, peer)| {
                    info!(%url, %peer, "forward client connected");
                    s.into_std()
                }) {
                    Ok(s) => s,
                    Err(e) => {
                        warn!(%url, error = %e, "accepting a forward client failed");
                        continue;
                    }
                };
                let router = router.clone();
                let cancel = cancel.clone();
                let url = url.clone();
                tokio::spawn(async move {
                    let conn = mavlink::TcpConfig::from_stream(stream)
                        .map(mavlink::ConnectionAddress::Tcp);
                    let conn = match conn {
                        Ok(a) => mavlink::AsyncConnectable::connect_async::<MavMessage>(&a).await,
                        Err(e) => Err(e),
                    };
                    match conn {
                        Ok(mut c) => {
                            c.set_allow_recv_any_version(true);
                            serve(&router, i, Arc::new(c), &cancel).await;
                            info!(%url, "forward client left");
                        }
                        Err(e) => warn!(%url, error = %e, "forward client connection failed"),
                    }
                });
            }
        }
        _ => loop {
            let socket = match transport::bind_udp_in(&url).await {
                Ok(s) => s,
                Err(e) => {
                    warn!(%url, error = %e, "forward endpoint cannot listen; it stays off");
                    return;
                }
            };
            if let Some(a) = socket.as_ref().and_then(|s| s.local_addr().ok()) {
                router.set_bound(i, a);
                info!(%url, bound = %a, "forward endpoint listening");
            }
            let conn = tokio::select! {
                _ = cancel.cancelled() => return,
                c = transport::connect(&url, socket.as_ref(), mavlink::MavlinkVersion::V2, None) => c,
            };
            match conn {
                Ok(c) => {
                    info!(%url, "forward endpoint open");
                    serve(&router, i, Arc::new(c), &cancel).await;
                }
                Err(e) => debug!(%url, error = %e, "forward endpoint cannot open; retrying"),
            }
            tokio::select! {
                _ = cancel.cancelled() => return,
                _ = tokio::time::sleep(ENDPOINT_RETRY) => {}
            }
        },
    }
}

/// Reads one client and writes to it until it fails or `cancel`.
async fn serve(
    router: &Arc<Router>,
    endpoint: usize,
    conn: Arc<Connection>,
    cancel: &CancellationToken,
) {
    let (id, mut rx) = router.add_outlet(endpoint);
    let writer_conn = conn.clone();
    let writer = tokio::spawn(async move {
        while let Some(raw) = rx.recv().await {
            if let Err(e) = writer_conn.send_raw(&raw).await {
                debug!(error = %e, "forwarding to an endpoint failed");
            }
        }
    });
    loop {
        let r = tokio::select! {
            _ = cancel.cancelled() => break,
            r = conn.recv_raw() => r,
        };
        match r {
            Ok(raw) => {
                let now = crate::clock::now();
                router.on_endpoint_frame(id, endpoint, raw, now).await;
            }
            Err(mavlink::error::MessageReadError::Parse(e)) => {
                debug!(error = %e, "undecodable frame")
            }
            Err(mavlink::error::MessageReadError::Io(e)) => {
                debug!(error = %e, "forward client read failed");
                break;
            }
        }
    }
    router.remove_outlet(id, endpoint);
    writer.abort();
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{
        MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_REQUEST_INT_DATA, MISSION_REQUEST_LIST_DATA,
    };

    const QGC: (u8, u8) = (255, 190);
    const US: (u8, u8) = (255, 191);
    const VEH: (u8, u8) = (1, 1);
    const MISSION: MavMissionType = MavMissionType::MAV_MISSION_TYPE_MISSION;

    fn count(n: u16) -> MavMessage {
        MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: n,
            target_system: VEH.0,
            target_component: VEH.1,
            mission_type: MISSION,
            opaque_id: 0,
        })
    }

    fn ack_to(to: (u8, u8), r: MavMissionResult) -> MavMessage {
        MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: to.0,
            target_component: to.1,
            mavtype: r,
            mission_type: MISSION,
            opaque_id: 0,
        })
    }

    #[test]
    fn routes_by_target_as_mavlink_says() {
        let e1 = LinkId::Endpoint(1);
        let e2 = LinkId::Endpoint(2);
        let links = [LinkId::Vehicle, e1, e2];
        let mut t = RouteTable::default();
        t.learn(LinkId::Vehicle, VEH.0, VEH.1);
        t.learn(LinkId::Vehicle, VEH.0, 100); // the camera
        t.learn(e1, QGC.0, QGC.1);
        // broadcast: everywhere but back
        assert_eq!(
            t.destinations(LinkId::Vehicle, None, US, &links),
            vec![e1, e2]
        );
        assert_eq!(
            t.destinations(e1, Some((0, 0)), US, &links),
            vec![LinkId::Vehicle, e2]
        );
        // to QGC: only where QGC was heard
        assert_eq!(
            t.destinations(LinkId::Vehicle, Some(QGC), US, &links),
            vec![e1]
        );
        // to us: nowhere
        assert!(
            t.destinations(LinkId::Vehicle, Some(US), US, &links)
                .is_empty()
        );
        // to the vehicle's camera, or any of its components
        assert_eq!(
            t.destinations(e1, Some((1, 100)), US, &links),
            vec![LinkId::Vehicle]
        );
        assert_eq!(
            t.destinations(e1, Some((1, 0)), US, &links),
            vec![LinkId::Vehicle]
        );
        // a component not heard yet of a heard system: where the system is
        assert_eq!(
            t.destinations(e1, Some((1, 154)), US, &links),
            vec![LinkId::Vehicle]
        );
        // an unknown system: nowhere
        assert!(t.destinations(e1, Some((7, 1)), US, &links).is_empty());
        // a client that left is forgotten
        t.forget(e1);
        assert!(
            t.destinations(LinkId::Vehicle, Some(QGC), US, &links)
                .is_empty()
        );
    }

    #[test]
    fn a_foreign_upload_is_followed_to_its_ack_and_counts_as_a_change() {
        let t0 = Instant::now();
        let mut g = MissionGate::default();
        assert_eq!(g.on_station_frame(QGC, &count(3), t0), Verdict::Pass);
        assert!(g.foreign_busy(t0));
        assert!(!g.begin_own(t0), "our upload waits");
        let req = MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq: 0,
            target_system: QGC.0,
            target_component: QGC.1,
            mission_type: MISSION,
        });
        let t1 = t0 + Duration::from_secs(2);
        assert!(!g.on_vehicle_frame(&req, t1));
        // the request kept it alive past the idle time from its start
        assert!(g.foreign_busy(t0 + Duration::from_secs(4)));
        // an ACK to someone else does not end it
        assert!(!g.on_vehicle_frame(&ack_to(US, MavMissionResult::MAV_MISSION_ACCEPTED), t1));
        assert!(g.foreign_busy(t1));
        assert!(g.on_vehicle_frame(&ack_to(QGC, MavMissionResult::MAV_MISSION_ACCEPTED), t1));
        assert!(!g.foreign_busy(t1));
        assert!(g.begin_own(t1));
    }

    #[test]
    fn a_refused_or_read_only_transfer_is_no_change() {
        let t0 = Instant::now();
        let mut g = MissionGate::default();
        g.on_station_frame(QGC, &count(3), t0);
        assert!(!g.on_vehicle_frame(&ack_to(QGC, MavMissionResult::MAV_MISSION_ERROR), t0));
        assert!(!g.foreign_busy(t0));
        let list = MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: VEH.0,
            target_component: VEH.1,
            mission_type: MISSION,
        });
        g.on_station_frame(QGC, &list, t0);
        assert!(g.foreign_busy(t0));
        // the station's final ACK ends its download
        g.on_station_frame(
            QGC,
            &ack_to(VEH, MavMissionResult::MAV_MISSION_ACCEPTED),
            t0,
        );
        assert!(!g.foreign_busy(t0));
    }

    #[test]
    fn a_silent_foreign_upload_expires_in_doubt() {
        let t0 = Instant::now();
        let mut g = MissionGate::default();
        g.on_station_frame(QGC, &count(2), t0);
        assert!(!g.expire(t0 + Duration::from_secs(1)));
        assert!(
            g.expire(t0 + FOREIGN_IDLE),
            "an upload that went silent may have changed the mission"
        );
        assert!(g.begin_own(t0 + FOREIGN_IDLE));
    }

    #[test]
    fn a_station_starting_during_our_transfer_is_held_then_released() {
        let t0 = Instant::now();
        let mut g = MissionGate::default();
        assert!(g.begin_own(t0));
        assert_eq!(g.on_station_frame(QGC, &count(3), t0), Verdict::Hold);
        let raw = || MAVLinkMessageRaw::V2(mavlink::MAVLinkV2MessageRaw::new());
        g.hold(QGC, &count(3), raw());
        g.hold(QGC, &count(3), raw());
        assert!(!g.foreign_busy(t0), "held, not started");
        let t1 = t0 + Duration::from_secs(5);
        assert_eq!(g.end_own(t1).len(), 1, "the newest of each message is kept");
        assert!(!g.own_busy());
        assert!(g.foreign_busy(t1), "the released transfer is followed");
        assert!(!g.begin_own(t1));
    }

    #[test]
    fn forward_urls_are_checked() {
        let ok = parse_forward(
            &["udpout:127.0.0.1:14550".into(), "tcpin:0.0.0.0:5760".into()],
            "udpin:0.0.0.0:14550",
        );
        assert_eq!(ok.map(|v| v.len()).ok(), Some(2));
        for bad in [
            "serial:/dev/ttyUSB0:57600",
            "udpin:0.0.0.0:14550",
            "udp:1:2",
        ] {
            assert!(
                parse_forward(&[bad.into()], "udpin:0.0.0.0:14550").is_err(),
                "{bad} should be refused"
            );
        }
    }
}
