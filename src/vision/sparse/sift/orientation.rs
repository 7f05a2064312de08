//! Reference orientations from a histogram of gradient directions (IPOL
//! "Anatomy of the SIFT method" §4.1, Algorithm 11; Lowe 2004 §5).

use std::f64::consts::TAU;

use super::SiftParams;
use super::detector::Extremum;
#[cfg(test)]
use crate::vision::Image;

/// `atan2(y, x)` to within 2.1e-4 rad (0.012°), several times faster than the libm one; the
/// descriptor evaluates it for thousands of samples per keypoint.
#[must_use]
#[inline]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_2, PI};
    let (ax, ay) = (x.abs(), y.abs());
    let (mn, mx) = if ax < ay { (ax, ay) } else { (ay, ax) };
    if mx == 0.0 {
        return 0.0;
    }
    let a = mn / mx;
    let s = a * a;
    let mut r = ((-0.046_496_47 * s + 0.159_314_2) * s - 0.327_622_76) * s * a + a;
    if ay > ax {
        r = FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = PI - r;
    }
    if y < 0.0 { -r } else { r }
}

/// Central-difference gradient of one scale-space image, as norm and direction
/// (radians in `(−π, π]`, from +x towards +y), computed once for all the keypoints
/// that use the image, into planes its caller owns. Border samples hold 0.
#[derive(Debug, Clone, Copy)]
pub struct GradField<'a> {
    pub width: usize,
    pub height: usize,
    pub mag: &'a [f32],
    pub ori: &'a [f32],
}

impl<'a> GradField<'a> {
    /// The gradient of the `w × h` plane `img`, written into `mag` and `ori` (`w·h` samples each).
    #[must_use]
    pub fn new(
        img: &[f32],
        (w, h): (usize, usize),
        mag: &'a mut [f32],
        ori: &'a mut [f32],
    ) -> Self {
        use rayon::prelude::*;
        if w >= 3 && h >= 3 {
            mag.par_chunks_mut(w)
                .zip(ori.par_chunks_mut(w))
                .enumerate()
                .for_each(|(y, (m, o))| {
                    if y == 0 || y == h - 1 {
                        m.fill(0.0);
                        o.fill(0.0);
                        return;
                    }
                    let row = |y: usize| &img[y * w..(y + 1) * w];
                    let (up, row, down) = (row(y - 1), row(y), row(y + 1));
                    (m[0], o[0], m[w - 1], o[w - 1]) = (0.0, 0.0, 0.0, 0.0);
                    for x in 1..w - 1 {
                        let gx = 0.5 * (row[x + 1] - row[x - 1]);
                        let gy = 0.5 * (down[x] - up[x]);
                        // No over/underflow risk for samples in [0, 1]: plain sqrt, not hypot.
                        m[x] = (gx * gx + gy * gy).sqrt();
                        o[x] = fast_atan2(gy, gx);
                    }
                });
        } else {
            mag.fill(0.0);
            ori.fill(0.0);
        }
        Self {
            width: w,
            height: h,
            mag,
            ori,
        }
    }

    /// `(norm, direction)` at sample `(x, y)`.
    #[must_use]
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> (f32, f32) {
        let i = y * self.width + x;
        (self.mag[i], self.ori[i])
    }
}

