//! The configuration, layered: built-in defaults → TOML file → `SDSEM_*`
//! environment → command-line `--set key=value`. Every section rejects keys it
//! does not know, naming them, and [`Config::validate`] checks what only makes
//! sense across sections (a series inside the stage's limits) before anything
//! is sent to an instrument.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

pub use self::layers::Layer;
use crate::acquisition::{PlanError, SeriesConfig, SeriesPlan, TrackingConfig};
use crate::daemon::DaemonConfig;
use crate::export::MeshParams;
use crate::imaging::{ImagingConfig, ImagingError};
use crate::stage::{StageConfig, StageError};
use crate::vision::datum::DatumKind;
use crate::vision::dense::DenseParams;
use crate::vision::sparse::SparseParams;
use crate::vision::{Preset, ReconstructionParams};

/// Where runs go and what they are called.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunConfig {
    /// Directory under which each run gets its own directory
    /// `<name>-<UTC timestamp>`. Default `runs`.
    pub output_dir: PathBuf,
    /// Name of the run (job name in the daemon). Default `run`.
    pub name: String,
    /// Reconstruct the pair at the end of the run. Default true.
    pub reconstruct: bool,
}

impl Default for RunConfig {
    fn default() -> Self {
        Self {
            output_dir: PathBuf::from("runs"),
            name: "run".into(),
            reconstruct: true,
        }
    }
}

/// The reconstruction of the pair (`sdsem acquire`, `reconstruct`, `replay`).
///
/// `mode` names the preset whose values every other key starts from; the configuration's
/// layers resolve it once, when they are loaded ([`Config::from_layers`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ReconstructionConfig {
    /// The preset: `improved` (default) or `paper` (the SD-SEM pipeline as published).
    pub mode: Preset,
    /// φ, the direction of the stage tilt axis in the image (degrees from +x
    /// towards +y), used when neither the command line nor the micrographs give
    /// it. It decides the sign of the relief.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_axis_deg: Option<f64>,
    /// What zero height means: `support` (default), `mean-plane` or `none`.
    pub datum: DatumKind,
    pub sparse: SparseParams,
    pub dense: DenseParams,
    pub mesh: MeshParams,
}

impl Default for ReconstructionConfig {
    fn default() -> Self {
        Self::preset(Preset::default())
    }
}

impl ReconstructionConfig {
    /// Every key at the value of `preset`.
    #[must_use]
    pub fn preset(preset: Preset) -> Self {
        let ReconstructionParams {
            sparse,
            dense,
            datum,
        } = ReconstructionParams::preset(preset);
        Self {
            mode: preset,
            tilt_axis_deg: None,
            datum,
            sparse,
            dense,
            mesh: MeshParams::default(),
        }
    }

    /// The pipeline's parameters.
    #[must_use]
    pub fn params(&self) -> ReconstructionParams {
        ReconstructionParams {
            sparse: self.sparse.clone(),
            dense: self.dense,
            datum: self.datum,
        }
    }
}

/// Re-bases the `[reconstruction]` table of a rendered configuration from the preset it was
/// resolved with to `to`: every key still at the old preset's value takes the new preset's
/// (removed here, so that the new preset's layer below shows through), every other key stays.
/// A later layer that changes `reconstruction.mode` re-bases the earlier ones this way.
pub fn rebase_reconstruction(root: &mut toml::Table, to: Preset) {
    let Some(toml::Value::Table(recon)) = root.get_mut("reconstruction") else {
        return;
    };
    let from = recon
        .get("mode")
        .and_then(|m| m.clone().try_into::<Preset>().ok())
        .unwrap_or_default();
    let Ok(toml::Value::Table(old)) = toml::Value::try_from(ReconstructionConfig::preset(from))
    else {
        return;
    };
    drop_equal(recon, &old);
    if from != to {
        recon.insert(
            "mode".to_owned(),
            toml::Value::try_from(to).unwrap_or_else(|_| toml::Value::String("improved".into())),
        );
        let Ok(toml::Value::Table(new)) = toml::Value::try_from(ReconstructionConfig::preset(to))
        else {
            return;
        };
        fill_missing(recon, &new);
    }
}

