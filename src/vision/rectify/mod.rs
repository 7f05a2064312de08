//! Quasi-Euclidean epipolar rectification (Fusiello & Irsara, "Quasi-Euclidean uncalibrated
//! epipolar rectification", ICPR 2008; Monasse, "Quasi-Euclidean Epipolar Rectification",
//! IPOL 2011).
//!
//! Both images are treated as views of a camera `K = [[f, 0, w/2], [0, f, h/2], [0, 0, 1]]`
//! with `f = 3^g · (w + h)`, rotated so that their epipolar lines become rows:
//! `H_left = K R_left K⁻¹`, `H_right = K R_right K⁻¹` (Monasse eq. 2). The rectified pair has
//! the fundamental matrix `[e₁]ₓ` (corresponding points share `y`), so the original one is
//! `F = K⁻ᵀ R_rightᵀ [e₁]ₓ R_left K⁻¹` (eq. 4). The six unknowns — left rotations about `y`
//! and `z`, right rotations about `x`, `y`, `z`, and `g` — minimise the Sampson error (H&Z
//! eq. 11.9) of the inlier matches by Levenberg–Marquardt.
//!
//! The in-plane rotations start from the epipolar direction of the ORSA fundamental matrix
//! rather than from 0 (Monasse's start), so pairs whose parallax is not roughly horizontal
//! (any tilt axis) rectify too. Rotations compose as `R = R_x · R_y · R_z`: the in-plane
//! rotation first, then the small corrections in the rectified frame.

pub mod instrument;
mod lm;
pub mod warp;

use nalgebra::{Matrix3, SMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Parameters of the rectification and of the checks that refuse implausible warps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RectifyParams {
    /// Levenberg–Marquardt iterations at most, per phase (default 60). The cost is nearly flat
    /// along the focal length near parallel projection: beyond 60 the final error moved by
    /// < 0.001 px on the simulator sweep and the Potamogeton pair, at 4× the time.
    pub max_iterations: usize,
    /// Stop when one step lowers the cost by less than this fraction (default 1e-9).
    pub tolerance: f64,
    /// Weight of the gauge-fixing prior on the out-of-plane rotations, px per radian (default 1;
    /// 0 is Monasse's cost exactly). See `residuals_with_prior`.
    pub rotation_prior: f64,
    /// Weight of the pull towards the tilt axis (when given) on the in-plane rotation, px per
    /// radian (default 10): decides the parallax direction on nearly flat specimens, where the
    /// matches cannot; real parallax of a pixel or more overrides it.
    pub tilt_axis_prior: f64,
    /// Lower and upper bound of the focal exponent `g` in `f = 3^g (w + h)` (default −2 … 10;
    /// SEM's parallel projection drives `g` to the upper bound, where the homographies are
    /// nearly affine).
    pub g_range: (f64, f64),
    /// Largest accepted in-plane rotation of the right image relative to the left, degrees
    /// (default 20). Stage handling rotates shots by a degree or two; more means wrong matches.
    pub max_relative_rotation_deg: f64,
    /// Largest accepted out-of-plane rotation (left `y`, right `x`, `y`), degrees (default 20).
    pub max_out_of_plane_deg: f64,
    /// Largest accepted canvas side, in multiples of the larger image side (default 2).
    pub max_canvas_scale: f64,
    /// Largest accepted RMS vertical disparity of the inliers after rectification, pixels
    /// (default 1.0). Above, the warp would not give the dense stage aligned rows.
    pub max_final_error_px: f64,
    /// Largest accepted uncertainty (1σ, pixels) of the rectified rows' alignment at the image
    /// corners, predicted from the inliers (default 0.75; on the simulator sweep the true
    /// misalignment was 3–4 times smaller than this prediction). Catches rectifications that fit their
    /// few or clustered inliers but are not determined by them (repetitive scenes).
    pub max_predicted_error_px: f64,
    /// Largest accepted angle between the tilt-axis normal `n` (when given) and the epipolar
    /// direction found, degrees (default 10).
    pub max_tilt_axis_mismatch_deg: f64,
    /// Scale of a Cauchy loss on the Sampson residuals for a first, robust optimisation,
    /// pixels (default 1; 0 = least squares only, Monasse's cost). Matches whose residual at
    /// the robust optimum exceeds `outlier_factor` × this scale (default 3) are left out of the
    /// final least-squares fit: wrong matches that slide along their epipolar line, which ORSA
    /// cannot reject.
    pub cauchy_scale_px: f64,
    pub outlier_factor: f64,
    /// `tilt_axis_prior` and `rotation_prior` of the robust pass, px per radian (default 100
    /// both): the out-of-plane rotations could otherwise turn the rows in its stead.
    pub robust_tilt_axis_prior: f64,
    pub robust_rotation_prior: f64,
}

impl Default for RectifyParams {
    fn default() -> Self {
        Self {
            max_iterations: 60,
            tolerance: 1e-9,
            rotation_prior: 1.0,
            tilt_axis_prior: 10.0,
            g_range: (-2.0, 10.0),
            max_relative_rotation_deg: 20.0,
            max_out_of_plane_deg: 20.0,
            max_canvas_scale: 2.0,
            max_final_error_px: 1.0,
            max_predicted_error_px: 0.75,
            max_tilt_axis_mismatch_deg: 10.0,
            cauchy_scale_px: 1.0,
            outlier_factor: 3.0,
            robust_tilt_axis_prior: 100.0,
            robust_rotation_prior: 100.0,
        }
    }
}

/// The six unknowns (radians; `g` dimensionless).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct QuasiEuclidean {
    pub left_y: f64,
    pub left_z: f64,
    pub right_x: f64,
    pub right_y: f64,
    pub right_z: f64,
    pub g: f64,
}

