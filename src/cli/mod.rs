//! The subcommands: each file holds one command's arguments and its body
//! (`slam_timing` and `slam_memory` are `slam`'s frame-time and memory
//! reports). `scenario` needs the
//! simulator: only with the `sim` feature.

pub mod eval;
pub mod features;
pub mod mission;
pub mod run;
#[cfg(feature = "sim")]
pub mod scenario;
pub mod shot;
pub mod slam;
mod slam_memory;
pub mod slam_timing;
pub mod vocab;
