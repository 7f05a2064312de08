//! The one image type of the vision core: a single channel of `f32` samples.
//!
//! Geometry follows DESIGN §3: x to the right, y down, pixel centres at integer
//! coordinates, rows stored one after another (row-major).

use rayon::prelude::*;
use std::fmt;

/// A single-channel image of `f32` samples, row-major.
///
/// Intensities are in `[0, 1]` for micrographs; other uses (disparity, height,
/// confidence) store whatever unit they document, with `NaN` for "unknown".
#[derive(Clone, PartialEq)]
pub struct Image {
    width: usize,
    height: usize,
    data: Vec<f32>,
}

/// The buffer handed to [`Image::from_vec`] does not hold `width × height` samples.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("image buffer holds {len} samples, expected {width} × {height} = {}", width * height)]
pub struct SizeMismatch {
    pub width: usize,
    pub height: usize,
    pub len: usize,
}

impl Image {
    /// An image filled with `value`.
    #[must_use]
    pub fn filled(width: usize, height: usize, value: f32) -> Self {
        let n = width * height;
        let data = if value.to_bits() == 0 {
            // Zeroed pages from the system, touched by their first writer.
            vec![0.0; n]
        } else {
            // Written by both cores (a full-resolution map is millions of pixels).
            let mut data = Vec::with_capacity(n);
            data.par_extend(rayon::iter::repeat_n(value, n));
            data
        };
        Self {
            width,
            height,
            data,
        }
    }

    /// An image of zeros.
    #[must_use]
    pub fn zeros(width: usize, height: usize) -> Self {
        Self::filled(width, height, 0.0)
    }

    /// Wraps a row-major buffer.
    ///
    /// # Errors
    /// [`SizeMismatch`] when `data.len() != width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Result<Self, SizeMismatch> {
        if data.len() == width * height {
            Ok(Self {
                width,
                height,
                data,
            })
        } else {
            Err(SizeMismatch {
                width,
                height,
                len: data.len(),
            })
        }
    }

    /// Builds an image by evaluating `f(x, y)` at every pixel.
    #[must_use]
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self {
            width,
            height,
            data,
        }
    }

    /// 8-bit samples scaled to `[0, 1]`.
    ///
    /// # Errors
    /// [`SizeMismatch`] when `data.len() != width * height`.
    pub fn from_u8(width: usize, height: usize, data: &[u8]) -> Result<Self, SizeMismatch> {
        Self::from_vec(
            width,
            height,
            data.iter().map(|&v| f32::from(v) / 255.0).collect(),
        )
    }

    /// 16-bit samples scaled to `[0, 1]`.
    ///
    /// # Errors
    /// [`SizeMismatch`] when `data.len() != width * height`.
    pub fn from_u16(width: usize, height: usize, data: &[u16]) -> Result<Self, SizeMismatch> {
        Self::from_vec(
            width,
            height,
            data.iter().map(|&v| f32::from(v) / 65535.0).collect(),
        )
    }

    /// Samples in `[0, 1]` quantised to 8 bits (clamped; `NaN` becomes 0).
    #[must_use]
    pub fn to_u8(&self) -> Vec<u8> {
        self.data
            .iter()
            .map(|&v| {
                let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
                // In [0, 255.5) after clamping, so the cast cannot truncate meaningfully.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let q = (v * 255.0 + 0.5) as u8;
                q
            })
            .collect()
    }

    #[must_use]
    pub fn width(&self) -> usize {
        self.width
    }

    #[must_use]
    pub fn height(&self) -> usize {
        self.height
    }

    /// `(width, height)`.
    #[must_use]
    pub fn dimensions(&self) -> (usize, usize) {
        (self.width, self.height)
    }

    /// Number of pixels.
    #[must_use]
    pub fn len(&self) -> usize {
        self.data.len()
    }

    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    /// All samples, row-major.
    #[must_use]
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// All samples, row-major, mutable.
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    /// The buffer, giving up the image.
    #[must_use]
    pub fn into_vec(self) -> Vec<f32> {
        self.data
    }

    /// Row `y`.
    ///
    /// # Panics
    /// When `y >= height`.
    #[must_use]
    pub fn row(&self, y: usize) -> &[f32] {
        &self.data[y * self.width..(y + 1) * self.width]
    }

    /// Row `y`, mutable.
    ///
    /// # Panics
    /// When `y >= height`.
    pub fn row_mut(&mut self, y: usize) -> &mut [f32] {
        &mut self.data[y * self.width..(y + 1) * self.width]
    }

    /// Sample at `(x, y)`.
    ///
    /// # Panics
    /// When the pixel lies outside the image.
    #[must_use]
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        debug_assert!(x < self.width && y < self.height);
        self.data[y * self.width + x]
    }

    /// Sets the sample at `(x, y)`.
    ///
    /// # Panics
    /// When the pixel lies outside the image.
    #[inline]
    pub fn set(&mut self, x: usize, y: usize, value: f32) {
        debug_assert!(x < self.width && y < self.height);
        self.data[y * self.width + x] = value;
    }

    /// Sample at integer coordinates clamped to the border (replicate padding).
    #[must_use]
    #[inline]
    pub fn get_clamped(&self, x: isize, y: isize) -> f32 {
        let cx = x.clamp(0, self.width as isize - 1) as usize;
        let cy = y.clamp(0, self.height as isize - 1) as usize;
        self.data[cy * self.width + cx]
    }

    /// Bilinear interpolation at real coordinates; `None` outside the convex
    /// hull of the pixel centres, `[0, w−1] × [0, h−1]`.
    #[must_use]
    pub fn sample_bilinear(&self, x: f64, y: f64) -> Option<f32> {
        if !(x >= 0.0 && y >= 0.0 && x <= (self.width - 1) as f64 && y <= (self.height - 1) as f64)
        {
            return None;
        }
        // Non-negative and bounded by the checks above: truncation is the floor (without the
        // library call that `floor` is on the baseline x86-64 target).
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (x0, y0) = (x as usize, y as usize);
        let x1 = (x0 + 1).min(self.width - 1);
        let y1 = (y0 + 1).min(self.height - 1);
        #[allow(clippy::cast_possible_truncation)]
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let top = self.get(x0, y0) * (1.0 - fx) + self.get(x1, y0) * fx;
        let bottom = self.get(x0, y1) * (1.0 - fx) + self.get(x1, y1) * fx;
        Some(top * (1.0 - fy) + bottom * fy)
    }

    /// A new image with `f` applied to every sample.
    #[must_use]
    pub fn map(&self, f: impl Fn(f32) -> f32) -> Self {
        Self {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(|&v| f(v)).collect(),
        }
    }

    /// Smallest and largest finite sample, `None` when there is none.
    #[must_use]
    pub fn finite_range(&self) -> Option<(f32, f32)> {
        self.data
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .fold(None, |acc, v| match acc {
                None => Some((v, v)),
                Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
            })
    }
}

