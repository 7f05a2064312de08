//! Refinement of a flow on the intensities (beyond the paper): the descriptor
//! cost is blunt at the scale of a pixel (a descriptor spans `4 · cell_size`
//! pixels and the smoothness pulls neighbours together), so the flow is
//! refined by a dense Lucas–Kanade (Lucas & Kanade 1981) in the
//! "warp, then filter" form — every pixel warps the second image by its own
//! flow, the Gauss–Newton normal equations are summed over a Gaussian window,
//! and every pixel takes its own step — on images whose local mean and
//! contrast are normalised (the secondary-electron yield changes a little
//! with tilt), with the symmetric gradient of ESM (Benhimane & Malis 2004) and
//! cubic interpolation (Keys 1981) so that the estimate is not pulled towards
//! integer shifts. Per pixel, rows in parallel, no reduction in a
//! thread-dependent order: the result does not depend on the thread count.

use std::borrow::Cow;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::dense::sift_flow::pyramid::coarse_position;
use crate::vision::filter::blur::{blur, blur_in_place, normalise_contrast};
use crate::vision::filter::cross_grid::{CrossGrid, range_key_smoothed};

/// Parameters of the intensity refinement of a flow ([`refine_flow`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineParams {
    /// σ of the Gaussian window of the normal equations, pixels: smaller follows finer relief.
    pub window_sigma: f32,
    /// σ of the local mean and contrast normalisation, pixels (drops the shading that changes with tilt).
    pub normalise_sigma: f32,
    /// Gaussian blur of both images first, pixels (0 = none).
    pub presmooth_sigma: f32,
    /// Gauss–Newton steps per pyramid level (0 = no refinement; paper 0).
    pub iterations: usize,
    /// Gauss–Newton steps at full resolution; none = `iterations`.
    pub full_resolution_iterations: Option<usize>,
    /// Largest change from the starting flow, full-resolution pixels (halved per coarser level).
    pub max_step: f32,
    /// Refine the vertical flow too (false: keep it).
    pub vertical: bool,
    /// Range σ of edge-aware windows (Yoon & Kweon 2006), standard deviations of the intensity; 0 = plain Gaussian.
    pub range_sigma: f32,
    /// Smooth the start over the window at every level (false: only at the first one, where
    /// the matcher's flow with its label steps enters; below, the start is a refined flow).
    pub resmooth_start: bool,
    /// Gaussian smoothing of the edge-aware windows' key image, pixels: wider drops fine
    /// texture from the key, so that windows on a textured surface stay whole (less noise).
    pub range_key_sigma: f32,
}

impl Default for RefineParams {
    fn default() -> Self {
        Self {
            window_sigma: 6.0,
            normalise_sigma: 2.5,
            presmooth_sigma: 0.0,
            iterations: 3,
            full_resolution_iterations: Some(2),
            max_step: 4.0,
            vertical: true,
            range_sigma: 0.5,
            resmooth_start: true,
            range_key_sigma: 1.0,
        }
    }
}

impl RefineParams {
    /// Whether every figure is usable; the name of the first bad one otherwise.
    #[must_use]
    pub fn invalid_field(&self) -> Option<&'static str> {
        let ok = |v: f32, lo: f32| v.is_finite() && v >= lo;
        if !ok(self.window_sigma, 0.3) || self.window_sigma > 20.0 {
            Some("refine.window_sigma")
        } else if !ok(self.normalise_sigma, 0.5) || self.normalise_sigma > 50.0 {
            Some("refine.normalise_sigma")
        } else if !ok(self.presmooth_sigma, 0.0) || self.presmooth_sigma > 10.0 {
            Some("refine.presmooth_sigma")
        } else if !ok(self.max_step, 0.0) {
            Some("refine.max_step")
        } else if !ok(self.range_sigma, 0.0) || self.range_sigma > 100.0 {
            Some("refine.range_sigma")
        } else if !ok(self.range_key_sigma, 0.3) || self.range_key_sigma > 20.0 {
            Some("refine.range_key_sigma")
        } else if self.iterations > 100 {
            Some("refine.iterations")
        } else if self.full_resolution_iterations.is_some_and(|n| n > 100) {
            Some("refine.full_resolution_iterations")
        } else {
            None
        }
    }
}

/// A refined flow on the grid of the first image.
#[derive(Debug, Clone)]
pub struct RefinedFlow {
    pub u: Vec<f32>,
    pub v: Vec<f32>,
    /// Zero-mean normalised cross-correlation of the two normalised images
    /// over the window at the final flow, in `[0, 1]` (0 where no match).
    pub ncc: Vec<f32>,
    /// The pixel's flow hit the `max_step` bound (the estimate is unreliable).
    pub clamped: Vec<bool>,
}

/// The central differences of `d` (width `w`, height `h`) at pixel `(x, y)`, one-sided at the border.
#[inline]
fn gradient_at(d: &[f32], w: usize, h: usize, x: usize, y: usize) -> (f32, f32) {
    let (yu, yd) = (y.saturating_sub(1), (y + 1).min(h - 1));
    let sy = if yd > yu { 1.0 / (yd - yu) as f32 } else { 0.0 };
    let (xl, xr) = (x.saturating_sub(1), (x + 1).min(w - 1));
    let sx = if xr > xl { 1.0 / (xr - xl) as f32 } else { 0.0 };
    (
        (d[y * w + xr] - d[y * w + xl]) * sx,
        (d[yd * w + x] - d[yu * w + x]) * sy,
    )
}

/// [`gradient_at`] of every pixel.
fn gradients(img: &Image) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = img.dimensions();
    let d = img.data();
    let mut gx = vec![0f32; w * h];
    let mut gy = vec![0f32; w * h];
    gx.par_chunks_mut(w)
        .zip(gy.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, (rx, ry))| {
            for x in 0..w {
                (rx[x], ry[x]) = gradient_at(d, w, h, x, y);
            }
        });
    (gx, gy)
}

