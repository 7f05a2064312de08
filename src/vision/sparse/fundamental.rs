//! Fundamental matrices: the projective 7-point minimal solver and normalised 8-point
//! least squares (Hartley & Zisserman, 2nd ed., §11.1–11.2), the affine fundamental matrix
//! (H&Z §14.2, exact for parallel projection such as SEM), and the residuals ORSA and the
//! rectification use.
//!
//! Convention: `F` relates left point `x` and right point `x'` (homogeneous, pixels) by
//! `x'ᵀ F x = 0`; `F x` is the epipolar line of `x` in the right image.

use nalgebra::{Matrix3, SMatrix, SymmetricEigen, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Which fundamental-matrix model ORSA fits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FundamentalModel {
    /// General projective F, 7 degrees of freedom, 7-point minimal solver (the paper's choice).
    Projective,
    /// Affine F (parallel projection, the exact model of SEM), 4 degrees of freedom,
    /// 4-point minimal solver: `F = [[0,0,a],[0,0,b],[c,d,e]]`.
    Affine,
}

impl FundamentalModel {
    /// Points in a minimal sample.
    #[must_use]
    pub fn sample_size(self) -> usize {
        match self {
            Self::Projective => 7,
            Self::Affine => 4,
        }
    }

    /// Most models a minimal sample can give (the 7-point cubic has up to 3 real roots).
    #[must_use]
    pub fn max_models(self) -> usize {
        match self {
            Self::Projective => 3,
            Self::Affine => 1,
        }
    }

    /// Minimal solver on the points `idx` of `left`/`right`.
    #[must_use]
    pub fn fit_minimal(
        self,
        left: &[Vector2<f64>],
        right: &[Vector2<f64>],
        idx: &[usize],
    ) -> Vec<Matrix3<f64>> {
        match self {
            Self::Projective => seven_point(left, right, idx),
            Self::Affine => affine_fit(left, right, idx).into_iter().collect(),
        }
    }

    /// Least-squares fit on many points (normalised 8-point with rank 2 enforced, or the
    /// affine Gold Standard), `None` when the points do not determine a model.
    #[must_use]
    pub fn fit_least_squares(
        self,
        left: &[Vector2<f64>],
        right: &[Vector2<f64>],
        idx: &[usize],
    ) -> Option<Matrix3<f64>> {
        match self {
            Self::Projective => eight_point(left, right, idx),
            Self::Affine => affine_fit(left, right, idx),
        }
    }
}

/// Hartley's normalisation: centroid to the origin, mean distance √2.
/// Returns `T` with `x̂ = T x`.
fn normalisation(points: impl Iterator<Item = Vector2<f64>> + Clone) -> Matrix3<f64> {
    let n = points.clone().count().max(1) as f64;
    let c = points.clone().fold(Vector2::zeros(), |a, p| a + p) / n;
    let mean_dist = points.map(|p| (p - c).norm()).sum::<f64>() / n;
    let s = if mean_dist > 0.0 {
        std::f64::consts::SQRT_2 / mean_dist
    } else {
        1.0
    };
    Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0)
}

fn apply(t: &Matrix3<f64>, p: &Vector2<f64>) -> Vector2<f64> {
    Vector2::new(t[(0, 0)] * p.x + t[(0, 2)], t[(1, 1)] * p.y + t[(1, 2)])
}

/// Row of the linear system `x'ᵀ F x = 0` in the entries of F (row-major).
fn epipolar_row(x: &Vector2<f64>, xp: &Vector2<f64>) -> [f64; 9] {
    [
        xp.x * x.x,
        xp.x * x.y,
        xp.x,
        xp.y * x.x,
        xp.y * x.y,
        xp.y,
        x.x,
        x.y,
        1.0,
    ]
}

/// The eigenvectors of `AᵀA` for its two smallest eigenvalues (the null space of A).
fn smallest_two(ata: SMatrix<f64, 9, 9>) -> (SMatrix<f64, 9, 1>, SMatrix<f64, 9, 1>) {
    let eig = SymmetricEigen::new(ata);
    let mut order: Vec<usize> = (0..9).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    (
        eig.eigenvectors.column(order[0]).into_owned(),
        eig.eigenvectors.column(order[1]).into_owned(),
    )
}

