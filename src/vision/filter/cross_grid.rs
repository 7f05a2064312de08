//! The cross (joint) bilateral grid: a window whose weights follow a guide
//! image, for the edge-aware sums of the flow refinement.

use rayon::prelude::*;

use super::blur::BINOMIAL_5 as XB_KERNEL;
use super::blur::blur_plane;

/// Cells of padding on every side of the cross-bilateral grid: the trilinear
/// splat reaches one cell beyond a pixel's, the binomial blur two more.
const XB_PAD: usize = 2;
/// Range cells at most; a wider intensity range coarsens the range sampling.
const XB_MAX_RANGE_CELLS: usize = 96;
/// Variance, in cells², of the whole grid filter along one axis: trilinear
/// splat (1/6), binomial blur (1), trilinear slice (1/6).
const XB_CELL_VARIANCE: f32 = 4.0 / 3.0;
/// σ (pixels) of the Gaussian pre-smoothing of the key image.
const XB_KEY_PRESMOOTH: f32 = 1.0;

/// Joint (cross) bilateral aggregation keyed on one image (Paris & Durand's
/// bilateral grid, with a guide image as in Petschnigg et al. 2004 and
/// Eisemann & Durand 2004): the weight of pixel `q` in the sum at `p` falls
/// with their distance (σ `window_sigma`) and with the difference of the
/// key's values at `p` and `q` (σ `range_sigma`), the adaptive support
/// weights of Yoon & Kweon (2006), so a window does not straddle an edge of
/// the key image. Sums are normalised by the same weights of all pixels (the
/// Gaussian window's normalisation), so invalid pixels count as zeros.
///
/// Values are splatted trilinearly at `(x/c, y/c, key/c_r)`, the grid blurred
/// by the binomial kernel along each axis and sliced trilinearly; the cell
/// sizes `c = σ/√(4/3)` give the filter the asked variances. Every grid row
/// sums its pixel rows in the order of the rows, in parallel over runs of grid
/// rows: the result does not depend on the thread count. The values may be
/// produced row by row while they are splatted and the sums taken row by row
/// while they are sliced ([`CrossGrid::splat_rows`], [`CrossGrid::slice_row`]),
/// so that no full-size buffer of values or sums need exist.
pub(crate) struct CrossGrid {
    w: usize,
    h: usize,
    nx: usize,
    ny: usize,
    nz: usize,
    /// Spatial cell size, pixels.
    cell: f32,
    /// Range coordinate of every pixel, cells (padding included).
    fz: Vec<f32>,
    /// Per pixel column `x`: its cell `x0` and the offset `tx` of `x / c` (padding
    /// included) within it, the same for every row.
    columns: Vec<(usize, f32)>,
    /// The filter's weight sum at every pixel (the normaliser).
    norm: Vec<f32>,
}

/// Runs of grid rows splatted, and blurred along y, at once per thread (the sums do not
/// depend on it).
const XB_RUNS_PER_THREAD: usize = 4;

impl CrossGrid {
    /// The grid of `key` (one value per pixel, `w × h`) for a window of
    /// `sigma_s` pixels and a range σ of `sigma_r` key units.
    #[cfg(test)]
    pub(crate) fn new(key: &[f32], w: usize, h: usize, sigma_s: f32, sigma_r: f32) -> Self {
        let mut ones = vec![[1f32; 1]; w * h];
        Self::with_sums(key, w, h, sigma_s, sigma_r, &mut ones, None)
    }