/// Keys' cubic convolution weights (a = −½) of the samples at −1, 0, 1, 2
/// for a fractional position `t ∈ [0, 1)`.
#[inline]
fn keys_weights(t: f32) -> [f32; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

/// One image prepared for sampling at real positions: the normalised
/// intensities, their gradients and the validity of every pixel.
struct Sampled<'a> {
    w: usize,
    h: usize,
    img: &'a [f32],
    gx: &'a [f32],
    gy: &'a [f32],
    valid: Option<&'a [bool]>,
}

impl Sampled<'_> {
    /// `(I, ∂x I, ∂y I)` at `(x, y)`: the intensity by cubic convolution,
    /// the gradients bilinearly. `None` outside the pixel-centre hull or
    /// next to an invalid pixel.
    #[inline]
    fn at(&self, x: f32, y: f32) -> Option<[f32; 3]> {
        let (w, h) = (self.w, self.h);
        if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
            return None;
        }
        // Non-negative (tested above): truncation is the floor, without a libm call.
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        if let Some(m) = self.valid
            && !(m[y0 * w + x0] && m[y0 * w + x1] && m[y1 * w + x0] && m[y1 * w + x1])
        {
            return None;
        }
        let (tx, ty) = (x - x0 as f32, y - y0 as f32);
        let (kx, ky) = (keys_weights(tx), keys_weights(ty));
        let bil = |g: &[f32]| {
            let top = g[y0 * w + x0] * (1.0 - tx) + g[y0 * w + x1] * tx;
            let bottom = g[y1 * w + x0] * (1.0 - tx) + g[y1 * w + x1] * tx;
            top * (1.0 - ty) + bottom * ty
        };
        let mut v = 0f32;
        if x0 >= 1 && y0 >= 1 && x0 + 2 < w && y0 + 2 < h {
            // All 4 × 4 samples inside: no clamping, the same sums in the same order.
            for (j, &wy) in ky.iter().enumerate() {
                let start = (y0 + j - 1) * w + x0 - 1;
                let row = &self.img[start..start + 4];
                let mut acc = 0f32;
                for (&wx, &s) in kx.iter().zip(row) {
                    acc += wx * s;
                }
                v += wy * acc;
            }
            return Some([v, bil(self.gx), bil(self.gy)]);
        }
        for (j, &wy) in ky.iter().enumerate() {
            let yy = (y0 as isize + j as isize - 1).clamp(0, h as isize - 1) as usize;
            let row = &self.img[yy * w..(yy + 1) * w];
            let mut acc = 0f32;
            for (i, &wx) in kx.iter().enumerate() {
                let xx = (x0 as isize + i as isize - 1).clamp(0, w as isize - 1) as usize;
                acc += wx * row[xx];
            }
            v += wy * acc;
        }
        Some([v, bil(self.gx), bil(self.gy)])
    }
}

/// Regularisation of the normal equations, relative to the window weight:
/// keeps textureless or one-dimensional windows from taking huge steps.
const TIKHONOV: f32 = 1e-3;
/// Largest step of one Gauss–Newton iteration, pixels.
const MAX_ITERATION_STEP: f32 = 0.5;