fn to_matrix(v: &SMatrix<f64, 9, 1>) -> Matrix3<f64> {
    Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8])
}

/// The 7-point algorithm (H&Z §11.1.2): up to three F of rank 2 through 7 matches.
#[must_use]
pub fn seven_point(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    idx: &[usize],
) -> Vec<Matrix3<f64>> {
    let t1 = normalisation(idx.iter().map(|&i| left[i]));
    let t2 = normalisation(idx.iter().map(|&i| right[i]));
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let r = SMatrix::<f64, 1, 9>::from_row_slice(&epipolar_row(
            &apply(&t1, &left[i]),
            &apply(&t2, &right[i]),
        ));
        ata += r.transpose() * r;
    }
    let (f1, f2) = smallest_two(ata);
    let (f1, f2) = (to_matrix(&f1), to_matrix(&f2));
    // det(f2 + a (f1 − f2)) is a cubic in a: recover its coefficients from four values.
    let d = |a: f64| (f2 + (f1 - f2) * a).determinant();
    let (d0, d1, dm1, d2) = (d(0.0), d(1.0), d(-1.0), d(2.0));
    let c0 = d0;
    let c2 = 0.5 * (d1 + dm1) - d0;
    let c3 = (d2 - 2.0 * d1 + d0 - 2.0 * c2) / 6.0;
    let c1 = d1 - d0 - c2 - c3;
    solve_cubic(c3, c2, c1, c0)
        .into_iter()
        .map(|a| {
            let f = t2.transpose() * (f2 + (f1 - f2) * a) * t1;
            f / f.norm()
        })
        .collect()
}

/// Real roots of `c3 a³ + c2 a² + c1 a + c0` (degenerating gracefully to lower degrees).
fn solve_cubic(c3: f64, c2: f64, c1: f64, c0: f64) -> Vec<f64> {
    let scale = c3.abs().max(c2.abs()).max(c1.abs()).max(c0.abs());
    if scale == 0.0 {
        return Vec::new();
    }
    if c3.abs() < 1e-12 * scale {
        if c2.abs() < 1e-12 * scale {
            return if c1 == 0.0 {
                Vec::new()
            } else {
                vec![-c0 / c1]
            };
        }
        let disc = c1 * c1 - 4.0 * c2 * c0;
        if disc < 0.0 {
            return Vec::new();
        }
        let s = disc.sqrt();
        return vec![(-c1 + s) / (2.0 * c2), (-c1 - s) / (2.0 * c2)];
    }
    // Depressed cubic t³ + p t + q with a = t − b/3.
    let (b, c, d) = (c2 / c3, c1 / c3, c0 / c3);
    let p = c - b * b / 3.0;
    let q = 2.0 * b * b * b / 27.0 - b * c / 3.0 + d;
    let disc = q * q / 4.0 + p * p * p / 27.0;
    let shift = -b / 3.0;
    let mut roots = if disc > 0.0 {
        let s = disc.sqrt();
        vec![(-q / 2.0 + s).cbrt() + (-q / 2.0 - s).cbrt() + shift]
    } else {
        // Three real roots (trigonometric form).
        let r = (-p / 3.0).max(0.0).sqrt();
        if r == 0.0 {
            vec![shift]
        } else {
            let phi = (3.0 * q / (2.0 * p * r)).clamp(-1.0, 1.0).acos() / 3.0;
            (0..3)
                .map(|k| {
                    2.0 * r * (phi - 2.0 * std::f64::consts::PI * f64::from(k) / 3.0).cos() + shift
                })
                .collect()
        }
    };
    // One Newton step each for accuracy.
    for a in &mut roots {
        let f = ((c3 * *a + c2) * *a + c1) * *a + c0;
        let df = (3.0 * c3 * *a + 2.0 * c2) * *a + c1;
        if df != 0.0 {
            *a -= f / df;
        }
    }
    roots
}

