//! The vehicle side of the API over the MAVLink link actor: status (with
//! the georeference), a localised shot's camera pose turned into a vehicle
//! target through the georeference, planned, uploaded and read back.

use std::sync::Arc;
use std::time::Duration;

use serde_json::json;

use tokio_util::sync::CancellationToken;

use super::geo_service::GeoService;
use crate::api::{
    AlignmentView, BoxFuture, GimbalManagerView, MissionProgressView, ShotTarget, StopOutcome,
    TargetView, VehicleError, VehicleGimbal, VehicleMissionView, VehiclePosition, VehicleStatus,
    VehicleView,
};
use crate::geo::{GeoAlignment, GeoError, GeoTarget};
use crate::mission::MissionItem;
use crate::mission::plan::{Flavour, Home, plan};
use crate::shot::reconcile::{VehicleMission, reconcile};
use crate::shot::record::{MissionRecord, MissionState, PoseJson, Shot};
use crate::shot::store::ShotStore;
use crate::vehicle::{LinkError, LinkHandle};
use crate::video::live::unix_now;

/// [`VehicleView`] over a [`LinkHandle`] and the daemon's georeference.
pub struct LinkVehicle {
    link: LinkHandle,
    plan: crate::mission::plan::Params,
    geo: Arc<GeoService>,
    refine: Option<super::refinement_task::RefineHandle>,
    /// The shot last uploaded and the target its mission flies.
    last_uploaded: std::sync::Mutex<Option<(Shot, crate::mission::plan::Target)>>,
    /// The shot whose mission the vehicle holds, as far as we know: the
    /// one uploaded last, or the one the last reconciliation found on the
    /// vehicle (None: another station's mission, or none). Photos the
    /// camera reports are stored with it.
    mission_owner: std::sync::Mutex<Option<String>>,
    /// The shot whose mission was started last.
    last_started: std::sync::Mutex<Option<String>>,
}

fn target_view(t: &GeoTarget) -> TargetView {
    TargetView {
        lat_deg: t.lat_deg,
        lon_deg: t.lon_deg,
        alt_above_home_m: t.alt_above_home_m,
        alt_m: t.alt_m,
        yaw_deg: t.yaw_deg,
        gimbal_pitch_deg: t.gimbal_pitch_deg,
        residual_roll_deg: t.residual_roll_deg,
        axis_error_deg: t.axis_error_deg,
        p_ned_vehicle: [t.p_ned_vehicle.x, t.p_ned_vehicle.y, t.p_ned_vehicle.z],
        camera_ned: PoseJson::from_isometry(&t.ned_from_cam),
    }
}

fn alignment_view(a: &GeoAlignment) -> AlignmentView {
    AlignmentView {
        scale: a.ned_from_map.scale,
        rms_m: a.quality.rms_m,
        keyframes_used: a.quality.inliers,
        pairs: a.quality.pairs,
        time_offset_s: a.quality.time_offset_s,
    }
}

/// The target `shot`'s mission flies, when the vehicle holds that
/// mission: `last` is the shot whose mission was uploaded last (or found
/// on the vehicle by reconciliation) with its target. Starting another
/// shot's mission would fly (and refine) the wrong shot.
fn mission_to_start(
    last: Option<&(Shot, crate::mission::plan::Target)>,
    shot: &Shot,
) -> Result<crate::mission::plan::Target, VehicleError> {
    match last {
        Some((s, target)) if s.id == shot.id => Ok(*target),
        _ => Err(VehicleError::NotOnVehicle {
            shot: shot.id.clone(),
            holder: last.map(|(s, _)| s.id.clone()),
        }),
    }
}

impl LinkVehicle {
    /// A view over `link`, planning with `plan`, georeferencing with `geo`.
    pub fn new(link: LinkHandle, plan: crate::mission::plan::Params, geo: Arc<GeoService>) -> Self {
        Self {
            link,
            plan,
            geo,
            refine: None,
            last_uploaded: std::sync::Mutex::new(None),
            mission_owner: std::sync::Mutex::new(None),
            last_started: std::sync::Mutex::new(None),
        }
    }

    /// Starting a mission also starts the refinement loop of the shot last
    /// uploaded; uploading another shot stops the running loop.
    pub fn with_refine(mut self, refine: super::refinement_task::RefineHandle) -> Self {
        self.refine = Some(refine);
        self
    }

