//! Simulator configuration: serde structs with documented defaults, so `sdsem`'s
//! configuration file can embed them under `[simulator]`.

use std::fmt;
use std::net::SocketAddr;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use sdsem_protocol::gcs::AxisId;

use crate::SimError;

/// Everything the simulator needs. The SEM imaging part adds its own table beside `stage`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of every random choice (fault probabilities, which byte a garbled reply
    /// loses): the same seed and the same commands give the same behaviour. Default 0.
    pub seed: u64,
    /// Real seconds per simulated second: 0.01 makes motion and settling 100×
    /// faster than real time; 1 is real time. Default 1.
    pub time_scale: f64,
    /// The simulated stage controller.
    pub stage: StageSimConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            time_scale: 1.0,
            stage: StageSimConfig::default(),
        }
    }
}

/// Where a simulated instrument listens.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum SimEndpoint {
    /// `tcp://IP:PORT`; port 0 picks a free port (the bound address is reported).
    Tcp(SocketAddr),
    /// `pty`: a pseudo-terminal; its slave device path is reported.
    Pty,
}

impl FromStr for SimEndpoint {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s == "pty" {
            return Ok(Self::Pty);
        }
        let addr = s.strip_prefix("tcp://").ok_or_else(|| {
            format!("endpoint {s:?} is neither `pty` nor `tcp://IP:PORT` (e.g. tcp://127.0.0.1:0)")
        })?;
        addr.parse::<SocketAddr>().map(Self::Tcp).map_err(|e| {
            format!("endpoint {s:?}: {e}; write an IP address and port, e.g. tcp://127.0.0.1:0")
        })
    }
}

impl TryFrom<String> for SimEndpoint {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<SimEndpoint> for String {
    fn from(e: SimEndpoint) -> Self {
        e.to_string()
    }
}

impl fmt::Display for SimEndpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Tcp(addr) => write!(f, "tcp://{addr}"),
            Self::Pty => f.write_str("pty"),
        }
    }
}

/// The simulated PI GCS stage controller: axes X, Y (specimen translation, µm)
/// and T (tilt, degrees).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StageSimConfig {
    /// Where the controller listens. Default `tcp://127.0.0.1:0`.
    pub endpoint: SimEndpoint,
    /// Answer to `*IDN?`.
    pub idn: String,
    /// GCS identifier of the X axis. Default `X` (real stages often use `1`).
    pub axis_x: AxisId,
    /// GCS identifier of the Y axis. Default `Y`.
    pub axis_y: AxisId,
    /// GCS identifier of the tilt axis. Default `T`.
    pub axis_tilt: AxisId,
    /// Start with every axis referenced (`FRF?` = 1). A real controller starts
    /// unreferenced; the default `true` keeps the normal simulated run simple.
    pub referenced: bool,
    /// Start with the servo on (`SVO?` = 1). Default `true`.
    pub servo_on: bool,
    /// Low soft limit of X and Y, µm. Default −5000.
    pub xy_min_um: f64,
    /// High soft limit of X and Y, µm. Default 5000.
    pub xy_max_um: f64,
    /// Low soft limit of the tilt, degrees. Default −5.
    pub tilt_min_deg: f64,
    /// High soft limit of the tilt, degrees. Default 70.
    pub tilt_max_deg: f64,
    /// Speed of X and Y, µm per simulated second. Default 100.
    pub xy_speed_um_s: f64,
    /// Tilt speed, degrees per simulated second. Default 1.
    pub tilt_speed_deg_s: f64,
    /// Time after the end of a motion before `ONT?` answers 1, simulated seconds. Default 0.2.
    pub settle_s: f64,
    /// Initial X, µm. Default 0.
    pub start_x_um: f64,
    /// Initial Y, µm. Default 0.
    pub start_y_um: f64,
    /// Initial tilt, degrees. Default 0.
    pub start_tilt_deg: f64,
    /// Faults injected on demand. Default: none.
    pub faults: FaultConfig,
}

fn axis(name: &str) -> AxisId {
    AxisId::new(name).unwrap_or_else(|e| unreachable!("built-in axis name: {e}"))
}

