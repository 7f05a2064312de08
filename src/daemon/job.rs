//! A job: what a user submits (a small TOML file) and the configuration it runs with.
//!
//! ```toml
//! name = "pollen-7"          # run name: letters, digits, '-', '_', '.'
//! start_tilt = 0.0           # degrees, first micrograph
//! end_tilt = 7.0             # degrees, last micrograph
//! step = 1.0                 # degrees per tilt step (default 1.0)
//!
//! [capture]                  # optional: overrides of capture keys
//! tracking.gain = 0.5
//!
//! [reconstruction]           # optional: overrides of reconstruction keys
//! run.reconstruct = true
//! reconstruction.mode = "paper"
//! ```
//!
//! The overrides are configuration keys written as in the configuration file,
//! merged over the daemon's configuration like `--set key=value`. A job may
//! only touch the keys listed in [`CAPTURE_KEYS`] and [`RECONSTRUCTION_KEYS`]:
//! the calibration and safety guards (`tracking.stage_to_image`,
//! `tracking.max_correction_um`, `tracking.max_lost_frames`), the stage (limits,
//! endpoint, protocol, safe tilt), the imaging endpoints, the daemon and the
//! output directory are the operator's.
//!
//! [`JobSpec::effective_config`] is the one check of a job: `sdsem submit` runs it
//! before queueing, the daemon again on every record it reads from the spool.
//! Besides the configuration's own rules it bounds the job by the operator's
//! `[daemon]` limits: a step floor, a number of steps and an estimated duration.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::untrusted::{Links, read_capped};
use crate::acquisition::run_dir::printable;
use crate::acquisition::{NameError, PlanError, RunName, SeriesPlan};
use crate::config::{Config, ConfigError};

/// Configuration keys (sections or single keys) a job's `[capture]` table may
/// set: how to scan and track, not how the instruments are calibrated, guarded or reached.
pub const CAPTURE_KEYS: &[&str] = &[
    "imaging.micrograph",
    "imaging.tracking",
    "imaging.bits",
    "tracking.enabled",
    "tracking.gain",
    "tracking.deadband_px",
];

/// Sections whose other keys belong to the operator: calibration, safety guards, endpoints.
const OPERATOR_SECTIONS: &[&str] = &["tracking", "stage", "imaging", "daemon", "run", "series"];

/// Largest job file `sdsem submit` reads, bytes.
pub const MAX_JOB_FILE_BYTES: u64 = 64 * 1024;

/// Configuration keys a job's `[reconstruction]` table may set: whether to
/// reconstruct, and every parameter of the pipeline (`reconstruction.mode`,
/// `reconstruction.dense.levels`, …).
pub const RECONSTRUCTION_KEYS: &[&str] = &["run.reconstruct", "reconstruction"];

fn default_step() -> f64 {
    1.0
}

/// A job as submitted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// Name of the run (its directory is `<name>-<UTC time>`).
    pub name: String,
    /// Stage tilt of the first micrograph, degrees (`series.start_tilt_deg`).
    pub start_tilt: f64,
    /// Stage tilt of the last micrograph, degrees (`series.end_tilt_deg`).
    pub end_tilt: f64,
    /// Tilt step, degrees (`series.step_deg`). Default 1.
    #[serde(default = "default_step")]
    pub step: f64,
    /// Overrides of capture keys (see [`CAPTURE_KEYS`]).
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    pub capture: toml::Table,
    /// Overrides of reconstruction keys (see [`RECONSTRUCTION_KEYS`]).
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    pub reconstruction: toml::Table,
}

