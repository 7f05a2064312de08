//! Simulator configuration: serde structs with documented defaults, so `sdsem`'s
//! configuration file embeds them as `[simulator]`, `[simulator.stage]`,
//! `[simulator.sem]` (with `[simulator.sem.scene]`, `.optics`, `.walk`,
//! `.shading`, `.noise`).
//!
//! ## Seeds
//! One `simulator.seed` drives everything. Every `seed` left unset below it
//! is derived from its parent's ([`derive_seed`]): `stage.seed` (fault draws)
//! and `sem.seed` from `simulator.seed`; `sem.scene.seed` (the specimen),
//! `sem.walk.seed` (the random walk) and the scan-noise seed from `sem.seed`.
//! Setting one fixes that part whatever its parent is. [`SimConfig::resolved`]
//! fills them all in, so the effective configuration names every seed used.

use std::fmt;
use std::net::SocketAddr;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use sdsem_protocol::gcs::AxisId;

use crate::SimError;
use crate::render::{NoiseParams, OpticsParams, ShadingParams};
use crate::scene::SceneParams;
use crate::scene::noise::mix64;
use crate::walk::WalkParams;

/// Everything the simulator needs: the time base, the seed, and one table per
/// simulated instrument.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `seed` | 0 | seed of every random choice (faults, specimen, walk, scan noise), see the module docs |
/// | `time_scale` | 1 | real seconds per simulated second: 0.01 runs motion, settling and scans 100× faster than real time; 1 is real time |
/// | `stage` | see [`StageSimConfig`] | the stage: PI GCS controller or Zeiss RemCon32 (`stage.protocol`) |
/// | `sem` | see [`SemSimConfig`] | the SEM imaging server |
/// | `folder` | none | the SEM's store folder, see [`crate::FolderSimConfig`] |
/// | `sharksem` | none | when present, the same SEM and stage also speak TESCAN SharkSEM ([`crate::sharksem`]) |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Seed of every random choice: the same seed and the same commands give
    /// the same replies, faults and frames. Default 0.
    pub seed: u64,
    /// Real seconds per simulated second: 0.01 makes motion, settling and
    /// scans 100× faster than real time; 1 is real time. Default 1.
    pub time_scale: f64,
    /// The simulated stage controller.
    pub stage: StageSimConfig,
    /// The simulated SEM's imaging server.
    pub sem: SemSimConfig,
    /// The SEM's store folder, when micrographs are also stored as vendor TIFFs.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub folder: Option<crate::FolderSimConfig>,
    /// The SharkSEM dialect of the same SEM and stage, when present.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sharksem: Option<crate::sharksem::SharkSemSimConfig>,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            seed: 0,
            time_scale: 1.0,
            stage: StageSimConfig::default(),
            sem: SemSimConfig::default(),
            folder: None,
            sharksem: None,
        }
    }
}

/// The seed of the part called `name` under a part seeded `parent`: a
/// well-mixed hash, so that sibling parts never correlate.
#[must_use]
pub fn derive_seed(parent: u64, name: &str) -> u64 {
    // FNV-1a of the name, then SplitMix64 with the parent.
    let tag = name.bytes().fold(0xCBF2_9CE4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01B3)
    });
    mix64(parent ^ mix64(tag))
}

impl SimConfig {
    /// This configuration with every unset seed derived (module docs): what
    /// the simulator runs, and what a record should store.
    #[must_use]
    pub fn resolved(&self) -> Self {
        let mut c = self.clone();
        c.stage
            .seed
            .get_or_insert_with(|| derive_seed(self.seed, "stage"));
        c.sem = self.sem.resolved(self.seed);
        if let Some(folder) = &mut c.folder {
            folder
                .seed
                .get_or_insert_with(|| derive_seed(self.seed, "folder"));
        }
        c
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

/// The language the simulated stage speaks on its link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum SimStageProtocol {
    /// PI GCS 2.0 (an aftermarket stage controller). The default.
    #[default]
    #[serde(rename = "pi-gcs")]
    PiGcs,
    /// Zeiss SmartSEM RemCon32 (the SEM's own stage; [`crate::remcon`]).
    #[serde(rename = "remcon32")]
    Remcon32,
}

impl FromStr for SimStageProtocol {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "pi-gcs" => Ok(Self::PiGcs),
            "remcon32" => Ok(Self::Remcon32),
            _ => Err(format!("stage protocol {s:?}: expected pi-gcs or remcon32")),
        }
    }
}