impl QuasiEuclidean {
    fn to_vec(self) -> [f64; 6] {
        [
            self.left_y,
            self.left_z,
            self.right_x,
            self.right_y,
            self.right_z,
            self.g,
        ]
    }
    fn from_vec(v: &[f64; 6]) -> Self {
        Self {
            left_y: v[0],
            left_z: v[1],
            right_x: v[2],
            right_y: v[3],
            right_z: v[4],
            g: v[5],
        }
    }
}

/// A rectification of one image pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    /// Original left pixel → rectified canvas pixel (homogeneous).
    pub h_left: Matrix3<f64>,
    /// Original right pixel → rectified canvas pixel; corresponding points share `y`.
    pub h_right: Matrix3<f64>,
    /// Canvas `(width, height)`: holds all of both warped images.
    pub canvas: (usize, usize),
    /// Translation applied after `K R K⁻¹` to put both images on the canvas, pixels.
    pub canvas_offset: (f64, f64),
    /// Extra shift of the right image along x (pixels) that makes the median inlier
    /// disparity 0; included in `h_right`.
    pub right_shift_px: f64,
    pub params: QuasiEuclidean,
    /// `f = 3^g (w + h)`, pixels.
    pub focal_px: f64,
    /// The rectification error before rectification, as Monasse's reference code defines and
    /// prints it ("Initial rectification error"): the RMS Sampson error of the inliers for the
    /// rectifying F of the start of the optimisation with all rotations 0 (`H = I`), which is
    /// `RMS(y_left − y_right) / √2` of the original positions. Pixels.
    pub initial_error_px: f64,
    /// The rectification error after rectification, as Monasse's code defines and prints it
    /// ("Final rectification error", the figure of the SD-SEM paper's Table 2): the RMS Sampson
    /// error (H&Z eq. 11.9) of the inliers for the rectifying `F = K⁻ᵀ R_rᵀ [e₁]ₓ R_l K⁻¹` at
    /// the optimum, i.e. the RMS distance each correspondence must move (both points together)
    /// to satisfy it; on rectified rows this is `RMS(y_left − y_right) / √2`. Pixels.
    pub final_error_px: f64,
    /// RMS of `y_left − y_right` of the inliers on the rectified canvas, pixels (≈ √2 ×
    /// `final_error_px`): the vertical disparity the dense stage sees.
    pub final_dy_rms_px: f64,
    /// Standard deviation of the rectified rows' misalignment predicted from the matches, at
    /// the worst image corner, pixels (see `predicted_error`).
    pub predicted_error_px: f64,
    /// Levenberg–Marquardt iterations run.
    pub iterations: usize,
    /// Unit direction, on the canvas, of the tilt-axis normal `n = (−sin φ, cos φ)` of the left
    /// image at its centre, when φ was given. With `n_rectified.x > 0` (what the start
    /// enforces), a point higher above the specimen has a larger `x_right − x_left`.
    pub n_rectified: Option<[f64; 2]>,
    /// Indices of the input matches left out of the final fit (see
    /// [`RectifyParams::cauchy_scale_px`]); every figure above is over the others.
    pub outliers: Vec<usize>,
}

/// Why no trustworthy rectification exists.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RectifyError {
    #[error("not enough inlier matches to rectify: found {found}, need {need}")]
    TooFewMatches { found: usize, need: usize },
    #[error(
        "the epipolar geometry is degenerate (no epipole found): the matches do not determine a rectification"
    )]
    Degenerate,
    #[error(
        "the tilt-axis normal (φ = {tilt_axis_deg:.1}°) ends {mismatch_deg:.1}° away from the rows the matches ask for (limit {limit_deg}°)"
    )]
    TiltAxisMismatch {
        tilt_axis_deg: f64,
        mismatch_deg: f64,
        limit_deg: f64,
    },
    #[error("implausible rectification refused: {what} = {value:.2} exceeds {limit:.2}")]
    Implausible {
        what: &'static str,
        value: f64,
        limit: f64,
    },
}

/// What [`RectifyError::Implausible`] names when too few or too clustered inliers leave the
/// rectified rows uncertain (a lack of evidence, unlike a large residual).
pub const ROW_UNCERTAINTY: &str = "uncertainty of the rectified rows at the image corners (px, 1σ)";

fn rot_x(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)
}
fn rot_y(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)
}
fn rot_z(a: f64) -> Matrix3<f64> {
    let (s, c) = a.sin_cos();
    Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)
}

/// Geometry shared by the cost and the homographies.
struct Frame {
    w: f64,
    h: f64,
}

