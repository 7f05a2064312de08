//! The Gaussian scale space and its difference of Gaussians (IPOL "Anatomy of
//! the SIFT method", Rey-Otero & Delbracio 2014, §2 and Algorithm 1).
//!
//! Scales are absolute: the image in octave `o`, slot `s` has blur
//! `σ(o, s) = (δ_o / δ_min) · σ_min · 2^(s / n_spo)` in input pixels and its samples
//! lie `δ_o = δ_min · 2^o` input pixels apart, sample `m` at input coordinate `m·δ_o`.

use rayon::prelude::*;

use super::SiftParams;
use crate::vision::Image;

/// One octave: `n_spo + 3` Gaussian images and `n_spo + 2` differences.
#[derive(Debug, Clone)]
pub struct Octave {
    /// Inter-sample distance δ_o in input pixels.
    pub delta: f64,
    /// Gaussian images v_s, s = 0 … n_spo + 2.
    pub gauss: Vec<Image>,
    /// Differences w_s = v_{s+1} − v_s, s = 0 … n_spo + 1.
    pub dog: Vec<Image>,
}

/// The whole scale space of one image.
#[derive(Debug, Clone)]
pub struct ScaleSpace {
    pub octaves: Vec<Octave>,
}

impl ScaleSpace {
    /// Builds the scale space of `image` (IPOL Algorithm 1).
    ///
    /// The number of octaves is the IPOL one, `⌊log2(min(w, h) / (δ_min · 12))⌋ + 1`
    /// (the last octave is at least 12 samples wide), capped by `params.n_oct_max`.
    /// Returns no octave for images too small to hold one.
    #[must_use]
    pub fn build(image: &Image, params: &SiftParams) -> Self {
        let n_spo = params.n_spo;
        let min_side = image.width().min(image.height()) as f64;
        if min_side < 12.0 * params.delta_min || image.is_empty() {
            return Self {
                octaves: Vec::new(),
            };
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let n_oct = ((min_side / (params.delta_min * 12.0)).log2().floor() as usize + 1)
            .min(params.n_oct_max.max(1));

        // Seed: resample to δ_min, then blur from σ_in to σ_min (in δ_min samples).
        let seed = if (params.delta_min - 1.0).abs() < 1e-12 {
            image.clone()
        } else {
            resample_bilinear(image, params.delta_min)
        };
        let seed_blur = (params.sigma_min.powi(2) - params.sigma_in.powi(2))
            .max(0.0)
            .sqrt()
            / params.delta_min;
        let mut first = gaussian_blur(&seed, seed_blur);

        let mut octaves = Vec::with_capacity(n_oct);
        for o in 0..n_oct {
            let delta = params.delta_min * f64::from(1u32 << o);
            let mut gauss = Vec::with_capacity(n_spo + 3);
            gauss.push(first);
            for s in 1..n_spo + 3 {
                // Blur increment between slots, in samples of this octave: σ_min/δ_min ·
                // sqrt(2^(2s/n) − 2^(2(s−1)/n)) (IPOL eq. 6), independent of the octave.
                let a = (2.0 * s as f64 / n_spo as f64).exp2();
                let b = (2.0 * (s - 1) as f64 / n_spo as f64).exp2();
                let rho = params.sigma_min / params.delta_min * (a - b).sqrt();
                let next = gaussian_blur(&gauss[s - 1], rho);
                gauss.push(next);
            }
            let dog = (0..n_spo + 2)
                .into_par_iter()
                .map(|s| difference(&gauss[s + 1], &gauss[s]))
                .collect();
            first = subsample2(&gauss[n_spo]);
            octaves.push(Octave { delta, gauss, dog });
            if first.width() < 2 || first.height() < 2 {
                break;
            }
        }
        Self { octaves }
    }
}

/// `a − b`, sample by sample.
fn difference(a: &Image, b: &Image) -> Image {
    let data = a.data().iter().zip(b.data()).map(|(x, y)| x - y).collect();
    Image::from_vec(a.width(), a.height(), data).expect("both images have the same size")
}

/// Every other sample in both directions (δ doubles).
#[must_use]
pub fn subsample2(image: &Image) -> Image {
    let (w, h) = (image.width().div_ceil(2), image.height().div_ceil(2));
    Image::from_fn(w, h, |x, y| image.get(2 * x, 2 * y))
}

/// Bilinear resampling to inter-sample distance `delta` (input pixels): output
/// sample `m` lies at input coordinate `m·delta` (IPOL's interpolation of the seed).
#[must_use]
pub fn resample_bilinear(image: &Image, delta: f64) -> Image {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let (w, h) = (
        ((image.width() - 1) as f64 / delta).floor() as usize + 1,
        ((image.height() - 1) as f64 / delta).floor() as usize + 1,
    );
    let mut out = Image::zeros(w, h);
    out.data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            let sy = (y as f64 * delta).min((image.height() - 1) as f64);
            for (x, v) in row.iter_mut().enumerate() {
                let sx = (x as f64 * delta).min((image.width() - 1) as f64);
                *v = image.sample_bilinear(sx, sy).unwrap_or(0.0);
            }
        });
    out
}

