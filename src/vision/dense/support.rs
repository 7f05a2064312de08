//! Whether the micrographs support a match, pixel by pixel (beyond the paper): where they
//! cannot tell, the disparity is unknown rather than invented by the matcher's smoothness.
//!
//! Two tests on the rectified pair (parallax along +x), beside the left–right check of
//! [`super::consistency`]:
//! Both judge the matcher's own Gaussian window (σ of the intensity refinement, or the
//! descriptor's extent), which is what decides a match:
//! 1. **texture**: the Cramér–Rao bound of the disparity over the window
//!    ([`crate::vision::precision`]: `σ_d² = 2σ² / (N · ḡ²)`, `N = 4πσ_w²`), with the
//!    signal-to-noise ratio of the gradient energy along x measured by the correlation of
//!    both images' gradients at the match (their noise is independent, their texture common),
//!    so that neither the noise's level nor its correlation after resampling has to be known;
//!    above `max_bound_px` the window has no texture along the parallax that stands out of
//!    the noise. The texture must hold throughout the window (every pixel within `2σ_w`
//!    passes): beside a featureless area a window textured only at its edge takes the
//!    disparity of whatever lies there (a raised feature's), not its own;
//! 2. **distinctiveness**: the window's mean squared difference between the left image and
//!    the right one at the match, against the same at offsets of 2 to `reach_px` pixels along
//!    the row; when another offset comes within `min_distinctiveness` standard deviations of
//!    the noise's share of that difference (`2σ² · √(2/N)`, σ the noise floor that
//!    [`noise_sigma`] estimates), the matching cost has no unique minimum (repetitive or flat
//!    texture) and the match is ambiguous.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::filter::blur::blur_plane;
use crate::vision::precision::noise_sigma;

/// Parameters of the support test (`[reconstruction.dense.support]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SupportParams {
    /// Leave unknown the pixels the micrographs do not support (opt-in: on real pairs it still
    /// leaves too much unknown, see README).
    pub enabled: bool,
    /// σ of the Gaussian window both tests judge, pixels; 0: the matcher's own window.
    pub window_sigma: f32,
    /// Largest Cramér–Rao bound of the disparity (texture along the parallax against the noise floor), pixels.
    pub max_bound_px: f32,
    /// Offsets along the row that compete with the match, up to this many pixels (0: no distinctiveness test).
    pub reach_px: usize,
    /// Least excess of a competing offset's mean squared difference over the match's, in standard deviations of the noise's share.
    pub min_distinctiveness: f32,
}

impl Default for SupportParams {
    fn default() -> Self {
        Self {
            enabled: false,
            window_sigma: 0.0,
            max_bound_px: 0.2,
            reach_px: 16,
            min_distinctiveness: 4.0,
        }
    }
}

impl SupportParams {
    /// The name of the first field out of range.
    #[must_use]
    pub fn invalid_field(&self) -> Option<&'static str> {
        let sigma_ok = |s: f32| s.is_finite() && (s == 0.0 || (0.5..=32.0).contains(&s));
        if !sigma_ok(self.window_sigma) {
            Some("support.window_sigma")
        } else if !(self.max_bound_px.is_finite() && self.max_bound_px > 0.0) {
            Some("support.max_bound_px")
        } else if self.reach_px > 256 {
            Some("support.reach_px")
        } else if !(self.min_distinctiveness.is_finite() && self.min_distinctiveness >= 0.0) {
            Some("support.min_distinctiveness")
        } else {
            None
        }
    }
}

/// Why a pixel of the height map has no measured height: the code `confidence.tif` carries in
/// its second page (0 where the height is measured).
#[repr(u8)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Unknown {
    /// Measured: not unknown.
    Measured = 0,
    /// Interpolated between measured neighbours (`fill_max_gap`): an estimate, not a measurement.
    Interpolated = 1,
    /// Not seen by both micrographs: outside the rectified overlap, or the match leaves the other image.
    NotSeen = 2,
    /// The two directions of matching disagree (an occlusion beside a step, or a mismatch).
    LeftRight = 3,
    /// No texture along the parallax above the noise floor.
    NoTexture = 4,
    /// Texture, but the matching cost has no unique minimum along the row (repetitive structure).
    Ambiguous = 5,
}

impl Unknown {
    /// Every code, in order.
    pub const ALL: [Self; 6] = [
        Self::Measured,
        Self::Interpolated,
        Self::NotSeen,
        Self::LeftRight,
        Self::NoTexture,
        Self::Ambiguous,
    ];

