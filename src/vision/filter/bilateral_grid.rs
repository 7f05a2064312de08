//! Bilateral filtering through the bilateral grid (Paris & Durand, IJCV 2009).
//!
//! The image is lifted into a coarse 3-D grid `(x/σs, y/σs, value/σr)` of
//! homogeneous values `(w·f, w)` by nearest-cell splatting, the grid is blurred
//! with the binomial kernel [1 4 6 4 1]/16 along each axis (a Gaussian of one
//! cell), and the result is read back by trilinear slicing and division — an
//! edge-preserving smoothing whose cost does not grow with σs.
//!
//! The grid is built tile by tile (32 × 32 cells of output, in parallel),
//! each tile's grid holding the cells its pixels read plus the blur's reach
//! and only the range of values found there: the same sums as one grid over
//! the whole image, in memory and time that follow the occupied cells rather
//! than the image times its whole disparity range.
//!
//! Used on the disparity (range axis = disparity itself, in pixels) with a
//! per-pixel weight: 0 drops a pixel (unknown, occluded), a confidence in
//! `(0, 1]` lets reliable pixels dominate. Pixels whose input is `NaN` stay `NaN`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::blur::BINOMIAL_5 as KERNEL;
use crate::vision::Image;

/// Parameters of the bilateral filter of the disparity (SD-SEM §2.4).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BilateralParams {
    /// Spatial σ, pixels: larger smooths over a wider area.
    pub sigma_s: f32,
    /// Range σ, disparity pixels: steps much larger than this stay sharp.
    pub sigma_r: f32,
}

impl Default for BilateralParams {
    fn default() -> Self {
        Self {
            sigma_s: 3.0,
            sigma_r: 3.0,
        }
    }
}

/// Grid cells along the range axis at most; a wider value range coarsens the
/// range sampling instead of exhausting memory (reported by [`GridInfo`]).
const MAX_RANGE_CELLS: usize = 512;
/// Cells of padding on every side, so the 5-tap blur never meets a border.
const PAD: usize = 2;

/// The shape of the grid used, for the report.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GridInfo {
    pub nx: usize,
    pub ny: usize,
    pub nz: usize,
    /// The range σ actually used (larger than asked when the range was capped).
    pub sigma_r_used: f32,
}

struct Grid {
    nx: usize,
    ny: usize,
    nz: usize,
    /// (w·f, w) interleaved, index ((z · ny + y) · nx + x) · 2.
    data: Vec<f32>,
}

impl Grid {
    #[inline]
    fn idx(&self, x: usize, y: usize, z: usize) -> usize {
        ((z * self.ny + y) * self.nx + x) * 2
    }
}

/// The binomial blur of `n` cells read through `get` (cell `j` → its
/// `(w·f, w)`), written to `out[i]`: taps beyond the line are skipped.
#[inline]
fn blur_line(n: usize, get: impl Fn(usize) -> [f32; 2], out: &mut [[f32; 2]]) {
    for (i, r) in out.iter_mut().enumerate().take(n) {
        let mut acc = [0f32; 2];
        for (t, &k) in KERNEL.iter().enumerate() {
            let j = i as isize + t as isize - 2;
            if j < 0 || j >= n as isize {
                continue;
            }
            let c = get(j as usize);
            acc[0] += k * c[0];
            acc[1] += k * c[1];
        }
        *r = acc;
    }
}

