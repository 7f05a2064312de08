//! The height map as a picture, for viewers that show images but not float maps with a
//! colour scale (Foxglove's Image panel): viridis over the robust range of the heights.
//!
//! Viridis (van der Walt & Smith, 2015, public domain) is perceptually uniform and reads
//! correctly in grey and for red–green colour-blind eyes: dark purple is low, yellow high.
//! The range is the 1st–99th percentile of the known heights, so a few outliers do not
//! wash the relief out; heights beyond it take the end colours, unknown (NaN) pixels are
//! black, a colour viridis never takes.

use std::io::Cursor;

use crate::vision::Image;

/// Viridis in sRGB at 17 evenly spaced stops, t = 0, 1/16, …, 1; linear between stops it
/// stays within 5/255 of the full 256-entry map.
const VIRIDIS: [[u8; 3]; 17] = [
    [68, 1, 84],
    [72, 24, 106],
    [71, 45, 123],
    [66, 64, 134],
    [59, 82, 139],
    [51, 99, 141],
    [44, 114, 142],
    [38, 130, 142],
    [33, 145, 140],
    [31, 160, 136],
    [40, 174, 128],
    [63, 188, 115],
    [94, 201, 98],
    [132, 212, 75],
    [173, 220, 48],
    [216, 226, 25],
    [253, 231, 37],
];

/// The colour of `t` in `[0, 1]` (clamped; NaN is black).
#[must_use]
pub fn viridis(t: f64) -> [u8; 3] {
    if t.is_nan() {
        return [0, 0, 0];
    }
    let x = t.clamp(0.0, 1.0) * 16.0;
    // In [0, 15] after the clamp.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let k = (x.floor() as usize).min(15);
    let f = x - k as f64;
    let (a, b) = (VIRIDIS[k], VIRIDIS[k + 1]);
    // Between two u8 values, so in [0, 255].
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    std::array::from_fn(|i| {
        (f64::from(a[i]) + f * (f64::from(b[i]) - f64::from(a[i]))).round() as u8
    })
}

/// The 1st and 99th percentiles of the finite heights; `None` when no height is known.
#[must_use]
pub fn robust_range(height_um: &Image) -> Option<(f32, f32)> {
    let mut known: Vec<f32> = height_um
        .data()
        .iter()
        .copied()
        .filter(|h| h.is_finite())
        .collect();
    if known.is_empty() {
        return None;
    }
    let last = known.len() - 1;
    // q·last ≤ last, a valid index.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let at = |q: f64| (q * last as f64).round() as usize;
    let (lo_i, hi_i) = (at(0.01), at(0.99));
    let lo = *known.select_nth_unstable_by(lo_i, f32::total_cmp).1;
    let hi = *known.select_nth_unstable_by(hi_i, f32::total_cmp).1;
    Some((lo, hi))
}

/// A height map coloured for viewing, with the heights its colours span.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightPreview {
    /// RGB, 8 bits, row-major, the height map's size.
    pub rgb: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// Heights (µm) of the first and the last colour; `None` when no height is known.
    pub range_um: Option<(f32, f32)>,
}

impl HeightPreview {
    /// Colours `height_um` (see the module docs).
    ///
    /// # Panics
    /// Never for a map whose sides fit `u32` (every height map this program makes).
    #[must_use]
    pub fn new(height_um: &Image) -> Self {
        let range_um = robust_range(height_um);
        let (lo, span) = match range_um {
            Some((lo, hi)) => (f64::from(lo), f64::from(hi - lo)),
            None => (0.0, 0.0),
        };
        let mut rgb = Vec::with_capacity(height_um.data().len() * 3);
        for &h in height_um.data() {
            let t = if !h.is_finite() {
                f64::NAN
            } else if span > 0.0 {
                (f64::from(h) - lo) / span
            } else {
                0.5
            };
            rgb.extend(viridis(t));
        }
        Self {
            rgb,
            width: u32::try_from(height_um.width()).expect("image width fits u32"),
            height: u32::try_from(height_um.height()).expect("image height fits u32"),
            range_um,
        }
    }

    /// The picture as a PNG file's bytes.
    ///
    /// # Errors
    /// When the PNG encoder fails (it does not for a buffer of the right size).
    pub fn png(&self) -> Result<Vec<u8>, image::ImageError> {
        let mut out = Cursor::new(Vec::new());
        image::write_buffer_with_format(
            &mut out,
            &self.rgb,
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
            image::ImageFormat::Png,
        )?;
        Ok(out.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn viridis_runs_from_purple_to_yellow_and_nan_is_black() {
        assert_eq!(viridis(0.0), [68, 1, 84]);
        assert_eq!(viridis(1.0), [253, 231, 37]);
        assert_eq!(viridis(-3.0), viridis(0.0));
        assert_eq!(viridis(7.0), viridis(1.0));
        assert_eq!(viridis(f64::NAN), [0, 0, 0]);
        // Between stops: between their colours.
        let mid = viridis(0.5 / 16.0);
        assert!(mid[1] > 1 && mid[1] < 24, "{mid:?}");
        // Lightness rises monotonically (a perceptual map): green channel as a proxy.
        let greens: Vec<u8> = (0..=64).map(|i| viridis(f64::from(i) / 64.0)[1]).collect();
        assert!(greens.windows(2).all(|w| w[0] <= w[1]), "{greens:?}");
    }

    #[test]
    fn the_range_ignores_outliers_and_unknown_heights() {
        let mut values: Vec<f32> = (0..1000).map(|i| i as f32 / 100.0).collect();
        values[0] = -1e6;
        values[999] = 1e6;
        values[500] = f32::NAN;
        let img = Image::from_vec(1000, 1, values).unwrap();
        let (lo, hi) = robust_range(&img).unwrap();
        assert!(
            (0.05..0.2).contains(&lo) && (9.8..9.95).contains(&hi),
            "{lo} {hi}"
        );
        assert_eq!(robust_range(&Image::filled(4, 4, f32::NAN)), None);
    }

    #[test]
    fn preview_colours_heights_and_blacks_out_unknown_ones() {
        let img = Image::from_vec(4, 1, vec![0.0, f32::NAN, 10.0, 5.0]).unwrap();
        let p = HeightPreview::new(&img);
        assert_eq!(p.range_um, Some((0.0, 10.0)));
        assert_eq!(&p.rgb[0..3], &viridis(0.0));
        assert_eq!(&p.rgb[3..6], &[0, 0, 0]);
        assert_eq!(&p.rgb[6..9], &viridis(1.0));
        assert_eq!(&p.rgb[9..12], &viridis(0.5));
        let png = p.png().unwrap();
        let back = image::load_from_memory(&png).unwrap().into_rgb8();
        assert_eq!(back.dimensions(), (4, 1));
        assert_eq!(back.into_raw(), p.rgb);
        // A flat map takes the middle colour.
        let flat = HeightPreview::new(&Image::filled(2, 2, 3.0));
        assert_eq!(&flat.rgb[0..3], &viridis(0.5));
    }
}
