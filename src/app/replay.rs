//! `sdsem replay RUN.mcap --out DIR [--set key=value]`: reconstruct a run
//! again from its record alone (DESIGN §4, §5).
//!
//! The end micrographs come from `/sem/frame` (frame ids `left`, `right`),
//! their geometry from `/sem/frame_info` through
//! [`pair_geometry_of`](crate::acquisition::job::pair_geometry_of), the
//! configuration from the `sdsem.run` metadata record (the `config.toml`
//! beside the record only when that record is missing), and the
//! reconstruction runs through [`reconstruct_recorded_pair`], the very code
//! `sdsem acquire` ran. The new height map is then compared with the recorded
//! `/recon/height`, bit for bit: the pipeline is deterministic (seeded
//! RANSAC, reductions independent of the thread count), so without `--set`
//! any difference is a defect worth reporting.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde::Serialize;

use super::reconstruct::{ReportFile, reconstruct_recorded_pair};
use crate::acquisition::job::{EndGeometry, pair_geometry_of};
use crate::config::Config;
use crate::record::{self, FrameRole, ReadError, RecordedMicrograph, topics};
use crate::vision::Image;
use crate::vision::geometry::PairGeometry;

/// The file `replay` writes beside the reconstruction outputs.
pub const REPLAY_REPORT: &str = "replay.json";

/// What a replay did and found (`DIR/replay.json`, `sdsem replay --json`).
#[derive(Debug, Clone, Serialize)]
pub struct ReplayReport {
    pub record: PathBuf,
    pub out: PathBuf,
    /// Where the configuration came from.
    pub config_source: String,
    /// The `--set` overrides applied over the recorded configuration.
    pub overrides: Vec<String>,
    /// False when the record was cut off (a killed run); `record_note` says where.
    pub record_complete: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub record_note: Option<String>,
    /// How the recorded run ended (`succeeded`, `failed`, `aborted`), if recorded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recorded_outcome: Option<String>,
    pub geometry: PairGeometry,
    pub comparison: Comparison,
    /// The new reconstruction's `report.json`.
    pub reconstruction: ReportFile,
}

impl ReplayReport {
    /// True when the replay is a failure: without overrides, a height map
    /// that differs from the recorded one (none recorded is not a failure).
    #[must_use]
    pub fn is_mismatch(&self) -> bool {
        self.overrides.is_empty() && matches!(self.comparison, Comparison::Differs(_))
    }
}

/// The new height map against the recorded `/recon/height`.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "verdict", rename_all = "snake_case")]
pub enum Comparison {
    /// Every pixel has the same bits (NaN where the record has NaN).
    Identical { width: usize, height: usize },
    /// At least one pixel differs.
    Differs(HeightDifference),
    /// The record holds no height map (the run did not reconstruct, or was cut off before).
    NotRecorded { reason: String },
}

/// How two height maps differ.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeightDifference {
    /// Size of the recorded map.
    pub recorded: [usize; 2],
    /// Size of the replayed map.
    pub replayed: [usize; 2],
    /// Pixels whose bits differ (all of them when the sizes differ).
    pub pixels_differing: usize,
    pub pixels: usize,
    /// Pixels known in one map only.
    pub valid_only_recorded: usize,
    pub valid_only_replayed: usize,
    /// Over the pixels known in both, µm.
    pub max_abs_diff_um: f64,
    pub rms_diff_um: f64,
}

impl Comparison {
    /// One line for the terminal.
    #[must_use]
    pub fn summary(&self) -> String {
        match self {
            Self::Identical { width, height } => format!(
                "height map bit-for-bit identical to the recorded /recon/height ({width}×{height})"
            ),
            Self::Differs(d) if d.recorded != d.replayed => format!(
                "height map differs from the recorded /recon/height: {}×{} here, {}×{} recorded",
                d.replayed[0], d.replayed[1], d.recorded[0], d.recorded[1]
            ),
            Self::Differs(d) => format!(
                "height map differs from the recorded /recon/height: {} of {} pixels \
                 ({:.4} %), max |Δh| {}, RMS {} over pixels known in both; \
                 known only in the record {}, only here {}",
                d.pixels_differing,
                d.pixels,
                100.0 * ratio(d.pixels_differing, d.pixels),
                crate::numbers::fmt_um(d.max_abs_diff_um),
                crate::numbers::fmt_um(d.rms_diff_um),
                d.valid_only_recorded,
                d.valid_only_replayed
            ),
            Self::NotRecorded { reason } => format!("nothing to compare with: {reason}"),
        }
    }
}

#[allow(clippy::cast_precision_loss)]
fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 { 0.0 } else { a as f64 / b as f64 }
}

