//! The simulator's integration tests: one binary, one module per subject
//! (`cargo test --release -p shotpilot-sim --test suite render::` runs one).

mod camera_effects;
mod ideal_unchanged;
mod inprocess_mission;
mod live_realism;
mod pymavlink_peers;
mod render;
mod vehicle_realism;
mod video;
mod worlds;
