//! Heights the matcher lends to featureless pixels beside a step (beyond the paper): the rims
//! beside raised features on a featureless support.
//!
//! A window matcher measures a pixel by the texture in its window. Where the pixel itself
//! lies on a featureless area, that texture lies elsewhere, and the pixel takes the
//! disparity of whatever surface carries it. Between textures of one smooth surface that is
//! right (a few weak features spread over a flat substrate pin it down); beside a raised
//! feature on a featureless support it is not: the matcher's window, and its smoothness
//! term, lend the feature's disparity to the featureless support next to it ("foreground
//! fattening", Scharstein & Szeliski 2002), both directions of matching agree on the lent
//! disparity, so the left–right check passes, and the support test passes too, because the
//! feature's outline lies within the window. Where the step between the feature and its
//! support lies on the featureless area, no image can tell; the geometry can tell that the
//! pixel's disparity is not pinned by texture on both sides of it.
//!
//! On the rectified pair (parallax along +x), row by row:
//! 1. **texture along the parallax**: a pixel is textured where the energy of the gradient
//!    along x of the left micrograph, after a light Gaussian pre-smoothing (`band_sigma`),
//!    over a small Gaussian window (`texture_sigma`) stands `min_snr` standard deviations of
//!    its spread on noise alone above the noise's share (the noise from Immerkær's estimate,
//!    [`crate::vision::precision::noise_sigma`], through the filter's gain);
//! 2. **anchors**: the nearest textured pixel with a measured disparity on each side of a
//!    featureless measured pixel along its row, within `reach` matcher σ;
//! 3. the featureless pixel keeps its disparity only when it has both anchors and lies
//!    within `step_px` of their linear interpolation: it is then measured between two
//!    textures of one surface (or one smooth slope), not extrapolated across an outline that
//!    may be a step.
//!
//! Pure: images and the disparity in, a mask out; rows in parallel.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::filter::blur::{gaussian_blur, gaussian_kernel};

/// Parameters of the test (`[reconstruction.dense.anchor]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AnchorParams {
    /// Leave unknown the featureless pixels whose disparity texture on both sides along the parallax does not pin down (improved; paper: off).
    pub enabled: bool,
    /// σ of the Gaussian pre-smoothing of the left micrograph before its gradient along the parallax, pixels; 0: none.
    pub band_sigma: f32,
    /// σ of the Gaussian window over which the gradient's energy is judged, pixels.
    pub texture_sigma: f32,
    /// Excess of that energy over the noise's, in standard deviations of its spread on noise alone, above which a pixel is textured.
    pub min_snr: f32,
    /// Largest distance of a featureless pixel's disparity from the interpolation of its anchors', pixels.
    pub step_px: f32,
    /// How far along the row the anchors may lie, in matcher σ.
    pub reach: f32,
    /// A pixel is textured where either micrograph shows texture at the match (the right one
    /// at `x + d`): one micrograph's gradient undersells low-contrast texture.
    pub both_images: bool,
    /// Judge only featureless regions (4-connected) of at least this many matcher windows
    /// (`π·(2σ)²` pixels each): a support, not specks amid weak texture; 0: all.
    pub min_region: f32,
}

impl Default for AnchorParams {
    fn default() -> Self {
        Self {
            enabled: true,
            band_sigma: 1.0,
            texture_sigma: 3.0,
            min_snr: 4.0,
            step_px: 1.0,
            reach: 3.0,
            both_images: false,
            min_region: 8.0,
        }
    }
}

