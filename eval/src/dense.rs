//! Accuracy of the reconstruction on the simulator's ground-truth scenes:
//! render a left/right pair at known tilts, run the sparse stage (SIFT, ORSA,
//! rectification), the dense stage and eq. (19), and score the height map on
//! the left grid against the renderer's true heights.
//!
//! Figures per case (the targets in brackets), over the pixels the
//! renderer says are visible in both micrographs:
//! coverage of visible pixels [≥ 95 %]; RMSE after removing the best-fit plane
//! of the error, relative to the true height range [≤ 5 %]; median of that
//! residual and its fraction above 1 px, in disparity pixels [≤ 0.2 px, ≤ 3 %];
//! the height scale, the slope of estimated against true height [1 ± 3 %], and the same
//! slope before the bilateral filter (`unfiltered`: the matcher's share of a compression);
//! the unknown fraction (visible pixels without a height) and, on scenes with a
//! featureless support, the share of the support left unknown, the fraction
//! of its *reported* heights more than 1 px of disparity off [≤ 1 %], and the coverage
//! of the visible pixels off the support, on which the coverage target is judged there
//! (the support's heights should be unknown: the micrographs cannot tell them).
//! A case the sparse stage refuses is a row of its own (`REFUSED`), not a failure
//! of the run.
//!
//! With [`Rectifier::Truth`] the sparse stage is replaced by the exact
//! rectification the simulator's geometry implies (both views rotated so that
//! the parallax direction n is +x): the dense stage's errors alone.

use std::time::Instant;

use nalgebra::{DMatrix, DVector, Matrix3};
use sdsem_sim::render::{
    NoiseParams, ShadingParams, View, correspondences, height_map, render_noisy,
};
use sdsem_sim::scene::{Scene, SceneKind, SceneParams};
use serde::Serialize;

use sdsem::vision::Image;
use sdsem::vision::Preset;
use sdsem::vision::dense::{DenseParams, DenseStats, dense_disparity_in_range};
use sdsem::vision::depth::{StereoGeometry, height_on_left_grid};
use sdsem::vision::pipeline::{Established, rectify_for_dense};
use sdsem::vision::rectify::warp::{Warped, warp};
use sdsem::vision::sparse::SparseParams;

/// Where the rectification of a simulated pair comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Rectifier {
    /// The sparse stage (SIFT, ORSA, quasi-Euclidean): the whole pipeline.
    Sparse,
    /// The simulator's exact geometry: the dense stage alone.
    Truth,
    /// The instrument's geometry (tilt axis, tiles' phase correlation; no sparse matches) as
    /// if the sparse stage had failed, with the dense stage's check of its rows: the fallback
    /// measured on every scene.
    Instrument,
}

/// One simulated acquisition.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SimCase {
    pub kind: SceneKind,
    pub width: usize,
    pub height: usize,
    /// θ, degrees: left at −θ/2, right at +θ/2.
    pub tilt_deg: f64,
    /// φ, degrees.
    pub tilt_axis_deg: f64,
    pub seed: u64,
    /// Render without scan noise (separates the noise floor from the rest).
    pub noiseless: bool,
    /// Pixel dwell time of both micrographs, µs: the scan noise falls as its
    /// square root.
    pub dwell_us: f64,
}

/// The figures of one case.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SimFigures {
    pub case: SimCase,
    pub mode: Preset,
    pub rectifier: Rectifier,
    /// Which path rectified the pair (`sparse`, `instrument`; `truth` for the exact one).
    pub geometry_source: &'static str,
    /// The dense stage's systematic vertical flow (the instrument's check of its rows).
    pub dense_rows: Option<sdsem::vision::rectify::instrument::DenseRows>,
    /// Fraction of pixels visible in both micrographs that got a height.
    pub coverage: f64,
    /// True height range (1st to 99th percentile) over the visible pixels, µm.
    pub height_range_um: f64,
    /// RMSE of the error after removing its best-fit plane, µm.
    pub rmse_um: f64,
    /// `rmse_um / height_range_um`.
    pub rmse_relative: f64,
    /// The height noise floor the micrographs allow at the matcher's
    /// window ([`sdsem::vision::precision`]) over `height_range_um`: an RMSE
    /// target below it cannot be met at that window.
    pub noise_floor_relative: Option<f64>,
    /// Median |residual| in disparity pixels (eq. 19 backwards).
    pub median_px: f64,
    /// Fraction of pixels whose |residual| exceeds one disparity pixel.
    pub over_1px: f64,
    /// Slope of the estimated height against the true one (plane removed): least squares of
    /// `estimated = s · true + a + b·x + c·y` over the visible pixels with a height.
    pub height_scale: f64,
    /// The same slope of the measured disparity before the bilateral filter
    /// ([`sdsem::vision::dense::Disparity::raw`]), over the visible pixels it covers: what the
    /// matcher loses, apart from what the filter does.
    pub height_scale_unfiltered: f64,
    /// Fraction of pixels visible in both micrographs left without a height.
    pub unknown: f64,
    /// On a featureless support: the fraction of the visible pixels *off* the support that
    /// got a height. The issue asks for heights where the micrographs can tell and unknown
    /// where they cannot, so the coverage target is judged on this figure there, and the
    /// support's unknown share is reported apart ([`SupportFigures::unknown`]).
    pub coverage_off_support: Option<f64>,
    /// On a featureless support (scenes `bare`, `calgrid`): what was reported there.
    pub support: Option<SupportFigures>,
    pub sparse_ms: f64,
    pub dense_ms: f64,
    pub depth_ms: f64,
    /// Median |error| of the horizontal disparity on the rectified canvas
    /// against the exact correspondences, before and after the bilateral
    /// filter, and of the vertical flow, pixels (no plane removed).
    pub canvas_error_px: CanvasErrors,
    pub dense: DenseStats,
}

/// The figures of a scene's featureless support (true height 0, no texture).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SupportFigures {
    /// Share of the visible pixels that lie on the support.
    pub share: f64,
    /// Fraction of the support's visible pixels left unknown.
    pub unknown: f64,
    /// Fraction of the support's reported heights whose residual exceeds one disparity pixel.
    pub reported_over_1px: f64,
}

impl SimFigures {
    /// The coverage the target is judged on: off the featureless support where the scene has
    /// one (the support's pixels should be unknown, see [`SupportFigures`]), else of every
    /// visible pixel.
    #[must_use]
    pub fn judged_coverage(&self) -> f64 {
        self.coverage_off_support.unwrap_or(self.coverage)
    }
}

