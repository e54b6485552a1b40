//! Test-only helpers of the MJPEG parser tests.

pub mod reference;