/// A configuration recorded by an earlier sdsem (the effective configuration of a run) in
/// today's keys: `reconstruction.dense.mode` is gone (the preset is `reconstruction.mode`), and
/// such a record in the paper mode ran the paper's values of the three sparse keys that were
/// then left at the improved defaults. Text that does not parse is returned as it is.
#[must_use]
pub fn upgrade_recorded(text: &str) -> String {
    let Ok(mut root) = toml::from_str::<toml::Table>(text) else {
        return text.to_owned();
    };
    let Some(toml::Value::Table(recon)) = root.get_mut("reconstruction") else {
        return text.to_owned();
    };
    let Some(toml::Value::Table(dense)) = recon.get_mut("dense") else {
        return text.to_owned();
    };
    if dense.remove("mode").is_none() {
        return text.to_owned();
    }
    let paper = recon.get("mode").and_then(toml::Value::as_str) == Some("paper");
    if paper && let Some(toml::Value::Table(sparse)) = recon.get_mut("sparse") {
        let improved = SparseParams::preset(Preset::Improved);
        let paper = SparseParams::preset(Preset::Paper);
        let mut set = |section: &str, key: &str, ours: toml::Value, theirs: toml::Value| {
            if let Some(toml::Value::Table(t)) = sparse.get_mut(section)
                && t.get(key) == Some(&ours)
            {
                t.insert(key.to_owned(), theirs);
            }
        };
        set(
            "sift",
            "c_dog",
            toml::Value::Float(improved.sift.c_dog),
            toml::Value::Float(paper.sift.c_dog),
        );
        set(
            "refine",
            "enabled",
            toml::Value::Boolean(improved.refine.enabled),
            toml::Value::Boolean(paper.refine.enabled),
        );
        set(
            "rectify",
            "cauchy_scale_px",
            toml::Value::Float(improved.rectify.cauchy_scale_px),
            toml::Value::Float(paper.rectify.cauchy_scale_px),
        );
    }
    toml::to_string(&root).unwrap_or_else(|_| text.to_owned())
}

/// Removes the leaves of `table` equal to those of `reference` (empty tables go too).
fn drop_equal(table: &mut toml::Table, reference: &toml::Table) {
    table.retain(|key, value| match (value, reference.get(key)) {
        (toml::Value::Table(t), Some(toml::Value::Table(r))) => {
            drop_equal(t, r);
            !t.is_empty()
        }
        (v, Some(r)) => key == "mode" || v != r,
        (_, None) => true,
    });
}

/// Adds the leaves of `reference` that `table` lacks.
fn fill_missing(table: &mut toml::Table, reference: &toml::Table) {
    for (key, r) in reference {
        match (table.get_mut(key), r) {
            (Some(toml::Value::Table(t)), toml::Value::Table(r)) => fill_missing(t, r),
            (Some(_), _) => {}
            (None, r) => {
                table.insert(key.clone(), r.clone());
            }
        }
    }
}

/// Logging on the terminal or journal.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LogConfig {
    /// `auto` (readable on a terminal, JSON lines otherwise), `text` or `json`.
    pub format: LogFormat,
    /// Filter in `tracing` syntax (`info`, `sdsem=debug,info`). `RUST_LOG` overrides it.
    pub filter: String,
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            format: LogFormat::Auto,
            filter: "info".into(),
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    Auto,
    Text,
    Json,
}

/// The whole configuration of sdsem. Each section is documented in
/// `config/sdsem.toml`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub run: RunConfig,
    pub series: SeriesConfig,
    pub tracking: TrackingConfig,
    pub stage: StageConfig,
    pub imaging: ImagingConfig,
    /// When present, sdsem starts the stage-and-SEM simulator inside its own
    /// process and connects to it through the real links, in place of
    /// `stage.endpoint` and `imaging.endpoint`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub simulator: Option<sdsem_sim::SimConfig>,
    pub reconstruction: ReconstructionConfig,
    pub log: LogConfig,
    pub daemon: DaemonConfig,
}

pub mod layers;

/// Why a configuration cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read configuration file {path}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A key or value that one layer gives (or, without a layer, the layers together).
    #[error("invalid configuration{}: {message}", layer.as_ref().map(|l| format!(" in {l}")).unwrap_or_default())]
    Invalid {
        layer: Option<Layer>,
        message: String,
    },
    #[error("--set {arg:?}: expected key=value, for example series.end_tilt_deg=5")]
    BadOverride { arg: String },
    /// The message already is the plan error's, so it is not also its `source`
    /// (a one-line `{:#}` would print it twice).
    #[error("invalid configuration: {0}")]
    Plan(PlanError),
    #[error("invalid configuration: {0}")]
    Stage(StageError),
    #[error("invalid configuration: {0}")]
    Imaging(ImagingError),
    #[error("invalid configuration: tracking.gain = {0} must lie in (0, 1]")]
    TrackingGain(f64),
    #[error(
        "invalid configuration: stage.protocol = \"{configured}\" but the simulated stage speaks \
         \"{simulated}\": set simulator.stage.protocol = \"{configured}\" too"
    )]
    SimulatedProtocol {
        configured: crate::stage::StageProtocol,
        simulated: crate::stage::StageProtocol,
    },
    #[error(
        "invalid configuration: imaging.protocol = \"watch-folder\": stored micrographs do not record \
         the tilt axis; set reconstruction.tilt_axis_deg (the direction of the stage tilt axis in the image)"
    )]
    WatchFolderTiltAxis,
    #[error("invalid configuration: run.name = {0:?} must be a non-empty name without '/'")]
    RunName(String),
}

