//! The SIFT descriptor: a 4×4 array of 8-bin gradient-orientation histograms in the
//! keypoint's frame, normalised, clipped at 0.2 and quantised to bytes (IPOL "Anatomy of
//! the SIFT method" §4.2, Algorithm 12; Lowe 2004 §6).

use std::f64::consts::TAU;

use super::SiftParams;
use super::detector::Extremum;
use super::orientation::GradField;

/// Length of the descriptor with the default 4×4×8 layout.
pub const DESCRIPTOR_LEN: usize = 128;

/// Descriptor of the extremum `e` at reference orientation `theta` (radians), or `None`
/// when its patch of half-width `√2·λ_descr·σ·(n_hist+1)/n_hist` leaves the image.
///
/// Every sample with normalised, rotated coordinates `(x̂, ŷ)` in
/// `[−λ_descr(n_hist+1)/n_hist, +…]²` adds its gradient norm, weighted by a Gaussian of
/// standard deviation `λ_descr` (in units of σ), to the spatial and angular bins around it with
/// trilinear weights (IPOL eq. 31–33). Bins are laid out `[x bin][y bin][orientation]`.
#[must_use]
pub fn describe(
    grad: &GradField<'_>,
    e: &Extremum,
    theta: f64,
    params: &SiftParams,
) -> Option<[u8; DESCRIPTOR_LEN]> {
    let n_hist = params.n_hist;
    let n_ori = params.n_ori;
    debug_assert_eq!(n_hist * n_hist * n_ori, DESCRIPTOR_LEN);
    let lambda = params.lambda_descr;
    let sigma = e.sigma_oct;
    let half = lambda * (n_hist + 1) as f64 / n_hist as f64;
    let radius = std::f64::consts::SQRT_2 * half * sigma;
    let (w, h) = (grad.width, grad.height);
    let (x_min, x_max) = ((e.x_oct - radius).ceil(), (e.x_oct + radius).floor());
    let (y_min, y_max) = ((e.y_oct - radius).ceil(), (e.y_oct + radius).floor());
    if x_min < 1.0 || y_min < 1.0 || x_max > (w - 2) as f64 || y_max > (h - 2) as f64 {
        return None;
    }
    #[allow(clippy::cast_possible_truncation)]
    let (sin_t, cos_t) = ((theta.sin() / sigma) as f32, (theta.cos() / sigma) as f32);
    #[allow(clippy::cast_possible_truncation)]
    let theta32 = theta as f32;
    let mut hist = [0.0f32; DESCRIPTOR_LEN];
    let inv_2l2 = 1.0 / (2.0 * lambda * lambda);
    // Spatial bin width 2λ/n_hist in units of σ; bin i has centre (i − (n_hist − 1)/2)·width.
    #[allow(clippy::cast_possible_truncation)]
    let (inv_bin, centre, half32, ori_per_rad) = (
        (n_hist as f64 / (2.0 * lambda)) as f32,
        ((n_hist as f64 - 1.0) / 2.0) as f32,
        half as f32,
        (n_ori as f64 / TAU) as f32,
    );
    let tau = std::f32::consts::TAU;
    let nh = n_hist as isize;
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let (x0, x1, y0, y1) = (
        x_min as usize,
        x_max as usize,
        y_min as usize,
        y_max as usize,
    );
    // The Gaussian weight is rotation invariant and separable: tabulate it per column and row.
    #[allow(clippy::cast_possible_truncation)]
    let gauss = |d: f64| (-(d * d) / (sigma * sigma) * inv_2l2).exp() as f32;
    let wcol: Vec<f32> = (x0..=x1).map(|x| gauss(x as f64 - e.x_oct)).collect();
    for y in y0..=y1 {
        let dy = y as f64 - e.y_oct;
        let wrow = gauss(dy);
        let row_start = y * grad.width;
        let mag_row = &grad.mag[row_start + x0..=row_start + x1];
        let ori_row = &grad.ori[row_start + x0..=row_start + x1];
        #[allow(clippy::cast_possible_truncation)]
        let (dx0, dy32) = ((x0 as f64 - e.x_oct) as f32, dy as f32);
        for (i, ((&mag, &ori), &wc)) in mag_row.iter().zip(ori_row).zip(&wcol).enumerate() {
            #[allow(clippy::cast_precision_loss)]
            let dx = dx0 + i as f32;
            let xh = cos_t * dx + sin_t * dy32;
            let yh = -sin_t * dx + cos_t * dy32;
            if xh.abs() >= half32 || yh.abs() >= half32 || mag == 0.0 {
                continue;
            }
            let weight = wrow * wc * mag;
            // ori ∈ (−π, π], θ ∈ [0, 2π): the difference lies in (−3π, π].
            let mut ang = ori - theta32;
            while ang < 0.0 {
                ang += tau;
            }
            // Continuous bin coordinates: centres at integers.
            let bx = xh * inv_bin + centre;
            let by = yh * inv_bin + centre;
            let bo = ang * ori_per_rad;
            let (ix, iy, io) = (floor_small(bx), floor_small(by), floor_small(bo));
            #[allow(clippy::cast_precision_loss)]
            let (fx, fy, fo) = (bx - ix as f32, by - iy as f32, bo - io as f32);
            #[allow(clippy::cast_sign_loss)]
            let (o0, o1) = ((io as usize) % n_ori, (io as usize + 1) % n_ori);
            for (cx, wx) in [(ix, 1.0 - fx), (ix + 1, fx)] {
                if cx < 0 || cx >= nh {
                    continue;
                }
                for (cy, wy) in [(iy, 1.0 - fy), (iy + 1, fy)] {
                    if cy < 0 || cy >= nh {
                        continue;
                    }
                    #[allow(clippy::cast_sign_loss)]
                    let base = (cx as usize * n_hist + cy as usize) * n_ori;
                    let w = weight * wx * wy;
                    hist[base + o0] += w * (1.0 - fo);
                    hist[base + o1] += w * fo;
                }
            }
        }
    }
    Some(normalise_and_quantise(&mut hist))
}

