//! UTC timestamps for job records and run directory names, from a `SystemTime`
//! given by the caller (time is an input), through `jiff`.

use std::time::SystemTime;

use jiff::Timestamp;

/// The instant; outside jiff's range (years −9999…9999) it is clamped.
fn timestamp(t: SystemTime) -> Timestamp {
    Timestamp::try_from(t).unwrap_or(if t < SystemTime::UNIX_EPOCH {
        Timestamp::MIN
    } else {
        Timestamp::MAX
    })
}

/// `2025-03-01T14:05:09Z` (RFC 3339, UTC, seconds).
#[must_use]
pub fn rfc3339(t: SystemTime) -> String {
    timestamp(t).strftime("%Y-%m-%dT%H:%M:%SZ").to_string()
}

/// `20250301T140509Z`: sortable and safe in a file name.
#[must_use]
pub fn compact(t: SystemTime) -> String {
    timestamp(t).strftime("%Y%m%dT%H%M%SZ").to_string()
}

/// True when `text` is an RFC 3339 instant (what [`rfc3339`] writes).
#[must_use]
pub fn is_rfc3339(text: &str) -> bool {
    text.len() <= 40 && text.parse::<Timestamp>().is_ok()
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, UNIX_EPOCH};

    use super::*;

    fn at(secs: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_secs(secs)
    }

    #[test]
    fn known_instants() {
        assert_eq!(rfc3339(at(0)), "1970-01-01T00:00:00Z");
        // `date -u -d @951782400` → 2000-02-29 00:00:00 (a leap day in a century year).
        assert_eq!(rfc3339(at(951_782_400)), "2000-02-29T00:00:00Z");
        // `date -u -d @1740837909` → 2025-03-01 14:05:09; sub-seconds are cut, not rounded.
        assert_eq!(
            rfc3339(at(1_740_837_909) + Duration::from_millis(999)),
            "2025-03-01T14:05:09Z"
        );
        assert_eq!(compact(at(1_740_837_909)), "20250301T140509Z");
        assert_eq!(
            rfc3339(UNIX_EPOCH - Duration::from_secs(1)),
            "1969-12-31T23:59:59Z"
        );
        assert!(is_rfc3339(&rfc3339(at(1_740_837_909))));
        assert!(!is_rfc3339("yesterday") && !is_rfc3339(""));
    }
}