/// Blurs a tile's grid in place along x, then y, then z, each line from a
/// copy of itself; taps beyond the tile's grid are skipped.
fn blur(grid: &mut Grid, line: &mut Vec<[f32; 2]>, copy: &mut Vec<[f32; 2]>) {
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    let n = nx.max(ny).max(nz);
    line.resize(n, [0.0; 2]);
    copy.resize(n, [0.0; 2]);
    let mut along = |len: usize, at: &dyn Fn(usize) -> usize, data: &mut [f32]| {
        for (j, c) in copy.iter_mut().enumerate().take(len) {
            *c = [data[at(j)], data[at(j) + 1]];
        }
        blur_line(len, |j| copy[j], line);
        for (j, r) in line.iter().enumerate().take(len) {
            data[at(j)..at(j) + 2].copy_from_slice(r);
        }
    };
    for z in 0..nz {
        for y in 0..ny {
            along(nx, &|x| ((z * ny + y) * nx + x) * 2, &mut grid.data);
        }
    }
    for z in 0..nz {
        for x in 0..nx {
            along(ny, &|y| ((z * ny + y) * nx + x) * 2, &mut grid.data);
        }
    }
    for y in 0..ny {
        for x in 0..nx {
            along(nz, &|z| ((z * ny + y) * nx + x) * 2, &mut grid.data);
        }
    }
}

/// Output pixels per tile side, in grid cells: the filter runs tile by
/// tile, each with its own grid of the cells its pixels read plus the blur's
/// reach, over the range of values found there — memory and time follow the
/// occupied cells, not the whole disparity range times the image.
const TILE_CELLS: usize = 32;