impl Frame {
    fn k(&self, g: f64) -> Matrix3<f64> {
        let f = 3f64.powf(g) * (self.w + self.h);
        Matrix3::new(f, 0.0, self.w / 2.0, 0.0, f, self.h / 2.0, 0.0, 0.0, 1.0)
    }
    fn k_inv(&self, g: f64) -> Matrix3<f64> {
        let f = 3f64.powf(g) * (self.w + self.h);
        Matrix3::new(
            1.0 / f,
            0.0,
            -self.w / (2.0 * f),
            0.0,
            1.0 / f,
            -self.h / (2.0 * f),
            0.0,
            0.0,
            1.0,
        )
    }
    fn rotations(q: &QuasiEuclidean) -> (Matrix3<f64>, Matrix3<f64>) {
        (
            rot_y(q.left_y) * rot_z(q.left_z),
            rot_x(q.right_x) * rot_y(q.right_y) * rot_z(q.right_z),
        )
    }
    /// `(H_left, H_right)` before the canvas translation.
    fn homographies(&self, q: &QuasiEuclidean) -> (Matrix3<f64>, Matrix3<f64>) {
        let (rl, rr) = Self::rotations(q);
        let (k, ki) = (self.k(q.g), self.k_inv(q.g));
        (k * rl * ki, k * rr * ki)
    }
    /// `F = K⁻ᵀ R_rᵀ [e₁]ₓ R_l K⁻¹` (Monasse eq. 4).
    fn fundamental(&self, q: &QuasiEuclidean) -> Matrix3<f64> {
        let (rl, rr) = Self::rotations(q);
        let ki = self.k_inv(q.g);
        let e1x = Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
        ki.transpose() * rr.transpose() * e1x * rl * ki
    }
}

/// Signed Sampson residuals of all matches for `q`, then `prior · (left_y, right_x, right_y)`.
///
/// The prior is a gauge fix, not part of Monasse's cost: near parallel projection (SEM), opposite
/// rotations about `y` at a long focal only shift one image along the rows, which the Sampson
/// error cannot see; without it Levenberg–Marquardt drifts along that valley. At 1 px/rad it
/// costs what a 1-px residual on one match costs at one radian: nothing where the data decide.
fn residuals_with_prior(
    frame: &Frame,
    q: &QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    prior: &Prior,
    out: &mut Vec<f64>,
) {
    residuals(frame, q, left, right, out);
    if let Some(c) = prior.cauchy {
        // ρ(r) = c² ln(1 + r²/c²) as a residual whose square is ρ.
        for r in out.iter_mut() {
            *r = r.signum() * c * (*r / c).mul_add(*r / c, 1.0).ln().sqrt();
        }
    }
    let r = prior.rotation;
    out.extend([r * q.left_y, r * q.right_x, r * q.right_y]);
    if let Some((weight, left_z)) = prior.axis {
        out.push(weight * (q.left_z - left_z));
    }
}

/// The soft constraints added to the Sampson residuals.
#[derive(Debug, Clone, Copy)]
struct Prior {
    /// px/rad on the out-of-plane rotations (gauge fix, see `residuals_with_prior`).
    rotation: f64,
    /// px/rad pulling the left in-plane rotation to the one that puts the tilt-axis normal
    /// along +x, when the axis is known: on nearly flat specimens the matches barely say where
    /// the parallax runs, and the axis does.
    axis: Option<(f64, f64)>,
    /// Scale of the Cauchy loss on the Sampson residuals, pixels (`None`: least squares).
    cauchy: Option<f64>,
}

/// Signed Sampson residuals of all matches for `q`.
fn residuals(
    frame: &Frame,
    q: &QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    out: &mut Vec<f64>,
) {
    let f = frame.fundamental(q);
    out.clear();
    out.extend(left.iter().zip(right).map(|(x, xp)| {
        let (xh, xph) = (Vector3::new(x.x, x.y, 1.0), Vector3::new(xp.x, xp.y, 1.0));
        let fx = f * xh;
        let ftx = f.transpose() * xph;
        let den = (fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y).sqrt();
        if den > 0.0 { xph.dot(&fx) / den } else { 0.0 }
    }));
}

