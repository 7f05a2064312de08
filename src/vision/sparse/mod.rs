//! The sparse stage of SD-SEM (Baghaie et al., Micron 97, 2017, §2.1 and Table 2) as one
//! call: SIFT in both micrographs → ratio-test matching → ORSA fundamental matrix →
//! quasi-Euclidean rectification → (optionally) both images warped onto one canvas.
//!
//! # Beyond the paper (the paper preset, [`SparseParams::preset`], turns the first three off)
//! - Half Lowe's DoG threshold (capped at 2000 keypoints): more true matches on weakly textured
//!   and repetitive specimens.
//! - The ORSA inliers' right positions refined to sub-pixel accuracy ([`refine`]) before the
//!   rectification, unconfirmed ones left out: SIFT's localisation noise was most of the
//!   rectification error.
//! - A robust first pass of the rectification ([`RectifyParams::cauchy_scale_px`]) that leaves
//!   out wrong matches sliding along their epipolar lines.
//! - With the tilt axis known, ORSA never scores a model whose epipolar lines cross the
//!   tilt-axis normal by more than [`RectifyParams::max_tilt_axis_mismatch_deg`]: on repetitive
//!   or nearly flat specimens a consistent set of wrong matches can otherwise win.
//!
//! # What the dense stage gets
//! [`SparseResult::rectification`] holds `H_left` and `H_right`, mapping ORIGINAL left/right
//! pixel coordinates to one rectified canvas of size `canvas` on which corresponding points
//! share their `y`. Both warps are proper (no mirror) and keep the images upright to within the
//! in-plane rotation that makes epipolar lines horizontal.
//!
//! # Disparity sign (DESIGN §3)
//! With the tilt axis φ known, the start of the rectification turns the tilt-axis normal
//! `n = (−sin φ, cos φ)` to +x on the canvas, and [`SparseResult::n_rectified`] reports where
//! it actually went (`x` component ≈ +1). Then, for rectified disparity `d = x_right − x_left`,
//! a surface point higher towards the beam has a larger `d`: `h = (d − d₀)·p / (2 sin(θ/2))`
//! (eq. 19) up to the global plane `d₀`. Without φ the sign of the relief is unknown
//! (`n_rectified` is `None`): the in-plane rotation is then the smallest that makes the epipolar
//! lines rows, and `d` grows with height if and only if `n` points to +x on that canvas.

use std::time::Instant;

use nalgebra::{Matrix3, Vector2};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::rectify::instrument::InstrumentParams;
use crate::vision::rectify::warp::{Warped, warp};
use crate::vision::rectify::{
    ROW_UNCERTAINTY, Rectification, RectifyError, RectifyParams, epipolar_direction, rectify,
};
use crate::vision::sparse::fundamental::FundamentalModel;
use crate::vision::sparse::matching::{MatchParams, match_keypoints};
use crate::vision::sparse::orsa::{ModelFilter, OrsaError, OrsaParams, orsa_filtered};
use crate::vision::sparse::sift::{Keypoint, SiftParams, SiftParamsError, sift};

pub mod fundamental;
pub mod matching;
pub mod orsa;
pub mod refine;
pub mod sift;
pub use refine::RefineParams;

/// Parameters of the sparse stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SparseParams {
    pub sift: SiftParams,
    pub matching: MatchParams,
    pub orsa: OrsaParams,
    pub rectify: RectifyParams,
    /// Sub-pixel refinement of the inliers' right positions before the rectification (beyond
    /// the paper; `refine.enabled = false` is the paper's path).
    pub refine: RefineParams,
    /// Fewest ORSA inliers accepted (default 8: the paper's "eight are enough" — the
    /// rectification has six unknowns). Fewer → [`SparseError::TooFewMatches`].
    pub min_inliers: usize,
    /// When the projective model (the paper's) is refused, try the affine one before giving up
    /// (default true). The result names the model used and why the first was refused.
    pub fallback_to_affine: bool,
    /// SIFT runs on a copy of each micrograph halved until it has at most this many megapixels,
    /// the keypoints scaled back (bounds its memory, ~120 bytes a pixel, on large micrographs);
    /// 0 = full resolution always.
    pub sift_max_megapixels: f64,
    /// When the matches are too few for an epipolar geometry, SIFT both micrographs again for a
    /// feature-poor pair ([`feature_poor_sift`]: the DoG threshold scaled to each micrograph's
    /// contrast, an upsampled first octave) and try once more (default true; beyond the paper).
    pub second_attempt: bool,
    /// When the epipolar geometry cannot be established (or is implausible), rectify from the
    /// tilt axis and the pair's correlation instead (the reconstruction's fallback, beyond the
    /// paper; [`crate::vision::rectify::instrument`]).
    pub instrument: InstrumentParams,
}

impl Default for SparseParams {
    fn default() -> Self {
        Self {
            // IPOL's scale space without its first, upsampled octave (VLFeat's first_octave 0):
            // the same blur per octave from σ = 1.6 on, four times less work, and on SEM images
            // the same rectification accuracy; half Lowe's DoG threshold, which on weakly
            // textured or repetitive specimens (the simulator's grid) finds three to four times
            // the true matches; and at most the 2000 keypoints of highest contrast, which bounds
            // the matching time on textured ones (where the threshold then changes nothing).
            sift: SiftParams {
                delta_min: 1.0,
                sigma_min: 1.6,
                c_dog: 0.02 / 3.0,
                max_keypoints: 2000,
                ..SiftParams::default()
            },
            matching: MatchParams::default(),
            orsa: OrsaParams::default(),
            rectify: RectifyParams::default(),
            refine: RefineParams::default(),
            min_inliers: 8,
            fallback_to_affine: true,
            sift_max_megapixels: 4.0,
            second_attempt: true,
            instrument: InstrumentParams::default(),
        }
    }
}