/// Normalised 8-point least squares with rank 2 enforced (H&Z Algorithm 11.1).
#[must_use]
pub fn eight_point(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    idx: &[usize],
) -> Option<Matrix3<f64>> {
    if idx.len() < 8 {
        return None;
    }
    let t1 = normalisation(idx.iter().map(|&i| left[i]));
    let t2 = normalisation(idx.iter().map(|&i| right[i]));
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let r = SMatrix::<f64, 1, 9>::from_row_slice(&epipolar_row(
            &apply(&t1, &left[i]),
            &apply(&t2, &right[i]),
        ));
        ata += r.transpose() * r;
    }
    let (f, _) = smallest_two(ata);
    let svd = to_matrix(&f).svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut s = svd.singular_values;
    s[2] = 0.0;
    let f = t2.transpose() * (u * Matrix3::from_diagonal(&s) * vt) * t1;
    let n = f.norm();
    (n > 0.0 && n.is_finite()).then(|| f / n)
}

/// Affine fundamental matrix by orthogonal regression on `(x', y', x, y)` (H&Z Algorithm
/// 14.1, the Gold Standard under isotropic noise); exact through 4 points in general position.
#[must_use]
pub fn affine_fit(
    left: &[Vector2<f64>],
    right: &[Vector2<f64>],
    idx: &[usize],
) -> Option<Matrix3<f64>> {
    if idx.len() < 4 {
        return None;
    }
    let n = idx.len() as f64;
    let row = |i: usize| nalgebra::Vector4::new(right[i].x, right[i].y, left[i].x, left[i].y);
    let mean = idx
        .iter()
        .fold(nalgebra::Vector4::zeros(), |a, &i| a + row(i))
        / n;
    let mut cov = nalgebra::Matrix4::zeros();
    for &i in idx {
        let d = row(i) - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov);
    let k = (0..4).min_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]))?;
    // Degenerate when the two smallest eigenvalues coincide (the normal is not determined).
    let mut ev: Vec<f64> = eig.eigenvalues.iter().copied().collect();
    ev.sort_by(f64::total_cmp);
    if ev[1] <= 1e-9 * ev[3].max(1e-300) {
        return None;
    }
    let v = eig.eigenvectors.column(k);
    let e = -v.dot(&mean);
    let f = Matrix3::new(0.0, 0.0, v[0], 0.0, 0.0, v[1], v[2], v[3], e);
    Some(f / f.norm())
}

fn homog(p: &Vector2<f64>) -> Vector3<f64> {
    Vector3::new(p.x, p.y, 1.0)
}

/// Distances (pixels) of `x'` to the epipolar line `F x` and of `x` to `Fᵀ x'`.
#[must_use]
pub fn epipolar_distances(f: &Matrix3<f64>, x: &Vector2<f64>, xp: &Vector2<f64>) -> (f64, f64) {
    let (xh, xph) = (homog(x), homog(xp));
    let l_right = f * xh;
    let l_left = f.transpose() * xph;
    let c = xph.dot(&l_right).abs();
    let nr = l_right.x.hypot(l_right.y);
    let nl = l_left.x.hypot(l_left.y);
    let dr = if nr > 0.0 { c / nr } else { f64::INFINITY };
    let dl = if nl > 0.0 { c / nl } else { f64::INFINITY };
    (dl, dr)
}

/// The larger of the two point-to-epipolar-line distances: ORSA's residual (IPOL 2016).
#[must_use]
pub fn symmetric_epipolar_error(f: &Matrix3<f64>, x: &Vector2<f64>, xp: &Vector2<f64>) -> f64 {
    let (a, b) = epipolar_distances(f, x, xp);
    a.max(b)
}

