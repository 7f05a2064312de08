//! The tilts a series visits, checked against the stage's limits before any
//! command is sent.

use serde::{Deserialize, Serialize};

/// What the user asks for: from `start_tilt_deg` to `end_tilt_deg` in steps of `step_deg`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SeriesConfig {
    /// Stage tilt of the first micrograph, degrees. Default 0.
    pub start_tilt_deg: f64,
    /// Stage tilt of the last micrograph, degrees. Default 7.
    pub end_tilt_deg: f64,
    /// Size of one tilt step, degrees, > 0 (the direction follows start → end).
    /// Default 1, the step the SD-SEM tracking is designed for.
    pub step_deg: f64,
}

impl Default for SeriesConfig {
    fn default() -> Self {
        Self {
            start_tilt_deg: 0.0,
            end_tilt_deg: 7.0,
            step_deg: 1.0,
        }
    }
}

/// Why a series cannot be planned. Every variant names the key at fault.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("series.step_deg = {step} must be greater than 0")]
    NonPositiveStep { step: f64 },
    #[error(
        "series.step_deg = {step} is larger than 10°: the tracking frames would lose the specimen"
    )]
    StepTooLarge { step: f64 },
    #[error(
        "series.start_tilt_deg = series.end_tilt_deg = {tilt}: a stereo pair needs two different tilts"
    )]
    NoTiltRange { tilt: f64 },
    #[error(
        "series.{key} = {tilt}° is outside the stage tilt limits [{min}°, {max}°] \
         (stage.tilt_min_deg / stage.tilt_max_deg)"
    )]
    OutsideLimits {
        key: &'static str,
        tilt: f64,
        min: f64,
        max: f64,
    },
    #[error("series.{key} is not a finite number")]
    NotFinite { key: &'static str },
    #[error(
        "series.step_deg = {step} gives more than {MAX_PLAN_STEPS} steps from \
         series.start_tilt_deg to series.end_tilt_deg: choose a larger step"
    )]
    TooManySteps { step: f64 },
    #[error(
        "the stage tilt limits are inverted: stage.tilt_min_deg = {min}° is not below \
         stage.tilt_max_deg = {max}° (swap them)"
    )]
    InvertedLimits { min: f64, max: f64 },
}

/// Most steps a plan holds, whatever the limits of the daemon: the plan is a list in memory.
pub const MAX_PLAN_STEPS: usize = 100_000;

/// Tilts of a series, in the order they are visited; the first and the last
/// are the end micrographs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeriesPlan {
    tilts: Vec<f64>,
}