impl SparseParams {
    /// The parameters of a preset. The paper's path (Baghaie et al. 2017 with Monasse's
    /// rectification): Lowe's DoG threshold, SIFT positions straight into the rectification
    /// (no sub-pixel refinement), least squares only (no robust pass); the rest as improved.
    #[must_use]
    pub fn preset(preset: crate::vision::Preset) -> Self {
        let mut p = Self::default();
        if preset == crate::vision::Preset::Paper {
            p.sift.c_dog = 0.04 / 3.0;
            p.refine.enabled = false;
            p.rectify.cauchy_scale_px = 0.0;
        }
        p
    }
}

/// Smallest image side the sparse stage accepts (SIFT needs a few octaves).
pub const MIN_SIDE: usize = 32;

/// Which micrograph of the pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Side {
    Left,
    Right,
}

impl std::fmt::Display for Side {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::Left => "left",
            Self::Right => "right",
        })
    }
}

/// Why the sparse stage refuses the pair. Every refusal is preferred to a wrong warp.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SparseError {
    #[error("images differ in size: {}×{} vs {}×{}: left and right must come from the same scan", left.0, left.1, right.0, right.1)]
    SizeMismatch {
        left: (usize, usize),
        right: (usize, usize),
    },
    #[error("{side} image is too small: {}×{}, need at least {min}×{min} pixels", size.0, size.1)]
    ImageTooSmall {
        side: Side,
        size: (usize, usize),
        min: usize,
    },
    #[error(
        "{side} image has no texture: {keypoints} keypoints (need {need}); is it blank or out of focus?"
    )]
    NoTexture {
        side: Side,
        keypoints: usize,
        need: usize,
    },
    #[error("not enough reliable matches: found {found}, need {need} ({stage})")]
    TooFewMatches {
        found: usize,
        need: usize,
        stage: &'static str,
    },
    #[error(
        "no meaningful epipolar geometry: best log10 NFA = {log10_nfa:.1} (must be < 0) with {inliers} of {matches} matches; the images may not show the same area"
    )]
    NotMeaningful {
        log10_nfa: f64,
        inliers: usize,
        matches: usize,
    },
    #[error(transparent)]
    Rectify(#[from] RectifyError),
    #[error(transparent)]
    Params(#[from] SiftParamsError),
}

impl SparseError {
    /// Whether the refusal is for too little evidence (too few keypoints, matches or inliers,
    /// no meaningful model, uncertain rows), which more keypoints can remedy; a geometry that
    /// contradicts its own matches or the tilt axis is not, and is refused as it is.
    #[must_use]
    pub fn is_lack_of_evidence(&self) -> bool {
        match self {
            Self::NoTexture { .. } | Self::TooFewMatches { .. } | Self::NotMeaningful { .. } => {
                true
            }
            Self::Rectify(RectifyError::TooFewMatches { .. }) => true,
            Self::Rectify(RectifyError::Implausible { what, .. }) => *what == ROW_UNCERTAINTY,
            Self::SizeMismatch { .. }
            | Self::ImageTooSmall { .. }
            | Self::Rectify(_)
            | Self::Params(_) => false,
        }
    }
}

/// One correspondence in original pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Correspondence {
    pub left: [f64; 2],
    pub right: [f64; 2],
}

/// Wall-clock time of each step, milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    /// Both images' SIFT, run concurrently.
    pub sift_ms: f64,
    pub sift_left_ms: f64,
    pub sift_right_ms: f64,
    pub matching_ms: f64,
    pub orsa_ms: f64,
    /// Sub-pixel refinement of the inliers (0 when off).
    pub refine_ms: f64,
    pub rectify_ms: f64,
    /// Warping both images (0 when not warped).
    pub warp_ms: f64,
    /// Everything above.
    pub total_ms: f64,
}

/// The sparse stage's result.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseResult {
    pub image_size: (usize, usize),
    pub keypoints_left: usize,
    pub keypoints_right: usize,
    /// Putative matches (ratio test and symmetric check), each pair of positions once,
    /// original pixels.
    pub matches: Vec<Correspondence>,
    /// ORSA inliers that the rectification kept (all but
    /// `rectification.outliers`), original pixels: the left positions as SIFT found them, the
    /// right ones refined where [`SparseResult::refined`] counts them.
    pub inliers: Vec<Correspondence>,
    /// Inliers whose right position the sub-pixel refinement moved (0 when it is off).
    pub refined: usize,
    /// ORSA's inlier count (the paper's Table 2 figure); `inliers` holds those of them the
    /// refinement confirmed (when on) and the rectification kept.
    pub orsa_inliers: usize,
    /// The model that gave the result (the requested one, or affine after a fallback).
    pub model: FundamentalModel,
    /// Why the requested projective model was abandoned for the affine one, if it was.
    pub fallback_reason: Option<String>,
    /// Why the first SIFT found too little and what the second attempt changed, when the
    /// geometry comes from the second attempt ([`SparseParams::second_attempt`]).
    pub second_attempt: Option<String>,
    /// The ORSA fundamental matrix, `x_rightᵀ F x_left = 0`.
    pub f: Matrix3<f64>,
    pub log10_nfa: f64,
    /// ORSA's automatic inlier threshold (symmetric epipolar distance), pixels.
    pub threshold_px: f64,
    pub orsa_iterations: usize,
    /// Homographies, canvas, errors; see the module docs for the disparity sign.
    pub rectification: Rectification,
    /// The tilt-axis normal's direction on the canvas, when φ was given.
    pub n_rectified: Option<[f64; 2]>,
    pub timings: Timings,
}