impl Default for StageSimConfig {
    fn default() -> Self {
        Self {
            endpoint: SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], 0))),
            idn: format!(
                "sdsem-sim, simulated PI GCS 2.0 stage controller, SN 0, {}",
                env!("CARGO_PKG_VERSION")
            ),
            axis_x: axis("X"),
            axis_y: axis("Y"),
            axis_tilt: axis("T"),
            referenced: true,
            servo_on: true,
            xy_min_um: -5000.0,
            xy_max_um: 5000.0,
            tilt_min_deg: -5.0,
            tilt_max_deg: 70.0,
            xy_speed_um_s: 100.0,
            tilt_speed_deg_s: 1.0,
            settle_s: 0.2,
            start_x_um: 0.0,
            start_y_um: 0.0,
            start_tilt_deg: 0.0,
            faults: FaultConfig::default(),
        }
    }
}

/// When a fault fires: at listed occurrences, and/or at random with a probability.
///
/// Occurrences count from 1: commands received (all links together) for reply
/// faults, accepted `MOV`/`MVR` commands for move faults.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FaultTrigger {
    /// Occurrences at which the fault fires, e.g. `[3, 10]`. Default none.
    pub at: Vec<u64>,
    /// Probability of firing at any other occurrence, 0…1 (seeded). Default 0.
    pub probability: f64,
}

impl FaultTrigger {
    /// Fires at these occurrences only.
    pub fn at(occurrences: impl Into<Vec<u64>>) -> Self {
        Self {
            at: occurrences.into(),
            probability: 0.0,
        }
    }

    /// Fires at random with this probability.
    pub fn probability(p: f64) -> Self {
        Self {
            at: Vec::new(),
            probability: p,
        }
    }

    /// Whether the trigger can ever fire.
    pub fn is_armed(&self) -> bool {
        !self.at.is_empty() || self.probability > 0.0
    }
}

/// Faults on demand, each one a failure real stages show (DESIGN §7).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FaultConfig {
    /// The reply to a query is lost (counted in commands).
    pub drop_reply: FaultTrigger,
    /// One byte of the reply is replaced by garbage (counted in commands).
    pub garble_reply: FaultTrigger,
    /// The reply comes `late_reply_delay_s` late (counted in commands).
    pub late_reply: FaultTrigger,
    /// Delay of a late reply, REAL seconds (a link property, not scaled by
    /// `time_scale`). Default 2.
    pub late_reply_delay_s: f64,
    /// The move is accepted without error but does not happen (counted in moves).
    pub ignore_move: FaultTrigger,
    /// After the move starts, `ONT?` says 1 and `#5` says "not moving" for
    /// `stale_on_target_s` although the axis moves (counted in moves).
    pub stale_on_target: FaultTrigger,
    /// Duration of a stale on-target flag, simulated seconds. Default 0.5.
    pub stale_on_target_s: f64,
    /// The move is refused with `move_error_code` (counted in moves).
    pub move_error: FaultTrigger,
    /// Error code set by `move_error`. Default 1024 (motion error; as on PI
    /// controllers it also switches the servo of the moved axes off).
    pub move_error_code: i32,
    /// Close the link after this many commands (once). Default: never.
    pub disconnect_after_commands: Option<u64>,
}

impl Default for FaultConfig {
    fn default() -> Self {
        Self {
            drop_reply: FaultTrigger::default(),
            garble_reply: FaultTrigger::default(),
            late_reply: FaultTrigger::default(),
            late_reply_delay_s: 2.0,
            ignore_move: FaultTrigger::default(),
            stale_on_target: FaultTrigger::default(),
            stale_on_target_s: 0.5,
            move_error: FaultTrigger::default(),
            move_error_code: 1024,
            disconnect_after_commands: None,
        }
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> SimError {
    SimError::Config {
        field,
        reason: reason.into(),
    }
}

fn positive(field: &'static str, v: f64) -> Result<(), SimError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(invalid(
            field,
            format!("must be a positive number, got {v}"),
        ))
    }
}

fn range(field: &'static str, min: f64, max: f64, start: f64) -> Result<(), SimError> {
    if !(min.is_finite() && max.is_finite() && min < max) {
        return Err(invalid(
            field,
            format!("limits [{min}, {max}] must be finite with min < max"),
        ));
    }
    if !(min..=max).contains(&start) {
        return Err(invalid(
            field,
            format!("start {start} outside the limits [{min}, {max}]"),
        ));
    }
    Ok(())
}

impl SimConfig {
    /// Checks every value, naming the first wrong field.
    pub fn validate(&self) -> Result<(), SimError> {
        positive("time_scale", self.time_scale)?;
        self.stage.validate()
    }
}