/// Errors of the flow on the rectified canvas against the exact correspondences.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CanvasErrors {
    pub raw_median: f64,
    pub filtered_median: f64,
    pub vertical_median: f64,
    /// Mean signed error of the filtered disparity (a bias shows here).
    pub filtered_mean: f64,
    /// Median |vertical offset| of the exact correspondences on the rectified canvas, pixels:
    /// the rectification's own row error, whatever the dense stage makes of it (0 for the exact
    /// rectification). The dense stage's check of the rows ([`SimFigures::dense_rows`]) is a
    /// different figure: a fit to its measured vertical flow, which wanders where the flow does.
    pub rows_median: f64,
    /// On a scene with a featureless support: how much of the raised features' relief the
    /// matcher measured before the filter.
    pub raised: Option<RaisedRelief>,
}

/// The relief of the raised features above a featureless support on the canvas, before the
/// bilateral filter: the matcher's own compression of it, apart from the support's invented
/// heights. On the calibration grid the bars' silhouettes are the strongest texture and, with
/// walls steeper than half the tilt, each micrograph sees one wall the other cannot: the
/// outline moves by about half the top's disparity, and a window that straddles it measures
/// the bar at about half its height.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RaisedRelief {
    /// Share of the visible pixels on the tops (true height at least 80 % of the 99th
    /// percentile), with a measured disparity.
    pub share: f64,
    /// Median true disparity of the tops minus that of the support, pixels.
    pub true_px: f64,
    /// The same measured: median measured disparity of the tops minus that of the support's
    /// measured pixels, both as errors against the exact disparities (a support left unknown
    /// leaves the figure undefined, NaN).
    pub measured_px: f64,
}

/// Errors of a simulated evaluation.
#[derive(Debug, thiserror::Error)]
pub enum SimEvalError {
    #[error("the exact rectification homography is singular")]
    Singular,
    #[error("scene: {0}")]
    Scene(sdsem_sim::scene::SceneError),
    #[error("{0}")]
    Rectify(sdsem::vision::pipeline::ReconstructError),
    #[error("instrument geometry not verified by the dense stage: {0}")]
    Unverified(sdsem::vision::rectify::instrument::InstrumentError),
    #[error("dense stage: {0}")]
    Dense(sdsem::vision::dense::DenseError),
    #[error("depth: {0}")]
    Depth(sdsem::vision::depth::DepthError),
    #[error("no pixel is visible in both micrographs")]
    NothingVisible,
}

sdsem::error_from!(SimEvalError {
    Scene(sdsem_sim::scene::SceneError),
    Rectify(sdsem::vision::pipeline::ReconstructError),
    Dense(sdsem::vision::dense::DenseError),
    Depth(sdsem::vision::depth::DepthError),
});

/// Pixel dwell of the rendered micrographs, µs (a capture, not a tracking frame).
const DWELL_US: f64 = 10.0;

/// Least-squares fit of `y` by the columns `[1, x, y, extra...]`; returns the
/// coefficients.
fn fit(rows: &[(f64, f64, Vec<f64>)], target: &[f64]) -> Option<Vec<f64>> {
    let n = rows.len();
    let m = 3 + rows.first().map_or(0, |r| r.2.len());
    let a = DMatrix::from_fn(n, m, |i, j| match j {
        0 => 1.0,
        1 => rows[i].0,
        2 => rows[i].1,
        _ => rows[i].2[j - 3],
    });
    let b = DVector::from_column_slice(target);
    let ata = a.transpose() * &a;
    let atb = a.transpose() * b;
    ata.lu().solve(&atb).map(|x| x.iter().copied().collect())
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i]
}

/// The exact rectification of a simulated pair: a rotation taking the
/// parallax direction n = (−sin φ, cos φ) to +x (proper, no mirror), shifted
/// onto the bounding box of the rotated frame. Both views get the same one:
/// with symmetric tilts a point's coordinate along the tilt axis is the same
/// in both, so rows correspond exactly. Returns `H` and the canvas size.
#[must_use]
pub fn exact_rectification(
    width: usize,
    height: usize,
    tilt_axis_deg: f64,
) -> (Matrix3<f64>, (usize, usize)) {
    let phi = tilt_axis_deg.to_radians();
    let (nx, ny) = (-phi.sin(), phi.cos());
    // x' = n·p, y' = (−n_y, n_x)·p: a rotation (determinant 1).
    let rot = Matrix3::new(nx, ny, 0.0, -ny, nx, 0.0, 0.0, 0.0, 1.0);
    let (w, h) = ((width - 1) as f64, (height - 1) as f64);
    let corners = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].map(|(x, y)| {
        let q = rot * nalgebra::Vector3::new(x, y, 1.0);
        (q.x, q.y)
    });
    let min_x = corners.iter().map(|c| c.0).fold(f64::INFINITY, f64::min);
    let max_x = corners
        .iter()
        .map(|c| c.0)
        .fold(f64::NEG_INFINITY, f64::max);
    let min_y = corners.iter().map(|c| c.1).fold(f64::INFINITY, f64::min);
    let max_y = corners
        .iter()
        .map(|c| c.1)
        .fold(f64::NEG_INFINITY, f64::max);
    // Snap tiny rounding of the axis-aligned cases so no column is lost.
    let snap = |v: f64| {
        if (v - v.round()).abs() < 1e-9 {
            v.round()
        } else {
            v
        }
    };
    let (min_x, min_y) = (snap(min_x), snap(min_y));
    let shift = Matrix3::new(1.0, 0.0, -min_x, 0.0, 1.0, -min_y, 0.0, 0.0, 1.0);
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let canvas = (
        (snap(max_x) - min_x).floor() as usize + 1,
        (snap(max_y) - min_y).floor() as usize + 1,
    );
    (shift * rot, canvas)
}

/// A rectified pair and the homographies that made it.
struct Rectified {
    left: Warped,
    right: Warped,
    h_left: Matrix3<f64>,
    h_right: Matrix3<f64>,
    /// Disparity range of the sparse inliers on the canvas (sparse only).
    range: Option<(f64, f64)>,
    source: &'static str,
}

