//! The autopilot's boot clock on the ground station's clock: telemetry
//! stamped with `time_boot_ms` is placed at the local (unix) time it was
//! taken by the smallest `receive - boot` seen (the link's fastest
//! delivery), so the link's jitter does not reach the samples' times.
//! [`BootClock::sample_time`] picks the clock [`TelemetryClock`] asks for.

use super::telemetry::TelemetryClock;

/// Maps the autopilot's boot time to the local (unix) clock: the offset is
/// the smallest `receive - boot` seen, i.e. the fastest delivery; a boot
/// time that goes back by more than a second (a reboot) starts over.
#[derive(Debug, Clone, Default)]
pub struct BootClock {
    offset_s: Option<f64>,
    last_boot_s: f64,
}

impl BootClock {
    /// The local time of a sample taken at `boot_s` (autopilot boot time,
    /// seconds) and received at `received_unix`; updates the offset.
    pub fn local(&mut self, boot_s: f64, received_unix: f64) -> f64 {
        if boot_s + 1.0 < self.last_boot_s {
            self.offset_s = None;
        }
        self.last_boot_s = boot_s;
        let o = received_unix - boot_s;
        let offset = self.offset_s.map_or(o, |x| x.min(o));
        self.offset_s = Some(offset);
        boot_s + offset
    }

    /// The offset now (`local - boot`, seconds), once a sample was seen.
    pub fn offset_s(&self) -> Option<f64> {
        self.offset_s
    }

    /// A telemetry sample's time on the local clock: by its boot time
    /// (`boot_ms`) when `clock` is [`TelemetryClock::Boot`] and the message
    /// carries one, else its receive time.
    pub fn sample_time(
        &mut self,
        clock: TelemetryClock,
        boot_ms: Option<u32>,
        received_unix: f64,
    ) -> f64 {
        match (clock, boot_ms) {
            (TelemetryClock::Boot, Some(ms)) => self.local(f64::from(ms) / 1e3, received_unix),
            _ => received_unix,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn boot_clock_takes_the_fastest_delivery_and_restarts_on_reboot() {
        let mut c = BootClock::default();
        assert_eq!(c.local(10.0, 1010.3), 10.0 + 1000.3);
        assert!((c.local(11.0, 1011.1) - 1011.1).abs() < 1e-9);
        // A slower delivery keeps the offset of 1000.1.
        assert!((c.local(12.0, 1012.5) - 1012.1).abs() < 1e-9);
        // Reboot: boot time restarts, offset is measured anew.
        assert!((c.local(1.0, 2000.2) - 2000.2).abs() < 1e-9);
    }

    #[test]
    fn receive_time_without_a_boot_time_or_on_the_receive_clock() {
        let mut c = BootClock::default();
        assert_eq!(c.sample_time(TelemetryClock::Boot, None, 5.0), 5.0);
        assert_eq!(c.offset_s(), None);
        assert_eq!(
            c.sample_time(TelemetryClock::Received, Some(1000), 5.0),
            5.0
        );
        assert_eq!(c.offset_s(), None);
        assert_eq!(c.sample_time(TelemetryClock::Boot, Some(1000), 5.5), 5.5);
        assert_eq!(c.offset_s(), Some(4.5));
    }
}
