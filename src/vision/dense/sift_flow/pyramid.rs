//! Coarse-to-fine plumbing: halving images, descriptor images and masks, and
//! carrying a flow field from one level to the next finer one.
//!
//! Halving blurs with the binomial kernel [1 4 6 4 1]/16 (σ ≈ 1) and keeps
//! every second sample, so level `l + 1` is `⌈w/2⌉ × ⌈h/2⌉` and its pixel `i`
//! sits at `2i` of level `l`.

use rayon::prelude::*;

use crate::vision::Image;
use crate::vision::dense::dense_sift::{DESCRIPTOR_LEN, DescriptorImage};
use crate::vision::filter::blur::BINOMIAL_5 as BINOMIAL;

/// Size of the next coarser level.
#[must_use]
pub fn half_size(n: usize) -> usize {
    n.div_ceil(2)
}

/// Index clamped into `0..n`.
#[inline]
fn clamp_index(i: isize, n: usize) -> usize {
    i.clamp(0, n as isize - 1) as usize
}

/// Blurs and halves a multi-channel row-major `f32` buffer.
fn halve_channels(src: &[f32], w: usize, h: usize, ch: usize) -> Vec<f32> {
    let (w2, h2) = (half_size(w), half_size(h));
    // Horizontal pass at the kept columns only.
    let mut tmp = vec![0f32; w2 * h * ch];
    tmp.par_chunks_mut(w2 * ch)
        .enumerate()
        .for_each(|(y, row)| {
            let s = &src[y * w * ch..(y + 1) * w * ch];
            if ch == 1 {
                halve_row(s, row);
                return;
            }
            for (x2, out) in row.chunks_exact_mut(ch).enumerate() {
                for (t, &k) in BINOMIAL.iter().enumerate() {
                    let sx = clamp_index(2 * x2 as isize + t as isize - 2, w);
                    for (o, &v) in out.iter_mut().zip(&s[sx * ch..(sx + 1) * ch]) {
                        *o += k * v;
                    }
                }
            }
        });
    let mut out = vec![0f32; w2 * h2 * ch];
    out.par_chunks_mut(w2 * ch)
        .enumerate()
        .for_each(|(y2, row)| {
            for (t, &k) in BINOMIAL.iter().enumerate() {
                let sy = clamp_index(2 * y2 as isize + t as isize - 2, h);
                for (o, &v) in row.iter_mut().zip(&tmp[sy * w2 * ch..(sy + 1) * w2 * ch]) {
                    *o += k * v;
                }
            }
        });
    out
}

/// The horizontal pass of [`halve_channels`] on one row of one channel: the same sums in the
/// same order, the taps read without clamping away from the ends.
fn halve_row(s: &[f32], out: &mut [f32]) {
    let w = s.len();
    for (x2, o) in out.iter_mut().enumerate() {
        let c = 2 * x2;
        // Starts from 0 as the multi-channel pass does (which keeps a −0 sum +0).
        let mut acc = 0f32;
        if c >= 2 && c + 2 < w {
            for (&k, &v) in BINOMIAL.iter().zip(&s[c - 2..c + 3]) {
                acc += k * v;
            }
        } else {
            for (t, &k) in BINOMIAL.iter().enumerate() {
                acc += k * s[clamp_index(c as isize + t as isize - 2, w)];
            }
        }
        *o = acc;
    }
}

/// The next coarser level of an intensity image.
#[must_use]
pub fn halve_image(img: &Image) -> Image {
    let (w, h) = img.dimensions();
    let data = halve_channels(img.data(), w, h, 1);
    Image::from_vec(half_size(w), half_size(h), data).expect("halved buffer has the halved size")
}