/// The flow's errors on the canvas: every visible left pixel and its exact
/// match, both through the rectification, against the flow sampled there.
///
/// `support_truth`: the true heights where the scene has a featureless support at z = 0
/// (then [`CanvasErrors::raised`] is measured).
fn canvas_errors(
    corr: &[Option<sdsem_sim::render::Correspondence>],
    visible: &[bool],
    width: usize,
    rect: &Rectified,
    disp: &sdsem::vision::dense::Disparity,
    support_truth: Option<&[f32]>,
) -> CanvasErrors {
    let map = |hm: &Matrix3<f64>, x: f64, y: f64| {
        let q = hm * nalgebra::Vector3::new(x, y, 1.0);
        (q.x / q.z, q.y / q.z)
    };
    let (mut raw, mut filt, mut vert, mut rows) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut sum = 0f64;
    // The tops' threshold, and per region (support, tops) the exact disparities and the
    // measured ones' errors.
    let top_from = support_truth.map(|t| {
        let mut v: Vec<f64> = t
            .iter()
            .zip(visible)
            .filter(|(h, vis)| **vis && h.is_finite())
            .map(|(h, _)| f64::from(*h))
            .collect();
        v.sort_by(f64::total_cmp);
        0.8 * percentile(&v, 0.99)
    });
    let (mut true_d, mut raw_err) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
    let mut n_visible = 0usize;
    for (p, c) in corr.iter().enumerate() {
        let Some(c) = c else { continue };
        if !visible[p] {
            continue;
        }
        n_visible += 1;
        let (xl, yl) = map(&rect.h_left, (p % width) as f64, (p / width) as f64);
        let (xr, yr) = map(&rect.h_right, c.x, c.y);
        let (du, dv) = (xr - xl, yr - yl);
        rows.push(dv.abs());
        let at = |img: &Image| {
            img.sample_bilinear(xl, yl)
                .map(f64::from)
                .filter(|v| v.is_finite())
        };
        if let (Some(t), Some(from)) = (support_truth, top_from) {
            let h = f64::from(t[p]);
            let region = if h.abs() < 1e-3 {
                Some(0)
            } else if h >= from {
                Some(1)
            } else {
                None
            };
            if let Some(k) = region {
                true_d[k].push(du);
                if let Some(r) = at(&disp.raw) {
                    raw_err[k].push(r - du);
                }
            }
        }
        if let (Some(r), Some(f), Some(v)) =
            (at(&disp.raw), at(&disp.disparity), at(&disp.vertical))
        {
            raw.push((r - du).abs());
            filt.push((f - du).abs());
            vert.push((v - dv).abs());
            sum += f - du;
        }
    }
    let n = filt.len().max(1) as f64;
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        percentile(&v, 0.5)
    };
    let raised = top_from.map(|_| {
        let share = raw_err[1].len() as f64 / n_visible.max(1) as f64;
        let [true_support, true_top] = true_d.map(median);
        let [err_support, err_top] = raw_err.map(median);
        RaisedRelief {
            share,
            true_px: true_top - true_support,
            measured_px: true_top - true_support + err_top - err_support,
        }
    });
    CanvasErrors {
        raw_median: median(raw),
        filtered_median: median(filt),
        vertical_median: median(vert),
        filtered_mean: sum / n,
        rows_median: median(rows),
        raised,
    }
}

/// A rendered case: the micrographs and what the truth needs.
pub struct RenderedCase {
    pub left: Image,
    pub right: Image,
    pub pixel_size_um: f64,
    scene: Scene,
    left_view: View,
    right_view: View,
}

/// Renders the left (−θ/2) and right (+θ/2) micrographs of a case.
///
/// # Errors
/// [`SimEvalError::Scene`] when the scene cannot be built.
pub fn render_case(case: &SimCase) -> Result<RenderedCase, SimEvalError> {
    let scene = Scene::generate(&SceneParams {
        kind: case.kind,
        seed: Some(case.seed),
        ..SceneParams::default()
    })?;
    // About 128 µm of field whatever the frame size.
    let pixel_size_um = 0.1 * 1280.0 / case.width as f64;
    let view = |tilt: f64| View {
        width: case.width,
        height: case.height,
        pixel_size_um,
        tilt_deg: tilt,
        tilt_axis_deg: case.tilt_axis_deg,
        ..View::default()
    };
    let (lv, rv) = (view(-case.tilt_deg / 2.0), view(case.tilt_deg / 2.0));
    let shading = ShadingParams::default();
    let noise = if case.noiseless {
        NoiseParams::none()
    } else {
        NoiseParams::default()
    };
    let left_px = render_noisy(
        &scene,
        &lv,
        &shading,
        &noise,
        case.dwell_us,
        case.seed * 2 + 1,
    );
    let right_px = render_noisy(
        &scene,
        &rv,
        &shading,
        &noise,
        case.dwell_us,
        case.seed * 2 + 2,
    );
    let left = Image::from_vec(case.width, case.height, left_px)
        .expect("rendered frame has the view size");
    let right = Image::from_vec(case.width, case.height, right_px)
        .expect("rendered frame has the view size");
    Ok(RenderedCase {
        left,
        right,
        pixel_size_um,
        scene,
        left_view: lv,
        right_view: rv,
    })
}

/// Writes a case's micrographs as 16-bit TIFFs with their tilt and pixel size
/// (`<kind>_<w>x<h>_left.tif`, `…_right.tif`): inputs for `sdsem reconstruct`; and their
/// ground truth, `…_truth.tif`, for `sdsem-eval score-height` ([`super::large`]).
///
/// # Errors
/// When the scene cannot be built or a file cannot be written.
pub fn write_case(
    case: &SimCase,
    dir: &std::path::Path,
) -> anyhow::Result<[std::path::PathBuf; 2]> {
    use sdsem::imaging::file::{MicrographTags, SampleDepth, write_micrograph_tiff};
    let r = render_case(case)?;
    std::fs::create_dir_all(dir)?;
    let stem = format!("{}_{}x{}", case.kind.name(), case.width, case.height);
    let mut out = Vec::new();
    for (side, img, tilt) in [
        ("left", &r.left, -case.tilt_deg / 2.0),
        ("right", &r.right, case.tilt_deg / 2.0),
    ] {
        let path = dir.join(format!("{stem}_{side}.tif"));
        let tags = MicrographTags {
            pixel_size_um: Some(r.pixel_size_um),
            tilt_deg: Some(tilt),
            extra: serde_json::Map::from_iter([(
                "tilt_axis_deg".to_owned(),
                serde_json::Value::from(case.tilt_axis_deg),
            )]),
        };
        write_micrograph_tiff(&path, img, &tags, SampleDepth::Bits16)?;
        out.push(path);
    }
    super::large::write_truth(
        &r.scene,
        &r.left_view,
        &r.right_view,
        &dir.join(format!("{stem}_truth.tif")),
    )?;
    Ok([out[0].clone(), out[1].clone()])
}