impl SeriesPlan {
    /// Plans the visit of every step from start to end; the last step is
    /// shortened when the range is not a whole number of steps.
    ///
    /// # Errors
    /// [`PlanError`] for a non-positive or huge step, an empty range, or a
    /// tilt outside `[tilt_min, tilt_max]`.
    pub fn new(series: &SeriesConfig, tilt_min: f64, tilt_max: f64) -> Result<Self, PlanError> {
        let SeriesConfig {
            start_tilt_deg: start,
            end_tilt_deg: end,
            step_deg: step,
        } = *series;
        for (key, v) in [
            ("start_tilt_deg", start),
            ("end_tilt_deg", end),
            ("step_deg", step),
        ] {
            if !v.is_finite() {
                return Err(PlanError::NotFinite { key });
            }
        }
        if step <= 0.0 {
            return Err(PlanError::NonPositiveStep { step });
        }
        if step > 10.0 {
            return Err(PlanError::StepTooLarge { step });
        }
        if start == end {
            return Err(PlanError::NoTiltRange { tilt: start });
        }
        // Checked before the series against them: with min ≥ max every tilt is "outside".
        if tilt_min >= tilt_max {
            return Err(PlanError::InvertedLimits {
                min: tilt_min,
                max: tilt_max,
            });
        }
        for (key, tilt) in [("start_tilt_deg", start), ("end_tilt_deg", end)] {
            if tilt < tilt_min || tilt > tilt_max {
                return Err(PlanError::OutsideLimits {
                    key,
                    tilt,
                    min: tilt_min,
                    max: tilt_max,
                });
            }
        }
        let direction = (end - start).signum();
        let span = (end - start).abs();
        // Tolerate floating-point dust: 7/1 must give 7 steps, not 8 with a 1e-15 one.
        let whole = (span / step + 1e-9).floor();
        #[allow(clippy::cast_precision_loss)]
        if whole >= MAX_PLAN_STEPS as f64 {
            return Err(PlanError::TooManySteps { step });
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let whole_steps = whole as usize;
        let mut tilts: Vec<f64> = (0..=whole_steps)
            .map(|k| start + direction * step * k as f64)
            .collect();
        if (span - whole * step).abs() > 1e-9 {
            tilts.push(end);
        } else if let Some(last) = tilts.last_mut() {
            *last = end;
        }
        Ok(Self { tilts })
    }

    /// Every tilt, first to last.
    #[must_use]
    pub fn tilts(&self) -> &[f64] {
        &self.tilts
    }

    /// Number of steps between the first and the last tilt.
    #[must_use]
    pub fn steps(&self) -> usize {
        self.tilts.len() - 1
    }

    #[must_use]
    pub fn first(&self) -> f64 {
        self.tilts[0]
    }

    #[must_use]
    pub fn last(&self) -> f64 {
        self.tilts[self.tilts.len() - 1]
    }

    /// True when the series climbs, so the first micrograph is the left one
    /// (DESIGN §3: left = lower tilt).
    #[must_use]
    pub fn ascending(&self) -> bool {
        self.last() > self.first()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(start: f64, end: f64, step: f64) -> SeriesConfig {
        SeriesConfig {
            start_tilt_deg: start,
            end_tilt_deg: end,
            step_deg: step,
        }
    }

    #[test]
    fn zero_to_seven_visits_eight_tilts() {
        let plan = SeriesPlan::new(&series(0.0, 7.0, 1.0), -5.0, 70.0).unwrap();
        assert_eq!(plan.tilts(), &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        assert_eq!(plan.steps(), 7);
        assert!(plan.ascending());
    }

    #[test]
    fn descending_series_and_partial_last_step() {
        let plan = SeriesPlan::new(&series(3.0, 0.5, 1.0), -5.0, 70.0).unwrap();
        assert_eq!(plan.tilts(), &[3.0, 2.0, 1.0, 0.5]);
        assert!(!plan.ascending());
    }

    #[test]
    fn fractional_steps_do_not_add_a_dust_step() {
        let plan = SeriesPlan::new(&series(0.0, 0.3, 0.1), -5.0, 70.0).unwrap();
        assert_eq!(plan.tilts().len(), 4);
        assert_eq!(plan.last(), 0.3);
    }

    #[test]
    fn bad_steps_name_the_key() {
        // 1e-9 would have been a 70-billion-tilt list (a 56 GB allocation): refused before.
        let err = SeriesPlan::new(&series(0.0, 70.0, 1e-9), -5.0, 70.0).unwrap_err();
        assert_eq!(err, PlanError::TooManySteps { step: 1e-9 });
        for step in [0.0, -1.0] {
            let err = SeriesPlan::new(&series(0.0, 7.0, step), -5.0, 70.0).unwrap_err();
            assert!(err.to_string().contains("series.step_deg"), "{err}");
        }
    }

    #[test]
    fn end_beyond_limits_names_key_and_limit() {
        let err = SeriesPlan::new(&series(0.0, 75.0, 1.0), -5.0, 70.0).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("series.end_tilt_deg = 75"), "{msg}");
        assert!(msg.contains("[-5°, 70°]"), "{msg}");
    }

    /// Swapped limits are named as such, not as a tilt "outside [60°, -5°]".
    #[test]
    fn inverted_limits_are_called_inverted() {
        let err = SeriesPlan::new(&series(0.0, 7.0, 1.0), 60.0, -5.0).unwrap_err();
        let msg = err.to_string();
        assert!(msg.contains("limits are inverted"), "{msg}");
        assert!(
            msg.contains("stage.tilt_min_deg = 60°") && msg.contains("stage.tilt_max_deg = -5°"),
            "{msg}"
        );
        assert!(!msg.contains("outside"), "{msg}");
    }
}
