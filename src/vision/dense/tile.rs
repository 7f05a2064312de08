//! The dense stage on a canvas larger than its memory budget (`memory_budget_mib`): the canvas is
//! cut into overlapping tiles, each matched by [`dense_disparity_in_range`] on its own, and the
//! tiles are blended across the seams. Peak memory is then one tile's, time stays linear in pixels.
//!
//! Why the tiles agree: coarse to fine, SIFT flow's top level searches ±`top_window` labels at
//! 1/2^(levels−1) of the resolution. Every tile runs with the pyramid depth and search centre of
//! the whole canvas (from the sparse matches' disparity range when `search_from_sparse`), so each
//! searches the same disparity range the untiled run does, and no tile depends on a neighbour's
//! coarse solution. What a tile cannot see is context beyond its border: the overlap
//! ([`margins`]) covers the search window (vertical, and horizontal for the right image), the
//! descriptor's extent, a few top-level pixels of BP context, the refinement window, the
//! re-assignment band, the opt-in passes that judge or re-measure the raw disparity (slanted,
//! plateau, support, anchor) and the bilateral filter's support; the seam is a linear
//! cross-fade over the inner half of the overlap. The plateau pass judges each plateau whole
//! (its size, its median shift): one cut by a seam is judged per tile.
//!
//! A rotated or sheared rectification leaves up to half the canvas outside the left micrograph
//! ([`Coverage`]): tiles are cut down to the columns it covers, with their overlap, and strips
//! are made as tall as the budget then allows, so that time follows the micrograph's pixels.
//!
//! [`dense_disparity_in_range`]: super::dense_disparity_in_range

use rayon::prelude::*;

use super::{DenseError, DenseParams, DenseStats, Disparity, dense_disparity_of_warped};
use crate::vision::Image;
use crate::vision::rectify::warp::Warped;

/// Bytes the dense stage holds per canvas pixel at its peak, with the descriptors of each level
/// recomputed (`per_level`) or halved from full resolution (`halved`, 256 bytes a pixel for the
/// descriptor pair alone); measured on the simulated pairs of `eval dense`.
const BYTES_PER_PIXEL_PER_LEVEL: usize = 200;
const BYTES_PER_PIXEL_HALVED: usize = 450;

/// Weight units of the cross-fade along one axis: a pixel's weights over the tiles covering it
/// sum to exactly `WEIGHT_UNITS²` (integers, so the sum needs 2 bytes a pixel, not 4).
const WEIGHT_UNITS: u32 = 255;

/// A rectangle of the canvas.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

/// One tile: the part of the canvas it answers for (`core`, the tiles' cores partition the
/// canvas) and the part it is matched on (`padded`, the core and the overlap, cut to the
/// columns the left micrograph covers: the core's pixels beyond them have no height).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tile {
    pub core: Rect,
    pub padded: Rect,
}

/// The tiling of a canvas.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TilePlan {
    pub tiles: Vec<Tile>,
    /// Overlap beyond each core, columns and rows.
    pub margin: (usize, usize),
    /// Width of the cross-fade centred on each inner core edge, columns and rows.
    pub blend: (usize, usize),
}

/// The canvas columns the left micrograph covers, row by row: `[start, end)` (empty when
/// `start >= end`). Tiles need not be matched where the left micrograph has no pixel.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Coverage {
    width: usize,
    rows: Vec<(usize, usize)>,
}

impl Coverage {
    /// Every pixel of a `width × height` canvas.
    #[must_use]
    pub fn full((width, height): (usize, usize)) -> Self {
        Self {
            width,
            rows: vec![(0, width); height],
        }
    }

    /// The pixels of a `width × height` canvas inside the convex quadrilateral `corners` (canvas
    /// coordinates, in order around it), widened by a pixel each side for interpolation.
    #[must_use]
    pub fn of_quadrilateral((width, height): (usize, usize), corners: [(f64, f64); 4]) -> Self {
        if corners
            .iter()
            .any(|(x, y)| !(x.is_finite() && y.is_finite()))
        {
            return Self::full((width, height));
        }
        let rows = (0..height)
            .map(|y| {
                let y = y as f64;
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for (i, &(x0, y0)) in corners.iter().enumerate() {
                    let (x1, y1) = corners[(i + 1) % 4];
                    if y < y0.min(y1) - 1e-6 || y > y0.max(y1) + 1e-6 {
                        continue;
                    }
                    let x = if (y1 - y0).abs() < 1e-9 {
                        [x0, x1]
                    } else {
                        let t = ((y - y0) / (y1 - y0)).clamp(0.0, 1.0);
                        [x0 + t * (x1 - x0); 2]
                    };
                    lo = lo.min(x[0].min(x[1]));
                    hi = hi.max(x[0].max(x[1]));
                }
                if lo > hi {
                    return (0, 0);
                }
                // Clamped to the canvas before the casts.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let start = (lo.floor() - 1.0).clamp(0.0, width as f64) as usize;
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let end = (hi.floor() + 2.0).clamp(0.0, width as f64) as usize;
                (start, end.max(start))
            })
            .collect();
        Self { width, rows }
    }

    /// The columns covered in any of the rows `[y0, y1)`, `None` when none is.
    #[must_use]
    pub fn columns(&self, y0: usize, y1: usize) -> Option<(usize, usize)> {
        let (lo, hi) = self.rows[y0.min(self.rows.len())..y1.min(self.rows.len())]
            .iter()
            .filter(|(a, b)| a < b)
            .fold((self.width, 0), |(lo, hi), &(a, b)| (lo.min(a), hi.max(b)));
        (lo < hi).then_some((lo, hi))
    }
}