/// Renders, reconstructs and scores one case.
///
/// # Errors
/// [`SimEvalError`] when the scene cannot be built or a stage fails.
pub fn evaluate_case(
    case: &SimCase,
    preset: Preset,
    sparse: &SparseParams,
    dense: &DenseParams,
    rectifier: Rectifier,
    dump: Option<&std::path::Path>,
) -> Result<SimFigures, SimEvalError> {
    let RenderedCase {
        left,
        right,
        pixel_size_um,
        scene,
        left_view: lv,
        right_view: rv,
    } = render_case(case)?;
    let truth = height_map(&scene, &lv);
    let corr = correspondences(&scene, &lv, &rv);
    let visible: Vec<bool> = corr
        .iter()
        .map(|c| c.is_some_and(|c| c.is_visible()))
        .collect();

    let t = Instant::now();
    let rect = match rectifier {
        Rectifier::Sparse => {
            // The reconstruction's own choice: the sparse stage, or the instrument's geometry.
            let g = rectify_for_dense(
                &left,
                &right,
                &sdsem::vision::geometry::PairGeometry {
                    tilt_deg: case.tilt_deg,
                    pixel_size_um,
                    tilt_axis_deg: case.tilt_axis_deg,
                },
                sparse,
            )?;
            let (cw, ch) = g.canvas;
            Rectified {
                left: warp(&left, &g.h_left, cw, ch).ok_or(SimEvalError::Singular)?,
                right: warp(&right, &g.h_right, cw, ch).ok_or(SimEvalError::Singular)?,
                h_left: g.h_left,
                h_right: g.h_right,
                range: g.range,
                source: match g.source {
                    Established::Sparse(_) => "sparse",
                    Established::Instrument { .. } => "instrument",
                },
            }
        }
        Rectifier::Instrument => {
            let r = sdsem::vision::rectify::instrument::instrument_rectification(
                &left,
                &right,
                case.tilt_axis_deg,
                &[],
                &sparse.instrument,
            )
            .map_err(SimEvalError::Unverified)?;
            let (cw, ch) = r.canvas;
            Rectified {
                left: warp(&left, &r.h_left, cw, ch).ok_or(SimEvalError::Singular)?,
                right: warp(&right, &r.h_right, cw, ch).ok_or(SimEvalError::Singular)?,
                h_left: r.h_left,
                h_right: r.h_right,
                range: r.disparity_range,
                source: "instrument",
            }
        }
        Rectifier::Truth => {
            let (hm, (cw, ch)) = exact_rectification(case.width, case.height, case.tilt_axis_deg);
            Rectified {
                left: warp(&left, &hm, cw, ch).ok_or(SimEvalError::Singular)?,
                right: warp(&right, &hm, cw, ch).ok_or(SimEvalError::Singular)?,
                h_left: hm,
                h_right: hm,
                range: None,
                source: "truth",
            }
        }
    };
    let sparse_ms = t.elapsed().as_secs_f64() * 1e3;
    let t = Instant::now();
    let disp = dense_disparity_in_range(
        &rect.left.image,
        &rect.right.image,
        Some(&rect.left.valid),
        Some(&rect.right.valid),
        dense,
        rect.range,
    )?;
    let dense_ms = t.elapsed().as_secs_f64() * 1e3;
    let dense_rows = sdsem::vision::rectify::instrument::dense_rows(
        &disp.vertical,
        &disp.disparity,
        &disp.unknown,
    );
    if rect.source == "instrument"
        && let Some(v) = &dense_rows
    {
        sdsem::vision::rectify::instrument::verify_dense_rows(
            v,
            case.tilt_axis_deg,
            &sparse.instrument,
        )
        .map_err(SimEvalError::Unverified)?;
    }
    let geometry = StereoGeometry {
        tilt_deg: case.tilt_deg,
        pixel_size_um,
        tilt_axis_deg: case.tilt_axis_deg,
    };
    let t = Instant::now();
    let heights = height_on_left_grid(
        &disp.disparity,
        &rect.h_left,
        &rect.h_right,
        &geometry,
        case.width,
        case.height,
    )?;
    let depth_ms = t.elapsed().as_secs_f64() * 1e3;
    let precision = sdsem::vision::precision::predict(
        &left,
        &right,
        case.tilt_axis_deg,
        sdsem::vision::pipeline::matcher_window_sigma(dense),
        geometry.um_per_px(),
    );
    let canvas_error_px = canvas_errors(
        &corr,
        &visible,
        case.width,
        &rect,
        &disp,
        featureless_support(case.kind).then_some(&truth[..]),
    );

    // Score.
    let w = case.width;
    let n_visible = visible
        .iter()
        .zip(&truth)
        .filter(|(v, t)| **v && t.is_finite())
        .count();
    if n_visible == 0 {
        return Err(SimEvalError::NothingVisible);
    }
    let mut rows = Vec::new();
    let mut est = Vec::new();
    let mut tru = Vec::new();
    for p in 0..truth.len() {
        let (h, t) = (heights.data()[p], truth[p]);
        if visible[p] && t.is_finite() && h.is_finite() {
            rows.push(((p % w) as f64, (p / w) as f64, vec![f64::from(t)]));
            est.push(f64::from(h));
            tru.push(f64::from(t));
        }
    }
    let coverage = est.len() as f64 / n_visible as f64;
    let mut sorted_truth = tru.clone();
    sorted_truth.sort_by(f64::total_cmp);
    let height_range_um = percentile(&sorted_truth, 0.99) - percentile(&sorted_truth, 0.01);
    // Error minus its best plane.
    let err: Vec<f64> = est.iter().zip(&tru).map(|(e, t)| e - t).collect();
    let plane_rows: Vec<(f64, f64, Vec<f64>)> =
        rows.iter().map(|(x, y, _)| (*x, *y, Vec::new())).collect();
    let c = fit(&plane_rows, &err).unwrap_or_else(|| vec![0.0; 3]);
    let resid: Vec<f64> = plane_rows
        .iter()
        .zip(&err)
        .map(|((x, y, _), e)| e - (c[0] + c[1] * x + c[2] * y))
        .collect();
    let n = resid.len().max(1) as f64;
    let rmse_um = (resid.iter().map(|r| r * r).sum::<f64>() / n).sqrt();
    let um_per_px = geometry.um_per_px();
    let mut abs_px: Vec<f64> = resid.iter().map(|r| (r / um_per_px).abs()).collect();
    abs_px.sort_by(f64::total_cmp);
    let median_px = percentile(&abs_px, 0.5);
    let over_1px = abs_px.iter().filter(|&&v| v > 1.0).count() as f64 / n;
    let support = featureless_support(case.kind).then(|| {
        // The support lies at z = 0 exactly; a particle's rim rises from it.
        let on_support = |p: usize| visible[p] && truth[p].is_finite() && truth[p].abs() < 1e-3;
        let n_support = (0..truth.len()).filter(|&p| on_support(p)).count();
        let (mut reported, mut off) = (0usize, 0usize);
        let mut k = 0;
        for p in 0..truth.len() {
            if visible[p] && truth[p].is_finite() && heights.data()[p].is_finite() {
                if on_support(p) {
                    reported += 1;
                    if (resid[k] / um_per_px).abs() > 1.0 {
                        off += 1;
                    }
                }
                k += 1;
            }
        }
        SupportFigures {
            share: n_support as f64 / n_visible as f64,
            unknown: 1.0 - reported as f64 / n_support.max(1) as f64,
            reported_over_1px: off as f64 / reported.max(1) as f64,
        }
    });
    // Height scale: estimated = s · true + plane.
    let height_scale = fit(&rows, &est).map_or(f64::NAN, |c| c[3]);
    let height_scale_unfiltered = {
        let raw = height_on_left_grid(
            &disp.raw,
            &rect.h_left,
            &rect.h_right,
            &geometry,
            case.width,
            case.height,
        )?;
        let (raw_rows, raw_est): (Vec<_>, Vec<f64>) = (0..truth.len())
            .filter(|&p| visible[p] && truth[p].is_finite() && raw.data()[p].is_finite())
            .map(|p| {
                (
                    ((p % w) as f64, (p / w) as f64, vec![f64::from(truth[p])]),
                    f64::from(raw.data()[p]),
                )
            })
            .unzip();
        fit(&raw_rows, &raw_est).map_or(f64::NAN, |c| c[3])
    };
    let coverage_off_support = featureless_support(case.kind).then(|| {
        let off = |p: usize| visible[p] && truth[p].is_finite() && truth[p].abs() >= 1e-3;
        let n_off = (0..truth.len()).filter(|&p| off(p)).count();
        let known = (0..truth.len())
            .filter(|&p| off(p) && heights.data()[p].is_finite())
            .count();
        known as f64 / n_off.max(1) as f64
    });
    if let Some(dir) = dump {
        let label = format!(
            "{}_{}_{}x{}",
            format!("{preset:?}").to_lowercase(),
            case.kind.name(),
            case.width,
            case.height
        );
        // The error map minus a robust plane (fitted to the errors within a
        // pixel of their median), so that gross errors do not tint the rest.
        let mut sorted_err = err.clone();
        sorted_err.sort_by(f64::total_cmp);
        let med = percentile(&sorted_err, 0.5);
        let (inl_rows, inl_err): (Vec<_>, Vec<f64>) = plane_rows
            .iter()
            .zip(&err)
            .filter(|(_, e)| ((**e - med) / um_per_px).abs() < 1.0)
            .map(|(r, e)| (r.clone(), *e))
            .unzip();
        let rc = fit(&inl_rows, &inl_err).unwrap_or_else(|| vec![med, 0.0, 0.0]);
        let mut err_px = vec![f32::NAN; truth.len()];
        let mut k = 0;
        for (p, e) in err_px.iter_mut().enumerate() {
            if visible[p] && truth[p].is_finite() && heights.data()[p].is_finite() {
                let (x, y) = (rows[k].0, rows[k].1);
                *e = ((err[k] - (rc[0] + rc[1] * x + rc[2] * y)) / um_per_px) as f32;
                k += 1;
            }
        }
        let (lo, hi) = (
            percentile(&sorted_truth, 0.01) as f32,
            percentile(&sorted_truth, 0.99) as f32,
        );
        let plane_at = |p: usize| (c[0] + c[1] * (p % w) as f64 + c[2] * (p / w) as f64) as f32;
        let est_map: Vec<f32> = (0..truth.len())
            .map(|p| heights.data()[p] - plane_at(p))
            .collect();
        match dump_maps(
            dir,
            &label,
            (case.width, case.height),
            &left,
            &truth,
            &est_map,
            &err_px,
            &visible,
            (lo, hi),
        ) {
            Ok(()) => eprintln!(
                "wrote {}/{label}_{{left, truth, height, error}}.png",
                dir.display()
            ),
            Err(e) => tracing::warn!("cannot write the maps of {label}: {e}"),
        }
    }
    Ok(SimFigures {
        case: *case,
        mode: preset,
        rectifier,
        geometry_source: rect.source,
        dense_rows,
        coverage,
        height_range_um,
        rmse_um,
        rmse_relative: rmse_um / height_range_um,
        noise_floor_relative: precision.map(|p| p.height_um / height_range_um),
        median_px,
        over_1px,
        height_scale,
        height_scale_unfiltered,
        unknown: 1.0 - coverage,
        coverage_off_support,
        support,
        sparse_ms,
        dense_ms,
        depth_ms,
        canvas_error_px,
        dense: disp.stats,
    })
}

