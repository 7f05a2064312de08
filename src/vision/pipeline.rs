//! The SD-SEM reconstruction of a stereo pair, start to finish (Baghaie et al.,
//! Micron 97, 2017):
//!
//! ```text
//! left, right ─▶ sparse SIFT ─▶ matching ─▶ ORSA ─▶ quasi-Euclidean rectification
//!                                  └─ refused ─▶ rectification from the tilt axis, verified
//!                                                by the tiles' rows and the dense vertical flow
//!             ─▶ dense SIFT ─▶ SIFT flow (dual-layer BP, coarse to fine)
//!             ─▶ [sub-pixel, left–right check] ─▶ bilateral grid
//!             ─▶ depth h = d·p / (2 sin(θ/2)) on the left micrograph's grid
//! ```
//!
//! Pure: images and numbers in, images and a serialisable report out.

use std::time::Instant;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use super::Image;
use super::datum::{Datum, apply_datum};
use super::dense::tile::{Coverage, Rect, fits_budget, scaled_for_size};
use super::dense::{
    CanvasDisparity, DenseError, DenseParams, DenseStats, Unknown, dense_disparity_of_warped,
    dense_disparity_tiled,
};
use super::depth::{DepthError, StereoGeometry, height_on_left_grid};
use super::geometry::{MAX_TILT_DEG, PairGeometry};
use super::params::ReconstructionParams;
use super::precision::{self, Precision};
use super::rectify::RectifyError;
use super::rectify::instrument::{
    InstrumentError, InstrumentFigures, InstrumentRectification, dense_rows, dense_rows_of_samples,
    instrument_rectification, median_row_offset, tile_measurements, verify_dense_rows,
};
use super::rectify::warp::{warp, warp_rect};
use super::sparse::{
    Correspondence, SparseError, SparseMatches, SparseParams, SparseResult, sparse_attempts,
};
use crate::progress::{Observer, Stage, unobserved};

/// Why a pair cannot be reconstructed.
#[derive(Debug, thiserror::Error)]
pub enum ReconstructError {
    #[error("tilt difference θ = {0}° must be greater than 0° and at most {MAX_TILT_DEG}°")]
    Tilt(f64),
    #[error("pixel size {0} µm must be a positive number")]
    PixelSize(f64),
    #[error("tilt axis angle {0}° is not a finite number")]
    TiltAxis(f64),
    #[error("sparse stage: {0}")]
    Sparse(SparseError),
    #[error("dense stage: {0}")]
    Dense(DenseError),
    #[error("depth: {0}")]
    Depth(DepthError),
    #[error(
        "no height could be computed: the rectified images do not overlap (is it the same specimen area?)"
    )]
    NoOverlap,
    /// Neither the sparse stage nor the instrument's geometry rectifies the pair.
    #[error("sparse stage: {sparse}; the instrument's geometry cannot replace it: {instrument}")]
    Unrectifiable {
        sparse: String,
        instrument: InstrumentError,
    },
}

error_from!(ReconstructError {
    Sparse(SparseError),
    Dense(DenseError),
    Depth(DepthError),
});

/// Wall time of each stage, ms.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct StageTimings {
    pub sparse_ms: f64,
    pub dense_ms: f64,
    pub depth_ms: f64,
    pub total_ms: f64,
}

/// The sparse stage in figures (the paper's Table 2 and the rectification).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SparseReport {
    pub keypoints_left: usize,
    pub keypoints_right: usize,
    pub matches: usize,
    pub inliers: usize,
    pub model: String,
    pub fallback_reason: Option<String>,
    /// Why SIFT ran a second time on a feature-poor pair, and what it found.
    pub second_attempt: Option<String>,
    pub log10_nfa: f64,
    pub threshold_px: f64,
    pub orsa_iterations: usize,
    pub initial_error_px: f64,
    pub final_error_px: f64,
    pub h_left: [[f64; 3]; 3],
    pub h_right: [[f64; 3]; 3],
    pub canvas: (usize, usize),
    pub timings: super::sparse::Timings,
}

/// The height map in figures.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DepthReport {
    /// Pixels of the left micrograph with a height.
    pub valid_fraction: f64,
    /// 1st and 99th percentile of the heights, µm.
    pub height_p01_um: f64,
    pub height_p99_um: f64,
    /// µm of height per pixel of disparity: p / (2 sin(θ/2)), eq. (19).
    pub um_per_disparity_px: f64,
}