impl fmt::Debug for Image {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Image")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("range", &self.finite_range())
            .finish_non_exhaustive()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn from_vec_rejects_wrong_length() {
        let err = Image::from_vec(3, 2, vec![0.0; 5]).unwrap_err();
        assert_eq!(err.len, 5);
        assert!(err.to_string().contains("expected 3 × 2 = 6"));
    }

    #[test]
    fn filled_holds_the_value_everywhere_on_any_number_of_threads() {
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for value in [f32::NAN, -0.0, 0.0, 2.5] {
                let img = pool.install(|| Image::filled(517, 9, value));
                assert_eq!(img.dimensions(), (517, 9));
                assert!(img.data().iter().all(|v| v.to_bits() == value.to_bits()));
            }
        }
    }

    #[test]
    fn row_major_layout() {
        let img = Image::from_fn(3, 2, |x, y| (10 * y + x) as f32);
        assert_eq!(img.row(1), &[10.0, 11.0, 12.0]);
        assert_eq!(img.get(2, 0), 2.0);
    }

    #[test]
    fn bilinear_interpolates_and_refuses_outside() {
        let img = Image::from_fn(2, 2, |x, y| (x + 2 * y) as f32);
        assert_eq!(img.sample_bilinear(0.5, 0.5), Some(1.5));
        assert_eq!(img.sample_bilinear(1.0, 1.0), Some(3.0));
        assert_eq!(img.sample_bilinear(1.01, 0.0), None);
        assert_eq!(img.sample_bilinear(-0.01, 0.0), None);
        assert_eq!(img.sample_bilinear(f64::NAN, 0.0), None);
    }

    #[test]
    fn u8_round_trip() {
        let bytes = [0u8, 1, 128, 255];
        let img = Image::from_u8(2, 2, &bytes).unwrap();
        assert_eq!(img.to_u8(), bytes);
    }

    #[test]
    fn clamped_access_replicates_border() {
        let img = Image::from_fn(2, 2, |x, y| (x + 2 * y) as f32);
        assert_eq!(img.get_clamped(-5, 0), 0.0);
        assert_eq!(img.get_clamped(9, 9), 3.0);
    }
}