/// Why a job cannot run. Each variant names the job key at fault and what is accepted.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The cause is in the message, not a `source` (a one-line `{:#}` would print it twice).
    #[error("cannot read job file {}: {cause}", path.display())]
    Read {
        path: PathBuf,
        cause: super::untrusted::UntrustedError,
    },
    #[error("not a valid job file: {message}")]
    Syntax { message: String },
    #[error("name = {0}")]
    Name(NameError),
    #[error(
        "[{table}] {key}: a job may not set this key{operator}; allowed in [{table}]: {allowed}"
    )]
    KeyNotAllowed {
        table: &'static str,
        key: String,
        operator: &'static str,
        allowed: String,
    },
    #[error("{key} = {value}: not a finite number")]
    NotFinite { key: String, value: String },
    #[error("[{table}] {key}: no such configuration key ({reason})")]
    UnknownKey {
        table: &'static str,
        key: String,
        reason: String,
    },
    #[error("[{table}] {key} = {value}: {message}")]
    BadOverride {
        table: &'static str,
        key: String,
        value: String,
        message: String,
    },
    #[error(
        "{key} = {value}° is outside the stage tilt limits [{min}°, {max}°] (stage.tilt_min_deg / stage.tilt_max_deg)"
    )]
    TiltOutsideLimits {
        key: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("{message}")]
    Tilts { message: String },
    #[error("step = {step}° is below the step floor daemon.min_step_deg = {min}°")]
    StepTooSmall { step: f64, min: f64 },
    #[error("the job has {steps} tilt steps, more than daemon.max_steps = {max}")]
    TooManySteps { steps: usize, max: u32 },
    #[error(
        "the job would take about {minutes:.0} min (estimated from its plan: tilt moves and \
         frames), more than daemon.max_job_minutes = {max}"
    )]
    TooLong { minutes: f64, max: f64 },
    #[error("the job's overrides give an invalid configuration: {message}")]
    Config { message: String },
}

impl JobSpec {
    /// Reads and checks a job file (syntax, name, which keys it overrides): a regular file
    /// of at most [`MAX_JOB_FILE_BYTES`], read without blocking (`submit /dev/zero` is
    /// refused at once).
    ///
    /// # Errors
    /// [`JobError`] naming the file's problem.
    pub fn load(path: &Path) -> Result<Self, JobError> {
        let bytes = read_capped(path, Links::Follow, MAX_JOB_FILE_BYTES).map_err(|cause| {
            JobError::Read {
                path: path.to_owned(),
                cause,
            }
        })?;
        let text = String::from_utf8(bytes).map_err(|e| JobError::Syntax {
            message: format!("not UTF-8 text (byte {})", e.utf8_error().valid_up_to()),
        })?;
        Self::parse(&text)
    }

    /// Parses and checks a job (syntax, name, finite numbers, which keys it overrides).
    ///
    /// # Errors
    /// [`JobError`] naming the problem.
    pub fn parse(text: &str) -> Result<Self, JobError> {
        let spec: Self = toml::from_str(text).map_err(|e| {
            // One line: "line 2, column 14: invalid type…", not the multi-line caret drawing.
            let place = e
                .span()
                .and_then(|span| text.get(..span.start))
                .map(|before| {
                    let line = before.matches('\n').count() + 1;
                    let line_start = before.rfind('\n').map_or(0, |i| i + 1);
                    let column = before[line_start..].chars().count() + 1;
                    format!("line {line}, column {column}: ")
                });
            JobError::Syntax {
                message: printable(
                    &format!(
                        "{}{}",
                        place.unwrap_or_default(),
                        e.message().trim_end().replace('\n', " ")
                    ),
                    300,
                ),
            }
        })?;
        spec.check_shape()?;
        Ok(spec)
    }

    /// The checks that need no configuration: the name, finite numbers, the keys overridden.
    ///
    /// # Errors
    /// [`JobError`] naming the key at fault.
    pub fn check_shape(&self) -> Result<(), JobError> {
        self.run_name()?;
        for (key, v) in [
            ("start_tilt", self.start_tilt),
            ("end_tilt", self.end_tilt),
            ("step", self.step),
        ] {
            if !v.is_finite() {
                return Err(JobError::NotFinite {
                    key: key.to_owned(),
                    value: v.to_string(),
                });
            }
        }
        for (key, value) in self.overrides()? {
            if let Some(bad) = non_finite(&value) {
                return Err(JobError::NotFinite {
                    key: format!("[{}] {key}", self.table_of(&key)),
                    value: bad.to_string(),
                });
            }
        }
        Ok(())
    }

    /// The job's name, checked: what its run directory is named after.
    ///
    /// # Errors
    /// [`JobError::Name`] saying what is wrong with it.
    pub fn run_name(&self) -> Result<RunName, JobError> {
        RunName::new(&self.name).map_err(JobError::Name)
    }

