//! The subcommands: each file holds one command's arguments and its body.

pub mod eval;
pub mod features;
pub mod mission;
pub mod run;
pub mod scenario;
pub mod shot;
pub mod slam;
pub mod vocab;
