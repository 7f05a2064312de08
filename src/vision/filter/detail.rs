//! Noise-adaptive restoration of the detail a smoothing filter took away (beyond the paper).
//!
//! The bilateral grid (σs = 3) removes the matcher's pixel-scale noise, and with it the relief
//! of the same scale: scratches, cusps, the rims of small particles. Per pixel, the detail
//! `r = d − s` between the measured disparity `d` and its smoothed `s` is put back with the
//! gain of a local Wiener (Lee 1980) filter,
//!
//! `out = s + g · r`, `g = max(0, 1 − κ·σ²(p) / E(p))`,
//!
//! with `E` the local mean of `r²` (Gaussian window) and `σ²(p)` the variance of the matcher's
//! disparity the micrographs predict at `p`: the Cramér–Rao bound of a window match,
//! `2σ_n² / (N · ḡ²(p))` (see [`crate::vision::precision`]), from the scan noise `σ_n` of both
//! images and the gradient energy `ḡ²` along the parallax (+x on the rectified canvas) in a
//! Gaussian window of `N = 4πσ_w²` pixels. Where the detail is no stronger than the noise
//! predicts, the smoothed value stays (`g = 0`); where the relief stands out of the noise,
//! the measurement stays (`g → 1`); without noise (`σ_n = 0`) the filter gives back the
//! measurement. `κ` absorbs what the bound leaves out: the share of the noise the filter
//! removes and the matcher's edge-aware windows, which see fewer pixels than `N`. A measured
//! value farther than `max_px` from its smoothed one is taken for an outlier (beside a wall,
//! a mismatch): it keeps the smoothed value and stays out of `E`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::blur::blur_in_place;
use crate::vision::Image;
use crate::vision::precision::{noise_sigma, windowed_gradient_energy};

/// Parameters of the detail restoration after the bilateral filter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DetailParams {
    /// Put back the detail the filter removed where it stands out of the predicted noise (opt-in).
    pub enabled: bool,
    /// κ: multiple of the predicted noise variance the local detail energy must exceed (smaller keeps more).
    pub noise_scale: f32,
    /// Largest detail put back (by either), disparity pixels; a farther measurement is an outlier.
    pub max_px: f32,
    /// σ of the Gaussian that smooths the detail before it is put back whole (twicing), pixels; 0 = none.
    pub twicing_sigma: f32,
}

impl Default for DetailParams {
    fn default() -> Self {
        Self {
            enabled: false,
            noise_scale: 8.0,
            max_px: 0.5,
            twicing_sigma: 0.0,
        }
    }
}

impl DetailParams {
    /// The first field out of its range, by name.
    #[must_use]
    pub fn invalid_field(&self) -> Option<&'static str> {
        if !(self.noise_scale.is_finite() && self.noise_scale >= 0.0) {
            Some("detail.noise_scale")
        } else if self.max_px.is_nan() || self.max_px < 0.0 {
            Some("detail.max_px")
        } else if !(self.twicing_sigma.is_finite() && self.twicing_sigma >= 0.0) {
            Some("detail.twicing_sigma")
        } else {
            None
        }
    }
}

/// Per pixel of the rectified pair `(a, b)` (valid where `va`, `vb`), the Cramér–Rao bound on
/// the variance of a horizontal disparity measured with a Gaussian window of `window_sigma`
/// pixels, disparity px² (infinite where the window holds no gradient along x). `None` when
/// the noise cannot be measured (too few valid neighbourhoods).
#[must_use]
pub fn disparity_noise_variance(
    (a, b): (&Image, &Image),
    (va, vb): (&[bool], &[bool]),
    window_sigma: f32,
) -> Option<Vec<f32>> {
    let (w, h) = a.dimensions();
    let noise = [noise_sigma(a, Some(va))?, noise_sigma(b, Some(vb))?];
    // The symmetric gradient's noise: a central difference of white noise has variance σ²/2,
    // the mean of both images' noise.
    let noise_var = 0.5 * (noise[0] * noise[0] + noise[1] * noise[1]);
    let grad_noise = (0.5 * noise_var) as f32;
    let d = a.data();
    // Gradient energy along x above the noise's share and its weight, blurred together.
    let planes = windowed_gradient_energy(
        (w, h),
        |q| {
            let x = q % w;
            (x > 0 && x + 1 < w && va[q] && va[q - 1] && va[q + 1])
                .then(|| 0.5 * (d[q + 1] - d[q - 1]))
        },
        grad_noise,
        window_sigma,
    );
    let n_eff = 4.0 * std::f32::consts::PI * window_sigma * window_sigma;
    let two_noise = (2.0 * noise_var) as f32;
    Some(
        planes
            .into_par_iter()
            .map(|[e, n]| {
                let mean = if n > 1e-3 { e / n } else { 0.0 };
                if mean > 0.0 {
                    two_noise / (n_eff * mean)
                } else if two_noise > 0.0 {
                    f32::INFINITY
                } else {
                    0.0
                }
            })
            .collect(),
    )
}

