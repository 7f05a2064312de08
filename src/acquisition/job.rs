//! One acquisition run, start to finish: record, connect, tilt series, end
//! micrographs on disk, reconstruction, outcome. `sdsem acquire` runs one; the
//! daemon runs one per job, keeping the instruments connected between them.
//!
//! Once the record exists, every failure ends up in it (the outcome metadata,
//! the `/log` topic) and the function still returns a report: the caller learns
//! how the run ended from [`JobReport::outcome`], never from a lost error.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use tracing::{error, info, warn};

use super::cancel::Cancel;
use super::instruments::{Instruments, RunObserver};
use super::machine::{FrameRole, Outcome, Series};
use super::plan::SeriesPlan;
use super::run_dir::RunDir;
use super::runner::{Captured, SeriesContext, SeriesRecord, run_series};
use crate::config::Config;
use crate::export::atomic::OutputDir;
use crate::imaging::SourceIdentity;
use crate::imaging::file::{MicrographTags, SampleDepth, encode_micrograph_tiff};
use crate::progress::Stage;
use crate::record::{
    RecordLogSwitch, RecordSummary, Recorder, RecorderHandle, RecorderOptions, RunOutcome,
    RunStatus, topics,
};
use crate::stage::StageAxis;
use crate::stage::observer::wall_ns;
use crate::vision::geometry::{Figures, GeometryError, GeometrySources, PairGeometry, Provenance};
use crate::vision::registration::PhaseCorrelationParams;

/// File names inside a run directory (DESIGN §4).
pub mod files {
    pub const RECORD: &str = "run.mcap";
    pub const LEFT: &str = "left.tif";
    pub const RIGHT: &str = "right.tif";
    pub const CONFIG: &str = "config.toml";
}

/// Why a run could not even be recorded.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("cannot create the run record {path}: {source}")]
    Record {
        path: PathBuf,
        source: crate::record::RecordError,
    },
}

/// How a run ended and what it left behind.
#[derive(Debug)]
pub struct JobReport {
    pub run_dir: PathBuf,
    pub outcome: Outcome,
    /// The series, when the instruments could be reached.
    pub series: Option<SeriesRecord>,
    /// The record as finished; `Err` with the cause when it could not be completed.
    pub record: Result<RecordSummary, String>,
}

/// What a run reports to, and hears from, whoever started it.
pub struct RunHooks<'a> {
    /// The operator's stop request.
    pub cancel: Cancel,
    /// Sends the run's log events into its record while it lasts.
    pub logs: Option<&'a RecordLogSwitch>,
    /// Each stage as it begins (tilt steps, frames, the reconstruction's stages), e.g. for
    /// the progress display or systemd's STATUS.
    pub progress: &'a (dyn Fn(Stage) + Send + Sync),
}

impl RunHooks<'_> {
    /// No operator, no log forwarding, no progress listener.
    #[must_use]
    pub fn detached() -> RunHooks<'static> {
        RunHooks {
            cancel: Cancel::never(),
            logs: None,
            progress: &|_| {},
        }
    }
}

/// Runs one acquisition into `run_dir` (fresh and empty). Connects the
/// instruments itself unless `instruments` are given (the daemon keeps them).
///
/// # Errors
/// [`JobError`] only when the record cannot be created; everything after that
/// is reported in [`JobReport::outcome`] and in the record. A record that could
/// not be written to its end (a full disk) fails the run with the write error.
pub async fn run_job(
    config: &Config,
    instruments: Option<&mut Instruments>,
    run_dir: &RunDir,
    hooks: RunHooks<'_>,
) -> Result<JobReport, JobError> {
    let RunHooks {
        cancel,
        logs,
        progress,
    } = hooks;
    let record_path = run_dir.join(files::RECORD);
    let record_error = |source| JobError::Record {
        path: record_path.clone(),
        source,
    };
    let file = run_dir.create_file(files::RECORD).map_err(|source| {
        record_error(crate::record::RecordError::Create {
            path: record_path.clone(),
            source,
        })
    })?;
    let recorder = Recorder::with_file(record_path.clone(), file, RecorderOptions::default())
        .map_err(record_error)?;
    let rec = recorder.handle();
    if let Some(logs) = logs {
        logs.attach(rec.clone());
    }
    let config_text = config.to_toml();
    if let Err(e) = run_dir.write_new(files::CONFIG, |w| w.write_all(config_text.as_bytes())) {
        warn!("cannot write the effective configuration beside the record: {e}");
    }
    let _ = rec.metadata(topics::METADATA_RUN, run_metadata(config, &config_text));
    info!(run_dir = %run_dir.path().display(), "run started");

    let (mut outcome, series) = acquire(config, instruments, run_dir, &rec, cancel, progress).await;
    // A record that stopped on a write error (a full disk) is the real cause of what followed.
    if let Some(cause) = rec.status().failed
        && !matches!(outcome, Outcome::Interrupted { .. })
    {
        outcome = failed(cause);
    }

    let (status, cause) = match &outcome {
        Outcome::Completed => (RunStatus::Succeeded, None),
        Outcome::Failed { reason } => (RunStatus::Failed, Some(reason.clone())),
        Outcome::Interrupted { reason } => (RunStatus::Aborted, Some(reason.clone())),
    };
    let _ = rec.outcome(&RunOutcome { status, cause });
    if let Some(logs) = logs {
        logs.detach();
    }
    drop(rec);
    let record = recorder.finish().map_err(|e| {
        error!(
            "the run record {} is incomplete: {e}",
            record_path.display()
        );
        e.to_string()
    });
    if let (Err(e), Outcome::Completed) = (&record, &outcome) {
        outcome = Outcome::Failed { reason: e.clone() };
    }
    Ok(JobReport {
        run_dir: run_dir.path().to_owned(),
        outcome,
        series,
        record,
    })
}

