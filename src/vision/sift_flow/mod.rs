//! SIFT flow (Liu, Yuen, Torralba, PAMI 2011): dense correspondence by
//! matching dense SIFT descriptors under the energy of eq. (10), minimised by
//! dual-layer belief propagation (BP-S), coarse to fine.
//!
//! [`sift_flow`] matches two arbitrary images (`sdsem flow`); the rectified
//! stereo stage ([`crate::vision::dense`]) drives the same engine with a
//! small vertical window.

pub mod bp;
pub mod energy;
pub mod pyramid;

use std::time::Instant;

use serde::{Deserialize, Serialize};

use self::bp::{DualLayerBp, MAX_STATES};
use self::energy::{DataTerm, EnergyWeights, LabelSpace};
use super::Image;
use super::dense::DenseError;
use super::dense_sift::{DenseSiftParams, DescriptorImage, dense_sift, dense_sift_where};
use super::subpixel::{RefineParams, RefinedFlow, refine_flow_down_to, upsample_flow};
use crate::progress::{Observer, Stage, unobserved};

/// Which pipeline to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// The SD-SEM paper's pipeline as published (Liu et al.'s public code):
    /// descriptors computed once at full resolution and their images blurred
    /// and subsampled for the pyramid, integer flow, no occlusion handling.
    Paper,
    /// This implementation's improvements: descriptors recomputed on each
    /// level of an image pyramid, sub-pixel flow, and for stereo a left–right
    /// consistency check, confidence-weighted filtering.
    #[default]
    Improved,
}

/// Parameters of SIFT flow, names as in eq. (10) and the reference code.
///
/// | parameter | default | effect |
/// | --- | --- | --- |
/// | `mode` | `improved` | `paper` reproduces the published pipeline (see [`Mode`]) |
/// | `cell_size` | 3 | dense SIFT cell, pixels (descriptor spans 4 cells) |
/// | `keep_cell_extent` | true | improved mode: the levels above the finest BP level compute their descriptors with the cell of the same extent in full-resolution pixels, `cell_size / 2^k` `k` levels up (rounded, at least 1), as the paper's descriptor pyramid keeps it; false = `cell_size` pixels of every level (see [`level_cell_size`]) |
/// | `alpha` | 2·255 | α, slope of the truncated L1 smoothness: larger is smoother |
/// | `d` | 40·255 | truncation of the smoothness: lower keeps flow discontinuities sharper |
/// | `finest_alpha_scale` | 4 | improved mode: α at the finest BP level is this many times `alpha` (the levels above keep `alpha`, which must let the flow jump between the bars of tall structures). There the flow searches ±`window` labels around the upsampled one, and a stronger pull between neighbours removes the label speckle on which the forward and backward fields disagree in weakly textured areas. 1 → 4: Potamogeton pairs agree over 71.5/66.4/65.0 → 79.8/73.5/72.6 % of the image at the same RMSE (0.73/0.72/0.40 → 0.74/0.72/0.40 µm); on the 16 simulated cases the targets met stay the same (grid 640×480 > 1 px 4.3 → 4.7 %, dome 1024×768 1.3 → 1.5 %, the rest within ±0.1 point), RubberWhale EPE 0.135 px either way. α itself raised instead (×2 at every level) breaks the grid at 1024×768 (RMSE 3.4 → 11.4 % at ×4 α) |
/// | `finest_d` | none | improved mode: truncation of the smoothness at the finest BP level; none = `d`. Lower lets the flow step sharply at walls (a step of `finest_d / (alpha · finest_alpha_scale)` labels or more costs the same as any larger one) but frees label speckle on weakly textured surface: 2550 (1.25 labels) takes the simulated grid 1024×768 from 3.5 to 2.6 % of pixels off by more than 1 px and grid 640×480's median from 0.204 to 0.196 px, and costs the Potamogeton pairs 3.7–3.9 points of the image where they agree (86.6/80.8/80.3 → 82.9/77.2/76.4 %), measured against `d` with `edge_d` off (a `finest_d` at or below `edge_d` switches `edge_d` off; the contrast-sensitive `edge_d` keeps most of the gain at a tenth of the loss) |
/// | `edge_d` | 2550 | improved mode, finest BP level: the truncation on the edges between pixels whose intensities differ strongly, where depth steps lie (contrast-sensitive: `edge_d + (d′ − edge_d)·exp(−(ΔI / (edge_contrast · median ΔI))²)`, `d′` = `finest_d` or `d`; `edge_d` ≥ `d′` switches it off). The flow steps sharply at walls without the label speckle a uniformly low truncation frees on weakly textured surface (see `finest_d`): simulated grid 1024×768 > 1 px 3.5 → 2.9 %, grid 640×480 median 0.204 → 0.198 px and RMSE 6.3 → 5.8 % of the relief, grid 1280×960 coverage 89.3 → 89.1 %; the Potamogeton pairs agree over 86.6/80.8/80.3 → 86.3/80.3/79.9 % of the image at the same RMSE; RubberWhale EPE 0.135 px either way |
/// | `edge_contrast` | 2 | improved mode: the intensity difference, in medians of all neighbour differences of the image, at which `edge_d` takes over (3: grid 1024×768 > 1 px 3.1 %) |
/// | `gamma` | 0.005·255 | η, weight of the small-displacement term \|u\| + \|v\| (doubled per coarser level) |
/// | `t` | none | truncation of the data term; none = plain L1 as the reference code |
/// | `levels` | 4 | pyramid levels (the top is 1/2^(levels−1) of the image) |
/// | `top_window` | 10 | half search window at the top level, top-level pixels |
/// | `window` | 2 | half search window around the upsampled flow at the finest BP level |
/// | `middle_window` | none | half search window at the levels between the top and the finest BP level; none = `window` (paper) or [`IMPROVED_MIDDLE_WINDOW`] (improved) |
/// | `top_iterations` | none | BP iterations at the top level; none = 60 (paper) or 20 (improved) |
/// | `iterations` | none | BP iterations at the finest level (falling to 60 % at the coarsest but one); none = 30 (paper) or 8 (improved) |
/// | `max_strips` | 4 | parallel row strips of the BP sweeps; 1 = strictly sequential BP-S |
/// | `finest_level` | none | the finest pyramid level BP runs on; none = 0 (paper) or 1 (improved, where the intensity refinement takes the flow to full resolution) |
/// | `refine` | see [`RefineParams`] | improved mode: Lucas–Kanade refinement of the flow on the intensities (`iterations = 0`: none) |
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FlowParams {
    pub mode: Mode,
    pub cell_size: usize,
    pub keep_cell_extent: bool,
    pub alpha: f32,
    pub finest_alpha_scale: f32,
    pub d: f32,
    pub finest_d: Option<f32>,
    pub edge_d: f32,
    pub edge_contrast: f32,
    pub gamma: f32,
    pub t: Option<f32>,
    pub levels: usize,
    pub top_window: usize,
    pub window: usize,
    pub middle_window: Option<usize>,
    pub top_iterations: Option<usize>,
    pub iterations: Option<usize>,
    pub max_strips: usize,
    pub finest_level: Option<usize>,
    pub refine: RefineParams,
}