error_from!(ConfigError {
    Plan(PlanError),
    Stage(StageError),
    Imaging(ImagingError),
});

/// Prefix of the environment variables that override configuration keys:
/// `SDSEM_SERIES__END_TILT_DEG=5` sets `series.end_tilt_deg`. Only variables
/// with a `__` (section separator) count, so `SDSEM_DATA` and the like are left alone.
const ENV_PREFIX: &str = "SDSEM_";

impl Config {
    /// Loads defaults, then `file` (if any), then the environment, then the
    /// `key=value` overrides, and validates the result.
    ///
    /// # Errors
    /// [`ConfigError`] naming the file, the key and the cause.
    pub fn load(file: Option<&Path>, overrides: &[String]) -> Result<Self, ConfigError> {
        Self::load_with_env(file, overrides, std::env::vars())
    }

    /// [`Config::load`] with the environment given explicitly (for tests).
    ///
    /// # Errors
    /// As [`Config::load`].
    pub fn load_with_env(
        file: Option<&Path>,
        overrides: &[String],
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self, ConfigError> {
        let text = match file {
            Some(path) => {
                Some(
                    std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
                        path: path.to_owned(),
                        source,
                    })?,
                )
            }
            None => None,
        };
        Self::from_layers(text.as_deref(), file, overrides, env)
    }

    /// [`Config::load_with_env`] with the file's text given (e.g. the effective
    /// configuration stored in a run record); `origin` names it in errors.
    ///
    /// # Errors
    /// As [`Config::load`].
    pub fn from_layers(
        text: Option<&str>,
        origin: Option<&Path>,
        overrides: &[String],
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self, ConfigError> {
        let file_layer = Layer::File(
            origin.map_or_else(|| PathBuf::from("the configuration text"), Path::to_owned),
        );
        let mut file = match text {
            Some(text) => {
                toml::from_str::<toml::Table>(text).map_err(|e| ConfigError::Invalid {
                    layer: Some(file_layer.clone()),
                    message: layers::one_line(&e.to_string()),
                })?
            }
            None => toml::Table::new(),
        };
        // Then each variable and --set, in the order they apply: (layer, key, value), the
        // environment and the command line typed alike (TOML-ish values).
        let mut later: Vec<(Layer, String, config::Value)> = Vec::new();
        for (name, value) in env {
            if let Some(rest) = name.strip_prefix(ENV_PREFIX)
                && rest.contains("__")
            {
                let key = rest.to_ascii_lowercase().replace("__", ".");
                let typed = parse_override_value(value.trim());
                later.push((Layer::Env { name, value }, key, typed));
            }
        }
        for arg in overrides {
            let (key, value) = arg
                .split_once('=')
                .filter(|(k, _)| !k.trim().is_empty())
                .ok_or_else(|| ConfigError::BadOverride { arg: arg.clone() })?;
            later.push((
                Layer::Set(arg.clone()),
                key.trim().to_owned(),
                parse_override_value(value.trim()),
            ));
        }
        // The built-in defaults are the first layer, so a file may give part
        // of a table (`[imaging.micrograph] width = 640`) and keep the rest;
        // they are the values of the preset the layers end with. A file's keys
        // still at its own preset's values follow a later layer's preset.
        let layered = |defaults: &Self, file: &toml::Table, upto: usize| {
            let mut builder = config::Config::builder()
                .add_source(config::File::from_str(
                    &defaults.to_toml(),
                    config::FileFormat::Toml,
                ))
                .add_source(config::File::from_str(
                    &toml::to_string(file).unwrap_or_default(),
                    config::FileFormat::Toml,
                ));
            for (layer, key, value) in &later[..upto] {
                builder =
                    builder
                        .set_override(key, value.clone())
                        .map_err(|e| ConfigError::Invalid {
                            layer: Some(layer.clone()),
                            message: format!("{key}: {e}"),
                        })?;
            }
            Ok::<_, ConfigError>(builder)
        };
        // The file on its own first: its errors are its own.
        if text.is_some() {
            build(layered(&Self::default(), &file, 0)?).map_err(|e| ConfigError::Invalid {
                message: layers::explain(&e, &file_layer, None),
                layer: Some(file_layer.clone()),
            })?;
        }
        let blame = |defaults: &Self, file: &toml::Table, e: &config::ConfigError| match layered(
            defaults, file, 0,
        ) {
            Ok(base) => blame_override(&base, &later, e),
            Err(e) => e,
        };
        let mut builder = layered(&Self::default(), &file, later.len())?;
        let preset = builder
            .clone()
            .build()
            .and_then(|merged| merged.get::<Preset>("reconstruction.mode"))
            .map_err(|e| blame(&Self::default(), &file, &e))?;
        let file_preset = file
            .get("reconstruction")
            .and_then(|r| r.get("mode"))
            .and_then(|m| m.clone().try_into::<Preset>().ok())
            .unwrap_or_default();
        let mut defaults = Self::default();
        if preset != Preset::default() || file_preset != preset {
            rebase_reconstruction(&mut file, preset);
            defaults = Self {
                reconstruction: ReconstructionConfig::preset(preset),
                ..Self::default()
            };
            builder = layered(&defaults, &file, later.len())?;
        }
        let config = build(builder).map_err(|e| blame(&defaults, &file, &e))?;
        config
            .validate()
            .map_err(|e| blame_rule(e, text, &file_layer, &later))?;
        Ok(config)
    }

    /// Checks the rules that span sections.
    ///
    /// # Errors
    /// [`ConfigError`] naming the keys at fault.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.plan()?;
        self.stage.validate()?;
        // The in-process simulator's store folder stands in for an unset watch_dir, as its
        // endpoints do for the configured ones.
        let mut imaging = self.imaging.clone();
        if let Some(folder) = self.simulator.as_ref().and_then(|s| s.folder.as_ref())
            && imaging.watch_dir.as_os_str().is_empty()
        {
            imaging.watch_dir.clone_from(&folder.dir);
        }
        imaging.validate()?;
        if let Some(sim) = &self.simulator {
            let simulated = crate::stage::StageProtocol::from(sim.stage.protocol);
            // A SharkSEM stage is the simulator's SharkSEM dialect, served beside its serial one.
            let sharksem = self.stage.protocol == crate::stage::StageProtocol::Sharksem;
            if simulated != self.stage.protocol && !sharksem {
                return Err(ConfigError::SimulatedProtocol {
                    configured: self.stage.protocol,
                    simulated,
                });
            }
        }
        let t = &self.tracking;
        if !(t.gain > 0.0 && t.gain <= 1.0) {
            return Err(ConfigError::TrackingGain(t.gain));
        }
        if self.imaging.protocol == crate::imaging::ImagingProtocol::WatchFolder
            && self.run.reconstruct
            && self.reconstruction.tilt_axis_deg.is_none()
        {
            return Err(ConfigError::WatchFolderTiltAxis);
        }
        if self.run.name.trim().is_empty() || self.run.name.contains('/') {
            return Err(ConfigError::RunName(self.run.name.clone()));
        }
        Ok(())
    }

    /// The tilts of the configured series.
    ///
    /// # Errors
    /// [`PlanError`] when the series does not fit the stage limits.
    pub fn plan(&self) -> Result<SeriesPlan, PlanError> {
        SeriesPlan::new(
            &self.series,
            self.stage.tilt_min_deg,
            self.stage.tilt_max_deg,
        )
    }

    /// The effective configuration as TOML (for the record and `check-config`), arrays on
    /// one line (`stage_to_image = [[-1.0, 0.0], [0.0, 1.0]]`).
    #[must_use]
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# cannot render: {e}\n"))
    }
}

