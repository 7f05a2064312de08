//! Parameters of the dense stage: SIFT flow (its keys inline), then the steps the stereo pair
//! adds to it.

use serde::{Deserialize, Serialize};

use super::DenseError;
use super::anchor::AnchorParams;
use super::reassign::ReassignParams;
use super::sift_flow::FlowParams;
use super::slanted::SlantedParams;
use super::support::SupportParams;
use crate::vision::Preset;
use crate::vision::filter::bilateral_grid::BilateralParams;
use crate::vision::filter::detail::DetailParams;

/// Parameters of the dense stage. One line each: effect, then the paper preset's value where
/// it differs from the improved default.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DenseParams {
    /// SIFT flow, eq. (10) of Liu et al. (its keys sit in this table).
    #[serde(flatten)]
    pub flow: FlowParams,
    /// Half search window of the vertical flow at the top level (paper 10, as wide as u's).
    pub vertical_top_window: usize,
    /// Half search window of the vertical flow below the top (paper 2, as wide as u's).
    pub vertical_window: usize,
    /// Centre the search on the sparse matches' disparity range, deepening the pyramid to span it (paper false).
    pub search_from_sparse: bool,
    /// Match both ways, mask pixels whose matches disagree, rate each by confidence (paper false).
    pub left_right_check: bool,
    /// Left–right disagreement above which a pixel is masked, pixels.
    pub lr_tolerance: f32,
    /// The tolerance away from steps of the flow (see `reassign.band`), pixels.
    pub lr_tolerance_smooth: f32,
    /// Fill runs of unknown pixels along a canvas row up to this long, measured at both ends; 0 = none.
    pub fill_max_gap: usize,
    /// Weigh every pixel in the bilateral filter by its confidence (paper false).
    pub weighted_filter: bool,
    /// Re-assignment of the flow beside depth discontinuities (paper: `enabled = false`).
    pub reassign: ReassignParams,
    /// The bilateral grid filter of the disparity (Paris & Durand 2009).
    pub bilateral: BilateralParams,
    /// Put back the relief the bilateral filter removed: beyond the predicted noise (`enabled`) or smoothed (`twicing_sigma`); both opt-in.
    pub detail: DetailParams,
    /// Leave unknown what the micrographs cannot tell: texture, distinctiveness (opt-in, `enabled = true`).
    pub support: SupportParams,
    /// Measure the flanks the left–right check rejects again with slanted windows (opt-in, `enabled = true`).
    pub slanted: SlantedParams,
    /// Leave unknown the featureless pixels texture on both sides along the parallax does not pin (opt-in, `enabled = true`).
    pub anchor: AnchorParams,
    /// Peak memory of the stage, MiB: a larger rectified canvas is matched in overlapping tiles; 0 = never tile.
    pub memory_budget_mib: usize,
    /// On a left micrograph above this many megapixels, raise `finest_level` and `levels` by one per
    /// halving that brings it within them (and double the left–right tolerances), so the matcher's
    /// windows span as much specimen as on a small micrograph (as SIFT's `sift_max_megapixels`
    /// copy does); 0 = never (paper 0).
    pub finest_max_megapixels: f64,
}

impl Default for DenseParams {
    fn default() -> Self {
        Self::preset(Preset::default())
    }
}

impl DenseParams {
    /// The parameters of a preset.
    #[must_use]
    pub fn preset(preset: Preset) -> Self {
        let improved = Self {
            flow: FlowParams::preset(Preset::Improved),
            vertical_top_window: 2,
            vertical_window: 1,
            search_from_sparse: true,
            left_right_check: true,
            lr_tolerance: 2.0,
            lr_tolerance_smooth: 4.0,
            fill_max_gap: 0,
            weighted_filter: true,
            reassign: ReassignParams::default(),
            bilateral: BilateralParams::default(),
            detail: DetailParams::default(),
            support: SupportParams::default(),
            slanted: SlantedParams::default(),
            anchor: AnchorParams::default(),
            memory_budget_mib: 1024,
            finest_max_megapixels: 4.0,
        };
        match preset {
            Preset::Improved => improved,
            Preset::Paper => Self {
                flow: FlowParams::preset(Preset::Paper),
                vertical_top_window: 10,
                vertical_window: 2,
                search_from_sparse: false,
                left_right_check: false,
                finest_max_megapixels: 0.0,
                weighted_filter: false,
                reassign: ReassignParams {
                    enabled: false,
                    ..ReassignParams::default()
                },
                support: SupportParams {
                    enabled: false,
                    rim_px: 0.0,
                    rim_from_texture: false,
                    rim_side: 0.0,
                    ..SupportParams::default()
                },
                detail: DetailParams {
                    enabled: false,
                    ..DetailParams::default()
                },
                anchor: AnchorParams {
                    enabled: false,
                    ..AnchorParams::default()
                },
                ..improved
            },
        }
    }

    /// Checks every figure; the first bad one is named.
    ///
    /// # Errors
    /// [`DenseError::InvalidParameter`].
    pub fn validate(&self) -> Result<(), DenseError> {
        self.flow.validate()?;
        let bad = |name: &'static str, reason: &str| {
            Err(DenseError::InvalidParameter {
                name,
                reason: reason.to_owned(),
            })
        };
        if self.vertical_window > 63 || self.vertical_top_window > 63 {
            return bad("vertical_window", "half windows are limited to 63 labels");
        }
        if self.lr_tolerance.is_nan() || self.lr_tolerance < 0.0 {
            return bad("lr_tolerance", "must be non-negative");
        }
        if self.lr_tolerance_smooth.is_nan() || self.lr_tolerance_smooth < 0.0 {
            return bad("lr_tolerance_smooth", "must be non-negative");
        }
        if !(self.finest_max_megapixels.is_finite() && self.finest_max_megapixels >= 0.0) {
            return bad("finest_max_megapixels", "must be finite and non-negative");
        }
        if let Some(name) = self.reassign.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        if let Some(name) = self.support.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        if let Some(name) = self.detail.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        if let Some(name) = self.slanted.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        if let Some(name) = self.anchor.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every key of the table is known: SIFT flow's, inlined, and the stage's own; any other
    /// is refused by name.
    #[test]
    fn unknown_keys_are_refused_by_name() {
        let text = toml::to_string(&DenseParams::default()).unwrap();
        let back: DenseParams = toml::from_str(&text).unwrap();
        assert_eq!(back, DenseParams::default());
        let p: DenseParams = toml::from_str("alpha = 100.0\nlr_tolerance = 3.0\n").unwrap();
        assert_eq!((p.flow.alpha, p.lr_tolerance), (100.0, 3.0));
        for bad in ["alpah = 1.0", "mode = \"paper\"", "[refine]\nwindow = 1"] {
            let err = toml::from_str::<DenseParams>(bad).unwrap_err().to_string();
            let key = bad
                .trim_start_matches("[refine]\n")
                .split(' ')
                .next()
                .unwrap();
            assert!(err.contains(key), "{bad}: {err}");
        }
    }
}
