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

use nalgebra::{Matrix3, SMatrix, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Parameters of the rectification and of the checks that refuse implausible warps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RectifyParams {
    /// Levenberg–Marquardt iterations at most (default 200).
    pub max_iterations: usize,
    /// Stop when one step lowers the cost by less than this fraction (default 1e-9).
    pub tolerance: f64,
    /// Weight of the gauge-fixing prior on the out-of-plane rotations, px per radian (default 1;
    /// 0 is Monasse's cost exactly). See `residuals_with_prior`.
    pub rotation_prior: f64,
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
    /// (default 1.5). Above, the warp would not give the dense stage aligned rows.
    pub max_final_error_px: f64,
    /// Largest accepted angle between the tilt-axis normal `n` (when given) and the epipolar
    /// direction found, degrees (default 30).
    pub max_tilt_axis_mismatch_deg: f64,
}

impl Default for RectifyParams {
    fn default() -> Self {
        Self {
            max_iterations: 200,
            tolerance: 1e-9,
            rotation_prior: 1.0,
            g_range: (-2.0, 10.0),
            max_relative_rotation_deg: 20.0,
            max_out_of_plane_deg: 20.0,
            max_canvas_scale: 2.0,
            max_final_error_px: 1.5,
            max_tilt_axis_mismatch_deg: 30.0,
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
    /// RMS of `y_left − y_right` of the inliers before rectification (identity warps), pixels.
    pub initial_error_px: f64,
    /// RMS of `y_left − y_right` of the inliers on the rectified canvas, pixels.
    pub final_error_px: f64,
    /// RMS Sampson error of the inliers for the rectifying F at the optimum, pixels
    /// (`final_error_px / √2` when the warps are exact).
    pub final_sampson_px: f64,
    /// Levenberg–Marquardt iterations run.
    pub iterations: usize,
    /// Unit direction, on the canvas, of the tilt-axis normal `n = (−sin φ, cos φ)` of the left
    /// image at its centre, when φ was given. With `n_rectified.x > 0` (what the start
    /// enforces), a point higher above the specimen has a larger `x_right − x_left`.
    pub n_rectified: Option<[f64; 2]>,
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
        "the tilt-axis normal (φ = {tilt_axis_deg:.1}°) is {mismatch_deg:.1}° away from the epipolar direction the matches give (limit {limit_deg}°): check --tilt-axis"
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
    prior: f64,
    out: &mut Vec<f64>,
) {
    residuals(frame, q, left, right, out);
    out.extend([prior * q.left_y, prior * q.right_x, prior * q.right_y]);
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

/// Unit direction of the epipolar lines of the left image at its centre, from `F` (the line
/// joining the centre to the epipole `e`, `F e = 0`; `e` may lie at infinity).
fn epipolar_direction(f: &Matrix3<f64>, centre: Vector2<f64>) -> Option<Vector2<f64>> {
    let svd = f.svd(false, true);
    let vt = svd.v_t?;
    let k = (0..3).min_by(|&a, &b| svd.singular_values[a].total_cmp(&svd.singular_values[b]))?;
    let e = vt.row(k).transpose();
    let d = Vector2::new(e.x - centre.x * e.z, e.y - centre.y * e.z);
    let n = d.norm();
    (n > 1e-12 && n.is_finite()).then(|| d / n)
}

fn angle_deg_between_axes(a: Vector2<f64>, b: Vector2<f64>) -> f64 {
    // Angle between lines (sign-free), in [0, 90].
    a.dot(&b).abs().min(1.0).acos().to_degrees()
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

    // Start: rotate each image in its plane so that its epipolar lines become rows.
    let mut dl = epipolar_direction(f, centre).ok_or(RectifyError::Degenerate)?;
    let mut dr = epipolar_direction(&f.transpose(), centre).ok_or(RectifyError::Degenerate)?;
    let normal = tilt_axis_deg.map(|phi| {
        let p = phi.to_radians();
        Vector2::new(-p.sin(), p.cos())
    });
    if let (Some(nv), Some(phi)) = (normal, tilt_axis_deg) {
        let mismatch = angle_deg_between_axes(nv, dl);
        if mismatch > params.max_tilt_axis_mismatch_deg {
            return Err(RectifyError::TiltAxisMismatch {
                tilt_axis_deg: phi,
                mismatch_deg: mismatch,
                limit_deg: params.max_tilt_axis_mismatch_deg,
            });
        }
        if dl.dot(&nv) < 0.0 {
            dl = -dl;
        }
    } else if dl.x < 0.0 {
        dl = -dl;
    }
    if dr.dot(&dl) < 0.0 {
        dr = -dr;
    }
    let start = QuasiEuclidean {
        left_y: 0.0,
        left_z: -dl.y.atan2(dl.x),
        right_x: 0.0,
        right_y: 0.0,
        right_z: -dr.y.atan2(dr.x),
        g: 0.0,
    };

    // The focal length trades off against the out-of-plane rotations along a long shallow
    // valley of the cost; solving first with g fixed, then with all six, avoids wandering in it.
    let (q, it1) = levenberg_marquardt(&frame, start, left, right, params, 5);
    let (q, it2) = levenberg_marquardt(&frame, q, left, right, params, 6);
    let iterations = it1 + it2;

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

    let initial_error_px = rms(left.iter().zip(right).map(|(a, b)| a.y - b.y));
    let final_error_px = rms(left
        .iter()
        .zip(right)
        .map(|(a, b)| transform(&h_left, a).y - transform(&h_right, b).y));
    let mut buf = Vec::new();
    residuals(&frame, &q, left, right, &mut buf);
    let final_sampson_px = rms(buf.iter().copied());
    check(
        "final rectification error (px RMS)",
        final_error_px,
        params.max_final_error_px,
    )?;

    let n_rectified = normal.map(|nv| {
        // Image of a short step along n from the left centre.
        let a = transform(&h_left, &centre);
        let b = transform(&h_left, &(centre + nv));
        let d = b - a;
        let d = d / d.norm();
        [d.x, d.y]
    });

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
        final_sampson_px,
        iterations,
        n_rectified,
    })
}

fn check(what: &'static str, value: f64, limit: f64) -> Result<(), RectifyError> {
    if value <= limit && value.is_finite() {
        Ok(())
    } else {
        Err(RectifyError::Implausible { what, value, limit })
    }
}

/// Levenberg–Marquardt (Marquardt's diagonal damping) on the Sampson residuals, with a
/// central-difference Jacobian; `g` is kept inside `params.g_range`. Only the first `n_free`
/// unknowns move (5: `g` fixed).
fn levenberg_marquardt(
    frame: &Frame,
    start: QuasiEuclidean,
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    params: &RectifyParams,
    n_free: usize,
) -> (QuasiEuclidean, usize) {
    let clamp_g = |mut v: [f64; 6]| {
        v[5] = v[5].clamp(params.g_range.0, params.g_range.1);
        v
    };
    let mut p = clamp_g(start.to_vec());
    let mut r = Vec::new();
    let mut r_try = Vec::new();
    let mut r_plus = Vec::new();
    let mut r_minus = Vec::new();
    let cost = |v: &[f64; 6], buf: &mut Vec<f64>| {
        residuals_with_prior(
            frame,
            &QuasiEuclidean::from_vec(v),
            left,
            right,
            params.rotation_prior,
            buf,
        );
        buf.iter().map(|x| x * x).sum::<f64>()
    };
    let mut c = cost(&p, &mut r);
    let mut lambda = 1e-3;
    let mut it = 0;
    while it < params.max_iterations {
        it += 1;
        // Jacobian columns by central differences.
        let mut jtj = SMatrix::<f64, 6, 6>::zeros();
        let mut jtr = SMatrix::<f64, 6, 1>::zeros();
        let mut cols: Vec<Vec<f64>> = Vec::with_capacity(6);
        for k in 0..6 {
            if k >= n_free {
                cols.push(vec![0.0; r.len()]);
                continue;
            }
            let step = 1e-6;
            let (mut a, mut b) = (p, p);
            a[k] += step;
            b[k] -= step;
            residuals_with_prior(
                frame,
                &QuasiEuclidean::from_vec(&a),
                left,
                right,
                params.rotation_prior,
                &mut r_plus,
            );
            residuals_with_prior(
                frame,
                &QuasiEuclidean::from_vec(&b),
                left,
                right,
                params.rotation_prior,
                &mut r_minus,
            );
            cols.push(
                r_plus
                    .iter()
                    .zip(&r_minus)
                    .map(|(u, v)| (u - v) / (2.0 * step))
                    .collect(),
            );
        }
        for a in 0..6 {
            jtr[a] = cols[a].iter().zip(&r).map(|(j, e)| j * e).sum();
            for b in a..6 {
                let v: f64 = cols[a].iter().zip(&cols[b]).map(|(x, y)| x * y).sum();
                jtj[(a, b)] = v;
                jtj[(b, a)] = v;
            }
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut damped = jtj;
            for d in 0..6 {
                damped[(d, d)] += lambda * jtj[(d, d)].max(1e-12);
                if d >= n_free {
                    damped[(d, d)] = 1.0;
                }
            }
            let Some(delta) = damped.cholesky().map(|ch| ch.solve(&(-jtr))) else {
                lambda *= 10.0;
                continue;
            };
            let mut trial = p;
            for k in 0..6 {
                trial[k] += delta[k];
            }
            let trial = clamp_g(trial);
            let ct = cost(&trial, &mut r_try);
            if ct < c {
                let rel = (c - ct) / c.max(1e-300);
                p = trial;
                c = ct;
                std::mem::swap(&mut r, &mut r_try);
                lambda = (lambda / 10.0).max(1e-15);
                improved = true;
                if rel < params.tolerance {
                    return (QuasiEuclidean::from_vec(&p), it);
                }
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    (QuasiEuclidean::from_vec(&p), it)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::fundamental::eight_point;
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
        assert!(
            matches!(err, RectifyError::TiltAxisMismatch { .. }),
            "{err}"
        );
        assert!(err.to_string().contains("--tilt-axis"));
    }
}
