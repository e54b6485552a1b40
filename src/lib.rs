//! shotpilot: a ground-control-station daemon for camera drones.
//!
//! It watches a drone's live video, builds a map with monocular visual SLAM,
//! finds the camera pose that takes the photograph an operator describes, and
//! sends the drone there as a MAVLink mission, then refines the pose from the
//! live view until the framing matches.
//!
//! ```text
//!  camera / image-transmission receiver     Pixhawk (radio serial) / SITL (UDP, TCP)
//!   RTSP H.264, RTP/UDP H.264, MJPEG, JPEG           MAVLink 2
//!           |                                        ^   |
//!    video/ sources (async) -> H.264 decode   vehicle/ link actor (async)
//!           | newest-frame slot                      |   | telemetry (watch)
//!           v                                        |   v
//!    slam/ tracking (the SLAM thread) --keyframes--> slam/ mapping thread
//!      ORB -> match -> PnP       (bounded ch)   triangulate, local BA, cull
//!                                                    | mapped keyframes
//!                                          slam/ loop closing thread: loops,
//!                                            merges, Sim(3), essential graph
//!            +-------> Map (atlas: keyframes, points, BoW database) <----+
//!                               | snapshots
//!   operator --HTTP--> api/ --> shot/ : anchors -> keyframe geometry -> PnP;
//!                                       photo -> candidate keyframes -> PnP
//!                                             |   -> target pose, sigma
//!                               geo/ : map frame -> NED -> lat/lon/alt
//!                                             |
//!                               mission/ : target -> items -> upload -> ACK
//!                                             |
//!                               refine/ : arrival -> shot error -> correction
//!                                 (new mission leg, or servoing) -> again
//! ```
//!
//! | module | what it holds |
//! |---|---|
//! | [`config`] | the typed tree of `config.toml` |
//! | [`camera`] | pinhole + radial-tangential distortion |
//! | [`video`] | frame sources: datasets (TUM, EuRoC); live MJPEG and snapshots over HTTP, RTSP and RTP/UDP (or SDP) H.264 decoded by OpenH264 with lost packets' rows masked, or the stream the vehicle's camera announces (`auto`); newest-frame slots |
//! | [`eval`] | trajectory evaluation: association, Umeyama alignment, ATE/RPE, plots |
//! | [`angle`] | angles wrapped to one turn: `wrap180` (degrees), `wrap_pi` (radians) |
//! | [`stats`] | median and nearest-rank quantiles of samples |
//! | [`trajectory`] | a camera trajectory (timestamped poses) and the TUM format, as SLAM writes it and eval reads it |
//! | [`clock`] | the daemon's clock: the tokio runtime's, so tests on paused time move every age and timeout |
//! | [`lie`] | SO(3)/SE(3)/Sim(3): skew, SE(3) exponential, quaternion renormalisation, [`lie::Sim3`] (below geometry and optimize) |
//! | [`features`] | image pyramid, FAST, orientation, rBRIEF (ORB) |
//! | [`matching`] | Hamming matching: brute force, keypoint grid for search by projection |
//! | [`features_eval`] | measuring the extractor: timing, homography-warp repeatability, matching, spread |
//! | [`geometry`] | two-view, triangulation, PnP, homography, Umeyama, Sim(3) RANSAC |
//! | [`optimize`] | Levenberg-Marquardt: pose-only, local BA (with position priors), Sim(3), the essential graph |
//! | [`slam`] | the map (an atlas of maps), tracking, local mapping and loop closing on three threads (map merging, telemetry priors), the map file |
//! | [`shot`] | desired shot from four anchors (warp) or a photo, and its localisation in the map; the operator's request, the shot model (records, statuses) and the shot store |
//! | [`bow`] | bag of binary words: vocabulary, BoW vectors, keyframe database |
//! | [`geo`] | map ↔ NED ↔ WGS84: telemetry history, the autopilot's boot clock, camera mounting, the georeference alignment (robust Sim(3), orientations, GNSS drift, newest pairs), the live georeference and its status, the saved georeference and its continuity across restarts (rebased to a new home), targets |
//! | [`vehicle`] | MAVLink link actor, transports, telemetry, forwarding to other ground stations, gimbal control, the camera protocol |
//! | [`api`] | the HTTP API (`/api/v1`): one error type, typed replies, the views it reads (SLAM, vehicle), the event stream; the operator page |
//! | [`daemon`] | `shotpilot run`: wires sim, video, SLAM, link and API; the georeference, shot and refinement services; the map and georeference on disk, the vehicle's mission reconciled; shutdown |
//! | [`mission`] | mission planning (pure) and the upload/download protocol |
//! | [`refine`] | closing the loop at the shot: shot error (homography) and its reachable floor, the desired picture, arrival, measurement over several frames, correction controller, the refinement session and its rounds, servoing on guided setpoints, re-targeting on the approach, the mission record's rounds, the daemon loop's tunables |
//! | `simulator` | (feature `sim`, on by default) the bundled simulator's adapters (camera, `[sim]`) and the closed-loop scenario harness in it; the only importer of `shotpilot_sim` outside tests |
//!
//! The synchronous core never imports tokio or axum; I/O lives in
//! `daemon`, `vehicle`, `video` (live sources), `api` and
//! `mission::upload`'s drivers. Every module imports only modules on lower
//! floors (no import circles, `.ci/import-circles`); `ARCHITECTURE.md` at
//! the repository root has the floors, the layout and the conventions.
//!
//! The `sim` cargo feature (on by default) brings in the bundled simulator:
//! the `simulator` module, the daemon's in-process simulator (`[sim]
//! enabled`) and the `scenario` subcommand. A field build
//! (`cargo build --release --no-default-features`) has none of them: the
//! daemon runs against a real camera and autopilot only, and refuses to
//! start with `[sim] enabled = true`
//! ([`daemon::DaemonError::NoSimulator`]). `[sim]` is parsed either way,
//! so configuration files stay valid.

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
// Feature `sim`; the unit tests, which render with the simulator (a
// dev-dependency), have it in either build.
#[cfg(any(feature = "sim", test))]
pub mod simulator;
pub mod slam;
pub mod stats;
pub mod trajectory;
pub mod vehicle;
pub mod video;
