//! Dense SIFT: one 128-byte SIFT descriptor at every pixel.
//!
//! The variant of Liu, Yuen and Torralba (SIFT flow, PAMI 2011, §3.1), as in
//! their public code: Sobel gradients; 8 orientation bands where a pixel adds
//! `|∇I| · max(cos(θ − θ_k), 0)^9` to band `k` (soft binning that decays fast);
//! 4 × 4 spatial cells of `cell_size` pixels; the 128-vector L2-normalised and
//! stored as `u8` (`255 · v / (|v| + ε)`, clamped to 255).
//!
//! Two deliberate differences from the reference code, both about geometry:
//! the 4 × 4 cells are centred on the pixel (the reference puts the centre
//! half a cell to the lower right, which shifts every correspondence field by
//! `cell_size / 2` against the image), and a pixel spreads into the cells with
//! a separable tent of half-width `cell_size` (Lowe's bilinear spatial binning)
//! instead of a box, which makes the descriptor vary smoothly with sub-pixel
//! shifts — what sub-pixel disparity needs.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;

/// Length of one descriptor: 4 × 4 cells × 8 orientations.
pub const DESCRIPTOR_LEN: usize = 128;
/// Number of orientation bands.
const N_BINS: usize = 8;
/// Added to the descriptor norm so that a flat patch gives a zero descriptor
/// instead of amplified noise (intensity units per pixel, images in `[0, 1]`).
const NORM_EPSILON: f32 = 1e-4;

/// Parameters of the dense descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DenseSiftParams {
    /// Side of one of the 4 × 4 cells, pixels (reference code 3): larger is steadier on weak texture, blurs depth edges.
    pub cell_size: usize,
}

impl Default for DenseSiftParams {
    fn default() -> Self {
        Self { cell_size: 3 }
    }
}

/// A descriptor image: `DESCRIPTOR_LEN` bytes per pixel, row-major.
#[derive(Clone, PartialEq, Eq)]
pub struct DescriptorImage {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl std::fmt::Debug for DescriptorImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DescriptorImage")
            .field("width", &self.width)
            .field("height", &self.height)
            .finish_non_exhaustive()
    }
}

impl DescriptorImage {
    /// An image of zero descriptors.
    #[must_use]
    pub fn zeros(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            data: vec![0; width * height * DESCRIPTOR_LEN],
        }
    }

    #[must_use]
    pub fn width(&self) -> usize {
        self.width
    }

    #[must_use]
    pub fn height(&self) -> usize {
        self.height
    }

    /// The descriptor at `(x, y)`.
    ///
    /// # Panics
    /// When the pixel lies outside the image.
    #[must_use]
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> &[u8; DESCRIPTOR_LEN] {
        let i = (y * self.width + x) * DESCRIPTOR_LEN;
        self.data[i..i + DESCRIPTOR_LEN]
            .try_into()
            .expect("slice of DESCRIPTOR_LEN bytes")
    }

    /// The descriptors of row `y`, `DESCRIPTOR_LEN` bytes per pixel.
    ///
    /// # Panics
    /// When the row lies outside the image.
    #[must_use]
    #[inline]
    pub fn row(&self, y: usize) -> &[u8] {
        let n = self.width * DESCRIPTOR_LEN;
        &self.data[y * n..(y + 1) * n]
    }

    /// All descriptors, row-major.
    #[must_use]
    pub fn data(&self) -> &[u8] {
        &self.data
    }

    /// All descriptors, row-major, mutable.
    pub fn data_mut(&mut self) -> &mut [u8] {
        &mut self.data
    }

    /// Bytes held.
    #[must_use]
    pub fn bytes(&self) -> usize {
        self.data.len()
    }
}