    /// Every override as (dotted configuration key, value), checked against
    /// the keys a job may set.
    ///
    /// # Errors
    /// [`JobError::KeyNotAllowed`] for a key outside [`CAPTURE_KEYS`] /
    /// [`RECONSTRUCTION_KEYS`].
    pub fn overrides(&self) -> Result<Vec<(String, toml::Value)>, JobError> {
        let mut out = Vec::new();
        for (table_name, table, allowed) in [
            ("capture", &self.capture, CAPTURE_KEYS),
            ("reconstruction", &self.reconstruction, RECONSTRUCTION_KEYS),
        ] {
            let mut leaves = Vec::new();
            flatten(table, "", &mut leaves);
            for (key, value) in leaves {
                let permitted = allowed.iter().any(|a| {
                    key == *a
                        || key
                            .strip_prefix(a)
                            .is_some_and(|rest| rest.starts_with('.'))
                });
                if !permitted {
                    let section = key.split('.').next().unwrap_or("");
                    return Err(JobError::KeyNotAllowed {
                        table: table_name,
                        operator: if OPERATOR_SECTIONS.contains(&section) {
                            " (operator-only: a calibration, safety guard or instrument setting of \
                             the daemon's configuration)"
                        } else {
                            ""
                        },
                        key: printable(&key, 100),
                        allowed: allowed.join(", "),
                    });
                }
                out.push((key, value));
            }
        }
        Ok(out)
    }

    /// The configuration this job runs with: `base` (the daemon's), with the
    /// job's tilts and name and its overrides, validated (tilt limits included) and
    /// bounded by `base`'s `[daemon]` limits. The one check of a job, for `sdsem submit`
    /// and for every record the daemon reads.
    ///
    /// # Errors
    /// [`JobError`] naming the job key and the limit it breaks.
    pub fn effective_config(&self, base: &Config) -> Result<Config, JobError> {
        self.check_shape()?;
        let overrides = self.overrides()?;
        let mut root = toml::Table::try_from(base).map_err(|e| JobError::Config {
            message: format!("the daemon's configuration cannot be rendered: {e}"),
        })?;
        for (table, key, value) in [
            ("run", "name", toml::Value::String(self.name.clone())),
            (
                "series",
                "start_tilt_deg",
                toml::Value::Float(self.start_tilt),
            ),
            ("series", "end_tilt_deg", toml::Value::Float(self.end_tilt)),
            ("series", "step_deg", toml::Value::Float(self.step)),
        ] {
            let section = root
                .entry(table)
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            if let toml::Value::Table(t) = section {
                t.insert(key.to_owned(), value);
            }
        }
        let series_only = root.clone();
        // A job that picks another preset starts from it: the base's keys
        // still at its own preset's values follow.
        if let Some((_, mode)) = overrides.iter().find(|(k, _)| k == "reconstruction.mode")
            && let Ok(preset) = mode.clone().try_into::<crate::vision::Preset>()
        {
            crate::config::rebase_reconstruction(&mut root, preset);
        }
        for (key, value) in &overrides {
            set_key(&mut root, key, value.clone()).map_err(|reason| JobError::UnknownKey {
                table: self.table_of(key),
                key: key.clone(),
                reason,
            })?;
        }
        let config: Config = match root.try_into() {
            Ok(config) => config,
            Err(e) => return Err(self.blame_override(&series_only, &overrides, &e)),
        };
        let limits = &base.daemon;
        if self.step < limits.min_step_deg {
            return Err(JobError::StepTooSmall {
                step: self.step,
                min: limits.min_step_deg,
            });
        }
        config.validate().map_err(job_error)?;
        let plan = config.plan().map_err(|e| job_error(ConfigError::Plan(e)))?;
        if plan.steps() > usize::try_from(limits.max_steps).unwrap_or(usize::MAX) {
            return Err(JobError::TooManySteps {
                steps: plan.steps(),
                max: limits.max_steps,
            });
        }
        let minutes = estimated_duration(&config, &plan).as_secs_f64() / 60.0;
        if minutes > limits.max_job_minutes {
            return Err(JobError::TooLong {
                minutes,
                max: limits.max_job_minutes,
            });
        }
        Ok(config)
    }