impl AnchorParams {
    /// `min_region` in pixels for the matcher's window σ `matcher_sigma`: a matcher window is
    /// `π·(2σ)²` pixels.
    #[must_use]
    // At most 1000 windows of a bounded σ: within usize.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    pub fn min_region_px(&self, matcher_sigma: f32) -> usize {
        (self.min_region * std::f32::consts::PI * (2.0 * matcher_sigma).powi(2)) as usize
    }

    /// The name of the first field out of range.
    #[must_use]
    pub fn invalid_field(&self) -> Option<&'static str> {
        let non_negative = |v: f32| v.is_finite() && v >= 0.0;
        if !(non_negative(self.band_sigma) && self.band_sigma <= 8.0) {
            Some("anchor.band_sigma")
        } else if !(self.texture_sigma.is_finite() && (0.5..=8.0).contains(&self.texture_sigma)) {
            Some("anchor.texture_sigma")
        } else if !non_negative(self.min_snr) {
            Some("anchor.min_snr")
        } else if !(self.step_px.is_finite() && self.step_px > 0.0) {
            Some("anchor.step_px")
        } else if !(self.reach.is_finite() && self.reach > 0.0 && self.reach <= 32.0) {
            Some("anchor.reach")
        } else if !non_negative(self.min_region) || self.min_region > 1000.0 {
            Some("anchor.min_region")
        } else {
            None
        }
    }
}

/// Per pixel: the energy of the gradient along x of `img`, pre-smoothed by `band_sigma`, over
/// a Gaussian window of `texture_sigma` stands `min_snr` standard deviations of its spread on
/// noise alone above what the noise gives (`noise`: the image's white-noise σ). The spread:
/// the window averages about `N / A` independent squares (`N = 4π·texture_sigma²` pixels,
/// `A = 4π·band_sigma²` the correlation area of the filtered noise), each of variance twice
/// its mean's square.
#[must_use]
pub fn textured_along_x(
    img: &Image,
    noise: f32,
    (band_sigma, texture_sigma): (f32, f32),
    min_snr: f32,
) -> Vec<bool> {
    let (energy, gain) = gradient_energy(img, (band_sigma, texture_sigma));
    let threshold = threshold(
        noise * noise * gain,
        (band_sigma, texture_sigma),
        min_snr,
        1.0,
    );
    energy.data().par_iter().map(|&e| e > threshold).collect()
}

/// The energy threshold: the noise's `mean` energy plus `min_snr` standard deviations of its
/// spread over `images` independent micrographs' windows.
fn threshold(mean: f32, (band_sigma, texture_sigma): (f32, f32), min_snr: f32, images: f32) -> f32 {
    let independent = images * (texture_sigma / band_sigma.max(0.5)).powi(2).max(1.0);
    mean * (1.0 + min_snr * (2.0 / independent).sqrt())
}

/// The windowed energy of the pre-smoothed gradient along x, and the filter's gain on white noise.
fn gradient_energy(img: &Image, (band_sigma, texture_sigma): (f32, f32)) -> (Image, f32) {
    let (w, h) = img.dimensions();
    let smooth = gaussian_blur(img, f64::from(band_sigma));
    // The filter's gain on white noise: Σ c² of the separable kernel `G(y) · (G(x−1) − G(x+1)) / 2`.
    let gain = if band_sigma > 0.0 {
        let k = gaussian_kernel(f64::from(band_sigma));
        let at = |i: isize| usize::try_from(i).ok().and_then(|i| k.get(i)).copied();
        let along_y: f32 = k.iter().map(|g| g * g).sum();
        let along_x: f32 = (-1..=k.len() as isize)
            .map(|i| {
                let d = (at(i - 1).unwrap_or(0.0) - at(i + 1).unwrap_or(0.0)) / 2.0;
                d * d
            })
            .sum();
        along_y * along_x
    } else {
        0.5
    };
    let mut energy = Image::zeros(w, h);
    energy
        .data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            let s = &smooth.data()[y * w..][..w];
            for x in 1..w.saturating_sub(1) {
                let g = (s[x + 1] - s[x - 1]) / 2.0;
                row[x] = g * g;
            }
        });
    (gaussian_blur(&energy, f64::from(texture_sigma)), gain)
}