/// `smooth + g · (raw − smooth)` per pixel, `g = max(0, 1 − κ·noise_var / E)` with `E` the
/// local mean of `(raw − smooth)²` over a Gaussian window of `sigma` pixels (see the module).
/// Pixels where `keep` is false (interpolated, not measured), either input is not finite or
/// `|raw − smooth| > max_px` keep `smooth` and add nothing to `E`.
#[must_use]
pub fn restore_detail(
    (raw, smooth): (&Image, &Image),
    noise_var: &[f32],
    keep: &[bool],
    sigma: f32,
    (kappa, max_px): (f32, f32),
) -> Image {
    let (w, h) = raw.dimensions();
    let residual: Vec<f32> = raw
        .data()
        .par_iter()
        .zip(smooth.data())
        .zip(keep)
        .map(|((&d, &s), &k)| {
            if k && d.is_finite() && s.is_finite() && (d - s).abs() <= max_px {
                d - s
            } else {
                f32::NAN
            }
        })
        .collect();
    let mut energy: Vec<[f32; 2]> = residual
        .par_iter()
        .map(|&r| {
            if r.is_finite() {
                [r * r, 1.0]
            } else {
                [0.0, 0.0]
            }
        })
        .collect();
    let mut scratch = vec![[0f32; 2]; w * h];
    blur_in_place(&mut energy, &mut scratch, w, h, sigma);
    let mut out = smooth.clone();
    out.data_mut()
        .par_iter_mut()
        .zip(&residual)
        .zip(&energy)
        .zip(noise_var)
        .for_each(|(((o, &r), &[e, n]), &nv)| {
            if !r.is_finite() || n <= 1e-6 {
                return;
            }
            let e = e / n;
            if e > 0.0 {
                let g = (1.0 - kappa * nv / e).max(0.0);
                *o += g * r;
            }
        });
    out
}