/// Deserializes the layers of `builder`.
fn build(
    builder: config::ConfigBuilder<config::builder::DefaultState>,
) -> Result<Config, config::ConfigError> {
    builder.build().and_then(config::Config::try_deserialize)
}

/// Names the variable or `--set` a deserialization error comes from: the first that fails
/// on its own over `base` (the error itself does not say which layer gave the value).
fn blame_override(
    base: &config::ConfigBuilder<config::builder::DefaultState>,
    set: &[(Layer, String, config::Value)],
    error: &config::ConfigError,
) -> ConfigError {
    for (layer, key, value) in set {
        let Ok(single) = base.clone().set_override(key, value.clone()) else {
            continue;
        };
        if let Err(e) = build(single) {
            return ConfigError::Invalid {
                message: layers::explain(&e, layer, Some(key)),
                layer: Some(layer.clone()),
            };
        }
    }
    ConfigError::Invalid {
        layer: None,
        message: error.to_string(),
    }
}

/// A rule across keys, named with the layer that set the key it names: the last variable or
/// `--set` that sets it, else the file when it does.
fn blame_rule(
    error: ConfigError,
    text: Option<&str>,
    file: &Layer,
    set: &[(Layer, String, config::Value)],
) -> ConfigError {
    let message = match &error {
        ConfigError::Read { .. }
        | ConfigError::Invalid { .. }
        | ConfigError::BadOverride { .. } => {
            return error;
        }
        rule => rule.to_string(),
    };
    let message = message
        .strip_prefix("invalid configuration: ")
        .map_or_else(|| message.clone(), str::to_owned);
    let named = |key: &str| {
        message.match_indices(key).any(|(i, _)| {
            !message[i + key.len()..].starts_with(|c: char| c.is_alphanumeric() || c == '_')
        })
    };
    let from_override = set
        .iter()
        .rev()
        .find(|(_, key, _)| named(key))
        .map(|(layer, _, _)| layer.clone());
    let from_file = || {
        let table: toml::Table = toml::from_str(text?).ok()?;
        let mut keys = Vec::new();
        leaves("", &toml::Value::Table(table), &mut keys);
        keys.iter().any(|k| named(k)).then(|| file.clone())
    };
    match from_override.or_else(from_file) {
        Some(layer) => ConfigError::Invalid {
            layer: Some(layer),
            message,
        },
        None => error,
    }
}

