//! Keypoint detection: extrema of the difference of Gaussians, sub-pixel
//! refinement, contrast and edge tests (IPOL "Anatomy of the SIFT method",
//! §3: Algorithms 4–7; Lowe 2004 §4).

use rayon::prelude::*;

use super::SiftParams;
use super::scale_space::OctaveView;

/// A refined DoG extremum, before orientation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Extremum {
    /// Octave index.
    pub octave: usize,
    /// Discrete scale slot `s` in `1 ..= n_spo` after refinement.
    pub slot: usize,
    /// Position in the octave's samples (sub-sample).
    pub x_oct: f64,
    pub y_oct: f64,
    /// Blur in the octave's samples, `σ / δ_o`.
    pub sigma_oct: f64,
    /// Position in input pixels.
    pub x: f64,
    pub y: f64,
    /// Absolute scale σ in input pixels.
    pub sigma: f64,
    /// Interpolated DoG value ω (IPOL eq. 19).
    pub response: f64,
}

/// Maximum number of refinement steps (IPOL: 5).
const MAX_INTERP_STEPS: usize = 5;
/// Offsets below this in every coordinate end the refinement (IPOL: 0.6).
const MAX_OFFSET: f64 = 0.6;

/// The keypoints of octave `o` passing the contrast and edge tests, by scale slot, row and
/// column of the sample they were found at.
///
/// The DoG threshold is `params.c_dog` scaled to `n_spo` as in IPOL eq. 21:
/// `C_DoG · (2^(1/n_spo) − 1) / (2^(1/3) − 1)`, so the default 0.04/3 holds for 3 scales per octave.
#[must_use]
pub fn detect_octave(o: usize, oct: &OctaveView<'_>, params: &SiftParams) -> Vec<Extremum> {
    let n = params.n_spo as f64;
    let c_dog = params.c_dog * ((1.0 / n).exp2() - 1.0) / ((1.0f64 / 3.0).exp2() - 1.0);
    let edge_max = (params.c_edge + 1.0).powi(2) / params.c_edge;
    let (w, h) = (oct.width(), oct.height());
    let jobs: Vec<(usize, usize)> = (1..=params.n_spo)
        .flat_map(|s| (1..h.saturating_sub(1)).map(move |y| (s, y)))
        .collect();
    jobs.into_par_iter()
        .flat_map_iter(|(s, y)| {
            let mut found = Vec::new();
            let pre = (0.8 * c_dog) as f32;
            for x in 1..w - 1 {
                let v = oct.dog(s, x, y);
                if v.abs() <= pre {
                    continue;
                }
                if !is_strict_extremum(v, oct, s, x, y) {
                    continue;
                }
                if let Some(e) = refine(oct, params, o, s, x, y, c_dog, edge_max) {
                    found.push(e);
                }
            }
            found
        })
        .collect()
}

/// `v` is strictly larger (or strictly smaller) than its 26 neighbours.
/// `v = w_s(x, y)`; its neighbours are those of `w_{s−1}`, `w_s` and `w_{s+1}`.
fn is_strict_extremum(v: f32, oct: &OctaveView<'_>, s: usize, x: usize, y: usize) -> bool {
    let mut is_max = true;
    let mut is_min = true;
    for l in 0..3 {
        for yy in y - 1..=y + 1 {
            for xx in x - 1..=x + 1 {
                if l == 1 && xx == x && yy == y {
                    continue;
                }
                let u = oct.dog(s + l - 1, xx, yy);
                is_max &= v > u;
                is_min &= v < u;
                if !is_max && !is_min {
                    return false;
                }
            }
        }
    }
    is_max || is_min
}

/// Quadratic refinement (IPOL Algorithm 5), then the contrast test |ω| ≥ C_DoG and the
/// edge test tr(H)²/det(H) < (C_edge + 1)²/C_edge on the spatial Hessian (Lowe eq. 12–13).
#[allow(clippy::too_many_arguments)]
fn refine(
    oct: &OctaveView<'_>,
    params: &SiftParams,
    o: usize,
    s0: usize,
    x0: usize,
    y0: usize,
    c_dog: f64,
    edge_max: f64,
) -> Option<Extremum> {
    let (w, h) = (oct.width(), oct.height());
    let (mut s, mut x, mut y) = (s0, x0, y0);
    for _ in 0..MAX_INTERP_STEPS {
        let d = |ds: isize, dx: isize, dy: isize| -> f64 {
            let ss_ = (s as isize + ds) as usize;
            let xx = (x as isize + dx) as usize;
            let yy = (y as isize + dy) as usize;
            f64::from(oct.dog(ss_, xx, yy))
        };
        let v = d(0, 0, 0);
        // Gradient and Hessian by central differences, variables ordered (s, x, y).
        let g = [
            0.5 * (d(1, 0, 0) - d(-1, 0, 0)),
            0.5 * (d(0, 1, 0) - d(0, -1, 0)),
            0.5 * (d(0, 0, 1) - d(0, 0, -1)),
        ];
        let hss = d(1, 0, 0) + d(-1, 0, 0) - 2.0 * v;
        let hxx = d(0, 1, 0) + d(0, -1, 0) - 2.0 * v;
        let hyy = d(0, 0, 1) + d(0, 0, -1) - 2.0 * v;
        let hsx = 0.25 * (d(1, 1, 0) - d(1, -1, 0) - d(-1, 1, 0) + d(-1, -1, 0));
        let hsy = 0.25 * (d(1, 0, 1) - d(1, 0, -1) - d(-1, 0, 1) + d(-1, 0, -1));
        let hxy = 0.25 * (d(0, 1, 1) - d(0, 1, -1) - d(0, -1, 1) + d(0, -1, -1));
        let hm = nalgebra::Matrix3::new(hss, hsx, hsy, hsx, hxx, hxy, hsy, hxy, hyy);
        let inv = hm.try_inverse()?;
        let alpha = -(inv * nalgebra::Vector3::from(g));
        if alpha.iter().all(|a| a.abs() < MAX_OFFSET) {
            let response = v + 0.5 * (g[0] * alpha[0] + g[1] * alpha[1] + g[2] * alpha[2]);
            if response.abs() < c_dog {
                return None;
            }
            let det = hxx * hyy - hxy * hxy;
            if det <= 0.0 || (hxx + hyy).powi(2) / det >= edge_max {
                return None;
            }
            let delta = oct.geometry.delta;
            let sigma_oct = params.sigma_min / params.delta_min
                * ((s as f64 + alpha[0]) / params.n_spo as f64).exp2();
            let x_oct = x as f64 + alpha[1];
            let y_oct = y as f64 + alpha[2];
            return Some(Extremum {
                octave: o,
                slot: s,
                x_oct,
                y_oct,
                sigma_oct,
                x: x_oct * delta,
                y: y_oct * delta,
                sigma: sigma_oct * delta,
                response,
            });
        }
        // Move to the neighbouring sample the offset points to and try again.
        let step = |a: f64| -> isize {
            #[allow(clippy::cast_possible_truncation)]
            let r = a.round() as isize;
            r.clamp(-1, 1)
        };
        let ns = s as isize + step(alpha[0]);
        let nx = x as isize + step(alpha[1]);
        let ny = y as isize + step(alpha[2]);
        if ns < 1
            || ns > params.n_spo as isize
            || nx < 1
            || ny < 1
            || nx >= w as isize - 1
            || ny >= h as isize - 1
        {
            return None;
        }
        #[allow(clippy::cast_sign_loss)]
        {
            (s, x, y) = (ns as usize, nx as usize, ny as usize);
        }
    }
    None
}