impl Default for FlowParams {
    fn default() -> Self {
        Self {
            mode: Mode::default(),
            cell_size: 3,
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
            middle_window: None,
            top_iterations: None,
            iterations: None,
            max_strips: 4,
            finest_level: None,
            refine: RefineParams::default(),
        }
    }
}

/// What one pyramid level did (goes into report.json).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LevelReport {
    /// 0 = full resolution.
    pub level: usize,
    pub width: usize,
    pub height: usize,
    /// Half windows of the u and v layers.
    pub window_u: usize,
    pub window_v: usize,
    /// Dense SIFT cell, pixels of the image the descriptors were computed on
    /// (this level's in the improved mode; full resolution in the paper mode,
    /// whose descriptor images are halved level by level).
    pub cell_size: usize,
    pub iterations: usize,
    /// Energy (10) after every BP iteration (the paper's Fig. 8).
    pub energy: Vec<f64>,
    pub descriptor_ms: f64,
    pub data_term_ms: f64,
    pub bp_ms: f64,
}

/// A dense correspondence from image A to image B: pixel `(x, y)` of A
/// matches `(x + u, y + v)` of B.
#[derive(Debug, Clone)]
pub struct Flow {
    pub u: Image,
    pub v: Image,
    /// Finest level first.
    pub levels: Vec<LevelReport>,
    pub total_ms: f64,
}

impl Flow {
    /// Figures of the flow for report.json (Table 4's v²/u² ratio).
    #[must_use]
    pub fn stats(&self) -> FlowStats {
        FlowStats::of(&self.u, &self.v)
    }
}

/// Summary of a flow field: how vertical it is (paper Table 4 reports the
/// ratio Σv²/Σu² before and after rectification).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FlowStats {
    /// Σv² / Σu² over the finite pixels.
    pub v2_over_u2: f64,
    /// √(mean v²), pixels.
    pub rms_v: f64,
    /// √(mean u²), pixels.
    pub rms_u: f64,
}

impl FlowStats {
    /// Over the pixels where both components are finite.
    #[must_use]
    pub fn of(u: &Image, v: &Image) -> Self {
        let (mut su, mut sv, mut n) = (0f64, 0f64, 0usize);
        for (&a, &b) in u.data().iter().zip(v.data()) {
            if a.is_finite() && b.is_finite() {
                su += f64::from(a).powi(2);
                sv += f64::from(b).powi(2);
                n += 1;
            }
        }
        let n = n.max(1) as f64;
        Self {
            v2_over_u2: if su > 0.0 { sv / su } else { f64::NAN },
            rms_v: (sv / n).sqrt(),
            rms_u: (su / n).sqrt(),
        }
    }
}

/// Per-level plan of the coarse-to-fine engine.
#[derive(Debug, Clone, Copy)]
pub(crate) struct LevelPlan {
    pub window: [usize; 2],
    /// Dense SIFT cell of the level (improved mode), its pixels.
    pub cell_size: usize,
    pub iterations: usize,
    /// Coarser grids of the multigrid BP initialisation.
    pub hierarchy: usize,
}

/// Half search window of the improved mode between the top and the finest
/// BP level. The top level cannot place a tall, steep-walled structure
/// exactly (its descriptors mix the walls, seen on one side in each view),
/// and a window of 2 cannot catch up level by level: on the simulated grid
/// of 1024×768 at θ = 11° the bars stayed 7 px low (median error 2.26 px,
/// RMSE 21 % of the relief); with 4, 0.64 px and 13.5 %, other scenes
/// unchanged, for a few per cent more matching time (these levels are small).
pub const IMPROVED_MIDDLE_WINDOW: usize = 4;

/// The dense SIFT cell of pyramid level `l` in the improved mode, where each
/// level computes its own descriptors: `cell_size` at the finest BP level
/// `finest` and, with `keep_cell_extent`, the same extent in full-resolution
/// pixels above it, `cell_size / 2^(l − finest)` rounded, at least 1 (the
/// paper's descriptor pyramid keeps that extent too). A cell of fixed size in
/// every level's pixels doubles the descriptor's footprint per level, so near
/// a wall the coarse levels match descriptors that mostly see the wall, one
/// side in each view. On the 16 simulated cases keeping the extent lifts the
/// grids (1024×768: coverage 67.3 → 78.4 %, RMSE 8.3 → 5.7 % of the relief,
/// median 0.32 → 0.24 px; 1280×960: 83.1 → 90.2 %, 7.6 → 6.8 %) and leaves
/// the others within ±0.1 % RMSE; Potamogeton's pairs agree better (RMSE
/// 0.86 / 1.03 / 0.51 → 0.83 / 0.85 / 0.45 µm).
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

/// Multigrid grids below the top level in the improved mode (the upsampled
/// flow already starts BP near the solution there).
const IMPROVED_LOWER_HIERARCHY: usize = 3;

