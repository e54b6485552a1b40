//! Frame sources. [`dataset`] reads recorded sequences (TUM and EuRoC layouts,
//! and the simulator's renders, which use the TUM layout); [`mjpeg`] reads
//! live MJPEG streams and snapshot URLs over HTTP into the latest-frame
//! pipeline of [`live`].

pub mod dataset;
pub mod live;
pub mod mjpeg;
