//! shotpilot: a ground-control-station daemon for camera drones.
//!
//! It watches a drone's live video, builds a map with monocular visual SLAM,
//! finds the camera pose that takes the photograph an operator describes, and
//! sends the drone there as a MAVLink mission.
//!
//! ```text
//!  image-transmission receiver          Pixhawk (3DR radio serial) / SITL (UDP)
//!    HTTP MJPEG / snapshot                       MAVLink 2
//!           |                                        ^   |
//!    video/ ingest (async)                 vehicle/ link actor (async)
//!           | latest-frame slot                      |   | telemetry (watch)
//!           v                                        |   v
//!    slam/ tracking thread --keyframes--> slam/ mapping thread
//!      ORB -> match -> PnP       (bounded ch)   triangulate, local BA, cull
//!           \                                     /
//!            +-------> Map (keyframes, points, BoW database) <----+
//!                               | read-only snapshots
//!   operator --HTTP--> api/ --> shot/ : anchors -> homography -> desired shot
//!                                       -> BoW query -> PnP -> target pose
//!                                             |
//!                               geo/ : map frame -> NED -> lat/lon/alt
//!                                             |
//!                               mission/ : target -> items -> upload -> ACK
//! ```
//!
//! | module | what it holds |
//! |---|---|
//! | [`config`] | the typed tree of `config.toml` |
//! | [`camera`] | pinhole + radial-tangential distortion |
//! | [`video`] | frame sources: datasets (TUM, EuRoC), live MJPEG/snapshot over HTTP, latest-frame slots |
//! | [`eval`] | TUM trajectories, association, Umeyama alignment, ATE/RPE, plots |
//! | [`angle`] | angles wrapped to one turn: `wrap180` (degrees), `wrap_pi` (radians) |
//! | [`stats`] | median and nearest-rank quantiles of samples |
//! | [`lie`] | SO(3)/SE(3)/Sim(3): skew, SE(3) exponential, quaternion renormalisation, [`lie::Sim3`] (below geometry and optimize) |
//! | [`features`] | image pyramid, FAST, orientation, rBRIEF (ORB) |
//! | [`matching`] | Hamming matching: brute force, keypoint grid for search by projection |
//! | [`features_eval`] | measuring the extractor: timing, homography-warp repeatability, matching, spread |
//! | [`geometry`] | two-view, triangulation, PnP, homography, Umeyama |
//! | [`optimize`] | Levenberg-Marquardt: pose-only, local BA, Sim(3) |
//! | [`slam`] | map, tracking, local mapping, map file |
//! | [`shot`] | desired shot from four anchors (warp) and its localisation in the map; the operator's request, the shot model (records, statuses) and the shot store |
//! | [`bow`] | bag of binary words: vocabulary, BoW vectors, keyframe database |
//! | [`geo`] | map ↔ NED ↔ WGS84: telemetry history, camera mounting, robust Sim(3), targets |
//! | [`vehicle`] | MAVLink link actor, transports, telemetry |
//! | [`api`] | the HTTP API (`/api/v1`): one error type, typed replies, the views it reads (SLAM, vehicle); the operator page |
//! | [`daemon`] | `shotpilot run`: wires sim, video, SLAM, link and API; shutdown |
//! | [`mission`] | mission planning (pure) and upload protocol |
//! | [`refine`] | closing the loop: shot error (homography), correction controller, the daemon loop's tunables |
//! | [`simulator`] | the bundled simulator's adapters (camera, `[sim]`) and the closed-loop scenario in it; the only importer of `shotpilot_sim` outside tests |
//!
//! The synchronous core never imports tokio or axum; I/O lives in
//! `vehicle`, `video` (live sources) and `mission::upload`. Every module
//! imports only modules on lower floors (no import circles,
//! `.ci/import-circles`); `ARCHITECTURE.md` at the repository root has the
//! floors, the layout and the conventions.

pub mod angle;
pub mod api;
pub mod bow;
pub mod camera;
pub mod clock;
pub mod config;
pub mod daemon;
pub mod eval;
pub mod features;
pub mod features_eval;
pub mod geo;
pub mod geometry;
pub mod lie;
pub mod matching;
pub mod mission;
pub mod optimize;
pub mod refine;
pub mod shot;
pub mod simulator;
pub mod slam;
pub mod stats;
pub mod vehicle;
pub mod video;