impl StageSimConfig {
    /// Checks every value, naming the first wrong field.
    pub fn validate(&self) -> Result<(), SimError> {
        let s = self;
        if s.axis_x == s.axis_y || s.axis_x == s.axis_tilt || s.axis_y == s.axis_tilt {
            return Err(invalid(
                "stage.axis_*",
                "the three axis identifiers must differ",
            ));
        }
        range("stage.xy_*_um (X)", s.xy_min_um, s.xy_max_um, s.start_x_um)?;
        range("stage.xy_*_um (Y)", s.xy_min_um, s.xy_max_um, s.start_y_um)?;
        range(
            "stage.tilt_*_deg",
            s.tilt_min_deg,
            s.tilt_max_deg,
            s.start_tilt_deg,
        )?;
        positive("stage.xy_speed_um_s", s.xy_speed_um_s)?;
        positive("stage.tilt_speed_deg_s", s.tilt_speed_deg_s)?;
        if !(s.settle_s.is_finite() && s.settle_s >= 0.0) {
            return Err(invalid("stage.settle_s", "must be ≥ 0"));
        }
        if s.idn.trim().is_empty() || s.idn.contains(['\n', '\r']) {
            return Err(invalid("stage.idn", "must be one non-empty line"));
        }
        s.faults.validate()
    }
}

impl FaultConfig {
    /// Checks probabilities and durations.
    pub fn validate(&self) -> Result<(), SimError> {
        for (field, t) in [
            ("stage.faults.drop_reply", &self.drop_reply),
            ("stage.faults.garble_reply", &self.garble_reply),
            ("stage.faults.late_reply", &self.late_reply),
            ("stage.faults.ignore_move", &self.ignore_move),
            ("stage.faults.stale_on_target", &self.stale_on_target),
            ("stage.faults.move_error", &self.move_error),
        ] {
            if !(0.0..=1.0).contains(&t.probability) {
                return Err(invalid(
                    field,
                    format!("probability {} outside 0…1", t.probability),
                ));
            }
        }
        for (field, v) in [
            ("stage.faults.late_reply_delay_s", self.late_reply_delay_s),
            ("stage.faults.stale_on_target_s", self.stale_on_target_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(invalid(field, format!("must be ≥ 0, got {v}")));
            }
        }
        if self.move_error.is_armed() && self.move_error_code == 0 {
            return Err(invalid("stage.faults.move_error_code", "0 means no error"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_round_trip_through_json() {
        let c = SimConfig::default();
        c.validate().unwrap();
        let json = serde_json::to_string(&c).unwrap();
        assert!(
            json.contains("\"endpoint\":\"tcp://127.0.0.1:0\""),
            "{json}"
        );
        let back: SimConfig = serde_json::from_str(&json).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn partial_tables_keep_the_other_defaults() {
        let c: SimConfig = serde_json::from_str(
            r#"{"time_scale": 0.01, "stage": {"tilt_max_deg": 60, "endpoint": "pty",
                "faults": {"drop_reply": {"at": [3]}}}}"#,
        )
        .unwrap();
        assert_eq!(c.time_scale, 0.01);
        assert_eq!(c.stage.tilt_max_deg, 60.0);
        assert_eq!(c.stage.tilt_min_deg, -5.0);
        assert_eq!(c.stage.endpoint, SimEndpoint::Pty);
        assert_eq!(c.stage.faults.drop_reply.at, vec![3]);
        assert_eq!(c.stage.faults.late_reply_delay_s, 2.0);
    }

    #[test]
    fn unknown_keys_are_refused() {
        assert!(serde_json::from_str::<SimConfig>(r#"{"stage": {"tilt_maxx": 3}}"#).is_err());
        assert!(
            serde_json::from_str::<SimConfig>(r#"{"stage": {"endpoint": "udp://x"}}"#).is_err()
        );
    }

    #[test]
    fn validation_names_the_wrong_field() {
        let mut c = SimConfig::default();
        c.stage.tilt_min_deg = 80.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("tilt"), "{e}");
        let c = SimConfig {
            time_scale: 0.0,
            ..SimConfig::default()
        };
        assert!(c.validate().unwrap_err().to_string().contains("time_scale"));
        let mut c = SimConfig::default();
        c.stage.faults.garble_reply.probability = 1.5;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("garble_reply")
        );
        let mut c = SimConfig::default();
        c.stage.axis_y = c.stage.axis_x.clone();
        assert!(c.validate().is_err());
    }
}
