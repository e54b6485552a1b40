//! What the API reads from the parts below it: the SLAM ([`SlamView`]) and
//! the vehicle ([`VehicleView`]), as traits the daemon implements over the
//! real parts and tests implement over their own, with the typed replies
//! they give.

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;

use image::GrayImage;
use serde::{Deserialize, Serialize};

use crate::shot::record::{MissionRecord, PoseJson, Shot};
use crate::shot::request::KeyframeImages;

/// A boxed future (the vehicle trait is object-safe).
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// SLAM status as the API reports it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SlamStatus {
    /// Whether a SLAM runs in this daemon.
    pub available: bool,
    /// `initializing`, `tracking`, `lost`, ... (`unavailable` without SLAM).
    pub state: String,
    /// Frames processed.
    pub frames: u64,
    /// Frames tracked.
    pub tracked: u64,
    /// Of the frames tracked, those posed by vision alone.
    pub posed_by_vision: u64,
    /// Those posed by the local map searched around the telemetry's
    /// prediction, with it as a prior (`[slam] aid`).
    pub posed_by_vision_telemetry: u64,
    /// Those posed by the telemetry's prediction alone (`[slam] aid`:
    /// vision found too little; no keyframe is made from them).
    pub posed_by_telemetry: u64,
    /// How the last frame was posed: `vision`, `vision+telemetry` or
    /// `telemetry` (None: not posed).
    pub last_source: Option<String>,
    /// Keyframes in the map.
    pub keyframes: usize,
    /// Map points.
    pub points: usize,
    /// Inliers of the last tracked frame.
    pub last_inliers: usize,
    /// Processing time of the last frame, ms.
    pub last_frame_ms: f64,
    /// 95th percentile of the processing time over recent frames, ms (the
    /// tracking thread keeps up while it stays below the frame interval).
    pub frame_ms_p95: Option<f64>,
    /// Median latency from capture to tracked pose over recent frames, ms.
    pub latency_ms_median: Option<f64>,
    /// 95th percentile of the same latencies, ms.
    pub latency_ms_p95: Option<f64>,
    /// Frames per second processed.
    pub fps: f64,
    /// Where the map came from at start (None before the SLAM started).
    pub map_start: Option<MapStart>,
    /// The map file last written (a checkpoint, or at shutdown).
    pub map_saved: Option<MapSaved>,
    /// The last failed write of the map file or of the georeference
    /// beside it (None: none since the last good write).
    pub map_save_error: Option<WriteFailure>,
    /// Loops closed since the SLAM started.
    pub loops_closed: u64,
    /// The latest loops closed, oldest first (at most
    /// [`SlamStatus::MAX_LOOPS`]).
    pub loops: Vec<LoopInfo>,
    /// New maps started after tracking losses since the SLAM started.
    pub maps_started: u64,
    /// Maps merged since the SLAM started.
    pub merges_made: u64,
    /// The latest merges, oldest first (at most
    /// [`SlamStatus::MAX_MERGES`]).
    pub merges: Vec<MergeInfo>,
    /// The frame the map is in: `vision_only` (its own frame and scale;
    /// the georeference is a Sim(3) fitted after the fact) or `gps_aided`
    /// (local NED at home, held by telemetry priors).
    pub map_mode: String,
    /// Why the map is in that mode (what a vision-only map waits for, how
    /// it was put in NED, or that priors are off).
    pub map_mode_reason: String,
}

impl SlamStatus {
    /// Loops the status lists at most (the count goes on).
    pub const MAX_LOOPS: usize = 20;
    /// Merges the status lists at most (the count goes on).
    pub const MAX_MERGES: usize = 20;
}

/// A map started after a tracking loss merged into an older one, as the
/// status reports it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MergeInfo {
    /// The keyframe of the new map that saw the old place.
    pub current_kf: u64,
    /// The old map's keyframe it matched.
    pub merge_kf: u64,
    /// Capture time of the current keyframe, seconds (the keyframes' clock).
    pub current_t: f64,
    /// Capture time of the old keyframe, seconds.
    pub merge_t: f64,
    /// The map merged (it no longer exists).
    pub from_map: u32,
    /// The map it joined.
    pub into_map: u32,
    /// Inliers of the Sim(3).
    pub inliers: usize,
    /// Keypoints matched by projection through the Sim(3).
    pub projection_matches: usize,
    /// Scale of the similarity (old map units per merged map unit).
    pub scale: f64,
    /// Keyframes moved into the old map.
    pub keyframes_moved: usize,
    /// Points fused.
    pub fused: usize,
    /// Time the merge took, ms.
    pub correction_ms: f64,
    /// When the daemon saw the merge, unix seconds.
    pub at_unix: f64,
}