    /// Names the override a deserialization error comes from: the first one
    /// that fails on its own (the error itself does not say which key).
    fn blame_override(
        &self,
        base: &toml::Table,
        overrides: &[(String, toml::Value)],
        error: &toml::de::Error,
    ) -> JobError {
        let message = |e: &toml::de::Error| e.message().trim_end().replace('\n', " ");
        for (key, value) in overrides {
            let mut single = base.clone();
            if set_key(&mut single, key, value.clone()).is_err() {
                continue;
            }
            if let Err(e) = single.try_into::<Config>() {
                return JobError::BadOverride {
                    table: self.table_of(key),
                    key: key.clone(),
                    value: value.to_string(),
                    message: message(&e),
                };
            }
        }
        JobError::Config {
            message: message(error),
        }
    }

    fn table_of(&self, key: &str) -> &'static str {
        if CAPTURE_KEYS.iter().any(|a| key.starts_with(a)) {
            "capture"
        } else {
            "reconstruction"
        }
    }
}

/// How long the acquisition of `plan` takes at least: the tilt moves (from the safe tilt,
/// through the series, back) at `stage.tilt_speed_deg_s`, a tracking frame per step when
/// tracking is on and the two micrographs, each width × height × dwell.
#[must_use]
pub fn estimated_duration(config: &Config, plan: &SeriesPlan) -> Duration {
    let safe = config.stage.safe_tilt_deg;
    let travel = (plan.first() - safe).abs()
        + (plan.last() - plan.first()).abs()
        + (plan.last() - safe).abs();
    let frame_s = |scan: &crate::imaging::ScanSettings| {
        f64::from(scan.width) * f64::from(scan.height) * scan.dwell_us * 1e-6
    };
    #[allow(clippy::cast_precision_loss)]
    let tracking = if config.tracking.enabled {
        plan.steps() as f64 * frame_s(&config.imaging.tracking)
    } else {
        0.0
    };
    let seconds = travel / config.stage.tilt_speed_deg_s
        + tracking
        + 2.0 * frame_s(&config.imaging.micrograph);
    Duration::try_from_secs_f64(seconds).unwrap_or(Duration::MAX)
}

/// The first non-finite float in a value (arrays included), if any.
fn non_finite(value: &toml::Value) -> Option<f64> {
    match value {
        toml::Value::Float(f) if !f.is_finite() => Some(*f),
        toml::Value::Array(items) => items.iter().find_map(non_finite),
        toml::Value::Table(t) => t.values().find_map(non_finite),
        _ => None,
    }
}

/// Leaves of a TOML table as dotted keys (`imaging.micrograph.dwell_us`).
fn flatten(table: &toml::Table, prefix: &str, out: &mut Vec<(String, toml::Value)>) {
    for (k, v) in table {
        let key = if prefix.is_empty() {
            k.clone()
        } else {
            format!("{prefix}.{k}")
        };
        match v {
            toml::Value::Table(t) => flatten(t, &key, out),
            other => out.push((key, other.clone())),
        }
    }
}

/// Sets a dotted key in the rendered configuration. The key's parent must be
/// a known section; whether the last part is a known field is left to the
/// configuration's own `deny_unknown_fields` (so optional fields work).
fn set_key(root: &mut toml::Table, key: &str, value: toml::Value) -> Result<(), String> {
    let parts: Vec<&str> = key.split('.').collect();
    let Some((last, parents)) = parts.split_last() else {
        return Err("empty key".into());
    };
    let mut table = root;
    let mut walked = String::new();
    for part in parents {
        if !walked.is_empty() {
            walked.push('.');
        }
        walked.push_str(part);
        table = match table.get_mut(*part) {
            Some(toml::Value::Table(t)) => t,
            Some(_) => return Err(format!("{walked} is a value, not a section")),
            None => return Err(format!("the configuration has no section {walked}")),
        };
    }
    if let Some(existing) = table.get(*last)
        && matches!(existing, toml::Value::Table(_))
    {
        return Err(format!("{key} is a section: set its keys one by one"));
    }
    table.insert((*last).to_owned(), value);
    Ok(())
}

/// The job key a series key comes from.
fn job_key(series_key: &str) -> &'static str {
    match series_key {
        "start_tilt_deg" => "start_tilt",
        "end_tilt_deg" => "end_tilt",
        _ => "step",
    }
}

