//! The Gaussian family. [`gaussian_blur`]: an image with symmetric borders and
//! a ⌈4σ⌉ kernel, as the SIFT scale space of IPOL's "Anatomy of SIFT" wants it.
//! [`blur`]: row-major buffers of `C`-channel pixels with replicated borders,
//! sampled taps up to a σ of a few pixels and a cascade of three box filters
//! (Wells 1986) beyond; the local contrast normalisation built on it. The
//! 5-tap binomial kernel of the pyramids and bilateral grids.

use rayon::prelude::*;

use crate::vision::Image;

/// The 5-tap binomial kernel (a Gaussian of variance 1): pyramid halving and the grids' blur.
pub(crate) const BINOMIAL_5: [f32; 5] =
    [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];

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
    let (w, h) = image.dimensions();
    let mut tmp = vec![0.0; w * h];
    let mut out = Image::zeros(w, h);
    gaussian_blur_into(image.data(), (w, h), sigma, &mut tmp, out.data_mut());
    out
}

/// [`gaussian_blur`] of the `w × h` plane `src` into `out`, with `tmp` for the horizontal
/// pass, whatever both held before: callers that own their planes (the SIFT scale space)
/// blur without allocating. `sigma ≤ 0` copies.
pub(crate) fn gaussian_blur_into(
    src: &[f32],
    (w, h): (usize, usize),
    sigma: f64,
    tmp: &mut [f32],
    out: &mut [f32],
) {
    if sigma <= 0.0 || w * h == 0 {
        out.copy_from_slice(src);
        return;
    }
    let kernel = gaussian_kernel(sigma);
    let r = kernel.len() / 2;
    // Horizontal pass: pad each row by mirroring, then a straight dot product. Each row is
    // cleared by the thread that sums it (not the whole plane first, on one core).
    tmp.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0.0f32; w + 2 * r],
        |padded, (y, o)| {
            let row = &src[y * w..(y + 1) * w];
            padded[r..r + w].copy_from_slice(row);
            for i in (0..r).chain(r + w..w + 2 * r) {
                padded[i] = row[mirror(i as isize - r as isize, w)];
            }
            // Tap by tap over the whole row: the inner loop vectorises.
            o.fill(0.0);
            for (k, &g) in kernel.iter().enumerate() {
                for (o, &v) in o.iter_mut().zip(&padded[k..k + w]) {
                    *o += g * v;
                }
            }
        },
    );
    // Vertical pass: accumulate whole rows so the inner loop runs along x (vectorises).
    let tmp = &*tmp;
    out.par_chunks_mut(w).enumerate().for_each(|(y, orow)| {
        orow.fill(0.0);
        for (k, &g) in kernel.iter().enumerate() {
            let sy = mirror(y as isize + k as isize - r as isize, h);
            for (o, &v) in orow.iter_mut().zip(&tmp[sy * w..(sy + 1) * w]) {
                *o += g * v;
            }
        }
    });
}

