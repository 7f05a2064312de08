//! Bilateral filtering through the bilateral grid (Paris & Durand, IJCV 2009).
//!
//! The image is lifted into a coarse 3-D grid `(x/σs, y/σs, value/σr)` of
//! homogeneous values `(w·f, w)` by nearest-cell splatting, the grid is blurred
//! with the binomial kernel [1 4 6 4 1]/16 along each axis (a Gaussian of one
//! cell), and the result is read back by trilinear slicing and division — an
//! edge-preserving smoothing whose cost does not grow with σs.
//!
//! Used on the disparity (range axis = disparity itself, in pixels) with a
//! per-pixel weight: 0 drops a pixel (unknown, occluded), a confidence in
//! `(0, 1]` lets reliable pixels dominate. Pixels whose input is `NaN` stay `NaN`.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::Image;

/// Parameters of the bilateral filter of the disparity (SD-SEM §2.4).
///
/// | parameter | default | effect |
/// | --- | --- | --- |
/// | `sigma_s` | 3 | spatial σ, pixels: larger smooths over a wider area |
/// | `sigma_r` | 3 | range σ, disparity pixels: disparity steps much larger than this are kept sharp |
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BilateralParams {
    pub sigma_s: f32,
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
/// The binomial kernel [1 4 6 4 1]/16 (variance one cell²), also the blur of
/// the refinement's cross-bilateral grid.
pub(super) const KERNEL: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];

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

/// Blurs the grid in place along x, then y, then z. Along x and y every
/// z-slab is one parallel task with a line buffer; along z the slabs are
/// swept in order, keeping copies of the two originals below the current
/// one, and each slab is computed in parallel — never a copy of the whole
/// grid, and every pass reads memory in order.
fn blur(grid: &mut Grid) {
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    let slab = nx * ny * 2;
    grid.data.par_chunks_mut(slab).for_each_init(
        || (vec![[0f32; 2]; nx.max(ny)], vec![0f32; slab]),
        |(line, copy), s| {
            // Along x: rows are contiguous.
            for row in s.chunks_mut(nx * 2) {
                blur_line(nx, |j| [row[2 * j], row[2 * j + 1]], line);
                for (c, r) in row.chunks_exact_mut(2).zip(line.iter()) {
                    c.copy_from_slice(r);
                }
            }
            // Along y: from a copy of the slab, one column at a time.
            copy.copy_from_slice(s);
            for x in 0..nx {
                let at = |y: usize| (y * nx + x) * 2;
                blur_line(ny, |j| [copy[at(j)], copy[at(j) + 1]], line);
                for (y, r) in line.iter().enumerate().take(ny) {
                    s[at(y)..at(y) + 2].copy_from_slice(r);
                }
            }
        },
    );
    // Along z: out[z] = Σ_t k_t · in[z + t − 2], the originals of z − 2 and
    // z − 1 kept aside before they are overwritten.
    let mut below = [vec![0f32; slab], vec![0f32; slab]];
    let mut out = vec![0f32; slab];
    for z in 0..nz {
        {
            let data = &grid.data;
            let (b2, b1) = (&below[0], &below[1]);
            out.par_chunks_mut(2 * nx).enumerate().for_each(|(y, o)| {
                let start = y * 2 * nx;
                for (i, v) in o.iter_mut().enumerate() {
                    let mut acc = 0f32;
                    for (t, &k) in KERNEL.iter().enumerate() {
                        let zz = z as isize + t as isize - 2;
                        if zz < 0 || zz >= nz as isize {
                            continue;
                        }
                        let c = match t {
                            0 => b2[start + i],
                            1 => b1[start + i],
                            _ => data[zz as usize * slab + start + i],
                        };
                        acc += k * c;
                    }
                    *v = acc;
                }
            });
        }
        let cur = &mut grid.data[z * slab..(z + 1) * slab];
        below.swap(0, 1);
        below[1].copy_from_slice(cur);
        cur.copy_from_slice(&out);
    }
}

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
    let Some((lo, hi)) = values.finite_range() else {
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
    let mut grid = Grid {
        nx: cells((w - 1) as f32, ss),
        ny: cells((h - 1) as f32, ss),
        nz: cells(hi - lo, sr),
        data: Vec::new(),
    };
    grid.data = vec![0f32; grid.nx * grid.ny * grid.nz * 2];

    // Splat: nearest cell.
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let wt = weight_of(p);
            if wt == 0.0 {
                continue;
            }
            let f = values.data()[p];
            let gx = (x as f32 / ss).round() as usize + PAD;
            let gy = (y as f32 / ss).round() as usize + PAD;
            let gz = ((f - lo) / sr).round() as usize + PAD;
            let i = grid.idx(gx, gy, gz);
            grid.data[i] += wt * f;
            grid.data[i + 1] += wt;
        }
    }

    // Blur along x, y, z.
    let (nx, ny, nz) = (grid.nx, grid.ny, grid.nz);
    blur(&mut grid);

    // Slice: trilinear.
    let mut out = values.clone();
    out.data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let f = *o;
                if !f.is_finite() {
                    continue;
                }
                let fx = x as f32 / ss + PAD as f32;
                let fy = y as f32 / ss + PAD as f32;
                let fz = (f - lo) / sr + PAD as f32;
                let (x0, y0, z0) = (
                    fx.floor() as usize,
                    fy.floor() as usize,
                    fz.floor() as usize,
                );
                let (tx, ty, tz) = (fx - x0 as f32, fy - y0 as f32, fz - z0 as f32);
                let mut acc = [0f32; 2];
                for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
                    for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
                        for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                            let i = grid.idx(x0 + dx, y0 + dy, z0 + dz);
                            let k = wx * wy * wz;
                            acc[0] += k * grid.data[i];
                            acc[1] += k * grid.data[i + 1];
                        }
                    }
                }
                if acc[1] > 1e-12 {
                    *o = acc[0] / acc[1];
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

#[cfg(test)]
mod tests {
    use super::*;

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