/// The dominant orientations (radians, in `[0, 2π)`, x right, y down) of one extremum.
///
/// Gradients within `3·λ_ori·σ` are accumulated, weighted by their norm and a Gaussian of
/// standard deviation `λ_ori·σ`, into `n_bins` bins; the histogram is smoothed six times by a
/// circular box of width 3; every local maximum above `t·max` gives an orientation, refined by a
/// parabola through three bins (IPOL eq. 29–30). Empty when the patch leaves the image.
#[must_use]
pub fn orientations(grad: &GradField<'_>, e: &Extremum, params: &SiftParams) -> Vec<f64> {
    let n_bins = params.n_bins;
    let sig_w = params.lambda_ori * e.sigma_oct;
    let radius = 3.0 * sig_w;
    let (w, h) = (grad.width, grad.height);
    let (x_min, x_max) = ((e.x_oct - radius).ceil(), (e.x_oct + radius).floor());
    let (y_min, y_max) = ((e.y_oct - radius).ceil(), (e.y_oct + radius).floor());
    if x_min < 1.0 || y_min < 1.0 || x_max > (w - 2) as f64 || y_max > (h - 2) as f64 {
        return Vec::new();
    }
    let mut hist = vec![0.0f64; n_bins];
    let inv_2s2 = 1.0 / (2.0 * sig_w * sig_w);
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let (x0, x1, y0, y1) = (
        x_min as usize,
        x_max as usize,
        y_min as usize,
        y_max as usize,
    );
    let bins_per_rad = n_bins as f64 / TAU;
    // Separable Gaussian window, tabulated per column.
    let wcol: Vec<f64> = (x0..=x1)
        .map(|x| (-(x as f64 - e.x_oct).powi(2) * inv_2s2).exp())
        .collect();
    for y in y0..=y1 {
        let dy = y as f64 - e.y_oct;
        let wrow = (-dy * dy * inv_2s2).exp();
        for (x, wc) in (x0..=x1).zip(&wcol) {
            let (mag, ori) = grad.at(x, y);
            let weight = wrow * wc * f64::from(mag);
            let theta = f64::from(ori).rem_euclid(TAU);
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let bin = ((theta * bins_per_rad + 0.5).floor() as usize) % n_bins;
            hist[bin] += weight;
        }
    }
    for _ in 0..6 {
        let prev = hist.clone();
        for k in 0..n_bins {
            hist[k] = (prev[(k + n_bins - 1) % n_bins] + prev[k] + prev[(k + 1) % n_bins]) / 3.0;
        }
    }
    let max = hist.iter().copied().fold(0.0, f64::max);
    if max <= 0.0 {
        return Vec::new();
    }
    let mut out = Vec::new();
    for k in 0..n_bins {
        let (hm, h0, hp) = (
            hist[(k + n_bins - 1) % n_bins],
            hist[k],
            hist[(k + 1) % n_bins],
        );
        if h0 > hm && h0 > hp && h0 >= params.t_ori * max {
            let offset = (hm - hp) / (2.0 * (hm - 2.0 * h0 + hp));
            out.push(((k as f64 + offset) / bins_per_rad).rem_euclid(TAU));
        }
    }
    out
}

/// `f` of the gradient field of `img`, in planes of its own.
#[cfg(test)]
pub(crate) fn with_field<R>(img: &Image, f: impl FnOnce(&GradField<'_>) -> R) -> R {
    let (mut mag, mut ori) = (vec![f32::NAN; img.len()], vec![f32::NAN; img.len()]);
    f(&GradField::new(
        img.data(),
        img.dimensions(),
        &mut mag,
        &mut ori,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_atan2_agrees_with_libm() {
        for i in 0..720 {
            let a = (i as f32).to_radians() * 0.5 - 3.1;
            for r in [1e-3f32, 1.0, 50.0] {
                let (y, x) = (r * a.sin(), r * a.cos());
                assert!((fast_atan2(y, x) - y.atan2(x)).abs() < 3e-4, "angle {a}");
            }
        }
        assert_eq!(fast_atan2(0.0, 0.0), 0.0);
    }

    #[test]
    fn ramp_orientation_points_uphill() {
        // Intensity grows along the direction 30° (x right, y down).
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        let img = Image::from_fn(41, 41, |x, y| (0.01 * (c * x as f64 + s * y as f64)) as f32);
        let e = Extremum {
            octave: 0,
            slot: 1,
            x_oct: 20.0,
            y_oct: 20.0,
            sigma_oct: 2.0,
            x: 20.0,
            y: 20.0,
            sigma: 2.0,
            response: 0.1,
        };
        let o = with_field(&img, |g| orientations(g, &e, &SiftParams::default()));
        assert_eq!(o.len(), 1);
        assert!((o[0] - 30f64.to_radians()).abs() < 0.02, "{o:?}");
    }
}