/// The dotted keys of a TOML value's leaves.
fn leaves(prefix: &str, v: &toml::Value, out: &mut Vec<String>) {
    if let toml::Value::Table(t) = v {
        for (k, v) in t {
            leaves(&format!("{prefix}{k}."), v, out);
        }
    } else {
        out.push(prefix.trim_end_matches('.').to_owned());
    }
}

/// `--set` values are TOML-ish: numbers and booleans become typed values,
/// `[..]` arrays are parsed as TOML, everything else is a string.
fn parse_override_value(value: &str) -> config::Value {
    if let Ok(parsed) = toml::from_str::<toml::Table>(&format!("v = {value}"))
        && let Some(v) = parsed.get("v")
    {
        return toml_to_config(v);
    }
    config::Value::from(value)
}

fn toml_to_config(v: &toml::Value) -> config::Value {
    match v {
        toml::Value::String(s) => config::Value::from(s.as_str()),
        toml::Value::Integer(i) => config::Value::from(*i),
        toml::Value::Float(f) => config::Value::from(*f),
        toml::Value::Boolean(b) => config::Value::from(*b),
        toml::Value::Array(a) => {
            config::Value::from(a.iter().map(toml_to_config).collect::<Vec<config::Value>>())
        }
        other => config::Value::from(other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn load(toml: &str, overrides: &[&str], env: &[(&str, &str)]) -> Result<Config, ConfigError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.toml");
        std::fs::write(&path, toml).unwrap();
        let overrides: Vec<String> = overrides.iter().map(|s| (*s).to_owned()).collect();
        Config::load_with_env(
            Some(&path),
            &overrides,
            env.iter().map(|(k, v)| ((*k).to_owned(), (*v).to_owned())),
        )
    }

    #[test]
    fn a_simulated_stage_must_speak_the_configured_protocol() {
        let e = load("[stage]\nprotocol = \"remcon32\"\n[simulator]\n", &[], &[])
            .unwrap_err()
            .to_string();
        assert!(e.contains("simulator.stage.protocol = \"remcon32\""), "{e}");
        let both = "[stage]\nprotocol = \"remcon32\"\n[simulator.stage]\nprotocol = \"remcon32\"\n";
        let c = load(both, &[], &[]).unwrap();
        assert_eq!(c.stage.effective_baud(), Some(9600));
    }

    #[test]
    fn layers_apply_in_order() {
        let c = load(
            "[series]\nend_tilt_deg = 5.0\nstep_deg = 0.5\n",
            &["series.step_deg=0.25"],
            &[("SDSEM_SERIES__END_TILT_DEG", "6"), ("SDSEM_DATA", "/x")],
        )
        .unwrap();
        assert_eq!(c.series.end_tilt_deg, 6.0, "environment beats the file");
        assert_eq!(c.series.step_deg, 0.25, "--set beats the environment");
        assert_eq!(c.series.start_tilt_deg, 0.0, "defaults fill the rest");
    }

    #[test]
    fn unknown_key_is_named() {
        let err = load("[series]\nend_tilt = 5.0\n", &[], &[]).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("end_tilt"), "{msg}");
    }

    #[test]
    fn unknown_section_is_named() {
        let err = load("[seris]\nend_tilt_deg = 5.0\n", &[], &[]).unwrap_err();
        assert!(err.to_string().contains("seris"), "{err}");
    }

    #[test]
    fn zero_step_and_out_of_limit_end_are_refused() {
        let err = load("[series]\nstep_deg = 0\n", &[], &[]).unwrap_err();
        assert!(err.to_string().contains("series.step_deg"), "{err}");
        let err = load("[series]\nend_tilt_deg = 80\n", &[], &[]).unwrap_err();
        assert!(
            err.to_string().contains("series.end_tilt_deg = 80"),
            "{err}"
        );
    }

    #[test]
    fn a_partial_table_keeps_the_defaults_of_its_other_keys() {
        let c = load(
            "[imaging.micrograph]\nwidth = 640\nheight = 480\n",
            &[],
            &[],
        )
        .unwrap();
        assert_eq!(c.imaging.micrograph.width, 640);
        assert_eq!(
            c.imaging.micrograph.dwell_us,
            Config::default().imaging.micrograph.dwell_us
        );
        let c = load("", &["imaging.tracking.width=160"], &[]).unwrap();
        assert_eq!(c.imaging.tracking.width, 160);
        assert_eq!(c.imaging.tracking.height, 240);
    }

    #[test]
    fn array_override_parses() {
        let c = load(
            "",
            &["tracking.stage_to_image=[[1.0, 0.0], [0.0, 1.0]]"],
            &[],
        )
        .unwrap();
        assert_eq!(c.tracking.stage_to_image, [[1.0, 0.0], [0.0, 1.0]]);
    }

    /// Each error names the layer it comes from and the key; a near miss names the key meant.
    #[test]
    fn errors_name_their_layer_and_the_key_meant() {
        let err = load("[series]\nend_tilt = 5.0\n", &[], &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with("invalid configuration in ")
                && err.contains(
                    "c.toml: unknown key series.end_tilt: did you mean series.end_tilt_deg?"
                ),
            "{err}"
        );
        // A bad --set or environment value is not blamed on the file.
        let err = load("", &["series.end_tilt_deg=abc"], &[])
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "invalid configuration in --set series.end_tilt_deg=abc: series.end_tilt_deg: \
             expected a floating point, found string \"abc\""
        );
        let err = load("", &[], &[("SDSEM_SERIES__END_TILT_DEG", "abc")])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with(
                "invalid configuration in environment variable SDSEM_SERIES__END_TILT_DEG=\"abc\": \
                 series.end_tilt_deg: expected"
            ),
            "{err}"
        );
        assert!(!err.contains("c.toml"), "{err}");
        // Unknown keys: the whole key as the layer writes it.
        let err = load("", &["seris.end_tilt_deg=5"], &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.ends_with("unknown key seris: did you mean series.end_tilt_deg?"),
            "{err}"
        );
        let err = load("", &[], &[("SDSEM_SERIES__END_TILTDEG", "5")])
            .unwrap_err()
            .to_string();
        assert!(
            err.ends_with(
                "unknown key series.end_tiltdeg: did you mean SDSEM_SERIES__END_TILT_DEG?"
            ),
            "{err}"
        );
        let err = load("[series]\ncolour = 1\n", &[], &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.ends_with(
                "unknown key series.colour (series has start_tilt_deg, end_tilt_deg, step_deg)"
            ),
            "{err}"
        );
        // A value out of its set, and a rule across keys, name the layer too.
        let err = load("", &["reconstruction.mode=papr"], &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.ends_with(
                "reconstruction.mode = \"papr\" is not a known value: did you mean \"paper\"?"
            ),
            "{err}"
        );
        let err = load("", &["series.end_tilt_deg=80"], &[])
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with(
                "invalid configuration in --set series.end_tilt_deg=80: series.end_tilt_deg = 80"
            ),
            "{err}"
        );
        let err = load("[series]\nend_tilt_deg = 80\n", &[], &[])
            .unwrap_err()
            .to_string();
        assert!(err.contains("c.toml: series.end_tilt_deg = 80"), "{err}");
        // A TOML syntax error: one line with where it is.
        let err = load("[series\n", &[], &[]).unwrap_err().to_string();
        assert!(!err.contains('\n') && err.contains("line 1"), "{err}");
    }

    #[test]
    fn malformed_override_is_explained() {
        let err = load("", &["series.end_tilt_deg"], &[]).unwrap_err();
        assert!(err.to_string().contains("expected key=value"), "{err}");
    }

    #[test]
    fn effective_config_round_trips_through_toml() {
        let c = load("[series]\nend_tilt_deg = 5.0\n", &[], &[]).unwrap();
        let again = load(&c.to_toml(), &[], &[]).unwrap();
        assert_eq!(c, again);
    }

    #[test]
    fn effective_config_writes_arrays_on_one_line() {
        let text = Config::default().to_toml();
        assert!(
            text.contains("stage_to_image = [[-1.0, 0.0], [0.0, -1.0]]\n"),
            "{text}"
        );
        assert!(!text.contains("[\n"), "{text}");
    }

    fn leaf_keys(prefix: &str, v: &toml::Value, out: &mut Vec<String>) {
        if let toml::Value::Table(t) = v {
            for (k, v) in t {
                leaf_keys(&format!("{prefix}{k}."), v, out);
            }
        } else {
            out.push(prefix.trim_end_matches('.').to_owned());
        }
    }

    /// config/sdsem.toml documents every key with its default: loading it
    /// gives the built-in defaults, and it names every key they have.
    #[test]
    fn the_documented_configuration_is_the_default_one() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sdsem.toml");
        let loaded = Config::load_with_env(Some(&path), &[], std::iter::empty()).unwrap();
        assert_eq!(
            loaded,
            Config::default(),
            "a value in {} is not the default",
            path.display()
        );
        let text = std::fs::read_to_string(&path).unwrap();
        let file: toml::Value = toml::from_str(&text).unwrap();
        let mut documented = Vec::new();
        leaf_keys("", &file, &mut documented);
        let mut known = Vec::new();
        leaf_keys(
            "",
            &toml::Value::try_from(Config::default()).unwrap(),
            &mut known,
        );
        let missing: Vec<_> = known.iter().filter(|k| !documented.contains(k)).collect();
        assert!(
            missing.is_empty(),
            "keys not documented in config/sdsem.toml: {missing:?}"
        );
    }

    #[test]
    fn a_preset_gives_every_reconstruction_key_its_value() {
        let c = load("[reconstruction]\nmode = \"paper\"\n", &[], &[]).unwrap();
        assert_eq!(
            c.reconstruction,
            ReconstructionConfig::preset(Preset::Paper)
        );
        let c = load("", &[], &[("SDSEM_RECONSTRUCTION__MODE", "paper")]).unwrap();
        assert_eq!(
            c.reconstruction,
            ReconstructionConfig::preset(Preset::Paper)
        );
        assert_eq!(
            load("", &[], &[]).unwrap().reconstruction,
            ReconstructionConfig::preset(Preset::Improved)
        );
    }

    /// A key the file sets keeps its value under the file's preset, also
    /// when that value is the other preset's.
    #[test]
    fn a_key_set_beside_the_preset_keeps_its_value() {
        let improved = SparseParams::preset(Preset::Improved);
        let c = load(
            &format!(
                "[reconstruction]\nmode = \"paper\"\n[reconstruction.sparse.sift]\nc_dog = {}\n\
                 [reconstruction.dense]\niterations = 8\n",
                improved.sift.c_dog
            ),
            &[],
            &[],
        )
        .unwrap();
        assert_eq!(c.reconstruction.sparse.sift.c_dog, improved.sift.c_dog);
        assert_eq!(c.reconstruction.dense.flow.iterations, 8);
        let paper = ReconstructionConfig::preset(Preset::Paper);
        assert_eq!(c.reconstruction.sparse.refine, paper.sparse.refine);
        assert_eq!(
            c.reconstruction.dense.flow.cell_size,
            paper.dense.flow.cell_size
        );
    }

    /// A full effective configuration (a record's) with the preset changed
    /// by a later layer: the keys at the old preset's values follow the new
    /// one, the others stay.
    #[test]
    fn a_later_layer_changing_the_preset_rebases_the_earlier_ones() {
        let mut base = Config::default();
        base.reconstruction.dense.lr_tolerance = 3.0;
        let c = load(&base.to_toml(), &["reconstruction.mode=paper"], &[]).unwrap();
        let mut want = ReconstructionConfig::preset(Preset::Paper);
        want.dense.lr_tolerance = 3.0;
        assert_eq!(c.reconstruction, want);
        // The same table re-based directly (the daemon's job overrides).
        let mut root = toml::Table::try_from(&base).unwrap();
        rebase_reconstruction(&mut root, Preset::Paper);
        let c: Config = root.try_into().unwrap();
        assert_eq!(c.reconstruction, want);
    }

    /// Both presets set every key: a key left out of one would take the
    /// other's value through the defaults of its table.
    #[test]
    fn both_presets_have_the_same_keys() {
        let keys = |p: Preset| {
            let mut out = Vec::new();
            leaf_keys(
                "",
                &toml::Value::try_from(ReconstructionConfig::preset(p)).unwrap(),
                &mut out,
            );
            out
        };
        assert_eq!(keys(Preset::Paper), keys(Preset::Improved));
    }

    #[test]
    fn unknown_and_retired_dense_keys_are_named() {
        let err = load("", &["reconstruction.dense.alpah=1"], &[]).unwrap_err();
        assert!(err.to_string().contains("alpah"), "{err}");
        let old = "[reconstruction]\nmode = \"paper\"\n[reconstruction.dense]\nmode = \"paper\"\n\
                   [reconstruction.sparse.refine]\nenabled = true\n";
        let err = load(old, &[], &[]).unwrap_err();
        assert!(err.to_string().contains("mode"), "{err}");
        // A record of an earlier sdsem: the retired key goes, and its paper
        // mode ran the paper's value of a sparse key left at the improved default.
        let upgraded = upgrade_recorded(old);
        let c = load(&upgraded, &[], &[]).unwrap();
        assert_eq!(
            c.reconstruction,
            ReconstructionConfig::preset(Preset::Paper)
        );
        assert_eq!(
            upgrade_recorded("[run]\nname = \"x\"\n"),
            "[run]\nname = \"x\"\n"
        );
    }

    /// config/sdsem.toml says "paper:" beside exactly the keys whose paper
    /// preset value differs from the improved default.
    #[test]
    fn the_documented_paper_values_are_the_keys_the_presets_differ_in() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sdsem.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let (mut section, mut comment, mut noted) = (String::new(), String::new(), Vec::new());
        for line in text.lines().map(str::trim) {
            if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
                section = name.to_owned();
                comment.clear();
            } else if let Some(c) = line.strip_prefix('#') {
                comment.push_str(c);
            } else if let Some((key, _)) = line.split_once('=') {
                if comment.contains("paper:") {
                    noted.push(format!("{section}.{}", key.trim()));
                }
                comment.clear();
            } else {
                comment.clear();
            }
        }
        let leaves = |p: Preset| {
            let mut keys = Vec::new();
            let v = toml::Value::try_from(ReconstructionConfig::preset(p)).unwrap();
            leaf_keys("reconstruction.", &v, &mut keys);
            keys.into_iter()
                .map(|k| {
                    let value = k
                        .trim_start_matches("reconstruction.")
                        .split('.')
                        .try_fold(&v, |v, part| v.get(part))
                        .cloned();
                    (k, value)
                })
                .collect::<Vec<_>>()
        };
        let differing: Vec<String> = leaves(Preset::Improved)
            .into_iter()
            .zip(leaves(Preset::Paper))
            .filter(|((_, a), (_, b))| a != b)
            .map(|((k, _), _)| k)
            .filter(|k| k != "reconstruction.mode")
            .collect();
        noted.sort();
        let mut differing = differing;
        differing.sort();
        assert_eq!(noted, differing);
    }

    #[test]
    fn the_sharksem_simulator_configuration_loads() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sim-sharksem.toml");
        let c = Config::load_with_env(Some(&path), &[], std::iter::empty()).unwrap();
        assert!(c.simulator.as_ref().is_some_and(|s| s.sharksem.is_some()));
        assert_eq!(c.stage.protocol, crate::stage::StageProtocol::Sharksem);
        assert_eq!(
            c.imaging.protocol,
            crate::imaging::ImagingProtocol::Sharksem
        );
        assert_eq!(c.reconstruction.tilt_axis_deg, Some(0.0));
    }

    #[test]
    fn the_simulator_configuration_loads() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sim.toml");
        let c = Config::load_with_env(Some(&path), &[], std::iter::empty()).unwrap();
        assert!(
            c.simulator.is_some(),
            "config/sim.toml must start the simulator"
        );
        assert_eq!(c.plan().unwrap().tilts().len(), 8, "0→7° in 1° steps");
    }
}