/// The paper's Table 4 for this pair: how vertical the correspondences are
/// before and after rectification, and the rectification error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RectificationFigures {
    /// Σv²/Σu² of the sparse inliers' displacements in the original images.
    pub v2_over_u2_before: f64,
    /// The same on the rectified canvas.
    pub v2_over_u2_after: f64,
    /// Σv²/Σu² of the dense flow on the canvas (`dense.flow`).
    pub v2_over_u2_dense: f64,
    /// RMS vertical misalignment of the inliers before / after, pixels.
    pub rmse_before_px: f64,
    pub rmse_after_px: f64,
}

/// Σv²/Σu² of displacements `(u, v)`.
fn v2_over_u2(d: impl Iterator<Item = (f64, f64)>) -> f64 {
    let (su, sv) = d.fold((0.0, 0.0), |(su, sv), (u, v)| (su + u * u, sv + v * v));
    if su > 0.0 { sv / su } else { f64::NAN }
}

/// Which path produced the rectification (report.json `geometry.source`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum GeometrySource {
    /// The sparse stage's epipolar geometry (SIFT, ORSA, quasi-Euclidean rectification).
    Sparse,
    /// The tilt axis and the pair's correlation ([`super::rectify::instrument`]).
    Instrument,
}

/// The pair's geometry in report.json: the acquisition's figures, the path that rectified the
/// pair, and how the instrument's path was verified when it ran.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GeometryReport {
    #[serde(flatten)]
    pub pair: PairGeometry,
    pub source: GeometrySource,
    /// Why the sparse stage's geometry was not used (instrument source only).
    pub sparse_refused: Option<String>,
    /// The instrument's measurements and checks (instrument source only).
    pub instrument: Option<InstrumentFigures>,
}

/// Everything a reconstruction reports (report.json, `/recon/report`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReconReport {
    pub geometry: GeometryReport,
    pub image_size: (usize, usize),
    pub sparse: SparseReport,
    pub dense: DenseStats,
    /// Table 4 of the paper.
    pub rectification: RectificationFigures,
    pub depth: DepthReport,
    /// What zero height means and the plane levelled away ([`super::datum`]).
    pub datum: Datum,
    /// The precision the micrographs' noise and texture allow at the
    /// matcher's window ([`precision`]); `None` when it cannot be measured.
    pub precision: Option<Precision>,
    pub timings: StageTimings,
}

/// The result on the left micrograph's grid.
#[derive(Debug, Clone)]
pub struct Reconstruction {
    /// Height, µm, positive towards the beam, `NaN` unknown (DESIGN §3).
    pub height_um: Image,
    /// Confidence in `(0, 1]` of each measured height, 0 where the height
    /// was interpolated between measured neighbours (`fill_max_gap`), `NaN`
    /// where the height is unknown.
    pub confidence: Image,
    /// Per pixel of the left grid, why its height is unknown or interpolated
    /// ([`Unknown::Measured`] where measured): `confidence.tif`'s second page.
    pub unknown: Vec<Unknown>,
    pub report: ReconReport,
}

/// Reconstructs the surface seen in a stereo pair.
///
/// # Errors
/// [`ReconstructError`] for an impossible geometry, a pair the sparse stage
/// cannot rectify reliably (never a silently wrong warp), a dense failure, or
/// rectified images that do not overlap.
pub fn reconstruct(
    left: &Image,
    right: &Image,
    geometry: &PairGeometry,
    params: &ReconstructionParams,
) -> Result<Reconstruction, ReconstructError> {
    reconstruct_observed(left, right, geometry, params, &unobserved)
}