    /// The geometry of the grid of `key`, without its normaliser.
    fn layout(key: &[f32], w: usize, h: usize, sigma_s: f32, sigma_r: f32) -> Self {
        let scale = XB_CELL_VARIANCE.sqrt();
        let cell = (sigma_s / scale).max(0.5);
        let (lo, hi) = key
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &k| {
                (lo.min(k), hi.max(k))
            });
        let (lo, hi) = if lo <= hi { (lo, hi) } else { (0.0, 0.0) };
        let mut cell_r = (sigma_r / scale).max(1e-6);
        if (hi - lo) / cell_r > (XB_MAX_RANGE_CELLS - 2 - 2 * XB_PAD) as f32 {
            cell_r = (hi - lo) / (XB_MAX_RANGE_CELLS - 2 - 2 * XB_PAD) as f32;
        }
        let cells = |extent: f32, c: f32| (extent / c).floor() as usize + 2 + 2 * XB_PAD;
        let fz: Vec<f32> = key
            .par_iter()
            .map(|&k| (k - lo) / cell_r + XB_PAD as f32)
            .collect();
        let pad = XB_PAD as f32;
        let columns = (0..w)
            .map(|x| {
                let fx = x as f32 / cell + pad;
                let x0 = fx as usize; // positive: truncation is the floor
                (x0, fx - x0 as f32)
            })
            .collect();
        Self {
            w,
            h,
            nx: cells((w - 1) as f32, cell),
            ny: cells((h - 1) as f32, cell),
            nz: cells(hi - lo, cell_r),
            cell,
            fz,
            columns,
            norm: Vec::new(),
        }
    }

    /// The grid of [`CrossGrid::new`], and in `values` their un-normalised
    /// sums through it: the last channel must hold ones, whose sums become
    /// the normaliser, so one pass of the filter serves both (channels do not
    /// mix: each one's sums are those of a pass of its own). Sums and
    /// normaliser are taken at the pixels `wanted` marks (zeros elsewhere;
    /// `None`: all): [`CrossGrid::aggregate`] is then right at those only.
    #[cfg(test)]
    pub(crate) fn with_sums<const C: usize>(
        key: &[f32],
        w: usize,
        h: usize,
        sigma_s: f32,
        sigma_r: f32,
        values: &mut [[f32; C]],
        wanted: Option<&[bool]>,
    ) -> Self {
        let mut g = Self::layout(key, w, h, sigma_s, sigma_r);
        g.sums(values, &mut Vec::new(), wanted);
        g.norm = values.iter().map(|v| v[C - 1]).collect();
        g
    }

    /// [`CrossGrid::with_sums`] of the values `produce` writes row by row (`produce(y, row)`
    /// fills pixel row `y`); `consume(y, sums, item)` takes the un-normalised sums of pixel
    /// row `y` with the `y`-th item of `rows`. `grid` is a reused buffer.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn with_row_sums<const C: usize, I>(
        key: &[f32],
        (w, h): (usize, usize),
        (sigma_s, sigma_r): (f32, f32),
        produce: &(impl Fn(usize, &mut [[f32; C]]) + Sync),
        wanted: Option<&[bool]>,
        grid: &mut Vec<f32>,
        rows: I,
        consume: impl Fn(usize, &[[f32; C]], I::Item) + Sync,
    ) -> Self
    where
        I: IndexedParallelIterator,
    {
        let mut g = Self::layout(key, w, h, sigma_s, sigma_r);
        g.splat_rows(produce, grid);
        let mut norm = vec![0f32; w * h];
        let grid: &[f32] = grid;
        rows.zip(norm.par_chunks_mut(w)).enumerate().for_each_init(
            || vec![[0f32; C]; w],
            |sums, (y, (item, norm_row))| {
                g.slice_row(grid, y, wanted, sums, false);
                for (n, s) in norm_row.iter_mut().zip(sums.iter()) {
                    *n = s[C - 1];
                }
                consume(y, sums, item);
            },
        );
        g.norm = norm;
        g
    }

    /// Replaces every pixel of `buf` by its normalised weighted sum (only
    /// those `wanted` marks, the others by zeros; `None`: all); `grid` is a
    /// reused buffer (resized as needed).
    #[cfg(test)]
    pub(crate) fn aggregate<const C: usize>(
        &self,
        buf: &mut [[f32; C]],
        grid: &mut Vec<f32>,
        wanted: Option<&[bool]>,
    ) {
        self.sums(buf, grid, wanted);
        buf.par_iter_mut().zip(&self.norm).for_each(|(v, &n)| {
            let inv = if n > 1e-12 { 1.0 / n } else { 0.0 };
            for c in v.iter_mut() {
                *c *= inv;
            }
        });
    }

    /// Un-normalised sums of the values in `buf`, in place ([`CrossGrid::splat_rows`] of
    /// its rows, then [`CrossGrid::slice_row`] of every row).
    #[cfg(test)]
    fn sums<const C: usize>(
        &self,
        buf: &mut [[f32; C]],
        grid: &mut Vec<f32>,
        wanted: Option<&[bool]>,
    ) {
        let w = self.w;
        {
            let src: &[[f32; C]] = buf;
            self.splat_rows(
                &|y, row: &mut [[f32; C]]| row.copy_from_slice(&src[y * w..(y + 1) * w]),
                grid,
            );
        }
        let grid: &[f32] = grid;
        buf.par_chunks_mut(w)
            .enumerate()
            .for_each(|(y, row)| self.slice_row(grid, y, wanted, row, false));
    }

    /// The pixel rows that can splat into grid row `gy` (a superset: those within one cell
    /// of it; [`CrossGrid::splat_rows`] tests the distance itself).
    fn pixel_rows(&self, gy: usize) -> std::ops::Range<usize> {
        let (cell, pad) = (self.cell, XB_PAD as f32);
        let y_lo = ((gy as f32 - 1.0 - pad) * cell).floor().max(0.0) as usize;
        let y_hi = (((gy as f32 + 1.0 - pad) * cell).ceil().max(0.0) as usize).min(self.h);
        y_lo..y_hi
    }

    /// Splat and blur: `grid` (resized as needed) takes the blurred grid of the values
    /// `produce(y, row)` writes into pixel row `y` (called once per row), ready for
    /// [`CrossGrid::slice_row`]. One grid-sized buffer: the x and z passes run inside each
    /// grid row, the y pass in place ([`blur_y_in_place`]).
    ///
    /// Grid row `gy` sums the pixel rows within one cell of it, in the order of the rows.
    /// Runs of grid rows splat in parallel, each producing its pixel rows in order and
    /// splatting each into the (up to two) grid rows of the run it reaches; the rows a
    /// run shares with the one before are produced once, before the runs start.
    ///
    /// Every pass computes only the box of cells its input can reach
    /// ([`Extent`]): a cell outside holds +0 before and after the pass (a sum of
    /// +0 terms), and a +0 term leaves a sum unchanged to the bit, so the result
    /// is that of the passes over the whole grid (the fill of a rotated canvas
    /// and the unused range cells cost nothing).
    pub(crate) fn splat_rows<const C: usize>(
        &self,
        produce: &(impl Fn(usize, &mut [[f32; C]]) + Sync),
        grid: &mut Vec<f32>,
    ) {
        let run = self
            .ny
            .div_ceil(XB_RUNS_PER_THREAD * rayon::current_num_threads());
        self.splat_rows_in_runs(produce, grid, run);
    }

    /// [`CrossGrid::splat_rows`] in runs of `run` grid rows.
    fn splat_rows_in_runs<const C: usize>(
        &self,
        produce: &(impl Fn(usize, &mut [[f32; C]]) + Sync),
        grid: &mut Vec<f32>,
        run: usize,
    ) {
        let (w, nx, ny, nz) = (self.w, self.nx, self.ny, self.nz);
        let slab = nx * nz;
        grid.clear();
        // Exactly: the 6-channel sums follow the 4-channel ones in the same buffer.
        grid.reserve_exact(slab * ny * C);
        // Zeroed by both cores: tens of MB at full resolution, whose clearing (and first touch)
        // on one core alone left the other idle.
        grid.par_extend(rayon::iter::repeat_n(0.0, slab * ny * C));
        let cell = self.cell;
        let pad = XB_PAD as f32;
        let run = run.max(1);
        // The pixel rows run `i` shares with run `i − 1`, produced once.
        let shared: Vec<(std::ops::Range<usize>, Vec<[f32; C]>)> = (0..ny.div_ceil(run))
            .into_par_iter()
            .map(|i| {
                if i == 0 {
                    return (0..0, Vec::new());
                }
                let g0 = i * run;
                let ys = self.pixel_rows(g0).start..self.pixel_rows(g0 - 1).end;
                let mut vals = vec![[0f32; C]; ys.len() * w];
                for (y, row) in ys.clone().zip(vals.chunks_mut(w)) {
                    produce(y, row);
                }
                (ys, vals)
            })
            .collect();
        let mut extents = vec![Extent::EMPTY; ny];
        grid.as_chunks_mut::<C>()
            .0
            .par_chunks_mut(run * slab)
            .zip(extents.par_chunks_mut(run))
            .zip(&shared)
            .enumerate()
            .for_each(|(i, ((cells, ext), (shared_ys, shared_vals)))| {
                let (g0, g1) = (i * run, i * run + ext.len());
                let mut own = vec![[0f32; C]; w];
                for y in self.pixel_rows(g0).start..self.pixel_rows(g1 - 1).end {
                    let vals: &[[f32; C]] = if shared_ys.contains(&y) {
                        &shared_vals[(y - shared_ys.start) * w..][..w]
                    } else {
                        produce(y, &mut own);
                        &own
                    };
                    let fy = y as f32 / cell + pad;
                    let near = fy as usize; // positive: truncation is the floor
                    for gy in near.saturating_sub(1).max(g0)..(near + 3).min(g1) {
                        let dy = fy - gy as f32;
                        if dy.abs() >= 1.0 || !self.pixel_rows(gy).contains(&y) {
                            continue;
                        }
                        let wy = 1.0 - dy.abs();
                        let s = &mut cells[(gy - g0) * slab..(gy - g0 + 1) * slab];
                        let e = &mut ext[gy - g0];
                        for (x, (&(x0, tx), v)) in self.columns.iter().zip(vals).enumerate() {
                            if v.iter().all(|&b| b == 0.0) {
                                // Adds nothing (the refinement's products are zero
                                // at unusable pixels: the fill of a rotated canvas).
                                continue;
                            }
                            let fz = self.fz[y * w + x];
                            let z0 = fz as usize; // positive: truncation is the floor
                            e.include(x0, z0);
                            let tz = fz - z0 as f32;
                            for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
                                for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                                    let k = wy * wz * wx;
                                    let cellv = &mut s[(z0 + dz) * nx + x0 + dx];
                                    for (a, &b) in cellv.iter_mut().zip(v) {
                                        *a += k * b;
                                    }
                                }
                            }
                        }
                    }
                }
            });
        let grid = grid.as_chunks_mut::<C>().0;
        // Blur along x, z (inside every slab, i.e. grid row) and y. The data
        // sit at least `XB_PAD` cells from every border and the slice reads
        // only those interior cells: each pass computes the interior of its
        // axis, where every tap is inside the grid (no bounds tests).
        let (px, pz) = (XB_PAD..nx - XB_PAD, XB_PAD..nz - XB_PAD);
        grid.par_chunks_mut(slab)
            .zip(extents.par_iter_mut())
            .for_each_init(
                || vec![[0f32; C]; slab],
                |out, (s, e)| {
                    if e.is_empty() {
                        return;
                    }
                    let zs = e.z.clone();
                    *e = e.grown(&px, &pz);
                    let (s, out) = (s.as_flattened_mut(), out.as_flattened_mut());
                    let cols = e.x.start * C..e.x.end * C;
                    // x: s → out, the rows with data; tap by tap along the row
                    // (contiguous: vectorises), each sum in the order of the taps.
                    for z in zs.clone() {
                        let row = z * nx * C;
                        let o = &mut out[row + cols.start..row + cols.end];
                        o.fill(0.0);
                        for (t, &k) in XB_KERNEL.iter().enumerate() {
                            let from = row + cols.start + t * C - 2 * C;
                            for (a, &b) in o.iter_mut().zip(&s[from..from + cols.len()]) {
                                *a += k * b;
                            }
                        }
                    }
                    // z: out → s; rows of `out` outside `zs` are zeros, not read.
                    for z in e.z.clone() {
                        let o = &mut s[z * nx * C + cols.start..z * nx * C + cols.end];
                        o.fill(0.0);
                        for (t, &k) in XB_KERNEL.iter().enumerate() {
                            let j = z + t - 2;
                            if !zs.contains(&j) {
                                continue;
                            }
                            let from = j * nx * C;
                            let src = &out[from + cols.start..from + cols.end];
                            for (a, &b) in o.iter_mut().zip(src) {
                                *a += k * b;
                            }
                        }
                    }
                },
            );
        blur_y_in_place(
            grid,
            nx,
            &extents,
            XB_RUNS_PER_THREAD * rayon::current_num_threads(),
        );
    }

    /// Slice: `row` takes the trilinear interpolation of the blurred `grid`
    /// ([`CrossGrid::splat_rows`]) at every pixel `(x, y, key)` of pixel row `y`, the
    /// un-normalised sums, or their normalised values when `normalised` (at the pixels
    /// `wanted` marks, zeros elsewhere).
    pub(crate) fn slice_row<const C: usize>(
        &self,
        grid: &[f32],
        y: usize,
        wanted: Option<&[bool]>,
        row: &mut [[f32; C]],
        normalised: bool,
    ) {
        let (w, nx, cell, pad) = (self.w, self.nx, self.cell, XB_PAD as f32);
        let slab = nx * self.nz;
        let s = grid.as_chunks::<C>().0;
        let fy = y as f32 / cell + pad;
        let y0 = fy.floor() as usize;
        let ty = fy - y0 as f32;
        for (x, o) in row.iter_mut().enumerate() {
            let p = y * w + x;
            if wanted.is_some_and(|m| !m[p]) {
                *o = [0f32; C];
                continue;
            }
            let (x0, tx) = self.columns[x];
            let fz = self.fz[p];
            let z0 = fz as usize; // positive: truncation is the floor
            let tz = fz - z0 as f32;
            let mut acc = [0f32; C];
            for (dy, wy) in [(0, 1.0 - ty), (1, ty)] {
                for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
                    for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                        let k = wy * wz * wx;
                        let v = &s[(y0 + dy) * slab + (z0 + dz) * nx + x0 + dx];
                        for (a, &b) in acc.iter_mut().zip(v) {
                            *a += k * b;
                        }
                    }
                }
            }
            *o = acc;
            if normalised {
                let n = self.norm[p];
                let inv = if n > 1e-12 { 1.0 / n } else { 0.0 };
                for c in o.iter_mut() {
                    *c *= inv;
                }
            }
        }
    }
}

