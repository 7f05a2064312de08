//! The parameters of the whole reconstruction, one type per stage, and the two presets.
//!
//! A preset is a complete set of values, chosen once when the configuration is loaded
//! (`reconstruction.mode`); the stages never ask which preset they run under.

use serde::{Deserialize, Serialize};

use super::datum::DatumKind;
use super::dense::DenseParams;
use super::sparse::SparseParams;

/// A complete set of reconstruction parameters.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// The SD-SEM paper's pipeline as published (Liu et al.'s public SIFT-flow code): Lowe's DoG
    /// threshold, SIFT positions straight into the rectification, descriptors computed once and
    /// their images halved, integer flow, no occlusion handling, the plain bilateral filter.
    Paper,
    /// This implementation: sub-pixel inliers and a robust rectification pass; descriptors per
    /// pyramid level, sub-pixel flow refined on the intensities, a left–right check, per-pixel
    /// confidence and a confidence-weighted filter.
    #[default]
    Improved,
}

/// Parameters of the reconstruction of a pair: the sparse stage (SIFT, matching, ORSA,
/// rectification) and the dense stage (SIFT flow, refinement, consistency, filter).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReconstructionParams {
    pub sparse: SparseParams,
    pub dense: DenseParams,
    /// What zero height means (`reconstruction.datum`).
    pub datum: DatumKind,
}

impl ReconstructionParams {
    /// Every stage's parameters of `preset`.
    #[must_use]
    pub fn preset(preset: Preset) -> Self {
        Self {
            sparse: SparseParams::preset(preset),
            dense: DenseParams::preset(preset),
            datum: DatumKind::default(),
        }
    }
}