async fn acquire(
    config: &Config,
    instruments: Option<&mut Instruments>,
    run_dir: &RunDir,
    rec: &RecorderHandle,
    mut cancel: Cancel,
    progress: &(dyn Fn(Stage) + Send + Sync),
) -> (Outcome, Option<SeriesRecord>) {
    progress(Stage::Connect);
    let plan = match config.plan() {
        Ok(plan) => plan,
        Err(e) => return (failed(format!("invalid series: {e}")), None),
    };
    let mut owned;
    let instruments = match instruments {
        Some(i) => {
            i.observer.attach(rec.clone());
            i
        }
        None => {
            // Recording from the first byte: the handshake is in /stage/io too.
            let observer = Arc::new(RunObserver::default());
            observer.attach(rec.clone());
            match Instruments::connect_observed(config, observer).await {
                Ok(i) => {
                    owned = i;
                    &mut owned
                }
                Err(e) => return (failed(format!("cannot reach the instruments: {e}")), None),
            }
        }
    };
    // The controller's soft limits are only known now: a series beyond them is
    // refused before the stage moves at all, not at the step that hits them.
    let limits = instruments.stage.limits(StageAxis::Tilt);
    if let Err(reason) = check_plan_against_limits(&plan, config.stage.safe_tilt_deg, limits) {
        instruments.observer.detach();
        return (failed(reason), None);
    }
    let mut ids = BTreeMap::new();
    ids.insert("stage".to_owned(), instruments.stage_identity.clone());
    let stage = instruments.stage.instrument();
    for (key, value) in [
        ("stage_protocol", &stage.protocol),
        ("stage_vendor", &stage.vendor),
        ("stage_model", &stage.model),
        ("stage_version", &stage.version),
        ("stage_serial", &stage.serial),
    ] {
        if !value.is_empty() {
            ids.insert(key.to_owned(), value.clone());
        }
    }
    ids.insert("sem".to_owned(), instruments.sem_identity.clone());
    ids.insert(
        "sem_protocol".to_owned(),
        config.imaging.protocol.as_str().to_owned(),
    );
    let known = instruments.imaging.identity();
    insert_sem_identity(&mut ids, &known);
    let _ = rec.metadata(topics::METADATA_INSTRUMENTS, ids);

    let mut series = Series::new(plan, config.tracking, config.stage.safe_tilt_deg);
    let mut ctx = SeriesContext {
        stage: &mut instruments.stage,
        imaging: instruments.imaging.as_mut(),
        imaging_config: &config.imaging,
        recorder: rec,
        phase: PhaseCorrelationParams::default(),
        progress,
    };
    let record = run_series(&mut series, &mut ctx, &mut cancel).await;
    instruments.observer.detach();
    let learnt = instruments.imaging.identity();
    if learnt != known && !learnt.is_empty() {
        // A watched folder names who stored the files only in the files themselves.
        let mut ids = BTreeMap::new();
        insert_sem_identity(&mut ids, &learnt);
        let _ = rec.metadata(topics::METADATA_INSTRUMENTS_FROM_FRAMES, ids);
    }

    let mut outcome = record.outcome.clone();
    if outcome.is_completed()
        && let Err(e) = write_micrographs(&record, run_dir)
    {
        outcome = failed(format!("cannot write the micrographs: {e}"));
    }
    if outcome.is_completed() && config.run.reconstruct {
        if let Some(reason) = cancel.reason() {
            outcome = Outcome::Interrupted { reason };
        } else {
            if let Err(e) = reconstruct_series(config, &record, run_dir, rec, progress).await {
                outcome = failed(format!("reconstruction failed: {e:#}"));
            }
        }
    }
    (outcome, Some(record))
}

