//! Settings of the SEM imaging: which source (the sdsem imaging link or a watched folder) and how to scan.

use std::path::PathBuf;
use std::time::Duration;

use sdsem_protocol::sem::{Bits, GrabRequest, Role};
use serde::{Deserialize, Serialize};

use super::ImagingError;

/// Default TCP port of the SEM imaging server (the simulator listens here).
pub const DEFAULT_PORT: u16 = 7520;

/// Size and dwell of one kind of scan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanSettings {
    pub width: u32,
    pub height: u32,
    /// Pixel dwell, µs: longer is less noisy and slower (width × height × dwell).
    pub dwell_us: f64,
}

/// Where frames come from (`imaging.protocol`, DESIGN §7b).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ImagingProtocol {
    /// sdsem's own imaging line protocol over TCP ([`sdsem_protocol::sem`]): sdsem-sim or an adapter.
    #[default]
    SdsemLink,
    /// The SEM's software stores each micrograph as a TIFF in a folder sdsem reads (VENDORS §4).
    WatchFolder,
    /// TESCAN SharkSEM remote control ([`crate::imaging::SharkSemSource`]).
    Sharksem,
}

impl ImagingProtocol {
    /// The name as written in the configuration.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::SdsemLink => "sdsem-link",
            Self::WatchFolder => "watch-folder",
            Self::Sharksem => "sharksem",
        }
    }
}

/// How to reach the SEM and how to scan.
///
/// | key | default | effect |
/// | --- | --- | --- |
/// | `protocol` | `sdsem-link` | where frames come from: `sdsem-link` (TCP), `watch-folder` (TIFFs the SEM stores) or `sharksem` (TESCAN) |
/// | `endpoint` | `127.0.0.1:7520` | host:port of the imaging server (sdsem-sim's); sharksem: `tcp://HOST:8300`, the control port |
/// | `data_port` | none | sharksem: the data port; none = control port + 1 |
/// | `detector` | `""` | sharksem: detector name (`SE`, case-insensitive) or id (`DtEnumDetectors`); empty = the first listed |
/// | `pixel_size_um` | none | sharksem: pixel size, set as view field = pixel size × width; none = keep the SEM's field, read back |
/// | `micrograph` | 1280 × 960, 10 µs | the left and right micrographs (12.3 s per frame) |
/// | `tracking` | 320 × 240, 1 µs | the quick frame after each tilt step (77 ms) |
/// | `bits` | 16 | sample depth, 8 or 16 |
/// | `timeout_ms` | 5000 | connecting, and waiting for a reply beyond the scan time itself |
/// | `watch_dir` | "" | watch-folder: the folder the SEM stores its micrographs in |
/// | `trigger` | "" | watch-folder: command sent over the stage link to store one micrograph ("" = wait) |
/// | `tracking_trigger` | "" | watch-folder: the command for a tracking frame, e.g. `MAC 1` running a macro that stores a small, fast frame ("" = `trigger`) |
/// | `watch_patterns` | `*.tif`, `*.tiff` | watch-folder: names of micrographs (case-insensitive) |
/// | `watch_ignore` | `~*`, `.*`, `*.tmp`, `*.part` | watch-folder: temporary names never read |
/// | `watch_sidecar` | "" | watch-folder: extension of a metadata file beside each image (`txt`: Hitachi, JEOL) |
/// | `watch_poll_ms` | 250 | watch-folder: interval between folder listings |
/// | `watch_stable_ms` | 2000 | watch-folder: size and mtime unchanged this long before a file is read |
/// | `watch_stable_polls` | 3 | watch-folder: …and over at least this many listings |
/// | `watch_timeout_s` | 300 | watch-folder: longest wait for one new micrograph |
/// | `watch_max_file_mb` | 1024 | watch-folder: larger files are never read |
/// | `watch_check_tilt` | true | watch-folder: compare the tilt a file records with the stage's (false for a tilt stage the SEM does not know) |
/// | `tilt_tolerance_deg` | 0.5 | watch-folder: a file recording a tilt this far from the stage's is refused |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImagingConfig {
    pub protocol: ImagingProtocol,
    pub endpoint: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub data_port: Option<u16>,
    pub detector: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pixel_size_um: Option<f64>,
    pub micrograph: ScanSettings,
    pub tracking: ScanSettings,
    pub bits: u8,
    pub timeout_ms: u64,
    pub watch_dir: PathBuf,
    pub trigger: String,
    pub tracking_trigger: String,
    pub watch_patterns: Vec<String>,
    pub watch_ignore: Vec<String>,
    pub watch_sidecar: String,
    pub watch_poll_ms: u64,
    pub watch_stable_ms: u64,
    pub watch_stable_polls: u32,
    pub watch_timeout_s: f64,
    pub watch_max_file_mb: u64,
    pub watch_check_tilt: bool,
    pub tilt_tolerance_deg: f64,
}

