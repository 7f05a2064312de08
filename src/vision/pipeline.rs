//! The SD-SEM reconstruction of a stereo pair, start to finish (Baghaie et al.,
//! Micron 97, 2017):
//!
//! ```text
//! left, right ─▶ sparse SIFT ─▶ matching ─▶ ORSA ─▶ quasi-Euclidean rectification
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
use super::dense::tile::{Coverage, Rect, fits_budget};
use super::dense::{
    CanvasDisparity, DenseError, DenseParams, DenseStats, Unknown, dense_disparity_of_warped,
    dense_disparity_tiled,
};
use super::depth::{DepthError, StereoGeometry, height_on_left_grid};
use super::geometry::{MAX_TILT_DEG, PairGeometry};
use super::params::ReconstructionParams;
use super::precision::{self, Precision};
use super::rectify::RectifyError;
use super::rectify::warp::warp_rect;
use super::sparse::{SparseError, sparse_stage, warp_onto_canvas};
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

/// Everything a reconstruction reports (report.json, `/recon/report`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReconReport {
    pub geometry: PairGeometry,
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
    let sparse = sparse_stage(left, right, Some(geometry.tilt_axis_deg), &params.sparse)?;
    let range = inlier_disparity_range(&sparse.inliers, &sparse.rectification);
    let canvas = sparse.rectification.canvas;
    let (sparse, disp, sparse_ms, dense_ms) = if fits_budget(&params.dense, canvas) {
        let rect = warp_onto_canvas(left, right, sparse)?;
        let sparse_ms = ms(t);
        let t = Instant::now();
        progress(Stage::Dense);
        // The rectified pair becomes the dense stage's working copy.
        let disp = dense_disparity_of_warped(rect.left, rect.right, &params.dense, range)?;
        (rect.sparse, CanvasDisparity::from(disp), sparse_ms, ms(t))
    } else {
        // Each tile warps its own rectangle: the rectified pair is never whole in memory.
        let sparse_ms = ms(t);
        let t = Instant::now();
        progress(Stage::Dense);
        let r = &sparse.rectification;
        if r.h_left.try_inverse().is_none() || r.h_right.try_inverse().is_none() {
            return Err(SparseError::Rectify(RectifyError::Degenerate).into());
        }
        let source = |rect: Rect| {
            let at = ((rect.x, rect.y), (rect.width, rect.height));
            let (l, r) = rayon::join(
                || warp_rect(left, &r.h_left, at.0, at.1),
                || warp_rect(right, &r.h_right, at.0, at.1),
            );
            (
                l.expect("H_left is invertible (checked above)"),
                r.expect("H_right is invertible (checked above)"),
            )
        };
        let coverage = left_coverage(left.dimensions(), &r.h_left, canvas);
        let disp = dense_disparity_tiled(canvas, &coverage, source, &params.dense, range)?;
        (sparse, disp, sparse_ms, ms(t))
    };

    let t = Instant::now();
    progress(Stage::Depth);
    let r = &sparse.rectification;
    let stereo = StereoGeometry {
        tilt_deg: geometry.tilt_deg,
        pixel_size_um: geometry.pixel_size_um,
        tilt_axis_deg: geometry.tilt_axis_deg,
    };
    let (w, h) = left.dimensions();
    let mut height_um = height_on_left_grid(&disp.disparity, &r.h_left, &r.h_right, &stereo, w, h)?;
    let datum = apply_datum(&mut height_um, params.datum, geometry.pixel_size_um);
    let confidence = left_grid_confidence(&disp.confidence, &disp.filled, &height_um, &r.h_left);
    let unknown = left_grid_unknown(&disp.unknown, canvas, &height_um, &confidence, &r.h_left);
    // The canvas maps (up to twice the micrograph's pixels) go before the precision's planes.
    let dense_stats = disp.stats;
    drop((disp.disparity, disp.confidence, disp.filled, disp.unknown));
    let depth = depth_report(&height_um, &stereo);
    if depth.valid_fraction == 0.0 {
        return Err(ReconstructError::NoOverlap);
    }
    let depth_ms = ms(t);
    let precision = precision::predict(
        left,
        right,
        geometry.tilt_axis_deg,
        matcher_window_sigma(&params.dense),
        depth.um_per_disparity_px,
    );

    let s = &sparse;
    let map = |hm: &Matrix3<f64>, p: [f64; 2]| {
        let q = hm * Vector3::new(p[0], p[1], 1.0);
        (q.x / q.z, q.y / q.z)
    };
    let rectification = RectificationFigures {
        v2_over_u2_before: v2_over_u2(
            s.inliers
                .iter()
                .map(|c| (c.right[0] - c.left[0], c.right[1] - c.left[1])),
        ),
        v2_over_u2_after: v2_over_u2(s.inliers.iter().map(|c| {
            let (l, r) = (map(&r.h_left, c.left), map(&r.h_right, c.right));
            (r.0 - l.0, r.1 - l.1)
        })),
        v2_over_u2_dense: dense_stats.flow.v2_over_u2,
        rmse_before_px: r.initial_error_px,
        rmse_after_px: r.final_error_px,
    };
    let report = ReconReport {
        geometry: *geometry,
        image_size: (w, h),
        sparse: SparseReport {
            keypoints_left: s.keypoints_left,
            keypoints_right: s.keypoints_right,
            matches: s.matches.len(),
            inliers: s.inliers.len(),
            model: format!("{:?}", s.model).to_lowercase(),
            fallback_reason: s.fallback_reason.clone(),
            log10_nfa: s.log10_nfa,
            threshold_px: s.threshold_px,
            orsa_iterations: s.orsa_iterations,
            initial_error_px: r.initial_error_px,
            final_error_px: r.final_error_px,
            h_left: rows(&r.h_left),
            h_right: rows(&r.h_right),
            canvas: r.canvas,
            timings: s.timings,
        },
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
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
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
    let mut finite: Vec<f32> = height
        .data()
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    finite.sort_by(f32::total_cmp);
    let pick = |q: f64| -> f64 {
        if finite.is_empty() {
            f64::NAN
        } else {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let i = ((finite.len() - 1) as f64 * q).round() as usize;
            f64::from(finite[i])
        }
    };
    DepthReport {
        valid_fraction: finite.len() as f64 / height.len().max(1) as f64,
        height_p01_um: pick(0.01),
        height_p99_um: pick(0.99),
        um_per_disparity_px: g.um_per_px(),
    }
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
        assert!(matches!(err, ReconstructError::Sparse(_)), "{err}");
        assert!(err.to_string().contains("texture"), "{err}");
    }
}
