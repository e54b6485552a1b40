//! Bodies of the longer subcommands (the argument types live in `main.rs`).

pub mod scenario;
pub mod shot;
pub mod slam;
