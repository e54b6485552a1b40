//! The autopilot's flight modes and their PX4 and ArduPilot custom-mode numbers.

/// Flight modes (PX4 names; the ArduPilot flavour maps them to copter modes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// PX4 MANUAL / ArduPilot STABILIZE (holds position: no RC in the sim).
    Manual,
    /// PX4 POSCTL / ArduPilot POSHOLD: hold position.
    Position,
    /// PX4 AUTO.LOITER / ArduPilot LOITER: hold position.
    Hold,
    /// PX4 AUTO.MISSION / ArduPilot AUTO.
    Mission,
    /// PX4 AUTO.TAKEOFF (ArduPilot: GUIDED takeoff).
    Takeoff,
    /// PX4 AUTO.LAND / ArduPilot LAND.
    Land,
    /// PX4 AUTO.RTL / ArduPilot RTL.
    Rtl,
    /// PX4 OFFBOARD / ArduPilot GUIDED: follows an external setpoint (the
    /// scripted operator).
    Offboard,
}

const PX4_MAIN_MANUAL: u32 = 1;
const PX4_MAIN_ALTCTL: u32 = 2;
const PX4_MAIN_POSCTL: u32 = 3;
const PX4_MAIN_AUTO: u32 = 4;
const PX4_MAIN_OFFBOARD: u32 = 6;
const PX4_MAIN_STABILIZED: u32 = 7;
const PX4_SUB_TAKEOFF: u32 = 2;
const PX4_SUB_LOITER: u32 = 3;
const PX4_SUB_MISSION: u32 = 4;
const PX4_SUB_RTL: u32 = 5;
const PX4_SUB_LAND: u32 = 6;

impl Mode {
    /// PX4 custom_mode: main_mode << 16 | sub_mode << 24.
    pub fn px4_custom_mode(self) -> u32 {
        let (main, sub) = match self {
            Mode::Manual => (PX4_MAIN_MANUAL, 0),
            Mode::Position => (PX4_MAIN_POSCTL, 0),
            Mode::Hold => (PX4_MAIN_AUTO, PX4_SUB_LOITER),
            Mode::Mission => (PX4_MAIN_AUTO, PX4_SUB_MISSION),
            Mode::Takeoff => (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF),
            Mode::Land => (PX4_MAIN_AUTO, PX4_SUB_LAND),
            Mode::Rtl => (PX4_MAIN_AUTO, PX4_SUB_RTL),
            Mode::Offboard => (PX4_MAIN_OFFBOARD, 0),
        };
        main << 16 | sub << 24
    }

    /// Decode PX4 (main, sub) modes.
    pub fn from_px4(main: u32, sub: u32) -> Option<Mode> {
        Some(match (main, sub) {
            (PX4_MAIN_MANUAL | PX4_MAIN_STABILIZED, _) => Mode::Manual,
            (PX4_MAIN_ALTCTL | PX4_MAIN_POSCTL, _) => Mode::Position,
            (PX4_MAIN_AUTO, PX4_SUB_LOITER) => Mode::Hold,
            (PX4_MAIN_AUTO, PX4_SUB_MISSION) => Mode::Mission,
            (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF) => Mode::Takeoff,
            (PX4_MAIN_AUTO, PX4_SUB_LAND) => Mode::Land,
            (PX4_MAIN_AUTO, PX4_SUB_RTL) => Mode::Rtl,
            (PX4_MAIN_OFFBOARD, _) => Mode::Offboard,
            _ => return None,
        })
    }

    /// ArduPilot copter mode number.
    pub fn ardupilot_custom_mode(self) -> u32 {
        match self {
            Mode::Manual => 0,    // STABILIZE
            Mode::Position => 16, // POSHOLD
            Mode::Hold => 5,      // LOITER
            Mode::Mission => 3,   // AUTO
            Mode::Takeoff => 4,   // GUIDED (takeoff)
            Mode::Land => 9,      // LAND
            Mode::Rtl => 6,       // RTL
            Mode::Offboard => 4,  // GUIDED
        }
    }

    /// Decode an ArduPilot copter mode number.
    pub fn from_ardupilot(mode: u32) -> Option<Mode> {
        Some(match mode {
            0 => Mode::Manual,
            2 | 16 => Mode::Position,
            3 => Mode::Mission,
            4 => Mode::Offboard,
            5 | 17 => Mode::Hold,
            6 | 21 => Mode::Rtl,
            9 => Mode::Land,
            _ => return None,
        })
    }
}
