//! The sparse stage of SD-SEM (Baghaie et al., Micron 97, 2017, §2.1 and Table 2) as one
//! call: SIFT in both micrographs → ratio-test matching → ORSA fundamental matrix →
//! quasi-Euclidean rectification → (optionally) both images warped onto one canvas.
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
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::fundamental::FundamentalModel;
use crate::vision::matching::{MatchParams, match_keypoints};
use crate::vision::orsa::{OrsaError, OrsaParams, orsa};
use crate::vision::rectify::{RectifyError, RectifyParams, Rectification, rectify};
use crate::vision::sift::{SiftParams, SiftParamsError, sift};
use crate::vision::warp::{Warped, warp};

/// Parameters of the sparse stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SparseParams {
    pub sift: SiftParams,
    pub matching: MatchParams,
    pub orsa: OrsaParams,
    pub rectify: RectifyParams,
    /// Fewest ORSA inliers accepted (default 8: the paper's "eight are enough" — the
    /// rectification has six unknowns). Fewer → [`SparseError::TooFewMatches`].
    pub min_inliers: usize,
}

impl Default for SparseParams {
    fn default() -> Self {
        Self {
            // IPOL's scale space without its first, upsampled octave (VLFeat's first_octave 0):
            // the same blur per octave from σ = 1.6 on, four times less work, and on SEM images
            // the same rectification accuracy (see the report); at most the 2500 keypoints of
            // highest contrast, which bounds the matching time.
            sift: SiftParams {
                delta_min: 1.0,
                sigma_min: 1.6,
                max_keypoints: 2500,
                ..SiftParams::default()
            },
            matching: MatchParams::default(),
            orsa: OrsaParams::default(),
            rectify: RectifyParams::default(),
            min_inliers: 8,
        }
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
    SizeMismatch { left: (usize, usize), right: (usize, usize) },
    #[error("{side} image is too small: {}×{}, need at least {min}×{min} pixels", size.0, size.1)]
    ImageTooSmall { side: Side, size: (usize, usize), min: usize },
    #[error("{side} image has no texture: {keypoints} keypoints (need {need}); is it blank or out of focus?")]
    NoTexture { side: Side, keypoints: usize, need: usize },
    #[error("not enough reliable matches: found {found}, need {need} ({stage})")]
    TooFewMatches { found: usize, need: usize, stage: &'static str },
    #[error(
        "no meaningful epipolar geometry: best log10 NFA = {log10_nfa:.1} (must be < 0) with {inliers} of {matches} matches; the images may not show the same area"
    )]
    NotMeaningful { log10_nfa: f64, inliers: usize, matches: usize },
    #[error(transparent)]
    Rectify(#[from] RectifyError),
    #[error(transparent)]
    Params(#[from] SiftParamsError),
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
    /// Putative matches (ratio test and symmetric check), original pixels.
    pub matches: Vec<Correspondence>,
    /// ORSA inliers, original pixels.
    pub inliers: Vec<Correspondence>,
    pub model: FundamentalModel,
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
    params.sift.validate()?;
    let need = params.min_inliers.max(params.orsa.model.sample_size() + 1);

    let t = Instant::now();
    let ((kl, tl), (kr, tr)) = rayon::join(
        || {
            let t = Instant::now();
            (sift(left, &params.sift), ms(t))
        },
        || {
            let t = Instant::now();
            (sift(right, &params.sift), ms(t))
        },
    );
    let (kl, kr) = (kl?, kr?);
    let mut timings = Timings {
        sift_ms: ms(t),
        sift_left_ms: tl,
        sift_right_ms: tr,
        ..Timings::default()
    };
    for (side, k) in [(Side::Left, &kl), (Side::Right, &kr)] {
        if k.len() < need {
            return Err(SparseError::NoTexture {
                side,
                keypoints: k.len(),
                need,
            });
        }
    }

    let t = Instant::now();
    let matches = match_keypoints(&kl, &kr, &params.matching);
    timings.matching_ms = ms(t);
    if matches.len() < need {
        return Err(SparseError::TooFewMatches {
            found: matches.len(),
            need,
            stage: "descriptor matching",
        });
    }
    let pl: Vec<Vector2<f64>> = matches.iter().map(|m| Vector2::new(kl[m.left].x, kl[m.left].y)).collect();
    let pr: Vec<Vector2<f64>> = matches.iter().map(|m| Vector2::new(kr[m.right].x, kr[m.right].y)).collect();

    let t = Instant::now();
    let size = left.dimensions();
    let found = orsa(&pl, &pr, [size, size], &params.orsa);
    timings.orsa_ms = ms(t);
    let found = match found {
        Ok(f) => f,
        Err(OrsaError::TooFewMatches { found, need }) => {
            return Err(SparseError::TooFewMatches {
                found,
                need,
                stage: "ORSA",
            });
        }
        Err(OrsaError::NotMeaningful { best_log10_nfa, inliers }) => {
            return Err(SparseError::NotMeaningful {
                log10_nfa: best_log10_nfa,
                inliers,
                matches: matches.len(),
            });
        }
    };
    if found.inliers.len() < need {
        return Err(SparseError::TooFewMatches {
            found: found.inliers.len(),
            need,
            stage: "ORSA inliers",
        });
    }
    let il: Vec<Vector2<f64>> = found.inliers.iter().map(|&i| pl[i]).collect();
    let ir: Vec<Vector2<f64>> = found.inliers.iter().map(|&i| pr[i]).collect();

    let t = Instant::now();
    let rectification = rectify(&il, &ir, &found.f, size, tilt_axis_deg, &params.rectify)?;
    timings.rectify_ms = ms(t);
    timings.total_ms = ms(t_total);

    let corr = |a: &Vector2<f64>, b: &Vector2<f64>| Correspondence {
        left: [a.x, a.y],
        right: [b.x, b.y],
    };
    Ok(SparseResult {
        image_size: size,
        keypoints_left: kl.len(),
        keypoints_right: kr.len(),
        matches: pl.iter().zip(&pr).map(|(a, b)| corr(a, b)).collect(),
        inliers: il.iter().zip(&ir).map(|(a, b)| corr(a, b)).collect(),
        model: params.orsa.model,
        f: found.f,
        log10_nfa: found.log10_nfa,
        threshold_px: found.threshold_px,
        orsa_iterations: found.iterations,
        n_rectified: rectification.n_rectified,
        rectification,
        timings,
    })
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
    let mut sparse = sparse_stage(left, right, tilt_axis_deg, params)?;
    let t = Instant::now();
    let r = &sparse.rectification;
    let (w, h) = r.canvas;
    let (wl, wr) = rayon::join(|| warp(left, &r.h_left, w, h), || warp(right, &r.h_right, w, h));
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
