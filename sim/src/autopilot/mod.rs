//! A PX4-like (or ArduPilot-like) autopilot speaking MAVLink 2.
// The legacy mission messages (MISSION_ITEM, MISSION_REQUEST,
// MISSION_SET_CURRENT) and DO_MOUNT_CONTROL are deprecated in the dialect
// but still spoken by real autopilots and ground stations: we implement them
// on purpose.
#![allow(deprecated)]

pub mod mission;