/// Normalised Gaussian taps `exp(−k²/2σ²)` for `k = −r..=r`, `r = ⌈3σ⌉`.
fn gaussian_taps(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as i32;
    let mut t: Vec<f32> = (-r..=r)
        .map(|k| (-(k * k) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f32 = t.iter().sum();
    for v in &mut t {
        *v /= s;
    }
    t
}

/// Beyond this σ the Gaussian is approximated by three box filters (Wells
/// 1986), whose cost does not grow with σ.
const BOX_SIGMA: f32 = 2.5;

/// Widths (odd) of the three boxes whose cascade has variance `σ²`
/// (Kovesi's construction: `m` boxes of width `wl`, the rest `wl + 2`).
fn box_widths(sigma: f32) -> [usize; 3] {
    let s2 = f64::from(sigma).powi(2);
    let ideal = (12.0 * s2 / 3.0 + 1.0).sqrt();
    let mut wl = ideal.floor() as i64;
    if wl % 2 == 0 {
        wl -= 1;
    }
    let wl = wl.max(1);
    let wlf = wl as f64;
    let m = ((12.0 * s2 - 3.0 * wlf * wlf - 12.0 * wlf - 9.0) / (-4.0 * wlf - 4.0)).round() as i64;
    let w_of = |i: i64| (if i < m { wl } else { wl + 2 }) as usize;
    [w_of(0), w_of(1), w_of(2)]
}

/// One box filter of odd width `width` along rows (`horizontal`) or columns,
/// replicated border, sums in f64 in a fixed order.
fn box_pass<const C: usize>(
    src: &[[f32; C]],
    out: &mut [[f32; C]],
    w: usize,
    h: usize,
    width: usize,
    horizontal: bool,
) {
    let r = (width / 2) as isize;
    let norm = 1.0 / width as f64;
    if horizontal {
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let s = &src[y * w..(y + 1) * w];
            let at = |i: isize| &s[i.clamp(0, w as isize - 1) as usize];
            let mut acc = [0f64; C];
            for k in -r..=r {
                for (a, &v) in acc.iter_mut().zip(at(k)) {
                    *a += f64::from(v);
                }
            }
            for (x, o) in row.iter_mut().enumerate() {
                for (oc, &a) in o.iter_mut().zip(&acc) {
                    *oc = (a * norm) as f32;
                }
                let (add, sub) = (at(x as isize + r + 1), at(x as isize - r));
                for ((a, &p), &m) in acc.iter_mut().zip(add).zip(sub) {
                    *a += f64::from(p) - f64::from(m);
                }
            }
        });
    } else {
        // Bands of rows, each with its own running sum started afresh: parallel,
        // and the band boundaries depend on the height only (not on threads).
        let band = h.div_ceil(VERTICAL_BANDS).max(1);
        let row = |i: isize| &src[(i.clamp(0, h as isize - 1) as usize) * w..][..w];
        out.par_chunks_mut(band * w)
            .enumerate()
            .for_each(|(b, chunk)| {
                let y0 = (b * band) as isize;
                let mut acc = vec![[0f64; C]; w];
                for k in y0 - r..=y0 + r {
                    for (a, v) in acc.iter_mut().zip(row(k)) {
                        for (ac, &vc) in a.iter_mut().zip(v) {
                            *ac += f64::from(vc);
                        }
                    }
                }
                for (i, orow) in chunk.chunks_mut(w).enumerate() {
                    let y = y0 + i as isize;
                    for (o, a) in orow.iter_mut().zip(&acc) {
                        for (oc, &ac) in o.iter_mut().zip(a) {
                            *oc = (ac * norm) as f32;
                        }
                    }
                    let (add, sub) = (row(y + r + 1), row(y - r));
                    for ((a, p), m) in acc.iter_mut().zip(add).zip(sub) {
                        for ((ac, &pc), &mc) in a.iter_mut().zip(p).zip(m) {
                            *ac += f64::from(pc) - f64::from(mc);
                        }
                    }
                }
            });
    }
}

/// Row bands of the vertical box pass.
const VERTICAL_BANDS: usize = 16;

/// Separable Gaussian blur of a row-major buffer of `C`-channel pixels
/// (replicated border): exact taps up to [`BOX_SIGMA`], a cascade of three
/// box filters beyond.
pub(crate) fn blur<const C: usize>(
    src: &[[f32; C]],
    w: usize,
    h: usize,
    sigma: f32,
) -> Vec<[f32; C]> {
    let mut buf = src.to_vec();
    let mut scratch = vec![[0f32; C]; w * h];
    blur_in_place(&mut buf, &mut scratch, w, h, sigma);
    buf
}