/// The box of one grid row (slab) outside which its cells are +0: columns
/// `x`, range cells `z` (empty when either is).
#[derive(Debug, Clone, PartialEq, Eq)]
struct Extent {
    x: std::ops::Range<usize>,
    z: std::ops::Range<usize>,
}

impl Extent {
    /// No cell: reversed ranges, the start of [`Extent::include`]'s minima and maxima.
    #[allow(clippy::reversed_empty_ranges)]
    const EMPTY: Self = Self {
        x: usize::MAX..0,
        z: usize::MAX..0,
    };

    fn is_empty(&self) -> bool {
        self.x.is_empty() || self.z.is_empty()
    }

    /// Takes in the 2 × 2 cells a splat at `(x0, z0)` writes.
    fn include(&mut self, x0: usize, z0: usize) {
        self.x = self.x.start.min(x0)..self.x.end.max(x0 + 2);
        self.z = self.z.start.min(z0)..self.z.end.max(z0 + 2);
    }

    /// The box after the 5-tap blur along x and z (two cells further each
    /// way), within the interior `px × pz` the passes compute.
    fn grown(&self, px: &std::ops::Range<usize>, pz: &std::ops::Range<usize>) -> Self {
        let grow = |r: &std::ops::Range<usize>, within: &std::ops::Range<usize>| {
            r.start.saturating_sub(2).max(within.start)..(r.end + 2).min(within.end)
        };
        Self {
            x: grow(&self.x, px),
            z: grow(&self.z, pz),
        }
    }
}

