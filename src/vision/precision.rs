//! The precision the micrographs allow, predicted from the images alone.
//!
//! A window matcher estimates the disparity from the intensity gradients
//! along the parallax inside its window; scan noise in both images limits how
//! well. For a translation `d` between two images with white noise of
//! standard deviation `σ` and a Gaussian window of weights `w` (Σw = 1), the
//! Cramér–Rao bound of the least-squares estimate is
//!
//! `var(d) ≥ 2σ² · Σ w² g² / (Σ w g²)² ≈ 2σ² / (N · ḡ²)`,
//!
//! with `g` the noise-free gradient along the parallax, `ḡ²` its weighted
//! mean and `N = (Σw)² / Σw² = 4πσ_w²` the window's effective number of
//! pixels. No estimator working at that spatial resolution does better on
//! average, so this bound tells how much of the relief a pair can resolve
//! before a single parameter is tuned: it falls with the dwell time (less
//! noise), the tilt (more disparity per µm of height) and the window (less
//! detail).
//!
//! The noise is Immerkær's Laplacian-difference estimate (CVIU 64, 1996)
//! made robust with the median of the absolute responses (edges and fine
//! structure then enter as outliers, not as noise).

use rayon::prelude::*;
use serde::Serialize;

use super::Image;
use super::filter::blur::blur_in_place;

/// The sum of squares of Immerkær's kernel `[1 −2 1; −2 4 −2; 1 −2 1]`:
/// its response to white noise of variance σ² has variance 36σ².
const KERNEL_NORM: f64 = 6.0;
/// The median of |x| for x ~ N(0, 1) is 1/1.4826 of its σ.
const MAD_TO_SIGMA: f64 = 1.4826;

/// Standard deviation of the white noise of `img` (its intensity units),
/// over the 3×3 neighbourhoods whose pixels are all `valid` (`None`: all
/// finite); `None` with fewer than 64 such neighbourhoods.
#[must_use]
pub fn noise_sigma(img: &Image, valid: Option<&[bool]>) -> Option<f64> {
    let (w, h) = img.dimensions();
    if w < 3 || h < 3 {
        return None;
    }
    let d = img.data();
    // Row by row: per x, whether its column of three pixels is usable (one pass that
    // vectorises), then the responses of the neighbourhoods whose three columns are.
    let responses: Vec<Vec<f32>> = (1..h - 1)
        .into_par_iter()
        .map(|y| {
            let rows = [(y - 1) * w, y * w, (y + 1) * w].map(|start| start..start + w);
            let [up, mid, down] = rows.clone().map(|r| &d[r]);
            let finite = |x: usize| up[x].is_finite() & mid[x].is_finite() & down[x].is_finite();
            let column: Vec<bool> = match valid {
                Some(m) => {
                    let [mu, mm, md] = rows.map(|r| &m[r]);
                    (0..w).map(|x| mu[x] & mm[x] & md[x] & finite(x)).collect()
                }
                None => (0..w).map(finite).collect(),
            };
            (1..w - 1)
                .filter(|&x| column[x - 1] & column[x] & column[x + 1])
                .map(|x| {
                    let (a, b, c) = (up[x - 1], up[x], up[x + 1]);
                    let (e, f, g) = (mid[x - 1], mid[x], mid[x + 1]);
                    let (i, j, k) = (down[x - 1], down[x], down[x + 1]);
                    (a + c + i + k - 2.0 * (b + e + g + j) + 4.0 * f).abs()
                })
                .collect()
        })
        .collect();
    let n: usize = responses.iter().map(Vec::len).sum();
    if n < 64 {
        return None;
    }
    let median = kth_smallest(&responses, n / 2);
    Some(MAD_TO_SIGMA * f64::from(median) / KERNEL_NORM)
}