    /// The shot's target camera pose as a vehicle target.
    fn target_of(&self, shot: &Shot) -> Result<(GeoTarget, GeoAlignment), VehicleError> {
        let Some(loc) = &shot.localisation else {
            return Err(VehicleError::Conflict {
                reason: format!("shot {} is not localised", shot.id),
            });
        };
        let Some(map_from_cam) = loc.world_from_cam.to_isometry() else {
            return Err(VehicleError::Conflict {
                reason: format!("shot {} has an invalid pose", shot.id),
            });
        };
        self.geo.target(&map_from_cam).map_err(|e| match e {
            GeoError::PitchOutOfRange { .. } | GeoError::NonFinite { .. } => {
                VehicleError::Conflict {
                    reason: format!("the target cannot be reproduced: {e}"),
                }
            }
            e => VehicleError::NoGeoreference {
                reason: e.to_string(),
            },
        })
    }

    /// Reads the vehicle's mission (three tries) and the progress reported
    /// since `since`, waiting up to two seconds for a fresh one.
    async fn read_vehicle_mission(
        &self,
        since: tokio::time::Instant,
    ) -> Result<VehicleMission, LinkError> {
        let mut last_err = None;
        let mut items = None;
        for attempt in 0..3 {
            match self.link.download_mission().await {
                Ok(d) => {
                    items = Some(d.items);
                    break;
                }
                Err(e) => {
                    tracing::warn!(attempt, "reconcile: mission download failed: {e}");
                    last_err = Some(e);
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
            }
        }
        let Some(items) = items else {
            return Err(last_err.unwrap_or(LinkError::NoVehicle));
        };
        let mut rx = self.link.telemetry.progress.clone();
        let fresh = |p: &Option<crate::vehicle::Stamped<crate::vehicle::MissionProgress>>| {
            p.filter(|p| tokio::time::Instant::from_std(p.received) >= since)
                .map(|p| p.value)
        };
        let mut progress = fresh(&rx.borrow_and_update());
        let deadline = tokio::time::Instant::now() + Duration::from_secs(2);
        while progress.is_none() {
            match tokio::time::timeout_at(deadline, rx.changed()).await {
                Ok(Ok(())) => progress = fresh(&rx.borrow_and_update()),
                _ => break,
            }
        }
        let skip_home = self.link.telemetry.vehicle.borrow().flavour == Some(Flavour::ArduPilot);
        Ok(VehicleMission {
            items,
            progress,
            skip_home,
        })
    }

    /// Sets every stored shot's mission state from the vehicle's mission
    /// (see [`super::reconcile`]); the shot whose mission the vehicle holds
    /// becomes the one that `start` refines. Returns the shots changed.
    pub async fn reconcile_shots(
        &self,
        store: &ShotStore,
        since: tokio::time::Instant,
    ) -> Vec<Shot> {
        let vehicle = self.read_vehicle_mission(since).await;
        let vehicle_read = vehicle.is_ok();
        let shots = store.list();
        let home = self.geo.home().map(|h| Home {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_amsl_m: h.alt_amsl_m,
        });
        let flavour = self.link.telemetry.vehicle.borrow().flavour;
        let replanned = |s: &Shot| -> Vec<Vec<MissionItem>> {
            match (
                s.mission.as_ref().and_then(MissionRecord::flown_target),
                home,
                flavour,
            ) {
                (Some(t), Some(h), Some(f)) => {
                    plan(&t, &h, f, &self.plan).ok().into_iter().collect()
                }
                _ => Vec::new(),
            }
        };
        let (changed, owner) = reconcile(&shots, &vehicle, replanned, unix_now());
        for s in &changed {
            let m = s.mission.as_ref();
            tracing::info!(
                shot = %s.id,
                state = m.map(|m| m.state.as_str()),
                reason = m
                    .and_then(|m| m.details["vehicle"]["reason"].as_str()),
                "reconciled with the vehicle's mission"
            );
            // Only the reconciled part (state and `details.vehicle`) goes
            // into the record as it is now: a refinement loop may have
            // written its rounds since the list was read.
            let (state, vehicle_detail) = match m {
                Some(m) => (m.state, m.details.get("vehicle").cloned()),
                None => continue,
            };
            let apply = |cur: &mut Shot| {
                if let Some(cm) = cur.mission.as_mut() {
                    cm.state = state;
                    if let Some(v) = vehicle_detail {
                        cm.set_detail("vehicle", v);
                    }
                }
            };
            if let Err(e) = store.update(&s.id, apply) {
                tracing::warn!(shot = %s.id, "reconcile: saving the shot: {e}");
            }
        }
        if vehicle_read && let Ok(mut o) = self.mission_owner.lock() {
            *o = owner.clone();
        }
        if let Some(id) = owner
            && let Some(shot) = store.get(&id)
            && let Some(t) = shot.mission.as_ref().and_then(MissionRecord::flown_target)
            && let Ok(mut last) = self.last_uploaded.lock()
            && last.as_ref().is_none_or(|(s, _)| s.id != id)
        {
            *last = Some((shot, t));
        }
        changed
    }

    fn heard(&self) -> Result<(), VehicleError> {
        let v = self.link.telemetry.vehicle.borrow();
        if !v.connected || v.link_lost || v.system_id.is_none() {
            return Err(VehicleError::NoVehicle {
                reason: if v.connected {
                    "no heartbeat from the vehicle".into()
                } else {
                    "the link is not open".into()
                },
            });
        }
        Ok(())
    }
}

/// Reconciles the stored shots with the vehicle's mission each time the
/// vehicle is heard after not being heard (the first heartbeat after
/// start, and after every link loss) and each time another ground station
/// on a forward endpoint stored or cleared a mission, until `cancel`.
pub async fn run_reconciler(
    vehicle: Arc<LinkVehicle>,
    store: Arc<ShotStore>,
    actions: Arc<tokio::sync::Mutex<()>>,
    cancel: CancellationToken,
) {
    let mut rx = vehicle.link.telemetry.vehicle.clone();
    let mut changes = vehicle.link.telemetry.mission_changes.clone();
    changes.borrow_and_update();
    let mut was_heard = false;
    let mut foreign_change = false;
    loop {
        let heard = {
            let v = rx.borrow_and_update();
            v.connected && !v.link_lost && v.system_id.is_some()
        };
        if heard && (!was_heard || foreign_change) {
            let since = tokio::time::Instant::now();
            if foreign_change {
                tracing::info!(
                    "another ground station changed the vehicle's mission: reconciling the shots' missions with it"
                );
            } else {
                tracing::info!("vehicle heard: reconciling the shots' missions with it");
            }
            let _guard = actions.lock().await;
            tokio::select! {
                _ = cancel.cancelled() => break,
                _ = vehicle.reconcile_shots(&store, since) => {}
            }
        }
        was_heard = heard;
        foreign_change = false;
        tokio::select! {
            _ = cancel.cancelled() => break,
            r = rx.changed() => if r.is_err() { break },
            r = changes.changed() => match r {
                Ok(()) => {
                    changes.borrow_and_update();
                    foreign_change = true;
                }
                Err(_) => break,
            },
        }
    }
}

/// Stores every picture the vehicle's camera reports (CAMERA_IMAGE_CAPTURED)
/// with the shot whose mission the vehicle holds (the one uploaded last, or
/// the one the last reconciliation found there), until `cancel`.
pub async fn run_photo_recorder(
    vehicle: Arc<LinkVehicle>,
    store: Arc<ShotStore>,
    cancel: CancellationToken,
) {
    let mut rx = vehicle.link.telemetry.captures.clone();
    let mut seen: Vec<(u8, i32)> = rx
        .borrow_and_update()
        .iter()
        .map(|c| (c.component_id, c.index))
        .collect();
    loop {
        tokio::select! {
            _ = cancel.cancelled() => break,
            r = rx.changed() => if r.is_err() { break },
        }
        let fresh: Vec<crate::vehicle::ImageCaptured> = rx
            .borrow_and_update()
            .iter()
            .filter(|c| !seen.contains(&(c.component_id, c.index)))
            .cloned()
            .collect();
        let owner = vehicle.mission_owner.lock().ok().and_then(|o| o.clone());
        for photo in fresh {
            seen.push((photo.component_id, photo.index));
            if seen.len() > 4 * crate::vehicle::CAPTURES_KEPT {
                seen.remove(0);
            }
            match &owner {
                Some(id) => {
                    tracing::info!(shot = %id, index = photo.index, ok = photo.ok, url = %photo.file_url, "photo stored with the shot");
                    if let Err(e) = store.update(id, |s| {
                        if let Some(m) = s.mission.as_mut() {
                            m.record_photo(&photo);
                        }
                    }) {
                        tracing::warn!(shot = %id, "storing the photo: {e}");
                    }
                }
                None => tracing::info!(
                    index = photo.index,
                    url = %photo.file_url,
                    "a photo was taken with no shot's mission uploaded: not stored"
                ),
            }
        }
    }
}

impl VehicleView for LinkVehicle {
    fn status(&self) -> VehicleStatus {
        let v = self.link.telemetry.vehicle.borrow().clone();
        let gp = *self.link.telemetry.global_position.borrow();
        let manager = *self.link.telemetry.gimbal_manager.borrow();
        let control = self.link.telemetry.gimbal_control.borrow().clone();
        VehicleStatus {
            configured: true,
            connected: v.connected && !v.link_lost,
            transport_open: v.connected,
            connections: v.connections,
            system_id: v.system_id,
            flavour: v.flavour.map(|f| format!("{f:?}")),
            mode: v.mode,
            armed: v.armed,
            last_heartbeat_age_s: v
                .last_heartbeat
                .map(|t| crate::clock::since(t).as_secs_f64()),
            position: gp.map(|p| VehiclePosition {
                lat_deg: p.value.lat_deg,
                lon_deg: p.value.lon_deg,
                rel_alt_m: p.value.rel_alt_m,
                heading_deg: p.value.heading_deg,
                ned_m: self.geo.home().map(|h| {
                    let frame = crate::geo::LocalFrame::new(crate::geo::Geodetic {
                        lat_deg: h.lat_deg,
                        lon_deg: h.lon_deg,
                        alt_m: h.alt_amsl_m,
                    });
                    let n = frame.geodetic_to_ned(&crate::geo::Geodetic {
                        lat_deg: p.value.lat_deg,
                        lon_deg: p.value.lon_deg,
                        alt_m: p.value.alt_amsl_m,
                    });
                    [n.x, n.y, n.z]
                }),
            }),
            fence: Some(self.plan.fence),
            forward: self.link.forward_status(),
            georeference: Some(self.geo.status()),
            gimbal: VehicleGimbal {
                manager: manager.map(|m| GimbalManagerView {
                    gimbal_device_id: m.value.gimbal_device_id,
                    primary: [m.value.primary.0, m.value.primary.1],
                    secondary: [m.value.secondary.0, m.value.secondary.1],
                    age_s: crate::clock::since(m.received).as_secs_f64(),
                }),
                control,
            },
        }
    }