impl Default for ImagingConfig {
    fn default() -> Self {
        Self {
            protocol: ImagingProtocol::SdsemLink,
            endpoint: format!("127.0.0.1:{DEFAULT_PORT}"),
            data_port: None,
            detector: String::new(),
            pixel_size_um: None,
            micrograph: ScanSettings {
                width: 1280,
                height: 960,
                dwell_us: 10.0,
            },
            tracking: ScanSettings {
                width: 320,
                height: 240,
                dwell_us: 1.0,
            },
            bits: 16,
            timeout_ms: 5000,
            watch_dir: PathBuf::new(),
            trigger: String::new(),
            tracking_trigger: String::new(),
            watch_patterns: vec!["*.tif".into(), "*.tiff".into()],
            watch_ignore: vec!["~*".into(), ".*".into(), "*.tmp".into(), "*.part".into()],
            watch_sidecar: String::new(),
            watch_poll_ms: 250,
            watch_stable_ms: 2000,
            watch_stable_polls: 3,
            watch_timeout_s: 300.0,
            watch_max_file_mb: 1024,
            watch_check_tilt: true,
            tilt_tolerance_deg: 0.5,
        }
    }
}

impl ImagingConfig {
    /// Checks every setting.
    ///
    /// # Errors
    /// [`ImagingError::InvalidConfig`] naming the setting and what it should be.
    pub fn validate(&self) -> Result<(), ImagingError> {
        let invalid = |name: &'static str, value: String, expected: &'static str| {
            ImagingError::InvalidConfig {
                name,
                value,
                expected,
            }
        };
        if self.protocol == ImagingProtocol::SdsemLink
            && (self.address().is_empty() || !self.address().contains(':'))
        {
            return Err(invalid(
                "imaging.endpoint",
                self.endpoint.clone(),
                "host:port or tcp://host:port",
            ));
        }
        for (name, s) in [
            ("imaging.micrograph", &self.micrograph),
            ("imaging.tracking", &self.tracking),
        ] {
            let max = sdsem_protocol::sem::MAX_SIDE;
            if !(1..=max).contains(&s.width) || !(1..=max).contains(&s.height) {
                return Err(invalid(
                    name,
                    format!("{}×{}", s.width, s.height),
                    "width and height from 1 to 16384",
                ));
            }
            if !(s.dwell_us > 0.0 && s.dwell_us <= sdsem_protocol::sem::MAX_DWELL_US) {
                return Err(invalid(
                    name,
                    format!("dwell_us {}", s.dwell_us),
                    "dwell_us in (0, 10000]",
                ));
            }
        }
        if self.bits != 8 && self.bits != 16 {
            return Err(invalid("imaging.bits", self.bits.to_string(), "8 or 16"));
        }
        if self.data_port == Some(0) {
            return Err(invalid(
                "imaging.data_port",
                "0".to_owned(),
                "a port number 1–65535 (or no key: control port + 1)",
            ));
        }
        if let Some(p) = self.pixel_size_um
            && !(p.is_finite() && p > 0.0)
        {
            return Err(invalid(
                "imaging.pixel_size_um",
                p.to_string(),
                "a positive number of micrometres (or no key: keep the SEM's field)",
            ));
        }
        if self.timeout_ms == 0 {
            return Err(invalid(
                "imaging.timeout_ms",
                "0".to_owned(),
                "a positive number of milliseconds",
            ));
        }
        if self.protocol == ImagingProtocol::WatchFolder {
            self.validate_watch()?;
        }
        Ok(())
    }

    /// The watch-folder keys, checked only when that source is chosen.
    fn validate_watch(&self) -> Result<(), ImagingError> {
        let invalid = |name: &'static str, value: String, expected: &'static str| {
            ImagingError::InvalidConfig {
                name,
                value,
                expected,
            }
        };
        if self.watch_dir.as_os_str().is_empty() {
            return Err(invalid(
                "imaging.watch_dir",
                String::new(),
                "the folder the SEM stores its micrographs in (imaging.protocol = \"watch-folder\")",
            ));
        }
        if self.watch_patterns.iter().all(|p| p.trim().is_empty()) {
            return Err(invalid(
                "imaging.watch_patterns",
                format!("{:?}", self.watch_patterns),
                "at least one file name pattern, e.g. [\"*.tif\"]",
            ));
        }
        if self.watch_sidecar.contains(['.', '/', '\\', '*']) {
            return Err(invalid(
                "imaging.watch_sidecar",
                self.watch_sidecar.clone(),
                "an extension without dot, e.g. \"txt\", or \"\"",
            ));
        }
        if self.watch_poll_ms == 0 {
            return Err(invalid(
                "imaging.watch_poll_ms",
                "0".to_owned(),
                "a positive number of milliseconds",
            ));
        }
        if self.watch_stable_polls < 2 {
            return Err(invalid(
                "imaging.watch_stable_polls",
                self.watch_stable_polls.to_string(),
                "2 or more (a file must be seen unchanged at least twice)",
            ));
        }
        if !(self.watch_timeout_s.is_finite() && self.watch_timeout_s > 0.0) {
            return Err(invalid(
                "imaging.watch_timeout_s",
                self.watch_timeout_s.to_string(),
                "a positive number of seconds",
            ));
        }
        if self.watch_max_file_mb == 0 {
            return Err(invalid(
                "imaging.watch_max_file_mb",
                "0".to_owned(),
                "a positive number of MiB",
            ));
        }
        if !(self.tilt_tolerance_deg.is_finite() && self.tilt_tolerance_deg > 0.0) {
            return Err(invalid(
                "imaging.tilt_tolerance_deg",
                self.tilt_tolerance_deg.to_string(),
                "a positive number of degrees",
            ));
        }
        Ok(())
    }