/// Compares a replayed height map with the recorded one, bit for bit.
#[must_use]
pub fn compare_heights(recorded: &Image, replayed: &Image) -> Comparison {
    let (rw, rh) = recorded.dimensions();
    let (pw, ph) = replayed.dimensions();
    let pixels = pw * ph;
    if (rw, rh) != (pw, ph) {
        return Comparison::Differs(HeightDifference {
            recorded: [rw, rh],
            replayed: [pw, ph],
            pixels_differing: pixels,
            pixels,
            valid_only_recorded: 0,
            valid_only_replayed: 0,
            max_abs_diff_um: f64::NAN,
            rms_diff_um: f64::NAN,
        });
    }
    let mut d = HeightDifference {
        recorded: [rw, rh],
        replayed: [pw, ph],
        pixels_differing: 0,
        pixels,
        valid_only_recorded: 0,
        valid_only_replayed: 0,
        max_abs_diff_um: 0.0,
        rms_diff_um: 0.0,
    };
    let mut sum_sq = 0.0_f64;
    for (&a, &b) in recorded.data().iter().zip(replayed.data()) {
        if a.to_bits() == b.to_bits() {
            continue;
        }
        d.pixels_differing += 1;
        match (a.is_finite(), b.is_finite()) {
            (true, true) => {
                let diff = f64::from(a) - f64::from(b);
                d.max_abs_diff_um = d.max_abs_diff_um.max(diff.abs());
                sum_sq += diff * diff;
            }
            (true, false) => d.valid_only_recorded += 1,
            (false, true) => d.valid_only_replayed += 1,
            (false, false) => {}
        }
    }
    if d.pixels_differing == 0 {
        return Comparison::Identical {
            width: pw,
            height: ph,
        };
    }
    // Identical pixels count in the RMS too: it is over every pixel known in both.
    let known_both = recorded
        .data()
        .iter()
        .zip(replayed.data())
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .count();
    #[allow(clippy::cast_precision_loss)]
    let known_both = known_both as f64;
    d.rms_diff_um = if known_both == 0.0 {
        0.0
    } else {
        (sum_sq / known_both).sqrt()
    };
    Comparison::Differs(d)
}

/// Reconstructs the run recorded in `record` into `out` with the recorded
/// configuration (and `overrides` over it), and compares the height map
/// with the recorded one.
///
/// # Errors
/// One line naming the cause: not an MCAP file, no end micrographs (with
/// where the record was cut off, if it was), no recorded configuration, an
/// invalid override, or the reconstruction's own error.
pub fn replay(record: &Path, out: &Path, overrides: &[String]) -> anyhow::Result<ReplayReport> {
    let inputs = record::read_replay_inputs(record).map_err(|e| match e {
        ReadError::NotMcap { .. } => {
            anyhow::anyhow!("{e} (give the run.mcap of a run directory, e.g. runs/sim-…/run.mcap)")
        }
        other => anyhow::Error::new(other),
    })?;
    let end = &inputs.ends.end;
    let cut_off = end
        .stopped_by
        .as_ref()
        .map(|why| format!("the record is truncated: {why}"));
    let outcome_note = inputs
        .outcome
        .as_ref()
        .map(|o| match &o.cause {
            Some(cause) => format!("the run {}: {cause}", o.status.as_str()),
            None => format!("the run {}", o.status.as_str()),
        })
        .or_else(|| cut_off.clone())
        .unwrap_or_else(|| "the record has no outcome".to_owned());
    let (left, right) = match (&inputs.ends.left, &inputs.ends.right) {
        (Some(l), Some(r)) => (l, r),
        (l, _) => {
            let missing = if l.is_none() {
                "no end micrographs (neither left nor right)"
            } else {
                "no right micrograph"
            };
            bail!(
                "{} holds {missing}: nothing to reconstruct ({outcome_note})",
                record.display()
            );
        }
    };

    let (config_text, config_source) = recorded_config(record, inputs.run.as_ref())?;
    let origin = if config_source.starts_with("its metadata") {
        PathBuf::from(format!("{} ({config_source})", record.display()))
    } else {
        PathBuf::from(&config_source)
    };
    let config_text = crate::config::upgrade_recorded(&config_text);
    let config = Config::from_layers(
        Some(&config_text),
        Some(&origin),
        overrides,
        std::iter::empty(),
    )
    .with_context(|| {
        if overrides.is_empty() {
            format!(
                "the configuration recorded in {} is unusable",
                record.display()
            )
        } else {
            "the recorded configuration with the --set overrides is invalid".to_owned()
        }
    })?;

    let (geometry, provenance) = pair_geometry_of(
        &config,
        end_geometry(record, left)?,
        end_geometry(record, right)?,
    )?;
    let (reconstruction, recon) = reconstruct_recorded_pair(
        &left.image,
        &right.image,
        (&geometry, provenance),
        &config.reconstruction,
        out,
        None,
        (
            &PathBuf::from(format!("{}#left", record.display())),
            &PathBuf::from(format!("{}#right", record.display())),
        ),
    )?;

    let comparison = match &inputs.height {
        Some(recorded) => {
            let recorded = recorded.to_image().with_context(|| {
                format!(
                    "the recorded /recon/height of {} is damaged",
                    record.display()
                )
            })?;
            compare_heights(&recorded, &recon.height_um)
        }
        None => Comparison::NotRecorded {
            reason: format!(
                "{} holds no /recon/height ({})",
                record.display(),
                if config.run.reconstruct {
                    outcome_note.clone()
                } else {
                    "the run had run.reconstruct = false".to_owned()
                }
            ),
        },
    };
    let report = ReplayReport {
        record: record.to_owned(),
        out: out.to_owned(),
        config_source,
        overrides: overrides.to_vec(),
        record_complete: end.complete,
        record_note: cut_off,
        recorded_outcome: inputs.outcome.map(|o| o.status.as_str().to_owned()),
        geometry,
        comparison,
        reconstruction,
    };
    crate::export::report::write_report_atomic(&out.join(REPLAY_REPORT), &report)?;
    Ok(report)
}

