//! Flight modes: what an operator may ask for, the autopilots' names for their
//! custom modes, and the DO_SET_MODE parameters of each.

use serde::{Deserialize, Serialize};

use crate::mission::Flavour;

/// Flight modes an operator may ask for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlightMode {
    /// Fly the uploaded mission (PX4 AUTO.MISSION, ArduPilot AUTO).
    Mission,
    /// Hold position (PX4 AUTO.LOITER, ArduPilot LOITER).
    Hold,
    /// Return to launch.
    Rtl,
    /// Follow the ground station's setpoints (PX4 OFFBOARD, ArduPilot
    /// GUIDED). PX4 accepts it only while a setpoint stream runs
    /// ([`crate::vehicle::LinkHandle::guide`]) and leaves it when the
    /// stream stops.
    Guided,
}

/// PX4's custom_mode: main mode in bits 16..24, sub mode in bits 24..32.
pub fn px4_mode_name(custom_mode: u32) -> String {
    let main = (custom_mode >> 16) & 0xff;
    let sub = (custom_mode >> 24) & 0xff;
    let name = match (main, sub) {
        (1, _) => "MANUAL",
        (2, _) => "ALTCTL",
        (3, _) => "POSCTL",
        (4, 1) => "AUTO.READY",
        (4, 2) => "AUTO.TAKEOFF",
        (4, 3) => "AUTO.LOITER",
        (4, 4) => "AUTO.MISSION",
        (4, 5) => "AUTO.RTL",
        (4, 6) => "AUTO.LAND",
        (4, 8) => "AUTO.FOLLOW_TARGET",
        (4, 9) => "AUTO.PRECLAND",
        (4, _) => "AUTO",
        (5, _) => "ACRO",
        (6, _) => "OFFBOARD",
        (7, _) => "STABILIZED",
        _ => return format!("PX4({main}.{sub})"),
    };
    name.to_string()
}

/// ArduCopter's custom_mode numbers.
pub fn ardupilot_mode_name(custom_mode: u32) -> String {
    let name = match custom_mode {
        0 => "STABILIZE",
        1 => "ACRO",
        2 => "ALT_HOLD",
        3 => "AUTO",
        4 => "GUIDED",
        5 => "LOITER",
        6 => "RTL",
        7 => "CIRCLE",
        9 => "LAND",
        16 => "POSHOLD",
        17 => "BRAKE",
        21 => "SMART_RTL",
        _ => return format!("MODE({custom_mode})"),
    };
    name.to_string()
}

/// DO_SET_MODE parameters (base mode, custom main mode, custom sub mode) for a flavour.
pub fn mode_params(flavour: Flavour, mode: FlightMode) -> (f32, f32, f32) {
    const CUSTOM: f32 = 1.0; // MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    match (flavour, mode) {
        (Flavour::Px4, FlightMode::Mission) => (CUSTOM, 4.0, 4.0),
        (Flavour::Px4, FlightMode::Hold) => (CUSTOM, 4.0, 3.0),
        (Flavour::Px4, FlightMode::Rtl) => (CUSTOM, 4.0, 5.0),
        (Flavour::ArduPilot, FlightMode::Mission) => (CUSTOM, 3.0, 0.0),
        (Flavour::ArduPilot, FlightMode::Hold) => (CUSTOM, 5.0, 0.0),
        (Flavour::ArduPilot, FlightMode::Rtl) => (CUSTOM, 6.0, 0.0),
        (Flavour::Px4, FlightMode::Guided) => (CUSTOM, 6.0, 0.0),
        (Flavour::ArduPilot, FlightMode::Guided) => (CUSTOM, 4.0, 0.0),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mode_names() {
        assert_eq!(px4_mode_name((4 << 16) | (4 << 24)), "AUTO.MISSION");
        assert_eq!(px4_mode_name(3 << 16), "POSCTL");
        assert_eq!(px4_mode_name(99 << 16), "PX4(99.0)");
        assert_eq!(ardupilot_mode_name(3), "AUTO");
        assert_eq!(ardupilot_mode_name(5), "LOITER");
        // the mode we set is the mode we then read back
        let (_, main, sub) = mode_params(Flavour::Px4, FlightMode::Mission);
        assert_eq!(
            px4_mode_name(((main as u32) << 16) | ((sub as u32) << 24)),
            "AUTO.MISSION"
        );
        let (_, m, _) = mode_params(Flavour::ArduPilot, FlightMode::Rtl);
        assert_eq!(ardupilot_mode_name(m as u32), "RTL");
        let (_, main, sub) = mode_params(Flavour::Px4, FlightMode::Guided);
        assert_eq!(
            px4_mode_name(((main as u32) << 16) | ((sub as u32) << 24)),
            "OFFBOARD"
        );
        let (_, m, _) = mode_params(Flavour::ArduPilot, FlightMode::Guided);
        assert_eq!(ardupilot_mode_name(m as u32), "GUIDED");
    }
}