/// Refines the flow `(u, v)` from `a` to `b` (same pixel grid as `a`; `b`
/// may differ in size) on the intensities, at one resolution. `valid_a` and
/// `valid_b` mark usable pixels (`None`: all). `max_step` bounds the change
/// from the starting flow.
#[must_use]
#[allow(clippy::too_many_arguments)]
fn refine_level(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    (u_start, v_start): (Vec<f32>, Vec<f32>),
    params: &RefineParams,
    iterations: usize,
    max_step: f32,
    (with_ncc, smooth_start): (bool, bool),
) -> RefinedFlow {
    let (w, h) = a.dimensions();
    let (u0, v0) = (&u_start[..], &v_start[..]);
    // The second image is sampled at real positions: its gradients are kept; the first one's
    // are taken where needed.
    let normalised =
        |img: &Image| normalise_contrast(img, params.presmooth_sigma, params.normalise_sigma);
    // The cross grid's range key (its serial sums) beside the normalisations.
    let key = || {
        (params.range_sigma > 0.0)
            .then(|| range_key_smoothed(a.data(), w, h, params.range_key_sigma))
    };
    let (key, (na, (nb, (gbx, gby)))) = rayon::join(key, || {
        rayon::join(
            || normalised(a),
            || {
                let n = normalised(b);
                let g = gradients(&n);
                (n, g)
            },
        )
    });
    let sb = Sampled {
        w: b.width(),
        h: b.height(),
        img: nb.data(),
        gx: &gbx,
        gy: &gby,
        valid: valid_b,
    };
    // Start from the flow smoothed over the window: every update below is a
    // ratio of window sums, hence smooth, so pixel-scale noise of the start
    // (the equiangular offsets, label steps) would otherwise stay for good.
    // With edge-aware windows the smoothing runs in the pass that builds the
    // grid: finite samples only, weighted by their own count (a pixel with no
    // flow stays without one and spreads nothing), ones last for the grid's
    // normaliser.
    // Only the pixels that take part spread their start: valid, with a
    // starting flow. The others keep theirs.
    let usable: Vec<bool> = (0..w * h)
        .into_par_iter()
        .map(|p| valid_a.is_none_or(|m| m[p]) && u0[p].is_finite() && v0[p].is_finite())
        .collect();
    let n = w * h;
    // The smoothed start of pixel `p` from its window sums `[u, v, count, ·]`.
    let mean = |p: usize, s: &[f32; 4], o: &[f32], c: usize| {
        if !usable[p] || !smooth_start {
            o[p]
        } else if s[2] > 1e-12 {
            s[c] / s[2]
        } else {
            f32::NAN
        }
    };
    // The cross grid's cells, reused by the start's sums (4 channels) and the iterations' (6).
    let mut grid: Vec<f32> = Vec::new();
    let (xb, (u0, v0)): (Option<CrossGrid>, (Vec<f32>, Vec<f32>)) = if let Some(key) = key {
        // The sums of the start, produced and taken row by row while the grid is built.
        let (mut su, mut sv) = (vec![0f32; n], vec![0f32; n]);
        let g = CrossGrid::with_row_sums(
            &key,
            (w, h),
            (params.window_sigma, params.range_sigma),
            &|y, row: &mut [[f32; 4]]| {
                for (x, s) in row.iter_mut().enumerate() {
                    let p = y * w + x;
                    *s = if usable[p] {
                        [u0[p], v0[p], 1.0, 1.0]
                    } else {
                        [0.0, 0.0, 0.0, 1.0]
                    };
                }
            },
            // Only the usable pixels' means are read.
            Some(&usable),
            &mut grid,
            su.par_chunks_mut(w).zip(sv.par_chunks_mut(w)),
            |y, sums, (ru, rv)| {
                for (x, s) in sums.iter().enumerate() {
                    let p = y * w + x;
                    (ru[x], rv[x]) = (mean(p, s, u0, 0), mean(p, s, v0, 1));
                }
            },
        );
        (Some(g), (su, sv))
    } else {
        let packed: Vec<[f32; 3]> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                if usable[p] {
                    [u0[p], v0[p], 1.0]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let sums: Vec<[f32; 4]> = blur(&packed, w, h, params.window_sigma)
            .into_par_iter()
            .map(|[a, b, n]| [a, b, n, 1.0])
            .collect();
        (
            None,
            (
                (0..w * h)
                    .into_par_iter()
                    .map(|p| mean(p, &sums[p], u0, 0))
                    .collect(),
                (0..w * h)
                    .into_par_iter()
                    .map(|p| mean(p, &sums[p], v0, 1))
                    .collect(),
            ),
        )
    };
    // The smoothed start replaces the given one.
    drop((u_start, v_start));
    let mut u = u0.clone();
    let mut v = v0.clone();
    // Pixel `p` = (x, y) warped by its flow (by rows: no division per pixel).
    let warped = |u: &[f32], v: &[f32], x: usize, y: usize| -> Option<[f32; 3]> {
        let p = y * w + x;
        if !usable[p] {
            return None;
        }
        sb.at(x as f32 + u[p], y as f32 + v[p])
    };
    // The Gauss–Newton products of pixel row `y` with its own warp.
    let products_row = |u: &[f32], v: &[f32], y: usize, row: &mut [[f32; 6]]| {
        for (x, out) in row.iter_mut().enumerate() {
            let Some([bw, bx, by]) = warped(u, v, x, y) else {
                *out = [0.0; 6];
                continue;
            };
            let (gax, gay) = gradient_at(na.data(), w, h, x, y);
            let gx = 0.5 * (gax + bx);
            let gy = if params.vertical {
                0.5 * (gay + by)
            } else {
                0.0
            };
            let e = bw - na.data()[y * w + x];
            *out = [gx * gx, gx * gy, gy * gy, gx * e, gy * e, 1.0];
        }
    };
    // The step of pixel `p` from its window sums of the products.
    let step = |p: usize, sums: &[f32; 6], up: &mut f32, vp: &mut f32, cl: &mut bool| {
        let [sxx, sxy, syy, sxe, sye, s1] = *sums;
        if !usable[p] || s1 < 1e-3 {
            return;
        }
        let lam = TIKHONOV * s1;
        let (du, dv) = if params.vertical {
            let (a11, a22) = (sxx + lam, syy + lam);
            let det = a11 * a22 - sxy * sxy;
            if det <= 0.0 {
                return;
            }
            (
                -(a22 * sxe - sxy * sye) / det,
                -(a11 * sye - sxy * sxe) / det,
            )
        } else {
            (-sxe / (sxx + lam), 0.0)
        };
        let lim = |d: f32| d.clamp(-MAX_ITERATION_STEP, MAX_ITERATION_STEP);
        let (nu, nv) = (*up + lim(du), *vp + lim(dv));
        let bound = |n: f32, o: f32| {
            let c = n.clamp(o - max_step, o + max_step);
            (c, c != n)
        };
        let (cu, hu) = bound(nu, u0[p]);
        let (cv, hv) = bound(nv, v0[p]);
        *up = cu;
        *vp = cv;
        *cl = hu || hv;
    };
    let mut clamped = vec![false; w * h];
    // The Gaussian window's products and its second buffer (the cross grid takes them row by
    // row: no full-size buffer), then the NCC's sums and their blur's second buffer (4 + 4).
    let mut work: Vec<f32> = Vec::new();
    let mut scratch = Vec::new();
    if xb.is_none() && iterations > 0 {
        work = vec![0f32; 6 * n];
        scratch = vec![[0f32; 6]; n];
    }
    for _ in 0..iterations {
        match &xb {
            Some(g) => {
                // The products splatted as they are made, the step taken as the sums are
                // sliced; the steps read the sums of usable pixels only.
                g.splat_rows(
                    &|y, row: &mut [[f32; 6]]| products_row(&u, &v, y, row),
                    &mut grid,
                );
                let grid = &grid[..];
                u.par_chunks_mut(w)
                    .zip(v.par_chunks_mut(w))
                    .zip(clamped.par_chunks_mut(w))
                    .enumerate()
                    .for_each_init(
                        || vec![[0f32; 6]; w],
                        |sums, (y, ((ru, rv), rc))| {
                            g.slice_row(grid, y, Some(&usable), sums, true);
                            for (x, s) in sums.iter().enumerate() {
                                step(y * w + x, s, &mut ru[x], &mut rv[x], &mut rc[x]);
                            }
                        },
                    );
            }
            None => {
                let products = work.as_chunks_mut::<6>().0;
                products
                    .par_chunks_mut(w)
                    .enumerate()
                    .for_each(|(y, row)| products_row(&u, &v, y, row));
                blur_in_place(products, &mut scratch, w, h, params.window_sigma);
                let sums = &*products;
                u.par_iter_mut()
                    .zip(v.par_iter_mut())
                    .zip(clamped.par_iter_mut())
                    .enumerate()
                    .for_each(|(p, ((up, vp), cl))| step(p, &sums[p], up, vp, cl));
            }
        }
    }
    // Quality of the final match: NCC of the normalised images over the window,
    // from the sums of [aa, bb, ab, 1]. A coarser level's is not used.
    drop((xb, u0, v0));
    if !with_ncc {
        return RefinedFlow {
            u,
            v,
            ncc: Vec::new(),
            clamped,
        };
    }
    // The sums in the Gaussian window's buffer, their blur's second buffer in the memory of the
    // iterations' grid or second buffer (touched pages, whatever they hold: the blur writes
    // before it reads); fresh zeroed pages where those are too small (every sum is written).
    let mut sums = if work.capacity() >= 4 * n {
        work.resize(4 * n, 0.0);
        work
    } else {
        zeroed(4 * n)
    };
    let mut second = [grid, scratch.into_flattened()]
        .into_iter()
        .find(|b| b.len() >= 4 * n)
        .map_or_else(
            || zeroed(4 * n),
            |mut b| {
                b.truncate(4 * n);
                b
            },
        );
    let (sums, scratch) = (sums.as_chunks_mut::<4>().0, second.as_chunks_mut::<4>().0);
    sums.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, s) in row.iter_mut().enumerate() {
            *s = match warped(&u, &v, x, y) {
                Some([bw, _, _]) => {
                    let av = na.data()[y * w + x];
                    [av * av, bw * bw, av * bw, 1.0]
                }
                None => [0.0; 4],
            };
        }
    });
    // The Gaussian window here even with `range_sigma`: as good a confidence
    // (simulated scenes) for less time.
    blur_in_place(sums, scratch, w, h, params.window_sigma);
    let ncc = sums
        .par_iter()
        .enumerate()
        .map(|(p, &[saa, sbb, sab, s1])| {
            if !usable[p] || s1 < 1e-3 || saa <= 0.0 || sbb <= 0.0 {
                0.0
            } else {
                (sab / (saa * sbb).sqrt()).clamp(0.0, 1.0)
            }
        })
        .collect();
    RefinedFlow { u, v, ncc, clamped }
}