/// Bilateral grid filter of `values` with per-pixel `weights` (same size;
/// `None` = 1 where the value is finite).
#[must_use]
pub fn bilateral_filter(
    values: &Image,
    weights: Option<&Image>,
    params: &BilateralParams,
) -> (Image, GridInfo) {
    let (w, h) = values.dimensions();
    let weight_of = |p: usize| -> f32 {
        let v = values.data()[p];
        if !v.is_finite() {
            return 0.0;
        }
        weights.map_or(1.0, |wt| {
            let a = wt.data()[p];
            if a.is_finite() { a.max(0.0) } else { 0.0 }
        })
    };
    // The finite range by both cores (a minimum and a maximum: the same in any order, up to
    // the sign of a zero, which no cell index or weight below can tell).
    let range = values
        .data()
        .par_chunks(w.max(1))
        .filter_map(|row| {
            row.iter().copied().filter(|v| v.is_finite()).fold(
                None,
                |acc: Option<(f32, f32)>, v| {
                    Some(acc.map_or((v, v), |(lo, hi)| (lo.min(v), hi.max(v))))
                },
            )
        })
        .reduce_with(|(a, b), (c, d)| (a.min(c), b.max(d)));
    let Some((lo, hi)) = range else {
        return (
            values.clone(),
            GridInfo {
                nx: 0,
                ny: 0,
                nz: 0,
                sigma_r_used: params.sigma_r,
            },
        );
    };
    let ss = params.sigma_s.max(1e-3);
    let mut sr = params.sigma_r.max(1e-6);
    if ((hi - lo) / sr) as usize + 1 > MAX_RANGE_CELLS {
        sr = (hi - lo) / (MAX_RANGE_CELLS - 1) as f32;
    }
    let cells = |extent: f32, sigma: f32| (extent / sigma).ceil() as usize + 1 + 2 * PAD;
    let (nx, ny, nz) = (
        cells((w - 1) as f32, ss),
        cells((h - 1) as f32, ss),
        cells(hi - lo, sr),
    );
    // The splat's nearest cell of every column and row (monotonic).
    let splat_x: Vec<usize> = (0..w)
        .map(|x| (x as f32 / ss).round() as usize + PAD)
        .collect();
    let splat_y: Vec<usize> = (0..h)
        .map(|y| (y as f32 / ss).round() as usize + PAD)
        .collect();
    let cell_z = |f: f32| round_non_negative((f - lo) / sr) + PAD;

    // One tile: output pixels x0..x1 × y0..y1; on each axis the cells
    // c_lo..=c_hi its slice reads plus the blur's two cells either side, and
    // the pixels s0..s1 that splat into them.
    let tile_px = ((TILE_CELLS as f32 * ss).floor() as usize).max(1);
    let tiles: Vec<(usize, usize)> = (0..h)
        .step_by(tile_px)
        .flat_map(|y0| (0..w).step_by(tile_px).map(move |x0| (x0, y0)))
        .collect();
    let range = |p0: usize, p1: usize, n: usize, splat: &[usize]| {
        let lo_cell = (p0 as f32 / ss).floor() as usize + PAD;
        let hi_cell = ((p1 - 1) as f32 / ss).floor() as usize + PAD + 1;
        let (c_lo, c_hi) = (lo_cell.saturating_sub(2), (hi_cell + 2).min(n - 1));
        let s0 = splat.partition_point(|&c| c < c_lo);
        let s1 = splat.partition_point(|&c| c <= c_hi);
        (c_lo, c_hi, s0, s1)
    };
    let results: Vec<((usize, usize), Vec<f32>)> = tiles
        .par_iter()
        .map_init(
            || (Vec::new(), Vec::new(), Vec::new()),
            |(data, line, copy), &(x0, y0)| {
                let (x1, y1) = ((x0 + tile_px).min(w), (y0 + tile_px).min(h));
                let (cx_lo, cx_hi, sx0, sx1) = range(x0, x1, nx, &splat_x);
                let (cy_lo, cy_hi, sy0, sy1) = range(y0, y1, ny, &splat_y);
                // The range of values of the tile's splats and outputs.
                let (mut z_lo, mut z_hi) = (usize::MAX, 0usize);
                for y in sy0.min(y0)..sy1.max(y1) {
                    for x in sx0.min(x0)..sx1.max(x1) {
                        let f = values.data()[y * w + x];
                        if f.is_finite() {
                            let z = cell_z(f);
                            z_lo = z_lo.min(z);
                            z_hi = z_hi.max(z);
                        }
                    }
                }
                let mut out = vec![f32::NAN; (x1 - x0) * (y1 - y0)];
                if z_lo > z_hi {
                    return ((x0, y0), out);
                }
                let (cz_lo, cz_hi) = (z_lo.saturating_sub(2), (z_hi + 2).min(nz - 1));
                let mut grid = Grid {
                    nx: cx_hi - cx_lo + 1,
                    ny: cy_hi - cy_lo + 1,
                    nz: cz_hi - cz_lo + 1,
                    data: std::mem::take(data),
                };
                grid.data.clear();
                grid.data.resize(grid.nx * grid.ny * grid.nz * 2, 0.0);
                // Splat: nearest cell, in the order of the whole image.
                for (y, &gy) in splat_y.iter().enumerate().take(sy1).skip(sy0) {
                    for (x, &gx) in splat_x.iter().enumerate().take(sx1).skip(sx0) {
                        let p = y * w + x;
                        let wt = weight_of(p);
                        if wt == 0.0 {
                            continue;
                        }
                        let f = values.data()[p];
                        let i = grid.idx(gx - cx_lo, gy - cy_lo, cell_z(f) - cz_lo);
                        grid.data[i] += wt * f;
                        grid.data[i + 1] += wt;
                    }
                }
                blur(&mut grid, line, copy);
                // Slice: trilinear; corners beyond the tile's range of values
                // are empty cells.
                for y in y0..y1 {
                    for x in x0..x1 {
                        let f = values.data()[y * w + x];
                        let o = &mut out[(y - y0) * (x1 - x0) + x - x0];
                        *o = f;
                        if !f.is_finite() {
                            continue;
                        }
                        let fx = x as f32 / ss + PAD as f32;
                        let fy = y as f32 / ss + PAD as f32;
                        let fz = (f - lo) / sr + PAD as f32;
                        // Non-negative (at least PAD): truncation is the floor, without a
                        // library call.
                        let (gx, gy, gz) = (fx as usize, fy as usize, fz as usize);
                        let (tx, ty, tz) = (fx - gx as f32, fy - gy as f32, fz - gz as f32);
                        let mut acc = [0f32; 2];
                        for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
                            let zz = gz + dz;
                            for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
                                for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                                    let k = wx * wy * wz;
                                    let c = if (cz_lo..=cz_hi).contains(&zz) {
                                        let i =
                                            grid.idx(gx + dx - cx_lo, gy + dy - cy_lo, zz - cz_lo);
                                        [grid.data[i], grid.data[i + 1]]
                                    } else {
                                        [0.0, 0.0]
                                    };
                                    acc[0] += k * c[0];
                                    acc[1] += k * c[1];
                                }
                            }
                        }
                        if acc[1] > 1e-12 {
                            *o = acc[0] / acc[1];
                        }
                    }
                }
                *data = grid.data;
                ((x0, y0), out)
            },
        )
        .collect();
    // The tiles into place, a band of tile rows per task (the tiles cover the image).
    let mut out = Image::zeros(w, h);
    let per_band = w.div_ceil(tile_px);
    out.data_mut()
        .par_chunks_mut(tile_px * w)
        .zip(results.par_chunks(per_band))
        .for_each(|(band, tiles)| {
            for ((x0, _), tile) in tiles {
                let tw = (x0 + tile_px).min(w) - x0;
                for (r, row) in tile.chunks(tw).enumerate() {
                    band[r * w + x0..r * w + x0 + tw].copy_from_slice(row);
                }
            }
        });
    let info = GridInfo {
        nx,
        ny,
        nz,
        sigma_r_used: sr,
    };
    (out, info)
}

