//! The Gaussian scale space and its difference of Gaussians (IPOL "Anatomy of
//! the SIFT method", Rey-Otero & Delbracio 2014, §2 and Algorithm 1).
//!
//! Scales are absolute: the image in octave `o`, slot `s` has blur
//! `σ(o, s) = (δ_o / δ_min) · σ_min · 2^(s / n_spo)` in input pixels and its samples
//! lie `δ_o = δ_min · 2^o` input pixels apart, sample `m` at input coordinate `m·δ_o`.
//!
//! # Memory
//! The octaves are built one after another into [`ScaleSpaceBuffers`], one allocation that
//! outlives them: the slots the keypoints are described in (`1 ..= n_spo`) of every octave,
//! plus four planes of the first octave's size that each octave reuses for its other slots and
//! the blur's intermediate, and that the gradient fields reuse after the detection. The
//! differences of Gaussians are never stored: the detection subtracts the slots it reads.
//! About 8 planes of the first octave in all, against 16 separate images for the whole scale
//! space and its differences built at once.

use std::ops::Range;

use rayon::prelude::*;

use super::SiftParams;
use crate::vision::Image;
use crate::vision::filter::blur::gaussian_blur_into;
use crate::vision::pages;

/// Size and inter-sample distance of one octave.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OctaveGeometry {
    pub width: usize,
    pub height: usize,
    /// Inter-sample distance δ_o in input pixels.
    pub delta: f64,
}

/// The octaves' geometry for an image of `(width, height)` (IPOL Algorithm 1).
///
/// The number of octaves is the IPOL one, `⌊log2(min(w, h) / (δ_min · 12))⌋ + 1`
/// (the last octave is at least 12 samples wide), capped by `params.n_oct_max`, and
/// stops before an octave narrower than 2 samples. None for images too small to hold one.
#[must_use]
pub fn octaves((width, height): (usize, usize), params: &SiftParams) -> Vec<OctaveGeometry> {
    let min_side = width.min(height) as f64;
    if min_side < 12.0 * params.delta_min || width == 0 || height == 0 {
        return Vec::new();
    }
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let n_oct = ((min_side / (params.delta_min * 12.0)).log2().floor() as usize + 1)
        .min(params.n_oct_max.max(1));
    let (mut w, mut h) = if (params.delta_min - 1.0).abs() < 1e-12 {
        (width, height)
    } else {
        resampled_size((width, height), params.delta_min)
    };
    let mut out = Vec::with_capacity(n_oct);
    for o in 0..n_oct {
        out.push(OctaveGeometry {
            width: w,
            height: h,
            delta: params.delta_min * f64::from(1u32 << o),
        });
        (w, h) = (w.div_ceil(2), h.div_ceil(2));
        if w < 2 || h < 2 {
            break;
        }
    }
    out
}

/// The working memory of the scale space, reusable from one image to the next (of any size):
/// it grows to the largest image it served and is never read before it is written.
#[derive(Debug, Default)]
pub struct ScaleSpaceBuffers {
    data: Vec<f32>,
}

/// Planes of the first octave's size shared by every octave: slot 0, slots `n_spo + 1` and
/// `n_spo + 2`, and the blur's intermediate.
const WORK_PLANES: usize = 4;

/// Where each octave's images lie in [`ScaleSpaceBuffers`].
#[derive(Debug, Clone)]
struct Layout {
    n_spo: usize,
    /// Samples of the first octave: the size of a work plane.
    plane: usize,
    /// Start of each octave's kept slots `1 ..= n_spo`.
    kept: Vec<usize>,
    total: usize,
}

impl Layout {
    fn new(octaves: &[OctaveGeometry], n_spo: usize) -> Self {
        let plane = octaves.first().map_or(0, |o| o.width * o.height);
        let mut at = WORK_PLANES * plane;
        let kept = octaves
            .iter()
            .map(|o| {
                let start = at;
                at += n_spo * o.width * o.height;
                start
            })
            .collect();
        Self {
            n_spo,
            plane,
            kept,
            total: at,
        }
    }

    /// Work plane `i` cut to `len` samples.
    fn work(&self, i: usize, len: usize) -> Range<usize> {
        i * self.plane..i * self.plane + len
    }