/// Whether a scene's support is flat and untextured: its heights are what the support test
/// should leave unknown rather than invent.
fn featureless_support(kind: SceneKind) -> bool {
    matches!(kind, SceneKind::Bare | SceneKind::Calgrid)
}

/// Writes `<label>_left.png`, `_truth.png`, `_height.png` (both scaled to the
/// true range `lo..hi`; invisible or unknown black) and `_error.png`
/// (residual in disparity pixels: red positive, blue negative, full at ±1 px;
/// visible but unknown green).
#[allow(clippy::too_many_arguments)]
fn dump_maps(
    dir: &std::path::Path,
    label: &str,
    (w, h): (usize, usize),
    left: &Image,
    truth: &[f32],
    est: &[f32],
    err_px: &[f32],
    visible: &[bool],
    (lo, hi): (f32, f32),
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    #[allow(clippy::cast_possible_truncation)]
    let (wu, hu) = (w as u32, h as u32);
    let grey = |v: &[f32]| -> Vec<u8> {
        v.iter()
            .zip(visible)
            .map(|(&x, &vis)| {
                if vis && x.is_finite() {
                    (((x - lo) / (hi - lo).max(1e-6)).clamp(0.0, 1.0) * 254.0 + 1.0) as u8
                } else {
                    0
                }
            })
            .collect()
    };
    let save_grey = |name: &str, px: Vec<u8>| -> anyhow::Result<()> {
        image::GrayImage::from_raw(wu, hu, px)
            .ok_or_else(|| anyhow::anyhow!("buffer size"))?
            .save(dir.join(format!("{label}_{name}.png")))?;
        Ok(())
    };
    save_grey("left", left.to_u8())?;
    save_grey("truth", grey(truth))?;
    save_grey("height", grey(est))?;
    let mut rgb = Vec::with_capacity(3 * w * h);
    for (&e, &vis) in err_px.iter().zip(visible) {
        let px = if !vis {
            [0, 0, 0]
        } else if !e.is_finite() {
            [0, 160, 0]
        } else {
            let t = e.clamp(-1.0, 1.0);
            let a = (255.0 * (1.0 - t.abs())) as u8;
            if t >= 0.0 { [255, a, a] } else { [a, a, 255] }
        };
        rgb.extend_from_slice(&px);
    }
    image::RgbImage::from_raw(wu, hu, rgb)
        .ok_or_else(|| anyhow::anyhow!("buffer size"))?
        .save(dir.join(format!("{label}_error.png")))?;
    Ok(())
}