/// The RemCon32 dialect's own settings (`[simulator.stage.remcon]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RemconSimConfig {
    /// Answer to `VER?`. Default names SmartSEM and the simulator.
    pub version: String,
    /// Stage type number answered by `IST?`. Default 1.
    pub stage_type: i64,
    /// Z, mm (set at once by `C95`, not moved). Default 10.
    pub z_mm: f64,
    /// Rotation, degrees (set at once by `C95`, modulo 360). Default 0.
    pub rotation_deg: f64,
    /// M, mm (set at once by `C95`). Default 0.
    pub m_mm: f64,
    /// Answer to `DET?`. Default `SE2`.
    pub detector: String,
    /// Answer to `EHT?`, kV. Default 5.
    pub eht_kv: f64,
    /// After every move command the moving flag reads `0.0` this long although the stage
    /// travels: SmartSEM sets it late, hence the ~1 s wait before trusting it [OD-Z].
    /// Simulated seconds. Default 1.
    pub moving_flag_delay_s: f64,
}

impl Default for RemconSimConfig {
    fn default() -> Self {
        Self {
            version: format!(
                "SmartSEM Remote Control (sdsem-sim {} simulation)",
                env!("CARGO_PKG_VERSION")
            ),
            stage_type: 1,
            z_mm: 10.0,
            rotation_deg: 0.0,
            m_mm: 0.0,
            detector: "SE2".to_owned(),
            eht_kv: 5.0,
            moving_flag_delay_s: 1.0,
        }
    }
}

/// The simulated stage: axes X, Y (specimen translation, µm) and T (tilt,
/// degrees), served as a PI GCS controller (default) or over Zeiss RemCon32.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StageSimConfig {
    /// Where the controller listens. Default `tcp://127.0.0.1:0`.
    pub endpoint: SimEndpoint,
    /// The language on the link: `pi-gcs` (default) or `remcon32`.
    pub protocol: SimStageProtocol,
    /// Seed of the fault draws (probabilities, garbled bytes). Default: derived
    /// from `simulator.seed`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
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
    /// RemCon32 settings (`protocol = "remcon32"`).
    pub remcon: RemconSimConfig,
}

fn axis(name: &str) -> AxisId {
    AxisId::new(name).unwrap_or_else(|e| unreachable!("built-in axis name: {e}"))
}

impl Default for StageSimConfig {
    fn default() -> Self {
        Self {
            endpoint: SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], 0))),
            protocol: SimStageProtocol::PiGcs,
            seed: None,
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
            remcon: RemconSimConfig::default(),
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

/// Faults on demand, each one a failure real stages show (DESIGN §7). On a
/// RemCon32 link (`stage.protocol = "remcon32"`) the same faults apply:
/// `stale_on_target` is a move that starts late (the stage stands still, its
/// moving flag at 0, for `stale_on_target_s`), and `move_error` refuses the
/// move with `*613` (parameter unattainable).
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

/// The simulated SEM's imaging server (protocol: [`sdsem_protocol::sem`]).
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `endpoint` | `tcp://127.0.0.1:0` | where the imaging server listens (TCP only; port 0 picks a free port) |
/// | `seed` | derived | seed of the SEM side (specimen, walk, scan noise); unset: derived from `simulator.seed` |
/// | `scene` | particles, 200 µm | the specimen ([`SceneParams`]) |
/// | `optics` | 1280×960, 0.1 µm, φ = 0 | full-resolution frame and pixel size, tilt axis, scan rotation, stage-to-image mapping ([`OpticsParams`]) |
/// | `walk` | 5 px/° + random 3 px per 2° | eucentric walk in full-resolution pixels ([`WalkParams`]) |
/// | `shading` | see [`ShadingParams`] | SE contrast |
/// | `noise` | 30 e⁻/µs | scan noise ([`NoiseParams`]) |
/// | `drift_um_per_s` | [0, 0] | slow drift of the specimen in the image plane, µm per simulated second |
/// | `history` | 100 000 | frames whose views are kept for ground truth (~100 bytes each) |
/// | `identity` | `sdsem,virtual-sem,0,<version>` | the `*IDN?` answer |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SemSimConfig {
    pub endpoint: SimEndpoint,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    pub scene: SceneParams,
    pub optics: OpticsParams,
    pub walk: WalkParams,
    pub shading: ShadingParams,
    pub noise: NoiseParams,
    pub drift_um_per_s: [f64; 2],
    pub history: usize,
    pub identity: String,
}