/// The Sampson error (H&Z eq. 11.9), the first-order geometric distance of the match to
/// the variety `x'ᵀ F x = 0`, in pixels (square root of H&Z's squared form).
#[must_use]
pub fn sampson_error(f: &Matrix3<f64>, x: &Vector2<f64>, xp: &Vector2<f64>) -> f64 {
    let (xh, xph) = (homog(x), homog(xp));
    let fx = f * xh;
    let ftx = f.transpose() * xph;
    let c = xph.dot(&fx);
    let den = fx.x * fx.x + fx.y * fx.y + ftx.x * ftx.x + ftx.y * ftx.y;
    if den > 0.0 {
        c.abs() / den.sqrt()
    } else {
        f64::INFINITY
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Matches from two projective cameras looking at random 3-D points.
    pub(crate) fn projective_pair(n: usize, seed: u64) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let k = Matrix3::new(800.0, 0.0, 320.0, 0.0, 800.0, 240.0, 0.0, 0.0, 1.0);
        let r = nalgebra::Rotation3::from_euler_angles(0.05, 0.2, 0.03);
        let t = Vector3::new(-1.0, 0.1, 0.05);
        let mut l = Vec::new();
        let mut rr = Vec::new();
        for _ in 0..n {
            let p = Vector3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(6.0..10.0),
            );
            let a = k * p;
            let b = k * (r * p + t);
            l.push(Vector2::new(a.x / a.z, a.y / a.z));
            rr.push(Vector2::new(b.x / b.z, b.y / b.z));
        }
        (l, rr)
    }

    /// Matches from two parallel projections (SEM): tilt about the image y axis.
    pub(crate) fn affine_pair(n: usize, seed: u64) -> (Vec<Vector2<f64>>, Vec<Vector2<f64>>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let t = 6f64.to_radians();
        let mut l = Vec::new();
        let mut r = Vec::new();
        for _ in 0..n {
            let (s, x, z) = (
                rng.random_range(0.0..480.0),
                rng.random_range(-300.0..300.0),
                rng.random_range(-40.0..40.0),
            );
            l.push(Vector2::new(320.0 + x, s));
            r.push(Vector2::new(
                320.0 + x * t.cos() + z * t.sin() + 12.0,
                s - 5.0 + 0.01 * x,
            ));
        }
        (l, r)
    }

    #[test]
    fn seven_point_finds_the_true_f() {
        let (l, r) = projective_pair(20, 1);
        let idx: Vec<usize> = (0..7).collect();
        let fs = seven_point(&l, &r, &idx);
        assert!(!fs.is_empty());
        // One of the solutions explains all 20 matches.
        let best = fs
            .iter()
            .map(|f| {
                (0..20)
                    .map(|i| symmetric_epipolar_error(f, &l[i], &r[i]))
                    .fold(0.0, f64::max)
            })
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-6, "max residual {best}");
    }

    #[test]
    fn eight_point_and_affine_fit_exact_data() {
        let (l, r) = projective_pair(30, 2);
        let idx: Vec<usize> = (0..30).collect();
        let f = eight_point(&l, &r, &idx).unwrap();
        assert!(idx.iter().all(|&i| sampson_error(&f, &l[i], &r[i]) < 1e-6));
        assert!(f.determinant().abs() < 1e-12);

        let (l, r) = affine_pair(30, 3);
        let fa = affine_fit(&l, &r, &[0, 1, 2, 3]).unwrap();
        assert!(
            idx.iter()
                .all(|&i| symmetric_epipolar_error(&fa, &l[i], &r[i]) < 1e-6)
        );
    }

    #[test]
    fn cubic_roots() {
        // (a − 1)(a + 2)(a − 3) = a³ − 2a² − 5a + 6
        let mut r = solve_cubic(1.0, -2.0, -5.0, 6.0);
        r.sort_by(f64::total_cmp);
        assert!(
            (r[0] + 2.0).abs() < 1e-9 && (r[1] - 1.0).abs() < 1e-9 && (r[2] - 3.0).abs() < 1e-9
        );
        assert_eq!(solve_cubic(1.0, 0.0, 1.0, 0.0).len(), 1);
    }

    #[test]
    fn distances_are_in_pixels() {
        // F of a pure horizontal translation: epipolar lines are rows, x'ᵀ F x = y − y'.
        let f = Matrix3::new(0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0);
        let (dl, dr) = epipolar_distances(&f, &Vector2::new(10.0, 5.0), &Vector2::new(40.0, 8.0));
        assert!((dl - 3.0).abs() < 1e-12 && (dr - 3.0).abs() < 1e-12);
        assert!(
            (sampson_error(&f, &Vector2::new(10.0, 5.0), &Vector2::new(40.0, 8.0))
                - 3.0 / 2f64.sqrt())
            .abs()
                < 1e-12
        );
    }
}