/// As [`textured_along_x`] on both micrographs at once: the mean of the left energy and the
/// right one at the match (`disparity` along x, rounded); half the noise's spread. Where the
/// match is unknown or off the right image, the left one alone.
#[must_use]
pub fn textured_along_x_both(
    (a, b): (&Image, &Image),
    (noise_a, noise_b): (f32, f32),
    disparity: &Image,
    (band_sigma, texture_sigma): (f32, f32),
    min_snr: f32,
) -> Vec<bool> {
    let (w, _) = a.dimensions();
    let sigmas = (band_sigma, texture_sigma);
    let (ea, gain) = gradient_energy(a, sigmas);
    let (eb, _) = gradient_energy(b, sigmas);
    let one = threshold(noise_a * noise_a * gain, sigmas, min_snr, 1.0);
    let mean = 0.5 * (noise_a * noise_a + noise_b * noise_b) * gain;
    let two = threshold(mean, sigmas, min_snr, 2.0);
    let wb = b.dimensions().0;
    ea.data()
        .par_iter()
        .zip(disparity.data().par_iter())
        .enumerate()
        .map(|(p, (&e, &d))| {
            let xb = (p % w) as f32 + d;
            // `xb` finite and within the row: its rounding is a column.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let q = (d.is_finite() && xb >= 0.0 && xb <= (wb - 1) as f32)
                .then(|| (p / w) * wb + (xb + 0.5) as usize);
            match q.and_then(|q| eb.data().get(q)) {
                Some(&f) => 0.5 * (e + f) > two,
                None => e > one,
            }
        })
        .collect()
}

/// The measured featureless pixels (finite `disparity`, not `textured`) whose disparity is
/// not pinned by texture on both sides along the row (see the module documentation):
/// `reach_px` the anchors' reach in pixels.
#[must_use]
pub fn unanchored(
    disparity: &Image,
    textured: &[bool],
    step_px: f32,
    reach_px: usize,
) -> Vec<bool> {
    unanchored_in(disparity, textured, None, step_px, reach_px)
}

/// [`unanchored`], judging only the featureless pixels in `judged` (all when `None`).
#[must_use]
pub fn unanchored_in(
    disparity: &Image,
    textured: &[bool],
    judged: Option<&[bool]>,
    step_px: f32,
    reach_px: usize,
) -> Vec<bool> {
    let (w, h) = disparity.dimensions();
    let mut out = vec![false; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let d = &disparity.data()[y * w..][..w];
        let t = &textured[y * w..][..w];
        let anchor = |x: usize| t[x] && d[x].is_finite();
        // The nearest anchor at or after x (`usize::MAX`: none); the one at or before it is
        // carried along the row below.
        let mut after = vec![usize::MAX; w];
        let mut next = usize::MAX;
        for (x, a) in after.iter_mut().enumerate().rev() {
            if anchor(x) {
                next = x;
            }
            *a = next;
        }
        let mut before = None;
        for (x, out) in row.iter_mut().enumerate() {
            if anchor(x) {
                before = Some(x);
            }
            if t[x] || !d[x].is_finite() || judged.is_some_and(|j| !j[y * w + x]) {
                continue;
            }
            let pinned = match (before, after[x]) {
                (Some(l), r) if r != usize::MAX && x - l <= reach_px && r - x <= reach_px => {
                    let f = (x - l) as f32 / (r - l) as f32;
                    let between = d[l] + f * (d[r] - d[l]);
                    (d[x] - between).abs() <= step_px
                }
                _ => false,
            };
            *out = !pinned;
        }
    });
    out
}