/// The next coarser level of a descriptor image (the reference code's pyramid
/// of SIFT images: every channel blurred and subsampled, not recomputed).
#[must_use]
pub fn halve_descriptors(d: &DescriptorImage) -> DescriptorImage {
    let (w, h) = (d.width(), d.height());
    let (w2, h2) = (half_size(w), half_size(h));
    let mut out = DescriptorImage::zeros(w2, h2);
    // Row by row, to keep the f32 copy small.
    out.data_mut()
        .par_chunks_mut(w2 * DESCRIPTOR_LEN)
        .enumerate()
        .for_each(|(y2, row)| {
            let mut acc = vec![0f32; w2 * DESCRIPTOR_LEN];
            for (ty, &ky) in BINOMIAL.iter().enumerate() {
                let sy = clamp_index(2 * y2 as isize + ty as isize - 2, h);
                let src = &d.data()[sy * w * DESCRIPTOR_LEN..(sy + 1) * w * DESCRIPTOR_LEN];
                for (x2, a) in acc.chunks_exact_mut(DESCRIPTOR_LEN).enumerate() {
                    for (tx, &kx) in BINOMIAL.iter().enumerate() {
                        let sx = clamp_index(2 * x2 as isize + tx as isize - 2, w);
                        let k = ky * kx;
                        for (o, &v) in a
                            .iter_mut()
                            .zip(&src[sx * DESCRIPTOR_LEN..(sx + 1) * DESCRIPTOR_LEN])
                        {
                            *o += k * f32::from(v);
                        }
                    }
                }
            }
            for (o, &a) in row.iter_mut().zip(&acc) {
                // A convex combination of u8 values.
                #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                let q = (a + 0.5).min(255.0) as u8;
                *o = q;
            }
        });
    out
}

/// The next coarser level of a validity mask: a coarse pixel is valid when
/// the fine pixel it sits on and its right and lower neighbours are.
#[must_use]
pub fn halve_mask(mask: &[bool], w: usize, h: usize) -> Vec<bool> {
    let (w2, h2) = (half_size(w), half_size(h));
    let mut out = vec![false; w2 * h2];
    // Row by row on every core (the full-resolution canvas's mask is millions of pixels).
    out.par_chunks_mut(w2.max(1))
        .enumerate()
        .for_each(|(y2, row)| {
            let y = 2 * y2;
            let y1 = (y + 1).min(h - 1);
            for (x2, o) in row.iter_mut().enumerate() {
                let x = 2 * x2;
                let x1 = (x + 1).min(w - 1);
                *o = mask[y * w + x] && mask[y * w + x1] && mask[y1 * w + x] && mask[y1 * w + x1];
            }
        });
    out
}

/// Carries the flow component `coarse` (`wc × hc`, coarse pixels) to the
/// finer grid `wf × hf`: bilinear interpolation at `x / 2`, times two, rounded
/// to the integer offsets of the finer level's label windows.
#[must_use]
pub fn upsample_offsets(coarse: &[f32], wc: usize, hc: usize, wf: usize, hf: usize) -> Vec<i32> {
    // Per column, its two coarse columns and their weights: the same for every row.
    let columns: Vec<(usize, usize, f32, f32)> = (0..wf)
        .map(|x| {
            let (x0, x1, tx) = coarse_position(x, true, 0.5, wc);
            (x0, x1, 1.0 - tx, tx)
        })
        .collect();
    let mut out = vec![0i32; wf * hf];
    out.par_chunks_mut(wf).enumerate().for_each(|(y, row)| {
        let (y0, y1, ty) = coarse_position(y, true, 0.5, hc);
        let (r0, r1) = (&coarse[y0 * wc..][..wc], &coarse[y1 * wc..][..wc]);
        for (o, &(x0, x1, sx, tx)) in row.iter_mut().zip(&columns) {
            let top = r0[x0] * sx + r0[x1] * tx;
            let bottom = r1[x0] * sx + r1[x1] * tx;
            *o = round_to_i32(2.0 * (top * (1.0 - ty) + bottom * ty));
        }
    });
    out
}

/// Where fine index `i` falls among the `n` coarse samples: the two neighbours and the second's
/// weight (at `i/2` when the coarse level is the halving, else at `i·scale`).
#[inline]
pub(crate) fn coarse_position(i: usize, half: bool, scale: f32, n: usize) -> (usize, usize, f32) {
    let f = if half {
        i as f32 / 2.0
    } else {
        i as f32 * scale
    }
    .min((n - 1) as f32);
    let i0 = f as usize; // non-negative: truncation is the floor
    (i0, (i0 + 1).min(n - 1), f - i0 as f32)
}