/// The element of rank `k` (0-based) of the values of `parts` together, in the order of
/// [`f32::total_cmp`]: the element a selection on one list of them all finds, without its
/// serial pass. That order is the order of the bits with the sign bit flipped (all bits, for
/// a negative value), so a parallel count of the top 16 of them finds the bin that holds rank
/// `k`, and a selection among that bin's few values the element.
pub(crate) fn kth_smallest<P: AsRef<[f32]> + Sync>(parts: &[P], k: usize) -> f32 {
    const SHIFT: u32 = 16;
    const BINS: usize = 1 << 16;
    const CHUNK: usize = 1 << 16;
    let key = |v: f32| {
        let bits = v.to_bits();
        if bits >> 31 == 1 {
            !bits
        } else {
            bits | 1 << 31
        }
    };
    let bin = |v: f32| (key(v) >> SHIFT) as usize;
    // Pieces of at most CHUNK values, gathered into groups of about CHUNK values each: one
    // histogram per group (not per part: a histogram per image row cleared 0.3 GB a call).
    let pieces: Vec<&[f32]> = parts
        .iter()
        .flat_map(|p| p.as_ref().chunks(CHUNK))
        .collect();
    let mut starts = vec![0];
    let mut filled = 0;
    for (i, piece) in pieces.iter().enumerate() {
        if filled >= CHUNK {
            starts.push(i);
            filled = 0;
        }
        filled += piece.len();
    }
    let groups: Vec<&[&[f32]]> = starts
        .iter()
        .zip(starts.iter().skip(1).chain([&pieces.len()]))
        .map(|(&a, &b)| &pieces[a..b])
        .collect();
    let counts = groups
        .par_iter()
        .map(|group| {
            let mut counts = vec![0u32; BINS];
            for &v in group.iter().copied().flatten() {
                counts[bin(v)] += 1;
            }
            counts
        })
        .reduce(
            || vec![0u32; BINS],
            |mut a, b| {
                a.iter_mut().zip(&b).for_each(|(a, b)| *a += b);
                a
            },
        );
    let (mut at, mut rank) = (0, k);
    while rank >= counts[at] as usize {
        rank -= counts[at] as usize;
        at += 1;
        assert!(at < BINS, "rank {k} beyond the values");
    }
    let mut members: Vec<f32> = pieces
        .par_iter()
        .flat_map_iter(|piece| piece.iter().copied().filter(|&v| bin(v) == at))
        .collect();
    *members.select_nth_unstable_by(rank, f32::total_cmp).1
}

/// The predicted precision of a pair, for report.json.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Precision {
    /// Noise of the left and right micrographs, as a fraction of the left
    /// one's intensity standard deviation (1 = as strong as the signal).
    pub noise_to_signal: [f64; 2],
    /// The Gaussian window the bound is taken for, σ in pixels.
    pub window_sigma_px: f64,
    /// Median over the valid pixels of the bound on the disparity's
    /// standard deviation, pixels (infinite where the window sees no
    /// texture along the parallax, which the median passes over).
    pub disparity_px: f64,
    /// The same as a height, µm: `disparity_px · p / (2 sin(θ/2))`.
    pub height_um: f64,
}

/// Per pixel of a `w × h` grid, the gradient energy above the noise's share `(g² − grad_noise)⁺`
/// and its weight (1 where `gradient` gives one, else 0), both blurred by a Gaussian of
/// `window_sigma` pixels: their ratio is the mean gradient energy the window match sees. The
/// two are the channels of one plane, blurred in place; each is what it would be alone.
pub(crate) fn windowed_gradient_energy(
    (w, h): (usize, usize),
    gradient: impl Fn(usize) -> Option<f32> + Sync,
    grad_noise: f32,
    window_sigma: f32,
) -> Vec<[f32; 2]> {
    let mut planes: Vec<[f32; 2]> = (0..w * h)
        .into_par_iter()
        .map(|q| gradient(q).map_or([0.0, 0.0], |g| [(g * g - grad_noise).max(0.0), 1.0]))
        .collect();
    let mut scratch = vec![[0f32; 2]; w * h];
    blur_in_place(&mut planes, &mut scratch, w, h, window_sigma);
    planes
}