/// A configuration error in the words of the job file.
fn job_error(e: ConfigError) -> JobError {
    match e {
        ConfigError::Plan(plan) => match plan {
            PlanError::OutsideLimits {
                key,
                tilt,
                min,
                max,
            } => JobError::TiltOutsideLimits {
                key: job_key(key),
                value: tilt,
                min,
                max,
            },
            PlanError::NonPositiveStep { step } => JobError::Tilts {
                message: format!("step = {step} must be greater than 0"),
            },
            PlanError::StepTooLarge { step } => JobError::Tilts {
                message: format!(
                    "step = {step}° is larger than 10°: the tracking frames would lose the specimen"
                ),
            },
            PlanError::NoTiltRange { tilt } => JobError::Tilts {
                message: format!(
                    "start_tilt = end_tilt = {tilt}°: a stereo pair needs two different tilts"
                ),
            },
            PlanError::NotFinite { key } => JobError::Tilts {
                message: format!("{} is not a finite number", job_key(key)),
            },
            PlanError::TooManySteps { step } => JobError::Tilts {
                message: format!(
                    "step = {step}° gives more than {} steps",
                    crate::acquisition::plan::MAX_PLAN_STEPS
                ),
            },
            // The daemon's configuration, not the job, is at fault.
            inverted @ PlanError::InvertedLimits { .. } => JobError::Config {
                message: inverted.to_string(),
            },
        },
        other => JobError::Config {
            message: other.to_string(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(text: &str) -> Result<Config, JobError> {
        JobSpec::parse(text)?.effective_config(&Config::default())
    }

    #[test]
    fn minimal_job_gets_step_one_and_its_tilts() {
        let c = job("name = \"pollen-7\"\nstart_tilt = 2\nend_tilt = 9\n").unwrap();
        assert_eq!(c.series.step_deg, 1.0);
        assert_eq!(c.series.start_tilt_deg, 2.0);
        assert_eq!(c.series.end_tilt_deg, 9.0);
        assert_eq!(c.run.name, "pollen-7");
    }

    #[test]
    fn end_tilt_beyond_the_limit_names_key_and_limit() {
        let err = job("name = \"a\"\nstart_tilt = 0\nend_tilt = 80\n").unwrap_err();
        let msg = err.to_string();
        assert!(msg.starts_with("end_tilt = 80°"), "{msg}");
        assert!(msg.contains("[-5°, 70°]"), "{msg}");
    }

    #[test]
    fn bad_step_and_equal_tilts_are_explained_in_job_keys() {
        let err = job("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\nstep = 0\n").unwrap_err();
        assert!(err.to_string().starts_with("step = 0"), "{err}");
        let err = job("name = \"a\"\nstart_tilt = 3\nend_tilt = 3\n").unwrap_err();
        assert!(
            err.to_string().contains("start_tilt = end_tilt = 3"),
            "{err}"
        );
    }

    #[test]
    fn missing_and_unknown_top_level_keys_are_named() {
        let err = JobSpec::parse("name = \"a\"\nstart_tilt = 0\n").unwrap_err();
        assert!(err.to_string().contains("end_tilt"), "{err}");
        let err =
            JobSpec::parse("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\nstpe = 2\n").unwrap_err();
        assert!(err.to_string().contains("stpe"), "{err}");
    }

    #[test]
    fn syntax_errors_say_where_on_one_line() {
        let err =
            JobSpec::parse("name = \"x\"\nstart_tilt = \"zero\"\nend_tilt = 7\n").unwrap_err();
        assert_eq!(
            err.to_string(),
            "not a valid job file: line 2, column 14: invalid type: string \"zero\", expected f64"
        );
    }

    #[test]
    fn names_that_make_bad_directories_are_refused() {
        for name in ["", "../x", "a/b", ".hidden", "a b", &"x".repeat(65)] {
            let text = format!("name = {name:?}\nstart_tilt = 0\nend_tilt = 5\n");
            let err = JobSpec::parse(&text).unwrap_err();
            assert!(matches!(err, JobError::Name(_)), "{name:?}: {err}");
        }
        JobSpec::parse("name = \"Probe_Müller.2\"\nstart_tilt = 0\nend_tilt = 5\n").unwrap();
    }

    #[test]
    fn overrides_apply_over_the_daemon_configuration() {
        let c = job("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n\
             [capture]\ntracking.gain = 0.5\n[reconstruction]\nrun.reconstruct = false\n")
        .unwrap();
        assert_eq!(c.tracking.gain, 0.5);
        assert!(!c.run.reconstruct);
        assert_eq!(c.run.output_dir, Config::default().run.output_dir);
    }

    #[test]
    fn reconstruction_parameters_are_job_overrides() {
        let c = job("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n\
             [reconstruction]\nreconstruction.mode = \"paper\"\nreconstruction.dense.levels = 3\n")
        .unwrap();
        assert_eq!(c.reconstruction.mode, crate::vision::Preset::Paper);
        assert_eq!(c.reconstruction.dense.flow.levels, 3);
        // The rest is the paper preset's.
        let paper = crate::config::ReconstructionConfig::preset(crate::vision::Preset::Paper);
        assert_eq!(
            c.reconstruction.dense.flow.iterations,
            paper.dense.flow.iterations
        );
        assert_eq!(c.reconstruction.sparse, paper.sparse);
        let err = JobSpec::parse(
            "name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\nreconstruction.mode = \"paper\"\n",
        )
        .unwrap_err();
        assert!(
            err.to_string().contains("a job may not set this key"),
            "{err}"
        );
    }

    #[test]
    fn a_job_cannot_touch_the_stage_or_the_output_directory() {
        for (table, key) in [
            ("capture", "series.end_tilt_deg = 80"),
            ("capture", "run.output_dir = \"/etc\""),
            ("capture", "imaging.endpoint = \"10.0.0.1:7520\""),
            ("reconstruction", "daemon.min_free_gib = 0"),
            ("reconstruction", "run.reconstructed = 1"),
        ] {
            let text = format!("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[{table}]\n{key}\n");
            let err = JobSpec::parse(&text).unwrap_err();
            assert!(
                err.to_string().contains("a job may not set this key"),
                "{key}: {err}"
            );
        }
    }

    #[test]
    fn unknown_and_mistyped_override_keys_are_named() {
        let err = job(
            "name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\nimaging.micrograph.widht = 640\n",
        )
        .unwrap_err();
        assert!(
            err.to_string()
                .starts_with("[capture] imaging.micrograph.widht = 640: unknown field `widht`"),
            "{err}"
        );
        let err = job(
            "name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\ntracking.gain = \"high\"\n",
        )
        .unwrap_err();
        assert_eq!(
            err.to_string(),
            "[capture] tracking.gain = \"high\": invalid type: string \"high\", expected f64"
        );
        let err =
            job("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\ntracking.gain = 2.0\n")
                .unwrap_err();
        assert!(err.to_string().contains("tracking.gain = 2"), "{err}");
    }

    /// The guard was overridden to drive the stage 450 µm in one step: calibration and
    /// guards are the operator's, refused with the key named.
    #[test]
    fn calibration_guards_and_endpoints_are_operator_only() {
        for key in [
            "tracking.stage_to_image = [[9.0, 0.0], [0.0, 9.0]]",
            "tracking.max_correction_um = 500.0",
            "tracking.max_lost_frames = 100",
            "stage.tilt_max_deg = 90",
            "stage.protocol = \"sharksem\"",
            "stage.endpoint = \"/dev/ttyS0\"",
            "imaging.endpoint = \"10.0.0.1:7520\"",
            "imaging.protocol = \"watch-folder\"",
        ] {
            let text = format!("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\n{key}\n");
            let err = JobSpec::parse(&text).unwrap_err().to_string();
            let name = key.split(' ').next().unwrap();
            assert!(
                err.starts_with(&format!(
                    "[capture] {name}: a job may not set this key (operator-only"
                )),
                "{err}"
            );
        }
        // What a job may still choose: how to scan and how eagerly to follow.
        let c = job("name = \"a\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\n\
             tracking.gain = 0.5\ntracking.deadband_px = 0.5\nimaging.micrograph.width = 640\n")
        .unwrap();
        assert_eq!((c.tracking.gain, c.imaging.micrograph.width), (0.5, 640));
    }

    /// inf/NaN were "queued" then silently set aside (JSON has no inf): refused at parse.
    #[test]
    fn numbers_must_be_finite_and_the_key_is_named() {
        for (body, key) in [
            ("start_tilt = nan\nend_tilt = 5\n", "start_tilt = NaN"),
            ("start_tilt = 0\nend_tilt = inf\n", "end_tilt = inf"),
            ("start_tilt = 0\nend_tilt = 5\nstep = -inf\n", "step = -inf"),
            (
                "start_tilt = 0\nend_tilt = 5\n[capture]\ntracking.gain = nan\n",
                "[capture] tracking.gain = NaN",
            ),
        ] {
            let err = JobSpec::parse(&format!("name = \"a\"\n{body}")).unwrap_err();
            assert_eq!(err.to_string(), format!("{key}: not a finite number"));
        }
    }

    /// `step = 1e-9` aborted submit and the daemon (a 56 GB plan); `1e-4` made a 70 000-step
    /// job: the operator's floor, step count and estimated duration bound every job.
    #[test]
    fn jobs_are_bounded_by_the_operators_limits() {
        let run = |body: &str| job(&format!("name = \"a\"\n{body}"));
        let err = run("start_tilt = 0\nend_tilt = 70\nstep = 1e-9\n").unwrap_err();
        assert_eq!(
            err.to_string(),
            "step = 0.000000001° is below the step floor daemon.min_step_deg = 0.1°"
        );
        let mut base = Config::default();
        base.daemon.min_step_deg = 1e-12;
        let err = JobSpec::parse("name = \"a\"\nstart_tilt = 0\nend_tilt = 70\nstep = 1e-9\n")
            .unwrap()
            .effective_config(&base)
            .unwrap_err();
        assert!(
            err.to_string().contains("gives more than 100000 steps"),
            "{err}"
        );
        let err = run("start_tilt = 0\nend_tilt = 70\nstep = 0.2\n").unwrap_err();
        assert_eq!(
            err.to_string(),
            "the job has 350 tilt steps, more than daemon.max_steps = 300"
        );
        // 0→10° of 2048×2048 micrographs at 500 µs a pixel and tracking frames to match: 7 h.
        let err = run(
            "start_tilt = 0\nend_tilt = 10\n[capture]\nimaging.micrograph.width = 2048\n\
             imaging.micrograph.height = 2048\nimaging.micrograph.dwell_us = 500.0\n\
             imaging.tracking.width = 2048\nimaging.tracking.height = 2048\n\
             imaging.tracking.dwell_us = 500.0\n",
        )
        .unwrap_err();
        assert!(
            err.to_string()
                .contains("more than daemon.max_job_minutes = 240"),
            "{err}"
        );
        run("start_tilt = 0\nend_tilt = 70\nstep = 0.5\n").unwrap();
    }

    #[test]
    fn a_huge_name_is_cut_short_in_the_error() {
        let name = "\u{1b}x".repeat(1_000_000);
        let err = JobSpec::parse(&format!(
            "name = \"{name}\"\nstart_tilt = 0\nend_tilt = 5\n"
        ))
        .unwrap_err()
        .to_string();
        assert!(
            err.len() < 500 && !err.contains('\u{1b}'),
            "{} bytes",
            err.len()
        );
    }

    #[test]
    fn a_job_file_is_read_capped_and_never_blocks() {
        let err = JobSpec::load(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "cannot read job file /dev/zero: it is a character device, not a regular file"
        );
        let dir = tempfile::tempdir().unwrap();
        let big = dir.path().join("big.toml");
        std::fs::write(&big, vec![b'#'; 100_000]).unwrap();
        let err = JobSpec::load(&big).unwrap_err().to_string();
        assert!(err.ends_with("it is larger than 65536 bytes"), "{err}");
    }

    #[test]
    fn spec_round_trips_through_json() {
        let spec = JobSpec::parse(
            "name = \"a\"\nstart_tilt = 0\nend_tilt = 5\nstep = 0.5\n[capture]\ntracking.gain = 0.5\n",
        )
        .unwrap();
        let json = serde_json::to_string(&spec).unwrap();
        let again: JobSpec = serde_json::from_str(&json).unwrap();
        assert_eq!(spec, again);
    }
}