    /// Slot `s` (`0 ..= n_spo + 2`) of octave `o` of `len` samples.
    fn slot(&self, o: usize, s: usize, len: usize) -> Range<usize> {
        if s == 0 {
            self.work(0, len)
        } else if s <= self.n_spo {
            let start = self.kept[o] + (s - 1) * len;
            start..start + len
        } else {
            self.work(s - self.n_spo, len)
        }
    }
}

/// The whole scale space of one image, built into borrowed buffers.
#[derive(Debug)]
pub struct ScaleSpace<'a> {
    pub octaves: Vec<OctaveGeometry>,
    layout: Layout,
    data: &'a mut Vec<f32>,
    /// The octave whose slots `0`, `n_spo + 1`, `n_spo + 2` the work planes hold.
    current: Option<usize>,
}

/// One octave's images, the Gaussians `v_s`, `s = 0 … n_spo + 2`; the differences
/// `w_s = v_{s+1} − v_s` are computed where read.
#[derive(Debug, Clone, Copy)]
pub struct OctaveView<'a> {
    pub geometry: OctaveGeometry,
    gauss: &'a [&'a [f32]],
}

impl OctaveView<'_> {
    pub fn width(&self) -> usize {
        self.geometry.width
    }

    pub fn height(&self) -> usize {
        self.geometry.height
    }

    /// Difference of Gaussians `w_s(x, y) = v_{s+1}(x, y) − v_s(x, y)`, `s = 0 … n_spo + 1`.
    #[inline]
    pub fn dog(&self, s: usize, x: usize, y: usize) -> f32 {
        let i = y * self.geometry.width + x;
        self.gauss[s + 1][i] - self.gauss[s][i]
    }

    /// Gaussian image `v_s`, row-major.
    pub fn gauss(&self, s: usize) -> &[f32] {
        self.gauss[s]
    }
}

impl<'a> ScaleSpace<'a> {
    /// Prepares the scale space of an image of `size` in `buffers` (grown if too small); the
    /// octaves are built by [`ScaleSpace::build_octave`], in order.
    pub fn new(
        size: (usize, usize),
        params: &SiftParams,
        buffers: &'a mut ScaleSpaceBuffers,
    ) -> Self {
        let octaves = octaves(size, params);
        let layout = Layout::new(&octaves, params.n_spo);
        let data = &mut buffers.data;
        if data.len() < layout.total {
            // Never read before written: a fresh zeroed block, not a copy of the old one.
            *data = Vec::new();
            *data = pages::zeroed(layout.total);
        }
        Self {
            octaves,
            layout,
            data,
            current: None,
        }
    }

    /// Builds octave `o` (IPOL Algorithm 1): its first image from `image` (octave 0) or from
    /// slot `n_spo` of octave `o − 1`, which must be the last one built; then the blurs.
    ///
    /// # Panics
    /// When `o` is not the octave after the last built one.
    pub fn build_octave(&mut self, o: usize, image: &Image, params: &SiftParams) {
        assert_eq!(
            self.current.map_or(0, |c| c + 1),
            o,
            "octaves are built in order"
        );
        let g = self.octaves[o];
        let (w, h) = (g.width, g.height);
        let n = w * h;
        let l = &self.layout;
        let tmp = l.work(WORK_PLANES - 1, n);
        if o == 0 {
            // Seed: resample to δ_min, then blur from σ_in to σ_min (in δ_min samples).
            let seed_blur = (params.sigma_min.powi(2) - params.sigma_in.powi(2))
                .max(0.0)
                .sqrt()
                / params.delta_min;
            let [t, out] = self
                .data
                .get_disjoint_mut([tmp.clone(), l.slot(0, 0, n)])
                .expect("work planes are disjoint");
            if (params.delta_min - 1.0).abs() < 1e-12 {
                gaussian_blur_into(image.data(), (w, h), seed_blur, t, out);
            } else {
                let seed = l.work(1, n);
                let [s, t, out] = self
                    .data
                    .get_disjoint_mut([seed, tmp.clone(), l.slot(0, 0, n)])
                    .expect("work planes are disjoint");
                resample_bilinear_into(image, params.delta_min, s, (w, h));
                gaussian_blur_into(s, (w, h), seed_blur, t, out);
            }
        } else {
            let p = self.octaves[o - 1];
            let src = l.slot(o - 1, l.n_spo, p.width * p.height);
            let [src, out] = self
                .data
                .get_disjoint_mut([src, l.slot(o, 0, n)])
                .expect("the previous octave's slot lies apart from the work planes");
            subsample2_into(src, p.width, out, (w, h));
        }
        let n_spo = l.n_spo;
        for s in 1..n_spo + 3 {
            // Blur increment between slots, in samples of this octave: σ_min/δ_min ·
            // sqrt(2^(2s/n) − 2^(2(s−1)/n)) (IPOL eq. 6), independent of the octave.
            let a = (2.0 * s as f64 / n_spo as f64).exp2();
            let b = (2.0 * (s - 1) as f64 / n_spo as f64).exp2();
            let rho = params.sigma_min / params.delta_min * (a - b).sqrt();
            let [src, t, out] = self
                .data
                .get_disjoint_mut([l.slot(o, s - 1, n), tmp.clone(), l.slot(o, s, n)])
                .expect("the slots of an octave are disjoint");
            gaussian_blur_into(src, (w, h), rho, t, out);
        }
        self.current = Some(o);
    }