/// The targets for one case.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Targets {
    pub coverage: bool,
    pub rmse: bool,
    pub median: bool,
    pub over_1px: bool,
    pub scale: bool,
}

impl Targets {
    /// Coverage ≥ 95 % (off a featureless support where the scene has one:
    /// [`SimFigures::coverage_off_support`]), RMSE ≤ 5 % of the range, median ≤ 0.2 px,
    /// ≤ 3 % above 1 px, height scale within 3 % of 1.
    #[must_use]
    pub fn of(f: &SimFigures) -> Self {
        Self {
            coverage: f.judged_coverage() >= 0.95,
            rmse: f.rmse_relative <= 0.05,
            median: f.median_px <= 0.2,
            over_1px: f.over_1px <= 0.03,
            scale: (f.height_scale - 1.0).abs() <= 0.03,
        }
    }

    #[must_use]
    pub fn all(&self) -> bool {
        self.coverage && self.rmse && self.median && self.over_1px && self.scale
    }
}

/// One line of figures per case, with the targets it misses.
#[must_use]
pub fn format_row(f: &SimFigures) -> String {
    let t = Targets::of(f);
    let mut missed = Vec::new();
    for (ok, name) in [
        (t.coverage, "coverage"),
        (t.rmse, "rmse"),
        (t.median, "median"),
        (t.over_1px, ">1px"),
        (t.scale, "scale"),
    ] {
        if !ok {
            missed.push(name);
        }
    }
    format!(
        "{:<8} {:<9} {:>4}x{:<4} θ {:>4.1}° φ {:>5.1}° | geometry: {} (rows off {:.2} px; dense check {}) | cover {:>5.1} % unknown {:>4.1} %{} | range {:>6.2} µm RMSE {:>5.3} µm ({:>4.1} %, floor {}) | median {:.3} px >1px {:>4.1} % | scale {:.3} (unfiltered {:.3}) | canvas raw {:.3} filtered {:.3} (bias {:+.3}) v {:.3} px{} | rect {:>5.0} ms dense {:>5.0} ms | {}",
        format!("{:?}", f.mode).to_lowercase(),
        f.case.kind.name(),
        f.case.width,
        f.case.height,
        f.case.tilt_deg,
        f.case.tilt_axis_deg,
        f.geometry_source,
        f.canvas_error_px.rows_median,
        f.dense_rows.map_or_else(
            || "—".to_owned(),
            |r| format!(
                "{:.2} px, axis {:+.1}° moving rows {:.2} px",
                r.offset_px, r.axis_error_deg, r.leak_px
            )
        ),
        100.0 * f.coverage,
        100.0 * f.unknown,
        f.support.map_or_else(String::new, |s| format!(
            " (support {:.0} % of view: unknown {:.1} %, reported >1px {:.2} %; off it cover {:.1} %)",
            100.0 * s.share,
            100.0 * s.unknown,
            100.0 * s.reported_over_1px,
            100.0 * f.coverage_off_support.unwrap_or(f.coverage)
        )),
        f.height_range_um,
        f.rmse_um,
        100.0 * f.rmse_relative,
        f.noise_floor_relative
            .map_or_else(|| "—".to_owned(), |r| format!("{:.1} %", 100.0 * r)),
        f.median_px,
        100.0 * f.over_1px,
        f.height_scale,
        f.height_scale_unfiltered,
        f.canvas_error_px.raw_median,
        f.canvas_error_px.filtered_median,
        f.canvas_error_px.filtered_mean,
        f.canvas_error_px.vertical_median,
        f.canvas_error_px.raised.map_or_else(String::new, |r| format!(
            ", tops' relief raw {:.2} of {:.2} px",
            r.measured_px, r.true_px
        )),
        f.sparse_ms,
        f.dense_ms,
        if missed.is_empty() {
            "ok".to_owned()
        } else {
            format!("misses {}", missed.join(", "))
        }
    )
}

/// The cases of the issue: every scene kind, 512×384 to 1280×960, tilts
/// 3–11°, tilt axis horizontal (0°), vertical (90°) and oblique (30°, −60°).
#[must_use]
pub fn standard_cases() -> Vec<SimCase> {
    let mut cases = Vec::new();
    let shapes = [
        (512, 384, 3.0, 0.0),
        (640, 480, 7.0, 90.0),
        (1024, 768, 11.0, 30.0),
        (1280, 960, 5.0, -60.0),
    ];
    for (i, kind) in SceneKind::ALL.into_iter().enumerate() {
        for (j, &(width, height, tilt_deg, tilt_axis_deg)) in shapes.iter().enumerate() {
            cases.push(SimCase {
                kind,
                width,
                height,
                tilt_deg,
                tilt_axis_deg,
                seed: (10 * i + j + 1) as u64,
                noiseless: false,
                dwell_us: DWELL_US,
            });
        }
    }
    cases.extend(hard_cases());
    cases
}

/// The scenes of the failure modes ([`SceneKind::HARD`]): particles on a featureless
/// support (1024×768, 7°), a calibration grid (1280×960, 7°) and a low-contrast rough metal
/// at small size (512×384, 11°).
#[must_use]
pub fn hard_cases() -> Vec<SimCase> {
    [
        (SceneKind::Bare, 1024, 768, 7.0, 90.0),
        (SceneKind::Calgrid, 1280, 960, 7.0, 90.0),
        (SceneKind::Metal, 512, 384, 11.0, 0.0),
    ]
    .into_iter()
    .enumerate()
    .map(
        |(i, (kind, width, height, tilt_deg, tilt_axis_deg))| SimCase {
            kind,
            width,
            height,
            tilt_deg,
            tilt_axis_deg,
            seed: 101 + i as u64,
            noiseless: false,
            dwell_us: DWELL_US,
        },
    )
    .collect()
}