    /// The code written to `confidence.tif`.
    #[must_use]
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The kebab-case name report.json and the TIFF description use.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Measured => "measured",
            Self::Interpolated => "interpolated",
            Self::NotSeen => "not-seen",
            Self::LeftRight => "left-right",
            Self::NoTexture => "no-texture",
            Self::Ambiguous => "ambiguous",
        }
    }

    /// The reason of a code (`None` for a code sdsem does not write).
    #[must_use]
    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.get(usize::from(code)).copied()
    }
}

/// Mean over the valid pixels of a Gaussian window: `blur(v·m) / blur(m)`, `NaN` where the
/// window holds (almost) no valid pixel.
fn window_mean(values: &[f32], mask: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    let weighted: Vec<f32> = values.par_iter().zip(mask).map(|(v, m)| v * m).collect();
    let (num, den) = rayon::join(
        || blur_plane(&weighted, w, h, sigma),
        || blur_plane(mask, w, h, sigma),
    );
    num.par_iter()
        .zip(&den)
        .map(|(n, d)| if *d > 1e-3 { n / d } else { f32::NAN })
        .collect()
}

/// Per pixel, whether a `mark`ed pixel lies within `r` pixels (a square), in two passes of
/// running counts.
fn near(mark: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    let rows: Vec<bool> = mark
        .par_chunks(w)
        .flat_map_iter(|row| {
            let mut prefix = vec![0u32; w + 1];
            for (x, &m) in row.iter().enumerate() {
                prefix[x + 1] = prefix[x] + u32::from(m);
            }
            (0..w).map(move |x| prefix[(x + r + 1).min(w)] > prefix[x.saturating_sub(r)])
        })
        .collect();
    let mut out = vec![false; w * h];
    out.par_iter_mut().enumerate().for_each(|(q, o)| {
        let (x, y) = (q % w, q / w);
        *o = (y.saturating_sub(r)..(y + r + 1).min(h)).any(|yy| rows[yy * w + x]);
    });
    out
}

/// The offsets a match competes with, both signs, up to `reach`.
fn offsets(reach: usize) -> Vec<f32> {
    let mut s: Vec<usize> = [2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256]
        .into_iter()
        .filter(|&s| s <= reach)
        .collect();
    s.dedup();
    s.iter().flat_map(|&s| [s as f32, -(s as f32)]).collect()
}