/// A loop closed by the SLAM, as the status reports it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopInfo {
    /// The keyframe that saw an old place again.
    pub current_kf: u64,
    /// The old keyframe it matched.
    pub loop_kf: u64,
    /// Capture time of the current keyframe, seconds (the keyframes' clock).
    pub current_t: f64,
    /// Capture time of the loop keyframe, seconds.
    pub loop_t: f64,
    /// Inliers of the loop's Sim(3).
    pub inliers: usize,
    /// Keypoints matched by projection through the corrected pose.
    pub projection_matches: usize,
    /// Scale of the correction (1: no scale drift).
    pub scale: f64,
    /// Rotation of the correction, degrees.
    pub rotation_deg: f64,
    /// Points fused.
    pub fused: usize,
    /// Time the correction took, ms.
    pub correction_ms: f64,
    /// When the daemon saw the loop closed, unix seconds.
    pub at_unix: f64,
}

/// A write that failed: what, why, when. The status carries the last one
/// of each kind until a write of that kind succeeds again.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct WriteFailure {
    /// What was written: `map`, `georeference`, `shot`.
    pub what: &'static str,
    /// The error.
    pub message: String,
    /// When, unix seconds.
    pub at_unix: f64,
}

/// The last map file written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MapSaved {
    /// `checkpoint` or `shutdown`.
    pub reason: String,
    /// Keyframes in it.
    pub keyframes: usize,
    /// Map points in it.
    pub points: usize,
    /// File size, bytes.
    pub bytes: u64,
    /// Pairs in the georeference written beside it (None: none written).
    pub geo_pairs: Option<usize>,
    /// When it was written, unix seconds.
    pub at_unix: f64,
}

/// Where the SLAM's map came from when the daemon started.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct MapStart {
    /// `fresh` (no saved map, or `[slam] continue_map = false`),
    /// `continued` (the saved map was loaded and is relocalised into), or
    /// `fresh_after_error` (the saved map could not be used).
    pub mode: String,
    /// Keyframes loaded from the saved map.
    pub keyframes: usize,
    /// Points loaded from the saved map.
    pub points: usize,
    /// The first frame (ingest sequence number) tracked in the loaded map.
    pub relocalised_at_frame: Option<u64>,
    /// Why the saved map was not used.
    pub error: Option<String>,
    /// Where a saved map that was not continued was moved to.
    pub set_aside: Option<std::path::PathBuf>,
}

/// A keyframe in the API.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeInfo {
    /// Id.
    pub id: u64,
    /// Timestamp, seconds.
    pub timestamp: f64,
    /// Pose.
    pub world_from_cam: PoseJson,
    /// Image width and height, pixels (0 when no image is kept).
    pub width: u32,
    /// See `width`.
    pub height: u32,
}

/// The newest tracked frame, placed relative to its reference keyframe (so
/// that it moves with it when bundle adjustment moves the keyframe): the
/// georeference pairs such frames with telemetry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedFrame {
    /// Ingest sequence number.
    pub seq: u64,
    /// Capture time, seconds (the keyframes' clock).
    pub timestamp: f64,
    /// The reference keyframe.
    pub reference_kf: u64,
    /// `cam ← ref_cam`: the frame's camera relative to the reference
    /// keyframe's.
    pub cam_from_ref: nalgebra::Isometry3<f64>,
}

/// The map for the top view.
#[derive(Debug, Clone, Default, Serialize)]
pub struct MapView {
    /// Points (decimated), map frame.
    pub points: Vec<[f32; 3]>,
    /// Points in the map before decimation.
    pub total_points: usize,
    /// Keyframe camera centres, in id order.
    pub trajectory: Vec<[f64; 3]>,
}

impl<T: SlamView + ?Sized> KeyframeImages for Arc<T> {
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        SlamView::keyframe_image(self.as_ref(), id)
    }
}