/// [`reconstruct`], telling `progress` each stage as it begins: [`Stage::Sparse`],
/// [`Stage::Dense`], [`Stage::Depth`].
///
/// # Errors
/// As [`reconstruct`].
pub fn reconstruct_observed(
    left: &Image,
    right: &Image,
    geometry: &PairGeometry,
    params: &ReconstructionParams,
    progress: Observer<'_>,
) -> Result<Reconstruction, ReconstructError> {
    validate(geometry)?;
    let t_total = Instant::now();

    let t = Instant::now();
    progress(Stage::Sparse);
    let established = rectify_for_dense(left, right, geometry, &params.sparse)?;
    let range = established.range;
    let canvas = established.canvas;
    let (h_left, h_right) = (established.h_left, established.h_right);
    // A large micrograph's matcher one level coarser per halving (opt-in; unchanged by default).
    let dense = scaled_for_size(&params.dense, left.len());
    // The precision's bound in disparity pixels (at 1 µm per pixel): it needs the micrographs
    // only. When the canvas fits the memory budget it runs beside the dense stage, whose serial
    // steps (pyramids, warm starts, the filters' splats) leave a core idle, and no core waits on
    // its own serial steps (selections) at the end; otherwise after the canvas maps are freed
    // (its planes would meet them: 8192×6144 peaked at 2.6 GiB side by side, 1.9 GiB in turn).
    let predict = || {
        precision::predict(
            left,
            right,
            geometry.tilt_axis_deg,
            matcher_window_sigma(&params.dense),
            1.0,
        )
    };
    let mut bound = None;
    let (disp, row_offset, sparse_ms, dense_ms) = if fits_budget(&dense, canvas) {
        let (wl, wr) = rayon::join(
            || warp(left, &h_left, canvas.0, canvas.1),
            || warp(right, &h_right, canvas.0, canvas.1),
        );
        let (Some(wl), Some(wr)) = (wl, wr) else {
            return Err(SparseError::Rectify(RectifyError::Degenerate).into());
        };
        let sparse_ms = ms(t);
        let t = Instant::now();
        progress(Stage::Dense);
        // The rectified pair becomes the dense stage's working copy.
        let (disp, b) = rayon::join(|| dense_disparity_of_warped(wl, wr, &dense, range), predict);
        bound = Some(b);
        let disp = disp?;
        let row_offset = match established.source {
            Established::Instrument { .. } => {
                dense_rows(&disp.vertical, &disp.disparity, &disp.unknown)
            }
            Established::Sparse(_) => None,
        };
        (CanvasDisparity::from(disp), row_offset, sparse_ms, ms(t))
    } else {
        // Each tile warps its own rectangle: the rectified pair is never whole in memory.
        let sparse_ms = ms(t);
        let t = Instant::now();
        progress(Stage::Dense);
        if h_left.try_inverse().is_none() || h_right.try_inverse().is_none() {
            return Err(SparseError::Rectify(RectifyError::Degenerate).into());
        }
        let source = |rect: Rect| {
            let at = ((rect.x, rect.y), (rect.width, rect.height));
            let (l, r) = rayon::join(
                || warp_rect(left, &h_left, at.0, at.1),
                || warp_rect(right, &h_right, at.0, at.1),
            );
            (
                l.expect("H_left is invertible (checked above)"),
                r.expect("H_right is invertible (checked above)"),
            )
        };
        let coverage = left_coverage(left.dimensions(), &h_left, canvas);
        let disp = dense_disparity_tiled(canvas, &coverage, source, &dense, range)?;
        // Tiles keep no vertical flow, only samples of it for this check.
        let row_offset = match established.source {
            Established::Instrument { .. } => dense_rows_of_samples(&disp.row_samples, canvas),
            Established::Sparse(_) => None,
        };
        (disp, row_offset, sparse_ms, ms(t))
    };
    // The instrument's rows are verified by the dense stage: what vertical flow is left.
    let mut instrument_figures = None;
    if let Established::Instrument {
        rectification, why, ..
    } = &established.source
    {
        if let Some(v) = &row_offset {
            verify_dense_rows(v, geometry.tilt_axis_deg, &params.sparse.instrument).map_err(
                |instrument| ReconstructError::Unrectifiable {
                    sparse: why.clone(),
                    instrument,
                },
            )?;
        }
        instrument_figures = Some(InstrumentFigures {
            dense_rows: row_offset,
            ..rectification.figures
        });
    }

    let t = Instant::now();
    progress(Stage::Depth);
    let stereo = StereoGeometry {
        tilt_deg: geometry.tilt_deg,
        pixel_size_um: geometry.pixel_size_um,
        tilt_axis_deg: geometry.tilt_axis_deg,
    };
    let (w, h) = left.dimensions();
    let mut height_um = height_on_left_grid(&disp.disparity, &h_left, &h_right, &stereo, w, h)?;
    let datum = apply_datum(&mut height_um, params.datum, geometry.pixel_size_um);
    let confidence = left_grid_confidence(&disp.confidence, &disp.filled, &height_um, &h_left);
    let unknown = left_grid_unknown(&disp.unknown, canvas, &height_um, &confidence, &h_left);
    // The canvas maps (up to twice the micrograph's pixels) go.
    let dense_stats = disp.stats;
    let maps = (disp.disparity, disp.confidence, disp.filled, disp.unknown);
    let (bound, depth) = match bound {
        // Unmapped on one core while the other ranks the heights (both are serial).
        Some(bound) => {
            let ((), depth) = rayon::join(|| drop(maps), || depth_report(&height_um, &stereo));
            (bound, depth)
        }
        None => {
            drop(maps);
            (predict(), depth_report(&height_um, &stereo))
        }
    };
    if depth.valid_fraction == 0.0 {
        return Err(ReconstructError::NoOverlap);
    }
    let depth_ms = ms(t);
    // The bound in disparity pixels (`predict` at 1 µm per pixel), in µm of height.
    let precision = bound.map(|b| Precision {
        height_um: b.disparity_px * depth.um_per_disparity_px,
        ..b
    });

    let map = |hm: &Matrix3<f64>, p: [f64; 2]| {
        let q = hm * Vector3::new(p[0], p[1], 1.0);
        (q.x / q.z, q.y / q.z)
    };
    let inliers = established.inliers();
    let (initial_error_px, final_error_px) = established.errors();
    let rectification = RectificationFigures {
        v2_over_u2_before: v2_over_u2(
            inliers
                .iter()
                .map(|c| (c.right[0] - c.left[0], c.right[1] - c.left[1])),
        ),
        v2_over_u2_after: v2_over_u2(inliers.iter().map(|c| {
            let (l, r) = (map(&h_left, c.left), map(&h_right, c.right));
            (r.0 - l.0, r.1 - l.1)
        })),
        v2_over_u2_dense: dense_stats.flow.v2_over_u2,
        rmse_before_px: initial_error_px,
        rmse_after_px: final_error_px,
    };
    let sparse = established.sparse_report(initial_error_px, final_error_px);
    let report = ReconReport {
        geometry: GeometryReport {
            pair: *geometry,
            source: match established.source {
                Established::Sparse(_) => GeometrySource::Sparse,
                Established::Instrument { .. } => GeometrySource::Instrument,
            },
            sparse_refused: match &established.source {
                Established::Sparse(_) => None,
                Established::Instrument { why, .. } => Some(why.clone()),
            },
            instrument: instrument_figures,
        },
        image_size: (w, h),
        sparse,
        dense: dense_stats,
        rectification,
        depth,
        datum,
        precision,
        timings: StageTimings {
            sparse_ms,
            dense_ms,
            depth_ms,
            total_ms: ms(t_total),
        },
    };
    Ok(Reconstruction {
        height_um,
        confidence,
        unknown,
        report,
    })
}

