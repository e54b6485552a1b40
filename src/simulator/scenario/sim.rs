//! The simulated world stepped in simulated time: the autopilot, its
//! telemetry as the daemon sees it (to the georeference and the SLAM's
//! priors feed, with frame losses), the live camera (GPS bias and mounting
//! errors included), the mission upload through the daemon's state machine
//! in-process.

use std::time::Instant;

use image::GrayImage;
use mavlink::MavHeader;
use mavlink::dialects::common::{MavMessage, MavMissionType};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use rand::{Rng, rngs::SmallRng};

use shotpilot_sim::autopilot::Autopilot;
use shotpilot_sim::imaging::Imager;
use shotpilot_sim::live::{LIVE_EXPOSURE_LAG_S, PoseHistory};
use shotpilot_sim::render::Renderer;

use crate::geo::{self, Geodetic, GimbalAngles, MountParams};
use crate::mission::plan::{self, Home, MissionItem};
use crate::mission::upload::{self, Peers, Uploader};
use crate::slam::priors::{TelemetryFeed, TelemetrySample};

use super::error::FlightError;
use super::params::Disturbances;

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

/// The simulated world, its autopilot and the telemetry the daemon sees.
pub(super) struct Sim {
    pub(super) ap: Autopilot,
    pub(super) renderer: Renderer,
    pub(super) t: f64,
    pub(super) dt: f64,
    pub(super) k: u64,
    pub(super) noise_seed: u64,
    pub(super) sensor_noise: bool,
    /// Most recent MISSION_ITEM_REACHED seq since the last upload.
    pub(super) reached: Option<u16>,
    pub(super) home: Home,
    pub(super) fence: plan::Fence,
    pub(super) fence_ok: bool,
    pub(super) disturb: Disturbances,
    /// The realistic camera (None: the plain renderer).
    pub(super) imager: Option<Imager>,
    /// The true camera poses of the last steps (for `imager`).
    pub(super) history: PoseHistory,
    /// Telemetry frame loss: probability and its dice.
    pub(super) telemetry_drop: Option<(f64, SmallRng)>,
    /// The telemetry priors' feed, filled as the daemon's georeference
    /// worker fills it (None: vision only).
    pub(super) priors: Option<PriorTap>,
    /// The georeference kept after the explore flight, fed every step's
    /// telemetry as the daemon's is (None: the explore's fit stands).
    pub(super) geo: Option<geo::Geo>,
}

/// What the priors' feed is filled from: each position report as the
/// camera's position with the latest attitude and GPS_RAW_INT.
pub(super) struct PriorTap {
    pub(super) feed: TelemetryFeed,
    pub(super) mount: MountParams,
    pub(super) attitude: Option<nalgebra::UnitQuaternion<f64>>,
    /// The latest GPS_RAW_INT.
    pub(super) gps: Option<crate::vehicle::GpsRaw>,
}

impl Sim {
    /// One simulation step; telemetry goes to `geo` when given.
    pub(super) fn step(&mut self, geo: Option<&mut geo::Geo>) {
        self.k += 1;
        self.t = self.k as f64 * self.dt;
        let mut out = self.ap.step(self.t, self.dt);
        let _ = self.ap.take_capture_requests();
        if self.imager.is_some() {
            let wfc = self.misaligned(&self.ap.vehicle().true_world_from_cam_stabilised());
            self.history.push(self.t, wfc);
        }
        if let Some((p, rng)) = &mut self.telemetry_drop {
            // The radio loses whole frames of the telemetry streams.
            out.retain(|m| {
                !matches!(
                    m,
                    MavMessage::GLOBAL_POSITION_INT(_)
                        | MavMessage::ATTITUDE(_)
                        | MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(_)
                ) || rng.random::<f64>() >= *p
            });
        }
        let mut geo = geo;
        for m in &out {
            match m {
                MavMessage::MISSION_ITEM_REACHED(r) => self.reached = Some(r.seq),
                MavMessage::GLOBAL_POSITION_INT(d) => {
                    if let Some(g) = geo.as_deref_mut() {
                        let t = f64::from(d.time_boot_ms) / 1e3;
                        let p = Geodetic {
                            lat_deg: f64::from(d.lat) / 1e7,
                            lon_deg: f64::from(d.lon) / 1e7,
                            alt_m: f64::from(d.alt) / 1e3,
                        };
                        let _ = g.push_position_geodetic(t, &p);
                        if let Some(tap) = &self.priors
                            && let (Some(frame), Some(q)) = (g.frame(), tap.attitude)
                        {
                            tap.feed.push(TelemetrySample::from_position_report(
                                t,
                                frame.geodetic_to_ned(&p),
                                q,
                                &tap.mount,
                                tap.gps.and_then(|r| r.fix_accuracy()),
                            ));
                        }
                    }
                }
                MavMessage::GPS_RAW_INT(d) => {
                    if let Some(tap) = &mut self.priors {
                        tap.gps = Some(crate::vehicle::GpsRaw::from_message(d));
                    }
                }
                MavMessage::ATTITUDE(d) => {
                    if let Some(tap) = &mut self.priors {
                        tap.attitude = Some(nalgebra::UnitQuaternion::from_euler_angles(
                            f64::from(d.roll),
                            f64::from(d.pitch),
                            f64::from(d.yaw),
                        ));
                    }
                    if let Some(g) = geo.as_deref_mut() {
                        let _ = g.history_mut().push_attitude_euler(
                            f64::from(d.time_boot_ms) / 1e3,
                            f64::from(d.roll),
                            f64::from(d.pitch),
                            f64::from(d.yaw),
                        );
                    }
                }
                MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(d) => {
                    if let Some(g) = geo.as_deref_mut() {
                        let (_, pitch, yaw) = crate::vehicle::quat_to_euler_deg(d.q);
                        let _ = g.history_mut().push_gimbal(
                            f64::from(d.time_boot_ms) / 1e3,
                            GimbalAngles {
                                pitch: f64::from(pitch).to_radians(),
                                yaw: f64::from(yaw).to_radians(),
                            },
                        );
                    }
                }
                _ => {}
            }
        }
        let v = self.ap.vehicle();
        if !v.landed() {
            let p = v.true_p_ned();
            let alt = -p.z;
            if p.xy().norm() > self.fence.radius_m || alt > self.fence.max_alt_m {
                self.fence_ok = false;
            }
        }
    }