/// The dense stage's estimate of its peak memory on a `width × height` canvas, bytes.
#[must_use]
pub fn estimated_bytes(params: &DenseParams, (width, height): (usize, usize)) -> usize {
    let per_pixel = match params.flow.descriptors {
        super::sift_flow::DescriptorPyramid::PerLevel => BYTES_PER_PIXEL_PER_LEVEL,
        super::sift_flow::DescriptorPyramid::Halved => BYTES_PER_PIXEL_HALVED,
    };
    width.saturating_mul(height).saturating_mul(per_pixel)
}

/// The halvings that bring `pixels` within `max_megapixels` (0 when it is 0): as many as
/// SIFT's copy of the same micrograph has (`sparse::sift_bounded`).
#[must_use]
pub fn halvings(pixels: usize, max_megapixels: f64) -> usize {
    // A count of pixels: a few million.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let limit = (max_megapixels * 1e6) as usize;
    let (mut n, mut k) = (pixels, 0);
    while limit > 0 && n > limit {
        n = n.div_ceil(4);
        k += 1;
    }
    k
}

/// `params` for a left micrograph of `pixels` pixels: with `finest_max_megapixels` set and
/// exceeded, the finest BP level and the pyramid's depth one deeper per halving, and the
/// left–right tolerances (full-resolution pixels) twice as wide per halving. The matcher's
/// windows are fixed in pixels of their level; on a micrograph of more pixels over the same
/// field they would span less specimen, and where the texture is coarser than them the two
/// directions' matches disagree (the simulated dome at 4096×3072: 6 % of its pixels failed the
/// left–right check, 18 % at 8192×6144, against 0.4 % at 1280×960).
#[must_use]
pub fn scaled_for_size(params: &DenseParams, pixels: usize) -> DenseParams {
    let k = halvings(pixels, params.finest_max_megapixels);
    let mut p = *params;
    if k > 0 {
        p.flow.finest_level += k;
        p.flow.levels += k;
        // The left–right check compares at the matcher's level: the same tolerance there.
        let f = (1u32 << k) as f32;
        p.lr_tolerance *= f;
        p.lr_tolerance_smooth *= f;
    }
    p
}

/// Whether the canvas is matched in one piece: within the budget, or tiling turned off (0).
#[must_use]
pub fn fits_budget(params: &DenseParams, canvas: (usize, usize)) -> bool {
    params.memory_budget_mib == 0
        || estimated_bytes(params, canvas) <= params.memory_budget_mib.saturating_mul(1 << 20)
}

/// The overlap a tile needs beyond its core so that its core sees what the untiled run sees,
/// columns and rows (full-resolution pixels), for parameters whose search is centred on
/// `top_shift`. Across the rows, the right image's crop must hold the true matches: as far as
/// the sparse `range` reaches (with the margin the search is centred with), or the whole search
/// window without one. Then, both ways, the context that reaches a pixel's result: half a
/// descriptor and two pixels of BP at the top level, the refinement window, the re-assignment's
/// reach and the bilateral filter's support; along the columns also the vertical search below
/// the top (the true vertical flow of a rectified pair is near 0, labels beyond the tile
/// cannot match).
#[must_use]
pub fn margins(params: &DenseParams, top_shift: f32, range: Option<(f64, f64)>) -> (usize, usize) {
    let f = &params.flow;
    let levels = f.levels.max(1);
    let finest = f.finest();
    let scale = |l: usize| 1usize << l;
    let top = scale(levels - 1);
    let between: usize = (finest..levels - 1).map(scale).sum();
    let u_reach = match range.filter(|(lo, hi)| lo.is_finite() && hi.is_finite() && hi >= lo) {
        Some((lo, hi)) if params.search_from_sparse => {
            (lo.abs().max(hi.abs()) + (hi - lo) * 0.25 + super::RANGE_MARGIN_PX).ceil() as usize
        }
        _ => {
            // The search centre lies within the canvas: its size bounds it.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let shift = top_shift.abs().ceil() as usize;
            shift + f.top_window * top + f.middle_window.max(f.window) * between
        }
    };
    let v_reach = params.vertical_window * between;
    let cell = match (f.descriptors, f.keep_cell_extent) {
        (super::sift_flow::DescriptorPyramid::PerLevel, false) => f.cell_size * top,
        _ => (f.cell_size << finest).max(top),
    };
    let descriptor = 2 * cell;
    let bp_context = 2 * top;
    let refine = f.refinement().map_or(0, |r| {
        (3.0 * r.window_sigma.max(r.normalise_sigma) + r.max_step).ceil() as usize
    });
    let reassign = if params.reassign.enabled {
        (params.reassign.band_radius + params.reassign.reach) * scale(finest)
    } else {
        0
    };
    let filter = (3.0 * params.bilateral.sigma_s).ceil() as usize;
    let context = descriptor + bp_context + refine + reassign + filter + judging(params);
    (u_reach + context, v_reach + context)
}