/// Applies a homography to a point.
#[must_use]
pub fn transform(h: &Matrix3<f64>, p: &Vector2<f64>) -> Vector2<f64> {
    let v = h * Vector3::new(p.x, p.y, 1.0);
    Vector2::new(v.x / v.z, v.y / v.z)
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 { 0.0 } else { (s / n as f64).sqrt() }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// The in-plane rotation of the right image relative to the left, robustly: the median, over
/// pairs of matches at least `min_separation` apart, of the angle the segment joining them turns
/// by. Wrong matches and parallax move single segments, not the median. 0 without such pairs.
fn relative_rotation(left: &[Vector2<f64>], right: &[Vector2<f64>], min_separation: f64) -> f64 {
    let n = left.len().min(right.len());
    let mut angles = Vec::with_capacity(3 * n);
    for i in 0..n {
        for k in [n / 2, n / 3, n / 5] {
            let j = (i + k.max(1)) % n;
            let (dl, dr) = (left[j] - left[i], right[j] - right[i]);
            if dl.norm() >= min_separation && dr.norm() > 0.0 {
                let a = dr.y.atan2(dr.x) - dl.y.atan2(dl.x);
                angles.push(
                    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                        - std::f64::consts::PI,
                );
            }
        }
    }
    median(angles)
}

/// The affine map `right ≈ A · left + t` fitted to the matches by least squares; `None` when
/// they do not determine it (fewer than 3, or collinear).
#[must_use]
pub fn affine_map(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
) -> Option<(nalgebra::Matrix2<f64>, Vector2<f64>)> {
    let n = left.len().min(right.len());
    if n < 3 {
        return None;
    }
    let c = left[..n].iter().sum::<Vector2<f64>>() / n as f64;
    let cr = right[..n].iter().sum::<Vector2<f64>>() / n as f64;
    let mut m = nalgebra::Matrix2::zeros();
    let (mut bx, mut by) = (Vector2::zeros(), Vector2::zeros());
    for (l, r) in left[..n].iter().zip(&right[..n]) {
        let d = l - c;
        m += d * d.transpose();
        bx += d * (r.x - cr.x);
        by += d * (r.y - cr.y);
    }
    let mi = m.try_inverse()?;
    let (ax, ay) = (mi * bx, mi * by);
    let a = nalgebra::Matrix2::new(ax.x, ax.y, ay.x, ay.y);
    Some((a, cr - a * c))
}

/// Unit direction of the epipolar lines of the left image at its centre, from `F` (the line
/// joining the centre to the epipole `e`, `F e = 0`; `e` may lie at infinity).
#[must_use]
pub fn epipolar_direction(f: &Matrix3<f64>, centre: Vector2<f64>) -> Option<Vector2<f64>> {
    let svd = f.svd(false, true);
    let vt = svd.v_t?;
    let k = (0..3).min_by(|&a, &b| svd.singular_values[a].total_cmp(&svd.singular_values[b]))?;
    let e = vt.row(k).transpose();
    let d = Vector2::new(e.x - centre.x * e.z, e.y - centre.y * e.z);
    let n = d.norm();
    (n > 1e-12 && n.is_finite()).then(|| d / n)
}

/// Rectifies the pair from its inlier matches `left[i] ↔ right[i]` (original pixels) and the
/// fundamental matrix `f` they satisfy (`x'ᵀ F x = 0`), for images of `size = (w, h)`.
///
/// `tilt_axis_deg` (DESIGN §3's φ), when known, fixes the orientation: the tilt-axis normal `n`
/// points along +x on the canvas, so disparity `x_right − x_left` grows with height.
/// Without it, the in-plane rotation is the smallest that makes the epipolar lines rows.
///
/// # Errors
/// [`RectifyError`] when there are fewer than 6 matches, the geometry is degenerate, the tilt
/// axis contradicts the matches, or the result fails a plausibility check (rotation, canvas
/// size, residual): a refused warp rather than a silently wrong one.
pub fn rectify(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    f: &Matrix3<f64>,
    size: (usize, usize),
    tilt_axis_deg: Option<f64>,
    params: &RectifyParams,
) -> Result<Rectification, RectifyError> {
    const NEED: usize = 6;
    let n = left.len().min(right.len());
    if n < NEED {
        return Err(RectifyError::TooFewMatches {
            found: n,
            need: NEED,
        });
    }
    let (left, right) = (&left[..n], &right[..n]);
    let frame = Frame {
        w: size.0 as f64,
        h: size.1 as f64,
    };
    let centre = Vector2::new((frame.w - 1.0) / 2.0, (frame.h - 1.0) / 2.0);

    // Start: rotate each image in its plane so that its epipolar lines become rows. With the tilt
    // axis known, the parallax runs along n in both images (up to the small scan rotation between
    // shots), which holds even where F says little about it (nearly flat specimens, small tilts);
    // otherwise the epipolar directions of F.
    let normal = tilt_axis_deg.map(|phi| {
        let p = phi.to_radians();
        Vector2::new(-p.sin(), p.cos())
    });
    let (dl, dr) = if let Some(nv) = normal {
        // The right shot may be turned in its plane (scan rotation, stage handling): its parallax
        // runs along n turned by that rotation.
        let psi = relative_rotation(left, right, frame.w.min(frame.h) / 8.0);
        (nv, nalgebra::Rotation2::new(psi) * nv)
    } else {
        let mut dl = epipolar_direction(f, centre).ok_or(RectifyError::Degenerate)?;
        let mut dr = epipolar_direction(&f.transpose(), centre).ok_or(RectifyError::Degenerate)?;
        if dl.x < 0.0 {
            dl = -dl;
        }
        if dr.dot(&dl) < 0.0 {
            dr = -dr;
        }
        (dl, dr)
    };
    let in_plane = QuasiEuclidean {
        left_y: 0.0,
        left_z: -dl.y.atan2(dl.x),
        right_x: 0.0,
        right_y: 0.0,
        right_z: -dr.y.atan2(dr.x),
        g: 0.0,
    };
    let robust = params.cauchy_scale_px > 0.0;
    let prior = Prior {
        rotation: params.rotation_prior,
        axis: normal.map(|_| (params.tilt_axis_prior, in_plane.left_z)),
        cauchy: None,
    };
    // The robust pass holds the rows to the tilt axis firmly: a wrong match costs at most
    // ~c² ln(1 + (r/c)²) under the Cauchy loss, so a weak pull would let a handful of them turn
    // the rows where the true matches leave the direction open; many true matches with real
    // parallax still turn them.
    let robust_prior = Prior {
        rotation: params.robust_rotation_prior,
        axis: normal.map(|_| (params.robust_tilt_axis_prior, in_plane.left_z)),
        cauchy: Some(params.cauchy_scale_px),
    };
    let (mut q, mut iterations) = optimise(
        &frame,
        &in_plane,
        left,
        right,
        params,
        if robust { &robust_prior } else { &prior },
    );

    // Robust pass (beyond Monasse): a few ORSA inliers can be wrong matches that slide along
    // their epipolar lines (repetitive structure), which F cannot reject; far from the others in
    // disparity, they decide the direction of the rows when the true matches leave it open
    // (nearly flat specimens). Under the Cauchy loss they barely count; those the optimum cannot
    // align are left out, and least squares on the rest gives the final figures.
    let mut outliers = Vec::new();
    let (mut kept_left, mut kept_right) = (left.to_vec(), right.to_vec());
    if robust {
        let mut buf = Vec::new();
        residuals(&frame, &q, left, right, &mut buf);
        let limit = params.outlier_factor * params.cauchy_scale_px;
        outliers = (0..n).filter(|&i| buf[i].abs() > limit).collect();
        if !outliers.is_empty() {
            kept_left.clear();
            kept_right.clear();
            for i in (0..n).filter(|i| buf[*i].abs() <= limit) {
                kept_left.push(left[i]);
                kept_right.push(right[i]);
            }
            if kept_left.len() < NEED {
                return Err(RectifyError::TooFewMatches {
                    found: kept_left.len(),
                    need: NEED,
                });
            }
        }
        let (q2, it) = levenberg_marquardt(&frame, q, &kept_left, &kept_right, params, &prior, 6);
        q = q2;
        iterations += it;
    }
    let (left, right) = (&kept_left[..], &kept_right[..]);

    // Plausibility of the optimum.
    let rel = (q.right_z - q.left_z + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
        - std::f64::consts::PI;
    check(
        "relative in-plane rotation (°)",
        rel.to_degrees().abs(),
        params.max_relative_rotation_deg,
    )?;
    for (what, a) in [
        ("left out-of-plane rotation about y (°)", q.left_y),
        ("right out-of-plane rotation about x (°)", q.right_x),
        ("right out-of-plane rotation about y (°)", q.right_y),
    ] {
        check(what, a.to_degrees().abs(), params.max_out_of_plane_deg)?;
    }

    let (hl0, hr0) = frame.homographies(&q);
    // Horizontal shifts of one image keep rows aligned, and the cost barely sees their
    // quasi-Euclidean form (opposite y rotations at a long focal): fix this freedom by
    // shifting the right image so that the median inlier disparity is 0. The dense stage then
    // searches around 0, and the canvas stays compact.
    let mut disparities: Vec<f64> = left
        .iter()
        .zip(right)
        .map(|(a, b)| transform(&hr0, b).x - transform(&hl0, a).x)
        .collect();
    disparities.sort_by(f64::total_cmp);
    let median_disparity = disparities[disparities.len() / 2];
    let hr0 = Matrix3::new(1.0, 0.0, -median_disparity, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0) * hr0;
    // Canvas: the bounding box of both warped images; every corner must stay in front.
    let corners = [
        Vector2::new(0.0, 0.0),
        Vector2::new(frame.w - 1.0, 0.0),
        Vector2::new(0.0, frame.h - 1.0),
        Vector2::new(frame.w - 1.0, frame.h - 1.0),
    ];
    let (mut lo, mut hi) = (
        Vector2::repeat(f64::INFINITY),
        Vector2::repeat(f64::NEG_INFINITY),
    );
    for h in [&hl0, &hr0] {
        for c in &corners {
            let v = h * Vector3::new(c.x, c.y, 1.0);
            check(
                "corner sent behind the camera (1/w)",
                if v.z > 0.0 { 0.0 } else { f64::INFINITY },
                0.0,
            )?;
            let p = Vector2::new(v.x / v.z, v.y / v.z);
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
    }
    let side = frame.w.max(frame.h);
    let limit = params.max_canvas_scale * side;
    check("canvas width (px)", hi.x - lo.x + 1.0, limit)?;
    check("canvas height (px)", hi.y - lo.y + 1.0, limit)?;
    let offset = (-lo.x.floor(), -lo.y.floor());
    let t = Matrix3::new(1.0, 0.0, offset.0, 0.0, 1.0, offset.1, 0.0, 0.0, 1.0);
    let (h_left, h_right) = (t * hl0, t * hr0);
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let canvas = (
        (hi.x + offset.0).floor() as usize + 1,
        (hi.y + offset.1).floor() as usize + 1,
    );

    // Monasse's figures: RMS Sampson error at P = 0 and at the optimum.
    let mut buf = Vec::new();
    let identity = QuasiEuclidean::from_vec(&[0.0; 6]);
    residuals(&frame, &identity, left, right, &mut buf);
    let initial_error_px = rms(buf.iter().copied());
    residuals(&frame, &q, left, right, &mut buf);
    let final_error_px = rms(buf.iter().copied());
    let final_dy_rms_px = rms(left
        .iter()
        .zip(right)
        .map(|(a, b)| transform(&h_left, a).y - transform(&h_right, b).y));
    check(
        "RMS vertical disparity of the inliers after rectification (px)",
        final_dy_rms_px,
        params.max_final_error_px,
    )?;
    let predicted_error_px =
        predicted_error(&frame, &q, left, right, &prior).unwrap_or(f64::INFINITY);
    check(
        ROW_UNCERTAINTY,
        predicted_error_px,
        params.max_predicted_error_px,
    )?;

    let n_rectified = normal.map(|nv| {
        // Image of a short step along n from the left centre.
        let a = transform(&h_left, &centre);
        let b = transform(&h_left, &(centre + nv));
        let d = b - a;
        let d = d / d.norm();
        [d.x, d.y]
    });

    // The data decide where the parallax runs: a tilt axis that the optimum had to turn away
    // from is wrong, and heights along it would be too.
    if let (Some(n), Some(phi)) = (n_rectified, tilt_axis_deg) {
        let mismatch = n[1].atan2(n[0]).to_degrees().abs();
        if mismatch > params.max_tilt_axis_mismatch_deg {
            return Err(RectifyError::TiltAxisMismatch {
                tilt_axis_deg: phi,
                mismatch_deg: mismatch,
                limit_deg: params.max_tilt_axis_mismatch_deg,
            });
        }
    }

    Ok(Rectification {
        h_left,
        h_right,
        canvas,
        canvas_offset: offset,
        right_shift_px: -median_disparity,
        params: q,
        focal_px: 3f64.powf(q.g) * (frame.w + frame.h),
        initial_error_px,
        final_error_px,
        final_dy_rms_px,
        predicted_error_px,
        iterations,
        n_rectified,
        outliers,
    })
}

/// Levenberg–Marquardt from two starts, the better optimum kept: Monasse's focal (g = 0), and
/// a long focal where the homographies are nearly affine, the SEM's parallel projection. From
/// g = 0 alone, the parallax of a parallel projection (two planes at different heights, say)
/// can lead the first steps down the cost's nearly flat common-rotation direction into a wrong
/// minimum. Each start fixes the rows' offset first, then solves with `g` fixed, then with all
/// six unknowns (the focal length trades off against the out-of-plane rotations along a long
/// shallow valley of the cost).
fn optimise(
    frame: &Frame,
    in_plane: &QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    params: &RectifyParams,
    prior: &Prior,
) -> (QuasiEuclidean, usize) {
    let mut best: Option<(QuasiEuclidean, usize, f64)> = None;
    let mut buf = Vec::new();
    for g0 in [0.0, LONG_FOCAL_G.clamp(params.g_range.0, params.g_range.1)] {
        let mut start = QuasiEuclidean { g: g0, ..*in_plane };
        // Turning the right camera about x by α moves its rows by −f·α.
        let (hl, hr) = frame.homographies(&start);
        let offset = median(
            left.iter()
                .zip(right)
                .map(|(a, b)| transform(&hr, b).y - transform(&hl, a).y)
                .collect(),
        );
        start.right_x = (offset / frame.k(g0)[(0, 0)]).atan();
        let (q, it1) = levenberg_marquardt(frame, start, left, right, params, prior, 5);
        let (q, it2) = levenberg_marquardt(frame, q, left, right, params, prior, 6);
        residuals_with_prior(frame, &q, left, right, prior, &mut buf);
        let cost = buf.iter().map(|x| x * x).sum::<f64>();
        if best.as_ref().is_none_or(|b| cost < b.2) {
            best = Some((q, it1 + it2, cost));
        }
    }
    best.map_or((*in_plane, 0), |(q, it, _)| (q, it))
}

/// How well the matches pin the rectification down: the standard deviation (pixels) of the
/// rectified `y_left − y_right` of a typical correspondence (the matches' median displacement), at the worst of
/// the image corners and centre, propagated from the parameter covariance `σ² (JᵀJ)⁻¹`
/// (σ² from the Sampson residuals, H&Z §5.2.2). Few, clustered or noisy inliers give a large
/// value even when they themselves fit well. `None` when `JᵀJ` is singular.
fn predicted_error(
    frame: &Frame,
    q: &QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    prior: &Prior,
) -> Option<f64> {
    let p0 = q.to_vec();
    let step = 1e-6;
    let mut r0 = Vec::new();
    residuals_with_prior(frame, q, left, right, prior, &mut r0);
    let n = left.len();
    if n <= 6 {
        return None;
    }
    let sigma2 = r0[..n].iter().map(|x| x * x).sum::<f64>() / (n - 6) as f64;
    let mut cols = Vec::with_capacity(6);
    let (mut rp, mut rm) = (Vec::new(), Vec::new());
    for k in 0..6 {
        let (mut a, mut b) = (p0, p0);
        a[k] += step;
        b[k] -= step;
        residuals_with_prior(
            frame,
            &QuasiEuclidean::from_vec(&a),
            left,
            right,
            prior,
            &mut rp,
        );
        residuals_with_prior(
            frame,
            &QuasiEuclidean::from_vec(&b),
            left,
            right,
            prior,
            &mut rm,
        );
        cols.push(
            rp.iter()
                .zip(&rm)
                .map(|(u, v)| (u - v) / (2.0 * step))
                .collect::<Vec<f64>>(),
        );
    }
    let mut jtj = SMatrix::<f64, 6, 6>::zeros();
    for a in 0..6 {
        for b in 0..6 {
            jtj[(a, b)] = cols[a].iter().zip(&cols[b]).map(|(x, y)| x * y).sum();
        }
    }
    let cov = jtj.try_inverse()? * sigma2;
    // A point at `pt` in the left image and at `pt + shift` in the right, `shift` the median
    // displacement of the matches: a typical correspondence, wherever in the image.
    let shift = Vector2::new(
        median(left.iter().zip(right).map(|(a, b)| b.x - a.x).collect()),
        median(left.iter().zip(right).map(|(a, b)| b.y - a.y).collect()),
    );
    let dy = |v: &[f64; 6], pt: &Vector2<f64>| {
        let (hl, hr) = frame.homographies(&QuasiEuclidean::from_vec(v));
        transform(&hl, pt).y - transform(&hr, &(pt + shift)).y
    };
    let points = [
        Vector2::new(0.0, 0.0),
        Vector2::new(frame.w - 1.0, 0.0),
        Vector2::new(0.0, frame.h - 1.0),
        Vector2::new(frame.w - 1.0, frame.h - 1.0),
        Vector2::new((frame.w - 1.0) / 2.0, (frame.h - 1.0) / 2.0),
    ];
    let mut worst = 0.0f64;
    for pt in &points {
        let mut g = SMatrix::<f64, 6, 1>::zeros();
        for k in 0..6 {
            let (mut a, mut b) = (p0, p0);
            a[k] += step;
            b[k] -= step;
            g[k] = (dy(&a, pt) - dy(&b, pt)) / (2.0 * step);
        }
        worst = worst.max((g.transpose() * cov * g)[(0, 0)]);
    }
    Some(worst.max(0.0).sqrt())
}

fn check(what: &'static str, value: f64, limit: f64) -> Result<(), RectifyError> {
    if value <= limit && value.is_finite() {
        Ok(())
    } else {
        Err(RectifyError::Implausible { what, value, limit })
    }
}

/// The focal exponent of the second start: `f = 3⁴ (w + h)`, a field of view well under a
/// degree.
const LONG_FOCAL_G: f64 = 4.0;
/// Largest step of one Levenberg–Marquardt iteration: 0.1 rad for the five angles, 0.5 in `g`.
/// The cost has nearly flat directions (common rotations of both cameras) along which an
/// undamped step would leave the basin.
const MAX_STEP: [f64; 6] = [0.1, 0.1, 0.1, 0.1, 0.1, 0.5];

/// [`lm::minimise`] of the Sampson residuals (with the prior) over the quasi-Euclidean unknowns,
/// `g` kept inside `params.g_range`. Only the first `n_free` unknowns move (5: `g` fixed).
fn levenberg_marquardt(
    frame: &Frame,
    start: QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    params: &RectifyParams,
    prior: &Prior,
    n_free: usize,
) -> (QuasiEuclidean, usize) {
    let (p, it) = lm::minimise(
        |v: &[f64; 6], buf: &mut Vec<f64>| {
            residuals_with_prior(frame, &QuasiEuclidean::from_vec(v), left, right, prior, buf);
        },
        start.to_vec(),
        &lm::Options {
            max_iterations: params.max_iterations,
            tolerance: params.tolerance,
            n_free,
            max_step: MAX_STEP,
            last_range: params.g_range,
        },
    );
    (QuasiEuclidean::from_vec(&p), it)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::sparse::fundamental::eight_point;
    use rand::{Rng, SeedableRng};

    /// An SEM-like pair: parallel projection, tilt about an axis at `phi` (DESIGN §3), plus an
    /// in-plane rotation `rot` and a shift of the right image.
    fn sem_pair(phi_deg: f64, rot_deg: f64, n: usize) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let phi = phi_deg.to_radians();
        let (a, nv) = (
            Vector2::new(phi.cos(), phi.sin()),
            Vector2::new(-phi.sin(), phi.cos()),
        );
        let (t1, t2) = ((-3f64).to_radians(), 3f64.to_radians());
        let c = Vector2::new(320.0, 240.0);
        let rot = nalgebra::Rotation2::new(rot_deg.to_radians());
        let (mut l, mut r) = (Vec::new(), Vec::new());
        for _ in 0..n {
            let (s, rr, z) = (
                rng.random_range(-200.0..200.0),
                rng.random_range(-200.0..200.0),
                rng.random_range(-30.0..30.0),
            );
            l.push(c + a * s + nv * (rr * t1.cos() + z * t1.sin()));
            let p = a * s + nv * (rr * t2.cos() + z * t2.sin());
            r.push(c + rot * p + Vector2::new(7.0, -4.0));
        }
        (l, r)
    }

    fn check_rectified(rec: &Rectification, l: &[Vector2<f64>], r: &[Vector2<f64>]) {
        for (a, b) in l.iter().zip(r) {
            let (pa, pb) = (transform(&rec.h_left, a), transform(&rec.h_right, b));
            assert!((pa.y - pb.y).abs() < 0.05, "Δy = {}", pa.y - pb.y);
            assert!(
                pa.x >= 0.0
                    && pa.y >= 0.0
                    && pa.x < rec.canvas.0 as f64
                    && pa.y < rec.canvas.1 as f64
            );
        }
    }

    #[test]
    fn rectifies_sem_pairs_for_any_tilt_axis_with_height_along_plus_x() {
        for phi in [-90.0, 0.0, 30.0, 135.0] {
            let (l, r) = sem_pair(phi, 0.8, 60);
            let idx: Vec<usize> = (0..60).collect();
            let f = eight_point(&l, &r, &idx).unwrap();
            let rec =
                rectify(&l, &r, &f, (640, 480), Some(phi), &RectifyParams::default()).unwrap();
            check_rectified(&rec, &l, &r);
            assert!(rec.final_error_px < 0.05, "φ {phi}: {}", rec.final_error_px);
            let n = rec.n_rectified.unwrap();
            assert!(n[0] > 0.99, "φ {phi}: n on the canvas {n:?}");
            // Height sign: a point raised by z moves by +x on the canvas in the right image.
            let phi_r = phi.to_radians();
            let nv = Vector2::new(-phi_r.sin(), phi_r.cos());
            let base = Vector2::new(320.0, 240.0);
            let t = 3f64.to_radians();
            let rot = nalgebra::Rotation2::new(0.8f64.to_radians());
            let d = |z: f64| {
                let lp = base + nv * (z * (-t).sin());
                let rp = base + rot * (nv * (z * t.sin())) + Vector2::new(7.0, -4.0);
                transform(&rec.h_right, &rp).x - transform(&rec.h_left, &lp).x
            };
            assert!(d(20.0) > d(0.0) + 1.0, "φ {phi}: {} vs {}", d(20.0), d(0.0));
        }
    }

    #[test]
    fn recovers_known_homography_pair() {
        // Points already rectified, then distorted by known rotation homographies: the
        // rectification must undo them up to a common rectifying transform (Δy = 0).
        let frame = Frame { w: 640.0, h: 480.0 };
        let truth = QuasiEuclidean {
            left_y: 0.02,
            left_z: -0.03,
            right_x: 0.01,
            right_y: -0.015,
            right_z: 0.02,
            g: 0.3,
        };
        let (hl, hr) = frame.homographies(&truth);
        let (hli, hri) = (hl.try_inverse().unwrap(), hr.try_inverse().unwrap());
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (mut l, mut r) = (Vec::new(), Vec::new());
        for _ in 0..80 {
            let (x, y, d) = (
                rng.random_range(40.0..600.0),
                rng.random_range(40.0..440.0),
                rng.random_range(-30.0..30.0),
            );
            l.push(transform(&hli, &Vector2::new(x, y)));
            r.push(transform(&hri, &Vector2::new(x + d, y)));
        }
        let idx: Vec<usize> = (0..80).collect();
        let f = eight_point(&l, &r, &idx).unwrap();
        let rec = rectify(&l, &r, &f, (640, 480), None, &RectifyParams::default()).unwrap();
        eprintln!(
            "{:?} {} after {} iterations",
            rec.params, rec.final_error_px, rec.iterations
        );
        check_rectified(&rec, &l, &r);
        assert!(rec.initial_error_px > 3.0, "{}", rec.initial_error_px);
        assert!(rec.final_error_px < 0.01, "{}", rec.final_error_px);
    }

    #[test]
    fn contradicting_tilt_axis_is_refused() {
        let (l, r) = sem_pair(-90.0, 0.0, 40);
        let idx: Vec<usize> = (0..40).collect();
        let f = eight_point(&l, &r, &idx).unwrap();
        let err =
            rectify(&l, &r, &f, (640, 480), Some(0.0), &RectifyParams::default()).unwrap_err();
        // Either the optimum turns n away from the rows, or it cannot align them: both refuse.
        assert!(
            matches!(
                err,
                RectifyError::TiltAxisMismatch { .. } | RectifyError::Implausible { .. }
            ),
            "{err}"
        );
    }

    #[test]
    fn errors_are_monasses_rms_sampson_figures() {
        let (l, r) = sem_pair(-90.0, 0.8, 60);
        let idx: Vec<usize> = (0..60).collect();
        let f = eight_point(&l, &r, &idx).unwrap();
        let rec = rectify(
            &l,
            &r,
            &f,
            (640, 480),
            Some(-90.0),
            &RectifyParams::default(),
        )
        .unwrap();
        // Before: all rotations 0, H = I, F ∝ [e₁]ₓ: the Sampson error is Δy/√2 exactly.
        let dy0 = rms(l.iter().zip(&r).map(|(a, b)| a.y - b.y));
        assert!(
            (rec.initial_error_px - dy0 / 2f64.sqrt()).abs() < 1e-9 * dy0,
            "{} vs {}",
            rec.initial_error_px,
            dy0
        );
        // After: on rectified rows, again the vertical disparity over √2 (the warps are nearly
        // distance-preserving).
        assert!(rec.final_dy_rms_px > 0.0);
        let ratio = rec.final_dy_rms_px / rec.final_error_px;
        assert!((ratio - 2f64.sqrt()).abs() < 0.05, "ratio {ratio}");
    }

    #[test]
    fn wrong_matches_sliding_along_the_rows_do_not_turn_them() {
        // A flat specimen: every true match has the same parallax, so the matches leave the
        // direction of the rows open and the tilt axis (φ = −90°: rows along x) decides. Two
        // wrong matches 300 px along a line 6° off the rows, which an F through them accepts,
        // would turn the rows by 6° under least squares; the robust pass leaves them out.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let t = 3f64.to_radians();
        let rot = nalgebra::Rotation2::new(0.5f64.to_radians());
        let c = Vector2::new(320.0, 240.0);
        let (mut l, mut r) = (Vec::new(), Vec::new());
        for _ in 0..80 {
            let (s, rr) = (
                rng.random_range(-220.0..220.0),
                rng.random_range(-180.0..180.0),
            );
            let noise = Vector2::new(rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1));
            l.push(c + Vector2::new(rr * t.cos(), s));
            r.push(c + rot * Vector2::new(rr * t.cos(), s) + Vector2::new(5.0, -3.0) + noise);
        }
        let off = Vector2::new(6f64.to_radians().cos(), 6f64.to_radians().sin()) * 300.0;
        for k in [3, 17] {
            let (a, b) = (l[k], r[k]);
            l.push(a);
            r.push(b + off);
        }
        let idx: Vec<usize> = (0..l.len()).collect();
        let f = eight_point(&l, &r, &idx[..80]).unwrap();
        let turned = |p: &RectifyParams| {
            let rec = rectify(&l, &r, &f, (640, 480), Some(-90.0), p).unwrap();
            let n = rec.n_rectified.unwrap();
            (n[1].atan2(n[0]).to_degrees().abs(), rec.outliers)
        };
        let (least_squares, none) = turned(&RectifyParams {
            cauchy_scale_px: 0.0,
            ..RectifyParams::default()
        });
        assert!(none.is_empty());
        assert!(
            least_squares > 3.0,
            "least squares turned the rows by {least_squares}°"
        );
        let (robust, outliers) = turned(&RectifyParams::default());
        assert_eq!(outliers, vec![80, 81]);
        assert!(robust < 0.5, "robust: rows turned by {robust}°");
    }
}