    /// The settings the connection depends on: all but the per-scan ones (sizes, dwell, depth),
    /// so a reloaded configuration that changes the source or how it is reached reconnects.
    /// SharkSEM keeps the micrograph width: its view field is pixel size × that width.
    #[must_use]
    pub fn link_settings(&self) -> Self {
        let d = Self::default();
        let mut micrograph = d.micrograph;
        if self.protocol == ImagingProtocol::Sharksem {
            micrograph.width = self.micrograph.width;
        }
        Self {
            micrograph,
            tracking: d.tracking,
            bits: d.bits,
            ..self.clone()
        }
    }

    /// The scan request for a frame of `role`: micrograph settings for left and
    /// right, tracking settings for tracking.
    #[must_use]
    pub fn request(&self, role: Role) -> GrabRequest {
        let s = match role {
            Role::Tracking => &self.tracking,
            Role::Left | Role::Right => &self.micrograph,
        };
        GrabRequest {
            width: s.width,
            height: s.height,
            dwell_us: s.dwell_us,
            role,
            bits: if self.bits == 8 {
                Bits::Eight
            } else {
                Bits::Sixteen
            },
        }
    }

    /// The watch-folder trigger for a frame of `role`: `tracking_trigger` for tracking frames
    /// when set, else `trigger`; trimmed, "" when none.
    #[must_use]
    pub fn trigger_for(&self, role: Role) -> &str {
        let tracking = self.tracking_trigger.trim();
        if role == Role::Tracking && !tracking.is_empty() {
            tracking
        } else {
            self.trigger.trim()
        }
    }

    /// Every trigger command configured (micrograph, then tracking), without empty ones.
    #[must_use]
    pub fn triggers(&self) -> Vec<&str> {
        let mut all = Vec::new();
        for t in [self.trigger.trim(), self.tracking_trigger.trim()] {
            if !t.is_empty() && !all.contains(&t) {
                all.push(t);
            }
        }
        all
    }

    /// The `host:port` to connect to: `endpoint` without an optional `tcp://`
    /// (the form `sdsem-sim` prints).
    #[must_use]
    pub fn address(&self) -> &str {
        let e = self.endpoint.trim();
        e.strip_prefix("tcp://").unwrap_or(e)
    }

    /// [`Self::timeout_ms`] as a duration.
    #[must_use]
    pub fn timeout(&self) -> Duration {
        Duration::from_millis(self.timeout_ms)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_follow_the_role() {
        let c = ImagingConfig::default();
        assert_eq!(c.request(Role::Left).width, 1280);
        assert_eq!(c.request(Role::Tracking).width, 320);
        assert_eq!(c.request(Role::Right).bits, Bits::Sixteen);
        c.validate().unwrap();
    }

    #[test]
    fn invalid_settings_are_named() {
        let c = ImagingConfig {
            bits: 12,
            ..ImagingConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("imaging.bits")
        );
        let c = ImagingConfig {
            endpoint: "localhost".to_owned(),
            ..ImagingConfig::default()
        };
        assert!(c.validate().unwrap_err().to_string().contains("host:port"));
        let mut c = ImagingConfig::default();
        c.tracking.dwell_us = 0.0;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("imaging.tracking")
        );
    }

    #[test]
    fn tracking_frames_take_their_own_trigger_when_set() {
        let mut c = ImagingConfig {
            trigger: " FREC ".into(),
            ..ImagingConfig::default()
        };
        assert_eq!(c.trigger_for(Role::Tracking), "FREC");
        assert_eq!(c.triggers(), ["FREC"]);
        c.tracking_trigger = "MAC 1".into();
        assert_eq!(c.trigger_for(Role::Tracking), "MAC 1");
        assert_eq!(c.trigger_for(Role::Left), "FREC");
        assert_eq!(c.triggers(), ["FREC", "MAC 1"]);
        c.trigger.clear();
        assert_eq!(c.trigger_for(Role::Right), "");
        assert_eq!(c.triggers(), ["MAC 1"]);
    }

    #[test]
    fn partial_config_takes_defaults_and_unknown_keys_fail() {
        let c: ImagingConfig = serde_json::from_str(r#"{"endpoint":"10.0.0.5:9000"}"#).unwrap();
        assert_eq!(c.tracking.dwell_us, 1.0);
        assert!(serde_json::from_str::<ImagingConfig>(r#"{"endpont":"x:1"}"#).is_err());
    }
}