/// The reach of the opt-in passes between the matching and the filter (the slanted and plateau
/// re-measurements, the support and anchor tests): each reads the images and the raw
/// disparity around a pixel, so a tile's core needs that much more context (0 when off).
fn judging(params: &DenseParams) -> usize {
    let sigma = crate::vision::pipeline::matcher_window_sigma(params);
    let own = |window_sigma: f32| {
        if window_sigma > 0.0 {
            f64::from(window_sigma)
        } else {
            sigma
        }
    };
    let mut reach = 0.0;
    let q = &params.slanted;
    if q.enabled {
        reach += q.max_gap as f64 + 3.0 * own(q.window_sigma);
    }
    if q.plateau {
        // Its box window, the rim that takes the window's results, and the mask's own reach:
        // the σ 1 blur (radius 4), the gradient and the erosion.
        reach += (q.plateau_radius + q.plateau_rim_px + 6) as f64;
    }
    let s = &params.support;
    if s.enabled {
        reach += 3.0 * own(s.window_sigma) * f64::from(s.wider_window.max(1.0))
            + s.reach_px as f64
            + 3.0 * f64::from(s.band_sigma + s.own_sigma)
            + f64::from(s.surface_reach) * sigma;
    }
    let a = &params.anchor;
    if a.enabled {
        reach += f64::from(a.reach) * sigma + 3.0 * f64::from(a.texture_sigma + a.band_sigma);
        // A featureless region of `min_region` windows (π (2σ)² each) spans about its square's
        // side: with that much context a tile sees such a region across its border whole.
        reach += (f64::from(a.min_region) * std::f64::consts::PI).sqrt() * 2.0 * sigma;
    }
    if (s.enabled || a.enabled) && s.rim_px > 0.0 {
        reach += 3.0 * f64::from(s.rim_px);
    }
    reach.ceil() as usize
}

/// Splits `n` pixels into `parts` runs of nearly equal length: the run starts and the end.
fn cuts(n: usize, parts: usize) -> Vec<usize> {
    (0..=parts).map(|i| i * n / parts).collect()
}

/// Grows `[lo, hi)` about its centre to at least `min` pixels within `[0, n)`.
fn grow(mut lo: usize, mut hi: usize, min: usize, n: usize) -> (usize, usize) {
    while hi - lo < min.min(n) {
        lo = lo.saturating_sub(1);
        hi = (hi + 1).min(n);
    }
    (lo, hi)
}

/// The tiles of a `width × height` canvas for `params` (already centred on the whole canvas's
/// search, see [`dense_disparity_tiled`]): as few padded pixels as the budget allows, the
/// cores at least as long as the overlap, every padded tile tall and wide enough for the
/// pyramid and cut to the columns `coverage` has in its rows. Full-width strips when they fit
/// the budget (each as tall as it allows), else a grid. A budget too small for the overlap and
/// the pyramid is exceeded (and logged) rather than refused.
#[must_use]
pub fn plan(
    params: &DenseParams,
    (width, height): (usize, usize),
    top_shift: f32,
    range: Option<(f64, f64)>,
    coverage: &Coverage,
) -> TilePlan {
    let (mx, my) = margins(params, top_shift, range);
    let min_side = super::sift_flow::min_side(params.flow.levels);
    let budget_px = (params.memory_budget_mib.saturating_mul(1 << 20)
        / estimated_bytes(params, (1, 1)).max(1))
    .max(1);
    // The padded rectangle of the core `[x0, x1) × [y0, y1)`: grown by the margins, cut to the
    // covered columns of its rows with their margin, then to the pyramid's smallest side;
    // `None` when it covers nothing.
    let padded = |(x0, x1): (usize, usize), (y0, y1): (usize, usize)| -> Option<Rect> {
        let (px0, px1) = grow(x0.saturating_sub(mx), (x1 + mx).min(width), min_side, width);
        let (py0, py1) = grow(
            y0.saturating_sub(my),
            (y1 + my).min(height),
            min_side,
            height,
        );
        let (c0, c1) = coverage.columns(py0, py1)?;
        if c1 <= px0 || c0 >= px1 {
            return None;
        }
        let lo = px0.max(c0.saturating_sub(mx));
        let hi = px1.min(c1 + mx);
        let (lo, hi) = grow(lo, hi, min_side, width);
        Some(Rect {
            x: lo,
            y: py0,
            width: hi - lo,
            height: py1 - py0,
        })
    };
    let area = |r: Option<Rect>| r.map_or(0, |r| r.width * r.height);
    let tiles_of = |xs: &[usize], ys: &[usize]| -> Vec<Tile> {
        let mut tiles = Vec::with_capacity((xs.len() - 1) * (ys.len() - 1));
        for y in ys.windows(2) {
            for x in xs.windows(2) {
                if let Some(p) = padded((x[0], x[1]), (y[0], y[1])) {
                    tiles.push(Tile {
                        core: Rect {
                            x: x[0],
                            y: y[0],
                            width: x[1] - x[0],
                            height: y[1] - y[0],
                        },
                        padded: p,
                    });
                }
            }
        }
        tiles
    };
    // Of the strips and the grids, the fewest padded pixels within the budget (or, when none
    // fits, the fewest padded pixels).
    let strip_cuts = strips(height, my, budget_px, |y0, y1| {
        area(padded((0, width), (y0, y1)))
    });
    let candidates = strip_cuts
        .map(|ys| (vec![0, width], ys))
        .into_iter()
        .chain(grids(width, height, (mx, my), min_side, budget_px));
    let mut best: Option<(bool, usize, Vec<Tile>)> = None;
    for (xs, ys) in candidates {
        let tiles = tiles_of(&xs, &ys);
        let fits = tiles
            .iter()
            .all(|t| t.padded.width * t.padded.height <= budget_px);
        let cost: usize = tiles.iter().map(|t| t.padded.width * t.padded.height).sum();
        if best
            .as_ref()
            .is_none_or(|(f, c, _)| (fits, std::cmp::Reverse(cost)) > (*f, std::cmp::Reverse(*c)))
        {
            best = Some((fits, cost, tiles));
        }
    }
    let tiles = best.map(|(_, _, t)| t).unwrap_or_default();
    let largest = tiles
        .iter()
        .map(|t| t.padded.width * t.padded.height)
        .max()
        .unwrap_or(0);
    if largest > budget_px {
        tracing::warn!(
            tile_mib = estimated_bytes(params, (largest, 1)) >> 20,
            budget_mib = params.memory_budget_mib,
            "dense stage: the smallest tile the overlap and pyramid allow exceeds the memory budget"
        );
    }
    TilePlan {
        tiles,
        margin: (mx, my),
        blend: (mx.max(2) / 2, my.max(2) / 2),
    }
}