/// The sparse stage with both images warped onto the canvas.
#[derive(Debug, Clone, PartialEq)]
pub struct RectifiedPair {
    pub sparse: SparseResult,
    pub left: Warped,
    pub right: Warped,
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Runs SIFT → matching → ORSA → rectification on a stereo pair (samples in `[0, 1]`, left =
/// lower tilt). `tilt_axis_deg` is DESIGN §3's φ when known; it orients the canvas.
///
/// # Errors
/// [`SparseError`] naming the cause: different sizes, tiny or blank images, too few matches or
/// inliers, no meaningful model (log10 NFA ≥ 0), or a rectification that fails its checks.
pub fn sparse_stage(
    left: &Image,
    right: &Image,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> Result<SparseResult, SparseError> {
    sparse_attempts(left, right, tilt_axis_deg, params)?.1
}

/// [`sparse_matches`] then [`sparse_geometry`]; when the geometry is refused for lack of
/// evidence ([`SparseError::is_lack_of_evidence`]) and [`SparseParams::second_attempt`] is on,
/// both again with [`feature_poor_sift`]. The matches
/// returned are those of the attempt that gave the geometry, else the more numerous ones (for
/// a fallback), with the first attempt's refusal.
///
/// # Errors
/// The outer error for a pair refused before any matching (sizes, parameters).
pub fn sparse_attempts(
    left: &Image,
    right: &Image,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> Result<(SparseMatches, Result<SparseResult, SparseError>), SparseError> {
    let first = sparse_matches(left, right, params)?;
    let refused = match sparse_geometry(left, right, &first, tilt_axis_deg, params) {
        Ok(s) => return Ok((first, Ok(s))),
        Err(e) if !params.second_attempt || !e.is_lack_of_evidence() => {
            return Ok((first, Err(e)));
        }
        Err(e) => e,
    };
    let sift = [left, right].map(|img| feature_poor_sift(&params.sift, img));
    let second = sparse_matches_with(left, right, params, &sift)?;
    match sparse_geometry(left, right, &second, tilt_axis_deg, params) {
        Ok(mut s) => {
            s.second_attempt = Some(format!(
                "{refused}; SIFT again with the DoG threshold at {:.2e} / {:.2e} (scaled to each \
                 micrograph's contrast) and an upsampled first octave: {} / {} keypoints, {} matches",
                sift[0].c_dog,
                sift[1].c_dog,
                second.keypoints_left,
                second.keypoints_right,
                second.putative
            ));
            s.timings.total_ms = ms(first.started);
            Ok((second, Ok(s)))
        }
        Err(_) if second.putative > first.putative => Ok((second, Err(refused))),
        Err(_) => Ok((first, Err(refused))),
    }
}

/// The percentile interval over which a micrograph's contrast is measured for
/// [`feature_poor_sift`]: robust to a few saturated or dead pixels.
const CONTRAST_PERCENTILES: (f64, f64) = (0.005, 0.995);

/// SIFT parameters for the second attempt on a feature-poor micrograph: Lowe's threshold is for
/// an image spanning `[0, 1]`, so it is scaled by the micrograph's contrast (its 0.5–99.5
/// percentile range, at most 1), and the first octave is upsampled ×2 (`δ_min` 0.5, `σ_min`
/// 0.8: IPOL's defaults), which finds the small-scale keypoints of fine texture.
#[must_use]
pub fn feature_poor_sift(sift: &SiftParams, image: &Image) -> SiftParams {
    let contrast = percentile_range(image, CONTRAST_PERCENTILES).clamp(0.01, 1.0);
    SiftParams {
        c_dog: sift.c_dog * contrast,
        delta_min: sift.delta_min.min(0.5),
        sigma_min: sift.sigma_min.min(0.8),
        ..sift.clone()
    }
}

/// The difference of two percentiles of the finite samples of `img`, from a 4096-bin
/// histogram of `[0, 1]`; 1 when it has none.
fn percentile_range(img: &Image, (lo, hi): (f64, f64)) -> f64 {
    const BINS: usize = 4096;
    let mut hist = vec![0usize; BINS];
    let mut n = 0usize;
    for &v in img.data().iter().filter(|v| v.is_finite()) {
        // Samples are in [0, 1]: a bin index.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let b = ((v.clamp(0.0, 1.0) * BINS as f32) as usize).min(BINS - 1);
        hist[b] += 1;
        n += 1;
    }
    if n == 0 {
        return 1.0;
    }
    let at = |q: f64| {
        // A rank among n samples.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let rank = ((q * n as f64) as usize).min(n - 1);
        let mut seen = 0;
        for (b, &c) in hist.iter().enumerate() {
            seen += c;
            if seen > rank {
                return (b as f64 + 0.5) / BINS as f64;
            }
        }
        1.0
    };
    at(hi) - at(lo)
}

/// SIFT in both micrographs and their distinct putative matches: what the epipolar geometry is
/// estimated from ([`sparse_geometry`]), and what a fallback can still use when it cannot be.
#[derive(Debug, Clone, PartialEq)]
pub struct SparseMatches {
    pub keypoints_left: usize,
    pub keypoints_right: usize,
    /// Putative matches before the distinct positions were taken (`descriptor matching`).
    pub putative: usize,
    left: Vec<Vector2<f64>>,
    right: Vec<Vector2<f64>>,
    sigmas: Vec<f64>,
    /// SIFT and matching so far; `total_ms` counts from the start of the stage.
    pub timings: Timings,
    started: Instant,
}

impl SparseMatches {
    /// The distinct putative matches, original pixels (unverified: many may be wrong).
    #[must_use]
    pub fn correspondences(&self) -> Vec<Correspondence> {
        self.left
            .iter()
            .zip(&self.right)
            .map(|(a, b)| Correspondence {
                left: [a.x, a.y],
                right: [b.x, b.y],
            })
            .collect()
    }
}

/// The first half of [`sparse_stage`]: checks of the pair and the parameters, SIFT in both
/// micrographs, ratio-test matching and the distinct positions.
///
/// # Errors
/// [`SparseError`] for different sizes, tiny images or invalid parameters.
pub fn sparse_matches(
    left: &Image,
    right: &Image,
    params: &SparseParams,
) -> Result<SparseMatches, SparseError> {
    sparse_matches_with(
        left,
        right,
        params,
        &[params.sift.clone(), params.sift.clone()],
    )
}

/// [`sparse_matches`] with SIFT parameters per micrograph (left, right).
fn sparse_matches_with(
    left: &Image,
    right: &Image,
    params: &SparseParams,
    sift: &[SiftParams; 2],
) -> Result<SparseMatches, SparseError> {
    let t_total = Instant::now();
    if left.dimensions() != right.dimensions() {
        return Err(SparseError::SizeMismatch {
            left: left.dimensions(),
            right: right.dimensions(),
        });
    }
    for (side, img) in [(Side::Left, left), (Side::Right, right)] {
        if img.width() < MIN_SIDE || img.height() < MIN_SIDE {
            return Err(SparseError::ImageTooSmall {
                side,
                size: img.dimensions(),
                min: MIN_SIDE,
            });
        }
    }
    for p in sift {
        p.validate()?;
    }
    if !(params.sift_max_megapixels >= 0.0 && params.sift_max_megapixels.is_finite()) {
        return Err(SiftParamsError::OutOfRange {
            name: "sift_max_megapixels",
            value: params.sift_max_megapixels,
            expected: "finite and non-negative",
        }
        .into());
    }

    let t = Instant::now();
    let ((kl, tl), (kr, tr)) = rayon::join(
        || {
            let t = Instant::now();
            (
                sift_bounded(left, &sift[0], params.sift_max_megapixels),
                ms(t),
            )
        },
        || {
            let t = Instant::now();
            (
                sift_bounded(right, &sift[1], params.sift_max_megapixels),
                ms(t),
            )
        },
    );
    let (kl, kr) = (kl?, kr?);
    let mut timings = Timings {
        sift_ms: ms(t),
        sift_left_ms: tl,
        sift_right_ms: tr,
        ..Timings::default()
    };
    let t = Instant::now();
    let matches = match_keypoints(&kl, &kr, &params.matching);
    timings.matching_ms = ms(t);
    let (pl, pr, sigmas) = distinct_positions(&kl, &kr, &matches);
    Ok(SparseMatches {
        keypoints_left: kl.len(),
        keypoints_right: kr.len(),
        putative: matches.len(),
        left: pl,
        right: pr,
        sigmas,
        timings,
        started: t_total,
    })
}

/// The second half of [`sparse_stage`]: ORSA on the matches, the refinement of its inliers and
/// their rectification.
///
/// # Errors
/// [`SparseError`] for blank images, too few matches or inliers, no meaningful model, or a
/// rectification that fails its checks.
pub fn sparse_geometry(
    left: &Image,
    right: &Image,
    m: &SparseMatches,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> Result<SparseResult, SparseError> {
    let need = params.min_inliers.max(params.orsa.model.sample_size() + 1);
    let mut timings = m.timings;
    for (side, k) in [
        (Side::Left, m.keypoints_left),
        (Side::Right, m.keypoints_right),
    ] {
        if k < need {
            return Err(SparseError::NoTexture {
                side,
                keypoints: k,
                need,
            });
        }
    }
    if m.putative < need {
        return Err(SparseError::TooFewMatches {
            found: m.putative,
            need,
            stage: "descriptor matching",
        });
    }
    let (pl, pr, sigmas) = (&m.left, &m.right, &m.sigmas);
    if pl.len() < need {
        return Err(SparseError::TooFewMatches {
            found: pl.len(),
            need,
            stage: "distinct matches",
        });
    }

    let size = left.dimensions();
    let matched = Matched {
        left: pl,
        right: pr,
        sigmas,
    };
    let mut stage = Stage {
        images: (left, right),
        prepared: None,
        size,
        tilt_axis_deg,
        params,
        need,
        timings: &mut timings,
    };
    let mut model = params.orsa.model;
    let mut geometry = stage.epipolar_geometry(&matched, model);
    let mut fallback_reason = None;
    if params.fallback_to_affine
        && model == FundamentalModel::Projective
        && let Err(e) = &geometry
    {
        // SEM is a parallel projection: the affine model is exact and has fewer ways to go
        // wrong on flat or weakly tilted specimens.
        fallback_reason = Some(e.to_string());
        model = FundamentalModel::Affine;
        geometry = stage.epipolar_geometry(&matched, model);
    }
    let g = geometry?;
    timings.total_ms = ms(m.started);

    let corr = |a: &Vector2<f64>, b: &Vector2<f64>| Correspondence {
        left: [a.x, a.y],
        right: [b.x, b.y],
    };
    Ok(SparseResult {
        image_size: size,
        keypoints_left: m.keypoints_left,
        keypoints_right: m.keypoints_right,
        matches: pl.iter().zip(pr).map(|(a, b)| corr(a, b)).collect(),
        inliers: g
            .left
            .iter()
            .zip(&g.right)
            .map(|(a, b)| corr(a, b))
            .collect(),
        refined: g.refined,
        orsa_inliers: g.orsa.inliers.len(),
        model,
        fallback_reason,
        second_attempt: None,
        f: g.orsa.f,
        log10_nfa: g.orsa.log10_nfa,
        threshold_px: g.orsa.threshold_px,
        orsa_iterations: g.orsa.iterations,
        n_rectified: g.rectification.n_rectified,
        rectification: g.rectification,
        timings,
    })
}

/// The distinct putative matches: positions and the left keypoints' scales.
struct Matched<'a> {
    left: &'a [Vector2<f64>],
    right: &'a [Vector2<f64>],
    sigmas: &'a [f64],
}

/// What the model-dependent steps share.
struct Stage<'a> {
    images: (&'a Image, &'a Image),
    /// Blurred images for the refinement, made on first use.
    prepared: Option<refine::Prepared>,
    size: (usize, usize),
    tilt_axis_deg: Option<f64>,
    params: &'a SparseParams,
    need: usize,
    timings: &'a mut Timings,
}

/// ORSA's model, its inliers (right positions refined) and their rectification.
struct Geometry {
    orsa: crate::vision::sparse::orsa::OrsaResult,
    left: Vec<Vector2<f64>>,
    right: Vec<Vector2<f64>>,
    refined: usize,
    rectification: Rectification,
}

impl Stage<'_> {
    /// ORSA with `model`, the refinement of its inliers, then their rectification.
    fn epipolar_geometry(
        &mut self,
        m: &Matched<'_>,
        model: FundamentalModel,
    ) -> Result<Geometry, SparseError> {
        let params = self.params;
        let t = Instant::now();
        let orsa_params = OrsaParams {
            model,
            ..params.orsa.clone()
        };
        // With the tilt axis known, the parallax runs along its normal n in both images (up to
        // the small scan rotation between shots): models whose epipolar lines cross n at more
        // than the rectification's own limit are ruled out before they are scored.
        let centre = Vector2::new(
            (self.size.0 as f64 - 1.0) / 2.0,
            (self.size.1 as f64 - 1.0) / 2.0,
        );
        let max_cos = params.rectify.max_tilt_axis_mismatch_deg.to_radians().cos();
        let normal = self.tilt_axis_deg.map(|phi| {
            let p = phi.to_radians();
            Vector2::new(-p.sin(), p.cos())
        });
        let along_n = |f: &Matrix3<f64>| {
            normal.is_none_or(|n| {
                [*f, f.transpose()].iter().all(|g| {
                    epipolar_direction(g, centre).is_some_and(|d| d.dot(&n).abs() >= max_cos)
                })
            })
        };
        let filter: Option<ModelFilter<'_>> = normal.map(|_| &along_n as ModelFilter<'_>);
        let found = orsa_filtered(
            m.left,
            m.right,
            [self.size, self.size],
            &orsa_params,
            filter,
        );
        self.timings.orsa_ms += ms(t);
        let found = match found {
            Ok(f) => f,
            Err(OrsaError::TooFewMatches { found, need }) => {
                return Err(SparseError::TooFewMatches {
                    found,
                    need: need + 1,
                    stage: "ORSA",
                });
            }
            Err(OrsaError::NotMeaningful {
                best_log10_nfa,
                inliers,
            }) => {
                return Err(SparseError::NotMeaningful {
                    log10_nfa: best_log10_nfa,
                    inliers,
                    matches: m.left.len(),
                });
            }
        };
        if found.inliers.len() < self.need {
            return Err(SparseError::TooFewMatches {
                found: found.inliers.len(),
                need: self.need,
                stage: "ORSA inliers",
            });
        }
        let il: Vec<Vector2<f64>> = found.inliers.iter().map(|&i| m.left[i]).collect();
        let mut ir: Vec<Vector2<f64>> = found.inliers.iter().map(|&i| m.right[i]).collect();
        let mut il = il;
        let mut refined = 0;
        if params.refine.enabled {
            let t = Instant::now();
            if let Some(a) = refine::robust_linear_map(&il, &ir) {
                let (l, r) = self.images;
                let prepared = self
                    .prepared
                    .get_or_insert_with(|| refine::Prepared::new(l, r, &params.refine));
                let seeds: Vec<refine::Seed> = found
                    .inliers
                    .iter()
                    .map(|&i| refine::Seed {
                        left: m.left[i],
                        sigma: m.sigmas[i],
                        right: m.right[i],
                    })
                    .collect();
                let out = refine::refine_matches(prepared, &seeds, &a, &params.refine);
                refined = out.iter().flatten().count();
                // A match the registration cannot confirm is at best as SIFT placed it, and
                // often a wrong one within ORSA's threshold: leave it out when enough remain.
                let drop = params.refine.drop_unconfirmed && refined >= self.need;
                let (mut kl, mut kr) = (Vec::with_capacity(il.len()), Vec::with_capacity(il.len()));
                for ((p, q), o) in il.iter().zip(&ir).zip(&out) {
                    match o {
                        Some(o) => {
                            kl.push(*p);
                            kr.push(*o);
                        }
                        None if !drop => {
                            kl.push(*p);
                            kr.push(*q);
                        }
                        None => {}
                    }
                }
                il = kl;
                ir = kr;
            }
            self.timings.refine_ms += ms(t);
        }
        let t = Instant::now();
        let rectification = rectify(
            &il,
            &ir,
            &found.f,
            self.size,
            self.tilt_axis_deg,
            &params.rectify,
        );
        self.timings.rectify_ms += ms(t);
        let rectification = rectification?;
        // The matches the rectification left out (sliding along their epipolar lines) are no
        // inliers of the result.
        let keep = |i: &usize| rectification.outliers.binary_search(i).is_err();
        let il = (0..il.len()).filter(keep).map(|i| il[i]).collect();
        let ir = (0..ir.len()).filter(keep).map(|i| ir[i]).collect();
        Ok(Geometry {
            orsa: found,
            left: il,
            right: ir,
            refined,
            rectification,
        })
    }
}

/// The matched positions, each pair of positions once, with the left keypoint's scale: a
/// keypoint with several orientations appears once per orientation, and its matches would
/// otherwise count several times in ORSA (inflating the NFA's evidence) and can make minimal
/// samples degenerate.
fn distinct_positions(
    kl: &[crate::vision::sparse::sift::Keypoint],
    kr: &[crate::vision::sparse::sift::Keypoint],
    matches: &[crate::vision::sparse::matching::Match],
) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>, Vec<f64>) {
    let mut seen = std::collections::HashSet::new();
    let (mut pl, mut pr, mut sigmas) = (Vec::new(), Vec::new(), Vec::new());
    for m in matches {
        let (a, b) = (&kl[m.left], &kr[m.right]);
        if seen.insert([a.x.to_bits(), a.y.to_bits(), b.x.to_bits(), b.y.to_bits()]) {
            pl.push(Vector2::new(a.x, a.y));
            pr.push(Vector2::new(b.x, b.y));
            sigmas.push(a.sigma);
        }
    }
    (pl, pr, sigmas)
}