/// L1 distance of two descriptors (the data term of SIFT flow, eq. 10).
///
/// On x86-64 eight `psadbw` (SSE2, always present there); the compiler does
/// not find them by itself once the call is inlined into the data-term loop.
#[must_use]
#[inline]
pub fn l1_distance(a: &[u8; DESCRIPTOR_LEN], b: &[u8; DESCRIPTOR_LEN]) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{
            __m128i, _mm_add_epi64, _mm_cvtsi128_si64, _mm_loadu_si128, _mm_sad_epu8,
            _mm_setzero_si128, _mm_unpackhi_epi64,
        };
        // SAFETY: SSE2 is part of the x86-64 baseline, so these intrinsics are
        // available; both arrays hold DESCRIPTOR_LEN bytes and i·16 + 16 ≤
        // DESCRIPTOR_LEN; `_mm_loadu_si128` accepts unaligned addresses.
        let total = unsafe {
            let mut acc = _mm_setzero_si128();
            for i in 0..DESCRIPTOR_LEN / 16 {
                let va = _mm_loadu_si128(a.as_ptr().add(i * 16).cast::<__m128i>());
                let vb = _mm_loadu_si128(b.as_ptr().add(i * 16).cast::<__m128i>());
                acc = _mm_add_epi64(acc, _mm_sad_epu8(va, vb));
            }
            _mm_cvtsi128_si64(_mm_add_epi64(acc, _mm_unpackhi_epi64(acc, acc)))
        };
        // At most 128 · 255.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let t = total as u32;
        t
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        a.iter()
            .zip(b)
            .map(|(&x, &y)| u32::from(x.abs_diff(y)))
            .sum()
    }
}

/// One descriptor kept in registers for the [`l1_distance`]s of a window of candidates against
/// it (the data term compares every pixel with 15 to 105 of them): loaded once, not per pair.
#[derive(Clone, Copy)]
pub struct L1Query {
    #[cfg(target_arch = "x86_64")]
    lanes: [std::arch::x86_64::__m128i; DESCRIPTOR_LEN / 16],
    #[cfg(not(target_arch = "x86_64"))]
    bytes: [u8; DESCRIPTOR_LEN],
}

impl L1Query {
    /// The query of descriptor `a`.
    #[must_use]
    #[inline(always)]
    pub fn new(a: &[u8; DESCRIPTOR_LEN]) -> Self {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{__m128i, _mm_loadu_si128};
            // SAFETY: SSE2 is part of the x86-64 baseline; `i · 16 + 16 ≤ DESCRIPTOR_LEN`, and
            // `_mm_loadu_si128` accepts unaligned addresses.
            let lanes = std::array::from_fn(|i| unsafe {
                _mm_loadu_si128(a.as_ptr().add(i * 16).cast::<__m128i>())
            });
            Self { lanes }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            Self { bytes: *a }
        }
    }

    /// [`l1_distance`] of the query and `b` (the same sum).
    #[must_use]
    #[inline(always)]
    pub fn distance(&self, b: &[u8; DESCRIPTOR_LEN]) -> u32 {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::x86_64::{
                __m128i, _mm_add_epi64, _mm_cvtsi128_si64, _mm_loadu_si128, _mm_sad_epu8,
                _mm_unpackhi_epi64,
            };
            // SAFETY: as in `new`; the sums of absolute differences are exact integers, so
            // the order of the additions does not matter.
            let total = unsafe {
                let sad = |i: usize| {
                    _mm_sad_epu8(
                        self.lanes[i],
                        _mm_loadu_si128(b.as_ptr().add(i * 16).cast::<__m128i>()),
                    )
                };
                let s01 = _mm_add_epi64(sad(0), sad(1));
                let s23 = _mm_add_epi64(sad(2), sad(3));
                let s45 = _mm_add_epi64(sad(4), sad(5));
                let s67 = _mm_add_epi64(sad(6), sad(7));
                let acc = _mm_add_epi64(_mm_add_epi64(s01, s23), _mm_add_epi64(s45, s67));
                _mm_cvtsi128_si64(_mm_add_epi64(acc, _mm_unpackhi_epi64(acc, acc)))
            };
            // At most 128 · 255.
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let t = total as u32;
            t
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            l1_distance(&self.bytes, b)
        }
    }
}