/// The featureless pixels (not `textured`) in 4-connected featureless regions of at least
/// `min_px` pixels.
///
/// By runs, not pixels: each row's featureless runs are found in parallel, a union–find joins
/// the runs that share a column with a run of the row above (serial, over the runs only), and
/// the runs of large regions are marked in parallel.
#[must_use]
pub fn large_featureless(textured: &[bool], (w, h): (usize, usize), min_px: usize) -> Vec<bool> {
    let mut out = vec![false; w * h];
    if w == 0 {
        return out;
    }
    // Per row, its featureless runs `start..end`.
    let runs: Vec<Vec<(usize, usize)>> = textured
        .par_chunks(w)
        .map(|row| {
            let mut runs = Vec::new();
            let mut x = 0;
            while let Some(start) = row[x..].iter().position(|&t| !t).map(|s| x + s) {
                let end = row[start..]
                    .iter()
                    .position(|&t| t)
                    .map_or(w, |e| start + e);
                runs.push((start, end));
                x = end;
            }
            runs
        })
        .collect();
    // The index of each row's first run among all runs.
    let first: Vec<usize> = runs
        .iter()
        .scan(0, |n, r| {
            let at = *n;
            *n += r.len();
            Some(at)
        })
        .collect();
    let mut parent: Vec<usize> = (0..runs.iter().map(Vec::len).sum()).collect();
    let root = |parent: &mut [usize], mut i: usize| {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    };
    for y in 1..h {
        // Two pointers over the runs of rows y − 1 and y: each overlapping pair is joined.
        let (above, here) = (&runs[y - 1], &runs[y]);
        let (mut i, mut j) = (0, 0);
        while i < above.len() && j < here.len() {
            let (a, b) = (above[i], here[j]);
            if a.0 < b.1 && b.0 < a.1 {
                let (ra, rb) = (
                    root(&mut parent, first[y - 1] + i),
                    root(&mut parent, first[y] + j),
                );
                parent[ra.max(rb)] = ra.min(rb);
            }
            if a.1 <= b.1 {
                i += 1;
            } else {
                j += 1;
            }
        }
    }
    let mut size = vec![0usize; parent.len()];
    let mut roots = vec![0usize; parent.len()];
    for (k, &(s, e)) in runs.iter().flatten().enumerate() {
        roots[k] = root(&mut parent, k);
        size[roots[k]] += e - s;
    }
    out.par_chunks_mut(w)
        .zip(&runs)
        .zip(&first)
        .for_each(|((row, runs), &f)| {
            for (k, &(s, e)) in runs.iter().enumerate() {
                if size[roots[f + k]] >= min_px {
                    row[s..e].fill(true);
                }
            }
        });
    out
}

/// The left micrograph's texture along the parallax by the test's criterion, against its own
/// noise ([`crate::vision::precision::noise_sigma`] over its real pixels `va`); `None` without
/// a noise estimate. The rims beside a featureless support grow from the same mask.
#[must_use]
pub fn left_textured(a: &Image, va: &[bool], params: &AnchorParams) -> Option<Vec<bool>> {
    let noise = crate::vision::precision::noise_sigma(a, Some(va))?;
    #[allow(clippy::cast_possible_truncation)]
    Some(textured_along_x(
        a,
        noise as f32,
        (params.band_sigma, params.texture_sigma),
        params.min_snr,
    ))
}