/// The canvas the dense stage works on, and the path that produced it.
#[derive(Debug, Clone)]
pub struct CanvasGeometry {
    /// Original left/right pixel → canvas pixel; corresponding points share their row and the
    /// disparity `x_right − x_left` grows with height.
    pub h_left: Matrix3<f64>,
    pub h_right: Matrix3<f64>,
    pub canvas: (usize, usize),
    /// Disparity range the dense search is centred on (`None`: its own search).
    pub range: Option<(f64, f64)>,
    pub source: Established,
}

/// How a [`CanvasGeometry`] was established.
#[derive(Debug, Clone)]
pub enum Established {
    /// The sparse stage's epipolar geometry.
    Sparse(SparseResult),
    /// The instrument's (tilt axis and correlation), because the sparse stage's was refused or
    /// implausible (`why`); `matches` are the sparse stage's putative matches.
    Instrument {
        rectification: InstrumentRectification,
        matches: SparseMatches,
        why: String,
    },
}

impl CanvasGeometry {
    fn sparse(s: SparseResult) -> Self {
        Self {
            h_left: s.rectification.h_left,
            h_right: s.rectification.h_right,
            canvas: s.rectification.canvas,
            range: inlier_disparity_range(&s.inliers, &s.rectification),
            source: Established::Sparse(s),
        }
    }

    /// The correspondences the geometry rests on: the sparse inliers, or the tiles and matches
    /// that agree on the instrument's rows.
    fn inliers(&self) -> &[Correspondence] {
        match &self.source {
            Established::Sparse(s) => &s.inliers,
            Established::Instrument { rectification, .. } => &rectification.agreeing,
        }
    }

    /// The rectification error before and after (Monasse's RMS Sampson figures; for the
    /// instrument's rows, the RMS vertical offset over √2, which is what they equal on rows).
    fn errors(&self) -> (f64, f64) {
        match &self.source {
            Established::Sparse(s) => (
                s.rectification.initial_error_px,
                s.rectification.final_error_px,
            ),
            Established::Instrument { rectification, .. } => {
                let a = &rectification.agreeing;
                let dy2 = a
                    .iter()
                    .map(|c| (c.right[1] - c.left[1]).powi(2))
                    .sum::<f64>()
                    / a.len().max(1) as f64;
                (
                    (dy2 / 2.0).sqrt(),
                    rectification.figures.row_residual_rms_px / std::f64::consts::SQRT_2,
                )
            }
        }
    }