/// `n` zeros written by both cores: memory glibc hands back from its arenas is cleared by
/// `calloc` on one core (full-resolution planes of the refinement: a core idle meanwhile).
fn zeroed(n: usize) -> Vec<f32> {
    let mut v = Vec::with_capacity(n);
    v.par_extend(rayon::iter::repeat_n(0f32, n));
    v
}

/// Gives the pages of freed buffers back to the system before the full-resolution level, the
/// refinement's largest: glibc keeps much of the matcher's freed memory resident in its
/// arenas, where the level's buffers, mapped afresh, do not reuse it (the 1280x960 pair's peak
/// resident memory 326 -> 301-311 MiB, the same CPU time within the noise).
fn release_free_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks and releases glibc's own free chunks; it takes the
    // arenas' locks and touches no memory in use.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Bilinear upsampling of a flow component from `wc × hc` to `wf × hf`,
/// values scaled by `sx` (the grid's scale factor along the component).
#[must_use]
pub fn upsample_flow(
    coarse: &[f32],
    wc: usize,
    hc: usize,
    wf: usize,
    hf: usize,
    s: f32,
) -> Vec<f32> {
    let (fx_scale, fy_scale) = (
        if wf > 1 {
            (wc - 1) as f32 / (wf - 1) as f32
        } else {
            0.0
        },
        if hf > 1 {
            (hc - 1) as f32 / (hf - 1) as f32
        } else {
            0.0
        },
    );
    // Level l+1's pixel i sits at 2i of level l (pyramid::halve_*): the exact
    // mapping is x/2; the ratio above only differs by the rounding of odd sizes.
    let half = wc == wf.div_ceil(2) && hc == hf.div_ceil(2);
    // Per column, its two coarse columns and their weights: the same for every row.
    let columns: Vec<(usize, usize, f32, f32)> = (0..wf)
        .map(|x| {
            let (x0, x1, tx) = coarse_position(x, half, fx_scale, wc);
            (x0, x1, 1.0 - tx, tx)
        })
        .collect();
    let mut out = zeroed(wf * hf);
    out.par_chunks_mut(wf).enumerate().for_each(|(y, row)| {
        let (y0, y1, ty) = coarse_position(y, half, fy_scale, hc);
        let (r0, r1) = (&coarse[y0 * wc..][..wc], &coarse[y1 * wc..][..wc]);
        for (o, &(x0, x1, sx, tx)) in row.iter_mut().zip(&columns) {
            let top = r0[x0] * sx + r0[x1] * tx;
            let bottom = r1[x0] * sx + r1[x1] * tx;
            *o = s * (top * (1.0 - ty) + bottom * ty);
        }
    });
    out
}

/// Refines a flow from `a` to `b` given at pyramid level `level` (the images
/// halved `level` times, [`super::sift_flow::pyramid::halve_image`]): refined
/// at that level, upsampled, refined again, down to full resolution.
#[must_use]
pub fn refine_flow(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    flow: (&[f32], &[f32]),
    level: usize,
    params: &RefineParams,
) -> RefinedFlow {
    refine_flow_down_to(a, b, valid_a, valid_b, flow, level, 0, params)
}

