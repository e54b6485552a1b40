//! LinkHandle: what other tasks hold to send commands and read telemetry
//! (mission transfer and its verified upload, arming, modes, the stop, the
//! camera protocol with its DO_DIGICAM_CONTROL fallback, the gimbal protocol
//! v2 taken and given back).

use std::time::Duration;

use serde::Serialize;
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{info, warn};

use crate::mission::{Download, Flavour, MissionItem, UploadReport};

use super::command::{Command, GuidedSetpoint, HoldAck};
use super::error::LinkError;
use super::modes::FlightMode;
use super::router;
use super::telemetry::{
    GimbalControl, GimbalManagerStatus, ImageCaptured, Telemetry, VehicleState,
};

/// How a picture was asked for ([`LinkHandle::capture_image`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhotoReport {
    /// `camera_protocol` (MAV_CMD_IMAGE_START_CAPTURE to the camera
    /// component) or `digicam_control` (MAV_CMD_DO_DIGICAM_CONTROL to the
    /// autopilot, where no MAVLink camera answered).
    pub method: &'static str,
    /// The component asked.
    pub component_id: u8,
    /// Its CAMERA_IMAGE_CAPTURED, when one came within the wait.
    pub captured: Option<ImageCaptured>,
}

/// The handle other tasks hold: sends commands, reads telemetry. Cheap to clone.
#[derive(Debug, Clone)]
pub struct LinkHandle {
    pub(super) tx: mpsc::Sender<Command>,
    /// The telemetry watch channels.
    pub telemetry: Telemetry,
    pub(super) gimbal: std::sync::Arc<watch::Sender<GimbalControl>>,
    pub(super) own: (u8, u8),
    pub(super) command_timeout: Duration,
    /// The `udpin:` socket's address once bound.
    pub(super) bound: watch::Receiver<Option<std::net::SocketAddr>>,
    pub(super) router: std::sync::Arc<router::Router>,
}

/// MAVLink message id of GIMBAL_MANAGER_STATUS.
const GIMBAL_MANAGER_STATUS_ID: u32 = 281;

/// A GIMBAL_MANAGER_STATUS younger than this is read as is; older, it is asked for.
const GIMBAL_STATUS_FRESH: Duration = Duration::from_secs(3);

/// GIMBAL_MANAGER_FLAGS_ROLL_LOCK | PITCH_LOCK | YAW_IN_VEHICLE_FRAME.
const GIMBAL_PITCHYAW_FLAGS: f32 = (4 | 8 | 32) as f32;