/// What the API reads from the SLAM.
pub trait SlamView: Send + Sync {
    /// The status.
    fn status(&self) -> SlamStatus;
    /// The keyframes, in id order.
    fn keyframes(&self) -> Vec<KeyframeInfo>;
    /// A keyframe's image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
    /// The map, with at most `max_points` points.
    fn map(&self, max_points: usize) -> MapView;
    /// The newest tracked frame (None: none yet, or no SLAM).
    fn last_tracked(&self) -> Option<TrackedFrame> {
        None
    }
    /// The keypoints of frame `seq` (None: the newest processed), while
    /// it is among the few recent frames kept (None: not kept, or no SLAM).
    fn features(&self, _seq: Option<u64>) -> Option<Arc<super::features::TrackedFeatures>> {
        None
    }
}

/// Errors of vehicle actions, each with its HTTP status.
#[derive(Debug, Clone, thiserror::Error)]
pub enum VehicleError {
    /// No vehicle link, or the vehicle is not heard.
    #[error("no vehicle: {reason}")]
    NoVehicle {
        /// Why.
        reason: String,
    },
    /// The map is not tied to the world yet.
    #[error("no georeference yet: {reason}")]
    NoGeoreference {
        /// Why.
        reason: String,
    },
    /// The action does not fit the shot's state.
    #[error("{reason}")]
    Conflict {
        /// Why.
        reason: String,
    },
    /// The vehicle holds another shot's mission (or none this daemon
    /// knows of): the shot's mission must be uploaded again first.
    #[error(
        "the vehicle does not hold shot {shot}'s mission ({}): upload it again",
        holder.as_deref().map_or("it holds none this daemon uploaded".to_owned(), |h| format!("it holds shot {h}'s"))
    )]
    NotOnVehicle {
        /// The shot asked for.
        shot: String,
        /// The shot whose mission the vehicle holds, if one does.
        holder: Option<String>,
    },
    /// The vehicle refused or the transfer failed.
    #[error("vehicle: {reason}")]
    Failed {
        /// Why.
        reason: String,
    },
}

/// The vehicle as `GET /status` reports it (under `vehicle`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct VehicleStatus {
    /// A link is configured (always true here; without one the status
    /// says `{"configured": false}` alone).
    pub configured: bool,
    /// The vehicle is heard (transport open, heartbeats arriving).
    pub connected: bool,
    /// The transport is open.
    pub transport_open: bool,
    /// Times the transport was (re)opened.
    pub connections: u32,
    /// The vehicle's MAVLink system id, once heard.
    pub system_id: Option<u8>,
    /// `PX4` or `ArduPilot`, once heard.
    pub flavour: Option<String>,
    /// Flight mode name.
    pub mode: String,
    /// Armed.
    pub armed: bool,
    /// Age of the last heartbeat, seconds.
    pub last_heartbeat_age_s: Option<f64>,
    /// The last global position, when one came.
    pub position: Option<VehiclePosition>,
    /// The georeference's state and evidence (the daemon's geo service
    /// report; None before the vehicle's view is made).
    pub georeference: Option<crate::geo::GeoreferenceStatus>,
    /// Gimbal protocol v2: the manager's last status and what the link did
    /// about control.
    pub gimbal: VehicleGimbal,
    /// The geofence every target must lie in (circle around home,
    /// altitude band).
    pub fence: Option<crate::mission::plan::Fence>,
    /// The forward endpoints other ground stations share the link through.
    pub forward: Vec<crate::vehicle::router::ForwardStatus>,
}

/// The gimbal part of the vehicle status.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct VehicleGimbal {
    /// The gimbal manager's last GIMBAL_MANAGER_STATUS, when one came.
    pub manager: Option<GimbalManagerView>,
    /// What the link did about gimbal control.
    pub control: crate::vehicle::GimbalControl,
}

/// A gimbal manager's status as the API shows it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GimbalManagerView {
    /// The gimbal device the manager is responsible for.
    pub gimbal_device_id: u8,
    /// (system, component) in primary control; [0, 0] nobody.
    pub primary: [u8; 2],
    /// (system, component) in secondary control; [0, 0] nobody.
    pub secondary: [u8; 2],
    /// Age of the status, seconds.
    pub age_s: f64,
}

/// The vehicle's position in the status.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct VehiclePosition {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above home, metres.
    pub rel_alt_m: f64,
    /// Heading, degrees (None when unknown).
    pub heading_deg: Option<f32>,
    /// North, east, down from home, metres (WGS84 local NED at home; None
    /// before home is known). The page's map draws the vehicle here.
    pub ned_m: Option<[f64; 3]>,
}