/// Full-width strips, each core as tall as `area(y0, y1)` (padded pixels of the core rows
/// `[y0, y1)`, growing with them) keeps within `budget_px`, none shorter than the overlap `my`:
/// the row cuts, `None` when a strip of `my` rows already exceeds the budget.
fn strips(
    height: usize,
    my: usize,
    budget_px: usize,
    area: impl Fn(usize, usize) -> usize,
) -> Option<Vec<usize>> {
    let mut cuts = vec![0];
    let mut y = 0;
    while y < height {
        let shortest = my.max(1).min(height - y);
        if area(y, y + shortest) > budget_px {
            return None;
        }
        let (mut lo, mut hi) = (shortest, height - y);
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            if area(y, y + mid) <= budget_px {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        y += lo;
        cuts.push(y);
    }
    // A last strip shorter than the overlap shares the rows of the one before.
    let n = cuts.len();
    if n > 2 && cuts[n - 1] - cuts[n - 2] < my {
        let start = cuts[n - 3];
        if height - start >= 2 * my {
            cuts[n - 2] = start + (height - start) / 2;
        } else {
            cuts.remove(n - 2);
        }
    }
    Some(cuts)
}

/// The column and row cuts of the grids of tiles over the whole canvas, one per number of
/// columns: each with its rows as tall as the budget allows, the cores at least as long as the
/// overlap.
fn grids(
    width: usize,
    height: usize,
    (mx, my): (usize, usize),
    min_side: usize,
    budget_px: usize,
) -> impl Iterator<Item = (Vec<usize>, Vec<usize>)> {
    let padded =
        move |core: usize, margin: usize, n: usize| (core + 2 * margin).min(n).max(min_side);
    (1..=width.div_ceil(mx.max(1)).max(1))
        .take_while(move |&nx| nx == 1 || width.div_ceil(nx) >= mx)
        .map(move |nx| {
            let pw = padded(width.div_ceil(nx), mx, width);
            // The tallest core whose padded tile fits the budget, at least the overlap.
            let ph_max = budget_px / pw.max(1);
            let ch = ph_max.saturating_sub(2 * my).max(my).max(1).min(height);
            (cuts(width, nx), cuts(height, height.div_ceil(ch)))
        })
}

/// The dense stage's result the reconstruction needs, on the canvas: what [`Disparity`] holds
/// without the diagnostics (raw and vertical flow, occlusion mask) that tiling does not keep.
#[derive(Debug, Clone)]
pub struct CanvasDisparity {
    /// Filtered disparity `x_right − x_left`, rectified pixels, `NaN` unknown.
    pub disparity: Image,
    /// Per-pixel confidence in `[0, 1]` (0 where unknown).
    pub confidence: Image,
    /// Pixels whose disparity was interpolated, not measured (`fill_max_gap`).
    pub filled: Vec<bool>,
    /// Per pixel, why its disparity is unknown or interpolated ([`Disparity::unknown`]).
    pub unknown: Vec<super::Unknown>,
    /// `(x, y, disparity, vertical flow)` of measured pixels, canvas pixels, at most about
    /// [`ROW_SAMPLES`]: what the check of the instrument's rows needs
    /// ([`crate::vision::rectify::instrument::dense_rows_of_samples`]) when the vertical flow
    /// itself is not kept (tiles); empty when the disparity came from one untiled run.
    pub row_samples: Vec<[f32; 4]>,
    pub stats: DenseStats,
}

/// About this many row samples at most ([`CanvasDisparity::row_samples`]).
pub const ROW_SAMPLES: usize = 200_000;

/// Appends the row samples of a tile's disparity `d`, matched on the canvas rectangle `at`,
/// within `core`: measured pixels at every `step`-th canvas pixel (`width` wide).
fn push_row_samples(
    out: &mut Vec<[f32; 4]>,
    d: &Disparity,
    at: Rect,
    core: Rect,
    (width, step): (usize, usize),
) {
    for y in core.y..core.y + core.height {
        for x in core.x..core.x + core.width {
            if (y * width + x) % step != 0 {
                continue;
            }
            let q = (y - at.y) * at.width + (x - at.x);
            if d.unknown[q] == super::Unknown::Measured {
                // Canvas coordinates: far below f32's exact-integer limit.
                #[allow(clippy::cast_precision_loss)]
                out.push([
                    x as f32,
                    y as f32,
                    d.disparity.data()[q],
                    d.vertical.data()[q],
                ]);
            }
        }
    }
}

impl From<Disparity> for CanvasDisparity {
    fn from(d: Disparity) -> Self {
        Self {
            disparity: d.disparity,
            confidence: d.confidence,
            filled: d.filled,
            unknown: d.unknown,
            row_samples: Vec::new(),
            stats: d.stats,
        }
    }
}

/// The weight, in [`WEIGHT_UNITS`], of the tile whose core is `[c0, c1)` at coordinate `x`
/// along an axis of length `n`: full inside the core, fading linearly over `blend` pixels
/// centred on an inner core edge; the weights of two neighbours sum to `WEIGHT_UNITS`.
fn axis_weight(x: usize, (c0, c1): (usize, usize), n: usize, blend: usize) -> u32 {
    let rising = |edge: usize| -> u32 {
        // Fraction of the fade passed at pixel centre x + 0.5, the fade starting blend/2 before.
        let t = ((x as f64 + 0.5) - (edge as f64 - blend as f64 / 2.0)) / blend.max(1) as f64;
        (t.clamp(0.0, 1.0) * f64::from(WEIGHT_UNITS)).round() as u32
    };
    let up = if c0 == 0 { WEIGHT_UNITS } else { rising(c0) };
    let down = if c1 == n {
        WEIGHT_UNITS
    } else {
        WEIGHT_UNITS - rising(c1)
    };
    up.min(down)
}

/// The dense stage tile by tile on a `canvas`-sized rectified pair: `source` gives the left and
/// right canvas samples of a rectangle (e.g. [`crate::vision::rectify::warp::warp_rect`]), so
/// that the whole rectified pair is never held; `coverage` says where the left micrograph lies
/// on the canvas (no height beyond it). A canvas within the budget is one tile, and then the
/// result is [`dense_disparity_in_range`]'s.
///
/// # Errors
/// As [`dense_disparity_in_range`]; [`DenseError::NoValidPixels`] when no tile has a valid pixel.
///
/// [`dense_disparity_in_range`]: super::dense_disparity_in_range
pub fn dense_disparity_tiled(
    canvas: (usize, usize),
    coverage: &Coverage,
    source: impl Fn(Rect) -> (Warped, Warped),
    params: &DenseParams,
    range: Option<(f64, f64)>,
) -> Result<CanvasDisparity, DenseError> {
    let (width, height) = canvas;
    if fits_budget(params, canvas) {
        let (l, r) = source(Rect {
            x: 0,
            y: 0,
            width,
            height,
        });
        return dense_disparity_of_warped(l, r, params, range).map(CanvasDisparity::from);
    }
    // The whole canvas's pyramid depth and search centre, for every tile.
    let (centred, top_shift) = super::centre_search_on_sparse_range(params, range, canvas);
    centred.validate()?;
    let plan = plan(&centred, canvas, top_shift, range, coverage);
    tracing::info!(
        tiles = plan.tiles.len(),
        margin = ?plan.margin,
        "dense stage in tiles (memory_budget_mib = {})",
        params.memory_budget_mib
    );
    let mut disparity = Image::zeros(width, height);
    let mut confidence = Image::zeros(width, height);
    let mut weight_sum = vec![0u16; width * height];
    let mut filled = vec![false; width * height];
    let mut unknown = vec![super::Unknown::NotSeen; width * height];
    let mut row_samples = Vec::new();
    let sample_step = (width * height / ROW_SAMPLES).max(1);
    let mut merged = StatsMerge::default();
    for tile in &plan.tiles {
        let p = tile.padded;
        let (l, r) = source(p);
        let n_valid_core = count_in(&l.valid, p, intersection(p, tile.core));
        // The tile's pair becomes the dense stage's working copy.
        let d = match dense_disparity_of_warped(l, r, &centred, range) {
            Ok(d) => d,
            // A tile wholly outside both micrographs (a corner of a rotated canvas).
            Err(DenseError::NoValidPixels) => continue,
            Err(e) => return Err(e),
        };
        let core = tile.core;
        push_row_samples(
            &mut row_samples,
            &d,
            p,
            intersection(p, core),
            (width, sample_step),
        );
        let wy: Vec<u32> = (p.y..p.y + p.height)
            .map(|y| axis_weight(y, (core.y, core.y + core.height), height, plan.blend.1))
            .collect();
        let wx: Vec<u32> = (p.x..p.x + p.width)
            .map(|x| axis_weight(x, (core.x, core.x + core.width), width, plan.blend.0))
            .collect();
        let rows = disparity.data_mut()[p.y * width..(p.y + p.height) * width]
            .par_chunks_mut(width)
            .zip(confidence.data_mut()[p.y * width..(p.y + p.height) * width].par_chunks_mut(width))
            .zip(weight_sum[p.y * width..(p.y + p.height) * width].par_chunks_mut(width))
            .zip(filled[p.y * width..(p.y + p.height) * width].par_chunks_mut(width))
            .zip(unknown[p.y * width..(p.y + p.height) * width].par_chunks_mut(width));
        rows.enumerate()
            .for_each(|(ty, ((((d_row, c_row), w_row), f_row), u_row))| {
                if wy[ty] == 0 {
                    return;
                }
                for (tx, &wxv) in wx.iter().enumerate() {
                    let w = wy[ty] * wxv;
                    if w == 0 {
                        continue;
                    }
                    let (q, x) = (ty * p.width + tx, p.x + tx);
                    let wf = w as f32;
                    let v = d.disparity.data()[q];
                    if v.is_finite() {
                        d_row[x] += wf * v;
                        // At most WEIGHT_UNITS² in all: fits.
                        #[allow(clippy::cast_possible_truncation)]
                        {
                            w_row[x] += w as u16;
                        }
                    }
                    c_row[x] += wf * d.confidence.data()[q];
                    if 2 * w >= WEIGHT_UNITS * WEIGHT_UNITS {
                        f_row[x] = d.filled[q];
                        u_row[x] = d.unknown[q];
                    }
                }
            });
        merged.add(&d.stats, n_valid_core);
    }
    let full = (WEIGHT_UNITS * WEIGHT_UNITS) as f32;
    disparity
        .data_mut()
        .par_iter_mut()
        .zip(confidence.data_mut().par_iter_mut())
        .zip(&weight_sum)
        .for_each(|((d, c), &w)| {
            *d = if w > 0 { *d / f32::from(w) } else { f32::NAN };
            *c /= full;
        });
    let stats = merged
        .finish(plan.tiles.len())
        .ok_or(DenseError::NoValidPixels)?;
    Ok(CanvasDisparity {
        disparity,
        confidence,
        filled,
        unknown,
        row_samples,
        stats,
    })
}

/// The rectangle both `a` and `b` hold (empty: zero width or height).
fn intersection(a: Rect, b: Rect) -> Rect {
    let (x0, y0) = (a.x.max(b.x), a.y.max(b.y));
    let x1 = (a.x + a.width).min(b.x + b.width).max(x0);
    let y1 = (a.y + a.height).min(b.y + b.height).max(y0);
    Rect {
        x: x0,
        y: y0,
        width: x1 - x0,
        height: y1 - y0,
    }
}

/// Valid pixels of the padded tile `p` (mask `valid`) inside `core` (within `p`).
fn count_in(valid: &[bool], p: Rect, core: Rect) -> usize {
    (core.y..core.y + core.height)
        .map(|y| {
            let row = (y - p.y) * p.width;
            valid[row + core.x - p.x..row + core.x - p.x + core.width]
                .iter()
                .filter(|&&v| v)
                .count()
        })
        .sum()
}

/// The tiles' figures as one: fractions and means weighted by the valid pixels of each core,
/// times summed, per-level reports and the filter's grid of the tile with most valid pixels.
#[derive(Default)]
struct StatsMerge {
    first: Option<(DenseStats, usize)>,
    weight: f64,
    sums: [f64; 12],
    timings: super::DenseTimings,
}

impl StatsMerge {
    fn figures(s: &DenseStats) -> [f64; 12] {
        [
            s.flow.v2_over_u2,
            s.flow.rms_v.powi(2),
            s.flow.rms_u.powi(2),
            s.coverage,
            s.filled_fraction,
            s.rejected_fraction,
            s.rejected_by_matching_fraction,
            s.reassigned_fraction,
            s.refine_clamped_fraction,
            s.refine_mean_ncc,
            s.no_texture_fraction,
            s.ambiguous_fraction,
        ]
    }

    fn add(&mut self, s: &DenseStats, n_valid: usize) {
        let w = n_valid as f64;
        for (sum, v) in self.sums.iter_mut().zip(Self::figures(s)) {
            if v.is_finite() {
                *sum += w * v;
            }
        }
        self.weight += w;
        let t = &mut self.timings;
        t.matching_ms += s.timings.matching_ms;
        t.reassign_ms += s.timings.reassign_ms;
        t.refine_ms += s.timings.refine_ms;
        t.consistency_ms += s.timings.consistency_ms;
        t.filter_ms += s.timings.filter_ms;
        t.total_ms += s.timings.total_ms;
        if self.first.as_ref().is_none_or(|(_, n)| n_valid > *n) {
            self.first = Some((s.clone(), n_valid));
        }
    }

    fn finish(self, tiles: usize) -> Option<DenseStats> {
        let (mut s, _) = self.first?;
        let m = self.sums.map(|v| v / self.weight.max(1.0));
        s.flow.v2_over_u2 = m[0];
        s.flow.rms_v = m[1].sqrt();
        s.flow.rms_u = m[2].sqrt();
        s.coverage = m[3];
        s.filled_fraction = m[4];
        s.rejected_fraction = m[5];
        s.rejected_by_matching_fraction = m[6];
        s.reassigned_fraction = m[7];
        s.refine_clamped_fraction = m[8];
        s.refine_mean_ncc = m[9];
        s.no_texture_fraction = m[10];
        s.ambiguous_fraction = m[11];
        s.timings = self.timings;
        s.tiles = tiles;
        Some(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{Texture, dome, render};
    use crate::vision::Preset;

    fn params(budget_mib: usize) -> DenseParams {
        let mut p = DenseParams::preset(Preset::Improved);
        p.flow.levels = 3;
        p.memory_budget_mib = budget_mib;
        p
    }

    /// `finest_max_megapixels` deepens the matcher by one level per halving of the micrograph
    /// (as many as SIFT's copy has), and changes nothing when off or when the micrograph fits;
    /// the improved preset has it at SIFT's 4 MP, the paper's pipeline never.
    #[test]
    fn large_micrographs_are_matched_from_a_coarser_level() {
        assert_eq!(halvings(1280 * 960, 4.0), 0);
        assert_eq!(halvings(4_000_000, 4.0), 0);
        assert_eq!(halvings(4096 * 3072, 4.0), 1);
        assert_eq!(halvings(8192 * 6144, 4.0), 2);
        assert_eq!(halvings(8192 * 6144, 0.0), 0);
        assert_eq!(
            DenseParams::preset(Preset::Improved).finest_max_megapixels,
            4.0
        );
        assert_eq!(
            DenseParams::preset(Preset::Paper).finest_max_megapixels,
            0.0
        );
        let off = DenseParams {
            finest_max_megapixels: 0.0,
            ..DenseParams::preset(Preset::Improved)
        };
        assert_eq!(scaled_for_size(&off, 8192 * 6144), off);
        let on = DenseParams {
            finest_max_megapixels: 4.0,
            ..off
        };
        assert_eq!(scaled_for_size(&on, 1280 * 960), on);
        let big = scaled_for_size(&on, 8192 * 6144);
        assert_eq!(big.flow.finest_level, off.flow.finest_level + 2);
        assert_eq!(big.flow.levels, off.flow.levels + 2);
        assert_eq!(big.lr_tolerance, 4.0 * off.lr_tolerance);
        assert!(big.validate().is_ok());
        let bad = DenseParams {
            finest_max_megapixels: -1.0,
            ..off
        };
        assert!(bad.validate().is_err());
    }

    /// The opt-in passes between matching and filter widen the overlap by their reach, each
    /// alone and together, and only when they are on.
    #[test]
    fn the_overlap_covers_the_opt_in_passes_reach() {
        let mut base = params(64);
        // The anchor test and the rims are on in the improved preset: all off for the reference.
        base.anchor.enabled = false;
        base.support.rim_px = 0.0;
        let sigma = crate::vision::pipeline::matcher_window_sigma(&base);
        let off = margins(&base, 0.0, Some((-4.0, 10.0)));
        let grown = |p: &DenseParams| {
            let m = margins(p, 0.0, Some((-4.0, 10.0)));
            (m.0 - off.0, m.1 - off.1)
        };
        let mut anchor = base;
        anchor.anchor.enabled = true;
        anchor.anchor.reach = 40.0;
        let a = grown(&anchor);
        assert!(a.0 as f64 >= 40.0 * sigma && a.0 == a.1, "{a:?}");
        // Its featureless regions of `min_region` windows are seen whole across a border.
        let mut regions = anchor;
        regions.anchor.min_region = 4.0 * anchor.anchor.min_region.max(1.0);
        let r = grown(&regions);
        assert!(r.0 > a.0, "{r:?} against {a:?}");
        let mut support = base;
        support.support.enabled = true;
        let s = grown(&support);
        let wider = 3.0 * sigma * f64::from(support.support.wider_window);
        assert!(
            s.0 as f64 >= wider + support.support.reach_px as f64,
            "{s:?}"
        );
        let mut slanted = base;
        slanted.slanted.enabled = true;
        assert!(grown(&slanted).0 >= slanted.slanted.max_gap, "slanted");
        let mut plateau = base;
        plateau.slanted.plateau = true;
        plateau.slanted.plateau_radius = 24;
        let q = plateau.slanted;
        let pl = grown(&plateau);
        assert!(
            pl.0 >= q.plateau_radius + q.plateau_rim_px && pl.0 == pl.1,
            "plateau {pl:?}"
        );
        let mut all = anchor;
        all.support = support.support;
        all.slanted = slanted.slanted;
        assert!(grown(&all).0 >= a.0 + s.0 + slanted.slanted.max_gap);
        all.slanted.plateau = true;
        all.slanted.plateau_radius = 24;
        assert!(grown(&all).0 >= a.0 + s.0 + slanted.slanted.max_gap + pl.0);
    }

    /// The cores partition the canvas, every padded tile holds the covered part of its core and
    /// suits the pyramid, and the cross-fade weights of every covered pixel sum to the full
    /// weight; a canvas the left micrograph half covers is matched on no more pixels.
    #[test]
    fn tiles_partition_the_canvas_and_their_weights_sum_to_one() {
        let cases = [
            ((900, 700), 1),
            ((3000, 500), 2),
            ((640, 2000), 1),
            ((900, 700), 64),
            ((640, 2000), 48),
        ];
        for (canvas, budget) in cases {
            let (w, h) = canvas;
            let (wf, hf) = (w as f64, h as f64);
            let diamond = [
                (wf / 2.0, 0.0),
                (wf, hf / 2.0),
                (wf / 2.0, hf),
                (0.0, hf / 2.0),
            ];
            let mut padded_px = Vec::new();
            for coverage in [
                Coverage::full(canvas),
                Coverage::of_quadrilateral(canvas, diamond),
            ] {
                let p = params(budget);
                let plan = plan(&p, canvas, 3.0, Some((-4.0, 10.0)), &coverage);
                assert!(plan.tiles.len() > 1, "{canvas:?}");
                let mut covered = vec![0u8; w * h];
                let mut weight = vec![0u32; w * h];
                for t in &plan.tiles {
                    let (c, pd) = (t.core, t.padded);
                    assert!(pd.x + pd.width <= w && pd.y + pd.height <= h);
                    assert!(super::super::sift_flow::check_size(pd.width, pd.height, 3).is_ok());
                    for y in c.y..c.y + c.height {
                        for x in c.x..c.x + c.width {
                            covered[y * w + x] += 1;
                        }
                    }
                    for y in pd.y..pd.y + pd.height {
                        let wy = axis_weight(y, (c.y, c.y + c.height), h, plan.blend.1);
                        for x in pd.x..pd.x + pd.width {
                            let wx = axis_weight(x, (c.x, c.x + c.width), w, plan.blend.0);
                            weight[y * w + x] += wx * wy;
                        }
                    }
                }
                let full = WEIGHT_UNITS * WEIGHT_UNITS;
                for y in 0..h {
                    let (a, b) = coverage.rows[y];
                    for x in a..b {
                        assert_eq!(covered[y * w + x], 1, "{canvas:?} ({x}, {y})");
                        assert_eq!(weight[y * w + x], full, "{canvas:?} ({x}, {y})");
                    }
                }
                padded_px.push(
                    plan.tiles
                        .iter()
                        .map(|t| t.padded.width * t.padded.height)
                        .sum::<usize>(),
                );
            }
            // The cut never matches more pixels than the whole canvas's tiles.
            assert!(padded_px[1] <= padded_px[0], "{canvas:?}: {padded_px:?}");
        }
        // Within the budget: one piece, the untiled run.
        assert!(fits_budget(&params(1024), (1280, 960)));
        assert!(fits_budget(&params(0), (100_000, 100_000)));
        assert!(!fits_budget(&params(1), (1280, 960)));
    }

    /// A quadrilateral's coverage holds every pixel inside it and little outside.
    #[test]
    fn coverage_of_a_quadrilateral_holds_its_pixels() {
        let (w, h) = (300, 200);
        let quad = [(40.5, 10.0), (290.0, 60.0), (250.0, 190.0), (10.0, 150.0)];
        let c = Coverage::of_quadrilateral((w, h), quad);
        let inside = |x: f64, y: f64| {
            (0..4).all(|i| {
                let ((x0, y0), (x1, y1)) = (quad[i], quad[(i + 1) % 4]);
                (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) >= 0.0
            })
        };
        for y in 0..h {
            let (a, b) = c.rows[y];
            let xs: Vec<usize> = (0..w).filter(|&x| inside(x as f64, y as f64)).collect();
            if let (Some(&first), Some(&last)) = (xs.first(), xs.last()) {
                assert!(
                    a <= first && last < b,
                    "row {y}: {a}..{b} misses {first}..={last}"
                );
                assert!(
                    first - a <= 2 && b - last <= 3,
                    "row {y}: {a}..{b} for {first}..={last}"
                );
            }
        }
        assert_eq!(c.rows[0], (0, 0));
        assert_eq!(c.columns(0, 5), None);
        assert_eq!(Coverage::full((w, h)).columns(3, 9), Some((0, w)));
    }

    /// The row samples a tiled run keeps give the instrument's row check what the untiled run's
    /// whole vertical flow gives: a right image 0.6 px too low shows as 0.6 px of offset.
    #[test]
    fn tiles_keep_enough_vertical_flow_to_check_the_rows() {
        use crate::vision::rectify::instrument::{dense_rows, dense_rows_of_samples};
        let (w, h) = (256, 640);
        let all = Coverage::full((w, h));
        let range = Some((3.0, 9.0));
        for dy in [0.0, 0.6] {
            let pair = render(w, h, Texture::new(5), &dome(w, h, 3.0, 6.0, 0.9), dy, 0.0);
            let source = |r: Rect| {
                let warped = |img: &Image| {
                    let image = Image::from_fn(r.width, r.height, |x, y| img.get(r.x + x, r.y + y));
                    let valid = vec![true; image.len()];
                    Warped { image, valid }
                };
                (warped(&pair.left), warped(&pair.right))
            };
            let tiled = dense_disparity_tiled((w, h), &all, source, &params(1), range).unwrap();
            assert!(tiled.stats.tiles >= 3);
            assert!(
                tiled.row_samples.len() > 10_000,
                "{}",
                tiled.row_samples.len()
            );
            let rows = dense_rows_of_samples(&tiled.row_samples, (w, h)).unwrap();
            let (l, r) = source(Rect {
                x: 0,
                y: 0,
                width: w,
                height: h,
            });
            let whole = super::super::dense_disparity_of_warped(l, r, &params(0), range).unwrap();
            let reference = dense_rows(&whole.vertical, &whole.disparity, &whole.unknown).unwrap();
            assert!(
                (rows.offset_px - dy).abs() < 0.15
                    && (rows.offset_px - reference.offset_px).abs() < 0.1,
                "dy {dy}: tiled {rows:?}, untiled {reference:?}"
            );
        }
    }

    /// Forced into tiles by a tiny budget, a dome's disparity across the seams agrees with the
    /// untiled run's within that run's own error: the overlap gives each tile the context the
    /// untiled run has, and the cross-fade leaves no step.
    #[test]
    fn heights_across_seams_agree_with_the_untiled_run() {
        let (w, h) = (256, 640);
        let pair = render(w, h, Texture::new(5), &dome(w, h, 3.0, 6.0, 0.9), 0.0, 0.0);
        let crop = |img: &Image, r: Rect| {
            Image::from_fn(r.width, r.height, |x, y| img.get(r.x + x, r.y + y))
        };
        let source = |r: Rect| {
            let warped = |img: &Image| {
                let image = crop(img, r);
                let valid = vec![true; image.len()];
                Warped { image, valid }
            };
            (warped(&pair.left), warped(&pair.right))
        };
        let range = Some((3.0, 9.0));
        let all = Coverage::full((w, h));
        let whole = dense_disparity_tiled((w, h), &all, source, &params(1024), range).unwrap();
        let tiled_params = params(1);
        let tiled = dense_disparity_tiled((w, h), &all, source, &tiled_params, range).unwrap();
        assert_eq!(whole.stats.tiles, 1);
        let (_, shift) = super::super::centre_search_on_sparse_range(&tiled_params, range, (w, h));
        let plan = plan(&tiled_params, (w, h), shift, range, &all);
        assert_eq!(tiled.stats.tiles, plan.tiles.len());
        assert!(plan.tiles.len() >= 3, "{} tiles", plan.tiles.len());
        // Pixels within the cross-fade of an inner seam, away from the canvas's own borders.
        let near = |v: usize, edges: &[usize], band: usize| {
            edges
                .iter()
                .any(|&e| e > 0 && v + band >= e && v < e + band)
        };
        let rows: Vec<usize> = plan.tiles.iter().map(|t| t.core.y).collect();
        let cols: Vec<usize> = plan.tiles.iter().map(|t| t.core.x).collect();
        let (mut diff, mut err) = (Vec::new(), Vec::new());
        for y in 16..h - 16 {
            for x in 24..w - 24 {
                if !(near(y, &rows, plan.blend.1) || near(x, &cols, plan.blend.0)) {
                    continue;
                }
                let p = y * w + x;
                let (a, b) = (whole.disparity.data()[p], tiled.disparity.data()[p]);
                assert!(
                    b.is_finite() || !a.is_finite(),
                    "seam pixel lost at ({x}, {y})"
                );
                if a.is_finite() && b.is_finite() {
                    diff.push((a - b).abs());
                    err.push((a - pair.disparity.data()[p]).abs());
                }
            }
        }
        assert!(diff.len() > 2000, "{} seam pixels", diff.len());
        let pct = |v: &mut Vec<f32>, q: f64| {
            v.sort_by(f32::total_cmp);
            v[((v.len() - 1) as f64 * q) as usize]
        };
        let (d50, e50) = (pct(&mut diff, 0.5), pct(&mut err, 0.5));
        let (d99, e99) = (pct(&mut diff, 0.99), pct(&mut err, 0.99));
        assert!(
            d50 <= e50 && d99 <= e99,
            "tiled vs untiled median {d50} p99 {d99} px; untiled error median {e50} p99 {e99} px"
        );
    }
}