/// [`blur`] of `buf` in place, `scratch` (same length) as the other buffer
/// of the ping-pong. The refinement blurs several full-size multi-channel
/// buffers per iteration: allocating them afresh each time cost more system
/// time (the kernel zeroing new pages) than the blur itself.
pub(crate) fn blur_in_place<const C: usize>(
    buf: &mut [[f32; C]],
    scratch: &mut [[f32; C]],
    w: usize,
    h: usize,
    sigma: f32,
) {
    if sigma > BOX_SIGMA {
        let widths = box_widths(sigma);
        box_pass(buf, scratch, w, h, widths[0], true);
        box_pass(scratch, buf, w, h, widths[1], true);
        box_pass(buf, scratch, w, h, widths[2], true);
        box_pass(scratch, buf, w, h, widths[0], false);
        box_pass(buf, scratch, w, h, widths[1], false);
        box_pass(scratch, buf, w, h, widths[2], false);
        return;
    }
    blur_taps(buf, scratch, w, h, sigma);
}

/// [`blur`] with the sampled Gaussian taps, in place (`tmp`: scratch).
fn blur_taps<const C: usize>(
    buf: &mut [[f32; C]],
    tmp: &mut [[f32; C]],
    w: usize,
    h: usize,
    sigma: f32,
) {
    let taps = gaussian_taps(sigma);
    let r = (taps.len() / 2) as isize;
    let src: &[[f32; C]] = buf;
    // Along rows: each row padded by replication, then tap by tap over the
    // whole row (contiguous, vectorisable), in the same order of taps per
    // pixel as the direct sum.
    tmp.par_chunks_mut(w).enumerate().for_each_init(
        || Vec::with_capacity(w + 2 * r as usize),
        |padded, (y, row)| {
            let s = &src[y * w..(y + 1) * w];
            padded.clear();
            padded.extend((-r..w as isize + r).map(|x| s[x.clamp(0, w as isize - 1) as usize]));
            row.fill([0f32; C]);
            for (t, &k) in taps.iter().enumerate() {
                for (o, v) in row.iter_mut().zip(&padded[t..t + w]) {
                    for (a, &b) in o.iter_mut().zip(v) {
                        *a += k * b;
                    }
                }
            }
        },
    );
    let tmp: &[[f32; C]] = tmp;
    buf.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        row.fill([0f32; C]);
        for (t, &k) in taps.iter().enumerate() {
            let sy = (y as isize + t as isize - r).clamp(0, h as isize - 1) as usize;
            for (o, v) in row.iter_mut().zip(&tmp[sy * w..(sy + 1) * w]) {
                for (a, &b) in o.iter_mut().zip(v) {
                    *a += k * b;
                }
            }
        }
    });
}

/// [`blur`] of one plane.
pub(crate) fn blur_plane(src: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    // The copy by both cores (a full-resolution plane).
    let mut buf: Vec<f32> = src.par_iter().copied().collect();
    let mut scratch = vec![0f32; buf.len()];
    blur_plane_in_place(&mut buf, &mut scratch, w, h, sigma);
    buf
}

/// [`blur_in_place`] of one plane (`scratch`: the other buffer, any contents), without
/// packing it into one-channel pixels first: the same layout, the same sums.
fn blur_plane_in_place(buf: &mut [f32], scratch: &mut [f32], w: usize, h: usize, sigma: f32) {
    blur_in_place(
        buf.as_chunks_mut::<1>().0,
        scratch.as_chunks_mut::<1>().0,
        w,
        h,
        sigma,
    );
}