/// Mission progress as the vehicle last reported it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct MissionProgressView {
    /// The item being executed.
    pub current_seq: Option<u16>,
    /// Items in the mission.
    pub total: Option<u16>,
    /// MAV_MISSION_STATE number (2 not started, 3 active, 4 paused, 5
    /// complete).
    pub state: Option<u8>,
    /// The last item reached.
    pub last_reached: Option<u16>,
    /// Age of the report, seconds.
    pub age_s: f64,
}

/// A localised shot's vehicle target (`GET /shots/{id}/target`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShotTarget {
    /// The shot.
    pub shot: String,
    /// Where the vehicle goes and how it points the camera.
    pub target: TargetView,
    /// The georeference it was computed with.
    pub georeference: AlignmentView,
    /// The shot's position sigma in metres (its sigma in map units times
    /// the georeference's scale); None when the shot reports no sigma.
    pub position_sigma_m: Option<f64>,
}

/// A vehicle target: position, yaw, gimbal pitch, and what the vehicle
/// cannot reproduce of the camera pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TargetView {
    /// Latitude, degrees (WGS84).
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above home, metres.
    pub alt_above_home_m: f64,
    /// Altitude above mean sea level, metres.
    pub alt_m: f64,
    /// Vehicle heading, degrees clockwise from north.
    pub yaw_deg: f64,
    /// Gimbal pitch, degrees (negative looks down).
    pub gimbal_pitch_deg: f64,
    /// Camera roll the vehicle cannot reproduce, degrees.
    pub residual_roll_deg: f64,
    /// Angle between the wanted and the reproduced optical axis, degrees.
    pub axis_error_deg: f64,
    /// Vehicle position, local NED at home, metres.
    pub p_ned_vehicle: [f64; 3],
    /// The target camera pose in local NED (`ned_from_cam`).
    pub camera_ned: PoseJson,
}

/// The georeference a target was computed with.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AlignmentView {
    /// Metres per map unit.
    pub scale: f64,
    /// RMS residual of the fit, metres.
    pub rms_m: f64,
    /// Keyframes (pairs) the fit kept.
    pub keyframes_used: usize,
    /// Pairs offered to the fit.
    pub pairs: usize,
    /// Video-to-telemetry time offset found, seconds (None: not fitted).
    pub time_offset_s: Option<f64>,
}

/// The mission the vehicle holds, read back (`GET /vehicle/mission`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VehicleMissionView {
    /// Items.
    pub count: usize,
    /// The items.
    pub items: Vec<crate::mission::MissionItem>,
    /// Retransmissions during the download.
    pub retries: u32,
    /// Download time, seconds.
    pub seconds: f64,
}

/// The reply of `GET /status` (and the `/events` stream's `status`
/// document, which `status_patch` events patch).
#[derive(Debug, Clone, Serialize)]
pub struct StatusView {
    /// Seconds since the daemon started.
    pub uptime_s: f64,
    /// The daemon's clock, unix seconds (simulated when it runs in
    /// lockstep with the bundled simulator).
    pub now_unix: f64,
    /// The video.
    pub video: VideoStatusView,
    /// The SLAM.
    pub slam: SlamStatus,
    /// The vehicle, or `{"configured": false}` without a link.
    pub vehicle: VehicleStatusView,
    /// Shots in the store.
    pub shots: usize,
    /// Writes that failed and are not repaired yet.
    pub errors: Vec<WriteFailure>,
}

/// The video part of [`StatusView`].
#[derive(Debug, Clone, Serialize)]
pub struct VideoStatusView {
    /// Frames received a second.
    pub received_fps: f64,
    /// Frames decoded a second.
    pub decoded_fps: f64,
    /// Frames the SLAM took a second.
    pub consumed_fps: f64,
    /// The ingest's counters.
    pub counters: crate::video::live::CountersSnapshot,
    /// What the link left the SLAM over its window.
    pub link: crate::video::live::LinkQuality,
    /// What the source is.
    pub source: crate::video::live::SourceInfo,
    /// The stream's bit rate, kbit/s.
    pub bitrate_kbps: f64,
    /// The newest frame's width (None: no frame yet).
    pub width: Option<u32>,
    /// The newest frame's height.
    pub height: Option<u32>,
    /// The newest frame's age, seconds.
    pub last_frame_age_s: Option<f64>,
}

