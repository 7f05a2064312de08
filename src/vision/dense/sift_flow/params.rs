//! Parameters of SIFT flow (Liu, Yuen, Torralba, PAMI 2011), names as in eq. (10) and the
//! reference code, and the plan of the coarse-to-fine engine they give.

use serde::{Deserialize, Serialize};

use super::bp::MAX_STATES;
use crate::vision::Preset;
use crate::vision::dense::DenseError;
use crate::vision::dense::refine::RefineParams;

/// How the descriptor images of the coarser pyramid levels are made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DescriptorPyramid {
    /// Descriptors once at full resolution, their images blurred and halved (the reference code).
    Halved,
    /// An image pyramid, descriptors recomputed on every level (see `keep_cell_extent`).
    PerLevel,
}

/// How many coarser grids BP's multigrid start descends below a level (the top always 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum WarmStartGrids {
    /// This many below every level.
    Count(usize),
    /// `"to_top"`: down to the top level's resolution, one more per level (the reference code).
    ToTop(ToTop),
}

/// The name of [`WarmStartGrids::ToTop`] in the configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ToTop {
    ToTop,
}

/// Parameters of SIFT flow. One line each: effect, then the paper preset's value where it
/// differs from the improved default.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct FlowParams {
    /// Dense SIFT cell at the finest BP level, pixels; a descriptor spans 4 cells (paper 3).
    pub cell_size: usize,
    /// Descriptors of the coarser levels: `per_level` or `halved` (paper).
    pub descriptors: DescriptorPyramid,
    /// `per_level`: coarser levels keep the finest cell's extent in full-resolution pixels.
    pub keep_cell_extent: bool,
    /// α, slope of the truncated-L1 smoothness of eq. (10): larger is smoother.
    pub alpha: f32,
    /// α at the finest BP level is `alpha` times this, against label speckle (paper 1).
    pub finest_alpha_scale: f32,
    /// d, truncation of the smoothness of eq. (10): lower keeps steps in the flow sharper.
    pub d: f32,
    /// Truncation of the smoothness at the finest BP level; none = `d`.
    pub finest_d: Option<f32>,
    /// Finest BP level: truncation on edges of strong intensity contrast; ≥ that level's d = off (paper inf).
    pub edge_d: f32,
    /// Contrast, in medians of the image's neighbour differences, at which `edge_d` takes over.
    pub edge_contrast: f32,
    /// η, weight of the small-displacement term |u| + |v| of eq. (10), doubled per coarser level.
    pub gamma: f32,
    /// t, truncation of the data term of eq. (10); none = plain L1 (the reference code).
    pub t: Option<f32>,
    /// Pyramid levels; the top is 1/2^(levels−1) of the image.
    pub levels: usize,
    /// Half search window at the top level, its pixels.
    pub top_window: usize,
    /// Half search window around the upsampled flow at the finest BP level.
    pub window: usize,
    /// Half search window at the levels between the top and the finest BP level (paper 2).
    pub middle_window: usize,
    /// BP iterations at the top level (paper 60).
    pub top_iterations: usize,
    /// BP iterations at the finest level, falling to 60 % at the coarsest but one (paper 30).
    pub iterations: usize,
    /// Coarser grids of BP's multigrid start below each level but the top (paper "to_top").
    pub warm_start_grids: WarmStartGrids,
    /// BP iterations on each grid of the multigrid start (paper 20).
    pub warm_start_iterations: usize,
    /// Levels above the finest stop after this many iterations without a label change; 0 = never (paper 0).
    pub settle_iterations: usize,
    /// Start the inter-layer messages from the data term (paper false).
    pub dual_init_from_data: bool,
    /// Equiangular sub-pixel offsets on the data term at the finest BP level (paper false: integer flow).
    pub subpixel: bool,
    /// Parallel row strips of the BP sweeps; 1 = strictly sequential BP-S.
    pub max_strips: usize,
    /// Finest pyramid level BP runs on; the refinement takes the flow on to full resolution (paper 0).
    pub finest_level: usize,
    /// Lucas–Kanade refinement of the flow on the intensities (paper: `iterations = 0`, none).
    pub refine: RefineParams,
}