/// The binomial blur along y of the grid rows (`slab` = `nx` · nz cells each) at least
/// `XB_PAD` rows from either end, in place: row `gy` becomes `Σ_t k_t · g[gy + t − 2]`
/// of the rows before the pass, summed in the order of `t` (the same bits as a pass
/// into a second grid). A row adds only the box of its [`Extent`] (+0 outside).
/// The rows are cut into `chunks` runs of about the same work (the boxes their taps add:
/// a rotated canvas's rows differ widely) that blur at the same time; each keeps the two
/// original rows before its current one, and the two rows past its end are copied before any
/// run starts, so the result does not depend on `chunks` or on where the runs are cut.
fn blur_y_in_place<const C: usize>(
    grid: &mut [[f32; C]],
    nx: usize,
    extents: &[Extent],
    chunks: usize,
) {
    let ny = extents.len();
    let slab = grid.len().checked_div(ny).unwrap_or(0);
    if ny < 2 * XB_PAD + 1 || slab == 0 {
        return;
    }
    let (first, end) = (XB_PAD, ny - XB_PAD);
    let rows = end - first;
    let chunks = chunks.clamp(1, rows);
    // Each row's work: the cells its five taps add, and its own row's clearing and swap.
    let area = |e: &Extent| {
        if e.is_empty() {
            0
        } else {
            e.x.len() * e.z.len()
        }
    };
    let work: Vec<usize> = (first..end)
        .map(|gy| slab / 8 + 1 + extents[gy - 2..=gy + 2].iter().map(area).sum::<usize>())
        .collect();
    let total: usize = work.iter().sum();
    let mut bounds: Vec<(usize, usize)> = Vec::with_capacity(chunks);
    let (mut a, mut done) = (first, 0usize);
    for (gy, &w) in (first..end).zip(&work) {
        done += w;
        // Cut after row gy once the run reaches its share of the total.
        if done * chunks >= total * (bounds.len() + 1) && bounds.len() + 1 < chunks {
            bounds.push((a, gy + 1));
            a = gy + 1;
        }
    }
    if a < end {
        bounds.push((a, end));
    }
    let row = |g: &[[f32; C]], j: usize| g[j * slab..(j + 1) * slab].to_vec();
    // Per run: the original rows a − 2, a − 1 (before it) and b, b + 1 (after it).
    let halos: Vec<[Vec<[f32; C]>; 4]> = bounds
        .iter()
        .map(|&(a, b)| {
            [
                row(grid, a - 2),
                row(grid, a - 1),
                row(grid, b),
                row(grid, b + 1),
            ]
        })
        .collect();
    let mut runs = Vec::with_capacity(bounds.len());
    let mut rest = &mut grid[first * slab..end * slab];
    for &(a, b) in &bounds {
        let (run, tail) = std::mem::take(&mut rest).split_at_mut((b - a) * slab);
        runs.push(run);
        rest = tail;
    }
    runs.into_par_iter().zip(halos).zip(&bounds).for_each(
        |((run, [mut before2, mut before1, after0, after1]), &(a, b))| {
            let mut acc = vec![[0f32; C]; slab];
            for gy in a..b {
                acc.fill([0f32; C]);
                let out = acc.as_flattened_mut();
                for (t, &k) in XB_KERNEL.iter().enumerate() {
                    let j = gy + t - 2;
                    let e = &extents[j];
                    if e.is_empty() {
                        continue;
                    }
                    let src: &[[f32; C]] = match j {
                        _ if j + 2 == gy => &before2,
                        _ if j + 1 == gy => &before1,
                        _ if j < b => &run[(j - a) * slab..(j - a + 1) * slab],
                        _ if j == b => &after0,
                        _ => &after1,
                    };
                    let src = src.as_flattened();
                    for z in e.z.clone() {
                        let cols = (z * nx + e.x.start) * C..(z * nx + e.x.end) * C;
                        for (o, &v) in out[cols.clone()].iter_mut().zip(&src[cols]) {
                            *o += k * v;
                        }
                    }
                }
                // Row gy takes its sum; its original moves into the two kept rows.
                run[(gy - a) * slab..(gy - a + 1) * slab].swap_with_slice(&mut acc);
                std::mem::swap(&mut before2, &mut before1);
                std::mem::swap(&mut before1, &mut acc);
            }
        },
    );
}