    /// The camera pose the vehicle really has (GPS bias, which the
    /// simulator's vehicle carries, and misalignment included).
    pub(super) fn true_camera(&self) -> Isometry3<f64> {
        self.misaligned(&self.ap.vehicle().true_world_from_cam())
    }

    /// `nominal` turned by the camera's mounting errors.
    fn misaligned(&self, nominal: &Isometry3<f64>) -> Isometry3<f64> {
        let d = &self.disturb;
        let rotation = UnitQuaternion::from_axis_angle(
            &Vector3::z_axis(),
            d.camera_yaw_offset_deg.to_radians(),
        ) * nominal.rotation
            // the camera's x axis points right: a negative turn about it
            // tips the optical axis towards +y, down
            * UnitQuaternion::from_axis_angle(
                &Vector3::x_axis(),
                -d.gimbal_pitch_offset_deg.to_radians(),
            );
        Isometry3::from_parts(nominal.translation, rotation)
    }

    pub(super) fn render(&mut self) -> GrayImage {
        let noise = self.sensor_noise.then(|| {
            self.noise_seed = self.noise_seed.wrapping_add(1);
            self.noise_seed
        });
        if let Some(imager) = &mut self.imager {
            // Exposed a moment back, over the true motion around then.
            let t = self.t - LIVE_EXPOSURE_LAG_S;
            let window = self.history.window(
                t - 0.12,
                t + 0.12,
                self.ap.vehicle().gimbal_error().cloned(),
            );
            match imager.capture(t, &|s| window.world_from_cam(s), noise) {
                Ok(shot) => return shot.image,
                Err(e) => tracing::warn!("realistic frame: {e}"),
            }
        }
        let wfc = self.true_camera();
        if let Some(seed) = noise {
            self.renderer.render_noisy(&wfc, seed)
        } else {
            self.renderer.render(&wfc)
        }
    }

    /// Uploads a mission through the upload state machine, in-process.
    pub(super) fn upload(
        &mut self,
        items: &[MissionItem],
    ) -> Result<upload::UploadReport, FlightError> {
        let peers = Peers {
            own_system: 255,
            own_component: 190,
            target_system: self.ap.params().system_id,
            target_component: self.ap.params().component_id,
        };
        let ap_header = MavHeader {
            system_id: u32::from(peers.target_system),
            component_id: peers.target_component,
            sequence: 0,
        };
        let mut out = Vec::new();
        let mut up = Uploader::new(
            items,
            peers,
            MavMissionType::MAV_MISSION_TYPE_MISSION,
            upload::Params::default(),
            Instant::now(),
            &mut out,
        )?;
        for _ in 0..10_000 {
            if up.is_done() {
                break;
            }
            let msgs = std::mem::take(&mut out);
            if msgs.is_empty() {
                // Nothing in flight without a lossy link; a timeout would be a bug.
                up.on_timeout(
                    Instant::now() + std::time::Duration::from_secs(3600),
                    &mut out,
                );
                continue;
            }
            for m in msgs {
                for r in self.ap.handle(&GCS, &m) {
                    up.on_message(&ap_header, &r, Instant::now(), &mut out);
                }
            }
        }
        self.reached = None;
        match up.take_outcome() {
            Some(Ok(r)) => Ok(r),
            Some(Err(e)) => Err(e.into()),
            None => Err(FlightError::UploadUnfinished),
        }
    }

    /// One step with its telemetry to the kept georeference, if any.
    pub(super) fn step_fed(&mut self) {
        let mut geo = self.geo.take();
        self.step(geo.as_mut());
        self.geo = geo;
    }

    /// Lets `seconds` of simulated time pass (hovering where it is).
    pub(super) fn advance(&mut self, seconds: f64) {
        let end = self.t + seconds;
        while self.t + 0.5 * self.dt < end {
            self.step_fed();
        }
    }
}