/// The image with its local mean removed and its local contrast scaled to
/// one (Gaussian windows of `sigma`), after an optional pre-smoothing.
/// `eps` — a tenth of the mean local contrast — keeps flat areas from
/// turning into amplified noise.
///
/// Three full-size planes (four with the pre-smoothing), each step in place: the refinement
/// normalises both images at every level, and fresh planes cost more in page faults than
/// the arithmetic.
#[must_use]
pub fn normalise_contrast(img: &Image, presmooth: f32, sigma: f32) -> Image {
    let (w, h) = img.dimensions();
    let mut scratch = vec![0f32; w * h];
    let smoothed = (presmooth > 0.0).then(|| {
        let mut b = img.data().to_vec();
        blur_plane_in_place(&mut b, &mut scratch, w, h, presmooth);
        b
    });
    let base: &[f32] = smoothed.as_deref().unwrap_or(img.data());
    // The local mean, then the high-pass `base − mean` in its place.
    let mut hp = base.to_vec();
    blur_plane_in_place(&mut hp, &mut scratch, w, h, sigma);
    hp.par_iter_mut().zip(base).for_each(|(m, &a)| *m = a - *m);
    // The squares in the pre-smoothed plane when there is one (no longer needed).
    let mut var = smoothed.unwrap_or_else(|| vec![0f32; w * h]);
    var.par_iter_mut().zip(&hp).for_each(|(s, &v)| *s = v * v);
    blur_plane_in_place(&mut var, &mut scratch, w, h, sigma);
    drop(scratch);
    // Sequential sum: the same figure whatever the thread count.
    let mean_sd = var
        .iter()
        .map(|v| f64::from(v.max(0.0)).sqrt())
        .sum::<f64>()
        / var.len().max(1) as f64;
    let eps2 = (0.1 * mean_sd as f32).powi(2).max(1e-12);
    hp.par_iter_mut()
        .zip(&var)
        .for_each(|(a, v)| *a /= (v.max(0.0) + eps2).sqrt());
    Image::from_vec(w, h, hp).expect("same size as the input")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blurring_into_used_planes_equals_the_gaussian_blur_to_the_bit() {
        let img = Image::from_fn(37, 23, |x, y| ((x * 7 + y * 13) % 17) as f32 / 17.0);
        for sigma in [0.0, 0.7, 1.52, 3.1, 9.0] {
            let want = gaussian_blur(&img, sigma);
            let mut tmp = vec![f32::NAN; img.len()];
            let mut out = vec![f32::NAN; img.len()];
            gaussian_blur_into(img.data(), img.dimensions(), sigma, &mut tmp, &mut out);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&out), bits(want.data()), "σ {sigma}");
        }
    }

    /// The contrast normalisation step by step, each in a plane of its own (packed into
    /// one-channel pixels for the blur): the in-place version gives the same bits.
    #[test]
    fn contrast_normalisation_in_place_equals_the_plane_by_plane_steps() {
        let (w, h) = (31, 19);
        let img = Image::from_fn(w, h, |x, y| {
            ((x * 7 + y * 13) % 17) as f32 / 17.0 + 0.01 * y as f32
        });
        let plane = |src: &[f32], sigma: f32| -> Vec<f32> {
            let packed: Vec<[f32; 1]> = src.iter().map(|&v| [v]).collect();
            blur(&packed, w, h, sigma)
                .into_iter()
                .map(|v| v[0])
                .collect()
        };
        for (presmooth, sigma) in [(0.0, 2.5), (0.8, 2.5), (0.0, 4.0), (1.5, 1.2)] {
            let base = if presmooth > 0.0 {
                plane(img.data(), presmooth)
            } else {
                img.data().to_vec()
            };
            let mean = plane(&base, sigma);
            let hp: Vec<f32> = base.iter().zip(&mean).map(|(a, m)| a - m).collect();
            let sq: Vec<f32> = hp.iter().map(|v| v * v).collect();
            let var = plane(&sq, sigma);
            let mean_sd = var
                .iter()
                .map(|v| f64::from(v.max(0.0)).sqrt())
                .sum::<f64>()
                / var.len() as f64;
            let eps2 = (0.1 * mean_sd as f32).powi(2).max(1e-12);
            let want: Vec<u32> = hp
                .iter()
                .zip(&var)
                .map(|(a, v)| (a / (v.max(0.0) + eps2).sqrt()).to_bits())
                .collect();
            let got: Vec<u32> = normalise_contrast(&img, presmooth, sigma)
                .data()
                .iter()
                .map(|v| v.to_bits())
                .collect();
            assert_eq!(got, want, "presmooth {presmooth}, σ {sigma}");
        }
    }

    /// The Gaussian blur by its definition: a double sum over the window.
    fn naive_blur(src: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
        let taps = gaussian_taps(sigma);
        let r = (taps.len() / 2) as isize;
        (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as isize, (p / w) as isize);
                let mut acc = 0f64;
                for (j, &ky) in taps.iter().enumerate() {
                    for (i, &kx) in taps.iter().enumerate() {
                        let sx = (x + i as isize - r).clamp(0, w as isize - 1) as usize;
                        let sy = (y + j as isize - r).clamp(0, h as isize - 1) as usize;
                        acc += f64::from(kx * ky * src[sy * w + sx]);
                    }
                }
                acc as f32
            })
            .collect()
    }

    #[test]
    fn separable_blur_matches_the_double_sum() {
        let (w, h) = (13, 9);
        let src: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 17) as f32).collect();
        for sigma in [0.5f32, 1.3, 2.0, 3.5] {
            let fast = blur_plane_taps(&src, w, h, sigma);
            let slow = naive_blur(&src, w, h, sigma);
            for (a, b) in fast.iter().zip(&slow) {
                assert!((a - b).abs() < 1e-4, "σ {sigma}: {a} vs {b}");
            }
        }
    }

    /// A box filter by its definition: the mean of the clamped window.
    fn naive_box(src: &[f32], w: usize, h: usize, width: usize, horizontal: bool) -> Vec<f32> {
        let r = (width / 2) as isize;
        (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as isize, (p / w) as isize);
                let sum: f64 = (-r..=r)
                    .map(|k| {
                        let (sx, sy) = if horizontal { (x + k, y) } else { (x, y + k) };
                        let (sx, sy) = (sx.clamp(0, w as isize - 1), sy.clamp(0, h as isize - 1));
                        f64::from(src[sy as usize * w + sx as usize])
                    })
                    .sum();
                (sum / width as f64) as f32
            })
            .collect()
    }

    #[test]
    fn running_box_sums_match_the_window_means() {
        let (w, h) = (17, 11);
        let src: Vec<f32> = (0..w * h).map(|i| ((i * 53) % 29) as f32 * 0.1).collect();
        let packed: Vec<[f32; 1]> = src.iter().map(|&v| [v]).collect();
        for width in [1, 3, 7, 25] {
            for horizontal in [true, false] {
                let mut fast = vec![[0f32; 1]; w * h];
                box_pass(&packed, &mut fast, w, h, width, horizontal);
                let slow = naive_box(&src, w, h, width, horizontal);
                for (a, b) in fast.iter().zip(&slow) {
                    assert!((a[0] - b).abs() < 1e-5, "width {width}: {} vs {b}", a[0]);
                }
            }
        }
    }

    #[test]
    fn box_cascade_has_the_variance_of_the_gaussian() {
        for sigma in [2.6f32, 4.0, 6.0, 9.5] {
            let var: f64 = box_widths(sigma)
                .iter()
                .map(|&b| ((b * b) as f64 - 1.0) / 12.0)
                .sum();
            assert!(
                (var.sqrt() - f64::from(sigma)).abs() < 0.35,
                "σ {sigma}: {}",
                var.sqrt()
            );
            // An impulse spreads like the Gaussian of that σ.
            let (w, h) = (81, 81);
            let mut img = vec![0f32; w * h];
            img[40 * w + 40] = 1.0;
            let fast = blur_plane(&img, w, h, sigma);
            let slow = blur_plane_taps(&img, w, h, sigma);
            let peak = slow[40 * w + 40];
            for (a, b) in fast.iter().zip(&slow) {
                assert!((a - b).abs() < 0.15 * peak, "σ {sigma}: {a} vs {b}");
            }
        }
    }

    fn blur_plane_taps(src: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
        let mut packed: Vec<[f32; 1]> = src.iter().map(|&v| [v]).collect();
        let mut tmp = vec![[0f32; 1]; w * h];
        blur_taps(&mut packed, &mut tmp, w, h, sigma);
        packed.into_iter().map(|v| v[0]).collect()
    }

    /// Direct 2-D convolution with the same kernel and boundary: the reference.
    fn naive_mirrored_blur(image: &Image, sigma: f64) -> Image {
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
            let slow = naive_mirrored_blur(&img, sigma);
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
}
