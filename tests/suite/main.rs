//! The integration tests: one binary, one module per subject (the file
//! names say what each covers: `api_*`, `bow_*`, `daemon_*`, `geo_*`,
//! `mission_*`, `shot_*`, `slam_*`, `video_*` ...), so `cargo test` links
//! the library into one test program instead of one per file, and the
//! tests share one pool of threads instead of waiting for each other file
//! by file. Run one subject with its module path as the filter, e.g.
//! `cargo test --release --test suite shot_photos:: -- --nocapture`.
//! The `*_support` modules are what several subjects share.

/// The repository's root: where cargo says the package is when it runs the
/// tests (`CARGO_MANIFEST_DIR` at run time), else where it was when the
/// tests were built. A test program built in another clone sharing the
/// target directory (cargo may reuse it when the sources are older than
/// it) must find this clone's files, not the other's.
pub fn repo_root() -> std::path::PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")))
}

mod cli_support;
mod daemon_support;
mod data_support;
mod geometry_support;
mod http_support;
mod link_support;
mod mjpeg_support;
mod sim_support;
mod video_support;

mod api_http;
mod api_photo_shots;
mod bow_cli;
mod bow_database;
mod bow_dbow2_import;
mod bow_retrieval;
mod bow_robustness;
mod browser;
mod cli_eval;
mod cli_features;
mod cli_newcomer;
mod daemon_e2e;
mod daemon_refine;
mod daemon_restart;
mod daemon_restart_field;
mod features_extractor;
mod features_quality;
mod foundation;
mod geo_align;
mod geo_conventions;
mod geo_daemon;
mod geo_interpolation;
mod geo_real;
mod geo_sim;
mod geometry_ba;
mod geometry_peer_opencv;
mod geometry_pnp;
mod geometry_two_view;
mod gimbal_v2;
mod ingest_robustness;
mod link_actor;
mod link_forward;
mod link_serial;
mod link_wire;
mod map_reload_probe;
mod mission_cli;
mod mission_mavsdk;
mod mission_sim;
mod mission_upload;
mod mjpeg_parser;
mod peer_evo;
mod priors_daemon;
mod scenario;
mod shot_aliasing;
mod shot_cli;
mod shot_photos;
mod shot_sim;
mod shot_teddy;
mod slam_aided;
mod slam_loop;
mod slam_merge;
mod slam_real;
mod slam_sim;
mod soak;
mod stop_sim;
mod video_720p;
mod video_feedback;
mod video_h264;
mod video_loss;
mod video_mjpeg;
mod video_peers;
mod video_sim_rtp;