/// Normalised Gaussian kernel of standard deviation `sigma`, radius ⌈4σ⌉.
#[must_use]
pub fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let radius = (4.0 * sigma).ceil().max(1.0) as usize;
    let mut k: Vec<f64> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-d * d / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let sum: f64 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= sum);
    #[allow(clippy::cast_possible_truncation)]
    k.into_iter().map(|v| v as f32).collect()
}

/// Index into `[0, n)` with symmetric (half-sample) mirroring at both ends.
#[inline]
fn mirror(i: isize, n: usize) -> usize {
    let n = n as isize;
    let period = 2 * n;
    let mut j = i.rem_euclid(period);
    if j >= n {
        j = period - 1 - j;
    }
    #[allow(clippy::cast_sign_loss)]
    let j = j as usize;
    j
}

/// Separable Gaussian blur with symmetric boundary, parallel over rows.
///
/// `sigma ≤ 0` returns a copy.
#[must_use]
pub fn gaussian_blur(image: &Image, sigma: f64) -> Image {
    if sigma <= 0.0 || image.is_empty() {
        return image.clone();
    }
    let kernel = gaussian_kernel(sigma);
    let r = kernel.len() / 2;
    let (w, h) = image.dimensions();

    // Horizontal pass: pad each row by mirroring, then a straight dot product.
    let mut tmp = Image::zeros(w, h);
    tmp.data_mut().par_chunks_mut(w).enumerate().for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (y, out)| {
            let row = image.row(y);
            padded[r..r + w].copy_from_slice(row);
            for i in (0..r).chain(r + w..w + 2 * r) {
                padded[i] = row[mirror(i as isize - r as isize, w)];
            }
            // Tap by tap over the whole row: the inner loop vectorises.
            for (k, &g) in kernel.iter().enumerate() {
                for (o, &v) in out.iter_mut().zip(&padded[k..k + w]) {
                    *o += g * v;
                }
            }
        },
    );

    // Vertical pass: accumulate whole rows so the inner loop runs along x (vectorises).
    let mut out = Image::zeros(w, h);
    out.data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, orow)| {
            for (k, &g) in kernel.iter().enumerate() {
                let sy = mirror(y as isize + k as isize - r as isize, h);
                for (o, &v) in orow.iter_mut().zip(tmp.row(sy)) {
                    *o += g * v;
                }
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct 2-D convolution with the same kernel and boundary: the reference.
    fn naive_blur(image: &Image, sigma: f64) -> Image {
        let k = gaussian_kernel(sigma);
        let r = (k.len() / 2) as isize;
        let (w, h) = image.dimensions();
        Image::from_fn(w, h, |x, y| {
            let mut acc = 0.0f64;
            for (j, kj) in k.iter().enumerate() {
                for (i, ki) in k.iter().enumerate() {
                    let sx = mirror(x as isize + i as isize - r, w);
                    let sy = mirror(y as isize + j as isize - r, h);
                    acc += f64::from(*ki) * f64::from(*kj) * f64::from(image.get(sx, sy));
                }
            }
            acc as f32
        })
    }

    #[test]
    fn separable_blur_matches_direct_convolution() {
        let img = Image::from_fn(13, 9, |x, y| ((x * 7 + y * 13) % 11) as f32 / 10.0);
        for sigma in [0.6, 1.3, 3.0] {
            let fast = gaussian_blur(&img, sigma);
            let slow = naive_blur(&img, sigma);
            for (a, b) in fast.data().iter().zip(slow.data()) {
                assert!((a - b).abs() < 1e-5, "σ={sigma}: {a} vs {b}");
            }
        }
    }

    #[test]
    fn blur_preserves_mean_of_constant_and_mirror_is_symmetric() {
        let img = Image::filled(5, 4, 0.25);
        let b = gaussian_blur(&img, 2.0);
        assert!(b.data().iter().all(|v| (v - 0.25).abs() < 1e-6));
        assert_eq!(mirror(-1, 5), 0);
        assert_eq!(mirror(5, 5), 4);
        assert_eq!(mirror(-6, 5), 4);
    }

    #[test]
    fn octave_count_and_sizes_follow_ipol() {
        let img = Image::from_fn(100, 60, |x, y| ((x ^ y) & 1) as f32);
        let params = SiftParams::default();
        let ss = ScaleSpace::build(&img, &params);
        // min side 60, δ_min 0.5: ⌊log2(60/6)⌋ + 1 = 4 octaves.
        assert_eq!(ss.octaves.len(), 4);
        assert_eq!(ss.octaves[0].gauss[0].dimensions(), (199, 119));
        assert_eq!(ss.octaves[1].gauss[0].dimensions(), (100, 60));
        assert_eq!(ss.octaves[0].gauss.len(), params.n_spo + 3);
        assert_eq!(ss.octaves[0].dog.len(), params.n_spo + 2);
    }
}