/// `sem_vendor`, `sem_model`, `sem_version`, `sem_serial`: those known.
fn insert_sem_identity(ids: &mut BTreeMap<String, String>, id: &SourceIdentity) {
    for (key, value) in [
        ("sem_vendor", &id.vendor),
        ("sem_model", &id.model),
        ("sem_version", &id.version),
        ("sem_serial", &id.serial),
    ] {
        if !value.is_empty() {
            ids.insert(key.to_owned(), value.clone());
        }
    }
}

/// Reconstructs the end micrographs into the run directory (every file new) and the
/// record, telling `progress` each stage. CPU-bound: runs on the blocking pool so the async
/// side stays responsive; the stages come back over a channel.
async fn reconstruct_series(
    config: &Config,
    record: &SeriesRecord,
    run_dir: &RunDir,
    rec: &RecorderHandle,
    progress: &(dyn Fn(Stage) + Send + Sync),
) -> anyhow::Result<()> {
    let (Some(left), Some(right)) = (&record.left, &record.right) else {
        anyhow::bail!("the pair is incomplete");
    };
    let (geometry, provenance) = pair_geometry(config, left, right)?;
    let (l, r) = (left.image.clone(), right.image.clone());
    let recon_config = config.reconstruction.clone();
    let out: OutputDir = run_dir.outputs()?;
    let rec = rec.clone();
    let (stages, mut told) = tokio::sync::mpsc::unbounded_channel();
    let mut work = tokio::task::spawn_blocking(move || {
        crate::app::reconstruct::reconstruct_recorded_pair(
            &l,
            &r,
            (&geometry, provenance),
            &recon_config,
            &out,
            Some(&rec),
            (Path::new(files::LEFT), Path::new(files::RIGHT)),
            &|stage| {
                let _ = stages.send(stage);
            },
        )
        .map(|(report, _)| report)
    });
    let report = loop {
        tokio::select! {
            biased;
            Some(stage) = told.recv() => progress(stage),
            done = &mut work => break done??,
        }
    };
    while let Ok(stage) = told.try_recv() {
        progress(stage);
    }
    let t = &report.reconstruction.timings;
    info!(
        total_s = crate::numbers::secs(t.total_ms / 1e3),
        inliers = report.reconstruction.sparse.inliers,
        "reconstruction done in {:.1} s: heights on {:.1} % of the left micrograph",
        t.total_ms / 1e3,
        100.0 * report.reconstruction.depth.valid_fraction
    );
    Ok(())
}

/// What the geometry of a pair is computed from, per end micrograph: what
/// the acquisition knew when it was grabbed, and what its record keeps
/// (`/sem/frame_info`), so `sdsem replay` computes the very same geometry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EndGeometry {
    /// The stage tilt verified before the frame was grabbed, degrees.
    pub tilt_deg: f64,
    /// The SEM's pixel size, µm.
    pub pixel_size_um: f64,
    /// φ as the SEM reported it, degrees; `None` if it did not.
    pub tilt_axis_deg: Option<f64>,
}

impl From<&Captured> for EndGeometry {
    fn from(c: &Captured) -> Self {
        Self {
            tilt_deg: c.stage.tilt_deg,
            pixel_size_um: c.frame.meta.pixel_size_um,
            tilt_axis_deg: Some(c.frame.meta.tilt_axis_deg),
        }
    }
}

impl From<EndGeometry> for Figures {
    fn from(e: EndGeometry) -> Self {
        Self {
            tilt_deg: Some(e.tilt_deg),
            pixel_size_um: Some(e.pixel_size_um),
            tilt_axis_deg: e.tilt_axis_deg,
        }
    }
}

/// θ from the verified tilts, the pixel size and the tilt axis from the SEM, the configured
/// `reconstruction.tilt_axis_deg` when the SEM did not report one: the precedence of every
/// command ([`GeometrySources::resolve`]), with nothing given on a command line.
///
/// # Errors
/// When the micrographs disagree on the pixel size, the right one is not at the higher tilt,
/// or no tilt axis is known.
pub fn pair_geometry(
    config: &Config,
    left: &Captured,
    right: &Captured,
) -> Result<(PairGeometry, Provenance), GeometryError> {
    pair_geometry_of(config, left.into(), right.into())
}

/// [`pair_geometry`] from the figures alone.
///
/// # Errors
/// As [`pair_geometry`].
pub fn pair_geometry_of(
    config: &Config,
    left: EndGeometry,
    right: EndGeometry,
) -> Result<(PairGeometry, Provenance), GeometryError> {
    GeometrySources {
        given: Figures::default(),
        left: left.into(),
        right: right.into(),
        configured_tilt_axis_deg: config.reconstruction.tilt_axis_deg,
        names: [files::LEFT.to_owned(), files::RIGHT.to_owned()],
    }
    .resolve()
}

