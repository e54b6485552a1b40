//! The subcommands: each file holds one command's arguments and its body
//! (`slam_timing` is `slam`'s frame-time report).

pub mod eval;
pub mod features;
pub mod mission;
pub mod run;
pub mod scenario;
pub mod shot;
pub mod slam;
pub mod slam_timing;
pub mod vocab;