    fn sparse_report(&self, initial_error_px: f64, final_error_px: f64) -> SparseReport {
        let (h_left, h_right, canvas) = (rows(&self.h_left), rows(&self.h_right), self.canvas);
        match &self.source {
            Established::Sparse(s) => SparseReport {
                keypoints_left: s.keypoints_left,
                keypoints_right: s.keypoints_right,
                matches: s.matches.len(),
                inliers: s.inliers.len(),
                model: format!("{:?}", s.model).to_lowercase(),
                fallback_reason: s.fallback_reason.clone(),
                second_attempt: s.second_attempt.clone(),
                log10_nfa: s.log10_nfa,
                threshold_px: s.threshold_px,
                orsa_iterations: s.orsa_iterations,
                initial_error_px,
                final_error_px,
                h_left,
                h_right,
                canvas,
                timings: s.timings,
            },
            Established::Instrument {
                rectification,
                matches,
                why,
            } => SparseReport {
                keypoints_left: matches.keypoints_left,
                keypoints_right: matches.keypoints_right,
                matches: matches.correspondences().len(),
                inliers: rectification.agreeing.len(),
                model: "instrument".to_owned(),
                fallback_reason: Some(why.clone()),
                second_attempt: None,
                log10_nfa: f64::NAN,
                threshold_px: f64::NAN,
                orsa_iterations: 0,
                initial_error_px,
                final_error_px,
                h_left,
                h_right,
                canvas,
                timings: matches.timings,
            },
        }
    }
}

/// The canvas for the dense stage: the sparse stage's rectification, or — when it refuses the
/// pair, or its canvas leaves the pair's correlated tiles more than
/// `instrument.max_sparse_row_offset_px` off their rows — the instrument's
/// ([`instrument_rectification`]) from the tilt axis, refined by the sparse stage's matches.
///
/// # Errors
/// [`ReconstructError::Sparse`] for a pair the sparse stage refuses before any matching (sizes,
/// parameters) or when the fallback is off; [`ReconstructError::Unrectifiable`] when the
/// instrument's geometry cannot replace the sparse stage's either.
pub fn rectify_for_dense(
    left: &Image,
    right: &Image,
    geometry: &PairGeometry,
    params: &SparseParams,
) -> Result<CanvasGeometry, ReconstructError> {
    let phi = geometry.tilt_axis_deg;
    let inst = &params.instrument;
    let (matches, geometry) = sparse_attempts(left, right, Some(phi), params)?;
    let why = match geometry {
        Ok(s) => match sparse_rows_off(left, right, &s, params) {
            None => return Ok(CanvasGeometry::sparse(s)),
            Some(why) => why,
        },
        Err(e) if !inst.enabled || matches!(e, SparseError::Params(_)) => return Err(e.into()),
        Err(e) => e.to_string(),
    };
    match instrument_rectification(left, right, phi, &matches.correspondences(), inst) {
        Ok(r) => Ok(CanvasGeometry {
            h_left: r.h_left,
            h_right: r.h_right,
            canvas: r.canvas,
            range: r.disparity_range,
            source: Established::Instrument {
                rectification: r,
                matches,
                why,
            },
        }),
        Err(instrument) => Err(ReconstructError::Unrectifiable {
            sparse: why,
            instrument,
        }),
    }
}

/// Why an accepted sparse geometry is nevertheless wrong, if it is: the pair's correlated tiles
/// lie more than `instrument.max_sparse_row_offset_px` (median) off their rows on its canvas —
/// on repetitive specimens a consistent set of wrong matches can pass ORSA and the
/// rectification's checks. `None` when it is right or the check cannot be made.
fn sparse_rows_off(
    left: &Image,
    right: &Image,
    s: &SparseResult,
    params: &SparseParams,
) -> Option<String> {
    let inst = &params.instrument;
    if !inst.enabled || inst.max_sparse_row_offset_px <= 0.0 {
        return None;
    }
    let tiles = tile_measurements(left, right, inst).ok()?.measured;
    if tiles.len() < inst.min_measurements {
        return None;
    }
    let r = &s.rectification;
    let off = median_row_offset(&tiles, &r.h_left, &r.h_right)?;
    (off > inst.max_sparse_row_offset_px).then(|| {
        format!(
            "its rectification leaves the correlated tiles {off:.2} px (median) off their rows (limit {} px)",
            inst.max_sparse_row_offset_px
        )
    })
}

/// Where the left micrograph (`width × height`) lies on the canvas: the quadrilateral its pixel
/// centres' hull maps to by `h_left`, or the whole canvas when a corner does not map.
fn left_coverage(
    (w, h): (usize, usize),
    h_left: &Matrix3<f64>,
    canvas: (usize, usize),
) -> Coverage {
    let (xm, ym) = (w.saturating_sub(1) as f64, h.saturating_sub(1) as f64);
    let corners = [(0.0, 0.0), (xm, 0.0), (xm, ym), (0.0, ym)].map(|(x, y)| {
        let q = h_left * Vector3::new(x, y, 1.0);
        if q.z > 1e-12 {
            (q.x / q.z, q.y / q.z)
        } else {
            (f64::NAN, f64::NAN)
        }
    });
    Coverage::of_quadrilateral(canvas, corners)
}

