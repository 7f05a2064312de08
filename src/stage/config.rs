//! Stage driver configuration (`[stage]` in sdsem's configuration file).

use std::fmt;
use std::time::Duration;

use sdsem_protocol::gcs::AxisId;
use serde::{Deserialize, Serialize};

use super::error::StageError;

/// Which stage axis, by role.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageAxis {
    /// Specimen translation X, µm.
    X,
    /// Specimen translation Y, µm.
    Y,
    /// Tilt, degrees.
    Tilt,
}

impl StageAxis {
    /// All three, in the order the driver queries them.
    pub const ALL: [Self; 3] = [Self::X, Self::Y, Self::Tilt];

    /// The configuration fields holding the limits of this axis.
    pub fn limit_fields(self) -> &'static str {
        match self {
            Self::X | Self::Y => "stage.xy_min_um/xy_max_um",
            Self::Tilt => "stage.tilt_min_deg/tilt_max_deg",
        }
    }

    /// The configuration field holding the tolerance of this axis.
    pub fn tolerance_field(self) -> &'static str {
        match self {
            Self::X | Self::Y => "stage.xy_tolerance_um",
            Self::Tilt => "stage.tilt_tolerance_deg",
        }
    }

    /// The configuration field holding the expected speed of this axis.
    pub fn speed_field(self) -> &'static str {
        match self {
            Self::X | Self::Y => "stage.xy_speed_um_s",
            Self::Tilt => "stage.tilt_speed_deg_s",
        }
    }

    /// The unit of the axis.
    pub fn unit(self) -> &'static str {
        match self {
            Self::X | Self::Y => "µm",
            Self::Tilt => "°",
        }
    }
}

impl fmt::Display for StageAxis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::X => "x",
            Self::Y => "y",
            Self::Tilt => "tilt",
        })
    }
}

/// Which language the stage speaks (`stage.protocol`, DESIGN §7b).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum StageProtocol {
    /// PI GCS 2.0 (an aftermarket stage controller). The default.
    #[default]
    #[serde(rename = "pi-gcs")]
    PiGcs,
    /// Zeiss SmartSEM RemCon32 (the SEM's own stage, RS-232).
    #[serde(rename = "remcon32")]
    Remcon32,
    /// The SEM's own stage over TESCAN SharkSEM (TCP, `tcp://HOST:8300`).
    #[serde(rename = "sharksem")]
    Sharksem,
}

impl StageProtocol {
    /// The name as written in the configuration.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::PiGcs => "pi-gcs",
            Self::Remcon32 => "remcon32",
            Self::Sharksem => "sharksem",
        }
    }

    /// The usual serial rate of the protocol: 115200 for PI controllers,
    /// 9600 for RemCon32 [SF, SF-old, ML]; none for SharkSEM, which runs over TCP only.
    pub fn default_baud(self) -> Option<u32> {
        match self {
            Self::PiGcs => Some(115_200),
            Self::Remcon32 => Some(9_600),
            Self::Sharksem => None,
        }
    }
}

impl From<sdsem_sim::SimStageProtocol> for StageProtocol {
    /// The protocol a simulated stage speaks.
    fn from(p: sdsem_sim::SimStageProtocol) -> Self {
        match p {
            sdsem_sim::SimStageProtocol::PiGcs => Self::PiGcs,
            sdsem_sim::SimStageProtocol::Remcon32 => Self::Remcon32,
        }
    }
}