impl Default for SemSimConfig {
    fn default() -> Self {
        Self {
            endpoint: SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], 0))),
            seed: None,
            scene: SceneParams::default(),
            optics: OpticsParams::default(),
            walk: WalkParams::default(),
            shading: ShadingParams::default(),
            noise: NoiseParams::default(),
            drift_um_per_s: [0.0, 0.0],
            history: 100_000,
            identity: format!("sdsem,virtual-sem,0,{}", env!("CARGO_PKG_VERSION")),
        }
    }
}

impl SemSimConfig {
    /// This configuration with `seed`, `scene.seed` and `walk.seed` filled in
    /// (when unset) from the simulator's seed `simulator_seed`.
    #[must_use]
    pub fn resolved(&self, simulator_seed: u64) -> Self {
        let mut c = self.clone();
        let seed = *c
            .seed
            .get_or_insert_with(|| derive_seed(simulator_seed, "sem"));
        c.scene
            .seed
            .get_or_insert_with(|| derive_seed(seed, "scene"));
        c.walk.seed.get_or_insert_with(|| derive_seed(seed, "walk"));
        c
    }

    /// The seed of the scan noise (frame `k` uses a hash of it and `k`).
    #[must_use]
    pub fn noise_seed(&self) -> u64 {
        derive_seed(self.seed.unwrap_or(0), "noise")
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
        self.stage.validate()?;
        self.sem.validate()?;
        self.folder
            .as_ref()
            .map_or(Ok(()), crate::FolderSimConfig::validate)?;
        self.sharksem.as_ref().map_or(Ok(()), |s| s.validate())
    }
}

fn finite(field: &'static str, v: f64) -> Result<(), SimError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(invalid(field, format!("must be a finite number, got {v}")))
    }
}

fn non_negative(field: &'static str, v: f64) -> Result<(), SimError> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(invalid(field, format!("must be ≥ 0, got {v}")))
    }
}

impl SemSimConfig {
    /// Checks every value, naming the first wrong field. (The scene's own
    /// ranges are checked when it is built.)
    pub fn validate(&self) -> Result<(), SimError> {
        if self.endpoint == SimEndpoint::Pty {
            return Err(invalid(
                "sem.endpoint",
                "the SEM imaging link is TCP only: write tcp://IP:PORT, e.g. tcp://127.0.0.1:0",
            ));
        }
        let o = &self.optics;
        let max = sdsem_protocol::sem::MAX_SIDE;
        for (field, side) in [
            ("sem.optics.width", o.width),
            ("sem.optics.height", o.height),
        ] {
            if side == 0 || u32::try_from(side).map_or(true, |s| s > max) {
                return Err(invalid(
                    field,
                    format!("must be 1 to {max} pixels, got {side}"),
                ));
            }
        }
        positive("sem.optics.pixel_size_um", o.pixel_size_um)?;
        finite("sem.optics.tilt_axis_deg", o.tilt_axis_deg)?;
        finite("sem.optics.scan_rotation_deg", o.scan_rotation_deg)?;
        if o.stage_to_image.iter().flatten().any(|v| !v.is_finite()) {
            return Err(invalid(
                "sem.optics.stage_to_image",
                "every entry must be a finite number",
            ));
        }
        let w = &self.walk;
        finite("sem.walk.px_per_deg", w.px_per_deg)?;
        finite("sem.walk.direction_deg", w.direction_deg)?;
        non_negative("sem.walk.random_px", w.random_px)?;
        positive("sem.walk.knot_deg", w.knot_deg)?;
        // Infinity is allowed: no shot noise.
        let e = self.noise.electrons_per_us;
        if e.is_nan() || e <= 0.0 {
            return Err(invalid(
                "sem.noise.electrons_per_us",
                format!("must be > 0, got {}", self.noise.electrons_per_us),
            ));
        }
        non_negative("sem.noise.read_noise", self.noise.read_noise)?;
        finite("sem.drift_um_per_s", self.drift_um_per_s[0])?;
        finite("sem.drift_um_per_s", self.drift_um_per_s[1])?;
        if self.history == 0 {
            return Err(invalid("sem.history", "must keep at least 1 frame"));
        }
        if self.identity.trim().is_empty() || self.identity.contains(['\n', '\r']) {
            return Err(invalid("sem.identity", "must be one non-empty line"));
        }
        Ok(())
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
        let r = &s.remcon;
        if r.version.trim().is_empty() || !r.version.bytes().all(|b| (0x20..=0x7E).contains(&b)) {
            return Err(invalid(
                "stage.remcon.version",
                "must be one non-empty line of printable ASCII",
            ));
        }
        finite("stage.remcon.z_mm", r.z_mm)?;
        finite("stage.remcon.rotation_deg", r.rotation_deg)?;
        finite("stage.remcon.m_mm", r.m_mm)?;
        non_negative("stage.remcon.moving_flag_delay_s", r.moving_flag_delay_s)?;
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
    use crate::scene::SceneKind;

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
        let resolved = c.resolved();
        let back: SimConfig =
            serde_json::from_str(&serde_json::to_string(&resolved).unwrap()).unwrap();
        assert_eq!(back, resolved, "seeds survive a round trip");
    }

