//! Warping an image through a homography onto a canvas (inverse mapping, bilinear).

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::vision::Image;

/// A warped image and where it holds data.
#[derive(Debug, Clone, PartialEq)]
pub struct Warped {
    /// Samples on the canvas; `NaN` where the source image does not reach.
    pub image: Image,
    /// `true` where `image` holds a sample of the source (row-major, like `image`).
    pub valid: Vec<bool>,
}

impl Warped {
    /// The image with `value` where it holds no data (e.g. 0 for display or PNG output).
    #[must_use]
    pub fn filled(&self, value: f32) -> Image {
        self.image.map(|v| if v.is_nan() { value } else { v })
    }
}

/// Warps `src` by `h` (source pixel → canvas pixel) onto a `width × height` canvas: each canvas
/// pixel takes the bilinear sample of `src` at `h⁻¹ · pixel`. `None` when `h` is singular.
#[must_use]
pub fn warp(src: &Image, h: &Matrix3<f64>, width: usize, height: usize) -> Option<Warped> {
    warp_rect(src, h, (0, 0), (width, height))
}

/// The `width × height` rectangle of the canvas of [`warp`] whose top-left pixel is `origin`:
/// the same samples, computed for that rectangle alone (a tile of the dense stage).
#[must_use]
pub fn warp_rect(
    src: &Image,
    h: &Matrix3<f64>,
    (x0, y0): (usize, usize),
    (width, height): (usize, usize),
) -> Option<Warped> {
    let inv = h.try_inverse()?;
    let mut image = Image::filled(width, height, f32::NAN);
    image
        .data_mut()
        .par_chunks_mut(width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, v) in row.iter_mut().enumerate() {
                let p = inv * Vector3::new((x0 + x) as f64, (y0 + y) as f64, 1.0);
                if p.z > 0.0 {
                    // Tolerate rounding just outside the pixel-centre hull.
                    let (sx, sy) = (p.x / p.z, p.y / p.z);
                    let (sx, sy) = (snap(sx, src.width()), snap(sy, src.height()));
                    if let Some(s) = src.sample_bilinear(sx, sy) {
                        *v = s;
                    }
                }
            }
        });
    let valid = image.data().iter().map(|v| !v.is_nan()).collect();
    Some(Warped { image, valid })
}

/// Moves a coordinate within 1e-6 px outside `[0, n − 1]` onto the border.
fn snap(c: f64, n: usize) -> f64 {
    let hi = n.saturating_sub(1) as f64;
    if c < 0.0 && c > -1e-6 {
        0.0
    } else if c > hi && c < hi + 1e-6 {
        hi
    } else {
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reference: the same mapping written per pixel without rayon.
    fn naive(src: &Image, h: &Matrix3<f64>, w: usize, hh: usize) -> Image {
        let inv = h.try_inverse().unwrap();
        Image::from_fn(w, hh, |x, y| {
            let p = inv * Vector3::new(x as f64, y as f64, 1.0);
            let (sx, sy) = (p.x / p.z, p.y / p.z);
            let (mx, my) = ((src.width() - 1) as f64, (src.height() - 1) as f64);
            // Same 1e-6 px tolerance at the border as the warp.
            let inside = sx > -1e-6 && sy > -1e-6 && sx < mx + 1e-6 && sy < my + 1e-6;
            if inside {
                src.sample_bilinear(sx.clamp(0.0, mx), sy.clamp(0.0, my))
                    .unwrap()
            } else {
                f32::NAN
            }
        })
    }

    #[test]
    fn translation_moves_pixels_and_marks_the_rest_invalid() {
        let src = Image::from_fn(4, 3, |x, y| (x + 10 * y) as f32);
        let h = Matrix3::new(1.0, 0.0, 2.0, 0.0, 1.0, 1.0, 0.0, 0.0, 1.0);
        let w = warp(&src, &h, 6, 4).unwrap();
        assert_eq!(w.image.get(2, 1), 0.0);
        assert_eq!(w.image.get(5, 3), 23.0);
        assert!(!w.valid[0] && w.image.get(0, 0).is_nan());
        assert_eq!(w.valid.iter().filter(|v| **v).count(), 12);
        assert_eq!(w.filled(0.0).get(0, 0), 0.0);
    }

    #[test]
    fn agrees_with_naive_projective_warp() {
        let src = Image::from_fn(20, 15, |x, y| ((x * 3 + y * 7) % 11) as f32);
        let h = Matrix3::new(0.9, 0.1, 3.0, -0.05, 1.1, 2.0, 0.001, -0.002, 1.0);
        let fast = warp(&src, &h, 25, 20).unwrap();
        let slow = naive(&src, &h, 25, 20);
        for (a, b) in fast.image.data().iter().zip(slow.data()) {
            assert!(
                (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-5,
                "{a} {b}"
            );
        }
        assert!(warp(&src, &Matrix3::zeros(), 5, 5).is_none());
    }
}
