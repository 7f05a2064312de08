//! The Gaussian scale space and its difference of Gaussians (IPOL "Anatomy of
//! the SIFT method", Rey-Otero & Delbracio 2014, §2 and Algorithm 1).
//!
//! Scales are absolute: the image in octave `o`, slot `s` has blur
//! `σ(o, s) = (δ_o / δ_min) · σ_min · 2^(s / n_spo)` in input pixels and its samples
//! lie `δ_o = δ_min · 2^o` input pixels apart, sample `m` at input coordinate `m·δ_o`.

use rayon::prelude::*;

use super::SiftParams;
use crate::vision::Image;
use crate::vision::filter::blur::gaussian_blur;

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

#[cfg(test)]
mod tests {
    use super::*;

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