/// Improved mode: BP at a coarser level stops once the labels of both layers
/// have not changed for this many iterations (such a level hands on only its
/// labels). On the 16 simulated cases, RubberWhale and the Potamogeton pairs
/// every figure stays the same to the last digit (on the simulated cases with
/// 2 as well), for 27 % fewer BP iterations over the 16 cases (528 → 386); at
/// the top level of the 1280×960 pair 20 → 10 iterations, 188 → 114 ms.
const SETTLED_ITERATIONS: usize = 3;

/// BP iterations on each coarser grid of the multigrid initialisation in the
/// improved mode (half the reference's: RubberWhale's EPE does not change).
const IMPROVED_HIERARCHY_ITERATIONS: usize = 10;

/// BP iterations on each coarser grid of the multigrid initialisation (reference code).
const HIERARCHY_ITERATIONS: usize = 20;

/// Everything the engine needs besides the images.
#[derive(Debug, Clone)]
pub(crate) struct Engine {
    pub mode: Mode,
    pub cell_size: usize,
    pub alpha: f32,
    /// α at the finest BP level is `alpha` times this (improved mode).
    pub finest_alpha_scale: f32,
    pub d: f32,
    /// Truncation at the finest BP level (improved mode; none = `d`).
    pub finest_d: Option<f32>,
    /// Contrast-sensitive truncation at the finest BP level (improved mode):
    /// the tight value and its intensity scale (see [`energy::contrast_truncation`]).
    pub edge_d: f32,
    pub edge_contrast: f32,
    pub gamma: f32,
    pub t: Option<f32>,
    /// Finest first.
    pub plan: Vec<LevelPlan>,
    pub max_strips: usize,
    /// The finest level BP runs on (0 = full resolution).
    pub finest: usize,
    /// Horizontal displacement the top level's window is centred on, from A
    /// to B, full-resolution pixels (B to A: the opposite); 0 = none.
    pub top_shift: f32,
}

/// The finest level's result of the engine.
pub(crate) struct EngineRun {
    /// Size of the grid of `u`, `v` and `margin` (level `finest` of image A).
    pub width: usize,
    pub height: usize,
    pub u: Vec<f32>,
    pub v: Vec<f32>,
    /// Per pixel, how much worse the second-best distinct u label is than the
    /// best (belief units); large = unambiguous.
    pub margin: Vec<f32>,
    pub levels: Vec<LevelReport>,
}

/// Rows per BP strip at least (strips below this height would lose more to
/// late boundary messages than they gain).
const MIN_STRIP_ROWS: usize = 48;
/// Smallest side of the top level.
const MIN_TOP_SIDE: usize = 8;

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

impl FlowParams {
    /// Iterations of level `l` (0 = finest) as the reference code spreads
    /// them: the top gets `top_iterations`, the others fall linearly from
    /// `iterations` at the finest to 60 % of it at the coarsest.
    fn iterations_at(&self, l: usize) -> usize {
        // With the multigrid warm start the energy barely moves after a few
        // sweeps (RubberWhale: EPE 0.289 px with 30/60 iterations, 0.288 with 3/10).
        let (fine, top) = match self.mode {
            Mode::Paper => (30, 60),
            Mode::Improved => (8, 20),
        };
        if l + 1 == self.levels {
            return self.top_iterations.unwrap_or(top);
        }
        let n = self.iterations.unwrap_or(fine) as f64;
        let frac = if self.levels > 1 {
            l as f64 / (self.levels - 1) as f64
        } else {
            0.0
        };
        (n - 0.4 * n * frac).round() as usize
    }

