//! Units in names and types.
//!
//! Times are `f64` seconds; currents `f64`/`f32` electrons per second; charges and
//! fluences `f64` electrons. Absolute times are UTC instants, held as [`UtcSeconds`]
//! (seconds since the Unix epoch, `f64`): at present-day epochs an `f64` resolves
//! 0.24 us, far below any time constant of the model (shortest 10 s), and two
//! instants are only ever subtracted, never compared for equality.

use chrono::{DateTime, SecondsFormat, Utc};
use serde::{Deserialize, Serialize};
use std::fmt;

/// A duration in seconds.
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Serialize, Deserialize)]
pub struct Seconds(pub f64);

/// An absolute UTC instant as seconds since 1970-01-01T00:00:00Z.
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd, Serialize, Deserialize)]
pub struct UtcSeconds(pub f64);

impl UtcSeconds {
    /// Parse an ISO 8601 / RFC 3339 UTC string such as `2026-03-01T00:02:31.500000Z`.
    pub fn parse(text: &str) -> Result<Self, String> {
        let t = DateTime::parse_from_rfc3339(text)
            .map_err(|e| format!("`{text}` is not an ISO 8601 UTC time: {e}"))?;
        let t = t.with_timezone(&Utc);
        Ok(Self::from_datetime(&t))
    }

    pub fn from_datetime(t: &DateTime<Utc>) -> Self {
        UtcSeconds(t.timestamp() as f64 + f64::from(t.timestamp_subsec_nanos()) * 1e-9)
    }

    /// The instant `self + d`.
    pub fn plus(self, d: Seconds) -> Self {
        UtcSeconds(self.0 + d.0)
    }

    /// Seconds from `earlier` to `self` (negative if `self` is earlier).
    pub fn since(self, earlier: UtcSeconds) -> Seconds {
        Seconds(self.0 - earlier.0)
    }

    /// ISO 8601 with microseconds, for humans and attributes.
    pub fn to_iso(self) -> String {
        let secs = self.0.floor();
        let nanos = ((self.0 - secs) * 1e9).round().min(999_999_999.0) as u32;
        match DateTime::<Utc>::from_timestamp(secs as i64, nanos) {
            Some(t) => t.to_rfc3339_opts(SecondsFormat::Micros, true),
            None => format!("{}s", self.0),
        }
    }
}

/// One of the six SPHEREx arrays, 1..=6.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct DetectorId(pub u8);

impl DetectorId {
    pub const MIN: u8 = 1;
    pub const MAX: u8 = 6;

    pub fn new(d: i64) -> Option<Self> {
        (i64::from(Self::MIN)..=i64::from(Self::MAX))
            .contains(&d)
            .then_some(DetectorId(d as u8))
    }
}

impl fmt::Display for DetectorId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// Position of an exposure in one detector's history; consecutive exposures have
/// consecutive indices.
pub type ExposureIndex = u64;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_icd_example_and_subtracts() {
        let a = UtcSeconds::parse("2026-03-01T00:02:31.500000Z").unwrap();
        let b = UtcSeconds::parse("2026-03-01T00:04:31.750000Z").unwrap();
        assert!((b.since(a).0 - 120.25).abs() < 1e-6);
        assert_eq!(a.to_iso(), "2026-03-01T00:02:31.500000Z");
    }

    #[test]
    fn refuses_non_time() {
        assert!(UtcSeconds::parse("yesterday").is_err());
    }

    #[test]
    fn detector_range() {
        assert!(DetectorId::new(0).is_none());
        assert_eq!(DetectorId::new(6), Some(DetectorId(6)));
        assert!(DetectorId::new(7).is_none());
    }
}