impl Default for FlowParams {
    fn default() -> Self {
        Self::preset(Preset::default())
    }
}

/// Rows per BP strip at least (strips below this height would lose more to
/// late boundary messages than they gain).
pub(super) const MIN_STRIP_ROWS: usize = 48;
/// Smallest side of the top level.
pub(super) const MIN_TOP_SIDE: usize = 8;

/// Per-level plan of the coarse-to-fine engine.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct LevelPlan {
    /// Half windows of the u and v layers.
    pub window: [usize; 2],
    /// Dense SIFT cell of the level (`per_level` descriptors), its pixels.
    pub cell_size: usize,
    pub iterations: usize,
    /// Coarser grids of the multigrid BP initialisation.
    pub hierarchy: usize,
}

impl FlowParams {
    /// The parameters of a preset: `improved` (this implementation) or `paper` (the reference code).
    #[must_use]
    pub fn preset(preset: Preset) -> Self {
        let improved = Self {
            cell_size: 2,
            descriptors: DescriptorPyramid::PerLevel,
            keep_cell_extent: true,
            alpha: 2.0 * 255.0,
            finest_alpha_scale: 4.0,
            d: 40.0 * 255.0,
            finest_d: None,
            edge_d: 10.0 * 255.0,
            edge_contrast: 2.0,
            gamma: 0.005 * 255.0,
            t: None,
            levels: 4,
            top_window: 10,
            window: 2,
            middle_window: 4,
            top_iterations: 20,
            iterations: 8,
            warm_start_grids: WarmStartGrids::Count(3),
            warm_start_iterations: 10,
            settle_iterations: 3,
            dual_init_from_data: true,
            subpixel: true,
            max_strips: 4,
            finest_level: 1,
            refine: RefineParams::default(),
        };
        match preset {
            Preset::Improved => improved,
            Preset::Paper => Self {
                cell_size: 3,
                descriptors: DescriptorPyramid::Halved,
                finest_alpha_scale: 1.0,
                edge_d: f32::INFINITY,
                middle_window: 2,
                top_iterations: 60,
                iterations: 30,
                warm_start_grids: WarmStartGrids::ToTop(ToTop::ToTop),
                warm_start_iterations: 20,
                settle_iterations: 0,
                dual_init_from_data: false,
                subpixel: false,
                finest_level: 0,
                refine: RefineParams {
                    iterations: 0,
                    ..RefineParams::default()
                },
                ..improved
            },
        }
    }

    /// Iterations of level `l` (0 = finest) as the reference code spreads
    /// them: the top gets `top_iterations`, the others fall linearly from
    /// `iterations` at the finest to 60 % of it at the coarsest.
    fn iterations_at(&self, l: usize) -> usize {
        if l + 1 == self.levels {
            return self.top_iterations;
        }
        let n = self.iterations as f64;
        let frac = if self.levels > 1 {
            l as f64 / (self.levels - 1) as f64
        } else {
            0.0
        };
        (n - 0.4 * n * frac).round() as usize
    }