/// SIFT of `image` on a copy halved (2×2 means) until it has at most `sift_max_megapixels`: the
/// keypoints' positions and scales in `image`'s pixels. The sub-pixel refinement of the inliers
/// and the rectification then work on the full-resolution positions.
fn sift_bounded(
    image: &Image,
    params: &SiftParams,
    max_megapixels: f64,
) -> Result<Vec<Keypoint>, SiftParamsError> {
    // A count of pixels: a few million.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let limit = (max_megapixels * 1e6) as usize;
    if limit == 0 || image.len() <= limit {
        return sift(image, params);
    }
    let mut small = halve(image);
    let mut k = 2.0;
    while small.len() > limit && small.width().min(small.height()) >= 4 * MIN_SIDE {
        small = halve(&small);
        k *= 2.0;
    }
    let mut keypoints = sift(&small, params)?;
    // Pixel i of the copy averages pixels k·i … k·i + k − 1: its centre is k·i + (k − 1)/2.
    let offset = (k - 1.0) / 2.0;
    for kp in &mut keypoints {
        kp.x = kp.x * k + offset;
        kp.y = kp.y * k + offset;
        kp.sigma *= k;
    }
    Ok(keypoints)
}

/// The image at half the resolution: means of 2×2 blocks (the last row or column alone when odd).
pub(crate) fn halve(img: &Image) -> Image {
    let (w, h) = img.dimensions();
    let (hw, hh) = (w.div_ceil(2), h.div_ceil(2));
    let mut out = Image::zeros(hw, hh);
    out.data_mut()
        .par_chunks_mut(hw)
        .enumerate()
        .for_each(|(y, row)| {
            let (y0, y1) = (2 * y, (2 * y + 1).min(h - 1));
            for (x, o) in row.iter_mut().enumerate() {
                let (x0, x1) = (2 * x, (2 * x + 1).min(w - 1));
                *o = 0.25 * (img.get(x0, y0) + img.get(x1, y0) + img.get(x0, y1) + img.get(x1, y1));
            }
        });
    out
}