/// `⌊x⌋` for the small values of bin coordinates, without a libm call (the baseline x86-64
/// target has no rounding instruction, and `floorf` was a tenth of the descriptor time).
#[inline]
fn floor_small(x: f32) -> isize {
    #[allow(clippy::cast_possible_truncation)]
    let t = x as isize;
    #[allow(clippy::cast_precision_loss)]
    if (t as f32) > x { t - 1 } else { t }
}

/// Normalise, clip every bin at 0.2 of the norm, renormalise and quantise as
/// `min(⌊512·f⌋, 255)` (IPOL Algorithm 12, last lines).
fn normalise_and_quantise(hist: &mut [f32; DESCRIPTOR_LEN]) -> [u8; DESCRIPTOR_LEN] {
    let norm = hist.iter().map(|v| v * v).sum::<f32>().sqrt();
    let mut out = [0u8; DESCRIPTOR_LEN];
    if norm <= 0.0 {
        return out;
    }
    let clip = 0.2 * norm;
    hist.iter_mut().for_each(|v| *v = v.min(clip));
    let norm = hist.iter().map(|v| v * v).sum::<f32>().sqrt();
    for (o, v) in out.iter_mut().zip(hist.iter()) {
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let q = (512.0 * v / norm).floor().min(255.0) as u8;
        *o = q;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::Image;
    use crate::vision::sparse::sift::orientation::with_field;

    fn extremum(x: f64, y: f64, sigma: f64) -> Extremum {
        Extremum {
            octave: 0,
            slot: 1,
            x_oct: x,
            y_oct: y,
            sigma_oct: sigma,
            x,
            y,
            sigma,
            response: 0.1,
        }
    }

    #[test]
    fn floor_small_is_floor() {
        for x in [-1.5f32, -1.0, -0.2, 0.0, 0.3, 2.0, 2.7, 7.999] {
            assert_eq!(floor_small(x), x.floor() as isize, "{x}");
        }
    }

    #[test]
    fn clipping_caps_dominant_bin() {
        let mut h = [0.0f32; DESCRIPTOR_LEN];
        h[0] = 10.0;
        h[1] = 1.0;
        let q = normalise_and_quantise(&mut h);
        // After clipping bin 0 to 0.2·|h| ≈ 2.01, it is ≈ 0.895 of the new norm → 255 (saturated).
        assert_eq!(q[0], 255);
        assert!(q[1] > 200 && q[1] < 255, "{}", q[1]);
    }

    #[test]
    fn descriptor_turns_with_the_image() {
        // A textured blob; rotating the image by 90° and the keypoint orientation by 90°
        // must give (nearly) the same descriptor.
        let f = |x: f64, y: f64| ((0.3 * x).sin() * (0.2 * y + 0.1 * x).cos() + 0.05 * x) as f32;
        let n = 61;
        let c = 30.0;
        let img = Image::from_fn(n, n, |x, y| f(x as f64 - c, y as f64 - c));
        // Rotated by +90° (x right, y down): new(x, y) = old(y', −x') about the centre.
        let rot = Image::from_fn(n, n, |x, y| f(y as f64 - c, -(x as f64 - c)));
        let p = SiftParams::default();
        let e = extremum(c, c, 2.0);
        let a = with_field(&img, |g| describe(g, &e, 0.3, &p)).unwrap();
        let b = with_field(&rot, |g| {
            describe(g, &e, 0.3 + std::f64::consts::FRAC_PI_2, &p)
        })
        .unwrap();
        let dist: f64 = a
            .iter()
            .zip(&b)
            .map(|(u, v)| (f64::from(*u) - f64::from(*v)).powi(2))
            .sum();
        let norm: f64 = a.iter().map(|u| f64::from(*u).powi(2)).sum();
        assert!(
            dist.sqrt() < 0.05 * norm.sqrt(),
            "dist {} norm {}",
            dist.sqrt(),
            norm.sqrt()
        );
        // And a different orientation gives a clearly different descriptor.
        let c2 = with_field(&img, |g| describe(g, &e, 1.5, &p)).unwrap();
        let d2: f64 = a
            .iter()
            .zip(&c2)
            .map(|(u, v)| (f64::from(*u) - f64::from(*v)).powi(2))
            .sum();
        assert!(d2.sqrt() > 0.3 * norm.sqrt());
    }

    #[test]
    fn patch_leaving_the_image_gives_none() {
        let img = Image::filled(30, 30, 0.5);
        assert!(
            with_field(&img, |g| describe(
                g,
                &extremum(5.0, 15.0, 2.0),
                0.0,
                &SiftParams::default()
            ))
            .is_none()
        );
    }
}
