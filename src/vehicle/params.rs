//! The link's parameters (`[link]`): the URL, ids, timeouts, telemetry rates,
//! signing and forward endpoints.

use serde::{Deserialize, Serialize};

use super::transport::Signing;

/// Telemetry rates requested with SET_MESSAGE_INTERVAL, Hz (0: leave as is).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Rates {
    /// GLOBAL_POSITION_INT.
    pub global_position_hz: f32,
    /// LOCAL_POSITION_NED.
    pub local_position_hz: f32,
    /// ATTITUDE.
    pub attitude_hz: f32,
    /// HOME_POSITION.
    pub home_position_hz: f32,
    /// GIMBAL_DEVICE_ATTITUDE_STATUS.
    pub gimbal_hz: f32,
    /// MISSION_CURRENT.
    pub mission_current_hz: f32,
}

impl Default for Rates {
    fn default() -> Self {
        // About 1.2 kB/s of telemetry: a fifth of a 57600 baud radio.
        Self {
            global_position_hz: 5.0,
            local_position_hz: 5.0,
            attitude_hz: 10.0,
            home_position_hz: 0.5,
            gimbal_hz: 5.0,
            mission_current_hz: 1.0,
        }
    }
}

/// The `[link]` section of the configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Where the vehicle is (see [`transport`]).
    pub url: String,
    /// Our MAVLink system id (255: the GCS convention).
    pub system_id: u8,
    /// Our component id (191 by default: not 190, MAV_COMP_ID_MISSIONPLANNER,
    /// which QGroundControl and Mission Planner use, so that a ground station
    /// sharing the link through [`Params::forward`] and shotpilot are told
    /// apart by the vehicle's mission and command protocols).
    pub component_id: u8,
    /// Forward endpoints for other ground stations (see [`router`]), in
    /// MAVProxy's and mavlink-router's URL syntax: `udpout:HOST:PORT`,
    /// `udpin:ADDR:PORT`, `tcpin:ADDR:PORT`, `tcpout:HOST:PORT`.
    pub forward: Vec<String>,
    /// Talk only to this vehicle system id; 0 takes the first autopilot heard.
    pub vehicle_system_id: u8,
    /// Send MAVLink 1 frames (old radios); MAVLink 1 and 2 are always received.
    pub mavlink1: bool,
    /// GCS heartbeat period, ms.
    pub heartbeat_period_ms: u64,
    /// The link counts as lost after this long without a vehicle heartbeat, ms.
    pub link_lost_after_ms: u64,
    /// First reconnect delay, ms (doubles up to the maximum).
    pub reconnect_min_ms: u64,
    /// Longest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// COMMAND_LONG retry timeout, ms.
    pub command_timeout_ms: u64,
    /// COMMAND_LONG sends before giving up.
    pub command_attempts: u32,
    /// Telemetry rates to ask for.
    pub rates: Rates,
    /// MAVLink 2 signing (none: unsigned).
    pub signing: Option<Signing>,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            url: "udpin:0.0.0.0:14550".into(),
            system_id: 255,
            component_id: 191,
            forward: Vec::new(),
            vehicle_system_id: 0,
            mavlink1: false,
            heartbeat_period_ms: 1000,
            link_lost_after_ms: 3000,
            reconnect_min_ms: 250,
            reconnect_max_ms: 5000,
            command_timeout_ms: 1000,
            command_attempts: 3,
            rates: Rates::default(),
            signing: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_round_trip_toml() {
        let text = r#"
            url = "serial:/dev/ttyUSB0:57600"
            vehicle_system_id = 1
            [rates]
            attitude_hz = 4.0
            [signing]
            key_hex = "0000000000000000000000000000000000000000000000000000000000000001"
        "#;
        let p: Params = toml::from_str(text).expect("parses");
        assert_eq!(p.url, "serial:/dev/ttyUSB0:57600");
        assert_eq!(p.rates.attitude_hz, 4.0);
        assert_eq!(p.rates.global_position_hz, 5.0);
        assert_eq!(p.heartbeat_period_ms, 1000);
        assert_eq!(p.signing.as_ref().map(|s| s.link_id), Some(0));
        assert!(
            toml::from_str::<Params>("bogus = 1").is_err(),
            "unknown fields refused"
        );
    }
}