/// The smoke set of `--quick`: every standard scene kind once, at 640×480, θ = 7°,
/// vertical tilt axis, and the failure modes' scenes.
#[must_use]
pub fn quick_cases() -> Vec<SimCase> {
    standard_cases()
        .into_iter()
        .filter(|c| c.width == 640 || SceneKind::HARD.contains(&c.kind))
        .collect()
}

/// What `sdsem-eval dense` was asked for beside the common options.
#[derive(Debug, Clone, Default)]
pub struct DenseEvalArgs {
    /// Use the simulator's exact rectification instead of the sparse stage.
    pub true_rectification: bool,
    /// Use the instrument's geometry instead of the sparse stage (the fallback's figures).
    pub instrument: bool,
    /// Only this mode (default: both).
    pub mode: Option<Preset>,
    /// Only the cases whose label (`kind WxH`, e.g. `dome 640x480`) contains this.
    pub only: Option<String>,
    /// Overrides of the dense parameters, `KEY=VALUE` in TOML syntax, keys
    /// as in `[reconstruction.dense]` (`refine.window_sigma=1.5`).
    pub set: Vec<String>,
    /// Render without scan noise.
    pub noiseless: bool,
    /// Pixel dwell time of the micrographs, µs (default: the standard cases').
    pub dwell_us: Option<f64>,
    /// Write the selected cases' micrographs there instead of evaluating.
    pub write_pairs: Option<std::path::PathBuf>,
    /// Render the selected cases at this size instead (same scene, field and seed).
    pub size: Option<(usize, usize)>,
    /// Write each case's maps there (left micrograph, true and estimated
    /// height, error in disparity pixels) as PNGs.
    pub dump: Option<std::path::PathBuf>,
}

/// Applies `KEY=VALUE` overrides (dotted keys, TOML values) to the dense parameters.
///
/// # Errors
/// An unknown key or a value of the wrong type.
pub fn apply_overrides(params: &DenseParams, set: &[String]) -> anyhow::Result<DenseParams> {
    use anyhow::Context;
    let mut value = toml::Value::try_from(params)?;
    for item in set {
        let (key, raw) = item
            .split_once('=')
            .with_context(|| format!("--set {item}: expected KEY=VALUE"))?;
        let mut parsed: toml::Table = toml::from_str(&format!("v = {raw}"))
            .with_context(|| format!("--set {item}: {raw} is not a TOML value"))?;
        let v = parsed.remove("v").context("--set: no value")?;
        let mut node = &mut value;
        for part in key.trim().split('.') {
            node = node
                .as_table_mut()
                .and_then(|o| o.get_mut(part))
                .with_context(|| format!("--set {item}: no dense parameter `{key}`"))?;
        }
        *node = v;
    }
    value.try_into().context("--set: a value of the wrong type")
}

/// Per mode, how many cases meet each target, and the worst figure.
fn summary(rows: &[SimFigures], mode: Preset) -> Option<String> {
    let rows: Vec<&SimFigures> = rows.iter().filter(|f| f.mode == mode).collect();
    if rows.is_empty() {
        return None;
    }
    let n = rows.len();
    let count =
        |pred: &dyn Fn(&Targets) -> bool| rows.iter().filter(|f| pred(&Targets::of(f))).count();
    let worst = |key: &dyn Fn(&SimFigures) -> f64, max: bool| {
        rows.iter().map(|f| key(f)).fold(
            if max {
                f64::NEG_INFINITY
            } else {
                f64::INFINITY
            },
            |a, b| {
                if max { a.max(b) } else { a.min(b) }
            },
        )
    };
    let worst_scale = rows.iter().map(|f| f.height_scale).fold(1.0f64, |a, b| {
        if (b - 1.0).abs() > (a - 1.0).abs() {
            b
        } else {
            a
        }
    });
    Some(
        format!(
            "{:<8} {n} cases, all targets met by {}: coverage ≥ 95 % (off featureless supports) {}/{n} (worst {:.1} %), RMSE ≤ 5 % {}/{n} (worst {:.1} %), median ≤ 0.2 px {}/{n} (worst {:.3}), >1 px ≤ 3 % {}/{n} (worst {:.1} %), scale 1 ± 3 % {}/{n} (worst {:.3})",
            format!("{mode:?}").to_lowercase(),
            count(&|t| t.all()),
            count(&|t| t.coverage),
            100.0 * worst(&|f| f.judged_coverage(), false),
            count(&|t| t.rmse),
            100.0 * worst(&|f| f.rmse_relative, true),
            count(&|t| t.median),
            worst(&|f| f.median_px, true),
            count(&|t| t.over_1px),
            100.0 * worst(&|f| f.over_1px, true),
            count(&|t| t.scale),
            worst_scale,
        ) + &support_summary(&rows),
    )
}

/// The featureless supports' figures over a mode's rows: the worst fraction of reported
/// heights more than 1 px off [≤ 1 %] and the largest unknown share.
fn support_summary(rows: &[&SimFigures]) -> String {
    let supports: Vec<SupportFigures> = rows.iter().filter_map(|f| f.support).collect();
    if supports.is_empty() {
        return String::new();
    }
    let worst = |key: fn(&SupportFigures) -> f64| supports.iter().map(key).fold(0.0, f64::max);
    format!(
        "; featureless support: reported >1 px ≤ 1 % {}/{} (worst {:.2} %), unknown up to {:.1} %",
        supports
            .iter()
            .filter(|s| s.reported_over_1px <= 0.01)
            .count(),
        supports.len(),
        100.0 * worst(|s| s.reported_over_1px),
        100.0 * worst(|s| s.unknown),
    )
}

