//! Settings of the simulated SharkSEM server (`[simulator.sharksem]`).

use std::net::SocketAddr;

use sdsem_protocol::sharksem::Version;
use serde::{Deserialize, Serialize};

use crate::SimError;
use crate::config::{FaultTrigger, SimEndpoint};

/// The simulated TESCAN SEM's remote control (module docs of [`super`]).
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `endpoint` | `tcp://127.0.0.1:0` | the control port (TCP only; port 0 picks a free port whose successor is free too) |
/// | `data_port` | control + 1 | the data port; 0 picks any free port |
/// | `version` | `2.0.25` | `TcpGetVersion`; functions newer than it are unknown (ignored) |
/// | `sw_version`, `device`, `model` | simulator values | `TcpGetSWVersion`, `TcpGetDevice`, `TcpGetModel` (3.2.20+) |
/// | `firewall_friendly` | false | one control + data pair only, `TcpRegDataPort` ignored |
/// | `tilt_y` | false | `StgGetPosition` answers a sixth value (tilt-Y, always 0), as 3.x stages with that axis do |
/// | `detectors` | `["SE", "BSE"]` | `DtEnumDetectors`: detector K has id 10 + K |
/// | `channels` | 2 | video channels `DtSelect`/`DtEnable` accept |
/// | `view_field_mm` | from `sem.optics` | initial field width (pixel size × optics width) |
/// | `view_field_min_mm`, `view_field_max_mm` | 0.0005, 20 | `SetViewField` clamps into this range |
/// | `speeds_us` | 0.1 … 100 | `ScEnumSpeeds`; `ScScanXY` without dwell uses `speed_index` |
/// | `speed_index` | 3 | the current scan speed (1-based into `speeds_us`) |
/// | `z_mm` | 10 | initial working height of the stage (z is not motorised in time: moves are instant) |
/// | `chunk_interval_s` | 0.05 | simulated seconds between `ScData` chunks |
/// | `data_stall_s` | 10 | REAL seconds a client may leave the data socket unread before it is dropped |
/// | `faults` | none | see [`SharkSemFaults`] |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SharkSemSimConfig {
    pub endpoint: SimEndpoint,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_port: Option<u16>,
    pub version: String,
    pub sw_version: String,
    pub device: String,
    pub model: String,
    pub firewall_friendly: bool,
    pub tilt_y: bool,
    pub detectors: Vec<String>,
    pub channels: u32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub view_field_mm: Option<f64>,
    pub view_field_min_mm: f64,
    pub view_field_max_mm: f64,
    pub speeds_us: Vec<f64>,
    pub speed_index: u32,
    pub z_mm: f64,
    pub chunk_interval_s: f64,
    pub data_stall_s: f64,
    pub faults: SharkSemFaults,
}

/// Faults of the SharkSEM dialect, each one a failure the protocol documents.
/// The stage's `ignore_move` fault (`[simulator.stage.faults]`) applies to
/// `StgMoveTo` too: it is the same stage model.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SharkSemFaults {
    /// The `ScData` chunk is never sent (counted in chunks, all scans).
    pub lose_chunk: FaultTrigger,
    /// The `ScData` chunk is sent twice (counted in chunks).
    pub resend_chunk: FaultTrigger,
    /// `SetViewField` is ignored silently (counted in `SetViewField` requests).
    pub ignore_view_field: FaultTrigger,
    /// After this many requests (all clients), the server closes the client's connections (once).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub disconnect_after_requests: Option<u64>,
    /// From this request on (all clients) the server never answers anything again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub silent_after_requests: Option<u64>,
}

impl Default for SharkSemSimConfig {
    fn default() -> Self {
        Self {
            endpoint: SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], 0))),
            data_port: None,
            version: "2.0.25".into(),
            sw_version: format!("sdsem-sim {}", env!("CARGO_PKG_VERSION")),
            device: "SDSEMSIM0001".into(),
            model: "sdsem-sim virtual TESCAN SEM".into(),
            firewall_friendly: false,
            tilt_y: false,
            detectors: vec!["SE".into(), "BSE".into()],
            channels: 2,
            view_field_mm: None,
            view_field_min_mm: 0.0005,
            view_field_max_mm: 20.0,
            speeds_us: vec![0.1, 0.32, 1.0, 3.2, 10.0, 32.0, 100.0],
            speed_index: 3,
            z_mm: 10.0,
            chunk_interval_s: 0.05,
            data_stall_s: 10.0,
            faults: SharkSemFaults::default(),
        }
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> SimError {
    SimError::Config {
        field,
        reason: reason.into(),
    }
}

