//! Planned items on the wire: to `MISSION_ITEM_INT`, from it and from the
//! legacy float `MISSION_ITEM`, and whether a read-back holds the plan.

// The legacy MISSION_ITEM is deprecated in the dialect; autopilots send it.
#![allow(deprecated)]

use mavlink::dialects::common::{
    MISSION_ITEM_DATA, MISSION_ITEM_INT_DATA, MavCmd, MavFrame, MavMissionType,
};
use num_traits::{FromPrimitive, ToPrimitive};

use super::{MissionError, Peers};
use crate::mission::plan::{self, MissionItem};

/// Converts a planned item to the wire message.
pub fn item_to_wire(
    item: &MissionItem,
    peers: &Peers,
    mission_type: MavMissionType,
) -> Result<MISSION_ITEM_INT_DATA, MissionError> {
    let command = MavCmd::from_u16(item.command).ok_or(MissionError::UnknownNumber {
        seq: item.seq,
        what: "command",
        value: u32::from(item.command),
    })?;
    let frame = MavFrame::from_u8(item.frame).ok_or(MissionError::UnknownNumber {
        seq: item.seq,
        what: "frame",
        value: u32::from(item.frame),
    })?;
    Ok(MISSION_ITEM_INT_DATA {
        param1: item.params[0],
        param2: item.params[1],
        param3: item.params[2],
        param4: item.params[3],
        x: item.x,
        y: item.y,
        z: item.z,
        seq: item.seq,
        command,
        target_system: peers.target_system,
        target_component: peers.target_component,
        frame,
        current: u8::from(item.current),
        autocontinue: u8::from(item.autocontinue),
        mission_type,
    })
}

/// Converts a received `MISSION_ITEM_INT` to a [`MissionItem`].
pub fn item_from_wire(data: &MISSION_ITEM_INT_DATA) -> MissionItem {
    MissionItem {
        seq: data.seq,
        frame: data.frame.to_u8().unwrap_or(u8::MAX),
        command: data.command.to_u16().unwrap_or(u16::MAX),
        current: data.current != 0,
        autocontinue: data.autocontinue != 0,
        params: [data.param1, data.param2, data.param3, data.param4],
        x: data.x,
        y: data.y,
        z: data.z,
    }
}

/// Converts a legacy float `MISSION_ITEM` (latitude/longitude in degrees for
/// global frames) to a [`MissionItem`].
pub fn item_from_legacy(data: &MISSION_ITEM_DATA) -> MissionItem {
    let mut item = MissionItem {
        seq: data.seq,
        frame: data.frame.to_u8().unwrap_or(u8::MAX),
        command: data.command.to_u16().unwrap_or(u16::MAX),
        current: data.current != 0,
        autocontinue: data.autocontinue != 0,
        params: [data.param1, data.param2, data.param3, data.param4],
        x: data.x as i32,
        y: data.y as i32,
        z: data.z,
    };
    if item.is_global() {
        item.x = plan::deg_to_e7(f64::from(data.x));
        item.y = plan::deg_to_e7(f64::from(data.y));
    }
    item
}

/// Whether a downloaded mission holds the planned one. For ArduPilot the
/// autopilot rewrites item 0 (home), so `skip_home` leaves it out.
pub fn same_mission(planned: &[MissionItem], downloaded: &[MissionItem], skip_home: bool) -> bool {
    let skip = usize::from(skip_home);
    planned.len() == downloaded.len()
        && planned
            .iter()
            .zip(downloaded)
            .skip(skip)
            .all(|(a, b)| a.same_content(b))
}