    #[test]
    fn partial_tables_keep_the_other_defaults() {
        let c: SimConfig = serde_json::from_str(
            r#"{"time_scale": 0.01, "stage": {"tilt_max_deg": 60, "endpoint": "pty",
                "faults": {"drop_reply": {"at": [3]}}},
                "sem": {"scene": {"kind": "grid"}, "walk": {"px_per_deg": 2.5}}}"#,
        )
        .unwrap();
        assert_eq!(c.time_scale, 0.01);
        assert_eq!(c.stage.tilt_max_deg, 60.0);
        assert_eq!(c.stage.tilt_min_deg, -5.0);
        assert_eq!(c.stage.endpoint, SimEndpoint::Pty);
        assert_eq!(c.stage.faults.drop_reply.at, vec![3]);
        assert_eq!(c.stage.faults.late_reply_delay_s, 2.0);
        assert_eq!(c.sem.scene.kind, SceneKind::Grid);
        assert_eq!(c.sem.scene.field_um, 200.0);
        assert_eq!(c.sem.walk.px_per_deg, 2.5);
        assert_eq!(c.sem.walk.direction_deg, 60.0);
        assert_eq!(c.sem.optics.pixel_size_um, 0.1);
    }

    #[test]
    fn unknown_keys_are_refused() {
        assert!(serde_json::from_str::<SimConfig>(r#"{"stage": {"tilt_maxx": 3}}"#).is_err());
        assert!(
            serde_json::from_str::<SimConfig>(r#"{"stage": {"endpoint": "udp://x"}}"#).is_err()
        );
        assert!(serde_json::from_str::<SimConfig>(r#"{"sem": {"optics": {"pixel": 1}}}"#).is_err());
        assert!(
            serde_json::from_str::<SimConfig>(r#"{"sem": {"walk": {"linear_um_per_deg": 1}}}"#)
                .is_err()
        );
    }

    #[test]
    fn one_seed_drives_every_part_unless_a_part_sets_its_own() {
        let at = |seed| {
            SimConfig {
                seed,
                ..SimConfig::default()
            }
            .resolved()
        };
        let (a, b, c) = (at(7), at(7), at(8));
        assert_eq!(a, b, "derivation is deterministic");
        assert!(a.stage.seed.is_some() && a.sem.scene.seed.is_some() && a.sem.walk.seed.is_some());
        assert_ne!(a.stage.seed, c.stage.seed);
        assert_ne!(a.sem.seed, c.sem.seed);
        assert_ne!(a.sem.scene.seed, c.sem.scene.seed);
        assert_ne!(a.sem.walk.seed, c.sem.walk.seed);
        assert_ne!(a.sem.noise_seed(), c.sem.noise_seed());
        // Sibling parts get different seeds.
        assert_ne!(a.sem.scene.seed, a.sem.walk.seed);
        assert_ne!(a.stage.seed, a.sem.seed);
        // An explicit seed wins over its parent's; the rest still follows the parent.
        let mut fixed = SimConfig {
            seed: 8,
            ..SimConfig::default()
        };
        fixed.sem.scene.seed = Some(a.sem.scene.seed.unwrap());
        fixed.stage.seed = Some(42);
        let fixed = fixed.resolved();
        assert_eq!(fixed.sem.scene.seed, a.sem.scene.seed);
        assert_eq!(fixed.stage.seed, Some(42));
        assert_eq!(fixed.sem.walk.seed, c.sem.walk.seed);
        // Resolving twice changes nothing.
        assert_eq!(fixed.resolved(), fixed);
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
        let mut c = SimConfig::default();
        c.sem.endpoint = SimEndpoint::Pty;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("sem.endpoint") && e.contains("TCP only"), "{e}");
        let mut c = SimConfig::default();
        c.sem.optics.pixel_size_um = 0.0;
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("sem.optics.pixel_size_um"), "{e}");
        let mut c = SimConfig::default();
        c.sem.walk.px_per_deg = f64::NAN;
        assert!(c.validate().unwrap_err().to_string().contains("px_per_deg"));
        let mut c = SimConfig::default();
        c.sem.noise = NoiseParams::none();
        c.validate().unwrap();
    }
}