/// `v.round() as usize` for a non-negative `v` (half away from zero), without the library
/// call that `round` is on the baseline x86-64 target: the fraction `v − ⌊v⌋` is exact.
#[inline]
fn round_non_negative(v: f32) -> usize {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let whole = v as usize;
    // Saturating as the cast is (an infinity).
    whole.saturating_add(usize::from(v - whole as f32 >= 0.5))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rounding without the library call equals `round`, at and beside every half.
    #[test]
    fn rounding_of_non_negative_values_equals_the_library_round() {
        let halves = (0..2000).map(|k| k as f32 * 0.5);
        let beside = (0..2000).flat_map(|k| {
            let h = k as f32 * 0.5;
            [h.next_down().max(0.0), h.next_up()]
        });
        let spread = (0..100_000).map(|k| k as f32 * 0.013_7);
        for v in halves.chain(beside).chain(spread).chain([
            0.499_999_97,
            8_388_607.5,
            1e7,
            f32::INFINITY,
            f32::NAN,
        ]) {
            assert_eq!(round_non_negative(v), v.round() as usize, "{v}");
        }
    }

    /// The filter the grid computes, written as a sum over pixel pairs:
    /// `out(p) = Σ_q K(p, q) w_q f_q / Σ_q K(p, q) w_q` with
    /// `K(p, q) = Σ_corners c of p  trilinear(p, c) · g(c − cell(q))` and `g` the
    /// separable binomial kernel.
    fn naive(values: &Image, ss: f32, sr: f32) -> Image {
        let (w, h) = values.dimensions();
        let (lo, _) = values.finite_range().unwrap();
        let g = |k: i64| {
            if k.abs() <= 2 {
                KERNEL[(k + 2) as usize]
            } else {
                0.0
            }
        };
        let cell = |x: usize, y: usize, f: f32| {
            (
                (x as f32 / ss).round() as i64,
                (y as f32 / ss).round() as i64,
                ((f - lo) / sr).round() as i64,
            )
        };
        Image::from_fn(w, h, |x, y| {
            let f = values.get(x, y);
            if !f.is_finite() {
                return f;
            }
            let (fx, fy, fz) = (x as f32 / ss, y as f32 / ss, (f - lo) / sr);
            let (num, den) = (0..h)
                .flat_map(|qy| (0..w).map(move |qx| (qx, qy)))
                .filter(|&(qx, qy)| values.get(qx, qy).is_finite())
                .fold((0f64, 0f64), |(num, den), (qx, qy)| {
                    let fq = values.get(qx, qy);
                    let (cx, cy, cz) = cell(qx, qy, fq);
                    let mut k = 0f64;
                    for dz in 0..2 {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                let (ax, ay, az) = (
                                    fx.floor() as i64 + dx,
                                    fy.floor() as i64 + dy,
                                    fz.floor() as i64 + dz,
                                );
                                let tri = (1.0 - (fx - ax as f32).abs())
                                    * (1.0 - (fy - ay as f32).abs())
                                    * (1.0 - (fz - az as f32).abs());
                                k += f64::from(tri * g(ax - cx) * g(ay - cy) * g(az - cz));
                            }
                        }
                    }
                    (num + k * f64::from(fq), den + k)
                });
            (num / den) as f32
        })
    }

    #[test]
    fn grid_matches_the_pairwise_definition() {
        let img = Image::from_fn(13, 11, |x, y| {
            if x == 4 && y == 5 {
                f32::NAN
            } else {
                (x as f32 * 0.7).sin() * 4.0 + if x > 6 { 9.0 } else { 0.0 } + 0.1 * y as f32
            }
        });
        let params = BilateralParams {
            sigma_s: 2.0,
            sigma_r: 1.5,
        };
        let (fast, _) = bilateral_filter(&img, None, &params);
        let slow = naive(&img, 2.0, 1.5);
        for (a, b) in fast.data().iter().zip(slow.data()) {
            if b.is_nan() {
                assert!(a.is_nan());
            } else {
                assert!((a - b).abs() < 1e-3, "{a} vs {b}");
            }
        }
    }

    /// Across tiles (σs = 1: 32-pixel tiles, 3 × 2 of them here) and with a
    /// range of values much wider than any one tile's: the same filter.
    #[test]
    fn tiles_match_the_pairwise_definition() {
        let img = Image::from_fn(70, 45, |x, y| {
            if (x, y) == (33, 20) {
                f32::NAN
            } else {
                0.6 * x as f32 + (y as f32 * 0.9).sin() * 2.0 + if y > 30 { 7.0 } else { 0.0 }
            }
        });
        let params = BilateralParams {
            sigma_s: 1.0,
            sigma_r: 1.5,
        };
        let (fast, info) = bilateral_filter(&img, None, &params);
        assert!(info.nz > 20, "{info:?}");
        let slow = naive(&img, 1.0, 1.5);
        for (a, b) in fast.data().iter().zip(slow.data()) {
            if b.is_nan() {
                assert!(a.is_nan());
            } else {
                assert!((a - b).abs() < 1e-3, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn smooths_noise_and_keeps_a_step() {
        let mut seed = 3u32;
        let truth = |x: usize| if x < 20 { 0.0 } else { 12.0 };
        let img = Image::from_fn(40, 30, |x, _| {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            truth(x) + ((seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5)
        });
        let (out, _) = bilateral_filter(&img, None, &BilateralParams::default());
        let rms = |im: &Image| {
            let s: f32 = (0..30)
                .flat_map(|y| (0..40).map(move |x| (x, y)))
                .map(|(x, y)| (im.get(x, y) - truth(x)).powi(2))
                .sum();
            (s / 1200.0).sqrt()
        };
        assert!(
            rms(&out) < 0.5 * rms(&img),
            "{} vs {}",
            rms(&out),
            rms(&img)
        );
        // The step stays a step: next to the edge the values keep their side.
        for y in 0..30 {
            assert!(out.get(19, y) < 1.0 && out.get(20, y) > 11.0);
        }
    }

    #[test]
    fn zero_weight_pixels_do_not_contribute() {
        let img = Image::from_fn(20, 20, |x, _| if x == 10 { 1.0 } else { 0.0 });
        let weights = Image::from_fn(20, 20, |x, _| if x == 10 { 0.0 } else { 1.0 });
        let (out, _) = bilateral_filter(
            &img,
            Some(&weights),
            &BilateralParams {
                sigma_s: 3.0,
                sigma_r: 10.0,
            },
        );
        assert!(out.data().iter().all(|v| v.abs() < 1e-6));
    }
}