    /// Checks every figure; the first bad one is named.
    ///
    /// # Errors
    /// [`DenseError::InvalidParameter`].
    pub fn validate(&self) -> Result<(), DenseError> {
        let bad = |name: &'static str, reason: &str| {
            Err(DenseError::InvalidParameter {
                name,
                reason: reason.to_owned(),
            })
        };
        let max_w = (MAX_STATES - 1) / 2;
        if self.levels == 0 {
            return bad("levels", "needs at least 1 pyramid level");
        }
        if self.cell_size == 0 {
            return bad("cell_size", "must be at least 1 pixel");
        }
        if self.window > max_w || self.top_window > max_w || self.middle_window > max_w {
            return bad("window", "half windows are limited to 63 labels");
        }
        let usable = |v: f32| v.is_finite() && v >= 0.0;
        if !(usable(self.alpha) && usable(self.d) && usable(self.gamma)) {
            return bad("alpha/d/gamma", "must be finite and non-negative");
        }
        if !usable(self.finest_alpha_scale) || self.finest_alpha_scale > 100.0 {
            return bad("finest_alpha_scale", "must be between 0 and 100");
        }
        if self.finest_d.is_some_and(|d| !usable(d)) {
            return bad("finest_d", "must be finite and non-negative");
        }
        if self.edge_d.is_nan() || self.edge_d < 0.0 {
            return bad("edge_d", "must be non-negative (inf: off)");
        }
        if !(self.edge_contrast.is_finite() && self.edge_contrast > 0.0) {
            return bad("edge_contrast", "must be a positive number");
        }
        if self.t.is_some_and(|t| t.is_nan() || t < 0.0) {
            return bad("t", "must be non-negative");
        }
        if self.max_strips == 0 {
            return bad("max_strips", "must be at least 1");
        }
        if self.finest_level >= self.levels {
            return bad("finest_level", "must be below `levels`");
        }
        if let Some(name) = self.refine.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        Ok(())
    }

    /// The finest BP level.
    #[must_use]
    pub fn finest(&self) -> usize {
        self.finest_level.min(self.levels.saturating_sub(1))
    }

    /// The intensity refinement, if any.
    #[must_use]
    pub fn refinement(&self) -> Option<&RefineParams> {
        (self.refine.iterations > 0).then_some(&self.refine)
    }

    /// The plan of every level, finest first; `vertical` gives the v layer's half windows below
    /// and at the top (`None`: as wide as u's).
    pub(crate) fn plan(&self, vertical: Option<(usize, usize)>) -> Vec<LevelPlan> {
        let finest = self.finest();
        (0..self.levels)
            .map(|l| {
                let top = l + 1 == self.levels;
                let wu = if top {
                    self.top_window
                } else if l > finest {
                    self.middle_window
                } else {
                    self.window
                };
                let wv = match vertical {
                    Some((below, at_top)) => {
                        if top {
                            at_top
                        } else {
                            below
                        }
                    }
                    None => wu,
                };
                LevelPlan {
                    window: [wu, wv],
                    cell_size: match self.descriptors {
                        DescriptorPyramid::Halved => self.cell_size,
                        DescriptorPyramid::PerLevel => {
                            level_cell_size(self.cell_size, l, finest, self.keep_cell_extent)
                        }
                    },
                    iterations: self.iterations_at(l),
                    hierarchy: match self.warm_start_grids {
                        _ if top => 2,
                        WarmStartGrids::Count(n) => n,
                        WarmStartGrids::ToTop(_) => self.levels - 1 - l,
                    },
                }
            })
            .collect()
    }
}

/// The dense SIFT cell of pyramid level `l` with `per_level` descriptors: `cell_size` at the
/// finest BP level `finest` and, with `keep_cell_extent`, the same extent in full-resolution
/// pixels above it, `cell_size / 2^(l − finest)` rounded, at least 1 (the paper's halved
/// descriptor pyramid keeps that extent too). A cell of fixed size in every level's pixels
/// doubles the descriptor's footprint per level, so near a wall the coarse levels match
/// descriptors that mostly see the wall, one side in each view.
#[must_use]
pub fn level_cell_size(cell_size: usize, l: usize, finest: usize, keep_cell_extent: bool) -> usize {
    if !keep_cell_extent || l <= finest {
        return cell_size;
    }
    let k = (l - finest).min(31) as i32;
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let c = (cell_size as f64 / 2f64.powi(k)).round() as usize;
    c.max(1)
}

/// Checks that the top level of `levels` still has a usable size.
/// The smallest image side `levels` pyramid levels accept.
pub(crate) fn min_side(levels: usize) -> usize {
    MIN_TOP_SIDE << levels.saturating_sub(1).min(16)
}

pub(crate) fn check_size(w: usize, h: usize, levels: usize) -> Result<(), DenseError> {
    let (mut tw, mut th) = (w, h);
    for _ in 1..levels {
        tw = super::pyramid::half_size(tw);
        th = super::pyramid::half_size(th);
    }
    if tw < MIN_TOP_SIDE || th < MIN_TOP_SIDE {
        return Err(DenseError::TooSmall {
            width: w,
            height: h,
            levels,
            min_top: MIN_TOP_SIDE,
        });
    }
    Ok(())
}