/// The vehicle part of [`StatusView`]: its status, or that no link is
/// configured.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum VehicleStatusView {
    /// A link is configured.
    Configured(Box<VehicleStatus>),
    /// No link: `{"configured": false}`.
    Absent {
        /// Always false.
        configured: bool,
    },
}

/// The reply of `GET /keyframes`.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeList {
    /// How many.
    pub count: usize,
    /// The keyframes.
    pub keyframes: Vec<KeyframeInfo>,
}

/// The reply of `GET /shots`.
#[derive(Debug, Clone, Serialize)]
pub struct ShotList {
    /// How many.
    pub count: usize,
    /// The shots.
    pub shots: Vec<Shot>,
}

/// The reply of `GET /shots/{id}/progress`.
#[derive(Debug, Clone, Serialize)]
pub struct ProgressView {
    /// The shot.
    pub shot: String,
    /// Its mission record.
    pub mission: Option<MissionRecord>,
    /// The vehicle's progress through the mission it holds.
    pub progress: Option<MissionProgressView>,
}

/// The reply of `POST /vehicle/stop`: what the vehicle acknowledged and
/// what was stopped.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StopView {
    /// Always true in a reply: the vehicle acknowledged the hold.
    pub stopped: bool,
    /// The command sent (`MAV_CMD_DO_SET_MODE`).
    pub command: &'static str,
    /// The mode asked for, as the autopilot names it (`AUTO.LOITER`, `LOITER`).
    pub mode: String,
    /// The COMMAND_ACK's result, as the vehicle sent it (`MAV_RESULT_ACCEPTED`).
    pub ack: String,
    /// The shot whose refinement loop was cancelled (None: none ran).
    pub refinement_cancelled: Option<String>,
    /// The shot whose mission the vehicle was flying, now marked
    /// `stopped` (None: no started shot).
    pub shot: Option<String>,
    /// Why, as recorded on the shot.
    pub reason: String,
    /// When the ACK came, unix seconds.
    pub at_unix: f64,
}

/// What [`VehicleView::stop`] did: the vehicle's acknowledgement, the
/// loop it cancelled, the shot whose mission it flew last.
#[derive(Debug, Clone, PartialEq)]
pub struct StopOutcome {
    /// The acknowledged hold.
    pub ack: crate::vehicle::HoldAck,
    /// The shot whose refinement loop was cancelled.
    pub refinement_cancelled: Option<String>,
    /// The shot whose mission was started last (the one flown).
    pub flying: Option<String>,
}

/// What the API asks of the vehicle.
pub trait VehicleView: Send + Sync {
    /// Link and vehicle state.
    fn status(&self) -> VehicleStatus;
    /// Plan the localised shot's mission and upload it.
    fn upload_shot<'a>(
        &'a self,
        shot: &'a Shot,
    ) -> BoxFuture<'a, Result<MissionRecord, VehicleError>>;
    /// Start `shot`'s uploaded mission (and refine that shot); refused
    /// when the vehicle holds another shot's mission.
    fn start_mission<'a>(&'a self, shot: &'a Shot) -> BoxFuture<'a, Result<(), VehicleError>>;
    /// Mission progress (None: none reported yet).
    fn progress(&self) -> Option<MissionProgressView>;
    /// The vehicle target of a localised shot, without uploading anything.
    fn shot_target(&self, shot: &Shot) -> Result<ShotTarget, VehicleError> {
        Err(VehicleError::NoGeoreference {
            reason: format!("no georeference for shot {}", shot.id),
        })
    }
    /// Stops the vehicle where it is: cancels the refinement loop (so it
    /// uploads nothing more), then switches the vehicle to hold and waits
    /// for its COMMAND_ACK (a refusal or no ACK is an error).
    fn stop<'a>(&'a self, _reason: &'a str) -> BoxFuture<'a, Result<StopOutcome, VehicleError>> {
        Box::pin(async {
            Err(VehicleError::NoVehicle {
                reason: "this vehicle cannot be stopped from here".into(),
            })
        })
    }
    /// The mission the vehicle holds, read back over the link.
    fn download_mission(&self) -> BoxFuture<'_, Result<VehicleMissionView, VehicleError>> {
        Box::pin(async {
            Err(VehicleError::NoVehicle {
                reason: "this vehicle cannot be read back".into(),
            })
        })
    }
}