    /// The images of octave `o`, which must be the last one built.
    ///
    /// # Panics
    /// When `o` is not the last octave built.
    pub fn with_octave<R>(&self, o: usize, f: impl FnOnce(&OctaveView<'_>) -> R) -> R {
        assert_eq!(self.current, Some(o), "only the last octave built is whole");
        let g = self.octaves[o];
        let n = g.width * g.height;
        let gauss: Vec<&[f32]> = (0..self.layout.n_spo + 3)
            .map(|s| &self.data[self.layout.slot(o, s, n)])
            .collect();
        f(&OctaveView {
            geometry: g,
            gauss: &gauss,
        })
    }

    /// Slot `s` (`1 ..= n_spo`) of any octave built, and two planes of the first octave's size
    /// to write into (the work planes: the octave being built loses its other slots).
    ///
    /// # Panics
    /// When `s` is not a kept slot.
    pub fn kept_slot_and_two_planes(
        &mut self,
        o: usize,
        s: usize,
    ) -> (&[f32], &mut [f32], &mut [f32]) {
        assert!(s >= 1 && s <= self.layout.n_spo, "slot {s} is not kept");
        self.current = None;
        let g = self.octaves[o];
        let n = g.width * g.height;
        let l = &self.layout;
        let [img, a, b] = self
            .data
            .get_disjoint_mut([l.slot(o, s, n), l.work(0, n), l.work(1, n)])
            .expect("kept slots lie apart from the work planes");
        (img, a, b)
    }
}

/// Every other sample of the `src_w`-wide plane `src` in both directions (δ doubles), into the
/// `w × h` plane `out`.
fn subsample2_into(src: &[f32], src_w: usize, out: &mut [f32], (w, h): (usize, usize)) {
    for (y, row) in out.chunks_mut(w).enumerate().take(h) {
        let from = &src[2 * y * src_w..];
        for (x, v) in row.iter_mut().enumerate() {
            *v = from[2 * x];
        }
    }
}

/// Size of the seed resampled to inter-sample distance `delta`.
fn resampled_size((w, h): (usize, usize), delta: f64) -> (usize, usize) {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let size = (
        ((w - 1) as f64 / delta).floor() as usize + 1,
        ((h - 1) as f64 / delta).floor() as usize + 1,
    );
    size
}

/// Bilinear resampling to inter-sample distance `delta` (input pixels) into the `w × h` plane
/// `out`: output sample `m` lies at input coordinate `m·delta` (IPOL's interpolation of the seed).
fn resample_bilinear_into(image: &Image, delta: f64, out: &mut [f32], (w, _): (usize, usize)) {
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let sy = (y as f64 * delta).min((image.height() - 1) as f64);
        for (x, v) in row.iter_mut().enumerate() {
            let sx = (x as f64 * delta).min((image.width() - 1) as f64);
            *v = image.sample_bilinear(sx, sy).unwrap_or(0.0);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::filter::blur::gaussian_blur;

    #[test]
    fn octave_count_and_sizes_follow_ipol() {
        let params = SiftParams::default();
        // min side 60, δ_min 0.5: ⌊log2(60/6)⌋ + 1 = 4 octaves.
        let o = octaves((100, 60), &params);
        assert_eq!(o.len(), 4);
        assert_eq!((o[0].width, o[0].height), (199, 119));
        assert_eq!((o[1].width, o[1].height), (100, 60));
        assert_eq!((o[3].width, o[3].height, o[3].delta), (25, 15, 4.0));
        let one = SiftParams {
            delta_min: 1.0,
            ..params
        };
        assert_eq!(octaves((100, 60), &one).len(), 3);
        assert!(octaves((10, 60), &one).is_empty());
    }

    /// Every octave equals the one built the IPOL way, image after image, whatever the buffers
    /// held before (a larger image, then a smaller one, then one upsampled).
    #[test]
    fn octaves_built_in_reused_buffers_equal_the_direct_construction() {
        let mut buffers = ScaleSpaceBuffers::default();
        let cases = [
            (
                Image::from_fn(90, 70, |x, y| ((x ^ y) % 5) as f32 / 5.0),
                1.0,
            ),
            (
                Image::from_fn(61, 40, |x, y| ((x * y) % 7) as f32 / 7.0),
                1.0,
            ),
            (
                Image::from_fn(50, 48, |x, y| ((x + 3 * y) % 9) as f32 / 9.0),
                0.5,
            ),
        ];
        for (img, delta_min) in cases {
            let params = SiftParams {
                delta_min,
                sigma_min: 1.6 * delta_min,
                ..SiftParams::default()
            };
            let want = direct(&img, &params);
            let mut ss = ScaleSpace::new(img.dimensions(), &params, &mut buffers);
            assert_eq!(ss.octaves.len(), want.len());
            for (o, gauss) in want.iter().enumerate() {
                ss.build_octave(o, &img, &params);
                ss.with_octave(o, |v| {
                    assert_eq!((v.width(), v.height()), gauss[0].dimensions());
                    for (s, g) in gauss.iter().enumerate() {
                        assert_eq!(v.gauss(s), g.data(), "octave {o} slot {s}");
                    }
                    assert_eq!(v.dog(1, 3, 2), gauss[2].get(3, 2) - gauss[1].get(3, 2));
                });
            }
            // The kept slots stay whole after later octaves overwrite the work planes.
            for (o, gauss) in want.iter().enumerate() {
                for (s, g) in gauss.iter().enumerate().take(params.n_spo + 1).skip(1) {
                    let (kept, _, _) = ss.kept_slot_and_two_planes(o, s);
                    assert_eq!(kept, g.data(), "kept octave {o} slot {s}");
                }
            }
        }
    }

    /// IPOL Algorithm 1 written plainly with whole images.
    fn direct(image: &Image, params: &SiftParams) -> Vec<Vec<Image>> {
        let geometry = octaves(image.dimensions(), params);
        let seed = if (params.delta_min - 1.0).abs() < 1e-12 {
            image.clone()
        } else {
            let (w, h) = resampled_size(image.dimensions(), params.delta_min);
            Image::from_fn(w, h, |x, y| {
                let sx = (x as f64 * params.delta_min).min((image.width() - 1) as f64);
                let sy = (y as f64 * params.delta_min).min((image.height() - 1) as f64);
                image.sample_bilinear(sx, sy).unwrap()
            })
        };
        let seed_blur =
            (params.sigma_min.powi(2) - params.sigma_in.powi(2)).sqrt() / params.delta_min;
        let mut first = gaussian_blur(&seed, seed_blur);
        let n = params.n_spo;
        let mut out = Vec::new();
        for _ in &geometry {
            let mut gauss = vec![first];
            for s in 1..n + 3 {
                let a = (2.0 * s as f64 / n as f64).exp2();
                let b = (2.0 * (s - 1) as f64 / n as f64).exp2();
                let rho = params.sigma_min / params.delta_min * (a - b).sqrt();
                let next = gaussian_blur(&gauss[s - 1], rho);
                gauss.push(next);
            }
            let g = &gauss[n];
            first = Image::from_fn(g.width().div_ceil(2), g.height().div_ceil(2), |x, y| {
                g.get(2 * x, 2 * y)
            });
            out.push(gauss);
        }
        out
    }
}
