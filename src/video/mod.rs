//! Frame sources. [`dataset`] reads recorded sequences (TUM and EuRoC layouts,
//! and the simulator's renders, which use the TUM layout).

pub mod dataset;