/// `v.round() as i32` (half away from zero) for a flow, without the library call that
/// `round` is on the baseline x86-64 target: the fraction `v − trunc(v)` is exact.
#[inline]
fn round_to_i32(v: f32) -> i32 {
    // Flows are bounded by the image size.
    #[allow(clippy::cast_possible_truncation)]
    let whole = v as i32;
    let fraction = v - whole as f32;
    // Saturating as the cast is (beyond ±2³¹, and for infinities).
    whole
        .saturating_add(i32::from(fraction >= 0.5))
        .saturating_sub(i32::from(fraction <= -0.5))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rounding without the library call equals `round`, at and beside every half, on
    /// both sides of zero.
    #[test]
    fn rounding_of_flows_equals_the_library_round() {
        let halves = (-3000..3000).map(|k| k as f32 * 0.5);
        let beside = halves.clone().flat_map(|h| [h.next_down(), h.next_up()]);
        let spread = (-100_000..100_000).map(|k| k as f32 * 0.013_7);
        let edge = [
            0.499_999_97,
            -0.499_999_97,
            0.0,
            -0.0,
            4_194_303.5,
            -4_194_303.5,
            3e9,
            -3e9,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        for v in halves.chain(beside).chain(spread).chain(edge) {
            assert_eq!(round_to_i32(v), v.round() as i32, "{v}");
        }
    }

    /// One channel takes the unclamped path away from the ends: the values of the general
    /// pass, bit for bit (the same image as both channels of a two-channel buffer).
    #[test]
    fn one_channel_halving_equals_the_general_pass() {
        for (w, h) in [(1, 1), (2, 3), (5, 4), (6, 7), (33, 9)] {
            let one: Vec<f32> = (0..w * h)
                .map(|i| ((i * 7919) % 97) as f32 * 0.173 - 4.0)
                .collect();
            let two: Vec<f32> = one.iter().flat_map(|&v| [v, -v]).collect();
            let a = halve_channels(&one, w, h, 1);
            let b = halve_channels(&two, w, h, 2);
            let b0: Vec<u32> = b.chunks_exact(2).map(|c| c[0].to_bits()).collect();
            let a: Vec<u32> = a.iter().map(|v| v.to_bits()).collect();
            assert_eq!(a, b0, "{w} x {h}");
        }
    }

    #[test]
    fn halving_keeps_constants_and_sizes() {
        let img = Image::filled(7, 5, 0.25);
        let h = halve_image(&img);
        assert_eq!(h.dimensions(), (4, 3));
        assert!(h.data().iter().all(|&v| (v - 0.25).abs() < 1e-6));
    }

    #[test]
    fn halving_descriptors_matches_halving_each_channel() {
        let (w, h) = (9, 6);
        let mut d = DescriptorImage::zeros(w, h);
        for (i, v) in d.data_mut().iter_mut().enumerate() {
            *v = ((i * 31) % 251) as u8;
        }
        let fast = halve_descriptors(&d);
        for c in [0, 17, 127] {
            let plane: Vec<f32> = (0..w * h)
                .map(|p| f32::from(d.data()[p * DESCRIPTOR_LEN + c]))
                .collect();
            let halved = halve_channels(&plane, w, h, 1);
            for (p, &v) in halved.iter().enumerate() {
                let got = fast.data()[p * DESCRIPTOR_LEN + c];
                assert!(
                    (f32::from(got) - v).abs() <= 0.5 + 1e-3,
                    "channel {c} pixel {p}"
                );
            }
        }
    }

    #[test]
    fn upsampling_doubles_a_linear_flow() {
        // Coarse flow 1 + 0.5 x: at fine x = 2i the flow is 2 (1 + 0.5 i) = 2 + x / 2.
        let (wc, hc) = (5, 3);
        let coarse: Vec<f32> = (0..wc * hc).map(|p| 1.0 + 0.5 * (p % wc) as f32).collect();
        let fine = upsample_offsets(&coarse, wc, hc, 9, 5);
        for (x, &f) in fine.iter().take(9).enumerate() {
            assert_eq!(f, (2.0 + x as f32 / 2.0).round() as i32);
        }
    }
}
