//! Heights from the rectified disparity, on the left micrograph's grid.
//!
//! SD-SEM eq. (19): `h = d · p / (2 sin(θ/2))`, with `d` the disparity in
//! pixels of the original micrograph along the parallax direction, `p` the
//! pixel size and `θ` the tilt difference. DESIGN §3 fixes the sign: a point
//! higher by `δh` moves in the right micrograph by `δh · sin θ` along
//! `n = (−sin φ, cos φ)` (φ = tilt axis angle), so a positive height is a
//! displacement along `+n`.
//!
//! The disparity is measured on the rectified canvas, where the homography of
//! the right image may scale, rotate or mirror `n`. For every left pixel we
//! follow the match into the right micrograph and divide the rectified
//! disparity by the x-component of `J_right · n` (the Jacobian of `H_right`
//! there): that converts it to original pixels along `n` and gets the sign
//! right whatever the rectification did.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::Image;

/// Why heights cannot be computed from a disparity.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DepthError {
    #[error(
        "tilt difference θ = {0}° must lie in (0°, 180°) (right is the micrograph at the higher tilt)"
    )]
    Tilt(f64),
    #[error("pixel size {0} µm must be a positive number")]
    PixelSize(f64),
    #[error(
        "the right rectification homography is singular; the sparse stage produced an unusable H_right"
    )]
    SingularHomography,
}

/// The acquisition geometry of a stereo pair.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StereoGeometry {
    /// θ = tilt(right) − tilt(left), degrees, > 0.
    pub tilt_deg: f64,
    /// Pixel size of the micrographs, micrometres.
    pub pixel_size_um: f64,
    /// φ, direction of the tilt axis in the image, degrees from +x towards +y.
    pub tilt_axis_deg: f64,
}

impl StereoGeometry {
    /// `n = (−sin φ, cos φ)`: where a raised point moves in the right image.
    #[must_use]
    pub fn parallax_direction(&self) -> (f64, f64) {
        let phi = self.tilt_axis_deg.to_radians();
        (-phi.sin(), phi.cos())
    }

    /// Micrometres of height per pixel of parallax, eq. (19).
    #[must_use]
    pub fn um_per_px(&self) -> f64 {
        self.pixel_size_um / (2.0 * (self.tilt_deg.to_radians() / 2.0).sin())
    }
}

/// Applies a homography to a point.
#[inline]
fn apply(hm: &Matrix3<f64>, x: f64, y: f64) -> Option<(f64, f64)> {
    let r = hm * Vector3::new(x, y, 1.0);
    (r.z.abs() > 1e-12).then(|| (r.x / r.z, r.y / r.z))
}

/// The Jacobian of the homography at `(x, y)` applied to the vector `(a, b)`.
#[inline]
fn jacobian_times(hm: &Matrix3<f64>, x: f64, y: f64, a: f64, b: f64) -> Option<(f64, f64)> {
    let r = hm * Vector3::new(x, y, 1.0);
    if r.z.abs() < 1e-12 {
        return None;
    }
    let (u, v, w) = (r.x, r.y, r.z);
    let du = |c: usize| (hm[(0, c)] * w - u * hm[(2, c)]) / (w * w);
    let dv = |c: usize| (hm[(1, c)] * w - v * hm[(2, c)]) / (w * w);
    Some((du(0) * a + du(1) * b, dv(0) * a + dv(1) * b))
}

/// Bilinear sample that ignores non-finite corners (renormalising the rest);
/// `None` outside the image or when no corner is finite.
fn sample_finite(img: &Image, x: f64, y: f64) -> Option<f32> {
    let (w, h) = img.dimensions();
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f64 && y <= (h - 1) as f64) {
        return None;
    }
    // Non-negative (tested above): truncation is the floor, without a library call.
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let mut acc = 0f32;
    let mut wsum = 0f32;
    for (xx, yy, wt) in [
        (x0, y0, (1.0 - tx) * (1.0 - ty)),
        (x1, y0, tx * (1.0 - ty)),
        (x0, y1, (1.0 - tx) * ty),
        (x1, y1, tx * ty),
    ] {
        let v = img.get(xx, yy);
        if v.is_finite() && wt > 0.0 {
            acc += wt * v;
            wsum += wt;
        }
    }
    // Require the finite corners to carry most of the weight, so holes do not
    // grow a rim of extrapolated values.
    (wsum >= 0.5).then(|| acc / wsum)
}