    fn upload_shot<'a>(
        &'a self,
        shot: &'a Shot,
    ) -> BoxFuture<'a, Result<MissionRecord, VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            let (target, alignment) = self.target_of(shot)?;
            let flavour = self
                .link
                .telemetry
                .vehicle
                .borrow()
                .flavour
                .ok_or_else(|| VehicleError::Failed {
                    reason: "the autopilot is neither PX4 nor ArduPilot".into(),
                })?;
            let home = self
                .geo
                .home()
                .ok_or_else(|| VehicleError::NoGeoreference {
                    reason: "home position not known yet".into(),
                })?;
            let home = Home {
                lat_deg: home.lat_deg,
                lon_deg: home.lon_deg,
                alt_amsl_m: home.alt_amsl_m,
            };
            let flown = target.to_mission_target(true);
            let items =
                plan(&flown, &home, flavour, &self.plan).map_err(|e| VehicleError::Conflict {
                    reason: format!("the target cannot be flown: {e}"),
                })?;
            // A new mission replaces the one a refinement loop is flying.
            if let Some(r) = &self.refine {
                r.uploading(shot.clone());
            }
            let (report, verified) =
                self.link
                    .upload_verified(&items, flavour)
                    .await
                    .map_err(|e| VehicleError::Failed {
                        reason: e.to_string(),
                    })?;
            if let Ok(mut last) = self.last_uploaded.lock() {
                *last = Some((shot.clone(), flown));
            }
            if let Ok(mut o) = self.mission_owner.lock() {
                *o = Some(shot.id.clone());
            }
            tracing::info!(
                shot = %shot.id,
                lat = target.lat_deg,
                lon = target.lon_deg,
                alt_above_home_m = target.alt_above_home_m,
                yaw_deg = target.yaw_deg,
                pitch_deg = target.gimbal_pitch_deg,
                items = items.len(),
                "mission uploaded"
            );
            Ok(MissionRecord {
                state: MissionState::Uploaded,
                items: items.len(),
                uploaded_unix: unix_now(),
                started_unix: None,
                target_lat_lon_alt: Some([target.lat_deg, target.lon_deg, target.alt_m]),
                details: json!({
                    "target": target_view(&target),
                    "georeference": alignment_view(&alignment),
                    "flavour": flavour,
                    "planned_items": items,
                    "upload": report,
                    "verified_by_read_back": verified,
                }),
            })
        })
    }

    fn shot_target(&self, shot: &Shot) -> Result<ShotTarget, VehicleError> {
        let (target, alignment) = self.target_of(shot)?;
        let position_sigma_m = shot
            .localisation
            .as_ref()
            .and_then(|l| l.sigma.as_ref())
            .map(|s| s.position * alignment.ned_from_map.scale);
        Ok(ShotTarget {
            shot: shot.id.clone(),
            target: target_view(&target),
            georeference: alignment_view(&alignment),
            position_sigma_m,
        })
    }

    fn download_mission(&self) -> BoxFuture<'_, Result<VehicleMissionView, VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            let d = self
                .link
                .download_mission()
                .await
                .map_err(|e| VehicleError::Failed {
                    reason: e.to_string(),
                })?;
            Ok(VehicleMissionView {
                count: d.items.len(),
                items: d.items,
                retries: d.retries,
                seconds: d.seconds,
            })
        })
    }

    fn start_mission<'a>(&'a self, shot: &'a Shot) -> BoxFuture<'a, Result<(), VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            let last = self.last_uploaded.lock().ok().and_then(|l| l.clone());
            let flown = mission_to_start(last.as_ref(), shot)?;
            self.link
                .start_mission()
                .await
                .map_err(|e| VehicleError::Failed {
                    reason: e.to_string(),
                })?;
            if let Ok(mut s) = self.last_started.lock() {
                *s = Some(shot.id.clone());
            }
            if let Some(r) = &self.refine {
                r.start(shot.clone(), flown);
            }
            Ok(())
        })
    }

    fn stop<'a>(&'a self, reason: &'a str) -> BoxFuture<'a, Result<StopOutcome, VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            // The loop first: it must not upload or start a correction
            // after the vehicle holds.
            let refinement_cancelled = match &self.refine {
                Some(r) => r.halt(reason.to_owned()).await,
                None => None,
            };
            let ack = self.link.hold().await.map_err(|e| VehicleError::Failed {
                reason: format!("the vehicle did not hold: {e}"),
            })?;
            let flying = self.last_started.lock().ok().and_then(|s| s.clone());
            tracing::info!(
                refined = ?refinement_cancelled,
                shot = ?flying,
                mode = %ack.mode,
                "vehicle holds (operator's stop)"
            );
            Ok(StopOutcome {
                ack,
                refinement_cancelled,
                flying,
            })
        })
    }

    fn progress(&self) -> Option<MissionProgressView> {
        let p = (*self.link.telemetry.progress.borrow())?;
        Some(MissionProgressView {
            current_seq: p.value.current_seq,
            total: p.value.total,
            state: p.value.state,
            last_reached: p.value.last_reached,
            age_s: crate::clock::since(p.received).as_secs_f64(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mission::plan::Target;
    use crate::shot::record::{ShotSource, ShotStatus};

    fn shot(id: &str) -> Shot {
        Shot {
            id: id.into(),
            created_unix: 0.0,
            source: ShotSource::Anchors {
                keyframe_id: 1,
                anchors: [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
            },
            status: ShotStatus::Localised,
            localisation: None,
            reason: None,
            nearest_keyframes: Vec::new(),
            has_image: false,
            mission: None,
        }
    }

    fn target(lat: f64) -> Target {
        Target {
            lat_deg: lat,
            lon_deg: 8.0,
            alt_m: 20.0,
            yaw_deg: 90.0,
            gimbal_pitch_deg: -30.0,
            photo: true,
        }
    }

    /// `start` flies and refines the shot asked for, never the one
    /// uploaded last whatever the id.
    #[test]
    fn start_refines_the_shot_asked_for_or_refuses() {
        let last = (shot("shot-2"), target(47.2));
        let t = mission_to_start(Some(&last), &shot("shot-2")).unwrap();
        assert_eq!(t.lat_deg, 47.2);
        match mission_to_start(Some(&last), &shot("shot-1")) {
            Err(VehicleError::NotOnVehicle { shot, holder }) => {
                assert_eq!(shot, "shot-1");
                assert_eq!(holder.as_deref(), Some("shot-2"));
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            mission_to_start(None, &shot("shot-1")),
            Err(VehicleError::NotOnVehicle { holder: None, .. })
        ));
    }
}