/// The eight orientation bands of one pixel's gradient: `|∇I| · max(cos(θ − θ_k), 0)^9`
/// (the exponent 9 of the reference code: energy falls off fast beyond one band).
#[inline]
fn orientation_bands(gx: f32, gy: f32, out: &mut [f32]) {
    let mag = (gx * gx + gy * gy).sqrt();
    if mag == 0.0 {
        out.fill(0.0);
        return;
    }
    let (cx, cy) = (gx / mag, gy / mag);
    const C: f32 = std::f32::consts::FRAC_1_SQRT_2;
    // (cos θ_k, sin θ_k) for θ_k = 2πk/8, x right, y down.
    const DIRS: [(f32, f32); N_BINS] = [
        (1.0, 0.0),
        (C, C),
        (0.0, 1.0),
        (-C, C),
        (-1.0, 0.0),
        (-C, -C),
        (0.0, -1.0),
        (C, -C),
    ];
    for (o, &(dx, dy)) in out.iter_mut().zip(&DIRS) {
        let c = (cx * dx + cy * dy).max(0.0);
        let c2 = c * c;
        let c4 = c2 * c2;
        *o = mag * c4 * c4 * c;
    }
}

/// Sobel gradients of one row from the rows above, at and below it
/// (replicated border), intensity per pixel.
#[inline]
fn sobel_row(up: &[f32], mid: &[f32], down: &[f32], out: &mut [f32]) {
    let w = mid.len();
    for x in 0..w {
        let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
        let gx = (up[r] + 2.0 * mid[r] + down[r]) - (up[l] + 2.0 * mid[l] + down[l]);
        let gy = (down[l] + 2.0 * down[x] + down[r]) - (up[l] + 2.0 * up[x] + up[r]);
        orientation_bands(gx / 8.0, gy / 8.0, &mut out[x * N_BINS..(x + 1) * N_BINS]);
    }
}

/// Sobel gradient at `(x, y)` in intensity per pixel (replicated border).
#[cfg(test)]
fn sobel(img: &Image, x: usize, y: usize) -> (f32, f32) {
    let (xi, yi) = (x as isize, y as isize);
    let p = |dx: isize, dy: isize| img.get_clamped(xi + dx, yi + dy);
    let gx = (p(1, -1) + 2.0 * p(1, 0) + p(1, 1)) - (p(-1, -1) + 2.0 * p(-1, 0) + p(-1, 1));
    let gy = (p(-1, 1) + 2.0 * p(0, 1) + p(1, 1)) - (p(-1, -1) + 2.0 * p(0, -1) + p(1, -1));
    (gx / 8.0, gy / 8.0)
}

/// Geometry of the spatial binning: the tent taps (offset, weight) of one
/// axis and the offsets of the four cell centres in the filtered band image.
struct CellLayout {
    taps: Vec<(isize, f32)>,
    cell_offsets: [isize; 4],
}

impl CellLayout {
    fn new(cell_size: usize) -> Self {
        let cs = cell_size as f64;
        // Cell centres at (m − 1.5)·cs; the filtered image is sampled at integer
        // indices i whose tent is centred at i + shift.
        let mut cell_offsets = [0isize; 4];
        for (m, o) in cell_offsets.iter_mut().enumerate() {
            *o = ((m as f64 - 1.5) * cs).floor() as isize;
        }
        let shift = -1.5 * cs - (-1.5 * cs).floor();
        let reach = cell_size as isize + 1;
        let mut taps: Vec<(isize, f32)> = (-reach..=reach)
            .filter_map(|k| {
                let w = 1.0 - (k as f64 - shift).abs() / cs;
                (w > 0.0).then_some((k, w as f32))
            })
            .collect();
        let sum: f32 = taps.iter().map(|t| t.1).sum();
        for t in &mut taps {
            t.1 /= sum;
        }
        Self { taps, cell_offsets }
    }
}

/// Quantises one 128-float descriptor: L2 normalisation, ×255, clamp.
#[cfg(test)]
fn quantise(v: &[f32; DESCRIPTOR_LEN], out: &mut [u8]) {
    let norm = v.iter().map(|a| a * a).sum::<f32>().sqrt();
    quantise_scaled(v, 255.0 / (norm + NORM_EPSILON), out);
}

/// Descriptors [`quantise_lanes`] takes at once.
const LANES: usize = 8;