/// The lowest confidence a measured height reads, so that 0 marks the
/// interpolated heights alone.
const MIN_MEASURED_CONFIDENCE: f32 = 1e-6;

/// The dense stage's confidence on the left micrograph's grid: 0 where the
/// height is mostly (by the resampling's weight) interpolated, `NaN` where
/// there is no height, at least [`MIN_MEASURED_CONFIDENCE`] elsewhere.
fn left_grid_confidence(
    canvas_confidence: &Image,
    filled: &[bool],
    height_um: &Image,
    h_left: &Matrix3<f64>,
) -> Image {
    let (w, h) = height_um.dimensions();
    let (cw, ch) = canvas_confidence.dimensions();
    let any_filled = filled.contains(&true);
    // The filled mask as 0/1 samples, interpolated as `Image::sample_bilinear` would, without
    // a canvas-sized copy of it.
    let filled_at = |x: f64, y: f64| -> f32 {
        if !(x >= 0.0 && y >= 0.0 && x <= (cw - 1) as f64 && y <= (ch - 1) as f64) {
            return 0.0;
        }
        // Non-negative (tested above): truncation is the floor, without a library call.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(cw - 1), (y0 + 1).min(ch - 1));
        #[allow(clippy::cast_possible_truncation)]
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let at = |x: usize, y: usize| f32::from(u8::from(filled[y * cw + x]));
        let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
        let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
        top * (1.0 - fy) + bottom * fy
    };
    let mut confidence = Image::zeros(w, h);
    confidence
        .data_mut()
        .par_chunks_mut(w.max(1))
        .zip(height_um.data().par_chunks(w.max(1)))
        .enumerate()
        .for_each(|(y, (row, height_row))| {
            for (x, (c, hv)) in row.iter_mut().zip(height_row).enumerate() {
                let p = h_left * Vector3::new(x as f64, y as f64, 1.0);
                let (mut sampled, mut filled) = (0.0, 0.0);
                if p.z.abs() > 1e-12 {
                    let (px, py) = (p.x / p.z, p.y / p.z);
                    sampled = canvas_confidence.sample_bilinear(px, py).unwrap_or(0.0);
                    if any_filled {
                        filled = filled_at(px, py);
                    }
                }
                *c = if !hv.is_finite() {
                    f32::NAN
                } else if filled >= 0.5 || !sampled.is_finite() {
                    0.0
                } else {
                    // A measured height whose match had no margin or correlation
                    // still is one: 0 stays reserved for interpolated heights.
                    sampled.max(MIN_MEASURED_CONFIDENCE)
                };
            }
        });
    confidence
}

/// Why each height of the left grid is unknown or interpolated: interpolated where its
/// confidence is 0, else the reason of the canvas pixels it is resampled from (the first of
/// the four around it that has one); [`Unknown::NotSeen`] off the canvas.
fn left_grid_unknown(
    canvas_unknown: &[Unknown],
    (cw, ch): (usize, usize),
    height_um: &Image,
    confidence: &Image,
    h_left: &Matrix3<f64>,
) -> Vec<Unknown> {
    let (w, h) = height_um.dimensions();
    (0..w * h)
        .into_par_iter()
        .map(|p| {
            if height_um.data()[p].is_finite() {
                return if confidence.data()[p] == 0.0 {
                    Unknown::Interpolated
                } else {
                    Unknown::Measured
                };
            }
            let q = h_left * Vector3::new((p % w) as f64, (p / w) as f64, 1.0);
            if q.z.abs() <= 1e-12 {
                return Unknown::NotSeen;
            }
            let (x, y) = (q.x / q.z, q.y / q.z);
            let inside = |c: f64, n: usize| c >= 0.0 && c <= (n - 1) as f64;
            if !(inside(x, cw) && inside(y, ch)) {
                return Unknown::NotSeen;
            }
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let corners = [
                (x.floor() as usize, y.floor() as usize),
                (x.ceil() as usize, y.floor() as usize),
                (x.floor() as usize, y.ceil() as usize),
                (x.ceil() as usize, y.ceil() as usize),
            ];
            corners
                .iter()
                .map(|&(cx, cy)| canvas_unknown[cy * cw + cx])
                .find(|u| !matches!(u, Unknown::Measured | Unknown::Interpolated))
                .unwrap_or(Unknown::NotSeen)
        })
        .collect()
}

/// The Gaussian window (σ, pixels) whose precision bounds the disparity:
/// the intensity refinement's window when there is one; without, the
/// descriptor's `4 · cell_size` square, as the Gaussian of the same
/// effective area (`4πσ² = (4 · cell_size)²`).
#[must_use]
pub fn matcher_window_sigma(dense: &DenseParams) -> f64 {
    let flow = &dense.flow;
    flow.refinement().map_or_else(
        || 4.0 * flow.cell_size as f64 / (4.0 * std::f64::consts::PI).sqrt(),
        |r| f64::from(r.window_sigma),
    )
}