/// The median over the pixels of `left` of the Cramér–Rao bound on
/// the disparity's standard deviation (pixels) for a Gaussian window of
/// `window_sigma` pixels, the parallax along the unit vector `parallax`
/// (image x, y), `noise` the standard deviations of the two images' noise.
/// `None` when no pixel has texture along the parallax.
#[must_use]
pub fn disparity_bound(
    left: &Image,
    noise: [f64; 2],
    parallax: [f64; 2],
    window_sigma: f64,
) -> Option<f64> {
    let (w, h) = left.dimensions();
    let d = left.data();
    let ok = |q: usize| d[q].is_finite();
    // A central difference of white noise has variance σ²/2 along either
    // axis, and so along any unit direction; the mean of the two images'
    // noise is what the symmetric gradient sees.
    let noise_var = 0.5 * (noise[0] * noise[0] + noise[1] * noise[1]);
    let grad_noise = (0.5 * noise_var) as f32;
    let (nx, ny) = (parallax[0] as f32, parallax[1] as f32);
    let counted = |q: usize| {
        let (x, y) = (q % w, q / w);
        x > 0
            && y > 0
            && x + 1 < w
            && y + 1 < h
            && ok(q)
            && ok(q - 1)
            && ok(q + 1)
            && ok(q - w)
            && ok(q + w)
    };
    let planes = windowed_gradient_energy(
        (w, h),
        |q| {
            counted(q).then(|| {
                let gx = 0.5 * (d[q + 1] - d[q - 1]);
                let gy = 0.5 * (d[q + w] - d[q - w]);
                nx * gx + ny * gy
            })
        },
        grad_noise,
        window_sigma as f32,
    );
    let n_eff = 4.0 * std::f64::consts::PI * window_sigma * window_sigma;
    // The bound falls as the mean gradient energy rises (monotone also as rounded), so the
    // median bound is the bound of the mirrored order statistic of the means.
    let means: Vec<f32> = (0..w * h)
        .into_par_iter()
        .filter(|&q| counted(q) && planes[q][1] > 1e-3)
        .map(|q| planes[q][0] / planes[q][1])
        .collect();
    drop(planes);
    if means.is_empty() {
        return None;
    }
    let mid = means.len() - 1 - means.len() / 2;
    let mean = f64::from(kth_smallest(&[means], mid));
    let median = if mean > 0.0 {
        (2.0 * noise_var / (n_eff * mean)).sqrt()
    } else {
        f64::INFINITY
    };
    median.is_finite().then_some(median)
}

/// Standard deviation of the finite samples of `img`.
fn signal_sigma(img: &Image) -> Option<f64> {
    let (mut n, mut s, mut s2) = (0f64, 0f64, 0f64);
    for &v in img.data() {
        if v.is_finite() {
            let v = f64::from(v);
            n += 1.0;
            s += v;
            s2 += v * v;
        }
    }
    (n > 1.0).then(|| ((s2 - s * s / n) / (n - 1.0)).max(0.0).sqrt())
}