/// Height map (µm, `NaN` unknown) on the left micrograph's grid
/// (`left_width × left_height`) from the disparity on the rectified canvas
/// (`x_right − x_left` in rectified pixels, left-rectified grid).
/// `h_left`/`h_right` map original left/right pixel coordinates to the canvas.
///
/// # Errors
/// [`DepthError`] for a tilt or pixel size out of range, or an `H_right` that cannot be inverted.
pub fn height_on_left_grid(
    disparity_rect: &Image,
    h_left: &Matrix3<f64>,
    h_right: &Matrix3<f64>,
    geometry: &StereoGeometry,
    left_width: usize,
    left_height: usize,
) -> Result<Image, DepthError> {
    if !(geometry.tilt_deg > 0.0 && geometry.tilt_deg < 180.0) {
        return Err(DepthError::Tilt(geometry.tilt_deg));
    }
    if !(geometry.pixel_size_um > 0.0 && geometry.pixel_size_um.is_finite()) {
        return Err(DepthError::PixelSize(geometry.pixel_size_um));
    }
    let h_right_inv = h_right
        .try_inverse()
        .ok_or(DepthError::SingularHomography)?;
    let (nx, ny) = geometry.parallax_direction();
    let scale = geometry.um_per_px();
    let mut out = Image::filled(left_width, left_height, f32::NAN);
    out.data_mut()
        .par_chunks_mut(left_width)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let Some((xr, yr)) = apply(h_left, x as f64, y as f64) else {
                    continue;
                };
                let Some(d) = sample_finite(disparity_rect, xr, yr) else {
                    continue;
                };
                let d = f64::from(d);
                let Some((xo, yo)) = apply(&h_right_inv, xr + d, yr) else {
                    continue;
                };
                let Some((jx, _)) = jacobian_times(h_right, xo, yo, nx, ny) else {
                    continue;
                };
                if jx.abs() < 1e-6 {
                    continue;
                }
                *o = (d / jx * scale) as f32;
            }
        });
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn geometry(phi: f64) -> StereoGeometry {
        StereoGeometry {
            tilt_deg: 6.0,
            pixel_size_um: 0.05,
            tilt_axis_deg: phi,
        }
    }

    #[test]
    fn raised_feature_is_positive_for_every_rectification_orientation() {
        // The tilt axis vertical (φ = 90°): n = (−1, 0), a raised point moves
        // towards −x in the right image. Rectification by identity keeps that:
        // the rectified disparity of a raised point is negative.
        let g = geometry(90.0);
        let raised = -2.0f32;
        let disp = Image::from_fn(20, 10, |x, _| if x > 10 { raised } else { 0.0 });
        let id = Matrix3::identity();
        let hmap = height_on_left_grid(&disp, &id, &id, &g, 20, 10).unwrap();
        assert!(
            hmap.get(15, 5) > 0.0,
            "raised feature must be positive: {}",
            hmap.get(15, 5)
        );
        assert_eq!(hmap.get(5, 5), 0.0);
        let expected = 2.0 * 0.05 / (2.0 * (3f64.to_radians()).sin());
        assert!((f64::from(hmap.get(15, 5)) - expected).abs() < 1e-4);

        // A rectification that mirrors x (H = diag(−1, 1, 1) shifted) flips the
        // measured disparity; the height must not flip.
        let mirror = Matrix3::new(-1.0, 0.0, 19.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        let disp_m = Image::from_fn(20, 10, |x, _| if 19 - x > 10 { -raised } else { 0.0 });
        let hm = height_on_left_grid(&disp_m, &mirror, &mirror, &g, 20, 10).unwrap();
        assert!((hm.get(15, 5) - hmap.get(15, 5)).abs() < 1e-5);

        // Tilt axis horizontal (φ = 0°): n = (0, 1), parallax along +y. A
        // rectification rotating by −90° (x' = y, y' = −x + c) turns +y into +x.
        let g0 = geometry(0.0);
        let rot = Matrix3::new(0.0, 1.0, 0.0, -1.0, 0.0, 19.0, 0.0, 0.0, 1.0);
        // Left 20×10 → canvas x' = y ∈ [0, 9], y' = 19 − x ∈ [0, 19].
        let disp_r = Image::from_fn(10, 20, |_, yr| if 19 - yr > 10 { 2.0 } else { 0.0 });
        let hr = height_on_left_grid(&disp_r, &rot, &rot, &g0, 20, 10).unwrap();
        assert!(
            (f64::from(hr.get(15, 5)) - expected).abs() < 1e-4,
            "{}",
            hr.get(15, 5)
        );
    }

    #[test]
    fn scale_of_the_rectification_is_undone() {
        // A rectification that doubles the image: disparity doubles, height does not.
        let g = geometry(-90.0); // n = (1, 0)
        let s2 = Matrix3::new(2.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0);
        let disp = Image::filled(40, 20, 3.0);
        let hmap = height_on_left_grid(&disp, &s2, &s2, &g, 20, 10).unwrap();
        let expected = 1.5 * g.um_per_px();
        assert!((f64::from(hmap.get(5, 5)) - expected).abs() < 1e-5);
    }

    #[test]
    fn unknown_disparity_gives_nan_and_bad_geometry_is_refused() {
        let disp = Image::filled(8, 8, f32::NAN);
        let id = Matrix3::identity();
        let hmap = height_on_left_grid(&disp, &id, &id, &geometry(0.0), 8, 8).unwrap();
        assert!(hmap.data().iter().all(|v| v.is_nan()));
        let mut g = geometry(0.0);
        g.tilt_deg = -3.0;
        assert!(height_on_left_grid(&disp, &id, &id, &g, 8, 8).is_err());
    }
}