/// The 1st and 99th percentile of the rectified horizontal disparity of the
/// sparse inliers (canvas pixels), `None` with fewer than 8 of them.
#[must_use]
pub fn inlier_disparity_range(
    inliers: &[super::sparse::Correspondence],
    r: &super::rectify::Rectification,
) -> Option<(f64, f64)> {
    let x = |hm: &Matrix3<f64>, p: [f64; 2]| {
        let q = hm * Vector3::new(p[0], p[1], 1.0);
        q.x / q.z
    };
    let mut d: Vec<f64> = inliers
        .iter()
        .map(|c| x(&r.h_right, c.right) - x(&r.h_left, c.left))
        .filter(|v| v.is_finite())
        .collect();
    if d.len() < 8 {
        return None;
    }
    d.sort_by(f64::total_cmp);
    let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize];
    Some((at(0.01), at(0.99)))
}

fn validate(g: &PairGeometry) -> Result<(), ReconstructError> {
    if !(g.tilt_deg > 0.0 && g.tilt_deg <= MAX_TILT_DEG) {
        return Err(ReconstructError::Tilt(g.tilt_deg));
    }
    if !(g.pixel_size_um > 0.0 && g.pixel_size_um.is_finite()) {
        return Err(ReconstructError::PixelSize(g.pixel_size_um));
    }
    if !g.tilt_axis_deg.is_finite() {
        return Err(ReconstructError::TiltAxis(g.tilt_axis_deg));
    }
    Ok(())
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    [
        [m[(0, 0)], m[(0, 1)], m[(0, 2)]],
        [m[(1, 0)], m[(1, 1)], m[(1, 2)]],
        [m[(2, 0)], m[(2, 1)], m[(2, 2)]],
    ]
}

fn depth_report(height: &Image, g: &StereoGeometry) -> DepthReport {
    let finite: Vec<f32> = height
        .data()
        .par_iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let (p01, p99) = percentiles_01_99(&finite);
    DepthReport {
        valid_fraction: finite.len() as f64 / height.len().max(1) as f64,
        height_p01_um: p01,
        height_p99_um: p99,
        um_per_disparity_px: g.um_per_px(),
    }
}