/// The recorded effective configuration: the `sdsem.run` metadata, else the
/// `config.toml` the run wrote beside its record.
fn recorded_config(
    record: &Path,
    run: Option<&std::collections::BTreeMap<String, String>>,
) -> anyhow::Result<(String, String)> {
    if let Some(text) = run.and_then(|m| m.get("config")) {
        return Ok((
            text.clone(),
            format!("its metadata {}", topics::METADATA_RUN),
        ));
    }
    let beside = record
        .parent()
        .unwrap_or(Path::new("."))
        .join(crate::acquisition::job::files::CONFIG);
    match std::fs::read_to_string(&beside) {
        Ok(text) => Ok((text, beside.display().to_string())),
        Err(_) => bail!(
            "{} holds no recorded configuration (no {} metadata with a config entry) and no {} \
             lies beside it: it was not written by sdsem acquire or the daemon",
            record.display(),
            topics::METADATA_RUN,
            beside.display()
        ),
    }
}

fn end_geometry(record: &Path, m: &RecordedMicrograph) -> anyhow::Result<EndGeometry> {
    let Some(info) = &m.info else {
        bail!(
            "{}: the {} micrograph has no /sem/frame_info (tilt and pixel size unknown)",
            record.display(),
            if m.role == FrameRole::Left {
                "left"
            } else {
                "right"
            }
        );
    };
    Ok(EndGeometry {
        tilt_deg: info.tilt_deg,
        pixel_size_um: info.pixel_size_um,
        tilt_axis_deg: info.tilt_axis_deg,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(values: &[f32]) -> Image {
        Image::from_vec(values.len(), 1, values.to_vec()).unwrap()
    }

    #[test]
    fn identical_maps_with_nan_compare_equal() {
        let a = image(&[1.0, f32::NAN, -2.5]);
        assert_eq!(
            compare_heights(&a, &a.clone()),
            Comparison::Identical {
                width: 3,
                height: 1
            }
        );
    }

    #[test]
    fn differences_are_measured() {
        let recorded = image(&[1.0, f32::NAN, -2.5, 0.0]);
        let replayed = image(&[1.0, 3.0, -2.0, f32::NAN]);
        let Comparison::Differs(d) = compare_heights(&recorded, &replayed) else {
            panic!("they differ");
        };
        assert_eq!(d.pixels_differing, 3);
        assert_eq!(d.pixels, 4);
        assert_eq!(d.valid_only_recorded, 1);
        assert_eq!(d.valid_only_replayed, 1);
        assert!((d.max_abs_diff_um - 0.5).abs() < 1e-12);
        // Known in both: pixels 0 (Δ 0) and 2 (Δ 0.5).
        assert!((d.rms_diff_um - (0.125_f64).sqrt()).abs() < 1e-12);
        assert!(
            compare_heights(&recorded, &image(&[1.0]))
                .summary()
                .contains("1×1 here")
        );
        let summary = compare_heights(&recorded, &replayed).summary();
        assert!(
            summary.contains("max |Δh| 0.5 µm, RMS 0.354 µm"),
            "{summary}"
        );
    }
}