impl fmt::Display for StageProtocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How to reach and drive the stage controller. Every field has a documented
/// default; durations are seconds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StageConfig {
    /// The stage's language: `pi-gcs` (the default), `remcon32` (a Zeiss SEM's own stage) or
    /// `sharksem` (a TESCAN SEM's own stage).
    pub protocol: StageProtocol,
    /// Where the controller is: a serial device (`/dev/ttyUSB0`,
    /// `/dev/serial/by-id/…`, a simulator's pty path, optionally written
    /// `serial:///dev/ttyUSB0`) or `tcp://HOST:PORT`. Default `/dev/ttyUSB0`.
    pub endpoint: String,
    /// Serial baud rate (ignored for TCP and pseudo-terminals); 0 = the
    /// protocol's usual rate (115200 for pi-gcs, 9600 for remcon32; sharksem has no serial
    /// line). Default 0.
    pub baud: u32,
    /// GCS identifier of the X axis. Default `1` (the simulator uses `X`).
    pub axis_x: AxisId,
    /// GCS identifier of the Y axis. Default `2` (simulator: `Y`).
    pub axis_y: AxisId,
    /// GCS identifier of the tilt axis. Default `3` (simulator: `T`).
    pub axis_tilt: AxisId,
    /// Text the identity must contain (`*IDN?` on PI GCS, e.g. `C-884`; `VER?`
    /// on RemCon32); empty accepts any. Default empty.
    pub expect_idn: String,
    /// Switch servos on and reference (`FRF`) unreferenced axes at connect.
    /// Referencing moves the stage to its reference switches: only enable it
    /// where that travel is safe for the specimen and the column. Default false:
    /// `connect` fails and says what to do.
    pub auto_reference: bool,
    /// Read the controller's soft limits (`TMN?`/`TMX?`) at connect and narrow
    /// the configured limits to them. Default true.
    pub read_controller_limits: bool,
    /// Time to open the connection. Default 5 s.
    pub connect_timeout_s: f64,
    /// Time for one reply to arrive. Default 1 s.
    pub reply_timeout_s: f64,
    /// Extra attempts for a query that timed out or came back garbled (queries
    /// only: commands that move are never re-sent blindly). Default 2.
    pub query_retries: u32,
    /// After a fault, input is discarded until it has been quiet this long. Default 0.05 s.
    pub resync_quiet_s: f64,
    /// Interval between `ONT?` polls while a move runs. Default 0.1 s.
    pub poll_interval_s: f64,
    /// Move timeout = factor × distance / speed + margin. Default factor 3.
    pub move_timeout_factor: f64,
    /// Move timeout margin (settling, acceleration). Default 5 s.
    pub move_timeout_margin_s: f64,
    /// The controller says "on target" yet the position is off target and has
    /// not changed for this long: the move did not happen (re-issued once).
    /// Default 1 s.
    pub no_motion_timeout_s: f64,
    /// Time allowed for referencing (`auto_reference`). Default 120 s.
    pub reference_timeout_s: f64,
    /// A tilt is reached when within this of the target, degrees. Default 0.01.
    pub tilt_tolerance_deg: f64,
    /// X/Y are reached when within this of the target, µm. Default 0.1.
    pub xy_tolerance_um: f64,
    /// Lowest tilt the driver will command, degrees. Default −5.
    pub tilt_min_deg: f64,
    /// Highest tilt the driver will command, degrees. Default 70.
    pub tilt_max_deg: f64,
    /// Lowest X/Y the driver will command, µm. Default −5000.
    pub xy_min_um: f64,
    /// Highest X/Y the driver will command, µm. Default 5000.
    pub xy_max_um: f64,
    /// Expected tilt speed, degrees/s (for move timeouts only). Default 1.
    pub tilt_speed_deg_s: f64,
    /// Expected X/Y speed, µm/s (for move timeouts only). Default 100.
    pub xy_speed_um_s: f64,
    /// Tilt to return to after a run or an abort, degrees. Default 0.
    pub safe_tilt_deg: f64,
    /// remcon32: time after a move command during which a "not moving" flag may be stale (it
    /// is set late; the documentation advises ~1 s [OD-Z]); until then arrival needs two polls
    /// on target with the position unchanged. Default 1 s.
    pub moving_flag_delay_s: f64,
    /// Time for the SEM to finish a watch-folder trigger (`imaging.trigger`,
    /// e.g. `FREC`), which answers only once done. Default 60 s.
    pub trigger_timeout_s: f64,
}

fn axis(name: &str) -> AxisId {
    AxisId::new(name).unwrap_or_else(|e| unreachable!("built-in axis name: {e}"))
}