/// [`quantise`] of the first `n` of `LANES` descriptors into `out[x]` for `x` in `xs[..n]`
/// (`DESCRIPTOR_LEN` bytes each). Each norm is the same sum of squares in the same order as
/// [`quantise`]'s, the lanes' sums interleaved: one sum is a chain of 128 dependent additions,
/// eight chains side by side keep the adder busy (the norm was most of the quantisation).
#[inline]
fn quantise_lanes(
    v: &[[f32; DESCRIPTOR_LEN]; LANES],
    n: usize,
    xs: &[usize; LANES],
    out: &mut [u8],
) {
    let mut sums = [0f32; LANES];
    for i in 0..DESCRIPTOR_LEN {
        for (s, d) in sums.iter_mut().zip(v) {
            *s += d[i] * d[i];
        }
    }
    for ((d, &s), &x) in v.iter().zip(&sums).zip(xs).take(n) {
        let scale = 255.0 / (s.sqrt() + NORM_EPSILON);
        quantise_scaled(
            d,
            scale,
            &mut out[x * DESCRIPTOR_LEN..(x + 1) * DESCRIPTOR_LEN],
        );
    }
}

/// The bytes of a descriptor multiplied by `scale` (255 over its norm): clamped, rounded.
#[inline]
fn quantise_scaled(v: &[f32; DESCRIPTOR_LEN], scale: f32, out: &mut [u8]) {
    for (o, &a) in out.iter_mut().zip(v) {
        let q = a * scale;
        let q = if q < 255.0 { q } else { 255.0 };
        // Round to the nearest integer by adding 2^23 (whose ulp is 1) and
        // keep the low mantissa byte: vectorises, where a saturating float →
        // integer cast compiled to scalar code (27 % of the descriptor time).
        #[allow(clippy::cast_possible_truncation)]
        let b = ((q + 8_388_608.0).to_bits() & 0xFF) as u8;
        *o = b;
    }
}

/// Dense SIFT descriptors of `img` at every pixel (Liu et al. 2011, §3.1).
///
/// Parallel over rows. Cost: about 30 operations per pixel for the bands and
/// the cells plus 128 per pixel for the descriptor assembly.
#[must_use]
pub fn dense_sift(img: &Image, params: &DenseSiftParams) -> DescriptorImage {
    dense_sift_where(img, params, None)
}

/// [`dense_sift`], assembled only at the pixels `wanted` marks (row-major;
/// `None`: all); the others hold zero descriptors. The cells are those of
/// the whole image, so a wanted pixel's descriptor is the same as
/// [`dense_sift`]'s. The dense stage wants its real pixels only: the fill
/// around an image rotated onto the rectified canvas is never matched.
///
/// # Panics
/// When `wanted` does not have one entry per pixel.
#[must_use]
pub fn dense_sift_where(
    img: &Image,
    params: &DenseSiftParams,
    wanted: Option<&[bool]>,
) -> DescriptorImage {
    let (w, h) = img.dimensions();
    if let Some(m) = wanted {
        assert_eq!(m.len(), w * h, "one mask entry per pixel");
    }
    let cell_size = params.cell_size.max(1);
    let layout = CellLayout::new(cell_size);
    if w == 0 || h == 0 {
        return DescriptorImage::zeros(w, h);
    }

    // Blocks of output rows, each computed from its own bands and cells (those of the rows
    // its descriptors reach, recomputed where blocks overlap): no full-size intermediate
    // plane, and each block's planes stay in cache. Every value is the same sum in the same
    // order whatever the blocks, so the descriptors do not depend on them.
    let block = h
        .div_ceil(BLOCKS_PER_THREAD * rayon::current_num_threads())
        .max(MIN_BLOCK_ROWS);
    let mut out = DescriptorImage::zeros(w, h);
    out.data
        .par_chunks_mut(block * w * DESCRIPTOR_LEN)
        .enumerate()
        .for_each_init(
            || (Vec::new(), Vec::new()),
            |(bands, horizontal), (b, rows)| {
                let y0 = b * block;
                let y1 = y0 + rows.len() / (w * DESCRIPTOR_LEN);
                if let Some(m) = wanted
                    && !m[y0 * w..y1 * w].contains(&true)
                {
                    return;
                }
                descriptor_block(img, &layout, (y0, y1), wanted, bands, horizontal, rows);
            },
        );
    out
}