/// [`sparse_stage`], then both images warped (bilinear) onto the rectified canvas.
///
/// # Errors
/// As [`sparse_stage`].
pub fn rectify_pair(
    left: &Image,
    right: &Image,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> Result<RectifiedPair, SparseError> {
    let sparse = sparse_stage(left, right, tilt_axis_deg, params)?;
    warp_onto_canvas(left, right, sparse)
}

/// Both micrographs warped onto the canvas of the sparse stage's rectification.
///
/// # Errors
/// [`RectifyError::Degenerate`] for a singular homography.
pub fn warp_onto_canvas(
    left: &Image,
    right: &Image,
    mut sparse: SparseResult,
) -> Result<RectifiedPair, SparseError> {
    let t = Instant::now();
    let r = &sparse.rectification;
    let (w, h) = r.canvas;
    let (wl, wr) = rayon::join(
        || warp(left, &r.h_left, w, h),
        || warp(right, &r.h_right, w, h),
    );
    // The checks in `rectify` keep every corner in front of the camera: H is invertible.
    let (Some(wl), Some(wr)) = (wl, wr) else {
        return Err(SparseError::Rectify(RectifyError::Degenerate));
    };
    sparse.timings.warp_ms = ms(t);
    sparse.timings.total_ms += sparse.timings.warp_ms;
    Ok(RectifiedPair {
        sparse,
        left: wl,
        right: wr,
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::vision::filter::blur::gaussian_blur;
    use crate::vision::rectify::transform;
    use rand::{Rng, SeedableRng};

    /// A parallel-projection (SEM) pair of a textured surface with a bump, after DESIGN §3's
    /// model: specimen point (s, r, z), tilt axis at φ, image coordinate along a: s, along n:
    /// r·cos t + z·sin t. The right shot is also rotated in-plane by `rot_deg` and shifted.
    pub(crate) struct SemPair {
        pub left: Image,
        pub right: Image,
        /// True correspondences on a grid of left pixels.
        pub truth: Vec<Correspondence>,
        /// Left pixel of the bump top and of a flat point.
        pub top: [f64; 2],
        pub flat: [f64; 2],
    }

    pub(crate) fn sem_pair(
        w: usize,
        h: usize,
        phi_deg: f64,
        tilt_deg: (f64, f64),
        rot_deg: f64,
        periodic: bool,
    ) -> SemPair {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
        let tex_n = 2 * w.max(h);
        let noise = Image::from_fn(tex_n, tex_n, |_, _| rng.random_range(0.0..1.0));
        let tex = gaussian_blur(&noise, 1.5);
        let (lo, hi) = tex.finite_range().unwrap();
        let tex = tex.map(|v| (v - lo) / (hi - lo));
        let phi = phi_deg.to_radians();
        let (a, n) = ([phi.cos(), phi.sin()], [-phi.sin(), phi.cos()]);
        let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let bump_r = 0.2 * w.min(h) as f64;
        let z = |s: f64, r: f64| {
            0.15 * w.min(h) as f64 * (-(s * s + r * r) / (2.0 * bump_r * bump_r)).exp()
        };
        let albedo = |s: f64, r: f64| -> f32 {
            if periodic {
                (0.5 + 0.25 * ((s * 0.5).sin() + (r * 0.5).sin())) as f32
            } else {
                tex.sample_bilinear(s + tex_n as f64 / 2.0, r + tex_n as f64 / 2.0)
                    .unwrap_or(0.5)
            }
        };
        // Image offset (relative to the centre) of specimen point (s, r) at tilt t.
        let project = |s: f64, r: f64, t: f64| {
            let v = r * t.cos() + z(s, r) * t.sin();
            (s * a[0] + v * n[0], s * a[1] + v * n[1])
        };
        let rot = rot_deg.to_radians();
        let shift = (6.3, -4.1);
        let to_right = |(x, y): (f64, f64)| {
            let (c, s) = (rot.cos(), rot.sin());
            (c * x - s * y + cx + shift.0, s * x + c * y + cy + shift.1)
        };
        let from_right = |px: f64, py: f64| {
            let (x, y) = (px - cx - shift.0, py - cy - shift.1);
            let (c, s) = (rot.cos(), rot.sin());
            (c * x + s * y, -s * x + c * y)
        };
        // Inverse projection by fixed point: s is the coordinate along a, r solves v = r cos t + z sin t.
        let unproject = |x: f64, y: f64, t: f64| {
            let s = x * a[0] + y * a[1];
            let v = x * n[0] + y * n[1];
            let mut r = v / t.cos();
            for _ in 0..30 {
                r = (v - z(s, r) * t.sin()) / t.cos();
            }
            (s, r)
        };
        let (t1, t2) = (tilt_deg.0.to_radians(), tilt_deg.1.to_radians());
        let left = Image::from_fn(w, h, |x, y| {
            let (s, r) = unproject(x as f64 - cx, y as f64 - cy, t1);
            albedo(s, r)
        });
        let right = Image::from_fn(w, h, |x, y| {
            let (u, v) = from_right(x as f64, y as f64);
            let (s, r) = unproject(u, v, t2);
            albedo(s, r)
        });
        let corr = |x: f64, y: f64| {
            let (s, r) = unproject(x - cx, y - cy, t1);
            let (rx, ry) = to_right(project(s, r, t2));
            Correspondence {
                left: [x, y],
                right: [rx, ry],
            }
        };
        let mut truth = Vec::new();
        for y in (20..h - 20).step_by(10) {
            for x in (20..w - 20).step_by(10) {
                truth.push(corr(x as f64, y as f64));
            }
        }
        let top = project(0.0, 0.0, t1);
        let flat = project(-0.4 * w as f64, 0.0, t1);
        SemPair {
            left,
            right,
            truth,
            top: [top.0 + cx, top.1 + cy],
            flat: [flat.0 + cx, flat.1 + cy],
        }
    }

    fn dy_stats(r: &SparseResult, truth: &[Correspondence]) -> (f64, f64) {
        let rec = &r.rectification;
        let mut dy: Vec<f64> = truth
            .iter()
            .map(|c| {
                let a = transform(&rec.h_left, &Vector2::new(c.left[0], c.left[1]));
                let b = transform(&rec.h_right, &Vector2::new(c.right[0], c.right[1]));
                (a.y - b.y).abs()
            })
            .collect();
        dy.sort_by(f64::total_cmp);
        (dy[dy.len() / 2], dy[dy.len() * 95 / 100])
    }

    #[test]
    fn rectifies_a_simulated_sem_pair_with_the_right_height_sign() {
        for (phi, model) in [
            (-90.0, FundamentalModel::Projective),
            (20.0, FundamentalModel::Affine),
        ] {
            let pair = sem_pair(320, 256, phi, (-4.0, 4.0), 0.7, false);
            let mut params = SparseParams::default();
            params.orsa.model = model;
            let r = sparse_stage(&pair.left, &pair.right, Some(phi), &params).unwrap();
            assert!(
                r.inliers.len() >= 16,
                "φ {phi}: {} inliers",
                r.inliers.len()
            );
            assert!(r.log10_nfa < 0.0);
            assert!(
                r.rectification.final_error_px < 0.3,
                "φ {phi}: final {}",
                r.rectification.final_error_px
            );
            let (med, p95) = dy_stats(&r, &pair.truth);
            assert!(
                med < 0.3 && p95 < 1.0,
                "φ {phi}: true |Δy| median {med}, p95 {p95}"
            );
            assert!(r.n_rectified.unwrap()[0] > 0.95);
            // The bump top is higher: larger x_right − x_left on the canvas than a flat point.
            let rec = &r.rectification;
            let disparity = |p: [f64; 2]| {
                let c = pair.truth.iter().min_by(|a, b| {
                    let da = (a.left[0] - p[0]).hypot(a.left[1] - p[1]);
                    let db = (b.left[0] - p[0]).hypot(b.left[1] - p[1]);
                    da.total_cmp(&db)
                });
                let c = c.unwrap();
                transform(&rec.h_right, &Vector2::new(c.right[0], c.right[1])).x
                    - transform(&rec.h_left, &Vector2::new(c.left[0], c.left[1])).x
            };
            assert!(disparity(pair.top) > disparity(pair.flat) + 2.0, "φ {phi}");
        }
    }

    #[test]
    fn same_seed_gives_identical_output() {
        let pair = sem_pair(256, 200, -90.0, (-3.0, 3.0), 0.3, false);
        let p = SparseParams::default();
        let mut a = sparse_stage(&pair.left, &pair.right, Some(-90.0), &p).unwrap();
        let mut b = sparse_stage(&pair.left, &pair.right, Some(-90.0), &p).unwrap();
        a.timings = Timings::default();
        b.timings = Timings::default();
        assert_eq!(a, b);
    }

    /// A micrograph of 3 % contrast (a low-contrast specimen, a low beam current): Lowe's
    /// threshold, meant for images spanning [0, 1], finds too little; the second attempt,
    /// its threshold scaled to the contrast, rectifies the pair.
    #[test]
    fn a_low_contrast_pair_is_rectified_by_the_second_attempt() {
        let pair = sem_pair(320, 240, -90.0, (-4.0, 4.0), 0.4, false);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (w, h) = pair.left.dimensions();
        let mut faint = |img: &Image| {
            let noise: Vec<f32> = (0..w * h)
                .map(|_| rng.random_range(-0.0015..0.0015))
                .collect();
            Image::from_fn(w, h, |x, y| {
                0.5 + 0.03 * (img.get(x, y) - 0.5) + noise[y * w + x]
            })
        };
        let (left, right) = (faint(&pair.left), faint(&pair.right));
        let c = feature_poor_sift(&SiftParams::default(), &left);
        assert!(
            (0.015..0.032).contains(&(c.c_dog / SiftParams::default().c_dog)),
            "threshold scaled by the contrast: {}",
            c.c_dog
        );
        let mut p = SparseParams {
            second_attempt: false,
            ..SparseParams::default()
        };
        let first = sparse_stage(&left, &right, Some(-90.0), &p).unwrap_err();
        p.second_attempt = true;
        let r = sparse_stage(&left, &right, Some(-90.0), &p).unwrap();
        let why = r.second_attempt.as_deref().unwrap();
        assert!(why.starts_with(&first.to_string()), "{why}");
        let (median, _) = dy_stats(&r, &pair.truth);
        assert!(median < 0.2, "rows off by {median} px");
        // A pair the first attempt rectifies is left alone.
        let r = sparse_stage(&pair.left, &pair.right, Some(-90.0), &p).unwrap();
        assert_eq!(r.second_attempt, None);
    }

    #[test]
    fn refusals_name_their_cause() {
        let pair = sem_pair(200, 160, -90.0, (-3.0, 3.0), 0.0, false);
        let small = Image::from_fn(180, 160, |x, y| pair.right.get(x, y));
        let p = SparseParams::default();
        let e = sparse_stage(&pair.left, &small, None, &p).unwrap_err();
        assert_eq!(
            e.to_string(),
            "images differ in size: 200×160 vs 180×160: left and right must come from the same scan"
        );
        let blank = Image::filled(200, 160, 0.4);
        let e = sparse_stage(&pair.left, &blank, None, &p).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("right image has no texture: 0 keypoints"),
            "{e}"
        );
        let tiny = Image::filled(20, 20, 0.4);
        let e = sparse_stage(&tiny, &tiny, None, &p).unwrap_err();
        assert!(
            matches!(
                e,
                SparseError::ImageTooSmall {
                    side: Side::Left,
                    ..
                }
            ),
            "{e}"
        );
        // Unrelated images: no meaningful model or too few matches, never a warp.
        let other = sem_pair(200, 160, 0.0, (-3.0, 3.0), 0.0, true);
        let e = sparse_stage(&pair.left, &other.left, None, &p).unwrap_err();
        assert!(
            matches!(
                e,
                SparseError::TooFewMatches { .. } | SparseError::NotMeaningful { .. }
            ),
            "{e}"
        );
    }

    #[test]
    fn periodic_texture_gives_a_right_warp_or_a_clear_refusal() {
        let pair = sem_pair(256, 200, -90.0, (-4.0, 4.0), 0.5, true);
        match sparse_stage(
            &pair.left,
            &pair.right,
            Some(-90.0),
            &SparseParams::default(),
        ) {
            Ok(r) => {
                let (med, _) = dy_stats(&r, &pair.truth);
                assert!(
                    med < 0.5,
                    "a wrong warp was accepted: true |Δy| median {med}"
                );
            }
            Err(e) => {
                let msg = e.to_string();
                assert!(
                    msg.contains("matches")
                        || msg.contains("meaningful")
                        || msg.contains("implausible"),
                    "{msg}"
                );
            }
        }
    }
}