    pub(crate) fn validate(&self) -> Result<(), DenseError> {
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
        if self.window > max_w
            || self.top_window > max_w
            || self.middle_window.is_some_and(|m| m > max_w)
        {
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
        if !usable(self.edge_d) {
            return bad("edge_d", "must be finite and non-negative");
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
        if self.finest_level.is_some_and(|f| f >= self.levels) {
            return bad("finest_level", "must be below `levels`");
        }
        if let Some(name) = self.refine.invalid_field() {
            return bad(name, "out of its range (see the parameter table)");
        }
        Ok(())
    }

    /// The half search window of the levels between the top and the finest.
    #[must_use]
    pub fn middle_window(&self) -> usize {
        self.middle_window.unwrap_or(match self.mode {
            Mode::Paper => self.window,
            Mode::Improved => IMPROVED_MIDDLE_WINDOW.max(self.window),
        })
    }

    /// The finest BP level of this mode.
    #[must_use]
    pub fn finest(&self) -> usize {
        match self.mode {
            Mode::Paper => self.finest_level.unwrap_or(0),
            Mode::Improved => self.finest_level.unwrap_or(1),
        }
        .min(self.levels.saturating_sub(1))
    }

    /// The intensity refinement of this mode, if any.
    #[must_use]
    pub fn refinement(&self) -> Option<&RefineParams> {
        (self.mode == Mode::Improved && self.refine.iterations > 0).then_some(&self.refine)
    }

    pub(crate) fn engine(&self, vertical: Option<(usize, usize)>) -> Engine {
        let plan = (0..self.levels)
            .map(|l| {
                let top = l + 1 == self.levels;
                let wu = if top {
                    self.top_window
                } else if l > self.finest() {
                    self.middle_window()
                } else {
                    self.window
                };
                let wv = match vertical {
                    Some((w_low, w_top)) => {
                        if top {
                            w_top
                        } else {
                            w_low
                        }
                    }
                    None => wu,
                };
                LevelPlan {
                    window: [wu, wv],
                    cell_size: match self.mode {
                        Mode::Paper => self.cell_size,
                        Mode::Improved => {
                            level_cell_size(self.cell_size, l, self.finest(), self.keep_cell_extent)
                        }
                    },
                    iterations: self.iterations_at(l),
                    // The reference code: 2 grids at the top, levels − 1 − l below.
                    hierarchy: if top {
                        2
                    } else if self.mode == Mode::Paper {
                        self.levels - 1 - l
                    } else {
                        IMPROVED_LOWER_HIERARCHY
                    },
                }
            })
            .collect();
        Engine {
            mode: self.mode,
            cell_size: self.cell_size,
            alpha: self.alpha,
            finest_alpha_scale: self.finest_alpha_scale,
            d: self.d,
            finest_d: self.finest_d,
            edge_d: self.edge_d,
            edge_contrast: self.edge_contrast,
            gamma: self.gamma,
            t: self.t,
            plan,
            max_strips: self.max_strips,
            finest: self.finest(),
            top_shift: 0.0,
        }
    }
}

/// Checks that the top level of `levels` still has a usable size.
pub(crate) fn check_size(w: usize, h: usize, levels: usize) -> Result<(), DenseError> {
    let (mut tw, mut th) = (w, h);
    for _ in 1..levels {
        tw = pyramid::half_size(tw);
        th = pyramid::half_size(th);
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

/// The flow of the coarser level and its size.
type Coarser<'f> = (&'f [Vec<f32>; 2], (usize, usize));

/// One level's label space and data term in one direction: all that BP
/// needs of the descriptors.
struct LevelData {
    space: LabelSpace,
    data: DataTerm,
    data_term_ms: f64,
}

/// Runs `forward`, and `backward` beside it when there is one.
fn forward_and_backward<T: Send>(
    forward: impl FnOnce() -> T + Send,
    backward: Option<impl FnOnce() -> T + Send>,
) -> (T, Option<T>) {
    match backward {
        Some(backward) => {
            let (f, b) = rayon::join(forward, backward);
            (f, Some(b))
        }
        None => (forward(), None),
    }
}

/// One direction's state between levels: the flow of the level just solved.
struct Direction {
    flow: [Vec<f32>; 2],
    margin: Vec<f32>,
    reports: Vec<LevelReport>,
}

/// Sizes of both images at every level, finest first: `(w_a, h_a, w_b, h_b)`.
fn level_sizes(a: &Image, b: &Image, levels: usize) -> Vec<(usize, usize, usize, usize)> {
    let mut sizes = vec![(a.width(), a.height(), b.width(), b.height())];
    for l in 1..levels {
        let (wa, ha, wb, hb) = sizes[l - 1];
        sizes.push((
            pyramid::half_size(wa),
            pyramid::half_size(ha),
            pyramid::half_size(wb),
            pyramid::half_size(hb),
        ));
    }
    sizes
}

/// Masks of every level, finest first.
fn mask_pyramid(
    mask: Option<&[bool]>,
    w: usize,
    h: usize,
    levels: usize,
) -> Vec<Option<Vec<bool>>> {
    let mut out = vec![mask.map(<[bool]>::to_vec)];
    let (mut w, mut h) = (w, h);
    for _ in 1..levels {
        let next = out
            .last()
            .and_then(|m| m.as_ref().map(|m| pyramid::halve_mask(m, w, h)));
        out.push(next);
        (w, h) = (pyramid::half_size(w), pyramid::half_size(h));
    }
    out
}

impl Engine {
    /// Runs coarse to fine from `a` to `b` and, when `both` is set, from `b`
    /// to `a` as well (for the left–right check). `valid_a`/`valid_b` mark
    /// usable pixels (row-major); an invalid pixel of the source image has no
    /// data term (its flow comes from its neighbours; beyond
    /// [`ACTIVE_MARGIN`] of a valid one BP leaves it out and it takes the flow
    /// of the nearest swept pixel of its row), one of the target cannot be
    /// matched.
    ///
    /// Level by level, the descriptors of both images are computed once and
    /// serve both directions, which then run at the same time (two sequential
    /// BP sweeps for two cores); only one level's descriptors are alive at once.
    pub(crate) fn run(
        &self,
        a: &Image,
        b: &Image,
        valid_a: Option<&[bool]>,
        valid_b: Option<&[bool]>,
        both: bool,
        progress: Observer<'_>,
    ) -> (EngineRun, Option<EngineRun>) {
        let levels = self.plan.len();
        let sift = DenseSiftParams {
            cell_size: self.cell_size,
        };
        let sizes = level_sizes(a, b, levels);
        let masks_a = mask_pyramid(valid_a, a.width(), a.height(), levels);
        let masks_b = mask_pyramid(valid_b, b.width(), b.height(), levels);

        // Paper: descriptors at full resolution, their images blurred and
        // subsampled (reference code). Improved: an image pyramid, descriptors
        // computed per level.
        let t0 = Instant::now();
        let mut desc_pyramid: Vec<(DescriptorImage, DescriptorImage)> = Vec::new();
        let mut img_pyramid: Vec<(Image, Image)> = Vec::new();
        match self.mode {
            Mode::Paper => {
                desc_pyramid.push(rayon::join(
                    || dense_sift(a, &sift),
                    || dense_sift(b, &sift),
                ));
                for l in 1..levels {
                    let (da, db) = &desc_pyramid[l - 1];
                    let next = rayon::join(
                        || pyramid::halve_descriptors(da),
                        || pyramid::halve_descriptors(db),
                    );
                    desc_pyramid.push(next);
                }
            }
            Mode::Improved => {
                img_pyramid.push((a.clone(), b.clone()));
                for l in 1..levels {
                    let (ia, ib) = &img_pyramid[l - 1];
                    let next = (pyramid::halve_image(ia), pyramid::halve_image(ib));
                    img_pyramid.push(next);
                }
            }
        }
        let pyramid_ms = ms(t0);

        let mut fwd: Option<Direction> = None;
        let mut bwd: Option<Direction> = None;
        for l in (self.finest..levels).rev() {
            progress(Stage::DenseLevel {
                level: levels - l,
                levels: levels - self.finest,
            });
            let td = Instant::now();
            // This level's descriptors, owned: they are dropped once its data
            // terms hold what BP needs of them (the paper mode's full-resolution
            // pair alone is 256 bytes a canvas pixel).
            let (da, db) = if self.mode == Mode::Paper {
                // Built finest first, taken coarsest first.
                desc_pyramid
                    .pop()
                    .expect("one descriptor level per BP level")
            } else {
                let (ia, ib) = &img_pyramid[l];
                let sift = DenseSiftParams {
                    cell_size: self.plan[l].cell_size,
                };
                // Each image's descriptors serve its real pixels only: as
                // the source they have the data term, as the target the
                // others are never matched.
                rayon::join(
                    || dense_sift_where(ia, &sift, masks_a[l].as_deref()),
                    || dense_sift_where(ib, &sift, masks_b[l].as_deref()),
                )
            };
            let descriptor_ms = ms(td) + if l + 1 == levels { pyramid_ms } else { 0.0 };
            let (wa, ha, wb, hb) = sizes[l];
            fn coarse(d: &Option<Direction>, wc_hc: (usize, usize)) -> Option<Coarser<'_>> {
                d.as_ref().map(|d| (&d.flow, wc_hc))
            }
            let up_a = if l + 1 < levels {
                Some((sizes[l + 1].0, sizes[l + 1].1))
            } else {
                None
            };
            let up_b = if l + 1 < levels {
                Some((sizes[l + 1].2, sizes[l + 1].3))
            } else {
                None
            };
            let source = |k: usize| {
                img_pyramid
                    .get(l)
                    .map(|(ia, ib)| if k == 0 { ia } else { ib })
            };
            let forward = || {
                self.data_term(
                    l,
                    &da,
                    &db,
                    (wa, ha, wb, hb),
                    masks_a[l].as_deref(),
                    masks_b[l].as_deref(),
                    up_a.and_then(|s| coarse(&fwd, s)),
                    self.top_shift,
                )
            };
            let backward = || {
                self.data_term(
                    l,
                    &db,
                    &da,
                    (wb, hb, wa, ha),
                    masks_b[l].as_deref(),
                    masks_a[l].as_deref(),
                    up_b.and_then(|s| coarse(&bwd, s)),
                    -self.top_shift,
                )
            };
            let (f, b) = forward_and_backward(forward, both.then_some(backward));
            drop((da, db));
            let mask_b = masks_b[l].as_deref();
            let (f, b) = forward_and_backward(
                || self.solve(l, source(0), f, masks_a[l].as_deref(), descriptor_ms),
                b.map(|b| move || self.solve(l, source(1), b, mask_b, descriptor_ms)),
            );
            fwd = Some(merge(fwd, f));
            bwd = match (bwd, b) {
                (prev, Some(b)) => Some(merge(prev, b)),
                (prev, None) => prev,
            };
        }
        let (width, height) = (sizes[self.finest].0, sizes[self.finest].1);
        let (width_b, height_b) = (sizes[self.finest].2, sizes[self.finest].3);
        let finish = |d: Direction, (width, height): (usize, usize)| {
            let [u, v] = d.flow;
            let mut reports = d.reports;
            reports.reverse();
            EngineRun {
                width,
                height,
                u,
                v,
                margin: d.margin,
                levels: reports,
            }
        };
        let fwd = fwd.expect("at least one level ran");
        (
            finish(fwd, (width, height)),
            bwd.map(|b| finish(b, (width_b, height_b))),
        )
    }

    /// The label space and data term of one level in one direction, around
    /// the flow of the coarser level (`None` at the top).
    #[allow(clippy::too_many_arguments)]
    fn data_term(
        &self,
        l: usize,
        da: &DescriptorImage,
        db: &DescriptorImage,
        (w, h, w2, h2): (usize, usize, usize, usize),
        mask_a: Option<&[bool]>,
        mask_b: Option<&[bool]>,
        coarser: Option<Coarser<'_>>,
        shift: f32,
    ) -> LevelData {
        let plan = self.plan[l];
        // The shift in this level's pixels (bounded by the image size).
        #[allow(clippy::cast_possible_truncation)]
        let top = (shift / (1u32 << l.min(31)) as f32).round() as i32;
        let offset = match coarser {
            // Top: proportional correspondence when the sizes differ, plus the shift.
            None => [
                (0..w * h)
                    .map(|p| proportional(p % w, w, w2) + top)
                    .collect(),
                (0..w * h).map(|p| proportional(p / w, h, h2)).collect(),
            ],
            Some((flow, (wc, hc))) => [
                pyramid::upsample_offsets(&flow[0], wc, hc, w, h),
                pyramid::upsample_offsets(&flow[1], wc, hc, w, h),
            ],
        };
        let space = LabelSpace {
            width: w,
            height: h,
            window: plan.window,
            offset,
        };
        let tdata = Instant::now();
        let data = DataTerm::compute(da, db, &space, mask_a, mask_b, self.t);
        LevelData {
            space,
            data,
            data_term_ms: ms(tdata),
        }
    }

    /// Solves one level in one direction by BP on its data term.
    fn solve(
        &self,
        l: usize,
        source: Option<&Image>,
        level: LevelData,
        mask_a: Option<&[bool]>,
        descriptor_ms: f64,
    ) -> Direction {
        let plan = self.plan[l];
        let LevelData {
            space,
            data,
            data_term_ms,
        } = level;
        let (w, h) = (space.width, space.height);
        // Improved mode: a stronger smoothness at the finest BP level only,
        // and there its own truncation if one is set.
        let finest_improved = l == self.finest && self.mode == Mode::Improved;
        let (alpha, d) = if finest_improved {
            (
                self.alpha * self.finest_alpha_scale,
                self.finest_d.unwrap_or(self.d),
            )
        } else {
            (self.alpha, self.d)
        };
        let weights = EnergyWeights {
            alpha,
            d,
            gamma: self.gamma * (1u32 << l.min(31)) as f32,
        };
        let tbp = Instant::now();
        let mut bp = DualLayerBp::new(&space, &data, weights, MIN_STRIP_ROWS, self.max_strips);
        let spans = mask_a.map(|m| bp::active_spans(m, w, h, ACTIVE_MARGIN));
        if let Some(spans) = &spans {
            bp.restrict(spans.clone());
        }
        // Contrast-sensitive truncation at the finest improved level: the
        // level's own source image says where depth may step.
        let edges =
            match source {
                Some(img) if finest_improved && self.edge_d < d => Some(
                    energy::contrast_truncation(img, d, self.edge_d, self.edge_contrast),
                ),
                _ => None,
            };
        if let Some(e) = &edges {
            bp.truncate_edges(e);
        }
        if self.mode == Mode::Improved {
            bp.init_dual_from_data();
        }
        let warm_iterations = match self.mode {
            Mode::Paper => HIERARCHY_ITERATIONS,
            Mode::Improved => IMPROVED_HIERARCHY_ITERATIONS,
        };
        bp.warm_start(plan.hierarchy, warm_iterations);
        // Improved mode, coarser levels (which hand on their labels only):
        // no more iterations once the labels have settled.
        let patience =
            (self.mode == Mode::Improved && l > self.finest).then_some(SETTLED_ITERATIONS);
        let outcome = bp.run_until_stable(plan.iterations, patience);
        let bp_ms = ms(tbp);
        let flow = if l == self.finest && self.mode == Mode::Improved {
            super::subpixel::refine(&data, &space, &outcome.labels)
        } else {
            [0, 1].map(|k| {
                (0..w * h)
                    .map(|p| space.flow(k, p, usize::from(outcome.labels[k][p])) as f32)
                    .collect()
            })
        };
        let flow = match &spans {
            Some(spans) => flow.map(|f| extend_rows(f, w, spans)),
            None => flow,
        };
        let margin = if l == self.finest {
            bp.margins(0)
        } else {
            Vec::new()
        };
        Direction {
            flow,
            margin,
            reports: vec![LevelReport {
                level: l,
                width: w,
                height: h,
                window_u: plan.window[0],
                window_v: plan.window[1],
                cell_size: plan.cell_size,
                iterations: outcome.energy.len(),
                energy: outcome.energy,
                descriptor_ms,
                data_term_ms,
                bp_ms,
            }],
        }
    }
}

/// Pixels (of the level) around the valid source pixels that BP sweeps with
/// them; farther ones take the flow of the nearest swept pixel of their row
/// ([`extend_rows`]). The fill has no data term: a wide ring of it only
/// carries the smoothness along the image's border. Measured: on the most
/// oblique simulated canvas (grid 1024×768, `sdsem eval dense`) RMSE 2.45 /
/// 2.43 / 2.70 / 3.05 / 3.47 % of the relief at margins 2 / 4 / 6 / 12 / 24
/// (3.48 % sweeping the whole canvas), the other 15 cases within 0.1 point;
/// the Potamogeton pairs (`sdsem eval potamogeton`) lose 0.1–0.3 point of
/// common coverage at 2, up to 0.1 at 4, none from 6.
const ACTIVE_MARGIN: usize = 4;

/// `field` (row-major, width `w`) with every pixel outside its row's span
/// set to the nearest one inside; a row without a span copies the nearest
/// row that has one (the field unchanged when none has).
fn extend_rows(mut field: Vec<f32>, w: usize, spans: &[(usize, usize)]) -> Vec<f32> {
    for (row, &(a, b)) in field.chunks_exact_mut(w).zip(spans) {
        if b > a {
            let (first, last) = (row[a], row[b - 1]);
            row[..a].fill(first);
            row[b..].fill(last);
        }
    }
    let filled: Vec<usize> = (0..spans.len())
        .filter(|&y| spans[y].1 > spans[y].0)
        .collect();
    for y in (0..spans.len()).filter(|&y| spans[y].1 <= spans[y].0) {
        // The nearest filled rows above and below; the upper one on a tie.
        let i = filled.partition_point(|&f| f < y);
        let src = match (i.checked_sub(1).map(|j| filled[j]), filled.get(i)) {
            (Some(up), Some(&down)) if down - y < y - up => down,
            (Some(up), _) => up,
            (None, Some(&down)) => down,
            (None, None) => continue,
        };
        field.copy_within(src * w..(src + 1) * w, y * w);
    }
    field
}

/// The newer level's direction state, keeping the reports of the older ones.
fn merge(prev: Option<Direction>, mut next: Direction) -> Direction {
    if let Some(p) = prev {
        let mut reports = p.reports;
        reports.append(&mut next.reports);
        next.reports = reports;
    }
    next
}

/// Offset that maps coordinate `i` of a side of `n` to the same relative
/// position of a side of `n2` (0 when the sizes agree).
fn proportional(i: usize, n: usize, n2: usize) -> i32 {
    if n == n2 || n < 2 {
        return 0;
    }
    let target = i as f64 * (n2 - 1) as f64 / (n - 1) as f64;
    (target - i as f64).round() as i32
}

/// Dense SIFT flow from `a` to `b` (two arbitrary images, no rectification).
///
/// # Errors
/// [`DenseError::InvalidParameter`] for unusable parameters,
/// [`DenseError::TooSmall`] when an image is too small for the pyramid.
pub fn sift_flow(a: &Image, b: &Image, params: &FlowParams) -> Result<Flow, DenseError> {
    params.validate()?;
    check_size(a.width(), a.height(), params.levels)?;
    check_size(b.width(), b.height(), params.levels)?;
    let t0 = Instant::now();
    let a = fill_non_finite(a);
    let b = fill_non_finite(b);
    let engine = params.engine(None);
    let (run, _) = engine.run(&a, &b, None, None, false, &unobserved);
    let (w, h) = a.dimensions();
    let levels = run.levels.clone();
    let full = to_full_resolution(
        &a,
        &b,
        None,
        None,
        run,
        engine.finest,
        0,
        params.refinement(),
    );
    Ok(Flow {
        u: Image::from_vec(w, h, full.u).expect("flow has the size of image A"),
        v: Image::from_vec(w, h, full.v).expect("flow has the size of image A"),
        levels,
        total_ms: ms(t0),
    })
}

/// The engine's flow (at level `finest`) carried to the full resolution of
/// `a`: refined on the intensities through the pyramid down to level `stop`
/// when `refine` is given, then upsampled bilinearly. `ncc` is 1 and nothing
/// is clamped without a refinement.
#[allow(clippy::too_many_arguments)]
pub(crate) fn to_full_resolution(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    run: EngineRun,
    finest: usize,
    stop: usize,
    refine: Option<&RefineParams>,
) -> RefinedFlow {
    if let Some(params) = refine {
        return refine_flow_down_to(
            a,
            b,
            valid_a,
            valid_b,
            (&run.u, &run.v),
            finest,
            stop,
            params,
        );
    }
    let (mut u, mut v) = (run.u, run.v);
    let mut size = (run.width, run.height);
    let mut sizes = vec![a.dimensions()];
    for _ in 0..finest {
        let &(w, h) = sizes.last().expect("not empty");
        sizes.push((pyramid::half_size(w), pyramid::half_size(h)));
    }
    for l in (0..finest).rev() {
        let (wf, hf) = sizes[l];
        u = upsample_flow(&u, size.0, size.1, wf, hf, 2.0);
        v = upsample_flow(&v, size.0, size.1, wf, hf, 2.0);
        size = (wf, hf);
    }
    let n = u.len();
    RefinedFlow {
        u,
        v,
        ncc: vec![1.0; n],
        clamped: vec![false; n],
    }
}

/// Replaces non-finite samples by the nearest finite one on the same row (or
/// the image mean when a row has none), so that no false edge enters a descriptor.
pub(crate) fn fill_non_finite(img: &Image) -> Image {
    if img.data().iter().all(|v| v.is_finite()) {
        return img.clone();
    }
    let (sum, n) = img
        .data()
        .iter()
        .filter(|v| v.is_finite())
        .fold((0f64, 0usize), |(s, n), &v| (s + f64::from(v), n + 1));
    let mean = if n == 0 { 0.0 } else { (sum / n as f64) as f32 };
    let mut out = img.clone();
    let w = img.width();
    let mut left = vec![None; w];
    for y in 0..img.height() {
        let src = img.row(y);
        let mut last = None;
        for x in 0..w {
            if src[x].is_finite() {
                last = Some(x);
            }
            left[x] = last;
        }
        let row = out.row_mut(y);
        let mut next = None;
        for x in (0..w).rev() {
            if src[x].is_finite() {
                next = Some(x);
                continue;
            }
            row[x] = match (left[x], next) {
                (Some(l), Some(r)) => src[if x - l <= r - x { l } else { r }],
                (Some(l), None) => src[l],
                (None, Some(r)) => src[r],
                (None, None) => mean,
            };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_extend_from_the_nearest_swept_pixel() {
        let w = 5;
        let spans = [(0, 0), (1, 3), (0, 0), (0, 0), (2, 5), (0, 0)];
        let field: Vec<f32> = (0..w * spans.len()).map(|p| p as f32).collect();
        let out = extend_rows(field, w, &spans);
        let row = |y: usize| &out[y * w..(y + 1) * w];
        assert_eq!(row(1), &[6.0, 6.0, 7.0, 7.0, 7.0]);
        assert_eq!(row(4), &[22.0, 22.0, 22.0, 23.0, 24.0]);
        // Empty rows copy the nearest row with a span (the upper one on a tie).
        assert_eq!(row(0), row(1));
        assert_eq!(row(2), row(1));
        assert_eq!(row(3), row(4));
        assert_eq!(row(5), row(4));
        // No span at all: unchanged.
        let field = vec![1.0, 2.0, 3.0, 4.0];
        assert_eq!(extend_rows(field.clone(), 2, &[(0, 0), (0, 0)]), field);
    }

    #[test]
    fn middle_levels_search_wider_in_the_improved_mode_only() {
        let improved = FlowParams::default();
        let plan = improved.engine(Some((1, 2))).plan;
        // Level 0 (below the finest BP level), 1 (the finest), 2, 3 (top).
        let windows: Vec<usize> = plan.iter().map(|p| p.window[0]).collect();
        assert_eq!(windows, vec![2, 2, IMPROVED_MIDDLE_WINDOW, 10]);
        let paper = FlowParams {
            mode: Mode::Paper,
            ..FlowParams::default()
        };
        let windows: Vec<usize> = paper
            .engine(None)
            .plan
            .iter()
            .map(|p| p.window[0])
            .collect();
        assert_eq!(windows, vec![2, 2, 2, 10]);
        let set = FlowParams {
            middle_window: Some(3),
            ..FlowParams::default()
        };
        assert_eq!(set.engine(None).plan[2].window[0], 3);
        let too_wide = FlowParams {
            middle_window: Some(64),
            ..FlowParams::default()
        };
        assert!(matches!(
            too_wide.validate(),
            Err(DenseError::InvalidParameter { name: "window", .. })
        ));
    }

    #[test]
    fn coarse_levels_keep_the_cells_extent_in_the_improved_mode_only() {
        let cells = |p: &FlowParams| -> Vec<usize> {
            p.engine(None).plan.iter().map(|l| l.cell_size).collect()
        };
        // Finest BP level 1: levels 0 and 1 keep the cell, coarser ones halve it.
        let two = FlowParams {
            cell_size: 2,
            ..FlowParams::default()
        };
        assert_eq!(cells(&two), vec![2, 2, 1, 1]);
        // 3 / 2 rounds to 2, 3 / 4 to 1.
        assert_eq!(cells(&FlowParams::default()), vec![3, 3, 2, 1]);
        let eight_at_full = FlowParams {
            cell_size: 8,
            finest_level: Some(0),
            ..FlowParams::default()
        };
        assert_eq!(cells(&eight_at_full), vec![8, 4, 2, 1]);
        let fixed = FlowParams {
            keep_cell_extent: false,
            ..two
        };
        assert_eq!(cells(&fixed), vec![2, 2, 2, 2]);
        // The paper mode halves descriptor images, not cells.
        let paper = FlowParams {
            mode: Mode::Paper,
            ..two
        };
        assert_eq!(cells(&paper), vec![2, 2, 2, 2]);
    }

    /// Smooth random texture (sum of a few hundred random blobs).
    pub(crate) fn texture(w: usize, h: usize, seed: u64) -> Image {
        let mut s = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1);
        let mut rnd = move || {
            s = s
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let blobs: Vec<(f64, f64, f64, f64)> = (0..(w * h / 40).max(20))
            .map(|_| {
                (
                    rnd() * w as f64,
                    rnd() * h as f64,
                    1.0 + 3.0 * rnd(),
                    rnd() - 0.5,
                )
            })
            .collect();
        let mut img = Image::zeros(w, h);
        for &(cx, cy, r, a) in &blobs {
            let (x0, x1) = (
                (cx - 3.0 * r).max(0.0) as usize,
                ((cx + 3.0 * r) as usize).min(w - 1),
            );
            let (y0, y1) = (
                (cy - 3.0 * r).max(0.0) as usize,
                ((cy + 3.0 * r) as usize).min(h - 1),
            );
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let d2 = ((x as f64 - cx).powi(2) + (y as f64 - cy).powi(2)) / (r * r);
                    let v = img.get(x, y) + (a * (-d2 / 2.0).exp()) as f32;
                    img.set(x, y, v);
                }
            }
        }
        img.map(|v| 0.5 + 0.5 * v)
    }

    /// `finest_alpha_scale`, `finest_d` and `edge_d` change the finest BP
    /// level of the improved mode only: the coarser levels run the same BP,
    /// the paper mode ignores them.
    #[test]
    fn the_finest_alpha_scale_and_truncation_act_on_the_finest_improved_level_only() {
        let (w, h) = (64, 48);
        // Unrelated images: the flow is noise, so the smoothness term is not 0.
        let a = texture(w, h, 3);
        let b = texture(w, h, 4);
        // Every level's energies, finest first, on three levels.
        let run = |params: FlowParams| -> Vec<Vec<f64>> {
            let params = FlowParams {
                levels: 3,
                ..params
            };
            sift_flow(&a, &b, &params)
                .unwrap()
                .levels
                .into_iter()
                .map(|l| l.energy)
                .collect()
        };
        let base = |mode: Mode| FlowParams {
            mode,
            ..FlowParams::default()
        };
        let energies = |mode: Mode, scale: f32| {
            run(FlowParams {
                finest_alpha_scale: scale,
                ..base(mode)
            })
        };
        let (one, four) = (energies(Mode::Improved, 1.0), energies(Mode::Improved, 4.0));
        // Finest first.
        assert_ne!(one[0], four[0], "the finest level must change");
        assert_eq!(one[1..], four[1..], "coarser levels must not change");
        assert_eq!(energies(Mode::Paper, 1.0), energies(Mode::Paper, 4.0));
        // `finest_d` likewise: the finest improved level only, none = `d`.
        let truncated = |mode: Mode, finest_d: Option<f32>| {
            run(FlowParams {
                finest_d,
                ..base(mode)
            })
        };
        let (loose, tight) = (
            truncated(Mode::Improved, None),
            truncated(Mode::Improved, Some(2.0 * 255.0)),
        );
        assert_eq!(loose, four, "none must mean `d`");
        assert_ne!(loose[0], tight[0], "the finest level must change");
        assert_eq!(loose[1..], tight[1..], "coarser levels must not change");
        assert_eq!(
            truncated(Mode::Paper, None),
            truncated(Mode::Paper, Some(2.0 * 255.0))
        );
        // `edge_d` likewise; at or above the finest level's `d` it is off.
        let edged = |mode: Mode, edge_d: f32| {
            run(FlowParams {
                edge_d,
                ..base(mode)
            })
        };
        let d = FlowParams::default().d;
        let (off, on) = (edged(Mode::Improved, d), edged(Mode::Improved, 255.0));
        assert_eq!(off, edged(Mode::Improved, 2.0 * d));
        assert_ne!(off[0], on[0], "the finest level must change");
        assert_eq!(off[1..], on[1..], "coarser levels must not change");
        assert_eq!(edged(Mode::Paper, d), edged(Mode::Paper, 255.0));
        for (name, bad) in [
            (
                "edge_d",
                FlowParams {
                    edge_d: f32::NAN,
                    ..FlowParams::default()
                },
            ),
            (
                "edge_contrast",
                FlowParams {
                    edge_contrast: 0.0,
                    ..FlowParams::default()
                },
            ),
        ] {
            assert!(
                matches!(bad.validate(), Err(DenseError::InvalidParameter { name: n, .. }) if n == name),
                "{name}"
            );
        }
        let bad_d = FlowParams {
            finest_d: Some(-1.0),
            ..FlowParams::default()
        };
        assert!(matches!(
            bad_d.validate(),
            Err(DenseError::InvalidParameter {
                name: "finest_d",
                ..
            })
        ));
        let bad = FlowParams {
            finest_alpha_scale: f32::NAN,
            ..FlowParams::default()
        };
        assert!(matches!(
            bad.validate(),
            Err(DenseError::InvalidParameter {
                name: "finest_alpha_scale",
                ..
            })
        ));
    }

    #[test]
    fn recovers_a_global_shift() {
        let (w, h) = (96, 80);
        let big = texture(w + 20, h + 20, 5);
        let a = Image::from_fn(w, h, |x, y| big.get(x + 10, y + 10));
        // b(x + 3, y − 2) = a(x, y): the flow is (3, −2).
        let b = Image::from_fn(w, h, |x, y| big.get(x + 7, y + 12));
        for mode in [Mode::Paper, Mode::Improved] {
            let params = FlowParams {
                mode,
                levels: 3,
                ..FlowParams::default()
            };
            let f = sift_flow(&a, &b, &params).unwrap();
            // Finest first: BP levels 1 and 2 (improved), 0 to 2 (paper).
            let cells: Vec<usize> = f.levels.iter().map(|l| l.cell_size).collect();
            let expected = match mode {
                Mode::Paper => vec![3, 3, 3],
                Mode::Improved => vec![3, 2],
            };
            assert_eq!(cells, expected, "{mode:?}");
            let good = (10..h - 10)
                .flat_map(|y| (10..w - 10).map(move |x| (x, y)))
                .filter(|&(x, y)| {
                    (f.u.get(x, y) - 3.0).abs() < 0.25 && (f.v.get(x, y) + 2.0).abs() < 0.25
                })
                .count();
            let total = (w - 20) * (h - 20);
            assert!(
                good * 100 >= 98 * total,
                "{mode:?}: {good} of {total} correct; u(40,40) = {}, v = {}",
                f.u.get(40, 40),
                f.v.get(40, 40)
            );
        }
    }
}