/// The predicted precision of the pair `(left, right)` (micrograph grids)
/// for a tilt axis at `tilt_axis_deg` (DESIGN §3's φ; the parallax runs
/// along its normal), a window of `window_sigma` pixels and `um_per_px` µm
/// of height per disparity pixel. `None` when the noise or the texture
/// cannot be measured (tiny or flat images).
#[must_use]
pub fn predict(
    left: &Image,
    right: &Image,
    tilt_axis_deg: f64,
    window_sigma: f64,
    um_per_px: f64,
) -> Option<Precision> {
    // The three measurements are independent: taken at the same time (each one's own
    // arithmetic, in its own order).
    let (noise_left, (noise_right, signal)) = rayon::join(
        || noise_sigma(left, None),
        || rayon::join(|| noise_sigma(right, None), || signal_sigma(left)),
    );
    let noise = [noise_left?, noise_right?];
    let signal = signal.filter(|&s| s > 0.0)?;
    let phi = tilt_axis_deg.to_radians();
    let parallax = [-phi.sin(), phi.cos()];
    let disparity_px = disparity_bound(left, noise, parallax, window_sigma)?;
    Some(Precision {
        noise_to_signal: [noise[0] / signal, noise[1] / signal],
        window_sigma_px: window_sigma,
        disparity_px,
        height_um: disparity_px * um_per_px,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use sdsem_sim::scene::noise::{gaussian, mix64};

    /// Standard normal deviates, one stream per seed (the simulator's
    /// hash-based generator).
    struct Rng {
        seed: u64,
        n: u64,
    }
    impl Rng {
        fn new(seed: u64) -> Self {
            Self {
                seed: mix64(seed),
                n: 0,
            }
        }
        fn gauss(&mut self) -> f64 {
            self.n += 1;
            gaussian(mix64(self.seed ^ self.n))
        }
    }

    /// A smooth texture: a sum of sines of a few pixels' period.
    fn texture(x: f64, y: f64) -> f64 {
        0.5 + 0.2 * (0.9 * x + 0.3 * y).sin() + 0.15 * (0.4 * x - 1.1 * y).sin()
    }

    fn noisy(w: usize, h: usize, sigma: f64, seed: u64) -> Image {
        let mut rng = Rng::new(seed);
        Image::from_fn(w, h, |x, y| {
            (texture(x as f64, y as f64) + sigma * rng.gauss()) as f32
        })
    }

    /// The prediction's measurements run side by side and its medians are taken from lists
    /// collected in parallel: the same figures, bit for bit, whatever the thread count.
    #[test]
    fn prediction_is_the_same_on_any_number_of_threads() {
        let (left, right) = (noisy(301, 203, 0.03, 11), noisy(301, 203, 0.05, 12));
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| predict(&left, &right, -60.0, 6.0, 0.7))
                .unwrap()
        };
        let one = on(1);
        for threads in [2, 3, 5] {
            let p = on(threads);
            assert_eq!(
                p.noise_to_signal.map(f64::to_bits),
                one.noise_to_signal.map(f64::to_bits)
            );
            assert_eq!(
                p.disparity_px.to_bits(),
                one.disparity_px.to_bits(),
                "{threads} threads"
            );
            assert_eq!(p.height_um.to_bits(), one.height_um.to_bits());
        }
    }

    /// The counted selection finds the element a selection on the whole list finds, bit for
    /// bit, at every rank and however the values are split: signed zeros, infinities, NaNs,
    /// ties and values sharing a bin.
    #[test]
    fn counted_selection_equals_the_selection_of_the_whole_list() {
        let mut rng = Rng::new(5);
        let mut values: Vec<f32> = (0..3000)
            .map(|i| match i % 7 {
                0 => (rng.gauss() * 1e-3) as f32,
                1 => 1.0 + (rng.gauss() * 1e-6) as f32,
                2 => [
                    0.0,
                    -0.0,
                    f32::INFINITY,
                    f32::NEG_INFINITY,
                    f32::NAN,
                    -f32::NAN,
                ][i % 6],
                3 => 0.25,
                _ => (rng.gauss() * 100.0) as f32,
            })
            .collect();
        values.extend((0..200_000).map(|_| rng.gauss().abs() as f32));
        let mut sorted = values.clone();
        sorted.sort_unstable_by(f32::total_cmp);
        for k in (0..values.len()).step_by(997).chain([0, values.len() - 1]) {
            let whole = kth_smallest(&[&values], k);
            assert_eq!(whole.to_bits(), sorted[k].to_bits(), "rank {k}");
            // The same values in parts of any sizes (empty ones too).
            let parts: Vec<&[f32]> = values.chunks(1 + k % 5000).chain([&[][..]]).collect();
            assert_eq!(
                kth_smallest(&parts, k).to_bits(),
                whole.to_bits(),
                "rank {k}"
            );
        }
    }

    #[test]
    fn noise_of_a_textured_image_is_recovered() {
        for sigma in [0.01, 0.03, 0.1] {
            let est = noise_sigma(&noisy(256, 192, sigma, 7), None).unwrap();
            assert!(
                (est / sigma - 1.0).abs() < 0.12,
                "σ {sigma}: estimated {est}"
            );
        }
        // Noise-free: the texture alone reads as (almost) no noise.
        let clean = noise_sigma(&noisy(256, 192, 0.0, 7), None).unwrap();
        assert!(clean < 0.004, "{clean}");
        // Invalid neighbourhoods are left out; too few leave no estimate.
        let img = noisy(64, 48, 0.03, 3);
        let mut valid = vec![false; 64 * 48];
        valid[..64 * 4].iter_mut().for_each(|v| *v = true);
        assert!(noise_sigma(&img, Some(&valid)).is_some());
        valid[64 * 3..].iter_mut().for_each(|v| *v = false);
        assert!(noise_sigma(&img, Some(&valid)).is_none());
    }

    /// The bound against the empirical spread of the least-squares shift of
    /// many noisy windows, computed directly.
    #[test]
    fn bound_matches_the_spread_of_window_estimates() {
        let (w, h, sigma, ws) = (96usize, 96usize, 0.05, 4.0);
        let grad = |x: f64, y: f64| {
            let e = 1e-4;
            (texture(x + e, y) - texture(x - e, y)) / (2.0 * e)
        };
        // Estimates of a zero shift at the centre window of independent
        // noisy pairs, linearised: d = Σ w g (b − a) / Σ w g².
        let mut rng = Rng::new(11);
        let (cx, cy) = (48.0, 48.0);
        let taps: Vec<(f64, f64)> = (0..w * h)
            .map(|q| {
                let (x, y) = ((q % w) as f64, (q / w) as f64);
                let r2 = (x - cx).powi(2) + (y - cy).powi(2);
                ((-r2 / (2.0 * ws * ws)).exp(), grad(x, y))
            })
            .collect();
        let estimates: Vec<f64> = (0..400)
            .map(|_| {
                let (mut num, mut den) = (0.0, 0.0);
                for &(wt, g) in &taps {
                    let diff = sigma * (rng.gauss() - rng.gauss());
                    num += wt * g * diff;
                    den += wt * g * g;
                }
                num / den
            })
            .collect();
        let mean = estimates.iter().sum::<f64>() / estimates.len() as f64;
        let spread = (estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>()
            / (estimates.len() - 1) as f64)
            .sqrt();
        let img = noisy(w, h, sigma, 5);
        let bound = disparity_bound(&img, [sigma, sigma], [1.0, 0.0], ws).unwrap();
        assert!(
            (bound / spread - 1.0).abs() < 0.25,
            "bound {bound} px, spread of the estimates {spread} px"
        );
        // A window twice as wide, half the bound.
        let bw = disparity_bound(&img, [sigma, sigma], [1.0, 0.0], 2.0 * ws).unwrap();
        assert!((bw / bound - 0.5).abs() < 0.05, "{bw} vs {bound}");
        // Twice the noise, twice the bound: the noise's share of the
        // gradient energy is taken out.
        let img2 = noisy(w, h, 2.0 * sigma, 5);
        let b2 = disparity_bound(&img2, [2.0 * sigma, 2.0 * sigma], [1.0, 0.0], ws).unwrap();
        assert!((b2 / bound - 2.0).abs() < 0.1, "{b2} vs {bound}");
    }

    #[test]
    fn texture_only_across_the_parallax_gives_no_bound() {
        // Stripes that vary along y only: nothing to match along x.
        let img = Image::from_fn(64, 64, |_, y| (0.5 + 0.3 * (0.8 * y as f64).sin()) as f32);
        assert_eq!(disparity_bound(&img, [0.01, 0.01], [1.0, 0.0], 3.0), None);
        assert!(disparity_bound(&img, [0.01, 0.01], [0.0, 1.0], 3.0).is_some());
        // A flat image has no measurable noise nor texture.
        let flat = Image::filled(64, 64, 0.5);
        assert_eq!(predict(&flat, &flat, 0.0, 3.0, 1.0), None);
    }
}