/// [`refine_flow`] refining only down to pyramid level `stop` (≤ `level`),
/// then upsampled to full resolution without refinement: enough where the
/// flow only has to be right within a pixel or two (the backward field of
/// the left–right check). The NCC and clamp flags are upsampled likewise.
#[must_use]
#[allow(clippy::too_many_arguments)]
pub fn refine_flow_down_to(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    flow: (&[f32], &[f32]),
    level: usize,
    stop: usize,
    params: &RefineParams,
) -> RefinedFlow {
    let stop = stop.min(level);
    let r = refine_flow_to_level(a, b, valid_a, valid_b, flow, level, stop, params);
    upsample_refined(r, a.dimensions(), stop)
}

/// [`refine_flow_down_to`] before its upsampling: the flow on the grid of pyramid level
/// `stop` (≤ `level`) of `a`; [`upsample_refined`] takes it to full resolution.
#[must_use]
#[allow(clippy::too_many_arguments)]
pub fn refine_flow_to_level(
    a: &Image,
    b: &Image,
    valid_a: Option<&[bool]>,
    valid_b: Option<&[bool]>,
    flow: (&[f32], &[f32]),
    level: usize,
    stop: usize,
    params: &RefineParams,
) -> RefinedFlow {
    use super::sift_flow::pyramid::{halve_image, halve_mask};
    let stop = stop.min(level);
    // Pyramids of both images and masks, finest first (the full resolution borrowed).
    let mut imgs = vec![(Cow::Borrowed(a), Cow::Borrowed(b))];
    let mut masks = vec![(valid_a.map(Cow::Borrowed), valid_b.map(Cow::Borrowed))];
    for l in 1..=level {
        let (ia, ib) = &imgs[l - 1];
        let (ma, mb) = &masks[l - 1];
        let next_m = (
            ma.as_ref()
                .map(|m| Cow::Owned(halve_mask(m, ia.width(), ia.height()))),
            mb.as_ref()
                .map(|m| Cow::Owned(halve_mask(m, ib.width(), ib.height()))),
        );
        let next = (Cow::Owned(halve_image(ia)), Cow::Owned(halve_image(ib)));
        imgs.push(next);
        masks.push(next_m);
    }
    let mut u = flow.0.to_vec();
    let mut v = flow.1.to_vec();
    let mut result = None;
    for l in (stop..=level).rev() {
        let (ia, ib) = &imgs[l];
        let (ma, mb) = &masks[l];
        if let Some(prev) = result.take() {
            let RefinedFlow { u: pu, v: pv, .. } = prev;
            let (wc, hc) = imgs[l + 1].0.dimensions();
            let (wf, hf) = ia.dimensions();
            u = upsample_flow(&pu, wc, hc, wf, hf, 2.0);
            v = upsample_flow(&pv, wc, hc, wf, hf, 2.0);
        }
        let max_step = params.max_step / (1u32 << l) as f32;
        if l == 0 {
            release_free_memory();
        }
        result = Some(refine_level(
            ia,
            ib,
            ma.as_deref(),
            mb.as_deref(),
            (std::mem::take(&mut u), std::mem::take(&mut v)),
            params,
            if l == 0 {
                params
                    .full_resolution_iterations
                    .unwrap_or(params.iterations)
            } else {
                params.iterations
            },
            // A coarse level may move a little more: its error doubles on the way up.
            if l > 0 { max_step.max(1.0) } else { max_step },
            // Only the last level's NCC is kept.
            (l == stop, l == level || params.resmooth_start),
        ));
    }
    result.expect("level `stop` always runs")
}

