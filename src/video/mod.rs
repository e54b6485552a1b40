//! Frame sources. [`dataset`] reads recorded sequences (TUM and EuRoC layouts,
//! and the simulator's renders, which use the TUM layout); [`mjpeg`] reads
//! live MJPEG streams and snapshot URLs over HTTP into the latest-frame
//! pipeline of [`live`]. [`source`] picks the source by `[video] url`:
//! [`rtsp`] (H.264 over RTSP, on `retina`), [`udp`] (raw RTP H.264,
//! depacketised by [`rtp`]), both decoded by [`h264`] (OpenH264) on the
//! thread of [`decode_loop`], sharing [`stream`]'s parameters, sink and errors; [`damage`] follows what a lost
//! packet damaged in each picture, through the content's vertical motion
//! that [`motion`] measures on the decoded pictures.

pub mod damage;
pub mod dataset;
pub mod decode_loop;
pub mod h264;
pub mod live;
pub mod mjpeg;
pub mod motion;
pub mod rtp;
pub mod rtsp;
pub mod source;
pub mod stream;
pub mod udp;