/// Twicing (Tukey 1977): `smooth + G_σ ∗ (raw − smooth)`, the detail the filter removed,
/// smoothed by a Gaussian of `sigma` (weighted by `weight`, normalised) and put back. With a
/// smoothing `S` of frequency response `s`, the result's response is `1 − (1 − s)²`: flat
/// where `s` is near 1 (the relief a few filter widths wide keeps its height), still falling
/// as `2s` where `s` is small (the pixel-scale noise stays removed). Pixels where `keep` is
/// false, either input is not finite or `|raw − smooth| > max_px` add nothing to the detail;
/// where `smooth` is finite they still receive it.
#[must_use]
pub fn twice(
    (raw, smooth): (&Image, &Image),
    weight: Option<&Image>,
    keep: &[bool],
    sigma: f32,
    max_px: f32,
) -> Image {
    let (w, h) = raw.dimensions();
    let mut planes: Vec<[f32; 2]> = raw
        .data()
        .par_iter()
        .zip(smooth.data())
        .zip(keep)
        .enumerate()
        .map(|(p, ((&d, &s), &k))| {
            let wt = weight.map_or(1.0, |im| im.data()[p]);
            if k && d.is_finite() && s.is_finite() && (d - s).abs() <= max_px && wt > 0.0 {
                [wt * (d - s), wt]
            } else {
                [0.0, 0.0]
            }
        })
        .collect();
    let mut scratch = vec![[0f32; 2]; w * h];
    blur_in_place(&mut planes, &mut scratch, w, h, sigma);
    let mut out = smooth.clone();
    out.data_mut()
        .par_iter_mut()
        .zip(&planes)
        .for_each(|(o, &[r, n])| {
            if o.is_finite() && n > 1e-6 {
                *o += r / n;
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::vision::filter::bilateral_grid::{BilateralParams, bilateral_filter};

    /// Uniform deviates in [−½, ½), one stream per seed.
    fn noise(seed: u32) -> impl FnMut() -> f32 {
        let mut s = seed;
        move || {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        }
    }

    /// A slope with a raised bar 3 px wide (height 1.5 px) on part of it: relief a σs = 3
    /// filter flattens.
    fn relief(x: usize, y: usize) -> f32 {
        0.05 * x as f32
            + if (30..33).contains(&x) && y > 10 {
                1.5
            } else {
                0.0
            }
    }

    /// RMS error against `relief` away from the bar (columns 5–24, rows 0–7).
    fn flat(im: &Image) -> f32 {
        let s: f32 = (5..25)
            .flat_map(|x| (0..8).map(move |y| (x, y)))
            .map(|(x, y)| (im.get(x, y) - relief(x, y)).powi(2))
            .sum();
        (s / 160.0).sqrt()
    }

    fn rms_against(im: &Image, truth: impl Fn(usize, usize) -> f32) -> f32 {
        let (w, h) = im.dimensions();
        let s: f32 = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| (im.get(x, y) - truth(x, y)).powi(2))
            .sum();
        (s / (w * h) as f32).sqrt()
    }

    fn filter(raw: &Image, noise_var: f32, kappa: f32) -> (Image, Image) {
        let params = BilateralParams::default();
        let (smooth, _) = bilateral_filter(raw, None, &params);
        let nv = vec![noise_var; raw.data().len()];
        let keep = vec![true; raw.data().len()];
        let out = restore_detail((raw, &smooth), &nv, &keep, params.sigma_s, (kappa, 2.0));
        (smooth, out)
    }

    /// Without noise the measurement comes back whole: the bar keeps its height, which the
    /// bilateral filter alone takes a good part of.
    #[test]
    fn noise_free_relief_is_given_back() {
        let raw = Image::from_fn(64, 40, relief);
        let (smooth, out) = filter(&raw, 0.0, 4.0);
        assert!(rms_against(&out, relief) < 1e-5);
        assert!(rms_against(&smooth, relief) > 0.05);
        assert!(out.get(31, 30) - out.get(26, 30) > 1.7);
        assert!(smooth.get(31, 30) - smooth.get(26, 30) < 1.3);
    }

    /// With noise of the predicted variance: flat stretches are smoothed as by the filter
    /// alone, the bar keeps most of its height, and the error falls below both.
    #[test]
    fn noise_is_removed_where_the_relief_does_not_stand_out() {
        let amp = 0.5f32; // uniform on ±0.25 px: variance amp²/12
        let mut rnd = noise(9);
        let raw = Image::from_fn(64, 40, |x, y| relief(x, y) + amp * rnd());
        let (smooth, out) = filter(&raw, amp * amp / 12.0, 1.0);
        let err_raw = rms_against(&raw, relief);
        let (err_s, err_o) = (rms_against(&smooth, relief), rms_against(&out, relief));
        assert!(err_o < 0.6 * err_raw, "{err_o} vs raw {err_raw}");
        assert!(err_o < err_s, "{err_o} vs smoothed {err_s}");
        // Away from the bar, as smooth as the filter alone.
        assert!(
            flat(&out) < 1.3 * flat(&smooth),
            "{} vs {}",
            flat(&out),
            flat(&smooth)
        );
        // The bar's height, averaged along it: within 10 % (the filter alone loses more).
        let bar = |im: &Image| {
            (15..40)
                .map(|y| im.get(31, y) - 0.5 * (im.get(26, y) + im.get(36, y)))
                .sum::<f32>()
                / 25.0
        };
        assert!((bar(&out) / 1.5 - 1.0).abs() < 0.1, "{}", bar(&out));
        assert!(
            bar(&smooth) < bar(&out) - 0.1,
            "{} vs {}",
            bar(&smooth),
            bar(&out)
        );
    }

    /// Twicing gives back most of what the filter took from a bar three pixels wide, keeps
    /// most of the noise reduction on flat stretches, and puts back nothing where the detail
    /// is an outlier or not measured.
    #[test]
    fn twicing_restores_relief_and_keeps_most_smoothing() {
        let amp = 0.5f32;
        let mut rnd = noise(3);
        let raw = Image::from_fn(64, 40, |x, y| relief(x, y) + amp * rnd());
        let params = BilateralParams::default();
        let (smooth, _) = bilateral_filter(&raw, None, &params);
        let keep = vec![true; 64 * 40];
        let out = twice((&raw, &smooth), None, &keep, params.sigma_s, 3.0);
        let bar = |im: &Image| {
            (15..40)
                .map(|y| im.get(31, y) - 0.5 * (im.get(24, y) + im.get(38, y)))
                .sum::<f32>()
                / 25.0
        };
        let (b_s, b_o) = (bar(&smooth), bar(&out));
        assert!(b_o > b_s + 0.2, "bar {b_o} vs smoothed {b_s}");
        assert!(
            flat(&out) < 0.6 * flat(&raw),
            "{} vs raw {}",
            flat(&out),
            flat(&raw)
        );
        // Outliers (max_px 0) and pixels not kept add nothing: the smoothed value stays.
        let none = twice((&raw, &smooth), None, &keep, params.sigma_s, 0.0);
        let dropped = twice((&raw, &smooth), None, &vec![false; 64 * 40], 3.0, 3.0);
        for im in [&none, &dropped] {
            for (a, b) in im.data().iter().zip(smooth.data()) {
                assert!((a - b).abs() < 1e-6);
            }
        }
    }

    /// Unmeasured pixels and pixels not kept leave the smoothed value; `NaN` stays `NaN`.
    #[test]
    fn pixels_not_kept_stay_smoothed() {
        let raw = Image::from_fn(32, 24, |x, y| {
            if (x, y) == (5, 5) {
                f32::NAN
            } else {
                relief(x + 15, y)
            }
        });
        let (smooth, _) = bilateral_filter(&raw, None, &BilateralParams::default());
        let keep: Vec<bool> = (0..32 * 24).map(|p| p % 32 != 16).collect();
        let nv = vec![0.0; 32 * 24];
        let out = restore_detail((&raw, &smooth), &nv, &keep, 3.0, (4.0, 2.0));
        assert!(out.get(5, 5).is_nan());
        for y in 0..24 {
            assert_eq!(out.get(16, y).to_bits(), smooth.get(16, y).to_bits());
            assert!((out.get(15, y) - raw.get(15, y)).abs() < 1e-5);
        }
    }

    /// The predicted variance follows the noise squared and the texture: (almost) none
    /// without noise, four times as much with twice the noise, infinite without texture along x.
    #[test]
    fn predicted_variance_follows_noise_and_texture() {
        // Smooth enough that the noise estimate reads (almost) no noise in it.
        let tex = |x: usize, y: usize| 0.5 + 0.2 * (0.35 * x as f32 + 0.2 * y as f32).sin();
        let pair = |sigma: f32, seed: u32| {
            let mut rnd = noise(seed);
            // Uniform deviates scaled to σ.
            Image::from_fn(96, 64, |x, y| tex(x, y) + sigma * 12f32.sqrt() * rnd())
        };
        let valid = vec![true; 96 * 64];
        let at = |v: &[f32]| v[32 * 96 + 48];
        let var = |sigma: f32| {
            let (a, b) = (pair(sigma, 1), pair(sigma, 2));
            disparity_noise_variance((&a, &b), (&valid, &valid), 4.0).unwrap()
        };
        let (v0, v1, v2) = (at(&var(0.0)), at(&var(0.01)), at(&var(0.02)));
        assert!(v0 < 0.01 * v1, "{v0} vs {v1}");
        assert!(v1 > 0.0 && (v2 / v1 - 4.0).abs() < 0.6, "{v1} {v2}");
        let stripes = Image::from_fn(96, 64, |_, y| {
            0.5 + 0.3 * (0.8 * y as f32).sin() + 0.01 * ((y * 7 + 3) % 5) as f32
        });
        let mut rnd = noise(5);
        let noisy = Image::from_fn(96, 64, |x, y| stripes.get(x, y) + 0.03 * rnd());
        let v = disparity_noise_variance((&noisy, &noisy), (&valid, &valid), 4.0).unwrap();
        assert!(at(&v) > 20.0 * v1, "{} vs {v1}", at(&v));
    }

    /// The result does not depend on the number of threads.
    #[test]
    fn parallel_equals_serial() {
        let mut rnd = noise(4);
        let raw = Image::from_fn(80, 50, |x, y| relief(x, y) + 0.3 * rnd());
        let run = || {
            let (a, b) = (
                Image::from_fn(80, 50, |x, y| (0.7 * x as f32 + 0.2 * y as f32).sin()),
                Image::from_fn(80, 50, |x, y| (0.7 * x as f32 + 0.2 * y as f32 + 0.1).sin()),
            );
            let valid = vec![true; 80 * 50];
            let nv = disparity_noise_variance((&a, &b), (&valid, &valid), 3.0).unwrap();
            let (smooth, _) = bilateral_filter(&raw, None, &BilateralParams::default());
            restore_detail((&raw, &smooth), &nv, &valid, 3.0, (4.0, 0.5))
        };
        let serial = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(run);
        let parallel = rayon::ThreadPoolBuilder::new()
            .num_threads(4)
            .build()
            .unwrap()
            .install(run);
        for (s, p) in serial.data().iter().zip(parallel.data()) {
            assert_eq!(s.to_bits(), p.to_bits());
        }
    }
}
