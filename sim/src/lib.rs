//! shotpilot-sim: the simulated world the shotpilot daemon flies in.
//!
//! A PX4-like multicopter with a 2-axis gimbal camera, a procedurally
//! textured 3D scene rendered through a pinhole + radial-tangential camera,
//! a MAVLink 2 autopilot and an MJPEG video server. This crate never
//! depends on `shotpilot`: its camera projection is its own code, an
//! independent check on the daemon's camera model.

// Vehicle, autopilot, link, scripts and the app (simvehicle).
pub mod app;
pub mod autopilot;
pub mod geodesy;
pub mod link;
pub mod live;
pub mod lockstep;
pub mod mavcam;
pub mod script;
pub mod vehicle;

// World, camera, renderer, paths, datasets and video (simworld).
pub mod camera;
pub mod clock;
pub mod dataset;
pub mod disturbance;
pub mod imaging;
pub mod paths;
pub mod realism;
pub mod render;
pub mod rtp;
pub mod texture;
pub mod video;
pub mod world;