/// The support test of the matches `disparity` (left canvas, `NaN` unknown) of the rectified
/// pair `(a, b)` with validity `(va, vb)`, over a window of σ `sigma` pixels (the matcher's,
/// unless `params.window_sigma` names one): per pixel [`Unknown::NoTexture`],
/// [`Unknown::Ambiguous`] or [`Unknown::Measured`] (supported, or no match to judge). `None`
/// when the noise floor cannot be measured (then nothing is judged).
#[must_use]
pub fn support_test(
    (a, b): (&Image, &Image),
    (va, vb): (&[bool], &[bool]),
    disparity: &Image,
    params: &SupportParams,
    sigma: f32,
) -> Option<Vec<Unknown>> {
    let sigma = if params.window_sigma > 0.0 {
        params.window_sigma
    } else {
        sigma.max(0.5)
    };
    let (w, h) = a.dimensions();
    let (ad, bd) = (a.data(), b.data());
    // The squared difference of the two images at the match and at an offset along the row.
    let du = disparity.data();
    let matched = |s: f32| -> (Vec<f32>, Vec<f32>) {
        (0..w * h)
            .into_par_iter()
            .map(|q| {
                let d = du[q];
                if !va[q] || !d.is_finite() {
                    return (0.0, 0.0);
                }
                let xr = (q % w) as f32 + d + s;
                if xr < 0.0 || xr > (w - 1) as f32 {
                    return (0.0, 0.0);
                }
                let x0 = xr.floor() as usize;
                let x1 = (x0 + 1).min(w - 1);
                let row = q - q % w;
                if !(vb[row + x0] && vb[row + x1]) {
                    return (0.0, 0.0);
                }
                let t = xr - x0 as f32;
                let v = bd[row + x0] + t * (bd[row + x1] - bd[row + x0]);
                let e = ad[q] - v;
                (e * e, 1.0)
            })
            .unzip()
    };
    let (e0, m0) = matched(0.0);
    // The noise floor ([`noise_sigma`], Immerkær) scales the distinctiveness test.
    let noise = [noise_sigma(a, Some(va))?, noise_sigma(b, Some(vb))?];
    let noise_var = (0.5 * (noise[0] * noise[0] + noise[1] * noise[1])) as f32;
    // 1. Texture: the gradients along x of both images at the match. Their noise is
    // independent and their texture common, so over the window the correlation
    // ρ = ⟨g_a g_b⟩ / √(⟨g_a²⟩⟨g_b²⟩) is s / (1 + s) for a signal-to-noise ratio s of the
    // gradient energy, whatever the noise's level or its correlation after resampling; with
    // the noise's gradient variance σ²/2 the bound is σ_d² = 2σ² / (N s σ²/2) = 4 / (N s).
    let grad = |d: &[f32], v: &[bool], q: usize| -> Option<f32> {
        let x = q % w;
        (x > 0 && x + 1 < w && v[q - 1] && v[q] && v[q + 1]).then(|| 0.5 * (d[q + 1] - d[q - 1]))
    };
    type Planes = (Vec<f32>, (Vec<f32>, (Vec<f32>, Vec<f32>)));
    let (gab, (gaa, (gbb, gm))): Planes = (0..w * h)
        .into_par_iter()
        .map(|q| {
            let none = (0.0, (0.0, (0.0, 0.0)));
            let d = du[q];
            let Some(ga) = grad(ad, va, q).filter(|_| d.is_finite()) else {
                return none;
            };
            let xr = (q % w) as f32 + d;
            if xr < 1.0 || xr > (w - 2) as f32 {
                return none;
            }
            let x0 = xr.floor() as usize;
            let row = q - q % w;
            let (Some(g0), Some(g1)) = (grad(bd, vb, row + x0), grad(bd, vb, row + x0 + 1)) else {
                return none;
            };
            let gb = g0 + (xr - x0 as f32) * (g1 - g0);
            (ga * gb, (ga * ga, (gb * gb, 1.0)))
        })
        .unzip();
    let (mab, (maa, mbb)) = rayon::join(
        || window_mean(&gab, &gm, w, h, sigma),
        || {
            rayon::join(
                || window_mean(&gaa, &gm, w, h, sigma),
                || window_mean(&gbb, &gm, w, h, sigma),
            )
        },
    );
    let n_eff = 4.0 * std::f32::consts::PI * sigma * sigma;
    let max_var = params.max_bound_px * params.max_bound_px;
    let textured: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|q| {
            let rho = mab[q] / (maa[q] * mbb[q]).sqrt();
            // s = ρ / (1 − ρ); 4 / (N s) ≤ max²  ⇔  4 (1 − ρ) ≤ N ρ max².
            rho.is_finite() && rho > 0.0 && 4.0 * (1.0 - rho) <= n_eff * rho * max_var
        })
        .collect();
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let reach = (2.0 * sigma).ceil() as usize;
    let flat: Vec<bool> = textured.iter().zip(va).map(|(t, v)| *v && !t).collect();
    let textured: Vec<bool> = near(&flat, w, h, reach)
        .into_iter()
        .zip(&textured)
        .map(|(n, t)| *t && !n)
        .collect();
    // 2. Distinctiveness: the match's window against competing offsets'.
    let at_match = window_mean(&e0, &m0, w, h, sigma);
    let mut least_excess = vec![f32::INFINITY; w * h];
    for s in offsets(params.reach_px) {
        let (e, m) = matched(s);
        let c = window_mean(&e, &m, w, h, sigma);
        least_excess
            .par_iter_mut()
            .zip(&c)
            .zip(&at_match)
            .for_each(|((l, &c), &c0)| {
                if c.is_finite() && c0.is_finite() {
                    *l = l.min(c - c0);
                }
            });
    }
    // The noise's own mean squared difference between the two images is 2σ²; its window
    // mean varies by about 2σ² · √(2/N).
    let min_excess = params.min_distinctiveness * 2.0 * noise_var * (2.0 / n_eff).sqrt();
    Some(
        (0..w * h)
            .into_par_iter()
            .map(|q| {
                if !va[q] || !du[q].is_finite() {
                    Unknown::Measured
                } else if !textured[q] {
                    Unknown::NoTexture
                } else if least_excess[q] < min_excess {
                    Unknown::Ambiguous
                } else {
                    Unknown::Measured
                }
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{Layer, Texture, render};

    /// Uniform deviates in [0, 1) (xorshift), for test noise.
    fn uniform(state: &mut u64) -> f32 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 40) as f32 / (1u64 << 24) as f32
    }

    fn shifted(width: usize, d: f64, noise: f64) -> crate::testing::SyntheticPair {
        let layers = vec![Layer {
            disparity: Box::new(move |_, _| d),
            region: Box::new(|_, _| true),
        }];
        render(width, 40, Texture::new(5), &layers, 0.0, noise)
    }

    #[test]
    fn a_textured_match_is_supported_and_a_flat_patch_is_not() {
        let pair = shifted(120, 3.0, 0.01);
        let mut a = pair.left.clone();
        let mut b = pair.right.clone();
        // Columns 60..100 of both images flat grey plus the same noise level.
        let mut k = 0x1234_5678_u64;
        let mut noise = || 0.01 * 3f32.sqrt() * (2.0 * uniform(&mut k) - 1.0);
        for y in 0..40 {
            for x in 60..100 {
                a.set(x, y, 0.5 + noise());
                b.set(x, y, 0.5 + noise());
            }
        }
        let valid = vec![true; 120 * 40];
        let disparity = Image::filled(120, 40, 3.0);
        let r = support_test(
            (&a, &b),
            (&valid, &valid),
            &disparity,
            &SupportParams::default(),
            3.0,
        )
        .unwrap();
        let at = |x: usize| r[20 * 120 + x];
        assert_eq!(at(30), Unknown::Measured);
        assert_eq!(at(80), Unknown::NoTexture);
    }

    #[test]
    fn a_texture_repeating_along_the_row_is_ambiguous() {
        // Stripes of period 6 px across the rows, plus noise: texture, but every 6 px alike.
        let (w, h) = (120, 40);
        let stripes = |x: f64| (x * std::f64::consts::TAU / 6.0).sin() as f32;
        let mut k = 0x9876_5432_u64;
        let mut noise = || 0.02 * (2.0 * uniform(&mut k) - 1.0);
        let a = Image::from_fn(w, h, |x, _| stripes(x as f64) + noise());
        let b = Image::from_fn(w, h, |x, _| stripes(x as f64 - 2.0) + noise());
        let valid = vec![true; w * h];
        let disparity = Image::filled(w, h, 2.0);
        let r = support_test(
            (&a, &b),
            (&valid, &valid),
            &disparity,
            &SupportParams::default(),
            3.0,
        )
        .unwrap();
        assert_eq!(r[20 * w + 50], Unknown::Ambiguous);
        // Without competing offsets the same pixel passes.
        let none = SupportParams {
            reach_px: 0,
            ..SupportParams::default()
        };
        let r = support_test((&a, &b), (&valid, &valid), &disparity, &none, 3.0).unwrap();
        assert_eq!(r[20 * w + 50], Unknown::Measured);
    }

    #[test]
    fn near_marks_the_square_around_each_mark() {
        let mut mark = vec![false; 7 * 5];
        mark[2 * 7 + 3] = true;
        let n = near(&mark, 7, 5, 1);
        let count = n.iter().filter(|&&b| b).count();
        assert_eq!(count, 9);
        assert!(n[7 + 2] && n[3 * 7 + 4] && !n[3 * 7 + 5] && !n[0]);
    }

    /// A flat floor beside a textured block: the floor pixels whose window (σ 3) reaches the
    /// block's edge only at its rim, 2σ away, are not supported either.
    #[test]
    fn texture_at_the_window_edge_does_not_support_a_flat_pixel() {
        let (w, h) = (100, 30);
        let mut k = 0x5555_u64;
        let mut noise = || 0.01 * (2.0 * uniform(&mut k) - 1.0);
        let tex = Texture::new(9);
        let a = Image::from_fn(w, h, |x, y| {
            let v = if x < 50 {
                tex.at(x as f64, y as f64) as f32
            } else {
                0.3
            };
            v + noise()
        });
        let b = Image::from_fn(w, h, |x, y| {
            let v = if x < 52 {
                tex.at(x as f64 - 2.0, y as f64) as f32
            } else {
                0.3
            };
            v + noise()
        });
        let valid = vec![true; w * h];
        let disparity = Image::filled(w, h, 2.0);
        let r = support_test(
            (&a, &b),
            (&valid, &valid),
            &disparity,
            &SupportParams::default(),
            3.0,
        )
        .unwrap();
        let row = &r[15 * w..16 * w];
        assert_eq!(row[30], Unknown::Measured);
        for (x, u) in row.iter().enumerate().take(90).skip(56) {
            assert_eq!(*u, Unknown::NoTexture, "x = {x}");
        }
    }

    #[test]
    fn codes_round_trip() {
        for u in Unknown::ALL {
            assert_eq!(Unknown::from_code(u.code()), Some(u));
        }
        assert_eq!(Unknown::from_code(6), None);
        assert_eq!(SupportParams::default().invalid_field(), None);
    }
}