/// `sdsem-eval dense`: the simulated scenes in both modes (or one), a line
/// per case and a summary line per mode against the targets.
///
/// # Errors
/// A bad `--set`; a case that fails is reported on its line, not fatal.
pub fn run(opts: &super::EvalOptions, args: &DenseEvalArgs) -> anyhow::Result<()> {
    let sparse = SparseParams::default();
    let cases: Vec<SimCase> = if opts.quick {
        quick_cases()
    } else {
        standard_cases()
    }
    .into_iter()
    .filter(|c| {
        args.only.as_ref().is_none_or(|o| {
            format!("{} {}x{}", c.kind.name(), c.width, c.height).contains(o.as_str())
        })
    })
    .map(|c| SimCase {
        noiseless: args.noiseless,
        dwell_us: args.dwell_us.unwrap_or(DWELL_US),
        width: args.size.map_or(c.width, |s| s.0),
        height: args.size.map_or(c.height, |s| s.1),
        ..c
    })
    .collect();
    if let Some(dir) = &args.write_pairs {
        for case in &cases {
            let [l, r] = write_case(case, dir)?;
            println!(
                "{} {} (θ {}°, φ {}°)",
                l.display(),
                r.display(),
                case.tilt_deg,
                case.tilt_axis_deg
            );
        }
        return Ok(());
    }
    let modes: Vec<Preset> = args
        .mode
        .map_or(vec![Preset::Improved, Preset::Paper], |m| vec![m]);
    let rectifier = if args.true_rectification {
        Rectifier::Truth
    } else if args.instrument {
        Rectifier::Instrument
    } else {
        Rectifier::Sparse
    };
    let mut rows = Vec::new();
    let mut failures = Vec::new();
    for case in &cases {
        for &mode in &modes {
            let dense = apply_overrides(&DenseParams::preset(mode), &args.set)?;
            match evaluate_case(case, mode, &sparse, &dense, rectifier, args.dump.as_deref()) {
                Ok(f) => {
                    if !opts.json {
                        println!("{}", format_row(&f));
                    }
                    rows.push(f);
                }
                Err(e) => {
                    let what =
                        if matches!(e, SimEvalError::Rectify(_) | SimEvalError::Unverified(_)) {
                            "REFUSED (no rectification)"
                        } else {
                            "FAILED"
                        };
                    let line = format!(
                        "{:<8} {:<9} {:>4}x{:<4} θ {:>4.1}° φ {:>5.1}° | {what}: {e}",
                        format!("{mode:?}").to_lowercase(),
                        case.kind.name(),
                        case.width,
                        case.height,
                        case.tilt_deg,
                        case.tilt_axis_deg
                    );
                    if !opts.json {
                        println!("{line}");
                    }
                    failures.push(serde_json::json!({
                        "case": case, "mode": mode, "error": e.to_string(),
                        "refused_by_rectification": matches!(e, SimEvalError::Rectify(_) | SimEvalError::Unverified(_)),
                    }));
                }
            }
        }
    }
    if opts.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "rectifier": rectifier,
                "cases": rows,
                "failures": failures,
            }))?
        );
    } else {
        println!(
            "rectification: {}; targets: coverage ≥ 95 % (off a featureless support), RMSE ≤ 5 % of range, median ≤ 0.2 px, >1 px ≤ 3 %, scale 1 ± 3 %",
            match rectifier {
                Rectifier::Sparse => "sparse stage (whole pipeline)",
                Rectifier::Truth => "exact, from the simulator's geometry (dense stage alone)",
                Rectifier::Instrument =>
                    "the instrument's (tilt axis and tiles, no sparse matches), checked by the dense stage",
            }
        );
        for &mode in &modes {
            if let Some(line) = summary(&rows, mode) {
                println!("{line}");
            }
        }
        if !failures.is_empty() {
            println!(
                "{} case(s) without a map (refused or failed, see above)",
                failures.len()
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_rectification_turns_the_parallax_direction_to_x() {
        for phi in [0.0f64, 90.0, 30.0, -60.0] {
            let (hm, (cw, ch)) = exact_rectification(64, 48, phi);
            let n = (-phi.to_radians().sin(), phi.to_radians().cos());
            let map = |x: f64, y: f64| {
                let q = hm * nalgebra::Vector3::new(x, y, 1.0);
                (q.x / q.z, q.y / q.z)
            };
            let (a, b) = (map(10.0, 10.0), map(10.0 + n.0, 10.0 + n.1));
            assert!(
                (b.0 - a.0 - 1.0).abs() < 1e-12 && (b.1 - a.1).abs() < 1e-12,
                "φ {phi}"
            );
            assert!(hm.determinant() > 0.0, "no mirror");
            // Every corner lands on the canvas.
            for (x, y) in [(0.0, 0.0), (63.0, 0.0), (0.0, 47.0), (63.0, 47.0)] {
                let (u, v) = map(x, y);
                assert!(
                    u > -1e-9 && v > -1e-9 && u < cw as f64 && v < ch as f64,
                    "φ {phi}: {u} {v}"
                );
            }
        }
        assert_eq!(exact_rectification(64, 48, 90.0).1, (64, 48));
        assert_eq!(exact_rectification(64, 48, 0.0).1, (48, 64));
    }

    #[test]
    fn overrides_reach_nested_keys_and_refuse_unknown_ones() {
        let p = apply_overrides(
            &DenseParams::default(),
            &["refine.window_sigma=1.25".to_owned(), "levels=3".to_owned()],
        )
        .unwrap();
        assert_eq!(p.flow.refine.window_sigma, 1.25);
        assert_eq!(p.flow.levels, 3);
        assert!(apply_overrides(&DenseParams::default(), &["nope=1".to_owned()]).is_err());
        assert!(apply_overrides(&DenseParams::default(), &["levels=\"x\"".to_owned()]).is_err());
    }

    /// The whole table (both modes). Long: about a minute per case on two cores.
    /// `cargo test -p sdsem-eval --release dense::tests::simulated_scenes -- --ignored --nocapture`
    /// (`SDSEM_CASES=n` runs the first n cases only).
    #[test]
    #[ignore = "renders and reconstructs simulated scenes; prints figures"]
    fn simulated_scenes() {
        let limit = std::env::var("SDSEM_CASES")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(usize::MAX);
        let sparse = SparseParams::default();
        for case in standard_cases().into_iter().take(limit) {
            for mode in [Preset::Improved, Preset::Paper] {
                let dense = DenseParams::preset(mode);
                match evaluate_case(&case, mode, &sparse, &dense, Rectifier::Sparse, None) {
                    Ok(f) => println!("{}", format_row(&f)),
                    Err(e) => println!(
                        "{mode:<8?} {:?} {}x{}: {e}",
                        case.kind, case.width, case.height
                    ),
                }
            }
        }
    }

    #[test]
    fn least_squares_recovers_a_plane_and_a_scale() {
        let rows: Vec<(f64, f64, Vec<f64>)> = (0..30)
            .map(|i| ((i % 6) as f64, (i / 6) as f64, vec![(i * 7 % 11) as f64]))
            .collect();
        let target: Vec<f64> = rows
            .iter()
            .map(|(x, y, t)| 1.0 + 0.5 * x - 2.0 * y + 0.97 * t[0])
            .collect();
        let c = fit(&rows, &target).unwrap();
        assert!((c[3] - 0.97).abs() < 1e-9 && (c[2] + 2.0).abs() < 1e-9);
    }
}