impl SharkSemSimConfig {
    /// The protocol version served.
    #[must_use]
    pub fn protocol_version(&self) -> Version {
        Version::parse(&self.version).unwrap_or(Version(2, 0, 25))
    }

    /// Checks every value, naming the first wrong field.
    ///
    /// # Errors
    /// [`SimError::Config`].
    pub fn validate(&self) -> Result<(), SimError> {
        if self.endpoint == SimEndpoint::Pty {
            return Err(invalid(
                "sharksem.endpoint",
                "SharkSEM is TCP only: write tcp://IP:PORT, e.g. tcp://127.0.0.1:8300",
            ));
        }
        if Version::parse(&self.version).is_none() {
            return Err(invalid(
                "sharksem.version",
                "expected a version such as 2.0.25",
            ));
        }
        for (field, v) in [
            ("sharksem.sw_version", &self.sw_version),
            ("sharksem.device", &self.device),
            ("sharksem.model", &self.model),
        ] {
            if v.contains(['\0', '\n']) {
                return Err(invalid(field, "must be one line without NUL"));
            }
        }
        if self.detectors.is_empty()
            || self
                .detectors
                .iter()
                .any(|d| d.trim().is_empty() || d.contains(['\n', '=']))
        {
            return Err(invalid(
                "sharksem.detectors",
                "one or more names without '=' or line breaks",
            ));
        }
        if self.channels == 0 || self.channels > 16 {
            return Err(invalid("sharksem.channels", "1 to 16"));
        }
        let (lo, hi) = (self.view_field_min_mm, self.view_field_max_mm);
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo < hi) {
            return Err(invalid("sharksem.view_field_*_mm", "0 < min < max, finite"));
        }
        if let Some(v) = self.view_field_mm
            && !(lo..=hi).contains(&v)
        {
            return Err(invalid(
                "sharksem.view_field_mm",
                format!("inside [{lo}, {hi}]"),
            ));
        }
        if self.speeds_us.is_empty() || self.speeds_us.iter().any(|s| !(s.is_finite() && *s > 0.0))
        {
            return Err(invalid(
                "sharksem.speeds_us",
                "one or more positive dwell times, µs",
            ));
        }
        if self.speed_index == 0 || self.speed_index as usize > self.speeds_us.len() {
            return Err(invalid(
                "sharksem.speed_index",
                "1 to the number of speeds_us",
            ));
        }
        if !self.z_mm.is_finite() {
            return Err(invalid("sharksem.z_mm", "a finite number"));
        }
        for (field, v) in [
            ("sharksem.chunk_interval_s", self.chunk_interval_s),
            ("sharksem.data_stall_s", self.data_stall_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(field, format!("must be positive, got {v}")));
            }
        }
        for (field, t) in [
            ("sharksem.faults.lose_chunk", &self.faults.lose_chunk),
            ("sharksem.faults.resend_chunk", &self.faults.resend_chunk),
            (
                "sharksem.faults.ignore_view_field",
                &self.faults.ignore_view_field,
            ),
        ] {
            if !(0.0..=1.0).contains(&t.probability) {
                return Err(invalid(
                    field,
                    format!("probability {} outside 0…1", t.probability),
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_mistakes_are_named() {
        SharkSemSimConfig::default().validate().unwrap();
        let c: SharkSemSimConfig = toml::from_str(
            "version = \"3.2.20\"\ntilt_y = true\n[faults]\nlose_chunk = { at = [3] }\n",
        )
        .unwrap();
        assert_eq!(c.protocol_version(), Version(3, 2, 20));
        assert_eq!(c.faults.lose_chunk.at, [3]);
        assert_eq!(c.channels, 2);
        for (bad, field) in [
            ("endpoint = \"pty\"", "sharksem.endpoint"),
            ("version = \"x\"", "sharksem.version"),
            ("speed_index = 9", "sharksem.speed_index"),
            ("view_field_min_mm = 0", "view_field"),
            ("detectors = []", "sharksem.detectors"),
        ] {
            let c: SharkSemSimConfig = toml::from_str(bad).unwrap();
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(field), "{bad}: {e}");
        }
        assert!(toml::from_str::<SharkSemSimConfig>("chunk_ms = 3").is_err());
    }
}