/// A [`RefinedFlow`] on the grid of pyramid level `level` of an image of size `full`,
/// upsampled bilinearly to `full` (flow, NCC and clamp flags).
#[must_use]
pub fn upsample_refined(mut r: RefinedFlow, full: (usize, usize), level: usize) -> RefinedFlow {
    use super::sift_flow::pyramid::half_size;
    let mut sizes = vec![full];
    for _ in 0..level {
        let &(w, h) = sizes.last().expect("not empty");
        sizes.push((half_size(w), half_size(h)));
    }
    for l in (0..level).rev() {
        let (wc, hc) = sizes[l + 1];
        let (wf, hf) = sizes[l];
        // The four fields side by side (each one's rows in parallel too).
        let up = |f: &[f32], scale: f32| upsample_flow(f, wc, hc, wf, hf, scale);
        let ((u, v), (ncc, clamped)) = rayon::join(
            || rayon::join(|| up(&r.u, 2.0), || up(&r.v, 2.0)),
            || {
                rayon::join(
                    || up(&r.ncc, 1.0),
                    || {
                        let clamped: Vec<f32> = r
                            .clamped
                            .par_iter()
                            .map(|&c| f32::from(u8::from(c)))
                            .collect();
                        up(&clamped, 1.0).into_par_iter().map(|c| c > 0.0).collect()
                    },
                )
            },
        );
        r = RefinedFlow { u, v, ncc, clamped };
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The four fields are upsampled side by side and each one's rows in parallel: the same
    /// values, bit for bit, on any number of threads.
    #[test]
    fn upsampling_a_refined_flow_is_the_same_on_any_number_of_threads() {
        let (w, h) = (61, 37);
        let field = |k: u32| -> Vec<f32> {
            (0..w * h)
                .map(|p| (((p as u32).wrapping_mul(2_654_435_761) ^ k) % 1000) as f32 / 37.0)
                .collect()
        };
        let start = || RefinedFlow {
            u: field(1),
            v: field(2),
            ncc: field(3),
            clamped: (0..w * h).map(|p| p % 7 == 0).collect(),
        };
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| upsample_refined(start(), (4 * w - 3, 4 * h - 1), 2))
        };
        let bits = |r: &RefinedFlow| {
            let b = |f: &[f32]| f.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            (b(&r.u), b(&r.v), b(&r.ncc), r.clamped.clone())
        };
        let one = bits(&on(1));
        assert_eq!(one.0.len(), (4 * w - 3) * (4 * h - 1));
        assert!(one.3.iter().any(|&c| c) && one.3.iter().any(|&c| !c));
        for threads in [2, 3, 4] {
            assert_eq!(bits(&on(threads)), one, "{threads} threads");
        }
    }

    use crate::testing::Texture;

    /// Cubic sampling with every tap clamped to the image, as at the borders: the interior's
    /// unclamped path gives the same bits.
    #[test]
    fn cubic_sampling_inside_equals_the_clamped_taps() {
        let (w, h) = (13, 9);
        let img: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 23) as f32 * 0.1).collect();
        let (gx, gy) = (vec![0f32; w * h], vec![0f32; w * h]);
        let s = Sampled {
            w,
            h,
            img: &img,
            gx: &gx,
            gy: &gy,
            valid: None,
        };
        let clamped = |x: f32, y: f32| {
            let (x0, y0) = (x as usize, y as usize);
            let (kx, ky) = (keys_weights(x - x0 as f32), keys_weights(y - y0 as f32));
            let mut v = 0f32;
            for (j, &wy) in ky.iter().enumerate() {
                let yy = (y0 as isize + j as isize - 1).clamp(0, h as isize - 1) as usize;
                let mut acc = 0f32;
                for (i, &wx) in kx.iter().enumerate() {
                    let xx = (x0 as isize + i as isize - 1).clamp(0, w as isize - 1) as usize;
                    acc += wx * img[yy * w + xx];
                }
                v += wy * acc;
            }
            v
        };
        for k in 0..400 {
            let (x, y) = ((k * 7 % 120) as f32 * 0.1, (k * 11 % 80) as f32 * 0.1);
            let got = s.at(x, y).expect("inside the hull")[0];
            assert_eq!(got.to_bits(), clamped(x, y).to_bits(), "({x}, {y})");
        }
    }

    /// A bright textured region moving 2 px more than its textured
    /// surroundings (a particle on a substrate): with the range weights the
    /// refined disparity keeps the step next to the edge, where the Gaussian
    /// window mixes both sides.
    #[test]
    fn range_weights_keep_a_disparity_step_at_an_intensity_edge() {
        let (w, h) = (112, 64);
        let (fg, bg) = (Texture::new(21), Texture::new(22));
        let edge = 56.0;
        let (d_bg, d_fg) = (1.0f64, 3.0f64);
        let a = Image::from_fn(w, h, |x, y| {
            let (x, y) = (x as f64, y as f64);
            (if x >= edge {
                0.6 + fg.at(x, y)
            } else {
                bg.at(x, y)
            }) as f32
        });
        let b = Image::from_fn(w, h, |x, y| {
            let (x, y) = (x as f64, y as f64);
            (if x >= edge + d_fg {
                0.6 + fg.at(x - d_fg, y)
            } else {
                bg.at(x - d_bg, y)
            }) as f32
        });
        let truth = |x: usize| if x as f64 >= edge { d_fg } else { d_bg };
        let u0: Vec<f32> = (0..w * h).map(|p| truth(p % w) as f32).collect();
        let v0 = vec![0f32; w * h];
        let band_error = |range_sigma: f32| {
            let params = RefineParams {
                range_sigma,
                ..RefineParams::default()
            };
            let r = refine_flow(&a, &b, None, None, (&u0, &v0), 0, &params);
            let (mut sum, mut n) = (0f64, 0usize);
            for y in 12..h - 12 {
                for x in 44..68 {
                    sum += (f64::from(r.u[y * w + x]) - truth(x)).abs();
                    n += 1;
                }
            }
            sum / n as f64
        };
        let (gaussian, bilateral) = (band_error(0.0), band_error(0.5));
        assert!(
            bilateral < 0.5 * gaussian && bilateral < 0.2,
            "mean error within 12 px of the edge: {bilateral} px with range weights, {gaussian} px without"
        );
    }

    /// A rough textured surface with scan noise in both images, shifted by 2.3 px: with the
    /// windows' key smoothed past the texture the windows stay whole and the refined
    /// disparity is less noisy than with the texture in the key.
    #[test]
    fn a_smoothed_key_lowers_the_noise_on_a_textured_surface() {
        let (w, h) = (160, 120);
        let tex = Texture::new(31);
        // Uniform noise of zero mean, standard deviation `sigma`, from a hash of the position.
        let noise = |x: usize, y: usize, k: u64, sigma: f64| {
            let mut z = (x as u64 * 7919 + y as u64 * 104_729 + k * 1_299_709)
                .wrapping_mul(0x9E37_79B9_7F4A_7C15);
            z ^= z >> 31;
            z = z.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z ^= z >> 29;
            let u = (z >> 11) as f64 / (1u64 << 53) as f64;
            (u - 0.5) * sigma * 12f64.sqrt()
        };
        let d = 2.3;
        let a = Image::from_fn(w, h, |x, y| {
            (tex.at(x as f64, y as f64) + noise(x, y, 1, 0.03)) as f32
        });
        let b = Image::from_fn(w, h, |x, y| {
            (tex.at(x as f64 - d, y as f64) + noise(x, y, 2, 0.03)) as f32
        });
        let u0 = vec![2.0f32; w * h];
        let v0 = vec![0f32; w * h];
        let rms = |range_key_sigma: f32| {
            let params = RefineParams {
                range_key_sigma,
                ..RefineParams::default()
            };
            let r = refine_flow(&a, &b, None, None, (&u0, &v0), 0, &params);
            let (mut sum, mut n) = (0f64, 0usize);
            for y in 16..h - 16 {
                for x in 16..w - 16 {
                    sum += (f64::from(r.u[y * w + x]) - d).powi(2);
                    n += 1;
                }
            }
            (sum / n as f64).sqrt()
        };
        let (texture_key, smoothed_key) = (rms(1.0), rms(2.5));
        assert!(
            smoothed_key < 0.85 * texture_key,
            "RMS error {smoothed_key} px with the smoothed key, {texture_key} px with the texture in it"
        );
    }

    #[test]
    fn cubic_sampling_is_exact_at_pixels_and_on_a_quadratic() {
        let (w, h) = (8, 6);
        let f = |x: f32, y: f32| 0.3 * x * x - 0.2 * x * y + 0.5 * y + 1.0;
        let img: Vec<f32> = (0..w * h)
            .map(|p| f((p % w) as f32, (p / w) as f32))
            .collect();
        let zeros = vec![0f32; w * h];
        let s = Sampled {
            w,
            h,
            img: &img,
            gx: &zeros,
            gy: &zeros,
            valid: None,
        };
        assert_eq!(s.at(3.0, 2.0).unwrap()[0], f(3.0, 2.0));
        // Keys' kernel reproduces quadratics away from the border.
        let got = s.at(3.37, 2.61).unwrap()[0];
        assert!((got - f(3.37, 2.61)).abs() < 1e-4, "{got}");
        assert!(s.at(7.5, 2.0).is_none());
    }

    /// A texture shifted by a smooth sub-pixel disparity: the refinement
    /// starting from the rounded disparity recovers it within a few hundredths
    /// of a pixel, with no pull towards integers.
    #[test]
    fn refinement_recovers_a_subpixel_shift_without_pixel_locking() {
        let (w, h) = (96, 64);
        let tex = Texture::new(4);
        let truth = |x: f64, y: f64| 1.0 + 1.5 * x / w as f64 + 0.2 * (y / 20.0).sin();
        let a = Image::from_fn(w, h, |x, y| tex.at(x as f64, y as f64) as f32);
        // b(x + d(x)) = a(x): solve x from x' by a fixed point.
        let b = Image::from_fn(w, h, |xr, y| {
            let mut x = xr as f64;
            for _ in 0..30 {
                x = xr as f64 - truth(x, y as f64);
            }
            (0.8 * tex.at(x, y as f64) + 0.1) as f32
        });
        let u0: Vec<f32> = (0..w * h)
            .map(|p| truth((p % w) as f64, (p / w) as f64).round() as f32)
            .collect();
        let v0 = vec![0f32; w * h];
        let r = refine_flow(&a, &b, None, None, (&u0, &v0), 0, &RefineParams::default());
        let mut errs = Vec::new();
        let mut frac_err = [0f64; 2];
        for y in 8..h - 8 {
            for x in 8..w - 8 {
                let p = y * w + x;
                let t = truth(x as f64, y as f64);
                let e = f64::from(r.u[p]) - t;
                errs.push(e.abs());
                // Pixel locking shows as errors correlated with the distance
                // of the truth to the nearest integer.
                let f = t - t.round();
                frac_err[0] += e * f;
                frac_err[1] += f * f;
            }
        }
        errs.sort_by(f64::total_cmp);
        let median = errs[errs.len() / 2];
        assert!(median < 0.03, "median error {median} px");
        let locking = frac_err[0] / frac_err[1];
        assert!(
            locking.abs() < 0.05,
            "error vs fractional part slope {locking}"
        );
        assert!(r.ncc[40 * w + 40] > 0.9, "ncc {}", r.ncc[40 * w + 40]);
    }

    /// Pixels outside `valid_a` hold whatever flow the matcher left there
    /// (here −20 px, as beside the edge of the field of view); the valid
    /// pixels beside them, whose windows reach over, still start from and
    /// converge to their own flow — with the edge-aware windows and with the
    /// plain Gaussian ones.
    #[test]
    fn flow_outside_the_valid_pixels_does_not_spread_into_their_neighbours() {
        let (w, h) = (128, 96);
        let tex = Texture::new(9);
        let a = Image::from_fn(w, h, |x, y| tex.at(x as f64, y as f64) as f32);
        let b = Image::from_fn(w, h, |x, y| tex.at(x as f64 - 3.3, y as f64) as f32);
        let valid: Vec<bool> = (0..w * h).map(|p| p % w < 80).collect();
        let u0: Vec<f32> = valid.iter().map(|&v| if v { 3.0 } else { -20.0 }).collect();
        let v0 = vec![0f32; w * h];
        for range_sigma in [0.5, 0.0] {
            let params = RefineParams {
                range_sigma,
                ..RefineParams::default()
            };
            let r = refine_flow(&a, &b, Some(&valid), None, (&u0, &v0), 0, &params);
            for x in 60..80 {
                let p = 48 * w + x;
                assert!(
                    (r.u[p] - 3.3).abs() < 0.05,
                    "range σ {range_sigma}: u at x = {x} is {}",
                    r.u[p]
                );
            }
            // The invalid pixels keep their start.
            assert_eq!(r.u[48 * w + 100], -20.0);
        }
    }

    /// 128×96 images shifted by (3.3, −0.4) and a half-resolution start of
    /// 1.5 / 0 (true 1.65 / −0.2).
    fn shifted_pair_and_half_start() -> (Image, Image, Vec<f32>, Vec<f32>) {
        let (w, h) = (128, 96);
        let tex = Texture::new(9);
        let a = Image::from_fn(w, h, |x, y| tex.at(x as f64, y as f64) as f32);
        let b = Image::from_fn(w, h, |x, y| tex.at(x as f64 - 3.3, y as f64 + 0.4) as f32);
        let n = w.div_ceil(2) * h.div_ceil(2);
        (a, b, vec![1.5f32; n], vec![0f32; n])
    }

    #[test]
    fn coarse_start_is_refined_through_the_pyramid() {
        let (a, b, u0, v0) = shifted_pair_and_half_start();
        let w = a.width();
        let r = refine_flow(&a, &b, None, None, (&u0, &v0), 1, &RefineParams::default());
        let p = 48 * w + 64;
        assert!((r.u[p] - 3.3).abs() < 0.03, "u {}", r.u[p]);
        assert!((r.v[p] + 0.4).abs() < 0.03, "v {}", r.v[p]);
    }

    /// The full-resolution step count governs level 0 only: with none there
    /// the result is the refined half-resolution flow, upsampled and smoothed
    /// (right within a tenth of a pixel); with steps it reaches full precision,
    /// and at level 0 alone the per-level count no longer matters.
    #[test]
    fn full_resolution_steps_refine_only_the_finest_level() {
        let (a, b, u0, v0) = shifted_pair_and_half_start();
        let p = 48 * a.width() + 64;
        let with = |full: Option<usize>, iterations: usize, level: usize| {
            let params = RefineParams {
                full_resolution_iterations: full,
                iterations,
                ..RefineParams::default()
            };
            let (u0, v0) = if level == 0 {
                let (w, h) = a.dimensions();
                (vec![3.0f32; w * h], vec![0f32; w * h])
            } else {
                (u0.clone(), v0.clone())
            };
            refine_flow(&a, &b, None, None, (&u0, &v0), level, &params).u[p]
        };
        let none = with(Some(0), 3, 1);
        assert!((none - 3.3).abs() < 0.1, "u {none}");
        assert!((none - 3.3).abs() > 0.005, "u {none}: refined at level 0");
        let two = with(Some(2), 3, 1);
        assert!((two - 3.3).abs() < 0.03, "u {two}");
        assert!((two - 3.3).abs() < (none - 3.3).abs());
        // At level 0 alone: the full-resolution count, whatever `iterations`.
        assert_eq!(with(Some(2), 3, 0), with(Some(2), 7, 0));
        assert_eq!(with(None, 2, 0), with(Some(2), 5, 0));
        let kept = with(Some(0), 3, 0);
        assert!((kept - 3.0).abs() < 1e-5, "u {kept}: no step, the start");
    }

    /// The upsampling with its per-column table gives the bits of the pixel-by-pixel
    /// bilinear interpolation, for halving sizes (even and odd) and other ratios.
    #[test]
    fn upsampling_by_column_table_equals_the_direct_interpolation() {
        let direct =
            |coarse: &[f32], (wc, hc): (usize, usize), (wf, hf): (usize, usize), s: f32| {
                let scale = |c: usize, f: usize| {
                    if f > 1 {
                        (c - 1) as f32 / (f - 1) as f32
                    } else {
                        0.0
                    }
                };
                let half = wc == wf.div_ceil(2) && hc == hf.div_ceil(2);
                let at = |i: usize, n: usize, c: usize, f: usize| {
                    let t = if half {
                        i as f32 / 2.0
                    } else {
                        i as f32 * scale(c, f)
                    }
                    .min((n - 1) as f32);
                    let i0 = t as usize;
                    (i0, (i0 + 1).min(n - 1), t - i0 as f32)
                };
                (0..wf * hf)
                    .map(|q| {
                        let (y0, y1, ty) = at(q / wf, hc, hc, hf);
                        let (x0, x1, tx) = at(q % wf, wc, wc, wf);
                        let top = coarse[y0 * wc + x0] * (1.0 - tx) + coarse[y0 * wc + x1] * tx;
                        let bottom = coarse[y1 * wc + x0] * (1.0 - tx) + coarse[y1 * wc + x1] * tx;
                        (s * (top * (1.0 - ty) + bottom * ty)).to_bits()
                    })
                    .collect::<Vec<_>>()
            };
        for (coarse, fine) in [
            ((8, 5), (16, 9)),
            ((9, 6), (17, 11)),
            ((7, 7), (20, 13)),
            ((1, 3), (1, 5)),
        ] {
            let values: Vec<f32> = (0..coarse.0 * coarse.1)
                .map(|q| ((q * 37 % 23) as f32 - 11.0) * 0.173)
                .collect();
            let got = upsample_flow(&values, coarse.0, coarse.1, fine.0, fine.1, 2.0);
            let bits: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
            assert_eq!(
                bits,
                direct(&values, coarse, fine, 2.0),
                "{coarse:?} -> {fine:?}"
            );
        }
    }

    #[test]
    fn stopping_at_half_resolution_upsamples_the_refined_half_flow() {
        let (a, b, u0, v0) = shifted_pair_and_half_start();
        let (w, h) = a.dimensions();
        let params = RefineParams::default();
        let r = refine_flow_down_to(&a, &b, None, None, (&u0, &v0), 1, 1, &params);
        // Full-resolution fields, refined at half resolution only: right
        // within a small fraction of a pixel, not to the full level's precision.
        assert_eq!(
            (r.u.len(), r.ncc.len(), r.clamped.len()),
            (w * h, w * h, w * h)
        );
        let p = 48 * w + 64;
        assert!((r.u[p] - 3.3).abs() < 0.1, "u {}", r.u[p]);
        assert!((r.v[p] + 0.4).abs() < 0.1, "v {}", r.v[p]);
        assert!(r.ncc[p] > 0.8, "ncc {}", r.ncc[p]);
        // Stopping at level 0 is the whole refinement.
        let full = refine_flow_down_to(&a, &b, None, None, (&u0, &v0), 1, 0, &params);
        let whole = refine_flow(&a, &b, None, None, (&u0, &v0), 1, &params);
        assert_eq!(full.u, whole.u);
        assert_eq!(full.v, whole.v);
    }
}