impl Default for StageConfig {
    fn default() -> Self {
        Self {
            protocol: StageProtocol::PiGcs,
            endpoint: "/dev/ttyUSB0".into(),
            baud: 0,
            axis_x: axis("1"),
            axis_y: axis("2"),
            axis_tilt: axis("3"),
            expect_idn: String::new(),
            auto_reference: false,
            read_controller_limits: true,
            connect_timeout_s: 5.0,
            reply_timeout_s: 1.0,
            query_retries: 2,
            resync_quiet_s: 0.05,
            poll_interval_s: 0.1,
            move_timeout_factor: 3.0,
            move_timeout_margin_s: 5.0,
            no_motion_timeout_s: 1.0,
            reference_timeout_s: 120.0,
            tilt_tolerance_deg: 0.01,
            xy_tolerance_um: 0.1,
            tilt_min_deg: -5.0,
            tilt_max_deg: 70.0,
            xy_min_um: -5000.0,
            xy_max_um: 5000.0,
            tilt_speed_deg_s: 1.0,
            xy_speed_um_s: 100.0,
            safe_tilt_deg: 0.0,
            moving_flag_delay_s: 1.0,
            trigger_timeout_s: 60.0,
        }
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> StageError {
    StageError::Config {
        field,
        reason: reason.into(),
    }
}

/// A duration in seconds from the configuration (validated to be finite and ≥ 0).
pub(crate) fn secs(s: f64) -> Duration {
    Duration::try_from_secs_f64(s.max(0.0)).unwrap_or(Duration::MAX)
}

impl StageConfig {
    /// The serial rate to open the port at: `baud`, or the protocol's usual one (none for a
    /// protocol without a serial line, unless `baud` is set).
    pub fn effective_baud(&self) -> Option<u32> {
        if self.baud == 0 {
            self.protocol.default_baud()
        } else {
            Some(self.baud)
        }
    }

    /// The GCS identifier of an axis.
    pub fn axis_id(&self, axis: StageAxis) -> &AxisId {
        match axis {
            StageAxis::X => &self.axis_x,
            StageAxis::Y => &self.axis_y,
            StageAxis::Tilt => &self.axis_tilt,
        }
    }

    /// The configured limits of an axis, `(min, max)`.
    pub fn limits(&self, axis: StageAxis) -> (f64, f64) {
        match axis {
            StageAxis::X | StageAxis::Y => (self.xy_min_um, self.xy_max_um),
            StageAxis::Tilt => (self.tilt_min_deg, self.tilt_max_deg),
        }
    }

    /// The position tolerance of an axis.
    pub fn tolerance(&self, axis: StageAxis) -> f64 {
        match axis {
            StageAxis::X | StageAxis::Y => self.xy_tolerance_um,
            StageAxis::Tilt => self.tilt_tolerance_deg,
        }
    }

    /// The expected speed of an axis, units per second.
    pub fn speed(&self, axis: StageAxis) -> f64 {
        match axis {
            StageAxis::X | StageAxis::Y => self.xy_speed_um_s,
            StageAxis::Tilt => self.tilt_speed_deg_s,
        }
    }

    /// Checks every value, naming the first wrong field.
    pub fn validate(&self) -> Result<(), StageError> {
        if self.endpoint.trim().is_empty() {
            return Err(invalid(
                "stage.endpoint",
                "empty: give a serial device path or tcp://HOST:PORT",
            ));
        }
        if self.axis_x == self.axis_y
            || self.axis_x == self.axis_tilt
            || self.axis_y == self.axis_tilt
        {
            return Err(invalid(
                "stage.axis_*",
                "the three axis identifiers must differ",
            ));
        }
        for (field, v) in [
            ("stage.connect_timeout_s", self.connect_timeout_s),
            ("stage.reply_timeout_s", self.reply_timeout_s),
            ("stage.poll_interval_s", self.poll_interval_s),
            ("stage.move_timeout_factor", self.move_timeout_factor),
            ("stage.no_motion_timeout_s", self.no_motion_timeout_s),
            ("stage.reference_timeout_s", self.reference_timeout_s),
            ("stage.tilt_tolerance_deg", self.tilt_tolerance_deg),
            ("stage.xy_tolerance_um", self.xy_tolerance_um),
            ("stage.tilt_speed_deg_s", self.tilt_speed_deg_s),
            ("stage.xy_speed_um_s", self.xy_speed_um_s),
            ("stage.trigger_timeout_s", self.trigger_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(
                    field,
                    format!("must be a positive number, got {v}"),
                ));
            }
        }
        for (field, v) in [
            ("stage.resync_quiet_s", self.resync_quiet_s),
            ("stage.move_timeout_margin_s", self.move_timeout_margin_s),
            ("stage.moving_flag_delay_s", self.moving_flag_delay_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(invalid(field, format!("must be ≥ 0, got {v}")));
            }
        }
        for (field, (min, max)) in [
            (
                "stage.tilt_min_deg/tilt_max_deg",
                self.limits(StageAxis::Tilt),
            ),
            ("stage.xy_min_um/xy_max_um", self.limits(StageAxis::X)),
        ] {
            if !(min.is_finite() && max.is_finite() && min < max) {
                return Err(invalid(
                    field,
                    format!("[{min}, {max}] must be finite with min < max"),
                ));
            }
        }
        if !(self.tilt_min_deg..=self.tilt_max_deg).contains(&self.safe_tilt_deg) {
            return Err(invalid(
                "stage.safe_tilt_deg",
                format!(
                    "{} outside the tilt limits [{}, {}]",
                    self.safe_tilt_deg, self.tilt_min_deg, self.tilt_max_deg
                ),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_partial_tables_keep_them() {
        StageConfig::default().validate().unwrap();
        let c: StageConfig = serde_json::from_str(
            r#"{"endpoint": "tcp://127.0.0.1:5000", "axis_tilt": "T", "tilt_max_deg": 60}"#,
        )
        .unwrap();
        assert_eq!(c.axis_tilt.as_str(), "T");
        assert_eq!(c.axis_x.as_str(), "1");
        assert_eq!(c.tilt_max_deg, 60.0);
        assert_eq!(c.tilt_tolerance_deg, 0.01);
        assert!(serde_json::from_str::<StageConfig>(r#"{"tilt_maximum": 3}"#).is_err());
        assert!(serde_json::from_str::<StageConfig>(r#"{"axis_x": "a b"}"#).is_err());
    }

    #[test]
    fn validation_names_the_field() {
        let c = StageConfig {
            safe_tilt_deg: 80.0,
            ..StageConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("safe_tilt_deg")
        );
        let c = StageConfig {
            reply_timeout_s: 0.0,
            ..StageConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("reply_timeout_s")
        );
    }
}