impl LinkHandle {
    async fn call<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<Result<T, LinkError>>) -> Command,
    ) -> Result<T, LinkError> {
        let (reply, rx) = oneshot::channel();
        self.tx
            .send(make(reply))
            .await
            .map_err(|_| LinkError::ActorGone)?;
        rx.await.map_err(|_| LinkError::ActorGone)?
    }

    /// Uploads a mission and waits for the vehicle's ACK.
    pub async fn upload_mission(&self, items: Vec<MissionItem>) -> Result<UploadReport, LinkError> {
        let points = crate::mission::plan::points_gimbal_v2(&items);
        let takes = crate::mission::plan::takes_gimbal_control(&items);
        let report = self
            .call(|reply| Command::UploadMission { items, reply })
            .await?;
        self.gimbal.send_modify(|g| {
            g.mission_points_gimbal = points;
            g.mission_takes_control = takes;
        });
        Ok(report)
    }

    /// Uploads `items`, then reads the vehicle's mission back and compares
    /// (without item 0 for ArduPilot, which keeps home there): `Some(true)`
    /// when it holds exactly the items, `None` when the read-back failed
    /// (logged). A read-back that differs is [`LinkError::ReadBackDiffers`].
    pub async fn upload_verified(
        &self,
        items: &[MissionItem],
        flavour: Flavour,
    ) -> Result<(UploadReport, Option<bool>), LinkError> {
        let report = self.upload_mission(items.to_vec()).await?;
        let verified = match self.download_mission().await {
            Ok(d) => Some(crate::mission::upload::same_mission(
                items,
                &d.items,
                flavour == Flavour::ArduPilot,
            )),
            Err(e) => {
                tracing::warn!("mission read-back failed: {e}");
                None
            }
        };
        if verified == Some(false) {
            return Err(LinkError::ReadBackDiffers);
        }
        Ok((report, verified))
    }

    /// Downloads the vehicle's mission.
    pub async fn download_mission(&self) -> Result<Download, LinkError> {
        self.call(|reply| Command::DownloadMission { reply }).await
    }

    /// Cancels the running transfer; true if one was running.
    pub async fn cancel_transfer(&self) -> Result<bool, LinkError> {
        self.call(|reply| Command::CancelTransfer { reply }).await
    }

    /// Arms or disarms (operator action).
    pub async fn arm(&self, arm: bool) -> Result<(), LinkError> {
        self.call(|reply| Command::Arm { arm, reply }).await
    }

    /// Changes flight mode (operator action). Switching to the mission
    /// mode starts the mission on an armed vehicle, so gimbal control is
    /// taken first as in [`LinkHandle::start_mission`]; leaving the mission
    /// for another mode gives back gimbal control taken for it.
    pub async fn set_mode(&self, mode: FlightMode) -> Result<(), LinkError> {
        if mode == FlightMode::Mission {
            self.acquire_for_mission().await;
        }
        self.call(|reply| Command::SetMode { mode, reply }).await?;
        let release =
            mode != FlightMode::Mission && self.telemetry.gimbal_control.borrow().for_mission;
        if release && let Err(e) = self.release_gimbal().await {
            warn!(error = %e, "gimbal release after the mode change failed");
        }
        Ok(())
    }

    /// Stops the vehicle where it is (operator action): `MAV_CMD_DO_SET_MODE`
    /// to hold (PX4 AUTO.LOITER, ArduPilot LOITER), which pauses the
    /// mission. Replies once the vehicle's COMMAND_ACK came, with that ACK:
    /// ACCEPTED is `Ok`; any other result is [`LinkError::CommandRejected`],
    /// no ACK after the link's retries [`LinkError::CommandTimeout`]. A stop
    /// is never held up by another command in flight (a gimbal command,
    /// say): the actor sends it at once beside it. Gimbal control taken for
    /// a mission is given back after, as on any mode change.
    pub async fn hold(&self) -> Result<HoldAck, LinkError> {
        let ack = self.call(|reply| Command::Hold { reply }).await?;
        if self.telemetry.gimbal_control.borrow().for_mission
            && let Err(e) = self.release_gimbal().await
        {
            warn!(error = %e, "gimbal release after the stop failed");
        }
        Ok(ack)
    }

    /// Starts (Some), moves or stops (None) the guided setpoint stream
    /// (SET_POSITION_TARGET_GLOBAL_INT every [`crate::vehicle::GUIDED_PERIOD`]),
    /// which [`FlightMode::Guided`] flies; the operator's stop
    /// ([`LinkHandle::hold`]) ends it too.
    pub async fn guide(&self, setpoint: Option<GuidedSetpoint>) -> Result<(), LinkError> {
        self.call(|reply| Command::Guide { setpoint, reply }).await
    }

    /// Starts the uploaded mission (operator action). When the mission
    /// points the gimbal with the gimbal manager, takes gimbal control first
    /// ([`LinkHandle::acquire_gimbal`]); a refusal is a warning in
    /// [`GimbalControl`], not a failed start.
    pub async fn start_mission(&self) -> Result<(), LinkError> {
        self.acquire_for_mission().await;
        self.call(|reply| Command::StartMission { reply }).await
    }

    /// Takes gimbal control for the uploaded mission when it points the
    /// gimbal; a failure is logged and kept in [`GimbalControl::warning`].
    ///
    /// Not when the autopilot already holds control and the mission is one
    /// that takes it itself: on PX4, switching an armed vehicle to the
    /// mission mode starts the mission, whose first item makes the
    /// autopilot the primary controller; taking control back then (the
    /// operator's `start` after the mode change) would get the mission's
    /// own PITCHYAW denied.
    async fn acquire_for_mission(&self) {
        {
            let g = self.telemetry.gimbal_control.borrow();
            if !g.mission_points_gimbal || (g.held && g.for_mission) {
                return;
            }
            let takes_itself = g.mission_takes_control;
            drop(g);
            let vehicle = self.telemetry.vehicle.borrow().clone();
            let primary = self
                .telemetry
                .gimbal_manager
                .borrow()
                .map(|s| s.value.primary);
            if takes_itself
                && vehicle
                    .system_id
                    .is_some_and(|s| primary == Some((s, vehicle.component_id)))
            {
                info!("gimbal: the running mission holds control itself; not taking it back");
                self.note(
                    "the mission's own configure item holds gimbal control".into(),
                    None,
                );
                return;
            }
        }
        match self.acquire_gimbal().await {
            Ok(_) => self.gimbal.send_modify(|g| {
                g.for_mission = true;
                g.mission_seen_active = false;
            }),
            Err(e) => warn!(error = %e, "gimbal control not taken; starting the mission anyway"),
        }
    }

    fn note(&self, event: String, warning: Option<String>) {
        self.gimbal.send_modify(|g| {
            g.last_event = Some(event);
            g.warning = warning;
        });
    }

    /// Sends one COMMAND_LONG with the link's retries and waits for its ACK.
    pub async fn command_long(
        &self,
        command: mavlink::dialects::common::MavCmd,
        params: [f32; 7],
        target_component: Option<u8>,
    ) -> Result<(), LinkError> {
        self.call(|reply| Command::Long {
            command,
            params,
            target_component,
            reply,
        })
        .await
    }

    /// Takes one picture: with MAV_CMD_IMAGE_START_CAPTURE (one image) to
    /// the first MAVLink camera that said it captures images, else with
    /// MAV_CMD_DO_DIGICAM_CONTROL (shoot) to the autopilot; then waits up
    /// to `wait` for the CAMERA_IMAGE_CAPTURED that reports it (a camera
    /// trigger wired to the autopilot may never send one: `captured` is
    /// then None). A refused or unacknowledged command is an error.
    pub async fn capture_image(&self, wait: Duration) -> Result<PhotoReport, LinkError> {
        use mavlink::dialects::common::MavCmd;
        let camera = self
            .telemetry
            .cameras
            .borrow()
            .iter()
            .find(|c| c.captures_images)
            .map(|c| c.component_id);
        let mut captures = self.telemetry.captures.clone();
        let seen: Vec<(u8, i32)> = captures
            .borrow()
            .iter()
            .map(|c| (c.component_id, c.index))
            .collect();
        let (method, component_id) = match camera {
            Some(c) => {
                // param1 camera id 0 (all), param2 interval 0, param3 one
                // image, param4 sequence 0
                self.command_long(
                    MavCmd::MAV_CMD_IMAGE_START_CAPTURE,
                    [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
                    Some(c),
                )
                .await?;
                ("camera_protocol", c)
            }
            None => {
                // param5 1: shoot
                self.command_long(
                    MavCmd::MAV_CMD_DO_DIGICAM_CONTROL,
                    [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                    None,
                )
                .await?;
                let autopilot = self.telemetry.vehicle.borrow().component_id;
                ("digicam_control", autopilot)
            }
        };
        info!(method, component = component_id, "picture asked for");
        let fresh = |v: &Vec<ImageCaptured>| {
            v.iter()
                .rev()
                .find(|c| {
                    c.component_id == component_id && !seen.contains(&(c.component_id, c.index))
                })
                .cloned()
        };
        let captured =
            match tokio::time::timeout(wait, captures.wait_for(|v| fresh(v).is_some())).await {
                Ok(Ok(v)) => fresh(&v),
                _ => None,
            };
        match &captured {
            Some(c) => info!(index = c.index, ok = c.ok, url = %c.file_url, "picture reported"),
            None => warn!(
                method,
                wait_s = wait.as_secs_f64(),
                "no CAMERA_IMAGE_CAPTURED for the picture"
            ),
        }
        Ok(PhotoReport {
            method,
            component_id,
            captured,
        })
    }

    /// The vehicle's GIMBAL_MANAGER_STATUS: the last one when younger than
    /// 3 s, else asked for with MAV_CMD_REQUEST_MESSAGE (three tries, one
    /// command timeout each).
    pub async fn gimbal_manager_status(&self) -> Result<GimbalManagerStatus, LinkError> {
        let mut rx = self.telemetry.gimbal_manager.clone();
        let now = crate::clock::now();
        if let Some(s) = *rx.borrow_and_update()
            && now.saturating_duration_since(s.received) < GIMBAL_STATUS_FRESH
        {
            return Ok(s.value);
        }
        let component = self.telemetry.vehicle.borrow().component_id;
        for _ in 0..3 {
            self.request_message(GIMBAL_MANAGER_STATUS_ID, component)
                .await?;
            match tokio::time::timeout(self.command_timeout, rx.changed()).await {
                Ok(Ok(())) => {
                    if let Some(s) = *rx.borrow_and_update() {
                        return Ok(s.value);
                    }
                }
                Ok(Err(_)) => return Err(LinkError::ActorGone),
                Err(_) => {}
            }
        }
        Err(LinkError::Timeout {
            what: "GIMBAL_MANAGER_STATUS",
            seconds: 3.0 * self.command_timeout.as_secs_f64(),
        })
    }

    /// Takes primary gimbal control (gimbal protocol v2): reads
    /// GIMBAL_MANAGER_STATUS, notes (and logs) who holds control, and sends
    /// MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE with our sysid/compid as primary
    /// for the manager's gimbal device. Without a status (an old autopilot)
    /// it still tries, for all devices. Does nothing when we already hold
    /// control. Errors are also recorded in [`GimbalControl::warning`].
    pub async fn acquire_gimbal(&self) -> Result<GimbalControl, LinkError> {
        let current = self.telemetry.gimbal_control.borrow().clone();
        if current.held {
            return Ok(current);
        }
        let status = match self.gimbal_manager_status().await {
            Ok(s) => Some(s),
            Err(LinkError::Timeout { .. }) => {
                warn!("no GIMBAL_MANAGER_STATUS from the vehicle; configuring all gimbals");
                None
            }
            Err(e) => return Err(e),
        };
        let (device, target, previous) = match status {
            Some(s) => (
                s.gimbal_device_id,
                Some(s.manager_component),
                Some(s.primary),
            ),
            None => (0, None, None),
        };
        let vehicle = self.telemetry.vehicle.borrow().clone();
        match previous {
            Some(p) if p == self.own => info!("gimbal: we already hold primary control"),
            Some((0, 0)) | None => info!(device, "gimbal: taking primary control"),
            Some((s, c)) if Some(s) == vehicle.system_id && c == vehicle.component_id => {
                info!(device, "gimbal: taking primary control from the autopilot")
            }
            Some((s, c)) => warn!(
                device,
                "gimbal: taking primary control from {s}/{c} (another controller)"
            ),
        }
        let params = [
            f32::from(self.own.0),
            f32::from(self.own.1),
            crate::mission::plan::GIMBAL_CONTROL_UNCHANGED,
            crate::mission::plan::GIMBAL_CONTROL_UNCHANGED,
            0.0,
            0.0,
            f32::from(device),
        ];
        use mavlink::dialects::common::MavCmd;
        match self
            .command_long(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, params, target)
            .await
        {
            Ok(()) => {
                let from = previous.map_or("unknown".to_string(), |(s, c)| format!("{s}/{c}"));
                let event = format!("took gimbal control (device {device}) from {from}");
                info!("{event}");
                self.gimbal.send_modify(|g| {
                    g.held = true;
                    g.device_id = device;
                    g.previous = previous;
                    g.last_event = Some(event);
                    g.warning = None;
                });
                Ok(self.telemetry.gimbal_control.borrow().clone())
            }
            Err(e) => {
                let w = format!("gimbal control not taken: {e}");
                warn!("{w}");
                self.note("DO_GIMBAL_MANAGER_CONFIGURE failed".into(), Some(w));
                Err(e)
            }
        }
    }

    /// Gives gimbal control back (DO_GIMBAL_MANAGER_CONFIGURE with -3/-3,
    /// "remove control if in control", so a controller that took over
    /// meanwhile keeps it). Returns false when we did not hold control.
    pub async fn release_gimbal(&self) -> Result<bool, LinkError> {
        let current = self.telemetry.gimbal_control.borrow().clone();
        if !current.held {
            return Ok(false);
        }
        let target = self
            .telemetry
            .gimbal_manager
            .borrow()
            .map(|s| s.value.manager_component);
        let params = release_params(current.device_id);
        use mavlink::dialects::common::MavCmd;
        let r = self
            .command_long(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, params, target)
            .await;
        // Whatever the answer, we no longer count on holding control.
        self.gimbal.send_modify(|g| {
            g.held = false;
            g.for_mission = false;
        });
        match r {
            Ok(()) => {
                info!("released gimbal control");
                self.note("released gimbal control".into(), None);
                Ok(true)
            }
            Err(e) => {
                let w = format!("gimbal release not acknowledged: {e}");
                warn!("{w}");
                self.note("release sent".into(), Some(w));
                Err(e)
            }
        }
    }

    /// Points the gimbal now (DO_GIMBAL_MANAGER_PITCHYAW; pitch positive
    /// up, yaw relative to the vehicle, degrees), taking control first.
    pub async fn point_gimbal(&self, pitch_deg: f32, yaw_deg: f32) -> Result<(), LinkError> {
        let g = self.acquire_gimbal().await?;
        let target = self
            .telemetry
            .gimbal_manager
            .borrow()
            .map(|s| s.value.manager_component);
        use mavlink::dialects::common::MavCmd;
        self.command_long(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [
                pitch_deg,
                yaw_deg,
                f32::NAN,
                f32::NAN,
                GIMBAL_PITCHYAW_FLAGS,
                0.0,
                f32::from(g.device_id),
            ],
            target,
        )
        .await
    }

    /// Asks `target_component` of the vehicle's system for one message
    /// (MAV_CMD_REQUEST_MESSAGE); the answer arrives on the telemetry.
    pub async fn request_message(
        &self,
        message_id: u32,
        target_component: u8,
    ) -> Result<(), LinkError> {
        self.call(|reply| Command::RequestMessage {
            message_id,
            target_component,
            reply,
        })
        .await
    }

    /// The local address of a `udpin:` link's socket (the kernel's port for
    /// `udpin:HOST:0`), waiting up to `timeout` for the bind. A link of
    /// another scheme never binds one: it times out.
    pub async fn bound_addr(&self, timeout: Duration) -> Result<std::net::SocketAddr, LinkError> {
        let mut rx = self.bound.clone();
        match tokio::time::timeout(timeout, rx.wait_for(Option::is_some)).await {
            Ok(Ok(addr)) => (*addr).ok_or(LinkError::ActorGone),
            Ok(Err(_)) => Err(LinkError::ActorGone),
            Err(_) => Err(LinkError::Timeout {
                what: "the link's UDP socket",
                seconds: timeout.as_secs_f64(),
            }),
        }
    }

    /// The forward endpoints' state (`[link] forward`).
    pub fn forward_status(&self) -> Vec<router::ForwardStatus> {
        self.router.status()
    }

    /// Frames of MAVLink message `id` received from the vehicle (counted
    /// only while forward endpoints are configured).
    pub fn frames_from_vehicle(&self, id: u32) -> u64 {
        self.router.frames_from_vehicle(id)
    }

    /// The address forward endpoint `i` (in `[link] forward`'s order) is
    /// bound to, once bound (`udpin:` and `tcpin:`, port 0 included).
    pub fn forward_bound(&self, i: usize) -> Option<std::net::SocketAddr> {
        self.router.bound(i)
    }

    /// Waits until a vehicle heartbeat has been heard and the link is up.
    pub async fn wait_for_vehicle(&self, timeout: Duration) -> Result<VehicleState, LinkError> {
        let mut rx = self.telemetry.vehicle.clone();
        let wait = rx.wait_for(|v| v.system_id.is_some() && !v.link_lost);
        match tokio::time::timeout(timeout, wait).await {
            Ok(Ok(state)) => Ok(state.clone()),
            Ok(Err(_)) => Err(LinkError::ActorGone),
            Err(_) => Err(LinkError::Timeout {
                what: "a vehicle heartbeat",
                seconds: timeout.as_secs_f64(),
            }),
        }
    }
}

/// DO_GIMBAL_MANAGER_CONFIGURE params that give control back for `device`.
pub fn release_params(device: u8) -> [f32; 7] {
    use crate::mission::plan::{GIMBAL_CONTROL_RELEASE, GIMBAL_CONTROL_UNCHANGED};
    [
        GIMBAL_CONTROL_RELEASE,
        GIMBAL_CONTROL_RELEASE,
        GIMBAL_CONTROL_UNCHANGED,
        GIMBAL_CONTROL_UNCHANGED,
        0.0,
        0.0,
        f32::from(device),
    ]
}