/// Blocks of output rows per thread of [`dense_sift_where`] (the descriptors do not depend on it).
const BLOCKS_PER_THREAD: usize = 4;
/// Fewest rows of a block: its halo (the rows its cells and tents reach) is recomputed.
const MIN_BLOCK_ROWS: usize = 32;

/// Rows `y0..y1` of [`dense_sift_where`] into `out` (their descriptors, `w · DESCRIPTOR_LEN`
/// bytes a row, zeros where not wanted), with `bands` and `horizontal` as working planes.
///
/// The descriptor of row `y` reads the cells of rows `y + cell_offsets` (clamped), a cell
/// row the horizontally filtered bands of the rows its tent reaches (clamped), a band row
/// the image rows around it: the block computes exactly those rows, each value as the
/// whole-image passes do (the tent taps in order, from zero).
#[allow(clippy::too_many_arguments)]
fn descriptor_block(
    img: &Image,
    layout: &CellLayout,
    (y0, y1): (usize, usize),
    wanted: Option<&[bool]>,
    bands: &mut Vec<f32>,
    horizontal: &mut Vec<f32>,
    out: &mut [u8],
) {
    let (w, h) = img.dimensions();
    let last = h as isize - 1;
    let clamp = |y: isize| y.clamp(0, last) as usize;
    let (co_lo, co_hi) = (layout.cell_offsets[0], layout.cell_offsets[3]);
    let (k_lo, k_hi) = (
        layout.taps.first().map_or(0, |t| t.0),
        layout.taps.last().map_or(0, |t| t.0),
    );
    // Cell rows c0..c1, band rows b0..b1 (clamped offsets are monotone: the bounds hold all).
    let (c0, c1) = (
        clamp(y0 as isize + co_lo),
        clamp(y1 as isize - 1 + co_hi) + 1,
    );
    let (b0, b1) = (clamp(c0 as isize + k_lo), clamp(c1 as isize - 1 + k_hi) + 1);
    let row_len = w * N_BINS;

    // 1. Orientation bands, interleaved [pixel][band].
    bands.resize((b1 - b0) * row_len, 0.0);
    for (y, row) in (b0..b1).zip(bands.chunks_exact_mut(row_len)) {
        let up = img.row(y.saturating_sub(1));
        let down = img.row((y + 1).min(h - 1));
        sobel_row(up, img.row(y), down, row);
    }

    // 2. Separable tent filter: horizontal, then vertical (replicated border).
    horizontal.resize((b1 - b0) * row_len, 0.0);
    for (src, row) in bands
        .chunks_exact(row_len)
        .zip(horizontal.chunks_exact_mut(row_len))
    {
        for (x, out) in row.chunks_exact_mut(N_BINS).enumerate() {
            out.fill(0.0);
            for &(k, wt) in &layout.taps {
                let sx = (x as isize + k).clamp(0, w as isize - 1) as usize;
                for (o, &s) in out.iter_mut().zip(&src[sx * N_BINS..(sx + 1) * N_BINS]) {
                    *o += wt * s;
                }
            }
        }
    }
    // The cells in the bands' plane (no longer needed).
    let cells = bands;
    for (y, row) in (c0..c1).zip(cells.chunks_exact_mut(row_len)) {
        row.fill(0.0);
        for &(k, wt) in &layout.taps {
            let sy = clamp(y as isize + k);
            let src = &horizontal[(sy - b0) * row_len..(sy - b0 + 1) * row_len];
            for (o, &s) in row.iter_mut().zip(src) {
                *o += wt * s;
            }
        }
    }

    // 3. Assemble, normalise, quantise: `LANES` descriptors of a row at a time.
    let mut v = [[0f32; DESCRIPTOR_LEN]; LANES];
    let mut xs = [0usize; LANES];
    for (y, row) in (y0..y1).zip(out.chunks_exact_mut(w * DESCRIPTOR_LEN)) {
        let mut n = 0;
        for x in 0..w {
            if wanted.is_some_and(|m| !m[y * w + x]) {
                continue;
            }
            let mut i = 0;
            for &oy in &layout.cell_offsets {
                let cy = clamp(y as isize + oy);
                for &ox in &layout.cell_offsets {
                    let cx = (x as isize + ox).clamp(0, w as isize - 1) as usize;
                    let c = (cy - c0) * row_len + cx * N_BINS;
                    v[n][i..i + N_BINS].copy_from_slice(&cells[c..c + N_BINS]);
                    i += N_BINS;
                }
            }
            xs[n] = x;
            n += 1;
            if n == LANES {
                quantise_lanes(&v, n, &xs, row);
                n = 0;
            }
        }
        if n > 0 {
            quantise_lanes(&v, n, &xs, row);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The descriptors quantised eight at a time are those of [`quantise`], byte for byte,
    /// whatever the number of lanes in use and the other lanes' contents.
    #[test]
    fn lanes_quantise_as_one_descriptor_at_a_time() {
        let mut seed = 0x9e37_79b9u32;
        let mut rnd = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        for n in 1..=LANES {
            let mut v = [[0f32; DESCRIPTOR_LEN]; LANES];
            for (j, d) in v.iter_mut().enumerate() {
                // Spread magnitudes (one flat descriptor) so the norms round differently.
                let scale = if j == 2 {
                    0.0
                } else {
                    10f32.powi(j as i32 - 4)
                };
                for a in d.iter_mut() {
                    *a = scale * rnd() * rnd();
                }
            }
            let xs: [usize; LANES] = std::array::from_fn(|j| (j * 5 + 3) % 11);
            let mut got = vec![7u8; 11 * DESCRIPTOR_LEN];
            quantise_lanes(&v, n, &xs, &mut got);
            let mut want = vec![7u8; 11 * DESCRIPTOR_LEN];
            for (d, &x) in v.iter().zip(&xs).take(n) {
                quantise(d, &mut want[x * DESCRIPTOR_LEN..(x + 1) * DESCRIPTOR_LEN]);
            }
            assert_eq!(got, want, "{n} lanes");
        }
    }

    /// The definition, pixel by pixel, with no separable filtering and no
    /// shared buffers: every cell sums the tent-weighted bands directly.
    fn naive_dense_sift(img: &Image, cell_size: usize) -> DescriptorImage {
        let (w, h) = img.dimensions();
        let cs = cell_size as f64;
        let tent = |d: f64| (1.0 - d.abs() / cs).max(0.0);
        // Normalisation of the tent over integer samples around a centre.
        let centre_frac = -1.5 * cs - (-1.5 * cs).floor();
        let norm: f64 = (-20..=20).map(|k| tent(f64::from(k) - centre_frac)).sum();
        let mut out = DescriptorImage::zeros(w, h);
        for y in 0..h {
            for x in 0..w {
                let mut v = [0f32; DESCRIPTOR_LEN];
                for my in 0..4 {
                    for mx in 0..4 {
                        let ccx = x as f64 + (mx as f64 - 1.5) * cs;
                        let ccy = y as f64 + (my as f64 - 1.5) * cs;
                        // Cell centres clamp to the image as whole cells do
                        // (replicated border), keeping their sub-pixel phase.
                        let ix = ccx.floor().clamp(0.0, (w - 1) as f64);
                        let iy = ccy.floor().clamp(0.0, (h - 1) as f64);
                        let (cx, cy) = (ix + centre_frac, iy + centre_frac);
                        let mut acc = [0f64; N_BINS];
                        for sy in -20i64..=20 {
                            for sx in -20i64..=20 {
                                let px = cx.floor() as i64 + sx;
                                let py = cy.floor() as i64 + sy;
                                let wt = tent(px as f64 - cx) * tent(py as f64 - cy);
                                if wt == 0.0 {
                                    continue;
                                }
                                let qx = px.clamp(0, w as i64 - 1) as usize;
                                let qy = py.clamp(0, h as i64 - 1) as usize;
                                let (gx, gy) = sobel(img, qx, qy);
                                let mag = f64::from(gx.hypot(gy));
                                if mag == 0.0 {
                                    continue;
                                }
                                let theta = f64::from(gy).atan2(f64::from(gx));
                                for (k, a) in acc.iter_mut().enumerate() {
                                    let tk = 2.0 * std::f64::consts::PI * k as f64 / 8.0;
                                    let c = (theta - tk).cos().max(0.0);
                                    *a += wt * mag * c.powi(9);
                                }
                            }
                        }
                        for k in 0..N_BINS {
                            v[(my * 4 + mx) * N_BINS + k] = (acc[k] / (norm * norm)) as f32;
                        }
                    }
                }
                let i = (y * w + x) * DESCRIPTOR_LEN;
                quantise(&v, &mut out.data[i..i + DESCRIPTOR_LEN]);
            }
        }
        out
    }

    /// The whole-image passes (a full plane of bands, of their horizontal tents, of cells),
    /// as [`dense_sift_where`] computed them before its blocks: the same bytes.
    fn dense_sift_planes(
        img: &Image,
        cell_size: usize,
        wanted: Option<&[bool]>,
    ) -> DescriptorImage {
        let (w, h) = img.dimensions();
        let layout = CellLayout::new(cell_size);
        // 1. Orientation bands, interleaved [pixel][band].
        let mut bands = vec![0f32; w * h * N_BINS];
        bands
            .par_chunks_mut(w * N_BINS)
            .enumerate()
            .for_each(|(y, row)| {
                let up = img.row(y.saturating_sub(1));
                let down = img.row((y + 1).min(h - 1));
                sobel_row(up, img.row(y), down, row);
            });

        // 2. Separable tent filter: horizontal, then vertical (replicated border).
        let mut horizontal = vec![0f32; w * h * N_BINS];
        horizontal
            .par_chunks_mut(w * N_BINS)
            .enumerate()
            .for_each(|(y, row)| {
                let src = &bands[y * w * N_BINS..(y + 1) * w * N_BINS];
                for (x, out) in row.chunks_exact_mut(N_BINS).enumerate() {
                    for &(k, wt) in &layout.taps {
                        let sx = (x as isize + k).clamp(0, w as isize - 1) as usize;
                        for (o, &s) in out.iter_mut().zip(&src[sx * N_BINS..(sx + 1) * N_BINS]) {
                            *o += wt * s;
                        }
                    }
                }
            });
        let mut cells = bands; // reuse the buffer
        cells
            .par_chunks_mut(w * N_BINS)
            .enumerate()
            .for_each(|(y, row)| {
                row.fill(0.0);
                for &(k, wt) in &layout.taps {
                    let sy = (y as isize + k).clamp(0, h as isize - 1) as usize;
                    let src = &horizontal[sy * w * N_BINS..(sy + 1) * w * N_BINS];
                    for (o, &s) in row.iter_mut().zip(src) {
                        *o += wt * s;
                    }
                }
            });
        drop(horizontal);

        // 3. Assemble, normalise, quantise.
        let mut out = DescriptorImage::zeros(w, h);
        out.data
            .par_chunks_mut(w * DESCRIPTOR_LEN)
            .enumerate()
            .for_each(|(y, row)| {
                let mut v = [0f32; DESCRIPTOR_LEN];
                for (x, desc) in row.chunks_exact_mut(DESCRIPTOR_LEN).enumerate() {
                    if wanted.is_some_and(|m| !m[y * w + x]) {
                        continue;
                    }
                    let mut i = 0;
                    for &oy in &layout.cell_offsets {
                        let cy = (y as isize + oy).clamp(0, h as isize - 1) as usize;
                        for &ox in &layout.cell_offsets {
                            let cx = (x as isize + ox).clamp(0, w as isize - 1) as usize;
                            let c = (cy * w + cx) * N_BINS;
                            v[i..i + N_BINS].copy_from_slice(&cells[c..c + N_BINS]);
                            i += N_BINS;
                        }
                    }
                    quantise(&v, desc);
                }
            });
        out
    }

    #[test]
    fn blocks_give_the_bytes_of_whole_image_passes() {
        for (w, h) in [(23, 17), (41, 150), (9, 70)] {
            let img = texture(w, h);
            let wanted: Vec<bool> = (0..w * h).map(|p| (p % w) * 3 + (p / w) > 20).collect();
            for cs in [1, 2, 3] {
                let params = DenseSiftParams { cell_size: cs };
                for mask in [None, Some(&wanted[..])] {
                    let blocks = dense_sift_where(&img, &params, mask);
                    let planes = dense_sift_planes(&img, cs, mask);
                    assert!(
                        blocks == planes,
                        "{w}x{h}, cell {cs}, mask {}",
                        mask.is_some()
                    );
                }
            }
        }
    }

    fn texture(w: usize, h: usize) -> Image {
        Image::from_fn(w, h, |x, y| {
            let (x, y) = (x as f32, y as f32);
            0.5 + 0.25 * (0.7 * x + 0.3 * y).sin()
                + 0.2 * (0.45 * y - 0.2 * x).cos() * (0.13 * x).sin()
        })
    }

    #[test]
    fn matches_naive_reference_for_odd_and_even_cells() {
        let img = texture(23, 17);
        for cs in [2, 3] {
            let fast = dense_sift(&img, &DenseSiftParams { cell_size: cs });
            let slow = naive_dense_sift(&img, cs);
            let worst = fast
                .data()
                .iter()
                .zip(slow.data())
                .map(|(&a, &b)| a.abs_diff(b))
                .max()
                .unwrap();
            // Rounding of f32 sums in a different order: off by one at most.
            assert!(worst <= 1, "cell size {cs}: worst byte difference {worst}");
        }
    }

    #[test]
    fn masked_descriptors_are_the_full_ones_where_wanted() {
        let img = texture(29, 23);
        let params = DenseSiftParams { cell_size: 2 };
        let full = dense_sift(&img, &params);
        let wanted: Vec<bool> = (0..29 * 23).map(|p| (p % 29) + (p / 29) > 12).collect();
        let masked = dense_sift_where(&img, &params, Some(&wanted));
        for (p, &keep) in wanted.iter().enumerate() {
            let (x, y) = (p % 29, p / 29);
            if keep {
                assert_eq!(masked.at(x, y), full.at(x, y), "pixel ({x}, {y})");
            } else {
                assert!(masked.at(x, y).iter().all(|&b| b == 0), "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn descriptors_are_unit_length_and_flat_is_zero() {
        let img = texture(20, 20);
        let d = dense_sift(&img, &DenseSiftParams::default());
        let v = d.at(10, 10);
        let norm = v.iter().map(|&a| f32::from(a).powi(2)).sum::<f32>().sqrt();
        assert!((norm - 255.0).abs() < 4.0, "norm {norm}");
        let flat = dense_sift(&Image::filled(12, 12, 0.3), &DenseSiftParams::default());
        assert!(flat.data().iter().all(|&b| b == 0));
    }

    #[test]
    fn shifted_image_shifts_descriptors() {
        let a = texture(40, 30);
        let b = Image::from_fn(40, 30, |x, y| a.get_clamped(x as isize - 3, y as isize));
        let da = dense_sift(&a, &DenseSiftParams::default());
        let db = dense_sift(&b, &DenseSiftParams::default());
        // Away from the borders, b(x + 3) is a(x): identical descriptors, and
        // the true shift is the unique best match along the row.
        assert_eq!(da.at(15, 15), db.at(18, 15));
        let best = (0..8)
            .min_by_key(|&s| l1_distance(da.at(15, 15), db.at(15 + s, 15)))
            .unwrap();
        assert_eq!(best, 3);
    }

    #[test]
    fn l1_distance_is_the_sum_of_absolute_differences() {
        let a: [u8; 128] = std::array::from_fn(|i| (i * 7 % 256) as u8);
        let b: [u8; 128] = std::array::from_fn(|i| (255 - i * 3 % 256) as u8);
        let naive: u32 = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| u32::from(x.abs_diff(y)))
            .sum();
        assert_eq!(l1_distance(&a, &b), naive);
    }
}