/// The 1st and 99th percentile of `v` (the values at ranks `round((n − 1)·q)` of its sorted
/// order), `NaN` when empty. Two counted selections instead of a sort: the same values, in
/// linear time on both cores.
fn percentiles_01_99(v: &[f32]) -> (f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let rank = |q: f64| ((v.len() - 1) as f64 * q).round() as usize;
    let (lo, hi) = (rank(0.01), rank(0.99));
    let at = |k: usize| f64::from(crate::vision::precision::kth_smallest(&[v], k));
    (at(lo), at(hi))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one line `main` prints (`{:#}`, the cause chain) names a stage's
    /// error once: the stage's message already carries it.
    #[test]
    fn a_stage_error_is_named_once_in_the_printed_chain() {
        let e = ReconstructError::from(DenseError::InvalidParameter {
            name: "finest_d",
            reason: "must be finite and non-negative".to_owned(),
        });
        let line = format!("{:#}", anyhow::Error::from(e));
        assert_eq!(
            line,
            "dense stage: invalid dense parameter `finest_d`: must be finite and non-negative"
        );
        let e = ReconstructError::from(DenseError::NoValidPixels);
        assert!(std::error::Error::source(&e).is_none());
    }

    /// On the left grid: NaN where there is no height, 0 where the height
    /// was interpolated, the dense stage's confidence elsewhere.
    #[test]
    fn confidence_marks_interpolated_and_unknown_heights() {
        let (w, h) = (6, 4);
        let canvas = Image::filled(w, h, 0.8);
        let mut filled = vec![false; w * h];
        filled[2 * w + 3] = true;
        let height = Image::from_fn(w, h, |x, y| if (x, y) == (0, 0) { f32::NAN } else { 1.0 });
        let c = left_grid_confidence(&canvas, &filled, &height, &Matrix3::identity());
        assert!(c.get(0, 0).is_nan());
        assert_eq!(c.get(3, 2), 0.0);
        assert!((c.get(5, 3) - 0.8).abs() < 1e-6 && (c.get(1, 0) - 0.8).abs() < 1e-6);
        let none =
            left_grid_confidence(&canvas, &vec![false; w * h], &height, &Matrix3::identity());
        assert_eq!(none.data().iter().filter(|v| **v == 0.0).count(), 0);
        // A measured height whose match had no margin still reads above 0.
        let flat = Image::filled(w, h, 0.0);
        let c = left_grid_confidence(&flat, &filled, &height, &Matrix3::identity());
        assert_eq!(c.get(3, 2), 0.0);
        assert!(c.get(1, 0) > 0.0 && c.get(5, 3) > 0.0);
    }

    /// The percentiles by selection are those of a full sort.
    #[test]
    fn percentiles_by_selection_equal_the_sorted_ranks() {
        let mut seed = 3u32;
        for n in [1usize, 2, 3, 50, 101, 1000, 4099] {
            let v: Vec<f32> = (0..n)
                .map(|_| {
                    seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    // Repeated values and both zeros, as heights have.
                    ((seed >> 20) % 97) as f32 - 48.0
                })
                .map(|x| if x == 0.0 { -0.0 } else { x / 3.0 })
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(f32::total_cmp);
            let at = |q: f64| f64::from(sorted[((n - 1) as f64 * q).round() as usize]);
            let (p01, p99) = percentiles_01_99(&v);
            assert_eq!(
                (p01.to_bits(), p99.to_bits()),
                (at(0.01).to_bits(), at(0.99).to_bits())
            );
        }
        assert!(percentiles_01_99(&[]).0.is_nan());
    }

    #[test]
    fn impossible_geometry_is_refused_before_any_work() {
        let img = Image::zeros(64, 64);
        let p = ReconstructionParams::default();
        for (tilt, pixel) in [
            (0.0, 0.1),
            (-3.0, 0.1),
            (61.0, 0.1),
            (5.0, 0.0),
            (5.0, f64::NAN),
        ] {
            let g = PairGeometry {
                tilt_deg: tilt,
                pixel_size_um: pixel,
                tilt_axis_deg: 0.0,
            };
            let err = reconstruct(&img, &img, &g, &p).unwrap_err();
            assert!(
                matches!(
                    err,
                    ReconstructError::Tilt(_) | ReconstructError::PixelSize(_)
                ),
                "{err}"
            );
        }
    }

    #[test]
    fn textureless_pair_is_a_clear_error() {
        let img = Image::filled(128, 96, 0.5);
        let g = PairGeometry {
            tilt_deg: 5.0,
            pixel_size_um: 0.1,
            tilt_axis_deg: 0.0,
        };
        let err = reconstruct(&img, &img, &g, &ReconstructionParams::default()).unwrap_err();
        assert!(
            matches!(
                err,
                ReconstructError::Unrectifiable {
                    instrument: InstrumentError::NoCorrelation(_),
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().contains("texture"), "{err}");
        let mut off = ReconstructionParams::default();
        off.sparse.instrument.enabled = false;
        let err = reconstruct(&img, &img, &g, &off).unwrap_err();
        assert!(matches!(err, ReconstructError::Sparse(_)), "{err}");
    }

    /// A pair the sparse stage refuses (here: more inliers asked for than exist) is rectified
    /// from the tilt axis; the report says so, and the relief keeps its sign.
    #[test]
    fn a_refused_sparse_stage_falls_back_to_the_instrument() {
        let pair = crate::vision::sparse::tests::sem_pair(320, 256, -90.0, (-4.0, 4.0), 0.4, false);
        let g = PairGeometry {
            tilt_deg: 8.0,
            pixel_size_um: 0.1,
            tilt_axis_deg: -90.0,
        };
        let mut p = ReconstructionParams::default();
        p.sparse.min_inliers = 100_000;
        p.sparse.instrument.tile_px = 64;
        let r = reconstruct(&pair.left, &pair.right, &g, &p).unwrap();
        let geometry = &r.report.geometry;
        assert_eq!(geometry.source, GeometrySource::Instrument);
        assert!(
            geometry
                .sparse_refused
                .as_deref()
                .is_some_and(|w| w.contains("need 100000")),
            "{geometry:?}"
        );
        let f = geometry.instrument.unwrap();
        let rows = f.dense_rows.unwrap();
        assert!(
            rows.offset_px < 0.3 && rows.axis_error_deg.abs() < 1.0,
            "{f:?}"
        );
        let at = |p: [f64; 2]| {
            f64::from(r.height_um.get(
                (p[0].round() as usize).min(319),
                (p[1].round() as usize).min(255),
            ))
        };
        assert!(
            at(pair.top) > at(pair.flat) + 1.0,
            "top {} flat {}",
            at(pair.top),
            at(pair.flat)
        );
        assert!(r.report.depth.valid_fraction > 0.8);
        // With the fallback off, the same pair is refused.
        p.sparse.instrument.enabled = false;
        assert!(matches!(
            reconstruct(&pair.left, &pair.right, &g, &p),
            Err(ReconstructError::Sparse(_))
        ));
    }
}
