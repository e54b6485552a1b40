//! The simulator's integration tests: one binary, one module per subject
//! (`cargo test --release -p shotpilot-sim --test suite render::` runs one).

/// The simulator package's folder: where cargo says it is when it runs the
/// tests (`CARGO_MANIFEST_DIR` at run time), else where it was when the
/// tests were built (a test program built in another clone sharing the
/// target directory must find this clone's files).
pub fn package_root() -> std::path::PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")))
}

mod camera_effects;
mod cli_log;
mod ideal_unchanged;
mod inprocess_mission;
mod live_realism;
mod pymavlink_peers;
mod render;
mod vehicle_realism;
mod video;
mod worlds;