/// The test on the dense stage's micrographs `a`, `b` (their real pixels `valid`) and measured
/// disparity: the pixels to leave unknown. `left`: [`left_textured`] of `a` (`None`: no noise
/// estimate, nothing is judged). `matcher_sigma`: the matcher's window σ, pixels.
#[must_use]
pub fn anchor_test(
    (a, b): (&Image, &Image),
    (va, vb): (&[bool], &[bool]),
    left: Option<&[bool]>,
    disparity: &Image,
    params: &AnchorParams,
    matcher_sigma: f32,
) -> Vec<bool> {
    let (w, h) = a.dimensions();
    let Some(left) = left else {
        return vec![false; w * h];
    };
    // Both micrographs' energy only when the right one is judged too (and has a noise
    // estimate); else the left one's alone.
    let noises = params
        .both_images
        .then(|| {
            let na = crate::vision::precision::noise_sigma(a, Some(va))?;
            let nb = crate::vision::precision::noise_sigma(b, Some(vb))?;
            Some((na, nb))
        })
        .flatten();
    #[allow(clippy::cast_possible_truncation)]
    let both = noises.map(|(na, nb)| {
        textured_along_x_both(
            (a, b),
            (na as f32, nb as f32),
            disparity,
            (params.band_sigma, params.texture_sigma),
            params.min_snr,
        )
    });
    let textured = both.as_deref().unwrap_or(left);
    // A reach of at most 32 σ: within usize.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let reach_px = (params.reach * matcher_sigma).round().max(1.0) as usize;
    let min_px = params.min_region_px(matcher_sigma);
    let judged = (min_px > 0).then(|| large_featureless(textured, (w, h), min_px));
    unanchored_in(
        disparity,
        textured,
        judged.as_deref(),
        params.step_px,
        reach_px,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(d: &[f32]) -> Image {
        Image::from_vec(d.len(), 1, d.to_vec()).unwrap()
    }

    /// Texture (every other pixel, and the last) up to x = `a` and from x = `b`, featureless
    /// between.
    fn textured_outside(a: usize, b: usize) -> Vec<bool> {
        (0..64)
            .map(|x| (x <= a || x >= b) && (x % 2 == 0 || x == 63))
            .collect()
    }

    /// A raised feature (disparity 5) up to x = 30 lends its disparity to 6 featureless pixels
    /// beyond its outline, the support (0) textured again from x = 50: the lent pixels, and the
    /// featureless support pixels whose disparity is not the interpolation of both sides', are
    /// left unknown; the textured pixels are kept.
    #[test]
    fn lent_disparity_beside_a_feature_is_left_unknown() {
        let d: Vec<f32> = (0..64).map(|x| if x <= 36 { 5.0 } else { 0.0 }).collect();
        let t = textured_outside(30, 50);
        let out = unanchored(&row(&d), &t, 1.0, 24);
        let masked: Vec<usize> = (0..64).filter(|&x| out[x]).collect();
        // The interpolation falls by 0.25 a pixel from 5 at x = 30 to 0 at x = 50: 31..=36
        // carry 5, off by more than 1 from x = 35; 37..=49 carry 0, off by more than 1 up to 45.
        assert_eq!(masked, (35..=45).collect::<Vec<_>>(), "{masked:?}");
        assert!(masked.iter().all(|&x| !t[x]));
    }

    /// Featureless pixels between two textures of one smooth surface are pinned: all kept.
    #[test]
    fn featureless_pixels_between_textures_of_one_surface_are_kept() {
        let d: Vec<f32> = (0..64).map(|x| 2.0 + 0.05 * x as f32).collect();
        let out = unanchored(&row(&d), &textured_outside(30, 50), 1.0, 24);
        assert!(!out.contains(&true));
    }

    /// Without texture within reach on one side the disparity is an extrapolation: unknown.
    #[test]
    fn texture_on_one_side_only_does_not_pin_a_pixel() {
        let d = vec![3.0f32; 64];
        let t: Vec<bool> = (0..64).map(|x| x <= 30 && x % 2 == 0).collect();
        let out = unanchored(&row(&d), &t, 1.0, 8);
        let masked: Vec<usize> = (0..64).filter(|&x| out[x]).collect();
        assert_eq!(masked, (31..64).collect::<Vec<_>>());
        // A gap wider than twice the reach: none of its pixels has both anchors.
        let out = unanchored(&row(&d), &textured_outside(30, 50), 1.0, 8);
        let masked: Vec<usize> = (0..64).filter(|&x| out[x]).collect();
        assert_eq!(masked, (31..=49).collect::<Vec<_>>(), "{masked:?}");
        // Within reach of both, the same pixels are kept.
        assert!(!unanchored(&row(&d), &textured_outside(30, 50), 1.0, 20).contains(&true));
    }

    /// Texture along x is found against the noise: a noisy flat image has (almost) none, a
    /// vertical edge is textured on every row (and its window's reach beside it).
    #[test]
    fn texture_along_x_stands_out_of_the_noise() {
        let (w, h) = (96, 64);
        let mut state = 7u64;
        let mut noise = || {
            // Sum of four uniforms: near-Gaussian.
            let mut s = 0.0f32;
            for _ in 0..4 {
                state = state
                    .wrapping_mul(6_364_136_223_846_793_005)
                    .wrapping_add(1_442_695_040_888_963_407);
                s += ((state >> 40) as f32 / (1u64 << 24) as f32) - 0.5;
            }
            s * 0.01
        };
        let data: Vec<f32> = (0..w * h)
            .map(|p| if p % w < 48 { 0.3 } else { 0.7 } + noise())
            .collect();
        let img = Image::from_vec(w, h, data).unwrap();
        let sigma = crate::vision::precision::noise_sigma(&img, None).unwrap() as f32;
        let t = textured_along_x(&img, sigma, (1.0, 1.5), 4.0);
        let flat = (0..w * h)
            .filter(|&p| (p % w).abs_diff(48) > 12 && p % w > 0 && p % w < w - 1)
            .filter(|&p| t[p])
            .count();
        assert!(flat * 1000 < w * h, "{flat} noise pixels textured");
        // The edge between columns 47 and 48: textured on every row.
        assert!((0..h).all(|y| t[y * w + 47] && t[y * w + 48]));
        // Without the noise figure scaled in, the threshold would not hold.
        let t0 = textured_along_x(&img, sigma / 100.0, (1.0, 1.5), 4.0);
        assert!(t0.iter().filter(|&&b| b).count() > w * h / 2);
    }

    /// The regions by a 4-connected flood fill from each unvisited featureless pixel: the
    /// reference of the run-based labelling.
    fn large_featureless_by_flood(
        textured: &[bool],
        (w, h): (usize, usize),
        min_px: usize,
    ) -> Vec<bool> {
        let mut seen = vec![false; w * h];
        let mut out = vec![false; w * h];
        for start in 0..w * h {
            if textured[start] || seen[start] {
                continue;
            }
            seen[start] = true;
            let (mut stack, mut members) = (vec![start], Vec::new());
            while let Some(q) = stack.pop() {
                members.push(q);
                let (x, y) = (q % w, q / w);
                let near = [
                    (x > 0).then(|| q - 1),
                    (x + 1 < w).then(|| q + 1),
                    (y > 0).then(|| q - w),
                    (y + 1 < h).then(|| q + w),
                ];
                for n in near.into_iter().flatten() {
                    if !textured[n] && !seen[n] {
                        seen[n] = true;
                        stack.push(n);
                    }
                }
            }
            if members.len() >= min_px {
                members.iter().for_each(|&q| out[q] = true);
            }
        }
        out
    }

    /// The run-based labelling marks the pixels the flood fill marks, on random masks of
    /// every density (winding regions that merge late, single rows and columns, empty masks).
    #[test]
    fn regions_by_runs_equal_the_flood_fill() {
        let mut state = 11u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 33) as usize
        };
        for case in 0..60 {
            let (w, h) = (1 + next() % 50, 1 + next() % 40);
            let density = next() % 100;
            let textured: Vec<bool> = (0..w * h).map(|_| next() % 100 < density).collect();
            for min_px in [0, 1, 2, 5, 17, 60, w * h] {
                assert_eq!(
                    large_featureless(&textured, (w, h), min_px),
                    large_featureless_by_flood(&textured, (w, h), min_px),
                    "case {case}: {w}x{h}, density {density} %, min_px {min_px}"
                );
            }
        }
        // A comb: teeth that join only along the last row form one region.
        let (w, h) = (9, 6);
        let comb: Vec<bool> = (0..w * h)
            .map(|q| q / w < h - 1 && q % w % 2 == 1)
            .collect();
        let big = large_featureless(&comb, (w, h), 5 * 5 + w);
        assert!((0..w * h).all(|q| big[q] != comb[q]));
        assert_eq!(big, large_featureless_by_flood(&comb, (w, h), 5 * 5 + w));
    }

    /// A large featureless region is judged, a speck amid texture is not.
    #[test]
    fn only_large_featureless_regions_are_judged() {
        let (w, h) = (40, 20);
        // Featureless: columns 0..15 (a support of 300 px) and a 2x2 speck at (30, 10).
        let textured: Vec<bool> = (0..w * h)
            .map(|q| {
                let (x, y) = (q % w, q / w);
                x >= 15 && !((30..32).contains(&x) && (10..12).contains(&y))
            })
            .collect();
        let big = large_featureless(&textured, (w, h), 20);
        assert!(big[5 * w + 3] && big[19 * w + 14]);
        assert!(
            !big[10 * w + 30] && !big[11 * w + 31],
            "the speck is judged"
        );
        assert!(!big[10 * w + 20], "a textured pixel is judged");
        let all = large_featureless(&textured, (w, h), 1);
        assert!(all[10 * w + 30]);
    }
}
