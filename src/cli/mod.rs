//! The subcommands: each file holds one command's arguments and its body
//! (`slam` is split: `slam_args` its arguments, `slam_report` its report,
//! `slam_timing` and `slam_memory` the frame-time and memory parts of it).
//! `scenario` needs the simulator: only with the `sim` feature.

pub mod eval;
pub mod features;
pub mod mission;
pub mod run;
#[cfg(feature = "sim")]
pub mod scenario;
pub mod shot;
pub mod slam;
mod slam_args;
mod slam_memory;
mod slam_report;
pub mod slam_timing;
pub mod vocab;