/// The key of the cross-bilateral aggregation: the first image lightly
/// smoothed, in units of its standard deviation (sequential sums: the same
/// figure whatever the thread count).
pub(crate) fn range_key(img: &[f32], w: usize, h: usize) -> Vec<f32> {
    range_key_smoothed(img, w, h, XB_KEY_PRESMOOTH)
}

/// [`range_key`] with the image smoothed by `sigma` pixels, still in units of the standard
/// deviation of the lightly smoothed image: a wider smoothing drops fine texture from the key
/// (the windows stay whole on a textured surface) and keeps the contrast of larger regions.
pub(crate) fn range_key_smoothed(img: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    let finite: Vec<f32> = img
        .par_iter()
        .map(|&v| if v.is_finite() { v } else { 0.0 })
        .collect();
    let spread = |s: &[f32]| {
        let n = s.len().max(1) as f64;
        let mean = s.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let var = s
            .iter()
            .map(|&v| (f64::from(v) - mean).powi(2))
            .sum::<f64>()
            / n;
        (mean, var)
    };
    let s = blur_plane(&finite, w, h, sigma);
    let (mean, var) = spread(&s);
    let var = if sigma == XB_KEY_PRESMOOTH {
        var
    } else {
        spread(&blur_plane(&finite, w, h, XB_KEY_PRESMOOTH)).1
    };
    let inv = if var > 0.0 { 1.0 / var.sqrt() } else { 1.0 };
    s.par_iter()
        .map(|&v| ((f64::from(v) - mean) * inv) as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two regions of different brightness, each with fine texture: the wider smoothing drops
    /// most of the texture from the key and keeps the regions' difference, in the same units.
    #[test]
    fn a_smoothed_key_keeps_regions_and_drops_fine_texture() {
        let (w, h) = (96, 64);
        let img: Vec<f32> = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f32, (p / w) as f32);
                let k = std::f32::consts::TAU / 6.0;
                let texture = 0.5 * (k * x).sin() * (k * y).sin();
                texture + if x >= 48.0 { 1.0 } else { 0.0 }
            })
            .collect();
        assert_eq!(range_key(&img, w, h), range_key_smoothed(&img, w, h, 1.0));
        let (fine, wide) = (range_key(&img, w, h), range_key_smoothed(&img, w, h, 3.0));
        // The key's mean and spread over 24 × 24 px of one region, away from the edge and border.
        let stats = |k: &[f32], x0: usize| {
            let v: Vec<f32> = (20..44)
                .flat_map(|y| (x0..x0 + 24).map(move |x| k[y * w + x]))
                .collect();
            let m = v.iter().sum::<f32>() / v.len() as f32;
            let s = (v.iter().map(|a| (a - m).powi(2)).sum::<f32>() / v.len() as f32).sqrt();
            (m, s)
        };
        let ((fl, fs), (fr, _)) = (stats(&fine, 10), stats(&fine, 62));
        let ((wl, ws), (wr, _)) = (stats(&wide, 10), stats(&wide, 62));
        assert!(
            ws < 0.1 * fs,
            "texture in the key: {ws} smoothed, {fs} light"
        );
        let (step_fine, step_wide) = (fr - fl, wr - wl);
        assert!(
            step_fine > 1.0 && (step_wide - step_fine).abs() < 0.05 * step_fine,
            "regions' difference {step_wide} smoothed, {step_fine} light"
        );
    }

    /// The filter the cross-bilateral grid computes, written as a sum over
    /// pixel pairs: `out(p) = Σ_q K(p, q) f_q / Σ_q K(p, q)` with
    /// `K(p, q) = Σ_c Σ_c' tri(p, c) · g(c − c') · tri(q, c')` over the grid
    /// corners `c` around `p` (slice) and `c'` around `q` (splat), `tri` the
    /// trilinear weights and `g` the separable binomial kernel.
    fn naive_cross(values: &[[f32; 2]], key: &[f32], w: usize, g: &CrossGrid) -> Vec<[f32; 2]> {
        let pad = XB_PAD as f32;
        let corners = |p: usize| -> Vec<([i64; 3], f32)> {
            let f = [
                (p % w) as f32 / g.cell + pad,
                (p / w) as f32 / g.cell + pad,
                g.fz[p],
            ];
            let mut out = Vec::new();
            for d in 0..8 {
                let mut c = [0i64; 3];
                let mut wt = 1f32;
                for (k, fk) in f.iter().enumerate() {
                    let base = fk.floor();
                    let t = fk - base;
                    let up = (d >> k) & 1 == 1;
                    c[k] = base as i64 + i64::from(up);
                    wt *= if up { t } else { 1.0 - t };
                }
                out.push((c, wt));
            }
            out
        };
        let binom = |k: i64| {
            if k.abs() <= 2 {
                XB_KERNEL[(k + 2) as usize]
            } else {
                0.0
            }
        };
        let n = key.len();
        (0..n)
            .map(|p| {
                let cp = corners(p);
                let (mut num, mut den) = ([0f64; 2], 0f64);
                for (q, vq) in values.iter().enumerate() {
                    let mut k = 0f64;
                    for (c, wc) in &cp {
                        for (d, wd) in corners(q) {
                            let kern = binom(c[0] - d[0]) * binom(c[1] - d[1]) * binom(c[2] - d[2]);
                            k += f64::from(wc * wd * kern);
                        }
                    }
                    num[0] += k * f64::from(vq[0]);
                    num[1] += k * f64::from(vq[1]);
                    den += k;
                }
                [(num[0] / den) as f32, (num[1] / den) as f32]
            })
            .collect()
    }

    #[test]
    fn cross_bilateral_grid_matches_the_pairwise_definition() {
        let (w, h) = (15, 11);
        // A key with a bright region (an edge the sums must respect) and a ramp.
        let key: Vec<f32> = (0..w * h)
            .map(|p| {
                let (x, y) = (p % w, p / w);
                0.1 * y as f32
                    + if x > 8 {
                        3.0
                    } else {
                        (x as f32 * 0.9).sin() * 0.4
                    }
            })
            .collect();
        let values: Vec<[f32; 2]> = (0..w * h)
            .map(|p| [((p * 37) % 17) as f32, if p % 5 == 0 { 0.0 } else { 1.0 }])
            .collect();
        for (sigma_s, sigma_r) in [(2.0f32, 0.7f32), (3.5, 2.5)] {
            let g = CrossGrid::new(&key, w, h, sigma_s, sigma_r);
            let mut fast = values.clone();
            let mut ga = Vec::new();
            g.aggregate(&mut fast, &mut ga, None);
            let slow = naive_cross(&values, &key, w, &g);
            for (a, b) in fast.iter().zip(&slow) {
                for c in 0..2 {
                    assert!(
                        (a[c] - b[c]).abs() < 1e-3 * (1.0 + b[c].abs()),
                        "σs {sigma_s} σr {sigma_r}: {a:?} vs {b:?}"
                    );
                }
            }
            // Only the wanted pixels: the same sums there, zeros elsewhere.
            let wanted: Vec<bool> = (0..w * h).map(|p| p % 3 != 0).collect();
            let mut some = values.clone();
            g.aggregate(&mut some, &mut ga, Some(&wanted));
            for ((a, b), &keep) in some.iter().zip(&fast).zip(&wanted) {
                if keep {
                    assert_eq!(a, b);
                } else {
                    assert_eq!(a, &[0.0; 2]);
                }
            }
        }
    }

    /// Sums taken while the grid is built are those of a separate pass, to
    /// the bit, and the ones channel gives the same normaliser.
    #[test]
    fn sums_taken_with_the_grid_equal_a_separate_pass() {
        let (w, h) = (23, 17);
        let key: Vec<f32> = (0..w * h).map(|p| ((p * 13) % 7) as f32 * 0.3).collect();
        let vals: Vec<f32> = (0..w * h).map(|p| ((p * 37) % 17) as f32 - 8.0).collect();
        let g = CrossGrid::new(&key, w, h, 3.0, 0.5);
        let mut separate: Vec<[f32; 1]> = vals.iter().map(|&v| [v]).collect();
        let mut ga = Vec::new();
        g.sums(&mut separate, &mut ga, None);
        let mut joint: Vec<[f32; 2]> = vals.iter().map(|&v| [v, 1.0]).collect();
        let gj = CrossGrid::with_sums(&key, w, h, 3.0, 0.5, &mut joint, None);
        assert_eq!(gj.norm, g.norm);
        for (j, s) in joint.iter().zip(&separate) {
            assert_eq!(j[0].to_bits(), s[0].to_bits());
        }
        let moved = joint
            .iter()
            .zip(&vals)
            .filter(|(j, v)| (j[0] / j[1] - **v).abs() > 0.1);
        assert!(moved.count() > w * h / 2, "the sums smooth");
    }

    /// The in-place y blur equals a pass into a second grid, to the bit, however
    /// the rows are cut into runs (the parallel kernel against its serial reference).
    #[test]
    fn in_place_y_blur_equals_the_two_buffer_pass() {
        let mut s = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        for (slab, ny) in [(7usize, 5usize), (12, 9), (30, 23), (4, 40)] {
            let grid: Vec<[f32; 3]> = (0..slab * ny).map(|_| [rnd(), rnd(), rnd()]).collect();
            let mut reference = grid.clone();
            for gy in XB_PAD..ny - XB_PAD {
                let out = &mut reference[gy * slab..(gy + 1) * slab];
                out.fill([0f32; 3]);
                for (t, &k) in XB_KERNEL.iter().enumerate() {
                    let j = gy + t - 2;
                    for (o, v) in out.iter_mut().zip(&grid[j * slab..(j + 1) * slab]) {
                        for (a, &b) in o.iter_mut().zip(v) {
                            *a += k * b;
                        }
                    }
                }
            }
            let all = vec![
                Extent {
                    x: 0..slab,
                    z: 0..1
                };
                ny
            ];
            // Boxes of data that differ from row to row (a rotated canvas): zeros outside,
            // as the splat leaves them; the runs are cut by the work of the boxes.
            let boxes: Vec<Extent> = (0..ny)
                .map(|gy| match gy % 4 {
                    0 => Extent::EMPTY,
                    1 => Extent {
                        x: 0..slab,
                        z: 0..1,
                    },
                    _ => Extent {
                        x: gy % slab..slab,
                        z: 0..1,
                    },
                })
                .collect();
            let sparse: Vec<[f32; 3]> = grid
                .iter()
                .enumerate()
                .map(|(i, &v)| {
                    if boxes[i / slab].x.contains(&(i % slab)) {
                        v
                    } else {
                        [0.0; 3]
                    }
                })
                .collect();
            let mut sparse_reference = sparse.clone();
            for gy in XB_PAD..ny - XB_PAD {
                let out = &mut sparse_reference[gy * slab..(gy + 1) * slab];
                out.fill([0f32; 3]);
                for (t, &k) in XB_KERNEL.iter().enumerate() {
                    let j = gy + t - 2;
                    for (o, v) in out.iter_mut().zip(&sparse[j * slab..(j + 1) * slab]) {
                        for (a, &b) in o.iter_mut().zip(v) {
                            *a += k * b;
                        }
                    }
                }
            }
            for chunks in [1, 2, 3, 5, 8, 64] {
                let mut fast = sparse.clone();
                blur_y_in_place(&mut fast, slab, &boxes, chunks);
                let bits = |g: &[[f32; 3]]| -> Vec<u32> {
                    g.iter().flatten().map(|v| v.to_bits()).collect()
                };
                assert_eq!(
                    bits(&fast),
                    bits(&sparse_reference),
                    "boxes: slab {slab}, {ny} rows, {chunks} runs"
                );
                let mut fast = grid.clone();
                blur_y_in_place(&mut fast, slab, &all, chunks);
                let bits = |g: &[[f32; 3]]| -> Vec<u32> {
                    g.iter().flatten().map(|v| v.to_bits()).collect()
                };
                assert_eq!(
                    bits(&fast),
                    bits(&reference),
                    "slab {slab}, {ny} rows, {chunks} runs"
                );
            }
        }
    }
    /// The sums over the whole grid, serially (splat in pixel order, each blur
    /// pass over every interior cell, slice): the reference of [`CrossGrid::sums`].
    fn reference_sums<const C: usize>(g: &CrossGrid, vals: &[[f32; C]]) -> Vec<[f32; C]> {
        let (w, nx, ny, nz) = (g.w, g.nx, g.ny, g.nz);
        let (slab, pad) = (nx * nz, XB_PAD as f32);
        let at = |x: usize, y: usize, z: usize| y * slab + z * nx + x;
        let mut grid = vec![[0f32; C]; slab * ny];
        for (p, v) in vals.iter().enumerate() {
            if v.iter().all(|&b| b == 0.0) {
                continue;
            }
            let (x, y) = (p % w, p / w);
            let (fx, fy, fz) = (x as f32 / g.cell + pad, y as f32 / g.cell + pad, g.fz[p]);
            let (x0, z0) = (fx as usize, fz as usize);
            let (tx, tz) = (fx - x0 as f32, fz - z0 as f32);
            for gy in [fy.floor() as usize, fy.floor() as usize + 1] {
                let dy = y as f32 / g.cell + pad - gy as f32;
                if dy.abs() >= 1.0 {
                    continue;
                }
                let wy = 1.0 - dy.abs();
                for (dz, wz) in [(0, 1.0 - tz), (1, tz)] {
                    for (dx, wx) in [(0, 1.0 - tx), (1, tx)] {
                        let k = wy * wz * wx;
                        for (a, &b) in grid[at(x0 + dx, gy, z0 + dz)].iter_mut().zip(v) {
                            *a += k * b;
                        }
                    }
                }
            }
        }
        let pass = |grid: &[[f32; C]], step: usize, n: usize, coord: &dyn Fn(usize) -> usize| {
            let mut out = grid.to_vec();
            for (i, o) in out.iter_mut().enumerate() {
                let c = coord(i);
                if c < XB_PAD || c >= n - XB_PAD {
                    continue;
                }
                let mut acc = [0f32; C];
                for (t, &k) in XB_KERNEL.iter().enumerate() {
                    for (a, &b) in acc.iter_mut().zip(&grid[i + t * step - 2 * step]) {
                        *a += k * b;
                    }
                }
                *o = acc;
            }
            out
        };
        // Cells outside the interior of an axis are zeros and stay so.
        let grid = pass(&grid, 1, nx, &|i| i % nx);
        let grid = pass(&grid, nx, nz, &|i| (i % slab) / nx);
        let grid = pass(&grid, slab, ny, &|i| i / slab);
        let mut out = vals.to_vec();
        for (y, row) in out.chunks_mut(w).enumerate() {
            g.slice_row(grid.as_flattened(), y, None, row, false);
        }
        out
    }

    /// The sums computed on the boxes of data equal those over the whole
    /// grid, to the bit, on a rotated canvas (a fill of zeros around the image).
    #[test]
    fn sums_on_the_boxes_of_data_equal_the_whole_grid_passes() {
        let (w, h) = (61, 47);
        let inside = |x: usize, y: usize| {
            let (u, v) = (x as f32 - 30.0, y as f32 - 23.0);
            (0.8 * u + 0.6 * v).abs() < 22.0 && (-0.6 * u + 0.8 * v).abs() < 15.0
        };
        let key: Vec<f32> = (0..w * h)
            .map(|p| ((p * 29) % 11) as f32 * 0.25 + (p % w) as f32 * 0.02)
            .collect();
        let vals: Vec<[f32; 3]> = (0..w * h)
            .map(|p| {
                if inside(p % w, p / w) {
                    [((p * 37) % 17) as f32 - 8.0, ((p * 13) % 5) as f32, 1.0]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let bits =
            |v: &[[f32; 3]]| -> Vec<u32> { v.iter().flatten().map(|x| x.to_bits()).collect() };
        for (sigma_s, sigma_r) in [(2.0f32, 0.3f32), (4.0, 1.5)] {
            let g = CrossGrid::new(&key, w, h, sigma_s, sigma_r);
            let mut fast = vals.clone();
            g.sums(&mut fast, &mut Vec::new(), None);
            let slow = reference_sums(&g, &vals);
            assert_eq!(bits(&fast), bits(&slow), "σs {sigma_s} σr {sigma_r}");
            assert!(fast.iter().any(|v| v[0] != 0.0));
            // However the grid rows are cut into runs (the rows two runs share produced once).
            for run in [1, 2, 3, 7, g.ny] {
                let mut grid = Vec::new();
                g.splat_rows_in_runs(
                    &|y, row: &mut [[f32; 3]]| row.copy_from_slice(&vals[y * w..(y + 1) * w]),
                    &mut grid,
                    run,
                );
                let mut out = vals.clone();
                for (y, row) in out.chunks_mut(w).enumerate() {
                    g.slice_row(&grid, y, None, row, false);
                }
                assert_eq!(
                    bits(&out),
                    bits(&slow),
                    "σs {sigma_s} σr {sigma_r}, runs of {run}"
                );
            }
        }
    }
}
