//! The vehicle side of the API over the MAVLink link actor.

use serde_json::{Value, json};

use crate::api::store::{MissionRecord, Shot};
use crate::api::{BoxFuture, VehicleError, VehicleView};
use crate::vehicle::LinkHandle;

/// [`VehicleView`] over a [`LinkHandle`].
pub struct LinkVehicle {
    link: LinkHandle,
    _plan: crate::mission::plan::Params,
}

impl LinkVehicle {
    /// A view over `link`, planning with `plan`.
    pub fn new(link: LinkHandle, plan: crate::mission::plan::Params) -> Self {
        Self { link, _plan: plan }
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

impl VehicleView for LinkVehicle {
    fn status(&self) -> Value {
        let v = self.link.telemetry.vehicle.borrow().clone();
        let gp = *self.link.telemetry.global_position.borrow();
        json!({
            "configured": true,
            "connected": v.connected && !v.link_lost,
            "transport_open": v.connected,
            "connections": v.connections,
            "system_id": v.system_id,
            "flavour": v.flavour.map(|f| format!("{f:?}")),
            "mode": v.mode,
            "armed": v.armed,
            "last_heartbeat_age_s": v.last_heartbeat.map(|t| t.elapsed().as_secs_f64()),
            "position": gp.map(|p| json!({
                "lat_deg": p.value.lat_deg,
                "lon_deg": p.value.lon_deg,
                "rel_alt_m": p.value.rel_alt_m,
                "heading_deg": p.value.heading_deg,
            })),
            "georeference": null,
        })
    }

    fn upload_shot<'a>(
        &'a self,
        _shot: &'a Shot,
    ) -> BoxFuture<'a, Result<MissionRecord, VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            // The target pose is in the SLAM map frame; turning it into
            // latitude/longitude needs the map->NED->WGS84 alignment
            // (crate::geo), which this build does not have yet.
            Err(VehicleError::NoGeoreference {
                reason:
                    "the map is not aligned to the world (georeference module not in this build)"
                        .into(),
            })
        })
    }

    fn start_mission(&self) -> BoxFuture<'_, Result<(), VehicleError>> {
        Box::pin(async move {
            self.heard()?;
            self.link
                .start_mission()
                .await
                .map_err(|e| VehicleError::Failed {
                    reason: e.to_string(),
                })
        })
    }

    fn progress(&self) -> Value {
        let p = *self.link.telemetry.progress.borrow();
        match p {
            Some(p) => json!({
                "current_seq": p.value.current_seq,
                "total": p.value.total,
                "state": p.value.state,
                "last_reached": p.value.last_reached,
                "age_s": p.received.elapsed().as_secs_f64(),
            }),
            None => Value::Null,
        }
    }
}