/// Every planned tilt and the safe tilt inside the limits the driver enforces
/// (the configured ones narrowed to the controller's `TMN?`/`TMX?`).
///
/// # Errors
/// One line naming the key, the value and both limits.
fn check_plan_against_limits(
    plan: &SeriesPlan,
    safe: f64,
    (min, max): (f64, f64),
) -> Result<(), String> {
    let outside = |t: f64| !(min..=max).contains(&t);
    let (first, last) = (plan.first(), plan.last());
    let culprit = [
        ("series.start_tilt_deg", first),
        ("series.end_tilt_deg", last),
        ("stage.safe_tilt_deg", safe),
    ]
    .into_iter()
    .find(|&(_, t)| outside(t));
    match culprit {
        None => Ok(()),
        Some((key, tilt)) => Err(format!(
            "{key} = {tilt}° is outside the tilt limits [{min}°, {max}°] of the stage \
             controller (its soft limits TMN?/TMX? narrow stage.tilt_min_deg/tilt_max_deg); \
             nothing was moved: choose tilts inside them"
        )),
    }
}

fn failed(reason: String) -> Outcome {
    error!("{reason}");
    Outcome::Failed { reason }
}

/// `left.tif` and `right.tif`, 16-bit, with tilt and pixel size in their metadata.
fn write_micrographs(record: &SeriesRecord, run_dir: &RunDir) -> Result<(), String> {
    for (role, captured, name) in [
        (FrameRole::Left, &record.left, files::LEFT),
        (FrameRole::Right, &record.right, files::RIGHT),
    ] {
        let Some(Captured {
            frame,
            image,
            stage,
        }) = captured
        else {
            return Err(format!("the {role} micrograph was not captured"));
        };
        let mut extra = serde_json::Map::new();
        extra.insert("role".into(), role.as_str().into());
        extra.insert("stage_x_um".into(), stage.x_um.into());
        extra.insert("stage_y_um".into(), stage.y_um.into());
        extra.insert("tilt_axis_deg".into(), frame.meta.tilt_axis_deg.into());
        extra.insert("dwell_us".into(), frame.meta.dwell_us.into());
        extra.insert("frame".into(), frame.meta.frame.into());
        let tags = MicrographTags {
            pixel_size_um: Some(frame.meta.pixel_size_um),
            tilt_deg: Some(stage.tilt_deg),
            extra,
        };
        let depth = if frame.pixels.bits() == 8 {
            SampleDepth::Bits8
        } else {
            SampleDepth::Bits16
        };
        run_dir
            .write_new(name, |w| {
                encode_micrograph_tiff(w, image, &tags, depth).map_err(std::io::Error::other)
            })
            .map_err(|e| format!("{}: {e}", run_dir.join(name).display()))?;
    }
    Ok(())
}

fn run_metadata(config: &Config, config_text: &str) -> BTreeMap<String, String> {
    let mut m = BTreeMap::new();
    m.insert("job".to_owned(), config.run.name.clone());
    m.insert("config".to_owned(), config_text.to_owned());
    m.insert("version".to_owned(), env!("CARGO_PKG_VERSION").to_owned());
    m.insert("host".to_owned(), host_name());
    m.insert("started".to_owned(), crate::record::utc_time(wall_ns()));
    m.insert(
        "simulated".to_owned(),
        config.simulator.is_some().to_string(),
    );
    m
}

fn host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|s| s.trim().to_owned())
        .ok()
        .filter(|s| !s.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "unknown".to_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_series_beyond_the_controller_limits_is_refused_naming_key_and_limits() {
        let config = crate::acquisition::SeriesConfig {
            start_tilt_deg: 0.0,
            end_tilt_deg: 65.0,
            step_deg: 1.0,
        };
        let plan = SeriesPlan::new(&config, -5.0, 70.0).unwrap();
        assert!(check_plan_against_limits(&plan, 0.0, (-5.0, 70.0)).is_ok());
        let e = check_plan_against_limits(&plan, 0.0, (-5.0, 60.0)).unwrap_err();
        assert!(
            e.contains("series.end_tilt_deg = 65°") && e.contains("[-5°, 60°]"),
            "{e}"
        );
        let e = check_plan_against_limits(&plan, 0.0, (1.0, 70.0)).unwrap_err();
        assert!(e.contains("series.start_tilt_deg = 0°"), "{e}");
        let short = SeriesPlan::new(
            &crate::acquisition::SeriesConfig {
                start_tilt_deg: 10.0,
                end_tilt_deg: 12.0,
                step_deg: 1.0,
            },
            -5.0,
            70.0,
        )
        .unwrap();
        let e = check_plan_against_limits(&short, 0.0, (5.0, 70.0)).unwrap_err();
        assert!(e.contains("stage.safe_tilt_deg = 0°"), "{e}");
    }
}
